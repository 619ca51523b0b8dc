//! Mapping between the optimiser's normalised `[0, 1]^n` and real parameter values.

use serde::{Deserialize, Serialize};

use crate::config::check_len;
use crate::{Bounds, CmaesConfig, Error, exact};

/// Floor on the sampling standard deviation of an integer parameter, as a fraction of the
/// (smallest) normalised width of one integer step: at 0.25 a step to a neighbouring integer is
/// still tried by ~5 % of the samples once the search has otherwise converged.
pub const INTEGER_STD_FRACTION: f64 = 0.25;

/// How a normalised coordinate `u ∈ [0, 1]` maps onto `[lower, upper]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Scale {
    /// `lower + u (upper - lower)`.
    Linear,
    /// `lower (upper / lower)^u`, for positive quantities spanning orders of magnitude
    /// (stiffness, damping); needs `lower > 0`.
    Log,
}

/// One optimised quantity: its name, range, scale and whether it takes integer values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Parameter {
    /// Name, for error messages and reports (e.g. `"stiffness"`, with its unit in the docs).
    pub name: String,
    /// Smallest value (real units).
    #[serde(with = "exact::scalar")]
    pub lower: f64,
    /// Largest value (real units).
    #[serde(with = "exact::scalar")]
    pub upper: f64,
    /// Linear or logarithmic mapping.
    pub scale: Scale,
    /// Round to the nearest integer on evaluation.
    pub integer: bool,
}

impl Parameter {
    /// A continuous parameter on a linear scale.
    pub fn linear(name: impl Into<String>, lower: f64, upper: f64) -> Self {
        Self {
            name: name.into(),
            lower,
            upper,
            scale: Scale::Linear,
            integer: false,
        }
    }

    /// A continuous parameter on a logarithmic scale (`lower > 0`).
    pub fn log(name: impl Into<String>, lower: f64, upper: f64) -> Self {
        Self {
            scale: Scale::Log,
            ..Self::linear(name, lower, upper)
        }
    }

    /// The same parameter, rounded to integers on evaluation.
    pub fn integer(self) -> Self {
        Self {
            integer: true,
            ..self
        }
    }

    fn validate(&self) -> Result<(), Error> {
        let fail = |reason: String| {
            Err(Error::InvalidParameter {
                name: self.name.clone(),
                reason,
            })
        };
        if !(self.lower.is_finite() && self.upper.is_finite() && self.lower < self.upper) {
            return fail(format!(
                "bounds must be finite with lower < upper, got [{}, {}]",
                self.lower, self.upper
            ));
        }
        if self.scale == Scale::Log && self.lower <= 0.0 {
            return fail(format!("a log scale needs lower > 0, got {}", self.lower));
        }
        if self.integer && self.lower.ceil() > self.upper.floor() {
            return fail(format!(
                "no integer lies in [{}, {}]",
                self.lower, self.upper
            ));
        }
        Ok(())
    }

    /// Real value of the normalised coordinate `u` (clamped to `[0, 1]`), rounded if integer.
    fn to_real(&self, u: f64) -> f64 {
        let u = u.clamp(0.0, 1.0);
        let v = if u == 1.0 {
            // Exact endpoint; the formulas below may miss it by an ulp.
            self.upper
        } else {
            match self.scale {
                Scale::Linear => self.lower + u * (self.upper - self.lower),
                Scale::Log => self.lower * (self.upper / self.lower).powf(u),
            }
        };
        // Rounding in the power can overshoot a bound by an ulp.
        let v = v.clamp(self.lower, self.upper);
        if self.integer {
            v.round().clamp(self.lower.ceil(), self.upper.floor())
        } else {
            v
        }
    }

    fn to_normalised(&self, v: f64) -> f64 {
        let u = match self.scale {
            Scale::Linear => (v - self.lower) / (self.upper - self.lower),
            Scale::Log => (v / self.lower).ln() / (self.upper / self.lower).ln(),
        };
        u.clamp(0.0, 1.0)
    }

    /// Smallest normalised width of one integer step over the range (0 when only one integer
    /// fits): uniform on a linear scale, narrowest at the top of a log scale.
    fn integer_step(&self) -> f64 {
        let (lo, hi) = (self.lower.ceil(), self.upper.floor());
        if !self.integer || hi <= lo {
            return 0.0;
        }
        match self.scale {
            Scale::Linear => 1.0 / (self.upper - self.lower),
            Scale::Log => (hi / (hi - 1.0)).ln() / (self.upper / self.lower).ln(),
        }
    }
}

/// An ordered set of [`Parameter`]s: the bridge between CMA-ES's unit cube and a model.
///
/// ```
/// use cmaes::{Parameter, Parameters};
///
/// let params = Parameters::new(vec![
///     Parameter::log("stiffness", 10.0, 5e4),
///     Parameter::linear("max_springs", 4.0, 200.0).integer(),
/// ])?;
/// let real = params.to_real(&[0.5, 0.5])?;
/// assert!((real[0] - (10.0_f64 * 5e4).sqrt()).abs() < 1e-9); // geometric midpoint
/// assert_eq!(real[1], 102.0); // rounded
/// let config = params.cmaes_config(&[1000.0, 50.0], 0.2, 7)?;
/// assert_eq!(config.dim(), 2);
/// # Ok::<(), cmaes::Error>(())
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Parameters {
    params: Vec<Parameter>,
}

impl Parameters {
    /// Validates every parameter (finite range, positive lower bound for log scales, at least
    /// one integer in the range of integer parameters).
    pub fn new(params: Vec<Parameter>) -> Result<Self, Error> {
        if params.is_empty() {
            return Err(Error::InvalidConfig("no parameters given".into()));
        }
        for p in &params {
            p.validate()?;
        }
        Ok(Self { params })
    }

    /// Number of parameters (the CMA-ES dimension).
    pub fn dim(&self) -> usize {
        self.params.len()
    }

    /// The parameters, in order.
    pub fn params(&self) -> &[Parameter] {
        &self.params
    }

    /// Real values of a normalised point. Coordinates outside `[0, 1]` are clamped (with
    /// [`Bounds::unit`] the optimiser never produces any); integer parameters are rounded to
    /// the nearest integer inside their range. NaN coordinates are an error.
    pub fn to_real(&self, normalised: &[f64]) -> Result<Vec<f64>, Error> {
        check_len("normalised point", self.dim(), normalised.len())?;
        self.params
            .iter()
            .zip(normalised)
            .map(|(p, &u)| {
                if u.is_nan() {
                    Err(Error::InvalidParameter {
                        name: p.name.clone(),
                        reason: "normalised coordinate is NaN".into(),
                    })
                } else {
                    Ok(p.to_real(u))
                }
            })
            .collect()
    }

    /// Normalised coordinates of real values; values outside a parameter's range are an error.
    pub fn to_normalised(&self, real: &[f64]) -> Result<Vec<f64>, Error> {
        check_len("real point", self.dim(), real.len())?;
        self.params
            .iter()
            .zip(real)
            .map(|(p, &v)| {
                if v >= p.lower && v <= p.upper {
                    Ok(p.to_normalised(v))
                } else {
                    Err(Error::InvalidParameter {
                        name: p.name.clone(),
                        reason: format!("value {v} lies outside [{}, {}]", p.lower, p.upper),
                    })
                }
            })
            .collect()
    }

    /// Per-coordinate floor on the normalised sampling standard deviation:
    /// [`INTEGER_STD_FRACTION`] of one integer step for integer parameters, 0 otherwise.
    pub fn min_std(&self) -> Vec<f64> {
        self.params
            .iter()
            .map(|p| INTEGER_STD_FRACTION * p.integer_step())
            .collect()
    }

    /// A CMA-ES configuration on the unit cube starting at the real point `x0_real`, with
    /// normalised step size `sigma0` (e.g. 0.2), the given seed, [`Bounds::unit`] and the
    /// integer floor from [`Parameters::min_std`]. Adjust population and termination after.
    pub fn cmaes_config(
        &self,
        x0_real: &[f64],
        sigma0: f64,
        seed: u64,
    ) -> Result<CmaesConfig, Error> {
        let mut config = CmaesConfig::new(self.to_normalised(x0_real)?, sigma0);
        config.seed = seed;
        config.bounds = Some(Bounds::unit(self.dim()));
        config.min_std = if self.params.iter().any(|p| p.integer) {
            self.min_std()
        } else {
            Vec::new()
        };
        config.validate()?;
        Ok(config)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_and_log_endpoints_and_midpoints() {
        let p = Parameters::new(vec![
            Parameter::linear("a", -1.0, 3.0),
            Parameter::log("b", 1e-2, 1e2),
        ])
        .unwrap();
        assert_eq!(p.to_real(&[0.0, 0.0]).unwrap(), vec![-1.0, 1e-2]);
        assert_eq!(p.to_real(&[1.0, 1.0]).unwrap(), vec![3.0, 1e2]);
        let mid = p.to_real(&[0.5, 0.5]).unwrap();
        assert!((mid[0] - 1.0).abs() < 1e-15);
        assert!((mid[1] - 1.0).abs() < 1e-12);
        assert_eq!(p.to_real(&[-0.5, 7.0]).unwrap(), vec![-1.0, 1e2]);
    }

    #[test]
    fn integer_parameters_round_inside_their_range() {
        let p = Parameters::new(vec![Parameter::linear("k", 3.5, 10.2).integer()]).unwrap();
        assert_eq!(p.to_real(&[0.0]).unwrap(), vec![4.0]);
        assert_eq!(p.to_real(&[1.0]).unwrap(), vec![10.0]);
        // 3.5 + 0.3 * 6.7 = 5.51 -> 6
        assert_eq!(p.to_real(&[0.3]).unwrap(), vec![6.0]);
        assert!((p.min_std()[0] - INTEGER_STD_FRACTION / 6.7).abs() < 1e-15);
    }

    #[test]
    fn bad_parameters_and_points_are_errors() {
        assert!(Parameters::new(vec![]).is_err());
        assert!(Parameters::new(vec![Parameter::log("x", 0.0, 1.0)]).is_err());
        assert!(Parameters::new(vec![Parameter::linear("x", 1.0, 1.0)]).is_err());
        assert!(Parameters::new(vec![Parameter::linear("x", 0.2, 0.8).integer()]).is_err());
        let p = Parameters::new(vec![Parameter::linear("x", 0.0, 1.0)]).unwrap();
        assert!(p.to_real(&[0.5, 0.5]).is_err());
        assert!(p.to_real(&[f64::NAN]).is_err());
        assert!(p.to_normalised(&[1.5]).is_err());
        assert!(p.to_normalised(&[f64::NAN]).is_err());
    }
}
