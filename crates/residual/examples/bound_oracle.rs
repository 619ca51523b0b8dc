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
//! # bounds: comma-separated m/s per axis, default 0.1,0.2,0.5,1,2; episodes: default 30
//! ```
//!
//! Only backbones without library effects (`backbone.json` without `effects`).

use dataset::{Dataset, Split};
use residual::TrainSet;
use scene::{Protocol, SceneConfig};

type Error = Box<dyn std::error::Error>;

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: bound_oracle <data-dir> <run-dir> [paper|deform] [bounds] [episodes]";
    let (Some(data_dir), Some(run)) = (args.first(), args.get(1)) else {
        return Err(usage.into());
    };
    let protocol = match args.get(2).map(String::as_str) {
        None | Some("paper") => Protocol::Paper,
        Some("deform") => Protocol::Deform,
        Some(p) => return Err(format!("unknown protocol {p}; {usage}").into()),
    };
    let bounds: Vec<f32> = args
        .get(3)
        .map_or("0.1,0.2,0.5,1,2", String::as_str)
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let max_episodes: usize = args.get(4).map_or(Ok(30), |s| s.parse())?;
    let data = Dataset::open(data_dir)?;
    let file: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(
        std::path::Path::new(run).join("backbone.json"),
    )?)?;
    if file
        .get("effects")
        .is_some_and(|e| e.as_array().is_some_and(|a| !a.is_empty()))
    {
        return Err("backbones with library effects are not supported here".into());
    }
    let params: springs::SpringParams = serde_json::from_value(file["params"].clone())?;
    let set = TrainSet::with_protocol(
        &data,
        Split::Train,
        &params,
        &SceneConfig::default(),
        protocol,
    )?;
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
