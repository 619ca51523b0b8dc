//! The command line both examples share: `<data-dir> <run-dir> [paper|deform] [more…]`, and the
//! run's plain backbone.
// Each example compiles this module on its own and reads only some of the fields.
#![allow(dead_code)]

use std::path::PathBuf;

use dataset::{Dataset, Split};
use residual::TrainSet;
use scene::{Protocol, SceneConfig};

pub type Error = Box<dyn std::error::Error>;

/// A dataset, a run directory and the fitted parameters of its backbone.
pub struct Inputs {
    pub data_dir: String,
    pub data: Dataset,
    pub run: PathBuf,
    pub protocol: Protocol,
    pub params: springs::SpringParams,
    /// The arguments after the protocol.
    pub rest: Vec<String>,
}

/// Reads the command line (`usage` is the message for a wrong one) and the run's
/// `backbone.json`; backbones with library effects are refused.
pub fn inputs(usage: &str) -> Result<Inputs, Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (Some(data_dir), Some(run)) = (args.first(), args.get(1)) else {
        return Err(usage.into());
    };
    let protocol = match args.get(2).map(String::as_str) {
        None | Some("paper") => Protocol::Paper,
        Some("deform") => Protocol::Deform,
        Some(p) => return Err(format!("unknown protocol {p}; {usage}").into()),
    };
    let run = PathBuf::from(run);
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("backbone.json"))?)?;
    if file
        .get("effects")
        .is_some_and(|e| e.as_array().is_some_and(|a| !a.is_empty()))
    {
        return Err("backbones with library effects are not supported here".into());
    }
    Ok(Inputs {
        data: Dataset::open(data_dir)?,
        data_dir: data_dir.clone(),
        params: serde_json::from_value(file["params"].clone())?,
        run,
        protocol,
        rest: args.into_iter().skip(3).collect(),
    })
}

impl Inputs {
    /// The training split with the run's backbone, under the chosen protocol (the val split
    /// stays unread).
    pub fn training_set(&self) -> Result<TrainSet, Error> {
        Ok(TrainSet::with_protocol(
            &self.data,
            Split::Train,
            &self.params,
            &SceneConfig::default(),
            self.protocol,
        )?)
    }
}
