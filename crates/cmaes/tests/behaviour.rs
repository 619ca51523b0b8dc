//! Bounds, integer parameters, non-finite fitness, errors, determinism and restarts.

use cmaes::{Bounds, CmaEs, CmaesConfig, Error, Ipop, Parameter, Parameters, StopReason, minimize};

fn sphere_at(center: &[f64]) -> impl Fn(&[f64]) -> f64 + '_ {
    move |x| x.iter().zip(center).map(|(a, b)| (a - b).powi(2)).sum()
}

/// Runs `es` to its stop, returning every population it asked for.
fn drive(es: &mut CmaEs, f: &dyn Fn(&[f64]) -> f64) -> Vec<Vec<Vec<f64>>> {
    let mut history = Vec::new();
    while es.should_stop().is_none() {
        let xs = es.ask();
        let fit: Vec<f64> = xs.iter().map(|x| f(x)).collect();
        es.tell(&xs, &fit).unwrap();
        history.push(xs);
    }
    history
}

#[test]
fn candidates_stay_in_bounds_and_find_the_boundary_optimum() {
    // Unconstrained optimum (1.5, -0.5, 0.3, 2.0) lies outside the unit box; the constrained
    // one is its projection (1, 0, 0.3, 1).
    let center = [1.5, -0.5, 0.3, 2.0];
    let f = sphere_at(&center);
    let mut config = CmaesConfig::new(vec![0.5; 4], 0.3);
    config.bounds = Some(Bounds::unit(4));
    config.seed = 11;
    config.termination.max_generations = Some(300);
    let mut es = CmaEs::new(config).unwrap();
    let history = drive(&mut es, &f);
    for x in history.iter().flatten() {
        assert!(x.iter().all(|&v| (0.0..=1.0).contains(&v)), "{x:?}");
    }
    let (best, _) = es.best().unwrap();
    let expected = [1.0, 0.0, 0.3, 1.0];
    for (b, e) in best.iter().zip(expected) {
        assert!((b - e).abs() < 1e-6, "best {best:?}");
    }
    assert!(es.mean().iter().all(|&v| (0.0..=1.0).contains(&v)));
}

#[test]
fn integer_parameters_are_rounded_and_keep_being_explored() {
    let params = Parameters::new(vec![
        Parameter::linear("k", 4.0, 200.0).integer(),
        Parameter::log("c", 1e-3, 1e3),
    ])
    .unwrap();
    let floor = params.min_std();
    assert!(floor[0] > 0.0 && floor[1] == 0.0);
    let mut config = params.cmaes_config(&[150.0, 10.0], 0.2, 5).unwrap();
    config.termination.max_generations = Some(200);
    let mut es = CmaEs::new(config).unwrap();
    let loss = |r: &[f64]| (r[0] - 37.0).powi(2) + (r[1].ln() - 0.5).powi(2);
    while es.should_stop().is_none() {
        let xs = es.ask();
        let fit: Vec<f64> = xs
            .iter()
            .map(|u| {
                let r = params.to_real(u).unwrap();
                assert_eq!(r[0], r[0].round(), "integer parameter not rounded: {r:?}");
                loss(&r)
            })
            .collect();
        es.tell(&xs, &fit).unwrap();
        // The floor on the integer coordinate's standard deviation holds after every update.
        assert!(es.stds()[0] >= floor[0] * (1.0 - 1e-12), "{:?}", es.stds());
    }
    let best = params.to_real(es.best().unwrap().0).unwrap();
    assert_eq!(best[0], 37.0);
    assert!((best[1] - 0.5_f64.exp()).abs() < 1e-3, "{best:?}");
}

#[test]
fn non_finite_fitness_ranks_last_and_is_never_best() {
    // Half of the space "crashes the simulator": NaN or infinity for x[0] > 0.6.
    let f = |x: &[f64]| {
        if x[0] > 0.6 {
            if x[1] > 0.0 { f64::NAN } else { f64::INFINITY }
        } else {
            (x[0] - 0.6).powi(2) + x[1] * x[1]
        }
    };
    let mut config = CmaesConfig::new(vec![0.0, 0.5], 0.5);
    config.seed = 2;
    config.termination.max_generations = Some(400);
    let mut es = CmaEs::new(config).unwrap();
    drive(&mut es, &f);
    let (x, fx) = es.best().unwrap();
    assert!(fx.is_finite());
    assert!((x[0] - 0.6).abs() < 1e-4 && x[1].abs() < 1e-4, "{x:?} {fx}");
}

#[test]
fn all_non_finite_generations_widen_the_search_and_stop_cleanly() {
    let mut config = CmaesConfig::new(vec![0.0; 3], 0.1);
    config.termination.max_generations = Some(5);
    let mut es = CmaEs::new(config).unwrap();
    let sigma0 = es.sigma();
    drive(&mut es, &|_| f64::NAN);
    assert!(es.best().is_none());
    assert!(es.sigma() > sigma0, "flat fitness must increase sigma");
    assert_eq!(es.should_stop(), Some(StopReason::MaxGenerations));

    let config = CmaesConfig::new(vec![0.0; 3], 0.1);
    let err = minimize(|p| vec![f64::NAN; p.len()], config, 0).unwrap_err();
    assert_eq!(err, Error::NoFiniteFitness);
}

#[test]
fn misuse_is_an_error_and_leaves_the_state_unchanged() {
    let f = sphere_at(&[0.2, 0.4, 0.6]);
    let mut config = CmaesConfig::new(vec![0.0; 3], 0.3);
    config.termination.max_generations = Some(15);
    let mut reference = CmaEs::new(config.clone()).unwrap();
    let expected = drive(&mut reference, &f);

    let mut es = CmaEs::new(config).unwrap();
    assert_eq!(es.tell(&[], &[]), Err(Error::NoPendingPopulation));
    let mut seen = Vec::new();
    while es.should_stop().is_none() {
        let xs = es.ask();
        let fit: Vec<f64> = xs.iter().map(|x| f(x)).collect();
        assert!(matches!(
            es.tell(&xs, &fit[1..]),
            Err(Error::LengthMismatch {
                what: "fitness",
                ..
            })
        ));
        assert!(matches!(
            es.tell(&xs[1..], &fit[1..]),
            Err(Error::LengthMismatch {
                what: "candidates",
                ..
            })
        ));
        let mut swapped = xs.clone();
        swapped.swap(0, 1);
        assert_eq!(
            es.tell(&swapped, &fit),
            Err(Error::ForeignCandidate { index: 0 })
        );
        let mut modified = xs.clone();
        modified[3][1] += 1e-9;
        assert_eq!(
            es.tell(&modified, &fit),
            Err(Error::ForeignCandidate { index: 3 })
        );
        let mut short = xs.clone();
        short[2].pop();
        assert!(matches!(
            es.tell(&short, &fit),
            Err(Error::LengthMismatch {
                what: "candidate",
                ..
            })
        ));
        // Asking again hands out the same population.
        assert_eq!(es.ask(), xs);
        es.tell(&xs, &fit).unwrap();
        seen.push(xs);
    }
    assert_eq!(seen, expected);
}

#[test]
fn same_seed_same_numbers_different_seed_different_numbers() {
    let f = sphere_at(&[1.0, -2.0, 0.5, 0.0, 3.0]);
    let run = |seed| {
        let mut config = CmaesConfig::new(vec![0.0; 5], 1.0);
        config.seed = seed;
        config.termination.max_generations = Some(40);
        let mut es = CmaEs::new(config).unwrap();
        let history = drive(&mut es, &f);
        (history, es.best().unwrap().1)
    };
    let (a, fa) = run(9);
    let (b, fb) = run(9);
    let (c, _) = run(10);
    assert_eq!(a, b);
    assert_eq!(fa.to_bits(), fb.to_bits());
    assert_ne!(a[0], c[0]);
}

#[test]
fn ipop_doubles_the_population_and_honours_the_global_budget() {
    // Rastrigin has many local minima; short runs force restarts.
    let rastrigin = |x: &[f64]| {
        10.0 * x.len() as f64
            + x.iter()
                .map(|v| v * v - 10.0 * (2.0 * std::f64::consts::PI * v).cos())
                .sum::<f64>()
    };
    let mut config = CmaesConfig::new(vec![3.0; 4], 2.0);
    config.seed = 4;
    config.termination.max_generations = Some(30);
    config.termination.max_evaluations = Some(2000);
    let lambda = config.population_size();
    let min = minimize(|p| p.iter().map(|x| rastrigin(x)).collect(), config, 10).unwrap();
    let pops: Vec<usize> = min.runs.iter().map(|r| r.population).collect();
    for (k, p) in pops.iter().enumerate() {
        assert_eq!(*p, lambda << k, "{pops:?}");
    }
    let total: u64 = min.runs.iter().map(|r| r.evaluations).sum();
    assert_eq!(total, min.evaluations);
    let last_lambda = *pops.last().unwrap() as u64;
    assert!(min.evaluations >= 2000 && min.evaluations < 2000 + last_lambda);
    assert_eq!(min.stop, StopReason::MaxEvaluations);
    assert!(
        min.runs[..min.runs.len() - 1]
            .iter()
            .all(|r| r.stop == StopReason::MaxGenerations)
    );
    let best_of_runs = min
        .runs
        .iter()
        .filter_map(|r| r.best_fitness)
        .fold(f64::INFINITY, f64::min);
    assert_eq!(best_of_runs, min.fitness);
}

#[test]
fn bounded_restarts_start_inside_the_box_at_new_points() {
    let mut config = CmaesConfig::new(vec![0.5; 3], 0.2);
    config.bounds = Some(Bounds::unit(3));
    config.termination.max_generations = Some(3);
    let mut opt = Ipop::new(config, 3).unwrap();
    let mut starts = vec![opt.current().mean()];
    while opt.should_stop().is_none() {
        let xs = opt.ask();
        let fit: Vec<f64> = xs.iter().map(|x| x.iter().sum()).collect();
        let before = opt.restarts();
        opt.tell(&xs, &fit).unwrap();
        if opt.restarts() > before {
            starts.push(opt.current().mean());
        }
    }
    assert_eq!(opt.runs().len(), 4);
    assert_eq!(starts.len(), 4);
    for s in &starts[1..] {
        assert!(s.iter().all(|v| (0.0..=1.0).contains(v)));
        assert_ne!(s, &starts[0]);
    }
}

#[test]
fn a_population_beyond_any_use_is_a_config_error_not_an_allocation_failure() {
    for p in [usize::MAX, cmaes::MAX_POPULATION + 1, 1] {
        let mut config = CmaesConfig::new(vec![0.5; 3], 0.2);
        config.population = Some(p);
        match CmaEs::new(config) {
            Err(Error::InvalidConfig(m)) => assert!(m.contains("population"), "{m}"),
            other => panic!("population {p}: {:?}", other.map(|_| ())),
        }
    }
    let mut config = CmaesConfig::new(vec![0.5; 3], 0.2);
    config.population = Some(cmaes::MAX_POPULATION);
    assert!(config.validate().is_ok());
}
