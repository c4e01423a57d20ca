//! The viewer's messages: what the page asks for (JSON text messages on the WebSocket) and
//! what the server answers (a binary frame message, or a JSON error).
//!
//! A request names everything the frame depends on (camera, pose, expression, eta, the
//! motion frame), so the server keeps no per-client state beyond the latest request, and any
//! request can be dropped in favour of a newer one. Every number is checked against the
//! bounds in [`super::limits`] before it reaches the avatar.
//!
//! Reply (binary): a little-endian `u32` header length, the header as JSON ([`FrameHeader`]),
//! then the payload: the image (JPEG or PNG) or the PLY file, followed by the ground-truth
//! image when [`FrameHeader::gt_bytes`] is non-zero.

use serde::{Deserialize, Serialize};

use super::limits;

/// What a request asks to get back.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Output {
    /// The render as JPEG (the live stream).
    Frame,
    /// The render as PNG (saving the current frame).
    Png,
    /// The frame's world-space Gaussians as a 3DGS PLY (saving them).
    Ply,
}

/// The camera of a request.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum CameraRequest {
    /// An orbit around the head centre (world y up, the face looking along +z).
    Orbit(Orbit),
    /// The dataset camera with this index (a dataset motion), at its own size.
    Preset(usize),
}

/// An orbit camera.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Orbit {
    /// Azimuth around world y, degrees (0: in front of the face).
    pub yaw: f32,
    /// Elevation, degrees (positive: above).
    pub pitch: f32,
    /// Distance from the orbit's centre, model units (metres for FLAME).
    pub distance: f32,
    /// Shift of the orbit's centre in the image plane (right, up), model units.
    #[serde(default)]
    pub pan: [f32; 2],
    /// Vertical field of view, degrees.
    pub fov: f32,
    /// Image width and height, pixels.
    pub width: u32,
    pub height: u32,
}

/// One request from the page.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Request {
    /// What to send back.
    #[serde(rename = "type")]
    pub output: Output,
    /// The page's number for this request, echoed in the reply.
    pub id: u64,
    pub camera: CameraRequest,
    /// A motion frame to show (its expression, pose and eta), or `None` for the sliders'
    /// pose below.
    #[serde(default)]
    pub frame: Option<usize>,
    /// Expression coefficients by index (at most the head's count; missing ones are 0).
    #[serde(default)]
    pub expr: Vec<f32>,
    /// Axis-angle rotations, radians.
    #[serde(default)]
    pub jaw: [f32; 3],
    #[serde(default)]
    pub neck: [f32; 3],
    /// Left then right eye.
    #[serde(default)]
    pub eyes: [f32; 6],
    /// Use eta: the motion frame's (or, for the sliders, that of motion frame `eta_frame`);
    /// off: zeros.
    #[serde(default = "yes")]
    pub eta: bool,
    /// The motion frame whose eta the sliders' pose uses.
    #[serde(default)]
    pub eta_frame: Option<usize>,
    /// Also send the dataset's image of this frame and camera, and the PSNR against it (a
    /// dataset motion with a `frame` and a `preset` camera).
    #[serde(default)]
    pub ground_truth: bool,
}

fn yes() -> bool {
    true
}

/// Why a message was refused (sent back as an [`ErrorReply`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Refused {
    /// The request's id when it could be read.
    pub id: Option<u64>,
    pub why: String,
}

impl Request {
    /// Parses and checks a text message: JSON of the right shape, every number finite and
    /// within [`super::limits`], at most `num_expr` expression values.
    pub fn parse(text: &str, num_expr: usize) -> Result<Request, Refused> {
        if text.len() > limits::MESSAGE_BYTES {
            return Err(Refused {
                id: None,
                why: format!(
                    "message of {} bytes, at most {}",
                    text.len(),
                    limits::MESSAGE_BYTES
                ),
            });
        }
        let r: Request = serde_json::from_str(text).map_err(|e| Refused {
            id: serde_json::from_str::<serde_json::Value>(text)
                .ok()
                .and_then(|v| v.get("id").and_then(|i| i.as_u64())),
            why: format!("not a request: {e}"),
        })?;
        r.check(num_expr).map_err(|why| Refused {
            id: Some(r.id),
            why,
        })?;
        Ok(r)
    }

    fn check(&self, num_expr: usize) -> Result<(), String> {
        if self.expr.len() > num_expr {
            return Err(format!(
                "expr: {} values, the head has {num_expr} expressions",
                self.expr.len()
            ));
        }
        finite_within("expr", &self.expr, limits::EXPRESSION)?;
        let angle = std::f32::consts::PI;
        finite_within("jaw", &self.jaw, angle)?;
        finite_within("neck", &self.neck, angle)?;
        finite_within("eyes", &self.eyes, angle)?;
        if let CameraRequest::Orbit(o) = &self.camera {
            finite_within("camera.orbit.yaw", &[o.yaw], 3600.0)?;
            finite_within("camera.orbit.pitch", &[o.pitch], 89.0)?;
            finite_within("camera.orbit.pan", &o.pan, limits::DISTANCE.1)?;
            let (lo, hi) = limits::DISTANCE;
            if !(o.distance.is_finite() && o.distance >= lo && o.distance <= hi) {
                return Err(format!(
                    "camera.orbit.distance: {} is outside [{lo}, {hi}]",
                    o.distance
                ));
            }
            let (lo, hi) = limits::FOV_DEGREES;
            if !(o.fov.is_finite() && o.fov >= lo && o.fov <= hi) {
                return Err(format!(
                    "camera.orbit.fov: {} degrees is outside [{lo}, {hi}]",
                    o.fov
                ));
            }
            for (name, v) in [("width", o.width), ("height", o.height)] {
                if !(limits::MIN_SIDE..=limits::MAX_SIDE).contains(&v) {
                    return Err(format!(
                        "camera.orbit.{name}: {v} pixels is outside [{}, {}]",
                        limits::MIN_SIDE,
                        limits::MAX_SIDE
                    ));
                }
            }
        }
        Ok(())
    }
}

fn finite_within(field: &str, v: &[f32], bound: f32) -> Result<(), String> {
    match v.iter().position(|x| !(x.is_finite() && x.abs() <= bound)) {
        Some(i) => Err(format!(
            "{field}[{i}]: {} is not a finite number within ±{bound}",
            v[i]
        )),
        None => Ok(()),
    }
}

/// Milliseconds spent per stage of one reply.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    /// The model's stages in order (TexAvatars: decoders, lifting; GaussianAvatars:
    /// binding), then the rasterizer.
    pub stages: Vec<(String, f64)>,
    /// Encoding the image (or the PLY).
    pub encode: f64,
    /// From taking the request to the reply being ready (posing the head included).
    pub total: f64,
}

/// The JSON header of a binary reply.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameHeader {
    /// Always "frame", "png" or "ply" (the request's output).
    #[serde(rename = "type")]
    pub output: Output,
    pub id: u64,
    /// "image/jpeg", "image/png" or "application/octet-stream" (PLY).
    pub mime: String,
    /// Image size (the render's; for a PLY, the camera's).
    pub width: u32,
    pub height: u32,
    /// Bytes of the payload's first part (image or PLY).
    pub bytes: usize,
    /// Bytes of the ground-truth PNG after it (0: none).
    pub gt_bytes: usize,
    /// PSNR of the render against the ground truth, dB (`None`: no ground truth, or
    /// identical images).
    pub psnr: Option<f64>,
    /// The motion frame shown (`None`: the sliders' pose).
    pub frame: Option<usize>,
    pub gaussians: usize,
    pub timings_ms: Timings,
    /// Requests of this client replaced by newer ones before they were rendered, so far.
    pub dropped: u64,
}

/// A refused message.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ErrorReply {
    /// Always "error".
    #[serde(rename = "type")]
    pub kind: String,
    pub id: Option<u64>,
    pub error: String,
}

impl ErrorReply {
    pub fn new(id: Option<u64>, error: impl Into<String>) -> Self {
        ErrorReply {
            kind: "error".into(),
            id,
            error: error.into(),
        }
    }
}

/// Packs a binary reply: header length, header JSON, payload parts.
pub fn pack(header: &FrameHeader, parts: &[&[u8]]) -> Vec<u8> {
    let json = serde_json::to_vec(header).unwrap_or_default();
    let len = u32::try_from(json.len()).unwrap_or(u32::MAX);
    let mut out = Vec::with_capacity(4 + json.len() + parts.iter().map(|p| p.len()).sum::<usize>());
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(&json);
    for p in parts {
        out.extend_from_slice(p);
    }
    out
}

/// Splits a binary reply into its header and payload (the inverse of [`pack`]; for clients
/// and tests).
pub fn unpack(bytes: &[u8]) -> Result<(FrameHeader, &[u8]), String> {
    let len = bytes
        .get(..4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
        .ok_or("shorter than its 4-byte header length")?;
    let json = bytes
        .get(4..4 + len)
        .ok_or("shorter than its header length says")?;
    let header: FrameHeader = serde_json::from_slice(json).map_err(|e| format!("header: {e}"))?;
    Ok((header, &bytes[4 + len..]))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn orbit() -> serde_json::Value {
        serde_json::json!({"orbit": {"yaw": 10, "pitch": 4, "distance": 1, "fov": 20,
                                     "width": 64, "height": 96}})
    }

    #[test]
    fn a_request_parses_with_defaults() {
        let text = serde_json::json!({"type": "frame", "id": 3, "camera": orbit(),
                                      "expr": [0.5]})
        .to_string();
        let r = Request::parse(&text, 52).expect("valid");
        assert_eq!(r.id, 3);
        assert_eq!(r.output, Output::Frame);
        assert!(r.eta, "eta defaults to on");
        assert_eq!(r.frame, None);
        assert_eq!(r.jaw, [0.0; 3]);
        let preset =
            serde_json::json!({"type": "png", "id": 4, "camera": {"preset": 8}}).to_string();
        let r = Request::parse(&preset, 52).expect("valid");
        assert_eq!(r.camera, CameraRequest::Preset(8));
    }

    #[test]
    fn bad_requests_are_refused_with_the_field_and_the_id() {
        let cases = [
            (
                serde_json::json!({"type": "frame", "id": 1, "camera": orbit(),
                                "expr": [0.0, 1e9]}),
                "expr[1]",
            ),
            (
                serde_json::json!({"type": "frame", "id": 2, "camera": orbit(),
                                "expr": vec![0.0; 53]}),
                "53 values",
            ),
            (
                serde_json::json!({"type": "frame", "id": 3, "camera": {"orbit":
                {"yaw": 0, "pitch": 0, "distance": 1, "fov": 20, "width": 100000,
                 "height": 10}}}),
                "camera.orbit.width",
            ),
            (
                serde_json::json!({"type": "frame", "id": 4, "camera": orbit(),
                                "jaw": [0, 7, 0]}),
                "jaw[1]",
            ),
            (
                serde_json::json!({"type": "frame", "id": 5, "camera": orbit(), "bogus": 1}),
                "unknown field",
            ),
            (
                serde_json::json!({"type": "movie", "id": 6, "camera": orbit()}),
                "unknown variant",
            ),
        ];
        for (json, want) in cases {
            let e = Request::parse(&json.to_string(), 52).expect_err("refused");
            assert!(e.why.contains(want), "{want}: {}", e.why);
            assert_eq!(e.id, json["id"].as_u64(), "{}", e.why);
        }
        let e = Request::parse("{not json", 52).expect_err("refused");
        assert_eq!(e.id, None);
        let long = "x".repeat(limits::MESSAGE_BYTES + 1);
        assert!(
            Request::parse(&long, 52)
                .expect_err("too long")
                .why
                .contains("bytes")
        );
    }

    #[test]
    fn pack_and_unpack_are_inverse() {
        let h = FrameHeader {
            output: Output::Frame,
            id: 9,
            mime: "image/jpeg".into(),
            width: 2,
            height: 3,
            bytes: 3,
            gt_bytes: 2,
            psnr: Some(30.5),
            frame: None,
            gaussians: 7,
            timings_ms: Timings::default(),
            dropped: 1,
        };
        let bytes = pack(&h, &[b"abc", b"de"]);
        let (back, payload) = unpack(&bytes).expect("valid");
        assert_eq!(back, h);
        assert_eq!(payload, b"abcde");
        assert!(unpack(&bytes[..3]).is_err());
        assert!(unpack(&bytes[..10]).is_err());
    }
}
