//! Restarts with increasing population (IPOP) and a whole-run driver.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::config::check_len;
use crate::{CmaEs, CmaesConfig, Error, StopReason, exact};

/// Population growth factor per restart (Auger & Hansen's IPOP-CMA-ES uses 2).
pub const POPULATION_GROWTH: usize = 2;

/// What one run of a restart sequence did.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// Population size λ of the run.
    pub population: usize,
    /// Seed of the run.
    pub seed: u64,
    /// Generations completed.
    pub generations: u64,
    /// Candidates evaluated.
    pub evaluations: u64,
    /// Best finite fitness of the run.
    #[serde(with = "exact::opt")]
    pub best_fitness: Option<f64>,
    /// Why it stopped.
    pub stop: StopReason,
}

/// Ask/tell CMA-ES with IPOP restarts: whenever a run stops for a reason other than reaching
/// the target or exhausting the evaluation budget, and restarts remain, a new run starts with
/// the population multiplied by [`POPULATION_GROWTH`].
///
/// Restart `k` (`k ≥ 1`) uses a seed derived from the configured one, starts at a uniformly
/// random point of the box when the configuration has bounds (else at `x0` again) with the
/// same σ₀. `termination.max_evaluations` is a budget for the whole sequence; every other
/// criterion applies to each run. The state serialises like [`CmaEs`].
///
/// ```
/// use cmaes::{CmaesConfig, Ipop};
///
/// let mut config = CmaesConfig::new(vec![2.0; 3], 0.5);
/// config.termination.target = Some(1e-8);
/// let mut opt = Ipop::new(config, 4)?;
/// while opt.should_stop().is_none() {
///     let xs = opt.ask();
///     let f: Vec<f64> = xs.iter().map(|x| x.iter().map(|v| v * v).sum()).collect();
///     opt.tell(&xs, &f)?;
/// }
/// assert!(opt.best().unwrap().1 <= 1e-8);
/// # Ok::<(), cmaes::Error>(())
/// ```
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Ipop {
    base: CmaesConfig,
    max_restarts: usize,
    current: CmaEs,
    finished: Vec<RunSummary>,
    #[serde(with = "exact::vec")]
    best_x: Vec<f64>,
    #[serde(with = "exact::opt")]
    best_f: Option<f64>,
    stop: Option<StopReason>,
}

impl Ipop {
    /// Starts the first run with `config`; at most `max_restarts` further runs follow.
    pub fn new(config: CmaesConfig, max_restarts: usize) -> Result<Self, Error> {
        let current = CmaEs::new(config.clone())?;
        Ok(Self {
            base: config,
            max_restarts,
            current,
            finished: Vec::new(),
            best_x: Vec::new(),
            best_f: None,
            stop: None,
        })
    }

    /// The current run's population (see [`CmaEs::ask`]).
    pub fn ask(&mut self) -> Vec<Vec<f64>> {
        self.current.ask()
    }

    /// Reports fitness values (see [`CmaEs::tell`]) and restarts when the run has stopped.
    pub fn tell(&mut self, candidates: &[Vec<f64>], fitness: &[f64]) -> Result<(), Error> {
        self.current.tell(candidates, fitness)?;
        if let Some((x, f)) = self.current.best()
            && self.best_f.is_none_or(|b| f < b)
        {
            self.best_f = Some(f);
            self.best_x = x.to_vec();
        }
        let Some(reason) = self.current.should_stop() else {
            return Ok(());
        };
        self.finished.push(RunSummary {
            population: self.current.population_size(),
            seed: self.current.config().seed,
            generations: self.current.generation(),
            evaluations: self.current.evaluations(),
            best_fitness: self.current.best().map(|(_, f)| f),
            stop: reason,
        });
        let spent: u64 = self.finished.iter().map(|r| r.evaluations).sum();
        let budget_left = self
            .base
            .termination
            .max_evaluations
            .is_none_or(|m| spent < m);
        let restarts_done = self.finished.len() - 1;
        if reason.restartable() && restarts_done < self.max_restarts && budget_left {
            self.current = CmaEs::new(self.restart_config(restarts_done + 1, spent))?;
        } else {
            self.stop = Some(reason);
        }
        Ok(())
    }

    fn restart_config(&self, k: usize, spent: u64) -> CmaesConfig {
        let mut config = self.base.clone();
        config.seed = derive_seed(self.base.seed, k as u64);
        config.population = Some(
            self.base
                .population_size()
                .saturating_mul(POPULATION_GROWTH.saturating_pow(k as u32))
                // Many restarts would double it past anything a computer can hold.
                .min(crate::MAX_POPULATION),
        );
        if let Some(m) = self.base.termination.max_evaluations {
            config.termination.max_evaluations = Some(m - spent);
        }
        if let Some(b) = &self.base.bounds {
            // A separate stream of the run's seed, so the start point and the first samples are
            // independent.
            let mut rng = ChaCha8Rng::seed_from_u64(config.seed);
            rng.set_stream(1);
            config.x0 = b
                .lower
                .iter()
                .zip(&b.upper)
                .map(|(&lo, &hi)| lo + rng.random::<f64>() * (hi - lo))
                .collect();
        }
        config
    }

    /// Why the whole sequence stopped (the last run's reason), or `None` while it goes on.
    pub fn should_stop(&self) -> Option<StopReason> {
        self.stop
    }

    /// Best candidate over all runs and its fitness.
    pub fn best(&self) -> Option<(&[f64], f64)> {
        self.best_f.map(|f| (self.best_x.as_slice(), f))
    }

    /// Evaluations over all runs, in whole generations.
    pub fn evaluations(&self) -> u64 {
        let finished: u64 = self.finished.iter().map(|r| r.evaluations).sum();
        // Once stopped, the current run is the last finished one and already counted.
        if self.stop.is_some() {
            finished
        } else {
            finished + self.current.evaluations()
        }
    }

    /// Restarts begun so far (runs started minus one).
    pub fn restarts(&self) -> usize {
        (self.finished.len() + usize::from(self.stop.is_none())).saturating_sub(1)
    }

    /// Summaries of the finished runs.
    pub fn runs(&self) -> &[RunSummary] {
        &self.finished
    }

    /// The run in progress (or the last one, once stopped).
    pub fn current(&self) -> &CmaEs {
        &self.current
    }
}

/// Seed of restart `k`: the configured seed for `k = 0`, a SplitMix64 mix of both otherwise.
fn derive_seed(seed: u64, k: u64) -> u64 {
    if k == 0 {
        return seed;
    }
    let mut z = seed.wrapping_add(k.wrapping_mul(0x9E37_79B9_7F4A_7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Result of [`minimize`].
#[derive(Debug, Clone, PartialEq)]
pub struct Minimum {
    /// Best candidate found (in the optimiser's coordinates).
    pub x: Vec<f64>,
    /// Its fitness.
    pub fitness: f64,
    /// Total evaluations over all runs.
    pub evaluations: u64,
    /// Why the last run stopped.
    pub stop: StopReason,
    /// One summary per run (1 + number of restarts).
    pub runs: Vec<RunSummary>,
}

/// Minimises `objective` with IPOP-CMA-ES: at most `restarts` restarts after the first run.
///
/// `objective` receives a whole population and returns one fitness per candidate, in order,
/// so it can evaluate them in parallel (e.g. with rayon's `par_iter`); results do not depend
/// on how it schedules them. Stops as [`Ipop`] does; set `config.termination` for a target or
/// a budget.
///
/// ```
/// use cmaes::{CmaesConfig, minimize};
///
/// let mut config = CmaesConfig::new(vec![0.0; 2], 0.5);
/// config.termination.target = Some(1e-12);
/// let rosen = |x: &[f64]| 100.0 * (x[1] - x[0] * x[0]).powi(2) + (1.0 - x[0]).powi(2);
/// let min = minimize(|pop| pop.iter().map(|x| rosen(x)).collect(), config, 3)?;
/// assert!((min.x[0] - 1.0).abs() < 1e-4 && (min.x[1] - 1.0).abs() < 1e-4);
/// # Ok::<(), cmaes::Error>(())
/// ```
///
/// Errors: invalid configuration, an objective returning the wrong number of values, or no
/// finite fitness value in the whole run ([`Error::NoFiniteFitness`]).
pub fn minimize<F>(mut objective: F, config: CmaesConfig, restarts: usize) -> Result<Minimum, Error>
where
    F: FnMut(&[Vec<f64>]) -> Vec<f64>,
{
    let mut opt = Ipop::new(config, restarts)?;
    let stop = loop {
        if let Some(reason) = opt.should_stop() {
            break reason;
        }
        let candidates = opt.ask();
        let fitness = objective(&candidates);
        check_len("objective output", candidates.len(), fitness.len())?;
        opt.tell(&candidates, &fitness)?;
    };
    let (x, fitness) = opt.best().ok_or(Error::NoFiniteFitness)?;
    Ok(Minimum {
        x: x.to_vec(),
        fitness,
        evaluations: opt.evaluations(),
        stop,
        runs: opt.runs().to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derived_seeds_differ() {
        let seeds: Vec<u64> = (0..5).map(|k| derive_seed(42, k)).collect();
        assert_eq!(seeds[0], 42);
        for i in 0..5 {
            for j in (i + 1)..5 {
                assert_ne!(seeds[i], seeds[j]);
            }
        }
    }
}
