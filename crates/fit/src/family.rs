use cmaes::{Parameter, Parameters};
use scene::Scene;
use springs::{BackboneOptions, ParamBounds, SpringParams};

/// How far beyond the scenes' widest free gap [`widen_threshold_range`] lets the spring
/// threshold reach: half as far again, so that the loosest particle can have springs to more
/// than its one nearest neighbour.
pub const GAP_REACH: f32 = 1.5;

/// `bounds` with the spring threshold's upper end raised to [`GAP_REACH`] times the scenes'
/// widest free gap ([`Scene::widest_free_gap_m`], the median over `scenes`) where that lies
/// beyond it; never lowered, and unchanged without scenes.
///
/// The reference range (up to 5 cm) suits dense point clouds. On sparse tracking, 60 points on
/// a 40 cm flag some 4.5 cm apart, no threshold within it gives every free particle a spring,
/// and a fit can only choose which particles fall freely (docs/pipelines.md, "The threshold's
/// range").
pub fn widen_threshold_range(bounds: ParamBounds, scenes: &[Scene]) -> ParamBounds {
    let mut gaps: Vec<f32> = scenes.iter().map(Scene::widest_free_gap_m).collect();
    gaps.sort_by(f32::total_cmp);
    let Some(&gap) = gaps.get(gaps.len() / 2) else {
        return bounds;
    };
    let reach = GAP_REACH * gap;
    let mut out = bounds;
    if reach.is_finite() && reach > bounds.threshold[1] {
        out.threshold[1] = reach;
    }
    out
}

/// A searchable model: its parameters (with ranges and scales) and how a real vector of them
/// becomes a backbone.
pub trait Family: Sync {
    /// Name written into checkpoints and reports (a checkpoint of another family is refused).
    fn name(&self) -> String;
    /// The searched parameters, with bounds and scales.
    fn parameters(&self) -> &Parameters;
    /// Starting point of the search, in real units.
    fn x0(&self) -> Vec<f64>;
    /// The backbone parameters and options (masses, effects) for a real parameter vector.
    fn build(&self, real: &[f64]) -> (SpringParams, BackboneOptions);
    /// [`build`](Self::build) for one scene: a family whose parameters say how to treat the
    /// scene's own particles (its anchors' rule, [`ControllerFamily`](crate::ControllerFamily)) reads them here. Every
    /// rollout a fit scores is built by this.
    fn build_for(&self, real: &[f64], scene: &Scene) -> (SpringParams, BackboneOptions) {
        let _ = scene;
        self.build(real)
    }
}

/// The paper's five backbone parameters: stiffness and damping searched on a log scale (they
/// span orders of magnitude; the reference code searches them linearly), threshold and ground
/// friction linearly, max springs per particle linearly and rounded to an integer.
#[derive(Debug, Clone)]
pub struct BackboneFamily {
    bounds: ParamBounds,
    parameters: Parameters,
}

impl BackboneFamily {
    /// The family over `bounds` (e.g. [`springs::REFERENCE_BOUNDS`]).
    pub fn new(bounds: ParamBounds) -> Result<Self, cmaes::Error> {
        let f = |v: f32| f64::from(v);
        let parameters = Parameters::new(vec![
            Parameter::log(
                "stiffness_n_per_m",
                f(bounds.stiffness[0]),
                f(bounds.stiffness[1]),
            ),
            Parameter::log(
                "damping_ns_per_m",
                f(bounds.damping[0]),
                f(bounds.damping[1]),
            ),
            Parameter::linear(
                "threshold_m",
                f(bounds.threshold[0]),
                f(bounds.threshold[1]),
            ),
            Parameter::linear(
                "max_springs",
                f64::from(bounds.max_springs[0]),
                f64::from(bounds.max_springs[1]),
            )
            .integer(),
            Parameter::linear(
                "ground_friction",
                f(bounds.ground_friction[0]),
                f(bounds.ground_friction[1]),
            ),
        ])?;
        Ok(BackboneFamily { bounds, parameters })
    }

    /// The search bounds.
    pub fn bounds(&self) -> &ParamBounds {
        &self.bounds
    }

    /// Spring parameters from the first five entries of a real vector.
    pub fn params(real: &[f64]) -> SpringParams {
        SpringParams {
            stiffness: real[0] as f32,
            damping: real[1] as f32,
            threshold: real[2] as f32,
            max_springs: real[3].round() as u32,
            ground_friction: real[4] as f32,
        }
    }
}

impl Family for BackboneFamily {
    fn name(&self) -> String {
        "spring-mass".to_string()
    }

    fn parameters(&self) -> &Parameters {
        &self.parameters
    }

    fn x0(&self) -> Vec<f64> {
        // The centre of the normalised box, as the reference starts.
        self.parameters
            .to_real(&vec![0.5; self.parameters.dim()])
            .unwrap_or_default()
    }

    fn build(&self, real: &[f64]) -> (SpringParams, BackboneOptions) {
        (Self::params(real), BackboneOptions::default())
    }
}
