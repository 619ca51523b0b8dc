//! Spring topology built once from the first frame.

use glam::{Vec3, Vec3A};
use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;

use crate::SimError;

/// Largest number of neighbour candidates the builder will hold at once (memory guard).
const MAX_CANDIDATES: u64 = 100_000_000;

/// The springs of an object: particle pairs and their rest lengths (m).
///
/// Orientation matters only for bookkeeping: spring `s` joins `springs[s][0]` and `springs[s][1]`,
/// and its force is computed from `x[springs[s][1]] - x[springs[s][0]]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Topology {
    /// Particle index pairs `[a, b]` with `a < b`.
    pub springs: Vec<[u32; 2]>,
    /// Rest length of each spring (the initial distance), m.
    pub rest_lengths: Vec<f32>,
}

/// Distance between two particles exactly as the force kernel computes it, so that a structure
/// built from `positions` is at rest with exactly zero spring force.
pub(crate) fn kernel_distance(a: Vec3, b: Vec3) -> f32 {
    (Vec3A::from(b) - Vec3A::from(a)).length()
}

fn dist2(a: Vec3, b: Vec3) -> f32 {
    (Vec3A::from(b) - Vec3A::from(a)).length_squared()
}

/// Which pairs of particles may be joined by a spring (beyond being within the threshold at
/// the start frame): e.g. material neighbours only, not parts of an object that merely touch
/// there (`scene`'s material springs). Must be symmetric in `a` and `b`.
pub trait PairFilter: std::fmt::Debug + Send + Sync {
    /// Whether particles `a` and `b` may be joined, under the spring radius `threshold` (m).
    fn keep(&self, a: usize, b: usize, threshold: f32) -> bool;
}

/// Particles that join the object by their own rule instead of the object's threshold and
/// spring count: PhysTwin's controller points, each joined to up to `max_springs` of the
/// nearest other particles within `radius_m` (its `controller_radius` and
/// `controller_max_neighbours`, 0.04 m and 50 by default there).
///
/// Anchors get no springs among themselves and take no part in the object's own springs, and
/// their springs do not count against an object particle's `max_springs`.
#[derive(Debug, Clone, PartialEq)]
pub struct AnchorSprings {
    /// The anchor particles, each named once.
    pub particles: std::sync::Arc<[u32]>,
    /// How far an anchor reaches, m.
    pub radius_m: f32,
    /// Most springs one anchor gets.
    pub max_springs: u32,
}

impl Topology {
    /// Build springs the reference way (docs/physics.md):
    /// 1. for every particle, its up to `max_springs + 3` nearest other particles with
    ///    `distance² <= threshold²` (k-d tree query; ties in distance broken by the lower index);
    /// 2. all candidate pairs, deduplicated, sorted by (distance, lower index, higher index);
    /// 3. accepted greedily while both ends have fewer than `max_springs` springs.
    ///
    /// Rest length = initial distance. The springs come out in acceptance order.
    ///
    /// ```
    /// use glam::Vec3;
    /// let pts: Vec<Vec3> = (0..5).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0)).collect();
    /// let topo = springs::Topology::build(&pts, 0.015, 8)?;
    /// assert_eq!(topo.springs, vec![[0, 1], [1, 2], [2, 3], [3, 4]]);
    /// # Ok::<(), springs::SimError>(())
    /// ```
    pub fn build(positions: &[Vec3], threshold: f32, max_springs: u32) -> Result<Self, SimError> {
        Self::build_with(positions, threshold, max_springs, None)
    }

    /// [`Topology::build`] with the pairs `filter` rejects left out before step 1, so that they
    /// neither become springs nor take a particle's place among its nearest candidates.
    ///
    /// ```
    /// use glam::Vec3;
    /// #[derive(Debug)]
    /// struct NotAcrossTwo;
    /// impl springs::PairFilter for NotAcrossTwo {
    ///     fn keep(&self, a: usize, b: usize, _threshold: f32) -> bool {
    ///         (a < 2) == (b < 2)
    ///     }
    /// }
    /// let pts: Vec<Vec3> = (0..4).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0)).collect();
    /// let topo = springs::Topology::build_with(&pts, 0.015, 8, Some(&NotAcrossTwo))?;
    /// assert_eq!(topo.springs, vec![[0, 1], [2, 3]]);
    /// # Ok::<(), springs::SimError>(())
    /// ```
    pub fn build_with(
        positions: &[Vec3],
        threshold: f32,
        max_springs: u32,
        filter: Option<&dyn PairFilter>,
    ) -> Result<Self, SimError> {
        Self::build_anchored(positions, threshold, max_springs, filter, None)
    }

    /// [`Topology::build_with`] over the particles that are not `anchors`, then each anchor, in
    /// the order listed, joined to its up to `anchors.max_springs` nearest non-anchor particles
    /// within `anchors.radius_m` (ties in distance broken by the lower index). The anchors'
    /// springs come last.
    ///
    /// ```
    /// use glam::Vec3;
    /// // A row of four points 1 cm apart and a controller point 3 cm above the first.
    /// let mut pts: Vec<Vec3> = (0..4).map(|i| Vec3::new(0.01 * i as f32, 0.0, 0.0)).collect();
    /// pts.push(Vec3::new(0.0, 0.0, 0.03));
    /// let anchors = springs::AnchorSprings { particles: vec![4].into(), radius_m: 0.04, max_springs: 2 };
    /// let topo = springs::Topology::build_anchored(&pts, 0.015, 8, None, Some(&anchors))?;
    /// // The object's own springs at 1.5 cm, then the anchor's two nearest within 4 cm.
    /// assert_eq!(topo.springs, vec![[0, 1], [1, 2], [2, 3], [0, 4], [1, 4]]);
    /// # Ok::<(), springs::SimError>(())
    /// ```
    pub fn build_anchored(
        positions: &[Vec3],
        threshold: f32,
        max_springs: u32,
        filter: Option<&dyn PairFilter>,
        anchors: Option<&AnchorSprings>,
    ) -> Result<Self, SimError> {
        if !(threshold.is_finite() && threshold > 0.0) {
            return Err(SimError::InvalidParameter {
                name: "threshold",
                value: f64::from(threshold),
                reason: "must be finite and > 0",
            });
        }
        if let Some(index) = positions.iter().position(|p| !p.is_finite()) {
            return Err(SimError::NonFinite {
                what: "positions",
                index,
            });
        }
        let n = positions.len();
        if n > u32::MAX as usize {
            return Err(SimError::TooLarge {
                what: "particle count",
                value: n as u64,
                limit: u64::from(u32::MAX),
            });
        }
        let per_point = u64::from(max_springs) + 3;
        if n as u64 * per_point.min(n as u64) > MAX_CANDIDATES {
            return Err(SimError::TooLarge {
                what: "neighbour candidates",
                value: n as u64 * per_point,
                limit: MAX_CANDIDATES,
            });
        }
        let is_anchor = anchor_mask(n, anchors)?;
        if n < 2 {
            return Ok(Self {
                springs: Vec::new(),
                rest_lengths: Vec::new(),
            });
        }
        let per_point = per_point as usize;
        let t2 = threshold * threshold;
        let pts: Vec<[f32; 3]> = positions.iter().map(|p| p.to_array()).collect();
        let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(&pts);
        // Query a slightly larger radius, then decide with our own distance so that the result
        // never depends on how the tree rounds.
        let query_r2 = t2 * (1.0 + 1e-4) + f32::MIN_POSITIVE;

        let mut candidates: Vec<(f32, u32, u32)> = Vec::new();
        let mut near: Vec<(f32, u32)> = Vec::new();
        for (i, &p) in positions.iter().enumerate() {
            if max_springs == 0 || is_anchor[i] {
                continue;
            }
            near.clear();
            for nb in tree.within_unsorted::<SquaredEuclidean>(&pts[i], query_r2) {
                let j = nb.item;
                if j as usize == i || is_anchor[j as usize] {
                    continue;
                }
                let d2 = dist2(p, positions[j as usize]);
                if d2 <= t2 && filter.is_none_or(|f| f.keep(i, j as usize, threshold)) {
                    near.push((d2, j));
                }
            }
            if near.len() > per_point {
                near.select_nth_unstable_by(per_point - 1, cmp_near);
                near.truncate(per_point);
            }
            let i = i as u32;
            candidates.extend(near.iter().map(|&(d2, j)| (d2, i.min(j), i.max(j))));
        }
        candidates
            .sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
        candidates.dedup_by(|a, b| a.1 == b.1 && a.2 == b.2);

        let mut count = vec![0u32; n];
        let mut springs = Vec::new();
        let mut rest_lengths = Vec::new();
        for &(_, a, b) in &candidates {
            let (ua, ub) = (a as usize, b as usize);
            if count[ua] < max_springs && count[ub] < max_springs {
                count[ua] += 1;
                count[ub] += 1;
                springs.push([a, b]);
                rest_lengths.push(kernel_distance(positions[ua], positions[ub]));
            }
        }
        if let Some(anchors) = anchors {
            let r2 = anchors.radius_m * anchors.radius_m;
            let query_r2 = r2 * (1.0 + 1e-4) + f32::MIN_POSITIVE;
            let most = anchors.max_springs as usize;
            for &a in anchors.particles.iter() {
                let p = positions[a as usize];
                near.clear();
                for nb in tree.within_unsorted::<SquaredEuclidean>(&pts[a as usize], query_r2) {
                    let j = nb.item;
                    let d2 = dist2(p, positions[j as usize]);
                    if !is_anchor[j as usize] && d2 <= r2 {
                        near.push((d2, j));
                    }
                }
                near.sort_unstable_by(cmp_near);
                for &(_, j) in near.iter().take(most) {
                    springs.push([a.min(j), a.max(j)]);
                    rest_lengths.push(kernel_distance(p, positions[j as usize]));
                }
            }
        }
        Ok(Self {
            springs,
            rest_lengths,
        })
    }

    /// Number of springs.
    pub fn len(&self) -> usize {
        self.springs.len()
    }

    /// Whether there are no springs.
    pub fn is_empty(&self) -> bool {
        self.springs.is_empty()
    }

    /// Springs attached to each of `num_particles` particles (indices beyond are ignored).
    pub fn springs_per_particle(&self, num_particles: usize) -> Vec<u32> {
        let mut count = vec![0u32; num_particles];
        for &[a, b] in &self.springs {
            for p in [a, b] {
                if let Some(c) = count.get_mut(p as usize) {
                    *c += 1;
                }
            }
        }
        count
    }
}

/// Which of `n` particles are anchors; an error for a bad radius, an index beyond the
/// particles or one named twice.
fn anchor_mask(n: usize, anchors: Option<&AnchorSprings>) -> Result<Vec<bool>, SimError> {
    let Some(anchors) = anchors else {
        return Ok(vec![false; n]);
    };
    if !(anchors.radius_m.is_finite() && anchors.radius_m > 0.0) {
        return Err(SimError::InvalidParameter {
            name: "anchor radius",
            value: f64::from(anchors.radius_m),
            reason: "must be finite and > 0",
        });
    }
    mark_each_once(n, &anchors.particles, "anchors")
}

/// Marks the `indices` among `n` particles; an error naming `what` for an index beyond them or
/// one named twice.
pub(crate) fn mark_each_once(
    n: usize,
    indices: &[u32],
    what: &'static str,
) -> Result<Vec<bool>, SimError> {
    let mut mask = vec![false; n];
    for &i in indices {
        let reason = match mask.get_mut(i as usize) {
            Some(seen) if !*seen => {
                *seen = true;
                continue;
            }
            Some(_) => "listed twice",
            None => "beyond the model's particles",
        };
        return Err(SimError::InvalidParameter {
            name: what,
            value: f64::from(i),
            reason,
        });
    }
    Ok(mask)
}

fn cmp_near(a: &(f32, u32), b: &(f32, u32)) -> std::cmp::Ordering {
    a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
}
