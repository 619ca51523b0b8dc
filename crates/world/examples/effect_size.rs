//! How far each switchable effect moves the object, before any model sees it: per object,
//! effect and strength (`Effects::only_scaled`), `world::effect_displacement_m` in cm (the
//! mean distance between the tracked particles with the effect alone and without any effect,
//! same seed, no observation model; 60 tracked particles, coarse resolution, one recording per
//! episode). An effect that barely moves the object cannot be diagnosed from its data,
//! whatever the diagnosis does.
//!
//! `cargo run --release -p pgrd-world --example effect_size -- [objects] [scales] [episodes]
//! [effects]` e.g. `-- rope,paper,sloth 1,4,16,64 8 magnet,rotating-frame` (default: every
//! effect).

use world::{EffectKind, Effects, GenConfig, ObjectKind};

fn displacement_cm(object: ObjectKind, effects: Effects, episodes: usize) -> anyhow::Result<f64> {
    let mut cfg = GenConfig::fixture(object);
    cfg.train_episodes = 0;
    cfg.val_episodes = episodes;
    cfg.episodes_per_recording = 1;
    cfg.tracked = 60;
    cfg.effects = effects;
    Ok(100.0 * world::effect_displacement_m(&cfg)?)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let objects = args.first().map_or("rope,paper,sloth", String::as_str);
    let scales: Vec<f32> = args
        .get(1)
        .map_or("1,4,16,64", String::as_str)
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?;
    let episodes: usize = args.get(2).map_or(Ok(8), |s| s.parse())?;
    let kinds: Vec<EffectKind> = match args.get(3) {
        Some(list) => list.split(',').map(str::parse).collect::<Result<_, _>>()?,
        None => EffectKind::ALL.to_vec(),
    };
    for object in objects.split(',') {
        let object: ObjectKind = object.parse()?;
        for &kind in &kinds {
            let row: Vec<String> = scales
                .iter()
                .map(|&s| {
                    let d =
                        displacement_cm(object, Effects::only_scaled(object, kind, s), episodes)?;
                    Ok(format!("×{s}: {d:6.2}"))
                })
                .collect::<anyhow::Result<_>>()?;
            println!("{object:7} {:24} {}", kind.name(), row.join("  "));
        }
    }
    Ok(())
}
