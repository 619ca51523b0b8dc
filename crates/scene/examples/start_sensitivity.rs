//! How much a backbone's val MDE moves when its start positions move by tracker-sized amounts.
//!
//! ```sh
//! cargo run --release -p pgrd-scene --example start_sensitivity -- \
//!     <data-dir> <run-dir> [sigma_mm,...] [draws] [all|normal|plane]
//! ```
//!
//! For every val episode (the paper's window, unseen start points placed as the pipelines do),
//! the run's plain backbone is rolled out from the scene's start, then again `draws` times with
//! every simulated particle's start position displaced by an independent N(0, σ²) per axis
//! (seeded, start velocities kept; the springs are built from the displaced positions, so the
//! displaced start is at rest, as a differently tracked start would be). Per σ it prints the
//! draws' mean val MDE, its spread over draws (standard deviation, min..max) and the per-episode
//! spread: how finely a row of the results can be read when the start is known to about σ.
//! Defaults: σ = 0.5, 1, 2 mm, 8 draws, displaced along all three axes. `normal` displaces
//! each particle only along the start shape's thinnest principal axis (per episode: the
//! eigenvector of the positions' covariance with the smallest eigenvalue, the normal of a
//! flat sheet) by N(0, σ²); `plane` only along the two other axes.

use std::num::NonZeroUsize;

use dataset::{Dataset, Split};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use scene::{Protocol, Scene, SceneConfig, score_steps};

type Error = Box<dyn std::error::Error>;

const USAGE: &str =
    "start_sensitivity <data-dir> <run-dir> [sigma_mm,...] [draws] [all|normal|plane]";

/// Which directions a start position is displaced along.
#[derive(Clone, Copy, PartialEq)]
enum Along {
    All,
    Normal,
    Plane,
}

/// The unit eigenvector of the positions' covariance with the smallest eigenvalue: power
/// iteration on `tr(C) I - C`, whose largest eigenvalue is C's smallest.
fn thinnest_axis(x: &[Vec3]) -> Vec3 {
    let n = x.len().max(1) as f32;
    let c = x.iter().copied().sum::<Vec3>() / n;
    let mut cov = glam::Mat3::ZERO;
    for p in x {
        let d = *p - c;
        cov += glam::Mat3::from_cols(d * d.x, d * d.y, d * d.z) / n;
    }
    let trace = cov.x_axis.x + cov.y_axis.y + cov.z_axis.z;
    let flipped = glam::Mat3::from_diagonal(Vec3::splat(trace)) - cov;
    // A start not parallel to any axis of a generic shape; 200 iterations are plenty for a
    // sheet, whose smallest eigenvalue is far below the others.
    let mut v = Vec3::new(0.36, 0.48, 0.8);
    for _ in 0..200 {
        v = (flipped * v).normalize_or(Vec3::Z);
    }
    v
}

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (Some(data_dir), Some(run)) = (args.first(), args.get(1)) else {
        return Err(USAGE.into());
    };
    let sigmas_mm: Vec<f32> = match args.get(2) {
        Some(s) => s
            .split(',')
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|e| format!("sigma list {s}: {e}; {USAGE}"))?,
        None => vec![0.5, 1.0, 2.0],
    };
    let draws: NonZeroUsize = match args.get(3) {
        Some(d) => d.parse().map_err(|e| format!("draws {d}: {e}; {USAGE}"))?,
        None => NonZeroUsize::new(8).ok_or("8 is non-zero")?,
    };
    let along = match args.get(4).map(String::as_str) {
        None | Some("all") => Along::All,
        Some("normal") => Along::Normal,
        Some("plane") => Along::Plane,
        Some(other) => return Err(format!("direction {other}; {USAGE}").into()),
    };
    let file: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(
        std::path::Path::new(run).join("backbone.json"),
    )?)?;
    if file
        .get("effects")
        .is_some_and(|e| e.as_array().is_some_and(|a| !a.is_empty()))
    {
        return Err("backbones with library effects are not supported here".into());
    }
    if file.get("substep").is_some_and(|s| s != "auto") {
        return Err("only backbones fitted with the auto substep are supported here".into());
    }
    let params: springs::SpringParams = serde_json::from_value(file["params"].clone())?;
    let data = Dataset::open(data_dir)?;
    let config = SceneConfig::default().with_neighbours_of(&data)?;

    let mut scenes: Vec<Scene> = Vec::new();
    for index in data.split_indices(Split::Val) {
        let episode = data.load_episode(index)?;
        let window = Protocol::Paper.window(episode.frames())?;
        scenes.push(Scene::new(&data.meta, &episode, window, &config)?);
    }
    if scenes.is_empty() {
        return Err("the dataset has no val episodes".into());
    }
    let episode_mde = |scene: &Scene| -> Result<f64, Error> {
        let pred = scene.rollout(&params, &scene.sim_config(), Default::default())?;
        let steps = score_steps(scene, &pred, false)?;
        Ok(scene::mean_over_steps(&steps, |s| s.mde).unwrap_or(0.0))
    };
    let base: Vec<f64> = scenes.iter().map(episode_mde).collect::<Result<_, _>>()?;
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let sd = |v: &[f64]| {
        let m = mean(v);
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len().max(2) - 1) as f64).sqrt()
    };
    println!(
        "{} val episodes, {} particles in the first scene; val MDE from the scenes' start: {:.3} cm",
        scenes.len(),
        scenes[0].particles(),
        100.0 * mean(&base)
    );
    let normals: Vec<Vec3> = scenes.iter().map(|s| thinnest_axis(&s.init.x)).collect();
    if along != Along::All {
        // How flat the starts are: RMS distance from the centroid along the thinnest axis.
        let mut rms: Vec<f64> = scenes
            .iter()
            .zip(&normals)
            .map(|(s, &n)| {
                let c = s.init.x.iter().copied().sum::<Vec3>() / s.init.x.len().max(1) as f32;
                let ss: f64 = s
                    .init
                    .x
                    .iter()
                    .map(|p| f64::from((*p - c).dot(n)).powi(2))
                    .sum();
                (ss / s.init.x.len().max(1) as f64).sqrt()
            })
            .collect();
        rms.sort_by(f64::total_cmp);
        println!(
            "starts' RMS extent along their thinnest axis: median {:.2} mm, max {:.2} mm",
            1000.0 * rms[rms.len() / 2],
            1000.0 * rms[rms.len() - 1]
        );
    }
    println!(
        "sigma_mm  draws  val_mde_cm(mean)  sd_over_draws_cm  min..max_cm  per_episode_sd_cm(median, max)"
    );
    for &sigma_mm in &sigmas_mm {
        // One row of draws per episode: mde[e][d].
        let mut mde = vec![Vec::with_capacity(draws.get()); scenes.len()];
        for draw in 0..draws.get() {
            for (e, scene) in scenes.iter().enumerate() {
                let mut rng = ChaCha8Rng::seed_from_u64((draw as u64) << 32 | e as u64);
                let mut moved = scene.clone();
                let normal = normals[e];
                for x in &mut moved.init.x {
                    let n: [f32; 3] = std::array::from_fn(|_| rng.sample(StandardNormal));
                    let d = Vec3::from_array(n);
                    let d = match along {
                        Along::All => d,
                        Along::Normal => normal * d.x,
                        Along::Plane => d - normal * d.dot(normal),
                    };
                    *x += d * (sigma_mm / 1000.0);
                }
                mde[e].push(episode_mde(&moved)?);
            }
        }
        let per_draw: Vec<f64> = (0..draws.get())
            .map(|d| mean(&mde.iter().map(|row| row[d]).collect::<Vec<_>>()))
            .collect();
        let mut per_episode_sd: Vec<f64> = mde.iter().map(|row| sd(row)).collect();
        per_episode_sd.sort_by(f64::total_cmp);
        let lo = per_draw.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = per_draw.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        println!(
            "{sigma_mm:8.1}  {:5}  {:16.3}  {:16.3}  {:.3}..{:.3}  {:.3}, {:.3}",
            draws.get(),
            100.0 * mean(&per_draw),
            100.0 * sd(&per_draw),
            100.0 * lo,
            100.0 * hi,
            100.0 * per_episode_sd[per_episode_sd.len() / 2],
            100.0 * per_episode_sd[per_episode_sd.len() - 1],
        );
    }
    Ok(())
}
