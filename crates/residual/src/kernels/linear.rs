//! Linear layers for inference: `y = x Wᵀ + b`, optionally followed by ReLU, in one pass.
//!
//! candle's `Linear` is a general matrix product (which packs both operands and zero-fills its
//! output on every call) followed by a separate pass that adds the bias, and for ReLU a third.
//! The network's layers are narrow (16 to 96 channels) and tall (one row per point of a group),
//! which a register-blocked loop handles without any of that: four rows times sixteen outputs
//! accumulate in eight vector registers while the layer's (transposed) weights stream by.

use candle_core::{CpuStorage, CustomOp3, Layout, Shape, Tensor};

use super::{Kernel, f32_slice, vecs, vecs_mut, vectorized};
use crate::Result;

/// Rows per block.
const ROWS: usize = 4;

/// `x Wᵀ + b` for `x (n, in)`, `W (out, in)`, `b (out)`; with `relu`, `max(·, 0)` after.
pub(crate) fn linear(x: &Tensor, w: &Tensor, b: &Tensor, relu: bool) -> Result<Tensor> {
    Ok(x.contiguous()?
        .apply_op3_no_bwd(&w.contiguous()?, &b.contiguous()?, &LinearOp { relu })?)
}

struct LinearOp {
    relu: bool,
}

impl CustomOp3 for LinearOp {
    fn name(&self) -> &'static str {
        "linear-rows"
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
        let w = f32_slice(s2, l2, "weight")?;
        let b = f32_slice(s3, l3, "bias")?;
        let (n, k) = l1.shape().dims2()?;
        let (o, k2) = l2.shape().dims2()?;
        if k != k2 || b.len() != o || k == 0 {
            candle_core::bail!(
                "linear: input {:?}, weight {:?}, bias {}",
                l1.dims(),
                l2.dims(),
                b.len()
            );
        }
        let y = vectorized(Affine {
            x,
            w,
            b,
            k,
            o,
            relu: self.relu,
        });
        Ok((CpuStorage::F32(y), Shape::from((n, o))))
    }
}

#[derive(Clone, Copy)]
struct Affine<'a> {
    x: &'a [f32],
    w: &'a [f32],
    b: &'a [f32],
    k: usize,
    o: usize,
    relu: bool,
}

impl Kernel for Affine<'_> {
    type Output = Vec<f32>;

    #[inline(always)]
    fn run<S: pulp::Simd>(self, simd: S) -> Vec<f32> {
        // Blocks of 16 outputs (two AVX2 vectors), or one vector where that is wider.
        if S::F32_LANES >= 16 {
            self.blocks::<S, 1>(simd)
        } else {
            self.blocks::<S, 2>(simd)
        }
    }
}

impl Affine<'_> {
    /// The layer in blocks of `NV` vectors of outputs.
    #[inline(always)]
    fn blocks<S: pulp::Simd, const NV: usize>(self, simd: S) -> Vec<f32> {
        let Affine {
            x,
            w,
            b,
            k,
            o,
            relu,
        } = self;
        let n = x.len() / k;
        let ob = NV * S::F32_LANES;
        let blocks = o.div_ceil(ob);
        // Weights transposed into blocks of `ob` outputs, `[block][input][output]`, padded
        // with zero outputs; the bias padded alike.
        let mut wt = vec![0f32; blocks * k * ob];
        for (oi, row) in w.chunks_exact(k).enumerate() {
            let block = &mut wt[oi / ob * k * ob..][..k * ob];
            for (ki, w) in row.iter().enumerate() {
                block[ki * ob + oi % ob] = *w;
            }
        }
        let mut bias = vec![0f32; blocks * ob];
        bias[..o].copy_from_slice(b);
        let mut y = vec![0f32; n * o];
        let zero = simd.splat_f32s(0.0);
        let mut buf = vec![0f32; ob];
        let full = n / ROWS * ROWS;
        for r0 in (0..full).step_by(ROWS) {
            let xs = &x[r0 * k..(r0 + ROWS) * k];
            let (x0, rest) = xs.split_at(k);
            let (x1, rest) = rest.split_at(k);
            let (x2, x3) = rest.split_at(k);
            let blocks = wt.chunks_exact(k * ob).zip(bias.chunks_exact(ob));
            for (blk, (wb, bb)) in blocks.enumerate() {
                // Four rows × NV vectors of outputs: the accumulators stay in registers.
                let mut acc = [[zero; NV]; ROWS];
                let inputs = x0.iter().zip(x1).zip(x2).zip(x3);
                for ((((a, b), c), d), wk) in inputs.zip(wb.chunks_exact(ob)) {
                    let wv = vecs::<S>(wk);
                    for (acc, x) in acc.iter_mut().zip([a, b, c, d]) {
                        let xv = simd.splat_f32s(*x);
                        for (a, w) in acc.iter_mut().zip(wv) {
                            *a = simd.mul_add_e_f32s(xv, *w, *a);
                        }
                    }
                }
                let bv = vecs::<S>(bb);
                for (r, acc) in acc.iter().enumerate() {
                    let row = &mut y[(r0 + r) * o..(r0 + r + 1) * o];
                    finish(simd, row, blk * ob, acc, bv, relu, &mut buf);
                }
            }
        }
        for r in full..n {
            let xs = &x[r * k..(r + 1) * k];
            let blocks = wt.chunks_exact(k * ob).zip(bias.chunks_exact(ob));
            for (blk, (wb, bb)) in blocks.enumerate() {
                let mut acc = [zero; NV];
                for (xv, wk) in xs.iter().zip(wb.chunks_exact(ob)) {
                    let xv = simd.splat_f32s(*xv);
                    for (a, w) in acc.iter_mut().zip(vecs::<S>(wk)) {
                        *a = simd.mul_add_e_f32s(xv, *w, *a);
                    }
                }
                let row = &mut y[r * o..(r + 1) * o];
                finish(simd, row, blk * ob, &acc, vecs::<S>(bb), relu, &mut buf);
            }
        }
        y
    }
}

/// Writes one block of outputs of a row, from `first` on: sum plus bias (candle's order),
/// then ReLU; whole vectors where the block fits in the row, through `buf` where it does not.
#[inline(always)]
fn finish<S: pulp::Simd, const NV: usize>(
    simd: S,
    row: &mut [f32],
    first: usize,
    acc: &[S::f32s; NV],
    bias: &[S::f32s],
    relu: bool,
    buf: &mut [f32],
) {
    let zero = simd.splat_f32s(0.0);
    let mut v = [zero; NV];
    for ((v, a), b) in v.iter_mut().zip(acc).zip(bias) {
        *v = simd.add_f32s(*a, *b);
        if relu {
            *v = simd.max_f32s(*v, zero);
        }
    }
    let dst = &mut row[first..];
    if dst.len() >= buf.len() {
        vecs_mut::<S>(&mut dst[..buf.len()]).copy_from_slice(&v);
    } else {
        vecs_mut::<S>(buf).copy_from_slice(&v);
        dst.copy_from_slice(&buf[..dst.len()]);
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Module};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    #[test]
    fn linear_matches_candle_for_every_shape_and_remainder() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let dev = &Device::Cpu;
        let mut random =
            |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0)).collect() };
        // Rows not a multiple of 4, outputs below, at and above one block of 16.
        for (n, k, o) in [
            (1, 3, 3),
            (7, 16, 48),
            (13, 65, 64),
            (10, 32, 17),
            (4, 24, 16),
        ] {
            let x = Tensor::from_vec(random(n * k), (n, k), dev).unwrap();
            let w = Tensor::from_vec(random(o * k), (o, k), dev).unwrap();
            let b = Tensor::from_vec(random(o), o, dev).unwrap();
            let want = candle_nn::Linear::new(w.clone(), Some(b.clone()))
                .forward(&x)
                .unwrap();
            for relu in [false, true] {
                let want = if relu {
                    want.relu().unwrap()
                } else {
                    want.clone()
                };
                let got = linear(&x, &w, &b, relu).unwrap();
                // pulp's scalar fallback (CPUs without AVX2) computes the same.
                let (xs, ws, bs): (Vec<f32>, Vec<f32>, Vec<f32>) = (
                    x.flatten_all().unwrap().to_vec1().unwrap(),
                    w.flatten_all().unwrap().to_vec1().unwrap(),
                    b.to_vec1().unwrap(),
                );
                let kernel = Affine {
                    x: &xs,
                    w: &ws,
                    b: &bs,
                    k,
                    o,
                    relu,
                };
                let scalar = Tensor::from_vec(kernel.run(pulp::Scalar::new()), (n, o), dev);
                for got in [got, scalar.unwrap()] {
                    assert_eq!(got.dims(), &[n, o]);
                    let diff = (got - &want)
                        .unwrap()
                        .abs()
                        .unwrap()
                        .flatten_all()
                        .unwrap()
                        .max(0)
                        .unwrap()
                        .to_scalar::<f32>()
                        .unwrap();
                    assert!(diff < 1e-5, "{n}x{k} -> {o}, relu {relu}: {diff}");
                }
            }
        }
        let x = Tensor::zeros((2, 5), candle_core::DType::F32, dev).unwrap();
        let w = Tensor::zeros((3, 4), candle_core::DType::F32, dev).unwrap();
        let b = Tensor::zeros(3, candle_core::DType::F32, dev).unwrap();
        assert!(linear(&x, &w, &b, false).is_err());
    }
}
