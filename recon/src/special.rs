//! The standard normal distribution: density and cumulative distribution.
//!
//! The renderer integrates each primitive's temporal Gaussian over a bin as a
//! difference of CDFs. Accuracy matters here (finite-difference gradient checks compare
//! the CDF's slope with the density), so the CDF is the correctly rounded-ish `erfc`
//! of `libm` (a port of FreeBSD's msun, < 1 ulp).

/// 1/√(2π).
pub const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

/// Standard normal density φ(z).
#[inline]
pub fn norm_pdf(z: f64) -> f64 {
    INV_SQRT_2PI * (-0.5 * z * z).exp()
}

/// Standard normal CDF Φ(z), accurate in both tails (no `1 − x` cancellation).
#[inline]
pub fn norm_cdf(z: f64) -> f64 {
    0.5 * libm::erfc(-z * std::f64::consts::FRAC_1_SQRT_2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdf_matches_known_values_and_tails() {
        assert!((norm_cdf(0.0) - 0.5).abs() < 1e-16);
        assert!((norm_cdf(1.0) - 0.841_344_746_068_542_9).abs() < 1e-15);
        assert!((norm_cdf(-3.0) - 1.349_898_031_630_094_6e-3).abs() < 1e-17);
        assert!(norm_cdf(-40.0) >= 0.0 && norm_cdf(40.0) == 1.0);
    }

    #[test]
    fn cdf_slope_is_the_density() {
        for z in [-4.0, -1.3, 0.0, 0.7, 2.5] {
            let h = 1e-5;
            let slope = (norm_cdf(z + h) - norm_cdf(z - h)) / (2.0 * h);
            assert!(
                (slope - norm_pdf(z)).abs() < 1e-9,
                "z = {z}: {slope} vs {}",
                norm_pdf(z)
            );
        }
    }
}
