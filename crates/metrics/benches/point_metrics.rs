//! Point-metric timings for 1000 x 1000 points (the evaluation protocol's cloud size).
//!
//! Run: `RAYON_NUM_THREADS=2 cargo bench -p pgrd-metrics --bench point_metrics` (and `=1`).
//! Two cloud pairs: "independent" (two unrelated uniform clouds in a 0.3 m cube, the hard case
//! for EMD) and "perturbed" (the ground truth moved by up to ±5 mm per axis and shuffled: what
//! a good prediction looks like).
//!
//! The `*_cpu_time` variants report the process's on-CPU time per call (all threads summed,
//! from `/proc/self/task/*/schedstat`) instead of wall time: on a machine shared with other
//! jobs they do not count time spent waiting for a core. With one rayon thread that is the
//! unloaded single-core time; with two it is the total work of both.

// criterion_group! generates an undocumented public function.
#![allow(missing_docs)]

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{Criterion, criterion_group, criterion_main};
use metrics::lsap::LsapSolver;
use metrics::{EmdSolver, PointIndex, chamfer, emd};

/// splitmix64 stream mapped to [0, 1).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        (z ^ (z >> 31)) as f64 / 2f64.powi(64)
    }
}

fn uniform_cloud(rng: &mut Rng, n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| {
            [
                0.3 * rng.next() as f32,
                0.3 * rng.next() as f32,
                0.3 * rng.next() as f32,
            ]
        })
        .collect()
}

fn perturbed(rng: &mut Rng, gt: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let mut out: Vec<[f32; 3]> = gt
        .iter()
        .map(|p| p.map(|c| c + 0.01 * (rng.next() as f32 - 0.5)))
        .collect();
    for i in (1..out.len()).rev() {
        let j = (rng.next() * (i + 1) as f64) as usize;
        out.swap(i, j);
    }
    out
}

/// On-CPU time of all threads of this process (Linux), or `None` elsewhere.
fn process_cpu() -> Option<Duration> {
    let mut ns = 0u64;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let s = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        ns += s.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(Duration::from_nanos(ns))
}

/// `iters` calls of `f`, timed in process CPU time (wall time if unavailable).
fn cpu_iters(iters: u64, mut f: impl FnMut()) -> Duration {
    let (c0, t0) = (process_cpu(), Instant::now());
    for _ in 0..iters {
        f();
    }
    match (c0, process_cpu()) {
        (Some(a), Some(b)) => b.saturating_sub(a),
        _ => t0.elapsed(),
    }
}

fn benches(c: &mut Criterion) {
    let mut rng = Rng(20_261_121);
    let gt = uniform_cloud(&mut rng, 1000);
    let independent = uniform_cloud(&mut rng, 1000);
    let close = perturbed(&mut rng, &gt);

    for (name, pred) in [("independent", &independent), ("perturbed", &close)] {
        c.bench_function(&format!("chamfer_two_sided_1000x1000_{name}"), |b| {
            b.iter(|| chamfer(black_box(pred), black_box(&gt)).unwrap())
        });
        c.bench_function(
            &format!("chamfer_two_sided_1000x1000_{name}_cpu_time"),
            |b| {
                b.iter_custom(|iters| {
                    cpu_iters(iters, || {
                        black_box(chamfer(black_box(pred), black_box(&gt)).unwrap());
                    })
                })
            },
        );
        let index = PointIndex::new(&gt).unwrap();
        c.bench_function(&format!("chamfer_two_sided_reused_gt_index_{name}"), |b| {
            b.iter(|| index.chamfer(black_box(pred)).unwrap())
        });
        c.bench_function(&format!("chamfer_pred_to_gt_reused_gt_index_{name}"), |b| {
            b.iter(|| index.one_sided(black_box(pred)).unwrap())
        });
        let mut group = c.benchmark_group("emd");
        group.sample_size(20);
        group.bench_function(format!("emd_1000x1000_{name}"), |b| {
            b.iter(|| emd(black_box(pred), black_box(&gt)).unwrap())
        });
        let mut solver = EmdSolver::new();
        group.bench_function(format!("emd_1000x1000_reused_solver_{name}"), |b| {
            b.iter(|| solver.emd(black_box(pred), black_box(&gt)).unwrap())
        });
        group.bench_function(
            format!("emd_1000x1000_reused_solver_{name}_cpu_time"),
            |b| {
                b.iter_custom(|iters| {
                    cpu_iters(iters, || {
                        black_box(solver.emd(black_box(pred), black_box(&gt)).unwrap());
                    })
                })
            },
        );
        // The dense solver alone (the fallback path), on the full f64 cost matrix.
        let cost: Vec<f64> = pred
            .iter()
            .flat_map(|p| {
                gt.iter().map(move |q| {
                    let d: f64 = (0..3)
                        .map(|a| (f64::from(p[a]) - f64::from(q[a])).powi(2))
                        .sum();
                    d.sqrt()
                })
            })
            .collect();
        let mut lsap = LsapSolver::new();
        group.sample_size(10);
        group.bench_function(format!("dense_lsap_1000x1000_{name}"), |b| {
            b.iter(|| lsap.solve(black_box(&cost), 1000, 1000).unwrap()[0])
        });
        group.finish();
    }
}

criterion_group!(point_metrics, benches);
criterion_main!(point_metrics);
