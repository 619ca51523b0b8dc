//! The planning tasks on the reference world's rope, and one closed-loop run against it.

use glam::Vec3;
use plan::{LoopSettings, Mppi, Slot, SpringMass, Task, TaskConfig, TaskKind, run_closed_loop};

/// A coarse rope observed through 60 points keeps these tests quick.
fn config(trial: u64) -> TaskConfig {
    TaskConfig {
        trial,
        tracked: 60,
        ..TaskConfig::new()
    }
}

#[test]
fn every_task_builds_with_a_target_away_from_its_start() {
    for kind in TaskKind::ALL {
        let task = Task::build(kind, &config(0)).unwrap();
        let start = task.start.observe();
        let o = task.objective().unwrap();
        let d = o.chamfer(&start).unwrap();
        assert!(d > 0.05, "{kind}: start only {d} m from the target");
        assert!(o.chamfer(&task.target).unwrap() < 1e-9);
        assert!(
            !task.success(&start, task.start.gripper()).unwrap(),
            "{kind}"
        );
        assert!(
            task.success(&task.target, task.target_gripper).unwrap(),
            "{kind}"
        );
        assert_eq!(kind.name().parse::<TaskKind>().unwrap(), kind);
    }
    let err = "rope-jump".parse::<TaskKind>().unwrap_err().to_string();
    assert!(
        err.contains("`rope-jump`") && err.contains("reroute"),
        "{err}"
    );
}

#[test]
fn rerouting_trials_differ_and_the_slot_test_is_geometric() {
    let a = Task::build(TaskKind::Reroute, &config(0)).unwrap();
    let b = Task::build(TaskKind::Reroute, &config(1)).unwrap();
    assert_ne!(a.start.observe(), b.start.observe());
    assert_ne!(a.target, b.target);
    let s = Slot::REROUTE;
    let through = vec![Vec3::new(0.0, s.far_y() + 0.01, 0.01); 3];
    assert!(s.passed(&through, Vec3::new(0.0, 1.0, 0.05)));
    // The gripper above the slot's top, or one point still in the slot: not passed.
    assert!(!s.passed(&through, Vec3::new(0.0, 1.0, s.height + 0.01)));
    let mut stuck = through.clone();
    stuck[1].y = s.near_y + 0.01;
    assert!(!s.passed(&stuck, Vec3::new(0.0, 1.0, 0.05)));
    // Both blocks leave exactly the slot's width between them.
    let [l, r] = s.boxes().unwrap();
    assert!((r.min.x - l.max.x - s.width).abs() < 1e-6);
}

/// A point's path from the near side to `end`, the wall's mid-plane crossed at `x_cross`.
fn crossing(x_cross: f32, end: Vec3) -> Vec<Vec<Vec3>> {
    let s = Slot::REROUTE;
    let mid = s.near_y + 0.5 * s.thickness;
    [
        Vec3::new(x_cross, s.near_y - 0.3, 0.01),
        Vec3::new(x_cross, mid - 0.01, 0.01),
        Vec3::new(x_cross, mid + 0.01, 0.01),
        end,
    ]
    .iter()
    .map(|p| vec![*p])
    .collect()
}

#[test]
fn rerouting_counts_only_a_rope_that_went_through_the_slot() {
    let s = Slot::REROUTE;
    let end = Vec3::new(0.0, s.far_y() + 1.3, 0.01);
    let wall_end = 0.5 * s.width + s.block_length;
    assert!(s.went_through(&crossing(0.0, end)));
    // A chord between two frames may cross beside the gap, within the wall's length.
    assert!(s.went_through(&crossing(0.2, end)));
    // Around the wall's end, on either side: not through the slot.
    assert!(!s.went_through(&crossing(wall_end + 0.05, end)));
    assert!(!s.went_through(&crossing(-wall_end - 0.05, end)));
    // Diagonal chords: interpolated at the mid-plane.
    let mid = s.near_y + 0.5 * s.thickness;
    let diagonal = |x0: f32, x1: f32| {
        vec![
            vec![Vec3::new(x0, mid - 0.1, 0.01)],
            vec![Vec3::new(x1, mid + 0.1, 0.01)],
        ]
    };
    assert!(s.went_through(&diagonal(0.5, 0.7)));
    assert!(!s.went_through(&diagonal(0.7, 0.8)));

    // A trial is judged on its whole path: the same final state counts only through the slot.
    let task = Task::build(TaskKind::Reroute, &config(0)).unwrap();
    let trial = |x_cross: f32| plan::Trajectory {
        observed: crossing(x_cross, end)
            .into_iter()
            .map(|f| vec![f[0]; 3])
            .collect(),
        grippers: crossing(0.0, end),
        chamfer_m: vec![0.0; 4],
        replans: Vec::new(),
        done: true,
        stopped: None,
    };
    assert!(task.success(&[end; 3], end).unwrap());
    assert!(task.trial_success(&trial(0.0)).unwrap());
    assert!(!task.trial_success(&trial(wall_end + 0.05)).unwrap());
    let mut empty = trial(0.0);
    empty.observed.clear();
    assert!(task.trial_success(&empty).is_err());
    // The simple tasks have no path condition.
    let lift = Task::build(TaskKind::RopeLift, &config(0)).unwrap();
    let held = plan::Trajectory {
        observed: vec![lift.target.clone(); 2],
        grippers: vec![vec![lift.target_gripper]; 2],
        ..trial(0.0)
    };
    assert!(lift.trial_success(&held).unwrap());
}

#[test]
fn spring_mass_mppi_lifts_the_world_rope() {
    let task = Task::build(TaskKind::RopeLift, &config(0)).unwrap();
    let model = SpringMass::new(
        task.backbone(springs::SpringParams::reference_rope())
            .unwrap(),
    );
    let mut mppi = Mppi::new(TaskKind::RopeLift.mppi(), 1).unwrap();
    let mut world = task.start.clone();
    let objective = task.objective().unwrap();
    let settings = LoopSettings {
        max_steps: 25,
        dt: 0.1,
    };
    let done = |x: &[Vec3], g: &[Vec3]| task.success(x, g[0]).unwrap();
    let traj = run_closed_loop(&model, &mut world, &mut mppi, &objective, settings, &done).unwrap();
    assert!(
        traj.done,
        "not lifted in 25 steps; Chamfer went {:?}",
        traj.chamfer_m
    );
    assert!(*traj.chamfer_m.last().unwrap() < task.success_chamfer_m);
    assert_eq!(traj.observed.len(), traj.grippers.len());
    assert_eq!(traj.replans.len() + 1, traj.observed.len());
}

#[test]
fn a_backbone_with_effects_predicts_differently_and_default_options_change_nothing() {
    use plan::{ForwardModel, ModelState};
    let task = Task::build(TaskKind::RopeRotate, &config(0)).unwrap();
    let params = springs::SpringParams::reference_rope();
    let rest = task.start.observe();
    let state = ModelState::from_frames(&[rest.clone(), rest.clone()], 0.1).unwrap();
    let g = task.start.gripper();
    let path: Vec<Vec<Vec3>> = (0..=5)
        .map(|k| vec![g + Vec3::new(0.0, 0.03 * k as f32, 0.0)])
        .collect();
    let actions = springs::Actions::new(path, vec![vec![true]; 6]).unwrap();
    let predict = |bb: springs::Backbone| SpringMass::new(bb).rollout(&state, &actions).unwrap();
    let plain = predict(task.backbone(params).unwrap());
    let default = predict(
        task.backbone_with(params, springs::BackboneOptions::default())
            .unwrap(),
    );
    assert_eq!(plain, default);
    let frame = gap::MaterialFrame::of_shape(&rest).unwrap();
    let effects = gap::BaseEffect::parse_list("bending=0.3").unwrap();
    let bent = predict(
        task.backbone_with(params, gap::backbone_options(&effects, &frame))
            .unwrap(),
    );
    let moved = plain[4]
        .iter()
        .zip(&bent[4])
        .map(|(a, b)| a.distance(*b))
        .fold(0.0f32, f32::max);
    assert!(
        moved > 1e-3,
        "bending moved the prediction by only {moved} m"
    );
}

#[test]
fn a_backbone_under_the_spectral_rule_takes_fewer_substeps_and_auto_is_the_default() {
    let task = Task::build(TaskKind::RopeLift, &config(0)).unwrap();
    // Stiff enough that the stability bound, not the 2 ms accuracy cap, sets the substep.
    let params = springs::SpringParams {
        stiffness: 4e5,
        ..springs::SpringParams::reference_rope()
    };
    let none = springs::BackboneOptions::default;
    let auto = task
        .backbone_under(params, springs::Substep::AUTO, none())
        .unwrap();
    let spectral = task
        .backbone_under(params, springs::Substep::SPECTRAL, none())
        .unwrap();
    assert_eq!(auto.substeps(), task.backbone(params).unwrap().substeps());
    assert!(
        spectral.substeps() < auto.substeps(),
        "spectral {} vs auto {}",
        spectral.substeps(),
        auto.substeps()
    );
}
