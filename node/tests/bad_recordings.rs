//! Recordings as users bring them, good and bad, without any research data: a small synthetic
//! recording in the EuRoC flat layout (imu.csv with jittered timestamps, cam0.yaml, tracks.csv,
//! groundtruth.tum) is written here, imported and run; then broken copies of it — truncated
//! file, timestamps going backwards, NaN, missing calibration, a track id that is not an
//! integer, an empty file, unknown columns — must each fail with the file, the line and the
//! reason, through `canopy import`, and broken replay logs through `canopy check` and
//! `canopy run`. Every process runs under a deadline: none may hang.

use std::path::Path;
use std::time::Duration;

mod common;
use common::run_bounded;

const T0: u64 = 1_403_715_273_262_143_232;

/// Jitter of sample k [ns]: −120 ns on every fourth sample (so the sample at 0.1 s lies just
/// before the world's 0.1 s batch boundary, the case that stalled `canopy run`), 0 otherwise.
fn jitter(k: u64) -> i64 {
    if k > 0 && k.is_multiple_of(4) {
        -120
    } else {
        0
    }
}

/// Writes the synthetic recording: 3 s at rest (IMU x up, as on the EuRoC MAV), 200 Hz IMU
/// with jittered timestamps, a camera looking along the IMU's −y axis at five static points,
/// 20 Hz frames on IMU sample times and one between them, a static ground truth.
fn write_recording(dir: &Path) {
    let mut imu = String::from(
        "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n",
    );
    let times: Vec<u64> = (0..=600u64)
        .map(|k| (T0 as i64 + k as i64 * 5_000_000 + jitter(k)) as u64)
        .collect();
    for (k, t) in times.iter().enumerate() {
        // Deterministic sensor noise: small sines.
        let n = (k as f64 * 0.7).sin();
        imu.push_str(&format!(
            "{t},{},{},{},{},{},{}\n",
            0.001 * n,
            0.02 + 0.001 * n,
            0.003,
            9.81 + 0.01 * n,
            0.01 * n,
            -0.02
        ));
    }
    std::fs::write(dir.join("imu.csv"), imu).unwrap();
    std::fs::write(
        dir.join("cam0.yaml"),
        "T_BS:\n  cols: 4\n  rows: 4\n  data: [0.0, 0.0, 1.0, 0.05, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]\n\
         rate_hz: 20\nresolution: [752, 480]\ncamera_model: pinhole\nintrinsics: [458.654, 457.296, 367.215, 248.375]\n\
         distortion_model: radial-tangential\ndistortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]\n",
    )
    .unwrap();
    let mut tracks = String::from("#timestamp [ns],track_id,x_n,y_n\n");
    for k in (10..=600).step_by(10) {
        for id in 1..=5 {
            tracks.push_str(&format!(
                "{},{id},{},{}\n",
                times[k],
                0.1 * f64::from(id) - 0.3,
                0.05 * f64::from(id) - 0.15
            ));
        }
    }
    // One frame between two IMU samples (2.5 ms after sample 300).
    tracks.push_str(&format!("{},9,0.0,0.0\n", times[300] + 2_500_000));
    // Tracks must be in time order: sort the rows by timestamp (stable).
    let mut rows: Vec<&str> = tracks.lines().skip(1).collect();
    rows.sort_by_key(|l| l.split(',').next().unwrap().parse::<u64>().unwrap());
    let tracks = format!("#timestamp [ns],track_id,x_n,y_n\n{}\n", rows.join("\n"));
    std::fs::write(dir.join("tracks.csv"), tracks).unwrap();
    let mut gt = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for k in (0..=600).step_by(10) {
        // IMU x up: the IMU frame rotated −90° about world y (x_S = z_W).
        let t = times[k];
        gt.push_str(&format!(
            "{}.{:09} 1.0 2.0 1.5 0.0 -0.7071067811865476 0.0 0.7071067811865476\n",
            t / 1_000_000_000,
            t % 1_000_000_000
        ));
    }
    std::fs::write(dir.join("groundtruth.tum"), gt).unwrap();
}

fn import(rec: &Path, out: &Path) -> (bool, String, String) {
    run_bounded(
        &[
            "import",
            rec.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--latitude",
            "47.376",
        ],
        Duration::from_secs(60),
    )
}

/// The synthetic recording with jittered timestamps and a frame between IMU samples imports,
/// checks, and runs to the end in `canopy sim` and `canopy run` (the world used to stall on
/// such timestamps), with outputs stamped with the recording's own timestamps.
#[test]
fn a_jittered_recording_imports_checks_and_runs() {
    let rec = tempfile::tempdir().unwrap();
    write_recording(rec.path());
    let out = tempfile::tempdir().unwrap();
    let (ok, stdout, stderr) = import(rec.path(), out.path());
    assert!(ok, "{stdout}{stderr}");
    assert!(
        stdout.contains("Static"),
        "at rest from the start: {stdout}"
    );
    let scenario = out.path().join("scenario.toml");
    let scenario = scenario.to_str().unwrap();
    let (ok, stdout, stderr) = run_bounded(&["check", scenario], Duration::from_secs(60));
    assert!(ok, "{stdout}{stderr}");
    // The frame between two samples splits one of them.
    assert!(stdout.contains("1 samples split"), "{stdout}");
    for cmd in ["sim", "run"] {
        let dir = out.path().join(cmd);
        let (ok, stdout, stderr) = run_bounded(
            &[cmd, scenario, "--out", dir.to_str().unwrap(), "--quiet"],
            Duration::from_secs(120),
        );
        assert!(ok, "canopy {cmd}: {stdout}{stderr}");
        let est = std::fs::read_to_string(dir.join("mav.est.tum")).unwrap();
        let stamps: Vec<&str> = est
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split(' ').next().unwrap())
            .collect();
        // 3 s at one estimate per 0.1 s, plus t = 0.
        assert!(stamps.len() >= 30, "{cmd}: {} poses", stamps.len());
        assert_eq!(
            stamps[0], "1403715273.262143232",
            "t = 0 is the first IMU timestamp"
        );
        let summary = std::fs::read_to_string(dir.join("summary.json")).unwrap();
        assert!(summary.contains("\"rejections\""), "{summary}");
    }
}

/// Each kind of bad recording fails `canopy import` with the file, the line and the reason.
#[test]
fn bad_recordings_fail_import_with_file_line_and_reason() {
    type Edit = fn(&Path);
    let cases: Vec<(&str, Edit, &str, &str)> = vec![
        (
            "truncated file",
            |d| {
                let t = std::fs::read_to_string(d.join("imu.csv")).unwrap();
                std::fs::write(d.join("imu.csv"), &t[..t.len() - 30]).unwrap();
            },
            "imu.csv:602:",
            "truncated",
        ),
        (
            "timestamps going backwards",
            |d| {
                let t = std::fs::read_to_string(d.join("imu.csv")).unwrap();
                let mut lines: Vec<String> = t.lines().map(str::to_string).collect();
                lines.swap(100, 101);
                std::fs::write(d.join("imu.csv"), lines.join("\n")).unwrap();
            },
            "imu.csv:102:",
            "timestamps must increase",
        ),
        (
            "NaN",
            |d| {
                let t = std::fs::read_to_string(d.join("imu.csv")).unwrap();
                let mut lines: Vec<String> = t.lines().map(str::to_string).collect();
                let f: Vec<&str> = lines[50].split(',').collect();
                lines[50] = format!("{},NaN,{}", f[0], f[2..].join(","));
                std::fs::write(d.join("imu.csv"), lines.join("\n")).unwrap();
            },
            "imu.csv:51:",
            "`w_RS_S_x` = `NaN` is not finite",
        ),
        (
            "missing calibration",
            |d| std::fs::remove_file(d.join("cam0.yaml")).unwrap(),
            "missing calibration",
            "--camera",
        ),
        (
            "a calibration without intrinsics",
            |d| {
                let t = std::fs::read_to_string(d.join("cam0.yaml")).unwrap();
                let t: String = t
                    .lines()
                    .filter(|l| !l.starts_with("intrinsics"))
                    .map(|l| format!("{l}\n"))
                    .collect();
                std::fs::write(d.join("cam0.yaml"), t).unwrap();
            },
            "cam0.yaml:1:",
            "missing calibration field `intrinsics`",
        ),
        (
            "a track id that is not an integer",
            |d| {
                let t = std::fs::read_to_string(d.join("tracks.csv")).unwrap();
                let t = t.replacen(",3,", ",3.5,", 1);
                std::fs::write(d.join("tracks.csv"), t).unwrap();
            },
            "tracks.csv:4:",
            "track id `3.5` is not a non-negative integer",
        ),
        (
            "an empty file",
            |d| std::fs::write(d.join("tracks.csv"), "").unwrap(),
            "tracks.csv:1:",
            "empty file",
        ),
        (
            "unknown columns",
            |d| {
                let t = std::fs::read_to_string(d.join("tracks.csv")).unwrap();
                let t = t.replacen("x_n,y_n", "px,py", 1);
                std::fs::write(d.join("tracks.csv"), t).unwrap();
            },
            "tracks.csv:1:",
            "unknown columns",
        ),
        (
            "ground truth going backwards",
            |d| {
                let t = std::fs::read_to_string(d.join("groundtruth.tum")).unwrap();
                let mut lines: Vec<String> = t.lines().map(str::to_string).collect();
                lines.swap(5, 6);
                std::fs::write(d.join("groundtruth.tum"), lines.join("\n")).unwrap();
            },
            "groundtruth.tum:7:",
            "timestamps must increase",
        ),
    ];
    for (name, edit, location, reason) in cases {
        let rec = tempfile::tempdir().unwrap();
        write_recording(rec.path());
        edit(rec.path());
        let out = tempfile::tempdir().unwrap();
        let (ok, stdout, stderr) = import(rec.path(), out.path());
        assert!(!ok, "{name}: the import succeeded:\n{stdout}");
        assert!(
            stderr.contains(location),
            "{name}: no `{location}` in:\n{stderr}"
        );
        assert!(
            stderr.contains(reason),
            "{name}: no `{reason}` in:\n{stderr}"
        );
        if location.contains(':') {
            let file = location.split(':').next().unwrap();
            assert!(
                stderr.contains(&rec.path().join(file).display().to_string()),
                "{name}: the file's path is not named:\n{stderr}"
            );
        }
    }
}

/// Broken replay logs: `canopy check` and `canopy run` fail alike, naming the file, line and
/// reason, before any process starts, and quickly.
#[test]
fn bad_replay_logs_fail_check_and_run_with_file_line_and_reason() {
    let rec = tempfile::tempdir().unwrap();
    write_recording(rec.path());
    let good = tempfile::tempdir().unwrap();
    let (ok, stdout, stderr) = import(rec.path(), good.path());
    assert!(ok, "{stdout}{stderr}");
    type Edit = fn(&Path);
    let cases: Vec<(&str, &str, Edit, &str)> = vec![
        (
            "NaN",
            "mav.imu.csv",
            |p| {
                edit_line(p, 10, |l| {
                    let mut f: Vec<&str> = l.split(',').collect();
                    f[2] = "NaN";
                    f.join(",")
                })
            },
            "not finite",
        ),
        (
            "timestamps going backwards",
            "mav.imu.csv",
            |p| {
                edit_line(p, 22, |l| {
                    let mut f: Vec<&str> = l.split(',').collect();
                    f[0] = "0.001";
                    f.join(",")
                })
            },
            "times must increase",
        ),
        (
            "truncated file",
            "mav.imu.csv",
            |p| {
                let t = std::fs::read_to_string(p).unwrap();
                std::fs::write(p, &t[..t.len() - 40]).unwrap();
            },
            "fields, expected 8",
        ),
        (
            "a descriptor that is not an integer",
            "mav.obs.csv",
            |p| {
                edit_line(p, 5, |l| {
                    let f: Vec<&str> = l.split(',').collect();
                    format!("{},1.5,{}", f[0], f[2..].join(","))
                })
            },
            "descriptor `1.5` is not an unsigned integer",
        ),
        (
            "a later format version",
            "mav.obs.csv",
            |p| {
                let t = std::fs::read_to_string(p).unwrap();
                std::fs::write(p, t.replacen("log v2", "log v3", 1)).unwrap();
            },
            "log format v3",
        ),
    ];
    for (name, file, edit, reason) in cases {
        let dir = tempfile::tempdir().unwrap();
        for e in std::fs::read_dir(good.path()).unwrap() {
            let p = e.unwrap().path();
            std::fs::copy(&p, dir.path().join(p.file_name().unwrap())).unwrap();
        }
        let path = dir.path().join(file);
        edit(&path);
        let scenario = dir.path().join("scenario.toml");
        let scenario = scenario.to_str().unwrap();
        let out = dir.path().join("out");
        for args in [
            vec!["check", scenario],
            vec!["run", scenario, "--out", out.to_str().unwrap(), "--quiet"],
        ] {
            let (ok, stdout, stderr) = run_bounded(&args, Duration::from_secs(60));
            assert!(!ok, "{name}: `canopy {}` succeeded:\n{stdout}", args[0]);
            let located = format!("{}:", path.display());
            assert!(
                stderr.contains(&located) && stderr.contains(reason),
                "{name}: `canopy {}` does not name `{located}<line>:` and `{reason}`:\n{stderr}",
                args[0]
            );
        }
    }
}

/// Replaces line `n` (1-based) of a file.
fn edit_line(p: &Path, n: usize, f: impl Fn(&str) -> String) {
    let t = std::fs::read_to_string(p).unwrap();
    let mut lines: Vec<String> = t.lines().map(str::to_string).collect();
    lines[n - 1] = f(&lines[n - 1]);
    std::fs::write(p, lines.join("\n") + "\n").unwrap();
}
