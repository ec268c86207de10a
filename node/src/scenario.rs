//! Scenario configuration: the `[world]` table and the `[[vehicle]]` array of a scenario TOML file.
//!
//! Every table is `deny_unknown_fields` (a typo is an error, not a silently ignored setting),
//! every field has a documented default unless it is marked *required*, and
//! [`Scenario::validate`] returns a typed [`ScenarioError::Invalid`] naming the offending field
//! (e.g. `vehicle[2].sensor.max_range_m`) and the reason. Units are part of the field names.
//!
//! Later issues add `[fusion]`, `[[link]]` and `[faults]` tables next to these; the top-level
//! [`Scenario`] is the only place that needs to grow.
//!
//! # Example
//! ```toml
//! [world]
//! seed = 7
//! earth_model = "wgs84"           # or "flat" (local SLAM)
//! origin = { lat_deg = -33.87, lon_deg = 151.21, height_m = 60.0 }
//! area = { size_north_m = 2400.0, size_east_m = 2400.0 }
//! features = { count = 400, max_height_above_ground_m = 10.0 }
//! terrain = { relief_m = 15.0 }
//!
//! [[vehicle]]
//! id = 1
//! name = "uav1"
//! trajectory = { altitude_m = 150.0, speed_mps = 25.0, shape = { kind = "orbit", radius_m = 500.0 } }
//! sensor = { model = { kind = "range_bearing", sigma_range_m = 0.5, sigma_bearing_deg = 0.2 } }
//! imu = { grade = "tactical", rate_hz = 100.0 }
//! ```

use std::path::{Path, PathBuf};

use canopy_fusion::imu::{ImuGrade, ImuNoise};
use canopy_fusion::sensor::{CameraIntrinsics, SensorModel, SensorMount};
use canopy_fusion::slam::{BearingConfig, BearingInit};
use canopy_fusion::state::NavFrame;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::world::SensorErrors;

pub use crate::network::{
    EventKind, EventSpec, FaultSpec, FusionConfig, FusionMode, LinkSpec, PartitionSpec, RunConfig,
    SecretsConfig, TransportKind,
};

/// A scenario's configuration error.
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// The scenario file could not be read.
    #[error("cannot read scenario {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The TOML did not parse or did not match the schema (unknown field, wrong type, …).
    #[error("scenario TOML: {0}")]
    Parse(#[from] toml::de::Error),
    /// An error in a scenario file (the file, then what is wrong in it).
    #[error("{path}: {error}")]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        error: Box<ScenarioError>,
    },
    /// A field holds a value that is out of range or inconsistent with another field.
    #[error("invalid `{field}`: {reason}")]
    Invalid {
        /// Dotted path of the field, e.g. `vehicle[2].sensor.max_range_m`.
        field: String,
        /// Why the value is rejected.
        reason: String,
    },
}

impl ScenarioError {
    /// An [`ScenarioError::Invalid`] for `field`.
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Invalid {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// Prefixes the field path of an [`ScenarioError::Invalid`] with `prefix.` (other variants are
    /// returned unchanged).
    pub fn within(self, prefix: &str) -> Self {
        match self {
            Self::Invalid { field, reason } => Self::Invalid {
                field: format!("{prefix}.{field}"),
                reason,
            },
            other => other,
        }
    }
}

/// A whole scenario: the world and its vehicles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    /// The simulated world (`[world]`). Defaults to [`WorldConfig::default`].
    #[serde(default)]
    pub world: WorldConfig,
    /// The vehicles (`[[vehicle]]`), at least one (*required*).
    #[serde(rename = "vehicle")]
    pub vehicles: Vec<VehicleConfig>,
    /// Duration, recording and pacing (`[run]`).
    #[serde(default)]
    pub run: RunConfig,
    /// Fusion architecture and parameters (`[fusion]`).
    #[serde(default)]
    pub fusion: FusionConfig,
    /// Links of the fusion network (`[[link]]`).
    #[serde(default, rename = "link", skip_serializing_if = "Vec::is_empty")]
    pub links: Vec<LinkSpec>,
    /// Network partitions (`[[partition]]`).
    #[serde(default, rename = "partition", skip_serializing_if = "Vec::is_empty")]
    pub partitions: Vec<PartitionSpec>,
    /// Crashes, restarts, hub loss (`[[event]]`).
    #[serde(default, rename = "event", skip_serializing_if = "Vec::is_empty")]
    pub events: Vec<EventSpec>,
    /// Credentials (`[secrets]`).
    #[serde(default)]
    pub secrets: SecretsConfig,
    /// zenoh deployment of a multi-host run (`[zenoh]`).
    #[serde(default, skip_serializing_if = "crate::deploy::zenoh_is_default")]
    pub zenoh: crate::deploy::ZenohDeploy,
    /// The hosts of a multi-host run and what each runs (`[[host]]`).
    #[serde(default, rename = "host", skip_serializing_if = "Vec::is_empty")]
    pub hosts: Vec<crate::deploy::HostSpec>,
}

impl Scenario {
    /// Parses and validates a scenario from TOML text.
    pub fn from_toml_str(text: &str) -> Result<Self, ScenarioError> {
        let scenario: Scenario = toml::from_str(text)?;
        scenario.validate()?;
        Ok(scenario)
    }

    /// Reads, parses and validates a scenario file.
    pub fn load(path: &Path) -> Result<Self, ScenarioError> {
        Self::load_with(path, true)
    }

    /// Reads and parses the resolved scenario of a run that its launcher has already
    /// validated in full ([`Scenario::load`]), as a role process does: every field check
    /// except building every vehicle's trajectory. Building them (arc-length tables, the
    /// bank-angle check) in each of N role processes made a run's start O(N²) in trigonometry
    /// (a sizable share of a 24- or 64-vehicle run's CPU); the world process builds each
    /// trajectory anyway, and fails with the same error if one cannot be built.
    pub fn load_prevalidated(path: &Path) -> Result<Self, ScenarioError> {
        Self::load_with(path, false)
    }

    fn load_with(path: &Path, trajectories: bool) -> Result<Self, ScenarioError> {
        let text = std::fs::read_to_string(path).map_err(|source| ScenarioError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let parsed = toml::from_str::<Scenario>(&text)
            .map_err(ScenarioError::from)
            .and_then(|mut s| {
                // Replay logs are named relative to the scenario file.
                let base = path.parent().unwrap_or(Path::new("."));
                for v in &mut s.vehicles {
                    if let Some(r) = v.replay.as_mut() {
                        r.resolve(base);
                    }
                }
                // So are the TLS files.
                if let Some(t) = s.zenoh.tls.as_mut() {
                    t.resolve(base);
                }
                s.validate_with(trajectories)?;
                Ok(s)
            });
        parsed.map_err(|error| ScenarioError::File {
            path: path.to_path_buf(),
            error: Box::new(error),
        })
    }

    /// The scenario as TOML text (round-trips through [`Scenario::from_toml_str`]).
    pub fn to_toml_string(&self) -> String {
        // Serialising plain data structs with string keys cannot fail.
        toml::to_string_pretty(self).expect("scenario serialises to TOML")
    }

    /// The built-in default: four UAVs surveying a 2 km × 2 km area around a launch site near
    /// Sydney at 120–180 m, range-bearing sensors looking down, tactical IMUs at 100 Hz, global
    /// (ECEF, rotating WGS-84 Earth) frame. Two lawnmowers split the area west/east, an orbit and a
    /// figure-eight cross both halves so that the vehicles' maps overlap.
    pub fn builtin_default() -> Self {
        let survey =
            |id: u32, east: f64, altitude: f64, phase: f64, first_leg: f64| VehicleConfig {
                id,
                name: Some(format!("uav{id}")),
                frame: None,
                trajectory: Some(TrajectoryConfig {
                    centre_ne_m: [0.0, east],
                    altitude_m: altitude,
                    speed_mps: 25.0,
                    phase,
                    heading_deg: first_leg,
                    shape: ShapeConfig::Lawnmower {
                        leg_length_m: 1800.0,
                        leg_spacing_m: 250.0,
                        legs: 4,
                        turn_ramp_fraction: default_turn_ramp_fraction(),
                    },
                    ..TrajectoryConfig::default()
                }),
                sensor: SensorConfig::default(),
                imu: ImuConfig::default(),
                initial: InitialConfig::default(),
                replay: None,
                bearing: BearingOptions::default(),
            };
        let mut orbit = survey(3, 0.0, 180.0, 0.25, 0.0);
        if let Some(t) = orbit.trajectory.as_mut() {
            t.shape = ShapeConfig::Orbit {
                radius_m: 650.0,
                clockwise: true,
            };
        }
        let mut eight = survey(4, 0.0, 140.0, 0.5, 45.0);
        if let Some(t) = eight.trajectory.as_mut() {
            t.shape = ShapeConfig::FigureEight {
                length_m: 1800.0,
                width_m: 900.0,
            };
        }
        Self {
            world: WorldConfig::default(),
            vehicles: vec![
                survey(1, -500.0, 120.0, 0.0, 0.0),
                survey(2, 500.0, 160.0, 0.5, 180.0),
                orbit,
                eight,
            ],
            run: RunConfig {
                name: Some("default (tree-4)".into()),
                ..RunConfig::default()
            },
            fusion: FusionConfig::default(),
            // A tree: uav3 (the orbit, crossing both halves) in the middle.
            links: [(1, 3), (2, 3), (3, 4)]
                .into_iter()
                .map(|(a, b)| LinkSpec {
                    a,
                    b,
                    transport: TransportKind::Shm,
                    listen: None,
                    byte_budget: None,
                    faults: FaultSpec::default(),
                    radio: None,
                })
                .collect(),
            partitions: Vec::new(),
            events: Vec::new(),
            secrets: SecretsConfig::default(),
            zenoh: Default::default(),
            hosts: Vec::new(),
        }
    }

    /// Checks every field and cross-field constraint (including ones that need the trajectory
    /// built, such as the bank angle its turns require).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        self.validate_with(true)
    }

    /// [`Scenario::validate`], building the trajectories only when `trajectories`.
    fn validate_with(&self, trajectories: bool) -> Result<(), ScenarioError> {
        self.world.validate().map_err(|e| e.within("world"))?;
        if self.vehicles.is_empty() {
            return Err(ScenarioError::invalid(
                "vehicle",
                "a scenario needs at least one [[vehicle]]",
            ));
        }
        let world_frame = self.world.earth_model.frame();
        for (i, v) in self.vehicles.iter().enumerate() {
            let prefix = format!("vehicle[{i}]");
            if trajectories {
                v.validate(world_frame)
            } else {
                v.validate_except_trajectory(world_frame)
            }
            .map_err(|e| e.within(&prefix))?;
            if v.id > crate::sim::MAX_VEHICLE_ID {
                return Err(ScenarioError::invalid(
                    format!("{prefix}.id"),
                    format!(
                        "must be at most {} (feature keys carry the vehicle id in 20 bits), got {}",
                        crate::sim::MAX_VEHICLE_ID,
                        v.id
                    ),
                ));
            }
            for (j, other) in self.vehicles[..i].iter().enumerate() {
                if other.id == v.id {
                    return Err(ScenarioError::invalid(
                        format!("{prefix}.id"),
                        format!("id {} is already used by vehicle[{j}]", v.id),
                    ));
                }
                if other.display_name() == v.display_name() {
                    return Err(ScenarioError::invalid(
                        format!("{prefix}.name"),
                        format!(
                            "name `{}` is already used by vehicle[{j}]",
                            v.display_name()
                        ),
                    ));
                }
            }
        }
        self.validate_frames()?;
        crate::network::validate(self)?;
        crate::deploy::validate(self)
    }

    /// `[world] frames = "own"`: local SLAM of simulated vehicles fusing decentralized (the
    /// alignment runs over the channel filters' links; global SLAM has ECEF as a frame every
    /// vehicle knows, a replayed vehicle's frame is its recording's).
    fn validate_frames(&self) -> Result<(), ScenarioError> {
        if self.world.frames != Frames::Own {
            return Ok(());
        }
        if self.world.earth_model != EarthModel::Flat {
            return Err(ScenarioError::invalid(
                "world.frames",
                "own frames need earth_model = \"flat\" (local SLAM); global SLAM shares ECEF",
            ));
        }
        if self.fusion.mode != crate::network::FusionMode::Decentralized {
            return Err(ScenarioError::invalid(
                "world.frames",
                "own frames need [fusion] mode = \"decentralized\" (vehicles align over their links)",
            ));
        }
        if let Some(i) = self.vehicles.iter().position(|v| v.replay.is_some()) {
            return Err(ScenarioError::invalid(
                format!("vehicle[{i}].replay"),
                "own frames are for simulated vehicles (a replayed vehicle's frame is its recording's)",
            ));
        }
        Ok(())
    }
}

/// The physics of the simulated world, which fixes the navigation frame of every vehicle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum EarthModel {
    /// Rotating WGS-84 Earth, normal gravity; vehicles run global (ECEF) SLAM.
    #[default]
    Wgs84,
    /// Flat, non-rotating world with constant gravity (`gravity_mps2`, default normal gravity at
    /// the launch site; the chapter's local-SLAM assumptions, §21.2.2.1); vehicles run local
    /// (launch-site NED) SLAM.
    Flat,
}

impl EarthModel {
    /// The navigation frame the vehicles of this world use.
    pub fn frame(self) -> NavFrame {
        match self {
            EarthModel::Wgs84 => NavFrame::Global,
            EarthModel::Flat => NavFrame::Local,
        }
    }
}

/// `[world]`: launch site, feature area, terrain and features.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorldConfig {
    /// Master seed of the run: terrain, features and (through [`crate::world::vehicle_seed`])
    /// every vehicle's noise streams derive from it. Default 1. TOML integers are limited to
    /// 0..2⁶³.
    pub seed: u64,
    /// Earth model, `"wgs84"` (global SLAM) or `"flat"` (local SLAM). Default `"wgs84"`.
    pub earth_model: EarthModel,
    /// Launch site: origin of the shared local NED frame. Default −33.87°, 151.21°, 60 m.
    pub origin: OriginConfig,
    /// Gravity of the flat world [m/s²] (`earth_model = "flat"` only), in [9.7, 9.9]: the
    /// simulated world's and the local-frame estimator's. Default: WGS-84 normal gravity
    /// (Somigliana, with the height correction) at `origin`'s latitude and height.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gravity_mps2: Option<f64>,
    /// The rectangle (in launch NED) where terrain features are scattered.
    pub area: AreaConfig,
    /// How many features and how high above the ground.
    pub features: FeatureConfig,
    /// The smooth seeded terrain surface the features sit on.
    pub terrain: TerrainConfig,
    /// What the sensors tell about a feature's identity (`[world.appearance]`).
    pub appearance: AppearanceConfig,
    /// Where the vehicles' estimates start (`earth_model = "flat"` only): `"shared"` (default:
    /// every vehicle in the launch frame, a frame the team shares by truth) or `"own"` (each
    /// vehicle in its own frame, its start position and heading; the vehicles align their
    /// frames from corresponding features, `crate::frames`).
    pub frames: Frames,
}

/// `[world] frames`: the frame each vehicle's estimate starts in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Frames {
    /// The launch frame, known to every vehicle (an oracle: the ablation of `Own`).
    #[default]
    Shared,
    /// Each vehicle's own start: origin at its true start position, north along its start
    /// heading. Nobody knows the others' starts.
    Own,
}

impl Default for WorldConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            earth_model: EarthModel::default(),
            origin: OriginConfig::default(),
            gravity_mps2: None,
            area: AreaConfig::default(),
            features: FeatureConfig::default(),
            terrain: TerrainConfig::default(),
            appearance: AppearanceConfig::default(),
            frames: Frames::Shared,
        }
    }
}

impl WorldConfig {
    /// Field checks of `[world]` (paths relative to `world`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let o = &self.origin;
        in_range(
            "origin.lat_deg",
            o.lat_deg,
            -85.0,
            85.0,
            "the local NED frame degenerates near the poles",
        )?;
        in_range("origin.lon_deg", o.lon_deg, -180.0, 180.0, "longitude")?;
        in_range(
            "origin.height_m",
            o.height_m,
            -500.0,
            10_000.0,
            "height above the ellipsoid",
        )?;
        if let Some(g) = self.gravity_mps2 {
            if self.earth_model != EarthModel::Flat {
                return Err(ScenarioError::invalid(
                    "gravity_mps2",
                    "applies to earth_model = \"flat\" only (the WGS-84 world has normal gravity \
                     at every position)",
                ));
            }
            in_range(
                "gravity_mps2",
                g,
                9.7,
                9.9,
                "gravity near the Earth's surface [m/s²] (normal gravity is 9.78–9.84)",
            )?;
        }
        let a = &self.area;
        finite("area.centre_north_m", a.centre_north_m)?;
        finite("area.centre_east_m", a.centre_east_m)?;
        positive_at_most("area.size_north_m", a.size_north_m, 200_000.0)?;
        positive_at_most("area.size_east_m", a.size_east_m, 200_000.0)?;
        let f = &self.features;
        match (f.count, f.density_per_km2) {
            (Some(_), Some(_)) => {
                return Err(ScenarioError::invalid(
                    "features",
                    "give either `count` or `density_per_km2`, not both",
                ));
            }
            (None, None) => {
                return Err(ScenarioError::invalid(
                    "features",
                    "give `count` or `density_per_km2`",
                ));
            }
            (Some(n), None) if n == 0 || n > MAX_FEATURES => {
                return Err(ScenarioError::invalid(
                    "features.count",
                    format!("must be in 1..={MAX_FEATURES}"),
                ));
            }
            (None, Some(d)) => positive_at_most("features.density_per_km2", d, 1e5)?,
            _ => {}
        }
        let n = self.feature_count();
        if n == 0 || n > MAX_FEATURES {
            return Err(ScenarioError::invalid(
                "features.density_per_km2",
                format!("gives {n} features over the area; must be in 1..={MAX_FEATURES}"),
            ));
        }
        non_negative_at_most(
            "features.max_height_above_ground_m",
            f.max_height_above_ground_m,
            1000.0,
        )?;
        let t = &self.terrain;
        non_negative_at_most("terrain.relief_m", t.relief_m, 2000.0)?;
        positive_at_most("terrain.min_wavelength_m", t.min_wavelength_m, 1e6)?;
        positive_at_most("terrain.max_wavelength_m", t.max_wavelength_m, 1e6)?;
        if t.max_wavelength_m < t.min_wavelength_m {
            return Err(ScenarioError::invalid(
                "terrain.max_wavelength_m",
                "must not be below terrain.min_wavelength_m",
            ));
        }
        if t.components == 0 || t.components > 4096 {
            return Err(ScenarioError::invalid(
                "terrain.components",
                "must be in 1..=4096",
            ));
        }
        self.appearance
            .validate()
            .map_err(|e| e.within("appearance"))
    }

    /// The launch site's gravity magnitude [m/s²]: `gravity_mps2`, or WGS-84 normal gravity at
    /// `origin` (the flat world's g).
    pub fn local_gravity(&self) -> f64 {
        self.gravity_mps2.unwrap_or_else(|| {
            canopy_fusion::geodesy::normal_gravity(
                self.origin.lat_deg.to_radians(),
                self.origin.height_m,
            )
        })
    }

    /// Number of features: `features.count`, or the density times the area, rounded.
    pub fn feature_count(&self) -> usize {
        match (self.features.count, self.features.density_per_km2) {
            (Some(n), _) => n,
            (None, Some(d)) => {
                let km2 = self.area.size_north_m * self.area.size_east_m * 1e-6;
                let n = (d * km2).round();
                if n.is_finite() && n >= 0.0 && n <= (MAX_FEATURES + 1) as f64 {
                    n as usize
                } else {
                    MAX_FEATURES + 1
                }
            }
            (None, None) => 0,
        }
    }
}

/// Upper bound on the number of features of a world (memory and per-frame search cost).
pub const MAX_FEATURES: usize = 1_000_000;

/// `[world.origin]`: the launch site, origin of the shared local NED frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OriginConfig {
    /// Geodetic latitude [deg], within ±85. Default −33.87.
    pub lat_deg: f64,
    /// Longitude [deg], within ±180. Default 151.21.
    pub lon_deg: f64,
    /// Height above the WGS-84 ellipsoid [m]. Default 60.
    pub height_m: f64,
}

impl Default for OriginConfig {
    fn default() -> Self {
        Self {
            lat_deg: -33.87,
            lon_deg: 151.21,
            height_m: 60.0,
        }
    }
}

/// `[world.area]`: rectangle of the launch NED frame (north × east) where features lie.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AreaConfig {
    /// North coordinate of the rectangle's centre [m]. Default 0.
    pub centre_north_m: f64,
    /// East coordinate of the rectangle's centre [m]. Default 0.
    pub centre_east_m: f64,
    /// North–south extent [m], > 0. Default 2400 (the 2 km survey plus a margin).
    pub size_north_m: f64,
    /// East–west extent [m], > 0. Default 2400.
    pub size_east_m: f64,
}

impl Default for AreaConfig {
    fn default() -> Self {
        Self {
            centre_north_m: 0.0,
            centre_east_m: 0.0,
            size_north_m: 2400.0,
            size_east_m: 2400.0,
        }
    }
}

/// `[world.features]`: give exactly one of `count` and `density_per_km2`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FeatureConfig {
    /// Number of features. Default 400 (≈ 70 per km², 5–8 in a default sensor's footprint).
    pub count: Option<usize>,
    /// Features per km² of the area (alternative to `count`).
    pub density_per_km2: Option<f64>,
    /// Features are objects standing on the terrain: each sits a uniform random height in
    /// [0, this] above the ground [m]. Default 10.
    pub max_height_above_ground_m: f64,
}

impl Default for FeatureConfig {
    fn default() -> Self {
        Self {
            count: Some(400),
            density_per_km2: None,
            max_height_above_ground_m: 10.0,
        }
    }
}

/// What the simulated sensors tell the estimators about which feature they see.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Identity {
    /// The observation's descriptor is the true feature id (the ablation of a perfect
    /// correspondence between all vehicles' maps; descriptor mismatches may be injected).
    Perfect,
    /// The descriptor is a per-vehicle tracker's short-lived track id and the observation
    /// carries a noisy 256-bit appearance descriptor ([`crate::world::appearance`]); the true
    /// id reaches only the monitor.
    Appearance,
}

impl std::fmt::Display for Identity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Perfect => "perfect",
            Self::Appearance => "appearance",
        })
    }
}

/// The identity model of every scenario that does not name one: simulated appearance, as real
/// sensors give (issue 12). `identity = "perfect"` is the named ablation.
pub const DEFAULT_IDENTITY: Identity = Identity::Appearance;

/// `[world.appearance]`: the identity model and, for `identity = "appearance"`, the
/// descriptors, their noise and the trackers (model in [`crate::world::appearance`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AppearanceConfig {
    /// `"perfect"` (descriptor = true id) or `"appearance"`. Default [`DEFAULT_IDENTITY`].
    pub identity: Identity,
    /// Share of the features whose descriptor is a near-copy of another feature's (repeated
    /// texture), in [0, 0.5]. Default 0.02.
    pub confusable_share: f64,
    /// Bits in which a confusable feature's descriptor differs from the one it copies, in
    /// [0, 256]. Default 8.
    pub confusable_bits: u32,
    /// Bit-flip probability of an observation's descriptor at the least range from the first
    /// viewpoint, in [0, 0.5]. Default 0.02.
    pub bit_flip_min: f64,
    /// Bit-flip probability at the sensor's maximum range or `viewpoint_full_deg` away from the
    /// first viewpoint, in [`bit_flip_min`, 0.5]. Default 0.10.
    pub bit_flip_max: f64,
    /// Change of viewpoint at which the descriptor noise reaches `bit_flip_max` [deg], in
    /// (0, 180]. Default 60.
    pub viewpoint_full_deg: f64,
    /// Probability per frame that a continuing track breaks (the tracker loses it), in
    /// [0, 1). Tracks also break when the feature is missed for a frame. Default 0.02.
    pub track_break_probability: f64,
    /// Largest descriptor distance [bits] of an association candidate. Default: the 99.9 %
    /// quantile of the distance between two noisy copies at `bit_flip_max`
    /// ([`crate::world::appearance::default_max_distance`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_distance: Option<u32>,
}

impl Default for AppearanceConfig {
    fn default() -> Self {
        Self {
            identity: DEFAULT_IDENTITY,
            confusable_share: 0.02,
            confusable_bits: 8,
            bit_flip_min: 0.02,
            bit_flip_max: 0.10,
            viewpoint_full_deg: 60.0,
            track_break_probability: 0.02,
            max_distance: None,
        }
    }
}

impl AppearanceConfig {
    /// Field checks (paths relative to `appearance`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        in_range(
            "confusable_share",
            self.confusable_share,
            0.0,
            0.5,
            "each confusable feature copies a distinct non-confusable one's descriptor",
        )?;
        if self.confusable_bits > crate::world::appearance::DESCRIPTOR_BITS {
            return Err(ScenarioError::invalid(
                "confusable_bits",
                format!("must be in 0..=256, got {}", self.confusable_bits),
            ));
        }
        in_range(
            "bit_flip_min",
            self.bit_flip_min,
            0.0,
            0.5,
            "a probability below ½ (at ½ the descriptor says nothing)",
        )?;
        in_range(
            "bit_flip_max",
            self.bit_flip_max,
            self.bit_flip_min,
            0.5,
            "a probability from bit_flip_min to ½",
        )?;
        positive_at_most("viewpoint_full_deg", self.viewpoint_full_deg, 180.0)?;
        if !(self.track_break_probability.is_finite()
            && (0.0..1.0).contains(&self.track_break_probability))
        {
            return Err(ScenarioError::invalid(
                "track_break_probability",
                format!("must be in [0, 1), got {}", self.track_break_probability),
            ));
        }
        if let Some(d) = self.max_distance {
            if self.identity == Identity::Perfect {
                return Err(ScenarioError::invalid(
                    "max_distance",
                    "applies to identity = \"appearance\" only",
                ));
            }
            if d > crate::world::appearance::DESCRIPTOR_BITS {
                return Err(ScenarioError::invalid(
                    "max_distance",
                    format!("must be in 0..=256, got {d}"),
                ));
            }
        }
        Ok(())
    }

    /// The association's largest candidate distance: `max_distance` or the default of the
    /// bit-flip model.
    pub fn association_distance(&self) -> u32 {
        self.max_distance
            .unwrap_or_else(|| crate::world::appearance::default_max_distance(self.bit_flip_max))
    }
}

/// `[world.terrain]`: a smooth seeded surface, a sum of `components` plane waves with random
/// directions and phases, wavelengths log-uniform in [min, max], amplitudes proportional to the
/// wavelength (equal slopes), scaled to the requested RMS height and shifted so the launch site is
/// at height 0.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TerrainConfig {
    /// RMS terrain height over the plane [m], ≥ 0 (0: flat ground). Default 15.
    pub relief_m: f64,
    /// Shortest wavelength [m], > 0. Default 150.
    pub min_wavelength_m: f64,
    /// Longest wavelength [m], ≥ min. Default 3000.
    pub max_wavelength_m: f64,
    /// Number of plane-wave components, 1..=4096. Default 24.
    pub components: usize,
}

impl Default for TerrainConfig {
    fn default() -> Self {
        Self {
            relief_m: 15.0,
            min_wavelength_m: 150.0,
            max_wavelength_m: 3000.0,
            components: 24,
        }
    }
}

/// `[[vehicle]]`: one UAV.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VehicleConfig {
    /// Unique vehicle id (*required*). Also selects the vehicle's random streams.
    pub id: u32,
    /// Unique name used in outputs and process names. Default `uav<id>`.
    #[serde(default)]
    pub name: Option<String>,
    /// Navigation frame; when given it must match the world's `earth_model` (`"global"` for
    /// `"wgs84"`, `"local"` for `"flat"`). Default: the world's.
    #[serde(default)]
    pub frame: Option<NavFrame>,
    /// Flight path (*required* for a simulated vehicle; a replayed vehicle has none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trajectory: Option<TrajectoryConfig>,
    /// Terrain sensor. Default [`SensorConfig::default`].
    #[serde(default)]
    pub sensor: SensorConfig,
    /// Inertial measurement unit. Default [`ImuConfig::default`].
    #[serde(default)]
    pub imu: ImuConfig,
    /// Initial estimate uncertainty. Default [`InitialConfig::default`].
    #[serde(default)]
    pub initial: InitialConfig,
    /// Replay this vehicle's sensor input from recorded logs instead of simulating it
    /// (`[vehicle.replay]`, see [`crate::replay`]); the trajectory, sensor noise and IMU errors
    /// are then not simulated, the sensor and IMU settings only describe the estimator's
    /// models, and the vehicle has no truth. Default: simulated.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replay: Option<crate::replay::ReplayConfig>,
    /// How a bearing-only or pixel sensor's tracks become map features (`[vehicle.bearing]`).
    /// Default: the chapter's two-ray initialization with the filter's defaults.
    #[serde(default, skip_serializing_if = "BearingOptions::is_default")]
    pub bearing: BearingOptions,
}

/// `[vehicle.bearing]`: bearing-only feature initialization (§21.4.2–21.4.3; the options of
/// [`BearingConfig`], angles in degrees). Every field is optional; an absent one keeps the
/// filter's default. For a bearing or pixel sensor only.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BearingOptions {
    /// `"pair"` (the chapter's two-ray triangulation behind a range-hypothesis gate; default)
    /// or `"multi_view"` (every stored ray at once, outlier tests, constraint updates from lost
    /// tracks; needs tracker ids as descriptors, as real feature trackers give).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub initialization: Option<BearingInit>,
    /// Rays of a track must span this angle before it initializes [deg]. Default 10.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_parallax_deg: Option<f64>,
    /// `multi_view`: stored rays a track needs before it initializes. Default 5.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_observations: Option<usize>,
    /// `multi_view`: least ray separation of a lost track for its constraint update [deg].
    /// Default 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub constraint_parallax_deg: Option<f64>,
    /// Rays missing each other by more than max(this, 3σ) are rejected [m]. Default 5.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_miss_distance_m: Option<f64>,
    /// Nearest range a feature may have [m] (and the nearest range hypothesis). Default 10.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_range_m: Option<f64>,
    /// Farthest range a feature may have [m]. Default 500.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_range_m: Option<f64>,
    /// `pair`: range hypotheses of a new track. Default 24.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub hypotheses: Option<usize>,
    /// Cap on stored poses in the state. Default 40.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_stored_poses: Option<usize>,
    /// A track not initialized this long after its first ray is dropped [s]. Default 30.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_track_age_s: Option<f64>,
    /// A track with this many stored rays that still cannot initialize is dropped. Default 40.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_track_observations: Option<usize>,
    /// σ of one observation's own error over the sensor's (equivalent white) σ, in (0, 1]:
    /// the outlier tests of single observations use it ([`BearingConfig::marginal_sigma_ratio`];
    /// `canopy import` writes σ/σ' of a time-correlated tracker error). Default 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub marginal_sigma_ratio: Option<f64>,
}

impl BearingOptions {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }

    /// The filter's options: the given fields over [`BearingConfig::default`].
    pub fn config(&self) -> BearingConfig {
        let d = BearingConfig::default();
        BearingConfig {
            min_parallax: self
                .min_parallax_deg
                .map_or(d.min_parallax, f64::to_radians),
            max_miss_distance: self.max_miss_distance_m.unwrap_or(d.max_miss_distance),
            hypotheses: self.hypotheses.unwrap_or(d.hypotheses),
            min_range: self.min_range_m.unwrap_or(d.min_range),
            max_range: self.max_range_m.unwrap_or(d.max_range),
            max_stored_poses: self.max_stored_poses.unwrap_or(d.max_stored_poses),
            max_track_age: self.max_track_age_s.unwrap_or(d.max_track_age),
            max_track_observations: self
                .max_track_observations
                .unwrap_or(d.max_track_observations),
            track_gate: d.track_gate,
            initialization: self.initialization.unwrap_or(d.initialization),
            min_observations: self.min_observations.unwrap_or(d.min_observations),
            constraint_parallax: self
                .constraint_parallax_deg
                .map_or(d.constraint_parallax, f64::to_radians),
            marginal_sigma_ratio: self.marginal_sigma_ratio.unwrap_or(d.marginal_sigma_ratio),
        }
    }

    /// Range checks (the filter's), for a vehicle whose sensor is `model`.
    pub fn validate(&self, model: &SensorModel) -> Result<(), ScenarioError> {
        if !self.is_default() && matches!(model, SensorModel::RangeBearing { .. }) {
            return Err(ScenarioError::invalid(
                "bearing",
                "applies to bearing and pixel sensors; this vehicle's sensor measures range",
            ));
        }
        self.config()
            .validate()
            .map_err(|e| ScenarioError::invalid("bearing", e.to_string()))
    }
}

impl VehicleConfig {
    /// The vehicle's name: `name`, or `uav<id>`.
    pub fn display_name(&self) -> String {
        self.name
            .clone()
            .unwrap_or_else(|| format!("uav{}", self.id))
    }

    /// Field checks of one vehicle (paths relative to the vehicle) in a world whose Earth model
    /// implies `world_frame`, including building the trajectory (bank-angle limit).
    pub fn validate(&self, world_frame: NavFrame) -> Result<(), ScenarioError> {
        self.validate_except_trajectory(world_frame)?;
        if let Some(t) = &self.trajectory {
            crate::world::trajectory::Trajectory::new(t).map_err(|e| e.within("trajectory"))?;
        }
        Ok(())
    }

    /// The flight path of a simulated vehicle (an error naming the field when it is missing).
    pub fn trajectory(&self) -> Result<&TrajectoryConfig, ScenarioError> {
        self.trajectory.as_ref().ok_or_else(|| {
            ScenarioError::invalid(
                "trajectory",
                "a simulated vehicle needs a trajectory (only a replayed vehicle has none)",
            )
        })
    }

    /// [`VehicleConfig::validate`] without building the trajectory (for callers that build it
    /// themselves and get its errors there).
    pub fn validate_except_trajectory(&self, world_frame: NavFrame) -> Result<(), ScenarioError> {
        if let Some(name) = &self.name
            && (name.is_empty()
                || !name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-'))
        {
            return Err(ScenarioError::invalid(
                "name",
                "must be non-empty ASCII letters, digits, `_` or `-` (it names files and services)",
            ));
        }
        if let Some(frame) = self.frame
            && frame != world_frame
        {
            return Err(ScenarioError::invalid(
                "frame",
                format!(
                    "`{frame}` does not match the world's earth_model, which implies `{world_frame}`"
                ),
            ));
        }
        match (&self.replay, &self.trajectory) {
            (None, None) => {
                self.trajectory()?;
            }
            (Some(_), Some(_)) => {
                return Err(ScenarioError::invalid(
                    "trajectory",
                    "a replayed vehicle is not simulated: leave its trajectory out",
                ));
            }
            _ => {}
        }
        self.imu.validate().map_err(|e| e.within("imu"))?;
        // A replayed vehicle's frames come when they were recorded: its rates are not tied.
        let tied_rate = self
            .replay
            .is_none()
            .then_some((self.imu.rate_hz, self.imu.timestamp_jitter_s));
        self.sensor
            .validate(tied_rate)
            .map_err(|e| e.within("sensor"))?;
        self.initial.validate().map_err(|e| e.within("initial"))?;
        self.bearing.validate(&self.sensor.model())?;
        if let Some(r) = &self.replay {
            r.validate().map_err(|e| e.within("replay"))?;
        }
        Ok(())
    }
}

/// `[vehicle.trajectory]`: the flight path, defined in the launch site's NED frame.
///
/// The horizontal pattern (`shape`) is laid out in a pattern frame whose x axis points along
/// `heading_deg` (clockwise from north) and is centred on `centre_ne_m`; the vehicle flies at
/// `altitude_m` above the launch site plus an optional sinusoidal climb. Attitude follows from
/// coordinated flight (see [`crate::world::trajectory`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrajectoryConfig {
    /// Pattern centre (north, east) in launch NED [m]. Default (0, 0).
    pub centre_ne_m: [f64; 2],
    /// Mean height above the launch site [m], > 0. Default 150.
    pub altitude_m: f64,
    /// Horizontal ground speed [m/s] in (0, 150], constant along every pattern. Default 25.
    pub speed_mps: f64,
    /// Start phase as a fraction of the pattern's period, in [0, 1). Default 0.
    pub phase: f64,
    /// Direction of the pattern's x axis (lawnmower legs, figure-eight long axis; where the orbit
    /// starts), clockwise from north [deg]. Default 0.
    pub heading_deg: f64,
    /// Amplitude of a sinusoidal altitude variation [m], ≥ 0 and below `altitude_m`. Default 0.
    pub climb_amplitude_m: f64,
    /// Period of that variation [s], > 0. Default 120.
    pub climb_period_s: f64,
    /// The horizontal pattern. Default: a lawnmower.
    pub shape: ShapeConfig,
}

impl Default for TrajectoryConfig {
    fn default() -> Self {
        Self {
            centre_ne_m: [0.0, 0.0],
            altitude_m: 150.0,
            speed_mps: 25.0,
            phase: 0.0,
            heading_deg: 0.0,
            climb_amplitude_m: 0.0,
            climb_period_s: 120.0,
            shape: ShapeConfig::default(),
        }
    }
}

/// `[vehicle.trajectory.shape]`: the horizontal pattern, tagged by `kind`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ShapeConfig {
    /// Survey pattern: `legs` parallel legs of `leg_length_m`, `leg_spacing_m` apart, joined by
    /// 180° turns whose curvature ramps smoothly in and out; flown back and forth over the legs
    /// (0, 1, …, n−1, n−2, …, 1, 0, …) so the pattern is periodic and revisits old ground. The
    /// turn size follows from the spacing; its bank angle must stay below 60°.
    Lawnmower {
        /// Length of each straight leg [m], > 0.
        leg_length_m: f64,
        /// Distance between adjacent legs [m], > 0.
        leg_spacing_m: f64,
        /// Number of legs, ≥ 2.
        legs: u32,
        /// Fraction of each turn's arc length spent ramping the curvature up (and the same
        /// fraction ramping it down), in (0, 0.5]. Default 0.4.
        #[serde(default = "default_turn_ramp_fraction")]
        turn_ramp_fraction: f64,
    },
    /// Circle of `radius_m` around the centre.
    Orbit {
        /// Radius [m], > 0.
        radius_m: f64,
        /// Clockwise seen from above (right turns). Default true.
        #[serde(default = "default_true")]
        clockwise: bool,
    },
    /// Lemniscate of Gerono x = L/2·sin θ, y = W/2·sin 2θ (pattern frame), flown at constant
    /// speed; it starts at the crossing heading along +x and +y.
    FigureEight {
        /// Extent along the pattern x axis [m], > 0.
        length_m: f64,
        /// Extent across [m], > 0.
        width_m: f64,
    },
}

impl Default for ShapeConfig {
    fn default() -> Self {
        ShapeConfig::Lawnmower {
            leg_length_m: 1800.0,
            leg_spacing_m: 250.0,
            legs: 5,
            turn_ramp_fraction: default_turn_ramp_fraction(),
        }
    }
}

fn default_turn_ramp_fraction() -> f64 {
    0.4
}

fn default_true() -> bool {
    true
}

/// Which way a sensor is mounted on the body.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum MountOrientation {
    /// Boresight along body z (down), image "down" towards the tail ([`SensorMount::downward`]).
    #[default]
    Down,
    /// Boresight along body x (forward): sensor frame = body frame.
    Forward,
}

/// `[vehicle.sensor]`: the terrain sensor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorConfig {
    /// Measurement model and noise. Default: range-bearing, σ 0.5 m and 0.2°.
    pub model: SensorModelConfig,
    /// Frame rate [Hz], > 0 (simulated vehicles: the IMU rate an integer multiple of it, or at
    /// most half the IMU rate, when frames fall between IMU samples; a replayed vehicle's frames
    /// come at their recorded times). Default 2.
    pub rate_hz: f64,
    /// Simulated vehicles: frame n is taken at n/`rate_hz` + this [s], in [0, 1/`rate_hz`): a
    /// camera not synchronised with the IMU, its frames between IMU samples. Default 0.
    pub time_offset_s: f64,
    /// Mounting orientation, `"down"` or `"forward"`. Default `"down"` unless
    /// `sensor_from_body` gives a general mount.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub orientation: Option<MountOrientation>,
    /// General mount: the rotation C_b^s (eq. 21.45) that maps body-frame vectors into the
    /// sensor frame (x along the boresight / optical axis, y right, z down in the image), as
    /// three rows. Orthonormal with determinant +1 (to 1e-6). Give this or `orientation`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sensor_from_body: Option<[[f64; 3]; 3]>,
    /// Lever arm p_sb^b: sensor origin from the centre of mass, body axes [m]. Default
    /// (0.3, 0, 0.1).
    pub lever_arm_m: [f64; 3],
    /// Features nearer than this are not seen [m], ≥ 0. Default 10.
    pub min_range_m: f64,
    /// Features farther than this are not seen [m], > min. Default 500.
    pub max_range_m: f64,
    /// Field of view: |azimuth| (eq. 21.41, atan(y^s/x^s)) at most this [deg], in (0, 90).
    /// Default 45. Pixel sensors must in addition project inside the image.
    pub half_fov_azimuth_deg: f64,
    /// Field of view: |elevation| (eq. 21.41) at most this [deg], in (0, 90). Default 45.
    pub half_fov_elevation_deg: f64,
    /// At most this many observations per frame, nearest first, ≥ 1. Default 8.
    pub max_observations: usize,
    /// Probability that an observation's descriptor is wrong, in [0, 1]. Default 0.
    pub mismatch_probability: f64,
    /// Of the wrong descriptors, the fraction that are random ids naming no feature (the rest
    /// name another, real feature), in [0, 1]. Default 0.5.
    pub mismatch_random_id_fraction: f64,
}

impl Default for SensorConfig {
    fn default() -> Self {
        Self {
            model: SensorModelConfig::default(),
            rate_hz: 2.0,
            time_offset_s: 0.0,
            orientation: None,
            sensor_from_body: None,
            lever_arm_m: [0.3, 0.0, 0.1],
            min_range_m: 10.0,
            max_range_m: 500.0,
            half_fov_azimuth_deg: 45.0,
            half_fov_elevation_deg: 45.0,
            max_observations: 8,
            mismatch_probability: 0.0,
            mismatch_random_id_fraction: 0.5,
        }
    }
}

impl SensorConfig {
    /// The estimator-facing sensor model.
    pub fn model(&self) -> SensorModel {
        self.model.model()
    }

    /// The estimator-facing mount (C_b^s and the lever arm of eq. 21.45).
    pub fn mount(&self) -> SensorMount {
        let lever = Vector3::from(self.lever_arm_m);
        if let Some(rows) = self.sensor_from_body {
            return SensorMount {
                sensor_from_body: Matrix3::from_fn(|r, c| rows[r][c]),
                lever_arm_body: lever,
            };
        }
        match self.orientation.unwrap_or_default() {
            MountOrientation::Down => SensorMount::downward(lever),
            MountOrientation::Forward => SensorMount {
                sensor_from_body: Matrix3::identity(),
                lever_arm_body: lever,
            },
        }
    }

    /// Field checks (paths relative to `sensor`); `imu`, when given (simulated vehicles: its
    /// rate [Hz] and timestamp jitter [s]), must put at most one frame in any IMU interval:
    /// frames on the samples (the IMU rate an integer multiple of the frame rate, no offset, no
    /// jitter), or a frame period of at least two nominal IMU periods (an interval is at most
    /// 1.5 of them with jitter ≤ Δt/4).
    pub fn validate(&self, imu: Option<(f64, f64)>) -> Result<(), ScenarioError> {
        self.model.validate().map_err(|e| e.within("model"))?;
        positive_at_most("rate_hz", self.rate_hz, 1000.0)?;
        let period = 1.0 / self.rate_hz;
        if !(self.time_offset_s.is_finite()
            && self.time_offset_s >= 0.0
            && self.time_offset_s < period)
        {
            return Err(ScenarioError::invalid(
                "time_offset_s",
                format!("must lie in [0, 1/rate_hz = {period}) s"),
            ));
        }
        if let Some((imu_rate_hz, jitter)) = imu {
            let ratio = imu_rate_hz / self.rate_hz;
            // Rates are user-typed decimals: 1e-9 relative slack absorbs their binary rounding
            // only.
            let on_samples = (ratio - ratio.round()).abs() <= 1e-9 * ratio
                && ratio.round() >= 1.0
                && self.time_offset_s == 0.0
                && jitter == 0.0;
            if !on_samples && ratio < 2.0 - 1e-9 {
                return Err(ScenarioError::invalid(
                    "rate_hz",
                    format!(
                        "frames between IMU samples (a frame rate that does not divide the IMU \
                         rate {imu_rate_hz} Hz, a time offset or timestamp jitter) need a frame \
                         rate of at most half the IMU rate"
                    ),
                ));
            }
        }
        if let Some(rows) = self.sensor_from_body {
            if self.orientation.is_some() {
                return Err(ScenarioError::invalid(
                    "sensor_from_body",
                    "give either `orientation` or `sensor_from_body`, not both",
                ));
            }
            validate_rotation("sensor_from_body", &rows)?;
        }
        for (i, l) in self.lever_arm_m.iter().enumerate() {
            in_range(&format!("lever_arm_m[{i}]"), *l, -100.0, 100.0, "lever arm")?;
        }
        non_negative_at_most("min_range_m", self.min_range_m, 1e6)?;
        positive_at_most("max_range_m", self.max_range_m, 1e6)?;
        if self.max_range_m <= self.min_range_m {
            return Err(ScenarioError::invalid(
                "max_range_m",
                "must exceed min_range_m",
            ));
        }
        for (name, v) in [
            ("half_fov_azimuth_deg", self.half_fov_azimuth_deg),
            ("half_fov_elevation_deg", self.half_fov_elevation_deg),
        ] {
            if !(v > 0.0 && v < 90.0) {
                return Err(ScenarioError::invalid(name, "must be in (0, 90) degrees"));
            }
        }
        if self.max_observations == 0 {
            return Err(ScenarioError::invalid(
                "max_observations",
                "must be at least 1",
            ));
        }
        in_range(
            "mismatch_probability",
            self.mismatch_probability,
            0.0,
            1.0,
            "a probability",
        )?;
        in_range(
            "mismatch_random_id_fraction",
            self.mismatch_random_id_fraction,
            0.0,
            1.0,
            "a fraction",
        )?;
        Ok(())
    }
}

/// `[vehicle.sensor.model]`: measurement kind and noise, tagged by `kind`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum SensorModelConfig {
    /// Range, azimuth, elevation (eq. 21.41).
    RangeBearing {
        /// Range noise σ [m], ≥ 0.
        sigma_range_m: f64,
        /// Azimuth and elevation noise σ [deg], ≥ 0.
        sigma_bearing_deg: f64,
    },
    /// Azimuth, elevation (eq. 21.42).
    Bearing {
        /// Azimuth and elevation noise σ [deg], ≥ 0.
        sigma_bearing_deg: f64,
    },
    /// Pinhole camera pixels (eq. 21.43).
    Pixel {
        /// Focal length along u [px], > 0.
        fu_px: f64,
        /// Focal length along v [px], > 0.
        fv_px: f64,
        /// Principal point u_0 [px].
        u0_px: f64,
        /// Principal point v_0 [px].
        v0_px: f64,
        /// Image width [px], > 0 (valid u in [0, width)).
        width_px: f64,
        /// Image height [px], > 0 (valid v in [0, height)).
        height_px: f64,
        /// Pixel noise σ [px], ≥ 0.
        sigma_px: f64,
    },
}

impl Default for SensorModelConfig {
    fn default() -> Self {
        SensorModelConfig::RangeBearing {
            sigma_range_m: 0.5,
            sigma_bearing_deg: 0.2,
        }
    }
}

impl SensorModelConfig {
    /// The simulated camera of the tests and examples: 640 × 480 px, 600 px focal length
    /// (±28° × ±22° field of view), principal point at the centre, σ `sigma_px`.
    pub fn vga_camera(sigma_px: f64) -> Self {
        SensorModelConfig::Pixel {
            fu_px: 600.0,
            fv_px: 600.0,
            u0_px: 320.0,
            v0_px: 240.0,
            width_px: 640.0,
            height_px: 480.0,
            sigma_px,
        }
    }

    /// The estimator-facing model (angles converted to radians).
    pub fn model(&self) -> SensorModel {
        match *self {
            SensorModelConfig::RangeBearing {
                sigma_range_m,
                sigma_bearing_deg,
            } => SensorModel::RangeBearing {
                sigma_range: sigma_range_m,
                sigma_bearing: sigma_bearing_deg.to_radians(),
            },
            SensorModelConfig::Bearing { sigma_bearing_deg } => SensorModel::Bearing {
                sigma_bearing: sigma_bearing_deg.to_radians(),
            },
            SensorModelConfig::Pixel {
                fu_px,
                fv_px,
                u0_px,
                v0_px,
                width_px,
                height_px,
                sigma_px,
            } => SensorModel::Pixel {
                camera: CameraIntrinsics {
                    fu: fu_px,
                    fv: fv_px,
                    u0: u0_px,
                    v0: v0_px,
                    width: width_px,
                    height: height_px,
                },
                sigma_pixel: sigma_px,
            },
        }
    }

    fn validate(&self) -> Result<(), ScenarioError> {
        match *self {
            SensorModelConfig::RangeBearing {
                sigma_range_m,
                sigma_bearing_deg,
            } => {
                non_negative_at_most("sigma_range_m", sigma_range_m, 1e4)?;
                non_negative_at_most("sigma_bearing_deg", sigma_bearing_deg, 30.0)?;
            }
            SensorModelConfig::Bearing { sigma_bearing_deg } => {
                non_negative_at_most("sigma_bearing_deg", sigma_bearing_deg, 30.0)?;
            }
            SensorModelConfig::Pixel {
                fu_px,
                fv_px,
                u0_px,
                v0_px,
                width_px,
                height_px,
                sigma_px,
            } => {
                positive_at_most("fu_px", fu_px, 1e6)?;
                positive_at_most("fv_px", fv_px, 1e6)?;
                positive_at_most("width_px", width_px, 1e6)?;
                positive_at_most("height_px", height_px, 1e6)?;
                finite("u0_px", u0_px)?;
                finite("v0_px", v0_px)?;
                non_negative_at_most("sigma_px", sigma_px, 1e3)?;
            }
        }
        Ok(())
    }
}

/// How the noise-free IMU sample of an interval (t_{k−1}, t_k] is synthesised from the truth
/// (`world::imu` module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ImuSynthesis {
    /// The exact coning- and sculling-compensated increments of the analytic motion (what a
    /// navigation IMU delivers), computed without any discrete mechanization.
    #[default]
    Exact,
    /// Ablation (an oracle): invert the estimator's own discrete mechanization on the truth at
    /// t_{k−1} and t_k, so a perfect IMU reproduces the true velocity and attitude exactly through
    /// that mechanization and its truncation errors are hidden.
    Discrete,
    /// Ablation: the continuous-time specific force and body rate at the interval midpoint, an
    /// IMU without coning/sculling compensation.
    Continuous,
}

/// Which error model the simulated IMU draws its errors from (`[vehicle.imu.truth] model`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ImuTruthModel {
    /// A sensor error model that differs from the estimator's (fields of
    /// [`ImuTruthConfig`], defaults from the grade).
    #[default]
    Sensor,
    /// Ablation (an oracle): exactly the estimator's own model (white noise, turn-on bias, random
    /// walk of `[vehicle.imu]`'s grade or `noise`), nothing else.
    Filter,
}

/// `[vehicle.imu.truth]`: the simulated sensor's errors — the world's truth, which the estimator
/// does not know (it assumes the model of `grade` or `[vehicle.imu.noise]`). With `model =
/// "sensor"` (the default) the IMU has white noise, a turn-on bias, a first-order Gauss–Markov
/// bias instability, a bias random walk, and per-axis scale-factor and misalignment errors drawn
/// at turn-on; every field is optional and defaults from the estimator's model and the grade
/// ([`ImuConfig::truth_errors`]) to errors the estimator's process noise covers. `model =
/// "filter"` draws exactly the estimator's model (an oracle for ablation) and takes no other
/// field. Densities and σ in the units of `[vehicle.imu.noise]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields, default)]
pub struct ImuTruthConfig {
    /// `"sensor"` (default) or `"filter"`.
    pub model: ImuTruthModel,
    /// Accelerometer white-noise density [m/s²/√Hz]. Default: the estimator's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_noise_density: Option<f64>,
    /// Gyro white-noise density [rad/s/√Hz]. Default: the estimator's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gyro_noise_density: Option<f64>,
    /// 1-σ turn-on accelerometer bias [m/s²]. Default: the estimator's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_bias_sigma: Option<f64>,
    /// 1-σ turn-on gyro bias [rad/s]. Default: the estimator's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gyro_bias_sigma: Option<f64>,
    /// Stationary 1-σ of the accelerometer's Gauss–Markov bias instability [m/s²]. Default:
    /// the estimator's bias random-walk density × √(τ/2), so that over times ≪ τ it drifts like
    /// the random walk the estimator assumes, and stays bounded beyond.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_bias_instability: Option<f64>,
    /// Stationary 1-σ of the gyro's Gauss–Markov bias instability [rad/s]. Default as for the
    /// accelerometer.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gyro_bias_instability: Option<f64>,
    /// Correlation time τ of the Gauss–Markov biases [s], in (0, 1e7]. Default 600.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bias_correlation_time_s: Option<f64>,
    /// Accelerometer bias random-walk density [m/s³/√Hz]. Default 0 (the instability drifts).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_bias_rw_density: Option<f64>,
    /// Gyro bias random-walk density [rad/s²/√Hz]. Default 0.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gyro_bias_rw_density: Option<f64>,
    /// 1-σ per-axis accelerometer scale-factor error [ppm], ≤ 1e5. Default by grade:
    /// navigation 10, tactical 100, consumer 1000.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_scale_factor_ppm: Option<f64>,
    /// 1-σ per-axis gyro scale-factor error [ppm], ≤ 1e5. Default by grade: navigation 1,
    /// tactical 10, consumer 100.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gyro_scale_factor_ppm: Option<f64>,
    /// 1-σ of each of the six accelerometer axis-misalignment terms [mrad], ≤ 100. Default by
    /// grade: navigation 0.01, tactical 0.05, consumer 0.5.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub accel_misalignment_mrad: Option<f64>,
    /// 1-σ of each of the six gyro axis-misalignment terms [mrad], ≤ 100. Default by grade:
    /// navigation 0.001, tactical 0.01, consumer 0.1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gyro_misalignment_mrad: Option<f64>,
}

impl ImuTruthConfig {
    /// The optional fields by name (for validation messages).
    fn fields(&self) -> [(&'static str, Option<f64>); 13] {
        [
            ("accel_noise_density", self.accel_noise_density),
            ("gyro_noise_density", self.gyro_noise_density),
            ("accel_bias_sigma", self.accel_bias_sigma),
            ("gyro_bias_sigma", self.gyro_bias_sigma),
            ("accel_bias_instability", self.accel_bias_instability),
            ("gyro_bias_instability", self.gyro_bias_instability),
            ("bias_correlation_time_s", self.bias_correlation_time_s),
            ("accel_bias_rw_density", self.accel_bias_rw_density),
            ("gyro_bias_rw_density", self.gyro_bias_rw_density),
            ("accel_scale_factor_ppm", self.accel_scale_factor_ppm),
            ("gyro_scale_factor_ppm", self.gyro_scale_factor_ppm),
            ("accel_misalignment_mrad", self.accel_misalignment_mrad),
            ("gyro_misalignment_mrad", self.gyro_misalignment_mrad),
        ]
    }

    /// Field checks (paths relative to `truth`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        for (name, value) in self.fields() {
            let Some(v) = value else { continue };
            if self.model == ImuTruthModel::Filter {
                return Err(ScenarioError::invalid(
                    name,
                    "applies to model = \"sensor\" only (\"filter\" draws exactly the estimator's model)",
                ));
            }
            match name {
                "bias_correlation_time_s" => positive_at_most(name, v, 1e7)?,
                "accel_scale_factor_ppm" | "gyro_scale_factor_ppm" => {
                    non_negative_at_most(name, v, 1e5)?
                }
                "accel_misalignment_mrad" | "gyro_misalignment_mrad" => {
                    non_negative_at_most(name, v, 100.0)?
                }
                _ => non_negative_at_most(name, v, 100.0)?,
            }
        }
        Ok(())
    }
}

/// Default correlation time of the truth model's Gauss–Markov biases [s].
pub const DEFAULT_BIAS_CORRELATION_TIME_S: f64 = 600.0;

/// Default (gyro scale factor [ppm], accelerometer scale factor [ppm], gyro misalignment
/// [mrad], accelerometer misalignment [mrad]) of the `sensor` truth model by grade. Chosen within
/// what the estimator's process noise covers on the shipped scenarios: a 180° turn picks up
/// π × (gyro scale factor) of heading error, 3e-5 rad for tactical, below the 6e-5 rad that the
/// tactical gyro's white noise adds over a 20 s turn; the accelerometer terms act on the ≈ 1 g
/// specific force as a bias well inside the turn-on σ (1 mg tactical: 100 ppm and 0.05 mrad
/// give 0.1 and 0.05 mg).
fn calibration_defaults(grade: ImuGrade) -> [f64; 4] {
    match grade {
        ImuGrade::Navigation => [1.0, 10.0, 0.001, 0.01],
        ImuGrade::Tactical => [10.0, 100.0, 0.01, 0.05],
        ImuGrade::Consumer => [100.0, 1000.0, 0.1, 0.5],
        ImuGrade::Perfect => [0.0; 4],
    }
}

/// `[vehicle.imu]`: grade, rate, synthesis, the estimator's error model and the sensor's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ImuConfig {
    /// Named grade (`navigation`, `tactical`, `consumer`, `perfect`): the estimator's error
    /// model and the defaults of the simulated sensor's (`truth`). Default `tactical`.
    pub grade: ImuGrade,
    /// Sample rate [Hz], in (0, 10000]. Default 100.
    pub rate_hz: f64,
    /// Noise-free sample synthesis. Default `exact`.
    pub synthesis: ImuSynthesis,
    /// Simulated vehicles: sample k is stamped k/`rate_hz` + U(−j, j) and measures its actual
    /// interval (a real IMU's clock jitter) [s], in [0, 1/(4·`rate_hz`)]. Default 0.
    pub timestamp_jitter_s: f64,
    /// Replaces the grade's noise figures in the estimator's model when given.
    pub noise: Option<ImuNoiseConfig>,
    /// The simulated sensor's errors (`[vehicle.imu.truth]`). Default: the `sensor` model with
    /// its defaults.
    pub truth: ImuTruthConfig,
}

impl Default for ImuConfig {
    fn default() -> Self {
        Self {
            grade: ImuGrade::Tactical,
            rate_hz: 100.0,
            synthesis: ImuSynthesis::Exact,
            timestamp_jitter_s: 0.0,
            noise: None,
            truth: ImuTruthConfig::default(),
        }
    }
}

impl ImuConfig {
    /// The simulated sensor's error model: `truth` resolved against the estimator's model
    /// ([`ImuConfig::noise_model`]) and the grade's defaults ([`ImuTruthConfig`]).
    pub fn truth_errors(&self) -> SensorErrors {
        let filter = self.noise_model();
        let t = &self.truth;
        if t.model == ImuTruthModel::Filter {
            return SensorErrors::filter_model(&filter);
        }
        let tau = t
            .bias_correlation_time_s
            .unwrap_or(DEFAULT_BIAS_CORRELATION_TIME_S);
        let [gyro_sf, accel_sf, gyro_mis, accel_mis] = calibration_defaults(self.grade);
        SensorErrors {
            accel_noise_density: t.accel_noise_density.unwrap_or(filter.accel_noise_density),
            gyro_noise_density: t.gyro_noise_density.unwrap_or(filter.gyro_noise_density),
            accel_bias_sigma: t.accel_bias_sigma.unwrap_or(filter.accel_bias_sigma),
            gyro_bias_sigma: t.gyro_bias_sigma.unwrap_or(filter.gyro_bias_sigma),
            accel_bias_instability: t
                .accel_bias_instability
                .unwrap_or(filter.accel_bias_rw_density * (0.5 * tau).sqrt()),
            gyro_bias_instability: t
                .gyro_bias_instability
                .unwrap_or(filter.gyro_bias_rw_density * (0.5 * tau).sqrt()),
            bias_correlation_time: tau,
            accel_bias_rw_density: t.accel_bias_rw_density.unwrap_or(0.0),
            gyro_bias_rw_density: t.gyro_bias_rw_density.unwrap_or(0.0),
            accel_scale_factor: t.accel_scale_factor_ppm.unwrap_or(accel_sf) * 1e-6,
            gyro_scale_factor: t.gyro_scale_factor_ppm.unwrap_or(gyro_sf) * 1e-6,
            accel_misalignment: t.accel_misalignment_mrad.unwrap_or(accel_mis) * 1e-3,
            gyro_misalignment: t.gyro_misalignment_mrad.unwrap_or(gyro_mis) * 1e-3,
        }
    }

    /// The estimator's noise model: the override, or the grade's.
    pub fn noise_model(&self) -> ImuNoise {
        match &self.noise {
            Some(n) => ImuNoise {
                accel_noise_density: n.accel_noise_density,
                gyro_noise_density: n.gyro_noise_density,
                accel_bias_rw_density: n.accel_bias_rw_density,
                gyro_bias_rw_density: n.gyro_bias_rw_density,
                accel_bias_sigma: n.accel_bias_sigma,
                gyro_bias_sigma: n.gyro_bias_sigma,
            },
            None => self.grade.noise(),
        }
    }

    /// Field checks (paths relative to `imu`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        positive_at_most("rate_hz", self.rate_hz, 10_000.0)?;
        non_negative_at_most(
            "timestamp_jitter_s",
            self.timestamp_jitter_s,
            0.25 / self.rate_hz,
        )?;
        if let Some(n) = &self.noise {
            for (name, v) in [
                ("noise.accel_noise_density", n.accel_noise_density),
                ("noise.gyro_noise_density", n.gyro_noise_density),
                ("noise.accel_bias_rw_density", n.accel_bias_rw_density),
                ("noise.gyro_bias_rw_density", n.gyro_bias_rw_density),
                ("noise.accel_bias_sigma", n.accel_bias_sigma),
                ("noise.gyro_bias_sigma", n.gyro_bias_sigma),
            ] {
                non_negative_at_most(name, v, 100.0)?;
            }
        }
        self.truth.validate().map_err(|e| e.within("truth"))
    }
}

/// `[vehicle.imu.noise]`: explicit noise figures (all required when the table is present);
/// see [`ImuNoise`] for units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImuNoiseConfig {
    /// Accelerometer white-noise density [m/s²/√Hz].
    pub accel_noise_density: f64,
    /// Gyro white-noise density [rad/s/√Hz].
    pub gyro_noise_density: f64,
    /// Accelerometer bias random-walk density [m/s³/√Hz].
    pub accel_bias_rw_density: f64,
    /// Gyro bias random-walk density [rad/s²/√Hz].
    pub gyro_bias_rw_density: f64,
    /// 1-σ turn-on accelerometer bias [m/s²].
    pub accel_bias_sigma: f64,
    /// 1-σ turn-on gyro bias [rad/s].
    pub gyro_bias_sigma: f64,
}

/// `[vehicle.initial]`: the initial estimate's uncertainty. It sets the estimator's initial
/// covariance and, with `draw_offset`, the distribution the initial truth-minus-estimate offset is
/// drawn from (so the initial error is consistent with the covariance). Bias uncertainty comes
/// from the IMU's turn-on σ.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InitialConfig {
    /// Position σ along the vehicle's local north, east, down [m], ≥ 0. Default (2, 2, 3).
    pub position_sigma_m: [f64; 3],
    /// Velocity σ along north, east, down [m/s], ≥ 0. Default (0.1, 0.1, 0.1).
    pub velocity_sigma_mps: [f64; 3],
    /// Roll, pitch, yaw σ [deg], ≥ 0. Default (0.2, 0.2, 0.5).
    pub attitude_sigma_deg: [f64; 3],
    /// Draw the initial estimate's offset from these σ (otherwise the estimate starts at the
    /// truth, with the same covariance). Default true.
    pub draw_offset: bool,
}

impl Default for InitialConfig {
    fn default() -> Self {
        Self {
            position_sigma_m: [2.0, 2.0, 3.0],
            velocity_sigma_mps: [0.1, 0.1, 0.1],
            attitude_sigma_deg: [0.2, 0.2, 0.5],
            draw_offset: true,
        }
    }
}

impl InitialConfig {
    /// Field checks (paths relative to `initial`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        for i in 0..3 {
            non_negative_at_most(
                &format!("position_sigma_m[{i}]"),
                self.position_sigma_m[i],
                1e5,
            )?;
            non_negative_at_most(
                &format!("velocity_sigma_mps[{i}]"),
                self.velocity_sigma_mps[i],
                1e3,
            )?;
            non_negative_at_most(
                &format!("attitude_sigma_deg[{i}]"),
                self.attitude_sigma_deg[i],
                30.0,
            )?;
        }
        Ok(())
    }
}

/// Largest deviation from orthonormality accepted in a configured rotation matrix: rows typed
/// with 7 significant digits (or more) are orthonormal to about 1e-7.
pub const ROTATION_TOLERANCE: f64 = 1e-6;

/// A rotation matrix check: finite, orthonormal (|R Rᵀ − I| ≤ [`ROTATION_TOLERANCE`]) and
/// proper (det +1, not a reflection).
pub fn validate_rotation(field: &str, rows: &[[f64; 3]; 3]) -> Result<(), ScenarioError> {
    let r = Matrix3::from_fn(|i, j| rows[i][j]);
    if !r.iter().all(|v| v.is_finite()) {
        return Err(ScenarioError::invalid(field, "has a non-finite entry"));
    }
    let err = (r * r.transpose() - Matrix3::identity()).abs().max();
    if err > ROTATION_TOLERANCE {
        return Err(ScenarioError::invalid(
            field,
            format!(
                "is not orthonormal: |R·Rᵀ − I| = {err:.3e} > {ROTATION_TOLERANCE:e} (rows are C_b^s)"
            ),
        ));
    }
    let det = r.determinant();
    if det < 0.0 {
        return Err(ScenarioError::invalid(
            field,
            format!("is a reflection (det = {det:.6}), not a rotation"),
        ));
    }
    Ok(())
}

/// Finite value check.
pub(crate) fn finite(field: &str, v: f64) -> Result<(), ScenarioError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(ScenarioError::invalid(
            field,
            format!("must be finite, got {v}"),
        ))
    }
}

/// `lo ≤ v ≤ hi` (finite) check.
pub(crate) fn in_range(
    field: &str,
    v: f64,
    lo: f64,
    hi: f64,
    what: &str,
) -> Result<(), ScenarioError> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(ScenarioError::invalid(
            field,
            format!("{what}: must be in [{lo}, {hi}], got {v}"),
        ))
    }
}

/// `0 < v ≤ hi` check.
pub(crate) fn positive_at_most(field: &str, v: f64, hi: f64) -> Result<(), ScenarioError> {
    if v.is_finite() && v > 0.0 && v <= hi {
        Ok(())
    } else {
        Err(ScenarioError::invalid(
            field,
            format!("must be positive and at most {hi}, got {v}"),
        ))
    }
}

/// `0 ≤ v ≤ hi` check.
pub(crate) fn non_negative_at_most(field: &str, v: f64, hi: f64) -> Result<(), ScenarioError> {
    if v.is_finite() && (0.0..=hi).contains(&v) {
        Ok(())
    } else {
        Err(ScenarioError::invalid(
            field,
            format!("must be in [0, {hi}], got {v}"),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The example of the module documentation, verbatim.
    const DOC_EXAMPLE: &str = r#"
[world]
seed = 7
earth_model = "wgs84"           # or "flat" (local SLAM)
origin = { lat_deg = -33.87, lon_deg = 151.21, height_m = 60.0 }
area = { size_north_m = 2400.0, size_east_m = 2400.0 }
features = { count = 400, max_height_above_ground_m = 10.0 }
terrain = { relief_m = 15.0 }

[[vehicle]]
id = 1
name = "uav1"
trajectory = { altitude_m = 150.0, speed_mps = 25.0, shape = { kind = "orbit", radius_m = 500.0 } }
sensor = { model = { kind = "range_bearing", sigma_range_m = 0.5, sigma_bearing_deg = 0.2 } }
imu = { grade = "tactical", rate_hz = 100.0 }
"#;

    /// A small valid two-vehicle scenario in table syntax, edited by the rejection tests.
    const BASE: &str = r#"
[world]
seed = 3
earth_model = "flat"

[fusion]
mode = "isolated"

[[vehicle]]
id = 1
[vehicle.trajectory]
altitude_m = 120
[vehicle.trajectory.shape]
kind = "figure_eight"
length_m = 1500
width_m = 700
[vehicle.sensor]
rate_hz = 4
max_range_m = 400
[vehicle.sensor.model]
kind = "pixel"
fu_px = 400
fv_px = 400
u0_px = 320
v0_px = 240
width_px = 640
height_px = 480
sigma_px = 1

[[vehicle]]
id = 2
name = "scout"
frame = "local"
[vehicle.trajectory.shape]
kind = "lawnmower"
leg_length_m = 1000
leg_spacing_m = 200
legs = 3
[vehicle.imu]
grade = "consumer"
rate_hz = 200
synthesis = "continuous"
"#;

    #[test]
    fn doc_example_and_table_syntax_parse_with_defaults() {
        let s = Scenario::from_toml_str(DOC_EXAMPLE).unwrap();
        assert_eq!(s.world.seed, 7);
        assert_eq!(s.vehicles[0].imu.rate_hz, 100.0);
        assert_eq!(s.vehicles[0].sensor.rate_hz, 2.0, "default");
        let b = Scenario::from_toml_str(BASE).unwrap();
        assert_eq!(b.world.earth_model, EarthModel::Flat);
        assert_eq!(b.world.features.count, Some(400), "default");
        assert_eq!(b.vehicles[0].display_name(), "uav1");
        assert_eq!(b.vehicles[1].display_name(), "scout");
        assert_eq!(
            b.vehicles[0].trajectory.as_ref().unwrap().altitude_m,
            120.0,
            "TOML integer into f64"
        );
        assert_eq!(
            b.vehicles[1].trajectory.as_ref().unwrap().altitude_m,
            150.0,
            "default"
        );
        assert_eq!(b.vehicles[1].imu.synthesis, ImuSynthesis::Continuous);
        assert!(matches!(
            b.vehicles[1].trajectory.as_ref().unwrap().shape,
            ShapeConfig::Lawnmower { turn_ramp_fraction, .. } if turn_ramp_fraction == 0.4
        ));
        assert!(matches!(
            b.vehicles[0].sensor.model(),
            SensorModel::Pixel { .. }
        ));
    }

    /// `[world] gravity_mps2` and `[vehicle.imu.truth]`: defaults, and bad values or misplaced
    /// fields rejected with the dotted path of the field (unknown names by the parser).
    #[test]
    fn gravity_and_imu_truth_fields() {
        let b = Scenario::from_toml_str(BASE).unwrap();
        // Absent: WGS-84 normal gravity at the default origin (−33.87°, 60 m), 9.796198 m/s²
        // by the independent `ahrs` implementation (geodesy tests).
        assert!((b.world.local_gravity() - 9.796_198_401_129_177).abs() < 1e-10);
        let g =
            Scenario::from_toml_str(&BASE.replacen("seed = 3", "seed = 3\ngravity_mps2 = 9.8", 1))
                .unwrap();
        assert_eq!(g.world.local_gravity(), 9.8);
        assert_eq!(Scenario::from_toml_str(&g.to_toml_string()).unwrap(), g);
        assert_eq!(b.vehicles[1].imu.synthesis, ImuSynthesis::Continuous);
        assert_eq!(b.vehicles[0].imu.synthesis, ImuSynthesis::Exact, "default");
        assert_eq!(
            b.vehicles[0].imu.truth.model,
            ImuTruthModel::Sensor,
            "default"
        );
        let with_truth = |table: &str| {
            BASE.replacen(
                "synthesis = \"continuous\"",
                &format!("synthesis = \"continuous\"\n[vehicle.imu.truth]\n{table}"),
                1,
            )
        };
        let t = Scenario::from_toml_str(&with_truth(
            "gyro_scale_factor_ppm = 50\nbias_correlation_time_s = 100",
        ))
        .unwrap();
        let e = t.vehicles[1].imu.truth_errors();
        assert!((e.gyro_scale_factor - 50e-6).abs() < 1e-20);
        assert_eq!(e.bias_correlation_time, 100.0);
        assert_eq!(Scenario::from_toml_str(&t.to_toml_string()).unwrap(), t);
        for (text, field) in [
            (
                BASE.replacen(
                    "earth_model = \"flat\"",
                    "earth_model = \"wgs84\"\ngravity_mps2 = 9.8",
                    1,
                )
                .replace("frame = \"local\"\n", ""),
                "world.gravity_mps2",
            ),
            (
                BASE.replacen("seed = 3", "seed = 3\ngravity_mps2 = 1.0", 1),
                "world.gravity_mps2",
            ),
            (
                with_truth("model = \"filter\"\ngyro_scale_factor_ppm = 5"),
                "vehicle[1].imu.truth.gyro_scale_factor_ppm",
            ),
            (
                with_truth("accel_misalignment_mrad = -1"),
                "vehicle[1].imu.truth.accel_misalignment_mrad",
            ),
            (
                with_truth("bias_correlation_time_s = 0"),
                "vehicle[1].imu.truth.bias_correlation_time_s",
            ),
            (
                with_truth("gyro_noise_density = nan"),
                "vehicle[1].imu.truth.gyro_noise_density",
            ),
        ] {
            assert_eq!(invalid_field(&text), field, "{text}");
        }
        match Scenario::from_toml_str(&with_truth("gyro_scale_ppm = 5")) {
            Err(ScenarioError::Parse(e)) => {
                assert!(e.to_string().contains("gyro_scale_ppm"), "{e}")
            }
            other => panic!("expected an unknown-field error, got {other:?}"),
        }
    }

    #[test]
    fn builtin_default_is_valid_and_round_trips_through_toml() {
        let d = Scenario::builtin_default();
        d.validate().unwrap();
        assert_eq!(d.vehicles.len(), 4);
        assert_eq!(d.world.earth_model.frame(), NavFrame::Global);
        for v in &d.vehicles {
            assert!((100.0..=200.0).contains(&v.trajectory.as_ref().unwrap().altitude_m));
            assert_eq!(v.imu.grade, ImuGrade::Tactical);
            assert!(matches!(
                v.sensor.model,
                SensorModelConfig::RangeBearing { .. }
            ));
        }
        let text = d.to_toml_string();
        assert_eq!(Scenario::from_toml_str(&text).unwrap(), d);
    }

    fn invalid_field(text: &str) -> String {
        match Scenario::from_toml_str(text) {
            Err(ScenarioError::Invalid { field, reason }) => {
                assert!(!reason.is_empty());
                field
            }
            other => panic!("expected a field error, got {other:?}"),
        }
    }

    /// Each bad value is rejected with the dotted path of the offending field.
    #[test]
    fn invalid_values_name_their_field() {
        let cases = [
            (
                "seed = 3",
                "seed = 3\norigin = { lat_deg = 95.0 }",
                "world.origin.lat_deg",
            ),
            (
                "seed = 3",
                "seed = 3\nfeatures = { count = 10, density_per_km2 = 5.0 }",
                "world.features",
            ),
            (
                "seed = 3",
                "seed = 3\nfeatures = { count = 0 }",
                "world.features.count",
            ),
            (
                "seed = 3",
                "seed = 3\nterrain = { min_wavelength_m = 500.0, max_wavelength_m = 100.0 }",
                "world.terrain.max_wavelength_m",
            ),
            (
                "altitude_m = 120",
                "altitude_m = nan",
                "vehicle[0].trajectory.altitude_m",
            ),
            (
                "altitude_m = 120",
                "altitude_m = 120\nphase = 1.0",
                "vehicle[0].trajectory.phase",
            ),
            (
                "width_m = 700",
                "width_m = 20",
                "vehicle[0].trajectory.shape.width_m",
            ),
            ("legs = 3", "legs = 1", "vehicle[1].trajectory.shape.legs"),
            (
                "max_range_m = 400",
                "max_range_m = 5",
                "vehicle[0].sensor.max_range_m",
            ),
            // 100 Hz IMU: 70 Hz frames do not fall on its samples and two could share one
            // interval.
            ("rate_hz = 4", "rate_hz = 70", "vehicle[0].sensor.rate_hz"),
            (
                "rate_hz = 4",
                "rate_hz = 4\ntime_offset_s = 0.25",
                "vehicle[0].sensor.time_offset_s",
            ),
            (
                "rate_hz = 200",
                "rate_hz = 200\ntimestamp_jitter_s = 0.002",
                "vehicle[1].imu.timestamp_jitter_s",
            ),
            (
                "sigma_px = 1",
                "sigma_px = -1",
                "vehicle[0].sensor.model.sigma_px",
            ),
            ("rate_hz = 200", "rate_hz = 0", "vehicle[1].imu.rate_hz"),
            (
                "frame = \"local\"",
                "frame = \"global\"",
                "vehicle[1].frame",
            ),
            ("id = 2", "id = 1", "vehicle[1].id"),
            ("name = \"scout\"", "name = \"uav1\"", "vehicle[1].name"),
            ("name = \"scout\"", "name = \"a b\"", "vehicle[1].name"),
        ];
        for (from, to, field) in cases {
            assert!(BASE.contains(from), "{from}");
            assert_eq!(invalid_field(&BASE.replacen(from, to, 1)), field, "{to}");
        }
        let text = BASE.replacen(
            "[vehicle.imu]",
            "[vehicle.initial]\nposition_sigma_m = [1.0, -1.0, 1.0]\n[vehicle.imu]",
            1,
        );
        assert_eq!(
            invalid_field(&text),
            "vehicle[1].initial.position_sigma_m[1]"
        );
        let text = BASE.replacen("synthesis = \"continuous\"", "[vehicle.imu.noise]\naccel_noise_density = 1e-3\ngyro_noise_density = 1e-4\naccel_bias_rw_density = 0\ngyro_bias_rw_density = 0\naccel_bias_sigma = inf\ngyro_bias_sigma = 0", 1);
        assert_eq!(
            invalid_field(&text),
            "vehicle[1].imu.noise.accel_bias_sigma"
        );
        assert_eq!(invalid_field("vehicle = []\n[world]\nseed = 1"), "vehicle");
    }

    /// Unknown fields anywhere are parse errors that name the field; a missing required field too.
    #[test]
    fn unknown_and_missing_fields_are_rejected() {
        for (from, to, word) in [
            ("seed = 3", "seed = 3\nsede = 4", "sede"),
            (
                "altitude_m = 120",
                "altitude_m = 120\naltitude = 3",
                "altitude",
            ),
            ("legs = 3", "legs = 3\nradius_m = 4", "radius_m"),
            (
                "sigma_px = 1",
                "sigma_px = 1\nsigma_range_m = 1",
                "sigma_range_m",
            ),
            ("grade = \"consumer\"", "grade = \"military\"", "military"),
            ("kind = \"lawnmower\"", "kind = \"spiral\"", "spiral"),
        ] {
            match Scenario::from_toml_str(&BASE.replacen(from, to, 1)) {
                Err(ScenarioError::Parse(e)) => assert!(e.to_string().contains(word), "{e}"),
                other => panic!("{to}: expected a parse error, got {other:?}"),
            }
        }
        match Scenario::from_toml_str(&BASE.replacen("legs = 3\n", "", 1)) {
            Err(ScenarioError::Parse(e)) => assert!(e.to_string().contains("legs"), "{e}"),
            other => panic!("expected a missing-field error, got {other:?}"),
        }
        assert!(matches!(
            Scenario::load(Path::new("/nonexistent/canopy.toml")),
            Err(ScenarioError::Io { .. })
        ));
    }

    #[test]
    fn density_sets_the_feature_count() {
        let w = WorldConfig {
            features: FeatureConfig {
                count: None,
                density_per_km2: Some(50.0),
                max_height_above_ground_m: 0.0,
            },
            ..WorldConfig::default()
        };
        w.validate().unwrap();
        // 2.4 km × 2.4 km = 5.76 km² at 50 per km².
        assert_eq!(w.feature_count(), 288);
    }

    /// A general mount is validated (orthonormal, proper, not with `orientation`) and used; a
    /// replayed vehicle has no trajectory, a simulated one must.
    #[test]
    fn general_mounts_and_replayed_vehicles_are_checked() {
        let with_mount = |rows: &str| {
            BASE.replacen(
                "rate_hz = 4",
                &format!("rate_hz = 4\nsensor_from_body = {rows}"),
                1,
            )
        };
        // 90° about z: body x → sensor y.
        let s = Scenario::from_toml_str(&with_mount(
            "[[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]",
        ))
        .unwrap();
        let m = s.vehicles[0].sensor.mount();
        assert_eq!(m.sensor_from_body * Vector3::x(), -Vector3::y());
        for (rows, why) in [
            (
                "[[1.0, 0.1, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]",
                "orthonormal",
            ),
            (
                "[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]",
                "reflection",
            ),
        ] {
            match Scenario::from_toml_str(&with_mount(rows)) {
                Err(ScenarioError::Invalid { field, reason }) => {
                    assert_eq!(field, "vehicle[0].sensor.sensor_from_body");
                    assert!(reason.contains(why), "{reason}");
                }
                other => panic!("{rows}: {other:?}"),
            }
        }
        let both = with_mount("[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]").replacen(
            "rate_hz = 4",
            "rate_hz = 4\norientation = \"forward\"",
            1,
        );
        assert_eq!(invalid_field(&both), "vehicle[0].sensor.sensor_from_body");
        // A simulated vehicle without a trajectory; a replayed one with a trajectory.
        let no_traj = BASE.replacen("[vehicle.trajectory]\naltitude_m = 120\n", "", 1).replacen(
            "[vehicle.trajectory.shape]\nkind = \"figure_eight\"\nlength_m = 1500\nwidth_m = 700\n",
            "",
            1,
        );
        assert_eq!(invalid_field(&no_traj), "vehicle[0].trajectory");
        let replayed_with_traj = BASE.replacen(
            "[vehicle.sensor]",
            "[vehicle.replay]\nimu = \"a.csv\"\nobservations = \"b.csv\"\ninitial = \"static\"\n[vehicle.sensor]",
            1,
        );
        assert_eq!(invalid_field(&replayed_with_traj), "vehicle[0].trajectory");
        let replayed = no_traj.replacen(
            "[vehicle.sensor]",
            "[vehicle.replay]\nimu = \"a.csv\"\nobservations = \"b.csv\"\ninitial = \"static\"\nrest_s = 2.5\n[vehicle.sensor]",
            1,
        );
        let s = Scenario::from_toml_str(&replayed).unwrap();
        assert!(s.vehicles[0].trajectory.is_none());
        let bad_rest = replayed.replacen("rest_s = 2.5", "rest_s = -1", 1);
        assert_eq!(invalid_field(&bad_rest), "vehicle[0].replay.rest_s");
        let zv = |z: &str| replayed.replacen("rest_s = 2.5", &format!("rest_s = 2.5\n{z}"), 1);
        let s = Scenario::from_toml_str(&zv("zero_velocity = { until_s = 2.4 }")).unwrap();
        let z = s.vehicles[0]
            .replay
            .as_ref()
            .unwrap()
            .zero_velocity
            .unwrap();
        assert_eq!(
            (z.until_s, z.sigma_mps, z.rate_hz),
            (2.4, 0.01, 20.0),
            "defaults"
        );
        assert_eq!(
            invalid_field(&zv("zero_velocity = { until_s = 0 }")),
            "vehicle[0].replay.zero_velocity.until_s"
        );
        assert_eq!(
            invalid_field(&zv("zero_velocity = { until_s = 2, sigma_mps = nan }")),
            "vehicle[0].replay.zero_velocity.sigma_mps"
        );
    }

    /// `[vehicle.bearing]` maps onto the filter's options (degrees to radians, absent fields at
    /// the filter's defaults), is range-checked as the filter checks it, and is refused for a
    /// sensor that measures range.
    #[test]
    fn bearing_options_map_onto_the_filter_and_are_checked() {
        let with = |extra: &str| {
            BASE.replacen(
                "[vehicle.sensor]\nrate_hz = 4",
                &format!("[vehicle.bearing]\n{extra}\n[vehicle.sensor]\nrate_hz = 4"),
                1,
            )
        };
        let s = Scenario::from_toml_str(&with(
            "initialization = \"multi_view\"\nmin_parallax_deg = 5\nmin_range_m = 0.1",
        ))
        .unwrap();
        let c = s.vehicles[0].bearing.config();
        let d = BearingConfig::default();
        assert_eq!(c.initialization, BearingInit::MultiView);
        assert!((c.min_parallax - 5f64.to_radians()).abs() < 1e-15);
        assert_eq!((c.min_range, c.max_range), (0.1, d.max_range));
        assert_eq!(c.min_observations, d.min_observations);
        assert_eq!(
            Scenario::from_toml_str(BASE).unwrap().vehicles[0]
                .bearing
                .config(),
            d,
            "absent table: the filter's defaults"
        );
        for bad in [
            "min_parallax_deg = 0",
            "min_range_m = 5\nmax_range_m = 4",
            "min_observations = 1",
        ] {
            assert_eq!(invalid_field(&with(bad)), "vehicle[0].bearing", "{bad}");
        }
        let ranging = with("initialization = \"multi_view\"").replacen(
            "kind = \"pixel\"\nfu_px = 400\nfv_px = 400\nu0_px = 320\nv0_px = 240\nwidth_px = 640\nheight_px = 480\nsigma_px = 1",
            "kind = \"range_bearing\"\nsigma_range_m = 1\nsigma_bearing_deg = 0.2",
            1,
        );
        assert!(ranging.contains("range_bearing"));
        assert_eq!(invalid_field(&ranging), "vehicle[0].bearing");
    }
}
