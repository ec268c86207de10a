//! Covariance intersection (Julier & Uhlmann), the fallback of bandwidth-limited links
//! (chapter §21.5.4, design.md §4).
//!
//! Two estimates with unknown cross-correlation are fused as
//! P⁻¹ = ω P_a⁻¹ + (1 − ω) P_b⁻¹, P⁻¹x = ω P_a⁻¹ x_a + (1 − ω) P_b⁻¹ x_b, ω ∈ [0, 1],
//! which is consistent for *any* cross-correlation; ω minimises the trace or the determinant of
//! the fused covariance ([`CiCriterion`]).
//!
//! A link that cannot carry its full delta sends a [`Submap`]: the marginal (x_S, P_S) of the
//! highest-priority features in covariance form. The receiver fuses it in information space with
//! the submap embedded (E maps submap rows into the receiver's map, new features augment it):
//! Y' = ω Y + (1 − ω) E Y_S Eᵀ, y' = ω y + (1 − ω) E y_S ([`fuse_submap`]).
//!
//! # Choosing ω cheaply and exactly
//! Split the receiver's map into the submap features s and the rest r. With A = Y (embedded),
//! B = Y_S, and Ā_s = A_ss − A_sr A_rr⁻¹ A_rs (the receiver's *marginal* information of s),
//! the Schur complement of Y'_rr = ω A_rr gives
//!   det Y' = ω^{n_r} det A_rr · det(ω Ā_s + (1 − ω) B),
//!   tr P'  = tr((I + GᵀG)(ω Ā_s + (1 − ω) B)⁻¹) + tr(A_rr⁻¹)/ω,  G = A_rr⁻¹ A_rs.
//! With B = L Lᵀ and L⁻¹ Ā_s L⁻ᵀ = Q diag(μ) Qᵀ, ω Ā_s + (1 − ω) B = L Q diag(1 − ω + ω μ_i) Qᵀ Lᵀ,
//! so both criteria are explicit sums over the n_s eigenvalues μ_i; both are convex in ω, and
//! ω is found by bisection on the analytic derivative. The two-full-estimate case is n_r = 0.

use crate::info::{InfoError, MapInformation, MapMarginal};
use crate::sensor::FeatureId;
use crate::state::FEATURE_DIM;
use faer::linalg::solvers::DenseSolveCore;
use faer::linalg::triangular_solve::{
    solve_lower_triangular_in_place, solve_upper_triangular_in_place,
};
use faer::{Col, Mat, MatRef, Par, Side};
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, HashSet};

/// What ω minimises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum CiCriterion {
    /// tr P (sum of variances).
    #[default]
    Trace,
    /// det P (volume of the uncertainty ellipsoid).
    Determinant,
}

/// Errors of covariance intersection.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CiError {
    /// Invalid or non-positive-definite input.
    #[error(transparent)]
    Info(#[from] InfoError),
    /// Two full estimates of different sizes.
    #[error("CI of estimates of different dimension: {0} vs {1}")]
    Dimension(usize, usize),
    /// A covariance or information that must be positive definite is not.
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
    /// The symmetric eigenvalue solver did not converge.
    #[error("symmetric eigenvalue solver did not converge")]
    Eigen,
}

/// A full estimate in covariance form.
#[derive(Clone, Debug)]
pub struct Gaussian {
    /// Mean x.
    pub mean: Col<f64>,
    /// Covariance P, symmetric positive definite.
    pub covariance: Mat<f64>,
}

/// The result of CI of two full estimates.
#[derive(Clone, Debug)]
pub struct CiFull {
    /// The weight ω of the first estimate.
    pub omega: f64,
    /// The fused estimate.
    pub fused: Gaussian,
}

/// The spectral form of the CI objective (module docs).
#[derive(Clone, Debug)]
struct Spectrum {
    /// Eigenvalues μ_i of L⁻¹ Ā_s L⁻ᵀ, clamped at 0 (Ā_s is PSD; round-off may dip below).
    mu: Vec<f64>,
    /// Trace weights w_i = q̃_iᵀ W q̃_i, q̃_i = L⁻ᵀ q_i.
    w: Vec<f64>,
    /// tr(A_rr⁻¹).
    c: f64,
    /// Dimension of the rest r.
    n_r: usize,
}

impl Spectrum {
    /// dφ/dω of the criterion (φ = tr P' or ln det P' up to constants); increasing in ω.
    fn derivative(&self, omega: f64, criterion: CiCriterion) -> f64 {
        match criterion {
            CiCriterion::Determinant => {
                // φ = −n_r ln ω − Σ ln(1 − ω + ω μ_i)
                // The n_r term only when there is a rest (0/0 at ω = 0 otherwise).
                let mut d = if self.n_r > 0 {
                    -(self.n_r as f64) / omega
                } else {
                    0.0
                };
                for &m in &self.mu {
                    d -= (m - 1.0) / (1.0 - omega + omega * m);
                }
                d
            }
            CiCriterion::Trace => {
                // φ = Σ w_i / (1 − ω + ω μ_i) + c / ω
                let mut d = if self.c > 0.0 {
                    -self.c / (omega * omega)
                } else {
                    0.0
                };
                for (&m, &w) in self.mu.iter().zip(&self.w) {
                    let h = 1.0 - omega + omega * m;
                    d -= w * (m - 1.0) / (h * h);
                }
                d
            }
        }
    }

    /// The minimiser over [0, 1]: the convex objective's derivative is increasing, so the
    /// endpoints decide the boundary cases and bisection finds the interior root to machine
    /// precision (the bracket halves 60 times: 2⁻⁶⁰ ≈ 1e-18).
    fn optimal_omega(&self, criterion: CiCriterion) -> f64 {
        // Endpoint derivatives: ω = 0 gives −∞ when n_r > 0 (the rest would lose all
        // information), ω = 1 gives +∞ when some μ_i = 0 (a submap direction unknown to the
        // receiver). NaN cannot arise: μ_i ≥ 0, 0 < h_i on the open interval, and the 1/ω terms
        // are only present when their numerators are positive.
        if self.derivative(0.0, criterion) >= 0.0 {
            return 0.0;
        }
        if self.derivative(1.0, criterion) <= 0.0 {
            return 1.0;
        }
        let (mut lo, mut hi) = (0.0_f64, 1.0_f64);
        for _ in 0..60 {
            let mid = 0.5 * (lo + hi);
            if self.derivative(mid, criterion) > 0.0 {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        0.5 * (lo + hi)
    }
}

fn cholesky_lower(m: MatRef<'_, f64>, what: &'static str) -> Result<Mat<f64>, CiError> {
    m.llt(Side::Lower)
        .map(|l| l.L().to_owned())
        .map_err(|_| CiError::NotPositiveDefinite(what))
}

/// The spectrum of ω Ā + (1 − ω) B against B = L Lᵀ, with trace weight W (identity if None).
fn spectrum(
    a_bar: MatRef<'_, f64>,
    b: MatRef<'_, f64>,
    weight: Option<MatRef<'_, f64>>,
    c: f64,
    n_r: usize,
) -> Result<Spectrum, CiError> {
    let n = b.nrows();
    let l = cholesky_lower(b, "submap information")?;
    // X = L⁻¹ Ā, then M = L⁻¹ Xᵀ = L⁻¹ Ā L⁻ᵀ (Ā symmetric).
    let mut x = a_bar.to_owned();
    solve_lower_triangular_in_place(l.as_ref(), x.as_mut(), Par::Seq);
    let mut m = x.transpose().to_owned();
    solve_lower_triangular_in_place(l.as_ref(), m.as_mut(), Par::Seq);
    let m = Mat::from_fn(n, n, |i, j| 0.5 * (m[(i, j)] + m[(j, i)]));
    let eig = m
        .as_ref()
        .self_adjoint_eigen(Side::Lower)
        .map_err(|_| CiError::Eigen)?;
    let mu: Vec<f64> = (0..n).map(|i| eig.S()[i].max(0.0)).collect();
    // q̃ = L⁻ᵀ Q.
    let mut qt = eig.U().to_owned();
    solve_upper_triangular_in_place(l.transpose(), qt.as_mut(), Par::Seq);
    let w = (0..n)
        .map(|i| {
            let q = qt.col(i);
            match weight {
                None => q.squared_norm_l2(),
                Some(wm) => (q.transpose() * wm * q).max(0.0),
            }
        })
        .collect();
    Ok(Spectrum { mu, w, c, n_r })
}

fn invert_spd(m: MatRef<'_, f64>, what: &'static str) -> Result<Mat<f64>, CiError> {
    let llt = m
        .llt(Side::Lower)
        .map_err(|_| CiError::NotPositiveDefinite(what))?;
    let inv = llt.inverse();
    let n = inv.nrows();
    Ok(Mat::from_fn(n, n, |i, j| 0.5 * (inv[(i, j)] + inv[(j, i)])))
}

/// ω of CI for two full estimates with covariances `p_a`, `p_b` (weight of `p_a`'s information).
pub fn omega_full(p_a: &Mat<f64>, p_b: &Mat<f64>, criterion: CiCriterion) -> Result<f64, CiError> {
    if p_a.nrows() != p_b.nrows() || p_a.ncols() != p_a.nrows() || p_b.ncols() != p_b.nrows() {
        return Err(CiError::Dimension(p_a.nrows(), p_b.nrows()));
    }
    for (what, p) in [("first covariance", p_a), ("second covariance", p_b)] {
        if (0..p.ncols()).any(|j| p.col_as_slice(j).iter().any(|v| !v.is_finite())) {
            return Err(CiError::Info(InfoError::NonFinite {
                what,
                row: 0,
                col: 0,
            }));
        }
    }
    let y_a = invert_spd(p_a.as_ref(), "first covariance")?;
    let y_b = invert_spd(p_b.as_ref(), "second covariance")?;
    Ok(spectrum(y_a.as_ref(), y_b.as_ref(), None, 0.0, 0)?.optimal_omega(criterion))
}

/// CI of two full estimates of the same state: ω by [`omega_full`], then
/// P = (ω P_a⁻¹ + (1 − ω) P_b⁻¹)⁻¹, x = P (ω P_a⁻¹ x_a + (1 − ω) P_b⁻¹ x_b).
pub fn fuse_full(a: &Gaussian, b: &Gaussian, criterion: CiCriterion) -> Result<CiFull, CiError> {
    let n = a.covariance.nrows();
    if a.mean.nrows() != n || b.mean.nrows() != n {
        return Err(CiError::Dimension(a.mean.nrows(), b.mean.nrows()));
    }
    let omega = omega_full(&a.covariance, &b.covariance, criterion)?;
    let y_a = invert_spd(a.covariance.as_ref(), "first covariance")?;
    let y_b = invert_spd(b.covariance.as_ref(), "second covariance")?;
    let y = Mat::from_fn(n, n, |i, j| {
        omega * y_a[(i, j)] + (1.0 - omega) * y_b[(i, j)]
    });
    let v = &y_a * &a.mean * omega + &y_b * &b.mean * (1.0 - omega);
    let covariance = invert_spd(y.as_ref(), "fused information")?;
    let mean = &covariance * v;
    Ok(CiFull {
        omega,
        fused: Gaussian { mean, covariance },
    })
}

/// A submap in covariance form, as sent over a bandwidth-limited link: the sender's marginal
/// (x_S, P_S) of a few features. Positions are stored relative to the team origin (module
/// docs of [`crate::info`]), so that ECEF coordinates do not cost digits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Submap {
    /// Feature ids, one per 3-block.
    pub ids: Vec<FeatureId>,
    /// The team origin o.
    pub origin: [f64; 3],
    /// x_S − o, 3n.
    pub offset_mean: Vec<f64>,
    /// P_S, upper triangle packed column by column: (0,0), (0,1), (1,1), (0,2), …
    pub covariance_packed: Vec<f64>,
}

/// Upper bound of bytes per f64 / id / length prefix in bincode's standard configuration.
const F64_BYTES: usize = 8;
const ID_BYTES: usize = 9;
const LEN_BYTES: usize = 9;

impl Submap {
    /// The submap of `ids` (in that order; ids absent from the marginal are skipped) taken
    /// from a marginal in absolute coordinates.
    pub fn from_marginal(marginal: &MapMarginal, ids: &[FeatureId], origin: Vector3<f64>) -> Self {
        let m = marginal.restrict(ids);
        let n = FEATURE_DIM * m.ids.len();
        let mut packed = Vec::with_capacity(n * (n + 1) / 2);
        for j in 0..n {
            for i in 0..=j {
                packed.push(m.covariance[(i, j)]);
            }
        }
        Submap {
            ids: m.ids,
            origin: origin.into(),
            offset_mean: (0..n)
                .map(|r| m.mean[r] - origin[r % FEATURE_DIM])
                .collect(),
            covariance_packed: packed,
        }
    }

    /// The submap in the key space of `keys` (module [`crate::keys`]): ids renamed to their
    /// canonical keys; when two of its features turn out to be one, the later one is left out
    /// (a submap is a marginal: dropping features keeps it valid and conservative).
    pub fn rekeyed(&self, keys: &crate::keys::KeyMap) -> Submap {
        if !keys.touches(&self.ids) {
            return self.clone();
        }
        let mut seen = HashSet::new();
        let keep: Vec<(usize, FeatureId)> = self
            .ids
            .iter()
            .enumerate()
            .filter_map(|(b, &id)| {
                let c = keys.canonical(id);
                seen.insert(c).then_some((b, c))
            })
            .collect();
        let rows: Vec<usize> = keep
            .iter()
            .flat_map(|&(b, _)| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * b + a))
            .collect();
        let p = self.covariance();
        let n = rows.len();
        let mut packed = Vec::with_capacity(n * (n + 1) / 2);
        for j in 0..n {
            for i in 0..=j {
                packed.push(p[(rows[i], rows[j])]);
            }
        }
        Submap {
            ids: keep.iter().map(|&(_, c)| c).collect(),
            origin: self.origin,
            offset_mean: rows.iter().map(|&r| self.offset_mean[r]).collect(),
            covariance_packed: packed,
        }
    }

    /// An upper bound of the bytes of a submap of `features` features on the wire.
    pub fn wire_bytes_for(features: usize) -> usize {
        let n = FEATURE_DIM * features;
        3 * LEN_BYTES + ID_BYTES * features + F64_BYTES * (3 + n + n * (n + 1) / 2)
    }

    /// An upper bound of this submap's bytes on the wire.
    pub fn wire_bytes(&self) -> usize {
        Self::wire_bytes_for(self.ids.len())
    }

    /// Checks sizes, unique ids and finiteness (positive definiteness is checked by
    /// [`information`](Self::information)).
    pub fn validate(&self) -> Result<(), InfoError> {
        let mut seen = HashSet::new();
        for &id in &self.ids {
            if !seen.insert(id) {
                return Err(InfoError::DuplicateId(id));
            }
        }
        let n = FEATURE_DIM * self.ids.len();
        for (what, expected, found) in [
            ("submap mean", n, self.offset_mean.len()),
            (
                "submap covariance",
                n * (n + 1) / 2,
                self.covariance_packed.len(),
            ),
        ] {
            if expected != found {
                return Err(InfoError::Dimension {
                    what,
                    expected,
                    found,
                });
            }
        }
        for (what, v) in [
            ("submap origin", &self.origin[..]),
            ("submap mean", &self.offset_mean[..]),
            ("submap covariance", &self.covariance_packed[..]),
        ] {
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(InfoError::NonFinite {
                    what,
                    row: i,
                    col: 0,
                });
            }
        }
        Ok(())
    }

    /// P_S as a dense symmetric matrix.
    pub fn covariance(&self) -> Mat<f64> {
        let n = FEATURE_DIM * self.ids.len();
        let mut p = Mat::zeros(n, n);
        let mut k = 0;
        for j in 0..n {
            for i in 0..=j {
                p[(i, j)] = self.covariance_packed[k];
                p[(j, i)] = self.covariance_packed[k];
                k += 1;
            }
        }
        p
    }

    /// The submap in information form (Y_S, y_S) = (P_S⁻¹, P_S⁻¹(x_S − o)) (eqs. 21.86, 21.87).
    pub fn information(&self) -> Result<MapInformation, InfoError> {
        self.validate()?;
        let n = FEATURE_DIM * self.ids.len();
        let marginal = MapMarginal {
            ids: self.ids.clone(),
            mean: Col::from_fn(n, |r| self.offset_mean[r]),
            covariance: self.covariance(),
        };
        let mut info = MapInformation::from_marginal(&marginal, Vector3::zeros())?;
        info.origin = Vector3::from(self.origin);
        Ok(info)
    }
}

/// The result of fusing a submap into a map by CI.
#[derive(Clone, Debug)]
pub struct CiFusion {
    /// The weight ω of the receiver's own information.
    pub omega: f64,
    /// The fused map information over the union of ids (receiver's ids first).
    pub fused: MapInformation,
    /// fused − receiver: what the caller adds to its estimate. Usually indefinite (CI lowers
    /// information in some directions), which is why deltas are validated as symmetric and
    /// finite but not definite.
    pub delta: MapInformation,
}

/// Partial-state CI in information space with the submap embedded (module docs):
/// Y' = ω Y + (1 − ω) E Y_S Eᵀ, y' = ω y + (1 − ω) E y_S, with ω minimising the trace or the
/// determinant of the receiver's whole fused covariance Y'⁻¹ (computed exactly through the
/// Schur complement on the features outside the submap). Features new to the receiver augment
/// its map. The receiver's information on its features outside the submap must be positive
/// definite.
pub fn fuse_submap(
    receiver: &MapInformation,
    submap: &Submap,
    criterion: CiCriterion,
) -> Result<CiFusion, CiError> {
    receiver.validate()?;
    let sub = submap.information()?;
    if receiver.origin != sub.origin {
        return Err(CiError::Info(InfoError::OriginMismatch {
            left: receiver.origin.into(),
            right: sub.origin.into(),
        }));
    }
    // Union (receiver's ids first): Â = receiver embedded, zero on new features.
    let union = receiver.add(&sub.scaled(0.0))?;
    let index: HashMap<FeatureId, usize> = union
        .ids
        .iter()
        .enumerate()
        .map(|(k, &id)| (id, k))
        .collect();
    let in_sub: HashSet<FeatureId> = sub.ids.iter().copied().collect();
    let rows = |blocks: &[usize]| -> Vec<usize> {
        blocks
            .iter()
            .flat_map(|&b| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * b + a))
            .collect()
    };
    let s_rows = rows(&sub.ids.iter().map(|id| index[id]).collect::<Vec<_>>());
    let r_blocks: Vec<usize> = (0..union.ids.len())
        .filter(|&b| !in_sub.contains(&union.ids[b]))
        .collect();
    let r_rows = rows(&r_blocks);
    let (ns, nr) = (s_rows.len(), r_rows.len());
    let a = &union.matrix;
    let a_ss = Mat::from_fn(ns, ns, |i, j| a[(s_rows[i], s_rows[j])]);
    let (a_bar, weight, c) = if nr == 0 {
        (a_ss, None, 0.0)
    } else {
        let a_rr = Mat::from_fn(nr, nr, |i, j| a[(r_rows[i], r_rows[j])]);
        let a_rs = Mat::from_fn(nr, ns, |i, j| a[(r_rows[i], s_rows[j])]);
        let llt = a_rr.as_ref().llt(Side::Lower).map_err(|e| {
            let faer::linalg::solvers::LltError::NonPositivePivot { index } = e;
            CiError::Info(InfoError::NotPositiveDefinite {
                what: "receiver information outside the submap",
                pivot: r_rows[index],
                feature: union.ids[r_rows[index] / FEATURE_DIM],
                axis: r_rows[index] % FEATURE_DIM,
            })
        })?;
        let l = llt.L();
        // G = A_rr⁻¹ A_rs by two triangular solves.
        let mut g = a_rs.clone();
        solve_lower_triangular_in_place(l, g.as_mut(), Par::Seq);
        solve_upper_triangular_in_place(l.transpose(), g.as_mut(), Par::Seq);
        let a_bar = Mat::from_fn(ns, ns, |i, j| {
            let mut v = a_ss[(i, j)];
            for k in 0..nr {
                v -= a_rs[(k, i)] * g[(k, j)];
            }
            v
        });
        let a_bar = Mat::from_fn(ns, ns, |i, j| 0.5 * (a_bar[(i, j)] + a_bar[(j, i)]));
        let (weight, c) = match criterion {
            CiCriterion::Determinant => (None, 0.0),
            CiCriterion::Trace => {
                // W = I + GᵀG; c = tr(A_rr⁻¹) = ‖L⁻¹‖_F².
                let mut w = g.transpose() * &g;
                for i in 0..ns {
                    w[(i, i)] += 1.0;
                }
                let mut linv = Mat::<f64>::identity(nr, nr);
                solve_lower_triangular_in_place(l, linv.as_mut(), Par::Seq);
                (Some(w), linv.squared_norm_l2())
            }
        };
        (a_bar, weight, c)
    };
    let spec = spectrum(
        a_bar.as_ref(),
        sub.matrix.as_ref(),
        weight.as_ref().map(|w| w.as_ref()),
        c,
        nr,
    )?;
    let omega = spec.optimal_omega(criterion);
    let mut fused = union.scaled(omega);
    fused.add_assign(&sub.scaled(1.0 - omega))?;
    let delta = fused.sub(receiver)?;
    Ok(CiFusion {
        omega,
        fused,
        delta,
    })
}

/// Priority of a feature for a submap (design.md §4: "largest information gain since the last
/// exchange").
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FeaturePriority {
    /// The feature.
    pub id: FeatureId,
    /// ln det P_ff(last sent) − ln det P_ff(now), ≥ 0 when the feature improved; +∞ when
    /// never sent on this link.
    pub gain: f64,
    /// When the feature was last sent on this link (caller's time), `None` if never.
    pub last_sent: Option<f64>,
}

/// Picks the submap: features sorted by gain (descending), ties by least recently sent (so
/// unchanged features take turns), then id; the longest prefix whose
/// [`Submap::wire_bytes_for`] fits `budget_bytes`.
pub fn select_submap(mut candidates: Vec<FeaturePriority>, budget_bytes: usize) -> Vec<FeatureId> {
    candidates.sort_by(|a, b| {
        b.gain
            .total_cmp(&a.gain)
            .then_with(|| {
                let (ta, tb) = (
                    a.last_sent.unwrap_or(f64::NEG_INFINITY),
                    b.last_sent.unwrap_or(f64::NEG_INFINITY),
                );
                ta.total_cmp(&tb)
            })
            .then(a.id.cmp(&b.id))
    });
    let mut k = 0;
    while k < candidates.len() && Submap::wire_bytes_for(k + 1) <= budget_bytes {
        k += 1;
    }
    candidates.truncate(k);
    candidates.into_iter().map(|c| c.id).collect()
}

/// Per-link record of what was sent in submaps, for [`FeaturePriority`].
///
/// A send counts once the receiver acknowledges the submap that carried it. Until then it is
/// *in flight*: it counts for `timeout` after sending (so the feature is not sent again while
/// its acknowledgement is on its way) and is forgotten after that (a lost or refused submap:
/// the feature's priority falls back to its last acknowledged send, or to never sent).
#[derive(Clone, Debug, Default)]
pub struct SubmapTracker {
    /// Acknowledged sends: feature → (ln det P_ff at the send, send time).
    confirmed: HashMap<FeatureId, (f64, f64)>,
    /// Latest unacknowledged send: feature → (submap number, ln det P_ff, send time).
    in_flight: HashMap<FeatureId, (u64, f64, f64)>,
}

/// ln det of the 3 × 3 block of feature block `b` of a covariance (`None` if not positive).
fn block_log_det(p: &Mat<f64>, b: usize) -> Option<f64> {
    let m = Matrix3::from_fn(|i, j| p[(FEATURE_DIM * b + i, FEATURE_DIM * b + j)]);
    let d = m.determinant();
    (d > 0.0 && d.is_finite()).then(|| d.ln())
}

impl SubmapTracker {
    /// The send that counts for `id` at time `now`: an in-flight one younger than `timeout`,
    /// else the last acknowledged one.
    fn counted(&self, id: FeatureId, now: f64, timeout: f64) -> Option<(f64, f64)> {
        self.in_flight
            .get(&id)
            .filter(|&&(_, _, t)| now - t <= timeout)
            .map(|&(_, l, t)| (l, t))
            .or_else(|| self.confirmed.get(&id).copied())
    }

    /// Priorities at time `now` of every feature whose covariance block (`blocks`: feature and
    /// its 3 × 3 P_ff) is positive definite (`timeout`: how long an unacknowledged send
    /// counts).
    pub fn priorities(
        &self,
        blocks: &[(FeatureId, Matrix3<f64>)],
        now: f64,
        timeout: f64,
    ) -> Vec<FeaturePriority> {
        blocks
            .iter()
            .filter_map(|&(id, p_ff)| {
                let d = p_ff.determinant();
                let logdet_now = (d > 0.0 && d.is_finite()).then(|| d.ln())?;
                Some(match self.counted(id, now, timeout) {
                    Some((logdet, t)) => FeaturePriority {
                        id,
                        gain: logdet - logdet_now,
                        last_sent: Some(t),
                    },
                    None => FeaturePriority {
                        id,
                        gain: f64::INFINITY,
                        last_sent: None,
                    },
                })
            })
            .collect()
    }

    /// Records that the features of `submap` (number `seq`) were sent at `now`, and forgets
    /// unacknowledged sends older than `timeout`.
    pub fn record_sent(&mut self, seq: u64, submap: &Submap, now: f64, timeout: f64) {
        self.in_flight
            .retain(|_, &mut (_, _, t)| now - t <= timeout);
        let p = submap.covariance();
        for (b, &id) in submap.ids.iter().enumerate() {
            if let Some(l) = block_log_det(&p, b) {
                self.in_flight.insert(id, (seq, l, now));
            }
        }
    }

    /// The receiver fused submaps `seqs`: their sends count for good.
    pub fn acknowledge(&mut self, seqs: &[u64]) {
        let acked: HashSet<u64> = seqs.iter().copied().collect();
        self.in_flight.retain(|&id, &mut (seq, l, t)| {
            if acked.contains(&seq) {
                self.confirmed.insert(id, (l, t));
                false
            } else {
                true
            }
        });
    }

    /// Forgets everything (the peer restarted and lost what it had).
    pub fn clear(&mut self) {
        self.confirmed.clear();
        self.in_flight.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn diag(d: &[f64]) -> Mat<f64> {
        Mat::from_fn(d.len(), d.len(), |i, j| if i == j { d[i] } else { 0.0 })
    }

    fn to_na(m: &Mat<f64>) -> DMatrix<f64> {
        DMatrix::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
    }

    fn from_na(m: &DMatrix<f64>) -> Mat<f64> {
        Mat::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
    }

    /// Random SPD with eigenvalues spread over [0.1, 10] (κ ≤ 100).
    fn random_spd(rng: &mut ChaCha8Rng, n: usize) -> DMatrix<f64> {
        let a = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        let q = a.qr().q();
        let d = DMatrix::from_diagonal(&DVector::from_fn(n, |_, _| {
            10f64.powf(rng.random_range(-1.0..1.0))
        }));
        let p = &q * d * q.transpose();
        (&p + p.transpose()) * 0.5
    }

    /// Independent dense objective: tr or ln det of (ω A + (1 − ω) B)⁻¹ by nalgebra.
    fn dense_objective(a: &DMatrix<f64>, b: &DMatrix<f64>, omega: f64, c: CiCriterion) -> f64 {
        let y = a * omega + b * (1.0 - omega);
        match y.cholesky() {
            None => f64::INFINITY,
            Some(ch) => match c {
                CiCriterion::Trace => ch.inverse().trace(),
                CiCriterion::Determinant => -ch.ln_determinant(),
            },
        }
    }

    /// Golden-section minimum of the dense objective on [0, 1] (independent of the spectral
    /// method), to ~1e-9 in ω.
    fn dense_argmin(a: &DMatrix<f64>, b: &DMatrix<f64>, c: CiCriterion) -> f64 {
        let g = (5f64.sqrt() - 1.0) / 2.0;
        let (mut lo, mut hi) = (0.0, 1.0);
        for _ in 0..60 {
            let x1 = hi - g * (hi - lo);
            let x2 = lo + g * (hi - lo);
            if dense_objective(a, b, x1, c) <= dense_objective(a, b, x2, c) {
                hi = x2;
            } else {
                lo = x1;
            }
        }
        0.5 * (lo + hi)
    }

    #[test]
    fn trace_omega_of_mirror_image_estimates_is_one_half() {
        let omega = omega_full(&diag(&[1.0, 4.0]), &diag(&[4.0, 1.0]), CiCriterion::Trace).unwrap();
        // Bisection to 2⁻⁶⁰; the closed form is exactly 0.5.
        assert!((omega - 0.5).abs() < 1e-15, "{omega}");
        let omega = omega_full(
            &diag(&[1.0, 4.0]),
            &diag(&[4.0, 1.0]),
            CiCriterion::Determinant,
        )
        .unwrap();
        assert!((omega - 0.5).abs() < 1e-15, "{omega}");
        // Dominance: if a is better in every direction, CI takes a alone (ω = 1).
        let omega = omega_full(&diag(&[1.0, 1.0]), &diag(&[2.0, 3.0]), CiCriterion::Trace).unwrap();
        assert_eq!(omega, 1.0);
    }

    #[test]
    fn determinant_optimum_satisfies_first_order_condition() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut interior = 0;
        for _ in 0..50 {
            let pa = random_spd(&mut rng, 6);
            let pb = random_spd(&mut rng, 6);
            let omega = omega_full(&from_na(&pa), &from_na(&pb), CiCriterion::Determinant).unwrap();
            let (ya, yb) = (
                pa.clone().try_inverse().unwrap(),
                pb.clone().try_inverse().unwrap(),
            );
            let f = |w: f64| dense_objective(&ya, &yb, w, CiCriterion::Determinant);
            if omega > 1e-6 && omega < 1.0 - 1e-6 {
                interior += 1;
                // Central difference, h = 1e-5: truncation h²·f''' ~ 1e-9, round-off
                // 1e-16·|f|/h ~ 1e-10; an O(1) slope would be 1e9 times larger.
                let h = 1e-5;
                let slope = (f(omega + h) - f(omega - h)) / (2.0 * h);
                assert!(slope.abs() < 1e-7, "d ln det P/dω = {slope} at ω = {omega}");
            } else {
                // Boundary optimum: the one-sided slope points outwards.
                let h = 1e-6;
                if omega <= 1e-6 {
                    assert!(f(h) >= f(0.0) - 1e-12);
                } else {
                    assert!(f(1.0 - h) >= f(1.0) - 1e-12);
                }
            }
            // And it is the global minimum on [0, 1] (independent golden section).
            let w_dense = dense_argmin(&ya, &yb, CiCriterion::Determinant);
            assert!(
                f(omega) <= f(w_dense) + 1e-12,
                "ω = {omega} vs dense {w_dense}"
            );
        }
        assert!(
            interior > 20,
            "the sample must exercise interior optima ({interior})"
        );
    }

    #[test]
    fn trace_optimum_matches_dense_golden_section() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        for _ in 0..50 {
            let pa = random_spd(&mut rng, 5);
            let pb = random_spd(&mut rng, 5);
            let omega = omega_full(&from_na(&pa), &from_na(&pb), CiCriterion::Trace).unwrap();
            let (ya, yb) = (
                pa.clone().try_inverse().unwrap(),
                pb.clone().try_inverse().unwrap(),
            );
            let w_dense = dense_argmin(&ya, &yb, CiCriterion::Trace);
            let f = |w: f64| dense_objective(&ya, &yb, w, CiCriterion::Trace);
            // Objective values agree to round-off (1e-12 relative); ω itself to 1e-6 (the
            // minimum is flat: ω error ~ √(ε_f) for the golden section reference).
            assert!(
                f(omega) <= f(w_dense) * (1.0 + 1e-12),
                "ω {omega} vs {w_dense}"
            );
            assert!((omega - w_dense).abs() < 1e-6, "ω {omega} vs {w_dense}");
        }
    }

    /// Fused covariance minus the true error covariance of the CI estimate, for estimates whose
    /// errors have the joint covariance `joint` (any valid cross-correlation).
    fn ci_excess(pa: &DMatrix<f64>, pb: &DMatrix<f64>, joint: &DMatrix<f64>, omega: f64) -> f64 {
        let n = pa.nrows();
        let (ya, yb) = (
            pa.clone().try_inverse().unwrap(),
            pb.clone().try_inverse().unwrap(),
        );
        let p = (&ya * omega + &yb * (1.0 - omega)).try_inverse().unwrap();
        // e = P (ω Y_a e_a + (1 − ω) Y_b e_b) = K [e_a; e_b].
        let mut k = DMatrix::zeros(n, 2 * n);
        k.view_mut((0, 0), (n, n)).copy_from(&(&p * &ya * omega));
        k.view_mut((0, n), (n, n))
            .copy_from(&(&p * &yb * (1.0 - omega)));
        let truth = &k * joint * k.transpose();
        let d = &p - truth;
        ((&d + d.transpose()) * 0.5).symmetric_eigenvalues().min()
    }

    #[test]
    fn ci_is_consistent_for_sampled_cross_correlations() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        let n = 4;
        let mut worst = f64::INFINITY;
        for trial in 0..300 {
            // A random joint covariance of (e_a, e_b): its blocks are the estimates' claimed
            // covariances and their true cross-covariance.
            let joint = if trial % 3 == 0 {
                // Fully correlated (e_a = e_b): the hardest case.
                let p = random_spd(&mut rng, n);
                let mut j = DMatrix::zeros(2 * n, 2 * n);
                for (r, c) in [(0, 0), (0, n), (n, 0), (n, n)] {
                    j.view_mut((r, c), (n, n)).copy_from(&p);
                }
                j
            } else {
                random_spd(&mut rng, 2 * n)
            };
            let pa = joint.view((0, 0), (n, n)).into_owned();
            let pb = joint.view((n, n), (n, n)).into_owned();
            for criterion in [CiCriterion::Trace, CiCriterion::Determinant] {
                let omega = omega_full(&from_na(&pa), &from_na(&pb), criterion).unwrap();
                let scale = pa.amax().max(pb.amax());
                let e = ci_excess(&pa, &pb, &joint, omega) / scale;
                worst = worst.min(e);
                // Round-off of two inversions (κ ≤ 100): 1e-12 relative.
                assert!(e >= -1e-12, "P_CI − P_true has eigenvalue {e} (relative)");
            }
            // Consistency holds for every ω, not only the optimum.
            let omega = rng.random_range(0.0..1.0);
            assert!(ci_excess(&pa, &pb, &joint, omega) / pa.amax().max(pb.amax()) >= -1e-12);
        }
        // The bound is tight for fully correlated errors (CI is then exact): the check has teeth.
        assert!(worst < 1e-9, "worst relative excess {worst}");
    }

    #[test]
    fn fuse_full_matches_dense_formula() {
        let mut rng = ChaCha8Rng::seed_from_u64(14);
        let pa = random_spd(&mut rng, 4);
        let pb = random_spd(&mut rng, 4);
        let xa = DVector::from_fn(4, |_, _| rng.random_range(-5.0..5.0));
        let xb = DVector::from_fn(4, |_, _| rng.random_range(-5.0..5.0));
        let g = |x: &DVector<f64>, p: &DMatrix<f64>| Gaussian {
            mean: Col::from_fn(4, |i| x[i]),
            covariance: from_na(p),
        };
        let r = fuse_full(&g(&xa, &pa), &g(&xb, &pb), CiCriterion::Trace).unwrap();
        let (ya, yb) = (pa.try_inverse().unwrap(), pb.try_inverse().unwrap());
        let y = &ya * r.omega + &yb * (1.0 - r.omega);
        let p = y.clone().try_inverse().unwrap();
        let x = &p * (&ya * &xa * r.omega + &yb * &xb * (1.0 - r.omega));
        // κ ≤ 100 inversions: 1e-12 relative.
        for i in 0..4 {
            assert!((r.fused.mean[i] - x[i]).abs() < 1e-12 * x.amax().max(1.0));
            for j in 0..4 {
                assert!((r.fused.covariance[(i, j)] - p[(i, j)]).abs() < 1e-12 * p.amax());
            }
        }
    }

    /// A receiver map (features 1..=4) and a submap on features {3, 4, 9} (9 new), with a random
    /// joint error covariance. Returns (receiver info, submap, embedded dense A, embedded dense
    /// B over the union [1, 2, 3, 4, 9], joint covariance of (e_A over 1..4, e_S over 3, 4, 9)).
    fn partial_case(
        rng: &mut ChaCha8Rng,
        origin: Vector3<f64>,
    ) -> (
        MapInformation,
        Submap,
        DMatrix<f64>,
        DMatrix<f64>,
        DMatrix<f64>,
    ) {
        let joint = random_spd(rng, 21);
        let pa = joint.view((0, 0), (12, 12)).into_owned();
        let ps = joint.view((12, 12), (9, 9)).into_owned();
        let xa = DVector::from_fn(12, |_, _| rng.random_range(-50.0..50.0));
        let xs = DVector::from_fn(9, |_, _| rng.random_range(-50.0..50.0));
        let recv = MapInformation::from_marginal(
            &MapMarginal {
                ids: vec![1, 2, 3, 4],
                mean: Col::from_fn(12, |i| xa[i] + origin[i % 3]),
                covariance: from_na(&pa),
            },
            origin,
        )
        .unwrap();
        let sub = Submap::from_marginal(
            &MapMarginal {
                ids: vec![3, 4, 9],
                mean: Col::from_fn(9, |i| xs[i] + origin[i % 3]),
                covariance: from_na(&ps),
            },
            &[3, 4, 9],
            origin,
        );
        let mut a = DMatrix::zeros(15, 15);
        a.view_mut((0, 0), (12, 12))
            .copy_from(&pa.try_inverse().unwrap());
        let mut b = DMatrix::zeros(15, 15);
        b.view_mut((6, 6), (9, 9))
            .copy_from(&ps.try_inverse().unwrap());
        (recv, sub, a, b, joint)
    }

    #[test]
    fn submap_omega_matches_dense_whole_map_optimum() {
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        let origin = Vector3::new(-2.7e6, 4.3e6, 3.9e6);
        for _ in 0..20 {
            let (recv, sub, a, b, _) = partial_case(&mut rng, origin);
            for criterion in [CiCriterion::Trace, CiCriterion::Determinant] {
                let r = fuse_submap(&recv, &sub, criterion).unwrap();
                let w_dense = dense_argmin(&a, &b, criterion);
                let f = |w: f64| dense_objective(&a, &b, w, criterion);
                // Same tolerances as the full-state comparison above.
                assert!(
                    f(r.omega) <= f(w_dense) + 1e-12 * f(w_dense).abs().max(1.0),
                    "{criterion:?}: ω {} vs {w_dense}",
                    r.omega
                );
                assert!(
                    (r.omega - w_dense).abs() < 1e-6,
                    "{criterion:?}: ω {} vs {w_dense}",
                    r.omega
                );
                assert!(r.omega > 0.0 && r.omega < 1.0);
                // The fused information is the embedded formula, with the new feature appended.
                assert_eq!(r.fused.ids, vec![1, 2, 3, 4, 9]);
                let y = &a * r.omega + &b * (1.0 - r.omega);
                for i in 0..15 {
                    for j in 0..15 {
                        // κ ≤ 100 inverses: 1e-11 relative.
                        assert!((r.fused.matrix[(i, j)] - y[(i, j)]).abs() < 1e-11 * y.amax());
                    }
                }
                let back = recv.add(&r.delta).unwrap();
                assert!(back.relative_difference(&r.fused).unwrap() < 1e-12);
            }
        }
    }

    #[test]
    fn submap_ci_is_consistent_for_sampled_cross_correlations() {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        for _ in 0..100 {
            let (recv, sub, a, b, joint) = partial_case(&mut rng, Vector3::zeros());
            for criterion in [CiCriterion::Trace, CiCriterion::Determinant] {
                let r = fuse_submap(&recv, &sub, criterion).unwrap();
                let y = to_na(&r.fused.matrix);
                let p = y.clone().try_inverse().unwrap();
                // e' = P (ω A e_A + (1 − ω) B e_S), with e_A embedded in rows 0..12 of the union
                // and e_S in rows 6..15: e' = K [e_A; e_S].
                let mut k = DMatrix::zeros(15, 21);
                k.view_mut((0, 0), (15, 12))
                    .copy_from(&(&p * a.columns(0, 12) * r.omega));
                k.view_mut((0, 12), (15, 9))
                    .copy_from(&(&p * b.columns(6, 9) * (1.0 - r.omega)));
                let d = &p - &k * &joint * k.transpose();
                let e = ((&d + d.transpose()) * 0.5).symmetric_eigenvalues().min() / p.amax();
                // Round-off of κ ≤ 1e4 products: 1e-10 relative.
                assert!(e >= -1e-10, "P' − P_true has eigenvalue {e}");
            }
        }
    }

    #[test]
    fn empty_receiver_takes_the_submap() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let p = random_spd(&mut rng, 6);
        let sub = Submap::from_marginal(
            &MapMarginal {
                ids: vec![5, 6],
                mean: Col::from_fn(6, |i| i as f64),
                covariance: from_na(&p),
            },
            &[5, 6],
            Vector3::zeros(),
        );
        let r = fuse_submap(
            &MapInformation::zero(Vector3::zeros()),
            &sub,
            CiCriterion::Trace,
        )
        .unwrap();
        assert_eq!(r.omega, 0.0);
        let m = r.fused.to_marginal().unwrap();
        for i in 0..6 {
            assert!((m.mean[i] - i as f64).abs() < 1e-12 * 10.0);
        }
    }

    #[test]
    fn submap_selection_respects_budget_and_priority() {
        let c = |id, gain, last_sent| FeaturePriority {
            id,
            gain,
            last_sent,
        };
        let cands = vec![
            c(1, 0.0, Some(5.0)),
            c(2, f64::INFINITY, None),
            c(3, 0.7, Some(1.0)),
            c(4, 0.0, Some(2.0)),
            c(5, 0.2, Some(1.0)),
        ];
        assert_eq!(
            select_submap(cands.clone(), Submap::wire_bytes_for(5)),
            vec![2, 3, 5, 4, 1]
        );
        assert_eq!(
            select_submap(cands.clone(), Submap::wire_bytes_for(3)),
            vec![2, 3, 5]
        );
        assert_eq!(
            select_submap(cands.clone(), Submap::wire_bytes_for(3) - 1),
            vec![2, 3]
        );
        assert!(select_submap(cands, Submap::wire_bytes_for(1) - 1).is_empty());
        // The byte bound holds for the real encoding.
        let mut rng = ChaCha8Rng::seed_from_u64(18);
        let p = random_spd(&mut rng, 9);
        let m = MapMarginal {
            ids: vec![7, 8, 9],
            mean: Col::from_fn(9, |i| 1e6 + i as f64),
            covariance: from_na(&p),
        };
        let s = Submap::from_marginal(&m, &[9, 7], Vector3::new(1e6, 1e6, 1e6));
        let bytes = bincode::serde::encode_to_vec(&s, bincode::config::standard()).unwrap();
        assert!(
            bytes.len() <= s.wire_bytes(),
            "{} > {}",
            bytes.len(),
            s.wire_bytes()
        );
        assert_eq!(s.ids, vec![9, 7]);
        assert!(s.validate().is_ok());
        let mut bad = s.clone();
        bad.covariance_packed.pop();
        assert!(bad.validate().is_err());
        bad = s.clone();
        bad.offset_mean[0] = f64::NAN;
        assert!(bad.information().is_err());
    }

    #[test]
    fn tracker_priorities_follow_information_gain() {
        let marginal = |s: f64| MapMarginal {
            ids: vec![1, 2],
            mean: Col::zeros(6),
            covariance: diag(&[s, s, s, 1.0, 1.0, 1.0]),
        };
        let cov = |s: f64| -> Vec<(FeatureId, Matrix3<f64>)> {
            vec![(1, Matrix3::identity() * s), (2, Matrix3::identity())]
        };
        // Unacknowledged sends count for this long.
        let timeout = 3.0;
        let mut t = SubmapTracker::default();
        let p0 = t.priorities(&cov(4.0), 0.0, timeout);
        assert!(
            p0.iter()
                .all(|p| p.gain == f64::INFINITY && p.last_sent.is_none())
        );
        t.record_sent(
            1,
            &Submap::from_marginal(&marginal(4.0), &[1, 2], Vector3::zeros()),
            3.0,
            timeout,
        );
        let p1 = t.priorities(&cov(1.0), 4.0, timeout);
        // Feature 1: ln det went from 3 ln 4 to 0 → gain 3 ln 4; feature 2 unchanged → 0.
        assert!((p1[0].gain - 3.0 * 4f64.ln()).abs() < 1e-12);
        assert_eq!(p1[1].gain, 0.0);
        assert_eq!(p1[0].last_sent, Some(3.0));
        // Never acknowledged: after the timeout both count as never sent again.
        assert!(
            t.priorities(&cov(1.0), 6.5, timeout)
                .iter()
                .all(|p| p.gain == f64::INFINITY && p.last_sent.is_none())
        );
        // Acknowledged (an unknown number changes nothing): counts for good.
        t.acknowledge(&[7, 1]);
        let p2 = t.priorities(&cov(1.0), 100.0, timeout);
        assert!((p2[0].gain - 3.0 * 4f64.ln()).abs() < 1e-12);
        assert_eq!(p2[1].last_sent, Some(3.0));
        // A later send of feature 2 whose submap is lost: feature 2 falls back to the
        // acknowledged send once the timeout passes.
        t.record_sent(
            2,
            &Submap::from_marginal(&marginal(1.0), &[2], Vector3::zeros()),
            101.0,
            timeout,
        );
        assert_eq!(
            t.priorities(&cov(1.0), 102.0, timeout)[1].last_sent,
            Some(101.0)
        );
        assert_eq!(
            t.priorities(&cov(1.0), 105.0, timeout)[1].last_sent,
            Some(3.0)
        );
        t.clear();
        assert!(
            t.priorities(&cov(1.0), 105.0, timeout)
                .iter()
                .all(|p| p.gain == f64::INFINITY)
        );
    }
}
