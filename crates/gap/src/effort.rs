//! What a diagnosis will cost before it runs, counted in simulator work rather than read off
//! a clock, so that a choice made from it (`cargo xtask diagnose --budget-min`) is the same on
//! every run of the same inputs.

use scene::Scene;
use serde::{Deserialize, Serialize};
use springs::{SpringParams, Substep};

use crate::{Candidate, DiagnoseConfig, GapError, RACE_SCENES};

/// Training scenes whose backbones are built to measure the work of one rollout (the
/// episodes of a dataset share one object, so a few say what all cost).
const SAMPLED_SCENES: usize = 8;

/// The simulator work of one diagnosis, before it runs.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Effort {
    /// Rollouts of training episodes by every refit (control, candidates, the probe from two
    /// starts, raced with a race), the race's looks and the final rescorings included.
    pub refit_rollouts: usize,
    /// Rollouts of held-out episodes: the model as given, the control, every candidate and
    /// the probe, and at most as many effect-off twins (only the probe and the library refits
    /// that beat the control are rolled out with their effect off, so this is an upper bound).
    pub heldout_rollouts: usize,
    /// Rollouts of training episodes for the residual signatures: the backbone once per
    /// scene and two per candidate and scene (the effect at its start and at neutral); with
    /// the probe, also the backbone on up to [`crate::FOCUS_SCENES`] scenes for its starting
    /// point.
    pub signature_rollouts: usize,
    /// Work of one rollout: steps × substeps per step × (springs + particles), mean over up
    /// to eight training episodes at the given parameters, with the base effects
    /// ([`DiagnoseConfig::base`]) in the backbone.
    pub work_per_rollout: f64,
    /// Substeps per step, springs and particles of those episodes' backbones (means).
    pub substeps: f64,
    /// See `substeps`.
    pub springs: f64,
    /// See `substeps`.
    pub particles: f64,
}

impl Effort {
    /// Total work: every rollout times the work of one.
    pub fn work(&self) -> f64 {
        (self.refit_rollouts + self.heldout_rollouts + self.signature_rollouts) as f64
            * self.work_per_rollout
    }

    /// Estimated wall time on the reference 2-core host of [`SECONDS_PER_WORK`] with both
    /// threads, seconds: [`Effort::work`] times [`SECONDS_PER_WORK`].
    pub fn estimated_s(&self) -> f64 {
        self.work() * SECONDS_PER_WORK
    }
}

/// Wall seconds per unit of [`Effort::work`] with two threads on the reference host, the
/// 2-core AMD EPYC machine CI runs on: the median ratio of measured time to count over its four
/// default-size diagnoses of sessions 45–46 (the paper, the teddy and the sloth at 2.14–2.17
/// times the count at the earlier constant of 3.1 ns, the duster at 3.10; `docs/gap.md`, "Time
/// budget"). The 2-core Intel VM of sessions 32–36 ran the same count at 3.1 ns (the median of
/// 18 diagnoses, 0.80–1.43 times their estimates), so there the estimate is about twice the
/// time taken. The refits move the stiffness, and with it the substeps, away from the fitted
/// backbone's (the duster's and the teddy's upward, which makes them the dearest per unit), so
/// the estimate is for choosing, not a promise.
pub const SECONDS_PER_WORK: f64 = 6.7e-9;

/// How far above its estimate a default diagnosis's wall time has been measured to run on the
/// reference host: the largest ratio of measured time to [`Effort::estimated_s`] over the
/// default diagnoses of the four dearest generated objects with the budget's ladder of
/// sessions 52–53 (the duster, 615 s against 466 s; the others 0.84–1.21). Its refits move
/// the stiffness, and with it the substep, away from the fitted backbone's further than the
/// count can see (the duster's stiffening law from 30 to 470), and the host's own speed moves
/// between runs (11 % in session 53; 1.3–1.7 times on identical refits in session 54, more
/// than this margin covers). A budget counts each estimate times this margin, so that what it
/// chooses fits on the measured objects rather than on average.
pub const ESTIMATE_MARGIN: f64 = 1.32;

/// The work of diagnosing `train` / `val` from `base` with `config`, every rollout under
/// `substep` (which need not be the scenes' own: the estimate can compare rules).
///
/// ```no_run
/// # fn main() -> Result<(), gap::GapError> {
/// # let (train, val, base): (Vec<scene::Scene>, Vec<scene::Scene>, springs::SpringParams) = todo!();
/// let config = gap::DiagnoseConfig::default();
/// let full = gap::effort(&train, &val, &base, &config, springs::Substep::AUTO)?;
/// let raced = gap::effort(&train, &val, &base, &gap::DiagnoseConfig { race: 3, ..config }, springs::Substep::AUTO)?;
/// assert!(raced.work() < full.work());
/// # Ok(()) }
/// ```
pub fn effort(
    train: &[Scene],
    val: &[Scene],
    base: &SpringParams,
    config: &DiagnoseConfig,
    substep: Substep,
) -> Result<Effort, GapError> {
    if train.is_empty() {
        return Err(GapError::NoScenes("training"));
    }
    if val.is_empty() {
        return Err(GapError::NoScenes("held-out"));
    }
    let n = train.len();
    // A generation scores every candidate on `samples` training scenes, all of them when
    // there are fewer.
    let generation = config.population * config.samples.min(n).max(1);
    // The optimiser's mean, the best of up to `rescore` generations of `generations`, and the
    // refit's start when it is kept (`keep_start`).
    let rescoring_of = |generations: usize| {
        if config.rescore > 0 {
            let scenes = if config.rescore_scenes == 0 {
                n
            } else {
                config.rescore_scenes.min(n)
            };
            (config.rescore.min(generations) + 1 + usize::from(config.keep_start)) * scenes
        } else {
            0
        }
    };
    let rescoring = rescoring_of(config.generations);
    let whole = config.generations * generation + rescoring;
    let library = config
        .candidates
        .iter()
        .filter(|c| **c != Candidate::ExternalField && !config.base.iter().any(|b| b.effect == **c))
        .count();
    // A raced refit runs half the generations and a look at two contenders (three when the
    // start is kept) on the race's scenes; the second half and the rescoring only if it is
    // kept.
    let half = config.generations.div_ceil(2);
    let look = (2 + usize::from(config.keep_start)) * RACE_SCENES.min(n);
    let raced_half = half * generation + look;
    let second_half = (config.generations - half) * generation + rescoring;
    // The probe is refitted from two starts (the residuals' focus and its broad start); with a
    // race the two are raced and one is finished, to a multiple of the library's generations
    // ([`DiagnoseConfig::probe_factor`]).
    let probe_generations = config.probe_generations();
    let probe_generation = config.probe_population() * config.samples.min(n).max(1);
    let probe_rescoring = rescoring_of(probe_generations);
    let probe_whole = probe_generations * probe_generation + probe_rescoring;
    let probe_raced_half = half * probe_generation + look;
    let probe = match (config.probe, config.race > 0) {
        (false, _) => 0,
        (true, false) => 2 * probe_whole,
        (true, true) => {
            2 * probe_raced_half
                + probe_generations.saturating_sub(half) * probe_generation
                + probe_rescoring
        }
    };
    let library_refits = if config.race > 0 && config.race < library {
        library * raced_half + config.race * second_half
    } else {
        library * whole
    };
    // The control, the probe and the library.
    let refit_rollouts = whole + probe + library_refits;
    let contenders = library + usize::from(config.probe);
    // The model as given and the control once each, every contender and, at most, its
    // effect-off twin (rolled out only for refits that beat the control); "how far" scores
    // rollouts already made.
    let heldout_rollouts = (2 + 2 * contenders) * val.len();
    let focus = if config.probe {
        crate::FOCUS_SCENES.min(n)
    } else {
        0
    };
    // Per signature scene the backbone once, and per contender the effect at its start and at
    // neutral.
    let scenes = config.signature_scenes.clamp(1, n);
    let signature_rollouts = (1 + 2 * contenders) * scenes + focus;
    let sampled = &train[..SAMPLED_SCENES.min(n)];
    // The base effects and a refined stiffness field are in every model, and their stiffness
    // counts toward the substep (a cable's refined field, up to e^3 times the fitted
    // stiffness, took 2.6 times the estimate's wall time while the count left it out).
    let frame = crate::material_frame(train)?;
    let field = config.field.clone().map(std::sync::Arc::new);
    let options = || {
        let mut o = crate::backbone_options(&config.base, &frame);
        if let Some(f) = &field {
            o.effects.push(Box::new(springs::StiffnessField {
                log_factor: f.clone(),
            }));
        }
        o
    };
    let mut sums = [0.0; 4];
    for s in sampled {
        let sim = springs::SimConfig {
            substep,
            ..s.sim_config()
        };
        let b = s.backbone(base, &sim, options())?;
        let (sub, springs, particles) = (
            f64::from(b.substeps()),
            b.springs().len() as f64,
            b.num_particles() as f64,
        );
        sums[0] += s.window.steps as f64 * sub * (springs + particles);
        sums[1] += sub;
        sums[2] += springs;
        sums[3] += particles;
    }
    let m = sampled.len() as f64;
    Ok(Effort {
        refit_rollouts,
        heldout_rollouts,
        signature_rollouts,
        work_per_rollout: sums[0] / m,
        substeps: sums[1] / m,
        springs: sums[2] / m,
        particles: sums[3] / m,
    })
}

/// How a time budget shaped a diagnosis (`cargo xtask diagnose --budget-min`): the estimate of
/// the whole diagnosis, the options chosen to fit the budget and their estimate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BudgetChoice {
    /// The budget, seconds on the reference machine of [`SECONDS_PER_WORK`].
    pub budget_s: f64,
    /// What each estimate was multiplied by before it was compared with the budget
    /// ([`ESTIMATE_MARGIN`]; 1 in reports made before the margin).
    #[serde(default = "no_margin")]
    pub margin: f64,
    /// Estimated wall time of the diagnosis without race and with the run's substep rule, s.
    pub full_estimated_s: f64,
    /// Estimated wall time with the options chosen, s.
    pub estimated_s: f64,
    /// The options chosen, as command-line flags (empty: none needed).
    pub options: String,
}

fn no_margin() -> f64 {
    1.0
}
