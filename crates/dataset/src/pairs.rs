//! How far apart each pair of tracked points usually is, learned from recordings: which points
//! that lie close together at one frame are material neighbours, and which only touch there.
//!
//! A spring-mass model connects the points that lie within a radius of each other at its start
//! frame (the paper's construction, made for a recording that starts at rest). An episode cut
//! from the middle of a recording can start with the object folded onto itself: a rope lying
//! across its own loop, a cloth's corner on its middle. Springs built there glue the touching
//! parts together for the whole rollout, and a rollout started later in such an episode, after
//! the parts came apart, sees those springs stretched tens of centimetres and snaps the parts
//! together in one step (docs/pipelines.md, "Material springs"). Tracked point `i` is the same
//! material point in every episode (docs/data-format.md), so the training recordings tell the
//! two apart: material neighbours stay close in every frame, touching parts do not.

use crate::Episode;

/// Frames sampled per episode while learning (evenly spaced, the first and last included).
const FRAMES_PER_EPISODE: usize = 8;
/// Co-visible samples a pair needs before its mean distance is trusted.
const MIN_SAMPLES: u32 = 3;
/// Most tracked points a table is learned for: it holds every pair, 12 bytes each while
/// learning and 4 after, so 4096 points take about 100 MB while learning and 34 MB after.
pub const MAX_PAIR_POINTS: usize = 4096;

/// Per pair of tracked points, the mean distance between them over the training recordings'
/// sampled frames where both were visible (m).
///
/// Learned by [`MaterialPairs::learn`]; read with [`MaterialPairs::mean_distance`].
#[derive(Clone, Debug, PartialEq)]
pub struct MaterialPairs {
    n: usize,
    /// Upper triangle, row by row: pair `(i, j)`, `i < j`, at `i (2n − i − 1) / 2 + j − i − 1`;
    /// NaN where the pair had fewer than [`MIN_SAMPLES`] co-visible samples.
    mean: Vec<f32>,
}

impl MaterialPairs {
    /// Learns the table from `episodes` (one dataset's, normally its training split): 8 frames
    /// sampled evenly from each episode, and per pair the mean distance over those where both
    /// points were visible (stale reports of lost points never count). `None` when there is no
    /// episode, the episodes disagree on the particle count (they cannot then share material
    /// points), or there are more than [`MAX_PAIR_POINTS`] points.
    ///
    /// ```
    /// use dataset::{Episode, MaterialPairs};
    /// use glam::Vec3;
    /// // Three points: 0 and 1 stay 1 cm apart; 2 touches 0 in the first frame, then leaves.
    /// let frames = [0.0f32, 0.1, 0.2, 0.3];
    /// let positions: Vec<Vec3> = frames
    ///     .iter()
    ///     .flat_map(|&s| [Vec3::ZERO, Vec3::new(0.01, 0.0, 0.0), Vec3::new(0.0, 0.01 + s, 0.0)])
    ///     .collect();
    /// let episode = Episode::new(4, 3, 1, positions, vec![Vec3::ZERO; 4])?;
    /// let pairs = MaterialPairs::learn([&episode]).unwrap();
    /// assert!((pairs.mean_distance(0, 1).unwrap() - 0.01).abs() < 1e-6);
    /// assert!((pairs.mean_distance(2, 0).unwrap() - 0.16).abs() < 1e-6);
    /// # Ok::<(), dataset::Error>(())
    /// ```
    pub fn learn<'a>(episodes: impl IntoIterator<Item = &'a Episode>) -> Option<Self> {
        let episodes: Vec<&Episode> = episodes.into_iter().collect();
        let n = episodes.first()?.particles();
        if !(2..=MAX_PAIR_POINTS).contains(&n) || episodes.iter().any(|e| e.particles() != n) {
            return None;
        }
        let pairs = n * (n - 1) / 2;
        let mut sum = vec![0.0f64; pairs];
        let mut count = vec![0u32; pairs];
        for e in &episodes {
            for t in sampled_frames(e.frames()) {
                let x = e.frame(t);
                let seen: Vec<bool> = (0..n).map(|i| e.visible(t, i)).collect();
                let mut k = 0;
                for i in 0..n {
                    for j in i + 1..n {
                        if seen[i] && seen[j] {
                            sum[k] += f64::from(x[i].distance(x[j]));
                            count[k] += 1;
                        }
                        k += 1;
                    }
                }
            }
        }
        let mean = sum
            .iter()
            .zip(&count)
            .map(|(s, &c)| {
                if c >= MIN_SAMPLES {
                    (s / f64::from(c)) as f32
                } else {
                    f32::NAN
                }
            })
            .collect();
        Some(MaterialPairs { n, mean })
    }

    /// Number of tracked points the table covers.
    pub fn particles(&self) -> usize {
        self.n
    }

    /// Mean distance between points `i` and `j` over the co-visible sampled frames, m; `None`
    /// for `i == j`, a point beyond the table, or a pair seen together too rarely to say.
    pub fn mean_distance(&self, i: usize, j: usize) -> Option<f32> {
        let (i, j) = (i.min(j), i.max(j));
        if i == j || j >= self.n {
            return None;
        }
        let k = i * (2 * self.n - i - 1) / 2 + (j - i - 1);
        Some(self.mean[k]).filter(|d| d.is_finite())
    }
}

/// `FRAMES_PER_EPISODE` frames spread evenly over `frames`, first and last included.
fn sampled_frames(frames: usize) -> impl Iterator<Item = usize> {
    let k = FRAMES_PER_EPISODE.min(frames);
    let mut picked: Vec<usize> = (0..k)
        .map(|s| {
            if k == 1 {
                0
            } else {
                s * (frames - 1) / (k - 1)
            }
        })
        .collect();
    picked.dedup();
    picked.into_iter()
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn pairs_are_indexed_symmetrically_and_every_pair_has_its_own_slot() {
        // Five points on a line at 0, 1, 3, 6, 10 m: every pair's distance is distinct.
        let at = [0.0f32, 1.0, 3.0, 6.0, 10.0];
        let positions: Vec<Vec3> = (0..3)
            .flat_map(|_| at.map(|x| Vec3::new(x, 0.0, 0.0)))
            .collect();
        let e = Episode::new(3, 5, 1, positions, vec![Vec3::ZERO; 3]).unwrap();
        let pairs = MaterialPairs::learn([&e]).unwrap();
        for i in 0..5 {
            assert_eq!(pairs.mean_distance(i, i), None);
            for j in 0..5 {
                if i != j {
                    let d = (at[i] - at[j]).abs();
                    assert_eq!(pairs.mean_distance(i, j), Some(d), "({i}, {j})");
                }
            }
        }
        assert_eq!(pairs.mean_distance(0, 5), None);
    }

    #[test]
    fn occluded_samples_do_not_count_and_rare_pairs_are_unknown() {
        // Point 2 is visible in 2 of 4 frames only; its stale reports sit on point 0.
        let positions: Vec<Vec3> = (0..4)
            .flat_map(|t| [Vec3::ZERO, Vec3::X, Vec3::new(0.0, 1.0 + t as f32, 0.0)])
            .collect();
        let visible = vec![1, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1, 0];
        let e = Episode::new(4, 3, 1, positions, vec![Vec3::ZERO; 4])
            .unwrap()
            .with_visible(visible)
            .unwrap();
        let pairs = MaterialPairs::learn([&e]).unwrap();
        assert_eq!(pairs.mean_distance(0, 1), Some(1.0));
        assert_eq!(pairs.mean_distance(0, 2), None);
        // Two episodes that disagree on the points share no table.
        let three = Episode::new(1, 3, 1, vec![Vec3::ZERO; 3], vec![Vec3::ZERO]).unwrap();
        let two = Episode::new(1, 2, 1, vec![Vec3::ZERO; 2], vec![Vec3::ZERO]).unwrap();
        assert!(MaterialPairs::learn([&three, &two]).is_none());
        assert!(MaterialPairs::learn(std::iter::empty()).is_none());
    }
}
