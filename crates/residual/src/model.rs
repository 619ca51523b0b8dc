//! The residual network: encoder, Fourier decoder, temporal aggregator, and its parameters.

use std::path::Path;

use candle_core::{D, DType, Device, Tensor, Var};
use candle_nn::{Linear, VarBuilder, VarMap};
use glam::Vec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::encoder::Encoder;
use crate::kernels::{LayerParams, Mix, TemporalParams};
use crate::nn::{Mlp, NORM_EPS, Norm, Pass, affine, apply, dense, linear, sigmoid, softmax};
use crate::serialize::{CURVES, Structure};
use crate::{Combine, ModelConfig, ResidualError, Result};

/// Input channels per particle: x, v, x(t−1), x(t−2), v(t−1), v(t−2), x_sim, v_sim.
pub const INPUTS: usize = 24;

/// Extra channels with [`ModelConfig::gripper_inputs`]: the nearest closed gripper's offset
/// from the particle and its velocity (see `docs/residual.md`, Normalisation).
pub const GRIPPER_INPUTS: usize = 6;

/// Extra channels with [`ModelConfig::ground_inputs`]: the height above the ground plane in
/// decimetres (clamped to [−1, 10]) and a contact proximity `exp(−|h| / 1 cm)`.
pub const GROUND_INPUTS: usize = 2;

/// Extra channels with [`ModelConfig::rest_inputs`]: the particle's rest position, centred on
/// the rest shape's centroid, m.
pub const REST_INPUTS: usize = 3;

/// Per particle, the [`REST_INPUTS`] channels: its position in the rest shape `rest` (m)
/// relative to the rest shape's centroid, appended to `out`.
pub(crate) fn rest_inputs(rest: &[Vec3], out: &mut Vec<f32>) {
    let centroid = rest.iter().sum::<Vec3>() / rest.len().max(1) as f32;
    for p in rest {
        out.extend((*p - centroid).to_array());
    }
}

/// Height (m) beyond which the ground channels read as "far from the ground": the first
/// channel saturates there, and a backbone without a ground plane reads as this far.
const GROUND_FAR_M: f32 = 1.0;

/// Per particle at `x` (m), the [`GROUND_INPUTS`] channels for a ground plane at height
/// `ground_z` (m; `None`: no ground, every particle far from it), appended to `out`. The first
/// channel tells lying from lifted; the second is near 1 only within a few centimetres of the
/// plane, where contact and friction act.
pub(crate) fn ground_inputs(x: &[Vec3], ground_z: Option<f32>, out: &mut Vec<f32>) {
    for p in x {
        let h = ground_z.map_or(GROUND_FAR_M, |z| (p.z - z).min(GROUND_FAR_M));
        out.push((h / 0.1).max(-1.0));
        out.push((-h.abs() / 0.01).exp());
    }
}

/// Per particle at `x` (m): the offset (m) to the nearest gripper closed in `from`, and that
/// gripper's velocity from `from` to `to` (m/s, times `velocity_scale`), as 6 values appended
/// to `out`; zeros where no gripper is closed. The network otherwise learns of the action only
/// through the held particles, and has to carry it along the object itself.
pub(crate) fn gripper_inputs(
    x: &[Vec3],
    from: springs::ActionFrame<'_>,
    to: springs::ActionFrame<'_>,
    dt: f32,
    velocity_scale: f32,
    out: &mut Vec<f32>,
) {
    let closed: Vec<usize> = (0..from.positions.len())
        .filter(|&g| from.closed.get(g).copied().unwrap_or(false))
        .collect();
    for p in x {
        let nearest = closed.iter().copied().min_by(|&a, &b| {
            let (da, db) = (
                from.positions[a].distance_squared(*p),
                from.positions[b].distance_squared(*p),
            );
            da.total_cmp(&db)
        });
        let (offset, velocity) = match nearest {
            Some(g) => {
                let end = to.positions.get(g).copied().unwrap_or(from.positions[g]);
                (
                    from.positions[g] - *p,
                    (end - from.positions[g]) * (velocity_scale / dt),
                )
            }
            None => (Vec3::ZERO, Vec3::ZERO),
        };
        out.extend(offset.to_array());
        out.extend(velocity.to_array());
    }
}

/// Hidden widths of the decoder MLP (the reference's 64 → 64 → 32 → 3).
const HEAD: [usize; 3] = [64, 64, 32];

/// Output layers start at this fraction of the default scale, so an untrained network adds a
/// residual close to zero (the hybrid starts as the backbone) while every layer still receives
/// a gradient.
const OUTPUT_INIT_GAIN: f64 = 0.01;

/// The paper's residual bound (m/s per axis). With a wider bound the residual-valued output
/// layers start smaller by `PAPER_RESIDUAL_SCALE / residual_scale`, so every untrained network
/// adds about the residual an untrained one of the paper's bound adds: step-0 networks, the
/// fallback of held-out selection, stay close to the backbone (without it the teddy's step-0
/// network at 1 m/s was 0.3 cm worse than the backbone on val; `docs/residual.md`, "The
/// bound's ceiling").
const PAPER_RESIDUAL_SCALE: f32 = 0.1;

#[derive(Debug)]
enum Head {
    /// `[x, sin 2^k x, cos 2^k x]` ⊕ feature → Linear → Linear+ReLU → Linear+ReLU → Linear.
    Fourier { layers: [Linear; 4], bands: usize },
    /// Ablation: one linear layer on the encoder feature.
    Linear(Linear),
}

/// One post-norm transformer layer of the temporal aggregator.
#[derive(Debug)]
struct TemporalLayer {
    qkv: Linear,
    proj: Linear,
    n1: Norm,
    ff: Mlp,
    n2: Norm,
}

#[derive(Debug)]
struct Temporal {
    embed: Linear,
    pe: Tensor,
    layers: Vec<TemporalLayer>,
    heads: usize,
    delta: Linear,
    gate: Option<Linear>,
}

/// PGRD's residual network (see `docs/residual.md` for the architecture and sizes).
///
/// Parameters live in a `VarMap`; [`ResidualNet::save`] writes them as safetensors with the
/// configuration as JSON beside them, [`ResidualNet::load`] reads both back.
pub struct ResidualNet {
    cfg: ModelConfig,
    varmap: VarMap,
    encoder: Encoder,
    head: Head,
    temporal: Option<Temporal>,
    device: Device,
    /// The other members of an ensemble (`crate::ensemble`); empty for a single network.
    pub(crate) members: Vec<ResidualNet>,
    /// How an ensemble combines its members' residuals.
    pub(crate) rule: crate::EnsembleRule,
}

impl std::fmt::Debug for ResidualNet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ResidualNet")
            .field("cfg", &self.cfg)
            .field("parameters", &self.parameter_count())
            .field("ensemble_size", &self.ensemble_size())
            .finish_non_exhaustive()
    }
}

fn sinusoid(w: usize, d: usize, dev: &Device) -> Result<Tensor> {
    let mut pe = vec![0f32; w * d];
    for t in 0..w {
        for i in 0..d {
            let freq = 1.0 / 10000f64.powf((2 * (i / 2)) as f64 / d as f64);
            let a = t as f64 * freq;
            pe[t * d + i] = if i % 2 == 0 { a.sin() } else { a.cos() } as f32;
        }
    }
    Ok(Tensor::from_vec(pe, (w, d), dev)?)
}

impl ResidualNet {
    /// A freshly initialised network; the same seed gives the same parameters.
    pub fn new(cfg: &ModelConfig, seed: u64) -> Result<Self> {
        cfg.validate()?;
        let device = Device::Cpu;
        let varmap = VarMap::new();
        let vb = VarBuilder::from_varmap(&varmap, DType::F32, &device);
        let encoder = Encoder::new(cfg.input_dim(), cfg, vb.pp("encoder"))?;
        let f = cfg.feature_dim();
        let head = if cfg.decoder {
            let fourier = 3 + 6 * cfg.fourier_bands;
            let vb = vb.pp("decoder");
            Head::Fourier {
                layers: [
                    linear(fourier + f, HEAD[0], vb.pp("l0"))?,
                    linear(HEAD[0], HEAD[1], vb.pp("l1"))?,
                    linear(HEAD[1], HEAD[2], vb.pp("l2"))?,
                    linear(HEAD[2], 3, vb.pp("out"))?,
                ],
                bands: cfg.fourier_bands,
            }
        } else {
            Head::Linear(linear(f, 3, vb.pp("decoder.out"))?)
        };
        let temporal = if cfg.combine == Combine::None {
            None
        } else {
            let d = cfg.temporal_dim;
            let vb = vb.pp("temporal");
            let layers = (0..cfg.temporal_layers)
                .map(|l| {
                    let vb = vb.pp(format!("layer{l}"));
                    Ok(TemporalLayer {
                        qkv: linear(d, 3 * d, vb.pp("qkv"))?,
                        proj: linear(d, d, vb.pp("proj"))?,
                        n1: Norm::new(d, vb.pp("norm1"))?,
                        ff: Mlp::new(d, cfg.temporal_ff, d, vb.pp("ff"))?,
                        n2: Norm::new(d, vb.pp("norm2"))?,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            Some(Temporal {
                embed: linear(3, d, vb.pp("embed"))?,
                pe: sinusoid(cfg.window, d, &device)?,
                layers,
                heads: cfg.temporal_heads,
                delta: linear(d, 3, vb.pp("delta.out"))?,
                gate: if cfg.combine == Combine::Gate {
                    Some(linear(d, 3, vb.pp("gate"))?)
                } else {
                    None
                },
            })
        };
        let net = ResidualNet {
            cfg: cfg.clone(),
            varmap,
            encoder,
            head,
            temporal,
            device,
            members: Vec::new(),
            rule: crate::EnsembleRule::Mean,
        };
        net.init(seed)?;
        Ok(net)
    }

    /// Seeded re-initialisation (candle's own initialisers draw from an unseeded generator):
    /// weights and biases uniform in ±1/√fan_in, output layers scaled by `OUTPUT_INIT_GAIN`
    /// (residual-valued ones also by `PAPER_RESIDUAL_SCALE / residual_scale` when that is
    /// below 1), norms at identity.
    fn init(&self, seed: u64) -> Result<()> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let vars = self.named_vars();
        let fan_in: std::collections::HashMap<String, usize> = vars
            .iter()
            .filter(|(n, v)| n.ends_with(".weight") && v.rank() == 2)
            .map(|(n, v)| (n.trim_end_matches(".weight").to_string(), v.dims()[1]))
            .collect();
        for (name, var) in &vars {
            let (layer, kind) = name.rsplit_once('.').unwrap_or(("", name));
            if kind != "weight" && kind != "bias" {
                continue;
            }
            let fan = fan_in.get(layer).copied().unwrap_or(1).max(1);
            let mut b = 1.0 / (fan as f64).sqrt();
            if layer.ends_with(".out") || layer.ends_with("gate") {
                b *= OUTPUT_INIT_GAIN;
            }
            if layer.ends_with(".out") {
                // Exactly 1 at the paper's bound, so such networks are drawn as before.
                b *= f64::from(PAPER_RESIDUAL_SCALE / self.cfg.residual_scale).min(1.0);
            }
            let n = var.elem_count();
            let vals: Vec<f32> = (0..n).map(|_| rng.random_range(-b..b) as f32).collect();
            var.set(&Tensor::from_vec(vals, var.shape(), &self.device)?)?;
        }
        Ok(())
    }

    /// A copy of this network that adds no residual: its residual-valued output layers (the
    /// decoder's last layer and the temporal aggregator's offset, the layers named `*.out`)
    /// are zero and every other parameter is copied, so `Δ = 0` for every input and the hybrid
    /// model steps exactly as its backbone alone.
    ///
    /// Held-out selection (`cargo xtask train --holdout`) writes it when no trained network
    /// beats the backbone clearly: "keep the backbone" is then exact, not a step-0 network
    /// that is only close to it (`docs/residual.md`).
    ///
    /// ```
    /// use residual::{ModelConfig, ResidualNet};
    /// let net = ResidualNet::new(&ModelConfig::tiny(), 1)?;
    /// let quiet = net.without_residual()?;
    /// assert_eq!(quiet.config(), net.config());
    /// assert_eq!(quiet.parameter_count(), net.parameter_count());
    /// # Ok::<(), residual::ResidualError>(())
    /// ```
    pub fn without_residual(&self) -> Result<ResidualNet> {
        self.map_members(|m| m.copy_as(m.cfg.clone(), true))
    }

    /// A network of configuration `cfg` (this one's but for the bound) holding this one's
    /// parameters, with the residual-valued output layers zeroed when `silence_output`.
    pub(crate) fn copy_as(&self, cfg: ModelConfig, silence_output: bool) -> Result<ResidualNet> {
        let copy = ResidualNet::new(&cfg, 0)?;
        let own: std::collections::HashMap<String, Var> = self.named_vars().into_iter().collect();
        for (name, var) in copy.named_vars() {
            let layer = name.rsplit_once('.').map_or(name.as_str(), |(l, _)| l);
            if silence_output && layer.ends_with(".out") {
                var.set(&var.as_tensor().zeros_like()?)?;
            } else if let Some(src) = own.get(&name) {
                var.set(src.as_tensor())?;
            }
        }
        Ok(copy)
    }

    /// A copy of this network whose residual is `gain` times its own (`gain` finite and
    /// ≥ 0; 0 gives [`ResidualNet::without_residual`]): every parameter is copied and the
    /// bound `residual_scale` multiplied by `gain`, which scales `Δ` and nothing else. A
    /// planner that sees how the system responds can choose how far to trust the network
    /// (`plan::OnlinePgrd`).
    ///
    /// ```
    /// use residual::{ModelConfig, ResidualNet};
    /// let net = ResidualNet::new(&ModelConfig::tiny(), 1)?;
    /// let half = net.with_residual_gain(0.5)?;
    /// assert_eq!(half.config().residual_scale, 0.5 * net.config().residual_scale);
    /// assert!(net.with_residual_gain(-1.0).is_err());
    /// # Ok::<(), residual::ResidualError>(())
    /// ```
    pub fn with_residual_gain(&self, gain: f32) -> Result<ResidualNet> {
        if !(gain.is_finite() && gain >= 0.0) {
            return Err(ResidualError::Config(format!(
                "residual gain {gain}: must be finite and >= 0"
            )));
        }
        if gain == 0.0 {
            return self.without_residual();
        }
        self.map_members(|m| {
            let cfg = ModelConfig {
                residual_scale: m.cfg.residual_scale * gain,
                ..m.cfg.clone()
            };
            m.copy_as(cfg, false)
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.cfg
    }

    /// Every trainable tensor with its name, sorted by name (a fixed order keeps gradient
    /// norms and optimiser updates reproducible).
    pub fn named_vars(&self) -> Vec<(String, Var)> {
        let data = self.varmap.data().lock().unwrap_or_else(|e| e.into_inner());
        let mut v: Vec<(String, Var)> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    /// Number of scalar parameters (of every member of an ensemble).
    pub fn parameter_count(&self) -> usize {
        self.ensemble_members()
            .map(|m| {
                m.named_vars()
                    .iter()
                    .map(|(_, v)| v.elem_count())
                    .sum::<usize>()
            })
            .sum()
    }

    /// The device tensors live on (CPU).
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Writes the parameters to `path` (safetensors) and the configuration to `path` with the
    /// extension `json` (an ensemble: every member's parameters under `member<k>.` and the
    /// member count in the JSON, see [`ResidualNet::ensemble`]). Each file is written beside
    /// its path and renamed into place, so an interrupted save leaves the old files whole.
    pub fn save(&self, path: &Path) -> Result<()> {
        if !self.members.is_empty() {
            return self.save_ensemble(path);
        }
        let tensors = self
            .named_vars()
            .into_iter()
            .map(|(name, var)| (name, var.as_tensor().clone()))
            .collect();
        save_tensors_atomic(&tensors, path)?;
        let json = path.with_extension("json");
        let text =
            serde_json::to_string_pretty(&self.cfg).map_err(|source| ResidualError::Json {
                path: json.display().to_string(),
                cause: source,
            })?;
        dataset::write_atomic(&json, text.as_bytes()).map_err(ResidualError::Dataset)?;
        Ok(())
    }

    /// Reads a network (or an ensemble) written by [`ResidualNet::save`].
    pub fn load(path: &Path) -> Result<Self> {
        let json = path.with_extension("json");
        let text = std::fs::read_to_string(&json).map_err(|source| ResidualError::Io {
            path: json.display().to_string(),
            cause: source,
        })?;
        let (cfg, saved) =
            crate::ensemble::parse_saved_config(&text).map_err(|source| ResidualError::Json {
                path: json.display().to_string(),
                cause: source,
            })?;
        if saved.members != 1 {
            return Self::load_ensemble(path, &cfg, saved.members, saved.rule);
        }
        let mut net = ResidualNet::new(&cfg, 0).map_err(|e| match e {
            ResidualError::Config(m) => ResidualError::Config(format!("{}: {m}", json.display())),
            e => e,
        })?;
        net.varmap.load(path)?;
        Ok(net)
    }

    /// One-shot residual (m/s, `(N, 3)`) for features `(N, input_dim)` at centred positions
    /// `pos` (m), with an empty temporal window (as at a rollout's first step) and the curves
    /// in their default order.
    pub fn predict(&self, feats: &Tensor, pos: &[Vec3]) -> Result<Tensor> {
        if feats.dims() != [pos.len(), self.cfg.input_dim()] {
            return Err(ResidualError::Input(format!(
                "features {:?} for {} positions",
                feats.dims(),
                pos.len()
            )));
        }
        let c = &self.cfg;
        let st = Structure::new(
            pos,
            c.enc_channels.len(),
            c.grid_m,
            c.pool_grid_m,
            c.patch,
            &self.device,
        )?;
        let flat: Vec<f32> = pos.iter().flat_map(|p| p.to_array()).collect();
        let p = Tensor::from_vec(flat, (pos.len(), 3), &self.device)?;
        let mut deltas = Vec::with_capacity(self.ensemble_size());
        for m in self.ensemble_members() {
            let r = m.decode(feats, &p, &st, [0, 1, 2, 3], Pass::Grad)?;
            deltas.push(m.aggregate(&[r], Pass::Grad)?);
        }
        crate::ensemble::combine(deltas, self.rule)
    }

    /// Decoder output `r ∈ (−1, 1)^3` per particle from the `(N, input_dim)` features and the
    /// centred positions `(N, 3)`.
    pub(crate) fn decode(
        &self,
        feats: &Tensor,
        pos: &Tensor,
        st: &Structure,
        curves: [usize; CURVES],
        pass: Pass,
    ) -> Result<Tensor> {
        let f = self.encoder.forward(feats, st, curves, pass)?;
        let out = match &self.head {
            Head::Fourier { layers, bands } => {
                let mut parts = vec![pos.clone()];
                for k in 0..*bands {
                    let s = (pos * f64::from(1u32 << k))?;
                    parts.push(s.sin()?);
                    parts.push(s.cos()?);
                }
                parts.push(f);
                let x = Tensor::cat(&parts, 1)?;
                let x = affine(&layers[0], &x, pass, false)?;
                let x = affine(&layers[1], &x, pass, true)?;
                let x = affine(&layers[2], &x, pass, true)?;
                affine(&layers[3], &x, pass, false)?
            }
            Head::Linear(l) => affine(l, &f, pass, false)?,
        };
        Ok(out.tanh()?)
    }

    /// The temporal aggregator's parameters for [`crate::kernels::TemporalParams::apply`]
    /// (inference), or `None` for a network without aggregator.
    pub(crate) fn temporal_params(&self) -> Result<Option<TemporalParams>> {
        let Some(t) = &self.temporal else {
            return Ok(None);
        };
        let layers = t
            .layers
            .iter()
            .map(|l| {
                let (fc1, fc2) = l.ff.layers();
                Ok(LayerParams {
                    qkv: dense(&l.qkv)?,
                    proj: dense(&l.proj)?,
                    n1: l.n1.params()?,
                    fc1: dense(fc1)?,
                    fc2: dense(fc2)?,
                    n2: l.n2.params()?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Some(TemporalParams {
            embed: dense(&t.embed)?,
            pe: t.pe.flatten_all()?.to_vec1()?,
            layers,
            heads: t.heads,
            delta: dense(&t.delta)?,
            mix: match &t.gate {
                Some(g) => Mix::Gate(dense(g)?),
                None => Mix::Add,
            },
            window: self.cfg.window,
            scale: self.cfg.residual_scale,
            eps: NORM_EPS,
        }))
    }

    /// [`Self::aggregate`] for inference on plain rows: the residual `(rows, 3)` flattened, m/s,
    /// from the window of decoder outputs (oldest first, each `(rows, 3)` flattened), with the
    /// parameters from [`Self::temporal_params`].
    pub(crate) fn aggregate_rows(
        &self,
        params: Option<&TemporalParams>,
        window: &[&[f32]],
        rows: usize,
    ) -> Vec<f32> {
        match params {
            Some(p) => p.apply(window, rows),
            None => {
                let s = self.cfg.residual_scale;
                window.last().map_or_else(
                    || vec![0.0; 3 * rows],
                    |r| r.iter().map(|r| r * s).collect(),
                )
            }
        }
    }

    /// The bounded residual `Δ (N, 3)` in m/s from the window of decoder outputs (oldest
    /// first; its last entry is the current `r`; shorter windows are left-padded with copies
    /// of the newest).
    pub(crate) fn aggregate(&self, window: &[Tensor], pass: Pass) -> Result<Tensor> {
        let s = f64::from(self.cfg.residual_scale);
        let r = window
            .last()
            .ok_or_else(|| ResidualError::Input("empty window".into()))?;
        let Some(t) = &self.temporal else {
            return Ok((r * s)?);
        };
        let w = self.cfg.window;
        let tail = &window[window.len().saturating_sub(w)..];
        let mut tokens: Vec<Tensor> = vec![r.clone(); w - tail.len()];
        tokens.extend(tail.iter().cloned());
        let x = Tensor::stack(&tokens, 1)?; // (N, W, 3)
        let mut h = apply(&t.embed, &x)?.broadcast_add(&t.pe)?;
        let n = h.dim(0)?;
        let d = self.cfg.temporal_dim;
        let (heads, hd) = (t.heads, d / t.heads);
        for (l, layer) in t.layers.iter().enumerate() {
            let last = l + 1 == t.layers.len();
            let qkv = apply(&layer.qkv, &h)?.reshape((n, w, 3, heads, hd))?;
            let part = |i: usize| -> Result<Tensor> {
                Ok(qkv.narrow(2, i, 1)?.squeeze(2)?.permute((0, 2, 1, 3))?)
            };
            // Only the newest token feeds the gate, so the last layer computes just that query.
            let (mut q, k, v) = (part(0)?, part(1)?, part(2)?);
            let mut resid = h.clone();
            if last {
                q = q.narrow(2, w - 1, 1)?;
                resid = h.narrow(1, w - 1, 1)?;
            }
            let wq = q.dim(2)?;
            // Tiny per-particle attention as broadcast products: one big element-wise op is far
            // cheaper on CPU than N·heads separate 5×5 matmuls.
            let scores = (q
                .unsqueeze(3)?
                .broadcast_mul(&k.unsqueeze(2)?)?
                .sum(D::Minus1)?
                * (1.0 / (hd as f64).sqrt()))?;
            let a = softmax(&scores, pass)?;
            let o = a.unsqueeze(4)?.broadcast_mul(&v.unsqueeze(2)?)?.sum(3)?;
            let o = o.permute((0, 2, 1, 3))?.reshape((n, wq, d))?;
            let x = layer
                .n1
                .forward(&(resid + apply(&layer.proj, &o)?)?, pass)?;
            h = layer
                .n2
                .forward(&(&x + layer.ff.forward(&x, pass)?)?, pass)?;
        }
        let last = h.narrow(1, h.dim(1)? - 1, 1)?.squeeze(1)?;
        let delta = apply(&t.delta, &last)?.tanh()?;
        match &t.gate {
            Some(gate) => {
                let g = sigmoid(&apply(gate, &last)?)?;
                let keep = (g.ones_like()? - &g)?;
                Ok((((keep * r)? + (g * delta)?)? * s)?)
            }
            None => Ok(((r + delta)? * (s / 2.0))?),
        }
    }
}

/// Writes `tensors` to `path` (safetensors) through a temporary file beside it, renamed into
/// place, so an interrupted write never leaves a truncated file under the final name.
pub(crate) fn save_tensors_atomic(
    tensors: &std::collections::HashMap<String, Tensor>,
    path: &Path,
) -> Result<()> {
    let tmp = path.with_extension("tmp");
    candle_core::safetensors::save(tensors, &tmp)?;
    std::fs::rename(&tmp, path).map_err(|source| ResidualError::Io {
        path: path.display().to_string(),
        cause: source,
    })
}

#[cfg(test)]
mod tests {
    use glam::Vec3;
    use springs::ActionFrame;

    use super::{gripper_inputs, ground_inputs, rest_inputs};

    #[test]
    fn rest_inputs_are_the_rest_shape_about_its_centroid() {
        let rest = [
            Vec3::new(1.0, 2.0, 0.0),
            Vec3::new(1.2, 2.0, 0.0),
            Vec3::new(1.1, 2.3, 0.3),
        ];
        let mut out = Vec::new();
        rest_inputs(&rest, &mut out);
        assert_eq!(out.len(), 9);
        let expect = [-0.1, -0.1, -0.1, 0.1, -0.1, -0.1, 0.0, 0.2, 0.2];
        for (o, e) in out.iter().zip(expect) {
            assert!((o - e).abs() < 1e-6, "{out:?}");
        }
        // Where the rest shape sat does not matter, only the particle's place in it.
        let moved: Vec<Vec3> = rest
            .iter()
            .map(|p| *p + Vec3::new(-3.0, 0.5, 1.0))
            .collect();
        let mut again = Vec::new();
        rest_inputs(&moved, &mut again);
        for (a, b) in out.iter().zip(&again) {
            assert!((a - b).abs() < 1e-5);
        }
    }

    #[test]
    fn gripper_inputs_use_the_nearest_closed_gripper() {
        let from = [Vec3::new(0.0, 0.0, 0.1), Vec3::new(1.0, 0.0, 0.1)];
        let to = [Vec3::new(0.0, 0.03, 0.1), Vec3::new(1.0, 0.0, 0.4)];
        let x = [Vec3::new(0.9, 0.0, 0.0), Vec3::new(0.2, 0.0, 0.0)];
        let frame = |p, c| ActionFrame {
            positions: p,
            closed: c,
        };
        let mut out = Vec::new();
        // Only the first gripper is closed: both particles see it, even the one nearer the
        // open second gripper. dt 0.1 s, velocity scale 2: 0.03 m / 0.1 s × 2 = 0.6.
        gripper_inputs(
            &x,
            frame(&from, &[true, false]),
            frame(&to, &[true, false]),
            0.1,
            2.0,
            &mut out,
        );
        let want = [-0.9, 0.0, 0.1, 0.0, 0.6, 0.0, -0.2, 0.0, 0.1, 0.0, 0.6, 0.0];
        for (a, b) in out.iter().zip(want) {
            assert!((a - b).abs() < 1e-5, "{out:?}");
        }
        // Both closed: each particle sees its nearest.
        out.clear();
        gripper_inputs(
            &x,
            frame(&from, &[true, true]),
            frame(&to, &[true, true]),
            0.1,
            2.0,
            &mut out,
        );
        assert!(
            (out[0] - 0.1).abs() < 1e-5 && (out[5] - 6.0).abs() < 1e-4,
            "{out:?}"
        );
        // None closed (or no gripper at all): zeros.
        out.clear();
        gripper_inputs(
            &x,
            frame(&from, &[false, false]),
            frame(&to, &[false, false]),
            0.1,
            2.0,
            &mut out,
        );
        gripper_inputs(&x, frame(&[], &[]), frame(&[], &[]), 0.1, 2.0, &mut out);
        assert_eq!(out, vec![0.0; 24]);
    }

    #[test]
    fn ground_inputs_tell_contact_from_lifted() {
        let x = [
            Vec3::new(0.3, 0.0, 0.05),
            Vec3::new(0.0, 0.0, 0.004),
            Vec3::new(0.0, 0.0, 2.0),
            Vec3::new(0.0, 0.0, -0.2),
        ];
        let mut out = Vec::new();
        ground_inputs(&x, Some(0.0), &mut out);
        let want = [
            0.5,
            (-5.0f32).exp(),
            0.04,
            (-0.4f32).exp(),
            10.0,
            0.0,
            -1.0,
            0.0,
        ];
        for (got, want) in out.iter().zip(want) {
            assert!((got - want).abs() < 1e-5, "{out:?}");
        }
        // A plane elsewhere moves the heights with it; no plane reads as far above.
        out.clear();
        ground_inputs(&x[..1], Some(0.04), &mut out);
        assert!((out[0] - 0.1).abs() < 1e-5 && (out[1] - (-1.0f32).exp()).abs() < 1e-5);
        out.clear();
        ground_inputs(&x[..1], None, &mut out);
        assert!(out[0] == 10.0 && out[1] < 1e-30, "{out:?}");
    }
}
