//! Monte Carlo consistency statistics over seeded runs (Bar-Shalom, Li & Kirubarajan, §5.4):
//! the average NEES over N runs of a consistent filter, divided by its dof, lies in
//! [χ²_{N·d}(0.025), χ²_{N·d}(0.975)] / (N·d) with 95 % probability.

use canopy_fusion::consistency::chi2_quantile;
use canopy_node::output::summary::feature_nees;
use canopy_node::record::VehicleRecord;

/// Two-sided 95 % band of the normalised ANEES (ANEES / dof) for `total_dof` = runs × dof.
pub fn normalised_band(total_dof: f64) -> (f64, f64) {
    (
        chi2_quantile(total_dof, 0.025).expect("dof > 0") / total_dof,
        chi2_quantile(total_dof, 0.975).expect("dof > 0") / total_dof,
    )
}

/// Pose (6-dof) ANEES per record time across runs, normalised by 6.
#[derive(Debug, Clone)]
pub struct PoseConsistency {
    /// Runs.
    pub runs: usize,
    /// Normalised ANEES at each record time (only times every run reached).
    pub per_time: Vec<(f64, f64)>,
    /// Mean over time of the normalised ANEES.
    pub time_mean: f64,
    /// The per-time 95 % band for `runs` runs.
    pub band: (f64, f64),
    /// Fraction of record times whose ANEES is inside the band.
    pub fraction_in_band: f64,
    /// RMS position error over runs and times [m].
    pub position_rmse: f64,
}

/// Pose consistency of one vehicle (by index) over many runs' records.
pub fn pose_consistency(records: &[&VehicleRecord], skip_before: f64) -> PoseConsistency {
    let runs = records.len();
    let n = records.iter().map(|r| r.samples.len()).min().unwrap_or(0);
    let band = normalised_band(6.0 * runs as f64);
    let mut per_time = Vec::new();
    let mut sq = 0.0;
    let mut cnt = 0usize;
    for k in 0..n {
        let t = records[0].samples[k].t;
        if t < skip_before {
            continue;
        }
        let s: f64 = records.iter().map(|r| r.samples[k].nees_pose).sum();
        per_time.push((t, s / (6.0 * runs as f64)));
        for r in records {
            sq += r.samples[k].position_error().powi(2);
            cnt += 1;
        }
    }
    let time_mean = per_time.iter().map(|p| p.1).sum::<f64>() / per_time.len().max(1) as f64;
    let inside = per_time
        .iter()
        .filter(|p| p.1 >= band.0 && p.1 <= band.1)
        .count();
    PoseConsistency {
        runs,
        fraction_in_band: inside as f64 / per_time.len().max(1) as f64,
        per_time,
        time_mean,
        band,
        position_rmse: (sq / cnt.max(1) as f64).sqrt(),
    }
}

/// Map consistency at the end of the runs: every feature with a truth, per-feature NEES.
#[derive(Debug, Clone)]
pub struct MapConsistency {
    /// Features summed over runs.
    pub features: usize,
    /// Σ NEES / Σ dof over all features of all runs.
    pub anees: f64,
    /// 95 % band for that many dof (features are correlated within a run, so this band is
    /// narrower than the truth; see the tests for how it is used).
    pub band: (f64, f64),
    /// Per-run normalised map NEES (Σ over the run's features / its dof).
    pub per_run: Vec<f64>,
    /// RMS map error [m].
    pub rmse: f64,
}

/// Map consistency over runs.
pub fn map_consistency(records: &[&VehicleRecord]) -> MapConsistency {
    let mut total = 0.0_f64;
    let mut dof = 0.0_f64;
    let mut sq = 0.0;
    let mut count = 0usize;
    let mut per_run = Vec::new();
    for r in records {
        let mut rt = 0.0;
        let mut rd = 0.0_f64;
        for f in &r.map {
            let Some(t) = f.truth else { continue };
            if let Some(n) = feature_nees(&f.est, &f.cov, &t) {
                rt += n;
                rd += 3.0;
                sq += (0..3).map(|i| (f.est[i] - t[i]).powi(2)).sum::<f64>();
                count += 1;
            }
        }
        total += rt;
        dof += rd;
        per_run.push(rt / rd.max(1.0));
    }
    MapConsistency {
        features: count,
        anees: total / dof.max(1.0),
        band: normalised_band(dof.max(1.0)),
        per_run,
        rmse: (sq / count.max(1) as f64).sqrt(),
    }
}
