//! Initial alignment of a vehicle from a period at rest (coarse static alignment), for starting
//! the filter on real recordings.
//!
//! At rest the accelerometers measure the specific force f^b = −C_n^b g^n (eq. 21.13 with zero
//! acceleration), so the mean specific force gives roll and pitch ("levelling"), and the gyros
//! measure the Earth rate plus their bias, so the mean rate gives the gyro bias. What levelling
//! cannot tell:
//! - the accelerometer bias: a bias b tilts the levelled attitude by J·b (J below) and is
//!   otherwise invisible, so the bias estimate stays zero with its turn-on σ, and the attitude
//!   error and the bias error are correlated: Cov(δΨ, δf) = −J·σ_b² (see [`static_alignment`]);
//! - yaw and position: they *define* the navigation frame of a local run (zero, with small σ
//!   given by the caller), or come from elsewhere.
//!
//! With gravity along +z of the navigation frame (NED), f^b = g·(sin θ, −cos θ sin φ,
//! −cos θ cos φ) for the z-y-x Euler angles of [`crate::rotation`], hence
//! φ = atan2(−f_y, −f_z), θ = atan2(f_x, √(f_y² + f_z²)) ([`level_attitude`]).
//!
//! [`detect_rest`] finds the rest period at the start of a recording from the IMU alone;
//! [`rest_noise_density`] measures the IMU's white-noise densities over it (Allan variance).

use nalgebra::{Matrix2x3, SMatrix, Vector3};

use crate::imu::ImuNoise;
use crate::rotation::nav_from_body;
use crate::sensor::ImuSample;
use crate::state::{ACC_BIAS, ATT, GYRO_BIAS, POS, VEHICLE_DIM, VEL};

/// Why an alignment is impossible.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AlignmentError {
    /// Fewer samples than the statistics need.
    #[error("{got} IMU samples at rest; at least {needed} are needed")]
    TooFewSamples {
        /// Samples given.
        got: usize,
        /// Samples needed.
        needed: usize,
    },
    /// A sample is NaN or infinite.
    #[error("IMU sample {index} is not finite")]
    NonFinite {
        /// Its index.
        index: usize,
    },
    /// The mean specific force is too small to level on (free fall, or no accelerometer data).
    #[error("the mean specific force |f| = {0} m/s² is too small to level on")]
    NoGravity(f64),
    /// An option is out of range.
    #[error("invalid alignment option: {0}")]
    InvalidOption(String),
}

/// Fewest samples an alignment accepts (the sample covariance needs several).
pub const MIN_REST_SAMPLES: usize = 10;

/// Smallest mean specific force to level on [m/s²]: a tenth of gravity; below it the direction
/// of the mean is dominated by noise and biases.
pub const MIN_LEVELLING_FORCE: f64 = 0.98;

/// Roll φ and pitch θ [rad] of a body at rest whose accelerometers measure the specific force
/// `f` (body axes): φ = atan2(−f_y, −f_z), θ = atan2(f_x, √(f_y² + f_z²)) (module docs).
pub fn level_attitude(f: &Vector3<f64>) -> (f64, f64) {
    let r = f.y.hypot(f.z);
    ((-f.y).atan2(-f.z), f.x.atan2(r))
}

/// ∂(φ, θ)/∂f of [`level_attitude`] (rows φ, θ).
pub fn level_attitude_jacobian(f: &Vector3<f64>) -> Matrix2x3<f64> {
    let r2 = f.y * f.y + f.z * f.z;
    let r = r2.sqrt();
    let n2 = r2 + f.x * f.x;
    Matrix2x3::new(
        0.0,
        f.z / r2,
        -f.y / r2,
        r / n2,
        -f.x * f.y / (r * n2),
        -f.x * f.z / (r * n2),
    )
}

/// Mean and sample covariance of a set of vectors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VectorStatistics {
    /// Mean.
    pub mean: Vector3<f64>,
    /// Unbiased sample covariance of one vector (divide by the count for the mean's).
    pub covariance: nalgebra::Matrix3<f64>,
}

fn statistics(values: impl Iterator<Item = Vector3<f64>> + Clone) -> VectorStatistics {
    let n = values.clone().count() as f64;
    let mean = values.clone().fold(Vector3::zeros(), |a, v| a + v) / n;
    let covariance = values.fold(nalgebra::Matrix3::zeros(), |a, v| {
        let d = v - mean;
        a + d * d.transpose()
    }) / (n - 1.0).max(1.0);
    VectorStatistics { mean, covariance }
}

/// Covariance of a mean of `n` samples over `duration` seconds: the sample covariance / n, each
/// variance floored at the white-noise model's density²/duration (a short or quantised rest
/// period can look quieter than the sensor is).
fn mean_covariance(
    s: &VectorStatistics,
    n: usize,
    density: f64,
    duration: f64,
) -> nalgebra::Matrix3<f64> {
    let mut c = s.covariance / n as f64;
    let floor = density * density / duration;
    for i in 0..3 {
        c[(i, i)] = c[(i, i)].max(floor);
    }
    c
}

/// What the caller fixes: the frame-defining states and the Earth rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignmentOptions {
    /// Yaw of the body [rad] (0 defines a local frame whose x axis is the body's heading).
    pub yaw: f64,
    /// σ of that yaw [rad], > 0.
    pub yaw_sigma: f64,
    /// σ of the position [m] (zero position, > 0), per axis.
    pub position_sigma: f64,
    /// σ of the velocity [m/s] (zero velocity at rest, > 0), per axis.
    pub velocity_sigma: f64,
    /// The Earth rate ω_ie^n in the navigation-level frame [rad/s], when the filter models a
    /// rotating Earth (global SLAM, [`crate::geodesy::earth_rate_ned`] at the site's latitude):
    /// its projection into the body is subtracted from the mean rate. `None` in local SLAM,
    /// where the filter models no Earth rotation and the gyro bias absorbs it.
    pub earth_rate_nav: Option<Vector3<f64>>,
}

/// The result of a static alignment at the start of the rest period.
#[derive(Clone, Debug, PartialEq)]
pub struct StaticAlignment {
    /// Ψ = (φ, θ, ψ) [rad].
    pub attitude: Vector3<f64>,
    /// Gyro bias estimate δω^b [rad/s].
    pub gyro_bias: Vector3<f64>,
    /// Mean measured specific force over the rest period (body axes) [m/s²].
    pub mean_specific_force: Vector3<f64>,
    /// Mean measured rate [rad/s].
    pub mean_rate: Vector3<f64>,
    /// Covariance of (p, v, Ψ, δf^b, δω^b), 15 × 15, in the order of [`crate::state`]; the
    /// estimate's p, v and δf^b are zero.
    pub covariance: SMatrix<f64, VEHICLE_DIM, VEHICLE_DIM>,
    /// Samples used.
    pub samples: usize,
    /// Time span of the rest period [s] (sum of the samples' Δt).
    pub duration: f64,
}

/// Aligns a vehicle that was at rest over `samples` (body axes): roll and pitch from the mean
/// specific force, the gyro bias from the mean rate (less the projected Earth rate, if given),
/// the accelerometer bias left at zero with the turn-on σ of `noise`, yaw, position and velocity
/// as `options` fix them.
///
/// Covariance: δΨ_{φ,θ} = J·(b_a + n̄_f) with J = [`level_attitude_jacobian`] at the mean, so
/// P_ΨΨ = J (Σ_f̄ + σ_ba² I) Jᵀ, P_Ψ,δf = −J σ_ba², P_δf = σ_ba² I; the gyro bias variance is
/// that of the mean rate, Σ_ω̄, plus the bias random walk between the start of the period and
/// its mean, rw²·T/3; Σ_f̄ and Σ_ω̄ are the sample covariances over the count, floored at the
/// white-noise model's density²/T. With an Earth rate and a yaw σ, the horizontal Earth rate's
/// projection error (|ω_h|·σ_ψ)² is added to the gyro bias variance.
pub fn static_alignment(
    samples: &[ImuSample],
    noise: &ImuNoise,
    options: &AlignmentOptions,
) -> Result<StaticAlignment, AlignmentError> {
    if samples.len() < MIN_REST_SAMPLES {
        return Err(AlignmentError::TooFewSamples {
            got: samples.len(),
            needed: MIN_REST_SAMPLES,
        });
    }
    for (name, v) in [
        ("yaw_sigma", options.yaw_sigma),
        ("position_sigma", options.position_sigma),
        ("velocity_sigma", options.velocity_sigma),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(AlignmentError::InvalidOption(format!(
                "{name} = {v} must be finite and > 0"
            )));
        }
    }
    if !options.yaw.is_finite() {
        return Err(AlignmentError::InvalidOption("yaw is not finite".into()));
    }
    if let Some(index) = samples.iter().position(|s| {
        !(s.dt.is_finite()
            && s.specific_force.iter().all(|v| v.is_finite())
            && s.angular_rate.iter().all(|v| v.is_finite()))
    }) {
        return Err(AlignmentError::NonFinite { index });
    }
    let n = samples.len();
    let duration: f64 = samples.iter().map(|s| s.dt).sum();
    let f = statistics(samples.iter().map(|s| s.specific_force));
    let w = statistics(samples.iter().map(|s| s.angular_rate));
    let norm = f.mean.norm();
    if norm < MIN_LEVELLING_FORCE {
        return Err(AlignmentError::NoGravity(norm));
    }
    let (roll, pitch) = level_attitude(&f.mean);
    let attitude = Vector3::new(roll, pitch, options.yaw);
    let j = level_attitude_jacobian(&f.mean);

    let sigma_ba2 = noise.accel_bias_sigma.powi(2);
    let cov_f = mean_covariance(&f, n, noise.accel_noise_density, duration);
    let mut cov_w = mean_covariance(&w, n, noise.gyro_noise_density, duration)
        + nalgebra::Matrix3::identity() * (noise.gyro_bias_rw_density.powi(2) * duration / 3.0);

    let mut gyro_bias = w.mean;
    if let Some(earth) = options.earth_rate_nav {
        let body_from_nav = nav_from_body(&attitude).transpose();
        gyro_bias -= body_from_nav * earth;
        let horizontal = earth.x.hypot(earth.y);
        cov_w += nalgebra::Matrix3::identity() * (horizontal * options.yaw_sigma).powi(2);
    }

    let mut p = SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::zeros();
    for i in 0..3 {
        p[(POS + i, POS + i)] = options.position_sigma.powi(2);
        p[(VEL + i, VEL + i)] = options.velocity_sigma.powi(2);
        p[(ACC_BIAS + i, ACC_BIAS + i)] = sigma_ba2;
    }
    let p_level = j * (cov_f + nalgebra::Matrix3::identity() * sigma_ba2) * j.transpose();
    let p_level = (p_level + p_level.transpose()) * 0.5;
    let p_level_bias = -j * sigma_ba2;
    for r in 0..2 {
        for c in 0..2 {
            p[(ATT + r, ATT + c)] = p_level[(r, c)];
        }
        for c in 0..3 {
            p[(ATT + r, ACC_BIAS + c)] = p_level_bias[(r, c)];
            p[(ACC_BIAS + c, ATT + r)] = p_level_bias[(r, c)];
        }
    }
    p[(ATT + 2, ATT + 2)] = options.yaw_sigma.powi(2);
    for r in 0..3 {
        for c in 0..3 {
            p[(GYRO_BIAS + r, GYRO_BIAS + c)] = cov_w[(r, c)];
        }
    }
    Ok(StaticAlignment {
        attitude,
        gyro_bias,
        mean_specific_force: f.mean,
        mean_rate: w.mean,
        covariance: p,
        samples: n,
        duration,
    })
}

/// How [`detect_rest`] decides that the vehicle still rests.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RestDetection {
    /// Length of the windows whose means are compared [s].
    pub window_s: f64,
    /// A window whose mean specific force differs from the rest so far by more than this (norm)
    /// ends the rest [m/s²].
    pub max_force_change: f64,
    /// The same for the mean rate [rad/s].
    pub max_rate_change: f64,
    /// Shortest rest period accepted [s].
    pub min_rest_s: f64,
}

impl Default for RestDetection {
    /// 0.25 s windows; 0.2 m/s² and 0.02 rad/s: about four times the σ of a quarter-second mean
    /// of a MEMS IMU on a vehicle whose motors run (≈ 1 m/s² and 0.08 rad/s vibration per
    /// sample at 200 Hz, as on the EuRoC MAV), and far below the change a start of motion
    /// makes; 1 s minimum.
    fn default() -> Self {
        Self {
            window_s: 0.25,
            max_force_change: 0.2,
            max_rate_change: 0.02,
            min_rest_s: 1.0,
        }
    }
}

/// The number of samples at the start of `samples` during which the vehicle rests: consecutive
/// windows of `window_s` are accepted while each window's mean specific force and mean rate stay
/// within the thresholds of the mean over the windows accepted so far; the last accepted window
/// is dropped (motion may start inside it). `None` when the rest is shorter than `min_rest_s`
/// (or the samples are not finite).
pub fn detect_rest(samples: &[ImuSample], cfg: &RestDetection) -> Option<usize> {
    if !(cfg.window_s > 0.0 && cfg.min_rest_s >= 0.0) {
        return None;
    }
    let t0 = samples.first()?.time - samples.first()?.dt;
    // Window boundaries: indices where the elapsed time crosses a multiple of window_s.
    let mut windows: Vec<(usize, usize)> = Vec::new();
    let mut start = 0;
    for (i, s) in samples.iter().enumerate() {
        if !(s.time.is_finite()
            && s.specific_force.iter().all(|v| v.is_finite())
            && s.angular_rate.iter().all(|v| v.is_finite()))
        {
            break;
        }
        let k = ((s.time - t0) / cfg.window_s).floor() as usize;
        if k > windows.len() {
            windows.push((start, i + 1));
            start = i + 1;
        }
    }
    let mut sum_f = Vector3::zeros();
    let mut sum_w = Vector3::zeros();
    let mut count = 0usize;
    let mut accepted = 0;
    for &(a, b) in &windows {
        let n = (b - a) as f64;
        if n == 0.0 {
            continue;
        }
        let wf = samples[a..b]
            .iter()
            .fold(Vector3::zeros(), |s, x| s + x.specific_force)
            / n;
        let ww = samples[a..b]
            .iter()
            .fold(Vector3::zeros(), |s, x| s + x.angular_rate)
            / n;
        if count > 0 {
            let rf = sum_f / count as f64;
            let rw = sum_w / count as f64;
            if (wf - rf).norm() > cfg.max_force_change || (ww - rw).norm() > cfg.max_rate_change {
                break;
            }
        }
        sum_f += wf * n;
        sum_w += ww * n;
        count += b - a;
        accepted += 1;
    }
    // Drop the last accepted window: the motion may already have started inside it.
    let end = if accepted >= 2 {
        windows[accepted - 2].1
    } else {
        0
    };
    let rest_s = if end > 0 {
        samples[end - 1].time - t0
    } else {
        0.0
    };
    (end > 0 && rest_s >= cfg.min_rest_s).then_some(end)
}

/// White-noise densities of an IMU measured over a rest period ([`rest_noise_density`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RestNoise {
    /// Gyro white-noise density [rad/s/√Hz] (RMS over the axes).
    pub gyro_density: f64,
    /// Accelerometer white-noise density [m/s²/√Hz] (RMS over the axes).
    pub accel_density: f64,
    /// Averaging times the estimate was taken over [s] (the largest value over them is kept).
    pub taus: (f64, f64),
}

/// The white-noise densities an estimator should assume for an IMU, measured on the recording
/// itself over a rest period: for averaging times τ = m·Δt on an octave grid from `min_tau`
/// (the interval the filter propagates on the IMU alone, a camera frame) up to `max_tau` and
/// at most a twelfth of the period (≥ 12 clusters), the Allan variance σ²(τ) =
/// ½⟨(ȳ_{k+1} − ȳ_k)²⟩ of non-overlapping cluster means ȳ_k; white noise of density N has
/// σ²(τ) = N²/τ, so N(τ) = √(σ²(τ)·τ) (RMS over the three axes). The largest N(τ) over the grid
/// is returned (conservative: at these τ the vibration of running motors adds to the sensor's
/// own noise, and the datasheet figure — for a still sensor — underestimates it; a bias
/// instability would lower N(τ) at large τ, never raise it). Below `min_tau` vibration at
/// motor frequencies averages out within one propagation interval and is not counted.
///
/// `None` when the samples are not finite, `min_tau`/`max_tau` are not positive and ordered, or
/// the period holds fewer than 12 clusters of `min_tau`.
pub fn rest_noise_density(samples: &[ImuSample], min_tau: f64, max_tau: f64) -> Option<RestNoise> {
    if !(min_tau > 0.0 && max_tau >= min_tau) {
        return None;
    }
    let n = samples.len();
    let ok = samples.iter().all(|s| {
        s.dt.is_finite()
            && s.dt > 0.0
            && s.specific_force.iter().all(|v| v.is_finite())
            && s.angular_rate.iter().all(|v| v.is_finite())
    });
    if !ok || n == 0 {
        return None;
    }
    let dt = samples.iter().map(|s| s.dt).sum::<f64>() / n as f64;
    const MIN_CLUSTERS: usize = 12;
    let mut m = ((min_tau / dt).round() as usize).max(1);
    let (mut gyro, mut accel): (f64, f64) = (0.0, 0.0);
    let (mut lo, mut hi) = (f64::NAN, f64::NAN);
    while n / m >= MIN_CLUSTERS && (m as f64) * dt <= max_tau * (1.0 + 1e-9) {
        let tau = m as f64 * dt;
        let means: Vec<(Vector3<f64>, Vector3<f64>)> = samples
            .chunks_exact(m)
            .map(|c| {
                let f = c.iter().fold(Vector3::zeros(), |a, s| a + s.specific_force);
                let w = c.iter().fold(Vector3::zeros(), |a, s| a + s.angular_rate);
                (f / m as f64, w / m as f64)
            })
            .collect();
        let k = (means.len() - 1) as f64;
        let (mut avar_f, mut avar_w) = (0.0, 0.0);
        for p in means.windows(2) {
            avar_f += 0.5 * (p[1].0 - p[0].0).norm_squared() / k;
            avar_w += 0.5 * (p[1].1 - p[0].1).norm_squared() / k;
        }
        // norm² sums the axes: /3 for the RMS over them.
        accel = accel.max((avar_f / 3.0 * tau).sqrt());
        gyro = gyro.max((avar_w / 3.0 * tau).sqrt());
        if lo.is_nan() {
            lo = tau;
        }
        hi = tau;
        m *= 2;
    }
    (!lo.is_nan()).then_some(RestNoise {
        gyro_density: gyro,
        accel_density: accel,
        taus: (lo, hi),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn noise() -> ImuNoise {
        crate::imu::ImuGrade::Consumer.noise()
    }

    /// Samples of a body at rest with attitude `att` under gravity g (NED, down +z), with
    /// biases and the white noise of `nz` at `rate` Hz.
    #[allow(clippy::too_many_arguments)]
    fn at_rest(
        nz: &ImuNoise,
        att: Vector3<f64>,
        accel_bias: Vector3<f64>,
        gyro_bias: Vector3<f64>,
        n: usize,
        rate: f64,
        seed: u64,
    ) -> Vec<ImuSample> {
        let g = 9.81;
        let dt = 1.0 / rate;
        // f^b = −C_n^b g^n, from the rotation module (independent of level_attitude).
        let f = -(nav_from_body(&att).transpose() * Vector3::new(0.0, 0.0, g));
        let sf = Normal::new(0.0, nz.accel_noise_density / dt.sqrt()).unwrap();
        let sw = Normal::new(0.0, nz.gyro_noise_density / dt.sqrt()).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (1..=n)
            .map(|k| ImuSample {
                time: k as f64 * dt,
                dt,
                specific_force: f + accel_bias + Vector3::from_fn(|_, _| sf.sample(&mut rng)),
                angular_rate: gyro_bias + Vector3::from_fn(|_, _| sw.sample(&mut rng)),
            })
            .collect()
    }

    fn options() -> AlignmentOptions {
        AlignmentOptions {
            yaw: 0.0,
            yaw_sigma: 1e-4,
            position_sigma: 1e-3,
            velocity_sigma: 1e-3,
            earth_rate_nav: None,
        }
    }

    #[test]
    fn levelling_inverts_the_gravity_projection() {
        for att in [
            Vector3::new(0.1, -0.2, 0.3),
            Vector3::new(-1.2, 0.7, -2.0),
            Vector3::new(0.0, 0.0, 1.0),
            Vector3::new(3.0, -1.3, 0.0),
        ] {
            let f = -(nav_from_body(&att).transpose() * Vector3::new(0.0, 0.0, 9.81));
            let (r, p) = level_attitude(&f);
            // Round-off of atan2 on O(10) inputs.
            assert!(
                (r - att.x).abs() < 1e-12 && (p - att.y).abs() < 1e-12,
                "{att}"
            );
        }
    }

    #[test]
    fn levelling_jacobian_matches_central_differences() {
        let f = Vector3::new(1.3, -2.1, -9.2);
        let j = level_attitude_jacobian(&f);
        let h = 1e-6;
        for c in 0..3 {
            let mut a = f;
            let mut b = f;
            a[c] += h;
            b[c] -= h;
            let (ra, pa) = level_attitude(&a);
            let (rb, pb) = level_attitude(&b);
            // Central differences: truncation O(h²) ≈ 1e-12, round-off ≈ 1e-16/h = 1e-10.
            assert!((j[(0, c)] - (ra - rb) / (2.0 * h)).abs() < 1e-8);
            assert!((j[(1, c)] - (pa - pb) / (2.0 * h)).abs() < 1e-8);
        }
    }

    #[test]
    fn alignment_recovers_roll_pitch_and_gyro_bias() {
        let att = Vector3::new(0.05, -0.4, 0.0);
        let bg = Vector3::new(0.01, -0.08, 0.003);
        let s = at_rest(&noise(), att, Vector3::zeros(), bg, 2000, 200.0, 1);
        let a = static_alignment(&s, &noise(), &options()).unwrap();
        let p = &a.covariance;
        for (k, i) in [(0, ATT), (1, ATT + 1)] {
            let sigma = p[(i, i)].sqrt();
            // 5σ: a single seeded draw.
            assert!((a.attitude[k] - att[k]).abs() < 5.0 * sigma, "{k}");
        }
        for k in 0..3 {
            let sigma = p[(GYRO_BIAS + k, GYRO_BIAS + k)].sqrt();
            assert!((a.gyro_bias[k] - bg[k]).abs() < 5.0 * sigma, "{k}");
        }
        assert_eq!(a.samples, 2000);
        assert!((a.duration - 10.0).abs() < 1e-9);
        assert!(a.covariance.cholesky().is_some());
        assert!((a.covariance - a.covariance.transpose()).abs().max() == 0.0);
    }

    /// Monte Carlo over accelerometer biases drawn from the turn-on σ and noise: the roll/pitch
    /// errors and the bias "errors" are consistent with the covariance (mean NEES of the 5-state
    /// (φ, θ, δf) block within its 99 % band for 400 runs). Tactical grade: the attitude error
    /// is almost all J·b, and the NEES weighs what is left against the mean's noise, so the
    /// second-order terms of atan2, ≈ (b/g)², must stay well below that noise; with a consumer
    /// IMU's 10 mg bias they do not (measured: mean NEES 5.66).
    #[test]
    fn alignment_covariance_is_consistent_over_bias_draws() {
        let nz = crate::imu::ImuGrade::Tactical.noise();
        let runs = 400;
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let sb = Normal::new(0.0, nz.accel_bias_sigma).unwrap();
        let att = Vector3::new(-0.3, 0.2, 0.0);
        let idx = [ATT, ATT + 1, ACC_BIAS, ACC_BIAS + 1, ACC_BIAS + 2];
        let mut total = 0.0;
        for r in 0..runs {
            let ba = Vector3::from_fn(|_, _| sb.sample(&mut rng));
            let s = at_rest(&nz, att, ba, Vector3::zeros(), 400, 100.0, 100 + r);
            let a = static_alignment(&s, &nz, &options()).unwrap();
            let e = nalgebra::SVector::<f64, 5>::from_column_slice(&[
                a.attitude.x - att.x,
                a.attitude.y - att.y,
                -ba.x,
                -ba.y,
                -ba.z,
            ]);
            let p = nalgebra::SMatrix::<f64, 5, 5>::from_fn(|i, j| a.covariance[(idx[i], idx[j])]);
            total += e.dot(&p.cholesky().unwrap().solve(&e));
        }
        let mean = total / runs as f64;
        // 99 % band of the mean of 400 χ²₅ / 400 draws: 5 ± 2.576·√(10/400).
        let half = 2.576 * (10.0_f64 / runs as f64).sqrt();
        assert!((mean - 5.0).abs() < half, "mean NEES {mean}");
    }

    #[test]
    fn earth_rate_is_removed_from_the_gyro_bias() {
        let lat = 47.4_f64.to_radians();
        let earth = crate::geodesy::earth_rate_ned(lat);
        let att = Vector3::new(0.1, 0.2, 0.7);
        // Perfect gyro at rest measures C_n^b ω_ie^n.
        let measured = nav_from_body(&att).transpose() * earth;
        let mut s = at_rest(&noise(), att, Vector3::zeros(), measured, 100, 100.0, 3);
        for x in &mut s {
            x.angular_rate = measured;
        }
        let opts = AlignmentOptions {
            yaw: 0.7,
            earth_rate_nav: Some(earth),
            ..options()
        };
        let a = static_alignment(&s, &noise(), &opts).unwrap();
        // Only levelling errors of the noisy accelerometers (≈ 1e-3 rad) tilt the projection of
        // a 7e-5 rad/s rate: below 1e-6 rad/s.
        assert!(a.gyro_bias.norm() < 1e-6, "{}", a.gyro_bias);
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        let s = at_rest(
            &noise(),
            Vector3::zeros(),
            Vector3::zeros(),
            Vector3::zeros(),
            5,
            100.0,
            1,
        );
        assert!(matches!(
            static_alignment(&s, &noise(), &options()),
            Err(AlignmentError::TooFewSamples { got: 5, .. })
        ));
        let mut s = at_rest(
            &noise(),
            Vector3::zeros(),
            Vector3::zeros(),
            Vector3::zeros(),
            50,
            100.0,
            1,
        );
        s[7].angular_rate.y = f64::NAN;
        assert_eq!(
            static_alignment(&s, &noise(), &options()),
            Err(AlignmentError::NonFinite { index: 7 })
        );
        let mut s = at_rest(
            &noise(),
            Vector3::zeros(),
            Vector3::zeros(),
            Vector3::zeros(),
            50,
            100.0,
            1,
        );
        for x in &mut s {
            x.specific_force = Vector3::new(0.01, 0.0, 0.0);
        }
        assert!(matches!(
            static_alignment(&s, &noise(), &options()),
            Err(AlignmentError::NoGravity(_))
        ));
        let s = at_rest(
            &noise(),
            Vector3::zeros(),
            Vector3::zeros(),
            Vector3::zeros(),
            50,
            100.0,
            1,
        );
        let bad = AlignmentOptions {
            yaw_sigma: 0.0,
            ..options()
        };
        assert!(matches!(
            static_alignment(&s, &noise(), &bad),
            Err(AlignmentError::InvalidOption(_))
        ));
    }

    #[test]
    fn rest_detection_stops_where_motion_starts() {
        let mut s = at_rest(
            &noise(),
            Vector3::new(0.1, 0.0, 0.0),
            Vector3::zeros(),
            Vector3::new(0.0, 0.05, 0.0),
            1000,
            200.0,
            5,
        );
        // Motion from t = 3 s: a 1 m/s² push and a 0.2 rad/s turn.
        for x in s.iter_mut().filter(|x| x.time > 3.0) {
            x.specific_force.x += 1.0;
            x.angular_rate.z += 0.2;
        }
        let n = detect_rest(&s, &RestDetection::default()).unwrap();
        let end = s[n - 1].time;
        // Accepted windows end at multiples of 0.25 s, the last one dropped: 2.5 s ≤ end ≤ 3 s.
        assert!((2.5 - 1e-9..=3.0 + 1e-9).contains(&end), "rest until {end}");
        // Moving from the start: no rest.
        let mut moving = s.clone();
        for (k, x) in moving.iter_mut().enumerate() {
            x.angular_rate.z = 0.01 * k as f64;
        }
        assert_eq!(detect_rest(&moving, &RestDetection::default()), None);
    }

    /// White noise of known density is recovered (closed form: σ²(τ) = N²/τ), and a strong
    /// vibration whose period divides the frame interval adds nothing, although it dominates the
    /// per-sample spread.
    #[test]
    fn rest_noise_density_recovers_white_noise_and_ignores_vibration() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let dt: f64 = 0.005;
        let (nw, nf) = (1.0e-3, 1.5e-2);
        let gw = Normal::new(0.0, nw / dt.sqrt()).unwrap();
        let gf = Normal::new(0.0, nf / dt.sqrt()).unwrap();
        let mut plain = Vec::new();
        let mut shaken = Vec::new();
        for k in 1..=2000 {
            let t = k as f64 * dt;
            let w = Vector3::from_fn(|_, _| gw.sample(&mut rng));
            let f = Vector3::from_fn(|_, _| gf.sample(&mut rng)) + Vector3::new(0.0, 0.0, -9.81);
            let s = ImuSample {
                time: t,
                dt,
                specific_force: f,
                angular_rate: w + Vector3::new(0.07, 0.02, 0.03),
            };
            plain.push(s);
            // 40 Hz (whole periods in every cluster of τ = 0.05·2^j s, so each cluster mean
            // cancels it), 1 m/s² and 0.05 rad/s: far above the white noise per sample.
            let v = (2.0 * std::f64::consts::PI * 40.0 * t).sin();
            shaken.push(ImuSample {
                specific_force: s.specific_force + Vector3::new(1.0, 0.5, 0.8) * v,
                angular_rate: s.angular_rate + Vector3::new(0.05, 0.03, 0.02) * v,
                ..s
            });
        }
        for samples in [&plain, &shaken] {
            let r = rest_noise_density(samples, 0.05, 1.0).unwrap();
            assert!(
                (r.taus.0 - 0.05).abs() < 1e-12 && r.taus.1 <= 1.0 + 1e-9,
                "{r:?}"
            );
            // The largest of 4–5 Allan estimates with ≥ 12 clusters each (RMS over 3 axes):
            // within −15 %/+35 % of the density (≈ 3σ of the estimator's spread, biased up by
            // the max).
            for (got, want) in [(r.gyro_density, nw), (r.accel_density, nf)] {
                assert!(
                    got > 0.85 * want && got < 1.35 * want,
                    "{got} vs {want} ({r:?})"
                );
            }
        }
        // The per-sample spread of the shaken sensor would claim a density ≈ 2.7× too large.
        let sd = (shaken
            .iter()
            .map(|s| (s.angular_rate.x - 0.07).powi(2))
            .sum::<f64>()
            / shaken.len() as f64)
            .sqrt();
        assert!(sd * dt.sqrt() > 2.0 * nw, "{sd}");
        // Too short a period for 12 clusters; bad arguments; non-finite samples.
        assert!(rest_noise_density(&plain[..100], 0.05, 1.0).is_none());
        assert!(rest_noise_density(&plain, 0.0, 1.0).is_none());
        let mut bad = plain.clone();
        bad[7].angular_rate.y = f64::NAN;
        assert!(rest_noise_density(&bad, 0.05, 1.0).is_none());
    }
}
