//! The world as its own forward model: it must predict the world it is executed on exactly,
//! from that world's current state, and refuse actions it cannot apply.

use glam::Vec3;
use plan::{ForwardModel, ModelState, PlanError, System, Task, TaskConfig, TaskKind, WorldOracle};
use springs::Actions;

fn task() -> Task {
    let cfg = TaskConfig {
        tracked: 40,
        ..TaskConfig::new()
    };
    Task::build(TaskKind::RopeLift, &cfg).unwrap()
}

fn path(from: Vec3, step: Vec3, frames: usize) -> Actions {
    let positions = (0..frames)
        .map(|k| vec![from + step * k as f32])
        .collect::<Vec<_>>();
    Actions::new(positions, vec![vec![true]; frames]).unwrap()
}

#[test]
fn the_oracle_predicts_what_its_system_then_does() {
    let task = task();
    let oracle = WorldOracle::new(task.start.clone());
    let mut system = oracle.system();
    // Move away from the start first, so a prediction from the start state would be wrong.
    let g = system.grippers()[0];
    for k in 1..=3 {
        system
            .step(&[g + Vec3::new(0.02, 0.0, 0.03) * k as f32])
            .unwrap();
    }
    let now = system.observe();
    assert_ne!(now, task.start.observe());
    let g = system.grippers()[0];
    let actions = path(g, Vec3::new(0.0, 0.03, 0.02), 5);
    let predicted = oracle
        .rollout(&ModelState::at_rest(now.clone()), &actions)
        .unwrap();
    assert_eq!(predicted.len(), 4);
    for (t, p) in predicted.iter().enumerate() {
        system
            .step(actions.frame(t + 1).unwrap().positions)
            .unwrap();
        assert_eq!(&system.observe(), p, "step {t}");
    }
    // Rolling out did not move the world itself; a plain copy stepped alike agrees.
    let mut copy = task.start.clone();
    for k in 1..=3 {
        copy.step(task.start.gripper() + Vec3::new(0.02, 0.0, 0.03) * k as f32)
            .unwrap();
    }
    for t in 1..5 {
        copy.step(actions.frame(t).unwrap().positions[0]).unwrap();
    }
    assert_eq!(copy.observe(), oracle.world().observe());
    assert_eq!(oracle.num_particles(), 40);
}

#[test]
fn the_oracle_refuses_actions_for_other_grippers() {
    let task = task();
    let oracle = WorldOracle::new(task.start.clone());
    let g = task.start.gripper();
    let two = Actions::new(vec![vec![g, g]; 3], vec![vec![true, true]; 3]).unwrap();
    let state = ModelState::at_rest(task.start.observe());
    assert!(matches!(
        oracle.rollout(&state, &two),
        Err(PlanError::Mismatch { .. })
    ));
    let bad = path(g, Vec3::new(0.0, 0.0, 1e30), 3);
    assert!(oracle.rollout(&state, &bad).is_err());
}
