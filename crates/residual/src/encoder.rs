//! Per-particle feature encoders: the serialized point transformer (PTv3-style U-Net) and the
//! PointNet++-style ablation. Both map `(N, inputs)` features to `(N, feature_dim)`.

use candle_core::Tensor;
use candle_nn::{Linear, VarBuilder};

use crate::nn::{Mlp, Norm, Pass, affine, apply, linear, softmax};
use crate::serialize::{CURVES, Order, Pooling, Structure};
use crate::{EncoderKind, ModelConfig, Result};

/// One transformer block: conditional positional encoding along the curve, patch attention,
/// feed-forward; pre-norm residual form as in PTv3.
#[derive(Debug)]
struct Block {
    cpe: Linear,
    cpe_norm: Norm,
    n1: Norm,
    qkv: Linear,
    proj: Linear,
    n2: Norm,
    mlp: Mlp,
    heads: usize,
}

impl Block {
    fn new(c: usize, head_dim: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Block {
            cpe: linear(3 * c, c, vb.pp("cpe"))?,
            cpe_norm: Norm::new(c, vb.pp("cpe_norm"))?,
            n1: Norm::new(c, vb.pp("norm1"))?,
            qkv: linear(c, 3 * c, vb.pp("qkv"))?,
            proj: linear(c, c, vb.pp("proj"))?,
            n2: Norm::new(c, vb.pp("norm2"))?,
            mlp: Mlp::new(c, 2 * c, c, vb.pp("mlp"))?,
            heads: c / head_dim,
        })
    }

    fn forward(&self, h: &Tensor, order: &Order, pass: Pass) -> Result<Tensor> {
        let c = h.dim(1)?;
        // Conditional positional encoding: a kernel-3 convolution along the curve, which keeps
        // spatial neighbours together (PTv3 uses a sparse 3-D convolution here).
        let nb = Tensor::cat(
            &[
                &h.index_select(&order.prev, 0)?,
                h,
                &h.index_select(&order.next, 0)?,
            ],
            1,
        )?;
        let h = (h + self
            .cpe_norm
            .forward(&affine(&self.cpe, &nb, pass, false)?, pass)?)?;
        let x = self.n1.forward(&h, pass)?;
        if pass == Pass::Infer {
            // One fused pass from the projections to each point's output (`kernels/attention.rs`).
            let o = crate::kernels::patch_attention(
                &affine(&self.qkv, &x, pass, false)?,
                &order.gather,
                order.mask.as_ref(),
                self.heads,
                order.patch,
            )?;
            let h = (h + affine(&self.proj, &o, pass, false)?)?;
            return Ok((&h + self.mlp.forward(&self.n2.forward(&h, pass)?, pass)?)?);
        }
        let qkv = apply(&self.qkv, &x)?.index_select(&order.gather, 0)?;
        let (np, p, hd) = (order.patches, order.patch, c / self.heads);
        let qkv = qkv
            .reshape((np, p, 3, self.heads, hd))?
            .permute((2, 0, 3, 1, 4))?;
        let scale = 1.0 / (hd as f64).sqrt();
        let q = (qkv.get(0)?.contiguous()? * scale)?;
        let k = qkv.get(1)?.contiguous()?;
        let v = qkv.get(2)?.contiguous()?;
        let mut s = q.matmul(&k.t()?)?;
        if let Some(mask) = &order.mask {
            s = s.broadcast_add(mask)?;
        }
        let a = softmax(&s, pass)?;
        let o = a.matmul(&v)?;
        let o = o.permute((0, 2, 1, 3))?.reshape((np * p, c))?;
        let o = o.index_select(&order.inverse, 0)?;
        let h = (h + apply(&self.proj, &o)?)?;
        Ok((&h + self.mlp.forward(&self.n2.forward(&h, pass)?, pass)?)?)
    }
}

/// Mean of the features of each pooling cluster.
fn pool_mean(x: &Tensor, pool: &Pooling) -> Result<Tensor> {
    let zeros = Tensor::zeros((pool.clusters, x.dim(1)?), x.dtype(), x.device())?;
    Ok(zeros
        .index_add(&pool.cluster, x, 0)?
        .broadcast_mul(&pool.inv_count)?)
}

/// Pooling (down) and unpooling (up) projections between two stages.
#[derive(Debug)]
struct Down {
    proj: Linear,
    norm: Norm,
}

#[derive(Debug)]
struct Up {
    coarse: Linear,
    skip: Linear,
    norm: Norm,
}

impl Up {
    fn forward(
        &self,
        coarse: &Tensor,
        skip: &Tensor,
        pool: &Pooling,
        pass: Pass,
    ) -> Result<Tensor> {
        let up = affine(&self.coarse, coarse, pass, false)?.index_select(&pool.cluster, 0)?;
        let h = (up + affine(&self.skip, skip, pass, false)?)?;
        Ok(self.norm.forward(&h, pass)?.relu()?)
    }
}

/// The stage-specific part of each encoder family.
#[derive(Debug)]
enum Stages {
    /// Transformer blocks per encoder / decoder stage.
    Ptv3 {
        enc: Vec<Vec<Block>>,
        dec: Vec<Vec<Block>>,
    },
    /// Shared per-point MLPs applied before pooling (on features and offsets to the cluster
    /// centre) and after unpooling.
    Pointnet { sa: Vec<Mlp>, fp: Vec<Mlp> },
}

/// A point encoder (see the module docs).
#[derive(Debug)]
pub(crate) struct Encoder {
    embed: Linear,
    embed_norm: Norm,
    down: Vec<Down>,
    up: Vec<Up>,
    stages: Stages,
}

impl Encoder {
    pub fn new(inputs: usize, cfg: &ModelConfig, vb: VarBuilder<'_>) -> Result<Self> {
        let ch = &cfg.enc_channels;
        let s = ch.len();
        let offset = usize::from(cfg.encoder == EncoderKind::Pointnet) * 3;
        let mut down = Vec::new();
        for k in 1..s {
            down.push(Down {
                proj: linear(ch[k - 1] + offset, ch[k], vb.pp(format!("down{k}.proj")))?,
                norm: Norm::new(ch[k], vb.pp(format!("down{k}.norm")))?,
            });
        }
        // Decoder stage j works at level s - 2 - j, merging the coarser result with the skip.
        let mut up = Vec::new();
        for j in 0..s.saturating_sub(1) {
            let level = s - 2 - j;
            let coarse = if j == 0 {
                ch[s - 1]
            } else {
                cfg.dec_channels[j - 1]
            };
            let out = cfg.dec_channels[j];
            up.push(Up {
                coarse: linear(coarse, out, vb.pp(format!("up{level}.coarse")))?,
                skip: linear(ch[level], out, vb.pp(format!("up{level}.skip")))?,
                norm: Norm::new(out, vb.pp(format!("up{level}.norm")))?,
            });
        }
        let stages = match cfg.encoder {
            EncoderKind::Ptv3 => {
                let mut enc = Vec::new();
                for (k, (&c, &depth)) in ch.iter().zip(&cfg.enc_depths).enumerate() {
                    let blocks = (0..depth)
                        .map(|b| Block::new(c, cfg.head_dim, vb.pp(format!("enc{k}.block{b}"))))
                        .collect::<Result<Vec<_>>>()?;
                    enc.push(blocks);
                }
                let mut dec = Vec::new();
                for j in 0..s.saturating_sub(1) {
                    let c = cfg.dec_channels[j];
                    let blocks = (0..cfg.dec_depths[j])
                        .map(|b| Block::new(c, cfg.head_dim, vb.pp(format!("dec{j}.block{b}"))))
                        .collect::<Result<Vec<_>>>()?;
                    dec.push(blocks);
                }
                Stages::Ptv3 { enc, dec }
            }
            EncoderKind::Pointnet => {
                let sa = (0..s)
                    .map(|k| Mlp::new(ch[k], ch[k], ch[k], vb.pp(format!("sa{k}"))))
                    .collect::<Result<Vec<_>>>()?;
                let fp = (0..s.saturating_sub(1))
                    .map(|j| {
                        let c = cfg.dec_channels[j];
                        Mlp::new(c, c, c, vb.pp(format!("fp{j}")))
                    })
                    .collect::<Result<Vec<_>>>()?;
                Stages::Pointnet { sa, fp }
            }
        };
        Ok(Encoder {
            embed: linear(inputs, ch[0], vb.pp("embed"))?,
            embed_norm: Norm::new(ch[0], vb.pp("embed_norm"))?,
            down,
            up,
            stages,
        })
    }

    /// Features `(N, inputs)` → `(N, feature_dim)`. `curves[b % 4]` is the curve block `b`
    /// attends along (shuffled per sample during training).
    pub fn forward(
        &self,
        x: &Tensor,
        st: &Structure,
        curves: [usize; CURVES],
        pass: Pass,
    ) -> Result<Tensor> {
        let mut h = self
            .embed_norm
            .forward(&affine(&self.embed, x, pass, false)?, pass)?
            .relu()?;
        let mut skips = Vec::new();
        let mut block = 0usize;
        let mut curve = || {
            block += 1;
            curves[(block - 1) % CURVES]
        };
        let s = st.levels.len();
        for k in 0..s {
            if k > 0 {
                let pool = &st.pools[k - 1];
                let input = match self.stages {
                    Stages::Ptv3 { .. } => h.clone(),
                    Stages::Pointnet { .. } => {
                        let centre = st.levels[k].pos.index_select(&pool.cluster, 0)?;
                        let offset = (&st.levels[k - 1].pos - centre)?;
                        Tensor::cat(&[&h, &offset], 1)?
                    }
                };
                let d = &self.down[k - 1];
                h = d
                    .norm
                    .forward(
                        &pool_mean(&affine(&d.proj, &input, pass, false)?, pool)?,
                        pass,
                    )?
                    .relu()?;
            }
            h = match &self.stages {
                Stages::Ptv3 { enc, .. } => {
                    let mut h = h;
                    for b in &enc[k] {
                        h = b.forward(&h, &st.levels[k].orders[curve()], pass)?;
                    }
                    h
                }
                Stages::Pointnet { sa, .. } => (&h + sa[k].forward(&h, pass)?)?.relu()?,
            };
            skips.push(h.clone());
        }
        for (j, u) in self.up.iter().enumerate() {
            let level = s - 2 - j;
            h = u.forward(&h, &skips[level], &st.pools[level], pass)?;
            h = match &self.stages {
                Stages::Ptv3 { dec, .. } => {
                    let mut h = h;
                    for b in &dec[j] {
                        h = b.forward(&h, &st.levels[level].orders[curve()], pass)?;
                    }
                    h
                }
                Stages::Pointnet { fp, .. } => (&h + fp[j].forward(&h, pass)?)?.relu()?,
            };
        }
        Ok(h)
    }
}
