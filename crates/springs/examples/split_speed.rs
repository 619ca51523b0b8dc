//! Wall time and whole-process CPU time of one 0.1 s step of the benchmark's 1000-particle rope,
//! unsplit and split into slabs (`SimConfig::partitions`), for both substep choices, with the
//! CPU time of the threads alive at the end (`/proc/self/task/*/schedstat`, Linux; a split
//! step's helper threads exit with the step, so for split runs this is the calling thread's).
//! Spinning helper threads need free cores: run it on an otherwise idle machine.
//!
//! Run: `RAYON_NUM_THREADS=2 cargo run --release -p pgrd-springs --example split_speed`

use std::time::{Duration, Instant};

use glam::Vec3;
use springs::{Actions, Backbone, SimConfig, SpringParams, State, Substep};

#[path = "../tests/common/mod.rs"]
mod common;

/// CPU time of every thread of this process so far (zero where unavailable).
fn process_cpu() -> Duration {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return Duration::ZERO;
    };
    let ns: u64 = dir
        .filter_map(|e| {
            let s = std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok()?;
            s.split_whitespace().next()?.parse::<u64>().ok()
        })
        .sum();
    Duration::from_nanos(ns)
}

fn main() -> Result<(), springs::SimError> {
    let x = common::rope(1000, 1.0, 0.005, 0.006);
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.02 { 0 } else { -1 }).collect();
    let frames: Vec<Vec<Vec3>> = (0..2)
        .map(|t| vec![Vec3::new(0.0, 0.0, 0.006 + 0.03 * t as f32)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 2])?;
    let (f0, f1) = (actions.frame(0).unwrap(), actions.frame(1).unwrap());
    let reps = 60;
    println!(
        "rayon threads: {}; {reps} steps each, best of 3 rounds",
        rayon::current_num_threads()
    );
    for (name, substep) in [("auto", Substep::AUTO), ("spectral", Substep::SPECTRAL)] {
        for partitions in [1, 2] {
            let cfg = SimConfig {
                substep,
                partitions,
                ..SimConfig::default()
            };
            let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), cfg)?;
            let mut sc = bb.scratch();
            let (mut wall, mut cpu) = (Duration::MAX, Duration::MAX);
            for _ in 0..3 {
                let (t0, c0) = (Instant::now(), process_cpu());
                for _ in 0..reps {
                    let mut st = State::at_rest(x.clone());
                    bb.step(&mut st, f0, f1, &mut sc)?;
                }
                wall = wall.min(t0.elapsed() / reps);
                cpu = cpu.min((process_cpu() - c0) / reps);
            }
            println!(
                "{name:9} {partitions} slab(s), {} substeps: wall {:6.2} ms, process CPU {:6.2} ms",
                bb.substeps(),
                wall.as_secs_f64() * 1e3,
                cpu.as_secs_f64() * 1e3
            );
        }
    }
    Ok(())
}
