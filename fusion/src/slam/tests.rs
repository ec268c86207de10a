//! Unit tests of the filter against independent dense computations (nalgebra `DMatrix`, full
//! n×n products and inverses), never against the structured code under test.

use super::*;
use crate::imu::ImuGrade;
use crate::info::MapInformation;
use crate::sensor::{Measurement, Observation};
use nalgebra::{DMatrix, DVector};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn mount() -> SensorMount {
    SensorMount::downward(Vector3::new(0.3, 0.0, 0.2))
}

fn range_bearing() -> SensorModel {
    SensorModel::RangeBearing {
        sigma_range: 0.5,
        sigma_bearing: 0.005,
    }
}

/// Gravity of the flat test world [m/s²].
const FLAT_GRAVITY: f64 = 9.81;

pub(super) fn config(frame: NavFrame, mode: AssociationMode) -> SlamConfig {
    SlamConfig {
        frame,
        local_gravity_mps2: FLAT_GRAVITY,
        origin: Vector3::zeros(),
        association: AssociationConfig {
            mode,
            gate_probability: 0.95,
            ..AssociationConfig::default()
        },
        fresh_id_namespace: 1,
    }
}

pub(super) fn vehicle(position: Vector3<f64>) -> VehicleSetup {
    let mut cov = VehicleCovariance::zeros();
    for i in 0..3 {
        cov[(i, i)] = 1.0;
        cov[(3 + i, 3 + i)] = 0.01;
        cov[(6 + i, 6 + i)] = 1e-6;
        cov[(9 + i, 9 + i)] = 1e-4;
        cov[(12 + i, 12 + i)] = 1e-8;
    }
    VehicleSetup {
        state: VehicleState {
            position,
            velocity: Vector3::new(20.0, 1.0, 0.0),
            attitude: Vector3::new(0.02, -0.01, 0.3),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        },
        covariance: cov,
        imu_noise: ImuGrade::Tactical.noise(),
        sensor: range_bearing(),
        mount: mount(),
    }
}

fn to_dense(m: &Mat<f64>) -> DMatrix<f64> {
    DMatrix::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
}

fn col_to_dense(c: &Col<f64>) -> DVector<f64> {
    DVector::from_fn(c.nrows(), |i, _| c[i])
}

/// Exact bit pattern of everything the filter holds.
fn snapshot(f: &SlamFilter) -> Vec<u64> {
    let mut v: Vec<u64> = (0..f.x.nrows()).map(|i| f.x[i].to_bits()).collect();
    for j in 0..f.p.ncols() {
        for i in 0..f.p.nrows() {
            v.push(f.p[(i, j)].to_bits());
        }
    }
    for s in &f.vehicles {
        v.extend(s.pending.iter().map(|x| x.to_bits()));
        v.push(u64::from(s.has_pending));
    }
    v.push(f.layout.dim() as u64);
    v.push(f.next_fresh);
    v
}

/// One vehicle at 100 m altitude in the local frame, with `k` features and a random SPD joint
/// covariance ([`randomize`]).
fn random_local_filter(k: usize, rng: &mut ChaCha8Rng) -> SlamFilter {
    let mut f = SlamFilter::new(
        config(NavFrame::Local, AssociationMode::Descriptor),
        &[vehicle(Vector3::new(0.0, 0.0, -100.0))],
    )
    .unwrap();
    randomize(&mut f, k, rng);
    f
}

/// Adds `k` features with ids 100.. and replaces (x, P) by a random well-conditioned joint
/// estimate: P = A Aᵀ + I·0.5 with A of unit-scale normal entries / √n.
fn randomize(f: &mut SlamFilter, k: usize, rng: &mut ChaCha8Rng) {
    for i in 0..k {
        f.grow(3);
        f.layout.push(SlotKind::Feature(100 + i as u64));
    }
    let n = f.dim();
    let a = DMatrix::from_fn(n, n, |_, _| rng.random::<f64>() - 0.5) / (n as f64).sqrt();
    let p = &a * a.transpose() + DMatrix::identity(n, n) * 0.5;
    for (j, i) in (0..n).flat_map(|j| (0..n).map(move |i| (j, i))) {
        f.p[(i, j)] = p[(i, j)];
    }
    for (id, off) in f.layout.features().collect::<Vec<_>>() {
        let _ = id;
        // Features on the ground around the vehicle, 60–120 m away in local NED.
        let m = Vector3::new(
            rng.random_range(-60.0..60.0),
            rng.random_range(-60.0..60.0),
            0.0,
        );
        for i in 0..3 {
            f.x[off + i] = m[i];
        }
    }
}

fn imu(t: f64) -> ImuSample {
    ImuSample {
        time: t,
        dt: 0.01,
        specific_force: Vector3::new(0.3 * t.sin(), -0.2, -9.7),
        angular_rate: Vector3::new(0.01, -0.02 * t.cos(), 0.03),
    }
}

#[test]
fn lazy_prediction_matches_dense_propagation() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for frame in [NavFrame::Local, NavFrame::Global] {
        let p0 = match frame {
            NavFrame::Local => Vector3::new(0.0, 0.0, -100.0),
            NavFrame::Global => crate::geodesy::geodetic_to_ecef(
                &crate::geodesy::Geodetic::from_degrees(-34.0, 151.0, 300.0),
            ),
        };
        let mut f = SlamFilter::new(
            config(frame, AssociationMode::Descriptor),
            &[vehicle(p0), vehicle(p0 + Vector3::new(50.0, 0.0, 0.0))],
        )
        .unwrap();
        randomize(&mut f, 5, &mut rng);
        // Global positions must stay ECEF-sized after randomize(): restore the vehicle means.
        for v in 0..2 {
            let off = f.layout.vehicle_block(v);
            let s = vehicle(p0 + Vector3::new(50.0 * v as f64, 0.0, 0.0))
                .state
                .to_vector();
            for i in 0..VEHICLE_DIM {
                f.x[off + i] = s[i];
            }
        }
        let mut p_ref = to_dense(&f.p);
        let n = f.dim();
        for k in 0..30 {
            let v = if k % 3 == 0 { 1 } else { 0 };
            let sample = imu(k as f64 * 0.01);
            let xv = f.vehicle_state(v).unwrap();
            let prop = ins::propagate_with_jacobians(
                &ins::Mechanization::new(frame, FLAT_GRAVITY).unwrap(),
                &xv,
                &sample,
            )
            .unwrap();
            let q = ins::process_noise(&ImuGrade::Tactical.noise(), sample.dt);
            // Dense reference: ∇F is identity except the vehicle block; ∇G has only vehicle rows.
            let off = f.layout.vehicle_block(v);
            let mut ff = DMatrix::identity(n, n);
            let mut gg = DMatrix::zeros(n, 12);
            for i in 0..VEHICLE_DIM {
                for j in 0..VEHICLE_DIM {
                    ff[(off + i, off + j)] = prop.transition[(i, j)];
                }
                for j in 0..12 {
                    gg[(off + i, j)] = prop.noise[(i, j)];
                }
            }
            let qd = DMatrix::from_fn(12, 12, |i, j| q[(i, j)]);
            p_ref = &ff * &p_ref * ff.transpose() + &gg * qd * gg.transpose();
            f.predict(v, &sample).unwrap();
            let got = f.vehicle_state(v).unwrap();
            // Small angles: the roll/yaw wrap of the filter is the identity here.
            assert_eq!(got, prop.state);
        }
        let p = to_dense(&f.joint_covariance());
        // Same products in another order: agreement to ≈ 1e-13 relative; 1e-10 leaves margin.
        let err = (&p - &p_ref).abs().max() / p_ref.abs().max();
        assert!(err < 1e-10, "{frame}: {err}");
        // The map block is untouched by prediction.
        let before = f.map_marginal();
        f.flush();
        let after = f.map_marginal();
        assert_eq!(to_dense(&before.covariance), to_dense(&after.covariance));
    }
}

#[test]
fn invalid_imu_sample_leaves_the_filter_bit_for_bit_unchanged() {
    let mut f = random_local_filter(3, &mut ChaCha8Rng::seed_from_u64(2));
    f.predict(0, &imu(0.0)).unwrap(); // leaves a pending Φ
    let before = snapshot(&f);
    let mut bad = Vec::new();
    for field in 0..6 {
        for value in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let mut s = imu(0.01);
            match field {
                0 => s.dt = value,
                1 => s.time = value,
                2 => s.specific_force.x = value,
                3 => s.specific_force.z = value,
                4 => s.angular_rate.y = value,
                _ => s.angular_rate.z = value,
            }
            bad.push(s);
        }
    }
    let mut zero_dt = imu(0.01);
    zero_dt.dt = 0.0;
    bad.push(zero_dt);
    let mut negative_dt = imu(0.01);
    negative_dt.dt = -0.01;
    bad.push(negative_dt);
    for s in &bad {
        assert!(matches!(f.predict(0, s), Err(SlamError::Ins(_))), "{s:?}");
        assert_eq!(snapshot(&f), before, "{s:?}");
    }
    assert_eq!(f.predict(3, &imu(0.01)), Err(SlamError::UnknownVehicle(3)));
    assert_eq!(snapshot(&f), before);
}

fn observe(f: &SlamFilter, v: usize, truth: &VehicleState, feature: &Vector3<f64>) -> DVector<f64> {
    let model = f.observation_model(v).unwrap();
    model
        .predict(
            &model.sensor_pose(&truth.position, &truth.attitude),
            feature,
        )
        .unwrap()
        .z
}

/// A clone of `f` after processing one frame of vehicle 0 (the report with it).
pub(super) fn after_frame(
    f: &SlamFilter,
    time: f64,
    observations: Vec<Observation>,
) -> (SlamFilter, FrameReport) {
    let mut g = f.clone();
    let r = g
        .process_frame(0, &ObservationFrame { time, observations })
        .unwrap();
    (g, r)
}

fn rb(z: &DVector<f64>) -> Measurement {
    Measurement::RangeBearing(Vector3::new(z[0], z[1], z[2]))
}

/// A refused measurement (NaN/∞, wrong kind, range ≤ 0) rejects only itself: the frame's good
/// observation is processed exactly as in a frame without the bad one (bit for bit); a frame of
/// refused measurements only is processed as an empty frame; a NaN frame time or an unknown
/// vehicle leaves the filter unchanged.
#[test]
fn invalid_observations_are_rejected_alone() {
    let mut f = random_local_filter(3, &mut ChaCha8Rng::seed_from_u64(3));
    f.predict(0, &imu(0.0)).unwrap();
    let truth = f.vehicle_state(0).unwrap();
    let good = Observation {
        descriptor: 100,
        z: rb(&observe(&f, 0, &truth, &f.feature(100).unwrap())),
        appearance: None,
    };
    let before = snapshot(&f);
    let mut frames = Vec::new();
    for (k, value) in [
        (0, f64::NAN),
        (1, f64::INFINITY),
        (2, f64::NAN),
        (1, f64::NEG_INFINITY),
    ] {
        let mut z = Vector3::new(100.0, 0.1, 0.2);
        z[k] = value;
        let bad = Observation {
            descriptor: 7,
            z: Measurement::RangeBearing(z),
            appearance: None,
        };
        frames.push(ObservationFrame {
            time: 1.0,
            observations: vec![good, bad],
        });
    }
    frames.push(ObservationFrame {
        time: 1.0,
        observations: vec![
            good,
            Observation {
                descriptor: 7,
                z: Measurement::Pixel(nalgebra::Vector2::new(1.0, 2.0)),
                appearance: None,
            },
        ],
    });
    let (alone, want_report) = after_frame(&f, 1.0, vec![good]);
    for (fr, fault) in frames.iter().zip(
        [MeasurementFault::NonFinite; 4]
            .into_iter()
            .chain([MeasurementFault::KindMismatch]),
    ) {
        let (g, r) = after_frame(&f, fr.time, fr.observations.clone());
        assert_eq!(
            r.outcomes[1],
            ObservationOutcome::Rejected(RejectReason::InvalidMeasurement(fault)),
            "{fr:?}"
        );
        assert_eq!(r.outcomes[0], want_report.outcomes[0]);
        assert_eq!(snapshot(&g), snapshot(&alone), "{fr:?}");
        // Only the bad observation: the same as an empty frame.
        let (empty, _) = after_frame(&f, 1.0, vec![]);
        let (g, r) = after_frame(&f, 1.0, vec![fr.observations[1]]);
        assert_eq!(r.rejected(), 1);
        assert_eq!(snapshot(&g), snapshot(&empty));
    }
    let nan_time = ObservationFrame {
        time: f64::NAN,
        observations: vec![good],
    };
    assert_eq!(f.process_frame(0, &nan_time), Err(SlamError::NonFiniteTime));
    assert_eq!(
        f.process_frame(1, &frames[0]),
        Err(SlamError::UnknownVehicle(1))
    );
    assert_eq!(snapshot(&f), before);

    // A finite but non-positive range rejects only its own observation: the good one is used.
    for range in [0.0, -1.0] {
        let mut g = f.clone();
        let bad = Observation {
            descriptor: 7,
            z: Measurement::RangeBearing(Vector3::new(range, 0.1, 0.2)),
            appearance: None,
        };
        let r = g
            .process_frame(
                0,
                &ObservationFrame {
                    time: 1.0,
                    observations: vec![bad, good],
                },
            )
            .unwrap();
        assert_eq!(
            r.outcomes[0],
            ObservationOutcome::Rejected(RejectReason::InvalidMeasurement(
                MeasurementFault::NonPositiveRange
            ))
        );
        assert!(matches!(
            r.outcomes[1],
            ObservationOutcome::Associated { feature: 100, .. }
        ));
        assert_eq!(g.num_features(), f.num_features());
    }
}

#[test]
fn stacked_joseph_update_matches_the_dense_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut f = random_local_filter(6, &mut rng);
    let n = f.dim();
    let x0 = col_to_dense(&f.x);
    let p0 = to_dense(&f.p);
    let est = f.vehicle_state(0).unwrap();
    let model = *f.observation_model(0).unwrap();
    let pose = model.sensor_pose(&est.position, &est.attitude);
    // Two observations with small innovations (inside the gate even for this random P).
    let ids = [101u64, 104];
    let voff = f.layout.vehicle_block(0);
    let mut h = DMatrix::zeros(6, n);
    let mut nu = DVector::zeros(6);
    let mut obs = Vec::new();
    for (k, id) in ids.iter().enumerate() {
        let off = f.layout.feature_offset(*id).unwrap();
        let pred = model.predict(&pose, &f.feature(*id).unwrap()).unwrap();
        let z = &pred.z + DVector::from_vec(vec![0.3, 0.002, -0.001]);
        nu.rows_mut(3 * k, 3)
            .copy_from(&model.innovation(&z, &pred.z));
        for i in 0..3 {
            for j in 0..3 {
                h[(3 * k + i, voff + POS_ + j)] = pred.d_position[(i, j)];
                h[(3 * k + i, voff + ATT_ + j)] = pred.d_attitude[(i, j)];
                h[(3 * k + i, off + j)] = pred.d_feature[(i, j)];
            }
        }
        obs.push(Observation {
            descriptor: *id,
            z: rb(&z),
            appearance: None,
        });
    }
    let r1 = model.noise_covariance();
    let mut r = DMatrix::zeros(6, 6);
    r.view_mut((0, 0), (3, 3)).copy_from(&r1);
    r.view_mut((3, 3), (3, 3)).copy_from(&r1);
    // Dense reference, eqs. 21.56–21.60 with the textbook Joseph form.
    let s = &h * &p0 * h.transpose() + &r;
    let k = &p0 * h.transpose() * s.clone().try_inverse().unwrap();
    let ikh = DMatrix::identity(n, n) - &k * &h;
    let p_ref = &ikh * &p0 * ikh.transpose() + &k * &r * k.transpose();
    let x_ref = &x0 + &k * &nu;

    let report = f
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: obs,
            },
        )
        .unwrap();
    assert_eq!(report.associated(), 2, "{report:?}");
    // Different but equivalent arithmetic on O(1) entries: 1e-11 absolute is ≈ 100 ulp·n.
    assert!((to_dense(&f.p) - &p_ref).abs().max() < 1e-11);
    assert!((col_to_dense(&f.x) - &x_ref).abs().max() < 1e-11);
    // Symmetric to the bit.
    let p = to_dense(&f.p);
    assert_eq!(p, p.transpose());
}

const POS_: usize = crate::state::POS;
const ATT_: usize = crate::state::ATT;

#[test]
fn feature_initialization_matches_eq_21_52() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for frame in [NavFrame::Local, NavFrame::Global] {
        let p0 = match frame {
            NavFrame::Local => Vector3::new(0.0, 0.0, -100.0),
            NavFrame::Global => crate::geodesy::geodetic_to_ecef(
                &crate::geodesy::Geodetic::from_degrees(10.0, 20.0, 150.0),
            ),
        };
        let mut f =
            SlamFilter::new(config(frame, AssociationMode::Descriptor), &[vehicle(p0)]).unwrap();
        randomize(&mut f, 4, &mut rng);
        let voff = f.layout.vehicle_block(0);
        let s = vehicle(p0).state.to_vector();
        for i in 0..VEHICLE_DIM {
            f.x[voff + i] = s[i];
        }
        let n = f.dim();
        let p0m = to_dense(&f.p);
        let model = *f.observation_model(0).unwrap();
        let z = DVector::from_vec(vec![120.0, 0.2, -0.1]);
        let est = f.vehicle_state(0).unwrap();
        let init = model
            .initialize(&model.sensor_pose(&est.position, &est.attitude), &z)
            .unwrap();
        // Dense eq. 21.52: [I 0; ∇J_x ∇J_z] diag(P, R) [I 0; ∇J_x ∇J_z]ᵀ.
        let mut j = DMatrix::zeros(n + 3, n + 3);
        j.view_mut((0, 0), (n, n)).fill_with_identity();
        for a in 0..3 {
            for b in 0..3 {
                j[(n + a, voff + POS_ + b)] = init.d_position[(a, b)];
                j[(n + a, voff + ATT_ + b)] = init.d_attitude[(a, b)];
                j[(n + a, n + b)] = init.d_measurement[(a, b)];
            }
        }
        let mut blk = DMatrix::zeros(n + 3, n + 3);
        blk.view_mut((0, 0), (n, n)).copy_from(&p0m);
        blk.view_mut((n, n), (3, 3))
            .copy_from(&model.noise_covariance());
        let p_ref = &j * blk * j.transpose();
        let report = f
            .process_frame(
                0,
                &ObservationFrame {
                    time: 0.0,
                    observations: vec![Observation {
                        descriptor: 9,
                        z: rb(&z),
                        appearance: None,
                    }],
                },
            )
            .unwrap();
        assert_eq!(
            report.outcomes,
            vec![ObservationOutcome::Initialized { feature: 9 }]
        );
        let err = (to_dense(&f.p) - &p_ref).abs().max() / p_ref.abs().max();
        // Same formula, different summation order: ≈ 1e-15 relative; 1e-12 leaves margin.
        assert!(err < 1e-12, "{frame}: {err}");
        assert!((f.feature(9).unwrap() - init.feature).norm() == 0.0);
    }
}

/// Builds a delta over `ids` whose information is `y` (3k×3k) and whose vector is y·(t − o) for
/// a target t (so fusing it pulls the features toward t).
pub(super) fn delta(
    ids: Vec<FeatureId>,
    y: DMatrix<f64>,
    target: &DVector<f64>,
    origin: Vector3<f64>,
) -> MapInformation {
    let k = ids.len() * 3;
    let t = DVector::from_fn(k, |i, _| target[i] - origin[i % 3]);
    let v = &y * t;
    MapInformation {
        ids,
        origin,
        matrix: Mat::from_fn(k, k, |i, j| y[(i, j)]),
        vector: Col::from_fn(k, |i| v[i]),
    }
}

/// Independent reference: dense joint information, add the delta, invert back. Returns the
/// expected (x, P) with new features appended in delta order.
pub(super) fn dense_fusion_reference(
    f: &SlamFilter,
    d: &MapInformation,
) -> (DVector<f64>, DMatrix<f64>) {
    let n = f.dim();
    let new: Vec<FeatureId> = d
        .ids
        .iter()
        .copied()
        .filter(|id| !f.layout.has_feature(*id))
        .collect();
    let m = n + 3 * new.len();
    let p = to_dense(&f.joint_covariance());
    let y = p.clone().try_inverse().unwrap();
    // Linearisation point c: the current estimate for filter states, o for new features.
    let mut c = DVector::zeros(m);
    c.rows_mut(0, n).copy_from(&col_to_dense(&f.x));
    for i in 0..3 * new.len() {
        c[n + i] = d.origin[i % 3];
    }
    let mut yj = DMatrix::zeros(m, m);
    yj.view_mut((0, 0), (n, n)).copy_from(&y);
    let mut yv = DVector::zeros(m); // y_joint w.r.t. c: Y (x̂ − c) = 0 for the prior
    let index = |id: FeatureId| -> usize {
        f.layout
            .feature_offset(id)
            .unwrap_or_else(|| n + 3 * new.iter().position(|x| *x == id).unwrap())
    };
    for (a, ida) in d.ids.iter().enumerate() {
        for (b, idb) in d.ids.iter().enumerate() {
            for i in 0..3 {
                for j in 0..3 {
                    yj[(index(*ida) + i, index(*idb) + j)] += d.matrix[(3 * a + i, 3 * b + j)];
                }
            }
        }
        for i in 0..3 {
            // Δy is w.r.t. x − o; re-express w.r.t. c: Δy − ΔY (c − o) on these rows.
            let mut corr = d.vector[3 * a + i];
            for (b, idb) in d.ids.iter().enumerate() {
                for j in 0..3 {
                    corr -= d.matrix[(3 * a + i, 3 * b + j)] * (c[index(*idb) + j] - d.origin[j]);
                }
            }
            yv[index(*ida) + i] += corr;
        }
    }
    let p_ref = yj.try_inverse().unwrap();
    let x_ref = &c + &p_ref * yv;
    (x_ref, p_ref)
}

fn marginal_information(f: &SlamFilter) -> (Vec<FeatureId>, DMatrix<f64>, DVector<f64>) {
    let mm = f.map_marginal();
    let y = to_dense(&mm.covariance).try_inverse().unwrap();
    let xm = DVector::from_fn(mm.mean.nrows(), |i, _| mm.mean[i] - f.origin()[i % 3]);
    let v = &y * xm;
    (mm.ids, y, v)
}

pub(super) fn random_spd(k: usize, scale: f64, rng: &mut ChaCha8Rng) -> DMatrix<f64> {
    let a = DMatrix::from_fn(k, k, |_, _| rng.random::<f64>() - 0.5);
    (&a * a.transpose() + DMatrix::identity(k, k) * 0.2) * scale
}

#[test]
fn fusion_matches_dense_information_form_and_adds_exactly_to_the_map_marginal() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    // (case, ids of the delta): known only, known + new, only new, low rank, indefinite.
    // Cases: 0 known only, 1 known + new, 2 only new, 3 low rank, 4 indefinite (pseudo-
    // measurement route); 5 whole map PD, 6 whole map indefinite, 7 whole map + new, 8 whole map
    // in state order (contiguous copies) (map route).
    for case in 0..9 {
        let mut f = SlamFilter::new(
            config(NavFrame::Local, AssociationMode::Descriptor),
            &[vehicle(Vector3::new(0.0, 0.0, -100.0))],
        )
        .unwrap();
        f.config.origin = Vector3::new(5.0, -3.0, 1.0);
        let n_feat = if case == 7 { 8 } else { 5 };
        randomize(&mut f, n_feat, &mut rng);
        f.predict(0, &imu(0.0)).unwrap(); // pending Φ must be flushed by the fusion
        let ids: Vec<FeatureId> = match case {
            0 => vec![101, 103],
            1 => vec![102, 900, 104, 901],
            2 => vec![900, 901],
            3 | 4 => vec![100, 101, 102],
            5 | 6 => vec![104, 100, 101, 102, 103],
            8 => vec![100, 101, 102, 103, 104],
            _ => vec![100, 101, 102, 903, 103, 104, 105, 106, 107],
        };
        let k = 3 * ids.len();
        let mut y = random_spd(k, 2.0, &mut rng);
        if case == 3 {
            // Rank 2: information only along two directions.
            let u = DMatrix::from_fn(k, 2, |_, _| rng.random::<f64>() - 0.5);
            y = &u * u.transpose() * 3.0;
        }
        if case == 4 || case == 6 {
            // Indefinite: subtract a bit of information along one direction (as a CI upstream
            // may), small enough that the fused result stays positive definite.
            let u = DVector::from_fn(k, |_, _| rng.random::<f64>() - 0.5).normalize();
            y = &u * u.transpose() * -0.05 + DMatrix::from_diagonal_element(k, k, 0.01);
            let mut ext = random_spd(k, 0.5, &mut rng);
            ext -= &u * u.transpose() * (u.transpose() * &ext * &u)[0];
            y += ext;
            assert!(
                y.symmetric_eigenvalues().min() < 0.0,
                "case must be indefinite"
            );
        }
        let target = DVector::from_fn(k, |_, _| rng.random_range(-50.0..50.0));
        let d = delta(ids.clone(), y.clone(), &target, f.origin());
        let (x_ref, p_ref) = dense_fusion_reference(&f, &d);
        let (ids0, y0, v0) = marginal_information(&f);
        if case == 5 || case == 7 || case == 8 {
            // map_information() matches the independent inverse, and primes the cache that the
            // whole-map route then reuses (cases 5, 7; case 6 computes its own inverse).
            let mi = f.map_information().unwrap();
            assert_eq!(mi.ids, ids0);
            let ey = (to_dense(&mi.matrix) - &y0).abs().max() / y0.abs().max();
            let ev = (col_to_dense(&mi.vector) - &v0).abs().max() / v0.abs().max();
            // Two independent inverses of a κ ≲ 1e3 matrix: 1e-11 relative.
            assert!(ey < 1e-11 && ev < 1e-11, "{ey} {ev}");
        }
        let rep = f.fuse_map_information(&d).unwrap();
        match case {
            3 => assert_eq!(rep.rank, Some(2)),
            4 => assert!(rep.negative_directions.unwrap() > 0),
            5..=8 => assert_eq!(rep.method, FuseMethod::MapInformation),
            _ => {}
        }
        if case < 2 || case == 3 || case == 4 {
            assert_eq!(rep.method, FuseMethod::PseudoMeasurement);
        }
        let p = to_dense(&f.p);
        let x = col_to_dense(&f.x);
        // Both sides are O(1)-conditioned products/inverses of ≈ 30×30 matrices: 1e-9
        // relative covers the inverse's round-off (κ ≈ 1e2–1e3 · 1e-16 · n).
        let scale = p_ref.abs().max();
        assert!(
            (&p - &p_ref).abs().max() < 1e-9 * scale,
            "case {case}: P {}",
            (&p - &p_ref).abs().max()
        );
        assert!(
            (&x - &x_ref).abs().max() < 1e-8 * x_ref.abs().max(),
            "case {case}: x {}",
            (&x - &x_ref).abs().max()
        );

        // Map marginal information after = before + Δ (with zero prior on new features).
        let (ids1, y1, v1) = marginal_information(&f);
        let pos = |id: FeatureId| ids1.iter().position(|x| *x == id).unwrap();
        let mut y_exp = DMatrix::zeros(y1.nrows(), y1.ncols());
        let mut v_exp = DVector::zeros(v1.len());
        for (a, ia) in ids0.iter().enumerate() {
            for (b, ib) in ids0.iter().enumerate() {
                y_exp
                    .view_mut((3 * pos(*ia), 3 * pos(*ib)), (3, 3))
                    .copy_from(&y0.view((3 * a, 3 * b), (3, 3)));
            }
            v_exp
                .rows_mut(3 * pos(*ia), 3)
                .copy_from(&v0.rows(3 * a, 3));
        }
        for (a, ia) in ids.iter().enumerate() {
            for (b, ib) in ids.iter().enumerate() {
                let blk = y.view((3 * a, 3 * b), (3, 3)).into_owned();
                let mut t = y_exp.view_mut((3 * pos(*ia), 3 * pos(*ib)), (3, 3));
                t += blk;
            }
            for i in 0..3 {
                v_exp[3 * pos(*ia) + i] += d.vector[3 * a + i];
            }
        }
        let ey = (&y1 - &y_exp).abs().max() / y_exp.abs().max();
        let ev = (&v1 - &v_exp).abs().max() / v_exp.abs().max();
        // Two inversions of ≈ 20×20 matrices with κ ≲ 1e3: 1e-9 relative.
        assert!(
            ey < 1e-9 && ev < 1e-9,
            "case {case}: ΔY err {ey}, Δy err {ev}"
        );
    }
}

#[test]
fn bad_information_is_rejected_and_leaves_the_filter_unchanged() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut f = random_local_filter(3, &mut rng);
    f.predict(0, &imu(0.0)).unwrap();
    let before = snapshot(&f);
    let good = delta(
        vec![100, 900],
        random_spd(6, 1.0, &mut rng),
        &DVector::zeros(6),
        Vector3::zeros(),
    );
    let mut cases: Vec<(MapInformation, &str)> = Vec::new();
    let mut d = good.clone();
    d.matrix[(1, 4)] = f64::NAN;
    cases.push((d, "nan matrix"));
    let mut d = good.clone();
    d.vector[5] = f64::INFINITY;
    cases.push((d, "inf vector"));
    let mut d = good.clone();
    d.matrix[(0, 5)] += 0.1;
    cases.push((d, "asymmetric"));
    let mut d = good.clone();
    d.ids = vec![100, 100];
    cases.push((d, "duplicate ids"));
    let mut d = good.clone();
    d.ids.push(5);
    cases.push((d, "size mismatch"));
    let mut d = good.clone();
    d.origin = Vector3::new(1.0, 0.0, 0.0);
    cases.push((d, "origin"));
    // Removing far more information than the filter holds: fused result not PD.
    cases.push((
        delta(
            vec![100, 101],
            -random_spd(6, 50.0, &mut rng),
            &DVector::zeros(6),
            Vector3::zeros(),
        ),
        "non-PD result",
    ));
    // A new feature with indefinite information cannot be initialized.
    let mut y = random_spd(6, 1.0, &mut rng);
    y[(4, 4)] = -5.0;
    cases.push((
        delta(vec![101, 901], y, &DVector::zeros(6), Vector3::zeros()),
        "indefinite new",
    ));
    for (d, what) in &cases {
        assert!(f.fuse_map_information(d).is_err(), "{what} accepted");
        assert_eq!(snapshot(&f), before, "{what} changed the filter");
    }
    assert!(f.fuse_map_information(&good).is_ok());

    // The map-information route (delta over the whole map) checks PD the same way.
    let mut g = random_local_filter(5, &mut rng);
    g.predict(0, &imu(0.0)).unwrap();
    let before = snapshot(&g);
    let ids: Vec<FeatureId> = (100..105).collect();
    let bad = delta(
        ids.clone(),
        -random_spd(15, 50.0, &mut rng),
        &DVector::zeros(15),
        Vector3::zeros(),
    );
    assert_eq!(
        g.fuse_map_information(&bad),
        Err(SlamError::NotPositiveDefinite("fused information"))
    );
    assert_eq!(snapshot(&g), before);
    let ok = delta(
        ids,
        random_spd(15, 1.0, &mut rng),
        &DVector::zeros(15),
        Vector3::zeros(),
    );
    assert_eq!(
        g.fuse_map_information(&ok).unwrap().method,
        FuseMethod::MapInformation
    );
}

/// A row of ground features spaced `spacing` m east, the vehicle 100 m above them, its estimate
/// offset `offset` m east of the truth; the map is known tightly (fused in as information).
fn association_scene(
    mode: AssociationMode,
    spacing: f64,
    offset: f64,
) -> (SlamFilter, Vec<Observation>, Vec<FeatureId>) {
    let truth_p = Vector3::new(0.0, 0.0, -100.0);
    let mut setup = vehicle(truth_p + Vector3::new(0.0, offset, 0.0));
    setup.state.attitude = Vector3::zeros();
    let mut f = SlamFilter::new(config(NavFrame::Local, mode), &[setup]).unwrap();
    let ids: Vec<FeatureId> = (0..6).map(|i| 10 + i).collect();
    let target = DVector::from_fn(18, |i, _| match i % 3 {
        0 => 5.0,
        1 => spacing * ((i / 3) as f64 - 2.5),
        _ => 0.0,
    });
    // 5 cm σ per axis, independent: the map is known much better than the vehicle.
    let y = DMatrix::from_diagonal_element(18, 18, 400.0);
    f.fuse_map_information(&delta(ids.clone(), y, &target, Vector3::zeros()))
        .unwrap();
    let mut truth = setup.state;
    truth.position = truth_p;
    let obs = ids
        .iter()
        .enumerate()
        .map(|(k, id)| {
            let m = Vector3::new(target[3 * k], target[3 * k + 1], target[3 * k + 2]);
            Observation {
                descriptor: *id,
                z: rb(&observe(&f, 0, &truth, &m)),
                appearance: None,
            }
        })
        .collect();
    (f, obs, ids)
}

fn wrong_associations(report: &FrameReport, ids: &[FeatureId]) -> usize {
    report
        .outcomes
        .iter()
        .zip(ids)
        .filter(
            |(o, id)| matches!(o, ObservationOutcome::Associated { feature, .. } if feature != *id),
        )
        .count()
}

#[test]
fn jcbb_resolves_a_coherent_offset_that_fools_nearest_neighbour() {
    // With 3 m spacing and a 1.6 m east error of the estimate, each observation's nearest
    // predicted feature is its east neighbour (1.4 m < 1.6 m), and both are inside the gate.
    let (mut nn, obs, ids) = association_scene(AssociationMode::NearestNeighbour, 3.0, 1.6);
    let frame = ObservationFrame {
        time: 0.0,
        observations: obs.clone(),
    };
    let r_nn = nn.process_frame(0, &frame).unwrap();
    let (mut jc, _, _) = association_scene(AssociationMode::Jcbb { max_nodes: 100_000 }, 3.0, 1.6);
    let prior = jc.clone();
    let r_jc = jc.process_frame(0, &frame).unwrap();
    // The incrementally factored joint NIS equals a dense stacked computation at the prior.
    let model = *prior.observation_model(0).unwrap();
    let est = prior.vehicle_state(0).unwrap();
    let pose = model.sensor_pose(&est.position, &est.attitude);
    let n = prior.dim();
    let voff = prior.layout.vehicle_block(0);
    let mut h = DMatrix::zeros(18, n);
    let mut nu = DVector::zeros(18);
    let mut r = DMatrix::zeros(18, 18);
    for (k, o) in r_jc.outcomes.iter().enumerate() {
        let ObservationOutcome::Associated { feature, .. } = o else {
            panic!("{o:?}")
        };
        let off = prior.layout.feature_offset(*feature).unwrap();
        let pred = model
            .predict(&pose, &prior.feature(*feature).unwrap())
            .unwrap();
        let z = model.measurement_vector(&obs[k].z).unwrap();
        nu.rows_mut(3 * k, 3)
            .copy_from(&model.innovation(&z, &pred.z));
        for i in 0..3 {
            for j in 0..3 {
                h[(3 * k + i, voff + POS_ + j)] = pred.d_position[(i, j)];
                h[(3 * k + i, voff + ATT_ + j)] = pred.d_attitude[(i, j)];
                h[(3 * k + i, off + j)] = pred.d_feature[(i, j)];
            }
        }
        r.view_mut((3 * k, 3 * k), (3, 3))
            .copy_from(&model.noise_covariance());
    }
    let p = to_dense(&prior.joint_covariance());
    let s = &h * p * h.transpose() + r;
    let dense_nis = (nu.transpose() * s.try_inverse().unwrap() * &nu)[0];
    let jnis = r_jc.jcbb_joint_nis.unwrap();
    // Same quadratic form via an 18×18 inverse vs a block Cholesky: 1e-9 relative.
    assert!(
        (jnis - dense_nis).abs() < 1e-9 * dense_nis,
        "{jnis} vs {dense_nis}"
    );
    assert!(
        wrong_associations(&r_nn, &ids) >= 4,
        "NN was expected to be fooled: {r_nn:?}"
    );
    assert_eq!(wrong_associations(&r_jc, &ids), 0, "{r_jc:?}");
    assert_eq!(r_jc.associated(), 6);
    assert!(!r_jc.jcbb_truncated);
    // The correct joint update pulls the vehicle back west toward the truth.
    // Six 5 cm-σ features vs a 1 m-σ vehicle: the posterior east σ is ≈ 0.1 m (bearing noise
    // 0.5 m at 100 m over 6 observations); 0.2 m is 2σ, while a wrong joint update leaves ≈ 1.6 m.
    assert!(jc.vehicle_state(0).unwrap().position.y.abs() < 0.2);
}

#[test]
fn nearest_neighbour_without_descriptors_and_descriptor_gating() {
    // Well separated features: NN pairs every observation correctly with descriptors ignored.
    let (mut f, mut obs, ids) = association_scene(AssociationMode::NearestNeighbour, 20.0, 0.5);
    for o in &mut obs {
        o.descriptor = 0; // garbage descriptors are ignored
    }
    let r = f
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: obs.clone(),
            },
        )
        .unwrap();
    assert_eq!(r.associated(), 6);
    assert_eq!(wrong_associations(&r, &ids), 0);
    assert_eq!(f.num_features(), 6);

    // Descriptor mode: a wrong descriptor naming a far feature fails the gate and creates nothing;
    // an unknown descriptor initializes a feature with that id.
    let (mut f, mut obs, _) = association_scene(AssociationMode::Descriptor, 20.0, 0.5);
    obs[0].descriptor = ids[5];
    obs[5].descriptor = 77;
    obs.truncate(6);
    let r = f
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: vec![obs[0], obs[5]],
            },
        )
        .unwrap();
    assert!(
        matches!(r.outcomes[0], ObservationOutcome::Rejected(RejectReason::GateFailed { feature, nis }) if feature == ids[5] && nis > 7.815)
    );
    assert_eq!(
        r.outcomes[1],
        ObservationOutcome::Initialized { feature: 77 }
    );
    assert_eq!(f.num_features(), 7);
    // A second feature seen with the same (now used) descriptor 77 in gating mode gets a fresh id.
    let (mut g, obs, _) = association_scene(AssociationMode::NearestNeighbour, 20.0, 0.5);
    let far = Observation {
        descriptor: 10,
        z: Measurement::RangeBearing(Vector3::new(150.0, 1.0, 0.2)),
        appearance: None,
    };
    let r = g
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: vec![obs[0], far],
            },
        )
        .unwrap();
    match r.outcomes[1] {
        ObservationOutcome::Initialized { feature } => {
            assert!(feature >= FRESH_ID_BASE && (feature >> 32) & 0x7FFF_FFFF == 1)
        }
        o => panic!("{o:?}"),
    }
}

#[test]
fn yaw_stays_wrapped_through_full_turns() {
    // Level attitude: with φ = θ = 0, E_b^n = I and ψ̇ = ω_z exactly.
    let mut setup = vehicle(Vector3::new(0.0, 0.0, -100.0));
    setup.state.attitude = Vector3::new(0.0, 0.0, 0.3);
    let mut f = SlamFilter::new(
        config(NavFrame::Local, AssociationMode::Descriptor),
        &[setup],
    )
    .unwrap();
    // 1 rad/s yaw rate for 20 s: more than three full turns.
    let spin = ImuSample {
        time: 0.0,
        dt: 0.01,
        specific_force: Vector3::new(0.0, 0.0, -FLAT_GRAVITY),
        angular_rate: Vector3::new(0.0, 0.0, 1.0),
    };
    let before = f.vehicle_covariance(0).unwrap();
    for _ in 0..2000 {
        f.predict(0, &spin).unwrap();
        let yaw = f.vehicle_state(0).unwrap().attitude.z;
        assert!(yaw > -std::f64::consts::PI && yaw <= std::f64::consts::PI);
    }
    let expected = crate::rotation::wrap_angle(0.3 + 20.0);
    let yaw = f.vehicle_state(0).unwrap().attitude.z;
    // 2000 additions of 0.01 rad plus 3 wraps: round-off ≈ 2000 ulp(π) ≈ 1e-12.
    assert!((yaw - expected).abs() < 1e-10, "{yaw} vs {expected}");
    // Yaw variance only grows in prediction (gyro noise, bias coupling).
    assert!(f.vehicle_covariance(0).unwrap()[(8, 8)] >= before[(8, 8)]);
}

#[test]
fn construction_rejects_invalid_setups() {
    let mut v = vehicle(Vector3::zeros());
    v.covariance[(0, 1)] = 0.5; // asymmetric
    assert!(matches!(
        SlamFilter::new(config(NavFrame::Local, AssociationMode::Descriptor), &[v]),
        Err(SlamError::InvalidConfig(_))
    ));
    let mut v = vehicle(Vector3::zeros());
    v.state.velocity.x = f64::NAN;
    assert!(SlamFilter::new(config(NavFrame::Local, AssociationMode::Descriptor), &[v]).is_err());
    assert!(SlamFilter::new(config(NavFrame::Local, AssociationMode::Descriptor), &[]).is_err());
    let mut c = config(NavFrame::Local, AssociationMode::Descriptor);
    c.association.gate_probability = 1.0;
    assert!(SlamFilter::new(c, &[vehicle(Vector3::zeros())]).is_err());
}

#[test]
fn map_information_cache_follows_map_changes() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let mut f = random_local_filter(4, &mut rng);
    let check = |f: &mut SlamFilter| {
        let (ids, y, v) = marginal_information(f);
        let mi = f.map_information().unwrap();
        assert_eq!(mi.ids, ids);
        // Independent nalgebra inverse vs faer Cholesky inverse, κ ≲ 1e3: 1e-11 relative.
        assert!((to_dense(&mi.matrix) - &y).abs().max() < 1e-11 * y.abs().max());
        assert!((col_to_dense(&mi.vector) - &v).abs().max() < 1e-11 * v.abs().max().max(1.0));
    };
    check(&mut f);
    // Prediction does not change the map: the cache stays valid and correct.
    f.predict(0, &imu(0.0)).unwrap();
    check(&mut f);
    // An update changes it (same feature count, so only the generation can tell) ...
    let est = f.vehicle_state(0).unwrap();
    let z = observe(&f, 0, &est, &f.feature(101).unwrap());
    let update = Observation {
        descriptor: 101,
        z: rb(&(z + DVector::from_vec(vec![0.2, 0.001, 0.0]))),
        appearance: None,
    };
    let r = f
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: vec![update],
            },
        )
        .unwrap();
    assert_eq!(r.associated(), 1);
    check(&mut f);
    // ... and so does an initialization.
    let new = Observation {
        descriptor: 55,
        z: rb(&DVector::from_vec(vec![90.0, 0.3, -0.2])),
        appearance: None,
    };
    let r = f
        .process_frame(
            0,
            &ObservationFrame {
                time: 0.0,
                observations: vec![new],
            },
        )
        .unwrap();
    assert_eq!(r.initialized(), 1);
    check(&mut f);
    // A fusion changes it too.
    let d = delta(
        vec![100],
        random_spd(3, 1.0, &mut rng),
        &DVector::zeros(3),
        Vector3::zeros(),
    );
    f.fuse_map_information(&d).unwrap();
    check(&mut f);
}

#[test]
fn randomized_fusions_match_the_dense_information_form() {
    // 60 random trials: filter size, delta subset and order, new features, PD / low-rank /
    // mildly indefinite information, both routes; each checked against the dense reference.
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut routes = [0usize; 3];
    for trial in 0..60 {
        let mut f = SlamFilter::new(
            config(NavFrame::Local, AssociationMode::Descriptor),
            &[vehicle(Vector3::new(0.0, 0.0, -100.0))],
        )
        .unwrap();
        f.config.origin = Vector3::new(rng.random_range(-5.0..5.0), 2.0, -1.0);
        // Every fourth trial covers a larger whole map (the map-information route needs the
        // delta to span at least half of the 15 + 3N states).
        let n_feat = if trial % 4 == 0 {
            rng.random_range(8..12)
        } else {
            rng.random_range(1..8)
        };
        randomize(&mut f, n_feat, &mut rng);
        if trial % 2 == 0 {
            f.predict(0, &imu(0.0)).unwrap();
        }
        let keep = if trial % 4 == 0 { 1.0 } else { 0.5 };
        let mut ids: Vec<FeatureId> = (0..n_feat as u64)
            .map(|i| 100 + i)
            .filter(|_| rng.random_bool(keep))
            .collect();
        for j in 0..rng.random_range(0..3) {
            ids.push(500 + j);
        }
        if ids.is_empty() {
            ids.push(100);
        }
        // Shuffle the delta order.
        for i in (1..ids.len()).rev() {
            ids.swap(i, rng.random_range(0..=i));
        }
        let k = 3 * ids.len();
        let mut y = match trial % 3 {
            0 => random_spd(k, 1.0, &mut rng),
            1 => {
                let r = rng.random_range(1..=k);
                let u = DMatrix::from_fn(k, r, |_, _| rng.random::<f64>() - 0.5);
                &u * u.transpose()
            }
            _ => {
                let u = DVector::from_fn(k, |_, _| rng.random::<f64>() - 0.5).normalize();
                random_spd(k, 1.0, &mut rng) - &u * u.transpose() * 0.02
            }
        };
        // New features need positive definite information of their own.
        for (b, id) in ids.iter().enumerate() {
            if *id >= 500 {
                for i in 0..3 {
                    y[(3 * b + i, 3 * b + i)] += 1.0;
                }
            }
        }
        let target = DVector::from_fn(k, |_, _| rng.random_range(-30.0..30.0));
        let d = delta(ids.clone(), y, &target, f.origin());
        let (x_ref, p_ref) = dense_fusion_reference(&f, &d);
        match f.fuse_map_information(&d) {
            Ok(rep) => {
                routes[rep.method as usize] += 1;
                let p = to_dense(&f.p);
                let x = col_to_dense(&f.x);
                // Well-conditioned ≤ 40×40 problems (κ ≲ 1e4 after low-rank/indefinite
                // deltas): 1e-8 relative on P and x covers the dense inverse's round-off.
                assert!(
                    (&p - &p_ref).abs().max() < 1e-8 * p_ref.abs().max(),
                    "trial {trial}: P"
                );
                assert!(
                    (&x - &x_ref).abs().max() < 1e-8 * x_ref.abs().max(),
                    "trial {trial}: x"
                );
            }
            // A rejected delta must really make the fused information indefinite.
            Err(e) => {
                let eig = p_ref.clone().symmetric_eigenvalues();
                assert!(
                    eig.min() <= 0.0,
                    "trial {trial}: rejected a PD fusion: {e:?}"
                );
            }
        }
    }
    // Both routes (and trials with only new features) were exercised.
    println!("fusion routes (none, pseudo, map): {routes:?}");
    assert!(
        routes[FuseMethod::PseudoMeasurement as usize] > 5
            && routes[FuseMethod::MapInformation as usize] > 5,
        "{routes:?}"
    );
}

/// The cached map information is maintained incrementally (Woodbury for updates, the bordered
/// inverse for augmentations, Y + ΔY for fusions) — not re-inverted — and equals an independent
/// dense inverse of P_mm after each kind of change.
#[test]
fn map_information_is_maintained_without_reinversion() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut f = random_local_filter(5, &mut rng);
    f.map_information().unwrap();
    assert_eq!(f.info_cache.steps, 0);
    let cached_matches_dense = |f: &SlamFilter, what: &str| {
        assert!(f.info_cache_current(), "{what}: cache not maintained");
        let (_, y, _) = marginal_information(f);
        let c = to_dense(f.info_cache.y.as_ref().unwrap());
        // Independent nalgebra inverse of P_mm, κ ≲ 1e3, a few rank updates: 1e-10 relative.
        let err = (&c - &y).abs().max() / y.abs().max();
        assert!(err < 1e-10, "{what}: relative error {err:e}");
    };
    let mut steps = 0;
    for round in 0..4 {
        let est = f.vehicle_state(0).unwrap();
        let ids: Vec<FeatureId> = f.features().iter().map(|(id, _)| *id).take(3).collect();
        let observations = ids
            .iter()
            .map(|&id| {
                let z = observe(&f, 0, &est, &f.feature(id).unwrap());
                Observation {
                    descriptor: id,
                    z: rb(&(z + DVector::from_vec(vec![0.1, 0.0005, -0.0005]))),
                    appearance: None,
                }
            })
            .chain([Observation {
                descriptor: 200 + round,
                z: rb(&DVector::from_vec(vec![
                    80.0 + 5.0 * round as f64,
                    0.2,
                    -0.3,
                ])),
                appearance: None,
            }])
            .collect();
        let r = f
            .process_frame(
                0,
                &ObservationFrame {
                    time: 0.0,
                    observations,
                },
            )
            .unwrap();
        assert_eq!((r.associated(), r.initialized()), (3, 1));
        assert!(
            f.info_cache.steps > steps,
            "round {round}: the update was not incremental"
        );
        steps = f.info_cache.steps;
        cached_matches_dense(&f, "update + augmentation");
        for _ in 0..10 {
            f.predict(0, &imu(0.0)).unwrap();
        }
        let known = f.features()[0].0;
        let d = delta(
            vec![known, 300 + round],
            random_spd(6, 0.5, &mut rng),
            &DVector::zeros(6),
            Vector3::zeros(),
        );
        f.fuse_map_information(&d).unwrap();
        assert!(
            f.info_cache.steps > steps,
            "round {round}: the fusion was not incremental"
        );
        steps = f.info_cache.steps;
        cached_matches_dense(&f, "fusion with a new feature");
        // map_information serves the maintained inverse (probe passes, no re-inversion).
        f.map_information().unwrap();
        assert_eq!(f.info_cache.steps, steps);
        // A delta on all features but one takes the map-information route with Y_aa from the
        // cache's Schur complement; the fused filter must agree with its maintained inverse.
        let ids: Vec<FeatureId> = f.features().iter().map(|(id, _)| *id).skip(1).collect();
        let k = 3 * ids.len();
        let d = delta(
            ids,
            random_spd(k, 0.2, &mut rng),
            &DVector::zeros(k),
            Vector3::zeros(),
        );
        let rep = f.fuse_map_information(&d).unwrap();
        assert_eq!(rep.method, FuseMethod::MapInformation, "round {round}");
        steps = f.info_cache.steps;
        cached_matches_dense(&f, "map route on a subset");
    }
}

/// How the attitude and bias states (rows 6..15) of the randomised joint covariance relate to
/// the rest in [`deferred_vs_sequential`].
#[derive(Clone, Copy)]
enum AttitudeCoupling {
    /// Uncorrelated with position, velocity and map: a fusion leaves their means unchanged.
    None,
    /// Correlated, scaled by this factor (σ of a few mrad for 1e-3 instead of ~0.7 rad).
    Scaled(f64),
}

/// Deferred fusion (module `deferred`): fuse a delta into a snapshot while a vehicle part is
/// predicted, then carry the predictions over; against sequential processing (fuse, then
/// predict the same samples) on the same filter. Returns (sequential, deferred).
fn deferred_vs_sequential(
    samples: &[ImuSample],
    seed: u64,
    coupling: AttitudeCoupling,
) -> (SlamFilter, SlamFilter) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut f = random_local_filter(6, &mut rng);
    let n = f.dim();
    let attitude_bias = |i: usize| (ATT..VEHICLE_DIM).contains(&i);
    for j in 0..n {
        for i in 0..n {
            let v = f.p[(i, j)];
            f.p[(i, j)] = match (coupling, attitude_bias(i), attitude_bias(j)) {
                (_, false, false) => v,
                (AttitudeCoupling::None, a, b) if a != b => 0.0,
                (AttitudeCoupling::None, _, _) => v,
                (AttitudeCoupling::Scaled(s), true, true) => v * s * s,
                (AttitudeCoupling::Scaled(s), _, _) => v * s,
            };
        }
    }
    f.predict(0, &imu(0.0)).unwrap(); // a pending transition the part must flush first
    // Known features and two new ones, so the fused snapshot has another layout.
    let ids: Vec<FeatureId> = vec![100, 101, 900, 103, 104, 105, 901];
    let k = 3 * ids.len();
    let d = delta(
        ids,
        random_spd(k, 2.0, &mut rng),
        &DVector::from_fn(k, |_, _| rng.random_range(-50.0..50.0)),
        f.origin(),
    );
    let mut sequential = f.clone();
    sequential.fuse_map_information(&d).unwrap();
    for s in samples {
        sequential.predict(0, s).unwrap();
    }
    // The estimator keeps predicting with its own filter while the snapshot is fused.
    let before = f.vehicle_part();
    let mut snapshot = f.clone();
    for s in samples {
        f.predict(0, s).unwrap();
    }
    snapshot.fuse_map_information(&d).unwrap();
    snapshot.carry_predictions(&before, &f).unwrap();
    (sequential, snapshot)
}

/// When the fusion leaves the states ∇F depends on unchanged (local frame: attitude and biases
/// uncorrelated with what the delta informs, so their means stay; zero specific force and rate)
/// both paths linearise the samples at the same points, and carrying predictions over is
/// exactly sequential processing: same layout, mean and joint covariance to round-off (1e-12
/// relative: the same products grouped differently).
#[test]
fn deferred_fusion_equals_sequential_for_state_independent_transitions() {
    let samples: Vec<ImuSample> = (1..=25)
        .map(|k| ImuSample {
            time: 0.01 * f64::from(k),
            dt: 0.01,
            specific_force: Vector3::zeros(),
            angular_rate: Vector3::zeros(),
        })
        .collect();
    let (a, b) = deferred_vs_sequential(&samples, 31, AttitudeCoupling::None);
    assert_eq!(a.layout().dim(), b.layout().dim());
    assert_eq!(
        a.features().iter().map(|f| f.0).collect::<Vec<_>>(),
        b.features().iter().map(|f| f.0).collect::<Vec<_>>()
    );
    let (pa, pb) = (
        to_dense(&a.joint_covariance()),
        to_dense(&b.joint_covariance()),
    );
    let err = (&pa - &pb).abs().max() / pa.abs().max();
    assert!(err < 1e-12, "covariance differs by {err:e} relative");
    let (xa, xb) = (col_to_dense(&a.x), col_to_dense(&b.x));
    let err = (&xa - &xb).abs().max() / xa.abs().max();
    assert!(err < 1e-12, "mean differs by {err:e} relative");
    // The map part is the fused snapshot's, untouched by the predictions: bit for bit.
    let (ma, mb) = (a.map_marginal(), b.map_marginal());
    assert_eq!(to_dense(&ma.covariance), to_dense(&mb.covariance));
}

/// With a real IMU (rotating, accelerating: ∇F depends on the attitude and specific force)
/// the deferred result differs from sequential processing only by where the later samples
/// are linearised (the pre-fusion rather than the fused estimate): the map marginal is bit
/// for bit the same, and the vehicle block and cross terms agree to first order in the fused
/// change of the vehicle estimate. Attitude σ of a few mrad, 0.25 s of samples: measured
/// 9e-8 relative on the covariance, 3e-7 m and 3e-6 m/s on the mean; bounds 100× that.
#[test]
fn deferred_fusion_matches_sequential_to_first_order() {
    let samples: Vec<ImuSample> = (1..=25).map(|k| imu(0.01 * f64::from(k))).collect();
    let (a, b) = deferred_vs_sequential(&samples, 32, AttitudeCoupling::Scaled(1e-3));
    let (ma, mb) = (a.map_marginal(), b.map_marginal());
    assert_eq!(to_dense(&ma.covariance), to_dense(&mb.covariance));
    assert_eq!(col_to_dense(&ma.mean), col_to_dense(&mb.mean));
    let (pa, pb) = (
        to_dense(&a.joint_covariance()),
        to_dense(&b.joint_covariance()),
    );
    let err = (&pa - &pb).abs().max() / pa.abs().max();
    eprintln!("deferred vs sequential, covariance: {err:e} relative");
    assert!(err < 1e-5, "covariance differs by {err:e} relative");
    let (va, vb) = (a.vehicle_state(0).unwrap(), b.vehicle_state(0).unwrap());
    let dp = (va.position - vb.position).norm();
    let dv = (va.velocity - vb.velocity).norm();
    eprintln!("deferred vs sequential, mean: {dp:e} m, {dv:e} m/s");
    assert!(dp < 3e-5 && dv < 3e-4, "mean differs: {dp} m, {dv} m/s");
}

/// The contract is checked: a part with a pending transition as `before`, or a full filter
/// where a part is expected, is an error and changes nothing.
#[test]
fn carry_predictions_rejects_what_is_not_a_vehicle_part() {
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    let mut f = random_local_filter(3, &mut rng);
    let before = f.vehicle_part();
    let mut predicted = before.clone();
    predicted.predict(0, &imu(0.01)).unwrap();
    let bits = snapshot(&f);
    // A part with a pending transition, or a full filter, as `before`.
    assert!(f.clone().carry_predictions(&predicted, &predicted).is_err());
    let full = f.clone();
    assert!(f.carry_predictions(&full, &predicted).is_err());
    // `since` changed by more than prediction (a frame or fusion bumps its map generation).
    let mut changed = full.clone();
    let d = delta(
        vec![100],
        random_spd(3, 1.0, &mut rng),
        &DVector::from_element(3, 1.0),
        changed.origin(),
    );
    changed.fuse_map_information(&d).unwrap();
    assert!(f.carry_predictions(&before, &changed).is_err());
    assert_eq!(snapshot(&f), bits);
    assert!(f.carry_predictions(&before, &predicted).is_ok());
    // The filter the part was taken from, predicted, serves as `since` too.
    let mut g = full.clone();
    let before = g.vehicle_part();
    let mut snap = g.clone();
    g.predict(0, &imu(0.02)).unwrap();
    assert!(snap.carry_predictions(&before, &g).is_ok());
    assert_eq!(
        to_dense(&snap.joint_covariance()),
        to_dense(&g.joint_covariance())
    );
}

/// A random submap over `known` existing feature ids and `new` unseen ones (ids 900..), in the
/// filter's origin: means near the filter's estimates, covariance S Sᵀ + 0.3 I.
fn random_submap(
    f: &SlamFilter,
    known: &[FeatureId],
    new: usize,
    rng: &mut ChaCha8Rng,
) -> crate::ci::Submap {
    let ids: Vec<FeatureId> = known
        .iter()
        .copied()
        .chain((0..new).map(|k| 900 + k as FeatureId))
        .collect();
    let n = 3 * ids.len();
    let s = DMatrix::from_fn(n, n, |_, _| rng.random::<f64>() - 0.5);
    let p = &s * s.transpose() + DMatrix::identity(n, n) * 0.3;
    let mut packed = Vec::new();
    for j in 0..n {
        for i in 0..=j {
            packed.push(p[(i, j)]);
        }
    }
    let origin = f.origin();
    let offset_mean = (0..n)
        .map(|r| {
            let base = f
                .feature(ids[r / 3])
                .map_or(rng.random_range(-50.0..50.0), |m| m[r % 3]);
            base + rng.random_range(-1.0..1.0) - origin[r % 3]
        })
        .collect();
    crate::ci::Submap {
        ids,
        origin: origin.into(),
        offset_mean,
        covariance_packed: packed,
    }
}

/// The dense information-form CI of the filter's joint with an embedded submap at weight ω:
/// Y' = ω Y + (1 − ω) E B Eᵀ, y' = ω Y x + (1 − ω) E B μ (new features appended after the
/// filter's states, in submap order). Returns (x', P', ids of the appended features).
fn dense_ci(
    f: &SlamFilter,
    s: &crate::ci::Submap,
    omega: f64,
) -> (DVector<f64>, DMatrix<f64>, Vec<FeatureId>) {
    let p = f.joint_covariance();
    let n = p.nrows();
    let x = f.state_vector();
    let new: Vec<FeatureId> = s
        .ids
        .iter()
        .copied()
        .filter(|id| f.layout().feature_offset(*id).is_none())
        .collect();
    let m = n + 3 * new.len();
    let p = DMatrix::from_fn(n, n, |i, j| p[(i, j)]);
    let y = p.clone().try_inverse().unwrap();
    let mut big = DMatrix::zeros(m, m);
    big.view_mut((0, 0), (n, n)).copy_from(&(&y * omega));
    let xv = DVector::from_fn(n, |i, _| x[i]);
    let mut vec = DVector::zeros(m);
    vec.rows_mut(0, n).copy_from(&(&y * &xv * omega));
    let row_of = |id: FeatureId| -> usize {
        f.layout()
            .feature_offset(id)
            .unwrap_or_else(|| n + 3 * new.iter().position(|&u| u == id).unwrap())
    };
    let ps = s.covariance();
    let ns = ps.nrows();
    let b = DMatrix::from_fn(ns, ns, |i, j| ps[(i, j)])
        .try_inverse()
        .unwrap();
    let mu = DVector::from_fn(ns, |i, _| s.offset_mean[i] + s.origin[i % 3]);
    let bmu = &b * mu;
    let rows: Vec<usize> = (0..ns).map(|r| row_of(s.ids[r / 3]) + r % 3).collect();
    for i in 0..ns {
        vec[rows[i]] += (1.0 - omega) * bmu[i];
        for j in 0..ns {
            big[(rows[i], rows[j])] += (1.0 - omega) * b[(i, j)];
        }
    }
    let cov = big.try_inverse().unwrap();
    let mean = &cov * vec;
    (mean, (&cov + cov.transpose()) * 0.5, new)
}

/// Covariance-form CI of a submap (Kalman update of the ω-scaled prior, new features through
/// the submap's conditional) equals the dense information-form CI of the joint at the same ω,
/// for known-only, new-only and mixed submaps, both criteria; the chosen ω is the minimum of
/// the criterion evaluated densely on a fine grid; bad submaps change nothing.
#[test]
fn covariance_form_ci_equals_the_dense_information_form() {
    use crate::ci::CiCriterion;
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for (known, new) in [(vec![100, 103, 104], 0), (vec![], 2), (vec![101, 105], 3)] {
        for criterion in [CiCriterion::Trace, CiCriterion::Determinant] {
            let mut f = random_local_filter(6, &mut rng);
            let s = random_submap(&f, &known, new, &mut rng);
            let (p_before, x_before) = (f.joint_covariance(), f.state_vector());
            let report = f.fuse_submap_ci(&s, criterion).unwrap();
            assert_eq!((report.known, report.added), (known.len(), new));
            let (want_x, want_p, appended) =
                dense_ci_of(&p_before, &x_before, &f, &s, report.omega);
            let got_p = f.joint_covariance();
            let got_x = f.state_vector();
            // Old state i keeps its index; appended features map through the layout.
            let n_old = p_before.nrows();
            let idx: Vec<usize> = (0..n_old)
                .chain(appended.iter().flat_map(|id| {
                    let o = f.layout().feature_offset(*id).unwrap();
                    o..o + 3
                }))
                .collect();
            let scale = want_p.abs().max();
            for (a, &i) in idx.iter().enumerate() {
                // Dense inversions of matrices with condition ~1e3: 1e-9 relative.
                assert!(
                    (got_x[i] - want_x[a]).abs() < 1e-8,
                    "{known:?}+{new} x[{a}]"
                );
                for (b, &j) in idx.iter().enumerate() {
                    assert!(
                        (got_p[(i, j)] - want_p[(a, b)]).abs() < 1e-9 * scale,
                        "{known:?}+{new} {criterion:?} P[{a},{b}] {} vs {}",
                        got_p[(i, j)],
                        want_p[(a, b)]
                    );
                }
            }
            // ω is the criterion's minimum: no grid point does better (beyond the search's
            // tolerance, 1e-9 relative).
            let objective = |omega: f64| {
                let g = SlamFilter::clone(&f);
                let (_, p, app) = dense_ci_of(&p_before, &x_before, &g, &s, omega);
                let map: Vec<usize> = (0..n_old)
                    .filter(|&i| i >= VEHICLE_DIM)
                    .chain((0..3 * app.len()).map(|k| n_old + k))
                    .collect();
                let pm = DMatrix::from_fn(map.len(), map.len(), |i, j| p[(map[i], map[j])]);
                match criterion {
                    CiCriterion::Trace => pm.trace(),
                    CiCriterion::Determinant => pm.determinant().ln(),
                }
            };
            let at = objective(report.omega);
            for k in 1..200 {
                let w = k as f64 / 200.0;
                assert!(
                    at <= objective(w) + 1e-9 * at.abs().max(1.0),
                    "{known:?}+{new} {criterion:?}: ω = {} gives {at}, ω = {w} gives {}",
                    report.omega,
                    objective(w)
                );
            }
        }
    }
    // Invalid submaps: nothing changes.
    let mut f = random_local_filter(4, &mut rng);
    let before = snapshot(&f);
    let good = random_submap(&f, &[100, 101], 1, &mut rng);
    let mut nan = good.clone();
    nan.offset_mean[2] = f64::NAN;
    let mut not_pd = good.clone();
    not_pd.covariance_packed[0] = -1.0;
    let mut moved = good.clone();
    moved.origin[0] += 1.0;
    for bad in [nan, not_pd, moved] {
        assert!(
            f.fuse_submap_ci(&bad, crate::ci::CiCriterion::Trace)
                .is_err()
        );
        assert_eq!(snapshot(&f), before);
    }
}

/// [`dense_ci`] from a saved joint (the filter `f` is only used for its layout: the old states
/// keep their indices and new features are appended in submap order).
fn dense_ci_of(
    p: &Mat<f64>,
    x: &Col<f64>,
    f: &SlamFilter,
    s: &crate::ci::Submap,
    omega: f64,
) -> (DVector<f64>, DMatrix<f64>, Vec<FeatureId>) {
    let n = p.nrows();
    let new: Vec<FeatureId> = s
        .ids
        .iter()
        .copied()
        .filter(|id| f.layout().feature_offset(*id).is_none_or(|o| o >= n))
        .collect();
    let mut g = f.clone();
    g.x = x.clone();
    g.p = p.clone();
    for id in &new {
        let _ = g.layout.remove(SlotKind::Feature(*id));
    }
    let (mean, cov, app) = dense_ci(&g, s, omega);
    debug_assert_eq!(app, new);
    (mean, cov, app)
}

/// A merge of two features equals the dense re-keying of the joint information Y' = Tᵀ Y T,
/// y' = Tᵀ y (design.md §8: condition on x_from = x_into, marginalise x_from); a merge of a key
/// the filter holds alone renames it; unknown keys change nothing.
#[test]
fn merging_features_equals_the_dense_re_keying() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut f = random_local_filter(5, &mut rng);
    let (from, into) = (103, 101);
    let p = f.joint_covariance();
    let n = p.nrows();
    let p = DMatrix::from_fn(n, n, |i, j| p[(i, j)]);
    let x = f.state_vector();
    let x = DVector::from_fn(n, |i, _| x[i]);
    let y = p.clone().try_inverse().unwrap();
    let (a, b) = (
        f.layout().feature_offset(from).unwrap(),
        f.layout().feature_offset(into).unwrap(),
    );
    // T: n × (n − 3); old state i ← new state t(i); `from`'s rows read `into`'s.
    let keep: Vec<usize> = (0..n).filter(|i| !(a..a + 3).contains(i)).collect();
    let mut t = DMatrix::zeros(n, n - 3);
    for (c, &i) in keep.iter().enumerate() {
        t[(i, c)] = 1.0;
    }
    let b_new = keep.iter().position(|&i| i == b).unwrap();
    for k in 0..3 {
        t[(a + k, b_new + k)] = 1.0;
    }
    let y_new = t.transpose() * &y * &t;
    let p_want = y_new.clone().try_inverse().unwrap();
    let x_want = &p_want * (t.transpose() * (&y * &x));
    f.merge_features(&crate::keys::Merge { from, into })
        .unwrap();
    assert!(f.layout().feature_offset(from).is_none());
    let p_got = f.joint_covariance();
    let x_got = f.state_vector();
    let scale = p_want.abs().max();
    for i in 0..n - 3 {
        // Dense inversions of a ~30-state joint with condition ~10: 1e-10 relative.
        assert!(
            (x_got[i] - x_want[i]).abs() < 1e-9 * (1.0 + x_want[i].abs()),
            "x[{i}]"
        );
        for j in 0..n - 3 {
            assert!(
                (p_got[(i, j)] - p_want[(i, j)]).abs() < 1e-10 * scale,
                "P[{i},{j}]"
            );
        }
    }
    // Rename and no-op.
    let before = snapshot(&f);
    f.merge_features(&crate::keys::Merge {
        from: 999,
        into: 998,
    })
    .unwrap();
    assert_eq!(snapshot(&f), before);
    let off = f.layout().feature_offset(104).unwrap();
    f.merge_features(&crate::keys::Merge {
        from: 104,
        into: 50,
    })
    .unwrap();
    assert_eq!(f.layout().feature_offset(50), Some(off));
    assert!(f.layout().feature_offset(104).is_none());
}

/// The vehicle process hands its filter to the fusion thread and predicts on
/// [`SlamFilter::vehicle_only`] meanwhile, then applies the same samples to the fused filter:
/// bit for bit what fusing at the round time and predicting afterwards on one filter gives, and
/// the part's vehicle estimate is the unfused filter's while it stands in.
#[test]
fn handing_over_and_replaying_predictions_is_sequential_bit_for_bit() {
    let mut rng = ChaCha8Rng::seed_from_u64(151);
    let mut f = random_local_filter(6, &mut rng);
    f.predict(0, &imu(0.0)).unwrap(); // a pending transition stays with the filter handed over
    let ids: Vec<FeatureId> = vec![100, 101, 900, 103, 104, 105, 901];
    let k = 3 * ids.len();
    let d = delta(
        ids,
        random_spd(k, 2.0, &mut rng),
        &DVector::from_fn(k, |_, _| rng.random_range(-50.0..50.0)),
        f.origin(),
    );
    let samples: Vec<ImuSample> = (1..=25).map(|s| imu(0.01 * f64::from(s))).collect();
    let mut sequential = f.clone();
    let mut unfused = f.clone();
    sequential.fuse_map_information(&d).unwrap();
    for s in &samples {
        sequential.predict(0, s).unwrap();
        unfused.predict(0, s).unwrap();
    }
    let mut part = f.vehicle_only();
    let mut handed = f;
    for s in &samples {
        part.predict(0, s).unwrap();
    }
    assert_eq!(
        part.vehicle_state(0).unwrap().to_vector(),
        unfused.vehicle_state(0).unwrap().to_vector()
    );
    assert_eq!(
        part.vehicle_covariance(0).unwrap(),
        unfused.vehicle_covariance(0).unwrap()
    );
    handed.fuse_map_information(&d).unwrap();
    for s in &samples {
        handed.predict(0, s).unwrap();
    }
    assert_eq!(col_to_dense(&handed.x), col_to_dense(&sequential.x));
    assert_eq!(
        to_dense(&handed.joint_covariance()),
        to_dense(&sequential.joint_covariance())
    );
}

/// The round's map information lent out of the filter ([`SlamFilter::take_map_information`])
/// is the copy [`SlamFilter::map_information`] returns, bit for bit; given back unchanged it is
/// the maintained Y again (no re-inversion: the next copy is the same bits); given back after
/// the map changed (or with other features) it is dropped.
#[test]
fn map_information_lent_and_given_back() {
    let mut rng = ChaCha8Rng::seed_from_u64(152);
    let mut f = random_local_filter(5, &mut rng);
    let copy = f.map_information().unwrap();
    let taken = f.take_map_information().unwrap();
    assert!(f.info_cache.y.is_none());
    assert_eq!(taken.ids, copy.ids);
    assert_eq!(to_dense(&taken.matrix), to_dense(&copy.matrix));
    assert_eq!(col_to_dense(&taken.vector), col_to_dense(&copy.vector));
    f.restore_map_information(taken);
    assert!(f.info_cache_current());
    let again = f.map_information().unwrap();
    assert_eq!(to_dense(&again.matrix), to_dense(&copy.matrix));
    // The map changed while Y was out: what comes back is stale and dropped.
    let taken = f.take_map_information().unwrap();
    f.forget_features(&[102]);
    f.restore_map_information(taken);
    assert!(f.info_cache.y.is_none());
    // Other features than the map's: dropped.
    let mut wrong = f.take_map_information().unwrap();
    wrong.ids.swap(0, 1);
    f.restore_map_information(wrong);
    assert!(f.info_cache.y.is_none());
}

/// Fusing a delta by value is fusing it by reference, bit for bit, whatever its order (it is
/// put in the filter's order either way); a delta refused before anything changed comes back
/// with the error, the same information in the filter's order.
#[test]
fn fusing_by_value_equals_fusing_by_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(153);
    let base = random_local_filter(6, &mut rng);
    // The whole map in another order (the batch path), and the whole map plus new features.
    for ids in [
        vec![105u64, 100, 103, 101, 104, 102],
        vec![100, 101, 102, 103, 104, 105],
        vec![104, 900, 100, 101, 102, 103, 105, 901],
    ] {
        let k = 3 * ids.len();
        let d = delta(
            ids.clone(),
            random_spd(k, 2.0, &mut rng),
            &DVector::from_fn(k, |_, _| rng.random_range(-50.0..50.0)),
            base.origin(),
        );
        let (mut by_ref, mut by_value) = (base.clone(), base.clone());
        by_ref.map_information().unwrap(); // both with the maintained Y
        by_value.map_information().unwrap();
        let a = by_ref.fuse_map_information(&d).unwrap();
        let b = by_value.fuse_map_information_owned(d).unwrap();
        assert_eq!(a, b);
        assert_eq!(col_to_dense(&by_ref.x), col_to_dense(&by_value.x));
        assert_eq!(to_dense(&by_ref.p), to_dense(&by_value.p));
        let (ya, yb) = (
            by_ref.map_information().unwrap(),
            by_value.map_information().unwrap(),
        );
        assert_eq!(to_dense(&ya.matrix), to_dense(&yb.matrix), "{ids:?}");
    }
    // Taking away more than the filter holds: not positive definite, refused, handed back.
    let mut f = base.clone();
    let y = f.map_information().unwrap();
    let ids = vec![102u64, 100, 101, 103, 104, 105];
    let order: Vec<usize> = ids
        .iter()
        .flat_map(|id| {
            let b = y.index_of(*id).unwrap();
            3 * b..3 * b + 3
        })
        .collect();
    let k = order.len();
    let d = MapInformation {
        ids,
        origin: y.origin,
        matrix: Mat::from_fn(k, k, |i, j| -2.0 * y.matrix[(order[i], order[j])]),
        vector: Col::from_fn(k, |i| -2.0 * y.vector[order[i]]),
    };
    let before = (col_to_dense(&f.x), to_dense(&f.p));
    let (e, back) = *f.fuse_map_information_owned(d.clone()).unwrap_err();
    assert!(matches!(e, SlamError::NotPositiveDefinite(_)), "{e:?}");
    let back = back.expect("refused before any change: the delta comes back");
    assert_eq!(back.ids, y.ids, "in the filter's order");
    let expect = d.restrict(&y.ids);
    assert_eq!(to_dense(&back.matrix), to_dense(&expect.matrix));
    assert_eq!(col_to_dense(&back.vector), col_to_dense(&expect.vector));
    assert_eq!((col_to_dense(&f.x), to_dense(&f.p)), before);
    // The same with a new feature in the delta (its known block is fused in the delta's own
    // buffer, `SplitDelta`): refused after that buffer was used, the delta comes back whole,
    // bit for bit, known features first in the filter's order, then the new one.
    let mut with_new = d.restrict(&y.ids);
    let k = with_new.matrix.nrows();
    let mut m = Mat::<f64>::zeros(k + 3, k + 3);
    m.as_mut()
        .submatrix_mut(0, 0, k, k)
        .copy_from(&with_new.matrix);
    for i in 0..3 {
        m[(k + i, k + i)] = 4.0 + i as f64;
        for j in 0..k {
            let v = 0.01 * ((i + 2 * j) % 7) as f64;
            m[(k + i, j)] = v;
            m[(j, k + i)] = v;
        }
    }
    with_new.ids.push(900);
    with_new.matrix = m;
    with_new.vector = Col::from_fn(k + 3, |i| if i < k { with_new.vector[i] } else { 1.5 });
    let shuffled = with_new.restrict(&[900, 104, 100, 105, 101, 103, 102]);
    let (e, back) = *f.fuse_map_information_owned(shuffled).unwrap_err();
    assert!(matches!(e, SlamError::NotPositiveDefinite(_)), "{e:?}");
    let back = back.expect("refused before any change: the delta comes back");
    assert_eq!(
        back.ids, with_new.ids,
        "known in the filter's order, then the new one"
    );
    assert_eq!(to_dense(&back.matrix), to_dense(&with_new.matrix));
    assert_eq!(col_to_dense(&back.vector), col_to_dense(&with_new.vector));
    assert_eq!((col_to_dense(&f.x), to_dense(&f.p)), before);
}

/// A batch that misses a few of the map's features (the vehicle's own newest ones, which no
/// neighbour holds yet) is fused as a whole-map delta with zero information on them
/// (`in_filter_order`): the result equals the dense information-form reference (an independent
/// nalgebra inverse of the joint information plus ΔY), the maintained map information equals
/// a dense inverse of the fused P_mm, and the route taken is the map route over the whole
/// map. With and without new features in the batch, and in a shuffled order.
#[test]
fn a_batch_missing_a_few_features_is_fused_as_a_whole_map_delta() {
    let mut rng = ChaCha8Rng::seed_from_u64(33);
    for (trial, new_features) in [0u64, 2, 0, 3].into_iter().enumerate() {
        let mut f = random_local_filter(40, &mut rng);
        f.map_information().unwrap();
        assert!(f.info_cache_current());
        // Two features missing (40 ≥ 16 × 2), the rest in a shuffled order, then new ones.
        let mut ids: Vec<FeatureId> = (100..140).filter(|id| *id != 107 && *id != 131).collect();
        for i in (1..ids.len()).rev() {
            ids.swap(i, rng.random_range(0..=i));
        }
        ids.extend((0..new_features).map(|j| 900 + j));
        let k = 3 * ids.len();
        let y = if trial % 2 == 0 {
            random_spd(k, 1.0, &mut rng)
        } else {
            // Low rank on the known features, positive definite on the new ones.
            let u = DMatrix::from_fn(k, 12, |_, _| rng.random::<f64>() - 0.5);
            let mut y = &u * u.transpose();
            for i in k - 3 * new_features as usize..k {
                y[(i, i)] += 1.0;
            }
            y
        };
        let target = DVector::from_fn(k, |_, _| rng.random_range(-30.0..30.0));
        let d = delta(ids, y, &target, f.origin());
        let (x_ref, p_ref) = dense_fusion_reference(&f, &d);
        let rep = f.fuse_map_information(&d).unwrap();
        assert_eq!(rep.method, FuseMethod::MapInformation, "trial {trial}");
        // Counted over the padded delta: every map feature.
        assert_eq!(
            rep.known_features, 40,
            "trial {trial}: not fused as a whole-map delta"
        );
        assert_eq!(rep.new_features.len(), new_features as usize);
        // ≤ 140 states, κ ≲ 1e3: 1e-8 relative covers the dense inverses' round-off (as in
        // `randomized_fusions_match_the_dense_information_form`).
        let p = to_dense(&f.p);
        let x = col_to_dense(&f.x);
        let ep = (&p - &p_ref).abs().max() / p_ref.abs().max();
        let ex = (&x - &x_ref).abs().max() / x_ref.abs().max();
        assert!(ep < 1e-8 && ex < 1e-8, "trial {trial}: P {ep:e}, x {ex:e}");
        assert!(
            f.info_cache_current(),
            "trial {trial}: map information not kept"
        );
        let (_, y_dense, _) = marginal_information(&f);
        let c = to_dense(f.info_cache.y.as_ref().unwrap());
        let ey = (&c - &y_dense).abs().max() / y_dense.abs().max();
        assert!(ey < 1e-8, "trial {trial}: maintained Y off by {ey:e}");
    }
}

/// A positive definite, exactly symmetric ((Y + Yᵀ)/2) delta on `ids` with a random target.
fn exact_random_delta(
    ids: Vec<FeatureId>,
    origin: Vector3<f64>,
    rng: &mut ChaCha8Rng,
) -> MapInformation {
    let k = 3 * ids.len();
    let y = random_spd(k, 1.0, rng);
    let y = (&y + y.transpose()) * 0.5;
    let target = DVector::from_fn(k, |_, _| rng.random_range(-30.0..30.0));
    delta(ids, y, &target, origin)
}

/// A vehicle's packed batch unpacked straight into the filter's order
/// (`dense_in_filter_order`) is the dense batch put in that order (`in_filter_order`), bit for
/// bit: padded (two map features missing, the cache current), with and without new features,
/// shuffled; not padded (cache not current; too many missing); and already in order (no gather).
/// The reference is the existing dense path: unpacking then gathering, which only copies.
#[test]
fn a_packed_batch_unpacks_into_the_filter_order_as_the_dense_batch_does() {
    let mut rng = ChaCha8Rng::seed_from_u64(35);
    // (map features, new features, missing ids, shuffle, cache current)
    let cases: [(usize, u64, &[u64], bool, bool); 6] = [
        (40, 0, &[107, 131], true, true),
        (40, 3, &[107, 131], true, true),
        (40, 2, &[107, 131], true, false),
        (40, 1, &[101, 102, 103, 104, 105, 106], true, true),
        (40, 0, &[], false, true),
        (40, 2, &[], false, true),
    ];
    for (trial, &(nf, new_features, missing, shuffle, current)) in cases.iter().enumerate() {
        let mut f = random_local_filter(nf, &mut rng);
        if current {
            f.map_information().unwrap();
        }
        assert_eq!(f.info_cache_current(), current, "trial {trial}");
        let mut ids: Vec<FeatureId> = (100..100 + nf as u64)
            .filter(|id| !missing.contains(id))
            .collect();
        if shuffle {
            for i in (1..ids.len()).rev() {
                ids.swap(i, rng.random_range(0..=i));
            }
        }
        ids.extend((0..new_features).map(|j| 900 + j));
        let d = exact_random_delta(ids, f.origin(), &mut rng);
        let packed = crate::ddf::PackedInformation::from_dense(&d).unwrap();
        let got = f.dense_in_filter_order(&packed);
        let want = f.in_filter_order(d.clone());
        assert_eq!(got.ids, want.ids, "trial {trial}: order");
        assert_eq!(got.origin, want.origin, "trial {trial}");
        assert_eq!(
            (got.matrix.nrows(), got.matrix.ncols()),
            (want.matrix.nrows(), want.matrix.ncols()),
            "trial {trial}"
        );
        for j in 0..want.matrix.ncols() {
            for i in 0..want.matrix.nrows() {
                assert_eq!(
                    got.matrix[(i, j)].to_bits(),
                    want.matrix[(i, j)].to_bits(),
                    "trial {trial}: ({i}, {j})"
                );
            }
        }
        for i in 0..want.vector.nrows() {
            assert_eq!(
                got.vector[i].to_bits(),
                want.vector[i].to_bits(),
                "trial {trial}"
            );
        }
        // The cases reach the routes they name: padded to the whole map or not.
        let padded = current && missing.len() == 2;
        assert_eq!(
            want.ids.len(),
            if padded { nf } else { nf - missing.len() } + new_features as usize,
            "trial {trial}"
        );
    }
}

/// Exactly symmetric deltas with new features (fused in the delta's own buffer, `SplitDelta`)
/// match the dense information form at a vehicle's sizes: whole-map batches of 40–160
/// features with 1–4 new ones (map route, the known block past faer's blocking sizes), and
/// subsets of 60–99-feature maps, positive definite and mildly indefinite, in map order and
/// shuffled (pseudo-measurement route). The deltas are made exactly symmetric ((Y + Yᵀ)/2), so
/// that the fusion takes that path (checked: `validate_information` reports them exact).
#[test]
fn exact_deltas_with_new_features_match_the_dense_information_form() {
    let mut rng = ChaCha8Rng::seed_from_u64(34);
    for (trial, (nf, new_features, missing)) in [
        (40usize, 2u64, false),
        (100, 3, false),
        (100, 1, true),
        (160, 4, true),
        (160, 4, false),
    ]
    .into_iter()
    .enumerate()
    {
        let mut f = random_local_filter(nf, &mut rng);
        f.map_information().unwrap();
        let mut ids: Vec<FeatureId> = (100..100 + nf as u64)
            .filter(|id| !missing || (*id != 107 && *id != 131))
            .collect();
        ids.extend((0..new_features).map(|j| 900 + j));
        let d = exact_random_delta(ids, f.origin(), &mut rng);
        assert!(f.validate_information(&d).unwrap(), "exact");
        fuse_and_check_against_the_dense_form(&mut f, d, trial, FuseMethod::MapInformation);
    }
    // Subsets (pseudo route), PD and indefinite, with new features.
    for trial in 0..40 {
        let nf = 60 + trial;
        let mut f = random_local_filter(nf, &mut rng);
        if trial % 2 == 0 {
            f.map_information().unwrap();
        }
        let mut ids: Vec<FeatureId> = (100..100 + nf as u64)
            .filter(|_| rng.random_bool(0.2))
            .collect();
        ids.extend((0..1 + trial as u64 % 3).map(|j| 900 + j));
        if trial % 3 == 0 {
            for i in (1..ids.len()).rev() {
                ids.swap(i, rng.random_range(0..=i));
            }
        }
        let k = 3 * ids.len();
        let mut y = random_spd(k, 1.0, &mut rng);
        if trial % 4 == 1 {
            let u = DVector::from_fn(k, |_, _| rng.random::<f64>() - 0.5).normalize();
            y -= &u * u.transpose() * 0.02;
        }
        for (b, id) in ids.iter().enumerate() {
            if *id >= 900 {
                for i in 0..3 {
                    y[(3 * b + i, 3 * b + i)] += 1.0;
                }
            }
        }
        let y = (&y + y.transpose()) * 0.5;
        let target = DVector::from_fn(k, |_, _| rng.random_range(-30.0..30.0));
        let d = delta(ids, y, &target, f.origin());
        assert!(f.validate_information(&d).unwrap(), "exact");
        fuse_and_check_against_the_dense_form(
            &mut f,
            d,
            100 + trial,
            FuseMethod::PseudoMeasurement,
        );
    }
}

/// Fuses `d` into `f` by `route` and checks (x, P) and the maintained map information against
/// [`dense_fusion_reference`]: ≤ 500 states with κ ≲ 1e3, so 1e-8 relative covers the dense
/// inverses' round-off (as in `randomized_fusions_match_the_dense_information_form`).
fn fuse_and_check_against_the_dense_form(
    f: &mut SlamFilter,
    d: MapInformation,
    trial: usize,
    route: FuseMethod,
) {
    let (x_ref, p_ref) = dense_fusion_reference(f, &d);
    let rep = f.fuse_map_information(&d).unwrap();
    assert_eq!(rep.method, route, "trial {trial}: route");
    let p = to_dense(&f.p);
    let x = col_to_dense(&f.x);
    let ep = (&p - &p_ref).abs().max() / p_ref.abs().max();
    let ex = (&x - &x_ref).abs().max() / x_ref.abs().max();
    assert!(ep < 1e-8 && ex < 1e-8, "trial {trial}: P {ep:e}, x {ex:e}");
    if let Some(c) = f.info_cache.y.as_ref().filter(|_| f.info_cache_current()) {
        let c = to_dense(c);
        let (_, y_dense, _) = marginal_information(f);
        let ey = (&c - &y_dense).abs().max() / y_dense.abs().max();
        assert!(ey < 1e-8, "trial {trial}: maintained Y off by {ey:e}");
    }
}

/// The means a sparsified delta is evaluated about (`MapSource::feature_means`) are the
/// features' entries of x, as the marginal reads them, in the order asked, unknown ids skipped.
#[test]
fn feature_means_are_the_marginal_means() {
    use crate::ddf::MapSource;
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let f = random_local_filter(7, &mut rng);
    let ids = [104, 100, 999, 106, 101];
    let means = f.feature_means(&ids);
    assert_eq!(
        means.iter().map(|m| m.0).collect::<Vec<_>>(),
        [104, 100, 106, 101]
    );
    for (id, x) in means {
        let off = f
            .layout
            .feature_offset(id)
            .expect("a feature of the filter");
        assert_eq!(x, Vector3::new(f.x[off], f.x[off + 1], f.x[off + 2]));
    }
    // The marginal (means and covariance) reads the same entries.
    let marginal = f.marginal(&ids);
    for (b, (id, x)) in f.feature_means(&ids).into_iter().enumerate() {
        assert_eq!(marginal.ids[b], id);
        assert_eq!(x, Vector3::from_fn(|a, _| marginal.mean[3 * b + a]));
    }
}

/// What it proves: starting a vehicle nothing has touched (data sharing's start record) is
/// exact — the filter then predicts bit for bit as one built with that estimate from the
/// start, and the other vehicle is unchanged — and starting one that was predicted, or with a
/// non-finite state or a covariance that is not positive definite, is refused and changes
/// nothing.
#[test]
fn starting_an_untouched_vehicle_is_exact_and_anything_else_is_refused() {
    let cfg = config(NavFrame::Local, AssociationMode::Descriptor);
    let own = vehicle(Vector3::new(0.0, 0.0, -100.0));
    let placeholder = vehicle(Vector3::new(0.0, 0.0, -100.0));
    let mut actual = vehicle(Vector3::new(500.0, -300.0, -150.0));
    actual.covariance[(0, 0)] = 4.0;
    actual.covariance[(0, 1)] = 0.5;
    actual.covariance[(1, 0)] = 0.5;
    let mut started = SlamFilter::new(cfg, &[own, placeholder]).unwrap();
    let mut direct = SlamFilter::new(cfg, &[own, actual]).unwrap();
    // The own vehicle moves first (as a team filter's own samples arrive before others').
    for k in 0..5 {
        started.predict(0, &imu(0.01 * k as f64)).unwrap();
        direct.predict(0, &imu(0.01 * k as f64)).unwrap();
    }
    started
        .start_vehicle(1, &actual.state, &actual.covariance)
        .unwrap();
    for k in 0..20 {
        started.predict(1, &imu(0.01 * k as f64)).unwrap();
        direct.predict(1, &imu(0.01 * k as f64)).unwrap();
    }
    assert_eq!(snapshot(&started), snapshot(&direct));

    // Predicted already: refused, nothing changes.
    let before = snapshot(&started);
    assert!(matches!(
        started.start_vehicle(1, &actual.state, &actual.covariance),
        Err(SlamError::InvalidConfig(_))
    ));
    assert_eq!(snapshot(&started), before);

    // Bad content on an untouched vehicle: refused, nothing changes.
    let mut fresh = SlamFilter::new(cfg, &[own, placeholder]).unwrap();
    let before = snapshot(&fresh);
    let mut nan = actual.state;
    nan.velocity.y = f64::NAN;
    let mut not_pd = actual.covariance;
    not_pd[(2, 2)] = -1.0;
    assert!(fresh.start_vehicle(1, &nan, &actual.covariance).is_err());
    assert!(fresh.start_vehicle(1, &actual.state, &not_pd).is_err());
    assert_eq!(
        fresh.start_vehicle(2, &actual.state, &actual.covariance),
        Err(SlamError::UnknownVehicle(2))
    );
    assert_eq!(snapshot(&fresh), before);
}

/// What it proves: restarting a vehicle that was predicted and correlated with the map
/// (data sharing's start of a new incarnation) leaves the map's mean and covariance and the
/// other vehicle untouched bit for bit, puts the new estimate in place uncorrelated with
/// everything else, keeps the joint covariance positive semi-definite, and refuses a
/// non-finite state without changing anything.
#[test]
fn restarting_a_vehicle_marginalises_its_old_state() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut f = random_local_filter(4, &mut rng);
    for k in 0..5 {
        f.predict(0, &imu(0.01 * k as f64)).unwrap();
    }
    f.flush();
    let map_before: Vec<_> = f
        .features()
        .into_iter()
        .map(|(id, m)| (id, m, f.feature_covariance(id).unwrap()))
        .collect();
    let new = vehicle(Vector3::new(900.0, 50.0, -120.0));
    let before = snapshot(&f);
    let mut bad = new.state;
    bad.position.x = f64::INFINITY;
    assert!(f.restart_vehicle(0, &bad, &new.covariance).is_err());
    assert_eq!(snapshot(&f), before);
    f.restart_vehicle(0, &new.state, &new.covariance).unwrap();
    let map_after: Vec<_> = f
        .features()
        .into_iter()
        .map(|(id, m)| (id, m, f.feature_covariance(id).unwrap()))
        .collect();
    assert_eq!(map_before, map_after);
    assert_eq!(f.vehicle_state(0).unwrap(), new.state);
    assert_eq!(f.vehicle_covariance(0).unwrap(), new.covariance);
    let p = to_dense(&f.joint_covariance());
    for i in 0..VEHICLE_DIM {
        for j in VEHICLE_DIM..p.ncols() {
            assert_eq!(p[(i, j)], 0.0, "cross term ({i}, {j})");
        }
    }
    let min_eig = p.symmetric_eigenvalues().min();
    assert!(min_eig > -1e-9 * p.amax(), "λ_min {min_eig}");
}
