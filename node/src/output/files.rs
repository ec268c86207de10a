//! Plain-file outputs: TUM trajectories, map CSV, metrics CSV, link CSV.

use crate::record::{RunRecord, VehicleRecord};
use std::fmt::Write as _;

/// Quaternion (qx, qy, qz, qw) of C_b^n for the z-y-x Euler triple (roll, pitch, yaw).
pub fn quaternion_from_euler(att: &[f64; 3]) -> [f64; 4] {
    let q = nalgebra::UnitQuaternion::from_euler_angles(att[0], att[1], att[2]);
    [q.i, q.j, q.k, q.w]
}

/// A timestamp for the outputs: with a recording's time origin [ns] (`[run] time_origin_ns`),
/// origin + t in seconds with all nine decimals, exact (t is rounded to the nanosecond, which
/// recovers the recording's integer timestamp: t was made from one, and f64 keeps nanoseconds
/// exactly for |t| < 2⁵³ ns ≈ 104 days); without one, t with six decimals.
pub fn stamp(origin_ns: Option<u64>, t: f64) -> String {
    match origin_ns {
        Some(o) => {
            let ns = i128::from(o) + (t * 1e9).round() as i128;
            let sign = if ns < 0 { "-" } else { "" };
            let a = ns.unsigned_abs();
            format!("{sign}{}.{:09}", a / 1_000_000_000, a % 1_000_000_000)
        }
        None => format!("{t:.6}"),
    }
}

/// A TUM trajectory (`timestamp tx ty tz qx qy qz qw`, one pose per line, space separated; see
/// the TUM RGB-D benchmark file-format page), of the estimate or of the truth; timestamps as
/// [`stamp`] writes them. Samples without that truth (a replayed vehicle) are left out.
pub fn tum(v: &VehicleRecord, truth: bool, origin_ns: Option<u64>) -> String {
    let mut out = String::with_capacity(v.samples.len() * 96);
    out.push_str("# timestamp tx ty tz qx qy qz qw (launch-site NED frame, metres)\n");
    for s in &v.samples {
        let (p, a) = if truth {
            (&s.truth_pos, &s.truth_att)
        } else {
            (&s.est_pos, &s.est_att)
        };
        if !p.iter().chain(a).all(|x| x.is_finite()) {
            continue;
        }
        let q = quaternion_from_euler(a);
        let _ = writeln!(
            out,
            "{} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
            stamp(origin_ns, s.t),
            p[0],
            p[1],
            p[2],
            q[0],
            q[1],
            q[2],
            q[3]
        );
    }
    out
}

/// Map CSV: one row per feature per vehicle (and per baseline feature, vehicle `baseline`).
pub fn map_csv(run: &RunRecord) -> String {
    let mut out = String::from(
        "vehicle,id,x,y,z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz,truth_x,truth_y,truth_z,error_m,\
         held_since_s,truth_id\n",
    );
    let baseline_map = run
        .baseline
        .as_ref()
        .and_then(|b| b.first())
        .map(|v| ("baseline", v));
    for (name, v) in run
        .vehicles
        .iter()
        .map(|v| (v.name.as_str(), v))
        .chain(baseline_map)
    {
        for f in &v.map {
            let c = &f.cov;
            let _ = write!(
                out,
                "{name},{},{:.6},{:.6},{:.6},{:.9e},{:.9e},{:.9e},{:.9e},{:.9e},{:.9e}",
                f.id, f.est[0], f.est[1], f.est[2], c[0], c[1], c[2], c[4], c[5], c[8]
            );
            match f.truth {
                Some(t) => {
                    let e = (0..3)
                        .map(|i| (f.est[i] - t[i]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    let _ = write!(out, ",{:.6},{:.6},{:.6},{e:.6}", t[0], t[1], t[2]);
                }
                None => out.push_str(",,,,"),
            }
            match f.held_since {
                Some(t) => {
                    let _ = write!(out, ",{t:.3}");
                }
                None => out.push(','),
            }
            match f.truth_id {
                Some(id) => {
                    let _ = writeln!(out, ",{id}");
                }
                None => out.push_str(",\n"),
            }
        }
    }
    out
}

/// Metrics CSV: the estimate-vs-truth time series of every vehicle (and the baseline, with
/// `source = baseline`).
pub fn metrics_csv(run: &RunRecord) -> String {
    let mut out = String::from(
        "source,vehicle,t,err_n,err_e,err_d,err_norm,sigma_n,sigma_e,sigma_d,nees_pos,nees_pose\n",
    );
    let sources = run.vehicles.iter().map(|v| ("decentralized", v));
    let base = run.baseline.iter().flatten().map(|v| ("baseline", v));
    for (source, v) in sources.chain(base) {
        for s in &v.samples {
            let e: Vec<f64> = (0..3).map(|i| s.est_pos[i] - s.truth_pos[i]).collect();
            let _ = writeln!(
                out,
                "{source},{},{:.3},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6},{:.6}",
                v.name,
                s.t,
                e[0],
                e[1],
                e[2],
                s.position_error(),
                s.sigma(0),
                s.sigma(1),
                s.sigma(2),
                s.nees_pos,
                s.nees_pose
            );
        }
    }
    out
}

/// Link CSV: cumulative link statistics over time.
pub fn links_csv(run: &RunRecord) -> String {
    let mut out =
        String::from("link,transport,t,bytes_ab,bytes_ba,messages,drops,rejections,up,a_up,b_up\n");
    for l in &run.links {
        for s in &l.samples {
            let _ = writeln!(
                out,
                "{}-{},{},{:.3},{},{},{},{},{},{},{},{}",
                l.a,
                l.b,
                l.transport,
                s.t,
                s.bytes_ab,
                s.bytes_ba,
                s.messages,
                s.drops,
                s.rejections,
                u8::from(s.up),
                u8::from(s.a_up),
                u8::from(s.b_up)
            );
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::record::PoseSample;

    #[test]
    fn quaternion_matches_the_zyx_convention() {
        // Independent construction: Rz(yaw)·Ry(pitch)·Rx(roll) from axis-angle rotations.
        let att = [0.3, -0.2, 2.0];
        let q = quaternion_from_euler(&att);
        let r = nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::z_axis(), att[2])
            * nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::y_axis(), att[1])
            * nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::x_axis(), att[0]);
        let same =
            (q[0] - r.i).abs() + (q[1] - r.j).abs() + (q[2] - r.k).abs() + (q[3] - r.w).abs();
        let opposite =
            (q[0] + r.i).abs() + (q[1] + r.j).abs() + (q[2] + r.k).abs() + (q[3] + r.w).abs();
        assert!(same.min(opposite) < 1e-12);
    }

    #[test]
    fn tum_lines_have_eight_numeric_fields() {
        let v = VehicleRecord {
            name: "uav1".into(),
            samples: vec![PoseSample {
                t: 1.5,
                est_pos: [1.0, 2.0, -100.0],
                est_att: [0.0, 0.0, 0.5],
                truth_pos: [1.1, 2.0, -100.0],
                truth_att: [0.0, 0.0, 0.5],
                pos_cov: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                nees_pos: 0.01,
                nees_pose: 0.02,
            }],
            ..Default::default()
        };
        for text in [tum(&v, false, None), tum(&v, true, None)] {
            let lines: Vec<_> = text.lines().filter(|l| !l.starts_with('#')).collect();
            assert_eq!(lines.len(), 1);
            let fields: Vec<f64> = lines[0].split(' ').map(|f| f.parse().unwrap()).collect();
            assert_eq!(fields.len(), 8);
            let qn: f64 = fields[4..].iter().map(|x| x * x).sum();
            assert!((qn - 1.0).abs() < 1e-8);
        }
    }

    #[test]
    fn stamps_keep_the_recordings_nanoseconds() {
        // EuRoC timestamps: t made from (ns − origin) / 1e9 stamps back to the same integer.
        let origin = 1_403_715_273_262_143_232_u64;
        for ns in [
            1_403_715_273_262_143_232_u64,
            1_403_715_273_267_142_912,
            1_403_715_303_262_143_232,
        ] {
            let t = (ns - origin) as f64 / 1e9;
            let s = stamp(Some(origin), t);
            let (sec, frac) = s.split_once('.').unwrap();
            assert_eq!(frac.len(), 9);
            let back: u64 =
                sec.parse::<u64>().unwrap() * 1_000_000_000 + frac.parse::<u64>().unwrap();
            assert_eq!(back, ns);
        }
        assert_eq!(stamp(Some(5), -1e-8), "-0.000000005");
        assert_eq!(stamp(None, 1.5), "1.500000");
    }
}
