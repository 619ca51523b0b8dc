//! The backbone's step as a node of candle's autograd graph ([`crate::SimGradient::Adjoint`]):
//! its forward value is the step the rollout already took, its backward pass the step's
//! adjoint (`springs::StepAdjoint::vjp`).

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp1, Layout, Shape, Tensor};
use glam::Vec3;
use springs::{StepAdjoint, StepTape};

/// One taped backbone step. Input and output are `(n, 6)`: each particle's position and
/// velocity, before and after the step.
pub(crate) struct BackboneStep {
    adjoint: Arc<StepAdjoint>,
    tape: StepTape,
    /// The step's result, `(n, 6)` row-major.
    out: Vec<f32>,
}

impl BackboneStep {
    pub fn new(adjoint: Arc<StepAdjoint>, tape: StepTape, x: &[Vec3], v: &[Vec3]) -> Self {
        let out = x
            .iter()
            .zip(v)
            .flat_map(|(p, q)| p.to_array().into_iter().chain(q.to_array()))
            .collect();
        BackboneStep { adjoint, tape, out }
    }
}

impl CustomOp1 for BackboneStep {
    fn name(&self) -> &'static str {
        "backbone-step"
    }

    fn cpu_fwd(
        &self,
        _storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        if layout.shape().elem_count() != self.out.len() {
            candle_core::bail!(
                "backbone-step: input has {} values, the step {}",
                layout.shape().elem_count(),
                self.out.len()
            );
        }
        Ok((CpuStorage::F32(self.out.clone()), layout.shape().clone()))
    }

    fn bwd(
        &self,
        _arg: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let g: Vec<f32> = grad_res.flatten_all()?.to_vec1()?;
        let n = g.len() / 6;
        let mut gx: Vec<Vec3> = (0..n).map(|i| Vec3::from_slice(&g[6 * i..])).collect();
        let mut gv: Vec<Vec3> = (0..n).map(|i| Vec3::from_slice(&g[6 * i + 3..])).collect();
        self.adjoint
            .vjp(&self.tape, &mut gx, &mut gv)
            .map_err(|e| candle_core::Error::Msg(format!("backbone-step backward: {e}")))?;
        let back: Vec<f32> = gx
            .iter()
            .zip(&gv)
            .flat_map(|(p, q)| p.to_array().into_iter().chain(q.to_array()))
            .collect();
        Ok(Some(Tensor::from_vec(back, (n, 6), grad_res.device())?))
    }
}
