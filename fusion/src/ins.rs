//! Strapdown INS mechanization in both navigation frames, with the analytic Jacobians ∇F, ∇G of
//! the discrete process model (eqs. 21.19–21.25 global, 21.33–21.38 local) and the discrete
//! process-noise covariance Q of eq. 21.17.
//!
//! # What a sample means: coning- and sculling-compensated increments
//! An [`ImuSample`] over (t_{k−1}, t_k] carries Δθ = ω̂Δt and Δv = f̂Δt defined from the
//! continuous motion by
//! ```text
//! exp([Δθ×])  = C_{b(k)}^{b(k−1)}                       body rotation over the interval, relative
//!                                                        to inertial space (local SLAM: to n)
//! J(Δθ) Δv    = ∫ C_{b(t)}^{b(k−1)} f^b(t) dt            specific force integrated in b(k−1)
//! J(φ)        = I + (1 − cos θ)/θ² [φ×] + (θ − sin θ)/θ³ [φ×]²,  θ = |φ|  (left Jacobian of SO(3))
//! ```
//! For a constant rate ω and force f over the interval Δθ = ωΔt and Δv = fΔt exactly; in general
//! they differ from ∫ω dt and ∫f dt by the coning and sculling terms (second order in Δt) that a
//! navigation IMU's high-rate processing adds. Raw interval averages ∫ω dt/Δt, ∫f dt/Δt are the
//! first-order approximation of the same quantities.
//!
//! # The discrete equations (a contract: the world simulator's `discrete` ablation inverts them)
//! Global (ECEF p^e, v^e; Ψ relative to the local-level NED frame at the *current* position;
//! Ω = ω_ie^e of eq. 21.6):
//! ```text
//! f = f̂ − δf_{k-1};  ω = ω̂ − δω_{k-1};  Δθ = ωΔt;  Δv = fΔt                      (21.13, 21.14)
//! C_be   = C_n^e(p_{k-1}) C_b^n(Ψ_{k-1})                                            (21.11, 21.12)
//! Δv_f   = (I − ½Δt[Ω×]) C_be J(Δθ) Δv          specific force, Earth turning ½ΩΔt meanwhile
//! γ      = g_l(p_{k-1} + ½ v_{k-1} Δt)           plumb-bob gravity at the interval midpoint
//! v_k    = v_{k-1} + Δv_f + γΔt − 2Ω × v̄ Δt,                                      (21.21)
//!          v̄ = v_{k-1} + ½(Δv_f + γΔt − 2Ω × v_{k-1} Δt)   the interval's mean velocity
//! p_k    = p_{k-1} + ½ (v_{k-1} + v_k) Δt                                          (21.20, trapezoid)
//! C_be,k = exp(−[Ω×]Δt) C_be exp([Δθ×])          exact attitude update in ECEF
//! Ψ_k    = euler(C_n^e(p_k)ᵀ C_be,k)                                                (21.22)
//! δf_k   = δf_{k-1} + w_b,accel;  δω_k = δω_{k-1} + w_b,gyro                        (21.23, 21.24)
//! ```
//! Local (NED p^n, v^n of the shared launch frame, flat non-rotating Earth, eqs. 21.33–21.38):
//! Ω = 0, C_n^e = I, γ = [0, 0, g] with g the configured gravity ([`Mechanization::local`]):
//! v_k = v_{k-1} + C_b^n J(Δθ) Δv + γΔt, p_k by the trapezoid, Ψ_k = euler(C_b^n exp([Δθ×])).
//!
//! With exact increments the attitude and the specific-force integral are exact; what remains
//! is the midpoint gravity and Coriolis terms, the Earth's turn within the interval to first
//! order in ΩΔt (≈ 7e-7 at 100 Hz) and the trapezoid, each O(Δt³) per step with sums that
//! telescope (e.g. Σ Δt³ȧ/12 = Δt²Δa/12), so a perfect IMU along a 300 s flight reproduces the
//! truth to well below a millimetre (`tests/tests/mechanization.rs` prints the figures).
//!
//! Deviations from the chapter, all deliberate:
//! * Eq. 21.22 integrates the Euler angles with a first-order step Ψ + E(ω − C_nᵇ ω_in)Δt. Its
//!   neglected cross term ½|ω||ω_in|Δt is a rate error of a few 1e-8 rad/s at 0.1 rad/s body
//!   rates, which tilts the platform and grows into metres of position error over minutes (t³).
//!   The attitude here is updated as a rotation, exactly, and Ψ re-extracted; the Earth rate
//!   and the transport rate ω_en (which eq. 21.5 omits, design.md §3) are both contained exactly
//!   in the change of C_n^e(p) and the ECEF rotation exp(−[Ω×]Δt).
//! * Eq. 21.21 rotates the specific force with the attitude at the interval start; the body's
//!   turn within the interval (the ½Δθ×Δv rotation term and higher) is taken by J(Δθ).
//! * Position uses the trapezoid rule instead of eq. 21.20's Euler step, gravity and Coriolis
//!   the interval midpoint (second order).
//! * g_l^e is [`geodesy::gravity_ecef`] (Somigliana normal gravity, the erratum of eq. 21.10);
//!   the local frame's g is a parameter (eq. 21.31 fixes none; sites differ by 0.5 %).
//!
//! # Noise (eq. 21.17)
//! w = [w_accel, w_gyro, w_b,accel, w_b,gyro] (offsets `state::W_*`) are discrete samples with
//! Cov(w_accel) = accel_noise_density²/Δt, Cov(w_gyro) = gyro_noise_density²/Δt (white noise
//! averaged over the interval, so v gains density²·Δt), Cov(w_b,·) = rw_density²·Δt (random walk).
//! w_accel and w_gyro enter exactly like the biases (f = f̂ − δf − w_accel, eqs. 21.13/21.14), so
//! their columns of ∇G are the bias columns of ∇F.

use crate::geodesy;
use crate::imu::ImuNoise;
use crate::rotation::{
    RotationIncrement, body_rate_from_euler_rate, euler_from_nav_from_body,
    euler_rate_from_body_rate, nav_from_body, skew,
};
use crate::sensor::ImuSample;
use crate::state::{
    ACC_BIAS, ATT, GYRO_BIAS, NOISE_DIM, NavFrame, POS, VEHICLE_DIM, VEL, W_ACC_BIAS, W_ACCEL,
    W_GYRO, W_GYRO_BIAS,
};
use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

/// ∇F: Jacobian of the vehicle transition w.r.t. the vehicle state (15×15).
pub type TransitionJacobian = SMatrix<f64, VEHICLE_DIM, VEHICLE_DIM>;
/// ∇G: Jacobian of the vehicle transition w.r.t. the noise vector w (15×12).
pub type NoiseJacobian = SMatrix<f64, VEHICLE_DIM, NOISE_DIM>;
/// Discrete process-noise covariance Q (12×12).
pub type ProcessNoise = SMatrix<f64, NOISE_DIM, NOISE_DIM>;
/// A 15-vector of vehicle states in the order of `state`.
pub type VehicleVector = SVector<f64, VEHICLE_DIM>;
/// A 15×15 vehicle covariance.
pub type VehicleCovariance = SMatrix<f64, VEHICLE_DIM, VEHICLE_DIM>;

/// One vehicle block of the state (eq. 21.1 / 21.26 without the map).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VehicleState {
    /// Position p (ECEF in global SLAM, local NED in local SLAM) [m].
    pub position: Vector3<f64>,
    /// Velocity v (same frame as the position) [m/s].
    pub velocity: Vector3<f64>,
    /// Euler attitude Ψ = (φ, θ, ψ) of C_b^n [rad].
    pub attitude: Vector3<f64>,
    /// Accelerometer bias δf^b [m/s²].
    pub accel_bias: Vector3<f64>,
    /// Gyro bias δω^b_ib [rad/s].
    pub gyro_bias: Vector3<f64>,
}

impl VehicleState {
    /// The state as a 15-vector in the order of `state`.
    pub fn to_vector(&self) -> VehicleVector {
        let mut x = VehicleVector::zeros();
        x.fixed_rows_mut::<3>(POS).copy_from(&self.position);
        x.fixed_rows_mut::<3>(VEL).copy_from(&self.velocity);
        x.fixed_rows_mut::<3>(ATT).copy_from(&self.attitude);
        x.fixed_rows_mut::<3>(ACC_BIAS).copy_from(&self.accel_bias);
        x.fixed_rows_mut::<3>(GYRO_BIAS).copy_from(&self.gyro_bias);
        x
    }

    /// Inverse of [`VehicleState::to_vector`].
    pub fn from_vector(x: &VehicleVector) -> Self {
        Self {
            position: x.fixed_rows::<3>(POS).into(),
            velocity: x.fixed_rows::<3>(VEL).into(),
            attitude: x.fixed_rows::<3>(ATT).into(),
            accel_bias: x.fixed_rows::<3>(ACC_BIAS).into(),
            gyro_bias: x.fixed_rows::<3>(GYRO_BIAS).into(),
        }
    }

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.to_vector().iter().all(|v| v.is_finite())
    }
}

/// Why an IMU sample, a propagation or a mechanization setting was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InsError {
    /// Δt is NaN, infinite, zero or negative.
    #[error("IMU sample has an invalid interval dt = {0}")]
    InvalidInterval(f64),
    /// A measured specific force, rate or the time stamp is NaN or infinite.
    #[error("IMU sample has a non-finite value")]
    NonFiniteSample,
    /// The propagated state is not finite (e.g. pitch at ±90°, where E_b^n is singular).
    #[error("INS propagation produced a non-finite state (pitch singularity or overflow)")]
    NonFiniteResult,
    /// The local frame's gravity is not a finite positive magnitude.
    #[error("local-frame gravity must be finite and positive, got {0} m/s²")]
    InvalidGravity(f64),
}

/// The navigation frame and the physics the mechanization assumes in it: global (ECEF, rotating
/// WGS-84 Earth, normal gravity at each position) or local (flat, non-rotating, gravity of a
/// configured magnitude along +down).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mechanization {
    frame: NavFrame,
    /// Gravity of the local frame [m/s²] (0 and unused in the global frame).
    local_gravity: f64,
}

impl Mechanization {
    /// Global SLAM (eqs. 21.19–21.25).
    pub fn global() -> Self {
        Self {
            frame: NavFrame::Global,
            local_gravity: 0.0,
        }
    }

    /// Local SLAM with gravity `gravity` [m/s²] along +down (eqs. 21.33–21.38); must be finite
    /// and positive (e.g. [`geodesy::normal_gravity`] at the launch site).
    pub fn local(gravity: f64) -> Result<Self, InsError> {
        if !(gravity.is_finite() && gravity > 0.0) {
            return Err(InsError::InvalidGravity(gravity));
        }
        Ok(Self {
            frame: NavFrame::Local,
            local_gravity: gravity,
        })
    }

    /// `frame`, with `local_gravity` used (and checked) only for the local frame.
    pub fn new(frame: NavFrame, local_gravity: f64) -> Result<Self, InsError> {
        match frame {
            NavFrame::Global => Ok(Self::global()),
            NavFrame::Local => Self::local(local_gravity),
        }
    }

    /// The navigation frame.
    pub fn frame(&self) -> NavFrame {
        self.frame
    }

    /// The local frame's gravity magnitude [m/s²] (`None` in the global frame).
    pub fn local_gravity(&self) -> Option<f64> {
        (self.frame == NavFrame::Local).then_some(self.local_gravity)
    }
}

/// Checks an IMU sample: finite time, force and rate, and 0 < Δt < ∞.
pub fn validate_sample(imu: &ImuSample) -> Result<(), InsError> {
    if !(imu.dt.is_finite() && imu.dt > 0.0) {
        return Err(InsError::InvalidInterval(imu.dt));
    }
    let finite = imu.time.is_finite()
        && imu.specific_force.iter().all(|v| v.is_finite())
        && imu.angular_rate.iter().all(|v| v.is_finite());
    if !finite {
        return Err(InsError::NonFiniteSample);
    }
    Ok(())
}

/// Result of one discrete INS step: the propagated state and the Jacobians at the prior state.
#[derive(Clone, Copy, Debug)]
pub struct Propagation {
    /// x_k = F[x_{k-1}, u_k] with w = 0 (module docs).
    pub state: VehicleState,
    /// ∇F = ∂x_k/∂x_{k-1} (15×15).
    pub transition: TransitionJacobian,
    /// ∇G = ∂x_k/∂w (15×12).
    pub noise: NoiseJacobian,
}

/// Discrete process-noise covariance Q of w (eq. 21.17) for an interval Δt, see the module docs.
pub fn process_noise(noise: &ImuNoise, dt: f64) -> ProcessNoise {
    let mut q = ProcessNoise::zeros();
    for i in 0..3 {
        q[(W_ACCEL + i, W_ACCEL + i)] = noise.accel_noise_density.powi(2) / dt;
        q[(W_GYRO + i, W_GYRO + i)] = noise.gyro_noise_density.powi(2) / dt;
        q[(W_ACC_BIAS + i, W_ACC_BIAS + i)] = noise.accel_bias_rw_density.powi(2) * dt;
        q[(W_GYRO_BIAS + i, W_GYRO_BIAS + i)] = noise.gyro_bias_rw_density.powi(2) * dt;
    }
    q
}

/// The state transition without Jacobians. Validates the sample.
pub fn propagate(
    m: &Mechanization,
    x: &VehicleState,
    imu: &ImuSample,
) -> Result<VehicleState, InsError> {
    Ok(propagate_with_jacobians(m, x, imu)?.state)
}

/// The Earth's rotation in the ECEF frame over Δt, exp(−[Ω×]Δt) (a turn about z).
fn earth_turn(dt: f64) -> Matrix3<f64> {
    let (s, c) = (geodesy::EARTH_RATE * dt).sin_cos();
    Matrix3::new(c, s, 0.0, -s, c, 0.0, 0.0, 0.0, 1.0)
}

/// What the frame contributes at one position: C_n^e, the NED frame's rotation per unit
/// position change ([`geodesy::ned_rotation_from_position`]), and (at the midpoint) gravity and
/// its gradient.
struct FrameAt {
    ecef_from_ned: Matrix3<f64>,
    ned_rotation_dp: Matrix3<f64>,
}

impl FrameAt {
    fn global(p: &Vector3<f64>) -> Self {
        let g = geodesy::ecef_to_geodetic(p);
        Self {
            ecef_from_ned: geodesy::ecef_from_ned(g.lat, g.lon),
            ned_rotation_dp: geodesy::ned_rotation_from_position(&g),
        }
    }

    fn local() -> Self {
        Self {
            ecef_from_ned: Matrix3::identity(),
            ned_rotation_dp: Matrix3::zeros(),
        }
    }
}

/// One discrete INS step with its Jacobians ∇F (eq. 21.46/21.47; the map and stored-pose blocks
/// of the full ∇F are identity, eqs. 21.25/21.38) and ∇G, evaluated at the prior state.
///
/// Derivatives are taken as small rotations: C_b^n(Ψ + dΨ) = C_b^n exp([(E⁻¹dΨ)×]) (eq. 21.8),
/// C_n^e(p + dp) = C_n^e exp([(R dp)×]) with R = [`geodesy::ned_rotation_from_position`],
/// exp([(Δθ + dφ)×]) = exp([Δθ×]) exp([(Jᵀdφ)×]), and a body-side rotation δ of C_b^n(k)
/// moves the extracted Euler angles by E(Ψ_k) δ.
pub fn propagate_with_jacobians(
    m: &Mechanization,
    x: &VehicleState,
    imu: &ImuSample,
) -> Result<Propagation, InsError> {
    validate_sample(imu)?;
    let dt = imu.dt;
    let half = 0.5 * dt;
    let i3 = Matrix3::identity();
    let dv_body = (imu.specific_force - x.accel_bias) * dt;
    let inc = RotationIncrement::new(&((imu.angular_rate - x.gyro_bias) * dt));
    let jac = inc.left_jacobian;
    let force_body = jac * dv_body; // ∫ C_{b(t)}^{b(k-1)} f dt
    let nav_from_body_prev = nav_from_body(&x.attitude);
    let body_from_euler = body_rate_from_euler_rate(&x.attitude); // E⁻¹(Ψ_{k-1})

    // Frame terms: C_n^e at p_{k-1}, Earth-rate matrices, gravity at the midpoint.
    let global = m.frame == NavFrame::Global;
    let (at_prev, omega, gravity, gravity_dp) = if global {
        let mid = geodesy::ecef_to_geodetic(&(x.position + x.velocity * half));
        (
            FrameAt::global(&x.position),
            skew(&geodesy::earth_rate_ecef()),
            geodesy::gravity_ecef_at(&mid),
            geodesy::gravity_ecef_jacobian_at(&mid),
        )
    } else {
        (
            FrameAt::local(),
            Matrix3::zeros(),
            Vector3::new(0.0, 0.0, m.local_gravity),
            Matrix3::zeros(),
        )
    };
    let earth_half = i3 - omega * half; // I − ½Δt[Ω×]
    let earth_coriolis = i3 - omega * dt; // applied to Δv_f + γΔt (the ½ of v̄ times 2Ω)
    // Applied to v_{k-1}: I − 2Δt[Ω×] + 2Δt²[Ω×]² (the Coriolis term at v̄).
    let earth_velocity = i3 - omega * (2.0 * dt) + omega * omega * (2.0 * dt * dt);
    let world_from_body_prev = at_prev.ecef_from_ned * nav_from_body_prev;
    let force_world = earth_half * (world_from_body_prev * force_body);
    let velocity = earth_velocity * x.velocity + earth_coriolis * (force_world + gravity * dt);
    let position = x.position + (x.velocity + velocity) * half;
    let world_from_body = if global {
        earth_turn(dt) * world_from_body_prev * inc.rotation
    } else {
        world_from_body_prev * inc.rotation
    };
    let at_next = if global {
        FrameAt::global(&position)
    } else {
        FrameAt::local()
    };
    let nav_from_body_next = at_next.ecef_from_ned.transpose() * world_from_body;
    let attitude = euler_from_nav_from_body(&nav_from_body_next);
    let state = VehicleState {
        position,
        velocity,
        attitude,
        accel_bias: x.accel_bias,
        gyro_bias: x.gyro_bias,
    };
    if !state.is_finite() {
        return Err(InsError::NonFiniteResult);
    }

    // ∂Δv_f/∂(p, Ψ, δf, δω); Δv_f = L C_n^e C_b^n J Δv.
    let lb = earth_half * world_from_body_prev;
    let force_dp = -(earth_half
        * at_prev.ecef_from_ned
        * skew(&(nav_from_body_prev * force_body))
        * at_prev.ned_rotation_dp);
    let force_datt = -(lb * skew(&force_body) * body_from_euler);
    let force_dbias_f = -(lb * jac * dt);
    let force_dbias_w = -(lb * inc.left_jacobian_times_partial(&dv_body) * dt);
    // v_k = A v + K (Δv_f + γΔt), A = I − 2Δt[Ω×] + 2Δt²[Ω×]², γ at p + ½vΔt.
    let v_dp = earth_coriolis * (force_dp + gravity_dp * dt);
    let v_dv = earth_velocity + earth_coriolis * gravity_dp * (half * dt);
    let v_datt = earth_coriolis * force_datt;
    let v_dbias_f = earth_coriolis * force_dbias_f;
    let v_dbias_w = earth_coriolis * force_dbias_w;
    // p_k = p + ½(v + v_k)Δt.
    let p_dp = i3 + v_dp * half;
    let p_dv = (i3 + v_dv) * half;
    let p_datt = v_datt * half;
    let p_dbias_f = v_dbias_f * half;
    let p_dbias_w = v_dbias_w * half;
    // Ψ_k: body-side rotations of C_b^n(k), mapped by E(Ψ_k). From C_n^e(p_{k-1}):
    // (C_b^n exp[Δθ×])ᵀ R_{k-1}; from C_b^n(Ψ_{k-1}): exp[Δθ×]ᵀ E⁻¹; from Δθ: Jᵀ; from
    // C_n^e(p_k)ᵀ: −C_b^n(k)ᵀ R_k, through p_k's own dependence on everything.
    let euler_from_body = euler_rate_from_body_rate(&attitude);
    let rot_t = inc.rotation.transpose();
    let via_next = -(nav_from_body_next.transpose() * at_next.ned_rotation_dp);
    let att_dp = euler_from_body
        * (rot_t * nav_from_body_prev.transpose() * at_prev.ned_rotation_dp + via_next * p_dp);
    let att_dv = euler_from_body * via_next * p_dv;
    let att_datt = euler_from_body * (rot_t * body_from_euler + via_next * p_datt);
    let att_dbias_f = euler_from_body * via_next * p_dbias_f;
    let att_dbias_w = euler_from_body * (via_next * p_dbias_w - jac.transpose() * dt);

    let mut ff = TransitionJacobian::identity();
    let mut gg = NoiseJacobian::zeros();
    for (row, [dp, dv, datt, dbf, dbw]) in [
        (POS, [p_dp, p_dv, p_datt, p_dbias_f, p_dbias_w]),
        (VEL, [v_dp, v_dv, v_datt, v_dbias_f, v_dbias_w]),
        (ATT, [att_dp, att_dv, att_datt, att_dbias_f, att_dbias_w]),
    ] {
        ff.fixed_view_mut::<3, 3>(row, POS).copy_from(&dp);
        ff.fixed_view_mut::<3, 3>(row, VEL).copy_from(&dv);
        ff.fixed_view_mut::<3, 3>(row, ATT).copy_from(&datt);
        ff.fixed_view_mut::<3, 3>(row, ACC_BIAS).copy_from(&dbf);
        ff.fixed_view_mut::<3, 3>(row, GYRO_BIAS).copy_from(&dbw);
        // w_accel, w_gyro enter like δf, δω (eqs. 21.13, 21.14).
        gg.fixed_view_mut::<3, 3>(row, W_ACCEL).copy_from(&dbf);
        gg.fixed_view_mut::<3, 3>(row, W_GYRO).copy_from(&dbw);
    }
    gg.fixed_view_mut::<3, 3>(ACC_BIAS, W_ACC_BIAS)
        .copy_from(&i3);
    gg.fixed_view_mut::<3, 3>(GYRO_BIAS, W_GYRO_BIAS)
        .copy_from(&i3);

    Ok(Propagation {
        state,
        transition: ff,
        noise: gg,
    })
}

/// The transition with an explicit noise sample w added (eq. 21.19): w_accel and w_gyro enter
/// like the biases (eqs. 21.13/21.14), w_b,· as bias jumps. Used to check ∇G by finite
/// differences.
pub fn propagate_with_noise(
    m: &Mechanization,
    x: &VehicleState,
    imu: &ImuSample,
    w: &SVector<f64, NOISE_DIM>,
) -> Result<VehicleState, InsError> {
    let noisy = ImuSample {
        specific_force: imu.specific_force - w.fixed_rows::<3>(W_ACCEL),
        angular_rate: imu.angular_rate - w.fixed_rows::<3>(W_GYRO),
        ..*imu
    };
    let mut next = propagate(m, x, &noisy)?;
    next.accel_bias += w.fixed_rows::<3>(W_ACC_BIAS);
    next.gyro_bias += w.fixed_rows::<3>(W_GYRO_BIAS);
    Ok(next)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geodesy::{Geodetic, geodetic_to_ecef};
    use nalgebra::Rotation3;

    /// Gravity of the flat test world [m/s²] (normal gravity near 45° N; any positive value).
    const FLAT_GRAVITY: f64 = 9.806;

    fn mechanization(frame: NavFrame) -> Mechanization {
        Mechanization::new(frame, FLAT_GRAVITY).unwrap()
    }

    fn sample(dt: f64) -> ImuSample {
        ImuSample {
            time: 1.0,
            dt,
            specific_force: Vector3::new(0.7, -0.4, -9.6),
            angular_rate: Vector3::new(0.05, -0.08, 0.12),
        }
    }

    fn global_state() -> VehicleState {
        VehicleState {
            position: geodetic_to_ecef(&Geodetic::from_degrees(-33.9, 151.2, 450.0)),
            // ≈ 60 m/s mostly horizontal, so transport rate and Coriolis are non-trivial.
            velocity: Vector3::new(35.0, -40.0, 22.0),
            attitude: Vector3::new(0.15, -0.25, 2.1),
            accel_bias: Vector3::new(0.01, -0.02, 0.03),
            gyro_bias: Vector3::new(1e-4, -2e-4, 3e-4),
        }
    }

    fn local_state() -> VehicleState {
        VehicleState {
            position: Vector3::new(120.0, -40.0, -150.0),
            velocity: Vector3::new(30.0, 5.0, -1.0),
            ..global_state()
        }
    }

    /// Finite-difference steps: 1 m in ECEF position and 1 m/s in ECEF velocity (the map curves
    /// in p and v only on the 6e6 m Earth scale, so truncation is ≈ 1e-13 relative), 1e-3 m and
    /// 1e-3 m/s locally, 1e-4 rad / 1e-4 units for attitude and accelerometer bias; the gyro
    /// bias moves the rotation vector by hΔt, which must stay ≈ 1e-5 rad for the truncation
    /// (≈ (hΔt)² relative: the step is strongly nonlinear in Δθ at Δt = 20 s) to stay ≤ 1e-6.
    fn step(frame: NavFrame, c: usize, dt: f64) -> f64 {
        match (frame, c) {
            (NavFrame::Global, c) if c < ATT => 1.0,
            (_, c) if c < ATT => 1e-3,
            (_, c) if c >= GYRO_BIAS => (1e-5 / dt).min(1e-4),
            _ => 1e-4,
        }
    }

    /// Central differences of the transition w.r.t. the state; per-block steps.
    fn fd_transition(m: &Mechanization, x: &VehicleState, imu: &ImuSample) -> TransitionJacobian {
        let x0 = x.to_vector();
        let mut j = TransitionJacobian::zeros();
        for c in 0..VEHICLE_DIM {
            let h = step(m.frame(), c, imu.dt);
            let mut xp = x0;
            let mut xm = x0;
            xp[c] += h;
            xm[c] -= h;
            let fp = propagate(m, &VehicleState::from_vector(&xp), imu)
                .unwrap()
                .to_vector();
            let fm = propagate(m, &VehicleState::from_vector(&xm), imu)
                .unwrap()
                .to_vector();
            j.set_column(c, &((fp - fm) / (2.0 * h)));
        }
        j
    }

    /// Finite-difference step of noise component c: 1e-4, except w_gyro as the gyro bias.
    fn noise_step(c: usize, dt: f64) -> f64 {
        if (W_GYRO..W_GYRO + 3).contains(&c) {
            (1e-5 / dt).min(1e-4)
        } else {
            1e-4
        }
    }

    fn fd_noise(m: &Mechanization, x: &VehicleState, imu: &ImuSample) -> NoiseJacobian {
        let mut j = NoiseJacobian::zeros();
        for c in 0..NOISE_DIM {
            let h = noise_step(c, imu.dt);
            let mut wp = SVector::<f64, NOISE_DIM>::zeros();
            wp[c] = h;
            let fp = propagate_with_noise(m, x, imu, &wp).unwrap().to_vector();
            let fm = propagate_with_noise(m, x, imu, &(-wp)).unwrap().to_vector();
            j.set_column(c, &((fp - fm) / (2.0 * h)));
        }
        j
    }

    /// The three cases of the Jacobian checks: (mechanization, prior state, Δt). Δt = 0.01 s (a
    /// real IMU step, rotation vector on the series branch of exp/J), 0.1 s, and an unphysical
    /// 20 s (a 3 rad rotation on the closed-form branch), which also magnifies the tiny
    /// position→attitude couplings above the absolute floor of the check.
    fn cases() -> Vec<(Mechanization, VehicleState, f64)> {
        let mut v = Vec::new();
        for (frame, x) in [
            (NavFrame::Global, global_state()),
            (NavFrame::Local, local_state()),
        ] {
            for dt in [0.01, 0.1, 20.0] {
                v.push((mechanization(frame), x, dt));
            }
        }
        v
    }

    #[test]
    fn transition_jacobian_matches_finite_differences_global_and_local() {
        for (m, x, dt) in cases() {
            let imu = sample(dt);
            let analytic = propagate_with_jacobians(&m, &x, &imu).unwrap().transition;
            let fd = fd_transition(&m, &x, &imu);
            let y = propagate(&m, &x, &imu).unwrap().to_vector();
            for r in 0..VEHICLE_DIM {
                for c in 0..VEHICLE_DIM {
                    // Rounding of an output of size |y_r| is ≤ 2 ulp ≈ 4.4e-16·|y_r| per
                    // evaluation, so a central difference errs by ≤ 4.4e-16·|y_r|/h (ECEF
                    // positions: 6e6 m → 2.6e-5 at h = 1e-4); truncation ≤ 1e-6 relative;
                    // 1e-12 absolute floor. The p→Ψ couplings (≈ 1e-12..1e-10) sit in rows with
                    // |y_r| ≈ 3 and h = 1 m, so they are checked at ≈ 1e-12.
                    let tol = 1e-12
                        + 1e-6 * analytic[(r, c)].abs()
                        + 4.4e-16 * y[r].abs().max(1.0) / step(m.frame(), c, dt);
                    assert!(
                        (analytic[(r, c)] - fd[(r, c)]).abs() < tol,
                        "{} dt {dt}: ∇F[{r},{c}] analytic {} vs fd {}",
                        m.frame(),
                        analytic[(r, c)],
                        fd[(r, c)]
                    );
                }
            }
        }
    }

    #[test]
    fn position_and_earth_couplings_are_nontrivial_in_global_frame() {
        // Guards the test above against checking only zeros: the p→Ψ, v→Ψ, δf→Ψ and p→v
        // blocks exist in the global frame (they are zero in the flat local frame).
        let imu = sample(0.1);
        let j = propagate_with_jacobians(&Mechanization::global(), &global_state(), &imu)
            .unwrap()
            .transition;
        // Expected sizes at Δt = 0.1 s: v→Ψ ≈ Δt/R ≈ 1.6e-8, p→Ψ ≈ Δt·Ω/R ≈ 1e-12,
        // δf→Ψ ≈ ½Δt²/R ≈ 8e-10, p→v ≈ Δt·g/R ≈ 1.5e-7; the bounds sit about an order of
        // magnitude below.
        assert!(j.fixed_view::<3, 3>(ATT, VEL).norm() > 1e-9);
        assert!(j.fixed_view::<3, 3>(ATT, POS).norm() > 1e-13);
        assert!(j.fixed_view::<3, 3>(ATT, ACC_BIAS).norm() > 1e-11);
        assert!(j.fixed_view::<3, 3>(VEL, POS).norm() > 1e-8);
    }

    #[test]
    fn noise_jacobian_matches_finite_differences_global_and_local() {
        for (m, x, dt) in cases() {
            let imu = sample(dt);
            let analytic = propagate_with_jacobians(&m, &x, &imu).unwrap().noise;
            let fd = fd_noise(&m, &x, &imu);
            let y = propagate(&m, &x, &imu).unwrap().to_vector();
            for r in 0..VEHICLE_DIM {
                for c in 0..NOISE_DIM {
                    // As for ∇F: rounding 4.4e-16·|y_r|/h, truncation 1e-6 relative, 1e-12 floor.
                    let tol = 1e-12
                        + 1e-6 * analytic[(r, c)].abs()
                        + 4.4e-16 * y[r].abs().max(1.0) / noise_step(c, dt);
                    assert!(
                        (analytic[(r, c)] - fd[(r, c)]).abs() < tol,
                        "{} dt {dt}: ∇G[{r},{c}] analytic {} vs fd {}",
                        m.frame(),
                        analytic[(r, c)],
                        fd[(r, c)]
                    );
                }
            }
            // The bias blocks alone are identity (norm ≥ √6): the check is not vacuous.
            assert!(analytic.norm() > 1.0);
        }
    }

    /// ∫₀ᵗ C₀ exp(τ[ω×]) f dτ by composite Simpson with nalgebra's rotations (independent of
    /// `RotationIncrement`); 2000 panels per second: error ≈ (Δτ)⁴·|ω|⁴|f|/180 ≈ 1e-16.
    fn rotated_force_integral(
        c0: &Matrix3<f64>,
        omega: &Vector3<f64>,
        f: &Vector3<f64>,
        t: f64,
    ) -> Vector3<f64> {
        let n = (2000.0 * t).ceil() as usize * 2;
        let h = t / n as f64;
        let at = |tau: f64| c0 * (Rotation3::from_scaled_axis(omega * tau) * f);
        let mut sum = at(0.0) + at(t);
        for i in 1..n {
            sum += at(i as f64 * h) * if i % 2 == 1 { 4.0 } else { 2.0 };
        }
        sum * (h / 3.0)
    }

    #[test]
    fn constant_rate_and_force_are_integrated_exactly_in_the_local_frame() {
        // A body turning at a constant 0.37 rad/s with a constant body specific force in the flat
        // world: the truth is C(t) = C₀ exp(t[ω×]), v(t) = v₀ + ∫ C f dτ + g t (closed form and
        // an independent quadrature), and exact increments are ωΔt, fΔt. The second-order step
        // reproduces v and Ψ to rounding; only the trapezoid position rule truncates.
        let m = mechanization(NavFrame::Local);
        let omega = Vector3::new(0.2, -0.1, 0.3);
        let f = Vector3::new(1.5, 0.4, -FLAT_GRAVITY - 0.8);
        let attitude0 = Vector3::new(0.1, -0.2, 0.5);
        let c0 = nav_from_body(&attitude0);
        for dt in [0.01f64, 0.05] {
            let mut x = VehicleState {
                position: Vector3::zeros(),
                velocity: Vector3::new(20.0, -3.0, 1.0),
                attitude: attitude0,
                accel_bias: Vector3::zeros(),
                gyro_bias: Vector3::zeros(),
            };
            let v0 = x.velocity;
            let steps = (2.0 / dt).round() as usize;
            for k in 1..=steps {
                let imu = ImuSample {
                    time: k as f64 * dt,
                    dt,
                    specific_force: f,
                    angular_rate: omega,
                };
                x = propagate(&m, &x, &imu).unwrap();
            }
            let t = steps as f64 * dt;
            let c_true = c0 * Rotation3::from_scaled_axis(omega * t).into_inner();
            let v_true = v0
                + rotated_force_integral(&c0, &omega, &f, t)
                + Vector3::new(0.0, 0.0, FLAT_GRAVITY) * t;
            let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(c_true).euler_angles();
            let att_err = (x.attitude - Vector3::new(roll, pitch, yaw)).norm();
            let v_err = (x.velocity - v_true).norm();
            // Rounding over ≤ 200 steps of ~1e-16 relative each on 20 m/s and O(1) rad.
            assert!(att_err < 1e-13, "dt {dt}: attitude error {att_err}");
            assert!(v_err < 1e-12, "dt {dt}: velocity error {v_err}");
        }
    }

    #[test]
    fn local_constant_acceleration_is_integrated_exactly() {
        // Level, non-rotating body with specific force cancelling gravity plus 1 m/s² north.
        let x = VehicleState {
            position: Vector3::zeros(),
            velocity: Vector3::new(10.0, 0.0, 0.0),
            attitude: Vector3::zeros(),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        };
        let imu = ImuSample {
            time: 0.0,
            dt: 0.5,
            specific_force: Vector3::new(1.0, 0.0, -FLAT_GRAVITY),
            angular_rate: Vector3::zeros(),
        };
        let m = mechanization(NavFrame::Local);
        let mut s = x;
        for _ in 0..20 {
            s = propagate(&m, &s, &imu).unwrap();
        }
        // Closed form after 10 s: p = v0 t + ½ a t² = 100 + 50; v = 20.
        // The trapezoid rule is exact for constant acceleration: only round-off (≈ 1e-14 m).
        assert!((s.position - Vector3::new(150.0, 0.0, 0.0)).norm() < 1e-10);
        assert!((s.velocity - Vector3::new(20.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(s.attitude.norm() < 1e-15);
        // The configured gravity is the one used: 9.81 instead would leave 0.004 m/s² × 10 s.
        let other = Mechanization::local(9.81).unwrap();
        let mut o = x;
        for _ in 0..20 {
            o = propagate(&other, &o, &imu).unwrap();
        }
        assert!((o.velocity.z - (9.81 - FLAT_GRAVITY) * 10.0).abs() < 1e-12);
    }

    #[test]
    fn global_stationary_vehicle_stays_put() {
        // A vehicle at rest on the Earth feels f = −g_l (in body) and ω = C_eᵇ ω_ie^e, constant
        // in the body, so these are its exact increments; the mechanization must keep it at rest
        // with constant attitude (validates gravity, Coriolis and the Earth's turn).
        let g = Geodetic::from_degrees(45.0, 7.0, 300.0);
        let p = geodetic_to_ecef(&g);
        let att = Vector3::new(0.02, -0.03, 0.8);
        let c_bn = nav_from_body(&att);
        let c_ne = geodesy::ecef_from_ned(g.lat, g.lon);
        let f_b = -(c_bn.transpose() * c_ne.transpose() * geodesy::gravity_ecef(&p));
        let w_b = c_bn.transpose() * geodesy::earth_rate_ned(g.lat);
        let mut s = VehicleState {
            position: p,
            velocity: Vector3::zeros(),
            attitude: att,
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        };
        let imu = ImuSample {
            time: 0.0,
            dt: 0.01,
            specific_force: f_b,
            angular_rate: w_b,
        };
        for _ in 0..1000 {
            s = propagate(&Mechanization::global(), &s, &imu).unwrap();
        }
        // 10 s: what remains is rounding of the ≈ 10 m/s² cancellation per step (≈ 1e-15 m/s
        // each) and of the 6e6 m ECEF position.
        assert!(
            (s.position - p).norm() < 1e-6,
            "{}",
            (s.position - p).norm()
        );
        assert!(s.velocity.norm() < 1e-9, "{}", s.velocity.norm());
        assert!(
            (s.attitude - att).norm() < 1e-12,
            "{}",
            (s.attitude - att).norm()
        );
    }

    #[test]
    fn invalid_samples_and_gravity_are_typed_errors() {
        let x = local_state();
        let m = mechanization(NavFrame::Local);
        for dt in [0.0, -0.01, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                propagate(&m, &x, &sample(dt)),
                Err(InsError::InvalidInterval(_))
            ));
        }
        let mut bad = sample(0.01);
        bad.specific_force.y = f64::NAN;
        assert_eq!(propagate(&m, &x, &bad), Err(InsError::NonFiniteSample));
        let mut bad = sample(0.01);
        bad.angular_rate.z = f64::NEG_INFINITY;
        assert_eq!(propagate(&m, &x, &bad), Err(InsError::NonFiniteSample));
        for g in [0.0, -9.8, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                Mechanization::local(g),
                Err(InsError::InvalidGravity(_))
            ));
        }
        // The global frame ignores the local gravity (WGS-84 normal gravity everywhere).
        assert_eq!(
            Mechanization::new(NavFrame::Global, f64::NAN),
            Ok(Mechanization::global())
        );
        assert_eq!(Mechanization::global().local_gravity(), None);
        assert_eq!(m.local_gravity(), Some(FLAT_GRAVITY));
    }

    #[test]
    fn process_noise_scaling() {
        let n = crate::imu::ImuGrade::Tactical.noise();
        let q = process_noise(&n, 0.01);
        // Same closed-form arithmetic: equal to round-off of values ≈ 7e-5 and ≈ 1e-18.
        assert!((q[(W_ACCEL, W_ACCEL)] - n.accel_noise_density.powi(2) / 0.01).abs() < 1e-20);
        assert!(
            (q[(W_GYRO_BIAS + 2, W_GYRO_BIAS + 2)] - n.gyro_bias_rw_density.powi(2) * 0.01).abs()
                < 1e-30
        );
    }
}
