//! Forward models the planner can roll out: the spring-mass backbone alone, or backbone plus
//! the residual network (PGRD), behind one trait.

use std::sync::Arc;

use glam::Vec3;
use rayon::prelude::*;
use springs::{Actions, Backbone, State};

use crate::{PlanError, Result};

/// What a forward model starts from: the current positions and velocities of its particles and
/// the two frames before (models with memory, like the residual network, read them).
#[derive(Clone, Debug, PartialEq)]
pub struct ModelState {
    /// Positions now, m.
    pub x: Vec<Vec3>,
    /// Velocities now, m/s.
    pub v: Vec<Vec3>,
    /// Positions one and two steps ago, m.
    pub past_x: [Vec<Vec3>; 2],
    /// Velocities one and two steps ago, m/s.
    pub past_v: [Vec<Vec3>; 2],
}

impl ModelState {
    /// Particles at `x`, at rest now and before.
    pub fn at_rest(x: Vec<Vec3>) -> Self {
        let v = vec![Vec3::ZERO; x.len()];
        ModelState {
            past_x: [x.clone(), x.clone()],
            past_v: [v.clone(), v.clone()],
            x,
            v,
        }
    }

    /// The state after observing `frames` (oldest first, the last one is now), one every `dt`
    /// seconds: velocities by backward differences; frames before the first repeat it (at rest).
    ///
    /// ```
    /// use glam::Vec3;
    /// let frames = vec![vec![Vec3::ZERO], vec![Vec3::new(0.1, 0.0, 0.0)]];
    /// let s = plan::ModelState::from_frames(&frames, 0.1)?;
    /// assert!((s.v[0].x - 1.0).abs() < 1e-6);
    /// assert_eq!(s.past_x[1][0], Vec3::ZERO); // before the first frame: held at rest
    /// # Ok::<(), plan::PlanError>(())
    /// ```
    pub fn from_frames(frames: &[Vec<Vec3>], dt: f32) -> Result<Self> {
        let Some(now) = frames.last() else {
            return Err(PlanError::Mismatch {
                what: "observed frames",
                expected: 1,
                got: 0,
            });
        };
        if !(dt.is_finite() && dt > 0.0) {
            return Err(PlanError::Config {
                name: "dt",
                value: f64::from(dt),
                reason: "must be finite and > 0",
            });
        }
        let n = now.len();
        if let Some(f) = frames.iter().find(|f| f.len() != n) {
            return Err(PlanError::Mismatch {
                what: "particles per observed frame",
                expected: n,
                got: f.len(),
            });
        }
        if frames.iter().flatten().any(|p| !p.is_finite()) {
            return Err(PlanError::NonFinite("an observed frame"));
        }
        // frame(k): k steps ago, clamped to the oldest frame.
        let frame = |k: usize| &frames[frames.len() - 1 - k.min(frames.len() - 1)];
        let vel = |k: usize| -> Vec<Vec3> {
            frame(k)
                .iter()
                .zip(frame(k + 1))
                .map(|(a, b)| (*a - *b) / dt)
                .collect()
        };
        Ok(ModelState {
            x: now.clone(),
            v: vel(0),
            past_x: [frame(1).clone(), frame(2).clone()],
            past_v: [vel(1), vel(2)],
        })
    }

    /// Number of particles.
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// Whether there are no particles.
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }
}

/// One candidate's predicted positions by each member of a model, `[member][step][particle]`,
/// m ([`ForwardModel::rollout_members_batch`]).
pub type MemberPredictions = Vec<Vec<Vec<Vec3>>>;

/// A model that predicts how particles move under gripper commands.
///
/// `rollout` returns the positions of all particles after each step (`actions.num_frames() − 1`
/// entries; frame 0 of `actions` is where the grippers are now). It must be deterministic and
/// safe to call from several threads at once: the planner evaluates candidates in parallel.
/// An `Err` drops that candidate without stopping the planner.
///
/// The planner hands a whole population to [`ForwardModel::rollout_batch`]; its default runs
/// `rollout` for each candidate in parallel. Models that can evaluate many candidates together
/// more cheaply (PGRD's network) override it.
pub trait ForwardModel: Sync {
    /// Particles the model simulates (the length of every predicted frame).
    fn num_particles(&self) -> usize;
    /// Positions after each step of `actions`, m.
    fn rollout(&self, state: &ModelState, actions: &Actions) -> Result<Vec<Vec<Vec3>>>;
    /// [`ForwardModel::rollout`] from `state` for every candidate of `actions`, one result per
    /// candidate in input order: a failing candidate gets its own `Err` and does not stop the
    /// others. Results must not depend on the number of threads.
    ///
    /// The default runs the candidates in parallel on the current rayon pool, each on one
    /// thread.
    fn rollout_batch(
        &self,
        state: &ModelState,
        actions: &[Actions],
    ) -> Vec<Result<Vec<Vec<Vec3>>>> {
        actions.par_iter().map(|a| self.rollout(state, a)).collect()
    }
    /// Every member's prediction for every candidate of `actions`, one result per candidate
    /// in input order: `[member][step][particle]`, each member as [`ForwardModel::rollout`]
    /// would predict alone. Models made of several members that may disagree (an ensemble of
    /// residual networks, [`Pgrd::with_member_trajectories`]) return one trajectory per
    /// member, and [`crate::Mppi`] scores a candidate by its cost under each of them (PETS's
    /// "trajectory sampling"); a failure of any member fails the candidate alone.
    ///
    /// The default is one member, the model's own [`ForwardModel::rollout_batch`].
    fn rollout_members_batch(
        &self,
        state: &ModelState,
        actions: &[Actions],
    ) -> Vec<Result<MemberPredictions>> {
        as_one_member(self.rollout_batch(state, actions))
    }
    /// A short name for reports ("spring-mass", "pgrd").
    fn name(&self) -> &str;
    /// Hears what the system did, after every executed step of [`crate::run_closed_loop`]:
    /// `observed` holds the observed points at the start and after each step so far,
    /// `grippers` the gripper positions at the same times, `dt` seconds apart. Models that
    /// adapt to the system they control ([`crate::OnlinePgrd`]) learn from it; the default
    /// ignores it. An `Err` ends the closed loop (recorded, not raised).
    fn observe_run(&self, observed: &[Vec<Vec3>], grippers: &[Vec<Vec3>], dt: f32) -> Result<()> {
        let _ = (observed, grippers, dt);
        Ok(())
    }
}

/// The spring-mass backbone alone.
#[derive(Debug)]
pub struct SpringMass {
    backbone: Backbone,
}

impl SpringMass {
    /// Wraps a backbone (its springs, held particles, obstacles and step length are used as is).
    pub fn new(backbone: Backbone) -> Self {
        SpringMass { backbone }
    }

    /// The backbone.
    pub fn backbone(&self) -> &Backbone {
        &self.backbone
    }
}

impl ForwardModel for SpringMass {
    fn num_particles(&self) -> usize {
        self.backbone.num_particles()
    }

    fn rollout(&self, state: &ModelState, actions: &Actions) -> Result<Vec<Vec<Vec3>>> {
        backbone_rollout(&self.backbone, state, actions)
    }

    fn name(&self) -> &str {
        "spring-mass"
    }
}

/// PGRD: the backbone with the residual network's velocity corrections after every step.
///
/// An ensemble of networks acts as one model (its members' residuals combined by its rule,
/// [`residual::EnsembleRule`]) unless built with [`Pgrd::with_member_trajectories`]: then
/// [`ForwardModel::rollout_members_batch`] runs every member on its own trajectory, so the
/// planner sees where they disagree about a candidate.
#[derive(Debug)]
pub struct Pgrd {
    backbone: Backbone,
    net: Arc<residual::ResidualNet>,
    /// The ensemble's members, each a network of its own; empty unless the members are
    /// rolled out apart.
    members: Vec<residual::ResidualNet>,
}

impl Pgrd {
    /// The hybrid model of `backbone` and `net` (trained on the same kind of particles); one
    /// network may be shared by many models.
    pub fn new(backbone: Backbone, net: Arc<residual::ResidualNet>) -> Self {
        Pgrd {
            backbone,
            net,
            members: Vec::new(),
        }
    }

    /// The hybrid model of `backbone` and the ensemble `net` whose
    /// [`ForwardModel::rollout_members_batch`] predicts with each member alone, on its own
    /// trajectory (the backbone's parameters shared); `rollout` and `rollout_batch` still
    /// predict with the ensemble as one model. A single network is one member. Each member's
    /// parameters are copied.
    pub fn with_member_trajectories(
        backbone: Backbone,
        net: Arc<residual::ResidualNet>,
    ) -> Result<Self> {
        let members = net
            .split_ensemble()
            .map_err(|e| PlanError::Model(e.to_string()))?;
        Ok(Pgrd {
            backbone,
            net,
            members,
        })
    }

    /// Members the planner scores each candidate with (1 unless built with
    /// [`Pgrd::with_member_trajectories`] from an ensemble).
    pub fn members(&self) -> usize {
        self.members.len().max(1)
    }

    /// The backbone.
    pub fn backbone(&self) -> &Backbone {
        &self.backbone
    }
}

impl ForwardModel for Pgrd {
    fn num_particles(&self) -> usize {
        self.backbone.num_particles()
    }

    fn rollout(&self, state: &ModelState, actions: &Actions) -> Result<Vec<Vec<Vec3>>> {
        hybrid_rollout(&self.backbone, &self.net, state, actions)
    }

    /// All candidates through [`residual::predict_batch`]: one network call per step on all
    /// candidates' clouds instead of one per candidate (the network's cost is mostly fixed
    /// per-operation overhead). Each candidate's prediction equals its own `rollout` up to
    /// float summation order.
    fn rollout_batch(
        &self,
        state: &ModelState,
        actions: &[Actions],
    ) -> Vec<Result<Vec<Vec<Vec3>>>> {
        hybrid_batch(&self.backbone, &self.net, state, actions)
    }

    /// Each member through [`residual::predict_batch`] on all candidates, one member after
    /// the other; the ensemble as one model when the members are not rolled out apart.
    fn rollout_members_batch(
        &self,
        state: &ModelState,
        actions: &[Actions],
    ) -> Vec<Result<MemberPredictions>> {
        if self.members.is_empty() {
            return as_one_member(self.rollout_batch(state, actions));
        }
        let mut out: Vec<Result<MemberPredictions>> = (0..actions.len())
            .map(|_| Ok(Vec::with_capacity(self.members.len())))
            .collect();
        for net in &self.members {
            for (slot, r) in out
                .iter_mut()
                .zip(hybrid_batch(&self.backbone, net, state, actions))
            {
                match (slot.as_mut(), r) {
                    (Ok(each), Ok(x)) => each.push(x),
                    (Ok(_), Err(e)) => *slot = Err(e),
                    // Already failed under an earlier member.
                    (Err(_), _) => {}
                }
            }
        }
        out
    }

    fn name(&self) -> &str {
        if self.members.is_empty() {
            "pgrd"
        } else {
            "pgrd-members"
        }
    }
}

/// Each candidate's prediction as the only member's.
fn as_one_member(batch: Vec<Result<Vec<Vec<Vec3>>>>) -> Vec<Result<MemberPredictions>> {
    batch.into_iter().map(|r| r.map(|x| vec![x])).collect()
}

/// The backbone alone from `state` (positions after each step).
pub(crate) fn backbone_rollout(
    backbone: &Backbone,
    state: &ModelState,
    actions: &Actions,
) -> Result<Vec<Vec<Vec3>>> {
    let init = State {
        x: state.x.clone(),
        v: state.v.clone(),
    };
    let mut out = backbone.rollout(&init, actions)?;
    out.positions.remove(0);
    Ok(out.positions)
}

/// The network's start: the state now and the two frames before.
fn start(state: &ModelState) -> (State, residual::History) {
    let init = State {
        x: state.x.clone(),
        v: state.v.clone(),
    };
    let history = residual::History {
        x: state.past_x.clone(),
        v: state.past_v.clone(),
    };
    (init, history)
}

/// Backbone and network from `state` and its history (positions after each step).
pub(crate) fn hybrid_rollout(
    backbone: &Backbone,
    net: &residual::ResidualNet,
    state: &ModelState,
    actions: &Actions,
) -> Result<Vec<Vec<Vec3>>> {
    let (init, history) = start(state);
    let steps = actions.num_frames().saturating_sub(1);
    residual::predict(net, backbone, &init, &history, actions, steps)
        .map_err(|e| PlanError::Model(e.to_string()))
}

/// [`hybrid_rollout`] for every candidate, the network evaluated on all of them at once.
pub(crate) fn hybrid_batch(
    backbone: &Backbone,
    net: &residual::ResidualNet,
    state: &ModelState,
    actions: &[Actions],
) -> Vec<Result<Vec<Vec<Vec3>>>> {
    let (init, history) = start(state);
    let jobs: Vec<residual::PredictJob<'_>> = actions
        .iter()
        .map(|a| residual::PredictJob {
            backbone,
            init: &init,
            history: &history,
            actions: a,
            steps: a.num_frames().saturating_sub(1),
        })
        .collect();
    match residual::predict_batch(net, &jobs) {
        Ok(out) => out
            .into_iter()
            .map(|r| r.map_err(|e| PlanError::Model(e.to_string())))
            .collect(),
        // The network evaluation itself failed: no candidate has a prediction.
        Err(e) => {
            let msg = e.to_string();
            actions
                .iter()
                .map(|_| Err(PlanError::Model(msg.clone())))
                .collect()
        }
    }
}
