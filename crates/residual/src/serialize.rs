//! Space-filling-curve serialization and grid pooling of a point cloud (no gradients: these
//! are index computations on the current positions).
//!
//! Point Transformer V3 sorts points along Z-order and Hilbert curves (and their transposed
//! variants, x and y swapped) of a voxel grid, attends inside fixed-size patches of that order,
//! and pools by merging the points of coarser grid cells. Ties inside one cell are broken by the
//! exact coordinates, so every order depends on positions only and per-particle outputs are
//! equivariant to the input order (up to float summation order).

use std::collections::BTreeMap;

use candle_core::{Device, Tensor};
use glam::Vec3;

use crate::{ResidualError, Result};

/// Bits per axis of the curve codes (cells beyond 2^16 per axis are clamped).
const BITS: u32 = 16;

/// The four curves PTv3 uses.
pub(crate) const CURVES: usize = 4;

/// Spreads the low 16 bits of `v` to every third bit (bit `k` to bit `3k`).
fn spread3(v: u32) -> u64 {
    let mut x = u64::from(v & 0xFFFF);
    x = (x | (x << 16)) & 0x0000_FF00_00FF;
    x = (x | (x << 8)) & 0x00F0_0F00_F00F;
    x = (x | (x << 4)) & 0x0C30_C30C_30C3;
    x = (x | (x << 2)) & 0x2492_4924_9249;
    x
}

/// Interleaves the low `BITS` bits of `a`, `b`, `c` (a in the most significant slot).
fn interleave(a: u32, b: u32, c: u32) -> u64 {
    (spread3(a) << 2) | (spread3(b) << 1) | spread3(c)
}

/// Hilbert index of a 3-D cell, after John Skilling's "transpose" formulation
/// (AIP Conf. Proc. 707, 2004): undo excess work, Gray-encode, then interleave.
///
/// The undo loop runs from the top bit of `BITS` down. At a level above every coordinate's
/// highest set bit it only exchanges whole coordinates (x0 with x1, then x0 with x2), so those
/// levels are applied as one rotation of the three coordinates and the loop starts at the
/// highest set bit: the same index in a third of the work for the small grids of one object.
fn hilbert(cell: [u32; 3]) -> u64 {
    let mut x = cell.map(|v| v & ((1 << BITS) - 1));
    // Coordinates are below 2^b; levels q = 2^e for e in [max(b, 1), BITS - 1] are the
    // exchanging ones.
    let b = 32 - (x[0] | x[1] | x[2]).leading_zeros();
    for _ in 0..(BITS - b.max(1)) % 3 {
        x = [x[2], x[0], x[1]];
    }
    let top = if b >= 2 { 1u32 << (b - 1) } else { 0 };
    let mut q = top;
    while q > 1 {
        let p = q - 1;
        for i in 0..3 {
            if x[i] & q != 0 {
                x[0] ^= p;
            } else {
                let t = (x[0] ^ x[i]) & p;
                x[0] ^= t;
                x[i] ^= t;
            }
        }
        q >>= 1;
    }
    for i in 1..3 {
        x[i] ^= x[i - 1];
    }
    // After the Gray encoding every coordinate is still below 2^b.
    let mut t = 0;
    q = top;
    while q > 1 {
        if x[2] & q != 0 {
            t ^= q - 1;
        }
        q >>= 1;
    }
    for v in &mut x {
        *v ^= t;
    }
    interleave(x[0], x[1], x[2])
}

fn cells(pos: &[Vec3], grid: f32) -> Vec<[u32; 3]> {
    let min = pos
        .iter()
        .fold(Vec3::splat(f32::INFINITY), |a, p| a.min(*p));
    let max_cell = ((1u32 << BITS) - 1) as f32;
    pos.iter()
        .map(|p| {
            let c = ((*p - min) / grid)
                .floor()
                .clamp(Vec3::ZERO, Vec3::splat(max_cell));
            [c.x as u32, c.y as u32, c.z as u32]
        })
        .collect()
}

/// Curve code of a cell: 0 Z-order, 1 transposed Z-order, 2 Hilbert, 3 transposed Hilbert.
fn curve_code([a, b, c]: [u32; 3], curve: usize) -> u64 {
    match curve {
        0 => interleave(a, b, c),
        1 => interleave(b, a, c),
        2 => hilbert([a, b, c]),
        _ => hilbert([b, a, c]),
    }
}

/// An integer with the order of `f32::total_cmp`.
fn total_key(x: f32) -> i32 {
    let b = x.to_bits() as i32;
    b ^ (((b >> 31) as u32) >> 1) as i32
}

/// Point indices sorted along each of the four curves; ties broken by exact coordinates, then
/// by index. The grid cells and tie keys are computed once for all curves.
pub(crate) fn curve_orders(pos: &[Vec3], grid: f32) -> [Vec<u32>; CURVES] {
    let cells = cells(pos, grid);
    let ties: Vec<[i32; 3]> = pos
        .iter()
        .map(|p| [total_key(p.x), total_key(p.y), total_key(p.z)])
        .collect();
    let mut keys: Vec<(u64, [i32; 3], u32)> = Vec::with_capacity(pos.len());
    std::array::from_fn(|curve| {
        keys.clear();
        keys.extend(
            cells
                .iter()
                .zip(&ties)
                .enumerate()
                .map(|(i, (c, t))| (curve_code(*c, curve), *t, i as u32)),
        );
        keys.sort_unstable();
        keys.iter().map(|k| k.2).collect()
    })
}

/// Point indices sorted along one curve (see [`curve_orders`]).
#[cfg(test)]
pub(crate) fn curve_order(pos: &[Vec3], grid: f32, curve: usize) -> Vec<u32> {
    curve_orders(pos, grid)[curve].clone()
}

/// One serialization of one level, as index tensors.
#[derive(Debug)]
pub(crate) struct Order {
    /// Points in curve order, padded to `patches * patch` by repeating the last one.
    pub gather: Tensor,
    /// Position of each point in the curve order (to scatter patch outputs back).
    pub inverse: Tensor,
    /// Curve predecessor and successor of each point (itself at the ends): the conditional
    /// positional encoding's neighbourhood.
    pub prev: Tensor,
    /// See `prev`.
    pub next: Tensor,
    /// Number of patches and their size.
    pub patches: usize,
    /// Points per patch.
    pub patch: usize,
    /// Additive attention mask `(patches, 1, 1, patch)`: −1e9 on padding keys; `None` without padding.
    pub mask: Option<Tensor>,
}

fn u32_tensor(v: &[u32], dev: &Device) -> Result<Tensor> {
    Ok(Tensor::from_slice(v, v.len(), dev)?)
}

impl Order {
    /// The orders of several clouds (`(curve order, index of the cloud's first point)`), as
    /// one: every cloud is cut into its own balanced patches exactly as it would be alone
    /// (`⌈n / max_patch⌉` patches of `⌈n / patches⌉` points), and every patch is padded to the
    /// largest patch size of the batch with masked copies of its cloud's last point, so no
    /// patch, and no curve neighbourhood, spans two clouds.
    fn new(clouds: &[(&[u32], u32)], max_patch: usize, dev: &Device) -> Result<Self> {
        let split: Vec<(usize, usize)> = clouds
            .iter()
            .map(|(o, _)| {
                let patches = o.len().div_ceil(max_patch.max(1));
                (patches, o.len().div_ceil(patches.max(1)))
            })
            .collect();
        let patch = split.iter().map(|s| s.1).max().unwrap_or(0);
        let patches: usize = split.iter().map(|s| s.0).sum();
        let total: usize = clouds.iter().map(|(o, _)| o.len()).sum();
        let mut gather = Vec::with_capacity(patches * patch);
        let mut mask = Vec::with_capacity(patches * patch);
        let mut inverse = vec![0u32; total];
        let (mut prev, mut next) = (vec![0u32; total], vec![0u32; total]);
        let mut first_patch = 0;
        for (&(order, off), &(np, size)) in clouds.iter().zip(&split) {
            let n = order.len();
            for (k, &i) in order.iter().enumerate() {
                let g = (off + i) as usize;
                inverse[g] = ((first_patch + k / size) * patch + k % size) as u32;
                prev[g] = off + order[k.saturating_sub(1)];
                next[g] = off + order[(k + 1).min(n - 1)];
            }
            for j in 0..np {
                for s in 0..patch {
                    let k = j * size + s;
                    if s < size && k < n {
                        gather.push(off + order[k]);
                        mask.push(0.0f32);
                    } else {
                        gather.push(off + order[n - 1]);
                        mask.push(-1e9);
                    }
                }
            }
            first_patch += np;
        }
        let mask = if mask.iter().any(|m| *m != 0.0) {
            Some(Tensor::from_vec(mask, (patches, 1, 1, patch), dev)?)
        } else {
            None
        };
        Ok(Order {
            gather: u32_tensor(&gather, dev)?,
            inverse: u32_tensor(&inverse, dev)?,
            prev: u32_tensor(&prev, dev)?,
            next: u32_tensor(&next, dev)?,
            patches,
            patch,
            mask,
        })
    }
}

/// The points of one resolution level with their four serializations.
#[derive(Debug)]
pub(crate) struct Level {
    /// Orders, indexed by curve.
    pub orders: Vec<Order>,
    /// Positions (point or cluster means), `(n, 3)`, m.
    pub pos: Tensor,
}

/// Merging of a level's points into the cells of a coarser grid.
#[derive(Debug)]
pub(crate) struct Pooling {
    /// Cluster of each fine point.
    pub cluster: Tensor,
    /// `1 / members` per cluster, `(clusters, 1)`.
    pub inv_count: Tensor,
    /// Number of clusters.
    pub clusters: usize,
}

/// Cell clusters of `pos` on a grid of `grid` m; returns (cluster per point, cluster means,
/// member counts). Clusters are numbered in lexicographic cell order.
pub(crate) fn grid_clusters(pos: &[Vec3], grid: f32) -> (Vec<u32>, Vec<Vec3>, Vec<u32>) {
    let mut ids = BTreeMap::new();
    let keys: Vec<[i64; 3]> = pos
        .iter()
        .map(|p| {
            let c = (*p / grid).floor();
            [c.x as i64, c.y as i64, c.z as i64]
        })
        .collect();
    for k in &keys {
        ids.entry(*k).or_insert(0u32);
    }
    for (i, v) in ids.values_mut().enumerate() {
        *v = i as u32;
    }
    let cluster: Vec<u32> = keys.iter().map(|k| ids[k]).collect();
    let mut sum = vec![Vec3::ZERO; ids.len()];
    let mut count = vec![0u32; ids.len()];
    for (p, c) in pos.iter().zip(&cluster) {
        sum[*c as usize] += *p;
        count[*c as usize] += 1;
    }
    let mean = sum
        .iter()
        .zip(&count)
        .map(|(s, c)| *s / *c as f32)
        .collect();
    (cluster, mean, count)
}

/// The serializations and poolings of one cloud as plain index arrays (no tensors yet): the
/// per-cloud half of a [`Structure`], cheap to build on any thread and to combine with others.
#[derive(Debug, Clone)]
pub(crate) struct Layout {
    /// Per level, finest first: positions (points, then cluster means), m.
    pos: Vec<Vec<Vec3>>,
    /// Per level: the point order along each curve.
    orders: Vec<[Vec<u32>; CURVES]>,
    /// Per pooling (level `k` to `k + 1`): cluster of each point and members per cluster.
    pools: Vec<(Vec<u32>, Vec<u32>)>,
}

impl Layout {
    /// Serializes `pos` (centred, m) on `stages` levels: level 0 on a grid of `grid_m`, level
    /// `k ≥ 1` the cells of `pool_grid_m · 2^(k−1)`.
    pub fn new(pos: &[Vec3], stages: usize, grid_m: f32, pool_grid_m: f32) -> Self {
        let mut out = Layout {
            pos: Vec::with_capacity(stages),
            orders: Vec::with_capacity(stages),
            pools: Vec::with_capacity(stages.saturating_sub(1)),
        };
        let mut current = pos.to_vec();
        for s in 0..stages {
            let grid = if s == 0 {
                grid_m
            } else {
                pool_grid_m * (1 << (s - 1)) as f32
            };
            out.orders.push(curve_orders(&current, grid));
            let next = if s + 1 < stages {
                let (cluster, mean, count) = grid_clusters(&current, pool_grid_m * (1 << s) as f32);
                out.pools.push((cluster, count));
                Some(mean)
            } else {
                None
            };
            out.pos
                .push(std::mem::replace(&mut current, next.unwrap_or_default()));
        }
        out
    }
}

/// All index structures one forward pass needs.
#[derive(Debug)]
pub(crate) struct Structure {
    /// Levels, finest first.
    pub levels: Vec<Level>,
    /// Pooling from level `k` to `k + 1`.
    pub pools: Vec<Pooling>,
}

impl Structure {
    /// Serializes `pos` (centred, m) on `stages` levels.
    pub fn new(
        pos: &[Vec3],
        stages: usize,
        grid_m: f32,
        pool_grid_m: f32,
        patch: usize,
        dev: &Device,
    ) -> Result<Self> {
        Self::batch(&[Layout::new(pos, stages, grid_m, pool_grid_m)], patch, dev)
    }

    /// The structure of several clouds processed as one: their points are concatenated (cloud
    /// `b`'s points follow cloud `b − 1`'s at every level), each keeps its own serializations,
    /// patches (see [`Order`]) and pooling clusters, so no operation of the encoder mixes two
    /// clouds. One cloud gives exactly [`Structure::new`].
    pub fn batch(clouds: &[Layout], patch: usize, dev: &Device) -> Result<Self> {
        let stages = clouds.first().map_or(0, |c| c.pos.len());
        if clouds.iter().any(|c| c.pos.len() != stages) {
            return Err(ResidualError::Input(
                "clouds serialized on different numbers of levels".into(),
            ));
        }
        let mut levels = Vec::with_capacity(stages);
        let mut pools = Vec::with_capacity(stages.saturating_sub(1));
        for s in 0..stages {
            // Index of each cloud's first point at this level.
            let offsets: Vec<u32> = clouds
                .iter()
                .scan(0u32, |acc, c| {
                    let first = *acc;
                    *acc += c.pos[s].len() as u32;
                    Some(first)
                })
                .collect();
            let orders = (0..CURVES)
                .map(|curve| {
                    let parts: Vec<(&[u32], u32)> = clouds
                        .iter()
                        .zip(&offsets)
                        .map(|(c, &off)| (c.orders[s][curve].as_slice(), off))
                        .collect();
                    Order::new(&parts, patch, dev)
                })
                .collect::<Result<Vec<_>>>()?;
            let flat: Vec<f32> = clouds
                .iter()
                .flat_map(|c| c.pos[s].iter().flat_map(|p| p.to_array()))
                .collect();
            let n = flat.len() / 3;
            let pos = Tensor::from_vec(flat, (n, 3), dev)?;
            levels.push(Level { orders, pos });
            if s + 1 < stages {
                let (mut cluster, mut inv) = (Vec::with_capacity(n), Vec::new());
                let mut first = 0u32;
                for c in clouds {
                    let (ids, count) = &c.pools[s];
                    cluster.extend(ids.iter().map(|i| first + i));
                    inv.extend(count.iter().map(|c| 1.0 / *c as f32));
                    first += count.len() as u32;
                }
                let clusters = inv.len();
                pools.push(Pooling {
                    cluster: u32_tensor(&cluster, dev)?,
                    inv_count: Tensor::from_vec(inv, (clusters, 1), dev)?,
                    clusters,
                });
            }
        }
        Ok(Structure { levels, pools })
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    #[test]
    fn hilbert_visits_neighbouring_cells() {
        // Along a Hilbert curve consecutive cells share a face: walk a 8^3 grid.
        let n = 8u32;
        let mut cells = Vec::new();
        for a in 0..n {
            for b in 0..n {
                for c in 0..n {
                    cells.push(([a, b, c], hilbert([a, b, c])));
                }
            }
        }
        cells.sort_by_key(|c| c.1);
        let codes: std::collections::BTreeSet<u64> = cells.iter().map(|c| c.1).collect();
        assert_eq!(codes.len(), cells.len(), "codes are unique");
        for w in cells.windows(2) {
            let d: u32 = (0..3).map(|i| w[0].0[i].abs_diff(w[1].0[i])).sum();
            assert_eq!(d, 1, "{:?} -> {:?}", w[0].0, w[1].0);
        }
    }

    /// Skilling's algorithm over all `BITS` levels, bit by bit: what `hilbert` and `interleave`
    /// must equal.
    fn hilbert_reference(cell: [u32; 3]) -> u64 {
        let mut x = cell;
        let m = 1u32 << (BITS - 1);
        let mut q = m;
        while q > 1 {
            let p = q - 1;
            for i in 0..3 {
                if x[i] & q != 0 {
                    x[0] ^= p;
                } else {
                    let t = (x[0] ^ x[i]) & p;
                    x[0] ^= t;
                    x[i] ^= t;
                }
            }
            q >>= 1;
        }
        for i in 1..3 {
            x[i] ^= x[i - 1];
        }
        let mut t = 0;
        q = m;
        while q > 1 {
            if x[2] & q != 0 {
                t ^= q - 1;
            }
            q >>= 1;
        }
        for v in &mut x {
            *v ^= t;
        }
        interleave_reference(x[0], x[1], x[2])
    }

    fn interleave_reference(a: u32, b: u32, c: u32) -> u64 {
        let mut code = 0u64;
        for bit in (0..BITS).rev() {
            for v in [a, b, c] {
                code = (code << 1) | u64::from((v >> bit) & 1);
            }
        }
        code
    }

    #[test]
    fn fast_codes_equal_the_bit_by_bit_algorithm() {
        let mut cells: Vec<[u32; 3]> = Vec::new();
        for a in 0..24 {
            for b in 0..24 {
                for c in 0..24 {
                    cells.push([a, b, c]);
                }
            }
        }
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        for bits in 1..=16 {
            for _ in 0..300 {
                cells.push(std::array::from_fn(|_| rng.random_range(0..1u32 << bits)));
            }
        }
        cells.push([65535; 3]);
        cells.push([0, 0, 65535]);
        for c in cells {
            assert_eq!(hilbert(c), hilbert_reference(c), "{c:?}");
            assert_eq!(
                interleave(c[0], c[1], c[2]),
                interleave_reference(c[0], c[1], c[2])
            );
        }
    }

    #[test]
    fn z_order_of_a_2x2x2_block() {
        let pos: Vec<Vec3> = (0..8)
            .map(|i| Vec3::new((i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32))
            .collect();
        // x is the most significant slot: x varies slowest.
        let order = curve_order(&pos, 1.0, 0);
        assert_eq!(order, vec![0, 4, 2, 6, 1, 5, 3, 7]);
        let trans = curve_order(&pos, 1.0, 1);
        assert_eq!(trans, vec![0, 4, 1, 5, 2, 6, 3, 7]);
    }

    #[test]
    fn grid_clusters_merge_cells() {
        let pos = [
            Vec3::new(0.01, 0.0, 0.0),
            Vec3::new(0.03, 0.0, 0.0),
            Vec3::new(0.11, 0.0, 0.0),
        ];
        let (cluster, mean, count) = grid_clusters(&pos, 0.1);
        assert_eq!(cluster, vec![0, 0, 1]);
        assert_eq!(count, vec![2, 1]);
        assert!((mean[0].x - 0.02).abs() < 1e-6);
    }
}
