//! `cargo xtask score`: score trajectories predicted elsewhere (another simulator, a user's own
//! model) on a dataset's episodes exactly as `eval` scores pgrd's, so that `compare` can pair
//! them with an `eval` report.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use dataset::{Dataset, Split};
use glam::Vec3;
use rayon::prelude::*;
use safetensors::{Dtype, SafeTensors};
use scene::{Protocol, Scene};
use serde::Deserialize;

use crate::cmd_eval::{EvalReport, ReportSpec, Scored, write_report};
use crate::common::{SceneSetting, load_scenes};

/// Arguments of `score`.
#[derive(clap::Args)]
pub struct ScoreArgs {
    /// Dataset directory (the episodes the predictions were made for).
    #[arg(long)]
    pub data: PathBuf,
    /// Directory laid out as `eval --save-predictions` writes it: `predictions.json` and one
    /// safetensors file per episode holding `predicted` [steps, points, 3] (float32 or
    /// float64, metres) for the dataset's tracked points at the window's frames.
    #[arg(long)]
    pub predictions: PathBuf,
    /// Write the report here (default: <predictions>/score_<split>.json).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Write the error-per-step plot here (default: beside the JSON, .svg).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Skip exact EMD (faster on large clouds).
    #[arg(long)]
    pub no_emd: bool,
}

/// `predictions.json`, as far as `score` reads it.
#[derive(Deserialize)]
struct Index {
    /// The model's name in the report.
    model: String,
    split: String,
    protocol: String,
    episodes: Vec<Entry>,
    /// Episodes whose rollout diverged (counted as `eval` counts them).
    #[serde(default)]
    diverged: Vec<usize>,
}

#[derive(Deserialize)]
struct Entry {
    episode: usize,
    file: String,
    start_frame: usize,
    steps: usize,
}

/// The `predicted` tensor of `bytes` as frames of points, checked against `scene`'s window;
/// `Err` inside when it holds a value that is not finite (a diverged rollout, counted as
/// `eval` counts them), with where.
fn predicted(bytes: &[u8], scene: &Scene) -> anyhow::Result<Result<Vec<Vec<Vec3>>, String>> {
    let st = SafeTensors::deserialize(bytes).context("not a safetensors file")?;
    let t = st
        .tensor("predicted")
        .context("no 'predicted' tensor [steps, points, 3]")?;
    let (steps, n) = (scene.window.steps, scene.tracked);
    anyhow::ensure!(
        t.shape() == [steps, n, 3],
        "'predicted' has shape {:?}; the dataset's window needs [{steps}, {n}, 3] (steps, \
         tracked points, xyz)",
        t.shape()
    );
    let values: Vec<f32> = match t.dtype() {
        Dtype::F32 => crate::eval_save::f32_values(t.data()),
        Dtype::F64 => t
            .data()
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap_or([0; 8])) as f32)
            .collect(),
        other => anyhow::bail!("'predicted' is {other:?}; float32 or float64 metres are read"),
    };
    if let Some(k) = values.iter().position(|v| !v.is_finite()) {
        return Ok(Err(format!(
            "'predicted' is not finite (as float32) at step {}, point {}: a diverged rollout",
            k / 3 / n,
            k / 3 % n
        )));
    }
    Ok(Ok(values
        .chunks_exact(3 * n)
        .map(|frame| {
            frame
                .chunks_exact(3)
                .map(|p| Vec3::new(p[0], p[1], p[2]))
                .collect()
        })
        .collect()))
}

/// Scores the predictions and writes the report.
pub fn run(args: &ScoreArgs) -> anyhow::Result<EvalReport> {
    let t0 = Instant::now();
    let data = Dataset::open(&args.data)?;
    let index_path = args.predictions.join(crate::eval_save::INDEX);
    let text = std::fs::read_to_string(&index_path)
        .with_context(|| format!("reading {}", index_path.display()))?;
    let index: Index =
        serde_json::from_str(&text).with_context(|| format!("parsing {}", index_path.display()))?;
    let split: Split = index
        .split
        .parse()
        .map_err(|e: String| anyhow::anyhow!("{}: split: {e}", index_path.display()))?;
    let protocol = match index.protocol.as_str() {
        "paper" => Protocol::Paper,
        "deform" => Protocol::Deform,
        other => anyhow::bail!(
            "{}: protocol '{other}' (expected paper or deform)",
            index_path.display()
        ),
    };
    // The truth and the tracker's visibility come from the episodes alone, so the default
    // scene setting scores any model's predictions alike.
    let config = SceneSetting::default().scene_config(&data)?;
    let scenes: HashMap<usize, Scene> = load_scenes(&data, split, protocol, &config)?
        .into_iter()
        .collect();
    for e in &index.episodes {
        let scene = scenes.get(&e.episode).with_context(|| {
            format!(
                "{}: episode {} is not a '{split}' episode of {}",
                index_path.display(),
                e.episode,
                args.data.display()
            )
        })?;
        anyhow::ensure!(
            (e.start_frame, e.steps) == (scene.window.start, scene.window.steps),
            "episode {}: predicted from frame {} for {} steps, where the {} protocol starts at \
             frame {} for {} steps",
            e.episode,
            e.start_frame,
            e.steps,
            protocol.name(),
            scene.window.start,
            scene.window.steps
        );
    }
    let with_emd = !args.no_emd;
    // A file that cannot be read or does not fit is an error to fix; a prediction that left
    // the finite numbers is a diverged rollout (the inner `Err`).
    let results: Vec<anyhow::Result<Result<Scored<'_>, String>>> = index
        .episodes
        .par_iter()
        .map(|e| {
            let scene = &scenes[&e.episode];
            let path = args.predictions.join(&e.file);
            let bytes =
                std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let pred = match predicted(&bytes, scene)
                .with_context(|| format!("episode {} ({})", e.episode, path.display()))?
            {
                Ok(pred) => pred,
                Err(why) => return Ok(Err(format!("episode {}: {why}", e.episode))),
            };
            let errors = scene::score_steps(scene, &pred, with_emd)?;
            let l1 = scene::deform_l1(scene, &pred)?;
            Ok(Ok((errors, l1, (e.episode, scene, Vec::new()))))
        })
        .collect();
    let (mut per_episode, mut diverged) = (Vec::new(), index.diverged.len());
    for r in results {
        match r? {
            Ok(v) if v.0.iter().all(Option::is_none) => eprintln!(
                "warning: episode {}: the tracker saw no tracked point in any predicted frame; \
                 not scored",
                (v.2).0
            ),
            Ok(v) => per_episode.push(v),
            Err(why) => {
                diverged += 1;
                eprintln!("warning: {why}");
            }
        }
    }
    per_episode.sort_by_key(|(_, _, (i, _, _))| *i);
    let missing = scenes
        .len()
        .saturating_sub(index.episodes.len() + index.diverged.len());
    if missing > 0 {
        eprintln!(
            "note: {missing} of the {} '{split}' episodes have no prediction here; the report \
             covers the others",
            scenes.len()
        );
    }
    let json = args
        .json
        .clone()
        .unwrap_or_else(|| args.predictions.join(format!("score_{split}.json")));
    let plot = args
        .plot
        .clone()
        .unwrap_or_else(|| json.with_extension("svg"));
    let spec = ReportSpec {
        model: index.model.clone(),
        variant: None,
        backbone: "(predicted elsewhere)".to_string(),
        data: &data,
        dataset: args.data.display().to_string(),
        split,
        protocol,
        horizon: None,
        with_emd,
        visual: false,
        json,
        plot,
        network_path: None,
        rollout_wall_s: 0.0,
        started: t0,
    };
    let report = write_report(&spec, &per_episode, diverged)?;
    anyhow::ensure!(
        diverged == 0,
        "{diverged} predicted rollouts diverged (see the index and the warnings above)"
    );
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd_eval::EvalArgs;
    use crate::cmd_fit::{FIXTURE_ROPE, FitArgs};
    use crate::common::ProtocolArg;

    /// Rewrites `file`'s `predicted` tensor through `edit` (its f32 values, flat).
    fn edit_predicted(file: &std::path::Path, edit: impl Fn(&mut Vec<f32>)) {
        let bytes = std::fs::read(file).unwrap();
        let st = SafeTensors::deserialize(&bytes).unwrap();
        let t = st.tensor("predicted").unwrap();
        let mut values = crate::eval_save::f32_values(t.data());
        edit(&mut values);
        let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view =
            safetensors::tensor::TensorView::new(Dtype::F32, t.shape().to_vec(), &data).unwrap();
        std::fs::write(
            file,
            safetensors::serialize([("predicted", view)], None).unwrap(),
        )
        .unwrap();
    }

    /// Predictions saved by `eval` score to the same numbers, episode by episode; a shifted,
    /// a diverged and a misshapen prediction are read as such.
    #[test]
    fn eval_predictions_score_as_eval_scored_them() {
        let root = std::env::temp_dir().join(format!("pgrd-score-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let run_dir = root.join("run");
        crate::cmd_fit::run(&FitArgs::quick_rope_fixture(run_dir.clone())).unwrap();
        let pred = root.join("pred");
        let eval = crate::cmd_eval::run(&EvalArgs {
            data: FIXTURE_ROPE.into(),
            run: run_dir.clone(),
            split: Split::Val,
            protocol: ProtocolArg::Paper,
            json: Some(root.join("eval.json")),
            plot: Some(root.join("eval.svg")),
            no_emd: false,
            visual: false,
            horizon: None,
            autograd: false,
            save_predictions: Some(pred.clone()),
        })
        .unwrap();
        let args = ScoreArgs {
            data: FIXTURE_ROPE.into(),
            predictions: pred.clone(),
            json: Some(root.join("score.json")),
            plot: None,
            no_emd: false,
        };
        let score = run(&args).unwrap();
        assert_eq!(score.model, "spring-mass");
        assert_eq!(score.per_episode, eval.per_episode);
        assert_eq!(score.metrics["mde_cm"], eval.metrics["mde_cm"]);
        // Every predicted point 1 cm higher: each point's distance moves by at most 1 cm.
        let first = pred.join("ep_0003.safetensors");
        let kept = std::fs::read(&first).unwrap();
        edit_predicted(&first, |v| {
            v.iter_mut().skip(2).step_by(3).for_each(|z| *z += 0.01)
        });
        let shifted = run(&args).unwrap();
        let (before, after) = (eval.per_episode[0].mde_cm, shifted.per_episode[0].mde_cm);
        assert!(
            after != before && (after - before).abs() <= 1.0 + 1e-6,
            "{before} -> {after}"
        );
        assert_eq!(shifted.per_episode[1], eval.per_episode[1]);
        // A NaN is a diverged rollout: reported, and the command fails as eval does.
        edit_predicted(&first, |v| v[7] = f32::NAN);
        let err = format!("{:#}", run(&args).unwrap_err());
        assert!(err.contains("1 predicted rollouts diverged"), "{err}");
        // A prediction of another shape names what the dataset needs.
        let st = SafeTensors::deserialize(&kept).unwrap();
        let t = st.tensor("predicted").unwrap();
        let (steps, n) = (t.shape()[0], t.shape()[1]);
        let short = &t.data()[..4 * 3 * steps * (n - 1)];
        let view =
            safetensors::tensor::TensorView::new(Dtype::F32, vec![steps, n - 1, 3], short).unwrap();
        std::fs::write(
            &first,
            safetensors::serialize([("predicted", view)], None).unwrap(),
        )
        .unwrap();
        let err = format!("{:#}", run(&args).unwrap_err());
        assert!(err.contains(&format!("needs [{steps}, {n}, 3]")), "{err}");
        std::fs::remove_dir_all(&root).ok();
    }
}
