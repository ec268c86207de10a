//! Bearing-only feature initialization geometry (§21.4.2.3): lines of sight (eqs. 21.69–21.71),
//! the closest point of two lines G (eqs. 21.72–21.74) and its Jacobians ∇G_p, ∇G_z (eq. 21.76),
//! and the stored-pose frame of eq. 21.66.
//!
//! # The stored-pose frame n0
//! A stored pose is x_p = (p^n, Ψ^n) (eq. 21.66). In local SLAM p^n is the vehicle position in
//! the shared local-level frame. In global SLAM p^n = C_e^{n0} (p^e − o^e) is the position in the
//! local-level frame n0 at the team origin o (the map-information origin, the launch site), and
//! Ψ^n is the vehicle's attitude relative to the local-level frame at its own position, exactly
//! as in the vehicle state. Features are triangulated in n0 (the text of 21.4.2) and transformed
//! to ECEF, m^e = o^e + C_{n0}^e m^{n0}; all Jacobians are chained through these maps.
//!
//! # Closest point of two lines
//! With lines y_a + s u_a and y_b + t u_b, d = y_b − y_a, a = u_a·u_a, b = u_a·u_b, c = u_b·u_b,
//! e = d·u_a, f = d·u_b and D = ac − b² = |u_a × u_b|² (unit directions):
//! s = (ec − fb)/D (eq. 21.73 by the Lagrange identity), t = (eb − fa)/D (eq. 21.74), and
//! m = ½(y_a + s u_a + y_b + t u_b) (eq. 21.72). The miss distance is |y_a + s u_a − y_b − t u_b|.
//! The Jacobians are the exact derivatives of these formulas (finite-difference tested).

use crate::geodesy::{LocalFrame, ecef_to_geodetic};
use crate::observation::{ObservationError, ObservationModel, Prediction};
use crate::state::NavFrame;
use nalgebra::{DMatrix, DVector, Matrix3, SMatrix, Vector3};

/// Why two lines of sight cannot initialize a feature.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TriangulationError {
    /// The lines of sight are separated by less than the required angle (near-parallel: the
    /// depth is not observable well enough for a Gaussian initialization).
    #[error("lines of sight separated by {angle} rad, below the threshold")]
    NearParallel {
        /// Separation angle [rad].
        angle: f64,
    },
    /// The lines miss each other by more than the threshold (a misassociation or a moving
    /// feature).
    #[error("lines of sight miss each other by {distance} m")]
    Miss {
        /// Distance between the closest points [m].
        distance: f64,
    },
    /// The closest point lies behind one of the sensors.
    #[error("the closest point lies behind a sensor")]
    Behind,
    /// A measurement could not be turned into a direction.
    #[error(transparent)]
    Observation(#[from] ObservationError),
    /// NaN or ∞ in the result.
    #[error("non-finite triangulation")]
    NonFinite,
}

/// The closest point of two lines with its derivatives.
#[derive(Clone, Copy, Debug)]
pub struct ClosestPoint {
    /// m of eq. 21.72.
    pub point: Vector3<f64>,
    /// Distance between the two closest points [m].
    pub miss: f64,
    /// Separation angle of the directions [rad], in [0, π].
    pub angle: f64,
    /// Line parameters (s, t) of eqs. 21.73, 21.74 (ranges along unit directions).
    pub along: (f64, f64),
    /// ∂m/∂y_a.
    pub d_origin_a: Matrix3<f64>,
    /// ∂m/∂u_a.
    pub d_direction_a: Matrix3<f64>,
    /// ∂m/∂y_b.
    pub d_origin_b: Matrix3<f64>,
    /// ∂m/∂u_b.
    pub d_direction_b: Matrix3<f64>,
    /// Miss vector e = (y_a + s u_a) − (y_b + t u_b) (its norm is `miss`).
    pub miss_vector: Vector3<f64>,
    /// ∂e/∂(y_a, u_a, y_b, u_b) (3×12).
    pub d_miss: SMatrix<f64, 3, 12>,
}

/// Angle between two directions [rad], robust near 0 and π.
pub fn separation_angle(u_a: &Vector3<f64>, u_b: &Vector3<f64>) -> f64 {
    u_a.cross(u_b).norm().atan2(u_a.dot(u_b))
}

/// Closest point of the lines y_a + s u_a and y_b + t u_b (eqs. 21.72–21.74, module docs).
/// `None` when the directions are parallel to working precision (D ≤ 1e-14·a·c).
pub fn closest_point(
    y_a: &Vector3<f64>,
    u_a: &Vector3<f64>,
    y_b: &Vector3<f64>,
    u_b: &Vector3<f64>,
) -> Option<ClosestPoint> {
    let d = y_b - y_a;
    let (a, b, c) = (u_a.dot(u_a), u_a.dot(u_b), u_b.dot(u_b));
    let (e, f) = (d.dot(u_a), d.dot(u_b));
    let den = a * c - b * b;
    // D = |u_a|²|u_b|² sin²(angle): below 1e-14 (angle ≈ 1e-7 rad) the depth is pure round-off.
    if den.is_nan() || den <= 1e-14 * a * c {
        return None;
    }
    let n_a = e * c - f * b;
    let n_b = e * b - f * a;
    let s = n_a / den;
    let t = n_b / den;
    let q_a = y_a + u_a * s;
    let q_b = y_b + u_b * t;
    // Gradients (1×12 rows over [y_a, u_a, y_b, u_b]) of the scalars a, b, c, e, f.
    type Row = SMatrix<f64, 1, 12>;
    let put = |row: &mut Row, block: usize, v: &Vector3<f64>, k: f64| {
        for i in 0..3 {
            row[3 * block + i] += k * v[i];
        }
    };
    let mut ga = Row::zeros();
    put(&mut ga, 1, u_a, 2.0);
    let mut gb = Row::zeros();
    put(&mut gb, 1, u_b, 1.0);
    put(&mut gb, 3, u_a, 1.0);
    let mut gc = Row::zeros();
    put(&mut gc, 3, u_b, 2.0);
    let mut ge = Row::zeros();
    put(&mut ge, 0, u_a, -1.0);
    put(&mut ge, 2, u_a, 1.0);
    put(&mut ge, 1, &d, 1.0);
    let mut gf = Row::zeros();
    put(&mut gf, 0, u_b, -1.0);
    put(&mut gf, 2, u_b, 1.0);
    put(&mut gf, 3, &d, 1.0);
    let g_den = ga * c + gc * a - gb * (2.0 * b);
    let g_na = gb * (-f) + gc * e + ge * c - gf * b;
    let g_nb = ga * (-f) + gb * e + ge * b - gf * a;
    let g_s = (g_na - g_den * s) / den;
    let g_t = (g_nb - g_den * t) / den;
    // ∂m = ½ (∂y_a + s ∂u_a + u_a ∂s + ∂y_b + t ∂u_b + u_b ∂t).
    let mut jac = SMatrix::<f64, 3, 12>::zeros();
    jac += u_a * g_s + u_b * g_t;
    for i in 0..3 {
        jac[(i, i)] += 1.0;
        jac[(i, 3 + i)] += s;
        jac[(i, 6 + i)] += 1.0;
        jac[(i, 9 + i)] += t;
    }
    jac *= 0.5;
    // ∂e = ∂y_a + s ∂u_a + u_a ∂s − ∂y_b − t ∂u_b − u_b ∂t.
    let mut d_miss = u_a * g_s - u_b * g_t;
    for i in 0..3 {
        d_miss[(i, i)] += 1.0;
        d_miss[(i, 3 + i)] += s;
        d_miss[(i, 6 + i)] -= 1.0;
        d_miss[(i, 9 + i)] -= t;
    }
    let block = |k: usize| -> Matrix3<f64> { jac.fixed_view::<3, 3>(0, 3 * k).into_owned() };
    Some(ClosestPoint {
        point: (q_a + q_b) * 0.5,
        miss: (q_a - q_b).norm(),
        angle: separation_angle(u_a, u_b),
        along: (s, t),
        d_origin_a: block(0),
        d_direction_a: block(1),
        d_origin_b: block(2),
        d_direction_b: block(3),
        miss_vector: q_a - q_b,
        d_miss,
    })
}

/// The stored-pose frame n0 (module docs): conversions between filter-frame positions and
/// stored-pose positions p^n.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseFrame {
    frame: NavFrame,
    /// o^e (global) or zero (local).
    origin: Vector3<f64>,
    /// C_{n0}^e (global) or I (local).
    filter_from_pose: Matrix3<f64>,
}

impl PoseFrame {
    /// The stored-pose frame of a filter: in global SLAM the local-level frame at the team origin
    /// `origin` (ECEF), which must then lie near the Earth's surface; in local SLAM the filter's
    /// own frame (`origin` unused).
    pub fn new(frame: NavFrame, origin: &Vector3<f64>) -> Option<Self> {
        match frame {
            NavFrame::Local => Some(Self {
                frame,
                origin: Vector3::zeros(),
                filter_from_pose: Matrix3::identity(),
            }),
            NavFrame::Global => {
                // The local-level frame needs a geodetic origin: within ±100 km of the ellipsoid.
                let g = ecef_to_geodetic(origin);
                if !(g.height.abs() < 1e5 && origin.iter().all(|v| v.is_finite())) {
                    return None;
                }
                let lf = LocalFrame::new(g);
                Some(Self {
                    frame,
                    origin: lf.origin_ecef,
                    filter_from_pose: lf.ecef_from_ned,
                })
            }
        }
    }

    /// The filter's navigation frame.
    pub fn frame(&self) -> NavFrame {
        self.frame
    }

    /// C_{n0}^e (global) or I (local): ∂p^frame/∂p^n.
    pub fn filter_from_pose(&self) -> Matrix3<f64> {
        self.filter_from_pose
    }

    /// p^frame of a stored-pose position p^n.
    pub fn to_filter(&self, p_pose: &Vector3<f64>) -> Vector3<f64> {
        self.origin + self.filter_from_pose * p_pose
    }

    /// p^n = C_e^{n0} (p^e − o^e) (eq. 21.66) of a filter-frame position.
    pub fn from_filter(&self, p_filter: &Vector3<f64>) -> Vector3<f64> {
        self.filter_from_pose.transpose() * (p_filter - self.origin)
    }
}

/// The predicted measurement of a feature (filter frame) from a stored pose (p^n, Ψ^n), with
/// ∂h/∂p^n = ∂h/∂p^frame · C_{n0}^frame, ∂h/∂Ψ^n and ∂h/∂m (the H rows of eq. 21.78).
pub fn predict_from_pose(
    frame: &PoseFrame,
    model: &ObservationModel,
    position: &Vector3<f64>,
    attitude: &Vector3<f64>,
    feature: &Vector3<f64>,
) -> Result<Prediction, ObservationError> {
    let pose = model.sensor_pose(&frame.to_filter(position), attitude);
    let mut pred = model.predict(&pose, feature)?;
    pred.d_position = &pred.d_position * frame.filter_from_pose;
    Ok(pred)
}

/// One stored observation entering G: its sensor model, the stored pose (p^n, Ψ^n) and z.
#[derive(Clone, Copy, Debug)]
pub struct PosedObservation<'a> {
    /// Sensor of the vehicle that made it.
    pub model: &'a ObservationModel,
    /// Stored pose position p^n (n0 frame, module docs) [m].
    pub position: Vector3<f64>,
    /// Stored pose attitude Ψ^n [rad].
    pub attitude: Vector3<f64>,
    /// The measurement.
    pub z: &'a DVector<f64>,
}

/// A line of sight in n0 with its Jacobians w.r.t. the stored pose (p^n, Ψ^n) and z.
#[derive(Clone, Debug)]
pub struct PoseLineOfSight {
    /// y^n (eq. 21.69).
    pub origin: Vector3<f64>,
    /// u^n (eq. 21.70), unit.
    pub direction: Vector3<f64>,
    /// ∂y/∂(p^n, Ψ^n) (3×6).
    pub origin_d_pose: SMatrix<f64, 3, 6>,
    /// ∂u/∂(p^n, Ψ^n) (3×6).
    pub direction_d_pose: SMatrix<f64, 3, 6>,
    /// ∂u/∂z (3 × measurement dimension).
    pub direction_d_z: DMatrix<f64>,
}

/// The line of sight of a stored observation in the stored-pose frame n0 (eqs. 21.69–21.71).
pub fn pose_line_of_sight(
    frame: &PoseFrame,
    obs: &PosedObservation<'_>,
) -> Result<PoseLineOfSight, ObservationError> {
    let r = frame.filter_from_pose;
    let rt = r.transpose();
    let pose = obs
        .model
        .sensor_pose(&frame.to_filter(&obs.position), &obs.attitude);
    let (dir, d_dir) = obs.model.sensor_direction(obs.z)?;
    let los = pose.line_of_sight(&dir);
    let mut origin_d_pose = SMatrix::<f64, 3, 6>::zeros();
    origin_d_pose
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(rt * los.origin_d_position * r));
    origin_d_pose
        .fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(rt * los.origin_d_attitude));
    let mut direction_d_pose = SMatrix::<f64, 3, 6>::zeros();
    direction_d_pose
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(rt * los.direction_d_position * r));
    direction_d_pose
        .fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&(rt * los.direction_d_attitude));
    let c = rt * los.frame_from_sensor;
    let c = DMatrix::from_fn(3, 3, |i, j| c[(i, j)]);
    Ok(PoseLineOfSight {
        origin: frame.from_filter(&los.origin),
        direction: rt * los.direction,
        origin_d_pose,
        direction_d_pose,
        direction_d_z: c * d_dir,
    })
}

/// A feature initialized from two stored observations (eqs. 21.72–21.77).
#[derive(Clone, Debug)]
pub struct PairInitialization {
    /// m in the filter frame (ECEF in global SLAM, m^e = o^e + C_{n0}^e m^n).
    pub feature: Vector3<f64>,
    /// ∇G_p for the first pose: ∂m/∂(p^n_a, Ψ^n_a) (3×6).
    pub d_pose_a: SMatrix<f64, 3, 6>,
    /// ∇G_p for the second pose.
    pub d_pose_b: SMatrix<f64, 3, 6>,
    /// ∇G_z for the first measurement (3 × d_a).
    pub d_z_a: DMatrix<f64>,
    /// ∇G_z for the second measurement.
    pub d_z_b: DMatrix<f64>,
    /// Miss distance of the lines [m].
    pub miss: f64,
    /// Unit direction of the miss vector in the filter frame (zero when the lines meet).
    pub miss_direction: Vector3<f64>,
    /// ∂w/∂(p^n_a, Ψ^n_a) of the signed miss w = ê·e along that direction (1×6).
    pub miss_d_pose_a: SMatrix<f64, 1, 6>,
    /// ∂w/∂(p^n_b, Ψ^n_b).
    pub miss_d_pose_b: SMatrix<f64, 1, 6>,
    /// ∂w/∂z_a (1 × d_a).
    pub miss_d_z_a: DMatrix<f64>,
    /// ∂w/∂z_b.
    pub miss_d_z_b: DMatrix<f64>,
    /// Separation angle [rad].
    pub angle: f64,
}

/// G of eq. 21.72 for two stored observations, in n0 and transformed to the filter frame, with
/// ∇G_p and ∇G_z. Rejects separation angles below `min_angle` (near-parallel), lines missing by
/// more than `max_miss` [m], and points behind either sensor.
pub fn initialize_from_pair(
    frame: &PoseFrame,
    a: &PosedObservation<'_>,
    b: &PosedObservation<'_>,
    min_angle: f64,
    max_miss: f64,
) -> Result<PairInitialization, TriangulationError> {
    let la = pose_line_of_sight(frame, a)?;
    let lb = pose_line_of_sight(frame, b)?;
    let angle = separation_angle(&la.direction, &lb.direction);
    if angle.is_nan() || angle < min_angle {
        return Err(TriangulationError::NearParallel { angle });
    }
    let cp = closest_point(&la.origin, &la.direction, &lb.origin, &lb.direction)
        .ok_or(TriangulationError::NearParallel { angle })?;
    if cp.miss.is_nan() || cp.miss > max_miss {
        return Err(TriangulationError::Miss { distance: cp.miss });
    }
    if cp.along.0 <= 0.0 || cp.along.1 <= 0.0 {
        return Err(TriangulationError::Behind);
    }
    let r = frame.filter_from_pose;
    let d_pose_a = r * (cp.d_origin_a * la.origin_d_pose + cp.d_direction_a * la.direction_d_pose);
    let d_pose_b = r * (cp.d_origin_b * lb.origin_d_pose + cp.d_direction_b * lb.direction_d_pose);
    let to_d = |m: &Matrix3<f64>| DMatrix::from_fn(3, 3, |i, j| m[(i, j)]);
    let d_z_a = to_d(&(r * cp.d_direction_a)) * &la.direction_d_z;
    let d_z_b = to_d(&(r * cp.d_direction_b)) * &lb.direction_d_z;
    // The signed miss along its own direction, w = ê·e, and its derivatives (ê held fixed:
    // ∂|e| = êᵀ ∂e).
    let e_hat = if cp.miss > 0.0 {
        cp.miss_vector / cp.miss
    } else {
        Vector3::zeros()
    };
    let w = e_hat.transpose() * cp.d_miss;
    let blk = |k: usize| w.fixed_view::<1, 3>(0, 3 * k).into_owned();
    let miss_d_pose_a = blk(0) * la.origin_d_pose + blk(1) * la.direction_d_pose;
    let miss_d_pose_b = blk(2) * lb.origin_d_pose + blk(3) * lb.direction_d_pose;
    let row = |v: SMatrix<f64, 1, 3>| DMatrix::from_fn(1, 3, |_, j| v[j]);
    let miss_d_z_a = row(blk(1)) * &la.direction_d_z;
    let miss_d_z_b = row(blk(3)) * &lb.direction_d_z;
    let feature = frame.to_filter(&cp.point);
    if !(feature.iter().all(|v| v.is_finite())
        && d_pose_a
            .iter()
            .chain(d_pose_b.iter())
            .all(|v| v.is_finite())
        && d_z_a.iter().chain(d_z_b.iter()).all(|v| v.is_finite()))
    {
        return Err(TriangulationError::NonFinite);
    }
    Ok(PairInitialization {
        feature,
        d_pose_a,
        d_pose_b,
        d_z_a,
        d_z_b,
        miss: cp.miss,
        miss_direction: r * e_hat,
        miss_d_pose_a,
        miss_d_pose_b,
        miss_d_z_a,
        miss_d_z_b,
        angle,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geodesy::{Geodetic, geodetic_to_ecef};
    use crate::rotation::nav_from_body;
    use crate::sensor::{CameraIntrinsics, SensorModel, SensorMount};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn closest_point_matches_closed_forms() {
        // Skew lines a: (1,2,3) + s(1,0,0), b: (5,−1,7) + t(0,1,0). Closest points (5,2,3) at
        // s = 4 and (5,2,7) at t = 3: midpoint (5,2,5), miss 4, angle π/2.
        let cp = closest_point(
            &Vector3::new(1.0, 2.0, 3.0),
            &Vector3::x(),
            &Vector3::new(5.0, -1.0, 7.0),
            &Vector3::y(),
        )
        .unwrap();
        // Exact arithmetic on small integers: round-off only.
        assert!((cp.point - Vector3::new(5.0, 2.0, 5.0)).norm() < 1e-12);
        assert!((cp.miss - 4.0).abs() < 1e-12);
        assert!((cp.along.0 - 4.0).abs() < 1e-12 && (cp.along.1 - 3.0).abs() < 1e-12);
        assert!((cp.angle - std::f64::consts::FRAC_PI_2).abs() < 1e-15);

        // Two lines through m = (10, 5, 100) from (0,0,0) and (20,0,0): they intersect at m.
        let m = Vector3::new(10.0, 5.0, 100.0);
        let (ya, yb) = (Vector3::zeros(), Vector3::new(20.0, 0.0, 0.0));
        let cp = closest_point(&ya, &(m - ya).normalize(), &yb, &(m - yb).normalize()).unwrap();
        // Round-off on 100 m coordinates.
        assert!((cp.point - m).norm() < 1e-10 && cp.miss < 1e-10);
        assert!((cp.along.0 - (m - ya).norm()).abs() < 1e-10);
        // The angle of the two rays: closed form from the dot product of the unit rays.
        let expect = ((m - ya).normalize().dot(&(m - yb).normalize())).acos();
        assert!((cp.angle - expect).abs() < 1e-12);

        // Exactly parallel lines have no closest point.
        assert!(closest_point(&ya, &Vector3::z(), &yb, &Vector3::z()).is_none());
    }

    #[test]
    fn closest_point_jacobians_match_finite_differences() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut v = |s: f64| Vector3::new(rng.random(), rng.random(), rng.random()) * s;
        for _ in 0..50 {
            let ya = v(50.0);
            let yb = v(50.0) + Vector3::new(30.0, 0.0, 0.0);
            let ua = (v(1.0) + Vector3::new(0.0, 0.0, 1.0)).normalize();
            let ub = (v(1.0) + Vector3::new(0.0, 0.3, 1.0)).normalize();
            let cp = closest_point(&ya, &ua, &yb, &ub).unwrap();
            let args = [ya, ua, yb, ub];
            let jac = [
                cp.d_origin_a,
                cp.d_direction_a,
                cp.d_origin_b,
                cp.d_direction_b,
            ];
            for k in 0..4 {
                // Step 1e-5 (m or unit-direction): truncation h²·|∂³m| with |∂³m| ≲ 1e4 for
                // these geometries (ranges ≈ 100 m, angles ≳ 0.1 rad) gives ≲ 1e-6; rounding
                // 1e-14·100/1e-5 ≈ 1e-7. Tolerance 1e-5 relative to the block's norm + 1e-6.
                let h = 1e-5;
                let mut fd = Matrix3::zeros();
                for j in 0..3 {
                    let mut plus = args;
                    let mut minus = args;
                    plus[k][j] += h;
                    minus[k][j] -= h;
                    let f = |a: &[Vector3<f64>; 4]| closest_point(&a[0], &a[1], &a[2], &a[3]);
                    let d = (f(&plus).unwrap().point - f(&minus).unwrap().point) / (2.0 * h);
                    fd.set_column(j, &d);
                }
                assert!(
                    (fd - jac[k]).norm() <= 1e-5 * jac[k].norm() + 1e-6,
                    "block {k}: {}",
                    (fd - jac[k]).norm()
                );
                // The miss vector's Jacobian, same steps and tolerance argument.
                let mut fd_e = Matrix3::zeros();
                for j in 0..3 {
                    let mut plus = args;
                    let mut minus = args;
                    plus[k][j] += h;
                    minus[k][j] -= h;
                    let f = |a: &[Vector3<f64>; 4]| {
                        closest_point(&a[0], &a[1], &a[2], &a[3])
                            .unwrap()
                            .miss_vector
                    };
                    fd_e.set_column(j, &((f(&plus) - f(&minus)) / (2.0 * h)));
                }
                let an = cp.d_miss.fixed_view::<3, 3>(0, 3 * k).into_owned();
                assert!(
                    (fd_e - an).norm() <= 1e-5 * an.norm() + 1e-6,
                    "miss block {k}"
                );
            }
        }
    }

    fn camera() -> SensorModel {
        SensorModel::Pixel {
            camera: CameraIntrinsics {
                fu: 600.0,
                fv: 600.0,
                u0: 320.0,
                v0: 240.0,
                width: 640.0,
                height: 480.0,
            },
            sigma_pixel: 1.0,
        }
    }

    fn mount() -> SensorMount {
        let mut m = SensorMount::downward(Vector3::new(0.4, -0.1, 0.25));
        m.sensor_from_body =
            nav_from_body(&Vector3::new(0.02, -0.03, 0.01)).transpose() * m.sensor_from_body;
        m
    }

    /// (pose frame, two stored poses (p^n, Ψ^n), feature in the filter frame).
    type PairCase = (PoseFrame, [(Vector3<f64>, Vector3<f64>); 2], Vector3<f64>);

    fn pair_cases() -> Vec<PairCase> {
        let poses = [
            (
                Vector3::new(0.0, 0.0, -150.0),
                Vector3::new(0.05, 0.02, 0.3),
            ),
            (
                Vector3::new(40.0, 12.0, -148.0),
                Vector3::new(-0.03, 0.04, 0.32),
            ),
        ];
        let m_n = Vector3::new(25.0, 10.0, 5.0);
        let o = geodetic_to_ecef(&Geodetic::from_degrees(-34.0, 150.6, 80.0));
        let global = PoseFrame::new(NavFrame::Global, &o).unwrap();
        let local = PoseFrame::new(NavFrame::Local, &Vector3::zeros()).unwrap();
        vec![(local, poses, m_n), (global, poses, global.to_filter(&m_n))]
    }

    #[test]
    fn pair_initialization_recovers_the_feature_and_its_jacobians_match_finite_differences() {
        for (pf, poses, m) in pair_cases() {
            for sensor in [
                SensorModel::Bearing {
                    sigma_bearing: 0.002,
                },
                camera(),
            ] {
                let model = ObservationModel {
                    frame: pf.frame(),
                    sensor,
                    mount: mount(),
                };
                let z: Vec<DVector<f64>> = poses
                    .iter()
                    .map(|(p, a)| {
                        let pose = model.sensor_pose(&pf.to_filter(p), a);
                        model.predict(&pose, &m).unwrap().z
                    })
                    .collect();
                let init = |poses: &[(Vector3<f64>, Vector3<f64>); 2], z: &[DVector<f64>]| {
                    let o = |k: usize| PosedObservation {
                        model: &model,
                        position: poses[k].0,
                        attitude: poses[k].1,
                        z: &z[k],
                    };
                    initialize_from_pair(&pf, &o(0), &o(1), 0.05, 1.0)
                };
                let g = init(&poses, &z).unwrap();
                let label = format!("{:?} {sensor:?}", pf.frame());
                // Noise-free rays meet at m: ECEF round-off ≈ 1e-9 m per operation.
                assert!((g.feature - m).norm() < 1e-6, "{label}");
                assert!(g.miss < 1e-6, "{label}");
                // ∇G_p: steps 1e-3 m and 1e-6 rad (ECEF rounding 1e-9/1e-6 ≈ 1e-3 relative to
                // the ≈ 1-unit entries of ∂m/∂p would be too coarse; 1e-3 m gives 1e-6 and a
                // truncation of h²|∂³m| ≈ 1e-6·1e-4); tolerances are stated per block below.
                for k in 0..2 {
                    let analytic = if k == 0 { g.d_pose_a } else { g.d_pose_b };
                    for j in 0..6 {
                        let h = if j < 3 { 1e-3 } else { 1e-6 };
                        let mut plus = poses;
                        let mut minus = poses;
                        if j < 3 {
                            plus[k].0[j] += h;
                            minus[k].0[j] -= h;
                        } else {
                            plus[k].1[j - 3] += h;
                            minus[k].1[j - 3] -= h;
                        }
                        let fd = (init(&plus, &z).unwrap().feature
                            - init(&minus, &z).unwrap().feature)
                            / (2.0 * h);
                        let col = analytic.column(j).into_owned();
                        // Position columns are O(1) (rounding 1e-9/1e-3 = 1e-6); attitude
                        // columns O(100 m/rad) (rounding 1e-9/1e-6 = 1e-3): 1e-5 relative + the
                        // rounding floor.
                        let floor = if j < 3 { 5e-6 } else { 5e-3 };
                        assert!(
                            (fd - col).norm() <= 1e-5 * col.norm() + floor,
                            "{label}: ∇G_p pose {k} column {j}: {} vs {}",
                            fd,
                            col
                        );
                    }
                    let analytic = if k == 0 { &g.d_z_a } else { &g.d_z_b };
                    let h = if matches!(sensor, SensorModel::Pixel { .. }) {
                        1e-3
                    } else {
                        1e-6
                    };
                    for j in 0..2 {
                        let mut zp = z.clone();
                        let mut zm = z.clone();
                        zp[k][j] += h;
                        zm[k][j] -= h;
                        let fd = (init(&poses, &zp).unwrap().feature
                            - init(&poses, &zm).unwrap().feature)
                            / (2.0 * h);
                        let col =
                            Vector3::new(analytic[(0, j)], analytic[(1, j)], analytic[(2, j)]);
                        // ∂m/∂z entries ≈ 0.2 m/px or 100 m/rad; rounding 1e-9/h.
                        let floor = 2e-9 / h;
                        assert!(
                            (fd - col).norm() <= 1e-5 * col.norm() + floor,
                            "{label}: ∇G_z obs {k} column {j}"
                        );
                    }
                }
                if pf.frame() == NavFrame::Global {
                    // The feature is in ECEF: the chain through C_{n0}^e is not the identity.
                    assert!(
                        (g.d_pose_a.fixed_view::<3, 3>(0, 0) - Matrix3::identity()).norm() > 0.1
                    );
                }
            }
        }
    }

    #[test]
    fn miss_jacobians_match_finite_differences() {
        for (pf, poses, m) in pair_cases() {
            let model = ObservationModel {
                frame: pf.frame(),
                sensor: camera(),
                mount: mount(),
            };
            let mut z: Vec<DVector<f64>> = poses
                .iter()
                .map(|(p, a)| {
                    let pose = model.sensor_pose(&pf.to_filter(p), a);
                    model.predict(&pose, &m).unwrap().z
                })
                .collect();
            // Offset the second pixel so the rays miss each other.
            z[1][0] += 6.0;
            z[1][1] -= 6.0;
            let miss = |poses: &[(Vector3<f64>, Vector3<f64>); 2], z: &[DVector<f64>]| {
                let o = |k: usize| PosedObservation {
                    model: &model,
                    position: poses[k].0,
                    attitude: poses[k].1,
                    z: &z[k],
                };
                initialize_from_pair(&pf, &o(0), &o(1), 0.05, f64::INFINITY).unwrap()
            };
            let g = miss(&poses, &z);
            assert!(g.miss > 0.1, "{}", g.miss);
            for k in 0..2 {
                let an = if k == 0 {
                    g.miss_d_pose_a
                } else {
                    g.miss_d_pose_b
                };
                for j in 0..6 {
                    let h = if j < 3 { 1e-3 } else { 1e-6 };
                    let (mut plus, mut minus) = (poses, poses);
                    if j < 3 {
                        plus[k].0[j] += h;
                        minus[k].0[j] -= h;
                    } else {
                        plus[k].1[j - 3] += h;
                        minus[k].1[j - 3] -= h;
                    }
                    let fd = (miss(&plus, &z).miss - miss(&minus, &z).miss) / (2.0 * h);
                    // Rounding 1e-9 m / h (ECEF) plus 1e-5 relative truncation.
                    assert!(
                        (fd - an[j]).abs() <= 1e-5 * an[j].abs() + 2e-9 / h,
                        "{:?} pose {k} col {j}: {fd} vs {}",
                        pf.frame(),
                        an[j]
                    );
                }
                let an = if k == 0 { &g.miss_d_z_a } else { &g.miss_d_z_b };
                for j in 0..2 {
                    let h = 1e-3;
                    let (mut zp, mut zm) = (z.clone(), z.clone());
                    zp[k][j] += h;
                    zm[k][j] -= h;
                    let fd = (miss(&poses, &zp).miss - miss(&poses, &zm).miss) / (2.0 * h);
                    assert!(
                        (fd - an[(0, j)]).abs() <= 1e-5 * an[(0, j)].abs() + 2e-9 / h,
                        "{:?} z {k} col {j}",
                        pf.frame()
                    );
                }
            }
        }
    }

    #[test]
    fn stored_pose_observation_jacobians_match_finite_differences() {
        for (pf, poses, m) in pair_cases() {
            for sensor in [
                SensorModel::Bearing {
                    sigma_bearing: 0.002,
                },
                camera(),
            ] {
                let model = ObservationModel {
                    frame: pf.frame(),
                    sensor,
                    mount: mount(),
                };
                let (p, a) = poses[0];
                let pred = predict_from_pose(&pf, &model, &p, &a, &m).unwrap();
                let h = |p: &Vector3<f64>, a: &Vector3<f64>, m: &Vector3<f64>| {
                    predict_from_pose(&pf, &model, p, a, m).unwrap().z
                };
                for j in 0..3 {
                    // Steps 0.1 m / 1e-5 rad as in the ∇H test of `observation` (truncation
                    // ≈ 1e-8 relative, ECEF rounding 1e-9 m / 0.2 m ≈ 5e-9 per metre-derivative).
                    let mut e = Vector3::zeros();
                    e[j] = 0.1;
                    let fd_p = model.innovation(&h(&(p + e), &a, &m), &h(&(p - e), &a, &m)) / 0.2;
                    let fd_m = model.innovation(&h(&p, &a, &(m + e)), &h(&p, &a, &(m - e))) / 0.2;
                    let mut e = Vector3::zeros();
                    e[j] = 1e-5;
                    let fd_a = model.innovation(&h(&p, &(a + e), &m), &h(&p, &(a - e), &m)) / 2e-5;
                    for (fd, an, what) in [
                        (fd_p, pred.d_position.column(j).into_owned(), "p^n"),
                        (fd_a, pred.d_attitude.column(j).into_owned(), "Ψ"),
                        (fd_m, pred.d_feature.column(j).into_owned(), "m"),
                    ] {
                        // 1e-6 relative + 1e-7 absolute (angles: ≈ 5e-3 per m, pixels ≈ 4 per m).
                        assert!(
                            (0..fd.len())
                                .all(|i| (fd[i] - an[i]).abs() <= 1e-6 * an[i].abs() + 1e-7),
                            "{:?} {sensor:?} ∂h/∂{what} column {j}: {fd} vs {an}",
                            pf.frame()
                        );
                    }
                }
                if pf.frame() == NavFrame::Global {
                    // The chain through C_{n0}^e matters: ∂h/∂p^n ≠ ∂h/∂p^e.
                    let raw = model
                        .predict(&model.sensor_pose(&pf.to_filter(&p), &a), &m)
                        .unwrap();
                    assert!((raw.d_position - &pred.d_position).norm() > 1e-3);
                }
            }
        }
    }

    #[test]
    fn pair_initialization_rejects_near_parallel_missing_and_behind_lines() {
        let (pf, _, _) = pair_cases()[0];
        let model = ObservationModel {
            frame: pf.frame(),
            sensor: SensorModel::Bearing {
                sigma_bearing: 0.002,
            },
            mount: SensorMount {
                sensor_from_body: Matrix3::identity(),
                lever_arm_body: Vector3::zeros(),
            },
        };
        // Sensor x forward (body = sensor, level attitude): (az, el) = (0, 0) looks north.
        let obs = |p: Vector3<f64>, az: f64, el: f64| (p, DVector::from_vec(vec![az, el]));
        let run = |a: &(Vector3<f64>, DVector<f64>), b: &(Vector3<f64>, DVector<f64>)| {
            let oa = PosedObservation {
                model: &model,
                position: a.0,
                attitude: Vector3::zeros(),
                z: &a.1,
            };
            let ob = PosedObservation {
                model: &model,
                position: b.0,
                attitude: Vector3::zeros(),
                z: &b.1,
            };
            // 0.05 rad (2.9°) minimum angle, 1 m maximum miss.
            initialize_from_pair(&pf, &oa, &ob, 0.05, 1.0)
        };
        // Rays from (0,0,0) and (0,10,0) to (100, 5, 0): 2·atan(5/100) = 0.0998 rad, accepted.
        let a = obs(Vector3::zeros(), (5.0f64 / 100.0).atan(), 0.0);
        let b = obs(Vector3::new(0.0, 10.0, 0.0), (-5.0f64 / 100.0).atan(), 0.0);
        let g = run(&a, &b).unwrap();
        // Closed form: the rays meet at (100, 5, 0); round-off only.
        assert!((g.feature - Vector3::new(100.0, 5.0, 0.0)).norm() < 1e-9);
        // Near-parallel: rays to (100, 5, 0) from 1 m apart: atan(0.05) − atan(0.04) ≈ 0.00998 < 0.05.
        let near = obs(Vector3::new(0.0, 1.0, 0.0), (4.0f64 / 100.0).atan(), 0.0);
        let near_a = obs(Vector3::zeros(), (5.0f64 / 100.0).atan(), 0.0);
        assert!(matches!(
            run(&near_a, &near),
            Err(TriangulationError::NearParallel { angle }) if (angle - 0.00999).abs() < 1e-4
        ));
        // Missing lines: b's ray tilted by 0.02 rad passes ≈ 2 m from a's. The distance of two
        // skew lines in closed form: |(y_b − y_a)·n| / |n| with n = u_a × u_b (eq. 21.71 rays).
        let el = 0.02f64;
        let az_b = (-5.0f64 / 100.0).atan();
        let high = obs(Vector3::new(0.0, 10.0, 0.0), az_b, el);
        let u_a = Vector3::new((0.05f64).atan().cos(), (0.05f64).atan().sin(), 0.0);
        let u_b = Vector3::new(az_b.cos() * el.cos(), az_b.sin() * el.cos(), el.sin());
        let n = u_a.cross(&u_b);
        let expect = (Vector3::new(0.0, 10.0, 0.0).dot(&n) / n.norm()).abs();
        assert!(expect > 1.5);
        assert!(matches!(
            run(&a, &high),
            Err(TriangulationError::Miss { distance }) if (distance - expect).abs() < 1e-9
        ));
        // Behind: rays that diverge meet behind the sensors.
        let away_a = obs(Vector3::zeros(), -(5.0f64 / 100.0).atan(), 0.0);
        let away_b = obs(Vector3::new(0.0, 10.0, 0.0), (5.0f64 / 100.0).atan(), 0.0);
        assert_eq!(
            run(&away_a, &away_b).unwrap_err(),
            TriangulationError::Behind
        );
    }
}
