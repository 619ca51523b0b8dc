//! Inner loops of one substep. Every loop is a plain pass over contiguous arrays with no
//! allocation. Particle arrays are padded to a power-of-two length and indices are masked with
//! `len - 1`, which lets the compiler drop bounds checks from the gather/scatter loops (the
//! indices are already valid, so masking never changes them). Springs arrive grouped so that
//! consecutive springs rarely share a particle, which keeps read-after-write chains out of the
//! scatters.

use glam::Vec3A;

use crate::params::GROUND_STIFFNESS;

/// One spring of the dashpot sweeps: endpoints and the per-sweep impulse weight (kg) already
/// divided by each end's mass (0 for a kinematic end).
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct DampSpring {
    pub a: u32,
    pub b: u32,
    pub wa: f32,
    pub wb: f32,
}

/// Elastic spring forces: adds `k (l - l0) d` to `f[a]` and subtracts it from `f[b]`
/// (`d` = unit vector from a to b), and stores `d` per spring for the dashpot sweeps.
/// `x.len()` and `f.len()` must equal the same power of two.
pub(crate) fn elastic(
    springs: &[[u32; 2]],
    stiffness: &[f32],
    rest: &[f32],
    x: &[Vec3A],
    f: &mut [Vec3A],
    dir: &mut [Vec3A],
) {
    let mask = x.len() - 1;
    let (x, f) = (&x[..=mask], &mut f[..=mask]);
    for ((&[a, b], (&k, &l0)), d_out) in springs
        .iter()
        .zip(stiffness.iter().zip(rest))
        .zip(dir.iter_mut())
    {
        let (a, b) = (a as usize & mask, b as usize & mask);
        let d = x[b] - x[a];
        let l = d.length();
        // Coincident particles (l = 0) give d = 0: no force and no damping this substep.
        let u = d * (1.0 / l.max(f32::MIN_POSITIVE));
        let fs = u * (k * (l - l0));
        f[a] += fs;
        f[b] -= fs;
        *d_out = u;
    }
}

/// Implicit dashpot: a forward then a backward Gauss–Seidel sweep of pair impulses. Spring s
/// with relative axial velocity `rel = d·(v_b - v_a)` applies the impulse `w_s rel` along `d`,
/// `+` to a and `-` to b (momentum is conserved). Each impulse multiplies that pair's `rel` by
/// `1 - w_s / mu_s` in [0, 1] (never adding energy), and the palindromic forward + backward
/// product is a symmetric contraction of the velocities (docs/physics.md).
/// `v.len()` must be a power of two.
pub(crate) fn damping_sweeps(springs: &[DampSpring], dir: &[Vec3A], v: &mut [Vec3A]) {
    let mask = v.len() - 1;
    let v = &mut v[..=mask];
    for (s, &u) in springs.iter().zip(dir) {
        pair_impulse(s, u, mask, v);
    }
    for (s, &u) in springs.iter().zip(dir).rev() {
        pair_impulse(s, u, mask, v);
    }
}

#[inline(always)]
fn pair_impulse(s: &DampSpring, u: Vec3A, mask: usize, v: &mut [Vec3A]) {
    let (a, b) = (s.a as usize & mask, s.b as usize & mask);
    let imp = u * u.dot(v[b] - v[a]);
    v[a] += imp * s.wa;
    v[b] -= imp * s.wb;
}

/// Ground penalty force on free particles below `h`.
pub(crate) fn ground_force(h: f32, x: &[Vec3A], inv_m: &[f32], f: &mut [Vec3A]) {
    for ((xi, fi), &im) in x.iter().zip(f.iter_mut()).zip(inv_m) {
        let depth = h - xi.z;
        if depth > 0.0 && im > 0.0 {
            fi.z += GROUND_STIFFNESS * depth;
        }
    }
}

/// Kick: `v += dt (f / m + g)`, then clear `f` for the next substep (one pass instead of two).
pub(crate) fn kick(dt: f32, gravity: Vec3A, f: &mut [Vec3A], inv_m: &[f32], v: &mut [Vec3A]) {
    for ((vi, fi), &im) in v.iter_mut().zip(f.iter_mut()).zip(inv_m) {
        *vi += dt * (*fi * im + gravity);
        *fi = Vec3A::ZERO;
    }
}

/// Drift: `x += dt v`.
pub(crate) fn drift(dt: f32, v: &[Vec3A], x: &mut [Vec3A]) {
    for (xi, vi) in x.iter_mut().zip(v) {
        *xi += dt * *vi;
    }
}
