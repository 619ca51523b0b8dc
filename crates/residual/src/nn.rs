//! Small layers built only from ops that have a backward pass in candle 0.11 (the fused
//! LayerNorm and `softmax_last_dim` silently drop gradients; see `docs/residual.md`).

use candle_core::{D, Tensor};
use candle_nn::{Init, Linear, VarBuilder};

use crate::Result;

/// Which kernels a forward pass uses: the same function either way, up to float rounding.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Pass {
    /// Ops with a backward pass (training, and the single-rollout paths).
    Grad,
    /// Forward-only fused kernels (`kernels.rs`) for linear layers, patch attention, LayerNorm
    /// and softmax, for predictions that need no gradient (the same function up to float
    /// rounding).
    Infer,
}

/// Epsilon of every layer normalisation.
pub(crate) const NORM_EPS: f32 = 1e-5;

/// Layer normalisation over the last dimension, composed of differentiable ops.
#[derive(Debug, Clone)]
pub(crate) struct Norm {
    gamma: Tensor,
    beta: Tensor,
}

impl Norm {
    pub fn new(dim: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Norm {
            gamma: vb.get_with_hints(dim, "gamma", Init::Const(1.0))?,
            beta: vb.get_with_hints(dim, "beta", Init::Const(0.0))?,
        })
    }

    /// The parameters as plain vectors, for the inference kernels.
    pub fn params(&self) -> Result<crate::kernels::NormParams> {
        Ok(crate::kernels::NormParams {
            gamma: self.gamma.to_vec1()?,
            beta: self.beta.to_vec1()?,
        })
    }

    pub fn forward(&self, x: &Tensor, pass: Pass) -> Result<Tensor> {
        if pass == Pass::Infer {
            return crate::kernels::layer_norm(x, &self.gamma, &self.beta, NORM_EPS);
        }
        // candle's `layer_norm_slow`, step for step, with the gain and shift applied by
        // `row_ops` (the same values; their gradients summed without a division per element).
        let hidden = x.dim(D::Minus1)? as f64;
        let centred = x.broadcast_sub(&(x.sum_keepdim(D::Minus1)? / hidden)?)?;
        let var = (centred.sqr()?.sum_keepdim(D::Minus1)? / hidden)?;
        let normed = centred.broadcast_div(&(var + f64::from(NORM_EPS))?.sqrt()?)?;
        crate::row_ops::add_row(&crate::row_ops::mul_row(&normed, &self.gamma)?, &self.beta)
    }
}

/// A linear layer's parameters as plain vectors, for the inference kernels.
pub(crate) fn dense(l: &Linear) -> Result<crate::kernels::Dense> {
    let (outputs, inputs) = l.weight().dims2()?;
    Ok(crate::kernels::Dense {
        w: l.weight().flatten_all()?.to_vec1()?,
        b: match l.bias() {
            Some(b) => b.to_vec1()?,
            None => vec![0.0; outputs],
        },
        inputs,
        outputs,
    })
}

/// A linear layer `in → out` with bias.
pub(crate) fn linear(i: usize, o: usize, vb: VarBuilder<'_>) -> Result<Linear> {
    Ok(candle_nn::linear(i, o, vb)?)
}

/// `x W^T + b` for rows `x` of shape `(n, in)`: candle's `Linear::forward` on rows, with the
/// bias added by `row_ops` (the same values; its gradient summed without a division per
/// element).
fn forward_rows(l: &Linear, x: &Tensor) -> Result<Tensor> {
    let y = x.matmul(&l.weight().t()?)?;
    match l.bias() {
        Some(b) => crate::row_ops::add_row(&y, b),
        None => Ok(y),
    }
}

/// Applies a linear layer to a tensor of any rank ≥ 2 (flattening the leading dims, because a
/// single large matmul is far faster on CPU than candle's per-batch gemm calls).
pub(crate) fn apply(l: &Linear, x: &Tensor) -> Result<Tensor> {
    let dims = x.dims();
    if dims.len() == 2 {
        return forward_rows(l, x);
    }
    let last = dims[dims.len() - 1];
    let flat = x.reshape(((), last))?;
    let y = forward_rows(l, &flat)?;
    let mut out = dims.to_vec();
    let n = out.len();
    out[n - 1] = y.dim(1)?;
    Ok(y.reshape(out)?)
}

/// [`apply`], then ReLU if `relu`; for `Pass::Infer` on rows `(n, in)` one fused kernel.
pub(crate) fn affine(l: &Linear, x: &Tensor, pass: Pass, relu: bool) -> Result<Tensor> {
    if let (Pass::Infer, 2, Some(b)) = (pass, x.rank(), l.bias()) {
        return crate::kernels::linear(x, l.weight(), b, relu);
    }
    let y = apply(l, x)?;
    Ok(if relu { y.relu()? } else { y })
}

/// Logistic sigmoid from differentiable primitives.
pub(crate) fn sigmoid(x: &Tensor) -> Result<Tensor> {
    Ok((x.neg()?.exp()? + 1.0)?.recip()?)
}

/// Softmax over the last dimension (with a backward pass unless `pass` is `Infer`).
pub(crate) fn softmax(x: &Tensor, pass: Pass) -> Result<Tensor> {
    if pass == Pass::Infer {
        return crate::kernels::softmax(x);
    }
    Ok(candle_nn::ops::softmax(x, D::Minus1)?)
}

/// Two-layer perceptron `C → hidden → C'` with ReLU (GELU costs several times more on CPU).
#[derive(Debug, Clone)]
pub(crate) struct Mlp {
    a: Linear,
    b: Linear,
}

impl Mlp {
    pub fn new(i: usize, h: usize, o: usize, vb: VarBuilder<'_>) -> Result<Self> {
        Ok(Mlp {
            a: linear(i, h, vb.pp("fc1"))?,
            b: linear(h, o, vb.pp("fc2"))?,
        })
    }

    pub fn forward(&self, x: &Tensor, pass: Pass) -> Result<Tensor> {
        affine(&self.b, &affine(&self.a, x, pass, true)?, pass, false)
    }

    /// The two layers.
    pub fn layers(&self) -> (&Linear, &Linear) {
        (&self.a, &self.b)
    }
}
