//! The map information Y_mm = P_mm⁻¹ (eq. 21.86), kept up to date through the filter's own
//! updates instead of being re-inverted every fusion round.
//!
//! A fusion round needs Y_mm (to form deltas) and, when a whole-map delta arrives, the
//! fused P_mm⁺ = (Y_mm + ΔY)⁻¹. Re-inverting P_mm each round as well would make a round cost two
//! k×k inversions. Every change the filter makes to the map marginal has a cheap exact
//! counterpart in information form, so the inverse is maintained instead:
//!
//! * EKF update (eqs. 21.56–21.60): P⁺ = P − M S⁻¹ Mᵀ with M = P Hᵀ, so on the map block
//!   (Woodbury) Y⁺ = Y + (Y M_m)(S − M_mᵀ Y M_m)⁻¹(Y M_m)ᵀ — O(k²·r). S − M_mᵀ Y M_m is the
//!   innovation covariance given the map (vehicle uncertainty plus R), positive definite.
//! * Feature augmentation (eq. 21.52): the bordered inverse with the 3×3 Schur complement
//!   Σ = P_ff − P_fm Y P_mf (the new feature's variance given the map, ⪰ J_z R J_zᵀ): O(k²).
//! * Fusion of received information: the map marginal information is exactly Y + ΔY
//!   (eqs. 21.92, 21.93 as corrected), aligned by id, new features appended: O(k²).
//! * Prediction leaves P_mm unchanged (eq. 21.25). Bearing-only pose bookkeeping and anything
//!   else invalidates the cache (the next round inverts).
//!
//! Round-off accumulates, so [`SlamFilter::map_information`] probes the cache before use:
//! r = P_mm (Y v) − v for a fixed vector v, and re-inverts when r exceeds the round-off scale of
//! that product or after [`MAX_INCREMENTAL_STEPS`] incremental steps.

use super::SlamFilter;
use faer::linalg::matmul::matmul;
use faer::linalg::solvers::DenseSolveCore;
use faer::prelude::*;
use faer::{Accum, Mat, Par, Side};

/// Re-invert after this many incremental steps even if the probe passes.
pub const MAX_INCREMENTAL_STEPS: u32 = 2000;

/// The cached Y_mm, in map-marginal (layout feature) order.
#[derive(Clone, Debug, Default)]
pub(super) struct InfoCache {
    /// The map generation the cache is valid for.
    pub generation: u64,
    /// Y_mm.
    pub y: Option<Mat<f64>>,
    /// Incremental steps since the last inversion.
    pub steps: u32,
}

impl SlamFilter {
    /// State indices of the map marginal, in its order (features in layout order).
    pub(super) fn map_state_indices(&self) -> Vec<usize> {
        self.layout
            .features()
            .flat_map(|(_, off)| off..off + 3)
            .collect()
    }

    /// Whether the cached Y_mm describes the current map.
    pub(super) fn info_cache_current(&self) -> bool {
        self.info_cache.generation == self.map_generation
            && self
                .info_cache
                .y
                .as_ref()
                .is_some_and(|y| y.nrows() == 3 * self.layout.num_features())
    }

    /// Marks the map as changed; keeps the cache valid when `maintained` (the caller updates
    /// it for the change).
    pub(super) fn bump_map_generation(&mut self, maintained: bool) {
        let was = self.info_cache_current();
        self.map_generation += 1;
        if was && maintained {
            self.info_cache.generation = self.map_generation;
        }
    }

    /// Y⁺ for an EKF update with gain rows M = P Hᵀ and innovation covariance S, if the cache is
    /// current (computed before P changes; `None` when it is not current or fails). The cache is
    /// taken and updated in place (no k × k copy per update): the caller stores the result
    /// ([`SlamFilter::store_info`]), and `None` leaves no cache, as storing `None` does.
    pub(super) fn info_after_update(
        &mut self,
        m: MatRef<'_, f64>,
        s: MatRef<'_, f64>,
    ) -> Option<Mat<f64>> {
        if !self.info_cache_current() {
            return None;
        }
        let idx = self.map_state_indices();
        let mut y = self.info_cache.y.take()?;
        let y_old = &y;
        let r = m.ncols();
        let m_m = Mat::from_fn(idx.len(), r, |i, j| m[(idx[i], j)]);
        let mut w = Mat::zeros(idx.len(), r);
        matmul(
            w.as_mut(),
            Accum::Replace,
            y_old.as_ref(),
            m_m.as_ref(),
            1.0,
            Par::Seq,
        );
        // Σ = S − M_mᵀ Y M_m.
        let mut sigma = s.to_owned();
        matmul(
            sigma.as_mut(),
            Accum::Add,
            m_m.transpose(),
            w.as_ref(),
            -1.0,
            Par::Seq,
        );
        let sigma = Mat::from_fn(r, r, |i, j| 0.5 * (sigma[(i, j)] + sigma[(j, i)]));
        let llt = sigma.llt(Side::Lower).ok()?;
        let sol = llt.solve(w.transpose()); // Σ⁻¹ Wᵀ
        matmul(
            y.as_mut(),
            Accum::Add,
            w.as_ref(),
            sol.as_ref(),
            1.0,
            Par::Seq,
        );
        crate::info::symmetrize(&mut y);
        all_finite(&y).then_some(y)
    }

    /// Y of the map augmented with one feature whose cross-covariance with the state is `cross`
    /// (3 × n, state order) and whose covariance is `p_ff`; `None` when not current or failing.
    /// The cache is taken and bordered in place (grown with spare capacity, [`grow_square`]),
    /// like [`SlamFilter::info_after_update`].
    pub(super) fn info_after_augment(
        &mut self,
        cross: MatRef<'_, f64>,
        p_ff: MatRef<'_, f64>,
    ) -> Option<Mat<f64>> {
        if !self.info_cache_current() {
            return None;
        }
        let idx = self.map_state_indices();
        let k = idx.len();
        let mut out = self.info_cache.y.take()?;
        let y = &out;
        let p_mf = Mat::from_fn(k, 3, |i, j| cross[(j, idx[i])]);
        let mut w = Mat::zeros(k, 3);
        matmul(
            w.as_mut(),
            Accum::Replace,
            y.as_ref(),
            p_mf.as_ref(),
            1.0,
            Par::Seq,
        );
        let mut sigma = p_ff.to_owned();
        matmul(
            sigma.as_mut(),
            Accum::Add,
            p_mf.transpose(),
            w.as_ref(),
            -1.0,
            Par::Seq,
        );
        let sigma = Mat::from_fn(3, 3, |i, j| 0.5 * (sigma[(i, j)] + sigma[(j, i)]));
        let sigma_inv = sigma.llt(Side::Lower).ok()?.inverse();
        let w_si = &w * &sigma_inv;
        grow_square(&mut out, k + 3);
        let mut top = out.as_mut().submatrix_mut(0, 0, k, k);
        matmul(
            top.as_mut(),
            Accum::Add,
            w_si.as_ref(),
            w.transpose(),
            1.0,
            Par::Seq,
        );
        for i in 0..k {
            for j in 0..3 {
                out[(i, k + j)] = -w_si[(i, j)];
                out[(k + j, i)] = -w_si[(i, j)];
            }
        }
        out.as_mut().submatrix_mut(k, k, 3, 3).copy_from(&sigma_inv);
        crate::info::symmetrize(&mut out);
        all_finite(&out).then_some(out)
    }

    /// Stores an incrementally updated Y for the current map generation (or drops the cache).
    pub(super) fn store_info(&mut self, y: Option<Mat<f64>>) {
        match y {
            Some(y) => {
                self.info_cache.y = Some(y);
                self.info_cache.generation = self.map_generation;
                self.info_cache.steps += 1;
            }
            None => self.info_cache.y = None,
        }
    }

    /// The cached Y if it is current and passes the accuracy probe against `p_mm`.
    pub(super) fn checked_info(&self, p_mm: MatRef<'_, f64>) -> Option<&Mat<f64>> {
        if !self.info_cache_current() || self.info_cache.steps > MAX_INCREMENTAL_STEPS {
            return None;
        }
        let y = self.info_cache.y.as_ref()?;
        if self.info_cache.steps == 0 {
            return Some(y);
        }
        let k = y.nrows();
        if k == 0 {
            return Some(y);
        }
        let v = Col::from_fn(k, |i| ((i as f64 + 1.0) * 0.754_877_666).sin());
        let yv = y * &v;
        let r = p_mm * &yv - &v;
        let max_abs = |c: &Col<f64>| (0..c.nrows()).fold(0.0_f64, |a, i| a.max(c[i].abs()));
        let p_max = (0..k).fold(0.0_f64, |a, i| a.max(p_mm[(i, i)].abs()));
        // Round-off scale of the product P (Y v): k terms of size |P|·|Yv|, relative 1e-9 leaves
        // room for a fresh inverse's cond·ε error while catching accumulated drift.
        let tol = 1e-9 * k as f64 * p_max * max_abs(&yv);
        (max_abs(&r) <= tol.max(1e-12)).then_some(y)
    }
}

/// Grows a square matrix to `n` × `n` in place, the new rows and columns zero, reserving ×1.5
/// spare capacity when it must re-allocate (the map grows by a feature at a time: without
/// spare room every new feature would copy the whole k × k matrix). The entries kept are
/// unchanged.
pub(super) fn grow_square(m: &mut Mat<f64>, n: usize) {
    if n <= m.nrows() {
        return;
    }
    reserve_square(m, n);
    m.resize_with(n, n, |_, _| 0.0);
}

/// Makes room in a square matrix for `n` × `n` without changing it (the re-allocation of
/// [`grow_square`], done ahead: a caller about to form large temporaries does it first).
pub(super) fn reserve_square(m: &mut Mat<f64>, n: usize) {
    // faer re-allocates only when the capacity is short; the columns then keep a stride of the
    // reserved row capacity (every access here is by column or through views).
    if n > capacity(m) {
        let cap = n.max(m.nrows() + m.nrows() / 2);
        m.reserve(cap, cap);
    }
}

/// Rows the columns of `m` have room for (its column stride).
fn capacity(m: &Mat<f64>) -> usize {
    usize::try_from(m.col_stride()).unwrap_or(0).max(m.nrows())
}

fn all_finite(m: &Mat<f64>) -> bool {
    super::update::all_finite(m.as_ref())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Growing keeps every entry, adds zero rows and columns, and leaves room to grow again
    /// without moving (the column stride does not change while the capacity lasts).
    #[test]
    fn grow_square_keeps_entries_and_reserves_room() {
        let mut m = Mat::from_fn(30, 30, |i, j| (i * 100 + j) as f64);
        grow_square(&mut m, 33);
        assert_eq!((m.nrows(), m.ncols()), (33, 33));
        for j in 0..33 {
            for i in 0..33 {
                let want = if i < 30 && j < 30 {
                    (i * 100 + j) as f64
                } else {
                    0.0
                };
                assert_eq!(m[(i, j)], want, "({i}, {j})");
            }
        }
        let stride = m.col_stride();
        assert!(capacity(&m) >= 45);
        grow_square(&mut m, 36);
        assert_eq!(m.col_stride(), stride, "grown within the capacity");
        assert_eq!(m[(29, 29)], 2929.0);
        assert_eq!(m[(35, 35)], 0.0);
        grow_square(&mut m, 20); // never shrinks
        assert_eq!(m.nrows(), 36);
    }
}
