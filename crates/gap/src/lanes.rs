//! Four springs at a time for the per-spring effects (nonlinear elasticity, plasticity), which
//! otherwise spend their substep on one square root and two divisions per spring, one lane at
//! a time: the profile of a sloth diagnosis had the strain term at 41 % of the CPU time, more
//! than the backbone's own elastic pass.
//!
//! Only the square roots and divisions run in SIMD lanes; every lane computes exactly what the
//! one-spring code computes, in the same order, and forces are scattered spring by spring in
//! order, so results are bit-identical to the one-spring loops (tested in `forces`). Each lane's
//! `|d|` sums `(x² + y²) + z²` as glam's `Vec3A::length` does.

use glam::{Vec3A, Vec4};

/// `d = x_b − x_a` of four springs as component lanes `[x, y, z]`, and `|d|` per lane.
#[inline(always)]
pub(crate) fn geometry(x: &[Vec3A], ab: &[[u32; 2]]) -> ([Vec4; 3], Vec4) {
    let d: [Vec3A; 4] = std::array::from_fn(|j| x[ab[j][1] as usize] - x[ab[j][0] as usize]);
    let c = [
        Vec4::new(d[0].x, d[1].x, d[2].x, d[3].x),
        Vec4::new(d[0].y, d[1].y, d[2].y, d[3].y),
        Vec4::new(d[0].z, d[1].z, d[2].z, d[3].z),
    ];
    let l2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
    (c, sqrt(l2))
}

/// Lane `j` of component lanes as a vector.
#[inline(always)]
pub(crate) fn lane(c: &[Vec4; 3], j: usize) -> Vec3A {
    Vec3A::new(c[0][j], c[1][j], c[2][j])
}

/// Lane-wise square root; written per lane, compiled to one packed instruction.
#[inline(always)]
fn sqrt(v: Vec4) -> Vec4 {
    let a = v.to_array();
    Vec4::from_array([a[0].sqrt(), a[1].sqrt(), a[2].sqrt(), a[3].sqrt()])
}
