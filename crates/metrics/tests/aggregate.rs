//! Rollout aggregation as the paper's tables: per-step mean and population std over episodes,
//! then means over steps.

use metrics::{MetricsError, RolloutAggregate};

#[test]
fn hand_computed_three_episodes() {
    // Step 0: {1, 2, 6} -> mean 3, population std sqrt(14/3).
    // Step 1: {4, 4, 4} -> mean 4, std 0.
    let curves = vec![vec![1.0, 4.0], vec![2.0, 4.0], vec![6.0, 4.0]];
    let a = RolloutAggregate::from_per_episode_curves(&curves).unwrap();
    assert_eq!(a.episodes, 3);
    assert_eq!(a.per_step_mean, vec![3.0, 4.0]);
    let s0 = (14.0f64 / 3.0).sqrt();
    assert!((a.per_step_std[0] - s0).abs() < 1e-15);
    assert_eq!(a.per_step_std[1], 0.0);
    assert_eq!(a.mean, 3.5);
    assert!((a.std - s0 / 2.0).abs() < 1e-15);
    // ddof = 0, not the sample std (which would be sqrt(7)).
    assert!((a.per_step_std[0] - 7f64.sqrt()).abs() > 0.1);
    let cm = a.scaled(100.0);
    assert_eq!(cm.mean, 350.0);
    assert!((cm.per_step_std[0] - 100.0 * s0).abs() < 1e-12);
}

#[test]
fn single_episode_has_zero_spread() {
    let a = RolloutAggregate::from_per_episode_curves(&[vec![0.5, 1.5]]).unwrap();
    assert_eq!(a.mean, 1.0);
    assert_eq!(a.std, 0.0);
}

#[test]
fn rejects_bad_curves() {
    let bad = |c: &[Vec<f64>]| {
        matches!(
            RolloutAggregate::from_per_episode_curves(c),
            Err(MetricsError::InvalidCurves(_))
        )
    };
    assert!(bad(&[]));
    assert!(bad(&[vec![]]));
    assert!(bad(&[vec![1.0, 2.0], vec![1.0]]));
    assert!(bad(&[vec![1.0, f64::NAN]]));
    assert!(bad(&[vec![1.0, f64::INFINITY]]));
}

#[test]
fn gaps_leave_their_step_to_the_episodes_that_have_it() {
    // Step 0: {1, 2, 6} as above; step 1: only {4} (two episodes saw nothing); step 2: none.
    let curves = vec![
        vec![Some(1.0), Some(4.0), None],
        vec![Some(2.0), None, None],
        vec![Some(6.0), None, None],
    ];
    let a = RolloutAggregate::from_per_episode_curves_with_gaps(&curves).unwrap();
    assert_eq!(a.per_step_mean[..2], [3.0, 4.0]);
    assert!(a.per_step_mean[2].is_nan() && a.per_step_std[2].is_nan());
    assert_eq!(a.mean, 3.5);
    let s0 = (14.0f64 / 3.0).sqrt();
    assert!((a.std - s0 / 2.0).abs() < 1e-15);
    // Without gaps, the same numbers as the plain form, bit for bit.
    let full = vec![vec![0.013, 0.029, 0.031], vec![0.017, 0.041, 0.043]];
    let wrapped: Vec<Vec<Option<f64>>> = full
        .iter()
        .map(|c| c.iter().copied().map(Some).collect())
        .collect();
    assert_eq!(
        RolloutAggregate::from_per_episode_curves_with_gaps(&wrapped).unwrap(),
        RolloutAggregate::from_per_episode_curves(&full).unwrap()
    );
    let bad = |c: &[Vec<Option<f64>>]| {
        matches!(
            RolloutAggregate::from_per_episode_curves_with_gaps(c),
            Err(MetricsError::InvalidCurves(_))
        )
    };
    assert!(bad(&[]));
    assert!(bad(&[vec![None, None]]));
    assert!(bad(&[vec![Some(1.0)], vec![]]));
    assert!(bad(&[vec![Some(f64::NAN)]]));
}
