//! Image metrics: mask IoU (J), DAVIS boundary F-measure (F), masked PSNR and masked SSIM.
//!
//! Masks are row-major `&[bool]` of `width * height`; images are row-major, channel-interleaved
//! `&[f32]` (`[y][x][c]`, like `image::Rgb32FImage`) with values in `[0, 1]`.
//!
//! ```
//! use metrics::image::{boundary_f_measure, mask_iou};
//! let (w, h) = (8, 8);
//! let gt: Vec<bool> = (0..w * h).map(|k| (k % w) < 4).collect(); // left half
//! let pred: Vec<bool> = (0..w * h).map(|k| (k % w) < 5).collect(); // one column wider
//! assert!((mask_iou(&pred, &gt)? - 0.8).abs() < 1e-12); // 32 / 40
//! assert_eq!(boundary_f_measure(&pred, &gt, w, h)?, 1.0); // within the 1 px tolerance
//! # Ok::<(), metrics::MetricsError>(())
//! ```

mod boundary;
mod quality;

pub use boundary::{
    BOUNDARY_TOLERANCE, boundary_f_measure, boundary_f_measure_with, boundary_radius,
};
pub use quality::{masked_psnr, masked_ssim};

use crate::error::MetricsError;

/// Pixels whose rendered opacity exceeds this count as foreground when a render is turned
/// into a mask (the PGRD evaluation thresholds renders at 0.1).
pub const RENDER_MASK_THRESHOLD: f32 = 0.1;

/// Foreground mask of an opacity (alpha) image: `alpha > threshold` per pixel.
pub fn threshold_mask(alpha: &[f32], threshold: f32) -> Vec<bool> {
    alpha.iter().map(|&a| a > threshold).collect()
}

/// J: intersection over union of two masks. Two empty masks give 1 (DAVIS convention: nothing
/// to find, nothing found).
///
/// # Errors
/// Masks of different lengths.
pub fn mask_iou(pred: &[bool], gt: &[bool]) -> Result<f64, MetricsError> {
    check_len(pred.len(), gt.len(), "prediction mask vs ground-truth mask")?;
    let (mut inter, mut union) = (0usize, 0usize);
    for (&p, &g) in pred.iter().zip(gt) {
        inter += usize::from(p && g);
        union += usize::from(p || g);
    }
    if union == 0 {
        return Ok(1.0);
    }
    Ok(inter as f64 / union as f64)
}

pub(crate) fn check_len(
    actual: usize,
    expected: usize,
    what: &'static str,
) -> Result<(), MetricsError> {
    if actual != expected {
        return Err(MetricsError::ImageSize {
            actual,
            expected,
            what,
        });
    }
    Ok(())
}

pub(crate) fn check_dims(width: usize, height: usize) -> Result<usize, MetricsError> {
    match width.checked_mul(height) {
        Some(n) if n > 0 => Ok(n),
        _ => Err(MetricsError::InvalidImage(format!(
            "bad image size {width} x {height}"
        ))),
    }
}
