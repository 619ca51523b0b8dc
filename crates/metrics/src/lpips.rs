//! LPIPS v0.1 with the AlexNet backbone (Zhang et al. 2018), on candle, CPU.
//!
//! The distance is computed as the `lpips` package defines it for `net='alex'`, v0.1: inputs in
//! `[-1, 1]` go through the fixed scaling layer and AlexNet's five conv + ReLU stages; each
//! stage's features are unit-normalised over channels (`x / (|x| + 1e-10)`), the squared
//! difference is weighted per channel by the learned linear head (a 1x1 convolution without
//! bias), averaged over the image, and the five stage values are summed.
//!
//! The weights (`assets/lpips_alex_v0.1.safetensors`, BSD licences in
//! `assets/LICENSE-lpips-weights.md`) are compiled into the crate, so no file or network access
//! is needed; [`Lpips::from_file`] loads another copy.
//!
//! ```
//! use metrics::lpips::Lpips;
//! let lpips = Lpips::new()?;
//! let (w, h) = (64, 64);
//! let img: Vec<f32> = (0..w * h * 3).map(|k| (k % 7) as f32 / 7.0).collect();
//! assert!(lpips.distance(&img, &img, w, h)?.abs() < 1e-6);
//! # Ok::<(), metrics::lpips::LpipsError>(())
//! ```

use std::collections::HashMap;
use std::path::Path;

use candle_core::{DType, Device, Tensor};

use crate::error::MetricsError;

/// The LPIPS v0.1 AlexNet weights, embedded.
const WEIGHTS: &[u8] = include_bytes!("../assets/lpips_alex_v0.1.safetensors");

/// Normalisation epsilon of the feature unit-normalisation, as in the `lpips` package.
const EPS: f64 = 1e-10;

/// Smallest image side AlexNet's stride-4 convolution and two 3x3 stride-2 poolings accept.
pub const MIN_SIDE: usize = 31;

/// Errors of the LPIPS metric.
#[derive(Debug, thiserror::Error)]
pub enum LpipsError {
    /// Bad image buffers or sizes.
    #[error(transparent)]
    Input(#[from] MetricsError),
    /// The weight file lacks a tensor or has a wrong shape.
    #[error("LPIPS weights: {0}")]
    Weights(String),
    /// A candle operation failed.
    #[error("candle: {0}")]
    Candle(candle_core::Error),
}

// The wrapped error is part of the message, not its source: a report printing the chain of
// causes would otherwise repeat its text.
impl From<candle_core::Error> for LpipsError {
    fn from(e: candle_core::Error) -> Self {
        LpipsError::Candle(e)
    }
}

/// One AlexNet convolution stage.
#[derive(Debug, Clone)]
struct Stage {
    weight: Tensor,
    bias: Tensor,
    stride: usize,
    padding: usize,
    /// Whether a 3x3 stride-2 max-pool precedes the convolution.
    pool_before: bool,
}

/// The LPIPS v0.1 (AlexNet) network, ready to compare images.
#[derive(Debug, Clone)]
pub struct Lpips {
    shift: Tensor,
    scale: Tensor,
    stages: Vec<Stage>,
    heads: Vec<Tensor>,
    device: Device,
}

impl Lpips {
    /// The network with the embedded v0.1 weights, on the CPU.
    ///
    /// # Errors
    /// Only if the embedded file were malformed.
    pub fn new() -> Result<Self, LpipsError> {
        let device = Device::Cpu;
        let tensors = candle_core::safetensors::load_buffer(WEIGHTS, &device)?;
        Self::from_tensors(tensors, device)
    }

    /// The network with weights from a safetensors file using the same tensor names as the
    /// embedded one (`net.slice1.0.weight`, …, `lin4.model.1.weight`, `scaling_layer.shift`).
    ///
    /// # Errors
    /// Unreadable file, missing tensors or wrong shapes.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Self, LpipsError> {
        let device = Device::Cpu;
        let tensors = candle_core::safetensors::load(path, &device)?;
        Self::from_tensors(tensors, device)
    }

    fn from_tensors(mut t: HashMap<String, Tensor>, device: Device) -> Result<Self, LpipsError> {
        let mut take = |name: &str, dims: &[usize]| -> Result<Tensor, LpipsError> {
            let x = t
                .remove(name)
                .ok_or_else(|| LpipsError::Weights(format!("missing tensor {name}")))?;
            if x.dims() != dims {
                return Err(LpipsError::Weights(format!(
                    "{name} has shape {:?}, expected {dims:?}",
                    x.dims()
                )));
            }
            Ok(x.to_dtype(DType::F32)?)
        };
        // (weight name, out, in, kernel, stride, padding, pool before): AlexNet's features.
        let layout = [
            ("net.slice1.0", 64, 3, 11, 4, 2, false),
            ("net.slice2.3", 192, 64, 5, 1, 2, true),
            ("net.slice3.6", 384, 192, 3, 1, 1, true),
            ("net.slice4.8", 256, 384, 3, 1, 1, false),
            ("net.slice5.10", 256, 256, 3, 1, 1, false),
        ];
        let mut stages = Vec::with_capacity(5);
        let mut heads = Vec::with_capacity(5);
        for (k, (name, out, inp, ks, stride, padding, pool_before)) in
            layout.into_iter().enumerate()
        {
            stages.push(Stage {
                weight: take(&format!("{name}.weight"), &[out, inp, ks, ks])?,
                bias: take(&format!("{name}.bias"), &[out])?.reshape((1, out, 1, 1))?,
                stride,
                padding,
                pool_before,
            });
            heads.push(take(&format!("lin{k}.model.1.weight"), &[1, out, 1, 1])?);
        }
        Ok(Self {
            shift: take("scaling_layer.shift", &[1, 3, 1, 1])?,
            scale: take("scaling_layer.scale", &[1, 3, 1, 1])?,
            stages,
            heads,
            device,
        })
    }

    /// LPIPS distance between two RGB images of `width x height`, row-major and
    /// channel-interleaved (`[y][x][rgb]`) with values in `[0, 1]` (mapped to `[-1, 1]` as the
    /// `lpips` package's `normalize=True` does). 0 for identical images; larger is more
    /// different.
    ///
    /// # Errors
    /// Buffers not of `width * height * 3` values, non-finite values, or a side shorter than
    /// [`MIN_SIDE`].
    pub fn distance(
        &self,
        a: &[f32],
        b: &[f32],
        width: usize,
        height: usize,
    ) -> Result<f64, LpipsError> {
        let x = self.to_input(a, width, height, "first image")?;
        let y = self.to_input(b, width, height, "second image")?;
        let both = Tensor::cat(&[&x, &y], 0)?;
        let d = self.forward_pairs(&both)?;
        Ok(f64::from(d.to_vec1::<f32>()?[0]))
    }

    /// `[1, 3, h, w]` tensor in `[-1, 1]` from an interleaved `[0, 1]` RGB buffer.
    fn to_input(
        &self,
        img: &[f32],
        w: usize,
        h: usize,
        what: &'static str,
    ) -> Result<Tensor, LpipsError> {
        let n = crate::image::check_dims(w, h)?;
        crate::image::check_len(img.len(), n * 3, what)?;
        if w < MIN_SIDE || h < MIN_SIDE {
            return Err(MetricsError::InvalidImage(format!(
                "LPIPS needs images of at least {MIN_SIDE} x {MIN_SIDE} px, got {w} x {h}"
            ))
            .into());
        }
        if img.iter().any(|v| !v.is_finite()) {
            return Err(
                MetricsError::InvalidImage(format!("non-finite value in the {what}")).into(),
            );
        }
        let t = Tensor::from_slice(img, (1, h, w, 3), &self.device)?.permute((0, 3, 1, 2))?;
        Ok(((t * 2.0)? - 1.0)?.contiguous()?)
    }

    /// Distances for a batch `[2, 3, h, w]` holding the two images of one pair.
    fn forward_pairs(&self, x: &Tensor) -> Result<Tensor, LpipsError> {
        let mut h = x.broadcast_sub(&self.shift)?.broadcast_div(&self.scale)?;
        let mut total: Option<Tensor> = None;
        for (stage, head) in self.stages.iter().zip(&self.heads) {
            if stage.pool_before {
                h = h.max_pool2d_with_stride(3, 2)?;
            }
            h = h
                .conv2d(&stage.weight, stage.padding, stage.stride, 1, 1)?
                .broadcast_add(&stage.bias)?
                .relu()?;
            let norm = (h.sqr()?.sum_keepdim(1)?.sqrt()? + EPS)?;
            let unit = h.broadcast_div(&norm)?;
            let diff = (unit.narrow(0, 0, 1)? - unit.narrow(0, 1, 1)?)?.sqr()?;
            // 1x1 convolution without bias = per-channel weights summed over channels.
            let weighted = diff.broadcast_mul(head)?.sum_keepdim(1)?;
            let layer = weighted.mean_keepdim(2)?.mean_keepdim(3)?.flatten_all()?;
            total = Some(match total {
                Some(t) => (t + layer)?,
                None => layer,
            });
        }
        total.ok_or_else(|| LpipsError::Weights("no stages".into()))
    }
}
