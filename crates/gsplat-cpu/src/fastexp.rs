//! A branch-free `exp` for the compositor's inner loop.
//!
//! The libm call cannot be vectorised; this one can (only multiplies, adds, compares and bit
//! manipulation, all SSE2). Relative error below 3e-7 on the range the
//! compositor uses (`x` in `[-87, 0]`), i.e. about two f32 ulps.

/// `exp(x)` for `x <= 0`; inputs below -87 are treated as -87 (`exp(-87) ≈ 1.6e-38`, far under
/// any alpha that is drawn), inputs above 0 as 0.
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f32) -> f32 {
    // Plain comparisons rather than f32::min/max: those add NaN handling that blocks
    // vectorisation (NaN cannot reach here: conics and offsets are finite).
    let x = if x < -87.0 { -87.0 } else { x };
    let x = if x > 0.0 { 0.0 } else { x };
    // x = n ln2 + r with n = round(x / ln2), |r| <= ln2 / 2. Adding 1.5 * 2^23 rounds to an
    // integer and leaves it in the low mantissa bits: no float-to-int conversion needed.
    const SHIFT: f32 = 12_582_912.0;
    let big = x * std::f32::consts::LOG2_E + SHIFT;
    let nf = big - SHIFT;
    let n = big.to_bits().wrapping_sub(SHIFT.to_bits());
    // ln2 split into a part exact in f32 and a small correction (Cody-Waite), so r keeps its
    // precision.
    let r = x - nf * 0.693_359_4 + nf * 2.121_944_4e-4;
    // Taylor series of exp(r) to degree 6: truncation error < |r|^7 / 7! ≈ 1.2e-7.
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    // 2^n from its exponent bits (n is in [-126, 0] as a two's-complement u32, so n + 127 is
    // a valid biased exponent of a normal float).
    p * f32::from_bits(n.wrapping_add(127) << 23)
}

#[cfg(test)]
mod tests {
    use super::exp_nonpositive;

    #[test]
    fn matches_f64_exp() {
        let mut worst = 0f64;
        for k in 0..=870_000 {
            let x = -(k as f32) * 1e-4;
            let want = (x as f64).exp();
            let got = exp_nonpositive(x) as f64;
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
        assert_eq!(exp_nonpositive(0.0), 1.0);
        assert!(exp_nonpositive(-1e30) > 0.0 && exp_nonpositive(-1e30) < 1e-37);
        assert_eq!(exp_nonpositive(5.0), 1.0);
        assert!(exp_nonpositive(f32::NEG_INFINITY) < 1e-37);
    }
}
