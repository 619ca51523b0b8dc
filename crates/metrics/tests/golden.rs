//! Reproduces every case of `../shared/golden/metrics.json` (values from scipy cKDTree,
//! scipy linear_sum_assignment and POT ot.emd2) to 1e-6 relative.
//!
//! The shared folder is found at `$PGRD_SHARED_DIR` or `<workspace>/../shared`; a missing file
//! fails the test (it never passes silently).

use std::path::PathBuf;

use metrics::{EmdSolver, PointIndex, chamfer, emd, mde};
use serde_json::Value;

fn shared_dir() -> PathBuf {
    match std::env::var_os("PGRD_SHARED_DIR") {
        Some(p) => PathBuf::from(p),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
    }
}

fn load(name: &str) -> Value {
    let path = shared_dir().join("golden").join(name);
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("cannot read {} (set PGRD_SHARED_DIR): {e}", path.display()));
    serde_json::from_str(&text).unwrap()
}

fn cloud(v: &Value) -> Vec<[f64; 3]> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let p = p.as_array().unwrap();
            assert_eq!(p.len(), 3);
            [
                p[0].as_f64().unwrap(),
                p[1].as_f64().unwrap(),
                p[2].as_f64().unwrap(),
            ]
        })
        .collect()
}

/// 1e-6 relative. The absolute floor of 1e-9 only matters for references that are rounding
/// noise around an exact zero (POT reports 9.3e-10 for the EMD of identical clouds).
fn check(case: &str, what: &str, got: f64, want: f64) {
    let tol = 1e-6 * want.abs() + 1e-9;
    assert!(
        (got - want).abs() <= tol,
        "{case}: {what} = {got:.17e}, reference {want:.17e}"
    );
}

#[test]
fn golden_point_metrics() {
    let golden = load("metrics.json");
    let cases = golden["cases"].as_array().unwrap();
    assert!(cases.len() >= 6);
    let mut checked = 0;
    let mut solver = EmdSolver::new();
    for case in cases {
        let name = case["name"].as_str().unwrap();
        let a = cloud(&case["a"]);
        let b = cloud(&case["b"]);
        let c = chamfer(&a, &b).unwrap();
        check(
            name,
            "chamfer_a_to_b",
            c.pred_to_gt,
            case["chamfer_a_to_b"].as_f64().unwrap(),
        );
        check(
            name,
            "chamfer_b_to_a",
            c.gt_to_pred,
            case["chamfer_b_to_a"].as_f64().unwrap(),
        );
        check(
            name,
            "two-sided sum",
            c.two_sided_sum(),
            case["chamfer_two_sided_sum"].as_f64().unwrap(),
        );
        check(
            name,
            "two-sided squared sum",
            c.two_sided_squared_sum(),
            case["chamfer_two_sided_squared_sum"].as_f64().unwrap(),
        );
        // The reusable index must give the same numbers as the one-shot function.
        let index = PointIndex::new(&b).unwrap();
        assert_eq!(index.chamfer(&a).unwrap(), c);
        if let Some(want) = case.get("mde").and_then(Value::as_f64) {
            check(name, "mde", mde(&a, &b).unwrap(), want);
        }
        if let Some(want) = case.get("emd").and_then(Value::as_f64) {
            check(name, "emd", emd(&a, &b).unwrap(), want);
            check(name, "emd (swapped)", emd(&b, &a).unwrap(), want);
            checked += 1;
        }
        if let Some(want) = case.get("emd_partial_rectangular").and_then(Value::as_f64) {
            assert_ne!(a.len(), b.len());
            let e = solver.solve(&a, &b).unwrap();
            check(name, "emd_partial_rectangular", e.mean, want);
            assert_eq!(e.pairs.len(), a.len().min(b.len()));
            check(
                name,
                "emd_partial_rectangular (swapped)",
                emd(&b, &a).unwrap(),
                want,
            );
            checked += 1;
        }
    }
    assert_eq!(checked, cases.len(), "every case has an EMD reference");
}

/// The same cases through `f32` input: the widening to f64 happens before any arithmetic, so
/// the only difference is the rounding of the coordinates themselves (~1e-7 relative).
#[test]
fn golden_point_metrics_f32_input() {
    let golden = load("metrics.json");
    for case in golden["cases"].as_array().unwrap() {
        let name = case["name"].as_str().unwrap();
        let to32 = |v: Vec<[f64; 3]>| -> Vec<[f32; 3]> {
            v.into_iter()
                .map(|p| [p[0] as f32, p[1] as f32, p[2] as f32])
                .collect()
        };
        let a = to32(cloud(&case["a"]));
        let b = to32(cloud(&case["b"]));
        let c = chamfer(&a, &b).unwrap();
        let want = case["chamfer_two_sided_sum"].as_f64().unwrap();
        assert!(
            (c.two_sided_sum() - want).abs() <= 1e-4 * want + 1e-6,
            "{name}"
        );
    }
}
