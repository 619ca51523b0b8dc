#![allow(missing_docs)]
use glam::{Quat, Vec3};
use gsplat::{GaussianRig, RigOptions};
fn main() {
    let pts: Vec<Vec3> = (0..1000)
        .map(|k| Vec3::new((k % 40) as f32, (k / 40) as f32, 0.0) * 0.01)
        .collect();
    let colors = vec![[0.8, 0.2, 0.2]; pts.len()];
    let rig = GaussianRig::from_particles(&pts, &colors, &RigOptions::default()).unwrap();
    let folded: Vec<Vec3> = pts
        .iter()
        .map(|p| Quat::from_rotation_y(-0.8 * p.x) * *p)
        .collect();
    let mut r = rig.clone();
    std::hint::black_box(r.deform(&folded).unwrap());
}
