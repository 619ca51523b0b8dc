//! The network's configuration (saved as JSON beside every checkpoint).

use serde::{Deserialize, Serialize};

use crate::{ResidualError, Result};

/// Which point encoder produces the per-particle features.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EncoderKind {
    /// Serialized point transformer in the spirit of Point Transformer V3 (the paper's).
    Ptv3,
    /// PointNet++-style set abstraction / feature propagation (the ablation).
    Pointnet,
}

/// What the residual corrects.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ResidualKind {
    /// `v = v_sim + Δv`, `x = x_sim + Δv dt` (the paper's).
    Velocity,
    /// `x = x_sim + Δx`, `v = v_sim` (the ablation the paper reports as diverging).
    Position,
}

/// How the temporal aggregator combines the decoder's output with its own offset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Combine {
    /// `Δv = s ((1 − g) r + g δ)` (the paper's).
    Gate,
    /// `Δv = s (r + δ) / 2` (ablation; halved so the bound stays `s`).
    Add,
    /// No temporal aggregator: `Δv = s r`.
    None,
}

/// Sizes and switches of the residual network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// Encoder family.
    pub encoder: EncoderKind,
    /// Channels of the encoder stages (one more stage per entry; each stage after the first
    /// starts with a grid pooling).
    pub enc_channels: Vec<usize>,
    /// Transformer blocks per encoder stage.
    pub enc_depths: Vec<usize>,
    /// Channels of the decoder stages, coarsest-but-one first (`enc_channels.len() - 1` entries);
    /// the last one is the per-particle feature width.
    pub dec_channels: Vec<usize>,
    /// Transformer blocks per decoder stage.
    pub dec_depths: Vec<usize>,
    /// Attention heads per block are `channels / head_dim`.
    pub head_dim: usize,
    /// Points per attention patch in serialized order.
    pub patch: usize,
    /// Cell size of the finest serialization grid, m.
    pub grid_m: f32,
    /// Cell size of the first pooling grid, m; doubled at every further pooling.
    pub pool_grid_m: f32,
    /// Use the Fourier-feature MLP decoder (false: a single linear head, the ablation).
    pub decoder: bool,
    /// Fourier frequencies `2^k`, `k = 0..fourier_bands`.
    pub fourier_bands: usize,
    /// Temporal combination (gate, addition, or none).
    pub combine: Combine,
    /// Decoder outputs kept per particle (W).
    pub window: usize,
    /// Width of the temporal transformer.
    pub temporal_dim: usize,
    /// Heads of the temporal transformer.
    pub temporal_heads: usize,
    /// Hidden width of its feed-forward layers.
    pub temporal_ff: usize,
    /// Its layers (post-norm).
    pub temporal_layers: usize,
    /// Bound of the residual, m/s per axis (0.1 in the paper).
    pub residual_scale: f32,
    /// Velocity or position residual.
    pub residual: ResidualKind,
    /// Factor applied to velocities before they enter the network (2 in the reference).
    pub velocity_scale: f32,
    /// How history and backbone positions enter the network. Configurations saved before this
    /// field existed used centred absolute positions and load as [`InputConvention::Absolute`],
    /// which this version refuses (its weights would be fed the wrong inputs).
    #[serde(default)]
    pub inputs: InputConvention,
    /// Also feed every particle the nearest closed gripper's offset from it (m) and velocity
    /// (times `velocity_scale`): [`GRIPPER_INPUTS`](crate::GRIPPER_INPUTS) more channels. Off
    /// in the paper (the gripper enters only through the held particles) and in configurations
    /// saved before the option existed.
    #[serde(default)]
    pub gripper_inputs: bool,
    /// Also feed every particle its height above the backbone's ground plane:
    /// [`GROUND_INPUTS`](crate::GROUND_INPUTS) more channels. The centred positions of the
    /// paper's inputs do not say where the table is, so a rope lying on it and the same shape
    /// held in the air look alike. Off in the paper and in configurations saved before the
    /// option existed.
    #[serde(default)]
    pub ground_inputs: bool,
    /// Also feed every particle its rest position in the backbone's rest shape, centred on
    /// the rest shape's centroid (m): [`REST_INPUTS`](crate::REST_INPUTS) more channels, a
    /// material coordinate that names the particle (a limb's tip, the body's middle) wherever
    /// the object is and however it is deformed. The paper's inputs are all current state, so
    /// a network must infer from the shape which part a particle belongs to. Not rotated by the
    /// augmentation (it is a label, not a direction). Off in the paper and in configurations
    /// saved before the option existed.
    #[serde(default)]
    pub rest_inputs: bool,
    /// Also correct particles held by a closed gripper. The paper's residual leaves them to
    /// the backbone's kinematic grasp, which moves them by the recorded gripper's displacement
    /// from wherever they are, so a correction shifts the grasp itself: what an object whose
    /// grasp slips, or whose gripper lags its recorded path, needs (`docs/residual-log.md`, "The
    /// grasp the network may not correct"). Off in the paper and in configurations saved
    /// before the option existed.
    #[serde(default)]
    pub held_residual: bool,
}

/// How the earlier and predicted positions are presented to the network.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InputConvention {
    /// Centred absolute positions (the first version's; no longer supported).
    #[default]
    Absolute,
    /// Displacements from the current position expressed as velocities (`docs/residual.md`).
    Displacement,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            encoder: EncoderKind::Ptv3,
            enc_channels: vec![16, 32, 64],
            enc_depths: vec![1, 1, 1],
            dec_channels: vec![32, 32],
            dec_depths: vec![1, 1],
            head_dim: 16,
            patch: 128,
            grid_m: 0.01,
            pool_grid_m: 0.02,
            decoder: true,
            fourier_bands: 5,
            combine: Combine::Gate,
            window: 5,
            temporal_dim: 16,
            temporal_heads: 2,
            temporal_ff: 32,
            temporal_layers: 1,
            residual_scale: 0.1,
            residual: ResidualKind::Velocity,
            velocity_scale: 2.0,
            inputs: InputConvention::Displacement,
            gripper_inputs: false,
            ground_inputs: false,
            rest_inputs: false,
            held_residual: false,
        }
    }
}

impl ModelConfig {
    /// A tiny configuration for tests and examples (same structure, fewer channels).
    pub fn tiny() -> Self {
        ModelConfig {
            enc_channels: vec![16, 32],
            enc_depths: vec![1, 1],
            dec_channels: vec![16],
            dec_depths: vec![1],
            head_dim: 8,
            patch: 32,
            temporal_dim: 16,
            temporal_heads: 2,
            temporal_ff: 32,
            ..ModelConfig::default()
        }
    }

    /// Input channels per particle: [`INPUTS`](crate::INPUTS), plus
    /// [`GRIPPER_INPUTS`](crate::GRIPPER_INPUTS) with `gripper_inputs` and
    /// [`GROUND_INPUTS`](crate::GROUND_INPUTS) with `ground_inputs` and
    /// [`REST_INPUTS`](crate::REST_INPUTS) with `rest_inputs`.
    pub fn input_dim(&self) -> usize {
        let mut dim = crate::INPUTS;
        if self.gripper_inputs {
            dim += crate::GRIPPER_INPUTS;
        }
        if self.ground_inputs {
            dim += crate::GROUND_INPUTS;
        }
        if self.rest_inputs {
            dim += crate::REST_INPUTS;
        }
        dim
    }

    /// Width of the per-particle feature the encoder produces.
    pub fn feature_dim(&self) -> usize {
        *self.dec_channels.last().unwrap_or(&self.enc_channels[0])
    }

    /// Checks every size and range.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(ResidualError::Config(m.to_string()));
        if self.inputs != InputConvention::Displacement {
            return bad(
                "network trained with the old absolute-position inputs; retrain it with this \
                 version (cargo xtask train --restart)",
            );
        }
        let stages = self.enc_channels.len();
        if stages == 0 || self.enc_depths.len() != stages {
            return bad("enc_channels and enc_depths need the same, non-zero length");
        }
        if self.dec_channels.len() + 1 != stages || self.dec_depths.len() + 1 != stages {
            return bad("dec_channels and dec_depths need enc_channels.len() - 1 entries");
        }
        let widths = self.enc_channels.iter().chain(&self.dec_channels);
        if self.head_dim == 0 || widths.clone().any(|c| *c == 0 || c % self.head_dim != 0) {
            return bad("every channel count must be a positive multiple of head_dim");
        }
        if self.patch < 2 || self.window == 0 || self.temporal_layers == 0 {
            return bad("patch >= 2, window >= 1 and temporal_layers >= 1 required");
        }
        if self.temporal_heads == 0 || !self.temporal_dim.is_multiple_of(self.temporal_heads) {
            return bad("temporal_dim must be a multiple of temporal_heads");
        }
        let positive = [
            self.grid_m,
            self.pool_grid_m,
            self.residual_scale,
            self.velocity_scale,
        ];
        if positive.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return bad("grid_m, pool_grid_m, residual_scale and velocity_scale must be > 0");
        }
        Ok(())
    }

    /// A short name of the ablation this configuration represents ("full" for the paper's).
    pub fn variant(&self) -> String {
        let mut parts = Vec::new();
        if self.encoder == EncoderKind::Pointnet {
            parts.push("pointnet");
        }
        if !self.decoder {
            parts.push("no-decoder");
        }
        match self.combine {
            Combine::Gate => {}
            Combine::Add => parts.push("add"),
            Combine::None => parts.push("no-temporal"),
        }
        if self.residual == ResidualKind::Position {
            parts.push("position-residual");
        }
        if self.gripper_inputs {
            parts.push("gripper-inputs");
        }
        if self.ground_inputs {
            parts.push("ground-inputs");
        }
        if self.rest_inputs {
            parts.push("rest-inputs");
        }
        if self.held_residual {
            parts.push("held-residual");
        }
        if parts.is_empty() {
            "full".into()
        } else {
            parts.join("+")
        }
    }
}
