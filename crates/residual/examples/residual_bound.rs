//! How hard a trained network pushes against its bound along the evaluation rollouts.
//!
//! The residual is `Δv = s ((1 − g) r + g δ)` with `r, δ ∈ (−1, 1)` from tanh, so `|Δv|` per
//! axis is below the bound `s` (0.1 m/s in the paper). A network whose outputs sit at the bound
//! learns little more (tanh's gradient vanishes there) and applies nearly the same correction
//! whatever its inputs. This runs the run's model over the val episodes as `cargo xtask eval`
//! does, re-runs the backbone step from each hybrid state to recover `Δv = (x − x_sim) / dt`,
//! and prints the distribution of `|Δv| / s` per axis over the free particles, plus the mean
//! `Δv` (a constant push shows there).
//!
//! ```sh
//! cargo run --release -p pgrd-residual --example residual_bound -- <data-dir> <run-dir> [paper|deform] [episodes]
//! ```
//!
//! Only backbones without library effects (`backbone.json` without `effects`).

mod common;

use dataset::Split;
use glam::Vec3;
use residual::{History, ResidualNet, RolloutOptions, hybrid_rollout};
use scene::{Scene, SceneConfig};

fn main() -> Result<(), common::Error> {
    let common::Inputs {
        data,
        run,
        protocol,
        params,
        rest,
        ..
    } = common::inputs("usage: residual_bound <data-dir> <run-dir> [paper|deform] [episodes]")?;
    let max_episodes: usize = rest.first().map_or(Ok(usize::MAX), |s| s.parse())?;
    let net = ResidualNet::load(&run.join("residual.safetensors"))?;
    let bound = net.config().residual_scale;
    // Fractions of the bound: < 0.1, < 0.5, < 0.9, < 0.99, ≥ 0.99.
    let edges = [0.1f32, 0.5, 0.9, 0.99];
    let mut counts = [0u64; 5];
    let (mut sum, mut total) = (Vec3::ZERO, 0u64);
    for i in data
        .split_indices(Split::Val)
        .into_iter()
        .take(max_episodes)
    {
        let ep = data.load_episode(i)?;
        let window = protocol.window(ep.frames())?;
        let scene = Scene::new(&data.meta, &ep, window, &SceneConfig::default())?;
        let history = History::from_episode(&scene, &ep, data.meta.fps)?;
        let bb = scene.backbone(&params, &scene.sim_config(), Default::default())?;
        let out = hybrid_rollout(&net, &bb, &scene, &history, RolloutOptions::default())?;
        let dt = bb.config().step_dt;
        let held = bb.held();
        let mut scratch = bb.scratch();
        for k in 0..out.positions.len() {
            let mut state = if k == 0 {
                scene.init.clone()
            } else {
                springs::State {
                    x: out.positions[k - 1].clone(),
                    v: out.velocities[k - 1].clone(),
                }
            };
            let (Some(from), Some(to)) = (scene.actions.frame(k), scene.actions.frame(k + 1))
            else {
                break;
            };
            bb.step(&mut state, from, to, &mut scratch)?;
            for (p, (x, x_sim)) in out.positions[k].iter().zip(&state.x).enumerate() {
                let g = held[p];
                if g >= 0 && from.closed.get(g as usize).copied().unwrap_or(false) {
                    continue;
                }
                let dv = (*x - *x_sim) / dt;
                sum += dv;
                total += 1;
                for a in dv.to_array() {
                    let f = a.abs() / bound;
                    counts[edges.iter().position(|e| f < *e).unwrap_or(4)] += 1;
                }
            }
        }
    }
    let axes = (3 * total).max(1) as f64;
    println!(
        "{} free particle-steps; |Δv| per axis as a fraction of the bound {bound} m/s:",
        total
    );
    for (label, c) in ["< 0.1", "0.1–0.5", "0.5–0.9", "0.9–0.99", "≥ 0.99"]
        .iter()
        .zip(counts)
    {
        println!("  {label:>9}: {:5.1} %", 100.0 * c as f64 / axes);
    }
    let mean = sum / total.max(1) as f32;
    println!(
        "mean Δv (x, y, z): ({:+.4}, {:+.4}, {:+.4}) m/s",
        mean.x, mean.y, mean.z
    );
    Ok(())
}
