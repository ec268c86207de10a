//! Fuse-back of received map information (eqs. 21.92, 21.93 and 21.96–21.99, corrected as in
//! design.md §4: only the received delta is added, never the node's own information again).
//!
//! The information-form addition Y_joint += Eᵀ ΔY E, y_joint += Eᵀ Δy (E selects the delta's
//! features; Δy is w.r.t. x_m − o, `info` module) is done in covariance form without inverting P:
//!
//! 1. New features u (never seen) are augmented with their conditional given the known ones k:
//!    B = ΔY_uu⁻¹ ΔY_uk, x_u = ΔY_uu⁻¹ (Δy_u − ΔY_uk (x_k − o)) + o, P_u· = −B P_k·,
//!    P_uu = ΔY_uu⁻¹ + B P_kk Bᵀ (ΔY_uu must be positive definite).
//! 2. The remaining information on the known features is the Schur complement
//!    Ȳ = ΔY_kk − ΔY_ku ΔY_uu⁻¹ ΔY_uk, ȳ = Δy_k − ΔY_ku ΔY_uu⁻¹ Δy_u, and g = ȳ − Ȳ (x_k − o).
//!    It is applied as a pseudo-measurement with Hᵀ D⁻¹ H = Ȳ and Hᵀ D⁻¹ ν = g, so the Kalman
//!    update equals the information update exactly: if Ȳ is positive definite, Ȳ = L Lᵀ,
//!    H = Lᵀ E_k, D = I, ν = L⁻¹ g (Joseph form); otherwise Ȳ = V Λ Vᵀ (rank r, eigenvalues below
//!    1e-12·max|λ| dropped), H = |Λ|^½ Vᵀ E_k, D = sign(Λ), ν = D |Λ|^{-½} Vᵀ g, Joseph form when
//!    every sign is positive (PSD, low rank) and P − K Mᵀ otherwise (indefinite deltas from a CI
//!    fusion upstream). Cost O(n²·r + n·k²), r ≤ 3·(features in the delta): only the changed
//!    feature blocks enter.
//!    When the delta covers at least half of the state (whole-map deltas) the same information is
//!    applied through the map block instead (`prepare_map_route`): P_aa⁺ = (P_aa⁻¹ + Ȳ)⁻¹ and the
//!    other states through their unchanged conditional, ≈ two k×k Cholesky inverses, one of which
//!    is the cached [`SlamFilter::map_information`] when it is current.
//! 3. Positive definiteness of the fused joint is checked *before* anything changes: with
//!    Y = P⁻¹ the fused information is PD iff ΔY_uu ≻ 0 and P_kk⁻¹ + Ȳ ≻ 0 (Schur complements;
//!    P_kk⁻¹ is the marginal information of the known features), i.e. iff I + Lᵀ Ȳ L ≻ 0 with
//!    P_kk = L Lᵀ (Cholesky). The check is implied when Ȳ ⪰ 0, and in the map route it is the
//!    Cholesky of P_aa⁻¹ + Ȳ itself.

use super::update::{UpdateForm, all_finite};
use super::{SlamError, SlamFilter, SlotKind};
use crate::ddf::PackedInformation;
use crate::info::MapInformation;
use crate::sensor::FeatureId;
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::linalg::solvers::DenseSolveCore;
use faer::prelude::*;
use faer::{Accum, Mat, Side};
use std::collections::HashSet;

/// How the information on already-known features was applied.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FuseMethod {
    /// No known feature in the delta.
    #[default]
    None,
    /// Pseudo-measurement Kalman update, O(n²·r) (deltas on few features).
    PseudoMeasurement,
    /// Map-information route, ≈ two k×k Cholesky inverses (deltas covering ≥ half the state).
    MapInformation,
}

/// A fusion refused: the error, and the delta when nothing had changed yet (in the filter's
/// order; see [`SlamFilter::fuse_map_information_owned`]). Boxed: the error path is rare.
pub type Refused = Box<(SlamError, Option<MapInformation>)>;

/// What a fusion did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FuseReport {
    /// Features added to the state (in the order of the delta).
    pub new_features: Vec<FeatureId>,
    /// Number of features of the delta that the filter already held (with the map's features
    /// the delta carried no information on, when it was fused as a whole-map delta).
    pub known_features: usize,
    /// How the known-feature information was applied.
    pub method: FuseMethod,
    /// Rank of the pseudo-measurement (pseudo-measurement route only).
    pub rank: Option<usize>,
    /// Negative eigen-directions of the information (pseudo-measurement route only; the
    /// Cholesky fast path for positive definite deltas reports 0).
    pub negative_directions: Option<usize>,
}

/// Gathers the rows/cols `ri`×`ci` of a matrix.
pub(super) fn gather(m: MatRef<'_, f64>, ri: &[usize], ci: &[usize]) -> Mat<f64> {
    match (contiguous(ri), contiguous(ci)) {
        // Contiguous index ranges (the common case: a delta in state order) copy whole columns.
        (Some(r0), Some(c0)) => m.submatrix(r0, c0, ri.len(), ci.len()).to_owned(),
        _ => {
            let some = |idx: &[usize]| idx.iter().map(|&i| Some(i)).collect::<Vec<_>>();
            gather_padded(m, &some(ri), &some(ci))
        }
    }
}

/// m[ri, ci] with zero rows (columns) where `ri` (`ci`) has `None`: contiguous runs of row
/// indices (features are 3-blocks, often consecutive) are copied column by column instead of
/// element by element, into a zeroed result.
fn gather_padded(m: MatRef<'_, f64>, ri: &[Option<usize>], ci: &[Option<usize>]) -> Mat<f64> {
    let mut runs: Vec<(usize, usize, usize)> = Vec::new(); // (src, dst, len)
    for (d, r) in ri.iter().enumerate() {
        let Some(r) = *r else { continue };
        match runs.last_mut() {
            Some((s0, d0, len)) if *s0 + *len == r && *d0 + *len == d => *len += 1,
            _ => runs.push((r, d, 1)),
        }
    }
    let mut out = Mat::zeros(ri.len(), ci.len());
    for (jj, j) in ci.iter().enumerate() {
        let Some(j) = *j else { continue };
        let src = m.col(j);
        let mut dst = out.as_mut().col_mut(jj);
        for &(s0, d0, len) in &runs {
            dst.as_mut()
                .subrows_mut(d0, len)
                .copy_from(src.subrows(s0, len));
        }
    }
    out
}

/// The first index if `idx` is `first, first+1, …`.
fn contiguous(idx: &[usize]) -> Option<usize> {
    let first = *idx.first()?;
    idx.iter()
        .enumerate()
        .all(|(k, &i)| i == first + k)
        .then_some(first)
}

/// ½ (m[ri, ci] + m[ci, ri]ᵀ): the symmetric part of a (validated, nearly symmetric) block.
fn gather_sym(m: MatRef<'_, f64>, ri: &[usize], ci: &[usize]) -> Mat<f64> {
    if ri == ci {
        let mut a = gather(m, ri, ci);
        crate::info::symmetrize(&mut a);
        return a;
    }
    let a = gather(m, ri, ci);
    let b = gather(m, ci, ri);
    Mat::from_fn(ri.len(), ci.len(), |i, j| 0.5 * (a[(i, j)] + b[(j, i)]))
}

/// An exactly symmetric delta matrix over nk known and nu new states (known first) whose
/// leading nk × nk block is fused in the matrix's own buffer: the upper triangle of that
/// block (packed, half of it) and the new states' rows, from which the whole matrix is
/// rebuilt bit for bit if the fusion is refused.
struct SplitDelta {
    nk: usize,
    /// ΔY_kk's upper triangle, column by column (j(j+1)/2 + i for i ≤ j).
    upper_kk: Vec<f64>,
    /// ΔY_uk (nu × nk).
    y_uk: Mat<f64>,
    /// ΔY_uu (nu × nu).
    y_uu: Mat<f64>,
}

impl SplitDelta {
    /// Keeps what rebuilds `m` and truncates it in place to its leading nk × nk block.
    fn take(m: &mut Mat<f64>, nk: usize) -> (Self, Mat<f64>) {
        let n = m.nrows();
        let (known, new): (Vec<usize>, Vec<usize>) = ((0..nk).collect(), (nk..n).collect());
        let mut upper_kk = Vec::with_capacity(nk * (nk + 1) / 2);
        for j in 0..nk {
            upper_kk.extend_from_slice(&m.col_as_slice(j)[..=j]);
        }
        let kept = Self {
            nk,
            upper_kk,
            y_uk: gather(m.as_ref(), &new, &known),
            y_uu: gather(m.as_ref(), &new, &new),
        };
        let mut y_kk = std::mem::replace(m, Mat::new());
        y_kk.truncate(nk, nk);
        (kept, y_kk)
    }

    /// Entry (i, j) of the matrix as it was before [`SplitDelta::take`].
    fn entry(&self, i: usize, j: usize) -> f64 {
        let nk = self.nk;
        match (i < nk, j < nk) {
            (true, true) => {
                let (i, j) = (i.min(j), i.max(j));
                self.upper_kk[j * (j + 1) / 2 + i]
            }
            (false, true) => self.y_uk[(i - nk, j)],
            (true, false) => self.y_uk[(j - nk, i)],
            (false, false) => self.y_uu[(i - nk, j - nk)],
        }
    }

    /// The matrix as it was before [`SplitDelta::take`].
    fn rebuild(&self) -> Mat<f64> {
        let n = self.nk + self.y_uu.nrows();
        Mat::from_fn(n, n, |i, j| self.entry(i, j))
    }
}

/// Tile edge for transposed access: 64 × 64 f64 tiles (32 KiB) keep both the column-major
/// reads and the transposed ones in L1/L2.
const TILE: usize = 64;

/// The first (i, j), i > j, with |a_ij − a_ji| > tol, scanning tile by tile.
fn asymmetry_beyond(a: MatRef<'_, f64>, tol: f64) -> Option<(usize, usize)> {
    let n = a.nrows();
    for jb in (0..n).step_by(TILE) {
        for ib in (jb..n).step_by(TILE) {
            for j in jb..(jb + TILE).min(n) {
                for i in ib.max(j + 1)..(ib + TILE).min(n) {
                    if (a[(i, j)] - a[(j, i)]).abs() > tol {
                        return Some((i, j));
                    }
                }
            }
        }
    }
    None
}

impl SlamFilter {
    /// Checks a received delta before anything changes: sizes, unique ids, finite values, the
    /// origin, symmetry to round-off. Returns whether the matrix is *exactly* symmetric (then
    /// its symmetric part is itself and no pass needs to form it).
    pub(super) fn validate_information(&self, delta: &MapInformation) -> Result<bool, SlamError> {
        let k = 3 * delta.ids.len();
        if delta.matrix.nrows() != k || delta.matrix.ncols() != k || delta.vector.nrows() != k {
            return Err(SlamError::InvalidInformation(format!(
                "{} ids but a {}×{} matrix and a {}-vector",
                delta.ids.len(),
                delta.matrix.nrows(),
                delta.matrix.ncols(),
                delta.vector.nrows()
            )));
        }
        let mut seen = HashSet::new();
        if let Some(d) = delta.ids.iter().find(|id| !seen.insert(**id)) {
            return Err(SlamError::InvalidInformation(format!(
                "duplicate feature id {d}"
            )));
        }
        // One pass for finiteness and the scale, one (tiled) for the symmetry.
        let (finite, scale) = crate::info::finite_and_norm_max(&delta.matrix);
        if !finite
            || !(0..k).all(|i| delta.vector[i].is_finite())
            || !delta.origin.iter().all(|v| v.is_finite())
        {
            return Err(SlamError::InvalidInformation("non-finite value".into()));
        }
        // Team origins are one configured constant; a mismatch beyond 1 µm is a wiring error.
        if (delta.origin - self.config.origin).norm() > 1e-6 {
            return Err(SlamError::OriginMismatch);
        }
        // Symmetric up to round-off of the sender's own arithmetic (1e-9 relative).
        let tol = 1e-9 * scale;
        let worst = crate::info::max_asymmetry(&delta.matrix).0;
        if worst > tol
            && let Some((i, j)) = asymmetry_beyond(delta.matrix.as_ref(), tol)
        {
            return Err(SlamError::InvalidInformation(format!(
                "matrix is not symmetric at ({i}, {j})"
            )));
        }
        Ok(worst == 0.0)
    }

    /// `delta` with its features in this filter's order: the ones the filter holds in map
    /// order, then the new ones in the delta's order (the order they are added in). A
    /// permutation of rows and columns (exact); no copy when it is in that order already.
    /// Fusing in the filter's order lets the maintained map information be used as it is
    /// (no permuted copy of Y_mm) and be updated by a plain sum.
    ///
    /// A delta that misses a few of the map's features (1/16 of those it holds at most: the
    /// round's batch lacks this vehicle's features no neighbour has yet) gets zero information
    /// for them in the same copy, so that it is fused as a whole-map delta: the maintained map
    /// information is then Y_aa itself, where the map route otherwise forms Y_aa as the Schur
    /// complement Y_aa − Y_ab Y_bb⁻¹ Y_ba in a k × k buffer of its own (27 MB at 620 features,
    /// at the peak of the round). The same fusion in exact arithmetic (zero information on b
    /// changes nothing; eq. 21.92); the inverse is k³ instead of k_a³ (≤ 1.2 × with this
    /// bound). Not padded when the cache is not current or the map route would not be taken.
    pub(super) fn in_filter_order(&self, delta: MapInformation) -> MapInformation {
        let Some(blocks) = self.filter_order_blocks(&delta.ids) else {
            return delta;
        };
        let rows: Vec<Option<usize>> = blocks
            .iter()
            .flat_map(|&(_, b)| (0..3).map(move |c| b.map(|b| 3 * b + c)))
            .collect();
        MapInformation {
            ids: blocks.iter().map(|&(id, _)| id).collect(),
            origin: delta.origin,
            matrix: gather_padded(delta.matrix.as_ref(), &rows, &rows),
            vector: Col::from_fn(rows.len(), |i| rows[i].map_or(0.0, |r| delta.vector[r])),
        }
    }

    /// A packed batch of received information ([`PackedInformation`]: a vehicle's sum of
    /// received deltas) in dense form, in the order [`fuse_map_information_owned`] would put
    /// it in (`in_filter_order`, padding included), formed straight from the packed form: one
    /// dense matrix instead of the dense batch and its gathered copy. The same numbers as
    /// `in_filter_order(batch.to_dense())`.
    ///
    /// [`fuse_map_information_owned`]: SlamFilter::fuse_map_information_owned
    pub fn dense_in_filter_order(&self, batch: &PackedInformation) -> MapInformation {
        match self.filter_order_blocks(batch.ids()) {
            Some(blocks) => batch.to_dense_gathered(&blocks),
            None => batch.to_dense(),
        }
    }

    /// Makes room in P and in the maintained Y for the features of `ids` this filter does not
    /// hold yet, without changing either (capacity only). The fusion does it itself; a caller
    /// that is about to unpack a batch into its dense form calls it first, so that a
    /// re-allocation's old and new copies are alive beside the packed batch, not the dense one.
    pub fn reserve_for_information(&mut self, ids: &[FeatureId]) {
        let nu = 3 * ids
            .iter()
            .filter(|&&id| self.layout.feature_offset(id).is_none())
            .count();
        if nu > 0 {
            self.reserve_new_features(nu);
        }
    }

    /// Room for `nu` more map states in P and, when it is current, in the maintained Y.
    fn reserve_new_features(&mut self, nu: usize) {
        self.reserve_states(nu);
        if self.info_cache_current()
            && let Some(y) = self.info_cache.y.as_mut()
        {
            let n = y.nrows() + nu;
            super::info_cache::reserve_square(y, n);
        }
    }

    /// The blocks of `in_filter_order`'s result for a delta on `ids`: (id, the delta's block,
    /// or None for zero information); `None` when the delta is already in that order.
    fn filter_order_blocks(&self, ids: &[FeatureId]) -> Option<Vec<(FeatureId, Option<usize>)>> {
        let nf = ids.len();
        let mut order: Vec<(usize, usize)> = ids
            .iter()
            .enumerate()
            .map(|(b, &id)| match self.layout.feature_offset(id) {
                Some(off) => (off, b),
                None => (usize::MAX, b),
            })
            .collect();
        order.sort_unstable();
        let known = order
            .iter()
            .take_while(|(off, _)| *off != usize::MAX)
            .count();
        let missing = self.layout.num_features().saturating_sub(known);
        let pad = self.info_cache_current()
            && known > 0
            && missing > 0
            && 16 * missing <= known
            && 2 * 3 * known >= self.dim() + 3 * (nf - known);
        if pad {
            let mut next = 0;
            let mut blocks: Vec<(FeatureId, Option<usize>)> = self
                .layout
                .features()
                .map(|(id, off)| match order.get(next) {
                    Some(&(o, b)) if next < known && o == off => {
                        next += 1;
                        (id, Some(b))
                    }
                    _ => (id, None),
                })
                .collect();
            blocks.extend(order[known..].iter().map(|&(_, b)| (ids[b], Some(b))));
            Some(blocks)
        } else {
            if order.iter().enumerate().all(|(i, &(_, b))| i == b) {
                return None;
            }
            Some(order.iter().map(|&(_, b)| (ids[b], Some(b))).collect())
        }
    }

    /// Adds received map information (ΔY, Δy) to the joint filter (module docs). On any error the
    /// filter's estimate is unchanged.
    pub fn fuse_map_information(
        &mut self,
        delta: &MapInformation,
    ) -> Result<FuseReport, SlamError> {
        let exact = self.validate_information(delta)?;
        let delta = self.in_filter_order(delta.clone());
        self.fuse_validated(delta, exact).map_err(|r| r.0)
    }

    /// [`SlamFilter::fuse_map_information`] taking the delta by value: a delta on the whole map
    /// in the filter's order (the round's batch of received deltas) is fused in its own buffer
    /// instead of a copy of it (k × k less at the peak of a round). On an error before the
    /// filter changed, the delta comes back with it (in the filter's order; `None` after a
    /// failure that rolled a change back).
    pub fn fuse_map_information_owned(
        &mut self,
        delta: MapInformation,
    ) -> Result<FuseReport, Refused> {
        let exact = match self.validate_information(&delta) {
            Ok(e) => e,
            Err(e) => return Err(Box::new((e, Some(delta)))),
        };
        let delta = self.in_filter_order(delta);
        self.fuse_validated(delta, exact)
    }

    /// The fusion of a validated delta in the filter's order ([`SlamFilter::in_filter_order`];
    /// `exact`: its matrix is exactly symmetric).
    fn fuse_validated(
        &mut self,
        mut delta: MapInformation,
        exact: bool,
    ) -> Result<FuseReport, Refused> {
        let o = self.config.origin;
        // Partition the delta's 3-blocks into known (in the filter) and new features: known
        // ones first (filter order).
        let mut known_state = Vec::new(); // state indices
        let mut new_ids = Vec::new();
        for &id in &delta.ids {
            match self.layout.feature_offset(id) {
                Some(off) => known_state.extend(off..off + 3),
                None => new_ids.push(id),
            }
        }
        let nk = known_state.len();
        let nu = 3 * new_ids.len();
        let known_pos: Vec<usize> = (0..nk).collect();
        let new_pos: Vec<usize> = (nk..nk + nu).collect();
        let mut report = FuseReport {
            known_features: nk / 3,
            ..Default::default()
        };
        if nk + nu == 0 {
            return Ok(report);
        }
        if nu > 0 {
            // Room for the new features in P and in the maintained Y first: a re-allocation
            // copies the matrix, and done here the old and the new copy are not alive beside
            // the k × k temporaries below (capacity only: no number changes). A caller holding
            // the delta in a smaller form reserves before unpacking it
            // ([`SlamFilter::reserve_for_information`]).
            self.reserve_new_features(nu);
        }
        let xk_minus_o = Col::from_fn(nk, |i| self.x[known_state[i]] - o[i % 3]);
        let dy_k = Col::from_fn(nk, |i| delta.vector[i]);
        // Deltas on at least half the state go through the map information (module docs).
        let map_route = nk > 0 && 2 * nk >= self.dim() + nu;
        // The whole map in map order (the usual batch): Y + ΔY is then the fused marginal
        // information itself, and ΔY is not needed after it is formed.
        let whole_map = map_route && nu == 0 && known_state == self.map_state_indices();
        // ΔY_kk: the delta's own matrix when it is the whole map (no copy), else its leading
        // block; its symmetric part only when it is not exactly symmetric. An exact delta with
        // new features gives up its buffer to ΔY_kk too (truncated in place: the copy was a
        // k × k at the peak of a vehicle's round), keeping what rebuilds it on a refusal.
        let mut split = None;
        let (y_kk, moved) = if whole_map {
            let mut m = std::mem::replace(&mut delta.matrix, Mat::new());
            if !exact {
                crate::info::symmetrize(&mut m);
            }
            (m, true)
        } else if exact && nu > 0 {
            let (kept, y_kk) = SplitDelta::take(&mut delta.matrix, nk);
            split = Some(kept);
            (y_kk, false)
        } else if exact {
            (
                delta.matrix.as_ref().submatrix(0, 0, nk, nk).to_owned(),
                false,
            )
        } else {
            (
                gather_sym(delta.matrix.as_ref(), &known_pos, &known_pos),
                false,
            )
        };
        // On an error before anything changed, the delta goes back to the caller whole.
        let give_back = |mut delta: MapInformation, y_kk: Option<Mat<f64>>| {
            if let Some(m) = y_kk {
                delta.matrix = m;
            } else if let Some(kept) = &split {
                delta.matrix = kept.rebuild();
            }
            Some(delta)
        };

        // Step 1 quantities (no mutation yet).
        let (schur, schur_vec, new_block) = if nu > 0 {
            let gathered;
            let (y_uu, y_uk) = match &split {
                Some(kept) => (&kept.y_uu, &kept.y_uk),
                None => {
                    gathered = (
                        gather_sym(delta.matrix.as_ref(), &new_pos, &new_pos),
                        gather_sym(delta.matrix.as_ref(), &new_pos, &known_pos),
                    );
                    (&gathered.0, &gathered.1)
                }
            };
            let dy_u = Col::from_fn(nu, |i| delta.vector[new_pos[i]]);
            let Ok(llt) = y_uu.llt(Side::Lower) else {
                return Err(Box::new((
                    SlamError::NotPositiveDefinite("information on new features ΔY_uu"),
                    give_back(delta, None),
                )));
            };
            let y_uu_inv = llt.inverse();
            let b = llt.solve(&y_uk); // ΔY_uu⁻¹ ΔY_uk
            let a = llt.solve(dy_u.as_mat()); // ΔY_uu⁻¹ Δy_u
            // Ȳ = ΔY_kk − ΔY_ukᵀ B accumulated into ΔY_kk's own buffer: neither a third k × k
            // beside ΔY_kk and the product nor the product itself (a k × k temporary at the
            // heap peak of a vehicle with three neighbours); equal to `&y_kk - …` up to the
            // order of round-off.
            let mut schur = y_kk;
            matmul(
                schur.as_mut(),
                Accum::Add,
                y_uk.transpose(),
                b.as_ref(),
                -1.0,
                Par::Seq,
            );
            let schur_vec = &dy_k - y_uk.transpose() * a.col(0);
            let x_u = Col::from_fn(nu, |i| a[(i, 0)] + o[i % 3]) - &b * &xk_minus_o;
            (schur, schur_vec, Some((b, y_uu_inv, x_u)))
        } else {
            (y_kk, dy_k, None)
        };
        if let Some((b, y_uu_inv, x_u)) = &new_block
            && (!all_finite(b.as_ref())
                || !all_finite(y_uu_inv.as_ref())
                || !(0..nu).all(|i| x_u[i].is_finite()))
        {
            return Err(Box::new((
                SlamError::NumericalFailure("new-feature conditional"),
                give_back(delta, None),
            )));
        }

        // Everything that can fail for the known-feature part is computed before any mutation
        // (map blocks are never stale, so no flush is needed for P_kk).
        let route = if nk == 0 {
            None
        } else {
            let g = &schur_vec - &schur * &xk_minus_o;
            let prepared = if map_route {
                // Ȳ + Y_aa is needed after the factorisation only as the whole map's new
                // information (and Ȳ on a refusal only as the delta given back): otherwise
                // the factor is formed in Ȳ's own buffer.
                self.prepare_map_route(&known_state, schur, g, whole_map)
            } else {
                self.prepare_pseudo_route(&known_state, &schur, g)
                    .map_err(|e| (e, schur))
            };
            match prepared {
                Ok(r) => Some(r),
                Err((e, schur)) => {
                    return Err(Box::new((e, give_back(delta, moved.then_some(schur)))));
                }
            }
        };

        // Mutation starts here. Flushing changes only the representation of P.
        self.flush();
        // The map information after the fusion is exactly Y + ΔY (aligned): keep the cache.
        // Taken, not cloned (k² copy): the cache is rebuilt below or dropped on error.
        let current = self.info_cache_current();
        let info_before = self.info_cache.y.take().filter(|_| current);
        self.bump_map_generation(false);
        let n0 = self.dim();
        if let Some((b, y_uu_inv, x_u)) = &new_block {
            // P_u· = −B P_k·, P_uu = ΔY_uu⁻¹ + B P_kk Bᵀ. The known states are one run of P
            // (the usual batch: every known feature) and are then read in place; a k × n and a
            // k × k copy of P otherwise, one at a time.
            let mut p_u_all = Mat::zeros(nu, n0);
            let mut p_uu = y_uu_inv.clone();
            if nk > 0 {
                let b_p_k = |p_k: MatRef<'_, f64>, out: &mut Mat<f64>| {
                    matmul(
                        out.as_mut(),
                        Accum::Replace,
                        b.as_ref(),
                        p_k,
                        -1.0,
                        Par::Seq,
                    );
                };
                match contiguous(&known_state) {
                    Some(k0) => {
                        b_p_k(self.p.as_ref().subrows(k0, nk), &mut p_u_all);
                        p_uu += b * self.p.as_ref().submatrix(k0, k0, nk, nk) * b.transpose();
                    }
                    None => {
                        let p_k_all = Mat::from_fn(nk, n0, |i, j| self.p[(known_state[i], j)]);
                        b_p_k(p_k_all.as_ref(), &mut p_u_all);
                        drop(p_k_all);
                        let p_kk = gather(self.p.as_ref(), &known_state, &known_state);
                        p_uu += b * &p_kk * b.transpose();
                    }
                }
            }
            self.grow(nu);
            for (f, &id) in new_ids.iter().enumerate() {
                let off = self.layout.push(SlotKind::Feature(id));
                debug_assert_eq!(off, n0 + 3 * f);
            }
            for i in 0..nu {
                self.x[n0 + i] = x_u[i];
                for j in 0..n0 {
                    self.p[(n0 + i, j)] = p_u_all[(i, j)];
                    self.p[(j, n0 + i)] = p_u_all[(i, j)];
                }
                for j in 0..nu {
                    self.p[(n0 + i, n0 + j)] = 0.5 * (p_uu[(i, j)] + p_uu[(j, i)]);
                }
            }
            report.new_features = new_ids.clone();
        }
        let mut map_route_post: Option<Mat<f64>> = None;
        let result = match route {
            None => Ok(()),
            Some(Route::Pseudo { h_k, signs, nu }) => {
                report.method = FuseMethod::PseudoMeasurement;
                report.rank = Some(signs.len());
                report.negative_directions = Some(signs.iter().filter(|s| **s < 0.0).count());
                self.apply_pseudo_route(&known_state, &h_k, &signs, &nu)
            }
            Some(Route::Map {
                p_aa_post,
                y_aa,
                dx_a,
                post,
            }) => {
                report.method = FuseMethod::MapInformation;
                let r = match y_aa.as_ref().or(info_before.as_ref()) {
                    Some(y_aa) => self.apply_map_route(&known_state, &p_aa_post, y_aa, &dx_a),
                    None => Err(SlamError::NumericalFailure("map-information cache")),
                };
                // Y_aa⁺: the whole map's new information when the delta is the whole map.
                map_route_post = post;
                r
            }
        };
        if let Err(e) = result {
            // Roll back the augmentation: the new features are the last slots.
            for id in &new_ids {
                self.layout.remove(SlotKind::Feature(*id));
            }
            self.truncate_to(n0);
            return Err(Box::new((e, None)));
        }
        // New features were appended behind any stored poses: restore vehicles, features, poses.
        self.settle_poses_last();
        let info_next = info_before.and_then(|y| {
            if whole_map {
                return map_route_post;
            }
            if moved {
                // ΔY went into the route (cannot happen: `moved` only for the whole map).
                return None;
            }
            let pos: std::collections::HashMap<FeatureId, usize> = self
                .layout
                .features()
                .enumerate()
                .map(|(i, (id, _))| (id, i))
                .collect();
            // Y grown in place (spare capacity: no k × k copy per new feature), then + ΔY.
            let mut out = y;
            super::info_cache::grow_square(&mut out, 3 * pos.len());
            let at: Vec<usize> = delta
                .ids
                .iter()
                .flat_map(|id| {
                    let b = 3 * pos[id];
                    b..b + 3
                })
                .collect();
            match (contiguous(&at), &split) {
                // The known features in map order, then the new ones: one run of columns.
                (Some(a0), None) => {
                    for (jj, j) in (a0..a0 + at.len()).enumerate() {
                        let src = delta.matrix.col_as_slice(jj);
                        let dst = &mut out.col_as_slice_mut(j)[a0..a0 + at.len()];
                        for (d, s) in dst.iter_mut().zip(src) {
                            *d += s;
                        }
                    }
                }
                (_, kept) => {
                    for (jj, &j) in at.iter().enumerate() {
                        for (ii, &i) in at.iter().enumerate() {
                            out[(i, j)] += match kept {
                                Some(kept) => kept.entry(ii, jj),
                                None => delta.matrix[(ii, jj)],
                            };
                        }
                    }
                }
            }
            Some(out)
        });
        self.store_info(info_next);
        Ok(report)
    }

    /// Pseudo-measurement route (small deltas): factors of Ȳ with Hᵀ D⁻¹ H = Ȳ, Hᵀ D⁻¹ ν = g.
    /// The PD check of the fused result is implied when Ȳ ⪰ 0 and explicit otherwise.
    fn prepare_pseudo_route(
        &self,
        known_state: &[usize],
        schur: &Mat<f64>,
        g: Col<f64>,
    ) -> Result<Route, SlamError> {
        let nk = known_state.len();
        if let Ok(llt) = schur.llt(Side::Lower) {
            // Positive definite (the common case): Ȳ = L Lᵀ, H_k = Lᵀ, D = I, ν = L⁻¹ g;
            // k³/3 instead of an eigendecomposition, and PD + PD needs no check.
            let l = llt.L().to_owned();
            let mut nu = g;
            l.solve_lower_triangular_in_place(nu.as_mat_mut());
            return Ok(Route::Pseudo {
                h_k: l.transpose().to_owned(),
                signs: vec![1.0; nk],
                nu,
            });
        }
        let evd = schur
            .self_adjoint_eigen(Side::Lower)
            .map_err(|_| SlamError::NumericalFailure("eigendecomposition of the delta"))?;
        let lambda: Vec<f64> = (0..nk).map(|i| evd.S().column_vector()[i]).collect();
        if lambda.iter().any(|l| *l < 0.0) {
            // Fused information PD ⇔ P_kk⁻¹ + Ȳ ≻ 0 ⇔ I + Lᵀ Ȳ L ≻ 0 with P_kk = L Lᵀ.
            let p_kk = gather(self.p.as_ref(), known_state, known_state);
            let l = p_kk
                .llt(Side::Lower)
                .map_err(|_| SlamError::NotPositiveDefinite("filter map covariance"))?
                .L()
                .to_owned();
            let t = Mat::<f64>::identity(nk, nk) + l.transpose() * schur * &l;
            if t.llt(Side::Lower).is_err() {
                return Err(SlamError::NotPositiveDefinite("fused information"));
            }
        }
        let vmat = evd.U().to_owned();
        let max = lambda.iter().fold(0.0_f64, |m, l| m.max(l.abs()));
        // Directions with |λ| ≤ 1e-12·max carry no information at double precision.
        let keep: Vec<usize> = (0..nk)
            .filter(|&i| max > 0.0 && lambda[i].abs() > 1e-12 * max)
            .collect();
        let r = keep.len();
        // H_k = |Λ|^½ Vᵀ (r × nk), D = sign(Λ), ν = D |Λ|^{-½} Vᵀ g.
        let h_k = Mat::from_fn(r, nk, |a, j| {
            lambda[keep[a]].abs().sqrt() * vmat[(j, keep[a])]
        });
        let signs: Vec<f64> = keep.iter().map(|&i| lambda[i].signum()).collect();
        let nu = Col::from_fn(r, |a| {
            let vg: f64 = (0..nk).map(|j| vmat[(j, keep[a])] * g[j]).sum();
            signs[a] * vg / lambda[keep[a]].abs().sqrt()
        });
        Ok(Route::Pseudo { h_k, signs, nu })
    }

    /// Kalman update with the pseudo-measurement: M = P[:, k] H_kᵀ, S = H_k M[k, :] + D.
    fn apply_pseudo_route(
        &mut self,
        known_state: &[usize],
        h_k: &Mat<f64>,
        signs: &[f64],
        nu: &Col<f64>,
    ) -> Result<(), SlamError> {
        let r = signs.len();
        if r == 0 {
            return Ok(());
        }
        let n = self.dim();
        let p_nk = Mat::from_fn(n, known_state.len(), |i, j| self.p[(i, known_state[j])]);
        let m = &p_nk * h_k.transpose();
        let m_k = gather(m.as_ref(), known_state, &(0..r).collect::<Vec<_>>());
        let mut s = h_k * &m_k;
        for (a, sg) in signs.iter().enumerate() {
            s[(a, a)] += sg;
        }
        let form = if signs.iter().all(|s| *s > 0.0) {
            UpdateForm::Joseph
        } else {
            UpdateForm::Indefinite
        };
        self.kalman_apply(m, s, nu, form)
    }

    /// Map-information route (deltas covering at least half the state): with a = the delta's
    /// known features, Y_aa = P_aa⁻¹ is the marginal information, P_aa⁺ = (Y_aa + Ȳ)⁻¹ (its
    /// Cholesky is the PD check), and everything else follows from the unchanged conditional of
    /// the other states b given a: with C = P_ba Y_aa, P_ba⁺ = C P_aa⁺,
    /// P_bb⁺ = P_bb + C (P_aa⁺ − P_aa) Cᵀ, x_a⁺ = x_a + P_aa⁺ g, x_b⁺ = x_b + C (x_a⁺ − x_a).
    /// Cost ≈ two k×k Cholesky inverses + O(n_b·k² + n_b²·k).
    ///
    /// On an error Ȳ (`schur`) comes back unchanged with it.
    fn prepare_map_route(
        &self,
        known_state: &[usize],
        schur: Mat<f64>,
        g: Col<f64>,
        keep_post: bool,
    ) -> Result<Route, (SlamError, Mat<f64>)> {
        let cached = self
            .info_cache
            .y
            .as_ref()
            .filter(|_| self.info_cache_current());
        // Y_aa, the marginal information of the delta's known features: from the maintained
        // map information when it is current (whole map: a permutation; a subset a of the
        // features with the rest b: the Schur complement Y_aa − Y_ab Y_bb⁻¹ Y_ba, an inversion
        // of the small b block only), else by inverting P_aa.
        let from_cache = cached.and_then(|y| {
            let mut pos = vec![usize::MAX; self.dim()];
            for (i, (_, off)) in self.layout.features().enumerate() {
                for c in 0..3 {
                    pos[off + c] = 3 * i + c;
                }
            }
            let a: Vec<usize> = known_state.iter().map(|s| pos[*s]).collect();
            if a.contains(&usize::MAX) || y.nrows() < a.len() {
                return None;
            }
            if a.len() == y.nrows() {
                // The whole map in map order is the cache itself (borrowed, not copied).
                return Some(if a.iter().enumerate().all(|(i, &p)| i == p) {
                    None
                } else {
                    Some(gather(y.as_ref(), &a, &a))
                });
            }
            let mut in_a = vec![false; y.nrows()];
            for &i in &a {
                in_a[i] = true;
            }
            let b: Vec<usize> = (0..y.nrows()).filter(|i| !in_a[*i]).collect();
            // Only worth it while the complement is small next to the delta.
            if 2 * b.len() > a.len() {
                return None;
            }
            let y_bb = gather_sym(y.as_ref(), &b, &b);
            let y_ba = gather(y.as_ref(), &b, &a);
            let llt = y_bb.llt(Side::Lower).ok()?;
            let sol = llt.solve(&y_ba); // Y_bb⁻¹ Y_ba
            let mut y_aa = gather(y.as_ref(), &a, &a);
            matmul(
                y_aa.as_mut(),
                Accum::Add,
                y_ba.transpose(),
                sol.as_ref(),
                -1.0,
                Par::Seq,
            );
            Some(Some(y_aa))
        });
        // `None`: Y_aa is the maintained cache itself (whole map, map order).
        let y_aa: Option<Mat<f64>> = match from_cache {
            Some(y) => y,
            None => match gather(self.p.as_ref(), known_state, known_state).llt(Side::Lower) {
                Ok(llt) => Some(llt.inverse()),
                Err(_) => {
                    return Err((
                        SlamError::NotPositiveDefinite("filter map covariance"),
                        schur,
                    ));
                }
            },
        };
        let y_aa_ref = match (&y_aa, cached) {
            (Some(y), _) => y,
            (None, Some(c)) => c,
            (None, None) => {
                return Err((SlamError::NumericalFailure("map-information cache"), schur));
            }
        };
        // P_aa⁺ = (Ȳ + Y_aa)⁻¹, the sum formed straight into the factor's buffer (its Cholesky
        // is the PD check). With `keep_post`, Ȳ stays as it is until everything that can fail
        // has passed, and Ȳ + Y_aa is then formed in its buffer (the same sums the factor was
        // formed from); without, the factor's buffer is Ȳ's own (one k × k less at the peak
        // of a round; Ȳ is not needed after a refusal then).
        let (p_aa_post, post) = if keep_post {
            match crate::info::spd_inverse_of_sum(schur.as_ref(), y_aa_ref.as_ref()) {
                Ok(p) => (p, Some(schur)),
                Err(_) => {
                    return Err((SlamError::NotPositiveDefinite("fused information"), schur));
                }
            }
        } else {
            match crate::info::spd_inverse_of_sum_into(schur, y_aa_ref.as_ref()) {
                Ok(p) => (p, None),
                Err(_) => {
                    return Err((
                        SlamError::NotPositiveDefinite("fused information"),
                        Mat::new(),
                    ));
                }
            }
        };
        let dx_a = &p_aa_post * &g;
        if !all_finite(p_aa_post.as_ref())
            || !all_finite(y_aa_ref.as_ref())
            || !all_finite(dx_a.as_mat())
        {
            let schur = post.unwrap_or_else(Mat::new);
            return Err((SlamError::NumericalFailure("map-information fusion"), schur));
        }
        let post = post.map(|mut post| {
            post += y_aa_ref;
            post
        });
        Ok(Route::Map {
            p_aa_post,
            y_aa,
            dx_a,
            post,
        })
    }

    fn apply_map_route(
        &mut self,
        known_state: &[usize],
        p_aa_post: &Mat<f64>,
        y_aa: &Mat<f64>,
        dx_a: &Col<f64>,
    ) -> Result<(), SlamError> {
        let n = self.dim();
        let mut in_a = vec![false; n];
        for &i in known_state {
            in_a[i] = true;
        }
        let rest: Vec<usize> = (0..n).filter(|i| !in_a[*i]).collect();
        let p_ba = gather(self.p.as_ref(), &rest, known_state);
        let c = &p_ba * y_aa;
        let p_ba_post = &c * p_aa_post;
        let dx_b = &c * dx_a;
        let mut p_bb = gather(self.p.as_ref(), &rest, &rest);
        // C (P_aa⁺ − P_aa) = P_ba⁺ − P_ba, since C P_aa = P_ba Y_aa P_aa = P_ba.
        let c_delta = &p_ba_post - &p_ba;
        triangular::matmul(
            p_bb.as_mut(),
            BlockStructure::TriangularLower,
            Accum::Add,
            c_delta.as_ref(),
            BlockStructure::Rectangular,
            c.transpose(),
            BlockStructure::Rectangular,
            1.0,
            Par::Seq,
        );
        if !all_finite(p_bb.as_ref())
            || !all_finite(p_ba_post.as_ref())
            || !all_finite(dx_b.as_mat())
        {
            return Err(SlamError::NumericalFailure("map-information fusion"));
        }
        for (jj, &j) in rest.iter().enumerate() {
            for (ii, &i) in rest.iter().enumerate().skip(jj) {
                self.p[(i, j)] = p_bb[(ii, jj)];
                self.p[(j, i)] = p_bb[(ii, jj)];
            }
            for (aa, &a) in known_state.iter().enumerate() {
                self.p[(j, a)] = p_ba_post[(jj, aa)];
                self.p[(a, j)] = p_ba_post[(jj, aa)];
            }
        }
        // P_aa⁺ from a Cholesky inverse is symmetric (faer mirrors it).
        if let Some(a0) = contiguous(known_state) {
            let k = known_state.len();
            self.p
                .as_mut()
                .submatrix_mut(a0, a0, k, k)
                .copy_from(p_aa_post);
        } else {
            for (bb, &b) in known_state.iter().enumerate() {
                for (aa, &a) in known_state.iter().enumerate() {
                    self.p[(a, b)] = p_aa_post[(aa, bb)];
                }
            }
        }
        for (aa, &a) in known_state.iter().enumerate() {
            self.x[a] += dx_a[aa];
        }
        for (jj, &j) in rest.iter().enumerate() {
            self.x[j] += dx_b[jj];
        }
        Ok(())
    }
}

/// The known-feature part of a fusion, prepared before any mutation.
enum Route {
    /// Pseudo-measurement factors.
    Pseudo {
        h_k: Mat<f64>,
        signs: Vec<f64>,
        nu: Col<f64>,
    },
    /// Map-information route quantities.
    Map {
        p_aa_post: Mat<f64>,
        /// Y_aa, or `None` when it is the maintained map information itself.
        y_aa: Option<Mat<f64>>,
        dx_a: Col<f64>,
        /// Y_aa + Ȳ: the fused marginal information of the delta's features (only when asked
        /// for: the whole map's).
        post: Option<Mat<f64>>,
    },
}

/// Relative size, against the largest entry of the map information and of the delta, below
/// which a feature's fused information counts as *vanished* (see
/// [`SlamFilter::fuse_map_information_forgetting`]).
///
/// Why this value: the fused information of a feature whose contributions cancel exactly (a
/// DDF resynchronisation removing what a restarted neighbour held) is the round-off of sums of
/// terms of the largest size, measured at ≲ 1e-11 of it in the crash–restart scenarios; a
/// feature that still carries genuine information has at least ~1e-5 of it (σ of tens of metres
/// against the best-known features' decimetres). 1e-9 sits between with two decades each way.
pub const VANISHED_RTOL: f64 = 1e-9;

/// What [`SlamFilter::fuse_map_information_forgetting`] did beyond a plain fusion.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ForgetReport {
    /// The fusion of the information that remained.
    pub fused: FuseReport,
    /// Known features whose information vanished: removed from the state.
    pub forgotten: Vec<FeatureId>,
    /// New features of the delta that carried no information: not added.
    pub skipped: Vec<FeatureId>,
}

impl SlamFilter {
    /// Removes features from the state: their entries of x and rows and columns of P are
    /// dropped, which in covariance form is exactly marginalizing them out (the other states'
    /// estimate and covariance are unchanged). Unknown ids are ignored; returns how many were
    /// removed.
    pub fn forget_features(&mut self, ids: &[FeatureId]) -> usize {
        let mut removed = 0;
        for &id in ids {
            if self.remove_block(SlotKind::Feature(id)) {
                removed += 1;
            }
        }
        if removed > 0 {
            self.map_generation += 1;
        }
        removed
    }

    /// [`SlamFilter::fuse_map_information`], and when that is refused because the fused
    /// information would not be positive definite *only* because some features are left with
    /// no information at all (their fused 3×3 diagonal block is below [`VANISHED_RTOL`] of the
    /// largest entry — round-off of an exact cancellation), fuses the rest and removes those
    /// features.
    ///
    /// This is what a channel-filter resynchronisation needs after a neighbour restarts
    /// (ddf module docs): the first delta removes everything the lost process held, which leaves
    /// the features only it had observed with exactly zero information — a state an EKF cannot
    /// hold (infinite covariance) but marginalization represents exactly. With Y' = Y + ΔY the
    /// fused map information and V the vanished features, Y'_VV ≈ 0 and, Y' being positive
    /// semi-definite, Y'_V· ≈ 0: the remaining features' information is Y'_rr. It is applied by
    /// fusing ΔY with its V×V block replaced by 0 (V keeps its current information, coupled to
    /// the rest only by the round-off Y'_Vr) and then removing V, whose marginal leaves Y'_rr up to
    /// that round-off. New features of V carry nothing and are not added.
    ///
    /// Any other refusal is returned unchanged, and on any error the filter is unchanged.
    pub fn fuse_map_information_forgetting(
        &mut self,
        delta: &MapInformation,
    ) -> Result<ForgetReport, SlamError> {
        self.fuse_map_information_forgetting_owned(delta.clone())
            .map_err(|r| r.0)
    }

    /// [`SlamFilter::fuse_map_information_forgetting`] taking the delta by value (see
    /// [`SlamFilter::fuse_map_information_owned`]); a refusal that changed nothing gives the
    /// delta back (the caller may retry it with what arrives meanwhile).
    pub fn fuse_map_information_forgetting_owned(
        &mut self,
        delta: MapInformation,
    ) -> Result<ForgetReport, Refused> {
        let (err, delta) = match self.fuse_map_information_owned(delta) {
            Ok(fused) => {
                return Ok(ForgetReport {
                    fused,
                    ..Default::default()
                });
            }
            Err(r) => match *r {
                (e @ SlamError::NotPositiveDefinite(_), Some(delta)) => (e, delta),
                other => return Err(Box::new(other)),
            },
        };
        let y = match self.map_information() {
            Ok(y) => y,
            Err(e) => return Err(Box::new((e, Some(delta)))),
        };
        let scale = y.matrix_norm_max().max(delta.matrix_norm_max());
        let mut vanished = HashSet::new();
        for (b, &id) in delta.ids.iter().enumerate() {
            let own = y.index_of(id);
            let mut blk = nalgebra::Matrix3::<f64>::zeros();
            for r in 0..3 {
                for c in 0..3 {
                    blk[(r, c)] = delta.matrix[(3 * b + r, 3 * b + c)]
                        + own.map_or(0.0, |o| y.matrix[(3 * o + r, 3 * o + c)]);
                }
            }
            let blk = (blk + blk.transpose()) * 0.5;
            if blk.symmetric_eigenvalues().abs().max() <= VANISHED_RTOL * scale {
                vanished.insert(id);
            }
        }
        if vanished.is_empty() {
            return Err(Box::new((err, Some(delta))));
        }
        // ΔY with the vanished features' own blocks zeroed (known ones) or removed (new ones).
        let keep: Vec<FeatureId> = delta
            .ids
            .iter()
            .copied()
            .filter(|id| !vanished.contains(id) || self.layout.has_feature(*id))
            .collect();
        let mut reduced = delta.restrict(&keep);
        let mut forgotten = Vec::new();
        for (b, &id) in reduced.ids.iter().enumerate() {
            if vanished.contains(&id) {
                forgotten.push(id);
                for r in 0..3 {
                    reduced.vector[3 * b + r] = 0.0;
                    for c in 0..3 {
                        reduced.matrix[(3 * b + r, 3 * b + c)] = 0.0;
                    }
                }
            }
        }
        let skipped: Vec<FeatureId> = delta
            .ids
            .iter()
            .copied()
            .filter(|id| vanished.contains(id) && !self.layout.has_feature(*id))
            .collect();
        let fused = self
            .fuse_map_information_owned(reduced)
            .map_err(|r| Box::new((r.0, None)))?;
        self.forget_features(&forgotten);
        Ok(ForgetReport {
            fused,
            forgotten,
            skipped,
        })
    }
}

impl SlamFilter {
    /// An external fix of a vehicle's position, velocity and attitude: the linear measurement
    /// z = (p, v, Ψ) + w, w ~ N(0, R) with `covariance` = R (9×9, in the state order p, v, Ψ of
    /// `state`), applied as an EKF update (eqs. 21.56–21.65, Joseph form, H = [I₉ 0] on the
    /// vehicle block; the attitude innovation is wrapped to (−π, π]).
    ///
    /// A vehicle process restarted mid-run re-initialises from such a fix; the centralized
    /// reference applies the same fix so that it still holds all the data of the team.
    pub fn vehicle_fix(
        &mut self,
        vehicle: usize,
        fix: &[f64; 9],
        covariance: &nalgebra::SMatrix<f64, 9, 9>,
    ) -> Result<(), SlamError> {
        if vehicle >= self.num_vehicles() {
            return Err(SlamError::UnknownVehicle(vehicle));
        }
        if !fix.iter().all(|v| v.is_finite()) || !covariance.iter().all(|v| v.is_finite()) {
            return Err(SlamError::NumericalFailure("vehicle fix inputs"));
        }
        if covariance.cholesky().is_none() {
            return Err(SlamError::NotPositiveDefinite("vehicle fix covariance"));
        }
        use crate::state::{ATT, POS, VEL};
        const { assert!(POS + 3 == VEL && VEL + 3 == ATT) };
        self.flush();
        let off = self.layout.vehicle_block(vehicle) + POS;
        let mut nu = Col::zeros(9);
        for i in 0..9 {
            nu[i] = fix[i] - self.x[off + i];
        }
        for i in ATT - POS..ATT - POS + 3 {
            nu[i] = crate::rotation::wrap_angle(nu[i]);
        }
        let r = Mat::from_fn(9, 9, |i, j| 0.5 * (covariance[(i, j)] + covariance[(j, i)]));
        let blocks = [super::update::HBlock {
            row: 0,
            col: off,
            mat: Mat::identity(9, 9),
        }];
        self.map_generation += 1;
        self.blocks_update(&blocks, &nu, r)
    }
}
