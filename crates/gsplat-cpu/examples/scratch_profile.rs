#![allow(missing_docs)]
use glam::{Quat, Vec3};
use gsplat::{Camera, Gaussians, render};
use std::f32::consts::TAU;
include!("/tmp/gsprof/scenes.rs");
fn main() {
    let cam = camera();
    for (name, scene) in [
        ("object", object_scene(50_000)),
        ("cloud", cloud_scene(50_000)),
    ] {
        let mut best = f64::MAX;
        let mut all = vec![];
        for _ in 0..20 {
            let t = std::time::Instant::now();
            std::hint::black_box(render(&scene, &cam, [1.0; 3]).unwrap());
            let d = t.elapsed().as_secs_f64() * 1e3;
            best = best.min(d);
            all.push(d);
        }
        all.sort_by(f64::total_cmp);
        println!("{name}: wall min {best:.1} ms, median {:.1} ms", all[10]);
    }
}
