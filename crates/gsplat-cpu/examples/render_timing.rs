//! Wall time of the benchmark scenes (`benches/scenes/mod.rs`), best and median of N renders:
//! on a machine shared with other jobs the best run is the closest to an idle machine, the
//! criterion bench's mean the closest to what a user of a busy machine sees.
//!
//! ```text
//! RAYON_NUM_THREADS=2 cargo run --release -p pgrd-gsplat-cpu --example render_timing -- [N]
//! ```

use std::time::Instant;

#[path = "../benches/scenes/mod.rs"]
mod scenes;

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg").map_or_else(|_| "n/a".into(), |s| s.trim().to_string())
}

fn main() -> Result<(), gsplat::Error> {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(30)
        .max(1);
    let cam = scenes::camera();
    println!(
        "threads {}, {n} renders per scene, load before: {}",
        rayon::current_num_threads(),
        load()
    );
    for (name, scene) in scenes::all() {
        gsplat::render(&scene, &cam, [1.0; 3])?; // warm-up
        let mut ms: Vec<f64> = (0..n)
            .map(|_| {
                let t = Instant::now();
                let img = gsplat::render(&scene, &cam, [1.0; 3]);
                std::hint::black_box(img).map(|_| t.elapsed().as_secs_f64() * 1e3)
            })
            .collect::<Result<_, _>>()?;
        ms.sort_by(f64::total_cmp);
        println!("{name}: best {:.1} ms, median {:.1} ms", ms[0], ms[n / 2]);
    }
    println!("load after: {}", load());
    Ok(())
}
