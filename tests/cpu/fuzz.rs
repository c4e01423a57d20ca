//! No panics on input: property-based fuzzing of every parser of hostile files.
//!
//! Crate: `proptest` (dev-dependency, `default-features = false, features = ["std"]`: no
//! fork or timeout machinery). It generates inputs from strategies, runs a fixed number of
//! cases per property and, on a failure, shrinks the input to a small one and prints it;
//! `failure_persistence: None` keeps it from writing regression files into the tree (each
//! crash it found is pinned below as a plain `#[test]` instead). Seeds are random per run
//! (set `PROPTEST_RNG_SEED` to replay one), so every run of the suite explores new inputs.
//!
//! Per format: (1) arbitrary bytes, (2) structured inputs built from hostile pieces (declared
//! counts and shapes such as 2^63, negative numbers, NaN, wrong JSON types, unknown dtypes),
//! (3) mutations of a valid file (bit flips, overwrites with hostile numbers, insertions,
//! deletions, truncation), and (4) inputs known to be bad (a strict prefix of a valid file)
//! that must be an `Err`. The property: the call returns, `Ok` or `Err`, without panicking
//! ([`no_panic`] turns a panic into a test failure that shows the input), and an `Ok` is
//! consistent (array lengths match shapes, and so on).
//!
//! Case budget: [`CASES`] = 1024 per property, 25 properties (JSON: each case picks one of
//! the five loaders), 25,600 cases in all, few enough for every debug test run (a longer
//! session with 40,000 per property found nothing more). Raise `CASES` locally for a longer
//! fuzzing session.
//!
//! Regression tests for the crashes found are at the end of the file (`regression_*`).

use std::fmt::Write as _;
use std::io::{Cursor, Write as _};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

use proptest::collection::vec;
use proptest::prelude::*;
use proptest::sample::{Index, select};
use proptest::test_runner::TestCaseError;
use serde_json::{Value as Json, json};
use texavatars::camera::CameraFile;
use texavatars::data::vhap::{FrameRecord, load_transforms, save_transforms};
use texavatars::io::npz::{Npz, NpzOut};
use texavatars::io::{npy, pickle};
use texavatars::mesh::UvMesh;
use texavatars::splat::ply;
use texavatars::synth::SynthConfig;
use texavatars::train::TrainConfig;

/// Cases per property.
const CASES: u32 = 1024;

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: CASES,
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

// ---------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------

/// Runs `f`, turning a panic into a test failure that names the parser and shows `input`.
fn no_panic<T>(parser: &str, input: &[u8], f: impl FnOnce() -> T) -> Result<T, TestCaseError> {
    catch_unwind(AssertUnwindSafe(f)).map_err(|p| {
        let msg = p
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default();
        TestCaseError::fail(format!(
            "{parser} panicked ({msg}) on {} bytes: {}",
            input.len(),
            show(input)
        ))
    })
}

/// The input as an escaped byte string, cut after 4000 characters.
fn show(bytes: &[u8]) -> String {
    let mut s = String::from("b\"");
    for c in bytes.escape_ascii() {
        if s.len() > 4000 {
            s.push_str("...");
            break;
        }
        s.push(c as char);
    }
    s.push('"');
    s
}

/// A fresh folder under the system's temp folder, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        static N: AtomicU64 = AtomicU64::new(0);
        let n = N.fetch_add(1, Ordering::Relaxed);
        let p =
            std::env::temp_dir().join(format!("texavatars-fuzz-{}-{tag}-{n}", std::process::id()));
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }

    /// Writes `bytes` to `name` in the folder and returns its path.
    fn file(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let p = self.0.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Hostile numbers as text: huge, negative, not a number, and a few ordinary ones.
const HOSTILE_NUMBERS: &[&str] = &[
    "0",
    "1",
    "2",
    "3",
    "-1",
    "-0",
    "255",
    "65536",
    "4294967295",
    "4294967296",
    "1000000000000",
    "9223372036854775807",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "99999999999999999999999999",
    "-9223372036854775808",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e39",
    "1e308",
    "1e999",
    "0.5",
    "1.5e-45",
    "",
];

/// One edit of a byte string; positions are fractions of the current length.
#[derive(Clone, Debug)]
enum Mutation {
    Flip(Index, u8),
    Set(Index, u8),
    Insert(Index, Vec<u8>),
    Delete(Index, usize),
    Truncate(Index),
    /// Overwrites with a hostile number (text) at the position.
    Number(Index, &'static str),
    /// Overwrites with a hostile little-endian integer at the position.
    Word(Index, u64),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let words = select(vec![
        0u64,
        1,
        u64::MAX,
        i64::MAX as u64,
        1 << 63,
        1 << 32,
        u32::MAX as u64,
        0x7fff_ffff,
        0xffff,
        1_000_000_000_000,
        f32::NAN.to_bits() as u64,
        f32::INFINITY.to_bits() as u64,
    ]);
    prop_oneof![
        (any::<Index>(), 1u8..=255).prop_map(|(i, m)| Mutation::Flip(i, m)),
        (any::<Index>(), any::<u8>()).prop_map(|(i, b)| Mutation::Set(i, b)),
        (any::<Index>(), vec(any::<u8>(), 1..16)).prop_map(|(i, b)| Mutation::Insert(i, b)),
        (any::<Index>(), 1usize..64).prop_map(|(i, n)| Mutation::Delete(i, n)),
        any::<Index>().prop_map(Mutation::Truncate),
        (any::<Index>(), select(HOSTILE_NUMBERS)).prop_map(|(i, s)| Mutation::Number(i, s)),
        (any::<Index>(), words).prop_map(|(i, w)| Mutation::Word(i, w)),
    ]
}

fn mutations() -> impl Strategy<Value = Vec<Mutation>> {
    vec(mutation(), 1..6)
}

fn apply(bytes: &[u8], ms: &[Mutation]) -> Vec<u8> {
    let mut b = bytes.to_vec();
    let at = |i: &Index, len: usize| if len == 0 { 0 } else { i.index(len) };
    for m in ms {
        let len = b.len();
        match m {
            Mutation::Flip(i, mask) if len > 0 => b[at(i, len)] ^= mask,
            Mutation::Set(i, v) if len > 0 => b[at(i, len)] = *v,
            Mutation::Insert(i, v) => {
                let p = at(i, len + 1);
                b.splice(p..p, v.iter().copied());
            }
            Mutation::Delete(i, n) if len > 0 => {
                let p = at(i, len);
                b.drain(p..(p + n).min(len));
            }
            Mutation::Truncate(i) => b.truncate(at(i, len)),
            Mutation::Number(i, s) => {
                let p = at(i, len + 1);
                let end = (p + s.len()).min(len);
                b.splice(p..end, s.bytes());
            }
            Mutation::Word(i, w) => {
                let p = at(i, len + 1);
                let end = (p + 8).min(len);
                b.splice(p..end, w.to_le_bytes());
            }
            _ => {}
        }
    }
    b
}

/// A strict prefix of `bytes` (at least one byte shorter).
fn prefix<'a>(bytes: &'a [u8], i: &Index) -> &'a [u8] {
    &bytes[..i.index(bytes.len())]
}

// ---------------------------------------------------------------------------------------
// PLY
// ---------------------------------------------------------------------------------------

const PLY_NAMES: &[&str] = &[
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
    "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
];

fn sample_gaussians(n: usize, degree: usize) -> ply::PlyGaussians {
    let k = (degree + 1) * (degree + 1);
    ply::PlyGaussians {
        means: (0..3 * n).map(|i| i as f32 * 0.25).collect(),
        sh: (0..3 * k * n).map(|i| (i as f32 * 0.37).sin()).collect(),
        sh_degree: degree,
        opacity_logits: (0..n).map(|i| i as f32 - 1.0).collect(),
        log_scales: (0..3 * n).map(|i| -(i as f32) * 0.1).collect(),
        quats: (0..4 * n).map(|i| (i % 4) as f32).collect(),
    }
}

/// A valid binary PLY of 3 Gaussians of SH degree 1 (from the crate's writer).
fn valid_ply() -> &'static [u8] {
    static B: OnceLock<Vec<u8>> = OnceLock::new();
    B.get_or_init(|| {
        let d = TempDir::new("ply-valid");
        let p = d.0.join("g.ply");
        ply::write(&p, &sample_gaussians(3, 1)).unwrap();
        std::fs::read(&p).unwrap()
    })
}

/// The same as an ASCII PLY (by hand: the writer writes binary only).
fn valid_ascii_ply() -> Vec<u8> {
    let mut s = String::from("ply\nformat ascii 1.0\nelement vertex 2\n");
    for name in PLY_NAMES {
        let _ = writeln!(s, "property float {name}");
    }
    s.push_str("end_header\n");
    for r in 0..2 {
        let row: Vec<String> = (0..PLY_NAMES.len())
            .map(|j| format!("{}", (r * 17 + j) as f32 * 0.5))
            .collect();
        s.push_str(&row.join(" "));
        s.push('\n');
    }
    s.into_bytes()
}

fn ply_header_line() -> impl Strategy<Value = String> {
    let ty = select(vec![
        "float",
        "double",
        "uchar",
        "char",
        "short",
        "ushort",
        "int",
        "uint",
        "int8",
        "float32",
        "float64",
        "half",
        "",
        "list uchar int",
        "list int float",
    ]);
    let name = prop_oneof![
        select(PLY_NAMES).prop_map(str::to_string),
        (0usize..50).prop_map(|i| format!("f_rest_{i}")),
        Just("binding_0".to_string()),
        "[a-z_0-9]{0,8}",
    ];
    prop_oneof![
        4 => (ty, name).prop_map(|(t, n)| format!("property {t} {n}")),
        1 => select(HOSTILE_NUMBERS).prop_map(|n| format!("element vertex {n}")),
        1 => select(HOSTILE_NUMBERS).prop_map(|n| format!("element face {n}")),
        1 => select(vec![
            "format ascii 1.0",
            "format binary_little_endian 1.0",
            "format binary_big_endian 1.0",
            "format",
            "comment hello",
            "obj_info x",
            "ply",
            "end_header",
            "",
        ])
        .prop_map(str::to_string),
        1 => "[ -~]{0,20}",
    ]
}

/// A PLY from hostile header lines (after `ply`, a format and a vertex count) and a body of
/// random bytes or numbers.
fn structured_ply() -> impl Strategy<Value = Vec<u8>> {
    let format = select(vec!["ascii", "binary_little_endian"]);
    let count = select(HOSTILE_NUMBERS);
    let body = prop_oneof![
        vec(any::<u8>(), 0..512),
        vec(select(HOSTILE_NUMBERS), 0..64).prop_map(|v| v.join(" ").into_bytes()),
    ];
    (
        format,
        count,
        vec(ply_header_line(), 0..40),
        any::<bool>(),
        body,
    )
        .prop_map(|(format, count, lines, all_names, body)| {
            let mut s = format!("ply\nformat {format} 1.0\nelement vertex {count}\n");
            if all_names {
                for name in PLY_NAMES {
                    let _ = writeln!(s, "property float {name}");
                }
            }
            for l in lines {
                s.push_str(&l);
                s.push('\n');
            }
            s.push_str("end_header\n");
            let mut b = s.into_bytes();
            b.extend(body);
            b
        })
}

/// Parses a PLY, checking an `Ok` for consistency.
fn check_ply(bytes: &[u8]) -> Result<Option<ply::PlyGaussians>, TestCaseError> {
    let r = no_panic("ply::parse", bytes, || ply::parse(bytes, "fuzz.ply"))?;
    match r {
        Ok(g) => {
            let n = g.len();
            prop_assert!(g.sh_degree <= 3);
            prop_assert_eq!(g.means.len(), 3 * n);
            prop_assert_eq!(g.sh.len(), 3 * g.sh_coeffs() * n);
            prop_assert_eq!(g.log_scales.len(), 3 * n);
            prop_assert_eq!(g.quats.len(), 4 * n);
            no_panic("PlyGaussians::cov6", bytes, || g.cov6())?;
            Ok(Some(g))
        }
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz.ply"), "{e}");
            Ok(None)
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn ply_arbitrary_bytes(bytes in vec(any::<u8>(), 0..1024)) {
        check_ply(&bytes)?;
        let mut with_magic = b"ply\nformat binary_little_endian 1.0\n".to_vec();
        with_magic.extend(&bytes);
        with_magic.extend(b"\nend_header\n");
        check_ply(&with_magic)?;
    }

    #[test]
    fn ply_structured(bytes in structured_ply()) {
        check_ply(&bytes)?;
    }

    #[test]
    fn ply_mutated(ms in mutations(), ascii in any::<bool>()) {
        let valid = if ascii { valid_ascii_ply() } else { valid_ply().to_vec() };
        check_ply(&apply(&valid, &ms))?;
    }

    #[test]
    fn ply_truncated_is_an_error(i in any::<Index>()) {
        // Any strict prefix of a binary file misses the body's end (or the header).
        let valid = valid_ply();
        prop_assert!(check_ply(prefix(valid, &i))?.is_none());
    }
}

// ---------------------------------------------------------------------------------------
// npy
// ---------------------------------------------------------------------------------------

/// A valid `.npy` of shape [2, 3] (from the crate's writer).
fn valid_npy() -> &'static [u8] {
    static B: OnceLock<Vec<u8>> = OnceLock::new();
    B.get_or_init(|| {
        let d = TempDir::new("npy-valid");
        let p = d.0.join("a.npy");
        npy::write(&p, &[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
        std::fs::read(&p).unwrap()
    })
}

/// A `.npy` from a header dict text, a version and a header length field (`None`: the
/// right one), followed by `data`.
fn npy_bytes(version: (u8, u8), dict: &str, declared: Option<u32>, data: &[u8]) -> Vec<u8> {
    let mut b = b"\x93NUMPY".to_vec();
    b.extend([version.0, version.1]);
    let len = declared.unwrap_or(dict.len() as u32);
    if version.0 == 1 {
        b.extend((len as u16).to_le_bytes());
    } else {
        b.extend(len.to_le_bytes());
    }
    b.extend(dict.as_bytes());
    b.extend(data);
    b
}

const DIMS: &[&str] = &[
    "0",
    "1",
    "2",
    "3",
    "7",
    "-1",
    "4294967296",
    "1000000000000",
    "9223372036854775808",
    "18446744073709551615",
    "18446744073709551616",
    "0x10",
    "1_0",
    "1.5",
    "True",
    "None",
    "'2'",
    "(2,)",
];

const DESCRS: &[&str] = &[
    "'<f4'",
    "'<f8'",
    "'>f4'",
    "'|f4'",
    "'<i4'",
    "'<i8'",
    "'<u4'",
    "'<u8'",
    "'|u1'",
    "'<f2'",
    "'<c8'",
    "'|b1'",
    "'<V0'",
    "'|V4'",
    "'<U3'",
    "'|S0'",
    "'O'",
    "'<M8[s]'",
    "'f4'",
    "''",
    "[('a', '<f4')]",
    "[('a', '<f4', (3,))]",
    "[('a', '<f4', (4294967296, 4294967296))]",
    "[]",
    "None",
    "3",
];

/// A header dict from hostile pieces.
fn npy_dict() -> impl Strategy<Value = String> {
    let shape = prop_oneof![
        vec(select(DIMS), 0..5).prop_map(|d| format!("({},)", d.join(", "))),
        vec(select(DIMS), 0..5).prop_map(|d| format!("[{}]", d.join(", "))),
        Just("()".to_string()),
        Just("(".to_string()),
        Just("None".to_string()),
        (1usize..40).prop_map(|n| format!("{}1{}", "(".repeat(n), ",)".repeat(n))),
    ];
    let fortran = select(vec!["False", "True", "0", "'x'"]);
    let extra = select(vec![
        "",
        "'x': 1, ",
        "'shape': (1,), ",
        "'descr': '<i4', ",
        "'a': [[[[[[[[]]]]]]]], ",
    ]);
    (select(DESCRS), fortran, shape, extra, any::<bool>()).prop_map(
        |(descr, fortran, shape, extra, pad)| {
            let mut s = format!(
                "{{'descr': {descr}, 'fortran_order': {fortran}, 'shape': {shape}, {extra}}}"
            );
            if pad {
                while (s.len() + 11) % 64 != 0 {
                    s.push(' ');
                }
                s.push('\n');
            }
            s
        },
    )
}

fn npy_structured() -> impl Strategy<Value = Vec<u8>> {
    let version = select(vec![(1u8, 0u8), (2, 0), (3, 0), (0, 0), (1, 1), (255, 255)]);
    let declared = prop_oneof![
        4 => Just(None),
        1 => select(vec![0u32, 1, 0xffff, 0x1_0000, u32::MAX, 0x7fff_ffff]).prop_map(Some),
    ];
    let data = prop_oneof![
        vec(any::<u8>(), 0..96),
        select(vec![0usize, 4, 8, 24, 48]).prop_map(|n| vec![0x3f; n]),
    ];
    (version, npy_dict(), declared, data)
        .prop_map(|(v, dict, declared, data)| npy_bytes(v, &dict, declared, &data))
}

/// Reads `bytes` as a `.npy` file, checking an `Ok` for consistency.
fn check_npy(bytes: &[u8]) -> Result<Option<npy::Array>, TestCaseError> {
    let d = TempDir::new("npy");
    let p = d.file("fuzz.npy", bytes);
    match no_panic("npy::read", bytes, || npy::read(&p))? {
        Ok(a) => {
            let n = a.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
            prop_assert_eq!(n, Some(a.data.len()), "shape {:?}", a.shape);
            Ok(Some(a))
        }
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz.npy"), "{e}");
            Ok(None)
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn npy_arbitrary_bytes(bytes in vec(any::<u8>(), 0..512), magic in any::<bool>()) {
        let bytes = if magic {
            let mut b = b"\x93NUMPY\x01\x00".to_vec();
            b.extend(bytes);
            b
        } else {
            bytes
        };
        check_npy(&bytes)?;
    }

    #[test]
    fn npy_structured_headers(bytes in npy_structured()) {
        check_npy(&bytes)?;
    }

    #[test]
    fn npy_mutated(ms in mutations()) {
        check_npy(&apply(valid_npy(), &ms))?;
    }

    #[test]
    fn npy_truncated_is_an_error(i in any::<Index>()) {
        prop_assert!(check_npy(prefix(valid_npy(), &i))?.is_none());
    }
}

// ---------------------------------------------------------------------------------------
// npz
// ---------------------------------------------------------------------------------------

/// A valid `.npz` with a float array `x` [2, 2] and an int array `f` [1, 3].
fn valid_npz() -> &'static [u8] {
    static B: OnceLock<Vec<u8>> = OnceLock::new();
    B.get_or_init(|| {
        let d = TempDir::new("npz-valid");
        let p = d.0.join("a.npz");
        NpzOut::default()
            .floats("x", &[2, 2], vec![1.0, 2.0, 3.0, 4.0])
            .ints("f", &[1, 3], vec![0, 1, 2])
            .write(&p)
            .unwrap();
        std::fs::read(&p).unwrap()
    })
}

/// One member of a zip built here: its name, its bytes, whether deflated, and an extra
/// field record (id, declared length, payload), if any.
type Member = (String, Vec<u8>, bool, Option<(u16, u16, Vec<u8>)>);

/// The id an extra field is written with (the writer refuses ids such as AES's 0x9901),
/// patched to the real one afterwards.
const PLACEHOLDER_ID: u16 = 0x7a7a;

/// A zip of `members` built in memory.
fn zip_of(members: &[Member]) -> Vec<u8> {
    use npyz::zip::{CompressionMethod, ZipWriter, write::FileOptions};
    let mut w = ZipWriter::new(Cursor::new(Vec::new()));
    for (name, bytes, deflate, extra) in members {
        let method = if *deflate {
            CompressionMethod::Deflated
        } else {
            CompressionMethod::Stored
        };
        let options = FileOptions::default().compression_method(method);
        // A name already used is skipped (the writer refuses duplicates).
        match extra {
            None => {
                if w.start_file(name.as_str(), options).is_err() {
                    continue;
                }
            }
            Some((_, _, payload)) => {
                if w.start_file_with_extra_data(name.as_str(), options)
                    .is_err()
                {
                    continue;
                }
                w.write_all(&PLACEHOLDER_ID.to_le_bytes()).unwrap();
                w.write_all(&(payload.len() as u16).to_le_bytes()).unwrap();
                w.write_all(payload).unwrap();
                w.end_extra_data().unwrap();
            }
        }
        w.write_all(bytes).unwrap();
    }
    let mut zip = w.finish().unwrap().into_inner();
    // The real ids and declared lengths, in the local and the central headers.
    for (_, _, _, extra) in members {
        if let Some((id, len, payload)) = extra {
            let mut from = PLACEHOLDER_ID.to_le_bytes().to_vec();
            from.extend((payload.len() as u16).to_le_bytes());
            let mut to = id.to_le_bytes().to_vec();
            to.extend(len.to_le_bytes());
            let mut i = 0;
            while let Some(p) = zip[i..].windows(4).position(|w| w == from.as_slice()) {
                zip[i + p..i + p + 4].copy_from_slice(&to);
                i += p + 4;
            }
        }
    }
    zip
}

/// Sets the compression method (when given) and flips `flags` in every local and central
/// header of a zip.
fn patch_zip(mut zip: Vec<u8>, method: Option<u16>, flags: u16) -> Vec<u8> {
    // (signature, offset of the flags, offset of the method)
    for (sig, flag_at, method_at) in [(b"PK\x03\x04", 6, 8), (b"PK\x01\x02", 8, 10)] {
        let starts: Vec<usize> = zip
            .windows(4)
            .enumerate()
            .filter(|(_, w)| w == sig)
            .map(|(i, _)| i)
            .collect();
        for i in starts {
            if let Some(b) = zip.get_mut(i + flag_at..i + flag_at + 2) {
                let v = (u16::from_le_bytes([b[0], b[1]]) ^ flags).to_le_bytes();
                b.copy_from_slice(&v);
            }
            if let (Some(m), Some(b)) = (method, zip.get_mut(i + method_at..i + method_at + 2)) {
                b.copy_from_slice(&m.to_le_bytes());
            }
        }
    }
    zip
}

/// The payload of WinZip's AES extra field: vendor version, "AE", strength, the real
/// method.
fn aes_payload(version: u16, strength: u8, method: u16) -> Vec<u8> {
    let mut v = version.to_le_bytes().to_vec();
    v.extend(b"AE");
    v.push(strength);
    v.extend(method.to_le_bytes());
    v
}

/// Opens `bytes` as an `.npz` and reads `x` and `f` both as floats and as ints, checking
/// every `Ok`. Returns whether everything succeeded.
fn check_npz(bytes: &[u8]) -> Result<bool, TestCaseError> {
    let path = Path::new("fuzz.npz");
    let opened = no_panic("Npz::from_bytes", bytes, || {
        Npz::from_bytes(bytes.to_vec(), path)
    })?;
    let mut z = match opened {
        Ok(z) => z,
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz.npz"), "{e}");
            return Ok(false);
        }
    };
    let mut all_ok = true;
    for name in ["x", "f", "y"] {
        no_panic("Npz::has", bytes, || z.has(name))?;
        match no_panic("Npz::floats", bytes, || z.floats(name))? {
            Ok(a) => {
                let n = a.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
                prop_assert_eq!(n, Some(a.data.len()));
                prop_assert!(a.data.iter().all(|v| v.is_finite()));
            }
            Err(e) => {
                prop_assert!(e.to_string().contains("fuzz.npz"), "{e}");
                all_ok &= name != "x";
            }
        }
        match no_panic("Npz::ints", bytes, || z.ints(name))? {
            Ok(a) => {
                let n = a.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
                prop_assert_eq!(n, Some(a.data.len()));
            }
            Err(e) => {
                prop_assert!(e.to_string().contains("fuzz.npz"), "{e}");
                all_ok &= name != "f";
            }
        }
    }
    Ok(all_ok)
}

fn npz_member() -> impl Strategy<Value = Member> {
    let name = select(vec![
        "x.npy", "f.npy", "x", "f", "y.npy", "../x.npy", "/x.npy", "x.npy/", "",
    ])
    .prop_map(str::to_string);
    let content = prop_oneof![
        3 => npy_structured(),
        2 => mutations().prop_map(|ms| apply(valid_npy(), &ms)),
        1 => vec(any::<u8>(), 0..64),
    ];
    let extra = prop_oneof![
        4 => Just(None),
        2 => (select(vec![7u16, 6, 0, 0xffff]), 0u16..4, 0u8..5, select(vec![0u16, 8, 12, 99, 7]))
            .prop_map(|(len, version, strength, method)| {
                Some((0x9901, len, aes_payload(version, strength, method)))
            }),
        1 => (select(vec![0x0001u16, 0x5455, 0x7875, 0x000a]), any::<u16>(), vec(any::<u8>(), 0..24))
            .prop_map(|(id, len, payload)| Some((id, len, payload))),
    ];
    (name, content, any::<bool>(), extra)
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn npz_arbitrary_bytes(bytes in vec(any::<u8>(), 0..512), eocd in any::<bool>()) {
        let mut bytes = bytes;
        if eocd {
            // An end-of-central-directory record, so the reader goes past its first check.
            bytes.extend(b"PK\x05\x06");
            bytes.extend([0u8; 18]);
        }
        check_npz(&bytes)?;
    }

    #[test]
    fn npz_valid_zip_of_hostile_npy(members in vec(npz_member(), 0..4)) {
        check_npz(&zip_of(&members))?;
    }

    #[test]
    fn npz_hostile_zip_headers(
        members in vec(npz_member(), 1..3),
        method in prop_oneof![
            Just(None),
            select(vec![0u16, 1, 8, 9, 12, 14, 93, 95, 98, 99, 0xffff]).prop_map(Some),
        ],
        flags in select(vec![0u16, 1, 8, 0x40, 0x800, 0x2000]),
    ) {
        check_npz(&patch_zip(zip_of(&members), method, flags))?;
    }

    #[test]
    fn npz_mutated(ms in mutations()) {
        check_npz(&apply(valid_npz(), &ms))?;
    }

    #[test]
    fn npz_truncated_is_an_error(i in any::<Index>()) {
        prop_assert!(!check_npz(prefix(valid_npz(), &i))?);
    }
}

// ---------------------------------------------------------------------------------------
// pickle
// ---------------------------------------------------------------------------------------

fn unicode(s: &str) -> Vec<u8> {
    let mut v = vec![b'X'];
    v.extend((s.len() as u32).to_le_bytes());
    v.extend(s.as_bytes());
    v
}

/// The opcodes numpy writes for a float32 array of `shape` (BININT dims), `data` as its
/// bytes (as in `src/io/pickle.rs`'s tests).
fn pickle_array(shape: &[i32], descr: &str, order: &str, fortran: bool, data: &[u8]) -> Vec<u8> {
    let mut v = Vec::new();
    v.extend(b"cnumpy.core.multiarray\n_reconstruct\n");
    v.extend(b"cnumpy\nndarray\n");
    v.extend([b'K', 0, 0x85, b'C', 1, b'b', 0x87, b'R']);
    v.extend([b'(', b'K', 1, b'(']);
    for &s in shape {
        v.push(b'J');
        v.extend(s.to_le_bytes());
    }
    v.push(b't');
    v.extend(b"cnumpy\ndtype\n");
    v.extend(unicode(descr));
    v.extend([0x89, 0x88, 0x87, b'R']);
    v.extend([b'(', b'K', 3]);
    v.extend(unicode(order));
    v.extend([b'N', b'N', b'N', b'J']);
    v.extend((-1i32).to_le_bytes());
    v.push(b'J');
    v.extend((-1i32).to_le_bytes());
    v.extend([b'K', 0, b't', b'b']);
    v.push(if fortran { 0x88 } else { 0x89 });
    v.push(b'B');
    v.extend((data.len() as u32).to_le_bytes());
    v.extend(data);
    v.extend([b't', b'b']);
    v
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// A valid checkpoint: `{"net": {"kernel": [2, 3] array, "bias": [2] array}}`.
fn valid_pickle() -> Vec<u8> {
    [
        &[0x80, 2, b'}', b'q', 0, b'('][..],
        &unicode("net"),
        &[b'}', b'q', 1, b'('],
        &unicode("kernel"),
        &pickle_array(
            &[2, 3],
            "f4",
            "<",
            false,
            &f32_bytes(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]),
        ),
        &unicode("bias"),
        &pickle_array(&[2], "f4", "<", true, &f32_bytes(&[-1.0, 0.5])),
        b"uu.",
    ]
    .concat()
}

/// One opcode with hostile arguments, or a whole numpy array with a hostile shape.
fn pickle_fragment() -> impl Strategy<Value = Vec<u8>> {
    let simple = select(vec![
        &b"("[..],
        b"N",
        b"\x88",
        b"\x89",
        b")",
        b"t",
        b"\x85",
        b"\x86",
        b"\x87",
        b"]",
        b"a",
        b"e",
        b"}",
        b"s",
        b"u",
        b"R",
        b"b",
        b".",
        b"cnumpy\ndtype\n",
        b"cnumpy\nndarray\n",
        b"cnumpy.core.multiarray\n_reconstruct\n",
        b"cos\nsystem\n",
        b"c",
        b"\x80\x02",
        b"\x80\x05",
        b"\x95",
    ])
    .prop_map(<[u8]>::to_vec);
    let int = select(vec![0i32, 1, 2, 3, -1, i32::MAX, i32::MIN, 65536, 1 << 30]);
    let with_arg = prop_oneof![
        int.clone()
            .prop_map(|v| [&[b'J'][..], &v.to_le_bytes()].concat()),
        any::<u8>().prop_map(|v| vec![b'K', v]),
        any::<u16>().prop_map(|v| [&[b'M'][..], &v.to_le_bytes()].concat()),
        select(vec![0.0f64, f64::NAN, f64::INFINITY, -1.0, 1e300]).prop_map(|v| [
            &[b'G'][..],
            &v.to_be_bytes()
        ]
        .concat()),
        (0u8..4).prop_map(|k| vec![b'q', k]),
        (0u8..4).prop_map(|k| vec![b'h', k]),
        select(vec![0u32, 1, u32::MAX]).prop_map(|k| [&[b'r'][..], &k.to_le_bytes()].concat()),
        select(vec![0u32, 1, u32::MAX]).prop_map(|k| [&[b'j'][..], &k.to_le_bytes()].concat()),
        select(vec![
            "f4", "f8", "<", ">", "=", "|", "i4", "", "net", "kernel"
        ])
        .prop_map(unicode),
        (
            select(vec![0u32, 1, 4, 8, u32::MAX, 1 << 31]),
            vec(any::<u8>(), 0..16)
        )
            .prop_map(|(n, b)| [&[b'B'][..], &n.to_le_bytes(), &b].concat()),
        (any::<u8>(), vec(any::<u8>(), 0..8)).prop_map(|(n, b)| [&[b'C'][..], &[n], &b].concat()),
        (any::<u8>(), vec(any::<u8>(), 0..8)).prop_map(|(n, b)| [&[b'U'][..], &[n], &b].concat()),
    ];
    let array = (
        vec(int, 0..5),
        select(vec!["f4", "f8", "i4", "O"]),
        select(vec!["<", ">", "=", "|", "<<"]),
        any::<bool>(),
        select(vec![0usize, 4, 8, 16, 24, 48]),
    )
        .prop_map(|(shape, descr, order, fortran, n)| {
            pickle_array(&shape, descr, order, fortran, &vec![0x3f; n])
        });
    prop_oneof![4 => simple, 4 => with_arg, 1 => array]
}

/// Reads a pickle and its array tree, checking an `Ok` for consistency.
fn check_pickle(bytes: &[u8]) -> Result<bool, TestCaseError> {
    let v = match no_panic("pickle::read", bytes, || pickle::read(bytes, "fuzz.ckpt"))? {
        Ok(v) => v,
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz.ckpt"), "{e}");
            return Ok(false);
        }
    };
    match no_panic("Value::arrays", bytes, || v.arrays("fuzz.ckpt"))? {
        Ok(arrays) => {
            for a in arrays.values() {
                let n = a.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
                prop_assert_eq!(n, Some(a.data.len()));
            }
            Ok(true)
        }
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz.ckpt"), "{e}");
            Ok(false)
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn pickle_arbitrary_bytes(bytes in vec(any::<u8>(), 0..512), proto in any::<bool>()) {
        let bytes = if proto { [&[0x80, 2][..], &bytes].concat() } else { bytes };
        check_pickle(&bytes)?;
    }

    #[test]
    fn pickle_opcode_sequences(frags in vec(pickle_fragment(), 0..48), stop in any::<bool>()) {
        let mut bytes = vec![0x80, 2];
        bytes.extend(frags.concat());
        if stop {
            bytes.push(b'.');
        }
        check_pickle(&bytes)?;
    }

    #[test]
    fn pickle_mutated(ms in mutations()) {
        check_pickle(&apply(&valid_pickle(), &ms))?;
    }

    #[test]
    fn pickle_truncated_is_an_error(i in any::<Index>()) {
        prop_assert!(!check_pickle(prefix(&valid_pickle(), &i))?);
    }
}

// ---------------------------------------------------------------------------------------
// OBJ
// ---------------------------------------------------------------------------------------

const VALID_OBJ: &str = "# a unit quad and a triangle\n\
    o quad\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 5 5 5\n\
    vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n\
    usemtl skin\ns 1\nf 3/3 4/4 1/1 2/2\nf -1/-1/1 -2/-2/1 -3/-3/1\n";

fn obj_line() -> impl Strategy<Value = String> {
    let num = select(HOSTILE_NUMBERS);
    let index = prop_oneof![
        (-6i64..8).prop_map(|i| i.to_string()),
        select(vec![
            "0",
            "9223372036854775807",
            "-9223372036854775808",
            "99999999999999999999",
            "4294967296",
            "-4294967297",
            "",
            "x",
        ])
        .prop_map(str::to_string),
    ];
    let corner = prop_oneof![
        (index.clone(), index.clone()).prop_map(|(p, t)| format!("{p}/{t}")),
        (index.clone(), index.clone(), index.clone()).prop_map(|(p, t, n)| format!("{p}/{t}/{n}")),
        (index.clone(), index.clone()).prop_map(|(p, n)| format!("{p}//{n}")),
        index.clone(),
        (index.clone(), index).prop_map(|(p, t)| format!("{p}/{t}/")),
    ];
    prop_oneof![
        3 => vec(num.clone(), 0..5).prop_map(|v| format!("v {}", v.join(" "))),
        2 => vec(num.clone(), 0..4).prop_map(|v| format!("vt {}", v.join(" "))),
        1 => vec(num, 0..4).prop_map(|v| format!("vn {}", v.join(" "))),
        4 => vec(corner, 0..6).prop_map(|c| format!("f {}", c.join(" "))),
        1 => select(vec![
            "o a", "g a b", "s off", "s 1", "mtllib a.mtl", "usemtl m", "l 1 2", "p 1",
            "#", "\\", "v 0 0 0 \\", "f", "vt", "v", "",
        ])
        .prop_map(str::to_string),
        1 => "[ -~]{0,16}",
    ]
}

/// Parses OBJ text, checking an `Ok` for consistency (every index in range).
fn check_obj(text: &str) -> Result<bool, TestCaseError> {
    match no_panic("UvMesh::parse", text.as_bytes(), || {
        UvMesh::parse(text, "fuzz.obj")
    })? {
        Ok(m) => {
            prop_assert_eq!(m.faces.len(), m.uv_faces.len());
            prop_assert!(!m.faces.is_empty());
            for (f, t) in m.faces.iter().zip(&m.uv_faces) {
                prop_assert!(f.iter().all(|&i| (i as usize) < m.positions.len()));
                prop_assert!(t.iter().all(|&i| (i as usize) < m.uvs.len()));
            }
            Ok(true)
        }
        Err(e) => {
            prop_assert!(e.to_string().contains("fuzz.obj"), "{e}");
            Ok(false)
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn obj_arbitrary_bytes(bytes in vec(any::<u8>(), 0..512)) {
        check_obj(&String::from_utf8_lossy(&bytes))?;
        // Through the file, where invalid UTF-8 is refused.
        let d = TempDir::new("obj");
        let p = d.file("fuzz.obj", &bytes);
        let r = no_panic("UvMesh::load", &bytes, || UvMesh::load(&p))?;
        if let Err(e) = r {
            prop_assert!(e.to_string().contains("fuzz.obj"), "{e}");
        }
    }

    #[test]
    fn obj_structured(lines in vec(obj_line(), 0..40)) {
        check_obj(&lines.join("\n"))?;
    }

    #[test]
    fn obj_mutated(ms in mutations()) {
        let bytes = apply(VALID_OBJ.as_bytes(), &ms);
        check_obj(&String::from_utf8_lossy(&bytes))?;
    }

    #[test]
    fn obj_out_of_range_face_is_an_error(extra in 1i64..1_000_000, uv in any::<bool>()) {
        let (p, t) = if uv { (1, 4 + extra) } else { (5 + extra, 1) };
        let text = format!("{VALID_OBJ}f 1/1 2/2 {p}/{t}\n");
        prop_assert!(!check_obj(&text)?);
    }
}

// ---------------------------------------------------------------------------------------
// JSON configs
// ---------------------------------------------------------------------------------------

fn tiny_net() -> Json {
    json!({
        "uv_res": 32,
        "condition": { "expression": 52, "pose": 15, "eta": 128, "zero_eta": false },
        "code_channels": 16,
        "untied_bias": true,
        "geometry": [16, 11],
        "appearance": { "before_view": [16], "mid": [8, 8], "after_view": [3] },
        "view": { "channels": [3, 3], "square_res": 512 }
    })
}

fn train_config(net: Json) -> Json {
    json!({
        "net": net,
        "ablations": { "global_uv": true, "jacobian": true, "eta": true, "vgg": false },
        "iterations": 20,
        "batch_size": 1,
        "lr_decoders": 0.0006,
        "lr_encoders": 0.0004,
        "adam_eps": 1e-15,
        "vgg_start": 0.5,
        "checkpoint_every": 10,
        "val_frames": 2,
        "log_every": 5,
        "seed": 1,
        "backend": "flex"
    })
}

fn synth_config() -> Json {
    serde_json::to_value(SynthConfig::default()).unwrap()
}

fn camera_file() -> Json {
    serde_json::to_value(texavatars::splat::demo::camera()).unwrap()
}

/// A valid `transforms_*.json` (from the crate's writer), with a frame lacking its own
/// intrinsics added so the top-level defaults are read too.
fn transforms() -> Json {
    static J: OnceLock<Json> = OnceLock::new();
    J.get_or_init(|| {
        let d = TempDir::new("vhap-valid");
        let p = d.0.join("transforms_train.json");
        let cam = texavatars::splat::demo::camera().camera;
        let rec = |t: usize| FrameRecord {
            timestep: t,
            camera_index: 2,
            file_path: format!("images/{t:05}_02.png"),
            fg_mask_path: format!("fg_masks/{t:05}_02.png"),
            flame_param_path: format!("flame_param/{t:05}.npz"),
            camera: cam,
        };
        save_transforms(&p, &[rec(0), rec(1)]).unwrap();
        let mut j: Json = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        let frames = j["frames"].as_array_mut().unwrap();
        let mut bare = frames[0].clone();
        for k in [
            "cx",
            "cy",
            "fl_x",
            "fl_y",
            "h",
            "w",
            "camera_angle_x",
            "camera_angle_y",
        ] {
            bare.as_object_mut().unwrap().remove(k);
        }
        frames.push(bare);
        j
    })
    .clone()
}

/// Which JSON loader a case goes to.
#[derive(Clone, Copy, Debug)]
enum Loader {
    /// `TrainConfig::load` with the net inline.
    TrainInline,
    /// `TrainConfig::load` with the net in `net.json` next to it (the mutated document is
    /// the net file; the train config itself is valid).
    TrainNetFile,
    Synth,
    Camera,
    Transforms,
}

const LOADERS: [Loader; 5] = [
    Loader::TrainInline,
    Loader::TrainNetFile,
    Loader::Synth,
    Loader::Camera,
    Loader::Transforms,
];

impl Loader {
    fn valid(self) -> Json {
        match self {
            Loader::TrainInline => train_config(tiny_net()),
            Loader::TrainNetFile => tiny_net(),
            Loader::Synth => synth_config(),
            Loader::Camera => camera_file(),
            Loader::Transforms => transforms(),
        }
    }

    /// Loads `bytes` (the document this loader fuzzes); `Ok(true)` when it loaded.
    fn check(self, bytes: &[u8]) -> Result<bool, TestCaseError> {
        let d = TempDir::new("json");
        let name = match self {
            Loader::TrainNetFile => "net.json",
            Loader::Transforms => "transforms_train.json",
            _ => "fuzz.json",
        };
        let p = d.file(name, bytes);
        let r: texavatars::error::Result<()> =
            no_panic(&format!("{self:?}"), bytes, || match self {
                Loader::TrainInline => TrainConfig::load(&p).map(|c| {
                    c.vgg_from();
                }),
                Loader::TrainNetFile => {
                    let cfg = serde_json::to_vec(&train_config(json!("net.json"))).unwrap();
                    TrainConfig::load(&d.file("fuzz.json", &cfg)).map(drop)
                }
                Loader::Synth => SynthConfig::load(&p).map(drop),
                Loader::Camera => CameraFile::load(&p).map(drop),
                Loader::Transforms => load_transforms(&p).map(drop),
            })?;
        match r {
            Ok(()) => Ok(true),
            Err(e) => {
                // The error names the file at fault: the document, or the net file a train
                // config names (any path, from the fuzzed `net` field).
                let e = e.to_string();
                let named = e.contains(name)
                    || e.contains("fuzz.json")
                    || matches!(self, Loader::TrainInline);
                prop_assert!(named, "{e}");
                Ok(false)
            }
        }
    }
}

/// Hostile JSON values: wrong types, huge and negative numbers, deep nesting, long arrays.
fn hostile_json() -> impl Strategy<Value = Json> {
    select(vec![
        json!(null),
        json!(true),
        json!(0),
        json!(1),
        json!(-1),
        json!(i64::MIN),
        json!(u64::MAX),
        json!(1u64 << 63),
        json!(1e308),
        json!(-1e308),
        json!(0.5),
        json!(1.5e-45),
        json!(4e9),
        json!(""),
        json!("NaN"),
        json!("x"),
        json!("../../../../etc/passwd"),
        json!("/dev/zero"),
        json!([]),
        json!({}),
        json!([1, 2, 3]),
        json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]),
        json!([[1e38, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
        json!(vec![3; 70]),
        json!(vec![u64::MAX; 3]),
        json!({"expression": u64::MAX, "pose": u64::MAX, "eta": 1}),
        json!({"channels": vec![3; 64], "square_res": 512}),
        json!({"before_view": vec![1; 70], "mid": [1], "after_view": [3]}),
        deep(200),
    ])
}

fn deep(n: usize) -> Json {
    (0..n).fold(json!(1), |v, _| json!([v]))
}

/// Every path (object keys and array indices) in `v`, the root included.
fn paths(v: &Json) -> Vec<Vec<Json>> {
    let mut out = vec![Vec::new()];
    let mut i = 0;
    while i < out.len() {
        let p = out[i].clone();
        let node = get(v, &p).unwrap();
        match node {
            Json::Object(m) => {
                for k in m.keys() {
                    out.push([p.clone(), vec![json!(k)]].concat());
                }
            }
            Json::Array(a) => {
                for j in 0..a.len() {
                    out.push([p.clone(), vec![json!(j)]].concat());
                }
            }
            _ => {}
        }
        i += 1;
    }
    out
}

fn get<'a>(v: &'a Json, path: &[Json]) -> Option<&'a Json> {
    path.iter().try_fold(v, |v, k| match k {
        Json::String(k) => v.get(k.as_str()),
        Json::Number(j) => v.get(j.as_u64()? as usize),
        _ => None,
    })
}

fn get_mut<'a>(v: &'a mut Json, path: &[Json]) -> Option<&'a mut Json> {
    path.iter().try_fold(v, |v, k| match k {
        Json::String(k) => v.get_mut(k.as_str()),
        Json::Number(j) => v.get_mut(j.as_u64()? as usize),
        _ => None,
    })
}

/// An edit of a JSON document at a path chosen by index.
#[derive(Clone, Debug)]
enum JsonEdit {
    Replace(Index, Json),
    Remove(Index),
    AddKey(Index, Json),
}

fn json_edit() -> impl Strategy<Value = JsonEdit> {
    prop_oneof![
        4 => (any::<Index>(), hostile_json()).prop_map(|(i, v)| JsonEdit::Replace(i, v)),
        2 => any::<Index>().prop_map(JsonEdit::Remove),
        1 => (any::<Index>(), hostile_json()).prop_map(|(i, v)| JsonEdit::AddKey(i, v)),
    ]
}

fn edit_json(mut doc: Json, edits: &[JsonEdit]) -> Json {
    for e in edits {
        let ps = paths(&doc);
        match e {
            JsonEdit::Replace(i, v) => {
                let p = &ps[i.index(ps.len())];
                *get_mut(&mut doc, p).unwrap() = v.clone();
            }
            JsonEdit::Remove(i) => {
                let p = &ps[i.index(ps.len())];
                if let Some((last, parent)) = p.split_last() {
                    match (get_mut(&mut doc, parent).unwrap(), last) {
                        (Json::Object(m), Json::String(k)) => {
                            m.remove(k);
                        }
                        (Json::Array(a), Json::Number(j)) => {
                            a.remove(j.as_u64().unwrap() as usize);
                        }
                        _ => {}
                    }
                }
            }
            JsonEdit::AddKey(i, v) => {
                let p = &ps[i.index(ps.len())];
                if let Some(Json::Object(m)) = get_mut(&mut doc, p) {
                    m.insert("unexpected".into(), v.clone());
                }
            }
        }
    }
    doc
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn json_arbitrary_bytes(bytes in vec(any::<u8>(), 0..256), loader in select(&LOADERS[..])) {
        loader.check(&bytes)?;
    }

    #[test]
    fn json_field_edits(edits in vec(json_edit(), 1..4), loader in select(&LOADERS[..])) {
        let doc = edit_json(loader.valid(), &edits);
        loader.check(&serde_json::to_vec_pretty(&doc).unwrap())?;
    }

    #[test]
    fn json_text_mutations(ms in mutations(), loader in select(&LOADERS[..])) {
        let text = serde_json::to_vec_pretty(&loader.valid()).unwrap();
        loader.check(&apply(&text, &ms))?;
    }

    #[test]
    fn json_truncated_is_an_error(i in any::<Index>(), loader in select(&LOADERS[..])) {
        let text = serde_json::to_vec_pretty(&loader.valid()).unwrap();
        prop_assert!(!loader.check(prefix(&text, &i))?);
    }
}

/// The valid documents load (so the mutation properties start from something real).
#[test]
fn valid_inputs_load() {
    assert!(check_ply(valid_ply()).unwrap().is_some());
    assert!(check_ply(&valid_ascii_ply()).unwrap().is_some());
    assert_eq!(check_npy(valid_npy()).unwrap().unwrap().shape, vec![2, 3]);
    assert!(check_npz(valid_npz()).unwrap());
    assert!(check_pickle(&valid_pickle()).unwrap());
    assert!(check_obj(VALID_OBJ).unwrap());
    for loader in LOADERS {
        let text = serde_json::to_vec_pretty(&loader.valid()).unwrap();
        assert!(loader.check(&text).unwrap(), "{loader:?}");
    }
}

// ---------------------------------------------------------------------------------------
// Regressions: each crash the fuzzing found, with its minimal input.
// ---------------------------------------------------------------------------------------

/// `f` returns an error naming the problem (`needle`), neither a panic nor `Ok`.
fn expect_err<T: std::fmt::Debug>(
    parser: &str,
    input: &[u8],
    needle: &str,
    f: impl FnOnce() -> texavatars::error::Result<T>,
) {
    let r = no_panic(parser, input, f).unwrap_or_else(|e| panic!("{e}"));
    let e = r.expect_err(parser).to_string();
    assert!(e.contains(needle), "`{needle}` not in: {e}");
}

fn npy_file(dict: &str, data: &[u8]) -> (TempDir, PathBuf, Vec<u8>) {
    let bytes = npy_bytes((1, 0), dict, None, data);
    let d = TempDir::new("regression");
    let p = d.file("r.npy", &bytes);
    (d, p, bytes)
}

/// Found by `npy_structured_headers`: npyz multiplied the dimensions unchecked
/// (`NpyHeader::from_parts`, "attempt to multiply with overflow").
#[test]
fn regression_npy_shape_product_overflow() {
    let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 9223372036854775808), }";
    let (_d, p, b) = npy_file(dict, &[]);
    expect_err("npy::read", &b, "too many elements", || npy::read(&p));
}

/// A header nested 30,000 deep: the header reader has no recursion (npyz's Python-literal
/// parser, pest, recursed and stopped at its own stack limit).
#[test]
fn regression_npy_deeply_nested_header() {
    let dict = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': {}1{}}}",
        "(".repeat(30_000),
        ",)".repeat(30_000)
    );
    let (_d, p, b) = npy_file(&dict, &[]);
    expect_err("npy::read", &b, "non-negative", || npy::read(&p));
}

/// Declared sizes beyond the file: a 4 GiB header length (npyz allocated a buffer of that
/// size before reading into it) and 10^12 elements; errors before any allocation.
#[test]
fn regression_npy_declared_sizes_beyond_the_file() {
    let b = npy_bytes((2, 0), "{}", Some(u32::MAX), &[]);
    let d = TempDir::new("regression");
    let p = d.file("h.npy", &b);
    expect_err("npy::read", &b, "at most", || npy::read(&p));
    let b = npy_bytes((2, 0), "{}", Some(0xffff), &[]);
    let p = d.file("h.npy", &b);
    expect_err("npy::read", &b, "truncated", || npy::read(&p));
    let dict = "{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000000,), }";
    let (_d, p, b) = npy_file(dict, &[0; 16]);
    expect_err("npy::read", &b, "truncated", || npy::read(&p));
}

/// Found by `npz_valid_zip_of_hostile_npy`: a member with WinZip's AES extra field but
/// without the encryption flag made `zip`'s `ZipArchive::by_name` unwrap an
/// `Err(InvalidPassword)` (through npyz's `NpzArchive::by_name`).
#[test]
fn regression_npz_aes_extra_field_without_encryption_flag() {
    let npy = valid_npy().to_vec();
    let zip = zip_of(&[(
        "x.npy".into(),
        npy,
        false,
        Some((0x9901, 7, aes_payload(1, 1, 0))),
    )]);
    let mut z = Npz::from_bytes(zip.clone(), Path::new("aes.npz")).unwrap();
    expect_err("Npz::floats", &zip, "encrypted", || z.floats("x"));
    expect_err("Npz::ints", &zip, "encrypted", || z.ints("x"));
}

/// The npy header checks hold inside an archive too, where the bound is the member's
/// declared size.
#[test]
fn regression_npz_member_shapes_beyond_the_member() {
    for (shape, why) in [
        ("(2, 9223372036854775808)", "too many elements"),
        ("(1000000000000,)", "truncated"),
        ("(4611686018427387904,)", "too large"),
    ] {
        let dict = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
        let npy = npy_bytes((1, 0), &dict, None, &[0; 8]);
        let zip = zip_of(&[("x.npy".into(), npy, true, None)]);
        let mut z = Npz::from_bytes(zip.clone(), Path::new("s.npz")).unwrap();
        expect_err("Npz::floats", &zip, why, || z.floats("x"));
    }
}

/// Found by `pickle_opcode_sequences`: the element count of an array of shape
/// (65536, 2^31 - 1, 2^31 - 1) overflowed in `Machine::array` ("attempt to multiply with
/// overflow").
#[test]
fn regression_pickle_array_shape_overflow() {
    let bytes = [
        &[0x80, 2][..],
        &pickle_array(&[65536, i32::MAX, i32::MAX], "f4", "<", false, &[]),
        b".",
    ]
    .concat();
    expect_err("pickle::read", &bytes, "too large", || {
        pickle::read(&bytes, "r.ckpt")
    });
}

/// Tuples nested 100,000 deep (one byte each): comparing, walking or dropping the value
/// recursed until the stack overflowed.
#[test]
fn regression_pickle_deep_nesting() {
    let mut bytes = vec![0x80, 2, b'N'];
    bytes.extend(std::iter::repeat_n(0x85, 100_000));
    bytes.push(b'.');
    expect_err("pickle::read", &bytes, "nested", || {
        pickle::read(&bytes, "r.ckpt")
    });
}

/// A value doubled through the memo 40 times in 200 bytes (`q 0, h 0, TUPLE2`): 2^40 leaves,
/// memory without bound.
#[test]
fn regression_pickle_memo_doubling() {
    let mut bytes = vec![0x80, 2, b'N'];
    for _ in 0..40 {
        bytes.extend([b'q', 0, b'h', 0, 0x86]);
    }
    bytes.push(b'.');
    expect_err("pickle::read", &bytes, "memo", || {
        pickle::read(&bytes, "r.ckpt")
    });
}

/// Loads `net` (a net config) both inline in a train config and from a net file.
fn train_with_net(net: Json, needle: &str) {
    let d = TempDir::new("regression");
    let inline = serde_json::to_vec(&train_config(net.clone())).unwrap();
    let p = d.file("inline.json", &inline);
    expect_err("TrainConfig::load", &inline, needle, || {
        TrainConfig::load(&p)
    });
    let net_bytes = serde_json::to_vec(&net).unwrap();
    d.file("net.json", &net_bytes);
    let cfg = serde_json::to_vec(&train_config(json!("net.json"))).unwrap();
    let p = d.file("file.json", &cfg);
    expect_err("TrainConfig::load", &net_bytes, needle, || {
        TrainConfig::load(&p)
    });
}

/// Found by `json_field_edits`: `"eta": 18446744073709551615` overflowed the condition's
/// width (`ConditionConfig::dim`, "attempt to add with overflow", in `NetConfig::validate`).
#[test]
fn regression_train_config_condition_width_overflow() {
    let mut net = tiny_net();
    net["condition"]["eta"] = json!(u64::MAX);
    train_with_net(net, "condition");
}

/// 64 view encoder layers shifted the encoder's input side by 64 bits
/// (`NetConfig::view_input_res`, "attempt to shift left with overflow"); 61 of them wrapped
/// it to 0 and, with `square_res` 0, divided by zero in `NetConfig::validate`.
#[test]
fn regression_train_config_view_stages_overflow() {
    let mut net = tiny_net();
    net["view"]["channels"] = json!(vec![3; 64]);
    train_with_net(net, "stages");
    let mut net = tiny_net();
    net["view"]["channels"] = json!(vec![3; 61]);
    net["view"]["square_res"] = json!(0);
    train_with_net(net, "stages");
}

/// A train config whose `net` names a device: reading `/dev/zero` never ended (memory
/// without bound).
#[cfg(unix)]
#[test]
fn regression_train_config_net_is_a_device() {
    let d = TempDir::new("regression");
    let cfg = serde_json::to_vec(&train_config(json!("/dev/zero"))).unwrap();
    let p = d.file("dev.json", &cfg);
    expect_err("TrainConfig::load", &cfg, "regular file", || {
        TrainConfig::load(&p)
    });
}

/// Found by `obj_mutated`: a face corner's normal index of -2^63 (any index far out of
/// range) overflowed in tobj (`add_vertex_multi_index`, `vn * 3`, "attempt to multiply with
/// overflow"); the line scan did not look at normal indices.
#[test]
fn regression_obj_normal_index_overflow() {
    let text = format!("{VALID_OBJ}f -1/-1/1 -2/-2/1 -3/-3/-9223372036854775808\n");
    expect_err("UvMesh::parse", text.as_bytes(), "normal index", || {
        UvMesh::parse(&text, "r.obj")
    });
    // The same through a polyline, which tobj reads as a face when it has three corners.
    let text = format!("{VALID_OBJ}l 1/1/1 2/2/1 3/3/9223372036854775807\n");
    expect_err("UvMesh::parse", text.as_bytes(), "normal index", || {
        UvMesh::parse(&text, "r.obj")
    });
}
