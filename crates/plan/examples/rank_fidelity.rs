//! How faithfully a run's models rank a planner's candidate paths, compared with the reference
//! world itself.
//!
//! MPPI only needs a model to *order* candidates correctly. This drives the world's rope along
//! the straight line from the task's start towards the gripper position of its target, stops at
//! a fraction of the way (and holds 0.3 s), samples 48 candidate gripper paths around a mean
//! that keeps heading to the target (MPPI's noise: covariance 0.1 of the normalised action,
//! piecewise constant over three parts of the horizon), and scores every candidate with the
//! task's running Chamfer cost as predicted by spring-mass, by PGRD and by the world. It prints,
//! per fraction, the Spearman rank correlation of each model's costs with the world's and the
//! regret (the world's cost of the model's best candidate minus the world's best), cm, averaged
//! over five candidate draws. For PGRD it also prints how the network's correction of the
//! backbone's costs (PGRD's cost minus spring-mass's, per candidate) compares with the correction
//! the world would need (the world's cost minus spring-mass's): their Pearson correlation over the
//! candidates and the two mean corrections, cm.
//!
//! ```sh
//! cargo run --release -p pgrd-plan --example rank_fidelity -- <run-dir> rope-rotate [0.4,0.6,0.8,1.0]
//! ```
//!
//! `<run-dir>` holds `backbone.json` (from `cargo xtask fit`) and `residual.safetensors` (from
//! `cargo xtask train`); a backbone that carries library effects (`diagnose --write-run`) gets
//! them. World rope at full resolution with 250 observed points, as in
//! `docs/RESULTS.md`.

mod support;

use glam::Vec3;
use plan::{ForwardModel, WorldOracle};
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

const CANDIDATES: usize = 48;
const DRAWS: u64 = 5;

fn main() -> Result<(), support::Error> {
    let (setup, fractions) = support::Setup::from_args("rank_fidelity", "0.4,0.6,0.8,1.0")?;
    let (kind, task) = (setup.kind, &setup.task);
    let objective = task.objective()?;
    let mppi = kind.mppi();
    let h = mppi.horizon;
    let segment = h.div_ceil(mppi.noise_segments.max(1));
    let noise = Normal::new(0.0f32, mppi.noise.sqrt() * mppi.max_step_m)?;
    println!(
        "{kind}: fraction of the way, Chamfer now, then spring-mass / PGRD: Spearman, regret (cm); \
         the network's cost correction vs the needed one: correlation, means (cm)"
    );
    for &frac in &fractions {
        let (w, state, at) = setup.part_way(frac)?;
        let models: [(&str, Box<dyn ForwardModel>); 2] = [
            ("spring-mass", Box::new(setup.spring_mass()?)),
            ("pgrd", Box::new(setup.pgrd()?)),
        ];
        let oracle = WorldOracle::new(w.clone());
        let mean = setup.mean_step(at);
        let mut sums = [[0.0f64; 2]; 2];
        // Network's correction vs the needed one: correlation, mean of each (cm).
        let mut correction = [0.0f64; 3];
        for draw in 0..DRAWS {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(draw);
            let mut paths = Vec::with_capacity(CANDIDATES);
            for _ in 0..CANDIDATES {
                let mut g = at;
                let mut d = Vec3::ZERO;
                let mut path = vec![vec![g]];
                for s in 0..h {
                    if s % segment == 0 {
                        let mut r = || noise.sample(&mut rng);
                        d = mean + Vec3::new(r(), r(), r());
                    }
                    g += d;
                    g.z = g.z.max(task.workspace.min.z);
                    path.push(vec![g]);
                }
                paths.push(path);
            }
            let costs = |m: &dyn ForwardModel| -> Result<Vec<f64>, support::Error> {
                paths
                    .iter()
                    .map(|p| {
                        let actions = springs::Actions::new(p.clone(), vec![vec![true]; h + 1])?;
                        let predicted = m.rollout(&state, &actions)?;
                        Ok(objective.cost(&predicted, &p[1..])?)
                    })
                    .collect()
            };
            let f32s = |v: &[f64]| v.iter().map(|x| *x as f32).collect::<Vec<f32>>();
            let truth = costs(&oracle)?;
            let truth_f32 = f32s(&truth);
            let best_true = truth.iter().copied().fold(f64::INFINITY, f64::min);
            let mut predicted = Vec::with_capacity(models.len());
            for (k, (_, m)) in models.iter().enumerate() {
                let c = costs(m.as_ref())?;
                predicted.push(c.clone());
                let chosen = (0..c.len())
                    .min_by(|a, b| c[*a].total_cmp(&c[*b]))
                    .unwrap_or(0);
                sums[k][0] += gap::spearman(&f32s(&c), &truth_f32);
                sums[k][1] += 100.0 * (truth[chosen] - best_true);
            }
            let net: Vec<f64> = (0..truth.len())
                .map(|i| predicted[1][i] - predicted[0][i])
                .collect();
            let needed: Vec<f64> = (0..truth.len())
                .map(|i| truth[i] - predicted[0][i])
                .collect();
            correction[0] += pearson(&net, &needed);
            correction[1] += 100.0 * average(&net);
            correction[2] += 100.0 * average(&needed);
        }
        let now = 100.0 * objective.chamfer(&w.observe())?;
        let d = DRAWS as f64;
        let mut line = format!("{frac:4.2}  {now:5.2} cm");
        for ((name, _), [rho, regret]) in models.iter().zip(sums) {
            line += &format!("  {name} {:.2}, {:.2}", rho / d, regret / d);
        }
        line += &format!(
            "  correction r {:.2}, mean {:+.2} (needed {:+.2})",
            correction[0] / d,
            correction[1] / d,
            correction[2] / d
        );
        println!("{line}");
    }
    Ok(())
}

fn average(a: &[f64]) -> f64 {
    a.iter().sum::<f64>() / a.len().max(1) as f64
}

/// Pearson correlation of `a` and `b` (0 when either is constant).
fn pearson(a: &[f64], b: &[f64]) -> f64 {
    let (ma, mb) = (average(a), average(b));
    let (mut ab, mut aa, mut bb) = (0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        ab += (x - ma) * (y - mb);
        aa += (x - ma) * (x - ma);
        bb += (y - mb) * (y - mb);
    }
    if aa > 0.0 && bb > 0.0 {
        ab / (aa * bb).sqrt()
    } else {
        0.0
    }
}
