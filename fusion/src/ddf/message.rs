//! The messages of the channel-filter protocol (sans-IO: the caller moves them; serde gives the
//! wire form).

use crate::ci::Submap;
use crate::info::MapInformation;
use crate::keys::Merge;
use crate::sensor::{Appearance, FeatureId};
use crate::topology::NodeId;
use serde::{Deserialize, Serialize};

/// Epoch tags and the liveness challenge carried by every message.
///
/// An epoch is chosen by a node process at start (a random u64 supplied by the caller) and
/// never changes during its life; a restarted process has a new epoch. The receiver drops a
/// message addressed to another epoch of itself (it was meant for a previous incarnation).
///
/// A message from an unknown epoch of a known peer may be a delayed message of an incarnation
/// that has died since (restarts faster than the network delay), so it does not switch the
/// channel at once: the receiver raises its `challenge` and adopts that epoch only when a
/// message from it echoes a challenge at least that high *of the receiver's epoch*, i.e. proves
/// it was alive after it was first heard of. Dead incarnations cannot do that, so a channel
/// never falls back to one. Echoes are tagged with the epoch they answer, because the prover
/// may still address its messages to a dead incarnation of the receiver.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// The sender's epoch.
    pub from_epoch: u64,
    /// The receiver's epoch as the sender knows it (`None` before the sender has heard from
    /// the receiver).
    pub to_epoch: Option<u64>,
    /// The sender's current liveness challenge on this link (raised when it hears of a new
    /// epoch of the receiver's node).
    pub challenge: u64,
    /// The epoch of the receiver's node that the sender heard from last.
    pub echo_epoch: u64,
    /// The highest challenge the sender has received from `echo_epoch`.
    pub echo: u64,
}

/// The periodic heartbeat: keeps loss detection alive when no delta flows, carries the sync
/// state and the link mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    /// Highest delta sequence number sent in the current epoch pair.
    pub seq_sent: u64,
    /// Contiguous receive watermark in the current epoch pair.
    pub applied: u64,
    /// The sender has been paired with some incarnation of the receiver before (decides who
    /// initiates a resynchronisation).
    pub history: bool,
    /// The sender has completed the Sync of the current epoch pair (acknowledges a Sync).
    pub synced: bool,
    /// The sender's side of the link has fallen back to covariance intersection.
    pub ci: bool,
}

/// The body of a [`DdfMessage`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub enum Body {
    /// Heartbeat.
    Hello(Hello),
    /// One channel-filter delta d = Y_i − C_ik (eqs. 21.94, 21.95 without the double counting):
    /// applied strictly in sequence order, exactly once.
    Delta {
        /// Sequence number in the epoch pair, from 1.
        seq: u64,
        /// The delta (symmetric, possibly indefinite).
        info: MapInformation,
    },
    /// Receiver → sender: "I have applied up to `applied`; a later delta is missing".
    Nack {
        /// The receiver's contiguous watermark.
        applied: u64,
    },
    /// Sender → receiver: the cumulative information S sent in this epoch pair, up to `upto`.
    /// The receiver applies S − R (what it has not applied yet) and sets R = S.
    Cumulative {
        /// The sequence number S includes.
        upto: u64,
        /// S.
        info: MapInformation,
    },
    /// Starts an epoch pair: the receiver sets R := baseline, S := 0; the sender has set
    /// S := baseline, R := 0. The baseline is everything the sender ever applied from any
    /// incarnation of the receiver (docs of [`crate::ddf`]).
    Sync {
        /// Generation (per channel, for diagnostics).
        generation: u64,
        /// The sender's history flag before initiating (tie-break between two initiators).
        history: bool,
        /// The baseline.
        baseline: MapInformation,
    },
    /// A covariance-form submap on a link that has fallen back to covariance intersection.
    Submap {
        /// Number of the submap on this link, from 1 (acknowledged by [`Body::SubmapAck`]).
        seq: u64,
        /// The submap.
        submap: Submap,
    },
    /// Receiver → sender on a CI link: the submaps fused since the last acknowledgement. The
    /// features of a submap never acknowledged (lost, dropped on arrival, refused by CI) are
    /// sent again once [`DdfConfig::submap_ack_timeout`](super::DdfConfig) passes.
    SubmapAck {
        /// Numbers of the fused submaps (at most [`MAX_SUBMAP_ACKS`]).
        seqs: Vec<u64>,
    },
    /// Correspondences the sender adopted (module [`crate::keys`]): the receiver may adopt them
    /// too. Independent of epochs and sequence numbers (a merge is idempotent and order does
    /// not matter for the bookkeeping).
    Merges {
        /// The merges (at most [`MAX_LIST`]).
        merges: Vec<Merge>,
    },
    /// Appearance descriptors of keys the sender is about to use on this link for the first
    /// time (so the receiver can associate them with its own features).
    Describe {
        /// Key and descriptor (at most [`MAX_LIST`]).
        features: Vec<(FeatureId, Appearance)>,
    },
    /// Keys the sender holds without a descriptor (a `Describe` lost, or sent before the
    /// neighbour knew the descriptor itself): the receiver answers with a `Describe` of those
    /// it knows at its next round. Repeated while keys stay undescribed, so any loss heals.
    DescribeRequest {
        /// The keys (at most [`MAX_LIST`]).
        keys: Vec<FeatureId>,
    },
    /// Local SLAM with each vehicle in its own frame (module [`crate::frames`]): a node already
    /// in the team frame sends its best-localised features, with their descriptors, to a
    /// neighbour it has not paired with, which aligns its own map to them before it joins the
    /// channel filters. Not part of the channel-filter bookkeeping.
    Anchor {
        /// The features (at most [`MAX_ANCHOR_FEATURES`]).
        features: Vec<AnchorFeature>,
    },
    /// The features the sender holds only loosely — marginal σ = √tr P_ff above
    /// `channel::UNCERTAIN_SIGMA_M`, loosest first — sent on a sparsified link so that the
    /// peer, whose per-feature priority sees only its own covariance, puts the ones it knows
    /// far better into its next marginal (docs/arch/ddf.md, "What the peer lacks"). Advisory:
    /// it changes which features a marginal carries, never what is booked. An empty list
    /// clears the peer's record.
    Uncertain {
        /// (key, σ [m]), at most [`MAX_UNCERTAIN`].
        features: Vec<(FeatureId, f32)>,
    },
    /// Data sharing (`crate::share`): a round's batch of the team's records for a neighbour.
    /// Only nodes in data-sharing mode take it; a DDF node refuses it.
    Share(crate::share::Batch<crate::share::Item>),
}

/// Most features one [`Body::Anchor`] carries.
pub const MAX_ANCHOR_FEATURES: usize = 1024;

/// One feature of a [`Body::Anchor`], in the team frame.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnchorFeature {
    /// The sender's key.
    pub key: FeatureId,
    /// Position [m].
    pub position: [f64; 3],
    /// Covariance, upper triangle row by row (xx, xy, xz, yy, yz, zz) [m²].
    pub covariance: [f64; 6],
    /// Appearance descriptor.
    pub appearance: Appearance,
}

/// A symmetric 3 × 3 covariance as its upper triangle row by row (xx, xy, xz, yy, yz, zz), the
/// form of [`AnchorFeature::covariance`] and of the vehicles' map reports.
pub fn upper_triangle(c: &nalgebra::Matrix3<f64>) -> [f64; 6] {
    [
        c[(0, 0)],
        c[(0, 1)],
        c[(0, 2)],
        c[(1, 1)],
        c[(1, 2)],
        c[(2, 2)],
    ]
}

/// The symmetric 3 × 3 matrix of an [`upper_triangle`].
pub fn from_upper_triangle(c: &[f64; 6]) -> nalgebra::Matrix3<f64> {
    nalgebra::Matrix3::new(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])
}

impl AnchorFeature {
    /// The 3 × 3 covariance.
    pub fn covariance(&self) -> nalgebra::Matrix3<f64> {
        from_upper_triangle(&self.covariance)
    }

    /// Finite position, positive definite covariance.
    pub fn is_valid(&self) -> bool {
        self.position
            .iter()
            .chain(&self.covariance)
            .all(|v| v.is_finite())
            && self.covariance().cholesky().is_some()
    }
}

/// Most features one [`Body::Uncertain`] lists (more is rejected as malformed).
pub const MAX_UNCERTAIN: usize = 32;

/// Most entries of one [`Body::Merges`] or [`Body::Describe`] (more is rejected as malformed).
pub const MAX_LIST: usize = 65_536;

/// Most submap numbers one [`Body::SubmapAck`] carries (more is rejected as malformed).
pub const MAX_SUBMAP_ACKS: usize = 256;

/// A protocol message.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DdfMessage {
    /// Epoch tags.
    pub header: Header,
    /// Payload.
    pub body: Body,
}

impl DdfMessage {
    /// Short name of the message kind (for logs and metrics).
    pub fn kind(&self) -> &'static str {
        match self.body {
            Body::Hello(_) => "hello",
            Body::Delta { .. } => "delta",
            Body::Nack { .. } => "nack",
            Body::Cumulative { .. } => "cumulative",
            Body::Sync { .. } => "sync",
            Body::Submap { .. } => "submap",
            Body::SubmapAck { .. } => "submap-ack",
            Body::Merges { .. } => "merges",
            Body::Describe { .. } => "describe",
            Body::DescribeRequest { .. } => "describe-request",
            Body::Anchor { .. } => "anchor",
            Body::Uncertain { .. } => "uncertain",
            Body::Share(_) => "share",
        }
    }

    /// An upper bound of the encoded size in bincode's standard configuration, in bytes.
    pub fn wire_bytes_bound(&self) -> usize {
        // Header: five u64 varints (≤ 9 each) and an Option tag; enum tag; small fields.
        const HEADER: usize = 5 * 9 + 1 + 1;
        HEADER
            + match &self.body {
                Body::Hello(_) => 9 + 9 + 3,
                Body::Delta { info, .. } | Body::Cumulative { info, .. } => {
                    9 + info.block_sparse_wire_bytes()
                }
                Body::Nack { .. } => 9,
                Body::Sync { baseline, .. } => 9 + 1 + baseline.block_sparse_wire_bytes(),
                Body::Submap { submap, .. } => 9 + submap.wire_bytes(),
                Body::SubmapAck { seqs } => 9 + 9 * seqs.len(),
                Body::Merges { merges } => 9 + 18 * merges.len(),
                Body::Describe { features } => 9 + (9 + 4 * 9) * features.len(),
                Body::DescribeRequest { keys } => 9 + 9 * keys.len(),
                Body::Anchor { features } => 9 + (9 + 9 * 8 + 4 * 9) * features.len(),
                Body::Uncertain { features } => 9 + (9 + 4) * features.len(),
                Body::Share(batch) => {
                    use crate::share::ShareRecord;
                    9 + 9
                        + batch.have.len() * (9 + 9 + 9)
                        + batch
                            .records
                            .iter()
                            .map(|(_, _, r)| 9 + 9 + 9 + r.wire_bytes())
                            .sum::<usize>()
                }
            }
    }
}

/// A message to send to a neighbour.
#[derive(Clone, Debug)]
pub struct Outgoing {
    /// Destination.
    pub to: NodeId,
    /// The message.
    pub message: DdfMessage,
}
