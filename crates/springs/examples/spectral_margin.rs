//! How much deformation raises the springs' largest eigenvalue above its rest value, which is
//! what `Substep::Spectral` estimates: the margin its `safety` factor must cover.
//!
//! Run: `cargo run --release -p pgrd-springs --example spectral_margin`
//!
//! Scenes: the benchmark's 1000-particle rope lifted by one end at 0.3 m/s, then swung; the
//! benchmark's lattice dropped from 5 cm; random blobs in the reference and "paper" CMA-ES
//! boxes grasped and dragged at up to 1 m/s per axis. For every state of every rollout (spectral
//! substep), it prints the largest ratio of the stiffness the bound covers at `x_t` (springs'
//! eigenvalue at `x_t` plus the ground's and effects' share) to the value the substep was
//! chosen for (springs at rest plus the same share).

use glam::Vec3;
use springs::{
    Actions, Backbone, PAPER_BOUNDS, REFERENCE_BOUNDS, SimConfig, SpringParams, State, Substep,
};

#[path = "../tests/common/mod.rs"]
mod common;

fn worst_ratio(bb: &Backbone, init: &State, actions: &Actions) -> Result<f64, springs::SimError> {
    // The bound's total stiffness per unit mass (springs + ground + effects) and its springs'
    // part; the ratio reported is the total at x_t over the total the substep was chosen for.
    let total = 4.0 / f64::from(bb.stable_dt()).powi(2);
    let rest = bb.stiffness_eigenvalue(bb.rest_positions())?;
    let out = bb.rollout(init, actions)?;
    let mut worst = 1.0f64;
    for x in &out.positions {
        worst = worst.max((bb.stiffness_eigenvalue(x)? - rest + total) / total);
    }
    Ok(worst)
}

fn main() -> Result<(), springs::SimError> {
    let cfg = SimConfig {
        substep: Substep::SPECTRAL,
        ..SimConfig::default()
    };

    let x = common::rope(1000, 1.0, 0.005, 0.006);
    let held: Vec<i32> = x.iter().map(|p| if p.x < 0.02 { 0 } else { -1 }).collect();
    let rope = Backbone::new(&x, &held, SpringParams::reference_rope(), cfg)?;
    let auto = Backbone::new(
        &x,
        &held,
        SpringParams::reference_rope(),
        SimConfig::default(),
    )?;
    let frames: Vec<Vec<Vec3>> = (0..31)
        .map(|t| {
            let t = t as f32;
            let lift = (0.03 * t).min(0.6);
            let swing = if t > 20.0 { 0.05 * (t - 20.0) } else { 0.0 };
            vec![Vec3::new(swing, 0.0, 0.006 + lift)]
        })
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 31])?;
    println!(
        "rope 1000 p: substeps {} (Gershgorin: {}), worst eigenvalue / rest over 30 steps: {:.3}",
        rope.substeps(),
        auto.substeps(),
        worst_ratio(&rope, &State::at_rest(x.clone()), &actions)?
    );

    let x = common::lattice(10, 10, 10, 0.01, Vec3::new(0.0, 0.0, 0.05));
    let params = SpringParams {
        threshold: 0.0175,
        ..SpringParams::reference_rope()
    };
    let lattice = Backbone::new(&x, &[], params, cfg)?;
    let auto = Backbone::new(&x, &[], params, SimConfig::default())?;
    println!(
        "lattice 1000 p dropped: substeps {} (Gershgorin: {}), worst ratio over 10 steps: {:.3}",
        lattice.substeps(),
        auto.substeps(),
        worst_ratio(
            &lattice,
            &State::at_rest(x.clone()),
            &Actions::without_grippers(11)
        )?
    );

    let mut rng = common::Rng::new(11);
    for (name, bounds) in [("reference", REFERENCE_BOUNDS), ("paper", PAPER_BOUNDS)] {
        let (mut worst, mut failed, mut ratio_sub) = (1.0f64, 0, 0.0f64);
        let trials = 400;
        for _ in 0..trials {
            let u: [f64; 5] = std::array::from_fn(|_| f64::from(rng.unit()));
            let params = bounds.denormalize(u);
            let n = 10 + (rng.unit() * 80.0) as usize;
            let x0 = common::blob(&mut rng, n, 0.03, Vec3::new(0.0, 0.0, 0.035));
            let grip = x0[0];
            let held: Vec<i32> = x0
                .iter()
                .map(|p| if p.distance(grip) < 0.015 { 0 } else { -1 })
                .collect();
            let vel = rng.vec3(1.0);
            let pos = (0..11)
                .map(|t| vec![grip + vel * (0.1 * t as f32)])
                .collect();
            let closed = (0..11).map(|t| vec![t < 6]).collect();
            let actions = Actions::new(pos, closed)?;
            let bb = Backbone::new(&x0, &held, params, cfg)?;
            let gersh = Backbone::new(&x0, &held, params, SimConfig::default())?;
            ratio_sub += f64::from(gersh.substeps()) / f64::from(bb.substeps());
            match worst_ratio(&bb, &State::at_rest(x0.clone()), &actions) {
                Ok(r) => worst = worst.max(r),
                Err(_) => failed += 1,
            }
        }
        println!(
            "{trials} random blobs in the {name} box: diverged {failed}, worst ratio {worst:.3}, \
             mean substep reduction {:.2}x",
            ratio_sub / f64::from(trials)
        );
    }
    Ok(())
}
