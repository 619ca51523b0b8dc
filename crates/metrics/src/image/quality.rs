//! Masked PSNR and SSIM.

use super::{check_dims, check_len};
use crate::error::MetricsError;

/// SSIM Gaussian window: 11 taps, sigma 1.5 px (Wang et al. 2004, and the 3D Gaussian
/// splatting code the splatting baselines use).
const SSIM_TAPS: usize = 11;
const SSIM_SIGMA: f64 = 1.5;
/// Stabilisers for a dynamic range of 1: (0.01 L)² and (0.03 L)².
const SSIM_C1: f64 = 0.01 * 0.01;
const SSIM_C2: f64 = 0.03 * 0.03;

fn check_inputs(
    pred: &[f32],
    gt: &[f32],
    mask: Option<&[bool]>,
    width: usize,
    height: usize,
    channels: usize,
) -> Result<usize, MetricsError> {
    let n = check_dims(width, height)?;
    if channels == 0 {
        return Err(MetricsError::InvalidImage("zero channels".into()));
    }
    check_len(pred.len(), n * channels, "predicted image")?;
    check_len(gt.len(), n * channels, "ground-truth image")?;
    if let Some(m) = mask {
        check_len(m.len(), n, "mask")?;
        if !m.iter().any(|&b| b) {
            return Err(MetricsError::InvalidImage(
                "the mask selects no pixel".into(),
            ));
        }
    }
    if pred.iter().chain(gt).any(|v| !v.is_finite()) {
        return Err(MetricsError::InvalidImage("non-finite pixel value".into()));
    }
    Ok(n)
}

/// PSNR in dB for values in `[0, 1]`: `10 log10(1 / MSE)`, the MSE taken over all channels of
/// the pixels the mask selects (all pixels for `None`). Identical images give `+inf`.
///
/// ```
/// // A 2x1 RGB image, off by 0.1 everywhere: MSE 0.01 -> 20 dB.
/// let gt = [0.2_f32, 0.2, 0.2, 0.5, 0.5, 0.5];
/// let pred: Vec<f32> = gt.iter().map(|v| v + 0.1).collect();
/// let psnr = metrics::image::masked_psnr(&pred, &gt, None, 2, 1, 3)?;
/// assert!((psnr - 20.0).abs() < 1e-4);
/// # Ok::<(), metrics::MetricsError>(())
/// ```
///
/// # Errors
/// Buffer sizes not matching `width * height (* channels)`, an all-false mask, or non-finite
/// values.
pub fn masked_psnr(
    pred: &[f32],
    gt: &[f32],
    mask: Option<&[bool]>,
    width: usize,
    height: usize,
    channels: usize,
) -> Result<f64, MetricsError> {
    let n = check_inputs(pred, gt, mask, width, height, channels)?;
    let (mut sum, mut count) = (0.0f64, 0usize);
    for k in 0..n {
        if mask.is_some_and(|m| !m[k]) {
            continue;
        }
        for c in 0..channels {
            let d = f64::from(pred[k * channels + c]) - f64::from(gt[k * channels + c]);
            sum += d * d;
        }
        count += channels;
    }
    let mse = sum / count as f64;
    Ok(10.0 * (1.0 / mse).log10())
}

/// Mean SSIM for values in `[0, 1]` over the pixels the mask selects (all for `None`) and all
/// channels. The SSIM map is computed per channel on the whole image with an 11 x 11 Gaussian
/// window (sigma 1.5), zero padding at the borders (a "same" convolution, as the 3D Gaussian
/// splatting code computes it), C1 = 0.01², C2 = 0.03²; the mask only selects which map values
/// are averaged.
///
/// # Errors
/// As [`masked_psnr`].
pub fn masked_ssim(
    pred: &[f32],
    gt: &[f32],
    mask: Option<&[bool]>,
    width: usize,
    height: usize,
    channels: usize,
) -> Result<f64, MetricsError> {
    let n = check_inputs(pred, gt, mask, width, height, channels)?;
    let g = gaussian_taps();
    let mut total = 0.0;
    let mut count = 0usize;
    let mut x = vec![0.0; n];
    let mut y = vec![0.0; n];
    let mut prod = vec![0.0; n];
    for c in 0..channels {
        for k in 0..n {
            x[k] = f64::from(pred[k * channels + c]);
            y[k] = f64::from(gt[k * channels + c]);
        }
        let mu_x = blur(&x, width, height, &g);
        let mu_y = blur(&y, width, height, &g);
        prod.iter_mut().zip(&x).for_each(|(p, v)| *p = v * v);
        let xx = blur(&prod, width, height, &g);
        prod.iter_mut().zip(&y).for_each(|(p, v)| *p = v * v);
        let yy = blur(&prod, width, height, &g);
        prod.iter_mut()
            .zip(x.iter().zip(&y))
            .for_each(|(p, (a, b))| *p = a * b);
        let xy = blur(&prod, width, height, &g);
        for k in 0..n {
            if mask.is_some_and(|m| !m[k]) {
                continue;
            }
            let (mx, my) = (mu_x[k], mu_y[k]);
            let sxx = xx[k] - mx * mx;
            let syy = yy[k] - my * my;
            let sxy = xy[k] - mx * my;
            let num = (2.0 * mx * my + SSIM_C1) * (2.0 * sxy + SSIM_C2);
            let den = (mx * mx + my * my + SSIM_C1) * (sxx + syy + SSIM_C2);
            total += num / den;
            count += 1;
        }
    }
    Ok(total / count as f64)
}

/// Normalised 1-D Gaussian; the 2-D window is its outer product, so blurring is separable.
fn gaussian_taps() -> [f64; SSIM_TAPS] {
    let half = (SSIM_TAPS / 2) as f64;
    let mut g = [0.0; SSIM_TAPS];
    for (i, t) in g.iter_mut().enumerate() {
        let d = i as f64 - half;
        *t = (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = g.iter().sum();
    g.iter_mut().for_each(|t| *t /= s);
    g
}

/// "Same"-size separable convolution with zero padding.
fn blur(img: &[f64], w: usize, h: usize, g: &[f64; SSIM_TAPS]) -> Vec<f64> {
    let half = SSIM_TAPS / 2;
    let mut tmp = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (t, gt) in g.iter().enumerate() {
                let xx = x + t;
                if xx >= half && xx - half < w {
                    s += gt * img[y * w + xx - half];
                }
            }
            tmp[y * w + x] = s;
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for (t, gt) in g.iter().enumerate() {
                let yy = y + t;
                if yy >= half && yy - half < h {
                    s += gt * tmp[(yy - half) * w + x];
                }
            }
            out[y * w + x] = s;
        }
    }
    out
}
