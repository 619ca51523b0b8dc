//! A dataset written from Python with numpy alone: `fixtures/numpy_writer/chain`, made by the
//! `write_dataset.py` beside it, whose `fixture_episode` holds the formulas checked here. It
//! shows that the script users copy into their own tracking pipelines writes what pgrd reads.

use std::path::{Path, PathBuf};

use dataset::{Dataset, Manipulation, Split, Structure};
use glam::Vec3;

fn chain() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/numpy_writer/chain")
}

/// The script's constants.
const POINTS: usize = 12;
const FRAMES: usize = 40;
const FPS: f64 = 10.0;

/// Point `i` of episode `k` at frame `t`, as `fixture_episode` computes it (in float64, then
/// stored as float32).
fn truth(k: usize, t: usize, i: usize) -> Vec3 {
    let time = t as f64 / FPS;
    let period = FRAMES as f64 / FPS;
    let x = 0.05 * (2.0 * std::f64::consts::PI * time / period).sin() + 0.1 * k as f64;
    Vec3::new(x as f32, 0.0, (0.5 - 0.02 * i as f64) as f32)
}

#[test]
fn pgrd_reads_what_the_numpy_script_writes() {
    let data = Dataset::open(chain()).unwrap();
    let meta = &data.meta;
    assert_eq!(meta.object, "chain");
    assert_eq!(meta.fps, 10.0);
    assert_eq!(meta.gravity, [0.0, 0.0, -9.81]);
    assert_eq!(meta.ground_z, Some(0.0));
    assert_eq!(meta.manipulation, Manipulation::Grasp);
    assert_eq!(meta.gripper_radius, 0.01);
    assert_eq!(meta.structure, Structure::Points);
    assert_eq!(data.split_indices(Split::Train), vec![0, 1]);
    assert_eq!(data.split_indices(Split::Val), vec![2]);
    for k in 0..3 {
        let ep = data.load_episode(k).unwrap();
        assert_eq!(
            (ep.frames(), ep.particles(), ep.grippers()),
            (FRAMES, POINTS, 1)
        );
        let mut worst = 0f32;
        for t in 0..FRAMES {
            for (i, p) in ep.frame(t).iter().enumerate() {
                worst = worst.max((*p - truth(k, t, i)).abs().max_element());
                // Point 5 is hidden in frames 4-6 only.
                assert_eq!(ep.visible(t, i), !(i == 5 && (4..7).contains(&t)));
            }
            let grip = ep.gripper_frame(t);
            assert_eq!(grip.len(), 1);
            worst = worst.max((grip[0] - truth(k, t, 0)).abs().max_element());
            assert!(ep.closed(t, 0));
        }
        // numpy's and Rust's sines may differ in the last bit of a float64.
        assert!(worst < 1e-6, "episode {k}: {worst} m from the formula");
        let mut held = vec![-1; POINTS];
        held[0] = 0;
        assert_eq!(ep.held(), Some(held.as_slice()));
        let colors = ep.colors().unwrap();
        assert_eq!(colors[0], [0.0; 3]);
        assert_eq!(colors[POINTS - 1], [1.0; 3]);
    }
}
