//! One simulated vehicle: trajectory, IMU, terrain sensor and truth, stepped at the IMU rate.

use std::sync::Arc;

use canopy_fusion::frames::Frame4;
use canopy_fusion::geodesy::{ecef_from_ned, ecef_to_geodetic};
use canopy_fusion::rotation::wrap_angle;
use canopy_fusion::sensor::{ImuSample, SensorModel, SensorMount};
use canopy_fusion::state::{ACC_BIAS, ATT, GYRO_BIAS, NavFrame, POS, VEHICLE_DIM, VEL};
use nalgebra::{Matrix3, SMatrix, Vector3};
use rand::Rng;
use rand_distr::StandardNormal;

use super::appearance::Tracker;
use super::imu::{
    BodyMotion, ImuErrors, ImuIdeal, ImuStreams, NavTruth, continuous_ideal, discrete_ideal,
    exact_increments,
};
use super::sensor::{SensedFrame, TerrainSensor};
use super::trajectory::{FlightState, Trajectory};
use super::{World, rng_stream};
use crate::scenario::{ImuSynthesis, ScenarioError, VehicleConfig};

/// Vehicle random streams (of the vehicle seed).
const STREAM_IMU_WHITE: u64 = 1;
const STREAM_IMU_WALK: u64 = 2;
const STREAM_SENSOR_NOISE: u64 = 3;
const STREAM_MISMATCH: u64 = 4;
const STREAM_INITIAL: u64 = 5;
const STREAM_IMU_CALIBRATION: u64 = 6;
const STREAM_IMU_INSTABILITY: u64 = 7;
const STREAM_APPEARANCE_FLIPS: u64 = 8;
const STREAM_TRACK_BREAKS: u64 = 9;
const STREAM_IMU_JITTER: u64 = 10;

/// Truth of one vehicle at one IMU step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthSample {
    /// Simulation time [s].
    pub time: f64,
    /// The frame of `position`, `velocity`, `attitude`.
    pub frame: NavFrame,
    /// p^e (global) or p^n (local) [m].
    pub position: Vector3<f64>,
    /// v^e or v^n [m/s].
    pub velocity: Vector3<f64>,
    /// Ψ of C_b^n, n the local-level frame at the current position (global) or launch NED
    /// (local) [rad].
    pub attitude: Vector3<f64>,
    /// True accelerometer bias δf^b [m/s²] (in effect for the IMU sample ending at `time`).
    pub accel_bias: Vector3<f64>,
    /// True gyro bias δω^b [rad/s].
    pub gyro_bias: Vector3<f64>,
    /// Position in the launch NED frame [m] (outputs, plots).
    pub launch_position: Vector3<f64>,
    /// Velocity in the launch NED frame [m/s].
    pub launch_velocity: Vector3<f64>,
    /// Ψ of C_b^{n0}, attitude relative to the launch NED frame [rad].
    pub launch_attitude: Vector3<f64>,
}

impl TruthSample {
    /// The navigation part (time, p, v, Ψ).
    pub fn nav(&self) -> NavTruth {
        NavTruth {
            time: self.time,
            position: self.position,
            velocity: self.velocity,
            attitude: self.attitude,
        }
    }
}

/// What one IMU step produces.
#[derive(Clone, Debug, PartialEq)]
pub struct StepOutput {
    /// The measured IMU sample (what the estimator receives).
    pub imu: ImuSample,
    /// The same interval's noise-free, bias-free sample (configured synthesis).
    pub imu_ideal: ImuSample,
    /// A terrain-sensor frame, when the sensor fires at this step.
    pub frame: Option<SensedFrame>,
    /// The truth at the end of the step.
    pub truth: TruthSample,
}

/// The estimator's initial state and covariance for a vehicle (15-state block, named indices of
/// `fusion::state`).
#[derive(Clone, Debug, PartialEq)]
pub struct InitialEstimate {
    /// Simulation time [s] (0).
    pub time: f64,
    /// Position estimate in the vehicle's frame [m].
    pub position: Vector3<f64>,
    /// Velocity estimate [m/s].
    pub velocity: Vector3<f64>,
    /// Attitude estimate Ψ [rad].
    pub attitude: Vector3<f64>,
    /// Accelerometer bias estimate (zero) [m/s²].
    pub accel_bias: Vector3<f64>,
    /// Gyro bias estimate (zero) [rad/s].
    pub gyro_bias: Vector3<f64>,
    /// Covariance of (p, v, Ψ, δf, δω), 15 × 15: the `[vehicle.initial]` σ along the vehicle's
    /// local north/east/down (rotated into ECEF for global), and the IMU's turn-on bias σ.
    pub covariance: SMatrix<f64, VEHICLE_DIM, VEHICLE_DIM>,
}

/// The own frame of a vehicle whose start is `start` (local frame): x_launch = Rz(ψ₀)·x_own + p₀.
pub fn launch_from_own(start: &TruthSample) -> Frame4 {
    Frame4 {
        yaw: start.attitude.z,
        translation: start.position,
    }
}

/// An own-frame start: the frame *is* the vehicle's start, so its position (0) and yaw (0) are
/// known exactly there (σ 1 mm and 1e-3 mrad, kept positive definite); velocity, roll, pitch
/// and biases keep their drawn errors and σ.
fn own_start(e: &InitialEstimate) -> InitialEstimate {
    let mut e = e.clone();
    e.position = Vector3::zeros();
    e.attitude.z = 0.0;
    for k in [POS, POS + 1, POS + 2, ATT + 2] {
        for j in 0..VEHICLE_DIM {
            e.covariance[(k, j)] = 0.0;
            e.covariance[(j, k)] = 0.0;
        }
    }
    for k in [POS, POS + 1, POS + 2] {
        e.covariance[(k, k)] = 1e-6;
    }
    e.covariance[(ATT + 2, ATT + 2)] = 1e-12;
    e
}

/// Re-expressing an initial estimate in another frame.
pub trait FrameEstimate {
    /// The estimate `e` (in this transform's target frame) in its source frame.
    fn inverse_estimate(&self, e: &InitialEstimate) -> InitialEstimate;
    /// The estimate `e` (in this transform's source frame) in its target frame.
    fn apply_estimate(&self, e: &InitialEstimate) -> InitialEstimate;
}

impl FrameEstimate for Frame4 {
    fn inverse_estimate(&self, e: &InitialEstimate) -> InitialEstimate {
        self.inverse().apply_estimate(e)
    }

    fn apply_estimate(&self, e: &InitialEstimate) -> InitialEstimate {
        let inv = *self;
        let r = inv.rotation();
        // Positions and velocities rotate, the yaw shifts, roll, pitch and biases (body axes)
        // stay: J = blockdiag(R, R, I, I, I) (`canopy_fusion::slam::SlamFilter::rebase`).
        let mut j = SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::identity();
        j.fixed_view_mut::<3, 3>(POS, POS).copy_from(&r);
        j.fixed_view_mut::<3, 3>(VEL, VEL).copy_from(&r);
        let mut attitude = e.attitude;
        attitude.z = wrap_angle(attitude.z + inv.yaw);
        InitialEstimate {
            time: e.time,
            position: inv.apply(&e.position),
            velocity: r * e.velocity,
            attitude,
            accel_bias: e.accel_bias,
            gyro_bias: e.gyro_bias,
            covariance: j * e.covariance * j.transpose(),
        }
    }
}

/// One simulated vehicle.
#[derive(Clone, Debug)]
pub struct VehicleSim {
    id: u32,
    name: String,
    world: Arc<World>,
    trajectory: Trajectory,
    synthesis: ImuSynthesis,
    dt: f64,
    frame_every: u64,
    /// Frame schedule: frame n ≥ 1 at n·`frame_period` + `frame_offset` [s].
    frame_period: f64,
    frame_offset: f64,
    /// Index of the next frame.
    next_frame: u64,
    /// Sample-time jitter: sample k at k·Δt + U(−j, j) [s] (`[vehicle.imu] timestamp_jitter_s`).
    jitter: f64,
    jitter_rng: rand_chacha::ChaCha8Rng,
    /// Time of the next IMU sample (drawn ahead, so the streams can say when they step next).
    next_time: f64,
    /// The second part of a sample split at a frame time ([`VehicleSim::stream_step`]).
    pending: Option<(ImuSample, TruthSample)>,
    /// Truth at the end of the last part [`VehicleSim::stream_step`] returned.
    stream_truth: TruthSample,
    imu: ImuErrors,
    sensor: TerrainSensor,
    step: u64,
    truth: TruthSample,
    /// The body's motion at the current step (start of the next IMU interval).
    motion: BodyMotion,
    initial_truth: TruthSample,
    initial_estimate: InitialEstimate,
    cfg: VehicleConfig,
    seed: u64,
}

impl VehicleSim {
    /// Sets up a vehicle in `world` with its own `seed` (see [`super::vehicle_seed`]). Validates
    /// the vehicle's configuration (error paths relative to the vehicle).
    pub fn new(cfg: &VehicleConfig, world: Arc<World>, seed: u64) -> Result<Self, ScenarioError> {
        cfg.validate_except_trajectory(world.frame())?;
        let trajectory = Trajectory::new(cfg.trajectory()?).map_err(|e| e.within("trajectory"))?;
        check_clearance(&trajectory, &world)?;
        let dt = 1.0 / cfg.imu.rate_hz;
        let frame_every = (cfg.imu.rate_hz / cfg.sensor.rate_hz).round() as u64;
        let imu = ImuErrors::new(
            cfg.imu.truth_errors(),
            dt,
            ImuStreams {
                white: rng_stream(seed, STREAM_IMU_WHITE),
                walk: rng_stream(seed, STREAM_IMU_WALK),
                instability: rng_stream(seed, STREAM_IMU_INSTABILITY),
                calibration: rng_stream(seed, STREAM_IMU_CALIBRATION),
            },
        );
        let tracker = world.appearance().map(|table| {
            Tracker::new(
                table.config(),
                cfg.sensor.min_range_m,
                cfg.sensor.max_range_m,
                rng_stream(seed, STREAM_APPEARANCE_FLIPS),
                rng_stream(seed, STREAM_TRACK_BREAKS),
            )
        });
        let sensor = TerrainSensor::new(
            &cfg.sensor,
            rng_stream(seed, STREAM_SENSOR_NOISE),
            rng_stream(seed, STREAM_MISMATCH),
            tracker,
        );
        let truth = truth_at(&world, &trajectory, &imu, 0.0);
        let motion = world.body_motion(0.0, &trajectory.state(0.0));
        let mut initial_estimate = draw_initial_estimate(cfg, &world, &truth, seed);
        if world.own_frames() {
            initial_estimate =
                own_start(&launch_from_own(&truth).inverse_estimate(&initial_estimate));
        }
        let jitter = cfg.imu.timestamp_jitter_s;
        let mut jitter_rng = rng_stream(seed, STREAM_IMU_JITTER);
        let next_time = sample_time(1, dt, jitter, &mut jitter_rng);
        Ok(Self {
            id: cfg.id,
            name: cfg.display_name(),
            world,
            trajectory,
            synthesis: cfg.imu.synthesis,
            dt,
            frame_every,
            frame_period: 1.0 / cfg.sensor.rate_hz,
            frame_offset: cfg.sensor.time_offset_s,
            next_frame: 1,
            jitter,
            jitter_rng,
            next_time,
            pending: None,
            stream_truth: truth,
            imu,
            sensor,
            step: 0,
            truth,
            motion,
            initial_truth: truth,
            initial_estimate,
            cfg: cfg.clone(),
            seed,
        })
    }

    /// A fresh initial estimate at the current time (truth plus an offset drawn from the
    /// configured σ), for a vehicle process that restarts mid-run and re-initializes from an
    /// external fix. `draw` selects an independent offset (e.g. the restart count).
    pub fn restart_estimate(&self, draw: u64) -> InitialEstimate {
        let seed = super::splitmix64(self.seed ^ draw.wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let e = draw_initial_estimate(&self.cfg, &self.world, &self.truth, seed);
        if self.world.own_frames() {
            launch_from_own(&self.initial_truth).inverse_estimate(&e)
        } else {
            e
        }
    }

    /// The vehicle's own frame in the launch frame (`[world] frames = "own"`): origin at its
    /// true start position, north along its true start heading. Truth: for the monitor's
    /// metrics only.
    pub fn launch_from_own(&self) -> Frame4 {
        if self.world.own_frames() {
            launch_from_own(&self.initial_truth)
        } else {
            Frame4::identity()
        }
    }

    /// Vehicle id.
    pub fn id(&self) -> u32 {
        self.id
    }

    /// Vehicle name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Navigation frame.
    pub fn frame(&self) -> NavFrame {
        self.world.frame()
    }

    /// The world.
    pub fn world(&self) -> &Arc<World> {
        &self.world
    }

    /// The trajectory.
    pub fn trajectory(&self) -> &Trajectory {
        &self.trajectory
    }

    /// IMU sample period Δt [s].
    pub fn imu_dt(&self) -> f64 {
        self.dt
    }

    /// IMU steps between terrain-sensor frames.
    pub fn frame_every(&self) -> u64 {
        self.frame_every
    }

    /// Steps taken so far.
    pub fn step_index(&self) -> u64 {
        self.step
    }

    /// Current simulation time [s].
    pub fn time(&self) -> f64 {
        self.truth.time
    }

    /// The sensor model the estimator must use.
    pub fn sensor_model(&self) -> SensorModel {
        *self.sensor.model()
    }

    /// The sensor mount the estimator must use.
    pub fn sensor_mount(&self) -> SensorMount {
        *self.sensor.mount()
    }

    /// Truth at the current step.
    pub fn truth(&self) -> &TruthSample {
        &self.truth
    }

    /// Truth at time 0 (the estimator's starting point).
    pub fn initial_truth(&self) -> &TruthSample {
        &self.initial_truth
    }

    /// The simulated IMU's errors (truth the estimator does not see).
    pub fn imu_errors(&self) -> &ImuErrors {
        &self.imu
    }

    /// The estimator's initial state and covariance (truth plus the drawn offset).
    pub fn initial_estimate(&self) -> &InitialEstimate {
        &self.initial_estimate
    }

    /// Noise-free kinematic truth (p, v, Ψ in the vehicle's frame) at any time.
    pub fn nav_truth_at(&self, time: f64) -> NavTruth {
        self.world.nav_truth(time, &self.trajectory.state(time))
    }

    /// The noise-free, bias-free IMU sample of the interval (t0, t1] by any synthesis.
    pub fn ideal_imu(&self, t0: f64, t1: f64, synthesis: ImuSynthesis) -> ImuIdeal {
        let (s0, s1) = (self.trajectory.state(t0), self.trajectory.state(t1));
        self.synthesise(
            synthesis,
            &self.world.body_motion(t0, &s0),
            &self.world.nav_truth(t0, &s0),
            &self.world.body_motion(t1, &s1),
            &self.world.nav_truth(t1, &s1),
        )
    }

    /// The noise-free sample between two truth instants (motion and navigation truth of each).
    fn synthesise(
        &self,
        synthesis: ImuSynthesis,
        motion0: &BodyMotion,
        nav0: &NavTruth,
        motion1: &BodyMotion,
        nav1: &NavTruth,
    ) -> ImuIdeal {
        let m = self.world.mechanization();
        match synthesis {
            ImuSynthesis::Exact => exact_increments(m, motion0, motion1, |t| {
                self.world.translation(&self.trajectory.kinematics(t))
            }),
            ImuSynthesis::Discrete => discrete_ideal(m, nav0, nav1),
            ImuSynthesis::Continuous => continuous_ideal(
                m,
                self.world.launch_frame(),
                &self.trajectory.state(0.5 * (nav0.time + nav1.time)),
            ),
        }
    }

    /// Time of the next IMU sample: k·Δt, plus the jitter of `[vehicle.imu] timestamp_jitter_s`.
    pub fn next_time(&self) -> f64 {
        self.next_time
    }

    /// Advances one IMU sample: the IMU sample of (t_{k−1}, t_k] (t_k = k·Δt, jittered when
    /// configured, the measurement over the actual interval), a sensor frame when one falls in
    /// that interval — at its own time n/rate + offset, seen from the truth at that time, so it
    /// may lie *between* t_{k−1} and t_k as a real camera's does — and the truth at t_k. Without
    /// jitter or offset and with the IMU rate a multiple of the frame rate, frames fall on the
    /// samples t_k with k a multiple of [`VehicleSim::frame_every`].
    pub fn step(&mut self) -> StepOutput {
        let prev = self.truth.nav();
        self.step += 1;
        let time = self.next_time;
        self.next_time = sample_time(self.step + 1, self.dt, self.jitter, &mut self.jitter_rng);
        let dt = time - prev.time;
        let state = self.trajectory.state(time);
        let nav = self.world.nav_truth(time, &state);
        let motion = self.world.body_motion(time, &state);
        let ideal = self.synthesise(self.synthesis, &self.motion, &prev, &motion, &nav);
        self.motion = motion;
        let measured = if self.jitter > 0.0 {
            self.imu.corrupt_over(&ideal, dt)
        } else {
            self.imu.corrupt(&ideal)
        };
        self.truth = truth_sample(&self.world, &state, &nav, &self.imu);
        let frame_time = self.next_frame as f64 * self.frame_period + self.frame_offset;
        // A frame at (or within 1 ns of: rates are decimals, their products round) this sample
        // time is taken at the sample; one before it, inside the interval, at its own time.
        let frame = (frame_time <= time + FRAME_SNAP_S).then(|| {
            self.next_frame += 1;
            let at = if frame_time >= time - FRAME_SNAP_S {
                self.truth
            } else {
                truth_at(&self.world, &self.trajectory, &self.imu, frame_time)
            };
            let nav = at.nav();
            let world_from_body = self.world.world_from_body(&nav);
            let frame = self.world.frame();
            self.sensor.observe(
                at.time,
                &world_from_body,
                &nav.position,
                self.world.features(),
                self.world.appearance(),
                |f| f.position(frame),
            )
        });
        let sample = |m: &ImuIdeal| ImuSample {
            time,
            dt,
            specific_force: m.specific_force,
            angular_rate: m.angular_rate,
        };
        StepOutput {
            imu: sample(&measured),
            imu_ideal: sample(&ideal),
            frame,
            truth: self.truth,
        }
    }

    /// The estimator's stream: [`VehicleSim::step`] with a sample that straddles a frame split
    /// at the frame time exactly as a replay splits it ([`crate::replay::split_at_frames`]: the
    /// same measured f̂ and ω̂ over both parts), the frame after the first part, the truth at the
    /// end of each part. Returns one part per call.
    pub fn stream_step(&mut self) -> StepOutput {
        if let Some((imu, truth)) = self.pending.take() {
            self.stream_truth = truth;
            return StepOutput {
                imu,
                imu_ideal: imu,
                frame: None,
                truth,
            };
        }
        let mut out = self.step();
        self.stream_truth = out.truth;
        let Some(tf) = out.frame.as_ref().map(|f| f.frame.time) else {
            return out;
        };
        if tf >= out.imu.time {
            return out;
        }
        let t_prev = out.imu.time - out.imu.dt;
        let rest = ImuSample {
            dt: out.imu.time - tf,
            ..out.imu
        };
        self.pending = Some((rest, out.truth));
        out.imu = ImuSample {
            time: tf,
            dt: tf - t_prev,
            ..out.imu
        };
        out.imu_ideal = out.imu;
        out.truth = truth_at(&self.world, &self.trajectory, &self.imu, tf);
        self.stream_truth = out.truth;
        out
    }

    /// Truth at the end of the last part [`VehicleSim::stream_step`] returned.
    pub fn stream_truth(&self) -> &TruthSample {
        &self.stream_truth
    }

    /// Time of the next part [`VehicleSim::stream_step`] returns.
    pub fn stream_next_time(&self) -> f64 {
        match &self.pending {
            Some((imu, _)) => imu.time,
            None => {
                let tf = self.next_frame as f64 * self.frame_period + self.frame_offset;
                if tf < self.next_time - FRAME_SNAP_S {
                    tf
                } else {
                    self.next_time
                }
            }
        }
    }

    /// Time of the last part [`VehicleSim::stream_step`] returned.
    pub fn stream_time(&self) -> f64 {
        self.stream_truth.time
    }
}

/// Frames within this of a sample time are taken at the sample [s]: products of decimal rates
/// round by ulps (1e-15 s); no camera is synchronised better than a microsecond.
const FRAME_SNAP_S: f64 = 1e-9;

/// Time of IMU sample k: k·Δt (no accumulated rounding), plus U(−j, j) when j > 0 (the stream
/// is drawn only then, so scenarios without jitter keep their draws).
fn sample_time(k: u64, dt: f64, jitter: f64, rng: &mut rand_chacha::ChaCha8Rng) -> f64 {
    let t = k as f64 * dt;
    if jitter > 0.0 {
        t + rng.random_range(-jitter..jitter)
    } else {
        t
    }
}

/// Draws the initial estimate: truth plus an offset from the configured σ (module doc of
/// [`InitialEstimate`]).
fn draw_initial_estimate(
    cfg: &VehicleConfig,
    world: &World,
    truth: &TruthSample,
    seed: u64,
) -> InitialEstimate {
    let mut rng = rng_stream(seed, STREAM_INITIAL);
    let mut draw = |sigma: [f64; 3]| -> Vector3<f64> {
        let n: [f64; 3] = [
            rng.sample(StandardNormal),
            rng.sample(StandardNormal),
            rng.sample(StandardNormal),
        ];
        if cfg.initial.draw_offset {
            Vector3::new(n[0] * sigma[0], n[1] * sigma[1], n[2] * sigma[2])
        } else {
            Vector3::zeros()
        }
    };
    let ic = &cfg.initial;
    let att_sigma = ic.attitude_sigma_deg.map(f64::to_radians);
    let dp = draw(ic.position_sigma_m);
    let dv = draw(ic.velocity_sigma_mps);
    let datt = draw(att_sigma);
    // NED offsets and σ are along the vehicle's local level; rotate them into ECEF.
    let rot = match world.frame() {
        NavFrame::Local => Matrix3::identity(),
        NavFrame::Global => {
            let g = ecef_to_geodetic(&truth.position);
            ecef_from_ned(g.lat, g.lon)
        }
    };
    let diag = |s: [f64; 3]| Matrix3::from_diagonal(&Vector3::from(s).map(|x| x * x));
    let noise = cfg.imu.noise_model();
    let mut covariance = SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::zeros();
    covariance
        .fixed_view_mut::<3, 3>(POS, POS)
        .copy_from(&(rot * diag(ic.position_sigma_m) * rot.transpose()));
    covariance
        .fixed_view_mut::<3, 3>(VEL, VEL)
        .copy_from(&(rot * diag(ic.velocity_sigma_mps) * rot.transpose()));
    covariance
        .fixed_view_mut::<3, 3>(ATT, ATT)
        .copy_from(&diag(att_sigma));
    covariance
        .fixed_view_mut::<3, 3>(ACC_BIAS, ACC_BIAS)
        .copy_from(&diag([noise.accel_bias_sigma; 3]));
    covariance
        .fixed_view_mut::<3, 3>(GYRO_BIAS, GYRO_BIAS)
        .copy_from(&diag([noise.gyro_bias_sigma; 3]));
    let t = truth;
    InitialEstimate {
        time: t.time,
        position: t.position + rot * dp,
        velocity: t.velocity + rot * dv,
        attitude: (t.attitude + datt).map(wrap_angle),
        accel_bias: Vector3::zeros(),
        gyro_bias: Vector3::zeros(),
        covariance,
    }
}

/// Least height a trajectory must keep above the terrain [m] (features stand up to
/// `max_height_above_ground_m` on it; the sensor needs some range).
pub const MIN_CLEARANCE: f64 = 10.0;

/// Rejects a trajectory that passes within [`MIN_CLEARANCE`] of the terrain, sampled at
/// [`super::trajectory::ENVELOPE_SAMPLES`] points over a period.
fn check_clearance(trajectory: &Trajectory, world: &World) -> Result<(), ScenarioError> {
    let n = super::trajectory::ENVELOPE_SAMPLES;
    let lowest = (0..n)
        .map(|i| {
            let p = trajectory
                .kinematics(trajectory.period() * i as f64 / n as f64)
                .position;
            -p.z - world.terrain().height(p.x, p.y)
        })
        .fold(f64::INFINITY, f64::min);
    if lowest < MIN_CLEARANCE {
        return Err(ScenarioError::invalid(
            "trajectory.altitude_m",
            format!(
                "the path comes within {lowest:.1} m of the terrain (at least {MIN_CLEARANCE} m)"
            ),
        ));
    }
    Ok(())
}

/// Truth of a vehicle at `time` with the IMU's current biases.
fn truth_at(world: &World, trajectory: &Trajectory, imu: &ImuErrors, time: f64) -> TruthSample {
    let s = trajectory.state(time);
    truth_sample(world, &s, &world.nav_truth(time, &s), imu)
}

/// Assembles a truth sample from the launch-frame state, its frame image and the IMU biases.
fn truth_sample(world: &World, s: &FlightState, nav: &NavTruth, imu: &ImuErrors) -> TruthSample {
    let time = nav.time;
    TruthSample {
        time,
        frame: world.frame(),
        position: nav.position,
        velocity: nav.velocity,
        attitude: nav.attitude,
        accel_bias: imu.accel_bias(),
        gyro_bias: imu.gyro_bias(),
        launch_position: s.kinematics.position,
        launch_velocity: s.kinematics.velocity,
        launch_attitude: s.attitude,
    }
}
