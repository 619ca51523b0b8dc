//! The dataset contract: round trips, and every malformed input gives an error naming the file.

use dataset::{Dataset, DatasetMeta, DatasetWriter, Episode, Error, Manipulation, Split};
use glam::Vec3;
use proptest::prelude::*;

mod common;

fn tmpdir(name: &str) -> common::TempDir {
    common::tmpdir("dataset", name)
}

fn small_episode(t: usize, n: usize, g: usize, seed: f32) -> Episode {
    let pos = (0..t * n)
        .map(|k| Vec3::new(k as f32 * 0.01 + seed, 0.5, (k % 7) as f32 * 0.1))
        .collect();
    let grip = (0..t * g).map(|k| Vec3::splat(k as f32 * 0.02)).collect();
    Episode::new(t, n, g, pos, grip).unwrap()
}

fn message(e: Error) -> String {
    e.to_string()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    #[test]
    fn episodes_round_trip(t in 1usize..6, n in 1usize..9, g in 1usize..3, seed in -1.0f32..1.0,
                           with_optional in any::<bool>()) {
        let mut ep = small_episode(t, n, g, seed);
        if with_optional {
            ep = ep.with_held((0..n).map(|i| (i % (g + 1)) as i32 - 1).collect()).unwrap()
                .with_closed((0..t * g).map(|k| (k % 2) as u8).collect()).unwrap()
                .with_colors((0..n).map(|i| [i as f32 / n as f32, 0.5, 1.0]).collect()).unwrap()
                .with_visible((0..t * n).map(|k| (k % 3 != 0) as u8).collect()).unwrap();
        }
        let bytes = ep.to_bytes().unwrap();
        let back = Episode::from_bytes(&bytes, std::path::Path::new("x")).unwrap();
        prop_assert_eq!(back, ep);
    }
}

#[test]
fn dataset_round_trip_and_splits() {
    let dir = tmpdir("roundtrip");
    let mut w =
        DatasetWriter::create(&dir, DatasetMeta::new("rope", 10.0, Manipulation::Grasp)).unwrap();
    for (k, split) in [Split::Train, Split::Val, Split::Train]
        .into_iter()
        .enumerate()
    {
        w.add_episode(&small_episode(3, 4, 1, k as f32), split)
            .unwrap();
    }
    w.finish().unwrap();
    let d = Dataset::open(&dir).unwrap();
    assert_eq!(d.split_indices(Split::Train), vec![0, 2]);
    assert_eq!(d.split_indices(Split::Val), vec![1]);
    assert_eq!(d.load_episode(2).unwrap(), small_episode(3, 4, 1, 2.0));
    assert!(d.load_episode(3).is_err());
    // No temporary files are left behind by atomic writes.
    let leftovers: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty());
}

#[test]
fn append_keeps_the_old_episodes_and_never_reuses_a_listed_name() {
    let dir = tmpdir("append");
    let mut meta = DatasetMeta::new("rope", 10.0, Manipulation::Grasp);
    meta.gripper_radius = 0.03;
    let mut w = DatasetWriter::create(&dir, meta).unwrap();
    w.add_episode(&small_episode(3, 4, 1, 0.0), Split::Train)
        .unwrap();
    w.add_episode(&small_episode(3, 4, 1, 1.0), Split::Val)
        .unwrap();
    w.finish().unwrap();
    // An importer may have named its files otherwise: "ep_0002" already taken by episode 1.
    let index = dir.join("dataset.json");
    let text = std::fs::read_to_string(&index).unwrap();
    std::fs::rename(
        dir.join("ep_0001.safetensors"),
        dir.join("ep_0002.safetensors"),
    )
    .unwrap();
    std::fs::write(&index, text.replace("ep_0001", "ep_0002")).unwrap();

    let mut w = DatasetWriter::append(&dir).unwrap();
    assert_eq!(w.meta().gripper_radius, 0.03);
    assert_eq!(
        w.add_episode(&small_episode(5, 4, 1, 2.0), Split::Train)
            .unwrap(),
        2
    );
    // Until finish, readers see the old index.
    assert_eq!(Dataset::open(&dir).unwrap().meta.episodes.len(), 2);
    w.finish().unwrap();
    let d = Dataset::open(&dir).unwrap();
    assert_eq!(d.split_indices(Split::Train), vec![0, 2]);
    assert_eq!(d.load_episode(0).unwrap(), small_episode(3, 4, 1, 0.0));
    assert_eq!(d.load_episode(1).unwrap(), small_episode(3, 4, 1, 1.0));
    assert_eq!(d.load_episode(2).unwrap(), small_episode(5, 4, 1, 2.0));
    assert_eq!(d.meta.episodes[2].file, "ep_0003.safetensors");
    assert!(DatasetWriter::append(dir.join("missing")).is_err());
}

#[test]
fn default_held_uses_gripper_radius_at_frame_zero() {
    let pos = vec![
        Vec3::ZERO,
        Vec3::new(0.03, 0.0, 0.0),
        Vec3::new(0.5, 0.0, 0.0),
        Vec3::new(0.97, 0.0, 0.0),
    ];
    let grip = vec![Vec3::ZERO, Vec3::new(1.0, 0.0, 0.0)];
    let ep = Episode::new(1, 4, 2, pos, grip).unwrap();
    assert_eq!(
        ep.held_or_default(Manipulation::Grasp, 0.04),
        vec![0, 0, -1, 1]
    );
    assert_eq!(ep.held_or_default(Manipulation::Push, 0.04), vec![-1; 4]);
}

#[test]
fn in_memory_validation() {
    let bad_len = Episode::new(2, 3, 1, vec![Vec3::ZERO; 5], vec![Vec3::ZERO; 2]);
    assert!(message(bad_len.unwrap_err()).contains("'positions' has 5 entries, expected 6"));
    let mut pos = vec![Vec3::ZERO; 6];
    pos[4].y = f32::NAN;
    let nan = Episode::new(2, 3, 1, pos, vec![Vec3::ZERO; 2]);
    assert!(message(nan.unwrap_err()).contains("non-finite value at frame 1, index 1"));
    let ep = small_episode(2, 3, 1, 0.0);
    assert!(
        ep.clone().with_held(vec![0, 1, -1]).is_err(),
        "gripper 1 does not exist"
    );
    assert!(ep.clone().with_closed(vec![0, 2]).is_err());
    assert!(ep.clone().with_colors(vec![[0.0, 0.0, 1.5]; 3]).is_err());
    assert!(Episode::new(0, 3, 1, vec![], vec![]).is_err());
}

fn write_index(dir: &std::path::Path, json: &str) {
    std::fs::write(dir.join("dataset.json"), json).unwrap();
}

#[test]
fn malformed_index_errors_name_the_file() {
    let dir = tmpdir("badindex");
    let cases = [
        (
            r#"{"format": "pgrd-dataset/9", "object": "x", "fps": 10, "gravity": [0,0,-9.81], "ground_z": 0, "manipulation": "grasp", "gripper_radius": 0.04, "episodes": []}"#,
            "unsupported format 'pgrd-dataset/9'",
        ),
        (
            r#"{"format": "pgrd-dataset/1", "object": "x", "fps": 0, "gravity": [0,0,-9.81], "ground_z": 0, "manipulation": "grasp", "gripper_radius": 0.04, "episodes": []}"#,
            "fps must be a positive number",
        ),
        (
            r#"{"format": "pgrd-dataset/1", "object": "x", "fps": 10, "gravity": [0,0,-9.81], "ground_z": 0, "manipulation": "hold", "gripper_radius": 0.04, "episodes": []}"#,
            "unknown variant `hold`",
        ),
        (
            r#"{"format": "pgrd-dataset/1", "object": "x", "fps": 10, "gravity": [0,0,-9.81], "ground_z": null, "manipulation": "push", "gripper_radius": 0.04, "episodes": [{"file": "../secret", "split": "train"}]}"#,
            "plain file name",
        ),
        (
            r#"{"format": "pgrd-dataset/1", "object": "x", "fps": 10, "gravity": [0,0,-9.81], "ground_z": 0, "manipulation": "grasp", "gripper_radius": 0.04, "episodes": [{"file": "a.safetensors", "split": "train"}, {"file": "a.safetensors", "split": "val"}]}"#,
            "already listed as episode 0",
        ),
        (
            r#"{"format": "pgrd-dataset/1", "object": "x", "fps": 10, "gravity": [0,0,-9.81], "ground_z": 0, "manipulation": "grasp", "gripper_radius": 0.04, "controller_springs": {"radius_m": 0.04, "max_springs": 50}, "episodes": []}"#,
            "controller_springs applies to manipulation 'attach' only",
        ),
        (
            r#"{"format": "pgrd-dataset/1", "object": "x", "fps": 10, "gravity": [0,0,-9.81], "ground_z": 0, "manipulation": "attach", "gripper_radius": 0.04, "controller_springs": {"radius_m": -1, "max_springs": 50}, "episodes": []}"#,
            "controller_springs.radius_m must be a positive number",
        ),
        ("{not json", "not a valid dataset index"),
    ];
    for (json, want) in cases {
        write_index(&dir, json);
        let msg = message(Dataset::open(&dir).unwrap_err());
        assert!(msg.contains("dataset.json"), "{msg}");
        assert!(msg.contains(want), "{msg} should contain {want}");
    }
    let missing = message(Dataset::open(dir.join("nowhere")).unwrap_err());
    assert!(missing.contains("nowhere"), "{missing}");
}

#[test]
fn malformed_episode_files_error_with_their_path() {
    let dir = tmpdir("badepisode");
    let path = dir.join("ep.safetensors");
    let good = small_episode(3, 4, 2, 0.0).to_bytes().unwrap();
    // Truncated file.
    std::fs::write(&path, &good[..good.len() / 2]).unwrap();
    let msg = message(Episode::read(&path).unwrap_err());
    assert!(
        msg.contains("ep.safetensors") && msg.contains("not a safetensors file"),
        "{msg}"
    );
    // Wrong dtype and shape for positions.
    let data = vec![0u8; 3 * 4 * 3 * 8];
    let views = vec![(
        "positions",
        safetensors::tensor::TensorView::new(safetensors::Dtype::F64, vec![3, 4, 3], &data)
            .unwrap(),
    )];
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();
    let msg = message(Episode::read(&path).unwrap_err());
    assert!(msg.contains("'positions' must be F32"), "{msg}");
    // Missing grippers.
    let pos = vec![0u8; 3 * 4 * 3 * 4];
    let views = vec![(
        "positions",
        safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![3, 4, 3], &pos).unwrap(),
    )];
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();
    let msg = message(Episode::read(&path).unwrap_err());
    assert!(msg.contains("missing tensor 'grippers'"), "{msg}");
    // held pointing at a gripper that does not exist.
    let held: Vec<u8> = [0i32, 5, -1, -1]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let grip = vec![0u8; 3 * 2 * 3 * 4];
    let views = vec![
        (
            "positions",
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![3, 4, 3], &pos)
                .unwrap(),
        ),
        (
            "grippers",
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![3, 2, 3], &grip)
                .unwrap(),
        ),
        (
            "held",
            safetensors::tensor::TensorView::new(safetensors::Dtype::I32, vec![4], &held).unwrap(),
        ),
    ];
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();
    let msg = message(Episode::read(&path).unwrap_err());
    assert!(msg.contains("held[1] = 5"), "{msg}");
}
