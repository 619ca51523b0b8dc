//! Cost of one CMA-ES generation (ask + tell, including the eigen-decomposition) for the
//! dimensions this project fits (5 and 12 physical parameters) and a larger 20-D case. The
//! objective is cheap pseudo-random noise: only the optimiser's own overhead is measured, and
//! the distribution neither converges nor diverges (no denormals, no restarts in the loop).
//!
//! Run: `cargo bench -p pgrd-cmaes --bench generation`

use cmaes::{CmaEs, CmaesConfig};
use criterion::{BenchmarkId, Criterion};
use std::hint::black_box;

fn generation(c: &mut Criterion) {
    let mut group = c.benchmark_group("cmaes_generation");
    for dim in [5usize, 12, 20] {
        group.bench_with_input(BenchmarkId::from_parameter(dim), &dim, |b, &dim| {
            let mut config = CmaesConfig::new(vec![0.5; dim], 0.2);
            config.seed = 1;
            // Keep the run alive for any number of iterations.
            config.termination.tol_fun = 0.0;
            config.termination.tol_x = 0.0;
            config.termination.stagnation = false;
            let mut es = CmaEs::new(config.clone()).unwrap();
            b.iter(|| {
                if es.should_stop().is_some() {
                    es = CmaEs::new(config.clone()).unwrap();
                }
                let xs = es.ask();
                let fit: Vec<f64> = xs
                    .iter()
                    .map(|x| (x.iter().sum::<f64>() * 1e6).sin())
                    .collect();
                es.tell(black_box(&xs), black_box(&fit)).unwrap();
            });
        });
    }
    group.finish();
}

// Written out instead of `criterion_group!`, whose generated function has no doc comment.
fn main() {
    let mut c = Criterion::default().configure_from_args();
    generation(&mut c);
    c.final_summary();
}
