//! Interior ("fill") particles for volumetric objects.

use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;

use rayon::prelude::*;

use crate::SimError;

/// Most grid points [`fill_interior`] will test (each costs up to 26 ray marches).
const MAX_CELLS: u64 = 1_000_000;

/// Fill the inside of a closed-ish surface point cloud with particles on a cubic grid of
/// `spacing_m` (m). Deterministic; output in grid order (z, then y, then x).
///
/// Method (docs/physics.md): a grid point is inside when every one of 26 rays from it (the
/// directions to the neighbours of a cube) is blocked by the surface. A ray is blocked when a
/// surface point lies within `min(r, t)` of the ray at some distance `t` along it, with
/// `r = 2 × median nearest-neighbour distance of the surface`: a tube that closes the gaps of a
/// sparsely sampled surface, narrowed to a 45° cone near the origin so that a point just outside
/// the surface is not blocked by the surface points beside it. Inside points closer than
/// `spacing_m / 2` to a surface point are dropped so fill particles do not sit on top of
/// surface particles.
///
/// Limits: an opening wider than about `2r` lets rays out, so an open surface (a tube without
/// caps) stays empty except for a skin up to `r` thick along its wall, where the rays running
/// beside the wall count as blocked; an outside pocket enclosed in every direction is filled. Work is
/// O(grid points × 26 × ray length / r) nearest-neighbour queries, run on the rayon pool.
///
/// ```
/// use glam::Vec3;
/// // A 0.1 m cube shell sampled every 5 mm.
/// let mut shell = Vec::new();
/// for i in 0..=20 { for j in 0..=20 { for k in 0..=20 {
///     if [i, j, k].iter().any(|&c| c == 0 || c == 20) {
///         shell.push(Vec3::new(i as f32, j as f32, k as f32) * 0.005);
///     }
/// }}}
/// let inside = springs::fill_interior(&shell, 0.02)?;
/// assert!(inside.len() >= 27 && inside.len() <= 125);
/// assert!(inside.iter().all(|p| p.min_element() > 0.0 && p.max_element() < 0.1));
/// # Ok::<(), springs::SimError>(())
/// ```
pub fn fill_interior(surface_points: &[Vec3], spacing_m: f32) -> Result<Vec<Vec3>, SimError> {
    if !(spacing_m.is_finite() && spacing_m > 0.0) {
        return Err(SimError::InvalidParameter {
            name: "spacing_m",
            value: f64::from(spacing_m),
            reason: "must be finite and > 0",
        });
    }
    if let Some(index) = surface_points.iter().position(|p| !p.is_finite()) {
        return Err(SimError::NonFinite {
            what: "surface_points",
            index,
        });
    }
    if surface_points.len() < 4 {
        return Ok(Vec::new());
    }
    let pts: Vec<[f32; 3]> = surface_points.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(&pts);
    let lo = surface_points
        .iter()
        .copied()
        .fold(Vec3::INFINITY, Vec3::min);
    let hi = surface_points
        .iter()
        .copied()
        .fold(Vec3::NEG_INFINITY, Vec3::max);
    let dims: [usize; 3] =
        std::array::from_fn(|a| (((hi[a] - lo[a]) / spacing_m).ceil() as usize).max(1));
    check_cells(dims)?;
    let r = 2.0 * median_nn_distance(surface_points, &tree);
    if r <= 0.0 {
        return Ok(Vec::new());
    }
    let rays = Rays {
        tree: &tree,
        lo: lo - Vec3::splat(r),
        hi: hi + Vec3::splat(r),
        r,
        step: 0.5 * r,
    };
    let min_d2 = 0.25 * spacing_m * spacing_m;
    let grid: Vec<Vec3> = (0..dims[2])
        .flat_map(|k| (0..dims[1]).flat_map(move |j| (0..dims[0]).map(move |i| [i, j, k])))
        .map(|[i, j, k]| lo + spacing_m * (Vec3::new(i as f32, j as f32, k as f32) + 0.5))
        .collect();
    // Each point's test is independent and `collect` keeps grid order, so the output does not
    // depend on the thread count.
    Ok(grid
        .into_par_iter()
        .filter(|q| {
            tree.nearest_one::<SquaredEuclidean>(&q.to_array()).distance >= min_d2
                && directions().all(|d| rays.blocked(*q, d))
        })
        .collect())
}

/// The 26 unit directions from a cube's centre to its faces, edges and corners.
fn directions() -> impl Iterator<Item = Vec3> {
    (-1i8..=1)
        .flat_map(|i| (-1i8..=1).flat_map(move |j| (-1i8..=1).map(move |k| [i, j, k])))
        .filter(|c| *c != [0, 0, 0])
        .map(|[i, j, k]| Vec3::new(f32::from(i), f32::from(j), f32::from(k)).normalize())
}

/// Ray marching against the surface points.
struct Rays<'a> {
    tree: &'a ImmutableKdTree<f32, u32, 3, 32>,
    /// Box the rays march in (the surface's bounds padded by `r`), m.
    lo: Vec3,
    hi: Vec3,
    /// Tube radius, m.
    r: f32,
    /// March step, m (half the tube radius, so no surface point within 0.97 r of the line is
    /// stepped over).
    step: f32,
}

impl Rays<'_> {
    /// Whether the ray from `origin` along the unit vector `dir` meets the surface before it
    /// leaves the box.
    fn blocked(&self, origin: Vec3, dir: Vec3) -> bool {
        let mut t = self.step;
        loop {
            let c = origin + t * dir;
            if c.cmplt(self.lo).any() || c.cmpgt(self.hi).any() {
                return false;
            }
            let radius = self.r.min(t);
            let d2 = self
                .tree
                .nearest_one::<SquaredEuclidean>(&c.to_array())
                .distance;
            if d2 <= radius * radius {
                return true;
            }
            t += self.step;
        }
    }
}

fn check_cells(dims: [usize; 3]) -> Result<(), SimError> {
    let cells = dims.iter().map(|&d| d as u64).product::<u64>();
    if cells > MAX_CELLS {
        return Err(SimError::TooLarge {
            what: "fill grid cells",
            value: cells,
            limit: MAX_CELLS,
        });
    }
    Ok(())
}

/// Median distance from each surface point to its nearest distinct neighbour, m.
fn median_nn_distance(points: &[Vec3], tree: &ImmutableKdTree<f32, u32, 3, 32>) -> f32 {
    let k = std::num::NonZero::new(8).expect("8 is non-zero");
    let mut d: Vec<f32> = points
        .iter()
        .filter_map(|p| {
            tree.nearest_n::<SquaredEuclidean>(&p.to_array(), k)
                .into_iter()
                .map(|nb| nb.distance)
                .filter(|&d2| d2 > 0.0)
                .reduce(f32::min)
        })
        .map(f32::sqrt)
        .collect();
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    *d.select_nth_unstable_by(mid, f32::total_cmp).1
}
