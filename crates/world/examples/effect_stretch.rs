//! How far one scaled effect moves neighbouring tracked points apart, on data made the way
//! `cargo xtask diagnose-bench` makes its cases (fixture resolution, 12 training episodes of
//! one recording each, 60 tracked points, default observation), with the world's links swept
//! once per substep (as every dataset is made) and more often ([`world::GenConfig::link_sweeps`]).
//!
//! ```sh
//! cargo run --release -p pgrd-world --example effect_stretch -- paper mass-distribution 16 37 1,16
//! ```
//!
//! For the pairs of tracked points whose median distance in the no-effect data is under 4 cm,
//! the statistic is the mean (and 90th percentile) of |distance / that median − 1| over every
//! frame where both are seen. Folding and noise give it a floor; its excess over the same
//! seed's no-effect data is what the effect adds. Where the excess with one sweep is much larger
//! than with many, the single-sweep solve, not the effect, stretches the object
//! (`docs/world.md`, "Solver").

use std::collections::HashMap;

use anyhow::{Context, bail};
use dataset::Episode;
use world::{EffectKind, Effects, GenConfig, ObjectKind};

/// The observed training episodes (tracked positions and visibility).
fn generate(
    object: ObjectKind,
    effects: Effects,
    seed: u64,
    sweeps: usize,
) -> anyhow::Result<Vec<Episode>> {
    let mut cfg = GenConfig::fixture(object);
    cfg.train_episodes = 12;
    cfg.val_episodes = 0;
    cfg.episodes_per_recording = 1;
    cfg.tracked = 60;
    cfg.seed = seed;
    cfg.effects = effects;
    cfg.gaussian_particles = 0;
    cfg.link_sweeps = sweeps;
    let data = world::generate(&cfg)?;
    Ok(data.episodes.into_iter().map(|(e, _)| e).collect())
}

/// Median distance of every pair seen together in at least 10 sampled frames (every 4th).
fn reference(data: &[Episode]) -> HashMap<(usize, usize), f32> {
    let mut dists: HashMap<(usize, usize), Vec<f32>> = HashMap::new();
    for ep in data {
        let n = ep.particles();
        for t in (0..ep.frames()).step_by(4) {
            let x = ep.frame(t);
            for i in 0..n {
                for j in i + 1..n {
                    if ep.visible(t, i) && ep.visible(t, j) {
                        dists.entry((i, j)).or_default().push(x[i].distance(x[j]));
                    }
                }
            }
        }
    }
    dists
        .into_iter()
        .filter(|(_, v)| v.len() >= 10)
        .map(|(k, mut v)| {
            v.sort_by(f32::total_cmp);
            (k, v[v.len() / 2])
        })
        .collect()
}

/// Mean and 90th percentile of |d / median − 1| over the near pairs.
fn stretch(data: &[Episode], near: &[((usize, usize), f32)]) -> (f64, f64) {
    let mut all: Vec<f32> = Vec::new();
    for ep in data {
        for t in 0..ep.frames() {
            let x = ep.frame(t);
            for &((i, j), d0) in near {
                if ep.visible(t, i) && ep.visible(t, j) {
                    all.push((x[i].distance(x[j]) / d0 - 1.0).abs());
                }
            }
        }
    }
    all.sort_by(f32::total_cmp);
    let mean = all.iter().map(|v| f64::from(*v)).sum::<f64>() / all.len().max(1) as f64;
    let p90 = all.get(all.len() * 9 / 10).copied().unwrap_or(0.0);
    (mean, f64::from(p90))
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [object, effect, scales, seed, sweeps] = args.as_slice() else {
        bail!("usage: effect_stretch <object> <effect> <scale>[,...] <seed> <sweeps>[,...]");
    };
    let object: ObjectKind = object.parse()?;
    let kind: EffectKind = effect.parse()?;
    let seed: u64 = seed.parse().context("seed")?;
    let scales: Vec<f32> = scales
        .split(',')
        .map(|s| s.parse().context("scale"))
        .collect::<Result<_, _>>()?;
    let sweeps: Vec<usize> = sweeps
        .split(',')
        .map(|s| s.parse().context("sweeps"))
        .collect::<Result<_, _>>()?;
    println!("{object}, {kind}, seed {seed}: mean (p90) of |d / median - 1| over near pairs");
    for &n in &sweeps {
        let plain = generate(object, Effects::none(), seed, n)?;
        let near: Vec<((usize, usize), f32)> = reference(&plain)
            .into_iter()
            .filter(|(_, d)| *d < 0.04)
            .collect();
        let (m0, p0) = stretch(&plain, &near);
        println!(
            "sweeps {n:>2}: no effect {m0:.3} ({p0:.3}), {} pairs",
            near.len()
        );
        for &s in &scales {
            let e = Effects::only_scaled(object, kind, s);
            let data = generate(object, e, seed, n)?;
            let (m, p) = stretch(&data, &near);
            println!(
                "sweeps {n:>2}: x{s:<4} {m:.3} ({p:.3}), excess {:+.3}",
                m - m0
            );
        }
    }
    Ok(())
}
