//! Lanczos estimate of the largest eigenvalue of the springs' mass-weighted stiffness matrix,
//! `M^-1 K`, for [`crate::Substep::Spectral`].
//!
//! Gershgorin's bound (the default substep) assumes every neighbour of a particle moves against
//! it at once, which the neighbours' own springs forbid; on our scenes it is 1.8–3.3× the true
//! largest eigenvalue. Explicit finite-element codes estimate the critical time step from the
//! assembled stiffness instead ("global estimation"); this is the same idea with a few dozen
//! Lanczos steps on `A = M^-1/2 K M^-1/2` (symmetric, same eigenvalues as `M^-1 K`).

use glam::DVec3;

/// Lanczos steps (each one product with the stiffness matrix). Ritz values approach the top of
/// the spectrum from below; 64 steps leave well under 1 % on our scenes (`tests/spectral.rs`).
const STEPS: usize = 64;

/// Tension fractions `1 − l0 / l` up to this are rounding, not stretch (see `largest_eigenvalue`).
const TINY_TENSION: f64 = 1e-5;

/// One spring's part of `A = M^-1/2 K M^-1/2`: with `g_a = sqrt(k / m_a) u` and
/// `g_b = sqrt(k / m_b) u`, its axial block maps `q` to `-(g_b·q_b - g_a·q_a) g_a` at `a` and
/// `+(…) g_b` at `b`. Stretched springs add the tension block `k t (I - u uᵀ)`, kept apart
/// because it is rare at rest.
struct Axial {
    a: usize,
    b: usize,
    ga: DVec3,
    gb: DVec3,
}

/// Tension part `k t (I − u uᵀ)` of a stretched spring (`t = 1 − l0 / l > 0`; a zero-length
/// spring has `t = 1` and no axial part, so its block is `k I`).
struct Tension {
    a: usize,
    b: usize,
    u: DVec3,
    /// `k t`, N/m.
    kt: f64,
}

/// Largest eigenvalue (1/s²) of `M^-1 K` for springs `springs` with stiffness `k` (N/m) and
/// rest lengths `rest` (m) at positions `x` (m), masses given by their inverses `inv_m` (1/kg).
/// `K` is the springs' Hessian at `x` with compressed springs' (negative) tension part left
/// out, which can only raise the largest eigenvalue. A deterministic start vector makes the
/// result reproducible.
pub(crate) fn largest_eigenvalue(
    springs: &[[u32; 2]],
    k: &[f32],
    rest: &[f32],
    x: &[glam::Vec3],
    inv_m: &[f32],
) -> f64 {
    let n = x.len();
    let s: Vec<f64> = inv_m.iter().map(|&w| f64::from(w).sqrt()).collect();
    let (mut axial, mut tension) = (Vec::with_capacity(springs.len()), Vec::new());
    let mut dropped = vec![0.0f64; n];
    for (&[a, b], (&k, &l0)) in springs.iter().zip(k.iter().zip(rest)) {
        if k <= 0.0 {
            continue;
        }
        let (a, b, k) = (a as usize, b as usize, f64::from(k));
        let d = x[b].as_dvec3() - x[a].as_dvec3();
        let l = d.length();
        let (u, t) = if l > 0.0 {
            (d / l, (1.0 - f64::from(l0) / l).max(0.0))
        } else {
            (DVec3::ZERO, 1.0)
        };
        if l > 0.0 {
            let sk = k.sqrt();
            axial.push(Axial {
                a,
                b,
                ga: u * (sk * s[a]),
                gb: u * (sk * s[b]),
            });
        }
        if t > TINY_TENSION {
            tension.push(Tension { a, b, u, kt: k * t });
        } else if t > 0.0 {
            // Rounding-level stretch (rest lengths are f32 distances): bound its share by
            // Gershgorin instead of carrying a block for nearly every spring.
            dropped[a] += 2.0 * k * t;
            dropped[b] += 2.0 * k * t;
        }
    }
    // Weyl: the dropped tension adds at most its largest mass-weighted row sum.
    let dropped_bound = dropped
        .iter()
        .zip(inv_m)
        .map(|(r, &w)| r * f64::from(w))
        .fold(0.0, f64::max);
    if axial.is_empty() && tension.is_empty() {
        return dropped_bound;
    }
    let apply = |q: &[DVec3], out: &mut [DVec3]| {
        out.fill(DVec3::ZERO);
        for sp in &axial {
            let e = sp.gb.dot(q[sp.b]) - sp.ga.dot(q[sp.a]);
            out[sp.a] -= sp.ga * e;
            out[sp.b] += sp.gb * e;
        }
        for sp in &tension {
            let d = q[sp.b] * s[sp.b] - q[sp.a] * s[sp.a];
            let f = (d - sp.u * sp.u.dot(d)) * sp.kt;
            out[sp.a] -= f * s[sp.a];
            out[sp.b] += f * s[sp.b];
        }
    };
    // Deterministic pseudo-random start (splitmix64 of the index), so that no eigenvector is
    // missed by symmetry.
    let mut q: Vec<DVec3> = (0..n as u64)
        .map(|i| DVec3::new(unit(3 * i), unit(3 * i + 1), unit(3 * i + 2)))
        .collect();
    let norm = dot(&q, &q).sqrt();
    q.iter_mut().for_each(|v| *v /= norm);
    let mut q_prev = vec![DVec3::ZERO; n];
    let mut w = vec![DVec3::ZERO; n];
    let (mut alpha, mut beta) = (Vec::with_capacity(STEPS), Vec::with_capacity(STEPS));
    let mut beta_prev = 0.0;
    for _ in 0..STEPS.min(3 * n) {
        apply(&q, &mut w);
        for (wi, pi) in w.iter_mut().zip(&q_prev) {
            *wi -= *pi * beta_prev;
        }
        let a = dot(&w, &q);
        for (wi, qi) in w.iter_mut().zip(&q) {
            *wi -= *qi * a;
        }
        alpha.push(a);
        let b = dot(&w, &w).sqrt();
        // Invariant subspace found (or a NaN, which cannot come from finite inputs): stop.
        if b.is_nan() || b <= 1e-12 * a.abs().max(f64::MIN_POSITIVE) {
            break;
        }
        beta.push(b);
        std::mem::swap(&mut q_prev, &mut q);
        for (qi, wi) in q.iter_mut().zip(&w) {
            *qi = *wi / b;
        }
        beta_prev = b;
    }
    beta.truncate(alpha.len() - 1);
    tridiagonal_max_eigenvalue(&alpha, &beta) + dropped_bound
}

fn dot(a: &[DVec3], b: &[DVec3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x.dot(*y)).sum()
}

/// A number in [-1, 1) from the 64-bit mix of `i` (splitmix64's finaliser).
fn unit(i: u64) -> f64 {
    let mut z = i.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

/// Largest eigenvalue of the symmetric tridiagonal matrix with diagonal `alpha` and
/// off-diagonal `beta` (`beta.len() + 1 == alpha.len()`), by bisection on Sturm counts.
pub(crate) fn tridiagonal_max_eigenvalue(alpha: &[f64], beta: &[f64]) -> f64 {
    let m = alpha.len();
    if m == 0 {
        return 0.0;
    }
    // Gershgorin interval of the tridiagonal matrix.
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for i in 0..m {
        let r = if i > 0 { beta[i - 1].abs() } else { 0.0 }
            + if i < m - 1 { beta[i].abs() } else { 0.0 };
        lo = lo.min(alpha[i] - r);
        hi = hi.max(alpha[i] + r);
    }
    // Number of eigenvalues below `x` (sign changes of the LDLᵀ pivots).
    let below = |x: f64| {
        let mut count = 0;
        let mut d = 1.0;
        for i in 0..m {
            let off = if i > 0 {
                beta[i - 1] * beta[i - 1] / d
            } else {
                0.0
            };
            d = alpha[i] - x - off;
            if d == 0.0 {
                d = -f64::EPSILON * (x.abs() + f64::MIN_POSITIVE);
            }
            if d < 0.0 {
                count += 1;
            }
        }
        count
    };
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if below(mid) == m {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    hi
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tridiagonal_of_the_path_laplacian() {
        // The path graph's Laplacian (1, 2, ..., 2, 1 on the diagonal, -1 off it) has largest
        // eigenvalue 2 + 2 cos(pi / m).
        let m = 12;
        let mut alpha = vec![2.0; m];
        alpha[0] = 1.0;
        alpha[m - 1] = 1.0;
        let beta = vec![-1.0; m - 1];
        let want = 2.0 + 2.0 * (std::f64::consts::PI / m as f64).cos();
        assert!((tridiagonal_max_eigenvalue(&alpha, &beta) - want).abs() < 1e-12);
        assert_eq!(tridiagonal_max_eigenvalue(&[3.5], &[]), 3.5);
    }

    #[test]
    fn chain_of_equal_springs() {
        // A straight chain of m unit masses and springs k, moving along its axis only in the
        // top mode: the axial problem is k times the path Laplacian; transverse modes are
        // zero at rest (no tension), so the largest eigenvalue is k (2 + 2 cos(pi / m)).
        let m = 10;
        let x: Vec<glam::Vec3> = (0..m)
            .map(|i| glam::Vec3::new(0.01 * i as f32, 0.0, 0.0))
            .collect();
        let springs: Vec<[u32; 2]> = (0..m as u32 - 1).map(|i| [i, i + 1]).collect();
        let k = vec![100.0; m - 1];
        let rest = vec![0.01; m - 1];
        let got = largest_eigenvalue(&springs, &k, &rest, &x, &vec![1.0; m]);
        let want = 100.0 * (2.0 + 2.0 * (std::f64::consts::PI / m as f64).cos());
        assert!((got - want).abs() < 1e-6 * want, "{got} vs {want}");
        // Halving every mass doubles it.
        let got2 = largest_eigenvalue(&springs, &k, &rest, &x, &vec![2.0; m]);
        assert!((got2 - 2.0 * want).abs() < 1e-6 * want);
    }
}
