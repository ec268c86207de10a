//! IMU error model (eqs. 21.13–21.17): white noise on the measured specific force and rate, and
//! random-walk biases (eqs. 21.15, 21.16 — the latter misprints w_b,accel for w_b,gyro).

/// Noise densities and initial bias uncertainty of an IMU.
///
/// Continuous-time densities: a white noise of density `d` sampled over Δt has variance d²/Δt;
/// a random walk driven by density `d` grows by variance d²·Δt per step.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImuNoise {
    /// Accelerometer white-noise density (velocity random walk) [m/s²/√Hz].
    pub accel_noise_density: f64,
    /// Gyro white-noise density (angle random walk) [rad/s/√Hz].
    pub gyro_noise_density: f64,
    /// Accelerometer bias random-walk density [m/s³/√Hz] (drives w_b,accel, eq. 21.15).
    pub accel_bias_rw_density: f64,
    /// Gyro bias random-walk density [rad/s²/√Hz] (drives w_b,gyro, eq. 21.16).
    pub gyro_bias_rw_density: f64,
    /// 1-σ turn-on accelerometer bias [m/s²] (initial bias draw and initial filter covariance).
    pub accel_bias_sigma: f64,
    /// 1-σ turn-on gyro bias [rad/s].
    pub gyro_bias_sigma: f64,
}

/// Named IMU grades. Figures are typical datasheet values, converted to SI.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImuGrade {
    /// Navigation grade (ring-laser gyro class): ARW 0.002°/√h, 0.01°/h bias, 25 µg bias.
    Navigation,
    /// Tactical grade (FOG / high-end MEMS): ARW 0.05°/√h, 1°/h bias, 0.05 m/s/√h VRW, 1 mg bias.
    Tactical,
    /// Consumer MEMS: ARW 0.3°/√h, 10°/h bias, 0.2 m/s/√h VRW, 10 mg bias.
    Consumer,
    /// No noise and no bias (for mechanization checks).
    Perfect,
}

const DEG: f64 = std::f64::consts::PI / 180.0;
const HOUR: f64 = 3600.0;
const G0: f64 = 9.80665;

impl ImuGrade {
    /// The grade's noise model.
    pub fn noise(self) -> ImuNoise {
        match self {
            ImuGrade::Navigation => ImuNoise {
                accel_noise_density: 0.005 / 60.0, // 0.005 m/s/√h
                gyro_noise_density: 0.002 * DEG / 60.0,
                accel_bias_rw_density: 1e-6,
                gyro_bias_rw_density: 1e-9,
                accel_bias_sigma: 25e-6 * G0,
                gyro_bias_sigma: 0.01 * DEG / HOUR,
            },
            ImuGrade::Tactical => ImuNoise {
                accel_noise_density: 0.05 / 60.0,
                gyro_noise_density: 0.05 * DEG / 60.0,
                accel_bias_rw_density: 1e-5,
                gyro_bias_rw_density: 1e-8,
                accel_bias_sigma: 1e-3 * G0,
                gyro_bias_sigma: 1.0 * DEG / HOUR,
            },
            ImuGrade::Consumer => ImuNoise {
                accel_noise_density: 0.2 / 60.0,
                gyro_noise_density: 0.3 * DEG / 60.0,
                accel_bias_rw_density: 1e-4,
                gyro_bias_rw_density: 1e-7,
                accel_bias_sigma: 10e-3 * G0,
                gyro_bias_sigma: 10.0 * DEG / HOUR,
            },
            ImuGrade::Perfect => ImuNoise {
                accel_noise_density: 0.0,
                gyro_noise_density: 0.0,
                accel_bias_rw_density: 0.0,
                gyro_bias_rw_density: 0.0,
                accel_bias_sigma: 0.0,
                gyro_bias_sigma: 0.0,
            },
        }
    }
}
