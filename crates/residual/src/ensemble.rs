//! Ensembles of residual networks: several networks of one configuration (e.g. trained from
//! different seeds) that act as one. At every step each member computes its residual from the
//! same inputs, with its own temporal window, and the hybrid model adds their mean:
//! `Δv = (1/K) Σ_k Δv_k`. Each member's residual is bounded, so the mean is too.
//!
//! Networks trained on a few hundred recordings differ from seed to seed and from checkpoint to
//! checkpoint by as much as they gain over the backbone; averaging their predictions removes
//! the part of each one's error the others do not share. Measured (`docs/residual.md`,
//! "Ensembles"): four seeds lowered the sloth's val MDE by 0.6 % and DLO1's by 2.1 %; on the
//! rope, the paper, DLO2 and DLO3 they did not beat the best seed on held-out recordings.
//! An ensemble costs K network evaluations per step and cannot be trained as a whole: train
//! the members, then combine them with [`ResidualNet::ensemble`].
//!
//! [`EnsembleRule::Agreement`] (session 65) shrinks the mean where the members disagree, per
//! particle: `Δv = m |m|² / (|m|² + s²)`, with `m` the members' mean and `s²` their mean
//! squared distance from it. Members that agree keep their mean; members that point every
//! which way (inputs unlike their training data, e.g. a planner's own motions) leave the
//! backbone nearly alone. It has no parameter; the factor is in `[0, 1]`, so the bound holds.

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};

use crate::{ModelConfig, ResidualError, ResidualNet, Result};

/// Key of the member count in an ensemble's JSON (absent for a single network).
const MEMBERS_KEY: &str = "ensemble_members";
/// Key of the rule in an ensemble's JSON (absent for [`EnsembleRule::Mean`]).
const RULE_KEY: &str = "ensemble_rule";

/// How an ensemble turns its members' residuals into one (see the module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EnsembleRule {
    /// The members' mean.
    #[default]
    Mean,
    /// The members' mean, shrunk per particle by `|m|² / (|m|² + s²)`.
    Agreement,
}

impl ResidualNet {
    /// One model made of `nets` (at least one, all of one configuration): its residual is the
    /// mean of theirs, each member keeping its own temporal window. Members that are
    /// themselves ensembles are refused.
    ///
    /// ```
    /// use residual::{ModelConfig, ResidualNet};
    /// let cfg = ModelConfig::tiny();
    /// let a = ResidualNet::new(&cfg, 1)?;
    /// let b = ResidualNet::new(&cfg, 2)?;
    /// let both = ResidualNet::ensemble(vec![a, b])?;
    /// assert_eq!(both.ensemble_size(), 2);
    /// assert_eq!(both.config(), &cfg);
    /// let other = ModelConfig { residual_scale: 0.3, ..cfg.clone() };
    /// let c = ResidualNet::new(&other, 3)?;
    /// assert!(ResidualNet::ensemble(vec![both, c]).is_err());
    /// assert!(ResidualNet::ensemble(Vec::new()).is_err());
    /// # Ok::<(), residual::ResidualError>(())
    /// ```
    pub fn ensemble(nets: Vec<ResidualNet>) -> Result<ResidualNet> {
        let mut nets = nets.into_iter();
        let Some(mut first) = nets.next() else {
            return Err(ResidualError::Config(
                "an ensemble needs at least one network".into(),
            ));
        };
        let rest: Vec<ResidualNet> = nets.collect();
        single_networks_of_one_config(std::iter::once(&first).chain(&rest), "ensemble member")?;
        first.members = rest;
        Ok(first)
    }

    /// One network whose every parameter is the mean of the same parameter in `nets` (at least
    /// one, all single networks of one configuration): stochastic weight averaging (Izmailov
    /// et al., 2018). Unlike [`ResidualNet::ensemble`] it costs one network per step, but it is
    /// only meaningful for networks that lie in one basin, e.g. late snapshots of one training
    /// run; networks trained from different seeds differ by permutations of their units, and
    /// their average is not a network either of them resembles.
    ///
    /// ```
    /// use residual::{ModelConfig, ResidualNet};
    /// let cfg = ModelConfig::tiny();
    /// let a = ResidualNet::new(&cfg, 1)?;
    /// let b = ResidualNet::new(&cfg, 2)?;
    /// let avg = ResidualNet::average_weights(&[a, b])?;
    /// assert_eq!(avg.ensemble_size(), 1);
    /// assert_eq!(avg.config(), &cfg);
    /// assert!(ResidualNet::average_weights(&[]).is_err());
    /// # Ok::<(), residual::ResidualError>(())
    /// ```
    pub fn average_weights(nets: &[ResidualNet]) -> Result<ResidualNet> {
        let Some(first) = nets.first() else {
            return Err(ResidualError::Config(
                "weight averaging needs at least one network".into(),
            ));
        };
        single_networks_of_one_config(nets, "network")?;
        let avg = first.copy_as(first.config().clone(), false)?;
        let all: Vec<HashMap<String, candle_core::Var>> = nets
            .iter()
            .map(|n| n.named_vars().into_iter().collect())
            .collect();
        let scale = 1.0 / nets.len() as f64;
        for (name, var) in avg.named_vars() {
            let mut sum = var.as_tensor().zeros_like()?;
            for (k, vars) in all.iter().enumerate() {
                let t = vars.get(&name).ok_or_else(|| {
                    ResidualError::Config(format!("network {k} has no parameter {name}"))
                })?;
                sum = (sum + t.as_tensor())?;
            }
            var.set(&(sum * scale)?)?;
        }
        Ok(avg)
    }

    /// The same ensemble combining its members by `rule` (a single network is unaffected).
    ///
    /// ```
    /// use residual::{EnsembleRule, ModelConfig, ResidualNet};
    /// let cfg = ModelConfig::tiny();
    /// let pair = ResidualNet::ensemble(vec![ResidualNet::new(&cfg, 1)?, ResidualNet::new(&cfg, 2)?])?;
    /// assert_eq!(pair.ensemble_rule(), EnsembleRule::Mean);
    /// let cautious = pair.with_ensemble_rule(EnsembleRule::Agreement);
    /// assert_eq!(cautious.ensemble_rule(), EnsembleRule::Agreement);
    /// # Ok::<(), residual::ResidualError>(())
    /// ```
    pub fn with_ensemble_rule(mut self, rule: EnsembleRule) -> ResidualNet {
        self.rule = rule;
        self
    }

    /// How this ensemble combines its members' residuals.
    pub fn ensemble_rule(&self) -> EnsembleRule {
        self.rule
    }

    /// Number of networks whose residuals this model averages (1 for a single network).
    pub fn ensemble_size(&self) -> usize {
        1 + self.members.len()
    }

    /// Every member of this ensemble as a network of its own, in order (one copy for a single
    /// network): for callers that run each member on its own trajectory, e.g. a planner
    /// scoring a candidate by every member's prediction (`plan::Pgrd::with_member_trajectories`).
    /// Parameters are copied; the copies predict exactly what the member predicts alone.
    ///
    /// ```
    /// use residual::{ModelConfig, ResidualNet};
    /// let cfg = ModelConfig::tiny();
    /// let pair = ResidualNet::ensemble(vec![ResidualNet::new(&cfg, 1)?, ResidualNet::new(&cfg, 2)?])?;
    /// let alone = pair.split_ensemble()?;
    /// assert_eq!(alone.len(), 2);
    /// assert!(alone.iter().all(|m| m.ensemble_size() == 1 && m.config() == &cfg));
    /// # Ok::<(), residual::ResidualError>(())
    /// ```
    pub fn split_ensemble(&self) -> Result<Vec<ResidualNet>> {
        self.ensemble_members()
            .map(|m| m.copy_as(m.config().clone(), false))
            .collect()
    }

    /// This network and the other members of its ensemble, in order.
    pub(crate) fn ensemble_members(&self) -> impl Iterator<Item = &ResidualNet> {
        std::iter::once(self).chain(&self.members)
    }

    /// The same ensemble with `f` applied to every member.
    pub(crate) fn map_members(
        &self,
        f: impl Fn(&ResidualNet) -> Result<ResidualNet>,
    ) -> Result<ResidualNet> {
        let mut first = f(self)?;
        first.members = self.members.iter().map(f).collect::<Result<_>>()?;
        first.rule = self.rule;
        Ok(first)
    }

    /// [`ResidualNet::save`] of an ensemble: every member's parameters in one safetensors
    /// file under `member<k>.`, written beside and renamed into place, then the shared
    /// configuration with the member count.
    pub(crate) fn save_ensemble(&self, path: &Path) -> Result<()> {
        let mut tensors: HashMap<String, Tensor> = HashMap::new();
        for (k, m) in self.ensemble_members().enumerate() {
            for (name, var) in m.named_vars() {
                tensors.insert(format!("member{k}.{name}"), var.as_tensor().clone());
            }
        }
        crate::model::save_tensors_atomic(&tensors, path)?;
        let json = path.with_extension("json");
        let mut value =
            serde_json::to_value(self.config()).map_err(|source| ResidualError::Json {
                path: json.display().to_string(),
                cause: source,
            })?;
        if let Some(map) = value.as_object_mut() {
            map.insert(MEMBERS_KEY.into(), self.ensemble_size().into());
            if self.rule != EnsembleRule::Mean {
                let rule =
                    serde_json::to_value(self.rule).map_err(|source| ResidualError::Json {
                        path: json.display().to_string(),
                        cause: source,
                    })?;
                map.insert(RULE_KEY.into(), rule);
            }
        }
        let text = serde_json::to_string_pretty(&value).map_err(|source| ResidualError::Json {
            path: json.display().to_string(),
            cause: source,
        })?;
        dataset::write_atomic(&json, text.as_bytes()).map_err(ResidualError::Dataset)
    }

    /// [`ResidualNet::load`] of an ensemble of `members` networks of configuration `cfg`.
    pub(crate) fn load_ensemble(
        path: &Path,
        cfg: &ModelConfig,
        members: usize,
        rule: EnsembleRule,
    ) -> Result<Self> {
        let tensors = candle_core::safetensors::load(path, &Device::Cpu)?;
        let mut nets = Vec::with_capacity(members);
        for k in 0..members {
            let net = ResidualNet::new(cfg, 0)?;
            for (name, var) in net.named_vars() {
                let key = format!("member{k}.{name}");
                let t = tensors.get(&key).ok_or_else(|| {
                    ResidualError::Input(format!("{}: no tensor {key}", path.display()))
                })?;
                var.set(t)?;
            }
            nets.push(net);
        }
        Ok(ResidualNet::ensemble(nets)?.with_ensemble_rule(rule))
    }
}

/// Refuses networks that are themselves ensembles or whose configuration differs from the
/// first one's (`what` names them in the error: "ensemble member", "network").
fn single_networks_of_one_config<'a>(
    nets: impl IntoIterator<Item = &'a ResidualNet>,
    what: &str,
) -> Result<()> {
    let mut first: Option<&ModelConfig> = None;
    for (k, net) in nets.into_iter().enumerate() {
        if !net.members.is_empty() {
            return Err(ResidualError::Config(format!(
                "{what} {k} is itself an ensemble of {}",
                net.ensemble_size()
            )));
        }
        let cfg = *first.get_or_insert(net.config());
        if net.config() != cfg {
            return Err(ResidualError::Config(format!(
                "{what} {k} has another configuration than {what} 0 \
                 (they must share encoder, inputs, window and bound)"
            )));
        }
    }
    Ok(())
}

/// What a saved network's JSON holds besides its configuration.
pub(crate) struct SavedEnsemble {
    /// Member count (1 for a single network).
    pub members: usize,
    pub rule: EnsembleRule,
}

/// The configuration, member count and rule of a saved network's JSON.
pub(crate) fn parse_saved_config(
    text: &str,
) -> std::result::Result<(ModelConfig, SavedEnsemble), serde_json::Error> {
    let mut value: serde_json::Value = serde_json::from_str(text)?;
    let mut take = |key: &str| value.as_object_mut().and_then(|m| m.remove(key));
    let members = take(MEMBERS_KEY)
        .map(serde_json::from_value::<usize>)
        .transpose()?
        .unwrap_or(1);
    let rule = take(RULE_KEY)
        .map(serde_json::from_value::<EnsembleRule>)
        .transpose()?
        .unwrap_or_default();
    Ok((
        serde_json::from_value(value)?,
        SavedEnsemble { members, rule },
    ))
}

/// The members' residuals `(N, 3)` combined by `rule` (the one residual itself, untouched, for
/// one member).
pub(crate) fn combine(deltas: Vec<Tensor>, rule: EnsembleRule) -> Result<Tensor> {
    let k = deltas.len();
    if k == 1 {
        return deltas
            .into_iter()
            .next()
            .ok_or_else(|| ResidualError::Input("an ensemble without members".into()));
    }
    let mean = mean(&deltas)?;
    match rule {
        EnsembleRule::Mean => Ok(mean),
        EnsembleRule::Agreement => {
            let mut spread = mean.zeros_like()?;
            for d in &deltas {
                spread = (spread + (d - &mean)?.sqr()?)?;
            }
            let spread = (spread.sum_keepdim(1)? / k as f64)?;
            let size = mean.sqr()?.sum_keepdim(1)?;
            // Where mean and spread are both 0 the mean is 0 too; any factor gives 0 then.
            let total = (&size + spread)?.maximum(f64::from(f32::MIN_POSITIVE))?;
            Ok(mean.broadcast_mul(&(size / total)?)?)
        }
    }
}

/// The members' mean residual.
fn mean(deltas: &[Tensor]) -> Result<Tensor> {
    let (first, rest) = deltas
        .split_first()
        .ok_or_else(|| ResidualError::Input("an ensemble without members".into()))?;
    let sum = rest.iter().try_fold(first.clone(), |s, d| s + d)?;
    Ok((sum / deltas.len() as f64)?)
}

/// [`combine`] on flat rows `[x, y, z, x, y, z, ...]`, one vector per member.
pub(crate) fn combine_rows(deltas: Vec<Vec<f32>>, rule: EnsembleRule) -> Vec<f32> {
    let k = deltas.len();
    let mut it = deltas.iter();
    let Some(first) = it.next() else {
        return Vec::new();
    };
    let mut mean = first.clone();
    for d in it {
        mean.iter_mut().zip(d).for_each(|(s, x)| *s += x);
    }
    if k == 1 {
        return mean;
    }
    mean.iter_mut().for_each(|s| *s /= k as f32);
    if rule == EnsembleRule::Agreement {
        for (i, m) in mean.chunks_exact_mut(3).enumerate() {
            let mut spread = 0.0f32;
            for axis in 0..3 {
                let mut s = 0.0f32;
                for d in &deltas {
                    s += (d[3 * i + axis] - m[axis]).powi(2);
                }
                spread += s;
            }
            let spread = spread / k as f32;
            let size: f32 = m.iter().map(|x| x * x).sum();
            let factor = size / (size + spread).max(f32::MIN_POSITIVE);
            m.iter_mut().for_each(|x| *x *= factor);
        }
    }
    mean
}
