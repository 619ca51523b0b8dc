//! `cargo xtask metrics --pred A.npy --gt B.npy`: point-cloud metrics of two `.npy` clouds,
//! printed as one JSON object with the convention of every number.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use metrics::{ChamferConvention, EmdSolver, chamfer, mde};

/// Arguments of `metrics`.
#[derive(clap::Args, Debug)]
pub struct MetricsArgs {
    /// Predicted cloud: `.npy`, shape (N, 3), float32 or float64.
    #[arg(long)]
    pub pred: PathBuf,
    /// Ground-truth cloud: `.npy`, shape (M, 3), float32 or float64.
    #[arg(long)]
    pub gt: PathBuf,
    /// Skip the exact EMD (an assignment problem: seconds for a few thousand points, far
    /// longer for tens of thousands in degenerate layouts, e.g. points along one line).
    #[arg(long)]
    pub no_emd: bool,
}

/// Reads both clouds and prints MDE (equal sizes only), both one-sided Chamfer means, their
/// sum, and exact EMD, in the input's units.
pub fn run(args: &MetricsArgs) -> anyhow::Result<()> {
    let pred = read_npy_points(&args.pred)?;
    let gt = read_npy_points(&args.gt)?;
    if !args.no_emd && pred.len().min(gt.len()) > 5000 {
        eprintln!(
            "exact EMD of {} x {} points may take minutes; --no-emd skips it",
            pred.len(),
            gt.len()
        );
    }
    let report = metrics_json(&pred, &gt, !args.no_emd)
        .with_context(|| format!("{} vs {}", args.pred.display(), args.gt.display()))?;
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// The JSON report for two clouds.
fn metrics_json(
    pred: &[[f64; 3]],
    gt: &[[f64; 3]],
    with_emd: bool,
) -> anyhow::Result<serde_json::Value> {
    let c = chamfer(pred, gt)?;
    let emd = if with_emd {
        Some(EmdSolver::new().emd(pred, gt)?)
    } else {
        None
    };
    let same_size = pred.len() == gt.len();
    let mde = if same_size {
        Some(mde(pred, gt)?)
    } else {
        None
    };
    let emd_convention = if !with_emd {
        "not computed (--no-emd)"
    } else if same_size {
        "exact EMD: optimal one-to-one assignment on Euclidean cost, mean matched distance"
    } else {
        "exact EMD, partial: each point of the smaller cloud matched to a distinct point of the \
         larger one (optimal), mean over the min(N, M) matched pairs"
    };
    Ok(serde_json::json!({
        "pred_points": pred.len(),
        "gt_points": gt.len(),
        "units": "the input's coordinate units",
        "mde": mde,
        "chamfer_pred_to_gt": c.pred_to_gt,
        "chamfer_gt_to_pred": c.gt_to_pred,
        "chamfer": c.two_sided_sum(),
        "chamfer_convention": ChamferConvention::TwoSidedSum.label(),
        "emd": emd,
        "conventions": {
            "mde": if same_size {
                "mean Euclidean distance between same-index points"
            } else {
                "undefined: the clouds differ in size (same-index metric)"
            },
            "chamfer_pred_to_gt": ChamferConvention::PredToGt.label(),
            "chamfer_gt_to_pred": ChamferConvention::GtToPred.label(),
            "chamfer": ChamferConvention::TwoSidedSum.label(),
            "emd": emd_convention,
        },
    }))
}

/// Element type of a `.npy` array.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Dtype {
    F32,
    F64,
}

/// Parsed `.npy` header.
#[derive(Debug, PartialEq)]
struct NpyHeader {
    dtype: Dtype,
    fortran_order: bool,
    shape: Vec<usize>,
    /// Byte offset of the data.
    data_start: usize,
}

/// Reads an `(N, 3)` little-endian float32 / float64 `.npy` file (format versions 1–3, C or
/// Fortran order) as points widened to f64.
fn read_npy_points(path: &Path) -> anyhow::Result<Vec<[f64; 3]>> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    parse_npy_points(&bytes)
        .with_context(|| format!("{} is not a usable point cloud", path.display()))
}

fn parse_npy_points(bytes: &[u8]) -> anyhow::Result<Vec<[f64; 3]>> {
    let h = parse_header(bytes)?;
    let (n, cols) = match h.shape[..] {
        [n, c] => (n, c),
        _ => bail!(
            "expected a 2-D array of shape (N, 3), got shape {:?}",
            h.shape
        ),
    };
    if cols != 3 {
        bail!("expected shape (N, 3), got ({n}, {cols})");
    }
    if n == 0 {
        bail!("the cloud is empty (shape (0, 3))");
    }
    let size = match h.dtype {
        Dtype::F32 => 4,
        Dtype::F64 => 8,
    };
    let data = &bytes[h.data_start..];
    let want = n.checked_mul(3 * size).context("array too large")?;
    if data.len() != want {
        bail!(
            "data has {} bytes, shape ({n}, 3) of {} needs {want}",
            data.len(),
            if size == 4 { "float32" } else { "float64" }
        );
    }
    let values: Vec<f64> = match h.dtype {
        Dtype::F32 => data
            .chunks_exact(4)
            .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
            .collect(),
        Dtype::F64 => data
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]))
            .collect(),
    };
    // C order stores x0 y0 z0 x1 …; Fortran order stores all x, then all y, then all z.
    let at = |i: usize, c: usize| {
        if h.fortran_order {
            values[c * n + i]
        } else {
            values[i * 3 + c]
        }
    };
    Ok((0..n).map(|i| [at(i, 0), at(i, 1), at(i, 2)]).collect())
}

fn parse_header(bytes: &[u8]) -> anyhow::Result<NpyHeader> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        bail!("not a .npy file (missing the \\x93NUMPY magic)");
    }
    let (len, start) = match bytes[6] {
        1 => (
            usize::from(u16::from_le_bytes([bytes[8], bytes[9]])),
            10usize,
        ),
        2 | 3 => {
            if bytes.len() < 12 {
                bail!("truncated .npy header");
            }
            let l = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
            (usize::try_from(l)?, 12)
        }
        v => bail!("unsupported .npy format version {v}"),
    };
    let end = start
        .checked_add(len)
        .filter(|&e| e <= bytes.len())
        .context("truncated .npy header")?;
    let text = std::str::from_utf8(&bytes[start..end]).context(".npy header is not text")?;
    let descr = dict_value(text, "descr")?;
    let dtype = match descr.trim_matches(|c| c == '\'' || c == '"') {
        "<f4" => Dtype::F32,
        "<f8" => Dtype::F64,
        other => bail!(
            "unsupported dtype {other:?}: only little-endian float32 ('<f4') and float64 ('<f8')"
        ),
    };
    let fortran_order = match dict_value(text, "fortran_order")? {
        "True" => true,
        "False" => false,
        other => bail!("bad fortran_order {other:?}"),
    };
    let shape_text = dict_value(text, "shape")?;
    let inner = shape_text
        .strip_prefix('(')
        .and_then(|s| s.strip_suffix(')'))
        .with_context(|| format!("bad shape {shape_text:?}"))?;
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse::<usize>())
        .collect::<Result<Vec<_>, _>>()
        .with_context(|| format!("bad shape {shape_text:?}"))?;
    Ok(NpyHeader {
        dtype,
        fortran_order,
        shape,
        data_start: end,
    })
}

/// The raw text of `key`'s value in the header's Python dict literal.
fn dict_value<'a>(dict: &'a str, key: &str) -> anyhow::Result<&'a str> {
    let pat_single = format!("'{key}'");
    let pat_double = format!("\"{key}\"");
    let at = dict
        .find(&pat_single)
        .map(|i| i + pat_single.len())
        .or_else(|| dict.find(&pat_double).map(|i| i + pat_double.len()))
        .with_context(|| format!(".npy header has no {key:?}"))?;
    let rest = dict[at..]
        .trim_start()
        .strip_prefix(':')
        .context("malformed .npy header")?
        .trim_start();
    // A value ends at the ',' that closes it: after ')' for tuples, else at the next ',' / '}'.
    let end = if rest.starts_with('(') {
        rest.find(')').map(|i| i + 1)
    } else {
        rest.find([',', '}'])
    }
    .context("malformed .npy header")?;
    Ok(rest[..end].trim())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bytes of a `.npy` file with the given header dict and payload (version 1 or 2).
    fn npy(version: u8, dict: &str, payload: &[u8]) -> Vec<u8> {
        let prefix = if version == 1 { 10 } else { 12 };
        let mut header = dict.to_string();
        // Pad with spaces so the data starts on a 64-byte boundary, ending in '\n'.
        while !(prefix + header.len() + 1).is_multiple_of(64) {
            header.push(' ');
        }
        header.push('\n');
        let mut out = b"\x93NUMPY".to_vec();
        out.extend([version, 0]);
        if version == 1 {
            out.extend((header.len() as u16).to_le_bytes());
        } else {
            out.extend((header.len() as u32).to_le_bytes());
        }
        out.extend(header.as_bytes());
        out.extend(payload);
        out
    }

    fn f32_bytes(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    fn f64_bytes(v: &[f64]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    #[test]
    fn reads_f32_v1_and_f64_v2() {
        let v = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.5];
        let a = npy(
            1,
            "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }",
            &f32_bytes(&v),
        );
        assert_eq!(
            parse_npy_points(&a).unwrap(),
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]]
        );
        let w = [0.1f64, 0.2, 0.3];
        let b = npy(
            2,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 3), }",
            &f64_bytes(&w),
        );
        assert_eq!(parse_npy_points(&b).unwrap(), vec![[0.1, 0.2, 0.3]]);
    }

    #[test]
    fn reads_fortran_order() {
        // Column-major (2, 3): x0 x1 y0 y1 z0 z1.
        let v = [1.0f64, 4.0, 2.0, 5.0, 3.0, 6.0];
        let a = npy(
            1,
            "{'descr': '<f8', 'fortran_order': True, 'shape': (2, 3), }",
            &f64_bytes(&v),
        );
        assert_eq!(
            parse_npy_points(&a).unwrap(),
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
        );
    }

    #[test]
    fn clear_errors() {
        let err = |bytes: &[u8]| format!("{:#}", parse_npy_points(bytes).unwrap_err());
        assert!(err(b"not a numpy file at all").contains("magic"));
        let v = f64_bytes(&[0.0; 6]);
        let e = err(&npy(
            1,
            "{'descr': '>f8', 'fortran_order': False, 'shape': (2, 3), }",
            &v,
        ));
        assert!(e.contains("dtype"), "{e}");
        let e = err(&npy(
            1,
            "{'descr': '<i8', 'fortran_order': False, 'shape': (2, 3), }",
            &v,
        ));
        assert!(e.contains("dtype"), "{e}");
        let e = err(&npy(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 2), }",
            &v,
        ));
        assert!(e.contains("(N, 3)"), "{e}");
        let e = err(&npy(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (6,), }",
            &v,
        ));
        assert!(e.contains("2-D"), "{e}");
        let e = err(&npy(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (0, 3), }",
            &[],
        ));
        assert!(e.contains("empty"), "{e}");
        let e = err(&npy(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 3), }",
            &v,
        ));
        assert!(e.contains("bytes"), "{e}");
        let mut truncated = npy(
            1,
            "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 3), }",
            &v,
        );
        truncated.truncate(20);
        assert!(err(&truncated).contains("truncated"));
    }

    #[test]
    fn report_fields_and_nan() {
        let pred = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]];
        let gt = [[0.0, 0.0, 0.5], [1.0, 0.0, 0.5]];
        let r = metrics_json(&pred, &gt, true).unwrap();
        for key in ["mde", "chamfer_pred_to_gt", "chamfer_gt_to_pred", "emd"] {
            assert!((r[key].as_f64().unwrap() - 0.5).abs() < 1e-12, "{key}");
            assert!(r["conventions"][key].is_string());
        }
        assert!((r["chamfer"].as_f64().unwrap() - 1.0).abs() < 1e-12);
        assert!(
            r["chamfer_convention"]
                .as_str()
                .unwrap()
                .contains("two-sided")
        );
        // Different sizes: no MDE, partial EMD.
        let r = metrics_json(&pred, &gt[..1], true).unwrap();
        assert!(r["mde"].is_null());
        assert!(
            r["conventions"]["emd"]
                .as_str()
                .unwrap()
                .contains("partial")
        );
        // Without the EMD: the field is null and its convention says why.
        let r = metrics_json(&pred, &gt, false).unwrap();
        assert!(r["emd"].is_null());
        assert!(
            r["conventions"]["emd"]
                .as_str()
                .unwrap()
                .contains("--no-emd")
        );
        let bad = [[0.0, f64::NAN, 0.0]];
        let e = format!("{:#}", metrics_json(&bad, &gt, true).unwrap_err());
        assert!(e.contains("non-finite") && e.contains("prediction"), "{e}");
    }
}
