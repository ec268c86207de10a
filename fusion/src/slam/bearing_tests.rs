//! Unit tests of the bearing-only pipeline against independent dense computations (nalgebra
//! `DMatrix`, textbook augmentation and Kalman update on the full joint covariance).

use super::tests::after_frame;
use super::triangulation::{PoseFrame, PosedObservation, initialize_from_pair, pose_line_of_sight};
use super::*;
use crate::geodesy::{Geodetic, geodetic_to_ecef};
use crate::imu::ImuGrade;
use crate::sensor::{CameraIntrinsics, Measurement, Observation};
use crate::state::{ATT, POS, POSE_ATT, POSE_DIM, POSE_POS};
use nalgebra::{DMatrix, DVector};

fn camera() -> CameraIntrinsics {
    CameraIntrinsics {
        fu: 600.0,
        fv: 600.0,
        u0: 320.0,
        v0: 240.0,
        width: 640.0,
        height: 480.0,
    }
}

fn bearing_sensor() -> SensorModel {
    SensorModel::Bearing {
        sigma_bearing: 0.003,
    }
}

fn pixel_sensor() -> SensorModel {
    SensorModel::Pixel {
        camera: camera(),
        sigma_pixel: 1.0,
    }
}

fn site() -> Vector3<f64> {
    geodetic_to_ecef(&Geodetic::from_degrees(-34.0, 150.6, 80.0))
}

/// A filter with one vehicle 150 m above the origin flying north at 20 m/s (local), or the same
/// over the ECEF site (global).
fn filter(frame: NavFrame, sensor: SensorModel, mode: AssociationMode) -> SlamFilter {
    let pf = PoseFrame::new(frame, &site()).unwrap();
    let r = pf.filter_from_pose();
    let mut cov = VehicleCovariance::zeros();
    for i in 0..3 {
        cov[(i, i)] = 4.0;
        cov[(3 + i, 3 + i)] = 0.01;
        cov[(6 + i, 6 + i)] = 1e-5;
        cov[(9 + i, 9 + i)] = 1e-4;
        cov[(12 + i, 12 + i)] = 1e-8;
    }
    // Correlate position and attitude a little so the cross terms are exercised.
    cov[(0, 8)] = 1e-3;
    cov[(8, 0)] = 1e-3;
    // Rotate the position/velocity blocks into ECEF in global SLAM.
    let mut rot = VehicleCovariance::identity();
    rot.fixed_view_mut::<3, 3>(0, 0).copy_from(&r);
    rot.fixed_view_mut::<3, 3>(3, 3).copy_from(&r);
    let cov = rot * cov * rot.transpose();
    let setup = VehicleSetup {
        state: VehicleState {
            position: pf.to_filter(&Vector3::new(0.0, 0.0, -150.0)),
            velocity: r * Vector3::new(20.0, 0.0, 0.0),
            attitude: Vector3::new(0.01, -0.02, 0.05),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        },
        covariance: cov,
        imu_noise: ImuGrade::Tactical.noise(),
        sensor,
        mount: SensorMount::downward(Vector3::new(0.3, 0.0, 0.2)),
    };
    SlamFilter::new(
        SlamConfig {
            frame,
            local_gravity_mps2: 9.81,
            origin: match frame {
                NavFrame::Global => site(),
                NavFrame::Local => Vector3::zeros(),
            },
            association: AssociationConfig {
                mode,
                gate_probability: 0.95,
                ..AssociationConfig::default()
            },
            fresh_id_namespace: 1,
        },
        &[setup],
    )
    .unwrap()
}

/// One second of IMU samples that keep a level vehicle roughly unaccelerated.
fn fly(f: &mut SlamFilter, t0: f64) {
    let dt = 0.01;
    for k in 1..=100 {
        let imu = ImuSample {
            time: t0 + k as f64 * dt,
            dt,
            specific_force: Vector3::new(0.0, 0.0, -9.8),
            angular_rate: Vector3::zeros(),
        };
        f.predict(0, &imu).unwrap();
    }
}

/// The measurement of `m` (filter frame) from the filter's current estimated pose, perturbed by
/// `delta` (so innovations are non-zero).
fn measure(f: &SlamFilter, m: &Vector3<f64>, delta: f64) -> Measurement {
    let model = f.observation_model(0).unwrap();
    let (p, a) = f.pose(0).unwrap();
    let z = model.predict(&model.sensor_pose(&p, &a), m).unwrap().z;
    match model.sensor {
        SensorModel::Pixel { .. } => Measurement::Pixel(nalgebra::Vector2::new(
            z[0] + delta * 300.0,
            z[1] - delta * 200.0,
        )),
        _ => Measurement::Bearing(nalgebra::Vector2::new(z[0] + delta, z[1] - 0.5 * delta)),
    }
}

fn dense_p(f: &SlamFilter) -> DMatrix<f64> {
    let p = f.joint_covariance();
    DMatrix::from_fn(p.nrows(), p.ncols(), |i, j| p[(i, j)])
}

fn dense_x(f: &SlamFilter) -> DVector<f64> {
    let x = f.state_vector();
    DVector::from_fn(x.nrows(), |i, _| x[i])
}

/// Dense textbook Joseph update.
fn dense_update(
    x: &DVector<f64>,
    p: &DMatrix<f64>,
    h: &DMatrix<f64>,
    r: &DMatrix<f64>,
    nu: &DVector<f64>,
) -> (DVector<f64>, DMatrix<f64>) {
    let s = h * p * h.transpose() + r;
    let k = p * h.transpose() * s.try_inverse().unwrap();
    let i_kh = DMatrix::identity(p.nrows(), p.nrows()) - &k * h;
    (
        x + &k * nu,
        &i_kh * p * i_kh.transpose() + &k * r * k.transpose(),
    )
}

/// Both navigation frames with both camera models.
fn frames_and_sensors() -> [(NavFrame, SensorModel); 4] {
    [
        (NavFrame::Local, bearing_sensor()),
        (NavFrame::Global, pixel_sensor()),
        (NavFrame::Local, pixel_sensor()),
        (NavFrame::Global, bearing_sensor()),
    ]
}

/// Pose augmentation (eq. 21.68), feature initialization (21.76), recovery (21.78) and pose
/// removal equal the same steps done densely on the joint (x, P), in both frames.
#[test]
fn delayed_initialization_equals_the_dense_computation() {
    for (frame, sensor) in frames_and_sensors() {
        let label = format!("{frame} {sensor:?}");
        let mut f = filter(frame, sensor, AssociationMode::Descriptor);
        f.set_bearing_config(BearingConfig {
            min_parallax: 12f64.to_radians(),
            ..BearingConfig::default()
        })
        .unwrap();
        let pf = PoseFrame::new(frame, &site()).unwrap();
        let r = pf.filter_from_pose();
        let model = *f.observation_model(0).unwrap();
        // The feature 150 m below and 40 m ahead of the start.
        let m = pf.to_filter(&Vector3::new(40.0, 10.0, 0.0));
        let mut stored: Vec<DVector<f64>> = Vec::new();
        let mut t = 0.0;
        let mut initialized = None;
        for frame_no in 0..6 {
            let before_x = dense_x(&f);
            let before_p = dense_p(&f);
            let n = before_x.len();
            let z_meas = measure(&f, &m, 1e-3 * (frame_no as f64 - 1.5));
            let z = model.measurement_vector(&z_meas).unwrap();
            let report = f
                .process_frame(
                    0,
                    &ObservationFrame {
                        time: t,
                        observations: vec![Observation {
                            descriptor: 7,
                            z: z_meas,
                            appearance: None,
                        }],
                    },
                )
                .unwrap();
            // Dense pose augmentation: x_p = (C_e^{n0}(p − o), Ψ), rows J = [R^T on p, I on Ψ].
            let mut j = DMatrix::zeros(n + POSE_DIM, n);
            for i in 0..n {
                j[(i, i)] = 1.0;
            }
            for i in 0..3 {
                for c in 0..3 {
                    j[(n + i, POS + c)] = r[(c, i)];
                }
                j[(n + 3 + i, ATT + i)] = 1.0;
            }
            // The pose stored is the vehicle's prior (no initialized feature updated it first).
            let p0 = Vector3::new(before_x[POS], before_x[POS + 1], before_x[POS + 2]);
            let a0 = Vector3::new(before_x[ATT], before_x[ATT + 1], before_x[ATT + 2]);
            let mut x_aug = DVector::zeros(n + POSE_DIM);
            x_aug.rows_mut(0, n).copy_from(&before_x);
            let pn = pf.from_filter(&p0);
            for i in 0..3 {
                x_aug[n + i] = pn[i];
                x_aug[n + 3 + i] = a0[i];
            }
            let p_aug = &j * &before_p * j.transpose();
            if report.initialized() == 0 {
                assert!(
                    matches!(report.outcomes[0], ObservationOutcome::Stored { .. }),
                    "{label}: {report:?}"
                );
                // Round-off on ECEF-sized states (≈ 6e6 m → 1e-9).
                assert!((dense_x(&f) - &x_aug).abs().max() < 1e-8, "{label}: x");
                assert!((dense_p(&f) - &p_aug).abs().max() < 1e-10, "{label}: P");
                stored.push(z);
                t += 1.0;
                fly(&mut f, t - 1.0);
                continue;
            }
            // Initialization frame: the current observation joins the stored ones.
            stored.push(z);
            let k = stored.len();
            // Offsets of the earlier stored poses in the pre-frame state: poses are the last
            // blocks, in storage order.
            let first_pose = n - POSE_DIM * (k - 1);
            let offs: Vec<usize> = (0..k).map(|i| first_pose + POSE_DIM * i).collect();
            let pose_state = |i: usize| -> (Vector3<f64>, Vector3<f64>) {
                let o = offs[i];
                (
                    Vector3::new(x_aug[o], x_aug[o + 1], x_aug[o + 2]),
                    Vector3::new(x_aug[o + 3], x_aug[o + 4], x_aug[o + 5]),
                )
            };
            // Pair with the largest angle.
            let dirs: Vec<Vector3<f64>> = (0..k)
                .map(|i| {
                    let (p, a) = pose_state(i);
                    pose_line_of_sight(
                        &pf,
                        &PosedObservation {
                            model: &model,
                            position: p,
                            attitude: a,
                            z: &stored[i],
                        },
                    )
                    .unwrap()
                    .direction
                })
                .collect();
            let mut best = (0, 1, -1.0);
            for a in 0..k {
                for b in a + 1..k {
                    let ang = dirs[a].cross(&dirs[b]).norm().atan2(dirs[a].dot(&dirs[b]));
                    if ang > best.2 {
                        best = (a, b, ang);
                    }
                }
            }
            let (ia, ib) = (best.0, best.1);
            let (pa, aa) = pose_state(ia);
            let (pb, ab) = pose_state(ib);
            let g = initialize_from_pair(
                &pf,
                &PosedObservation {
                    model: &model,
                    position: pa,
                    attitude: aa,
                    z: &stored[ia],
                },
                &PosedObservation {
                    model: &model,
                    position: pb,
                    attitude: ab,
                    z: &stored[ib],
                },
                12f64.to_radians(),
                5.0,
            )
            .unwrap();
            // Dense eq. 21.76.
            let na = n + POSE_DIM;
            let mut jf = DMatrix::zeros(na + 3, na + 4);
            for i in 0..na {
                jf[(i, i)] = 1.0;
            }
            for i in 0..3 {
                for c in 0..POSE_DIM {
                    jf[(na + i, offs[ia] + c)] += g.d_pose_a[(i, c)];
                    jf[(na + i, offs[ib] + c)] += g.d_pose_b[(i, c)];
                }
                for c in 0..2 {
                    jf[(na + i, na + c)] = g.d_z_a[(i, c)];
                    jf[(na + i, na + 2 + c)] = g.d_z_b[(i, c)];
                }
            }
            let rz = model.noise_covariance();
            let mut big = DMatrix::zeros(na + 4, na + 4);
            big.view_mut((0, 0), (na, na)).copy_from(&p_aug);
            big.view_mut((na, na), (2, 2)).copy_from(&rz);
            big.view_mut((na + 2, na + 2), (2, 2)).copy_from(&rz);
            let mut p_f = &jf * big * jf.transpose();
            let mut x_f = DVector::zeros(na + 3);
            x_f.rows_mut(0, na).copy_from(&x_aug);
            x_f.rows_mut(na, 3).copy_from(&g.feature);
            // Dense eq. 21.78 with the remaining observations (gates pass: noise-free data).
            let rest: Vec<usize> = (0..k).filter(|i| *i != ia && *i != ib).collect();
            if !rest.is_empty() {
                let d = 2;
                let mut h = DMatrix::zeros(d * rest.len(), na + 3);
                let mut nu = DVector::zeros(d * rest.len());
                let mut rr = DMatrix::zeros(d * rest.len(), d * rest.len());
                for (row, &i) in rest.iter().enumerate() {
                    let (p, a) = pose_state(i);
                    let pred = model
                        .predict(&model.sensor_pose(&pf.to_filter(&p), &a), &g.feature)
                        .unwrap();
                    let dp = DMatrix::from_fn(d, 3, |a, b| pred.d_position[(a, b)])
                        * DMatrix::from_fn(3, 3, |a, b| r[(a, b)]);
                    for a in 0..d {
                        for c in 0..3 {
                            h[(row * d + a, offs[i] + POSE_POS + c)] = dp[(a, c)];
                            h[(row * d + a, offs[i] + 3 + c)] = pred.d_attitude[(a, c)];
                            h[(row * d + a, na + c)] = pred.d_feature[(a, c)];
                        }
                    }
                    let v = model.innovation(&stored[i], &pred.z);
                    nu.rows_mut(row * d, d).copy_from(&v);
                    rr.view_mut((row * d, row * d), (d, d)).copy_from(&rz);
                }
                let (xu, pu) = dense_update(&x_f, &p_f, &h, &rr, &nu);
                x_f = xu;
                p_f = pu;
            }
            // Remove every pose (the track is closed, nothing else refers to them) and move
            // the feature in front: the final state is [vehicle, feature].
            let keep: Vec<usize> = (0..VEHICLE_DIM).chain(na..na + 3).collect();
            let x_ref = DVector::from_fn(keep.len(), |i, _| x_f[keep[i]]);
            let p_ref = DMatrix::from_fn(keep.len(), keep.len(), |i, j| p_f[(keep[i], keep[j])]);
            assert_eq!(f.num_stored_poses(), 0, "{label}");
            assert_eq!(f.num_tracks(), 0, "{label}");
            assert_eq!(f.dim(), VEHICLE_DIM + 3, "{label}");
            let (xe, pe) = (dense_x(&f), dense_p(&f));
            // Round-off: ECEF states ≈ 6e6 m (≈ 1e-9 per operation, a few hundred operations);
            // the covariance entries are O(1..100) and well conditioned.
            assert!(
                (&xe - &x_ref).abs().max() < 1e-6,
                "{label}: x {}",
                (&xe - &x_ref).abs().max()
            );
            assert!(
                (&pe - &p_ref).abs().max() < 1e-8 * p_ref.abs().max(),
                "{label}: P {}",
                (&pe - &p_ref).abs().max()
            );
            initialized = Some(report);
            break;
        }
        let report = initialized.unwrap_or_else(|| panic!("{label}: never initialized"));
        assert_eq!(report.initialized_tracks.len(), 1, "{label}");
        assert_eq!(
            report.initialized_tracks[0].1, 7,
            "{label}: descriptor id kept"
        );
        // Three frames: 20 m apart at ≈ 150 m → 7.6°/frame, initialized at the third (15°)
        // with one observation recovered.
        let stats = f.bearing_stats();
        assert_eq!(stats.features_initialized, 1, "{label}");
        assert_eq!(stats.observations_recovered, 1, "{label}: {stats:?}");
        assert_eq!(stats.poses_added, stats.poses_removed, "{label}");
    }
}

fn snapshot(
    f: &SlamFilter,
) -> (
    DVector<f64>,
    DMatrix<f64>,
    Vec<TrackInfo>,
    usize,
    BearingStats,
) {
    (
        dense_x(f),
        dense_p(f),
        f.tracks(),
        f.num_stored_poses(),
        f.bearing_stats(),
    )
}

/// A NaN pixel or a pixel outside the image rejects only itself: the frame's good observation is
/// processed exactly as in a frame without it (state, covariance, tracks, stored poses, counters
/// bit for bit), and a frame of bad pixels only is processed as an empty frame.
#[test]
fn invalid_camera_observations_are_rejected_alone() {
    let mut f = filter(NavFrame::Local, pixel_sensor(), AssociationMode::Descriptor);
    let m = Vector3::new(40.0, 10.0, 0.0);
    let good = measure(&f, &m, 0.0);
    f.process_frame(
        0,
        &ObservationFrame {
            time: 0.0,
            observations: vec![Observation {
                descriptor: 3,
                z: good,
                appearance: None,
            }],
        },
    )
    .unwrap();
    fly(&mut f, 0.0);
    assert_eq!(f.num_tracks(), 1);
    assert_eq!(f.num_stored_poses(), 1);
    let good = Observation {
        descriptor: 3,
        z: measure(&f, &m, 0.0),
        appearance: None,
    };
    let (alone, want) = after_frame(&f, 1.0, vec![good]);
    assert!(matches!(
        want.outcomes[0],
        ObservationOutcome::Stored { .. }
    ));
    for (bad, fault) in [
        (
            Measurement::Pixel(nalgebra::Vector2::new(f64::NAN, 100.0)),
            MeasurementFault::NonFinite,
        ),
        (
            Measurement::Pixel(nalgebra::Vector2::new(100.0, 480.5)),
            MeasurementFault::OutsideImage,
        ),
        (
            Measurement::Pixel(nalgebra::Vector2::new(-3.0, 10.0)),
            MeasurementFault::OutsideImage,
        ),
        (
            Measurement::Bearing(nalgebra::Vector2::new(0.1, 0.2)),
            MeasurementFault::KindMismatch,
        ),
    ] {
        let bad = Observation {
            descriptor: 4,
            z: bad,
            appearance: None,
        };
        let (g, r) = after_frame(&f, 1.0, vec![good, bad]);
        assert_eq!(
            r.outcomes[1],
            ObservationOutcome::Rejected(RejectReason::InvalidMeasurement(fault))
        );
        assert_eq!(r.outcomes[0], want.outcomes[0]);
        assert_eq!(snapshot(&g), snapshot(&alone));
        let (empty, _) = after_frame(&f, 1.0, vec![]);
        let (g, r) = after_frame(&f, 1.0, vec![bad]);
        assert_eq!(r.rejected(), 1);
        assert_eq!(snapshot(&g), snapshot(&empty));
    }
}

/// Features seen once and never again: the stored poses stay at the cap (oldest tracks dropped,
/// counted), and tracks past the age limit are dropped, so the state stays bounded.
#[test]
fn stored_poses_are_capped_and_old_tracks_dropped() {
    let mut f = filter(
        NavFrame::Local,
        bearing_sensor(),
        AssociationMode::Descriptor,
    );
    f.set_bearing_config(BearingConfig {
        max_stored_poses: 4,
        max_track_age: 5.0,
        ..BearingConfig::default()
    })
    .unwrap();
    let mut max_poses = 0;
    for k in 0..12u64 {
        // Two new features per frame, each seen only in this frame.
        let obs = (0..2)
            .map(|j| {
                let m = Vector3::new(20.0 * k as f64 + 30.0, 15.0 * j as f64 - 10.0, 0.0);
                Observation {
                    descriptor: 100 + 2 * k + j,
                    z: measure(&f, &m, 0.0),
                    appearance: None,
                }
            })
            .collect();
        let r = f
            .process_frame(
                0,
                &ObservationFrame {
                    time: k as f64,
                    observations: obs,
                },
            )
            .unwrap();
        assert_eq!(r.stored(), 2, "{r:?}");
        max_poses = max_poses.max(f.num_stored_poses());
        assert_eq!(
            f.dim(),
            VEHICLE_DIM + POSE_DIM * f.num_stored_poses(),
            "no features"
        );
        fly(&mut f, k as f64);
    }
    let stats = f.bearing_stats();
    assert_eq!(max_poses, 4);
    assert_eq!(stats.max_stored_poses, 4);
    assert_eq!(f.num_stored_poses(), 4);
    // 12 frames, 4 kept: 8 frames' tracks (2 each) dropped for capacity.
    assert_eq!(stats.tracks_dropped_capacity, 16, "{stats:?}");
    assert_eq!(stats.poses_added - stats.poses_removed, 4);
    // Age: a frame at t = 20 s with no observations drops every track (> 5 s old).
    f.process_frame(
        0,
        &ObservationFrame {
            time: 20.0,
            observations: vec![],
        },
    )
    .unwrap();
    assert_eq!(f.num_tracks(), 0);
    assert_eq!(f.num_stored_poses(), 0);
    assert_eq!(f.dim(), VEHICLE_DIM);
    assert_eq!(f.bearing_stats().tracks_dropped_age, 8);
}

/// A centralized filter mixing a range-bearing and a bearing-only vehicle keeps the order
/// vehicles, features, poses: a feature initialized while poses exist moves in front of them,
/// and every covariance block between pre-existing slots is unchanged by the move.
#[test]
fn mixed_team_keeps_features_before_poses() {
    let rb = filter(
        NavFrame::Local,
        SensorModel::RangeBearing {
            sigma_range: 0.5,
            sigma_bearing: 0.003,
        },
        AssociationMode::Descriptor,
    );
    let bo = filter(
        NavFrame::Local,
        bearing_sensor(),
        AssociationMode::Descriptor,
    );
    let mut setups = Vec::new();
    for f in [&rb, &bo] {
        setups.push(VehicleSetup {
            state: f.vehicle_state(0).unwrap(),
            covariance: f.vehicle_covariance(0).unwrap(),
            imu_noise: ImuGrade::Tactical.noise(),
            sensor: f.observation_model(0).unwrap().sensor,
            mount: f.observation_model(0).unwrap().mount,
        });
    }
    let mut f = SlamFilter::new(*rb.config(), &setups).unwrap();
    let m_b = Vector3::new(30.0, 5.0, 0.0);
    let (p, a) = f.pose(1).unwrap();
    let model_b = *f.observation_model(1).unwrap();
    let zb = model_b
        .predict(&model_b.sensor_pose(&p, &a), &m_b)
        .unwrap()
        .z;
    f.process_frame(
        1,
        &ObservationFrame {
            time: 0.0,
            observations: vec![Observation {
                descriptor: 50,
                z: Measurement::Bearing(nalgebra::Vector2::new(zb[0], zb[1])),
                appearance: None,
            }],
        },
    )
    .unwrap();
    assert_eq!(f.num_stored_poses(), 1);
    let before_p = dense_p(&f);
    let before_slots: Vec<Slot> = f.layout().slots().to_vec();
    let model_a = *f.observation_model(0).unwrap();
    let (p, a) = f.pose(0).unwrap();
    let za = model_a
        .predict(&model_a.sensor_pose(&p, &a), &Vector3::new(-20.0, 0.0, 0.0))
        .unwrap()
        .z;
    let r = f
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: vec![Observation {
                    descriptor: 9,
                    z: Measurement::RangeBearing(Vector3::new(za[0], za[1], za[2])),
                    appearance: None,
                }],
            },
        )
        .unwrap();
    assert_eq!(r.initialized(), 1);
    let slots = f.layout().slots();
    let first_pose = slots
        .iter()
        .position(|s| matches!(s.kind, SlotKind::Pose(_)))
        .unwrap();
    assert!(
        slots[first_pose..]
            .iter()
            .all(|s| matches!(s.kind, SlotKind::Pose(_)))
    );
    assert!(f.layout().feature_offset(9).unwrap() < f.layout().pose_offset(0).unwrap());
    let after_p = dense_p(&f);
    for a in &before_slots {
        for b in &before_slots {
            let (ra, rb2) = (a.offset, b.offset);
            let (na, nb) = (
                f.layout().offset(a.kind).unwrap(),
                f.layout().offset(b.kind).unwrap(),
            );
            for i in 0..a.kind.dim() {
                for j in 0..b.kind.dim() {
                    // A permutation moves entries exactly.
                    assert_eq!(before_p[(ra + i, rb2 + j)], after_p[(na + i, nb + j)]);
                }
            }
        }
    }
}

/// Fusing received map information while stored poses are in the state equals the dense
/// information form (stored poses move with the map through their correlations), new features
/// land in front of the poses, and a descriptor-mode track whose feature arrived by fusion has its
/// stored observation recovered onto that feature at the next frame.
#[test]
fn fusion_with_stored_poses_matches_the_dense_information_form_and_merges_tracks() {
    use super::tests::{delta, dense_fusion_reference, random_spd};
    use rand::SeedableRng;
    for frame in [NavFrame::Local, NavFrame::Global] {
        let mut f = filter(frame, bearing_sensor(), AssociationMode::Descriptor);
        let pf = PoseFrame::new(frame, &site()).unwrap();
        let feats = [
            (7, pf.to_filter(&Vector3::new(40.0, 10.0, 0.0))),
            (8, pf.to_filter(&Vector3::new(50.0, -20.0, 5.0))),
        ];
        let obs = |f: &SlamFilter, ids: &[(FeatureId, Vector3<f64>)]| -> Vec<Observation> {
            ids.iter()
                .map(|(id, m)| Observation {
                    descriptor: *id,
                    z: measure(f, m, 0.0),
                    appearance: None,
                })
                .collect()
        };
        let mut t = 0.0;
        for _ in 0..3 {
            let o = obs(&f, &feats);
            f.process_frame(
                0,
                &ObservationFrame {
                    time: t,
                    observations: o,
                },
            )
            .unwrap();
            fly(&mut f, t);
            t += 1.0;
        }
        assert_eq!(f.num_features(), 2, "{frame}");
        // A new feature seen once: a track and one stored pose.
        let m9 = pf.to_filter(&Vector3::new(90.0, 0.0, 0.0));
        let o = obs(&f, &[(9, m9)]);
        f.process_frame(
            0,
            &ObservationFrame {
                time: t,
                observations: o,
            },
        )
        .unwrap();
        fly(&mut f, t);
        t += 1.0;
        assert_eq!((f.num_tracks(), f.num_stored_poses()), (1, 1), "{frame}");
        // Delta over a known feature (8), the track's descriptor (9) and another new one (20).
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let y = random_spd(9, 0.5, &mut rng);
        let mut target = DVector::zeros(9);
        for (k, m) in [feats[1].1, m9, pf.to_filter(&Vector3::new(0.0, 60.0, 2.0))]
            .iter()
            .enumerate()
        {
            for i in 0..3 {
                target[3 * k + i] = m[i] + 0.3 * (i as f64 - 1.0);
            }
        }
        let d = delta(vec![8, 9, 20], y, &target, f.origin());
        let (x_ref, p_ref) = dense_fusion_reference(&f, &d);
        let old_slots: Vec<Slot> = f.layout().slots().to_vec();
        let n_old = f.dim();
        f.fuse_map_information(&d).unwrap();
        // Reference order: old slots, then 9 and 20 appended; the filter moved them before the
        // pose. Compare slot by slot.
        let ref_offset = |kind: SlotKind| -> usize {
            match old_slots.iter().find(|s| s.kind == kind) {
                Some(s) => s.offset,
                None => match kind {
                    SlotKind::Feature(9) => n_old,
                    _ => n_old + 3,
                },
            }
        };
        let slots: Vec<Slot> = f.layout().slots().to_vec();
        let last_feature = slots
            .iter()
            .rposition(|s| matches!(s.kind, SlotKind::Feature(_)))
            .unwrap();
        assert!(
            slots[last_feature + 1..]
                .iter()
                .all(|s| matches!(s.kind, SlotKind::Pose(_))),
            "{frame}: poses last"
        );
        let (xe, pe) = (dense_x(&f), dense_p(&f));
        let scale = p_ref.abs().max();
        let (mut dx, mut dp) = (0.0f64, 0.0f64);
        for a in &slots {
            let ra = ref_offset(a.kind);
            for i in 0..a.kind.dim() {
                dx = dx.max((xe[a.offset + i] - x_ref[ra + i]).abs());
                for b in &slots {
                    let rb = ref_offset(b.kind);
                    for j in 0..b.kind.dim() {
                        dp = dp.max(
                            (pe[(a.offset + i, b.offset + j)] - p_ref[(ra + i, rb + j)]).abs(),
                        );
                    }
                }
            }
        }
        eprintln!(
            "{frame}: max |Δx| {dx:.1e} m, max |ΔP| {:.1e} of max |P|",
            dp / scale
        );
        // The dense reference inverts the joint P (n ≈ 30, position variances ≈ 4 m² next to
        // attitude variances ≈ 1e-5 rad² and a pose nearly a copy of the vehicle's) and the
        // fused information back: its round-off, not the filter's, sets these bounds
        // (measured 3e-10 m and 5e-10 relative locally, 1e-9 and 2e-9 in ECEF): 100× margin.
        assert!(dx < 1e-7, "{frame}: x {dx}");
        assert!(dp < 2e-7 * scale, "{frame}: P {dp}");
        // The next frame recovers the track's stored observation onto the fused feature 9.
        let before = f.feature_covariance(9).unwrap().trace();
        let s0 = f.bearing_stats();
        f.process_frame(
            0,
            &ObservationFrame {
                time: t,
                observations: vec![],
            },
        )
        .unwrap();
        let s1 = f.bearing_stats();
        assert_eq!(s1.tracks_merged, s0.tracks_merged + 1, "{frame}");
        assert_eq!(
            s1.observations_recovered,
            s0.observations_recovered + 1,
            "{frame}"
        );
        assert_eq!((f.num_tracks(), f.num_stored_poses()), (0, 0), "{frame}");
        assert!(f.feature_covariance(9).unwrap().trace() < before, "{frame}");
    }
}

/// The correlated track gate's γ equals νᵀ S⁻¹ ν with S from an independent finite-difference
/// linearization of h(current pose, G(stored pose, z₁, r)) over the joint covariance of
/// (current pose, stored pose), R₁, σ_r² and R (eqs. 21.79–21.82 without the 21.83
/// independence assumption).
#[test]
fn correlated_track_gate_matches_a_finite_difference_linearization() {
    use super::bearing::StoredObservation;
    for (frame, sensor) in [
        (NavFrame::Local, bearing_sensor()),
        (NavFrame::Global, pixel_sensor()),
    ] {
        let mut f = filter(frame, sensor, AssociationMode::Descriptor);
        let pf = PoseFrame::new(frame, &site()).unwrap();
        let model = *f.observation_model(0).unwrap();
        let m = pf.to_filter(&Vector3::new(40.0, 10.0, 0.0));
        let z0_meas = measure(&f, &m, 0.0);
        let z0 = model.measurement_vector(&z0_meas).unwrap();
        f.process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: vec![Observation {
                    descriptor: 1,
                    z: z0_meas,
                    appearance: None,
                }],
            },
        )
        .unwrap();
        let pose_id = f.layout().poses().next().unwrap().0;
        fly(&mut f, 0.0);
        f.flush();
        let z = model.measurement_vector(&measure(&f, &m, 2e-3)).unwrap();
        let cur = f.current_geometry(0, &model);
        let anchor = f
            .anchor_of(
                &pf,
                0,
                &StoredObservation {
                    pose: pose_id,
                    vehicle: 0,
                    z: z0.clone(),
                },
            )
            .unwrap();
        // A hypothesis ≈ 45 m short of the feature (≈ 155 m away): a clear innovation.
        let (range, sigma_r) = (110.0, 10.0);
        let gamma = SlamFilter::anchored_gamma(&pf, &cur, &z, &anchor, range, sigma_r);

        // Independent: h(x) with x = [p_v, Ψ_v, p_a, Ψ_a, z₁, r], Jacobian by central differences.
        let (pv, av) = f.pose(0).unwrap();
        let (pa, aa) = f.stored_pose(pose_id).unwrap();
        let nx = 12 + z0.len() + 1;
        let mut x0 = DVector::zeros(nx);
        for i in 0..3 {
            x0[i] = pv[i];
            x0[3 + i] = av[i];
            x0[6 + i] = pa[i];
            x0[9 + i] = aa[i];
        }
        for i in 0..z0.len() {
            x0[12 + i] = z0[i];
        }
        x0[nx - 1] = range;
        let h = |x: &DVector<f64>| -> DVector<f64> {
            let v3 = |k: usize| Vector3::new(x[k], x[k + 1], x[k + 2]);
            let z1 = x.rows(12, z0.len()).into_owned();
            let los = pose_line_of_sight(
                &pf,
                &PosedObservation {
                    model: &model,
                    position: v3(6),
                    attitude: v3(9),
                    z: &z1,
                },
            )
            .unwrap();
            let feature = pf.to_filter(&(los.origin + los.direction * x[nx - 1]));
            model
                .predict(&model.sensor_pose(&v3(0), &v3(3)), &feature)
                .unwrap()
                .z
        };
        let d = z.len();
        let mut jac = DMatrix::zeros(d, nx);
        for k in 0..nx {
            // Steps: 1e-3 m on positions and range, 1e-6 rad on angles, 1e-3 px / 1e-6 rad on z₁.
            let step = match k {
                0..3 | 6..9 => 1e-3,
                _ if k == nx - 1 => 1e-3,
                12.. if matches!(sensor, SensorModel::Pixel { .. }) => 1e-3,
                _ => 1e-6,
            };
            let mut xp = x0.clone();
            let mut xm = x0.clone();
            xp[k] += step;
            xm[k] -= step;
            let col = model.innovation(&h(&xp), &h(&xm)) / (2.0 * step);
            jac.set_column(k, &col);
        }
        // Joint covariance of (p_v, Ψ_v, p_a, Ψ_a) from the filter's P, then R₁ and σ_r².
        let p = dense_p(&f);
        let voff = f.layout().vehicle_offset(0).unwrap();
        let aoff = f.layout().pose_offset(pose_id).unwrap();
        let idx: Vec<usize> = (0..3)
            .map(|i| voff + POS + i)
            .chain((0..3).map(|i| voff + ATT + i))
            .chain((0..6).map(|i| aoff + i))
            .collect();
        let mut cov = DMatrix::zeros(nx, nx);
        for i in 0..12 {
            for j in 0..12 {
                cov[(i, j)] = p[(idx[i], idx[j])];
            }
        }
        let r = model.noise_covariance();
        cov.view_mut((12, 12), (d, d)).copy_from(&r);
        cov[(nx - 1, nx - 1)] = sigma_r * sigma_r;
        let s = &jac * cov * jac.transpose() + &r;
        let nu = model.innovation(&z, &h(&x0));
        let gamma_ref = nu.dot(&(s.clone().try_inverse().unwrap() * &nu));
        eprintln!("{frame}: γ {gamma:.6} vs finite-difference reference {gamma_ref:.6}");
        // Finite-difference Jacobians are accurate to ≈ 1e-6 relative here; γ inherits that.
        assert!(
            (gamma - gamma_ref).abs() <= 1e-4 * gamma_ref,
            "{frame}: {gamma} vs {gamma_ref}"
        );
        assert!(
            gamma_ref > 1.0,
            "the innovation must be non-trivial: {gamma_ref}"
        );
    }
}

/// A filter with multi-view initialization that never initializes on its own
/// (`min_observations` out of reach), so a test can drive `initialize_track` / `finish_track`.
fn multiview_filter(frame: NavFrame, sensor: SensorModel) -> SlamFilter {
    let mut f = filter(frame, sensor, AssociationMode::Descriptor);
    f.set_bearing_config(BearingConfig {
        initialization: BearingInit::MultiView,
        min_observations: 1000,
        max_track_observations: 1000,
        min_parallax: 5f64.to_radians(),
        constraint_parallax: 1f64.to_radians(),
        ..BearingConfig::default()
    })
    .unwrap();
    f
}

/// Feeds `frames` frames, 1 s of flight apart, each observing the features `ms` (descriptors
/// 7, 8, …) with small perturbations so that the innovations are not zero.
fn observe_features(f: &mut SlamFilter, ms: &[Vector3<f64>], frames: usize) {
    for k in 0..frames {
        let observations = ms
            .iter()
            .enumerate()
            .map(|(i, m)| Observation {
                descriptor: 7 + i as u64,
                z: measure(
                    f,
                    m,
                    1e-3 * ((k + i) as f64 - 1.7) * if i % 2 == 0 { 1.0 } else { -0.6 },
                ),
                appearance: None,
            })
            .collect();
        let report = f
            .process_frame(
                0,
                &ObservationFrame {
                    time: k as f64,
                    observations,
                },
            )
            .unwrap();
        assert_eq!(report.stored(), ms.len(), "{report:?}");
        fly(f, k as f64);
    }
}

/// The stacked measurement function of a track's stored observations at stored poses and a
/// feature, with Jacobians by central differences (independent of the analytic ones).
struct DenseTrack {
    /// Residuals z − h at the linearization point, stacked.
    r: DVector<f64>,
    /// ∂h/∂x (rows × state), non-zero on the stored poses.
    h_x: DMatrix<f64>,
    /// ∂h/∂m (rows × 3).
    h_m: DMatrix<f64>,
    /// Block-diagonal R.
    noise: DMatrix<f64>,
}

fn dense_track(f: &SlamFilter, id: TrackId, m: &Vector3<f64>) -> DenseTrack {
    let pf = f.pose_frame().unwrap();
    let track = f.bearing.tracks.iter().find(|t| t.id == id).unwrap();
    let x = dense_x(f);
    let n = x.len();
    let model = *f.observation_model(0).unwrap();
    let d = model.measurement_dim();
    let rows = d * track.observations.len();
    let h = |p: &Vector3<f64>, a: &Vector3<f64>, m: &Vector3<f64>| -> DVector<f64> {
        model
            .predict(&model.sensor_pose(&pf.to_filter(p), a), m)
            .unwrap()
            .z
    };
    let mut out = DenseTrack {
        r: DVector::zeros(rows),
        h_x: DMatrix::zeros(rows, n),
        h_m: DMatrix::zeros(rows, 3),
        noise: DMatrix::zeros(rows, rows),
    };
    // Steps: 1e-2 m (features 150 m away: truncation ∝ (step/range)² ≈ 4e-9 relative; rounding
    // ∝ |coordinate|·ε/step ≈ 6e6·1.1e-16/1e-2 ≈ 7e-8 for ECEF coordinates) and 1e-6 rad.
    for (j, o) in track.observations.iter().enumerate() {
        let off = f.layout().pose_offset(o.pose).unwrap();
        let p = Vector3::new(x[off], x[off + 1], x[off + 2]);
        let a = Vector3::new(x[off + 3], x[off + 4], x[off + 5]);
        let row = j * d;
        let nu = model.innovation(&o.z, &h(&p, &a, m));
        out.r.rows_mut(row, d).copy_from(&nu);
        out.noise
            .view_mut((row, row), (d, d))
            .copy_from(&model.noise_covariance());
        for c in 0..6 {
            let step = if c < 3 { 1e-2 } else { 1e-6 };
            let (mut pp, mut ap, mut pm, mut am) = (p, a, p, a);
            if c < 3 {
                pp[c] += step;
                pm[c] -= step;
            } else {
                ap[c - 3] += step;
                am[c - 3] -= step;
            }
            let col = model.innovation(&h(&pp, &ap, m), &h(&pm, &am, m)) / (2.0 * step);
            out.h_x.view_mut((row, off + c), (d, 1)).copy_from(&col);
        }
        for c in 0..3 {
            let (mut mp, mut mm) = (*m, *m);
            mp[c] += 1e-2;
            mm[c] -= 1e-2;
            let col = model.innovation(&h(&p, &a, &mp), &h(&p, &a, &mm)) / 2e-2;
            out.h_m.view_mut((row, c), (d, 1)).copy_from(&col);
        }
    }
    out
}

/// The batch posterior of (x, m) given the prior N(x̂, P) on x, no prior on m, and the track's
/// observations linearized at (x̂, m̂): information form on the joint, solved densely.
fn dense_batch(
    x: &DVector<f64>,
    p: &DMatrix<f64>,
    m: &Vector3<f64>,
    t: &DenseTrack,
) -> (DVector<f64>, DMatrix<f64>) {
    let n = x.len();
    let r_inv = t.noise.clone().try_inverse().unwrap();
    let mut h = DMatrix::zeros(t.r.len(), n + 3);
    h.view_mut((0, 0), (t.r.len(), n)).copy_from(&t.h_x);
    h.view_mut((0, n), (t.r.len(), 3)).copy_from(&t.h_m);
    let mut info = h.transpose() * &r_inv * &h;
    let p_inv = p.clone().try_inverse().unwrap();
    let mut block = info.view((0, 0), (n, n)).into_owned();
    block += p_inv;
    info.view_mut((0, 0), (n, n)).copy_from(&block);
    let cov = info.try_inverse().unwrap();
    let shift = &cov * h.transpose() * &r_inv * &t.r;
    let mut mean = DVector::zeros(n + 3);
    mean.rows_mut(0, n).copy_from(x);
    mean.rows_mut(n, 3).copy_from(m);
    (mean + shift, (&cov + cov.transpose()) * 0.5)
}

/// Multi-view initialization (QR split: augmentation by the invertible part, update by the
/// null-space part) equals the dense batch posterior of the joint (x, m) given the prior on x and
/// all of the track's observations, with Jacobians from central differences; the constraint
/// update of a lost track equals that posterior's marginal on x. Both frames, both camera models.
#[test]
fn multiview_initialization_and_constraint_equal_the_dense_batch() {
    for (frame, sensor) in frames_and_sensors() {
        let label = format!("{frame} {sensor:?}");
        for constraint in [false, true] {
            let mut f = multiview_filter(frame, sensor);
            let pf = PoseFrame::new(frame, &site()).unwrap();
            let ms = [
                pf.to_filter(&Vector3::new(50.0, 10.0, 0.0)),
                pf.to_filter(&Vector3::new(45.0, -15.0, 5.0)),
            ];
            observe_features(&mut f, &ms, 5);
            // The pipeline runs inside `process_frame`, after the lazy cross-covariance flush.
            f.flush();
            let id = f.tracks().iter().find(|t| t.descriptor == 7).unwrap().id;
            let obs = f
                .bearing
                .tracks
                .iter()
                .find(|t| t.id == id)
                .unwrap()
                .observations
                .clone();
            let system = match f.track_system(&pf, &obs, 1e-3) {
                Ok(s) => s,
                Err(_) => panic!("{label}: no system"),
            };
            let m_hat = system.feature;
            let t = dense_track(&f, id, &m_hat);
            // The triangulated point is the least-squares optimum: the gradient H_mᵀ R⁻¹ r of
            // the residuals vanishes (to the GN stopping rule and FD rounding).
            let grad = t.h_m.transpose() * t.noise.clone().try_inverse().unwrap() * &t.r;
            let scale =
                (t.h_m.transpose() * t.noise.clone().try_inverse().unwrap() * &t.h_m).norm() * 1e-6;
            assert!(grad.norm() < scale, "{label}: gradient {grad} vs {scale}");
            let (x0, p0) = (dense_x(&f), dense_p(&f));
            let n = x0.len();
            let (mean, cov) = dense_batch(&x0, &p0, &m_hat, &t);
            f.bearing.config.min_observations = 2;
            // Old state i → its index after the step (the feature was inserted before the poses).
            let old_slots: Vec<(SlotKind, usize)> = f
                .layout()
                .slots()
                .iter()
                .map(|s| (s.kind, s.offset))
                .collect();
            let feature = if constraint {
                f.finish_track(&pf, id, false);
                assert_eq!(f.bearing_stats().constraint_updates, 1, "{label}");
                None
            } else {
                let fid = f.initialize_track(&pf, id).unwrap().unwrap();
                Some(fid)
            };
            let mut map = vec![0; n];
            for (kind, off) in &old_slots {
                let new = f.layout().offset(*kind).unwrap();
                for c in 0..kind.dim() {
                    map[off + c] = new + c;
                }
            }
            if let Some(fid) = feature {
                map.extend((0..3).map(|c| f.layout().feature_offset(fid).unwrap() + c));
            }
            let k = map.len();
            let (x1, p1) = (dense_x(&f), dense_p(&f));
            assert_eq!(x1.len(), k, "{label}: state size");
            let got_x = DVector::from_fn(k, |i, _| x1[map[i]]);
            let got_p = DMatrix::from_fn(k, k, |i, j| p1[(map[i], map[j])]);
            let want_x = mean.rows(0, k).into_owned();
            let want_p = cov.view((0, 0), (k, k)).into_owned();
            // Finite-difference Jacobians agree to ~1e-7 relative; the posterior inherits it.
            let dx = (&got_x - &want_x).abs().max();
            let dp = (&got_p - &want_p).abs().max() / want_p.abs().max();
            assert!(
                dx < 1e-5,
                "{label} constraint={constraint}: mean differs by {dx}: {}",
                (&got_x - &want_x).transpose()
            );
            assert!(
                dp < 1e-6,
                "{label} constraint={constraint}: covariance differs by {dp}"
            );
            // Sanity: the update did something (the check above is not vacuous).
            let moved = (&got_p - p0.view((0, 0), (n.min(k), n.min(k))).resize(k, k, 0.0))
                .abs()
                .max();
            assert!(moved > 1e-6, "{label}: the update changed nothing");
        }
    }
}

/// Index of the bearing-only track of `descriptor` in `f` (which must hold one).
fn track_index(f: &SlamFilter, descriptor: u64) -> usize {
    f.bearing
        .tracks
        .iter()
        .position(|t| t.descriptor == descriptor)
        .expect("a track of that descriptor")
}

/// A track with one grossly wrong observation: the joint χ² test fails, the worst observation
/// is removed and the rest initializes; a track of mutually inconsistent observations is refused
/// and leaves the state as it was.
#[test]
fn multiview_removes_an_outlier_and_refuses_an_inconsistent_track() {
    let frame = NavFrame::Local;
    let mut f = multiview_filter(frame, pixel_sensor());
    let pf = PoseFrame::new(frame, &site()).unwrap();
    let ms = [pf.to_filter(&Vector3::new(50.0, 10.0, 0.0))];
    observe_features(&mut f, &ms, 6);
    f.flush();
    // Corrupt the third stored observation by 25 px (σ = 1 px).
    let k = track_index(&f, 7);
    f.bearing.tracks[k].observations[2].z[0] += 25.0;
    let id = f.bearing.tracks[k].id;
    f.bearing.config.min_observations = 4;
    let fid = f.initialize_track(&pf, id).unwrap();
    assert!(fid.is_some());
    assert_eq!(f.bearing_stats().outliers_removed, 1);

    // Every observation pulled a different way: nothing consistent is left.
    let mut g = multiview_filter(frame, pixel_sensor());
    observe_features(&mut g, &ms, 6);
    g.flush();
    let k = track_index(&g, 7);
    for (j, o) in g.bearing.tracks[k].observations.iter_mut().enumerate() {
        o.z[0] += 40.0 * (j as f64 - 2.5);
        o.z[1] -= 30.0 * ((j * 7 % 5) as f64 - 2.0);
    }
    let id = g.bearing.tracks[k].id;
    g.bearing.config.min_observations = 4;
    let (x0, p0) = (dense_x(&g), dense_p(&g));
    assert_eq!(g.initialize_track(&pf, id).unwrap(), None);
    assert_eq!(g.bearing_stats().tracks_rejected, 1);
    assert_eq!(dense_x(&g), x0);
    assert_eq!(dense_p(&g), p0);
}

/// `marginal_sigma_ratio`: with a sensor σ' = 4 px standing for a tracker whose own error has
/// σ = 1 px (ratio 0.25), a stored observation 8 px off (2σ', 8σ) passes the joint test with
/// the ratio at 1 but is removed as a gross outlier with the ratio at 0.25; and a
/// well-determined feature's observation 8 px off is associated with the ratio at 1 and
/// rejected at 0.25.
#[test]
fn marginal_sigma_ratio_catches_outliers_that_the_equivalent_white_sigma_lets_through() {
    let frame = NavFrame::Local;
    let wide = SensorModel::Pixel {
        camera: camera(),
        sigma_pixel: 4.0,
    };
    let pf = PoseFrame::new(frame, &site()).unwrap();
    let ms = [pf.to_filter(&Vector3::new(50.0, 10.0, 0.0))];
    let mut removed = Vec::new();
    let mut outcome = Vec::new();
    for ratio in [1.0, 0.25] {
        let mut f = multiview_filter(frame, wide);
        f.bearing.config.marginal_sigma_ratio = ratio;
        observe_features(&mut f, &ms, 5);
        f.flush();
        let k = track_index(&f, 7);
        f.bearing.tracks[k].observations[2].z[0] += 8.0;
        let id = f.bearing.tracks[k].id;
        f.bearing.config.min_observations = 4;
        let fid = f.initialize_track(&pf, id).unwrap().expect("initialized");
        removed.push(f.bearing_stats().outliers_removed);
        // A well-determined feature and pose (P scaled by 0.1, still PD: H P Hᵀ ≈ 0.7 px²
        // instead of ≈ 7 px² after five rays), as after many observations; then its next
        // observation 8 px off: NIS ≈ 64/16.7 against σ' (inside the 95 % gate), ≈ 64/1.7
        // against σ (beyond the 0.9999 gate, 18.4).
        f.flush();
        let n = f.dim();
        for i in 0..n {
            for j in 0..n {
                f.p[(i, j)] *= 0.1;
            }
        }
        f.forget_map_information();
        let z = match measure(&f, &ms[0], 0.0) {
            Measurement::Pixel(z) => Measurement::Pixel(z + nalgebra::Vector2::new(8.0, 0.0)),
            m => m,
        };
        let report = f
            .process_frame(
                0,
                &ObservationFrame {
                    time: 5.0,
                    observations: vec![Observation {
                        descriptor: fid,
                        z,
                        appearance: None,
                    }],
                },
            )
            .unwrap();
        outcome.push(report.outcomes[0]);
    }
    assert_eq!(removed, [0, 1]);
    assert!(
        matches!(outcome[0], ObservationOutcome::Associated { .. }),
        "{outcome:?}"
    );
    assert!(
        matches!(
            outcome[1],
            ObservationOutcome::Rejected(RejectReason::GateFailed { .. })
        ),
        "{outcome:?}"
    );
}

/// The linearization bound: tracks are reported once the relative attitude variance between
/// their first stored pose and the vehicle passes 2 σ_θ (1 px / 600 px here: a σ of 3.3°),
/// and not with the filter's own small attitude uncertainty.
#[test]
fn tracks_past_the_linearization_bound_are_the_ones_with_an_uncertain_relative_attitude() {
    let frame = NavFrame::Local;
    let mut f = multiview_filter(frame, pixel_sensor());
    let pf = PoseFrame::new(frame, &site()).unwrap();
    let ms = [pf.to_filter(&Vector3::new(50.0, 10.0, 0.0))];
    observe_features(&mut f, &ms, 3);
    f.flush();
    assert!(f.tracks_past_linearization_bound(0).is_empty());
    // The vehicle's yaw variance alone grows (its cross-covariances unchanged: P stays PD):
    // just under and just over the bound 2 σ_θ, σ_θ = 1/600 rad, on top of the relative
    // variance the filter already has.
    let yaw = f.layout.vehicle_block(0) + ATT + 2;
    let id = f.bearing.tracks[0].id;
    let first = f.bearing.tracks[0].observations[0].pose;
    let off = f.layout.pose_offset(first).unwrap() + POSE_ATT + 2;
    let rel = f.p[(yaw, yaw)] + f.p[(off, off)] - 2.0 * f.p[(yaw, off)];
    let bound = 2.0 / 600.0;
    f.p[(yaw, yaw)] += 0.99 * bound - rel;
    assert!(f.tracks_past_linearization_bound(0).is_empty());
    f.p[(yaw, yaw)] += 0.02 * bound;
    assert_eq!(f.tracks_past_linearization_bound(0), vec![id]);
}

/// End to end: frames through `process_frame` initialize a feature once the track has
/// `min_observations` and the parallax, and the feature is then associated like any other.
#[test]
fn multiview_initializes_through_process_frame() {
    for frame in [NavFrame::Local, NavFrame::Global] {
        let mut f = filter(frame, pixel_sensor(), AssociationMode::Descriptor);
        f.set_bearing_config(BearingConfig {
            initialization: BearingInit::MultiView,
            min_observations: 4,
            min_parallax: 5f64.to_radians(),
            ..BearingConfig::default()
        })
        .unwrap();
        let pf = PoseFrame::new(frame, &site()).unwrap();
        let m = pf.to_filter(&Vector3::new(50.0, 10.0, 0.0));
        let mut outcomes = Vec::new();
        for k in 0..6 {
            let report = f
                .process_frame(
                    0,
                    &ObservationFrame {
                        time: k as f64,
                        observations: vec![Observation {
                            descriptor: 7,
                            z: measure(&f, &m, 0.0),
                            appearance: None,
                        }],
                    },
                )
                .unwrap();
            outcomes.push(report.outcomes[0]);
            fly(&mut f, k as f64);
        }
        assert!(
            matches!(outcomes[3], ObservationOutcome::Initialized { feature: 7 }),
            "{outcomes:?}"
        );
        assert!(
            matches!(
                outcomes[4],
                ObservationOutcome::Associated { feature: 7, .. }
            ),
            "{outcomes:?}"
        );
        let err = (f.feature(7).unwrap() - m).norm();
        // Noise-free measurements from the estimated poses: the feature sits where the rays meet.
        assert!(err < 1e-6, "{frame}: feature off by {err}");
        assert_eq!(f.num_stored_poses(), 0, "{frame}: poses released");
    }
}

/// Multi-view initialization needs tracker ids; a gating association mode is refused.
#[test]
fn multiview_needs_descriptor_association() {
    let mut f = filter(
        NavFrame::Local,
        pixel_sensor(),
        AssociationMode::NearestNeighbour,
    );
    let err = f.set_bearing_config(BearingConfig {
        initialization: BearingInit::MultiView,
        ..BearingConfig::default()
    });
    assert!(matches!(err, Err(SlamError::InvalidConfig(_))), "{err:?}");
}

/// The zero-velocity pseudo-measurement equals the textbook Kalman update with H = [0 I 0] on the
/// velocity and z = 0, in both frames, with stored poses and features in the state; invalid σ
/// changes nothing.
#[test]
fn zero_velocity_update_equals_the_dense_kalman_update() {
    for frame in [NavFrame::Local, NavFrame::Global] {
        let mut f = multiview_filter(frame, pixel_sensor());
        let pf = PoseFrame::new(frame, &site()).unwrap();
        observe_features(&mut f, &[pf.to_filter(&Vector3::new(50.0, 10.0, 0.0))], 3);
        let (x0, p0) = (dense_x(&f), dense_p(&f));
        let n = x0.len();
        let sigma = 0.05;
        let mut h = DMatrix::zeros(3, n);
        for i in 0..3 {
            h[(i, crate::state::VEL + i)] = 1.0;
        }
        let nu = -(&h * &x0);
        let r = DMatrix::identity(3, 3) * sigma * sigma;
        let (want_x, want_p) = dense_update(&x0, &p0, &h, &r, &nu);
        let s = &h * &p0 * h.transpose() + &r;
        let want_nis = nu.dot(&(s.try_inverse().unwrap() * &nu));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(f.zero_velocity_update(0, bad).is_err());
        }
        assert!(f.zero_velocity_update(3, sigma).is_err());
        assert_eq!(dense_x(&f), x0, "{frame}: a refused update changed x");
        let nis = f.zero_velocity_update(0, sigma).unwrap();
        // ECEF-sized states round at ~1e-9 m; covariances at ~1e-12 of their scale.
        assert!((dense_x(&f) - want_x).abs().max() < 1e-8, "{frame}: x");
        assert!(
            (dense_p(&f) - &want_p).abs().max() < 1e-10 * want_p.abs().max(),
            "{frame}: P"
        );
        assert!(
            (nis - want_nis).abs() < 1e-9 * want_nis.max(1.0),
            "{frame}: NIS {nis} vs {want_nis}"
        );
        assert!(
            dense_x(&f).rows(crate::state::VEL, 3).norm() < x0.rows(crate::state::VEL, 3).norm()
        );
    }
}
