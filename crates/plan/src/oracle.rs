//! The reference world as its own forward model: a perfect model of the "real system", for
//! telling a task the planner cannot solve from a model that is not good enough.

use std::sync::{PoisonError, RwLock};

use glam::Vec3;
use springs::Actions;
use world::Plant;

use crate::{ForwardModel, ModelState, PlanError, Result, System};

/// The reference world itself as the forward model ("oracle").
///
/// It owns the world that plays the real system: [`WorldOracle::system`] is the handle the
/// closed loop executes on, and every rollout steps a copy of that world's exact current state
/// (positions, velocities, hidden material state such as plastic rest lengths) through the
/// candidate's gripper path and observes it. The [`ModelState`] built from observations is
/// therefore ignored: a model cannot be better than this one, so a task that MPPI fails with
/// it fails because of the planner or the task, not the model.
///
/// ```
/// use plan::{LoopSettings, Mppi, Task, TaskConfig, TaskKind, WorldOracle, run_closed_loop};
/// let cfg = TaskConfig { tracked: 40, ..TaskConfig::new() };
/// let task = Task::build(TaskKind::RopeLift, &cfg)?;
/// let oracle = WorldOracle::new(task.start.clone());
/// let mut mppi = Mppi::new(TaskKind::RopeLift.mppi(), 1)?;
/// let settings = LoopSettings { max_steps: 3, dt: 0.1 };
/// let traj = run_closed_loop(&oracle, &mut oracle.system(), &mut mppi, &task.objective()?, settings, &|_, _| false)?;
/// assert!(traj.chamfer_m[3] < traj.chamfer_m[0]);
/// # Ok::<(), plan::PlanError>(())
/// ```
#[derive(Debug)]
pub struct WorldOracle {
    world: RwLock<Plant>,
}

impl WorldOracle {
    /// The oracle of `world`, which becomes the system the plan is executed on.
    pub fn new(world: Plant) -> Self {
        WorldOracle {
            world: RwLock::new(world),
        }
    }

    /// The handle through which the closed loop observes and steps the world.
    pub fn system(&self) -> OracleSystem<'_> {
        OracleSystem(self)
    }

    /// A copy of the world as it is now.
    pub fn world(&self) -> Plant {
        // The lock is poisoned only if a step panicked, which has already unwound the loop
        // that owned this oracle; reading the world afterwards is harmless.
        self.world
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

impl ForwardModel for WorldOracle {
    fn num_particles(&self) -> usize {
        self.world
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .tracked_indices()
            .len()
    }

    fn rollout(&self, _state: &ModelState, actions: &Actions) -> Result<Vec<Vec<Vec3>>> {
        if actions.num_grippers() != 1 {
            return Err(PlanError::Mismatch {
                what: "grippers in the oracle's actions",
                expected: 1,
                got: actions.num_grippers(),
            });
        }
        let mut plant = self.world();
        let mut out = Vec::with_capacity(actions.num_frames().saturating_sub(1));
        for t in 1..actions.num_frames() {
            let frame = actions.frame(t).ok_or(PlanError::Mismatch {
                what: "action frames",
                expected: t + 1,
                got: t,
            })?;
            plant.step(frame.positions[0])?;
            out.push(plant.observe());
        }
        Ok(out)
    }

    fn name(&self) -> &str {
        "world"
    }
}

/// The closed loop's view of a [`WorldOracle`]'s world (see [`WorldOracle::system`]).
#[derive(Debug)]
pub struct OracleSystem<'a>(&'a WorldOracle);

impl System for OracleSystem<'_> {
    fn observe(&self) -> Vec<Vec3> {
        self.0
            .world
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .observe()
    }

    fn grippers(&self) -> Vec<Vec3> {
        vec![
            self.0
                .world
                .read()
                .unwrap_or_else(PoisonError::into_inner)
                .gripper(),
        ]
    }

    fn step(&mut self, to: &[Vec3]) -> Result<()> {
        let mut w = self.0.world.write().unwrap_or_else(PoisonError::into_inner);
        System::step(&mut *w, to)
    }
}
