//! PGRD whose residual gain is chosen in closed loop, from how well each gain has predicted
//! what the system did so far.
//!
//! A residual network learned from recorded motions can predict a planner's own motions worse
//! than its backbone (`docs/plan-log.md`: the rope's networks, 13–72 % worse along the planner's
//! paths). In closed loop the system's response to every executed step is observed, so the
//! model can measure that itself: [`OnlinePgrd`] keeps a few copies of the network with its
//! residual scaled by a gain (0 = the backbone alone), scores each on the executed path after
//! every step, and plans with the one whose predictions have been best.

use std::sync::{Arc, Mutex, MutexGuard};

use glam::Vec3;
use springs::{Actions, Backbone};

use crate::model::{backbone_rollout, hybrid_batch, hybrid_rollout};
use crate::{ForwardModel, ModelState, PlanError, Result};

/// Gains tried by default: the backbone alone, half the network's residual, all of it.
pub const DEFAULT_GAINS: [f32; 3] = [0.0, 0.5, 1.0];

/// The backbone plus the residual network scaled by the gain that has predicted the executed
/// steps best so far in this run.
///
/// After each executed step ([`ForwardModel::observe_run`]) every gain predicts the path from
/// `window` steps back (fewer at the start of a run) to the newest observation, from the
/// observed frames and the executed gripper positions (grippers closed, as the planner drives
/// them); its mean distance per particle and step joins its running sum, and the gain with
/// the smallest sum (the first in the list on ties) plans the next step. Until the first step has
/// been observed it plans with gain 1 (the network as trained) if that is among the gains,
/// else with the largest. A run that starts again (fewer observed frames than already
/// scored) starts the sums again; [`OnlinePgrd::reset`] does so explicitly.
#[derive(Debug)]
pub struct OnlinePgrd {
    backbone: Backbone,
    /// One network per gain (`None`: gain 0, the backbone alone), in the order of `gains`.
    nets: Vec<Option<Arc<residual::ResidualNet>>>,
    gains: Vec<f32>,
    window: usize,
    learner: Mutex<Learner>,
}

/// What the run has taught so far.
#[derive(Clone, Debug)]
struct Learner {
    /// Per gain, the summed mean prediction error over the windows scored, m.
    error: Vec<f64>,
    /// Observed frames already scored (windows ending at frames `1..scored`).
    scored: usize,
    /// Index of the gain in use.
    choice: usize,
    /// The gain in use after each observation of this run.
    chosen: Vec<f32>,
}

impl OnlinePgrd {
    /// The hybrid of `backbone` and `net` with the residual gains `gains` (each finite and
    /// ≥ 0; [`DEFAULT_GAINS`] for the usual choice), scored on windows of up to `window`
    /// executed steps (≥ 1; the planner's horizon predicts that far).
    ///
    /// ```
    /// use plan::{DEFAULT_GAINS, ForwardModel, OnlinePgrd, Task, TaskConfig, TaskKind};
    /// let cfg = TaskConfig { tracked: 60, ..TaskConfig::new() };
    /// let task = Task::build(TaskKind::RopeLift, &cfg)?;
    /// let backbone = task.backbone(springs::SpringParams::reference_rope())?;
    /// let net = residual::ResidualNet::new(&residual::ModelConfig::tiny(), 0)?;
    /// let model = OnlinePgrd::new(backbone, &net, &DEFAULT_GAINS, 10)?;
    /// assert_eq!(model.gain(), 1.0); // nothing observed yet: the network as trained
    /// assert_eq!(model.name(), "pgrd-online");
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn new(
        backbone: Backbone,
        net: &residual::ResidualNet,
        gains: &[f32],
        window: usize,
    ) -> Result<Self> {
        if gains.is_empty() {
            return Err(PlanError::Mismatch {
                what: "residual gains",
                expected: 1,
                got: 0,
            });
        }
        if let Some(&g) = gains.iter().find(|g| !(g.is_finite() && **g >= 0.0)) {
            return Err(PlanError::Config {
                name: "residual gain",
                value: f64::from(g),
                reason: "must be finite and >= 0",
            });
        }
        if window == 0 {
            return Err(PlanError::Config {
                name: "window",
                value: 0.0,
                reason: "must be >= 1 step",
            });
        }
        let nets = gains
            .iter()
            .map(|&g| {
                if g == 0.0 {
                    return Ok(None);
                }
                net.with_residual_gain(g)
                    .map(|n| Some(Arc::new(n)))
                    .map_err(|e| PlanError::Model(e.to_string()))
            })
            .collect::<Result<Vec<_>>>()?;
        let model = OnlinePgrd {
            backbone,
            nets,
            gains: gains.to_vec(),
            window,
            learner: Mutex::new(Learner {
                error: Vec::new(),
                scored: 0,
                choice: 0,
                chosen: Vec::new(),
            }),
        };
        model.reset();
        Ok(model)
    }

    /// The gains this model chooses among.
    pub fn gains(&self) -> &[f32] {
        &self.gains
    }

    /// The gain it plans with now.
    pub fn gain(&self) -> f32 {
        self.gains[self.learner().choice]
    }

    /// The gain in use after each observation of this run, oldest first.
    pub fn chosen_gains(&self) -> Vec<f32> {
        self.learner().chosen.clone()
    }

    /// Per gain, the mean prediction error of the windows scored in this run, m (empty
    /// before the first observation).
    pub fn mean_errors_m(&self) -> Vec<f64> {
        let l = self.learner();
        let windows = l.scored.saturating_sub(1);
        if windows == 0 {
            return Vec::new();
        }
        l.error.iter().map(|e| e / windows as f64).collect()
    }

    /// Forgets the run: sums cleared, the starting gain in use.
    pub fn reset(&self) {
        let start = self
            .gains
            .iter()
            .position(|&g| g == 1.0)
            .unwrap_or_else(|| largest(&self.gains));
        *self.learner() = Learner {
            error: vec![0.0; self.gains.len()],
            scored: 0,
            choice: start,
            chosen: Vec::new(),
        };
    }

    fn learner(&self) -> MutexGuard<'_, Learner> {
        // A panic elsewhere cannot leave the sums half-updated in a way that matters more
        // than losing them, so a poisoned lock is used as is.
        self.learner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Positions after each step of `actions` with gain number `k`.
    fn rollout_with(
        &self,
        k: usize,
        state: &ModelState,
        actions: &Actions,
    ) -> Result<Vec<Vec<Vec3>>> {
        match &self.nets[k] {
            None => backbone_rollout(&self.backbone, state, actions),
            Some(net) => hybrid_rollout(&self.backbone, net, state, actions),
        }
    }
}

/// Index of the largest value (the first of equals).
fn largest(values: &[f32]) -> usize {
    let mut best = 0;
    for (i, v) in values.iter().enumerate() {
        if *v > values[best] {
            best = i;
        }
    }
    best
}

/// Mean over steps of the mean distance per particle between predicted and observed frames, m.
fn mean_distance(predicted: &[Vec<Vec3>], observed: &[Vec<Vec3>]) -> f64 {
    let steps = predicted.len().min(observed.len());
    if steps == 0 {
        return f64::INFINITY;
    }
    let total: f64 = predicted
        .iter()
        .zip(observed)
        .map(|(p, o)| {
            p.iter()
                .zip(o)
                .map(|(a, b)| f64::from(a.distance(*b)))
                .sum::<f64>()
                / p.len().max(1) as f64
        })
        .sum();
    total / steps as f64
}

impl ForwardModel for OnlinePgrd {
    fn num_particles(&self) -> usize {
        self.backbone.num_particles()
    }

    fn rollout(&self, state: &ModelState, actions: &Actions) -> Result<Vec<Vec<Vec3>>> {
        let k = self.learner().choice;
        self.rollout_with(k, state, actions)
    }

    fn rollout_batch(
        &self,
        state: &ModelState,
        actions: &[Actions],
    ) -> Vec<Result<Vec<Vec<Vec3>>>> {
        let k = self.learner().choice;
        match &self.nets[k] {
            None => {
                use rayon::prelude::*;
                actions
                    .par_iter()
                    .map(|a| backbone_rollout(&self.backbone, state, a))
                    .collect()
            }
            Some(net) => hybrid_batch(&self.backbone, net, state, actions),
        }
    }

    fn name(&self) -> &str {
        "pgrd-online"
    }

    fn observe_run(&self, observed: &[Vec<Vec3>], grippers: &[Vec<Vec3>], dt: f32) -> Result<()> {
        if grippers.len() != observed.len() {
            return Err(PlanError::Mismatch {
                what: "gripper frames vs observed frames",
                expected: observed.len(),
                got: grippers.len(),
            });
        }
        let mut l = self.learner();
        if observed.len() < l.scored {
            drop(l);
            self.reset();
            l = self.learner();
        }
        for end in l.scored.max(1)..observed.len() {
            let start = end.saturating_sub(self.window);
            let state = ModelState::from_frames(&observed[start.saturating_sub(3)..=start], dt)?;
            let path = grippers[start..=end].to_vec();
            let held = vec![vec![true; path[0].len()]; path.len()];
            let actions = Actions::new(path, held)?;
            let truth = &observed[start + 1..=end];
            for k in 0..self.gains.len() {
                // A gain whose prediction fails is the worst possible choice, not an error of
                // the run.
                let e = self
                    .rollout_with(k, &state, &actions)
                    .map_or(f64::INFINITY, |p| mean_distance(&p, truth));
                l.error[k] += e;
            }
        }
        l.scored = l.scored.max(observed.len());
        let mut best = l.choice;
        if observed.len() > 1 {
            best = 0;
            for k in 1..l.error.len() {
                if l.error[k] < l.error[best] {
                    best = k;
                }
            }
        }
        l.choice = best;
        let g = self.gains[best];
        l.chosen.push(g);
        Ok(())
    }
}
