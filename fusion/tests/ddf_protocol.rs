//! Protocol scenarios driven message by message: bad input, refusals, duplicates,
//! reordering, gap recovery, epochs, the double-initiation tie-break, link events and the CI
//! switch. Each test says what it proves.

mod common;

use canopy_fusion::ddf::{
    Body, DdfConfig, DdfError, DdfMessage, DdfNode, FuseRejected, FuseTarget, Header, LinkMode,
    MAX_UNCERTAIN, Outgoing,
};
use canopy_fusion::info::{InfoError, MapInformation};
use canopy_fusion::topology::NodeId;
use common::{direct_observation, features, origin, random_observations};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;

const A: NodeId = NodeId(1);
const B: NodeId = NodeId(2);

/// Exact equality up to summation-order round-off.
const EQ_TOL: f64 = 1e-12;

/// Messages in flight, with their senders.
type Queue = Vec<(NodeId, Outgoing)>;
/// Which error a bad input must produce.
type ErrorCheck = fn(&InfoError) -> bool;

/// A few nodes with estimates, and explicit message passing.
struct Net {
    nodes: BTreeMap<NodeId, (DdfNode, MapInformation)>,
}

impl Net {
    fn new(links: &[(NodeId, NodeId)], config: DdfConfig) -> Self {
        let mut nodes = BTreeMap::new();
        let ids: std::collections::BTreeSet<NodeId> =
            links.iter().flat_map(|&(a, b)| [a, b]).collect();
        for id in ids {
            let peers: Vec<NodeId> = links
                .iter()
                .filter_map(|&(a, b)| {
                    if a == id {
                        Some(b)
                    } else if b == id {
                        Some(a)
                    } else {
                        None
                    }
                })
                .collect();
            let node = DdfNode::new(id, 1000 + id.0 as u64, peers, origin(), config.clone());
            nodes.insert(id, (node, MapInformation::zero(origin())));
        }
        Net { nodes }
    }

    fn restart(&mut self, id: NodeId, epoch: u64, config: DdfConfig) {
        let peers: Vec<NodeId> = self.nodes[&id].0.neighbours().collect();
        self.nodes.insert(
            id,
            (
                DdfNode::new(id, epoch, peers, origin(), config),
                MapInformation::zero(origin()),
            ),
        );
    }

    /// `on_round` of one node; returns its messages (not delivered).
    fn round(&mut self, id: NodeId, now: f64) -> Vec<(NodeId, Outgoing)> {
        let (node, est) = self.nodes.get_mut(&id).unwrap();
        let out = node.on_round(now, est).unwrap();
        out.messages.into_iter().map(|o| (id, o)).collect()
    }

    fn round_all(&mut self, now: f64) -> Vec<(NodeId, Outgoing)> {
        let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        ids.into_iter().flat_map(|id| self.round(id, now)).collect()
    }

    /// Delivers one message; returns the replies.
    fn deliver_one(&mut self, now: f64, from: NodeId, o: Outgoing) -> Vec<(NodeId, Outgoing)> {
        let to = o.to;
        let (node, est) = self.nodes.get_mut(&to).unwrap();
        node.on_message(now, from, o.message, est)
            .unwrap()
            .into_iter()
            .map(|r| (to, r))
            .collect()
    }

    /// Delivers messages and all replies until quiet.
    fn deliver(&mut self, now: f64, mut queue: Vec<(NodeId, Outgoing)>) {
        while !queue.is_empty() {
            let (from, o) = queue.remove(0);
            let replies = self.deliver_one(now, from, o);
            queue.extend(replies);
        }
    }

    /// Delivers messages and replies until quiet, except Syncs, which are returned (with
    /// whatever else was left).
    fn pump_holding_syncs(
        &mut self,
        now: f64,
        mut queue: Vec<(NodeId, Outgoing)>,
    ) -> (Queue, Queue) {
        let mut held = Vec::new();
        while !queue.is_empty() {
            let (from, o) = queue.remove(0);
            if matches!(o.message.body, Body::Sync { .. }) {
                held.push((from, o));
            } else {
                let replies = self.deliver_one(now, from, o);
                queue.extend(replies);
            }
        }
        (held, queue)
    }

    fn link_up_all(&mut self, now: f64) {
        let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        let mut q = Vec::new();
        for id in ids {
            let peers: Vec<NodeId> = self.nodes[&id].0.neighbours().collect();
            for p in peers {
                q.extend(
                    self.nodes
                        .get_mut(&id)
                        .unwrap()
                        .0
                        .on_link_up(now, p)
                        .unwrap()
                        .into_iter()
                        .map(|o| (id, o)),
                );
            }
        }
        self.deliver(now, q);
    }

    fn est(&self, id: NodeId) -> &MapInformation {
        &self.nodes[&id].1
    }

    fn observe(&mut self, id: NodeId, info: &MapInformation) {
        self.nodes.get_mut(&id).unwrap().1.add_assign(info).unwrap();
    }

    fn stats(&self, id: NodeId, peer: NodeId) -> canopy_fusion::ddf::ChannelStats {
        self.nodes[&id].0.channel(peer).unwrap().stats
    }
}

fn deltas(msgs: &[(NodeId, Outgoing)]) -> Vec<(NodeId, Outgoing)> {
    msgs.iter()
        .filter(|(_, o)| matches!(o.message.body, Body::Delta { .. }))
        .cloned()
        .collect()
}

fn synced_pair() -> Net {
    let mut net = Net::new(&[(A, B)], DdfConfig::default());
    net.link_up_all(0.0);
    assert!(
        net.nodes[&A].0.channel(B).unwrap().synced && net.nodes[&B].0.channel(A).unwrap().synced
    );
    net
}

/// Three deltas from A, delivered to B as 3, 1, 3, 2, 1: each takes effect exactly once.
#[test]
fn duplicates_and_reordering_take_effect_exactly_once() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let feats = features(4, &mut rng);
    let mut net = synced_pair();
    let mut sent = Vec::new();
    let mut total = MapInformation::zero(origin());
    for t in 1..=3 {
        let obs = random_observations(&feats, &mut rng, true);
        net.observe(A, &obs);
        total.add_assign(&obs).unwrap();
        sent.extend(deltas(&net.round(A, t as f64)));
    }
    assert_eq!(sent.len(), 3);
    for k in [2, 0, 2, 1, 0] {
        net.deliver(4.0, vec![sent[k].clone()]);
    }
    assert!(net.est(B).relative_difference(&total).unwrap() <= EQ_TOL);
    let s = net.stats(B, A);
    assert_eq!((s.deltas_applied, s.duplicates, s.out_of_order), (3, 2, 1));
}

/// A lost delta is recovered by Nack → Cumulative after `gap_timeout` (gap seen from a later
/// delta), and a lost last delta by the Hello announcing seq_sent.
#[test]
fn lost_deltas_are_recovered_by_cumulative() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let feats = features(4, &mut rng);
    let mut net = synced_pair();
    let mut total = MapInformation::zero(origin());
    let mut obs = || random_observations(&feats, &mut rng, true);
    // Delta 1 lost, delta 2 delivered: B buffers 2 and waits.
    let o1 = obs();
    net.observe(A, &o1);
    total.add_assign(&o1).unwrap();
    let _lost = net.round(A, 1.0);
    let o2 = obs();
    net.observe(A, &o2);
    total.add_assign(&o2).unwrap();
    let d2 = deltas(&net.round(A, 2.0));
    net.deliver(2.0, d2);
    assert!(net.est(B).is_empty(), "delta 2 must wait for delta 1");
    // Before the timeout B does not Nack; after it, it does, and A's cumulative fills the gap.
    assert!(
        net.round(B, 3.0)
            .iter()
            .all(|(_, o)| !matches!(o.message.body, Body::Nack { .. }))
    );
    let out = net.round(B, 4.5);
    assert!(
        out.iter()
            .any(|(_, o)| matches!(o.message.body, Body::Nack { applied: 0 }))
    );
    net.deliver(4.5, out);
    assert!(net.est(B).relative_difference(&total).unwrap() <= EQ_TOL);
    assert_eq!(net.stats(B, A).cumulatives_applied, 1);
    // The last delta lost: only A's Hello tells B that seq 3 exists.
    let o3 = obs();
    net.observe(A, &o3);
    total.add_assign(&o3).unwrap();
    let out = net.round(A, 5.0);
    let hellos: Vec<_> = out
        .iter()
        .filter(|(_, o)| matches!(o.message.body, Body::Hello(_)))
        .cloned()
        .collect();
    assert!(!deltas(&out).is_empty());
    net.deliver(5.0, hellos);
    let out = net.round(B, 7.5);
    net.deliver(7.5, out);
    assert!(net.est(B).relative_difference(&total).unwrap() <= EQ_TOL);
    // A stale cumulative (upto ≤ applied) is ignored.
    assert_eq!(net.stats(B, A).cumulatives_applied, 2);
}

/// Unknown senders and invalid payloads are rejected with typed errors and counted, and change
/// nothing: a valid delta afterwards still applies as seq 1.
#[test]
fn bad_input_is_rejected_counted_and_harmless() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let feats = features(3, &mut rng);
    let mut net = synced_pair();
    let obs = direct_observation(feats[0].0, &feats[0].1, &mut rng);
    net.observe(A, &obs);
    let good = deltas(&net.round(A, 1.0)).remove(0).1;
    let Body::Delta { info, .. } = &good.message.body else {
        unreachable!()
    };
    let header = good.message.header;
    let bad = |f: &dyn Fn(&mut MapInformation)| {
        let mut i = info.clone();
        f(&mut i);
        DdfMessage {
            header,
            body: Body::Delta { seq: 1, info: i },
        }
    };
    let uncertain = |features: Vec<(u64, f32)>| DdfMessage {
        header,
        body: Body::Uncertain { features },
    };
    let (node, est) = net.nodes.get_mut(&B).unwrap();
    let cases: Vec<(DdfMessage, ErrorCheck)> = vec![
        // A list of loosely held features: longer than MAX_UNCERTAIN, a NaN, a σ ≤ 0.
        (
            uncertain((0..=MAX_UNCERTAIN as u64).map(|k| (k, 20.0)).collect()),
            |e| matches!(e, InfoError::Dimension { .. }),
        ),
        (uncertain(vec![(1, 20.0), (2, f32::NAN)]), |e| {
            matches!(e, InfoError::NonFinite { row: 1, .. })
        }),
        (uncertain(vec![(1, -3.0)]), |e| {
            matches!(e, InfoError::NonFinite { row: 0, .. })
        }),
        (bad(&|i| i.matrix[(0, 1)] = f64::NAN), |e| {
            matches!(e, InfoError::NonFinite { .. })
        }),
        (bad(&|i| i.vector[2] = f64::INFINITY), |e| {
            matches!(e, InfoError::NonFinite { .. })
        }),
        (bad(&|i| i.matrix[(0, 2)] += 1.0), |e| {
            matches!(e, InfoError::NotSymmetric { .. })
        }),
        (bad(&|i| i.origin.x += 1.0), |e| {
            matches!(e, InfoError::OriginMismatch { .. })
        }),
        (bad(&|i| i.ids.push(77)), |e| {
            matches!(e, InfoError::Dimension { .. })
        }),
    ];
    let n_cases = cases.len() as u64;
    for (msg, expected) in cases {
        match node.on_message(1.0, A, msg, est) {
            Err(DdfError::InvalidMessage { from, source }) => {
                assert_eq!(from, A);
                assert!(expected(&source), "{source:?}");
            }
            other => panic!("expected InvalidMessage, got {other:?}"),
        }
    }
    assert!(est.is_empty());
    assert_eq!(node.channel(A).unwrap().stats.rejected, n_cases);
    // Unknown sender.
    let err = node
        .on_message(1.0, NodeId(99), good.message.clone(), est)
        .unwrap_err();
    assert_eq!(err, DdfError::UnknownSender(NodeId(99)));
    assert_eq!(node.stats().unknown_sender, 1);
    // Non-finite time, invalid own estimate.
    assert!(matches!(
        node.on_message(f64::NAN, A, good.message.clone(), est),
        Err(DdfError::InvalidTime(_))
    ));
    let mut broken = obs.clone();
    broken.vector[0] = f64::NAN;
    assert!(matches!(
        node.on_round(1.0, &mut broken),
        Err(DdfError::InvalidEstimate(_))
    ));
    assert!(matches!(
        node.on_round(f64::INFINITY, est),
        Err(DdfError::InvalidTime(_))
    ));
    // The valid delta still applies as seq 1.
    node.on_message(1.0, A, good.message, est).unwrap();
    assert!(est.relative_difference(&obs).unwrap() <= EQ_TOL);
    assert_eq!(node.channel(A).unwrap().stats.deltas_applied, 1);
}

/// An estimator that refuses the first `refuse` deltas it is offered.
struct Refusing {
    inner: MapInformation,
    refuse: usize,
}

impl FuseTarget for Refusing {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        if self.refuse > 0 {
            self.refuse -= 1;
            return Err(FuseRejected {
                reason: "not positive definite".into(),
            });
        }
        self.inner.fuse(delta)
    }

    fn fuse_submap(
        &mut self,
        submap: &canopy_fusion::ci::Submap,
        criterion: canopy_fusion::ci::CiCriterion,
    ) -> Result<(), FuseRejected> {
        self.inner.fuse_submap(submap, criterion)
    }

    fn merge(&mut self, merge: &canopy_fusion::keys::Merge) -> Result<(), FuseRejected> {
        self.inner.merge(merge)
    }
}

/// A refused delta is not recorded: it stays pending, is retried with the next message, and
/// takes effect exactly once.
#[test]
fn refused_fusion_is_retried_and_applied_once() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let feats = features(3, &mut rng);
    let mut net = synced_pair();
    let mut total = MapInformation::zero(origin());
    let mut out = Vec::new();
    for t in 1..=2 {
        let o = random_observations(&feats, &mut rng, false);
        net.observe(A, &o);
        total.add_assign(&o).unwrap();
        out.extend(deltas(&net.round(A, t as f64)));
    }
    let mut target = Refusing {
        inner: MapInformation::zero(origin()),
        refuse: 1,
    };
    let node = &mut net.nodes.get_mut(&B).unwrap().0;
    let err = node
        .on_message(2.0, A, out[0].1.message.clone(), &mut target)
        .unwrap_err();
    assert!(matches!(err, DdfError::FuseRejected { from: A, .. }));
    assert!(target.inner.is_empty());
    // Delta 2 arrives: delta 1 is retried first, then 2.
    node.on_message(2.0, A, out[1].1.message.clone(), &mut target)
        .unwrap();
    // A duplicate of 1 changes nothing.
    node.on_message(2.0, A, out[0].1.message.clone(), &mut target)
        .unwrap();
    assert!(target.inner.relative_difference(&total).unwrap() <= EQ_TOL);
    let s = node.channel(A).unwrap().stats;
    assert_eq!((s.fuse_failures, s.deltas_applied, s.duplicates), (1, 2, 1));
}

/// Epochs: after B restarts, A resynchronises (A has history, so A initiates with its R_total
/// as baseline); a delayed message of B's old incarnation is dropped as stale, and so is a
/// message A addressed to B's old incarnation.
#[test]
fn restart_epochs_drop_stale_messages_and_resynchronise() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let feats = features(4, &mut rng);
    let mut net = synced_pair();
    let ob = random_observations(&feats, &mut rng, true);
    net.observe(B, &ob);
    let from_old_b = net.round(B, 1.0);
    net.deliver(1.0, from_old_b.clone());
    let oa = random_observations(&feats, &mut rng, true);
    net.observe(A, &oa);
    let to_old_b = deltas(&net.round(A, 2.0));
    // B restarts before A's delta arrives.
    net.restart(B, 4242, DdfConfig::default());
    let ob2 = random_observations(&feats, &mut rng, true);
    net.observe(B, &ob2);
    net.deliver(2.0, to_old_b);
    assert!(
        net.est(B).relative_difference(&ob2).unwrap() <= EQ_TOL,
        "message for old B applied"
    );
    assert_eq!(net.stats(B, A).stale, 1);
    // B's link comes up: Hello → A sees the new epoch, initiates the Sync.
    let hello = net.nodes.get_mut(&B).unwrap().0.on_link_up(3.0, A).unwrap();
    net.deliver(3.0, hello.into_iter().map(|o| (B, o)).collect());
    assert_eq!(net.stats(A, B).peer_restarts, 1);
    assert_eq!(net.stats(A, B).syncs_initiated, 2);
    assert_eq!(net.stats(B, A).syncs_applied, 1);
    // A delayed message of old B is now stale at A.
    net.deliver(3.0, from_old_b);
    assert!(net.stats(A, B).stale >= 1);
    for t in 4..8 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    // Old B's information (ob) is gone, the rest is there once.
    let target = oa.add(&ob2).unwrap();
    assert!(net.est(A).relative_difference(&target).unwrap() <= 1e-9);
    assert!(net.est(B).relative_difference(&target).unwrap() <= 1e-9);
}

/// Both sides initiate the same epoch pair (possible when a very old Hello without history
/// reaches a restarted node): the side with history wins the tie-break, the other abandons its
/// Sync and applies the winner's, and nothing is double counted. Setup: A (id 1) and B (id 2)
/// pair; B's Hello from *before* the pairing is delayed; A restarts; the delayed Hello tells
/// new A that B has no history, so A (lower id) initiates; B, with history, initiates too.
#[test]
fn double_initiation_is_resolved_in_favour_of_history() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let feats = features(4, &mut rng);
    let mut net = Net::new(&[(A, B)], DdfConfig::default());
    // B's first Hello (no history, not addressed) is held back.
    let b_hello = net.nodes.get_mut(&B).unwrap().0.on_link_up(0.0, A).unwrap();
    assert!(matches!(b_hello[0].message.body, Body::Hello(h) if !h.history));
    let a_hello = net.nodes.get_mut(&A).unwrap().0.on_link_up(0.0, B).unwrap();
    net.deliver(0.0, a_hello.into_iter().map(|o| (A, o)).collect());
    let m = net.round_all(1.0);
    net.deliver(1.0, m);
    let m = net.round_all(2.0);
    net.deliver(2.0, m);
    assert!(net.nodes[&B].0.channel(A).unwrap().synced);
    let ob = random_observations(&feats, &mut rng, true);
    let oa_old = random_observations(&feats, &mut rng, true);
    net.observe(B, &ob);
    net.observe(A, &oa_old);
    for t in 3..6 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    // A restarts; the stale Hello reaches it first: A initiates (lower id, no history seen).
    net.restart(A, 777, DdfConfig::default());
    let oa = random_observations(&feats, &mut rng, true);
    net.observe(A, &oa);
    let first = net.deliver_one(6.0, B, b_hello[0].clone());
    let (a_sync, rest) = net.pump_holding_syncs(6.0, first);
    assert!(rest.is_empty());
    assert!(
        a_sync
            .iter()
            .any(|(_, o)| matches!(o.message.body, Body::Sync { history: false, .. }))
    );
    // A's Hello reaches B: B challenges A's new epoch, A answers (liveness proof), B adopts it
    // and, having history, initiates as well.
    let a_hello: Vec<_> = net
        .nodes
        .get_mut(&A)
        .unwrap()
        .0
        .on_link_up(6.0, B)
        .unwrap()
        .into_iter()
        .map(|o| (A, o))
        .collect();
    let (syncs, _) = net.pump_holding_syncs(6.0, a_hello);
    let (b_sync, more_a): (Vec<_>, Vec<_>) = syncs.into_iter().partition(|(from, _)| *from == B);
    assert!(
        b_sync
            .iter()
            .any(|(_, o)| matches!(o.message.body, Body::Sync { history: true, .. }))
    );
    assert!(
        more_a
            .iter()
            .all(|(_, o)| matches!(o.message.body, Body::Sync { history: false, .. }))
    );
    // Cross delivery: B ignores A's Sync, A yields to B's.
    let b_applied_before = net.stats(B, A).syncs_applied;
    net.deliver(6.0, a_sync);
    net.deliver(6.0, b_sync);
    assert_eq!(net.stats(A, B).syncs_applied, 1);
    assert_eq!(net.stats(B, A).syncs_applied, b_applied_before);
    for t in 7..12 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    let target = oa.add(&ob).unwrap();
    for id in [A, B] {
        assert!(
            net.est(id).relative_difference(&target).unwrap() <= 1e-9,
            "node {id}"
        );
    }
}

/// Link events: nothing is sent on a link that is down; what accumulated goes out as one delta
/// after it comes up, and the link-up Hello is immediate.
#[test]
fn link_down_holds_back_and_link_up_catches_up() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let feats = features(3, &mut rng);
    let mut net = synced_pair();
    net.nodes.get_mut(&A).unwrap().0.on_link_down(B).unwrap();
    let mut total = MapInformation::zero(origin());
    for t in 1..4 {
        let o = random_observations(&feats, &mut rng, false);
        net.observe(A, &o);
        total.add_assign(&o).unwrap();
        assert!(net.round(A, t as f64).is_empty());
    }
    let up = net.nodes.get_mut(&A).unwrap().0.on_link_up(4.0, B).unwrap();
    assert!(matches!(up[0].message.body, Body::Hello(_)));
    let out = net.round(A, 4.0);
    assert_eq!(deltas(&out).len(), 1);
    net.deliver(4.0, out);
    assert!(net.est(B).relative_difference(&total).unwrap() <= EQ_TOL);
    assert!(
        net.nodes
            .get_mut(&A)
            .unwrap()
            .0
            .on_link_down(NodeId(9))
            .is_err()
    );
}

/// A byte budget the delta cannot fit switches the link to CI, for good and in both
/// directions: submaps flow, exact deltas stop, estimates stay positive definite and never
/// claim more than the two nodes' pooled information.
#[test]
fn tight_budget_switches_the_link_to_ci_in_both_directions() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    let feats = features(6, &mut rng);
    let config = DdfConfig::default();
    let mut net = Net::new(&[(A, B)], config);
    // Budget on A's side only: room for a 2-feature submap, not for a 6-feature delta.
    net.nodes
        .get_mut(&A)
        .unwrap()
        .0
        .set_link_budget(B, Some(canopy_fusion::ci::Submap::wire_bytes_for(2)))
        .unwrap();
    net.link_up_all(0.0);
    let mut pooled = MapInformation::zero(origin());
    for &(id, ref p) in &feats {
        for node in [A, B] {
            let o = direct_observation(id, p, &mut rng);
            net.observe(node, &o);
            pooled.add_assign(&o).unwrap();
        }
    }
    // Round 1: A's delta does not fit, A switches; B (no budget) still sends its delta, which
    // A drops as stale (its channel filter is retired); B switches on A's submap.
    let m = net.round_all(1.0);
    net.deliver(1.0, m);
    assert_eq!(net.stats(A, B).stale, 1);
    let sent_before: Vec<u64> = [(A, B), (B, A)]
        .iter()
        .map(|&(x, y)| net.stats(x, y).deltas_sent)
        .collect();
    assert_eq!(sent_before, vec![0, 1]);
    for t in 2..8 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    for (k, (x, y)) in [(A, B), (B, A)].into_iter().enumerate() {
        let c = net.nodes[&x].0.channel(y).unwrap();
        assert_eq!(c.mode, LinkMode::Ci, "{x} → {y}");
        assert!(
            c.stats.submaps_sent > 0 && c.stats.submaps_fused > 0,
            "{x} → {y}: {:?}",
            c.stats
        );
        assert_eq!(
            c.stats.deltas_sent, sent_before[k],
            "no exact deltas after the switch"
        );
        let est = net.est(x);
        assert!(est.min_eigenvalue().unwrap() > 0.0);
        // CI never exceeds the pooled information (the exact centralized result here).
        assert!(est.psd_excess_over(&pooled).unwrap() <= 1e-9 * pooled.matrix_norm_max());
    }
    // Submaps respect the budget (A's side).
    let out = net.round(A, 9.0);
    for (_, o) in &out {
        if let Body::Submap { submap: s, .. } = &o.message.body {
            assert!(
                s.ids.len() <= 2 && s.wire_bytes() <= canopy_fusion::ci::Submap::wire_bytes_for(2)
            );
        }
    }
}

/// Every submap on a CI link reaches the receiver: two submaps that arrive between two of its
/// rounds are both fused (in arrival order) and acknowledged, and the features of a submap
/// that is lost are sent again once its acknowledgement is overdue (`submap_ack_timeout`),
/// so the receiver ends up holding every feature of the sender.
#[test]
fn ci_submaps_are_all_fused_and_lost_ones_resent() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let feats = features(6, &mut rng);
    let config = DdfConfig::default();
    let timeout = config.submap_ack_timeout;
    let mut net = Net::new(&[(A, B)], config);
    // Room for 2 features per submap on A's side: 3 submaps carry A's 6 features.
    net.nodes
        .get_mut(&A)
        .unwrap()
        .0
        .set_link_budget(B, Some(canopy_fusion::ci::Submap::wire_bytes_for(2)))
        .unwrap();
    net.link_up_all(0.0);
    for &(id, ref p) in &feats {
        let o = direct_observation(id, p, &mut rng);
        net.observe(A, &o);
    }
    let submaps = |q: &Queue| -> Vec<(u64, Vec<u64>)> {
        q.iter()
            .filter_map(|(_, o)| match &o.message.body {
                Body::Submap { seq, submap } => Some((*seq, submap.ids.clone())),
                _ => None,
            })
            .collect()
    };
    // Two rounds of A before B hears anything: A switches to CI, submaps 1 and 2 carry four
    // different features (the first two are in flight, so not chosen again).
    let mut q = net.round(A, 1.0);
    q.extend(net.round(A, 2.0));
    let sent = submaps(&q);
    assert_eq!(sent.len(), 2, "{sent:?}");
    let first_four: std::collections::BTreeSet<u64> =
        sent.iter().flat_map(|s| s.1.clone()).collect();
    assert_eq!(first_four.len(), 4);
    net.deliver(2.0, q);
    // B's round fuses both and acknowledges both.
    let q = net.round(B, 2.5);
    assert_eq!(net.stats(B, A).submaps_fused, 2);
    let acked: Vec<u64> = q
        .iter()
        .filter_map(|(_, o)| match &o.message.body {
            Body::SubmapAck { seqs } => Some(seqs.clone()),
            _ => None,
        })
        .flatten()
        .collect();
    assert_eq!(acked, vec![1, 2]);
    assert_eq!(net.est(B).ids.len(), 4);
    net.deliver(2.5, q);
    assert_eq!(net.stats(A, B).submap_acks, 2);
    // Submap 3, with the last two features, is lost.
    let lost = submaps(&net.round(A, 3.0));
    assert_eq!(lost.len(), 1);
    let last_two = lost[0].1.clone();
    assert!(last_two.iter().all(|id| !first_four.contains(id)));
    // A keeps improving the first four features (they gain information, so they outrank
    // unchanged features). While the lost submap's acknowledgement may still come, its
    // features count as sent (no gain) and are not chosen; once it is overdue they count as
    // never sent (first in priority) and go out again.
    let mut resent_at = None;
    for k in 1..=6 {
        let t = 3.0 + f64::from(k);
        for &(id, ref p) in feats.iter().filter(|f| first_four.contains(&f.0)) {
            let o = direct_observation(id, p, &mut rng);
            net.observe(A, &o);
        }
        let q = net.round(A, t);
        let s = submaps(&q);
        if s.iter().any(|x| x.1 == last_two) {
            resent_at.get_or_insert(t);
        }
        net.deliver(t, q);
        let q = net.round(B, t + 0.5);
        net.deliver(t + 0.5, q);
    }
    let resent_at = resent_at.expect("the lost submap's features were never sent again");
    assert!(
        resent_at > 3.0 + timeout,
        "resent at {resent_at} s, before the acknowledgement was overdue"
    );
    // B holds every feature of A, positive definite, never above A's information.
    let (a, b) = (net.est(A), net.est(B));
    let mut ids_a = a.ids.clone();
    let mut ids_b = b.ids.clone();
    ids_a.sort_unstable();
    ids_b.sort_unstable();
    assert_eq!(ids_a, ids_b);
    assert!(b.min_eigenvalue().unwrap() > 0.0);
    assert!(b.psd_excess_over(a).unwrap() <= 1e-9 * a.matrix_norm_max());
}

/// A message addressed to a different epoch of the receiver is dropped as stale.
#[test]
fn messages_for_another_epoch_of_the_receiver_are_stale() {
    let mut net = synced_pair();
    let msg = DdfMessage {
        header: Header {
            from_epoch: 1001,
            to_epoch: Some(5),
            challenge: 1,
            echo_epoch: 1001,
            echo: 1,
        },
        body: Body::Nack { applied: 0 },
    };
    let (node, est) = net.nodes.get_mut(&B).unwrap();
    assert!(node.on_message(1.0, A, msg, est).unwrap().is_empty());
    assert_eq!(node.channel(A).unwrap().stats.stale, 1);
}

/// A restarts faster than the network delay: B's first restarted incarnation B2 dies before
/// its Hello reaches A, the next one B3 is adopted after proving it is alive; B2's delayed
/// Hello then arrives and must not take the channel back to a dead epoch (it would block the
/// link for good). Both sides still converge.
#[test]
fn a_delayed_message_of_a_dead_incarnation_is_never_adopted() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let feats = features(4, &mut rng);
    let mut net = synced_pair();
    net.restart(B, 2000, DdfConfig::default());
    let b2_hello = net.nodes.get_mut(&B).unwrap().0.on_link_up(1.0, A).unwrap();
    net.restart(B, 3000, DdfConfig::default());
    let b3_hello: Vec<_> = net
        .nodes
        .get_mut(&B)
        .unwrap()
        .0
        .on_link_up(1.0, A)
        .unwrap()
        .into_iter()
        .map(|o| (B, o))
        .collect();
    net.deliver(1.0, b3_hello);
    assert_eq!(net.stats(A, B).peer_restarts, 1);
    let stale_before = net.stats(A, B).stale;
    net.deliver(1.5, b2_hello.into_iter().map(|o| (B, o)).collect());
    assert_eq!(
        net.stats(A, B).peer_restarts,
        1,
        "switched to a dead incarnation"
    );
    assert_eq!(net.stats(A, B).stale, stale_before + 1);
    let (oa, ob) = (
        random_observations(&feats, &mut rng, true),
        random_observations(&feats, &mut rng, true),
    );
    net.observe(A, &oa);
    net.observe(B, &ob);
    for t in 2..6 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    let target = oa.add(&ob).unwrap();
    for id in [A, B] {
        assert!(
            net.est(id).relative_difference(&target).unwrap() <= EQ_TOL,
            "node {id}"
        );
    }
}

/// The history side refuses a Sync from a fresh node that acted on stale knowledge, even when
/// that Sync is the first message of the node's new epoch it accepts (the liveness proof), and
/// initiates instead. Applying it would set C to the fresh node's empty baseline and send back
/// the dead incarnation's information. Setup as in the double-initiation test, but only A's
/// Sync (never its Hellos) reaches B.
#[test]
fn the_history_side_refuses_a_sync_built_on_stale_knowledge() {
    let mut rng = ChaCha8Rng::seed_from_u64(10);
    let feats = features(4, &mut rng);
    let mut net = Net::new(&[(A, B)], DdfConfig::default());
    let b_hello = net.nodes.get_mut(&B).unwrap().0.on_link_up(0.0, A).unwrap();
    let a_hello = net.nodes.get_mut(&A).unwrap().0.on_link_up(0.0, B).unwrap();
    net.deliver(0.0, a_hello.into_iter().map(|o| (A, o)).collect());
    let m = net.round_all(1.0);
    net.deliver(1.0, m);
    let ob = random_observations(&feats, &mut rng, true);
    let oa_old = random_observations(&feats, &mut rng, true);
    net.observe(B, &ob);
    net.observe(A, &oa_old);
    for t in 2..5 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    net.restart(A, 888, DdfConfig::default());
    let oa = random_observations(&feats, &mut rng, true);
    net.observe(A, &oa);
    // The stale Hello makes new A initiate; its Sync reaches B (unknown epoch: challenged).
    let a_out = net.deliver_one(5.0, B, b_hello[0].clone());
    let a_sync: Vec<_> = a_out
        .into_iter()
        .filter(|(_, o)| matches!(o.message.body, Body::Sync { .. }))
        .collect();
    assert_eq!(a_sync.len(), 1);
    let challenge = net.deliver_one(5.0, A, a_sync[0].1.clone());
    assert!(net.stats(B, A).stale >= 1);
    // A learns the challenge; its next Sync resend carries the echo and is the proof.
    for (from, o) in challenge {
        let _ = net.deliver_one(5.0, from, o);
    }
    let resend: Vec<_> = net
        .round(A, 6.0)
        .into_iter()
        .filter(|(_, o)| matches!(o.message.body, Body::Sync { .. }))
        .collect();
    assert_eq!(resend.len(), 1);
    let syncs_applied_before = net.stats(B, A).syncs_applied;
    let b_out = net.deliver_one(6.0, A, resend[0].1.clone());
    assert_eq!(
        net.stats(B, A).peer_restarts,
        1,
        "the Sync proved A's new epoch alive"
    );
    assert_eq!(
        net.stats(B, A).syncs_applied,
        syncs_applied_before,
        "B must refuse it"
    );
    assert!(
        b_out
            .iter()
            .any(|(_, o)| matches!(o.message.body, Body::Sync { history: true, .. }))
    );
    net.deliver(6.0, b_out);
    assert_eq!(net.stats(A, B).syncs_applied, 1);
    for t in 7..12 {
        let m = net.round_all(t as f64);
        net.deliver(t as f64, m);
    }
    let target = oa.add(&ob).unwrap();
    for id in [A, B] {
        assert!(
            net.est(id).relative_difference(&target).unwrap() <= 1e-9,
            "node {id}"
        );
    }
}

/// A lost `Describe` heals: a node holding a key without its descriptor asks its neighbours
/// (`DescribeRequest`), and a neighbour that knows it answers at its next round — under the
/// key the asker used, also when the neighbour has since merged that key into another; a key
/// nobody can describe is not answered. Without the request the descriptor would never come.
#[test]
fn a_lost_describe_is_asked_for_and_answered() {
    use canopy_fusion::ddf::InformationStore;
    use canopy_fusion::keys::Merge;
    let look = [1u64, 2, 3, 4];
    let mut a = DdfNode::new(A, 11, vec![B], origin(), DdfConfig::default());
    let mut b = DdfNode::new(B, 22, vec![A], origin(), DdfConfig::default());
    let (mut sa, mut sb) = (
        InformationStore::new(origin()),
        InformationStore::new(origin()),
    );
    // A knows key 5's descriptor and has merged key 9 (what B calls it) into 5.
    sa.describe(&[(5, look)]);
    sa.merge(&Merge { from: 9, into: 5 }).unwrap();
    a.adopt_merge(9, 5, &mut sa);
    a.on_link_up(0.0, B).unwrap();
    b.on_link_up(0.0, A).unwrap();
    b.request_descriptors(&[9, 8]);
    let out = b.on_round(1.0, &mut sb).unwrap().messages;
    let asked: Vec<&DdfMessage> = out
        .iter()
        .map(|o| &o.message)
        .filter(|m| matches!(m.body, Body::DescribeRequest { .. }))
        .collect();
    assert_eq!(asked.len(), 1);
    for m in out {
        a.on_message(1.0, B, m.message, &mut sa).unwrap();
    }
    let answer: Vec<Outgoing> = a
        .on_round(2.0, &mut sa)
        .unwrap()
        .messages
        .into_iter()
        .filter(|o| matches!(o.message.body, Body::Describe { .. }))
        .collect();
    assert_eq!(answer.len(), 1);
    let Body::Describe { features } = &answer[0].message.body else {
        unreachable!()
    };
    assert_eq!(
        features,
        &vec![(9, look)],
        "only the key A can describe, as B named it"
    );
    for m in answer {
        b.on_message(2.0, A, m.message, &mut sb).unwrap();
    }
    assert_eq!(sb.descriptor(9), Some(&look));
    assert_eq!(sb.descriptor(8), None);
    // Answered once: the next round of A carries no Describe.
    assert!(
        a.on_round(3.0, &mut sa)
            .unwrap()
            .messages
            .iter()
            .all(|o| !matches!(o.message.body, Body::Describe { .. }))
    );
}
