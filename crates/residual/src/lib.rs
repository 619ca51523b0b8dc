//! PGRD's residual network on candle (CPU) and its training.
//!
//! A [`ResidualNet`] predicts, per particle, a bounded velocity residual that is added to the
//! spring-mass backbone's prediction: `v = v_sim + Δv`, `x = x_sim + Δv dt`. It reads the
//! current state, two history frames and the backbone's prediction ([`INPUTS`] channels;
//! [`GRIPPER_INPUTS`] more with [`ModelConfig::gripper_inputs`], [`GROUND_INPUTS`] with
//! [`ModelConfig::ground_inputs`], [`REST_INPUTS`] with [`ModelConfig::rest_inputs`]), encodes them with a serialized point transformer (Z-order / Hilbert curves, patch attention,
//! grid pooling U-Net; or a PointNet++-style ablation), decodes with Fourier features of the
//! position, and smooths over time with a per-particle transformer over its last `W` outputs
//! and a learned gate: `Δv = s ((1 − g) r + g δ)`, `s = 0.1 m/s`.
//!
//! [`hybrid_rollout`] runs backbone and network together; [`Trainer`] trains on 5-step
//! rollouts drawn from a [`TrainSet`]; [`ResidualNet::ensemble`] makes trained networks act as
//! one (their mean residual, or with [`EnsembleRule::Agreement`] that mean shrunk where they
//! disagree); [`ResidualNet::average_weights`] averages one run's snapshots' parameters into
//! one network; [`TrainSet::oracle_mde_cm`] measures how much a
//! corrector held to a given bound could gain at all. Architecture, sizes, normalisation,
//! costs and deviations from the paper: `docs/residual.md`.
//!
//! Set `RAYON_NUM_THREADS` in a program that trains: without it candle opens and parses
//! `/proc/cpuinfo` on every matrix product to count the cores, which took about 40 % of a
//! training step's time on a 2-core Linux host (`cargo xtask` sets it; `docs/BENCHMARKS.md`,
//! "Training: candle's thread count").
//!
//! ```no_run
//! # fn main() -> Result<(), residual::ResidualError> {
//! use residual::{History, ModelConfig, ResidualNet, RolloutOptions, hybrid_rollout};
//! let data = dataset::Dataset::open("fixtures/rope")?;
//! let episode = data.load_episode(0)?;
//! let window = scene::Protocol::Paper.window(episode.frames())?;
//! let scene = scene::Scene::new(&data.meta, &episode, window, &Default::default())?;
//! let backbone = scene.backbone(&springs::SpringParams::reference_rope(), &scene.sim_config(), Default::default())?;
//! let history = History::from_episode(&scene, &episode, data.meta.fps)?;
//! let net = ResidualNet::new(&ModelConfig::default(), 0)?;
//! let out = hybrid_rollout(&net, &backbone, &scene, &history, RolloutOptions::default())?;
//! assert_eq!(out.positions.len(), scene.window.steps);
//! # Ok(()) }
//! ```

mod augment;
mod backbone_op;
mod batch;
mod config;
mod encoder;
mod ensemble;
mod error;
mod kernels;
mod loss;
mod model;
mod nn;
mod rollout;
mod row_ops;
mod serialize;
mod train;

pub use augment::{rotate_history, rotate_scene};
pub use batch::{JobResult, PredictJob, predict_batch};
pub use config::{Combine, EncoderKind, InputConvention, ModelConfig, ResidualKind};
pub use ensemble::EnsembleRule;
pub use error::{ResidualError, Result};
pub use loss::{DISTANCE_EPS_CM, TrainLoss};
pub use model::{GRIPPER_INPUTS, GROUND_INPUTS, INPUTS, REST_INPUTS, ResidualNet};
pub use rollout::{History, HybridRollout, RolloutOptions, SimGradient, hybrid_rollout, predict};
pub use train::{
    BackboneOptionsFn, Sample, StartFrom, StepStats, TrainConfig, TrainSet, Trainer,
    clearly_better, paired_difference,
};
