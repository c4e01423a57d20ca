//! The VHAP dataset and batcher on a tiny export written here: 2 timesteps x 2 cameras of
//! 8x6 images (camera 0: RGBA with a mask, camera 1: RGB without), FLAME parameters with
//! fewer and more expression coefficients than the model, eta for timestep 0 only.
//! Round trip, batching, burn's data loader, and every malformed input named by file and
//! field.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use burn::data::dataloader::DataLoaderBuilder;
use burn::data::dataloader::batcher::Batcher;
use burn::data::dataset::Dataset;
use burn::tensor::{Device, Tensor};
use serde_json::json;
use texavatars::data::vhap::{ETA_DIM, opencv_world_to_camera};
use texavatars::data::{HeadBatcher, HeadDataset, HeadItem, Split};
use texavatars::device::BackendKind;
use texavatars::head::model::HeadModel;
use texavatars::head::{HeadPose, lbs};
use texavatars::io::npz::NpzOut;

use crate::common;

const W: u32 = 8;
const H: u32 = 6;
const E: usize = 3;
const V: usize = 6;

/// The shared tiny head with three expression directions.
fn tiny() -> HeadModel {
    common::head::tiny_head(E)
}

/// Timestep 0: two expression coefficients (padded), a static offset, eta on disk.
/// Timestep 1: five (truncated), no static offset, no eta.
fn pose(t: usize) -> HeadPose {
    if t == 0 {
        HeadPose {
            shape: vec![0.1],
            expr: vec![0.5, -0.25],
            jaw: [0.3, 0.0, 0.0],
            translation: [0.0, 0.0, 1.0],
            static_offset: Some((0..V).map(|i| [0.01 * i as f32, 0.0, -0.02]).collect()),
            ..Default::default()
        }
    } else {
        HeadPose {
            shape: vec![-0.2],
            expr: vec![1.0, 2.0, 3.0, 4.0, 5.0],
            rotation: [0.0, 0.2, 0.0],
            neck: [0.1, 0.0, 0.0],
            eyes: [0.0, 0.1, 0.0, 0.0, -0.1, 0.0],
            translation: [0.5, -0.5, 0.0],
            ..Default::default()
        }
    }
}

fn eta0() -> Vec<f32> {
    (0..ETA_DIM).map(|i| i as f32 / 10.0 - 3.0).collect()
}

/// VHAP's camera-to-world (OpenGL) of camera `c`.
fn c2w(c: usize) -> [[f32; 4]; 4] {
    if c == 0 {
        [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 3.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    } else {
        [
            [0.0, 0.0, 1.0, 3.0],
            [0.0, 1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }
}

/// The 8-bit value of channel `ch` at pixel (`x`, `y`) of timestep `t`, camera `c`; channel
/// 3 is alpha, channel 4 the mask.
fn texel(t: usize, c: usize, x: u32, y: u32, ch: usize) -> u8 {
    ((t * 7 + c * 13 + x as usize * 17 + y as usize * 29 + ch * 41) % 256) as u8
}

/// Expected item `i` (= timestep i / 2, camera i % 2) image and mask.
fn expected_pixels(t: usize, c: usize) -> (Vec<f32>, Vec<f32>) {
    let mut image = Vec::new();
    let mut mask = Vec::new();
    for y in 0..H {
        for x in 0..W {
            let a = if c == 0 {
                f32::from(texel(t, c, x, y, 3)) / 255.0
            } else {
                1.0
            };
            for ch in 0..3 {
                image.push(f32::from(texel(t, c, x, y, ch)) / 255.0 * a + (1.0 - a));
            }
            mask.push(if c == 0 {
                f32::from(texel(t, c, x, y, 4)) / 255.0
            } else {
                1.0
            });
        }
    }
    (image, mask)
}

/// The arrays of a VHAP `flame_param` file, to edit before writing with [`write_arrays`].
fn arrays(p: &HeadPose) -> Vec<(&'static str, Vec<usize>, Vec<f32>)> {
    let mut a = vec![
        ("translation", vec![1, 3], p.translation.to_vec()),
        ("rotation", vec![1, 3], p.rotation.to_vec()),
        ("neck_pose", vec![1, 3], p.neck.to_vec()),
        ("jaw_pose", vec![1, 3], p.jaw.to_vec()),
        ("eyes_pose", vec![1, 6], p.eyes.to_vec()),
        ("expr", vec![1, p.expr.len()], p.expr.clone()),
        ("shape", vec![p.shape.len()], p.shape.clone()),
    ];
    if let Some(o) = &p.static_offset {
        a.push(("static_offset", vec![1, o.len(), 3], o.concat()));
    }
    a
}

fn write_arrays(path: &Path, arrays: &[(&str, Vec<usize>, Vec<f32>)]) {
    let mut out = NpzOut::default();
    for (name, shape, data) in arrays {
        out.floats(name, shape, data.clone());
    }
    out.write(path).expect("write npz");
}

/// A tiny export in a fresh temporary folder.
struct Fixture {
    root: PathBuf,
    model: Arc<HeadModel>,
}

impl Fixture {
    fn new(name: &str) -> Self {
        let root =
            std::env::temp_dir().join(format!("texavatars-data-{}-{name}", std::process::id()));
        if root.exists() {
            std::fs::remove_dir_all(&root).expect("clear");
        }
        for d in ["images", "fg_masks", "flame_param", "eta"] {
            std::fs::create_dir_all(root.join(d)).expect("dir");
        }
        let model_path = root.join("head.npz");
        tiny().save(&model_path).expect("save model");
        let model = Arc::new(HeadModel::load(&model_path).expect("load model"));
        let mut frames = Vec::new();
        for t in 0..2 {
            pose(t)
                .save_npz(&root.join(format!("flame_param/{t:05}.npz")))
                .expect("params");
            for c in 0..2 {
                let image = format!("images/{t:05}_{c:02}.png");
                let mask = format!("fg_masks/{t:05}_{c:02}.png");
                if c == 0 {
                    image::RgbaImage::from_fn(W, H, |x, y| {
                        image::Rgba(std::array::from_fn(|ch| texel(t, c, x, y, ch)))
                    })
                    .save(root.join(&image))
                    .expect("png");
                    image::GrayImage::from_fn(W, H, |x, y| image::Luma([texel(t, c, x, y, 4)]))
                        .save(root.join(&mask))
                        .expect("mask");
                } else {
                    image::RgbImage::from_fn(W, H, |x, y| {
                        image::Rgb(std::array::from_fn(|ch| texel(t, c, x, y, ch)))
                    })
                    .save(root.join(&image))
                    .expect("png");
                }
                let mut f = json!({
                    "timestep_index": t,
                    "camera_index": c,
                    "file_path": image,
                    "flame_param_path": format!("flame_param/{t:05}.npz"),
                    "transform_matrix": c2w(c),
                });
                if c == 0 {
                    f["fg_mask_path"] = json!(mask);
                }
                frames.push(f);
            }
        }
        texavatars::io::npy::write(&root.join("eta/00000.npy"), &[ETA_DIM], &eta0()).expect("eta");
        let transforms = json!({
            "cx": 4.0, "cy": 3.0, "fl_x": 10.0, "fl_y": 11.0, "h": H, "w": W,
            "timestep_indices": [0, 1], "camera_indices": [0, 1],
            "frames": frames,
        });
        std::fs::write(
            root.join("transforms_train.json"),
            serde_json::to_string_pretty(&transforms).expect("json"),
        )
        .expect("write json");
        Fixture { root, model }
    }

    fn path(&self, rel: &str) -> PathBuf {
        self.root.join(rel)
    }

    fn open(&self) -> texavatars::error::Result<HeadDataset> {
        HeadDataset::open(&self.root, Split::Train, self.model.clone())
    }

    fn truncate(&self, rel: &str) {
        let p = self.path(rel);
        let bytes = std::fs::read(&p).expect("read");
        std::fs::write(&p, &bytes[..bytes.len() / 2]).expect("truncate");
    }
}

fn cpu() -> Device {
    BackendKind::Cpu.device()
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().iter::<f32>().collect()
}

fn close(a: &[f32], b: &[f32], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() < 1e-6, "{what}[{i}]: {x} vs {y}");
    }
}

/// Asserts that `err`'s message contains every one of `parts`.
fn assert_names(err: impl std::fmt::Display, parts: &[&str]) {
    let msg = err.to_string();
    for p in parts {
        assert!(msg.contains(p), "{msg:?} does not name {p:?}");
    }
}

#[test]
fn split_names_and_files() {
    for s in Split::ALL {
        assert_eq!(s.to_string().parse::<Split>().expect("parse"), s);
        assert_eq!(s.file_name(), format!("transforms_{s}.json"));
    }
    assert_eq!(Split::Free.file_name(), "transforms_free.json");
    assert_names(
        "validation".parse::<Split>().expect_err("bad name"),
        &["validation", "split"],
    );
    let fx = Fixture::new("split");
    let e = HeadDataset::open(&fx.root, Split::Val, fx.model.clone()).expect_err("no val");
    assert_names(e, &["transforms_val.json"]);
}

#[test]
fn items_round_trip() {
    let fx = Fixture::new("round-trip");
    let ds = fx.open().expect("open");
    assert_eq!(ds.len(), 4);
    assert_eq!(Dataset::len(&ds), 4);
    for i in 0..4 {
        let (t, c) = (i / 2, i % 2);
        let item = ds.load_item(i).expect("item");
        assert_eq!(Dataset::get(&ds, i).expect("get"), item);
        assert_eq!((item.timestep, item.camera_index), (t, c));
        assert_eq!(
            item.image_path,
            fx.path(&format!("images/{t:05}_{c:02}.png"))
        );
        assert_eq!((item.camera.width, item.camera.height), (W, H));
        assert_eq!(
            (
                item.camera.fx,
                item.camera.fy,
                item.camera.cx,
                item.camera.cy
            ),
            (10.0, 11.0, 4.0, 3.0)
        );
        assert_eq!(item.camera.world_to_camera, opencv_world_to_camera(&c2w(c)));
        let (image, mask) = expected_pixels(t, c);
        close(&item.image, &image, "image");
        close(&item.mask, &mask, "mask");
        // Expression fitted to the model's 3: padded for timestep 0, truncated for 1.
        let want_expr = if t == 0 {
            vec![0.5, -0.25, 0.0]
        } else {
            vec![1.0, 2.0, 3.0]
        };
        assert_eq!(item.expr, want_expr);
        assert_eq!(item.pose, pose(t).pose15());
        let want_eta = if t == 0 { eta0() } else { vec![0.0; ETA_DIM] };
        assert_eq!(item.eta, want_eta);
        // One identity per subject: timestep 0's shape and static offsets (the first
        // timestep of the training split, GaussianAvatars' `load_meshes`) for every frame.
        let posed = HeadPose {
            expr: want_expr,
            shape: pose(0).shape,
            static_offset: pose(0).static_offset,
            ..pose(t)
        };
        assert_eq!(item.vertices, lbs(&fx.model, &posed).expect("lbs"));
    }
    // The static offset and translation of timestep 0 reach the vertices.
    let item = ds.load_item(0).expect("item");
    assert!((item.vertices[0][2] - (1.0 - 0.02)).abs() < 1e-6);
}

#[test]
fn conditioning_is_cached_per_timestep() {
    let fx = Fixture::new("cache");
    let ds = fx.open().expect("open");
    let (a, b, c) = (
        ds.conditioning(0).expect("0"),
        ds.conditioning(1).expect("1"),
        ds.conditioning(2).expect("2"),
    );
    assert!(Arc::ptr_eq(&a, &b), "cameras of one timestep share it");
    assert!(!Arc::ptr_eq(&a, &c));
    let ds = ds.with_cache(false);
    let (a2, b2) = (
        ds.conditioning(0).expect("0"),
        ds.conditioning(1).expect("1"),
    );
    assert!(!Arc::ptr_eq(&a2, &b2));
    assert_eq!(a2, a);
}

#[test]
fn batch_shapes_and_condition_layout() {
    let fx = Fixture::new("batch");
    let ds = fx.open().expect("open");
    let items: Vec<HeadItem> = (0..4).map(|i| ds.load_item(i).expect("item")).collect();
    let b = HeadBatcher.batch(items.clone(), &cpu());
    let (h, w) = (H as usize, W as usize);
    assert_eq!(b.images.dims(), [4, h, w, 3]);
    assert_eq!(b.masks.dims(), [4, h, w, 1]);
    assert_eq!(b.expr.dims(), [4, E]);
    assert_eq!(b.pose.dims(), [4, 15]);
    assert_eq!(b.eta.dims(), [4, ETA_DIM]);
    assert_eq!(b.condition.dims(), [4, E + 15 + ETA_DIM]);
    assert_eq!(b.vertices.dims(), [4, V, 3]);
    assert_eq!(b.timesteps, vec![0, 0, 1, 1]);
    assert_eq!(b.camera_indices, vec![0, 1, 0, 1]);
    assert_eq!(
        b.cameras,
        items.iter().map(|it| it.camera).collect::<Vec<_>>()
    );
    let concat = |f: &dyn Fn(&HeadItem) -> Vec<f32>| items.iter().flat_map(f).collect::<Vec<_>>();
    assert_eq!(host(b.images), concat(&|it| it.image.clone()));
    assert_eq!(host(b.masks), concat(&|it| it.mask.clone()));
    assert_eq!(host(b.vertices), concat(&|it| it.vertices.concat()));
    // The paper's order: [expr, pose, eta] per row.
    assert_eq!(
        host(b.condition),
        concat(&|it| [it.expr.clone(), it.pose.to_vec(), it.eta.clone()].concat())
    );
    assert_eq!(host(b.expr), concat(&|it| it.expr.clone()));
    assert_eq!(host(b.pose), concat(&|it| it.pose.to_vec()));
    assert_eq!(host(b.eta), concat(&|it| it.eta.clone()));

    // Items that do not stack.
    let mut odd = items[1].clone();
    odd.camera.width = W - 1;
    odd.image.truncate(h * (w - 1) * 3);
    odd.mask.truncate(h * (w - 1));
    let e = HeadBatcher
        .try_batch(vec![items[0].clone(), odd], &cpu())
        .expect_err("sizes differ");
    assert_names(e, &["images", "item 1", "00000_01.png", "00000_00.png"]);
    assert_names(
        HeadBatcher
            .try_batch(Vec::new(), &cpu())
            .expect_err("empty"),
        &["items"],
    );
}

#[test]
fn burn_data_loader_batches_the_dataset() {
    let fx = Fixture::new("loader");
    let loader = DataLoaderBuilder::new(HeadBatcher)
        .batch_size(3)
        .set_device(cpu())
        .build(fx.open().expect("open"));
    let sizes: Vec<usize> = loader
        .iter()
        .map(|b| b.expect("batch").images.dims()[0])
        .collect();
    assert_eq!(sizes, vec![3, 1]);
    // A bad file surfaces as the batch's error, naming the file.
    fx.truncate("flame_param/00001.npz");
    let loader = DataLoaderBuilder::new(HeadBatcher)
        .batch_size(3)
        .set_device(cpu())
        .build(fx.open().expect("open"));
    // Only the first result: burn 0.22's loader does not move past a failed batch, it
    // yields the same error again on every `next`.
    let first = loader.iter().next().expect("a result");
    assert_names(first.map(|_| ()).expect_err("bad npz"), &["00001.npz"]);
    // With worker threads the error ends the iteration.
    let loader = DataLoaderBuilder::new(HeadBatcher)
        .batch_size(1)
        .num_workers(2)
        .set_device(cpu())
        .build(fx.open().expect("open"));
    let e = loader.iter().find_map(Result::err).expect("an error");
    assert_names(e, &["00001.npz", "`archive`"]);
}

/// Breaks the fixture with `edit`, then asserts that item `index` (through `load_item` and
/// through burn's `Dataset::get`) fails naming every one of `parts`.
fn item_fails(name: &str, index: usize, edit: impl FnOnce(&Fixture), parts: &[&str]) {
    let fx = Fixture::new(name);
    edit(&fx);
    // The subject's identity is read when the dataset opens: a broken first timestep fails
    // there.
    match fx.open() {
        Err(e) => assert_names(e, parts),
        Ok(ds) => {
            assert_names(ds.load_item(index).expect_err(name), parts);
            assert_names(Dataset::get(&ds, index).expect_err(name), parts);
        }
    }
}

#[test]
fn npz_missing_key() {
    item_fails(
        "no-expr",
        0,
        |fx| {
            let mut a = arrays(&pose(0));
            a.retain(|(n, _, _)| *n != "expr");
            write_arrays(&fx.path("flame_param/00000.npz"), &a);
        },
        &["00000.npz", "`expr`", "missing"],
    );
}

#[test]
fn npz_wrong_shape() {
    item_fails(
        "rotation-2",
        2,
        |fx| {
            let mut a = arrays(&pose(1));
            a[1] = ("rotation", vec![1, 2], vec![0.0, 0.1]);
            write_arrays(&fx.path("flame_param/00001.npz"), &a);
        },
        &["00001.npz", "`rotation`", "[1, 2]"],
    );
    item_fails(
        "offset-count",
        0,
        |fx| {
            let mut a = arrays(&pose(0));
            a.retain(|(n, _, _)| *n != "static_offset");
            a.push(("static_offset", vec![1, 7, 3], vec![0.0; 21]));
            write_arrays(&fx.path("flame_param/00000.npz"), &a);
        },
        &["00000.npz", "`static_offset`", "6 vertices"],
    );
    item_fails(
        "shape-count",
        1,
        |fx| {
            let mut a = arrays(&pose(0));
            a[6] = ("shape", vec![2], vec![0.1, 0.2]);
            write_arrays(&fx.path("flame_param/00000.npz"), &a);
        },
        &["00000.npz", "`shape`", "2 coefficients"],
    );
    item_fails(
        "eta-shape",
        1,
        |fx| {
            texavatars::io::npy::write(&fx.path("eta/00000.npy"), &[2], &[0.0, 1.0]).expect("eta");
        },
        &["00000.npy", "`eta`"],
    );
}

#[test]
fn truncated_npz() {
    item_fails(
        "npz-trunc",
        3,
        |fx| fx.truncate("flame_param/00001.npz"),
        &["00001.npz", "`archive`"],
    );
}

#[test]
fn truncated_png() {
    item_fails(
        "png-trunc",
        0,
        |fx| fx.truncate("images/00000_00.png"),
        &["00000_00.png", "`image`"],
    );
    item_fails(
        "mask-trunc",
        2,
        |fx| fx.truncate("fg_masks/00001_00.png"),
        &["00001_00.png", "`mask`"],
    );
}

#[test]
fn missing_image_file() {
    item_fails(
        "no-image",
        3,
        |fx| std::fs::remove_file(fx.path("images/00001_01.png")).expect("rm"),
        &[
            "transforms_train.json",
            "frames[3].file_path",
            "00001_01.png",
        ],
    );
    // Masks are optional (GaussianAvatars never reads them): a named mask file that does
    // not exist means no mask.
    let fx = Fixture::new("no-mask");
    std::fs::remove_file(fx.path("fg_masks/00000_00.png")).expect("rm");
    let item = fx.open().expect("open").load_item(0).expect("item");
    assert!(item.mask.iter().all(|&m| m == 1.0));
}

#[test]
fn image_size_must_match_the_camera() {
    item_fails(
        "size",
        1,
        |fx| {
            image::RgbImage::new(W - 1, H)
                .save(fx.path("images/00000_01.png"))
                .expect("png");
        },
        &["00000_01.png", "`size`", "7x6", "w = 8, h = 6"],
    );
    item_fails(
        "mask-size",
        0,
        |fx| {
            image::GrayImage::new(W, H + 1)
                .save(fx.path("fg_masks/00000_00.png"))
                .expect("png");
        },
        &["00000_00.png", "`size`", "8x7"],
    );
}

#[test]
fn truncated_or_incomplete_json() {
    let fx = Fixture::new("json-trunc");
    fx.truncate("transforms_train.json");
    assert_names(
        fx.open().expect_err("truncated"),
        &["transforms_train.json", "`json`"],
    );
    // A frame without FLAME parameters is refused when the dataset is opened.
    let fx = Fixture::new("json-no-flame");
    let p = fx.path("transforms_train.json");
    let mut j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&p).expect("read")).expect("json");
    j["frames"][2]
        .as_object_mut()
        .expect("frame")
        .remove("flame_param_path");
    std::fs::write(&p, j.to_string()).expect("write");
    assert_names(
        fx.open().expect_err("no flame_param_path"),
        &["transforms_train.json", "frames[2].flame_param_path"],
    );
}

#[test]
fn index_past_the_end_is_an_error() {
    let fx = Fixture::new("index");
    let ds = fx.open().expect("open");
    assert_names(
        ds.load_item(4).expect_err("past the end"),
        &["transforms_train.json", "`frames`", "index 4"],
    );
    assert!(Dataset::get(&ds, 4).is_err());
}

/// A hand-written export in VHAP's and GaussianAvatars' conventions (not through our
/// writer): two sequences of a union export with different `shape` and `static_offset`, an
/// off-centre principal point, a `file_path` without `.png`, an RGBA image, no masks,
/// `camera_id`/`timestep_id` strings, and a second split with GaussianAvatars' minimum
/// (`camera_angle_x` only).
#[test]
fn vhap_style_export_is_read_as_the_peers_mean_it() {
    let root = std::env::temp_dir().join(format!("texavatars-data-{}-vhap", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let (w, h) = (16u32, 12u32);
    let model = Arc::new(tiny());
    // Sequence A: shape 0.1, offsets for 4 of the 6 vertices (zero-padded, as
    // GaussianAvatars' `FlameGaussianModel.load_meshes` pads them). Sequence B: another
    // subject fit.
    let seq_pose = |seq: usize| HeadPose {
        shape: vec![if seq == 0 { 0.1 } else { -0.3 }],
        expr: vec![0.2 * seq as f32, 0.0, 0.1],
        jaw: [0.1 * seq as f32, 0.0, 0.0],
        static_offset: Some(vec![[0.01 + 0.02 * seq as f32, 0.0, 0.0]; 4]),
        ..Default::default()
    };
    for (seq, name) in ["A", "B"].iter().enumerate() {
        let d = root.join(name);
        std::fs::create_dir_all(d.join("images")).expect("dir");
        std::fs::create_dir_all(d.join("flame_param")).expect("dir");
        write_arrays(&d.join("flame_param/00000.npz"), &arrays(&seq_pose(seq)));
        // Each source sequence of a combined export is an export of its own
        // (`vhap/combine_nerf_datasets.py`, `NeRFDatasetAssembler.combine_dbs` reads
        // `src_folder / "transforms.json"`); only such siblings may be read through `..`.
        std::fs::write(d.join("transforms.json"), "{}").expect("json");
        // RGBA: left half transparent (white after compositing), right half opaque red.
        image::RgbaImage::from_fn(w, h, |x, _| {
            if x < w / 2 {
                image::Rgba([0, 0, 255, 0])
            } else {
                image::Rgba([255, 0, 0, 255])
            }
        })
        .save(d.join("images/00000_00.png"))
        .expect("png");
    }
    let union = root.join("union");
    std::fs::create_dir_all(&union).expect("dir");
    // VHAP's camera-to-world (OpenGL) for a camera at z = +3 looking down -z; intrinsics
    // as VHAP stores them: cy is `h - cy_opencv` (`vhap/util/camera.py`,
    // `convert_camera_convention`, "opencv->opengl").
    let frame = |seq: &str, t: usize| {
        json!({
            "timestep_index": t, "camera_index": 0,
            "camera_id": "222200037", "timestep_id": "frame_00000",
            "file_path": format!("../{seq}/images/00000_00"),
            "flame_param_path": format!("../{seq}/flame_param/00000.npz"),
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]],
            "cx": 5.0, "cy": 2.0, "fl_x": 30.0, "fl_y": 30.0, "h": h, "w": w,
        })
    };
    let train = json!({
        "cx": 8.0, "cy": 6.0, "fl_x": 99.0, "fl_y": 99.0, "h": h, "w": w,
        "frames": [frame("A", 0), frame("B", 1)],
    });
    std::fs::write(union.join("transforms_train.json"), train.to_string()).expect("json");
    // GaussianAvatars' minimum: only camera_angle_x (2 atan(8 / 30): focal 30 for w = 16).
    let angle = 2.0 * (8.0f32 / 30.0).atan();
    let test = json!({
        "camera_angle_x": angle,
        "frames": [{
            "timestep_index": 1, "camera_index": 0, "w": w, "h": h,
            "file_path": "../B/images/00000_00.png",
            "flame_param_path": "../B/flame_param/00000.npz",
            "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,3],[0,0,0,1]],
        }],
    });
    std::fs::write(union.join("transforms_test.json"), test.to_string()).expect("json");

    let ds = HeadDataset::open(&union, Split::Train, model.clone()).expect("open");
    let a = ds.load_item(0).expect("A");
    let b = ds.load_item(1).expect("B");
    // The world point (0.1, 0.2, 0) is 3 in front of the camera with y flipped (OpenCV):
    // (0.1, -0.2, 3). By hand: u = 30 * 0.1 / 3 + 5 = 6, v = 30 * -0.2 / 3 + (12 - 2) = 8.
    let project = |c: &texavatars::camera::Camera, p: [f32; 3]| {
        let m = c.world_to_camera;
        let q: [f32; 3] =
            std::array::from_fn(|i| (0..3).map(|k| m[i][k] * p[k]).sum::<f32>() + m[i][3]);
        (c.fx * q[0] / q[2] + c.cx, c.fy * q[1] / q[2] + c.cy)
    };
    let (u, v) = project(&a.camera, [0.1, 0.2, 0.0]);
    assert!(
        (u - 6.0).abs() < 1e-5 && (v - 8.0).abs() < 1e-5,
        "({u}, {v})"
    );
    // `.png` appended to a file_path without it (GaussianAvatars' readCamerasFromTransforms).
    assert!(a.image_path.ends_with("A/images/00000_00.png"));
    // RGBA composited on white; no masks: all ones.
    assert_eq!(&a.image[..3], &[1.0, 1.0, 1.0]);
    let right = ((w - 1) * 3) as usize;
    assert_eq!(&a.image[right..right + 3], &[1.0, 0.0, 0.0]);
    assert!(a.mask.iter().all(|&m| m == 1.0));
    // One identity for the subject: sequence A's shape and zero-padded offsets pose B too.
    let id = ds.identity();
    assert_eq!(id.shape, vec![0.1]);
    let mut padded = vec![[0.01, 0.0, 0.0]; 4];
    padded.extend([[0.0; 3]; 2]);
    assert_eq!(id.static_offset.as_deref(), Some(padded.as_slice()));
    let posed_b = HeadPose {
        expr: seq_pose(1).expr,
        shape: vec![0.1],
        static_offset: Some(padded.clone()),
        ..seq_pose(1)
    };
    assert_eq!(b.vertices, lbs(&model, &posed_b).expect("lbs"));
    // The test split takes the training split's identity, and camera_angle_x alone gives a
    // centred pinhole with fx = fy.
    let t = HeadDataset::open(&union, Split::Test, model.clone()).expect("test split");
    assert_eq!(t.identity().shape, vec![0.1]);
    let c = t.load_item(0).expect("test item").camera;
    assert!((c.fx - 30.0).abs() < 1e-3 && c.fy == c.fx, "{c:?}");
    assert_eq!((c.cx, c.cy), (8.0, 6.0));
    // canonical_flame_param.npz, when present, is the subject (VHAP's combine step copies it).
    let canonical = HeadPose {
        shape: vec![0.5],
        ..HeadPose::default()
    };
    canonical
        .save_npz(&union.join("canonical_flame_param.npz"))
        .expect("canonical");
    let ds = HeadDataset::open(&union, Split::Train, model.clone()).expect("open");
    assert_eq!(ds.identity().shape, vec![0.5]);
    assert_eq!(ds.identity().static_offset, None);

    // Offsets for VHAP's 120 teeth vertices more than the model: the error names the command.
    let mut teeth = seq_pose(0);
    teeth.static_offset = Some(vec![[0.0; 3]; V + 120]);
    teeth
        .save_npz(&union.join("canonical_flame_param.npz"))
        .expect("teeth");
    assert_names(
        HeadDataset::open(&union, Split::Train, model.clone()).expect_err("teeth offsets"),
        &[
            "canonical_flame_param.npz",
            "`static_offset`",
            "head add-teeth",
        ],
    );
    std::fs::remove_file(union.join("canonical_flame_param.npz")).expect("rm");

    // A motion of T frames in one file, as GaussianAvatars' flame_param.npz holds it:
    // (T, ·) per-frame arrays, shape and static_offset once, dynamic_offset ignored.
    let tt = 3;
    let motion_file = root.join("flame_param.npz");
    let rows = |n: usize, f: &dyn Fn(usize, usize) -> f32| -> Vec<f32> {
        (0..tt * n).map(|i| f(i / n, i % n)).collect()
    };
    NpzOut::default()
        .floats(
            "translation",
            &[tt, 3],
            rows(3, &|t, k| (k == 2) as u8 as f32 * t as f32),
        )
        .floats("rotation", &[tt, 3], rows(3, &|_, _| 0.0))
        .floats("neck_pose", &[tt, 3], rows(3, &|_, _| 0.0))
        .floats(
            "jaw_pose",
            &[tt, 3],
            rows(3, &|t, k| (k == 0) as u8 as f32 * 0.1 * t as f32),
        )
        .floats("eyes_pose", &[tt, 6], rows(6, &|_, _| 0.0))
        .floats("expr", &[tt, 5], rows(5, &|t, k| 0.1 * (t + k) as f32))
        .floats("shape", &[1], vec![-0.7])
        .floats("static_offset", &[1, V, 3], vec![0.3; V * 3])
        .floats("dynamic_offset", &[tt, V, 3], vec![9.0; tt * V * 3])
        .write(&motion_file)
        .expect("motion");
    let identity = texavatars::data::Identity {
        shape: vec![0.1],
        ..Default::default()
    };
    let motion = texavatars::drive::Motion::load(
        &motion_file,
        &model,
        &texavatars::head::HeadMeta::default(),
        &identity,
    )
    .expect("motion");
    assert_eq!(motion.frames.len(), tt);
    for (t, f) in motion.frames.iter().enumerate() {
        let pose = HeadPose {
            shape: vec![0.1],
            expr: (0..E).map(|k| 0.1 * (t + k) as f32).collect(),
            jaw: [0.1 * t as f32, 0.0, 0.0],
            translation: [0.0, 0.0, t as f32],
            ..Default::default()
        };
        assert_eq!(
            f.conditioning.vertices,
            lbs(&model, &pose).expect("lbs"),
            "frame {t}"
        );
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// `HeadDataset::check_files` reads every frame's headers and every timestep's parameters,
/// and lists all problems at once (issue 15.5).
#[test]
fn check_files_lists_every_broken_frame_before_training() {
    let fx = Fixture::new("check-files");
    let ds = fx.open().expect("open");
    let checked = ds.check_files().expect("a good export passes");
    assert_eq!((checked.frames, checked.timesteps), (4, 2));

    // Frame 1's image missing, frame 2's image of the wrong size, frame 0's mask cut short
    // inside its header, timestep 1's parameters not an npz.
    std::fs::remove_file(fx.path("images/00000_01.png")).expect("rm");
    image::RgbImage::new(W + 1, H)
        .save(fx.path("images/00001_00.png"))
        .expect("png");
    std::fs::write(fx.path("fg_masks/00000_00.png"), b"\x89PNG\r\n").expect("mask");
    std::fs::write(fx.path("flame_param/00001.npz"), b"not a zip").expect("npz");
    let ds = fx
        .open()
        .expect("open reads no frame files but the identity's");
    let e = ds.check_files().expect_err("four problems");
    assert_names(
        &e,
        &[
            "transforms_train.json",
            "4 problem(s)",
            "frames[1].file_path",
            "00000_01.png",
            "frames[2].file_path",
            &format!("{}x{H} pixels, the frame's w x h is {W}x{H}", W + 1),
            "frames[0].fg_mask_path",
            "frames[2].flame_param_path",
            "00001.npz",
        ],
    );
}

/// Files named by a transforms JSON stay inside the dataset root unless allowed; VHAP's
/// combined exports reach sibling exports through `..` (`vhap/combine_nerf_datasets.py`,
/// `NeRFDatasetAssembler.combine_dbs`), which stays allowed (issue 15.6).
#[test]
fn dataset_paths_stay_inside_the_root_unless_allowed() {
    let fx = Fixture::new("paths");
    let json = fx.path("transforms_train.json");
    let mut t: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("read")).expect("json");
    t["frames"][1]["file_path"] = json!("../../../../../../etc/passwd");
    t["frames"][3]["flame_param_path"] = json!("/etc/hostname");
    std::fs::write(&json, t.to_string()).expect("write");
    let e = fx.open().expect_err("outside the root");
    assert_names(
        &e,
        &[
            "2 problem(s)",
            "frames[1].file_path",
            "/etc/passwd",
            "frames[3].flame_param_path",
            "outside the dataset root",
            "--allow-outside-paths",
        ],
    );
    // Allowed, the files are read and fail as what they are.
    let ds = HeadDataset::open_with(
        &fx.root,
        Split::Train,
        fx.model.clone(),
        texavatars::data::PathPolicy::Anywhere,
    )
    .expect("allowed");
    let e = ds.check_files().expect_err("not a PNG, not an npz");
    assert_names(&e, &["frames[1].file_path", "frames[3].flame_param_path"]);
}
