//! The pose NEES of a replayed vehicle against its ground truth, split into position,
//! roll/pitch and yaw, with the filter's σ and its bias estimates over time: the diagnostic
//! behind docs/benchmarks.md, "Real data" (its roll/pitch and yaw columns).
//!
//! ```sh
//! cargo run --release -p canopy-node --example pose_nees_split -- SCENARIO.toml [PRINT_EVERY_S [OUTCOMES.csv]]
//! ```
//!
//! Replays the scenario's first vehicle exactly as `canopy sim` does (same sources, same agent,
//! same record instants every `record_interval_s`) and prints, every `PRINT_EVERY_S` seconds
//! (default 1), the attitude error and σ [deg], the position error and σ [m], the bias
//! estimates and σ, then the averages: pose ANEES (6 dof, as `summary.json`), position ANEES
//! (3), roll/pitch ANEES (2), yaw NEES (1).

use anyhow::{Context, Result, bail};
use canopy_fusion::consistency::vehicle_error;
use canopy_fusion::state::{ACC_BIAS, ATT, POS};
use canopy_node::metrics::truth_state;
use canopy_node::replay::SensorSource;
use canopy_node::scenario::Scenario;
use nalgebra::{DMatrix, DVector};

/// NEES of the error components `idx` against the covariance's block on them.
fn nees(e: &[f64], p: &DMatrix<f64>, idx: &[usize]) -> f64 {
    let ee = DVector::from_iterator(idx.len(), idx.iter().map(|&i| e[i]));
    let pp = DMatrix::from_fn(idx.len(), idx.len(), |r, c| p[(idx[r], idx[c])]);
    pp.cholesky().map_or(f64::NAN, |c| ee.dot(&c.solve(&ee)))
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        bail!("usage: pose_nees_split SCENARIO.toml [PRINT_EVERY_S]");
    };
    let every: f64 = args.get(1).map_or(Ok(1.0), |a| a.parse())?;
    // Optional: every observation's outcome as CSV (time, track id, outcome, NIS).
    let mut outcomes = match args.get(2) {
        Some(p) => Some(std::io::BufWriter::new(std::fs::File::create(p)?)),
        None => None,
    };
    let s = Scenario::load(std::path::Path::new(path)).context("loading the scenario")?;
    let (world, mut sources) = SensorSource::for_scenario(&s)?;
    let src = sources.first_mut().context("no vehicle")?;
    let est = src.initial_estimate();
    let mut agent = canopy_node::sim::vehicle_agent(&s, &s.vehicles[0], &world, &est, 0, 1)?;
    let record_dt = s.run.record_interval_s;
    let duration = s.run.duration_s;
    let eps = 1e-9;
    let mut next_record = 0.0;
    let mut next_print = 0.0;
    let deg = 1f64.to_degrees();
    // Sums: pose/6, position/3, roll-pitch/2, yaw/1, count.
    let mut sums = [0.0; 5];
    let mut segments: Vec<(f64, [f64; 5])> = Vec::new();
    println!(
        "{:>6} | {:>7} {:>7} {:>7} | {:>6} {:>6} {:>6} | {:>6} {:>6} | {:>7} {:>7} {:>7} {:>6} | {:>7} {:>7} {:>7} | rp yaw NEES",
        "t",
        "e_roll",
        "e_pit",
        "e_yaw",
        "σ_r",
        "σ_p",
        "σ_y",
        "|e_p|",
        "σ_p",
        "ba_x",
        "ba_y",
        "ba_z",
        "σ_ba",
        "bg_x",
        "bg_y",
        "bg_z"
    );
    let mut record = |t: f64,
                      agent: &canopy_node::agent::VehicleAgent,
                      truth: Option<canopy_node::world::TruthSample>| {
        let f = agent.filter();
        let (Ok(x), Ok(cov)) = (f.vehicle_state(0), f.vehicle_covariance(0)) else {
            return;
        };
        let Some(truth) = truth else { return };
        let e = vehicle_error(&x, &truth_state(&truth));
        let p = DMatrix::from_fn(15, 15, |i, j| cov[(i, j)]);
        let pose: Vec<usize> = (POS..POS + 3).chain(ATT..ATT + 3).collect();
        let n = [
            nees(e.as_slice(), &p, &pose) / 6.0,
            nees(e.as_slice(), &p, &[POS, POS + 1, POS + 2]) / 3.0,
            nees(e.as_slice(), &p, &[ATT, ATT + 1]) / 2.0,
            nees(e.as_slice(), &p, &[ATT + 2]),
            1.0,
        ];
        for (sum, x) in sums.iter_mut().zip(n) {
            *sum += x;
        }
        let seg = (t / 5.0).floor() * 5.0;
        match segments.last_mut() {
            Some((s0, acc)) if *s0 == seg => acc.iter_mut().zip(n).for_each(|(a, x)| *a += x),
            _ => segments.push((seg, n)),
        }
        if t + eps >= next_print {
            next_print += every;
            let sd = |i: usize| cov[(i, i)].sqrt();
            let ep = (e[POS].powi(2) + e[POS + 1].powi(2) + e[POS + 2].powi(2)).sqrt();
            let sp = (cov[(POS, POS)] + cov[(POS + 1, POS + 1)] + cov[(POS + 2, POS + 2)]).sqrt();
            println!(
                "{t:6.2} | {:7.3} {:7.3} {:7.3} | {:6.3} {:6.3} {:6.3} | {ep:6.3} {sp:6.3} | {:7.3} {:7.3} {:7.3} {:6.3} | {:7.4} {:7.4} {:7.4} | {:5.2} {:5.2}",
                e[ATT] * deg,
                e[ATT + 1] * deg,
                e[ATT + 2] * deg,
                sd(ATT) * deg,
                sd(ATT + 1) * deg,
                sd(ATT + 2) * deg,
                x.accel_bias.x,
                x.accel_bias.y,
                x.accel_bias.z,
                sd(ACC_BIAS),
                x.gyro_bias.x,
                x.gyro_bias.y,
                x.gyro_bias.z,
                n[2],
                n[3],
            );
        }
    };
    record(0.0, &agent, src.truth().copied());
    next_record += record_dt;
    while let Some(t) = src.next_time() {
        if t > duration + eps {
            break;
        }
        let Some(out) = src.step() else { break };
        let _ = agent.on_imu(&out.imu);
        if let Some((frame, _)) = &out.frame
            && let Ok(report) = agent.on_frame(frame)
            && let Some(w) = outcomes.as_mut()
        {
            use canopy_fusion::slam::{ObservationOutcome as O, RejectReason as R};
            use std::io::Write;
            for (o, r) in frame.observations.iter().zip(&report.outcomes) {
                let (kind, nis) = match r {
                    O::Associated { nis, .. } => ("associated", *nis),
                    O::Initialized { .. } => ("initialized", f64::NAN),
                    O::Stored { .. } => ("stored", f64::NAN),
                    O::Rejected(R::GateFailed { nis, .. }) => ("gate_failed", *nis),
                    O::Rejected(r) => (r.label(), f64::NAN),
                };
                writeln!(w, "{},{},{kind},{nis}", frame.time, o.descriptor)?;
            }
        }
        let now = src.time();
        if now + eps >= next_record {
            record(now, &agent, src.truth().copied());
            next_record += record_dt;
        }
    }
    let c = sums[4];
    println!(
        "pose ANEES {:.3}  position ANEES {:.3}  roll/pitch ANEES {:.3}  yaw NEES {:.3}  ({} samples)",
        sums[0] / c,
        sums[1] / c,
        sums[2] / c,
        sums[3] / c,
        c
    );
    for (s0, a) in segments {
        println!(
            "  {s0:5.1}–{:5.1} s: pose {:.2}  position {:.2}  roll/pitch {:.2}  yaw {:.2}",
            s0 + 5.0,
            a[0] / a[4],
            a[1] / a[4],
            a[2] / a[4],
            a[3] / a[4]
        );
    }
    let r = agent.rejections();
    println!("rejections: {:?}", r);
    Ok(())
}
