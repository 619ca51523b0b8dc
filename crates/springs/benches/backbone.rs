//! Backbone timings: substep and model step on a 1000-particle lattice, a model step of a
//! 1000-particle rope (automatic vs the reference's fixed substep), batched rollouts, and the
//! interior fill of a sampled surface.
//! Run: `cargo bench -p pgrd-springs` (set RAYON_NUM_THREADS to compare thread counts).
#![allow(missing_docs)] // criterion_group! generates an undocumented pub fn

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use glam::Vec3;
use springs::{
    ActionFrame, Actions, Backbone, Dashpot, RolloutJob, SimConfig, SpringParams, State, Substep,
    rollout_batch,
};

#[path = "../tests/common/mod.rs"]
mod common;

/// 10 x 10 x 10 lattice, 1 cm spacing, 1 cm above the ground; threshold 1.75 cm takes face,
/// edge and body diagonals: 10,476 springs.
fn lattice_backbone(config: SimConfig) -> (Backbone, State) {
    let x = common::lattice(10, 10, 10, 0.01, Vec3::new(0.0, 0.0, 0.01));
    let params = SpringParams {
        threshold: 0.0175,
        ..SpringParams::reference_rope()
    };
    let bb = Backbone::new(&x, &[], params, config).expect("lattice backbone");
    (bb, State::at_rest(x))
}

/// 1000-particle rope, 1 m long, 5 mm radius, lying on the ground, first 2 cm held by gripper 0.
fn rope_backbone(config: SimConfig) -> (Backbone, State) {
    let x = common::rope(1000, 1.0, 0.005, 0.006);
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.02 { 0 } else { -1 }).collect();
    let bb =
        Backbone::new(&x, &held, SpringParams::reference_rope(), config).expect("rope backbone");
    (bb, State::at_rest(x))
}

/// On-CPU time of the calling thread (Linux `/proc/thread-self/schedstat`, ns), so timings are
/// not inflated when other processes share the machine; falls back to wall time elsewhere.
fn cpu_now() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    Some(Duration::from_nanos(
        s.split_whitespace().next()?.parse().ok()?,
    ))
}

/// Time `iters` runs of `f` in thread CPU time (wall time if unavailable), divided by `per`.
fn cpu_iters(iters: u64, per: u32, mut f: impl FnMut()) -> Duration {
    let (c0, t0) = (cpu_now(), Instant::now());
    for _ in 0..iters {
        f();
    }
    match (c0, cpu_now()) {
        (Some(a), Some(b)) => (b - a) / per,
        _ => t0.elapsed() / per,
    }
}

fn lift_actions(frames: usize) -> Actions {
    let pos = (0..frames)
        .map(|t| vec![Vec3::new(0.0, 0.0, 0.006 + 0.03 * t as f32)])
        .collect();
    Actions::new(pos, vec![vec![true]; frames]).expect("actions")
}

fn bench(c: &mut Criterion) {
    let (auto_bb, _) = lattice_backbone(SimConfig::default());
    let dt = auto_bb.substep_dt();
    eprintln!(
        "lattice: {} springs, auto substep {:.3e} s ({} per 0.1 s)",
        auto_bb.springs().len(),
        dt,
        auto_bb.substeps()
    );
    // One model step of exactly 10 automatic-size substeps; report time per substep.
    let cfg10 = SimConfig {
        step_dt: 10.0 * dt,
        substep: Substep::Fixed { dt },
        ..SimConfig::default()
    };
    let (bb10, state0) = lattice_backbone(cfg10);
    let none = ActionFrame {
        positions: &[],
        closed: &[],
    };
    c.bench_function("lattice_1000p_10.5k_springs/substep", |b| {
        let mut sc = bb10.scratch();
        let mut st = state0.clone();
        b.iter_custom(|iters| {
            let t0 = Instant::now();
            for _ in 0..iters {
                bb10.step(&mut st, none, none, &mut sc).expect("step");
            }
            t0.elapsed() / 10
        })
    });
    // The same in thread CPU time; each iteration is 10 model steps (100 substeps) because the
    // kernel updates a thread's CPU time only every scheduler tick.
    c.bench_function("lattice_1000p_10.5k_springs/substep_cpu_time", |b| {
        let mut sc = bb10.scratch();
        let mut st = state0.clone();
        b.iter_custom(|iters| {
            cpu_iters(iters, 100, || {
                for _ in 0..10 {
                    bb10.step(&mut st, none, none, &mut sc).expect("step");
                }
            })
        })
    });
    let (auto_ex, _) = lattice_backbone(SimConfig {
        dashpot: Dashpot::Explicit,
        ..SimConfig::default()
    });
    eprintln!(
        "lattice, explicit dashpot: auto substep {:.3e} s ({} per 0.1 s)",
        auto_ex.substep_dt(),
        auto_ex.substeps()
    );
    // The reference's scheme (explicit dashpot, the same single pass over the springs that
    // Warp's CPU backend runs per substep) at the reference's 2e-5 s substep.
    let (bb_ex, _) = lattice_backbone(SimConfig {
        step_dt: 10.0 * 2e-5,
        substep: Substep::Fixed { dt: 2e-5 },
        dashpot: Dashpot::Explicit,
        ..SimConfig::default()
    });
    c.bench_function(
        "lattice_1000p_10.5k_springs/substep_explicit_dashpot",
        |b| {
            let mut sc = bb_ex.scratch();
            let mut st = state0.clone();
            b.iter_custom(|iters| {
                let t0 = Instant::now();
                for _ in 0..iters {
                    bb_ex.step(&mut st, none, none, &mut sc).expect("step");
                }
                t0.elapsed() / 10
            })
        },
    );
    c.bench_function(
        "lattice_1000p_10.5k_springs/substep_explicit_dashpot_cpu_time",
        |b| {
            let mut sc = bb_ex.scratch();
            let mut st = state0.clone();
            b.iter_custom(|iters| {
                cpu_iters(iters, 100, || {
                    for _ in 0..10 {
                        bb_ex.step(&mut st, none, none, &mut sc).expect("step");
                    }
                })
            })
        },
    );
    c.bench_function("lattice_1000p_10.5k_springs/step_0.1s_auto", |b| {
        let mut sc = auto_bb.scratch();
        let mut st = state0.clone();
        b.iter(|| {
            auto_bb
                .step(black_box(&mut st), none, none, &mut sc)
                .expect("step")
        })
    });

    let (rope, rope0) = rope_backbone(SimConfig::default());
    eprintln!(
        "rope: {} springs ({:.1} per particle), auto substep {:.3e} s ({} per 0.1 s)",
        rope.springs().len(),
        2.0 * rope.springs().len() as f64 / rope.num_particles() as f64,
        rope.substep_dt(),
        rope.substeps()
    );
    let acts = lift_actions(2);
    let (f0, f1) = (acts.frame(0).expect("frame"), acts.frame(1).expect("frame"));
    c.bench_function("rope_1000p/step_0.1s_auto", |b| {
        let mut sc = rope.scratch();
        b.iter_batched_ref(
            || rope0.clone(),
            |st| rope.step(st, f0, f1, &mut sc).expect("step"),
            criterion::BatchSize::SmallInput,
        )
    });
    c.bench_function("rope_1000p/step_0.1s_auto_cpu_time", |b| {
        let mut sc = rope.scratch();
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let mut st = rope0.clone();
                total += cpu_iters(1, 1, || rope.step(&mut st, f0, f1, &mut sc).expect("step"));
            }
            total
        })
    });
    // Training through the backbone: the taped step, and the adjoint carried back through it.
    c.bench_function("rope_1000p/step_taped", |b| {
        let mut sc = rope.scratch();
        let mut tape = springs::StepTape::new();
        b.iter_batched_ref(
            || rope0.clone(),
            |st| {
                rope.step_taped(st, f0, f1, &mut sc, &mut tape)
                    .expect("step")
            },
            criterion::BatchSize::SmallInput,
        )
    });
    c.bench_function("rope_1000p/step_adjoint", |b| {
        let (mut sc, mut tape) = (rope.scratch(), springs::StepTape::new());
        let mut st = rope0.clone();
        rope.step_taped(&mut st, f0, f1, &mut sc, &mut tape)
            .expect("step");
        let adjoint = rope.step_adjoint();
        let n = rope.num_particles();
        b.iter_batched_ref(
            || (vec![Vec3::ONE; n], vec![Vec3::ONE; n]),
            |(gx, gv)| adjoint.vjp(&tape, gx, gv).expect("vjp"),
            criterion::BatchSize::SmallInput,
        )
    });
    // The same step with the spectral substep (Lanczos estimate instead of Gershgorin's bound).
    let (rope_sp, _) = rope_backbone(SimConfig {
        substep: Substep::SPECTRAL,
        ..SimConfig::default()
    });
    eprintln!(
        "rope, spectral substep: {:.3e} s ({} per 0.1 s)",
        rope_sp.substep_dt(),
        rope_sp.substeps()
    );
    c.bench_function("rope_1000p/step_0.1s_spectral", |b| {
        let mut sc = rope_sp.scratch();
        b.iter_batched_ref(
            || rope0.clone(),
            |st| rope_sp.step(st, f0, f1, &mut sc).expect("step"),
            criterion::BatchSize::SmallInput,
        )
    });
    c.bench_function("rope_1000p/step_0.1s_spectral_cpu_time", |b| {
        let mut sc = rope_sp.scratch();
        b.iter_custom(|iters| {
            let mut total = Duration::ZERO;
            for _ in 0..iters {
                let mut st = rope0.clone();
                total += cpu_iters(1, 1, || {
                    rope_sp.step(&mut st, f0, f1, &mut sc).expect("step")
                });
            }
            total
        })
    });
    // One rollout split into 2 slabs (`SimConfig::partitions`): both cores work on one step.
    // Wall time only (thread CPU time would count one of the two threads).
    for (name, substep) in [("auto", Substep::AUTO), ("spectral", Substep::SPECTRAL)] {
        let (bb, _) = rope_backbone(SimConfig {
            substep,
            partitions: 2,
            ..SimConfig::default()
        });
        c.bench_function(
            &format!(
                "rope_1000p/step_0.1s_{name}_2_slabs_threads_{}",
                rayon::current_num_threads()
            ),
            |b| {
                let mut sc = bb.scratch();
                b.iter_batched_ref(
                    || rope0.clone(),
                    |st| bb.step(st, f0, f1, &mut sc).expect("step"),
                    criterion::BatchSize::SmallInput,
                )
            },
        );
    }
    c.bench_function("rope_1000p/build_spectral", |b| {
        let x = common::rope(1000, 1.0, 0.005, 0.006);
        b.iter(|| {
            Backbone::new(
                &x,
                &[],
                SpringParams::reference_rope(),
                SimConfig {
                    substep: Substep::SPECTRAL,
                    ..SimConfig::default()
                },
            )
            .expect("rope")
        })
    });
    c.bench_function("rope_1000p/build_auto", |b| {
        let x = common::rope(1000, 1.0, 0.005, 0.006);
        b.iter(|| {
            Backbone::new(
                &x,
                &[],
                SpringParams::reference_rope(),
                SimConfig::default(),
            )
            .expect("rope")
        })
    });
    let (rope_ref, _) = rope_backbone(SimConfig {
        substep: Substep::Fixed { dt: 2e-5 },
        ..SimConfig::default()
    });
    let mut g = c.benchmark_group("rope_1000p_reference_substep");
    g.sample_size(10).measurement_time(Duration::from_secs(10));
    g.bench_function("step_0.1s_fixed_5000x2e-5", |b| {
        let mut sc = rope_ref.scratch();
        b.iter_batched_ref(
            || rope0.clone(),
            |st| rope_ref.step(st, f0, f1, &mut sc).expect("step"),
            criterion::BatchSize::SmallInput,
        )
    });
    g.finish();

    // 8 rope rollouts of 5 model steps each (one CMA-ES population member's worth of samples).
    let acts5 = lift_actions(6);
    let jobs: Vec<RolloutJob<'_>> = (0..8)
        .map(|_| RolloutJob {
            backbone: &rope,
            init: &rope0,
            actions: &acts5,
        })
        .collect();
    let mut g = c.benchmark_group("rope_1000p_rollout_batch");
    g.sample_size(10);
    g.bench_function(
        format!("8x5_steps_threads_{}", rayon::current_num_threads()),
        |b| b.iter(|| rollout_batch(black_box(&jobs))),
    );
    g.finish();
}

/// Interior fill of a 0.1 m-radius sphere sampled at 300 surface points (≈ 2 cm apart, the
/// density of a tracked plush toy), at a 2 cm grid.
fn bench_fill(c: &mut Criterion) {
    let n = 300;
    let surface: Vec<Vec3> = (0..n)
        .map(|i| {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let rho = (1.0 - z * z).sqrt();
            let phi = i as f32 * 2.399_963;
            0.1 * Vec3::new(rho * phi.cos(), rho * phi.sin(), z)
        })
        .collect();
    let name = format!(
        "fill_interior/sphere_300_surface_points_threads_{}",
        rayon::current_num_threads()
    );
    c.bench_function(&name, |b| {
        b.iter(|| springs::fill_interior(black_box(&surface), 0.02).expect("fill"))
    });
}

criterion_group!(benches, bench, bench_fill);
criterion_main!(benches);
