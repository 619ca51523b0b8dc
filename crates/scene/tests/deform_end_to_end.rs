//! Import a real DEFORM cable (DLO1, from ../shared) and roll one eval episode out with
//! hand-picked parameters: the whole path from pickles to DEFORM's own score.

use std::path::Path;

use dataset::{Dataset, Split};
use scene::{Protocol, Scene, SceneConfig};
use springs::SpringParams;

#[test]
fn dlo1_eval_episode_end_to_end() {
    // `$PGRD_SHARED_DIR` or the `shared/` folder beside the workspace.
    let shared = std::env::var_os("PGRD_SHARED_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared"));
    let src = shared.join("data/deform/DLO1");
    if !src.is_dir() {
        eprintln!("skipped: ../shared/data/deform is not present on this machine");
        return;
    }
    let out = std::env::temp_dir().join(format!("pgrd-e2e-dlo1-{}", std::process::id()));
    dataset::import::deform::import(&src, &out).unwrap();
    let data = Dataset::open(&out).unwrap();
    let index = data.split_indices(Split::Val)[0];
    let episode = data.load_episode(index).unwrap();
    let window = Protocol::Deform.window(episode.frames()).unwrap();
    assert_eq!(window.steps, 498);
    let scene = Scene::new(&data.meta, &episode, window, &SceneConfig::default()).unwrap();
    // 13 markers and 4 hidden particles in each of the 12 gaps.
    assert_eq!(scene.particles(), 13 + 12 * 4);
    // Hand-picked: springs reach the neighbouring hidden particles (~2 cm apart), moderately
    // stiff and damped, as a user would try first.
    let params = SpringParams {
        stiffness: 20000.0,
        damping: 100.0,
        threshold: 0.045,
        max_springs: 6,
        ground_friction: 0.3,
    };
    let pred = scene
        .rollout(&params, &scene.sim_config(), Default::default())
        .unwrap();
    assert_eq!(pred.len(), 498);
    assert!(pred.iter().flatten().all(|p| p.is_finite()));
    // The driven end markers follow their recorded trajectories exactly.
    for (step, p) in pred.iter().enumerate() {
        for i in [0, 1, 11, 12] {
            let d = p[i].distance(scene.truth[step][i]);
            assert!(d < 1e-4, "driven marker {i} is {d} m off at step {step}");
        }
    }
    let l1 = scene::deform_l1(&scene, &pred).unwrap();
    let errors = scene::score_steps(&scene, &pred, true).unwrap();
    let mde_mean = scene::mean_over_steps(&errors, |e| e.mde).unwrap();
    eprintln!(
        "DLO1 episode {index}: deform_l1 {l1:.4} m, mean MDE {:.2} cm",
        100.0 * mde_mean
    );
    // A cable whose ends are driven cannot drift far: errors stay well below its 1 m length.
    assert!(l1 > 0.0 && l1 < 0.05, "deform_l1 {l1}");
    assert!(mde_mean < 0.1, "mean MDE {mde_mean} m");
    std::fs::remove_dir_all(&out).ok();
}
