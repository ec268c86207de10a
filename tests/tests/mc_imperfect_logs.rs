//! Simulator-made logs with real-world imperfections replay with consistent estimates (issue
//! #11, acceptance 2).
//!
//! Each seed simulates the default scenario's first UAV alone in the local (flat) frame with what
//! real recordings have and the simulator's defaults do not:
//! - IMU time stamps jittered by U(−0.5, 0.5) ms around the 100 Hz grid, each sample measuring
//!   its actual interval;
//! - camera frames at 3 Hz with a 12.3 ms offset: off the IMU grid (33⅓ samples per frame), so
//!   every frame falls between two IMU samples and the replay must split the sample;
//! - the camera on a general mount (looking down, pitched 20° forward, rolled 10°) with a lever
//!   arm;
//! - a consumer-grade (MEMS) IMU whose errors go beyond the filter's model (the simulator's
//!   default `sensor` truth model: turn-on biases, Gauss–Markov bias instability, scale-factor
//!   and misalignment errors);
//! - outlier tracks: 2 % of observations carry a wrong descriptor (half of them naming another
//!   real feature), which association must reject.
//!
//! `canopy sim --record-logs` writes the logs (and, in a flat world, the truth as the replay's
//! ground truth); the logs are replayed as a replay scenario and judged against that truth only.
//! Proves: (1) the live simulation and the replay of its logs give the same estimate (the
//! simulator's split of a straddling sample is the replay's), (2) over 10 seeds the replayed
//! estimates are consistent — the pose ANEES in the χ² 95 % band of the runs — and position
//! errors stay small, both with the default range-bearing sensor and with the real-data path's
//! sensor: a pixel camera (640 × 480 px, σ 1 px) on the same mount whose tracks (descriptors,
//! 2 % of them wrong) initialize features by `multi_view` triangulation, as `canopy import`
//! configures a real recording.

use canopy_fusion::slam::BearingInit;
use canopy_node::network::FusionMode;
use canopy_node::scenario::{EarthModel, Identity, Scenario, SensorModelConfig};
use canopy_node::sim::{SimOptions, simulate};
use canopy_tests::montecarlo::pose_consistency;

const RUNS: u64 = 10;
/// Simulated seconds per run: long enough for several passes over mapped ground.
const DURATION: f64 = 120.0;

/// The imperfect single-vehicle scenario of `seed`; `camera`: a pixel camera with multi-view
/// initialization instead of the range-bearing sensor.
fn scenario(seed: u64, camera: bool) -> Scenario {
    let mut s = Scenario::builtin_default();
    s.vehicles.truncate(1);
    s.links.clear();
    s.fusion.mode = FusionMode::Isolated;
    s.world.earth_model = EarthModel::Flat;
    s.world.seed = seed;
    // Outliers here are wrong descriptors (`mismatch_probability`), a model of perfect
    // identities; the appearance model (the default) has its own errors instead.
    s.world.appearance.identity = Identity::Perfect;
    s.run.duration_s = DURATION;
    s.run.baseline = false;
    let v = &mut s.vehicles[0];
    v.imu.grade = canopy_fusion::imu::ImuGrade::Consumer;
    v.imu.timestamp_jitter_s = 0.5e-3;
    v.sensor.rate_hz = 3.0;
    v.sensor.time_offset_s = 0.0123;
    v.sensor.mismatch_probability = 0.02;
    v.sensor.orientation = None;
    v.sensor.sensor_from_body = Some(rows(&mount()));
    v.sensor.lever_arm_m = [0.2, -0.05, 0.15];
    if camera {
        v.sensor.model = SensorModelConfig::vga_camera(1.0);
        v.bearing.initialization = Some(BearingInit::MultiView);
    }
    s
}

/// C_b^s of a camera looking down, pitched 20° towards the nose and rolled 10°: the downward
/// mount (boresight x^s = +z^b) turned about the body's y and x axes.
fn mount() -> nalgebra::Matrix3<f64> {
    use nalgebra::{Rotation3, Vector3};
    let down = canopy_fusion::sensor::SensorMount::downward(Vector3::zeros()).sensor_from_body;
    let tilt = Rotation3::from_euler_angles(10f64.to_radians(), 20f64.to_radians(), 0.0);
    down * tilt.matrix().transpose()
}

fn rows(m: &nalgebra::Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// The replay scenario of `s`'s logs in `dir`.
fn replay_scenario(s: &Scenario, dir: &std::path::Path) -> Scenario {
    let logs = canopy_node::replay::record_logs(s, dir, DURATION).expect("logs are written");
    assert_eq!(logs.len(), 1);
    let mut r = s.clone();
    let v = &mut r.vehicles[0];
    v.trajectory = None;
    v.replay = Some(logs[0].1.clone());
    assert!(
        logs[0].1.groundtruth.is_some(),
        "a flat-world recording carries its truth"
    );
    // The imperfections are in the logs: every frame between two IMU samples (the replay
    // splits one sample per frame) and sample intervals that are not all the nominal 10 ms.
    let log = canopy_node::replay::ReplayLog::load(&logs[0].1, &r.vehicles[0], &r.world)
        .expect("the logs load");
    assert!(!log.frames.is_empty());
    assert_eq!(
        log.steps.len(),
        log.imu.len() + log.frames.len(),
        "every frame splits a sample"
    );
    let spread = log
        .imu
        .iter()
        .skip(1)
        .map(|x| (x.dt - 0.01).abs())
        .fold(0.0, f64::max);
    assert!(
        spread > 1e-4,
        "IMU intervals jitter (largest deviation {spread} s)"
    );
    r
}

#[test]
fn imperfect_logs_replay_consistently() {
    replay_consistently(false);
}

#[test]
fn imperfect_camera_logs_replay_consistently() {
    replay_consistently(true);
}

fn replay_consistently(camera: bool) {
    let tmp = tempfile::tempdir().unwrap();
    let mut records = Vec::new();
    for seed in 1..=RUNS {
        let s = scenario(seed, camera);
        s.validate().expect("the imperfect scenario is valid");
        let dir = tmp.path().join(format!("seed{seed}"));
        let replay = replay_scenario(&s, &dir);
        replay.validate().expect("the replay scenario is valid");
        let out = simulate(&replay, SimOptions::default()).expect("the replay runs");
        let rec = out.record.vehicles.into_iter().next().unwrap();
        if seed == 1 {
            // (1) The live run of the same scenario: the same inputs reach the estimator, so
            // the estimates agree sample by sample (the logs keep every digit).
            let live = simulate(&s, SimOptions::default()).expect("the live run runs");
            let lv = &live.record.vehicles[0];
            assert_eq!(lv.samples.len(), rec.samples.len(), "record times");
            let mut worst: f64 = 0.0;
            for (a, b) in lv.samples.iter().zip(&rec.samples) {
                assert_eq!(a.t, b.t, "record times");
                for k in 0..3 {
                    worst = worst.max((a.est_pos[k] - b.est_pos[k]).abs());
                }
            }
            println!("seed 1: live vs replay, largest position difference {worst:.3e} m");
            // Bit-for-bit is expected (same f64 inputs, same code path); 1 µm allows nothing
            // that would show in a metric.
            assert!(worst < 1e-6, "live and replay differ by {worst} m");
        }
        println!(
            "seed {seed}: observations {}, rejections {:?}, samples {}",
            rec.observations,
            rec.rejections,
            rec.samples.len()
        );
        records.push(rec);
    }
    let refs: Vec<_> = records.iter().collect();
    let pose = pose_consistency(&refs, 0.0);
    println!(
        "{} {RUNS} runs × {DURATION} s: pose ANEES/6 = {:.3} (band [{:.3}, {:.3}], {:.0} % of record times in band), position RMSE {:.3} m",
        if camera { "camera" } else { "range-bearing" },
        pose.time_mean,
        pose.band.0,
        pose.band.1,
        100.0 * pose.fraction_in_band,
        pose.position_rmse
    );
    // The time average of a per-time statistic that lies in [lo, hi] lies in [lo, hi] too.
    assert!(
        pose.time_mean >= pose.band.0 && pose.time_mean <= pose.band.1,
        "pose ANEES {:.3} outside {:?}",
        pose.time_mean,
        pose.band
    );
}
