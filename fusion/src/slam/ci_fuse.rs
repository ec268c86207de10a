//! Covariance intersection of a received submap with the whole filter, in covariance form.
//!
//! A bandwidth-limited link carries a [`Submap`]: the sender's marginal (μ_S, P_S) of a few
//! features, whose correlation with the receiver's estimate is unknown (chapter §21.5.4,
//! design.md §4). Partial-state CI with the submap embedded in the receiver's *joint* state x
//! (vehicle, map, stored poses) is
//!
//! ```text
//! Y' = ω Y + (1 − ω) E B Eᵀ,  y' = ω y + (1 − ω) E B μ_S,   B = P_S⁻¹,  ω ∈ (0, 1),
//! ```
//!
//! consistent for any cross-correlation. For the submap features K the receiver already holds,
//! this is a Kalman update (eqs. 21.56–21.60) of the prior (x, P/ω) with the measurement
//! z = μ_K of x_K and noise P_S,KK/(1 − ω) (information form of the same sum), so it costs
//! O(n²·|K|) and never forms Y = P⁻¹. Features U new to the receiver enter through the submap's
//! conditional given K: m_U = μ_U + G (x_K − μ_K) + w, G = P_S,UK P_S,KK⁻¹,
//! Cov w = (P_S,UU − G P_S,KU)/(1 − ω) (the conditional of the (1 − ω)-scaled submap
//! information), an augmentation like eq. 21.52.
//!
//! ω minimises the trace or the determinant of the fused covariance of the map (existing and
//! new features). With A = P_KK, R = P_S,KK = L Lᵀ, L⁻¹ A L⁻ᵀ = Q diag(μ) Qᵀ, M = P_·K
//! restricted to the map rows, W = MᵀM and w̃ = diag(Qᵀ L⁻¹ W L⁻ᵀ Q):
//!
//! ```text
//! tr P'_map(ω)   = T/ω − Σ_i w̃_i (1 − ω)/(ω (μ_i (1 − ω) + ω)) + c_U/(1 − ω),
//! ln det P'(ω)   = −n ln ω − Σ_i ln(1 + μ_i (1 − ω)/ω) − n_U ln(1 − ω) + const,
//! ```
//!
//! T = tr P_map, c_U = tr Cov(m_U | m_K) in the submap, n the map dimension, n_U = 3|U|; for
//! the trace, new features add tr(Gᵀ G P'_KK), which is the same form (T += tr(GᵀG A),
//! W += A GᵀG A).
//! Both are evaluated on a grid and refined by golden-section search (a 1-D problem; any ω is
//! consistent, the search only decides how much is gained).

use super::update::HBlock;
use super::{SlamError, SlamFilter, SlotKind};
use crate::ci::{CiCriterion, Submap};
use crate::sensor::FeatureId;
use crate::state::FEATURE_DIM;
use faer::{Col, Mat};
use nalgebra::{DMatrix, DVector};

/// Lower and upper ends of the ω search (ω = 0 or 1 would drop one side entirely).
const OMEGA_MIN: f64 = 1e-4;
const OMEGA_MAX: f64 = 1.0 - 1e-4;

/// What a covariance-intersection fusion did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CiReport {
    /// The weight ω of the receiver's own estimate.
    pub omega: f64,
    /// Submap features the receiver already held.
    pub known: usize,
    /// Submap features added to the map.
    pub added: usize,
}

/// The criterion as a function of ω (module docs).
struct Criterion {
    kind: CiCriterion,
    /// Generalised eigenvalues μ_i of (A, R).
    mu: Vec<f64>,
    /// w̃_i (trace only).
    w: Vec<f64>,
    /// tr P_map (trace) or the map dimension n (determinant).
    scale: f64,
    /// c_U (trace) or n_U (determinant).
    new_term: f64,
}

impl Criterion {
    fn value(&self, omega: f64) -> f64 {
        let rest = 1.0 - omega;
        match self.kind {
            CiCriterion::Trace => {
                let gain: f64 = self
                    .mu
                    .iter()
                    .zip(&self.w)
                    .map(|(&mu, &w)| w * rest / (omega * (mu * rest + omega)))
                    .sum();
                self.scale / omega - gain + self.new_term / rest
            }
            CiCriterion::Determinant => {
                let gain: f64 = self
                    .mu
                    .iter()
                    .map(|&mu| (1.0 + mu * rest / omega).ln())
                    .sum();
                -self.scale * omega.ln() - gain - self.new_term * rest.ln()
            }
        }
    }

    /// Grid of 64 points, then golden-section search around the best one.
    fn minimise(&self) -> f64 {
        const GRID: usize = 64;
        let at = |k: usize| OMEGA_MIN + (OMEGA_MAX - OMEGA_MIN) * k as f64 / GRID as f64;
        let best = (0..=GRID)
            .min_by(|&a, &b| self.value(at(a)).total_cmp(&self.value(at(b))))
            .unwrap_or(GRID);
        let (mut lo, mut hi) = (at(best.saturating_sub(1)), at((best + 1).min(GRID)));
        let phi = 0.5 * (5f64.sqrt() - 1.0);
        let (mut a, mut b) = (hi - phi * (hi - lo), lo + phi * (hi - lo));
        let (mut fa, mut fb) = (self.value(a), self.value(b));
        for _ in 0..60 {
            if fa <= fb {
                hi = b;
                b = a;
                fb = fa;
                a = hi - phi * (hi - lo);
                fa = self.value(a);
            } else {
                lo = a;
                a = b;
                fa = fb;
                b = lo + phi * (hi - lo);
                fb = self.value(b);
            }
        }
        0.5 * (lo + hi)
    }
}

fn dm(m: &Mat<f64>) -> DMatrix<f64> {
    DMatrix::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
}

impl SlamFilter {
    /// Fuses a received submap by partial-state covariance intersection in covariance form
    /// (module docs). The submap must be valid, in this filter's origin, with a positive
    /// definite covariance. On any error the filter is unchanged.
    pub fn fuse_submap_ci(
        &mut self,
        submap: &Submap,
        criterion: CiCriterion,
    ) -> Result<CiReport, SlamError> {
        submap
            .validate()
            .map_err(|e| SlamError::InvalidInformation(e.to_string()))?;
        if nalgebra::Vector3::from(submap.origin) != self.config.origin {
            return Err(SlamError::OriginMismatch);
        }
        let ps = dm(&submap.covariance());
        let mu_s = DVector::from_fn(submap.offset_mean.len(), |i, _| {
            submap.offset_mean[i] + submap.origin[i % FEATURE_DIM]
        });
        if ps.clone().cholesky().is_none() {
            return Err(SlamError::NotPositiveDefinite("submap covariance"));
        }
        self.flush();
        // Submap rows of the known (K) and new (U) features.
        let mut known: Vec<(FeatureId, usize, usize)> = Vec::new(); // (id, submap block, offset)
        let mut new: Vec<(FeatureId, usize)> = Vec::new();
        for (b, &id) in submap.ids.iter().enumerate() {
            match self.layout.feature_offset(id) {
                Some(off) => known.push((id, b, off)),
                None => new.push((id, b)),
            }
        }
        let rows = |blocks: &[usize]| -> Vec<usize> {
            blocks
                .iter()
                .flat_map(|&b| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * b + a))
                .collect()
        };
        let k_rows = rows(&known.iter().map(|k| k.1).collect::<Vec<_>>());
        let u_rows = rows(&new.iter().map(|u| u.1).collect::<Vec<_>>());
        let k_state: Vec<usize> = known
            .iter()
            .flat_map(|k| (0..FEATURE_DIM).map(move |a| k.2 + a))
            .collect();
        let (nk, nu) = (k_rows.len(), u_rows.len());
        let sub =
            |r: &[usize], c: &[usize]| DMatrix::from_fn(r.len(), c.len(), |i, j| ps[(r[i], c[j])]);
        let r_kk = sub(&k_rows, &k_rows);
        let (g, cov_u) = if nk == 0 {
            (DMatrix::zeros(nu, 0), sub(&u_rows, &u_rows))
        } else {
            let chol = r_kk
                .clone()
                .cholesky()
                .ok_or(SlamError::NotPositiveDefinite(
                    "submap covariance of known features",
                ))?;
            let p_uk = sub(&u_rows, &k_rows);
            let g = chol.solve(&p_uk.transpose()).transpose();
            let cov_u = sub(&u_rows, &u_rows) - &g * p_uk.transpose();
            (g, (&cov_u + cov_u.transpose()) * 0.5)
        };
        // The criterion's ingredients.
        let map_rows: Vec<usize> = self.layout.features().flat_map(|(_, o)| o..o + 3).collect();
        let mut trace_map: f64 = map_rows.iter().map(|&i| self.p[(i, i)]).sum();
        let (mu, w) = if nk == 0 {
            (Vec::new(), Vec::new())
        } else {
            let a = DMatrix::from_fn(nk, nk, |i, j| self.p[(k_state[i], k_state[j])]);
            // New features follow K through G: their part of tr P' is tr(Gᵀ G P'_KK), i.e. the
            // same form with T += tr(Gᵀ G A) and W += A Gᵀ G A.
            let gtg = g.transpose() * &g;
            trace_map += (&gtg * &a).trace();
            let w_new = &a * &gtg * &a;
            let l = r_kk
                .clone()
                .cholesky()
                .ok_or(SlamError::NotPositiveDefinite(
                    "submap covariance of known features",
                ))?
                .l();
            let l_inv = l
                .try_inverse()
                .ok_or(SlamError::NumericalFailure("CI: submap factor"))?;
            let c = &l_inv * a * l_inv.transpose();
            let eig = nalgebra::SymmetricEigen::new((&c + c.transpose()) * 0.5);
            let m = DMatrix::from_fn(map_rows.len(), nk, |i, j| self.p[(map_rows[i], k_state[j])]);
            let t = &eig.eigenvectors.transpose() * &l_inv;
            let wt = &t * (m.transpose() * &m + w_new) * t.transpose();
            (
                eig.eigenvalues.iter().copied().collect(),
                (0..nk).map(|i| wt[(i, i)]).collect(),
            )
        };
        let crit = Criterion {
            kind: criterion,
            mu,
            w,
            scale: match criterion {
                CiCriterion::Trace => trace_map,
                CiCriterion::Determinant => map_rows.len() as f64,
            },
            new_term: match criterion {
                CiCriterion::Trace => cov_u.trace(),
                CiCriterion::Determinant => nu as f64,
            },
        };
        let omega = crit.minimise();
        if !omega.is_finite() {
            return Err(SlamError::NumericalFailure("CI weight"));
        }
        if nu > 0 && cov_u.clone().cholesky().is_none() {
            return Err(SlamError::NotPositiveDefinite(
                "submap conditional of new features",
            ));
        }
        let backup = self.clone();
        let result = self.apply_ci(omega, &known, &new, &k_rows, &u_rows, &k_state, &ps, &mu_s);
        if let Err(e) = result {
            *self = backup;
            return Err(e);
        }
        Ok(CiReport {
            omega,
            known: known.len(),
            added: new.len(),
        })
    }

    /// The state change of [`Self::fuse_submap_ci`] for a chosen ω (the caller restores the
    /// filter on error).
    #[allow(clippy::too_many_arguments)]
    fn apply_ci(
        &mut self,
        omega: f64,
        known: &[(FeatureId, usize, usize)],
        new: &[(FeatureId, usize)],
        k_rows: &[usize],
        u_rows: &[usize],
        k_state: &[usize],
        ps: &DMatrix<f64>,
        mu_s: &DVector<f64>,
    ) -> Result<(), SlamError> {
        let rest = 1.0 - omega;
        let nk = k_rows.len();
        // Prior P/ω, then the Kalman update with z = μ_K, R = P_S,KK/(1 − ω).
        let n = self.dim();
        let inv = 1.0 / omega;
        for j in 0..n {
            for i in 0..n {
                self.p[(i, j)] *= inv;
            }
        }
        self.bump_map_generation(false);
        if nk > 0 {
            let blocks: Vec<HBlock> = known
                .iter()
                .enumerate()
                .map(|(r, k)| HBlock {
                    row: FEATURE_DIM * r,
                    col: k.2,
                    mat: Mat::identity(FEATURE_DIM, FEATURE_DIM),
                })
                .collect();
            let nu_k = Col::from_fn(nk, |i| mu_s[k_rows[i]] - self.x[k_state[i]]);
            let r = Mat::from_fn(nk, nk, |i, j| ps[(k_rows[i], k_rows[j])] / rest);
            self.blocks_update(&blocks, &nu_k, r)?;
        }
        // New features, one at a time, each conditioned (in the submap) on K and the new
        // features before it: the chain rule reproduces the joint conditional of U given K.
        let mut cond_rows: Vec<usize> = k_rows.to_vec();
        let mut cond_ids: Vec<FeatureId> = known.iter().map(|k| k.0).collect();
        for (u, &(id, _)) in new.iter().enumerate() {
            let own: Vec<usize> = u_rows[FEATURE_DIM * u..FEATURE_DIM * (u + 1)].to_vec();
            let sub = |r: &[usize], c: &[usize]| {
                DMatrix::from_fn(r.len(), c.len(), |i, j| ps[(r[i], c[j])])
            };
            let (g, cov) = if cond_rows.is_empty() {
                (DMatrix::zeros(FEATURE_DIM, 0), sub(&own, &own))
            } else {
                let chol = sub(&cond_rows, &cond_rows)
                    .cholesky()
                    .ok_or(SlamError::NotPositiveDefinite("submap covariance"))?;
                let p_uc = sub(&own, &cond_rows);
                let g = chol.solve(&p_uc.transpose()).transpose();
                let cov = sub(&own, &own) - &g * p_uc.transpose();
                (g, cov)
            };
            let offsets: Vec<usize> = cond_ids
                .iter()
                .map(|c| {
                    self.layout
                        .feature_offset(*c)
                        .ok_or(SlamError::NumericalFailure("CI: feature slot"))
                })
                .collect::<Result<_, _>>()?;
            let mut mean = [0.0; FEATURE_DIM];
            for (a, m) in mean.iter_mut().enumerate() {
                *m = mu_s[own[a]];
                for (c, &r) in cond_rows.iter().enumerate() {
                    *m +=
                        g[(a, c)] * (self.x[offsets[c / FEATURE_DIM] + c % FEATURE_DIM] - mu_s[r]);
                }
            }
            let jac: Vec<(usize, Mat<f64>)> = offsets
                .iter()
                .enumerate()
                .map(|(b, &off)| {
                    (
                        off,
                        Mat::from_fn(FEATURE_DIM, FEATURE_DIM, |i, j| g[(i, FEATURE_DIM * b + j)]),
                    )
                })
                .collect();
            let noise = Mat::from_fn(FEATURE_DIM, FEATURE_DIM, |i, j| {
                0.5 * (cov[(i, j)] + cov[(j, i)]) / rest
            });
            self.augment_linear(SlotKind::Feature(id), &mean, &jac, &noise, true)?;
            cond_rows.extend(&own);
            cond_ids.push(id);
        }
        Ok(())
    }
}
