//! `.npz` archives (numpy's zip of `.npy` arrays), through `npyz`: float arrays (f4/f8) and
//! integer arrays (any width and sign) by name, with errors naming the file and the array.

use std::io::{Cursor, Read};
use std::path::{Path, PathBuf};

use npyz::WriterBuilder;
use npyz::npz::NpzArchive;

use crate::error::{Error, Result};
use crate::io::npy::{self, Array, Header};

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

    /// The bytes of the member `name.npy` and its parsed header. The member is checked
    /// before it is decompressed (`zip` panics on some hostile entries: an AES extra field
    /// without the encryption flag, an unknown compression method), its size against the
    /// header's shape before the data is read, and no more than the header and the shape
    /// need is read (whatever the member decompresses to).
    fn member(&mut self, name: &str) -> Result<(Vec<u8>, Header)> {
        use npyz::zip::CompressionMethod;
        let what = self.what();
        let err = |why: String| Error::invalid(&what, name, why);
        let file_name = format!("{name}.npy");
        let zip = self.archive.zip_archive();
        if !zip.file_names().any(|n| n == file_name) {
            return Err(err("missing from the archive".into()));
        }
        // The last entry of that name, as `zip`'s own lookup takes.
        let index = (0..zip.len())
            .rev()
            .find(|&i| {
                zip.by_index_raw(i)
                    .is_ok_and(|f| f.name() == file_name.as_str())
            })
            .ok_or_else(|| err("unreadable: its local header is damaged".into()))?;
        let declared = {
            let f = zip
                .by_index_raw(index)
                .map_err(|e| err(format!("unreadable: {e}")))?;
            let known = matches!(
                f.compression(),
                CompressionMethod::Stored
                    | CompressionMethod::Deflated
                    | CompressionMethod::Bzip2
                    | CompressionMethod::Zstd
            );
            if !known {
                return Err(err(format!(
                    "unsupported compression method {:?}",
                    f.compression()
                )));
            }
            if extra_field_ids(f.extra_data()).any(|id| id == AES_EXTRA_FIELD) {
                return Err(err("encrypted members are not supported".into()));
            }
            f.size()
        };
        let mut f = zip
            .by_index(index)
            .map_err(|e| err(format!("unreadable: {e}")))?;
        let read = |f: &mut dyn Read, bytes: &mut Vec<u8>, n: usize| {
            (&mut *f)
                .take(n.saturating_sub(bytes.len()) as u64)
                .read_to_end(bytes)
                .map_err(|e| err(format!("truncated or unreadable: {e}")))
        };
        // The header first (its 10 or 12 leading bytes give its length), then the data.
        let mut bytes = Vec::new();
        read(&mut f, &mut bytes, 12)?;
        let (start, len) = npy::prelude(&bytes, &what, name)?;
        read(&mut f, &mut bytes, start + len)?;
        let header = Header::parse(&bytes, &what, name)?;
        let size = item_size(&header.descr).unwrap_or(0);
        let need = header.file_len(size).ok_or_else(|| {
            err(format!(
                "shape {:?} is too large for any file",
                header.shape
            ))
        })?;
        if need as u64 > declared {
            return Err(err(format!(
                "truncated: shape {:?} of {} needs {need} bytes, the member holds {declared}",
                header.shape, header.descr
            )));
        }
        read(&mut f, &mut bytes, need)?;
        Ok((bytes, header))
    }

    /// A float array (float32, or float64 converted), all values finite.
    pub fn floats(&mut self, name: &str) -> Result<Array> {
        let what = self.what();
        let (bytes, _) = self.member(name)?;
        let Array { shape, data } = npy::parse(&bytes, &what, name)?;
        if let Some(i) = data.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                &what,
                name,
                format!("value {i} is not finite"),
            ));
        }
        Ok(Array { shape, data })
    }

    /// An integer array of any width and sign (`<i4`, `<i8`, `<u4`, `<u8`; `u8` values
    /// above `i64::MAX` read as -1).
    pub fn ints(&mut self, name: &str) -> Result<IntArray> {
        let what = self.what();
        let (bytes, h) = self.member(name)?;
        let w4 = |c: &[u8]| [c[0], c[1], c[2], c[3]];
        let w8 = |c: &[u8]| [c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]];
        let data: Vec<i64> = match h.descr.as_str() {
            "<i8" => h.values(&bytes, 8, &what, name, |c| i64::from_le_bytes(w8(c)))?,
            "<i4" => h.values(&bytes, 4, &what, name, |c| {
                i64::from(i32::from_le_bytes(w4(c)))
            })?,
            "<u4" => h.values(&bytes, 4, &what, name, |c| {
                i64::from(u32::from_le_bytes(w4(c)))
            })?,
            "<u8" => h.values(&bytes, 8, &what, name, |c| {
                i64::try_from(u64::from_le_bytes(w8(c))).unwrap_or(-1)
            })?,
            other => {
                return Err(Error::invalid(
                    &what,
                    name,
                    format!("expected an integer dtype, got {other}"),
                ));
            }
        };
        Ok(IntArray {
            shape: h.shape,
            data,
        })
    }
}

/// The header id of WinZip's AES extra field.
const AES_EXTRA_FIELD: u16 = 0x9901;

/// The ids of a zip entry's extra fields (a malformed tail ends the list).
fn extra_field_ids(extra: &[u8]) -> impl Iterator<Item = u16> + '_ {
    let mut rest = extra;
    std::iter::from_fn(move || {
        let (head, tail) = rest.split_at_checked(4)?;
        let id = u16::from_le_bytes([head[0], head[1]]);
        let len = usize::from(u16::from_le_bytes([head[2], head[3]]));
        rest = tail.get(len..).unwrap_or(&[]);
        Some(id)
    })
}

/// Bytes per element of the dtypes read here (0 for others: refused after the header).
fn item_size(descr: &str) -> Option<usize> {
    match descr {
        "<f4" | "<i4" | "<u4" => Some(4),
        "<f8" | "<i8" | "<u8" => Some(8),
        _ => None,
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
