//! Per-Gaussian projection to screen space (EWA splatting, as in the original 3DGS).

use glam::{Mat3, Quat, Vec3};

use crate::gaussians::normalize_quat;
use crate::{Camera, Gaussians};

/// Added to the diagonal of every 2-D covariance, px²: the screen-space low-pass filter of EWA
/// splatting / 3DGS, so that every splat covers at least about a pixel.
pub const LOW_PASS_PX2: f32 = 0.3;

/// Largest alpha a single splat may contribute (3DGS caps at 0.99).
pub const MAX_ALPHA: f32 = 0.99;

/// Splat/pixel pairs with a smaller alpha are skipped (3DGS: 1/255).
pub const MIN_ALPHA: f32 = 1.0 / 255.0;

/// A pixel stops compositing when its transmittance would fall below this (3DGS: 1e-4); the
/// splat that would push it below is not drawn.
pub const MIN_TRANSMITTANCE: f32 = 1e-4;

/// Mean-direction clamp of the EWA Jacobian, as a fraction of the image size beyond each edge:
/// 3DGS evaluates the Jacobian at `x/z` clamped to `±1.3 tan(fov_x / 2)`, i.e. 15 % of the
/// width beyond each image edge for a centred principal point; the same for y.
pub const JACOBIAN_GUARD: f32 = 0.15;

/// A Gaussian as seen by one camera: everything the compositor needs.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Splat {
    /// Projected centre, continuous pixel coordinates.
    pub(crate) u: f32,
    pub(crate) v: f32,
    /// Inverse 2-D covariance (conic) `[[a, b], [b, c]]`, 1/px².
    pub(crate) a: f32,
    pub(crate) b: f32,
    pub(crate) c: f32,
    pub(crate) opacity: f32,
    /// `ln(MIN_ALPHA / opacity)`: exponents below this give alpha < MIN_ALPHA, so the pixel
    /// loop can skip `exp` for them.
    pub(crate) min_power: f32,
    /// Row spans: on the row at offset `dy` the pixels with power >= min_power lie within
    /// `sqrt(span_p - span_q dy²) / a` of `u - (b / a) dy`.
    pub(crate) span_p: f32,
    pub(crate) span_q: f32,
    pub(crate) b_over_a: f32,
    pub(crate) inv_a: f32,
    pub(crate) color: [f32; 3],
    /// Camera z of the centre, metres (the sort key and the depth output).
    pub(crate) depth: f32,
    /// Pixel rectangle `[x0, x1) × [y0, y1)` outside which alpha < MIN_ALPHA, clipped to the
    /// image; non-empty.
    pub(crate) x0: u32,
    pub(crate) x1: u32,
    pub(crate) y0: u32,
    pub(crate) y1: u32,
}

/// Projects Gaussian `i`, or `None` when it cannot contribute to any pixel: centre not beyond
/// the near plane, opacity below [`MIN_ALPHA`], non-finite projection (overflowing inputs), or
/// no pixel inside its `MIN_ALPHA` ellipse.
pub(crate) fn project(g: &Gaussians, i: usize, cam: &Camera) -> Option<Splat> {
    let opacity = g.opacities[i];
    // alpha = opacity * exp(power) with power <= 0: below MIN_ALPHA everywhere.
    if opacity < MIN_ALPHA {
        return None;
    }
    let t = cam.world_to_camera(g.means[i]);
    if t.z.is_nan() || t.z <= cam.near {
        return None;
    }
    let (w, h) = (cam.width as f32, cam.height as f32);
    // EWA: the perspective map linearised at the centre. 3DGS clamps the direction used for
    // the Jacobian so that far off-screen Gaussians do not smear across the whole image.
    let lim_x = (
        (-cam.cx - JACOBIAN_GUARD * w) / cam.fx,
        (w - cam.cx + JACOBIAN_GUARD * w) / cam.fx,
    );
    let lim_y = (
        (-cam.cy - JACOBIAN_GUARD * h) / cam.fy,
        (h - cam.cy + JACOBIAN_GUARD * h) / cam.fy,
    );
    let tx = (t.x / t.z).clamp(lim_x.0, lim_x.1) * t.z;
    let ty = (t.y / t.z).clamp(lim_y.0, lim_y.1) * t.z;
    let inv_z = 1.0 / t.z;
    // Rows of J (2 x 3): j0 = (j00, 0, j02), j1 = (0, j11, j12); the third row of the usual
    // 3 x 3 form does not affect the 2-D block.
    let (j00, j02) = (cam.fx * inv_z, -cam.fx * tx * inv_z * inv_z);
    let (j11, j12) = (cam.fy * inv_z, -cam.fy * ty * inv_z * inv_z);
    // Σ_cam = M Mᵀ with M = W R S (camera rotation, Gaussian rotation, scales), so
    // J Σ_cam Jᵀ = (Mᵀ j0, Mᵀ j1) Gram matrix: no 3 x 3 covariance is formed.
    let m = cam.rotation * Mat3::from_quat(unit_quat(g.rotations[i]));
    let sc = g.scales[i];
    let cols = [m.x_axis * sc.x, m.y_axis * sc.y, m.z_axis * sc.z];
    let v0 = Vec3::from_array(cols.map(|c| j00 * c.x + j02 * c.z));
    let v1 = Vec3::from_array(cols.map(|c| j11 * c.y + j12 * c.z));
    let cov_a = v0.dot(v0) + LOW_PASS_PX2;
    let cov_b = v0.dot(v1);
    let cov_c = v1.dot(v1) + LOW_PASS_PX2;
    let det = cov_a * cov_c - cov_b * cov_b;
    if !(det > 0.0 && det.is_finite()) {
        return None;
    }
    let u = cam.fx * t.x * inv_z + cam.cx;
    let v = cam.fy * t.y * inv_z + cam.cy;
    let min_power = (MIN_ALPHA / opacity).ln();
    // Pixels with alpha >= MIN_ALPHA satisfy d² = xᵀ Σ⁻¹ x <= -2 min_power: an ellipse whose
    // bounding box has half-widths sqrt(d² Σxx), sqrt(d² Σyy). A 1e-3 relative margin plus
    // 1e-3 px keeps pixels that rounding in the compositor might still let through.
    let d2 = -2.0 * min_power;
    let rx = (d2 * cov_a).sqrt() * 1.001 + 1e-3;
    let ry = (d2 * cov_c).sqrt() * 1.001 + 1e-3;
    if !(u.is_finite() && v.is_finite() && rx.is_finite() && ry.is_finite()) {
        return None;
    }
    // Pixel i is sampled at i + 0.5: pixels with centres in [u - rx, u + rx].
    let x0 = (u - rx - 0.5).ceil().clamp(0.0, w);
    let x1 = (u + rx - 0.5).floor().clamp(-1.0, w - 1.0) + 1.0;
    let y0 = (v - ry - 0.5).ceil().clamp(0.0, h);
    let y1 = (v + ry - 0.5).floor().clamp(-1.0, h - 1.0) + 1.0;
    if x0 >= x1 || y0 >= y1 {
        return None;
    }
    let (a, b, c) = (cov_c / det, -cov_b / det, cov_a / det);
    Some(Splat {
        u,
        v,
        a,
        b,
        c,
        opacity,
        min_power,
        // a dx² + 2 b dx dy + c dy² <= -2 min_power, solved for dx.
        span_p: -2.0 * a * min_power,
        span_q: a * c - b * b,
        b_over_a: b / a,
        inv_a: 1.0 / a,
        color: g.colors[i],
        depth: t.z,
        x0: x0 as u32,
        x1: x1 as u32,
        y0: y0 as u32,
        y1: y1 as u32,
    })
}

/// Unit quaternion: f32 normalisation in the common case, the f64 path for tiny or huge
/// (but valid) ones whose squared norm under- or overflows.
fn unit_quat(q: Quat) -> Quat {
    let n2 = q.length_squared();
    if n2.is_normal() && n2 > 1e-30 {
        q * n2.sqrt().recip()
    } else {
        normalize_quat(q)
    }
}
