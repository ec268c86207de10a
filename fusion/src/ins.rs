//! Strapdown INS mechanization in both navigation frames, with the analytic Jacobians ∇F, ∇G of
//! the discrete process model (eqs. 21.19–21.25 global, 21.33–21.38 local) and the discrete
//! process-noise covariance Q of eq. 21.17.
//!
//! # The discrete equations (a contract: the world simulator inverts them)
//!
//! Global (ECEF p^e, v^e; Ψ relative to the local-level NED frame at the *current* position):
//! ```text
//! g      = ecef_to_geodetic(p_{k-1});  C_ne = ecef_from_ned(g.lat, g.lon)
//! C_bn   = nav_from_body(Ψ_{k-1});     C_be = C_ne · C_bn                         (21.11)
//! f      = f̂ − δf_{k-1};               ω = ω̂ − δω_{k-1}                           (21.13, 21.14)
//! v_k    = v_{k-1} + [C_be f − 2 ω_ie^e × v_{k-1} + g_l^e(p_{k-1})] Δt               (21.21)
//! p_k    = p_{k-1} + ½ (v_{k-1} + v_k) Δt                                         (21.20, trapezoid)
//! v^n    = C_neᵀ v_{k-1};  ω_in^n = ω_ie^n(λ) + ω_en^n(g, v^n)
//! Ψ_k    = Ψ_{k-1} + E_b^n(Ψ_{k-1}) (ω − C_bnᵀ ω_in^n) Δt                          (21.22 + ω_en)
//! δf_k   = δf_{k-1} + w_b,accel;  δω_k = δω_{k-1} + w_b,gyro                        (21.23, 21.24)
//! ```
//! Local (NED p^n, v^n, flat non-rotating Earth, eqs. 21.33–21.38): C_be → C_bn, no Coriolis,
//! g = [0, 0, [`LOCAL_GRAVITY`]], ω_in^n = 0.
//!
//! Deviations from the chapter, all deliberate:
//! * Position uses the trapezoid rule (second order) instead of eq. 21.20's Euler step
//!   p_k = p_{k-1} + v Δt, so a constant acceleration is integrated exactly.
//! * The attitude rate includes the transport rate ω_en^n of the local-level frame moving over the
//!   curved Earth, which eq. 21.5/21.22 omit (design.md §3).
//! * g_l^e is [`geodesy::gravity_ecef`] (Somigliana normal gravity, the erratum of eq. 21.10).
//!
//! # Noise (eq. 21.17)
//! w = [w_accel, w_gyro, w_b,accel, w_b,gyro] (offsets `state::W_*`) are discrete samples with
//! Cov(w_accel) = accel_noise_density²/Δt, Cov(w_gyro) = gyro_noise_density²/Δt (white noise
//! averaged over the interval, so v gains density²·Δt), Cov(w_b,·) = rw_density²·Δt (random walk).
//! w_accel enters v as −C_be w Δt and p as −½ C_be w Δt² (trapezoid); w_gyro enters Ψ as −E w Δt.

use crate::geodesy::{self, Geodetic, LOCAL_GRAVITY};
use crate::imu::ImuNoise;
use crate::rotation::{
    euler_rate_from_body_rate, euler_rate_from_body_rate_partials, nav_from_body,
    nav_from_body_partials, skew,
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

/// Why an IMU sample or a propagation was refused.
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
    /// x_k = F[x_{k-1}, u_k] with w = 0 (eqs. 21.20–21.24 / 21.33–21.37).
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

/// The state transition without Jacobians (what the world simulator inverts). Validates the sample.
pub fn propagate(
    frame: NavFrame,
    x: &VehicleState,
    imu: &ImuSample,
) -> Result<VehicleState, InsError> {
    Ok(propagate_with_jacobians(frame, x, imu)?.state)
}

/// Navigation-frame quantities at the prior position shared by the mean and the Jacobians.
struct FrameTerms {
    /// C_n^e at p (identity in local SLAM).
    ecef_from_ned: Matrix3<f64>,
    /// ∂C_n^e/∂p_j for the three position components (zero in local SLAM).
    ecef_from_ned_dp: [Matrix3<f64>; 3],
    /// Plumb-bob gravity g_l (ECEF) or [0, 0, g] (local).
    gravity: Vector3<f64>,
    /// ∂g_l/∂p.
    gravity_dp: Matrix3<f64>,
    /// ω_in^n = ω_ie^n + ω_en^n (zero in local SLAM).
    nav_rate: Vector3<f64>,
    /// ∂ω_in^n/∂p.
    nav_rate_dp: Matrix3<f64>,
    /// ∂ω_in^n/∂v.
    nav_rate_dv: Matrix3<f64>,
    /// Earth rate ω_ie^e for the Coriolis term (zero in local SLAM).
    earth_rate: Vector3<f64>,
}

/// ∂C/∂p_j = Σ_k ∂C/∂geo_k · ∂geo_k/∂p_j for C = C_n^e(λ, l) (independent of h).
fn ecef_from_ned_position_partials(g: &Geodetic, geo_from_p: &Matrix3<f64>) -> [Matrix3<f64>; 3] {
    let [d_lat, d_lon] = geodesy::ecef_from_ned_partials(g.lat, g.lon);
    std::array::from_fn(|j| d_lat * geo_from_p[(0, j)] + d_lon * geo_from_p[(1, j)])
}

/// ∂ω_in^n/∂(λ, h) and ∂ω_in^n/∂v^n for ω_in^n = ω_ie^n(λ) + ω_en^n(λ, h, v^n).
fn nav_rate_partials(
    g: &Geodetic,
    v_ned: &Vector3<f64>,
) -> (Vector3<f64>, Vector3<f64>, Matrix3<f64>) {
    let (m, n) = geodesy::radii_of_curvature(g.lat);
    let (s, c) = g.lat.sin_cos();
    let w2 = 1.0 - geodesy::WGS84_E2 * s * s;
    // dN/dλ = a e² sinλ cosλ / w³, dM/dλ = 3 a (1−e²) e² sinλ cosλ / w⁵ (w² = 1 − e² sin²λ).
    let dn = geodesy::WGS84_A * geodesy::WGS84_E2 * s * c / w2.powf(1.5);
    let dm = 3.0 * geodesy::WGS84_A * (1.0 - geodesy::WGS84_E2) * geodesy::WGS84_E2 * s * c
        / w2.powf(2.5);
    let (rn, rm) = (n + g.height, m + g.height);
    let t = g.lat.tan();
    let (vn, ve) = (v_ned.x, v_ned.y);
    let d_earth_dlat = Vector3::new(-geodesy::EARTH_RATE * s, 0.0, -geodesy::EARTH_RATE * c);
    let d_transport_dlat = Vector3::new(
        -ve * dn / (rn * rn),
        vn * dm / (rm * rm),
        -ve * (1.0 / (c * c) / rn - t * dn / (rn * rn)),
    );
    let d_dh = Vector3::new(-ve / (rn * rn), vn / (rm * rm), ve * t / (rn * rn));
    let d_dv = Matrix3::new(0.0, 1.0 / rn, 0.0, -1.0 / rm, 0.0, 0.0, 0.0, -t / rn, 0.0);
    (d_earth_dlat + d_transport_dlat, d_dh, d_dv)
}

fn frame_terms(frame: NavFrame, p: &Vector3<f64>, v: &Vector3<f64>) -> FrameTerms {
    match frame {
        NavFrame::Local => FrameTerms {
            ecef_from_ned: Matrix3::identity(),
            ecef_from_ned_dp: [Matrix3::zeros(); 3],
            gravity: Vector3::new(0.0, 0.0, LOCAL_GRAVITY),
            gravity_dp: Matrix3::zeros(),
            nav_rate: Vector3::zeros(),
            nav_rate_dp: Matrix3::zeros(),
            nav_rate_dv: Matrix3::zeros(),
            earth_rate: Vector3::zeros(),
        },
        NavFrame::Global => {
            let g = geodesy::ecef_to_geodetic(p);
            let c_ne = geodesy::ecef_from_ned(g.lat, g.lon);
            let geo_from_p = geodesy::geodetic_from_ecef_jacobian(&g);
            let c_dp = ecef_from_ned_position_partials(&g, &geo_from_p);
            let v_ned = c_ne.transpose() * v;
            let nav_rate = geodesy::earth_rate_ned(g.lat) + geodesy::transport_rate_ned(&g, &v_ned);
            let (d_dlat, d_dh, d_dvn) = nav_rate_partials(&g, &v_ned);
            // ω_in depends on p through (λ, h) and through v^n = C_neᵀ(p) v.
            let vn_dp = Matrix3::from_columns(&c_dp.map(|d| d.transpose() * v));
            let geo_part = Matrix3::from_columns(&[d_dlat, Vector3::zeros(), d_dh]) * geo_from_p;
            FrameTerms {
                ecef_from_ned: c_ne,
                ecef_from_ned_dp: c_dp,
                gravity: geodesy::gravity_ecef(p),
                gravity_dp: geodesy::gravity_ecef_jacobian(p),
                nav_rate,
                nav_rate_dp: geo_part + d_dvn * vn_dp,
                nav_rate_dv: d_dvn * c_ne.transpose(),
                earth_rate: geodesy::earth_rate_ecef(),
            }
        }
    }
}

/// One discrete INS step with its Jacobians ∇F (eq. 21.46/21.47; the map and stored-pose blocks
/// of the full ∇F are identity, eqs. 21.25/21.38) and ∇G, evaluated at the prior state.
pub fn propagate_with_jacobians(
    frame: NavFrame,
    x: &VehicleState,
    imu: &ImuSample,
) -> Result<Propagation, InsError> {
    validate_sample(imu)?;
    let dt = imu.dt;
    let t = frame_terms(frame, &x.position, &x.velocity);
    let c_bn = nav_from_body(&x.attitude);
    let c_bn_d = nav_from_body_partials(&x.attitude);
    let c_be = t.ecef_from_ned * c_bn;
    let e = euler_rate_from_body_rate(&x.attitude);
    let e_d = euler_rate_from_body_rate_partials(&x.attitude);

    let f = imu.specific_force - x.accel_bias; // (21.13)
    let w = imu.angular_rate - x.gyro_bias; // (21.14)
    // (21.21) / (21.34)
    let accel = c_be * f - 2.0 * t.earth_rate.cross(&x.velocity) + t.gravity;
    let v_next = x.velocity + accel * dt;
    let p_next = x.position + 0.5 * (x.velocity + v_next) * dt;
    // (21.22) with the transport rate / (21.35)
    let rel_rate = w - c_bn.transpose() * t.nav_rate;
    let att_next = x.attitude + e * rel_rate * dt;
    let state = VehicleState {
        position: p_next,
        velocity: v_next,
        attitude: att_next,
        accel_bias: x.accel_bias,
        gyro_bias: x.gyro_bias,
    };
    if !state.is_finite() {
        return Err(InsError::NonFiniteResult);
    }

    // ∂accel/∂(p, v, Ψ, δf).
    let mut a_dp = t.gravity_dp;
    for j in 0..3 {
        a_dp.set_column(j, &(a_dp.column(j) + t.ecef_from_ned_dp[j] * c_bn * f));
    }
    let a_dv = -2.0 * skew(&t.earth_rate);
    let a_datt = Matrix3::from_columns(&c_bn_d.map(|d| t.ecef_from_ned * d * f));
    let a_dbias = -c_be;

    // ∂(Ψ rate)/∂(p, v, Ψ, δω) with Ψ̇ = E(Ψ)(ω − C_bnᵀ ω_in).
    let r_dp = -(c_bn.transpose() * t.nav_rate_dp);
    let r_dv = -(c_bn.transpose() * t.nav_rate_dv);
    let mut psi_datt = Matrix3::zeros();
    for j in 0..3 {
        psi_datt.set_column(
            j,
            &(e_d[j] * rel_rate - e * (c_bn_d[j].transpose() * t.nav_rate)),
        );
    }

    let i3 = Matrix3::identity();
    let half_dt2 = 0.5 * dt * dt;
    let mut ff = TransitionJacobian::identity();
    // p_k = p + v Δt + ½ a Δt²
    ff.fixed_view_mut::<3, 3>(POS, POS)
        .copy_from(&(i3 + a_dp * half_dt2));
    ff.fixed_view_mut::<3, 3>(POS, VEL)
        .copy_from(&(i3 * dt + a_dv * half_dt2));
    ff.fixed_view_mut::<3, 3>(POS, ATT)
        .copy_from(&(a_datt * half_dt2));
    ff.fixed_view_mut::<3, 3>(POS, ACC_BIAS)
        .copy_from(&(a_dbias * half_dt2));
    // v_k = v + a Δt
    ff.fixed_view_mut::<3, 3>(VEL, POS).copy_from(&(a_dp * dt));
    ff.fixed_view_mut::<3, 3>(VEL, VEL)
        .copy_from(&(i3 + a_dv * dt));
    ff.fixed_view_mut::<3, 3>(VEL, ATT)
        .copy_from(&(a_datt * dt));
    ff.fixed_view_mut::<3, 3>(VEL, ACC_BIAS)
        .copy_from(&(a_dbias * dt));
    // Ψ_k = Ψ + E r Δt
    ff.fixed_view_mut::<3, 3>(ATT, POS)
        .copy_from(&(e * r_dp * dt));
    ff.fixed_view_mut::<3, 3>(ATT, VEL)
        .copy_from(&(e * r_dv * dt));
    ff.fixed_view_mut::<3, 3>(ATT, ATT)
        .copy_from(&(i3 + psi_datt * dt));
    ff.fixed_view_mut::<3, 3>(ATT, GYRO_BIAS)
        .copy_from(&(-e * dt));

    let mut gg = NoiseJacobian::zeros();
    gg.fixed_view_mut::<3, 3>(POS, W_ACCEL)
        .copy_from(&(-c_be * half_dt2));
    gg.fixed_view_mut::<3, 3>(VEL, W_ACCEL)
        .copy_from(&(-c_be * dt));
    gg.fixed_view_mut::<3, 3>(ATT, W_GYRO).copy_from(&(-e * dt));
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

/// The transition with an explicit noise sample w added (eq. 21.19 with G[w] linear in w for the
/// additive model above). Used to check ∇G by finite differences and by the simulator to inject
/// IMU noise consistently with the filter.
pub fn propagate_with_noise(
    frame: NavFrame,
    x: &VehicleState,
    imu: &ImuSample,
    w: &SVector<f64, NOISE_DIM>,
) -> Result<VehicleState, InsError> {
    // The noise enters exactly like a bias (w_accel, w_gyro, eqs. 21.13/21.14) plus a bias jump.
    let noisy = ImuSample {
        specific_force: imu.specific_force - w.fixed_rows::<3>(W_ACCEL),
        angular_rate: imu.angular_rate - w.fixed_rows::<3>(W_GYRO),
        ..*imu
    };
    let mut next = propagate(frame, x, &noisy)?;
    next.accel_bias += w.fixed_rows::<3>(W_ACC_BIAS);
    next.gyro_bias += w.fixed_rows::<3>(W_GYRO_BIAS);
    Ok(next)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geodesy::geodetic_to_ecef;

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

    /// Central differences of the transition w.r.t. the state; per-block steps.
    fn fd_transition(frame: NavFrame, x: &VehicleState, imu: &ImuSample) -> TransitionJacobian {
        let x0 = x.to_vector();
        let mut j = TransitionJacobian::zeros();
        for c in 0..VEHICLE_DIM {
            // Steps: 1 m in ECEF position and 1 m/s in ECEF velocity (the transition is affine in
            // v and curves in p only on the 6e6 m Earth scale, so truncation is ≈ 1e-13 relative),
            // 1e-3 m and 1e-3 m/s locally, 1e-4 rad / 1e-4 units for attitude and biases.
            let h = match (frame, c) {
                (NavFrame::Global, c) if c < ATT => 1.0,
                (_, c) if c < ATT => 1e-3,
                _ => 1e-4,
            };
            let mut xp = x0;
            let mut xm = x0;
            xp[c] += h;
            xm[c] -= h;
            let fp = propagate(frame, &VehicleState::from_vector(&xp), imu)
                .unwrap()
                .to_vector();
            let fm = propagate(frame, &VehicleState::from_vector(&xm), imu)
                .unwrap()
                .to_vector();
            j.set_column(c, &((fp - fm) / (2.0 * h)));
        }
        j
    }

    fn fd_noise(frame: NavFrame, x: &VehicleState, imu: &ImuSample) -> NoiseJacobian {
        let mut j = NoiseJacobian::zeros();
        for c in 0..NOISE_DIM {
            // The map is affine in w up to the dependence of E and C on nothing of w: 1e-4 steps
            // leave round-off ≈ 1e-16·6e6/1e-4 ≈ 6e-6 on ECEF positions (see tolerance below).
            let h = 1e-4;
            let mut wp = SVector::<f64, NOISE_DIM>::zeros();
            wp[c] = h;
            let fp = propagate_with_noise(frame, x, imu, &wp)
                .unwrap()
                .to_vector();
            let fm = propagate_with_noise(frame, x, imu, &(-wp))
                .unwrap()
                .to_vector();
            j.set_column(c, &((fp - fm) / (2.0 * h)));
        }
        j
    }

    #[test]
    fn transition_jacobian_matches_finite_differences_global_and_local() {
        // Δt = 0.1 s (larger than a real IMU step) and an unphysical 20 s, which magnifies the
        // tiny transport-rate couplings p→Ψ (≈ Δt·Ω/R) above the absolute floor of the check.
        let cases = [
            (NavFrame::Global, global_state()),
            (NavFrame::Local, local_state()),
        ];
        for ((frame, x), dt) in cases.iter().flat_map(|c| [(*c, 0.1), (*c, 20.0)]) {
            let imu = sample(dt);
            let analytic = propagate_with_jacobians(frame, &x, &imu)
                .unwrap()
                .transition;
            let fd = fd_transition(frame, &x, &imu);
            let y = propagate(frame, &x, &imu).unwrap().to_vector();
            let steps = |c: usize| match (frame, c) {
                (NavFrame::Global, c) if c < ATT => 1.0,
                (_, c) if c < ATT => 1e-3,
                _ => 1e-4,
            };
            for r in 0..VEHICLE_DIM {
                for c in 0..VEHICLE_DIM {
                    // Rounding of an output of size |y_r| is ≤ 2 ulp ≈ 4.4e-16·|y_r| per
                    // evaluation, so a central difference errs by ≤ 4.4e-16·|y_r|/h (ECEF
                    // positions: 6e6 m → 2.6e-5 at h = 1e-4); truncation ≤ 1e-6 relative;
                    // 1e-12 absolute floor. The p→Ψ couplings (≈ 2e-10 at Δt = 20 s) sit in
                    // rows with |y_r| ≈ 3 and h = 1 m, so they are checked at ≈ 1e-12.
                    let tol = 1e-12
                        + 1e-6 * analytic[(r, c)].abs()
                        + 4.4e-16 * y[r].abs().max(1.0) / steps(c);
                    assert!(
                        (analytic[(r, c)] - fd[(r, c)]).abs() < tol,
                        "{frame} dt {dt}: ∇F[{r},{c}] analytic {} vs fd {}",
                        analytic[(r, c)],
                        fd[(r, c)]
                    );
                }
            }
        }
    }

    #[test]
    fn transport_rate_and_position_couplings_are_nontrivial_in_global_frame() {
        // Guards the test above against checking only zeros: the p→Ψ and v→Ψ blocks exist.
        let imu = sample(0.1);
        let j = propagate_with_jacobians(NavFrame::Global, &global_state(), &imu)
            .unwrap()
            .transition;
        // Expected sizes at Δt = 0.1 s: v→Ψ ≈ Δt/R ≈ 1.6e-8, p→Ψ ≈ Δt·Ω/R ≈ 1e-12, p→v ≈ Δt·g/R
        // ≈ 1.5e-7; the bounds sit an order of magnitude below.
        assert!(j.fixed_view::<3, 3>(ATT, VEL).norm() > 1e-9);
        assert!(j.fixed_view::<3, 3>(ATT, POS).norm() > 1e-13);
        assert!(j.fixed_view::<3, 3>(VEL, POS).norm() > 1e-8);
    }

    #[test]
    fn noise_jacobian_matches_finite_differences_global_and_local() {
        for (frame, x) in [
            (NavFrame::Global, global_state()),
            (NavFrame::Local, local_state()),
        ] {
            let imu = sample(0.1);
            let analytic = propagate_with_jacobians(frame, &x, &imu).unwrap().noise;
            let fd = fd_noise(frame, &x, &imu);
            // G is exact for the affine noise entry; the 1e-5 bound is the ECEF round-off above.
            assert!(
                (analytic - fd).abs().max() < 1e-5,
                "{frame}: {}",
                (analytic - fd).abs().max()
            );
            // The bias blocks alone are identity (norm ≥ √6): the check is not vacuous.
            assert!(analytic.norm() > 1.0);
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
            specific_force: Vector3::new(1.0, 0.0, -LOCAL_GRAVITY),
            angular_rate: Vector3::zeros(),
        };
        let mut s = x;
        for _ in 0..20 {
            s = propagate(NavFrame::Local, &s, &imu).unwrap();
        }
        // Closed form after 10 s: p = v0 t + ½ a t² = 100 + 50; v = 20.
        // The trapezoid rule is exact for constant acceleration: only round-off (≈ 1e-14 m).
        assert!((s.position - Vector3::new(150.0, 0.0, 0.0)).norm() < 1e-10);
        assert!((s.velocity - Vector3::new(20.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(s.attitude.norm() < 1e-15);
    }

    #[test]
    fn global_stationary_vehicle_stays_put() {
        // A vehicle at rest on the Earth feels f = −g_l (in body) and ω = ω_ie^b; the mechanization
        // must keep it at rest with constant attitude (validates gravity, Coriolis and ω_in^n).
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
            s = propagate(NavFrame::Global, &s, &imu).unwrap();
        }
        // 10 s: the only drift is second-order (Coriolis on a velocity that stays at round-off).
        assert!(
            (s.position - p).norm() < 1e-6,
            "{}",
            (s.position - p).norm()
        );
        // Velocity/attitude stay at round-off level of the ≈ 10 m/s² cancellation per step.
        assert!(s.velocity.norm() < 1e-9);
        assert!((s.attitude - att).norm() < 1e-12);
    }

    #[test]
    fn invalid_samples_are_typed_errors() {
        let x = local_state();
        for dt in [0.0, -0.01, f64::NAN, f64::INFINITY] {
            assert!(matches!(
                propagate(NavFrame::Local, &x, &sample(dt)),
                Err(InsError::InvalidInterval(_))
            ));
        }
        let mut bad = sample(0.01);
        bad.specific_force.y = f64::NAN;
        assert_eq!(
            propagate(NavFrame::Local, &x, &bad),
            Err(InsError::NonFiniteSample)
        );
        let mut bad = sample(0.01);
        bad.angular_rate.z = f64::NEG_INFINITY;
        assert_eq!(
            propagate(NavFrame::Local, &x, &bad),
            Err(InsError::NonFiniteSample)
        );
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
