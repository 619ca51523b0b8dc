//! The library of candidate effects, their parameters and ranges, and the model family that
//! refits one of them together with the backbone's continuous parameters.

use std::sync::Arc;

use cmaes::{Parameter, Parameters};
use fit::Family;
use glam::Vec3;
use serde::{Deserialize, Serialize};
use springs::{BackboneOptions, Effect, SpringParams};

use crate::GapError;
use crate::base::{BaseEffect, check_distinct};
use crate::forces::{
    ActuationLag, BendingDamping, BendingSprings, ExternalField, GravityScale, MassGradient,
    PlasticCreep, QuadraticDrag, SlippingGrasp, StickSlipFriction, StiffnessGradient,
    StrainStiffening, Twist,
};

/// A candidate unmodelled effect (the nine library effects and the extras), or the generic
/// probe.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Candidate {
    /// Quadratic air drag.
    Drag,
    /// Stiffness varying along the principal axis.
    StiffnessHeterogeneity,
    /// Strain stiffening in tension, softening in compression.
    NonlinearElasticity,
    /// Bending springs to the second ring of neighbours.
    Bending,
    /// Stick-slip ground friction.
    Friction,
    /// Plastic creep of rest lengths above a yield strain.
    Plasticity,
    /// Gripper motion delayed by a fractional number of steps.
    ActuationDelay,
    /// Compliant grasp that slips above a force.
    GraspSlip,
    /// Mass varying along the principal axis.
    MassDistribution,
    /// Beyond the library, offered on request ([`Candidate::EXTRA`]): gravity scaled by a
    /// factor, which also stands for a recording clock off its nominal rate.
    GravityScale,
    /// Beyond the library, offered on request ([`Candidate::EXTRA`]), chains only: internal
    /// damping of the bending along a cable ([`BendingDamping`]).
    BendingDamping,
    /// Beyond the library, offered on request ([`Candidate::EXTRA`]), chains only: a cable's
    /// torsion between its clamped ends ([`Twist`]).
    Twist,
    /// Beyond the library, offered on request ([`Candidate::EXTRA`]): stiffness varying along
    /// the grasp lag ([`MaterialFrame::lag`]), soft where the object trails the grippers.
    StiffnessLag,
    /// Not in the library: a generic external acceleration field (the `unknown` probe).
    ExternalField,
}

/// The range of the external-field probe's window radius, m: from a few centimetres (a local
/// source) to metres (a global field).
pub const PROBE_WINDOW_M: [f64; 2] = [0.05, 5.0];

/// How far the probe's centre may lie from the training data's mean position, m, per axis.
const PROBE_OFFSET_M: f64 = 0.5;

/// Bound of each component of the probe's gyroscopic vector b, 1/s (a frame turning at Ω
/// gives |b| = 2Ω, so up to 10 rad/s).
pub const PROBE_GYRO: f64 = 20.0;

impl Candidate {
    /// The nine named library effects.
    pub const LIBRARY: [Candidate; 9] = [
        Candidate::Drag,
        Candidate::StiffnessHeterogeneity,
        Candidate::NonlinearElasticity,
        Candidate::Bending,
        Candidate::Friction,
        Candidate::Plasticity,
        Candidate::ActuationDelay,
        Candidate::GraspSlip,
        Candidate::MassDistribution,
    ];

    /// Candidates beyond the nine, offered on request only (`--candidates`): the reference
    /// world cannot switch them on, so the bench cannot check them, and they stay out of the
    /// default list.
    pub const EXTRA: [Candidate; 4] = [
        Candidate::GravityScale,
        Candidate::BendingDamping,
        Candidate::Twist,
        Candidate::StiffnessLag,
    ];

    /// The effect's name, as used by the reference world and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Candidate::Drag => "drag",
            Candidate::StiffnessHeterogeneity => "stiffness-heterogeneity",
            Candidate::NonlinearElasticity => "nonlinear-elasticity",
            Candidate::Bending => "bending",
            Candidate::Friction => "friction",
            Candidate::Plasticity => "plasticity",
            Candidate::ActuationDelay => "actuation-delay",
            Candidate::GraspSlip => "grasp-slip",
            Candidate::MassDistribution => "mass-distribution",
            Candidate::GravityScale => "gravity-scale",
            Candidate::BendingDamping => "bending-damping",
            Candidate::Twist => "twist",
            Candidate::StiffnessLag => "stiffness-lag",
            Candidate::ExternalField => "external-field",
        }
    }

    /// Parses a name from [`Candidate::name`].
    pub fn parse(name: &str) -> Result<Candidate, GapError> {
        Candidate::LIBRARY
            .into_iter()
            .chain(Candidate::EXTRA)
            .chain([Candidate::ExternalField])
            .find(|c| c.name() == name)
            .ok_or_else(|| GapError::Config(format!("unknown candidate effect '{name}'")))
    }

    /// The effect's searched parameters (name, range, scale).
    pub fn parameters(self) -> Vec<Parameter> {
        match self {
            Candidate::Drag => vec![Parameter::log("drag_kg_per_m", 1e-3, 10.0)],
            Candidate::StiffnessHeterogeneity => {
                vec![Parameter::linear("log_stiffness_slope", -2.0, 2.0)]
            }
            // Anchored along the grasp lag (`MaterialFrame::lag`): up to e^20 between the parts
            // that move with the grippers and those that trail them most (session 100).
            Candidate::StiffnessLag => {
                vec![Parameter::linear("log_stiffness_lag_slope", -10.0, 10.0)]
            }
            Candidate::NonlinearElasticity => vec![
                Parameter::log("stiffening_beta", 1.0, 1000.0),
                // Down to a thousandth: a fabric or a rope barely resists compression.
                Parameter::log("compression_ratio", 1e-3, 1.0),
            ],
            Candidate::Bending => vec![Parameter::log("bending_relative_stiffness", 1e-3, 1.0)],
            Candidate::Friction => vec![Parameter::linear("static_excess_mu", 0.0, 2.0)],
            Candidate::Plasticity => vec![
                Parameter::linear("yield_strain", 0.0, 0.1),
                Parameter::log("creep_rate_per_s", 0.1, 100.0),
            ],
            // Up to 2 s at 10 fps: the reference world allows lags up to 2 s.
            Candidate::ActuationDelay => vec![Parameter::linear("delay_steps", 0.0, 20.0)],
            // Relative to the object's weight (`forces::SlippingGrasp`): from a grasp that
            // stretches a metre under the weight and slips at a hundredth of it, to one that
            // is practically rigid.
            Candidate::GraspSlip => vec![
                Parameter::log("grasp_relative_stiffness", 0.01, 1e4),
                Parameter::log("grasp_relative_slip_force", 0.01, 1e4),
            ],
            Candidate::MassDistribution => vec![Parameter::linear("log_mass_slope", -2.0, 2.0)],
            Candidate::GravityScale => vec![Parameter::linear("gravity_factor", 0.5, 4.0)],
            // From a trace to a damping that stops a chain's bending modes within a step.
            Candidate::BendingDamping => vec![Parameter::log("bending_damping_time_s", 1e-5, 0.3)],
            // GJ/EI of a solid isotropic rod is about 0.77 and the chain bending's κ is searched
            // over [1e-3, 1]: the same range. Its stability bound grows as 16 κ_t k per particle.
            Candidate::Twist => vec![Parameter::log("twist_relative_stiffness", 1e-3, 1.0)],
            Candidate::ExternalField => vec![
                Parameter::linear("field_x_m_per_s2", -5.0, 5.0),
                Parameter::linear("field_y_m_per_s2", -5.0, 5.0),
                Parameter::linear("field_z_m_per_s2", -5.0, 5.0),
                // The gradient as the radial acceleration it gives at the window's radius
                // (g = a_r / w): a narrow window needs a steep gradient to matter at all.
                Parameter::linear("field_radial_m_per_s2", -30.0, 30.0),
                // The field's centre relative to the training data's mean position, and its
                // window: from a few centimetres (a local source) to metres (a global field).
                Parameter::linear("field_centre_dx_m", -PROBE_OFFSET_M, PROBE_OFFSET_M),
                Parameter::linear("field_centre_dy_m", -PROBE_OFFSET_M, PROBE_OFFSET_M),
                Parameter::linear("field_centre_dz_m", -PROBE_OFFSET_M, PROBE_OFFSET_M),
                Parameter::log("field_window_m", PROBE_WINDOW_M[0], PROBE_WINDOW_M[1]),
                // The workless first-order velocity term v × b (global): a frame turning at
                // up to 10 rad/s, or any force that deflects motion sideways.
                Parameter::linear("field_gyro_x_per_s", -PROBE_GYRO, PROBE_GYRO),
                Parameter::linear("field_gyro_y_per_s", -PROBE_GYRO, PROBE_GYRO),
                Parameter::linear("field_gyro_z_per_s", -PROBE_GYRO, PROBE_GYRO),
            ],
        }
    }

    /// Where the refit starts: a moderate strength, also used for the residual signature (on
    /// data, the probe's start depends on the residuals: [`Candidate::start_in`]).
    pub fn start(self) -> Vec<f64> {
        match self {
            Candidate::Drag => vec![0.3],
            Candidate::StiffnessHeterogeneity => vec![0.5],
            // The trailing parts e^4 softer than those that move with the grippers.
            Candidate::StiffnessLag => vec![-2.0],
            Candidate::NonlinearElasticity => vec![30.0, 0.7],
            Candidate::Bending => vec![0.05],
            Candidate::Friction => vec![0.5],
            Candidate::Plasticity => vec![0.02, 5.0],
            Candidate::ActuationDelay => vec![1.0],
            Candidate::GraspSlip => vec![1.0, 1.0],
            Candidate::MassDistribution => vec![0.5],
            Candidate::GravityScale => vec![1.2],
            Candidate::BendingDamping => vec![1e-3],
            Candidate::Twist => vec![0.05],
            Candidate::ExternalField => {
                vec![0.5, 0.5, 0.5, -2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
            }
        }
    }

    /// Where the refit starts on data in `frame`: [`Candidate::start`], except for the probe
    /// when the frame knows where the backbone's residuals converge ([`crate::residual_focus`]):
    /// then a central field there, no uniform part, pulling (or pushing, as the residuals do)
    /// with the start's 2 m/s² at a window as wide as the lines' spread. The centre offset and
    /// the window are clamped to their ranges.
    pub fn start_in(self, frame: &MaterialFrame) -> Vec<f64> {
        match (self, frame.focus) {
            (Candidate::ExternalField, Some(f)) => {
                let reach = Vec3::splat(PROBE_OFFSET_M as f32);
                let d = (f.point() - frame.centre).clamp(-reach, reach);
                let radial = if f.attracting { -2.0 } else { 2.0 };
                let window = f.window_m();
                let [dx, dy, dz] = d.to_array().map(f64::from);
                vec![0.0, 0.0, 0.0, radial, dx, dy, dz, window, 0.0, 0.0, 0.0]
            }
            _ => self.start(),
        }
    }

    /// Parameter values at which the effect vanishes (grasp slip: a very stiff grasp that
    /// never slips, which only approaches the kinematic grasp).
    pub fn neutral(self) -> Vec<f64> {
        match self {
            Candidate::Drag | Candidate::Bending => vec![0.0],
            Candidate::StiffnessHeterogeneity | Candidate::MassDistribution => vec![0.0],
            Candidate::StiffnessLag => vec![0.0],
            Candidate::NonlinearElasticity => vec![0.0, 1.0],
            Candidate::Friction | Candidate::ActuationDelay => vec![0.0],
            Candidate::GravityScale => vec![1.0],
            Candidate::BendingDamping | Candidate::Twist => vec![0.0],
            Candidate::Plasticity => vec![0.02, 0.0],
            Candidate::GraspSlip => vec![1e9, 1e12],
            Candidate::ExternalField => {
                vec![0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
            }
        }
    }

    /// The effect for parameter values `v` (in the order of [`Candidate::parameters`]).
    pub fn effect(self, v: &[f64], frame: &MaterialFrame) -> Box<dyn Effect> {
        let f = |i: usize| value(v, i);
        match self {
            Candidate::Drag => Box::new(QuadraticDrag { coefficient: f(0) }),
            Candidate::StiffnessHeterogeneity => Box::new(StiffnessGradient {
                slope: f(0),
                material: frame.coordinate.clone(),
                lag_slope: 0.0,
                lag: None,
            }),
            Candidate::StiffnessLag => Box::new(StiffnessGradient {
                slope: 0.0,
                material: frame.coordinate.clone(),
                lag_slope: f(0),
                lag: frame.lag.clone(),
            }),
            Candidate::NonlinearElasticity => Box::new(stiffening(v)),
            Candidate::Bending => Box::new(BendingSprings::new(f(0))),
            Candidate::Friction => Box::new(StickSlipFriction {
                static_excess: f(0),
            }),
            Candidate::Plasticity => Box::new(PlasticCreep {
                yield_strain: f(0),
                rate: f(1),
            }),
            Candidate::ActuationDelay => Box::new(ActuationLag { steps: f(0) }),
            Candidate::GraspSlip => Box::new(SlippingGrasp::new(f(0), f(1))),
            Candidate::MassDistribution => Box::new(MassGradient {
                slope: f(0),
                material: frame.coordinate.clone(),
            }),
            Candidate::GravityScale => Box::new(GravityScale { factor: f(0) }),
            Candidate::BendingDamping => Box::new(BendingDamping::new(f(0))),
            Candidate::Twist => Box::new(Twist::new(f(0))),
            Candidate::ExternalField => {
                let width = v.get(7).map_or(1.0, |w| *w as f32);
                Box::new(ExternalField {
                    uniform: Vec3::new(f(0), f(1), f(2)),
                    gradient: f(3) / width,
                    centre: frame.centre + Vec3::new(f(4), f(5), f(6)),
                    width,
                    gyro: Vec3::new(f(8), f(9), f(10)),
                })
            }
        }
    }
}

/// The effects of `list` (each a candidate at its parameter values), in the order they are set
/// up: the stiffness fields first (`stiffness-heterogeneity`, `stiffness-lag`), so that
/// effects built on the springs' stiffness (bending,
/// [`crate::forces::BendingSprings`]) see it; the rest in the order given. Bending springs
/// also follow the list's spring law (`nonlinear-elasticity`), when it has one.
pub(crate) fn compose<'a>(
    list: impl IntoIterator<Item = (Candidate, &'a [f64])>,
    frame: &MaterialFrame,
) -> Vec<Box<dyn Effect>> {
    let mut list: Vec<(Candidate, &[f64])> = list.into_iter().collect();
    list.sort_by_key(|(c, _)| {
        !matches!(
            c,
            Candidate::StiffnessHeterogeneity | Candidate::StiffnessLag
        )
    });
    let law = list
        .iter()
        .find(|(c, _)| *c == Candidate::NonlinearElasticity)
        .map(|(_, v)| stiffening(v));
    list.into_iter()
        .map(|(c, v)| match (c, law) {
            (Candidate::Bending, Some(law)) => {
                Box::new(BendingSprings::new(value(v, 0)).with_stiffening(law))
            }
            _ => c.effect(v, frame),
        })
        .collect()
}

/// Parameter `i` of `v`, 0 when absent.
fn value(v: &[f64], i: usize) -> f32 {
    v.get(i).copied().unwrap_or(0.0) as f32
}

/// The `nonlinear-elasticity` candidate's spring law at values `v`.
fn stiffening(v: &[f64]) -> StrainStiffening {
    StrainStiffening {
        beta: value(v, 0),
        gamma: 1.0 - value(v, 1),
    }
}

/// Where each tracked particle lies on the object, shared by every episode of a dataset (the
/// tracked particles are the same material points in every episode).
#[derive(Clone, Debug, PartialEq)]
pub struct MaterialFrame {
    /// Coordinate along the principal axis of the reference shape, scaled to [−1, 1].
    pub coordinate: Arc<Vec<f32>>,
    /// Each tracked particle's grasp lag, scaled to [−1, 1]: −1 for the part that moves most
    /// rigidly with the grippers, +1 for the part that trails them most
    /// ([`crate::grasp_lag`]). Learned from training data; `None` without it (a frame made
    /// from one shape) or when every particle lags alike, and then `stiffness-lag` leaves the
    /// stiffness uniform.
    pub lag: Option<Arc<Vec<f32>>>,
    /// Mean tracked position over the training data, m (the external-field probe's centre is
    /// searched around it).
    pub centre: Vec3,
    /// Where the backbone's residuals converge, when known: the probe's refit in this frame
    /// starts there ([`Candidate::start_in`]; the diagnosis also refits it in the frame
    /// without a focus, from the broad start).
    pub focus: Option<crate::ResidualFocus>,
}

impl MaterialFrame {
    /// From a reference shape (tracked positions, m) and the training data's mean position.
    /// The axis is oriented so that the coordinate grows with the particle index, which keeps
    /// its sign the same across datasets of one object.
    pub fn new(reference: &[Vec3], centre: Vec3) -> Result<Self, GapError> {
        if reference.len() < 2 || !reference.iter().all(|p| p.is_finite()) {
            return Err(GapError::Config(
                "reference shape needs >= 2 finite points".into(),
            ));
        }
        let axis = principal_axis(reference);
        let mean = reference.iter().copied().sum::<Vec3>() / reference.len() as f32;
        let mut u: Vec<f32> = reference.iter().map(|p| (*p - mean).dot(axis)).collect();
        let n = u.len() as f32;
        let mean_i = (n - 1.0) / 2.0;
        let cov: f32 = u
            .iter()
            .enumerate()
            .map(|(i, v)| (i as f32 - mean_i) * v)
            .sum();
        let sign = if cov < 0.0 { -1.0 } else { 1.0 };
        let scale = u.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-9);
        for v in &mut u {
            *v *= sign / scale;
        }
        Ok(MaterialFrame {
            coordinate: Arc::new(u),
            centre,
            lag: None,
            focus: None,
        })
    }

    /// The same frame with the grasp-lag coordinate `lag` (one value per tracked particle, in
    /// [−1, 1]; [`crate::grasp_lag`]).
    pub fn with_lag(self, lag: Option<Vec<f32>>) -> Self {
        MaterialFrame {
            lag: lag.map(Arc::new),
            ..self
        }
    }

    /// The same frame with the probe's start at `focus`.
    pub fn with_focus(self, focus: Option<crate::ResidualFocus>) -> Self {
        MaterialFrame { focus, ..self }
    }

    /// From one shape alone, centred on its own mean: the frame of a model that has no
    /// training data at hand, such as a planning task's rope at its start.
    pub fn of_shape(shape: &[Vec3]) -> Result<Self, GapError> {
        let centre = shape.iter().copied().sum::<Vec3>() / shape.len().max(1) as f32;
        Self::new(shape, centre)
    }
}

/// Unit principal axis of a point set (power iteration on the covariance, deterministic start).
pub fn principal_axis(points: &[Vec3]) -> Vec3 {
    let n = points.len().max(1) as f32;
    let mean = points.iter().copied().sum::<Vec3>() / n;
    let mut c = glam::Mat3::ZERO;
    for p in points {
        let d = *p - mean;
        c += glam::Mat3::from_cols(d * d.x, d * d.y, d * d.z);
    }
    let mut v = Vec3::new(1.0, 0.7, 0.3).normalize();
    for _ in 0..100 {
        let w = c * v;
        if w.length() < 1e-12 {
            break;
        }
        v = w.normalize();
    }
    v
}

/// The backbone's continuous parameters (stiffness, damping, ground friction) refitted together
/// with the base effects' (if any) and one candidate's (or none: the control refit). Threshold
/// and springs per particle stay at the fitted values: they change the topology and would make
/// the short refits noisy.
///
/// The real parameter vector is `[stiffness, damping, ground friction, base effects' values in
/// order…, candidate's values…]`.
#[derive(Debug, Clone)]
pub struct CandidateFamily {
    base: SpringParams,
    base_effects: Vec<BaseEffect>,
    candidate: Option<Candidate>,
    frame: MaterialFrame,
    parameters: Parameters,
    /// A refined stiffness field held at its values (not refitted).
    field: Option<std::sync::Arc<Vec<f32>>>,
    /// The base effects are held at their values (not refitted).
    base_held: bool,
}

impl CandidateFamily {
    /// The family around the fitted `base`: stiffness and damping within ×/÷ 4 (log scale),
    /// ground friction in [0, 1]. No base effects.
    pub fn new(
        base: SpringParams,
        candidate: Option<Candidate>,
        frame: MaterialFrame,
    ) -> Result<Self, GapError> {
        CandidateFamily::with_base(base, &[], candidate, frame)
    }

    /// As [`CandidateFamily::new`], with `base_effects` refitted too (from their values). With
    /// an empty list it is the same family as [`CandidateFamily::new`]. The candidate must not
    /// be one of the base effects.
    pub fn with_base(
        base: SpringParams,
        base_effects: &[BaseEffect],
        candidate: Option<Candidate>,
        frame: MaterialFrame,
    ) -> Result<Self, GapError> {
        base.validate()
            .map_err(|e| GapError::Config(format!("fitted backbone: {e}")))?;
        check_distinct(base_effects, candidate)?;
        let k = f64::from(base.stiffness).max(1e-3);
        let c = f64::from(base.damping).max(1e-3);
        let mut p = vec![
            Parameter::log("stiffness_n_per_m", k / 4.0, k * 4.0),
            Parameter::log("damping_ns_per_m", c / 4.0, c * 4.0),
            Parameter::linear(
                "ground_friction",
                0.0,
                1.0_f64.max(f64::from(base.ground_friction)),
            ),
        ];
        for b in base_effects {
            // Re-checked here: the fields are public, so a list may not come from `new`.
            BaseEffect::new(b.effect, b.values.clone())?;
            p.extend(b.effect.parameters());
        }
        if let Some(cand) = candidate {
            p.extend(cand.parameters());
        }
        Ok(CandidateFamily {
            base,
            base_effects: base_effects.to_vec(),
            candidate,
            frame,
            parameters: Parameters::new(p)?,
            field: None,
            base_held: false,
        })
    }

    /// The same family with its base effects held at their values (`hold`) or refitted with
    /// the backbone (the default): held, a refit moves the backbone's stiffness, damping and
    /// friction and the candidate's values only, so the candidate is judged against the model
    /// as it was given rather than against base effects free to trade their values for it.
    pub fn with_base_held(mut self, hold: bool) -> Result<Self, GapError> {
        if hold == self.base_held {
            return Ok(self);
        }
        let all = self.parameters.params();
        let n_base: usize = self.base_effects.iter().map(|b| b.values.len()).sum();
        let mut p = all[..3].to_vec();
        if hold {
            p.extend_from_slice(&all[3 + n_base..]);
        } else {
            for b in &self.base_effects {
                p.extend(b.effect.parameters());
            }
            p.extend_from_slice(&all[3..]);
        }
        self.parameters = Parameters::new(p)?;
        self.base_held = hold;
        Ok(self)
    }

    /// The same family with every model's stiffness multiplied by a refined per-particle field
    /// (`springs::StiffnessField`, log factors of the tracked particles, from
    /// `fit::refine_stiffness`), held at its values: the refits move the global stiffness it
    /// multiplies, not the field.
    pub fn with_field(mut self, log_factor: Option<std::sync::Arc<Vec<f32>>>) -> Self {
        self.field = log_factor;
        self
    }

    /// The candidate (None: the control).
    pub fn candidate(&self) -> Option<Candidate> {
        self.candidate
    }

    /// The base effects (at their starting values).
    pub fn base_effects(&self) -> &[BaseEffect] {
        &self.base_effects
    }

    /// Backbone parameters and effect values (base effects' in order, then the candidate's) of
    /// a real vector; held base effects ([`CandidateFamily::with_base_held`]) at their values.
    pub fn split(&self, real: &[f64]) -> (SpringParams, Vec<f64>) {
        let params = SpringParams {
            stiffness: real[0] as f32,
            damping: real[1] as f32,
            ground_friction: real[2] as f32,
            ..self.base
        };
        let mut values = Vec::with_capacity(real.len());
        if self.base_held {
            for b in &self.base_effects {
                values.extend(&b.values);
            }
        }
        values.extend(real.get(3..).unwrap_or(&[]));
        (params, values)
    }

    /// Every named value of a real vector: the optimised ones, with held base effects' values
    /// in their places (the layout of a family that refits them, which
    /// `Diagnosis::refitted_model` reads).
    pub fn named_values(&self, real: &[f64]) -> Vec<(String, f64)> {
        let names = self.parameters.params().iter().map(|p| p.name.clone());
        let mut out: Vec<(String, f64)> = names.zip(real.iter().copied()).collect();
        if self.base_held {
            let held = self.base_effects.iter().flat_map(|b| {
                let names = b.effect.parameters().into_iter().map(|p| p.name);
                names.zip(b.values.iter().copied())
            });
            let at = out.len().min(3);
            out.splice(at..at, held);
        }
        out
    }

    /// The base effects at the values of a real vector (e.g. a refit's best); held ones at
    /// their values.
    pub fn base_effects_at(&self, real: &[f64]) -> Vec<BaseEffect> {
        if self.base_held {
            return self.base_effects.clone();
        }
        let mut at = 3;
        self.base_effects
            .iter()
            .map(|b| {
                let n = b.values.len();
                let values = real
                    .get(at..at + n)
                    .map_or(b.values.clone(), <[f64]>::to_vec);
                at += n;
                BaseEffect {
                    effect: b.effect,
                    values,
                }
            })
            .collect()
    }
}

impl Family for CandidateFamily {
    fn name(&self) -> String {
        let base: String = self
            .base_effects
            .iter()
            .map(|b| format!("+{}", b.effect.name()))
            .collect();
        format!(
            "spring-mass{base}+{}",
            self.candidate.map_or("control", |c| c.name())
        )
    }
    fn parameters(&self) -> &Parameters {
        &self.parameters
    }
    fn x0(&self) -> Vec<f64> {
        let b = &self.base;
        let mut x = vec![
            f64::from(b.stiffness).max(1e-3),
            f64::from(b.damping).max(1e-3),
            f64::from(b.ground_friction),
        ];
        if !self.base_held {
            for e in &self.base_effects {
                x.extend(&e.values);
            }
        }
        if let Some(c) = self.candidate {
            x.extend(c.start_in(&self.frame));
        }
        x
    }
    fn build(&self, real: &[f64]) -> (SpringParams, BackboneOptions) {
        let (params, values) = self.split(real);
        let mut list = Vec::with_capacity(self.base_effects.len() + 1);
        let mut at = 0;
        for b in &self.base_effects {
            list.push((b.effect, values.get(at..).unwrap_or(&[])));
            at += b.values.len();
        }
        if let Some(c) = self.candidate {
            list.push((c, values.get(at..).unwrap_or(&[])));
        }
        let mut effects = compose(list, &self.frame);
        if let Some(f) = &self.field {
            effects.push(Box::new(springs::StiffnessField {
                log_factor: f.clone(),
            }));
        }
        (
            params,
            BackboneOptions {
                effects,
                ..Default::default()
            },
        )
    }
}
