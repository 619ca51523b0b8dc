//! Two-sided Chamfer distance to a fixed target by brute force, for the small clouds MPPI
//! scores thousands of times per replanning step.
//!
//! `metrics::PointIndex` answers nearest-neighbour queries with k-d trees in f64, and a Chamfer
//! distance to a new cloud builds a tree of that cloud first. For a 150-point rope that cost
//! about 30 µs per predicted state, 6 % of a PGRD replanning step at the rerouting settings
//! (1350 states). Here one pass over all (point, target point) pairs finds both directions'
//! nearest squared distances at once, eight pairs per vector instruction (runtime dispatch by
//! `pulp`): a few µs per state. Distances are computed in f32 and summed in f64; they agree
//! with the k-d trees to float rounding (the same nearest neighbours up to ties).

use glam::Vec3;
use pulp::Simd;

/// Largest number of (point, target point) pairs evaluated by brute force; above it the k-d
/// trees are cheaper (their cost grows as `n log n`, brute force as `n · m`).
pub(crate) const MAX_PAIRS: usize = 512 * 512;

/// The target's coordinates, one array per axis, padded with far-away points to a multiple of
/// [`PAD`] so that every vector width divides it.
#[derive(Clone, Debug)]
pub(crate) struct Target {
    axes: [Vec<f32>; 3],
    len: usize,
}

/// Padding multiple of the target arrays (the widest vector pulp uses: 16 lanes).
const PAD: usize = 16;

/// Coordinate of padding points: their squared distances (≈ 1e36) stay finite in f32 and are
/// never the nearest.
const FAR: f32 = 1e18;

impl Target {
    pub(crate) fn new(points: &[Vec3]) -> Self {
        let n = points.len().div_ceil(PAD) * PAD;
        let axis = |k: usize| {
            let mut v: Vec<f32> = points.iter().map(|p| p[k]).collect();
            v.resize(n, FAR);
            v
        };
        Target {
            axes: [axis(0), axis(1), axis(2)],
            len: points.len(),
        }
    }

    /// Number of target points.
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Mean distance from each point of `x` to its nearest target point plus mean distance
    /// from each target point to its nearest point of `x`, m. `x` and the target must be
    /// non-empty and finite (the caller checks).
    pub(crate) fn two_sided_sum(&self, x: &[Vec3]) -> f64 {
        pulp::Arch::new().dispatch(Pass { target: self, x })
    }
}

struct Pass<'a> {
    target: &'a Target,
    x: &'a [Vec3],
}

impl pulp::WithSimd for Pass<'_> {
    type Output = f64;

    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) -> f64 {
        let [tx, ty, tz] = &self.target.axes;
        let (tx, ty, tz) = (
            S::as_simd_f32s(tx).0,
            S::as_simd_f32s(ty).0,
            S::as_simd_f32s(tz).0,
        );
        let inf = simd.splat_f32s(f32::INFINITY);
        // Nearest squared distance of every target point to `x`, updated point by point.
        let mut col = vec![inf; tx.len()];
        let mut rows = 0f64;
        for p in self.x {
            let (px, py, pz) = (
                simd.splat_f32s(p.x),
                simd.splat_f32s(p.y),
                simd.splat_f32s(p.z),
            );
            let mut best = inf;
            for (((cx, cy), cz), c) in tx.iter().zip(ty).zip(tz).zip(&mut col) {
                let dx = simd.sub_f32s(*cx, px);
                let dy = simd.sub_f32s(*cy, py);
                let dz = simd.sub_f32s(*cz, pz);
                let d = simd.mul_f32s(dx, dx);
                let d = simd.mul_add_e_f32s(dy, dy, d);
                let d = simd.mul_add_e_f32s(dz, dz, d);
                best = simd.min_f32s(best, d);
                *c = simd.min_f32s(*c, d);
            }
            rows += f64::from(simd.reduce_min_f32s(best)).sqrt();
        }
        let mut cols = 0f64;
        let mut buf = vec![0f32; col.len() * S::F32_LANES];
        S::as_mut_simd_f32s(&mut buf).0.copy_from_slice(&col);
        for d in &buf[..self.target.len] {
            cols += f64::from(*d).sqrt();
        }
        rows / self.x.len() as f64 + cols / self.target.len as f64
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    #[test]
    fn brute_force_matches_the_kd_trees() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let mut cloud = |n: usize, spread: f32| -> Vec<Vec3> {
            (0..n)
                .map(|_| {
                    Vec3::new(
                        rng.random_range(-spread..spread),
                        rng.random_range(-spread..spread),
                        rng.random_range(0.0..spread),
                    )
                })
                .collect()
        };
        // Sizes around and off the vector widths, clouds of different extent.
        for (n, m) in [(1, 1), (7, 150), (150, 150), (33, 17), (250, 96)] {
            let target = cloud(m, 0.5);
            let x = cloud(n, 0.3);
            let to = |v: &[Vec3]| v.iter().map(|p| p.to_array()).collect::<Vec<_>>();
            let want = metrics::chamfer(&to(&x), &to(&target))
                .unwrap()
                .two_sided_sum();
            let got = Target::new(&target).two_sided_sum(&x);
            assert!(
                (got - want).abs() <= 1e-6 * want.max(1e-3),
                "{n} vs {m}: {got} vs {want}"
            );
        }
    }
}
