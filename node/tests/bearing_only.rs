//! Bearing-only inertial SLAM (§21.4) driven by the world simulator: association and hypothesis
//! culling against the simulator's truth, Monte Carlo consistency of bearing-only vehicles next
//! to a range-bearing vehicle flying the same trajectory in the global and local frames, and a
//! mixed centralized team.
//!
//! Runtime (release, one core): the scenario is a single-vehicle 3-leg lawnmower over 150
//! features at 100 Hz IMU / 2 Hz camera; the Monte Carlo is 30 runs × 120 s × 3 sensors × 2
//! frames (≈ 25 s), the association test 2 × 60 s, the team test 20 × 60 s (≈ 3 s).

use canopy_fusion::consistency::{anees_band, nees, vehicle_error};
use canopy_fusion::ins::VehicleState;
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::slam::{
    AssociationConfig, AssociationMode, BearingConfig, BearingStats, ObservationOutcome,
    RejectReason, SlamConfig, SlamFilter, VehicleSetup,
};
use canopy_fusion::state::{ATT, POS};
use canopy_node::scenario::{
    AppearanceConfig, AreaConfig, EarthModel, FeatureConfig, Identity, InitialConfig, Scenario,
    SensorConfig, SensorModelConfig, ShapeConfig, TrajectoryConfig, VehicleConfig, WorldConfig,
};
use canopy_node::world::{self, TruthSample};
use nalgebra::{DMatrix, DVector};
use std::collections::HashMap;

const SIGMA_BEARING_DEG: f64 = 0.2;

fn bearing_sensor() -> SensorModelConfig {
    SensorModelConfig::Bearing {
        sigma_bearing_deg: SIGMA_BEARING_DEG,
    }
}

/// A 640×480 camera with 600 px focal length (±28° × ±22°), σ 1 px (≈ 0.1°).
fn pixel_sensor() -> SensorModelConfig {
    SensorModelConfig::vga_camera(1.0)
}

fn range_bearing_sensor() -> SensorModelConfig {
    SensorModelConfig::RangeBearing {
        sigma_range_m: 0.5,
        sigma_bearing_deg: SIGMA_BEARING_DEG,
    }
}

/// One vehicle flying a 3-leg lawnmower (600 m legs, 150 m apart) at 120 m over a 900 m square
/// with 150 features; a 60 s run covers two legs and a turn.
fn scenario(earth: EarthModel, sensor: SensorModelConfig, seed: u64) -> Scenario {
    Scenario {
        world: WorldConfig {
            seed,
            earth_model: earth,
            area: AreaConfig {
                centre_north_m: 0.0,
                centre_east_m: 0.0,
                size_north_m: 900.0,
                size_east_m: 900.0,
            },
            features: FeatureConfig {
                count: Some(150),
                ..FeatureConfig::default()
            },
            // These runs judge the filter's single-vehicle pipelines against the true ids
            // (the map is keyed by them): perfect identities, the named ablation.
            appearance: AppearanceConfig {
                identity: Identity::Perfect,
                ..AppearanceConfig::default()
            },
            ..WorldConfig::default()
        },
        vehicles: vec![VehicleConfig {
            id: 1,
            name: None,
            frame: None,
            trajectory: Some(TrajectoryConfig {
                altitude_m: 120.0,
                speed_mps: 20.0,
                shape: ShapeConfig::Lawnmower {
                    leg_length_m: 600.0,
                    leg_spacing_m: 150.0,
                    legs: 3,
                    turn_ramp_fraction: 0.4,
                },
                ..TrajectoryConfig::default()
            }),
            sensor: SensorConfig {
                model: sensor,
                ..SensorConfig::default()
            },
            imu: Default::default(),
            initial: InitialConfig::default(),
            replay: None,
            bearing: Default::default(),
        }],
        run: Default::default(),
        fusion: canopy_node::scenario::FusionConfig {
            mode: canopy_node::scenario::FusionMode::Isolated,
            ..Default::default()
        },
        links: Vec::new(),
        partitions: Vec::new(),
        events: Vec::new(),
        secrets: Default::default(),
        zenoh: Default::default(),
        hosts: Vec::new(),
    }
}

fn truth_state(t: &TruthSample) -> VehicleState {
    VehicleState {
        position: t.position,
        velocity: t.velocity,
        attitude: t.attitude,
        accel_bias: t.accel_bias,
        gyro_bias: t.gyro_bias,
    }
}

/// What one run measured.
#[derive(Debug, Default)]
struct RunResult {
    /// 6-dof pose (p, Ψ) NEES at the end.
    pose_nees: f64,
    /// Sum of 3-dof feature NEES over the final map, and the number of features.
    map_nees_sum: f64,
    map_features: usize,
    /// Sum of squared feature position errors [m²].
    map_sq_err: f64,
    /// Observations stored with a track of another feature.
    wrong_stored: usize,
    /// Observations used on (or initializing) a map feature of another true feature.
    wrong_in_map: usize,
    /// Observations gated into another feature's track whose triangulation was then rejected
    /// (the miss test of 21.4.2.3 caught the misassociation; nothing was stored or used).
    caught_by_triangulation: usize,
    /// Tracks checked for culling, and the ones whose surviving hypotheses were not the ones
    /// nearest the true range.
    culling_checked: usize,
    culling_failed: usize,
    /// Sum over checked tracks of the number of surviving hypotheses.
    survivors_sum: usize,
    /// Observations processed (stored, associated or rejected).
    observations: usize,
    stats: BearingStats,
    max_poses: usize,
}

/// How to run one scenario.
#[derive(Clone, Copy, Debug)]
struct Options {
    mode: AssociationMode,
    duration: f64,
    /// Replaces the filter's default bearing-only options.
    bearing: Option<BearingConfig>,
    /// Check the culling of tracks with at least this many stored observations.
    culling_min_observations: Option<usize>,
}

impl Options {
    fn new(mode: AssociationMode, duration: f64) -> Self {
        Self {
            mode,
            duration,
            bearing: None,
            culling_min_observations: None,
        }
    }
}

/// Runs one scenario with the filter fed the simulator's messages.
fn run(scn: &Scenario, opt: Options) -> RunResult {
    let Options {
        mode,
        duration,
        bearing,
        culling_min_observations,
    } = opt;
    let (world, mut sims) = world::build(scn).unwrap();
    let frame = world.frame();
    let sim = &mut sims[0];
    let init = sim.initial_estimate().clone();
    let setup = VehicleSetup {
        state: VehicleState {
            position: init.position,
            velocity: init.velocity,
            attitude: init.attitude,
            accel_bias: init.accel_bias,
            gyro_bias: init.gyro_bias,
        },
        covariance: init.covariance,
        imu_noise: scn.vehicles[0].imu.noise_model(),
        sensor: sim.sensor_model(),
        mount: sim.sensor_mount(),
    };
    let mut filter = SlamFilter::new(
        SlamConfig {
            frame,
            local_gravity_mps2: world.local_gravity(),
            origin: world.map_origin(),
            association: AssociationConfig {
                mode,
                gate_probability: 0.95,
                ..AssociationConfig::default()
            },
            fresh_id_namespace: 1,
        },
        &[setup],
    )
    .unwrap();
    if let Some(b) = bearing {
        filter.set_bearing_config(b).unwrap();
    }
    let model = *filter.observation_model(0).unwrap();
    let cfg = *filter.bearing_config();
    let spacing = (cfg.max_range - cfg.min_range) / (cfg.hypotheses - 1) as f64;
    let mut result = RunResult::default();
    // Truth behind tracks and features: track → (true id, true range at its first observation).
    let mut track_truth: HashMap<u64, (FeatureId, f64)> = HashMap::new();
    let mut feature_truth: HashMap<FeatureId, FeatureId> = HashMap::new();
    // Tracks holding an observation of another feature (their culling follows a mixture).
    let mut wrong_tracks = std::collections::HashSet::new();
    let steps = (duration / sim.imu_dt()).round() as u64;
    let mut truth = *sim.truth();
    for _ in 0..steps {
        let out = sim.step();
        truth = out.truth;
        filter.predict(0, &out.imu).unwrap();
        let Some(sensed) = out.frame else {
            continue;
        };
        let report = filter.process_frame(0, &sensed.frame).unwrap();
        let pose = model.sensor_pose(&truth.position, &truth.attitude);
        for (track, feature) in &report.initialized_tracks {
            if let Some((true_id, _)) = track_truth.get(track) {
                feature_truth.insert(*feature, *true_id);
            }
        }
        result.observations += report.outcomes.len();
        for (i, outcome) in report.outcomes.iter().enumerate() {
            let true_id = sensed.true_ids[i];
            match outcome {
                ObservationOutcome::Stored { track } => {
                    let m = world.feature(true_id).unwrap().position(frame);
                    let range = pose.relative_position(&m).value.norm();
                    let entry = track_truth.entry(*track).or_insert((true_id, range));
                    if entry.0 != true_id {
                        result.wrong_stored += 1;
                        wrong_tracks.insert(*track);
                    }
                }
                ObservationOutcome::Associated { feature, .. }
                | ObservationOutcome::Initialized { feature } => {
                    let entry = feature_truth.entry(*feature).or_insert(true_id);
                    if *entry != true_id {
                        result.wrong_in_map += 1;
                    }
                }
                ObservationOutcome::Rejected(RejectReason::TriangulationFailed { track }) => {
                    if track_truth.get(track).is_some_and(|t| t.0 != true_id) {
                        result.caught_by_triangulation += 1;
                    }
                }
                ObservationOutcome::Rejected(_) => {}
            }
        }
        if let Some(min_obs) = culling_min_observations {
            for t in filter.tracks() {
                if t.observations < min_obs || wrong_tracks.contains(&t.id) {
                    continue;
                }
                let Some((_, r_true)) = track_truth.get(&t.id) else {
                    continue;
                };
                result.culling_checked += 1;
                // Index of each surviving hypothesis on the original grid.
                let grid: Vec<usize> = t
                    .hypothesis_ranges
                    .iter()
                    .map(|r| ((r - cfg.min_range) / spacing).round() as usize)
                    .collect();
                let contiguous = grid.windows(2).all(|w| w[1] == w[0] + 1);
                let farthest = t
                    .hypothesis_ranges
                    .iter()
                    .map(|r| (r - r_true).abs())
                    .fold(0.0, f64::max);
                result.survivors_sum += t.hypothesis_ranges.len();
                // Culled to the hypotheses nearest the true range: a non-empty contiguous window
                // of the grid, every survivor within 2 spacings of the truth. (Each hypothesis
                // has a range σ of half a spacing and the window centres on the *estimated*
                // range, a few metres from the truth, so up to three neighbours survive, the
                // outer one up to ≈ 1.7 spacings from the truth.)
                if grid.is_empty() || !contiguous || farthest > 2.0 * spacing {
                    result.culling_failed += 1;
                }
            }
        }
        result.max_poses = result.max_poses.max(filter.num_stored_poses());
    }
    // Final pose NEES (6 dof: p, Ψ).
    let est = filter.vehicle_state(0).unwrap();
    let err = vehicle_error(&est, &truth_state(&truth));
    let cov = filter.vehicle_covariance(0).unwrap();
    let idx = [POS, POS + 1, POS + 2, ATT, ATT + 1, ATT + 2];
    let e = DVector::from_fn(6, |i, _| err[idx[i]]);
    let c = DMatrix::from_fn(6, 6, |i, j| cov[(idx[i], idx[j])]);
    result.pose_nees = nees(&e, &c).unwrap();
    for (id, m) in filter.features() {
        let true_id = feature_truth.get(&id).copied().unwrap_or(id);
        let Some(tf) = world.feature(true_id) else {
            continue;
        };
        let e = m - tf.position(frame);
        let c = filter.feature_covariance(id).unwrap();
        let e_d = DVector::from_column_slice(e.as_slice());
        let c_d = DMatrix::from_fn(3, 3, |i, j| c[(i, j)]);
        result.map_nees_sum += nees(&e_d, &c_d).unwrap();
        result.map_sq_err += e.norm_squared();
        result.map_features += 1;
    }
    result.stats = filter.bearing_stats();
    result
}

/// Descriptor mode (the default) with 10 % wrong descriptors injected by the simulator (half
/// naming another real feature, half naming none), default noise, 5 seeds × 60 s per frame: no
/// observation is stored with, used on, or initializes a feature other than its own — wrong
/// descriptors are stopped by the feature gate (21.55) or the track gate (21.81–21.82).
#[test]
fn descriptor_mode_stops_wrong_descriptors() {
    for earth in [EarthModel::Flat, EarthModel::Wgs84] {
        let (mut wrong, mut obs, mut feats) = (0, 0, 0);
        for seed in 0..5 {
            let mut scn = scenario(earth, bearing_sensor(), 300 + seed);
            scn.vehicles[0].sensor.mismatch_probability = 0.1;
            let r = run(&scn, Options::new(AssociationMode::Descriptor, 60.0));
            wrong += r.wrong_stored + r.wrong_in_map;
            obs += r.observations;
            feats += r.stats.features_initialized;
        }
        eprintln!("{earth:?}: {wrong} wrong associations in {obs} observations, {feats} features");
        assert_eq!(wrong, 0, "{earth:?}");
        assert!(feats > 150, "{earth:?}: {feats}");
    }
}

/// Descriptors ignored (nearest-neighbour and JCBB modes): every observation reaches its track or
/// feature through the gates alone (21.55 for initialized features, 21.81–21.82 with the
/// correlated track gate for uninitialized ones). At the default noise, wrong associations are
/// rare: they happen between features a few metres apart (a few bearing σ at 150 m), which a
/// bearing cannot tell apart; the measured rate is printed and bounded.
#[test]
fn association_without_descriptors_is_rarely_wrong() {
    use canopy_fusion::slam::TrackGate;
    let nn = AssociationMode::NearestNeighbour;
    let jcbb = AssociationMode::Jcbb { max_nodes: 2000 };
    let cases = [
        (EarthModel::Flat, nn, TrackGate::Correlated, 0..10),
        (EarthModel::Wgs84, nn, TrackGate::Correlated, 0..4),
        (EarthModel::Flat, jcbb, TrackGate::Correlated, 0..4),
        (EarthModel::Flat, nn, TrackGate::Chapter, 0..10),
    ];
    for (earth, mode, track_gate, seeds) in cases {
        let (mut stored, mut in_map, mut caught, mut obs, mut feats) = (0, 0, 0, 0, 0);
        for seed in seeds {
            let opt = Options {
                bearing: Some(BearingConfig {
                    track_gate,
                    ..BearingConfig::default()
                }),
                ..Options::new(mode, 60.0)
            };
            let r = run(&scenario(earth, bearing_sensor(), seed), opt);
            stored += r.wrong_stored;
            in_map += r.wrong_in_map;
            caught += r.caught_by_triangulation;
            obs += r.observations;
            feats += r.stats.features_initialized;
        }
        let rate = (stored + in_map) as f64 / obs as f64;
        eprintln!(
            "{earth:?} {mode:?} {track_gate:?}: {obs} observations, wrong stored {stored}, wrong \
             in map {in_map} (rate {:.3} %), caught by the miss test {caught}, {feats} features",
            100.0 * rate
        );
        // Measured 0.15–0.18 % with the correlated gate and 0.33 % with 21.83 (close feature
        // pairs); 1 % flags a regression of the gates.
        assert!(rate < 0.01, "{earth:?} {mode:?} {track_gate:?}: {rate}");
        assert!(feats > 100, "{earth:?} {mode:?}: {feats}");
    }
}

/// A feature watched over a long baseline (initialization held back to 40° of parallax so tracks
/// collect observations), descriptors ignored: the hypotheses of every track with six or more
/// observations (tracks holding a misassociated observation excluded; they are rare, see the
/// test above) are culled to a contiguous window of the grid around its true range (every
/// survivor within 2 spacings of the truth) in all but a rare track, about two hypotheses of
/// 24 on average (21.4.3.2, Fig. 21.4).
#[test]
fn hypotheses_are_culled_to_the_true_range() {
    for earth in [EarthModel::Flat, EarthModel::Wgs84] {
        let (mut checked, mut failed, mut survivors) = (0, 0, 0);
        for seed in 0..4 {
            let r = run(
                &scenario(earth, bearing_sensor(), 400 + seed),
                Options {
                    bearing: Some(BearingConfig {
                        min_parallax: 40f64.to_radians(),
                        ..BearingConfig::default()
                    }),
                    culling_min_observations: Some(6),
                    ..Options::new(AssociationMode::NearestNeighbour, 60.0)
                },
            );
            checked += r.culling_checked;
            failed += r.culling_failed;
            survivors += r.survivors_sum;
        }
        let mean = survivors as f64 / checked.max(1) as f64;
        eprintln!(
            "{earth:?}: {checked} track checks, {failed} not culled to the true range, mean \
             survivors {mean:.2} of 24"
        );
        assert!(checked > 200, "{earth:?}: {checked}");
        // Culling is a sequence of 95 % gates, so a track can occasionally lose the hypotheses
        // at its true range (measured: 1 check in ≈ 1700); 1 % flags a systematic error.
        assert!(
            (failed as f64) < 0.01 * checked as f64,
            "{earth:?}: {failed}/{checked}"
        );
        assert!(mean < 3.0, "{earth:?}: {mean}");
    }
}

/// Summary of a Monte Carlo batch.
#[derive(Debug)]
struct Batch {
    pose_anees: f64,
    map_anees_per_dof: f64,
    map_rmse: f64,
    map_features: usize,
    max_poses: usize,
}

const MC_DURATION: f64 = 120.0;

fn monte_carlo(earth: EarthModel, sensor: SensorModelConfig, runs: u64) -> Batch {
    let mut pose = 0.0;
    let (mut map_nees, mut map_dof, mut sq, mut feats, mut max_poses) = (0.0, 0, 0.0, 0, 0);
    for seed in 0..runs {
        let r = run(
            &scenario(earth, sensor, 1000 + seed),
            Options::new(AssociationMode::Descriptor, MC_DURATION),
        );
        pose += r.pose_nees;
        map_nees += r.map_nees_sum;
        map_dof += 3 * r.map_features;
        sq += r.map_sq_err;
        feats += r.map_features;
        max_poses = max_poses.max(r.max_poses);
    }
    Batch {
        pose_anees: pose / runs as f64,
        map_anees_per_dof: map_nees / map_dof as f64,
        map_rmse: (sq / feats as f64).sqrt(),
        map_features: feats,
        max_poses,
    }
}

/// Monte Carlo (30 seeded runs per case; world, noise and initial offset all re-drawn) of
/// bearing-only vehicles (angles, and a pixel camera) and a range-bearing vehicle on the same
/// 120 s trajectory (two legs, a turn, part of a third leg), global and local: the final 6-dof
/// pose ANEES and the map NEES per dof.
///
/// Criterion: each figure is at most the χ² 95 % band's upper bound, or — EKF linearisation of
/// the bearing-only initialization makes the band unreachable in places — no worse than 1.5×
/// the range-bearing vehicle's figure on the same trajectory and seeds.
#[test]
fn monte_carlo_bearing_only_is_consistent_or_close_to_range_bearing() {
    let runs = 30;
    let (lo6, hi6) = anees_band(runs as usize, 6, 0.95).unwrap();
    // Map NEES per dof: band of χ²(3N)/(3N) over all N features of all runs (features of a run
    // share the vehicle's error, so this band is optimistic; the criterion falls back to the
    // range-bearing comparison).
    let band = |n: usize| {
        let (l, h) = anees_band(1, 3 * n, 0.95).unwrap();
        (l / (3 * n) as f64, h / (3 * n) as f64)
    };
    for earth in [EarthModel::Flat, EarthModel::Wgs84] {
        let rb = monte_carlo(earth, range_bearing_sensor(), runs);
        let (rl, rh) = band(rb.map_features);
        eprintln!(
            "{earth:?} range-bearing: pose ANEES {:.2} (band [{lo6:.2}, {hi6:.2}]), map NEES/dof \
             {:.3} (band [{rl:.3}, {rh:.3}]), map RMSE {:.2} m over {} features",
            rb.pose_anees, rb.map_anees_per_dof, rb.map_rmse, rb.map_features
        );
        for (name, sensor) in [("bearing", bearing_sensor()), ("pixel", pixel_sensor())] {
            let bo = monte_carlo(earth, sensor, runs);
            let (ml, mh) = band(bo.map_features);
            eprintln!(
                "{earth:?} {name}: pose ANEES {:.2} (band [{lo6:.2}, {hi6:.2}]), map NEES/dof \
                 {:.3} (band [{ml:.3}, {mh:.3}]), map RMSE {:.2} m over {} features, max stored \
                 poses {}",
                bo.pose_anees, bo.map_anees_per_dof, bo.map_rmse, bo.map_features, bo.max_poses
            );
            let pose_ok = bo.pose_anees <= hi6 || bo.pose_anees <= 1.5 * rb.pose_anees;
            let map_ok =
                bo.map_anees_per_dof <= mh || bo.map_anees_per_dof <= 1.5 * rb.map_anees_per_dof;
            assert!(
                pose_ok,
                "{earth:?} {name}: pose {} vs {}",
                bo.pose_anees, rb.pose_anees
            );
            assert!(
                map_ok,
                "{earth:?} {name}: map {} vs {}",
                bo.map_anees_per_dof, rb.map_anees_per_dof
            );
            // Not grossly under-confident either (that would hide a wrong covariance).
            assert!(
                bo.pose_anees >= 0.5 * lo6,
                "{earth:?} {name}: {}",
                bo.pose_anees
            );
            assert!(bo.map_anees_per_dof >= 0.5 * ml, "{earth:?} {name}");
            assert!(bo.max_poses <= 40);
        }
    }
}

/// Two vehicles in one centralized filter: (pose NEES summed over vehicles, map NEES sum, map
/// features, features first initialized by each vehicle).
fn run_team(scn: &Scenario, duration: f64) -> (f64, f64, usize, [usize; 2]) {
    let (world, mut sims) = world::build(scn).unwrap();
    let frame = world.frame();
    let setups: Vec<VehicleSetup> = sims
        .iter()
        .zip(&scn.vehicles)
        .map(|(sim, cfg)| {
            let init = sim.initial_estimate().clone();
            VehicleSetup {
                state: VehicleState {
                    position: init.position,
                    velocity: init.velocity,
                    attitude: init.attitude,
                    accel_bias: init.accel_bias,
                    gyro_bias: init.gyro_bias,
                },
                covariance: init.covariance,
                imu_noise: cfg.imu.noise_model(),
                sensor: sim.sensor_model(),
                mount: sim.sensor_mount(),
            }
        })
        .collect();
    let mut filter = SlamFilter::new(
        SlamConfig {
            frame,
            local_gravity_mps2: world.local_gravity(),
            origin: world.map_origin(),
            association: AssociationConfig::default(),
            fresh_id_namespace: 0,
        },
        &setups,
    )
    .unwrap();
    let mut by_vehicle = [0usize; 2];
    let steps = (duration / sims[0].imu_dt()).round() as u64;
    let mut truths = vec![*sims[0].truth(); sims.len()];
    for _ in 0..steps {
        for (v, sim) in sims.iter_mut().enumerate() {
            let out = sim.step();
            truths[v] = out.truth;
            filter.predict(v, &out.imu).unwrap();
            if let Some(sf) = out.frame {
                let r = filter.process_frame(v, &sf.frame).unwrap();
                by_vehicle[v] += r.initialized();
            }
        }
    }
    let mut pose_nees = 0.0;
    for (v, truth) in truths.iter().enumerate() {
        let err = vehicle_error(&filter.vehicle_state(v).unwrap(), &truth_state(truth));
        let cov = filter.vehicle_covariance(v).unwrap();
        let idx = [POS, POS + 1, POS + 2, ATT, ATT + 1, ATT + 2];
        let e = DVector::from_fn(6, |i, _| err[idx[i]]);
        let c = DMatrix::from_fn(6, 6, |i, j| cov[(idx[i], idx[j])]);
        pose_nees += nees(&e, &c).unwrap();
    }
    let (mut map_nees, mut n) = (0.0, 0);
    for (id, m) in filter.features() {
        let e = m - world.feature(id).unwrap().position(frame);
        let c = filter.feature_covariance(id).unwrap();
        map_nees += nees(
            &DVector::from_column_slice(e.as_slice()),
            &DMatrix::from_fn(3, 3, |i, j| c[(i, j)]),
        )
        .unwrap();
        n += 1;
    }
    (pose_nees, map_nees, n, by_vehicle)
}

/// A mixed team in one centralized filter — a range-bearing vehicle and a bearing-only vehicle
/// on a second, overlapping lawnmower — picks each vehicle's pipeline from its sensor model
/// (both initialize features; the bearing-only one through stored poses) and stays as
/// consistent as an all-range-bearing team on the same seeds (10 runs, 60 s, local frame):
/// 2×6-dof pose ANEES and map NEES per dof within 1.5× of the all-range-bearing team's.
#[test]
fn mixed_centralized_team_is_consistent() {
    let team = |second: SensorModelConfig, seed: u64| {
        let mut scn = scenario(EarthModel::Flat, range_bearing_sensor(), seed);
        let mut v2 = scn.vehicles[0].clone();
        v2.id = 2;
        v2.sensor.model = second;
        v2.trajectory.as_mut().unwrap().centre_ne_m = [0.0, 75.0];
        v2.trajectory.as_mut().unwrap().altitude_m = 140.0;
        v2.trajectory.as_mut().unwrap().phase = 0.1;
        scn.vehicles.push(v2);
        scn
    };
    let runs = 10;
    let (mut mixed, mut pure) = ((0.0, 0.0, 0), (0.0, 0.0, 0));
    for seed in 0..runs {
        let (p, m, n, by) = run_team(&team(bearing_sensor(), 2000 + seed), 60.0);
        assert!(
            by[0] > 10 && by[1] > 5,
            "both vehicles initialize features: {by:?}"
        );
        mixed = (mixed.0 + p, mixed.1 + m, mixed.2 + n);
        let (p, m, n, _) = run_team(&team(range_bearing_sensor(), 2000 + seed), 60.0);
        pure = (pure.0 + p, pure.1 + m, pure.2 + n);
    }
    let (lo, hi) = anees_band(runs as usize, 12, 0.95).unwrap();
    let mixed_pose = mixed.0 / runs as f64;
    let pure_pose = pure.0 / runs as f64;
    let mixed_map = mixed.1 / (3 * mixed.2) as f64;
    let pure_map = pure.1 / (3 * pure.2) as f64;
    eprintln!(
        "mixed team: pose ANEES {mixed_pose:.2} (band [{lo:.2}, {hi:.2}]), map NEES/dof \
         {mixed_map:.3} over {} features; all range-bearing: {pure_pose:.2}, {pure_map:.3} over {}",
        mixed.2, pure.2
    );
    assert!(
        mixed_pose <= hi || mixed_pose <= 1.5 * pure_pose,
        "{mixed_pose} vs {pure_pose}"
    );
    assert!(
        mixed_map <= 1.5 * pure_map.max(1.0),
        "{mixed_map} vs {pure_map}"
    );
}
