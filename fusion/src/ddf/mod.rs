//! Decentralized data fusion: channel filters over a tree, as a sans-IO state machine
//! (design.md §4; chapter §21.5.2–21.5.4, eqs. 21.88–21.99 with their errata).
//!
//! # Bookkeeping
//! Node i keeps, for each neighbour k, the channel information C_ik: what i knows it shares
//! with k. Sending: d = Y_i − C_ik, C_ik += d (eqs. 21.94, 21.95 per link). Receiving d from k:
//! (Y_i, y_i) += d, C_ik += d (21.96, 21.97 per link, *without* eq. 21.96's sum over all
//! vehicles including i itself, which double counts). Deltas commute, so delay and reordering
//! are harmless; loss, duplication and outages are handled by sequence numbers and a
//! cumulative resync; restarts by link epochs. On a tree no information reaches a node by two
//! paths, so after as many rounds as the diameter every node holds the centralized sum.
//!
//! Central mode (eqs. 21.88–21.93) is the star special case: the hub is a [`DdfNode`] without
//! observations whose estimate is the sum of what it received, and each vehicle–hub link is a
//! channel filter, so the feedback to a vehicle carries only what it does not hold (eq. 21.92
//! as printed adds the whole central increment, including the vehicle's own contribution).
//!
//! # Exactly-once per epoch pair
//! C = S + R: S is what i sent k in the current epoch pair, R what i received from k and
//! applied. Deltas carry seq = 1, 2, …; the receiver applies seq = applied + 1 and drains its
//! reorder buffer, buffers later ones, drops earlier ones (duplicates). A gap that persists
//! (buffered deltas ahead of it, or a Hello announcing seq_sent > applied) for `gap_timeout`,
//! or a full buffer, triggers `Nack{applied}`; the sender answers `Cumulative{upto, S}` and the
//! receiver applies S − R, sets R := S and applied := upto. S − R is exactly the sum of the
//! deltas it has not applied, so each delta takes effect once, whatever was lost or repeated.
//!
//! # Epochs and resynchronisation
//! Every process has a random epoch; messages carry (sender epoch, receiver epoch as known).
//! A message for another epoch of the receiver, or from a retired epoch of the sender, is
//! dropped. A new epoch of the peer starts a new epoch pair, which must be synchronised before
//! deltas flow: the side with *history* (it was paired with an earlier incarnation of the peer)
//! initiates; at first contact the lower id does. The initiator i sends `Sync{baseline = Rtot}`
//! where Rtot is everything i ever received from k (all epochs) and sets S := Rtot, R := 0; the
//! responder sets R := Rtot, S := 0. Both then hold C = Rtot, and deltas flow. The same rule
//! decides which Sync is *applied*: a Sync from the side that may not initiate (it acted on a
//! stale view of the other's history, e.g. a delayed Hello) is refused, and the refusing side
//! initiates itself; with two crossing Syncs exactly one is applied.
//!
//! Adopting a new epoch of a known peer needs a liveness proof. Restarts can be faster than
//! the network delay, so a delayed message of an incarnation that has died since may arrive
//! after its successor took over; adopting it would point the channel at a dead process for
//! good. An unknown epoch is therefore only a *candidate*: the node raises its per-link
//! challenge (carried in every header) and adopts the candidate when a message from it echoes
//! a challenge at least that high, tagged with the node's own epoch — proof that the candidate
//! was alive after it was first heard of, which a dead incarnation cannot give. (First contact
//! adopts at once; if that was a dead incarnation, the live one proves itself and replaces it.)
//!
//! Why this does not double count when a middle node k restarts between subtrees I and J
//! (I, J: the information originating there; K_old: old k's own, lost with it; K_new: new k's):
//! before the restart, i holds I + J + K_old and Rtot_ik = J + K_old (everything k sent i).
//! i's first delta to k is Y_i − C_ik = I + J + K_old − (J + K_old) = I: only i's side. k's first
//! delta to i is Y_k − C_ki = K_new − (J + K_old) (indefinite): it removes from i exactly what
//! k can no longer vouch for. i then holds I + K_new, and j's side J reaches i through k by the
//! next deltas: i ends with I + J + K_new. Information is lost (K_old), never counted twice;
//! at every instant each node holds a sum of distinct contributions. The same argument with
//! J = ∅ covers a leaf, and with Rtot = 0 first contact.
//!
//! The integrator's design sends `Sync{fuse = Y_i − Rtot, baseline = Y_i}` instead; ours is
//! the same algebra with the i-side information moved from the Sync into i's first delta
//! (it needs no Y_i when the restart is detected, so the Sync can be answered inside
//! `on_message`), at the cost of one more round for J to reach i.
//!
//! # Sparsified links
//! A link made [`LinkMode::Sparse`] ([`DdfNode::use_sparse`]) sends the delta as is while it
//! fits its budget, and otherwise its marginal information on the features that fit
//! ([`crate::sparse`]); both ends book what was sent, the rest stays in Y_i − C_ik. A round
//! whose residual block is not positive definite is refused (nothing sent, counted).
//!
//! # Covariance intersection fallback
//! When a link's byte budget cannot carry the delta — or from the start, for a
//! capacity-limited link ([`DdfNode::use_ci`]) — the link switches to CI for good, in both
//! directions (the peer switches on the first submap or on a Hello with `ci` set): its channel
//! filter is retired, and each round a budgeted [`Submap`](crate::ci::Submap) of the
//! highest-priority features is sent and fused by the receiver's estimator
//! ([`FuseTarget::fuse_submap`]: the EKF in covariance form, `SlamFilter::fuse_submap_ci`; a
//! plain information map by [`crate::ci::fuse_submap`]) as it arrives. Submaps are
//! numbered and the receiver acknowledges those it fused (`SubmapAck`); a feature whose submap
//! was never acknowledged (lost, or refused) counts as unsent again after
//! `submap_ack_timeout`, so every feature eventually crosses the link. Exact-protocol
//! messages still in flight on that link are dropped (information lost, never double counted).
//! The CI change of the estimate reaches the node's exact links as part of Y_i − C_ij, so
//! deltas there may be indefinite: payloads are validated as finite and symmetric, positive
//! definiteness is the estimator's check on its fused result.

mod channel;
mod message;
mod node;
mod store;

pub use channel::{ChannelStats, MAX_INTRODUCED_SIGMA_M, PROMOTE_SIGMA_RATIO, UNCERTAIN_SIGMA_M};
pub use message::{
    AnchorFeature, Body, DdfMessage, Header, Hello, MAX_ANCHOR_FEATURES, MAX_LIST, MAX_SUBMAP_ACKS,
    MAX_UNCERTAIN, Outgoing, from_upper_triangle, upper_triangle,
};
pub use node::{ChannelView, DdfConfig, DdfError, DdfNode, DeltaPrecision, NodeStats, RoundOutput};
pub use store::PackedInformation;

use crate::ci::{CiCriterion, Submap};
use crate::info::{InfoError, MapInformation, MapMarginal};
use crate::keys::Merge;
use crate::sensor::{Appearance, FeatureId};
use crate::state::FEATURE_DIM;
use crate::topology::NodeId;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

/// How a team fuses maps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Mode {
    /// Channel filters on a tree of vehicles, hop by hop (eqs. 21.94–21.99, corrected).
    Decentralized,
    /// A hub without observations; channel filters on each vehicle–hub link (the independent
    /// opinion pool with local feedback, eqs. 21.88–21.93, corrected).
    Central {
        /// The hub's id.
        hub: NodeId,
    },
    /// No fusion.
    Isolated,
}

/// Whether a link runs the exact channel filter or the CI fallback.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LinkMode {
    /// Channel filter: exact, additive deltas.
    Exact,
    /// Covariance intersection of budgeted submaps (one-way switch).
    Ci,
    /// Channel filter whose delta, when it does not fit the link's budget, is conservatively
    /// sparsified: the marginal information of the delta on the features that fit
    /// ([`crate::sparse`]) is sent and booked, the rest stays in Y_i − C_ik for later rounds.
    /// Exact whenever the whole delta fits. Set per link ([`DdfNode::use_sparse`]).
    Sparse,
}

/// The estimator refused to fuse information.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("fusion refused: {reason}")]
pub struct FuseRejected {
    /// Why.
    pub reason: String,
}

/// The caller's estimator as seen by the channel filters: received information is added to
/// it (the EKF's fuse-back, eqs. 21.92, 21.93 / 21.96–21.99). A refusal (e.g. the fused map
/// would not be positive definite) leaves the delta pending.
pub trait FuseTarget {
    /// Adds `delta` (aligned by feature id; new features augment the map).
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected>;
    /// Fuses a submap received on a CI link by covariance intersection (ω by `criterion`). A
    /// refusal is counted and the submap is not acknowledged (its features go out again).
    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected>;
    /// Applies a correspondence (module [`crate::keys`]) to the estimate: `from` and `into`
    /// become one feature named `into` (or `from` is renamed when only it is held). A refusal
    /// is counted; the node's bookkeeping is merged anyway, and outgoing information is
    /// re-keyed, so the estimate may hold the two a while longer without harm.
    fn merge(&mut self, merge: &Merge) -> Result<(), FuseRejected>;
    /// Whether to adopt a correspondence a neighbour adopted (`false`: this estimate has
    /// evidence against it, e.g. the two features are far apart; the node then keeps them
    /// apart, which is exact too).
    fn accept_merge(&mut self, merge: &Merge) -> bool {
        let _ = merge;
        true
    }
    /// Correspondences between keys of a received delta (in this node's key space) and the
    /// estimate's own features, proposed before it is fused (cross-vehicle association).
    fn associate(&mut self, delta: &MapInformation) -> Vec<Merge> {
        let _ = delta;
        Vec::new()
    }
    /// Appearance descriptors of keys a neighbour is about to use.
    fn describe(&mut self, features: &[(FeatureId, Appearance)]) {
        let _ = features;
    }
}

/// What a node reads from its estimator in a round: the map information only when an exact
/// link sends a delta (forming Y = P⁻¹ is the expensive part), the covariance form of a few
/// features when a CI link sends a submap.
pub trait MapSource {
    /// The map information (Y, y) (eqs. 21.86, 21.87) in the node's origin.
    fn information(&mut self) -> Result<MapInformation, InfoError>;
    /// Takes back, unchanged, what [`information`](Self::information) returned, once the
    /// round is done with it: a source that keeps Y up to date can hand that matrix out
    /// instead of a copy (k × k per round) and keep it. The default drops it.
    fn restore_information(&mut self, info: MapInformation) {
        drop(info);
    }
    /// Every map feature with its 3 × 3 covariance block (submap priorities).
    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)>;
    /// The marginal (x_S, P_S) of `ids` (in that order; unknown ids are skipped).
    fn marginal(&self, ids: &[FeatureId]) -> MapMarginal;
    /// The estimated positions x_S of `ids` (in that order; unknown ids are skipped), as in
    /// [`marginal`](Self::marginal) without its covariance (a sparsified delta is evaluated
    /// about them: gathering P_S for them would cost a k × k copy per link and round). The
    /// default takes them from [`marginal`](Self::marginal).
    fn feature_means(&self, ids: &[FeatureId]) -> Vec<(FeatureId, Vector3<f64>)> {
        let m = self.marginal(ids);
        m.ids
            .iter()
            .enumerate()
            .map(|(b, &id)| (id, Vector3::from_fn(|a, _| m.mean[FEATURE_DIM * b + a])))
            .collect()
    }
    /// Appearance descriptors of `ids`, where known (sent with keys new to a link).
    fn descriptors(&self, ids: &[FeatureId]) -> Vec<(FeatureId, Appearance)> {
        let _ = ids;
        Vec::new()
    }
}

fn rejected(e: impl std::fmt::Display) -> FuseRejected {
    FuseRejected {
        reason: e.to_string(),
    }
}

/// A plain information accumulator (the hub's estimate, and the stand-in for the EKF's map in
/// linear-Gaussian tests): adds every delta; fuses submaps by information-form CI.
impl FuseTarget for MapInformation {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        self.add_assign(delta).map_err(rejected)
    }

    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected> {
        *self = crate::ci::fuse_submap(self, submap, criterion)
            .map_err(rejected)?
            .fused;
        Ok(())
    }

    fn merge(&mut self, merge: &Merge) -> Result<(), FuseRejected> {
        let mut keys = crate::keys::KeyMap::default();
        keys.adopt(merge.from, merge.into);
        *self = self.rekeyed(&keys);
        Ok(())
    }
}

/// Map information as its own source (the hub, tests): the covariance form by one inversion.
impl MapSource for MapInformation {
    fn information(&mut self) -> Result<MapInformation, InfoError> {
        Ok(self.clone())
    }

    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)> {
        let Ok(m) = self.to_marginal() else {
            return Vec::new();
        };
        m.ids
            .iter()
            .enumerate()
            .map(|(b, &id)| {
                (
                    id,
                    Matrix3::from_fn(|i, j| m.covariance[(3 * b + i, 3 * b + j)]),
                )
            })
            .collect()
    }

    fn marginal(&self, ids: &[FeatureId]) -> MapMarginal {
        match self.to_marginal() {
            Ok(m) => m.restrict(ids),
            Err(_) => MapMarginal {
                ids: Vec::new(),
                mean: faer::Col::zeros(0),
                covariance: faer::Mat::zeros(0, 0),
            },
        }
    }
}

/// An estimate that is only information — the hub of central mode: the sum of what it
/// received ([`MapInformation`] as [`FuseTarget`]) and the appearance descriptors its
/// neighbours sent with their keys, which it passes on with those keys ([`MapSource::descriptors`])
/// so that the vehicles behind it can associate each other's features.
#[derive(Clone, Debug)]
pub struct InformationStore {
    /// The information held.
    pub info: MapInformation,
    descriptors: std::collections::BTreeMap<FeatureId, Appearance>,
}

impl InformationStore {
    /// An empty store with the team origin `origin`.
    pub fn new(origin: nalgebra::Vector3<f64>) -> Self {
        Self {
            info: MapInformation::zero(origin),
            descriptors: Default::default(),
        }
    }

    /// The descriptor a neighbour sent for `key`.
    pub fn descriptor(&self, key: FeatureId) -> Option<&Appearance> {
        self.descriptors.get(&key)
    }

    /// Keys held without a descriptor, once any descriptor has been seen (a team with
    /// identities never sends any, and is not asked).
    pub fn undescribed(&self) -> Vec<FeatureId> {
        if self.descriptors.is_empty() {
            return Vec::new();
        }
        self.info
            .ids
            .iter()
            .copied()
            .filter(|k| !self.descriptors.contains_key(k))
            .collect()
    }
}

impl FuseTarget for InformationStore {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        self.info.fuse(delta)
    }

    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected> {
        self.info.fuse_submap(submap, criterion)
    }

    fn merge(&mut self, merge: &Merge) -> Result<(), FuseRejected> {
        if let Some(a) = self.descriptors.remove(&merge.from) {
            self.descriptors.entry(merge.into).or_insert(a);
        }
        self.info.merge(merge)
    }

    fn describe(&mut self, features: &[(FeatureId, Appearance)]) {
        for (f, a) in features {
            self.descriptors.entry(*f).or_insert(*a);
        }
    }
}

impl MapSource for InformationStore {
    fn information(&mut self) -> Result<MapInformation, InfoError> {
        self.info.information()
    }

    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)> {
        self.info.feature_covariances()
    }

    fn marginal(&self, ids: &[FeatureId]) -> MapMarginal {
        self.info.marginal(ids)
    }

    fn descriptors(&self, ids: &[FeatureId]) -> Vec<(FeatureId, Appearance)> {
        ids.iter()
            .filter_map(|f| self.descriptors.get(f).map(|a| (*f, *a)))
            .collect()
    }
}
