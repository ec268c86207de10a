//! The inertial EKF-SLAM filter (§21.3) with M ≥ 1 vehicle blocks and one map.
//!
//! The same type is the per-vehicle filter (M = 1) and the centralized all-data reference EKF
//! (M = all vehicles sharing one map). State layout (see [`layout`]): vehicle blocks, then
//! features (3 each, keyed by [`FeatureId`]), then stored poses of bearing-only SLAM (6 each),
//! with all index bookkeeping in the [`Layout`] slot table. x is a faer `Col`, P a faer `Mat`; small blocks use nalgebra.
//!
//! # Prediction (eqs. 21.46, 21.47) with a lazy transition
//! An IMU sample changes only the vehicle's rows and columns of P. [`SlamFilter::predict`] updates
//! the 15×15 block P_vv ← F P_vv Fᵀ + G Q Gᵀ at once and accumulates Φ ← F Φ; the cross-covariance
//! P_v· ← Φ P_v· is applied when P is next read in full ([`SlamFilter::flush`]: before updates,
//! augmentation, fusion or [`SlamFilter::joint_covariance`]). A prediction therefore costs O(1)
//! in the map size, and a flush O(15²·n). Map blocks are untouched (∇F is identity there, eqs.
//! 21.25, 21.38), so the map marginal is always current without a flush.
//!
//! # Frames of observations
//! [`SlamFilter::process_frame`] validates the whole frame first (a bad frame is a typed error
//! and leaves the filter bit-for-bit unchanged), associates every observation against the prior
//! (Mahalanobis gate of eq. 21.55 at `gate_probability`; descriptor, nearest-neighbour or JCBB),
//! performs one stacked EKF update (eqs. 21.56–21.65) for the associated observations in Joseph
//! form, then initializes the unassociated observations from the updated vehicle estimate: a
//! range-bearing vehicle directly (eqs. 21.48–21.54), a bearing or pixel vehicle through stored
//! poses, multi-hypothesis tracks and delayed triangulation (§21.4, module `bearing`; the
//! geometry is in [`triangulation`]). The pipeline follows each vehicle's `SensorModel`, so a
//! centralized filter may mix both kinds.

mod appearance;
mod association;
mod bearing;
mod ci_fuse;
mod correspond;
mod deferred;
mod fuse;
mod info_cache;
pub mod layout;
mod multiview;
mod rebase;
mod source;
pub mod triangulation;
mod update;

pub use bearing::{BearingConfig, BearingInit, BearingStats, TrackGate, TrackId, TrackInfo};
pub use ci_fuse::CiReport;
pub use correspond::{CorrespondenceConfig, CorrespondenceReport};
pub use fuse::{ForgetReport, FuseMethod, FuseReport, Refused, VANISHED_RTOL};
pub use layout::{Layout, PoseId, Slot, SlotKind};
pub use rebase::{GAUGE_SIGMA_TRANSLATION_M, GAUGE_SIGMA_YAW_RAD, default_gauge};

use crate::consistency::chi2_quantile;
use crate::imu::ImuNoise;
use crate::info::{MapInformation, MapMarginal};
use crate::ins::{self, InsError, VehicleCovariance, VehicleState};
use crate::observation::{ObservationError, ObservationModel};
use crate::rotation::wrap_angle;
use crate::sensor::{FeatureId, ImuSample, ObservationFrame, SensorModel, SensorMount};
use crate::state::{ATT, NavFrame, VEHICLE_DIM};
use faer::{Col, Mat};
use nalgebra::{Matrix3, SMatrix, Vector3};

/// Base of the reserved id range for features whose descriptor is unusable (already taken):
/// ids ≥ this are `FRESH_ID_BASE | namespace << 32 | counter`. Simulated descriptors must stay
/// below it.
pub const FRESH_ID_BASE: FeatureId = 1 << 63;

/// How observations are matched to map features.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AssociationMode {
    /// Trust the descriptor for the candidate, verify it with the gate: a failed gate rejects the
    /// observation (no duplicate feature); an unknown descriptor initializes a feature with it.
    Descriptor,
    /// Ignore descriptors: greedy nearest neighbour over all gated (observation, feature) pairs.
    NearestNeighbour,
    /// Ignore descriptors: joint compatibility branch and bound (Neira & Tardós 2001), exploring
    /// at most `max_nodes` hypothesis nodes per frame (then the best hypothesis so far is used).
    Jcbb {
        /// Search budget per frame.
        max_nodes: usize,
    },
    /// No identities (module `appearance`): the descriptor is the tracker's short-lived track
    /// id, each observation carries a 256-bit appearance descriptor. A track that follows a
    /// feature is tried against it first; otherwise candidates are the features whose
    /// descriptor is within `max_distance` bits, gated (21.55) and chosen jointly by JCBB
    /// (`max_nodes` per frame). New features get this filter's own keys.
    Appearance {
        /// Largest Hamming distance (of 256 bits) of a candidate.
        max_distance: u32,
        /// JCBB search budget per frame.
        max_nodes: usize,
    },
}

/// Data-association options.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AssociationConfig {
    /// Matching strategy.
    pub mode: AssociationMode,
    /// Probability of the χ² validation gate (eq. 21.55; 0.95 gives 7.815 for 3 dof).
    pub gate_probability: f64,
    /// Gating modes only: an observation that matches no feature at `gate_probability` starts a
    /// new feature only if it is also outside this wider gate of every feature (0.9999 gives
    /// 21.1 for 3 dof); in between it is rejected. Without this band, the 5 % of a feature's own
    /// observations that fall outside the 95 % gate would each start a duplicate of it.
    pub new_feature_probability: f64,
}

impl Default for AssociationConfig {
    fn default() -> Self {
        Self {
            mode: AssociationMode::Descriptor,
            gate_probability: 0.95,
            new_feature_probability: DEFAULT_NEW_FEATURE_PROBABILITY,
        }
    }
}

/// Default of [`AssociationConfig::new_feature_probability`].
pub const DEFAULT_NEW_FEATURE_PROBABILITY: f64 = 0.9999;

/// Filter-wide options.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SlamConfig {
    /// Navigation frame of positions and the map.
    pub frame: NavFrame,
    /// Gravity magnitude of the flat local frame [m/s²] (local SLAM; finite and positive, e.g.
    /// WGS-84 normal gravity at the launch site). Global SLAM ignores it: it uses WGS-84 normal
    /// gravity at each position.
    pub local_gravity_mps2: f64,
    /// Team-wide origin o of map information (ECEF launch site in global SLAM, zero in local
    /// SLAM; `info` module docs).
    pub origin: Vector3<f64>,
    /// Data association.
    pub association: AssociationConfig,
    /// Namespace of fresh feature ids (make it unique per filter in a team, e.g. the vehicle id;
    /// only the low 31 bits are used).
    pub fresh_id_namespace: u32,
}

/// One vehicle of the filter: initial estimate and its sensors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VehicleSetup {
    /// Initial state estimate.
    pub state: VehicleState,
    /// Initial 15×15 covariance (symmetric positive definite).
    pub covariance: VehicleCovariance,
    /// IMU noise model (Q of eq. 21.17).
    pub imu_noise: ImuNoise,
    /// Terrain sensor kind and noise.
    pub sensor: SensorModel,
    /// Terrain sensor mounting.
    pub mount: SensorMount,
}

/// Everything that can go wrong; the filter is unchanged whenever one is returned.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SlamError {
    /// No such vehicle block.
    #[error("unknown vehicle {0}")]
    UnknownVehicle(usize),
    /// Invalid IMU sample or failed propagation.
    #[error(transparent)]
    Ins(#[from] InsError),
    /// An invalid observation in a frame.
    #[error("observation {index}: {source}")]
    Observation {
        /// Index in the frame.
        index: usize,
        /// What was wrong.
        source: ObservationError,
    },
    /// The frame time is NaN or infinite.
    #[error("frame time is not finite")]
    NonFiniteTime,
    /// A construction argument is invalid.
    #[error("invalid configuration: {0}")]
    InvalidConfig(String),
    /// A received map-information delta is malformed (sizes, duplicates, non-finite, asymmetric).
    #[error("invalid map information: {0}")]
    InvalidInformation(String),
    /// The map information uses another origin than this filter.
    #[error("map information origin differs from the filter's origin")]
    OriginMismatch,
    /// A matrix that must be positive definite is not (Cholesky failed).
    #[error("{0} is not positive definite")]
    NotPositiveDefinite(&'static str),
    /// A computation produced NaN or ∞ (the result was discarded).
    #[error("numerical failure in {0}")]
    NumericalFailure(&'static str),
}

/// Why an observation was not used.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum RejectReason {
    /// Descriptor mode: the feature with this id failed the gate (NIS above the threshold).
    GateFailed {
        /// Candidate feature.
        feature: FeatureId,
        /// Its normalized innovation squared.
        nis: f64,
    },
    /// Compatible with a feature that another observation of the frame took (or with one that
    /// the joint hypothesis excluded): neither updated nor initialized, to avoid a duplicate.
    Ambiguous,
    /// No compatible feature, and the sensor cannot initialize one from a single observation.
    NotInitializable,
    /// The candidate feature is not observable from this pose (behind the camera, degenerate).
    DegenerateGeometry,
    /// The update or augmentation failed numerically and was skipped.
    NumericalFailure,
    /// The measurement was refused before use (corrupt or physically invalid); the frame's other
    /// observations were processed without it.
    InvalidMeasurement(MeasurementFault),
    /// Bearing-only: no stored pose could be freed under `max_stored_poses` (every track was
    /// matched in this frame).
    PoseCapacity,
    /// Bearing-only: the observation matched a track, but the triangulation it took part in was
    /// rejected (lines missing each other, or meeting behind a sensor: typically a
    /// misassociation); the observation and its partner were discarded.
    TriangulationFailed {
        /// The track it had matched.
        track: TrackId,
    },
}

/// What is wrong with a refused measurement ([`RejectReason::InvalidMeasurement`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MeasurementFault {
    /// The measurement kind does not match the vehicle's sensor model.
    KindMismatch,
    /// A NaN or infinite component.
    NonFinite,
    /// A range ≤ 0 (Gaussian range noise near the sensor can produce one).
    NonPositiveRange,
    /// An elevation outside [−π/2, π/2].
    ElevationOutOfRange,
    /// A pixel outside the configured image bounds.
    OutsideImage,
}

impl MeasurementFault {
    fn of(e: &ObservationError) -> Option<Self> {
        match e {
            ObservationError::KindMismatch { .. } => Some(Self::KindMismatch),
            ObservationError::NonFinite => Some(Self::NonFinite),
            ObservationError::NonPositiveRange(_) => Some(Self::NonPositiveRange),
            ObservationError::ElevationOutOfRange(_) => Some(Self::ElevationOutOfRange),
            ObservationError::OutsideImage { .. } => Some(Self::OutsideImage),
            ObservationError::DegenerateGeometry | ObservationError::NotInitializable(_) => None,
        }
    }
}

impl RejectReason {
    /// A stable snake-case name for counting rejections by reason (outputs, logs).
    pub fn label(&self) -> &'static str {
        match self {
            RejectReason::GateFailed { .. } => "gate_failed",
            RejectReason::Ambiguous => "ambiguous",
            RejectReason::NotInitializable => "not_initializable",
            RejectReason::DegenerateGeometry => "degenerate_geometry",
            RejectReason::NumericalFailure => "numerical_failure",
            RejectReason::InvalidMeasurement(f) => match f {
                MeasurementFault::KindMismatch => "invalid_measurement:kind_mismatch",
                MeasurementFault::NonFinite => "invalid_measurement:non_finite",
                MeasurementFault::NonPositiveRange => "invalid_measurement:non_positive_range",
                MeasurementFault::ElevationOutOfRange => {
                    "invalid_measurement:elevation_out_of_range"
                }
                MeasurementFault::OutsideImage => "invalid_measurement:outside_image",
            },
            RejectReason::PoseCapacity => "pose_capacity",
            RejectReason::TriangulationFailed { .. } => "triangulation_failed",
        }
    }
}

/// What happened to one observation of a frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum ObservationOutcome {
    /// Associated to a feature and used in the update.
    Associated {
        /// Feature id.
        feature: FeatureId,
        /// NIS of the individual innovation against the prior.
        nis: f64,
    },
    /// Initialized a new feature (bearing-only: completed the initialization of a track).
    Initialized {
        /// The new feature's id.
        feature: FeatureId,
    },
    /// Bearing-only: stored with an uninitialized feature track (delayed initialization).
    Stored {
        /// The track.
        track: TrackId,
    },
    /// Not used.
    Rejected(RejectReason),
}

/// Per-observation outcomes of a frame, in the frame's order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameReport {
    /// One entry per observation.
    pub outcomes: Vec<ObservationOutcome>,
    /// Hypothesis nodes explored by JCBB (0 for the other modes).
    pub jcbb_nodes: usize,
    /// True when JCBB stopped at its node budget.
    pub jcbb_truncated: bool,
    /// Joint NIS of the hypothesis JCBB accepted (None for the other modes or no pairing).
    pub jcbb_joint_nis: Option<f64>,
    /// Bearing-only: tracks that initialized a feature in this frame (track, feature).
    pub initialized_tracks: Vec<(TrackId, FeatureId)>,
}

impl FrameReport {
    /// Number of associated observations.
    pub fn associated(&self) -> usize {
        self.outcomes
            .iter()
            .filter(|o| matches!(o, ObservationOutcome::Associated { .. }))
            .count()
    }
    /// Number of initialized features.
    pub fn initialized(&self) -> usize {
        self.outcomes
            .iter()
            .filter(|o| matches!(o, ObservationOutcome::Initialized { .. }))
            .count()
    }
    /// Number of observations stored with uninitialized tracks (bearing-only).
    pub fn stored(&self) -> usize {
        self.outcomes
            .iter()
            .filter(|o| matches!(o, ObservationOutcome::Stored { .. }))
            .count()
    }
    /// Number of rejected observations.
    pub fn rejected(&self) -> usize {
        self.outcomes
            .iter()
            .filter(|o| matches!(o, ObservationOutcome::Rejected(_)))
            .count()
    }
}

#[derive(Clone, Debug)]
struct VehicleSlot {
    model: ObservationModel,
    imu_noise: ImuNoise,
    /// Accumulated transition Φ = F_k⋯F_1 not yet applied to the cross-covariance.
    pending: SMatrix<f64, VEHICLE_DIM, VEHICLE_DIM>,
    has_pending: bool,
}

/// The inertial EKF-SLAM filter. See the module docs.
#[derive(Clone, Debug)]
pub struct SlamFilter {
    config: SlamConfig,
    /// The INS mechanization of `config.frame` and `config.local_gravity_mps2`.
    mechanization: ins::Mechanization,
    vehicles: Vec<VehicleSlot>,
    layout: Layout,
    x: Col<f64>,
    p: Mat<f64>,
    next_fresh: u64,
    /// χ² gate thresholds at `gate_probability`, index = degrees of freedom (0 unused).
    gates: Vec<f64>,
    /// Bumped whenever x_m or P_mm may change (updates, augmentation, fusion; not prediction).
    map_generation: u64,
    /// Y_mm = P_mm⁻¹, maintained through updates, augmentations and fusions
    /// (`info_cache` module), valid while its generation equals `map_generation`.
    info_cache: info_cache::InfoCache,
    /// Reserved row/column capacity of P (see `grow`).
    capacity: usize,
    /// Bearing-only tracks, stored observations and stored-pose bookkeeping.
    bearing: bearing::BearingState,
    /// Appearance of features and tracker links ([`AssociationMode::Appearance`]).
    appearance: appearance::AppearanceBook,
}

fn is_symmetric_pd(m: &SMatrix<f64, VEHICLE_DIM, VEHICLE_DIM>) -> bool {
    let sym = (m - m.transpose()).abs().max() <= 1e-12 * m.abs().max().max(f64::MIN_POSITIVE);
    sym && m.iter().all(|v| v.is_finite()) && m.cholesky().is_some()
}

/// Checks an estimate of vehicle `v` given to the filter (`what`: initial, start, restart):
/// a finite state and a symmetric positive definite covariance.
fn check_estimate(
    v: usize,
    state: &VehicleState,
    covariance: &VehicleCovariance,
    what: &str,
) -> Result<(), SlamError> {
    if !state.is_finite() {
        return Err(SlamError::InvalidConfig(format!(
            "vehicle {v}: non-finite {what} state"
        )));
    }
    if !is_symmetric_pd(covariance) {
        return Err(SlamError::InvalidConfig(format!(
            "vehicle {v}: {what} covariance is not symmetric positive definite"
        )));
    }
    Ok(())
}

/// Writes a vehicle's state and covariance block at offset `off` of `x` and `p`.
pub(crate) fn write_vehicle_block(
    x: &mut Col<f64>,
    p: &mut Mat<f64>,
    off: usize,
    state: &ins::VehicleVector,
    covariance: &VehicleCovariance,
) {
    for i in 0..VEHICLE_DIM {
        x[off + i] = state[i];
        for j in 0..VEHICLE_DIM {
            p[(off + i, off + j)] = covariance[(i, j)];
        }
    }
}

impl SlamFilter {
    /// A filter with the given vehicles and an empty map.
    pub fn new(config: SlamConfig, vehicles: &[VehicleSetup]) -> Result<Self, SlamError> {
        if vehicles.is_empty() {
            return Err(SlamError::InvalidConfig(
                "at least one vehicle is required".into(),
            ));
        }
        let p_gate = config.association.gate_probability;
        if !(p_gate > 0.0 && p_gate < 1.0) {
            return Err(SlamError::InvalidConfig(format!(
                "gate probability {p_gate} not in (0, 1)"
            )));
        }
        if !config.origin.iter().all(|v| v.is_finite()) {
            return Err(SlamError::InvalidConfig("origin is not finite".into()));
        }
        let mechanization = ins::Mechanization::new(config.frame, config.local_gravity_mps2)
            .map_err(|e| SlamError::InvalidConfig(e.to_string()))?;
        let layout = Layout::new(vehicles.len());
        let n = layout.dim();
        let mut x = Col::zeros(n);
        let mut p = Mat::zeros(n, n);
        let mut slots = Vec::with_capacity(vehicles.len());
        for (v, setup) in vehicles.iter().enumerate() {
            check_estimate(v, &setup.state, &setup.covariance, "initial")?;
            let off = layout.vehicle_block(v);
            write_vehicle_block(
                &mut x,
                &mut p,
                off,
                &setup.state.to_vector(),
                &setup.covariance,
            );
            slots.push(VehicleSlot {
                model: ObservationModel {
                    frame: config.frame,
                    sensor: setup.sensor,
                    mount: setup.mount,
                },
                imu_noise: setup.imu_noise,
                pending: SMatrix::identity(),
                has_pending: false,
            });
        }
        // Gate thresholds for the measurement sizes (2, 3); JCBB computes larger ones on demand.
        let mut gates = vec![f64::NAN];
        for dof in 1..=3 {
            gates.push(
                chi2_quantile(dof as f64, p_gate)
                    .map_err(|e| SlamError::InvalidConfig(e.to_string()))?,
            );
        }
        let pose_frame = triangulation::PoseFrame::new(config.frame, &config.origin);
        let bearing_only = vehicles
            .iter()
            .any(|v| !matches!(v.sensor, SensorModel::RangeBearing { .. }));
        if bearing_only && pose_frame.is_none() {
            return Err(SlamError::InvalidConfig(
                "bearing-only vehicles in global SLAM need the team origin (ECEF launch site) \
                 near the Earth's surface"
                    .into(),
            ));
        }
        Ok(Self {
            bearing: bearing::BearingState::new(pose_frame),
            appearance: appearance::AppearanceBook::default(),
            capacity: n,
            map_generation: 0,
            info_cache: info_cache::InfoCache::default(),
            config,
            mechanization,
            vehicles: slots,
            layout,
            x,
            p,
            next_fresh: 0,
            gates,
        })
    }

    /// Filter options.
    pub fn config(&self) -> &SlamConfig {
        &self.config
    }

    /// Navigation frame.
    pub fn frame(&self) -> NavFrame {
        self.config.frame
    }

    /// The INS mechanization of the filter's frame and gravity.
    pub fn mechanization(&self) -> &ins::Mechanization {
        &self.mechanization
    }

    /// Map-information origin o.
    pub fn origin(&self) -> Vector3<f64> {
        self.config.origin
    }

    /// The slot table.
    pub fn layout(&self) -> &Layout {
        &self.layout
    }

    /// State dimension n.
    pub fn dim(&self) -> usize {
        self.layout.dim()
    }

    /// Number of vehicle blocks.
    pub fn num_vehicles(&self) -> usize {
        self.vehicles.len()
    }

    /// Number of map features.
    pub fn num_features(&self) -> usize {
        self.layout.num_features()
    }

    /// The observation model of a vehicle.
    pub fn observation_model(&self, vehicle: usize) -> Result<&ObservationModel, SlamError> {
        self.vehicles
            .get(vehicle)
            .map(|v| &v.model)
            .ok_or(SlamError::UnknownVehicle(vehicle))
    }

    fn check_vehicle(&self, vehicle: usize) -> Result<usize, SlamError> {
        if vehicle < self.vehicles.len() {
            Ok(self.layout.vehicle_block(vehicle))
        } else {
            Err(SlamError::UnknownVehicle(vehicle))
        }
    }

    /// The vehicle's state estimate.
    pub fn vehicle_state(&self, vehicle: usize) -> Result<VehicleState, SlamError> {
        let off = self.check_vehicle(vehicle)?;
        Ok(VehicleState::from_vector(&ins::VehicleVector::from_fn(
            |i, _| self.x[off + i],
        )))
    }

    /// The vehicle's 15×15 covariance P_vv (always current).
    pub fn vehicle_covariance(&self, vehicle: usize) -> Result<VehicleCovariance, SlamError> {
        let off = self.check_vehicle(vehicle)?;
        Ok(VehicleCovariance::from_fn(|i, j| {
            self.p[(off + i, off + j)]
        }))
    }

    /// The vehicle's pose (position, Euler attitude).
    pub fn pose(&self, vehicle: usize) -> Result<(Vector3<f64>, Vector3<f64>), SlamError> {
        let s = self.vehicle_state(vehicle)?;
        Ok((s.position, s.attitude))
    }

    fn vec3_at(&self, off: usize) -> Vector3<f64> {
        Vector3::new(self.x[off], self.x[off + 1], self.x[off + 2])
    }

    fn mat3_at(&self, r: usize, c: usize) -> Matrix3<f64> {
        Matrix3::from_fn(|i, j| self.p[(r + i, c + j)])
    }

    /// Features (id, position) in state order.
    pub fn features(&self) -> Vec<(FeatureId, Vector3<f64>)> {
        self.layout
            .features()
            .map(|(id, off)| (id, self.vec3_at(off)))
            .collect()
    }

    /// One feature's position estimate.
    pub fn feature(&self, id: FeatureId) -> Option<Vector3<f64>> {
        self.layout.feature_offset(id).map(|off| self.vec3_at(off))
    }

    /// One feature's 3×3 covariance.
    pub fn feature_covariance(&self, id: FeatureId) -> Option<Matrix3<f64>> {
        self.layout
            .feature_offset(id)
            .map(|off| self.mat3_at(off, off))
    }

    /// The map marginal (x_m, P_mm) of eqs. 21.84/21.85 keyed by feature id, in state order.
    /// Map blocks are never stale, so this needs no flush.
    pub fn map_marginal(&self) -> MapMarginal {
        let feats: Vec<(FeatureId, usize)> = self.layout.features().collect();
        let k = feats.len() * 3;
        let idx: Vec<usize> = feats.iter().flat_map(|&(_, off)| off..off + 3).collect();
        MapMarginal {
            ids: feats.iter().map(|&(id, _)| id).collect(),
            mean: Col::from_fn(k, |i| self.x[idx[i]]),
            // Runs of consecutive state indices copy column slices (features are contiguous).
            covariance: fuse::gather(self.p.as_ref(), &idx, &idx),
        }
    }

    /// The map information (Y, y) = (P_mm⁻¹, P_mm⁻¹ (x_m − o)) of eqs. 21.86/21.87 with the
    /// origin convention of `info`, keyed by feature id in state order. The inverse is cached
    /// until the map changes, and a later fusion of a whole-map delta reuses it.
    pub fn map_information(&mut self) -> Result<MapInformation, SlamError> {
        let info = self.take_map_information()?;
        let out = info.clone();
        self.restore_map_information(info);
        Ok(out)
    }

    /// [`SlamFilter::map_information`] with the maintained Y itself as its matrix instead of a
    /// copy: the filter holds no map information until it gets it back
    /// ([`SlamFilter::restore_map_information`]); without that, the next round inverts P_mm
    /// afresh (the estimate is the same either way).
    pub fn take_map_information(&mut self) -> Result<MapInformation, SlamError> {
        let feats: Vec<(FeatureId, usize)> = self.layout.features().collect();
        let k = feats.len() * 3;
        let idx: Vec<usize> = feats.iter().flat_map(|&(_, off)| off..off + 3).collect();
        let ids: Vec<FeatureId> = feats.iter().map(|&(id, _)| id).collect();
        let mean = Col::from_fn(k, |i| self.x[idx[i]]);
        // P_mm as a view of P when the features are contiguous in the state (they are: vehicles,
        // features, stored poses), else gathered: no k×k copy per round.
        let gathered;
        let p_mm = match idx.first() {
            Some(&first) if idx.iter().enumerate().all(|(i, &s)| s == first + i) => {
                self.p.as_ref().submatrix(first, first, k, k)
            }
            _ => {
                gathered = fuse::gather(self.p.as_ref(), &idx, &idx);
                gathered.as_ref()
            }
        };
        let cached = self.checked_info(p_mm).is_some_and(|y| y.nrows() == k);
        // A stale cache is dropped before P_mm is inverted, not held beside the fresh inverse
        // (a k × k at the heap peak of tree-8's uav3: its capacity, with spare room, was 62 MB).
        let kept = self.info_cache.y.take().filter(|_| cached);
        let y = match kept {
            Some(y) => y,
            None => {
                let y = crate::info::spd_inverse(p_mm)
                    .map_err(|_| SlamError::NotPositiveDefinite("map covariance"))?;
                // Fresh: handed out now, kept when it comes back.
                self.info_cache = info_cache::InfoCache {
                    generation: self.map_generation,
                    y: None,
                    steps: 0,
                };
                y
            }
        };
        let o = self.config.origin;
        let centred = Col::from_fn(k, |i| mean[i] - o[i % 3]);
        let vector = &y * &centred;
        Ok(MapInformation {
            ids,
            origin: o,
            matrix: y,
            vector,
        })
    }

    /// Takes back what [`SlamFilter::take_map_information`] handed out, as the maintained map
    /// information, if the map has not changed since (same map generation, the same features
    /// in the same order); otherwise drops it.
    pub fn restore_map_information(&mut self, info: MapInformation) {
        let k = 3 * self.layout.num_features();
        if self.info_cache.y.is_none()
            && self.info_cache.generation == self.map_generation
            && info.matrix.nrows() == k
            && info.matrix.ncols() == k
            && info.ids.len() == self.layout.num_features()
            && self
                .layout
                .features()
                .zip(&info.ids)
                .all(|((id, _), other)| id == *other)
        {
            self.info_cache.y = Some(info.matrix);
        }
    }

    /// Drops the maintained map information, so the next [`SlamFilter::map_information`]
    /// inverts P_mm afresh (benchmarks compare both; the estimate is not affected).
    pub fn forget_map_information(&mut self) {
        self.info_cache = info_cache::InfoCache::default();
    }

    /// The full state vector x.
    pub fn state_vector(&self) -> Col<f64> {
        self.x.clone()
    }

    /// The full covariance P with any pending transitions applied (a copy; the filter keeps its
    /// lazy representation).
    pub fn joint_covariance(&self) -> Mat<f64> {
        let mut c = self.clone();
        c.flush();
        c.p
    }

    /// Applies every pending vehicle transition Φ to the cross-covariances (P_v· ← Φ P_v·).
    /// Changes only the representation, not the estimate.
    pub fn flush(&mut self) {
        for v in 0..self.vehicles.len() {
            self.flush_vehicle(v);
        }
    }

    fn flush_vehicle(&mut self, v: usize) {
        if !self.vehicles[v].has_pending {
            return;
        }
        let phi = self.vehicles[v].pending;
        let off = self.layout.vehicle_block(v);
        let n = self.dim();
        let phi_f = Mat::from_fn(VEHICLE_DIM, VEHICLE_DIM, |i, j| phi[(i, j)]);
        let rows = self.p.as_ref().submatrix(off, 0, VEHICLE_DIM, n).to_owned();
        let new_rows = &phi_f * &rows;
        for c in (0..n).filter(|c| !(off..off + VEHICLE_DIM).contains(c)) {
            for r in 0..VEHICLE_DIM {
                let val = new_rows[(r, c)];
                self.p[(off + r, c)] = val;
                self.p[(c, off + r)] = val;
            }
        }
        self.vehicles[v].pending = SMatrix::identity();
        self.vehicles[v].has_pending = false;
    }

    /// Zero-velocity pseudo-measurement of a vehicle known to be at rest (a static period of a
    /// real recording, used for the initial alignment): z = 0 = v + n, n ~ N(0, σ²I), a linear
    /// EKF update (eqs. 21.56–21.60 with H = [0 I 0] on the velocity; at rest on the Earth v^e = 0
    /// in global SLAM as v^n = 0 in local SLAM). Returns the NIS of the pseudo-measurement
    /// against the prior (3 dof). σ must be positive and finite; on any error nothing changes.
    pub fn zero_velocity_update(&mut self, vehicle: usize, sigma: f64) -> Result<f64, SlamError> {
        self.check_vehicle(vehicle)?;
        if !(sigma.is_finite() && sigma > 0.0) {
            return Err(SlamError::InvalidConfig(format!(
                "zero-velocity σ must be positive and finite, got {sigma}"
            )));
        }
        self.flush();
        let voff = self.layout.vehicle_block(vehicle) + crate::state::VEL;
        let v = self.vec3_at(voff);
        let s = Matrix3::from_fn(|i, j| self.p[(voff + i, voff + j)])
            + Matrix3::identity() * sigma * sigma;
        let nis = s
            .cholesky()
            .ok_or(SlamError::NotPositiveDefinite(
                "zero-velocity innovation covariance",
            ))?
            .solve(&v)
            .dot(&v);
        let block = update::HBlock {
            row: 0,
            col: voff,
            mat: Mat::identity(3, 3),
        };
        let nu = Col::from_fn(3, |i| -v[i]);
        self.bump_map_generation(false);
        let r = Mat::<f64>::identity(3, 3) * (sigma * sigma);
        self.blocks_update(&[block], &nu, r)?;
        Ok(nis)
    }

    /// Starts vehicle `vehicle` at `state` with `covariance`: how a team filter of data sharing
    /// learns a vehicle's initial estimate, from the first record of its stream
    /// (`crate::share`). Only a vehicle nothing has touched can be started: no prediction
    /// pending and its block exactly uncorrelated with every other state. Replacing its prior
    /// is then exact (that prior was never used). Anything else is an error that changes
    /// nothing.
    pub fn start_vehicle(
        &mut self,
        vehicle: usize,
        state: &VehicleState,
        covariance: &VehicleCovariance,
    ) -> Result<(), SlamError> {
        let off = self.check_vehicle(vehicle)?;
        check_estimate(vehicle, state, covariance, "start")?;
        let n = self.layout.dim();
        let touched = self.vehicles[vehicle].has_pending
            || (off..off + VEHICLE_DIM).any(|i| {
                (0..n).any(|j| !(off..off + VEHICLE_DIM).contains(&j) && self.p[(i, j)] != 0.0)
            });
        if touched {
            return Err(SlamError::InvalidConfig(format!(
                "vehicle {vehicle} cannot be started: it has been predicted or correlated"
            )));
        }
        write_vehicle_block(
            &mut self.x,
            &mut self.p,
            off,
            &state.to_vector(),
            covariance,
        );
        Ok(())
    }

    /// Restarts vehicle `vehicle` at `state` with `covariance`, independent of every other state:
    /// how a team filter of data sharing takes a restarted vehicle's new stream, whose start is
    /// an external fix (`crate::share`). The old state is marginalised out (its rows and columns
    /// dropped — exact in covariance form, and what it knew is given up, never counted twice)
    /// and the new one joins uncorrelated, so the joint covariance stays positive
    /// semi-definite. An invalid state or covariance is an error that changes nothing.
    pub fn restart_vehicle(
        &mut self,
        vehicle: usize,
        state: &VehicleState,
        covariance: &VehicleCovariance,
    ) -> Result<(), SlamError> {
        let off = self.check_vehicle(vehicle)?;
        check_estimate(vehicle, state, covariance, "restart")?;
        let n = self.layout.dim();
        for i in off..off + VEHICLE_DIM {
            for j in 0..n {
                if !(off..off + VEHICLE_DIM).contains(&j) {
                    self.p[(i, j)] = 0.0;
                    self.p[(j, i)] = 0.0;
                }
            }
        }
        let slot = &mut self.vehicles[vehicle];
        slot.pending = SMatrix::identity();
        slot.has_pending = false;
        // x_m and P_mm are unchanged (the map's information stays valid).
        write_vehicle_block(
            &mut self.x,
            &mut self.p,
            off,
            &state.to_vector(),
            covariance,
        );
        Ok(())
    }

    /// INS prediction of one vehicle over one IMU sample (eqs. 21.19–21.25 / 21.33–21.38 for the
    /// mean, 21.46/21.47 for the covariance, applied lazily to the cross terms; module docs).
    /// An invalid sample or a non-finite result is a typed error and changes nothing.
    pub fn predict(&mut self, vehicle: usize, imu: &ImuSample) -> Result<(), SlamError> {
        let off = self.check_vehicle(vehicle)?;
        let xv = self.vehicle_state(vehicle)?;
        let prop = ins::propagate_with_jacobians(&self.mechanization, &xv, imu)?;
        let q = ins::process_noise(&self.vehicles[vehicle].imu_noise, imu.dt);
        let pvv = self.vehicle_covariance(vehicle)?;
        let (f, g) = (prop.transition, prop.noise);
        let mut next = f * pvv * f.transpose() + g * q * g.transpose();
        next = (next + next.transpose()) * 0.5;
        let phi = f * self.vehicles[vehicle].pending;
        if !next.iter().chain(phi.iter()).all(|v| v.is_finite()) {
            return Err(SlamError::NumericalFailure("covariance prediction"));
        }
        let mut xn = prop.state.to_vector();
        // Keep roll and yaw in (−π, π] (C_b^n and E_b^n are 2π-periodic in them, so the
        // covariance is unaffected); pitch stays in its ±π/2 range by construction.
        xn[ATT] = wrap_angle(xn[ATT]);
        xn[ATT + 2] = wrap_angle(xn[ATT + 2]);
        write_vehicle_block(&mut self.x, &mut self.p, off, &xn, &next);
        let slot = &mut self.vehicles[vehicle];
        slot.pending = phi;
        slot.has_pending = true;
        Ok(())
    }

    /// χ² gate at `gate_probability` for `dof` degrees of freedom (cached).
    fn gate(&mut self, dof: usize) -> f64 {
        while self.gates.len() <= dof {
            let d = self.gates.len() as f64;
            let g =
                chi2_quantile(d, self.config.association.gate_probability).unwrap_or(f64::INFINITY);
            self.gates.push(g);
        }
        self.gates[dof]
    }

    /// A fresh feature id: the descriptor if unused, else the next id of this filter's reserved
    /// range.
    fn new_feature_id(&mut self, descriptor: FeatureId) -> FeatureId {
        // Tracker ids are not feature identities: features get this filter's own keys.
        let identities = !matches!(
            self.config.association.mode,
            AssociationMode::Appearance { .. }
        );
        if identities && !self.layout.has_feature(descriptor) {
            return descriptor;
        }
        loop {
            let id = FRESH_ID_BASE
                | (u64::from(self.config.fresh_id_namespace & 0x7FFF_FFFF) << 32)
                | (self.next_fresh & 0xFFFF_FFFF);
            self.next_fresh += 1;
            if !self.layout.has_feature(id) {
                return id;
            }
        }
    }

    /// Associates, updates and initializes from one terrain-sensor frame of `vehicle` (module
    /// docs). A non-finite frame time or an unknown vehicle is an error before anything changes.
    /// A refused measurement (wrong kind, NaN/∞, range ≤ 0, elevation beyond ±π/2, pixel outside
    /// the image) rejects only itself ([`RejectReason::InvalidMeasurement`]): the frame's other
    /// observations are processed exactly as if it were absent (a frame of refused measurements
    /// only is processed as an empty frame). Numerical failures of single observations
    /// are reported as [`RejectReason::NumericalFailure`].
    pub fn process_frame(
        &mut self,
        vehicle: usize,
        frame: &ObservationFrame,
    ) -> Result<FrameReport, SlamError> {
        self.check_vehicle(vehicle)?;
        if !frame.time.is_finite() {
            return Err(SlamError::NonFiniteTime);
        }
        let model = self.vehicles[vehicle].model;
        let mut zs = Vec::with_capacity(frame.observations.len());
        let mut valid = Vec::with_capacity(frame.observations.len());
        let mut outcomes = Vec::with_capacity(frame.observations.len());
        for o in &frame.observations {
            match model.measurement_vector(&o.z) {
                Ok(z) => {
                    zs.push(z);
                    valid.push(outcomes.len());
                    outcomes.push(ObservationOutcome::Rejected(RejectReason::NumericalFailure));
                }
                Err(e) => outcomes.push(ObservationOutcome::Rejected(
                    MeasurementFault::of(&e).map_or(RejectReason::DegenerateGeometry, |f| {
                        RejectReason::InvalidMeasurement(f)
                    }),
                )),
            }
        }
        self.flush();
        let descriptors: Vec<FeatureId> = valid
            .iter()
            .map(|&i| frame.observations[i].descriptor)
            .collect();
        let appearances: Vec<Option<crate::sensor::Appearance>> = valid
            .iter()
            .map(|&i| frame.observations[i].appearance)
            .collect();
        let plan = self.associate(vehicle, &model, &zs, &descriptors, &appearances);
        if !plan.updates.is_empty() || !plan.initializations.is_empty() {
            // The map changes below; updates and augmentations keep the cached Y_mm current.
            self.bump_map_generation(true);
        }
        let mut report = FrameReport {
            outcomes: plan.outcomes.clone(),
            jcbb_nodes: plan.jcbb_nodes,
            jcbb_truncated: plan.jcbb_truncated,
            jcbb_joint_nis: plan.jcbb_joint_nis,
            initialized_tracks: Vec::new(),
        };
        self.apply_updates(vehicle, &model, &plan.updates, &mut report);
        if !matches!(model.sensor, SensorModel::RangeBearing { .. }) {
            // Bearing-only: delayed initialization through stored poses and tracks (§21.4).
            let pipeline = match self.bearing.config.initialization {
                bearing::BearingInit::Pair => Self::process_bearing_observations,
                bearing::BearingInit::MultiView => Self::process_multiview_observations,
            };
            pipeline(
                self,
                vehicle,
                &model,
                frame.time,
                &zs,
                &descriptors,
                &plan.initializations,
                &mut report,
            );
        }
        for &i in plan
            .initializations
            .iter()
            .filter(|_| matches!(model.sensor, SensorModel::RangeBearing { .. }))
        {
            match self.initialize_feature(vehicle, &model, &zs[i], descriptors[i]) {
                Ok(id) => report.outcomes[i] = ObservationOutcome::Initialized { feature: id },
                Err(_) => {
                    report.outcomes[i] =
                        ObservationOutcome::Rejected(RejectReason::NumericalFailure)
                }
            }
        }
        if matches!(
            self.config.association.mode,
            AssociationMode::Appearance { .. }
        ) {
            for (k, o) in report.outcomes.iter().enumerate() {
                let (track, a) = (descriptors[k], &appearances[k]);
                match o {
                    ObservationOutcome::Associated { feature, .. }
                    | ObservationOutcome::Initialized { feature } => {
                        self.appearance.observed(vehicle, track, *feature, a)
                    }
                    ObservationOutcome::Stored { .. } => self.appearance.pending(vehicle, track, a),
                    ObservationOutcome::Rejected(_) => {}
                }
            }
            let layout = &self.layout;
            self.appearance.retain(|f| layout.has_feature(f));
        }
        // Back to the frame's indexing.
        for (k, &i) in valid.iter().enumerate() {
            outcomes[i] = report.outcomes[k];
        }
        report.outcomes = outcomes;
        Ok(report)
    }
}

#[cfg(test)]
mod bearing_tests;
#[cfg(test)]
mod tests;
