//! Small dense linear algebra: row-major square matrices and a cyclic Jacobi eigen-solver.
//!
//! CMA-ES here runs in at most a few dozen dimensions, where the Jacobi method is simple, exact to
//! machine precision (it also resolves small eigenvalues of ill-conditioned matrices to high
//! relative accuracy) and fully deterministic.

/// Upper limit on Jacobi sweeps; convergence is quadratic, so well-conditioned inputs need < 10.
const MAX_SWEEPS: usize = 60;

/// Eigen-decomposition of the symmetric `n`×`n` row-major matrix `a`.
///
/// Returns `(values, vectors)` where column `k` of the row-major `vectors` (entries
/// `vectors[i * n + k]`) is the unit eigenvector for `values[k]`. Only the upper triangle of `a`
/// is read: the caller keeps the matrix symmetric, and reading one triangle makes tiny
/// asymmetries from rounding irrelevant.
pub(crate) fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    debug_assert_eq!(a.len(), n * n);
    let mut m = vec![0.0; n * n];
    for i in 0..n {
        for j in i..n {
            m[i * n + j] = a[i * n + j];
            m[j * n + i] = a[i * n + j];
        }
    }
    let mut v = identity(n);
    for _ in 0..MAX_SWEEPS {
        let mut rotated = false;
        for p in 0..n {
            for q in (p + 1)..n {
                let apq = m[p * n + q];
                let app = m[p * n + p];
                let aqq = m[q * n + q];
                // Element-wise threshold (rather than a norm-wise one) keeps the small
                // eigenvalues of an ill-conditioned covariance accurate relative to themselves.
                if apq == 0.0 || apq.abs() <= f64::EPSILON * (app.abs() * aqq.abs()).sqrt() {
                    continue;
                }
                rotated = true;
                rotate(&mut m, &mut v, n, p, q);
            }
        }
        if !rotated {
            break;
        }
    }
    let values = (0..n).map(|i| m[i * n + i]).collect();
    (values, v)
}

/// One Jacobi rotation that zeroes `m[p][q]`, accumulated into the eigenvector matrix `v`.
fn rotate(m: &mut [f64], v: &mut [f64], n: usize, p: usize, q: usize) {
    let apq = m[p * n + q];
    let theta = (m[q * n + q] - m[p * n + p]) / (2.0 * apq);
    // tan of the rotation angle, choosing the smaller root for stability; for huge theta the
    // square would overflow, and t ~ 1 / (2 theta) there.
    let t = if theta.abs() > 1e150 {
        0.5 / theta
    } else {
        theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
    };
    let c = 1.0 / (t * t + 1.0).sqrt();
    let s = t * c;
    m[p * n + p] -= t * apq;
    m[q * n + q] += t * apq;
    m[p * n + q] = 0.0;
    m[q * n + p] = 0.0;
    for r in 0..n {
        if r != p && r != q {
            let arp = m[r * n + p];
            let arq = m[r * n + q];
            let new_rp = c * arp - s * arq;
            let new_rq = s * arp + c * arq;
            m[r * n + p] = new_rp;
            m[p * n + r] = new_rp;
            m[r * n + q] = new_rq;
            m[q * n + r] = new_rq;
        }
    }
    for r in 0..n {
        let vrp = v[r * n + p];
        let vrq = v[r * n + q];
        v[r * n + p] = c * vrp - s * vrq;
        v[r * n + q] = s * vrp + c * vrq;
    }
}

/// The `n`×`n` identity, row-major.
pub(crate) fn identity(n: usize) -> Vec<f64> {
    let mut m = vec![0.0; n * n];
    for i in 0..n {
        m[i * n + i] = 1.0;
    }
    m
}

/// `out = M x` for a row-major `n`×`n` matrix.
pub(crate) fn mat_vec(m: &[f64], x: &[f64]) -> Vec<f64> {
    let n = x.len();
    (0..n)
        .map(|i| (0..n).map(|j| m[i * n + j] * x[j]).sum())
        .collect()
}

/// `out = Mᵀ x` for a row-major `n`×`n` matrix.
pub(crate) fn mat_t_vec(m: &[f64], x: &[f64]) -> Vec<f64> {
    let n = x.len();
    (0..n)
        .map(|j| (0..n).map(|i| m[i * n + j] * x[i]).sum())
        .collect()
}

/// Euclidean norm.
pub(crate) fn norm(x: &[f64]) -> f64 {
    x.iter().map(|v| v * v).sum::<f64>().sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn reconstruct(values: &[f64], vectors: &[f64], n: usize) -> Vec<f64> {
        let mut out = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                out[i * n + j] = (0..n)
                    .map(|k| vectors[i * n + k] * values[k] * vectors[j * n + k])
                    .sum();
            }
        }
        out
    }

    #[test]
    fn tridiagonal_toeplitz_matches_closed_form() {
        // tridiag(-1, 2, -1) has eigenvalues 2 - 2 cos(k pi / (n + 1)), k = 1..n.
        let n = 12;
        let mut a = vec![0.0; n * n];
        for i in 0..n {
            a[i * n + i] = 2.0;
            if i + 1 < n {
                a[i * n + i + 1] = -1.0;
                a[(i + 1) * n + i] = -1.0;
            }
        }
        let (mut values, _) = symmetric_eigen(&a, n);
        values.sort_by(f64::total_cmp);
        for (k, v) in values.iter().enumerate() {
            let expected =
                2.0 - 2.0 * (((k + 1) as f64) * std::f64::consts::PI / (n as f64 + 1.0)).cos();
            assert!((v - expected).abs() < 1e-13, "k={k}: {v} vs {expected}");
        }
    }

    #[test]
    fn random_symmetric_matrices_reconstruct_and_are_orthonormal() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        for n in [1, 2, 3, 7, 20] {
            let mut a = vec![0.0; n * n];
            for i in 0..n {
                for j in i..n {
                    let x: f64 = rng.random_range(-1.0..1.0);
                    a[i * n + j] = x;
                    a[j * n + i] = x;
                }
            }
            let (values, vectors) = symmetric_eigen(&a, n);
            let back = reconstruct(&values, &vectors, n);
            for (x, y) in a.iter().zip(&back) {
                assert!((x - y).abs() < 1e-12, "n={n}: {x} vs {y}");
            }
            for p in 0..n {
                for q in 0..n {
                    let dot: f64 = (0..n)
                        .map(|i| vectors[i * n + p] * vectors[i * n + q])
                        .sum();
                    let expected = if p == q { 1.0 } else { 0.0 };
                    assert!((dot - expected).abs() < 1e-12);
                }
            }
        }
    }

    #[test]
    fn ill_conditioned_small_eigenvalues_keep_relative_accuracy() {
        // Q diag(1, 1e-6, 1e-12) Qᵀ with a fixed rotation Q: the smallest eigenvalue must come
        // back to many significant digits, which a norm-wise stopping rule would not give.
        let n = 3;
        let (c, s) = (0.6_f64, 0.8_f64);
        let q = [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0];
        let q2 = [1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c];
        let mut rot = vec![0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                rot[i * 3 + j] = (0..3).map(|k| q[i * 3 + k] * q2[k * 3 + j]).sum();
            }
        }
        let d = [1.0, 1e-6, 1e-12];
        let a = reconstruct(&d, &rot, n);
        let (mut values, _) = symmetric_eigen(&a, n);
        values.sort_by(f64::total_cmp);
        assert!((values[0] / 1e-12 - 1.0).abs() < 1e-3, "{values:?}");
        assert!((values[1] / 1e-6 - 1.0).abs() < 1e-8, "{values:?}");
        assert!((values[2] - 1.0).abs() < 1e-12, "{values:?}");
    }
}
