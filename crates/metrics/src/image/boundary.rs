//! DAVIS boundary F-measure.

use super::{check_dims, check_len};
use crate::error::MetricsError;

/// DAVIS's boundary tolerance as a fraction of the image diagonal.
pub const BOUNDARY_TOLERANCE: f64 = 0.008;

/// Matching radius in pixels for a `width x height` image and a tolerance given as a fraction
/// of the diagonal: `ceil(tolerance * sqrt(w^2 + h^2))`.
pub fn boundary_radius(width: usize, height: usize, tolerance: f64) -> usize {
    let diag = (width as f64).hypot(height as f64);
    (tolerance * diag).ceil() as usize
}

/// F: the DAVIS boundary F-measure of a predicted mask against a ground-truth mask, with the
/// standard tolerance (dilation radius `ceil(0.008 * diagonal)` px).
///
/// Boundary pixels are foreground/background changes towards the right, lower and lower-right
/// neighbour (DAVIS's `seg2bmap` for same-size maps). A predicted boundary pixel is correct when
/// a ground-truth boundary pixel lies within a disk of the radius (`dx² + dy² <= r²`), and vice
/// versa for recall; F = 2PR / (P + R). With no boundary on either side F = 1; with a boundary
/// on one side only, F = 0.
///
/// # Errors
/// Zero-sized images or masks not of `width * height` pixels.
pub fn boundary_f_measure(
    pred: &[bool],
    gt: &[bool],
    width: usize,
    height: usize,
) -> Result<f64, MetricsError> {
    boundary_f_measure_with(pred, gt, width, height, BOUNDARY_TOLERANCE)
}

/// As [`boundary_f_measure`] with another tolerance (fraction of the diagonal; DAVIS treats
/// values `>= 1` as a radius in pixels, and so does this function).
///
/// # Errors
/// Zero-sized images, masks not of `width * height` pixels, or a negative / non-finite
/// tolerance.
pub fn boundary_f_measure_with(
    pred: &[bool],
    gt: &[bool],
    width: usize,
    height: usize,
    tolerance: f64,
) -> Result<f64, MetricsError> {
    let n = check_dims(width, height)?;
    check_len(pred.len(), n, "prediction mask")?;
    check_len(gt.len(), n, "ground-truth mask")?;
    if !(tolerance.is_finite() && tolerance >= 0.0) {
        return Err(MetricsError::InvalidImage(format!(
            "bad boundary tolerance {tolerance}"
        )));
    }
    let radius = if tolerance >= 1.0 {
        tolerance.ceil() as usize
    } else {
        boundary_radius(width, height, tolerance)
    };
    let pb = boundary_map(pred, width, height);
    let gb = boundary_map(gt, width, height);
    let n_pred = pb.iter().filter(|&&b| b).count();
    let n_gt = gb.iter().filter(|&&b| b).count();
    let (precision, recall) = match (n_pred, n_gt) {
        (0, 0) => (1.0, 1.0),
        (0, _) => (1.0, 0.0),
        (_, 0) => (0.0, 1.0),
        _ => {
            let pd = dilate(&pb, width, height, radius);
            let gd = dilate(&gb, width, height, radius);
            let pred_hit = pb.iter().zip(&gd).filter(|(b, d)| **b && **d).count();
            let gt_hit = gb.iter().zip(&pd).filter(|(b, d)| **b && **d).count();
            (pred_hit as f64 / n_pred as f64, gt_hit as f64 / n_gt as f64)
        }
    };
    if precision + recall == 0.0 {
        return Ok(0.0);
    }
    Ok(2.0 * precision * recall / (precision + recall))
}

/// One-pixel-wide boundary of a mask: pixels that differ from their right, lower or
/// lower-right neighbour. In the last row only the right neighbour counts, in the last column
/// only the lower one, and the bottom-right pixel is never a boundary (so a mask touching the
/// image border gets no boundary along that border).
fn boundary_map(mask: &[bool], w: usize, h: usize) -> Vec<bool> {
    let at = |x: usize, y: usize| mask[y * w + x];
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let s = at(x, y);
            let right = x + 1 < w;
            let down = y + 1 < h;
            out[y * w + x] = match (right, down) {
                (true, true) => s != at(x + 1, y) || s != at(x, y + 1) || s != at(x + 1, y + 1),
                (true, false) => s != at(x + 1, y),
                (false, true) => s != at(x, y + 1),
                (false, false) => false,
            };
        }
    }
    out
}

/// Binary dilation with a disk `dx² + dy² <= r²`; pixels outside the image are ignored.
fn dilate(map: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    let ri = r as isize;
    let offsets: Vec<(isize, isize)> = (-ri..=ri)
        .flat_map(|dy| (-ri..=ri).map(move |dx| (dx, dy)))
        .filter(|(dx, dy)| dx * dx + dy * dy <= ri * ri)
        .collect();
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            if !map[y * w + x] {
                continue;
            }
            for &(dx, dy) in &offsets {
                let (xx, yy) = (x as isize + dx, y as isize + dy);
                if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                    out[yy as usize * w + xx as usize] = true;
                }
            }
        }
    }
    out
}
