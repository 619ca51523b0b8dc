//! The ask/tell CMA-ES optimiser.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::config::check_len;
use crate::linalg::{identity, mat_t_vec, mat_vec, norm, symmetric_eigen};
use crate::stop::{StopReason, median, push_capped, stagnated, stagnation_window, tolfun_window};
use crate::strategy::Strategy;
use crate::{CmaesConfig, Error, exact};

/// Factor by which σ grows in a generation whose better 70 % all share one fitness value: the
/// ranking carries no information there (typically a plateau from integer rounding or a
/// constant penalty), and a larger step is the only way off it.
const FLAT_FITNESS_SIGMA_BOOST: f64 = 0.2;

/// Everything that evolves during a run, in serialisable form.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    config: CmaesConfig,
    /// Distribution mean (genotype: unbounded coordinates, mirrored into the box on output).
    #[serde(with = "exact::vec")]
    mean: Vec<f64>,
    #[serde(with = "exact::scalar")]
    sigma: f64,
    /// Covariance matrix C, row-major, kept exactly symmetric.
    #[serde(with = "exact::vec")]
    cov: Vec<f64>,
    /// Eigenvectors of C (columns of the row-major matrix B).
    #[serde(with = "exact::vec")]
    axes: Vec<f64>,
    /// Square roots of the eigenvalues of C (the diagonal of D).
    #[serde(with = "exact::vec")]
    axis_lengths: Vec<f64>,
    #[serde(with = "exact::vec")]
    path_c: Vec<f64>,
    #[serde(with = "exact::vec")]
    path_sigma: Vec<f64>,
    generation: u64,
    evaluations: u64,
    /// Genotypes handed out by the last `ask` and not yet told (empty when none).
    #[serde(with = "exact::nested")]
    pending: Vec<Vec<f64>>,
    /// Best candidate seen so far (as evaluated, i.e. inside the box), empty before any.
    #[serde(with = "exact::vec")]
    best_x: Vec<f64>,
    #[serde(with = "exact::opt")]
    best_f: Option<f64>,
    /// Best finite fitness of each recent generation, for `TolFun`.
    #[serde(with = "exact::vec")]
    recent_best: Vec<f64>,
    /// Best and median fitness (non-finite as +inf) of each recent generation, for stagnation.
    #[serde(with = "exact::vec")]
    stagnation_best: Vec<f64>,
    #[serde(with = "exact::vec")]
    stagnation_median: Vec<f64>,
    stop: Option<StopReason>,
    /// Position of the random stream, refreshed whenever the state is serialised.
    #[serde(with = "exact::big")]
    rng_word_pos: u128,
}

/// An ask/tell CMA-ES run: sample a population with [`CmaEs::ask`], evaluate it however you
/// like (in parallel), report the fitness values with [`CmaEs::tell`], and repeat until
/// [`CmaEs::should_stop`] says why to stop. Lower fitness is better.
///
/// The whole state, including the random stream position and a population awaiting its
/// fitness, serialises with serde, and a deserialised run continues with exactly the numbers
/// the original would have produced.
///
/// ```
/// use cmaes::{CmaEs, CmaesConfig};
///
/// let mut config = CmaesConfig::new(vec![1.0; 4], 0.5);
/// config.seed = 3;
/// config.termination.target = Some(1e-10);
/// let mut es = CmaEs::new(config)?;
/// while es.should_stop().is_none() {
///     let candidates = es.ask();
///     // Evaluate in any order or in parallel; only the order of `fitness` matters.
///     let fitness: Vec<f64> = candidates.iter().map(|x| x.iter().map(|v| v * v).sum()).collect();
///     es.tell(&candidates, &fitness)?;
/// }
/// let (x, f) = es.best().unwrap();
/// assert!(f <= 1e-10 && x.iter().all(|v| v.abs() < 1e-4));
/// # Ok::<(), cmaes::Error>(())
/// ```
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(into = "State", try_from = "State")]
pub struct CmaEs {
    state: State,
    strategy: Strategy,
    rng: ChaCha8Rng,
}

impl CmaEs {
    /// Starts a run at `config.x0` with step size `config.sigma0` and `C = I`.
    pub fn new(config: CmaesConfig) -> Result<Self, Error> {
        config.validate()?;
        let n = config.dim();
        let state = State {
            mean: config.x0.clone(),
            sigma: config.sigma0,
            cov: identity(n),
            axes: identity(n),
            axis_lengths: vec![1.0; n],
            path_c: vec![0.0; n],
            path_sigma: vec![0.0; n],
            generation: 0,
            evaluations: 0,
            pending: Vec::new(),
            best_x: Vec::new(),
            best_f: None,
            recent_best: Vec::new(),
            stagnation_best: Vec::new(),
            stagnation_median: Vec::new(),
            stop: None,
            rng_word_pos: 0,
            config,
        };
        Self::from_state(state)
    }

    fn from_state(state: State) -> Result<Self, Error> {
        let strategy = Strategy::new(state.config.dim(), state.config.population_size());
        let mut rng = ChaCha8Rng::seed_from_u64(state.config.seed);
        rng.set_word_pos(state.rng_word_pos);
        Ok(Self {
            state,
            strategy,
            rng,
        })
    }

    /// The current population of candidates (λ points of dimension `n`), inside the bounds when
    /// the configuration has them.
    ///
    /// Calling `ask` again before [`CmaEs::tell`] returns the same population without drawing
    /// new random numbers, so a caller that crashed (or resumed from a checkpoint) between the
    /// two simply asks again.
    pub fn ask(&mut self) -> Vec<Vec<f64>> {
        if self.state.pending.is_empty() {
            self.sample();
        }
        self.state
            .pending
            .iter()
            .map(|x| self.phenotype(x))
            .collect()
    }

    fn sample(&mut self) {
        let n = self.dim();
        let s = &self.state;
        let pending = (0..self.strategy.lambda)
            .map(|_| {
                let scaled: Vec<f64> = s
                    .axis_lengths
                    .iter()
                    .map(|d| {
                        let z: f64 = StandardNormal.sample(&mut self.rng);
                        d * z
                    })
                    .collect();
                let y = mat_vec(&s.axes, &scaled);
                (0..n).map(|i| s.mean[i] + s.sigma * y[i]).collect()
            })
            .collect();
        self.state.pending = pending;
    }

    fn phenotype(&self, genotype: &[f64]) -> Vec<f64> {
        match &self.state.config.bounds {
            Some(b) => b.reflect(genotype),
            None => genotype.to_vec(),
        }
    }

    /// Reports the fitness of the population returned by the last [`CmaEs::ask`] (lower is
    /// better; `fitness[k]` belongs to `candidates[k]`) and updates the distribution.
    ///
    /// NaN and ±infinity are accepted and rank below every finite value (ties among them keep
    /// their order), so a failed simulation simply counts as the worst candidate. They never
    /// become [`CmaEs::best`].
    ///
    /// Errors: no population pending, wrong number of candidates or fitness values, or a
    /// candidate that is not the one `ask` returned (reordered or modified). The state is left
    /// unchanged on error.
    pub fn tell(&mut self, candidates: &[Vec<f64>], fitness: &[f64]) -> Result<(), Error> {
        if self.state.pending.is_empty() {
            return Err(Error::NoPendingPopulation);
        }
        let lambda = self.strategy.lambda;
        check_len("candidates", lambda, candidates.len())?;
        check_len("fitness", lambda, fitness.len())?;
        for (index, (cand, genotype)) in candidates.iter().zip(&self.state.pending).enumerate() {
            check_len("candidate", self.dim(), cand.len())?;
            if *cand != self.phenotype(genotype) {
                return Err(Error::ForeignCandidate { index });
            }
        }

        // Ranking: finite values ascending, then all non-finite ones in their given order.
        let key = |f: f64| if f.is_finite() { f } else { f64::INFINITY };
        let mut order: Vec<usize> = (0..lambda).collect();
        order.sort_by(|&a, &b| key(fitness[a]).total_cmp(&key(fitness[b])));
        let ranked: Vec<f64> = order.iter().map(|&k| key(fitness[k])).collect();

        let first = order[0];
        if fitness[first].is_finite() && self.state.best_f.is_none_or(|b| fitness[first] < b) {
            self.state.best_f = Some(fitness[first]);
            self.state.best_x = candidates[first].clone();
        }

        let pending = std::mem::take(&mut self.state.pending);
        self.update(&pending, &order, &ranked);
        self.state.generation += 1;
        self.state.evaluations += lambda as u64;
        self.record_history(&ranked);
        self.state.stop = self.check_stop(&ranked);
        Ok(())
    }

    /// One CMA-ES update (tutorial, Table 1 / Eqs. 39-47): mean, both evolution paths, σ by
    /// cumulative step-size adaptation, and C by the rank-one plus (active) rank-μ update.
    fn update(&mut self, genotypes: &[Vec<f64>], order: &[usize], ranked: &[f64]) {
        let n = self.dim();
        let st = &self.strategy;
        let s = &mut self.state;
        let old_mean = s.mean.clone();
        let sigma = s.sigma;

        // Steps y_k = (x_k - m) / σ in rank order, and their weighted mean over the parents.
        let steps: Vec<Vec<f64>> = order
            .iter()
            .map(|&k| {
                (0..n)
                    .map(|i| (genotypes[k][i] - old_mean[i]) / sigma)
                    .collect()
            })
            .collect();
        let mut y_w = vec![0.0; n];
        for (w, y) in st.weights[..st.mu].iter().zip(&steps) {
            for i in 0..n {
                y_w[i] += w * y[i];
            }
        }
        for i in 0..n {
            s.mean[i] = old_mean[i] + sigma * y_w[i];
        }

        // C^{-1/2} v = B D^{-1} Bᵀ v, with the decomposition of the C that generated the steps.
        let whiten = |v: &[f64]| -> Vec<f64> {
            let mut t = mat_t_vec(&s.axes, v);
            for (ti, d) in t.iter_mut().zip(&s.axis_lengths) {
                *ti /= d;
            }
            t
        };
        let white_y_w = mat_vec(&s.axes, &whiten(&y_w));
        let cs_norm = (st.cs * (2.0 - st.cs) * st.mueff).sqrt();
        for (p, w) in s.path_sigma.iter_mut().zip(&white_y_w) {
            *p = (1.0 - st.cs) * *p + cs_norm * w;
        }
        let ps_norm = norm(&s.path_sigma);

        // Stall the rank-one path while p_σ is long (σ still growing), which prevents C from
        // stretching too fast along a direction of a linear slope.
        let decay = 1.0 - (1.0 - st.cs).powf(2.0 * (s.generation as f64 + 1.0));
        let hsig = ps_norm / decay.sqrt() < (1.4 + 2.0 / (n as f64 + 1.0)) * st.chi_n;
        let cc_norm = (st.cc * (2.0 - st.cc) * st.mueff).sqrt();
        for (p, y) in s.path_c.iter_mut().zip(&y_w) {
            let push = if hsig { cc_norm * y } else { 0.0 };
            *p = (1.0 - st.cc) * *p + push;
        }

        // Active rank-μ weights: negative weights are rescaled by n / ‖C^{-1/2} y‖² so that the
        // variance removed along a bad step is bounded whatever the step's length.
        let adjusted: Vec<f64> = st
            .weights
            .iter()
            .zip(&steps)
            .map(|(&w, y)| {
                if w >= 0.0 {
                    w
                } else {
                    let len2 = norm(&whiten(y)).powi(2);
                    if len2 > 0.0 { w * n as f64 / len2 } else { 0.0 }
                }
            })
            .collect();
        let weight_sum: f64 = st.weights.iter().sum();
        let delta_h = if hsig { 0.0 } else { st.cc * (2.0 - st.cc) };
        let keep = 1.0 + st.c1 * delta_h - st.c1 - st.cmu * weight_sum;
        for i in 0..n {
            for j in i..n {
                let mut rank_mu = 0.0;
                for (w, y) in adjusted.iter().zip(&steps) {
                    rank_mu += w * y[i] * y[j];
                }
                let v =
                    keep * s.cov[i * n + j] + st.c1 * s.path_c[i] * s.path_c[j] + st.cmu * rank_mu;
                s.cov[i * n + j] = v;
                s.cov[j * n + i] = v;
            }
        }

        // Cumulative step-size adaptation; the exponent is capped at 1 (a factor e per
        // generation) as a guard against a single wild generation.
        let csa = (st.cs / st.damps) * (ps_norm / st.chi_n - 1.0);
        s.sigma *= csa.min(1.0).exp();
        let flat_rank = ((0.7 * st.lambda as f64).ceil() as usize).clamp(1, st.lambda) - 1;
        if ranked[0] == ranked[flat_rank] {
            s.sigma *= (FLAT_FITNESS_SIGMA_BOOST + st.cs / st.damps).exp();
        }

        // Variance floor for integer coordinates: raising a diagonal entry of a positive
        // definite matrix keeps it positive definite.
        for (i, &floor) in s.config.min_std.iter().enumerate() {
            let min_var = (floor / s.sigma).powi(2);
            if s.cov[i * n + i] < min_var {
                s.cov[i * n + i] = min_var;
            }
        }

        let (values, vectors) = symmetric_eigen(&s.cov, n);
        let largest = values.iter().copied().fold(0.0_f64, f64::max);
        // Rounding can push a theoretically positive eigenvalue to <= 0; clamp it to a tiny
        // positive value, far beyond any sensible condition limit, which ConditionCov reports.
        let floor = largest * 1e-30;
        s.axis_lengths = values.iter().map(|&v| v.max(floor).sqrt()).collect();
        s.axes = vectors;
    }

    fn record_history(&mut self, ranked: &[f64]) {
        let n = self.dim();
        let lambda = self.strategy.lambda;
        let s = &mut self.state;
        if ranked[0].is_finite() {
            push_capped(&mut s.recent_best, ranked[0], tolfun_window(n, lambda));
        }
        if s.config.termination.stagnation {
            let cap = stagnation_window(n, lambda);
            push_capped(&mut s.stagnation_best, ranked[0], cap);
            push_capped(&mut s.stagnation_median, median(ranked), cap);
        }
    }

    fn check_stop(&self, ranked: &[f64]) -> Option<StopReason> {
        let s = &self.state;
        let t = &s.config.termination;
        let n = self.dim();
        if let (Some(target), Some(best)) = (t.target, s.best_f)
            && best <= target
        {
            return Some(StopReason::TargetReached);
        }
        if t.max_evaluations.is_some_and(|m| s.evaluations >= m) {
            return Some(StopReason::MaxEvaluations);
        }
        if t.max_generations.is_some_and(|m| s.generation >= m) {
            return Some(StopReason::MaxGenerations);
        }
        let finite = s.sigma.is_finite()
            && s.mean.iter().all(|v| v.is_finite())
            && s.cov.iter().all(|v| v.is_finite())
            && s.axis_lengths.iter().all(|v| v.is_finite() && *v > 0.0);
        if !finite || s.sigma <= 0.0 {
            return Some(StopReason::NumericalInstability);
        }
        let d_max = s.axis_lengths.iter().copied().fold(0.0_f64, f64::max);
        let d_min = s.axis_lengths.iter().copied().fold(f64::INFINITY, f64::min);
        if s.sigma * d_max / s.config.sigma0 > t.tol_up_sigma {
            return Some(StopReason::TolUpSigma);
        }
        if (d_max / d_min).powi(2) > t.max_condition {
            return Some(StopReason::ConditionCov);
        }
        if s.recent_best.len() >= tolfun_window(n, self.strategy.lambda)
            && ranked.iter().all(|f| f.is_finite())
        {
            let hi = s
                .recent_best
                .iter()
                .chain(ranked)
                .copied()
                .fold(f64::MIN, f64::max);
            let lo = s
                .recent_best
                .iter()
                .chain(ranked)
                .copied()
                .fold(f64::MAX, f64::min);
            if hi - lo < t.tol_fun {
                return Some(StopReason::TolFun);
            }
        }
        let stds_small = (0..n).all(|i| s.sigma * s.cov[i * n + i].sqrt() < t.tol_x);
        if stds_small && s.path_c.iter().all(|p| s.sigma * p.abs() < t.tol_x) {
            return Some(StopReason::TolX);
        }
        let axis = (s.generation % n as u64) as usize;
        let shift = 0.1 * s.sigma * s.axis_lengths[axis];
        if (0..n).all(|i| s.mean[i] + shift * s.axes[i * n + axis] == s.mean[i]) {
            return Some(StopReason::NoEffectAxis);
        }
        if (0..n).any(|i| s.mean[i] + 0.2 * s.sigma * s.cov[i * n + i].sqrt() == s.mean[i]) {
            return Some(StopReason::NoEffectCoord);
        }
        if t.stagnation {
            let window = stagnation_window(n, self.strategy.lambda);
            if stagnated(&s.stagnation_best, window) && stagnated(&s.stagnation_median, window) {
                return Some(StopReason::Stagnation);
            }
        }
        None
    }

    /// Why the run should stop, or `None` while it should go on. Checked after every
    /// [`CmaEs::tell`]; asking and telling after a stop is allowed but rarely useful.
    pub fn should_stop(&self) -> Option<StopReason> {
        self.state.stop
    }

    /// The best candidate evaluated so far and its fitness (finite values only).
    pub fn best(&self) -> Option<(&[f64], f64)> {
        self.state.best_f.map(|f| (self.state.best_x.as_slice(), f))
    }

    /// Distribution mean, mapped into the bounds when those are set.
    pub fn mean(&self) -> Vec<f64> {
        self.phenotype(&self.state.mean)
    }

    /// Current step size σ.
    pub fn sigma(&self) -> f64 {
        self.state.sigma
    }

    /// Per-coordinate sampling standard deviations `σ √C_ii`.
    pub fn stds(&self) -> Vec<f64> {
        let n = self.dim();
        (0..n)
            .map(|i| self.state.sigma * self.state.cov[i * n + i].sqrt())
            .collect()
    }

    /// Completed generations (calls to [`CmaEs::tell`]).
    pub fn generation(&self) -> u64 {
        self.state.generation
    }

    /// Evaluated candidates, counted in whole generations as pycma does.
    pub fn evaluations(&self) -> u64 {
        self.state.evaluations
    }

    /// Search dimension `n`.
    pub fn dim(&self) -> usize {
        self.state.mean.len()
    }

    /// Population size λ.
    pub fn population_size(&self) -> usize {
        self.strategy.lambda
    }

    /// The configuration the run was started with.
    pub fn config(&self) -> &CmaesConfig {
        &self.state.config
    }
}

impl From<CmaEs> for State {
    fn from(es: CmaEs) -> Self {
        let mut state = es.state;
        state.rng_word_pos = es.rng.get_word_pos();
        state
    }
}

impl TryFrom<State> for CmaEs {
    type Error = Error;

    fn try_from(state: State) -> Result<Self, Error> {
        let bad = |msg: String| Err(Error::InvalidCheckpoint(msg));
        state
            .config
            .validate()
            .map_err(|e| Error::InvalidCheckpoint(e.to_string()))?;
        let n = state.config.dim();
        let lambda = state.config.population_size();
        for (name, len, expected) in [
            ("mean", state.mean.len(), n),
            ("cov", state.cov.len(), n * n),
            ("axes", state.axes.len(), n * n),
            ("axis_lengths", state.axis_lengths.len(), n),
            ("path_c", state.path_c.len(), n),
            ("path_sigma", state.path_sigma.len(), n),
        ] {
            if len != expected {
                return bad(format!("{name} has length {len}, expected {expected}"));
            }
        }
        if !state.pending.is_empty()
            && (state.pending.len() != lambda || state.pending.iter().any(|x| x.len() != n))
        {
            return bad(format!(
                "pending population is not {lambda} points of dimension {n}"
            ));
        }
        if state.best_f.is_some() != (state.best_x.len() == n) {
            return bad("best_x and best_f disagree".into());
        }
        if state.sigma.is_nan() || state.sigma <= 0.0 {
            return bad(format!("sigma = {} is not positive", state.sigma));
        }
        Self::from_state(state)
    }
}
