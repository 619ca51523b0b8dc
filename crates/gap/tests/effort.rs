//! The work estimate of a diagnosis (`gap::effort`): what it counts, and that it moves the
//! way the options it is used to choose between move the real cost.

use gap::{BaseEffect, Candidate, DiagnoseConfig};

mod common;
use common::{backbone, scenes};

fn small() -> DiagnoseConfig {
    DiagnoseConfig {
        population: 3,
        generations: 3,
        samples: 1,
        rescore: 1,
        probe_factor: 1,
        candidates: vec![
            Candidate::Drag,
            Candidate::ActuationDelay,
            Candidate::Bending,
        ],
        // The rule before session 95; the start's extra contender is counted on its own below.
        keep_start: false,
        ..DiagnoseConfig::default()
    }
}

#[test]
fn rollouts_are_counted_as_the_diagnosis_runs_them() {
    let train = scenes(dataset::Split::Train);
    let val = scenes(dataset::Split::Val);
    let (n, v) = (train.len(), val.len());
    let auto = springs::Substep::AUTO;
    let whole_cfg = small();
    let whole = gap::effort(&train, &val, &backbone(), &whole_cfg, auto).unwrap();
    // One refit: 3 generations of 3 candidates on 1 scene, then the optimiser's mean and the
    // best generation's best (rescore 1) on every training scene. The control, the probe
    // twice (from the residuals' focus and from its broad start) and three candidates refit
    // whole.
    let refit = 3 * 3 + 2 * n;
    assert_eq!(whole.refit_rollouts, 6 * refit);
    // Held out: the model as given and the control once each, each candidate and the probe,
    // and at most as many effect-off twins ("how far" scores rollouts already made).
    // Signatures: the backbone once and two rollouts per candidate and probe on each of up to
    // `signature_scenes` training scenes, and the backbone on up to FOCUS_SCENES for the
    // probe's start.
    assert_eq!(whole.heldout_rollouts, (2 + 2 * 4) * v);
    assert_eq!(
        whole.signature_rollouts,
        (1 + 2 * 4) * 4.min(n) + gap::FOCUS_SCENES.min(n)
    );
    // A race keeping one of three: the control whole; every candidate's and each of the
    // probe's two starts' first two generations and their looks (two contenders on up to
    // RACE_SCENES scenes); then the kept candidate's and the kept start's last generation and
    // rescoring.
    // Keeping each refit's start scores it among the rescoring's contenders and the race's
    // looks: one more on every training scene per refit, on RACE_SCENES per look.
    let kept = |race| DiagnoseConfig {
        keep_start: true,
        race,
        ..small()
    };
    let kept_refit = 3 * 3 + 3 * n;
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &kept(0), auto)
            .unwrap()
            .refit_rollouts,
        6 * kept_refit
    );
    let (kept_first, kept_second) = (2 * 3 + 3 * gap::RACE_SCENES.min(n), 3 + 3 * n);
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &kept(1), auto)
            .unwrap()
            .refit_rollouts,
        kept_refit + 2 * kept_first + kept_second + 3 * kept_first + kept_second
    );
    let raced_cfg = DiagnoseConfig { race: 1, ..small() };
    let raced = gap::effort(&train, &val, &backbone(), &raced_cfg, auto).unwrap();
    let look = 2 * gap::RACE_SCENES.min(n);
    let (first_half, second_half) = (2 * 3 + look, 3 + 2 * n);
    assert_eq!(
        raced.refit_rollouts,
        refit + 2 * first_half + second_half + 3 * first_half + second_half
    );
    assert_eq!(raced.work_per_rollout, whole.work_per_rollout);
    // Keeping every candidate is no race for the library (as in the diagnosis); the probe's
    // starts are still raced.
    let all = DiagnoseConfig { race: 3, ..small() };
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &all, auto)
            .unwrap()
            .refit_rollouts,
        refit + 2 * first_half + second_half + 3 * refit
    );
    // A longer probe: its two refits (or, raced, its kept start's second half) run to twice
    // the generations; nothing else changes.
    let long = DiagnoseConfig {
        probe_factor: 2,
        ..small()
    };
    let probe_refit = 6 * 3 + 2 * n;
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &long, auto)
            .unwrap()
            .refit_rollouts,
        4 * refit + 2 * probe_refit
    );
    let long_raced = DiagnoseConfig {
        race: 1,
        ..long.clone()
    };
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &long_raced, auto)
            .unwrap()
            .refit_rollouts,
        refit + 2 * first_half + (4 * 3 + 2 * n) + 3 * first_half + second_half
    );
    assert_eq!(long.probe_generations(), 6);
    // 0 (reports written before the factor existed) means "as every refit".
    let old = DiagnoseConfig {
        probe_factor: 0,
        ..small()
    };
    assert_eq!(old.probe_generations(), 3);
    // A larger population for the probe alone: its generations score 5 candidates instead
    // of 3, its two starts' race halves too; the library's refits are unchanged.
    let wide = DiagnoseConfig {
        probe_population: 5,
        ..small()
    };
    assert_eq!(wide.probe_population(), 5);
    assert_eq!(
        small().probe_population(),
        3,
        "0 reads as the library's population"
    );
    let wide_refit = 3 * 5 + 2 * n;
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &wide, auto)
            .unwrap()
            .refit_rollouts,
        4 * refit + 2 * wide_refit
    );
    let wide_raced = DiagnoseConfig {
        race: 1,
        ..wide.clone()
    };
    let wide_first_half = 2 * 5 + look;
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &wide_raced, auto)
            .unwrap()
            .refit_rollouts,
        refit + 2 * wide_first_half + (5 + 2 * n) + 3 * first_half + second_half
    );
    // A base effect is part of the model, not a candidate: one refit fewer.
    let based = DiagnoseConfig {
        base: BaseEffect::parse_list("bending").unwrap(),
        ..small()
    };
    let b = gap::effort(&train, &val, &backbone(), &based, auto).unwrap();
    assert_eq!(b.refit_rollouts, 5 * refit);
    assert_eq!(b.heldout_rollouts, (2 + 2 * 3) * v);
    assert!(b.work() > 0.0 && b.estimated_s() > 0.0);
    // A generation samples at most every training scene.
    let many = DiagnoseConfig {
        samples: n + 5,
        ..small()
    };
    let all_scenes = DiagnoseConfig {
        samples: n,
        ..small()
    };
    assert_eq!(
        gap::effort(&train, &val, &backbone(), &many, auto)
            .unwrap()
            .refit_rollouts,
        gap::effort(&train, &val, &backbone(), &all_scenes, auto)
            .unwrap()
            .refit_rollouts
    );
}

#[test]
fn work_per_rollout_follows_the_substep_rule_and_the_stiffness() {
    let train = scenes(dataset::Split::Train);
    let val = scenes(dataset::Split::Val);
    // Stiff enough that neither rule sits at the 2 ms accuracy cap.
    let stiff = springs::SpringParams {
        stiffness: 2e5,
        ..backbone()
    };
    let cfg = small();
    let e = |p: &springs::SpringParams, s| gap::effort(&train, &val, p, &cfg, s).unwrap();
    let auto = e(&stiff, springs::Substep::AUTO);
    let spectral = e(&stiff, springs::Substep::SPECTRAL);
    assert!(
        spectral.substeps < auto.substeps,
        "spectral {} vs auto {} substeps",
        spectral.substeps,
        auto.substeps
    );
    assert!(spectral.work_per_rollout < auto.work_per_rollout);
    // Same springs and particles: only the substep differs.
    assert_eq!(
        (spectral.springs, spectral.particles),
        (auto.springs, auto.particles)
    );
    let soft = e(&backbone(), springs::Substep::AUTO);
    assert!(soft.substeps <= auto.substeps);
    // The definition: steps × substeps × (springs + particles), mean over the sampled
    // training episodes (all of the fixture's).
    let sampled = &train[..train.len().min(8)];
    let mean = sampled
        .iter()
        .map(|s| {
            let b = s
                .backbone(&stiff, &s.sim_config(), springs::BackboneOptions::default())
                .unwrap();
            s.window.steps as f64
                * f64::from(b.substeps())
                * (b.springs().len() + b.num_particles()) as f64
        })
        .sum::<f64>()
        / sampled.len() as f64;
    assert!((auto.work_per_rollout - mean).abs() <= 1e-9 * mean);
}

#[test]
fn empty_splits_are_errors() {
    let val = scenes(dataset::Split::Val);
    let r = gap::effort(
        &[],
        &val,
        &backbone(),
        &DiagnoseConfig::default(),
        springs::Substep::AUTO,
    );
    assert!(matches!(r, Err(gap::GapError::NoScenes(_))));
}

#[test]
fn a_refined_stiffness_field_counts_toward_the_substep() {
    let train = scenes(dataset::Split::Train);
    let val = scenes(dataset::Split::Val);
    let auto = springs::Substep::AUTO;
    // Stiff enough that the substep follows the stiffness, not the 2 ms accuracy cap.
    let base = springs::SpringParams {
        stiffness: 2e5,
        ..backbone()
    };
    let e = |p: &springs::SpringParams, field: Option<Vec<f32>>| {
        let cfg = DiagnoseConfig { field, ..small() };
        gap::effort(&train, &val, p, &cfg, auto).unwrap()
    };
    let plain = e(&base, None);
    let tracked = train[0].tracked;
    // A field of e^2 everywhere is the same model as e^2 times the stiffness.
    let field = e(&base, Some(vec![2.0; tracked]));
    let scaled = springs::SpringParams {
        stiffness: base.stiffness * 2f32.exp(),
        ..base
    };
    let stiffer = e(&scaled, None);
    assert!(
        field.substeps > plain.substeps,
        "field {} vs plain {} substeps",
        field.substeps,
        plain.substeps
    );
    assert_eq!(field.substeps, stiffer.substeps);
    assert_eq!(field.work_per_rollout, stiffer.work_per_rollout);
    // A zero field changes nothing.
    assert_eq!(e(&base, Some(vec![0.0; tracked])).substeps, plain.substeps);
}
