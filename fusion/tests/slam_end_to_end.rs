//! End-to-end sanity of the range-bearing inertial SLAM filter without the world simulator:
//! closed-form truths (straight level flight in the local frame, a vehicle at rest on the
//! rotating Earth in the global frame), synthetic IMU samples and terrain observations.

use canopy_fusion::consistency::{anees_band, chi2_quantile, nees, vehicle_error};
use canopy_fusion::geodesy::{self, Geodetic, LocalFrame};
use canopy_fusion::imu::{ImuGrade, ImuNoise};
use canopy_fusion::ins::{VehicleCovariance, VehicleState};
use canopy_fusion::observation::ObservationModel;
use canopy_fusion::rotation::nav_from_body;
use canopy_fusion::sensor::{
    FeatureId, ImuSample, Measurement, Observation, ObservationFrame, SensorModel, SensorMount,
};
use canopy_fusion::slam::{
    AssociationConfig, AssociationMode, SlamConfig, SlamFilter, VehicleSetup,
};
use canopy_fusion::state::NavFrame;
use nalgebra::{DMatrix, DVector, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const SIGMA_RANGE: f64 = 0.5;
const SIGMA_BEARING: f64 = 0.002;

fn sensor() -> SensorModel {
    SensorModel::RangeBearing {
        sigma_range: SIGMA_RANGE,
        sigma_bearing: SIGMA_BEARING,
    }
}

fn mount() -> SensorMount {
    SensorMount::downward(Vector3::new(0.5, 0.0, 0.3))
}

fn initial_covariance(noise: &ImuNoise) -> VehicleCovariance {
    let mut p = VehicleCovariance::zeros();
    let diag = [
        1.0, 1.0, 1.0, // position [m²]
        0.01, 0.01, 0.01, // velocity [m²/s²]
        1e-6, 1e-6, 1e-6, // attitude [rad²]
    ];
    for (i, d) in diag.iter().enumerate() {
        p[(i, i)] = *d;
    }
    for i in 0..3 {
        p[(9 + i, 9 + i)] = noise.accel_bias_sigma.powi(2);
        p[(12 + i, 12 + i)] = noise.gyro_bias_sigma.powi(2);
    }
    p
}

/// Ground features of a grid in local NED (z = 0), ids 1000 + k.
fn grid(xs: impl Iterator<Item = f64> + Clone, ys: &[f64]) -> Vec<(FeatureId, Vector3<f64>)> {
    let mut v = Vec::new();
    for x in xs {
        for &y in ys {
            v.push((1000 + v.len() as FeatureId, Vector3::new(x, y, 0.0)));
        }
    }
    v
}

/// Observations of every feature within 150 m and 60° of the boresight, measured from `truth`,
/// plus `noise` (σ-scaled standard normal draws) if given.
fn observe(
    model: &ObservationModel,
    truth: &VehicleState,
    features: &[(FeatureId, Vector3<f64>)],
    mut noise: Option<&mut ChaCha8Rng>,
) -> Vec<Observation> {
    let pose = model.sensor_pose(&truth.position, &truth.attitude);
    let std = Normal::new(0.0, 1.0).unwrap();
    let mut out = Vec::new();
    for (id, m) in features {
        let rel = pose.relative_position(m).value;
        if rel.norm() > 150.0 || rel.x < rel.norm() * 60f64.to_radians().cos() {
            continue;
        }
        let mut z = model.predict(&pose, m).unwrap().z;
        if let Some(rng) = noise.as_deref_mut() {
            z[0] += SIGMA_RANGE * std.sample(rng);
            z[1] += SIGMA_BEARING * std.sample(rng);
            z[2] += SIGMA_BEARING * std.sample(rng);
        }
        out.push(Observation {
            descriptor: *id,
            z: Measurement::RangeBearing(Vector3::new(z[0], z[1], z[2])),
            appearance: None,
        });
    }
    out
}

/// Gravity of the flat test world [m/s²].
const FLAT_GRAVITY: f64 = 9.81;

fn config(frame: NavFrame, origin: Vector3<f64>) -> SlamConfig {
    config_with_gate(frame, origin, 0.95)
}

fn config_with_gate(frame: NavFrame, origin: Vector3<f64>, gate_probability: f64) -> SlamConfig {
    SlamConfig {
        frame,
        local_gravity_mps2: FLAT_GRAVITY,
        origin,
        association: AssociationConfig {
            mode: AssociationMode::Descriptor,
            gate_probability,
            ..AssociationConfig::default()
        },
        fresh_id_namespace: 0,
    }
}

fn trace3(m: &nalgebra::Matrix3<f64>) -> f64 {
    m.trace()
}

/// Straight level flight north at 20 m/s, 100 m above a feature grid, noise-free IMU and
/// measurements: the estimate must stay at the closed-form truth p(t) = p0 + v t, features must be
/// mapped at their true positions, and covariances must behave as EKF-SLAM predicts.
#[test]
fn local_straight_flight_noise_free_stays_at_truth() {
    let noise = ImuGrade::Tactical.noise();
    let p0 = Vector3::new(0.0, 0.0, -100.0);
    let v0 = Vector3::new(20.0, 0.0, 0.0);
    let truth_at = |t: f64| VehicleState {
        position: p0 + v0 * t,
        velocity: v0,
        attitude: Vector3::zeros(),
        accel_bias: Vector3::zeros(),
        gyro_bias: Vector3::zeros(),
    };
    let setup = VehicleSetup {
        state: truth_at(0.0),
        covariance: initial_covariance(&noise),
        imu_noise: noise,
        sensor: sensor(),
        mount: mount(),
    };
    let mut slam = SlamFilter::new(config(NavFrame::Local, Vector3::zeros()), &[setup]).unwrap();
    let mut ins_only =
        SlamFilter::new(config(NavFrame::Local, Vector3::zeros()), &[setup]).unwrap();
    let model = *slam.observation_model(0).unwrap();
    let features = grid(
        (0..=30).map(|i| -40.0 + 20.0 * i as f64),
        &[-40.0, 0.0, 40.0],
    );
    // Level, unaccelerated flight: the IMU measures f = −g (up) and no rotation.
    let dt = 0.01;
    let mut first_feature_traces = Vec::new();
    for k in 1..=2000 {
        let t = k as f64 * dt;
        let imu = ImuSample {
            time: t,
            dt,
            specific_force: Vector3::new(0.0, 0.0, -FLAT_GRAVITY),
            angular_rate: Vector3::zeros(),
        };
        slam.predict(0, &imu).unwrap();
        ins_only.predict(0, &imu).unwrap();
        if k % 20 == 0 {
            let obs = observe(&model, &truth_at(t), &features, None);
            let report = slam
                .process_frame(
                    0,
                    &ObservationFrame {
                        time: t,
                        observations: obs,
                    },
                )
                .unwrap();
            assert_eq!(report.rejected(), 0, "{report:?}");
            if let Some(c) = slam.feature_covariance(features[0].0) {
                first_feature_traces.push(trace3(&c));
            }
        }
    }
    let est = slam.vehicle_state(0).unwrap();
    let truth = truth_at(20.0);
    // Exact IMU and exact measurements: the only error is floating-point round-off of 2000
    // steps over ≈ 400 m (≈ 1e-13 relative per step).
    assert!(
        (est.position - truth.position).norm() < 1e-6,
        "{}",
        (est.position - truth.position).norm()
    );
    // Same round-off argument for velocity and attitude (O(1) values).
    assert!((est.velocity - truth.velocity).norm() < 1e-8);
    assert!(est.attitude.norm() < 1e-9);
    // The 150 m / 60° footprint sweeps ≈ 3 × 24 grid points over 400 m of flight.
    assert!(slam.num_features() > 40, "{}", slam.num_features());
    for (id, m) in slam.features() {
        let truth_m = features.iter().find(|(i, _)| *i == id).unwrap().1;
        // Features are initialized from exact measurements at the exact pose: round-off only.
        assert!((m - truth_m).norm() < 1e-6, "feature {id}");
    }
    // Re-observation only ever adds information: the first feature's covariance trace is
    // non-increasing (1e-12 relative slack for round-off) and shrinks overall.
    for w in first_feature_traces.windows(2) {
        assert!(w[1] <= w[0] * (1.0 + 1e-12), "{w:?}");
    }
    assert!(first_feature_traces.last().unwrap() < &(0.9 * first_feature_traces[0]));
    // Terrain observations bound the drift: SLAM's velocity and attitude σ are far below the
    // INS-only ones, and its position σ is no larger.
    let p_slam = slam.vehicle_covariance(0).unwrap();
    let p_ins = ins_only.vehicle_covariance(0).unwrap();
    println!(
        "first feature trace {:.4} -> {:.4} m²; σ_vx SLAM {:.2e} vs INS {:.2e} m/s; σ_φ {:.2e} vs {:.2e} rad",
        first_feature_traces[0],
        first_feature_traces.last().unwrap(),
        p_slam[(3, 3)].sqrt(),
        p_ins[(3, 3)].sqrt(),
        p_slam[(6, 6)].sqrt(),
        p_ins[(6, 6)].sqrt()
    );
    assert!(
        p_slam[(3, 3)] < 0.1 * p_ins[(3, 3)],
        "{} vs {}",
        p_slam[(3, 3)],
        p_ins[(3, 3)]
    );
    assert!(p_slam[(6, 6)] < p_ins[(6, 6)]);
    assert!(p_slam.fixed_view::<3, 3>(0, 0).trace() <= p_ins.fixed_view::<3, 3>(0, 0).trace());
    // The map is correlated through the vehicle: two features' relative position is known
    // better than either absolute position (the common-mode vehicle uncertainty cancels).
    let mm = slam.map_marginal();
    let var = |i: usize, j: usize| mm.covariance[(i, j)];
    let rel_var = var(0, 0) + var(3, 3) - 2.0 * var(0, 3);
    println!(
        "relative variance {rel_var:.4} vs absolute {:.4} m²",
        var(0, 0)
    );
    assert!(rel_var < 0.5 * var(0, 0), "{rel_var} vs {}", var(0, 0));
}

/// A vehicle at rest on the rotating Earth (global ECEF SLAM, Sydney), features around it, exact
/// IMU (f = −g_l, ω = ω_ie in body axes) and measurements: stays at the true position.
#[test]
fn global_hover_noise_free_stays_at_truth() {
    let noise = ImuGrade::Navigation.noise();
    let site = Geodetic::from_degrees(-33.87, 151.21, 120.0);
    let local = LocalFrame::new(site);
    let p = local.ecef_from_local(&Vector3::new(0.0, 0.0, -100.0));
    let g = geodesy::ecef_to_geodetic(&p);
    let att = Vector3::new(0.01, -0.02, 0.6);
    let c_bn = nav_from_body(&att);
    let c_ne = geodesy::ecef_from_ned(g.lat, g.lon);
    let f_b = -(c_bn.transpose() * c_ne.transpose() * geodesy::gravity_ecef(&p));
    let w_b = c_bn.transpose() * geodesy::earth_rate_ned(g.lat);
    let truth = VehicleState {
        position: p,
        velocity: Vector3::zeros(),
        attitude: att,
        accel_bias: Vector3::zeros(),
        gyro_bias: Vector3::zeros(),
    };
    let setup = VehicleSetup {
        state: truth,
        covariance: initial_covariance(&noise),
        imu_noise: noise,
        sensor: sensor(),
        mount: mount(),
    };
    let mut slam = SlamFilter::new(config(NavFrame::Global, local.origin_ecef), &[setup]).unwrap();
    let model = *slam.observation_model(0).unwrap();
    let features: Vec<(FeatureId, Vector3<f64>)> =
        grid((-2..=2).map(|i| 30.0 * i as f64), &[-30.0, 0.0, 30.0])
            .into_iter()
            .map(|(id, m)| (id, local.ecef_from_local(&m)))
            .collect();
    let mut traces = Vec::new();
    for k in 1..=1000 {
        let t = k as f64 * 0.01;
        slam.predict(
            0,
            &ImuSample {
                time: t,
                dt: 0.01,
                specific_force: f_b,
                angular_rate: w_b,
            },
        )
        .unwrap();
        if k % 50 == 0 {
            let obs = observe(&model, &truth, &features, None);
            let r = slam
                .process_frame(
                    0,
                    &ObservationFrame {
                        time: t,
                        observations: obs,
                    },
                )
                .unwrap();
            assert_eq!(r.rejected(), 0);
            traces.push(trace3(&slam.feature_covariance(features[7].0).unwrap()));
        }
    }
    let est = slam.vehicle_state(0).unwrap();
    // The discrete mechanization drifts < 1e-6 m in 10 s at rest (ins tests); the filter
    // corrects toward the exact measurements, so 1e-5 m bounds the error with margin.
    assert!(
        (est.position - p).norm() < 1e-5,
        "{}",
        (est.position - p).norm()
    );
    // Velocity/attitude at the mechanization's drift level (ins tests: < 1e-9 m/s, < 1e-12 rad)
    // plus the filter's corrections of the same order.
    assert!(est.velocity.norm() < 1e-6);
    assert!((est.attitude - att).norm() < 1e-8);
    for (id, m) in slam.features() {
        let truth_m = features.iter().find(|(i, _)| *i == id).unwrap().1;
        assert!(
            (m - truth_m).norm() < 1e-5,
            "feature {id}: {}",
            (m - truth_m).norm()
        );
    }
    assert!(traces.last().unwrap() < &traces[0]);
}

/// Two vehicles in one centralized filter (M = 2) with IMU and measurement noise drawn from the
/// filter's own models: a small Monte Carlo of the final vehicle errors must have an average
/// NEES inside the two-sided 95 % ANEES band (the filter is neither over- nor under-confident on
/// a short run, where linearisation errors are still small), and the map marginal's NEES summed
/// over runs must lie in its two-sided 95 % χ² band. The seeds are fixed, so the test is
/// deterministic; a consistent filter lands outside a band for 5 % of seed choices.
#[test]
fn two_vehicle_centralized_monte_carlo_is_consistent() {
    const RUNS: usize = 40;
    let noise = ImuGrade::Tactical.noise();
    let features = grid(
        (0..=12).map(|i| -40.0 + 20.0 * i as f64),
        &[-60.0, -20.0, 20.0, 60.0],
    );
    let dt = 0.01;
    let mut nees_pose = Vec::new();
    let (mut observed, mut rejected) = (0usize, 0usize);
    let (mut map_nees, mut map_dof) = (0.0, 0usize);
    for run in 0..RUNS {
        let mut rng = ChaCha8Rng::seed_from_u64(1000 + run as u64);
        let std = Normal::new(0.0, 1.0).unwrap();
        let starts = [
            Vector3::new(0.0, -20.0, -100.0),
            Vector3::new(0.0, 20.0, -110.0),
        ];
        let v0 = Vector3::new(15.0, 0.0, 0.0);
        // True biases drawn from the turn-on distribution; the true motion is unaccelerated.
        let mut truth: Vec<VehicleState> = starts
            .iter()
            .map(|p| VehicleState {
                position: *p,
                velocity: v0,
                attitude: Vector3::zeros(),
                accel_bias: Vector3::from_fn(|_, _| noise.accel_bias_sigma * std.sample(&mut rng)),
                gyro_bias: Vector3::from_fn(|_, _| noise.gyro_bias_sigma * std.sample(&mut rng)),
            })
            .collect();
        // Initial estimates x̂ = x + e with e ~ N(0, P0): the filter's prior is exactly right.
        let p0 = initial_covariance(&noise);
        let chol = p0.cholesky().unwrap();
        let setups: Vec<VehicleSetup> = truth
            .iter()
            .map(|t| {
                let e =
                    chol.l() * nalgebra::SVector::<f64, 15>::from_fn(|_, _| std.sample(&mut rng));
                let state = VehicleState::from_vector(&(t.to_vector() + e));
                VehicleSetup {
                    state,
                    covariance: p0,
                    imu_noise: noise,
                    sensor: sensor(),
                    mount: mount(),
                }
            })
            .collect();
        // A 95 % gate on correct pairings discards the 5 % largest innovations, which truncates
        // the noise the filter sees and biases the NEES low (measured: ANEES 4.8 for 6 dof).
        // The consistency check therefore uses a 99.99 % gate; association is by descriptor.
        let mut slam = SlamFilter::new(
            config_with_gate(NavFrame::Local, Vector3::zeros(), 0.9999),
            &setups,
        )
        .unwrap();
        let model = *slam.observation_model(0).unwrap();
        for k in 1..=1500 {
            let t = k as f64 * dt;
            for (v, tr) in truth.iter_mut().enumerate() {
                // Bias random walks, then the IMU reading f̂ = f + δf + w (eqs. 21.13, 21.14).
                tr.accel_bias += Vector3::from_fn(|_, _| {
                    noise.accel_bias_rw_density * dt.sqrt() * std.sample(&mut rng)
                });
                tr.gyro_bias += Vector3::from_fn(|_, _| {
                    noise.gyro_bias_rw_density * dt.sqrt() * std.sample(&mut rng)
                });
                let wa = Vector3::from_fn(|_, _| {
                    noise.accel_noise_density / dt.sqrt() * std.sample(&mut rng)
                });
                let wg = Vector3::from_fn(|_, _| {
                    noise.gyro_noise_density / dt.sqrt() * std.sample(&mut rng)
                });
                let f_true = Vector3::new(0.0, 0.0, -FLAT_GRAVITY);
                let imu = ImuSample {
                    time: t,
                    dt,
                    specific_force: f_true + tr.accel_bias + wa,
                    angular_rate: tr.gyro_bias + wg,
                };
                tr.position += tr.velocity * dt;
                slam.predict(v, &imu).unwrap();
            }
            if k % 20 == 0 {
                for (v, tr) in truth.iter().enumerate() {
                    let obs = observe(&model, tr, &features, Some(&mut rng));
                    let r = slam
                        .process_frame(
                            v,
                            &ObservationFrame {
                                time: t,
                                observations: obs,
                            },
                        )
                        .unwrap();
                    observed += r.outcomes.len();
                    rejected += r.rejected();
                }
            }
        }
        // One independent sample per run: the joint NEES of both vehicles' pose blocks (p, Ψ)
        // from the joint covariance (the two vehicles' errors are correlated through the map).
        let p_joint = slam.joint_covariance();
        let idx: Vec<usize> = (0..truth.len())
            .flat_map(|v| {
                let off = slam.layout().vehicle_offset(v).unwrap();
                [0, 1, 2, 6, 7, 8].map(|i| off + i)
            })
            .collect();
        let mut e = DVector::zeros(idx.len());
        for (v, tr) in truth.iter().enumerate() {
            let ev = vehicle_error(&slam.vehicle_state(v).unwrap(), tr);
            for (k, i) in [0, 1, 2, 6, 7, 8].into_iter().enumerate() {
                e[6 * v + k] = ev[i];
            }
        }
        let p = DMatrix::from_fn(idx.len(), idx.len(), |i, j| p_joint[(idx[i], idx[j])]);
        nees_pose.push(nees(&e, &p).unwrap());
        // The whole map: NEES of the map marginal against the true feature positions.
        let mm = slam.map_marginal();
        let k = mm.mean.nrows();
        let em = DVector::from_fn(k, |i, _| {
            let truth = features
                .iter()
                .find(|(id, _)| *id == mm.ids[i / 3])
                .unwrap()
                .1;
            mm.mean[i] - truth[i % 3]
        });
        let pm = DMatrix::from_fn(k, k, |i, j| mm.covariance[(i, j)]);
        map_nees += nees(&em, &pm).unwrap();
        map_dof += k;
    }
    let runs = nees_pose.len();
    let anees = nees_pose.iter().sum::<f64>() / runs as f64;
    let (lo, hi) = anees_band(runs, 12, 0.95).unwrap();
    println!(
        "ANEES(p, Ψ of both vehicles, 12 dof) over {runs} runs: {anees:.3}, 95 % band [{lo:.3}, {hi:.3}]; gate rejections {rejected}/{observed}"
    );
    // Correct pairings with a 99.99 % gate: ≈ 1e-4 are rejected by design; 1e-3 allows the
    // sampling spread over ≈ 1.4e5 observations.
    assert!(
        (rejected as f64) < 1e-3 * observed as f64,
        "{rejected}/{observed}"
    );
    assert!(
        anees > lo && anees < hi,
        "ANEES {anees} outside [{lo}, {hi}]"
    );
    // Σ NEES over runs of the map marginal is χ² with Σ dof degrees of freedom if consistent.
    let (mlo, mhi) = (
        chi2_quantile(map_dof as f64, 0.025).unwrap(),
        chi2_quantile(map_dof as f64, 0.975).unwrap(),
    );
    println!(
        "map: Σ NEES {map_nees:.1} over Σ dof {map_dof} (per dof {:.3}), 95 % band [{mlo:.1}, {mhi:.1}]",
        map_nees / map_dof as f64
    );
    assert!(
        map_nees > mlo && map_nees < mhi,
        "map NEES {map_nees} outside [{mlo}, {mhi}]"
    );
}

/// Global (ECEF) SLAM Monte Carlo: a vehicle hovering over Sydney on the rotating Earth, IMU
/// noise and biases from the filter's model, noisy range-bearing observations of ground features.
/// The 15-dof vehicle NEES averaged over runs must lie in the 95 % ANEES band: this exercises the
/// global ∇F/∇G/∇H inside the filter (a Jacobian or frame error shows up as over-confidence).
#[test]
fn global_hover_monte_carlo_is_consistent() {
    const RUNS: usize = 30;
    let noise = ImuGrade::Tactical.noise();
    let site = Geodetic::from_degrees(-33.87, 151.21, 120.0);
    let local = LocalFrame::new(site);
    let p = local.ecef_from_local(&Vector3::new(0.0, 0.0, -100.0));
    let g = geodesy::ecef_to_geodetic(&p);
    let att = Vector3::new(0.01, -0.02, 0.6);
    let c_bn = nav_from_body(&att);
    let c_ne = geodesy::ecef_from_ned(g.lat, g.lon);
    let f_true = -(c_bn.transpose() * c_ne.transpose() * geodesy::gravity_ecef(&p));
    let w_true = c_bn.transpose() * geodesy::earth_rate_ned(g.lat);
    let features: Vec<(FeatureId, Vector3<f64>)> =
        grid((-2..=2).map(|i| 30.0 * i as f64), &[-30.0, 0.0, 30.0])
            .into_iter()
            .map(|(id, m)| (id, local.ecef_from_local(&m)))
            .collect();
    let dt = 0.01;
    let mut total = 0.0;
    for run in 0..RUNS {
        let mut rng = ChaCha8Rng::seed_from_u64(7000 + run as u64);
        let std = Normal::new(0.0, 1.0).unwrap();
        let mut truth = VehicleState {
            position: p,
            velocity: Vector3::zeros(),
            attitude: att,
            accel_bias: Vector3::from_fn(|_, _| noise.accel_bias_sigma * std.sample(&mut rng)),
            gyro_bias: Vector3::from_fn(|_, _| noise.gyro_bias_sigma * std.sample(&mut rng)),
        };
        let p0 = initial_covariance(&noise);
        let e = p0.cholesky().unwrap().l()
            * nalgebra::SVector::<f64, 15>::from_fn(|_, _| std.sample(&mut rng));
        let setup = VehicleSetup {
            state: VehicleState::from_vector(&(truth.to_vector() + e)),
            covariance: p0,
            imu_noise: noise,
            sensor: sensor(),
            mount: mount(),
        };
        // 99.99 % gate: see the local Monte Carlo for why a 95 % gate biases the NEES low.
        let mut slam = SlamFilter::new(
            config_with_gate(NavFrame::Global, local.origin_ecef, 0.9999),
            &[setup],
        )
        .unwrap();
        let model = *slam.observation_model(0).unwrap();
        for k in 1..=1000 {
            let t = k as f64 * dt;
            truth.accel_bias += Vector3::from_fn(|_, _| {
                noise.accel_bias_rw_density * dt.sqrt() * std.sample(&mut rng)
            });
            truth.gyro_bias += Vector3::from_fn(|_, _| {
                noise.gyro_bias_rw_density * dt.sqrt() * std.sample(&mut rng)
            });
            let wa = Vector3::from_fn(|_, _| {
                noise.accel_noise_density / dt.sqrt() * std.sample(&mut rng)
            });
            let wg = Vector3::from_fn(|_, _| {
                noise.gyro_noise_density / dt.sqrt() * std.sample(&mut rng)
            });
            let imu = ImuSample {
                time: t,
                dt,
                specific_force: f_true + truth.accel_bias + wa,
                angular_rate: w_true + truth.gyro_bias + wg,
            };
            slam.predict(0, &imu).unwrap();
            if k % 20 == 0 {
                let obs = observe(&model, &truth, &features, Some(&mut rng));
                slam.process_frame(
                    0,
                    &ObservationFrame {
                        time: t,
                        observations: obs,
                    },
                )
                .unwrap();
            }
        }
        let e = vehicle_error(&slam.vehicle_state(0).unwrap(), &truth);
        let pv = slam.vehicle_covariance(0).unwrap();
        let ed = DVector::from_fn(15, |i, _| e[i]);
        let pd = DMatrix::from_fn(15, 15, |i, j| pv[(i, j)]);
        total += nees(&ed, &pd).unwrap();
    }
    let anees = total / RUNS as f64;
    let (lo, hi) = anees_band(RUNS, 15, 0.95).unwrap();
    println!(
        "global hover ANEES (15 dof) over {RUNS} runs: {anees:.3}, 95 % band [{lo:.3}, {hi:.3}]"
    );
    assert!(
        anees > lo && anees < hi,
        "ANEES {anees} outside [{lo}, {hi}]"
    );
}
