//! MPPI planning of gripper paths with a forward model of a deformable object, executed in
//! closed loop against the reference world.
//!
//! PGRD's planning application (the paper's Section "Planning using PGRD"): a [`ForwardModel`]
//! (the spring-mass backbone alone, [`SpringMass`], or with the residual network, [`Pgrd`];
//! the world itself, [`WorldOracle`], as a perfect model for checking the planner and the tasks;
//! PGRD whose residual gain is chosen in closed loop from the observed steps, [`OnlinePgrd`])
//! predicts what candidate gripper paths do to the object; [`Mppi`] samples candidates around
//! its mean path, scores them with an [`Objective`] (Chamfer distance to a target point cloud
//! plus workspace and obstacle penalties) and moves the mean towards the cheap ones. A model of
//! several members ([`Pgrd::with_member_trajectories`]: each network of an ensemble on its own
//! trajectory) has every candidate scored under each member, by their mean cost plus
//! [`MppiConfig::member_risk`] times their spread.
//! [`run_closed_loop`] executes the first step of each plan on a [`System`] — the reference
//! world's [`world::Plant`] stands in for the real one — observes, and replans. [`Task`] builds
//! the paper's rope tasks (lift, lower, rotate, curve, cable rerouting through a [`Slot`]).
//! Design and tasks: `docs/plan.md`; the measured runs: `docs/plan-log.md`.
//!
//! ```
//! use plan::{LoopSettings, Mppi, SpringMass, Task, TaskConfig, TaskKind, run_closed_loop};
//! let cfg = TaskConfig { tracked: 60, ..TaskConfig::new() };
//! let task = Task::build(TaskKind::RopeLift, &cfg)?;
//! let model = SpringMass::new(task.backbone(springs::SpringParams::reference_rope())?);
//! let mut mppi = Mppi::new(TaskKind::RopeLift.mppi(), 1)?;
//! let mut world = task.start.clone(); // the "real system"
//! let settings = LoopSettings { max_steps: 4, dt: 0.1 };
//! let traj = run_closed_loop(&model, &mut world, &mut mppi, &task.objective()?, settings, &|_, _| false)?;
//! // Chamfer distance to the target (m) before and after four executed steps.
//! assert!(traj.chamfer_m[4] < traj.chamfer_m[0]);
//! # Ok::<(), plan::PlanError>(())
//! ```

mod closed_loop;
mod cost;
mod error;
mod model;
mod mppi;
mod nearest;
mod online;
mod oracle;
pub mod render;
mod task;

pub use closed_loop::{LoopSettings, ReplanStats, System, Trajectory, run_closed_loop};
pub use cost::{CostMode, Objective, Workspace};
pub use error::{PlanError, Result};
pub use model::{ForwardModel, MemberPredictions, ModelState, Pgrd, SpringMass};
pub use mppi::{Mppi, MppiConfig, PlanStep};
pub use online::{DEFAULT_GAINS, OnlinePgrd};
pub use oracle::{OracleSystem, WorldOracle};
pub use task::{Slot, Task, TaskConfig, TaskKind};
