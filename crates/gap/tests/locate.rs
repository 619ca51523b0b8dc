//! "Where" finds an error planted in known places: one end of the rope, late in the window,
//! and in proportion to speed.

mod common;

use dataset::Split;
use gap::locate;
use glam::Vec3;
use scene::Scene;

/// Each tracked particle's coordinate along x of the first scene's start, scaled to [−1, 1].
fn material(scenes: &[Scene]) -> Vec<f32> {
    let x: Vec<f32> = scenes[0].init.x[..scenes[0].tracked]
        .iter()
        .map(|p| p.x)
        .collect();
    let (lo, hi) = x
        .iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), v| {
            (l.min(*v), h.max(*v))
        });
    x.iter().map(|v| 2.0 * (v - lo) / (hi - lo) - 1.0).collect()
}

#[test]
fn an_error_planted_at_one_end_late_in_the_window_is_found_there() {
    let scenes = common::scenes(Split::Val);
    let m = material(&scenes);
    // The fifth of the particles furthest along the axis: the last of the five equal-count
    // regions "where" bins the axis into.
    let mut sorted = m.clone();
    sorted.sort_by(f32::total_cmp);
    let cut = sorted[sorted.len() - sorted.len() / 5];
    let planted = |i: usize| m[i] >= cut;
    let late = |s: usize, scene: &Scene| s >= scene.truth.len() / 2;
    let predictions: Vec<Vec<Vec<Vec3>>> = scenes
        .iter()
        .map(|scene| {
            (0..scene.truth.len())
                .map(|s| {
                    let mut frame = scene.truth[s].clone();
                    for (i, p) in frame.iter_mut().enumerate().take(scene.tracked) {
                        if planted(i) && late(s, scene) {
                            *p += Vec3::new(0.0, 0.0, 0.03);
                        }
                    }
                    frame
                })
                .collect()
        })
        .collect();
    let w = locate(&scenes, &predictions, &m);
    // Per particle: the planted end only.
    for (i, e) in w.per_particle_cm.iter().enumerate() {
        if e.is_nan() {
            continue;
        }
        if planted(i) {
            assert!(*e > 0.5, "particle {i}: {e} cm");
        } else {
            assert!(*e < 1e-6, "particle {i}: {e} cm");
        }
    }
    // Per region: the last fifth of the axis holds the error, the others none.
    let worst = w
        .regions
        .iter()
        .max_by(|a, b| a.mean_error_cm.total_cmp(&b.mean_error_cm))
        .unwrap();
    assert_eq!(worst.label, "axis segment 5 of 5");
    for r in &w.regions[..4] {
        assert!(
            r.mean_error_cm < 1e-6,
            "{}: {} cm",
            r.label,
            r.mean_error_cm
        );
    }
    // Per step: nothing in the first half of the window, then the error.
    let half = scenes.iter().map(|s| s.truth.len()).min().unwrap() / 2;
    assert!(w.per_step_cm[..half].iter().all(|e| *e < 1e-6));
    let longest = scenes.iter().map(|s| s.truth.len()).max().unwrap();
    let last_half = &w.per_step_cm[longest / 2..];
    assert!(last_half.iter().all(|e| *e > 0.1), "{last_half:?}");
}

#[test]
fn an_error_proportional_to_speed_shows_in_the_speed_trend() {
    let scenes = common::scenes(Split::Val);
    let m = material(&scenes);
    // The speed "where" measures: each tracked particle's recorded displacement over the step.
    let predictions: Vec<Vec<Vec<Vec3>>> = scenes
        .iter()
        .map(|scene| {
            let dt = scene.sim_config().step_dt;
            (0..scene.truth.len())
                .map(|s| {
                    let prev = if s == 0 {
                        &scene.init.x
                    } else {
                        &scene.truth[s - 1]
                    };
                    (0..scene.truth[s].len())
                        .map(|i| {
                            let g = scene.truth[s][i];
                            let speed = if i < scene.tracked {
                                g.distance(prev[i]) / dt
                            } else {
                                0.0
                            };
                            g + Vec3::new(0.05 * speed * dt, 0.0, 0.0)
                        })
                        .collect()
                })
                .collect()
        })
        .collect();
    let w = locate(&scenes, &predictions, &m);
    let speed = w
        .state
        .iter()
        .find(|t| t.quantity == "speed_m_per_s")
        .unwrap();
    assert!(speed.spearman > 0.99, "spearman {}", speed.spearman);
    let means: Vec<f64> = speed.bins.iter().map(|b| b.mean_error_cm).collect();
    assert!(means.windows(2).all(|p| p[0] <= p[1]), "{means:?}");
    // The fast phase carries more error than free motion; the other trends are weaker.
    let phase = |label: &str| {
        w.phases
            .iter()
            .find(|p| p.label.starts_with(label))
            .unwrap()
            .mean_error_cm
    };
    assert!(phase("fast motion") > phase("free motion"));
    for t in w.state.iter().filter(|t| t.quantity != "speed_m_per_s") {
        assert!(
            t.spearman < speed.spearman,
            "{}: {}",
            t.quantity,
            t.spearman
        );
    }
}

#[test]
fn an_episode_with_another_tracked_count_is_counted_as_skipped() {
    let mut scenes = common::scenes(Split::Val);
    assert!(scenes.len() >= 2);
    let m = material(&scenes);
    let exact: Vec<Vec<Vec<Vec3>>> = scenes.iter().map(|s| s.truth.clone()).collect();
    let clean = locate(&scenes, &exact, &m);
    assert_eq!(clean.skipped_episodes, 0);
    // The last episode loses its last tracked particle: "where" cannot number its particles
    // as the first episode's, so it is left out and counted, not silently dropped.
    let last = scenes.len() - 1;
    scenes[last].tracked -= 1;
    let w = locate(&scenes, &exact, &m);
    assert_eq!(w.skipped_episodes, 1);
    assert_eq!(w.per_particle_cm.len(), clean.per_particle_cm.len());
    // And a report written before the field existed still reads, as 0.
    let mut json = serde_json::to_value(&w).unwrap();
    json.as_object_mut().unwrap().remove("skipped_episodes");
    let old: gap::Where = serde_json::from_value(json).unwrap();
    assert_eq!(old.skipped_episodes, 0);
}
