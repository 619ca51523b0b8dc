use std::path::Path;
use std::time::Instant;

use cmaes::CmaEs;
use rand::SeedableRng;
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use scene::Scene;
use serde::{Deserialize, Serialize};

use crate::Family;

/// Loss given to a candidate whose rollout diverged or produced non-finite values (the
/// reference code's value, in m²).
pub const PENALTY: f64 = 1e8;

/// Settings of one fit (the reference's defaults).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitConfig {
    /// Candidates per generation.
    pub population: usize,
    /// Generations to run, at least 1 ([`fit`] refuses 0).
    pub generations: usize,
    /// Training scenes sampled per generation.
    pub samples: usize,
    /// Initial step size in the normalised [0, 1] space.
    pub sigma0: f64,
    /// Seed of the optimiser and of the scene sampling.
    pub seed: u64,
    /// Final selection. `0` (the reference's rule): the best candidate by the loss on its own
    /// generation's sampled scenes, which favours whichever generation drew easy scenes.
    /// `k > 0`: after the last generation the optimiser's mean and the best candidates of the
    /// `k` generations with the lowest sampled loss are scored on *all* scenes (or
    /// [`rescore_scenes`](Self::rescore_scenes) of them), and the best of those by that loss is
    /// kept (`k + 1` extra evaluations over every scored scene, `k + 2` with
    /// [`rescore_start`](Self::rescore_start)).
    #[serde(default)]
    pub rescore: usize,
    /// Most scenes the final rescoring scores (0: all). With more scenes than this, a subset
    /// of this many drawn with the seed, the same for every contender, so that the rescoring
    /// of a large dataset costs at most `(rescore + 1) × rescore_scenes` rollouts (one more
    /// set with [`rescore_start`](Self::rescore_start)).
    #[serde(default)]
    pub rescore_scenes: usize,
    /// With [`rescore`](Self::rescore): also score the run's start (the family's `x0`) in the
    /// final rescoring, so that a refit from a fitted model never ends worse than where it
    /// started by the rescoring's loss (ties go to the earlier contenders: the mean and the
    /// generations' best). Off: the reference's rule, the optimiser's points only.
    #[serde(default)]
    pub rescore_start: bool,
}

impl Default for FitConfig {
    fn default() -> Self {
        FitConfig {
            population: 8,
            generations: 20,
            samples: 8,
            sigma0: 0.2,
            seed: 0,
            rescore: 0,
            rescore_scenes: 0,
            rescore_start: false,
        }
    }
}

/// What one generation did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Generation {
    /// 0-based generation index.
    pub index: usize,
    /// Best candidate loss of this generation, m².
    pub best_loss: f64,
    /// Median candidate loss of this generation, m².
    pub median_loss: f64,
    /// Best loss seen so far, m².
    pub best_so_far: f64,
    /// Candidates that diverged (scored [`PENALTY`] on some scene).
    pub diverged: usize,
    /// Wall time of the generation, s.
    pub wall_s: f64,
}

/// The result of a fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitOutcome {
    /// Family name.
    pub family: String,
    /// Names of the parameters, in order.
    pub names: Vec<String>,
    /// The box searched, `[lower, upper]` per parameter in real units, in `names`' order.
    /// Empty in outcomes written before it was recorded (2026-12-07).
    #[serde(default)]
    pub ranges: Vec<[f64; 2]>,
    /// Best parameters seen (real units, integers rounded).
    pub best: Vec<f64>,
    /// Their loss, m²: on the scenes of the generation they were found in, or on the
    /// rescored scenes when [`FitConfig::rescore`] is set.
    pub best_loss: f64,
    /// Per-generation history.
    pub history: Vec<Generation>,
    /// Candidates evaluated.
    pub evaluations: u64,
    /// Generation the run resumed from (`None`: started fresh).
    pub resumed_from: Option<usize>,
    /// Best candidate of every generation (real units), in order; used by the rescoring.
    #[serde(default)]
    pub generation_best: Vec<Vec<f64>>,
    /// The final rescoring, when [`FitConfig::rescore`] asked for one.
    #[serde(default)]
    pub rescored: Option<Rescore>,
}

/// What the final rescoring found (see [`FitConfig::rescore`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rescore {
    /// Contenders scored, in order: the optimiser's final mean, then generation bests.
    pub contenders: Vec<Contender>,
    /// Index into `contenders` of the one kept.
    pub chosen: usize,
    /// Scenes each contender was scored on ([`FitConfig::rescore_scenes`]); 0 in outcomes
    /// written before the cap existed, which scored all scenes.
    #[serde(default)]
    pub scenes: usize,
}

/// One contender of the final rescoring.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Contender {
    /// Generation whose best candidate this is; `None` for the optimiser's final mean and for
    /// the start.
    pub generation: Option<usize>,
    /// The run's start ([`FitConfig::rescore_start`]).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub start: bool,
    /// Mean loss over the rescored scenes, m².
    pub loss: f64,
}

/// Why a fit failed.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// The optimiser refused its configuration or state.
    #[error("CMA-ES: {0}")]
    Cmaes(cmaes::Error),
    /// There is nothing to fit to.
    #[error("no training scenes to fit to")]
    NoScenes,
    /// The checkpoint file could not be read or written.
    #[error("checkpoint {path}: {message}")]
    Checkpoint {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// Settings or inputs that cannot work.
    #[error("{0}")]
    Config(String),
    /// A scene could not be built.
    #[error(transparent)]
    Scene(#[from] scene::SceneError),
    /// The simulator refused a model or failed a step.
    #[error(transparent)]
    Sim(#[from] springs::SimError),
}

// The wrapped error is part of the message, not its source: a report printing the chain of
// causes would otherwise repeat its text.
impl From<cmaes::Error> for FitError {
    fn from(e: cmaes::Error) -> Self {
        FitError::Cmaes(e)
    }
}

#[derive(Serialize, Deserialize)]
struct Checkpoint {
    family: String,
    config: FitConfig,
    scenes: usize,
    /// The scenes' substep rule: the damping is fitted for one integrator. Absent in
    /// checkpoints written before it was recorded, all of which used the default.
    #[serde(default)]
    substep: Option<springs::Substep>,
    /// [`data_fingerprint`] of the scenes fitted. Absent in checkpoints written before
    /// session 100, which are resumed on the count check alone, as then.
    #[serde(default)]
    data: Option<String>,
    es: CmaEs,
    outcome: FitOutcome,
}

/// A fingerprint of the scenes a fit sees (FNV-1a over each scene's window, tracked count,
/// start positions and last tracked frame), so a checkpoint is not resumed on other data of
/// the same size. Not a cryptographic hash: it guards against mistakes, not against forgery.
fn data_fingerprint(scenes: &[Scene]) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for b in bytes {
            h ^= u64::from(*b);
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    };
    for s in scenes {
        eat(&(s.window.start as u64).to_le_bytes());
        eat(&(s.window.steps as u64).to_le_bytes());
        eat(&(s.tracked as u64).to_le_bytes());
        for p in s.init.x.iter().chain(s.truth.last().into_iter().flatten()) {
            for c in p.to_array() {
                eat(&c.to_bits().to_le_bytes());
            }
        }
    }
    format!("{h:016x}")
}

/// Why a checkpoint's outcome cannot belong to a search of `dim` parameters, if it cannot
/// (a hand-edited or truncated file must be refused, not indexed out of bounds).
fn outcome_mismatch(outcome: &FitOutcome, dim: usize) -> Option<String> {
    if outcome.names.len() != dim {
        return Some(format!(
            "{} parameter names for {dim} parameters",
            outcome.names.len()
        ));
    }
    if !outcome.best.is_empty() && outcome.best.len() != dim {
        return Some(format!(
            "best has {} values for {dim} parameters",
            outcome.best.len()
        ));
    }
    if outcome.generation_best.len() != outcome.history.len() {
        return Some(format!(
            "{} generation bests for {} generations",
            outcome.generation_best.len(),
            outcome.history.len()
        ));
    }
    outcome
        .generation_best
        .iter()
        .position(|b| b.len() != dim)
        .map(|g| format!("generation {g}'s best has the wrong length"))
}

/// `[lower, upper]` of every parameter of `params`, in order.
fn search_box(params: &cmaes::Parameters) -> Vec<[f64; 2]> {
    params.params().iter().map(|p| [p.lower, p.upper]).collect()
}

/// Loss of one candidate on one scene: mean squared position error, or [`PENALTY`].
pub fn scene_loss<F: Family + ?Sized>(family: &F, real: &[f64], scene: &Scene) -> f64 {
    let (params, options) = family.build_for(real, scene);
    let loss = scene
        .rollout(&params, &scene.sim_config(), options)
        .and_then(|pred| scene::position_mse(scene, &pred));
    match loss {
        Ok(l) if l.is_finite() => l,
        _ => PENALTY,
    }
}

pub(crate) fn checkpoint_error(path: &Path, message: impl ToString) -> FitError {
    FitError::Checkpoint {
        path: path.display().to_string(),
        message: message.to_string(),
    }
}

/// Fits `family` to `scenes`. `on_generation` sees every finished generation (for progress).
pub fn fit<F: Family>(
    scenes: &[Scene],
    family: &F,
    config: &FitConfig,
    checkpoint: Option<&Path>,
    on_generation: &mut dyn FnMut(&Generation),
) -> Result<FitOutcome, FitError> {
    if scenes.is_empty() {
        return Err(FitError::NoScenes);
    }
    if config.generations == 0 {
        // With no generation the "fit" would rescore its start and report it as fitted.
        return Err(FitError::Config(
            "a fit needs generations >= 1 (with none it would return its start unfitted)".into(),
        ));
    }
    let mut run = match checkpoint.filter(|p| p.is_file()) {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(|e| checkpoint_error(path, e))?;
            let ck: Checkpoint =
                serde_json::from_str(&text).map_err(|e| checkpoint_error(path, e))?;
            // Asking for more generations extends a run, and the final selection may change;
            // anything else must match.
            let same = FitConfig {
                generations: config.generations,
                rescore: config.rescore,
                rescore_scenes: config.rescore_scenes,
                rescore_start: config.rescore_start,
                ..ck.config.clone()
            };
            let substep = ck.substep.unwrap_or(springs::Substep::AUTO);
            if ck.family != family.name()
                || same != *config
                || ck.scenes != scenes.len()
                || scenes.iter().any(|s| s.sim_config().substep != substep)
                || ck
                    .data
                    .as_ref()
                    .is_some_and(|d| *d != data_fingerprint(scenes))
            {
                return Err(checkpoint_error(
                    path,
                    "was written by a fit with other settings or data; remove it to start afresh",
                ));
            }
            // The optimiser works in the box's normalised coordinates: on another box the
            // same state would mean other parameters.
            if !ck.outcome.ranges.is_empty() && ck.outcome.ranges != search_box(family.parameters())
            {
                return Err(checkpoint_error(
                    path,
                    "was written for other parameter ranges; remove it to start afresh",
                ));
            }
            if let Some(why) = outcome_mismatch(&ck.outcome, ck.es.dim()) {
                return Err(checkpoint_error(
                    path,
                    format!("is damaged ({why}); remove it to start afresh"),
                ));
            }
            let mut outcome = ck.outcome;
            outcome.resumed_from = Some(outcome.history.len());
            PausedFit {
                es: ck.es,
                outcome,
                config: config.clone(),
                scenes: scenes.len(),
            }
        }
        None => PausedFit::start(scenes, family, config)?,
    };
    run.advance_inner(
        scenes,
        family,
        config.generations,
        checkpoint,
        on_generation,
    )?;
    run.finish(scenes, family, config.rescore, config.rescore_scenes)
}

/// A fit that runs in stages in memory: start it, [`advance`](Self::advance) it some
/// generations, look at where it stands ([`finish`](Self::finish) on a clone), advance it
/// further. Advancing to `generations` and finishing gives exactly the outcome of [`fit`] with
/// that many generations (tested), so a caller can stop spending on a run that is losing a
/// race (the diagnosis's `race`) without changing the runs it keeps.
///
/// ```
/// # use fit::{BackboneFamily, FitConfig, PausedFit};
/// # fn demo(scenes: &[scene::Scene], family: &BackboneFamily) -> Result<(), fit::FitError> {
/// let config = FitConfig { generations: 10, rescore: 3, ..FitConfig::default() };
/// let mut run = PausedFit::start(scenes, family, &config)?;
/// run.advance(scenes, family, 5)?;
/// let halfway = run.clone().finish(scenes, family, 1, 16)?; // a cheap look
/// run.advance(scenes, family, 10)?;
/// let outcome = run.finish(scenes, family, config.rescore, config.rescore_scenes)?;
/// # Ok(()) }
/// ```
#[derive(Clone, Debug)]
pub struct PausedFit {
    es: CmaEs,
    outcome: FitOutcome,
    config: FitConfig,
    scenes: usize,
}

impl PausedFit {
    /// A fresh run of `config` (its `generations` and rescoring are ignored: the stages say
    /// how far to go and how to finish). Nothing is evaluated yet.
    pub fn start<F: Family>(
        scenes: &[Scene],
        family: &F,
        config: &FitConfig,
    ) -> Result<Self, FitError> {
        if scenes.is_empty() {
            return Err(FitError::NoScenes);
        }
        let params = family.parameters();
        let mut cfg = params.cmaes_config(&family.x0(), config.sigma0, config.seed)?;
        cfg.population = Some(config.population);
        let outcome = FitOutcome {
            family: family.name(),
            names: params.params().iter().map(|p| p.name.clone()).collect(),
            ranges: search_box(params),
            best: family.x0(),
            best_loss: f64::INFINITY,
            history: Vec::new(),
            evaluations: 0,
            resumed_from: None,
            generation_best: Vec::new(),
            rescored: None,
        };
        Ok(PausedFit {
            es: CmaEs::new(cfg)?,
            outcome,
            config: config.clone(),
            scenes: scenes.len(),
        })
    }

    /// Generations run so far.
    pub fn generations(&self) -> usize {
        self.outcome.history.len()
    }

    /// Runs generations until `generations` have run (none if that many already have).
    pub fn advance<F: Family>(
        &mut self,
        scenes: &[Scene],
        family: &F,
        generations: usize,
    ) -> Result<(), FitError> {
        self.advance_inner(scenes, family, generations, None, &mut |_| {})
    }

    fn check_scenes<F: Family>(&self, scenes: &[Scene], family: &F) -> Result<(), FitError> {
        if scenes.len() != self.scenes || family.name() != self.outcome.family {
            return Err(FitError::Config(format!(
                "a paused fit of {} on {} scenes was continued with {} on {} scenes",
                self.outcome.family,
                self.scenes,
                family.name(),
                scenes.len()
            )));
        }
        Ok(())
    }

    fn advance_inner<F: Family>(
        &mut self,
        scenes: &[Scene],
        family: &F,
        generations: usize,
        checkpoint: Option<&Path>,
        on_generation: &mut dyn FnMut(&Generation),
    ) -> Result<(), FitError> {
        self.check_scenes(scenes, family)?;
        let params = family.parameters();
        let config = &self.config;
        let (es, outcome) = (&mut self.es, &mut self.outcome);
        let samples = config.samples.min(scenes.len()).max(1);
        while outcome.history.len() < generations {
            let t0 = Instant::now();
            let index = outcome.history.len();
            let mut rng = ChaCha8Rng::seed_from_u64(
                config.seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            );
            let mut picked = sample(&mut rng, scenes.len(), samples).into_vec();
            picked.sort_unstable();
            let candidates = es.ask();
            let reals = candidates
                .iter()
                .map(|u| params.to_real(u))
                .collect::<Result<Vec<_>, _>>()?;
            let losses = losses_on(family, &reals, scenes, &picked);
            let fitness: Vec<f64> = losses
                .chunks(samples)
                .map(|l| l.iter().sum::<f64>() / samples as f64)
                .collect();
            let diverged = losses
                .chunks(samples)
                .filter(|l| l.contains(&PENALTY))
                .count();
            es.tell(&candidates, &fitness)?;
            let (best_c, best_loss) =
                fitness
                    .iter()
                    .enumerate()
                    .fold(
                        (0, f64::INFINITY),
                        |b, (i, f)| if *f < b.1 { (i, *f) } else { b },
                    );
            if best_loss < outcome.best_loss {
                outcome.best_loss = best_loss;
                outcome.best = reals[best_c].clone();
            }
            outcome.generation_best.push(reals[best_c].clone());
            let mut sorted = fitness.clone();
            sorted.sort_by(f64::total_cmp);
            outcome.evaluations += fitness.len() as u64;
            let generation = Generation {
                index,
                best_loss,
                median_loss: sorted[sorted.len() / 2],
                best_so_far: outcome.best_loss,
                diverged,
                wall_s: t0.elapsed().as_secs_f64(),
            };
            outcome.history.push(generation.clone());
            if let Some(path) = checkpoint {
                let ck = Checkpoint {
                    family: family.name(),
                    config: config.clone(),
                    scenes: scenes.len(),
                    substep: scenes.first().map(|s| s.sim_config().substep),
                    data: Some(data_fingerprint(scenes)),
                    es: es.clone(),
                    outcome: outcome.clone(),
                };
                let text = serde_json::to_string(&ck).map_err(|e| checkpoint_error(path, e))?;
                dataset::write_atomic(path, text.as_bytes())
                    .map_err(|e| checkpoint_error(path, e))?;
            }
            on_generation(&generation);
        }
        Ok(())
    }

    /// The outcome so far, with the final selection [`FitConfig::rescore`] describes made
    /// with `rescore` and `rescore_scenes` (`rescore = 0`: the best candidate by its own
    /// generation's sample).
    pub fn finish<F: Family>(
        mut self,
        scenes: &[Scene],
        family: &F,
        rescore: usize,
        rescore_scenes: usize,
    ) -> Result<FitOutcome, FitError> {
        self.check_scenes(scenes, family)?;
        let config = FitConfig {
            rescore,
            rescore_scenes,
            ..self.config.clone()
        };
        if rescore > 0 && self.outcome.rescored.is_none() {
            rescore_run(
                scenes,
                family,
                family.parameters(),
                &self.es,
                &config,
                &mut self.outcome,
            )?;
        }
        Ok(self.outcome)
    }
}

/// Loss of every candidate on every picked scene, candidate-major, computed in parallel and
/// returned in a fixed order (so reductions do not depend on the thread count).
fn losses_on<F: Family>(
    family: &F,
    reals: &[Vec<f64>],
    scenes: &[Scene],
    picked: &[usize],
) -> Vec<f64> {
    let jobs: Vec<(usize, usize)> = (0..reals.len())
        .flat_map(|c| picked.iter().map(move |s| (c, *s)))
        .collect();
    jobs.par_iter()
        .map(|(c, s)| scene_loss(family, &reals[*c], &scenes[*s]))
        .collect()
}

/// Scores the optimiser's mean and the best candidates of the `config.rescore` best
/// generations on every scene (or a seeded subset of `config.rescore_scenes`) and keeps the
/// best (ties: the earlier contender, so the mean wins an exact tie).
fn rescore_run<F: Family>(
    scenes: &[Scene],
    family: &F,
    params: &cmaes::Parameters,
    es: &CmaEs,
    config: &FitConfig,
    outcome: &mut FitOutcome,
) -> Result<(), FitError> {
    let k = config.rescore;
    let mut order: Vec<usize> = (0..outcome.history.len().min(outcome.generation_best.len()))
        .filter(|&g| outcome.history[g].best_loss < PENALTY)
        .collect();
    order.sort_by(|&a, &b| {
        outcome.history[a]
            .best_loss
            .total_cmp(&outcome.history[b].best_loss)
            .then(a.cmp(&b))
    });
    order.truncate(k);
    let mut reals = vec![params.to_real(&es.mean())?];
    let mut labels = vec![(None, false)];
    for g in order {
        reals.push(outcome.generation_best[g].clone());
        labels.push((Some(g), false));
    }
    if config.rescore_start {
        reals.push(family.x0());
        labels.push((None, true));
    }
    let scored = rescored_scenes(scenes.len(), config);
    let losses = losses_on(family, &reals, scenes, &scored);
    let contenders: Vec<Contender> = losses
        .chunks(scored.len())
        .zip(labels)
        .map(|(l, (generation, start))| Contender {
            generation,
            start,
            loss: l.iter().sum::<f64>() / scored.len() as f64,
        })
        .collect();
    let chosen =
        contenders.iter().enumerate().fold(
            0,
            |b, (i, c)| if c.loss < contenders[b].loss { i } else { b },
        );
    outcome.evaluations += contenders.len() as u64;
    outcome.best = reals[chosen].clone();
    outcome.best_loss = contenders[chosen].loss;
    outcome.rescored = Some(Rescore {
        contenders,
        chosen,
        scenes: scored.len(),
    });
    Ok(())
}

/// The scenes the final rescoring scores, in increasing order: all of them, or a subset of
/// `rescore_scenes` drawn from a stream of its own (the generations' draws stay as they were).
fn rescored_scenes(n: usize, config: &FitConfig) -> Vec<usize> {
    if config.rescore_scenes == 0 || config.rescore_scenes >= n {
        return (0..n).collect();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(config.seed ^ 0x5245_5343_4f52_4553); // "RESCORES"
    let mut picked = sample(&mut rng, n, config.rescore_scenes).into_vec();
    picked.sort_unstable();
    picked
}
