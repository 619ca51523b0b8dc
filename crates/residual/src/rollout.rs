//! Hybrid rollouts: backbone step, then the network's bounded residual, fed back as the next
//! state. Used for evaluation (detached, one step at a time) and for training (one graph
//! through all steps of a segment).

use std::sync::Arc;

use candle_core::{DType, Tensor};
use dataset::Episode;
use glam::Vec3;
use scene::Scene;
use serde::{Deserialize, Serialize};
use springs::{Actions, Backbone, SimError, State, StepTape};

use crate::backbone_op::BackboneStep;
use crate::loss::{TrainLoss, step_loss};
use crate::model::{
    GRIPPER_INPUTS, GROUND_INPUTS, REST_INPUTS, ResidualNet, gripper_inputs, ground_inputs,
    rest_inputs,
};
use crate::nn::Pass;
use crate::serialize::{CURVES, Structure};
use crate::{ResidualError, ResidualKind, Result};

/// Hybrid positions farther than this from the object's centre mean the rollout diverged, m.
pub(crate) const DIVERGED_M: f32 = 100.0;

/// The two frames before a rollout's start (the network's history inputs).
#[derive(Clone, Debug, PartialEq)]
pub struct History {
    /// Positions at `t − 1` and `t − 2`, m.
    pub x: [Vec<Vec3>; 2],
    /// Velocities at `t − 1` and `t − 2`, m/s.
    pub v: [Vec<Vec3>; 2],
}

impl History {
    /// Constant-velocity extrapolation backwards from `state` (used where no earlier frame
    /// exists: hidden or interior particles, or a start at frame 1).
    pub fn extrapolated(state: &State, dt: f32) -> Self {
        let back = |k: f32| {
            state
                .x
                .iter()
                .zip(&state.v)
                .map(|(x, v)| *x - *v * (k * dt))
                .collect()
        };
        History {
            x: [back(1.0), back(2.0)],
            v: [state.v.clone(), state.v.clone()],
        }
    }

    /// History of `scene` read from its episode: tracked particles take the recorded frames
    /// `start − 1` and `start − 2` as the scene reads them ([`Scene::start_frame`]: occluded
    /// points carried along, by default), velocities by finite difference; the rest is
    /// extrapolated.
    pub fn from_episode(scene: &Scene, episode: &Episode, fps: f32) -> Result<Self> {
        let start = scene.window.start;
        if episode.particles() != scene.tracked || start >= episode.frames() {
            return Err(ResidualError::Input(format!(
                "episode has {} particles / {} frames, scene tracks {} from frame {start}",
                episode.particles(),
                episode.frames(),
                scene.tracked
            )));
        }
        let mut h = Self::extrapolated(&scene.init, 1.0 / fps);
        // The frames as the scene read its start (occluded points carried, by default).
        let frame = |t: Option<usize>| t.map(|t| scene.start_frame(episode, t));
        let (f1, f2, f3) = (
            frame(start.checked_sub(1)),
            frame(start.checked_sub(2)),
            frame(start.checked_sub(3)),
        );
        for i in 0..scene.tracked {
            if let Some(f1) = &f1 {
                h.x[0][i] = f1[i];
            }
            if let Some(f2) = &f2 {
                h.x[1][i] = f2[i];
                h.v[0][i] = (h.x[0][i] - h.x[1][i]) * fps;
                h.v[1][i] = h.v[0][i];
            } else {
                h.x[1][i] = h.x[0][i] - h.v[0][i] / fps;
            }
            if let Some(f3) = &f3 {
                h.v[1][i] = (h.x[1][i] - f3[i]) * fps;
            }
        }
        Ok(h)
    }
}

/// What a hybrid rollout returns.
#[derive(Debug)]
pub struct HybridRollout {
    /// Positions of all simulated particles after each step, m.
    pub positions: Vec<Vec<Vec3>>,
    /// Velocities of all simulated particles after each step, m/s.
    pub velocities: Vec<Vec<Vec3>>,
    /// Sum over steps of the mean squared distance to the truth (cm²), with its graph when
    /// the rollout was run for training.
    pub loss: Option<Tensor>,
}

/// Options of [`hybrid_rollout`].
#[derive(Clone, Copy, Debug)]
pub struct RolloutOptions {
    /// Steps to run (at most the scene's window).
    pub steps: usize,
    /// Keep the autograd graph through all steps and compute the loss.
    pub train: bool,
    /// Curve each transformer block attends along (`curves[b % 4]`).
    pub curves: [usize; CURVES],
    /// With `train`: how a residual's effect on later steps reaches the loss.
    pub sim_gradient: SimGradient,
}

/// How gradients cross the backbone's step in a training rollout (the backbone itself is not
/// differentiable).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SimGradient {
    /// Not at all (the paper's training): the backbone's prediction is a constant, so a
    /// step's residual is scored only on that step's positions (and reaches later steps only
    /// through the network's inputs). A velocity residual keeps moving the object afterwards,
    /// which this loss never charges it for.
    #[default]
    Detached,
    /// Through the Jacobian of free flight, `x' = x + v' dt`, `v' = v + a dt` with the
    /// acceleration `a` taken as independent of the state: every later step's loss sees the
    /// displacement a velocity residual keeps causing (springs, damping and contacts, which
    /// absorb part of it, are ignored). Held particles carry nothing. The forward values are
    /// unchanged.
    FreeFlight,
    /// Through the backbone step's own adjoint (`springs::StepAdjoint`: springs, dashpots,
    /// ground contact and grasp linearised along the step actually taken): a later step's loss
    /// sees how far the backbone carries, damps or undoes a residual. The adjoint costs about
    /// four backbone steps per step (`docs/BENCHMARKS.md`). The forward values are unchanged.
    Adjoint,
}

impl Default for RolloutOptions {
    fn default() -> Self {
        RolloutOptions {
            steps: usize::MAX,
            train: false,
            curves: [0, 1, 2, 3],
            sim_gradient: SimGradient::Detached,
        }
    }
}

pub(crate) fn to_tensor(v: &[Vec3], dev: &candle_core::Device) -> Result<Tensor> {
    let flat: Vec<f32> = v.iter().flat_map(|p| p.to_array()).collect();
    Ok(Tensor::from_vec(flat, (v.len(), 3), dev)?)
}

fn to_vec3(t: &Tensor) -> Result<Vec<Vec3>> {
    let flat: Vec<f32> = t.flatten_all()?.to_vec1()?;
    Ok(flat
        .chunks_exact(3)
        .map(|c| Vec3::new(c[0], c[1], c[2]))
        .collect())
}

/// Runs the hybrid model (backbone + residual network) over `scene`'s window.
///
/// Each step: the backbone advances the detached state; the network sees the current state,
/// two history frames and the backbone's prediction (positions centred on the current mean,
/// velocities times `velocity_scale`) and returns a residual bounded by `residual_scale` per
/// axis; particles held by a closed gripper get none. Returns [`ResidualError::Diverged`] when
/// the state stops being finite and bounded.
pub fn hybrid_rollout(
    net: &ResidualNet,
    backbone: &Backbone,
    scene: &Scene,
    history: &History,
    opts: RolloutOptions,
) -> Result<HybridRollout> {
    hybrid_rollout_with_loss(net, backbone, scene, history, opts, TrainLoss::Mse)
}

/// [`hybrid_rollout`] whose training loss (with `opts.train`) is `kind`.
pub(crate) fn hybrid_rollout_with_loss(
    net: &ResidualNet,
    backbone: &Backbone,
    scene: &Scene,
    history: &History,
    opts: RolloutOptions,
    kind: TrainLoss,
) -> Result<HybridRollout> {
    let n = scene.particles();
    if backbone.num_particles() != n {
        return Err(ResidualError::Input(format!(
            "scene has {n} particles, backbone {}",
            backbone.num_particles()
        )));
    }
    let steps = opts.steps.min(scene.window.steps);
    let loss = |step: usize, x: &Tensor| step_loss(kind, scene, step, x);
    run(
        net,
        backbone,
        &scene.init,
        history,
        &scene.actions,
        steps,
        opts,
        opts.train.then_some(&loss as &LossFn<'_>),
    )
}

/// The training loss of the backbone alone on `scene`'s first `steps` steps (no residual),
/// the yardstick of a training rollout's loss: a network that learns something useful scores
/// below it on the same segments. `None` when the backbone does not stay finite.
pub(crate) fn backbone_loss(
    backbone: &Backbone,
    scene: &Scene,
    steps: usize,
    kind: TrainLoss,
) -> Result<Option<f64>> {
    let dev = candle_core::Device::Cpu;
    let mut sim = scene.init.clone();
    let mut scratch = backbone.scratch();
    let mut total = 0.0;
    for step in 0..steps.min(scene.window.steps) {
        let (Some(from), Some(to)) = (scene.actions.frame(step), scene.actions.frame(step + 1))
        else {
            return Err(ResidualError::Input(format!(
                "no action frame for step {step}"
            )));
        };
        match backbone.step(&mut sim, from, to, &mut scratch) {
            Ok(()) => {}
            Err(SimError::NonFinite { .. }) => return Ok(None),
            Err(e) => return Err(ResidualError::Sim(e)),
        }
        let l = step_loss(kind, scene, step, &to_tensor(&sim.x, &dev)?)?;
        total += f64::from(l.to_scalar::<f32>()?);
    }
    Ok(total.is_finite().then_some(total))
}

/// Predicts the positions of all particles of `backbone` after each of `steps` steps of
/// `actions` (frame `k` to `k + 1` is step `k`), starting from `init` with `history` before it:
/// the hybrid model without ground truth, e.g. as a planner's forward model. Held particles come
/// from [`Backbone::held`], the step length from the backbone's configuration.
///
/// This runs the network through the same autograd operations as [`hybrid_rollout`] (what
/// `eval --autograd` scores); [`crate::predict_batch`] with one job predicts the same up to
/// float rounding through forward-only kernels, two to three times faster, and is what `eval`
/// scores by default (`docs/BENCHMARKS.md`).
///
/// ```no_run
/// # fn main() -> Result<(), residual::ResidualError> {
/// # let (net, backbone, init, actions): (residual::ResidualNet, springs::Backbone, springs::State, springs::Actions) = todo!();
/// let history = residual::History::extrapolated(&init, backbone.config().step_dt);
/// let positions = residual::predict(&net, &backbone, &init, &history, &actions, 10)?;
/// assert_eq!(positions.len(), 10);
/// # Ok(()) }
/// ```
pub fn predict(
    net: &ResidualNet,
    backbone: &Backbone,
    init: &State,
    history: &History,
    actions: &Actions,
    steps: usize,
) -> Result<Vec<Vec<Vec3>>> {
    if steps >= actions.num_frames() {
        return Err(ResidualError::Input(format!(
            "{steps} steps need {} action frames, got {}",
            steps + 1,
            actions.num_frames()
        )));
    }
    let opts = RolloutOptions {
        steps,
        ..RolloutOptions::default()
    };
    Ok(run(net, backbone, init, history, actions, steps, opts, None)?.positions)
}

/// Loss of one step given the hybrid positions (with their graph).
type LossFn<'a> = dyn Fn(usize, &Tensor) -> Result<Tensor> + 'a;

#[allow(clippy::too_many_arguments)]
fn run(
    net: &ResidualNet,
    backbone: &Backbone,
    init: &State,
    history: &History,
    actions: &Actions,
    steps: usize,
    opts: RolloutOptions,
    step_loss: Option<&LossFn<'_>>,
) -> Result<HybridRollout> {
    let cfg = net.config();
    let dev = net.device().clone();
    let n = backbone.num_particles();
    if init.x.len() != n
        || init.v.len() != n
        || history.x.iter().chain(&history.v).any(|h| h.len() != n)
    {
        return Err(ResidualError::Input(format!(
            "backbone has {n} particles, state {}, history {}",
            init.x.len(),
            history.x[0].len()
        )));
    }
    let held = backbone.held();
    let train = step_loss.is_some();
    if train && net.ensemble_size() > 1 {
        return Err(ResidualError::Config(
            "an ensemble cannot be trained as a whole: train its members, then combine them".into(),
        ));
    }
    let dt = backbone.config().step_dt;
    let vs = f64::from(cfg.velocity_scale);
    let mut scratch = backbone.scratch();
    // With the adjoint gradient each step is taped and becomes a graph node.
    let adjoint = (train && opts.sim_gradient == SimGradient::Adjoint)
        .then(|| Arc::new(backbone.step_adjoint()));
    let mut tape = adjoint.as_ref().map(|_| StepTape::new());
    let mut sim = init.clone();
    let mut x = to_tensor(&sim.x, &dev)?;
    let mut v = to_tensor(&sim.v, &dev)?;
    let mut hx = [
        to_tensor(&history.x[0], &dev)?,
        to_tensor(&history.x[1], &dev)?,
    ];
    let mut hv = [
        to_tensor(&history.v[0], &dev)?,
        to_tensor(&history.v[1], &dev)?,
    ];
    // One temporal window per member of an ensemble (one for a single network).
    let mut windows: Vec<Vec<Tensor>> = vec![Vec::with_capacity(cfg.window); net.ensemble_size()];
    let mut positions = Vec::with_capacity(steps);
    let mut velocities = Vec::with_capacity(steps);
    let mut loss: Option<Tensor> = None;
    // The rest shape does not change along a rollout: its channels are built once.
    let rest = if cfg.rest_inputs {
        let mut r = Vec::with_capacity(n * REST_INPUTS);
        rest_inputs(backbone.rest_positions(), &mut r);
        Some(Tensor::from_vec(r, (n, REST_INPUTS), &dev)?)
    } else {
        None
    };
    for step in 0..steps {
        let (Some(from), Some(to)) = (actions.frame(step), actions.frame(step + 1)) else {
            return Err(ResidualError::Input(format!(
                "no action frame for step {step}"
            )));
        };
        let current = sim.x.clone();
        let stepped = match tape.as_mut() {
            Some(t) => backbone.step_taped(&mut sim, from, to, &mut scratch, t),
            None => backbone.step(&mut sim, from, to, &mut scratch),
        };
        stepped.map_err(|e| match e {
            SimError::NonFinite { .. } | SimError::Diverged { .. } => ResidualError::Diverged {
                step,
                what: e.to_string(),
            },
            e => ResidualError::Sim(e),
        })?;
        let centre = current.iter().sum::<Vec3>() / n.max(1) as f32;
        let c = Tensor::from_slice(&centre.to_array(), (1, 3), &dev)?;
        let free: Vec<f32> = held
            .iter()
            .map(|&g| {
                let held = g >= 0 && from.closed.get(g as usize).copied().unwrap_or(false);
                if held { 0.0 } else { 1.0 }
            })
            .collect();
        let free = Tensor::from_vec(free, (n, 1), &dev)?;
        // Which particles the residual moves: the free ones, or all with `held_residual`.
        let corrected = if cfg.held_residual {
            Tensor::ones((n, 1), DType::F32, &dev)?
        } else {
            free.clone()
        };
        let mut x_sim = to_tensor(&sim.x, &dev)?;
        let mut v_sim = to_tensor(&sim.v, &dev)?;
        if let (Some(adjoint), Some(t)) = (&adjoint, tape.take()) {
            let xv = Tensor::cat(&[&x, &v], 1)?;
            let out = xv.apply_op1(BackboneStep::new(adjoint.clone(), t, &sim.x, &sim.v))?;
            x_sim = out.narrow(1, 0, 3)?;
            v_sim = out.narrow(1, 3, 3)?;
            tape = Some(StepTape::new());
        }
        if train && opts.sim_gradient == SimGradient::FreeFlight {
            // `a − a.detach()` is zero with `a`'s gradient: the values stay the backbone's.
            let gx = (&x - x.detach())?.broadcast_mul(&free)?;
            let gv = (&v - v.detach())?.broadcast_mul(&free)?;
            x_sim = ((x_sim + gx)? + (&gv * f64::from(dt))?)?;
            v_sim = (v_sim + gv)?;
        }
        let pos = x.broadcast_sub(&c)?;
        // Earlier and predicted positions enter as displacements from the current position,
        // expressed like velocities (m per step / dt, times `velocity_scale`): the corrections
        // the network must find are centimetres, which absolute coordinates (tens of
        // centimetres) would bury.
        let ds = vs / f64::from(dt);
        let mut parts = vec![
            pos.clone(),
            (&v * vs)?,
            ((&hx[0] - &x)? * ds)?,
            ((&hx[1] - &x)? * (ds / 2.0))?,
            (&hv[0] * vs)?,
            (&hv[1] * vs)?,
            ((&x_sim - &x)? * ds)?,
            (&v_sim * vs)?,
        ];
        if cfg.gripper_inputs {
            let mut g = Vec::with_capacity(n * GRIPPER_INPUTS);
            gripper_inputs(&current, from, to, dt, cfg.velocity_scale, &mut g);
            parts.push(Tensor::from_vec(g, (n, GRIPPER_INPUTS), &dev)?);
        }
        if cfg.ground_inputs {
            let mut g = Vec::with_capacity(n * GROUND_INPUTS);
            ground_inputs(&current, backbone.config().ground_z, &mut g);
            parts.push(Tensor::from_vec(g, (n, GROUND_INPUTS), &dev)?);
        }
        if let Some(r) = &rest {
            parts.push(r.clone());
        }
        let feats = Tensor::cat(&parts, 1)?;
        debug_assert_eq!(feats.dim(1)?, cfg.input_dim());
        let centred: Vec<Vec3> = current.iter().map(|p| *p - centre).collect();
        let st = Structure::new(
            &centred,
            cfg.enc_channels.len(),
            cfg.grid_m,
            cfg.pool_grid_m,
            cfg.patch,
            &dev,
        )?;
        let mut deltas = Vec::with_capacity(windows.len());
        for (member, window) in net.ensemble_members().zip(&mut windows) {
            window.push(member.decode(&feats, &pos, &st, opts.curves, Pass::Grad)?);
            if window.len() > cfg.window {
                window.remove(0);
            }
            deltas.push(member.aggregate(window, Pass::Grad)?);
        }
        let delta =
            crate::ensemble::combine(deltas, net.ensemble_rule())?.broadcast_mul(&corrected)?;
        let (nx, nv) = match cfg.residual {
            ResidualKind::Velocity => ((&x_sim + (&delta * f64::from(dt))?)?, (&v_sim + &delta)?),
            ResidualKind::Position => ((&x_sim + (&delta * f64::from(dt))?)?, v_sim.clone()),
        };
        let (nx, nv) = if train {
            (nx, nv)
        } else {
            (nx.detach(), nv.detach())
        };
        if !train {
            for w in windows.iter_mut().flatten() {
                *w = w.detach();
            }
        }
        sim.x = to_vec3(&nx)?;
        sim.v = to_vec3(&nv)?;
        if let Some(i) = sim.x.iter().zip(&sim.v).position(|(p, q)| {
            !(p.is_finite() && q.is_finite()) || (*p - centre).length() > DIVERGED_M
        }) {
            return Err(ResidualError::Diverged {
                step,
                what: format!("particle {i} at {:?} m, {:?} m/s", sim.x[i], sim.v[i]),
            });
        }
        if let Some(step_loss) = step_loss {
            let term = step_loss(step, &nx)?;
            loss = Some(match loss {
                Some(l) => (l + term)?,
                None => term,
            });
        }
        let [hx0, _] = hx;
        let [hv0, _] = hv;
        hx = [x, hx0];
        hv = [v, hv0];
        x = nx;
        v = nv;
        positions.push(sim.x.clone());
        velocities.push(sim.v.clone());
    }
    Ok(HybridRollout {
        positions,
        velocities,
        loss,
    })
}
