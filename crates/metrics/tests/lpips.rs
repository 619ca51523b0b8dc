//! LPIPS against `../shared/golden/lpips.json` (values from the `lpips` 0.1.4 package) to 1e-3
//! absolute. Needs `--features lpips`.
#![cfg(feature = "lpips")]

use std::path::PathBuf;

use metrics::lpips::Lpips;
use serde_json::Value;

fn golden() -> Value {
    let dir = match std::env::var_os("PGRD_SHARED_DIR") {
        Some(p) => PathBuf::from(p),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
    };
    let path = dir.join("golden/lpips.json");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("cannot read {} (set PGRD_SHARED_DIR): {e}", path.display()));
    serde_json::from_str(&text).unwrap()
}

/// Nested `[c][y][x]` lists -> interleaved `[y][x][c]` buffer, with width and height.
fn image(v: &Value) -> (Vec<f32>, usize, usize) {
    let chans = v.as_array().unwrap();
    assert_eq!(chans.len(), 3);
    let rows = |c: usize| chans[c].as_array().unwrap();
    let (h, w) = (rows(0).len(), rows(0)[0].as_array().unwrap().len());
    let mut out = vec![0.0f32; w * h * 3];
    for c in 0..3 {
        for (y, row) in rows(c).iter().enumerate() {
            for (x, val) in row.as_array().unwrap().iter().enumerate() {
                out[(y * w + x) * 3 + c] = val.as_f64().unwrap() as f32;
            }
        }
    }
    (out, w, h)
}

#[test]
fn golden_lpips_pairs() {
    let g = golden();
    let lpips = Lpips::new().unwrap();
    let pairs = g["pairs"].as_array().unwrap();
    assert_eq!(pairs.len(), 4);
    for p in pairs {
        let (a, b) = (p["a"].as_str().unwrap(), p["b"].as_str().unwrap());
        let (ia, w, h) = image(&g["images"][a]);
        let (ib, w2, h2) = image(&g["images"][b]);
        assert_eq!((w, h), (w2, h2));
        let want = p["lpips"].as_f64().unwrap();
        let got = lpips.distance(&ia, &ib, w, h).unwrap();
        assert!(
            (got - want).abs() <= 1e-3,
            "{a} vs {b}: {got} vs reference {want}"
        );
        // Symmetric by construction.
        let back = lpips.distance(&ib, &ia, w, h).unwrap();
        assert!((got - back).abs() <= 1e-6);
    }
}

#[test]
fn loads_the_shipped_weight_file_and_rejects_bad_input() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/lpips_alex_v0.1.safetensors");
    let from_file = Lpips::from_file(&path).unwrap();
    let img: Vec<f32> = (0..40 * 36 * 3)
        .map(|k| ((k * 37) % 101) as f32 / 100.0)
        .collect();
    let other: Vec<f32> = img.iter().map(|v| 1.0 - v).collect();
    let embedded = Lpips::new().unwrap();
    let d = embedded.distance(&img, &other, 40, 36).unwrap();
    assert!(d > 0.0);
    assert_eq!(d, from_file.distance(&img, &other, 40, 36).unwrap());
    assert!(embedded.distance(&img, &other, 36, 40).is_ok());
    assert!(embedded.distance(&img[..30], &other, 40, 36).is_err());
    assert!(
        embedded
            .distance(&img[..20 * 20 * 3], &other[..20 * 20 * 3], 20, 20)
            .is_err()
    );
    let mut nan = img.clone();
    nan[5] = f32::NAN;
    assert!(embedded.distance(&nan, &other, 40, 36).is_err());
    assert!(Lpips::from_file("/nonexistent/weights.safetensors").is_err());
}
