//! `.npy` arrays of float32 (read and write), through `npyz`.

use std::path::Path;

use npyz::WriterBuilder;

use crate::error::{Error, Result};

/// A float32 array with its shape.
#[derive(Clone, Debug, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

/// Reads a float32 (or float64, converted) `.npy` file.
pub fn read(path: &Path) -> Result<Array> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let what = path.display().to_string();
    let npy = npyz::NpyFile::new(&bytes[..])
        .map_err(|e| Error::invalid(&what, "header", format!("not a .npy file: {e}")))?;
    floats(npy, &what, "data")
}

/// The values of an open `.npy` (float32, or float64 converted) with its shape; errors
/// name `what` and `field`.
pub fn floats<R: std::io::Read>(npy: npyz::NpyFile<R>, what: &str, field: &str) -> Result<Array> {
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let descr = npy.dtype().descr();
    let bad =
        |e: std::io::Error| Error::invalid(what, field, format!("truncated or unreadable: {e}"));
    let data: Vec<f32> = match descr.trim_matches('\'') {
        "<f4" => npy.into_vec::<f32>().map_err(bad)?,
        "<f8" => npy
            .into_vec::<f64>()
            .map_err(bad)?
            .into_iter()
            .map(|v| v as f32)
            .collect(),
        other => {
            return Err(Error::invalid(
                what,
                field,
                format!("expected little-endian float32 or float64, got dtype {other}"),
            ));
        }
    };
    if data.len() != shape.iter().product::<usize>() {
        return Err(Error::invalid(what, field, "truncated"));
    }
    Ok(Array { shape, data })
}

/// Writes a float32 `.npy` file (to a temporary name, then renamed into place).
pub fn write(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(Error::invalid(
            path.display().to_string(),
            "shape",
            format!("{shape:?} does not hold {} values", data.len()),
        ));
    }
    let tmp = path.with_extension("npy.partial");
    let mut bytes = Vec::new();
    {
        let shape64: Vec<u64> = shape.iter().map(|&d| d as u64).collect();
        let mut w = npyz::WriteOptions::<f32>::new()
            .default_dtype()
            .writer(&mut bytes)
            .shape(&shape64)
            .begin_nd()
            .map_err(|e| Error::io(path, e))?;
        w.extend(data.iter().copied())
            .map_err(|e| Error::io(path, e))?;
        w.finish().map_err(|e| Error::io(path, e))?;
    }
    std::fs::write(&tmp, &bytes).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let dir = std::env::temp_dir().join(format!("texavatars-npy-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.npy");
        write(&p, &[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]).unwrap();
        let a = read(&p).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() - 5]).unwrap();
        let e = read(&p).unwrap_err().to_string();
        assert!(e.contains("a.npy"), "{e}");
        assert!(write(&p, &[4], &[1.0]).is_err());
        assert!(
            read(&dir.join("none.npy"))
                .unwrap_err()
                .to_string()
                .contains("none.npy")
        );
    }
}
