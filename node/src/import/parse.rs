//! Readers of the recording files `canopy import` understands. Every error names the file,
//! the line (1-based; 1 for whole-file problems) and the reason.
//!
//! - IMU: the EuRoC / ASL `imu0/data.csv` layout: `timestamp [ns], w_RS_S_x, w_RS_S_y,
//!   w_RS_S_z [rad s^-1], a_RS_S_x, a_RS_S_y, a_RS_S_z [m s^-2]`.
//! - Feature tracks: `timestamp, track_id, x_n, y_n` (undistorted normalized coordinates
//!   x_n = X_c/Z_c, y_n = Y_c/Z_c of the camera frame: z forward, x right, y down) or
//!   `timestamp, track_id, u, v` (raw-image pixels, undistorted with the calibration).
//! - Ground truth: TUM (`timestamp tx ty tz qx qy qz qw`, seconds, space separated) or the ASL
//!   `state_groundtruth_estimate0/data.csv` (`timestamp [ns], p_RS_R_xyz, q_RS_wxyz, v_RS_R_xyz,
//!   b_w_RS_S_xyz, b_a_RS_S_xyz`).
//! - Calibration: EuRoC `sensor.yaml` (camera: `T_BS`, `intrinsics`, `distortion_model`,
//!   `distortion_coefficients`, `resolution`; IMU: noise densities), or a Kalibr
//!   `camchain-imucam.yaml` (`cam0`: `T_cam_imu`, `intrinsics`, `distortion_model`,
//!   `distortion_coeffs`, `resolution`).
//!
//! Timestamps: an integer is nanoseconds; a number with a decimal point is seconds (at most
//! nine decimals). Both are read exactly into integer nanoseconds (no f64 rounding: 1.4e9 s
//! as f64 would keep only ~0.2 µs).

use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Matrix4, UnitQuaternion, Vector3};

use super::camera::{Camera, Distortion};

/// An unreadable or malformed recording file, or a missing one.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A line (or the file) is malformed.
    #[error("{path}:{line}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// Something the import needs is not there.
    #[error("{0}")]
    Missing(String),
}

fn bad(path: &Path, line: usize, reason: impl Into<String>) -> ImportError {
    ImportError::Format {
        path: path.to_path_buf(),
        line,
        reason: reason.into(),
    }
}

/// Reads a file as text.
pub fn read(path: &Path) -> Result<String, ImportError> {
    std::fs::read_to_string(path).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// A timestamp in integer nanoseconds: an integer is nanoseconds, a decimal seconds.
pub fn parse_time_ns(s: &str) -> Result<u64, String> {
    let s = s.trim();
    let err = || format!("timestamp `{s}` is not a non-negative integer [ns] or decimal [s]");
    match s.split_once('.') {
        None => s.parse::<u64>().map_err(|_| err()),
        Some((sec, frac)) => {
            if frac.len() > 9 {
                return Err(format!(
                    "timestamp `{s}` has more than nine decimals (below a nanosecond)"
                ));
            }
            if sec.is_empty()
                || !sec.bytes().all(|b| b.is_ascii_digit())
                || !frac.bytes().all(|b| b.is_ascii_digit())
            {
                return Err(err());
            }
            let sec: u64 = sec.parse().map_err(|_| err())?;
            let frac_ns: u64 = if frac.is_empty() {
                0
            } else {
                frac.parse::<u64>().map_err(|_| err())? * 10u64.pow(9 - frac.len() as u32)
            };
            sec.checked_mul(1_000_000_000)
                .and_then(|x| x.checked_add(frac_ns))
                .ok_or_else(err)
        }
    }
}

fn number(path: &Path, line: usize, name: &str, s: &str) -> Result<f64, ImportError> {
    let v: f64 = s.trim().parse().map_err(|_| {
        bad(
            path,
            line,
            format!("`{name}` = `{}` is not a number", s.trim()),
        )
    })?;
    if !v.is_finite() {
        return Err(bad(
            path,
            line,
            format!("`{name}` = `{}` is not finite", s.trim()),
        ));
    }
    Ok(v)
}

/// A column name without its unit and decoration: `w_RS_S_x [rad s^-1]` → `w_rs_s_x`.
fn column_name(s: &str) -> String {
    let s = s.trim().trim_start_matches('#').trim();
    let s = s.split('[').next().unwrap_or("").trim();
    s.to_ascii_lowercase()
}

/// A CSV file's column names and its data lines (line number, fields).
type CsvTable = (Vec<String>, Vec<(usize, Vec<String>)>);

/// Data lines of a CSV file with a header line (commented with `#` or not): the header's
/// column names and (line, fields) of every other non-empty line. Every line must have as many
/// fields as the header.
fn csv_lines(path: &Path, text: &str, sep: char) -> Result<CsvTable, ImportError> {
    let mut header: Option<Vec<String>> = None;
    let mut rows = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let n = i + 1;
        let l = raw.trim();
        if l.is_empty() {
            continue;
        }
        let split = |l: &str| -> Vec<String> {
            if sep == ' ' {
                l.split_whitespace().map(str::to_string).collect()
            } else {
                l.split(sep).map(|f| f.trim().to_string()).collect()
            }
        };
        match &header {
            None => header = Some(split(l).iter().map(|c| column_name(c)).collect()),
            Some(h) => {
                if l.starts_with('#') {
                    continue;
                }
                let f = split(l);
                if f.len() != h.len() {
                    return Err(bad(
                        path,
                        n,
                        format!(
                            "{} fields, expected {} (the header's columns{})",
                            f.len(),
                            h.len(),
                            if f.len() < h.len() {
                                "; a truncated line?"
                            } else {
                                ""
                            }
                        ),
                    ));
                }
                rows.push((n, f));
            }
        }
    }
    let Some(header) = header else {
        return Err(bad(path, 1, "empty file: no header, no data"));
    };
    if rows.is_empty() {
        return Err(bad(path, 1, "no data lines after the header"));
    }
    Ok((header, rows))
}

fn expect_columns(
    path: &Path,
    header: &[String],
    want: &[&str],
    layout: &str,
) -> Result<(), ImportError> {
    if header.len() != want.len() {
        return Err(bad(
            path,
            1,
            format!(
                "{} columns, expected {} ({layout}: {})",
                header.len(),
                want.len(),
                want.join(", ")
            ),
        ));
    }
    for (k, (got, w)) in header.iter().zip(want).enumerate() {
        if got != w {
            return Err(bad(
                path,
                1,
                format!(
                    "unknown column `{got}` at position {}: expected `{w}` ({layout}: {})",
                    k + 1,
                    want.join(", ")
                ),
            ));
        }
    }
    Ok(())
}

/// One raw IMU sample of the recording (IMU axes S).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RawImu {
    /// Timestamp [ns].
    pub t_ns: u64,
    /// Angular rate ω^S [rad/s].
    pub gyro: Vector3<f64>,
    /// Specific force f^S [m/s²].
    pub accel: Vector3<f64>,
    /// Line in the file.
    pub line: usize,
}

/// Checks that timestamps strictly increase.
fn increasing(path: &Path, prev: Option<u64>, t: u64, line: usize) -> Result<(), ImportError> {
    if let Some(p) = prev
        && t <= p
    {
        return Err(bad(
            path,
            line,
            format!(
                "timestamp {t} ns is {} the previous one ({p} ns): timestamps must increase",
                if t == p { "equal to" } else { "before" }
            ),
        ));
    }
    Ok(())
}

/// Reads an EuRoC/ASL IMU CSV.
pub fn imu_csv(path: &Path) -> Result<Vec<RawImu>, ImportError> {
    let (header, rows) = csv_lines(path, &read(path)?, ',')?;
    expect_columns(
        path,
        &header,
        &[
            "timestamp",
            "w_rs_s_x",
            "w_rs_s_y",
            "w_rs_s_z",
            "a_rs_s_x",
            "a_rs_s_y",
            "a_rs_s_z",
        ],
        "EuRoC/ASL IMU layout",
    )?;
    let names = [
        "w_RS_S_x", "w_RS_S_y", "w_RS_S_z", "a_RS_S_x", "a_RS_S_y", "a_RS_S_z",
    ];
    let mut out: Vec<RawImu> = Vec::with_capacity(rows.len());
    for (n, f) in rows {
        let t_ns = parse_time_ns(&f[0]).map_err(|r| bad(path, n, r))?;
        increasing(path, out.last().map(|x| x.t_ns), t_ns, n)?;
        let mut v = [0.0; 6];
        for k in 0..6 {
            v[k] = number(path, n, names[k], &f[k + 1])?;
        }
        out.push(RawImu {
            t_ns,
            gyro: Vector3::new(v[0], v[1], v[2]),
            accel: Vector3::new(v[3], v[4], v[5]),
            line: n,
        });
    }
    Ok(out)
}

/// How a track file gives its coordinates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackCoordinates {
    /// Undistorted normalized x_n = X_c/Z_c, y_n = Y_c/Z_c.
    Normalized,
    /// Raw-image pixels (u, v).
    Pixels,
}

/// One feature-track observation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackObservation {
    /// Timestamp [ns].
    pub t_ns: u64,
    /// Track id.
    pub id: u64,
    /// The two coordinates as given.
    pub xy: [f64; 2],
    /// Line in the file.
    pub line: usize,
}

/// Reads a feature-track CSV: `timestamp, track_id, x_n, y_n` or `timestamp, track_id, u, v`
/// (header required), timestamps non-decreasing (rows of one time form a frame), a track id at
/// most once per frame.
pub fn tracks_csv(path: &Path) -> Result<(TrackCoordinates, Vec<TrackObservation>), ImportError> {
    let (header, rows) = csv_lines(path, &read(path)?, ',')?;
    let coords = match header.get(2..4) {
        Some([a, b]) if a == "x_n" && b == "y_n" => TrackCoordinates::Normalized,
        Some([a, b]) if a == "u" && b == "v" => TrackCoordinates::Pixels,
        _ => {
            return Err(bad(
                path,
                1,
                format!(
                    "unknown columns `{}`: expected `timestamp, track_id, x_n, y_n` (normalized) \
                     or `timestamp, track_id, u, v` (pixels)",
                    header.join(", ")
                ),
            ));
        }
    };
    let want = match coords {
        TrackCoordinates::Normalized => ["timestamp", "track_id", "x_n", "y_n"],
        TrackCoordinates::Pixels => ["timestamp", "track_id", "u", "v"],
    };
    expect_columns(path, &header, &want, "feature-track layout")?;
    let mut out: Vec<TrackObservation> = Vec::with_capacity(rows.len());
    let mut frame_ids: std::collections::HashSet<u64> = std::collections::HashSet::new();
    for (n, f) in rows {
        let t_ns = parse_time_ns(&f[0]).map_err(|r| bad(path, n, r))?;
        if let Some(p) = out.last() {
            if t_ns < p.t_ns {
                return Err(bad(
                    path,
                    n,
                    format!(
                        "timestamp {t_ns} ns is before the previous row's ({} ns): rows must be \
                         in time order",
                        p.t_ns
                    ),
                ));
            }
            if t_ns != p.t_ns {
                frame_ids.clear();
            }
        }
        let id: u64 = f[1].parse().map_err(|_| {
            bad(
                path,
                n,
                format!("track id `{}` is not a non-negative integer", f[1]),
            )
        })?;
        if id >= canopy_fusion::slam::FRESH_ID_BASE {
            return Err(bad(
                path,
                n,
                format!("track id {id} is ≥ 2⁶³, the range the filter reserves for its own ids"),
            ));
        }
        if !frame_ids.insert(id) {
            return Err(bad(
                path,
                n,
                format!("track id {id} appears twice in the frame at {t_ns} ns"),
            ));
        }
        let x = number(path, n, want[2], &f[2])?;
        let y = number(path, n, want[3], &f[3])?;
        out.push(TrackObservation {
            t_ns,
            id,
            xy: [x, y],
            line: n,
        });
    }
    Ok((coords, out))
}

/// One ground-truth pose of the IMU frame S in the world frame W (z up).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundTruth {
    /// Timestamp [ns].
    pub t_ns: u64,
    /// p^W of S's origin [m].
    pub position: Vector3<f64>,
    /// C_S^W as a unit quaternion (Hamilton).
    pub world_from_imu: UnitQuaternion<f64>,
    /// v^W [m/s] (ASL layout only).
    pub velocity: Option<Vector3<f64>>,
    /// Gyro and accelerometer bias estimates in S (ASL layout only).
    pub biases: Option<(Vector3<f64>, Vector3<f64>)>,
}

fn quaternion(
    path: &Path,
    n: usize,
    w: f64,
    x: f64,
    y: f64,
    z: f64,
) -> Result<UnitQuaternion<f64>, ImportError> {
    let q = nalgebra::Quaternion::new(w, x, y, z);
    let norm = q.norm();
    // Text with six decimals keeps the norm within ~1e-5 of 1; far off means a wrong column.
    if (norm - 1.0).abs() > 1e-3 {
        return Err(bad(
            path,
            n,
            format!("quaternion norm {norm} is not 1 (wrong column order?)"),
        ));
    }
    Ok(UnitQuaternion::from_quaternion(q))
}

/// Reads ground truth: TUM (`.tum`, `.txt`) or ASL (`.csv`) by the file's extension.
pub fn ground_truth(path: &Path) -> Result<Vec<GroundTruth>, ImportError> {
    let text = read(path)?;
    let asl = path.extension().is_some_and(|e| e == "csv");
    let mut out: Vec<GroundTruth> = Vec::new();
    if asl {
        let (header, rows) = csv_lines(path, &text, ',')?;
        let want = [
            "timestamp",
            "p_rs_r_x",
            "p_rs_r_y",
            "p_rs_r_z",
            "q_rs_w",
            "q_rs_x",
            "q_rs_y",
            "q_rs_z",
            "v_rs_r_x",
            "v_rs_r_y",
            "v_rs_r_z",
            "b_w_rs_s_x",
            "b_w_rs_s_y",
            "b_w_rs_s_z",
            "b_a_rs_s_x",
            "b_a_rs_s_y",
            "b_a_rs_s_z",
        ];
        expect_columns(
            path,
            &header,
            &want,
            "ASL state_groundtruth_estimate0 layout",
        )?;
        for (n, f) in rows {
            let t_ns = parse_time_ns(&f[0]).map_err(|r| bad(path, n, r))?;
            increasing(path, out.last().map(|g| g.t_ns), t_ns, n)?;
            let mut v = [0.0; 16];
            for k in 0..16 {
                v[k] = number(path, n, want[k + 1], &f[k + 1])?;
            }
            out.push(GroundTruth {
                t_ns,
                position: Vector3::new(v[0], v[1], v[2]),
                world_from_imu: quaternion(path, n, v[3], v[4], v[5], v[6])?,
                velocity: Some(Vector3::new(v[7], v[8], v[9])),
                biases: Some((
                    Vector3::new(v[10], v[11], v[12]),
                    Vector3::new(v[13], v[14], v[15]),
                )),
            });
        }
    } else {
        let names = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"];
        for (i, raw) in text.lines().enumerate() {
            let n = i + 1;
            let l = raw.trim();
            if l.is_empty() || l.starts_with('#') {
                continue;
            }
            let f: Vec<&str> = l.split_whitespace().collect();
            if f.len() != 8 {
                return Err(bad(
                    path,
                    n,
                    format!(
                        "{} fields, expected 8 (TUM: timestamp tx ty tz qx qy qz qw)",
                        f.len()
                    ),
                ));
            }
            let t_ns = parse_time_ns(f[0]).map_err(|r| bad(path, n, r))?;
            increasing(path, out.last().map(|g| g.t_ns), t_ns, n)?;
            let mut v = [0.0; 7];
            for k in 0..7 {
                v[k] = number(path, n, names[k], f[k + 1])?;
            }
            out.push(GroundTruth {
                t_ns,
                position: Vector3::new(v[0], v[1], v[2]),
                world_from_imu: quaternion(path, n, v[6], v[3], v[4], v[5])?,
                velocity: None,
                biases: None,
            });
        }
        if out.is_empty() {
            return Err(bad(path, 1, "no poses (empty TUM file)"));
        }
    }
    Ok(out)
}

/// A camera calibration relative to the IMU.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraCalibration {
    /// The camera model of the raw image.
    pub camera: Camera,
    /// C_C^S: rotates camera-frame vectors into IMU axes.
    pub imu_from_camera: Matrix3<f64>,
    /// The camera's origin in IMU axes [m].
    pub camera_in_imu: Vector3<f64>,
    /// Frame rate [Hz], when the calibration says.
    pub rate_hz: Option<f64>,
}

/// IMU noise figures of a calibration (EuRoC `imu0/sensor.yaml`, Kalibr `imu.yaml`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuCalibration {
    /// gyroscope_noise_density [rad/s/√Hz].
    pub gyro_noise_density: f64,
    /// gyroscope_random_walk [rad/s²/√Hz].
    pub gyro_random_walk: f64,
    /// accelerometer_noise_density [m/s²/√Hz].
    pub accel_noise_density: f64,
    /// accelerometer_random_walk [m/s³/√Hz].
    pub accel_random_walk: f64,
    /// T_BS of the IMU (its pose in the sensor body frame B), when given.
    pub body_from_imu: Option<Matrix4<f64>>,
}

fn yaml(path: &Path) -> Result<serde_yaml::Value, ImportError> {
    serde_yaml::from_str(&read(path)?).map_err(|e| {
        bad(
            path,
            e.location().map_or(1, |l| l.line()),
            format!("not valid YAML: {e}"),
        )
    })
}

fn field<'a>(
    path: &Path,
    v: &'a serde_yaml::Value,
    key: &str,
    what: &str,
) -> Result<&'a serde_yaml::Value, ImportError> {
    v.get(key).ok_or_else(|| {
        bad(
            path,
            1,
            format!("missing calibration field `{key}` ({what})"),
        )
    })
}

fn floats(
    path: &Path,
    v: &serde_yaml::Value,
    key: &str,
    n: usize,
) -> Result<Vec<f64>, ImportError> {
    let seq = v
        .as_sequence()
        .ok_or_else(|| bad(path, 1, format!("`{key}` must be a list of {n} numbers")))?;
    let flat: Vec<&serde_yaml::Value> = seq
        .iter()
        .flat_map(|x| match x.as_sequence() {
            Some(row) => row.iter().collect::<Vec<_>>(),
            None => vec![x],
        })
        .collect();
    let nums: Option<Vec<f64>> = flat.iter().map(|x| x.as_f64()).collect();
    match nums {
        Some(v) if v.len() == n && v.iter().all(|x| x.is_finite()) => Ok(v),
        _ => Err(bad(
            path,
            1,
            format!("`{key}` must be {n} finite numbers, got {}", flat.len()),
        )),
    }
}

fn float(path: &Path, v: &serde_yaml::Value, key: &str, what: &str) -> Result<f64, ImportError> {
    let x = field(path, v, key, what)?;
    x.as_f64()
        .filter(|x| x.is_finite())
        .ok_or_else(|| bad(path, 1, format!("`{key}` must be a finite number ({what})")))
}

fn distortion(path: &Path, model: &str, coeffs: &[f64]) -> Result<Distortion, ImportError> {
    let c4 = || -> Result<[f64; 4], ImportError> {
        coeffs.try_into().map_err(|_| {
            bad(
                path,
                1,
                format!(
                    "distortion `{model}` needs 4 coefficients, got {}",
                    coeffs.len()
                ),
            )
        })
    };
    match model {
        "radial-tangential" | "radtan" => Ok(Distortion::RadTan(c4()?)),
        "equidistant" => Ok(Distortion::Equidistant(c4()?)),
        "none" => Ok(Distortion::None),
        other => Err(bad(
            path,
            1,
            format!(
                "distortion model `{other}` is not radial-tangential (radtan), equidistant or none"
            ),
        )),
    }
}

fn rigid(path: &Path, key: &str, m: Matrix4<f64>) -> Result<Matrix4<f64>, ImportError> {
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into();
    // Calibration files print 8+ digits: orthonormal to ~1e-7; 1e-5 catches wrong matrices.
    let err = (r * r.transpose() - Matrix3::identity()).abs().max();
    if err > 1e-5 || r.determinant() < 0.0 {
        return Err(bad(
            path,
            1,
            format!(
                "`{key}` is not a rigid transform (|R·Rᵀ − I| = {err:.2e}, det {:.4})",
                r.determinant()
            ),
        ));
    }
    // Re-orthonormalise (nearest rotation) so the chain of frames stays exact.
    let svd = r.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Err(bad(path, 1, format!("`{key}`: SVD failed")));
    };
    let mut out = m;
    out.fixed_view_mut::<3, 3>(0, 0).copy_from(&(u * vt));
    Ok(out)
}

/// Reads a EuRoC camera `sensor.yaml` (`T_BS` = camera pose in the body frame, which EuRoC's
/// IMU defines; `body_from_imu` composes another IMU pose when the IMU's own `T_BS` is not
/// identity).
pub fn euroc_camera(
    path: &Path,
    body_from_imu: Option<Matrix4<f64>>,
) -> Result<CameraCalibration, ImportError> {
    let v = yaml(path)?;
    let t = field(path, &v, "T_BS", "camera pose in the body frame")?;
    let data = floats(path, field(path, t, "data", "T_BS data")?, "T_BS.data", 16)?;
    let body_from_cam = rigid(path, "T_BS", Matrix4::from_row_slice(&data))?;
    let imu_from_body = match body_from_imu {
        Some(b) => b
            .try_inverse()
            .ok_or_else(|| bad(path, 1, "IMU T_BS is singular"))?,
        None => Matrix4::identity(),
    };
    let imu_from_cam = imu_from_body * body_from_cam;
    let camera = camera_model(path, &v, "distortion_model", "distortion_coefficients")?;
    Ok(CameraCalibration {
        camera,
        imu_from_camera: imu_from_cam.fixed_view::<3, 3>(0, 0).into(),
        camera_in_imu: imu_from_cam.fixed_view::<3, 1>(0, 3).into(),
        rate_hz: v.get("rate_hz").and_then(serde_yaml::Value::as_f64),
    })
}

fn camera_model(
    path: &Path,
    v: &serde_yaml::Value,
    model_key: &str,
    coeff_key: &str,
) -> Result<Camera, ImportError> {
    if let Some(m) = v.get("camera_model").and_then(serde_yaml::Value::as_str)
        && m != "pinhole"
    {
        return Err(bad(path, 1, format!("camera model `{m}` is not pinhole")));
    }
    let k = floats(
        path,
        field(path, v, "intrinsics", "fu, fv, cu, cv")?,
        "intrinsics",
        4,
    )?;
    let res = floats(
        path,
        field(path, v, "resolution", "width, height")?,
        "resolution",
        2,
    )?;
    if !(k[0] > 0.0 && k[1] > 0.0 && res[0] > 0.0 && res[1] > 0.0) {
        return Err(bad(
            path,
            1,
            "focal lengths and resolution must be positive",
        ));
    }
    let model = field(path, v, model_key, "lens distortion model")?
        .as_str()
        .ok_or_else(|| bad(path, 1, format!("`{model_key}` must be a string")))?;
    let coeffs = match v.get(coeff_key) {
        Some(c) => {
            let n = c.as_sequence().map_or(0, Vec::len);
            floats(path, c, coeff_key, n)?
        }
        None if model == "none" => Vec::new(),
        None => {
            return Err(bad(
                path,
                1,
                format!("missing calibration field `{coeff_key}`"),
            ));
        }
    };
    Ok(Camera {
        intrinsics: [k[0], k[1], k[2], k[3]],
        resolution: [res[0], res[1]],
        distortion: distortion(path, model, &coeffs)?,
    })
}

/// Reads `cam0` of a Kalibr `camchain-imucam.yaml` (`T_cam_imu` maps IMU points into the
/// camera frame).
pub fn kalibr_camera(path: &Path) -> Result<CameraCalibration, ImportError> {
    let v = yaml(path)?;
    let cam = field(path, &v, "cam0", "the first camera")?;
    let data = floats(
        path,
        field(path, cam, "T_cam_imu", "IMU-to-camera transform")?,
        "T_cam_imu",
        16,
    )?;
    let cam_from_imu = rigid(path, "T_cam_imu", Matrix4::from_row_slice(&data))?;
    let imu_from_cam = cam_from_imu
        .try_inverse()
        .ok_or_else(|| bad(path, 1, "T_cam_imu is singular"))?;
    let camera = camera_model(path, cam, "distortion_model", "distortion_coeffs")?;
    Ok(CameraCalibration {
        camera,
        imu_from_camera: imu_from_cam.fixed_view::<3, 3>(0, 0).into(),
        camera_in_imu: imu_from_cam.fixed_view::<3, 1>(0, 3).into(),
        rate_hz: None,
    })
}

/// Reads IMU noise figures (EuRoC `imu0/sensor.yaml` or Kalibr `imu.yaml`).
pub fn imu_calibration(path: &Path) -> Result<ImuCalibration, ImportError> {
    let v = yaml(path)?;
    let body_from_imu = match v.get("T_BS") {
        Some(t) => {
            let data = floats(path, field(path, t, "data", "T_BS data")?, "T_BS.data", 16)?;
            Some(rigid(path, "T_BS", Matrix4::from_row_slice(&data))?)
        }
        None => None,
    };
    Ok(ImuCalibration {
        gyro_noise_density: float(path, &v, "gyroscope_noise_density", "rad/s/√Hz")?,
        gyro_random_walk: float(path, &v, "gyroscope_random_walk", "rad/s²/√Hz")?,
        accel_noise_density: float(path, &v, "accelerometer_noise_density", "m/s²/√Hz")?,
        accel_random_walk: float(path, &v, "accelerometer_random_walk", "m/s³/√Hz")?,
        body_from_imu,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn file(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    const IMU_HEADER: &str = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n";

    #[test]
    fn timestamps_read_exactly() {
        assert_eq!(
            parse_time_ns("1403715273262143232"),
            Ok(1_403_715_273_262_143_232)
        );
        assert_eq!(
            parse_time_ns("1403715273.26214"),
            Ok(1_403_715_273_262_140_000)
        );
        assert_eq!(
            parse_time_ns("1403715273.262143232"),
            Ok(1_403_715_273_262_143_232)
        );
        assert_eq!(parse_time_ns("12."), Ok(12_000_000_000));
        for bad in ["-5", "1e9", "1.2.3", ".5", "1.0000000001", "nan", ""] {
            assert!(parse_time_ns(bad).is_err(), "{bad}");
        }
    }

    /// Each kind of bad recording gets an error naming the file, the line and the reason.
    #[test]
    fn bad_recordings_name_file_line_and_reason() {
        let dir = tempfile::tempdir().unwrap();
        let good = "1000,0.1,0.2,0.3,9.8,0.0,0.1\n";
        let cases: Vec<(&str, String, usize, &str)> = vec![
            (
                "truncated",
                format!("{IMU_HEADER}{good}2000,0.1,0.2"),
                3,
                "truncated",
            ),
            (
                "backwards",
                format!("{IMU_HEADER}{good}500,0.1,0.2,0.3,9.8,0.0,0.1\n"),
                3,
                "before the previous",
            ),
            (
                "repeated",
                format!("{IMU_HEADER}{good}{good}"),
                3,
                "equal to the previous",
            ),
            (
                "nan",
                format!("{IMU_HEADER}{good}2000,0.1,NaN,0.3,9.8,0.0,0.1\n"),
                3,
                "not finite",
            ),
            (
                "text",
                format!("{IMU_HEADER}{good}2000,0.1,x,0.3,9.8,0.0,0.1\n"),
                3,
                "not a number",
            ),
            ("empty", String::new(), 1, "empty file"),
            ("header only", IMU_HEADER.to_string(), 1, "no data lines"),
            (
                "columns",
                "#timestamp,gx,gy,gz,ax,ay,az\n1,0,0,0,0,0,0\n".into(),
                1,
                "unknown column `gx`",
            ),
            (
                "time",
                format!("{IMU_HEADER}1.5e9,0.1,0.2,0.3,9.8,0.0,0.1\n"),
                2,
                "timestamp",
            ),
        ];
        for (name, text, line, reason) in cases {
            let p = file(&dir, "imu.csv", &text);
            let e = imu_csv(&p).unwrap_err().to_string();
            let want = format!("{}:{line}:", p.display());
            assert!(e.starts_with(&want), "{name}: {e}");
            assert!(e.contains(reason), "{name}: {e}");
        }
        let tracks = [
            (
                "#timestamp [ns],track_id,x_n,y_n\n1000,1.5,0.1,0.2\n",
                2,
                "track id `1.5` is not a non-negative integer",
            ),
            (
                "#timestamp [ns],track_id,x_n,y_n\n1000,-3,0.1,0.2\n",
                2,
                "not a non-negative integer",
            ),
            (
                "#timestamp [ns],track_id,x_n,y_n\n1000,3,0.1,0.2\n1000,3,0.1,0.2\n",
                3,
                "twice",
            ),
            (
                "#timestamp [ns],track_id,x_n,y_n\n1000,3,0.1,0.2\n900,4,0.1,0.2\n",
                3,
                "time order",
            ),
            (
                "#timestamp [ns],track_id,x_n,y_n\n1000,3,inf,0.2\n",
                2,
                "not finite",
            ),
            ("#timestamp,id,a,b\n1000,3,0.1,0.2\n", 1, "unknown columns"),
        ];
        for (text, line, reason) in tracks {
            let p = file(&dir, "tracks.csv", text);
            let e = tracks_csv(&p).unwrap_err().to_string();
            assert!(e.starts_with(&format!("{}:{line}:", p.display())), "{e}");
            assert!(e.contains(reason), "{e}");
        }
        let gt = [
            (
                "1.0 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n",
                2,
                "before the previous",
            ),
            ("1.0 0 0 0 0 0 0 2\n", 1, "norm"),
            ("1.0 0 0 0 0 0 1\n", 1, "8"),
        ];
        for (text, line, reason) in gt {
            let p = file(&dir, "gt.tum", text);
            let e = ground_truth(&p).unwrap_err().to_string();
            assert!(e.starts_with(&format!("{}:{line}:", p.display())), "{e}");
            assert!(e.contains(reason), "{e}");
        }
        let cam = file(
            &dir,
            "cam0.yaml",
            "intrinsics: [1, 1, 0, 0]\nresolution: [10, 10]\n",
        );
        let e = euroc_camera(&cam, None).unwrap_err().to_string();
        assert!(e.contains("missing calibration field `T_BS`"), "{e}");
        let cam = file(
            &dir,
            "cam0.yaml",
            "T_BS: {data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}\nintrinsics: [1, 1, 0, 0]\nresolution: [10, 10]\n",
        );
        let e = euroc_camera(&cam, None).unwrap_err().to_string();
        assert!(e.contains("distortion_model"), "{e}");
    }

    #[test]
    fn euroc_and_kalibr_calibrations_agree_on_the_same_mount() {
        let dir = tempfile::tempdir().unwrap();
        // A camera rotated 90° about the IMU's z axis, 5 cm along IMU y.
        let euroc = file(
            &dir,
            "cam0.yaml",
            "T_BS:\n  cols: 4\n  rows: 4\n  data: [0, -1, 0, 0, 1, 0, 0, 0.05, 0, 0, 1, 0, 0, 0, 0, 1]\nintrinsics: [400, 401, 320, 240]\nresolution: [640, 480]\ndistortion_model: radial-tangential\ndistortion_coefficients: [-0.1, 0.01, 0.0, 0.0]\nrate_hz: 20\n",
        );
        // T_cam_imu is the inverse: R' = Rᵀ, t' = −Rᵀ t.
        let kalibr = file(
            &dir,
            "camchain-imucam.yaml",
            "cam0:\n  T_cam_imu:\n  - [0, 1, 0, -0.05]\n  - [-1, 0, 0, 0]\n  - [0, 0, 1, 0]\n  - [0, 0, 0, 1]\n  camera_model: pinhole\n  intrinsics: [400, 401, 320, 240]\n  distortion_model: radtan\n  distortion_coeffs: [-0.1, 0.01, 0.0, 0.0]\n  resolution: [640, 480]\n",
        );
        let a = euroc_camera(&euroc, None).unwrap();
        let b = kalibr_camera(&kalibr).unwrap();
        assert!((a.imu_from_camera - b.imu_from_camera).abs().max() < 1e-12);
        assert!((a.camera_in_imu - b.camera_in_imu).norm() < 1e-12);
        assert!((a.camera_in_imu - Vector3::new(0.0, 0.05, 0.0)).norm() < 1e-12);
        assert_eq!(a.camera, b.camera);
        assert_eq!(a.rate_hz, Some(20.0));
    }
}
