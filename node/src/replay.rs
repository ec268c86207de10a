//! Recorded sensor logs (CSV) and the sensor sources of a run: a simulated vehicle, or a vehicle
//! whose IMU samples and observation frames are replayed from logs.
//!
//! # Log format (version 2)
//! Three CSV files per vehicle, comma separated, `#` starts a comment line, the first
//! non-comment line is the exact header given below. Numbers are decimal (Rust `f64` syntax;
//! `canopy sim --record-logs` and `canopy import` write the shortest text that reads back to the
//! same bits). Quantities are those the estimator receives, in its navigation frame (ECEF for a
//! `wgs84` world, the launch site's NED frame for a `flat` one). Times are seconds of the run's
//! clock: `[run] time_origin_ns` (if given) is the instant of the recording's own clock that is
//! t = 0, and the outputs stamp their times with origin + t.
//!
//! - `<name>.imu.csv` — one IMU sample per row, times strictly increasing:
//!   `t,dt,f_x,f_y,f_z,w_x,w_y,w_z` — end of the sample interval [s], interval Δt [s],
//!   measured specific force f̂^b [m/s²] and body rate ω̂^b_ib [rad/s] (eqs. 21.13, 21.14). The
//!   intervals tile time: each starts where the previous one ended (|t − Δt − t_prev| ≤
//!   [`TILE_TOLERANCE_S`]), the first one at the time of the initial estimate. Δt may vary
//!   (jitter, gaps: the INS holds the sample over its whole interval).
//! - `<name>.obs.csv` — one observation per row; rows with the same `t` form one frame, frame
//!   times strictly after the initial estimate, non-decreasing, and at most the last IMU time:
//!   `t,descriptor,kind,z0,z1,z2` — frame time [s], the feature descriptor (u64, below 2⁶³;
//!   e.g. a track id), and `kind` = `range_bearing` (z0 = range [m], z1 = azimuth,
//!   z2 = elevation [rad], eq. 21.41), `bearing` (z0 = azimuth, z1 = elevation [rad], z2
//!   empty, eq. 21.42) or `pixel` (z0 = u, z1 = v [px], z2 empty, eq. 21.43). A frame without
//!   observations is one row `t,,none,,,`. A frame may fall anywhere inside an IMU interval:
//!   the replay splits that sample at the frame time (same f̂, ω̂ over both parts), so the filter
//!   propagates exactly to the frame.
//! - `<name>.init.csv` — the initial estimate: 16 rows `what,t,v0,…,v14`; `what` = `mean`
//!   (state p, v, Ψ, δf^b, δω^b in the order of `fusion::state`) then `cov0` … `cov14` (the rows
//!   of the 15×15 covariance); `t` is the time of the estimate (the start of the logs). Instead
//!   of this file a scenario may ask for `initial = "static"`: the alignment of
//!   [`canopy_fusion::alignment`] over the rest period at the start of the IMU log.
//!
//! Version 1 (canopy before the real-data path) is the same columns with every frame at the
//! time of an IMU sample; it reads as version 2. A file whose first comment names a later
//! version (`# canopy … log v3`) is refused with a clear error.
//!
//! A replayed vehicle has no truth: its metrics are marked unavailable in the outputs.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use canopy_fusion::alignment::{self, AlignmentOptions, RestDetection};
use canopy_fusion::sensor::{FeatureId, ImuSample, Measurement, Observation, ObservationFrame};
use canopy_fusion::slam::FRESH_ID_BASE;
use canopy_fusion::state::VEHICLE_DIM;
use nalgebra::{SMatrix, UnitQuaternion, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::scenario::{EarthModel, Scenario, ScenarioError, VehicleConfig, WorldConfig};
use crate::world::{self, FrameEstimate, InitialEstimate, TruthSample, VehicleSim, World};

/// Version of the log format this canopy writes (module docs).
pub const FORMAT_VERSION: u32 = 2;

/// Largest gap or overlap accepted between consecutive IMU intervals [s]: far below any IMU
/// period, far above the round-off of times written as shortest decimals (≈ 1e-15 s at t ≈ 100 s).
pub const TILE_TOLERANCE_S: f64 = 1e-6;

/// σ of the frame-defining states of a static alignment: position [m], velocity at rest
/// [m/s] and yaw [rad]. They define the local frame (zero at the start), so they are small, but
/// not so small that P becomes ill-conditioned next to the other states (a 1e-12 m² position
/// variance beside 1e2 m² feature variances would leave ~4 significant digits).
pub const STATIC_FRAME_SIGMA: (f64, f64, f64) = (1e-3, 1e-3, 1e-4);

/// Header of the IMU log.
pub const IMU_HEADER: &str = "t,dt,f_x,f_y,f_z,w_x,w_y,w_z";
/// Header of the observation log.
pub const OBS_HEADER: &str = "t,descriptor,kind,z0,z1,z2";
/// Header of the initial-estimate file.
pub const INIT_HEADER: &str = "what,t,v0,v1,v2,v3,v4,v5,v6,v7,v8,v9,v10,v11,v12,v13,v14";

/// `[vehicle.replay]`: stream this vehicle's sensor input from recorded logs instead of
/// simulating it. Relative paths are relative to the scenario file's directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayConfig {
    /// IMU log (*required*).
    pub imu: PathBuf,
    /// Observation log (*required*).
    pub observations: PathBuf,
    /// Initial estimate (*required*): a file, or `"static"` (write `./static` for a file of
    /// that name).
    pub initial: InitialSource,
    /// `initial = "static"` only: the vehicle rests for this long from the start of the IMU
    /// log [s]; absent = detected ([`canopy_fusion::alignment::detect_rest`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rest_s: Option<f64>,
    /// Zero-velocity updates while the vehicle is known to rest at the start of the log
    /// (`zero_velocity = { until_s = 3.9 }`). Default: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub zero_velocity: Option<ZeroVelocityConfig>,
    /// Ground truth of the vehicle (TUM: `t x y z qx qy qz qw`, the body's pose in the
    /// vehicle's navigation frame, as `canopy import` writes it; stamps in the recording's time
    /// base when `[run] time_origin_ns` is set, else run time). The run's outputs then carry
    /// position errors, pose NEES and the ATE against it, as for a simulated vehicle. Local
    /// (flat-world) runs only. Default: none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub groundtruth: Option<PathBuf>,
}

/// `zero_velocity`: the vehicle rests from the start of its log until `until_s`; the estimator
/// applies a zero-velocity pseudo-measurement ([`canopy_fusion::slam::SlamFilter::zero_velocity_update`])
/// before the frames of that period, at most `rate_hz` times per second (with frames, so that
/// a replay is deterministic across `canopy sim` and `canopy run`). Without it the accelerometer bias is barely
/// observable at rest and an INS drifts by ½·b·t² before the first features initialize.
/// `canopy check` refuses a period the IMU log does not show at rest.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZeroVelocityConfig {
    /// End of the rest period, in run time [s] (*required*).
    pub until_s: f64,
    /// σ of each update [m/s]. Default 0.01: a vehicle standing on the ground with its motors
    /// running moves by millimetres (the vibration is in the IMU noise, not in a net velocity).
    #[serde(default = "default_zero_velocity_sigma")]
    pub sigma_mps: f64,
    /// Most updates per second. Default 20 (a camera's rate: more repeats the same
    /// information, whose errors are correlated over short times).
    #[serde(default = "default_zero_velocity_rate")]
    pub rate_hz: f64,
}

fn default_zero_velocity_sigma() -> f64 {
    0.01
}

fn default_zero_velocity_rate() -> f64 {
    20.0
}

impl ZeroVelocityConfig {
    /// Field checks (paths relative to `zero_velocity`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        for (field, v) in [
            ("until_s", self.until_s),
            ("sigma_mps", self.sigma_mps),
            ("rate_hz", self.rate_hz),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(ScenarioError::invalid(
                    field,
                    format!("must be a finite number > 0, got {v}"),
                ));
            }
        }
        Ok(())
    }
}

/// Where a replayed vehicle's initial estimate comes from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "PathBuf", into = "PathBuf")]
pub enum InitialSource {
    /// Static alignment over the rest period at the start of the IMU log (`"static"`).
    Static,
    /// An initial-estimate file (`<name>.init.csv`).
    File(PathBuf),
}

impl From<PathBuf> for InitialSource {
    fn from(p: PathBuf) -> Self {
        if p.as_os_str() == "static" {
            InitialSource::Static
        } else {
            InitialSource::File(p)
        }
    }
}

impl From<InitialSource> for PathBuf {
    fn from(s: InitialSource) -> Self {
        match s {
            InitialSource::Static => PathBuf::from("static"),
            InitialSource::File(p) => p,
        }
    }
}

impl ReplayConfig {
    /// The three files of vehicle `name` in `dir`, named as `--record-logs` writes them.
    pub fn in_dir(dir: &Path, name: &str) -> Self {
        Self {
            imu: dir.join(format!("{name}.imu.csv")),
            observations: dir.join(format!("{name}.obs.csv")),
            initial: InitialSource::File(dir.join(format!("{name}.init.csv"))),
            rest_s: None,
            zero_velocity: None,
            groundtruth: None,
        }
    }

    /// The files, for path rewriting (the initial estimate only when it is a file).
    pub fn paths_mut(&mut self) -> Vec<&mut PathBuf> {
        let mut v = vec![&mut self.imu, &mut self.observations];
        if let InitialSource::File(p) = &mut self.initial {
            v.push(p);
        }
        if let Some(p) = &mut self.groundtruth {
            v.push(p);
        }
        v
    }

    /// Makes relative paths relative to `base`.
    pub fn resolve(&mut self, base: &Path) {
        for p in self.paths_mut() {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
    }

    /// Field checks (paths relative to `replay`).
    pub fn validate(&self) -> Result<(), ScenarioError> {
        if let Some(z) = &self.zero_velocity {
            z.validate().map_err(|e| e.within("zero_velocity"))?;
        }
        if let Some(r) = self.rest_s {
            if self.initial != InitialSource::Static {
                return Err(ScenarioError::invalid(
                    "rest_s",
                    "only a static alignment (`initial = \"static\"`) uses a rest period",
                ));
            }
            if !(r.is_finite() && r > 0.0) {
                return Err(ScenarioError::invalid(
                    "rest_s",
                    format!("must be a finite number > 0, got {r}"),
                ));
            }
        }
        Ok(())
    }
}

/// A malformed or unreadable log.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A line is malformed.
    #[error("{path}:{line}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// The scenario cannot be replayed or recorded as asked.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
}

/// A vehicle's logs, parsed and checked.
#[derive(Clone, Debug, PartialEq)]
pub struct ReplayLog {
    /// IMU samples in time order, as logged.
    pub imu: Vec<ImuSample>,
    /// Frames in time order.
    pub frames: Vec<ObservationFrame>,
    /// Initial estimate.
    pub initial: InitialEstimate,
    /// What the estimator receives, in order: the IMU samples, those that straddle a frame time
    /// split there, each followed by the index of the frame that comes after it, if any.
    pub steps: Vec<(ImuSample, Option<usize>)>,
    /// The static alignment, when the initial estimate came from one.
    pub alignment: Option<alignment::StaticAlignment>,
}

/// Splits IMU samples at frame times: each frame follows a sample that ends exactly at its
/// time (a straddling sample becomes two with the same measured f̂ and ω̂). Frames must lie in
/// (start, last sample time] in non-decreasing order (checked by the caller).
pub fn split_at_frames(
    start: f64,
    imu: &[ImuSample],
    frames: &[ObservationFrame],
) -> Vec<(ImuSample, Option<usize>)> {
    let mut out = Vec::with_capacity(imu.len() + frames.len());
    let mut f = 0;
    let mut t_prev = start;
    for s in imu {
        // Frames inside the interval (t_prev, s.time): cut the sample there.
        while f < frames.len() && frames[f].time < s.time {
            // Frame times strictly increase (rows of one time form one frame) and every frame at
            // or before t_prev was placed already, so tf > t_prev: no empty interval.
            let tf = frames[f].time;
            out.push((
                ImuSample {
                    time: tf,
                    dt: tf - t_prev,
                    ..*s
                },
                Some(f),
            ));
            t_prev = tf;
            f += 1;
        }
        let rest = ImuSample {
            dt: s.time - t_prev,
            ..*s
        };
        let frame = (f < frames.len() && frames[f].time == s.time).then(|| {
            f += 1;
            f - 1
        });
        out.push((rest, frame));
        t_prev = s.time;
    }
    out
}

fn read(path: &Path) -> Result<String, ReplayError> {
    std::fs::read_to_string(path).map_err(|source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// The format version a comment line names (`# canopy IMU log v2: …` → 2), if any.
fn comment_version(line: &str) -> Option<u32> {
    let rest = line
        .strip_prefix('#')?
        .trim_start()
        .strip_prefix("canopy ")?;
    let (_, after) = rest.split_once(" v")?;
    let digits: String = after.chars().take_while(char::is_ascii_digit).collect();
    digits.parse().ok()
}

/// Data lines of a CSV log after its header: (1-based line number, fields). A comment that
/// names a format version later than [`FORMAT_VERSION`] is refused.
fn data_lines<'a>(
    path: &Path,
    text: &'a str,
    header: &str,
) -> Result<Vec<(usize, Vec<&'a str>)>, ReplayError> {
    for (i, l) in text.lines().enumerate() {
        let l = l.trim();
        if !l.starts_with('#') {
            if l.is_empty() {
                continue;
            }
            break;
        }
        if let Some(v) = comment_version(l)
            && v > FORMAT_VERSION
        {
            return Err(ReplayError::Format {
                path: path.to_path_buf(),
                line: i + 1,
                reason: format!(
                    "written in log format v{v}; this canopy reads v1 and v{FORMAT_VERSION}"
                ),
            });
        }
    }
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    match lines.next() {
        Some((_, h)) if h == header => {}
        Some((n, h)) => {
            return Err(ReplayError::Format {
                path: path.to_path_buf(),
                line: n,
                reason: format!("header `{h}` is not `{header}`"),
            });
        }
        None => {
            return Err(ReplayError::Format {
                path: path.to_path_buf(),
                line: 1,
                reason: format!("empty file (expected the header `{header}`)"),
            });
        }
    }
    let width = header.split(',').count();
    lines
        .map(|(n, l)| {
            let f: Vec<&str> = l.split(',').map(str::trim).collect();
            if f.len() != width {
                return Err(ReplayError::Format {
                    path: path.to_path_buf(),
                    line: n,
                    reason: format!("{} fields, expected {width}", f.len()),
                });
            }
            Ok((n, f))
        })
        .collect()
}

fn num(path: &Path, line: usize, name: &str, s: &str) -> Result<f64, ReplayError> {
    let v: f64 = s.parse().map_err(|_| ReplayError::Format {
        path: path.to_path_buf(),
        line,
        reason: format!("`{name}` = `{s}` is not a number"),
    })?;
    if !v.is_finite() {
        return Err(ReplayError::Format {
            path: path.to_path_buf(),
            line,
            reason: format!("`{name}` = `{s}` is not finite"),
        });
    }
    Ok(v)
}

/// Parses an IMU log.
pub fn parse_imu(path: &Path, text: &str) -> Result<Vec<ImuSample>, ReplayError> {
    let mut out: Vec<ImuSample> = Vec::new();
    for (n, f) in data_lines(path, text, IMU_HEADER)? {
        let names = ["t", "dt", "f_x", "f_y", "f_z", "w_x", "w_y", "w_z"];
        let mut v = [0.0; 8];
        for (k, name) in names.iter().enumerate() {
            v[k] = num(path, n, name, f[k])?;
        }
        if v[1] <= 0.0 {
            return Err(ReplayError::Format {
                path: path.to_path_buf(),
                line: n,
                reason: format!("dt = {} must be > 0", v[1]),
            });
        }
        if let Some(prev) = out.last() {
            if v[0] <= prev.time {
                return Err(ReplayError::Format {
                    path: path.to_path_buf(),
                    line: n,
                    reason: format!(
                        "t = {} does not follow {} (times must increase)",
                        v[0], prev.time
                    ),
                });
            }
            let start = v[0] - v[1];
            if (start - prev.time).abs() > TILE_TOLERANCE_S {
                return Err(ReplayError::Format {
                    path: path.to_path_buf(),
                    line: n,
                    reason: format!(
                        "the interval starts at t − dt = {start}, not where the previous sample \
                         ended (t = {}): dt must be the time since the previous sample",
                        prev.time
                    ),
                });
            }
        }
        out.push(ImuSample {
            time: v[0],
            dt: v[1],
            specific_force: Vector3::new(v[2], v[3], v[4]),
            angular_rate: Vector3::new(v[5], v[6], v[7]),
        });
    }
    Ok(out)
}

/// Parses an observation log.
pub fn parse_observations(path: &Path, text: &str) -> Result<Vec<ObservationFrame>, ReplayError> {
    Ok(parse_observation_lines(path, text)?
        .into_iter()
        .map(|(_, f)| f)
        .collect())
}

/// Parses an observation log: the frames with the line of each frame's first row.
fn parse_observation_lines(
    path: &Path,
    text: &str,
) -> Result<Vec<(usize, ObservationFrame)>, ReplayError> {
    let mut frames: Vec<(usize, ObservationFrame)> = Vec::new();
    for (n, f) in data_lines(path, text, OBS_HEADER)? {
        let t = num(path, n, "t", f[0])?;
        let bad = |reason: String| ReplayError::Format {
            path: path.to_path_buf(),
            line: n,
            reason,
        };
        let new_frame = match frames.last() {
            Some((_, last)) if last.time == t => false,
            Some((_, last)) if t < last.time => {
                return Err(bad(format!(
                    "t = {t} is before the previous frame at {} (frames must be in time order)",
                    last.time
                )));
            }
            _ => true,
        };
        if new_frame {
            frames.push((
                n,
                ObservationFrame {
                    time: t,
                    observations: Vec::new(),
                },
            ));
        }
        let kind = f[2];
        if kind == "none" {
            if !new_frame
                || f[1..]
                    .iter()
                    .enumerate()
                    .any(|(i, x)| i != 1 && !x.is_empty())
            {
                return Err(bad(
                    "`none` marks an empty frame: one row `t,,none,,,` and no other row at that t"
                        .into(),
                ));
            }
            continue;
        }
        let descriptor: FeatureId = f[1]
            .parse()
            .map_err(|_| bad(format!("descriptor `{}` is not an unsigned integer", f[1])))?;
        if descriptor >= FRESH_ID_BASE {
            return Err(bad(format!(
                "descriptor {descriptor} is in the range ≥ 2⁶³ that the filter reserves for its own ids"
            )));
        }
        let z0 = num(path, n, "z0", f[3])?;
        let z1 = num(path, n, "z1", f[4])?;
        let z = match kind {
            "range_bearing" => {
                Measurement::RangeBearing(Vector3::new(z0, z1, num(path, n, "z2", f[5])?))
            }
            "bearing" | "pixel" => {
                if !f[5].is_empty() {
                    return Err(bad(format!("`{kind}` rows leave z2 empty")));
                }
                let v = Vector2::new(z0, z1);
                if kind == "bearing" {
                    Measurement::Bearing(v)
                } else {
                    Measurement::Pixel(v)
                }
            }
            other => {
                return Err(bad(format!(
                    "kind `{other}` is not range_bearing, bearing, pixel or none"
                )));
            }
        };
        let (_, frame) = frames.last_mut().expect("pushed above");
        if frame.observations.is_empty() && !new_frame {
            // The frame was declared empty by a `none` row.
            return Err(bad(format!("frame at t = {t} was declared empty (`none`)")));
        }
        frame.observations.push(Observation {
            descriptor,
            z,
            appearance: None,
        });
    }
    Ok(frames)
}

/// Parses an initial-estimate file.
pub fn parse_initial(path: &Path, text: &str) -> Result<InitialEstimate, ReplayError> {
    let rows = data_lines(path, text, INIT_HEADER)?;
    let mut mean: Option<(f64, [f64; VEHICLE_DIM])> = None;
    let mut cov = SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::zeros();
    let mut seen = [false; VEHICLE_DIM];
    for (n, f) in &rows {
        let t = num(path, *n, "t", f[1])?;
        let mut v = [0.0; VEHICLE_DIM];
        for (k, x) in v.iter_mut().enumerate() {
            *x = num(path, *n, &format!("v{k}"), f[2 + k])?;
        }
        let bad = |reason: String| ReplayError::Format {
            path: path.to_path_buf(),
            line: *n,
            reason,
        };
        match f[0] {
            "mean" if mean.is_none() => mean = Some((t, v)),
            w => {
                let r: usize = w
                    .strip_prefix("cov")
                    .and_then(|r| r.parse().ok())
                    .filter(|&r: &usize| r < VEHICLE_DIM)
                    .ok_or_else(|| {
                        bad(format!("`{w}` is not `mean` (once) or `cov0` … `cov14`"))
                    })?;
                if seen[r] {
                    return Err(bad(format!("row `{w}` given twice")));
                }
                seen[r] = true;
                for (c, x) in v.iter().enumerate() {
                    cov[(r, c)] = *x;
                }
            }
        }
    }
    let Some((t, m)) = mean else {
        return Err(ReplayError::Format {
            path: path.to_path_buf(),
            line: 1,
            reason: "no `mean` row".into(),
        });
    };
    if let Some(r) = seen.iter().position(|s| !s) {
        return Err(ReplayError::Format {
            path: path.to_path_buf(),
            line: 1,
            reason: format!("no `cov{r}` row"),
        });
    }
    let sym_err = (cov - cov.transpose()).abs().max();
    if sym_err > 1e-9 * cov.abs().max().max(1e-300) || cov.cholesky().is_none() {
        return Err(ReplayError::Format {
            path: path.to_path_buf(),
            line: 1,
            reason: "the covariance is not symmetric positive definite".into(),
        });
    }
    let v3 = |i: usize| Vector3::new(m[i], m[i + 1], m[i + 2]);
    use canopy_fusion::state::{ACC_BIAS, ATT, GYRO_BIAS, POS, VEL};
    Ok(InitialEstimate {
        time: t,
        position: v3(POS),
        velocity: v3(VEL),
        attitude: v3(ATT),
        accel_bias: v3(ACC_BIAS),
        gyro_bias: v3(GYRO_BIAS),
        covariance: cov,
    })
}

impl ReplayLog {
    /// Reads and checks the logs of `cfg` for vehicle `vehicle` in `world` (whose Earth model
    /// and origin a static alignment needs).
    pub fn load(
        cfg: &ReplayConfig,
        vehicle: &VehicleConfig,
        world: &WorldConfig,
    ) -> Result<Self, ReplayError> {
        let imu = parse_imu(&cfg.imu, &read(&cfg.imu)?)?;
        let Some(first) = imu.first() else {
            return Err(ReplayError::Format {
                path: cfg.imu.clone(),
                line: 1,
                reason: "no IMU samples after the header".into(),
            });
        };
        if let Some(z) = &cfg.zero_velocity {
            check_rest(cfg, &imu, z)?;
        }
        let frames = parse_observation_lines(&cfg.observations, &read(&cfg.observations)?)?;
        let (initial, alignment) = match &cfg.initial {
            InitialSource::File(p) => (parse_initial(p, &read(p)?)?, None),
            InitialSource::Static => {
                let (e, a) = static_initial(cfg, &imu, vehicle, world)?;
                (e, Some(a))
            }
        };
        let start = first.time - first.dt;
        if (start - initial.time).abs() > TILE_TOLERANCE_S {
            return Err(ReplayError::Format {
                path: cfg.imu.clone(),
                line: 1,
                reason: format!(
                    "the first sample's interval starts at t − dt = {start}, not at the initial \
                     estimate's time {}",
                    initial.time
                ),
            });
        }
        let last = imu.last().map_or(initial.time, |s| s.time);
        for (line, fr) in &frames {
            if fr.time <= initial.time || fr.time > last {
                return Err(ReplayError::Format {
                    path: cfg.observations.clone(),
                    line: *line,
                    reason: format!(
                        "the frame at t = {} lies outside the IMU log's span ({}, {}]: the IMU \
                         cannot propagate the estimate to it",
                        fr.time, initial.time, last
                    ),
                });
            }
        }
        let frames: Vec<ObservationFrame> = frames.into_iter().map(|(_, f)| f).collect();
        let steps = split_at_frames(initial.time, &imu, &frames);
        Ok(Self {
            imu,
            frames,
            initial,
            steps,
            alignment,
        })
    }
}

/// Refuses zero-velocity updates over a period the IMU log does not show at rest: the rest
/// detected at the start of the log ([`alignment::detect_rest`], which drops its last window)
/// must reach `until_s` to within one detection window.
fn check_rest(
    cfg: &ReplayConfig,
    imu: &[ImuSample],
    z: &ZeroVelocityConfig,
) -> Result<(), ReplayError> {
    let detection = RestDetection::default();
    let rest_end = alignment::detect_rest(imu, &detection).map(|n| imu[n - 1].time);
    match rest_end {
        Some(end) if z.until_s <= end + detection.window_s => Ok(()),
        _ => Err(ReplayError::Format {
            path: cfg.imu.clone(),
            line: 1,
            reason: format!(
                "zero_velocity.until_s = {} but the IMU log rests only {} (canopy_fusion::alignment::detect_rest): zero-velocity updates while moving would corrupt the estimate",
                z.until_s,
                rest_end.map_or_else(
                    || format!("less than {} s at its start", detection.min_rest_s),
                    |e| format!("until t = {e:.3} s")
                )
            ),
        }),
    }
}

/// The initial estimate of a static alignment over the rest period at the start of `imu`
/// (given by `cfg.rest_s` or detected), at the start of the log; yaw, position and velocity zero
/// with [`STATIC_FRAME_SIGMA`]: they define the local frame.
fn static_initial(
    cfg: &ReplayConfig,
    imu: &[ImuSample],
    vehicle: &VehicleConfig,
    world: &WorldConfig,
) -> Result<(InitialEstimate, alignment::StaticAlignment), ReplayError> {
    let bad = |reason: String| ReplayError::Format {
        path: cfg.imu.clone(),
        line: 1,
        reason,
    };
    if world.earth_model != EarthModel::Flat {
        return Err(ReplayError::Scenario(ScenarioError::invalid(
            "replay.initial",
            "a static alignment finds no north: it needs a local frame (`[world] earth_model = \"flat\"`); give an initial-estimate file for a wgs84 world",
        )));
    }
    let start = imu[0].time - imu[0].dt;
    let n = match cfg.rest_s {
        Some(r) => imu.partition_point(|s| s.time <= start + r + TILE_TOLERANCE_S),
        None => alignment::detect_rest(imu, &RestDetection::default()).ok_or_else(|| {
            bad(format!(
                "no rest period of at least {} s found at the start (see canopy_fusion::alignment::detect_rest); give `rest_s` or an initial-estimate file",
                RestDetection::default().min_rest_s
            ))
        })?,
    };
    let (sp, sv, sy) = STATIC_FRAME_SIGMA;
    let opts = AlignmentOptions {
        yaw: 0.0,
        yaw_sigma: sy,
        position_sigma: sp,
        velocity_sigma: sv,
        // Local SLAM models no Earth rotation: the gyro bias absorbs it.
        earth_rate_nav: None,
    };
    let a = alignment::static_alignment(&imu[..n], &vehicle.imu.noise_model(), &opts)
        .map_err(|e| bad(format!("static alignment over the first {n} samples: {e}")))?;
    let e = InitialEstimate {
        time: start,
        position: Vector3::zeros(),
        velocity: Vector3::zeros(),
        attitude: a.attitude,
        accel_bias: Vector3::zeros(),
        gyro_bias: a.gyro_bias,
        covariance: a.covariance,
    };
    Ok((e, a))
}

fn write_num(out: &mut String, v: f64) {
    // `Display` of f64 is the shortest text that parses back to the same value.
    let _ = write!(out, ",{v}");
}

/// One IMU row.
pub fn imu_row(out: &mut String, s: &ImuSample) {
    let _ = write!(out, "{}", s.time);
    for v in [
        s.dt,
        s.specific_force.x,
        s.specific_force.y,
        s.specific_force.z,
        s.angular_rate.x,
        s.angular_rate.y,
        s.angular_rate.z,
    ] {
        write_num(out, v);
    }
    out.push('\n');
}

/// The rows of one frame.
pub fn frame_rows(out: &mut String, f: &ObservationFrame) {
    if f.observations.is_empty() {
        let _ = writeln!(out, "{},,none,,,", f.time);
    }
    for o in &f.observations {
        let _ = write!(out, "{},{}", f.time, o.descriptor);
        match o.z {
            Measurement::RangeBearing(z) => {
                let _ = writeln!(out, ",range_bearing,{},{},{}", z.x, z.y, z.z);
            }
            Measurement::Bearing(z) => {
                let _ = writeln!(out, ",bearing,{},{},", z.x, z.y);
            }
            Measurement::Pixel(z) => {
                let _ = writeln!(out, ",pixel,{},{},", z.x, z.y);
            }
        }
    }
}

/// The initial-estimate file.
pub fn initial_text(e: &InitialEstimate) -> String {
    let mut out = format!(
        "# canopy initial estimate v{FORMAT_VERSION} (estimator navigation frame)\n{INIT_HEADER}\n"
    );
    let _ = write!(out, "mean,{}", e.time);
    for v in [
        e.position,
        e.velocity,
        e.attitude,
        e.accel_bias,
        e.gyro_bias,
    ] {
        for x in v.iter() {
            write_num(&mut out, *x);
        }
    }
    out.push('\n');
    for r in 0..VEHICLE_DIM {
        let _ = write!(out, "cov{r},{}", e.time);
        for c in 0..VEHICLE_DIM {
            write_num(&mut out, e.covariance[(r, c)]);
        }
        out.push('\n');
    }
    out
}

fn write_file(path: &Path, text: &str) -> Result<(), ReplayError> {
    std::fs::write(path, text).map_err(|source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Writes the logs of every simulated vehicle of `s` up to `duration` into `dir`
/// (`<name>.imu.csv`, `<name>.obs.csv`, `<name>.init.csv`): exactly the stream `canopy sim`
/// and the world process feed the estimators (the simulator is deterministic given the
/// scenario). Returns the per-vehicle replay configurations.
pub fn record_logs(
    s: &Scenario,
    dir: &Path,
    duration: f64,
) -> Result<Vec<(String, ReplayConfig)>, ReplayError> {
    std::fs::create_dir_all(dir).map_err(|source| ReplayError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let (world, _) = world::build(s)?;
    let mut out = Vec::new();
    for (i, v) in s.vehicles.iter().enumerate() {
        if v.replay.is_some() {
            continue;
        }
        let mut sim = VehicleSim::new(v, world.clone(), world::vehicle_seed(s.world.seed, v.id))
            .map_err(|e| e.within(&format!("vehicle[{i}]")))?;
        let name = v.display_name();
        let mut cfg = ReplayConfig::in_dir(dir, &name);
        // Flat world: the truth in the navigation frame is the replay's ground truth (global
        // runs have none: a ground-truth file is read in a local frame).
        let mut truth = (s.world.earth_model == EarthModel::Flat).then(|| {
            format!(
                "# ground truth of {name} (canopy sim --record-logs): run time [s], body position in the navigation frame (NED) [m], C_b^n as qx qy qz qw\n"
            )
        });
        let mut imu = format!(
            "# canopy IMU log v{FORMAT_VERSION}: vehicle {name}, estimator navigation frame\n{IMU_HEADER}\n"
        );
        let mut obs = format!(
            "# canopy observation log v{FORMAT_VERSION}: vehicle {name}, estimator navigation frame\n{OBS_HEADER}\n"
        );
        if let Some(t) = &mut truth {
            truth_row(t, sim.truth());
        }
        // The raw samples (a sample that straddles a frame is split by the replay, as a real
        // recording's is), the frames at their own times.
        while sim.next_time() <= duration + 1e-9 {
            let step = sim.step();
            imu_row(&mut imu, &step.imu);
            if let Some(f) = &step.frame {
                frame_rows(&mut obs, &f.frame);
            }
            if let Some(t) = &mut truth {
                truth_row(t, &step.truth);
            }
        }
        write_file(&cfg.imu, &imu)?;
        write_file(&cfg.observations, &obs)?;
        if let Some(t) = truth {
            let path = dir.join(format!("{name}.groundtruth.tum"));
            write_file(&path, &t)?;
            cfg.groundtruth = Some(path);
        }
        if let InitialSource::File(p) = &cfg.initial {
            write_file(p, &initial_text(sim.initial_estimate()))?;
        }
        out.push((name, cfg));
    }
    Ok(out)
}

/// One TUM row of a truth sample (run time, position, C_b^n), every digit kept.
fn truth_row(out: &mut String, t: &TruthSample) {
    let q = UnitQuaternion::from_matrix(&canopy_fusion::rotation::nav_from_body(&t.attitude));
    let p = t.position;
    let _ = writeln!(
        out,
        "{} {} {} {} {} {} {} {}",
        t.time, p.x, p.y, p.z, q.i, q.j, q.k, q.w
    );
}

/// One step of a sensor source.
#[derive(Clone, Debug)]
pub struct SourceStep {
    /// The IMU sample.
    pub imu: ImuSample,
    /// A frame following the sample, with the true feature ids when the source knows them.
    pub frame: Option<(ObservationFrame, Option<Vec<FeatureId>>)>,
    /// Truth after the step (simulated vehicles only).
    pub truth: Option<TruthSample>,
}

/// Longest interval between two ground-truth poses that [`GroundTruth::sample`] interpolates
/// over [s]: motion capture and GNSS/INS references give ≥ 10 Hz; a longer gap is a dropout,
/// where interpolation would invent a truth.
pub const GROUNDTRUTH_MAX_GAP_S: f64 = 0.25;

/// A replayed vehicle's ground truth (`[vehicle.replay] groundtruth`), in run time.
#[derive(Clone, Debug)]
pub struct GroundTruth {
    /// (run time [s], position p^n [m], C_b^n).
    poses: Vec<(f64, Vector3<f64>, UnitQuaternion<f64>)>,
}

impl GroundTruth {
    /// Reads `cfg.groundtruth` (none: `Ok(None)`); stamps shifted to run time by the run's
    /// `time_origin_ns`. The truth must overlap the IMU log's span `[start, end]`.
    pub fn load(
        cfg: &ReplayConfig,
        s: &Scenario,
        span: [f64; 2],
    ) -> Result<Option<Self>, ReplayError> {
        let Some(path) = &cfg.groundtruth else {
            return Ok(None);
        };
        let bad = |reason: String| ReplayError::Format {
            path: path.clone(),
            line: 1,
            reason,
        };
        if s.world.earth_model != EarthModel::Flat {
            return Err(ReplayError::Scenario(ScenarioError::invalid(
                "replay.groundtruth",
                "a ground-truth file is read in a local navigation frame: it needs `[world] earth_model = \"flat\"`",
            )));
        }
        let traj = crate::eval::Trajectory::load(path).map_err(|e| bad(e.to_string()))?;
        // The stamps are f64 seconds (UNIX time keeps ≈ 0.2 µs of resolution, far below the
        // interpolation's needs).
        let origin = s.run.time_origin_ns.map_or(0.0, |o| o as f64 * 1e-9);
        let poses: Vec<_> = traj
            .poses()
            .iter()
            .map(|p| {
                (
                    p.t - origin,
                    p.world_from_body.translation.vector,
                    p.world_from_body.rotation,
                )
            })
            .collect();
        let (first, last) = (poses[0].0, poses[poses.len() - 1].0);
        if last < span[0] || first > span[1] {
            return Err(bad(format!(
                "the ground truth spans run time [{first:.3}, {last:.3}] s, outside the IMU log's [{:.3}, {:.3}] s: are both in the same time base (`[run] time_origin_ns`)?",
                span[0], span[1]
            )));
        }
        Ok(Some(Self { poses }))
    }

    /// The truth at run time `t`: position linearly and attitude spherically interpolated
    /// between the two poses around `t`, velocity their difference quotient; biases unknown
    /// (zero: [`crate::metrics`] uses position and attitude only). `None` outside the truth's
    /// span or across a gap longer than [`GROUNDTRUTH_MAX_GAP_S`].
    pub fn sample(&self, t: f64) -> Option<TruthSample> {
        let k = self.poses.partition_point(|p| p.0 < t);
        let (a, b) = if k < self.poses.len() && self.poses[k].0 == t {
            (
                &self.poses[k],
                self.poses.get(k + 1).unwrap_or(&self.poses[k]),
            )
        } else if k == 0 || k == self.poses.len() {
            return None;
        } else {
            (&self.poses[k - 1], &self.poses[k])
        };
        let dt = b.0 - a.0;
        if dt > GROUNDTRUTH_MAX_GAP_S {
            return None;
        }
        let f = if dt > 0.0 { (t - a.0) / dt } else { 0.0 };
        let position = a.1 + (b.1 - a.1) * f;
        let velocity = if dt > 0.0 {
            (b.1 - a.1) / dt
        } else {
            Vector3::zeros()
        };
        let rotation = a.2.try_slerp(&b.2, f, 1e-12).unwrap_or(a.2);
        let attitude = canopy_fusion::rotation::euler_from_nav_from_body(
            rotation.to_rotation_matrix().matrix(),
        );
        Some(TruthSample {
            time: t,
            frame: canopy_fusion::state::NavFrame::Local,
            position,
            velocity,
            attitude,
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
            launch_position: position,
            launch_velocity: velocity,
            launch_attitude: attitude,
        })
    }
}

/// A replayed vehicle being streamed.
#[derive(Clone, Debug)]
pub struct ReplayStream {
    log: Arc<ReplayLog>,
    next: usize,
    /// Its ground truth, if any.
    groundtruth: Option<Arc<GroundTruth>>,
    /// The ground truth at the last step (boxed: the stream is one variant of
    /// [`SensorSource`]).
    truth: Option<Box<TruthSample>>,
}

impl ReplayStream {
    /// The log being streamed.
    pub fn log(&self) -> &ReplayLog {
        &self.log
    }
}

/// Where a vehicle's sensor input comes from.
#[derive(Clone, Debug)]
pub enum SensorSource {
    /// The world simulator.
    Sim(Box<VehicleSim>),
    /// Recorded logs.
    Replay(ReplayStream),
}

impl SensorSource {
    /// The sources of every vehicle of `s` (loading and checking replay logs). Every check
    /// that a run makes of its inputs before it starts happens here (`canopy check` calls it
    /// too).
    pub fn for_scenario(s: &Scenario) -> Result<(Arc<World>, Vec<SensorSource>), ReplayError> {
        let (world, sims) = world::build_parts(s)?;
        let mut out = Vec::with_capacity(sims.len());
        for (i, (v, sim)) in s.vehicles.iter().zip(sims).enumerate() {
            out.push(match (sim, &v.replay) {
                (Some(sim), _) => SensorSource::Sim(Box::new(sim)),
                (None, Some(r)) => {
                    let log = ReplayLog::load(r, v, &s.world)?;
                    let span = [
                        log.initial.time,
                        log.imu.last().map_or(log.initial.time, |x| x.time),
                    ];
                    let groundtruth = GroundTruth::load(r, s, span)?.map(Arc::new);
                    let truth = groundtruth
                        .as_ref()
                        .and_then(|g| g.sample(log.initial.time))
                        .map(Box::new);
                    SensorSource::Replay(ReplayStream {
                        log: Arc::new(log),
                        next: 0,
                        groundtruth,
                        truth,
                    })
                }
                (None, None) => {
                    return Err(ReplayError::Scenario(ScenarioError::invalid(
                        format!("vehicle[{i}]"),
                        "neither simulated nor replayed",
                    )));
                }
            });
        }
        Ok((world, out))
    }

    /// Time of the last step (or of the initial estimate).
    pub fn time(&self) -> f64 {
        match self {
            SensorSource::Sim(s) => s.stream_time(),
            SensorSource::Replay(r) => r
                .next
                .checked_sub(1)
                .map_or(r.log.initial.time, |k| r.log.steps[k].0.time),
        }
    }

    /// Time of the next step; `None` once a log is exhausted (a simulator never is).
    pub fn next_time(&self) -> Option<f64> {
        match self {
            SensorSource::Sim(s) => Some(s.stream_next_time()),
            SensorSource::Replay(r) => r.log.steps.get(r.next).map(|s| s.0.time),
        }
    }

    /// Advances one IMU sample (of a replay: one sample or part of a sample split at a frame).
    pub fn step(&mut self) -> Option<SourceStep> {
        match self {
            SensorSource::Sim(s) => {
                let out = s.stream_step();
                Some(SourceStep {
                    imu: out.imu,
                    frame: out.frame.map(|f| (f.frame, Some(f.true_ids))),
                    truth: Some(out.truth),
                })
            }
            SensorSource::Replay(r) => {
                let &(imu, frame) = r.log.steps.get(r.next)?;
                r.next += 1;
                r.truth = r
                    .groundtruth
                    .as_ref()
                    .and_then(|g| g.sample(imu.time))
                    .map(Box::new);
                Some(SourceStep {
                    imu,
                    frame: frame.map(|f| (r.log.frames[f].clone(), None)),
                    truth: r.truth.as_deref().copied(),
                })
            }
        }
    }

    /// The estimator's initial estimate.
    pub fn initial_estimate(&self) -> InitialEstimate {
        match self {
            SensorSource::Sim(s) => s.initial_estimate().clone(),
            SensorSource::Replay(r) => r.log.initial.clone(),
        }
    }

    /// The initial estimate in the launch frame, for the centralized reference (differs from
    /// [`Self::initial_estimate`] with `[world] frames = "own"` only).
    pub fn reference_initial_estimate(&self) -> InitialEstimate {
        match self {
            SensorSource::Sim(s) => s.launch_from_own().apply_estimate(s.initial_estimate()),
            SensorSource::Replay(r) => r.log.initial.clone(),
        }
    }

    /// [`Self::restart_estimate`] in the launch frame, for the reference.
    pub fn reference_restart_estimate(&self, draw: u64) -> Option<InitialEstimate> {
        match self {
            SensorSource::Sim(s) => Some(
                s.launch_from_own()
                    .apply_estimate(&s.restart_estimate(draw)),
            ),
            SensorSource::Replay(_) => None,
        }
    }

    /// A re-initialisation from an external fix at the current time (simulated vehicles only).
    pub fn restart_estimate(&self, draw: u64) -> Option<InitialEstimate> {
        match self {
            SensorSource::Sim(s) => Some(s.restart_estimate(draw)),
            SensorSource::Replay(_) => None,
        }
    }

    /// Current truth: the simulator's, or a replayed vehicle's ground truth where it has one.
    pub fn truth(&self) -> Option<&TruthSample> {
        match self {
            SensorSource::Sim(s) => Some(s.stream_truth()),
            SensorSource::Replay(r) => r.truth.as_deref(),
        }
    }

    /// The simulator, when this source is one (for the estimator's setup).
    pub fn sim(&self) -> Option<&VehicleSim> {
        match self {
            SensorSource::Sim(s) => Some(s),
            SensorSource::Replay(_) => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> PathBuf {
        PathBuf::from("x.csv")
    }

    #[test]
    fn imu_rows_round_trip_bit_exactly() {
        let s = ImuSample {
            time: 0.01,
            dt: 0.01,
            specific_force: Vector3::new(0.1 + 0.2, -9.806_651_234_567_89, 1e-17),
            angular_rate: Vector3::new(7.292115e-5, -3.0e-300, std::f64::consts::PI),
        };
        let mut text = format!("{IMU_HEADER}\n");
        imu_row(&mut text, &s);
        let back = parse_imu(&p(), &text).unwrap();
        assert_eq!(back, vec![s]);
    }

    #[test]
    fn frames_round_trip_including_empty_ones() {
        let frames = vec![
            ObservationFrame {
                time: 0.1,
                observations: vec![
                    Observation {
                        descriptor: 7,
                        z: Measurement::RangeBearing(Vector3::new(150.25, 0.1, -0.7)),
                        appearance: None,
                    },
                    Observation {
                        descriptor: FRESH_ID_BASE - 1,
                        z: Measurement::Pixel(Vector2::new(320.5, 10.0)),
                        appearance: None,
                    },
                ],
            },
            ObservationFrame {
                time: 0.2,
                observations: vec![],
            },
            ObservationFrame {
                time: 0.3,
                observations: vec![Observation {
                    descriptor: 3,
                    z: Measurement::Bearing(Vector2::new(-0.3, 0.2)),
                    appearance: None,
                }],
            },
        ];
        let mut text = format!("# comment\n{OBS_HEADER}\n");
        for f in &frames {
            frame_rows(&mut text, f);
        }
        assert_eq!(parse_observations(&p(), &text).unwrap(), frames);
    }

    #[test]
    fn malformed_rows_name_the_line_and_reason() {
        let cases = [
            (format!("{IMU_HEADER}\n0.01,0.01,1,2,3,4,5\n"), "fields"),
            (
                format!("{IMU_HEADER}\n0.01,0.01,1,2,x,4,5,6\n"),
                "not a number",
            ),
            (
                format!("{IMU_HEADER}\n0.01,0.01,1,2,NaN,4,5,6\n"),
                "not finite",
            ),
            (format!("{IMU_HEADER}\n0.01,0,1,2,3,4,5,6\n"), "dt"),
            (
                format!("{IMU_HEADER}\n0.02,0.01,1,2,3,4,5,6\n0.01,0.01,1,2,3,4,5,6\n"),
                "increase",
            ),
            ("t,dt\n".to_string(), "header"),
            (String::new(), "empty"),
        ];
        for (text, want) in cases {
            let e = parse_imu(&p(), &text).unwrap_err().to_string();
            assert!(e.contains(want), "{e} should mention {want}");
            assert!(e.starts_with("x.csv:"), "{e} should name the file and line");
        }
        let obs = [
            (format!("{OBS_HEADER}\n0.1,5,sonar,1,2,3\n"), "kind"),
            (format!("{OBS_HEADER}\n0.1,-5,bearing,1,2,\n"), "unsigned"),
            (
                format!("{OBS_HEADER}\n0.1,{},bearing,1,2,\n", u64::MAX),
                "reserves",
            ),
            (format!("{OBS_HEADER}\n0.1,5,bearing,1,2,3\n"), "z2 empty"),
            (
                format!("{OBS_HEADER}\n0.2,5,bearing,1,2,\n0.1,5,bearing,1,2,\n"),
                "time order",
            ),
            (
                format!("{OBS_HEADER}\n0.1,,none,,,\n0.1,5,bearing,1,2,\n"),
                "empty",
            ),
        ];
        for (text, want) in obs {
            let e = parse_observations(&p(), &text).unwrap_err().to_string();
            assert!(e.contains(want), "{e} should mention {want}");
        }
    }

    #[test]
    fn initial_estimate_round_trips_and_rejects_non_pd() {
        let mut cov = SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::identity() * 0.25;
        cov[(0, 1)] = 0.1;
        cov[(1, 0)] = 0.1;
        let e = InitialEstimate {
            time: 0.0,
            position: Vector3::new(-4.6e6, 2.5e6, -3.5e6),
            velocity: Vector3::new(1.0, 2.0, 3.0),
            attitude: Vector3::new(0.1, -0.2, 3.0),
            accel_bias: Vector3::new(1e-3, 0.0, -1e-3),
            gyro_bias: Vector3::new(1e-6, 2e-6, 3e-6),
            covariance: cov,
        };
        let text = initial_text(&e);
        assert_eq!(parse_initial(&p(), &text).unwrap(), e);
        let mut bad = e.clone();
        bad.covariance[(3, 3)] = -1.0;
        let err = parse_initial(&p(), &initial_text(&bad)).unwrap_err();
        assert!(err.to_string().contains("positive definite"), "{err}");
        let missing: String = text
            .lines()
            .filter(|l| !l.starts_with("cov7"))
            .collect::<Vec<_>>()
            .join("\n");
        assert!(
            parse_initial(&p(), &missing)
                .unwrap_err()
                .to_string()
                .contains("cov7")
        );
    }

    #[test]
    fn frames_between_samples_split_the_sample_they_fall_in() {
        let sample = |time: f64, dt: f64, f: f64| ImuSample {
            time,
            dt,
            specific_force: Vector3::new(f, 0.0, -9.8),
            angular_rate: Vector3::new(0.0, f, 0.0),
        };
        // Jittered samples ending at 0.005, 0.0099998, 0.0150003.
        let imu = vec![
            sample(0.005, 0.005, 1.0),
            sample(0.0099998, 0.0049998, 2.0),
            sample(0.0150003, 0.0050005, 3.0),
        ];
        let frame = |time: f64| ObservationFrame {
            time,
            observations: vec![],
        };
        // One frame inside the second interval, one on the third sample's time.
        let frames = vec![frame(0.007), frame(0.0150003)];
        let steps = split_at_frames(0.0, &imu, &frames);
        let times: Vec<f64> = steps.iter().map(|s| s.0.time).collect();
        assert_eq!(times, vec![0.005, 0.007, 0.0099998, 0.0150003]);
        let which: Vec<Option<usize>> = steps.iter().map(|s| s.1).collect();
        assert_eq!(which, vec![None, Some(0), None, Some(1)]);
        // The two parts keep the sample's measurement and tile its interval.
        assert_eq!(steps[1].0.specific_force, imu[1].specific_force);
        assert_eq!(steps[2].0.angular_rate, imu[1].angular_rate);
        assert!((steps[1].0.dt - 0.002).abs() < 1e-15);
        assert!((steps[1].0.dt + steps[2].0.dt - imu[1].dt).abs() < 1e-15);
        let mut t = 0.0;
        for (s, _) in &steps {
            // Round-off of the subtractions only.
            assert!((s.time - s.dt - t).abs() < 1e-15, "{s:?}");
            t = s.time;
        }
    }

    #[test]
    fn imu_intervals_must_tile_and_versions_after_two_are_refused() {
        let text = format!("{IMU_HEADER}\n0.01,0.01,0,0,-9.8,0,0,0\n0.02,0.005,0,0,-9.8,0,0,0\n");
        let e = parse_imu(&p(), &text).unwrap_err().to_string();
        assert!(
            e.starts_with("x.csv:3:") && e.contains("previous sample"),
            "{e}"
        );
        let text = format!("# canopy IMU log v3: later\n{IMU_HEADER}\n0.01,0.01,0,0,-9.8,0,0,0\n");
        let e = parse_imu(&p(), &text).unwrap_err().to_string();
        assert!(e.starts_with("x.csv:1:") && e.contains("v3"), "{e}");
        let text = format!("# canopy IMU log v1: older\n{IMU_HEADER}\n0.01,0.01,0,0,-9.8,0,0,0\n");
        assert_eq!(parse_imu(&p(), &text).unwrap().len(), 1);
    }

    #[test]
    fn the_initial_source_reads_static_or_a_path() {
        assert_eq!(
            InitialSource::from(PathBuf::from("static")),
            InitialSource::Static
        );
        assert_eq!(
            InitialSource::from(PathBuf::from("./static")),
            InitialSource::File(PathBuf::from("./static"))
        );
        assert_eq!(
            PathBuf::from(InitialSource::Static),
            PathBuf::from("static")
        );
    }

    /// Ground truth in run time: between two poses the position is interpolated linearly and
    /// the attitude along the rotation joining them (closed forms below), the velocity is the
    /// difference quotient; outside the span and across a gap there is no truth.
    #[test]
    fn ground_truth_interpolates_within_its_span_and_gaps() {
        use canopy_fusion::rotation::nav_from_body;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gt.tum");
        // Yaw 0 → 0.2 rad over [10, 10.1] s, moving 1 m/s north; a 1 s gap after 10.1 s.
        let q = |yaw: f64| UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
        let row = |t: f64, x: f64, yaw: f64| {
            let q = q(yaw);
            format!("{t} {x} 0 0 {} {} {} {}\n", q.i, q.j, q.k, q.w)
        };
        let text = format!(
            "{}{}{}",
            row(1000.0, 0.0, 0.0),
            row(1000.1, 0.1, 0.2),
            row(1001.1, 1.1, 0.2)
        );
        std::fs::write(&path, text).unwrap();
        let mut s = Scenario::builtin_default();
        s.world.earth_model = EarthModel::Flat;
        s.run.time_origin_ns = Some(990_000_000_000);
        let cfg = ReplayConfig {
            groundtruth: Some(path.clone()),
            ..ReplayConfig::in_dir(dir.path(), "v")
        };
        let gt = GroundTruth::load(&cfg, &s, [0.0, 20.0]).unwrap().unwrap();
        let x = gt.sample(10.025).unwrap();
        assert!((x.position - Vector3::new(0.025, 0.0, 0.0)).norm() < 1e-6);
        assert!((x.velocity - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-6);
        let want = nav_from_body(&Vector3::new(0.0, 0.0, 0.05));
        let got = nav_from_body(&x.attitude);
        assert!((got - want).norm() < 1e-6, "{got} vs {want}");
        assert!(gt.sample(9.99).is_none(), "before the span");
        assert!(gt.sample(10.6).is_none(), "inside the 1 s gap");
        assert!(gt.sample(11.2).is_none(), "after the span");
        // A truth that does not overlap the log names the time base.
        let err = GroundTruth::load(&cfg, &s, [100.0, 120.0]).unwrap_err();
        assert!(err.to_string().contains("time_origin_ns"), "{err}");
        // A global world has no local frame to read it in.
        let mut g = s.clone();
        g.world.earth_model = EarthModel::Wgs84;
        assert!(GroundTruth::load(&cfg, &g, [0.0, 20.0]).is_err());
    }

    /// Zero-velocity updates over a period the IMU log shows moving are refused.
    #[test]
    fn zero_velocity_beyond_the_rest_is_refused() {
        let dt = 0.005;
        let g = Vector3::new(0.0, 0.0, -9.81);
        // At rest 2 s, then accelerating 1 m/s² north.
        let imu: Vec<ImuSample> = (1..=800)
            .map(|k| ImuSample {
                time: k as f64 * dt,
                dt,
                specific_force: if k as f64 * dt <= 2.0 {
                    g
                } else {
                    g + Vector3::new(1.0, 0.0, 0.0)
                },
                angular_rate: Vector3::zeros(),
            })
            .collect();
        let cfg = ReplayConfig::in_dir(Path::new("/nonexistent"), "v");
        let z = |until_s| ZeroVelocityConfig {
            until_s,
            sigma_mps: 0.01,
            rate_hz: 20.0,
        };
        assert!(check_rest(&cfg, &imu, &z(1.9)).is_ok());
        let err = check_rest(&cfg, &imu, &z(3.0)).unwrap_err().to_string();
        assert!(err.contains("rests only until"), "{err}");
    }
}
