//! Interior ("fill") particles for volumetric objects.

use glam::Vec3;
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;

use crate::SimError;

/// Largest voxel grid [`fill_interior`] will scan.
const MAX_CELLS: u64 = 20_000_000;

/// Fill the inside of a closed-ish surface point cloud with particles on a cubic grid of
/// `spacing_m` (m). Deterministic; output in grid order (z, then y, then x).
///
/// Method (docs/physics.md): voxels of edge `v = max(spacing_m, 1.5 × median nearest-neighbour
/// distance of the surface)` that hold a surface point form a wall; a flood fill through the
/// other voxels (6-connected) from outside the bounding box marks the exterior; grid centres in
/// voxels that are neither wall nor exterior are inside. Centres closer than `spacing_m / 4` to
/// a surface point are dropped so fill particles do not sit on top of surface particles.
///
/// Limits: a gap in the surface wider than about one voxel lets the flood in, and the region
/// behind it stays empty (open surfaces are never filled); parts thinner than about two voxels
/// get no interior particles; the layer of wall voxels (up to ~v deep) stays empty.
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

    // Output grid.
    let dims: [usize; 3] =
        std::array::from_fn(|a| (((hi[a] - lo[a]) / spacing_m).ceil() as usize).max(1));
    check_cells(dims)?;
    // Voxel grid of the flood fill, with at least one empty voxel of padding on every side so
    // that the exterior is connected around the object.
    let v = spacing_m.max(1.5 * median_nn_distance(surface_points, &tree));
    let origin = lo - Vec3::splat(v);
    let vd: [usize; 3] = std::array::from_fn(|a| ((hi[a] - lo[a]) / v).ceil() as usize + 3);
    check_cells(vd)?;
    let voxel = |p: Vec3| -> [usize; 3] {
        std::array::from_fn(|a| (((p[a] - origin[a]) / v).floor().max(0.0) as usize).min(vd[a] - 1))
    };
    let idx = |c: [usize; 3]| (c[2] * vd[1] + c[1]) * vd[0] + c[0];
    const WALL: u8 = 1;
    const OUTSIDE: u8 = 2;
    let mut state = vec![0u8; vd[0] * vd[1] * vd[2]];
    for &p in surface_points {
        state[idx(voxel(p))] = WALL;
    }
    // Flood the exterior from every non-wall voxel of the boundary layer.
    let mut stack: Vec<[usize; 3]> = Vec::new();
    for k in 0..vd[2] {
        for j in 0..vd[1] {
            for i in 0..vd[0] {
                let border = i == 0
                    || j == 0
                    || k == 0
                    || i == vd[0] - 1
                    || j == vd[1] - 1
                    || k == vd[2] - 1;
                if border && state[idx([i, j, k])] == 0 {
                    state[idx([i, j, k])] = OUTSIDE;
                    stack.push([i, j, k]);
                }
            }
        }
    }
    while let Some(c) = stack.pop() {
        for a in 0..3 {
            for n in [c[a].checked_sub(1), Some(c[a] + 1).filter(|&u| u < vd[a])]
                .into_iter()
                .flatten()
            {
                let mut m = c;
                m[a] = n;
                let s = &mut state[idx(m)];
                if *s == 0 {
                    *s = OUTSIDE;
                    stack.push(m);
                }
            }
        }
    }
    let min_d2 = 0.0625 * spacing_m * spacing_m;
    let mut out = Vec::new();
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let q = lo + spacing_m * (Vec3::new(i as f32, j as f32, k as f32) + 0.5);
                if state[idx(voxel(q))] == 0
                    && tree.nearest_one::<SquaredEuclidean>(&q.to_array()).distance >= min_d2
                {
                    out.push(q);
                }
            }
        }
    }
    Ok(out)
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
