//! Ground-truth Gaussians (`truth_ep_NNNN.safetensors`): exact file round trips, agreement with
//! the dataset's tracked positions, determinism, and clear errors on bad input.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::Vec3;
use world::{
    Effects, Error, GenConfig, ObjectKind, Observation, TRUTH_GAUSSIANS_FORMAT, TruthGaussians,
    generate,
};

/// A tensor as (name, dtype, shape, little-endian bytes).
type Tensor = (String, safetensors::Dtype, Vec<usize>, Vec<u8>);

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("pgrd-world-tg-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// A small noise-free dataset: with `Observation::none()` the tracked positions are the true
/// ones, which the ground-truth Gaussians must reproduce.
fn small(object: ObjectKind, seed: u64) -> GenConfig {
    let mut cfg = GenConfig::fixture(object);
    (
        cfg.train_episodes,
        cfg.val_episodes,
        cfg.episodes_per_recording,
        cfg.tracked,
    ) = (2, 1, 2, 60);
    cfg.observation = Observation::none();
    cfg.effects = Effects::none();
    cfg.seed = seed;
    cfg.gaussian_particles = 120;
    cfg
}

fn sample() -> (Vec<Vec3>, TruthGaussians) {
    // Three particles over four frames: a bounding box of 1.2 × 0.3 × 0 m (flat in z).
    let pos: Vec<Vec3> = (0..4)
        .flat_map(|t| {
            let t = t as f32;
            [
                Vec3::new(-0.5 + 0.1 * t, 0.0, 0.25),
                Vec3::new(0.3 * t, 0.1, 0.25),
                Vec3::new(0.2, 0.3 - 0.1 * t, 0.25),
            ]
        })
        .collect();
    let g = TruthGaussians::new(
        4,
        &pos,
        vec![[1.0, 0.5, 0.0], [0.0, 0.0, 1.0], [0.2, 0.2, 0.2]],
        vec![0.004, 0.005, 0.006],
        vec![0.95, 1.0, 0.5],
        vec![3, 10, 11],
    )
    .unwrap();
    (pos, g)
}

#[test]
fn round_trip_is_exact_and_positions_within_half_a_step() {
    let (pos, g) = sample();
    assert_eq!((g.frames(), g.particles()), (4, 3));
    // Step = extent / 65535 per axis (x: -0.5 .. 0.9, y: 0 .. 0.3).
    assert!((g.step_m().x - 1.4 / 65535.0).abs() < 1e-9);
    assert!((g.step_m().y - 0.3 / 65535.0).abs() < 1e-9);
    for t in 0..4 {
        for (a, b) in g.frame(t).iter().zip(&pos[3 * t..3 * t + 3]) {
            let err = (*a - *b).abs();
            assert!(
                err.cmple(g.step_m() * 0.5 + Vec3::splat(1e-6)).all(),
                "frame {t}: {a} vs {b}"
            );
        }
    }
    let bytes = g.to_bytes().unwrap();
    let back = TruthGaussians::from_bytes(&bytes, Path::new("mem")).unwrap();
    assert_eq!(back, g);
    assert_eq!(back.to_bytes().unwrap(), bytes);
    assert_eq!(back.colors()[0], [1.0, 0.5, 0.0]);
    assert_eq!(back.sigmas_m(), &[0.004, 0.005, 0.006]);
    assert_eq!(back.opacities(), &[0.95, 1.0, 0.5]);
    assert_eq!(back.fine_indices(), &[3, 10, 11]);

    let dir = tmpdir("roundtrip");
    std::fs::create_dir_all(&dir).unwrap();
    let path = TruthGaussians::path(&dir, 7);
    assert!(path.ends_with("truth_ep_0007.safetensors"));
    g.write(&path).unwrap();
    assert_eq!(TruthGaussians::read(&path).unwrap(), g);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn generated_truth_matches_the_tracked_positions_and_is_written_per_episode() {
    let cfg = small(ObjectKind::Flag, 3);
    let data = generate(&cfg).unwrap();
    assert_eq!(data.gaussians.len(), data.episodes.len());
    assert_eq!(data.truth.gaussian_particles, 120);
    let tracked = &data.truth.tracked_indices;
    for ((ep, _), g) in data.episodes.iter().zip(&data.gaussians) {
        assert_eq!((g.frames(), g.particles()), (ep.frames(), 120));
        assert!(g.sigmas_m().iter().all(|s| *s > 0.0 && *s < 0.1));
        // Tracked particles that also carry a Gaussian: same place at every frame, to within
        // the quantisation (noise-free observation, so the dataset holds true positions).
        let mut shared = 0;
        for (k, fine) in g.fine_indices().iter().enumerate() {
            let Some(i) = tracked.iter().position(|t| t == fine) else {
                continue;
            };
            shared += 1;
            assert_eq!(g.colors()[k], ep.colors().unwrap()[i]);
            for t in 0..ep.frames() {
                let d = (g.frame(t)[k] - ep.frame(t)[i]).abs();
                assert!(d.cmple(g.step_m() * 0.5 + Vec3::splat(1e-6)).all());
            }
        }
        assert!(shared > 0, "no tracked particle carries a Gaussian");
    }
    // Overlapping episodes of one recording share their frames: episode 1 starts 20 frames
    // after episode 0 (same recording), so their overlap holds the same true positions.
    let (g0, g1) = (&data.gaussians[0], &data.gaussians[1]);
    for t in 0..20 {
        for (a, b) in g0.frame(t + 20).iter().zip(g1.frame(t)) {
            assert!((*a - b).length() < 1e-4);
        }
    }

    let dir = tmpdir("write");
    data.write(&dir).unwrap();
    for (k, g) in data.gaussians.iter().enumerate() {
        assert_eq!(
            &TruthGaussians::read(TruthGaussians::path(&dir, k)).unwrap(),
            g
        );
    }
    assert!(!TruthGaussians::path(&dir, data.episodes.len()).exists());
    std::fs::remove_dir_all(&dir).ok();

    // Off: no Gaussians, no files, truth.json says 0.
    let mut off = cfg.clone();
    off.gaussian_particles = 0;
    let data = generate(&off).unwrap();
    assert!(data.gaussians.is_empty());
    assert_eq!(data.truth.gaussian_particles, 0);
    let dir = tmpdir("off");
    data.write(&dir).unwrap();
    assert!(!TruthGaussians::path(&dir, 0).exists());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn generation_is_deterministic_and_caps_apply() {
    let cfg = small(ObjectKind::Teddy, 5);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| generate(&cfg).unwrap())
    };
    let (a, b) = (run(1), run(3));
    let bytes = |d: &world::GeneratedDataset| -> Vec<Vec<u8>> {
        d.gaussians.iter().map(|g| g.to_bytes().unwrap()).collect()
    };
    assert_eq!(bytes(&a), bytes(&b));
    // A cap above the number of surface particles takes all of them, a smaller one a subset
    // of distinct particles.
    let mut all = cfg.clone();
    all.gaussian_particles = 1_000_000;
    let all = generate(&all).unwrap();
    let n_all = all.truth.gaussian_particles;
    assert!(n_all > 120 && n_all < all.truth.fine_particles, "{n_all}");
    let mut idx = a.gaussians[0].fine_indices().to_vec();
    idx.dedup();
    assert_eq!(idx.len(), 120);
    assert!(idx.windows(2).all(|w| w[0] < w[1]));
    assert!(
        idx.iter()
            .all(|i| all.gaussians[0].fine_indices().contains(i))
    );
}

#[test]
fn bad_input_is_an_error() {
    let (pos, g) = sample();
    let colors = g.colors().to_vec();
    let s = vec![0.005; 3];
    let o = vec![0.9; 3];
    let ids = vec![0, 1, 2];
    let cases: Vec<(&str, Result<TruthGaussians, Error>)> = vec![
        (
            "frames",
            TruthGaussians::new(0, &[], colors.clone(), s.clone(), o.clone(), ids.clone()),
        ),
        (
            "positions",
            TruthGaussians::new(3, &pos, colors.clone(), s.clone(), o.clone(), ids.clone()),
        ),
        ("non-finite", {
            let mut p = pos.clone();
            p[5].y = f32::NAN;
            TruthGaussians::new(4, &p, colors.clone(), s.clone(), o.clone(), ids.clone())
        }),
        (
            "colour",
            TruthGaussians::new(
                4,
                &pos,
                vec![[0.0, 1.5, 0.0]; 3],
                s.clone(),
                o.clone(),
                ids.clone(),
            ),
        ),
        (
            "standard deviation",
            TruthGaussians::new(
                4,
                &pos,
                colors.clone(),
                vec![0.005, 0.0, 0.005],
                o.clone(),
                ids.clone(),
            ),
        ),
        (
            "opacity",
            TruthGaussians::new(
                4,
                &pos,
                colors.clone(),
                s.clone(),
                vec![0.5, 1.1, 0.5],
                ids.clone(),
            ),
        ),
        (
            "fine indices",
            TruthGaussians::new(4, &pos, colors.clone(), s.clone(), o.clone(), vec![0]),
        ),
    ];
    for (what, r) in cases {
        match r {
            Err(Error::Config(m)) => assert!(m.contains(what), "{what}: {m}"),
            other => panic!("{what}: expected a Config error, got {other:?}"),
        }
    }

    let read_err = |bytes: &[u8]| match TruthGaussians::from_bytes(bytes, Path::new("x.st")) {
        Err(Error::Read { path, message }) => {
            assert_eq!(path, Path::new("x.st"));
            message
        }
        other => panic!("expected a Read error, got {other:?}"),
    };
    assert!(read_err(b"garbage").contains("not a safetensors file"));
    // Valid safetensors built here with tensors that break the contract one at a time.
    let good = g.to_bytes().unwrap();
    let st = safetensors::SafeTensors::deserialize(&good).unwrap();
    let rebuild = |format: &str, edit: &dyn Fn(&mut Vec<Tensor>)| {
        let mut t: Vec<_> = st
            .names()
            .into_iter()
            .map(|n| {
                let v = st.tensor(n).unwrap();
                (
                    n.to_string(),
                    v.dtype(),
                    v.shape().to_vec(),
                    v.data().to_vec(),
                )
            })
            .collect();
        edit(&mut t);
        let views: Vec<_> = t
            .iter()
            .map(|(n, d, s, b)| {
                (
                    n.clone(),
                    safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
                )
            })
            .collect();
        let info = HashMap::from([("format".to_string(), format.to_string())]);
        safetensors::serialize(views, Some(info)).unwrap()
    };
    let same = rebuild(TRUTH_GAUSSIANS_FORMAT, &|_| {});
    assert_eq!(
        TruthGaussians::from_bytes(&same, Path::new("x")).unwrap(),
        g
    );
    assert!(read_err(&rebuild("pgrd-dataset/1", &|_| {})).contains("format tag"));
    assert!(
        read_err(&rebuild(TRUTH_GAUSSIANS_FORMAT, &|t| t.retain(|x| x.0 != "sigmas")))
            .contains("missing tensor 'sigmas'")
    );
    assert!(
        read_err(&rebuild(TRUTH_GAUSSIANS_FORMAT, &|t| {
            t.push(("extra".into(), safetensors::Dtype::U8, vec![1], vec![0]))
        }))
        .contains("unknown tensor 'extra'")
    );
    assert!(
        read_err(&rebuild(TRUTH_GAUSSIANS_FORMAT, &|t| {
            let o = t.iter_mut().find(|x| x.0 == "opacities").unwrap();
            (o.2, o.3) = (vec![2], o.3[..8].to_vec());
        }))
        .contains("'opacities' has shape [2], expected [3]")
    );
    assert!(
        read_err(&rebuild(TRUTH_GAUSSIANS_FORMAT, &|t| {
            let o = t.iter_mut().find(|x| x.0 == "colors").unwrap();
            o.3[0..4].copy_from_slice(&(-0.5f32).to_le_bytes());
        }))
        .contains("colour")
    );
    assert!(
        read_err(&rebuild(TRUTH_GAUSSIANS_FORMAT, &|t| {
            let o = t.iter_mut().find(|x| x.0 == "step").unwrap();
            o.3[4..8].copy_from_slice(&0f32.to_le_bytes());
        }))
        .contains("quantisation box")
    );
    assert!(
        read_err(&rebuild(TRUTH_GAUSSIANS_FORMAT, &|t| {
            let o = t.iter_mut().find(|x| x.0 == "positions").unwrap();
            o.1 = safetensors::Dtype::I16;
        }))
        .contains("'positions' is I16")
    );
    match TruthGaussians::read("/nonexistent/truth_ep_0000.safetensors") {
        Err(Error::Read { path, .. }) => assert!(path.ends_with("truth_ep_0000.safetensors")),
        other => panic!("expected a Read error, got {other:?}"),
    }
}
