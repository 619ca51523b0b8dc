//! Renderer and rig benchmarks.
//!
//! `cargo bench -p pgrd-gsplat-cpu --bench render`; set `RAYON_NUM_THREADS` to compare thread
//! counts. Besides wall time, the `*_cpu` groups report the CPU time the process spent per
//! frame (all threads, from `/proc/self/task/*/schedstat`; Linux only, wall time elsewhere):
//! on a machine shared with other jobs, wall time also measures the others. Scenes (seeded, 640 x 480, 50° vertical field of view, camera 1.2 m away):
//! - `object`: 50 000 flat, mostly opaque Gaussians tiling the surfaces of a sphere (r 25 cm)
//!   and a torus around it (R 35 cm, r 6 cm), ~5 mm apart: what a fitted 3DGS object looks like.
//! - `cloud`: 50 000 Gaussians filling a 40 cm ball, random orientations, log-uniform std
//!   1-15 mm, opacities uniform in 0.05-1: semi-transparent volume, a harder case.

// criterion_group! generates an undocumented public function.
#![allow(missing_docs)]

use std::f32::consts::TAU;
use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use glam::{Quat, Vec3};
use gsplat::{Camera, GaussianRig, Gaussians, RigOptions, render};

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

fn object_scene(n: usize) -> Gaussians {
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

fn cloud_scene(n: usize) -> Gaussians {
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

fn camera() -> Camera {
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

/// CPU time of every thread of this process so far, or `None` off Linux.
fn process_cpu() -> Option<Duration> {
    let mut ns = 0u64;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let stat = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        ns += stat.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(Duration::from_nanos(ns))
}

fn bench_render(c: &mut Criterion) {
    let cam = camera();
    let threads = rayon::current_num_threads();
    let scenes = [
        ("object_50k", object_scene(50_000)),
        ("cloud_50k", cloud_scene(50_000)),
    ];
    let mut group = c.benchmark_group(format!("render_640x480_{threads}threads"));
    group.sample_size(30);
    for (name, scene) in &scenes {
        group.bench_function(*name, |b| {
            b.iter(|| render(black_box(scene), &cam, [1.0; 3]).expect("renders"))
        });
    }
    group.finish();
    let mut group = c.benchmark_group(format!("render_640x480_{threads}threads_cpu"));
    group.sample_size(30);
    for (name, scene) in &scenes {
        group.bench_function(*name, |b| {
            b.iter_custom(|iters| {
                let (cpu0, wall0) = (process_cpu(), Instant::now());
                for _ in 0..iters {
                    black_box(render(black_box(scene), &cam, [1.0; 3]).expect("renders"));
                }
                match (cpu0, process_cpu()) {
                    (Some(a), Some(b)) => b.saturating_sub(a),
                    _ => wall0.elapsed(),
                }
            })
        });
    }
    group.finish();
}

fn bench_rig(c: &mut Criterion) {
    // A 40 x 25 cloth of 1000 particles 1 cm apart, one deformation step (a fold).
    let pts: Vec<Vec3> = (0..1000)
        .map(|k| Vec3::new((k % 40) as f32, (k / 40) as f32, 0.0) * 0.01)
        .collect();
    let colors = vec![[0.8, 0.2, 0.2]; pts.len()];
    let rig = GaussianRig::from_particles(&pts, &colors, &RigOptions::default()).expect("rig");
    let folded: Vec<Vec3> = pts
        .iter()
        .map(|p| Quat::from_rotation_y(-0.8 * p.x) * *p)
        .collect();
    let threads = rayon::current_num_threads();
    c.bench_function(&format!("rig_deform_1000_{threads}threads"), |b| {
        b.iter(|| {
            let mut r = rig.clone();
            r.deform(black_box(&folded)).expect("deforms").len()
        })
    });
}

criterion_group!(benches, bench_render, bench_rig);
criterion_main!(benches);
