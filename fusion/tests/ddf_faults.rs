//! Acceptance: channel filters under faults. A deterministic in-test network drives the DDF
//! state machine with loss, duplication, reordering, delays, multi-link outages and node
//! restarts. At every round no node holds more information than the centralized filter (PSD
//! order), and once the links recover every node holds the centralized sum of what live
//! processes observed.

mod common;

use canopy_fusion::ddf::{ChannelStats, DdfConfig, Mode};
use canopy_fusion::topology::NodeId;
use common::{Faults, Shape, Sim, features, random_observations, tree};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A fault schedule (data): link faults during `fault_rounds`, outages and restarts at rounds.
#[derive(Clone, Debug)]
struct Schedule {
    nodes: usize,
    shape: Shape,
    fault_rounds: u64,
    faults: Faults,
    /// (start, end, number of links down together), drawn at random links.
    outages: Vec<(u64, u64, usize)>,
    /// Rounds at which a random node restarts (new epoch, empty map).
    restarts: Vec<u64>,
    /// Probability per node and round of a new observation.
    observe: f64,
}

/// PSD-order tolerance: λ_max(Y_i − Y_central) ≤ 1e-9 · max|Y_central|. Exact arithmetic gives
/// ≤ 0; sums of a few hundred deltas in different orders leave ~1e-14 relative, and the
/// indefinite removal deltas after a restart cancel to the same level.
const PSD_TOL: f64 = 1e-9;
/// Equality after recovery, relative (the acceptance criterion's 1e-9).
const EQ_TOL: f64 = 1e-9;

struct Outcome {
    recovery_rounds: u64,
    worst_excess: f64,
    stats: ChannelStats,
}

fn add(a: &mut ChannelStats, b: &ChannelStats) {
    a.deltas_sent += b.deltas_sent;
    a.deltas_applied += b.deltas_applied;
    a.duplicates += b.duplicates;
    a.stale += b.stale;
    a.out_of_order += b.out_of_order;
    a.buffer_overflows += b.buffer_overflows;
    a.nacks_sent += b.nacks_sent;
    a.cumulatives_sent += b.cumulatives_sent;
    a.cumulatives_applied += b.cumulatives_applied;
    a.syncs_initiated += b.syncs_initiated;
    a.syncs_applied += b.syncs_applied;
    a.peer_restarts += b.peer_restarts;
    a.rejected += b.rejected;
}

fn run(schedule: &Schedule, seed: u64) -> Outcome {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let topo = tree(schedule.shape, schedule.nodes, &mut rng);
    let ids: Vec<NodeId> = topo.nodes().to_vec();
    let links: Vec<(NodeId, NodeId)> = topo.links().to_vec();
    let diameter = topo.diameter().unwrap() as u64;
    let feats = features(10, &mut rng);
    let config = DdfConfig {
        max_buffer: 8,
        ..DdfConfig::default()
    };
    let mut sim = Sim::new(topo, Mode::Decentralized, config, rng.random());
    sim.faults = schedule.faults;
    sim.link_all_up();
    let mut worst_excess = f64::NEG_INFINITY;
    // Outage intervals on concrete links.
    let mut outages: Vec<(u64, u64, (NodeId, NodeId))> = Vec::new();
    for &(start, end, count) in &schedule.outages {
        for _ in 0..count {
            outages.push((start, end, links[rng.random_range(0..links.len())]));
        }
    }
    let mut down: Vec<(NodeId, NodeId)> = Vec::new();
    for r in 0..schedule.fault_rounds {
        for &(start, end, link) in &outages {
            if r == start && !down.contains(&link) {
                sim.set_link(link.0, link.1, false);
                down.push(link);
            }
            if r == end
                && down.contains(&link)
                && !outages.iter().any(|o| o.2 == link && o.0 < r && o.1 > r)
            {
                sim.set_link(link.0, link.1, true);
                down.retain(|l| *l != link);
            }
        }
        if schedule.restarts.contains(&r) {
            let victim = ids[rng.random_range(0..ids.len())];
            sim.restart(victim);
        }
        for &id in &ids {
            if rng.random_bool(schedule.observe) {
                let obs = random_observations(&feats, &mut rng, true);
                sim.observe(id, &obs);
            }
        }
        sim.round();
        let excess = sim.max_psd_excess();
        worst_excess = worst_excess.max(excess);
        assert!(
            excess <= PSD_TOL,
            "seed {seed} round {r}: a node exceeds the centralized information by {excess:e}"
        );
    }
    // Recovery: links healed, faults off (messages already in flight keep their delays).
    for link in down.drain(..) {
        sim.set_link(link.0, link.1, true);
    }
    sim.faults = Faults::default();
    let target = sim.live_sum();
    let mut recovery_rounds = None;
    for r in 0..(diameter + 60) {
        sim.round();
        let excess = sim.max_psd_excess();
        worst_excess = worst_excess.max(excess);
        assert!(
            excess <= PSD_TOL,
            "seed {seed} recovery round {r}: excess {excess:e}"
        );
        if sim.max_relative_difference(&target) <= EQ_TOL && sim.in_flight() == 0 {
            recovery_rounds = Some(r + 1);
            break;
        }
    }
    let diff = sim.max_relative_difference(&target);
    if diff > EQ_TOL {
        for (id, n) in &sim.nodes {
            for c in n.ddf.channels() {
                eprintln!(
                    "node {id} ch {} synced {} up {} {:?}",
                    c.peer, c.synced, c.link_up, c.stats
                );
            }
            eprintln!(
                "node {id} diff {:e}",
                n.estimate.relative_difference(&target).unwrap()
            );
        }
    }
    let recovery_rounds = recovery_rounds.unwrap_or_else(|| {
        panic!("seed {seed}: no convergence after recovery, max relative difference {diff:e}")
    });
    let mut stats = ChannelStats::default();
    for n in sim.nodes.values() {
        for c in n.ddf.channels() {
            add(&mut stats, &c.stats);
        }
    }
    Outcome {
        recovery_rounds,
        worst_excess,
        stats,
    }
}

fn report(name: &str, outcomes: &[Outcome]) -> ChannelStats {
    let mut total = ChannelStats::default();
    for o in outcomes {
        add(&mut total, &o.stats);
    }
    let max_rec = outcomes.iter().map(|o| o.recovery_rounds).max().unwrap();
    let worst = outcomes
        .iter()
        .map(|o| o.worst_excess)
        .fold(f64::NEG_INFINITY, f64::max);
    println!(
        "{name}: {} runs, recovery <= {max_rec} rounds, max PSD excess {worst:.2e}; totals: \
         deltas sent {} applied {}, duplicates {}, stale {}, out-of-order {}, overflows {}, \
         nacks {}, cumulatives sent {} applied {}, syncs {}/{}, peer restarts {}",
        outcomes.len(),
        total.deltas_sent,
        total.deltas_applied,
        total.duplicates,
        total.stale,
        total.out_of_order,
        total.buffer_overflows,
        total.nacks_sent,
        total.cumulatives_sent,
        total.cumulatives_applied,
        total.syncs_initiated,
        total.syncs_applied,
        total.peer_restarts,
    );
    total
}

/// Loss 30 %, 20 % duplicates, delays (hence reordering) up to 10 rounds, and outages of up to
/// three links at once, on 20 random trees of 6–12 nodes, 80 faulty rounds each.
#[test]
fn loss_duplication_reordering_delay_and_outages() {
    let shapes = [Shape::Random, Shape::Chain, Shape::Balanced, Shape::Star];
    let outcomes: Vec<Outcome> = (0..20)
        .map(|seed| {
            let s = Schedule {
                nodes: 6 + (seed as usize % 7),
                shape: shapes[seed as usize % 4],
                fault_rounds: 80,
                faults: Faults {
                    loss: 0.3,
                    duplicate: 0.2,
                    max_delay: 10,
                },
                outages: vec![(5, 25, 3), (30, 45, 2), (50, 70, 1), (60, 75, 2)],
                restarts: vec![],
                observe: 0.3,
            };
            run(&s, 100 + seed)
        })
        .collect();
    let t = report("faults", &outcomes);
    // The schedule must actually exercise every recovery path.
    // (Stale here: cumulatives overtaken by deltas or by another cumulative.)
    assert!(t.duplicates > 0 && t.out_of_order > 0 && t.stale > 0);
    assert!(t.nacks_sent > 0 && t.cumulatives_applied > 0 && t.buffer_overflows > 0);
}

/// The same faults plus node restarts (new epoch, empty map), including restarts during
/// outages and repeated restarts: the network converges to the sum of what the live
/// incarnations observed (information of a dead incarnation is lost, never double counted).
#[test]
fn restarts_under_faults_resynchronise_without_double_counting() {
    let shapes = [Shape::Chain, Shape::Random, Shape::Balanced, Shape::Star];
    let outcomes: Vec<Outcome> = (0..20)
        .map(|seed| {
            let s = Schedule {
                nodes: 5 + (seed as usize % 6),
                shape: shapes[seed as usize % 4],
                fault_rounds: 90,
                faults: Faults {
                    loss: 0.3,
                    duplicate: 0.2,
                    max_delay: 10,
                },
                outages: vec![(10, 30, 2), (40, 55, 2), (60, 80, 1)],
                restarts: vec![15, 20, 35, 50, 52, 70, 85],
                observe: 0.3,
            };
            run(&s, 500 + seed)
        })
        .collect();
    let t = report("faults+restarts", &outcomes);
    assert!(t.peer_restarts > 0 && t.syncs_applied > 0 && t.stale > 0);
}

/// Restarts every third round (28 per run), faster than the 10-round network delay, so that
/// delayed messages of dead incarnations keep arriving after their successors took over, and
/// a fresh node may first hear of a dead incarnation of its neighbour.
#[test]
fn frequent_restarts_faster_than_the_network_delay() {
    let shapes = [Shape::Random, Shape::Chain, Shape::Star, Shape::Balanced];
    let outcomes: Vec<Outcome> = (0..20)
        .map(|seed| {
            let s = Schedule {
                nodes: 4 + (seed as usize % 7),
                shape: shapes[seed as usize % 4],
                fault_rounds: 90,
                faults: Faults {
                    loss: 0.3,
                    duplicate: 0.2,
                    max_delay: 10,
                },
                outages: vec![(10, 30, 2), (40, 55, 1)],
                restarts: (5..88).step_by(3).collect(),
                observe: 0.3,
            };
            run(&s, 900 + seed)
        })
        .collect();
    let t = report("frequent restarts", &outcomes);
    assert!(t.peer_restarts > 100 && t.stale > 0);
}

/// Restarts on perfect links, at every position of a chain (ends and middle), after the
/// network converged: the old incarnation's information disappears everywhere and the rest
/// is kept, exactly.
#[test]
fn restart_at_every_position_of_a_chain_removes_exactly_the_lost_information() {
    let mut rng = ChaCha8Rng::seed_from_u64(77);
    for victim_index in 0..5 {
        let topo = tree(Shape::Chain, 5, &mut rng);
        let ids: Vec<NodeId> = topo.nodes().to_vec();
        let feats = features(6, &mut rng);
        let mut sim = Sim::new(
            topo,
            Mode::Decentralized,
            DdfConfig::default(),
            rng.random(),
        );
        sim.handshake(5);
        for &id in &ids {
            let obs = random_observations(&feats, &mut rng, true);
            sim.observe(id, &obs);
        }
        for _ in 0..5 {
            sim.round();
        }
        assert!(sim.max_relative_difference(&sim.all_ever.clone()) <= EQ_TOL);
        let victim = ids[victim_index];
        sim.restart(victim);
        let obs = random_observations(&feats, &mut rng, true);
        sim.observe(victim, &obs);
        let target = sim.live_sum();
        for _ in 0..12 {
            sim.round();
            assert!(sim.max_psd_excess() <= PSD_TOL);
        }
        let diff = sim.max_relative_difference(&target);
        assert!(diff <= EQ_TOL, "victim {victim_index}: {diff:e}");
        // And the lost incarnation's information is really gone (the test has teeth).
        assert!(sim.max_relative_difference(&sim.all_ever.clone()) > 1e-6);
    }
}
