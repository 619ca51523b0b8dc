//! `eval --horizon K`: K-step predictions started from every recorded step of an episode's
//! window, the way a planner uses a model (MPPI predicts a short horizon from the state it
//! has just observed), instead of one rollout over the whole window.

use anyhow::Context;
use dataset::{Dataset, Episode};
use scene::{Scene, SceneConfig, StepErrors, Window};

/// What a model is asked to predict from each start: the backbone alone, or with the network.
pub struct Predictor<'a> {
    /// Fitted parameters.
    pub params: &'a springs::SpringParams,
    /// The run's backbone options (effects, refined field).
    pub options: &'a residual::BackboneOptionsFn,
    /// The residual network, when the run has one.
    pub net: Option<&'a residual::ResidualNet>,
    /// How the network is evaluated.
    pub path: crate::common::NetworkPath,
}

/// Per horizon step (1..=`horizon`), the errors of the `horizon`-step predictions started at
/// every frame of `scene`'s window that leaves `horizon` recorded frames after it, averaged
/// over the starts; and the mean DEFORM L1 of those predictions (m).
///
/// Every start reads its state and the network's history from the recording as the scene
/// reads its own start ([`Scene::new`], [`residual::History::from_episode`]). The springs are
/// the episode's: the backbone built at the window's first frame, as in the full-window
/// evaluation and in training, so only the starting state moves; a start whose particles are
/// not the window's (a filled volume's interior, filled afresh at every start) gets its own
/// backbone, as in training.
pub fn horizon_errors(
    data: &Dataset,
    episode: &Episode,
    scene: &Scene,
    config: &SceneConfig,
    horizon: usize,
    model: &Predictor<'_>,
) -> anyhow::Result<(Vec<Option<StepErrors>>, f64)> {
    anyhow::ensure!(
        (1..=scene.window.steps).contains(&horizon),
        "--horizon {horizon} must be between 1 and the window's {} steps",
        scene.window.steps
    );
    let sim = scene.sim_config();
    let base = scene.backbone(model.params, &sim, (model.options)())?;
    let starts = scene.window.start..=scene.window.start + scene.window.steps - horizon;
    let mut sum = vec![
        StepErrors {
            mde: 0.0,
            chamfer_pred_to_gt: 0.0,
            chamfer_gt_to_pred: 0.0,
            emd: f64::NAN,
        };
        horizon
    ];
    // How many predictions scored each step (a start whose step the tracker saw nothing in
    // does not).
    let mut scored = vec![0usize; horizon];
    // Every start's scene, and its own springs where it needs them.
    let mut windows = Vec::new();
    for start in starts {
        let at = Scene::new(
            &data.meta,
            episode,
            Window {
                start,
                steps: horizon,
            },
            config,
        )
        .with_context(|| format!("the {horizon}-step window from frame {start}"))?;
        // A volume's interior is filled afresh at every start: other material points than the
        // window's, even where as many, so they get their own springs (as in training).
        let fresh_interior =
            data.meta.structure == dataset::Structure::Volume && at.particles() > at.tracked;
        let own = if at.particles() == base.num_particles() && !fresh_interior {
            None
        } else {
            Some(at.backbone(model.params, &sim, (model.options)())?)
        };
        windows.push((start, at, own));
    }
    let predictions: Vec<Vec<Vec<glam::Vec3>>> = match model.net {
        Some(net) => {
            let histories = windows
                .iter()
                .map(|(_, at, _)| residual::History::from_episode(at, episode, data.meta.fps))
                .collect::<Result<Vec<_>, _>>()?;
            let jobs: Vec<residual::PredictJob<'_>> = windows
                .iter()
                .zip(&histories)
                .map(|((_, at, own), history)| residual::PredictJob {
                    backbone: own.as_ref().unwrap_or(&base),
                    init: &at.init,
                    history,
                    actions: &at.actions,
                    steps: horizon,
                })
                .collect();
            let results: Vec<residual::JobResult> = match model.path {
                // All starts at once: one network call per step for several starts (each
                // start's prediction is its own `residual::predict` up to float rounding).
                crate::common::NetworkPath::ForwardOnly => residual::predict_batch(net, &jobs)?,
                crate::common::NetworkPath::Autograd => jobs
                    .iter()
                    .map(|j| {
                        residual::predict(net, j.backbone, j.init, j.history, j.actions, j.steps)
                    })
                    .collect(),
            };
            results
                .into_iter()
                .zip(&windows)
                .map(|(r, (start, _, _))| {
                    r.with_context(|| format!("the {horizon}-step prediction from frame {start}"))
                })
                .collect::<anyhow::Result<_>>()?
        }
        None => windows
            .iter()
            .map(|(_, at, own)| {
                let mut out = own
                    .as_ref()
                    .unwrap_or(&base)
                    .rollout(&at.init, &at.actions)?
                    .positions;
                out.remove(0);
                Ok(out)
            })
            .collect::<anyhow::Result<_>>()?,
    };
    let mut l1 = 0.0;
    let count = windows.len();
    for ((_, at, _), mut pred) in windows.iter().zip(predictions) {
        for p in &mut pred {
            p.truncate(at.tracked);
        }
        let errors = scene::score_steps(at, &pred, false)?;
        for ((s, k), e) in sum.iter_mut().zip(&mut scored).zip(&errors) {
            if let Some(e) = e {
                s.mde += e.mde;
                s.chamfer_pred_to_gt += e.chamfer_pred_to_gt;
                s.chamfer_gt_to_pred += e.chamfer_gt_to_pred;
                *k += 1;
            }
        }
        l1 += scene::deform_l1(at, &pred)?;
    }
    let mean = sum
        .into_iter()
        .zip(scored)
        .map(|(mut s, k)| {
            (k > 0).then(|| {
                let k = k as f64;
                s.mde /= k;
                s.chamfer_pred_to_gt /= k;
                s.chamfer_gt_to_pred /= k;
                s
            })
        })
        .collect();
    Ok((mean, l1 / count as f64))
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use crate::cmd_eval::{EvalArgs, EvalReport, run};
    use crate::cmd_fit::FIXTURE_ROPE;
    use crate::common::ProtocolArg;

    fn eval(run_dir: &Path, horizon: Option<usize>, name: &str) -> anyhow::Result<EvalReport> {
        eval_by(run_dir, horizon, name, false)
    }

    fn eval_by(
        run_dir: &Path,
        horizon: Option<usize>,
        name: &str,
        autograd: bool,
    ) -> anyhow::Result<EvalReport> {
        run(&EvalArgs {
            data: FIXTURE_ROPE.into(),
            run: run_dir.to_path_buf(),
            split: dataset::Split::Val,
            protocol: ProtocolArg::Paper,
            json: Some(run_dir.join(format!("{name}.json"))),
            plot: Some(run_dir.join(format!("{name}.svg"))),
            no_emd: true,
            visual: false,
            horizon,
            autograd,
            save_predictions: None,
        })
    }

    fn assert_close(a: &EvalReport, b: &EvalReport) {
        assert_eq!(a.per_episode.len(), b.per_episode.len());
        for (x, y) in a.per_episode.iter().zip(&b.per_episode) {
            assert!(
                (x.mde_cm - y.mde_cm).abs() < 1e-9 * x.mde_cm.max(1.0),
                "episode {}: {} against {}",
                x.episode,
                x.mde_cm,
                y.mde_cm
            );
        }
    }

    /// A horizon as long as the window has one start, the window's own: the horizon
    /// evaluation must then be the full-window evaluation, for the backbone and for PGRD (its
    /// history read the same way).
    #[test]
    fn a_horizon_of_the_whole_window_is_the_full_window_evaluation() {
        let dir = std::env::temp_dir().join(format!("pgrd-horizon-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let bb = dir.join("bb");
        crate::cmd_fit::run(&crate::cmd_fit::FitArgs::quick_rope_fixture(bb.clone())).unwrap();
        let full = eval(&bb, None, "full").unwrap();
        let whole = eval(&bb, Some(full.steps), "whole").unwrap();
        assert_eq!(whole.steps, full.steps);
        assert_close(&whole, &full);
        let short = eval(&bb, Some(3), "short").unwrap();
        assert_eq!((short.steps, short.horizon), (3, Some(3)));
        assert!(short.per_episode.iter().all(|e| e.mde_cm.is_finite()));
        // Out of range: a clear error, not a panic.
        let Err(err) = eval(&bb, Some(full.steps + 1), "long") else {
            panic!("a horizon longer than the window was accepted");
        };
        assert!(format!("{err:#}").contains("--horizon"), "{err:#}");

        let net = dir.join("net");
        std::fs::create_dir_all(&net).unwrap();
        std::fs::copy(bb.join("backbone.json"), net.join("backbone.json")).unwrap();
        let argv = [
            "train",
            "--data",
            FIXTURE_ROPE,
            "--run",
            net.to_str().unwrap(),
            "--iterations",
            "2",
            "--quiet",
        ];
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            train: crate::cmd_train::TrainArgs,
        }
        let train = <Cli as clap::Parser>::try_parse_from(argv).unwrap().train;
        crate::cmd_train::run(&train).unwrap();
        let full = eval(&net, None, "full").unwrap();
        assert_eq!(full.model, "pgrd");
        assert_eq!(full.network_path, Some("forward-only"));
        assert_close(&eval(&net, Some(full.steps), "whole").unwrap(), &full);
        // The autograd path predicts the same up to float rounding, on the whole window and
        // on many short predictions batched together (0.00001 cm: forty times the largest
        // difference measured on these short windows, 2.4e-7 cm; the tables print 0.001 cm).
        for horizon in [None, Some(3)] {
            let fast = eval_by(&net, horizon, "fast", false).unwrap();
            let slow = eval_by(&net, horizon, "slow", true).unwrap();
            assert_eq!(slow.network_path, Some("autograd"));
            assert_eq!(fast.per_episode.len(), slow.per_episode.len());
            for (x, y) in fast.per_episode.iter().zip(&slow.per_episode) {
                assert!(
                    (x.mde_cm - y.mde_cm).abs() < 1e-5,
                    "{horizon:?}, episode {}: {} against {}",
                    x.episode,
                    x.mde_cm,
                    y.mde_cm
                );
            }
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
