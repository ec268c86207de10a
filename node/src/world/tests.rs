//! Tests of the assembled simulator: determinism, IMU synthesis and noise statistics, terrain
//! sensor geometry and limits, global-frame truth, descriptor mismatches, features, initial
//! estimates. Reference values come from closed forms, independent computations written here
//! (other rotation and frame code paths), or statistics of many seeded draws.

use std::sync::Arc;

use canopy_fusion::geodesy::{Geodetic, ecef_to_geodetic, geodetic_to_ecef};
use canopy_fusion::imu::ImuGrade;
use canopy_fusion::ins::{VehicleState, propagate};
use canopy_fusion::rotation::{nav_from_body, wrap_angle};
use canopy_fusion::sensor::{Measurement, SensorModel};
use canopy_fusion::state::{ATT, NavFrame, POS, VEHICLE_DIM, VEL};
use nalgebra::{Matrix3, Rotation3, Vector3};

use super::*;
use crate::scenario::{
    EarthModel, ImuConfig, ImuSynthesis, ImuTruthModel, SensorConfig, SensorModelConfig,
    ShapeConfig, TrajectoryConfig, VehicleConfig,
};

/// A world whose sensors report true ids (`identity = "perfect"`): these tests check the
/// sensor model against truth id by id; the appearance model has its own tests below.
fn world(model: EarthModel, seed: u64) -> Arc<World> {
    let cfg = WorldConfig {
        seed,
        earth_model: model,
        appearance: crate::scenario::AppearanceConfig {
            identity: crate::scenario::Identity::Perfect,
            ..Default::default()
        },
        ..WorldConfig::default()
    };
    Arc::new(World::new(&cfg, seed).unwrap())
}

fn vehicle_cfg(shape: ShapeConfig) -> VehicleConfig {
    VehicleConfig {
        id: 7,
        name: None,
        frame: None,
        trajectory: Some(TrajectoryConfig {
            altitude_m: 150.0,
            speed_mps: 25.0,
            shape,
            ..TrajectoryConfig::default()
        }),
        sensor: SensorConfig::default(),
        imu: ImuConfig::default(),
        initial: Default::default(),
        replay: None,
        bearing: Default::default(),
    }
}

fn lawnmower() -> ShapeConfig {
    ShapeConfig::Lawnmower {
        leg_length_m: 1800.0,
        leg_spacing_m: 250.0,
        legs: 4,
        turn_ramp_fraction: 0.4,
    }
}

/// The same seed gives bit-identical outputs; another seed gives different noise.
#[test]
fn simulation_is_deterministic_for_a_seed() {
    let run = |seed: u64| {
        let mut cfg = vehicle_cfg(lawnmower());
        cfg.sensor.mismatch_probability = 0.1;
        let w = world(EarthModel::Wgs84, seed);
        let mut v = VehicleSim::new(&cfg, w.clone(), vehicle_seed(seed, cfg.id)).unwrap();
        let init = v.initial_estimate().clone();
        let outs: Vec<StepOutput> = (0..600).map(|_| v.step()).collect();
        (w.features().to_vec(), init, outs)
    };
    let (a, b, c) = (run(11), run(11), run(12));
    assert_eq!(a.0, b.0);
    assert_eq!(a.1, b.1);
    assert_eq!(a.2, b.2);
    assert!(a.2.iter().filter(|o| o.frame.is_some()).count() == 12);
    assert_ne!(a.0, c.0, "another world seed moves the features");
    assert_ne!(a.2[0].imu, c.2[0].imu, "another seed changes the noise");
    // The truth does not depend on the seed (only on the trajectory).
    assert_eq!(a.2[599].truth.position, c.2[599].truth.position);
}

/// Noise-free `discrete` samples (the ablation) fed through the estimator's mechanization
/// (`fusion::ins::propagate`, the contract they invert) reproduce the truth: per step to
/// rounding in v and Ψ, and over a 120 s free run (including turns) the position drifts only by
/// the trapezoidal rule's truncation.
#[test]
fn discrete_synthesis_inverts_the_mechanization() {
    for model in [EarthModel::Wgs84, EarthModel::Flat] {
        let mut cfg = vehicle_cfg(lawnmower());
        cfg.imu.grade = ImuGrade::Perfect;
        cfg.imu.synthesis = ImuSynthesis::Discrete;
        cfg.trajectory.as_mut().unwrap().phase = 0.2; // starts shortly before the first turn
        cfg.trajectory.as_mut().unwrap().climb_amplitude_m = 8.0;
        let w = world(model, 3);
        let m = *w.mechanization();
        let mut v = VehicleSim::new(&cfg, w, 5).unwrap();
        let state = |n: &NavTruth| VehicleState {
            position: n.position,
            velocity: n.velocity,
            attitude: n.attitude,
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        };
        let mut free = state(&v.truth().nav());
        let (mut step_v, mut step_att) = (0.0f64, 0.0f64);
        let (mut free_p, mut free_v, mut free_att) = (0.0f64, 0.0f64, 0.0f64);
        for _ in 0..12_000 {
            let prev = v.truth().nav();
            let out = v.step();
            assert_eq!(out.imu, out.imu_ideal, "perfect grade adds nothing");
            let one = propagate(&m, &state(&prev), &out.imu).unwrap();
            step_v = step_v.max((one.velocity - out.truth.velocity).norm());
            step_att = step_att.max((one.attitude - out.truth.attitude).map(wrap_angle).norm());
            free = propagate(&m, &free, &out.imu).unwrap();
            free_p = free_p.max((free.position - out.truth.position).norm());
            free_v = free_v.max((free.velocity - out.truth.velocity).norm());
            free_att = free_att.max((free.attitude - out.truth.attitude).map(wrap_angle).norm());
        }
        eprintln!(
            "{model:?}: one-step |Δv| {step_v:.1e} |ΔΨ| {step_att:.1e}; 120 s free run |Δp| {free_p:.2e} \
             |Δv| {free_v:.1e} |ΔΨ| {free_att:.1e}"
        );
        // Rounding: v ~ 25 m/s and ECEF p ~ 6e6 m enter the inverse; 1e-9 m/s and 1e-11 rad
        // leave ~100× margin over the double-precision residue.
        assert!(step_v < 1e-9, "{model:?}: {step_v}");
        assert!(step_att < 1e-11, "{model:?}: {step_att}");
        // Trapezoid truncation Δt²/12·|Δa| telescopes (≈ 1e-4 m for |Δa| ≲ 10 m/s²); velocity
        // and attitude then only feel the position error through gravity and C_n^e(p).
        assert!(free_p < 1e-3, "{model:?}: {free_p}");
        assert!(
            free_v < 1e-6 && free_att < 1e-8,
            "{model:?}: {free_v} {free_att}"
        );
    }
}

/// Largest differences (|Δf̂|, |Δω̂|) between two syntheses over the intervals of length `dt`
/// tiling [`start`, `start + span`).
fn synthesis_difference(
    v: &VehicleSim,
    a: ImuSynthesis,
    b: ImuSynthesis,
    start: f64,
    span: f64,
    dt: f64,
) -> (f64, f64) {
    let (mut df, mut dw) = (0.0f64, 0.0f64);
    for i in 0..(span / dt) as usize {
        let t0 = start + i as f64 * dt;
        let x = v.ideal_imu(t0, t0 + dt, a);
        let y = v.ideal_imu(t0, t0 + dt, b);
        df = df.max((x.specific_force - y.specific_force).norm());
        dw = dw.max((x.angular_rate - y.angular_rate).norm());
    }
    (df, dw)
}

/// The default `exact` synthesis and the `discrete` inverse of the mechanization: identical in
/// the flat world (the local step is exact for exact increments), and in the rotating world
/// apart by the step's O(Δt³) truncation per step (gravity and Coriolis at the midpoint, the
/// Earth's turn to first order in ΩΔt), i.e. O(Δt²) in f̂: a 4× shorter step gives a ≈ 16×
/// smaller difference. A sign error in the Earth rate or Coriolis term of either would differ
/// by ≈ 1e-4 rad/s or 4e-3 m/s² and not shrink with Δt.
#[test]
fn exact_and_discrete_synthesis_agree_to_the_mechanizations_truncation() {
    for model in [EarthModel::Wgs84, EarthModel::Flat] {
        let mut cfg = vehicle_cfg(lawnmower());
        cfg.trajectory.as_mut().unwrap().climb_amplitude_m = 8.0;
        let v = VehicleSim::new(&cfg, world(model, 3), 5).unwrap();
        // The first turn spans t ≈ 72–94 s; the leg before it is straight.
        let diff = |dt| {
            synthesis_difference(
                &v,
                ImuSynthesis::Exact,
                ImuSynthesis::Discrete,
                66.0,
                30.0,
                dt,
            )
        };
        let (f1, w1) = diff(0.01);
        let (f4, w4) = diff(0.0025);
        eprintln!(
            "{model:?}: exact vs discrete, Δt 10 ms |Δf| {f1:.2e} |Δω| {w1:.2e}; Δt 2.5 ms |Δf| {f4:.2e} |Δω| {w4:.2e}"
        );
        // The attitude update is exact in both frames: only rounding of Δθ/Δt (≈ 1e-16/Δt).
        assert!(w1 < 1e-12 && w4 < 1e-11, "{model:?}: {w1} {w4}");
        match model {
            // Same closed form up to rounding of (v_k − v_{k−1})/Δt.
            EarthModel::Flat => assert!(f1 < 1e-11 && f4 < 1e-10, "{f1} {f4}"),
            EarthModel::Wgs84 => {
                // Gravity gradient × ⅛aΔt², Coriolis × Δt·a: ≲ 1e-8 m/s² at 10 ms.
                assert!(f1 < 1e-7, "{f1}");
                // Second order (16×), with room for the rounding floor at 2.5 ms.
                assert!(f1 / f4 > 8.0, "{}", f1 / f4);
            }
        }
    }
}

/// On straight level flight the `continuous` ablation (rates at the interval midpoint in the
/// launch frame) agrees with the exact increments to ~1e-7: a sign error in the Coriolis term
/// (3.6e-3 m/s² at 25 m/s), the Earth rate (1.5e-4 rad/s) or gravity in either would stand out.
/// In turns midpoint rates miss the coning and sculling terms, O(Δt²) in the rates: the
/// difference shrinks ≈ 16× for a 4× shorter step.
#[test]
fn continuous_and_exact_synthesis_agree() {
    for model in [EarthModel::Wgs84, EarthModel::Flat] {
        let cfg = vehicle_cfg(lawnmower());
        let v = VehicleSim::new(&cfg, world(model, 3), 5).unwrap();
        // First leg: 1800 m at 25 m/s from t = 0.
        let (df, dw) = synthesis_difference(
            &v,
            ImuSynthesis::Exact,
            ImuSynthesis::Continuous,
            2.0,
            50.0,
            0.01,
        );
        eprintln!("{model:?} straight leg: |Δf| {df:.1e} m/s², |Δω| {dw:.1e} rad/s");
        // Earth-rate coupling of the rotating body over half a step (ΩΔt·|f| ≈ 7e-6·... ) and
        // the gravity gradient: ≪ 1e-6 m/s²; body rates differ by O(Δt²·Ω²).
        assert!(df < 1e-6, "{model:?}: {df}");
        assert!(dw < 1e-9, "{model:?}: {dw}");

        let turn_diff = |dt| {
            synthesis_difference(
                &v,
                ImuSynthesis::Exact,
                ImuSynthesis::Continuous,
                71.0,
                24.0,
                dt,
            )
        };
        let (f1, w1) = turn_diff(0.01);
        let (f4, w4) = turn_diff(0.0025);
        eprintln!(
            "{model:?} turn: Δt 10 ms |Δf| {f1:.2e} |Δω| {w1:.2e}; Δt 2.5 ms |Δf| {f4:.2e} |Δω| {w4:.2e}"
        );
        // Second order: 16× (12–20 allows the next order and the sampling of the maximum).
        assert!((12.0..20.0).contains(&(f1 / f4)), "{model:?}: {}", f1 / f4);
        assert!((12.0..20.0).contains(&(w1 / w4)), "{model:?}: {}", w1 / w4);
    }
}

/// On a level orbit the body turns at a constant rate with a constant specific force, so the
/// exact increments, the continuous sample and the closed-form coordinated turn coincide:
/// f^b = (0, 0, −√(a² + g²)), ω^b = Ω (0, sin φ, cos φ) with tan φ = V²/(R g), in a flat world
/// whose gravity is the design gravity.
#[test]
fn exact_and_continuous_synthesis_match_a_closed_form_turn() {
    let cfg = vehicle_cfg(ShapeConfig::Orbit {
        radius_m: 400.0,
        clockwise: true,
    });
    let g = super::trajectory::DESIGN_GRAVITY;
    let wcfg = WorldConfig {
        seed: 1,
        earth_model: EarthModel::Flat,
        gravity_mps2: Some(g),
        ..WorldConfig::default()
    };
    let v = VehicleSim::new(&cfg, Arc::new(World::new(&wcfg, 1).unwrap()), 1).unwrap();
    let (speed, r) = (25.0f64, 400.0f64);
    let (acc, rate) = (speed * speed / r, speed / r);
    let bank = (acc / g).atan();
    for synthesis in [ImuSynthesis::Exact, ImuSynthesis::Continuous] {
        let s = v.ideal_imu(10.0, 10.01, synthesis);
        // Closed form vs trig evaluation (continuous: 1e-12 relative); the exact increments
        // divide (v_k − v_{k−1}) ≈ 0.016 m/s by Δt: rounding 25·1e-16/0.01 ≈ 3e-13 m/s².
        let f = (s.specific_force - Vector3::new(0.0, 0.0, -(acc * acc + g * g).sqrt())).norm();
        let w = (s.angular_rate - rate * Vector3::new(0.0, bank.sin(), bank.cos())).norm();
        assert!(f < 1e-11, "{synthesis:?}: {f}");
        assert!(w < 1e-13, "{synthesis:?}: {w}");
    }
}

/// With `[vehicle.imu.truth] model = "filter"` the IMU errors follow the estimator's densities: white noise σ = density/√Δt (sample std within 3 %, six
/// standard errors at n = 60 000), mean ≈ 0, uncorrelated in time, bias increments of
/// σ = rw·√Δt, and turn-on biases of the grade's σ across vehicles (within 10 %: 5 standard
/// errors at n = 1200).
#[test]
fn imu_noise_statistics_match_the_densities() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.imu.grade = ImuGrade::Consumer;
    cfg.imu.rate_hz = 200.0;
    cfg.imu.truth.model = ImuTruthModel::Filter;
    cfg.sensor.rate_hz = 1.0;
    let noise = ImuGrade::Consumer.noise();
    let w = world(EarthModel::Flat, 1);
    let mut v = VehicleSim::new(&cfg, w.clone(), 99).unwrap();
    let dt = v.imu_dt();
    let n = 20_000;
    let mut acc_noise = Vec::with_capacity(3 * n);
    let mut gyro_noise = Vec::with_capacity(3 * n);
    let mut acc_walk = Vec::with_capacity(3 * n);
    let mut gyro_walk = Vec::with_capacity(3 * n);
    let mut prev = *v.truth();
    for _ in 0..n {
        let o = v.step();
        let e_f = o.imu.specific_force - o.imu_ideal.specific_force - o.truth.accel_bias;
        let e_w = o.imu.angular_rate - o.imu_ideal.angular_rate - o.truth.gyro_bias;
        acc_noise.extend(e_f.iter());
        gyro_noise.extend(e_w.iter());
        acc_walk.extend((o.truth.accel_bias - prev.accel_bias).iter());
        gyro_walk.extend((o.truth.gyro_bias - prev.gyro_bias).iter());
        prev = o.truth;
    }
    let stats = |x: &[f64]| {
        let m = x.iter().sum::<f64>() / x.len() as f64;
        let s = (x.iter().map(|a| (a - m) * (a - m)).sum::<f64>() / (x.len() - 1) as f64).sqrt();
        (m, s)
    };
    for (name, x, sigma) in [
        (
            "accel white",
            &acc_noise,
            noise.accel_noise_density / dt.sqrt(),
        ),
        (
            "gyro white",
            &gyro_noise,
            noise.gyro_noise_density / dt.sqrt(),
        ),
        (
            "accel bias walk",
            &acc_walk,
            noise.accel_bias_rw_density * dt.sqrt(),
        ),
        (
            "gyro bias walk",
            &gyro_walk,
            noise.gyro_bias_rw_density * dt.sqrt(),
        ),
    ] {
        let (m, s) = stats(x);
        let cnt = x.len() as f64;
        eprintln!(
            "{name}: σ expected {sigma:.4e}, sample {s:.4e} (ratio {:.4}), mean/σ {:.2e}",
            s / sigma,
            m / sigma
        );
        assert!((s / sigma - 1.0).abs() < 0.03, "{name}: {s} vs {sigma}");
        // Mean within 5 standard errors.
        assert!(m.abs() < 5.0 * sigma / cnt.sqrt(), "{name}: mean {m}");
        // Lag-1 autocorrelation (per axis, stride 3) within 5/√n of zero: white in time.
        let lag: f64 = (3..x.len())
            .map(|i| (x[i] - m) * (x[i - 3] - m))
            .sum::<f64>()
            / ((cnt - 3.0) * s * s);
        assert!(
            lag.abs() < 5.0 / (cnt / 3.0).sqrt(),
            "{name}: lag-1 correlation {lag}"
        );
    }
    // Turn-on biases across 400 vehicles.
    let (mut ab, mut gb) = (Vec::new(), Vec::new());
    for seed in 0..400 {
        let v = VehicleSim::new(&cfg, w.clone(), seed).unwrap();
        ab.extend(v.initial_truth().accel_bias.iter());
        gb.extend(v.initial_truth().gyro_bias.iter());
    }
    let (_, sa) = stats(&ab);
    let (_, sg) = stats(&gb);
    eprintln!(
        "turn-on: accel σ ratio {:.3}, gyro σ ratio {:.3}",
        sa / noise.accel_bias_sigma,
        sg / noise.gyro_bias_sigma
    );
    assert!((sa / noise.accel_bias_sigma - 1.0).abs() < 0.1);
    assert!((sg / noise.gyro_bias_sigma - 1.0).abs() < 0.1);
}

/// The `sensor` truth model: measured = (I + S)·ideal + bias + white noise, with the white
/// noise of the configured density, the Gauss–Markov bias following its exact discretisation
/// (residual σ = σ_b·√(1 − e^{−2Δt/τ}) within 3 %: six standard errors at n = 60 000), its
/// stationary σ across vehicles, and the scale-factor and misalignment draws of their σ across
/// vehicles (within 10 %: 5 standard errors at n = 1200 and 2400).
#[test]
fn sensor_truth_model_statistics() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.imu.grade = ImuGrade::Consumer;
    cfg.imu.rate_hz = 200.0;
    cfg.sensor.rate_hz = 1.0;
    let t = &mut cfg.imu.truth;
    t.accel_bias_sigma = Some(0.0);
    t.gyro_bias_sigma = Some(0.0);
    t.accel_bias_instability = Some(0.02);
    t.gyro_bias_instability = Some(1e-4);
    t.bias_correlation_time_s = Some(2.0);
    t.accel_scale_factor_ppm = Some(5000.0);
    t.gyro_scale_factor_ppm = Some(2000.0);
    t.accel_misalignment_mrad = Some(1.0);
    t.gyro_misalignment_mrad = Some(0.5);
    cfg.validate(NavFrame::Local).unwrap();
    let model = cfg.imu.truth_errors();
    assert_eq!(
        model.accel_noise_density,
        ImuGrade::Consumer.noise().accel_noise_density
    );
    let w = world(EarthModel::Flat, 1);
    let mut v = VehicleSim::new(&cfg, w.clone(), 99).unwrap();
    let dt = v.imu_dt();
    let decay = (-dt / 2.0f64).exp();
    let (ca, cg) = (
        *v.imu_errors().accel_calibration(),
        *v.imu_errors().gyro_calibration(),
    );
    let (mut white_a, mut white_g, mut resid_a, mut resid_g) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut prev = *v.truth();
    for _ in 0..20_000 {
        let o = v.step();
        let e_f = o.imu.specific_force - ca * o.imu_ideal.specific_force - o.truth.accel_bias;
        let e_w = o.imu.angular_rate - cg * o.imu_ideal.angular_rate - o.truth.gyro_bias;
        white_a.extend(e_f.iter());
        white_g.extend(e_w.iter());
        resid_a.extend((o.truth.accel_bias - prev.accel_bias * decay).iter());
        resid_g.extend((o.truth.gyro_bias - prev.gyro_bias * decay).iter());
        prev = o.truth;
    }
    let sd = |x: &[f64]| (x.iter().map(|a| a * a).sum::<f64>() / x.len() as f64).sqrt();
    let drive = (1.0 - decay * decay).sqrt();
    for (name, x, sigma) in [
        (
            "accel white",
            &white_a,
            model.accel_noise_density / dt.sqrt(),
        ),
        ("gyro white", &white_g, model.gyro_noise_density / dt.sqrt()),
        ("accel Gauss–Markov residual", &resid_a, 0.02 * drive),
        ("gyro Gauss–Markov residual", &resid_g, 1e-4 * drive),
    ] {
        let ratio = sd(x) / sigma;
        eprintln!("{name}: σ ratio {ratio:.4}");
        assert!((ratio - 1.0).abs() < 0.03, "{name}: {ratio}");
    }
    // Across 400 vehicles: stationary initial bias, scale factors, misalignments.
    let (mut b, mut sf, mut mis) = (Vec::new(), Vec::new(), Vec::new());
    for seed in 0..400 {
        let v = VehicleSim::new(&cfg, w.clone(), seed).unwrap();
        b.extend(v.initial_truth().accel_bias.iter().map(|x| x / 0.02));
        let c = v.imu_errors().gyro_calibration() - Matrix3::identity();
        for i in 0..3 {
            sf.push(c[(i, i)] / 2e-3);
            for j in (0..3).filter(|&j| j != i) {
                mis.push(c[(i, j)] / 0.5e-3);
            }
        }
    }
    for (name, x) in [
        ("stationary bias", &b),
        ("scale factor", &sf),
        ("misalignment", &mis),
    ] {
        let ratio = sd(x);
        eprintln!("{name}: σ ratio {ratio:.3}");
        assert!((ratio - 1.0).abs() < 0.1, "{name}: {ratio}");
    }
}

/// `model = "filter"` reproduces the estimator's model bit for bit (no instability, scale factor
/// or misalignment; the turn-on and walk streams as before), and the `sensor` defaults derive
/// from it (same densities and turn-on σ, instability matched to the random walk).
#[test]
fn truth_model_defaults_and_filter_oracle() {
    let mut cfg = vehicle_cfg(lawnmower());
    let noise = cfg.imu.noise_model();
    let sensor = cfg.imu.truth_errors();
    assert_eq!(sensor.gyro_noise_density, noise.gyro_noise_density);
    assert_eq!(sensor.accel_bias_sigma, noise.accel_bias_sigma);
    let tau = crate::scenario::DEFAULT_BIAS_CORRELATION_TIME_S;
    assert!(
        (sensor.gyro_bias_instability - noise.gyro_bias_rw_density * (tau / 2.0).sqrt()).abs()
            < 1e-20
    );
    // 10 ppm → 1e-5 (one rounding of the unit conversion).
    assert!(
        (sensor.gyro_scale_factor - 1e-5).abs() < 1e-20,
        "tactical default"
    );
    cfg.imu.truth.model = ImuTruthModel::Filter;
    let oracle = cfg.imu.truth_errors();
    assert_eq!(oracle, SensorErrors::filter_model(&noise));
    let v = VehicleSim::new(&cfg, world(EarthModel::Flat, 1), 3).unwrap();
    assert_eq!(*v.imu_errors().gyro_calibration(), Matrix3::identity());
    assert_eq!(*v.imu_errors().accel_calibration(), Matrix3::identity());
}

/// Independent sensor-frame position: body-to-world rotation built by nalgebra's Euler
/// constructor from the *launch-frame* attitude, positions in launch NED (for global runs this
/// also checks that the current-level attitude and ECEF positions describe the same pose).
fn independent_sensor_position(
    truth: &TruthSample,
    mount: &canopy_fusion::sensor::SensorMount,
    m_ned: &Vector3<f64>,
) -> Vector3<f64> {
    let a = truth.launch_attitude;
    let r = Rotation3::from_euler_angles(a.x, a.y, a.z);
    let lever_world = r * mount.lever_arm_body;
    mount.sensor_from_body * (r.inverse() * (m_ned - truth.launch_position - lever_world))
}

/// Every observation is of a feature inside range and field of view; every feature strictly
/// inside them is observed (no cap); noise-free measurements equal eq. 21.41 evaluated
/// independently; frames arrive at the sensor rate with the IMU time stamp.
#[test]
fn sensor_respects_range_and_field_of_view() {
    for model in [EarthModel::Wgs84, EarthModel::Flat] {
        let mut cfg = vehicle_cfg(lawnmower());
        cfg.trajectory.as_mut().unwrap().phase = 0.2;
        cfg.sensor.model = SensorModelConfig::RangeBearing {
            sigma_range_m: 0.0,
            sigma_bearing_deg: 0.0,
        };
        cfg.sensor.max_observations = 10_000;
        cfg.sensor.min_range_m = 120.0;
        cfg.sensor.max_range_m = 190.0;
        cfg.sensor.half_fov_azimuth_deg = 30.0;
        cfg.sensor.half_fov_elevation_deg = 40.0;
        let w = world(model, 8);
        let mut v = VehicleSim::new(&cfg, w.clone(), 1).unwrap();
        let mount = v.sensor_mount();
        let (mut frames, mut obs, mut max_err) = (0, 0, 0.0f64);
        for k in 1..=8000u64 {
            let out = v.step();
            assert_eq!(
                out.frame.is_some(),
                k % 50 == 0,
                "2 Hz frames at 100 Hz IMU"
            );
            let Some(sf) = out.frame else { continue };
            frames += 1;
            assert_eq!(sf.frame.time, out.imu.time);
            let mut expected = Vec::new();
            for f in w.features() {
                let p = independent_sensor_position(&out.truth, &mount, &f.position_ned);
                let (r, az, el) = (
                    p.norm(),
                    p.y.atan2(p.x),
                    (p.z / (p.x * p.x + p.y * p.y).sqrt()).atan(),
                );
                // Strictly inside by 1e-6 (m, rad): the two computations agree to ~1e-9.
                let inside = p.x > 0.0
                    && r > 120.0 + 1e-6
                    && r < 190.0 - 1e-6
                    && az.abs() < 30f64.to_radians() - 1e-6
                    && el.abs() < 40f64.to_radians() - 1e-6;
                let outside = p.x <= 0.0
                    || !(120.0 - 1e-6..=190.0 + 1e-6).contains(&r)
                    || az.abs() > 30f64.to_radians() + 1e-6
                    || el.abs() > 40f64.to_radians() + 1e-6;
                let seen = sf.true_ids.iter().position(|&id| id == f.id);
                if inside {
                    expected.push(f.id);
                    assert!(
                        seen.is_some(),
                        "feature {} inside the FOV was not observed",
                        f.id
                    );
                }
                if let Some(i) = seen {
                    assert!(
                        !outside,
                        "feature {} outside the limits was observed: r {r} az {az} el {el}",
                        f.id
                    );
                    let Measurement::RangeBearing(z) = sf.frame.observations[i].z else {
                        panic!()
                    };
                    max_err = max_err.max((z - Vector3::new(r, az, el)).abs().max());
                    assert_eq!(sf.frame.observations[i].descriptor, f.id);
                }
            }
            obs += sf.true_ids.len();
        }
        eprintln!(
            "{model:?}: {frames} frames, {obs} observations, max |z − z_independent| {max_err:.1e}"
        );
        assert!(obs > 100, "the test must see features: {obs}");
        // The global path goes through ECEF (6.4e6 m) and back: ~1e-9 m on 100 m ranges.
        assert!(max_err < 1e-8, "{model:?}: {max_err}");
    }
}

/// The per-frame cap keeps the nearest features.
#[test]
fn sensor_cap_keeps_the_nearest() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.sensor.max_observations = 3;
    cfg.sensor.max_range_m = 1000.0;
    cfg.sensor.half_fov_azimuth_deg = 80.0;
    cfg.sensor.half_fov_elevation_deg = 80.0;
    let w = world(EarthModel::Flat, 2);
    let mut v = VehicleSim::new(&cfg, w.clone(), 1).unwrap();
    let mount = v.sensor_mount();
    let mut checked = 0;
    for _ in 0..3000 {
        let out = v.step();
        let Some(sf) = out.frame else { continue };
        assert!(sf.true_ids.len() <= 3);
        let range = |id| {
            independent_sensor_position(&out.truth, &mount, &w.feature(id).unwrap().position_ned)
                .norm()
        };
        let farthest_kept = sf.true_ids.iter().map(|&id| range(id)).fold(0.0, f64::max);
        let nearer_visible = w
            .features()
            .iter()
            .filter(|f| !sf.true_ids.contains(&f.id))
            .filter(|f| {
                let p = independent_sensor_position(&out.truth, &mount, &f.position_ned);
                p.x > 0.0
                    && p.norm() >= 10.0
                    && p.y.atan2(p.x).abs() < 80f64.to_radians()
                    && (p.z / p.xy().norm()).atan().abs() < 80f64.to_radians()
                    && p.norm() < farthest_kept - 1e-9
            })
            .count();
        assert_eq!(nearer_visible, 0);
        checked += usize::from(sf.true_ids.len() == 3);
    }
    assert!(checked > 20, "frames at the cap: {checked}");
}

/// Camera observations lie inside the image, and so do their noise-free projections
/// (eq. 21.43 evaluated independently).
#[test]
fn pixel_observations_stay_inside_the_image() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.sensor.model = SensorModelConfig::Pixel {
        fu_px: 400.0,
        fv_px: 400.0,
        u0_px: 320.0,
        v0_px: 240.0,
        width_px: 640.0,
        height_px: 480.0,
        sigma_px: 1.0,
    };
    cfg.sensor.half_fov_azimuth_deg = 80.0;
    cfg.sensor.half_fov_elevation_deg = 80.0;
    cfg.sensor.max_observations = 50;
    let w = world(EarthModel::Flat, 4);
    let mut v = VehicleSim::new(&cfg, w.clone(), 1).unwrap();
    let mount = v.sensor_mount();
    let (mut n, mut near_edge) = (0, 0);
    for _ in 0..6000 {
        let out = v.step();
        let Some(sf) = out.frame else { continue };
        for (o, id) in sf.frame.observations.iter().zip(&sf.true_ids) {
            let Measurement::Pixel(uv) = o.z else {
                panic!("pixel sensor")
            };
            assert!(
                (0.0..640.0).contains(&uv.x) && (0.0..480.0).contains(&uv.y),
                "{uv:?}"
            );
            let p = independent_sensor_position(
                &out.truth,
                &mount,
                &w.feature(*id).unwrap().position_ned,
            );
            let (u, vv) = (400.0 * p.y / p.x + 320.0, 400.0 * p.z / p.x + 240.0);
            assert!(p.x > 0.0 && (0.0..640.0).contains(&u) && (0.0..480.0).contains(&vv));
            near_edge += usize::from(!(40.0..=600.0).contains(&u) || !(40.0..=440.0).contains(&vv));
            n += 1;
        }
    }
    eprintln!("pixel: {n} observations, {near_edge} within 40 px of the border");
    assert!(
        n > 100 && near_edge > 0,
        "the image border must be exercised: {n} {near_edge}"
    );
}

/// The observed mismatch rate matches the configured probability (within 5 binomial standard
/// errors), random ids name no feature, and wrong real ids differ from the true one.
#[test]
fn descriptor_mismatch_rate_matches_the_probability() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.sensor.mismatch_probability = 0.2;
    cfg.sensor.mismatch_random_id_fraction = 0.3;
    cfg.sensor.rate_hz = 100.0;
    cfg.sensor.max_observations = 8;
    let w = world(EarthModel::Flat, 5);
    let mut v = VehicleSim::new(&cfg, w.clone(), 3).unwrap();
    let (mut total, mut wrong, mut random) = (0usize, 0usize, 0usize);
    while total < 20_000 {
        let out = v.step();
        let Some(sf) = out.frame else { continue };
        for (o, &id) in sf.frame.observations.iter().zip(&sf.true_ids) {
            total += 1;
            if o.descriptor != id {
                wrong += 1;
                if o.descriptor >= RANDOM_ID_BASE {
                    random += 1;
                    assert!(w.feature(o.descriptor).is_none());
                } else {
                    assert!(
                        w.feature(o.descriptor).is_some(),
                        "a wrong real id names a feature"
                    );
                }
            }
        }
    }
    let rate = wrong as f64 / total as f64;
    let frac = random as f64 / wrong as f64;
    eprintln!("mismatch rate {rate:.4} (0.2), random-id fraction {frac:.3} (0.3) over {total}");
    assert!((rate - 0.2).abs() < 5.0 * (0.2f64 * 0.8 / total as f64).sqrt());
    assert!((frac - 0.3).abs() < 5.0 * (0.3f64 * 0.7 / wrong as f64).sqrt());
}

/// Global truth: Ψ is relative to the local-level frame at the *current* position. Checked by
/// an independent construction of that frame (north and east as normalised finite differences of
/// the geodetic → ECEF map, down as their cross product) and the body axes C_{n0}^e C_b^{n0}; the
/// difference from the launch-frame attitude (≈ distance / Earth radius) must be visible.
#[test]
fn global_attitude_is_relative_to_the_current_level_frame() {
    let cfg = vehicle_cfg(ShapeConfig::Orbit {
        radius_m: 900.0,
        clockwise: true,
    });
    let w = world(EarthModel::Wgs84, 1);
    let mut v = VehicleSim::new(&cfg, w.clone(), 1).unwrap();
    let launch = *w.launch_frame();
    let (mut max_err, mut min_tilt) = (0.0f64, f64::MAX);
    for _ in 0..40 {
        for _ in 0..99 {
            v.step();
        }
        let t = v.step().truth;
        let g = ecef_to_geodetic(&t.position);
        let h = 1e-7; // rad: truncation ~h²·R ≈ 6e-8 m on ~1.3 m chords → ~5e-8 relative
        let north = (geodetic_to_ecef(&Geodetic {
            lat: g.lat + h,
            ..g
        }) - geodetic_to_ecef(&Geodetic {
            lat: g.lat - h,
            ..g
        }))
        .normalize();
        let east = (geodetic_to_ecef(&Geodetic {
            lon: g.lon + h,
            ..g
        }) - geodetic_to_ecef(&Geodetic {
            lon: g.lon - h,
            ..g
        }))
        .normalize();
        let down = north.cross(&east);
        let level_from_ecef =
            Matrix3::from_rows(&[north.transpose(), east.transpose(), down.transpose()]);
        let body_in_ecef = launch.ecef_from_ned * nav_from_body(&t.launch_attitude);
        let expected = level_from_ecef * body_in_ecef;
        max_err = max_err.max((nav_from_body(&t.attitude) - expected).norm());
        min_tilt =
            min_tilt.min((nav_from_body(&t.attitude) - nav_from_body(&t.launch_attitude)).norm());
        // Velocity: ECEF image of the launch-frame velocity; position round-trips.
        assert!((launch.ecef_from_ned.transpose() * t.velocity - t.launch_velocity).norm() < 1e-12);
        assert!((w.to_launch(&t.position) - t.launch_position).norm() < 1e-6);
    }
    eprintln!(
        "global attitude: max |C_b^n − independent| {max_err:.1e}, min |C_b^n − C_b^n0| {min_tilt:.1e}"
    );
    assert!(max_err < 1e-6, "{max_err}");
    // 900 m from the launch site the level frames differ by ≈ 900/6.37e6 = 1.4e-4 rad.
    assert!(min_tilt > 1e-4, "{min_tilt}");
}

/// Features: ids 1..=n, inside the area, standing 0–10 m above the terrain, and their ECEF and
/// NED truths describe the same point (via geodetic coordinates, an independent path).
#[test]
fn features_lie_on_the_terrain_inside_the_area() {
    let cfg = WorldConfig::default();
    let w = World::new(&cfg, 21).unwrap();
    assert_eq!(w.features().len(), 400);
    for (i, f) in w.features().iter().enumerate() {
        assert_eq!(f.id, i as u64 + 1);
        assert_eq!(w.feature(f.id), Some(f));
        let p = f.position_ned;
        assert!(p.x.abs() <= 1200.0 && p.y.abs() <= 1200.0);
        let above = -p.z - w.terrain().height(p.x, p.y);
        assert!((0.0..=10.0).contains(&above), "{above}");
        // Height above the ellipsoid ≈ launch height − down + d²/(2R): the tangent plane rises above
        // the curved ellipsoid (≤ 0.3 m here; R between M and N, 0.5 % apart → ≤ 2 mm error).
        let g = ecef_to_geodetic(&f.position_ecef);
        let drop = p.xy().norm_squared() / (2.0 * 6.37e6);
        assert!(
            (g.height - (60.0 - p.z + drop)).abs() < 0.01,
            "{} vs {}",
            g.height,
            60.0 - p.z + drop
        );
    }
    assert!(w.feature(0).is_none() && w.feature(401).is_none());
    assert!(w.feature(RANDOM_ID_BASE).is_none());
}

/// The initial estimate's offset is drawn from its own covariance: over 500 vehicles the mean
/// NEES of (p, v, Ψ) is 9 within 5 standard errors (χ²₉: σ = √18 per draw).
#[test]
fn initial_offsets_are_consistent_with_the_covariance() {
    let cfg = vehicle_cfg(lawnmower());
    let w = world(EarthModel::Wgs84, 1);
    let runs = 500;
    let mut sum = 0.0;
    for seed in 0..runs {
        let v = VehicleSim::new(&cfg, w.clone(), seed).unwrap();
        let (e, t) = (v.initial_estimate(), v.initial_truth());
        assert_eq!(e.covariance.nrows(), VEHICLE_DIM);
        let mut err = nalgebra::SVector::<f64, 9>::zeros();
        err.fixed_rows_mut::<3>(POS)
            .copy_from(&(e.position - t.position));
        err.fixed_rows_mut::<3>(VEL)
            .copy_from(&(e.velocity - t.velocity));
        err.fixed_rows_mut::<3>(ATT)
            .copy_from(&(e.attitude - t.attitude).map(wrap_angle));
        let p = e.covariance.fixed_view::<9, 9>(0, 0).into_owned();
        sum += (err.transpose() * p.try_inverse().unwrap() * err)[0];
    }
    let mean = sum / runs as f64;
    eprintln!("initial NEES mean {mean:.3} (9)");
    assert!(
        (mean - 9.0).abs() < 5.0 * (18.0 / runs as f64).sqrt(),
        "{mean}"
    );
    // Without the draw the estimate starts at the truth.
    let mut cfg = cfg;
    cfg.initial.draw_offset = false;
    let v = VehicleSim::new(&cfg, w, 1).unwrap();
    assert_eq!(v.initial_estimate().position, v.initial_truth().position);
}

/// Sensor models hand the estimator radians: the config's degrees are converted.
#[test]
fn sensor_model_units() {
    let cfg = SensorConfig::default();
    let SensorModel::RangeBearing {
        sigma_range,
        sigma_bearing,
    } = cfg.model()
    else {
        panic!()
    };
    assert_eq!(sigma_range, 0.5);
    assert!((sigma_bearing - 0.2f64.to_radians()).abs() < 1e-18);
}

/// The built-in default builds: four vehicles, global frame, and every vehicle sees features.
#[test]
fn builtin_default_builds_and_observes() {
    let (w, mut vs) = build(&crate::scenario::Scenario::builtin_default()).unwrap();
    assert_eq!(w.frame(), NavFrame::Global);
    assert_eq!(vs.len(), 4);
    for v in &mut vs {
        let mut seen = 0;
        for _ in 0..6000 {
            if let Some(f) = v.step().frame {
                seen += f.frame.observations.len();
            }
        }
        let alt = -v.truth().launch_position.z;
        eprintln!(
            "{}: {} observations in 60 s (≈{:.1}/frame), altitude {alt:.0} m, max bank {:.1}°",
            v.name(),
            seen,
            seen as f64 / 120.0,
            v.trajectory().max_bank().to_degrees()
        );
        assert!(seen > 120, "{}: {seen}", v.name());
        assert!((100.0..=200.0).contains(&alt));
    }
}

/// A path that would fly into the terrain is rejected, naming the altitude.
#[test]
fn low_flight_is_rejected() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.trajectory.as_mut().unwrap().altitude_m = 5.0;
    match VehicleSim::new(&cfg, world(EarthModel::Flat, 1), 1) {
        Err(crate::scenario::ScenarioError::Invalid { field, .. }) => {
            assert_eq!(field, "trajectory.altitude_m")
        }
        other => panic!(
            "expected a clearance error, got {:?}",
            other.map(|v| v.name().to_owned())
        ),
    }
}

/// The bearing-only measurements the estimator receives (angles of eq. 21.42, pixels of
/// eq. 21.43) agree with the estimator's own observation model evaluated at the true pose and
/// feature, through the turns (roll up to the coordinated-flight bank) of both Earth models:
/// the simulator and `fusion::observation` share conventions (sensor mount, Euler order, global
/// attitude relative to the current level frame), which delayed initialization relies on.
#[test]
fn bearing_and_pixel_measurements_match_the_estimators_model_at_the_truth() {
    use canopy_fusion::observation::ObservationModel;
    let pixel = SensorModelConfig::vga_camera(0.0);
    let bearing = SensorModelConfig::Bearing {
        sigma_bearing_deg: 0.0,
    };
    for earth in [EarthModel::Wgs84, EarthModel::Flat] {
        for sensor in [bearing, pixel] {
            let mut cfg = vehicle_cfg(lawnmower());
            cfg.sensor.model = sensor;
            cfg.sensor.max_observations = 50;
            // Start just before the first turn so the run covers straight flight and a turn.
            cfg.trajectory.as_mut().unwrap().phase = 0.2;
            let w = world(earth, 5);
            let mut v = VehicleSim::new(&cfg, w.clone(), 1).unwrap();
            let model = ObservationModel {
                frame: w.frame(),
                sensor: v.sensor_model(),
                mount: v.sensor_mount(),
            };
            let (mut n, mut max_err, mut max_roll) = (0, 0.0f64, 0.0f64);
            for _ in 0..8000 {
                let out = v.step();
                let Some(sf) = out.frame else { continue };
                let t = out.truth;
                max_roll = max_roll.max(t.attitude.x.abs());
                let pose = model.sensor_pose(&t.position, &t.attitude);
                for (o, id) in sf.frame.observations.iter().zip(&sf.true_ids) {
                    let m = w.feature(*id).unwrap().position(w.frame());
                    let predicted = model.predict(&pose, &m).unwrap().z;
                    let z = model.measurement_vector(&o.z).unwrap();
                    let err = model.innovation(&z, &predicted).amax();
                    max_err = max_err.max(err);
                    n += 1;
                }
            }
            eprintln!(
                "{earth:?} {sensor:?}: {n} observations, max roll {max_roll:.2} rad, max |z − h| \
                 {max_err:.1e}"
            );
            assert!(n > 200, "{n}");
            assert!(max_roll > 0.3, "the run must include a banked turn");
            // Noise-free: only round-off of the two computation paths (ECEF ≈ 6.4e6 m ⇒ 1e-9 m
            // on ≥ 100 m ranges ⇒ ≈ 1e-11 rad, ≈ 1e-8 px at 600 px focal length).
            assert!(max_err < 1e-7, "{earth:?} {sensor:?}: {max_err}");
        }
    }
}

/// With `identity = "appearance"` the estimator's frame names no true feature: each descriptor
/// is a track id that follows one true feature only, tracks break (more tracks than features
/// seen), every observation carries a descriptor whose share of flipped bits against the
/// feature's lies between the configured p_min and p_max; the true ids travel beside the frame.
#[test]
fn appearance_frames_carry_tracks_and_noisy_descriptors() {
    use crate::scenario::{AppearanceConfig, Identity};
    let cfg_w = WorldConfig {
        seed: 4,
        earth_model: EarthModel::Flat,
        appearance: AppearanceConfig {
            identity: Identity::Appearance,
            ..AppearanceConfig::default()
        },
        ..WorldConfig::default()
    };
    let w = Arc::new(World::new(&cfg_w, 4).unwrap());
    let table = w.appearance().expect("appearance world has descriptors");
    let mut v = VehicleSim::new(&vehicle_cfg(lawnmower()), w.clone(), 2).unwrap();
    let mut track_truth: std::collections::HashMap<u64, u64> = Default::default();
    let mut features = std::collections::HashSet::new();
    let (mut bits, mut total) = (0u64, 0u64);
    while total < 5_000 {
        let Some(sf) = v.step().frame else { continue };
        assert_eq!(sf.frame.observations.len(), sf.true_ids.len());
        for (o, &id) in sf.frame.observations.iter().zip(&sf.true_ids) {
            let a = o.appearance.expect("every observation is described");
            let t = *track_truth.entry(o.descriptor).or_insert(id);
            assert_eq!(t, id, "track {} follows one feature", o.descriptor);
            features.insert(id);
            bits += u64::from(canopy_fusion::sensor::hamming(
                &a,
                table.descriptor(id as usize - 1).unwrap(),
            ));
            total += 1;
        }
    }
    let share = bits as f64 / (256 * total) as f64;
    eprintln!(
        "{} tracks for {} features; flipped-bit share {share:.4} over {total} observations",
        track_truth.len(),
        features.len()
    );
    assert!(track_truth.len() > features.len());
    assert!((0.02..=0.10).contains(&share), "{share}");
}

/// Off-grid frames and jittered samples (issue #11): sample k lies within the configured jitter
/// of k·Δt and the intervals tile; frame n is stamped n/rate + offset, inside the interval of the
/// sample it comes with, and its observations are those of the truth at its own time (noise-free
/// ranges equal the distance from the sensor at that time, computed here); the
/// estimator's stream splits that sample at the frame, the parts tiling the interval with the
/// frame after the first.
#[test]
fn off_grid_frames_and_jittered_samples() {
    let mut cfg = vehicle_cfg(lawnmower());
    cfg.imu.rate_hz = 100.0;
    cfg.imu.timestamp_jitter_s = 1e-3;
    cfg.sensor.rate_hz = 3.0;
    cfg.sensor.time_offset_s = 0.0123;
    // Noise-free ranges: a frame taken at the sample's time instead of its own would be off by
    // the distance flown in between (up to 25 m/s × 10 ms), far above round-off.
    cfg.sensor.model = crate::scenario::SensorModelConfig::RangeBearing {
        sigma_range_m: 0.0,
        sigma_bearing_deg: 0.0,
    };
    let w = world(EarthModel::Flat, 3);
    let mut raw = VehicleSim::new(&cfg, w.clone(), 5).unwrap();
    let mut stream = VehicleSim::new(&cfg, w.clone(), 5).unwrap();
    let (dt, j) = (0.01, 1e-3);
    let mut prev = 0.0;
    let mut frames = 0u64;
    let mut checked = 0;
    let mut parts = Vec::new();
    for k in 1..=1000u64 {
        let o = raw.step();
        let t = o.imu.time;
        assert!((t - k as f64 * dt).abs() <= j, "sample {k} at {t}");
        assert!((o.imu.dt - (t - prev)).abs() < 1e-15, "intervals tile");
        if let Some(f) = &o.frame {
            frames += 1;
            let tf = frames as f64 / 3.0 + 0.0123;
            assert!(
                (f.frame.time - tf).abs() < 1e-12,
                "frame {frames} at {}",
                f.frame.time
            );
            assert!(
                f.frame.time > prev && f.frame.time < t,
                "inside its interval"
            );
            let truth = raw.nav_truth_at(tf);
            for (obs, id) in f.frame.observations.iter().zip(&f.true_ids) {
                if let (Measurement::RangeBearing(z), Some(feat)) =
                    (&obs.z, w.features().iter().find(|x| x.id == *id))
                {
                    let nav_from_body = canopy_fusion::rotation::nav_from_body(&truth.attitude);
                    let lever = Vector3::from(cfg.sensor.lever_arm_m);
                    let r = (feat.position_ned - truth.position - nav_from_body * lever).norm();
                    // Round-off of an independent sum of a few hundred metres.
                    assert!((z.x - r).abs() < 1e-6, "range {} vs {r}", z.x);
                    checked += 1;
                }
            }
        }
        // The stream's parts up to this sample's time.
        while stream.stream_next_time() <= t + 1e-12 {
            let before = stream.stream_time();
            let p = stream.stream_step();
            assert!((p.imu.time - p.imu.dt - before).abs() < 1e-12, "parts tile");
            assert_eq!(stream.stream_time(), p.imu.time);
            parts.push((p.imu.time, p.frame.map(|f| f.frame.time)));
        }
        prev = t;
    }
    assert!(
        frames >= 25 && checked > 0,
        "{frames} frames, {checked} ranges checked"
    );
    let with_frame: Vec<_> = parts.iter().filter(|p| p.1.is_some()).collect();
    assert_eq!(with_frame.len() as u64, frames);
    assert!(
        with_frame.iter().all(|p| p.1 == Some(p.0)),
        "a frame ends its part"
    );
    assert_eq!(
        parts.len() as u64,
        1000 + frames,
        "one extra part per frame"
    );
}
