//! A trained network's held-out errors beside a diagnosis: what it adds to the report and when
//! it turns `none` into `unknown`.

use gap::{Candidate, DiagnoseConfig, Diagnosis};

mod common;
use common::{backbone, scenes};

fn tiny_diagnosis() -> Diagnosis {
    let cfg = DiagnoseConfig {
        population: 2,
        generations: 1,
        samples: 1,
        resamples: 200,
        candidates: vec![Candidate::Drag],
        signature_scenes: 1,
        probe: false,
        ..DiagnoseConfig::default()
    };
    let base = backbone();
    let train = scenes(dataset::Split::Train);
    let val = scenes(dataset::Split::Val);
    gap::diagnose(&train, &val, &base, &cfg, &mut |_| {}).unwrap()
}

#[test]
fn a_network_that_beats_the_control_makes_none_unknown_and_one_that_does_not_leaves_it() {
    let d0 = tiny_diagnosis();
    let control = d0
        .how_far
        .as_ref()
        .unwrap()
        .before
        .per_episode_mde_cm
        .clone();
    let n = control.len();
    assert_eq!(n, d0.episodes[1]);
    // Every episode's error halved: a large, consistent, learnable gap.
    let halved: Vec<f64> = control.iter().map(|e| 0.5 * e).collect();
    let backbone = d0.backbone_as_given.per_episode_mde_cm.clone();

    let mut d = d0.clone();
    d.verdict = "none".into();
    gap::add_learnable(&mut d, &halved, &backbone).unwrap();
    let l = d.learnable.as_ref().unwrap();
    assert_eq!(d.verdict, "unknown");
    assert!(l.changed_verdict);
    assert_eq!(l.model, "control");
    assert!(
        (l.vs_model.shrinkage - 0.5).abs() < 1e-9,
        "{:?}",
        l.vs_model
    );
    let json = serde_json::to_value(&d).unwrap();
    assert_eq!(json["learnable"]["model"], "control");
    assert!(gap::render_html(&d, "t").contains("How much is learnable"));

    // A network no better than the control: `none` stands.
    let mut d = d0.clone();
    d.verdict = "none".into();
    gap::add_learnable(&mut d, &control, &backbone).unwrap();
    assert_eq!(d.verdict, "none");
    assert!(!d.learnable.as_ref().unwrap().changed_verdict);

    // An effect verdict is kept; the network is compared with that effect's model.
    let mut d = d0.clone();
    d.verdict = "drag".into();
    gap::add_learnable(&mut d, &halved, &backbone).unwrap();
    assert_eq!(d.verdict, "drag");
    assert_eq!(d.learnable.as_ref().unwrap().model, "drag");
}

#[test]
fn errors_of_the_wrong_length_are_rejected() {
    let mut d = tiny_diagnosis();
    let n = d.episodes[1];
    let e = gap::add_learnable(&mut d, &vec![1.0; n + 1], &vec![1.0; n]).unwrap_err();
    assert!(e.to_string().contains("episodes"), "{e}");
    assert!(d.learnable.is_none());
}
