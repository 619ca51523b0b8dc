//! The numpy objects of an array's pickle, interpreted by name: never called.

use std::rc::Rc;

use super::Obj;

/// The element types of the numpy arrays this reader accepts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    /// `bool` (`b1`).
    Bool,
    /// Signed integers of 1, 2, 4 or 8 bytes.
    Int(u8),
    /// Unsigned integers of 1, 2, 4 or 8 bytes.
    Uint(u8),
    /// IEEE floats of 4 or 8 bytes.
    Float(u8),
}

impl Dtype {
    fn parse(code: &str) -> Option<Dtype> {
        let (kind, size) = code.split_at(code.len().min(1));
        let size: u8 = size.parse().ok()?;
        match (kind, size) {
            ("b", 1) => Some(Dtype::Bool),
            ("i", 1 | 2 | 4 | 8) => Some(Dtype::Int(size)),
            ("u", 1 | 2 | 4 | 8) => Some(Dtype::Uint(size)),
            ("f", 4 | 8) => Some(Dtype::Float(size)),
            _ => None,
        }
    }

    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            Dtype::Bool => 1,
            Dtype::Int(s) | Dtype::Uint(s) | Dtype::Float(s) => s as usize,
        }
    }
}

/// A numpy array: its element type, shape and data (C order, little-endian).
#[derive(Clone, Debug, PartialEq)]
pub struct NdArray {
    /// Element type.
    pub dtype: Dtype,
    /// Shape (empty for a numpy scalar).
    pub shape: Vec<usize>,
    data: Vec<u8>,
}

impl NdArray {
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    /// Whether the array has no element.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The elements as f64, in C order (a bool is 0 or 1).
    pub fn to_f64(&self) -> Vec<f64> {
        let s = self.dtype.size();
        self.data
            .chunks_exact(s)
            .map(|b| {
                let mut w = [0u8; 8];
                w[..s].copy_from_slice(b);
                match self.dtype {
                    Dtype::Bool => f64::from(u8::from(b[0] != 0)),
                    Dtype::Float(4) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Dtype::Float(_) => f64::from_le_bytes(w),
                    Dtype::Uint(_) => u64::from_le_bytes(w) as f64,
                    Dtype::Int(_) => {
                        // Sign-extend from the element's width.
                        let shift = 64 - 8 * s as u32;
                        ((i64::from_le_bytes(w) << shift) >> shift) as f64
                    }
                }
            })
            .collect()
    }

    /// The elements as flags, in C order: nonzero is true.
    pub fn to_bool(&self) -> Vec<bool> {
        self.data
            .chunks_exact(self.dtype.size())
            .map(|b| b.iter().any(|x| *x != 0))
            .collect()
    }
}

/// The numpy (and codecs) names an array's pickle refers to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Global {
    Reconstruct,
    NdarrayClass,
    DtypeClass,
    FromBuffer,
    Scalar,
    Encode,
    BytesClass,
}

impl Global {
    pub(super) fn lookup(module: &str, name: &str) -> Option<Global> {
        let numpy_core = |m: &str, sub: &str| {
            m == format!("numpy.core.{sub}") || m == format!("numpy._core.{sub}")
        };
        match name {
            "_reconstruct" if numpy_core(module, "multiarray") => Some(Global::Reconstruct),
            "scalar" if numpy_core(module, "multiarray") => Some(Global::Scalar),
            "_frombuffer" if numpy_core(module, "numeric") => Some(Global::FromBuffer),
            "ndarray" if module == "numpy" => Some(Global::NdarrayClass),
            "dtype" if module == "numpy" => Some(Global::DtypeClass),
            "encode" if module == "_codecs" => Some(Global::Encode),
            // Protocol 2 writes empty bytes as a call of the bytes type.
            "bytes" if module == "__builtin__" || module == "builtins" => Some(Global::BytesClass),
            _ => None,
        }
    }
}

pub(super) fn global(module: &str, name: &str, at: usize) -> Result<Obj, String> {
    Global::lookup(module, name)
        .map(Obj::Global)
        .ok_or_else(|| {
            format!(
                "pickle refers to {module}.{name} at offset {at}: refused (only numbers, strings, \
             lists, tuples, dicts and numpy arrays are read)"
            )
        })
}

fn bad_args(what: &str, at: usize) -> String {
    format!("malformed pickle: unexpected arguments to {what} at offset {at}")
}

pub(super) fn reduce(g: Global, args: Obj, at: usize) -> Result<Obj, String> {
    let Obj::Tuple(args) = args else {
        return Err(bad_args("a call", at));
    };
    match (g, args.as_slice()) {
        (Global::Reconstruct, [Obj::Global(Global::NdarrayClass), ..]) => Ok(Obj::PendingArray),
        (Global::DtypeClass, [Obj::Str(code), ..]) => Ok(Obj::Dtype {
            code: code.clone(),
            big_endian: false,
        }),
        (Global::FromBuffer, [Obj::Bytes(data), dtype, Obj::Tuple(shape), Obj::Str(order)]) => {
            array(dtype, shape, order.as_ref() == "F", data, at)
        }
        (Global::Scalar, [dtype, Obj::Bytes(data)]) => array(dtype, &[], false, data, at),
        (Global::Encode, [Obj::Str(s), Obj::Str(codec)]) if codec.as_ref() == "latin1" => {
            // Protocol 2 writes bytes as their latin-1 decoding.
            let b = s
                .chars()
                .map(|c| u8::try_from(u32::from(c)).map_err(|_| bad_args("_codecs.encode", at)))
                .collect::<Result<Vec<u8>, String>>()?;
            Ok(Obj::Bytes(Rc::from(b)))
        }
        (Global::BytesClass, []) => Ok(Obj::Bytes(Rc::from(&[][..]))),
        (g, _) => Err(bad_args(&format!("{g:?}"), at)),
    }
}

pub(super) fn build(obj: Obj, state: Obj, at: usize) -> Result<Obj, String> {
    let Obj::Tuple(state) = state else {
        return Err(bad_args("BUILD", at));
    };
    match obj {
        Obj::PendingArray => {
            // (version, shape, dtype, is_fortran, data), or without the version.
            let s = match state.as_slice() {
                [Obj::Int(_), rest @ ..] if rest.len() == 4 => rest,
                s => s,
            };
            match s {
                [
                    Obj::Tuple(shape),
                    dtype,
                    Obj::Bool(fortran),
                    Obj::Bytes(data),
                ] => array(dtype, shape, *fortran, data, at),
                [_, _, _, Obj::List(_)] => Err(format!(
                    "a numpy array of Python objects at offset {at}: refused (numbers only)"
                )),
                _ => Err(bad_args("an array's state", at)),
            }
        }
        Obj::Dtype { code, .. } => match state.get(1) {
            Some(Obj::Str(order)) => Ok(Obj::Dtype {
                code,
                big_endian: order.as_ref() == ">",
            }),
            _ => Err(bad_args("a dtype's state", at)),
        },
        _ => Err(format!(
            "malformed pickle: BUILD of a value that is not a numpy array or dtype at offset {at}"
        )),
    }
}

fn array(dtype: &Obj, shape: &[Obj], fortran: bool, data: &[u8], at: usize) -> Result<Obj, String> {
    let Obj::Dtype { code, big_endian } = dtype else {
        return Err(bad_args("an array (no dtype)", at));
    };
    let dtype = Dtype::parse(code).ok_or_else(|| {
        format!(
            "a numpy array of dtype '{code}' at offset {at}: only bool, integer and float32/64 \
             arrays are read"
        )
    })?;
    let shape = shape
        .iter()
        .map(|d| match d {
            Obj::Int(n) => usize::try_from(*n).map_err(|_| bad_args("an array's shape", at)),
            _ => Err(bad_args("an array's shape", at)),
        })
        .collect::<Result<Vec<usize>, String>>()?;
    let count = shape
        .iter()
        .try_fold(1usize, |a, d| a.checked_mul(*d))
        .ok_or_else(|| bad_args("an array's shape", at))?;
    let s = dtype.size();
    if count.checked_mul(s) != Some(data.len()) {
        return Err(format!(
            "a numpy array at offset {at} of shape {shape:?} and dtype '{code}' holds {} bytes, \
             not {count} × {s}",
            data.len()
        ));
    }
    let mut le: Vec<u8> = data.to_vec();
    if *big_endian && s > 1 {
        le.chunks_exact_mut(s).for_each(<[u8]>::reverse);
    }
    if fortran && shape.len() > 1 {
        le = fortran_to_c(&le, &shape, s);
    }
    Ok(Obj::Array(Rc::new(NdArray {
        dtype,
        shape,
        data: le,
    })))
}

/// Reorders column-major elements of `size` bytes into row-major order.
fn fortran_to_c(data: &[u8], shape: &[usize], size: usize) -> Vec<u8> {
    let n: usize = shape.iter().product();
    let mut out = vec![0u8; data.len()];
    let mut index = vec![0usize; shape.len()];
    for c in 0..n {
        // `index` is element c's multi-index in C order; its Fortran offset:
        let mut f = 0;
        for d in (0..shape.len()).rev() {
            f = f * shape[d] + index[d];
        }
        out[c * size..(c + 1) * size].copy_from_slice(&data[f * size..(f + 1) * size]);
        for d in (0..shape.len()).rev() {
            index[d] += 1;
            if index[d] < shape[d] {
                break;
            }
            index[d] = 0;
        }
    }
    out
}
