//! Data sharing (`[fusion] mode = "shared_data"`, issue 13; docs/arch/sharing.md) in
//! `canopy sim`: every vehicle's data relayed over the tree and every vehicle running the
//! team's EKF on all of it.
//!
//! It proves, on the shipped `topologies/shared-data-8k.toml` and on the range-limited radio
//! team switched to data sharing, over the 300 s: each vehicle's final map is the centralized all-data reference's (pooled map
//! RMSE within 5 %, map and pose ANEES within 10 % of the reference's), no vehicle is ever
//! more confident about a feature than the reference, no association is wrong, and every link
//! end stays within its radio's capacity (mean and every ten-second window) — at 8 kB/s, the
//! issue's goal beyond, and over range-limited links that drop and come back. The reference
//! is an independent filter (one EKF fed every sample in time order, with the true ids); the
//! vehicles get the data late, out of order across vehicles, with remote IMU in 0.1-s
//! increments and appearance association, so equality is not built in: a stream lost, applied
//! twice or out of order shows as a larger RMSE or ANEES.
//!
//! And `topologies/shared-data-8k.toml` as real processes (`canopy run`: one process per
//! vehicle over iceoryx2 with the radio model in each link end, the estimator and the relay on
//! the vehicle's two threads): the run is sound ([`procs::assert_sound`]), the team's map is
//! the reference's within the same 5 %, and every link end stays within 8 kB/s; and the
//! range-limited team the same way, with the outage suite's checks ([`procs::assert_sound`]).

mod procs;

use std::collections::BTreeMap;

use canopy_node::network::FusionMode;
use canopy_node::record::{LinkRecord, VehicleRecord};
use canopy_node::scenario::Scenario;
use canopy_node::sim::{SimOptions, SimOutcome, simulate};
use canopy_tests::montecarlo::{map_consistency, pose_consistency};

/// The duration.
const DURATION: f64 = 300.0;
/// Largest team map RMSE / reference: measured 1.002 (radio-8k) and 1.007 (radio-range). The
/// vehicles' filters are the reference's EKF on the same data, linearised in another order
/// (remote data arrives a round per hop late) with remote IMU in 0.1-s increments; 5 % bounds
/// that, while a lost stream (a vehicle's frames missing from the others' maps) or one applied
/// twice moves it by far more (decentralized channel filters at 8 kB/s: 1.02–1.18).
const MAX_MAP_RATIO: f64 = 1.05;
/// Largest map or pose ANEES / the reference's: the bar (1.1× the exact run's).
const MAX_ANEES_RATIO: f64 = 1.1;
/// Largest λ_max(P_ref P_i⁻¹) over features and record times: linearisation points differ
/// between the filters (the decentralized suite's bound, tests/tests/mc_team.rs); counting
/// data twice would show as ≈ 2.
const MAX_CONFIDENCE_RATIO: f64 = 1.2;

fn load(path: &str) -> Scenario {
    let file = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(path);
    let mut s = Scenario::load(&file).expect("scenario loads");
    s.fusion.mode = FusionMode::SharedData;
    s.run.duration_s = DURATION;
    s
}

fn run(s: &Scenario) -> SimOutcome {
    simulate(
        s,
        SimOptions {
            baseline: Some(true),
            ..SimOptions::default()
        },
    )
    .expect("simulation runs")
}

/// Largest mean and ten-second-window rate [bytes/s] any end of `link` sent.
fn rates(link: &LinkRecord) -> (f64, f64) {
    let mut mean: f64 = 0.0;
    let mut window: f64 = 0.0;
    for end in [0, 1] {
        let series: Vec<(f64, f64)> = link
            .samples
            .iter()
            .map(|x| (x.t, if end == 0 { x.bytes_ab } else { x.bytes_ba } as f64))
            .collect();
        if let Some(&(t, b)) = series.last() {
            mean = mean.max(b / t);
        }
        for w in series.windows(11) {
            let (t0, b0) = w[0];
            let (t1, b1) = w[10];
            window = window.max((b1 - b0) / (t1 - t0));
        }
    }
    (mean, window)
}

/// No `share.*` rejection among a vehicle's rejections by reason.
fn assert_no_shared_record_refused(who: &str, rejections: &BTreeMap<String, u64>) {
    let refused: u64 = rejections
        .iter()
        .filter(|(k, _)| k.starts_with("share."))
        .map(|(_, n)| n)
        .sum();
    assert_eq!(refused, 0, "{who}: shared records refused: {rejections:?}");
}

/// The checks of the module docs on one run; returns (map ratio, busiest mean, busiest window).
fn assert_is_the_reference(name: &str, o: &SimOutcome, capacity: f64) -> (f64, f64, f64) {
    let vehicles: Vec<&VehicleRecord> = o.record.vehicles.iter().collect();
    let reference = o.record.baseline.as_ref().expect("the reference ran");
    let ours = map_consistency(&vehicles);
    let theirs = map_consistency(&[&reference[0]]);
    let pose_ours = pose_consistency(&vehicles, 0.0).time_mean;
    let pose_theirs = pose_consistency(&reference.iter().collect::<Vec<_>>(), 0.0).time_mean;
    let ratio = ours.rmse / theirs.rmse;
    let confidence = o
        .checks
        .confidence_ratio
        .iter()
        .map(|x| x.1)
        .fold(0.0, f64::max);
    let wrong: u64 = vehicles
        .iter()
        .map(|v| v.association.wrong_associations)
        .sum();
    let (mut mean, mut window) = (0.0_f64, 0.0_f64);
    for l in &o.record.links {
        let (m, w) = rates(l);
        mean = mean.max(m);
        window = window.max(w);
    }
    println!(
        "{name}: map RMSE {:.3} m (reference {:.3}, {ratio:.3}×), map ANEES {:.3} ({:.3}), \
         pose ANEES {pose_ours:.3} ({pose_theirs:.3}), confidence ratio ≤ {confidence:.3}, \
         busiest link end {mean:.0} B/s mean, {window:.0} B/s over 10 s",
        ours.rmse, theirs.rmse, ours.anees, theirs.anees
    );
    assert!(
        ratio <= MAX_MAP_RATIO,
        "{name}: map RMSE {ratio:.3}× the reference"
    );
    assert!(
        ours.anees <= MAX_ANEES_RATIO * theirs.anees,
        "{name}: map ANEES {:.3} against the reference's {:.3}",
        ours.anees,
        theirs.anees
    );
    assert!(
        pose_ours <= MAX_ANEES_RATIO * pose_theirs,
        "{name}: pose ANEES {pose_ours:.3} against the reference's {pose_theirs:.3}"
    );
    assert!(
        confidence <= MAX_CONFIDENCE_RATIO,
        "{name}: a vehicle was {confidence:.3}× more confident than the reference"
    );
    assert_eq!(wrong, 0, "{name}: wrong associations");
    assert!(
        mean <= capacity,
        "{name}: a link end averaged {mean:.0} B/s"
    );
    assert!(
        window <= capacity,
        "{name}: a link end sent {window:.0} B/s over 10 s"
    );
    for v in &vehicles {
        assert_no_shared_record_refused(&format!("{name}: {}", v.name), &v.rejections);
    }
    (ratio, mean, window)
}

/// Over 8 kB/s radios (the goal beyond: ≤ 8 kB/s per link at ≤ 1.25× the
/// reference), each vehicle holds the reference's map: the shipped
/// `topologies/shared-data-8k.toml`.
#[test]
fn shared_data_over_8k_radios_is_the_reference() {
    let s = load("topologies/shared-data-8k.toml");
    let o = run(&s);
    assert_is_the_reference("radio-8k", &o, 8_000.0);
}

/// Over range-limited radios (`topologies/radio-range.toml`: a link is up only while its two
/// vehicles are within 1200 m), the records lost while a link was out of range are sent
/// again when it is back, and each vehicle still ends with the reference's map. Premise
/// asserted: the links did drop messages.
#[test]
fn shared_data_over_range_limited_radios_catches_up() {
    let s = load("topologies/radio-range.toml");
    let capacity = s
        .links
        .iter()
        .filter_map(|l| l.radio.as_ref().map(|r| r.bytes_per_s))
        .fold(f64::INFINITY, f64::min);
    let o = run(&s);
    let drops: u64 = o
        .record
        .links
        .iter()
        .filter_map(|l| l.samples.last().map(|x| x.drops))
        .sum();
    assert!(
        drops > 0,
        "the premise: range-limited links dropped messages"
    );
    assert_is_the_reference("radio-range", &o, capacity);
}

/// Team map RMSE (every vehicle's final map, pooled) and the centralized reference's [m], of a
/// multi-process run.
fn team_and_reference_rmse(r: &procs::Run) -> (f64, f64) {
    let pooled = |m: &mut dyn Iterator<Item = &BTreeMap<u64, (f64, f64, f64)>>| {
        let errs: Vec<f64> = m
            .flat_map(|x| x.values().map(|v| v.1))
            .filter(|e| e.is_finite())
            .collect();
        (errs.iter().map(|e| e * e).sum::<f64>() / errs.len().max(1) as f64).sqrt()
    };
    let maps = r.maps();
    let base = pooled(&mut maps.get("baseline").into_iter());
    let team = pooled(
        &mut maps
            .iter()
            .filter(|(k, _)| k.as_str() != "baseline")
            .map(|(_, m)| m),
    );
    (team, base)
}

/// `topologies/shared-data-8k.toml` as real processes (module docs).
#[test]
fn shared_data_8k_runs_as_processes() {
    let _g = procs::serial();
    let file = procs::topology("shared-data-8k.toml");
    let r = procs::run(&file, &["--quiet"]);
    r.print_standing("shared-data-8k");
    procs::assert_sound(&r);
    let (team, base) = team_and_reference_rmse(&r);
    let ratio = team / base;
    let duration = r.summary.duration_s;
    let mut busiest: f64 = 0.0;
    for e in &r.checks.link_ends {
        let rate = e.report.sent_bytes as f64 / duration;
        busiest = busiest.max(rate);
        assert!(rate <= 8_000.0, "{}->{}: {rate:.0} B/s", e.node, e.peer);
    }
    eprintln!(
        "shared-data-8k as processes: team map RMSE {team:.3} m, reference {base:.3} m \
         ({ratio:.3}×), busiest link end {busiest:.0} B/s"
    );
    assert!(
        ratio <= MAX_MAP_RATIO,
        "team map RMSE {ratio:.3}× the reference"
    );
    for v in &r.checks.vehicles {
        for c in &v.counters {
            assert_no_shared_record_refused(&v.name, &c.rejections);
        }
    }
}

/// `topologies/NAME` with `mode = "shared_data"`, run as real processes with `args`.
fn run_shared_as_processes(name: &str, args: &[&str]) -> procs::Run {
    let text = std::fs::read_to_string(procs::topology(name)).expect("reads");
    assert!(
        text.contains("mode = \"decentralized\""),
        "{name}: a decentralized team"
    );
    let file = std::env::temp_dir().join(format!("canopy-shared-{}-{name}", std::process::id()));
    std::fs::write(
        &file,
        text.replace("mode = \"decentralized\"", "mode = \"shared_data\""),
    )
    .expect("writes");
    let r = procs::run(&file, args);
    let _ = std::fs::remove_file(&file);
    r
}

/// Outage-suite checks on a shared-data run: sound ([`procs::assert_sound`]: clean processes,
/// no lost input, never more confident than the reference, pose NEES in band), the team's map
/// within [`MAX_MAP_RATIO`] of the reference's, and the premise that the faults happened
/// (messages dropped, or a link reported down at some record time).
fn assert_survives(label: &str, r: &procs::Run) {
    r.print_standing(label);
    procs::assert_sound(r);
    let drops: u64 = r
        .checks
        .link_ends
        .iter()
        .map(|e| e.report.dropped_faults)
        .sum();
    // A link reported down after the start (every link is down in the first sample, before
    // it connects).
    let down = r
        .csv("links.csv")
        .iter()
        .any(|row| row["up"] == "0" && row["t"].parse::<f64>().is_ok_and(|t| t >= 5.0));
    let (team, base) = team_and_reference_rmse(r);
    eprintln!(
        "{label} (shared data, processes): team map RMSE {team:.3} m, reference {base:.3} m \
         ({:.3}×), {drops} drops, a link down: {down}",
        team / base
    );
    assert!(
        drops > 0 || down,
        "{label}: the premise, faults that drop or cut links"
    );
    assert!(
        team / base <= MAX_MAP_RATIO,
        "{label}: team map RMSE {:.3}× the reference",
        team / base
    );
}

/// `topologies/radio-range.toml` switched to data sharing, as real processes over 300 s: links
/// go out of range and come back, and the run passes the outage suite's checks
/// ([`assert_survives`]; measured 1.005× the reference, 155 drops).
#[test]
fn shared_data_over_range_limited_radios_runs_as_processes() {
    let _g = procs::serial();
    let r = run_shared_as_processes("radio-range.toml", &["--quiet", "--duration", "300"]);
    assert_survives("radio-range", &r);
}

/// The outage suite's fault scenarios (`outage-long`, `outage-flapping`, `partition-heal`,
/// `lossy`) switched to data sharing, as real processes: each passes [`assert_survives`] —
/// the relay sends again what an outage, a partition or a loss took, and each vehicle still
/// ends with the reference's map (measured 0.997–1.020×).
#[test]
fn shared_data_survives_the_outage_scenarios() {
    let _g = procs::serial();
    for name in [
        "outage-long.toml",
        "outage-flapping.toml",
        "partition-heal.toml",
        "lossy.toml",
    ] {
        let r = run_shared_as_processes(name, &["--quiet"]);
        assert_survives(name, &r);
    }
}

/// Largest team map RMSE / reference for a team whose hub restarts: measured 1.093 as
/// processes and 1.099 in `canopy sim` (the channel filters: 1.053 and 1.045). The restart
/// marginalises the hub's old vehicle state out of every team filter (what it knew of its own
/// motion is given up) and the restarted hub does not apply its own earlier stream; 1.2 keeps
/// the guard below isolated vehicles (~1.4×) while allowing for process timing.
const MAX_MAP_RATIO_RESTART: f64 = 1.2;

/// `topologies/crash-restart.toml` switched to data sharing, as real processes: uav3, the hub,
/// is killed at 30 s and restarted at 40 s with a new epoch from an external fix. The run is
/// sound, the launcher reports the kill, the new incarnation applies the team's records and
/// exits cleanly at the end, every team filter takes the new incarnation's stream
/// as a restart (its start replaces the old vehicle state, marginalised out), the relay sends
/// the restarted hub every stream again, and the team map stays within
/// [`MAX_MAP_RATIO_RESTART`] of the reference's.
#[test]
fn shared_data_survives_a_hub_restart() {
    let _g = procs::serial();
    let r = run_shared_as_processes("crash-restart.toml", &["--quiet"]);
    r.print_standing("crash-restart");
    procs::assert_sound(&r);
    // The launcher killed uav3's first process and the second ran to the end, cleanly, and
    // applied the team's records again.
    procs::assert_process_restarted(&r, "uav3", 90.0);
    let (team, base) = team_and_reference_rmse(&r);
    eprintln!(
        "crash-restart (shared data, processes): team map RMSE {team:.3} m, reference \
         {base:.3} m ({:.3}×)",
        team / base
    );
    assert!(
        team / base <= MAX_MAP_RATIO_RESTART,
        "team map RMSE {:.3}× the reference",
        team / base
    );
}

/// Seeds of the SLAM Monte Carlo below.
const SEEDS: u64 = 6;
/// Its simulated seconds per run (as tests/tests/mc_team.rs: every UAV's map overlaps its
/// neighbours' within the first minute).
const MC_DURATION: f64 = 120.0;

/// The SLAM Monte Carlo of data sharing: the default team (tree-4) over 8 kB/s radios in
/// `shared_data` mode, six seeds (each a new world and new noise), against the centralized
/// reference of the same seed. Pooled over the seeds: map RMSE within 5 % of the reference's,
/// map and pose ANEES within 10 % of the reference's (a stream applied twice would halve the
/// vehicles' covariances and double the ANEES; a lost one would raise the RMSE), no vehicle
/// ever more than 1.2× as confident as the reference about a feature, no wrong association,
/// and every link end within 8 kB/s on every seed.
#[test]
fn shared_data_slam_monte_carlo() {
    let mut vehicles = Vec::new();
    let mut references = Vec::new();
    let mut outcomes = Vec::new();
    for seed in 1..=SEEDS {
        let mut s = load("topologies/shared-data-8k.toml");
        s.world.seed = seed;
        s.run.duration_s = MC_DURATION;
        outcomes.push(run(&s));
    }
    for o in &outcomes {
        vehicles.extend(o.record.vehicles.iter());
        let reference = o.record.baseline.as_ref().expect("the reference ran");
        references.extend(reference.iter());
    }
    // The reference's map is one joint map: once per seed.
    let reference_maps: Vec<&VehicleRecord> = outcomes
        .iter()
        .map(|o| &o.record.baseline.as_ref().expect("the reference ran")[0])
        .collect();
    let (ours, theirs) = (map_consistency(&vehicles), map_consistency(&reference_maps));
    let pose = |rs: &[&VehicleRecord]| {
        rs.iter()
            .map(|r| canopy_node::output::summary::summarize_vehicle(r).pose_anees)
            .sum::<f64>()
            / rs.len() as f64
    };
    let (pose_ours, pose_theirs) = (pose(&vehicles), pose(&references));
    let confidence = outcomes
        .iter()
        .flat_map(|o| o.checks.confidence_ratio.iter().map(|p| p.1))
        .fold(0.0, f64::max);
    let wrong: u64 = vehicles
        .iter()
        .map(|v| v.association.wrong_associations)
        .sum();
    let busiest = outcomes
        .iter()
        .flat_map(|o| o.record.links.iter())
        .map(|l| rates(l).1)
        .fold(0.0, f64::max);
    println!(
        "{SEEDS} seeds × {MC_DURATION} s, shared data over 8 kB/s: map RMSE {:.3} m against the \
         reference's {:.3} ({:.3}×), map ANEES {:.3} ({:.3}), pose ANEES {pose_ours:.3} \
         ({pose_theirs:.3}), confidence ratio ≤ {confidence:.3}, wrong associations {wrong}, \
         busiest 10-s window {busiest:.0} B/s",
        ours.rmse,
        theirs.rmse,
        ours.rmse / theirs.rmse,
        ours.anees,
        theirs.anees
    );
    assert!(ours.rmse <= MAX_MAP_RATIO * theirs.rmse);
    assert!(ours.anees <= MAX_ANEES_RATIO * theirs.anees);
    assert!(pose_ours <= MAX_ANEES_RATIO * pose_theirs);
    assert!(confidence <= MAX_CONFIDENCE_RATIO);
    assert_eq!(wrong, 0);
    assert!(busiest <= 8_000.0);
}
