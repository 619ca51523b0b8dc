//! How far each part of the rope moves, from the gripper to the far end, in the reference world
//! and as spring-mass and PGRD predict it.
//!
//! `rank_fidelity` says *whether* a model orders a planner's candidates as the world does; this
//! says *where on the object* its prediction departs from the world's. It drives the world's
//! rope straight towards the task target's gripper position, stops at a fraction of the way
//! (and holds 0.3 s), as `rank_fidelity` does, then moves the gripper along the candidates'
//! mean path (straight on towards the target, at most 2 cm per step) for one planning horizon.
//! The observed points are split by their distance from the gripper into five equal groups;
//! per group it prints the mean displacement over the horizon (x, y, z, cm) in the world and
//! in each model's prediction, and each prediction's Chamfer distance to the target.
//!
//! ```sh
//! cargo run --release -p pgrd-plan --example part_response -- <run-dir> rope-rotate [0.4,0.6]
//! ```
//!
//! `<run-dir>` as for `rank_fidelity` (`backbone.json`, `residual.safetensors`).

mod support;

use glam::Vec3;
use plan::{ForwardModel, WorldOracle};

const GROUPS: usize = 5;

fn main() -> Result<(), support::Error> {
    let (setup, fractions) = support::Setup::from_args("part_response", "0.4,0.6")?;
    let kind = setup.kind;
    let objective = setup.task.objective()?;
    let h = kind.mppi().horizon;
    for &frac in &fractions {
        let (w, state, at) = setup.part_way(frac)?;
        let step = setup.mean_step(at);
        let path: Vec<Vec<Vec3>> = (0..=h).map(|k| vec![at + step * k as f32]).collect();
        let actions = springs::Actions::new(path, vec![vec![true]; h + 1])?;
        let models: [(&str, Box<dyn ForwardModel>); 3] = [
            ("world", Box::new(WorldOracle::new(w))),
            ("spring-mass", Box::new(setup.spring_mass()?)),
            ("pgrd", Box::new(setup.pgrd()?)),
        ];
        let x0 = &state.x;
        let mut order: Vec<usize> = (0..x0.len()).collect();
        order.sort_by(|a, b| x0[*a].distance(at).total_cmp(&x0[*b].distance(at)));
        let finals = models
            .iter()
            .map(|(_, m)| Ok(m.rollout(&state, &actions)?.pop().unwrap_or_default()))
            .collect::<Result<Vec<_>, support::Error>>()?;
        println!(
            "{kind} at {frac:.2} of the way: gripper moves ({:.1}, {:.1}, {:.1}) cm over {h} steps",
            100.0 * step.x * h as f32,
            100.0 * step.y * h as f32,
            100.0 * step.z * h as f32
        );
        for group in order.chunks(order.len().div_ceil(GROUPS)) {
            let mut line = format!(
                "  {:3.0}-{:3.0} cm from the gripper:",
                100.0 * x0[group[0]].distance(at),
                100.0 * x0[group[group.len() - 1]].distance(at)
            );
            for ((name, _), last) in models.iter().zip(&finals) {
                let d = group
                    .iter()
                    .map(|&i| last.get(i).copied().unwrap_or(x0[i]) - x0[i])
                    .sum::<Vec3>()
                    * (100.0 / group.len() as f32);
                line += &format!("  {name} ({:5.1}, {:5.1}, {:5.1})", d.x, d.y, d.z);
            }
            println!("{line}");
        }
        let mut line = "  Chamfer to the target after the horizon, cm:".to_string();
        for ((name, _), last) in models.iter().zip(&finals) {
            line += &format!("  {name} {:.2}", 100.0 * objective.chamfer(last)?);
        }
        println!("{line}");
    }
    Ok(())
}
