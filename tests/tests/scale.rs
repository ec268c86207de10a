//! Scale suite: 24- and 64-vehicle tree teams (`canopy team N`) run as N vehicle processes plus
//! the world and the monitor over iceoryx2 shared memory, for a short simulated time, and must be
//! sound ([`procs::assert_sound`]: clean exits, no lost sensor batch or rejected input, never
//! more confident than the centralized reference, consistent NEES) with every vehicle
//! reporting to the end, fusing its neighbours' information, and holding every feature a
//! neighbour held long enough before the end for one hop of fusion to carry it (a bound from
//! the run's own timing, not a share of the team's map: see [`hop_window_s`]).

mod procs;

use std::collections::{BTreeMap, BTreeSet};

use canopy_node::scenario::Scenario;
use canopy_node::team::team_scenario;
use procs::{Run, assert_sound, run, serial};

/// Simulated seconds: 20 fusion rounds at 1 Hz, 2000 IMU samples per vehicle; long enough
/// that the features held 7 s ([`hop_window_s`]) before the end are checked on every link.
const DURATION_S: f64 = 20.0;

/// 24 vehicles: beyond iceoryx2's default of 20 nodes per service.
#[test]
fn twenty_four_vehicle_processes_run_soundly() {
    check_team(24);
}

/// 64 vehicles, the most `canopy team` generates (issue #15): 66 processes on one host, each
/// with its own iceoryx2 node, within the file-descriptor and node limits canopy configures.
#[test]
fn sixty_four_vehicle_processes_run_soundly() {
    check_team(64);
}

/// The longest a feature can take, in simulation time, from the first map report of a vehicle
/// that holds it to the first report of a neighbour that fused it — derived from the run's own
/// settings, not from how fast this machine happened to be:
/// - the holder sends it at its next fusion round: ≤ one fusion period after it holds it;
/// - when that delta arrives the receiver's clock is at most `max_lead_s` ahead of the sender's
///   (the world never runs more than `max_lead_s` ahead of the slowest vehicle);
/// - the receiver fuses it at its next round (≤ one period; its estimator does not run past a
///   terrain frame while a round is out) and reports it at its next record time (≤ one record
///   interval);
/// - map reports are taken at record times, so both ends' `held_since` are rounded up to one
///   record interval each.
///
/// The sum, plus one more fusion period of margin for a round whose fused copy comes back just
/// after a record time.
fn hop_window_s(s: &Scenario) -> f64 {
    let period = 1.0 / s.fusion.rate_hz;
    let record = s.run.record_interval_s;
    3.0 * period + s.run.max_lead_s + 2.0 * record
}

/// Final map of every vehicle: true feature id → held since [s] (map.csv `truth_id`: the
/// vehicles key their maps by their own keys, which differ between neighbours until a
/// correspondence is adopted and told).
fn final_maps(r: &Run) -> BTreeMap<String, BTreeMap<u64, f64>> {
    let mut maps: BTreeMap<String, BTreeMap<u64, f64>> = BTreeMap::new();
    for row in r.csv("map.csv") {
        let id: u64 = row["truth_id"].parse().expect("truth id");
        let held: f64 = row["held_since_s"].parse().expect("held_since_s");
        maps.entry(row["vehicle"].clone())
            .or_default()
            .insert(id, held);
    }
    maps
}

fn check_team(team: u32) {
    let _machine = serial();
    let dir = tempfile::tempdir().expect("temp dir");
    let file = dir.path().join(format!("tree-{team}.toml"));
    std::fs::write(&file, team_scenario(team, DURATION_S).to_toml_string()).expect("write");
    let r = run(&file, &["--quiet"]);
    assert_sound(&r);

    assert_eq!(r.summary.vehicles.len(), team as usize);
    let vehicle_exits = r
        .checks
        .processes
        .iter()
        .filter(|p| p.name.starts_with("uav"))
        .count();
    assert_eq!(vehicle_exits, team as usize, "one process per vehicle");
    for v in &r.checks.vehicles {
        // Every vehicle reported up to the end of the stream (records every 1 s; the last
        // one at the end).
        assert!(
            v.last_report_t >= DURATION_S - 1.0,
            "{} last reported at {:.1} s",
            v.name,
            v.last_report_t
        );
        let c = v.counters.last().expect("counters");
        // 100 Hz for 20 s, minus at most the first samples before the initial estimate.
        assert!(
            c.imu_samples >= 1990,
            "{}: {} IMU samples",
            v.name,
            c.imu_samples
        );
        assert!(c.fused > 0, "{} never fused a neighbour's delta", v.name);
        assert_eq!(c.messages_rejected, 0, "{}: DDF messages rejected", v.name);
    }
    // Every feature a neighbour held by the end minus one hop's window is held at the end
    // (fusion carried it across the link), on every tree link (uav i ↔ uav ⌊i/2⌋), both ways.
    let scenario = team_scenario(team, DURATION_S);
    let window = hop_window_s(&scenario);
    let maps = final_maps(&r);
    let empty = BTreeMap::new();
    let mut checked = 0usize;
    let mut missing = Vec::new();
    for i in 2..=team {
        let (a, b) = (format!("uav{i}"), format!("uav{}", i / 2));
        for (from, to) in [(&a, &b), (&b, &a)] {
            let held_to: BTreeSet<u64> = maps.get(to).unwrap_or(&empty).keys().copied().collect();
            for (&f, &since) in maps.get(from).unwrap_or(&empty) {
                if since <= DURATION_S - window {
                    checked += 1;
                    if !held_to.contains(&f) {
                        missing.push(format!(
                            "{to} lacks feature {f} that {from} held since {since} s"
                        ));
                    }
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "{} of {checked} (link, feature) pairs missing (window {window} s): {:?}",
        missing.len(),
        &missing[..missing.len().min(20)]
    );
    // Not vacuous: every link carried features that old enough, both ways, on average.
    assert!(
        checked >= 2 * (team as usize - 1),
        "only {checked} (link, feature) pairs were old enough to check (window {window} s)"
    );
    // Every link end saw its peer (team − 1 tree links, two ends each).
    assert_eq!(r.checks.link_ends.len(), 2 * (team as usize - 1));
    for l in &r.checks.link_ends {
        assert!(
            l.report.received_messages > 0,
            "{} never heard from {}",
            l.node,
            l.peer
        );
    }
}
