//! The temporal aggregator for inference, eight particles at a time.
//!
//! The aggregator is a transformer over each particle's own last `W` decoder outputs: its
//! matrices are tiny (16 × 48 in the default network) and it has no interaction between
//! particles. As candle tensor operations that meant many small matrix products and about
//! thirty passes over `(N, W, ·)` tensors per step; here every lane of a 256-bit register holds
//! one particle, so every multiply-add of the layer is one vector instruction for eight
//! particles and nothing but a few scratch rows is written to memory. Same operations, in the
//! same order per particle as `ResidualNet::aggregate`; `exp`, `tanh` and the sigmoid use the
//! vectorisable [`super::exp`].

use super::{Kernel, exp, exp_v, vectorized};

/// A linear layer `y = W x + b`, `W` row-major `(outputs, inputs)` as candle stores it.
#[derive(Debug)]
pub(crate) struct Dense {
    pub w: Vec<f32>,
    pub b: Vec<f32>,
    pub inputs: usize,
    pub outputs: usize,
}

/// Layer normalisation parameters.
#[derive(Debug)]
pub(crate) struct NormParams {
    pub gamma: Vec<f32>,
    pub beta: Vec<f32>,
}

/// One post-norm transformer layer.
#[derive(Debug)]
pub(crate) struct LayerParams {
    pub qkv: Dense,
    pub proj: Dense,
    pub n1: NormParams,
    pub fc1: Dense,
    pub fc2: Dense,
    pub n2: NormParams,
}

/// How the decoder output `r` and the aggregator's `δ` make the residual.
#[derive(Debug)]
pub(crate) enum Mix {
    /// `s ((1 − g) r + g δ)`, `g = sigmoid(gate(h))`.
    Gate(Dense),
    /// `s (r + δ) / 2`.
    Add,
}

/// The aggregator's parameters, copied out of the network for one batch of predictions.
#[derive(Debug)]
pub(crate) struct TemporalParams {
    pub embed: Dense,
    /// Positional encoding `(window, d)`.
    pub pe: Vec<f32>,
    pub layers: Vec<LayerParams>,
    pub heads: usize,
    pub delta: Dense,
    pub mix: Mix,
    pub window: usize,
    /// Residual bound `s`, m/s.
    pub scale: f32,
    /// Layer normalisation epsilon.
    pub eps: f32,
}

impl TemporalParams {
    /// The residual `(rows, 3)`, m/s, flattened, from the window of decoder outputs (oldest
    /// first, each `(rows, 3)` flattened; shorter windows are left-padded with the newest, as
    /// in `ResidualNet::aggregate`).
    pub fn apply(&self, window: &[&[f32]], rows: usize) -> Vec<f32> {
        vectorized(Aggregate {
            p: self,
            window,
            rows,
        })
    }
}

#[derive(Clone, Copy)]
struct Aggregate<'a> {
    p: &'a TemporalParams,
    window: &'a [&'a [f32]],
    rows: usize,
}

impl Kernel for Aggregate<'_> {
    type Output = Vec<f32>;

    #[inline(always)]
    fn run<S: pulp::Simd>(self, simd: S) -> Vec<f32> {
        aggregate(simd, self.p, self.window, self.rows)
    }
}

/// `y = W x + b` on vectors of particles (`x.len() == inputs`, `y.len() == outputs`); the sum
/// first, then the bias, as candle's `Linear`. Four outputs at a time: four independent chains
/// of multiply-adds.
#[inline(always)]
fn dense<S: pulp::Simd>(simd: S, l: &Dense, x: &[S::f32s], y: &mut [S::f32s]) {
    let k = l.inputs;
    let full = l.outputs / 4 * 4;
    let rows = l.w[..full * k].chunks_exact(4 * k).zip(l.b.chunks_exact(4));
    let (y4, y1) = y.split_at_mut(full);
    for ((w, b), y) in rows.zip(y4.chunks_exact_mut(4)) {
        let (w0, rest) = w.split_at(k);
        let (w1, rest) = rest.split_at(k);
        let (w2, w3) = rest.split_at(k);
        let mut acc = [simd.splat_f32s(0.0); 4];
        for ((((x, a), b), c), d) in x.iter().zip(w0).zip(w1).zip(w2).zip(w3) {
            for (acc, w) in acc.iter_mut().zip([a, b, c, d]) {
                *acc = simd.mul_add_e_f32s(simd.splat_f32s(*w), *x, *acc);
            }
        }
        for ((y, a), b) in y.iter_mut().zip(acc).zip(b) {
            *y = simd.add_f32s(a, simd.splat_f32s(*b));
        }
    }
    let rest = l.w[full * k..].chunks_exact(k).zip(&l.b[full..]);
    for ((w, b), y) in rest.zip(y1.iter_mut()) {
        let mut acc = simd.splat_f32s(0.0);
        for (w, x) in w.iter().zip(x) {
            acc = simd.mul_add_e_f32s(simd.splat_f32s(*w), *x, acc);
        }
        *y = simd.add_f32s(acc, simd.splat_f32s(*b));
    }
}

/// Layer normalisation of one row of vectors, in place (as `kernels::LayerNorm`).
#[inline(always)]
fn norm<S: pulp::Simd>(simd: S, n: &NormParams, eps: f32, x: &mut [S::f32s]) {
    let inv_n = simd.splat_f32s(1.0 / x.len() as f32);
    let mut mean = simd.splat_f32s(0.0);
    for x in x.iter() {
        mean = simd.add_f32s(mean, *x);
    }
    let mean = simd.mul_f32s(mean, inv_n);
    let mut var = simd.splat_f32s(0.0);
    for x in x.iter() {
        let d = simd.sub_f32s(*x, mean);
        var = simd.add_f32s(var, simd.mul_f32s(d, d));
    }
    let var = simd.add_f32s(simd.mul_f32s(var, inv_n), simd.splat_f32s(eps));
    let inv = simd.div_f32s(simd.splat_f32s(1.0), simd.sqrt_f32s(var));
    for ((x, g), b) in x.iter_mut().zip(&n.gamma).zip(&n.beta) {
        let y = simd.mul_f32s(
            simd.mul_f32s(simd.sub_f32s(*x, mean), inv),
            simd.splat_f32s(*g),
        );
        *x = simd.add_f32s(y, simd.splat_f32s(*b));
    }
}

/// `tanh x = 1 − 2 / (e^2x + 1)`: absolute error a few 1e-8 (relative error grows near 0,
/// where the residual it scales is near 0 too).
#[inline(always)]
fn tanh(x: f32) -> f32 {
    1.0 - 2.0 / (exp(2.0 * x) + 1.0)
}

#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + exp(-x))
}

#[inline(always)]
fn aggregate<S: pulp::Simd>(
    simd: S,
    p: &TemporalParams,
    window: &[&[f32]],
    rows: usize,
) -> Vec<f32> {
    let mut out = vec![0f32; 3 * rows];
    let Some(newest) = window.last() else {
        return out;
    };
    let zero = simd.splat_f32s(0.0);
    let lanes = S::F32_LANES;
    let w = p.window;
    let d = p.embed.outputs;
    let (heads, hd) = (p.heads, d / p.heads);
    let attn_scale = simd.splat_f32s((1.0 / (hd as f64).sqrt()) as f32);
    let tail = &window[window.len().saturating_sub(w)..];
    let pad = w - tail.len();
    let token = |t: usize| if t < pad { newest } else { &tail[t - pad] };
    let ff = p.layers.iter().map(|l| l.fc1.outputs).max().unwrap_or(0);
    // Scratch, one vector of particles per channel: tokens, hidden states (W × d), their
    // projections (W × 3d), and one query's attention, output and feed-forward rows.
    let mut xin = vec![zero; w * 3];
    let mut h = vec![zero; w * d];
    let mut next = vec![zero; w * d];
    let mut qkv = vec![zero; w * 3 * d];
    let mut a = vec![zero; w];
    let mut o = vec![zero; d];
    let mut y = vec![zero; d];
    let mut f = vec![zero; ff];
    let mut res = vec![zero; 3];
    let mut g = vec![zero; 3];
    let mut lane = vec![0f32; lanes];
    let (mut rv, mut dv, mut gv) = (vec![0f32; lanes], vec![0f32; lanes], vec![0f32; lanes]);
    for start in (0..rows).step_by(lanes) {
        let count = lanes.min(rows - start);
        for t in 0..w {
            let src = token(t);
            for c in 0..3 {
                for (l, v) in lane[..count].iter_mut().enumerate() {
                    *v = src[(start + l) * 3 + c];
                }
                xin[t * 3 + c] = simd.partial_load_f32s(&lane[..count]);
            }
            let row = &mut h[t * d..(t + 1) * d];
            dense(simd, &p.embed, &xin[t * 3..t * 3 + 3], row);
            for (h, pe) in row.iter_mut().zip(&p.pe[t * d..(t + 1) * d]) {
                *h = simd.add_f32s(*h, simd.splat_f32s(*pe));
            }
        }
        for (li, layer) in p.layers.iter().enumerate() {
            // Only the newest token feeds the output, so the last layer computes just that query.
            let first = if li + 1 == p.layers.len() { w - 1 } else { 0 };
            for t in 0..w {
                let dst = &mut qkv[t * 3 * d..][..3 * d];
                dense(simd, &layer.qkv, &h[t * d..(t + 1) * d], dst);
            }
            for tq in first..w {
                for head in 0..heads {
                    let q = &qkv[tq * 3 * d + head * hd..][..hd];
                    for (t, a) in a.iter_mut().enumerate() {
                        let k = &qkv[t * 3 * d + d + head * hd..][..hd];
                        let mut s = zero;
                        for (q, k) in q.iter().zip(k) {
                            s = simd.mul_add_e_f32s(*q, *k, s);
                        }
                        *a = simd.mul_f32s(s, attn_scale);
                    }
                    // Softmax over the window, per particle.
                    let max = a.iter().fold(simd.splat_f32s(f32::NEG_INFINITY), |m, a| {
                        simd.max_f32s(m, *a)
                    });
                    let mut sum = zero;
                    for a in a.iter_mut() {
                        *a = exp_v(simd, simd.sub_f32s(*a, max));
                        sum = simd.add_f32s(sum, *a);
                    }
                    let inv = simd.div_f32s(simd.splat_f32s(1.0), sum);
                    for a in a.iter_mut() {
                        *a = simd.mul_f32s(*a, inv);
                    }
                    for (e, o) in o[head * hd..(head + 1) * hd].iter_mut().enumerate() {
                        let mut acc = zero;
                        for (t, a) in a.iter().enumerate() {
                            let v = qkv[t * 3 * d + 2 * d + head * hd + e];
                            acc = simd.mul_add_e_f32s(*a, v, acc);
                        }
                        *o = acc;
                    }
                }
                dense(simd, &layer.proj, &o, &mut y);
                let x = &mut next[tq * d..(tq + 1) * d];
                for ((x, h), y) in x.iter_mut().zip(&h[tq * d..(tq + 1) * d]).zip(&y) {
                    *x = simd.add_f32s(*h, *y);
                }
                norm(simd, &layer.n1, p.eps, x);
                let f = &mut f[..layer.fc1.outputs];
                dense(simd, &layer.fc1, x, f);
                for v in f.iter_mut() {
                    *v = simd.max_f32s(*v, zero);
                }
                dense(simd, &layer.fc2, f, &mut y);
                for (x, y) in x.iter_mut().zip(&y) {
                    *x = simd.add_f32s(*x, *y);
                }
                norm(simd, &layer.n2, p.eps, x);
            }
            std::mem::swap(&mut h, &mut next);
        }
        let last = &h[(w - 1) * d..w * d];
        dense(simd, &p.delta, last, &mut res);
        if let Mix::Gate(gate) = &p.mix {
            dense(simd, gate, last, &mut g);
        }
        // The few transcendental values per particle: scalar.
        for c in 0..3 {
            simd.partial_store_f32s(&mut rv, xin[(w - 1) * 3 + c]);
            simd.partial_store_f32s(&mut dv, res[c]);
            simd.partial_store_f32s(&mut gv, g[c]);
            for l in 0..count {
                let (r, delta) = (rv[l], tanh(dv[l]));
                out[(start + l) * 3 + c] = match p.mix {
                    Mix::Gate(_) => {
                        let g = sigmoid(gv[l]);
                        ((1.0 - g) * r + g * delta) * p.scale
                    }
                    Mix::Add => (r + delta) * (p.scale / 2.0),
                };
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Tensor};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::{Aggregate, Kernel};
    use crate::nn::Pass;
    use crate::{Combine, ModelConfig, ResidualNet};

    /// The kernel against the differentiable `ResidualNet::aggregate` on random windows, with
    /// the aggregator's weights drawn large enough that every part of it moves the output.
    #[test]
    fn the_kernel_computes_what_the_tensor_ops_compute() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let two_layers = ModelConfig {
            temporal_layers: 2,
            ..ModelConfig::default()
        };
        let add = ModelConfig {
            combine: Combine::Add,
            ..ModelConfig::tiny()
        };
        for cfg in [ModelConfig::default(), two_layers, add] {
            let net = ResidualNet::new(&cfg, 1).unwrap();
            for (name, var) in net.named_vars() {
                if name.starts_with("temporal.") && !name.contains("norm") {
                    let v: Vec<f32> = (0..var.elem_count())
                        .map(|_| rng.random_range(-0.6..0.6))
                        .collect();
                    var.set(&Tensor::from_vec(v, var.shape(), &Device::Cpu).unwrap())
                        .unwrap();
                }
            }
            let params = net.temporal_params().unwrap().unwrap();
            // 13 rows: one full vector of particles and a partial one. Windows shorter than,
            // equal to and longer than the network's.
            let rows = 13;
            for len in [1, cfg.window, cfg.window + 2] {
                let window: Vec<Vec<f32>> = (0..len)
                    .map(|_| (0..3 * rows).map(|_| rng.random_range(-1.0..1.0)).collect())
                    .collect();
                let tensors: Vec<Tensor> = window
                    .iter()
                    .map(|w| Tensor::from_slice(w, (rows, 3), &Device::Cpu).unwrap())
                    .collect();
                let want: Vec<f32> = net
                    .aggregate(&tensors, Pass::Grad)
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .to_vec1()
                    .unwrap();
                let slices: Vec<&[f32]> = window.iter().map(Vec::as_slice).collect();
                let got = params.apply(&slices, rows);
                // pulp's scalar fallback (CPUs without AVX2) computes the same.
                let kernel = Aggregate {
                    p: &params,
                    window: &slices,
                    rows,
                };
                let scalar = kernel.run(pulp::Scalar::new());
                let off = got
                    .iter()
                    .zip(&scalar)
                    .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
                assert!(
                    off < 1e-6 * cfg.residual_scale,
                    "scalar fallback differs by {off}"
                );
                let newest = window.last().unwrap();
                let s = cfg.residual_scale;
                let (mut worst, mut moved) = (0f32, 0f32);
                for ((g, w), r) in got.iter().zip(&want).zip(newest) {
                    worst = worst.max((g - w).abs());
                    // How far the aggregator moves the residual from the plain decoder output.
                    moved = moved.max((w - r * s).abs());
                }
                assert!(moved > 0.01 * s, "aggregator barely acts: {moved}");
                assert!(worst < 1e-6 * s * 10.0, "{:?}: {worst}", cfg.combine);
            }
        }
    }
}
