//! Splitting one rollout over several cores ([`crate::SimConfig::partitions`]).
//!
//! The particles are cut into `P` slabs along the rest shape's longest principal axis. Springs
//! with both ends in one slab are that slab's; the few that join two slabs are "cross" springs.
//! The backbone's spring order becomes `[slab 0 | slab 1 | … | cross]`, each group in the usual
//! colour order. Per substep the slabs' springs run in parallel on private copies of their
//! particles, the cross springs run after them on the shared arrays. Slabs never share a
//! particle, so the result is the same whichever thread runs which slab, and whatever the
//! number of threads; it differs from `partitions = 1` only by the order in which each
//! particle's spring forces and dashpot impulses are summed.

use glam::{Vec3, Vec3A};

use crate::Topology;
use crate::kernels::DampSpring;

/// The slabs of a partitioned backbone.
#[derive(Debug, Clone)]
pub(crate) struct Partition {
    /// Global particle ids of each slab, ascending.
    pub members: Vec<Vec<u32>>,
    /// Each slab's springs as a range of the backbone's spring order.
    pub ranges: Vec<std::ops::Range<usize>>,
    /// Endpoints of the slab springs (`springs[..cross_start]`) in their slab's local indices.
    pub local_springs: Vec<[u32; 2]>,
    /// First cross spring; cross springs run to the end of the spring order.
    pub cross_start: usize,
}

/// One slab's private working copy for a substep.
#[derive(Debug, Clone, Default)]
pub(crate) struct SlabBuffers {
    pub x: Vec<Vec3A>,
    pub v: Vec<Vec3A>,
    pub f: Vec<Vec3A>,
    pub dir: Vec<Vec3A>,
    pub damp: Vec<DampSpring>,
}

impl Partition {
    /// Fresh buffers for every slab (particle arrays padded to a power of two, as the kernels
    /// require).
    pub fn buffers(&self, damping: bool) -> Vec<SlabBuffers> {
        self.members
            .iter()
            .zip(&self.ranges)
            .map(|(m, r)| {
                let padded = m.len().next_power_of_two();
                SlabBuffers {
                    x: vec![Vec3A::ZERO; padded],
                    v: vec![Vec3A::ZERO; padded],
                    f: vec![Vec3A::ZERO; padded],
                    dir: vec![Vec3A::ZERO; r.len()],
                    damp: vec![DampSpring::default(); if damping { r.len() } else { 0 }],
                }
            })
            .collect()
    }
}

/// Order `topo`'s springs for `parts` slabs of the particles at `rest` (see the module docs);
/// `color_order` orders one group. Returns the springs, their rest lengths and the partition.
pub(crate) fn order(
    topo: Topology,
    rest: &[Vec3],
    parts: usize,
    color_order: impl Fn(Topology, usize) -> (Vec<[u32; 2]>, Vec<f32>),
) -> (Vec<[u32; 2]>, Vec<f32>, Partition) {
    let n = rest.len();
    let slab = slabs(rest, parts);
    let mut members = vec![Vec::new(); parts];
    let mut local = vec![0u32; n];
    for (i, &s) in slab.iter().enumerate() {
        local[i] = members[s].len() as u32;
        members[s].push(i as u32);
    }
    let mut groups = vec![
        Topology {
            springs: Vec::new(),
            rest_lengths: Vec::new()
        };
        parts + 1
    ];
    for (&[a, b], &l) in topo.springs.iter().zip(&topo.rest_lengths) {
        let (sa, sb) = (slab[a as usize], slab[b as usize]);
        let g = if sa == sb { sa } else { parts };
        groups[g].springs.push([a, b]);
        groups[g].rest_lengths.push(l);
    }
    let (mut springs, mut lengths) = (Vec::new(), Vec::new());
    let mut ranges = Vec::with_capacity(parts);
    let mut local_springs = Vec::new();
    for (g, group) in groups.into_iter().enumerate() {
        let (s, l) = color_order(group, n);
        if g < parts {
            ranges.push(springs.len()..springs.len() + s.len());
            local_springs.extend(
                s.iter()
                    .map(|&[a, b]| [local[a as usize], local[b as usize]]),
            );
        }
        springs.extend(s);
        lengths.extend(l);
    }
    let cross_start = local_springs.len();
    let partition = Partition {
        members,
        ranges,
        local_springs,
        cross_start,
    };
    (springs, lengths, partition)
}

/// Slab of each particle: rank along the principal axis (ties by index), cut into `parts`
/// equal counts.
fn slabs(rest: &[Vec3], parts: usize) -> Vec<usize> {
    let n = rest.len();
    let axis = principal_axis(rest);
    let mut idx: Vec<usize> = (0..n).collect();
    let key = |i: usize| f64::from(rest[i].dot(axis));
    idx.sort_by(|&a, &b| key(a).total_cmp(&key(b)).then(a.cmp(&b)));
    let mut slab = vec![0; n];
    for (rank, &i) in idx.iter().enumerate() {
        slab[i] = rank * parts / n.max(1);
    }
    slab
}

/// Unit direction of largest spread of the points (power iteration on the covariance; x when
/// the points do not spread).
fn principal_axis(p: &[Vec3]) -> Vec3 {
    let n = p.len().max(1) as f64;
    let mean = p.iter().fold(glam::DVec3::ZERO, |s, q| s + q.as_dvec3()) / n;
    let mut c = glam::DMat3::ZERO;
    for q in p {
        let d = q.as_dvec3() - mean;
        c += glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    // Start between the axes so that no principal direction is orthogonal to the start.
    let mut v = glam::DVec3::new(0.8, 0.5, 0.3).normalize();
    for _ in 0..100 {
        let w = c * v;
        let len = w.length();
        if len.is_nan() || len <= 0.0 {
            return Vec3::X;
        }
        v = w / len;
    }
    v.as_vec3()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rope_is_cut_across_its_length() {
        let x: Vec<Vec3> = (0..100)
            .map(|i| Vec3::new(0.01 * (i % 10) as f32, 0.3 - 0.01 * i as f32, 0.0))
            .collect();
        let s = slabs(&x, 2);
        assert_eq!(s.iter().filter(|&&p| p == 0).count(), 50);
        // The cut runs across y (the long axis): every particle of slab 0 is on one side.
        let y0: Vec<f32> = (0..100).filter(|&i| s[i] == 0).map(|i| x[i].y).collect();
        let y1: Vec<f32> = (0..100).filter(|&i| s[i] == 1).map(|i| x[i].y).collect();
        let (max0, min0) = (
            y0.iter().cloned().fold(f32::MIN, f32::max),
            y0.iter().cloned().fold(f32::MAX, f32::min),
        );
        let (max1, min1) = (
            y1.iter().cloned().fold(f32::MIN, f32::max),
            y1.iter().cloned().fold(f32::MAX, f32::min),
        );
        assert!(max0 < min1 || max1 < min0);
    }
}
