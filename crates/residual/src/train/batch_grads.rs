//! One optimiser step's loss and gradients over its batch of training rollouts, in one of two
//! ways ([`TrainConfig::parallel_batch`]):
//!
//! - **one graph** (the default, every run before session 72): the rollouts' losses are summed
//!   into one scalar and differentiated once, one rollout after another on the calling thread;
//! - **per rollout, in parallel**: each rollout's forward pass and backward pass run on a rayon
//!   thread of their own, and the gradients are summed afterwards in the batch's order.
//!
//! Both compute the gradient of the same mean loss; they differ in the order in which floating
//! point adds the rollouts' contributions, so their weights agree to rounding, not bit for bit.
//! The parallel one gives the same bits on any number of threads: each rollout's arithmetic
//! does not depend on where it runs, and the sum's order is fixed.

use candle_core::{Tensor, Var};
use rayon::prelude::*;

use super::{Sample, TrainConfig, TrainSet};
use crate::rollout::{backbone_loss, hybrid_rollout_with_loss};
use crate::{ResidualError, ResidualNet, Result, RolloutOptions};

/// What a batch's forward and backward passes give the optimiser step.
pub(super) struct BatchGrads {
    /// The batch's mean rollout loss.
    pub loss: Tensor,
    /// Gradient of `loss` for each trainable variable, in the trainer's order (`None`: the
    /// variable took no part).
    pub grads: Vec<Option<Tensor>>,
    /// Rollouts that diverged (skipped).
    pub diverged: usize,
    /// Sum and count of the backbone's yardstick losses scored.
    pub backbone: (f64, usize),
}

/// The rollouts of one batch: the network, its variables and the step's settings.
pub(super) struct Batch<'a> {
    pub net: &'a ResidualNet,
    pub vars: &'a [(String, Var)],
    pub set: &'a TrainSet,
    pub cfg: &'a TrainConfig,
    /// Whether this step scores the backbone's yardstick.
    pub yardstick: bool,
}

/// One rollout's loss (and its gradients, when computed per rollout) and yardstick.
struct Rollout {
    loss: Tensor,
    grads: Option<Vec<Option<Tensor>>>,
    backbone: Option<f64>,
}

impl Batch<'_> {
    /// Loss and gradients over `samples`, each rolled out with its `opts`; `None` when every
    /// rollout diverged.
    pub fn grads(&self, samples: &[Sample], opts: &[RolloutOptions]) -> Result<Option<BatchGrads>> {
        let rollouts: Vec<Option<Rollout>> = if self.cfg.parallel_batch {
            samples
                .par_iter()
                .zip(opts.par_iter())
                .map(|(s, o)| self.rollout(s, *o, true))
                .collect::<Result<_>>()?
        } else {
            samples
                .iter()
                .zip(opts)
                .map(|(s, o)| self.rollout(s, *o, false))
                .collect::<Result<_>>()?
        };
        let diverged = rollouts.iter().filter(|r| r.is_none()).count();
        let done: Vec<Rollout> = rollouts.into_iter().flatten().collect();
        let Some(first) = done.first() else {
            return Ok(None);
        };
        let backbone = done
            .iter()
            .filter_map(|r| r.backbone)
            .fold((0.0, 0usize), |(s, n), b| (s + b, n + 1));
        let mut total = first.loss.clone();
        for r in &done[1..] {
            total = (total + &r.loss)?;
        }
        let used = done.len() as f64;
        let loss = (total / used)?;
        let grads = if self.cfg.parallel_batch {
            let mut sum: Vec<Option<Tensor>> = vec![None; self.vars.len()];
            for r in &done {
                let Some(grads) = &r.grads else { continue };
                for (acc, g) in sum.iter_mut().zip(grads) {
                    if let Some(g) = g {
                        *acc = Some(match acc.take() {
                            Some(a) => (a + g)?,
                            None => g.clone(),
                        });
                    }
                }
            }
            sum.into_iter()
                .map(|g| g.map(|g| g / used).transpose())
                .collect::<candle_core::Result<_>>()?
        } else if finite(&loss)? {
            self.var_grads(&loss)?
        } else {
            // Differentiating a NaN loss is wasted work; the caller reports the divergence.
            vec![None; self.vars.len()]
        };
        Ok(Some(BatchGrads {
            loss,
            grads,
            diverged,
            backbone,
        }))
    }

    /// One rollout of `sample`; with `backward`, also its own gradients. `None` when it
    /// diverged.
    fn rollout(
        &self,
        sample: &Sample,
        opts: RolloutOptions,
        backward: bool,
    ) -> Result<Option<Rollout>> {
        let backbone = self.set.backbone(sample);
        let out = match hybrid_rollout_with_loss(
            self.net,
            backbone,
            &sample.scene,
            &sample.history,
            opts,
            self.cfg.loss,
        ) {
            Ok(out) => out,
            Err(ResidualError::Diverged { .. }) => return Ok(None),
            Err(e) => return Err(e),
        };
        let loss = out
            .loss
            .ok_or_else(|| ResidualError::Input("no loss".into()))?;
        let grads = if backward && finite(&loss)? {
            Some(self.var_grads(&loss)?)
        } else {
            None
        };
        let backbone = if self.yardstick {
            backbone_loss(
                backbone,
                &sample.scene,
                self.cfg.rollout_steps,
                self.cfg.loss,
            )?
        } else {
            None
        };
        Ok(Some(Rollout {
            loss,
            grads,
            backbone,
        }))
    }

    /// The gradient of `loss` for each trainable variable, in the trainer's order.
    fn var_grads(&self, loss: &Tensor) -> Result<Vec<Option<Tensor>>> {
        let store = loss.backward()?;
        Ok(self
            .vars
            .iter()
            .map(|(_, v)| store.get(v.as_tensor()).cloned())
            .collect())
    }
}

/// Whether a scalar tensor is finite.
fn finite(t: &Tensor) -> Result<bool> {
    Ok(t.to_scalar::<f32>()?.is_finite())
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::ModelConfig;

    /// The rope fixture's training split on the reference rope parameters.
    fn rope_set() -> TrainSet {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/rope");
        let data = dataset::Dataset::open(dir).unwrap();
        TrainSet::new(
            &data,
            dataset::Split::Train,
            &springs::SpringParams::reference_rope(),
            &scene::SceneConfig::default(),
        )
        .unwrap()
    }

    fn grads_of(parallel: bool, threads: usize) -> (f32, Vec<Option<Vec<f32>>>) {
        let set = rope_set();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let samples: Vec<Sample> = (0..3)
            .map(|_| set.sample(&mut rng, 3, true).unwrap())
            .collect();
        let opts: Vec<RolloutOptions> = (0..3)
            .map(|k| RolloutOptions {
                steps: 3,
                train: true,
                curves: [k % 4, (k + 1) % 4, (k + 2) % 4, (k + 3) % 4],
                ..Default::default()
            })
            .collect();
        let model = ModelConfig {
            residual_scale: 0.5,
            ..ModelConfig::tiny()
        };
        let net = ResidualNet::new(&model, 4).unwrap();
        let vars = net.named_vars();
        let cfg = TrainConfig {
            parallel_batch: parallel,
            ..TrainConfig::default()
        };
        let batch = Batch {
            net: &net,
            vars: &vars,
            set: &set,
            cfg: &cfg,
            yardstick: false,
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let out = pool
            .install(|| batch.grads(&samples, &opts))
            .unwrap()
            .unwrap();
        let grads = out
            .grads
            .iter()
            .map(|g| {
                g.as_ref()
                    .map(|g| g.flatten_all().unwrap().to_vec1().unwrap())
            })
            .collect();
        (out.loss.to_scalar().unwrap(), grads)
    }

    /// Per rollout in parallel, the batch's loss is the one-graph way's bit for bit (the same
    /// forward arithmetic) and every variable's gradient agrees with it to rounding: within
    /// 1e-5 of the largest gradient entry of that variable; the same variables get a gradient.
    #[test]
    fn per_rollout_gradients_sum_to_the_one_graph_gradient() {
        let (loss_one, one) = grads_of(false, 1);
        let (loss_par, par) = grads_of(true, 2);
        assert_eq!(loss_one, loss_par);
        assert_eq!(one.len(), par.len());
        let mut compared = 0;
        for (k, (a, b)) in one.iter().zip(&par).enumerate() {
            assert_eq!(a.is_some(), b.is_some(), "variable {k}");
            let (Some(a), Some(b)) = (a, b) else { continue };
            let scale = a.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-12);
            let worst = a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(
                worst <= 1e-5 * scale,
                "variable {k}: differs by {worst} (largest entry {scale})"
            );
            compared += 1;
        }
        assert!(compared > 10, "only {compared} variables had gradients");
    }

    /// The parallel way gives the same bits on one thread and on three.
    #[test]
    fn per_rollout_gradients_do_not_depend_on_the_thread_count() {
        assert_eq!(grads_of(true, 1), grads_of(true, 3));
    }
}
