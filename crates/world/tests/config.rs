//! Bad input gives clear errors; `truth.json` records what was generated.

use world::{
    Drag, EffectKind, Effects, Error, GenConfig, ObjectKind, Observation, Truth, default_kinds,
    generate,
};

fn message(e: Error) -> String {
    e.to_string()
}

#[test]
fn names_parse_and_unknown_names_are_errors() {
    for o in ObjectKind::ALL {
        assert_eq!(o.name().parse::<ObjectKind>().unwrap(), o);
    }
    for k in EffectKind::ALL {
        assert_eq!(k.name().parse::<EffectKind>().unwrap(), k);
    }
    assert!(message("cloth".parse::<ObjectKind>().unwrap_err()).contains("unknown object 'cloth'"));
    let e = Effects::parse("drag,wind", ObjectKind::Flag).unwrap_err();
    assert!(message(e).contains("unknown effect 'wind'"));
    assert_eq!(
        Effects::parse("none", ObjectKind::Rope).unwrap(),
        Effects::none()
    );
    assert_eq!(
        Effects::parse("default", ObjectKind::Rope)
            .unwrap()
            .enabled(),
        default_kinds(ObjectKind::Rope)
    );
    assert!(Observation::parse("perfect").is_err());
    // Every effect appears in some object's defaults, except the out-of-library ones.
    for k in EffectKind::ALL {
        let used = ObjectKind::ALL
            .iter()
            .any(|o| default_kinds(*o).contains(&k));
        assert_eq!(used, k.in_library(), "{k}");
    }
}

#[test]
fn bad_configurations_are_errors_not_panics() {
    let mut cfg = GenConfig::fixture(ObjectKind::Rope);
    cfg.tracked = 100_000;
    assert!(message(generate(&cfg).unwrap_err()).contains("surface particles"));

    let mut cfg = GenConfig::fixture(ObjectKind::Rope);
    (cfg.train_episodes, cfg.val_episodes) = (0, 0);
    assert!(generate(&cfg).is_err());

    let mut cfg = GenConfig::fixture(ObjectKind::Flag);
    cfg.effects.drag = Some(Drag {
        air_density_kg_m3: -1.0,
        normal_coefficient: 1.0,
        tangential_coefficient: 0.0,
        wind_m_s: [0.0; 3],
    });
    assert!(message(generate(&cfg).unwrap_err()).contains("drag"));

    let mut cfg = GenConfig::fixture(ObjectKind::Flag);
    cfg.observation.noise_std_m = f32::NAN;
    assert!(generate(&cfg).is_err());

    for sweeps in [0, world::MAX_LINK_SWEEPS + 1] {
        let mut cfg = GenConfig::fixture(ObjectKind::Paper);
        cfg.link_sweeps = sweeps;
        assert!(message(generate(&cfg).unwrap_err()).contains("link sweeps"));
    }
}

#[test]
fn truth_json_records_effects_parameters_and_recordings() {
    let mut cfg = GenConfig::fixture(ObjectKind::Sloth);
    (
        cfg.train_episodes,
        cfg.val_episodes,
        cfg.episodes_per_recording,
        cfg.tracked,
    ) = (3, 2, 2, 80);
    cfg.effects.enable(EffectKind::Magnet, ObjectKind::Sloth);
    let data = generate(&cfg).unwrap();
    let dir = std::env::temp_dir().join(format!("pgrd-world-truth-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    data.write(&dir).unwrap();
    let text = std::fs::read_to_string(dir.join("truth.json")).unwrap();
    let truth: Truth = serde_json::from_str(&text).unwrap();
    assert_eq!(truth, data.truth);
    assert_eq!(truth.out_of_library, vec![EffectKind::Magnet]);
    assert!(truth.effects_enabled.contains(&EffectKind::GraspSlip));
    assert!(
        text.contains("\"grasp-slip\": {"),
        "effect names are the CLI names"
    );
    assert!(text.contains("\"magnet\": {"));
    // 3 train episodes in recordings of 2 and 1, then 2 val episodes in one recording.
    let splits: Vec<(usize, usize)> = truth
        .recordings
        .iter()
        .map(|r| (r.episodes.len(), r.frames))
        .collect();
    assert_eq!(splits, vec![(2, 60), (1, 40), (2, 60)]);
    assert_eq!(truth.tracked_indices.len(), 80);
    // The default sweep count is not written, so datasets keep the truth.json they had.
    assert_eq!(truth.timing.link_sweeps, 1);
    assert!(!text.contains("link_sweeps"));
    assert!(truth.fine_particles > 3 * 80);
    // The overlapping episodes of one recording share their 20 common frames exactly.
    let (a, b) = (&data.episodes[0].0, &data.episodes[1].0);
    assert_eq!(a.frame(20), b.frame(0));
    assert_eq!(a.gripper_frame(39), b.gripper_frame(19));
    std::fs::remove_dir_all(&dir).ok();
}
