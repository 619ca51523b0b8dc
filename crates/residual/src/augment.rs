//! Random rotation about the vertical axis (z), the training augmentation. Gravity and the
//! ground plane are invariant under it, so a rotated scene is as physical as the original.

use glam::{Quat, Vec3};
use scene::Scene;
use springs::Actions;

use crate::{History, Result};

fn rot(q: Quat, v: &[Vec3]) -> Vec<Vec3> {
    v.iter().map(|p| q * *p).collect()
}

/// `scene` rotated by `angle` radians about the z axis through the origin: initial state,
/// gripper positions and truth (held, visibility and window unchanged).
pub fn rotate_scene(scene: &Scene, angle: f32) -> Result<Scene> {
    let q = Quat::from_rotation_z(angle);
    let mut out = scene.clone();
    out.init.x = rot(q, &scene.init.x);
    out.init.v = rot(q, &scene.init.v);
    out.truth = scene.truth.iter().map(|t| rot(q, t)).collect();
    let frames = scene.actions.num_frames();
    let (mut pos, mut closed) = (Vec::with_capacity(frames), Vec::with_capacity(frames));
    for t in 0..frames {
        if let Some(f) = scene.actions.frame(t) {
            pos.push(rot(q, f.positions));
            closed.push(f.closed.to_vec());
        }
    }
    out.actions = if scene.actions.num_grippers() == 0 {
        Actions::without_grippers(frames)
    } else {
        Actions::new(pos, closed)?
    };
    Ok(out)
}

/// `history` rotated by `angle` radians about the z axis.
pub fn rotate_history(history: &History, angle: f32) -> History {
    let q = Quat::from_rotation_z(angle);
    History {
        x: [rot(q, &history.x[0]), rot(q, &history.x[1])],
        v: [rot(q, &history.v[0]), rot(q, &history.v[1])],
    }
}
