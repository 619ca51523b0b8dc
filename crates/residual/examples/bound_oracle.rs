//! How much a perfect corrector could gain under each residual bound, on training episodes.
//!
//! The residual network can change each free particle's velocity by at most `s` m/s per axis
//! and step (`residual_scale`, 0.1 in the paper). This prints, for each bound, the rollout MDE
//! (cm) of the greedy bounded oracle (`TrainSet::oracle_mde_cm`, `docs/residual.md`, "The
//! bound's ceiling") over training episodes, and what fraction of the backbone's own MDE it
//! removes. Only training episodes are read, so nothing here sees the val split.
//!
//! ```sh
//! cargo run --release -p pgrd-residual --example bound_oracle -- <data-dir> <run-dir> [paper|deform] [bounds] [episodes]
//! # bounds: comma-separated m/s per axis, default 0.1,0.2,0.5,1,2; episodes: default all
//! ```
//!
//! A smaller `episodes` takes a subset spread evenly over the split, which can fall on
//! recordings' first episodes: 30 of a generated dataset's 100 are episodes 0, 3 and 6 of each
//! recording, a third of them starts from rest (one in ten in the split). Until session 45 the
//! default was 30.
//!
//! Only backbones without library effects (`backbone.json` without `effects`).

mod common;

fn main() -> Result<(), common::Error> {
    let inputs = common::inputs(
        "usage: bound_oracle <data-dir> <run-dir> [paper|deform] [bounds] [episodes]",
    )?;
    let (data_dir, rest) = (&inputs.data_dir, &inputs.rest);
    let bounds: Vec<f32> = rest
        .first()
        .map_or("0.1,0.2,0.5,1,2", String::as_str)
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let max_episodes: usize = rest.get(1).map_or(Ok(usize::MAX), |s| s.parse())?;
    let set = inputs.training_set()?;
    let mean = |v: Vec<(usize, f64)>| v.iter().map(|e| e.1).sum::<f64>() / v.len().max(1) as f64;
    let own = set.oracle_mde_cm(0.0, max_episodes)?;
    println!(
        "{data_dir}: {} training episodes, oracle rollout MDE (cm) per residual bound (m/s per axis)",
        own.len()
    );
    let backbone = mean(own);
    println!("    backbone: {backbone:6.2} cm");
    for &bound in &bounds {
        let mde = mean(set.oracle_mde_cm(bound, max_episodes)?);
        println!(
            "  bound {bound:>4}: {mde:6.2} cm  (removes {:5.1} % of the backbone's)",
            100.0 * (1.0 - mde / backbone)
        );
    }
    Ok(())
}
