//! Closed-loop execution: plan with the model, execute the first step on the real system,
//! observe, replan — until done or a step limit.

use std::time::Instant;

use glam::Vec3;

use crate::{ForwardModel, ModelState, Mppi, Objective, PlanError, Result};

/// The system a plan is executed on ("the real system"): observed through its tracked points,
/// driven by gripper position commands one step at a time.
pub trait System {
    /// Positions of the observed points now, m (the same points, in the same order, as the
    /// forward model's particles).
    fn observe(&self) -> Vec<Vec3>;
    /// Where the grippers are now, m.
    fn grippers(&self) -> Vec<Vec3>;
    /// Moves the grippers to `to` (m) over one step.
    fn step(&mut self, to: &[Vec3]) -> Result<()>;
}

impl System for world::Plant {
    fn observe(&self) -> Vec<Vec3> {
        world::Plant::observe(self)
    }
    fn grippers(&self) -> Vec<Vec3> {
        vec![self.gripper()]
    }
    fn step(&mut self, to: &[Vec3]) -> Result<()> {
        match to {
            [g] => Ok(world::Plant::step(self, *g)?),
            _ => Err(PlanError::Mismatch {
                what: "gripper commands for a plant",
                expected: 1,
                got: to.len(),
            }),
        }
    }
}

/// Settings of [`run_closed_loop`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopSettings {
    /// Most steps executed.
    pub max_steps: usize,
    /// Step length of the system and the model, s (velocities are observed by differences).
    pub dt: f32,
}

/// One replanning step's statistics.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplanStats {
    /// Wall time of the replanning step, s.
    pub wall_s: f64,
    /// The best candidate's cost in the last iteration.
    pub best_cost: f64,
    /// The standard deviation of that candidate's costs over the model's members (0 for a
    /// model of one member; [`crate::PlanStep::best_member_sd`]).
    pub best_member_sd: f64,
    /// Candidate rollouts that failed.
    pub failed: usize,
    /// Candidate rollouts run.
    pub rollouts: usize,
    /// Wall time the model then took to hear what the executed step did
    /// ([`ForwardModel::observe_run`]; about 0 for models that ignore it), s.
    pub observe_wall_s: f64,
}

/// What happened in one closed-loop run.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    /// Observed points at the start and after every executed step, m.
    pub observed: Vec<Vec<Vec3>>,
    /// Gripper positions at the start and after every executed step, m.
    pub grippers: Vec<Vec<Vec3>>,
    /// Chamfer distance (two-sided sum, m) of every observed frame to the target.
    pub chamfer_m: Vec<f64>,
    /// One entry per replanning step.
    pub replans: Vec<ReplanStats>,
    /// Whether `done` held before the step limit.
    pub done: bool,
    /// Why the run stopped early, if it did (every candidate failed, or the system refused a
    /// command or diverged).
    pub stopped: Option<String>,
}

/// Runs MPPI in closed loop: observe the system, build the model's state from the observations
/// (velocities by differences over `dt`), plan, command the first step, repeat until
/// `done(observed, grippers)` holds or `max_steps` steps were executed. Failures inside the loop
/// end the run and are recorded in [`Trajectory::stopped`]; mismatched inputs are errors.
pub fn run_closed_loop(
    model: &dyn ForwardModel,
    system: &mut dyn System,
    mppi: &mut Mppi,
    objective: &Objective,
    settings: LoopSettings,
    done: &dyn Fn(&[Vec3], &[Vec3]) -> bool,
) -> Result<Trajectory> {
    let first = system.observe();
    if first.len() != model.num_particles() {
        return Err(PlanError::Mismatch {
            what: "observed points vs model particles",
            expected: model.num_particles(),
            got: first.len(),
        });
    }
    let mut out = Trajectory {
        chamfer_m: vec![objective.chamfer(&first)?],
        observed: vec![first],
        grippers: vec![system.grippers()],
        replans: Vec::new(),
        done: false,
        stopped: None,
    };
    for _ in 0..settings.max_steps {
        let (obs, grip) = (
            &out.observed[out.observed.len() - 1],
            &out.grippers[out.grippers.len() - 1],
        );
        if done(obs, grip) {
            out.done = true;
            break;
        }
        let recent = &out.observed[out.observed.len().saturating_sub(4)..];
        let state = ModelState::from_frames(recent, settings.dt)?;
        let t0 = Instant::now();
        let step = match mppi.plan(model, &state, grip, objective) {
            Ok(s) => s,
            Err(e @ PlanError::AllRolloutsFailed { .. }) => {
                out.stopped = Some(e.to_string());
                break;
            }
            Err(e) => return Err(e),
        };
        out.replans.push(ReplanStats {
            wall_s: t0.elapsed().as_secs_f64(),
            best_cost: step.best_cost.last().copied().unwrap_or(f64::INFINITY),
            best_member_sd: step.best_member_sd.last().copied().unwrap_or(f64::NAN),
            failed: step.failed,
            rollouts: step.rollouts,
            observe_wall_s: 0.0,
        });
        if let Err(e) = system.step(&step.next) {
            out.stopped = Some(e.to_string());
            break;
        }
        let obs = system.observe();
        out.chamfer_m.push(objective.chamfer(&obs)?);
        out.observed.push(obs);
        out.grippers.push(system.grippers());
        let t1 = Instant::now();
        let heard = model.observe_run(&out.observed, &out.grippers, settings.dt);
        if let Some(last) = out.replans.last_mut() {
            last.observe_wall_s = t1.elapsed().as_secs_f64();
        }
        if let Err(e) = heard {
            out.stopped = Some(e.to_string());
            break;
        }
    }
    if !out.done && out.stopped.is_none() {
        let (obs, grip) = (
            &out.observed[out.observed.len() - 1],
            &out.grippers[out.grippers.len() - 1],
        );
        out.done = done(obs, grip);
    }
    Ok(out)
}
