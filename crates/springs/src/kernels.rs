//! Inner loops of one substep. Every loop is a plain pass over contiguous arrays with no
//! allocation. Particle arrays are padded to a power-of-two length and indices are masked with
//! `len - 1`, which lets the compiler drop bounds checks from the gather/scatter loops (the
//! indices are already valid, so masking never changes them). Springs arrive grouped so that
//! consecutive springs rarely share a particle, which keeps read-after-write chains out of the
//! scatters.

use glam::{Vec3A, Vec4};

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
    let blocks = springs.len() / 4 * 4;
    for (((ab, k), l0), d_out) in springs[..blocks]
        .chunks_exact(4)
        .zip(stiffness[..blocks].chunks_exact(4))
        .zip(rest[..blocks].chunks_exact(4))
        .zip(dir[..blocks].chunks_exact_mut(4))
    {
        let ab = block_ends(ab, mask);
        let (d, l, inv) = block_geometry(&ab, x);
        let s = Vec4::from_slice(k) * (l - Vec4::from_slice(l0));
        for j in 0..4 {
            let u = from_lanes(d[0] * inv, d[1] * inv, d[2] * inv, j);
            let fs = u * s[j];
            f[ab[j].0] += fs;
            f[ab[j].1] -= fs;
            d_out[j] = u;
        }
    }
    for ((&[a, b], (&k, &l0)), d_out) in springs[blocks..]
        .iter()
        .zip(stiffness[blocks..].iter().zip(&rest[blocks..]))
        .zip(dir[blocks..].iter_mut())
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

/// Elastic forces plus the reference's explicit dashpot in one pass: adds
/// `(k (l - l0) + c u·(v_b - v_a)) u` to `f[a]` and subtracts it from `f[b]`.
/// `x.len()`, `v.len()` and `f.len()` must equal the same power of two.
pub(crate) fn elastic_explicit_dashpot(
    springs: &[[u32; 2]],
    stiffness: &[f32],
    damping: &[f32],
    rest: &[f32],
    x: &[Vec3A],
    v: &[Vec3A],
    f: &mut [Vec3A],
) {
    let mask = x.len() - 1;
    let (x, v, f) = (&x[..=mask], &v[..=mask], &mut f[..=mask]);
    let blocks = springs.len() / 4 * 4;
    for ((ab, k), (c, l0)) in springs[..blocks]
        .chunks_exact(4)
        .zip(stiffness[..blocks].chunks_exact(4))
        .zip(
            damping[..blocks]
                .chunks_exact(4)
                .zip(rest[..blocks].chunks_exact(4)),
        )
    {
        let ab = block_ends(ab, mask);
        let (d, l, inv) = block_geometry(&ab, x);
        let u = [d[0] * inv, d[1] * inv, d[2] * inv];
        let dv = transpose(std::array::from_fn(|j| v[ab[j].1] - v[ab[j].0]));
        let rel = u[0] * dv[0] + u[1] * dv[1] + u[2] * dv[2];
        let s = Vec4::from_slice(k) * (l - Vec4::from_slice(l0)) + Vec4::from_slice(c) * rel;
        for j in 0..4 {
            let fs = from_lanes(u[0], u[1], u[2], j) * s[j];
            f[ab[j].0] += fs;
            f[ab[j].1] -= fs;
        }
    }
    for (&[a, b], ((&k, &c), &l0)) in springs[blocks..].iter().zip(
        stiffness[blocks..]
            .iter()
            .zip(&damping[blocks..])
            .zip(&rest[blocks..]),
    ) {
        let (a, b) = (a as usize & mask, b as usize & mask);
        let d = x[b] - x[a];
        let l = d.length();
        let u = d * (1.0 / l.max(f32::MIN_POSITIVE));
        let fs = u * (k * (l - l0) + c * u.dot(v[b] - v[a]));
        f[a] += fs;
        f[b] -= fs;
    }
}

// Four springs at a time: positions are gathered per spring, then transposed so that the
// arithmetic (square root and division included) runs once per four springs in SIMD lanes.
// Every lane computes exactly what the one-spring loop computes, in the same order
// (`(x² + y²) + z²`, as glam's `dot`), and forces are scattered spring by spring in order, so
// the results are bit-identical to that loop.

#[inline(always)]
fn block_ends(ab: &[[u32; 2]], mask: usize) -> [(usize, usize); 4] {
    std::array::from_fn(|j| (ab[j][0] as usize & mask, ab[j][1] as usize & mask))
}

/// Per-component lanes `[x, y, z]` of `d = x_b - x_a`, the lengths `l` and `1 / max(l, tiny)`.
#[inline(always)]
fn block_geometry(ab: &[(usize, usize); 4], x: &[Vec3A]) -> ([Vec4; 3], Vec4, Vec4) {
    let d = transpose(std::array::from_fn(|j| x[ab[j].1] - x[ab[j].0]));
    let l2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    let l = sqrt4(l2);
    let inv = Vec4::ONE / l.max(Vec4::splat(f32::MIN_POSITIVE));
    (d, l, inv)
}

#[inline(always)]
fn transpose(p: [Vec3A; 4]) -> [Vec4; 3] {
    [
        Vec4::new(p[0].x, p[1].x, p[2].x, p[3].x),
        Vec4::new(p[0].y, p[1].y, p[2].y, p[3].y),
        Vec4::new(p[0].z, p[1].z, p[2].z, p[3].z),
    ]
}

#[inline(always)]
fn from_lanes(x: Vec4, y: Vec4, z: Vec4, j: usize) -> Vec3A {
    Vec3A::new(x[j], y[j], z[j])
}

/// Lane-wise square root; written per lane, compiled to one packed instruction.
#[inline(always)]
fn sqrt4(v: Vec4) -> Vec4 {
    let a = v.to_array();
    Vec4::from_array([a[0].sqrt(), a[1].sqrt(), a[2].sqrt(), a[3].sqrt()])
}

/// Implicit dashpot: a forward then a backward Gauss–Seidel sweep of pair impulses. Spring s
/// with relative axial velocity `rel = d·(v_b - v_a)` applies the impulse `w_s rel` along `d`,
/// `+` to a and `-` to b (momentum is conserved). Each impulse multiplies that pair's `rel` by
/// `1 - w_s / mu_s` in [0, 1] (never adding energy), and the palindromic forward + backward
/// product is a symmetric contraction of the velocities (docs/physics.md).
/// `v.len()` must be a power of two.
pub(crate) fn damping_sweeps(springs: &[DampSpring], dir: &[Vec3A], v: &mut [Vec3A]) {
    damping_forward(springs, dir, v);
    damping_backward(springs, dir, v);
}

/// The forward half of [`damping_sweeps`].
pub(crate) fn damping_forward(springs: &[DampSpring], dir: &[Vec3A], v: &mut [Vec3A]) {
    let mask = v.len() - 1;
    let v = &mut v[..=mask];
    for (s, &u) in springs.iter().zip(dir) {
        pair_impulse(s, u, mask, v);
    }
}

/// The backward half of [`damping_sweeps`].
pub(crate) fn damping_backward(springs: &[DampSpring], dir: &[Vec3A], v: &mut [Vec3A]) {
    let mask = v.len() - 1;
    let v = &mut v[..=mask];
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A small random scene: 16 particles (a power of two), 23 springs (five blocks of four
    /// plus a tail of three), random positions, velocities, stiffness, damping and rest lengths.
    #[allow(clippy::type_complexity)]
    fn scene() -> (
        Vec<[u32; 2]>,
        Vec<f32>,
        Vec<f32>,
        Vec<f32>,
        Vec<Vec3A>,
        Vec<Vec3A>,
    ) {
        let mut state = 0x9e37_79b9_7f4a_7c15_u64;
        let mut rnd = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32
        };
        let x: Vec<Vec3A> = (0..16)
            .map(|_| Vec3A::new(rnd(), rnd(), rnd()) * 0.05)
            .collect();
        let v: Vec<Vec3A> = (0..16)
            .map(|_| Vec3A::new(rnd(), rnd(), rnd()) - 0.5)
            .collect();
        let springs: Vec<[u32; 2]> = (0..23u32).map(|s| [s % 16, (s * 7 + 3) % 16]).collect();
        let k = springs.iter().map(|_| 10.0 + 5e4 * rnd()).collect();
        let c = springs.iter().map(|_| 1e3 * rnd()).collect();
        let rest = springs.iter().map(|_| 0.05 * rnd()).collect();
        (springs, k, c, rest, x, v)
    }

    /// The four-spring blocks give exactly (bit for bit) what the one-spring loop gives.
    #[test]
    fn blocks_equal_one_spring_at_a_time() {
        let (springs, k, c, rest, x, v) = scene();
        let n = springs.len();
        let (mut f, mut dir) = (vec![Vec3A::ZERO; 16], vec![Vec3A::ZERO; n]);
        elastic(&springs, &k, &rest, &x, &mut f, &mut dir);
        let mut fe = vec![Vec3A::ZERO; 16];
        elastic_explicit_dashpot(&springs, &k, &c, &rest, &x, &v, &mut fe);
        let (mut f1, mut dir1, mut fe1) = (
            vec![Vec3A::ZERO; 16],
            vec![Vec3A::ZERO; n],
            vec![Vec3A::ZERO; 16],
        );
        for s in 0..n {
            let r = s..s + 1;
            elastic(
                &springs[r.clone()],
                &k[r.clone()],
                &rest[r.clone()],
                &x,
                &mut f1,
                &mut dir1[r.clone()],
            );
            elastic_explicit_dashpot(
                &springs[r.clone()],
                &k[r.clone()],
                &c[r.clone()],
                &rest[r],
                &x,
                &v,
                &mut fe1,
            );
        }
        let bits = |a: &[Vec3A]| {
            a.iter()
                .map(|p| p.to_array().map(f32::to_bits))
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&f), bits(&f1));
        assert_eq!(bits(&dir), bits(&dir1));
        assert_eq!(bits(&fe), bits(&fe1));
        assert!(f.iter().any(|p| p.length() > 0.0) && fe.iter().any(|p| p.length() > 0.0));
    }
}
