//! Filter-consistency helpers: NEES of an error/covariance pair, χ² quantiles and the two-sided
//! ANEES acceptance band for Monte Carlo runs (Bar-Shalom, Li & Kirubarajan §5.4), and
//! angle-aware state errors.

use crate::ins::{VehicleState, VehicleVector};
use crate::rotation::wrap_angle;
use crate::state::ATT;
use nalgebra::{DMatrix, DVector};
use statrs::distribution::{ChiSquared, ContinuousCDF};

/// Why a consistency statistic could not be computed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ConsistencyError {
    /// Error vector and covariance sizes differ.
    #[error("error has {error} components but the covariance is {rows}×{cols}")]
    DimensionMismatch {
        /// Error length.
        error: usize,
        /// Covariance rows.
        rows: usize,
        /// Covariance columns.
        cols: usize,
    },
    /// The covariance is not symmetric positive definite (Cholesky failed).
    #[error("covariance is not positive definite")]
    NotPositiveDefinite,
    /// A NaN or infinite input.
    #[error("non-finite input")]
    NonFinite,
    /// Degrees of freedom or probability out of range.
    #[error("invalid χ² arguments: dof {dof}, probability {probability}")]
    InvalidQuantile {
        /// Degrees of freedom.
        dof: f64,
        /// Probability.
        probability: f64,
    },
}

/// Normalized estimation error squared ε = eᵀ P⁻¹ e (by Cholesky; no explicit inverse).
pub fn nees(error: &DVector<f64>, covariance: &DMatrix<f64>) -> Result<f64, ConsistencyError> {
    if covariance.nrows() != error.len() || covariance.ncols() != error.len() {
        return Err(ConsistencyError::DimensionMismatch {
            error: error.len(),
            rows: covariance.nrows(),
            cols: covariance.ncols(),
        });
    }
    if !error.iter().chain(covariance.iter()).all(|v| v.is_finite()) {
        return Err(ConsistencyError::NonFinite);
    }
    let chol = covariance
        .clone()
        .cholesky()
        .ok_or(ConsistencyError::NotPositiveDefinite)?;
    let mut w = error.clone();
    chol.l().solve_lower_triangular_mut(&mut w);
    Ok(w.norm_squared())
}

/// The χ² quantile with `dof` degrees of freedom at `probability` (e.g. 7.815 for 3 dof at 0.95).
pub fn chi2_quantile(dof: f64, probability: f64) -> Result<f64, ConsistencyError> {
    if !(dof > 0.0 && dof.is_finite() && probability > 0.0 && probability < 1.0) {
        return Err(ConsistencyError::InvalidQuantile { dof, probability });
    }
    let d =
        ChiSquared::new(dof).map_err(|_| ConsistencyError::InvalidQuantile { dof, probability })?;
    Ok(d.inverse_cdf(probability))
}

/// Two-sided `confidence` band for the average NEES over `runs` Monte Carlo runs of `dof`-dimensional
/// errors: [χ²_{runs·dof}((1−c)/2), χ²_{runs·dof}((1+c)/2)] / runs.
pub fn anees_band(
    runs: usize,
    dof: usize,
    confidence: f64,
) -> Result<(f64, f64), ConsistencyError> {
    let n = (runs * dof) as f64;
    let tail = (1.0 - confidence) / 2.0;
    let lo = chi2_quantile(n, tail)?;
    let hi = chi2_quantile(n, 1.0 - tail)?;
    Ok((lo / runs as f64, hi / runs as f64))
}

/// Estimate − truth for a vehicle state, with the Euler-angle differences wrapped to (−π, π].
pub fn vehicle_error(estimate: &VehicleState, truth: &VehicleState) -> VehicleVector {
    let mut e = estimate.to_vector() - truth.to_vector();
    for i in ATT..ATT + 3 {
        e[i] = wrap_angle(e[i]);
    }
    e
}

/// a − b for angles, wrapped to (−π, π].
pub fn angle_difference(a: f64, b: f64) -> f64 {
    wrap_angle(a - b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn chi2_quantiles_match_tables() {
        // Published table values (Abramowitz & Stegun 26.4), to the printed 3 decimals.
        assert!((chi2_quantile(3.0, 0.95).unwrap() - 7.815).abs() < 1e-3);
        assert!((chi2_quantile(2.0, 0.95).unwrap() - 5.991).abs() < 1e-3);
        assert!((chi2_quantile(1.0, 0.975).unwrap() - 5.024).abs() < 1e-3);
        assert!(chi2_quantile(0.0, 0.5).is_err());
        assert!(chi2_quantile(3.0, 1.0).is_err());
    }

    #[test]
    fn anees_band_for_fifty_runs_of_three_dof() {
        // χ²_150 quantiles 117.98 and 185.80 (table), divided by 50 runs.
        let (lo, hi) = anees_band(50, 3, 0.95).unwrap();
        assert!((lo - 117.985 / 50.0).abs() < 2e-3, "{lo}");
        assert!((hi - 185.800 / 50.0).abs() < 2e-3, "{hi}");
    }

    #[test]
    fn nees_matches_closed_form_and_rejects_bad_input() {
        // Diagonal covariance: ε = Σ e_i²/σ_i².
        let p = DMatrix::from_diagonal(&DVector::from_vec(vec![4.0, 1.0, 0.25]));
        let e = DVector::from_vec(vec![2.0, 1.0, 0.5]);
        // Cholesky of a diagonal matrix is exact up to one rounding per entry.
        assert!((nees(&e, &p).unwrap() - 3.0).abs() < 1e-14);
        // Correlated 2×2: closed-form inverse.
        let p = DMatrix::from_row_slice(2, 2, &[2.0, 0.5, 0.5, 1.0]);
        let e = DVector::from_vec(vec![1.0, -1.0]);
        // P⁻¹ = [[p11, −p01], [−p01, p00]] / det, so ε = (e0² p11 − 2 e0 e1 p01 + e1² p00) / det.
        let (p00, p01, p11) = (2.0, 0.5, 1.0);
        let (e0, e1) = (1.0, -1.0);
        let det = p00 * p11 - p01 * p01;
        let expected = (e0 * e0 * p11 - 2.0 * e0 * e1 * p01 + e1 * e1 * p00) / det;
        // 2×2 Cholesky vs the closed form: a few roundings on O(1) values.
        assert!((nees(&e, &p).unwrap() - expected).abs() < 1e-14);
        let bad = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]);
        assert_eq!(nees(&e, &bad), Err(ConsistencyError::NotPositiveDefinite));
        assert_eq!(
            nees(&DVector::from_vec(vec![f64::NAN, 0.0]), &p),
            Err(ConsistencyError::NonFinite)
        );
        assert!(matches!(
            nees(&DVector::zeros(3), &p),
            Err(ConsistencyError::DimensionMismatch { .. })
        ));
    }

    #[test]
    fn vehicle_error_wraps_yaw() {
        let mut a = VehicleState {
            position: Vector3::zeros(),
            velocity: Vector3::zeros(),
            attitude: Vector3::new(0.0, 0.0, 3.1),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        };
        let mut b = a;
        b.attitude.z = -3.1;
        a.position.x = 1.0;
        let e = vehicle_error(&a, &b);
        // Exact wrap arithmetic on O(1) angles: round-off only.
        assert!((e[ATT + 2] - (6.2 - std::f64::consts::TAU)).abs() < 1e-12);
        assert_eq!(e[0], 1.0);
    }
}
