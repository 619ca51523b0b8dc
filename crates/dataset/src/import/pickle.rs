//! A reader for the data-only subset of Python's pickle protocol (2–5): numbers, strings,
//! bytes, lists, tuples, dicts and numpy arrays. Pickles can run code, so nothing is ever
//! called: the few numpy names an array's pickle refers to (`_reconstruct`, `ndarray`,
//! `dtype`, `_frombuffer`, `scalar`; `_codecs.encode` and `bytes` for protocol-2 bytes) are recognised
//! by name and interpreted here; any other name, and any opcode outside the subset, is refused
//! with the opcode (or name) and its byte offset.
//!
//! Python shares objects between the places that refer to them; this reader copies them
//! instead (arrays and byte strings cheaply, by reference count). A list or dict changed after
//! the pickle stored it for a later reference cannot be shared that way and is refused if
//! referred to again, which plain data pickles never do; and the copies one pickle may make are
//! bounded ([`MAX_VALUES`]) so a small file cannot expand into an enormous value.

use std::collections::HashMap;
use std::rc::Rc;

mod numpy;

pub use numpy::{Dtype, NdArray};
use numpy::{Global, build, global, reduce};

/// A value from a data-only pickle.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    /// `None`.
    None,
    /// A Python bool.
    Bool(bool),
    /// A Python int that fits in 64 bits.
    Int(i64),
    /// A Python float.
    Float(f64),
    /// A Python str.
    Str(String),
    /// Python bytes (or a bytearray).
    Bytes(Vec<u8>),
    /// A Python list.
    List(Vec<Value>),
    /// A Python tuple.
    Tuple(Vec<Value>),
    /// A Python dict, in the pickle's order.
    Dict(Vec<(Value, Value)>),
    /// A numpy array (or numpy scalar, with an empty shape).
    Array(NdArray),
}

impl Value {
    /// The number as f64, if this is a number.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Float(v) => Some(*v),
            Value::Int(v) => Some(*v as f64),
            _ => None,
        }
    }

    /// The value of `key` in a dict with string keys.
    pub fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Value::Dict(items) => items
                .iter()
                .find(|(k, _)| matches!(k, Value::Str(s) if s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }
}

/// How deeply lists, tuples and dicts may nest. DEFORM's files nest three deep; the limit keeps
/// a hostile file from building a value whose (recursive) drop overflows the stack.
pub const MAX_DEPTH: u32 = 32;

/// Most values (numbers, strings, containers, arrays; an array's elements count as one) a
/// pickle may build, counting every copy of a value referred to again.
pub const MAX_VALUES: usize = 50_000_000;

/// Everything on the pickle machine's stack: the public values and the numpy objects that
/// only exist while an array is being built.
#[derive(Clone, Debug)]
enum Obj {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(Rc<str>),
    Bytes(Rc<[u8]>),
    List(Vec<Obj>),
    Tuple(Vec<Obj>),
    Dict(Vec<(Obj, Obj)>),
    Global(Global),
    Dtype { code: Rc<str>, big_endian: bool },
    PendingArray,
    Array(Rc<NdArray>),
}

/// A stack entry: a mark, or a value with how deeply containers nest in it, how many values
/// it holds, and the memo slots that refer to it.
#[derive(Clone, Debug)]
enum Item {
    Mark,
    Value(Node),
}

#[derive(Clone, Debug)]
struct Node {
    obj: Obj,
    depth: u32,
    size: usize,
    memo: Vec<u32>,
}

impl Node {
    fn leaf(obj: Obj) -> Node {
        Node {
            obj,
            depth: 0,
            size: 1,
            memo: Vec::new(),
        }
    }
}

enum Slot {
    Kept(Node),
    /// A list or dict changed after it was stored.
    Changed,
}

struct Machine<'a> {
    bytes: &'a [u8],
    pos: usize,
    stack: Vec<Item>,
    memo: HashMap<u32, Slot>,
    values: usize,
}

/// Parses a data-only pickle (see the module docs).
pub fn parse(bytes: &[u8]) -> Result<Value, String> {
    if bytes.first() != Some(&0x80) {
        return Err(
            "not a pickle of protocol 2 or later (it does not start with the PROTO opcode 0x80)"
                .into(),
        );
    }
    let mut m = Machine {
        bytes,
        pos: 0,
        stack: Vec::new(),
        memo: HashMap::new(),
        values: 0,
    };
    let node = m.run()?;
    to_value(node.obj)
}

impl Machine<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let at = self.pos;
        let end = at
            .checked_add(n)
            .filter(|e| *e <= self.bytes.len())
            .ok_or_else(|| format!("truncated pickle: needed {n} more bytes at offset {at}"))?;
        self.pos = end;
        Ok(&self.bytes[at..end])
    }

    fn take_len(&mut self, width: usize) -> Result<usize, String> {
        let b = self.take(width)?;
        let mut w = [0u8; 8];
        w[..width].copy_from_slice(b);
        usize::try_from(u64::from_le_bytes(w)).map_err(|_| "length beyond memory".to_string())
    }

    fn take_line(&mut self) -> Result<String, String> {
        let at = self.pos;
        let rest = &self.bytes[at..];
        let n = rest
            .iter()
            .position(|b| *b == b'\n')
            .ok_or_else(|| format!("truncated pickle: unterminated name at offset {at}"))?;
        let line = String::from_utf8(rest[..n].to_vec())
            .map_err(|_| format!("a name that is not UTF-8 at offset {at}"))?;
        self.pos += n + 1;
        Ok(line)
    }

    fn push(&mut self, node: Node) -> Result<(), String> {
        self.values = self.values.saturating_add(node.size);
        if self.values > MAX_VALUES {
            return Err(format!(
                "pickle builds more than {MAX_VALUES} values (counting every copy of a value \
                 referred to again) at offset {}",
                self.pos
            ));
        }
        if node.depth > MAX_DEPTH {
            return Err(format!(
                "pickle nests lists, tuples or dicts more than {MAX_DEPTH} deep at offset {}",
                self.pos
            ));
        }
        self.stack.push(Item::Value(node));
        Ok(())
    }

    fn pop(&mut self, at: usize) -> Result<Node, String> {
        match self.stack.pop() {
            Some(Item::Value(n)) => Ok(n),
            _ => Err(format!(
                "malformed pickle: expected a value on the stack at offset {at}"
            )),
        }
    }

    /// The values above the topmost mark, and the mark removed.
    fn pop_mark(&mut self, at: usize) -> Result<Vec<Node>, String> {
        let mark = self
            .stack
            .iter()
            .rposition(|i| matches!(i, Item::Mark))
            .ok_or_else(|| format!("malformed pickle: no MARK for the opcode at offset {at}"))?;
        let items = self
            .stack
            .drain(mark + 1..)
            .map(|i| match i {
                Item::Value(n) => n,
                Item::Mark => unreachable!("the topmost mark is below these"),
            })
            .collect();
        self.stack.pop();
        Ok(items)
    }

    fn top(&mut self, at: usize) -> Result<&mut Node, String> {
        match self.stack.last_mut() {
            Some(Item::Value(n)) => Ok(n),
            _ => Err(format!(
                "malformed pickle: expected a value on the stack at offset {at}"
            )),
        }
    }

    /// Records that the value on top changed: memo slots holding a list or dict can no longer
    /// be copied; others take the new value.
    fn changed(&mut self, at: usize) -> Result<(), String> {
        let top = self.top(at)?;
        if top.depth > MAX_DEPTH {
            return Err(format!(
                "pickle nests lists, tuples or dicts more than {MAX_DEPTH} deep at offset {at}"
            ));
        }
        if top.memo.is_empty() {
            return Ok(());
        }
        let kept = match top.obj {
            Obj::List(_) | Obj::Dict(_) => None,
            _ => Some(top.clone()),
        };
        for slot in top.memo.clone() {
            let s = kept.clone().map_or(Slot::Changed, Slot::Kept);
            self.memo.insert(slot, s);
        }
        Ok(())
    }

    fn memoize(&mut self, slot: u32, at: usize) -> Result<(), String> {
        let node = self.top(at)?;
        node.memo.push(slot);
        let kept = node.clone();
        self.memo.insert(slot, Slot::Kept(kept));
        Ok(())
    }

    fn recall(&mut self, slot: u32, at: usize) -> Result<(), String> {
        let node = match self.memo.get(&slot) {
            Some(Slot::Kept(n)) => n.clone(),
            Some(Slot::Changed) => {
                return Err(format!(
                    "pickle refers again (offset {at}) to a list or dict it changed after \
                     storing it; only plain data pickles are read"
                ));
            }
            None => {
                return Err(format!(
                    "pickle refers to memo slot {slot} it never stored (offset {at})"
                ));
            }
        };
        // Every slot this node is stored in, so a later change reaches them too.
        self.push(node)
    }

    fn run(&mut self) -> Result<Node, String> {
        loop {
            let at = self.pos;
            let op = self.take(1)?[0];
            match op {
                0x80 => {
                    let proto = self.take(1)?[0];
                    if !(2..=5).contains(&proto) {
                        return Err(format!("unsupported pickle protocol {proto}"));
                    }
                }
                0x95 => drop(self.take(8)?), // FRAME: a length hint only
                b'.' => {
                    let node = self.pop(at)?;
                    if !self.stack.is_empty() {
                        return Err(format!("pickle stack not empty at STOP (offset {at})"));
                    }
                    return Ok(node);
                }
                b'(' => self.stack.push(Item::Mark),
                b'N' => self.push(Node::leaf(Obj::None))?,
                0x88 => self.push(Node::leaf(Obj::Bool(true)))?,
                0x89 => self.push(Node::leaf(Obj::Bool(false)))?,
                b'K' => {
                    let v = self.take(1)?[0];
                    self.push(Node::leaf(Obj::Int(i64::from(v))))?;
                }
                b'M' => {
                    let b = self.take(2)?;
                    let v = u16::from_le_bytes([b[0], b[1]]);
                    self.push(Node::leaf(Obj::Int(i64::from(v))))?;
                }
                b'J' => {
                    let b = self.take(4)?;
                    let v = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    self.push(Node::leaf(Obj::Int(i64::from(v))))?;
                }
                0x8a => {
                    // LONG1: little-endian two's complement of n bytes.
                    let n = self.take(1)?[0] as usize;
                    if n > 8 {
                        return Err(format!("an integer wider than 64 bits at offset {at}"));
                    }
                    let b = self.take(n)?;
                    let v = if n == 0 {
                        0
                    } else {
                        let mut w = [0u8; 8];
                        w[..n].copy_from_slice(b);
                        let shift = 64 - 8 * n as u32;
                        (i64::from_le_bytes(w) << shift) >> shift
                    };
                    self.push(Node::leaf(Obj::Int(v)))?;
                }
                b'G' => {
                    let b = self.take(8)?;
                    let v = f64::from_be_bytes(b.try_into().map_err(|_| "bad float")?);
                    self.push(Node::leaf(Obj::Float(v)))?;
                }
                0x8c | b'X' | 0x8d => {
                    let width = match op {
                        0x8c => 1,
                        b'X' => 4,
                        _ => 8,
                    };
                    let n = self.take_len(width)?;
                    let s = std::str::from_utf8(self.take(n)?)
                        .map_err(|_| format!("a string that is not UTF-8 at offset {at}"))?;
                    let s: Rc<str> = Rc::from(s);
                    self.push(Node::leaf(Obj::Str(s)))?;
                }
                b'C' | b'B' | 0x8e | 0x96 | b'U' | b'T' => {
                    // Bytes, a bytearray, or a Python 2 str (protocol 2).
                    let width = match op {
                        b'C' | b'U' => 1,
                        b'B' | b'T' => 4,
                        _ => 8,
                    };
                    let n = self.take_len(width)?;
                    let b: Rc<[u8]> = Rc::from(self.take(n)?);
                    self.push(Node::leaf(Obj::Bytes(b)))?;
                }
                b']' => self.push(Node {
                    depth: 1,
                    ..Node::leaf(Obj::List(Vec::new()))
                })?,
                b'}' => self.push(Node {
                    depth: 1,
                    ..Node::leaf(Obj::Dict(Vec::new()))
                })?,
                b')' => self.push(Node {
                    depth: 1,
                    ..Node::leaf(Obj::Tuple(Vec::new()))
                })?,
                b'l' | b't' | b'd' => {
                    let items = self.pop_mark(at)?;
                    let node = match op {
                        b'l' => container(items, Obj::List),
                        b't' => container(items, Obj::Tuple),
                        _ => dict(items, at)?,
                    };
                    self.push(node)?;
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n
                        || self.stack[self.stack.len() - n..]
                            .iter()
                            .any(|i| matches!(i, Item::Mark))
                    {
                        return Err(format!(
                            "malformed pickle: TUPLE{n} without {n} values at offset {at}"
                        ));
                    }
                    let items = self
                        .stack
                        .split_off(self.stack.len() - n)
                        .into_iter()
                        .filter_map(|i| match i {
                            Item::Value(v) => Some(v),
                            Item::Mark => None,
                        })
                        .collect();
                    self.push(container(items, Obj::Tuple))?;
                }
                b'a' | b'e' => {
                    let items = if op == b'a' {
                        vec![self.pop(at)?]
                    } else {
                        self.pop_mark(at)?
                    };
                    let top = self.top(at)?;
                    let Obj::List(list) = &mut top.obj else {
                        return Err(format!(
                            "malformed pickle: append to a non-list at offset {at}"
                        ));
                    };
                    for n in items {
                        top.depth = top.depth.max(n.depth + 1);
                        top.size += n.size;
                        list.push(n.obj);
                    }
                    self.changed(at)?;
                }
                b's' | b'u' => {
                    let items = if op == b's' {
                        let v = self.pop(at)?;
                        let k = self.pop(at)?;
                        vec![k, v]
                    } else {
                        self.pop_mark(at)?
                    };
                    if !items.len().is_multiple_of(2) {
                        return Err(format!(
                            "malformed pickle: a key without a value at offset {at}"
                        ));
                    }
                    let top = self.top(at)?;
                    let Obj::Dict(entries) = &mut top.obj else {
                        return Err(format!(
                            "malformed pickle: set an item of a non-dict at offset {at}"
                        ));
                    };
                    let mut it = items.into_iter();
                    while let (Some(k), Some(v)) = (it.next(), it.next()) {
                        top.depth = top.depth.max(k.depth.max(v.depth) + 1);
                        top.size += k.size + v.size;
                        entries.push((k.obj, v.obj));
                    }
                    self.changed(at)?;
                }
                0x94 => {
                    let slot = u32::try_from(self.memo.len())
                        .map_err(|_| "too many memo entries".to_string())?;
                    self.memoize(slot, at)?;
                }
                b'q' | b'r' | b'h' | b'j' => {
                    // BINPUT and LONG_BINPUT store the top in a memo slot, BINGET and
                    // LONG_BINGET push a slot's value again.
                    let width = if matches!(op, b'q' | b'h') { 1 } else { 4 };
                    let slot = u32::try_from(self.take_len(width)?)
                        .map_err(|_| "a memo slot beyond 32 bits".to_string())?;
                    if matches!(op, b'q' | b'r') {
                        self.memoize(slot, at)?;
                    } else {
                        self.recall(slot, at)?;
                    }
                }
                b'c' => {
                    let module = self.take_line()?;
                    let name = self.take_line()?;
                    self.push(Node::leaf(global(&module, &name, at)?))?;
                }
                0x93 => {
                    let name = self.pop(at)?;
                    let module = self.pop(at)?;
                    let (Obj::Str(module), Obj::Str(name)) = (module.obj, name.obj) else {
                        return Err(format!(
                            "malformed pickle: STACK_GLOBAL without two names at offset {at}"
                        ));
                    };
                    self.push(Node::leaf(global(&module, &name, at)?))?;
                }
                b'R' => {
                    let args = self.pop(at)?;
                    let callable = self.pop(at)?;
                    let Obj::Global(g) = callable.obj else {
                        return Err(format!(
                            "malformed pickle: REDUCE of a value that is not a callable name at offset {at}"
                        ));
                    };
                    self.push(Node::leaf(reduce(g, args.obj, at)?))?;
                }
                b'b' => {
                    let state = self.pop(at)?;
                    let top = self.top(at)?;
                    let obj = std::mem::replace(&mut top.obj, Obj::None);
                    top.obj = build(obj, state.obj, at)?;
                    self.changed(at)?;
                }
                other => {
                    return Err(format!(
                        "unsupported pickle opcode 0x{other:02x} at offset {at} (only numbers, \
                         strings, lists, tuples, dicts and numpy arrays are read)"
                    ));
                }
            }
        }
    }
}

fn container(items: Vec<Node>, make: fn(Vec<Obj>) -> Obj) -> Node {
    let depth = 1 + items.iter().map(|n| n.depth).max().unwrap_or(0);
    let size = 1 + items.iter().map(|n| n.size).sum::<usize>();
    Node {
        obj: make(items.into_iter().map(|n| n.obj).collect()),
        depth,
        size,
        memo: Vec::new(),
    }
}

fn dict(items: Vec<Node>, at: usize) -> Result<Node, String> {
    if !items.len().is_multiple_of(2) {
        return Err(format!(
            "malformed pickle: a key without a value at offset {at}"
        ));
    }
    let depth = 1 + items.iter().map(|n| n.depth).max().unwrap_or(0);
    let size = 1 + items.iter().map(|n| n.size).sum::<usize>();
    let mut it = items.into_iter();
    let mut entries = Vec::new();
    while let (Some(k), Some(v)) = (it.next(), it.next()) {
        entries.push((k.obj, v.obj));
    }
    Ok(Node {
        obj: Obj::Dict(entries),
        depth,
        size,
        memo: Vec::new(),
    })
}

fn to_value(obj: Obj) -> Result<Value, String> {
    let all = |v: Vec<Obj>| v.into_iter().map(to_value).collect::<Result<Vec<_>, _>>();
    Ok(match obj {
        Obj::None => Value::None,
        Obj::Bool(b) => Value::Bool(b),
        Obj::Int(i) => Value::Int(i),
        Obj::Float(f) => Value::Float(f),
        Obj::Str(s) => Value::Str(s.to_string()),
        Obj::Bytes(b) => Value::Bytes(b.to_vec()),
        Obj::List(v) => Value::List(all(v)?),
        Obj::Tuple(v) => Value::Tuple(all(v)?),
        Obj::Dict(v) => Value::Dict(
            v.into_iter()
                .map(|(k, v)| Ok((to_value(k)?, to_value(v)?)))
                .collect::<Result<Vec<_>, String>>()?,
        ),
        Obj::Array(a) => Value::Array(Rc::unwrap_or_clone(a)),
        Obj::Global(_) | Obj::Dtype { .. } | Obj::PendingArray => {
            return Err("pickle holds a numpy type outside an array".into());
        }
    })
}

#[cfg(test)]
mod tests;
