//! Radio-link suite (issue #13): the shipped `topologies/radio-32k.toml` — the tree-4 team with
//! every link a 32 kB/s radio (one-second drop-tail queue, 20 ms latency) — runs as real
//! processes (world, one process per vehicle, over iceoryx2 with the transport's radio model
//! in each end's fault layer, on the vehicles' simulation clocks). Every link runs the
//! sparsified channel filter (the default `fusion = "sparse"`): exact deltas while they fit,
//! otherwise the delta's marginal on the features that fit, each round within a budget derived
//! from the capacity and the link's outbound queue.
//!
//! It proves: the run is sound ([`procs::assert_sound`]: no vehicle ever more confident about a
//! feature than the centralized all-data reference, clean processes, no lost input); no link
//! switched to CI, every end sent deltas and the links sparsified; the bytes each end sent stay
//! within the capacity (mean over the run, and every 10 s window of links.csv); the drop-tail
//! queue dropped few messages; and the team's map RMSE is within the guard below of the
//! reference's. Until the sparsified marginal's vector was gated (`sparse::VECTOR_GATE_PROBABILITY`,
//! docs/arch/ddf.md "Sparsified links") a vehicle's pose and map drifted together by metres per
//! round in about one run of ninety (one in thirty on a loaded machine), and this test failed
//! on the pose consistency, as it should.
//!
//! `topologies/radio-range.toml` (the same team, links up only within 1200 m): each link is
//! reported down exactly while its vehicles are out of range, within its capacity, and no
//! vehicle is more confident about a feature than the reference; and the outage suite's full
//! consistency checks hold, the late-joining vehicle's pose included ([`radio_range_is_sound`]).

mod procs;

use std::collections::BTreeMap;

use canopy_node::network::node_names;
use canopy_node::radio::TrueSeparation;
use canopy_node::scenario::Scenario;
use canopy_transport::fault::Separation;
use procs::{
    assert_clean_and_never_over_confident, assert_in_band, assert_sound, run, serial, topology,
};

/// Capacity of each direction of every radio-32k link [bytes/s] (the scenario's `radio`).
const CAPACITY: f64 = 32_000.0;
/// Queue of each direction [bytes] (the scenario's `queue_bytes`).
const QUEUE: f64 = 32_000.0;
/// Largest team map RMSE / reference accepted (pooled final maps). Not the 1.15 (its
/// bar is for 300 s: `canopy sim` 1.12, `canopy run` 1.11, 1.11, 1.17; docs/benchmarks.md):
/// this 90 s team is mid-catch-up and its multi-process runs spread with process timing —
/// 1.16, 1.26, 1.28 on 2026-12-05 with the machine loaded (0.99 idle with an earlier build of
/// the day; 1.05–1.48 before the regularisation was booked, docs/arch/ddf.md). 2.0 keeps the
/// guard below isolated vehicles (2.15 in `canopy sim`) and CI on these links (2.90 in
/// `canopy sim`, 3.20–5.63 multi-process), with a margin of 0.7 over the largest run seen; it
/// also catches a diverged map (before the negative-marginal refusal uav1's map RMSE was
/// 816 m, 198×).
const MAX_MAP_RATIO: f64 = 2.0;
/// Window over which links.csv's sent bytes are compared with the capacity [s]: ten rounds.
const WINDOW_S: f64 = 10.0;

/// Pooled RMS of the final map errors of `maps` (map.csv rows with a finite error).
fn pooled_rmse<'a>(maps: impl IntoIterator<Item = &'a BTreeMap<u64, (f64, f64, f64)>>) -> f64 {
    let errs: Vec<f64> = maps
        .into_iter()
        .flat_map(|m| m.values().map(|v| v.1))
        .filter(|e| e.is_finite())
        .collect();
    (errs.iter().map(|e| e * e).sum::<f64>() / errs.len().max(1) as f64).sqrt()
}

/// Team map RMSE (every vehicle's final map, pooled) and the centralized reference's [m].
fn team_and_reference_rmse(r: &procs::Run) -> (f64, f64) {
    let maps = r.maps();
    let base = pooled_rmse(maps.get("baseline"));
    let team = pooled_rmse(
        maps.iter()
            .filter(|(k, _)| k.as_str() != "baseline")
            .map(|(_, m)| m),
    );
    (team, base)
}

#[test]
fn radio_32k() {
    let _g = serial();
    let file = topology("radio-32k.toml");
    let s = Scenario::load(&file).expect("loads");
    for l in &s.links {
        let r = l.radio.as_ref().expect("every link is a radio");
        assert_eq!(
            (r.bytes_per_s, r.queue_bytes(&s.fusion) as f64),
            (CAPACITY, QUEUE)
        );
    }
    let r = run(&file, &["--quiet"]);
    r.print_standing("radio-32k");
    assert_sound(&r);

    // Sparsified channel filters on every link, both directions: deltas flow, never CI, and
    // the capacity forced sparsified rounds.
    let mut sparsified = 0;
    for l in &r.summary.links {
        assert!(!l.ci, "{} switched to CI", l.link);
    }
    for e in &r.checks.link_ends {
        let c = &e.report.channel;
        assert!(!e.report.ci, "{}->{}: CI", e.node, e.peer);
        assert!(c.deltas_sent > 0, "{}->{}: no delta sent", e.node, e.peer);
        assert_eq!(c.submaps_sent, 0, "{}->{}: submaps sent", e.node, e.peer);
        eprintln!(
            "radio-32k {}->{}: {} deltas sent, {} of them sparsified ({} regularised beyond the \
             floor, {} with the vector gated), {} features new to the peer held back, {} rounds \
             refused, {} starved",
            e.node,
            e.peer,
            c.deltas_sent,
            c.sparse_deltas,
            c.sparse_regularised,
            c.sparse_vector_dropped,
            c.sparse_withheld_new,
            c.sparse_refused,
            c.budget_starved
        );
        sparsified += c.sparse_deltas;
    }
    assert!(
        sparsified > 0,
        "the capacity never forced a sparsified delta"
    );

    // Bytes per second each end offered: the mean over the run within the capacity.
    let duration = r.summary.duration_s;
    let mut drops = 0;
    let mut received = 0;
    for e in &r.checks.link_ends {
        let rate = e.report.sent_bytes as f64 / duration;
        eprintln!(
            "radio-32k {}->{}: {:.0} B/s sent ({:.0} % of {CAPACITY} B/s), {} messages \
             received, {} dropped by the queue (drop-tail)",
            e.node,
            e.peer,
            rate,
            100.0 * rate / CAPACITY,
            e.report.received_messages,
            e.report.dropped_faults
        );
        assert!(rate <= CAPACITY, "{}->{}: {rate:.0} B/s", e.node, e.peer);
        drops += e.report.dropped_faults;
        received += e.report.received_messages;
    }
    // Every 10 s window of links.csv (per direction, cumulative bytes sampled each second):
    // at most the capacity plus one queue's worth, the most a drop-tail channel accepts
    // beyond its drain in a window (the queue may fill in it).
    let mut series: BTreeMap<(String, &str), Vec<(f64, f64)>> = BTreeMap::new();
    for row in r.csv("links.csv") {
        let t: f64 = row["t"].parse().expect("t");
        for dir in ["bytes_ab", "bytes_ba"] {
            let b: f64 = row[dir].parse().expect("bytes");
            series
                .entry((row["link"].clone(), dir))
                .or_default()
                .push((t, b));
        }
    }
    assert_eq!(series.len(), 2 * s.links.len(), "links.csv directions");
    for ((link, dir), pts) in &series {
        let mut worst: f64 = 0.0;
        for (i, &(t0, b0)) in pts.iter().enumerate() {
            if let Some(&(t1, b1)) = pts[i..].iter().find(|p| p.0 >= t0 + WINDOW_S - 1e-6) {
                worst = worst.max((b1 - b0) / (t1 - t0));
                assert!(
                    b1 - b0 <= CAPACITY * (t1 - t0) + QUEUE,
                    "{link} {dir}: {:.0} bytes in [{t0}, {t1}] s",
                    b1 - b0
                );
            }
        }
        eprintln!("radio-32k {link} {dir}: busiest {WINDOW_S} s window {worst:.0} B/s");
    }
    // Drop-tail drops small: the budget keeps each round within a round's drain, so the
    // queue overflows only when a round's messages land on a backlog the sender's mirror
    // did not see (clock skew between processes); at most 1 % of the messages.
    let drop_fraction = drops as f64 / (drops + received).max(1) as f64;
    eprintln!(
        "radio-32k: {drops} drop-tail drops of {} messages",
        drops + received
    );
    assert!(
        drop_fraction <= 0.01,
        "drop-tail dropped {drop_fraction:.3}"
    );

    // Team map RMSE (every vehicle's final map, pooled) against the centralized reference.
    let (team, base) = team_and_reference_rmse(&r);
    let ratio = team / base;
    // Guard: MAX_MAP_RATIO (see its comment for the measured figures and the margin).
    eprintln!("radio-32k: team map RMSE {team:.2} m, reference {base:.2} m, ratio {ratio:.2}");
    assert!(
        ratio <= MAX_MAP_RATIO,
        "team map RMSE {team:.2} m is {ratio:.2}× the reference's {base:.2} m"
    );
}

/// In-band fraction required of the pose NEES, as in the outage suite (tests/tests/outage.rs
/// `IN_BAND`: 95 % for an ideal filter; correlated samples and EKF-SLAM's mild
/// over-confidence, the reference itself 87–100 %).
const IN_BAND: f64 = 0.8;

/// Distance from the range within which a links.csv sample may show either state [m]: the
/// samples are 1 s apart and the ends' clocks may differ by a round, and two vehicles at
/// 25 m/s close or open at most 50 m/s.
const RANGE_SETTLE_M: f64 = 100.0;

/// radio-range.toml: the links follow the vehicles' true separation (down beyond 1200 m, up
/// within it), some link goes both down and up during the run, every end stays within the
/// capacity, and [`procs::assert_clean_and_never_over_confident`] holds (clean processes, no
/// lost input, no vehicle ever more confident about a feature than the centralized
/// reference). The outage suite's pose checks are [`radio_range_is_sound`]'s.
#[test]
fn radio_range_links_follow_the_separation() {
    let _g = serial();
    let file = topology("radio-range.toml");
    let s = Scenario::load(&file).expect("loads");
    let r = run(&file, &["--quiet"]);
    r.print_standing("radio-range");
    assert_clean_and_never_over_confident(&r);
    let (mut downs, mut ups) = (0, 0);
    for l in &s.links {
        let radio = l.radio.as_ref().expect("every link is a radio");
        let range = radio.range_m.expect("range-limited");
        let link = l.label(&node_names(&s));
        let sep = TrueSeparation::new(&s, [l.a, l.b]).expect("trajectories");
        let samples = r.link_up(&link);
        assert!(!samples.is_empty(), "no samples of {link}");
        let (mut down_s, mut up_s) = (0, 0);
        for (t, up) in samples {
            // t = 0 is written before the first Hello: no link is up yet.
            if t < 1.5 {
                continue;
            }
            let d = sep.distance_m(t);
            if d > range + RANGE_SETTLE_M {
                assert!(!up, "{link} up at {t} s with its vehicles {d:.0} m apart");
                down_s += 1;
            } else if d < range - RANGE_SETTLE_M {
                assert!(up, "{link} down at {t} s with its vehicles {d:.0} m apart");
                up_s += 1;
            }
        }
        eprintln!("radio-range {link}: {up_s} samples up in range, {down_s} down out of range");
        downs += usize::from(down_s > 0);
        ups += usize::from(up_s > 0);
    }
    assert!(downs > 0 && ups > 0, "no link went out of and into range");
    for e in &r.checks.link_ends {
        let rate = e.report.sent_bytes as f64 / r.summary.duration_s;
        assert!(rate <= CAPACITY, "{}->{}: {rate:.0} B/s", e.node, e.peer);
    }
    let (team, base) = team_and_reference_rmse(&r);
    // Printed, not judged: a few features started from weak marginals just before a link went
    // out of range keep σ of 0.5–0.7 km (consistent, but they dominate a pooled RMSE;
    // docs/arch/ddf.md).
    eprintln!(
        "radio-range: team map RMSE {team:.2} m, reference {base:.2} m, ratio {:.2}",
        team / base
    );
}

/// radio-range.toml with the outage suite's consistency checks ([`procs::assert_sound`],
/// [`procs::assert_in_band`]): what it proves is that uav1, the vehicle that comes into uav3's
/// range only at ~34 s and catches up on the team's map through a sparsified link, keeps a
/// consistent pose (ANEES within the suite's bound of the reference's) and every vehicle's
/// NEES stays in its band.
///
/// This test was ignored from 2026-12-05 to 2026-12-06: it failed in about one run of ten,
/// always on uav1 (pose ANEES 4.10–5.92 against the reference's 1.58, bound 2.25; uav1's map
/// RMSE 82–164 m against 4–10 m in passing runs). Measured again on 2026-12-06 with the same
/// scenario: a build from before the correspondence bound (`fusion.correspondence_max_sigma_m`,
/// docs/arch/association.md) and the sparsified links' introduction rule
/// (`channel::MAX_INTRODUCED_SIGMA_M`, docs/arch/ddf.md) gave 4 such runs of 40 (uav1's map RMSE
/// 35–138 m, pose ANEES up to 4.73); the build with both, 0 of 80 `canopy run`s (uav1's pose
/// ANEES 1.60–1.77, map RMSE 2.7–11.7 m) and 100 of 100 runs of this test (40 of them beside a
/// `canopy sim` loading the second core). Three of the four old failures had a wrong merge
/// (none in the 80 new runs), the fourth 42 fusion rounds of uav1 refused for an invalid
/// estimate (one new run had 33 such refusals, and uav1's map RMSE was 6.3 m).
#[test]
fn radio_range_is_sound() {
    let _g = serial();
    let r = run(&topology("radio-range.toml"), &["--quiet"]);
    r.print_standing("radio-range");
    assert_sound(&r);
    assert_in_band(&r, IN_BAND);
}
