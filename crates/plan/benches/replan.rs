//! One MPPI replanning step at the paper's cable-rerouting settings (15 samples, horizon 15,
//! 6 iterations: 1350 model steps) on the rerouting task's rope (150 observed points), with the
//! spring-mass backbone and with PGRD: the network `PGRD_RESIDUAL` names (a
//! `residual.safetensors`; an absolute path, since cargo runs benches in the crate's
//! directory), or an untrained one of the default architecture (same cost). MPPI
//! hands each iteration's candidates to `ForwardModel::rollout_members_batch`, which PGRD
//! evaluates through `residual::predict_batch`; when `PGRD_RESIDUAL` is an ensemble, PGRD with
//! each member on its own trajectory (`pgrd-members`) is measured too.
//! Run with `RAYON_NUM_THREADS=2` to match the 2-core budget of `docs/plan.md`. Besides the
//! wall time, it prints the process CPU time per replanning step (all threads, from
//! `/proc/self/stat` on Linux), which other jobs on a shared machine do not inflate, as mean
//! and minimum over `PLAN_BENCH_REPS` (default 3) replanning steps. The benchmark binary uses
//! mimalloc, as `cargo xtask` does.
#![allow(missing_docs)] // criterion_group! generates an undocumented pub fn

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use plan::{ForwardModel, ModelState, Mppi, Pgrd, SpringMass, Task, TaskConfig, TaskKind};

/// The allocator `cargo xtask` uses: glibc's malloc returns the network's freed buffers to the
/// system after every call and faults them back in on the next (`docs/plan-log.md`, "Planning
/// speed").
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn replan(c: &mut Criterion) {
    // `PLAN_BENCH_TRACKED` changes the number of observed points (= model particles).
    let tracked = std::env::var("PLAN_BENCH_TRACKED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(150);
    let cfg = TaskConfig {
        tracked,
        ..TaskConfig::new()
    };
    let task = Task::build(TaskKind::Reroute, &cfg).expect("rerouting task");
    let params = springs::SpringParams::reference_rope();
    let objective = task.objective().expect("objective");
    let state = ModelState::at_rest(task.start.observe());
    let grippers = [task.start.gripper()];
    let mut models: Vec<Box<dyn ForwardModel>> = vec![Box::new(SpringMass::new(
        task.backbone(params).expect("backbone"),
    ))];
    // A trained network when `PGRD_RESIDUAL` names one; otherwise an untrained network of the
    // default architecture, which costs the same per step.
    let net = match std::env::var("PGRD_RESIDUAL") {
        Ok(path) => residual::ResidualNet::load(std::path::Path::new(&path))
            .unwrap_or_else(|e| panic!("PGRD_RESIDUAL={path}: {e}")),
        Err(_) => residual::ResidualNet::new(&residual::ModelConfig::default(), 0).expect("net"),
    };
    let net = Arc::new(net);
    models.push(Box::new(Pgrd::new(
        task.backbone(params).expect("backbone"),
        net.clone(),
    )));
    // An ensemble is also planned with each member on its own trajectory.
    if net.ensemble_size() > 1 {
        models.push(Box::new(
            Pgrd::with_member_trajectories(task.backbone(params).expect("backbone"), net)
                .expect("members"),
        ));
    }
    for model in &models {
        cpu_time_per_replan(model.as_ref(), &state, &grippers, &objective);
    }
    let mut group = c.benchmark_group("replan_rerouting");
    group.sample_size(10);
    for model in &models {
        let mut mppi = Mppi::new(TaskKind::Reroute.mppi(), 1).expect("planner");
        group.bench_function(model.name(), |b| {
            b.iter(|| {
                black_box(
                    mppi.plan(model.as_ref(), &state, &grippers, &objective)
                        .expect("plan"),
                )
            })
        });
    }
    group.finish();
}

/// Process CPU time (user + system, all threads), s, or `None` off Linux.
fn process_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    // USER_HZ is 100 on every mainstream Linux configuration.
    Some(ticks / 100.0)
}

fn cpu_time_per_replan(
    model: &dyn ForwardModel,
    state: &ModelState,
    grippers: &[glam::Vec3],
    objective: &plan::Objective,
) {
    let mut mppi = Mppi::new(TaskKind::Reroute.mppi(), 1).expect("planner");
    // `PLAN_BENCH_REPS` replanning steps (default 3); the minimum is the least disturbed by
    // other jobs on a shared machine.
    let reps: usize = std::env::var("PLAN_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3)
        .max(1);
    let (mut cpu, mut wall) = (Vec::new(), Vec::new());
    for _ in 0..reps {
        let (Some(c0), t0) = (process_cpu_s(), std::time::Instant::now()) else {
            return;
        };
        black_box(mppi.plan(model, state, grippers, objective).expect("plan"));
        wall.push(t0.elapsed().as_secs_f64());
        let Some(c1) = process_cpu_s() else { return };
        cpu.push(c1 - c0);
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let min = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    println!(
        "replan_rerouting/{}: {:.3} s CPU time (all threads) and {:.3} s wall per replanning step, mean of {reps} (min {:.3} s CPU, {:.3} s wall)",
        model.name(),
        mean(&cpu),
        mean(&wall),
        min(&cpu),
        min(&wall),
    );
}

criterion_group!(benches, replan);
criterion_main!(benches);
