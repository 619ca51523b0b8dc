//! Gradients reach every parameter; outputs are equivariant to point order; checkpoints reload
//! exactly; the rotation augmentation round-trips.

mod common;

use candle_core::{Device, Tensor};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use residual::{
    Combine, EncoderKind, INPUTS, ModelConfig, ResidualKind, ResidualNet, RolloutOptions,
    hybrid_rollout, rotate_history, rotate_scene,
};

fn grads_reach_every_parameter(cfg: &ModelConfig) {
    let (_, _, scene, history, bb) = common::scene("rope", 0);
    let net = ResidualNet::new(cfg, 1).unwrap();
    let opts = RolloutOptions {
        steps: 3,
        train: true,
        ..Default::default()
    };
    let out = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
    let loss = out.loss.unwrap();
    let grads = loss.backward().unwrap();
    let vars = net.named_vars();
    assert!(vars.len() > 10);
    for (name, var) in vars {
        let g = grads
            .get(var.as_tensor())
            .unwrap_or_else(|| panic!("{name}: no gradient"));
        let norm = g
            .sqr()
            .unwrap()
            .sum_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        assert!(
            norm.is_finite() && norm > 0.0,
            "{name}: gradient norm {norm}"
        );
    }
}

#[test]
fn every_parameter_gets_a_gradient() {
    grads_reach_every_parameter(&ModelConfig::tiny());
}

#[test]
fn every_parameter_gets_a_gradient_in_the_ablations() {
    let t = ModelConfig::tiny();
    grads_reach_every_parameter(&ModelConfig {
        encoder: EncoderKind::Pointnet,
        decoder: false,
        ..t.clone()
    });
    grads_reach_every_parameter(&ModelConfig {
        combine: Combine::Add,
        residual: ResidualKind::Position,
        ..t.clone()
    });
    grads_reach_every_parameter(&ModelConfig {
        combine: Combine::None,
        ..t.clone()
    });
    grads_reach_every_parameter(&ModelConfig {
        gripper_inputs: true,
        ground_inputs: true,
        rest_inputs: true,
        ..t
    });
}

#[test]
fn outputs_are_equivariant_to_point_order() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let n = 90;
    let pos: Vec<Vec3> = (0..n)
        .map(|_| {
            Vec3::new(
                rng.random_range(-0.2..0.2),
                rng.random_range(-0.2..0.2),
                rng.random_range(0.0..0.1),
            )
        })
        .collect();
    let feats: Vec<f32> = (0..n * INPUTS)
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    let mut perm: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        perm.swap(i, rng.random_range(0..=i));
    }
    let pos_p: Vec<Vec3> = perm.iter().map(|&i| pos[i]).collect();
    let feats_p: Vec<f32> = perm
        .iter()
        .flat_map(|&i| feats[i * INPUTS..(i + 1) * INPUTS].to_vec())
        .collect();
    // Patch 32 with 90 points: three padded patches, two pooling levels.
    for cfg in [
        ModelConfig::tiny(),
        ModelConfig {
            encoder: EncoderKind::Pointnet,
            ..ModelConfig::tiny()
        },
    ] {
        let net = ResidualNet::new(&cfg, 3).unwrap();
        let a = net
            .predict(
                &Tensor::from_vec(feats.clone(), (n, INPUTS), &Device::Cpu).unwrap(),
                &pos,
            )
            .unwrap();
        let b = net
            .predict(
                &Tensor::from_vec(feats_p.clone(), (n, INPUTS), &Device::Cpu).unwrap(),
                &pos_p,
            )
            .unwrap();
        let a = a.to_vec2::<f32>().unwrap();
        let b = b.to_vec2::<f32>().unwrap();
        let scale = a.iter().flatten().fold(0f32, |m, v| m.max(v.abs()));
        assert!(scale > 1e-6, "outputs are all zero");
        for (k, &i) in perm.iter().enumerate() {
            for c in 0..3 {
                assert!(
                    (a[i][c] - b[k][c]).abs() <= 1e-4 * scale,
                    "point {i} axis {c}: {} vs {}",
                    a[i][c],
                    b[k][c]
                );
            }
        }
    }
}

#[test]
fn checkpoint_reloads_to_identical_predictions() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let net = ResidualNet::new(&ModelConfig::tiny(), 5).unwrap();
    let dir = common::temp_dir("ckpt");
    let path = dir.join("residual.safetensors");
    net.save(&path).unwrap();
    let back = ResidualNet::load(&path).unwrap();
    assert_eq!(back.config(), net.config());
    let opts = RolloutOptions {
        steps: 4,
        ..Default::default()
    };
    let a = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
    let b = hybrid_rollout(&back, &bb, &scene, &history, opts).unwrap();
    assert_eq!(a.positions, b.positions);
    // A different seed gives a different network: the comparison above can fail.
    let other = ResidualNet::new(&ModelConfig::tiny(), 6).unwrap();
    let c = hybrid_rollout(&other, &bb, &scene, &history, opts).unwrap();
    assert_ne!(a.positions, c.positions);
    // Saving over a checkpoint replaces it whole and leaves no temporary file behind.
    other.save(&path).unwrap();
    let replaced = ResidualNet::load(&path).unwrap();
    let d = hybrid_rollout(&replaced, &bb, &scene, &history, opts).unwrap();
    assert_eq!(d.positions, c.positions);
    let mut files: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(files, ["residual.json", "residual.safetensors"]);
    // A directory that does not exist is an error, not a panic.
    assert!(
        net.save(&dir.join("missing").join("r.safetensors"))
            .is_err()
    );
    // A configuration from before the input convention was recorded (absolute positions) is
    // refused with a message naming the file, not run with the wrong inputs.
    let json = path.with_extension("json");
    let mut cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    cfg.as_object_mut().unwrap().remove("inputs");
    std::fs::write(&json, cfg.to_string()).unwrap();
    let err = ResidualNet::load(&path).unwrap_err().to_string();
    assert!(
        err.contains("residual.json") && err.contains("retrain"),
        "{err}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// A network without its residual steps exactly as the backbone alone, in every variant, and
/// keeps every other parameter of the network it came from.
#[test]
fn a_network_without_residual_is_the_backbone() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let opts = RolloutOptions {
        steps: 4,
        ..Default::default()
    };
    let sim = bb.rollout(&scene.init, &scene.actions).unwrap().positions;
    let t = ModelConfig::tiny();
    let variants = [
        t.clone(),
        ModelConfig {
            residual_scale: 1.0,
            ..t.clone()
        },
        ModelConfig {
            encoder: EncoderKind::Pointnet,
            decoder: false,
            ..t.clone()
        },
        ModelConfig {
            combine: Combine::Add,
            residual: ResidualKind::Position,
            ..t.clone()
        },
        ModelConfig {
            combine: Combine::None,
            ..t
        },
    ];
    for cfg in variants {
        let net = ResidualNet::new(&cfg, 7).unwrap();
        let before = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
        // The untrained network itself is not the backbone: the check below can fail.
        assert_ne!(before.positions[..], sim[1..5], "{cfg:?}");
        let quiet = net.without_residual().unwrap();
        let out = hybrid_rollout(&quiet, &bb, &scene, &history, opts).unwrap();
        assert_eq!(out.positions[..], sim[1..5], "{cfg:?}");
        let pred =
            residual::predict(&quiet, &bb, &scene.init, &history, &scene.actions, 4).unwrap();
        assert_eq!(pred[..], sim[1..5], "{cfg:?}");
        // Only the output layers changed.
        let own = net.named_vars();
        for ((name, a), (other, b)) in own.iter().zip(quiet.named_vars()) {
            assert_eq!(name, &other);
            let a: Vec<f32> = a.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            let b: Vec<f32> = b.as_tensor().flatten_all().unwrap().to_vec1().unwrap();
            if name.contains(".out.") {
                assert!(b.iter().all(|&x| x == 0.0), "{name}");
            } else {
                assert_eq!(a, b, "{name}");
            }
        }
        // The original network is untouched.
        let again = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
        assert_eq!(again.positions, before.positions);
    }
}

/// A residual gain scales the first step's residual and nothing else: half the gain, half
/// the first step's offset from the backbone.
#[test]
fn a_residual_gain_scales_the_residual() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let opts = RolloutOptions {
        steps: 1,
        ..Default::default()
    };
    let sim = bb.rollout(&scene.init, &scene.actions).unwrap().positions;
    let net = ResidualNet::new(&ModelConfig::tiny(), 7).unwrap();
    let offsets = |gain: f32| -> Vec<Vec3> {
        let scaled = net.with_residual_gain(gain).unwrap();
        let out = hybrid_rollout(&scaled, &bb, &scene, &history, opts).unwrap();
        out.positions[0]
            .iter()
            .zip(&sim[1])
            .map(|(a, b)| *a - *b)
            .collect()
    };
    let (full, half, none) = (offsets(1.0), offsets(0.5), offsets(0.0));
    let largest = full.iter().map(|d| d.length()).fold(0.0f32, f32::max);
    assert!(largest > 0.0);
    for (f, h) in full.iter().zip(&half) {
        assert!((*f * 0.5 - *h).length() <= 1e-2 * largest, "{f} vs {h}");
    }
    assert!(none.iter().all(|d| *d == Vec3::ZERO));
    assert!(net.with_residual_gain(f32::NAN).is_err());
}

/// An untrained network adds about the same residual whatever its bound (its output layers
/// start smaller by 0.1 / bound), so a step-0 network stays near the backbone; at the paper's
/// bound the draw is unchanged.
#[test]
fn untrained_residual_does_not_grow_with_the_bound() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let opts = RolloutOptions {
        steps: 3,
        ..Default::default()
    };
    let sim = bb.rollout(&scene.init, &scene.actions).unwrap().positions;
    // Largest distance from the backbone alone over the first steps, m.
    let offset = |scale: f32| {
        let cfg = ModelConfig {
            residual_scale: scale,
            ..ModelConfig::tiny()
        };
        let net = ResidualNet::new(&cfg, 5).unwrap();
        let out = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
        out.positions
            .iter()
            .zip(&sim[1..])
            .flat_map(|(p, s)| p.iter().zip(s).map(|(a, b)| a.distance(*b)))
            .fold(0.0f32, f32::max)
    };
    let paper = offset(0.1);
    assert!(paper > 0.0);
    for wide in [1.0, 2.0] {
        let d = offset(wide);
        assert!(
            d < 2.0 * paper && d > 0.5 * paper,
            "bound {wide}: {d} m vs {paper} m at 0.1"
        );
    }
    // A bound below the paper's is not scaled up: its residual is smaller.
    assert!(offset(0.01) < paper);
}

/// `predict` (a planner's entry point: state, history, actions, no truth) runs the same model
/// as the scene-based rollout, and a segment of a scene continues it exactly.
#[test]
fn predict_matches_the_scene_rollout_and_segments_continue_it() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let net = ResidualNet::new(&ModelConfig::tiny(), 3).unwrap();
    let opts = RolloutOptions {
        steps: 6,
        ..Default::default()
    };
    let full = hybrid_rollout(&net, &bb, &scene, &history, opts).unwrap();
    let pred = residual::predict(&net, &bb, &scene.init, &history, &scene.actions, 6).unwrap();
    assert_eq!(pred, full.positions);
    // Three steps in, from the rollout's own state and history: the same next three steps
    // (the temporal window restarts empty, so allow float-level differences only where the
    // window matters: compare with a tolerance well below the residual's 1 cm/step reach).
    let k = 3;
    let init = springs::State {
        x: full.positions[k - 1].clone(),
        v: full.velocities[k - 1].clone(),
    };
    let hist = residual::History {
        x: [full.positions[k - 2].clone(), full.positions[k - 3].clone()],
        v: [
            full.velocities[k - 2].clone(),
            full.velocities[k - 3].clone(),
        ],
    };
    let seg = scene.segment(k, 3, init).unwrap();
    assert_eq!(seg.truth[0], scene.truth[k]);
    let rest = hybrid_rollout(&net, &bb, &seg, &hist, opts).unwrap();
    assert_eq!(rest.positions.len(), 3);
    for (a, b) in rest.positions.iter().zip(&full.positions[k..]) {
        let worst = a
            .iter()
            .zip(b)
            .map(|(p, q)| (*p - *q).length())
            .fold(0.0, f32::max);
        assert!(
            worst < 5e-3,
            "segment departs from the rollout by {worst} m"
        );
    }
    // Too few action frames is an error, not a panic.
    assert!(residual::predict(&net, &bb, &scene.init, &history, &scene.actions, 10_000).is_err());
    assert!(
        scene
            .segment(scene.window.steps, 1, scene.init.clone())
            .is_err()
    );
}

#[test]
fn same_seed_same_network() {
    let a = ResidualNet::new(&ModelConfig::tiny(), 9).unwrap();
    let b = ResidualNet::new(&ModelConfig::tiny(), 9).unwrap();
    for ((na, va), (nb, vb)) in a.named_vars().iter().zip(b.named_vars().iter()) {
        assert_eq!(na, nb);
        assert_eq!(
            va.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            vb.flatten_all().unwrap().to_vec1::<f32>().unwrap()
        );
    }
}

#[test]
fn rotation_round_trips_and_moves_points() {
    let (_, _, scene, history, _) = common::scene("rope", 0);
    let r = rotate_scene(&scene, 1.1).unwrap();
    assert!(
        (r.init.x[3] - scene.init.x[3]).length() > 1e-3
            || scene.init.x[3].truncate().length() < 1e-3
    );
    // Heights and distances from the axis are preserved.
    for (a, b) in r.init.x.iter().zip(&scene.init.x) {
        assert!((a.z - b.z).abs() < 1e-6);
        assert!((a.truncate().length() - b.truncate().length()).abs() < 1e-5);
    }
    let back = rotate_scene(&r, -1.1).unwrap();
    let close = |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).all(|(p, q)| (*p - *q).length() < 1e-5);
    assert!(close(&back.init.x, &scene.init.x));
    assert!(close(&back.init.v, &scene.init.v));
    for (a, b) in back.truth.iter().zip(&scene.truth) {
        assert!(close(a, b));
    }
    for t in 0..scene.actions.num_frames() {
        let (a, b) = (
            back.actions.frame(t).unwrap(),
            scene.actions.frame(t).unwrap(),
        );
        assert!(close(a.positions, b.positions));
        assert_eq!(a.closed, b.closed);
    }
    let h = rotate_history(&rotate_history(&history, 0.4), -0.4);
    assert!(close(&h.x[1], &history.x[1]) && close(&h.v[0], &history.v[0]));
}

#[test]
fn invalid_configurations_are_refused() {
    let bad = ModelConfig {
        head_dim: 5,
        ..ModelConfig::tiny()
    };
    assert!(ResidualNet::new(&bad, 0).is_err());
    let bad = ModelConfig {
        dec_channels: vec![],
        ..ModelConfig::tiny()
    };
    assert!(ResidualNet::new(&bad, 0).is_err());
    assert_eq!(ModelConfig::default().variant(), "full");
}
