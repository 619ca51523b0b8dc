//! Forward-only CPU kernels for inference (`Pass::Infer`): linear layers ([`linear`]), attention
//! inside the serialization patches ([`patch_attention`]), the temporal aggregator
//! ([`TemporalParams`]), softmax and layer normalisation, each one fused pass.
//!
//! Why not candle's fused ops: its softmax and LayerNorm split rows over rayon, which only adds
//! overhead when the caller already runs one network per rayon thread (batched prediction), and
//! element-wise ops on large score tensors go to candle's spinning thread pool (tensors of
//! ≥ 64 Ki elements), which was measured to cost more than it saves there.
//!
//! The kernels run through [`vectorized`]: compiled for the best instruction set the CPU has
//! (AVX2 + FMA where available, chosen at run time; SSE2 otherwise), so the plain loops below
//! become vector code. The choice depends on the CPU only, so results do not depend on the
//! number of threads.

mod attention;
mod linear;
mod temporal;

pub(crate) use attention::patch_attention;
pub(crate) use linear::linear;
pub(crate) use temporal::{Dense, LayerParams, Mix, NormParams, TemporalParams};

use candle_core::{CpuStorage, CustomOp1, CustomOp3, Layout, Shape, Tensor};

use crate::Result;

pub(crate) fn f32_slice<'a>(
    s: &'a CpuStorage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: expected f32");
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected a contiguous tensor"),
    }
}

/// A kernel for [`vectorized`]: its arguments and, in `run`, its body.
trait Kernel {
    type Output;
    /// The body, with `simd`'s vector operations for the hot loops. Must be
    /// `#[inline(always)]`, like everything it calls: only code inlined into the dispatched
    /// function is compiled for the detected instruction set (a closure would not be inlined,
    /// and its `mul_add`s would become calls to a software `fmaf`).
    fn run<S: pulp::Simd>(self, simd: S) -> Self::Output;
}

/// Runs `kernel` compiled for the best SIMD instruction set this CPU supports (runtime
/// detection by `pulp`).
fn vectorized<K: Kernel>(kernel: K) -> K::Output {
    pulp::Arch::new().dispatch(Vectorized(kernel))
}

struct Vectorized<K>(K);

impl<K: Kernel> pulp::WithSimd for Vectorized<K> {
    type Output = K::Output;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> K::Output {
        self.0.run(simd)
    }
}

/// `a · b + c`, fused (one rounding) where the instruction set has fused multiply-adds: every
/// vector set pulp dispatches to does; its scalar fallback (e.g. x86 without AVX2) may not, and
/// there `mul_add` would be a slow library call.
#[inline(always)]
fn fma<S: pulp::Simd>(a: f32, b: f32, c: f32) -> f32 {
    if S::IS_SCALAR {
        a * b + c
    } else {
        a.mul_add(b, c)
    }
}

/// `S`'s vectors covering `x` (whose length is a multiple of the vector width).
#[inline(always)]
fn vecs<S: pulp::Simd>(x: &[f32]) -> &[S::f32s] {
    S::as_simd_f32s(x).0
}

/// Mutable [`vecs`].
#[inline(always)]
fn vecs_mut<S: pulp::Simd>(x: &mut [f32]) -> &mut [S::f32s] {
    S::as_mut_simd_f32s(x).0
}

const LOG2E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_145_75; // 0x3F317200: 15 significant bits
const LN2_LO: f32 = 1.428_606_8e-6; // ln 2 − LN2_HI
/// Adding 1.5 · 2^23 rounds to an integer, which then sits in the low mantissa bits.
const SHIFT: f32 = 12_582_912.0;
/// Taylor coefficients of `e^r`.
const EXP_POLY: [f32; 8] = [
    1.0,
    1.0,
    0.5,
    1.0 / 6.0,
    1.0 / 24.0,
    1.0 / 120.0,
    1.0 / 720.0,
    1.0 / 5040.0,
];
const EXP_MIN: f32 = -86.0;
const EXP_MAX: f32 = 88.0;

/// `e^x` to about 2 ulp, branch-free so that loops over it vectorise (glibc's `expf` is a
/// function call per element and was the largest single cost of the attention softmax).
///
/// Range reduction `x = n ln 2 + r`, |r| ≤ ln 2 / 2 (Cody–Waite: `n · LN2_HI` is exact), degree-7
/// Taylor polynomial of `e^r` (truncation error below 1e-8 relative), and `2^n` added to the
/// exponent bits. Below −86 it returns 0 (the true value is < 5e-38); above 88 it returns
/// `e^88`; NaN stays NaN.
#[inline(always)]
pub(crate) fn exp(x: f32) -> f32 {
    let xc = x.clamp(EXP_MIN, EXP_MAX);
    let t = xc * LOG2E + SHIFT;
    let n = t - SHIFT;
    let r = (xc - n * LN2_HI) - n * LN2_LO;
    let mut p = EXP_POLY[7];
    for c in EXP_POLY[..7].iter().rev() {
        p = p * r + c;
    }
    let two_n = t.to_bits().wrapping_sub(SHIFT.to_bits()) << 23;
    let y = f32::from_bits(p.to_bits().wrapping_add(two_n));
    if x < EXP_MIN {
        0.0
    } else if x.is_nan() {
        x
    } else {
        y
    }
}

/// [`exp`] on a vector, lane by lane.
#[inline(always)]
pub(crate) fn exp_v<S: pulp::Simd>(simd: S, x: S::f32s) -> S::f32s {
    let f = |v: f32| simd.splat_f32s(v);
    // As `exp`, with fused multiply-adds where the instruction set has them (rounding
    // differs in the last bit).
    let xc = simd.min_f32s(simd.max_f32s(x, f(EXP_MIN)), f(EXP_MAX));
    let t = simd.mul_add_e_f32s(xc, f(LOG2E), f(SHIFT));
    let n = simd.sub_f32s(t, f(SHIFT));
    let r = simd.mul_add_e_f32s(n, f(-LN2_HI), xc);
    let r = simd.mul_add_e_f32s(n, f(-LN2_LO), r);
    let mut p = f(EXP_POLY[7]);
    for c in EXP_POLY[..7].iter().rev() {
        p = simd.mul_add_e_f32s(p, r, f(*c));
    }
    let bits = simd.transmute_u32s_f32s(t);
    let n_int = simd.sub_u32s(bits, simd.splat_u32s(SHIFT.to_bits()));
    let two_n = simd.wrapping_dyn_shl_u32s(n_int, simd.splat_u32s(23));
    let p_bits = simd.transmute_u32s_f32s(p);
    let y = simd.transmute_f32s_u32s(simd.add_u32s(p_bits, two_n));
    let y = simd.select_f32s(simd.less_than_f32s(x, f(EXP_MIN)), f(0.0), y);
    // NaN stays NaN (x ≠ x only for NaN).
    simd.select_f32s(simd.equal_f32s(x, x), y, x)
}

/// Replaces `row` by `e^(v − max)` and returns the sum: a softmax before its division.
#[inline(always)]
pub(crate) fn exp_shifted_row<S: pulp::Simd>(simd: S, row: &mut [f32]) -> f32 {
    let (head, tail) = S::as_mut_simd_f32s(row);
    let mut mv = simd.splat_f32s(f32::NEG_INFINITY);
    for v in head.iter() {
        mv = simd.max_f32s(mv, *v);
    }
    let max = tail
        .iter()
        .fold(simd.reduce_max_f32s(mv), |m, v| if *v > m { *v } else { m });
    let (m, mut acc) = (simd.splat_f32s(max), simd.splat_f32s(0.0));
    for v in head.iter_mut() {
        *v = exp_v(simd, simd.sub_f32s(*v, m));
        acc = simd.add_f32s(acc, *v);
    }
    let mut sum = simd.reduce_sum_f32s(acc);
    for v in tail.iter_mut() {
        *v = exp(*v - max);
        sum += *v;
    }
    sum
}

/// Sum of `f(v)` over `x` with eight independent accumulators, so the compiler can use vector
/// adds (the order of additions differs from a left-to-right sum only by float rounding).
#[inline(always)]
fn sum8(x: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    let mut acc = [0f32; 8];
    let mut chunks = x.chunks_exact(8);
    for c in &mut chunks {
        for (a, v) in acc.iter_mut().zip(c) {
            *a += f(*v);
        }
    }
    // A tree, not a chain of seven dependent additions (rows are short: 16 to 64 values).
    let tree = ((acc[0] + acc[4]) + (acc[2] + acc[6])) + ((acc[1] + acc[5]) + (acc[3] + acc[7]));
    tree + chunks.remainder().iter().map(|v| f(*v)).sum::<f32>()
}

/// In-place softmax of one row (max subtracted first, as every stable softmax does).
#[inline(always)]
fn softmax_row<S: pulp::Simd>(simd: S, row: &mut [f32]) {
    let inv = 1.0 / exp_shifted_row(simd, row);
    for v in row.iter_mut() {
        *v *= inv;
    }
}

/// Row-wise softmax over the last dimension.
struct Softmax;

struct SoftmaxRows<'a>(&'a mut [f32], usize);

impl Kernel for SoftmaxRows<'_> {
    type Output = ();

    #[inline(always)]
    fn run<S: pulp::Simd>(self, simd: S) {
        for row in self.0.chunks_mut(self.1) {
            softmax_row(simd, row);
        }
    }
}

impl CustomOp1 for Softmax {
    fn name(&self) -> &'static str {
        "softmax-rows"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let mut out = f32_slice(s, l, "scores")?.to_vec();
        let keys = l.shape().dims().last().copied().unwrap_or(1).max(1);
        vectorized(SoftmaxRows(&mut out, keys));
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }
}

/// Softmax over the last dimension of `x`; no gradient.
pub(crate) fn softmax(x: &Tensor) -> Result<Tensor> {
    Ok(x.contiguous()?.apply_op1_no_bwd(&Softmax)?)
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
        vectorized(NormRows {
            x,
            gamma,
            beta,
            eps: self.eps,
            out: &mut out,
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

struct NormRows<'a> {
    x: &'a [f32],
    gamma: &'a [f32],
    beta: &'a [f32],
    eps: f32,
    out: &'a mut [f32],
}

impl Kernel for NormRows<'_> {
    type Output = ();

    #[inline(always)]
    fn run<S: pulp::Simd>(self, _: S) {
        let c = self.gamma.len();
        let inv_n = 1.0 / c as f32;
        let rows = self.x.len() / c;
        let (mut mean, mut inv) = (vec![0f32; rows], vec![0f32; rows]);
        for ((src, m), v) in self.x.chunks_exact(c).zip(&mut mean).zip(&mut inv) {
            *m = sum8(src, |v| v) * inv_n;
            *v = sum8(src, |v| (v - *m) * (v - *m)) * inv_n;
        }
        // Square roots and divisions of all rows together: as vector instructions, instead of
        // two long-latency scalar ones per (short) row.
        for v in &mut inv {
            *v = 1.0 / (*v + self.eps).sqrt();
        }
        let rows = self.x.chunks_exact(c).zip(self.out.chunks_exact_mut(c));
        for ((src, dst), (m, inv)) in rows.zip(mean.iter().zip(&inv)) {
            for (((d, s), g), b) in dst.iter_mut().zip(src).zip(self.gamma).zip(self.beta) {
                *d = (s - m) * inv * g + b;
            }
        }
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
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

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

    fn random(rng: &mut ChaCha8Rng, shape: &[usize], scale: f32) -> Tensor {
        let n = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| rng.random_range(-scale..scale)).collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    #[test]
    fn exp_is_accurate_over_the_whole_range() {
        let mut worst = 0f64;
        for k in 0..=400_000 {
            let x = -86.0 + 174.0 * k as f32 / 400_000.0;
            let want = f64::from(x).exp();
            let got = f64::from(exp(x));
            worst = worst.max((got - want).abs() / want);
        }
        // f32 itself resolves 6e-8 relative.
        assert!(worst < 3e-7, "relative error {worst}");
        let row: Vec<f32> = [-1e9f32, -90.0, f32::NEG_INFINITY, 0.0, f32::NAN]
            .iter()
            .map(|x| exp(*x))
            .collect();
        assert_eq!(&row[..4], &[0.0, 0.0, 0.0, 1.0]);
        assert!(row[4].is_nan());
    }

    /// [`exp_v`] over a slice (its tail, past the last whole vector, with [`exp`]).
    struct ExpAll<'a>(&'a mut [f32]);

    impl Kernel for ExpAll<'_> {
        type Output = ();

        #[inline(always)]
        fn run<S: pulp::Simd>(self, simd: S) {
            let (head, tail) = S::as_mut_simd_f32s(self.0);
            for v in head {
                *v = exp_v(simd, *v);
            }
            for v in tail {
                *v = exp(*v);
            }
        }
    }

    #[test]
    fn vector_exp_is_accurate_over_the_whole_range() {
        let xs: Vec<f32> = (0..=400_000)
            .map(|k| -86.0 + 174.0 * k as f32 / 400_000.0)
            .chain([-1e9, -90.0, f32::NEG_INFINITY, 0.0, f32::NAN, 1.0, 2.0, 3.0])
            .collect();
        let mut ys = xs.clone();
        vectorized(ExpAll(&mut ys));
        let mut worst = 0f64;
        for (x, y) in xs.iter().zip(&ys).take(400_001) {
            let want = f64::from(*x).exp();
            worst = worst.max((f64::from(*y) - want).abs() / want);
        }
        assert!(worst < 3e-7, "relative error {worst}");
        let edge = &ys[400_001..];
        assert_eq!(&edge[..4], &[0.0, 0.0, 0.0, 1.0]);
        assert!(edge[4].is_nan());
    }

    /// The differentiable path of `encoder::Block`: gather into patches, masked softmax
    /// attention per head, scatter back.
    fn reference(
        qkv: &Tensor,
        gather: &[u32],
        mask: Option<&Tensor>,
        heads: usize,
        patch: usize,
    ) -> Tensor {
        let (n, c3) = qkv.dims2().unwrap();
        let (c, np) = (c3 / 3, gather.len() / patch);
        let hd = c / heads;
        let mut inverse = vec![0u32; n];
        // The first occurrence of each point is its real position (padding repeats the last).
        let mut seen = vec![false; n];
        for (k, &i) in gather.iter().enumerate() {
            if !seen[i as usize] {
                seen[i as usize] = true;
                inverse[i as usize] = k as u32;
            }
        }
        let dev = &Device::Cpu;
        let g = Tensor::from_slice(gather, gather.len(), dev).unwrap();
        let qkv = qkv
            .index_select(&g, 0)
            .unwrap()
            .reshape((np, patch, 3, heads, hd))
            .unwrap()
            .permute((2, 0, 3, 1, 4))
            .unwrap();
        let q = (qkv.get(0).unwrap().contiguous().unwrap() * (1.0 / (hd as f64).sqrt())).unwrap();
        let k = qkv.get(1).unwrap().contiguous().unwrap();
        let v = qkv.get(2).unwrap().contiguous().unwrap();
        let mut s = q.matmul(&k.t().unwrap()).unwrap();
        if let Some(m) = mask {
            s = s.broadcast_add(m).unwrap();
        }
        let a = candle_nn::ops::softmax(&s, D::Minus1).unwrap();
        let o = a.matmul(&v).unwrap();
        let o = o
            .permute((0, 2, 1, 3))
            .unwrap()
            .reshape((np * patch, c))
            .unwrap();
        let inv = Tensor::from_slice(&inverse, n, dev).unwrap();
        o.index_select(&inv, 0).unwrap()
    }

    #[test]
    fn patch_attention_matches_the_differentiable_ops() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let dev = &Device::Cpu;
        // 11 points in patches of 6 (the second padded with a masked copy of its last point),
        // in a shuffled order; 2 heads of 8 channels.
        let gather: Vec<u32> = vec![4, 0, 9, 2, 7, 5, 1, 10, 3, 8, 6, 6];
        let m: Vec<f32> = (0..12).map(|k| if k == 11 { -1e9 } else { 0.0 }).collect();
        let mask = Tensor::from_vec(m, (2, 1, 1, 6), dev).unwrap();
        let qkv = random(&mut rng, &[11, 48], 2.0);
        let got = patch_attention(
            &qkv,
            &Tensor::from_slice(&gather, 12, dev).unwrap(),
            Some(&mask),
            2,
            6,
        )
        .unwrap();
        let want = reference(&qkv, &gather, Some(&mask), 2, 6);
        assert!(close(&got, &want) < 1e-5, "{}", close(&got, &want));
        // Unmasked: 12 points, one head, patches of 4.
        let gather: Vec<u32> = vec![11, 3, 0, 7, 1, 2, 10, 4, 9, 5, 8, 6];
        let qkv = random(&mut rng, &[12, 24], 2.0);
        let g = Tensor::from_slice(&gather, 12, dev).unwrap();
        let got = patch_attention(&qkv, &g, None, 1, 4).unwrap();
        let want = reference(&qkv, &gather, None, 1, 4);
        assert!(close(&got, &want) < 1e-5, "{}", close(&got, &want));
        // Bad shapes are errors.
        assert!(patch_attention(&qkv, &g, None, 5, 4).is_err());
        assert!(patch_attention(&qkv, &g, None, 1, 5).is_err());
        assert!(patch_attention(&qkv, &g, Some(&mask.narrow(0, 0, 1).unwrap()), 1, 4).is_err());
    }

    #[test]
    fn softmax_and_layer_norm_match_the_differentiable_ops() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let s = random(&mut rng, &[3, 2, 5, 7], 6.0);
        let plain = candle_nn::ops::softmax(&s, D::Minus1).unwrap();
        assert!(close(&softmax(&s).unwrap(), &plain) < 1e-6);
        let x = (random(&mut rng, &[11, 16], 3.0) + 0.5).unwrap();
        let g = (random(&mut rng, &[16], 0.2) + 1.0).unwrap();
        let b = random(&mut rng, &[16], 0.2);
        let want = candle_nn::ops::layer_norm_slow(&x, &g, &b, 1e-5).unwrap();
        assert!(close(&layer_norm(&x, &g, &b, 1e-5).unwrap(), &want) < 1e-5);
        // Bad shapes are errors.
        assert!(layer_norm(&x, &b.narrow(0, 0, 8).unwrap(), &b, 1e-5).is_err());
    }
}
