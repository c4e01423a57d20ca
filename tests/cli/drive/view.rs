//! `texavatars view` end to end: the server on an ephemeral port with the tiny trained
//! avatar, spoken to as the page does (HTTP for the page and the info, the WebSocket
//! protocol of `texavatars::view::protocol`), and the page itself in headless Chromium when
//! it is installed.

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use texavatars::device::BackendKind;
use texavatars::view::protocol::{FrameHeader, unpack};
use texavatars::view::{SceneOptions, ViewOptions, Viewer};
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

type Socket = WebSocket<MaybeTlsStream<TcpStream>>;

fn start(motion: Option<PathBuf>) -> Viewer {
    let f = super::fixture();
    Viewer::start(ViewOptions {
        scene: SceneOptions {
            checkpoint: Some(f.run.clone()),
            net: "configs/tiny.json".into(),
            motion,
            head: None,
            identity: None,
            backend: BackendKind::Flex,
        },
        host: "127.0.0.1".parse().expect("address"),
        port: 0,
        stop_on_ctrl_c: false,
    })
    .expect("viewer starts")
}

fn get(url: &str) -> (u16, String, String) {
    let r = ureq::get(url).call().expect("GET");
    let mime = r.header("content-type").unwrap_or("").to_string();
    (r.status(), mime, r.into_string().expect("text body"))
}

fn connect(v: &Viewer) -> Socket {
    let (s, _) = tungstenite::connect(format!("ws://{}/ws", v.addr())).expect("websocket");
    if let MaybeTlsStream::Plain(t) = s.get_ref() {
        t.set_read_timeout(Some(Duration::from_secs(120)))
            .expect("timeout");
    }
    s
}

fn orbit(width: u32, height: u32) -> Value {
    json!({"orbit": {"yaw": 0, "pitch": 4, "distance": 1, "fov": 20,
                     "width": width, "height": height}})
}

/// Reads messages until a reply (frame or error) arrives.
enum Reply {
    Frame(FrameHeader, Vec<u8>),
    Error(Value),
}

fn recv(s: &mut Socket) -> Reply {
    loop {
        match s.read().expect("a reply") {
            Message::Binary(b) => {
                let (h, payload) = unpack(&b).expect("a framed reply");
                return Reply::Frame(h, payload.to_vec());
            }
            Message::Text(t) => {
                return Reply::Error(serde_json::from_str(t.as_str()).expect("error JSON"));
            }
            _ => continue,
        }
    }
}

fn frame(s: &mut Socket, request: Value) -> (FrameHeader, Vec<u8>) {
    s.send(Message::text(request.to_string())).expect("send");
    match recv(s) {
        Reply::Frame(h, p) => (h, p),
        Reply::Error(e) => panic!("refused: {e}"),
    }
}

fn decode(bytes: &[u8]) -> image::RgbImage {
    image::load_from_memory(bytes).expect("an image").to_rgb8()
}

fn mean_abs_diff(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions());
    let s: u64 = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| u64::from(x.abs_diff(*y)))
        .sum();
    s as f64 / a.as_raw().len() as f64
}

#[test]
fn the_viewer_serves_the_page_and_frames_to_two_clients() {
    let f = super::fixture();
    let test_split = f.data.join("union/transforms_test.json");
    let v = start(Some(test_split));
    let base = v.url();

    // The page and its files, embedded in the binary.
    let (status, mime, html) = get(&base);
    assert_eq!(status, 200);
    assert!(mime.starts_with("text/html"), "{mime}");
    assert!(
        html.contains("/viewer.js") && html.contains("exprsliders"),
        "{html}"
    );
    let (status, mime, js) = get(&format!("{base}viewer.js"));
    assert_eq!((status, mime.starts_with("text/javascript")), (200, true));
    assert!(js.contains("new WebSocket"));
    let (_, _, info) = get(&format!("{base}api/info"));
    let info: Value = serde_json::from_str(&info).expect("info JSON");
    let names: Vec<&str> = info["expressions"]
        .as_array()
        .expect("names")
        .iter()
        .map(|n| n.as_str().expect("name"))
        .collect();
    let jaw_open = names.iter().position(|n| *n == "jawOpen").expect("jawOpen");
    assert_eq!(info["model"], "TexAvatars");
    assert_eq!(info["motion"]["kind"], "dataset");
    let cameras = info["motion"]["cameras"]
        .as_array()
        .expect("cameras")
        .clone();
    assert!(!cameras.is_empty());
    assert!(matches!(
        ureq::get(&format!("{base}nothing-here")).call(),
        Err(ureq::Error::Status(404, _))
    ));

    // A frame of the requested size.
    let mut a = connect(&v);
    let (h, jpeg) = frame(
        &mut a,
        json!({"type": "frame", "id": 1, "camera": orbit(64, 96)}),
    );
    assert_eq!(
        (h.id, h.width, h.height, h.mime.as_str()),
        (1, 64, 96, "image/jpeg")
    );
    let neutral = decode(&jpeg[..h.bytes]);
    assert_eq!(neutral.dimensions(), (64, 96));
    let stages: Vec<&str> = h.timings_ms.stages.iter().map(|s| s.0.as_str()).collect();
    assert_eq!(stages, ["decoders", "lifting", "rasterizer"]);
    assert!(h.gaussians > 0);

    // Moving jawOpen changes the frame.
    let mut expr = vec![0.0f32; names.len()];
    expr[jaw_open] = 1.0;
    let (h, jpeg) = frame(
        &mut a,
        json!({"type": "frame", "id": 2, "camera": orbit(64, 96), "expr": expr}),
    );
    let open = decode(&jpeg[..h.bytes]);
    let d = mean_abs_diff(&neutral, &open);
    assert!(
        d > 0.05,
        "jawOpen 1 changed the frame by {d} levels on average"
    );

    // A malformed message is refused with a reason, and the next one works.
    a.send(Message::text("{\"type\": \"frame\", \"id\": 3"))
        .expect("send");
    match recv(&mut a) {
        Reply::Error(e) => assert!(e["error"].as_str().expect("why").contains("not a request")),
        Reply::Frame(..) => panic!("a malformed message was answered with a frame"),
    }
    a.send(Message::text(
        json!({"type": "frame", "id": 4, "camera": orbit(100000, 96)}).to_string(),
    ))
    .expect("send");
    match recv(&mut a) {
        Reply::Error(e) => {
            assert_eq!(e["id"], 4);
            assert!(
                e["error"]
                    .as_str()
                    .expect("why")
                    .contains("camera.orbit.width"),
                "{e}"
            );
        }
        Reply::Frame(..) => panic!("an oversized frame was rendered"),
    }
    a.send(Message::binary(vec![1u8, 2, 3])).expect("send");
    assert!(matches!(recv(&mut a), Reply::Error(_)));
    let (h, _) = frame(
        &mut a,
        json!({"type": "frame", "id": 5, "camera": orbit(32, 48)}),
    );
    assert_eq!((h.id, h.width), (5, 32));

    // Two clients at once, each gets its own frames.
    let mut b = connect(&v);
    a.send(Message::text(
        json!({"type": "frame", "id": 10, "camera": orbit(40, 60)}).to_string(),
    ))
    .expect("send");
    b.send(Message::text(
        json!({"type": "frame", "id": 20, "camera": orbit(48, 72)}).to_string(),
    ))
    .expect("send");
    let Reply::Frame(ha, _) = recv(&mut a) else {
        panic!("a: no frame")
    };
    let Reply::Frame(hb, _) = recv(&mut b) else {
        panic!("b: no frame")
    };
    assert_eq!((ha.id, ha.width, hb.id, hb.width), (10, 40, 20, 48));

    // Latest wins: a burst is answered with increasing ids ending at the last one, and
    // every request is either answered or counted as dropped.
    for id in 30..36 {
        b.send(Message::text(
            json!({"type": "frame", "id": id, "camera": orbit(48, 72)}).to_string(),
        ))
        .expect("send");
    }
    let mut ids = Vec::new();
    let last = loop {
        let Reply::Frame(h, _) = recv(&mut b) else {
            panic!("refused")
        };
        ids.push(h.id);
        if h.id == 35 {
            break h;
        }
    };
    assert!(ids.windows(2).all(|w| w[0] < w[1]), "{ids:?}");
    assert_eq!(
        ids.len() as u64 + last.dropped,
        6,
        "{ids:?}, dropped {}",
        last.dropped
    );

    // A dataset frame from a dataset camera, with its image and the PSNR.
    let cam = cameras[0].as_u64().expect("index");
    let (h, payload) = frame(
        &mut a,
        json!({"type": "frame", "id": 40, "camera": {"preset": cam}, "frame": 0,
               "ground_truth": true}),
    );
    assert!(h.gt_bytes > 0, "{h:?}");
    let gt = decode(&payload[h.bytes..]);
    assert_eq!(gt.dimensions(), (h.width, h.height));
    // The dataset's own image of motion frame 0 (the split's first timestep) and camera.
    let ds = texavatars::data::HeadDataset::from_transforms(
        &f.data.join("union/transforms_test.json"),
        std::sync::Arc::new(texavatars::head::HeadAsset::embedded().expect("head").model),
    )
    .expect("split");
    let first = ds
        .frames()
        .iter()
        .map(|f| f.timestep)
        .min()
        .expect("frames");
    let i = ds
        .frames()
        .iter()
        .position(|f| f.timestep == first && f.camera_index as u64 == cam)
        .expect("the frame");
    let want = texavatars::io::image::to_bytes8(&ds.load_item(i).expect("image").image);
    assert_eq!(
        gt.as_raw(),
        &want,
        "the ground truth is the dataset's image"
    );
    // The PSNR is the render's against it (checked on the lossless PNG of the same request).
    let (hp, png) = frame(
        &mut a,
        json!({"type": "png", "id": 42, "camera": {"preset": cam}, "frame": 0,
               "ground_truth": true}),
    );
    let render = decode(&png[..hp.bytes]);
    let mse = render
        .as_raw()
        .iter()
        .zip(gt.as_raw())
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2) / 255f64.powi(2))
        .sum::<f64>()
        / want.len() as f64;
    let psnr = hp.psnr.expect("a PSNR");
    assert!((psnr - -10.0 * mse.log10()).abs() < 0.05, "{psnr} vs {mse}");
    assert_eq!(
        h.psnr, hp.psnr,
        "the same frame scores the same in JPEG and PNG"
    );
    let Reply::Error(e) = ({
        a.send(Message::text(
            json!({"type": "frame", "id": 41, "camera": {"preset": 999}, "frame": 0}).to_string(),
        ))
        .expect("send");
        recv(&mut a)
    }) else {
        panic!("an unknown camera was rendered")
    };
    assert!(
        e["error"].as_str().expect("why").contains("camera.preset"),
        "{e}"
    );

    // Saving: the frame as PNG, the Gaussians as a PLY a 3DGS reader opens.
    let (h, png) = frame(
        &mut a,
        json!({"type": "png", "id": 50, "camera": orbit(32, 48)}),
    );
    assert_eq!(h.mime, "image/png");
    assert_eq!(decode(&png).dimensions(), (32, 48));
    let (h, ply) = frame(
        &mut a,
        json!({"type": "ply", "id": 51, "camera": orbit(32, 48)}),
    );
    let g = texavatars::splat::ply::parse(&ply, "view.ply").expect("a PLY");
    assert_eq!(g.len(), h.gaussians);

    drop((a, b));
    v.stop().expect("stops");
}

/// The Chromium binary, when one is installed (`CHROMIUM` names another).
fn chromium() -> Option<PathBuf> {
    let candidates = std::env::var_os("CHROMIUM")
        .map(PathBuf::from)
        .into_iter()
        .chain(["chromium", "chromium-browser", "google-chrome"].map(PathBuf::from));
    candidates.into_iter().find(|c| {
        Command::new(c)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

/// A headless Chromium driven over the DevTools protocol.
struct Browser {
    child: Child,
    socket: Socket,
    session: String,
    next: u64,
    _profile: PathBuf,
}

impl Browser {
    /// Starts Chromium and opens `url` in a new tab. `Err` when the browser itself does
    /// not come up (no DevTools address within a minute): an environment problem, not the
    /// viewer's, reported by the caller.
    fn launch(exe: &PathBuf, url: &str) -> Result<Browser, String> {
        let profile = super::tmp("chromium-profile");
        let mut child = Command::new(exe)
            .args([
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                // Containers often have a small /dev/shm; Chromium then crashes without this.
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--window-size=900,700",
                "--remote-debugging-port=0",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg("about:blank")
            .stderr(Stdio::piped())
            .stdout(Stdio::null())
            .spawn()
            .map_err(|e| format!("{}: {e}", exe.display()))?;
        let stderr = child.stderr.take().expect("stderr");
        // Read stderr on a thread (kept draining it so the browser never blocks on it) and
        // hand over the DevTools address.
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let mut seen = Vec::new();
        let deadline = Instant::now() + Duration::from_secs(60);
        let ws = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left) {
                Ok(line) => match line.find("ws://") {
                    Some(at) => break line[at..].trim().to_string(),
                    None => seen.push(line),
                },
                Err(_) => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return Err(format!(
                        "no DevTools address within a minute; stderr: {}",
                        seen.join(" | ")
                    ));
                }
            }
        };
        let (socket, _) = tungstenite::connect(ws).map_err(|e| format!("DevTools socket: {e}"))?;
        let mut b = Browser {
            child,
            socket,
            session: String::new(),
            next: 1,
            _profile: profile,
        };
        let target = b.call("Target.createTarget", json!({"url": url}), false);
        let id = target["targetId"].as_str().expect("target").to_string();
        let attached = b.call(
            "Target.attachToTarget",
            json!({"targetId": id, "flatten": true}),
            false,
        );
        b.session = attached["sessionId"].as_str().expect("session").to_string();
        Ok(b)
    }

    fn call(&mut self, method: &str, params: Value, in_page: bool) -> Value {
        let id = self.next;
        self.next += 1;
        let mut m = json!({"id": id, "method": method, "params": params});
        if in_page {
            m["sessionId"] = json!(self.session);
        }
        self.socket
            .send(Message::text(m.to_string()))
            .expect("send");
        loop {
            if let Message::Text(t) = self.socket.read().expect("DevTools reply") {
                let v: Value = serde_json::from_str(t.as_str()).expect("JSON");
                if v["id"] == json!(id) {
                    assert!(v.get("error").is_none(), "{method}: {v}");
                    return v["result"].clone();
                }
            }
        }
    }

    fn eval(&mut self, expression: &str) -> Value {
        let r = self.call(
            "Runtime.evaluate",
            json!({"expression": expression, "returnByValue": true}),
            true,
        );
        r["result"]["value"].clone()
    }

    /// Polls `expression` until it is true (a minute at most).
    fn until(&mut self, expression: &str) {
        let start = Instant::now();
        while self.eval(expression) != json!(true) {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "waited for {expression}"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    fn screenshot(&mut self) -> image::RgbImage {
        use base64::Engine;
        let r = self.call("Page.captureScreenshot", json!({"format": "png"}), true);
        let png = base64::engine::general_purpose::STANDARD
            .decode(r["data"].as_str().expect("data"))
            .expect("base64");
        image::load_from_memory(&png).expect("png").to_rgb8()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn in_headless_chromium_a_slider_changes_the_face() {
    let Some(exe) = chromium() else {
        eprintln!("skipped: no chromium on the PATH (apt-get install chromium, or set CHROMIUM)");
        return;
    };
    let v = start(None);
    let mut b = match Browser::launch(&exe, &v.url()) {
        Ok(b) => b,
        Err(why) => {
            eprintln!("skipped: {} did not start: {why}", exe.display());
            return;
        }
    };
    b.until("!!(window.viewer && window.viewer.ready && window.viewer.framesShown >= 1)");
    // The render's box on the page, in CSS pixels (the screenshot's scale is 1).
    let rect = b.eval(
        "(() => { const r = document.getElementById('render').getBoundingClientRect(); \
         return [r.left, r.top, r.width, r.height]; })()",
    );
    let rect: Vec<f64> = serde_json::from_value(rect).expect("rect");
    assert!(rect[2] > 50.0 && rect[3] > 50.0, "render box {rect:?}");
    let before = b.screenshot();
    let shown = b.eval("window.viewer.framesShown");
    b.eval(
        "(() => { const i = document.querySelector('input[data-name=\"jawOpen\"]'); \
         i.value = '1'; i.dispatchEvent(new Event('input')); return true; })()",
    );
    b.until(&format!(
        "window.viewer.framesShown > {shown} && window.viewer.lastHeader.id > 1"
    ));
    let after = b.screenshot();
    assert_eq!(before.dimensions(), after.dimensions());
    // The face is the middle of the render: compare that region, and the same-sized header
    // strip far from it for contrast (it only holds text).
    let region = |img: &image::RgbImage, x0: f64, y0: f64, w: f64, h: f64| -> image::RgbImage {
        image::imageops::crop_imm(img, x0 as u32, y0 as u32, w as u32, h as u32).to_image()
    };
    let (x, y, w, h) = (rect[0], rect[1], rect[2], rect[3]);
    let face = |img| region(img, x + 0.25 * w, y + 0.25 * h, 0.5 * w, 0.6 * h);
    let d = mean_abs_diff(&face(&before), &face(&after));
    assert!(d > 0.05, "the face region changed by {d} levels on average");
    assert!(b.eval("window.viewer.errors.length") == json!(0));
    drop(b);
    v.stop().expect("stops");
}
