//! The per-process DDF state machine: one [`DdfNode`] per vehicle or hub, one channel per
//! configured neighbour.

use super::channel::{Channel, ChannelStats, LazyInformation, NodeCtx};
use super::message::Body;
use super::message::{DdfMessage, MAX_LIST, Outgoing};
use super::{FuseRejected, FuseTarget, LinkMode, MapSource, Mode};
use crate::ci::CiCriterion;
use crate::info::InfoError;
use crate::keys::{KeyMap, Merge};
use crate::sensor::FeatureId;
use crate::topology::{NodeId, Topology, TopologyError};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Protocol parameters. Times are in the caller's clock units (seconds in the node process,
/// rounds in a lock-step simulation).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DdfConfig {
    /// Interval between Hellos on each link.
    pub hello_interval: f64,
    /// How long a gap in the received sequence may persist before a Nack (and between Nacks).
    pub gap_timeout: f64,
    /// Interval between resends of an unacknowledged Sync.
    pub sync_resend_interval: f64,
    /// Out-of-order deltas buffered per link; beyond it a Nack is sent at once.
    pub max_buffer: usize,
    /// A block of a delta is not sent while its max-abs is at most this times max|Y_i| (for Y)
    /// or max|y_i| (for y). It stays in Y_i − C_ik and goes out once it grows: nothing is lost.
    /// The default 1e-12 is ~4500 ulps: above the round-off left by aligned sums (so a quiet
    /// network sends no deltas), far below any tolerance a user would judge estimates by.
    pub block_threshold_rel: f64,
    /// Per-link byte budget of one round's delta (`None`: unlimited). A delta that does not fit
    /// switches the link to covariance intersection for good (design.md §4). Recovery messages
    /// (Sync, Cumulative) are exempt.
    pub byte_budget: Option<usize>,
    /// What CI's ω minimises.
    pub ci_criterion: CiCriterion,
    /// On a CI link, how long a sent submap may stay unacknowledged before its features count
    /// as unsent again (and are resent by priority).
    #[serde(default = "default_submap_ack_timeout")]
    pub submap_ack_timeout: f64,
    /// Precision of the Y blocks of deltas on the wire: exact f64, or f32 made conservative
    /// (Y_q ⪯ Y, [`MapInformation::quantized_f32_conservative`]) — half the bytes per block;
    /// what is held back stays in Y − C and goes out with later deltas.
    #[serde(default)]
    pub delta_precision: DeltaPrecision,
    /// How many retired epochs of each peer are remembered (messages from them are dropped),
    /// and how many unproven candidate epochs are kept.
    pub retired_epochs: usize,
    /// On a capacity-limited link (one with a byte budget), the shortest time [s] between two
    /// rounds that form its delta (or CI submap); rounds between send only the small protocol
    /// messages, and what waits stays in Y_i − C_ik (nothing is lost). 0 (default): every
    /// round. Why: forming a sparsified delta costs a Schur complement over every held-back
    /// feature, O(k³) per link and round on a map of k states; one delta per interval, with
    /// the interval's budget, bounds that cost per second at the same bytes per second. The
    /// driver sizes each round's budget for the interval (a budget is per delta).
    #[serde(default)]
    pub budget_interval: f64,
    /// On a sparsified link, list this node's loosely held features to the peer
    /// ([`super::message::Body::Uncertain`]) and put the peer's, where this node holds them far
    /// better, first into its marginals (default true; false is the ablation: the per-feature
    /// priority alone).
    #[serde(default = "default_true")]
    pub uncertain_lists: bool,
}

impl Default for DdfConfig {
    fn default() -> Self {
        Self {
            hello_interval: 1.0,
            gap_timeout: 2.0,
            sync_resend_interval: 1.0,
            max_buffer: 64,
            block_threshold_rel: 1e-12,
            byte_budget: None,
            ci_criterion: CiCriterion::Trace,
            submap_ack_timeout: default_submap_ack_timeout(),
            delta_precision: DeltaPrecision::F64,
            retired_epochs: 64,
            budget_interval: 0.0,
            uncertain_lists: true,
        }
    }
}

fn default_true() -> bool {
    true
}

/// Three rounds at the default 1 Hz: the receiver acknowledges at its next round.
fn default_submap_ack_timeout() -> f64 {
    3.0
}

/// Precision of the information blocks of deltas.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeltaPrecision {
    /// Exact f64 (deltas add up to the centralized sum to round-off).
    #[default]
    F64,
    /// f32 with a conservative deflation (never more information than exact; consistent).
    F32,
}

/// Errors of the DDF state machine. None of them leaves a channel half-updated.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DdfError {
    /// A message from a node that is not a configured neighbour (counted in [`NodeStats`]).
    #[error("message from node {0}, which is not a neighbour")]
    UnknownSender(NodeId),
    /// An API call naming a node that is not a neighbour.
    #[error("node {0} is not a neighbour")]
    UnknownNeighbour(NodeId),
    /// A non-finite time stamp.
    #[error("time stamp {0} is not finite")]
    InvalidTime(f64),
    /// A message whose payload is invalid (counted as rejected on its channel).
    #[error("invalid message from node {from}: {source}")]
    InvalidMessage {
        /// Sender.
        from: NodeId,
        /// What is wrong.
        source: InfoError,
    },
    /// The caller's own estimate passed to `on_round` is invalid.
    #[error("invalid local estimate: {0}")]
    InvalidEstimate(InfoError),
    /// The caller's estimator refused a delta (it stays pending and is retried) or a CI submap
    /// (not acknowledged, so the peer sends its features again).
    #[error("estimator refused information from node {from}: {source}")]
    FuseRejected {
        /// Sender of the refused information.
        from: NodeId,
        /// The estimator's reason.
        source: FuseRejected,
    },
    /// The topology does not suit the mode.
    #[error(transparent)]
    Topology(#[from] TopologyError),
    /// An internal invariant broke (shapes or origins of validated data); reported, not
    /// panicked on.
    #[error("internal error: {0}")]
    Internal(InfoError),
    /// A message kind this node does not take (a data-sharing batch at a channel-filter node:
    /// a neighbour configured for another fusion mode).
    #[error("a {kind} message from node {from}, which this node's fusion mode does not take")]
    Unexpected {
        /// The sender.
        from: NodeId,
        /// [`DdfMessage::kind`].
        kind: &'static str,
    },
}

/// Node-level counters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct NodeStats {
    /// Messages from nodes that are not neighbours (rejected).
    pub unknown_sender: u64,
    /// Correspondences adopted (own proposals and neighbours' facts).
    #[serde(default)]
    pub merges_adopted: u64,
    /// Neighbours' facts this node's estimate had evidence against (kept apart).
    #[serde(default)]
    pub merges_refused: u64,
    /// Adopted correspondences the estimator could not apply yet (its outgoing information is
    /// re-keyed meanwhile).
    #[serde(default)]
    pub merges_failed: u64,
}

/// What [`DdfNode::on_round`] asks the caller to do.
#[derive(Clone, Debug, Default)]
pub struct RoundOutput {
    /// Messages to send.
    pub messages: Vec<Outgoing>,
}

/// A read-only view of one channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChannelView {
    /// The neighbour.
    pub peer: NodeId,
    /// Exact channel filter or CI fallback.
    pub mode: LinkMode,
    /// The current epoch pair is synchronised (deltas flow).
    pub synced: bool,
    /// The caller reported the link up.
    pub link_up: bool,
    /// Counters.
    pub stats: ChannelStats,
    /// Σ δ of the sparsified marginals sent on this link ([`crate::sparse::Shift`]): the
    /// information each of them claimed beyond the delta along held-back features is at most
    /// its δ (times the identity), so a receiver's map information can exceed the centralized
    /// sum by at most this much (plus what other links add).
    pub sparse_shift: f64,
}

/// The DDF state machine of one process (vehicle or hub). Sans-IO: the caller feeds time,
/// its current map information, received messages and link events, and moves the returned
/// messages; received information reaches the caller's estimator through [`FuseTarget`].
#[derive(Clone, Debug)]
pub struct DdfNode {
    id: NodeId,
    epoch: u64,
    origin: Vector3<f64>,
    config: DdfConfig,
    channels: BTreeMap<NodeId, Channel>,
    /// Correspondences adopted (module [`crate::keys`]).
    keys: KeyMap,
    stats: NodeStats,
}

impl DdfNode {
    /// A node with channels to `neighbours`. `epoch` must be chosen afresh (randomly) at every
    /// process start; `origin` is the team origin of all map information.
    pub fn new(
        id: NodeId,
        epoch: u64,
        neighbours: impl IntoIterator<Item = NodeId>,
        origin: Vector3<f64>,
        config: DdfConfig,
    ) -> Self {
        let channels = neighbours
            .into_iter()
            .map(|k| (k, Channel::new(k, origin, config.byte_budget)))
            .collect();
        Self {
            id,
            epoch,
            origin,
            config,
            channels,
            keys: KeyMap::default(),
            stats: NodeStats::default(),
        }
    }

    /// A node configured for a mode on a topology: `Decentralized` needs a tree and links the
    /// node to its tree neighbours; `Central { hub }` needs the star around the hub (vehicles
    /// get one channel to the hub, the hub one per vehicle); `Isolated` has no channels.
    pub fn for_mode(
        mode: Mode,
        id: NodeId,
        epoch: u64,
        topology: &Topology,
        origin: Vector3<f64>,
        config: DdfConfig,
    ) -> Result<Self, DdfError> {
        let neighbours: Vec<NodeId> = match mode {
            Mode::Isolated => Vec::new(),
            Mode::Decentralized => {
                topology.require_tree()?;
                topology
                    .neighbours(id)
                    .ok_or(TopologyError::UnknownNode {
                        node: id,
                        a: id,
                        b: id,
                    })?
                    .to_vec()
            }
            Mode::Central { hub } => {
                topology.require_star(hub)?;
                topology
                    .neighbours(id)
                    .ok_or(TopologyError::UnknownNode {
                        node: id,
                        a: id,
                        b: id,
                    })?
                    .to_vec()
            }
        };
        Ok(Self::new(id, epoch, neighbours, origin, config))
    }

    /// This node's id.
    pub fn id(&self) -> NodeId {
        self.id
    }

    /// This node's epoch.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// The configured neighbours.
    pub fn neighbours(&self) -> impl Iterator<Item = NodeId> + '_ {
        self.channels.keys().copied()
    }

    /// Node-level counters.
    pub fn stats(&self) -> NodeStats {
        self.stats
    }

    /// A view of the channel to `peer`.
    pub fn channel(&self, peer: NodeId) -> Option<ChannelView> {
        self.channels.get(&peer).map(|c| ChannelView {
            peer,
            mode: c.mode(),
            synced: c.is_synced(),
            link_up: c.link_up(),
            stats: c.stats,
            sparse_shift: c.sparse_shift(),
        })
    }

    /// Views of all channels.
    pub fn channels(&self) -> impl Iterator<Item = ChannelView> + '_ {
        self.channels.keys().filter_map(|&k| self.channel(k))
    }

    /// Sets the byte budget of one link (`None`: unlimited).
    pub fn set_link_budget(&mut self, peer: NodeId, budget: Option<usize>) -> Result<(), DdfError> {
        self.channels
            .get_mut(&peer)
            .ok_or(DdfError::UnknownNeighbour(peer))?
            .set_budget(budget);
        Ok(())
    }

    /// Makes the link to `peer` a covariance-intersection link from now on (one-way, as when a
    /// delta exceeds the budget): for a capacity-limited link, which never carries exact deltas
    /// (design note 13: the channel filter's deltas grow with the map; budgeted CI submaps do
    /// not). The peer switches on the first submap or Hello it gets.
    pub fn use_ci(&mut self, peer: NodeId) -> Result<(), DdfError> {
        self.channels
            .get_mut(&peer)
            .ok_or(DdfError::UnknownNeighbour(peer))?
            .switch_to_ci(self.origin);
        Ok(())
    }

    /// Makes the link to `peer` a sparsified channel filter ([`LinkMode::Sparse`]): exact
    /// deltas while they fit the link's budget, the marginal information of the delta on the
    /// features that fit otherwise (conservative, booked in the channel filter; module
    /// [`crate::sparse`]). For a capacity-limited link. No protocol change: the peer receives
    /// ordinary deltas. A link already switched to CI stays CI.
    pub fn use_sparse(&mut self, peer: NodeId) -> Result<(), DdfError> {
        self.channels
            .get_mut(&peer)
            .ok_or(DdfError::UnknownNeighbour(peer))?
            .use_sparse();
        Ok(())
    }

    fn check_time(now: f64) -> Result<(), DdfError> {
        if now.is_finite() {
            Ok(())
        } else {
            Err(DdfError::InvalidTime(now))
        }
    }

    /// One fusion round. `source` is this node's estimator: its map information (Y_i, y_i)
    /// (eqs. 21.86, 21.87; formed only if an exact link sends a delta) and the covariance form
    /// of a few features (CI links). For every link that is up: a Hello when due, the Sync
    /// while initiating, the channel-filter delta d = Y_i − C_ik when it is not empty
    /// (C_ik += d), a Nack when a gap persists, or the acknowledgements and a submap on a CI
    /// link. The messages collected; [`DdfNode::on_round_each`] hands them over one by one.
    pub fn on_round(
        &mut self,
        now: f64,
        source: &mut dyn MapSource,
    ) -> Result<RoundOutput, DdfError> {
        let mut messages = Vec::new();
        self.on_round_each(now, source, &mut |o| messages.push(o))?;
        Ok(RoundOutput { messages })
    }

    /// [`DdfNode::on_round`], handing each message to `emit` as soon as it is formed (per link
    /// in the order it is to be sent), so that the caller can encode a delta and drop its
    /// dense form before the next channel forms its own: a vehicle with three neighbours held
    /// three dense k × k deltas at once otherwise. On an error, the messages emitted before it
    /// are booked in their channels and are to be sent; the rest of the round is not formed.
    pub fn on_round_each(
        &mut self,
        now: f64,
        source: &mut dyn MapSource,
        emit: &mut dyn FnMut(Outgoing),
    ) -> Result<(), DdfError> {
        Self::check_time(now)?;
        let ctx = NodeCtx {
            id: self.id,
            epoch: self.epoch,
            origin: self.origin,
            config: &self.config,
        };
        let all = self.keys.merges();
        for channel in self.channels.values_mut() {
            if std::mem::take(&mut channel.needs_all_facts) && !all.is_empty() {
                channel.queue_facts(&all);
            }
        }
        let mut info = LazyInformation::new(source, self.origin, &self.keys);
        // Exact parts first: a delta that does not fit its budget switches its link to CI.
        for (&peer, channel) in self.channels.iter_mut() {
            for message in channel.round_exact(now, &mut info, &ctx)? {
                emit(Outgoing { to: peer, message });
            }
        }
        let loose = super::channel::LooseFeatures::new();
        for (&peer, channel) in self.channels.iter_mut() {
            for message in channel.round_finish(now, info.source(), &loose, &self.keys, &ctx) {
                emit(Outgoing { to: peer, message });
            }
        }
        Ok(())
    }

    /// Asks every neighbour, at the next round, for the descriptors of `keys` (keys this
    /// node's estimate holds without one: a `Describe` was lost, or the neighbour did not know
    /// the descriptor when it first used the key). Call it every round while keys stay
    /// undescribed; at most [`MAX_LIST`] keys per neighbour and round are sent.
    pub fn request_descriptors(&mut self, keys: &[FeatureId]) {
        let keys = &keys[..keys.len().min(MAX_LIST)];
        for c in self.channels.values_mut() {
            c.request_descriptors(keys);
        }
    }

    /// The node's context and its channel to `peer`.
    fn peer_channel(&mut self, peer: NodeId) -> Result<(NodeCtx<'_>, &mut Channel), DdfError> {
        let ctx = NodeCtx {
            id: self.id,
            epoch: self.epoch,
            origin: self.origin,
            config: &self.config,
        };
        let channel = self
            .channels
            .get_mut(&peer)
            .ok_or(DdfError::UnknownNeighbour(peer))?;
        Ok((ctx, channel))
    }

    /// A message for neighbour `peer` outside the channel-filter bookkeeping (an
    /// [`Body::Anchor`]), tagged with this node's epochs like any other.
    pub fn message_to(&mut self, peer: NodeId, body: Body) -> Result<Outgoing, DdfError> {
        let (ctx, channel) = self.peer_channel(peer)?;
        Ok(Outgoing {
            to: peer,
            message: channel.msg(&ctx, body),
        })
    }

    /// Validates a received message as [`DdfNode::on_message`] would (sender a neighbour,
    /// payload well-formed), without acting on it: for messages the caller handles itself.
    pub fn validate(&self, from: NodeId, message: &DdfMessage) -> Result<(), DdfError> {
        if !self.channels.contains_key(&from) {
            return Err(DdfError::UnknownSender(from));
        }
        Channel::validate_payload(message, self.origin)
            .map_err(|source| DdfError::InvalidMessage { from, source })
    }

    /// The correspondences this node adopted.
    pub fn keys(&self) -> &KeyMap {
        &self.keys
    }

    /// Adopts "a and b name one feature" (module [`crate::keys`]): every channel filter, the
    /// buffered deltas and the estimate (`target.merge`) are re-keyed, and the fact is queued
    /// for every neighbour. Returns the effective merge (`None`: already one).
    pub fn adopt_merge(
        &mut self,
        a: FeatureId,
        b: FeatureId,
        target: &mut dyn FuseTarget,
    ) -> Option<Merge> {
        let m = self.keys.adopt(a, b)?;
        for channel in self.channels.values_mut() {
            channel.rekey(&self.keys, m);
        }
        self.stats.merges_adopted += 1;
        if target.merge(&m).is_err() {
            self.stats.merges_failed += 1;
        }
        Some(m)
    }

    /// Node-level handling before the channel sees a message: facts and descriptors concern
    /// every channel; information is brought into this node's key space, and the estimator may
    /// associate the delta's keys with its own features first (each adopted merge re-keys the
    /// delta again). Returns `None` when nothing is left for the channel.
    fn prepare(
        &mut self,
        from: NodeId,
        mut message: DdfMessage,
        target: &mut dyn FuseTarget,
    ) -> Option<DdfMessage> {
        match &mut message.body {
            Body::Merges { merges } => {
                for m in std::mem::take(merges) {
                    if target.accept_merge(&m) {
                        self.adopt_merge(m.from, m.into, target);
                    } else {
                        self.stats.merges_refused += 1;
                    }
                }
                return None;
            }
            Body::Describe { features } => {
                for f in features.iter_mut() {
                    f.0 = self.keys.canonical(f.0);
                }
                target.describe(features);
                return None;
            }
            // Anchors are for a vehicle not yet in the team frame, handled by its driver before
            // the node; one that reaches the node (the vehicle is in the team frame by now) has
            // nothing for the channel filters.
            Body::Anchor { .. } => return None,
            Body::DescribeRequest { keys } => {
                if let Some(c) = self.channels.get_mut(&from) {
                    c.descriptors_requested(keys);
                }
                return None;
            }
            Body::Delta { info, .. } | Body::Cumulative { info, .. } => {
                info.rekey(&self.keys);
                for m in target.associate(info) {
                    self.adopt_merge(m.from, m.into, target);
                }
                info.rekey(&self.keys);
            }
            Body::Uncertain { features } => {
                for f in features.iter_mut() {
                    f.0 = self.keys.canonical(f.0);
                }
            }
            Body::Sync { baseline, .. } => baseline.rekey(&self.keys),
            Body::Submap { submap, .. } => *submap = submap.rekeyed(&self.keys),
            Body::Hello(_) | Body::Nack { .. } | Body::SubmapAck { .. } | Body::Share(_) => {}
        }
        Some(message)
    }

    /// Handles a message from `from`. Information to fuse goes to `target` (the caller's
    /// estimator); the channel records a delta only after `target` accepted it, so every
    /// delta takes effect exactly once. Returns replies to send.
    ///
    /// Errors: [`DdfError::UnknownSender`] (not a neighbour), [`DdfError::InvalidMessage`]
    /// (payload not finite/symmetric/well-sized, or another origin; nothing changed),
    /// [`DdfError::FuseRejected`] (the estimator refused; the delta stays pending).
    pub fn on_message(
        &mut self,
        now: f64,
        from: NodeId,
        message: DdfMessage,
        target: &mut dyn FuseTarget,
    ) -> Result<Vec<Outgoing>, DdfError> {
        Self::check_time(now)?;
        let origin = self.origin;
        let Some(channel) = self.channels.get_mut(&from) else {
            self.stats.unknown_sender += 1;
            return Err(DdfError::UnknownSender(from));
        };
        if matches!(message.body, Body::Share(_)) {
            channel.stats.messages_received += 1;
            channel.stats.rejected += 1;
            return Err(DdfError::Unexpected {
                from,
                kind: message.kind(),
            });
        }
        if let Err(source) = Channel::validate_payload(&message, origin) {
            channel.stats.messages_received += 1;
            channel.stats.rejected += 1;
            return Err(DdfError::InvalidMessage { from, source });
        }
        let Some(message) = self.prepare(from, message, target) else {
            if let Some(c) = self.channels.get_mut(&from) {
                c.stats.messages_received += 1;
            }
            return Ok(Vec::new());
        };
        let ctx = NodeCtx {
            id: self.id,
            epoch: self.epoch,
            origin,
            config: &self.config,
        };
        let channel = self
            .channels
            .get_mut(&from)
            .ok_or(DdfError::UnknownSender(from))?;
        let replies = channel.on_message(now, message, &ctx, target)?;
        Ok(replies
            .into_iter()
            .map(|message| Outgoing { to: from, message })
            .collect())
    }

    /// The transport reports the link to `peer` up: sends a Hello at once (and the pending Sync
    /// if this node is initiating), so a peer that lost messages during an outage detects the
    /// gap without waiting for the next round.
    pub fn on_link_up(&mut self, now: f64, peer: NodeId) -> Result<Vec<Outgoing>, DdfError> {
        Self::check_time(now)?;
        let (ctx, channel) = self.peer_channel(peer)?;
        Ok(channel
            .on_link_up(now, &ctx)
            .into_iter()
            .map(|message| Outgoing { to: peer, message })
            .collect())
    }

    /// The transport reports the link to `peer` down: nothing is sent on it until it is up
    /// again; what accumulates in Y_i − C_ik goes out as one delta afterwards.
    pub fn on_link_down(&mut self, peer: NodeId) -> Result<(), DdfError> {
        self.channels
            .get_mut(&peer)
            .ok_or(DdfError::UnknownNeighbour(peer))?
            .on_link_down();
        Ok(())
    }
}
