//! How far the faster options move a rollout: the spectral substep (`Substep::SPECTRAL`) and
//! split rollouts (`SimConfig::partitions`), against the model's converged solution (our
//! integrator at the reference's 2e-5 s substep) and next to the default's own distance from it
//! and the reference's integrator (explicit dashpot, 5000 × 2e-5 s per 0.1 s step).
//!
//! Run: `cargo run --release -p pgrd-springs --example split_accuracy`
//!
//! Scene (docs/physics.md): the benchmark's 1000-particle rope with the reference's fitted
//! values, one end lifted 30 cm over 1 s, then released and dropped for 0.5 s. Printed: the
//! mean distance over particles between two rollouts (mm) at 0.5 s, 1 s and 1.5 s.

use glam::Vec3;
use springs::{Actions, Backbone, Dashpot, SimConfig, SpringParams, State, Substep};

#[path = "../tests/common/mod.rs"]
mod common;

fn main() -> Result<(), springs::SimError> {
    let x = common::rope(1000, 1.0, 0.005, 0.006);
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.02 { 0 } else { -1 }).collect();
    let frames = 16;
    let pos = (0..frames)
        .map(|t| vec![Vec3::new(0.0, 0.0, 0.006 + 0.03 * (t.min(10)) as f32)])
        .collect();
    let closed = (0..frames).map(|t| vec![t < 10]).collect();
    let actions = Actions::new(pos, closed)?;
    let init = State::at_rest(x.clone());
    let run = |substep: Substep, dashpot: Dashpot, partitions: u32| {
        let cfg = SimConfig {
            substep,
            dashpot,
            partitions,
            ..SimConfig::default()
        };
        let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), cfg)?;
        let t0 = std::time::Instant::now();
        let out = bb.rollout(&init, &actions)?;
        eprintln!(
            "  {substep:?}, {dashpot:?}, {partitions} slab(s): {} substeps, {:.2} s",
            bb.substeps(),
            t0.elapsed().as_secs_f64()
        );
        Ok::<_, springs::SimError>(out)
    };
    // The model's converged solution (our integrator at the reference's substep, where the
    // dashpot sweeps are nearly exact) and the reference's own integrator.
    let converged = run(Substep::Fixed { dt: 2e-5 }, Dashpot::Implicit, 1)?;
    let reference = run(Substep::Fixed { dt: 2e-5 }, Dashpot::Explicit, 1)?;
    let fine = run(Substep::Fixed { dt: 1e-4 }, Dashpot::Implicit, 1)?;
    let auto = run(Substep::AUTO, Dashpot::Implicit, 1)?;
    let auto2 = run(Substep::AUTO, Dashpot::Implicit, 2)?;
    let spectral = run(Substep::SPECTRAL, Dashpot::Implicit, 1)?;
    let spectral2 = run(Substep::SPECTRAL, Dashpot::Implicit, 2)?;
    let mean_mm = |a: &springs::Rollout, b: &springs::Rollout, t: usize| {
        let s: f64 = a.positions[t]
            .iter()
            .zip(&b.positions[t])
            .map(|(p, q)| f64::from(p.distance(*q)))
            .sum();
        1e3 * s / a.positions[t].len() as f64
    };
    println!("mean distance (mm) at      0.5 s   1.0 s   1.5 s");
    for (name, a, b) in [
        ("converged vs reference", &converged, &reference),
        ("1e-4 s substep vs converged", &fine, &converged),
        ("default vs converged", &auto, &converged),
        ("2 slabs vs converged", &auto2, &converged),
        ("spectral vs converged", &spectral, &converged),
        ("spectral + 2 slabs vs converged", &spectral2, &converged),
        ("2 slabs vs default", &auto2, &auto),
        ("spectral vs default", &spectral, &auto),
    ] {
        println!(
            "{name:32} {:6.2}  {:6.2}  {:6.2}",
            mean_mm(a, b, 5),
            mean_mm(a, b, 10),
            mean_mm(a, b, 15)
        );
    }
    Ok(())
}
