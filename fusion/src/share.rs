//! Data sharing: every vehicle's *data* relayed over the tree, record by record, so that each
//! node can run the team's EKF itself (docs/arch/sharing.md).
//!
//! The channel filters of [`crate::ddf`] share map information. On links of tens of kB/s a
//! sparsified delta leaves a high-rank residual pending (the vehicle–map cross-information of
//! every round, docs/benchmarks.md "Thirteenth pass"), and the map's means lag the centralized
//! filter's by 10–15 %. A vehicle's data is ~1 kB/s whatever the map's size (IMU increments at
//! 10 Hz and its observation frames), so a tree of radios can carry every vehicle's data to
//! every node, where the centralized EKF over all of it is the reference itself, delayed.
//!
//! This module is the relay, sans I/O and generic over the record ([`ShareRecord`]):
//!
//! - Each node publishes its own records into its stream ([`StreamId`]: the origin and an
//!   epoch that is fresh for every process start), numbered 0, 1, 2, …
//! - Each round it sends each neighbour a [`Batch`]: what it holds of every stream (a
//!   cumulative acknowledgement, `have`) and the records the neighbour lacks of the streams
//!   it forwards to it, round-robin over the streams, up to the round's byte budget.
//! - A stream is forwarded to every neighbour except the one the tree routes its origin
//!   through (which holds it), and it is accepted only from that neighbour: a record of
//!   another origin arriving over another link is refused ([`ShareError::WrongRoute`]).
//!   A node's own streams of earlier epochs (from before a restart) come back from any
//!   neighbour: they are data about the map like any other.
//! - Records are delivered to the estimator ([`Relay::take_ready`]) once, in their stream's
//!   order; records past a gap wait (at most [`RelayConfig::max_ahead`] per stream).
//! - Losses are repaired by going back: when a neighbour's acknowledgements have not moved for
//!   [`RelayConfig::retransmit_after`] while it lacks records sent to it, or the link comes
//!   back up, sending restarts from what it acknowledged. A neighbour whose batch
//!   comes with a new epoch has restarted and lost its streams: they are sent again from what
//!   it holds now. Batches are numbered per link, so the acknowledgements of a batch that
//!   arrives after a later one (reordered) are not taken.
//!
//! Bytes per link per second are bounded by the data rates of the vehicles whose streams the
//! link forwards, independent of the map (and a backlog after an outage drains at the budget).

use std::collections::{BTreeMap, VecDeque};

use serde::{Deserialize, Serialize};

use crate::ins::{VehicleCovariance, VehicleState};
use crate::sensor::{ImuSample, Measurement, ObservationFrame};
use crate::topology::{NodeId, Topology, TopologyError};

/// A record's number in its stream, from 0.
pub type Seq = u64;

/// One stream: the records of one origin's process start.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct StreamId {
    /// The vehicle whose data it is.
    pub origin: NodeId,
    /// Fresh for every start of the origin's process.
    pub epoch: u64,
}

/// What the relay needs of a record.
pub trait ShareRecord: Clone {
    /// Bytes it takes in a batch on the wire (for the budget).
    fn wire_bytes(&self) -> usize;
    /// Checks its content (finite, in range); `Err` says why not.
    fn validate(&self) -> Result<(), String>;
}

/// Bytes a batch spends per `have` entry (stream id and count), for the budget.
pub const HAVE_ENTRY_BYTES: usize = 4 + 8 + 8;
/// Bytes of a batch's own header (epoch, number, the two list lengths).
pub const BATCH_HEADER_BYTES: usize = 8 + 8 + 2 + 2;
/// Bytes a batch spends per record besides the record (stream index and sequence number).
pub const RECORD_HEADER_BYTES: usize = 2 + 8;

/// One round's message from a node to a neighbour.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Batch<R> {
    /// The sender's epoch (its own stream's).
    pub epoch: u64,
    /// Numbers the sender's batches to this neighbour within its epoch, from 1: a batch that
    /// arrives after a later one (reordered) carries older acknowledgements, which are not
    /// taken.
    pub number: u64,
    /// Every stream the sender holds and how many of its records, contiguous from the first.
    pub have: Vec<(StreamId, u64)>,
    /// Records the receiver lacks: (stream, number, record).
    pub records: Vec<(StreamId, Seq, R)>,
}

impl<R: ShareRecord> Batch<R> {
    /// Its size on the wire as the budget counts it.
    pub fn wire_bytes(&self) -> usize {
        BATCH_HEADER_BYTES
            + self.have.len() * HAVE_ENTRY_BYTES
            + self
                .records
                .iter()
                .map(|(_, _, r)| RECORD_HEADER_BYTES + r.wire_bytes())
                .sum::<usize>()
    }
}

/// Relay options.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RelayConfig {
    /// Records of one stream kept past a gap; a record further ahead is refused (sent again
    /// once the gap is filled).
    pub max_ahead: usize,
    /// Seconds without progress of a neighbour's acknowledgements, while it lacks records
    /// sent to it, after which sending goes back to what it acknowledged.
    pub retransmit_after: f64,
    /// Streams (process starts) accepted per origin.
    pub max_streams_per_origin: usize,
}

impl Default for RelayConfig {
    fn default() -> Self {
        Self {
            max_ahead: 4096,
            retransmit_after: 3.0,
            max_streams_per_origin: 16,
        }
    }
}

/// Why a batch or one of its records was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ShareError {
    /// The batch came from a node that is not a neighbour.
    #[error("a batch from {0}, which is not a neighbour of this node")]
    NotNeighbour(NodeId),
    /// A record of an origin outside the team.
    #[error("a record of {0}, which is not in the team")]
    NotInTeam(NodeId),
    /// A record of another origin over a link the tree does not route it through.
    #[error("a record of {origin} from {from}; the tree routes {origin} through {expected}")]
    WrongRoute {
        /// The stream's origin.
        origin: NodeId,
        /// The neighbour it came from.
        from: NodeId,
        /// The neighbour it must come from.
        expected: NodeId,
    },
    /// This node's own current stream, sent back to it.
    #[error("this node's own current stream came back from {0}")]
    OwnStream(NodeId),
    /// A record too far past a gap.
    #[error("record {seq} of {stream:?} is more than {max} past the {held} held")]
    TooFarAhead {
        /// The stream.
        stream: StreamId,
        /// Its number.
        seq: Seq,
        /// Records held contiguously.
        held: u64,
        /// [`RelayConfig::max_ahead`].
        max: usize,
    },
    /// More process starts of one origin than [`RelayConfig::max_streams_per_origin`].
    #[error("more than {max} streams of {origin}")]
    TooManyStreams {
        /// The origin.
        origin: NodeId,
        /// The bound.
        max: usize,
    },
    /// A record whose content is invalid.
    #[error("record {seq} of {stream:?} is invalid: {reason}")]
    InvalidRecord {
        /// The stream.
        stream: StreamId,
        /// Its number.
        seq: Seq,
        /// Why.
        reason: String,
    },
    /// The topology is not a tree containing this node.
    #[error(transparent)]
    Topology(#[from] TopologyError),
    /// This node is not in the topology.
    #[error("{0} is not in the topology")]
    NotInTopology(NodeId),
}

impl ShareError {
    /// A short stable name for counting by reason.
    pub fn reason(&self) -> &'static str {
        match self {
            Self::NotNeighbour(_) => "not_neighbour",
            Self::NotInTeam(_) => "not_in_team",
            Self::WrongRoute { .. } => "wrong_route",
            Self::OwnStream(_) => "own_stream",
            Self::TooFarAhead { .. } => "too_far_ahead",
            Self::TooManyStreams { .. } => "too_many_streams",
            Self::InvalidRecord { .. } => "invalid_record",
            Self::Topology(_) => "topology",
            Self::NotInTopology(_) => "not_in_topology",
        }
    }
}

/// What a batch brought.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Received {
    /// New records (held now, in order or waiting past a gap).
    pub accepted: usize,
    /// Records already held.
    pub duplicates: usize,
    /// Records refused, each with its reason.
    pub refused: Vec<ShareError>,
}

#[derive(Clone, Debug)]
struct Stream<R> {
    records: Vec<R>,
    ahead: BTreeMap<Seq, R>,
    delivered: usize,
}

impl<R> Default for Stream<R> {
    fn default() -> Self {
        Self {
            records: Vec::new(),
            ahead: BTreeMap::new(),
            delivered: 0,
        }
    }
}

#[derive(Clone, Debug, Default)]
struct Peer {
    up: bool,
    /// What the neighbour said it holds, per stream.
    acked: BTreeMap<StreamId, u64>,
    /// The next record to send it, per stream.
    next: BTreeMap<StreamId, u64>,
    /// When its acknowledgements last moved (or sending last went back).
    last_progress: f64,
    /// Round-robin start.
    cursor: usize,
    /// Batches sent to it in this epoch.
    sent_batches: u64,
    /// The epoch and number of the last batch whose acknowledgements were taken.
    heard: Option<(u64, u64)>,
}

/// Counters of a relay.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RelayCounters {
    /// Records published by this node.
    pub published: u64,
    /// Records accepted from neighbours.
    pub accepted: u64,
    /// Records received again.
    pub duplicates: u64,
    /// Records or batches refused.
    pub refused: u64,
    /// Records sent (first sends and repeats).
    pub sent: u64,
    /// Times sending went back to a neighbour's acknowledgement (loss, restart, link up).
    pub rewinds: u64,
}

/// The relay of one node (module docs).
#[derive(Clone, Debug)]
pub struct Relay<R> {
    me: NodeId,
    own: StreamId,
    /// The neighbour the tree routes each other node through.
    route: BTreeMap<NodeId, NodeId>,
    streams: BTreeMap<StreamId, Stream<R>>,
    peers: BTreeMap<NodeId, Peer>,
    config: RelayConfig,
    counters: RelayCounters,
}

impl<R: ShareRecord> Relay<R> {
    /// The relay of `me` (started with `epoch`, fresh per process start) on `topology`, a
    /// tree. Links start up.
    pub fn new(
        me: NodeId,
        epoch: u64,
        topology: &Topology,
        config: RelayConfig,
    ) -> Result<Self, ShareError> {
        topology.require_tree()?;
        let neighbours = topology
            .neighbours(me)
            .ok_or(ShareError::NotInTopology(me))?;
        let mut route = BTreeMap::new();
        for &n in topology.nodes() {
            if n == me {
                continue;
            }
            if let Some(path) = topology.path(me, n)
                && let Some(&hop) = path.get(1)
            {
                route.insert(n, hop);
            }
        }
        let peers = neighbours
            .iter()
            .map(|&p| {
                (
                    p,
                    Peer {
                        up: true,
                        ..Peer::default()
                    },
                )
            })
            .collect();
        let own = StreamId { origin: me, epoch };
        let mut streams = BTreeMap::new();
        streams.insert(own, Stream::default());
        Ok(Self {
            me,
            own,
            route,
            streams,
            peers,
            config,
            counters: RelayCounters::default(),
        })
    }

    /// This node's current stream.
    pub fn own_stream(&self) -> StreamId {
        self.own
    }

    /// Counters so far.
    pub fn counters(&self) -> RelayCounters {
        self.counters
    }

    /// Every stream held and how many of its records, contiguous from the first.
    pub fn have(&self) -> Vec<(StreamId, u64)> {
        self.streams
            .iter()
            .map(|(id, s)| (*id, s.records.len() as u64))
            .collect()
    }

    /// The records held of `stream`, contiguous from the first.
    pub fn records(&self, stream: StreamId) -> &[R] {
        self.streams.get(&stream).map_or(&[], |s| &s.records)
    }

    /// Appends a record to this node's stream; its number.
    pub fn publish(&mut self, record: R) -> Result<Seq, ShareError> {
        let stream = self.streams.entry(self.own).or_default();
        let seq = stream.records.len() as Seq;
        record
            .validate()
            .map_err(|reason| ShareError::InvalidRecord {
                stream: self.own,
                seq,
                reason,
            })?;
        stream.records.push(record);
        self.counters.published += 1;
        Ok(seq)
    }

    /// Records not yet delivered, per stream in order (each record once, ever).
    pub fn take_ready(&mut self) -> Vec<(StreamId, Seq, R)> {
        let mut out = Vec::new();
        for (id, s) in &mut self.streams {
            for (k, r) in s.records.iter().enumerate().skip(s.delivered) {
                out.push((*id, k as Seq, r.clone()));
            }
            s.delivered = s.records.len();
        }
        out
    }

    /// The link to `peer` went down: nothing is sent to it until it is up again.
    pub fn on_link_down(&mut self, peer: NodeId) {
        if let Some(p) = self.peers.get_mut(&peer) {
            p.up = false;
        }
    }

    /// The link to `peer` is up (again): sending restarts from what it acknowledged.
    pub fn on_link_up(&mut self, peer: NodeId, now: f64) {
        if let Some(p) = self.peers.get_mut(&peer) {
            p.up = true;
            p.next = p.acked.clone();
            p.last_progress = now;
            self.counters.rewinds += 1;
        }
    }

    /// Whether the stream is forwarded to `peer`: not when the tree routes its origin through
    /// `peer` (it came from there) — unless `peer` is the origin itself, which after a restart
    /// lacks its earlier streams (its acknowledgements say what it holds, so its current
    /// stream is never echoed).
    fn forwards(&self, stream: StreamId, peer: NodeId) -> bool {
        stream.origin == self.me
            || stream.origin == peer
            || self.route.get(&stream.origin) != Some(&peer)
    }

    /// The batch for `peer` this round, within `budget` bytes (at least one record when any is
    /// due, so that a record larger than the budget cannot stall the link); `None` while the
    /// link is down.
    pub fn outgoing(&mut self, peer: NodeId, budget: usize, now: f64) -> Option<Batch<R>> {
        let have = self.have();
        let eligible: Vec<StreamId> = self
            .streams
            .keys()
            .copied()
            .filter(|&id| self.forwards(id, peer))
            .collect();
        let p = self.peers.get_mut(&peer)?;
        if !p.up {
            return None;
        }
        let lacking = eligible
            .iter()
            .any(|id| p.next.get(id).copied().unwrap_or(0) > p.acked.get(id).copied().unwrap_or(0));
        if lacking && now - p.last_progress >= self.config.retransmit_after {
            p.next = p.acked.clone();
            p.last_progress = now;
            self.counters.rewinds += 1;
        }
        p.sent_batches += 1;
        let mut batch = Batch {
            epoch: self.own.epoch,
            number: p.sent_batches,
            have,
            records: Vec::new(),
        };
        let mut used = BATCH_HEADER_BYTES + batch.have.len() * HAVE_ENTRY_BYTES;
        if !eligible.is_empty() {
            let mut queue: VecDeque<StreamId> = eligible
                .iter()
                .cycle()
                .skip(p.cursor % eligible.len())
                .take(eligible.len())
                .copied()
                .collect();
            p.cursor = p.cursor.wrapping_add(1);
            while let Some(id) = queue.pop_front() {
                let Some(stream) = self.streams.get(&id) else {
                    continue;
                };
                let next = p.next.entry(id).or_insert(0);
                let acked = p.acked.get(&id).copied().unwrap_or(0);
                *next = (*next).max(acked);
                let Some(r) = stream.records.get(*next as usize) else {
                    continue;
                };
                let bytes = RECORD_HEADER_BYTES + r.wire_bytes();
                if used + bytes > budget && !batch.records.is_empty() {
                    break;
                }
                used += bytes;
                batch.records.push((id, *next, r.clone()));
                *next += 1;
                self.counters.sent += 1;
                queue.push_back(id);
            }
        }
        Some(batch)
    }

    /// Takes a neighbour's batch: its acknowledgements and the records this node lacks.
    /// `Err` refuses the whole batch (a sender that is not a neighbour); refused records are
    /// listed in [`Received::refused`] and change nothing.
    pub fn on_batch(
        &mut self,
        from: NodeId,
        batch: Batch<R>,
        now: f64,
    ) -> Result<Received, ShareError> {
        if !self.peers.contains_key(&from) {
            self.counters.refused += 1;
            return Err(ShareError::NotNeighbour(from));
        }
        // Records first, so that the acknowledgements below cover the streams they start.
        let mut out = Received::default();
        let mut sender_holds: BTreeMap<StreamId, u64> = BTreeMap::new();
        for (id, seq, record) in batch.records {
            match self.accept(from, id, seq, record) {
                Ok(true) => out.accepted += 1,
                Ok(false) => out.duplicates += 1,
                Err(e) => {
                    out.refused.push(e);
                    continue;
                }
            }
            // A sender sends only records it holds contiguously: it holds seq + 1 of them
            // (so even a reordered batch keeps this node from echoing them back).
            let n = sender_holds.entry(id).or_insert(0);
            *n = (*n).max(seq + 1);
        }
        let Some(p) = self.peers.get_mut(&from) else {
            return Ok(out);
        };
        if p.heard.is_none_or(|(e, _)| e == batch.epoch) {
            for (id, n) in sender_holds {
                let acked = p.acked.entry(id).or_insert(0);
                *acked = (*acked).max(n);
            }
        }
        // Its acknowledgements, unless a later batch of its epoch was heard already. A new
        // epoch is a restart: it holds what it lists now, and sending goes back to that.
        let restarted = p.heard.is_some_and(|(e, _)| e != batch.epoch);
        let fresh = match p.heard {
            Some((e, n)) => e != batch.epoch || batch.number > n,
            None => true,
        };
        if fresh {
            p.heard = Some((batch.epoch, batch.number));
            // A stream it does not list, it does not hold (the list is complete). Entries for
            // streams this node does not hold are not needed (and a hostile list of them must
            // not grow the books).
            let listed: BTreeMap<StreamId, u64> = batch.have.iter().copied().collect();
            for id in self.streams.keys() {
                let n = listed.get(id).copied().unwrap_or(0);
                let acked = p.acked.entry(*id).or_insert(0);
                if n > *acked {
                    *acked = n;
                    p.last_progress = now;
                } else if n < *acked && restarted {
                    *acked = n;
                }
            }
            if restarted {
                p.next = p.acked.clone();
                p.last_progress = now;
                self.counters.rewinds += 1;
            }
        }
        self.counters.accepted += out.accepted as u64;
        self.counters.duplicates += out.duplicates as u64;
        self.counters.refused += out.refused.len() as u64;
        Ok(out)
    }

    /// One record; `Ok(false)` when already held.
    fn accept(&mut self, from: NodeId, id: StreamId, seq: Seq, r: R) -> Result<bool, ShareError> {
        if id.origin == self.me {
            if id == self.own {
                return Err(ShareError::OwnStream(from));
            }
        } else {
            let expected = *self
                .route
                .get(&id.origin)
                .ok_or(ShareError::NotInTeam(id.origin))?;
            if expected != from {
                return Err(ShareError::WrongRoute {
                    origin: id.origin,
                    from,
                    expected,
                });
            }
        }
        if !self.streams.contains_key(&id) {
            let of_origin = self
                .streams
                .keys()
                .filter(|s| s.origin == id.origin)
                .count();
            if of_origin >= self.config.max_streams_per_origin {
                return Err(ShareError::TooManyStreams {
                    origin: id.origin,
                    max: self.config.max_streams_per_origin,
                });
            }
        }
        let held = self.streams.get(&id).map_or(0, |s| s.records.len() as u64);
        if seq < held
            || self
                .streams
                .get(&id)
                .is_some_and(|s| s.ahead.contains_key(&seq))
        {
            return Ok(false);
        }
        if seq - held > self.config.max_ahead as u64 {
            return Err(ShareError::TooFarAhead {
                stream: id,
                seq,
                held,
                max: self.config.max_ahead,
            });
        }
        r.validate().map_err(|reason| ShareError::InvalidRecord {
            stream: id,
            seq,
            reason,
        })?;
        let s = self.streams.entry(id).or_default();
        if seq == held {
            s.records.push(r);
            while let Some(next) = s.ahead.remove(&(s.records.len() as Seq)) {
                s.records.push(next);
            }
        } else {
            s.ahead.insert(seq, r);
        }
        Ok(true)
    }
}

/// Most observations one shared frame may carry (more is refused as malformed).
pub const MAX_FRAME_OBSERVATIONS: usize = 4096;

/// A record of a vehicle's stream in data sharing: what its own estimator took, in order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Item {
    /// The vehicle's initial estimate: the first record of every stream.
    Start {
        /// The estimate.
        state: VehicleState,
        /// Its covariance (boxed: 1.8 kB, once per stream).
        covariance: Box<VehicleCovariance>,
    },
    /// IMU samples summed into one increment: the mean specific force and rate over its Δt
    /// (Δv / Δt, Δθ / Δt), ending at its time.
    Imu(ImuSample),
    /// A terrain-sensor frame as the vehicle's estimator took it (tracker ids, appearance).
    Frame(ObservationFrame),
}

impl ShareRecord for Item {
    /// An upper bound of bincode's standard encoding (f64 fixed, integers varint ≤ 9).
    fn wire_bytes(&self) -> usize {
        1 + match self {
            Item::Start { .. } => 15 * 8 + 225 * 8,
            Item::Imu(_) => 8 * 8,
            Item::Frame(f) => {
                8 + 9
                    + f.observations
                        .iter()
                        .map(|o| {
                            9 + 1
                                + match o.z {
                                    Measurement::RangeBearing(_) => 24,
                                    Measurement::Bearing(_) | Measurement::Pixel(_) => 16,
                                }
                                + 1
                                + if o.appearance.is_some() { 4 * 9 } else { 0 }
                        })
                        .sum::<usize>()
            }
        }
    }

    fn validate(&self) -> Result<(), String> {
        match self {
            Item::Start { state, covariance } => {
                if !state.is_finite() {
                    return Err("start state not finite".into());
                }
                if !covariance.iter().all(|v| v.is_finite()) {
                    return Err("start covariance not finite".into());
                }
                if covariance.cholesky().is_none() {
                    return Err("start covariance not positive definite".into());
                }
                Ok(())
            }
            Item::Imu(s) => {
                let finite = s.time.is_finite()
                    && s.specific_force
                        .iter()
                        .chain(s.angular_rate.iter())
                        .all(|v| v.is_finite());
                if !finite {
                    Err("IMU increment not finite".into())
                } else if !(s.dt.is_finite() && s.dt > 0.0) {
                    Err(format!("IMU increment Δt {} not positive", s.dt))
                } else {
                    Ok(())
                }
            }
            Item::Frame(f) => {
                if !f.time.is_finite() {
                    Err("frame time not finite".into())
                } else if f.observations.len() > MAX_FRAME_OBSERVATIONS {
                    Err(format!(
                        "{} observations in a frame (at most {MAX_FRAME_OBSERVATIONS})",
                        f.observations.len()
                    ))
                } else {
                    // The estimator refuses a non-finite measurement alone
                    // (`RejectReason::InvalidMeasurement`), as for its own frames.
                    Ok(())
                }
            }
        }
    }
}

#[cfg(test)]
mod tests;
