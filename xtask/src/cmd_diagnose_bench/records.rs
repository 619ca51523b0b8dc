//! What the bench writes (`--json`) and returns: per object its base model and calibration,
//! per case the verdict and the gap it recovered, and the summary over the classes.

use serde::Serialize;
use springs::SpringParams;

/// One iteration of an object's base-model search.
#[derive(Serialize, Clone, Debug)]
pub struct BaseStep {
    /// Base effects at the start of the iteration (`name=values`).
    pub base: Vec<String>,
    /// The diagnosis' verdict.
    pub verdict: String,
    /// Shrinkage of the verdict's effect (None when the verdict is not an effect).
    pub shrinkage: Option<f64>,
    /// Held-out MDE of the control refit, cm.
    pub control_mde_cm: f64,
    /// Wall time, s.
    pub wall_s: f64,
}

/// An object's base model.
#[derive(Serialize, Clone, Debug)]
pub struct ObjectModel {
    /// Object.
    pub object: String,
    /// The backbone fitted on the no-effect data (its topology is kept for every case).
    pub backbone: SpringParams,
    /// The base-model search.
    pub steps: Vec<BaseStep>,
    /// The base model: the backbone refitted with the base effects on the no-effect data.
    pub model: SpringParams,
    /// Base effects at their refitted values.
    pub base: Vec<String>,
    /// Held-out MDE of the control refit (from the base model) on the no-effect data, cm (the
    /// reference of every case's effect-attributable gap).
    pub mde_without_effect_cm: f64,
    /// Training MDE of that refit, cm (the reference of the strength calibration).
    pub train_mde_without_effect_cm: f64,
    /// Wall time of steps 1–2, s.
    pub wall_s: f64,
}

/// One rung of the strength ladder.
#[derive(Serialize, Clone, Debug)]
pub struct Rung {
    /// Multiple of the world's default strength.
    pub scale: f32,
    /// Training MDE of the control refit on the effect data minus that on the no-effect data,
    /// cm.
    pub raise_cm: f64,
    /// How far the effect at this scale moves the object in the world, before any fit
    /// ([`world::effect_displacement_m`], on the held-out episodes' count of recordings), cm.
    pub displacement_cm: f64,
}

/// One bench case.
#[derive(Serialize, Clone, Debug)]
pub struct BenchCase {
    /// Object.
    pub object: String,
    /// The effect switched on in the data (`none` and the out-of-library effects included).
    pub truth: String,
    /// `none`, `in-library`, `in-base` (the withheld effect is one of the object's base
    /// effects, so the model already has it: expected `none`) or `out-of-library`.
    pub class: String,
    /// What the diagnosis should say.
    pub expected: String,
    /// What it said (with `--second-round`, the answer after the second round).
    pub verdict: String,
    /// With `--second-round`, when the first round named an effect: that round's verdict and
    /// the second round's (the model with the effect added).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rounds: Option<[String; 2]>,
    /// Strength used, as a multiple of the world's default (1 for `none`).
    pub scale: f32,
    /// The ladder as measured (empty for `none`).
    pub ladder: Vec<Rung>,
    /// Whether some rung reached the target raise.
    pub target_reached: bool,
    /// Shrinkage of the verdict's effect (None when the verdict is not an effect).
    pub verdict_shrinkage: Option<f64>,
    /// Held-out MDE of the control refit (base model refitted on this data), cm.
    pub mde_before_cm: f64,
    /// Held-out MDE of the base model on the same data generated without the effect, cm.
    pub mde_without_effect_cm: f64,
    /// `mde_before_cm − mde_without_effect_cm`: the effect-attributable gap, cm.
    pub attributable_gap_cm: f64,
    /// Held-out MDE with the true effect's candidate refitted (the probe's for an
    /// out-of-library effect), cm.
    pub mde_after_cm: Option<f64>,
    /// Shrinkage of the true effect's candidate (the probe's for an out-of-library effect).
    pub shrinkage: Option<f64>,
    /// Its 95% bootstrap interval.
    pub ci95: Option<[f64; 2]>,
    /// `(before − after) / gap`: share of the effect-attributable gap recovered (None when the
    /// gap is not positive or nothing was refitted for the true effect).
    pub recovered: Option<f64>,
    /// The true effect's refit lost the race (`--race`), so `mde_after_cm`, `shrinkage` and
    /// `recovered` are its halfway refit's. Absent when it did not.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub true_effect_raced_out: bool,
    /// Wall time of the diagnosis, s.
    pub diagnose_wall_s: f64,
    /// The diagnosis's estimate before it ran (`gap::effort`: seconds with two threads on the
    /// reference host; a bench on one thread takes about twice as long), for checking the
    /// count that `diagnose --budget-min` chooses by.
    pub diagnose_estimated_s: f64,
    /// The trained network's comparison (`--network-minutes`), when this case got one.
    pub network: Option<gap::Learnable>,
    /// Significant candidates tied on held-out error, when there were any: `by_shrinkage` is
    /// what the verdict would have been without the signature tie-break.
    pub tie_break: Option<gap::TieBreak>,
    /// The diagnosis carried the caution [`gap::Diagnosis::carry_over_caution`] (its control
    /// refit scored worse held out than the model as given; the first round's, with
    /// `--second-round`).
    pub caution: bool,
}

/// A case `--plan visible` left out: the effect hardly moves the object.
#[derive(Serialize, Clone, Debug)]
pub struct SkippedCase {
    /// Object.
    pub object: String,
    /// The effect.
    pub truth: String,
    /// The ladder's top scale.
    pub scale: f32,
    /// Its world-level displacement at that scale, cm.
    pub displacement_cm: f64,
}

/// Bench summary.
#[derive(Serialize, Debug)]
pub struct BenchSummary {
    /// The bench's arguments as run (`DiagnoseBenchArgs`, field names in snake case) and the
    /// version of pgrd that ran it ([`settings`]).
    pub settings: serde_json::Value,
    /// Search bounds of the backbone fits (`reference` or `paper`).
    pub bounds: String,
    /// Episodes cut from one recording in every generated dataset.
    pub episodes_per_recording: usize,
    /// Share of in-library cases (target strength reached) with the right verdict.
    pub in_library_accuracy: f64,
    /// Same over every in-library case, target reached or not.
    pub in_library_accuracy_all: f64,
    /// In-library cases counted (target reached, all).
    pub in_library_cases: [usize; 2],
    /// Share of `none` cases answered `none`.
    pub none_accuracy: f64,
    /// Share of out-of-library cases answered `unknown`.
    pub unknown_accuracy: f64,
    /// Share of in-base cases answered `none`.
    pub in_base_accuracy: f64,
    /// Median recovered share of the attributable gap over in-library cases (target reached,
    /// positive gap).
    pub median_recovered: f64,
    /// Share of those cases recovering at least 70 %.
    pub recovered_70_share: f64,
    /// Confusion matrix rows: truth, then counts per verdict label.
    pub confusion: Vec<(String, Vec<(String, usize)>)>,
    /// The objects' base models.
    pub objects: Vec<ObjectModel>,
    /// All cases.
    pub cases: Vec<BenchCase>,
    /// Cases `--plan visible` left out.
    pub skipped: Vec<SkippedCase>,
    /// Wall time, s.
    pub wall_s: f64,
}

/// What `--json` holds while the bench runs: the summary's `objects` and `cases` so far.
#[derive(Serialize)]
pub(super) struct PartialBench<'a> {
    pub settings: &'a serde_json::Value,
    pub objects: &'a [ObjectModel],
    pub cases: &'a [BenchCase],
}

/// The bench's arguments as JSON, plus `pgrd_version` (the xtask package's version): what
/// `--json` records as `settings`, so that a stored bench says how it was made.
pub fn settings(args: &super::DiagnoseBenchArgs) -> anyhow::Result<serde_json::Value> {
    let mut v = serde_json::to_value(args)?;
    if let Some(map) = v.as_object_mut() {
        map.insert(
            "pgrd_version".into(),
            env!("CARGO_PKG_VERSION").to_string().into(),
        );
    }
    Ok(v)
}
