//! `OnlinePgrd` finds the residual gain the system itself runs with: a "real system" that is
//! the hybrid model at a known gain (or the backbone alone) is told apart from the others by
//! the executed steps alone, inside the closed loop.

use std::sync::Arc;

use glam::Vec3;
use plan::{
    DEFAULT_GAINS, ForwardModel, LoopSettings, ModelState, Mppi, OnlinePgrd, Pgrd, SpringMass,
    System, Task, TaskConfig, TaskKind, run_closed_loop,
};
use residual::{ModelConfig, ResidualNet};
use springs::{Actions, SpringParams};

const DT: f32 = 0.1;

/// A forward model playing the real system: each step is its one-step prediction from the
/// last four observed frames, exactly what a model in the loop is handed.
struct ModelSystem {
    model: Box<dyn ForwardModel>,
    frames: Vec<Vec<Vec3>>,
    gripper: Vec3,
}

impl System for ModelSystem {
    fn observe(&self) -> Vec<Vec3> {
        self.frames[self.frames.len() - 1].clone()
    }
    fn grippers(&self) -> Vec<Vec3> {
        vec![self.gripper]
    }
    fn step(&mut self, to: &[Vec3]) -> plan::Result<()> {
        let recent = &self.frames[self.frames.len().saturating_sub(4)..];
        let state = ModelState::from_frames(recent, DT)?;
        let actions = Actions::new(vec![vec![self.gripper], to.to_vec()], vec![vec![true]; 2])?;
        let next = self.model.rollout(&state, &actions)?.remove(0);
        self.frames.push(next);
        self.gripper = to[0];
        Ok(())
    }
}

fn task() -> Task {
    let cfg = TaskConfig {
        tracked: 40,
        ..TaskConfig::new()
    };
    Task::build(TaskKind::RopeLift, &cfg).unwrap()
}

fn backbone(task: &Task) -> springs::Backbone {
    task.backbone(SpringParams::reference_rope()).unwrap()
}

/// An untrained network with a wide bound, so its residual is well above float rounding.
fn network() -> ResidualNet {
    let cfg = ModelConfig {
        residual_scale: 1.0,
        ..ModelConfig::tiny()
    };
    ResidualNet::new(&cfg, 11).unwrap()
}

#[test]
fn the_gain_the_system_runs_with_is_found() {
    let task = task();
    let net = network();
    // The system's own gain (None: the backbone alone).
    for truth in [None, Some(0.5f32), Some(1.0)] {
        let system_model: Box<dyn ForwardModel> = match truth {
            None => Box::new(SpringMass::new(backbone(&task))),
            Some(g) => Box::new(Pgrd::new(
                backbone(&task),
                Arc::new(net.with_residual_gain(g).unwrap()),
            )),
        };
        let mut system = ModelSystem {
            model: system_model,
            frames: vec![task.start.observe()],
            gripper: task.start.gripper(),
        };
        // Windows of one step: the model in the loop sees exactly the system's inputs, so
        // the true gain predicts without error and the others do not.
        let model = OnlinePgrd::new(backbone(&task), &net, &DEFAULT_GAINS, 1).unwrap();
        assert_eq!(model.gain(), 1.0);
        let mut mppi = Mppi::new(TaskKind::RopeLift.mppi(), 1).unwrap();
        let settings = LoopSettings {
            max_steps: 4,
            dt: DT,
        };
        let objective = task.objective().unwrap();
        let traj = run_closed_loop(
            &model,
            &mut system,
            &mut mppi,
            &objective,
            settings,
            &|_, _| false,
        )
        .unwrap();
        assert!(traj.stopped.is_none(), "{:?}", traj.stopped);
        let chosen = model.chosen_gains();
        assert_eq!(chosen.len(), 4, "one choice per executed step");
        let want = truth.unwrap_or(0.0);
        assert!(chosen.iter().all(|&g| g == want), "{truth:?}: {chosen:?}");
        let errors = model.mean_errors_m();
        let k = DEFAULT_GAINS.iter().position(|&g| g == want).unwrap();
        assert_eq!(errors[k], 0.0, "{errors:?}");
        assert!(
            errors.iter().enumerate().all(|(i, &e)| i == k || e > 0.0),
            "{errors:?}"
        );
        // A new run (fewer frames than scored) starts over at the network as trained.
        model
            .observe_run(&traj.observed[..1], &traj.grippers[..1], DT)
            .unwrap();
        assert_eq!(model.gain(), 1.0);
        model.reset();
        assert!(model.chosen_gains().is_empty());
        assert!(model.mean_errors_m().is_empty());
    }
}

#[test]
fn bad_settings_are_refused() {
    let task = task();
    let net = network();
    assert!(OnlinePgrd::new(backbone(&task), &net, &[], 5).is_err());
    assert!(OnlinePgrd::new(backbone(&task), &net, &[0.0, -1.0], 5).is_err());
    assert!(OnlinePgrd::new(backbone(&task), &net, &[f32::NAN], 5).is_err());
    assert!(OnlinePgrd::new(backbone(&task), &net, &DEFAULT_GAINS, 0).is_err());
    // Without gain 1 it starts at the largest.
    let m = OnlinePgrd::new(backbone(&task), &net, &[0.0, 0.25, 0.5], 5).unwrap();
    assert_eq!(m.gain(), 0.5);
    // Mismatched histories are an error, not a panic.
    let x = task.start.observe();
    assert!(
        m.observe_run(&[x.clone(), x], &[vec![task.start.gripper()]], DT)
            .is_err()
    );
}

/// Against the reference world, the gains chosen and the executed path do not depend on how
/// many threads evaluate the candidates.
#[test]
fn the_choice_does_not_depend_on_the_thread_count() {
    let task = task();
    let net = network();
    let in_pool = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let model = OnlinePgrd::new(backbone(&task), &net, &DEFAULT_GAINS, 3).unwrap();
                let mut world = task.start.clone();
                let mut mppi = Mppi::new(TaskKind::RopeLift.mppi(), 1).unwrap();
                let settings = LoopSettings {
                    max_steps: 5,
                    dt: DT,
                };
                let objective = task.objective().unwrap();
                let traj = run_closed_loop(
                    &model,
                    &mut world,
                    &mut mppi,
                    &objective,
                    settings,
                    &|_, _| false,
                )
                .unwrap();
                (traj.observed, model.chosen_gains(), model.mean_errors_m())
            })
    };
    let (a, b) = (in_pool(1), in_pool(2));
    assert_eq!(a.1.len(), 5);
    assert_eq!(a, b);
}
