//! The DEFORM importer on the real cable recordings (in ../shared, never committed) and on
//! malformed pickles.

use std::path::{Path, PathBuf};

use dataset::import::deform;
use dataset::{Dataset, Split, Structure};

mod common;

fn deform_dir(k: u32) -> Option<PathBuf> {
    let d =
        Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../../../shared/data/deform/DLO{k}"));
    d.is_dir().then_some(d)
}

fn tmpdir(name: &str) -> common::TempDir {
    common::tmpdir("deform", name)
}

#[test]
fn reads_a_real_recording() {
    let Some(dir) = deform_dir(1) else {
        eprintln!("skipped: ../shared/data/deform is not present on this machine");
        return;
    };
    let rec = deform::read_recording(&dir.join("eval/100.pkl")).unwrap();
    assert_eq!((rec.frames, rec.markers), (500, 13));
    // First marker of the first frame, as Python's pickle reads it: 0.652791, then y and z.
    assert!((rec.positions[0].x - 0.652791).abs() < 1e-6);
    let ep = rec.to_episode().unwrap();
    assert_eq!(ep.grippers(), 4);
    assert_eq!(
        ep.held().unwrap(),
        &[0, 1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 2, 3]
    );
    for t in [0, 250, 499] {
        assert_eq!(ep.gripper_frame(t)[3], ep.frame(t)[12]);
    }
    // The cable is about 1.04 m long, markers ~10 cm apart.
    let f = ep.frame(0);
    let length: f32 = f.windows(2).map(|w| w[0].distance(w[1])).sum();
    assert!((0.95..1.15).contains(&length), "cable length {length}");
}

#[test]
fn imports_a_whole_cable() {
    let Some(dir) = deform_dir(2) else {
        eprintln!("skipped: ../shared/data/deform is not present on this machine");
        return;
    };
    let out = tmpdir("dlo2");
    let report = deform::import(&dir, &out).unwrap();
    let data = Dataset::open(&out).unwrap();
    assert_eq!(data.meta.fps, 100.0);
    assert_eq!(data.meta.ground_z, None);
    assert_eq!(data.meta.structure, Structure::Chain);
    assert_eq!(data.split_indices(Split::Train).len(), 56);
    assert_eq!(data.split_indices(Split::Val).len(), 14);
    assert_eq!(report.markers, 12);
    let ep = data
        .load_episode(data.split_indices(Split::Val)[0])
        .unwrap();
    assert_eq!((ep.frames(), ep.particles()), (500, 12));
    assert!(out.join("import.json").is_file());
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn malformed_pickles_give_clear_errors() {
    let dir = tmpdir("bad");
    let py_list = |frames: usize, n: usize| -> Vec<u8> {
        // Protocol-2 pickle of [[[x]*n]*3]*frames written by hand: PROTO, lists, BINFLOATs.
        let mut b = vec![0x80, 2, b']', b'('];
        for _ in 0..frames {
            b.extend([b']', b'(']);
            for _ in 0..3 {
                b.extend([b']', b'(']);
                for _ in 0..n {
                    b.push(b'G');
                    b.extend(0.5f64.to_be_bytes());
                }
                b.push(b'e');
            }
            b.push(b'e');
        }
        b.extend([b'e', b'.']);
        b
    };
    let good = py_list(4, 6);
    std::fs::write(dir.join("good.pkl"), &good).unwrap();
    assert_eq!(
        deform::read_recording(&dir.join("good.pkl"))
            .unwrap()
            .markers,
        6
    );

    let cases: [(&str, Vec<u8>, &str); 4] = [
        (
            "truncated.pkl",
            good[..good.len() - 7].to_vec(),
            "truncated",
        ),
        ("short.pkl", py_list(2, 6), "at least 3 frames"),
        ("few_markers.pkl", py_list(4, 3), ">= 5"),
        ("not_pickle.pkl", b"hello".to_vec(), "not a pickle"),
    ];
    for (name, bytes, want) in cases {
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        let msg = deform::read_recording(&path).unwrap_err().to_string();
        assert!(
            msg.contains(name) && msg.contains(want),
            "{msg} should name {name} and say {want}"
        );
    }
    let missing = deform::import(&dir, &dir.join("out"))
        .unwrap_err()
        .to_string();
    assert!(missing.contains("train"), "{missing}");
}
