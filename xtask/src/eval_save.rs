//! `eval --save-predictions <dir>`: each episode's predicted trajectory beside what was
//! recorded, as safetensors a user loads without pgrd (`safetensors.numpy.load_file`), and an
//! index (`predictions.json`) saying what the files hold.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use glam::Vec3;
use safetensors::{Dtype, tensor::TensorView};
use scene::Scene;
use serde::Serialize;

/// The index file's name inside the directory.
pub const INDEX: &str = "predictions.json";

/// One episode's entry in the index.
#[derive(Serialize)]
struct Entry {
    episode: usize,
    file: String,
    start_frame: usize,
    steps: usize,
    mde_cm: f64,
}

/// What `predictions.json` holds.
#[derive(Serialize)]
struct Index<'a> {
    model: &'a str,
    dataset: &'a str,
    split: String,
    protocol: &'a str,
    /// Seconds between consecutive frames of the files.
    step_s: f32,
    /// Tensors in every episode file, with their shapes and meaning.
    tensors: [&'static str; 5],
    episodes: Vec<Entry>,
    /// Episodes of the split whose rollout diverged: no file.
    diverged: &'a [usize],
    /// Episodes of the split the tracker saw nothing of in the window: not scored, no file.
    unseen: &'a [usize],
}

/// One scored episode: its index in the dataset, its scene, the predicted tracked positions
/// at frames `start + 1 ..= start + steps` (m) and its mean MDE (cm).
pub struct Saved<'a> {
    /// Episode index in the dataset.
    pub episode: usize,
    /// The scene the prediction was made on.
    pub scene: &'a Scene,
    /// Predicted tracked positions, one frame per step, m.
    pub predicted: &'a [Vec<Vec3>],
    /// The episode's mean MDE over its steps, cm.
    pub mde_cm: f64,
}

/// Header fields of `predictions.json` that are the same for every episode.
pub struct About<'a> {
    /// The model's name in reports (`spring-mass`, `pgrd`, ...).
    pub model: &'a str,
    /// The dataset directory as given.
    pub dataset: &'a str,
    /// The split scored.
    pub split: dataset::Split,
    /// The protocol's name.
    pub protocol: &'a str,
    /// Seconds per model step.
    pub step_s: f32,
    /// Episodes whose rollout diverged (no file: nothing to save).
    pub diverged: &'a [usize],
    /// Episodes the tracker saw no point of in any predicted frame (not scored, no file).
    pub unseen: &'a [usize],
}

fn f32_bytes(values: impl Iterator<Item = f32>) -> Vec<u8> {
    values.flat_map(f32::to_le_bytes).collect()
}

/// Little-endian float32 bytes (a safetensors tensor's data) as values.
pub(crate) fn f32_values(bytes: &[u8]) -> Vec<f32> {
    bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn points_bytes<'a>(frames: impl Iterator<Item = &'a [Vec3]>) -> Vec<u8> {
    f32_bytes(frames.flat_map(|f| f.iter().flat_map(|p| p.to_array())))
}

/// The safetensors bytes of one episode.
fn episode_bytes(s: &Saved<'_>) -> anyhow::Result<Vec<u8>> {
    let scene = s.scene;
    let (steps, n) = (s.predicted.len(), scene.tracked);
    anyhow::ensure!(
        steps == scene.truth.len() && s.predicted.iter().all(|f| f.len() == n),
        "episode {}: {} predicted frames of {:?} points for {} recorded frames of {n}",
        s.episode,
        steps,
        s.predicted.first().map(Vec::len),
        scene.truth.len()
    );
    let grippers = scene.actions.num_grippers();
    let gripper_frames: Vec<Vec<Vec3>> = (0..scene.actions.num_frames())
        .filter_map(|t| scene.actions.frame(t).map(|f| f.positions.to_vec()))
        .collect();
    let visible: Vec<u8> = scene.visible.iter().flatten().map(|&v| v as u8).collect();
    let owned: Vec<(&str, Dtype, Vec<usize>, Vec<u8>)> = vec![
        (
            "predicted",
            Dtype::F32,
            vec![steps, n, 3],
            points_bytes(s.predicted.iter().map(Vec::as_slice)),
        ),
        (
            "recorded",
            Dtype::F32,
            vec![steps, n, 3],
            points_bytes(scene.truth.iter().map(Vec::as_slice)),
        ),
        ("visible", Dtype::U8, vec![steps, n], visible),
        (
            "start",
            Dtype::F32,
            vec![n, 3],
            points_bytes(std::iter::once(&scene.init.x[..n])),
        ),
        (
            "grippers",
            Dtype::F32,
            vec![gripper_frames.len(), grippers, 3],
            points_bytes(gripper_frames.iter().map(Vec::as_slice)),
        ),
    ];
    let views = owned
        .iter()
        .map(|(name, dtype, shape, bytes)| {
            TensorView::new(*dtype, shape.clone(), bytes).map(|v| (*name, v))
        })
        .collect::<Result<Vec<_>, _>>()
        .context("building the episode's tensors")?;
    let info = HashMap::from([("units".to_string(), "metres".to_string())]);
    Ok(safetensors::serialize(views, Some(info))?)
}

/// Writes `ep_<index>.safetensors` for every episode of `saved` and `predictions.json` into
/// `dir` (created), each file written to a temporary name and renamed. Returns the index path.
pub fn write(dir: &Path, about: &About<'_>, saved: &[Saved<'_>]) -> anyhow::Result<PathBuf> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut episodes = Vec::with_capacity(saved.len());
    for s in saved {
        let file = format!("ep_{:04}.safetensors", s.episode);
        dataset::write_atomic(&dir.join(&file), &episode_bytes(s)?)?;
        episodes.push(Entry {
            episode: s.episode,
            file,
            start_frame: s.scene.window.start,
            steps: s.predicted.len(),
            mde_cm: s.mde_cm,
        });
    }
    let index = Index {
        model: about.model,
        dataset: about.dataset,
        split: about.split.to_string(),
        protocol: about.protocol,
        step_s: about.step_s,
        tensors: [
            "predicted [steps, points, 3] f32: the model's tracked points at frames start_frame + 1 ..= start_frame + steps, m",
            "recorded [steps, points, 3] f32: the dataset's positions at those frames, m",
            "visible [steps, points] u8: 1 where the tracker saw the point (only those are scored)",
            "start [points, 3] f32: the tracked points where the rollout started (frame start_frame), m",
            "grippers [steps + 1, grippers, 3] f32: the gripper positions driving the rollout, frames start_frame ..= start_frame + steps, m",
        ],
        episodes,
        diverged: about.diverged,
        unseen: about.unseen,
    };
    let path = dir.join(INDEX);
    crate::report::write_json(&path, &index)?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use safetensors::SafeTensors;

    use crate::cmd_eval::{EvalArgs, run};
    use crate::cmd_fit::{FIXTURE_ROPE, FitArgs};
    use crate::common::ProtocolArg;

    /// The saved files hold what the report scored: the mean distance between the saved
    /// predicted and recorded points, over the visible ones, is each episode's reported MDE.
    #[test]
    fn saved_predictions_reproduce_the_reported_errors() {
        let root = std::env::temp_dir().join(format!("pgrd-eval-save-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let run_dir = root.join("run");
        crate::cmd_fit::run(&FitArgs::quick_rope_fixture(run_dir.clone())).unwrap();
        let out = root.join("pred");
        let args = |save: Option<std::path::PathBuf>, horizon| EvalArgs {
            data: FIXTURE_ROPE.into(),
            run: run_dir.clone(),
            split: dataset::Split::Val,
            protocol: ProtocolArg::Paper,
            json: Some(root.join("eval.json")),
            plot: Some(root.join("eval.svg")),
            no_emd: true,
            visual: false,
            horizon,
            autograd: false,
            save_predictions: save,
        };
        let report = run(&args(Some(out.clone()), None)).unwrap();
        let index: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join(super::INDEX)).unwrap())
                .unwrap();
        let episodes = index["episodes"].as_array().unwrap();
        assert_eq!(episodes.len(), report.per_episode.len());
        assert_eq!(index["model"], "spring-mass");
        assert_eq!(index["diverged"], serde_json::json!([]));
        for (entry, score) in episodes.iter().zip(&report.per_episode) {
            assert_eq!(entry["episode"], score.episode);
            let bytes = std::fs::read(out.join(entry["file"].as_str().unwrap())).unwrap();
            let st = SafeTensors::deserialize(&bytes).unwrap();
            let (pred, rec, vis) = (
                st.tensor("predicted").unwrap(),
                st.tensor("recorded").unwrap(),
                st.tensor("visible").unwrap(),
            );
            let steps = entry["steps"].as_u64().unwrap() as usize;
            assert_eq!(pred.shape(), rec.shape());
            assert_eq!(pred.shape()[0], steps);
            assert_eq!(vis.shape(), &pred.shape()[..2]);
            let grippers = st.tensor("grippers").unwrap();
            assert_eq!(grippers.shape()[0], steps + 1);
            let (p, r) = (
                super::f32_values(pred.data()),
                super::f32_values(rec.data()),
            );
            // MDE per step over the visible points, then the mean over steps (eval's rule).
            let n = pred.shape()[1];
            let mut per_step = Vec::new();
            for t in 0..steps {
                let (mut sum, mut count) = (0.0f64, 0usize);
                for i in 0..n {
                    if vis.data()[t * n + i] == 0 {
                        continue;
                    }
                    let k = 3 * (t * n + i);
                    let d: f64 = (0..3)
                        .map(|c| f64::from(p[k + c] - r[k + c]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    sum += d;
                    count += 1;
                }
                if count > 0 {
                    per_step.push(sum / count as f64);
                }
            }
            let mde_cm = 100.0 * per_step.iter().sum::<f64>() / per_step.len() as f64;
            assert!(
                (mde_cm - score.mde_cm).abs() < 1e-4,
                "episode {}: {mde_cm} from the files, {} reported",
                score.episode,
                score.mde_cm
            );
        }
        // Every rollout diverging (gravity a million times too strong, upward): the command
        // fails, and the index still names the episodes.
        let strong = root.join("strong");
        crate::cmd_fit::diverging_rope_fixture(&strong);
        let dead = root.join("dead");
        let Err(err) = run(&EvalArgs {
            data: strong,
            ..args(Some(dead.clone()), None)
        }) else {
            panic!("every rollout diverged, yet eval succeeded");
        };
        assert!(format!("{err:#}").contains("diverged"), "{err:#}");
        let index: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dead.join(super::INDEX)).unwrap())
                .unwrap();
        assert_eq!(index["episodes"], serde_json::json!([]));
        assert_eq!(index["diverged"], serde_json::json!([3, 4]));
        let Err(err) = run(&args(Some(root.join("h")), Some(3))) else {
            panic!("--save-predictions with --horizon was accepted");
        };
        assert!(format!("{err:#}").contains("--horizon"), "{err:#}");
        std::fs::remove_dir_all(&root).ok();
    }
}
