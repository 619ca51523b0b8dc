//! Adding a row vector to, and multiplying one into, every row of a tensor (a linear layer's
//! bias, a layer norm's gain and shift), with a backward pass that sums the parameter's
//! gradient row after row.
//!
//! candle's `broadcast_add` / `broadcast_mul` give the same values, but their backward pass
//! sums the gradient over the leading dimensions with an integer division per element, and
//! that reduction took a fifth of a training step (`docs/BENCHMARKS.md`, "Training: the
//! parameters' gradient sums"). Here the sum runs over the same elements in the same order
//! (row 0 first, one running sum per column, from zero), so the gradients, and every trained
//! weight, are the same bits; `tests` below check both passes against candle's.

use candle_core::{CpuStorage, CustomOp2, DType, Layout, Shape, Tensor};

use crate::Result;
use crate::kernels::f32_slice;

/// `x + b`, `b` of shape `[c]` added to every row of `x` (any rank, last dimension `c`).
pub(crate) fn add_row(x: &Tensor, b: &Tensor) -> Result<Tensor> {
    if !fast_path(x, b) {
        return Ok(x.broadcast_add(b)?);
    }
    Ok(x.apply_op2(b, RowOp::Add)?)
}

/// `x * g`, `g` of shape `[c]` multiplied into every row of `x` (any rank, last dimension `c`).
pub(crate) fn mul_row(x: &Tensor, g: &Tensor) -> Result<Tensor> {
    if !fast_path(x, g) {
        return Ok(x.broadcast_mul(g)?);
    }
    Ok(x.apply_op2(g, RowOp::Mul)?)
}

/// Contiguous f32 tensors on the CPU whose last dimension is the vector's length.
fn fast_path(x: &Tensor, v: &Tensor) -> bool {
    x.is_contiguous()
        && v.is_contiguous()
        && x.dtype() == DType::F32
        && v.dtype() == DType::F32
        && x.device().is_cpu()
        && v.device().is_cpu()
        && v.rank() == 1
        && x.dims().last() == v.dims().first()
}

#[derive(Clone, Copy, Debug)]
enum RowOp {
    Add,
    Mul,
}

/// Calls `f` with a tensor's elements in logical order, borrowed where the tensor is a
/// contiguous CPU f32 one (as gradients are), copied otherwise.
fn with_values<R>(
    t: &Tensor,
    f: impl FnOnce(&[f32]) -> candle_core::Result<R>,
) -> candle_core::Result<R> {
    {
        let (storage, layout) = t.storage_and_layout();
        if let candle_core::Storage::Cpu(cpu) = &*storage
            && let Ok(values) = f32_slice(cpu, layout, "gradient")
        {
            return f(values);
        }
    }
    f(&t.flatten_all()?.to_vec1::<f32>()?)
}

impl CustomOp2 for RowOp {
    fn name(&self) -> &'static str {
        match self {
            RowOp::Add => "add-row",
            RowOp::Mul => "mul-row",
        }
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = f32_slice(s1, l1, "row op input")?;
        let v = f32_slice(s2, l2, "row op vector")?;
        if v.is_empty() {
            return Ok((CpuStorage::F32(x.to_vec()), l1.shape().clone()));
        }
        let mut out = x.to_vec();
        for row in out.chunks_exact_mut(v.len()) {
            match self {
                RowOp::Add => row.iter_mut().zip(v).for_each(|(a, b)| *a += b),
                RowOp::Mul => row.iter_mut().zip(v).for_each(|(a, b)| *a *= b),
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        v: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let c = v.dim(0)?;
        let mut sums = vec![0f32; c];
        let dx = match self {
            RowOp::Add => {
                with_values(grad, |g| {
                    if c > 0 {
                        for row in g.chunks_exact(c) {
                            sums.iter_mut().zip(row).for_each(|(s, g)| *s += g);
                        }
                    }
                    Ok(())
                })?;
                grad.clone()
            }
            RowOp::Mul => {
                let vs = v.to_vec1::<f32>()?;
                let dx = with_values(grad, |g| {
                    with_values(x, |xs| {
                        let mut dx = g.to_vec();
                        if c > 0 {
                            for ((drow, grow), xrow) in dx
                                .chunks_exact_mut(c)
                                .zip(g.chunks_exact(c))
                                .zip(xs.chunks_exact(c))
                            {
                                drow.iter_mut().zip(&vs).for_each(|(d, v)| *d *= v);
                                // The product is rounded to f32 before it is added, as candle
                                // rounds the materialised `grad * x` before its sum.
                                sums.iter_mut()
                                    .zip(grow.iter().zip(xrow))
                                    .for_each(|(s, (g, x))| *s += g * x);
                            }
                        }
                        Ok(dx)
                    })
                })?;
                Tensor::from_vec(dx, grad.shape(), grad.device())?
            }
        };
        Ok((Some(dx), Some(Tensor::from_vec(sums, c, v.device())?)))
    }
}

#[cfg(test)]
mod tests {
    use candle_core::{Device, Var};

    use super::*;

    fn grads_of(
        op: impl Fn(&Tensor, &Tensor) -> Result<Tensor>,
        x: &Var,
        v: &Var,
        weights: &Tensor,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let y = op(x.as_tensor(), v.as_tensor()).unwrap();
        let loss = (&y * weights).unwrap().sum_all().unwrap();
        let g = loss.backward().unwrap();
        let flat = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        (
            flat(&y),
            flat(g.get(x.as_tensor()).unwrap()),
            flat(g.get(v.as_tensor()).unwrap()),
        )
    }

    /// Values spread over several binades, so that a different summation order would show.
    fn spread(n: usize, seed: u32) -> Vec<f32> {
        (0..n)
            .map(|i| {
                let k = (i as u32).wrapping_mul(2_654_435_761).wrapping_add(seed) >> 8;
                let m = (k % 2000) as f32 / 1000.0 - 1.0;
                m * 10f32.powi((k % 7) as i32 - 3)
            })
            .collect()
    }

    #[test]
    fn both_passes_are_candles_bits_for_any_rank_and_a_strided_input_falls_back() {
        let dev = Device::Cpu;
        for dims in [vec![5usize], vec![37, 6], vec![3, 11, 6], vec![2, 3, 4, 6]] {
            let n: usize = dims.iter().product();
            let c = *dims.last().unwrap();
            let x = Var::from_vec(spread(n, 1), dims.as_slice(), &dev).unwrap();
            let v = Var::from_vec(spread(c, 2), c, &dev).unwrap();
            let w = Tensor::from_vec(spread(n, 3), dims.as_slice(), &dev).unwrap();
            let ours = grads_of(add_row, &x, &v, &w);
            let theirs = grads_of(|a, b| Ok(a.broadcast_add(b)?), &x, &v, &w);
            assert_eq!(ours, theirs, "add, {dims:?}");
            let ours = grads_of(mul_row, &x, &v, &w);
            let theirs = grads_of(|a, b| Ok(a.broadcast_mul(b)?), &x, &v, &w);
            assert_eq!(ours, theirs, "mul, {dims:?}");
        }
        // A transposed (non-contiguous) input takes candle's ops.
        let x = Var::from_vec(spread(6 * 9, 4), (6, 9), &dev).unwrap();
        let v = Var::from_vec(spread(6, 5), 6, &dev).unwrap();
        let w = Tensor::from_vec(spread(54, 6), (9, 6), &dev).unwrap();
        let t =
            |f: fn(&Tensor, &Tensor) -> Result<Tensor>| move |a: &Tensor, b: &Tensor| f(&a.t()?, b);
        assert_eq!(
            grads_of(t(add_row), &x, &v, &w),
            grads_of(t(|a, b| Ok(a.broadcast_add(b)?)), &x, &v, &w)
        );
        assert_eq!(
            grads_of(t(mul_row), &x, &v, &w),
            grads_of(t(|a, b| Ok(a.broadcast_mul(b)?)), &x, &v, &w)
        );
    }

    #[test]
    fn other_shapes_take_candles_own_ops() {
        let dev = Device::Cpu;
        let x = Tensor::ones((4, 3), DType::F32, &dev).unwrap();
        let col = Tensor::ones((4, 1), DType::F32, &dev).unwrap();
        assert!(!fast_path(&x, &col));
        let y = add_row(&x, &col).unwrap();
        assert_eq!(y.to_vec2::<f32>().unwrap(), vec![vec![2f32; 3]; 4]);
    }
}
