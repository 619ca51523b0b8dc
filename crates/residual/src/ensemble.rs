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

use std::collections::HashMap;
use std::path::Path;

use candle_core::{Device, Tensor};

use crate::{ModelConfig, ResidualError, ResidualNet, Result};

/// Key of the member count in an ensemble's JSON (absent for a single network).
const MEMBERS_KEY: &str = "ensemble_members";

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
        for (k, net) in std::iter::once(&first).chain(&rest).enumerate() {
            if !net.members.is_empty() {
                return Err(ResidualError::Config(format!(
                    "ensemble member {k} is itself an ensemble of {}",
                    net.ensemble_size()
                )));
            }
            if net.config() != first.config() {
                return Err(ResidualError::Config(format!(
                    "ensemble member {k} has another configuration than member 0 \
                     (members must share encoder, inputs, window and bound)"
                )));
            }
        }
        first.members = rest;
        Ok(first)
    }

    /// Number of networks whose residuals this model averages (1 for a single network).
    pub fn ensemble_size(&self) -> usize {
        1 + self.members.len()
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
                source,
            })?;
        if let Some(map) = value.as_object_mut() {
            map.insert(MEMBERS_KEY.into(), self.ensemble_size().into());
        }
        let text = serde_json::to_string_pretty(&value).map_err(|source| ResidualError::Json {
            path: json.display().to_string(),
            source,
        })?;
        dataset::write_atomic(&json, text.as_bytes()).map_err(ResidualError::Dataset)
    }

    /// [`ResidualNet::load`] of an ensemble of `members` networks of configuration `cfg`.
    pub(crate) fn load_ensemble(path: &Path, cfg: &ModelConfig, members: usize) -> Result<Self> {
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
        ResidualNet::ensemble(nets)
    }
}

/// The configuration and member count (1 for a single network) of a saved network's JSON.
pub(crate) fn parse_saved_config(
    text: &str,
) -> std::result::Result<(ModelConfig, usize), serde_json::Error> {
    let mut value: serde_json::Value = serde_json::from_str(text)?;
    let members = value
        .as_object_mut()
        .and_then(|m| m.remove(MEMBERS_KEY))
        .map(serde_json::from_value::<usize>)
        .transpose()?
        .unwrap_or(1);
    Ok((serde_json::from_value(value)?, members))
}

/// The mean of the members' residuals (the one residual itself, untouched, for one member).
pub(crate) fn mean(deltas: Vec<Tensor>) -> Result<Tensor> {
    let k = deltas.len();
    let mut it = deltas.into_iter();
    let first = it
        .next()
        .ok_or_else(|| ResidualError::Input("an ensemble without members".into()))?;
    if k == 1 {
        return Ok(first);
    }
    let sum = it.try_fold(first, |s, d| s + d)?;
    Ok((sum / k as f64)?)
}
