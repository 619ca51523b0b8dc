//! Base effects: library effects already part of the model, refitted with the backbone.

use serde::{Deserialize, Serialize};

use crate::GapError;
use crate::candidates::Candidate;

/// A library effect already part of the model (a *base effect*), e.g. the verdict of an earlier
/// diagnosis. It is refitted together with the backbone's continuous parameters in the control
/// and in every candidate refit, starting from `values`, and is not itself a candidate.
///
/// ```
/// use gap::{BaseEffect, Candidate};
/// let b = BaseEffect::parse("bending=0.12")?;
/// assert_eq!(b.effect, Candidate::Bending);
/// assert_eq!(b.values, vec![0.12]);
/// // Without values the effect starts at its usual starting strength.
/// assert_eq!(BaseEffect::parse("drag")?.values, Candidate::Drag.start());
/// // Two values are separated by ':'.
/// let list = BaseEffect::parse_list("bending=0.1,plasticity=0.02:5")?;
/// assert_eq!(list[1].values, vec![0.02, 5.0]);
/// assert!(BaseEffect::parse("bending=7").is_err()); // outside [1e-3, 1]
/// # Ok::<(), gap::GapError>(())
/// ```
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BaseEffect {
    /// The library effect.
    pub effect: Candidate,
    /// Its parameter values where the refits start, in the order of
    /// [`Candidate::parameters`] (units there).
    pub values: Vec<f64>,
}

impl BaseEffect {
    /// A base effect at `values`; checked against the effect's parameter count and ranges. The
    /// generic probe (`external-field`) cannot be a base effect: it stands for "no library
    /// effect".
    pub fn new(effect: Candidate, values: Vec<f64>) -> Result<Self, GapError> {
        if effect == Candidate::ExternalField {
            return Err(GapError::Config(
                "external-field is the probe for unknown gaps, not a base effect".into(),
            ));
        }
        let params = effect.parameters();
        if values.len() != params.len() {
            return Err(GapError::Config(format!(
                "{} takes {} value(s), got {}",
                effect.name(),
                params.len(),
                values.len()
            )));
        }
        let mut values = values;
        for (p, v) in params.iter().zip(values.iter_mut()) {
            // Refitted values come back through exp/ln and may overshoot a bound by an ulp.
            let slack = 1e-9 * p.lower.abs().max(p.upper.abs()).max(1.0);
            if !(v.is_finite() && *v >= p.lower - slack && *v <= p.upper + slack) {
                return Err(GapError::Config(format!(
                    "{} {} = {v} lies outside [{}, {}]",
                    effect.name(),
                    p.name,
                    p.lower,
                    p.upper
                )));
            }
            *v = v.clamp(p.lower, p.upper);
        }
        Ok(BaseEffect { effect, values })
    }

    /// The effect at its starting strength ([`Candidate::start`]).
    pub fn at_start(effect: Candidate) -> Result<Self, GapError> {
        BaseEffect::new(effect, effect.start())
    }

    /// Parses `name` or `name=v1[:v2]` (values in the order and units of
    /// [`Candidate::parameters`]).
    pub fn parse(spec: &str) -> Result<Self, GapError> {
        let (name, values) = match spec.split_once('=') {
            Some((n, v)) => (n.trim(), Some(v)),
            None => (spec.trim(), None),
        };
        let effect = Candidate::parse(name)?;
        match values {
            None => BaseEffect::at_start(effect),
            Some(v) => {
                let values = v
                    .split(':')
                    .map(|x| {
                        x.trim().parse::<f64>().map_err(|_| {
                            GapError::Config(format!("'{x}' in '{spec}' is not a number"))
                        })
                    })
                    .collect::<Result<Vec<_>, _>>()?;
                BaseEffect::new(effect, values)
            }
        }
    }

    /// Parses a comma-separated list of [`BaseEffect::parse`] specs; an effect may appear once.
    pub fn parse_list(spec: &str) -> Result<Vec<Self>, GapError> {
        let list = spec
            .split(',')
            .filter(|s| !s.trim().is_empty())
            .map(BaseEffect::parse)
            .collect::<Result<Vec<_>, _>>()?;
        check_distinct(&list, None)?;
        Ok(list)
    }

    /// `name=v1[:v2]` with 9 significant digits, the form [`BaseEffect::parse`] reads back.
    pub fn label(&self) -> String {
        let v: Vec<String> = self
            .values
            .iter()
            // 9 digits stay within the 1e-9 relative slack `new` allows at a bound.
            .map(|v| {
                format!("{v:.8e}")
                    .parse::<f64>()
                    .map_or_else(|_| v.to_string(), |r| r.to_string())
            })
            .collect();
        format!("{}={}", self.effect.name(), v.join(":"))
    }
}

/// Errors if an effect appears twice among `base`, or `candidate` is one of them.
pub(crate) fn check_distinct(
    base: &[BaseEffect],
    candidate: Option<Candidate>,
) -> Result<(), GapError> {
    for (i, b) in base.iter().enumerate() {
        if base[..i].iter().any(|o| o.effect == b.effect) {
            return Err(GapError::Config(format!(
                "base effect {} is listed twice",
                b.effect.name()
            )));
        }
        if candidate == Some(b.effect) {
            return Err(GapError::Config(format!(
                "{} is already a base effect and cannot also be a candidate",
                b.effect.name()
            )));
        }
    }
    Ok(())
}

/// Backbone options carrying `effects` at their values, in order (for a model that keeps the
/// effects a diagnosis found: evaluation, residual training). `frame` places the particles on
/// the object for the effects that vary along it ([`crate::material_frame`] of the training
/// scenes the values were fitted on).
///
/// ```
/// use gap::{BaseEffect, MaterialFrame};
/// use glam::Vec3;
/// let frame = MaterialFrame::new(&[Vec3::ZERO, Vec3::X], Vec3::new(0.5, 0.0, 0.0))?;
/// let effects = BaseEffect::parse_list("drag=0.9,bending=0.1")?;
/// let options = gap::backbone_options(&effects, &frame);
/// assert_eq!(options.effects.len(), 2);
/// assert!(options.masses.is_none());
/// # Ok::<(), gap::GapError>(())
/// ```
pub fn backbone_options(
    effects: &[BaseEffect],
    frame: &crate::MaterialFrame,
) -> springs::BackboneOptions {
    springs::BackboneOptions {
        effects: crate::candidates::compose(
            effects.iter().map(|b| (b.effect, &b.values[..])),
            frame,
        ),
        ..Default::default()
    }
}
