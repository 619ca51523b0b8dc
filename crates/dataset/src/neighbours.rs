//! Which tracked points lie next to each other on the object, learned from recordings, and where
//! that places a point the tracker has not seen yet.
//!
//! An episode cut from a longer recording starts with whatever the tracker last reported: a point
//! occluded since before the cut is stored where it was then, possibly tens of centimetres from
//! the object's current place (a point held in a moving gripper, seen half a second earlier).
//! [`carried_frame`](crate::carried_frame) can only carry points seen earlier in the episode. For
//! the rest, its neighbours on the object say where it is: tracked point `i` is the same material
//! point in every episode of a dataset (the format's contract, `docs/data-format.md`), so the
//! points that stay close to it across the training recordings are its material neighbours, and
//! their centroid is usually a far better guess than the stale report (docs/pipelines.md).

use glam::Vec3;
use std::num::NonZeroUsize;

use kiddo::SquaredEuclidean;
use kiddo::immutable::float::kdtree::ImmutableKdTree;

use crate::Episode;

/// Frames sampled per episode while learning (evenly spaced, the first included).
const FRAMES_PER_EPISODE: usize = 4;
/// Nearest points per sampled frame that become candidate neighbours.
const CANDIDATES_PER_FRAME: usize = 12;
/// Neighbours kept per point, nearest first.
const KEPT: usize = 16;
/// Co-visible samples a pair needs before its mean distance is trusted.
const MIN_SAMPLES: u32 = 3;
/// Seen neighbours whose centroid places an unseen point.
pub const PLACING_NEIGHBOURS: usize = 4;

/// Per tracked point, the points that stay nearest to it across recordings, nearest first.
///
/// Learned by [`MaterialNeighbours::learn`]; used by [`MaterialNeighbours::place_unseen`].
#[derive(Clone, Debug, PartialEq)]
pub struct MaterialNeighbours {
    lists: Vec<Vec<u32>>,
}

impl MaterialNeighbours {
    /// Learns the neighbours from `episodes` (one dataset's, normally its training split): a pair
    /// of points is a candidate when either is among the other's 12 nearest visible points in
    /// some sampled frame (4 per episode, evenly spaced); candidates are ranked by their mean
    /// distance over every sampled frame where both were visible (at least 3 such frames), and
    /// the 16 nearest are kept per point. Only visible positions are used, so stale reports
    /// never teach a neighbourhood.
    ///
    /// `None` when there is no episode or the episodes disagree on the particle count (they
    /// cannot then share material points).
    ///
    /// ```
    /// use dataset::{Episode, MaterialNeighbours};
    /// use glam::Vec3;
    /// // Five points on a line at 0, 1, 3, 7 and 15 cm, in four frames sliding along x.
    /// let at = [0.0, 0.01, 0.03, 0.07, 0.15];
    /// let positions: Vec<Vec3> = (0..4)
    ///     .flat_map(|t| at.map(|x| Vec3::new(x + 0.1 * t as f32, 0.0, 0.0)))
    ///     .collect();
    /// let episode = Episode::new(4, 5, 1, positions, vec![Vec3::ZERO; 4])?;
    /// let table = MaterialNeighbours::learn([&episode]).unwrap();
    /// assert_eq!(table.of(2), [1, 0, 3, 4]);
    /// # Ok::<(), dataset::Error>(())
    /// ```
    pub fn learn<'a>(episodes: impl IntoIterator<Item = &'a Episode>) -> Option<Self> {
        let episodes: Vec<&Episode> = episodes.into_iter().collect();
        let n = episodes.first()?.particles();
        if n == 0 || episodes.iter().any(|e| e.particles() != n) {
            return None;
        }
        let samples: Vec<(&Episode, usize)> = episodes
            .iter()
            .flat_map(|e| sampled_frames(e.frames()).map(move |t| (*e, t)))
            .collect();
        let candidates = candidate_pairs(&samples, n);
        let lists = candidates
            .into_iter()
            .enumerate()
            .map(|(i, cands)| {
                let mut ranked: Vec<(f32, u32)> = cands
                    .into_iter()
                    .filter_map(|j| mean_distance(&samples, i, j as usize).map(|d| (d, j)))
                    .collect();
                ranked.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                ranked.truncate(KEPT);
                ranked.into_iter().map(|(_, j)| j).collect()
            })
            .collect();
        Some(MaterialNeighbours { lists })
    }

    /// Number of tracked points the table covers.
    pub fn particles(&self) -> usize {
        self.lists.len()
    }

    /// The material neighbours of point `i`, nearest first (empty when `i` is out of range).
    pub fn of(&self, i: usize) -> &[u32] {
        self.lists.get(i).map_or(&[], Vec::as_slice)
    }

    /// Moves every point of `frame` (frame `t` of `episode`, e.g. as
    /// [`carried_frame`](crate::carried_frame) returns it) that was not visible at any frame
    /// `0..=t` to the centroid of its first 4 listed neighbours that were; a point without such
    /// a neighbour keeps its position. Only frames up to `t` are read. Points beyond the table
    /// (or the frame) are left alone.
    pub fn place_unseen(&self, episode: &Episode, t: usize, frame: &mut [Vec3]) {
        let seen = |i: usize| (0..=t).any(|s| episode.visible(s, i));
        let n = frame.len().min(self.particles()).min(episode.particles());
        let placed: Vec<(usize, Vec3)> = (0..n)
            .filter(|&i| !seen(i))
            .filter_map(|i| {
                let near: Vec<Vec3> = self
                    .of(i)
                    .iter()
                    .map(|&j| j as usize)
                    .filter(|&j| j < n && seen(j))
                    .take(PLACING_NEIGHBOURS)
                    .map(|j| frame[j])
                    .collect();
                (!near.is_empty()).then(|| (i, near.iter().sum::<Vec3>() / near.len() as f32))
            })
            .collect();
        for (i, p) in placed {
            frame[i] = p;
        }
    }
}

/// The frames sampled from an episode of `frames` frames.
fn sampled_frames(frames: usize) -> impl Iterator<Item = usize> {
    let k = FRAMES_PER_EPISODE.min(frames);
    let mut picked: Vec<usize> = (0..k).map(|s| s * frames / k).collect();
    picked.dedup();
    picked.into_iter()
}

/// Per point, the points that were among its nearest visible ones (or it among theirs) in some
/// sampled frame; sorted, without repeats.
fn candidate_pairs(samples: &[(&Episode, usize)], n: usize) -> Vec<Vec<u32>> {
    let mut cands: Vec<Vec<u32>> = vec![Vec::new(); n];
    // The point itself comes back first.
    let query = NonZeroUsize::new(CANDIDATES_PER_FRAME + 1).expect("at least one");
    for &(episode, t) in samples {
        let frame = episode.frame(t);
        let visible: Vec<usize> = (0..n).filter(|&i| episode.visible(t, i)).collect();
        // The immutable tree: kiddo's mutable one panics past a bucket of points at one position.
        let pts: Vec<[f32; 3]> = visible.iter().map(|&i| frame[i].to_array()).collect();
        let tree: ImmutableKdTree<f32, u32, 3, 32> = ImmutableKdTree::new_from_slice(&pts);
        for (&i, p) in visible.iter().zip(&pts) {
            for hit in tree.nearest_n::<SquaredEuclidean>(p, query) {
                let j = visible[hit.item as usize];
                if j != i {
                    cands[i].push(j as u32);
                    cands[j].push(i as u32);
                }
            }
        }
        // The same neighbours come back frame after frame; compact long lists as they grow so
        // memory follows the distinct candidates, not the number of sampled frames.
        for c in cands.iter_mut().filter(|c| c.len() > COMPACT_AT) {
            compact(c);
        }
    }
    cands.iter_mut().for_each(compact);
    cands
}

/// Candidate-list length past which it is sorted and deduplicated during learning.
const COMPACT_AT: usize = 1024;

/// Sorts `c` and drops repeats.
fn compact(c: &mut Vec<u32>) {
    c.sort_unstable();
    c.dedup();
}

/// Mean distance of points `i` and `j` over the sampled frames where both were visible, when
/// there are enough of them.
fn mean_distance(samples: &[(&Episode, usize)], i: usize, j: usize) -> Option<f32> {
    let (mut sum, mut count) = (0.0f64, 0u32);
    for &(episode, t) in samples {
        if episode.visible(t, i) && episode.visible(t, j) {
            let f = episode.frame(t);
            sum += f64::from(f[i].distance(f[j]));
            count += 1;
        }
    }
    let needed = MIN_SAMPLES.min(samples.len() as u32);
    (count >= needed.max(1)).then(|| (sum / f64::from(count)) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4 × 4 grid of points 1 cm apart (index = 4 row + column) in `frames` frames, drifting
    /// along x; `hide` lists (frame, point) pairs the tracker lost, stored at a stale place.
    fn grid(frames: usize, hide: &[(usize, usize)]) -> Episode {
        let mut positions = Vec::new();
        for t in 0..frames {
            for i in 0..16 {
                let (r, c) = ((i / 4) as f32, (i % 4) as f32);
                positions.push(Vec3::new(0.01 * c + 0.05 * t as f32, 0.01 * r, 0.0));
            }
        }
        let mut visible = vec![1u8; frames * 16];
        for &(t, i) in hide {
            visible[t * 16 + i] = 0;
            positions[t * 16 + i] = Vec3::new(1.0, 1.0, 1.0);
        }
        Episode::new(frames, 16, 1, positions, vec![Vec3::ZERO; frames])
            .and_then(|e| e.with_visible(visible))
            .unwrap()
    }

    #[test]
    fn neighbours_are_the_points_that_stay_close() {
        let table = MaterialNeighbours::learn([&grid(8, &[])]).unwrap();
        assert_eq!(table.particles(), 16);
        // Point 5 (row 1, column 1): its four direct neighbours first.
        let mut first = table.of(5)[..4].to_vec();
        first.sort_unstable();
        assert_eq!(first, [1, 4, 6, 9]);
        assert!(table.of(16).is_empty());
    }

    #[test]
    fn stale_reports_teach_nothing() {
        // Point 0 is stored at (1, 1, 1) in every sampled frame but one: a pair seen together
        // fewer than three times is not ranked, so point 0 gets no neighbour from a stale place.
        let hide: Vec<(usize, usize)> = (1..8).map(|t| (t, 0)).collect();
        let table = MaterialNeighbours::learn([&grid(8, &hide)]).unwrap();
        assert!(table.of(0).is_empty(), "{:?}", table.of(0));
        assert!(!table.of(5).contains(&0));
    }

    #[test]
    fn an_unseen_point_goes_to_its_neighbours_centroid() {
        let table = MaterialNeighbours::learn([&grid(8, &[])]).unwrap();
        // Point 5 lost in frames 0..=2, point 6 in frame 2 only (seen before: not moved here).
        let episode = grid(4, &[(0, 5), (1, 5), (2, 5), (2, 6)]);
        let mut frame = episode.frame(2).to_vec();
        table.place_unseen(&episode, 2, &mut frame);
        // Neighbours 1, 4, 9 are seen; 6 was seen at frames 0-1, so it counts too, at its
        // (stale) frame-2 position: the caller carries such points first.
        let want =
            (episode.frame(2)[1] + episode.frame(2)[4] + episode.frame(2)[6] + episode.frame(2)[9])
                / 4.0;
        assert!((frame[5] - want).length() < 1e-6, "{:?}", frame[5]);
        assert_eq!(frame[6], episode.frame(2)[6]);
        assert_eq!(frame[0], episode.frame(2)[0]);
    }

    #[test]
    fn many_points_at_one_place_are_no_error() {
        // A tracker that reports 40 points at the origin in every frame.
        let episode = Episode::new(4, 40, 1, vec![Vec3::ZERO; 160], vec![Vec3::ZERO; 4]).unwrap();
        let table = MaterialNeighbours::learn([&episode]).unwrap();
        assert_eq!(table.particles(), 40);
    }

    #[test]
    fn episodes_that_disagree_on_the_points_learn_nothing() {
        let three = Episode::new(1, 3, 1, vec![Vec3::ZERO; 3], vec![Vec3::ZERO]).unwrap();
        assert!(MaterialNeighbours::learn([&grid(2, &[]), &three]).is_none());
        assert!(MaterialNeighbours::learn(std::iter::empty()).is_none());
    }
}
