//! A frame where the tracker saw no tracked point is not scored.

use dataset::{DatasetMeta, Episode, Manipulation};
use glam::Vec3;
use scene::{Scene, SceneConfig, Window};

/// Two points 2 cm apart, still, over 6 frames; frame 4 (step 3 of a window starting at 1)
/// has neither seen, and their stored positions there are 30 cm off (a stale report).
fn scene() -> Scene {
    let meta = DatasetMeta::new("pair", 10.0, Manipulation::Grasp);
    let mut positions = Vec::new();
    let mut visible = Vec::new();
    for t in 0..6 {
        let off = if t == 4 { Vec3::X * 0.3 } else { Vec3::ZERO };
        positions.push(Vec3::new(0.0, 0.0, 0.1) + off);
        positions.push(Vec3::new(0.02, 0.0, 0.1) + off);
        visible.extend([u8::from(t != 4); 2]);
    }
    let episode = Episode::new(6, 2, 1, positions, vec![Vec3::splat(0.5); 6])
        .and_then(|e| e.with_visible(visible))
        .unwrap();
    let window = Window { start: 1, steps: 4 };
    Scene::new(&meta, &episode, window, &SceneConfig::default()).unwrap()
}

#[test]
fn a_frame_nothing_was_seen_in_is_not_scored() {
    let s = scene();
    // A prediction 1 cm above the truth everywhere it was seen.
    let pred: Vec<Vec<Vec3>> = (0..4)
        .map(|_| vec![Vec3::new(0.0, 0.0, 0.11), Vec3::new(0.02, 0.0, 0.11)])
        .collect();
    let steps = scene::score_steps(&s, &pred, true).unwrap();
    assert_eq!(
        steps.iter().map(Option::is_some).collect::<Vec<_>>(),
        [true, true, false, true]
    );
    for e in steps.iter().flatten() {
        assert!(
            (e.mde - 0.01).abs() < 1e-6 && (e.emd - 0.01).abs() < 1e-6,
            "{e:?}"
        );
    }
    let mean = scene::mean_over_steps(&steps, |e| e.mde).unwrap();
    assert!(
        (mean - 0.01).abs() < 1e-6,
        "the stale frame would have raised it: {mean}"
    );
    // The fitting loss skips it too: 1 cm squared.
    let mse = scene::position_mse(&s, &pred).unwrap();
    assert!((mse - 1e-4).abs() < 1e-9, "{mse}");
    assert_eq!(scene::sum_over_steps(&steps, |e| e.mde).1, 3);
}
