//! A reader for the small subset of Python's pickle protocol that plain nested lists of numbers
//! use (protocols 2–5). Anything else is refused with the offending opcode and byte offset:
//! pickles can run code, so an importer must never try to be general.

/// A value from a plain pickle: a number or a list.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    /// A Python float.
    Float(f64),
    /// A Python int that fits in 64 bits.
    Int(i64),
    /// A Python list.
    List(Vec<Value>),
}

impl Value {
    /// The number as f64, if this is a number.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Float(v) => Some(*v),
            Value::Int(v) => Some(*v as f64),
            Value::List(_) => None,
        }
    }
}

/// How deeply lists may nest. DEFORM's files nest three deep; the limit keeps a hostile file
/// from building a value whose (recursive) drop overflows the stack.
pub const MAX_DEPTH: u32 = 32;

enum Item {
    Mark,
    /// A value and how deeply lists nest in it (a number 0, an empty list 1).
    Value(Value, u32),
}

/// Parses a pickle of nested lists of floats and ints.
pub fn parse(bytes: &[u8]) -> Result<Value, String> {
    let mut pos = 0usize;
    let mut stack: Vec<Item> = Vec::new();
    let take = |pos: &mut usize, n: usize| -> Result<&[u8], String> {
        let end = pos
            .checked_add(n)
            .filter(|e| *e <= bytes.len())
            .ok_or_else(|| format!("truncated pickle: needed {n} more bytes at offset {}", *pos))?;
        let s = &bytes[*pos..end];
        *pos = end;
        Ok(s)
    };
    loop {
        let at = pos;
        let op = *take(&mut pos, 1)?.first().unwrap_or(&0);
        match op {
            0x80 => {
                let proto = take(&mut pos, 1)?[0];
                if !(2..=5).contains(&proto) {
                    return Err(format!("unsupported pickle protocol {proto}"));
                }
            }
            0x95 => {
                take(&mut pos, 8)?; // FRAME: length hint only
            }
            b']' => stack.push(Item::Value(Value::List(Vec::new()), 1)),
            b'(' => stack.push(Item::Mark),
            b'G' => {
                let b = take(&mut pos, 8)?;
                let v = f64::from_be_bytes(b.try_into().map_err(|_| "bad float")?);
                stack.push(Item::Value(Value::Float(v), 0));
            }
            b'K' => {
                let v = take(&mut pos, 1)?[0];
                stack.push(Item::Value(Value::Int(v as i64), 0));
            }
            b'M' => {
                let b = take(&mut pos, 2)?;
                stack.push(Item::Value(
                    Value::Int(u16::from_le_bytes([b[0], b[1]]) as i64),
                    0,
                ));
            }
            b'J' => {
                let b = take(&mut pos, 4)?;
                let v = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                stack.push(Item::Value(Value::Int(v as i64), 0));
            }
            0x94 => {}                        // MEMOIZE: we never read memo entries back
            b'q' => drop(take(&mut pos, 1)?), // BINPUT
            b'r' => drop(take(&mut pos, 4)?), // LONG_BINPUT
            b'a' => {
                let (v, depth) = pop_value(&mut stack, at)?;
                list_on_top(&mut stack, at, depth)?.push(v);
            }
            b'e' => {
                let mark = stack
                    .iter()
                    .rposition(|i| matches!(i, Item::Mark))
                    .ok_or_else(|| format!("APPENDS without MARK at offset {at}"))?;
                let mut deepest = 0;
                let items: Vec<Value> = stack
                    .drain(mark + 1..)
                    .map(|i| match i {
                        Item::Value(v, depth) => {
                            deepest = deepest.max(depth);
                            Ok(v)
                        }
                        Item::Mark => Err(format!("nested MARK at offset {at}")),
                    })
                    .collect::<Result<_, _>>()?;
                stack.pop(); // the mark
                list_on_top(&mut stack, at, deepest)?.extend(items);
            }
            b'.' => {
                let (v, _) = pop_value(&mut stack, at)?;
                if !stack.is_empty() {
                    return Err(format!("pickle stack not empty at STOP (offset {at})"));
                }
                return Ok(v);
            }
            other => {
                return Err(format!(
                    "unsupported pickle opcode 0x{other:02x} at offset {at} (only plain lists of numbers are accepted)"
                ));
            }
        }
    }
}

fn pop_value(stack: &mut Vec<Item>, at: usize) -> Result<(Value, u32), String> {
    match stack.pop() {
        Some(Item::Value(v, depth)) => Ok((v, depth)),
        _ => Err(format!(
            "malformed pickle: expected a value on the stack at offset {at}"
        )),
    }
}

/// The list on top of the stack, about to take values nesting `depth` deep.
fn list_on_top(stack: &mut [Item], at: usize, depth: u32) -> Result<&mut Vec<Value>, String> {
    match stack.last_mut() {
        Some(Item::Value(Value::List(l), d)) => {
            *d = (*d).max(depth + 1);
            if *d > MAX_DEPTH {
                return Err(format!(
                    "pickle nests lists more than {MAX_DEPTH} deep at offset {at}"
                ));
            }
            Ok(l)
        }
        _ => Err(format!(
            "malformed pickle: append to a non-list at offset {at}"
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Bytes written by CPython 3.11 `pickle.dumps([[1.5, 2.0], [3]], protocol=4)`.
    const NESTED: &[u8] = b"\x80\x04\x95\x20\x00\x00\x00\x00\x00\x00\x00]\x94(]\x94(G?\xf8\x00\x00\x00\x00\x00\x00G@\x00\x00\x00\x00\x00\x00\x00e]\x94K\x03ae.";

    #[test]
    fn parses_nested_lists() {
        let v = parse(NESTED).unwrap();
        let want = Value::List(vec![
            Value::List(vec![Value::Float(1.5), Value::Float(2.0)]),
            Value::List(vec![Value::Int(3)]),
        ]);
        assert_eq!(v, want);
    }

    #[test]
    fn every_truncation_is_an_error() {
        for cut in 0..NESTED.len() {
            assert!(parse(&NESTED[..cut]).is_err(), "cut at {cut} parsed");
        }
    }

    #[test]
    fn refuses_lists_nested_past_the_limit_without_overflowing_the_stack() {
        // `[[[...]]]` a million deep: built by appending each list to the one below it.
        let n = 1_000_000;
        let mut bytes = b"\x80\x02".to_vec();
        bytes.extend(std::iter::repeat_n(b']', n));
        bytes.extend(std::iter::repeat_n(b'a', n - 1));
        bytes.push(b'.');
        let err = parse(&bytes).unwrap_err();
        assert!(err.contains("more than 32 deep"), "{err}");
        // At the limit it parses.
        let d = MAX_DEPTH as usize;
        let mut ok = b"\x80\x02".to_vec();
        ok.extend(std::iter::repeat_n(b']', d));
        ok.extend(std::iter::repeat_n(b'a', d - 1));
        ok.push(b'.');
        assert!(parse(&ok).is_ok());
    }

    #[test]
    fn refuses_code_objects() {
        // `pickle.dumps(print)` uses STACK_GLOBAL (0x93), which must be refused.
        let err = parse(b"\x80\x04\x95\x00\x00\x00\x00\x00\x00\x00\x00\x8c\x08builtins\x93.")
            .unwrap_err();
        assert!(err.contains("unsupported pickle opcode"), "{err}");
    }
}
