//! The development split: which episodes move where, the copy is faithful, bad requests are
//! refused before anything is written.

use dataset::{
    Dataset, DatasetMeta, DatasetWriter, Episode, EpisodeEntry, Error, Manipulation, Split,
    dev_split, dev_split_meta, select_split, select_split_meta,
};
use glam::Vec3;
use proptest::prelude::*;

mod common;

fn episode(k: usize) -> Episode {
    let x = k as f32 * 0.01;
    Episode::new(
        2,
        2,
        1,
        vec![
            Vec3::new(x, 0.0, 0.0),
            Vec3::X,
            Vec3::new(x, 0.1, 0.0),
            Vec3::X,
        ],
        vec![Vec3::ZERO, Vec3::Z],
    )
    .unwrap()
}

/// A dataset whose splits are interleaved, so "the last training episodes" is not "the last
/// episodes".
fn interleaved(dir: &std::path::Path) -> Dataset {
    use Split::*;
    let splits = [Train, Train, Val, Train, Test, Train, Val, Train, Train];
    let mut w =
        DatasetWriter::create(dir, DatasetMeta::new("rope", 10.0, Manipulation::Grasp)).unwrap();
    for (k, s) in splits.into_iter().enumerate() {
        w.add_episode(&episode(k), s).unwrap();
    }
    std::fs::write(dir.join("import.json"), b"{\"source\": \"test\"}").unwrap();
    w.finish().unwrap()
}

#[test]
fn moves_the_last_training_episodes_to_val_and_val_to_test() {
    let base = common::tmpdir("devsplit", "moves");
    let src = interleaved(&base.join("src"));
    let out = base.join("dev");
    let report = dev_split(&src, &out, 2).unwrap();
    assert_eq!(report.val_indices, vec![7, 8]);
    assert_eq!((report.train, report.val, report.test), (4, 2, 3));
    let dev = Dataset::open(&out).unwrap();
    assert_eq!(dev.split_indices(Split::Train), vec![0, 1, 3, 5]);
    assert_eq!(dev.split_indices(Split::Val), vec![7, 8]);
    assert_eq!(dev.split_indices(Split::Test), vec![2, 4, 6]);
    // What `train --holdout 2` holds out of the original: its last two training episodes.
    let train = src.split_indices(Split::Train);
    assert_eq!(report.val_indices, train[train.len() - 2..]);
    // Everything else is the source's, and every file is copied byte for byte.
    assert_eq!(dev.meta.object, src.meta.object);
    for k in 0..src.meta.episodes.len() {
        assert_eq!(dev.load_episode(k).unwrap(), src.load_episode(k).unwrap());
        assert_eq!(
            std::fs::read(dev.episode_path(k).unwrap()).unwrap(),
            std::fs::read(src.episode_path(k).unwrap()).unwrap()
        );
    }
    assert_eq!(
        std::fs::read(out.join("import.json")).unwrap(),
        std::fs::read(src.root.join("import.json")).unwrap()
    );
    // The source is untouched.
    assert_eq!(Dataset::open(&src.root).unwrap().meta, src.meta);
}

#[test]
fn refuses_bad_counts_and_occupied_outputs_before_writing() {
    let base = common::tmpdir("devsplit", "refuses");
    let src = interleaved(&base.join("src"));
    for n in [0, 6, 7] {
        let out = base.join(format!("dev{n}"));
        let err = dev_split(&src, &out, n).unwrap_err();
        assert!(matches!(err, Error::Invalid { .. }), "{err}");
        let text = err.to_string();
        assert!(text.contains("6 training episodes"), "{text}");
        assert!(text.contains("dataset.json"), "{text}");
        assert!(!out.exists(), "nothing may be written for n = {n}");
    }
    let occupied = base.join("occupied");
    std::fs::create_dir_all(&occupied).unwrap();
    std::fs::write(occupied.join("keep.txt"), b"mine").unwrap();
    let err = dev_split(&src, &occupied, 2).unwrap_err().to_string();
    assert!(err.contains("not empty"), "{err}");
    assert_eq!(std::fs::read(occupied.join("keep.txt")).unwrap(), b"mine");
    assert!(!occupied.join("dataset.json").exists());
    // An empty directory is fine.
    let empty = base.join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    assert!(dev_split(&src, &empty, 1).is_ok());
}

#[test]
fn select_split_keeps_the_last_val_episodes_and_every_training_one() {
    let base = common::tmpdir("devsplit", "select");
    let src = interleaved(&base.join("src"));
    let out = base.join("sel");
    let report = select_split(&src, &out, 1).unwrap();
    // val episodes of the source: 2 and 6; the last one is the selection set.
    assert_eq!(report.val_indices, vec![6]);
    assert_eq!((report.train, report.val, report.test), (6, 1, 2));
    let sel = Dataset::open(&out).unwrap();
    assert_eq!(
        sel.split_indices(Split::Train),
        src.split_indices(Split::Train)
    );
    assert_eq!(sel.split_indices(Split::Val), vec![6]);
    assert_eq!(sel.split_indices(Split::Test), vec![2, 4]);
    for k in 0..src.meta.episodes.len() {
        assert_eq!(sel.load_episode(k).unwrap(), src.load_episode(k).unwrap());
    }
    // Keeping every val episode (nothing left to report on) or none is refused, unwritten.
    for n in [0, 2, 3] {
        let out = base.join(format!("sel{n}"));
        let err = select_split(&src, &out, n).unwrap_err().to_string();
        assert!(err.contains("2 val episodes"), "{err}");
        assert!(err.contains("dataset.json"), "{err}");
        assert!(!out.exists(), "nothing may be written for n = {n}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn select_split_moves_only_the_earlier_val_episodes(splits in prop::collection::vec(0u8..3, 1..30), n in 0usize..12) {
        let split_of = |k: u8| match k { 0 => Split::Train, 1 => Split::Val, _ => Split::Test };
        let mut meta = DatasetMeta::new("x", 10.0, Manipulation::Grasp);
        meta.episodes = splits.iter().enumerate()
            .map(|(i, &k)| EpisodeEntry { file: format!("ep_{i:04}.safetensors"), split: split_of(k) })
            .collect();
        let val: Vec<usize> = (0..splits.len()).filter(|&i| splits[i] == 1).collect();
        match select_split_meta(&meta, n) {
            Err(_) => prop_assert!(n == 0 || n >= val.len()),
            Ok((sel, kept)) => {
                prop_assert!(n >= 1 && n < val.len());
                prop_assert_eq!(&kept, &val[val.len() - n..].to_vec());
                for (i, (a, b)) in meta.episodes.iter().zip(&sel.episodes).enumerate() {
                    prop_assert_eq!(&a.file, &b.file);
                    let want = match a.split {
                        Split::Val if kept.contains(&i) => Split::Val,
                        Split::Val => Split::Test,
                        other => other,
                    };
                    prop_assert_eq!(b.split, want);
                }
            }
        }
    }

    #[test]
    fn counts_and_order_are_kept(splits in prop::collection::vec(0u8..3, 1..30), n in 0usize..12) {
        let split_of = |k: u8| match k { 0 => Split::Train, 1 => Split::Val, _ => Split::Test };
        let mut meta = DatasetMeta::new("x", 10.0, Manipulation::Grasp);
        meta.episodes = splits.iter().enumerate()
            .map(|(i, &k)| EpisodeEntry { file: format!("ep_{i:04}.safetensors"), split: split_of(k) })
            .collect();
        let train: Vec<usize> = (0..splits.len()).filter(|&i| splits[i] == 0).collect();
        match dev_split_meta(&meta, n) {
            Err(_) => prop_assert!(n == 0 || n >= train.len()),
            Ok((dev, moved)) => {
                prop_assert!(n >= 1 && n < train.len());
                prop_assert_eq!(&moved, &train[train.len() - n..].to_vec());
                for (i, (a, b)) in meta.episodes.iter().zip(&dev.episodes).enumerate() {
                    prop_assert_eq!(&a.file, &b.file);
                    let want = match a.split {
                        Split::Train if moved.contains(&i) => Split::Val,
                        Split::Train => Split::Train,
                        _ => Split::Test,
                    };
                    prop_assert_eq!(b.split, want);
                }
            }
        }
    }
}

#[cfg(unix)]
#[test]
fn an_episode_stored_as_a_link_is_copied_as_its_file() {
    let base = common::tmpdir("devsplit", "link");
    let src = interleaved(&base.join("src"));
    // Move episode 3's file elsewhere and leave a link in its place.
    let stored = src.episode_path(3).unwrap();
    let elsewhere = base.join("elsewhere.safetensors");
    std::fs::rename(&stored, &elsewhere).unwrap();
    std::os::unix::fs::symlink(&elsewhere, &stored).unwrap();
    let out = base.join("dev");
    dev_split(&src, &out, 2).unwrap();
    let dev = Dataset::open(&out).unwrap();
    let copied = dev.episode_path(3).unwrap();
    assert!(!copied.is_symlink(), "the copy holds the file itself");
    assert_eq!(dev.load_episode(3).unwrap(), episode(3));
}

#[test]
fn a_damaged_episode_stops_the_copy_with_its_name_and_leaves_no_index() {
    let base = common::tmpdir("devsplit", "damaged");
    let src = interleaved(&base.join("src"));
    let file = src.root.join(&src.meta.episodes[3].file);
    let bytes = std::fs::read(&file).unwrap();
    std::fs::write(&file, &bytes[..bytes.len() / 2]).unwrap();
    let out = base.join("dev");
    let err = dev_split(&src, &out, 2).unwrap_err().to_string();
    assert!(err.contains(&src.meta.episodes[3].file), "{err}");
    assert!(!out.join("dataset.json").exists());
}
