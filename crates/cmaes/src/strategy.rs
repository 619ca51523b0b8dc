//! Default strategy parameters of CMA-ES as given in Table 1 of Hansen, "The CMA Evolution
//! Strategy: A Tutorial" (arXiv:1604.00772), including the negative ("active") recombination
//! weights. They depend only on the dimension `n` and the population size `λ`, so they are
//! recomputed (not stored) when a checkpoint is resumed.

/// Learning rates, damping and recombination weights for one `(n, λ)`.
#[derive(Debug, Clone)]
pub(crate) struct Strategy {
    /// Population size λ.
    pub lambda: usize,
    /// Number of parents μ = ⌊λ/2⌋ (the candidates with positive weight).
    pub mu: usize,
    /// λ recombination weights, best candidate first: μ positive ones summing to 1, then
    /// non-positive ones for the active covariance update.
    pub weights: Vec<f64>,
    /// Variance-effective selection mass of the positive weights.
    pub mueff: f64,
    /// Cumulation rate of the evolution path `p_c`.
    pub cc: f64,
    /// Cumulation rate of the conjugate evolution path `p_σ`.
    pub cs: f64,
    /// Rank-one learning rate.
    pub c1: f64,
    /// Rank-μ learning rate.
    pub cmu: f64,
    /// Step-size damping.
    pub damps: f64,
    /// E‖N(0, I)‖, the expected length of a standard normal vector in `n` dimensions.
    pub chi_n: f64,
}

impl Strategy {
    pub(crate) fn new(n: usize, lambda: usize) -> Self {
        let nf = n as f64;
        let mu = lambda / 2;
        let raw: Vec<f64> = (1..=lambda)
            .map(|i| ((lambda as f64 + 1.0) / 2.0).ln() - (i as f64).ln())
            .collect();
        let pos = &raw[..mu];
        let neg = &raw[mu..];
        let pos_sum: f64 = pos.iter().sum();
        let pos_sq: f64 = pos.iter().map(|w| w * w).sum();
        let mueff = pos_sum * pos_sum / pos_sq;
        let neg_sum: f64 = neg.iter().map(|w| w.abs()).sum();
        let neg_sq: f64 = neg.iter().map(|w| w * w).sum();
        let mueff_neg = if neg_sq > 0.0 {
            neg_sum * neg_sum / neg_sq
        } else {
            0.0
        };

        let alpha_cov = 2.0;
        let c1 = alpha_cov / ((nf + 1.3).powi(2) + mueff);
        let cmu = (1.0 - c1).min(
            alpha_cov * (0.25 + mueff + 1.0 / mueff - 2.0)
                / ((nf + 2.0).powi(2) + alpha_cov * mueff / 2.0),
        );

        // Scale of the negative weights: the smallest of three limits. The first makes
        // c1 + cμ Σw = 0 (no net decay of C), the second bounds it by the negative selection
        // mass, the third keeps C positive definite.
        let alpha_mu_neg = 1.0 + c1 / cmu;
        let alpha_mueff_neg = 1.0 + 2.0 * mueff_neg / (mueff + 2.0);
        let alpha_posdef_neg = (1.0 - c1 - cmu) / (nf * cmu);
        let neg_scale = alpha_mu_neg.min(alpha_mueff_neg).min(alpha_posdef_neg);

        let weights = raw
            .iter()
            .enumerate()
            .map(|(i, &w)| {
                if i < mu {
                    w / pos_sum
                } else if neg_sum > 0.0 {
                    neg_scale * w / neg_sum
                } else {
                    0.0
                }
            })
            .collect();

        let cs = (mueff + 2.0) / (nf + mueff + 5.0);
        let damps = 1.0 + 2.0 * (((mueff - 1.0) / (nf + 1.0)).sqrt() - 1.0).max(0.0) + cs;
        let cc = (4.0 + mueff / nf) / (nf + 4.0 + 2.0 * mueff / nf);
        let chi_n = nf.sqrt() * (1.0 - 1.0 / (4.0 * nf) + 1.0 / (21.0 * nf * nf));
        Self {
            lambda,
            mu,
            weights,
            mueff,
            cc,
            cs,
            c1,
            cmu,
            damps,
            chi_n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positive_weights_sum_to_one_and_decrease() {
        for (n, lambda) in [(2, 6), (10, 10), (10, 11), (20, 80)] {
            let s = Strategy::new(n, lambda);
            let pos: f64 = s.weights[..s.mu].iter().sum();
            assert!((pos - 1.0).abs() < 1e-12);
            assert!(s.weights.windows(2).all(|w| w[0] >= w[1]));
            assert!(s.weights[s.mu..].iter().all(|&w| w <= 0.0));
        }
    }

    #[test]
    fn ten_dimensional_constants_match_hand_computation() {
        // n = 10, λ = 10, μ = 5: raw weights ln(5.5) - ln(i).
        let s = Strategy::new(10, 10);
        let raw: Vec<f64> = (1..=5).map(|i| 5.5_f64.ln() - (i as f64).ln()).collect();
        let sum: f64 = raw.iter().sum();
        let sq: f64 = raw.iter().map(|w| w * w).sum();
        let mueff = sum * sum / sq;
        assert!((s.mueff - mueff).abs() < 1e-12);
        assert!((mueff - 3.1672).abs() < 1e-3, "mueff {mueff}");
        assert!((s.cs - (mueff + 2.0) / (15.0 + mueff)).abs() < 1e-15);
        assert!((s.c1 - 2.0 / (11.3 * 11.3 + mueff)).abs() < 1e-15);
        // Here the first limit binds: Σ|w⁻| = 1 + c1/cμ (≈ 1.649 < 2.54 and 4.08 for the
        // other two), so c1 + cμ Σw = 0.
        let neg: f64 = s.weights[5..].iter().map(|w| w.abs()).sum();
        assert!((neg - (1.0 + s.c1 / s.cmu)).abs() < 1e-12);
        assert!((neg - 1.649).abs() < 1e-3, "{neg}");
        let total: f64 = s.weights.iter().sum();
        assert!((s.c1 + s.cmu * total).abs() < 1e-15);
    }
}
