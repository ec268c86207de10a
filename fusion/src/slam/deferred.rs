//! Deferred fusion: received map information is fused into the filter on another thread while
//! the estimator keeps applying IMU samples, and the predictions made meanwhile are carried
//! over to the fused filter afterwards.
//!
//! Two ways, both here. The vehicle process hands its whole filter to its fusion thread and
//! keeps only [`SlamFilter::vehicle_only`] to predict and report from; when the fused filter
//! comes back it applies the same IMU samples to it again (exactly what one thread doing the
//! fusion at the round time and predicting afterwards computes, at O(1) per sample; no copy
//! of P). [`SlamFilter::carry_predictions`] instead carries the predictions made on a filter
//! over to a fused *copy* of it, to first order:
//!
//! Between two frames the filter changes only by prediction (eqs. 21.46, 21.47), which is
//! linear in the prior: over samples k = 1…m with transitions F_k (linearised along the
//! trajectory the estimator followed) and noise Q_k,
//!
//!   P_vv(t) = Φ P_vv(s) Φᵀ + Σ_k (F_m⋯F_{k+1}) G_k Q_k G_kᵀ (F_m⋯F_{k+1})ᵀ,   Φ = F_m⋯F_1,
//!   P_v·(t) = Φ P_v·(s),   P_··(t) = P_··(s)   (map and stored poses are static),
//!
//! so a change ΔP made to the snapshot at time s (the fusion) reaches time t as Φ ΔP Φᵀ on the
//! vehicle block, Φ ΔP_v· on its cross terms and ΔP itself elsewhere, and a change Δx of the
//! vehicle mean as Φ Δx (the INS error dynamics to first order). [`SlamFilter::vehicle_part`]
//! records the part of the filter that prediction touches (vehicle means and blocks) when the
//! snapshot is taken; the estimator keeps predicting with its own filter (`since`); and
//! [`SlamFilter::carry_predictions`] applies those predictions to the fused snapshot:
//!
//!   x_v = x_v(since) + Φ (x_v(fused) − x_v(before)),
//!   P_vv = P_vv(since) + Φ (P_vv(fused) − P_vv(before)) Φᵀ,
//!   P_v· = Φ P_v·(fused)   (kept lazy: Φ becomes the pending transition, module docs).
//!
//! The covariance is the one sequential processing gives with the transitions F_k of the
//! trajectory actually predicted (the EKF linearises the later samples at the pre-fusion
//! estimate instead of the fused one); the map part is exact. The contract: between
//! `vehicle_part` and `carry_predictions` nothing but [`SlamFilter::predict`] may touch `since`
//! (checked: a frame or fusion changes its map generation), and the snapshot must be a copy of
//! the filter the part was taken from, taken right after it.

use super::{SlamError, SlamFilter, VehicleSlot, bearing, info_cache, triangulation};
use crate::ins::{TransitionJacobian, VehicleCovariance, VehicleVector};
use crate::rotation::wrap_angle;
use crate::state::{ATT, VEHICLE_DIM};

impl SlamFilter {
    /// The vehicles of this filter without its map or stored poses: what
    /// [`SlamFilter::predict`] reads and writes. Flushes the pending transitions first (this
    /// changes only the representation of P), so the part starts with none and this filter's
    /// later pending transition is exactly what it predicts from here on; take the snapshot for
    /// the fusion thread after this call.
    pub fn vehicle_part(&mut self) -> SlamFilter {
        self.flush();
        self.vehicle_only()
    }

    /// The vehicles of this filter (means, 15 × 15 blocks, IMU models) without its map, stored
    /// poses or pending transitions, as a filter of its own that can go on predicting: what
    /// stands in for the whole filter while that is handed to another thread for a fusion
    /// round (the vehicle process reports its estimate from it; the IMU samples it predicts are
    /// then applied again to the fused filter). O(vehicles): the vehicle blocks P_vv are
    /// current without a flush (prediction updates them at once, module `slam` docs).
    pub fn vehicle_only(&self) -> SlamFilter {
        let layout = super::Layout::new(self.vehicles.len());
        let n = layout.dim();
        let mut x = faer::Col::zeros(n);
        let mut p = faer::Mat::zeros(n, n);
        for v in 0..self.vehicles.len() {
            let (from, to) = (self.layout.vehicle_block(v), layout.vehicle_block(v));
            for i in 0..VEHICLE_DIM {
                x[to + i] = self.x[from + i];
                for j in 0..VEHICLE_DIM {
                    p[(to + i, to + j)] = self.p[(from + i, from + j)];
                }
            }
        }
        SlamFilter {
            config: self.config,
            mechanization: self.mechanization,
            vehicles: self
                .vehicles
                .iter()
                .map(|s| VehicleSlot {
                    pending: TransitionJacobian::identity(),
                    has_pending: false,
                    ..s.clone()
                })
                .collect(),
            layout,
            x,
            p,
            next_fresh: 0,
            gates: self.gates.clone(),
            // The map it was taken with (`carry_predictions` checks `since` still has it).
            map_generation: self.map_generation,
            info_cache: info_cache::InfoCache::default(),
            capacity: n,
            bearing: bearing::BearingState::new(triangulation::PoseFrame::new(
                self.config.frame,
                &self.config.origin,
            )),
            appearance: Default::default(),
        }
    }

    /// Whether this filter is a [`vehicle_part`](Self::vehicle_part) (no map, no stored poses).
    pub fn is_vehicle_part(&self) -> bool {
        self.dim() == VEHICLE_DIM * self.vehicles.len()
    }

    /// Carries the predictions made on `since` over to `self` (module docs). `before` is the
    /// [`vehicle_part`](Self::vehicle_part) taken from `since` when the snapshot was; `since`
    /// has only been predicted since (it may be that filter or a clone of `before`); `self` is
    /// the snapshot, changed by fusion. On an error (the contract broken, or a non-finite
    /// result) `self` is unchanged.
    pub fn carry_predictions(
        &mut self,
        before: &SlamFilter,
        since: &SlamFilter,
    ) -> Result<(), SlamError> {
        let m = self.vehicles.len();
        if !before.is_vehicle_part()
            || before.vehicles.len() != m
            || since.vehicles.len() != m
            || before.vehicles.iter().any(|s| s.has_pending)
            || since.map_generation != before.map_generation
        {
            return Err(SlamError::InvalidConfig(
                "carry_predictions needs the vehicle part taken with the snapshot (no pending \
                 transition) and a filter only predicted since"
                    .into(),
            ));
        }
        let block =
            |f: &SlamFilter, v: usize| -> Result<(VehicleVector, VehicleCovariance), SlamError> {
                let off = f.layout.vehicle_block(v);
                Ok((
                    VehicleVector::from_fn(|i, _| f.x[off + i]),
                    f.vehicle_covariance(v)?,
                ))
            };
        let mut out = Vec::with_capacity(m);
        for v in 0..m {
            let (x_fused, p_fused) = block(self, v)?;
            let (x_before, p_before) = block(before, v)?;
            let (x_since, p_since) = block(since, v)?;
            let phi = if since.vehicles[v].has_pending {
                since.vehicles[v].pending
            } else {
                TransitionJacobian::identity()
            };
            let mut dx = x_fused - x_before;
            for a in ATT..ATT + 3 {
                dx[a] = wrap_angle(dx[a]);
            }
            let mut x = x_since + phi * dx;
            x[ATT] = wrap_angle(x[ATT]);
            x[ATT + 2] = wrap_angle(x[ATT + 2]);
            let mut p = p_since + phi * (p_fused - p_before) * phi.transpose();
            p = (p + p.transpose()) * 0.5;
            let pending = phi * self.vehicles[v].pending;
            if !x
                .iter()
                .chain(p.iter())
                .chain(pending.iter())
                .all(|a| a.is_finite())
            {
                return Err(SlamError::NumericalFailure("carrying predictions over"));
            }
            out.push((x, p, pending));
        }
        for (v, (x, p, pending)) in out.into_iter().enumerate() {
            let off = self.layout.vehicle_block(v);
            super::write_vehicle_block(&mut self.x, &mut self.p, off, &x, &p);
            self.vehicles[v].pending = pending;
            self.vehicles[v].has_pending = pending != TransitionJacobian::identity();
        }
        Ok(())
    }
}
