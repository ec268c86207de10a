//! Multi-view delayed initialization of bearing-only features ([`BearingInit::MultiView`]).
//!
//! The chapter (§21.4.2) initializes a feature from the two stored lines of sight with the widest
//! separation (eqs. 21.72–21.77) and applies the track's other stored observations afterwards
//! (eq. 21.78), with range hypotheses (21.79–21.83) gating the track while it waits. On a real
//! camera (features 1–10 m away, slow motion, outlier tracks) two rays at the parallax threshold
//! give a poor linearization point, and hypotheses spaced for one range band gate the wrong
//! things. This module keeps the chapter's structure — stored poses in the state (21.66–21.68),
//! delayed initialization, augmentation with the exact linearized cross-covariances — and uses
//! every stored observation of the track at once:
//!
//! 1. **Triangulation.** Linear least squares of the rays (Σ (I − u uᵀ)) m = Σ (I − u uᵀ) y,
//!    eqs. 21.69/21.70 for y and u), then Gauss–Newton on the measurement residuals of eq. 21.42 /
//!    21.43 with the stored poses held at their estimates. Refused when the widest separation of
//!    two rays is below `min_parallax`, a point lies behind a sensor, or the range leaves
//!    [`min_range`, `max_range`].
//! 2. **Linearized system.** Each stored observation j, whitened by its R_j = L_j L_jᵀ:
//!    L_j⁻¹ (z_j − h_j) = L_j⁻¹ H_{x,j} δx_{pose(j)} + L_j⁻¹ H_{m,j} δm + n_j, n_j ~ N(0, I)
//!    (the stored-pose rows of eq. 21.78). Stacked: r = H_x δx + H_m δm + n.
//! 3. **Split.** With H_m = Q [R₁; 0] (Householder QR, Q orthogonal so Qᵀn stays white):
//!    r₁ = R₁ δm + H₁ δx + n₁ (3 rows) and r₂ = H₂ δx + n₂ (2k − 3 rows, free of m).
//! 4. **Joint test.** First, with `marginal_sigma_ratio` below 1, the observation with the
//!    largest residual at the triangulated point is removed while that residual exceeds the χ²
//!    gate at `new_feature_probability` in units of its own (marginal) σ: a test against σ'
//!    has no power against a track that jumped or drifted by several σ (`BearingConfig`).
//!    Then γ = r₂ᵀ (H₂ P H₂ᵀ + I)⁻¹ r₂ against χ²(2k − 3) at `gate_probability`
//!    (eq. 21.55 for the whole track). On failure the observation with the largest whitened
//!    residual is removed and the track is tried again while it keeps `min_observations`
//!    (2 for a constraint update).
//! 5. **Initialization** (a track observed in the current frame with ≥ `min_observations`):
//!    m = m̂ + R₁⁻¹ r₁ − R₁⁻¹ H₁ δx − R₁⁻¹ n₁, augmented like eq. 21.76 with ∇G_x = −R₁⁻¹ H₁ and
//!    noise R₁⁻¹ R₁⁻ᵀ; then the EKF update (21.56–21.60) with (r₂, H₂, I). n₁ and n₂ are
//!    independent, so the two steps together are the joint update of all k observations.
//! 6. **Constraint update** (a track lost from view, or holding the oldest stored pose when the
//!    cap is reached, before it could initialize): the update with (r₂, H₂, I) alone — the
//!    multi-state constraint of Mourikis & Roumeliotis (2007). The feature never enters the
//!    state. A restarted track continues with the next observation of its descriptor.
//!
//! 7. **Linearization bound** (before the current pose is stored): a track whose first stored
//!    pose has a relative attitude σ to the current pose beyond √(2 σ_θ) — σ_θ one ray's own
//!    angular σ, so that the projection's second-order term δ²/2 stays below the ray's noise —
//!    is finished now like a track holding the oldest pose at the cap (initialized if it can,
//!    else a constraint update) and restarts. In a filter whose attitude is known to a fraction
//!    of a degree (σ_θ = 1 px / 458 px: bound 3.8°) this never triggers; after a start with an
//!    unknown gyro bias it keeps the rays from waiting until the attitude has drifted by many
//!    degrees (`tracks_finished_linearization`).
//!
//! Association to tracks is by descriptor (the tracker's ids); an observation of a feature
//! already in the map is associated and gated before this step like any other (§21.3.4).

use super::bearing::{StoredObservation, Track};
use super::triangulation::{PoseFrame, predict_from_pose, separation_angle};
use super::update::HBlock;
use super::{
    AssociationMode, FrameReport, ObservationOutcome, PoseId, RejectReason, SlamError, SlamFilter,
    SlotKind,
};
use crate::consistency::chi2_quantile;
use crate::observation::ObservationModel;
use crate::sensor::FeatureId;
use crate::state::POSE_DIM;
use faer::{Col, Mat};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use std::collections::{BTreeMap, HashMap, HashSet};

/// Gauss–Newton iterations of the triangulation (converges in 3–5 from the linear solution).
const GN_ITERATIONS: usize = 10;

/// The stacked, whitened and split linear system of one track (module docs, steps 2–3).
pub(super) struct TrackSystem {
    /// Triangulated feature (filter frame).
    pub(super) feature: Vector3<f64>,
    /// Stored poses in the system's column order.
    poses: Vec<PoseId>,
    /// R₁ (3×3, upper triangular).
    r1: Matrix3<f64>,
    /// H₁ (3 × 6·poses).
    h1: DMatrix<f64>,
    /// r₁.
    res1: Vector3<f64>,
    /// H₂ ((m − 3) × 6·poses).
    h2: DMatrix<f64>,
    /// r₂.
    res2: DVector<f64>,
    /// Whitened residual norm² of each observation at the triangulated point.
    residuals: Vec<f64>,
}

/// Why a track's system could not be formed.
pub(super) enum SystemError {
    /// Too little parallax, behind a sensor, range outside the configured band, or no
    /// convergence: the geometry does not determine the feature.
    Geometry,
    /// A stored pose is missing or a matrix is not finite.
    Numerical,
}

impl SlamFilter {
    /// The multi-view pipeline for the observations `pending` (indices into `zs`) that the
    /// association against initialized features left over (module docs).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn process_multiview_observations(
        &mut self,
        vehicle: usize,
        _model: &ObservationModel,
        time: f64,
        zs: &[DVector<f64>],
        descriptors: &[FeatureId],
        pending: &[usize],
        report: &mut FrameReport,
    ) {
        let Ok(frame) = self.pose_frame() else {
            return;
        };
        if !matches!(
            self.config.association.mode,
            AssociationMode::Descriptor | AssociationMode::Appearance { .. }
        ) {
            // `set_bearing_config` refuses this combination; keep the filter unchanged.
            for &i in pending {
                report.outcomes[i] = ObservationOutcome::Rejected(RejectReason::NotInitializable);
            }
            return;
        }
        self.prune_tracks(time);
        let by_descriptor: HashMap<FeatureId, usize> = self
            .bearing
            .tracks
            .iter()
            .enumerate()
            .map(|(k, t)| (t.descriptor, k))
            .collect();
        let mut continuing: HashMap<usize, usize> = HashMap::new(); // track index → observation
        let mut new_tracks = Vec::new();
        let mut seen = HashSet::new();
        for &i in pending {
            if !seen.insert(descriptors[i]) {
                // One descriptor twice in a frame: neither can be trusted.
                report.outcomes[i] = ObservationOutcome::Rejected(RejectReason::Ambiguous);
                continue;
            }
            match by_descriptor.get(&descriptors[i]) {
                Some(&k) => {
                    continuing.insert(k, i);
                }
                None => new_tracks.push(i),
            }
        }
        // Tracks of this vehicle not seen in this frame are finished: constraint update.
        let lost: Vec<u64> = self
            .bearing
            .tracks
            .iter()
            .enumerate()
            .filter(|(k, t)| {
                !continuing.contains_key(k)
                    && t.observations.first().is_some_and(|o| o.vehicle == vehicle)
            })
            .map(|(_, t)| t.id)
            .collect();
        let continuing: BTreeMap<u64, usize> = continuing
            .into_iter()
            .map(|(k, i)| (self.bearing.tracks[k].id, i))
            .collect();
        for id in lost {
            self.finish_track(&frame, id, false);
        }
        if continuing.is_empty() && new_tracks.is_empty() {
            self.remove_unreferenced_poses();
            return;
        }
        // Linearization bound: a track whose rays would be linearized across too uncertain a
        // relative attitude is used now (initialized or a constraint update) and restarts.
        for id in self.tracks_past_linearization_bound(vehicle) {
            self.finish_track(&frame, id, true);
            self.bearing.stats.tracks_finished_linearization += 1;
        }
        // Keep the stored poses under the cap: the tracks holding the oldest pose are finished
        // (initialized if they can, else a constraint update) and restart empty.
        while self.bearing.poses.len() >= self.bearing.config.max_stored_poses {
            let Some(&oldest) = self.bearing.poses.keys().next() else {
                break;
            };
            let holders: Vec<u64> = self
                .bearing
                .tracks
                .iter()
                .filter(|t| t.observations.iter().any(|o| o.pose == oldest))
                .map(|t| t.id)
                .collect();
            for id in holders {
                self.finish_track(&frame, id, true);
                self.bearing.stats.tracks_dropped_capacity += 1;
            }
            self.remove_unreferenced_poses();
            if self.bearing.poses.contains_key(&oldest) {
                break; // referenced by something else: cannot free (not expected)
            }
        }
        let stored = self.store_current_pose(vehicle, &[]);
        let Ok(Some(pose)) = stored else {
            let reason = match stored {
                Ok(_) => RejectReason::PoseCapacity,
                Err(_) => RejectReason::NumericalFailure,
            };
            for &i in continuing.values().chain(&new_tracks) {
                report.outcomes[i] = ObservationOutcome::Rejected(reason);
            }
            self.remove_unreferenced_poses();
            return;
        };
        let observation = |i: usize| StoredObservation {
            pose,
            vehicle,
            z: zs[i].clone(),
        };
        let mut grown = Vec::new();
        for (&id, &i) in &continuing {
            let Some(track) = self.bearing.tracks.iter_mut().find(|t| t.id == id) else {
                // Finished and dropped above (its restarted remainder was empty): start again.
                new_tracks.push(i);
                continue;
            };
            track.observations.push(observation(i));
            if track.observations.len() == 1 {
                track.anchor = track.observations[0].clone();
            }
            self.bearing.poses.get_mut(&pose).expect("just stored").refs += 1;
            self.bearing.stats.observations_stored += 1;
            report.outcomes[i] = ObservationOutcome::Stored { track: id };
            grown.push((id, i));
        }
        for &i in &new_tracks {
            let id = self.bearing.next_track;
            self.bearing.next_track += 1;
            self.bearing
                .tracks
                .push(Track::plain(id, descriptors[i], time, observation(i)));
            self.bearing.poses.get_mut(&pose).expect("just stored").refs += 1;
            self.bearing.stats.tracks_started += 1;
            self.bearing.stats.observations_stored += 1;
            report.outcomes[i] = ObservationOutcome::Stored { track: id };
        }
        // Initialize the tracks that gained an observation, when they can.
        let cfg = self.bearing.config;
        for (id, i) in grown {
            let Some(k) = self.bearing.tracks.iter().position(|t| t.id == id) else {
                continue;
            };
            let n = self.bearing.tracks[k].observations.len();
            if n < cfg.min_observations {
                continue;
            }
            match self.initialize_track(&frame, id) {
                Ok(Some(feature)) => {
                    report.outcomes[i] = ObservationOutcome::Initialized { feature };
                    report.initialized_tracks.push((id, feature));
                }
                Ok(None) => {
                    if n >= cfg.max_track_observations {
                        self.finish_track(&frame, id, false);
                        self.bearing.stats.tracks_dropped_observations += 1;
                    }
                }
                Err(_) => {
                    self.finish_track(&frame, id, false);
                    report.outcomes[i] =
                        ObservationOutcome::Rejected(RejectReason::NumericalFailure);
                }
            }
        }
        self.remove_unreferenced_poses();
    }

    /// Tracks of `vehicle` (in state order) whose first stored pose's attitude, relative to
    /// the vehicle's current attitude, has a σ (√ of the largest eigenvalue of the 3×3
    /// covariance of Ψ_now − Ψ_first, from the joint P) beyond √(2 σ_θ), σ_θ the angular σ of
    /// one ray (the sensor's σ × `marginal_sigma_ratio`, over the focal length for pixels). The
    /// projection's second-order term under an attitude error δ is ≈ δ²/2 in angle, so past
    /// this bound the EKF's linearization error of the track's rays is larger than their
    /// noise (module docs, step 7).
    pub(super) fn tracks_past_linearization_bound(&self, vehicle: usize) -> Vec<u64> {
        let model = &self.vehicles[vehicle].model;
        let r = model.noise_covariance();
        let sigma = r.diagonal().iter().copied().fold(0.0, f64::max).sqrt()
            * self.bearing.config.marginal_sigma_ratio;
        let sigma_theta = match model.sensor {
            crate::sensor::SensorModel::Pixel { camera, .. } => sigma / camera.fu.max(camera.fv),
            _ => sigma,
        };
        // σ_rel² ≤ 2 σ_θ.
        let variance_bound = 2.0 * sigma_theta;
        let voff = self.layout.vehicle_block(vehicle) + crate::state::ATT;
        self.bearing
            .tracks
            .iter()
            .filter(|t| t.observations.first().is_some_and(|o| o.vehicle == vehicle))
            .filter_map(|t| {
                let off = self.layout.pose_offset(t.observations[0].pose)? + crate::state::POSE_ATT;
                let rel = Matrix3::from_fn(|i, j| {
                    self.p[(voff + i, voff + j)] + self.p[(off + i, off + j)]
                        - self.p[(voff + i, off + j)]
                        - self.p[(off + i, voff + j)]
                });
                let largest = rel.symmetric_eigenvalues().max();
                (largest > variance_bound).then_some(t.id)
            })
            .collect()
    }

    /// Tries to initialize track `id` as a feature (module docs, steps 1–5). `Ok(None)`: not yet
    /// (too little parallax) or refused (then the refused observations were removed).
    pub(super) fn initialize_track(
        &mut self,
        frame: &PoseFrame,
        id: u64,
    ) -> Result<Option<FeatureId>, SlamError> {
        let min_obs = self.bearing.config.min_observations;
        let min_parallax = self.bearing.config.min_parallax;
        let Some(system) = self.tested_system(frame, id, min_obs, min_parallax) else {
            return Ok(None);
        };
        let k = self
            .bearing
            .tracks
            .iter()
            .position(|t| t.id == id)
            .ok_or(SlamError::NumericalFailure("track"))?;
        // Step 5: augmentation with ∇G_x = −R₁⁻¹ H₁, noise R₁⁻¹ R₁⁻ᵀ.
        let r1_inv = system
            .r1
            .try_inverse()
            .ok_or(SlamError::NumericalFailure("track R1"))?;
        let mean = system.feature + r1_inv * system.res1;
        let g = -r1_inv * &system.h1;
        let mut jacobians = Vec::with_capacity(system.poses.len());
        for (c, pid) in system.poses.iter().enumerate() {
            let off = self
                .layout
                .pose_offset(*pid)
                .ok_or(SlamError::NumericalFailure("stored pose slot"))?;
            jacobians.push((
                off,
                Mat::from_fn(3, POSE_DIM, |i, j| g[(i, c * POSE_DIM + j)]),
            ));
        }
        let noise = r1_inv * r1_inv.transpose();
        let noise = Mat::from_fn(3, 3, |i, j| noise[(i, j)]);
        let feature_id = self.new_feature_id(self.bearing.tracks[k].descriptor);
        self.map_generation += 1;
        self.augment_linear(
            SlotKind::Feature(feature_id),
            mean.as_slice(),
            &jacobians,
            &noise,
            true,
        )?;
        // The null-space part: offsets re-read (the augmentation permuted the pose tail).
        if self.null_space_update(&system).is_err() {
            // The feature stands on the invertible part alone: still consistent (less used).
            self.bearing.stats.recovery_rejected += 1;
        }
        let track = self.bearing.tracks.remove(k);
        self.bearing.stats.features_initialized += 1;
        self.bearing.stats.observations_recovered += track.observations.len() as u64;
        self.release(&track.observations);
        Ok(Some(feature_id))
    }

    /// Ends track `id` and drops it (the descriptor's next observation starts a new track).
    /// With `may_initialize` (a track still in view whose oldest pose must go) it becomes a
    /// feature when it can; otherwise — and always for a lost track, whose feature this tracker
    /// id will not see again — its observations constrain the stored poses (step 6).
    pub(super) fn finish_track(&mut self, frame: &PoseFrame, id: u64, may_initialize: bool) {
        let Some(k) = self.bearing.tracks.iter().position(|t| t.id == id) else {
            return;
        };
        let n = self.bearing.tracks[k].observations.len();
        if may_initialize
            && n >= self.bearing.config.min_observations
            && matches!(self.initialize_track(frame, id), Ok(Some(_)))
        {
            return;
        }
        if n >= 2
            && let Some(system) =
                self.tested_system(frame, id, 2, self.bearing.config.constraint_parallax)
        {
            let used = system.residuals.len() as u64;
            if self.null_space_update(&system).is_ok() {
                self.bearing.stats.constraint_updates += 1;
                self.bearing.stats.constraint_observations += used;
            }
        }
        if let Some(k) = self.bearing.tracks.iter().position(|t| t.id == id) {
            self.drop_track(k);
        }
    }

    /// The track's system after the joint χ² test with outlier removal (module docs, step 4);
    /// `None` when the geometry does not determine the feature yet or the track was refused
    /// (then its refused observations are gone).
    fn tested_system(
        &mut self,
        frame: &PoseFrame,
        id: u64,
        min_obs: usize,
        min_parallax: f64,
    ) -> Option<TrackSystem> {
        loop {
            let k = self.bearing.tracks.iter().position(|t| t.id == id)?;
            let obs = self.bearing.tracks[k].observations.clone();
            if obs.len() < min_obs.max(2) {
                return None;
            }
            let system = match self.track_system(frame, &obs, min_parallax) {
                Ok(s) => s,
                Err(SystemError::Geometry) => return None,
                Err(SystemError::Numerical) => {
                    self.bearing.stats.tracks_rejected += 1;
                    self.drop_track(k);
                    return None;
                }
            };
            // Gross outliers first: a residual at the triangulated point beyond the gate at
            // `new_feature_probability` of the observation's own (marginal) error
            // (`BearingConfig::marginal_sigma_ratio`; none when the ratio is 1).
            let ratio = self.bearing.config.marginal_sigma_ratio;
            let outlier = (ratio < 1.0)
                .then(|| {
                    let (worst, r2) = system
                        .residuals
                        .iter()
                        .enumerate()
                        .max_by(|a, b| a.1.total_cmp(b.1))?;
                    let dof = self.stored_model(&obs[worst]).measurement_dim() as f64;
                    let gate = chi2_quantile(dof, self.config.association.new_feature_probability)
                        .unwrap_or(f64::INFINITY);
                    (r2 / (ratio * ratio) > gate).then_some(worst)
                })
                .flatten();
            if let Some(worst) = outlier {
                self.remove_outlier(k, worst, obs.len(), min_obs)?;
                continue;
            }
            let dof = system.res2.len();
            let Some(gamma) = self.null_space_nis(&system) else {
                self.bearing.stats.tracks_rejected += 1;
                self.drop_track(k);
                return None;
            };
            let threshold = chi2_quantile(dof as f64, self.config.association.gate_probability)
                .unwrap_or(f64::INFINITY);
            if gamma <= threshold {
                return Some(system);
            }
            // Remove the worst observation and try again while enough remain.
            let worst = system
                .residuals
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map(|(j, _)| j)?;
            self.remove_outlier(k, worst, obs.len(), min_obs)?;
        }
    }

    /// Removes observation `worst` of track `k` (of `n` observations), or refuses and drops
    /// the whole track when fewer than `min_obs` (at least 2) would remain: `None` then.
    fn remove_outlier(&mut self, k: usize, worst: usize, n: usize, min_obs: usize) -> Option<()> {
        if n - 1 < min_obs.max(2) {
            self.bearing.stats.tracks_rejected += 1;
            self.drop_track(k);
            return None;
        }
        let removed = self.bearing.tracks[k].observations.remove(worst);
        self.release(std::slice::from_ref(&removed));
        self.bearing.stats.outliers_removed += 1;
        Some(())
    }

    /// Steps 1–3 for the stored observations `obs`.
    pub(super) fn track_system(
        &self,
        frame: &PoseFrame,
        obs: &[StoredObservation],
        min_parallax: f64,
    ) -> Result<TrackSystem, SystemError> {
        let cfg = self.bearing.config;
        // Rays (eqs. 21.69, 21.70) in the filter frame, relative to the first sensor origin.
        let mut rays = Vec::with_capacity(obs.len());
        for o in obs {
            let (p, att) = self.stored_pose(o.pose).ok_or(SystemError::Numerical)?;
            let model = self.stored_model(o);
            let pose = model.sensor_pose(&frame.to_filter(&p), &att);
            let (dir, _) = model
                .sensor_direction(&o.z)
                .map_err(|_| SystemError::Numerical)?;
            let los = pose.line_of_sight(&dir);
            rays.push((los.origin, los.direction.normalize()));
        }
        let mut parallax: f64 = 0.0;
        for a in 0..rays.len() {
            for b in a + 1..rays.len() {
                parallax = parallax.max(separation_angle(&rays[a].1, &rays[b].1));
            }
        }
        if parallax < min_parallax {
            return Err(SystemError::Geometry);
        }
        let base = rays[0].0;
        let mut a = Matrix3::zeros();
        let mut b = Vector3::zeros();
        for (y, u) in &rays {
            let proj = Matrix3::identity() - u * u.transpose();
            a += proj;
            b += proj * (y - base);
        }
        let mut feature = base + a.lu().solve(&b).ok_or(SystemError::Geometry)?;
        // Gauss–Newton on the measurement residuals, poses fixed.
        for _ in 0..GN_ITERATIONS {
            let mut info = Matrix3::zeros();
            let mut grad = Vector3::zeros();
            for o in obs {
                let (p, att) = self.stored_pose(o.pose).ok_or(SystemError::Numerical)?;
                let model = self.stored_model(o);
                let pred = predict_from_pose(frame, &model, &p, &att, &feature)
                    .map_err(|_| SystemError::Geometry)?;
                let r_inv = model
                    .noise_covariance()
                    .try_inverse()
                    .ok_or(SystemError::Numerical)?;
                let nu = model.innovation(&o.z, &pred.z);
                let hm = &pred.d_feature;
                let ht_rinv = hm.transpose() * &r_inv;
                info += &ht_rinv * hm;
                grad += &ht_rinv * nu;
            }
            let step = info.cholesky().ok_or(SystemError::Geometry)?.solve(&grad);
            feature += step;
            if !feature.iter().all(|v| v.is_finite()) {
                return Err(SystemError::Geometry);
            }
            if step.norm() < 1e-9 * (1.0 + (feature - base).norm()) {
                break;
            }
        }
        for (y, _) in &rays {
            let range = (feature - y).norm();
            if !(range >= cfg.min_range && range <= cfg.max_range) {
                return Err(SystemError::Geometry);
            }
        }
        // Step 2: whitened rows.
        let mut columns: Vec<PoseId> = Vec::new();
        let mut column_of: HashMap<PoseId, usize> = HashMap::new();
        for o in obs {
            column_of.entry(o.pose).or_insert_with(|| {
                columns.push(o.pose);
                columns.len() - 1
            });
        }
        let rows: usize = obs
            .iter()
            .map(|o| self.stored_model(o).measurement_dim())
            .sum();
        let cols = POSE_DIM * columns.len();
        let mut hm_all = DMatrix::zeros(rows, 3);
        let mut rest = DMatrix::zeros(rows, cols + 1);
        let mut residuals = Vec::with_capacity(obs.len());
        let mut row = 0;
        for o in obs {
            let (p, att) = self.stored_pose(o.pose).ok_or(SystemError::Numerical)?;
            let model = self.stored_model(o);
            let pred = predict_from_pose(frame, &model, &p, &att, &feature)
                .map_err(|_| SystemError::Geometry)?;
            let d = pred.z.len();
            let chol = model
                .noise_covariance()
                .cholesky()
                .ok_or(SystemError::Numerical)?;
            let l_inv = chol.l().try_inverse().ok_or(SystemError::Numerical)?;
            let nu = &l_inv * model.innovation(&o.z, &pred.z);
            residuals.push(nu.norm_squared());
            let hm = &l_inv * &pred.d_feature;
            let hp = &l_inv * &pred.d_position;
            let ha = &l_inv * &pred.d_attitude;
            let c = column_of[&o.pose] * POSE_DIM;
            for i in 0..d {
                for j in 0..3 {
                    hm_all[(row + i, j)] = hm[(i, j)];
                    rest[(row + i, c + j)] = hp[(i, j)];
                    rest[(row + i, c + 3 + j)] = ha[(i, j)];
                }
                rest[(row + i, cols)] = nu[i];
            }
            row += d;
        }
        if rows < 4 {
            return Err(SystemError::Geometry);
        }
        // Step 3: Qᵀ [H_m | H_x | r].
        let qr = hm_all.qr();
        qr.q_tr_mul(&mut rest);
        let r = qr.r();
        let r1 = Matrix3::from_fn(|i, j| r[(i, j)]);
        let scale = r1.diagonal().abs().max();
        if !(r1.diagonal().iter().all(|v| v.abs() > 1e-9 * scale) && scale.is_finite()) {
            return Err(SystemError::Geometry);
        }
        let h1 = rest.view((0, 0), (3, cols)).into_owned();
        let res1 = Vector3::new(rest[(0, cols)], rest[(1, cols)], rest[(2, cols)]);
        let h2 = rest.view((3, 0), (rows - 3, cols)).into_owned();
        let res2 = rest.view((3, cols), (rows - 3, 1)).column(0).into_owned();
        if !(h1.iter().chain(h2.iter()).all(|v| v.is_finite())
            && res2.iter().all(|v| v.is_finite()))
        {
            return Err(SystemError::Numerical);
        }
        Ok(TrackSystem {
            feature,
            poses: columns,
            r1,
            h1,
            res1,
            h2,
            res2,
            residuals,
        })
    }

    /// Covariance of the system's stored poses (6·poses square) from P.
    fn pose_block_covariance(&self, poses: &[PoseId]) -> Option<DMatrix<f64>> {
        let offs: Vec<usize> = poses
            .iter()
            .map(|p| self.layout.pose_offset(*p))
            .collect::<Option<_>>()?;
        let n = POSE_DIM * offs.len();
        Some(DMatrix::from_fn(n, n, |i, j| {
            self.p[(
                offs[i / POSE_DIM] + i % POSE_DIM,
                offs[j / POSE_DIM] + j % POSE_DIM,
            )]
        }))
    }

    /// γ = r₂ᵀ (H₂ P H₂ᵀ + I)⁻¹ r₂ (step 4); `None` on a numerical failure.
    fn null_space_nis(&self, s: &TrackSystem) -> Option<f64> {
        let p = self.pose_block_covariance(&s.poses)?;
        let cov = &s.h2 * p * s.h2.transpose() + DMatrix::identity(s.h2.nrows(), s.h2.nrows());
        let chol = cov.cholesky()?;
        let g = s.res2.dot(&chol.solve(&s.res2));
        g.is_finite().then_some(g)
    }

    /// The EKF update with (r₂, H₂, I) through the stored poses (steps 5, 6).
    fn null_space_update(&mut self, s: &TrackSystem) -> Result<(), SlamError> {
        let m = s.res2.len();
        let mut blocks = Vec::with_capacity(s.poses.len());
        for (c, pid) in s.poses.iter().enumerate() {
            let off = self
                .layout
                .pose_offset(*pid)
                .ok_or(SlamError::NumericalFailure("stored pose slot"))?;
            blocks.push(HBlock {
                row: 0,
                col: off,
                mat: Mat::from_fn(m, POSE_DIM, |i, j| s.h2[(i, c * POSE_DIM + j)]),
            });
        }
        let nu = Col::from_fn(m, |i| s.res2[i]);
        self.map_generation += 1;
        self.blocks_update(&blocks, &nu, Mat::identity(m, m))
    }
}
