//! Success rates and evaluation counts on the 10-D sphere, ellipsoid and Rosenbrock functions
//! over many seeds, with the settings of `tests/golden.rs` (pycma-like defaults, target 1e-8).
//!
//! `cargo run --release -p pgrd-cmaes --example golden_stats -- 200` runs seeds 0..200.

use cmaes::{CmaEs, CmaesConfig, StopReason};

/// A test function of a point.
type Objective = fn(&[f64]) -> f64;

fn sphere(x: &[f64]) -> f64 {
    x.iter().map(|v| v * v).sum()
}

fn ellipsoid(x: &[f64]) -> f64 {
    let n = x.len() as f64;
    x.iter()
        .enumerate()
        .map(|(i, v)| 1e6_f64.powf(i as f64 / (n - 1.0)) * v * v)
        .sum()
}

fn rosenbrock(x: &[f64]) -> f64 {
    x.windows(2)
        .map(|w| 100.0 * (w[1] - w[0] * w[0]).powi(2) + (1.0 - w[0]).powi(2))
        .sum()
}

fn median(v: &mut [u64]) -> f64 {
    v.sort_unstable();
    let k = v.len();
    if k == 0 {
        f64::NAN
    } else if k % 2 == 1 {
        v[k / 2] as f64
    } else {
        0.5 * (v[k / 2 - 1] + v[k / 2]) as f64
    }
}

fn main() {
    let seeds: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().expect("seed count"))
        .unwrap_or(100);
    let cases: [(&str, Objective, f64); 3] = [
        ("sphere", sphere, 1.0),
        ("ellipsoid", ellipsoid, 1.0),
        ("rosenbrock", rosenbrock, 0.0),
    ];
    for (name, f, x0) in cases {
        let mut evals = Vec::new();
        let mut failures = Vec::new();
        for seed in 0..seeds {
            let mut config = CmaesConfig::new(vec![x0; 10], 0.5);
            config.seed = seed;
            config.termination.target = Some(1e-8);
            let mut es = CmaEs::new(config).expect("valid config");
            let stop = loop {
                if let Some(r) = es.should_stop() {
                    break r;
                }
                let xs = es.ask();
                let fit: Vec<f64> = xs.iter().map(|x| f(x)).collect();
                es.tell(&xs, &fit).expect("tell");
            };
            if stop == StopReason::TargetReached {
                evals.push(es.evaluations());
            } else {
                failures.push((seed, stop, es.best().map(|b| b.1)));
            }
        }
        let successes = evals.len();
        let med = median(&mut evals);
        println!(
            "{name}: {successes}/{seeds} successes, median {med} evaluations (min {:?}, max {:?})",
            evals.first(),
            evals.last()
        );
        if !failures.is_empty() {
            println!("  failures (seed, stop, best f): {failures:?}");
        }
    }
}
