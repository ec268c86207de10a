//! Bearing-only inertial SLAM (§21.4): stored poses, delayed initialization, recovery of stored
//! observations and multi-hypothesis association of uninitialized features.
//!
//! # Pipeline (per frame of a bearing or pixel vehicle, after the update of initialized features)
//! 1. *Housekeeping*: tracks older than `max_track_age` are dropped; in descriptor mode a track
//!    whose descriptor has meanwhile become a map feature (fused from a neighbour, or
//!    initialized by another vehicle of a centralized filter) has its stored observations
//!    recovered onto that feature (gated batch update, eq. 21.78) and is closed.
//! 2. *Association to uninitialized tracks* (21.4.3.2/21.4.3.3): every observation left over by
//!    the association against initialized features is gated (χ² at `gate_probability`, 5.991 for
//!    2 dof at 95 %) against every hypothesis of every track, with ν of eq. 21.81 and S of
//!    eq. 21.82. S uses either P_hyp of eq. 21.83 (current p, Ψ and hypothesis assumed
//!    uncorrelated, [`TrackGate::Chapter`]) or, by default, the exact linearized joint
//!    covariance of the current pose and the track's first stored pose, off which the
//!    hypotheses hang ([`TrackGate::Correlated`]; `docs/arch/bearing.md` has the measured
//!    difference). Descriptor mode gates only the track with the observation's descriptor (a
//!    failed gate rejects); the gating modes match an observation to a track when at least one
//!    hypothesis passes, reject an observation that matches several tracks (`Ambiguous`), and
//!    give a track matched by several observations of one frame the lowest γ. Non-matching
//!    hypotheses of a matched track are culled.
//! 3. *Storing* (21.4.2.1): the current vehicle pose is added to the state once per frame
//!    (eqs. 21.66–21.68; shared by all observations stored in the frame, so a frame adds at most
//!    one 6-state block) and every matched or new observation is stored outside the state with
//!    a reference to it. A new track gets `hypotheses` hypotheses at equally spaced ranges in
//!    [min_range, max_range] along the line of sight (eqs. 21.79, 21.80; the range itself gets
//!    a σ of half the spacing, so neighbouring hypotheses overlap and cover the segment).
//! 4. *Initialization* (21.4.2.2/21.4.2.3): a track initializes once the largest separation
//!    angle of any two of its stored lines of sight reaches `min_parallax`; that pair is
//!    triangulated (eqs. 21.69–21.74) and the state augmented with ∇G_p, ∇G_z (21.75–21.77).
//!    Lines missing each other by more than max(`max_miss_distance`, 3 σ_miss) — σ_miss the
//!    miss's predicted σ from the two stored poses' joint covariance and R, so that drift
//!    between poses long apart does not reject correct pairs — or meeting behind a sensor,
//!    discard the pair's observations (counted) and the track goes on.
//! 5. *Recovery* (21.4.2.4): the track's remaining stored observations are applied in one
//!    stacked EKF update (eq. 21.78) through their stored poses; an observation failing its
//!    individual gate against the new feature is discarded (counted). In global SLAM the feature
//!    was triangulated in n0 and transformed to ECEF before augmentation (module
//!    [`super::triangulation`]), so the update runs in the filter frame.
//! 6. *Bounding*: stored poses without stored observations are removed (x and P shrink); tracks
//!    with `max_track_observations` stored observations that still cannot initialize are
//!    dropped; before a pose is added at `max_stored_poses`, the oldest tracks not matched in the
//!    frame are dropped until one frees a pose (all counted in [`BearingStats`]).

use super::triangulation::{
    PoseFrame, PosedObservation, TriangulationError, initialize_from_pair, predict_from_pose,
};
use super::update::HBlock;
use super::{
    AssociationMode, FrameReport, ObservationOutcome, PoseId, RejectReason, SlamError, SlamFilter,
    SlotKind,
};
use crate::observation::ObservationModel;
use crate::sensor::FeatureId;
use crate::state::{ATT, POS, POSE_ATT, POSE_DIM, POSE_POS};
use faer::{Col, Mat};
use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, Vector3};
use std::collections::{BTreeMap, HashMap};

/// Id of an uninitialized feature track (filter-local, never reused).
pub type TrackId = u64;

type Mat6 = SMatrix<f64, 6, 6>;

/// How an observation is gated against a track's hypotheses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackGate {
    /// Eq. 21.83 as printed: P_hyp = diag(P_pp, P_j), the current pose and the hypothesis
    /// (frozen at the track's first observation) assumed uncorrelated. Both carry the absolute
    /// pose uncertainty, so the gate is wide (≈ the absolute position σ over the range).
    Chapter,
    /// The hypotheses as functions of the track's first stored pose, which is in the state: the
    /// means follow that pose's current estimate and S uses the exact linearized joint
    /// covariance of (current pose, stored pose), so only their *relative* uncertainty widens
    /// the gate. Same cost order (one 6×6 cross-covariance block per track).
    Correlated,
}

/// Options of bearing-only SLAM.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BearingConfig {
    /// Minimum separation angle of two stored lines of sight before a feature is initialized
    /// [rad] (21.4.2.2). Default 10°.
    pub min_parallax: f64,
    /// Lines of sight missing each other by more than max(this, 3 σ) are rejected [m], σ the
    /// predicted standard deviation of the miss from the stored poses' covariance and R
    /// (21.4.2.3). Default 5.
    pub max_miss_distance: f64,
    /// Number of range hypotheses of a new track (21.4.3.1). Default 24 (≈ 21 m apart).
    pub hypotheses: usize,
    /// Range of the nearest hypothesis [m]. Default 10 (the default sensor's minimum range).
    pub min_range: f64,
    /// Range of the farthest hypothesis [m]. Default 500 (the default sensor's maximum range).
    pub max_range: f64,
    /// Cap on the number of stored poses in the state. Default 40.
    pub max_stored_poses: usize,
    /// A track not initialized this long after its first observation is dropped [s].
    /// Default 30.
    pub max_track_age: f64,
    /// A track with this many stored observations that still cannot initialize is dropped.
    /// Default 40.
    pub max_track_observations: usize,
    /// Gate of observations against track hypotheses. Default [`TrackGate::Correlated`].
    pub track_gate: TrackGate,
    /// How a track becomes a feature. Default [`BearingInit::Pair`] (the chapter's method).
    pub initialization: BearingInit,
    /// [`BearingInit::MultiView`]: stored observations a track needs before it may initialize.
    /// Default 5.
    pub min_observations: usize,
    /// [`BearingInit::MultiView`]: minimum separation of two rays of a track for its
    /// constraint update (lost tracks) [rad]. Default 1°.
    pub constraint_parallax: f64,
    /// σ of one observation's own error over the sensor's σ (in (0, 1]; default 1). A tracker's
    /// error is correlated along a track, and the sensor's R is then the *equivalent white*
    /// noise σ' > σ that weighs a sequence of such observations correctly
    /// (`docs/arch/import.md`); a test of one observation against its marginal error must use
    /// σ = ratio · σ', or a gross outlier (a track that jumped or drifted onto another point)
    /// passes a gate scaled by σ'. With a ratio below 1: an initialized feature's observation
    /// whose NIS against S = H P Hᵀ + ratio² R exceeds the χ² gate at
    /// `new_feature_probability` is rejected (`GateFailed`) besides the usual gate (21.55), and
    /// [`BearingInit::MultiView`] removes a stored observation whose residual at the
    /// triangulated point exceeds the same gate in units of ratio · σ' before its joint test.
    pub marginal_sigma_ratio: f64,
}

/// How an uninitialized track becomes a map feature.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BearingInit {
    /// §21.4.2 as in the chapter: range hypotheses gate the track's observations; the pair of
    /// stored lines of sight with the widest separation is triangulated (21.72–21.77) and the
    /// other stored observations are applied afterwards (21.78).
    Pair,
    /// Every stored observation of the track at once (module `multiview`): Gauss–Newton
    /// triangulation, then the stacked linearized system is split by a QR decomposition of its
    /// feature columns into an invertible part that initializes the feature and a null-space part
    /// that updates the stored poses, after a joint χ² test of the track. Tracks lost before they
    /// can initialize update the stored poses through their null-space part alone (the
    /// multi-state constraint of Mourikis & Roumeliotis 2007). Needs descriptor association
    /// (tracker ids), which replaces the hypothesis gate.
    MultiView,
}

impl Default for BearingConfig {
    fn default() -> Self {
        Self {
            min_parallax: 10f64.to_radians(),
            max_miss_distance: 5.0,
            hypotheses: 24,
            min_range: 10.0,
            max_range: 500.0,
            max_stored_poses: 40,
            max_track_age: 30.0,
            max_track_observations: 40,
            track_gate: TrackGate::Correlated,
            initialization: BearingInit::Pair,
            min_observations: 5,
            constraint_parallax: 1f64.to_radians(),
            marginal_sigma_ratio: 1.0,
        }
    }
}

impl BearingConfig {
    /// Checks ranges (what [`SlamFilter::set_bearing_config`](super::SlamFilter::set_bearing_config) refuses).
    pub fn validate(&self) -> Result<(), SlamError> {
        let bad = |what: &str| Err(SlamError::InvalidConfig(format!("bearing: {what}")));
        if !(self.min_parallax > 0.0 && self.min_parallax < std::f64::consts::PI) {
            return bad("min_parallax must be in (0, π)");
        }
        if self.max_miss_distance.is_nan() || self.max_miss_distance <= 0.0 {
            return bad("max_miss_distance must be positive");
        }
        if self.hypotheses == 0 {
            return bad("at least one hypothesis");
        }
        if !(self.min_range > 0.0 && self.max_range > self.min_range && self.max_range.is_finite())
        {
            return bad("need 0 < min_range < max_range < ∞");
        }
        if self.max_stored_poses < 2 {
            return bad("max_stored_poses must be at least 2");
        }
        if self.max_track_age.is_nan() || self.max_track_age <= 0.0 {
            return bad("max_track_age must be positive");
        }
        if self.max_track_observations < 2 {
            return bad("max_track_observations must be at least 2");
        }
        if !(self.constraint_parallax > 0.0 && self.constraint_parallax < std::f64::consts::PI) {
            return bad("constraint_parallax must be in (0, π)");
        }
        if self.min_observations < 2 {
            return bad("min_observations must be at least 2");
        }
        if !(self.marginal_sigma_ratio > 0.0 && self.marginal_sigma_ratio <= 1.0) {
            return bad("marginal_sigma_ratio must be in (0, 1]");
        }
        Ok(())
    }
}

/// Counters of the bearing-only pipeline (monotone over the filter's life, except the current
/// sizes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct BearingStats {
    /// Tracks started (new uninitialized features).
    pub tracks_started: u64,
    /// Observations stored with a track.
    pub observations_stored: u64,
    /// Features initialized by triangulation.
    pub features_initialized: u64,
    /// Triangulations rejected (lines missing each other, or meeting behind a sensor).
    pub triangulations_rejected: u64,
    /// Stored observations discarded by rejected triangulations.
    pub observations_discarded: u64,
    /// Stored observations applied by recovery updates (eq. 21.78).
    pub observations_recovered: u64,
    /// Stored observations that failed their gate in a recovery and were discarded.
    pub recovery_rejected: u64,
    /// Tracks dropped to keep the stored poses under the cap.
    pub tracks_dropped_capacity: u64,
    /// Tracks dropped for age.
    pub tracks_dropped_age: u64,
    /// Tracks dropped at the observation limit.
    pub tracks_dropped_observations: u64,
    /// Descriptor-mode tracks whose feature arrived otherwise (fusion, another vehicle) and
    /// whose observations were recovered onto it.
    pub tracks_merged: u64,
    /// Stored poses added.
    pub poses_added: u64,
    /// Stored poses removed.
    pub poses_removed: u64,
    /// Largest number of stored poses held at once.
    pub max_stored_poses: usize,
    /// Multi-view: tracks whose null-space part alone updated the state (lost or restarted
    /// before they could initialize).
    pub constraint_updates: u64,
    /// Multi-view: stored observations used by those updates.
    pub constraint_observations: u64,
    /// Multi-view: tracks (or parts of them) refused by the joint χ² test after the outlier
    /// removal, or whose triangulation failed (too little parallax, behind a camera, out of the
    /// configured range); their observations were discarded.
    pub tracks_rejected: u64,
    /// Multi-view: single observations removed from a track as outliers (largest residual of a
    /// track that failed the joint test).
    pub outliers_removed: u64,
    /// Multi-view: tracks finished early because the relative attitude σ between their first
    /// stored pose and the current pose passed the linearization bound (module `multiview`).
    pub tracks_finished_linearization: u64,
}

/// A read-only view of an uninitialized track.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackInfo {
    /// Track id.
    pub id: TrackId,
    /// Descriptor of its first observation (its feature id in descriptor mode).
    pub descriptor: FeatureId,
    /// Stored observations.
    pub observations: usize,
    /// Ranges of the surviving hypotheses along the first line of sight [m].
    pub hypothesis_ranges: Vec<f64>,
    /// Time of the first observation [s].
    pub created: f64,
}

#[derive(Clone, Debug)]
pub(super) struct StoredPose {
    /// Stored observations referring to it.
    pub(super) refs: usize,
}

#[derive(Clone, Debug)]
pub(super) struct StoredObservation {
    pub(super) pose: PoseId,
    pub(super) vehicle: usize,
    pub(super) z: DVector<f64>,
}

/// One Gaussian hypothesis of a track (eqs. 21.79, 21.80), in the filter frame.
#[derive(Clone, Debug)]
struct Hypothesis {
    range: f64,
    mean: Vector3<f64>,
    covariance: Matrix3<f64>,
}

#[derive(Clone, Debug)]
pub(super) struct Track {
    pub(super) id: TrackId,
    pub(super) descriptor: FeatureId,
    pub(super) created: f64,
    pub(super) observations: Vec<StoredObservation>,
    hypotheses: Vec<Hypothesis>,
    /// The first observation, which the hypotheses hang off (its pose stays in the state while
    /// the observation is stored).
    pub(super) anchor: StoredObservation,
    /// Range σ of every hypothesis [m].
    sigma_range: f64,
}

impl Track {
    /// A track without range hypotheses (multi-view initialization associates by descriptor).
    pub(super) fn plain(
        id: TrackId,
        descriptor: FeatureId,
        created: f64,
        first: StoredObservation,
    ) -> Self {
        Self {
            id,
            descriptor,
            created,
            observations: vec![first.clone()],
            hypotheses: Vec::new(),
            anchor: first,
            sigma_range: 0.0,
        }
    }
}

/// The first observation's line of sight and covariance blocks, for the correlated gate.
pub(super) struct Anchor {
    los: super::triangulation::PoseLineOfSight,
    /// P of the current vehicle's (p, Ψ) with the anchor pose (6×6).
    p_va: Mat6,
    /// P of the anchor pose (6×6).
    p_aa: Mat6,
    /// R of the anchor observation.
    r: DMatrix<f64>,
}

/// Bearing-only bookkeeping of a filter.
#[derive(Clone, Debug)]
pub(super) struct BearingState {
    pub(super) config: BearingConfig,
    /// The stored-pose frame (None when no vehicle is bearing-only and the origin cannot define
    /// one).
    pose_frame: Option<PoseFrame>,
    pub(super) tracks: Vec<Track>,
    pub(super) poses: BTreeMap<PoseId, StoredPose>,
    pub(super) next_track: TrackId,
    next_pose: PoseId,
    pub(super) stats: BearingStats,
}

impl BearingState {
    /// Applies `f` to the mean and covariance of every range hypothesis (a frame change of the
    /// filter: `super::rebase`).
    pub(super) fn transform_hypotheses(
        &mut self,
        f: impl Fn(&Vector3<f64>, &Matrix3<f64>) -> (Vector3<f64>, Matrix3<f64>),
    ) {
        for t in &mut self.tracks {
            for h in &mut t.hypotheses {
                (h.mean, h.covariance) = f(&h.mean, &h.covariance);
            }
        }
    }

    /// A merged feature key: tracks that carried it as their descriptor carry the new one.
    pub(super) fn rename_descriptor(&mut self, from: FeatureId, into: FeatureId) {
        for t in &mut self.tracks {
            if t.descriptor == from {
                t.descriptor = into;
            }
        }
    }

    pub(super) fn new(pose_frame: Option<PoseFrame>) -> Self {
        Self {
            config: BearingConfig::default(),
            pose_frame,
            tracks: Vec::new(),
            poses: BTreeMap::new(),
            next_track: 0,
            next_pose: 0,
            stats: BearingStats::default(),
        }
    }
}

/// The match of one observation to one track in a frame.
#[derive(Clone, Debug)]
struct TrackMatch {
    obs: usize,
    track: usize,
    /// Indices of the hypotheses that passed the gate.
    passed: Vec<usize>,
    gamma: f64,
}

/// Per-frame geometry of the observing vehicle.
pub(super) struct Current<'a> {
    model: &'a ObservationModel,
    pose: crate::observation::SensorPose,
    /// Covariance of the vehicle's (p, Ψ) (the P_pp of eq. 21.83).
    p_pp: Mat6,
    r: DMatrix<f64>,
}

fn nis(nu: &DVector<f64>, s: &DMatrix<f64>) -> f64 {
    match s.clone().cholesky() {
        Some(c) => nu.dot(&c.solve(nu)),
        None => f64::INFINITY,
    }
}

fn to_faer(m: &DMatrix<f64>) -> Mat<f64> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
}

impl SlamFilter {
    /// Bearing-only options.
    pub fn bearing_config(&self) -> &BearingConfig {
        &self.bearing.config
    }

    /// Replaces the bearing-only options (validated; existing tracks keep their hypotheses).
    pub fn set_bearing_config(&mut self, config: BearingConfig) -> Result<(), SlamError> {
        config.validate()?;
        if config.initialization == BearingInit::MultiView
            && !matches!(
                self.config.association.mode,
                AssociationMode::Descriptor | AssociationMode::Appearance { .. }
            )
        {
            return Err(SlamError::InvalidConfig(
                "bearing: multi-view initialization associates tracks by descriptor (tracker ids)"
                    .into(),
            ));
        }
        self.bearing.config = config;
        Ok(())
    }

    /// Counters of the bearing-only pipeline.
    pub fn bearing_stats(&self) -> BearingStats {
        self.bearing.stats
    }

    /// Number of stored poses in the state.
    pub fn num_stored_poses(&self) -> usize {
        self.layout.num_poses()
    }

    /// Number of uninitialized tracks.
    pub fn num_tracks(&self) -> usize {
        self.bearing.tracks.len()
    }

    /// The uninitialized tracks.
    pub fn tracks(&self) -> Vec<TrackInfo> {
        self.bearing
            .tracks
            .iter()
            .map(|t| TrackInfo {
                id: t.id,
                descriptor: t.descriptor,
                observations: t.observations.len(),
                hypothesis_ranges: t.hypotheses.iter().map(|h| h.range).collect(),
                created: t.created,
            })
            .collect()
    }

    /// A stored pose (p^n, Ψ^n) (position in the stored-pose frame n0, see
    /// [`super::triangulation`]).
    pub fn stored_pose(&self, id: PoseId) -> Option<(Vector3<f64>, Vector3<f64>)> {
        let off = self.layout.pose_offset(id)?;
        Some((self.vec3_at(off + POSE_POS), self.vec3_at(off + POSE_ATT)))
    }

    pub(super) fn pose_frame(&self) -> Result<PoseFrame, SlamError> {
        self.bearing.pose_frame.ok_or_else(|| {
            SlamError::InvalidConfig(
                "bearing-only SLAM needs an origin near the Earth's surface".into(),
            )
        })
    }

    pub(super) fn current_geometry<'a>(
        &self,
        vehicle: usize,
        model: &'a ObservationModel,
    ) -> Current<'a> {
        let voff = self.layout.vehicle_block(vehicle);
        let idx = |k: usize| {
            if k < 3 {
                voff + POS + k
            } else {
                voff + ATT + k - 3
            }
        };
        let x = self
            .vehicle_state(vehicle)
            .expect("vehicle validated by the caller");
        Current {
            model,
            pose: model.sensor_pose(&x.position, &x.attitude),
            p_pp: Mat6::from_fn(|i, j| self.p[(idx(i), idx(j))]),
            r: model.noise_covariance(),
        }
    }

    /// γ of an observation against one hypothesis (eqs. 21.55, 21.81–21.83); ∞ when the
    /// hypothesis cannot be observed from the current pose.
    fn hypothesis_gamma(cur: &Current<'_>, z: &DVector<f64>, h: &Hypothesis) -> f64 {
        let Ok(pred) = cur.model.predict(&cur.pose, &h.mean) else {
            return f64::INFINITY;
        };
        let nu = cur.model.innovation(z, &pred.z);
        let d = nu.len();
        let hv = DMatrix::from_fn(d, 6, |i, j| {
            if j < 3 {
                pred.d_position[(i, j)]
            } else {
                pred.d_attitude[(i, j - 3)]
            }
        });
        let hm = DMatrix::from_fn(d, 3, |i, j| pred.d_feature[(i, j)]);
        let p_pp = DMatrix::from_fn(6, 6, |i, j| cur.p_pp[(i, j)]);
        let p_j = DMatrix::from_fn(3, 3, |i, j| h.covariance[(i, j)]);
        let s = &hv * p_pp * hv.transpose() + &hm * p_j * hm.transpose() + &cur.r;
        nis(&nu, &s)
    }

    /// The anchor geometry of a track for the correlated gate (`None`: its first observation's
    /// pose is gone, or the gate is [`TrackGate::Chapter`]).
    fn anchor(&self, frame: &PoseFrame, vehicle: usize, track: &Track) -> Option<Anchor> {
        self.anchor_of(frame, vehicle, &track.anchor)
    }

    /// The anchor geometry of a first observation (see [`Self::anchored_gamma`]).
    pub(super) fn anchor_of(
        &self,
        frame: &PoseFrame,
        vehicle: usize,
        a: &StoredObservation,
    ) -> Option<Anchor> {
        if self.bearing.config.track_gate != TrackGate::Correlated {
            return None;
        }
        let off = self.layout.pose_offset(a.pose)?;
        let (p, att) = self.stored_pose(a.pose)?;
        let model = self.stored_model(a);
        let los = super::triangulation::pose_line_of_sight(
            frame,
            &PosedObservation {
                model: &model,
                position: p,
                attitude: att,
                z: &a.z,
            },
        )
        .ok()?;
        let voff = self.layout.vehicle_block(vehicle);
        let vi = |k: usize| {
            if k < 3 {
                voff + POS + k
            } else {
                voff + ATT + k - 3
            }
        };
        Some(Anchor {
            los,
            p_va: Mat6::from_fn(|i, j| self.p[(vi(i), off + j)]),
            p_aa: Mat6::from_fn(|i, j| self.p[(off + i, off + j)]),
            r: model.noise_covariance(),
        })
    }

    /// γ against the hypothesis at `range` hanging off the anchor (eqs. 21.55, 21.79–21.82 with
    /// the exact joint covariance of the current and the anchor pose instead of 21.83):
    /// x_j = y + r u (n0, mapped to the filter frame), ∂x_j/∂x_a = C (∂y + r ∂u)/∂x_a,
    /// S = H_v P_vv H_vᵀ + A P_aa Aᵀ + H_v P_va Aᵀ + A P_vaᵀ H_vᵀ + H_m N_j H_mᵀ + R with
    /// A = H_m ∂x_j/∂x_a and N_j = (r C ∂u/∂z) R_a (·)ᵀ + σ_r² u uᵀ.
    pub(super) fn anchored_gamma(
        frame: &PoseFrame,
        cur: &Current<'_>,
        z: &DVector<f64>,
        a: &Anchor,
        range: f64,
        sigma_range: f64,
    ) -> f64 {
        let c = frame.filter_from_pose();
        let mean = frame.to_filter(&(a.los.origin + a.los.direction * range));
        let Ok(pred) = cur.model.predict(&cur.pose, &mean) else {
            return f64::INFINITY;
        };
        let nu = cur.model.innovation(z, &pred.z);
        let d = nu.len();
        let g_a = c * (a.los.origin_d_pose + a.los.direction_d_pose * range);
        let u = c * a.los.direction;
        let c_d = DMatrix::from_fn(3, 3, |i, j| c[(i, j)]);
        let g_z = &c_d * &a.los.direction_d_z * range;
        let noise = &g_z * &a.r * g_z.transpose();
        let noise =
            Matrix3::from_fn(|i, j| noise[(i, j)]) + u * u.transpose() * sigma_range.powi(2);
        let to = |m: &dyn Fn(usize, usize) -> f64, r: usize, c: usize| DMatrix::from_fn(r, c, m);
        let hv = to(
            &|i, j| {
                if j < 3 {
                    pred.d_position[(i, j)]
                } else {
                    pred.d_attitude[(i, j - 3)]
                }
            },
            d,
            6,
        );
        let hm = to(&|i, j| pred.d_feature[(i, j)], d, 3);
        let a_m = &hm * to(&|i, j| g_a[(i, j)], 3, 6);
        let p_vv = to(&|i, j| cur.p_pp[(i, j)], 6, 6);
        let p_va = to(&|i, j| a.p_va[(i, j)], 6, 6);
        let p_aa = to(&|i, j| a.p_aa[(i, j)], 6, 6);
        let cross = &hv * p_va * a_m.transpose();
        let s = &hv * p_vv * hv.transpose()
            + &a_m * p_aa * a_m.transpose()
            + &cross
            + cross.transpose()
            + &hm * to(&|i, j| noise[(i, j)], 3, 3) * hm.transpose()
            + &cur.r;
        nis(&nu, &s)
    }

    /// Hypotheses along the line of sight of z from the current pose (eqs. 21.79, 21.80).
    fn make_hypotheses(
        &self,
        cur: &Current<'_>,
        z: &DVector<f64>,
    ) -> Result<(Vec<Hypothesis>, f64), SlamError> {
        let cfg = &self.bearing.config;
        let (dir, d_dir) = cur
            .model
            .sensor_direction(z)
            .map_err(|source| SlamError::Observation { index: 0, source })?;
        let los = cur.pose.line_of_sight(&dir);
        let n = cfg.hypotheses;
        let spacing = (cfg.max_range - cfg.min_range) / (n.max(2) - 1) as f64;
        // Each hypothesis stands for the range bin of width Δ around it, with a range σ of Δ/2:
        // neighbours overlap at 1 σ, so a feature between two bins keeps matching one of them
        // (the tighter uniform-bin σ, Δ/√12, let the true range be culled between two bins).
        let width = if n == 1 {
            cfg.max_range - cfg.min_range
        } else {
            spacing
        };
        let sigma_r = width / 2.0;
        let u = los.direction;
        let c_fs = DMatrix::from_fn(3, 3, |i, j| los.frame_from_sensor[(i, j)]);
        let du_dz = &c_fs * &d_dir;
        let mut out = Vec::with_capacity(n);
        for k in 0..n {
            let range = if n == 1 {
                0.5 * (cfg.min_range + cfg.max_range)
            } else {
                cfg.min_range + spacing * k as f64
            };
            let mut gv = SMatrix::<f64, 3, 6>::zeros();
            gv.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(los.origin_d_position + los.direction_d_position * range));
            gv.fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&(los.origin_d_attitude + los.direction_d_attitude * range));
            let gz = &du_dz * range;
            let pz = &gz * &cur.r * gz.transpose();
            let covariance = gv * cur.p_pp * gv.transpose()
                + Matrix3::from_fn(|i, j| pz[(i, j)])
                + u * u.transpose() * sigma_r * sigma_r;
            let mean = los.origin + u * range;
            if !(mean.iter().all(|v| v.is_finite()) && covariance.iter().all(|v| v.is_finite())) {
                return Err(SlamError::NumericalFailure("track hypotheses"));
            }
            out.push(Hypothesis {
                range,
                mean,
                covariance: (covariance + covariance.transpose()) * 0.5,
            });
        }
        Ok((out, sigma_r))
    }

    /// The bearing-only part of a frame (module docs, steps 1–6) for the observations `pending`
    /// (indices into `zs`) that the association against initialized features left over.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn process_bearing_observations(
        &mut self,
        vehicle: usize,
        model: &ObservationModel,
        time: f64,
        zs: &[DVector<f64>],
        descriptors: &[FeatureId],
        pending: &[usize],
        report: &mut FrameReport,
    ) {
        // `SlamFilter::new` refuses bearing-only vehicles without a stored-pose frame.
        let Ok(pose_frame) = self.pose_frame() else {
            return;
        };
        self.prune_tracks(time);
        if pending.is_empty() {
            self.remove_unreferenced_poses();
            return;
        }
        let cur = self.current_geometry(vehicle, model);
        let gate = self.gate(model.measurement_dim());

        // Step 2: association to tracks.
        let mut matches: Vec<TrackMatch> = Vec::new();
        let mut new_tracks: Vec<usize> = Vec::new();
        let anchors: Vec<Option<Anchor>> = self
            .bearing
            .tracks
            .iter()
            .map(|t| self.anchor(&pose_frame, vehicle, t))
            .collect();
        let tracks = &self.bearing.tracks;
        let gate_track = |t: usize, z: &DVector<f64>| -> (Vec<usize>, f64) {
            let track = &tracks[t];
            let mut passed = Vec::new();
            let mut best = f64::INFINITY;
            for (k, h) in track.hypotheses.iter().enumerate() {
                let g = match &anchors[t] {
                    Some(a) => {
                        Self::anchored_gamma(&pose_frame, &cur, z, a, h.range, track.sigma_range)
                    }
                    None => Self::hypothesis_gamma(&cur, z, h),
                };
                best = best.min(g);
                if g <= gate {
                    passed.push(k);
                }
            }
            (passed, best)
        };
        match self.config.association.mode {
            // Tracker ids (appearance mode) key tracks like descriptors do.
            AssociationMode::Descriptor | AssociationMode::Appearance { .. } => {
                let by_descriptor: HashMap<FeatureId, usize> = self
                    .bearing
                    .tracks
                    .iter()
                    .enumerate()
                    .map(|(k, t)| (t.descriptor, k))
                    .collect();
                for &i in pending {
                    match by_descriptor.get(&descriptors[i]) {
                        None => new_tracks.push(i),
                        Some(&k) => {
                            let (passed, gamma) = gate_track(k, &zs[i]);
                            if passed.is_empty() {
                                report.outcomes[i] =
                                    ObservationOutcome::Rejected(RejectReason::GateFailed {
                                        feature: descriptors[i],
                                        nis: gamma,
                                    });
                            } else {
                                matches.push(TrackMatch {
                                    obs: i,
                                    track: k,
                                    passed,
                                    gamma,
                                });
                            }
                        }
                    }
                }
            }
            AssociationMode::NearestNeighbour | AssociationMode::Jcbb { .. } => {
                for &i in pending {
                    let mut hits: Vec<TrackMatch> = Vec::new();
                    for k in 0..self.bearing.tracks.len() {
                        let (passed, gamma) = gate_track(k, &zs[i]);
                        if !passed.is_empty() {
                            hits.push(TrackMatch {
                                obs: i,
                                track: k,
                                passed,
                                gamma,
                            });
                        }
                    }
                    match hits.len() {
                        0 => new_tracks.push(i),
                        1 => matches.extend(hits),
                        // Matches several uninitialized features: rejected (21.4.3.3).
                        _ => {
                            report.outcomes[i] =
                                ObservationOutcome::Rejected(RejectReason::Ambiguous)
                        }
                    }
                }
                // A track matched by several observations of the frame keeps the lowest γ.
                matches.sort_by(|a, b| a.gamma.total_cmp(&b.gamma));
                let mut taken = std::collections::HashSet::new();
                matches.retain(|m| {
                    if taken.insert(m.track) {
                        true
                    } else {
                        report.outcomes[m.obs] =
                            ObservationOutcome::Rejected(RejectReason::Ambiguous);
                        false
                    }
                });
            }
        }
        if matches.is_empty() && new_tracks.is_empty() {
            self.remove_unreferenced_poses();
            return;
        }

        // Step 3: store the current pose (once) and the observations.
        let matched_ids: Vec<TrackId> = matches
            .iter()
            .map(|m| self.bearing.tracks[m.track].id)
            .collect();
        let stored = self.store_current_pose(vehicle, &matched_ids);
        let Ok(Some(pose)) = stored else {
            let reason = match stored {
                Ok(_) => RejectReason::PoseCapacity,
                Err(_) => RejectReason::NumericalFailure,
            };
            for i in matches
                .iter()
                .map(|m| m.obs)
                .chain(new_tracks.iter().copied())
            {
                report.outcomes[i] = ObservationOutcome::Rejected(reason);
            }
            self.remove_unreferenced_poses();
            return;
        };
        // Track indices may have shifted when tracks were dropped for capacity: re-find by id.
        let mut touched: Vec<TrackId> = Vec::new();
        for (m, id) in matches.iter().zip(&matched_ids) {
            let Some(k) = self.bearing.tracks.iter().position(|t| t.id == *id) else {
                report.outcomes[m.obs] = ObservationOutcome::Rejected(RejectReason::PoseCapacity);
                continue;
            };
            let track = &mut self.bearing.tracks[k];
            // Cull the hypotheses the observation does not match (21.4.3.2).
            let mut keep = m.passed.iter().copied().peekable();
            let mut idx = 0;
            track.hypotheses.retain(|_| {
                let kept = keep.peek() == Some(&idx);
                if kept {
                    keep.next();
                }
                idx += 1;
                kept
            });
            track.observations.push(StoredObservation {
                pose,
                vehicle,
                z: zs[m.obs].clone(),
            });
            self.bearing.poses.get_mut(&pose).expect("just stored").refs += 1;
            self.bearing.stats.observations_stored += 1;
            report.outcomes[m.obs] = ObservationOutcome::Stored { track: *id };
            touched.push(*id);
        }
        for &i in &new_tracks {
            let (hypotheses, sigma_range) = match self.make_hypotheses(&cur, &zs[i]) {
                Ok(h) => h,
                Err(_) => {
                    report.outcomes[i] =
                        ObservationOutcome::Rejected(RejectReason::NumericalFailure);
                    continue;
                }
            };
            let id = self.bearing.next_track;
            self.bearing.next_track += 1;
            let first = StoredObservation {
                pose,
                vehicle,
                z: zs[i].clone(),
            };
            self.bearing.tracks.push(Track {
                id,
                descriptor: descriptors[i],
                created: time,
                observations: vec![first.clone()],
                hypotheses,
                anchor: first,
                sigma_range,
            });
            self.bearing.poses.get_mut(&pose).expect("just stored").refs += 1;
            self.bearing.stats.tracks_started += 1;
            self.bearing.stats.observations_stored += 1;
            report.outcomes[i] = ObservationOutcome::Stored { track: id };
        }

        // Steps 4, 5: initialize the tracks that gained an observation, when they can.
        for (m, id) in matches.iter().zip(&matched_ids) {
            if !touched.contains(id) {
                continue;
            }
            match self.try_initialize(&pose_frame, *id, m.obs, report) {
                Err(_) => {
                    // A numerical failure (e.g. a non-positive-definite initial covariance):
                    // nothing changed for this track; drop it rather than retry every frame.
                    if let Some(k) = self.bearing.tracks.iter().position(|t| t.id == *id) {
                        self.drop_track(k);
                    }
                    self.bearing.stats.triangulations_rejected += 1;
                    report.outcomes[m.obs] =
                        ObservationOutcome::Rejected(RejectReason::NumericalFailure);
                }
                Ok(Some(feature)) => {
                    report.outcomes[m.obs] = ObservationOutcome::Initialized { feature };
                    report.initialized_tracks.push((*id, feature));
                }
                Ok(None) => {
                    if let Some(k) = self.bearing.tracks.iter().position(|t| t.id == *id)
                        && self.bearing.tracks[k].observations.len()
                            >= self.bearing.config.max_track_observations
                    {
                        self.drop_track(k);
                        self.bearing.stats.tracks_dropped_observations += 1;
                    }
                }
            }
        }
        self.remove_unreferenced_poses();
    }

    /// Drops tracks past their age, and (descriptor mode) recovers tracks whose feature is now
    /// in the map onto it.
    pub(super) fn prune_tracks(&mut self, time: f64) {
        let max_age = self.bearing.config.max_track_age;
        let mut k = 0;
        while k < self.bearing.tracks.len() {
            let t = &self.bearing.tracks[k];
            if time - t.created > max_age {
                self.drop_track(k);
                self.bearing.stats.tracks_dropped_age += 1;
                continue;
            }
            if self.config.association.mode == AssociationMode::Descriptor
                && self.layout.has_feature(t.descriptor)
            {
                let track = self.bearing.tracks.remove(k);
                let off = self.layout.feature_offset(track.descriptor);
                if let Some(off) = off {
                    self.recover(off, &track.observations);
                }
                self.release(&track.observations);
                self.bearing.stats.tracks_merged += 1;
                continue;
            }
            k += 1;
        }
    }

    pub(super) fn release(&mut self, observations: &[StoredObservation]) {
        for o in observations {
            if let Some(p) = self.bearing.poses.get_mut(&o.pose) {
                p.refs = p.refs.saturating_sub(1);
            }
        }
    }

    pub(super) fn drop_track(&mut self, k: usize) {
        let track = self.bearing.tracks.remove(k);
        self.release(&track.observations);
    }

    /// Removes stored poses that no stored observation refers to (21.4.2.4): x and P shrink.
    pub(super) fn remove_unreferenced_poses(&mut self) {
        let unused: Vec<PoseId> = self
            .bearing
            .poses
            .iter()
            .filter(|(_, p)| p.refs == 0)
            .map(|(id, _)| *id)
            .collect();
        for id in unused {
            self.bearing.poses.remove(&id);
            if self.remove_block(SlotKind::Pose(id)) {
                self.bearing.stats.poses_removed += 1;
            }
        }
    }

    /// Adds the current pose of `vehicle` to the state (eqs. 21.66–21.68), first dropping the
    /// oldest tracks not in `keep` while the cap is reached. `None` when no pose can be freed.
    pub(super) fn store_current_pose(
        &mut self,
        vehicle: usize,
        keep: &[TrackId],
    ) -> Result<Option<PoseId>, SlamError> {
        let cap = self.bearing.config.max_stored_poses;
        self.remove_unreferenced_poses();
        while self.bearing.poses.len() >= cap {
            let oldest = self
                .bearing
                .tracks
                .iter()
                .enumerate()
                .filter(|(_, t)| !keep.contains(&t.id))
                .min_by(|a, b| {
                    a.1.created
                        .total_cmp(&b.1.created)
                        .then(a.1.id.cmp(&b.1.id))
                })
                .map(|(k, _)| k);
            let Some(k) = oldest else {
                return Ok(None);
            };
            self.drop_track(k);
            self.bearing.stats.tracks_dropped_capacity += 1;
            self.remove_unreferenced_poses();
        }
        let frame = self.pose_frame()?;
        let voff = self.layout.vehicle_block(vehicle);
        let state = self.vehicle_state(vehicle)?;
        let p_n = frame.from_filter(&state.position);
        let mean = [
            p_n.x,
            p_n.y,
            p_n.z,
            state.attitude.x,
            state.attitude.y,
            state.attitude.z,
        ];
        // x_p = (C_e^{n0} (p − o), Ψ): ∂x_p/∂p = C_e^{n0} (I in local SLAM), ∂x_p/∂Ψ = I.
        let rt = frame.filter_from_pose().transpose();
        let mut j_pos = Mat::zeros(POSE_DIM, 3);
        let mut j_att = Mat::zeros(POSE_DIM, 3);
        for i in 0..3 {
            for j in 0..3 {
                j_pos[(POSE_POS + i, j)] = rt[(i, j)];
            }
            j_att[(POSE_ATT + i, i)] = 1.0;
        }
        let id = self.bearing.next_pose;
        self.augment_linear(
            SlotKind::Pose(id),
            &mean,
            &[(voff + POS, j_pos), (voff + ATT, j_att)],
            &Mat::zeros(POSE_DIM, POSE_DIM),
            false,
        )?;
        self.bearing.next_pose += 1;
        self.bearing.poses.insert(id, StoredPose { refs: 0 });
        self.bearing.stats.poses_added += 1;
        let held = self.bearing.poses.len();
        self.bearing.stats.max_stored_poses = self.bearing.stats.max_stored_poses.max(held);
        Ok(Some(id))
    }

    /// The sensor model of a stored observation's vehicle.
    pub(super) fn stored_model(&self, o: &StoredObservation) -> ObservationModel {
        self.vehicles[o.vehicle].model
    }

    /// Steps 4 and 5 for one track; returns the new feature's id when it initialized.
    fn try_initialize(
        &mut self,
        frame: &PoseFrame,
        id: TrackId,
        current_obs: usize,
        report: &mut FrameReport,
    ) -> Result<Option<FeatureId>, SlamError> {
        let Some(k) = self.bearing.tracks.iter().position(|t| t.id == id) else {
            return Ok(None);
        };
        if self.bearing.tracks[k].observations.len() < 2 {
            return Ok(None);
        }
        // Lines of sight of every stored observation from its stored pose.
        let obs = self.bearing.tracks[k].observations.clone();
        let mut dirs = Vec::with_capacity(obs.len());
        for o in &obs {
            let Some((p, a)) = self.stored_pose(o.pose) else {
                return Err(SlamError::NumericalFailure("stored pose slot"));
            };
            let model = self.stored_model(o);
            let posed = PosedObservation {
                model: &model,
                position: p,
                attitude: a,
                z: &o.z,
            };
            let los = super::triangulation::pose_line_of_sight(frame, &posed)
                .map_err(|source| SlamError::Observation { index: 0, source })?;
            dirs.push(los.direction);
        }
        let mut best = (0, 0, -1.0);
        for a in 0..dirs.len() {
            for b in a + 1..dirs.len() {
                let angle = super::triangulation::separation_angle(&dirs[a], &dirs[b]);
                if angle > best.2 {
                    best = (a, b, angle);
                }
            }
        }
        let cfg = self.bearing.config;
        if best.2 < cfg.min_parallax {
            return Ok(None);
        }
        let (ia, ib) = (best.0, best.1);
        let (pa, aa) = self.stored_pose(obs[ia].pose).expect("checked above");
        let (pb, ab) = self.stored_pose(obs[ib].pose).expect("checked above");
        let (ma, mb) = (self.stored_model(&obs[ia]), self.stored_model(&obs[ib]));
        let oa = PosedObservation {
            model: &ma,
            position: pa,
            attitude: aa,
            z: &obs[ia].z,
        };
        let ob = PosedObservation {
            model: &mb,
            position: pb,
            attitude: ab,
            z: &obs[ib].z,
        };
        // The miss is judged against max(max_miss_distance, 3 σ_w) below, σ_w from the stored
        // poses' joint covariance and R, so no distance limit here.
        let init = match initialize_from_pair(frame, &oa, &ob, cfg.min_parallax, f64::INFINITY) {
            Ok(init) => Some(init),
            Err(TriangulationError::NearParallel { .. }) => return Ok(None),
            Err(_) => None,
        };
        let init = init.filter(|g| {
            let off = |o: &StoredObservation| self.layout.pose_offset(o.pose);
            let (Some(oa), Some(ob)) = (off(&obs[ia]), off(&obs[ib])) else {
                return false;
            };
            let block = |r: usize, c: usize| Mat6::from_fn(|i, j| self.p[(r + i, c + j)]);
            let var = (g.miss_d_pose_a * block(oa, oa) * g.miss_d_pose_a.transpose())[0]
                + 2.0 * (g.miss_d_pose_a * block(oa, ob) * g.miss_d_pose_b.transpose())[0]
                + (g.miss_d_pose_b * block(ob, ob) * g.miss_d_pose_b.transpose())[0]
                + (&g.miss_d_z_a * ma.noise_covariance() * g.miss_d_z_a.transpose())[(0, 0)]
                + (&g.miss_d_z_b * mb.noise_covariance() * g.miss_d_z_b.transpose())[(0, 0)];
            // 3 σ: a correct pairing passes with 99.7 % (a misassociation typically misses by
            // far more); never tighter than the configured distance.
            g.miss <= cfg.max_miss_distance.max(3.0 * var.max(0.0).sqrt())
        });
        let Some(init) = init else {
            // Discard the pair's observations (21.4.2.3); the track goes on.
            let track = &mut self.bearing.tracks[k];
            let pair = [
                track.observations[ib].clone(),
                track.observations[ia].clone(),
            ];
            track.observations.remove(ib);
            track.observations.remove(ia);
            self.release(&pair);
            self.bearing.stats.triangulations_rejected += 1;
            self.bearing.stats.observations_discarded += 2;
            // The frame's observation is the track's last one.
            if ib == obs.len() - 1 {
                report.outcomes[current_obs] =
                    ObservationOutcome::Rejected(RejectReason::TriangulationFailed { track: id });
            }
            if self.bearing.tracks[k].observations.is_empty() {
                self.drop_track(k);
            }
            return Ok(None);
        };
        // Eq. 21.76: P_m· = ∇G_p P_{poses,·}, P_mm = ∇G_p P_pp ∇G_pᵀ + ∇G_z R₂ ∇G_zᵀ (21.77).
        let off_a = self
            .layout
            .pose_offset(obs[ia].pose)
            .expect("checked above");
        let off_b = self
            .layout
            .pose_offset(obs[ib].pose)
            .expect("checked above");
        let ga = Mat::from_fn(3, POSE_DIM, |i, j| init.d_pose_a[(i, j)]);
        let gb = Mat::from_fn(3, POSE_DIM, |i, j| init.d_pose_b[(i, j)]);
        let noise = &init.d_z_a * ma.noise_covariance() * init.d_z_a.transpose()
            + &init.d_z_b * mb.noise_covariance() * init.d_z_b.transpose();
        let feature_id = self.new_feature_id(self.bearing.tracks[k].descriptor);
        let jac = if off_a == off_b {
            // Both observations from one stored pose (two vehicles' frames never share one, but
            // keep the algebra right): the Jacobians add.
            vec![(off_a, &ga + &gb)]
        } else {
            vec![(off_a, ga), (off_b, gb)]
        };
        self.map_generation += 1;
        self.augment_linear(
            SlotKind::Feature(feature_id),
            init.feature.as_slice(),
            &jac,
            &to_faer(&noise),
            true,
        )?;
        self.bearing.stats.features_initialized += 1;
        // Step 5: recover the remaining stored observations (eq. 21.78).
        let track = self.bearing.tracks.remove(k);
        let rest: Vec<StoredObservation> = track
            .observations
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != ia && *j != ib)
            .map(|(_, o)| o.clone())
            .collect();
        let foff = self
            .layout
            .feature_offset(feature_id)
            .expect("feature just augmented");
        self.recover(foff, &rest);
        self.release(&track.observations);
        Ok(Some(feature_id))
    }

    /// Batch EKF update (eq. 21.78) of stored observations against the feature at `foff`, each
    /// through its stored pose; observations failing their individual gate are discarded.
    fn recover(&mut self, foff: usize, observations: &[StoredObservation]) {
        let Ok(frame) = self.pose_frame() else {
            return;
        };
        let m = self.vec3_at(foff);
        struct Row {
            poff: usize,
            h_pos: DMatrix<f64>,
            h_att: DMatrix<f64>,
            h_m: DMatrix<f64>,
            nu: DVector<f64>,
            r: DMatrix<f64>,
        }
        let mut rows: Vec<Row> = Vec::new();
        for o in observations {
            let Some(poff) = self.layout.pose_offset(o.pose) else {
                continue;
            };
            let model = self.stored_model(o);
            let p_n = self.vec3_at(poff + POSE_POS);
            let att = self.vec3_at(poff + POSE_ATT);
            let Ok(pred) = predict_from_pose(&frame, &model, &p_n, &att, &m) else {
                self.bearing.stats.recovery_rejected += 1;
                continue;
            };
            let d = pred.z.len();
            let nu = model.innovation(&o.z, &pred.z);
            let h_pos = DMatrix::from_fn(d, 3, |i, j| pred.d_position[(i, j)]);
            let h_att = DMatrix::from_fn(d, 3, |i, j| pred.d_attitude[(i, j)]);
            let h_m = DMatrix::from_fn(d, 3, |i, j| pred.d_feature[(i, j)]);
            let r = model.noise_covariance();
            // Individual gate against the current joint covariance of (pose, feature).
            let idx: Vec<usize> = (0..6)
                .map(|c| poff + c)
                .chain((0..3).map(|c| foff + c))
                .collect();
            let p_sub = DMatrix::from_fn(9, 9, |i, j| self.p[(idx[i], idx[j])]);
            let mut h = DMatrix::zeros(d, 9);
            h.view_mut((0, POSE_POS), (d, 3)).copy_from(&h_pos);
            h.view_mut((0, POSE_ATT), (d, 3)).copy_from(&h_att);
            h.view_mut((0, 6), (d, 3)).copy_from(&h_m);
            let s = &h * p_sub * h.transpose() + &r;
            if nis(&nu, &s) > self.gate(d) {
                self.bearing.stats.recovery_rejected += 1;
                continue;
            }
            rows.push(Row {
                poff,
                h_pos,
                h_att,
                h_m,
                nu,
                r,
            });
        }
        if rows.is_empty() {
            return;
        }
        let apply = |filter: &mut SlamFilter, rows: &[&Row]| -> Result<(), SlamError> {
            let total: usize = rows.iter().map(|r| r.nu.len()).sum();
            let mut blocks = Vec::with_capacity(3 * rows.len());
            let mut nu = Col::zeros(total);
            let mut r = Mat::zeros(total, total);
            let mut row = 0;
            for x in rows {
                let d = x.nu.len();
                blocks.push(HBlock {
                    row,
                    col: x.poff + POSE_POS,
                    mat: to_faer(&x.h_pos),
                });
                blocks.push(HBlock {
                    row,
                    col: x.poff + POSE_ATT,
                    mat: to_faer(&x.h_att),
                });
                blocks.push(HBlock {
                    row,
                    col: foff,
                    mat: to_faer(&x.h_m),
                });
                for i in 0..d {
                    nu[row + i] = x.nu[i];
                }
                r.as_mut()
                    .submatrix_mut(row, row, d, d)
                    .copy_from(&to_faer(&x.r));
                row += d;
            }
            filter.blocks_update(&blocks, &nu, r)
        };
        let all: Vec<&Row> = rows.iter().collect();
        self.map_generation += 1;
        if apply(self, &all).is_ok() {
            self.bearing.stats.observations_recovered += rows.len() as u64;
            return;
        }
        // One at a time if the stacked S failed numerically (each re-linearization skipped:
        // the rows were linearized at the same estimate).
        for x in &rows {
            if apply(self, &[x]).is_ok() {
                self.bearing.stats.observations_recovered += 1;
            } else {
                self.bearing.stats.recovery_rejected += 1;
            }
        }
    }
}
