//! `.npz` archives (numpy's zip of `.npy` arrays), through `npyz`: float arrays (f4/f8) and
//! integer arrays (any width and sign) by name, with errors naming the file and the array.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use npyz::WriterBuilder;
use npyz::npz::NpzArchive;

use crate::error::{Error, Result};
use crate::io::npy::Array;

/// An integer array with its shape.
#[derive(Clone, Debug, PartialEq)]
pub struct IntArray {
    pub shape: Vec<usize>,
    pub data: Vec<i64>,
}

/// An open `.npz` archive (read fully into memory).
pub struct Npz {
    path: PathBuf,
    archive: NpzArchive<Cursor<Vec<u8>>>,
}

impl Npz {
    /// Opens `path`.
    pub fn open(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        Self::from_bytes(bytes, path)
    }

    /// Reads an archive held in memory; `path` names it in error messages.
    pub fn from_bytes(bytes: Vec<u8>, path: &Path) -> Result<Self> {
        let archive = NpzArchive::new(Cursor::new(bytes)).map_err(|e| {
            Error::invalid(
                path.display().to_string(),
                "archive",
                format!("not a .npz file: {e}"),
            )
        })?;
        Ok(Npz {
            path: path.to_path_buf(),
            archive,
        })
    }

    fn what(&self) -> String {
        self.path.display().to_string()
    }

    /// Whether the archive holds an array called `name`.
    pub fn has(&self, name: &str) -> bool {
        self.archive.array_names().any(|n| n == name)
    }

    fn npy(&mut self, name: &str) -> Result<npyz::NpyFile<impl std::io::Read + '_>> {
        let what = self.what();
        match self.archive.by_name(name) {
            Ok(Some(f)) => Ok(f),
            Ok(None) => Err(Error::invalid(what, name, "missing from the archive")),
            Err(e) => Err(Error::invalid(what, name, format!("unreadable: {e}"))),
        }
    }

    /// A float array (float32, or float64 converted), all values finite.
    pub fn floats(&mut self, name: &str) -> Result<Array> {
        let what = self.what();
        let npy = self.npy(name)?;
        let Array { shape, data } = crate::io::npy::floats(npy, &what, name)?;
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                &what,
                name,
                format!("value {i} is not finite"),
            ));
        }
        Ok(Array { shape, data })
    }

    /// An integer array of any width and sign.
    pub fn ints(&mut self, name: &str) -> Result<IntArray> {
        let what = self.what();
        let npy = self.npy(name)?;
        let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
        let descr = npy.dtype().descr();
        let bad = |e: std::io::Error| {
            Error::invalid(&what, name, format!("truncated or unreadable: {e}"))
        };
        let data: Vec<i64> = match descr.trim_matches('\'') {
            "<i8" => npy.into_vec::<i64>().map_err(bad)?,
            "<i4" => npy
                .into_vec::<i32>()
                .map_err(bad)?
                .into_iter()
                .map(i64::from)
                .collect(),
            "<u4" => npy
                .into_vec::<u32>()
                .map_err(bad)?
                .into_iter()
                .map(i64::from)
                .collect(),
            "<u8" => npy
                .into_vec::<u64>()
                .map_err(bad)?
                .into_iter()
                .map(|v| if v > i64::MAX as u64 { -1 } else { v as i64 })
                .collect(),
            other => {
                return Err(Error::invalid(
                    &what,
                    name,
                    format!("expected an integer dtype, got {other}"),
                ));
            }
        };
        if data.len() != shape.iter().product::<usize>() {
            return Err(Error::invalid(&what, name, "truncated"));
        }
        Ok(IntArray { shape, data })
    }
}

/// Arrays to write into an `.npz`.
#[derive(Default)]
pub struct NpzOut {
    floats: Vec<(String, Vec<usize>, Vec<f32>)>,
    ints: Vec<(String, Vec<usize>, Vec<i64>)>,
}

impl NpzOut {
    pub fn floats(&mut self, name: &str, shape: &[usize], data: Vec<f32>) -> &mut Self {
        self.floats.push((name.into(), shape.to_vec(), data));
        self
    }

    pub fn ints(&mut self, name: &str, shape: &[usize], data: Vec<i64>) -> &mut Self {
        self.ints.push((name.into(), shape.to_vec(), data));
        self
    }

    /// Writes the archive (to a temporary name, then renamed into place).
    pub fn write(&self, path: &Path) -> Result<()> {
        let tmp = path.with_extension("npz.partial");
        let io = |e: std::io::Error| Error::io(&tmp, e);
        {
            let mut w = npyz::npz::NpzWriter::create(&tmp).map_err(io)?;
            for (name, shape, data) in &self.floats {
                put(&mut w, path, &tmp, name, shape, data)?;
            }
            for (name, shape, data) in &self.ints {
                put(&mut w, path, &tmp, name, shape, data)?;
            }
        }
        std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
    }
}

/// Appends one array `name` to the archive being written at `tmp` (for `path`).
fn put<T, W>(
    w: &mut npyz::npz::NpzWriter<W>,
    path: &Path,
    tmp: &Path,
    name: &str,
    shape: &[usize],
    data: &[T],
) -> Result<()>
where
    T: npyz::AutoSerialize + Copy,
    W: std::io::Write + std::io::Seek,
{
    if shape.iter().product::<usize>() != data.len() {
        return Err(Error::invalid(
            path.display().to_string(),
            name,
            format!("shape {shape:?} does not hold {} values", data.len()),
        ));
    }
    let io = |e: std::io::Error| Error::io(tmp, e);
    let s: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
    let mut a = w
        .array::<T>(
            name,
            // A fixed timestamp: the same arrays give the same bytes.
            npyz::zip::write::FileOptions::default()
                .last_modified_time(npyz::zip::DateTime::default()),
        )
        .map_err(io)?
        .default_dtype()
        .shape(&s)
        .begin_nd()
        .map_err(io)?;
    a.extend(data.iter().copied()).map_err(io)?;
    a.finish().map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let dir = std::env::temp_dir().join(format!("texavatars-npz-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let p = dir.join("a.npz");
        NpzOut::default()
            .floats("x", &[2, 2], vec![1.0, 2.0, 3.0, 4.0])
            .ints("f", &[1, 3], vec![0, 1, 2])
            .write(&p)
            .expect("write");
        let mut z = Npz::open(&p).expect("open");
        assert!(z.has("x") && !z.has("y"));
        assert_eq!(z.floats("x").expect("x").data, vec![1.0, 2.0, 3.0, 4.0]);
        assert_eq!(z.ints("f").expect("f").shape, vec![1, 3]);
        let e = z.floats("y").expect_err("missing").to_string();
        assert!(
            e.contains("a.npz") && e.contains("`y`") && e.contains("missing"),
            "{e}"
        );
        let e = z.floats("f").expect_err("dtype").to_string();
        assert!(e.contains("float"), "{e}");
        let bytes = std::fs::read(&p).expect("read");
        std::fs::write(&p, &bytes[..bytes.len() / 2]).expect("truncate");
        let e = Npz::open(&p)
            .map(|_| ())
            .expect_err("truncated")
            .to_string();
        assert!(e.contains("a.npz"), "{e}");
    }
}
