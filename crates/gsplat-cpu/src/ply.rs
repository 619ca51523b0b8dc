//! The `.ply` layout of the original 3DGS implementation (and of most viewers and trainers).
//!
//! One `vertex` element with per-Gaussian float properties: `x y z` (mean), `f_dc_0..2`
//! (degree-0 spherical-harmonic coefficients), `opacity` (logit), `scale_0..2` (natural log of
//! the standard deviations), `rot_0..3` (quaternion `w x y z`, not necessarily normalised).
//! Other properties (`nx ny nz`, `f_rest_*`) are ignored: colour is the degree-0 term only,
//! `0.5 + C0 · f_dc` with `C0 = 1 / (2 √π)`, clamped below at 0 as 3DGS does. Files with
//! `red green blue` (0–255) instead of `f_dc_*` are read too.

use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{Quat, Vec3};

use crate::{Error, Gaussians};

/// Degree-0 real spherical-harmonic basis constant `1 / (2 √π)`.
pub const SH_C0: f32 = 0.282_094_8;

#[derive(Clone, Copy, PartialEq)]
enum Format {
    Ascii,
    Little,
    Big,
}

#[derive(Clone, Copy)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Self> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn read(self, b: &[u8], big: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                f64::from(if big {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                })
            }};
        }
        match self {
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U8 => f64::from(b[0]),
            Scalar::I16 => num!(i16, 2),
            Scalar::U16 => num!(u16, 2),
            Scalar::I32 => num!(i32, 4),
            Scalar::U32 => num!(u32, 4),
            Scalar::F32 => num!(f32, 4),
            Scalar::F64 => num!(f64, 8),
        }
    }
}

struct Element {
    name: String,
    count: usize,
    props: Vec<(String, Scalar)>,
}

/// Reads a 3DGS `.ply` file.
///
/// # Errors
/// [`Error::Io`], or [`Error::Ply`] for a malformed header, a missing property, truncated data
/// or values that make invalid Gaussians (non-finite, zero quaternion).
pub fn read_ply(path: impl AsRef<Path>) -> Result<Gaussians, Error> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        cause: source,
    })?;
    parse_ply(&bytes, path)
}

/// Parses `.ply` bytes (see [`read_ply`]); `path` only names the source in errors.
///
/// # Errors
/// As [`read_ply`].
pub fn parse_ply(bytes: &[u8], path: &Path) -> Result<Gaussians, Error> {
    let bad = |what: String| Error::Ply {
        path: path.to_path_buf(),
        what,
    };
    let end = find(bytes, b"end_header\n").ok_or_else(|| bad("no end_header line".into()))?;
    let header =
        std::str::from_utf8(&bytes[..end]).map_err(|_| bad("header is not UTF-8".into()))?;
    let body = &bytes[end + b"end_header\n".len()..];
    let mut lines = header.lines().map(|l| l.trim_end_matches('\r'));
    if lines.next() != Some("ply") {
        return Err(bad("does not start with 'ply'".into()));
    }
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", f, _version] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::Little,
                    "binary_big_endian" => Format::Big,
                    other => return Err(bad(format!("unknown format '{other}'"))),
                });
            }
            ["element", name, count] => elements.push(Element {
                name: (*name).to_string(),
                count: count
                    .parse()
                    .map_err(|_| bad(format!("bad element count '{count}'")))?,
                props: Vec::new(),
            }),
            ["property", "list", ..] => {
                let e = elements
                    .last()
                    .ok_or_else(|| bad("property before any element".into()))?;
                if e.name == "vertex" || elements.iter().all(|e| e.name != "vertex") {
                    return Err(bad(format!(
                        "list property in element '{}' is not supported",
                        e.name
                    )));
                }
            }
            ["property", ty, name] => {
                let ty = Scalar::parse(ty)
                    .ok_or_else(|| bad(format!("unknown property type '{ty}'")))?;
                let e = elements
                    .last_mut()
                    .ok_or_else(|| bad("property before any element".into()))?;
                e.props.push(((*name).to_string(), ty));
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            _ => return Err(bad(format!("cannot read header line '{line}'"))),
        }
    }
    let format = format.ok_or_else(|| bad("no format line".into()))?;
    let vi = elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| bad("no vertex element".into()))?;
    let values = if format == Format::Ascii {
        read_ascii(body, &elements, vi).map_err(bad)?
    } else {
        read_binary(body, &elements, vi, format == Format::Big).map_err(bad)?
    };
    let vertex = &elements[vi];
    let col = |name: &str| vertex.props.iter().position(|p| p.0 == name);
    let need =
        |name: &str| col(name).ok_or_else(|| bad(format!("vertex has no '{name}' property")));
    let stride = vertex.props.len();
    let get = |row: usize, c: usize| values[row * stride + c];
    let pos = [need("x")?, need("y")?, need("z")?];
    let opacity = need("opacity")?;
    let scale = [need("scale_0")?, need("scale_1")?, need("scale_2")?];
    let rot = [
        need("rot_0")?,
        need("rot_1")?,
        need("rot_2")?,
        need("rot_3")?,
    ];
    let color = match (col("f_dc_0"), col("f_dc_1"), col("f_dc_2")) {
        (Some(r), Some(g), Some(b)) => ([r, g, b], true),
        _ => ([need("red")?, need("green")?, need("blue")?], false),
    };
    let mut g = Gaussians::default();
    for row in 0..vertex.count {
        let v3 = |c: [usize; 3]| {
            Vec3::new(
                get(row, c[0]) as f32,
                get(row, c[1]) as f32,
                get(row, c[2]) as f32,
            )
        };
        g.means.push(v3(pos));
        g.scales.push(Vec3::new(
            get(row, scale[0]).exp() as f32,
            get(row, scale[1]).exp() as f32,
            get(row, scale[2]).exp() as f32,
        ));
        g.opacities
            .push((1.0 / (1.0 + (-get(row, opacity)).exp())) as f32);
        let (w, x, y, z) = (
            get(row, rot[0]),
            get(row, rot[1]),
            get(row, rot[2]),
            get(row, rot[3]),
        );
        g.rotations
            .push(Quat::from_xyzw(x as f32, y as f32, z as f32, w as f32));
        let c = color.0.map(|c| get(row, c) as f32);
        g.colors.push(if color.1 {
            c.map(|f| (0.5 + SH_C0 * f).max(0.0))
        } else {
            c.map(|u| u / 255.0)
        });
    }
    g.validate().map_err(|e| bad(e.to_string()))?;
    Ok(g)
}

/// Writes `gaussians` as a binary little-endian 3DGS `.ply` (`x y z f_dc_0..2 opacity
/// scale_0..2 rot_0..3`, all float), readable by 3DGS viewers. Zero scales are written as
/// `ln(1e-12)` and opacities are kept inside `[1e-6, 1 − 1e-6]` so the logs stay finite.
/// Written atomically, as [`crate::write_png`].
///
/// # Errors
/// Invalid Gaussians or [`Error::Io`].
pub fn write_ply(path: impl AsRef<Path>, gaussians: &Gaussians) -> Result<(), Error> {
    gaussians.validate()?;
    let path = path.as_ref();
    let names = [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ];
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\n",
        gaussians.len()
    );
    for n in names {
        out.push_str(&format!("property float {n}\n"));
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    for i in 0..gaussians.len() {
        let m = gaussians.means[i];
        let c = gaussians.colors[i].map(|c| (c - 0.5) / SH_C0);
        let o = gaussians.opacities[i].clamp(1e-6, 1.0 - 1e-6);
        let s = gaussians.scales[i].max(Vec3::splat(1e-12));
        let q = gaussians.rotations[i];
        let row = [
            m.x,
            m.y,
            m.z,
            c[0],
            c[1],
            c[2],
            (o / (1.0 - o)).ln(),
            s.x.ln(),
            s.y.ln(),
            s.z.ln(),
            q.w,
            q.x,
            q.y,
            q.z,
        ];
        for v in row {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    crate::output::write_atomically(path, |w| {
        w.write_all(&bytes).map_err(|source| Error::Io {
            path: PathBuf::from(path),
            cause: source,
        })
    })
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// All vertex values as f64, row-major.
fn read_binary(
    body: &[u8],
    elements: &[Element],
    vi: usize,
    big: bool,
) -> Result<Vec<f64>, String> {
    let row_size = |e: &Element| e.props.iter().map(|p| p.1.size()).sum::<usize>();
    // Elements before the vertices have fixed-size rows (no list properties were accepted).
    let mut offset = 0usize;
    for e in &elements[..vi] {
        offset = e
            .count
            .checked_mul(row_size(e))
            .and_then(|n| n.checked_add(offset))
            .ok_or("element sizes overflow")?;
    }
    let v = &elements[vi];
    let size = row_size(v);
    let need = v
        .count
        .checked_mul(size)
        .and_then(|n| n.checked_add(offset))
        .ok_or("vertex count overflows")?;
    if body.len() < need {
        return Err(format!(
            "data truncated: {} bytes, {} needed for {} vertices",
            body.len(),
            need,
            v.count
        ));
    }
    let mut values = Vec::with_capacity(v.count * v.props.len());
    let mut at = offset;
    for _ in 0..v.count {
        for (_, ty) in &v.props {
            values.push(ty.read(&body[at..], big));
            at += ty.size();
        }
    }
    Ok(values)
}

fn read_ascii(body: &[u8], elements: &[Element], vi: usize) -> Result<Vec<f64>, String> {
    let text = std::str::from_utf8(body).map_err(|_| "ascii body is not UTF-8".to_string())?;
    let mut words = text.split_whitespace();
    let total = |e: &Element| {
        e.count
            .checked_mul(e.props.len())
            .ok_or("element count overflows")
    };
    for e in &elements[..vi] {
        for _ in 0..total(e)? {
            words.next().ok_or("data truncated")?;
        }
    }
    let v = &elements[vi];
    let n = total(v)?;
    // Each value takes at least two bytes ("0 "), which bounds a lying header's allocation.
    let mut values = Vec::with_capacity(n.min(body.len() / 2 + 1));
    for _ in 0..n {
        let w = words
            .next()
            .ok_or_else(|| format!("data truncated: {} vertices expected", v.count))?;
        values.push(w.parse::<f64>().map_err(|_| format!("bad number '{w}'"))?);
    }
    Ok(values)
}
