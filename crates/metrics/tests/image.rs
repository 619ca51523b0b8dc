//! Image metrics on hand-computed cases and against direct (non-separable) formulas.

use metrics::MetricsError;
use metrics::image::{
    boundary_f_measure, boundary_f_measure_with, boundary_radius, mask_iou, masked_psnr,
    masked_ssim, threshold_mask,
};

fn mask(w: usize, h: usize, f: impl Fn(usize, usize) -> bool) -> Vec<bool> {
    (0..w * h).map(|k| f(k % w, k / w)).collect()
}

#[test]
fn iou_cases() {
    let a = mask(10, 10, |x, _| x < 5);
    let b = mask(10, 10, |_, y| y < 5);
    assert_eq!(mask_iou(&a, &b).unwrap(), 25.0 / 75.0);
    assert_eq!(mask_iou(&a, &a).unwrap(), 1.0);
    let none = vec![false; 100];
    assert_eq!(mask_iou(&none, &none).unwrap(), 1.0);
    assert_eq!(mask_iou(&a, &none).unwrap(), 0.0);
    assert!(matches!(
        mask_iou(&a, &none[..99]),
        Err(MetricsError::ImageSize { .. })
    ));
    assert_eq!(
        threshold_mask(&[0.05, 0.1, 0.11, 1.0], 0.1),
        vec![false, false, true, true]
    );
}

#[test]
fn boundary_radius_follows_the_diagonal() {
    assert_eq!(boundary_radius(100, 100, 0.008), 2); // 1.13 -> 2
    assert_eq!(boundary_radius(854, 480, 0.008), 8); // DAVIS 480p: 7.84 -> 8
    assert_eq!(boundary_radius(8, 8, 0.008), 1);
}

/// Top `rows` rows of a 100 x 100 image: the boundary is the single row `rows - 1`.
fn top(rows: usize) -> Vec<bool> {
    mask(100, 100, |_, y| y < rows)
}

#[test]
fn boundary_f_tolerance_is_a_disk_of_the_radius() {
    // Radius 2 px: boundaries 2 rows apart still match, 3 rows apart do not.
    assert_eq!(
        boundary_f_measure(&top(50), &top(50), 100, 100).unwrap(),
        1.0
    );
    assert_eq!(
        boundary_f_measure(&top(50), &top(52), 100, 100).unwrap(),
        1.0
    );
    assert_eq!(
        boundary_f_measure(&top(50), &top(53), 100, 100).unwrap(),
        0.0
    );
    // An explicit radius (>= 1 means pixels, as in DAVIS).
    assert_eq!(
        boundary_f_measure_with(&top(50), &top(53), 100, 100, 3.0).unwrap(),
        1.0
    );
}

#[test]
fn boundary_f_partial_match_by_hand() {
    // Prediction boundary: row 49, 100 px. Ground truth: rows 0..50 for x < 50 and rows 0..60
    // for x >= 50, so its boundary is row 49 for x in 0..50 (50 px), row 59 for x in 50..100
    // (50 px) and column 49 for y in 50..60 (10 px, the left neighbour of the step): 110 px.
    // With radius 2: 52 predicted pixels (x in 0..52 of row 49) have a ground-truth boundary
    // pixel within 2 px, and 52 ground-truth pixels (row-49 part plus (49, 50) and (49, 51))
    // have a predicted one. P = 52/100, R = 52/110, F = 2PR/(P+R) = 104/210.
    let gt = mask(100, 100, |x, y| if x < 50 { y < 50 } else { y < 60 });
    let f = boundary_f_measure(&top(50), &gt, 100, 100).unwrap();
    assert!((f - 104.0 / 210.0).abs() < 1e-12, "{f}");
}

#[test]
fn boundary_f_edge_cases() {
    let none = vec![false; 100 * 100];
    let full = vec![true; 100 * 100];
    // A mask that fills the image has no boundary (image borders are not boundaries).
    assert_eq!(boundary_f_measure(&full, &none, 100, 100).unwrap(), 1.0);
    assert_eq!(boundary_f_measure(&none, &none, 100, 100).unwrap(), 1.0);
    assert_eq!(boundary_f_measure(&top(50), &none, 100, 100).unwrap(), 0.0);
    assert_eq!(boundary_f_measure(&none, &top(50), 100, 100).unwrap(), 0.0);
    assert!(boundary_f_measure(&none, &none, 0, 100).is_err());
    assert!(boundary_f_measure(&none[..10], &none, 100, 100).is_err());
    assert!(boundary_f_measure_with(&none, &none, 100, 100, f64::NAN).is_err());
}

#[test]
fn psnr_cases() {
    let (w, h) = (6, 5);
    let gt: Vec<f32> = (0..w * h * 3).map(|k| (k % 11) as f32 / 20.0).collect();
    // Off by 0.1 inside the mask, by 0.5 outside: the masked PSNR sees only 0.1 -> 20 dB.
    let m = mask(w, h, |x, _| x < 3);
    let pred: Vec<f32> = gt
        .iter()
        .enumerate()
        .map(|(k, v)| v + if m[k / 3] { 0.1 } else { 0.5 })
        .collect();
    let masked = masked_psnr(&pred, &gt, Some(&m), w, h, 3).unwrap();
    assert!((masked - 20.0).abs() < 1e-4, "{masked}");
    // Unmasked: MSE = (0.01 + 0.25) / 2 = 0.13.
    let full = masked_psnr(&pred, &gt, None, w, h, 3).unwrap();
    assert!(
        (full - 10.0 * (1.0 / 0.13f64).log10()).abs() < 1e-4,
        "{full}"
    );
    assert_eq!(masked_psnr(&gt, &gt, None, w, h, 3).unwrap(), f64::INFINITY);
    assert!(masked_psnr(&gt, &gt, Some(&vec![false; w * h]), w, h, 3).is_err());
    assert!(masked_psnr(&gt[1..], &gt, None, w, h, 3).is_err());
}

/// SSIM by the textbook definition: a direct 2-D weighted window per pixel (zero outside the
/// image), no separable filtering.
fn direct_ssim_map(x: &[f64], y: &[f64], w: usize, h: usize) -> Vec<f64> {
    let g: Vec<f64> = (0..11)
        .map(|i| (-((i as f64 - 5.0).powi(2)) / (2.0 * 1.5 * 1.5)).exp())
        .collect();
    let s: f64 = g.iter().sum();
    let (c1, c2) = (1e-4, 9e-4);
    let mut out = vec![0.0; w * h];
    for py in 0..h {
        for px in 0..w {
            let (mut mx, mut my, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for dy in 0..11 {
                for dx in 0..11 {
                    let (qx, qy) = (px as i64 + dx as i64 - 5, py as i64 + dy as i64 - 5);
                    if qx < 0 || qy < 0 || qx >= w as i64 || qy >= h as i64 {
                        continue;
                    }
                    let wt = g[dx] * g[dy] / (s * s);
                    let k = qy as usize * w + qx as usize;
                    mx += wt * x[k];
                    my += wt * y[k];
                    xx += wt * x[k] * x[k];
                    yy += wt * y[k] * y[k];
                    xy += wt * x[k] * y[k];
                }
            }
            let (vx, vy, cxy) = (xx - mx * mx, yy - my * my, xy - mx * my);
            out[py * w + px] = ((2.0 * mx * my + c1) * (2.0 * cxy + c2))
                / ((mx * mx + my * my + c1) * (vx + vy + c2));
        }
    }
    out
}

#[test]
fn ssim_matches_direct_formula() {
    let (w, h) = (23, 17);
    let x: Vec<f32> = (0..w * h)
        .map(|k| ((k * 7919) % 97) as f32 / 97.0)
        .collect();
    let y: Vec<f32> = x
        .iter()
        .enumerate()
        .map(|(k, v)| (v * 0.8 + 0.1 * ((k % 5) as f32) / 5.0).min(1.0))
        .collect();
    let map = direct_ssim_map(
        &x.iter().map(|&v| f64::from(v)).collect::<Vec<_>>(),
        &y.iter().map(|&v| f64::from(v)).collect::<Vec<_>>(),
        w,
        h,
    );
    let all = masked_ssim(&x, &y, None, w, h, 1).unwrap();
    assert!((all - map.iter().sum::<f64>() / map.len() as f64).abs() < 1e-12);
    let m = mask(w, h, |px, py| (px + py) % 3 == 0);
    let want = map
        .iter()
        .zip(&m)
        .filter(|(_, b)| **b)
        .map(|(v, _)| v)
        .sum::<f64>()
        / m.iter().filter(|b| **b).count() as f64;
    assert!((masked_ssim(&x, &y, Some(&m), w, h, 1).unwrap() - want).abs() < 1e-12);
}

#[test]
fn ssim_closed_forms() {
    let (w, h) = (16, 16);
    let a = vec![0.25f32; w * h * 3];
    assert!((masked_ssim(&a, &a, None, w, h, 3).unwrap() - 1.0).abs() < 1e-12);
    // Constant images: no variance, so SSIM = (2ab + C1) / (a² + b² + C1) where the window
    // lies inside the image. (Near the border the zero padding shrinks both means and the
    // value differs, so compare the centre pixel only.)
    let b = vec![0.75f32; w * h * 3];
    let mut centre = vec![false; w * h];
    centre[8 * w + 8] = true;
    let want = (2.0 * 0.25 * 0.75 + 1e-4) / (0.25f64.powi(2) + 0.75f64.powi(2) + 1e-4);
    let got = masked_ssim(&a, &b, Some(&centre), w, h, 3).unwrap();
    assert!((got - want).abs() < 1e-9, "{got} vs {want}");
}
