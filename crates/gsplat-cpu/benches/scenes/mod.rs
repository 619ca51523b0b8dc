//! The benchmark scenes, shared by `benches/render.rs` and `examples/render_timing.rs`.
//!
//! Seeded, 640 x 480, 50° vertical field of view, camera about 1.2 m away:
//! - `object`: 50 000 flat, mostly opaque Gaussians tiling the surfaces of a sphere (r 25 cm)
//!   and a torus around it (R 35 cm, r 6 cm), ~5 mm apart: what a fitted 3DGS object looks like.
//! - `cloud`: 50 000 Gaussians filling a 40 cm ball, random orientations, log-uniform std
//!   1-15 mm, opacities uniform in 0.05-1: semi-transparent volume, a harder case.

use std::f32::consts::TAU;

use glam::{Quat, Vec3};
use gsplat::{Camera, Gaussians};

/// SplitMix64 stream of uniforms in [0, 1).
struct Rng(u64);

impl Rng {
    fn f(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A Gaussian flat along `normal` (std 0.5 mm), `tangent_std` wide, at `p`.
fn push_flat(
    g: &mut Gaussians,
    rng: &mut Rng,
    p: Vec3,
    normal: Vec3,
    tangent_std: f32,
    color: [f32; 3],
) {
    let spin = Quat::from_axis_angle(normal, TAU * rng.f());
    g.means.push(p);
    g.rotations
        .push(spin * Quat::from_rotation_arc(Vec3::Z, normal));
    g.scales.push(Vec3::new(
        tangent_std * (0.7 + 0.6 * rng.f()),
        tangent_std * (0.7 + 0.6 * rng.f()),
        5e-4,
    ));
    g.opacities.push(0.7 + 0.3 * rng.f());
    g.colors.push(color);
}

pub fn object_scene(n: usize) -> Gaussians {
    let mut rng = Rng(1);
    let mut g = Gaussians::default();
    for k in 0..n {
        if k % 2 == 0 {
            // Sphere: uniform directions.
            let z = 2.0 * rng.f() - 1.0;
            let phi = TAU * rng.f();
            let n = Vec3::new(
                (1.0 - z * z).sqrt() * phi.cos(),
                (1.0 - z * z).sqrt() * phi.sin(),
                z,
            );
            let c = [0.5 + 0.4 * n.x, 0.5 + 0.4 * n.y, 0.6];
            push_flat(&mut g, &mut rng, n * 0.25, n, 0.004, c);
        } else {
            // Torus about z: uniform angles (denser on the inner side, like real captures).
            let (u, v) = (TAU * rng.f(), TAU * rng.f());
            let ring = Vec3::new(u.cos(), u.sin(), 0.0);
            let n = ring * v.cos() + Vec3::Z * v.sin();
            let c = [0.9, 0.5 + 0.4 * (3.0 * u).sin(), 0.2];
            push_flat(&mut g, &mut rng, ring * 0.35 + n * 0.06, n, 0.004, c);
        }
    }
    g
}

pub fn cloud_scene(n: usize) -> Gaussians {
    let mut rng = Rng(2);
    let mut g = Gaussians::default();
    while g.len() < n {
        let p = Vec3::new(rng.f(), rng.f(), rng.f()) * 2.0 - Vec3::ONE;
        if p.length() > 1.0 {
            continue;
        }
        g.means.push(p * 0.4);
        g.rotations.push(Quat::from_xyzw(
            rng.f() - 0.5,
            rng.f() - 0.5,
            rng.f() - 0.5,
            rng.f() - 0.5,
        ));
        // log-uniform in [1 mm, 15 mm]
        let mut ls = || ((1e-3f32).ln() + rng.f() * (15f32).ln()).exp();
        let s = Vec3::new(ls(), ls(), ls());
        g.scales.push(s);
        g.opacities.push(0.05 + 0.95 * rng.f());
        g.colors.push([rng.f(), rng.f(), rng.f()]);
    }
    g
}

pub fn camera() -> Camera {
    Camera::look_at(
        Vec3::new(0.9, -0.6, 0.5),
        Vec3::ZERO,
        Vec3::Z,
        50f32.to_radians(),
        640,
        480,
    )
    .expect("valid camera")
}

/// Both scenes with their names.
pub fn all() -> [(&'static str, Gaussians); 2] {
    [
        ("object_50k", object_scene(50_000)),
        ("cloud_50k", cloud_scene(50_000)),
    ]
}
