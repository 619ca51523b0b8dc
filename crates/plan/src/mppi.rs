//! Model Predictive Path Integral control over gripper position sequences.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use springs::Actions;

use crate::{ForwardModel, ModelState, Objective, PlanError, Result};

/// MPPI settings. The defaults are the paper's settings for simple tasks
/// ([`MppiConfig::simple`]); [`MppiConfig::rerouting`] has its cable-rerouting settings.
///
/// Actions are gripper displacements per step, normalised so that 1 means `max_step_m` metres
/// along an axis, and clamped to [−1, 1]. `noise` is the covariance of the normalised action
/// noise per axis (the paper's "action noise covariance 0.1"): standard deviation
/// `sqrt(noise) · max_step_m` metres per step. The noise is piecewise constant over
/// `noise_segments` equal parts of the horizon, so that candidates are smooth paths rather than
/// jitter.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct MppiConfig {
    /// Candidate action sequences per iteration (the first is the current mean, unperturbed).
    pub samples: usize,
    /// Steps per candidate sequence.
    pub horizon: usize,
    /// Sample–weight–update rounds per replanning step.
    pub iterations: usize,
    /// Covariance of the normalised action noise per axis.
    pub noise: f32,
    /// Gripper displacement per step and axis at a normalised action of 1, m.
    pub max_step_m: f32,
    /// Pieces of the horizon over which a candidate's noise is constant.
    pub noise_segments: usize,
    /// Temperature `λ` of the candidate weights `exp(−(c − c_min) / λ)`, in cost units (metres
    /// of Chamfer distance; default 0.01). Candidates that differ by much less than `λ` weigh
    /// about the same, so where the cost is flat the mean stays put instead of chasing noise.
    pub temperature: f64,
    /// Project every candidate gripper path into the objective's workspace (default true).
    /// Without it the workspace acts only through its penalty, which biases the mean away from
    /// a workspace face the gripper works at (the table): noise towards the face is punished,
    /// noise away from it is not.
    pub clamp_to_workspace: bool,
    /// Weight `κ` of the disagreement between a model's members in a candidate's cost: a
    /// candidate costs `mean_k c_k + κ · sd_k c_k` over the costs `c_k` of its members'
    /// predictions ([`ForwardModel::rollout_members_batch`]; default 0, the members' mean
    /// cost as in PETS). Models of one member cost `c` whatever `κ`.
    #[serde(default)]
    pub member_risk: f64,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for MppiConfig {
    fn default() -> Self {
        Self::simple()
    }
}

impl MppiConfig {
    /// The paper's settings for simple tasks: 8 samples, horizon 10, 3 iterations, noise 0.1.
    pub fn simple() -> Self {
        MppiConfig {
            samples: 8,
            horizon: 10,
            iterations: 3,
            noise: 0.1,
            max_step_m: 0.04,
            noise_segments: 3,
            temperature: 0.01,
            clamp_to_workspace: true,
            member_risk: 0.0,
            seed: 0,
        }
    }

    /// The paper's settings for cable rerouting: 15 samples, horizon 15, 6 iterations, noise 0.1.
    pub fn rerouting() -> Self {
        MppiConfig {
            samples: 15,
            horizon: 15,
            iterations: 6,
            ..Self::simple()
        }
    }

    /// Model steps one replanning step runs: `samples · horizon · iterations`.
    pub fn model_steps_per_replan(&self) -> usize {
        self.samples * self.horizon * self.iterations
    }

    /// Check every setting.
    pub fn validate(&self) -> Result<()> {
        let bad = |name, value: f64, reason| {
            Err(PlanError::Config {
                name,
                value,
                reason,
            })
        };
        for (name, v) in [
            ("samples", self.samples),
            ("horizon", self.horizon),
            ("iterations", self.iterations),
            ("noise_segments", self.noise_segments),
        ] {
            if v == 0 {
                return bad(name, 0.0, "must be >= 1");
            }
        }
        if !(self.noise.is_finite() && self.noise >= 0.0) {
            return bad("noise", f64::from(self.noise), "must be finite and >= 0");
        }
        if !(self.max_step_m.is_finite() && self.max_step_m > 0.0) {
            return bad(
                "max_step_m",
                f64::from(self.max_step_m),
                "must be finite and > 0",
            );
        }
        if !(self.temperature.is_finite() && self.temperature > 0.0) {
            return bad("temperature", self.temperature, "must be finite and > 0");
        }
        if !(self.member_risk.is_finite() && self.member_risk >= 0.0) {
            return bad("member_risk", self.member_risk, "must be finite and >= 0");
        }
        Ok(())
    }
}

/// What one replanning step decided and saw.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanStep {
    /// Gripper positions to command for the next step, m.
    pub next: Vec<Vec3>,
    /// The planned gripper path after the last update: `horizon` frames after now, m.
    pub path: Vec<Vec<Vec3>>,
    /// Lowest candidate cost of each iteration.
    pub best_cost: Vec<f64>,
    /// Standard deviation of the lowest-cost candidate's costs over the model's members, each
    /// iteration (0 for a model of one member; NaN where every candidate failed): how much
    /// the members disagree about the candidate the planner likes best.
    pub best_member_sd: Vec<f64>,
    /// Candidate rollouts that failed, over all iterations.
    pub failed: usize,
    /// Candidate rollouts run, over all iterations.
    pub rollouts: usize,
}

/// An MPPI planner. It keeps its mean action sequence between calls (shifted by one step after
/// each plan: a warm start), so call [`Mppi::plan`] once per executed step.
///
/// ```
/// use glam::Vec3;
/// use plan::{ForwardModel, ModelState, Mppi, MppiConfig, Objective, Workspace};
/// // A toy model: one particle that sits exactly at the gripper.
/// struct Follow;
/// impl ForwardModel for Follow {
///     fn num_particles(&self) -> usize { 1 }
///     fn name(&self) -> &str { "follow" }
///     fn rollout(&self, _: &ModelState, a: &springs::Actions) -> plan::Result<Vec<Vec<Vec3>>> {
///         Ok((1..a.num_frames()).map(|t| a.frame(t).unwrap().positions.to_vec()).collect())
///     }
/// }
/// let ws = Workspace { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) };
/// let goal = Objective::new(&[Vec3::new(0.2, 0.0, 0.0)], ws)?;
/// let mut mppi = Mppi::new(MppiConfig::simple(), 1)?;
/// let mut g = Vec3::ZERO;
/// for _ in 0..15 {
///     let step = mppi.plan(&Follow, &ModelState::at_rest(vec![g]), &[g], &goal)?;
///     g = step.next[0];
/// }
/// assert!(g.distance(Vec3::new(0.2, 0.0, 0.0)) < 0.02);
/// # Ok::<(), plan::PlanError>(())
/// ```
#[derive(Clone, Debug)]
pub struct Mppi {
    cfg: MppiConfig,
    grippers: usize,
    /// Normalised mean actions, `[step][gripper]` flattened.
    mean: Vec<Vec3>,
    replans: u64,
}

impl Mppi {
    /// A planner for `grippers` grippers, starting from a mean of "stand still".
    pub fn new(cfg: MppiConfig, grippers: usize) -> Result<Self> {
        cfg.validate()?;
        if grippers == 0 {
            return Err(PlanError::Config {
                name: "grippers",
                value: 0.0,
                reason: "must be >= 1",
            });
        }
        Ok(Mppi {
            cfg,
            grippers,
            mean: vec![Vec3::ZERO; cfg.horizon * grippers],
            replans: 0,
        })
    }

    /// The settings.
    pub fn config(&self) -> &MppiConfig {
        &self.cfg
    }

    /// Plans from `state` with the grippers at `grippers` (m): `iterations` rounds of sampling
    /// `samples` action sequences around the mean, rolling each out with `model` (in parallel;
    /// results do not depend on the thread count), scoring with `objective` and moving the mean
    /// to the cost-weighted average. Candidates whose rollout fails are dropped; only when all
    /// of them fail in every iteration is that an error.
    pub fn plan(
        &mut self,
        model: &dyn ForwardModel,
        state: &ModelState,
        grippers: &[Vec3],
        objective: &Objective,
    ) -> Result<PlanStep> {
        let (h, g, k) = (self.cfg.horizon, self.grippers, self.cfg.samples);
        if grippers.len() != g {
            return Err(PlanError::Mismatch {
                what: "grippers",
                expected: g,
                got: grippers.len(),
            });
        }
        if state.len() != model.num_particles() {
            return Err(PlanError::Mismatch {
                what: "state particles",
                expected: model.num_particles(),
                got: state.len(),
            });
        }
        if !grippers.iter().all(|p| p.is_finite()) {
            return Err(PlanError::NonFinite("gripper positions"));
        }
        let sigma = self.cfg.noise.sqrt();
        let seg_len = h.div_ceil(self.cfg.noise_segments.min(h));
        let (mut failed, mut rollouts, mut first_error) = (0, 0, None);
        let mut best_cost = Vec::with_capacity(self.cfg.iterations);
        let mut best_member_sd = Vec::with_capacity(self.cfg.iterations);
        for it in 0..self.cfg.iterations {
            let mut rng = ChaCha8Rng::seed_from_u64(mix(&[self.cfg.seed, self.replans, it as u64]));
            let candidates: Vec<Vec<Vec3>> = (0..k)
                .map(|c| {
                    if c == 0 {
                        return self.mean.clone();
                    }
                    let knots: Vec<Vec3> = (0..h.div_ceil(seg_len) * g)
                        .map(|_| {
                            Vec3::new(
                                rng.sample(StandardNormal),
                                rng.sample(StandardNormal),
                                rng.sample(StandardNormal),
                            ) * sigma
                        })
                        .collect();
                    (0..h * g)
                        .map(|j| {
                            let (t, gi) = (j / g, j % g);
                            let u = self.mean[j] + knots[(t / seg_len) * g + gi];
                            u.clamp(Vec3::splat(-1.0), Vec3::splat(1.0))
                        })
                        .collect()
                })
                .collect();
            // Gripper paths first, then the whole population through the model at once (a
            // model may evaluate candidates together), then the costs; a candidate that fails
            // at any stage is dropped alone.
            let mut actions = Vec::with_capacity(k);
            let paths: Vec<Result<Vec<Vec<Vec3>>>> = candidates
                .iter()
                .map(|u| {
                    let (a, path) = self.gripper_path(grippers, u, objective)?;
                    actions.push(a);
                    Ok(path)
                })
                .collect();
            let mut predicted = model.rollout_members_batch(state, &actions);
            if predicted.len() != actions.len() {
                let got = predicted.len();
                predicted = (0..actions.len())
                    .map(|_| {
                        Err(PlanError::Mismatch {
                            what: "model results per batch",
                            expected: actions.len(),
                            got,
                        })
                    })
                    .collect();
            }
            let mut predicted = predicted.into_iter();
            let outcomes: Vec<Result<_>> = paths
                .into_iter()
                .map(|path| {
                    let path = path?;
                    // One result per action sequence (lengths checked above).
                    let members = predicted.next().unwrap_or_else(|| {
                        Err(PlanError::Model("no result for a candidate".into()))
                    })?;
                    Ok((members, path))
                })
                .collect();
            let risk = self.cfg.member_risk;
            let costs: Vec<Result<(f64, f64)>> = outcomes
                .into_par_iter()
                .map(|r| {
                    let (members, path) = r?;
                    let mut each = Vec::with_capacity(members.len());
                    for predicted in &members {
                        if predicted.len() != h {
                            return Err(PlanError::Mismatch {
                                what: "predicted steps",
                                expected: h,
                                got: predicted.len(),
                            });
                        }
                        each.push(objective.cost(predicted, &path)?);
                    }
                    let (c, sd) = member_cost(&each, risk)?;
                    if c.is_finite() {
                        Ok((c, sd))
                    } else {
                        Err(PlanError::NonFinite("candidate cost"))
                    }
                })
                .collect();
            rollouts += k;
            // (candidate, cost, members' spread) of the candidates that were scored.
            let mut ok: Vec<(usize, f64, f64)> = Vec::with_capacity(k);
            for (c, r) in costs.into_iter().enumerate() {
                match r {
                    Ok((v, sd)) => ok.push((c, v, sd)),
                    Err(e) => {
                        failed += 1;
                        first_error.get_or_insert_with(|| e.to_string());
                    }
                }
            }
            if ok.is_empty() {
                best_cost.push(f64::INFINITY);
                best_member_sd.push(f64::NAN);
                continue;
            }
            let lo = ok.iter().map(|c| c.1).fold(f64::INFINITY, f64::min);
            best_cost.push(lo);
            // The first candidate at the lowest cost (ties keep input order).
            let best = ok.iter().find(|c| c.1 == lo).map_or(f64::NAN, |c| c.2);
            best_member_sd.push(best);
            let weights: Vec<f64> = ok
                .iter()
                .map(|c| (-(c.1 - lo) / self.cfg.temperature).exp())
                .collect();
            let total: f64 = weights.iter().sum();
            for (j, m) in self.mean.iter_mut().enumerate() {
                let mut acc = glam::DVec3::ZERO;
                for ((c, _, _), w) in ok.iter().zip(&weights) {
                    acc += candidates[*c][j].as_dvec3() * *w;
                }
                *m = (acc / total).as_vec3();
            }
        }
        if failed == rollouts {
            return Err(PlanError::AllRolloutsFailed {
                samples: k,
                first: first_error.unwrap_or_default(),
            });
        }
        let (_, path) = self.gripper_path(grippers, &self.mean, objective)?;
        let next = path[0].clone();
        // Warm start: drop the executed step; the new last step stands still.
        self.mean.drain(..g);
        self.mean.extend(std::iter::repeat_n(Vec3::ZERO, g));
        self.replans += 1;
        Ok(PlanStep {
            next,
            path,
            best_cost,
            best_member_sd,
            failed,
            rollouts,
        })
    }

    /// Gripper frames (now, then one per step) for normalised actions `u`, as `Actions` with
    /// every gripper closed and as the path after now.
    fn gripper_path(
        &self,
        now: &[Vec3],
        u: &[Vec3],
        objective: &Objective,
    ) -> Result<(Actions, Vec<Vec<Vec3>>)> {
        let g = self.grippers;
        let mut frames = Vec::with_capacity(self.cfg.horizon + 1);
        frames.push(now.to_vec());
        for t in 0..self.cfg.horizon {
            let prev = &frames[t];
            let next: Vec<Vec3> = (0..g)
                .map(|gi| {
                    let p = prev[gi] + u[t * g + gi] * self.cfg.max_step_m;
                    if self.cfg.clamp_to_workspace {
                        objective.workspace.clamp(p)
                    } else {
                        p
                    }
                })
                .collect();
            frames.push(next);
        }
        let closed = vec![vec![true; g]; frames.len()];
        let path = frames[1..].to_vec();
        Ok((Actions::new(frames, closed)?, path))
    }
}

/// A candidate's cost from its members' costs, `mean + risk · sd`, and `sd` (population
/// standard deviation); one member's cost is returned exactly, with `sd` 0.
fn member_cost(each: &[f64], risk: f64) -> Result<(f64, f64)> {
    match each {
        [] => Err(PlanError::Model("no member predicted the candidate".into())),
        [c] => Ok((*c, 0.0)),
        _ => {
            let n = each.len() as f64;
            let mean = each.iter().sum::<f64>() / n;
            let sd = (each.iter().map(|c| (c - mean).powi(2)).sum::<f64>() / n).sqrt();
            // Without risk the mean itself, not mean + 0 · sd (bit for bit, and NaN-free).
            let cost = if risk == 0.0 { mean } else { mean + risk * sd };
            Ok((cost, sd))
        }
    }
}

/// SplitMix64-style combination of seed words into one seed.
fn mix(words: &[u64]) -> u64 {
    let mut z = 0x243F_6A88_85A3_08D3u64;
    for &w in words {
        z ^= w;
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
    }
    z
}

#[cfg(test)]
mod tests {
    use super::member_cost;

    #[test]
    fn member_cost_is_the_mean_plus_risk_times_the_spread() {
        // Costs 1, 2, 3, 6: mean 3, population standard deviation sqrt(3.5).
        let each = [1.0, 2.0, 3.0, 6.0];
        let (c, sd) = member_cost(&each, 0.0).unwrap();
        assert_eq!(c, 3.0);
        assert!((sd - 3.5f64.sqrt()).abs() < 1e-12, "{sd}");
        let (c, _) = member_cost(&each, 2.0).unwrap();
        assert!((c - (3.0 + 2.0 * 3.5f64.sqrt())).abs() < 1e-12, "{c}");
        // One member: its cost, whatever the risk, and no spread.
        assert_eq!(member_cost(&[0.37], 5.0).unwrap(), (0.37, 0.0));
        assert!(member_cost(&[], 0.0).is_err());
    }
}
