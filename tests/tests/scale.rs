//! Scale suite: a 24-vehicle tree team (`canopy team 24`) runs as 24 vehicle processes plus the
//! world and the monitor over iceoryx2 shared memory, for a short simulated time, and must be
//! sound ([`procs::assert_sound`]: clean exits, no lost sensor batch or rejected input, never
//! more confident than the centralized reference, consistent NEES) with every vehicle
//! reporting to the end, fusing its neighbours' information and holding the team's map.

mod procs;

use canopy_node::team::team_scenario;
use procs::{assert_sound, run, serial};

/// Vehicles of the team (beyond iceoryx2's default of 20 nodes per service).
const TEAM: u32 = 24;
/// Simulated seconds: 15 fusion rounds at 1 Hz, 1500 IMU samples per vehicle (≈ 20 s wall
/// on a 2-core machine).
const DURATION_S: f64 = 15.0;

#[test]
fn twenty_four_vehicle_processes_run_soundly() {
    let _machine = serial();
    let dir = tempfile::tempdir().expect("temp dir");
    let file = dir.path().join("tree-24.toml");
    std::fs::write(&file, team_scenario(TEAM, DURATION_S).to_toml_string()).expect("write");
    let r = run(&file, &["--quiet"]);
    assert_sound(&r);

    assert_eq!(r.summary.vehicles.len(), TEAM as usize);
    let vehicle_exits = r
        .checks
        .processes
        .iter()
        .filter(|p| p.name.starts_with("uav"))
        .count();
    assert_eq!(vehicle_exits, TEAM as usize, "one process per vehicle");
    // The largest team map any vehicle holds at the end (the union the team has built).
    let team_map = r
        .checks
        .vehicles
        .iter()
        .map(|v| v.final_map_features)
        .max()
        .unwrap_or(0);
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
        // 100 Hz for 15 s, minus at most the first sample before the initial estimate.
        assert!(
            c.imu_samples >= 1490,
            "{}: {} IMU samples",
            v.name,
            c.imu_samples
        );
        assert!(c.fused > 0, "{} never fused a neighbour's delta", v.name);
        assert_eq!(c.messages_rejected, 0, "{}: DDF messages rejected", v.name);
        // The tree spreads every vehicle's features to all in a few rounds; after 15 rounds each
        // holds nearly the team's map (the last deltas may still be in flight: 80 %).
        assert!(
            v.final_map_features * 5 >= team_map * 4,
            "{} holds {} features of the team's {}",
            v.name,
            v.final_map_features,
            team_map
        );
    }
    // Every link end saw its peer (23 tree links, two ends each).
    assert_eq!(r.checks.link_ends.len(), 2 * (TEAM as usize - 1));
    for l in &r.checks.link_ends {
        assert!(
            l.report.received_messages > 0,
            "{} never heard from {}",
            l.node,
            l.peer
        );
    }
}
