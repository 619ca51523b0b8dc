//! Multi-head attention inside the serialization patches of one transformer block, fused into
//! one pass: gather of the patch's keys and values, scores, mask, softmax and the weighted sum
//! of values, written straight back to the points' own rows.
//!
//! What it replaces (the `Pass::Grad` path of `encoder::Block`): a gather of the `qkv` rows into
//! patch order, a permute and three copies, a batched score matmul, the softmax over a
//! `(patches, heads, patch, patch)` tensor, a second batched matmul and a scatter back. Those
//! allocate and write the full score tensor twice; here each score row lives in a small scratch
//! buffer, and `exp` is the vectorisable [`super::exp`].

use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Shape, Tensor};

use super::{Kernel, f32_slice, fma, vecs, vecs_mut, vectorized};
use crate::Result;

/// Attention output `(n, c)` of every point, from its `(n, 3c)` projections `[q | k | v]`
/// (each `heads` blocks of `c / heads` channels), attending within the patches of `patch`
/// points that `gather` lists (point indices, patch after patch) under the additive key mask
/// `mask` (`(patches, 1, 1, patch)`; nonzero marks a padding copy, which is neither read as a
/// query nor written). Equals `softmax(q kᵀ / √d + mask) v` per patch and head, rows in point
/// order.
pub(crate) fn patch_attention(
    qkv: &Tensor,
    gather: &Tensor,
    mask: Option<&Tensor>,
    heads: usize,
    patch: usize,
) -> Result<Tensor> {
    let qkv = qkv.contiguous()?;
    let op = PatchAttention { heads, patch };
    Ok(match mask {
        Some(m) => qkv.apply_op3_no_bwd(gather, &m.contiguous()?, &op)?,
        None => qkv.apply_op2_no_bwd(gather, &op)?,
    })
}

struct PatchAttention {
    heads: usize,
    patch: usize,
}

impl PatchAttention {
    fn run(
        &self,
        qkv: (&CpuStorage, &Layout),
        gather: (&CpuStorage, &Layout),
        mask: Option<(&CpuStorage, &Layout)>,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = f32_slice(qkv.0, qkv.1, "qkv")?;
        let (CpuStorage::U32(g), Some((a, b))) = (gather.0, gather.1.contiguous_offsets()) else {
            candle_core::bail!("patch attention: gather must be contiguous u32");
        };
        let gather = &g[a..b];
        let (n, c3) = qkv.1.shape().dims2()?;
        let c = c3 / 3;
        if c3 % 3 != 0 || self.heads == 0 || c % self.heads != 0 {
            candle_core::bail!(
                "patch attention: {c3} qkv channels for {} heads",
                self.heads
            );
        }
        if gather.iter().any(|&i| i as usize >= n) {
            candle_core::bail!("patch attention: gather index out of range ({n} points)");
        }
        let patch = self.patch;
        if patch == 0 || gather.len() % patch != 0 {
            candle_core::bail!(
                "patch attention: {} gathered points in patches of {patch}",
                gather.len()
            );
        }
        let mask = match mask {
            Some((s, l)) => {
                let m = f32_slice(s, l, "mask")?;
                if m.len() != gather.len() {
                    candle_core::bail!(
                        "patch attention: mask {:?} for {} gathered points",
                        l.dims(),
                        gather.len()
                    );
                }
                Some(m)
            }
            None => None,
        };
        let out = vectorized(Attend {
            qkv: x,
            c,
            heads: self.heads,
            gather,
            mask,
            patch,
        });
        Ok((CpuStorage::F32(out), Shape::from((n, c))))
    }
}

impl CustomOp2 for PatchAttention {
    fn name(&self) -> &'static str {
        "patch-attention"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        self.run((s1, l1), (s2, l2), None)
    }
}

impl CustomOp3 for PatchAttention {
    fn name(&self) -> &'static str {
        "patch-attention-masked"
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
        self.run((s1, l1), (s2, l2), Some((s3, l3)))
    }
}

/// The kernel's inputs (checked by the caller).
#[derive(Clone, Copy)]
struct Attend<'a> {
    qkv: &'a [f32],
    c: usize,
    heads: usize,
    gather: &'a [u32],
    mask: Option<&'a [f32]>,
    patch: usize,
}

impl Kernel for Attend<'_> {
    type Output = Vec<f32>;

    #[inline(always)]
    fn run<S: pulp::Simd>(self, simd: S) -> Vec<f32> {
        let Attend {
            qkv,
            c,
            heads,
            gather,
            mask,
            patch,
        } = self;
        // Common head widths as constants, so one output row stays in registers.
        match c / heads {
            8 => attend::<S, 8>(simd, qkv, c, heads, gather, mask, patch),
            16 => attend::<S, 16>(simd, qkv, c, heads, gather, mask, patch),
            32 => attend::<S, 32>(simd, qkv, c, heads, gather, mask, patch),
            _ => attend::<S, 0>(simd, qkv, c, heads, gather, mask, patch),
        }
    }
}

/// `HD`: the head width if known at compile time (a multiple of 8), 0 otherwise.
#[inline(always)]
fn attend<S: pulp::Simd, const HD: usize>(
    simd: S,
    qkv: &[f32],
    c: usize,
    heads: usize,
    gather: &[u32],
    mask: Option<&[f32]>,
    patch: usize,
) -> Vec<f32> {
    let hd = if HD == 0 { c / heads } else { HD };
    let n = qkv.len() / (3 * c);
    // As the differentiable path: queries are scaled before the dot products.
    let scale = (1.0 / (hd as f64).sqrt()) as f32;
    let mut out = vec![0f32; n * c];
    // The patch's keys of one head in blocks of one vector of keys (8 with AVX2), each block
    // channel-major (`[block][channel][lane]`), so that one block of scores is `hd`
    // multiply-adds of whole vectors; an even number of blocks (two are computed together),
    // keys past the patch zero. Values row-major, one query's scores, the scaled query.
    let lanes = S::F32_LANES;
    let blocks = patch.div_ceil(lanes);
    let mut kt = vec![0f32; blocks * hd * lanes];
    let mut v = vec![0f32; patch * hd];
    let mut s = vec![0f32; blocks * lanes];
    let mut q = vec![0f32; hd];
    for (p, idx) in gather.chunks_exact(patch).enumerate() {
        let m = mask.map(|m| &m[p * patch..(p + 1) * patch]);
        for h in 0..heads {
            for (j, &i) in idx.iter().enumerate() {
                let row = &qkv[i as usize * 3 * c..][..3 * c];
                let block = &mut kt[j / lanes * hd * lanes..][..hd * lanes];
                for (d, k) in row[c + h * hd..][..hd].iter().enumerate() {
                    block[d * lanes + j % lanes] = *k;
                }
                v[j * hd..(j + 1) * hd].copy_from_slice(&row[2 * c + h * hd..][..hd]);
            }
            for (t, &i) in idx.iter().enumerate() {
                if m.is_some_and(|m| m[t] != 0.0) {
                    continue; // a padding copy of the patch's last point
                }
                for (q, x) in q.iter_mut().zip(&qkv[i as usize * 3 * c + h * hd..][..hd]) {
                    *q = x * scale;
                }
                scores(simd, &q, &kt, vecs_mut::<S>(&mut s));
                if let Some(m) = m {
                    for (s, m) in s.iter_mut().zip(m) {
                        *s += m;
                    }
                }
                s[patch..].fill(f32::NEG_INFINITY); // keys past the patch: weight 0
                // Unnormalised weights; the output is divided by their sum once.
                let sum = super::exp_shifted_row(simd, &mut s);
                let dst = &mut out[i as usize * c + h * hd..][..hd];
                let (a, inv) = (&s[..patch], 1.0 / sum);
                // Head width in vectors, as a constant (2 for 16 channels with AVX2).
                match HD / lanes {
                    1 => weighted_sum::<S, 1>(simd, a, &v, inv, dst),
                    2 => weighted_sum::<S, 2>(simd, a, &v, inv, dst),
                    4 => weighted_sum::<S, 4>(simd, a, &v, inv, dst),
                    _ => weighted_sum_rows::<S>(a, &v, inv, dst),
                }
            }
        }
    }
    out
}

/// One query's scores against blocks of keys: `s[b] = Σ_d q_d kt[b][d]`, one vector of keys per
/// block. Four blocks at a time, each with two partial sums (even and odd channels): eight
/// independent chains of multiply-adds, enough to hide their latency.
#[inline(always)]
fn scores<S: pulp::Simd>(simd: S, q: &[f32], kt: &[f32], s: &mut [S::f32s]) {
    let hd = q.len();
    let zero = simd.splat_f32s(0.0);
    let kt = vecs::<S>(kt);
    let (q2, q1) = q.as_chunks::<2>();
    let mut blocks = s.chunks_exact_mut(4);
    let mut keys = kt.chunks_exact(4 * hd);
    for (s, k) in (&mut blocks).zip(&mut keys) {
        let mut acc = [[zero; 2]; 4];
        for (d, q) in q2.iter().enumerate() {
            let (qa, qb) = (simd.splat_f32s(q[0]), simd.splat_f32s(q[1]));
            for (b, acc) in acc.iter_mut().enumerate() {
                acc[0] = simd.mul_add_e_f32s(qa, k[b * hd + 2 * d], acc[0]);
                acc[1] = simd.mul_add_e_f32s(qb, k[b * hd + 2 * d + 1], acc[1]);
            }
        }
        for ((s, acc), b) in s.iter_mut().zip(&acc).zip(0..) {
            let mut sum = simd.add_f32s(acc[0], acc[1]);
            for (q, k) in q1.iter().zip(&k[b * hd + hd - q1.len()..(b + 1) * hd]) {
                sum = simd.mul_add_e_f32s(simd.splat_f32s(*q), *k, sum);
            }
            *s = sum;
        }
    }
    for (s, k) in blocks
        .into_remainder()
        .iter_mut()
        .zip(keys.remainder().chunks_exact(hd))
    {
        let mut sum = zero;
        for (q, k) in q.iter().zip(k) {
            sum = simd.mul_add_e_f32s(simd.splat_f32s(*q), *k, sum);
        }
        *s = sum;
    }
}

/// `out = scale · Σ_j a_j v_j` for the rows `v_j` of `v` (`out.len()` wide).
#[inline(always)]
fn weighted_sum_rows<S: pulp::Simd>(a: &[f32], v: &[f32], scale: f32, out: &mut [f32]) {
    out.fill(0.0);
    for (a, vj) in a.iter().zip(v.chunks_exact(out.len())) {
        for (o, v) in out.iter_mut().zip(vj) {
            *o = fma::<S>(*a, *v, *o);
        }
    }
    out.iter_mut().for_each(|o| *o *= scale);
}

/// [`weighted_sum_rows`] for rows of `NV` vectors.
#[inline(always)]
fn weighted_sum<S: pulp::Simd, const NV: usize>(
    simd: S,
    a: &[f32],
    v: &[f32],
    scale: f32,
    out: &mut [f32],
) {
    // Four rows at a time into four accumulators: independent chains of multiply-adds.
    let zero = simd.splat_f32s(0.0);
    let mut acc = [[zero; NV]; 4];
    let rows = vecs::<S>(v).as_chunks::<NV>().0;
    let (a4, a1) = a.as_chunks::<4>();
    for (a, v) in a4.iter().zip(rows.as_chunks::<4>().0) {
        for ((acc, a), v) in acc.iter_mut().zip(a).zip(v) {
            let av = simd.splat_f32s(*a);
            for (o, v) in acc.iter_mut().zip(v) {
                *o = simd.mul_add_e_f32s(av, *v, *o);
            }
        }
    }
    for (a, vj) in a1.iter().zip(&rows[4 * a4.len()..]) {
        let av = simd.splat_f32s(*a);
        for (o, v) in acc[0].iter_mut().zip(vj) {
            *o = simd.mul_add_e_f32s(av, *v, *o);
        }
    }
    let sv = simd.splat_f32s(scale);
    for (e, dst) in vecs_mut::<S>(out).iter_mut().enumerate() {
        let sum = simd.add_f32s(
            simd.add_f32s(acc[0][e], acc[1][e]),
            simd.add_f32s(acc[2][e], acc[3][e]),
        );
        *dst = simd.mul_f32s(sum, sv);
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// pulp's scalar fallback (CPUs without AVX2) computes what the dispatched kernel does, for
    /// head widths with and without a specialised path and patches off the vector width.
    #[test]
    fn the_scalar_fallback_agrees() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        for (c, heads, patch) in [(32, 2, 11), (64, 4, 21), (24, 2, 7), (16, 1, 40)] {
            let n = 2 * patch - 3;
            let qkv: Vec<f32> = (0..n * 3 * c)
                .map(|_| rng.random_range(-2.0..2.0))
                .collect();
            // Two patches, the second padded with three masked copies of its last point.
            let mut gather: Vec<u32> = (0..n as u32).collect();
            gather.extend([n as u32 - 1; 3]);
            let mask: Vec<f32> = (0..2 * patch)
                .map(|k| if k >= n { -1e9 } else { 0.0 })
                .collect();
            let kernel = Attend {
                qkv: &qkv,
                c,
                heads,
                gather: &gather,
                mask: Some(&mask),
                patch,
            };
            let vector = vectorized(kernel);
            let scalar = kernel.run(pulp::Scalar::new());
            let off = vector
                .iter()
                .zip(&scalar)
                .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(off < 1e-5, "{c} channels, {heads} heads: {off}");
            assert!(vector.iter().any(|v| v.abs() > 0.1));
        }
    }
}
