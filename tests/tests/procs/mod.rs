//! Harness of the multi-process suites: runs the real `canopy` binary (`canopy run`, `canopy
//! check`) and reads what it wrote (summary.json, checks.json, map.csv, links.csv).
//!
//! The binary is the one `cargo build --release` put next to the test executables
//! (`target/release/canopy`); the README's test command (`scripts/test.sh`) builds it first.
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::{Mutex, MutexGuard};

use canopy_node::output::Summary;
use canopy_node::process::monitor::RunChecks;

/// One multi-process run at a time: a run uses every core of this machine, and its
/// flow-controlled timing does not need to compete with another.
static SERIAL: Mutex<()> = Mutex::new(());

/// Holds the machine for one multi-process run.
pub fn serial() -> MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|e| e.into_inner())
}

/// The `canopy` binary next to this test executable (`target/<profile>/canopy`).
pub fn canopy_bin() -> PathBuf {
    let exe = std::env::current_exe().expect("test executable path");
    // target/<profile>/deps/<test>-<hash>  →  target/<profile>/canopy
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("test executable lives in target/<profile>/deps");
    let bin = dir.join("canopy");
    assert!(
        bin.is_file(),
        "the canopy binary is missing at {}: build it first with \
         `cargo build --release -p canopy-node` (scripts/test.sh does)",
        bin.display()
    );
    bin
}

/// The workspace root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is inside the workspace")
        .to_path_buf()
}

/// A scenario file of `topologies/`.
pub fn topology(name: &str) -> PathBuf {
    root().join("topologies").join(name)
}

/// What a `canopy run` left behind.
#[derive(Debug)]
pub struct Run {
    /// Output directory (kept until the test ends).
    pub dir: tempfile::TempDir,
    /// The command's exit status, stdout and stderr.
    pub output: Output,
    /// summary.json.
    pub summary: Summary,
    /// checks.json.
    pub checks: RunChecks,
}

impl Run {
    /// stdout and stderr of the launcher.
    pub fn text(&self) -> String {
        format!(
            "{}{}",
            String::from_utf8_lossy(&self.output.stdout),
            String::from_utf8_lossy(&self.output.stderr)
        )
    }

    /// The path of an output file.
    pub fn file(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    /// Rows of a CSV output as maps from column name to value.
    pub fn csv(&self, name: &str) -> Vec<BTreeMap<String, String>> {
        let text = std::fs::read_to_string(self.file(name)).expect("csv output exists");
        let mut lines = text.lines();
        let header: Vec<String> = lines
            .next()
            .expect("csv header")
            .split(',')
            .map(String::from)
            .collect();
        lines
            .map(|l| {
                header
                    .iter()
                    .cloned()
                    .zip(l.split(',').map(String::from))
                    .collect()
            })
            .collect()
    }

    /// The final maps of map.csv per vehicle (and `baseline`): true feature id → (trace of the
    /// covariance, error to truth, held since [s]). Keyed by `truth_id` (the feature a key
    /// stands for, `canopy_node::truth`), so that vehicles keying their maps by their own keys
    /// (simulated appearance) compare with the reference, which keys by true id; where a map
    /// holds a feature under two keys (a duplicate) the later row stands for it. Rows without a
    /// truth (replayed vehicles) keep their key.
    pub fn maps(&self) -> BTreeMap<String, BTreeMap<u64, (f64, f64, f64)>> {
        let mut out: BTreeMap<String, BTreeMap<u64, (f64, f64, f64)>> = BTreeMap::new();
        for r in self.csv("map.csv") {
            let tr: f64 = ["cov_xx", "cov_yy", "cov_zz"]
                .iter()
                .map(|k| r[*k].parse::<f64>().expect("number"))
                .sum();
            let err = r["error_m"].parse::<f64>().unwrap_or(f64::NAN);
            let since = r["held_since_s"].parse::<f64>().expect("held_since_s");
            let key = match r["truth_id"].as_str() {
                "" => r["id"].parse().expect("id"),
                t => t.parse().expect("truth_id"),
            };
            out.entry(r["vehicle"].clone())
                .or_default()
                .insert(key, (tr, err, since));
        }
        out
    }

    /// Per vehicle: how its final map compares with the centralized reference's (coverage of
    /// the features mature for [`MATURE_S`]).
    pub fn map_standing(&self) -> BTreeMap<String, Standing> {
        self.map_standing_mature(MATURE_S)
    }

    /// [`Run::map_standing`] with coverage over the features the reference has held for
    /// `mature_s` before the end (a longer window for links whose repairs take longer).
    pub fn map_standing_mature(&self, mature_s: f64) -> BTreeMap<String, Standing> {
        let maps = self.maps();
        let base = maps.get("baseline").expect("the run has a baseline");
        let end = self.summary.duration_s;
        let mature: Vec<u64> = base
            .iter()
            .filter(|(_, v)| v.2 <= end - mature_s)
            .map(|(id, _)| *id)
            .collect();
        maps.iter()
            .filter(|(k, _)| *k != "baseline")
            .map(|(name, m)| {
                let mut shares: Vec<f64> = m
                    .iter()
                    .filter_map(|(id, v)| base.get(id).map(|b| b.0 / v.0))
                    .collect();
                shares.sort_by(f64::total_cmp);
                let common = shares.len();
                let held_mature = mature.iter().filter(|id| m.contains_key(id)).count();
                let mut latencies: Vec<f64> = m
                    .iter()
                    .filter_map(|(id, v)| base.get(id).map(|b| v.2 - b.2))
                    .collect();
                latencies.sort_by(f64::total_cmp);
                let latency_p90 = latencies
                    .get((latencies.len() * 9) / 10)
                    .copied()
                    .unwrap_or(f64::NAN);
                // The share a vehicle lagging the team by `latency_p90` holds at least, feature
                // by feature, if information accrues evenly over a feature's life: (age − L) /
                // age of the reference's age (its own observations are current, so it holds
                // more).
                let mut floors: Vec<f64> = m
                    .keys()
                    .filter_map(|id| base.get(id))
                    .map(|b| {
                        let age = end - b.2;
                        if age > 0.0 {
                            ((age - latency_p90) / age).max(0.0)
                        } else {
                            1.0
                        }
                    })
                    .collect();
                floors.sort_by(f64::total_cmp);
                let errs: Vec<f64> = m.values().map(|v| v.1).filter(|e| e.is_finite()).collect();
                (
                    name.clone(),
                    Standing {
                        coverage: held_mature as f64 / mature.len().max(1) as f64,
                        coverage_all: common as f64 / base.len().max(1) as f64,
                        latency_p90,
                        share: shares.get(common / 2).copied().unwrap_or(0.0),
                        share_floor: floors.get(floors.len() / 2).copied().unwrap_or(1.0),
                        features: m.len(),
                        rmse: (errs.iter().map(|e| e * e).sum::<f64>() / errs.len().max(1) as f64)
                            .sqrt(),
                    },
                )
            })
            .collect()
    }

    /// Prints every vehicle's standing (figures for the test log) and returns it.
    pub fn print_standing(&self, label: &str) -> BTreeMap<String, Standing> {
        self.print_standing_mature(label, MATURE_S)
    }

    /// [`Run::print_standing`] with coverage over features mature for `mature_s`.
    pub fn print_standing_mature(&self, label: &str, mature_s: f64) -> BTreeMap<String, Standing> {
        let standing = self.map_standing_mature(mature_s);
        for (name, s) in &standing {
            eprintln!(
                "{label} {name}: coverage {:.3} (all features {:.3}), arrival p90 {:.1} s, \
                 share {:.2}, map RMSE {:.2} m",
                s.coverage, s.coverage_all, s.latency_p90, s.share, s.rmse
            );
        }
        standing
    }

    /// What a failed check on `vehicle` prints besides its figures: its counters and
    /// rejections per incarnation, its last map reports (time, features), the channel of
    /// every link end it has, in both directions, and when each of its links was up on which
    /// end — enough to tell a lost map report, a refused fusion, a resynchronisation, a
    /// stalled or cut link apart from a test's tolerance.
    pub fn diagnosis(&self, vehicle: &str) -> String {
        let mut out = String::new();
        if let Some(v) = self.checks.vehicles.iter().find(|v| v.name == vehicle) {
            let tail = v.map_sizes.len().saturating_sub(6);
            out += &format!(
                "{vehicle}: last estimate report {} s, map reports (t, features) …{:?}\n",
                v.last_report_t,
                &v.map_sizes[tail..]
            );
            for (i, c) in v.counters.iter().enumerate() {
                out += &format!("  incarnation {i}: {c:?}\n");
            }
        }
        for l in &self.checks.link_ends {
            if l.node == vehicle || l.peer == vehicle {
                out += &format!("  {}->{}: {:?}\n", l.node, l.peer, l.report);
            }
        }
        // When each of its links was up on which end (links.csv, changes only): a link cut
        // late in the run explains information the vehicle never got back.
        let mut last: BTreeMap<String, String> = BTreeMap::new();
        let mut changes: BTreeMap<String, Vec<String>> = BTreeMap::new();
        for row in self.csv("links.csv") {
            let link = &row["link"];
            if !link.split('-').any(|n| n == vehicle) {
                continue;
            }
            let state = format!("a_up {} b_up {}", row["a_up"], row["b_up"]);
            if last.get(link) != Some(&state) {
                changes
                    .entry(link.clone())
                    .or_default()
                    .push(format!("{} s: {state}", row["t"]));
                last.insert(link.clone(), state);
            }
        }
        for (link, c) in changes {
            out += &format!("  {link} up over time: {}\n", c.join("; "));
        }
        out
    }

    /// `up` of one link in links.csv over time: (t, up).
    pub fn link_up(&self, link: &str) -> Vec<(f64, bool)> {
        self.csv("links.csv")
            .into_iter()
            .filter(|r| r["link"] == link)
            .map(|r| (r["t"].parse().expect("t"), r["up"] == "1"))
            .collect()
    }
}

/// One end's view of a fusion link at the end of a run (`checks.json` `link_ends`).
pub fn link_end<'a>(
    r: &'a Run,
    node: &str,
    peer: &str,
) -> &'a canopy_node::process::monitor::LinkEndCheck {
    r.checks
        .link_ends
        .iter()
        .find(|l| l.node == node && l.peer == peer)
        .unwrap_or_else(|| panic!("no link end {node}->{peer}"))
}

/// The process side of a crash-restart: `vehicle` ran twice — killed with SIGKILL by the
/// launcher, then incarnation 1 exiting cleanly —, was initialised twice, fused again after the
/// restart (channel-filter deltas, or in data sharing the team's records) and reported until
/// the end (`end` − 1 s).
pub fn assert_process_restarted(r: &Run, vehicle: &str, end: f64) {
    let procs: Vec<_> = r
        .checks
        .processes
        .iter()
        .filter(|p| p.name == vehicle)
        .collect();
    assert_eq!(procs.len(), 2, "{vehicle} should run twice: {procs:?}");
    assert!(
        procs[0].killed_by_monitor && procs[0].signal == Some(9),
        "{:?}",
        procs[0]
    );
    assert!(
        procs[1].clean_exit() && procs[1].incarnation == 1,
        "{:?}",
        procs[1]
    );
    let v = r
        .checks
        .vehicles
        .iter()
        .find(|v| v.name == vehicle)
        .expect("the restarted vehicle");
    assert_eq!(v.initialisations, 2);
    assert!(
        v.counters[1].fused > 0,
        "the restarted {vehicle} never fused"
    );
    assert!(
        v.last_report_t >= end - 1.0,
        "the restarted {vehicle} stopped reporting at {}",
        v.last_report_t
    );
}

/// The crash-restart checks (outage.rs `crash_restart`, hosts.rs across machines):
/// [`assert_process_restarted`]; every neighbour saw the new epoch and, holding history, initiated
/// the new pair's Sync (the side with history initiates), which the new incarnation applied (its
/// link ends report the new incarnation's counters) without initiating any; and the team converged
/// on one map: the vehicles' information shares agree within 0.05 of each other (measured identical
/// to 0.01).
pub fn assert_crash_restarted(r: &Run, vehicle: &str, neighbours: &[&str], end: f64) {
    assert_process_restarted(r, vehicle, end);
    for n in neighbours {
        let c = &link_end(r, n, vehicle).report.channel;
        assert!(c.peer_restarts >= 1, "{n} did not see {vehicle} restart");
        assert!(
            c.syncs_initiated >= 1,
            "{n} did not resynchronise with the new {vehicle}"
        );
        let back = &link_end(r, vehicle, n).report.channel;
        assert!(
            back.syncs_applied >= 1 && back.syncs_initiated == 0,
            "the new {vehicle} did not take {n}'s Sync: {back:?}"
        );
    }
    let shares: Vec<f64> = r.map_standing().values().map(|s| s.share).collect();
    let (lo, hi) = shares
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    assert!(
        hi - lo <= 0.05,
        "vehicles disagree after the restart: shares {shares:?}"
    );
}

/// A feature the reference has held for this long before the end of a run has had time to
/// reach every vehicle: 10 fusion rounds at 1 Hz for a tree of diameter ≤ 3, with room for
/// the 2 s gap timeout of a lost delta and the sensor-paced lag between processes (measured
/// arrival p90 ≤ 5 s fault-free). Features younger than that may still be on their way, by an
/// amount that depends on process scheduling, not on the fusion. Suites whose links lose
/// messages for the whole run use a longer window ([`Run::map_standing_mature`]).
pub const MATURE_S: f64 = 10.0;

/// Every vehicle of a fault-free run holds the team's map: at least `coverage` of the
/// reference's mature features, and an information share within 0.05 of what the run's timing
/// allows ([`Standing::share_floor`]; 0.05: linearisation differences and uneven accrual) and
/// at most 1.05 (not more than the whole team's data). A fixed share bound (0.95) failed now
/// and then when a vehicle's last feedback came a round later than usual (central-4 over 30 s:
/// 0.954–0.999 in 26 runs here); the floor follows the lag the run measured, and a vehicle that
/// lost information (not lag) still fails it. Returns the standings (printed under `label`).
pub fn assert_holds_the_team_map(
    r: &Run,
    label: &str,
    coverage: f64,
) -> BTreeMap<String, Standing> {
    let standing = r.print_standing(label);
    for (name, s) in &standing {
        assert!(
            s.coverage >= coverage,
            "{name}: coverage {:.2}\n{}",
            s.coverage,
            r.diagnosis(name)
        );
        eprintln!(
            "{label} {name}: share {:.3}, floor from its lag of {:.1} s {:.3}",
            s.share, s.latency_p90, s.share_floor
        );
        assert!(
            s.share >= s.share_floor - 0.05 && s.share <= 1.05,
            "{name}: information share {:.3}, the run's timing allows down to {:.3} (lag {:.1} s)\n{}",
            s.share,
            s.share_floor,
            s.latency_p90,
            r.diagnosis(name)
        );
    }
    standing
}

/// A vehicle's final map against the reference's.
#[derive(Clone, Copy, Debug)]
pub struct Standing {
    /// Fraction of the reference's *mature* features (held by the reference since at least
    /// [`MATURE_S`] before the end) that the vehicle holds.
    pub coverage: f64,
    /// Fraction of all the reference's features the vehicle holds.
    pub coverage_all: f64,
    /// 90th percentile over the vehicle's features of how much later than the reference it
    /// came to hold them [s] (`held_since_s` of map.csv).
    pub latency_p90: f64,
    /// Median over common features of tr(P_ref) / tr(P_vehicle): 1 when the vehicle holds
    /// what the whole team's data gives, below 1 when it holds less.
    pub share: f64,
    /// The share the run's own timing lets the vehicle hold: the median over common features
    /// of (age − L) / age, age the time since the reference first held the feature and L the
    /// vehicle's `latency_p90` (how late the team's information reaches it in this run). A
    /// vehicle lagging by L on everything holds at least that if information accrues evenly
    /// (its own observations are current: more). [`assert_holds_the_team_map`] judges by it.
    pub share_floor: f64,
    /// Features in its map.
    pub features: usize,
    /// RMS error of its map [m].
    pub rmse: f64,
}

/// Runs `canopy run SCENARIO --out <temp> ARGS…` and reads its outputs. Panics (with the
/// launcher's output) if it fails or an output is missing.
pub fn run(scenario: &Path, args: &[&str]) -> Run {
    run_with(Command::new(canopy_bin()), scenario, args)
}

/// [`run`] with a prepared command (environment, wrapper).
pub fn run_with(mut cmd: Command, scenario: &Path, args: &[&str]) -> Run {
    let dir = tempfile::tempdir().expect("temporary output directory");
    let output = cmd
        .arg("run")
        .arg(scenario)
        .arg("--out")
        .arg(dir.path())
        .args(args)
        .output()
        .expect("the canopy binary runs");
    collect(dir, output, scenario)
}

/// Reads what a finished `canopy run SCENARIO --out DIR` left in `dir`. Panics (with the
/// launcher's output) if it failed or an output is missing.
pub fn collect(dir: tempfile::TempDir, output: Output, scenario: &Path) -> Run {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(
        output.status.success(),
        "canopy run {} failed ({}):\n{text}",
        scenario.display(),
        output.status
    );
    let read = |name: &str| {
        std::fs::read_to_string(dir.path().join(name))
            .unwrap_or_else(|e| panic!("{name} missing ({e}):\n{text}"))
    };
    let summary: Summary =
        serde_json::from_str(&read("summary.json")).expect("summary.json parses");
    let checks: RunChecks = serde_json::from_str(&read("checks.json")).expect("checks.json parses");
    Run {
        dir,
        output,
        summary,
        checks,
    }
}

/// `canopy check FILE`: (success, stdout + stderr).
pub fn check(file: &Path) -> (bool, String) {
    let out = Command::new(canopy_bin())
        .arg("check")
        .arg(file)
        // The error chain, not a backtrace, is what a user reads.
        .env("RUST_BACKTRACE", "0")
        .env("RUST_LIB_BACKTRACE", "0")
        .output()
        .expect("the canopy binary runs");
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

/// Confidence tolerance: no vehicle may ever be more confident about a feature than the
/// centralized reference by more than this factor (λ_max(P_ref P_i⁻¹)). The decentralized EKFs
/// linearise at other points than the reference (measured ≤ 1.001 on these scenarios); counting
/// a feature's information twice shows as ≈ 2.
pub const CONFIDENCE_TOL: f64 = 1.2;

/// Samples (1 s apart) below which a single vehicle's fraction of over-confident pose samples is
/// not judged on its own (see [`assert_sound`]): 30 s, several correlation times of the NEES.
pub const MIN_BAND_SAMPLES: usize = 30;

/// The checks every run must pass: no process panicked or failed, every process exited
/// cleanly unless the monitor killed it on purpose, no stream gap and no rejected estimator
/// input, the confidence bound at every map report, and NEES consistent with the χ² bounds.
pub fn assert_sound(r: &Run) {
    assert_sound_with(r, 0.1);
}

/// [`assert_sound`] with a floor of `band_floor` (instead of 0.1) on each vehicle's share of
/// over-confident pose samples: for local SLAM in own frames, where a vehicle runs alone until
/// it has aligned its frame while the reference uses every vehicle's data from the start.
pub fn assert_sound_with(r: &Run, band_floor: f64) {
    assert_clean_and_never_over_confident(r);
    assert_pose_consistent(r, band_floor);
}

/// The part of [`assert_sound`] about the run and the maps: no process panicked or failed,
/// every process exited cleanly unless the monitor killed it on purpose, every vehicle reported
/// its peak memory, no stream gap and no rejected estimator input, and the confidence bound at
/// every map report (no vehicle more confident about a feature than the reference).
pub fn assert_clean_and_never_over_confident(r: &Run) {
    let text = r.text();
    assert!(
        r.checks.failure.is_none(),
        "run failed: {:?}",
        r.checks.failure
    );
    assert!(!r.checks.interrupted);
    assert!(!text.contains("panicked"), "the launcher panicked:\n{text}");
    // Every vehicle process reports its peak resident memory (Linux VmHWM), printed for the
    // test log.
    for v in &r.checks.vehicles {
        let mb = v.peak_rss_mb.expect("peak RSS reported");
        assert!(mb.is_finite() && mb > 0.0, "{}: peak RSS {mb} MB", v.name);
        eprintln!("{}: peak RSS {mb:.0} MB", v.name);
    }
    for p in &r.checks.processes {
        assert!(
            !p.panicked,
            "process {} panicked; log {}",
            p.name,
            p.log.display()
        );
        assert!(
            p.clean_exit() || p.killed_by_monitor,
            "process {} (incarnation {}) ended with code {:?} signal {:?}; log {}",
            p.name,
            p.incarnation,
            p.exit_code,
            p.signal,
            p.log.display()
        );
    }
    for v in &r.checks.vehicles {
        for c in &v.counters {
            assert_eq!(c.stream_gaps, 0, "{}: sensor batches lost", v.name);
            assert_eq!(
                c.inputs_rejected, 0,
                "{}: estimator inputs rejected",
                v.name
            );
        }
        assert!(v.estimate_reports > 0, "{} never reported", v.name);
    }
    let worst = r
        .checks
        .max_confidence_ratio
        .expect("map reports were checked against the reference");
    assert!(
        worst <= CONFIDENCE_TOL,
        "a vehicle is {worst:.3}× more confident about a feature than the centralized reference"
    );
    assert!(
        r.checks.confidence.len() >= r.checks.vehicles.len(),
        "too few confidence checks"
    );
}

/// The part of [`assert_sound`] about the vehicles' poses: NEES consistent with the χ² bounds
/// against the reference's ([`assert_sound_with`] for `band_floor`).
fn assert_pose_consistent(r: &Run, band_floor: f64) {
    // Pose samples per vehicle (metrics.csv rows of the decentralized estimate).
    let mut samples: BTreeMap<String, usize> = BTreeMap::new();
    for row in r.csv("metrics.csv") {
        if row["source"] != "baseline" {
            *samples.entry(row["vehicle"].clone()).or_default() += 1;
        }
    }
    let base = r.summary.baseline.as_ref().expect("baseline figures");
    for (v, b) in r.summary.vehicles.iter().zip(&base.vehicles) {
        // Pose NEES time average: the vehicles hold at most the reference's information, so
        // their NEES tracks the reference's on the same data (clean runs: within 0.05); 30 % +
        // 0.2 absorbs the spread of a ~90-sample average of strongly time-correlated NEES.
        // EKF-SLAM is mildly over-confident by itself (the reference's ANEES here is 0.8–1.6).
        // Per vehicle only over at least `MIN_BAND_SAMPLES` (below, as for the over-confident
        // fraction): a 16-sample average of a NEES correlated over several seconds is one or two
        // excursions — the 15 s 64-vehicle run had vehicles at 1.35–1.63 against references of
        // 0.64–1.29 while the team's pooled ANEES was 0.95 against the reference's 1.03 and every
        // confidence ratio against the reference ≤ 1. Short runs are judged on the team's pooled
        // ANEES below, with the same bound.
        let n = samples.get(&v.name).copied().unwrap_or(0);
        assert!(
            n < MIN_BAND_SAMPLES || v.pose_anees <= 1.3 * b.pose_anees + 0.2,
            "{}: pose ANEES {:.2} vs the reference's {:.2} ({n} samples)",
            v.name,
            v.pose_anees,
            b.pose_anees
        );
        // Per-sample pose NEES above the χ²₆ 97.5 % quantile (over-confident samples) at most
        // 10 % of the time: 2.5 % for an ideal filter; consecutive samples are correlated and
        // EKF-SLAM is mildly over-confident (the reference reaches 3.3 % on the outage
        // scenarios). Where the centralized reference itself is over-confident more often on
        // the same data (the pixel-camera vehicle of bearing-only.toml: 22 % over 40 s, one
        // excursion of correlated samples), the vehicle may match it plus 0.05 (two samples of
        // a 40-sample run): the DDF must not add over-confidence, the estimator's own is the
        // reference's. Samples *below* the band are conservative ones (covariance
        // intersection); the two-sided test is [`assert_in_band`].
        //
        // Per vehicle only over at least `MIN_BAND_SAMPLES`: a vehicle that learns the team's
        // information some rounds after the reference repeats the reference's excursions at
        // other times, and over a short run one such excursion of 2–3 correlated samples is
        // 12–19 % of 16 (the 15 s scale run: its reference is above the band 25–31 % of the
        // time on two vehicles). Short runs are judged on the team's pooled fraction below.
        let n = samples.get(&v.name).copied().unwrap_or(0);
        if n >= MIN_BAND_SAMPLES {
            let bound = (b.pose_nees_above_band + 0.05).max(band_floor);
            assert!(
                v.pose_nees_above_band <= bound,
                "{}: pose NEES above the χ² band {:.1} % of the time (reference {:.1} %, bound \
                 {:.1} %)",
                v.name,
                100.0 * v.pose_nees_above_band,
                100.0 * b.pose_nees_above_band,
                100.0 * bound
            );
        }
        // Map NEES per dof ≤ 2: features are never grossly over-confident (χ²₃ per feature has
        // mean 1 per dof; the team's maps sit at 0.1–0.6, conservative).
        assert!(
            v.map_anees <= 2.0,
            "{}: map ANEES {:.2}",
            v.name,
            v.map_anees
        );
    }
    // The same bound on the team's pooled fraction (weighted by each vehicle's samples), which
    // short runs are judged on: the DDF must not make the team over-confident more often than
    // the reference on the same data.
    let pooled = |vs: &[canopy_node::output::summary::VehicleSummary]| {
        let (mut above, mut total) = (0.0, 0.0);
        for v in vs.iter().filter(|v| v.pose_nees_above_band.is_finite()) {
            let n = samples.get(&v.name).copied().unwrap_or(0) as f64;
            above += n * v.pose_nees_above_band;
            total += n;
        }
        above / f64::max(total, 1.0)
    };
    // Pooled pose ANEES (sample-weighted): the team as a whole within 30 % + 0.2 of the
    // reference, as a single vehicle of a long run (a pooled average over the team's vehicles
    // has at least the samples of one long run).
    let pooled_anees = |vs: &[canopy_node::output::summary::VehicleSummary]| {
        let (mut sum, mut total) = (0.0, 0.0);
        for v in vs.iter().filter(|v| v.pose_anees.is_finite()) {
            let n = samples.get(&v.name).copied().unwrap_or(0) as f64;
            sum += n * v.pose_anees;
            total += n;
        }
        sum / f64::max(total, 1.0)
    };
    let (team_anees, reference_anees) = (
        pooled_anees(&r.summary.vehicles),
        pooled_anees(&base.vehicles),
    );
    assert!(
        team_anees <= 1.3 * reference_anees + 0.2,
        "the team's pooled pose ANEES {team_anees:.2} vs the reference's {reference_anees:.2}"
    );
    let team = pooled(&r.summary.vehicles);
    let reference = pooled(&base.vehicles);
    assert!(
        team <= (reference + 0.05).max(0.1),
        "the team's pose NEES is above the χ² band {:.1} % of the time (reference {:.1} %)",
        100.0 * team,
        100.0 * reference
    );
}

/// Per-sample pose NEES inside the two-sided 95 % χ²₆ band at least `min` of the time, for
/// every vehicle: neither over- nor under-confident. Runs with exact fusion only: covariance
/// intersection is conservative by design and leaves samples below the band.
pub fn assert_in_band(r: &Run, min: f64) {
    for v in &r.summary.vehicles {
        assert!(
            v.pose_nees_in_band >= min,
            "{}: pose NEES inside the χ² band only {:.0} % of the time",
            v.name,
            100.0 * v.pose_nees_in_band
        );
    }
}
