//! Comparison with pycma 4.5.0 on the 10-D sphere, ellipsoid and Rosenbrock functions
//! (`../shared/golden/cmaes_pycma.json`, 11 seeds each, default settings, target 1e-8).
//!
//! A run succeeds when its best fitness reaches the target before any of the default
//! tolerance-based stopping criteria fires (pycma-like defaults, no evaluation limit and no
//! restarts). Evaluations count whole generations; the median is over successful runs.

use cmaes::{CmaEs, CmaesConfig, StopReason};
use serde_json::Value;
use std::path::PathBuf;

/// Seeds used for our 11 runs, fixed before any result was seen.
const SEEDS: std::ops::Range<u64> = 0..11;

/// Accepted ratio between our median evaluation count and pycma's, either way.
const MEDIAN_RATIO: f64 = 1.1;

/// The shared folder: `$PGRD_SHARED_DIR` or `<workspace>/../shared`. A missing file fails the
/// test; it never passes silently.
fn golden() -> Value {
    let dir = match std::env::var_os("PGRD_SHARED_DIR") {
        Some(p) => PathBuf::from(p),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../../shared"),
    };
    let path = dir.join("golden/cmaes_pycma.json");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("cannot read {} (set PGRD_SHARED_DIR): {e}", path.display()));
    serde_json::from_str(&text).unwrap()
}

fn sphere(x: &[f64]) -> f64 {
    x.iter().map(|v| v * v).sum()
}

/// pycma's `felli`: condition number 1e6, axis scales 1e6^(i / (n - 1)).
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

struct Outcome {
    successes: usize,
    median: f64,
    evaluations: Vec<u64>,
    failures: Vec<(u64, StopReason, f64)>,
}

fn run_all(f: fn(&[f64]) -> f64, spec: &Value) -> Outcome {
    let dim = spec["dim"].as_u64().unwrap() as usize;
    let x0 = spec["x0"].as_f64().unwrap();
    let sigma0 = spec["sigma0"].as_f64().unwrap();
    let target = spec["target"].as_f64().unwrap();
    let mut evaluations = Vec::new();
    let mut failures = Vec::new();
    for seed in SEEDS {
        let mut config = CmaesConfig::new(vec![x0; dim], sigma0);
        config.seed = seed;
        config.termination.target = Some(target);
        let mut es = CmaEs::new(config).unwrap();
        assert_eq!(
            es.population_size() as u64,
            spec["popsize"].as_u64().unwrap()
        );
        let stop = loop {
            if let Some(reason) = es.should_stop() {
                break reason;
            }
            let xs = es.ask();
            let fit: Vec<f64> = xs.iter().map(|x| f(x)).collect();
            es.tell(&xs, &fit).unwrap();
        };
        if stop == StopReason::TargetReached {
            evaluations.push(es.evaluations());
        } else {
            failures.push((seed, stop, es.best().unwrap().1));
        }
    }
    let mut sorted = evaluations.clone();
    sorted.sort_unstable();
    let k = sorted.len();
    let median = if k == 0 {
        f64::NAN
    } else if k % 2 == 1 {
        sorted[k / 2] as f64
    } else {
        0.5 * (sorted[k / 2 - 1] + sorted[k / 2]) as f64
    };
    Outcome {
        successes: k,
        median,
        evaluations,
        failures,
    }
}

fn check(name: &str, f: fn(&[f64]) -> f64) -> Outcome {
    let g = golden();
    let spec = &g["results"][name];
    let out = run_all(f, spec);
    let reference = spec["median_evaluations"].as_f64().unwrap();
    eprintln!(
        "{name}: {} / {} successes, median {} evaluations (pycma {} / {}, median {reference}); \
         successful runs {:?}; failures (seed, stop, best f) {:?}",
        out.successes,
        SEEDS.count(),
        out.median,
        spec["successes"],
        spec["runs"],
        out.evaluations,
        out.failures,
    );
    let ratio = out.median / reference;
    assert!(
        (1.0 / MEDIAN_RATIO..=MEDIAN_RATIO).contains(&ratio),
        "{name}: median {} vs pycma {reference} (ratio {ratio:.3})",
        out.median
    );
    out
}

#[test]
fn sphere_matches_pycma() {
    let out = check("sphere", sphere);
    assert_eq!(out.successes, 11);
}

#[test]
fn ellipsoid_matches_pycma() {
    let out = check("ellipsoid", ellipsoid);
    assert_eq!(out.successes, 11);
}

/// Rosenbrock from x0 = 0 ends in the local minimum near (-1, 1, ..., 1) (f ≈ 3.99) in a few
/// per cent of runs: pycma 4.5.0 failed 13 of its seeds 1..=400 (3.3 %; seed 6 of the golden
/// 11), this implementation 29 of seeds 0..1000 (2.9 %, `examples/golden_stats.rs`). With 11
/// seeds 10 or 11 successes are both typical, so the count may exceed pycma's 10 by one; fewer
/// than pycma's (two or more failures, probability ~4 % at these rates) fail the test.
#[test]
fn rosenbrock_matches_pycma() {
    let out = check("rosenbrock", rosenbrock);
    let reference = golden()["results"]["rosenbrock"]["successes"]
        .as_u64()
        .unwrap() as usize;
    assert!(
        out.successes == reference || out.successes == reference + 1,
        "{} successes vs pycma's {reference}",
        out.successes
    );
    // Every failure must be the known local minimum, not a numerical breakdown.
    for (seed, stop, f) in &out.failures {
        assert!(
            (f - 3.9866).abs() < 1e-3,
            "seed {seed}: stopped ({stop:?}) at f = {f}"
        );
    }
}
