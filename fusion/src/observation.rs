//! Terrain observation models (§21.2.3) with analytic Jacobians, and the range-bearing feature
//! initialization function J_1 (eqs. 21.48–21.50).
//!
//! * Relative position (eq. 21.45): p_ms^s = C_b^s C_n^b [m − p − C_b^n p_sb^b] (local) and
//!   p_ms^s = C_b^s C_e^b [m − p − C_b^e p_sb^b] (global). Since C_e^b C_b^e = I both reduce to
//!   p_ms^s = C_b^s (C_bnᵀ C_neᵀ (m − p) − p_sb^b) with C_ne = C_n^e(λ(p), l(p)) in global SLAM
//!   (so the global ∇H has a p-dependence through λ, l) and C_ne = I in local SLAM.
//! * Range-bearing (21.41), bearing angles (21.42), pixels (21.43 with the erratum: camera x
//!   forward, u = f_u y/x + u_0, v = f_v z/x + v_0), pixels → angles (21.44).
//! * Azimuths use atan2 (the chapter's tan⁻¹(y/x) is its x > 0 branch) and azimuth innovations
//!   are wrapped to (−π, π].
//!
//! Jacobians are w.r.t. the vehicle position p, the attitude Ψ and the feature m. A stored pose of
//! bearing-only SLAM (p^n, Ψ^n, eq. 21.66) enters exactly like (p, Ψ) of the local model.

use crate::geodesy;
use crate::rotation::{nav_from_body, nav_from_body_partials, wrap_angle};
use crate::sensor::{CameraIntrinsics, Measurement, SensorModel, SensorMount};
use crate::state::NavFrame;
use nalgebra::{DMatrix, DVector, Matrix2, Matrix3, Matrix3x2, MatrixXx3, Vector2, Vector3};

/// Why an observation could not be used.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ObservationError {
    /// The measurement kind does not match the sensor model.
    #[error("measurement kind {got} does not match the sensor model {expected}")]
    KindMismatch {
        /// Kind the sensor model expects.
        expected: &'static str,
        /// Kind that arrived.
        got: &'static str,
    },
    /// The measurement has a NaN or infinite component.
    #[error("measurement has a non-finite component")]
    NonFinite,
    /// A range measurement is not positive.
    #[error("range must be positive, got {0}")]
    NonPositiveRange(f64),
    /// The feature cannot be observed from this pose (behind the camera, at the sensor origin,
    /// or on the elevation singularity).
    #[error("feature geometry is degenerate for this sensor")]
    DegenerateGeometry,
    /// Initialization from a single observation needs a range (bearing-only needs delayed init).
    #[error("a single {0} observation cannot initialize a 3-D feature")]
    NotInitializable(&'static str),
    /// A pixel lies outside the camera image [0, width) × [0, height).
    #[error("pixel ({u}, {v}) lies outside the image")]
    OutsideImage {
        /// Column u [px].
        u: f64,
        /// Row v [px].
        v: f64,
    },
    /// An elevation angle outside [−π/2, π/2].
    #[error("elevation {0} rad is outside [-pi/2, pi/2]")]
    ElevationOutOfRange(f64),
}

fn kind_name(z: &Measurement) -> &'static str {
    match z {
        Measurement::RangeBearing(_) => "range-bearing",
        Measurement::Bearing(_) => "bearing",
        Measurement::Pixel(_) => "pixel",
    }
}

fn sensor_kind_name(s: &SensorModel) -> &'static str {
    match s {
        SensorModel::RangeBearing { .. } => "range-bearing",
        SensorModel::Bearing { .. } => "bearing",
        SensorModel::Pixel { .. } => "pixel",
    }
}

/// The vehicle/sensor geometry at one pose, shared by all features observed from it.
#[derive(Clone, Copy, Debug)]
pub struct SensorPose {
    position: Vector3<f64>,
    /// C_n^e at p (identity in local SLAM).
    ecef_from_ned: Matrix3<f64>,
    /// ∂C_n^e/∂p_j (zero in local SLAM).
    ecef_from_ned_dp: [Matrix3<f64>; 3],
    /// C_b^n.
    nav_from_body: Matrix3<f64>,
    /// ∂C_b^n/∂Ψ_j.
    nav_from_body_datt: [Matrix3<f64>; 3],
    /// C_b^s.
    sensor_from_body: Matrix3<f64>,
    /// p_sb^b.
    lever_arm_body: Vector3<f64>,
}

impl SensorPose {
    /// Precomputes the frame matrices for a vehicle at `position` with attitude Ψ.
    pub fn new(
        frame: NavFrame,
        mount: &SensorMount,
        position: &Vector3<f64>,
        attitude: &Vector3<f64>,
    ) -> Self {
        let (ecef_from_ned, ecef_from_ned_dp) = match frame {
            NavFrame::Local => (Matrix3::identity(), [Matrix3::zeros(); 3]),
            NavFrame::Global => {
                let g = geodesy::ecef_to_geodetic(position);
                let geo_from_p = geodesy::geodetic_from_ecef_jacobian(&g);
                let [d_lat, d_lon] = geodesy::ecef_from_ned_partials(g.lat, g.lon);
                let dp = std::array::from_fn(|j| {
                    d_lat * geo_from_p[(0, j)] + d_lon * geo_from_p[(1, j)]
                });
                (geodesy::ecef_from_ned(g.lat, g.lon), dp)
            }
        };
        Self {
            position: *position,
            ecef_from_ned,
            ecef_from_ned_dp,
            nav_from_body: nav_from_body(attitude),
            nav_from_body_datt: nav_from_body_partials(attitude),
            sensor_from_body: mount.sensor_from_body,
            lever_arm_body: mount.lever_arm_body,
        }
    }

    /// C_s^frame: maps sensor-frame vectors into the filter frame (ECEF or local NED).
    pub fn frame_from_sensor(&self) -> Matrix3<f64> {
        self.ecef_from_ned * self.nav_from_body * self.sensor_from_body.transpose()
    }

    /// The line of sight of the sensor-frame direction `direction_sensor` (p̄^s of eq. 21.71)
    /// from this pose (eqs. 21.69, 21.70), with its Jacobians w.r.t. p and Ψ.
    pub fn line_of_sight(&self, direction_sensor: &Vector3<f64>) -> LineOfSight {
        let body_from_sensor = self.sensor_from_body.transpose();
        let d_body = body_from_sensor * direction_sensor;
        let c_fb = self.ecef_from_ned * self.nav_from_body;
        let mut origin_d_position = Matrix3::identity();
        let mut origin_d_attitude = Matrix3::zeros();
        let mut direction_d_position = Matrix3::zeros();
        let mut direction_d_attitude = Matrix3::zeros();
        for j in 0..3 {
            let dp = self.ecef_from_ned_dp[j] * self.nav_from_body;
            let da = self.ecef_from_ned * self.nav_from_body_datt[j];
            origin_d_position
                .set_column(j, &(origin_d_position.column(j) + dp * self.lever_arm_body));
            origin_d_attitude.set_column(j, &(da * self.lever_arm_body));
            direction_d_position.set_column(j, &(dp * d_body));
            direction_d_attitude.set_column(j, &(da * d_body));
        }
        LineOfSight {
            origin: self.position + c_fb * self.lever_arm_body,
            origin_d_position,
            origin_d_attitude,
            direction: c_fb * d_body,
            direction_d_position,
            direction_d_attitude,
            frame_from_sensor: c_fb * body_from_sensor,
        }
    }

    /// p_ms^s of eq. 21.45 and its Jacobians w.r.t. p, Ψ and m.
    pub fn relative_position(&self, feature: &Vector3<f64>) -> RelativePosition {
        let d = feature - self.position;
        let q_nav = self.ecef_from_ned.transpose() * d;
        let s_from_n = self.sensor_from_body * self.nav_from_body.transpose();
        let value = s_from_n * q_nav - self.sensor_from_body * self.lever_arm_body;
        let d_feature = s_from_n * self.ecef_from_ned.transpose();
        let mut d_position = -d_feature;
        let mut d_attitude = Matrix3::zeros();
        for j in 0..3 {
            d_position.set_column(
                j,
                &(d_position.column(j) + s_from_n * (self.ecef_from_ned_dp[j].transpose() * d)),
            );
            d_attitude.set_column(
                j,
                &(self.sensor_from_body * (self.nav_from_body_datt[j].transpose() * q_nav)),
            );
        }
        RelativePosition {
            value,
            d_position,
            d_attitude,
            d_feature,
        }
    }
}

/// A line of sight in the filter frame (eqs. 21.69, 21.70) with its Jacobians w.r.t. the pose.
#[derive(Clone, Copy, Debug)]
pub struct LineOfSight {
    /// y = p + C_n^e C_b^n p_sb^b: the sensor origin (eq. 21.69) [m].
    pub origin: Vector3<f64>,
    /// ∂y/∂p.
    pub origin_d_position: Matrix3<f64>,
    /// ∂y/∂Ψ.
    pub origin_d_attitude: Matrix3<f64>,
    /// u = C_n^e C_b^n C_s^b p̄^s: the direction (eq. 21.70; unit when p̄^s is).
    pub direction: Vector3<f64>,
    /// ∂u/∂p (non-zero in global SLAM only, through C_n^e(p)).
    pub direction_d_position: Matrix3<f64>,
    /// ∂u/∂Ψ.
    pub direction_d_attitude: Matrix3<f64>,
    /// C_s^frame = C_n^e C_b^n C_s^b (∂u/∂p̄^s).
    pub frame_from_sensor: Matrix3<f64>,
}

/// p_ms^s and its Jacobians.
#[derive(Clone, Copy, Debug)]
pub struct RelativePosition {
    /// p_ms^s [m].
    pub value: Vector3<f64>,
    /// ∂p_ms^s/∂p.
    pub d_position: Matrix3<f64>,
    /// ∂p_ms^s/∂Ψ.
    pub d_attitude: Matrix3<f64>,
    /// ∂p_ms^s/∂m.
    pub d_feature: Matrix3<f64>,
}

/// A predicted measurement H(x) and its Jacobians (rows = measurement dimension).
#[derive(Clone, Debug)]
pub struct Prediction {
    /// Predicted measurement.
    pub z: DVector<f64>,
    /// ∂H/∂p.
    pub d_position: MatrixXx3<f64>,
    /// ∂H/∂Ψ.
    pub d_attitude: MatrixXx3<f64>,
    /// ∂H/∂m.
    pub d_feature: MatrixXx3<f64>,
}

/// Range, azimuth, elevation of a sensor-frame point (eq. 21.41) and its 3×3 Jacobian.
pub fn range_bearing(p: &Vector3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
    let r2 = p.x * p.x + p.y * p.y;
    let rho2 = r2 + p.z * p.z;
    // The elevation is singular on the sensor z axis; refuse within 1e-9 m of it.
    if r2 < 1e-18 {
        return None;
    }
    let (r, rho) = (r2.sqrt(), rho2.sqrt());
    let z = Vector3::new(rho, p.y.atan2(p.x), p.z.atan2(r));
    let j = Matrix3::new(
        p.x / rho,
        p.y / rho,
        p.z / rho,
        -p.y / r2,
        p.x / r2,
        0.0,
        -p.x * p.z / (rho2 * r),
        -p.y * p.z / (rho2 * r),
        r / rho2,
    );
    Some((z, j))
}

/// Pixel coordinates of a sensor-frame point (eq. 21.43, erratum: x forward) and Jacobian.
pub fn pixel(
    camera: &CameraIntrinsics,
    p: &Vector3<f64>,
) -> Option<(Vector2<f64>, nalgebra::Matrix2x3<f64>)> {
    // Points at or behind the image plane have no projection; 1 mm margin.
    if p.x <= 1e-3 {
        return None;
    }
    let z = Vector2::new(
        camera.fu * p.y / p.x + camera.u0,
        camera.fv * p.z / p.x + camera.v0,
    );
    let x2 = p.x * p.x;
    let j = nalgebra::Matrix2x3::new(
        -camera.fu * p.y / x2,
        camera.fu / p.x,
        0.0,
        -camera.fv * p.z / x2,
        0.0,
        camera.fv / p.x,
    );
    Some((z, j))
}

/// Pixels → azimuth, elevation (eq. 21.44): φ = atan((u−u0)/f_u), ϑ = atan((v−v0)/f_v · cos φ).
pub fn angles_from_pixel(camera: &CameraIntrinsics, uv: &Vector2<f64>) -> Vector2<f64> {
    let az = ((uv.x - camera.u0) / camera.fu).atan();
    let el = ((uv.y - camera.v0) / camera.fv * az.cos()).atan();
    Vector2::new(az, el)
}

/// ∂(φ, ϑ)/∂(u, v) of eq. 21.44 (2×2, row-major [∂φ/∂u, ∂φ/∂v; ∂ϑ/∂u, ∂ϑ/∂v]).
pub fn angles_from_pixel_jacobian(camera: &CameraIntrinsics, uv: &Vector2<f64>) -> Matrix2<f64> {
    let a = (uv.x - camera.u0) / camera.fu;
    let b = (uv.y - camera.v0) / camera.fv;
    let az = a.atan();
    let (s, c) = az.sin_cos();
    let daz_du = 1.0 / ((1.0 + a * a) * camera.fu);
    let g = 1.0 / (1.0 + (b * c).powi(2));
    Matrix2::new(daz_du, 0.0, -g * b * s * daz_du, g * c / camera.fv)
}

/// The sensor-frame unit vector of azimuth φ and elevation ϑ (eq. 21.71) and its 3×2 Jacobian.
pub fn unit_from_angles(angles: &Vector2<f64>) -> (Vector3<f64>, Matrix3x2<f64>) {
    let (sa, ca) = angles.x.sin_cos();
    let (se, ce) = angles.y.sin_cos();
    (
        Vector3::new(ca * ce, sa * ce, se),
        Matrix3x2::new(-sa * ce, -ca * se, ca * ce, -sa * se, 0.0, ce),
    )
}

/// J_2 of eq. 21.50: the sensor-frame point of a range-bearing measurement, with ∂/∂z.
pub fn sensor_point_from_range_bearing(z: &Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
    let (rho, az, el) = (z.x, z.y, z.z);
    let (sa, ca) = az.sin_cos();
    let (se, ce) = el.sin_cos();
    let p = Vector3::new(rho * ca * ce, rho * sa * ce, rho * se);
    let j = Matrix3::new(
        ca * ce,
        -rho * sa * ce,
        -rho * ca * se,
        sa * ce,
        rho * ca * ce,
        -rho * sa * se,
        se,
        0.0,
        rho * ce,
    );
    (p, j)
}

/// A new feature from J_1 (eqs. 21.48/21.49) with ∇J_x (w.r.t. p, Ψ; every other state has a zero
/// Jacobian) and ∇J_z.
#[derive(Clone, Copy, Debug)]
pub struct Initialization {
    /// m = p + C_n^e C_b^n p_sb^b + C_n^e C_b^n C_s^b p_ms^s.
    pub feature: Vector3<f64>,
    /// ∂m/∂p.
    pub d_position: Matrix3<f64>,
    /// ∂m/∂Ψ.
    pub d_attitude: Matrix3<f64>,
    /// ∇J_z = ∂m/∂z.
    pub d_measurement: Matrix3<f64>,
}

/// A terrain sensor in a navigation frame: the observation function H and its inverse J.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObservationModel {
    /// Navigation frame of the filter.
    pub frame: NavFrame,
    /// Sensor kind and noise.
    pub sensor: SensorModel,
    /// Mounting (C_b^s, lever arm).
    pub mount: SensorMount,
}

impl ObservationModel {
    /// Dimension of one measurement (3 for range-bearing, 2 otherwise).
    pub fn measurement_dim(&self) -> usize {
        match self.sensor {
            SensorModel::RangeBearing { .. } => 3,
            SensorModel::Bearing { .. } | SensorModel::Pixel { .. } => 2,
        }
    }

    /// Measurement noise covariance R.
    pub fn noise_covariance(&self) -> DMatrix<f64> {
        let diag: Vec<f64> = match self.sensor {
            SensorModel::RangeBearing {
                sigma_range,
                sigma_bearing,
            } => {
                vec![
                    sigma_range.powi(2),
                    sigma_bearing.powi(2),
                    sigma_bearing.powi(2),
                ]
            }
            SensorModel::Bearing { sigma_bearing } => vec![sigma_bearing.powi(2); 2],
            SensorModel::Pixel { sigma_pixel, .. } => vec![sigma_pixel.powi(2); 2],
        };
        DMatrix::from_diagonal(&DVector::from_vec(diag))
    }

    /// Geometry at a vehicle pose.
    pub fn sensor_pose(&self, position: &Vector3<f64>, attitude: &Vector3<f64>) -> SensorPose {
        SensorPose::new(self.frame, &self.mount, position, attitude)
    }

    /// Checks a measurement (kind, finiteness, positive range, elevation within ±π/2, pixel
    /// inside the image) and returns it as a vector.
    pub fn measurement_vector(&self, z: &Measurement) -> Result<DVector<f64>, ObservationError> {
        let v = match (self.sensor, z) {
            (SensorModel::RangeBearing { .. }, Measurement::RangeBearing(v)) => {
                DVector::from_column_slice(v.as_slice())
            }
            (SensorModel::Bearing { .. }, Measurement::Bearing(v)) => {
                DVector::from_column_slice(v.as_slice())
            }
            (SensorModel::Pixel { .. }, Measurement::Pixel(v)) => {
                DVector::from_column_slice(v.as_slice())
            }
            _ => {
                return Err(ObservationError::KindMismatch {
                    expected: sensor_kind_name(&self.sensor),
                    got: kind_name(z),
                });
            }
        };
        if !v.iter().all(|x| x.is_finite()) {
            return Err(ObservationError::NonFinite);
        }
        if let Measurement::RangeBearing(rb) = z
            && rb.x <= 0.0
        {
            return Err(ObservationError::NonPositiveRange(rb.x));
        }
        let elevation = match z {
            Measurement::RangeBearing(rb) => Some(rb.z),
            Measurement::Bearing(b) => Some(b.y),
            Measurement::Pixel(_) => None,
        };
        if let Some(el) = elevation
            && el.abs() > std::f64::consts::FRAC_PI_2
        {
            return Err(ObservationError::ElevationOutOfRange(el));
        }
        if let (SensorModel::Pixel { camera, .. }, Measurement::Pixel(uv)) = (&self.sensor, z)
            && !(uv.x >= 0.0 && uv.x < camera.width && uv.y >= 0.0 && uv.y < camera.height)
        {
            return Err(ObservationError::OutsideImage { u: uv.x, v: uv.y });
        }
        Ok(v)
    }

    /// Index of the azimuth within the measurement vector, if the measurement has one.
    pub fn azimuth_index(&self) -> Option<usize> {
        match self.sensor {
            SensorModel::RangeBearing { .. } => Some(1),
            SensorModel::Bearing { .. } => Some(0),
            SensorModel::Pixel { .. } => None,
        }
    }

    /// Innovation ν = z − H(x) (eqs. 21.58/21.63) with the azimuth wrapped to (−π, π].
    pub fn innovation(&self, z: &DVector<f64>, predicted: &DVector<f64>) -> DVector<f64> {
        let mut nu = z - predicted;
        if let Some(i) = self.azimuth_index() {
            nu[i] = wrap_angle(nu[i]);
        }
        nu
    }

    /// Predicted measurement H(x) of a feature from a pose, with ∂H/∂(p, Ψ, m).
    pub fn predict(
        &self,
        pose: &SensorPose,
        feature: &Vector3<f64>,
    ) -> Result<Prediction, ObservationError> {
        let rel = pose.relative_position(feature);
        let (z, dz): (DVector<f64>, DMatrix<f64>) = match &self.sensor {
            SensorModel::RangeBearing { .. } => {
                let (z, j) =
                    range_bearing(&rel.value).ok_or(ObservationError::DegenerateGeometry)?;
                (
                    DVector::from_column_slice(z.as_slice()),
                    DMatrix::from_column_slice(3, 3, j.as_slice()),
                )
            }
            SensorModel::Bearing { .. } => {
                let (z, j) =
                    range_bearing(&rel.value).ok_or(ObservationError::DegenerateGeometry)?;
                (
                    DVector::from_column_slice(&z.as_slice()[1..]),
                    DMatrix::from_fn(2, 3, |r, c| j[(r + 1, c)]),
                )
            }
            SensorModel::Pixel { camera, .. } => {
                let (z, j) =
                    pixel(camera, &rel.value).ok_or(ObservationError::DegenerateGeometry)?;
                (
                    DVector::from_column_slice(z.as_slice()),
                    DMatrix::from_column_slice(2, 3, j.as_slice()),
                )
            }
        };
        let chain = |m: &Matrix3<f64>| -> MatrixXx3<f64> {
            MatrixXx3::from_fn(dz.nrows(), |r, c| (dz.row(r) * m.column(c))[0])
        };
        Ok(Prediction {
            z,
            d_position: chain(&rel.d_position),
            d_attitude: chain(&rel.d_attitude),
            d_feature: chain(&rel.d_feature),
        })
    }

    /// The line-of-sight direction p̄^s of a measurement in the sensor frame (eq. 21.44 for pixels,
    /// then eq. 21.71) with its Jacobian ∂p̄^s/∂z (3 × measurement dimension; the range column of
    /// a range-bearing measurement is zero).
    pub fn sensor_direction(
        &self,
        z: &DVector<f64>,
    ) -> Result<(Vector3<f64>, DMatrix<f64>), ObservationError> {
        let (angles, d_angles): (Vector2<f64>, DMatrix<f64>) = match &self.sensor {
            SensorModel::RangeBearing { .. } => (
                Vector2::new(z[1], z[2]),
                DMatrix::from_row_slice(2, 3, &[0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
            ),
            SensorModel::Bearing { .. } => (Vector2::new(z[0], z[1]), DMatrix::identity(2, 2)),
            SensorModel::Pixel { camera, .. } => {
                let uv = Vector2::new(z[0], z[1]);
                let j = angles_from_pixel_jacobian(camera, &uv);
                (
                    angles_from_pixel(camera, &uv),
                    DMatrix::from_fn(2, 2, |r, c| j[(r, c)]),
                )
            }
        };
        if !angles.iter().all(|a| a.is_finite()) {
            return Err(ObservationError::NonFinite);
        }
        let (unit, d_unit) = unit_from_angles(&angles);
        let d_unit = DMatrix::from_fn(3, 2, |r, c| d_unit[(r, c)]);
        Ok((unit, d_unit * d_angles))
    }

    /// Feature initialization J_1(x, J_2(z)) (eqs. 21.48–21.50) with ∇J_x and ∇J_z.
    pub fn initialize(
        &self,
        pose: &SensorPose,
        z: &DVector<f64>,
    ) -> Result<Initialization, ObservationError> {
        if !matches!(self.sensor, SensorModel::RangeBearing { .. }) {
            return Err(ObservationError::NotInitializable(sensor_kind_name(
                &self.sensor,
            )));
        }
        let (p_s, dp_dz) = sensor_point_from_range_bearing(&Vector3::new(z[0], z[1], z[2]));
        // q = p_sb^b + C_s^b p_ms^s (body frame); m = p + C_ne C_bn q.
        let q = pose.lever_arm_body + pose.sensor_from_body.transpose() * p_s;
        let c_fb = pose.ecef_from_ned * pose.nav_from_body;
        let feature = pose.position + c_fb * q;
        let mut d_position = Matrix3::identity();
        let mut d_attitude = Matrix3::zeros();
        for j in 0..3 {
            d_position.set_column(
                j,
                &(d_position.column(j) + pose.ecef_from_ned_dp[j] * pose.nav_from_body * q),
            );
            d_attitude.set_column(j, &(pose.ecef_from_ned * pose.nav_from_body_datt[j] * q));
        }
        let d_measurement = c_fb * pose.sensor_from_body.transpose() * dp_dz;
        Ok(Initialization {
            feature,
            d_position,
            d_attitude,
            d_measurement,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geodesy::Geodetic;

    fn camera() -> CameraIntrinsics {
        CameraIntrinsics {
            fu: 800.0,
            fv: 780.0,
            u0: 320.0,
            v0: 240.0,
            width: 640.0,
            height: 480.0,
        }
    }

    fn mount() -> SensorMount {
        // A slightly skewed downward mount with a lever arm, so every term of eq. 21.45 matters.
        let mut m = SensorMount::downward(Vector3::new(0.4, -0.1, 0.25));
        m.sensor_from_body =
            nav_from_body(&Vector3::new(0.05, -0.03, 0.02)).transpose() * m.sensor_from_body;
        m
    }

    /// (frame, vehicle position, attitude, feature).
    type Case = (NavFrame, Vector3<f64>, Vector3<f64>, Vector3<f64>);

    /// Cases: a feature ≈ 200 m below and ahead, in both frames.
    fn cases() -> Vec<Case> {
        let att = Vector3::new(0.1, -0.05, 0.7);
        let local_p = Vector3::new(50.0, 20.0, -200.0);
        let local_m = Vector3::new(90.0, 45.0, 3.0);
        let frame = geodesy::LocalFrame::new(Geodetic::from_degrees(-34.0, 150.6, 80.0));
        vec![
            (NavFrame::Local, local_p, att, local_m),
            (
                NavFrame::Global,
                frame.ecef_from_local(&local_p),
                att,
                frame.ecef_from_local(&local_m),
            ),
        ]
    }

    fn sensors() -> Vec<SensorModel> {
        vec![
            SensorModel::RangeBearing {
                sigma_range: 1.0,
                sigma_bearing: 0.01,
            },
            SensorModel::Bearing {
                sigma_bearing: 0.01,
            },
            SensorModel::Pixel {
                camera: camera(),
                sigma_pixel: 1.0,
            },
        ]
    }

    /// Element-wise |a − b| ≤ rel·|a| + abs (element-wise so that small angle rows are checked
    /// at their own scale, not hidden behind the range row).
    fn close(a: &DMatrix<f64>, b: &DMatrix<f64>, rel: f64, abs: f64) -> bool {
        a.iter()
            .zip(b.iter())
            .all(|(x, y)| (x - y).abs() <= rel * x.abs() + abs)
    }

    #[test]
    fn observation_jacobians_match_finite_differences_in_both_frames() {
        for (frame, p, att, m) in cases() {
            for sensor in sensors() {
                let model = ObservationModel {
                    frame,
                    sensor,
                    mount: mount(),
                };
                let pred = model.predict(&model.sensor_pose(&p, &att), &m).unwrap();
                // Steps: 0.1 m on positions (ECEF coordinates round at ≈ 1e-9 m, i.e. ≈ 5e-9 in a
                // range derivative; truncation h²/6·|∂³ρ| ≈ 0.01/6/ρ ≈ 1e-5·… ≈ 4e-8 at ρ ≈ 200 m)
                // and 1e-5 rad on angles (truncation ≈ 1e-10·ρ, rounding ≈ 1e-9).
                let fd = |which: usize, h: f64| -> DMatrix<f64> {
                    let mut out = DMatrix::zeros(pred.z.len(), 3);
                    for j in 0..3 {
                        let (mut pp, mut ap, mut mp) = (p, att, m);
                        let (mut pm, mut am, mut mm) = (p, att, m);
                        match which {
                            0 => {
                                pp[j] += h;
                                pm[j] -= h;
                            }
                            1 => {
                                ap[j] += h;
                                am[j] -= h;
                            }
                            _ => {
                                mp[j] += h;
                                mm[j] -= h;
                            }
                        }
                        let zp = model.predict(&model.sensor_pose(&pp, &ap), &mp).unwrap().z;
                        let zm = model.predict(&model.sensor_pose(&pm, &am), &mm).unwrap().z;
                        out.set_column(j, &(model.innovation(&zp, &zm) / (2.0 * h)));
                    }
                    out
                };
                let as_d = |m: &MatrixXx3<f64>| DMatrix::from_fn(m.nrows(), 3, |r, c| m[(r, c)]);
                // Tolerance 1e-6 relative + 1e-7 absolute: the truncation/rounding bounds above
                // with margin. The small C_n^e(p) term of the angle rows is checked tighter below.
                let label = format!("{frame} {sensor:?}");
                assert!(
                    close(&as_d(&pred.d_position), &fd(0, 0.1), 1e-6, 1e-7),
                    "∂H/∂p {label}"
                );
                assert!(
                    close(&as_d(&pred.d_attitude), &fd(1, 1e-5), 1e-6, 1e-7),
                    "∂H/∂Ψ {label}"
                );
                assert!(
                    close(&as_d(&pred.d_feature), &fd(2, 0.1), 1e-6, 1e-7),
                    "∂H/∂m {label}"
                );
                // Angle rows (scale 1/ρ ≈ 5e-3 m⁻¹) have FD error ≈ 1e-10: check them at 2e-9,
                // which the C_n^e(p) term of global ∂H/∂p (≈ 1.5e-7) would fail.
                if !matches!(sensor, SensorModel::Pixel { .. }) {
                    let first = if matches!(sensor, SensorModel::RangeBearing { .. }) {
                        1
                    } else {
                        0
                    };
                    let rows = pred.z.len() - first;
                    let a = as_d(&pred.d_position).rows(first, rows).into_owned();
                    let b = fd(0, 0.1).rows(first, rows).into_owned();
                    assert!(
                        close(&a, &b, 1e-6, 2e-9),
                        "∂(angles)/∂p {label}: {}",
                        (a - b).abs().max()
                    );
                }
            }
        }
    }

    #[test]
    fn global_position_jacobian_includes_the_latitude_longitude_dependence() {
        // Without the ∂C_ne/∂p term ∂H/∂p would equal −∂H/∂m; the difference is ≈ |m − p|/R_earth.
        let (frame, p, att, m) = cases()[1];
        let model = ObservationModel {
            frame,
            sensor: sensors()[0],
            mount: mount(),
        };
        let pred = model.predict(&model.sensor_pose(&p, &att), &m).unwrap();
        // Range is rotation invariant, so the term only shows in the angle rows (≈ |m−p|/R/ρ).
        let diff = (&pred.d_position + &pred.d_feature).rows(1, 2).norm();
        assert!(diff > 1e-8, "{diff}");
    }

    #[test]
    fn initialization_inverts_the_observation_and_its_jacobians_match_finite_differences() {
        for (frame, p, att, m) in cases() {
            let model = ObservationModel {
                frame,
                sensor: sensors()[0],
                mount: mount(),
            };
            let pose = model.sensor_pose(&p, &att);
            let z = model.predict(&pose, &m).unwrap().z;
            let init = model.initialize(&pose, &z).unwrap();
            // J_1(x, H(x, m)) = m up to the ECEF rounding of ≈ 1e-9 m per operation.
            assert!(
                (init.feature - m).norm() < 1e-7,
                "{frame}: {}",
                (init.feature - m).norm()
            );

            let j1 = |p: &Vector3<f64>, a: &Vector3<f64>, z: &DVector<f64>| {
                model
                    .initialize(&model.sensor_pose(p, a), z)
                    .unwrap()
                    .feature
            };
            let mut fd_p = Matrix3::zeros();
            let mut fd_a = Matrix3::zeros();
            let mut fd_z = Matrix3::zeros();
            for j in 0..3 {
                // Steps as in the ∇H test (1e-3 m, 1e-6 rad); the range step is 1e-3 m.
                let mut e = Vector3::zeros();
                e[j] = 1e-3;
                fd_p.set_column(
                    j,
                    &((j1(&(p + e), &att, &z) - j1(&(p - e), &att, &z)) / 2e-3),
                );
                let mut e = Vector3::zeros();
                e[j] = 1e-6;
                fd_a.set_column(
                    j,
                    &((j1(&p, &(att + e), &z) - j1(&p, &(att - e), &z)) / 2e-6),
                );
                let h = if j == 0 { 1e-3 } else { 1e-6 };
                let mut zp = z.clone();
                let mut zm = z.clone();
                zp[j] += h;
                zm[j] -= h;
                fd_z.set_column(j, &((j1(&p, &att, &zp) - j1(&p, &att, &zm)) / (2.0 * h)));
            }
            // ECEF outputs are ≈ 6e6 m: rounding 1e-9 m / 2e-6 rad ≈ 5e-4 absolute on ∇J_Ψ
            // (whose entries are ≈ 200 m), so 1e-5 relative; 1e-6 relative elsewhere.
            assert!(
                (init.d_position - fd_p).norm() < 1e-6 * init.d_position.norm(),
                "∇J_p {frame}"
            );
            assert!(
                (init.d_attitude - fd_a).norm() < 1e-5 * init.d_attitude.norm(),
                "∇J_Ψ {frame}"
            );
            assert!(
                (init.d_measurement - fd_z).norm() < 1e-5 * init.d_measurement.norm(),
                "∇J_z {frame}"
            );
            if frame == NavFrame::Global {
                // ∂C_n^e/∂p · C_bn q is ≈ |q|/R ≈ 3e-5: well above 1e-6.
                assert!((init.d_position - Matrix3::identity()).norm() > 1e-6);
            }
        }
    }

    #[test]
    fn pixel_to_angles_agrees_with_the_bearing_model() {
        let (frame, p, att, m) = cases()[0];
        let pix = ObservationModel {
            frame,
            sensor: sensors()[2],
            mount: mount(),
        };
        let brg = ObservationModel {
            frame,
            sensor: sensors()[1],
            mount: mount(),
        };
        let pose = pix.sensor_pose(&p, &att);
        let uv = pix.predict(&pose, &m).unwrap().z;
        let angles = angles_from_pixel(&camera(), &Vector2::new(uv[0], uv[1]));
        let direct = brg.predict(&pose, &m).unwrap().z;
        // Closed-form identity (21.44 inverts 21.43 for x > 0): only rounding remains.
        assert!((angles - Vector2::new(direct[0], direct[1])).norm() < 1e-13);
    }

    #[test]
    fn range_bearing_and_j2_are_inverse() {
        let p = Vector3::new(120.0, -30.0, 45.0);
        let (z, _) = range_bearing(&p).unwrap();
        let (back, _) = sensor_point_from_range_bearing(&z);
        // Closed-form inverse pair on a 130 m vector: round-off only.
        assert!((back - p).norm() < 1e-12);
    }

    #[test]
    fn azimuth_innovation_is_wrapped() {
        let model = ObservationModel {
            frame: NavFrame::Local,
            sensor: sensors()[0],
            mount: mount(),
        };
        let z = DVector::from_vec(vec![100.0, 3.1, 0.2]);
        let h = DVector::from_vec(vec![100.0, -3.1, 0.2]);
        let nu = model.innovation(&z, &h);
        // Exact wrap arithmetic on O(1) angles: round-off only.
        assert!((nu[1] - (6.2 - std::f64::consts::TAU)).abs() < 1e-12);
    }

    #[test]
    fn line_of_sight_and_sensor_direction_jacobians_match_finite_differences() {
        for (frame, p, att, m) in cases() {
            for sensor in sensors() {
                let model = ObservationModel {
                    frame,
                    sensor,
                    mount: mount(),
                };
                let pose = model.sensor_pose(&p, &att);
                let z = model.predict(&pose, &m).unwrap().z;
                let (dir, d_dir) = model.sensor_direction(&z).unwrap();
                let los = pose.line_of_sight(&dir);
                // The line of sight of a noise-free measurement passes through the feature: the
                // distance of m from the line is round-off only (ECEF ≈ 6e6 m: 1e-9 m per op).
                let off = m - los.origin;
                let miss = (off - los.direction * off.dot(&los.direction)).norm();
                assert!(miss < 1e-6, "{frame} {sensor:?}: miss {miss}");
                assert!((los.direction.norm() - 1.0).abs() < 1e-12);
                // Central differences: 0.1 m on positions (the functions are smooth on the
                // Earth-radius scale: truncation ≈ h²/R² ≈ 1e-16), 1e-5 rad on angles (truncation
                // ≈ 1e-10), 1e-4 px / 1e-6 rad on measurements; ECEF rounding ≈ 1e-9 m / 0.2 m
                // ≈ 5e-9 dominates the origin's position derivative.
                let eval = |p: &Vector3<f64>, a: &Vector3<f64>| {
                    let l = model.sensor_pose(p, a).line_of_sight(&dir);
                    (l.origin, l.direction)
                };
                for j in 0..3 {
                    let mut e = Vector3::zeros();
                    e[j] = 0.1;
                    let (yp, up) = eval(&(p + e), &att);
                    let (ym, um) = eval(&(p - e), &att);
                    let fd_y = (yp - ym) / 0.2;
                    let fd_u = (up - um) / 0.2;
                    assert!((fd_y - los.origin_d_position.column(j)).norm() < 1e-7);
                    assert!((fd_u - los.direction_d_position.column(j)).norm() < 1e-12);
                    let mut e = Vector3::zeros();
                    e[j] = 1e-5;
                    let (yp, up) = eval(&p, &(att + e));
                    let (ym, um) = eval(&p, &(att - e));
                    let fd_y = (yp - ym) / 2e-5;
                    let fd_u = (up - um) / 2e-5;
                    // y: ECEF rounding 1e-9 m / 2e-5 rad ≈ 5e-5 absolute (lever arm ≈ 0.5 m).
                    assert!((fd_y - los.origin_d_attitude.column(j)).norm() < 2e-4);
                    assert!((fd_u - los.direction_d_attitude.column(j)).norm() < 1e-9);
                }
                let h = if matches!(sensor, SensorModel::Pixel { .. }) {
                    1e-4
                } else {
                    1e-6
                };
                for j in 0..z.len() {
                    let mut zp = z.clone();
                    let mut zm = z.clone();
                    zp[j] += h;
                    zm[j] -= h;
                    let fd = (model.sensor_direction(&zp).unwrap().0
                        - model.sensor_direction(&zm).unwrap().0)
                        / (2.0 * h);
                    // Unit-vector entries O(1), curvature O(1/f²) per px²: truncation ≤ 1e-12.
                    assert!(
                        (fd - d_dir.column(j)).norm() < 1e-8,
                        "∂p̄/∂z {sensor:?} column {j}"
                    );
                }
            }
        }
    }

    #[test]
    fn pixels_outside_the_image_and_impossible_elevations_are_typed_errors() {
        let cam = ObservationModel {
            frame: NavFrame::Local,
            sensor: sensors()[2],
            mount: mount(),
        };
        for (u, v) in [(-0.5, 10.0), (640.0, 10.0), (10.0, -1e-9), (10.0, 480.0)] {
            assert_eq!(
                cam.measurement_vector(&Measurement::Pixel(Vector2::new(u, v))),
                Err(ObservationError::OutsideImage { u, v })
            );
        }
        assert!(
            cam.measurement_vector(&Measurement::Pixel(Vector2::new(0.0, 479.9)))
                .is_ok()
        );
        assert_eq!(
            cam.measurement_vector(&Measurement::Pixel(Vector2::new(f64::NAN, 1.0))),
            Err(ObservationError::NonFinite)
        );
        let brg = ObservationModel {
            frame: NavFrame::Local,
            sensor: sensors()[1],
            mount: mount(),
        };
        assert_eq!(
            brg.measurement_vector(&Measurement::Bearing(Vector2::new(0.1, 1.6))),
            Err(ObservationError::ElevationOutOfRange(1.6))
        );
    }

    #[test]
    fn invalid_measurements_are_typed_errors() {
        let model = ObservationModel {
            frame: NavFrame::Local,
            sensor: sensors()[0],
            mount: mount(),
        };
        assert_eq!(
            model.measurement_vector(&Measurement::RangeBearing(Vector3::new(1.0, f64::NAN, 0.0))),
            Err(ObservationError::NonFinite)
        );
        assert_eq!(
            model.measurement_vector(&Measurement::RangeBearing(Vector3::new(-1.0, 0.0, 0.0))),
            Err(ObservationError::NonPositiveRange(-1.0))
        );
        assert!(matches!(
            model.measurement_vector(&Measurement::Pixel(Vector2::new(1.0, 2.0))),
            Err(ObservationError::KindMismatch { .. })
        ));
        let cam = ObservationModel {
            frame: NavFrame::Local,
            sensor: sensors()[2],
            mount: mount(),
        };
        let pose = cam.sensor_pose(&Vector3::zeros(), &Vector3::zeros());
        // The downward camera cannot see a point above the vehicle.
        assert_eq!(
            cam.predict(&pose, &Vector3::new(0.0, 0.0, -10.0))
                .unwrap_err(),
            ObservationError::DegenerateGeometry
        );
    }
}
