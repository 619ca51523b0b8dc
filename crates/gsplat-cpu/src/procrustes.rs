//! Rotation of an orthogonal Procrustes fit.

use glam::{Mat3, Quat, Vec3};

/// Iterations of the rotation extraction; each is a few dozen flops and convergence from a
/// nearby start takes a handful.
const MAX_ITERS: usize = 40;

/// The rotation `R` that best maps offsets `from[k]` onto `to[k]` in the least-squares sense
/// (maximises `Σ to[k] · R from[k]`), starting the search at `start`.
///
/// With `A = Σ to[k] from[k]ᵀ` this is the rotation closest to `A` (its polar factor). It is
/// found by the iteration of Müller, Bender, Chentanez and Macklin ("A Robust Method to Extract
/// the Rotational Part of Deformations", 2016): rotate `R` about
/// `ω = Σᵢ rᵢ × aᵢ / |Σᵢ rᵢ · aᵢ|` (columns `rᵢ` of `R`, `aᵢ` of `A`) until `ω` vanishes. Unlike
/// an SVD it never jumps: where the offsets do not determine the rotation (collinear
/// neighbours, as along a straight rope, leave the twist free; coincident ones leave it all
/// free) the undetermined part keeps its value from `start`.
pub(crate) fn fit_rotation(from: &[Vec3], to: &[Vec3], start: Quat) -> Quat {
    let mut a = Mat3::ZERO;
    for (p, q) in from.iter().zip(to) {
        a += Mat3::from_cols(*q * p.x, *q * p.y, *q * p.z);
    }
    // Scale-free: the stopping rule and the 1e-9 guard below then mean the same thing for
    // millimetre and metre offsets.
    let norm = a.to_cols_array().iter().map(|v| v * v).sum::<f32>().sqrt();
    if !(norm > 0.0 && norm.is_finite()) {
        return start;
    }
    let a = a * (1.0 / norm);
    let mut q = start.normalize();
    for _ in 0..MAX_ITERS {
        let r = Mat3::from_quat(q);
        let torque = r.x_axis.cross(a.x_axis) + r.y_axis.cross(a.y_axis) + r.z_axis.cross(a.z_axis);
        let align = r.x_axis.dot(a.x_axis) + r.y_axis.dot(a.y_axis) + r.z_axis.dot(a.z_axis);
        let omega = torque / (align.abs() + 1e-9);
        let angle = omega.length();
        if !angle.is_finite() || angle <= 1e-7 {
            break;
        }
        q = (Quat::from_axis_angle(omega / angle, angle) * q).normalize();
    }
    q
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_known_rotation() {
        let truth = Quat::from_euler(glam::EulerRot::XYZ, 0.3, -0.5, 0.9);
        let from = [Vec3::X, Vec3::Y, Vec3::Z, Vec3::new(0.3, -0.2, 0.7)];
        let to: Vec<Vec3> = from.iter().map(|p| truth * *p).collect();
        let q = fit_rotation(&from, &to, Quat::IDENTITY);
        assert!(q.dot(truth).abs() > 1.0 - 1e-6, "{q} vs {truth}");
    }

    #[test]
    fn collinear_offsets_keep_the_start_twist() {
        // Offsets along x, unchanged: any rotation about x fits; the start's twist is kept.
        let from = [Vec3::X, -Vec3::X * 2.0];
        let start = Quat::from_rotation_x(0.4);
        let q = fit_rotation(&from, &from, start);
        assert!(q.dot(start).abs() > 1.0 - 1e-6);
    }

    #[test]
    fn no_offsets_give_the_start() {
        assert_eq!(
            fit_rotation(&[Vec3::ZERO], &[Vec3::ZERO], Quat::IDENTITY),
            Quat::IDENTITY
        );
    }
}
