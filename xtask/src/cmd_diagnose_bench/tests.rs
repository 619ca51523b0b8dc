use super::summary::percent;
use super::*;

#[test]
fn an_empty_class_prints_a_dash_not_nan() {
    assert_eq!(percent(f64::NAN), "–");
    assert_eq!(percent(0.6875), "69%");
    assert_eq!(percent(1.0), "100%");
}

#[test]
fn every_effect_is_relevant_to_at_least_three_objects() {
    for kind in EffectKind::ALL {
        let objects: Vec<ObjectKind> = ObjectKind::ALL
            .into_iter()
            .filter(|o| relevant_cases(*o).contains(&kind.name()))
            .collect();
        assert!(objects.len() >= 3, "{kind}: {objects:?}");
    }
    // Only real effect names (a typo would silently drop a case).
    for object in ObjectKind::ALL {
        for name in relevant_cases(object) {
            assert!(name.parse::<EffectKind>().is_ok(), "{object}: {name}");
        }
    }
}

#[test]
fn a_case_runs_at_its_last_rung_or_its_most_visible_one() {
    let rung = |scale, raise_cm, displacement_cm| Rung {
        scale,
        raise_cm,
        displacement_cm,
    };
    // Reached at x16: the last rung climbed.
    let reached = [
        rung(1.0, 0.1, 0.5),
        rung(4.0, 0.3, 2.0),
        rung(16.0, 1.2, 4.0),
    ];
    assert_eq!(pick_rung(&reached, 1.0), Some((2, true)));
    // Never reached: the rung that moves the object most, not the one with the largest
    // raise (x1 here).
    let missed = [
        rung(1.0, 0.4, 0.4),
        rung(4.0, -0.2, 1.5),
        rung(16.0, 0.1, 3.0),
        rung(64.0, 0.0, 2.9),
    ];
    assert_eq!(pick_rung(&missed, 1.0), Some((2, false)));
    assert_eq!(pick_rung(&[], 1.0), None);
}

/// The bench's arguments as parsed from a command line (after the subcommand).
fn bench_args(argv: &[&str]) -> DiagnoseBenchArgs {
    #[derive(clap::Parser)]
    struct Bench {
        #[command(flatten)]
        args: DiagnoseBenchArgs,
    }
    let argv = std::iter::once("bench").chain(argv.iter().copied());
    <Bench as clap::Parser>::try_parse_from(argv).unwrap().args
}

/// A rope bench small enough for a test (4 training episodes of 12 tracked points, two
/// generations of two episodes in every refit), writing under `work`, with the test's
/// own `extra` flags.
fn tiny_rope_bench(work: &str, extra: &[&str]) -> DiagnoseBenchArgs {
    let mut argv = vec![
        "--objects",
        "rope",
        "--episodes",
        "4",
        "--tracked",
        "12",
        "--generations",
        "2",
        "--fit-generations",
        "2",
        "--samples",
        "2",
        "--work",
        work,
    ];
    argv.extend_from_slice(extra);
    bench_args(&argv)
}

#[test]
fn network_cases_outside_the_bench_are_refused_before_any_work() {
    let work = std::env::temp_dir().join(format!("pgrd-bench-nc-{}", std::process::id()));
    let parse = |cases: &str| {
        bench_args(&[
            "--cases",
            "none,drag",
            "--network-minutes",
            "1",
            "--network-cases",
            cases,
            "--work",
            work.to_str().unwrap(),
        ])
    };
    let e = run_bench(&parse("none,magnet")).unwrap_err().to_string();
    assert!(e.contains("`magnet`") && e.contains("none,drag"), "{e}");
    assert!(!work.exists(), "nothing is generated before the check");
}

#[test]
fn networks_go_by_default_to_none_and_the_out_of_library_cases_present() {
    let cases = |list: &str| -> Vec<String> { list.split(',').map(String::from).collect() };
    let args = bench_args(&["--network-minutes", "1"]);
    let picked = network_cases(&args, &cases("none,drag,magnet")).unwrap();
    assert_eq!(picked, cases("none,magnet"));
    let picked = network_cases(&args, &cases("drag,rotating-frame,none")).unwrap();
    assert_eq!(picked, cases("rotating-frame,none"));
    let args = bench_args(&["--network-minutes", "1", "--network-cases", "drag"]);
    assert_eq!(
        network_cases(&args, &cases("none,drag")).unwrap(),
        cases("drag")
    );
}

#[test]
fn held_out_episodes_come_from_their_own_recordings_by_default() {
    let parse = |extra: &[&str]| {
        let mut argv = vec!["--episodes", "2", "--val", "3", "--tracked", "12"];
        argv.extend_from_slice(extra);
        bench_args(&argv)
    };
    let dir = std::env::temp_dir().join(format!("pgrd-bench-rec-{}", std::process::id()));
    let recordings = |args: &DiagnoseBenchArgs| {
        let effects = Effects::none();
        let data = generate(ObjectKind::Rope, effects, 0, args, &dir).unwrap();
        let text = std::fs::read_to_string(data.root.join("truth.json")).unwrap();
        let truth: world::Truth = serde_json::from_str(&text).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        truth.recordings.len()
    };
    assert_eq!(recordings(&parse(&[])), 5, "one recording per episode");
    let shared = parse(&["--episodes-per-recording", "10"]);
    assert_eq!(recordings(&shared), 2, "one train and one val recording");

    let e = run_bench(&parse(&[
        "--episodes-per-recording",
        "0",
        "--work",
        "/nonexistent",
    ]))
    .unwrap_err()
    .to_string();
    assert!(e.contains("--episodes-per-recording"), "{e}");
}

#[test]
fn a_raced_bench_races_the_cases_not_the_base_search_and_flags_raced_out_truths() {
    // `--case-samples` too reaches the cases' diagnoses only; `--probe-factor` every
    // diagnosis.
    let dir = std::env::temp_dir().join(format!("pgrd-bench-race-{}", std::process::id()));
    let work = dir.display().to_string();
    let args = tiny_rope_bench(
        &work,
        &[
            "--cases",
            "drag,bending",
            "--val",
            "2",
            "--scales",
            "1",
            "--race",
            "1",
            "--case-samples",
            "1",
            "--probe-factor",
            "3",
            "--case-seed",
            "7",
            "--json",
            &format!("{work}/bench.json"),
        ],
    );
    let summary = run_bench(&args).unwrap();
    // The stored bench says how it was made.
    let text = std::fs::read_to_string(dir.join("bench.json")).unwrap();
    let stored: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(stored["settings"]["case_seed"], 7);
    assert_eq!(stored["settings"]["race"], 1);
    assert_eq!(stored["settings"], summary.settings);
    let read = |report: &str| -> Diagnosis {
        let text = std::fs::read_to_string(dir.join(report).join("report.json")).unwrap();
        serde_json::from_str(&text).unwrap()
    };
    let base = read("rope-none/report-base0");
    assert_eq!(base.config.race, 0, "the base search is not raced");
    assert_eq!(base.config.samples, 2, "the base search keeps --samples");
    assert_eq!(base.config.probe_factor, 3, "and the probe's length");
    assert_eq!(base.config.seed, 0, "and the bench's seed");
    assert_eq!(summary.cases.len(), 2);
    for case in &summary.cases {
        let d = read(&format!("rope-{}-x1/report", case.truth));
        assert_eq!(d.config.race, 1);
        assert_eq!(d.config.samples, 1);
        assert_eq!(d.config.seed, 7, "the cases' own seed");
        assert_eq!(d.config.probe_generations(), 6);
        let raced = d.ranking.iter().filter(|r| r.raced_out).count();
        assert_eq!(raced, d.ranking.len() - 1, "all but one raced out");
        let truth = d.ranking.iter().find(|r| r.effect == case.truth).unwrap();
        assert_eq!(
            case.true_effect_raced_out, truth.raced_out,
            "{}",
            case.truth
        );
        // And whether its report carries the caution.
        assert_eq!(case.caution, d.carry_over_caution().is_some());
        // Each case records its estimate, made with the case's own (raced) settings.
        assert!(
            case.diagnose_estimated_s > 0.0,
            "{}",
            case.diagnose_estimated_s
        );
    }
    // The object's base model is kept as a run directory, and `diagnose` run from it on a
    // case's data with the case's settings gives the case's report again.
    let run = crate::common::read_backbone(&dir.join("rope-base")).unwrap();
    assert_eq!(run.params, summary.objects[0].model);
    #[derive(clap::Parser)]
    struct Diag {
        #[command(flatten)]
        args: crate::cmd_diagnose::DiagnoseArgs,
    }
    let path = |p: &str| dir.join(p).display().to_string();
    let (data, base_run, out) = (path("rope-drag-x1"), path("rope-base"), path("replay"));
    let argv = [
        "diagnose",
        "--data",
        &data,
        "--run",
        &base_run,
        "--out",
        &out,
        "--race",
        "1",
        "--samples",
        "1",
        "--seed",
        "7",
        "--generations",
        "2",
        "--probe-factor",
        "3",
        "--budget-min",
        "0",
        "--no-network",
        "--quiet",
    ];
    let replay_args = <Diag as clap::Parser>::try_parse_from(argv).unwrap().args;
    let replay = crate::cmd_diagnose::run(&replay_args).unwrap();
    let stored = read("rope-drag-x1/report");
    assert_eq!(replay.control.heldout_mde_cm, stored.control.heldout_mde_cm);
    assert_eq!(replay.verdict, stored.verdict);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_second_round_adds_the_first_rounds_effect_and_answers_by_the_rule() {
    let dir = std::env::temp_dir().join(format!("pgrd-bench-round2-{}", std::process::id()));
    let work = dir.display().to_string();
    let args = tiny_rope_bench(
        &work,
        &[
            "--cases",
            "actuation-delay,grasp-slip",
            "--val",
            "3",
            "--scales",
            "4",
            "--probe-factor",
            "1",
            "--max-base",
            "0",
            "--second-round",
        ],
    );
    let summary = run_bench(&args).unwrap();
    let read = |report: &Path| -> Diagnosis {
        let text = std::fs::read_to_string(report.join("report.json")).unwrap();
        serde_json::from_str(&text).unwrap()
    };
    let mut second_rounds = 0;
    for case in &summary.cases {
        let case_dir = dir.join(format!("rope-{}-x4", case.truth));
        let first = read(&case_dir.join("report"));
        match &case.rounds {
            Some([named, second]) => {
                second_rounds += 1;
                assert_eq!(named, &first.verdict);
                let d2 = read(&case_dir.join("report-round2"));
                assert_eq!(second, &d2.verdict);
                // The second round's model: the first round's effect, at its refitted
                // values, added to the (here empty) base.
                let entry = first.ranking.iter().find(|r| &r.effect == named).unwrap();
                let added = d2.config.base.last().unwrap();
                assert_eq!(added.effect.name(), named);
                let n = added.values.len();
                let refitted: Vec<f64> = entry.fitted[entry.fitted.len() - n..]
                    .iter()
                    .map(|(_, v)| *v)
                    .collect();
                assert_eq!(added.values, refitted);
                let answer = if second == "unknown" { second } else { named };
                assert_eq!(&case.verdict, answer);
                // The shrinkage shown is the answer's: none once it is `unknown`.
                assert_eq!(case.verdict_shrinkage.is_some(), answer == named);
            }
            None => {
                assert!(
                    Candidate::parse(&first.verdict).is_err(),
                    "{}",
                    first.verdict
                );
                assert_eq!(case.verdict, first.verdict);
                assert!(!case_dir.join("report-round2").exists());
            }
        }
    }
    assert!(
        second_rounds > 0,
        "no case named an effect: the test saw no second round"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn scale_one_is_the_world_default_and_scales_stay_valid() {
    // The default ladder's rungs above 1, and a finer ladder's.
    let ladder: Vec<f32> = bench_args(&[])
        .scales
        .split(',')
        .map(|s| s.parse().unwrap())
        .collect();
    assert_eq!(ladder.first(), Some(&1.0));
    let stronger: Vec<f32> = ladder.into_iter().skip(1).chain([2.0, 8.0]).collect();
    for object in ObjectKind::ALL {
        for kind in EffectKind::ALL {
            assert_eq!(
                Effects::only_scaled(object, kind, 1.0),
                Effects::only(object, kind),
                "{object} {kind}"
            );
            for &s in &stronger {
                let e = Effects::only_scaled(object, kind, s);
                assert!(e.validate().is_ok(), "{object} {kind} x{s}");
                assert_eq!(e.enabled(), vec![kind]);
                assert_ne!(e, Effects::only(object, kind), "{object} {kind} x{s}");
            }
        }
    }
    // Stronger means stronger: twice the drag coefficient, half the grasp's slip force.
    let d = Effects::only_scaled(ObjectKind::Paper, EffectKind::Drag, 2.0);
    assert_eq!(d.drag.unwrap().normal_coefficient, 2.4);
    let g = Effects::only_scaled(ObjectKind::Rope, EffectKind::GraspSlip, 2.0);
    assert_eq!(g.grasp_slip.unwrap().slip_force_n, 1.5);
}

#[test]
fn the_nonlinear_candidate_reaches_every_rungs_compression_ratio() {
    // Until session 22 the candidate's compression term stopped at 0.1 of the tension
    // stiffness, while the world's ratio at ×4 is 0.3⁴ ≈ 0.008 on the sloth: the refit
    // could not express the effect it was asked to find.
    let params = Candidate::NonlinearElasticity.parameters();
    let ratio = params
        .iter()
        .find(|p| p.name == "compression_ratio")
        .expect("the candidate has a compression ratio");
    for object in ObjectKind::ALL {
        for s in [1.0, 4.0, 16.0, 64.0] {
            let e = Effects::only_scaled(object, EffectKind::NonlinearElasticity, s);
            let rho = f64::from(e.nonlinear_elasticity.unwrap().compression_ratio);
            assert!(
                (ratio.lower..=ratio.upper).contains(&rho),
                "{object} x{s}: world ratio {rho} outside [{}, {}]",
                ratio.lower,
                ratio.upper
            );
        }
    }
}

#[test]
fn a_bench_records_its_settings() {
    let args = bench_args(&[
        "--seed",
        "5",
        "--link-sweeps",
        "16",
        "--plan",
        "visible",
        "--bounds",
        "paper",
        "--second-round",
    ]);
    let s = records::settings(&args).unwrap();
    assert_eq!(s["seed"], 5);
    assert_eq!(s["case_seed"], serde_json::Value::Null, "not given");
    assert_eq!(s["link_sweeps"], 16);
    assert_eq!(s["plan"], "visible");
    assert_eq!(s["bounds"], "paper");
    assert_eq!(s["second_round"], true);
    assert_eq!(s["scales"], "1,4,16,64", "defaults are recorded too");
    assert_eq!(s["pgrd_version"], env!("CARGO_PKG_VERSION"));
}

/// The bench's page shades a matrix cell green only where its verdicts are right (an in-base
/// effect's `none` included) and lists every case.
#[test]
fn the_page_marks_right_and_wrong_verdicts() {
    let summary = serde_json::json!({
        "in_library_accuracy": 0.5, "in_library_cases": [2, 3], "wall_s": 12.0,
        "confusion": [
            ["drag", [["none", 1], ["drag", 1], ["unknown", 0]]],
            ["bending", [["none", 1], ["drag", 0], ["unknown", 0]]],
        ],
        "cases": [
            {"object": "rope", "truth": "drag", "class": "in-library", "expected": "drag",
             "verdict": "drag", "scale": 4.0, "target_reached": true},
            {"object": "paper", "truth": "drag", "class": "in-library", "expected": "drag",
             "verdict": "none", "scale": 16.0, "target_reached": true},
            {"object": "flag", "truth": "bending", "class": "in-base", "expected": "none",
             "verdict": "none", "scale": 1.0, "target_reached": false},
        ],
    });
    let dir = std::env::temp_dir().join(format!("pgrd-bench-page-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("bench.html");
    page::write(&path, &summary).unwrap();
    let html = std::fs::read_to_string(&path).unwrap();
    let row = |truth: &str| {
        let start = html
            .find(&format!("<tr><td>{truth}</td><td style"))
            .unwrap();
        html[start..start + html[start..].find("</tr>").unwrap()].to_string()
    };
    // drag: its `none` is wrong (red), its `drag` right (green); bending's `none` is right.
    let drag = row("drag");
    let cells: Vec<&str> = drag.split("<td").skip(2).collect();
    assert!(cells[0].contains("rgba(214,39,40"), "{drag}");
    assert!(cells[1].contains("rgba(44,160,44"), "{drag}");
    assert!(
        row("bending")
            .split("<td")
            .nth(2)
            .unwrap()
            .contains("rgba(44,160,44")
    );
    assert_eq!(html.matches("<tr><td>rope</td>").count(), 1);
    assert!(html.contains("50 % of 2 cases"));
    std::fs::remove_dir_all(&dir).ok();
}
