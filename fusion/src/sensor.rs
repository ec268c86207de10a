//! Estimator inputs: IMU samples and terrain observations, as they arrive in messages.
//!
//! The estimator never calls the simulator (design.md §2): everything it knows about the world
//! comes through these types, from the world process, a replayed log, or a test.

use nalgebra::{Matrix3, Vector2, Vector3};

/// Globally unique id of a map feature (the simulated descriptor, §4 of design.md). Used to align
/// map information between vehicles; association inside one vehicle can work without it.
pub type FeatureId = u64;

/// A 256-bit binary appearance descriptor (e.g. ORB/BRIEF-like): what a camera can tell about
/// a feature without knowing which one it is. Compared by Hamming distance.
pub type Appearance = [u64; 4];

/// Hamming distance between two appearance descriptors (0–256).
pub fn hamming(a: &Appearance, b: &Appearance) -> u32 {
    a.iter().zip(b).map(|(x, y)| (x ^ y).count_ones()).sum()
}

/// One IMU sample (eq. 21.13, 21.14 notation): measured specific force f̂^b [m/s²] and measured
/// body rate ω̂^b_ib [rad/s] over the interval ending at `time`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImuSample {
    /// End of the sample interval, simulation time [s].
    pub time: f64,
    /// Interval length Δt [s] (eq. 21.20).
    pub dt: f64,
    /// Measured specific force f̂^b [m/s²].
    pub specific_force: Vector3<f64>,
    /// Measured angular rate ω̂^b_ib [rad/s].
    pub angular_rate: Vector3<f64>,
}

/// The measured quantity of one terrain observation.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Measurement {
    /// Range ρ [m], azimuth φ and elevation ϑ [rad] (eq. 21.41).
    RangeBearing(Vector3<f64>),
    /// Azimuth φ and elevation ϑ [rad] (eq. 21.42).
    Bearing(Vector2<f64>),
    /// Pixel coordinates (u, v) (eq. 21.43).
    Pixel(Vector2<f64>),
}

/// One feature observation from the terrain sensor.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Observation {
    /// What the sensor calls the observed thing: the tracker's (short-lived) track id, or, in
    /// the perfect-identity ablation of the simulator, the true feature id. May be wrong in
    /// robustness tests.
    pub descriptor: FeatureId,
    /// The measurement.
    pub z: Measurement,
    /// The appearance descriptor extracted with it (`None`: the sensor gives none; then the
    /// tracker id is all association has).
    #[serde(default)]
    pub appearance: Option<Appearance>,
}

/// All observations of one terrain-sensor frame.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ObservationFrame {
    /// Frame time, simulation time [s]; equals the time of the last IMU sample before it.
    pub time: f64,
    /// Observations.
    pub observations: Vec<Observation>,
}

/// Pinhole intrinsics of eq. 21.43: u = f_u·y^s/x^s + u_0, v = f_v·z^s/x^s + v_0.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CameraIntrinsics {
    /// Focal length along u [px].
    pub fu: f64,
    /// Focal length along v [px].
    pub fv: f64,
    /// Principal point u_0 [px].
    pub u0: f64,
    /// Principal point v_0 [px].
    pub v0: f64,
    /// Image width [px] (valid u in [0, width)).
    pub width: f64,
    /// Image height [px] (valid v in [0, height)).
    pub height: f64,
}

/// Kind and noise of a terrain sensor.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum SensorModel {
    /// Range-bearing sensor (radar, lidar): σ_range [m], σ_bearing [rad] for azimuth and elevation.
    RangeBearing {
        /// Range noise σ [m].
        sigma_range: f64,
        /// Azimuth and elevation noise σ [rad].
        sigma_bearing: f64,
    },
    /// Bearing-only angles (eq. 21.42): σ [rad].
    Bearing {
        /// Azimuth and elevation noise σ [rad].
        sigma_bearing: f64,
    },
    /// Camera pixels (eq. 21.43): σ [px].
    Pixel {
        /// Intrinsics.
        camera: CameraIntrinsics,
        /// Pixel noise σ [px].
        sigma_pixel: f64,
    },
}

/// Terrain-sensor mounting (eq. 21.45): C_b^s and the lever arm p_sb^b.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SensorMount {
    /// C_b^s: maps body-frame vectors into the sensor frame.
    pub sensor_from_body: Matrix3<f64>,
    /// Lever arm p_sb^b: sensor origin relative to the vehicle centre of mass, body frame [m].
    pub lever_arm_body: Vector3<f64>,
}

impl SensorMount {
    /// A sensor looking straight down (sensor x = body z), sensor y = body y, with a lever arm.
    pub fn downward(lever_arm_body: Vector3<f64>) -> Self {
        // sensor x = body z (down), sensor y = body y (right), sensor z = −body x (so the image
        // "down" axis points to the tail); right-handed: x × y = z ⇒ z_b × y_b = −x_b.
        let sensor_from_body = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, -1.0, 0.0, 0.0);
        Self {
            sensor_from_body,
            lever_arm_body,
        }
    }
}
