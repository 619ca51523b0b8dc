//! Box obstacles in full rollouts: objects rest on them, are stopped by them, and a scene
//! without obstacles is unchanged by their existence.

use glam::Vec3;
use springs::{Actions, Backbone, BoxObstacle, Obstacles, SimConfig, SpringParams, State};

fn chain(n: usize, start: Vec3, step: Vec3) -> Vec<Vec3> {
    (0..n).map(|i| start + step * i as f32).collect()
}

fn config(boxes: &[BoxObstacle]) -> SimConfig {
    SimConfig {
        obstacles: Obstacles::new(boxes).unwrap(),
        ..SimConfig::default()
    }
}

#[test]
fn a_dropped_chain_comes_to_rest_on_top_of_a_block() {
    // A 20 cm chain 5 cm above a 10 cm tall block that is wider than the chain.
    let x = chain(21, Vec3::new(-0.1, 0.0, 0.15), Vec3::new(0.01, 0.0, 0.0));
    let block = BoxObstacle::new(Vec3::new(-0.2, -0.1, 0.0), Vec3::new(0.2, 0.1, 0.1)).unwrap();
    let bb = Backbone::new(&x, &[], SpringParams::reference_rope(), config(&[block])).unwrap();
    let out = bb
        .rollout(&State::at_rest(x), &Actions::without_grippers(11))
        .unwrap();
    for p in &out.positions[10] {
        assert!(
            (p.z - 0.1).abs() < 2e-3,
            "particle at {p:?} should rest on the block top (z = 0.1)"
        );
    }
    assert!(out.velocities[10].iter().all(|v| v.length() < 0.05));
}

#[test]
fn a_chain_pulled_through_a_slot_folds_through_the_gap() {
    // The middle particle is held and pulled 30 cm in +y through a 2 cm gap between two blocks,
    // while the chain lies across the gap along x: it must fold and follow through the gap.
    let x = chain(31, Vec3::new(-0.15, 0.0, 0.005), Vec3::new(0.01, 0.0, 0.0));
    let mut held = vec![-1; x.len()];
    held[15] = 0;
    let wall = |x0: f32, x1: f32| {
        BoxObstacle::new(Vec3::new(x0, 0.05, 0.0), Vec3::new(x1, 0.09, 0.2)).unwrap()
    };
    let boxes = [wall(-0.5, -0.01), wall(0.01, 0.5)];
    let bb = Backbone::new(&x, &held, SpringParams::reference_rope(), config(&boxes)).unwrap();
    let frames: Vec<Vec<Vec3>> = (0..16)
        .map(|t| vec![x[15] + Vec3::new(0.0, 0.02 * t as f32, 0.0)])
        .collect();
    let actions = Actions::new(frames, vec![vec![true]; 16]).unwrap();
    let out = bb.rollout(&State::at_rest(x), &actions).unwrap();
    for frame in &out.positions {
        for (i, p) in frame.iter().enumerate() {
            if i != 15 {
                assert!(
                    !boxes.iter().any(|b| b.contains(*p)),
                    "free particle {i} inside a wall at {p:?}"
                );
            }
        }
    }
    // Both ends came through the gap: past the wall, and funnelled close to the gap's axis.
    let last = out.positions.last().unwrap();
    for end in [last[0], last[30]] {
        assert!(end.y > 0.09 && end.x.abs() < 0.05, "end at {end:?}");
    }
}

#[test]
fn obstacles_far_away_change_nothing() {
    let x = chain(21, Vec3::new(-0.1, 0.0, 0.05), Vec3::new(0.01, 0.0, 0.0));
    let far = BoxObstacle::new(Vec3::splat(5.0), Vec3::splat(6.0)).unwrap();
    let run = |cfg: SimConfig| {
        Backbone::new(&x, &[], SpringParams::reference_rope(), cfg)
            .unwrap()
            .rollout(&State::at_rest(x.clone()), &Actions::without_grippers(6))
            .unwrap()
    };
    assert_eq!(run(config(&[far])), run(SimConfig::default()));
}

#[test]
fn invalid_obstacles_are_rejected() {
    assert!(BoxObstacle::new(Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0)).is_err());
    assert!(BoxObstacle::new(Vec3::ZERO, Vec3::new(f32::NAN, 1.0, 1.0)).is_err());
    let b = BoxObstacle::new(Vec3::ZERO, Vec3::ONE).unwrap();
    assert!(Obstacles::new(&[b; Obstacles::MAX + 1]).is_err());
}
