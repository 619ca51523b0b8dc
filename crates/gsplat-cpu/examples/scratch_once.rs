#![allow(missing_docs)]
use glam::{Quat, Vec3};
use gsplat::{Camera, Gaussians, render};
use std::f32::consts::TAU;
include!("/tmp/gsprof/scenes.rs");
fn main() {
    let cam = camera();
    let which = std::env::args().nth(1).unwrap();
    let scene = if which == "object" {
        object_scene(50_000)
    } else {
        cloud_scene(50_000)
    };
    std::hint::black_box(render(&scene, &cam, [1.0; 3]).unwrap());
}
