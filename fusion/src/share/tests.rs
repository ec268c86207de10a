//! The relay on a five-node tree with lossy, reordering, intermittent links (a deterministic
//! in-test network, seeded).
use super::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[derive(Clone, Debug, PartialEq)]
struct Rec {
    origin: u32,
    n: u64,
    bytes: usize,
    value: f64,
}

impl ShareRecord for Rec {
    fn wire_bytes(&self) -> usize {
        self.bytes
    }
    fn validate(&self) -> Result<(), String> {
        if self.value.is_finite() {
            Ok(())
        } else {
            Err(format!("value {} is not finite", self.value))
        }
    }
}

fn id(n: u32) -> NodeId {
    NodeId(n)
}

/// 1 − 3 − 4 − 5 and 2 − 3: diameter 3.
fn tree() -> Topology {
    Topology::tree(
        (1..=5).map(id),
        [(1, 3), (2, 3), (3, 4), (4, 5)].map(|(a, b)| (id(a), id(b))),
    )
    .unwrap()
}

type Link = (NodeId, NodeId);

struct Net {
    topology: Topology,
    relays: BTreeMap<NodeId, Relay<Rec>>,
    /// (due round, from, to, batch).
    in_flight: Vec<(u64, NodeId, NodeId, Batch<Rec>)>,
    /// Per node, what it delivered, in delivery order.
    delivered: BTreeMap<NodeId, Vec<(StreamId, Seq, Rec)>>,
    /// Per stream, what its origin published.
    published: BTreeMap<StreamId, Vec<Rec>>,
    rng: ChaCha8Rng,
    down_now: BTreeSet<Link>,
    largest_batch_over_budget: usize,
}

use std::collections::BTreeSet;

impl Net {
    fn new(seed: u64) -> Self {
        let topology = tree();
        let relays = topology
            .nodes()
            .iter()
            .map(|&n| {
                (
                    n,
                    Relay::new(n, 1, &topology, RelayConfig::default()).unwrap(),
                )
            })
            .collect();
        Self {
            topology,
            relays,
            in_flight: Vec::new(),
            delivered: BTreeMap::new(),
            published: BTreeMap::new(),
            rng: ChaCha8Rng::seed_from_u64(seed),
            down_now: BTreeSet::new(),
            largest_batch_over_budget: 0,
        }
    }

    fn publish(&mut self, node: NodeId, bytes: usize) {
        let r = self.relays.get_mut(&node).unwrap();
        let stream = r.own_stream();
        let n = self.published.get(&stream).map_or(0, Vec::len) as u64;
        let rec = Rec {
            origin: node.0,
            n,
            bytes,
            value: n as f64,
        };
        assert_eq!(r.publish(rec.clone()).unwrap(), n);
        self.published.entry(stream).or_default().push(rec);
    }

    /// One round at time `round` (seconds): links per `down`, then every node sends every
    /// neighbour a batch (lost with probability `loss`, delayed 0..=`max_delay` rounds), then
    /// what is due arrives, then every node delivers what is ready.
    fn round(
        &mut self,
        round: u64,
        budget: usize,
        loss: f64,
        max_delay: u64,
        down: &dyn Fn(u64, Link) -> bool,
    ) {
        let t = round as f64;
        let links: Vec<Link> = self.topology.links().to_vec();
        for &(a, b) in &links {
            let is_down = down(round, (a, b));
            let was_down = self.down_now.contains(&(a, b));
            if is_down && !was_down {
                self.relays.get_mut(&a).unwrap().on_link_down(b);
                self.relays.get_mut(&b).unwrap().on_link_down(a);
                self.down_now.insert((a, b));
            } else if !is_down && was_down {
                self.relays.get_mut(&a).unwrap().on_link_up(b, t);
                self.relays.get_mut(&b).unwrap().on_link_up(a, t);
                self.down_now.remove(&(a, b));
            }
        }
        for &(a, b) in &links {
            for (from, to) in [(a, b), (b, a)] {
                let Some(batch) = self.relays.get_mut(&from).unwrap().outgoing(to, budget, t)
                else {
                    continue;
                };
                let bytes = batch.wire_bytes();
                if bytes > budget {
                    assert_eq!(
                        batch.records.len(),
                        1,
                        "a batch over the budget carries one record"
                    );
                    self.largest_batch_over_budget = self.largest_batch_over_budget.max(bytes);
                }
                if self.rng.random::<f64>() < loss {
                    continue;
                }
                let delay = self.rng.random_range(0..=max_delay);
                self.in_flight.push((round + delay, from, to, batch));
            }
        }
        let (due, later): (Vec<_>, Vec<_>) = std::mem::take(&mut self.in_flight)
            .into_iter()
            .partition(|m| m.0 <= round);
        self.in_flight = later;
        for (_, from, to, batch) in due {
            let link = (from.min(to), from.max(to));
            let link = links
                .iter()
                .copied()
                .find(|&(a, b)| (a.min(b), a.max(b)) == link)
                .unwrap();
            if self.down_now.contains(&link) {
                continue; // Lost with the link.
            }
            let got = self
                .relays
                .get_mut(&to)
                .unwrap()
                .on_batch(from, batch, t)
                .unwrap();
            assert!(got.refused.is_empty(), "{to} refused {:?}", got.refused);
        }
        for (&n, r) in &mut self.relays {
            self.delivered.entry(n).or_default().extend(r.take_ready());
        }
    }

    /// Whether every node holds every published record.
    fn complete(&self) -> bool {
        self.relays.values().all(|r| {
            let have: BTreeMap<StreamId, u64> = r.have().into_iter().collect();
            self.published
                .iter()
                .all(|(s, recs)| have.get(s).copied().unwrap_or(0) == recs.len() as u64)
        })
    }

    /// Every node delivered every published record once, in its stream's order.
    fn assert_exactly_once_in_order(&self) {
        for (node, got) in &self.delivered {
            let mut per: BTreeMap<StreamId, Vec<(Seq, Rec)>> = BTreeMap::new();
            for (s, k, r) in got {
                per.entry(*s).or_default().push((*k, r.clone()));
            }
            for (s, recs) in &self.published {
                let d = per.get(s).cloned().unwrap_or_default();
                assert_eq!(
                    d.len(),
                    recs.len(),
                    "{node}: {s:?}: delivered {} of {}",
                    d.len(),
                    recs.len()
                );
                for (k, ((seq, r), want)) in d.iter().zip(recs).enumerate() {
                    assert_eq!(*seq, k as u64, "{node}: {s:?} out of order");
                    assert_eq!(r, want, "{node}: {s:?} record {k}");
                }
            }
        }
    }
}

/// What it proves: over links that lose 30 % of the batches, reorder them by up to three
/// rounds and go down for stretches (one link down 40 rounds, another flapping), with a budget
/// that a burst of records overruns, every node ends up delivering every record of every
/// stream exactly once and in order, and no batch exceeds the budget except by a single
/// record. Five seeds.
#[test]
fn every_record_reaches_every_node_once_in_order_over_lossy_links() {
    for seed in 0..5 {
        let mut net = Net::new(seed);
        let down = |round: u64, link: Link| {
            (link == (id(3), id(4)) && (20..60).contains(&round))
                || (link == (id(1), id(3)) && (round / 7) % 3 == 1)
        };
        let mut round = 0;
        while round < 100 {
            for n in 1..=5 {
                // ~1 kB per round per node, with a 3 kB record now and then.
                let bytes = if round % 17 == n { 3000 } else { 500 };
                net.publish(id(n as u32), bytes);
                net.publish(id(n as u32), 500);
            }
            net.round(round, 8000, 0.3, 3, &down);
            round += 1;
        }
        while !net.complete() {
            assert!(round < 400, "seed {seed}: not complete by round 400");
            net.round(round, 8000, 0.3, 3, &down);
            round += 1;
        }
        net.assert_exactly_once_in_order();
        assert!(net.largest_batch_over_budget <= 8000 + 3000 + RECORD_HEADER_BYTES);
        let c = net.relays[&id(3)].counters();
        assert!(
            c.rewinds > 0,
            "seed {seed}: losses were repaired by going back"
        );
        assert_eq!(c.refused, 0);
    }
}

/// What it proves: with lossless, immediate links and a budget above the data rate, a record
/// published in round r is delivered by a node h hops away in round r + h − 1 at the latest
/// (one round per hop: a node forwards in the round after it received), so a team's data
/// reaches every node within the tree's diameter in rounds.
#[test]
fn a_record_travels_one_hop_per_round() {
    let mut net = Net::new(7);
    let up = |_: u64, _: Link| false;
    for round in 0..30 {
        for n in 1..=5 {
            net.publish(id(n), 200);
        }
        net.round(round, 4000, 0.0, 0, &up);
        // Record `round` of node 1 is 3 hops from node 5 (1 − 3 − 4 − 5).
        if round >= 2 {
            let s1 = net.relays[&id(1)].own_stream();
            let have5: BTreeMap<_, _> = net.relays[&id(5)].have().into_iter().collect();
            assert!(
                have5.get(&s1).copied().unwrap_or(0) >= round - 1,
                "round {round}: node 5 holds {:?} of node 1's records",
                have5.get(&s1)
            );
        }
    }
}

/// What it proves: a relay that restarts (a fresh process with a new epoch, holding nothing)
/// gets every stream back from its neighbours, its own earlier stream included, and the
/// others take its new stream; the earlier stream's records are not lost anywhere.
#[test]
fn a_restarted_node_gets_everything_back() {
    let mut net = Net::new(3);
    let up = |_: u64, _: Link| false;
    let mut round = 0;
    while round < 30 {
        for n in 1..=5 {
            net.publish(id(n), 300);
        }
        net.round(round, 6000, 0.1, 1, &up);
        round += 1;
    }
    // The hub restarts: a fresh relay, a new epoch; what it delivered before is gone with it.
    let topology = net.topology.clone();
    net.relays.insert(
        id(3),
        Relay::new(id(3), 2, &topology, RelayConfig::default()).unwrap(),
    );
    net.delivered.insert(id(3), Vec::new());
    while round < 60 {
        for n in 1..=5 {
            net.publish(id(n), 300);
        }
        net.round(round, 6000, 0.1, 1, &up);
        round += 1;
    }
    while !net.complete() {
        assert!(round < 300, "not complete by round 300");
        net.round(round, 6000, 0.1, 1, &up);
        round += 1;
    }
    net.assert_exactly_once_in_order();
    assert_eq!(
        net.published.keys().filter(|s| s.origin == id(3)).count(),
        2
    );
}

/// What it proves: hostile or misrouted input is refused with its reason and changes nothing
/// the node holds or delivers: a batch from a non-neighbour, a record of node 1 arriving at
/// node 4 from node 5 (the tree routes 1 through 3), the node's own current stream sent back,
/// an origin outside the team, a record far past a gap, a non-finite record, and more
/// streams of one origin than allowed.
#[test]
fn hostile_records_are_refused_by_reason_and_harmless() {
    let topology = tree();
    let mut r4: Relay<Rec> = Relay::new(id(4), 1, &topology, RelayConfig::default()).unwrap();
    let rec = |value: f64| Rec {
        origin: 0,
        n: 0,
        bytes: 10,
        value,
    };
    let s = |origin: u32, epoch: u64| StreamId {
        origin: id(origin),
        epoch,
    };
    let before = r4.have();
    assert_eq!(
        r4.on_batch(
            id(1),
            Batch {
                epoch: 7,
                number: 1,
                have: vec![],
                records: vec![(s(1, 1), 0, rec(1.0))]
            },
            0.0
        ),
        Err(ShareError::NotNeighbour(id(1)))
    );
    let mut records = vec![
        (s(1, 1), 0, rec(1.0)),      // node 1 is routed through 3, not 5
        (s(4, 1), 0, rec(1.0)),      // this node's own current stream
        (s(9, 1), 0, rec(1.0)),      // not in the team
        (s(5, 1), 5000, rec(1.0)),   // far past a gap
        (s(5, 1), 0, rec(f64::NAN)), // not finite
    ];
    for epoch in 0..17 {
        records.push((s(5, 100 + epoch), 0, rec(1.0)));
    }
    let got = r4
        .on_batch(
            id(5),
            Batch {
                epoch: 7,
                number: 1,
                have: vec![],
                records,
            },
            0.0,
        )
        .unwrap();
    let reasons: Vec<&str> = got.refused.iter().map(ShareError::reason).collect();
    assert_eq!(
        reasons,
        [
            "wrong_route",
            "own_stream",
            "not_in_team",
            "too_far_ahead",
            "invalid_record",
            "too_many_streams"
        ]
    );
    // The 16 streams of node 5 that were allowed hold one record each; nothing else changed.
    assert_eq!(got.accepted, 16);
    let after: BTreeMap<_, _> = r4.have().into_iter().collect();
    for (id, n) in before {
        assert_eq!(after[&id], n);
    }
    assert!(!after.contains_key(&s(1, 1)));
    assert!(r4.take_ready().iter().all(|(_, _, r)| r.value == 1.0));
}
