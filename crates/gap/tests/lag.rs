//! The grasp lag: how far each tracked particle strays from moving rigidly with the grippers.

mod common;

use dataset::Split;
use glam::Vec3;

#[test]
fn the_grasp_lag_ranks_particles_by_how_far_they_stray_from_the_grippers_translation() {
    let mut scenes = common::scenes(Split::Train);
    let n = scenes[0].tracked;
    assert!(n > 4);
    // Every particle moves with the grippers' mean translation, offset by 1 mm per index;
    // particle 2 also strays 1 m at the frames where it is not seen, which must not count.
    for s in &mut scenes {
        let g = |f: usize| {
            let fr = s.actions.frame(f).unwrap();
            fr.positions.iter().copied().sum::<Vec3>() / fr.positions.len() as f32
        };
        let g0 = g(0);
        for t in 0..s.truth.len() {
            let shift = g(t + 1) - g0;
            for i in 0..n {
                let unseen = i == 2 && t % 2 == 0;
                let stray = if unseen { 1.0 } else { 0.001 * i as f32 };
                s.truth[t][i] = s.init.x[i] + shift + Vec3::new(0.0, 0.0, stray);
                s.visible[t][i] = !unseen;
            }
        }
    }
    let lag = gap::grasp_lag(&scenes).expect("the lags spread");
    assert_eq!(lag.len(), n);
    for (i, l) in lag.iter().enumerate() {
        let want = 2.0 * i as f32 / (n - 1) as f32 - 1.0;
        assert!((l - want).abs() < 1e-3, "particle {i}: {l} vs {want}");
    }
    // The frame of these windows carries it.
    let frame = gap::material_frame(&scenes).unwrap();
    assert_eq!(frame.lag.as_deref(), Some(&lag));
    // Particles that all move rigidly with the grippers have no lag coordinate.
    for s in &mut scenes {
        for t in 0..s.truth.len() {
            for i in 0..n {
                s.truth[t][i] = s.init.x[i] + (s.truth[t][0] - s.init.x[0]);
            }
        }
    }
    assert!(gap::grasp_lag(&scenes).is_none());
}
