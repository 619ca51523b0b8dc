//! Resuming `cargo xtask train` only with the settings the checkpoint was trained with.
//!
//! A checkpoint holds weights and Adam moments, which load whatever the command line now says;
//! resuming a run of one start mode or bound with another would silently train the rest of the
//! schedule differently (and a recipe choice would then compare mislabelled networks).

use std::path::Path;

use anyhow::Context;
use residual::{ModelConfig, TrainConfig};

/// Training settings that must match to resume. `iterations` and `decay_steps` may change (to
/// extend a run); everything else decides what is learned.
const TRAIN_KEYS: [&str; 15] = [
    "rollout_steps",
    "batch",
    "lr",
    "lr_min",
    "clip",
    "augment",
    "seed",
    "start_from",
    "refresh_every",
    "loss",
    "sim_gradient",
    // The weight average is part of the checkpoint: resuming it with another decay (or
    // switching it on halfway) would average a different network than the one named.
    "ema_decay",
    "weight_decay",
    "input_noise_m",
    // Another order of adding the gradients: resuming across it would train on with other
    // rounding than the run's name says.
    "parallel_batch",
];

/// An error naming every setting in which `checkpoint_json` (a `train_ckpt.json`) differs from
/// `model` and `train`. Keys that an older checkpoint lacks are not compared.
pub fn check(
    checkpoint_json: &Path,
    model: &ModelConfig,
    train: &TrainConfig,
) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(checkpoint_json)
        .with_context(|| format!("reading {}", checkpoint_json.display()))?;
    let saved: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("parsing {}", checkpoint_json.display()))?;
    let model_now = serde_json::to_value(model)?;
    let train_now = serde_json::to_value(train)?;
    let mut differ = Vec::new();
    if let (Some(was), Some(now)) = (saved["model"].as_object(), model_now.as_object()) {
        for (key, value) in now {
            if let Some(old) = was.get(key).filter(|old| *old != value) {
                differ.push(format!("{key} {old} (now {value})"));
            }
        }
    }
    for key in TRAIN_KEYS {
        let (old, now) = (&saved["train"][key], &train_now[key]);
        if !old.is_null() && old != now {
            differ.push(format!("{key} {old} (now {now})"));
        }
    }
    anyhow::ensure!(
        differ.is_empty(),
        "{} was trained with other settings: {}; rerun with the flags it was trained with, pass \
         --restart to start over, or train in another --run directory",
        checkpoint_json.display(),
        differ.join(", ")
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use residual::StartFrom;

    fn checkpoint(dir: &Path, model: &ModelConfig, train: &TrainConfig) -> std::path::PathBuf {
        let path = dir.join("train_ckpt.json");
        let json = serde_json::json!({ "step": 3, "model": model, "train": train });
        std::fs::write(&path, json.to_string()).unwrap();
        path
    }

    #[test]
    fn resuming_needs_the_settings_the_checkpoint_was_trained_with() {
        let dir = std::env::temp_dir().join(format!("pgrd-train-resume-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let model = ModelConfig::tiny();
        let train = TrainConfig::default();
        let path = checkpoint(&dir, &model, &train);
        check(&path, &model, &train).unwrap();

        // More iterations extend the run.
        let longer = TrainConfig {
            iterations: train.iterations * 2,
            decay_steps: train.decay_steps * 2,
            ..train.clone()
        };
        check(&path, &model, &longer).unwrap();

        // Another start mode or bound would train a different network under the same name.
        let recorded = TrainConfig {
            start_from: StartFrom::Recorded,
            ..train.clone()
        };
        let err = check(&path, &model, &recorded).unwrap_err().to_string();
        assert!(
            err.contains("start_from") && err.contains("--restart"),
            "{err}"
        );
        let wider = ModelConfig {
            residual_scale: 1.0,
            ..model.clone()
        };
        let err = check(&path, &wider, &train).unwrap_err().to_string();
        assert!(err.contains("residual_scale"), "{err}");
        let averaged = TrainConfig {
            ema_decay: 0.99,
            ..train.clone()
        };
        let err = check(&path, &model, &averaged).unwrap_err().to_string();
        assert!(err.contains("ema_decay"), "{err}");
        // The batch's gradient added in another order trains other digits.
        let parallel = TrainConfig {
            parallel_batch: true,
            ..train.clone()
        };
        let err = check(&path, &model, &parallel).unwrap_err().to_string();
        assert!(err.contains("parallel_batch"), "{err}");

        // A checkpoint written before a setting existed is not held to it.
        let mut old: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        old["train"].as_object_mut().unwrap().remove("start_from");
        std::fs::write(&path, old.to_string()).unwrap();
        check(&path, &model, &recorded).unwrap();
        std::fs::remove_dir_all(dir).ok();
    }
}
