//! A cable's torsion between its two clamped ends: the twist–bend coupling a chain of point
//! masses does not have.

use std::any::Any;

use glam::{DVec3, Vec3A};
use springs::{Backbone, Effect, ModelSetup, SimError, SubstepContext};

use super::{ChainStencil, bad, check_finite};

/// Torsion of a cable clamped at both ends, quasi-static and isotropic (a discrete elastic
/// rod's twist energy with the twist spread evenly along the rod): `E = GJ/(2L) (m − m₀)²`,
/// with `m` the total twist (rad) between the frames of the chain's first and last edges, `L`
/// the chain's rest length and `GJ = κ_t k l̄³` (N·m²; κ_t the twist stiffness relative to the
/// fitted spring stiffness k, l̄ the mean rest segment length: the same base as the chain
/// bending's `EI = κ k l̄³`, so κ_t/κ is the rod's GJ/EI).
///
/// Why: turning a hanging loop about the chord between its clamps twists a real cable (the
/// frame carried along the bent centreline no longer meets the far clamp's), so the cable
/// resists swinging out of its sag plane; a chain with stretching and curvature bending only
/// swings freely (DLO1's remaining error, `docs/gap-log.md`, session 94).
///
/// The clamps' roll is not recorded (two markers per end give a tangent, not a roll), so each
/// end's frame is carried in time by the smallest rotation of its edge: grippers that turn but
/// do not roll. The twist is measured from a rollout's first state (`m₀ = 0` there, as the
/// springs' rest shape is the first frame) and released while either end of the chain is not
/// held by a closed gripper (`m₀` follows `m`). The forces `−GJ/L (m − m₀) ∂m/∂x` use the
/// holonomy gradient of discrete elastic rods (Bergou et al. 2010): with `m` the angle about
/// the last edge from the first end's frame carried along the chain to the last end's, each
/// interior vertex with edges e₁ (in) and e₂ (out) and curvature binormal `κb = 2 e₁ × e₂ /
/// (|e₁||e₂| + e₁·e₂)` contributes `−κb/(2|e₁|)` to `∂m/∂x` at its previous particle,
/// `κb/(2|e₂|)` at its next and minus their sum at itself (checked against finite
/// differences); the forces sum to zero (momentum is kept), the clamps take the torque.
/// Explicit; its adjoint is held fixed (`refine` treats its forces as constants).
#[derive(Debug, Clone, Default)]
pub struct Twist {
    /// Relative twist stiffness κ_t (0: none).
    pub relative_stiffness: f32,
    order: Vec<u32>,
    /// Grippers holding the chain's first and last particles, when both are held.
    clamps: Option<[usize; 2]>,
    /// GJ/L, N·m.
    coefficient: f64,
}

impl Twist {
    /// Torsion of relative stiffness κ_t.
    pub fn new(relative_stiffness: f32) -> Self {
        Twist {
            relative_stiffness,
            ..Default::default()
        }
    }
}

/// The twist carried through a rollout: each end's frame (a unit vector normal to its edge),
/// the edges' last tangents, the total twist (unwrapped, rad) and its rest value.
#[derive(Debug, Clone, Default)]
struct TwistState {
    frames: Option<EndFrames>,
    twist: f64,
    rest: f64,
}

#[derive(Debug, Clone, Copy)]
struct EndFrames {
    first: DVec3,
    last: DVec3,
    first_tangent: DVec3,
    last_tangent: DVec3,
}

impl Effect for Twist {
    fn name(&self) -> &str {
        "twist"
    }

    fn setup(&mut self, model: &mut ModelSetup<'_>) -> Result<(), SimError> {
        check_finite(
            self.name(),
            &[("relative_stiffness", self.relative_stiffness)],
        )?;
        let Some(order) = model.chain.filter(|c| c.len() >= 3) else {
            return Err(bad(
                self.name(),
                "needs a chain: the particles' order along a cable (a `chain` dataset)".into(),
            ));
        };
        let mean = f64::from(ChainStencil::new(model.rest_positions, order).mean_length);
        let length = mean * (order.len() - 1) as f64;
        self.order = order.to_vec();
        let gripper = |p: u32| usize::try_from(model.held[p as usize]).ok();
        self.clamps = match (gripper(order[0]), gripper(order[order.len() - 1])) {
            (Some(a), Some(b)) => Some([a, b]),
            _ => None,
        };
        self.coefficient = if length > 0.0 {
            f64::from(self.relative_stiffness.max(0.0))
                * f64::from(model.params.stiffness)
                * mean.powi(3)
                / length
        } else {
            0.0
        };
        Ok(())
    }

    fn stability(&self, backbone: &Backbone, row: &mut [f32], _damping: &mut [f32]) {
        // The Hessian is GJ/L ∇m ∇mᵀ plus GJ/L (m − m₀) ∇²m. With turns of at most 90° per
        // vertex (|κb| ≤ 2) each particle's |∂m/∂x| ≤ 4/l̄, so a Gershgorin row of the first
        // term is at most GJ/L · 4/l̄ · 4n/l̄ = 16 κ_t k n/(n − 1); the second, with |m − m₀|
        // ≤ π, adds a term of order 1/n of that.
        if self.coefficient <= 0.0 {
            return;
        }
        let n = self.order.len() as f32;
        let k = self.relative_stiffness.max(0.0) * backbone.params().stiffness;
        let bound = k * (16.0 * n / (n - 1.0) + 16.0 / (n - 1.0));
        for &p in &self.order {
            row[p as usize] += bound;
        }
    }

    fn new_state(&self, _backbone: &Backbone) -> Box<dyn Any + Send> {
        Box::new(TwistState::default())
    }

    fn add_forces(
        &self,
        ctx: &SubstepContext<'_>,
        state: &mut dyn Any,
        _rest_lengths: &[f32],
        force: &mut [Vec3A],
    ) {
        if self.coefficient <= 0.0 {
            return;
        }
        let Some(st) = state.downcast_mut::<TwistState>() else {
            return;
        };
        st.advance(ctx.x, &self.order);
        let clamped = self.clamps.is_some_and(|[a, b]| {
            ctx.closed.get(a) == Some(&true) && ctx.closed.get(b) == Some(&true)
        });
        if !clamped {
            st.rest = st.twist;
            return;
        }
        let g = -self.coefficient * (st.twist - st.rest);
        if g != 0.0 {
            add_twist_gradient(ctx.x, &self.order, g, force);
        }
    }
}

impl TwistState {
    /// Carries the end frames to the chain's shape `x` and measures the twist there.
    fn advance(&mut self, x: &[Vec3A], order: &[u32]) {
        let n = order.len();
        let (t_first, t_last) = (tangent(x, order, 0), tangent(x, order, n - 2));
        let Some(f) = self.frames else {
            // A rollout's first state is its rest: the far frame is the near one carried along
            // the chain, untwisted by construction.
            let first = normal_to(t_first);
            self.frames = Some(EndFrames {
                first,
                last: carry_along(x, order, first),
                first_tangent: t_first,
                last_tangent: t_last,
            });
            (self.twist, self.rest) = (0.0, 0.0);
            return;
        };
        let frames = EndFrames {
            first: renormal(transport(f.first_tangent, t_first, f.first), t_first),
            last: renormal(transport(f.last_tangent, t_last, f.last), t_last),
            first_tangent: t_first,
            last_tangent: t_last,
        };
        // The measured angle lies in (−π, π]; the twist follows it continuously.
        let raw = twist_between(x, order, frames.first, frames.last);
        self.twist += wrap(raw - wrap(self.twist));
        self.frames = Some(frames);
    }
}

/// Unit tangent of edge `j` of the chain (from `order[j]` to `order[j + 1]`); a collapsed
/// edge gives zero.
fn tangent(x: &[Vec3A], order: &[u32], j: usize) -> DVec3 {
    let (a, b) = (x[order[j] as usize], x[order[j + 1] as usize]);
    (b.as_dvec3() - a.as_dvec3()).normalize_or_zero()
}

/// The smallest rotation taking unit `a` to unit `b`, applied to `u` (none when they are
/// opposite or either is zero: the rotation is not defined).
fn transport(a: DVec3, b: DVec3, u: DVec3) -> DVec3 {
    let c = a.dot(b);
    if c <= -1.0 + 1e-9 || a == DVec3::ZERO || b == DVec3::ZERO {
        return u;
    }
    let v = a.cross(b);
    u * c + v.cross(u) + v * (v.dot(u) / (1.0 + c))
}

/// `u` made exactly normal to unit `t` and of unit length (rounding drifts over a rollout).
fn renormal(u: DVec3, t: DVec3) -> DVec3 {
    let w = (u - t * t.dot(u)).normalize_or_zero();
    if w == DVec3::ZERO { normal_to(t) } else { w }
}

/// A unit vector normal to `t`.
fn normal_to(t: DVec3) -> DVec3 {
    let axis = if t.x.abs() < 0.6 { DVec3::X } else { DVec3::Y };
    (axis - t * t.dot(axis)).normalize_or_zero()
}

/// `u` (normal to the first edge) carried along the chain to its last edge.
fn carry_along(x: &[Vec3A], order: &[u32], u: DVec3) -> DVec3 {
    let mut t = tangent(x, order, 0);
    let mut u = u;
    for j in 1..order.len() - 1 {
        let next = tangent(x, order, j);
        u = transport(t, next, u);
        t = next;
    }
    u
}

/// The signed angle (rad, in (−π, π]) about the last edge from `first` carried along the
/// chain to `last`: the total twist between two end frames.
fn twist_between(x: &[Vec3A], order: &[u32], first: DVec3, last: DVec3) -> f64 {
    let t = tangent(x, order, order.len() - 2);
    let u = carry_along(x, order, first);
    u.cross(last).dot(t).atan2(u.dot(last))
}

/// `a` wrapped into (−π, π].
fn wrap(a: f64) -> f64 {
    let tau = std::f64::consts::TAU;
    a - tau * ((a + std::f64::consts::PI) / tau).ceil() + tau
}

/// Adds `g ∂m/∂x` (the holonomy gradient of the total twist at `x`) to `out`.
fn add_twist_gradient(x: &[Vec3A], order: &[u32], g: f64, out: &mut [Vec3A]) {
    let at = |p: u32| x[p as usize].as_dvec3();
    for w in order.windows(3) {
        let (a, b, c) = (at(w[0]), at(w[1]), at(w[2]));
        let (e1, e2) = (b - a, c - b);
        let (l1, l2) = (e1.length(), e2.length());
        let denom = l1 * l2 + e1.dot(e2);
        if l1 <= 0.0 || l2 <= 0.0 || denom <= 1e-9 * l1 * l2 {
            continue;
        }
        let kb = e1.cross(e2) * (2.0 / denom);
        let before = kb * (-g / (2.0 * l1));
        let after = kb * (g / (2.0 * l2));
        out[w[0] as usize] += Vec3A::from(before.as_vec3());
        out[w[2] as usize] += Vec3A::from(after.as_vec3());
        out[w[1] as usize] -= Vec3A::from((before + after).as_vec3());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bent, non-planar chain of `n` particles.
    fn helix(n: usize) -> (Vec<Vec3A>, Vec<u32>) {
        let x = (0..n)
            .map(|i| {
                let s = i as f32 * 0.35;
                Vec3A::new(0.1 * s.cos(), 0.1 * s.sin(), 0.03 * i as f32 + 0.01 * s * s)
            })
            .collect();
        (x, (0..n as u32).collect())
    }

    #[test]
    fn wrap_stays_in_the_half_open_interval() {
        for a in [-7.0, -3.2, -1.0, 0.0, 1.0, 3.1, std::f64::consts::PI, 9.5] {
            let w = wrap(a);
            assert!(w > -std::f64::consts::PI - 1e-12 && w <= std::f64::consts::PI + 1e-12);
            let k = (a - w) / std::f64::consts::TAU;
            assert!((k - k.round()).abs() < 1e-9, "{a} -> {w}");
        }
    }

    #[test]
    fn transport_takes_one_tangent_to_the_other_and_keeps_normals_normal() {
        let a = DVec3::new(1.0, 0.2, -0.3).normalize();
        let b = DVec3::new(0.1, 1.0, 0.4).normalize();
        assert!((transport(a, b, a) - b).length() < 1e-12);
        let u = normal_to(a);
        let w = transport(a, b, u);
        assert!(w.dot(b).abs() < 1e-12 && (w.length() - 1.0).abs() < 1e-12);
    }

    /// The analytic gradient against central differences of the twist, moving interior
    /// particles only (the end edges, and so the end frames, stay put).
    #[test]
    fn the_gradient_is_the_twist_s_derivative() {
        let n = 9;
        let (x, order) = helix(n);
        let t0 = tangent(&x, &order, 0);
        let first = normal_to(t0);
        // A far frame turned 0.4 rad from the carried one: a twisted rod.
        let carried = carry_along(&x, &order, first);
        let tn = tangent(&x, &order, n - 2);
        let last = carried * 0.4f64.cos() + tn.cross(carried) * 0.4f64.sin();
        let m = twist_between(&x, &order, first, last);
        assert!((m - 0.4).abs() < 1e-9, "{m}");
        let mut grad = vec![Vec3A::ZERO; n];
        add_twist_gradient(&x, &order, 1.0, &mut grad);
        let h = 1e-3f32;
        let mut worst = 0.0f64;
        let mut scale = 0.0f64;
        for p in 2..n - 2 {
            for k in 0..3 {
                let mut plus = x.clone();
                let mut minus = x.clone();
                plus[p][k] += h;
                minus[p][k] -= h;
                let fd = (twist_between(&plus, &order, first, last)
                    - twist_between(&minus, &order, first, last))
                    / (2.0 * f64::from(h));
                worst = worst.max((fd - f64::from(grad[p][k])).abs());
                scale = scale.max(fd.abs());
            }
        }
        assert!(scale > 0.1, "the twist should depend on the shape: {scale}");
        assert!(
            worst < 1e-3 * scale.max(1.0) + 1e-3,
            "mismatch {worst} at scale {scale}"
        );
    }

    #[test]
    fn the_gradient_sums_to_zero() {
        let (x, order) = helix(12);
        let mut grad = vec![Vec3A::ZERO; x.len()];
        add_twist_gradient(&x, &order, 1.0, &mut grad);
        let sum: Vec3A = grad.iter().copied().sum();
        assert!(sum.length() < 1e-5, "{sum}");
    }

    /// A planar chain turned about the normal of its plane: both end edges turn about an axis
    /// normal to them, so grippers that do not roll keep the end frames turning with the
    /// chain, and the twist stays at rest; a translation leaves it too.
    #[test]
    fn turning_in_the_plane_and_moving_do_not_twist() {
        let n = 10;
        let x: Vec<Vec3A> = (0..n)
            .map(|i| {
                let s = i as f32 * 0.3;
                Vec3A::new(0.2 * s.sin(), 0.0, 0.2 * (1.0 - s.cos()))
            })
            .collect();
        let order: Vec<u32> = (0..n as u32).collect();
        let mut st = TwistState::default();
        st.advance(&x, &order);
        assert_eq!(st.twist, st.rest);
        for step in 1..=30 {
            let q = glam::Quat::from_rotation_y(0.05 * step as f32);
            let shift = Vec3A::new(0.01, -0.02, 0.005) * step as f32;
            let moved: Vec<Vec3A> = x
                .iter()
                .map(|p| Vec3A::from(q * glam::Vec3::from(*p)) + shift)
                .collect();
            st.advance(&moved, &order);
        }
        assert!((st.twist - st.rest).abs() < 1e-6, "{}", st.twist - st.rest);
    }

    /// Rolling the far end's frame by 0.1 rad forty times twists the chain by 4 rad: the
    /// measured twist follows continuously past ±π (unwrapped).
    #[test]
    fn the_twist_is_unwrapped_past_half_a_turn() {
        let n = 8;
        let (x, order) = helix(n);
        let mut st = TwistState::default();
        st.advance(&x, &order);
        for _ in 0..40 {
            let f = st.frames.unwrap();
            let t = f.last_tangent;
            let roll = 0.1f64;
            let rolled = f.last * roll.cos() + t.cross(f.last) * roll.sin();
            st.frames = Some(EndFrames { last: rolled, ..f });
            st.advance(&x, &order);
        }
        assert!(
            (st.twist - st.rest - 4.0).abs() < 1e-6,
            "{}",
            st.twist - st.rest
        );
    }
}
