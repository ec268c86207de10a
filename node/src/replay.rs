//! Recorded sensor logs (CSV) and the sensor sources of a run: a simulated vehicle, or a vehicle
//! whose IMU samples and observation frames are replayed from logs.
//!
//! # Log format (version 1)
//! Three CSV files per vehicle, comma separated, `#` starts a comment line, the first
//! non-comment line is the exact header given below. Numbers are decimal (Rust `f64` syntax;
//! `canopy sim --record-logs` writes the shortest text that reads back to the same bits).
//! Quantities are those the estimator receives, in its navigation frame (ECEF for a `wgs84`
//! world, the launch site's NED frame for a `flat` one).
//!
//! - `<name>.imu.csv` — one IMU sample per row, times strictly increasing:
//!   `t,dt,f_x,f_y,f_z,w_x,w_y,w_z` — end of the sample interval [s], interval Δt [s],
//!   measured specific force f̂^b [m/s²] and body rate ω̂^b_ib [rad/s] (eqs. 21.13, 21.14).
//! - `<name>.obs.csv` — one observation per row; rows with the same `t` form one frame, frame
//!   times non-decreasing:
//!   `t,descriptor,kind,z0,z1,z2` — frame time [s] (the time of the IMU sample it follows),
//!   the feature descriptor (u64), and `kind` = `range_bearing` (z0 = range [m], z1 = azimuth,
//!   z2 = elevation [rad], eq. 21.41), `bearing` (z0 = azimuth, z1 = elevation [rad], z2
//!   empty, eq. 21.42) or `pixel` (z0 = u, z1 = v [px], z2 empty, eq. 21.43). A frame without
//!   observations is one row `t,,none,,,`.
//! - `<name>.init.csv` — the initial estimate: 16 rows `what,t,v0,…,v14`; `what` = `mean`
//!   (state p, v, Ψ, δf^b, δω^b in the order of `fusion::state`) then `cov0` … `cov14` (the rows
//!   of the 15×15 covariance); `t` is the time of the estimate (the start of the logs).
//!
//! A replayed vehicle has no truth: its metrics are marked unavailable in the outputs.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use canopy_fusion::sensor::{FeatureId, ImuSample, Measurement, Observation, ObservationFrame};
use canopy_fusion::state::VEHICLE_DIM;
use nalgebra::{SMatrix, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::scenario::{Scenario, ScenarioError, VehicleConfig};
use crate::world::{self, InitialEstimate, TruthSample, VehicleSim, World};

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
    /// Initial estimate (*required*).
    pub initial: PathBuf,
}

impl ReplayConfig {
    /// The three files of vehicle `name` in `dir`, named as `--record-logs` writes them.
    pub fn in_dir(dir: &Path, name: &str) -> Self {
        Self {
            imu: dir.join(format!("{name}.imu.csv")),
            observations: dir.join(format!("{name}.obs.csv")),
            initial: dir.join(format!("{name}.init.csv")),
        }
    }

    /// Makes relative paths relative to `base`.
    pub fn resolve(&mut self, base: &Path) {
        for p in [&mut self.imu, &mut self.observations, &mut self.initial] {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        }
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
    /// IMU samples in time order.
    pub imu: Vec<ImuSample>,
    /// Frames in time order.
    pub frames: Vec<ObservationFrame>,
    /// Initial estimate.
    pub initial: InitialEstimate,
}

fn read(path: &Path) -> Result<String, ReplayError> {
    std::fs::read_to_string(path).map_err(|source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Data lines of a CSV log after its header: (1-based line number, fields).
fn data_lines<'a>(
    path: &Path,
    text: &'a str,
    header: &str,
) -> Result<Vec<(usize, Vec<&'a str>)>, ReplayError> {
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
        if let Some(prev) = out.last()
            && v[0] <= prev.time
        {
            return Err(ReplayError::Format {
                path: path.to_path_buf(),
                line: n,
                reason: format!(
                    "t = {} does not follow {} (times must increase)",
                    v[0], prev.time
                ),
            });
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
    let mut frames: Vec<ObservationFrame> = Vec::new();
    for (n, f) in data_lines(path, text, OBS_HEADER)? {
        let t = num(path, n, "t", f[0])?;
        let bad = |reason: String| ReplayError::Format {
            path: path.to_path_buf(),
            line: n,
            reason,
        };
        let new_frame = match frames.last() {
            Some(last) if last.time == t => false,
            Some(last) if t < last.time => {
                return Err(bad(format!(
                    "t = {t} is before the previous frame at {} (frames must be in time order)",
                    last.time
                )));
            }
            _ => true,
        };
        if new_frame {
            frames.push(ObservationFrame {
                time: t,
                observations: Vec::new(),
            });
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
        let frame = frames.last_mut().expect("pushed above");
        if frame.observations.is_empty() && !new_frame {
            // The frame was declared empty by a `none` row.
            return Err(bad(format!("frame at t = {t} was declared empty (`none`)")));
        }
        frame.observations.push(Observation { descriptor, z });
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
    /// Reads and checks the three files of `cfg`. A frame time must equal the time of an IMU
    /// sample (the frame follows that sample).
    pub fn load(cfg: &ReplayConfig) -> Result<Self, ReplayError> {
        let imu = parse_imu(&cfg.imu, &read(&cfg.imu)?)?;
        let frames = parse_observations(&cfg.observations, &read(&cfg.observations)?)?;
        let initial = parse_initial(&cfg.initial, &read(&cfg.initial)?)?;
        let mut k = 0;
        for fr in &frames {
            while k < imu.len() && imu[k].time < fr.time {
                k += 1;
            }
            if k == imu.len() || imu[k].time != fr.time {
                return Err(ReplayError::Format {
                    path: cfg.observations.clone(),
                    line: 1,
                    reason: format!(
                        "the frame at t = {} does not follow an IMU sample of the same time",
                        fr.time
                    ),
                });
            }
        }
        if let Some(first) = imu.first()
            && first.time <= initial.time
        {
            return Err(ReplayError::Format {
                path: cfg.imu.clone(),
                line: 1,
                reason: format!(
                    "the first sample (t = {}) is not after the initial estimate (t = {})",
                    first.time, initial.time
                ),
            });
        }
        Ok(Self {
            imu,
            frames,
            initial,
        })
    }
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
    let mut out =
        format!("# canopy initial estimate v1 (estimator navigation frame)\n{INIT_HEADER}\n");
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
        let cfg = ReplayConfig::in_dir(dir, &name);
        let mut imu = format!(
            "# canopy IMU log v1: vehicle {name}, estimator navigation frame\n{IMU_HEADER}\n"
        );
        let mut obs = format!(
            "# canopy observation log v1: vehicle {name}, estimator navigation frame\n{OBS_HEADER}\n"
        );
        while sim.time() + sim.imu_dt() <= duration + 1e-9 {
            let step = sim.step();
            imu_row(&mut imu, &step.imu);
            if let Some(f) = &step.frame {
                frame_rows(&mut obs, &f.frame);
            }
        }
        write_file(&cfg.imu, &imu)?;
        write_file(&cfg.observations, &obs)?;
        write_file(&cfg.initial, &initial_text(sim.initial_estimate()))?;
        out.push((name, cfg));
    }
    Ok(out)
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

/// A replayed vehicle being streamed.
#[derive(Clone, Debug)]
pub struct ReplayStream {
    log: Arc<ReplayLog>,
    next_imu: usize,
    next_frame: usize,
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
    /// The sources of every vehicle of `s` (loading replay logs).
    pub fn for_scenario(s: &Scenario) -> Result<(Arc<World>, Vec<SensorSource>), ReplayError> {
        let (world, sims) = world::build(s)?;
        let mut out = Vec::with_capacity(sims.len());
        for (v, sim) in s.vehicles.iter().zip(sims) {
            out.push(Self::for_vehicle(v, sim)?);
        }
        Ok((world, out))
    }

    fn for_vehicle(v: &VehicleConfig, sim: VehicleSim) -> Result<Self, ReplayError> {
        Ok(match &v.replay {
            None => SensorSource::Sim(Box::new(sim)),
            Some(r) => SensorSource::Replay(ReplayStream {
                log: Arc::new(ReplayLog::load(r)?),
                next_imu: 0,
                next_frame: 0,
            }),
        })
    }

    /// Time of the last step (or of the initial estimate).
    pub fn time(&self) -> f64 {
        match self {
            SensorSource::Sim(s) => s.time(),
            SensorSource::Replay(r) => r
                .next_imu
                .checked_sub(1)
                .map_or(r.log.initial.time, |k| r.log.imu[k].time),
        }
    }

    /// Time of the next step; `None` once a log is exhausted (a simulator never is).
    pub fn next_time(&self) -> Option<f64> {
        match self {
            SensorSource::Sim(s) => Some(s.time() + s.imu_dt()),
            SensorSource::Replay(r) => r.log.imu.get(r.next_imu).map(|s| s.time),
        }
    }

    /// Advances one IMU sample.
    pub fn step(&mut self) -> Option<SourceStep> {
        match self {
            SensorSource::Sim(s) => {
                let out = s.step();
                Some(SourceStep {
                    imu: out.imu,
                    frame: out.frame.map(|f| (f.frame, Some(f.true_ids))),
                    truth: Some(out.truth),
                })
            }
            SensorSource::Replay(r) => {
                let imu = *r.log.imu.get(r.next_imu)?;
                r.next_imu += 1;
                let frame = r
                    .log
                    .frames
                    .get(r.next_frame)
                    .filter(|f| f.time == imu.time)
                    .cloned();
                if frame.is_some() {
                    r.next_frame += 1;
                }
                Some(SourceStep {
                    imu,
                    frame: frame.map(|f| (f, None)),
                    truth: None,
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

    /// A re-initialisation from an external fix at the current time (simulated vehicles only).
    pub fn restart_estimate(&self, draw: u64) -> Option<InitialEstimate> {
        match self {
            SensorSource::Sim(s) => Some(s.restart_estimate(draw)),
            SensorSource::Replay(_) => None,
        }
    }

    /// Current truth (simulated vehicles only).
    pub fn truth(&self) -> Option<&TruthSample> {
        match self {
            SensorSource::Sim(s) => Some(s.truth()),
            SensorSource::Replay(_) => None,
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
                    },
                    Observation {
                        descriptor: u64::MAX,
                        z: Measurement::Pixel(Vector2::new(320.5, 10.0)),
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
}
