//! Acceptance: on a tree with perfect links, channel filters reach the centralized sum in
//! exactly `diameter` rounds (linear-Gaussian static map, design.md §4 "ground truth").

mod common;

use canopy_fusion::ddf::{DdfConfig, Mode};
use common::{Shape, Sim, features, random_observations, tree};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn deltas_sent(sim: &Sim) -> u64 {
    sim.nodes
        .values()
        .flat_map(|n| n.ddf.channels())
        .map(|c| c.stats.deltas_sent)
        .sum()
}

/// Property test over 75 random trees (2–16 nodes; chain, star, balanced, random recursive;
/// random node ids), each node with independent direct observations of a random subset of
/// features plus one relative observation (off-diagonal blocks): after the link handshake and
/// then `diameter` rounds, every node's (Y, y) equals the centralized sum to 1e-9 relative;
/// after `diameter − 1` rounds some node does not (information moves one hop per round), and a
/// converged network sends no further deltas.
#[test]
fn perfect_links_reach_the_centralized_sum_in_diameter_rounds() {
    let mut rng = ChaCha8Rng::seed_from_u64(2024);
    let (mut cases, mut worst, mut worst_early, mut max_handshake) = (0, 0.0_f64, f64::INFINITY, 0);
    for n in 2..=16 {
        for shape in [
            Shape::Chain,
            Shape::Star,
            Shape::Balanced,
            Shape::Random,
            Shape::Random,
        ] {
            let topo = tree(shape, n, &mut rng);
            let diameter = topo.diameter().unwrap() as u64;
            let feats = features(rng.random_range(3..=12), &mut rng);
            let ids: Vec<_> = topo.nodes().to_vec();
            let mut sim = Sim::new(
                topo,
                Mode::Decentralized,
                DdfConfig::default(),
                rng.random(),
            );
            // Hello → Sync → acknowledgement, within the first rounds.
            max_handshake = max_handshake.max(sim.handshake(5));
            for &id in &ids {
                let obs = random_observations(&feats, &mut rng, true);
                sim.observe(id, &obs);
            }
            let central = sim.all_ever.clone();
            for r in 0..diameter {
                if r == diameter - 1 {
                    // One round short, the two ends of a longest path miss each other.
                    let early = sim.max_relative_difference(&central);
                    worst_early = worst_early.min(early);
                    assert!(
                        early > 1e-6,
                        "{shape:?} n={n}: converged before {diameter} rounds"
                    );
                }
                sim.round();
            }
            let diff = sim.max_relative_difference(&central);
            // Sums of ≤ 16 contributions in different orders: ~1e-15 relative round-off, and
            // the 1e-12 block threshold leaves at most that much unsent; 1e-9 is the target.
            assert!(
                diff <= 1e-9,
                "{shape:?} n={n}: max relative difference {diff:e}"
            );
            worst = worst.max(diff);
            // Quiet afterwards: nothing left to send, and still equal.
            let before = deltas_sent(&sim);
            for _ in 0..3 {
                sim.round();
            }
            assert_eq!(
                deltas_sent(&sim),
                before,
                "{shape:?} n={n}: deltas after convergence"
            );
            assert!(sim.max_relative_difference(&central) <= 1e-9);
            cases += 1;
        }
    }
    println!(
        "perfect links: {cases} trees (2-16 nodes), handshake <= {max_handshake} rounds, \
         max relative difference after diameter rounds {worst:.3e}, \
         min difference one round earlier {worst_early:.3e}"
    );
}

/// Lossy mode: with f32 deltas (conservatively deflated) on 30 random trees, no node ever
/// holds more information than the centralized sum (PSD order, every round), and a few rounds
/// after `diameter` every node is within 1e-6 relative of it (what each round holds back is
/// ~2⁻²² of the delta and goes out with the next one, so the gap shrinks geometrically).
#[test]
fn f32_deltas_stay_below_and_converge_to_the_centralized_sum() {
    let mut rng = ChaCha8Rng::seed_from_u64(4242);
    let config = DdfConfig {
        delta_precision: canopy_fusion::ddf::DeltaPrecision::F32,
        ..DdfConfig::default()
    };
    let mut worst_excess = f64::NEG_INFINITY;
    let mut worst_diff = 0.0_f64;
    for case in 0..30 {
        let shape = [Shape::Chain, Shape::Star, Shape::Balanced, Shape::Random][case % 4];
        let n = 2 + case % 12;
        let topo = tree(shape, n, &mut rng);
        let diameter = topo.diameter().unwrap() as u64;
        let feats = features(rng.random_range(3..=10), &mut rng);
        let ids: Vec<_> = topo.nodes().to_vec();
        let mut sim = Sim::new(topo, Mode::Decentralized, config.clone(), rng.random());
        sim.handshake(5);
        for &id in &ids {
            let obs = random_observations(&feats, &mut rng, true);
            sim.observe(id, &obs);
        }
        let central = sim.all_ever.clone();
        for _ in 0..diameter + 4 {
            sim.round();
            // λ_max(Y_node − Y_central) ≤ round-off of the sums (1e-9 of max|Y|).
            let excess = sim.max_psd_excess();
            worst_excess = worst_excess.max(excess);
            assert!(
                excess <= 1e-9,
                "{shape:?} n={n}: a node exceeds the central sum by {excess:e}"
            );
        }
        let diff = sim.max_relative_difference(&central);
        worst_diff = worst_diff.max(diff);
        assert!(
            diff <= 1e-6,
            "{shape:?} n={n}: {diff:e} from the central sum"
        );
    }
    println!("f32 deltas: worst PSD excess {worst_excess:e}, worst relative gap {worst_diff:e}");
}
