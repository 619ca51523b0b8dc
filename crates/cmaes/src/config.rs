//! Run configuration: start point, step size, population, bounds and stopping rules.

use serde::{Deserialize, Serialize};

use crate::Error;
use crate::exact;

/// An axis-aligned box `lower[i] <= x[i] <= upper[i]` in the optimiser's coordinates.
///
/// With [`crate::Parameters`] the box is the unit cube `[0, 1]^n` ([`Bounds::unit`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    /// Lower bound per coordinate.
    #[serde(with = "exact::vec")]
    pub lower: Vec<f64>,
    /// Upper bound per coordinate (strictly greater than the lower bound).
    #[serde(with = "exact::vec")]
    pub upper: Vec<f64>,
}

impl Bounds {
    /// The unit cube `[0, 1]^dim`.
    pub fn unit(dim: usize) -> Self {
        Self {
            lower: vec![0.0; dim],
            upper: vec![1.0; dim],
        }
    }

    /// Maps an unconstrained point into the box by mirroring at the faces (period `2 (upper -
    /// lower)` per coordinate), so that a step across a face comes back in as if reflected.
    ///
    /// Mirroring is continuous and piecewise linear: nearby genotypes stay nearby candidates,
    /// which keeps the ranking information CMA-ES learns from meaningful near a bound, and
    /// optima on a face are reachable exactly.
    pub fn reflect(&self, x: &[f64]) -> Vec<f64> {
        x.iter()
            .zip(self.lower.iter().zip(&self.upper))
            .map(|(&v, (&lo, &hi))| {
                let width = hi - lo;
                if !v.is_finite() {
                    // Cannot happen before a stop criterion fires; keep candidates finite anyway.
                    return lo + 0.5 * width;
                }
                let t = (v - lo).rem_euclid(2.0 * width);
                let folded = if t > width { 2.0 * width - t } else { t };
                (lo + folded).clamp(lo, hi)
            })
            .collect()
    }

    pub(crate) fn validate(&self, dim: usize) -> Result<(), Error> {
        check_len("bounds.lower", dim, self.lower.len())?;
        check_len("bounds.upper", dim, self.upper.len())?;
        for (i, (&lo, &hi)) in self.lower.iter().zip(&self.upper).enumerate() {
            if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                return Err(Error::InvalidConfig(format!(
                    "bounds of coordinate {i} must be finite with lower < upper, got [{lo}, {hi}]"
                )));
            }
        }
        Ok(())
    }
}

/// When a run stops. Every criterion is checked after each [`crate::CmaEs::tell`].
///
/// The tolerance defaults follow pycma 4.x's documented defaults (`tolfun = tolx = 1e-11`,
/// condition limit 1e14, `tolupsigma = 1e20`, stagnation after `100 + 100 n^1.5 / λ`
/// generations), so a run with `target` set ends like a pycma run with `ftarget`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Termination {
    /// Stop once the best fitness is `<= target` ([`crate::StopReason::TargetReached`]).
    #[serde(with = "exact::opt")]
    pub target: Option<f64>,
    /// Stop once at least this many candidates were evaluated (checked after whole
    /// generations, so a run may exceed it by up to `population - 1`).
    pub max_evaluations: Option<u64>,
    /// Stop after this many generations.
    pub max_generations: Option<u64>,
    /// Stop when the best fitness of the last `10 + ⌈30 n / λ⌉` generations and all fitness
    /// values of the current one lie within this range.
    #[serde(with = "exact::scalar")]
    pub tol_fun: f64,
    /// Stop when every coordinate's sampling standard deviation `σ √C_ii` and every component
    /// of `σ p_c` is below this (same units as the coordinates).
    #[serde(with = "exact::scalar")]
    pub tol_x: f64,
    /// Stop when the condition number of `C` exceeds this.
    #[serde(with = "exact::scalar")]
    pub max_condition: f64,
    /// Stop when `σ · max √eig(C) / σ₀` exceeds this (divergence).
    #[serde(with = "exact::scalar")]
    pub tol_up_sigma: f64,
    /// Enable the stagnation test: over a window of `100 + 100 n^1.5 / λ` generations, the
    /// median of the 20 newest generation-best and generation-median values is no better than
    /// that of the 20 oldest ones.
    pub stagnation: bool,
}

impl Default for Termination {
    fn default() -> Self {
        Self {
            target: None,
            max_evaluations: None,
            max_generations: None,
            tol_fun: 1e-11,
            tol_x: 1e-11,
            max_condition: 1e14,
            tol_up_sigma: 1e20,
            stagnation: true,
        }
    }
}

impl Termination {
    fn validate(&self) -> Result<(), Error> {
        if let Some(t) = self.target
            && t.is_nan()
        {
            return Err(Error::InvalidConfig("termination.target is NaN".into()));
        }
        for (name, v) in [
            ("termination.tol_fun", self.tol_fun),
            ("termination.tol_x", self.tol_x),
        ] {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(Error::InvalidConfig(format!(
                    "{name} must be finite and >= 0, got {v}"
                )));
            }
        }
        for (name, v) in [
            ("termination.max_condition", self.max_condition),
            ("termination.tol_up_sigma", self.tol_up_sigma),
        ] {
            if v.is_nan() || v <= 1.0 {
                return Err(Error::InvalidConfig(format!("{name} must be > 1, got {v}")));
            }
        }
        Ok(())
    }
}

/// Everything a [`crate::CmaEs`] run needs. The search dimension is `x0.len()`.
///
/// ```
/// use cmaes::CmaesConfig;
/// let mut config = CmaesConfig::new(vec![0.5; 4], 0.2);
/// config.seed = 7;
/// config.population = Some(8);
/// assert_eq!(config.dim(), 4);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CmaesConfig {
    /// Initial mean (inside `bounds` when those are set).
    #[serde(with = "exact::vec")]
    pub x0: Vec<f64>,
    /// Initial step size σ₀ (coordinate units; for the normalised `[0, 1]` space about a
    /// quarter of the range is a good default).
    #[serde(with = "exact::scalar")]
    pub sigma0: f64,
    /// Population size λ; `None` uses the default `4 + ⌊3 ln n⌋`.
    pub population: Option<usize>,
    /// Seed for all random numbers of the run.
    pub seed: u64,
    /// Optional box; candidates are mirrored into it (see [`Bounds::reflect`]).
    pub bounds: Option<Bounds>,
    /// Per-coordinate lower limit on the sampling standard deviation `σ √C_ii` (empty: none).
    ///
    /// Used for integer parameters: once the search narrows below one integer step, rounding
    /// makes the fitness flat along that coordinate and the variance would collapse; a floor
    /// keeps neighbouring integers being tried. [`crate::Parameters::cmaes_config`] fills this.
    #[serde(with = "exact::vec")]
    pub min_std: Vec<f64>,
    /// Stopping rules.
    pub termination: Termination,
}

impl CmaesConfig {
    /// A configuration with default population, seed 0, no bounds, no standard-deviation floor
    /// and default [`Termination`].
    pub fn new(x0: Vec<f64>, sigma0: f64) -> Self {
        Self {
            x0,
            sigma0,
            population: None,
            seed: 0,
            bounds: None,
            min_std: Vec::new(),
            termination: Termination::default(),
        }
    }

    /// The search dimension `n`.
    pub fn dim(&self) -> usize {
        self.x0.len()
    }

    /// The population size λ this configuration runs with.
    pub fn population_size(&self) -> usize {
        self.population
            .unwrap_or_else(|| default_population(self.dim()))
    }

    /// Checks every field; called by [`crate::CmaEs::new`].
    pub fn validate(&self) -> Result<(), Error> {
        let n = self.dim();
        if n == 0 {
            return Err(Error::InvalidConfig(
                "x0 is empty: the search space needs at least one dimension".into(),
            ));
        }
        if let Some(i) = self.x0.iter().position(|v| !v.is_finite()) {
            return Err(Error::InvalidConfig(format!(
                "x0[{i}] = {} is not finite",
                self.x0[i]
            )));
        }
        if !(self.sigma0 > 0.0 && self.sigma0.is_finite()) {
            return Err(Error::InvalidConfig(format!(
                "sigma0 must be finite and > 0, got {}",
                self.sigma0
            )));
        }
        if let Some(p) = self.population
            && !(2..=MAX_POPULATION).contains(&p)
        {
            return Err(Error::InvalidConfig(format!(
                "population must be between 2 and {MAX_POPULATION}, got {p}"
            )));
        }
        if let Some(b) = &self.bounds {
            b.validate(n)?;
            for (i, ((&x, &lo), &hi)) in self.x0.iter().zip(&b.lower).zip(&b.upper).enumerate() {
                if x < lo || x > hi {
                    return Err(Error::InvalidConfig(format!(
                        "x0[{i}] = {x} lies outside the bounds [{lo}, {hi}]"
                    )));
                }
            }
        }
        if !self.min_std.is_empty() {
            check_len("min_std", n, self.min_std.len())?;
            if let Some(i) = self
                .min_std
                .iter()
                .position(|v| !(v.is_finite() && *v >= 0.0))
            {
                return Err(Error::InvalidConfig(format!(
                    "min_std[{i}] = {} must be finite and >= 0",
                    self.min_std[i]
                )));
            }
        }
        self.termination.validate()
    }
}

/// The largest population [`CmaesConfig::validate`] accepts: far beyond any use (pycma's
/// restarts with growing populations reach a few thousand), and small enough that a typo such
/// as `--population 18446744073709551615` is an error rather than an allocation failure.
pub const MAX_POPULATION: usize = 100_000;

/// pycma's and Hansen's default population size `4 + ⌊3 ln n⌋`.
pub fn default_population(dim: usize) -> usize {
    4 + (3.0 * (dim.max(1) as f64).ln()).floor() as usize
}

pub(crate) fn check_len(what: &'static str, expected: usize, got: usize) -> Result<(), Error> {
    if expected == got {
        Ok(())
    } else {
        Err(Error::LengthMismatch {
            what,
            expected,
            got,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflection_folds_back_into_the_box() {
        let b = Bounds::unit(1);
        let cases = [
            (0.3, 0.3),
            (-0.2, 0.2),
            (1.25, 0.75),
            (2.1, 0.1),
            (-1.7, 0.3),
            (0.0, 0.0),
            (1.0, 1.0),
            (4.0, 0.0),
        ];
        for (x, expected) in cases {
            let y = b.reflect(&[x])[0];
            assert!(
                (y - expected).abs() < 1e-12,
                "{x} -> {y}, expected {expected}"
            );
        }
    }

    #[test]
    fn default_population_matches_formula() {
        assert_eq!(default_population(10), 10);
        assert_eq!(default_population(5), 8);
        assert_eq!(default_population(1), 4);
    }

    #[test]
    fn invalid_configs_are_rejected() {
        let ok = CmaesConfig::new(vec![0.5; 3], 0.3);
        assert!(ok.validate().is_ok());
        let mut c = ok.clone();
        c.x0.clear();
        assert!(c.validate().is_err());
        let mut c = ok.clone();
        c.sigma0 = -1.0;
        assert!(c.validate().is_err());
        let mut c = ok.clone();
        c.population = Some(1);
        assert!(c.validate().is_err());
        let mut c = ok.clone();
        c.bounds = Some(Bounds::unit(2));
        assert!(matches!(c.validate(), Err(Error::LengthMismatch { .. })));
        let mut c = ok.clone();
        c.bounds = Some(Bounds::unit(3));
        c.x0[1] = 1.5;
        assert!(c.validate().is_err());
        let mut c = ok.clone();
        c.min_std = vec![0.1; 2];
        assert!(c.validate().is_err());
        let mut c = ok;
        c.termination.tol_x = f64::NAN;
        assert!(c.validate().is_err());
    }
}
