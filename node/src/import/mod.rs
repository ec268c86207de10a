//! `canopy import`: a real visual-inertial recording → a replay scenario (scenario.toml, the
//! replay logs, and the ground truth in canopy's frames).
//!
//! Layouts: the ASL folder (`mav0/imu0/data.csv`, `mav0/imu0/sensor.yaml`,
//! `mav0/cam0/sensor.yaml`, `mav0/state_groundtruth_estimate0/data.csv`, tracks in
//! `tracks.csv` or `mav0/cam0/tracks.csv`) or flat files (`imu.csv`, `cam0.yaml`,
//! `camchain-imucam.yaml`, `imu0.yaml`, `tracks.csv`, `groundtruth.tum` / `groundtruth.csv`);
//! any file can be named explicitly instead. File formats: [`parse`].
//!
//! # Frames (the importer's job, not the user's)
//! - **Body frame b.** The filter uses z-y-x Euler angles (singular at pitch ±90°) and expects a
//!   body frame near level (x forward, y right, z down). A recording's IMU axes S need not be
//!   (EuRoC's x points up at rest). The importer picks b as a fixed rotation of S: z_b along
//!   gravity (−mean specific force over the rest period at the start; the ground truth's
//!   vertical when there is no rest), x_b along the camera's optical axis projected on the
//!   horizontal plane (image up, projected, for a camera looking straight down), y_b = z_b × x_b.
//!   The body origin is the IMU's. IMU samples are rotated into b: f^b = C_S^b f^S.
//! - **Camera mount.** The filter's sensor frame s (eq. 21.43): x along the optical axis, y right,
//!   z down in the image, i.e. s = (z_c, x_c, y_c) of the camera frame c. C_b^s = C_c^s C_S^c
//!   C_b^S and the lever arm p^b = C_S^b p^S_cam, from EuRoC's `T_BS` (camera pose in S) or
//!   Kalibr's `T_cam_imu` (its inverse).
//! - **Observations.** Undistorted normalized coordinates become pixels of a virtual undistorted
//!   pinhole camera ([`camera::VirtualPinhole`]): the calibration's focal lengths, the principal
//!   point and size chosen so the image holds every undistorted raw pixel. Pixel tracks are
//!   undistorted with the calibration's model first.
//! - **Navigation frame n** (local, `earth_model = "flat"`): origin at the body at the start,
//!   north along the body's initial heading, down along gravity; yaw and position zero at the
//!   start define it. The ground truth (motion-capture world W, z up) is expressed in it:
//!   C_b^n = C_W^n C_S^W C_b^S with C_W^n = R_z(ψ₀)ᵀ·diag(1, −1, −1), ψ₀ the body's initial
//!   heading in that NED version of W, p^n = C_W^n (p^W − p^W₀).
//!
//! # Noise (measured on the recording, not tuned)
//! IMU white-noise densities: the larger of the calibration's and those measured over the rest
//! period ([`canopy_fusion::alignment::rest_noise_density`]). Pixel σ: `--sigma-px` per
//! observation, correlated along a track over `--track-correlation-s`, written as the
//! equivalent independent σ at the frame interval ([`equivalent_white_sigma`]). The defaults
//! and their measurements: docs/arch/import.md.
//!
//! # Time
//! The recording's clock is kept: `[run] time_origin_ns` is the first replayed IMU timestamp
//! (t = 0, the time of the initial estimate); log times are (ns − origin)/1e9 as f64, which
//! rounds back to the exact nanosecond; every output (TUM files) is stamped origin + t exactly.
//! An IMU sample is the measurement over the interval ending at its timestamp (Δt = time since
//! the previous sample, so jitter and gaps are kept); frames keep their own times, and the replay
//! splits the IMU sample a frame falls in.

pub mod camera;
pub mod parse;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use canopy_fusion::alignment::{self, RestDetection};
use canopy_fusion::rotation::{euler_from_nav_from_body, nav_from_body};
use canopy_fusion::sensor::{ImuSample, Measurement, Observation, ObservationFrame};
use canopy_fusion::state::{ACC_BIAS, ATT, GYRO_BIAS, POS, VEHICLE_DIM, VEL};
use nalgebra::{Matrix3, SMatrix, UnitQuaternion, Vector2, Vector3};

use self::camera::VirtualPinhole;
use self::parse::{
    CameraCalibration, GroundTruth, ImportError, ImuCalibration, RawImu, TrackCoordinates,
};
use crate::replay::{IMU_HEADER, OBS_HEADER, frame_rows, imu_row, initial_text};
use crate::scenario::{ImuNoiseConfig, OriginConfig, Scenario};
use crate::world::InitialEstimate;

/// ADIS16448 noise figures (the EuRoC MAV's IMU, from EuRoC's `imu0/sensor.yaml`), used when the
/// recording has no IMU calibration: gyro and accelerometer white-noise densities
/// [rad/s/√Hz, m/s²/√Hz] and bias random walks [rad/s²/√Hz, m/s³/√Hz].
pub const ADIS16448: ImuCalibration = ImuCalibration {
    gyro_noise_density: 1.6968e-4,
    gyro_random_walk: 1.9393e-5,
    accel_noise_density: 2.0e-3,
    accel_random_walk: 3.0e-3,
    body_from_imu: None,
};

/// Where the initial estimate comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum InitialChoice {
    /// Static alignment if a rest period is found at the start, else the ground truth.
    Auto,
    /// Static alignment over the rest period (`initial = "static"`).
    Static,
    /// The first ground-truth pose (written as `<name>.init.csv`).
    Groundtruth,
}

/// `canopy import` options.
#[derive(Clone, Debug, clap::Args)]
pub struct ImportArgs {
    /// Recording folder (ASL layout with mav0/, or flat files); the files below override what
    /// is found there.
    pub dir: Option<PathBuf>,
    /// Output directory for the scenario (created).
    #[arg(long)]
    pub out: PathBuf,
    /// IMU CSV (EuRoC/ASL layout).
    #[arg(long)]
    pub imu: Option<PathBuf>,
    /// Camera calibration, EuRoC `sensor.yaml` layout.
    #[arg(long)]
    pub camera: Option<PathBuf>,
    /// Camera calibration, Kalibr `camchain-imucam.yaml` (instead of --camera).
    #[arg(long)]
    pub kalibr: Option<PathBuf>,
    /// IMU noise calibration (EuRoC `imu0/sensor.yaml` or Kalibr `imu.yaml`); default: the
    /// ADIS16448 figures.
    #[arg(long)]
    pub imu_calib: Option<PathBuf>,
    /// Feature tracks CSV.
    #[arg(long)]
    pub tracks: Option<PathBuf>,
    /// Ground truth (TUM `.tum`/`.txt`, or ASL `.csv`).
    #[arg(long)]
    pub groundtruth: Option<PathBuf>,
    /// Initial estimate.
    #[arg(long, value_enum, default_value = "auto")]
    pub initial: InitialChoice,
    /// The vehicle rests this long from the start [s] (default: detected).
    #[arg(long)]
    pub rest: Option<f64>,
    /// Site latitude [deg] (the scenario's origin: WGS-84 normal gravity there).
    #[arg(long)]
    pub latitude: Option<f64>,
    /// Site longitude [deg].
    #[arg(long)]
    pub longitude: Option<f64>,
    /// Site height above the WGS-84 ellipsoid [m].
    #[arg(long)]
    pub height: Option<f64>,
    /// Gravity magnitude [m/s²] (`[world] gravity_mps2`), instead of the site's normal gravity.
    #[arg(long)]
    pub gravity: Option<f64>,
    /// Pixel noise σ of one observation of a track [px] (normalized tracks: σ/f in the image
    /// plane). Default 1 px: the EuRoC V1_01 tracks against the motion capture, per axis, after
    /// the common error of each frame is removed (0.85 / 0.96 px, `real_data.rs`;
    /// docs/arch/import.md).
    #[arg(long, default_value_t = 1.0)]
    pub sigma_px: f64,
    /// Correlation time of a track's pixel error [s] (0: independent frames). A tracker follows
    /// its own previous estimate, so the error of one track is correlated from frame to frame;
    /// the filter takes observations as independent, so the scenario's σ is the equivalent
    /// white σ at the recording's frame interval Δ: σ·√((1+ρ)/(1−ρ)), ρ = exp(−Δ/τ) (the
    /// variance of a long average of a first-order Gauss–Markov sequence). Default 0.33 s:
    /// measured on the EuRoC V1_01 tracks against the motion capture (autocorrelation 0.86,
    /// 0.76, 0.49, 0.20 at 1, 2, 5, 10 frames).
    #[arg(long, default_value_t = 0.33)]
    pub track_correlation_s: f64,
    /// 1-σ turn-on accelerometer bias [m/s²] (unobservable at rest; ≈ 10 mg for a MEMS IMU).
    #[arg(long, default_value_t = 0.1)]
    pub accel_bias_sigma: f64,
    /// 1-σ turn-on gyro bias [rad/s] (EuRoC's ADIS16448 shows ≈ 0.08 rad/s on one axis).
    #[arg(long, default_value_t = 0.1)]
    pub gyro_bias_sigma: f64,
    /// Scale on the IMU white-noise densities of the calibration (default 1: the figures as
    /// given). The densities written are the larger of these and the densities measured on the
    /// recording's own rest period (`--calibration-noise` to skip the measurement).
    #[arg(long, default_value_t = 1.0)]
    pub imu_noise_scale: f64,
    /// Use only the calibration's IMU noise densities (× `--imu-noise-scale`) and bias random
    /// walks, not the white noise measured over the rest period
    /// ([`canopy_fusion::alignment::rest_noise_density`]) nor the in-flight bias walks below.
    #[arg(long)]
    pub calibration_noise: bool,
    /// Gyro bias random walk of the IMU in flight [rad/s²/√Hz]; the scenario gets the larger of
    /// this and the calibration's. A calibration's figure is for a still sensor at constant
    /// temperature; on a running multirotor the bias wanders far more (vibration, temperature,
    /// g-sensitivity). Default 1.0e-3: measured on EuRoC V1_01 (ADIS16448 on the AscTec
    /// Firefly) against the motion capture, the Allan deviation of the IMU's rate less the
    /// ground truth's over the flight at τ = 3.2 s as a rate random walk, K = σ(τ)·√(3/τ), RMS
    /// over the axes (`real_data.rs`; docs/arch/import.md). Give your platform's figure.
    #[arg(long, default_value_t = 1.0e-3)]
    pub gyro_bias_walk: f64,
    /// Accelerometer bias random walk in flight [m/s³/√Hz] (as `--gyro-bias-walk`). Default
    /// 3.2e-2: measured the same way on EuRoC V1_01 (specific force less the ground truth's).
    #[arg(long, default_value_t = 3.2e-2)]
    pub accel_bias_walk: f64,
    /// Feature initialization: rays of a track must span this angle [deg]. Default 10°, the
    /// filter's own default: a triangulation's relative depth error is ≈ σ_θ/parallax (σ_θ =
    /// σ/f, the equivalent white σ above: 0.45° on EuRoC at 20 Hz), ≈ 9 % at 5° and 4.5 % at 10°,
    /// and the EKF linearizes at that point (on EuRoC V1_01, 5° left pose ANEES 5.7 and a 4 %
    /// scale error, 10° 3.1 and 1.4 %: docs/benchmarks.md).
    #[arg(long, default_value_t = 10.0)]
    pub min_parallax: f64,
    /// Nearest depth a feature may have [m].
    #[arg(long, default_value_t = 0.1)]
    pub min_depth: f64,
    /// Farthest depth a feature may have [m].
    #[arg(long, default_value_t = 100.0)]
    pub max_depth: f64,
    /// No zero-velocity updates over the rest period at the start (ablation).
    #[arg(long)]
    pub no_zero_velocity: bool,
    /// Vehicle name (names the log files).
    #[arg(long, default_value = "mav")]
    pub name: String,
    /// Scenario name (default: the recording folder's name).
    #[arg(long)]
    pub scenario_name: Option<String>,
    /// Interval of the estimates in the outputs [s].
    #[arg(long, default_value_t = 0.1)]
    pub record_interval: f64,
}

/// The files of a recording.
#[derive(Clone, Debug, Default)]
pub struct RecordingFiles {
    /// IMU CSV.
    pub imu: Option<PathBuf>,
    /// EuRoC camera sensor.yaml.
    pub camera: Option<PathBuf>,
    /// Kalibr camchain.
    pub kalibr: Option<PathBuf>,
    /// IMU calibration yaml.
    pub imu_calib: Option<PathBuf>,
    /// Tracks CSV.
    pub tracks: Option<PathBuf>,
    /// Ground truth.
    pub groundtruth: Option<PathBuf>,
}

fn first_existing(dir: &Path, names: &[&str]) -> Option<PathBuf> {
    names.iter().map(|n| dir.join(n)).find(|p| p.is_file())
}

/// Finds a recording's files in `dir` (ASL or flat layout); explicit ones in `args` win.
pub fn find_files(args: &ImportArgs) -> RecordingFiles {
    let mut f = RecordingFiles::default();
    if let Some(d) = &args.dir {
        let mav = if d.join("mav0").is_dir() {
            d.join("mav0")
        } else {
            d.clone()
        };
        f.imu =
            first_existing(&mav, &["imu0/data.csv"]).or_else(|| first_existing(d, &["imu.csv"]));
        f.imu_calib = first_existing(&mav, &["imu0/sensor.yaml"])
            .or_else(|| first_existing(d, &["imu0.yaml", "imu.yaml"]));
        f.camera = first_existing(&mav, &["cam0/sensor.yaml"])
            .or_else(|| first_existing(d, &["cam0.yaml"]));
        f.kalibr = first_existing(d, &["camchain-imucam.yaml"]);
        f.tracks = first_existing(d, &["tracks.csv"])
            .or_else(|| first_existing(&mav, &["cam0/tracks.csv"]));
        f.groundtruth =
            first_existing(&mav, &["state_groundtruth_estimate0/data.csv"]).or_else(|| {
                first_existing(
                    d,
                    &["groundtruth.tum", "groundtruth.txt", "groundtruth.csv"],
                )
            });
    }
    let over = |a: &Option<PathBuf>, b: &mut Option<PathBuf>| {
        if a.is_some() {
            b.clone_from(a);
        }
    };
    over(&args.imu, &mut f.imu);
    over(&args.camera, &mut f.camera);
    over(&args.kalibr, &mut f.kalibr);
    over(&args.imu_calib, &mut f.imu_calib);
    over(&args.tracks, &mut f.tracks);
    over(&args.groundtruth, &mut f.groundtruth);
    if args.kalibr.is_some() && args.camera.is_none() {
        f.camera = None;
    }
    f
}

/// What an import produced (also printed by the command).
#[derive(Clone, Debug)]
pub struct ImportSummary {
    /// The scenario file written.
    pub scenario: PathBuf,
    /// The ground-truth file written (canopy's navigation frame, recording time base).
    pub groundtruth: Option<PathBuf>,
    /// IMU samples written.
    pub imu_samples: usize,
    /// Frames and observations written.
    pub frames: usize,
    /// Observations written.
    pub observations: usize,
    /// Frames dropped (at or before the start, after the last IMU sample).
    pub frames_dropped: usize,
    /// `[run] time_origin_ns`.
    pub time_origin_ns: u64,
    /// C_b^S: IMU axes of the body axes.
    pub imu_from_body: Matrix3<f64>,
    /// Rest period used [s], if any.
    pub rest_s: Option<f64>,
    /// Initial estimate chosen.
    pub initial: InitialChoice,
    /// The virtual camera.
    pub pinhole: VirtualPinhole,
    /// Lines to print.
    pub notes: Vec<String>,
}

fn need(p: Option<PathBuf>, what: &str, flag: &str) -> Result<PathBuf, ImportError> {
    p.ok_or_else(|| {
        ImportError::Missing(format!(
            "missing {what}: give {flag} or a recording folder that holds it"
        ))
    })
}

/// A unit vector orthogonal to `d` closest to `v` (Gram–Schmidt); `None` when `v` ∥ `d`.
fn horizontal(v: &Vector3<f64>, down: &Vector3<f64>) -> Option<Vector3<f64>> {
    let h = v - down * v.dot(down);
    (h.norm() > 0.1).then(|| h.normalize())
}

/// C_b^S of the body frame: z along `down_imu`, x along the camera's optical axis (or image
/// up) projected on the horizontal.
pub fn body_frame(down_imu: &Vector3<f64>, imu_from_camera: &Matrix3<f64>) -> Matrix3<f64> {
    let z = down_imu.normalize();
    let optical = imu_from_camera.column(2).into_owned();
    let image_up = -imu_from_camera.column(1).into_owned();
    let x = horizontal(&optical, &z)
        .or_else(|| horizontal(&image_up, &z))
        .expect("the optical axis and image up are orthogonal: one is not vertical");
    let y = z.cross(&x);
    Matrix3::from_columns(&[x, y, z])
}

/// The white σ that stands for observations of σ `sigma` every `interval` whose errors are
/// correlated with time constant `tau` (first-order Gauss–Markov, ρ = exp(−interval/τ)): the
/// mean of n such observations has variance σ²/n·(1+ρ)/(1−ρ) for large n, that of n independent
/// ones of σ' is σ'²/n, so σ' = σ·√((1+ρ)/(1−ρ)). `tau` = 0: independent, σ' = σ.
pub fn equivalent_white_sigma(sigma: f64, interval: f64, tau: f64) -> f64 {
    if tau <= 0.0 || interval <= 0.0 {
        return sigma;
    }
    let rho = (-interval / tau).exp();
    sigma * ((1.0 + rho) / (1.0 - rho)).sqrt()
}

/// C_c^s: camera frame (x right, y down, z forward) → filter sensor frame (x forward, y right,
/// z down), eq. 21.43.
pub fn sensor_from_camera() -> Matrix3<f64> {
    Matrix3::new(0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
}

/// Ground truth interpolated at `t_ns` (linear position, slerp attitude), clamped to the ends.
fn gt_at(gt: &[GroundTruth], t_ns: u64) -> (Vector3<f64>, UnitQuaternion<f64>) {
    let k = gt.partition_point(|g| g.t_ns <= t_ns);
    if k == 0 {
        return (gt[0].position, gt[0].world_from_imu);
    }
    if k == gt.len() {
        let g = gt[k - 1];
        return (g.position, g.world_from_imu);
    }
    let (a, b) = (gt[k - 1], gt[k]);
    let s = (t_ns - a.t_ns) as f64 / (b.t_ns - a.t_ns) as f64;
    (
        a.position + (b.position - a.position) * s,
        a.world_from_imu.slerp(&b.world_from_imu, s),
    )
}

/// Ground-truth velocity v^W at `t_ns`: the ASL estimate, or the central difference of the
/// interpolated positions over ±one ground-truth interval.
fn gt_velocity(gt: &[GroundTruth], t_ns: u64) -> Vector3<f64> {
    let k = gt
        .partition_point(|g| g.t_ns <= t_ns)
        .clamp(1, gt.len() - 1);
    if let Some(v) = gt[k - 1].velocity {
        return v;
    }
    let dt = gt[k].t_ns - gt[k - 1].t_ns;
    let (a, b) = (t_ns.saturating_sub(dt), t_ns + dt);
    (gt_at(gt, b).0 - gt_at(gt, a).0) / ((b - a) as f64 * 1e-9)
}

/// C_W^n of the navigation frame whose origin and heading are the body's at the start:
/// R_z(ψ₀)ᵀ·diag(1, −1, −1) (module docs).
fn nav_from_world(
    world_from_imu: &UnitQuaternion<f64>,
    imu_from_body: &Matrix3<f64>,
) -> Matrix3<f64> {
    let ned_from_world = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
    let c = ned_from_world * world_from_imu.to_rotation_matrix().matrix() * imu_from_body;
    let yaw = euler_from_nav_from_body(&c).z;
    nav_from_body(&Vector3::new(0.0, 0.0, yaw)).transpose() * ned_from_world
}

fn write(path: &Path, text: &str) -> Result<(), ImportError> {
    std::fs::write(path, text).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })
}

fn rel_s(t_ns: u64, origin: u64) -> f64 {
    (t_ns as i128 - origin as i128) as f64 * 1e-9
}

/// Runs an import.
pub fn import(args: &ImportArgs) -> Result<ImportSummary, ImportError> {
    let files = find_files(args);
    let imu_path = need(files.imu.clone(), "the IMU CSV", "--imu")?;
    let tracks_path = need(files.tracks.clone(), "the feature tracks", "--tracks")?;
    let raw = parse::imu_csv(&imu_path)?;
    if raw.len() < 2 {
        return Err(ImportError::Format {
            path: imu_path,
            line: 1,
            reason: "fewer than two IMU samples".into(),
        });
    }
    let imu_calib = match &files.imu_calib {
        Some(p) => parse::imu_calibration(p)?,
        None => ADIS16448,
    };
    let cam: CameraCalibration = match (&files.kalibr, &files.camera) {
        (Some(k), None) => parse::kalibr_camera(k)?,
        (_, Some(c)) => parse::euroc_camera(c, imu_calib.body_from_imu)?,
        (None, None) => {
            return Err(ImportError::Missing(
                "missing calibration: give --camera (EuRoC sensor.yaml) or --kalibr \
                 (camchain-imucam.yaml), or a recording folder that holds one"
                    .into(),
            ));
        }
    };
    let (coords, tracks) = parse::tracks_csv(&tracks_path)?;
    let gt = files
        .groundtruth
        .as_ref()
        .map(|p| parse::ground_truth(p))
        .transpose()?;
    let mut notes = Vec::new();

    // The rest period, from the raw samples (S axes; the detection compares norms only).
    let t0 = raw[0].t_ns;
    let raw_samples: Vec<ImuSample> = raw
        .windows(2)
        .map(|w| ImuSample {
            time: rel_s(w[1].t_ns, t0),
            dt: (w[1].t_ns - w[0].t_ns) as f64 * 1e-9,
            specific_force: w[1].accel,
            angular_rate: w[1].gyro,
        })
        .collect();
    let rest_n = match args.rest {
        Some(r) => {
            if !(r.is_finite() && r > 0.0) {
                return Err(ImportError::Missing(format!("--rest {r}: must be > 0")));
            }
            Some(raw_samples.partition_point(|s| s.time <= r + 1e-9))
        }
        None => alignment::detect_rest(&raw_samples, &RestDetection::default()),
    };
    let rest_s = rest_n.map(|n| raw_samples[n - 1].time);
    let down_imu = match (rest_n, &gt) {
        (Some(n), _) => {
            let mean = raw_samples[..n]
                .iter()
                .fold(Vector3::zeros(), |a, s| a + s.specific_force)
                / n as f64;
            -mean
        }
        (None, Some(gt)) => gt_at(gt, t0).1.inverse() * Vector3::new(0.0, 0.0, -1.0),
        (None, None) => {
            return Err(ImportError::Missing(
                "cannot choose a level body frame: no rest period found at the start of the IMU \
                 log and no ground truth; give --rest SECONDS or --groundtruth"
                    .into(),
            ));
        }
    };
    let imu_from_body = body_frame(&down_imu, &cam.imu_from_camera);
    let body_from_imu = imu_from_body.transpose();

    let initial = match args.initial {
        InitialChoice::Auto if rest_n.is_some() => InitialChoice::Static,
        InitialChoice::Auto if gt.is_some() => InitialChoice::Groundtruth,
        InitialChoice::Auto => {
            return Err(ImportError::Missing(
                "no initial estimate: no rest period at the start (give --rest) and no ground \
                 truth (give --groundtruth)"
                    .into(),
            ));
        }
        InitialChoice::Static if rest_n.is_none() => {
            return Err(ImportError::Missing(
                "--initial static: no rest period of at least 1 s found at the start; give --rest SECONDS"
                    .into(),
            ));
        }
        InitialChoice::Groundtruth if gt.is_none() => {
            return Err(ImportError::Missing(
                "--initial groundtruth needs --groundtruth".into(),
            ));
        }
        c => c,
    };
    // The first replayed instant: the first IMU sample (static), or the first IMU sample at or
    // after the first ground-truth pose.
    let start = match (initial, &gt) {
        (InitialChoice::Groundtruth, Some(g)) => raw.partition_point(|s| s.t_ns < g[0].t_ns),
        _ => 0,
    };
    if start + 1 >= raw.len() {
        return Err(ImportError::Missing(
            "the ground truth starts after the last IMU sample".into(),
        ));
    }
    let origin = raw[start].t_ns;

    std::fs::create_dir_all(&args.out).map_err(|source| ImportError::Io {
        path: args.out.clone(),
        source,
    })?;
    let name = &args.name;
    let source = |p: &Path| p.display().to_string();

    // IMU log.
    let mut imu_text = format!(
        "# canopy IMU log v{}: vehicle {name}, body axes (b = C_S^b · IMU axes), imported from {}\n{IMU_HEADER}\n",
        crate::replay::FORMAT_VERSION,
        source(&imu_path)
    );
    let mut imu_samples: Vec<ImuSample> = Vec::with_capacity(raw.len() - start);
    for w in raw[start..].windows(2) {
        let (a, b): (&RawImu, &RawImu) = (&w[0], &w[1]);
        let t = rel_s(b.t_ns, origin);
        let s = ImuSample {
            time: t,
            dt: t - rel_s(a.t_ns, origin),
            specific_force: body_from_imu * b.accel,
            angular_rate: body_from_imu * b.gyro,
        };
        imu_row(&mut imu_text, &s);
        imu_samples.push(s);
    }
    let last_t = imu_samples.last().map_or(0.0, |s| s.time);

    // Camera and observations: normalized coordinates first, then the virtual camera that
    // holds them all.
    // Per frame: its time [ns] and its (track id, normalized point) pairs.
    type Frame = (u64, Vec<(u64, Vector2<f64>)>);
    let mut normalized: Vec<Frame> = Vec::new();
    let mut dropped = 0usize;
    let mut undistort_failed = 0usize;
    let mut k = 0;
    while k < tracks.len() {
        let t_ns = tracks[k].t_ns;
        let end = k + tracks[k..].partition_point(|o| o.t_ns == t_ns);
        if t_ns <= origin || rel_s(t_ns, origin) > last_t {
            dropped += 1;
            k = end;
            continue;
        }
        let mut obs = Vec::with_capacity(end - k);
        for o in &tracks[k..end] {
            let n = match coords {
                TrackCoordinates::Normalized => Some(Vector2::new(o.xy[0], o.xy[1])),
                TrackCoordinates::Pixels => cam
                    .camera
                    .normalized_from_pixel(Vector2::new(o.xy[0], o.xy[1])),
            };
            match n {
                Some(n) => obs.push((o.id, n)),
                None => undistort_failed += 1,
            }
        }
        normalized.push((t_ns, obs));
        k = end;
    }
    let border = cam.camera.undistorted_bounds().ok_or_else(|| {
        ImportError::Missing("the camera model cannot undistort any pixel of its image".into())
    })?;
    let all_points = || normalized.iter().flat_map(|f| f.1.iter().map(|o| o.1));
    let beyond = all_points()
        .filter(|p| p.x < border[0] || p.x > border[1] || p.y < border[2] || p.y > border[3])
        .count();
    if beyond > 0 {
        notes.push(format!(
            "{beyond} observation(s) lie beyond the raw image's undistorted border (tracker \
             outliers or calibration mismatch); the virtual image was widened to hold them"
        ));
    }
    let pinhole = VirtualPinhole::covering(&cam.camera, all_points(), 1.0).ok_or_else(|| {
        ImportError::Missing("the camera model cannot undistort any pixel of its image".into())
    })?;
    let frames: Vec<ObservationFrame> = normalized
        .iter()
        .map(|(t_ns, obs)| ObservationFrame {
            time: rel_s(*t_ns, origin),
            observations: obs
                .iter()
                .map(|&(id, n)| Observation {
                    descriptor: id,
                    z: Measurement::Pixel(pinhole.pixel(n)),
                    appearance: None,
                })
                .collect(),
        })
        .collect();
    if dropped > 0 {
        notes.push(format!(
            "{dropped} frame(s) at or before the first replayed IMU sample or after the last one dropped"
        ));
    }
    if undistort_failed > 0 {
        notes.push(format!(
            "{undistort_failed} pixel observation(s) the camera model cannot undistort dropped"
        ));
    }
    let mut obs_text = format!(
        "# canopy observation log v{}: vehicle {name}, virtual undistorted pinhole (scenario.toml), imported from {}\n{OBS_HEADER}\n",
        crate::replay::FORMAT_VERSION,
        source(&tracks_path)
    );
    for f in &frames {
        frame_rows(&mut obs_text, f);
    }

    // IMU noise and the initial estimate.
    if !(args.imu_noise_scale.is_finite() && args.imu_noise_scale >= 1.0) {
        return Err(ImportError::Missing(format!(
            "--imu-noise-scale {}: must be ≥ 1 (a vehicle's IMU is no quieter than its calibration)",
            args.imu_noise_scale
        )));
    }
    // The frame interval (median of the recording's; the nominal rate if there is one frame).
    let frame_interval = {
        let mut d: Vec<f64> = frames.windows(2).map(|w| w[1].time - w[0].time).collect();
        d.sort_by(f64::total_cmp);
        d.get(d.len() / 2)
            .copied()
            .or(cam.rate_hz.map(|r| 1.0 / r))
            .unwrap_or(0.05)
    };
    // White-noise densities measured over the rest period, from the frame interval up to 1 s.
    let measured = match (rest_n, args.calibration_noise) {
        (Some(n), false) => alignment::rest_noise_density(&raw_samples[..n], frame_interval, 1.0),
        _ => None,
    };
    let (mut accel_nd, mut gyro_nd) = (
        imu_calib.accel_noise_density * args.imu_noise_scale,
        imu_calib.gyro_noise_density * args.imu_noise_scale,
    );
    let noise_source = match measured {
        Some(m) => {
            notes.push(format!(
                "IMU noise measured over the rest period (Allan variance, τ {:.3}–{:.3} s): gyro \
                 {:.3e} rad/s/√Hz, accelerometer {:.3e} m/s²/√Hz (calibration × {}: {:.3e}, {:.3e})",
                m.taus.0,
                m.taus.1,
                m.gyro_density,
                m.accel_density,
                args.imu_noise_scale,
                gyro_nd,
                accel_nd
            ));
            let s = format!(
                "white-noise densities: the larger of the calibration's × {} and those measured over \
                 the rest period (Allan variance, τ {:.3}–{:.3} s: gyro {:.4e}, accelerometer {:.4e})",
                args.imu_noise_scale, m.taus.0, m.taus.1, m.gyro_density, m.accel_density
            );
            gyro_nd = gyro_nd.max(m.gyro_density);
            accel_nd = accel_nd.max(m.accel_density);
            s
        }
        None => {
            if !args.calibration_noise {
                notes.push(
                    "no rest period to measure the IMU noise on: the calibration's densities are \
                     used (a datasheet's are for a still sensor; give figures measured on a \
                     recording of the same vehicle with --imu-calib, or --imu-noise-scale)"
                        .into(),
                );
            }
            format!(
                "white-noise densities: the calibration's × {}",
                args.imu_noise_scale
            )
        }
    };
    for (flag, v) in [
        ("--gyro-bias-walk", args.gyro_bias_walk),
        ("--accel-bias-walk", args.accel_bias_walk),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(ImportError::Missing(format!(
                "{flag} {v}: must be a finite number ≥ 0"
            )));
        }
    }
    // Bias random walks: the calibration's (a still sensor), or the in-flight figures when
    // larger.
    let (accel_rw, gyro_rw) = if args.calibration_noise {
        (imu_calib.accel_random_walk, imu_calib.gyro_random_walk)
    } else {
        (
            imu_calib.accel_random_walk.max(args.accel_bias_walk),
            imu_calib.gyro_random_walk.max(args.gyro_bias_walk),
        )
    };
    let noise = ImuNoiseConfig {
        accel_noise_density: accel_nd,
        gyro_noise_density: gyro_nd,
        accel_bias_rw_density: accel_rw,
        gyro_bias_rw_density: gyro_rw,
        accel_bias_sigma: args.accel_bias_sigma,
        gyro_bias_sigma: args.gyro_bias_sigma,
    };
    if !(args.sigma_px.is_finite() && args.sigma_px > 0.0) {
        return Err(ImportError::Missing(format!(
            "--sigma-px {}: must be a finite number > 0",
            args.sigma_px
        )));
    }
    if !(args.track_correlation_s.is_finite() && args.track_correlation_s >= 0.0) {
        return Err(ImportError::Missing(format!(
            "--track-correlation-s {}: must be a finite number ≥ 0",
            args.track_correlation_s
        )));
    }
    let walk_source = if args.calibration_noise {
        "bias random walks: the calibration's".to_string()
    } else {
        format!(
            "bias random walks: the larger of the calibration's and the in-flight figures \
             (--gyro-bias-walk {}, --accel-bias-walk {}: measured on EuRoC V1_01 against the \
             motion capture)",
            args.gyro_bias_walk, args.accel_bias_walk
        )
    };
    let sigma_px = equivalent_white_sigma(args.sigma_px, frame_interval, args.track_correlation_s);
    // One observation's own error over the equivalent white σ: the outlier tests of single
    // observations use it (`BearingConfig::marginal_sigma_ratio`).
    let marginal_ratio = (args.sigma_px / sigma_px).min(1.0);
    notes.push(format!(
        "pixel σ {} px per observation, correlated over {} s along a track: {:.3} px as independent \
         observations every {:.4} s",
        args.sigma_px, args.track_correlation_s, sigma_px, frame_interval
    ));
    let imu_rate = (imu_samples.len() as f64 / last_t).max(1e-3);
    let frame_rate = cam.rate_hz.unwrap_or_else(|| {
        if frames.len() > 1 {
            (frames.len() - 1) as f64 / (frames[frames.len() - 1].time - frames[0].time)
        } else {
            1.0
        }
    });

    // Ground truth in the navigation frame.
    let mut gt_path = None;
    let mut init_file = None;
    if let Some(gt) = &gt {
        let (p0, q0) = gt_at(gt, origin);
        let c_nw = nav_from_world(&q0, &imu_from_body);
        let mut text = format!(
            "# ground truth of {name} in canopy's navigation frame (origin and heading of the body at t = 0, NED), recording time base; from {}\n# timestamp tx ty tz qx qy qz qw\n",
            source(files.groundtruth.as_deref().unwrap_or(Path::new("")))
        );
        for g in gt {
            let p = c_nw * (g.position - p0);
            let c = c_nw * g.world_from_imu.to_rotation_matrix().matrix() * imu_from_body;
            let q = UnitQuaternion::from_matrix(&c);
            let _ = writeln!(
                text,
                "{} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
                crate::output::files::stamp(Some(g.t_ns), 0.0),
                p.x,
                p.y,
                p.z,
                q.i,
                q.j,
                q.k,
                q.w
            );
        }
        let path = args.out.join("groundtruth.tum");
        write(&path, &text)?;
        gt_path = Some(path);
        if initial == InitialChoice::Groundtruth {
            let c_nb = c_nw * q0.to_rotation_matrix().matrix() * imu_from_body;
            let v = c_nw * gt_velocity(gt, origin);
            // Biases: the ASL estimate, or the rest period's mean rate for the gyro.
            let (bg, ba) = match gt[0].biases {
                Some((bw, ba)) => (body_from_imu * bw, body_from_imu * ba),
                None => match rest_n {
                    Some(n) => (
                        body_from_imu
                            * (raw_samples[..n]
                                .iter()
                                .fold(Vector3::zeros(), |a, s| a + s.angular_rate)
                                / n as f64),
                        Vector3::zeros(),
                    ),
                    None => (Vector3::zeros(), Vector3::zeros()),
                },
            };
            let mut cov = SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::zeros();
            let (sp, sv, sy) = crate::replay::STATIC_FRAME_SIGMA;
            // Motion capture: ≈ 1 mm and a few 0.1° per pose; the velocity is differenced.
            let roll_pitch = 0.5_f64.to_radians();
            for i in 0..3 {
                cov[(POS + i, POS + i)] = sp * sp;
                cov[(VEL + i, VEL + i)] = (0.05_f64).powi(2).max(sv * sv);
                cov[(ACC_BIAS + i, ACC_BIAS + i)] = args.accel_bias_sigma.powi(2);
                cov[(GYRO_BIAS + i, GYRO_BIAS + i)] = args.gyro_bias_sigma.powi(2);
            }
            cov[(ATT, ATT)] = roll_pitch * roll_pitch;
            cov[(ATT + 1, ATT + 1)] = roll_pitch * roll_pitch;
            cov[(ATT + 2, ATT + 2)] = sy * sy;
            let e = InitialEstimate {
                time: 0.0,
                position: Vector3::zeros(),
                velocity: v,
                attitude: euler_from_nav_from_body(&c_nb),
                accel_bias: ba,
                gyro_bias: bg,
                covariance: cov,
            };
            let path = args.out.join(format!("{name}.init.csv"));
            write(&path, &initial_text(&e))?;
            init_file = Some(path);
        }
    }

    write(&args.out.join(format!("{name}.imu.csv")), &imu_text)?;
    write(&args.out.join(format!("{name}.obs.csv")), &obs_text)?;

    // The scenario.
    let sensor_from_body = sensor_from_camera() * cam.imu_from_camera.transpose() * imu_from_body;
    let lever = body_from_imu * cam.camera_in_imu;
    let scenario_name = args.scenario_name.clone().unwrap_or_else(|| {
        args.dir
            .as_ref()
            .and_then(|d| d.file_name())
            .map_or_else(|| "recording".into(), |n| n.to_string_lossy().into_owned())
    });
    let default_origin = OriginConfig::default();
    let site =
        (args.latitude.is_some() || args.longitude.is_some() || args.height.is_some()).then(|| {
            OriginConfig {
                lat_deg: args.latitude.unwrap_or(default_origin.lat_deg),
                lon_deg: args.longitude.unwrap_or(default_origin.lon_deg),
                height_m: args.height.unwrap_or(default_origin.height_m),
            }
        });
    if site.is_none() {
        notes.push(
            "no --latitude/--longitude/--height: the scenario keeps canopy's default origin \
             (its normal gravity); give the site for the right gravity"
                .into(),
        );
    }
    let num = |v: f64| format!("{v:?}");
    let row = |r: usize| {
        format!(
            "[{}, {}, {}]",
            num(sensor_from_body[(r, 0)]),
            num(sensor_from_body[(r, 1)]),
            num(sensor_from_body[(r, 2)])
        )
    };
    let mut toml = String::new();
    let _ = writeln!(
        toml,
        "# Imported by `canopy import` from {}.\n\
         # Vehicle `{name}` is replayed from {name}.imu.csv / {name}.obs.csv in its body frame b, a fixed\n\
         # rotation of the IMU axes S: C_b^S = [{}] (row-major; z_b along gravity at rest, x_b along\n\
         # the camera's optical axis made horizontal). Ground truth in canopy's navigation frame:\n\
         # groundtruth.tum (recording time base; compare with the run's {name}.est.tum).",
        args.dir
            .as_ref()
            .map_or_else(|| source(&imu_path), |d| source(d)),
        imu_from_body
            .transpose()
            .as_slice()
            .iter()
            .map(|x| format!("{x:.9}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let _ = writeln!(
        toml,
        "\n[run]\nname = {scenario_name:?}\nduration_s = {}\nrecord_interval_s = {}\nbaseline = false\n\
         # t = 0 is this instant of the recording's clock [ns]; outputs are stamped origin + t.\n\
         time_origin_ns = {origin}",
        num(last_t),
        num(args.record_interval)
    );
    let _ = writeln!(toml, "\n[world]\nearth_model = \"flat\"");
    if let Some(o) = site {
        let _ = writeln!(
            toml,
            "origin = {{ lat_deg = {}, lon_deg = {}, height_m = {} }}",
            num(o.lat_deg),
            num(o.lon_deg),
            num(o.height_m)
        );
    }
    if let Some(g) = args.gravity {
        let _ = writeln!(toml, "gravity_mps2 = {}", num(g));
    }
    let _ = writeln!(toml, "\n[fusion]\nmode = \"isolated\"");
    let _ = writeln!(
        toml,
        "\n[[vehicle]]\nid = 1\nname = {name:?}\n\n[vehicle.sensor]\nrate_hz = {}\n\
         # C_b^s: body → sensor frame (x along the optical axis, y right, z down in the image).\n\
         sensor_from_body = [{}, {}, {}]\n\
         # Camera origin from the body (IMU) origin, body axes [m].\n\
         lever_arm_m = [{}, {}, {}]\n\
         # A virtual undistorted pinhole (the calibration's focal lengths; image holding every\n\
         # undistorted pixel of the raw image and every observation).\n\
         model = {{ kind = \"pixel\", fu_px = {}, fv_px = {}, u0_px = {}, v0_px = {}, width_px = {}, height_px = {}, sigma_px = {} }}",
        num(frame_rate),
        row(0),
        row(1),
        row(2),
        num(lever.x),
        num(lever.y),
        num(lever.z),
        num(pinhole.focal[0]),
        num(pinhole.focal[1]),
        num(pinhole.principal[0]),
        num(pinhole.principal[1]),
        num(pinhole.size[0]),
        num(pinhole.size[1]),
        num(sigma_px)
    );
    let _ = writeln!(
        toml,
        "# sigma_px: {} px per observation, its error correlated over {} s along a track (--sigma-px,\n\
         # --track-correlation-s), as independent observations every {} s: σ·√((1+ρ)/(1−ρ)), ρ = exp(−Δ/τ).",
        num(args.sigma_px),
        num(args.track_correlation_s),
        num(frame_interval)
    );
    let _ = writeln!(
        toml,
        "\n[vehicle.imu]\nrate_hz = {}\n# {}\nnoise = {{ accel_noise_density = {}, gyro_noise_density = {}, accel_bias_rw_density = {}, gyro_bias_rw_density = {}, accel_bias_sigma = {}, gyro_bias_sigma = {} }}",
        num(imu_rate),
        match &files.imu_calib {
            Some(p) => format!(
                "noise figures from {}; {noise_source}; {walk_source}",
                source(p)
            ),
            None => format!(
                "noise figures of the ADIS16448 (EuRoC's IMU; no IMU calibration given); {noise_source}; {walk_source}"
            ),
        },
        num(noise.accel_noise_density),
        num(noise.gyro_noise_density),
        num(noise.accel_bias_rw_density),
        num(noise.gyro_bias_rw_density),
        num(noise.accel_bias_sigma),
        num(noise.gyro_bias_sigma)
    );
    let _ = writeln!(
        toml,
        "\n[vehicle.replay]\nimu = \"{name}.imu.csv\"\nobservations = \"{name}.obs.csv\""
    );
    match (&init_file, rest_s) {
        (Some(_), _) => {
            let _ = writeln!(
                toml,
                "initial = \"{name}.init.csv\"  # the first ground-truth pose"
            );
        }
        (None, Some(r)) => {
            let _ = writeln!(
                toml,
                "initial = \"static\"  # alignment over the rest period\nrest_s = {}",
                num(r)
            );
        }
        (None, None) => {
            let _ = writeln!(toml, "initial = \"static\"");
        }
    }
    if gt_path.is_some() {
        let _ = writeln!(
            toml,
            "# Position error, pose NEES and ATE in the run's outputs against it.\ngroundtruth = \"groundtruth.tum\""
        );
    }
    // Zero-velocity updates over the rest period (in run time: the origin may be later than
    // the first raw sample when the ground truth starts later).
    let rest_until = rest_s.map(|r| r - rel_s(origin, t0));
    match rest_until {
        Some(u) if u > RestDetection::default().window_s && !args.no_zero_velocity => {
            let _ = writeln!(
                toml,
                "# At rest until {} s (detected, or --rest): zero-velocity updates meanwhile.\n\
                 zero_velocity = {{ until_s = {} }}",
                num(u),
                num(u)
            );
        }
        _ => {}
    }
    let _ = writeln!(
        toml,
        "\n[vehicle.bearing]\n\
         # Every stored ray of a track at once (tracker ids are the descriptors), after {}° of\n\
         # parallax; features between {} and {} m.\n\
         initialization = \"multi_view\"\nmin_parallax_deg = {}\nmin_range_m = {}\nmax_range_m = {}\n\
         # One observation's own error σ over the sensor's equivalent white σ (above): single\n\
         # observations are tested for gross outliers (a track that jumped or drifted) against it.\n\
         marginal_sigma_ratio = {}",
        num(args.min_parallax),
        num(args.min_depth),
        num(args.max_depth),
        num(args.min_parallax),
        num(args.min_depth),
        num(args.max_depth),
        num(marginal_ratio)
    );
    let scenario_path = args.out.join("scenario.toml");
    // The scenario must load as written (it is parsed exactly as `canopy check` will).
    Scenario::from_toml_str(&toml).map_err(|e| {
        ImportError::Missing(format!(
            "the scenario the import made does not validate: {e}"
        ))
    })?;
    write(&scenario_path, &toml)?;

    Ok(ImportSummary {
        scenario: scenario_path,
        groundtruth: gt_path,
        imu_samples: imu_samples.len(),
        frames: frames.len(),
        observations: frames.iter().map(|f| f.observations.len()).sum(),
        frames_dropped: dropped,
        time_origin_ns: origin,
        imu_from_body,
        rest_s,
        initial,
        pinhole,
        notes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_body_frame_is_level_and_looks_along_the_camera() {
        // EuRoC-like: IMU x up (down = −x_S), camera optical axis ≈ −y_S … any tilt.
        let down = Vector3::new(-0.93, -0.01, 0.37).normalize();
        let imu_from_camera = Matrix3::new(
            0.0148655, -0.9998809, 0.0041403, 0.9995572, 0.0149672, 0.0257155, -0.0257744,
            0.0037562, 0.9996607,
        );
        let c = body_frame(&down, &imu_from_camera);
        // Orthonormal, proper.
        assert!((c.transpose() * c - Matrix3::identity()).abs().max() < 1e-12);
        assert!((c.determinant() - 1.0).abs() < 1e-12);
        // z_b is down; x_b is horizontal and within 90° of the optical axis.
        assert!((c.column(2) - down).norm() < 1e-12);
        assert!(c.column(0).dot(&down).abs() < 1e-12);
        assert!(c.column(0).dot(&imu_from_camera.column(2)) > 0.0);
    }

    #[test]
    fn the_sensor_frame_follows_eq_21_43() {
        // A point 2 m ahead of the camera, 0.5 m right, 0.25 m down (camera frame).
        let p_c = Vector3::new(0.5, 0.25, 2.0);
        let p_s = sensor_from_camera() * p_c;
        // u − u0 = f·y^s/x^s must equal f·X_c/Z_c, and v likewise.
        assert!((p_s.y / p_s.x - p_c.x / p_c.z).abs() < 1e-15);
        assert!((p_s.z / p_s.x - p_c.y / p_c.z).abs() < 1e-15);
        assert!((sensor_from_camera().determinant() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn equivalent_white_sigma_matches_the_variance_of_a_long_correlated_mean() {
        // Exact variance of the mean of n samples of a first-order Gauss–Markov sequence:
        // σ²/n²·(n + 2 Σ_{k=1}^{n−1} (n − k) ρ^k), against n independent samples of σ'.
        let (sigma, interval, tau): (f64, f64, f64) = (1.0, 0.05, 0.33);
        let rho: f64 = (-interval / tau).exp();
        let n = 20_000usize;
        let sum: f64 = (1..n).map(|k| (n - k) as f64 * rho.powi(k as i32)).sum();
        let exact = sigma * sigma * (n as f64 + 2.0 * sum) / (n * n) as f64;
        let white = equivalent_white_sigma(sigma, interval, tau).powi(2) / n as f64;
        // The finite-n correction is O(1/(n(1−ρ))) ≈ 4e-4 relative here.
        assert!((white / exact - 1.0).abs() < 1e-3, "{white} vs {exact}");
        // 20 Hz and 10 Hz frames of the EuRoC tracks (closed form); independent frames.
        let at = |dt| equivalent_white_sigma(1.0, dt, 0.33);
        assert!((at(0.05) - 3.6367).abs() < 1e-3 && (at(0.1) - 2.5788).abs() < 1e-3);
        assert_eq!(equivalent_white_sigma(1.5, 0.05, 0.0), 1.5);
    }
}
