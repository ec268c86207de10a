//! EKF update (eqs. 21.56–21.65) in Joseph form exploiting the sparsity of H, and feature
//! augmentation (eqs. 21.51–21.54).

use super::association::UpdateItem;
use super::{FrameReport, ObservationOutcome, RejectReason, SlamError, SlamFilter, SlotKind};
use crate::observation::ObservationModel;
use crate::sensor::FeatureId;
use crate::state::{ATT, POS};
use faer::linalg::matmul::matmul;
use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::prelude::*;
use faer::{Accum, Mat, Side};
use nalgebra::{DMatrix, DVector};

/// A dense block of a sparse observation matrix H: rows `row..row+mat.nrows()`, columns
/// `col..col+mat.ncols()` of H.
#[derive(Clone, Debug)]
pub(super) struct HBlock {
    pub row: usize,
    pub col: usize,
    pub mat: Mat<f64>,
}

/// How to form the posterior covariance.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum UpdateForm {
    /// Joseph form P − K Mᵀ − M Kᵀ + K S Kᵀ (S positive definite, Cholesky).
    Joseph,
    /// P − K Mᵀ with an indefinite "noise" (fusion of indefinite information, LU on S).
    Indefinite,
}

/// dst_lower += alpha · lhs · rhsᵀ, touching only the lower triangle (incl. diagonal) of dst.
fn lower_add(dst: MatMut<'_, f64>, lhs: MatRef<'_, f64>, rhs: MatRef<'_, f64>, alpha: f64) {
    triangular::matmul(
        dst,
        BlockStructure::TriangularLower,
        Accum::Add,
        lhs,
        BlockStructure::Rectangular,
        rhs.transpose(),
        BlockStructure::Rectangular,
        alpha,
        Par::Seq,
    );
}

fn to_faer(m: &DMatrix<f64>) -> Mat<f64> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
}

pub(super) fn all_finite(m: MatRef<'_, f64>) -> bool {
    // NaN and ±∞ have every exponent bit set; branch-free over contiguous columns so that it
    // vectorises (element indexing with bounds checks was a few % of a fusion round).
    const EXP: u64 = 0x7ff0_0000_0000_0000;
    (0..m.ncols()).all(|j| {
        let col = m.col(j);
        match col.try_as_col_major() {
            Some(c) => c
                .as_slice()
                .iter()
                .fold(true, |ok, &x| ok & (x.to_bits() & EXP != EXP)),
            None => (0..col.nrows()).all(|i| col[i].is_finite()),
        }
    })
}

impl SlamFilter {
    /// M = P Hᵀ (n × m) from the blocks of H: only the columns of P that H touches are read.
    pub(super) fn p_times_ht(&self, blocks: &[HBlock], m: usize) -> Mat<f64> {
        let n = self.dim();
        let mut out = Mat::zeros(n, m);
        for b in blocks {
            let (h, w) = (b.mat.nrows(), b.mat.ncols());
            matmul(
                out.as_mut().submatrix_mut(0, b.row, n, h),
                Accum::Add,
                self.p.as_ref().submatrix(0, b.col, n, w),
                b.mat.transpose(),
                1.0,
                Par::Seq,
            );
        }
        out
    }

    /// Kalman update with M = P Hᵀ, S = H P Hᵀ + R and innovation ν (eqs. 21.56–21.60):
    /// K = M S⁻¹, x ← x + K ν, and P ← P − K Mᵀ − M Kᵀ + K S Kᵀ (the Joseph form
    /// (I−KH)P(I−KH)ᵀ + KRKᵀ expanded, O(n²·m)), computed as P − K Mᵀ + (K S − M) Kᵀ in one
    /// rank-2m product on the lower triangle only (the sum is symmetric), then mirrored so P is
    /// exactly symmetric. Everything that can fail is checked before P or x change.
    pub(super) fn kalman_apply(
        &mut self,
        m: Mat<f64>,
        s: Mat<f64>,
        nu: &Col<f64>,
        form: UpdateForm,
    ) -> Result<(), SlamError> {
        let r = s.nrows();
        let n = self.dim();
        let mut s = s;
        for j in 0..r {
            for i in j + 1..r {
                let a = 0.5 * (s[(i, j)] + s[(j, i)]);
                s[(i, j)] = a;
                s[(j, i)] = a;
            }
        }
        if !all_finite(s.as_ref()) || !all_finite(m.as_ref()) || !(0..r).all(|i| nu[i].is_finite())
        {
            return Err(SlamError::NumericalFailure("update inputs"));
        }
        // Kᵀ = S⁻¹ Mᵀ (S symmetric).
        let kt: Mat<f64> = match form {
            UpdateForm::Joseph => {
                let llt = s
                    .llt(Side::Lower)
                    .map_err(|_| SlamError::NotPositiveDefinite("innovation covariance S"))?;
                llt.solve(m.transpose())
            }
            UpdateForm::Indefinite => s.partial_piv_lu().solve(m.transpose()),
        };
        let k = kt.transpose().to_owned();
        let dx = &k * nu;
        if !all_finite(k.as_ref()) || !(0..n).all(|i| dx[i].is_finite()) {
            return Err(SlamError::NumericalFailure("Kalman gain"));
        }
        // The map information after this update (Woodbury on the map block), before P changes.
        let info_next = self.info_after_update(m.as_ref(), s.as_ref());
        match form {
            UpdateForm::Joseph => {
                // lhs = [K | K S − M], rhs = [−M | K]: P += lhs · rhsᵀ = −K Mᵀ + (K S − M) Kᵀ.
                let mut lhs = Mat::zeros(n, 2 * r);
                let mut rhs = Mat::zeros(n, 2 * r);
                lhs.as_mut().submatrix_mut(0, 0, n, r).copy_from(&k);
                let mut ks_m = &k * &s;
                ks_m -= &m;
                lhs.as_mut().submatrix_mut(0, r, n, r).copy_from(&ks_m);
                rhs.as_mut().submatrix_mut(0, 0, n, r).copy_from(-&m);
                rhs.as_mut().submatrix_mut(0, r, n, r).copy_from(&k);
                lower_add(self.p.as_mut(), lhs.as_ref(), rhs.as_ref(), 1.0);
            }
            UpdateForm::Indefinite => {
                lower_add(self.p.as_mut(), k.as_ref(), m.as_ref(), -1.0);
            }
        }
        self.mirror_lower();
        for i in 0..n {
            self.x[i] += dx[i];
        }
        self.store_info(info_next);
        Ok(())
    }

    /// Copies the lower triangle of P onto the upper one (P exactly symmetric).
    pub(super) fn mirror_lower(&mut self) {
        let n = self.dim();
        for j in 0..n {
            for i in j + 1..n {
                self.p[(j, i)] = self.p[(i, j)];
            }
        }
    }

    /// One stacked EKF update of observation items of `vehicle` (linearized at the prior).
    pub(super) fn observation_update(
        &mut self,
        vehicle: usize,
        model: &ObservationModel,
        items: &[&UpdateItem],
    ) -> Result<(), SlamError> {
        let voff = self.layout.vehicle_block(vehicle);
        let d = model.measurement_dim();
        let m = d * items.len();
        let r_one = to_faer(&model.noise_covariance());
        let mut blocks = Vec::with_capacity(3 * items.len());
        let mut nu = Col::zeros(m);
        let mut r = Mat::zeros(m, m);
        for (k, it) in items.iter().enumerate() {
            let row = k * d;
            let off = self
                .layout
                .feature_offset(it.feature)
                .ok_or(SlamError::NumericalFailure("feature slot"))?;
            blocks.push(HBlock {
                row,
                col: voff + POS,
                mat: Mat::from_fn(d, 3, |i, j| it.h_vehicle[(i, j)]),
            });
            blocks.push(HBlock {
                row,
                col: voff + ATT,
                mat: Mat::from_fn(d, 3, |i, j| it.h_vehicle[(i, j + 3)]),
            });
            blocks.push(HBlock {
                row,
                col: off,
                mat: to_faer(&it.h_feature),
            });
            for i in 0..d {
                nu[row + i] = it.innovation[i];
            }
            r.as_mut().submatrix_mut(row, row, d, d).copy_from(&r_one);
        }
        self.blocks_update(&blocks, &nu, r)
    }

    /// Stacked EKF update (eqs. 21.56–21.65) with a sparse H given by its dense blocks, innovation
    /// ν and noise R (m × m): M = P Hᵀ from the touched columns, S = H M + R, Joseph form.
    pub(super) fn blocks_update(
        &mut self,
        blocks: &[HBlock],
        nu: &Col<f64>,
        r: Mat<f64>,
    ) -> Result<(), SlamError> {
        let m = nu.nrows();
        let mm = self.p_times_ht(blocks, m);
        // S = H M + R, reading only the rows of M that H touches.
        let mut s = r;
        for b in blocks {
            let (h, w) = (b.mat.nrows(), b.mat.ncols());
            matmul(
                s.as_mut().submatrix_mut(b.row, 0, h, m),
                Accum::Add,
                b.mat.as_ref(),
                mm.as_ref().submatrix(b.col, 0, w, m),
                1.0,
                Par::Seq,
            );
        }
        self.kalman_apply(mm, s, nu, UpdateForm::Joseph)
    }

    /// Augments the state with a block that is a linear function of existing states plus
    /// independent noise (eqs. 21.52, 21.68, 21.76): x_new = `mean`,
    /// P_new,· = Σ_b J_b P_{b,·}, P_new,new = Σ_b Σ_c J_b P_{b,c} J_cᵀ + `noise`, where each
    /// `(col, J_b)` names the first state of a block b and its k × w Jacobian. Checks finiteness
    /// and (when `require_pd`) positive definiteness of P_new,new before anything changes; then
    /// appends the slot and restores the pose-last order. Returns the new block's offset.
    pub(super) fn augment_linear(
        &mut self,
        kind: SlotKind,
        mean: &[f64],
        jacobians: &[(usize, Mat<f64>)],
        noise: &Mat<f64>,
        require_pd: bool,
    ) -> Result<usize, SlamError> {
        let k = mean.len();
        debug_assert_eq!(kind.dim(), k);
        let n = self.dim();
        let mut cross = Mat::zeros(k, n);
        for (col, j) in jacobians {
            matmul(
                cross.as_mut(),
                Accum::Add,
                j.as_ref(),
                self.p.as_ref().submatrix(*col, 0, j.ncols(), n),
                1.0,
                Par::Seq,
            );
        }
        let mut block = noise.clone();
        for (col, j) in jacobians {
            matmul(
                block.as_mut(),
                Accum::Add,
                cross.as_ref().submatrix(0, *col, k, j.ncols()),
                j.transpose(),
                1.0,
                Par::Seq,
            );
        }
        let block = Mat::from_fn(k, k, |i, j| 0.5 * (block[(i, j)] + block[(j, i)]));
        if !all_finite(cross.as_ref())
            || !all_finite(block.as_ref())
            || !mean.iter().all(|v| v.is_finite())
        {
            return Err(SlamError::NumericalFailure("state augmentation"));
        }
        if require_pd && block.llt(Side::Lower).is_err() {
            return Err(SlamError::NotPositiveDefinite("augmented block covariance"));
        }
        self.grow(k);
        let off = self.layout.push(kind);
        debug_assert_eq!(off, n);
        for i in 0..k {
            self.x[off + i] = mean[i];
            for c in 0..n {
                self.p[(off + i, c)] = cross[(i, c)];
                self.p[(c, off + i)] = cross[(i, c)];
            }
            for j in 0..k {
                self.p[(off + i, off + j)] = block[(i, j)];
            }
        }
        self.settle_poses_last();
        Ok(self.layout.offset(kind).unwrap_or(off))
    }

    /// Restores the layout order vehicles, features, poses (a feature appended behind stored
    /// poses moves in front of them) by permuting the tail of x and P: O(n · tail).
    pub(super) fn settle_poses_last(&mut self) {
        let Some((start, order)) = self.layout.poses_last() else {
            return;
        };
        let n = self.dim();
        let t = order.len();
        debug_assert_eq!(start + t, n);
        // Old rows, new tail columns.
        let cols = Mat::from_fn(n, t, |i, k| self.p[(i, order[k])]);
        let old_row = |i: usize| if i < start { i } else { order[i - start] };
        for k in 0..t {
            for i in 0..n {
                self.p[(i, start + k)] = cols[(old_row(i), k)];
            }
            for j in 0..start {
                self.p[(start + k, j)] = cols[(j, k)];
            }
        }
        let xt: Vec<f64> = order.iter().map(|&i| self.x[i]).collect();
        for (k, v) in xt.into_iter().enumerate() {
            self.x[start + k] = v;
        }
    }

    /// Removes a non-vehicle block from the layout, x and P (later blocks move up): O(n · tail).
    pub(super) fn remove_block(&mut self, kind: SlotKind) -> bool {
        let n = self.dim();
        let Some(slot) = self.layout.remove(kind) else {
            return false;
        };
        let (off, k) = (slot.offset, kind.dim());
        for j in off + k..n {
            for i in 0..n {
                self.p[(i, j - k)] = self.p[(i, j)];
            }
        }
        for j in 0..n - k {
            for i in off + k..n {
                self.p[(i - k, j)] = self.p[(i, j)];
            }
        }
        for i in off + k..n {
            self.x[i - k] = self.x[i];
        }
        self.truncate_to(n - k);
        true
    }

    /// Applies the associated observations: one stacked update; if that fails numerically, one
    /// update per observation, rejecting the ones that fail.
    pub(super) fn apply_updates(
        &mut self,
        vehicle: usize,
        model: &ObservationModel,
        items: &[UpdateItem],
        report: &mut FrameReport,
    ) {
        if items.is_empty() {
            return;
        }
        let all: Vec<&UpdateItem> = items.iter().collect();
        if self.observation_update(vehicle, model, &all).is_ok() {
            return;
        }
        for it in items {
            if self.observation_update(vehicle, model, &[it]).is_err() {
                report.outcomes[it.obs] =
                    ObservationOutcome::Rejected(RejectReason::NumericalFailure);
            }
        }
    }

    /// Grows x and P by `k` states (zero-filled), keeping capacity to amortize later growth.
    pub(super) fn grow(&mut self, k: usize) {
        let new_n = self.dim() + k;
        self.reserve_states(k);
        self.p.resize_with(new_n, new_n, |_, _| 0.0);
        self.x.resize_with(new_n, |_| 0.0);
    }

    /// Makes room in P for `k` more states without changing it (the re-allocation, when
    /// needed, copies P: a caller about to form large temporaries does it first, so that the
    /// old and the new P are not alive beside them).
    pub(super) fn reserve_states(&mut self, k: usize) {
        let new_n = self.dim() + k;
        // Geometric (×1.5) capacity growth keeps repeated augmentation amortized O(n²) in total
        // copying while bounding the unused memory to ≈ 2.25× of P at worst (only the part in
        // use is ever written, so the rest is never made resident).
        if new_n > self.capacity {
            self.capacity = new_n.max(self.capacity + self.capacity / 2);
            self.p.reserve(self.capacity, self.capacity);
        }
    }

    /// Shrinks x and P back to `n` states (rollback of a failed augmentation).
    pub(super) fn truncate_to(&mut self, n: usize) {
        self.p.truncate(n, n);
        self.x.truncate(n);
    }

    /// Feature initialization (eqs. 21.48–21.54) from a range-bearing measurement of `vehicle`:
    /// m = J_1(x, z), P_m· = ∇J_x P_x·, P_mm = ∇J_x P_xx ∇J_xᵀ + ∇J_z R ∇J_zᵀ. ∇J_x is non-zero
    /// only on the vehicle's p and Ψ, so this is O(n).
    pub(super) fn initialize_feature(
        &mut self,
        vehicle: usize,
        model: &ObservationModel,
        z: &DVector<f64>,
        descriptor: FeatureId,
    ) -> Result<FeatureId, SlamError> {
        let voff = self.layout.vehicle_block(vehicle);
        let state = self.vehicle_state(vehicle)?;
        let pose = model.sensor_pose(&state.position, &state.attitude);
        let init = model
            .initialize(&pose, z)
            .map_err(|source| SlamError::Observation { index: 0, source })?;
        let n = self.dim();
        let jp = Mat::from_fn(3, 3, |i, j| init.d_position[(i, j)]);
        let ja = Mat::from_fn(3, 3, |i, j| init.d_attitude[(i, j)]);
        let mut cross = Mat::zeros(3, n);
        matmul(
            cross.as_mut(),
            Accum::Add,
            jp.as_ref(),
            self.p.as_ref().submatrix(voff + POS, 0, 3, n),
            1.0,
            Par::Seq,
        );
        matmul(
            cross.as_mut(),
            Accum::Add,
            ja.as_ref(),
            self.p.as_ref().submatrix(voff + ATT, 0, 3, n),
            1.0,
            Par::Seq,
        );
        let r = model.noise_covariance();
        let jz = init.d_measurement;
        let jr = DMatrix::from_fn(3, 3, |i, j| jz[(i, j)])
            * &r
            * DMatrix::from_fn(3, 3, |i, j| jz[(j, i)]);
        let mut pmm = Mat::from_fn(3, 3, |i, j| jr[(i, j)]);
        matmul(
            pmm.as_mut(),
            Accum::Add,
            cross.as_ref().submatrix(0, voff + POS, 3, 3),
            jp.transpose(),
            1.0,
            Par::Seq,
        );
        matmul(
            pmm.as_mut(),
            Accum::Add,
            cross.as_ref().submatrix(0, voff + ATT, 3, 3),
            ja.transpose(),
            1.0,
            Par::Seq,
        );
        let pmm = Mat::from_fn(3, 3, |i, j| 0.5 * (pmm[(i, j)] + pmm[(j, i)]));
        if !all_finite(cross.as_ref())
            || !all_finite(pmm.as_ref())
            || !init.feature.iter().all(|v| v.is_finite())
        {
            return Err(SlamError::NumericalFailure("feature initialization"));
        }
        if pmm.llt(Side::Lower).is_err() {
            return Err(SlamError::NotPositiveDefinite("new feature covariance"));
        }
        let info_next = self.info_after_augment(cross.as_ref(), pmm.as_ref());
        let id = self.new_feature_id(descriptor);
        self.grow(3);
        let off = self.layout.push(SlotKind::Feature(id));
        debug_assert_eq!(off, n);
        for i in 0..3 {
            self.x[off + i] = init.feature[i];
            for c in 0..n {
                self.p[(off + i, c)] = cross[(i, c)];
                self.p[(c, off + i)] = cross[(i, c)];
            }
            for j in 0..3 {
                self.p[(off + i, off + j)] = pmm[(i, j)];
            }
        }
        // Stored poses of bearing-only vehicles (mixed teams) stay behind the features.
        self.settle_poses_last();
        self.store_info(info_next);
        Ok(id)
    }
}
