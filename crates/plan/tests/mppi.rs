//! MPPI on a toy forward model: a point mass dragged by the gripper through a spring and a
//! damper. The same dynamics serve as "the real system", so a working planner must steer the
//! mass onto targets it can reach, and must not care how many threads evaluate its candidates.

use glam::Vec3;
use plan::{
    ForwardModel, LoopSettings, ModelState, Mppi, MppiConfig, Objective, PlanError, System,
    Workspace, run_closed_loop,
};
use springs::{Actions, BoxObstacle};

/// Spring constant and damping rate of the toy's gripper link, 1/s² and 1/s.
const K: f32 = 60.0;
const C: f32 = 12.0;
const DT: f32 = 0.1;
const SUBSTEPS: usize = 20;

/// One 0.1 s step of the point mass, the gripper moving linearly from `g0` to `g1`.
fn toy_step(x: &mut Vec3, v: &mut Vec3, g0: Vec3, g1: Vec3) {
    let h = DT / SUBSTEPS as f32;
    for s in 1..=SUBSTEPS {
        let g = g0.lerp(g1, s as f32 / SUBSTEPS as f32);
        *v += (K * (g - *x) - C * *v) * h;
        *x += *v * h;
    }
}

/// The toy as a forward model.
struct PointMass;

impl ForwardModel for PointMass {
    fn num_particles(&self) -> usize {
        1
    }
    fn name(&self) -> &str {
        "point-mass"
    }
    fn rollout(&self, s: &ModelState, a: &Actions) -> plan::Result<Vec<Vec<Vec3>>> {
        let (mut x, mut v) = (s.x[0], s.v[0]);
        let mut out = Vec::new();
        for t in 1..a.num_frames() {
            let (from, to) = (a.frame(t - 1).unwrap(), a.frame(t).unwrap());
            toy_step(&mut x, &mut v, from.positions[0], to.positions[0]);
            out.push(vec![x]);
        }
        Ok(out)
    }
}

/// The toy as the real system.
struct Toy {
    x: Vec3,
    v: Vec3,
    g: Vec3,
}

impl System for Toy {
    fn observe(&self) -> Vec<Vec3> {
        vec![self.x]
    }
    fn grippers(&self) -> Vec<Vec3> {
        vec![self.g]
    }
    fn step(&mut self, to: &[Vec3]) -> plan::Result<()> {
        toy_step(&mut self.x, &mut self.v, self.g, to[0]);
        self.g = to[0];
        Ok(())
    }
}

/// Fails about a third of the candidates, picked by the digits of their first step (so the
/// failures are spread over all directions).
struct FailsSome;

impl ForwardModel for FailsSome {
    fn num_particles(&self) -> usize {
        1
    }
    fn name(&self) -> &str {
        "fails-some"
    }
    fn rollout(&self, s: &ModelState, a: &Actions) -> plan::Result<Vec<Vec<Vec3>>> {
        let step = a.frame(1).unwrap().positions[0] - a.frame(0).unwrap().positions[0];
        if ((step.y * 1e5).abs() as i64) % 3 == 0 {
            return Err(PlanError::Model("diverged".into()));
        }
        PointMass.rollout(s, a)
    }
}

/// Fails always.
struct Broken;

impl ForwardModel for Broken {
    fn num_particles(&self) -> usize {
        1
    }
    fn name(&self) -> &str {
        "broken"
    }
    fn rollout(&self, _: &ModelState, _: &Actions) -> plan::Result<Vec<Vec<Vec3>>> {
        Err(PlanError::Model("always fails".into()))
    }
}

fn workspace() -> Workspace {
    Workspace {
        min: Vec3::splat(-1.0),
        max: Vec3::splat(1.0),
    }
}

fn run(
    model: &dyn ForwardModel,
    target: Vec3,
    objective: Option<Objective>,
    seed: u64,
) -> plan::Trajectory {
    let objective = objective.unwrap_or_else(|| Objective::new(&[target], workspace()).unwrap());
    let mut cfg = MppiConfig::simple();
    cfg.seed = seed;
    let mut mppi = Mppi::new(cfg, 1).unwrap();
    let mut toy = Toy {
        x: Vec3::ZERO,
        v: Vec3::ZERO,
        g: Vec3::ZERO,
    };
    let settings = LoopSettings {
        max_steps: 40,
        dt: DT,
    };
    run_closed_loop(model, &mut toy, &mut mppi, &objective, settings, &|_, _| {
        false
    })
    .unwrap()
}

#[test]
fn mppi_brings_a_point_mass_to_a_reachable_target() {
    let target = Vec3::new(0.3, -0.2, 0.1);
    let traj = run(&PointMass, target, None, 0);
    let end = traj.observed.last().unwrap()[0];
    assert!(
        end.distance(target) < 0.02,
        "mass ended at {end}, {:.3} m from the target",
        end.distance(target)
    );
    // Chamfer of one point to one point is twice their distance (two one-sided means).
    let first = traj.chamfer_m[0];
    assert!((first - 2.0 * f64::from(target.length())).abs() < 1e-6);
    assert!(*traj.chamfer_m.last().unwrap() < 0.1 * first);
}

#[test]
fn same_seed_same_plan_for_any_thread_count() {
    let target = Vec3::new(0.3, -0.2, 0.1);
    let in_pool = |threads: usize, seed: u64| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| run(&PointMass, target, None, seed))
    };
    let a = in_pool(1, 7);
    let b = in_pool(2, 7);
    assert_eq!(a.observed, b.observed);
    assert_eq!(a.chamfer_m, b.chamfer_m);
    let c = in_pool(2, 8);
    assert_ne!(
        a.observed, c.observed,
        "another seed should sample other paths"
    );
}

#[test]
fn failing_samples_are_dropped_and_planning_goes_on() {
    let target = Vec3::new(-0.25, 0.1, 0.0);
    let traj = run(&FailsSome, target, None, 0);
    let failed: usize = traj.replans.iter().map(|r| r.failed).sum();
    assert!(failed > 0, "some candidates should have failed");
    assert!(
        traj.stopped.is_none() && traj.observed.len() == 41,
        "the run went on to the end"
    );
    // With a third fewer candidates the plan is noisier, but it still gets there.
    let closest = traj.chamfer_m.iter().copied().fold(f64::INFINITY, f64::min);
    assert!(
        closest < 0.1 * traj.chamfer_m[0],
        "closest Chamfer {closest} m, start {} m",
        traj.chamfer_m[0]
    );
}

#[test]
fn a_model_that_always_fails_is_reported_not_hidden() {
    let objective = Objective::new(&[Vec3::X * 0.1], workspace()).unwrap();
    let mut mppi = Mppi::new(MppiConfig::simple(), 1).unwrap();
    let state = ModelState::at_rest(vec![Vec3::ZERO]);
    let err = mppi
        .plan(&Broken, &state, &[Vec3::ZERO], &objective)
        .unwrap_err();
    assert!(
        matches!(err, PlanError::AllRolloutsFailed { samples: 8, .. }),
        "{err}"
    );
    // In closed loop the run stops and says why.
    let traj = run(&Broken, Vec3::X * 0.1, None, 0);
    assert!(
        traj.stopped
            .as_deref()
            .unwrap_or("")
            .contains("always fails")
    );
    assert_eq!(traj.observed.len(), 1);
}

#[test]
fn the_gripper_respects_workspace_and_obstacles() {
    // Target above the workspace ceiling: the gripper stops at the ceiling.
    let ws = Workspace {
        min: Vec3::splat(-1.0),
        max: Vec3::new(1.0, 1.0, 0.05),
    };
    let target = Vec3::new(0.0, 0.0, 0.3);
    let objective = Objective::new(&[target], ws).unwrap();
    let traj = run(&PointMass, target, Some(objective), 0);
    assert!(traj.grippers.iter().all(|g| g[0].z <= 0.05 + 1e-6));
    // A wall between start and target that the gripper must not touch: it goes around.
    let wall = BoxObstacle::new(Vec3::new(0.1, -0.15, -1.0), Vec3::new(0.15, 0.15, 1.0)).unwrap();
    let target = Vec3::new(0.3, 0.0, 0.0);
    let mut objective = Objective::new(&[target], workspace()).unwrap();
    objective.obstacles = vec![wall];
    objective.gripper_clearance_m = 0.01;
    let traj = run(&PointMass, target, Some(objective.clone()), 0);
    for g in &traj.grippers {
        assert!(
            wall.distance(g[0]) >= 0.0099,
            "gripper at {} touches the wall",
            g[0]
        );
    }
    assert!(objective.violates(Vec3::new(0.12, 0.0, 0.0)));
}

#[test]
fn bad_inputs_are_errors() {
    assert!(
        Mppi::new(
            MppiConfig {
                samples: 0,
                ..MppiConfig::simple()
            },
            1
        )
        .is_err()
    );
    assert!(
        Mppi::new(
            MppiConfig {
                noise: f32::NAN,
                ..MppiConfig::simple()
            },
            1
        )
        .is_err()
    );
    assert!(Mppi::new(MppiConfig::simple(), 0).is_err());
    let objective = Objective::new(&[Vec3::ZERO], workspace()).unwrap();
    let mut mppi = Mppi::new(MppiConfig::simple(), 1).unwrap();
    let two = ModelState::at_rest(vec![Vec3::ZERO; 2]);
    assert!(
        mppi.plan(&PointMass, &two, &[Vec3::ZERO], &objective)
            .is_err()
    );
    let one = ModelState::at_rest(vec![Vec3::ZERO]);
    assert!(
        mppi.plan(&PointMass, &one, &[Vec3::ZERO; 2], &objective)
            .is_err()
    );
    assert!(
        mppi.plan(&PointMass, &one, &[Vec3::NAN], &objective)
            .is_err()
    );
    assert!(Objective::new(&[], workspace()).is_err());
    assert!(ModelState::from_frames(&[], 0.1).is_err());
    assert!(ModelState::from_frames(&[vec![Vec3::ZERO], vec![]], 0.1).is_err());
}

/// A workspace whose corners are swapped or not finite is refused with its smallest extent.
#[test]
fn a_bad_workspace_is_a_clear_error() {
    let swapped = Workspace {
        min: Vec3::new(-1.0, 1.0, -1.0),
        max: Vec3::new(1.0, 0.5, 1.0),
    };
    let err = Objective::new(&[Vec3::ZERO], swapped)
        .unwrap_err()
        .to_string();
    assert!(err.contains("workspace") && err.contains("-0.5"), "{err}");
    let open = Workspace {
        min: Vec3::splat(-1.0),
        max: Vec3::new(1.0, f32::INFINITY, 1.0),
    };
    assert!(Objective::new(&[Vec3::ZERO], open).is_err());
}
