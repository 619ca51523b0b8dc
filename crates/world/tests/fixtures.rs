//! `fixtures/` is reproduced byte for byte by the generator, and generation is deterministic
//! regardless of the number of threads.

use std::path::{Path, PathBuf};

use world::{GenConfig, ObjectKind, generate};

fn fixtures_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures")
}

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pgrd-world-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn files(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

fn check_fixture(object: ObjectKind) {
    let expected = fixtures_dir().join(object.name());
    let out = tmpdir(object.name());
    generate(&GenConfig::fixture(object))
        .unwrap()
        .write(&out)
        .unwrap();
    let names = files(&expected);
    assert_eq!(
        names,
        files(&out),
        "{object}: regenerated file set differs from fixtures/ (regenerate with the command in \
         docs/world.md if the generator changed on purpose)"
    );
    for name in names {
        let a = std::fs::read(expected.join(&name)).unwrap();
        let b = std::fs::read(out.join(&name)).unwrap();
        assert!(
            a == b,
            "{object}: {name} differs from fixtures/{object}/{name}"
        );
    }
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn fixture_rope() {
    check_fixture(ObjectKind::Rope);
}

#[test]
fn fixture_paper() {
    check_fixture(ObjectKind::Paper);
}

#[test]
fn fixture_flag() {
    check_fixture(ObjectKind::Flag);
}

#[test]
fn fixture_sloth() {
    check_fixture(ObjectKind::Sloth);
}

#[test]
fn fixture_duster() {
    check_fixture(ObjectKind::Duster);
}

#[test]
fn fixture_teddy() {
    check_fixture(ObjectKind::Teddy);
}

#[test]
fn fixtures_open_as_datasets_with_the_documented_shape() {
    for object in ObjectKind::ALL {
        let d = dataset::Dataset::open(fixtures_dir().join(object.name())).unwrap();
        assert_eq!(d.meta.object, object.name());
        assert_eq!(d.split_indices(dataset::Split::Train).len(), 3);
        assert_eq!(d.split_indices(dataset::Split::Val).len(), 2);
        let ep = d.load_episode(0).unwrap();
        assert_eq!((ep.frames(), ep.particles(), ep.grippers()), (40, 150, 1));
        assert!(ep.colors().is_some());
        let held = d.held(&ep);
        if object.is_push() {
            assert!(held.iter().all(|h| *h == -1));
        } else {
            assert!(held.contains(&0), "{object}: no tracked particle is held");
        }
    }
}

#[test]
fn generation_does_not_depend_on_thread_count() {
    let mut cfg = GenConfig::fixture(ObjectKind::Flag);
    (
        cfg.train_episodes,
        cfg.val_episodes,
        cfg.episodes_per_recording,
        cfg.tracked,
    ) = (2, 1, 1, 50);
    cfg.seed = 7;
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| generate(&cfg).unwrap())
    };
    let (a, b) = (run(1), run(3));
    assert_eq!(a.episodes, b.episodes);
    assert_eq!(a.truth, b.truth);
    // A different seed gives different data.
    cfg.seed = 8;
    let c = generate(&cfg).unwrap();
    assert_ne!(a.episodes[0].0.positions(), c.episodes[0].0.positions());
}
