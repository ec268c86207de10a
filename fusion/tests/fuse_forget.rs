//! Feature removal, fusion that leaves features without information, and the external fix of a
//! restarted vehicle — each against an independent dense computation (nalgebra `DMatrix`
//! inverses and the textbook Kalman update), never against the structured code under test.

use canopy_fusion::imu::ImuGrade;
use canopy_fusion::info::MapInformation;
use canopy_fusion::ins::{VehicleCovariance, VehicleState};
use canopy_fusion::sensor::{FeatureId, ImuSample, SensorModel, SensorMount};
use canopy_fusion::slam::{AssociationConfig, SlamConfig, SlamError, SlamFilter, VehicleSetup};
use canopy_fusion::state::NavFrame;
use faer::{Col, Mat};
use nalgebra::{DMatrix, DVector, SMatrix, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn filter() -> SlamFilter {
    let mut cov = VehicleCovariance::zeros();
    for i in 0..3 {
        cov[(i, i)] = 4.0;
        cov[(3 + i, 3 + i)] = 0.01;
        cov[(6 + i, 6 + i)] = 1e-5;
        cov[(9 + i, 9 + i)] = 1e-4;
        cov[(12 + i, 12 + i)] = 1e-8;
    }
    let setup = VehicleSetup {
        state: VehicleState {
            position: Vector3::new(10.0, -20.0, -150.0),
            velocity: Vector3::new(20.0, 1.0, 0.0),
            attitude: Vector3::new(0.02, -0.01, 3.1),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        },
        covariance: cov,
        imu_noise: ImuGrade::Tactical.noise(),
        sensor: SensorModel::RangeBearing {
            sigma_range: 0.5,
            sigma_bearing: 0.005,
        },
        mount: SensorMount::downward(Vector3::new(0.3, 0.0, 0.2)),
    };
    let cfg = SlamConfig {
        frame: NavFrame::Local,
        local_gravity_mps2: 9.81,
        origin: Vector3::new(5.0, 5.0, 0.0),
        association: AssociationConfig::default(),
        fresh_id_namespace: 1,
    };
    let mut f = SlamFilter::new(cfg, &[setup]).unwrap();
    // A few IMU steps so the vehicle block is correlated with itself over time.
    for k in 1..=5 {
        f.predict(
            0,
            &ImuSample {
                time: 0.01 * k as f64,
                dt: 0.01,
                specific_force: Vector3::new(0.1, 0.0, -9.81),
                angular_rate: Vector3::new(0.0, 0.0, 0.01),
            },
        )
        .unwrap();
    }
    f
}

/// A random positive definite information over `ids` (features spread around the origin).
fn info(ids: &[FeatureId], origin: Vector3<f64>, rng: &mut ChaCha8Rng) -> MapInformation {
    let n = 3 * ids.len();
    let a = DMatrix::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
    let y = &a * a.transpose() + DMatrix::identity(n, n) * 0.5;
    let x = DVector::from_fn(n, |_, _| rng.random_range(-200.0..200.0));
    let yv = &y * &x; // y = Y (m − o) with m − o = x
    let _ = origin;
    MapInformation {
        ids: ids.to_vec(),
        origin,
        matrix: Mat::from_fn(n, n, |i, j| y[(i, j)]),
        vector: Col::from_fn(n, |i| yv[i]),
    }
}

fn negated(d: &MapInformation) -> MapInformation {
    d.scaled(-1.0)
}

fn dense(m: &Mat<f64>) -> DMatrix<f64> {
    DMatrix::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
}

/// Joint covariance and state of a filter, as dense nalgebra objects.
fn joint(f: &SlamFilter) -> (DMatrix<f64>, DVector<f64>) {
    let p = dense(&f.joint_covariance());
    let x = f.state_vector();
    (p, DVector::from_fn(x.nrows(), |i, _| x[i]))
}

fn max_abs(m: &DMatrix<f64>) -> f64 {
    m.iter().fold(0.0f64, |a, v| a.max(v.abs()))
}

#[test]
fn forgetting_features_is_dropping_their_rows_and_columns() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut f = filter();
    let o = f.origin();
    f.fuse_map_information(&info(&[11, 12, 13], o, &mut rng))
        .unwrap();
    let (p0, x0) = joint(&f);
    let keep: Vec<usize> = (0..f.dim())
        .filter(|&i| !(15 + 3..15 + 6).contains(&i))
        .collect();
    assert_eq!(f.forget_features(&[12, 999]), 1);
    let (p1, x1) = joint(&f);
    assert_eq!(p1.nrows(), keep.len());
    let p_ref = p0.select_rows(&keep).select_columns(&keep);
    let x_ref = x0.select_rows(&keep);
    // Pure copies: exact.
    assert_eq!(p1, p_ref);
    assert_eq!(x1, x_ref);
    assert_eq!(
        f.features().iter().map(|(id, _)| *id).collect::<Vec<_>>(),
        vec![11, 13]
    );
}

/// The DDF resynchronisation pattern: a node held its own information on feature 21 (delta A)
/// and received a neighbour's information on 21 and 22 (delta B); after the neighbour's
/// restart the channel takes B back (−B). Feature 22 is left with no information and is
/// removed; the rest must be exactly as if B had never been fused: the dense information form
/// J0 + E A Eᵀ, inverted.
#[test]
fn a_delta_taking_back_everything_on_a_feature_removes_it_and_keeps_the_rest_exact() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut f = filter();
    let o = f.origin();
    let (p_start, x_start) = joint(&f);
    let a = info(&[21], o, &mut rng);
    let b = info(&[21, 22], o, &mut rng);
    f.fuse_map_information(&a).unwrap();
    f.fuse_map_information(&b).unwrap();
    // A plain fusion refuses −B: feature 22 would be left with (numerically) zero information.
    let mut plain = f.clone();
    assert!(matches!(
        plain.fuse_map_information(&negated(&b)),
        Err(SlamError::NotPositiveDefinite(_))
    ));
    let report = f.fuse_map_information_forgetting(&negated(&b)).unwrap();
    assert_eq!(report.forgotten, vec![22]);
    assert!(report.skipped.is_empty());
    // Dense reference: joint information of the start plus A on feature 21's block.
    let j0 = p_start.clone().try_inverse().unwrap();
    let mut j = DMatrix::zeros(18, 18);
    j.view_mut((0, 0), (15, 15)).copy_from(&j0);
    let mut jy = DVector::zeros(18);
    jy.rows_mut(0, 15).copy_from(&(&j0 * &x_start));
    for r in 0..3 {
        for c in 0..3 {
            j[(15 + r, 15 + c)] += a.matrix[(r, c)];
        }
        // y = Y (m − o) + Y o in absolute coordinates.
        jy[15 + r] += a.vector[r];
        for c in 0..3 {
            jy[15 + r] += a.matrix[(r, c)] * o[c];
        }
    }
    let p_ref = j.clone().try_inverse().unwrap();
    let x_ref = &p_ref * &jy;
    let (p, x) = joint(&f);
    assert_eq!(p.nrows(), 18);
    // Relative round-off of a handful of 18×18 inverses and the add/subtract of B, whose
    // entries are ~10× those of the result: 1e-8 relative is far above it, far below any
    // modelling difference.
    let dp = max_abs(&(&p - &p_ref)) / max_abs(&p_ref);
    assert!(dp < 1e-8, "covariance differs by {dp:e} relative");
    let dx = (&x - &x_ref).amax();
    // Positions of hundreds of metres; 1e-6 m is round-off of the same operations.
    assert!(dx < 1e-6, "state differs by {dx:e}");
}

#[test]
fn new_features_without_information_are_not_added() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut f = filter();
    let o = f.origin();
    f.fuse_map_information(&info(&[31], o, &mut rng)).unwrap();
    // A delta on a known feature plus a new feature whose block cancelled to round-off
    // (slightly indefinite, as measured in the crash–restart runs).
    let mut d = info(&[31, 32], o, &mut rng);
    let residue = [1e-13, -2e-14, 0.0];
    for r in 0..6 {
        for c in 0..6 {
            if r >= 3 || c >= 3 {
                d.matrix[(r, c)] = if r == c { residue[r - 3] } else { 0.0 };
            }
        }
    }
    for r in 3..6 {
        d.vector[r] = 0.0;
    }
    let mut plain = f.clone();
    assert!(plain.fuse_map_information(&d).is_err());
    let (p_before, _) = joint(&f);
    let report = f.fuse_map_information_forgetting(&d).unwrap();
    assert_eq!(report.skipped, vec![32]);
    assert!(report.forgotten.is_empty());
    assert_eq!(f.num_features(), 1);
    // Feature 31 received the known part: its information grew.
    let (p_after, _) = joint(&f);
    assert!(p_after[(15, 15)] < p_before[(15, 15)]);
}

#[test]
fn a_genuinely_indefinite_result_is_still_refused_and_leaves_the_filter_unchanged() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let mut f = filter();
    let o = f.origin();
    let a = info(&[41, 42], o, &mut rng);
    f.fuse_map_information(&a).unwrap();
    let before = joint(&f);
    // Taking back twice what was given: strongly negative, nothing vanishes.
    let bad = a.scaled(-2.0);
    assert!(f.fuse_map_information_forgetting(&bad).is_err());
    assert_eq!(joint(&f), before);
}

#[test]
fn the_vehicle_fix_is_the_textbook_kalman_update() {
    let mut f = filter();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let o = f.origin();
    f.fuse_map_information(&info(&[51], o, &mut rng)).unwrap();
    let (p, x) = joint(&f);
    let mut fix = [0.0; 9];
    for (i, v) in fix.iter_mut().enumerate() {
        *v = x[i] + rng.random_range(-0.5..0.5);
    }
    // Attitude innovation across ±π: yaw 3.1 rad observed as −3.1 (i.e. 0.083 rad further on).
    fix[8] = -3.1;
    let mut r = SMatrix::<f64, 9, 9>::zeros();
    for i in 0..9 {
        r[(i, i)] = [1.0, 1.0, 2.0, 0.01, 0.01, 0.01, 1e-6, 1e-6, 4e-6][i];
    }
    r[(0, 1)] = 0.3;
    r[(1, 0)] = 0.3;
    f.vehicle_fix(0, &fix, &r).unwrap();
    // Textbook: H = [I₉ 0], S = H P Hᵀ + R, K = P Hᵀ S⁻¹, x⁺ = x + K ν, P⁺ = (I − K H) P.
    let n = p.nrows();
    let mut h = DMatrix::zeros(9, n);
    for i in 0..9 {
        h[(i, i)] = 1.0;
    }
    let rr = DMatrix::from_fn(9, 9, |i, j| r[(i, j)]);
    let s = &h * &p * h.transpose() + rr;
    let k = &p * h.transpose() * s.try_inverse().unwrap();
    let mut nu = DVector::from_fn(9, |i, _| fix[i] - x[i]);
    let two_pi = 2.0 * std::f64::consts::PI;
    nu[8] -= two_pi * (nu[8] / two_pi).round();
    let x_ref = &x + &k * nu;
    let p_ref = (DMatrix::identity(n, n) - &k * &h) * &p;
    let (p1, x1) = joint(&f);
    // Joseph form vs (I − KH)P agree to round-off of an 18-state update (1e-9 relative).
    let dp = max_abs(&(&p1 - &p_ref)) / max_abs(&p_ref);
    assert!(dp < 1e-9, "covariance differs by {dp:e} relative");
    let dx = (&x1 - &x_ref).amax();
    assert!(dx < 1e-9 * x.amax().max(1.0), "state differs by {dx:e}");
    // Invalid inputs are refused and change nothing.
    let before = joint(&f);
    assert!(f.vehicle_fix(3, &fix, &r).is_err());
    let mut nan = fix;
    nan[0] = f64::NAN;
    assert!(f.vehicle_fix(0, &nan, &r).is_err());
    assert!(f.vehicle_fix(0, &fix, &(-r)).is_err());
    assert_eq!(joint(&f), before);
}
