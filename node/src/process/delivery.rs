//! Simulation-time delivery of DDF messages in a vehicle process (`[fusion] delivery =
//! "simulation_time"`).
//!
//! With arrival delivery (the default) a vehicle hands a neighbour's message to its fusion half
//! as soon as it arrives, so which round fuses it — and with it every later linearisation point
//! and association decision — depends on how the processes were scheduled: the same scenario
//! spreads from run to run (tree-8, 60 s, on one host: team map RMSE 1.887–1.911 m in three
//! runs at load ~10, 3 % over five runs at load ~20; isolated runs, which exchange nothing, are
//! identical bit for bit).
//!
//! Here every exchange happens at simulation-time boundaries instead:
//! - a message's time is its sender's round time (the envelope's simulation time: a vehicle
//!   sends only at its rounds — the round's deltas and the replies to what it applied there);
//! - after each round a vehicle sends a **time marker** ([`MessageKind::TIME_MARKER`]) on every
//!   link, stamped with the round's time: it has sent everything it stamps up to then (links are
//!   FIFO);
//! - a message stamped `t` is applied at the receiver's first round at or after `t + delay`
//!   (`delay` = one round period), in a fixed order (link events, then messages by neighbour id,
//!   each neighbour's in the order sent), before that round;
//! - before its round at `T`, a vehicle waits until every neighbour on a *gated* link (fault-free,
//!   no radio model: nothing on it is lost or held back) is up and has marked `T − delay`; at its
//!   first round it waits for every such link to be up, so the links come up at the same
//!   simulated instant in every run.
//!
//! The wait cannot deadlock: what `i` waits for at `T` (a neighbour's round in
//! `[T − delay, T)`, marked when that round's copy is taken back at its next frame) lies less
//! than a frame interval past `T`, and the neighbour, to get there, waits only for `i`'s rounds
//! before `T`, which `i` has done; the worlds' flow control lets any vehicle run `max_lead_s`
//! ahead of the slowest. A link that goes down after it was up (a crash, a cut) is no longer
//! waited for: faults make a run depend on timing anyway.

use std::collections::{BTreeMap, VecDeque};

use canopy_fusion::ddf::DdfMessage;
use canopy_transport::NodeId;
use canopy_transport::link::LinkEvent;

/// Slack on simulated times that should be equal (round times from different sums).
const EPS: f64 = 1e-9;

/// What one neighbour has delivered, not yet applied.
#[derive(Debug, Default)]
struct Inbox {
    /// Waited for at every round (a fault-free link without radio model).
    gated: bool,
    /// The link is up now.
    up: bool,
    /// Its `PeerUp` has been applied once.
    announced: bool,
    /// It went down after it was up: no longer waited for.
    lost: bool,
    /// Everything it stamps up to this time has arrived (its latest marker).
    marked: f64,
    /// Link events not yet applied, in arrival order.
    events: Vec<LinkEvent>,
    /// Messages not yet applied, in arrival order (their stamps ascend).
    queue: VecDeque<(f64, DdfMessage)>,
}

/// One thing to hand to the fusion half before a round, in order.
#[derive(Debug)]
pub(crate) enum Due {
    /// A link event of neighbour `.0`.
    Event(NodeId, LinkEvent),
    /// A message of neighbour `.0`.
    Message(NodeId, Box<DdfMessage>),
}

/// The simulation-time gate of one vehicle's links.
#[derive(Debug)]
pub(crate) struct SimTimeDelivery {
    delay: f64,
    start: f64,
    inboxes: BTreeMap<NodeId, Inbox>,
}

impl SimTimeDelivery {
    /// A gate for the links to `peers` (`(neighbour, gated)`), applying a message stamped `t`
    /// at the first round at or after `t + delay`, for a vehicle whose stream starts at `start`
    /// (no neighbour stamps anything before its own start, which is the team's).
    pub fn new(delay: f64, start: f64, peers: impl IntoIterator<Item = (NodeId, bool)>) -> Self {
        Self {
            delay,
            start,
            inboxes: peers
                .into_iter()
                .map(|(p, gated)| {
                    (
                        p,
                        Inbox {
                            gated,
                            marked: f64::NEG_INFINITY,
                            ..Inbox::default()
                        },
                    )
                })
                .collect(),
        }
    }

    /// What a link delivered: its events, its messages with their stamps (in arrival order) and
    /// its latest time marker.
    pub fn push(
        &mut self,
        peer: NodeId,
        events: Vec<LinkEvent>,
        msgs: Vec<(f64, DdfMessage)>,
        marker: Option<f64>,
    ) {
        let Some(b) = self.inboxes.get_mut(&peer) else {
            return;
        };
        for e in events {
            match e {
                LinkEvent::PeerUp => b.up = true,
                LinkEvent::PeerDown => {
                    b.up = false;
                    b.lost |= b.announced;
                }
            }
            b.events.push(e);
        }
        b.queue.extend(msgs);
        if let Some(m) = marker {
            b.marked = b.marked.max(m);
        }
    }

    /// The neighbours the round at `round` must still wait for (empty: it may go): every gated
    /// link not lost must be up and, unless nothing can be stamped that early, marked up to
    /// `round − delay`.
    pub fn waiting_for(&self, round: f64) -> Vec<NodeId> {
        let due = round - self.delay;
        self.inboxes
            .iter()
            .filter(|(_, b)| b.gated && !b.lost)
            .filter(|(_, b)| !b.up || (due >= self.start + EPS && b.marked < due - EPS))
            .map(|(&p, _)| p)
            .collect()
    }

    /// What to apply before the round at `round`, in order: every neighbour's pending link
    /// events, then its messages stamped up to `round − delay`, neighbour by neighbour (id
    /// order).
    pub fn due(&mut self, round: f64) -> Vec<Due> {
        let due = round - self.delay + EPS;
        let mut out = Vec::new();
        for (&p, b) in &mut self.inboxes {
            for e in b.events.drain(..) {
                b.announced |= e == LinkEvent::PeerUp;
                out.push(Due::Event(p, e));
            }
        }
        for (&p, b) in &mut self.inboxes {
            while b.queue.front().is_some_and(|(t, _)| *t <= due) {
                let (_, m) = b.queue.pop_front().expect("checked");
                out.push(Due::Message(p, Box::new(m)));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_fusion::ddf::{Body, Header};

    fn msg(seq: u64) -> DdfMessage {
        DdfMessage {
            header: Header {
                from_epoch: 1,
                to_epoch: None,
                challenge: 0,
                echo_epoch: 0,
                echo: 0,
            },
            body: Body::Nack { applied: seq },
        }
    }

    fn seqs(d: &[Due]) -> Vec<String> {
        d.iter()
            .map(|x| match x {
                Due::Event(p, e) => format!("{p}:{e:?}"),
                Due::Message(p, m) => match m.body {
                    Body::Nack { applied } => format!("{p}:{applied}"),
                    _ => format!("{p}:?"),
                },
            })
            .collect()
    }

    /// A message is applied at the first round one period after its stamp, never earlier, in
    /// the order sent; a round waits for a marker of that time from every gated neighbour, and
    /// for every gated link to be up; an ungated link is never waited for.
    #[test]
    fn messages_wait_for_their_round_and_rounds_for_their_markers() {
        // Rounds every 1 s at phase 0.25 from t = 0; neighbours 2 (gated) and 5 (not).
        let mut g = SimTimeDelivery::new(1.0, 0.0, [(2, true), (5, false)]);
        assert_eq!(
            g.waiting_for(0.25),
            vec![2],
            "the first round waits for the link"
        );
        g.push(2, vec![LinkEvent::PeerUp], vec![], None);
        // Nothing can be stamped before the start: the first round goes.
        assert!(g.waiting_for(0.25).is_empty());
        assert_eq!(seqs(&g.due(0.25)), vec!["2:PeerUp"]);
        // Neighbour 2's rounds at 0.5 and 1.5 send messages 1, 2 then 3.
        g.push(2, vec![], vec![(0.5, msg(1)), (0.5, msg(2))], Some(0.5));
        assert!(g.waiting_for(1.25).is_empty());
        // 0.5 + 1 > 1.25: not yet.
        assert!(g.due(1.25).is_empty());
        // The round at 2.25 needs everything stamped up to 1.25: marker 0.5 is not enough.
        assert_eq!(g.waiting_for(2.25), vec![2]);
        g.push(2, vec![], vec![(1.5, msg(3))], Some(1.5));
        assert!(g.waiting_for(2.25).is_empty());
        assert_eq!(seqs(&g.due(2.25)), vec!["2:1", "2:2"]);
        assert_eq!(seqs(&g.due(3.25)), vec!["2:3"]);
        // Neighbour 5 sends no marker and is never waited for; its messages still wait for
        // their round.
        g.push(5, vec![LinkEvent::PeerUp], vec![(3.0, msg(9))], None);
        g.push(2, vec![], vec![], Some(3.5));
        assert!(g.waiting_for(4.25).is_empty());
        assert_eq!(seqs(&g.due(3.5)), vec!["5:PeerUp"]);
        assert_eq!(seqs(&g.due(4.25)), vec!["5:9"]);
    }

    /// A gated link that goes down after it was up is no longer waited for (a crash or a cut
    /// must not stop the team); before it was ever up it is (the first round).
    #[test]
    fn a_lost_link_is_not_waited_for() {
        let mut g = SimTimeDelivery::new(1.0, 0.0, [(2, true)]);
        g.push(2, vec![LinkEvent::PeerDown], vec![], None);
        assert_eq!(g.waiting_for(0.5), vec![2], "never up: still waited for");
        g.push(2, vec![LinkEvent::PeerUp], vec![], None);
        assert_eq!(seqs(&g.due(0.5)), vec!["2:PeerDown", "2:PeerUp"]);
        assert_eq!(g.waiting_for(5.5), vec![2], "up, not marked");
        g.push(2, vec![LinkEvent::PeerDown], vec![], None);
        assert!(g.waiting_for(5.5).is_empty(), "lost");
    }
}
