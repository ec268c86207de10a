//! IMU synthesis: noise-free increments from the truth, then the sensor's errors.
//!
//! An [`ImuSample`](canopy_fusion::sensor::ImuSample) carries the coning- and
//! sculling-compensated increments Δθ = ω̂Δt, Δv = f̂Δt of its interval (defined in the
//! `fusion::ins` module docs: exp([Δθ×]) = C_{b(k)}^{b(k−1)}, J(Δθ)Δv = ∫ C_{b(t)}^{b(k−1)} f dt).
//! Three noise-free syntheses of the sample for (t_{k−1}, t_k]:
//!
//! - [`exact_increments`] (`synthesis = "exact"`, the default) computes those increments from the
//!   continuous motion, with no discrete mechanization anywhere: Δθ is the rotation vector of
//!   C_{b(k−1)}^{i ᵀ} C_{b(k)}^i (attitudes at the two ends, inertial through the Earth's turn
//!   exp([Ω×]Δt)), and ∫ C_{b(t)}^{b(k−1)} f dt = C_{b(k−1)}^{eᵀ} ∫ exp([Ω×]τ)(a^e + 2Ω×v^e − g_l) dτ,
//!   integrated by parts into exp([Ω×]Δt)v_k − v_{k−1} + ∫ exp([Ω×]τ)(Ω×v − g_l(p)) dτ, whose
//!   slowly varying remainder Simpson's rule integrates to ~1e-17 m/s per step (its error is
//!   Δt⁵/2880 times the fourth derivative). In the flat world it is exact in closed form:
//!   C_{b(k−1)}^{nᵀ}(v_k − v_{k−1} − gΔt). A perfect IMU from this synthesis reproduces the truth
//!   through any correct mechanization of sufficient order; that is what it is for.
//! - [`discrete_ideal`] (`"discrete"`, an ablation) inverts the estimator's own discrete step (the
//!   contract of `fusion::ins`) on the truth at t_{k−1} and t_k: fed through that step, a perfect
//!   IMU reproduces v_k and Ψ_k to rounding. It is an oracle — it hides every truncation error of
//!   the mechanization — and exists only to separate those errors from others.
//! - [`continuous_ideal`] (`"continuous"`, an ablation) evaluates the continuous-time specific
//!   force and body rate at the interval midpoint: an IMU without coning/sculling compensation,
//!   whose samples the mechanization integrates with second-order error in turns.
//!
//! [`ImuErrors`] then corrupts the sample with the simulated sensor's errors ([`SensorErrors`]):
//! f̂ = (I + S_a) f + δf + w_a, ω̂ = (I + S_g) ω + δω + w_g, with S the scale-factor (diagonal)
//! and misalignment (off-diagonal) errors drawn at turn-on, the bias the sum of a turn-on draw, a
//! first-order Gauss–Markov bias instability and a random walk, and white noise of
//! σ = density/√Δt. [`SensorErrors::filter_model`] is the estimator's own model (eqs.
//! 21.13–21.16: turn-on bias, random walk, white noise, nothing else) — an oracle kept for
//! ablation.

use canopy_fusion::geodesy::{
    EARTH_RATE, LocalFrame, earth_rate_ecef, ecef_from_ned, ecef_to_geodetic, gravity_ecef,
};
use canopy_fusion::imu::ImuNoise;
use canopy_fusion::ins::Mechanization;
use canopy_fusion::rotation::{
    RotationIncrement, body_rate_from_euler_rate, nav_from_body, rotation_vector, skew,
};
use nalgebra::{Matrix3, Vector3};
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

/// The body's motion at one instant in the world frame: ECEF position, velocity and C_b^e in a
/// rotating WGS-84 world; launch-NED position, velocity and C_b^n in a flat one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyMotion {
    /// Simulation time [s].
    pub time: f64,
    /// p^e or p^n [m].
    pub position: Vector3<f64>,
    /// v^e or v^n [m/s].
    pub velocity: Vector3<f64>,
    /// C_b^e or C_b^n.
    pub world_from_body: Matrix3<f64>,
}

/// Noise-free specific force f^b [m/s²] and body rate ω_ib^b [rad/s] (as increments over Δt).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuIdeal {
    /// f^b.
    pub specific_force: Vector3<f64>,
    /// ω_ib^b.
    pub angular_rate: Vector3<f64>,
}

/// exp([Ω×]τ) for the Earth rate Ω = ω_ie^e: a turn by Ωτ about the ECEF z axis.
fn earth_spin(tau: f64) -> Matrix3<f64> {
    let (s, c) = (EARTH_RATE * tau).sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// The sample of increments Δθ and Δv = J(Δθ)⁻¹·`force_integral` over Δt (module doc).
fn sample_from_increments(
    rotation: &Matrix3<f64>,
    force_integral: &Vector3<f64>,
    dt: f64,
) -> ImuIdeal {
    let phi = rotation_vector(rotation);
    let dv = RotationIncrement::new(&phi).left_jacobian_inverse() * force_integral;
    ImuIdeal {
        specific_force: dv / dt,
        angular_rate: phi / dt,
    }
}

/// The exact coning- and sculling-compensated sample of the motion between `start` and `end`
/// (module doc). `midpoint(t)` gives the position and velocity at the interval's midpoint time
/// t; it is called only in the rotating world, where gravity is integrated by Simpson's rule.
pub fn exact_increments(
    world: &Mechanization,
    start: &BodyMotion,
    end: &BodyMotion,
    midpoint: impl FnOnce(f64) -> (Vector3<f64>, Vector3<f64>),
) -> ImuIdeal {
    let dt = end.time - start.time;
    let body_from_world = start.world_from_body.transpose();
    match world.local_gravity() {
        Some(g) => sample_from_increments(
            &(body_from_world * end.world_from_body),
            &(body_from_world * (end.velocity - start.velocity - Vector3::new(0.0, 0.0, g) * dt)),
            dt,
        ),
        None => {
            let omega = earth_rate_ecef();
            let remainder = |tau: f64, p: &Vector3<f64>, v: &Vector3<f64>| {
                earth_spin(tau) * (omega.cross(v) - gravity_ecef(p))
            };
            let (p_mid, v_mid) = midpoint(start.time + 0.5 * dt);
            let simpson = (remainder(0.0, &start.position, &start.velocity)
                + 4.0 * remainder(0.5 * dt, &p_mid, &v_mid)
                + remainder(dt, &end.position, &end.velocity))
                * (dt / 6.0);
            let spin = earth_spin(dt);
            sample_from_increments(
                &(body_from_world * spin * end.world_from_body),
                &(body_from_world * (spin * end.velocity - start.velocity + simpson)),
                dt,
            )
        }
    }
}

/// (I − c[ω×])⁻¹ = I + (c[ω×] + c²[ω×]²)/(1 + c²|ω|²).
fn inverse_of_identity_minus(c: f64, omega: &Vector3<f64>) -> Matrix3<f64> {
    let w = skew(omega) * c;
    Matrix3::identity() + (w + w * w) / (1.0 + c * c * omega.norm_squared())
}

/// The inverse of the estimator's discrete step over (prev.time, next.time] (module doc; the
/// equations are the contract in `fusion::ins`): Δθ from C_be,k = exp(−[Ω×]Δt) C_be exp([Δθ×]),
/// Δv from v_k = (I − 2Δt[Ω×] + 2Δt²[Ω×]²) v + (I − Δt[Ω×])((I − ½Δt[Ω×]) C_be J(Δθ) Δv + γΔt).
pub fn discrete_ideal(m: &Mechanization, prev: &NavTruth, next: &NavTruth) -> ImuIdeal {
    let dt = next.time - prev.time;
    match m.local_gravity() {
        Some(g) => {
            let body_from_nav = nav_from_body(&prev.attitude).transpose();
            sample_from_increments(
                &(body_from_nav * nav_from_body(&next.attitude)),
                &(body_from_nav * (next.velocity - prev.velocity - Vector3::new(0.0, 0.0, g) * dt)),
                dt,
            )
        }
        None => {
            let world_from_body = |n: &NavTruth| {
                let g = ecef_to_geodetic(&n.position);
                ecef_from_ned(g.lat, g.lon) * nav_from_body(&n.attitude)
            };
            let body_from_world = world_from_body(prev).transpose();
            let omega = earth_rate_ecef();
            let gravity = gravity_ecef(&(prev.position + prev.velocity * (0.5 * dt)));
            let coriolis_free = inverse_of_identity_minus(dt, &omega)
                * (next.velocity - prev.velocity + 2.0 * dt * omega.cross(&prev.velocity)
                    - 2.0 * dt * dt * omega.cross(&omega.cross(&prev.velocity)));
            sample_from_increments(
                &(body_from_world * earth_spin(dt) * world_from_body(next)),
                &(body_from_world
                    * inverse_of_identity_minus(0.5 * dt, &omega)
                    * (coriolis_free - gravity * dt)),
                dt,
            )
        }
    }
}

/// The continuous-time sample at a flight state (the interval midpoint), module doc.
pub fn continuous_ideal(m: &Mechanization, launch: &LocalFrame, s: &FlightState) -> ImuIdeal {
    let launch_from_body = nav_from_body(&s.attitude);
    let rel_rate = body_rate_from_euler_rate(&s.attitude) * s.attitude_rate;
    let k = &s.kinematics;
    match m.local_gravity() {
        Some(g) => ImuIdeal {
            specific_force: launch_from_body.transpose()
                * (k.acceleration - Vector3::new(0.0, 0.0, g)),
            angular_rate: rel_rate,
        },
        None => {
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

/// The simulated sensor's error model: the world's truth, which the estimator does not see
/// (module doc). All σ are 1-σ; densities as in [`ImuNoise`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SensorErrors {
    /// Accelerometer white-noise density [m/s²/√Hz].
    pub accel_noise_density: f64,
    /// Gyro white-noise density [rad/s/√Hz].
    pub gyro_noise_density: f64,
    /// Turn-on accelerometer bias σ [m/s²].
    pub accel_bias_sigma: f64,
    /// Turn-on gyro bias σ [rad/s].
    pub gyro_bias_sigma: f64,
    /// Accelerometer bias instability: stationary σ of a first-order Gauss–Markov bias [m/s²].
    pub accel_bias_instability: f64,
    /// Gyro bias instability: stationary σ of a first-order Gauss–Markov bias [rad/s].
    pub gyro_bias_instability: f64,
    /// Correlation time of the Gauss–Markov biases [s] (> 0).
    pub bias_correlation_time: f64,
    /// Accelerometer bias random-walk density [m/s³/√Hz].
    pub accel_bias_rw_density: f64,
    /// Gyro bias random-walk density [rad/s²/√Hz].
    pub gyro_bias_rw_density: f64,
    /// Per-axis accelerometer scale-factor error σ (a fraction: 1e-4 = 100 ppm).
    pub accel_scale_factor: f64,
    /// Per-axis gyro scale-factor error σ (fraction).
    pub gyro_scale_factor: f64,
    /// σ of each of the six off-diagonal accelerometer misalignment terms [rad].
    pub accel_misalignment: f64,
    /// σ of each of the six off-diagonal gyro misalignment terms [rad].
    pub gyro_misalignment: f64,
}

impl SensorErrors {
    /// Exactly the estimator's model of `noise` (eqs. 21.13–21.16): white noise, turn-on bias and
    /// random walk, no instability, scale-factor or misalignment error. An oracle for ablation.
    pub fn filter_model(noise: &ImuNoise) -> Self {
        Self {
            accel_noise_density: noise.accel_noise_density,
            gyro_noise_density: noise.gyro_noise_density,
            accel_bias_sigma: noise.accel_bias_sigma,
            gyro_bias_sigma: noise.gyro_bias_sigma,
            accel_bias_instability: 0.0,
            gyro_bias_instability: 0.0,
            bias_correlation_time: f64::INFINITY,
            accel_bias_rw_density: noise.accel_bias_rw_density,
            gyro_bias_rw_density: noise.gyro_bias_rw_density,
            accel_scale_factor: 0.0,
            gyro_scale_factor: 0.0,
            accel_misalignment: 0.0,
            gyro_misalignment: 0.0,
        }
    }
}

/// One IMU's error state and random streams (module doc).
#[derive(Clone, Debug)]
pub struct ImuErrors {
    model: SensorErrors,
    dt: f64,
    /// Turn-on bias plus random walk.
    accel_walk: Vector3<f64>,
    gyro_walk: Vector3<f64>,
    /// Gauss–Markov bias states.
    accel_markov: Vector3<f64>,
    gyro_markov: Vector3<f64>,
    /// I + scale-factor + misalignment.
    accel_calibration: Matrix3<f64>,
    gyro_calibration: Matrix3<f64>,
    white: ChaCha8Rng,
    walk: ChaCha8Rng,
    instability: ChaCha8Rng,
}

fn normal3(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    Vector3::new(
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
        rng.sample(StandardNormal),
    )
}

/// I + diag(scale σ·n) + off-diagonal(misalignment σ·n), drawn from `rng` only when a σ is
/// non-zero (so a model without them leaves the stream untouched).
fn draw_calibration(rng: &mut ChaCha8Rng, scale: f64, misalignment: f64) -> Matrix3<f64> {
    let mut m = Matrix3::identity();
    if scale > 0.0 {
        let d = normal3(rng) * scale;
        for i in 0..3 {
            m[(i, i)] += d[i];
        }
    }
    if misalignment > 0.0 {
        for i in 0..3 {
            for j in (0..3).filter(|&j| j != i) {
                m[(i, j)] = misalignment * rng.sample::<f64, _>(StandardNormal);
            }
        }
    }
    m
}

/// The random streams of one IMU's errors, each independent of the others (toggling one error
/// term never reshuffles another's draws).
#[derive(Clone, Debug)]
pub struct ImuStreams {
    /// White noise.
    pub white: ChaCha8Rng,
    /// Turn-on biases, then the random walk.
    pub walk: ChaCha8Rng,
    /// Gauss–Markov bias instability (initial stationary draw, then its driving noise).
    pub instability: ChaCha8Rng,
    /// Scale-factor and misalignment errors (drawn once).
    pub calibration: ChaCha8Rng,
}

impl ImuErrors {
    /// Draws the turn-on biases (from `walk`, which then drives the random walk), the stationary
    /// initial Gauss–Markov biases and the scale-factor and misalignment errors.
    pub fn new(model: SensorErrors, dt: f64, streams: ImuStreams) -> Self {
        let ImuStreams {
            white,
            mut walk,
            mut instability,
            mut calibration,
        } = streams;
        let accel_walk = normal3(&mut walk) * model.accel_bias_sigma;
        let gyro_walk = normal3(&mut walk) * model.gyro_bias_sigma;
        let (accel_markov, gyro_markov) =
            if model.accel_bias_instability > 0.0 || model.gyro_bias_instability > 0.0 {
                (
                    normal3(&mut instability) * model.accel_bias_instability,
                    normal3(&mut instability) * model.gyro_bias_instability,
                )
            } else {
                (Vector3::zeros(), Vector3::zeros())
            };
        let accel_calibration = draw_calibration(
            &mut calibration,
            model.accel_scale_factor,
            model.accel_misalignment,
        );
        let gyro_calibration = draw_calibration(
            &mut calibration,
            model.gyro_scale_factor,
            model.gyro_misalignment,
        );
        Self {
            model,
            dt,
            accel_walk,
            gyro_walk,
            accel_markov,
            gyro_markov,
            accel_calibration,
            gyro_calibration,
            white,
            walk,
            instability,
        }
    }

    /// The error model.
    pub fn model(&self) -> &SensorErrors {
        &self.model
    }

    /// Current true accelerometer bias δf^b (turn-on + instability + walk) [m/s²].
    pub fn accel_bias(&self) -> Vector3<f64> {
        self.accel_walk + self.accel_markov
    }

    /// Current true gyro bias δω^b [rad/s].
    pub fn gyro_bias(&self) -> Vector3<f64> {
        self.gyro_walk + self.gyro_markov
    }

    /// I + S_a: the accelerometer's scale-factor and misalignment errors.
    pub fn accel_calibration(&self) -> &Matrix3<f64> {
        &self.accel_calibration
    }

    /// I + S_g: the gyro's scale-factor and misalignment errors.
    pub fn gyro_calibration(&self) -> &Matrix3<f64> {
        &self.gyro_calibration
    }

    /// Advances the biases one sample and returns the measured sample (module doc).
    pub fn corrupt(&mut self, ideal: &ImuIdeal) -> ImuIdeal {
        self.corrupt_over(ideal, self.dt)
    }

    /// [`ImuErrors::corrupt`] over an interval of `dt` seconds instead of the nominal period (a
    /// sample whose time stamp jitters integrates over its actual interval).
    pub fn corrupt_over(&mut self, ideal: &ImuIdeal, dt: f64) -> ImuIdeal {
        let m = &self.model;
        let sdt = dt.sqrt();
        self.accel_walk += normal3(&mut self.walk) * (m.accel_bias_rw_density * sdt);
        self.gyro_walk += normal3(&mut self.walk) * (m.gyro_bias_rw_density * sdt);
        if m.accel_bias_instability > 0.0 || m.gyro_bias_instability > 0.0 {
            // Exact discretisation of ḃ = −b/τ + w: b_k = e^{−Δt/τ} b + σ√(1 − e^{−2Δt/τ}) n.
            let decay = (-dt / m.bias_correlation_time).exp();
            let drive = (1.0 - decay * decay).sqrt();
            self.accel_markov = self.accel_markov * decay
                + normal3(&mut self.instability) * (m.accel_bias_instability * drive);
            self.gyro_markov = self.gyro_markov * decay
                + normal3(&mut self.instability) * (m.gyro_bias_instability * drive);
        }
        ImuIdeal {
            specific_force: self.accel_calibration * ideal.specific_force
                + self.accel_bias()
                + normal3(&mut self.white) * (m.accel_noise_density / sdt),
            angular_rate: self.gyro_calibration * ideal.angular_rate
                + self.gyro_bias()
                + normal3(&mut self.white) * (m.gyro_noise_density / sdt),
        }
    }
}
