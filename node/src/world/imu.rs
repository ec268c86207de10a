//! IMU synthesis: noise-free specific force and body rate from the truth, then biases and noise.
//!
//! Two independent noise-free syntheses of the sample for the interval (t_{k−1}, t_k]:
//!
//! - [`discrete_ideal`] inverts the estimator's discrete mechanization (the contract of
//!   `fusion::ins`, eqs. 21.20–21.22 global and 21.33–21.35 local, with the transport-rate
//!   correction of design.md §3) on the truth at t_{k−1} and t_k:
//!   ω̂ = E(Ψ_{k−1})⁻¹ wrap(Ψ_k − Ψ_{k−1})/Δt + C_bnᵀ ω_in^n,
//!   f̂ = C_beᵀ [(v_k − v_{k−1})/Δt + 2 ω_ie^e × v_{k−1} − g_l(p_{k−1})]
//!   (local: C_be → C_bn, no Coriolis, g = [0, 0, LOCAL_GRAVITY], ω_in^n = 0). Fed through that
//!   mechanization a perfect IMU reproduces the true v_k and Ψ_k exactly.
//! - [`continuous_ideal`] evaluates the continuous-time kinematics of the analytic trajectory at
//!   the interval midpoint in the launch frame n0, without the current local-level frame or the
//!   transport rate: ω_ib^b = C_b^{n0 T} ω_ie^{n0} + E(Ψ⁰)⁻¹ Ψ̇⁰ (n0 is Earth-fixed) and
//!   f^b = C_b^{eT} (a^e + 2 ω_ie^e × v^e − g_l(p^e)) with C_b^e = C_{n0}^e C_b^{n0}.
//!
//! The two agree to O(Δt) in general and to rounding on straight level flight; a sign error in
//! either (Coriolis, Earth rate, transport rate) shows up as a difference that does not shrink
//! with Δt.
//!
//! [`ImuErrors`] then adds the error model of eqs. 21.13–21.16: f̂ = f + δf + w_accel,
//! ω̂ = ω + δω + w_gyro, white noise of σ = density/√Δt, biases drawn from the turn-on σ and
//! random-walking by σ = rw_density·√Δt per sample.

use canopy_fusion::geodesy::{
    LOCAL_GRAVITY, LocalFrame, earth_rate_ecef, earth_rate_ned, ecef_from_ned, ecef_to_geodetic,
    gravity_ecef, transport_rate_ned,
};
use canopy_fusion::imu::ImuNoise;
use canopy_fusion::rotation::{body_rate_from_euler_rate, nav_from_body, wrap_angle};
use canopy_fusion::state::NavFrame;
use nalgebra::Vector3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::trajectory::FlightState;

/// Navigation truth in a vehicle's frame: ECEF position and velocity with Ψ relative to the
/// local-level frame at the current position (global), or launch NED (local).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavTruth {
    /// Simulation time [s].
    pub time: f64,
    /// p^e or p^n [m].
    pub position: Vector3<f64>,
    /// v^e or v^n [m/s].
    pub velocity: Vector3<f64>,
    /// Ψ = (φ, θ, ψ) of C_b^n [rad].
    pub attitude: Vector3<f64>,
}

/// Noise-free specific force f^b [m/s²] and body rate ω_ib^b [rad/s].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuIdeal {
    /// f^b.
    pub specific_force: Vector3<f64>,
    /// ω_ib^b.
    pub angular_rate: Vector3<f64>,
}

/// The discrete inverse of the estimator's mechanization over (prev.time, next.time] (module doc).
pub fn discrete_ideal(frame: NavFrame, prev: &NavTruth, next: &NavTruth) -> ImuIdeal {
    let dt = next.time - prev.time;
    let nav_from_body_prev = nav_from_body(&prev.attitude);
    let d_att = (next.attitude - prev.attitude).map(wrap_angle) / dt;
    let rel_rate = body_rate_from_euler_rate(&prev.attitude) * d_att;
    let accel = (next.velocity - prev.velocity) / dt;
    match frame {
        NavFrame::Local => ImuIdeal {
            specific_force: nav_from_body_prev.transpose()
                * (accel - Vector3::new(0.0, 0.0, LOCAL_GRAVITY)),
            angular_rate: rel_rate,
        },
        NavFrame::Global => {
            let g = ecef_to_geodetic(&prev.position);
            let ecef_from_nav = ecef_from_ned(g.lat, g.lon);
            let ecef_from_body = ecef_from_nav * nav_from_body_prev;
            let coriolis = 2.0 * earth_rate_ecef().cross(&prev.velocity);
            let omega_in = earth_rate_ned(g.lat)
                + transport_rate_ned(&g, &(ecef_from_nav.transpose() * prev.velocity));
            ImuIdeal {
                specific_force: ecef_from_body.transpose()
                    * (accel + coriolis - gravity_ecef(&prev.position)),
                angular_rate: rel_rate + nav_from_body_prev.transpose() * omega_in,
            }
        }
    }
}

/// The continuous-time sample at a flight state (the interval midpoint), module doc.
pub fn continuous_ideal(frame: NavFrame, launch: &LocalFrame, s: &FlightState) -> ImuIdeal {
    let launch_from_body = nav_from_body(&s.attitude);
    let rel_rate = body_rate_from_euler_rate(&s.attitude) * s.attitude_rate;
    let k = &s.kinematics;
    match frame {
        NavFrame::Local => ImuIdeal {
            specific_force: launch_from_body.transpose()
                * (k.acceleration - Vector3::new(0.0, 0.0, LOCAL_GRAVITY)),
            angular_rate: rel_rate,
        },
        NavFrame::Global => {
            let c = launch.ecef_from_ned;
            let p = launch.ecef_from_local(&k.position);
            let v = c * k.velocity;
            let a = c * k.acceleration;
            let w = earth_rate_ecef();
            let ecef_from_body = c * launch_from_body;
            ImuIdeal {
                specific_force: ecef_from_body.transpose()
                    * (a + 2.0 * w.cross(&v) - gravity_ecef(&p)),
                angular_rate: rel_rate + ecef_from_body.transpose() * w,
            }
        }
    }
}

/// True IMU biases and the white-noise generator of one IMU (eqs. 21.13–21.16).
#[derive(Clone, Debug)]
pub struct ImuErrors {
    noise: ImuNoise,
    dt: f64,
    accel_bias: Vector3<f64>,
    gyro_bias: Vector3<f64>,
    white: ChaCha8Rng,
    walk: ChaCha8Rng,
}

fn normal3(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
    )
}

impl ImuErrors {
    /// Draws the turn-on biases from `walk` (which then drives the random walk); `white` drives
    /// the white noise. Separate streams keep the bias path independent of the noise draws.
    pub fn new(noise: ImuNoise, dt: f64, white: ChaCha8Rng, mut walk: ChaCha8Rng) -> Self {
        let accel_bias = normal3(&mut walk) * noise.accel_bias_sigma;
        let gyro_bias = normal3(&mut walk) * noise.gyro_bias_sigma;
        Self {
            noise,
            dt,
            accel_bias,
            gyro_bias,
            white,
            walk,
        }
    }

    /// Current true accelerometer bias δf^b [m/s²].
    pub fn accel_bias(&self) -> Vector3<f64> {
        self.accel_bias
    }

    /// Current true gyro bias δω^b [rad/s].
    pub fn gyro_bias(&self) -> Vector3<f64> {
        self.gyro_bias
    }

    /// Advances the biases one sample (eqs. 21.23, 21.24) and returns the measured sample:
    /// ideal + bias + white noise.
    pub fn corrupt(&mut self, ideal: &ImuIdeal) -> ImuIdeal {
        let sdt = self.dt.sqrt();
        self.accel_bias += normal3(&mut self.walk) * (self.noise.accel_bias_rw_density * sdt);
        self.gyro_bias += normal3(&mut self.walk) * (self.noise.gyro_bias_rw_density * sdt);
        ImuIdeal {
            specific_force: ideal.specific_force
                + self.accel_bias
                + normal3(&mut self.white) * (self.noise.accel_noise_density / sdt),
            angular_rate: ideal.angular_rate
                + self.gyro_bias
                + normal3(&mut self.white) * (self.noise.gyro_noise_density / sdt),
        }
    }
}
