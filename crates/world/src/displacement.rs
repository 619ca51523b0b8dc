//! How far a set of effects moves an object, measured in the world before any model sees it.

use crate::{Effects, Error, GenConfig, Observation, generate};

/// Mean distance, m, between the true tracked positions of `cfg`'s episodes generated with
/// `cfg.effects` and the same episodes generated with no effect at all: same seed, hence the
/// same placements, tracked particles and gripper motions, and no observation model (noise,
/// drift and occlusion would blur the comparison). The mean runs over every episode, frame and
/// tracked particle. An effect whose displacement is far below a model's own error cannot be
/// found from its data by any diagnosis.
///
/// Generates the episodes twice; Gaussians are never generated.
///
/// ```
/// use world::{EffectKind, Effects, GenConfig, ObjectKind};
/// let mut cfg = GenConfig::fixture(ObjectKind::Rope);
/// (cfg.train_episodes, cfg.val_episodes, cfg.tracked) = (1, 0, 30);
/// cfg.effects = Effects::none();
/// assert_eq!(world::effect_displacement_m(&cfg)?, 0.0);
/// cfg.effects = Effects::only(ObjectKind::Rope, EffectKind::ActuationDelay);
/// assert!(world::effect_displacement_m(&cfg)? > 0.001);
/// # Ok::<(), world::Error>(())
/// ```
pub fn effect_displacement_m(cfg: &GenConfig) -> Result<f64, Error> {
    let mut with = cfg.clone();
    with.observation = Observation::none();
    with.gaussian_particles = 0;
    let mut without = with.clone();
    without.effects = Effects::none();
    let a = generate(&with)?;
    let b = generate(&without)?;
    let mut sum = 0.0f64;
    let mut count = 0usize;
    for ((ea, _), (eb, _)) in a.episodes.iter().zip(&b.episodes) {
        for (p, q) in ea.positions().iter().zip(eb.positions()) {
            sum += f64::from(p.distance(*q));
            count += 1;
        }
    }
    Ok(if count == 0 { 0.0 } else { sum / count as f64 })
}
