//! Renderer and rig benchmarks.
//!
//! `cargo bench -p pgrd-gsplat-cpu --bench render`; set `RAYON_NUM_THREADS` to compare thread
//! counts. Besides wall time, the `*_cpu` groups report the CPU time the process spent per
//! frame (all threads, from `/proc/self/task/*/schedstat`; Linux only, wall time elsewhere):
//! on a machine shared with other jobs, wall time also measures the others. Scenes: see
//! `scenes/mod.rs`.

// criterion_group! generates an undocumented public function.
#![allow(missing_docs)]

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use glam::{Quat, Vec3};
use gsplat::{GaussianRig, RigOptions, render};

mod scenes;

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
    let cam = scenes::camera();
    let threads = rayon::current_num_threads();
    let scenes = scenes::all();
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
