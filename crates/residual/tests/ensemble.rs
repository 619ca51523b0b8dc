//! Ensembles: the residual is the members' mean, each member keeps its own temporal window,
//! an ensemble saves and reloads exactly, and it cannot be trained as a whole.

mod common;

use glam::Vec3;
use residual::{
    EnsembleRule, ModelConfig, ResidualNet, RolloutOptions, TrainConfig, Trainer, hybrid_rollout,
};

/// An ensemble of two tiny networks of seeds 1 and 2.
fn two_tiny_networks() -> ResidualNet {
    let cfg = ModelConfig::tiny();
    ResidualNet::ensemble(vec![
        ResidualNet::new(&cfg, 1).unwrap(),
        ResidualNet::new(&cfg, 2).unwrap(),
    ])
    .unwrap()
}

/// Offsets from the backbone after one step (the same state for every member) of three tiny
/// networks of seeds `seed..seed + 3`, each alone and as an ensemble combined by `rule`, and
/// the largest member offset (checked to be above 1 µm, so comparisons with it can fail).
fn first_step_offsets(seed: u64, rule: EnsembleRule) -> (Vec<Vec<Vec3>>, Vec<Vec3>, f32) {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let sim = bb.rollout(&scene.init, &scene.actions).unwrap().positions;
    let cfg = ModelConfig::tiny();
    let nets: Vec<ResidualNet> = (0..3)
        .map(|s| ResidualNet::new(&cfg, seed + s).unwrap())
        .collect();
    let offsets = |net: &ResidualNet| -> Vec<Vec3> {
        let out = hybrid_rollout(net, &bb, &scene, &history, opts(1)).unwrap();
        out.positions[0]
            .iter()
            .zip(&sim[1])
            .map(|(a, b)| *a - *b)
            .collect()
    };
    let each: Vec<Vec<Vec3>> = nets.iter().map(offsets).collect();
    let ens = ResidualNet::ensemble(nets)
        .unwrap()
        .with_ensemble_rule(rule);
    let combined = offsets(&ens);
    let largest = each
        .iter()
        .flatten()
        .map(|d| d.length())
        .fold(0.0f32, f32::max);
    assert!(largest > 1e-6, "the members move nothing");
    (each, combined, largest)
}

fn opts(steps: usize) -> RolloutOptions {
    RolloutOptions {
        steps,
        ..Default::default()
    }
}

/// Two copies of one network are that network, bit for bit (a + a and the halving are exact),
/// over several steps: the members' windows are kept apart and both see the same inputs.
#[test]
fn an_ensemble_of_copies_is_the_network() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let net = ResidualNet::new(&ModelConfig::tiny(), 3).unwrap();
    let copy = net.with_residual_gain(1.0).unwrap();
    let single = hybrid_rollout(&net, &bb, &scene, &history, opts(5)).unwrap();
    let pair = ResidualNet::ensemble(vec![net.with_residual_gain(1.0).unwrap(), copy]).unwrap();
    assert_eq!(pair.ensemble_size(), 2);
    assert_eq!(pair.parameter_count(), 2 * net.parameter_count());
    let out = hybrid_rollout(&pair, &bb, &scene, &history, opts(5)).unwrap();
    assert_eq!(out.positions, single.positions);
    // Copies agree everywhere, so the agreement rule keeps their mean untouched.
    let agreeing = pair.with_ensemble_rule(EnsembleRule::Agreement);
    let out = hybrid_rollout(&agreeing, &bb, &scene, &history, opts(5)).unwrap();
    assert_eq!(out.positions, single.positions);
}

/// After one step, the agreement rule's offset from the backbone is the members' mean offset
/// shrunk per particle by |m|² / (|m|² + s²), s² the members' mean squared distance from m:
/// never longer than the mean, and shorter where the members disagree.
#[test]
fn agreement_shrinks_the_mean_where_members_disagree() {
    let (each, got, largest) = first_step_offsets(20, EnsembleRule::Agreement);
    let mut shrunk = 0.0f32;
    for (i, g) in got.iter().enumerate() {
        let m = (each[0][i] + each[1][i] + each[2][i]) / 3.0;
        let s2 = each
            .iter()
            .map(|e| (e[i] - m).length_squared())
            .sum::<f32>()
            / 3.0;
        let total = m.length_squared() + s2;
        // Held particles: no member moves them, nor may the rule (no 0 / 0).
        let expect = if total > 0.0 {
            m * (m.length_squared() / total)
        } else {
            Vec3::ZERO
        };
        assert!((*g - expect).length() <= 1e-3 * largest, "{g} vs {expect}");
        assert!(
            g.length() <= m.length() + 1e-3 * largest,
            "{g} longer than {m}"
        );
        shrunk = shrunk.max(m.length() - g.length());
    }
    assert!(shrunk > 1e-2 * largest, "nothing was shrunk");
}

/// After one step (same state for every member), the ensemble's offset from the backbone is
/// the mean of the members' offsets, and differs from each member's.
#[test]
fn the_first_residual_is_the_members_mean() {
    let (each, mean, largest) = first_step_offsets(10, EnsembleRule::Mean);
    let mut apart = 0.0f32;
    for (i, m) in mean.iter().enumerate() {
        let expect = (each[0][i] + each[1][i] + each[2][i]) / 3.0;
        assert!((*m - expect).length() <= 1e-3 * largest, "{m} vs {expect}");
        apart = apart.max((*m - each[0][i]).length());
    }
    assert!(apart > 1e-2 * largest, "the mean equals member 0");
}

/// An ensemble saves to one file pair and reloads to identical predictions; a single
/// network's JSON keeps its old form (no member count).
#[test]
fn an_ensemble_reloads_exactly() {
    let (_, _, scene, history, bb) = common::scene("rope", 0);
    let cfg = ModelConfig::tiny();
    let ens = two_tiny_networks();
    let dir = common::temp_dir("ensemble");
    let path = dir.join("residual.safetensors");
    ens.save(&path).unwrap();
    let json = std::fs::read_to_string(path.with_extension("json")).unwrap();
    assert!(json.contains("\"ensemble_members\": 2"), "{json}");
    let back = ResidualNet::load(&path).unwrap();
    assert_eq!(back.ensemble_size(), 2);
    assert_eq!(back.config(), ens.config());
    let a = hybrid_rollout(&ens, &bb, &scene, &history, opts(4)).unwrap();
    let b = hybrid_rollout(&back, &bb, &scene, &history, opts(4)).unwrap();
    assert_eq!(a.positions, b.positions);
    // Member 0 alone predicts otherwise: the comparison above can fail.
    let one = ResidualNet::new(&cfg, 1).unwrap();
    let c = hybrid_rollout(&one, &bb, &scene, &history, opts(4)).unwrap();
    assert_ne!(a.positions, c.positions);
    let single = dir.join("single.safetensors");
    one.save(&single).unwrap();
    let text = std::fs::read_to_string(single.with_extension("json")).unwrap();
    assert!(!text.contains("ensemble_members"), "{text}");
    // The rule travels with the file; the mean's files do not name it.
    assert!(!json.contains("ensemble_rule"), "{json}");
    let agreeing = two_tiny_networks().with_ensemble_rule(EnsembleRule::Agreement);
    let other = dir.join("agreement.safetensors");
    agreeing.save(&other).unwrap();
    let back = ResidualNet::load(&other).unwrap();
    assert_eq!(back.ensemble_rule(), EnsembleRule::Agreement);
    let a = hybrid_rollout(&agreeing, &bb, &scene, &history, opts(4)).unwrap();
    let b = hybrid_rollout(&back, &bb, &scene, &history, opts(4)).unwrap();
    assert_eq!(a.positions, b.positions);
    assert_ne!(a.positions, c.positions);
    // A file that names more members than it holds is an error, not a panic.
    let mut value: serde_json::Value = serde_json::from_str(&json).unwrap();
    value["ensemble_members"] = 3.into();
    std::fs::write(path.with_extension("json"), value.to_string()).unwrap();
    let err = ResidualNet::load(&path).unwrap_err().to_string();
    assert!(err.contains("member2"), "{err}");
    std::fs::remove_dir_all(dir).ok();
}

/// A gain scales every member; gain 0 is the backbone exactly.
#[test]
fn a_gain_applies_to_every_member() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let sim = bb.rollout(&scene.init, &scene.actions).unwrap().positions;
    let cfg = ModelConfig::tiny();
    let ens = ResidualNet::ensemble(vec![
        ResidualNet::new(&cfg, 4).unwrap(),
        ResidualNet::new(&cfg, 5).unwrap(),
    ])
    .unwrap();
    let quiet = ens.without_residual().unwrap();
    assert_eq!(quiet.ensemble_size(), 2);
    let out = hybrid_rollout(&quiet, &bb, &scene, &history, opts(3)).unwrap();
    assert_eq!(out.positions[..], sim[1..4]);
    let half = ens
        .with_ensemble_rule(EnsembleRule::Agreement)
        .with_residual_gain(0.5)
        .unwrap();
    assert_eq!(half.ensemble_size(), 2);
    assert_eq!(half.ensemble_rule(), EnsembleRule::Agreement);
    assert_eq!(half.config().residual_scale, 0.5 * cfg.residual_scale);
}

/// Training an ensemble as a whole is refused (its members are trained one by one).
#[test]
fn an_ensemble_cannot_be_trained() {
    let (_, _, scene, history, bb) = common::scene("rope", 0);
    let ens = two_tiny_networks();
    let train = RolloutOptions {
        steps: 2,
        train: true,
        ..Default::default()
    };
    let err = hybrid_rollout(&ens, &bb, &scene, &history, train).unwrap_err();
    assert!(err.to_string().contains("ensemble"), "{err}");
    let Err(err) = Trainer::new(ens, TrainConfig::default()) else {
        panic!("training an ensemble was accepted");
    };
    assert!(err.to_string().contains("ensemble"), "{err}");
}

/// Split apart, an ensemble's members predict exactly what each network predicts alone, over
/// several steps (their parameters copied, nothing of the ensemble's rule or windows kept).
#[test]
fn split_members_are_the_networks_they_were_built_from() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let cfg = ModelConfig::tiny();
    let alone: Vec<ResidualNet> = (4..7).map(|s| ResidualNet::new(&cfg, s).unwrap()).collect();
    let ens = ResidualNet::ensemble((4..7).map(|s| ResidualNet::new(&cfg, s).unwrap()).collect())
        .unwrap()
        .with_ensemble_rule(EnsembleRule::Agreement);
    let split = ens.split_ensemble().unwrap();
    assert_eq!(split.len(), 3);
    let predict = |net: &ResidualNet| {
        hybrid_rollout(net, &bb, &scene, &history, opts(4))
            .unwrap()
            .positions
    };
    let first = predict(&alone[0]);
    for (member, net) in split.iter().zip(&alone) {
        assert_eq!(member.ensemble_size(), 1);
        assert_eq!(predict(member), predict(net));
    }
    // The members differ, so the comparison above can fail.
    assert_ne!(predict(&split[1]), first);
}

/// An ensemble's rollout is the same, bit for bit, on one thread and on three, for both
/// rules (candle's kernels may use the pool's threads; the members' order is fixed).
#[test]
fn an_ensemble_rolls_out_the_same_on_any_thread_count() {
    let (_, _, scene, history, bb) = common::scene("rope", 0);
    let cfg = ModelConfig::tiny();
    for rule in [EnsembleRule::Mean, EnsembleRule::Agreement] {
        let ens = ResidualNet::ensemble(
            (0..3)
                .map(|s| ResidualNet::new(&cfg, 10 + s).unwrap())
                .collect(),
        )
        .unwrap()
        .with_ensemble_rule(rule);
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| hybrid_rollout(&ens, &bb, &scene, &history, opts(4)).unwrap())
        };
        let (one, three) = (on(1), on(3));
        assert_eq!(one.positions, three.positions, "{rule:?}");
        assert_eq!(one.velocities, three.velocities, "{rule:?}");
    }
}

/// Weight averaging: two copies of one network average to that network bit for bit (a + a and
/// the halving are exact); two different networks average to the midpoint of every parameter;
/// ensembles and networks of another configuration are refused.
#[test]
fn averaged_weights_are_the_parameters_mean() {
    let (_, _, scene, history, bb) = common::scene("rope", 1);
    let cfg = ModelConfig::tiny();
    let net = ResidualNet::new(&cfg, 3).unwrap();
    let copy = net.with_residual_gain(1.0).unwrap();
    let avg = ResidualNet::average_weights(&[net.with_residual_gain(1.0).unwrap(), copy]).unwrap();
    assert_eq!(avg.ensemble_size(), 1);
    assert_eq!(avg.parameter_count(), net.parameter_count());
    let single = hybrid_rollout(&net, &bb, &scene, &history, opts(3)).unwrap();
    let out = hybrid_rollout(&avg, &bb, &scene, &history, opts(3)).unwrap();
    assert_eq!(out.positions, single.positions);

    let other = ResidualNet::new(&cfg, 4).unwrap();
    let mid = ResidualNet::average_weights(&[
        net.with_residual_gain(1.0).unwrap(),
        other.with_residual_gain(1.0).unwrap(),
    ])
    .unwrap();
    let (a, b, m) = (
        common::weights(&net),
        common::weights(&other),
        common::weights(&mid),
    );
    let mut differing = 0;
    for ((a, b), m) in a.iter().zip(&b).zip(&m) {
        for ((a, b), m) in a.iter().zip(b).zip(m) {
            assert!((m - 0.5 * (a + b)).abs() <= 1e-6 * (1.0 + a.abs() + b.abs()));
            differing += usize::from(a != b);
        }
    }
    assert!(differing > 0, "the two networks are the same");

    let err = ResidualNet::average_weights(&[two_tiny_networks()]).unwrap_err();
    assert!(err.to_string().contains("ensemble"), "{err}");
    let wider = ModelConfig {
        residual_scale: 0.3,
        ..cfg
    };
    let err =
        ResidualNet::average_weights(&[net, ResidualNet::new(&wider, 5).unwrap()]).unwrap_err();
    assert!(err.to_string().contains("configuration"), "{err}");
}
