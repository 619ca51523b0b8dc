//! Forward-only CPU kernels for inference (`Pass::Infer`): softmax with the attention mask
//! folded in, and layer normalisation, each one sequential pass over the rows.
//!
//! Why not candle's fused ops: its softmax and LayerNorm split rows over rayon, which only adds
//! overhead when the caller already runs one network per rayon thread (batched prediction), and
//! the separate mask addition on large score tensors goes to candle's spinning thread pool
//! (tensors of ≥ 64 Ki elements), which was measured to cost more than it saves there.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};

use crate::Result;

fn f32_slice<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: expected f32");
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected a contiguous tensor"),
    }
}

/// Softmax over the last dimension of `(patches, heads, queries, keys)` scores after adding a
/// `(patches, 1, 1, keys)` mask.
struct MaskedSoftmax;

impl CustomOp2 for MaskedSoftmax {
    fn name(&self) -> &'static str {
        "masked-softmax"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let scores = f32_slice(s1, l1, "scores")?;
        let mask = f32_slice(s2, l2, "mask")?;
        let dims = l1.shape().dims();
        let (Some(&keys), true) = (dims.last(), dims.len() == 4) else {
            candle_core::bail!("masked softmax: scores {dims:?} are not 4-d");
        };
        let per_patch = dims[1] * dims[2] * keys;
        if mask.len() != dims[0] * keys {
            candle_core::bail!("masked softmax: mask {:?} for scores {dims:?}", l2.dims());
        }
        let mut out = vec![0f32; scores.len()];
        for (p, (src, dst)) in scores
            .chunks(per_patch)
            .zip(out.chunks_mut(per_patch))
            .enumerate()
        {
            let m = &mask[p * keys..(p + 1) * keys];
            for (s, d) in src.chunks(keys).zip(dst.chunks_mut(keys)) {
                for ((d, s), m) in d.iter_mut().zip(s).zip(m) {
                    *d = s + m;
                }
                softmax_row(d);
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// Sum of `f(v)` over `x` with eight independent accumulators, so the compiler can use vector
/// adds (the order of additions differs from a left-to-right sum only by float rounding).
fn sum8(x: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    let mut acc = [0f32; 8];
    let mut chunks = x.chunks_exact(8);
    for c in &mut chunks {
        for (a, v) in acc.iter_mut().zip(c) {
            *a += f(*v);
        }
    }
    acc.iter().sum::<f32>() + chunks.remainder().iter().map(|v| f(*v)).sum::<f32>()
}

/// In-place softmax of one row (max subtracted first, as every stable softmax does).
fn softmax_row(row: &mut [f32]) {
    let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    for v in row.iter_mut() {
        *v = (*v - max).exp();
    }
    let inv = 1.0 / sum8(row, |v| v);
    for v in row.iter_mut() {
        *v *= inv;
    }
}

/// Row-wise softmax over the last dimension.
struct Softmax;

impl CustomOp1 for Softmax {
    fn name(&self) -> &'static str {
        "softmax-rows"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let mut out = f32_slice(s, l, "scores")?.to_vec();
        let keys = l.shape().dims().last().copied().unwrap_or(1).max(1);
        for row in out.chunks_mut(keys) {
            softmax_row(row);
        }
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }
}

/// Softmax over the last dimension of `x`, after adding `mask` when given (see
/// [`MaskedSoftmax`] for the shapes); no gradient.
pub(crate) fn softmax(x: &Tensor, mask: Option<&Tensor>) -> Result<Tensor> {
    let x = x.contiguous()?;
    match mask {
        Some(m) => Ok(x.apply_op2_no_bwd(&m.contiguous()?, &MaskedSoftmax)?),
        None => Ok(x.apply_op1_no_bwd(&Softmax)?),
    }
}

/// Layer normalisation over the last dimension (mean and variance in two passes, like the
/// differentiable version), times `gamma` plus `beta`.
struct LayerNorm {
    eps: f32,
}

impl CustomOp3 for LayerNorm {
    fn name(&self) -> &'static str {
        "layer-norm-rows"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "input")?;
        let gamma = f32_slice(s2, l2, "gamma")?;
        let beta = f32_slice(s3, l3, "beta")?;
        let c = l1.shape().dims().last().copied().unwrap_or(0);
        if c == 0 || gamma.len() != c || beta.len() != c {
            candle_core::bail!(
                "layer norm: input {:?}, gamma {}, beta {}",
                l1.dims(),
                gamma.len(),
                beta.len()
            );
        }
        let mut out = vec![0f32; x.len()];
        let n = c as f32;
        for (src, dst) in x.chunks(c).zip(out.chunks_mut(c)) {
            let mean = sum8(src, |v| v) / n;
            let var = sum8(src, |v| (v - mean) * (v - mean)) / n;
            let inv = 1.0 / (var + self.eps).sqrt();
            for (((d, s), g), b) in dst.iter_mut().zip(src).zip(gamma).zip(beta) {
                *d = (s - mean) * inv * g + b;
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// Layer normalisation of the rows of `x` with `gamma`, `beta`; no gradient.
pub(crate) fn layer_norm(x: &Tensor, gamma: &Tensor, beta: &Tensor, eps: f32) -> Result<Tensor> {
    Ok(x.contiguous()?
        .apply_op3_no_bwd(gamma, beta, &LayerNorm { eps })?)
}

#[cfg(test)]
mod tests {
    use candle_core::{D, Device};

    use super::*;

    fn close(a: &Tensor, b: &Tensor) -> f32 {
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(D::Minus1)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    #[test]
    fn kernels_match_the_differentiable_ops() {
        let dev = Device::Cpu;
        let s = Tensor::randn(0f32, 3.0, (3, 2, 5, 7), &dev).unwrap();
        let m: Vec<f32> = (0..3 * 7)
            .map(|k| if k % 7 >= 5 && k / 7 == 2 { -1e9 } else { 0.0 })
            .collect();
        let m = Tensor::from_vec(m, (3, 1, 1, 7), &dev).unwrap();
        let want = candle_nn::ops::softmax(&s.broadcast_add(&m).unwrap(), D::Minus1).unwrap();
        assert!(close(&softmax(&s, Some(&m)).unwrap(), &want) < 1e-6);
        // The masked keys of the last patch get no weight.
        let got = softmax(&s, Some(&m)).unwrap().flatten_all().unwrap();
        let got = got.to_vec1::<f32>().unwrap();
        for row in got[2 * 2 * 5 * 7..].chunks(7) {
            assert_eq!(&row[5..], &[0.0, 0.0]);
            assert!((row.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        }
        let plain = candle_nn::ops::softmax(&s, D::Minus1).unwrap();
        assert!(close(&softmax(&s, None).unwrap(), &plain) < 1e-6);
        let x = Tensor::randn(0.5f32, 2.0, (11, 16), &dev).unwrap();
        let g = Tensor::randn(1f32, 0.1, 16, &dev).unwrap();
        let b = Tensor::randn(0f32, 0.1, 16, &dev).unwrap();
        let want = candle_nn::ops::layer_norm_slow(&x, &g, &b, 1e-5).unwrap();
        assert!(close(&layer_norm(&x, &g, &b, 1e-5).unwrap(), &want) < 1e-5);
        // Bad shapes are errors.
        assert!(layer_norm(&x, &b.narrow(0, 0, 8).unwrap(), &b, 1e-5).is_err());
        assert!(softmax(&s, Some(&m.narrow(0, 0, 2).unwrap())).is_err());
    }
}
