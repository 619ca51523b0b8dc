//! The PhysTwin importer on `fixtures/phystwin/rope_lift`, a synthetic case written by numpy
//! 1.26 as PhysTwin lays out its files (`make.py` beside it holds the formulas checked here).

mod common;

use std::path::{Path, PathBuf};

use dataset::import::phystwin::{self, PhysTwinOptions};
use dataset::{ControllerSprings, Dataset, Manipulation, Split};
use glam::Vec3;

fn case() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/phystwin/rope_lift")
}

/// Ten kept frames every five: the fixture's 120 frames at 30 fps give 28 kept training
/// frames (source frames 0..84) and 12 test frames.
fn small() -> PhysTwinOptions {
    PhysTwinOptions {
        episode_frames: 10,
        stride_frames: 5,
        ..PhysTwinOptions::default()
    }
}

/// Point `i` of `make.py`'s rope at source frame `f`, in pgrd's frame (z up).
fn truth(i: usize, f: usize) -> Vec3 {
    let t = f as f64 / 30.0;
    let lift = 0.1 * (t / 2.0).clamp(0.0, 1.0);
    let swing = 0.05 * (2.0 * std::f64::consts::PI * t / 4.0).sin();
    let share = 1.0 - i as f64 / 15.0;
    Vec3::new(
        (0.02 * i as f64) as f32,
        -(0.1 + swing * share) as f32,
        (0.01 + lift * share) as f32,
    )
}

fn close(a: Vec3, b: Vec3) -> bool {
    a.distance(b) < 1e-6
}

#[test]
fn a_case_becomes_overlapping_episodes_in_a_z_up_frame() {
    let out = common::tmpdir("phystwin", "case");
    let report = phystwin::import(&case(), &out.join("data"), &small()).unwrap();
    assert_eq!(
        (report.frames, report.points, report.never_seen),
        (120, 15, 1)
    );
    assert_eq!(report.controllers, 2);
    assert!(report.split.contains("split.json"), "{}", report.split);
    let data = Dataset::open(out.join("data")).unwrap();
    assert_eq!(data.meta.object, "rope_lift");
    assert_eq!(data.meta.fps, 10.0);
    assert_eq!(data.meta.ground_z, Some(0.0));
    assert_eq!(data.meta.manipulation, Manipulation::Attach);
    assert_eq!(
        data.meta.controller_springs,
        Some(ControllerSprings {
            radius_m: 0.04,
            max_springs: 50
        })
    );
    let train = data.split_indices(Split::Train);
    let val = data.split_indices(Split::Val);
    assert_eq!((train.len(), val.len()), (4, 1));
    let firsts: Vec<[usize; 2]> = report.episodes.iter().map(|e| e.source_frames).collect();
    assert_eq!(firsts, [[0, 27], [15, 42], [30, 57], [45, 72], [84, 111]]);

    // Every kept point where the tracker saw it: PhysTwin's z turned up, the rope on the table.
    let ep0 = data.load_episode(train[0]).unwrap();
    assert_eq!((ep0.frames(), ep0.particles(), ep0.grippers()), (10, 15, 2));
    for i in 0..15 {
        assert!(
            close(ep0.frame(0)[i], truth(i, 0)),
            "point {i}: {}",
            ep0.frame(0)[i]
        );
        assert!(
            close(ep0.frame(9)[i], truth(i, 27)),
            "point {i} at frame 27"
        );
    }
    let end = truth(0, 0);
    assert!(close(
        ep0.gripper_frame(0)[0],
        end + Vec3::new(0.0, -0.005, 0.0)
    ));
    let colors = ep0.colors().unwrap();
    assert!((colors[3][0] - 3.0 / 15.0).abs() < 1e-6);

    // Point 5, unseen at source frames 30..44: not visible there, stored where last seen (29).
    let ep1 = data.load_episode(train[1]).unwrap();
    for (k, f) in (15..=42).step_by(3).enumerate() {
        let unseen = (30..45).contains(&f);
        assert_eq!(ep1.visible(k, 5), !unseen, "frame {f}");
        let want = if unseen { truth(5, 29) } else { truth(5, f) };
        assert!(
            close(ep1.frame(k)[5], want),
            "frame {f}: {}",
            ep1.frame(k)[5]
        );
    }
    // Point 8, seen at frame 60 but its motion into it invalid: not counted there.
    let ep3 = data.load_episode(train[3]).unwrap();
    assert!(!ep3.visible(5, 8) && ep3.visible(4, 8) && ep3.visible(6, 8));
    assert!(close(ep3.frame(5)[8], truth(8, 59)));

    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("data/import.json")).unwrap())
            .unwrap();
    assert_eq!(json["never_seen"], 1);
}

#[test]
fn controller_springs_are_written_for_attach_only() {
    let out = common::tmpdir("phystwin", "controllers");
    let own = ControllerSprings {
        radius_m: 0.025,
        max_springs: 12,
    };
    let with = |manipulation, controller_springs| PhysTwinOptions {
        manipulation,
        controller_springs,
        ..small()
    };
    let cases = [
        ("own", with(Manipulation::Attach, Some(own)), Some(own)),
        ("shared", with(Manipulation::Attach, None), None),
        ("grasp", with(Manipulation::Grasp, Some(own)), None),
    ];
    for (name, opts, expected) in cases {
        phystwin::import(&case(), &out.join(name), &opts).unwrap();
        let data = Dataset::open(out.join(name)).unwrap();
        assert_eq!(data.meta.controller_springs, expected, "{name}");
    }
}

#[test]
fn without_split_json_the_first_70_percent_train() {
    let out = common::tmpdir("phystwin", "nosplit");
    let pkl = out.join("final_data.pkl");
    std::fs::copy(case().join("final_data.pkl"), &pkl).unwrap();
    // The pickle itself may be given; its directory is the case.
    let report = phystwin::import(&pkl, &out.join("data"), &small()).unwrap();
    assert!(report.split.contains("70 %"), "{}", report.split);
    assert_eq!(report.episodes.last().unwrap().source_frames, [84, 111]);
}

#[test]
fn bad_cases_get_clear_errors() {
    let out = common::tmpdir("phystwin", "bad");
    // The default 40-frame episodes do not fit the fixture's 12 kept test frames.
    let err = phystwin::import(&case(), &out.join("a"), &PhysTwinOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("fewer than one episode") && err.contains("--episode-frames"),
        "{err}"
    );

    let dir = out.join("renamed");
    std::fs::create_dir_all(&dir).unwrap();
    let bytes = std::fs::read(case().join("final_data.pkl")).unwrap();
    // Rename a key in place (same length): the array is then missing.
    let at = bytes
        .windows(17)
        .position(|w| w == b"controller_points")
        .unwrap();
    let mut renamed = bytes.clone();
    renamed[at + 16] = b'z';
    std::fs::write(dir.join("final_data.pkl"), &renamed).unwrap();
    let err = phystwin::import(&dir, &out.join("b"), &small())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("final_data.pkl") && err.contains("no 'controller_points'"),
        "{err}"
    );

    std::fs::write(dir.join("final_data.pkl"), b"not a pickle").unwrap();
    let err = phystwin::import(&dir, &out.join("c"), &small())
        .unwrap_err()
        .to_string();
    assert!(err.contains("not a pickle"), "{err}");

    std::fs::write(dir.join("final_data.pkl"), &bytes).unwrap();
    std::fs::write(
        dir.join("split.json"),
        r#"{"train": [0, 50], "test": [60, 120]}"#,
    )
    .unwrap();
    let err = phystwin::import(&dir, &out.join("d"), &small())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("split.json") && err.contains("[0, a)"),
        "{err}"
    );

    // A non-finite position where the point is not seen is replaced; where it is seen, refused.
    let data_at = bytes
        .windows(5)
        .position(|w| w[0] == b'B' && w[1..] == 46080u32.to_le_bytes())
        .expect("object_points' 120 x 16 x 3 float64 data")
        + 5;
    let entry = |t: usize, i: usize| data_at + 8 * (t * 16 + i) * 3;
    let mut nan = bytes.clone();
    nan[entry(0, 15)..entry(0, 15) + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::remove_file(dir.join("split.json")).unwrap();
    std::fs::write(dir.join("final_data.pkl"), &nan).unwrap();
    let report = phystwin::import(&dir, &out.join("e"), &small()).unwrap();
    assert_eq!(report.points, 15);
    nan[entry(2, 0)..entry(2, 0) + 8].copy_from_slice(&f64::NAN.to_le_bytes());
    std::fs::write(dir.join("final_data.pkl"), &nan).unwrap();
    let err = phystwin::import(&dir, &out.join("f"), &small())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("frame 2, point 0 is seen but not a finite"),
        "{err}"
    );

    let err = phystwin::import(&out.join("nowhere"), &out.join("g"), &small())
        .unwrap_err()
        .to_string();
    assert!(err.contains("nowhere"), "{err}");
}

/// PhysTwin's `optimal_params.pkl` (numpy scalars and Python ints, written by numpy as
/// `make_params.py` says) gives the controller rule it fitted; other pickles are refused.
#[test]
fn the_fitted_controller_rule_is_read_from_optimal_params() {
    let rule = phystwin::read_controller_rule(&case().join("optimal_params.pkl")).unwrap();
    assert_eq!((rule.radius_m, rule.max_springs), (0.035, 24));
    // final_data.pkl is a dict too, without the rule.
    let err = phystwin::read_controller_rule(&case().join("final_data.pkl"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("controller_radius"), "{err}");
}
