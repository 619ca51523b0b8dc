//! Checkpoint/resume: a run serialised to JSON and read back continues with exactly the numbers
//! of the uninterrupted run, wherever it is interrupted.

use cmaes::{Bounds, CmaEs, CmaesConfig, Ipop};

fn rosenbrock(x: &[f64]) -> f64 {
    x.windows(2)
        .map(|w| 100.0 * (w[1] - w[0] * w[0]).powi(2) + (1.0 - w[0]).powi(2))
        .sum()
}

fn config() -> CmaesConfig {
    let mut config = CmaesConfig::new(vec![0.3; 6], 0.25);
    config.seed = 77;
    config.bounds = Some(Bounds {
        lower: vec![-2.0; 6],
        upper: vec![2.0; 6],
    });
    config.min_std = vec![0.0, 0.0, 0.01, 0.0, 0.0, 0.0];
    config.termination.max_generations = Some(120);
    config
}

fn round_trip<T: serde::Serialize + serde::de::DeserializeOwned>(value: &T) -> T {
    let json = serde_json::to_string(value).unwrap();
    serde_json::from_str(&json).unwrap()
}

/// Populations and fitness of a full run; `interrupt(g, asked)` decides whether to checkpoint
/// and resume before generation `g`'s tell (`asked = true`) or before its ask (`false`).
fn run(interrupt: impl Fn(u64, bool) -> bool) -> (Vec<Vec<Vec<f64>>>, String) {
    let mut es = CmaEs::new(config()).unwrap();
    let mut history = Vec::new();
    while es.should_stop().is_none() {
        if interrupt(es.generation(), false) {
            es = round_trip(&es);
        }
        let mut xs = es.ask();
        if interrupt(es.generation(), true) {
            es = round_trip(&es);
            // The pending population survives the checkpoint.
            let again = es.ask();
            assert_eq!(again, xs);
            xs = again;
        }
        let fit: Vec<f64> = xs.iter().map(|x| rosenbrock(x)).collect();
        es.tell(&xs, &fit).unwrap();
        history.push(xs);
    }
    (history, serde_json::to_string(&es).unwrap())
}

#[test]
fn resumed_run_is_bit_identical_to_the_uninterrupted_one() {
    let (plain, plain_state) = run(|_, _| false);
    assert_eq!(plain.len(), 120);
    let (resumed, resumed_state) = run(|g, asked| (g % 7 == 3 && !asked) || (g % 11 == 5 && asked));
    assert_eq!(plain, resumed);
    assert_eq!(plain_state, resumed_state);
    // Every generation resumed from a checkpoint also gives identical results.
    let (every, _) = run(|_, asked| !asked);
    assert_eq!(plain, every);
}

#[test]
fn ipop_checkpoints_across_restarts() {
    let mut config = config();
    config.termination.max_generations = Some(8);
    let drive = |checkpoint: bool| {
        let mut opt = Ipop::new(config.clone(), 3).unwrap();
        let mut history = Vec::new();
        while opt.should_stop().is_none() {
            if checkpoint {
                opt = round_trip(&opt);
            }
            let xs = opt.ask();
            let fit: Vec<f64> = xs.iter().map(|x| rosenbrock(x)).collect();
            opt.tell(&xs, &fit).unwrap();
            history.push(xs);
        }
        (history, opt.evaluations(), opt.runs().to_vec())
    };
    let plain = drive(false);
    let resumed = drive(true);
    assert_eq!(plain.2.len(), 4);
    assert_eq!(plain, resumed);
}

#[test]
fn corrupted_checkpoints_are_errors_not_panics() {
    let mut es = CmaEs::new(config()).unwrap();
    let xs = es.ask();
    let fit: Vec<f64> = xs.iter().map(|x| rosenbrock(x)).collect();
    es.tell(&xs, &fit).unwrap();
    let json: serde_json::Value = serde_json::to_value(&es).unwrap();

    let mut short_mean = json.clone();
    short_mean["mean"].as_array_mut().unwrap().pop();
    let err = serde_json::from_value::<CmaEs>(short_mean).unwrap_err();
    assert!(err.to_string().contains("mean has length 5"), "{err}");

    let mut bad_sigma = json.clone();
    bad_sigma["sigma"] = "-1.0".into();
    assert!(serde_json::from_value::<CmaEs>(bad_sigma).is_err());

    let mut bad_float = json.clone();
    bad_float["sigma"] = "abc".into();
    assert!(serde_json::from_value::<CmaEs>(bad_float).is_err());

    let mut bad_config = json;
    bad_config["config"]["sigma0"] = "0".into();
    let err = serde_json::from_value::<CmaEs>(bad_config).unwrap_err();
    assert!(err.to_string().contains("sigma0"), "{err}");
    assert!(err.to_string().contains("invalid checkpoint"), "{err}");
}
