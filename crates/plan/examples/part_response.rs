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

use std::path::Path;
use std::sync::Arc;

use glam::Vec3;
use plan::{ForwardModel, ModelState, Pgrd, SpringMass, Task, TaskConfig, TaskKind, WorldOracle};

const GROUPS: usize = 5;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        return Err("usage: part_response <run-dir> <task> [fractions, comma-separated]".into());
    }
    let run = Path::new(&args[1]);
    let kind: TaskKind = args[2].parse()?;
    let fractions: Vec<f32> = args
        .get(3)
        .map_or("0.4,0.6", String::as_str)
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let backbone: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("backbone.json"))?)?;
    let params: springs::SpringParams = serde_json::from_value(backbone["params"].clone())?;
    let effects: Vec<gap::BaseEffect> = match backbone.get("effects") {
        Some(e) => serde_json::from_value(e.clone())?,
        None => Vec::new(),
    };
    let net = Arc::new(residual::ResidualNet::load(
        &run.join("residual.safetensors"),
    )?);
    let cfg = TaskConfig {
        tracked: 250,
        resolution: world::Resolution::Full,
        ..TaskConfig::new()
    };
    let task = Task::build(kind, &cfg)?;
    let objective = task.objective()?;
    let rest = task.start.observe();
    let centre = rest.iter().copied().sum::<Vec3>() / rest.len() as f32;
    let frame = gap::MaterialFrame::new(&rest, centre)?;
    let make = || task.backbone_with(params, gap::backbone_options(&effects, &frame));
    let h = kind.mppi().horizon;

    for &frac in &fractions {
        let mut w = task.start.clone();
        let g0 = w.gripper();
        let at = g0 + (task.target_gripper - g0) * frac;
        let n = ((at - g0).length() / 0.03).ceil().max(1.0) as usize;
        let mut frames = vec![w.observe()];
        for k in 1..=n {
            w.step(g0 + (at - g0) * (k as f32 / n as f32))?;
            frames.push(w.observe());
        }
        for _ in 0..3 {
            w.step(at)?;
            frames.push(w.observe());
        }
        let state = ModelState::from_frames(&frames[frames.len() - 4..], 0.1)?;
        let left = task.target_gripper - at;
        let step = left.normalize_or_zero() * (left.length() / h as f32).min(0.02);
        let path: Vec<Vec<Vec3>> = (0..=h).map(|k| vec![at + step * k as f32]).collect();
        let actions = springs::Actions::new(path, vec![vec![true]; h + 1])?;
        let models: [(&str, Box<dyn ForwardModel>); 3] = [
            ("world", Box::new(WorldOracle::new(w.clone()))),
            ("spring-mass", Box::new(SpringMass::new(make()?))),
            ("pgrd", Box::new(Pgrd::new(make()?, net.clone()))),
        ];
        let x0 = &state.x;
        let mut order: Vec<usize> = (0..x0.len()).collect();
        order.sort_by(|a, b| x0[*a].distance(at).total_cmp(&x0[*b].distance(at)));
        let finals = models
            .iter()
            .map(|(_, m)| Ok(m.rollout(&state, &actions)?.pop().unwrap_or_default()))
            .collect::<Result<Vec<_>, Box<dyn std::error::Error>>>()?;
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
