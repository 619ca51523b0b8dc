//! Many hybrid rollouts advanced together (a planner's population of candidates): groups of
//! rollouts step in lockstep with one network call per step for all clouds of a group, through
//! candle's fused forward-only kernels. Measured costs and the choice of group size:
//! `docs/plan-log.md`, "Batched network evaluation".

use candle_core::Tensor;
use glam::Vec3;
use rayon::prelude::*;
use springs::{Actions, Backbone, Scratch, SimError, State};

use crate::model::{
    GRIPPER_INPUTS, GROUND_INPUTS, INPUTS, REST_INPUTS, ResidualNet, gripper_inputs, ground_inputs,
    rest_inputs,
};
use crate::nn::Pass;
use crate::rollout::{DIVERGED_M, History};
use crate::serialize::{Layout, Structure};
use crate::{ResidualError, ResidualKind, Result};

/// One rollout of a [`predict_batch`] call: what [`crate::predict`] takes.
#[derive(Clone, Copy, Debug)]
pub struct PredictJob<'a> {
    /// The backbone (jobs may have different backbones and particle counts).
    pub backbone: &'a Backbone,
    /// State at the start.
    pub init: &'a State,
    /// The two frames before the start.
    pub history: &'a History,
    /// Gripper actions; at least `steps + 1` frames.
    pub actions: &'a Actions,
    /// Steps to predict.
    pub steps: usize,
}

/// Positions after each step of one job, or why that job failed.
pub type JobResult = Result<Vec<Vec<Vec3>>>;

/// Runs [`crate::predict`] for every job, evaluating the network on several clouds at once.
///
/// Consecutive jobs form groups of at most 600 particles (at least one job each); a group
/// advances its jobs in lockstep with one network evaluation per step on all its clouds, and
/// groups run in parallel on the current rayon pool, each on one thread. Each cloud keeps its
/// own serialization, attention patches, pooling clusters, centre and temporal window, so every
/// job's prediction equals its own `predict` up to float rounding (fused kernels and larger
/// matrix products add in another order). The grouping depends on the jobs only, so results do
/// not depend on the thread count.
///
/// A job with bad inputs, a backbone error or a diverging state gets its own `Err` and leaves
/// the batch; the others go on. The outer `Err` is a failure of the network evaluation itself,
/// which no job survives.
///
/// ```no_run
/// # fn main() -> Result<(), residual::ResidualError> {
/// # let (net, backbone, init, candidates): (residual::ResidualNet, springs::Backbone, springs::State, Vec<springs::Actions>) = todo!();
/// use residual::{History, PredictJob, predict_batch};
/// let history = History::extrapolated(&init, backbone.config().step_dt);
/// let jobs: Vec<PredictJob<'_>> = candidates
///     .iter()
///     .map(|actions| PredictJob { backbone: &backbone, init: &init, history: &history, actions, steps: 10 })
///     .collect();
/// for positions in predict_batch(&net, &jobs)? {
///     assert_eq!(positions?.len(), 10);
/// }
/// # Ok(()) }
/// ```
pub fn predict_batch(net: &ResidualNet, jobs: &[PredictJob<'_>]) -> Result<Vec<JobResult>> {
    let mut results: Vec<Option<JobResult>> = jobs.iter().map(|_| None).collect();
    let mut groups: Vec<Vec<Live<'_>>> = Vec::new();
    let mut points = usize::MAX;
    for (k, job) in jobs.iter().enumerate() {
        match check(job) {
            Ok(()) if job.steps == 0 => results[k] = Some(Ok(Vec::new())),
            Ok(()) => {
                let n = job.backbone.num_particles();
                if points.saturating_add(n) > GROUP_POINTS {
                    groups.push(Vec::new());
                    points = 0;
                }
                points += n;
                if let Some(g) = groups.last_mut() {
                    g.push(Live::new(k, job));
                }
            }
            Err(e) => results[k] = Some(Err(e)),
        }
    }
    let done: Vec<Result<Vec<(usize, JobResult)>>> =
        groups.into_par_iter().map(|g| run_group(net, g)).collect();
    for group in done {
        for (k, r) in group? {
            results[k] = Some(r);
        }
    }
    Ok(results
        .into_iter()
        .map(|r| r.unwrap_or_else(|| Err(ResidualError::Input("job was not run".into()))))
        .collect())
}

/// Particles per group of jobs (at least one job per group). Four clouds of 150 points save
/// 78 % of the instructions (per-operation overhead) that one group of all 15 MPPI candidates
/// saves over one cloud per group, while the element-wise tensors of the default network stay
/// below the 64 Ki elements from which candle 0.11 runs element-wise operations on its own
/// spinning thread pool (which, from several rayon threads at once, cost more than it saved),
/// and 15 candidates still make 4 groups for 2 threads (`docs/plan-log.md`, "Batched network
/// evaluation").
const GROUP_POINTS: usize = 600;

/// Runs one group in lockstep: backbone steps, then one network call for all its clouds.
fn run_group<'a>(net: &ResidualNet, mut live: Vec<Live<'a>>) -> Result<Vec<(usize, JobResult)>> {
    let cfg = net.config();
    let dev = net.device();
    let mut done = Vec::with_capacity(live.len());
    let members: Vec<&ResidualNet> = net.ensemble_members().collect();
    let temporal = members
        .iter()
        .map(|m| m.temporal_params())
        .collect::<Result<Vec<_>>>()?;
    // Per member of an ensemble (one for a single network), decoder outputs `(rows, 3)` of
    // the last `window` steps, flattened, rows = the live clouds' particles in order.
    let mut windows: Vec<Vec<Vec<f32>>> = vec![Vec::with_capacity(cfg.window + 1); members.len()];
    let mut step = 0;
    while !live.is_empty() {
        live.iter_mut().for_each(|l| l.prepare(net, step));
        retire(&mut live, &mut windows, &mut done, |l| l.failed.is_some())?;
        if live.is_empty() {
            break;
        }
        let layouts: Vec<Layout> = live.iter_mut().filter_map(|l| l.layout.take()).collect();
        let st = Structure::batch(&layouts, cfg.patch, dev)?;
        let rows: usize = live.iter().map(|l| l.n).sum();
        let feats: Vec<f32> = live.iter().flat_map(|l| l.feats.iter().copied()).collect();
        let feats = Tensor::from_vec(feats, (rows, cfg.input_dim()), dev)?;
        let centred: Vec<f32> = live
            .iter()
            .flat_map(|l| l.centred.iter().flat_map(|p| p.to_array()))
            .collect();
        let pos = Tensor::from_vec(centred, (rows, 3), dev)?;
        let mut deltas = Vec::with_capacity(members.len());
        for ((member, window), temporal) in members.iter().zip(&mut windows).zip(&temporal) {
            window.push(
                member
                    .decode(&feats, &pos, &st, [0, 1, 2, 3], Pass::Infer)?
                    .flatten_all()?
                    .to_vec1()?,
            );
            if window.len() > cfg.window {
                window.remove(0);
            }
            let rows_of: Vec<&[f32]> = window.iter().map(Vec::as_slice).collect();
            deltas.push(member.aggregate_rows(temporal.as_ref(), &rows_of, rows));
        }
        let delta = crate::ensemble::combine_rows(deltas, net.ensemble_rule());
        let mut rest = delta.as_slice();
        for l in &mut live {
            let (head, tail) = rest.split_at(3 * l.n);
            l.finish(net, step, head);
            rest = tail;
        }
        retire(&mut live, &mut windows, &mut done, |l| {
            l.failed.is_some() || l.positions.len() == l.steps
        })?;
        step += 1;
    }
    Ok(done)
}

fn check(job: &PredictJob<'_>) -> Result<()> {
    let n = job.backbone.num_particles();
    let h = &job.history;
    if n == 0
        || job.init.x.len() != n
        || job.init.v.len() != n
        || h.x.iter().chain(&h.v).any(|h| h.len() != n)
    {
        return Err(ResidualError::Input(format!(
            "backbone has {n} particles (at least 1 needed), state {} / {}, history {} / {} / {} / {}",
            job.init.x.len(),
            job.init.v.len(),
            h.x[0].len(),
            h.x[1].len(),
            h.v[0].len(),
            h.v[1].len()
        )));
    }
    if job.steps >= job.actions.num_frames() {
        return Err(ResidualError::Input(format!(
            "{} steps need {} action frames, got {}",
            job.steps,
            job.steps + 1,
            job.actions.num_frames()
        )));
    }
    Ok(())
}

/// Moves the live rollouts `done` selects to `results` (positions or error) and drops their
/// rows from every member's temporal window.
fn retire(
    live: &mut Vec<Live<'_>>,
    windows: &mut [Vec<Vec<f32>>],
    results: &mut Vec<(usize, JobResult)>,
    done: impl Fn(&Live<'_>) -> bool,
) -> Result<()> {
    if !live.iter().any(&done) {
        return Ok(());
    }
    let mut keep: Vec<u32> = Vec::new();
    let mut row = 0u32;
    let mut kept = Vec::with_capacity(live.len());
    for mut l in live.drain(..) {
        let n = l.n as u32;
        if done(&l) {
            let r = match l.failed.take() {
                Some(e) => Err(e),
                None => Ok(std::mem::take(&mut l.positions)),
            };
            results.push((l.job, r));
        } else {
            keep.extend(row..row + n);
            kept.push(l);
        }
        row += n;
    }
    *live = kept;
    for w in windows.iter_mut().flatten() {
        *w = keep
            .iter()
            .flat_map(|&r| w[3 * r as usize..3 * r as usize + 3].iter().copied())
            .collect();
    }
    Ok(())
}

/// A running job: its hybrid state and what the current step has prepared for the network.
struct Live<'a> {
    job: usize,
    backbone: &'a Backbone,
    actions: &'a Actions,
    steps: usize,
    n: usize,
    /// The hybrid state (after `prepare`: the backbone's prediction).
    sim: State,
    scratch: Scratch,
    /// State before the current step, and the two before that.
    x: Vec<Vec3>,
    v: Vec<Vec3>,
    hx: [Vec<Vec3>; 2],
    hv: [Vec<Vec3>; 2],
    /// Prepared by `prepare` for the network: centre of `x`, centred `x`, features, structure,
    /// and 1 for particles the residual moves during the step (free of a closed gripper, or
    /// all with `held_residual`), 0 otherwise.
    centre: Vec3,
    centred: Vec<Vec3>,
    feats: Vec<f32>,
    layout: Option<Layout>,
    free: Vec<f32>,
    positions: Vec<Vec<Vec3>>,
    failed: Option<ResidualError>,
}

impl<'a> Live<'a> {
    fn new(job: usize, j: &PredictJob<'a>) -> Self {
        let n = j.backbone.num_particles();
        Live {
            job,
            backbone: j.backbone,
            actions: j.actions,
            steps: j.steps,
            n,
            sim: j.init.clone(),
            scratch: j.backbone.scratch(),
            x: Vec::with_capacity(n),
            v: Vec::with_capacity(n),
            hx: j.history.x.clone(),
            hv: j.history.v.clone(),
            centre: Vec3::ZERO,
            centred: Vec::with_capacity(n),
            feats: Vec::with_capacity(n * INPUTS),
            layout: None,
            free: Vec::with_capacity(n),
            positions: Vec::with_capacity(j.steps),
            failed: None,
        }
    }

    /// Backbone step and the network's inputs for step `step` (the same values, computed the
    /// same way in f32, as the single-rollout path's tensor operations).
    fn prepare(&mut self, net: &ResidualNet, step: usize) {
        let (Some(from), Some(to)) = (self.actions.frame(step), self.actions.frame(step + 1))
        else {
            self.failed = Some(ResidualError::Input(format!(
                "no action frame for step {step}"
            )));
            return;
        };
        self.x.clone_from(&self.sim.x);
        self.v.clone_from(&self.sim.v);
        if let Err(e) = self
            .backbone
            .step(&mut self.sim, from, to, &mut self.scratch)
        {
            self.failed = Some(match e {
                SimError::NonFinite { .. } | SimError::Diverged { .. } => ResidualError::Diverged {
                    step,
                    what: e.to_string(),
                },
                e => ResidualError::Sim(e),
            });
            return;
        }
        let cfg = net.config();
        let dt = self.backbone.config().step_dt;
        let vs = f64::from(cfg.velocity_scale);
        let ds = vs / f64::from(dt);
        let (vs, ds, ds2) = (vs as f32, ds as f32, (ds / 2.0) as f32);
        self.centre = self.x.iter().sum::<Vec3>() / self.n as f32;
        self.centred.clear();
        self.centred.extend(self.x.iter().map(|p| *p - self.centre));
        self.feats.clear();
        let mut gripper = Vec::new();
        if cfg.gripper_inputs {
            gripper_inputs(&self.x, from, to, dt, cfg.velocity_scale, &mut gripper);
        }
        let mut ground = Vec::new();
        if cfg.ground_inputs {
            ground_inputs(&self.x, self.backbone.config().ground_z, &mut ground);
        }
        let mut rest = Vec::new();
        if cfg.rest_inputs {
            rest_inputs(self.backbone.rest_positions(), &mut rest);
        }
        for i in 0..self.n {
            let x = self.x[i];
            for f in [
                self.centred[i],
                self.v[i] * vs,
                (self.hx[0][i] - x) * ds,
                (self.hx[1][i] - x) * ds2,
                self.hv[0][i] * vs,
                self.hv[1][i] * vs,
                (self.sim.x[i] - x) * ds,
                self.sim.v[i] * vs,
            ] {
                self.feats.extend(f.to_array());
            }
            if cfg.gripper_inputs {
                self.feats
                    .extend_from_slice(&gripper[i * GRIPPER_INPUTS..(i + 1) * GRIPPER_INPUTS]);
            }
            if cfg.ground_inputs {
                self.feats
                    .extend_from_slice(&ground[i * GROUND_INPUTS..(i + 1) * GROUND_INPUTS]);
            }
            if cfg.rest_inputs {
                self.feats
                    .extend_from_slice(&rest[i * REST_INPUTS..(i + 1) * REST_INPUTS]);
            }
        }
        self.layout = Some(Layout::new(
            &self.centred,
            cfg.enc_channels.len(),
            cfg.grid_m,
            cfg.pool_grid_m,
        ));
        self.free.clear();
        self.free.extend(self.backbone.held().iter().map(|&g| {
            let held = g >= 0 && from.closed.get(g as usize).copied().unwrap_or(false);
            if held && !cfg.held_residual { 0.0 } else { 1.0 }
        }));
    }

    /// Applies the network's residual `delta` (`3 n` values, m/s) to the backbone's prediction.
    fn finish(&mut self, net: &ResidualNet, step: usize, delta: &[f32]) {
        let dt = self.backbone.config().step_dt;
        let position_only = net.config().residual == ResidualKind::Position;
        for i in 0..self.n {
            let d = Vec3::from_slice(&delta[3 * i..3 * i + 3]) * self.free[i];
            self.sim.x[i] += d * dt;
            if !position_only {
                self.sim.v[i] += d;
            }
        }
        let centre = self.centre;
        if let Some(i) = self.sim.x.iter().zip(&self.sim.v).position(|(p, q)| {
            !(p.is_finite() && q.is_finite()) || (*p - centre).length() > DIVERGED_M
        }) {
            self.failed = Some(ResidualError::Diverged {
                step,
                what: format!(
                    "particle {i} at {:?} m, {:?} m/s",
                    self.sim.x[i], self.sim.v[i]
                ),
            });
            return;
        }
        // History shifts: the state before this step becomes t − 1.
        let [hx0, hx1] = &mut self.hx;
        std::mem::swap(hx1, hx0);
        std::mem::swap(hx0, &mut self.x);
        let [hv0, hv1] = &mut self.hv;
        std::mem::swap(hv1, hv0);
        std::mem::swap(hv0, &mut self.v);
        self.positions.push(self.sim.x.clone());
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Device;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::ModelConfig;

    /// Residuals `(n, 3)` of `clouds` evaluated as one batch (`batch`) or one by one, over a
    /// temporal window of two steps (two feature sets per cloud).
    fn residuals(
        net: &ResidualNet,
        clouds: &[(Vec<Vec3>, [Vec<f32>; 2])],
        batch: bool,
        merged: bool,
    ) -> Vec<f32> {
        let cfg = net.config();
        let dev = &Device::Cpu;
        let stages = cfg.enc_channels.len();
        let layout = |p: &[Vec3]| Layout::new(p, stages, cfg.grid_m, cfg.pool_grid_m);
        let run = |clouds: &[&(Vec<Vec3>, [Vec<f32>; 2])]| -> Vec<f32> {
            let pos: Vec<Vec3> = clouds.iter().flat_map(|c| c.0.clone()).collect();
            let st = if merged {
                // What a wrong batch would do: one cloud of all points.
                Structure::batch(&[layout(&pos)], cfg.patch, dev).unwrap()
            } else {
                let layouts: Vec<Layout> = clouds.iter().map(|c| layout(&c.0)).collect();
                Structure::batch(&layouts, cfg.patch, dev).unwrap()
            };
            let flat: Vec<f32> = pos.iter().flat_map(|p| p.to_array()).collect();
            let p = Tensor::from_vec(flat, (pos.len(), 3), dev).unwrap();
            let window: Vec<Tensor> = (0..2)
                .map(|t| {
                    let f: Vec<f32> = clouds.iter().flat_map(|c| c.1[t].clone()).collect();
                    let f = Tensor::from_vec(f, (pos.len(), INPUTS), dev).unwrap();
                    net.decode(&f, &p, &st, [0, 1, 2, 3], Pass::Infer).unwrap()
                })
                .collect();
            let d = net.aggregate(&window, Pass::Infer).unwrap();
            d.flatten_all().unwrap().to_vec1().unwrap()
        };
        if batch {
            run(&clouds.iter().collect::<Vec<_>>())
        } else {
            clouds.iter().flat_map(|c| run(&[c])).collect()
        }
    }

    #[test]
    fn one_network_call_on_many_clouds_equals_one_call_per_cloud() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        // Overlapping clouds of different sizes: a structure that mixed them would show.
        let clouds: Vec<(Vec<Vec3>, [Vec<f32>; 2])> = [150usize, 90, 41]
            .iter()
            .map(|&n| {
                let pos = (0..n)
                    .map(|_| {
                        Vec3::new(
                            rng.random_range(-0.2..0.2),
                            rng.random_range(-0.1..0.1),
                            rng.random_range(0.0..0.05),
                        )
                    })
                    .collect();
                let mut feats = || {
                    (0..n * INPUTS)
                        .map(|_| rng.random_range(-1.0..1.0))
                        .collect()
                };
                (pos, [feats(), feats()])
            })
            .collect();
        for cfg in [ModelConfig::default(), ModelConfig::tiny()] {
            let net = ResidualNet::new(&cfg, 2).unwrap();
            let single = residuals(&net, &clouds, false, false);
            let batch = residuals(&net, &clouds, true, false);
            let scale = single.iter().fold(0f32, |m, v| m.max(v.abs()));
            assert!(scale > 1e-6);
            let worst = single
                .iter()
                .zip(&batch)
                .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(worst <= 1e-5 * scale, "{worst} vs scale {scale}");
            // Serializing, patching and pooling all points as one cloud changes the result, so
            // the comparison above can fail.
            let merged = residuals(&net, &clouds, true, true);
            let off = single
                .iter()
                .zip(&merged)
                .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(off > 1e-2 * scale, "{off} vs scale {scale}");
        }
    }
}
