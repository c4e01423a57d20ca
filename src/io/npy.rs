//! `.npy` arrays: float32 written through `npyz`; read by this module's own parser of the
//! header numpy writes (`{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }`),
//! which checks the declared shape against the bytes present before anything is allocated
//! and refuses what it does not understand with an error, never a panic (a hostile header
//! could otherwise overflow the element count, nest deep enough to exhaust the stack, or
//! ask for gigabytes).

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
    parse(&bytes, &path.display().to_string(), "data")
}

/// Parses a `.npy` held in memory: float32, or float64 converted, in C order (a Fortran
/// order file is reordered); errors name `what` and `field`.
pub fn parse(bytes: &[u8], what: &str, field: &str) -> Result<Array> {
    let h = Header::parse(bytes, what, field)?;
    let data = match h.descr.as_str() {
        "<f4" => h.values(bytes, 4, what, field, |c| {
            f32::from_le_bytes([c[0], c[1], c[2], c[3]])
        })?,
        "<f8" => h.values(bytes, 8, what, field, |c| {
            f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32
        })?,
        other => {
            return Err(Error::invalid(
                what,
                field,
                format!("expected little-endian float32 or float64, got dtype {other}"),
            ));
        }
    };
    Ok(Array {
        shape: h.shape,
        data,
    })
}

/// The longest header text read. numpy writes about 120 bytes for a plain array and its own
/// reader refuses more than 10,000 by default.
pub const MAX_HEADER: usize = 1 << 16;

/// A checked `.npy` header: its element count fits `usize` and the header text is whole.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Header {
    /// The dtype string, e.g. `<f4`.
    pub descr: String,
    /// Whether the data is stored column-major.
    pub fortran: bool,
    /// The shape.
    pub shape: Vec<usize>,
    /// Elements: the product of `shape`.
    pub count: usize,
    /// Offset of the data in the file.
    pub data_offset: usize,
}

/// Where the header text of a `.npy` starts and how long it is, from the first 10 (version
/// 1) or 12 (versions 2 and 3) bytes.
pub(crate) fn prelude(bytes: &[u8], what: &str, field: &str) -> Result<(usize, usize)> {
    let bad = |why: String| Error::invalid(what, field, format!("not a .npy file: {why}"));
    if bytes.len() < 10 || !bytes.starts_with(b"\x93NUMPY") {
        return Err(bad("no `\\x93NUMPY` magic".into()));
    }
    let (start, len) = match (bytes[6], bytes[7]) {
        (1, 0) => (10, usize::from(u16::from_le_bytes([bytes[8], bytes[9]]))),
        (2 | 3, 0) => match bytes.get(8..12) {
            Some(b) => (12, u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize),
            None => return Err(bad("truncated header".into())),
        },
        (a, b) => return Err(bad(format!("unsupported format version {a}.{b}"))),
    };
    if len > MAX_HEADER {
        return Err(bad(format!(
            "header of {len} bytes (at most {MAX_HEADER} are read)"
        )));
    }
    Ok((start, len))
}

impl Header {
    /// Parses the header at the start of `bytes`, which must hold all of it (the data may
    /// follow).
    pub fn parse(bytes: &[u8], what: &str, field: &str) -> Result<Header> {
        let (start, len) = prelude(bytes, what, field)?;
        let bad = |why: String| Error::invalid(what, field, format!("bad .npy header: {why}"));
        let text = bytes.get(start..start + len).ok_or_else(|| {
            bad(format!(
                "truncated: {len} bytes declared, {} present",
                bytes.len().saturating_sub(start)
            ))
        })?;
        let text = std::str::from_utf8(text).map_err(|_| bad("not text".into()))?;
        let (mut descr, mut fortran, mut shape) = (None, None, None);
        for (key, value) in parse_dict(text).map_err(bad)? {
            let slot_taken = match (key.as_str(), value) {
                ("descr", Literal::Str(s)) => descr.replace(s).is_some(),
                ("fortran_order", Literal::Bool(b)) => fortran.replace(b).is_some(),
                ("shape", Literal::Ints(dims)) => shape.replace(dims).is_some(),
                ("descr" | "fortran_order" | "shape", v) => {
                    return Err(bad(format!("`{key}` has the wrong type ({})", v.kind())));
                }
                _ => return Err(bad(format!("unexpected key `{key}`"))),
            };
            if slot_taken {
                return Err(bad(format!("key `{key}` appears twice")));
            }
        }
        let missing = |k: &str| bad(format!("key `{k}` is missing"));
        let descr = descr.ok_or_else(|| missing("descr"))?;
        let fortran = fortran.ok_or_else(|| missing("fortran_order"))?;
        let dims = shape.ok_or_else(|| missing("shape"))?;
        let mut shape = Vec::with_capacity(dims.len());
        let mut count = 1usize;
        for d in dims {
            let d = usize::try_from(d)
                .ok()
                .ok_or_else(|| bad(format!("dimension {d} is too large")))?;
            count = count
                .checked_mul(d)
                .ok_or_else(|| bad(format!("shape {:?}.. has too many elements", shape)))?;
            shape.push(d);
        }
        Ok(Header {
            descr,
            fortran,
            shape,
            count,
            data_offset: start + len,
        })
    }

    /// Bytes of the whole file (header and data) for items of `size` bytes; `None` when that
    /// does not fit `usize`.
    pub fn file_len(&self, size: usize) -> Option<usize> {
        self.count
            .checked_mul(size)
            .and_then(|n| n.checked_add(self.data_offset))
    }

    /// The data of `bytes` (the whole file) as `T`s of `size` bytes each, decoded by `f`, in
    /// C order. An error when the file is shorter than the shape needs (bytes after the data
    /// are ignored).
    pub fn values<T: Copy>(
        &self,
        bytes: &[u8],
        size: usize,
        what: &str,
        field: &str,
        f: impl Fn(&[u8]) -> T,
    ) -> Result<Vec<T>> {
        let end = self.file_len(size).ok_or_else(|| {
            Error::invalid(
                what,
                field,
                format!("shape {:?} is too large for any file", self.shape),
            )
        })?;
        let data = bytes.get(self.data_offset..end).ok_or_else(|| {
            Error::invalid(
                what,
                field,
                format!(
                    "truncated: shape {:?} of {} needs {} bytes of data, found {}",
                    self.shape,
                    self.descr,
                    end - self.data_offset,
                    bytes.len().saturating_sub(self.data_offset)
                ),
            )
        })?;
        let values: Vec<T> = data.chunks_exact(size.max(1)).map(f).collect();
        Ok(if self.fortran && self.shape.len() > 1 {
            fortran_to_c(&values, &self.shape)
        } else {
            values
        })
    }
}

/// A value of the header dict.
enum Literal {
    Str(String),
    Bool(bool),
    Ints(Vec<u64>),
}

impl Literal {
    fn kind(&self) -> &'static str {
        match self {
            Literal::Str(_) => "a string",
            Literal::Bool(_) => "a bool",
            Literal::Ints(_) => "a tuple",
        }
    }
}

/// The Python dict literal of a `.npy` header, as numpy writes it: string keys; values that
/// are strings (no escapes), `True`/`False`, or tuples or lists of non-negative decimal
/// integers. Anything else (structured dtypes among them) is refused. No recursion.
fn parse_dict(text: &str) -> std::result::Result<Vec<(String, Literal)>, String> {
    let mut p = Cursor {
        s: text.as_bytes(),
        i: 0,
    };
    if !p.eat(b'{') {
        return Err("expected a dict `{...}`".into());
    }
    let mut out = Vec::new();
    while !p.eat(b'}') {
        let key = p.string()?;
        if !p.eat(b':') {
            return Err(format!("expected `:` after `{key}`"));
        }
        let value = p.value()?;
        out.push((key, value));
        if !p.eat(b',') {
            if !p.eat(b'}') {
                return Err("expected `,` or `}`".into());
            }
            break;
        }
    }
    p.ws();
    if p.i != p.s.len() {
        return Err("text after the dict".into());
    }
    Ok(out)
}

struct Cursor<'t> {
    s: &'t [u8],
    i: usize,
}

impl Cursor<'_> {
    fn ws(&mut self) {
        while matches!(self.s.get(self.i), Some(b' ' | b'\t' | b'\n' | b'\r')) {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        self.ws();
        let hit = self.s.get(self.i) == Some(&c);
        if hit {
            self.i += 1;
        }
        hit
    }

    fn string(&mut self) -> std::result::Result<String, String> {
        self.ws();
        let q = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err("expected a string".into()),
        };
        let start = self.i + 1;
        let len = self.s[start..]
            .iter()
            .position(|&c| c == q || c == b'\\' || c == b'\n')
            .filter(|&n| self.s[start + n] == q)
            .ok_or("unterminated string (or an escape, which is not supported)")?;
        self.i = start + len + 1;
        Ok(String::from_utf8_lossy(&self.s[start..start + len]).into_owned())
    }

    fn value(&mut self) -> std::result::Result<Literal, String> {
        self.ws();
        let rest = &self.s[self.i..];
        let close = match rest.first() {
            Some(b'\'' | b'"') => return self.string().map(Literal::Str),
            Some(b'(') => b')',
            Some(b'[') => b']',
            _ if rest.starts_with(b"True") => return self.word(4, Literal::Bool(true)),
            _ if rest.starts_with(b"False") => return self.word(5, Literal::Bool(false)),
            _ => return Err("unsupported value (strings, bools and int tuples only)".into()),
        };
        self.i += 1;
        let mut dims = Vec::new();
        loop {
            if self.eat(close) {
                return Ok(Literal::Ints(dims));
            }
            dims.push(self.int()?);
            if !self.eat(b',') {
                if self.eat(close) {
                    return Ok(Literal::Ints(dims));
                }
                return Err("expected `,` or the closing bracket in the shape".into());
            }
        }
    }

    fn word(&mut self, n: usize, v: Literal) -> std::result::Result<Literal, String> {
        self.i += n;
        Ok(v)
    }

    fn int(&mut self) -> std::result::Result<u64, String> {
        self.ws();
        let start = self.i;
        while self.s.get(self.i).is_some_and(u8::is_ascii_digit) {
            self.i += 1;
        }
        let digits = &self.s[start..self.i];
        if digits.is_empty() {
            return Err(
                "expected a non-negative decimal integer in a tuple (values are \
                        strings, True/False or integer tuples: structured dtypes are not \
                        supported)"
                    .into(),
            );
        }
        std::str::from_utf8(digits)
            .ok()
            .and_then(|d| d.parse().ok())
            .ok_or_else(|| "a dimension does not fit 64 bits".into())
    }
}

/// Reorders column-major (Fortran) `values` of `shape` to row-major. `values` holds the
/// product of `shape` elements.
pub(crate) fn fortran_to_c<T: Copy>(values: &[T], shape: &[usize]) -> Vec<T> {
    if values.is_empty() {
        return Vec::new();
    }
    let nd = shape.len();
    let mut fstride = vec![1usize; nd];
    for k in 1..nd {
        fstride[k] = fstride[k - 1] * shape[k - 1];
    }
    let mut idx = vec![0usize; nd];
    let mut out = Vec::with_capacity(values.len());
    for _ in 0..values.len() {
        out.push(values[idx.iter().zip(&fstride).map(|(i, s)| i * s).sum::<usize>()]);
        // Advance the row-major index (last axis fastest).
        for k in (0..nd).rev() {
            idx[k] += 1;
            if idx[k] < shape[k] {
                break;
            }
            idx[k] = 0;
        }
    }
    out
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

    /// A `.npy` with header text `dict` (version 1.0) and `data`.
    fn npy(dict: &str, data: &[u8]) -> Vec<u8> {
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((dict.len() as u16).to_le_bytes());
        b.extend(dict.as_bytes());
        b.extend(data);
        b
    }

    #[test]
    fn fortran_order_is_reordered_and_f8_converted() {
        // [[1, 2, 3], [4, 5, 6]] stored column-major: 1 4 2 5 3 6.
        let data: Vec<u8> = [1.0f64, 4.0, 2.0, 5.0, 3.0, 6.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let b = npy(
            "{'descr': '<f8', 'fortran_order': True, 'shape': (2, 3), }      \n",
            &data,
        );
        let a = parse(&b, "f.npy", "data").unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        // A scalar (shape ()) holds one value; a list shape is accepted like a tuple.
        let b = npy(
            "{\"descr\": \"<f4\", \"fortran_order\": False, \"shape\": []}",
            &[0, 0, 128, 63],
        );
        assert_eq!(parse(&b, "s.npy", "data").unwrap().data, vec![1.0]);
    }

    #[test]
    fn hostile_headers_are_errors() {
        let cases: &[(&str, &str)] = &[
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (4294967296, 4294967296), }",
                "too many",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (18446744073709551616,), }",
                "64 bits",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1000000000000,), }",
                "truncated",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (-1,), }",
                "non-negative",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': ((((1,),),),), }",
                "non-negative",
            ),
            (
                "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (1,), }",
                "structured dtypes are not supported",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), 'x': 1}",
                "unsupported",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), 'x': ''}",
                "unexpected key",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1,), 'shape': (1,)}",
                "twice",
            ),
            ("{'descr': '<f4', 'shape': (1,)}", "missing"),
            (
                "{'descr': '<f4', 'fortran_order': 0, 'shape': (1,)}",
                "unsupported",
            ),
            (
                "{'descr': '<i4', 'fortran_order': False, 'shape': (1,)}",
                "float32",
            ),
            (
                "{'descr': '<f4\\', 'fortran_order': False, 'shape': (1,)}",
                "escape",
            ),
            (
                "{'descr': '<f4', 'fortran_order': False, 'shape': (1,)} x",
                "after the dict",
            ),
        ];
        for (dict, why) in cases {
            let e = parse(&npy(dict, &[0; 8]), "h.npy", "data")
                .unwrap_err()
                .to_string();
            assert!(e.contains("h.npy") && e.contains(why), "{dict}: {e}");
        }
        let deep = format!("{{'shape': {}1{}}}", "(".repeat(30000), ")".repeat(30000));
        assert!(parse(&npy(&deep, &[]), "d.npy", "data").is_err());
        // A header length beyond the file, or beyond the cap.
        let mut b = npy("{}", &[]);
        b[8] = 0xff;
        assert!(
            parse(&b, "l.npy", "data")
                .unwrap_err()
                .to_string()
                .contains("truncated")
        );
        let mut b = b"\x93NUMPY\x02\x00".to_vec();
        b.extend(u32::MAX.to_le_bytes());
        assert!(
            parse(&b, "l.npy", "data")
                .unwrap_err()
                .to_string()
                .contains("at most")
        );
    }
}
