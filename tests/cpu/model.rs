//! The networks of method §3: configurations, shapes, gradients, Pluecker maps, and the
//! hand-off to the lifting operator.

#![allow(deprecated)]

use std::path::Path;
use std::sync::Arc;

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Device, Distribution, Gradients, Tensor, TensorData};
use texavatars::camera::Camera;
use texavatars::lift::{self, LiftMode, LiftParams, Topology};
use texavatars::mesh::UvMesh;
use texavatars::models::texavatars::constants::*;
use texavatars::models::texavatars::{
    Bias, ConditionConfig, NetConfig, PlueckerMap, TexAvatarNet, WnConvTranspose2d,
    WnConvTranspose2dConfig, WnLinear, WnLinearConfig, view_input,
};
use texavatars::texel::FrameKind;

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

fn config(name: &str) -> NetConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("configs")
        .join(format!("{name}.json"));
    NetConfig::load(&path).expect("shipped config")
}

/// A 40 x 30 camera at `(0.1, -0.2, -1.5)` looking along +z, rolled by 90 degrees.
fn camera() -> Camera {
    // Rows of R (world to camera): x_cam = -y_world, y_cam = x_world, z_cam = z_world.
    let r = [[0.0f32, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
    let c = [0.1f32, -0.2, -1.5];
    let mut m = [[0.0f32; 4]; 4];
    for i in 0..3 {
        m[i][..3].copy_from_slice(&r[i]);
        m[i][3] = -(r[i][0] * c[0] + r[i][1] * c[1] + r[i][2] * c[2]);
    }
    m[3][3] = 1.0;
    Camera {
        width: 40,
        height: 30,
        fx: 50.0,
        fy: 48.0,
        cx: 20.5,
        cy: 14.5,
        world_to_camera: m,
    }
}

fn condition(n: usize, dim: usize, seed: f32, device: &Device) -> Tensor<2> {
    let v: Vec<f32> = (0..n * dim)
        .map(|k| ((k as f32 * 0.37 + seed).sin()) * 0.8)
        .collect();
    Tensor::from_data(TensorData::new(v, [n, dim]), device)
}

fn seeded(device: Device, seed: u64) -> Device {
    device.seed(seed);
    device
}

#[test]
fn shipped_configs_match_their_constructors() {
    assert_eq!(config("paper"), NetConfig::paper());
    assert_eq!(
        config("cpu"),
        NetConfig::scaled(128, 4)
            .unwrap()
            .with_condition(ConditionConfig::default_head())
    );
    assert_eq!(
        config("mid"),
        NetConfig::scaled(256, 2)
            .unwrap()
            .with_condition(ConditionConfig::default_head())
    );
    assert_eq!(
        config("tiny"),
        NetConfig::scaled(32, 16)
            .unwrap()
            .with_condition(ConditionConfig::default_head())
    );
    assert_eq!(NetConfig::scaled(512, 1).unwrap(), NetConfig::paper());
    assert_eq!(NetConfig::paper().condition.dim(), 243);
    assert_eq!(ConditionConfig::default_head().dim(), 195);
    let paper = NetConfig::paper();
    assert_eq!(
        (paper.stages(), paper.view_res(), paper.view_input_res()),
        (6, 32, 128)
    );
    let tiny = config("tiny");
    assert_eq!(
        (tiny.stages(), tiny.view_res(), tiny.view_input_res()),
        (2, 16, 64)
    );
    // JSON round trip.
    let back: NetConfig = serde_json::from_str(&paper.to_json()).unwrap();
    assert_eq!(back, paper);
}

#[test]
fn scaled_plans_are_valid_for_every_resolution() {
    for k in 1..=6 {
        for divisor in [1, 2, 4, 8, 16, 64] {
            let c = NetConfig::scaled(BASE_RES << k, divisor).unwrap();
            c.validate("scaled").unwrap();
            assert_eq!(c.stages(), k);
            assert_eq!(c.geometry.len(), k);
            assert!(c.view_res() <= 32 && c.view_res() < c.uv_res);
        }
    }
    assert!(NetConfig::scaled(1024, 1).is_err());
    assert!(NetConfig::scaled(100, 1).is_err());
    assert!(NetConfig::scaled(8, 1).is_err());
    assert!(NetConfig::scaled(64, 0).is_err());
}

#[test]
fn invalid_configs_are_rejected_with_the_field() {
    let bad = |f: &dyn Fn(&mut NetConfig), field: &str| {
        let mut c = NetConfig::paper();
        f(&mut c);
        let e = c.validate("cfg.json").unwrap_err().to_string();
        assert!(e.contains("cfg.json") && e.contains(field), "{e}");
    };
    bad(&|c| c.uv_res = 500, "uv_res");
    bad(&|c| c.geometry.pop().map(|_| ()).unwrap(), "geometry");
    bad(&|c| *c.geometry.last_mut().unwrap() = 12, "geometry");
    bad(
        &|c| c.appearance.after_view = vec![64, 64, 3, 4],
        "appearance",
    );
    bad(&|c| c.appearance.before_view = vec![256], "appearance");
    bad(&|c| c.appearance.mid = vec![128, 0], "appearance.mid");
    bad(&|c| c.view.square_res = 500, "view.square_res");
    bad(&|c| c.view.channels.clear(), "view.channels");
    bad(
        &|c| {
            c.condition = ConditionConfig {
                expression: 0,
                pose: 0,
                eta: 0,
                zero_eta: false,
            }
        },
        "condition",
    );
    let dir = std::env::temp_dir().join(format!("texavatars-net-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("typo.json");
    let json = NetConfig::paper()
        .to_json()
        .replace("\"uv_res\"", "\"uv_resolution\"");
    std::fs::write(&file, json).unwrap();
    let e = NetConfig::load(&file).unwrap_err().to_string();
    assert!(
        e.contains("typo.json") && e.contains("uv_resolution"),
        "{e}"
    );
}

#[test]
fn paper_networks_have_the_papers_shapes() {
    let device = seeded(Device::ndarray(), 1);
    let net = NetConfig::paper().init(&device).unwrap();
    // Exp2Code 243 -> 256 x 8 x 8 (v, g, bias).
    assert_eq!(net.exp2code.linear.v.val().dims(), [256 * 64, 243]);
    let geometry: Vec<([usize; 4], [usize; 3])> = net
        .geometry
        .layers
        .iter()
        .map(|l| {
            (
                l.v.val().dims(),
                l.untied_bias.as_ref().unwrap().val().dims(),
            )
        })
        .collect();
    assert_eq!(
        geometry,
        vec![
            ([256, 256, 4, 4], [256, 16, 16]),
            ([256, 128, 4, 4], [128, 32, 32]),
            ([128, 128, 4, 4], [128, 64, 64]),
            ([128, 64, 4, 4], [64, 128, 128]),
            ([64, 32, 4, 4], [32, 256, 256]),
            ([32, 11, 4, 4], [11, 512, 512]),
        ]
    );
    let a = &net.appearance;
    let ups = |ls: &[WnConvTranspose2d]| -> Vec<[usize; 4]> {
        ls.iter().map(|l| l.v.val().dims()).collect()
    };
    assert_eq!(
        ups(&a.before_view),
        vec![[256, 256, 4, 4], [256, 128, 4, 4]]
    );
    let mid: Vec<[usize; 4]> = a.mid.iter().map(|l| l.v.val().dims()).collect();
    assert_eq!(mid, vec![[128, 160, 3, 3], [128, 128, 3, 3]]);
    assert_eq!(
        ups(&a.after_view),
        vec![[128, 64, 4, 4], [64, 64, 4, 4], [64, 3, 4, 4], [3, 3, 4, 4]]
    );
    assert_eq!(
        a.after_view[3].untied_bias.as_ref().unwrap().val().dims(),
        [3, 512, 512]
    );
    let view: Vec<[usize; 4]> = net
        .view_encoder
        .convs
        .iter()
        .map(|l| l.v.val().dims())
        .collect();
    assert_eq!(view, vec![[16, 6, 3, 3], [32, 16, 3, 3]]);
    // Counted by hand (weights + g + biases): 8,131,378 with per-channel biases, of which
    // the weights alone match the 8.1M of the PyTorch anchor; untied biases add 9.24M.
    assert_eq!(net.num_params(), 17_370_817);
    let mut tied = NetConfig::paper();
    tied.untied_bias = false;
    assert_eq!(tied.init(&device).unwrap().num_params(), 8_131_378);
}

#[test]
fn forward_shapes_at_tiny_and_cpu_sizes() {
    let device = seeded(Device::ndarray(), 2);
    for (name, n, params) in [("tiny", 2, 237_925), ("cpu", 1, 1_580_430)] {
        let cfg = config(name);
        let net = cfg.init(&device).unwrap();
        assert_eq!(net.num_params(), params, "{name}");
        let cameras = vec![camera(); n];
        let maps = net
            .forward_cameras(condition(n, cfg.condition.dim(), 0.0, &device), &cameras)
            .unwrap();
        let r = cfg.uv_res;
        assert_eq!(maps.geometry.dims(), [n, 11, r, r], "{name}");
        assert_eq!(maps.rgb.dims(), [n, 3, r, r], "{name}");
        assert_eq!(maps.offset().dims(), [n, 3, r, r]);
        assert_eq!(maps.rotation().dims(), [n, 4, r, r]);
        assert_eq!(maps.log_scale().dims(), [n, 3, r, r]);
        assert_eq!(maps.opacity_logit().dims(), [n, 1, r, r]);
        assert_eq!(maps.frame(n - 1).dims(), [14, r, r]);
        // Packed channels are the lifting operator's: geometry 0..11, RGB 11..14.
        let packed = host(maps.packed().narrow(1, 11, 3));
        assert_eq!(packed, host(maps.rgb.clone()));
        assert!(host(maps.geometry).iter().all(|v| v.is_finite()));
    }
}

/// Folding the weight norms for inference reaches every layer and keeps the outputs.
#[test]
fn folded_net_computes_the_same_maps() {
    let device = seeded(Device::ndarray(), 4);
    let cfg = config("tiny");
    let net = cfg.init(&device).unwrap();
    // At initialisation v is the effective weight; scaling v (which the norm undoes) makes a
    // fold that skipped the norm without storing the weight show in the outputs.
    let net = TexAvatarNet {
        exp2code: texavatars::models::texavatars::Exp2Code {
            linear: WnLinear {
                v: Param::from_tensor(net.exp2code.linear.v.val() * 3.0),
                ..net.exp2code.linear
            },
            ..net.exp2code
        },
        ..net
    };
    let run = |net: &TexAvatarNet| {
        let maps = net
            .forward_cameras(condition(1, cfg.condition.dim(), 0.5, &device), &[camera()])
            .unwrap();
        (host(maps.geometry), host(maps.rgb))
    };
    let before = run(&net);
    let net = net.fold();
    let a = &net.appearance;
    assert!(net.exp2code.linear.folded);
    assert!(net.view_encoder.convs.iter().all(|c| c.folded));
    assert!(a.mid.iter().all(|c| c.folded));
    let ups = net
        .geometry
        .layers
        .iter()
        .chain(&a.before_view)
        .chain(&a.after_view);
    assert!(ups.clone().count() > 0 && ups.into_iter().all(|c| c.folded));
    let after = run(&net);
    for (b, f) in [(&before.0, &after.0), (&before.1, &after.1)] {
        let diff = b
            .iter()
            .zip(f)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(diff < 1e-5, "{diff}");
    }
}

#[test]
fn forward_rejects_mismatched_inputs() {
    let device = seeded(Device::ndarray(), 3);
    let cfg = config("tiny");
    let net = cfg.init(&device).unwrap();
    let e = net
        .forward_cameras(condition(1, 243, 0.0, &device), &[camera()])
        .unwrap_err()
        .to_string();
    assert!(e.contains("condition") && e.contains("195"), "{e}");
    let e = net
        .forward_cameras(condition(2, 195, 0.0, &device), &[camera()])
        .unwrap_err()
        .to_string();
    assert!(e.contains("pluecker"), "{e}");
}

#[test]
fn zero_eta_ablation_ignores_eta() {
    let device = seeded(Device::ndarray(), 4);
    let mut cfg = config("tiny");
    let dim = cfg.condition.dim();
    let eta = cfg.condition.eta;
    let base = condition(1, dim, 0.0, &device);
    let other_eta = Tensor::cat(
        vec![
            base.clone().narrow(1, 0, dim - eta),
            condition(1, eta, 5.0, &device),
        ],
        1,
    );
    for zero_eta in [false, true] {
        cfg.condition.zero_eta = zero_eta;
        device.seed(4);
        let net = cfg.init(&device).unwrap();
        let run = |c: Tensor<2>| host(net.forward_cameras(c, &[camera()]).unwrap().packed());
        let (a, b) = (run(base.clone()), run(other_eta.clone()));
        let diff = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        if zero_eta {
            assert_eq!(diff, 0.0);
        } else {
            assert!(diff > 1e-4, "eta must change the output, diff {diff}");
        }
    }
}

/// Checks that every float parameter has a finite, non-zero gradient.
struct GradCheck<'a> {
    grads: &'a Gradients,
    path: Vec<String>,
    checked: usize,
    failures: Vec<String>,
}

impl ModuleVisitor for GradCheck<'_> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        self.checked += 1;
        let name = format!("{} {:?}", self.path.join("."), param.val().dims());
        match param.val().grad(self.grads) {
            None => self.failures.push(format!("{name}: no gradient")),
            Some(g) => {
                assert_eq!(g.dims(), param.val().dims());
                let g = host(g);
                if g.iter().any(|v| !v.is_finite()) {
                    self.failures.push(format!("{name}: non-finite gradient"));
                } else if g.iter().all(|&v| v == 0.0) {
                    self.failures.push(format!("{name}: zero gradient"));
                }
            }
        }
    }
}

#[test]
fn every_parameter_receives_a_gradient() {
    let device = seeded(Device::ndarray().autodiff(), 5);
    let cfg = config("tiny");
    let net: TexAvatarNet = cfg.init(&device).unwrap();
    let n = 2;
    let maps = net
        .forward_cameras(
            condition(n, cfg.condition.dim(), 1.0, &device),
            &[camera(); 2],
        )
        .unwrap();
    let r = cfg.uv_res;
    let w = Tensor::<4>::random([n, 14, r, r], Distribution::Uniform(-1.0, 1.0), &device);
    let grads = (maps.packed() * w).sum().backward();
    let mut check = GradCheck {
        grads: &grads,
        path: Vec::new(),
        checked: 0,
        failures: Vec::new(),
    };
    net.visit(&mut check);
    // Exp2Code 3, view encoder 2 x 3, geometry 2 x 3, appearance (1 + 2 + 1) x 3.
    assert_eq!(check.checked, 3 + 6 + 6 + 12);
    assert!(check.failures.is_empty(), "{:#?}", check.failures);
}

// ---------------------------------------------------------------------------------------------
// Finite differences of one weight-normalised layer w.r.t. g and v.

/// loss = sum(layer(x) * w) of a transposed convolution 2 -> 3 (k4 s2 p1, untied bias) with
/// the given `v` [2, 3, 4, 4] and `g` [3]; returns the layer too.
fn conv_loss(v: &[f32], g: &[f32], device: &Device) -> (Tensor<1>, WnConvTranspose2d) {
    let mut layer = WnConvTranspose2dConfig::new([2, 3], [4, 4])
        .with_stride([2, 2])
        .with_padding([1, 1])
        .with_bias(Bias::Untied {
            height: 6,
            width: 6,
        })
        .init(device);
    layer.v = Param::from_data(TensorData::new(v.to_vec(), [2, 3, 4, 4]), device);
    layer.g = Param::from_data(TensorData::new(g.to_vec(), [3]), device);
    let x: Vec<f32> = (0..2 * 2 * 3 * 3)
        .map(|k| (k as f32 * 0.71).sin())
        .collect();
    let x = Tensor::<4>::from_data(TensorData::new(x, [2, 2, 3, 3]), device);
    let w: Vec<f32> = (0..2 * 3 * 6 * 6)
        .map(|k| (k as f32 * 1.3 + 0.2).cos())
        .collect();
    let w = Tensor::<4>::from_data(TensorData::new(w, [2, 3, 6, 6]), device);
    ((layer.forward(x) * w).sum(), layer)
}

/// loss = sum(layer(x) * w) of a linear layer 4 -> 3; returns the layer too.
fn linear_loss(v: &[f32], g: &[f32], device: &Device) -> (Tensor<1>, WnLinear) {
    let mut layer: WnLinear = WnLinearConfig::new(4, 3).init(device);
    layer.v = Param::from_data(TensorData::new(v.to_vec(), [3, 4]), device);
    layer.g = Param::from_data(TensorData::new(g.to_vec(), [3]), device);
    // A fixed bias: `init` draws a random one, which would differ between evaluations.
    layer.bias = Some(Param::from_data(
        TensorData::new(vec![0.1f32, -0.2, 0.3], [3]),
        device,
    ));
    let x: Vec<f32> = (0..5 * 4).map(|k| (k as f32 * 0.53).sin()).collect();
    let x = Tensor::<2>::from_data(TensorData::new(x, [5, 4]), device);
    let w: Vec<f32> = (0..5 * 3).map(|k| (k as f32 * 0.9 + 0.4).cos()).collect();
    let w = Tensor::<2>::from_data(TensorData::new(w, [5, 3]), device);
    ((layer.forward(x) * w).sum(), layer)
}

/// Central differences of `loss` w.r.t. every entry of `v` and `g`, compared with the
/// autodiff gradients.
fn check_fd<F, G>(v: Vec<f32>, g: Vec<f32>, loss: F, analytic: G)
where
    F: Fn(&[f32], &[f32]) -> f32,
    G: Fn(&[f32], &[f32]) -> (Vec<f32>, Vec<f32>),
{
    let (dv, dg) = analytic(&v, &g);
    let h = 1e-2f32;
    let fd = |which: usize, i: usize| -> f32 {
        let (mut vp, mut gp, mut vm, mut gm) = (v.clone(), g.clone(), v.clone(), g.clone());
        if which == 0 {
            vp[i] += h;
            vm[i] -= h;
        } else {
            gp[i] += h;
            gm[i] -= h;
        }
        (loss(&vp, &gp) - loss(&vm, &gm)) / (2.0 * h)
    };
    let mut worst = 0.0f32;
    for (which, analytic) in [(0, &dv), (1, &dg)] {
        for (i, &a) in analytic.iter().enumerate() {
            let n = fd(which, i);
            let err = (n - a).abs() / (1e-2 + a.abs().max(n.abs()));
            worst = worst.max(err);
            assert!(
                err < 2e-2,
                "{} [{i}]: autodiff {a}, finite differences {n}",
                ["v", "g"][which]
            );
        }
    }
    eprintln!("worst relative error {worst:.2e}");
}

#[test]
fn weight_norm_gradients_match_finite_differences() {
    let plain = Device::ndarray();
    let ad = Device::ndarray().autodiff();
    let scalar = |t: Tensor<1>| host(t)[0];
    // Values of order 1 so that h = 1e-2 is small against them and large against f32 noise.
    let v: Vec<f32> = (0..2 * 3 * 16)
        .map(|k| (k as f32 * 0.77 + 0.3).sin())
        .collect();
    let g = vec![0.8f32, -1.3, 2.1];
    check_fd(
        v,
        g.clone(),
        |v, g| scalar(conv_loss(v, g, &plain).0),
        |v, g| {
            let (loss, layer) = conv_loss(v, g, &ad);
            let grads = loss.backward();
            (
                host(layer.v.val().grad(&grads).unwrap()),
                host(layer.g.val().grad(&grads).unwrap()),
            )
        },
    );
    let v: Vec<f32> = (0..12).map(|k| (k as f32 * 1.1 - 0.5).cos()).collect();
    check_fd(
        v,
        g,
        |v, g| scalar(linear_loss(v, g, &plain).0),
        |v, g| {
            let (loss, layer) = linear_loss(v, g, &ad);
            let grads = loss.backward();
            (
                host(layer.v.val().grad(&grads).unwrap()),
                host(layer.g.val().grad(&grads).unwrap()),
            )
        },
    );
}

// ---------------------------------------------------------------------------------------------
// Pluecker maps.

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn ray(map: &PlueckerMap, y: usize, x: usize) -> ([f32; 3], [f32; 3]) {
    let m = [map.at(0, y, x), map.at(1, y, x), map.at(2, y, x)];
    let d = [map.at(3, y, x), map.at(4, y, x), map.at(5, y, x)];
    (m, d)
}

#[test]
fn pluecker_rays_of_a_known_camera() {
    let cam = camera();
    let map = PlueckerMap::of_camera(&cam);
    assert_eq!((map.height, map.width), (30, 40));
    let o = cam.position();
    for y in 0..map.height {
        for x in 0..map.width {
            let (m, d) = ray(&map, y, x);
            assert!((dot(d, d) - 1.0).abs() < 1e-6, "unit direction");
            assert!(dot(m, d).abs() < 1e-6, "moment orthogonal to direction");
            // m = o x d: every point o + t d of the ray has the same moment.
            let p = [o[0] + 2.0 * d[0], o[1] + 2.0 * d[1], o[2] + 2.0 * d[2]];
            let mp = [
                p[1] * d[2] - p[2] * d[1],
                p[2] * d[0] - p[0] * d[2],
                p[0] * d[1] - p[1] * d[0],
            ];
            for k in 0..3 {
                assert!((mp[k] - m[k]).abs() < 1e-5);
            }
        }
    }
    // The principal point (20.5, 14.5) is the centre of pixel (20, 14): its ray is the
    // optical axis, the camera's +z in world space (the third row of R): world +z here.
    let (m, d) = ray(&map, 14, 20);
    let axis = cam.rotation()[2];
    for k in 0..3 {
        assert!((d[k] - axis[k]).abs() < 1e-6, "{d:?} vs {axis:?}");
    }
    let expected_m = [
        o[1] * axis[2] - o[2] * axis[1],
        o[2] * axis[0] - o[0] * axis[2],
        o[0] * axis[1] - o[1] * axis[0],
    ];
    for k in 0..3 {
        assert!((m[k] - expected_m[k]).abs() < 1e-6);
    }
    // Row 0 is the top of the image: OpenCV's y_cam points down, so the top row's rays have
    // y_cam < 0; with this camera's roll y_cam = x_world.
    assert!(ray(&map, 0, 20).1[0] < 0.0 && ray(&map, 29, 20).1[0] > 0.0);
    // Column 0 is the left: x_cam < 0, and x_cam = -y_world here.
    assert!(ray(&map, 14, 0).1[1] > 0.0 && ray(&map, 14, 39).1[1] < 0.0);
}

#[test]
fn view_input_of_a_centred_camera_is_symmetric() {
    // A camera at the world origin has zero moments; with the principal point at the image
    // centre, the 128^2 input is mirror-symmetric in x_cam and its centre looks along +z.
    let mut cam = camera();
    cam.world_to_camera = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    cam.cx = 20.0;
    cam.cy = 15.0;
    let map = view_input(&cam, PLUECKER_SQUARE_RES, 128).unwrap();
    assert_eq!(
        (map.height, map.width, map.data.len()),
        (128, 128, 6 * 128 * 128)
    );
    for y in 0..128 {
        for x in 0..128 {
            let (m, d) = ray(&map, y, x);
            assert!(m.iter().all(|v| v.abs() < 1e-6));
            let (_, dm) = ray(&map, y, 127 - x);
            assert!((d[0] + dm[0]).abs() < 1e-5 && (d[1] - dm[1]).abs() < 1e-5);
            assert!(d[2] > 0.0);
        }
    }
    let (_, d) = ray(&map, 63, 63);
    let (_, e) = ray(&map, 64, 64);
    assert!((d[0] + e[0]).abs() < 1e-5 && (d[1] + e[1]).abs() < 1e-5);
}

// ---------------------------------------------------------------------------------------------

#[test]
fn decoder_outputs_feed_the_lifting_operator() {
    let device = seeded(Device::ndarray().autodiff(), 6);
    let cfg = config("tiny");
    let net = cfg.init(&device).unwrap();
    let mesh = UvMesh::cylinder_patch(6);
    let topology = Arc::new(Topology::new(&mesh, cfg.uv_res, cfg.uv_res).unwrap());
    let params = LiftParams {
        topology: topology.clone(),
        mode: LiftMode::Global,
        frame: FrameKind::Jacobian,
    };
    let maps = net
        .forward_cameras(condition(1, cfg.condition.dim(), 2.0, &device), &[camera()])
        .unwrap();
    let verts: Vec<f32> = mesh.positions.iter().flatten().copied().collect();
    let verts = Tensor::<2>::from_data(TensorData::new(verts, [mesh.positions.len(), 3]), &device);
    let lifted = lift::lift(maps.frame(0), verts, &params).unwrap();
    assert_eq!(lifted.means.dims(), [topology.len(), 3]);
    let loss =
        lifted.means.sum() + lifted.colors.sum() + lifted.opacities.sum() + lifted.cov6.sum();
    let grads = loss.backward();
    let g = net.geometry.layers[0]
        .v
        .val()
        .grad(&grads)
        .expect("gradient through the lift");
    assert!(host(g).iter().any(|v| *v != 0.0));
}

/// The transposed convolution's wgpu path (burn's own kernels behind the extension) against
/// the host path, values and gradients, at the decoders' kernel, stride and padding.
#[test]
fn conv_transpose_wgpu_matches_host() {
    use texavatars::cpu::conv::{ConvParams, conv};
    let p = ConvParams::transposed([2, 2], [1, 1]);
    let run = |device: Device| {
        let x: Vec<f32> = (0..2 * 3 * 5 * 4)
            .map(|i| ((i * 37 % 17) as f32 - 8.0) / 8.0)
            .collect();
        let w: Vec<f32> = (0..3 * 2 * 4 * 4)
            .map(|i| ((i * 53 % 13) as f32 - 6.0) / 6.0)
            .collect();
        let x = Tensor::<4>::from_data(TensorData::new(x, [2, 3, 5, 4]), &device).require_grad();
        let w = Tensor::<4>::from_data(TensorData::new(w, [3, 2, 4, 4]), &device).require_grad();
        let y = conv(x.clone(), w.clone(), p);
        assert_eq!(y.dims(), [2, 2, 10, 8]);
        let weights = Tensor::<4>::from_data(
            TensorData::new(
                (0..320).map(|i| (i % 7) as f32 - 3.0).collect(),
                [2, 2, 10, 8],
            ),
            &device,
        );
        let grads = (y.clone() * weights).sum().backward();
        (
            host(y),
            host(x.grad(&grads).expect("x grad")),
            host(w.grad(&grads).expect("w grad")),
        )
    };
    let cpu = run(Device::flex().autodiff());
    let gpu = run(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice).autodiff());
    for (name, a, b) in [
        ("y", cpu.0, gpu.0),
        ("dx", cpu.1, gpu.1),
        ("dw", cpu.2, gpu.2),
    ] {
        let d = a
            .iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(d < 1e-4, "{name}: max difference {d}");
    }
}

/// The fused 3x3 layer (convolution + bias + LeakyReLU) on wgpu, where it composes burn's
/// `conv2d`, its backward functions and the element-wise ops (the trait's default bodies),
/// against the host op on flex: values and the gradients of input, weight and both bias
/// kinds, at the view encoder's (stride 2) and the appearance decoder's (stride 1) maps.
#[test]
fn conv_bias_act_wgpu_matches_host() {
    use texavatars::cpu::conv::ConvParams;
    use texavatars::cpu::conv_bias_act::conv_bias_act;
    let value = |i: usize, a: usize, m: usize, d: f32| ((i * a % m) as f32 - (m / 2) as f32) / d;
    for stride in [1usize, 2] {
        let p = ConvParams::plain([stride, stride], [1, 1]);
        let [ho, wo] = p.output_size([6, 5], [3, 3]).expect("valid");
        let run = |device: Device, untied: bool| {
            let x: Vec<f32> = (0..2 * 3 * 6 * 5).map(|i| value(i, 37, 17, 8.0)).collect();
            let w: Vec<f32> = (0..2 * 3 * 9).map(|i| value(i, 53, 13, 6.0)).collect();
            let x =
                Tensor::<4>::from_data(TensorData::new(x, [2, 3, 6, 5]), &device).require_grad();
            let w =
                Tensor::<4>::from_data(TensorData::new(w, [2, 3, 3, 3]), &device).require_grad();
            let up = Tensor::<4>::from_data(
                TensorData::new(
                    (0..2 * 2 * ho * wo).map(|i| (i % 7) as f32 - 3.0).collect(),
                    [2, 2, ho, wo],
                ),
                &device,
            );
            let (y, grads, db) = if untied {
                let b: Vec<f32> = (0..2 * ho * wo).map(|i| value(i, 29, 11, 5.0)).collect();
                let b =
                    Tensor::<3>::from_data(TensorData::new(b, [2, ho, wo]), &device).require_grad();
                let y = conv_bias_act(x.clone(), w.clone(), b.clone(), p, true);
                let grads = (y.clone() * up).sum().backward();
                let db = host(b.grad(&grads).expect("bias grad"));
                (y, grads, db)
            } else {
                let b = Tensor::<1>::from_data(TensorData::new(vec![0.3f32, -0.4], [2]), &device)
                    .require_grad();
                let y = conv_bias_act(x.clone(), w.clone(), b.clone(), p, true);
                let grads = (y.clone() * up).sum().backward();
                let db = host(b.grad(&grads).expect("bias grad"));
                (y, grads, db)
            };
            [
                host(y),
                host(x.grad(&grads).expect("x grad")),
                host(w.grad(&grads).expect("w grad")),
                db,
            ]
        };
        for untied in [false, true] {
            let cpu = run(Device::flex().autodiff(), untied);
            let gpu = run(
                Device::wgpu(burn::tensor::DeviceKind::DefaultDevice).autodiff(),
                untied,
            );
            for ((name, a), b) in ["y", "dx", "dw", "db"].iter().zip(&cpu).zip(&gpu) {
                let scale = a.iter().fold(1.0f32, |m, v| m.max(v.abs()));
                let d = a
                    .iter()
                    .zip(b)
                    .map(|(x, y)| (x - y).abs())
                    .fold(0.0, f32::max);
                assert!(
                    d < 1e-4 * scale,
                    "stride {stride}, untied {untied}, {name}: max difference {d}"
                );
            }
        }
    }
}

/// With the `fusion` feature (on by default) burn's cubecl backend is its kernel-fusion
/// backend, so every wgpu test in this suite runs on `Fusion<CubeBackend>`.
#[cfg(feature = "fusion")]
#[test]
fn the_cube_backend_is_fused() {
    use std::any::TypeId;
    assert_eq!(
        TypeId::of::<burn::backend::Cube>(),
        TypeId::of::<burn::backend::fusion::Fusion<burn_cubecl::CubeBackend>>()
    );
}

/// The decoders on wgpu (fused element-wise chains: bias, LeakyReLU, weight norm) against
/// flex, the same weights on both: local maps and the gradients of the first geometry layer.
#[test]
fn decoders_on_wgpu_match_flex() {
    let cfg = config("tiny");
    let cpu = seeded(Device::flex().autodiff(), 11);
    let gpu = Device::wgpu(burn::tensor::DeviceKind::DefaultDevice).autodiff();
    let net = cfg.init(&cpu).unwrap();
    let run = |net: TexAvatarNet, device: &Device| {
        let maps = net
            .forward_cameras(condition(1, cfg.condition.dim(), 0.5, device), &[camera()])
            .unwrap();
        let packed = maps.packed();
        // A weighted sum, so that every map value has its own gradient.
        let n = packed.shape().num_elements();
        let w: Vec<f32> = (0..n).map(|i| ((i * 29 % 11) as f32 - 5.0) / 5.0).collect();
        let w = Tensor::<4>::from_data(TensorData::new(w, packed.dims()), device);
        let grads = (packed.clone() * w).sum().backward();
        let g = net.geometry.layers[0]
            .v
            .val()
            .grad(&grads)
            .expect("gradient");
        (host(packed), host(g))
    };
    let (maps_cpu, g_cpu) = run(net.clone(), &cpu);
    let (maps_gpu, g_gpu) = run(net.fork(&gpu), &gpu);
    for (name, a, b) in [("maps", maps_cpu, maps_gpu), ("d v", g_cpu, g_gpu)] {
        assert_eq!(a.len(), b.len(), "{name}");
        let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-6);
        let d = a
            .iter()
            .zip(&b)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(
            d <= 1e-4 * scale,
            "{name}: max difference {d} (scale {scale})"
        );
    }
}
