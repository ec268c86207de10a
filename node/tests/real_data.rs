//! The real-data path on the EuRoC MAV V1_01_easy recording (first 30 s, `shared/data`, never
//! committed): `canopy import` into a replay scenario, then `canopy check`, `canopy sim` and
//! `canopy run` on it. What is asserted is the import's correctness against independent data
//! (the motion-capture ground truth, the recording's own timestamps), not the estimation
//! accuracy (the filter's business).
//!
//! Where the data is: `$CANOPY_EUROC_DIR`, else `../shared/data/euroc-v1_01-30s` relative to
//! the repository root. Without it these tests FAIL, naming both; set
//! `CANOPY_SKIP_REAL_DATA=1` to opt out explicitly (README, "Real data").
//!
//! Every child process runs under a deadline ([`run_bounded`]): a hang is a failure, not a
//! stuck CI.

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Duration;

mod common;
use common::run_bounded;

use canopy_fusion::rotation::nav_from_body;
use canopy_node::replay::ReplayLog;
use canopy_node::scenario::Scenario;
use nalgebra::{Matrix3, UnitQuaternion, Vector2, Vector3, Vector4};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("node/ is inside the workspace")
        .to_path_buf()
}

/// The recording, or `None` when the user opted out; panics loudly when it is missing.
fn euroc_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("CANOPY_EUROC_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("../shared/data/euroc-v1_01-30s"));
    if dir.join("imu.csv").is_file() {
        return Some(dir);
    }
    if std::env::var_os("CANOPY_SKIP_REAL_DATA").is_some_and(|v| v == "1") {
        eprintln!(
            "real-data test opted out (CANOPY_SKIP_REAL_DATA=1); the data was not at {}",
            dir.display()
        );
        return None;
    }
    panic!(
        "the EuRoC recording is not at {} (no imu.csv): point CANOPY_EUROC_DIR at your copy \
         (README, \"Real data\"), or set CANOPY_SKIP_REAL_DATA=1 to opt out of this test",
        dir.display()
    );
}

/// Imports the recording into `out`.
fn import(dir: &Path, out: &Path) {
    let (ok, stdout, stderr) = run_bounded(
        &[
            "import",
            dir.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            // ETH Zurich (approximate site: the normal gravity there).
            "--latitude",
            "47.376",
            "--longitude",
            "8.548",
            "--height",
            "500",
        ],
        Duration::from_secs(120),
    );
    assert!(ok, "canopy import failed:\n{stdout}{stderr}");
    println!("{stdout}");
}

/// The recording's IMU timestamps [ns], read here independently of the importer.
fn recording_imu_times(dir: &Path) -> Vec<u64> {
    std::fs::read_to_string(dir.join("imu.csv"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect()
}

/// A TUM file: (timestamp text, position, C_b^n).
fn tum(path: &Path) -> Vec<(String, Vector3<f64>, Matrix3<f64>)> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let v: Vec<f64> = f[1..].iter().map(|x| x.parse().unwrap()).collect();
            let q =
                UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[6], v[3], v[4], v[5]));
            (
                f[0].to_string(),
                Vector3::new(v[0], v[1], v[2]),
                q.to_rotation_matrix().into_inner(),
            )
        })
        .collect()
}

/// "sec.nnnnnnnnn" → ns.
fn ns(stamp: &str) -> u64 {
    let (s, f) = stamp.split_once('.').unwrap();
    assert_eq!(f.len(), 9, "{stamp}: nine decimals");
    s.parse::<u64>().unwrap() * 1_000_000_000 + f.parse::<u64>().unwrap()
}

/// The import: timestamps round-trip exactly, the body frame is level at rest (and agrees with
/// the motion capture), the rotated gyro agrees with the ground truth's rotation, and the camera
/// mount reprojects triangulated tracks consistently with the ground-truth poses (and a mount
/// off by 3° does not).
#[test]
fn euroc_import_is_consistent_with_the_recording_and_its_ground_truth() {
    let Some(dir) = euroc_dir() else { return };
    let out = tempfile::tempdir().unwrap();
    import(&dir, out.path());
    let s = Scenario::load(&out.path().join("scenario.toml")).unwrap();
    let v = &s.vehicles[0];
    let log = ReplayLog::load(v.replay.as_ref().unwrap(), v, &s.world).unwrap();
    let origin = s
        .run
        .time_origin_ns
        .expect("an imported scenario keeps the time origin");

    // Timestamps: origin + t rounds back to every recording timestamp, exactly.
    let rec = recording_imu_times(&dir);
    assert_eq!(origin, rec[0]);
    assert_eq!(log.imu.len(), rec.len() - 1);
    for (s, &t) in log.imu.iter().zip(&rec[1..]) {
        let back = (origin as i128 + (s.time * 1e9).round() as i128) as u64;
        assert_eq!(back, t);
    }
    let track_times: HashSet<u64> = std::fs::read_to_string(dir.join("tracks.csv"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split(',').next().unwrap().parse().unwrap())
        .collect();
    for f in &log.frames {
        let back = (origin as i128 + (f.time * 1e9).round() as i128) as u64;
        assert!(
            track_times.contains(&back),
            "frame at {back} ns is not a track time"
        );
    }
    // 601 track times; the one at t = 0 (the initial estimate's time) is dropped.
    assert_eq!(log.frames.len(), track_times.len() - 1);

    // Level at rest: the mean specific force over the rest period points up the body z axis.
    let rest = v
        .replay
        .as_ref()
        .unwrap()
        .rest_s
        .expect("a rest period was found");
    assert!((4.0..5.5).contains(&rest), "rest {rest} s (README: ~5 s)");
    let at_rest: Vec<_> = log.imu.iter().filter(|s| s.time <= rest).collect();
    let mean = at_rest
        .iter()
        .fold(Vector3::zeros(), |a, s| a + s.specific_force)
        / at_rest.len() as f64;
    // By construction of the body frame; 1e-9 of |f| leaves room for the f64 rotation only.
    assert!(
        mean.x.abs() < 1e-9 * mean.norm() && mean.y.abs() < 1e-9 * mean.norm(),
        "{mean}"
    );
    assert!(mean.z < -9.0, "{mean}");
    // Independently: the motion capture's attitude at t = 0 (its own vertical) agrees with the
    // levelled IMU within 1.5° (Vicon frame vs gravity, IMU-marker calibration: ≲ 1°).
    let gt = tum(&out.path().join("groundtruth.tum"));
    let (_, p0, c0) = &gt[0];
    assert!(
        p0.norm() < 1e-3,
        "the navigation frame starts at the body: {p0}"
    );
    let tilt = (c0 * Vector3::z()).angle(&Vector3::z()).to_degrees();
    println!("ground truth tilt of the levelled body at t = 0: {tilt:.3}°");
    assert!(tilt < 1.5, "tilt {tilt}°");
    let heading = (c0 * Vector3::x())
        .y
        .atan2((c0 * Vector3::x()).x)
        .to_degrees();
    assert!(
        heading.abs() < 1e-3,
        "yaw at t = 0 defines the frame: {heading}°"
    );

    // The rotated gyro against the ground truth's rotation: ω^b = log(C(t_k)ᵀ C(t_{k+1}))/Δt,
    // against the mean body rate over the same 50 ms, less the aligned gyro bias.
    let bias = log.alignment.as_ref().unwrap().gyro_bias;
    let gt_ns: Vec<u64> = gt.iter().map(|g| ns(&g.0)).collect();
    let mut err2 = 0.0;
    let mut sig2 = 0.0;
    let mut n = 0.0;
    for k in 0..gt.len() - 1 {
        let (ta, tb) = (gt_ns[k], gt_ns[k + 1]);
        if ta < origin + 6_000_000_000 {
            continue; // flight only
        }
        let rel = gt[k].2.transpose() * gt[k + 1].2;
        let w_gt = nalgebra::Rotation3::from_matrix_unchecked(rel).scaled_axis()
            / ((tb - ta) as f64 * 1e-9);
        let w: Vec<_> = log
            .imu
            .iter()
            .filter(|s| {
                let t = origin as f64 + s.time * 1e9;
                t > ta as f64 && t <= tb as f64
            })
            .map(|s| s.angular_rate - bias)
            .collect();
        if w.is_empty() {
            continue;
        }
        let w_imu = w.iter().fold(Vector3::zeros(), |a, x| a + x) / w.len() as f64;
        err2 += (w_imu - w_gt).norm_squared();
        sig2 += w_gt.norm_squared();
        n += 1.0;
    }
    let (rms_err, rms_sig) = ((err2 / n).sqrt(), (sig2 / n).sqrt());
    println!(
        "body rate: ground truth RMS {rms_sig:.4} rad/s, IMU − ground truth RMS {rms_err:.4} rad/s over {n} intervals"
    );
    // A wrong axis assignment leaves an error of the order of the signal; the bias drift,
    // vibration and 10 µs ground-truth timestamps leave a fraction of it.
    assert!(rms_err < 0.3 * rms_sig, "{rms_err} vs {rms_sig}");

    // Camera mount: triangulate long tracks from the ground-truth poses, reproject.
    let mount = v.sensor.mount();
    let model = v.sensor.model();
    let median = median_reprojection_px(
        &log,
        &gt,
        &gt_ns,
        origin,
        mount.sensor_from_body,
        mount.lever_arm_body,
        &model,
    );
    let off = mount.sensor_from_body * nav_from_body(&Vector3::new(0.0, 3f64.to_radians(), 0.0));
    let median_off =
        median_reprojection_px(&log, &gt, &gt_ns, origin, off, mount.lever_arm_body, &model);
    println!(
        "median reprojection error of triangulated tracks: {median:.3} px (mount tilted 3°: {median_off:.3} px)"
    );
    assert!(median < 2.0, "{median} px");
    assert!(median_off > 2.0 * median, "{median_off} px vs {median} px");
}

/// One sighting of a track: sensor origin (navigation frame), C_n^s, pixel.
type Sighting = (Vector3<f64>, Matrix3<f64>, Vector2<f64>);

/// Median over long tracks of the median reprojection error [px]: each track triangulated
/// (linear least squares on the bearing constraints) from the ground-truth body poses through
/// the given mount, then reprojected through the pinhole of eq. 21.43.
fn median_reprojection_px(
    log: &ReplayLog,
    gt: &[(String, Vector3<f64>, Matrix3<f64>)],
    gt_ns: &[u64],
    origin: u64,
    sensor_from_body: Matrix3<f64>,
    lever: Vector3<f64>,
    model: &canopy_fusion::sensor::SensorModel,
) -> f64 {
    let canopy_fusion::sensor::SensorModel::Pixel { camera, .. } = model else {
        panic!("pixel model expected")
    };
    let pose = |t: f64| -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let t_ns = origin as f64 + t * 1e9;
        let k = gt_ns.partition_point(|&g| (g as f64) <= t_ns);
        if k == 0 || k >= gt.len() {
            return None;
        }
        let s = (t_ns - gt_ns[k - 1] as f64) / (gt_ns[k] - gt_ns[k - 1]) as f64;
        let p = gt[k - 1].1 + (gt[k].1 - gt[k - 1].1) * s;
        let qa = UnitQuaternion::from_matrix(&gt[k - 1].2);
        let qb = UnitQuaternion::from_matrix(&gt[k].2);
        Some((p, qa.slerp(&qb, s).to_rotation_matrix().into_inner()))
    };
    // Observations per track: (sensor origin, C_n^s, pixel).
    let mut tracks: BTreeMap<u64, Vec<Sighting>> = BTreeMap::new();
    for f in &log.frames {
        let Some((p, c_nb)) = pose(f.time) else {
            continue;
        };
        for o in &f.observations {
            let canopy_fusion::sensor::Measurement::Pixel(z) = o.z else {
                continue;
            };
            let sensor_from_nav = sensor_from_body * c_nb.transpose();
            tracks
                .entry(o.descriptor)
                .or_default()
                .push((p + c_nb * lever, sensor_from_nav, z));
        }
    }
    let mut medians = Vec::new();
    for obs in tracks.values().filter(|o| o.len() >= 10) {
        // Baseline ≥ 0.3 m for a well-conditioned triangulation.
        if (obs[0].0 - obs[obs.len() - 1].0).norm() < 0.3 {
            continue;
        }
        // Each pixel: y^s·(u−u0)/fu … as two linear constraints on the point m^n:
        // ((u−u0)/fu)·x^s − y^s = 0, ((v−v0)/fv)·x^s − z^s = 0, x^s = C (m − o).
        let mut a = nalgebra::DMatrix::zeros(2 * obs.len(), 4);
        for (i, (o, c, z)) in obs.iter().enumerate() {
            let a_n = (z.x - camera.u0) / camera.fu;
            let b_n = (z.y - camera.v0) / camera.fv;
            let r1 = c.row(1) - c.row(0) * a_n;
            let r2 = c.row(2) - c.row(0) * b_n;
            for (k, r) in [(2 * i, r1), (2 * i + 1, r2)] {
                let d = -(r * o)[0];
                a.set_row(
                    k,
                    &nalgebra::RowDVector::from_row_slice(&[r[0], r[1], r[2], d]),
                );
            }
        }
        let svd = a.svd(false, true);
        let Some(vt) = svd.v_t else { continue };
        let h: Vector4<f64> = vt.row(3).transpose().fixed_rows::<4>(0).into();
        if h[3].abs() < 1e-12 {
            continue;
        }
        let m = h.fixed_rows::<3>(0) / h[3];
        let mut errs: Vec<f64> = obs
            .iter()
            .filter_map(|(o, c, z)| {
                let x = c * (m - o);
                (x.x > 0.1).then(|| {
                    let u = camera.fu * x.y / x.x + camera.u0;
                    let v = camera.fv * x.z / x.x + camera.v0;
                    ((u - z.x).powi(2) + (v - z.y).powi(2)).sqrt()
                })
            })
            .collect();
        if errs.len() < obs.len() / 2 {
            continue;
        }
        errs.sort_by(f64::total_cmp);
        medians.push(errs[errs.len() / 2]);
    }
    assert!(medians.len() >= 20, "only {} long tracks", medians.len());
    medians.sort_by(f64::total_cmp);
    medians[medians.len() / 2]
}

/// check, sim and run on the imported scenario, each bounded in time: the outputs exist, their
/// timestamps are recording timestamps, `sim` and `run` replay the same estimate, and rejections
/// are counted by reason.
#[test]
fn euroc_replays_in_check_sim_and_run() {
    let Some(dir) = euroc_dir() else { return };
    let out = tempfile::tempdir().unwrap();
    import(&dir, out.path());
    let scenario = out.path().join("scenario.toml");
    let scenario = scenario.to_str().unwrap();
    let (ok, stdout, stderr) = run_bounded(&["check", scenario], Duration::from_secs(60));
    assert!(ok, "{stdout}{stderr}");
    assert!(stdout.contains("static alignment"), "{stdout}");
    let sim_dir = out.path().join("sim");
    let run_dir = out.path().join("run");
    let (ok, stdout, stderr) = run_bounded(
        &[
            "sim",
            scenario,
            "--out",
            sim_dir.to_str().unwrap(),
            "--quiet",
        ],
        Duration::from_secs(300),
    );
    assert!(ok, "canopy sim: {stdout}{stderr}");
    let (ok, stdout, stderr) = run_bounded(
        &[
            "run",
            scenario,
            "--out",
            run_dir.to_str().unwrap(),
            "--quiet",
        ],
        Duration::from_secs(300),
    );
    assert!(ok, "canopy run: {stdout}{stderr}");
    let rec: HashSet<u64> = recording_imu_times(&dir).into_iter().collect();
    for d in [&sim_dir, &run_dir] {
        let est = tum(&d.join("mav.est.tum"));
        // One estimate per record interval (0.1 s) over 30 s.
        assert!(est.len() >= 290, "{}: {} poses", d.display(), est.len());
        for (stamp, ..) in &est {
            assert!(
                rec.contains(&ns(stamp)),
                "{stamp} is not a recording timestamp"
            );
        }
        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d.join("summary.json")).unwrap())
                .unwrap();
        let v = &summary["vehicles"][0];
        // The estimate against the motion capture (the scenario names the imported ground
        // truth): ATE after SE(3) alignment within the 0.10 m that good open-source
        // visual-inertial estimators reach on V1_01 (measured 0.027 m; the replay is
        // deterministic, so any figure above it is a regression, not noise). The pose ANEES
        // against this ground truth is reported (measured 16.7: see docs/benchmarks.md).
        let ate = v["ate"]["se3_m"]
            .as_f64()
            .expect("an ATE against the ground truth");
        let ate4 = v["ate"]["posyaw_m"].as_f64().expect("a 4-DOF ATE");
        let anees = v["pose_anees"]
            .as_f64()
            .expect("a pose ANEES against the ground truth");
        println!(
            "{}: ATE SE(3) {ate:.3} m, 4-DOF {ate4:.3} m, pose ANEES {anees:.2}, position RMSE {} m",
            d.display(),
            v["position_rmse_m"]
        );
        assert!(ate <= 0.10 && ate4 <= 0.10, "ATE {ate} m / {ate4} m");
        assert!(anees.is_finite());
        // Every observation the import wrote (600 frames, 13304 observations) was processed.
        assert_eq!(v["observations"], 13304, "{}", d.display());
        let rejections = v["rejections"].as_object().expect("rejections by reason");
        println!("{}: rejections {rejections:?}", d.display());
        for (k, n) in rejections {
            assert!(
                k.contains('.') && n.as_u64().is_some_and(|n| n > 0),
                "{k}: {n}"
            );
        }
        assert!(
            std::fs::read_to_string(d.join("report.html"))
                .unwrap()
                .contains("canopy")
        );
    }
    let checks: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run_dir.join("checks.json")).unwrap())
            .unwrap();
    assert!(checks["failure"].is_null(), "{}", checks["failure"]);
    assert_eq!(
        checks["vehicles"][0]["rejections"],
        serde_json::from_str::<serde_json::Value>(
            &std::fs::read_to_string(run_dir.join("summary.json")).unwrap()
        )
        .unwrap()["vehicles"][0]["rejections"]
    );
    // Deterministic replay: the same estimate from one process and from many.
    assert_eq!(
        std::fs::read_to_string(sim_dir.join("mav.est.tum")).unwrap(),
        std::fs::read_to_string(run_dir.join("mav.est.tum")).unwrap()
    );
}
