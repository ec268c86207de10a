//! The INS against references it did not make (issue 11).
//!
//! 1. An analytic flight generated here, with no canopy mechanization anywhere: position in the
//!    launch NED frame n0 at 58° N as closed-form functions of time (loops of a 25 m/s circle
//!    swept along by a 12 m/s drift: ground speed 13–37 m/s, the heading turning through 360°
//!    every 105 s; climbs of up to 3.2 m/s), attitude from closed-form Euler angles through
//!    nalgebra's rotations (yawing, pitching and rolling independently of the path, with a
//!    1.7 rad/s roll wobble that makes coning). The IMU increments of each 10 ms interval are
//!    the exact coning- and sculling-compensated increments of that motion
//!    (`world::imu::exact_increments`: the rotation between the two ends' attitudes and the
//!    integral of the specific force, no discrete step involved), checked here against a
//!    brute-force quadrature of the true specific force. `fusion::ins::propagate` integrates
//!    them for 300 s with no observations from the true initial state, in the rotating-Earth
//!    global frame (ECEF) and in a flat local frame; the position error must stay ≤ 1 cm.
//! 2. The world simulator's IMU for the default scenario's first UAV (lawnmower, 60° turns at
//!    25 m/s) under each synthesis: the default `exact` and the `discrete` ablation are
//!    reproduced to millimetres over 600 s; the `continuous` ablation (midpoint rates, no
//!    coning/sculling) is printed.

use canopy_fusion::geodesy::{
    EARTH_RATE, Geodetic, LocalFrame, ecef_from_ned, ecef_to_geodetic, gravity_ecef, normal_gravity,
};
use canopy_fusion::imu::ImuGrade;
use canopy_fusion::ins::{Mechanization, VehicleState, propagate};
use canopy_fusion::rotation::RotationIncrement;
use canopy_fusion::sensor::ImuSample;
use canopy_node::scenario::{EarthModel, ImuSynthesis, ImuTruthConfig, ImuTruthModel, Scenario};
use canopy_node::world::{self, BodyMotion, exact_increments};
use nalgebra::{Matrix3, Rotation3, Vector3};

/// Loop radius [m] of the 25 m/s circle at 0.06 rad/s.
const LOOP_RADIUS: f64 = 25.0 / 0.06;

/// Position, velocity and acceleration in n0 at time t (closed forms).
fn kinematics(t: f64) -> [Vector3<f64>; 3] {
    let (w, r) = (0.06, LOOP_RADIUS);
    let (s, c) = (w * t).sin_cos();
    let (s3, c3) = (0.03 * t).sin_cos();
    let (s2, c2) = (0.2 * t).sin_cos();
    [
        Vector3::new(
            12.0 * t + r * s,
            r * (1.0 - c),
            -150.0 - 40.0 * s3 - 10.0 * s2,
        ),
        Vector3::new(
            12.0 + r * w * c,
            r * w * s,
            -40.0 * 0.03 * c3 - 10.0 * 0.2 * c2,
        ),
        Vector3::new(
            -r * w * w * s,
            r * w * w * c,
            40.0 * 0.03 * 0.03 * s3 + 10.0 * 0.04 * s2,
        ),
    ]
}

/// C_b^{n0} at time t: roll, pitch, yaw closed forms through nalgebra (Rz·Ry·Rx).
fn launch_from_body(t: f64) -> Matrix3<f64> {
    let roll = 0.3 * (0.06 * t).sin() + 0.08 * (1.7 * t).sin();
    let pitch = 0.05 + 0.1 * (0.09 * t + 0.5).sin();
    let yaw = 0.4 + 0.06 * t + 0.3 * (0.11 * t).sin();
    *Rotation3::from_euler_angles(roll, pitch, yaw).matrix()
}

/// The launch site: 58° N (the latitude), 14° E, 100 m.
fn launch() -> LocalFrame {
    LocalFrame::new(Geodetic::from_degrees(58.0, 14.0, 100.0))
}

/// The reference motion in the world frame of `m` at time t.
fn motion(m: &Mechanization, launch: &LocalFrame, t: f64) -> BodyMotion {
    let [p, v, _] = kinematics(t);
    match m.local_gravity() {
        Some(_) => BodyMotion {
            time: t,
            position: p,
            velocity: v,
            world_from_body: launch_from_body(t),
        },
        None => BodyMotion {
            time: t,
            position: launch.ecef_from_local(&p),
            velocity: launch.ecef_from_ned * v,
            world_from_body: launch.ecef_from_ned * launch_from_body(t),
        },
    }
}

/// Euler angles of C_b^n relative to the local level at the body (nalgebra's extraction).
fn attitude(m: &Mechanization, b: &BodyMotion) -> Vector3<f64> {
    let nav_from_body = match m.local_gravity() {
        Some(_) => b.world_from_body,
        None => {
            let g = ecef_to_geodetic(&b.position);
            ecef_from_ned(g.lat, g.lon).transpose() * b.world_from_body
        }
    };
    let (roll, pitch, yaw) = Rotation3::from_matrix_unchecked(nav_from_body).euler_angles();
    Vector3::new(roll, pitch, yaw)
}

/// The exact sample of (t0, t0 + dt] of the reference flight.
fn sample(m: &Mechanization, launch: &LocalFrame, t0: f64, dt: f64) -> ImuSample {
    let ideal = exact_increments(
        m,
        &motion(m, launch, t0),
        &motion(m, launch, t0 + dt),
        |t| {
            let b = motion(m, launch, t);
            (b.position, b.velocity)
        },
    );
    ImuSample {
        time: t0 + dt,
        dt,
        specific_force: ideal.specific_force,
        angular_rate: ideal.angular_rate,
    }
}

/// ∫ C_{b(t)}^{b(t0)} f^b dt of the reference flight by a composite Gauss–Legendre rule, with
/// f^b = C_b^{eᵀ}(a^e + 2Ω×v^e − g_l(p^e)) from the closed-form acceleration and
/// C_{b(t)}^{b(t0)} = C_b^e(t0)ᵀ exp([Ω×](t − t0)) C_b^e(t) (global); f^b = C_b^{nᵀ}(a − g) in
/// the flat world. Independent of `exact_increments`' integration by parts.
fn brute_force_integral(m: &Mechanization, launch: &LocalFrame, t0: f64, dt: f64) -> Vector3<f64> {
    let start = motion(m, launch, t0);
    let integrand = |t: f64| {
        let b = motion(m, launch, t);
        let [_, _, a] = kinematics(t);
        let force_world = match m.local_gravity() {
            Some(g) => a - Vector3::new(0.0, 0.0, g),
            None => {
                let omega = Vector3::new(0.0, 0.0, EARTH_RATE);
                launch.ecef_from_ned * a + 2.0 * omega.cross(&b.velocity)
                    - gravity_ecef(&b.position)
            }
        };
        let spin = match m.local_gravity() {
            Some(_) => Matrix3::identity(),
            None => *Rotation3::from_axis_angle(&Vector3::z_axis(), EARTH_RATE * (t - t0)).matrix(),
        };
        start.world_from_body.transpose() * spin * force_world
    };
    // Composite two-point Gauss–Legendre over 400 panels (nodes at the panel centre ± h/(2√3)).
    let n = 400;
    let h = dt / n as f64;
    let offset = 0.5 * h / 3f64.sqrt();
    (0..n)
        .map(|i| {
            let centre = t0 + (i as f64 + 0.5) * h;
            integrand(centre - offset) + integrand(centre + offset)
        })
        .sum::<Vector3<f64>>()
        * (0.5 * h)
}

const DT: f64 = 0.01;
const DURATION: f64 = 300.0;
const REPORT_AT: [f64; 5] = [10.0, 60.0, 120.0, 200.0, 300.0];

/// Replays the exact increments through the mechanization; position errors at `REPORT_AT`.
fn free_inertial(m: &Mechanization) -> Vec<f64> {
    let launch = launch();
    let b0 = motion(m, &launch, 0.0);
    let mut x = VehicleState {
        position: b0.position,
        velocity: b0.velocity,
        attitude: attitude(m, &b0),
        accel_bias: Vector3::zeros(),
        gyro_bias: Vector3::zeros(),
    };
    let mut errors = Vec::new();
    let (mut max_v, mut max_att) = (0.0f64, 0.0f64);
    let steps = (DURATION / DT).round() as usize;
    for k in 0..steps {
        let t0 = k as f64 * DT;
        x = propagate(m, &x, &sample(m, &launch, t0, DT)).expect("finite samples");
        let truth = motion(m, &launch, t0 + DT);
        max_v = max_v.max((x.velocity - truth.velocity).norm());
        let d_att = attitude(m, &truth) - x.attitude;
        max_att = max_att.max(d_att.map(canopy_fusion::rotation::wrap_angle).norm());
        let t = (k + 1) as f64 * DT;
        if REPORT_AT.iter().any(|r| (r - t).abs() < 0.5 * DT) {
            errors.push((x.position - truth.position).norm());
        }
    }
    println!(
        "{:?}: position error {} ; max |Δv| {max_v:.2e} m/s, max |ΔΨ| {max_att:.2e} rad",
        m.frame(),
        REPORT_AT
            .iter()
            .zip(&errors)
            .map(|(t, e)| format!("{e:.2e} m at {t} s"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    errors
}

fn frames() -> [Mechanization; 2] {
    let site = launch().origin;
    [
        Mechanization::global(),
        Mechanization::local(normal_gravity(site.lat, site.height)).expect("positive gravity"),
    ]
}

/// The exact increments equal a brute-force quadrature of the true specific force (to the
/// quadrature error of 400 panels over 10 ms, ≈ 1e-16 m/s) in turns, climbs and the roll wobble.
#[test]
fn exact_increments_match_a_brute_force_quadrature() {
    let launch = launch();
    for m in frames() {
        let mut worst = 0.0f64;
        for t0 in [0.0, 17.3, 52.9, 131.07, 250.5] {
            let s = sample(&m, &launch, t0, DT);
            let inc = RotationIncrement::new(&(s.angular_rate * DT));
            let force = inc.left_jacobian * (s.specific_force * DT);
            let reference = brute_force_integral(&m, &launch, t0, DT);
            worst = worst.max((force - reference).norm());
        }
        println!("{:?}: |J(Δθ)Δv − ∫C f dt| ≤ {worst:.1e} m/s", m.frame());
        // |∫ f dt| ≈ 0.1 m/s per 10 ms; rounding of the sums ≈ 1e-16 relative, gravity
        // evaluated at 401 points: 1e-13 m/s is far below what 1 cm over 300 s allows
        // (≈ 2e-9 m/s per step of systematic error).
        assert!(worst < 1e-13, "{:?}: {worst}", m.frame());
    }
}

/// Acceptance of issue 11: error-free IMU along the independent rotating-Earth flight, ≤ 1 cm
/// at 300 s in the global frame (the first-order Euler-angle step drifted 1.9 m on a similar
/// flight); the same in the local frame.
#[test]
fn free_inertial_flight_matches_the_independent_reference() {
    for m in frames() {
        let errors = free_inertial(&m);
        assert_eq!(errors.len(), REPORT_AT.len());
        // 1 cm: the acceptance bound (the mechanization's remaining truncation terms
        // telescope and leave ≪ 1 mm, see `fusion::ins`).
        assert!(
            errors.iter().all(|e| *e <= 0.01),
            "{:?}: {errors:?}",
            m.frame()
        );
    }
}

/// The world simulator's IMU for the default scenario's first UAV, integrated from the true
/// initial state; position error after 60 s and 600 s.
fn simulated_drift(earth: EarthModel, synthesis: ImuSynthesis) -> (f64, f64) {
    let mut s = Scenario::builtin_default();
    s.world.earth_model = earth;
    s.vehicles[0].imu.grade = ImuGrade::Perfect;
    s.vehicles[0].imu.synthesis = synthesis;
    s.vehicles[0].imu.truth = ImuTruthConfig {
        model: ImuTruthModel::Filter,
        ..ImuTruthConfig::default()
    };
    let (_, mut vehicles) = world::build(&s).expect("default scenario builds");
    let v = &mut vehicles[0];
    let t0 = *v.truth();
    let mut x = VehicleState {
        position: t0.position,
        velocity: t0.velocity,
        attitude: t0.attitude,
        accel_bias: t0.accel_bias,
        gyro_bias: t0.gyro_bias,
    };
    let m = *v.world().mechanization();
    let mut at60 = f64::NAN;
    let steps = (600.0 / v.imu_dt()).round() as u64;
    let mut err = f64::NAN;
    for k in 1..=steps {
        let out = v.step();
        assert_eq!(out.imu, out.imu_ideal, "perfect grade adds nothing");
        x = propagate(&m, &x, &out.imu).expect("finite samples");
        err = (x.position - out.truth.position).norm();
        if k == (60.0 / v.imu_dt()).round() as u64 {
            at60 = err;
        }
    }
    println!(
        "{earth:?}/{synthesis:?}: position error after 60 s {at60:.3e} m, after 600 s {err:.3e} m"
    );
    (at60, err)
}

/// The default synthesis (exact increments) and the `discrete` ablation (the mechanization's
/// inverse) are both reproduced over the 600 s lawnmower: 1 cm bound, as above.
#[test]
fn simulated_exact_and_discrete_imu_are_reproduced() {
    for earth in [EarthModel::Wgs84, EarthModel::Flat] {
        for synthesis in [ImuSynthesis::Exact, ImuSynthesis::Discrete] {
            let (e60, e600) = simulated_drift(earth, synthesis);
            assert!(
                e60 < 1e-2 && e600 < 1e-2,
                "{earth:?}/{synthesis:?}: {e60} m, {e600} m"
            );
        }
    }
}

/// The `continuous` ablation samples the rates at the interval midpoints without coning or
/// sculling compensation. On the first 60 s (a straight leg) that matches the increments to
/// O(Δt²): below 1 m, where a sign error in the Coriolis term alone (2·ω_ie·v ≈ 3.6e-3 m/s²)
/// would give ≈ 6.5 m. The 600 s figure (turns) is printed: what an uncompensated IMU costs.
#[test]
fn continuous_ablation_stays_close_on_the_straight_leg() {
    for earth in [EarthModel::Wgs84, EarthModel::Flat] {
        let (e60, _) = simulated_drift(earth, ImuSynthesis::Continuous);
        assert!(e60 < 1.0, "{earth:?}: {e60} m after 60 s");
    }
}
