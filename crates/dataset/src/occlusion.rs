//! Positions of occluded tracked points, carried along from their last sighting.
//!
//! A tracker that loses a point keeps reporting where it last saw it (the reference world's
//! observation model does this, `docs/world.md`). Scoring masks such points out, but a rollout
//! that starts at a frame where a point is occluded would start it at a stale position, possibly
//! centimetres from where the object is now: a held point left behind by its moving gripper, a
//! free point left where the rope was a second ago. [`carried_frame`] moves each such point by
//! the motion its surroundings made since it was last seen, using only frames up to `t`.

use glam::Vec3;

use crate::Episode;

/// Neighbours whose mean displacement carries a free occluded point.
const NEIGHBOURS: usize = 4;

/// Tracked positions at frame `t` (m), with every point occluded at `t` moved from its last
/// sighting `s < t` by the motion since `s` of what it moves with:
/// - a held point (`held[i] = g ≥ 0`) by its gripper's displacement `g(t) − g(s)` (grippers are
///   exact), when the gripper stayed closed from `s` to `t` (else as a free point);
/// - a free point by the mean displacement of the 4 points nearest it at `s` that
///   are visible at both `s` and `t`.
///
/// A point never seen up to `t`, or a free one without such neighbours, keeps its stored
/// position. Visible points are returned as stored. `held` shorter than the particle count
/// counts the missing ones as free.
///
/// ```
/// use dataset::{Episode, carried_frame};
/// use glam::Vec3;
/// // 3 frames × 1 particle, held by the one gripper, which moves 1 m along x per frame; the
/// // tracker lost the particle after frame 0 and kept reporting its frame-0 position.
/// let positions = vec![Vec3::ZERO; 3];
/// let grippers = vec![Vec3::ZERO, Vec3::X, 2.0 * Vec3::X];
/// let episode = Episode::new(3, 1, 1, positions, grippers)?.with_visible(vec![1, 0, 0])?;
/// assert_eq!(carried_frame(&episode, 2, &[0]), vec![2.0 * Vec3::X]);
/// # Ok::<(), dataset::Error>(())
/// ```
pub fn carried_frame(episode: &Episode, t: usize, held: &[i32]) -> Vec<Vec3> {
    let stored = episode.frame(t);
    let mut out = stored.to_vec();
    for (i, slot) in out.iter_mut().enumerate() {
        if episode.visible(t, i) {
            continue;
        }
        let Some(s) = (0..t).rev().find(|&s| episode.visible(s, i)) else {
            continue;
        };
        let seen = episode.frame(s)[i];
        // A held point follows its gripper only while the gripper stays closed.
        let gripper = usize::try_from(held.get(i).copied().unwrap_or(-1))
            .ok()
            .filter(|&g| g < episode.grippers() && (s..=t).all(|f| episode.closed(f, g)));
        if let Some(g) = gripper {
            *slot = seen + episode.gripper_frame(t)[g] - episode.gripper_frame(s)[g];
        } else if let Some(shift) = neighbour_shift(episode, i, s, t) {
            *slot = seen + shift;
        }
    }
    out
}

/// Mean displacement from frame `s` to `t` of the points nearest `i` at `s` that are visible at
/// both frames.
fn neighbour_shift(episode: &Episode, i: usize, s: usize, t: usize) -> Option<Vec3> {
    let at_s = episode.frame(s);
    let at_t = episode.frame(t);
    let centre = at_s[i];
    let mut near: Vec<(f32, usize)> = (0..episode.particles())
        .filter(|&j| j != i && episode.visible(s, j) && episode.visible(t, j))
        .map(|j| (at_s[j].distance_squared(centre), j))
        .collect();
    if near.is_empty() {
        return None;
    }
    let k = NEIGHBOURS.min(near.len());
    near.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0));
    let sum: Vec3 = near[..k].iter().map(|&(_, j)| at_t[j] - at_s[j]).sum();
    Some(sum / k as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two particles 1 m apart sliding +x at 0.5 m per frame; particle 1 is occluded from
    /// frame 1 on and stored at its frame-0 position.
    fn sliding_pair() -> Episode {
        let mut positions = Vec::new();
        for t in 0..4 {
            positions.push(0.5 * t as f32 * Vec3::X);
            positions.push(Vec3::Y);
        }
        let grippers = (0..4).map(|t| Vec3::new(0.0, 5.0, t as f32)).collect();
        Episode::new(4, 2, 1, positions, grippers)
            .unwrap()
            .with_visible(vec![1, 1, 1, 0, 1, 0, 1, 0])
            .unwrap()
    }

    fn assert_near(got: Vec3, want: Vec3) {
        assert!((got - want).length() < 1e-6, "{got:?} != {want:?}");
    }

    #[test]
    fn a_free_point_moves_with_its_visible_neighbours() {
        let e = sliding_pair();
        let f = carried_frame(&e, 3, &[-1, -1]);
        assert_eq!(f[0], e.frame(3)[0]);
        assert_near(f[1], Vec3::Y + 1.5 * Vec3::X);
    }

    #[test]
    fn a_held_point_moves_with_its_gripper() {
        let e = sliding_pair();
        let f = carried_frame(&e, 2, &[-1, 0]);
        // The gripper rose 2 m along z between frames 0 and 2.
        assert_near(f[1], Vec3::Y + 2.0 * Vec3::Z);
    }

    #[test]
    fn a_point_whose_gripper_opened_moves_with_its_neighbours() {
        let e = sliding_pair().with_closed(vec![1, 0, 1, 1]).unwrap();
        let f = carried_frame(&e, 2, &[-1, 0]);
        assert_near(f[1], Vec3::Y + Vec3::X);
    }

    #[test]
    fn visible_and_never_seen_points_keep_their_stored_positions() {
        let positions = vec![Vec3::ZERO, Vec3::X, Vec3::ZERO, 2.0 * Vec3::X];
        let grippers = vec![Vec3::ZERO; 2];
        let e = Episode::new(2, 2, 1, positions, grippers)
            .unwrap()
            .with_visible(vec![0, 1, 0, 1])
            .unwrap();
        assert_eq!(carried_frame(&e, 1, &[0, -1]), e.frame(1).to_vec());
        assert_eq!(carried_frame(&e, 0, &[]), e.frame(0).to_vec());
    }
}
