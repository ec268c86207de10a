//! Map information in information form, keyed by global feature id (eqs. 21.86, 21.87).
//!
//! Block `i` of a map vector or matrix (rows `3i..3i+3`) belongs to feature `ids[i]`.
//!
//! # Origin convention
//! ECEF coordinates are ~6.4e6 m; forming y = Y·x with them and subtracting such vectors across
//! vehicles would lose digits. Every [`MapInformation`] therefore carries a team-wide `origin`
//! o (the ECEF launch site in global SLAM, zero in local SLAM) and stores y = Y·(x_m − o) with the
//! origin subtracted from every feature. All nodes of a team share the same origin.

use crate::sensor::FeatureId;
use faer::{Col, Mat};
use nalgebra::Vector3;

/// A vehicle's map marginal (x_m, P_mm) of eqs. 21.84, 21.85, keyed by feature id.
#[derive(Clone, Debug)]
pub struct MapMarginal {
    /// Feature ids, one per 3-block.
    pub ids: Vec<FeatureId>,
    /// Feature positions x_m in absolute frame coordinates (ECEF or local NED) [m].
    pub mean: Col<f64>,
    /// Covariance P_mm, 3n × 3n, symmetric positive definite.
    pub covariance: Mat<f64>,
}

/// Map information (Y, y) = (P_mm⁻¹, P_mm⁻¹ (x_m − o)) (eqs. 21.86, 21.87, origin convention
/// above), or a difference of two such (a delta, which may be indefinite).
#[derive(Clone, Debug)]
pub struct MapInformation {
    /// Feature ids, one per 3-block.
    pub ids: Vec<FeatureId>,
    /// The team-wide origin o subtracted from feature positions in `vector`.
    pub origin: Vector3<f64>,
    /// Y, 3n × 3n, symmetric.
    pub matrix: Mat<f64>,
    /// y, 3n.
    pub vector: Col<f64>,
}
