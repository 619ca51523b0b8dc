//! The planning tasks on the reference world's rope: lift, lower, rotate, curve, and cable
//! rerouting through a slot. Each task's start is a settled state of the world; its target is
//! the world's state after a scripted gripper path (so the target is reachable in the world),
//! settled again. Geometry and success tests: `docs/plan.md`.

use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use springs::{
    Backbone, BackboneOptions, BoxObstacle, Obstacles, SimConfig, SpringParams, Substep,
};
use world::{ObjectKind, Plant, PlantConfig, Resolution};

use crate::{CostMode, MppiConfig, Objective, PlanError, Result, Trajectory, Workspace};

/// Seconds the world settles after placing the rope and after a scripted path.
const SETTLE_S: f32 = 1.0;
/// Gripper travel per step of the scripted paths, m.
const SCRIPT_STEP_M: f32 = 0.03;
/// Grasp point of the unrotated rope on the table (it runs +x from there, 0.9 m), m.
const ROPE_GRASP: Vec3 = Vec3::new(-0.4375, 0.0, 0.0);
/// Clearance kept between the gripper point and obstacles: the rope's radius (8 mm) around the
/// held end plus 4 mm, m.
const GRIPPER_CLEARANCE_M: f32 = 0.012;
/// Lowest gripper height allowed, m: the held end must not be pushed into the table.
const FLOOR_M: f32 = 0.008;
/// How far `rope-rotate` turns the rope about its far end, degrees. The largest of 50°, 40°,
/// 30°, 20° at which MPPI with the world itself as its model (`WorldOracle`) reached the
/// target in 3 of 3 trials: at 30–50° the dragged, plastic rope's shape depends on the exact
/// path and the oracle ended 2.3–4.3 cm away (`docs/plan.md`), so the task tested the planner,
/// not the model.
const ROTATE_DEG: f32 = 20.0;

/// A planning task.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TaskKind {
    /// Lift the rope's held end 30 cm off the table.
    RopeLift,
    /// Lower a lifted rope onto the table at another place.
    RopeLower,
    /// Rotate the rope on the table about its far end by 20° (the far end roughly fixed).
    RopeRotate,
    /// Drag the rope's end into a curved shape on the table.
    RopeCurve,
    /// Cable rerouting: pull the rope entirely through a narrow slot between two blocks.
    Reroute,
}

impl TaskKind {
    /// All five tasks.
    pub const ALL: [TaskKind; 5] = [
        TaskKind::RopeLift,
        TaskKind::RopeLower,
        TaskKind::RopeRotate,
        TaskKind::RopeCurve,
        TaskKind::Reroute,
    ];

    /// The name used on the command line (`rope-lift`, ..., `reroute`).
    pub fn name(self) -> &'static str {
        match self {
            TaskKind::RopeLift => "rope-lift",
            TaskKind::RopeLower => "rope-lower",
            TaskKind::RopeRotate => "rope-rotate",
            TaskKind::RopeCurve => "rope-curve",
            TaskKind::Reroute => "reroute",
        }
    }

    /// The paper's MPPI settings for this task: [`MppiConfig::rerouting`] for rerouting,
    /// [`MppiConfig::simple`] otherwise.
    pub fn mppi(self) -> MppiConfig {
        match self {
            TaskKind::Reroute => MppiConfig::rerouting(),
            _ => MppiConfig::simple(),
        }
    }
}

impl std::fmt::Display for TaskKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for TaskKind {
    type Err = PlanError;
    fn from_str(s: &str) -> Result<Self> {
        TaskKind::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| PlanError::UnknownTask(s.to_string()))
    }
}

/// The rerouting slot: a wall across the table along x, made of two blocks with a gap between
/// them, m.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Slot {
    /// x of the gap's centre.
    pub centre_x: f32,
    /// y of the wall's near face (the rope starts at smaller y).
    pub near_y: f32,
    /// Wall thickness along y.
    pub thickness: f32,
    /// Gap width along x.
    pub width: f32,
    /// Wall height (the top of the slot).
    pub height: f32,
    /// Length of each block along x.
    pub block_length: f32,
}

impl Slot {
    /// The slot of the rerouting task: a 6 cm gap (the rope is 1.6 cm thick) in a 4 cm thick,
    /// 10 cm tall wall whose near face is at y = 0.15 m, each block 0.6 m long.
    pub const REROUTE: Slot = Slot {
        centre_x: 0.0,
        near_y: 0.15,
        thickness: 0.04,
        width: 0.06,
        height: 0.10,
        block_length: 0.6,
    };

    /// y of the wall's far face.
    pub fn far_y(&self) -> f32 {
        self.near_y + self.thickness
    }

    /// The two blocks (left, right).
    pub fn boxes(&self) -> Result<[BoxObstacle; 2]> {
        let half = self.width / 2.0;
        let block = |x0: f32, x1: f32| {
            BoxObstacle::new(
                Vec3::new(x0, self.near_y, -0.05),
                Vec3::new(x1, self.far_y(), self.height),
            )
        };
        Ok([
            block(
                self.centre_x - half - self.block_length,
                self.centre_x - half,
            )?,
            block(
                self.centre_x + half,
                self.centre_x + half + self.block_length,
            )?,
        ])
    }

    /// The final-state half of rerouting's success test: every observed point lies beyond the
    /// wall's far face and the gripper is below the slot's top. (The workspace's ceiling is
    /// below the top, so a planned gripper always is; the test does not rely on it.)
    pub fn passed(&self, observed: &[Vec3], gripper: Vec3) -> bool {
        observed.iter().all(|p| p.y > self.far_y()) && gripper.z < self.height
    }

    /// The path half of the test: whether every crossing of the wall's mid-plane between
    /// consecutive frames (by each point of the frames, at its linearly interpolated x) lies
    /// within the wall's length, so that the rope went through the slot and not around the
    /// wall's ends, which the workspace leaves room for (17 cm beyond each end). Inside the
    /// wall's length the blocks are solid for the world's rope, so a crossing there is the
    /// gap's; the wall's length, not the gap's width, is the bound because a point's chord
    /// between two frames 0.1 s apart can cross the plane beside the gap while the point
    /// itself went through it. Frames are the observed points (or the gripper) at the start
    /// and after every executed step; frames of different lengths are compared over their
    /// common points.
    pub fn went_through<F: AsRef<[Vec3]>>(&self, frames: &[F]) -> bool {
        let mid = self.near_y + 0.5 * self.thickness;
        let reach = 0.5 * self.width + self.block_length;
        frames.windows(2).all(|w| {
            w[0].as_ref().iter().zip(w[1].as_ref()).all(|(a, b)| {
                let (da, db) = (a.y - mid, b.y - mid);
                if (da < 0.0) == (db < 0.0) {
                    return true;
                }
                let x = a.x + (b.x - a.x) * (da / (da - db));
                (x - self.centre_x).abs() <= reach
            })
        })
    }
}

/// What to build a task from.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskConfig {
    /// Trial index: rerouting draws its start and target from it; the simple tasks use the same
    /// start and target in every trial (as in the paper).
    pub trial: u64,
    /// The world's rope resolution.
    pub resolution: Resolution,
    /// Tracked (observed) rope particles.
    pub tracked: usize,
    /// The world's effects (default: the rope's defaults).
    pub effects: world::Effects,
    /// Seed of the world's material fields and tracked-point choice.
    pub world_seed: u64,
}

impl TaskConfig {
    /// Trial 0, coarse rope, 150 tracked points, the rope's default effects, world seed 0.
    pub fn new() -> Self {
        TaskConfig {
            trial: 0,
            resolution: Resolution::Coarse,
            tracked: 150,
            effects: world::Effects::defaults(ObjectKind::Rope),
            world_seed: 0,
        }
    }
}

impl Default for TaskConfig {
    fn default() -> Self {
        Self::new()
    }
}

/// A task instance: the world at its start, the target point cloud, workspace, obstacles, step
/// limit and success test.
#[derive(Clone, Debug)]
pub struct Task {
    /// Which task.
    pub kind: TaskKind,
    /// The world at the start (settled); clone it to run a trial.
    pub start: Plant,
    /// Target positions of the observed points, m.
    pub target: Vec<Vec3>,
    /// Where the scripted path that made the target left the gripper, m.
    pub target_gripper: Vec3,
    /// Where the gripper may go.
    pub workspace: Workspace,
    /// The slot (rerouting only).
    pub slot: Option<Slot>,
    /// Most executed steps per trial.
    pub max_steps: usize,
    /// Whether a trial ends as soon as it succeeds (the default for every task: the closed
    /// loop runs until done or the step limit) or always runs `max_steps` steps (so that final
    /// distances compare like for like).
    pub stop_at_success: bool,
    /// Success threshold of the simple tasks: final Chamfer distance (two-sided sum) below it, m.
    pub success_chamfer_m: f64,
}

impl Task {
    /// Builds task `kind`: places and settles the rope, runs the scripted path in a copy of the
    /// world to get the target.
    pub fn build(kind: TaskKind, cfg: &TaskConfig) -> Result<Task> {
        let slot = (kind == TaskKind::Reroute).then_some(Slot::REROUTE);
        let mut pc = PlantConfig::new(ObjectKind::Rope);
        pc.effects = cfg.effects.clone();
        pc.resolution = cfg.resolution;
        pc.seed = cfg.world_seed;
        pc.tracked = cfg.tracked;
        pc.grasp_at_m = ROPE_GRASP;
        let mut rng = ChaCha8Rng::seed_from_u64(
            0x0072_6572_6f75_7465 ^ cfg.trial.wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let mut reroute_end = Vec3::ZERO;
        if let Some(s) = &slot {
            pc.obstacles = s
                .boxes()?
                .iter()
                .map(|b| world::BoxObstacle::new(b.min, b.max))
                .collect::<std::result::Result<_, _>>()?;
            // The rope lies on the near side, running away from the wall (−y) within ±35° from
            // a grasp point 15 cm before the wall, up to 15 cm either side of the gap.
            pc.yaw_rad = -std::f32::consts::FRAC_PI_2 + rng.random_range(-0.6..0.6);
            pc.grasp_at_m = Vec3::new(s.centre_x + rng.random_range(-0.15..0.15), 0.0, 0.0);
            reroute_end = Vec3::new(
                s.centre_x + rng.random_range(-0.25..0.25),
                s.far_y() + rng.random_range(1.25..1.4),
                0.02,
            );
        }
        let mut start = Plant::new(&pc)?;
        start.settle(SETTLE_S)?;
        let g0 = start.gripper();
        if kind == TaskKind::RopeLower {
            drive(&mut start, &[g0 + Vec3::new(0.1, 0.0, 0.35)])?;
            start.settle(SETTLE_S)?;
        }
        let g = start.gripper();
        let path: Vec<Vec3> = match kind {
            TaskKind::RopeLift => vec![g + Vec3::new(0.0, 0.0, 0.30)],
            TaskKind::RopeLower => vec![Vec3::new(g0.x + 0.25, g0.y + 0.2, 0.02)],
            TaskKind::RopeRotate => {
                // Straight to the point ROTATE_DEG around the far end on the circle through
                // the gripper, at 2 cm height: the rope swings about its far end.
                let far = start
                    .observe()
                    .into_iter()
                    .max_by(|a, b| a.x.total_cmp(&b.x))
                    .unwrap_or(g);
                let r = Vec3::new(g.x - far.x, g.y - far.y, 0.0).length();
                let th = std::f32::consts::PI - ROTATE_DEG.to_radians();
                vec![Vec3::new(far.x + r * th.cos(), far.y + r * th.sin(), 0.02)]
            }
            TaskKind::RopeCurve => vec![g + Vec3::new(0.25, 0.35, 0.01)],
            TaskKind::Reroute => {
                let s = Slot::REROUTE;
                vec![
                    Vec3::new(s.centre_x, s.near_y - 0.06, 0.02),
                    Vec3::new(s.centre_x, s.far_y() + 0.06, 0.02),
                    reroute_end,
                ]
            }
        };
        let mut scripted = start.clone();
        drive(&mut scripted, &path)?;
        scripted.settle(SETTLE_S)?;
        let target = scripted.observe();
        let workspace = match &slot {
            Some(s) => Workspace {
                min: Vec3::new(-0.8, -1.1, FLOOR_M),
                max: Vec3::new(0.8, s.far_y() + 1.6, s.height - GRIPPER_CLEARANCE_M),
            },
            None => Workspace {
                min: Vec3::new(-1.0, -1.0, FLOOR_M),
                max: Vec3::new(1.0, 1.0, 0.6),
            },
        };
        if let Some(s) = &slot
            && !s.passed(&target, scripted.gripper())
        {
            return Err(PlanError::Model(format!(
                "rerouting trial {}: the scripted path did not pull the rope through the slot",
                cfg.trial
            )));
        }
        Ok(Task {
            kind,
            start,
            target,
            target_gripper: scripted.gripper(),
            workspace,
            slot,
            max_steps: if slot.is_some() { 80 } else { 30 },
            stop_at_success: true,
            success_chamfer_m: 0.02,
        })
    }

    /// The obstacles as the backbone sees them.
    pub fn obstacles(&self) -> Result<Vec<BoxObstacle>> {
        Ok(match &self.slot {
            Some(s) => s.boxes()?.to_vec(),
            None => Vec::new(),
        })
    }

    /// The planning objective: running Chamfer to the target (the mean over the horizon, which
    /// converged faster than the final-state Chamfer in our trials, see `docs/plan.md`), the
    /// workspace, the obstacles with the gripper's clearance.
    pub fn objective(&self) -> Result<Objective> {
        let mut o = Objective::new(&self.target, self.workspace)?;
        o.obstacles = self.obstacles()?;
        o.gripper_clearance_m = GRIPPER_CLEARANCE_M;
        o.mode = CostMode::Running;
        Ok(o)
    }

    /// Whether a trial that ended with `observed` points and the gripper at `gripper` succeeded
    /// by its final state: rerouting uses [`Slot::passed`], the simple tasks a Chamfer distance
    /// to the target below [`Task::success_chamfer_m`]. The closed loop stops on it; a trial is
    /// judged by [`Task::trial_success`].
    pub fn success(&self, observed: &[Vec3], gripper: Vec3) -> Result<bool> {
        match &self.slot {
            Some(s) => Ok(s.passed(observed, gripper)),
            None => Ok(self.objective()?.chamfer(observed)? < self.success_chamfer_m),
        }
    }

    /// Whether a closed-loop trial succeeded: [`Task::success`] on its last frame and, for
    /// rerouting, the rope and the gripper reached the far side through the slot
    /// ([`Slot::went_through`] on every frame). An empty trajectory is an error.
    pub fn trial_success(&self, trajectory: &Trajectory) -> Result<bool> {
        let (Some(last), Some(grip)) = (
            trajectory.observed.last(),
            trajectory.grippers.last().and_then(|g| g.first()),
        ) else {
            return Err(PlanError::Mismatch {
                what: "trajectory frames",
                expected: 1,
                got: 0,
            });
        };
        let path_ok = match &self.slot {
            Some(s) => s.went_through(&trajectory.observed) && s.went_through(&trajectory.grippers),
            None => true,
        };
        Ok(path_ok && self.success(last, *grip)?)
    }

    /// The spring-mass backbone of the observed rope at the start: its particles are the
    /// tracked points (springs from their start positions), held ones follow the gripper, the
    /// table is at z = 0 and the slot's blocks are obstacles.
    pub fn backbone(&self, params: SpringParams) -> Result<Backbone> {
        self.backbone_with(params, BackboneOptions::default())
    }

    /// [`Task::backbone`] with extra force terms or masses (a backbone that carries the
    /// effects of a gap diagnosis).
    pub fn backbone_with(
        &self,
        params: SpringParams,
        options: BackboneOptions,
    ) -> Result<Backbone> {
        self.backbone_under(params, Substep::AUTO, options)
    }

    /// [`Task::backbone_with`] under another substep rule: a model fitted with
    /// `Substep::SPECTRAL` has its damping fitted for that integrator, so it plans with it.
    pub fn backbone_under(
        &self,
        params: SpringParams,
        substep: Substep,
        options: BackboneOptions,
    ) -> Result<Backbone> {
        let config = SimConfig {
            obstacles: Obstacles::new(&self.obstacles()?)?,
            substep,
            ..SimConfig::default()
        };
        Ok(Backbone::with_options(
            &self.start.observe(),
            self.start.held(),
            params,
            config,
            options,
        )?)
    }
}

/// Moves the plant's gripper through `waypoints` in straight lines at up to
/// [`SCRIPT_STEP_M`] per step.
fn drive(plant: &mut Plant, waypoints: &[Vec3]) -> Result<()> {
    for &w in waypoints {
        let from = plant.gripper();
        let steps = ((w - from).length() / SCRIPT_STEP_M).ceil().max(1.0) as usize;
        for k in 1..=steps {
            plant.step(from.lerp(w, k as f32 / steps as f32))?;
        }
    }
    Ok(())
}
