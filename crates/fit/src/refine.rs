//! The paper's "Diff. Spring-Mass" baseline (PhysTwin's second stage): after CMA-ES has fitted
//! the five global parameters, the stiffness is let vary over the object and refined by
//! gradient descent through the simulator.
//!
//! The varying stiffness is a [`StiffnessField`]: one log factor per tracked particle, every
//! spring scaled by the geometric mean of its ends' factors, hidden and interior particles
//! taking their nearest tracked particle's. Tracked particles are the same material points in
//! every episode, so one field serves every episode, whatever springs its start frame gives
//! (the paper registers one canonical spring graph to each episode for the same reason).
//!
//! Each iteration rolls `batch` training scenes out with the step tapes kept, takes the mean
//! squared position error over the window (the CMA-ES stage's loss), carries its adjoint back
//! through every step ([`springs::StepAdjoint::vjp_stiffness`]) and moves the field by Adam.
//! With [`RefineConfig::scene_norm`] every scene's gradient is scaled to unit norm first.
//! Contacts switching within a step are not differentiable: the gradient is that of the smooth
//! piece each step is on. The field with the lowest loss over all training scenes, checked
//! every [`RefineConfig::check_every`] iterations, is kept.
//!
//! The field can sit on a backbone that carries effects (a diagnosis's refitted drag, bending,
//! ...): `model` builds those options and the field is added to them. Every effect must be one
//! the adjoint differentiates (not [`springs::EffectAdjoint::HeldFixed`]); a refinement
//! through a model whose adjoint holds some effect fixed is refused.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use glam::Vec3;
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use scene::Scene;
use serde::{Deserialize, Serialize};
use springs::{BackboneOptions, SpringParams, State, StepTape, StiffnessField};

use crate::FitError;
use crate::run::checkpoint_error;

/// Settings of a stiffness refinement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineConfig {
    /// Adam iterations.
    pub iterations: usize,
    /// Training scenes per iteration.
    pub batch: usize,
    /// Adam step size on the log factors.
    pub learning_rate: f64,
    /// Bound on every log factor (3: stiffness between e⁻³ ≈ 1/20 and 20 times the fitted).
    pub max_log_factor: f32,
    /// Steps of each window rolled out and scored (`None`: the whole window). Shorter windows
    /// keep the adjoint from growing over long recordings.
    pub steps: Option<usize>,
    /// How often (iterations) the field is scored on every training scene.
    pub check_every: usize,
    /// Seed of the scene sampling.
    pub seed: u64,
    /// Scale each scene's gradient to unit norm before the batch mean ([`batch_gradient`]):
    /// one scene whose contacts switched, or whose adjoint grew, then cannot take Adam's step
    /// and inflate its second moment for the iterations after. On by default; files written
    /// before it existed read back with it off (they used the plain mean).
    #[serde(default)]
    pub scene_norm: bool,
}

impl Default for RefineConfig {
    fn default() -> Self {
        RefineConfig {
            iterations: 200,
            batch: 4,
            learning_rate: 0.05,
            max_log_factor: 3.0,
            steps: None,
            check_every: 25,
            seed: 0,
            scene_norm: true,
        }
    }
}

/// One iteration's record.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineStep {
    /// Iteration index.
    pub iteration: usize,
    /// Mean loss of the iteration's batch before its update, m² (NaN when every rollout of the
    /// batch failed).
    #[serde(deserialize_with = "null_as_nan")]
    pub batch_loss_m2: f64,
    /// Norm of the batch's mean gradient with respect to the log factors, before any
    /// per-scene normalisation (not finite: the update was skipped).
    #[serde(deserialize_with = "null_as_nan")]
    pub grad_norm: f64,
    /// Scenes of the batch whose rollout failed (left out of the update).
    pub failed: usize,
    /// Loss over every training scene, m², on the iterations where it was checked (read back
    /// as `None` where it was not finite: JSON has no infinity).
    pub train_loss_m2: Option<f64>,
}

/// The result of a refinement.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RefineOutcome {
    /// The kept field: log stiffness factor per tracked particle.
    pub log_factor: Vec<f32>,
    /// Its loss over every training scene, m².
    #[serde(deserialize_with = "null_as_nan")]
    pub best_loss_m2: f64,
    /// The loss of the fitted backbone without a field (all factors 0), m² (infinite when a
    /// training episode's rollout fails).
    #[serde(deserialize_with = "null_as_nan")]
    pub initial_loss_m2: f64,
    /// Iteration after which the kept field was checked (`None`: the zero field).
    pub best_iteration: Option<usize>,
    /// Every iteration.
    pub history: Vec<RefineStep>,
    /// The settings.
    pub config: RefineConfig,
    /// Wall time, s (summed over resumed sessions).
    pub wall_s: f64,
}

#[derive(Serialize, Deserialize)]
struct Checkpoint {
    config: RefineConfig,
    scenes: usize,
    log_factor: Vec<f32>,
    adam_m: Vec<f64>,
    adam_v: Vec<f64>,
    outcome: RefineOutcome,
}

/// The backbone options of a field (for [`Scene::rollout`] and everything that builds a
/// backbone of a refined run).
pub fn field_options(log_factor: &[f32]) -> BackboneOptions {
    with_field(&BackboneOptions::default, log_factor)
}

/// The backbone options of a model before its field: effects and masses
/// ([`BackboneOptions::default`] for the plain spring-mass backbone).
pub type ModelOptions = dyn Fn() -> BackboneOptions + Sync;

/// The field's options added to a model's.
fn with_field(model: &ModelOptions, log_factor: &[f32]) -> BackboneOptions {
    let mut options = model();
    options.effects.push(Box::new(StiffnessField {
        log_factor: Arc::new(log_factor.to_vec()),
    }));
    options
}

/// Refines a per-particle stiffness field on `scenes` (every one tracking the same number of
/// particles) for the fitted `params` of the backbone `model` builds (its effects, if any, at
/// their fixed values). With a checkpoint path, the state is written
/// atomically at every check; a later call with the same settings resumes from it and ends
/// where the uninterrupted run would have. `on_step` sees every iteration (for progress).
///
/// ```no_run
/// # fn demo(train: &[scene::Scene], params: &springs::SpringParams) -> Result<(), fit::FitError> {
/// let cfg = fit::RefineConfig { iterations: 100, ..Default::default() };
/// let plain = springs::BackboneOptions::default;
/// let out = fit::refine_stiffness(train, params, &plain, &cfg, None, &mut |_| {})?;
/// println!("{:.3e} -> {:.3e} m²", out.initial_loss_m2, out.best_loss_m2);
/// # Ok(()) }
/// ```
pub fn refine_stiffness(
    scenes: &[Scene],
    params: &SpringParams,
    model: &ModelOptions,
    config: &RefineConfig,
    checkpoint: Option<&Path>,
    on_step: &mut dyn FnMut(&RefineStep),
) -> Result<RefineOutcome, FitError> {
    let first = scenes.first().ok_or(FitError::NoScenes)?;
    let tracked = first.tracked;
    if let Some(s) = scenes.iter().find(|s| s.tracked != tracked) {
        return Err(FitError::Config(format!(
            "scenes track different particle counts ({} and {tracked}); one field needs the same",
            s.tracked
        )));
    }
    if config.iterations == 0
        || config.batch == 0
        || config.check_every == 0
        || config.steps == Some(0)
    {
        return Err(FitError::Config(
            "iterations, batch, check interval and steps must be at least 1".into(),
        ));
    }
    if !(config.learning_rate > 0.0 && config.max_log_factor > 0.0) {
        return Err(FitError::Config(
            "learning rate and factor bound must be > 0".into(),
        ));
    }
    let bb = first.backbone(params, &first.sim_config(), model())?;
    let held = bb.held_fixed_effects();
    if !held.is_empty() {
        return Err(FitError::Config(format!(
            "the adjoint holds the forces of {} fixed, so the field's gradient would be wrong; \
             refine a model without them",
            held.join(", ")
        )));
    }
    let t0 = Instant::now();
    let all_loss = |a: &[f32]| -> f64 {
        let losses: Vec<f64> = scenes
            .par_iter()
            .map(|s| {
                scene_gradient(s, params, model, a, config.steps, false)
                    .map_or(f64::INFINITY, |g| g.0)
            })
            .collect();
        losses.iter().sum::<f64>() / scenes.len() as f64
    };
    let (mut a, mut m, mut v, mut outcome) = match checkpoint.filter(|p| p.is_file()) {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(|e| checkpoint_error(path, e))?;
            let ck: Checkpoint =
                serde_json::from_str(&text).map_err(|e| checkpoint_error(path, e))?;
            let same = RefineConfig {
                iterations: config.iterations,
                ..ck.config.clone()
            };
            if same != *config || ck.scenes != scenes.len() || ck.log_factor.len() != tracked {
                return Err(checkpoint_error(
                    path,
                    "was written by a refinement with other settings or data; remove it to start afresh",
                ));
            }
            (ck.log_factor, ck.adam_m, ck.adam_v, ck.outcome)
        }
        None => {
            let zero = vec![0.0f32; tracked];
            let initial = all_loss(&zero);
            let outcome = RefineOutcome {
                log_factor: zero.clone(),
                best_loss_m2: initial,
                initial_loss_m2: initial,
                best_iteration: None,
                history: Vec::new(),
                config: config.clone(),
                wall_s: 0.0,
            };
            (zero, vec![0.0; tracked], vec![0.0; tracked], outcome)
        }
    };
    let wall_before = outcome.wall_s;
    let batch = config.batch.min(scenes.len());
    let (beta1, beta2) = (0.9f64, 0.999f64);
    while outcome.history.len() < config.iterations {
        let it = outcome.history.len();
        let mut rng = ChaCha8Rng::seed_from_u64(
            config.seed ^ (it as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let mut picked = sample(&mut rng, scenes.len(), batch).into_vec();
        picked.sort_unstable();
        let results: Vec<Option<(f64, Vec<f64>)>> = picked
            .par_iter()
            .map(|&s| scene_gradient(&scenes[s], params, model, &a, config.steps, true).ok())
            .collect();
        let ok: Vec<&(f64, Vec<f64>)> = results.iter().flatten().collect();
        let failed = results.len() - ok.len();
        // Every rollout of the batch failed: no loss to report.
        let loss = if ok.is_empty() {
            f64::NAN
        } else {
            ok.iter().map(|(l, _)| l).sum::<f64>() / ok.len() as f64
        };
        let grads: Vec<&[f64]> = ok.iter().map(|(_, g)| g.as_slice()).collect();
        let grad = batch_gradient(&grads, tracked, config.scene_norm);
        // Recorded before any normalisation: the size of the gradient is what tells a useful
        // one from a grown one.
        let norm = |g: &[f64]| g.iter().map(|x| x * x).sum::<f64>().sqrt();
        let grad_norm = if config.scene_norm {
            norm(&batch_gradient(&grads, tracked, false))
        } else {
            norm(&grad)
        };
        // A gradient the adjoint let grow to infinity says nothing about the direction.
        if !ok.is_empty() && grad_norm.is_finite() {
            let step = (it + 1) as i32;
            let lr =
                config.learning_rate * (1.0 - beta2.powi(step)).sqrt() / (1.0 - beta1.powi(step));
            for i in 0..tracked {
                m[i] = beta1 * m[i] + (1.0 - beta1) * grad[i];
                v[i] = beta2 * v[i] + (1.0 - beta2) * grad[i] * grad[i];
                let update = lr * m[i] / (v[i].sqrt() + 1e-12);
                let bound = f64::from(config.max_log_factor);
                a[i] = ((f64::from(a[i]) - update).clamp(-bound, bound)) as f32;
            }
        }
        let check = (it + 1) % config.check_every == 0 || it + 1 == config.iterations;
        let train_loss = check.then(|| all_loss(&a));
        // A best read back from a checkpoint as NaN (it was infinite) is beaten by any finite.
        let beats =
            |l: &f64| l.is_finite() && (outcome.best_loss_m2.is_nan() || *l < outcome.best_loss_m2);
        if let Some(l) = train_loss.filter(beats) {
            outcome.best_loss_m2 = l;
            outcome.log_factor = a.clone();
            outcome.best_iteration = Some(it);
        }
        let record = RefineStep {
            iteration: it,
            batch_loss_m2: loss,
            grad_norm,
            failed,
            train_loss_m2: train_loss,
        };
        outcome.history.push(record.clone());
        outcome.wall_s = wall_before + t0.elapsed().as_secs_f64();
        if let (true, Some(path)) = (check, checkpoint) {
            let ck = Checkpoint {
                config: config.clone(),
                scenes: scenes.len(),
                log_factor: a.clone(),
                adam_m: m.clone(),
                adam_v: v.clone(),
                outcome: outcome.clone(),
            };
            let text = serde_json::to_string(&ck).map_err(|e| checkpoint_error(path, e))?;
            dataset::write_atomic(path, text.as_bytes()).map_err(|e| checkpoint_error(path, e))?;
        }
        on_step(&record);
    }
    outcome.config = config.clone();
    Ok(outcome)
}

/// The batch's update direction: the mean of the scenes' gradients (`len` entries each), every
/// one first scaled to unit norm when `scene_norm`. A scene whose gradient is zero or not finite
/// keeps it unscaled (a non-finite one makes the mean non-finite, and the update is skipped).
///
/// ```
/// let g = fit::batch_gradient(&[&[3.0, 4.0], &[0.0, 1e6]], 2, true);
/// assert!((g[0] - 0.3).abs() < 1e-12 && (g[1] - 0.9).abs() < 1e-12);
/// ```
pub fn batch_gradient(grads: &[&[f64]], len: usize, scene_norm: bool) -> Vec<f64> {
    let mut mean = vec![0.0f64; len];
    for g in grads {
        let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
        let scale = if scene_norm && norm.is_finite() && norm > 0.0 {
            1.0 / norm
        } else {
            1.0
        };
        for (acc, x) in mean.iter_mut().zip(g.iter()) {
            *acc += x * scale;
        }
    }
    let count = grads.len().max(1) as f64;
    for x in &mut mean {
        *x /= count;
    }
    mean
}

/// JSON has no NaN or infinity: `serde_json` writes them as `null`, read back here as NaN, so
/// a checkpoint or run file with a skipped update survives the round trip.
fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Option::<f64>::deserialize(d).map(|v| v.unwrap_or(f64::NAN))
}

/// The loss of one scene (mean squared position error over the first `steps` steps and the
/// particles seen, m²) with the field `log_factor` added to `model`'s backbone, and, when
/// `with_gradient`, its gradient with respect to every log factor. Errors when the rollout
/// fails or is not finite.
pub fn scene_gradient(
    scene: &Scene,
    params: &SpringParams,
    model: &ModelOptions,
    log_factor: &[f32],
    steps: Option<usize>,
    with_gradient: bool,
) -> Result<(f64, Vec<f64>), FitError> {
    let bb = scene.backbone(params, &scene.sim_config(), with_field(model, log_factor))?;
    let steps = steps.map_or(scene.window.steps, |s| s.min(scene.window.steps));
    let n = bb.num_particles();
    let tracked = scene.tracked;
    let mut state: State = scene.init.clone();
    let mut scratch = bb.scratch();
    let mut tapes: Vec<StepTape> = Vec::with_capacity(if with_gradient { steps } else { 0 });
    let mut residuals: Vec<Vec<Vec3>> = Vec::with_capacity(steps);
    let (mut sum, mut count) = (0.0f64, 0usize);
    for t in 0..steps {
        let (from, to) = match (scene.actions.frame(t), scene.actions.frame(t + 1)) {
            (Some(f), Some(g)) => (f, g),
            _ => break,
        };
        if with_gradient {
            let mut tape = StepTape::new();
            bb.step_taped(&mut state, from, to, &mut scratch, &mut tape)?;
            tapes.push(tape);
        } else {
            bb.step(&mut state, from, to, &mut scratch)?;
        }
        let vis = &scene.visible[t];
        let mut r = vec![Vec3::ZERO; tracked];
        for (i, (x, y)) in state.x[..tracked].iter().zip(&scene.truth[t]).enumerate() {
            if vis[i] {
                let d = *x - *y;
                sum += f64::from(d.length_squared());
                count += 1;
                r[i] = d;
            }
        }
        residuals.push(r);
    }
    let loss = sum / count.max(1) as f64;
    if !loss.is_finite() || state.x.iter().any(|p| !p.is_finite()) {
        return Err(FitError::Config("the rollout is not finite".into()));
    }
    if !with_gradient {
        return Ok((loss, Vec::new()));
    }
    let scale = 2.0 / count.max(1) as f32;
    let adjoint = bb.step_adjoint();
    let (mut gx, mut gv) = (vec![Vec3::ZERO; n], vec![Vec3::ZERO; n]);
    let mut gk = vec![0.0f32; bb.springs().len()];
    for (tape, r) in tapes.iter().zip(&residuals).rev() {
        for (g, d) in gx.iter_mut().zip(r) {
            *g += *d * scale;
        }
        adjoint.vjp_stiffness(tape, &mut gx, &mut gv, &mut gk)?;
    }
    // k_s = k⁰_s exp((a_i + a_j) / 2): ∂L/∂a_i gets half of k_s ∂L/∂k_s from each spring.
    let owner = StiffnessField::owners(tracked, scene.init.x.as_slice());
    let mut grad = vec![0.0f64; tracked];
    for ((&[i, j], &k), &g) in bb.springs().iter().zip(bb.stiffness()).zip(&gk) {
        let half = 0.5 * f64::from(k) * f64::from(g);
        grad[owner[i as usize]] += half;
        grad[owner[j as usize]] += half;
    }
    Ok((loss, grad))
}
