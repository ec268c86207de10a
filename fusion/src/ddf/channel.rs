//! One channel filter: node i's record of what it shares with neighbour k, and the per-link
//! protocol state (sequence numbers, reorder buffer, epochs, sync, CI fallback).

use super::message::{Body, DdfMessage, Header, Hello, MAX_LIST, MAX_SUBMAP_ACKS, MAX_UNCERTAIN};
use super::node::{DdfConfig, DdfError};
use super::store::{self, PackedInformation};
use super::{FuseTarget, LinkMode, MapSource};
use crate::ci::{self, Submap, SubmapTracker};
use crate::info::{InfoError, MapInformation};
use crate::keys::{KeyMap, Merge};
use crate::sensor::{Appearance, FeatureId};
use crate::sparse;
use crate::topology::NodeId;
use nalgebra::Matrix3;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use std::cell::OnceCell;
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};

/// How many times a sparsified round moves the feature of a failing pivot of D_RR into S
/// before it is refused. Why 8: each attempt is one Cholesky of D_RR (the round's main cost);
/// 8 bounds a round at 9 of them.
const MAX_PIVOT_SWAPS: usize = 8;

/// Counters of one channel (one neighbour), for metrics and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChannelStats {
    /// Messages handed to the caller for this neighbour.
    pub messages_sent: u64,
    /// Messages received from this neighbour (valid or not).
    pub messages_received: u64,
    /// Deltas sent.
    pub deltas_sent: u64,
    /// Deltas applied (fused) in sequence.
    pub deltas_applied: u64,
    /// Deltas or Syncs received again after they took effect (dropped).
    pub duplicates: u64,
    /// Messages of a retired epoch, addressed to another epoch of this node, of the wrong
    /// phase (e.g. a delta before the Sync), or outdated cumulatives (dropped).
    pub stale: u64,
    /// Deltas that arrived ahead of a gap and were buffered.
    pub out_of_order: u64,
    /// Deltas dropped because the reorder buffer was full (recovered by a cumulative).
    pub buffer_overflows: u64,
    /// Nacks sent.
    pub nacks_sent: u64,
    /// Nacks received.
    pub nacks_received: u64,
    /// Cumulatives sent.
    pub cumulatives_sent: u64,
    /// Cumulatives applied.
    pub cumulatives_applied: u64,
    /// Epoch pairs this node initiated (first contact or after a peer restart).
    pub syncs_initiated: u64,
    /// Syncs of the peer this node applied.
    pub syncs_applied: u64,
    /// Times the peer was seen with a new epoch after an earlier one (restarts).
    pub peer_restarts: u64,
    /// Messages rejected as invalid (non-finite, asymmetric, wrong size or origin).
    pub rejected: u64,
    /// Deltas the caller's estimator refused to fuse (retried later).
    pub fuse_failures: u64,
    /// Submaps sent (CI mode).
    pub submaps_sent: u64,
    /// Submaps fused by CI.
    pub submaps_fused: u64,
    /// Received submaps dropped unfused because more than `max_buffer` waited for one round
    /// (the sender resends their features when no acknowledgement comes).
    #[serde(default)]
    pub submaps_dropped: u64,
    /// Submap acknowledgements received (each names one fused submap).
    #[serde(default)]
    pub submap_acks: u64,
    /// Submaps that could not be fused (CI error, e.g. a receiver map that is not positive
    /// definite) or not built (the sender's map not positive definite).
    pub ci_failures: u64,
    /// Rounds in which a CI link had no room for even one feature, or a sparsified link no
    /// room for one feature's delta.
    pub budget_starved: u64,
    /// Deltas sent sparsified (the marginal on the features that fit; [`crate::sparse`]).
    #[serde(default)]
    pub sparse_deltas: u64,
    /// Of those, the ones whose residual block needed regularisation (not strictly ⪯ the
    /// delta: the claim may exceed it by δ on held-back features, module docs).
    #[serde(default)]
    pub sparse_regularised: u64,
    /// Of the sparsified deltas, those whose vector had components removed by its χ² gate
    /// against the marginal's information ([`crate::sparse::VECTOR_GATE_PROBABILITY`]: books
    /// formed about earlier estimates; for linear-Gaussian data once in 10⁶).
    #[serde(default)]
    pub sparse_vector_dropped: u64,
    /// Sparsified marginals after which the sender re-centred its books
    /// ([`RECENTRE_AFTER_GATED`] consecutive gated ones).
    #[serde(default)]
    pub sparse_recentred: u64,
    /// Rounds a sparsified link sent no delta (the delta stays pending): the sum of the four
    /// reasons below.
    #[serde(default)]
    pub sparse_refused: u64,
    /// Of those, rounds whose residual block D_RR was not positive definite up to the largest
    /// regularisation ([`crate::sparse::SparsifyError::Indefinite`]).
    #[serde(default)]
    pub sparse_refused_indefinite: u64,
    /// Of those, rounds whose marginal came out non-finite
    /// ([`crate::sparse::SparsifyError::NonFinite`]).
    #[serde(default)]
    pub sparse_refused_non_finite: u64,
    /// Of those, rounds whose marginal removed too much information
    /// ([`crate::sparse::SparsifyError::TooNegative`]).
    #[serde(default)]
    pub sparse_refused_too_negative: u64,
    /// Of those, rounds that would have held back more than `MAX_WITHHELD_NEW` features new
    /// to the peer ([`MAX_INTRODUCED_SIGMA_M`]).
    #[serde(default)]
    pub sparse_refused_withheld: u64,
    /// Features the peer knows only from this side (it sent none of their information) held
    /// back from a sparsified delta because what the peer would then hold on them (all sent
    /// before plus the marginal) was not positive definite with σ ≤
    /// [`MAX_INTRODUCED_SIGMA_M`] (they stay in the residual for later rounds).
    #[serde(default)]
    pub sparse_withheld_new: u64,
    /// [`Body::Uncertain`] lists sent (this node's loosely held features).
    #[serde(default)]
    pub uncertain_sent: u64,
    /// Features put first into a sparsified marginal because the peer listed them as
    /// loosely held and this node holds them far better ([`PROMOTE_SIGMA_RATIO`]).
    #[serde(default)]
    pub uncertain_promoted: u64,
}

impl ChannelStats {
    /// Counts a sparsified round refused for `e`, in the total and under its reason.
    fn count_sparse_refusal(&mut self, e: &sparse::SparsifyError) {
        self.sparse_refused += 1;
        match e {
            sparse::SparsifyError::Indefinite { .. } => self.sparse_refused_indefinite += 1,
            sparse::SparsifyError::NonFinite => self.sparse_refused_non_finite += 1,
            sparse::SparsifyError::TooNegative { .. } => self.sparse_refused_too_negative += 1,
        }
    }
}

/// The largest σ [m] along its worst axis with which a sparsified delta leaves a feature at a
/// peer that knows it only from this side (`Channel::sparsify`, [`sparse::weakest_new_feature`]).
/// An EKF's delta Y_i − C_ik is not exactly positive semi-definite (its information was formed
/// about other estimates than the books'), and its Schur marginal on a feature mostly explained
/// by held-back ones can be nearly nothing or indefinite. Measured on tree-8 with 128 kB/s
/// radios (60 s, 40 multi-process runs): new features arrived with block eigenvalues down to
/// −2.5e-3 m⁻², alone or summed over the deltas of a batch; the receiver must then refuse the
/// batch (its new-feature information ΔY_uu is not positive definite) and after three attempts
/// drops it (7 of 40 runs refused one, 6 dropped one, 2 ended with a feature ~1.3 km off at
/// σ ≈ 2 m in four vehicles); known to kilometres, such features let a χ² gate take a lookalike
/// hundreds of metres away for the same feature. 100 m is 20× the σ of a range-bearing
/// feature at its first sighting in the shipped scenarios (≤ 5 m) and 5× the correspondence
/// search's bound (`canopy_fusion::slam::CorrespondenceConfig::max_difference_sigma_m`).
pub const MAX_INTRODUCED_SIGMA_M: f64 = 100.0;

/// After how many consecutive gated marginals on a link the sender re-centres its books
/// ([`sparse::Marginal::recentre`], module [`crate::sparse`], "Re-centring").
///
/// Why not at the first: the re-centring also drops the pull through C of data not yet
/// delivered, which moves means across the whole map. Re-centring at every gated marginal,
/// `canopy sim` of radio-32k (seed 1, 300 s, one gated marginal in the run) ended at team map
/// RMSE 1.936 m (1.234× the reference) against 1.717 m without. An isolated gate is mostly a
/// one-round excursion; gating that persists is the stale drift the re-centring is for. Why 3:
/// a storm is tens of consecutive rounds (up to 115 of 131 marginals at one end in a tree-8-radio
/// run with a two-second interval), so re-centring at the third costs it two rounds.
pub(crate) const RECENTRE_AFTER_GATED: u32 = 3;

/// A feature held with a marginal σ = √tr P_ff above this [m] is listed to the peers of
/// sparsified links ([`Body::Uncertain`]). Why 10 m: the shipped radio scenarios hold a
/// feature they observe at σ ≤ 5 m; the features the per-feature priority left unrefined
/// (docs/benchmarks.md, seventeenth pass) sat at 18–73 m for minutes at leaves whose hub held
/// them at 2.2 m.
pub const UNCERTAIN_SIGMA_M: f64 = 10.0;

/// A feature the peer listed as loosely held goes first into this node's next marginal when
/// its σ here is at most the peer's divided by this. Why 3: the marginal then carries an
/// information gain of at least ln 9 per axis to the peer, more than the typical feature of a
/// round's selection, and a feature both sides hold about equally is left to the priority.
pub const PROMOTE_SIGMA_RATIO: f64 = 3.0;

/// How many features a sparsified delta may hold back by [`MAX_INTRODUCED_SIGMA_M`] before
/// the round sends nothing on the link (each costs a Schur marginal).
const MAX_WITHHELD_NEW: usize = 8;

/// Where the current epoch pair is.
#[derive(Clone, Debug)]
enum Pair {
    /// Peer epoch unknown, or known but roles not decided (waiting for the peer's Hello).
    Unpaired,
    /// This node sent the Sync and waits for its acknowledgement; the Sync is resent as is.
    Initiating {
        generation: u64,
        history: bool,
        baseline: MapInformation,
    },
    /// The peer initiates; this node waits for its Sync (sends only Hellos).
    Awaiting,
    /// Deltas flow.
    Synced,
}

/// The channel filter of node i for neighbour k (design.md §4), plus its link protocol.
#[derive(Clone, Debug)]
pub(crate) struct Channel {
    peer: NodeId,
    link_up: bool,
    mode: LinkMode,
    budget: Option<usize>,
    peer_epoch: Option<u64>,
    retired: VecDeque<u64>,
    /// Unknown epochs of the peer heard of, with the challenge they must echo to be adopted.
    candidates: VecDeque<(u64, u64)>,
    /// Our liveness challenge on this link (raised for every new candidate).
    challenge: u64,
    /// The peer epoch heard from last (any non-retired one) and the highest challenge it sent.
    heard: Option<(u64, u64)>,
    /// Paired (or initiated a pairing) with some incarnation of the peer.
    history: bool,
    /// The peer's history flag, from its latest Hello in the current peer epoch.
    peer_history: Option<bool>,
    pair: Pair,
    sync_gen: u64,
    /// S: cumulative information sent in the current epoch pair (packed: `store` module).
    sent: PackedInformation,
    /// Σ δ of the sparsified marginals sent ([`super::ChannelView::sparse_shift`]).
    sparse_shift: f64,
    /// Σ pad_R(δ I, δ x̄) of the sparsified marginals sent in the current pair, per held-back
    /// feature, less the re-centrings of gated marginals (vector only): `sent` books
    /// D' − pad_R(δ I) and the re-centring while the peer received and booked D', so what
    /// the peer holds of us is `sent` plus this ([`Self::wire_sent`]).
    booked_shift: BTreeMap<FeatureId, (f64, Vector3<f64>)>,
    /// R: cumulative information received from the peer and applied in the current pair.
    received: PackedInformation,
    seq_sent: u64,
    applied: u64,
    buffer: BTreeMap<u64, MapInformation>,
    /// Highest sequence number the peer is known to have sent in this pair.
    peer_seq_hint: u64,
    gap_since: Option<f64>,
    last_nack: Option<f64>,
    last_hello: Option<f64>,
    last_sync: Option<f64>,
    /// Round time of the last delta (or CI submap) formed on this capacity-limited link
    /// ([`super::DdfConfig::budget_interval`]).
    last_budgeted: Option<f64>,
    /// Consecutive sparsified marginals whose vector was gated ([`RECENTRE_AFTER_GATED`]).
    gated_streak: u32,
    /// The peer's latest [`Body::Uncertain`] list: its loosely held features, σ [m].
    peer_uncertain: HashMap<FeatureId, f64>,
    /// Whether the last [`Body::Uncertain`] this node sent listed anything (an empty list is
    /// sent once to clear the peer's record).
    listed_uncertain: bool,
    /// R_total − R: R_total is everything ever received from the peer and applied, over all
    /// epochs; it differs from R only by what earlier epoch pairs left (`None`: nothing, the
    /// case until a peer restarts), so only that difference is stored.
    total_offset: Option<PackedInformation>,
    tracker: SubmapTracker,
    /// Number of the last submap sent on this link.
    submap_seq: u64,
    /// Numbers of the submaps fused since the last acknowledgement sent.
    submap_acks: Vec<u64>,
    /// Merges to tell the peer (sent first in the next round).
    facts_out: Vec<Merge>,
    /// Keys to ask the peer to describe at the next round ([`Body::DescribeRequest`]).
    requests_out: Vec<FeatureId>,
    /// Keys the peer asked this node to describe (answered at the next round).
    requested: BTreeSet<FeatureId>,
    /// The peer's epoch changed: it must be told every merge this node holds.
    pub(crate) needs_all_facts: bool,
    /// Keys whose descriptors the peer's current epoch has been sent.
    described: HashSet<FeatureId>,
    pub(crate) stats: ChannelStats,
}

/// The node's map information, formed on first use in a round (only exact links need it),
/// with its largest entries (the thresholds of every link's delta). What the source handed
/// out goes back to it when the round is done ([`MapSource::restore_information`]: a source
/// may lend its maintained matrix instead of copying it).
pub(crate) struct LazyInformation<'a> {
    source: &'a mut dyn MapSource,
    origin: Vector3<f64>,
    keys: &'a KeyMap,
    value: Option<MapInformation>,
    /// max |Y|, max |y| of `value`.
    norms: (f64, f64),
    /// `value` is what the source handed out (not a re-keyed copy): it goes back.
    returnable: bool,
}

impl<'a> LazyInformation<'a> {
    pub(crate) fn new(
        source: &'a mut dyn MapSource,
        origin: Vector3<f64>,
        keys: &'a KeyMap,
    ) -> Self {
        Self {
            source,
            origin,
            keys,
            value: None,
            norms: (0.0, 0.0),
            returnable: false,
        }
    }

    /// The information, validated and in the node's origin, with its largest matrix and
    /// vector entries.
    pub(crate) fn get_with_norms(&mut self) -> Result<(&MapInformation, f64, f64), DdfError> {
        if self.value.is_none() {
            let info = self
                .source
                .information()
                .map_err(DdfError::InvalidEstimate)?;
            let checked = info.validate().and_then(|()| {
                if info.origin != self.origin {
                    Err(InfoError::OriginMismatch {
                        left: self.origin.into(),
                        right: info.origin.into(),
                    })
                } else {
                    Ok(())
                }
            });
            if let Err(e) = checked {
                self.source.restore_information(info);
                return Err(DdfError::InvalidEstimate(e));
            }
            // In the node's key space (an estimate that could not apply a merge yet still
            // shares its information under the merged keys).
            // (Moved, not copied, when no merge touches it: it is the size of the map.)
            let info = if self.keys.touches(&info.ids) {
                let rekeyed = info.rekeyed(self.keys);
                self.source.restore_information(info);
                rekeyed
            } else {
                self.returnable = true;
                info
            };
            self.norms = (info.matrix_norm_max(), info.vector_norm_max());
            self.value = Some(info);
        }
        let (m, v) = self.norms;
        Ok((self.value.as_ref().expect("just set"), m, v))
    }

    /// The source itself (covariance-form reads).
    pub(crate) fn source(&self) -> &dyn MapSource {
        &*self.source
    }
}

impl Drop for LazyInformation<'_> {
    fn drop(&mut self) {
        if let Some(info) = self.value.take()
            && self.returnable
        {
            self.source.restore_information(info);
        }
    }
}

/// What a channel needs to know about its node.
#[derive(Clone, Copy, Debug)]
pub(crate) struct NodeCtx<'a> {
    pub id: NodeId,
    pub epoch: u64,
    pub origin: Vector3<f64>,
    pub config: &'a DdfConfig,
}

impl Channel {
    pub(crate) fn new(peer: NodeId, origin: Vector3<f64>, budget: Option<usize>) -> Self {
        Self {
            peer,
            link_up: true,
            mode: LinkMode::Exact,
            budget,
            peer_epoch: None,
            retired: VecDeque::new(),
            candidates: VecDeque::new(),
            challenge: 1,
            heard: None,
            history: false,
            peer_history: None,
            pair: Pair::Unpaired,
            sync_gen: 0,
            sent: PackedInformation::zero(origin),
            sparse_shift: 0.0,
            booked_shift: BTreeMap::new(),
            received: PackedInformation::zero(origin),
            seq_sent: 0,
            applied: 0,
            buffer: BTreeMap::new(),
            peer_seq_hint: 0,
            gap_since: None,
            last_nack: None,
            last_hello: None,
            last_sync: None,
            last_budgeted: None,
            gated_streak: 0,
            peer_uncertain: HashMap::new(),
            listed_uncertain: false,
            total_offset: None,
            tracker: SubmapTracker::default(),
            submap_seq: 0,
            submap_acks: Vec::new(),
            facts_out: Vec::new(),
            requests_out: Vec::new(),
            requested: BTreeSet::new(),
            needs_all_facts: false,
            described: HashSet::new(),
            stats: ChannelStats::default(),
        }
    }

    pub(crate) fn mode(&self) -> LinkMode {
        self.mode
    }

    pub(crate) fn is_synced(&self) -> bool {
        matches!(self.pair, Pair::Synced)
    }

    pub(crate) fn sparse_shift(&self) -> f64 {
        self.sparse_shift
    }

    pub(crate) fn link_up(&self) -> bool {
        self.link_up
    }

    pub(crate) fn set_budget(&mut self, budget: Option<usize>) {
        self.budget = budget;
    }

    /// Submap `seq` was fused: acknowledged with the next round's messages.
    fn submap_fused(&mut self, seq: u64) {
        self.stats.submaps_fused += 1;
        if self.submap_acks.len() < MAX_SUBMAP_ACKS {
            self.submap_acks.push(seq);
        }
    }

    fn header(&self, ctx: &NodeCtx<'_>) -> Header {
        Header {
            from_epoch: ctx.epoch,
            to_epoch: self.peer_epoch,
            challenge: self.challenge,
            echo_epoch: self.heard.map_or(0, |(e, _)| e),
            echo: self.heard.map_or(0, |(_, c)| c),
        }
    }

    pub(crate) fn msg(&mut self, ctx: &NodeCtx<'_>, body: Body) -> DdfMessage {
        self.stats.messages_sent += 1;
        DdfMessage {
            header: self.header(ctx),
            body,
        }
    }

    fn hello(&mut self, ctx: &NodeCtx<'_>, now: f64) -> DdfMessage {
        self.last_hello = Some(now);
        let body = Body::Hello(Hello {
            seq_sent: self.seq_sent,
            applied: self.applied,
            history: self.history,
            synced: self.is_synced(),
            ci: self.mode == LinkMode::Ci,
        });
        self.msg(ctx, body)
    }

    /// R_total = R + (R_total − R).
    fn received_total(&self) -> PackedInformation {
        let mut total = self.received.clone();
        if let Some(offset) = &self.total_offset {
            total.add_packed(offset, 1.0);
        }
        total
    }

    /// Replaces R by `received`, keeping R_total: the offset R_total − R becomes the old
    /// R_total minus the new R.
    fn set_received(&mut self, received: PackedInformation) {
        let mut offset = self.received_total();
        offset.add_packed(&received, -1.0);
        self.total_offset = (!offset.is_zero()).then_some(offset);
        self.received = received;
    }

    /// Forgets the epoch pair: a new one starts with the peer's new epoch (R_total is kept).
    fn reset_pair(&mut self, origin: Vector3<f64>) {
        self.pair = Pair::Unpaired;
        self.sent = PackedInformation::zero(origin);
        self.booked_shift.clear();
        self.set_received(PackedInformation::zero(origin));
        self.seq_sent = 0;
        self.applied = 0;
        self.buffer.clear();
        self.peer_seq_hint = 0;
        self.gap_since = None;
        self.last_nack = None;
        self.last_sync = None;
        self.last_budgeted = None;
        self.gated_streak = 0;
        self.peer_history = None;
        // A new pair starts without lists (a restarted peer holds another map).
        self.peer_uncertain.clear();
        self.listed_uncertain = false;
    }

    fn new_peer_epoch(&mut self, epoch: u64, ctx: &NodeCtx<'_>) {
        if let Some(old) = self.peer_epoch {
            self.stats.peer_restarts += 1;
            self.retired.push_back(old);
            while self.retired.len() > ctx.config.retired_epochs {
                self.retired.pop_front();
            }
        }
        self.peer_epoch = Some(epoch);
        self.candidates.clear();
        self.reset_pair(ctx.origin);
        // The restarted peer lost what it had from us.
        self.tracker.clear();
        self.submap_acks.clear();
        self.described.clear();
        self.needs_all_facts = true;
    }

    /// Applies a merge to everything this channel holds (module [`crate::keys`]): S, R,
    /// R_total, buffered deltas and a pending Sync baseline; the fact is queued for the peer.
    pub(crate) fn rekey(&mut self, keys: &KeyMap, fact: Merge) {
        self.sent.rekey(keys);
        if keys.touches(&self.booked_shift.keys().copied().collect::<Vec<_>>()) {
            let mut merged = BTreeMap::new();
            for (id, (a, v)) in std::mem::take(&mut self.booked_shift) {
                book_shift(&mut merged, keys.canonical(id), a, v);
            }
            self.booked_shift = merged;
        }
        self.received.rekey(keys);
        if let Some(o) = self.total_offset.as_mut() {
            o.rekey(keys);
        }
        for d in self.buffer.values_mut() {
            d.rekey(keys);
        }
        if let Pair::Initiating { baseline, .. } = &mut self.pair {
            baseline.rekey(keys);
        }
        self.facts_out.push(fact);
    }

    /// Queues merges for the peer.
    pub(crate) fn queue_facts(&mut self, facts: &[Merge]) {
        self.facts_out.extend_from_slice(facts);
    }

    /// Asks the peer, at the next round, to describe `keys` (replacing an unsent request).
    pub(crate) fn request_descriptors(&mut self, keys: &[FeatureId]) {
        self.requests_out = keys.to_vec();
    }

    /// The peer asked for descriptors of `keys`: answered at the next round.
    pub(crate) fn descriptors_requested(&mut self, keys: &[FeatureId]) {
        self.requested.extend(keys.iter().copied());
    }

    /// The round's descriptor traffic: the request of keys this node lacks, and the answer to
    /// the peer's request (the descriptors this node knows, under the keys the peer used).
    fn descriptor_messages(
        &mut self,
        source: &dyn MapSource,
        keys: &KeyMap,
        ctx: &NodeCtx<'_>,
        out: &mut Vec<DdfMessage>,
    ) {
        let ask = std::mem::take(&mut self.requests_out);
        for chunk in ask.chunks(MAX_LIST) {
            let msg = self.msg(
                ctx,
                Body::DescribeRequest {
                    keys: chunk.to_vec(),
                },
            );
            out.push(msg);
        }
        if self.requested.is_empty() {
            return;
        }
        let asked: Vec<FeatureId> = std::mem::take(&mut self.requested).into_iter().collect();
        let canonical: Vec<FeatureId> = asked.iter().map(|&k| keys.canonical(k)).collect();
        let known: HashMap<FeatureId, Appearance> =
            source.descriptors(&canonical).into_iter().collect();
        let features: Vec<(FeatureId, Appearance)> = asked
            .iter()
            .zip(&canonical)
            .filter_map(|(&k, c)| known.get(c).map(|a| (k, *a)))
            .collect();
        for chunk in features.chunks(MAX_LIST) {
            let msg = self.msg(
                ctx,
                Body::Describe {
                    features: chunk.to_vec(),
                },
            );
            out.push(msg);
        }
    }

    /// A `Describe` of the keys of `ids` this peer epoch has not been sent yet (`None` when
    /// there are none or the estimator knows no descriptor for them).
    fn describe_new(
        &mut self,
        ids: &[FeatureId],
        source: &dyn MapSource,
        ctx: &NodeCtx<'_>,
    ) -> Option<DdfMessage> {
        let new: Vec<FeatureId> = ids
            .iter()
            .copied()
            .filter(|k| !self.described.contains(k))
            .collect();
        if new.is_empty() {
            return None;
        }
        self.described.extend(&new);
        let features = source.descriptors(&new);
        if features.is_empty() {
            return None;
        }
        Some(self.msg(ctx, Body::Describe { features }))
    }

    /// Decides this node's role in an undecided epoch pair, and initiates if it is ours:
    /// the side with history initiates (it alone knows R_total); at first contact the lower id.
    fn decide(&mut self, now: f64, ctx: &NodeCtx<'_>, out: &mut Vec<DdfMessage>) {
        if !matches!(self.pair, Pair::Unpaired)
            || self.mode == LinkMode::Ci
            || self.peer_epoch.is_none()
        {
            return;
        }
        let initiate = if self.history {
            true
        } else {
            match self.peer_history {
                None => return,
                Some(peer_history) => !peer_history && ctx.id < self.peer,
            }
        };
        if !initiate {
            self.pair = Pair::Awaiting;
            return;
        }
        // S := baseline = R_total, R := 0: this node claims the peer holds everything it ever
        // sent us; the restarted peer's first delta (Y_k − C_k, C_k = baseline) removes that
        // old information again where it is no longer backed (docs of `crate::ddf`).
        self.sync_gen += 1;
        let total = self.received_total();
        let baseline = total.to_dense();
        self.sent = total;
        self.booked_shift.clear();
        self.set_received(PackedInformation::zero(ctx.origin));
        self.stats.syncs_initiated += 1;
        self.pair = Pair::Initiating {
            generation: self.sync_gen,
            history: self.history,
            baseline,
        };
        self.history = true;
        if self.link_up {
            let sync = self.sync_message(ctx);
            out.push(sync);
            self.last_sync = Some(now);
        }
    }

    fn sync_message(&mut self, ctx: &NodeCtx<'_>) -> DdfMessage {
        let Pair::Initiating {
            generation,
            history,
            baseline,
        } = &self.pair
        else {
            unreachable!("sync_message is only called while initiating")
        };
        let body = Body::Sync {
            generation: *generation,
            history: *history,
            baseline: baseline.clone(),
        };
        self.msg(ctx, body)
    }

    /// Any message of the peer that proves it applied our Sync completes the pair.
    fn acknowledge(&mut self) {
        if matches!(self.pair, Pair::Initiating { .. }) {
            self.pair = Pair::Synced;
        }
    }

    fn gap_open(&self) -> bool {
        let last_buffered = self.buffer.keys().next_back().copied().unwrap_or(0);
        self.peer_seq_hint.max(last_buffered) > self.applied
    }

    fn update_gap(&mut self, now: f64) {
        if self.gap_open() {
            self.gap_since.get_or_insert(now);
        } else {
            self.gap_since = None;
        }
    }

    pub(crate) fn use_sparse(&mut self) {
        if self.mode == LinkMode::Exact {
            self.mode = LinkMode::Sparse;
        }
    }

    pub(crate) fn switch_to_ci(&mut self, origin: Vector3<f64>) {
        if self.mode == LinkMode::Ci {
            return;
        }
        // One-way: the channel filter is retired on this link (design.md §4).
        self.mode = LinkMode::Ci;
        self.reset_pair(origin);
        self.total_offset = None;
    }

    /// Fuses `info` into the caller's estimate, then records it (R, R_total, watermark).
    fn apply(
        &mut self,
        info: &MapInformation,
        target: &mut dyn FuseTarget,
    ) -> Result<(), DdfError> {
        if let Err(e) = target.fuse(info) {
            self.stats.fuse_failures += 1;
            return Err(DdfError::FuseRejected {
                from: self.peer,
                source: e,
            });
        }
        // R_total moves with R (the offset R_total − R is unchanged).
        self.received
            .accumulate(info, 1.0)
            .map_err(DdfError::Internal)?;
        Ok(())
    }

    /// Applies buffered deltas that are next in sequence.
    fn drain(&mut self, target: &mut dyn FuseTarget) -> Result<(), DdfError> {
        while let Some(info) = self.buffer.remove(&(self.applied + 1)) {
            if let Err(e) = self.apply(&info, target) {
                self.buffer.insert(self.applied + 1, info);
                return Err(e);
            }
            self.applied += 1;
            self.stats.deltas_applied += 1;
        }
        Ok(())
    }

    /// Handles one received message (already validated). Returns the replies.
    pub(crate) fn on_message(
        &mut self,
        now: f64,
        msg: DdfMessage,
        ctx: &NodeCtx<'_>,
        target: &mut dyn FuseTarget,
    ) -> Result<Vec<DdfMessage>, DdfError> {
        self.stats.messages_received += 1;
        let mut out = Vec::new();
        let h = msg.header;
        if self.retired.contains(&h.from_epoch) {
            // From an incarnation of the peer this channel has moved on from.
            self.stats.stale += 1;
            return Ok(out);
        }
        // Remember the sender's challenge (echoed in our headers); answer a raised one at once
        // so that a node checking our liveness need not wait for our next round.
        let previous = match self.heard {
            Some((e, c)) if e == h.from_epoch => c,
            _ => 0,
        };
        if h.challenge > previous {
            self.heard = Some((h.from_epoch, h.challenge));
            // Challenges start at 1; a higher one was raised for a candidate epoch.
            if h.challenge > 1 && self.link_up {
                out.push(self.hello(ctx, now));
            }
        } else {
            self.heard = Some((h.from_epoch, previous));
        }
        let for_me = h.to_epoch.is_none_or(|e| e == ctx.epoch);
        match self.peer_epoch {
            Some(current) if current == h.from_epoch => {}
            None => {
                // First contact: adopt it (if it is a dead incarnation, the live one will prove
                // itself as a candidate and replace it).
                self.new_peer_epoch(h.from_epoch, ctx);
            }
            Some(_) => {
                let required = self
                    .candidates
                    .iter()
                    .find(|&&(e, _)| e == h.from_epoch)
                    .map(|&(_, r)| r);
                match required {
                    Some(r) if h.echo_epoch == ctx.epoch && h.echo >= r => {
                        // Proven alive after we first heard of it: the peer restarted.
                        self.new_peer_epoch(h.from_epoch, ctx);
                    }
                    Some(_) => {
                        self.stats.stale += 1;
                        return Ok(out);
                    }
                    None => {
                        // Challenge it: raise the challenge and tell the peer's node at once.
                        self.challenge += 1;
                        self.candidates.push_back((h.from_epoch, self.challenge));
                        while self.candidates.len() > ctx.config.retired_epochs {
                            self.candidates.pop_front();
                        }
                        self.stats.stale += 1;
                        if self.link_up {
                            out.push(self.hello(ctx, now));
                        }
                        return Ok(out);
                    }
                }
            }
        }
        if !for_me {
            // Meant for a previous incarnation of this node.
            self.stats.stale += 1;
            return Ok(out);
        }
        let addressed = h.to_epoch.is_some();
        let result = match msg.body {
            Body::Hello(hello) => {
                self.on_hello(now, hello, addressed, ctx);
                Ok(())
            }
            Body::Submap { seq, submap } => {
                self.switch_to_ci(ctx.origin);
                // Fused as it arrives: each CI fusion is consistent whatever the correlation
                // with what was fused before it.
                match target.fuse_submap(&submap, ctx.config.ci_criterion) {
                    Ok(()) => {
                        self.submap_fused(seq);
                        Ok(())
                    }
                    Err(e) => {
                        // Counted here, and its reason goes to the caller (counted by reason
                        // and logged there, like a refused delta).
                        self.stats.ci_failures += 1;
                        Err(DdfError::FuseRejected {
                            from: self.peer,
                            source: e,
                        })
                    }
                }
            }
            Body::SubmapAck { seqs } => {
                self.stats.submap_acks += seqs.len() as u64;
                self.tracker.acknowledge(&seqs);
                Ok(())
            }
            Body::Uncertain { features } => {
                self.peer_uncertain = features
                    .into_iter()
                    .map(|(id, sigma)| (id, f64::from(sigma)))
                    .collect();
                Ok(())
            }
            // Handled by the node (they concern every channel, or, a data-sharing batch, are
            // refused by it); nothing left to do here.
            Body::Merges { .. }
            | Body::Describe { .. }
            | Body::DescribeRequest { .. }
            | Body::Anchor { .. }
            | Body::Share(_) => Ok(()),
            _ if self.mode == LinkMode::Ci || !addressed => {
                // Exact-protocol messages on a CI link, or not addressed to this epoch.
                self.stats.stale += 1;
                Ok(())
            }
            Body::Sync {
                history, baseline, ..
            } => {
                self.on_sync(now, history, baseline, ctx, &mut out);
                Ok(())
            }
            Body::Delta { seq, info } => self.on_delta(now, seq, info, ctx, target, &mut out),
            Body::Nack { applied } => {
                self.on_nack(applied, ctx, &mut out);
                Ok(())
            }
            Body::Cumulative { upto, info } => self.on_cumulative(now, upto, info, target),
        };
        self.decide(now, ctx, &mut out);
        result.map(|()| out)
    }

    fn on_hello(&mut self, now: f64, hello: Hello, addressed: bool, ctx: &NodeCtx<'_>) {
        self.peer_history = Some(hello.history);
        if hello.ci {
            self.switch_to_ci(ctx.origin);
            return;
        }
        if !addressed || !hello.synced {
            return;
        }
        self.acknowledge();
        if self.is_synced() {
            self.peer_seq_hint = self.peer_seq_hint.max(hello.seq_sent);
            self.update_gap(now);
        }
    }

    fn on_sync(
        &mut self,
        now: f64,
        peer_history: bool,
        baseline: MapInformation,
        ctx: &NodeCtx<'_>,
        out: &mut Vec<DdfMessage>,
    ) {
        match &self.pair {
            Pair::Synced => {
                // Already applied (or we initiated and were acknowledged): re-acknowledge.
                self.stats.duplicates += 1;
                let hello = self.hello(ctx, now);
                out.push(hello);
                return;
            }
            Pair::Initiating { .. } | Pair::Unpaired | Pair::Awaiting => {}
        }
        // Who may initiate this epoch pair: the side with history, else the lower id. A Sync
        // from the side that may not (it acted on stale knowledge of our history, e.g. a Hello
        // delayed from before our pairing) is refused, and we initiate instead: applying it
        // would set C to its baseline (0 for a fresh node) and send back everything we hold,
        // including what the peer's dead incarnation gave us. Both sides evaluate the same rule
        // on the same flags, so exactly one Sync of the pair is applied.
        let my_history = match &self.pair {
            Pair::Initiating { history, .. } => *history,
            _ => self.history,
        };
        self.peer_history = Some(peer_history);
        let peer_wins =
            (peer_history && !my_history) || (peer_history == my_history && self.peer < ctx.id);
        if !peer_wins {
            self.stats.stale += 1;
            return;
        }
        // Apply: R := baseline, S := 0 (nothing to fuse: the baseline is what the peer
        // already received from us, however long ago).
        let baseline = match PackedInformation::from_dense(&baseline) {
            Ok(b) => b,
            Err(e) => {
                // Validated on receipt (shape, origin), so this is not reached; refused, not
                // applied, if it were.
                self.stats.rejected += 1;
                debug_assert!(false, "validated Sync baseline refused: {e}");
                return;
            }
        };
        self.sent = PackedInformation::zero(ctx.origin);
        self.booked_shift.clear();
        self.set_received(baseline);
        self.seq_sent = 0;
        self.applied = 0;
        self.buffer.clear();
        self.peer_seq_hint = 0;
        self.gap_since = None;
        self.pair = Pair::Synced;
        self.history = true;
        self.stats.syncs_applied += 1;
        let hello = self.hello(ctx, now);
        out.push(hello);
    }

    fn on_delta(
        &mut self,
        now: f64,
        seq: u64,
        info: MapInformation,
        ctx: &NodeCtx<'_>,
        target: &mut dyn FuseTarget,
        out: &mut Vec<DdfMessage>,
    ) -> Result<(), DdfError> {
        // A delta of this pair proves the peer applied our Sync.
        self.acknowledge();
        if !self.is_synced() {
            self.stats.stale += 1;
            return Ok(());
        }
        self.peer_seq_hint = self.peer_seq_hint.max(seq);
        if seq <= self.applied || self.buffer.contains_key(&seq) {
            self.stats.duplicates += 1;
        } else if seq > self.applied + 1 && self.buffer.len() >= ctx.config.max_buffer {
            // No room ahead of the gap: drop it (the cumulative will cover it) and ask now.
            self.stats.buffer_overflows += 1;
            self.stats.nacks_sent += 1;
            self.last_nack = Some(now);
            let nack = self.msg(
                ctx,
                Body::Nack {
                    applied: self.applied,
                },
            );
            out.push(nack);
        } else {
            if seq > self.applied + 1 {
                self.stats.out_of_order += 1;
            }
            self.buffer.insert(seq, info);
        }
        // Apply what is next in sequence (including a delta the estimator refused earlier).
        let result = self.drain(target);
        self.update_gap(now);
        result
    }

    fn on_nack(&mut self, applied: u64, ctx: &NodeCtx<'_>, out: &mut Vec<DdfMessage>) {
        self.acknowledge();
        self.stats.nacks_received += 1;
        if self.is_synced() && self.seq_sent > applied {
            self.stats.cumulatives_sent += 1;
            let body = Body::Cumulative {
                upto: self.seq_sent,
                info: self.wire_sent().to_dense(),
            };
            let msg = self.msg(ctx, body);
            out.push(msg);
        }
    }

    /// What the peer received from us in this pair and booked as R: S plus the shifts booked
    /// beside the sparsified marginals (they went on the wire as D'). A Cumulative carries it:
    /// carrying S itself would hand the peer −δ I on held-back features it may not hold
    /// (refused by its estimator as new features whose information is not positive definite).
    fn wire_sent(&self) -> PackedInformation {
        let mut wire = self.sent.clone();
        wire.add_diagonal(self.booked_shift.iter().map(|(id, (a, v))| (*id, *a, *v)));
        wire
    }

    fn on_cumulative(
        &mut self,
        now: f64,
        upto: u64,
        info: MapInformation,
        target: &mut dyn FuseTarget,
    ) -> Result<(), DdfError> {
        self.acknowledge();
        if !self.is_synced() || upto <= self.applied {
            self.stats.stale += 1;
            return Ok(());
        }
        // Apply S − R: exactly the deltas ≤ upto not applied yet.
        let received = PackedInformation::from_dense(&info).map_err(DdfError::Internal)?;
        let mut missing = info;
        let mut minus_r = self.received.to_dense();
        minus_r.matrix *= -1.0;
        minus_r.vector *= -1.0;
        missing.add_assign(&minus_r).map_err(DdfError::Internal)?;
        if let Err(e) = target.fuse(&missing) {
            self.stats.fuse_failures += 1;
            return Err(DdfError::FuseRejected {
                from: self.peer,
                source: e,
            });
        }
        // R_total += S − R and R := S: the offset R_total − R is unchanged.
        self.received = received;
        self.applied = upto;
        self.peer_seq_hint = self.peer_seq_hint.max(upto);
        self.buffer.retain(|&s, _| s > upto);
        self.stats.cumulatives_applied += 1;
        let result = self.drain(target);
        self.update_gap(now);
        result
    }

    /// The periodic exact part: Sync resend while initiating, the delta d = Y_i − C_ik, a Nack
    /// on a persisting gap. A delta over budget switches the link to CI instead.
    pub(crate) fn round_exact(
        &mut self,
        now: f64,
        current: &mut LazyInformation<'_>,
        ctx: &NodeCtx<'_>,
    ) -> Result<Vec<DdfMessage>, DdfError> {
        let mut out = Vec::new();
        if self.link_up && !self.facts_out.is_empty() {
            for chunk in std::mem::take(&mut self.facts_out).chunks(MAX_LIST) {
                let msg = self.msg(
                    ctx,
                    Body::Merges {
                        merges: chunk.to_vec(),
                    },
                );
                out.push(msg);
            }
        }
        self.decide(now, ctx, &mut out);
        if !self.link_up || self.mode == LinkMode::Ci {
            return Ok(out);
        }
        let cfg = ctx.config;
        match self.pair {
            Pair::Initiating { .. } => {
                if self
                    .last_sync
                    .is_none_or(|t| now - t >= cfg.sync_resend_interval)
                {
                    let sync = self.sync_message(ctx);
                    out.push(sync);
                    self.last_sync = Some(now);
                }
            }
            Pair::Synced => {
                if self.budgeted_round_due(now, cfg) {
                    self.send_delta(current, ctx, &mut out)?;
                }
                if self.gap_since.is_some_and(|t| now - t >= cfg.gap_timeout)
                    && self.last_nack.is_none_or(|t| now - t >= cfg.gap_timeout)
                {
                    self.stats.nacks_sent += 1;
                    self.last_nack = Some(now);
                    let nack = self.msg(
                        ctx,
                        Body::Nack {
                            applied: self.applied,
                        },
                    );
                    out.push(nack);
                }
            }
            Pair::Unpaired | Pair::Awaiting => {}
        }
        Ok(out)
    }

    /// The rest of a round: a submap on a CI link (from the node's covariance form, `None` if
    /// it could not be formed), then the Hello when due (last, so that it announces this
    /// round's seq_sent).
    pub(crate) fn round_finish(
        &mut self,
        now: f64,
        source: &dyn MapSource,
        loose: &LooseFeatures,
        keys: &KeyMap,
        ctx: &NodeCtx<'_>,
    ) -> Vec<DdfMessage> {
        let mut out = Vec::new();
        if !self.link_up {
            return out;
        }
        self.descriptor_messages(source, keys, ctx, &mut out);
        if self.mode == LinkMode::Sparse && self.is_synced() && ctx.config.uncertain_lists {
            self.uncertain_message(loose.get_or_init(|| loose_features(source)), ctx, &mut out);
        }
        if self.mode == LinkMode::Ci {
            if !self.submap_acks.is_empty() {
                let seqs = std::mem::take(&mut self.submap_acks);
                let ack = self.msg(ctx, Body::SubmapAck { seqs });
                out.push(ack);
            }
            if self.budgeted_round_due(now, ctx.config) {
                self.send_submap(now, source, ctx, &mut out);
            }
        }
        if self
            .last_hello
            .is_none_or(|t| now - t >= ctx.config.hello_interval)
        {
            let hello = self.hello(ctx, now);
            out.push(hello);
        }
        out
    }

    /// The [`Body::Uncertain`] of this round on a sparsified link, listing `loose` (this
    /// node's [`loose_features`]); nothing when there are none and the peer was told so
    /// already.
    fn uncertain_message(
        &mut self,
        loose: &[(FeatureId, f32)],
        ctx: &NodeCtx<'_>,
        out: &mut Vec<DdfMessage>,
    ) {
        if loose.is_empty() && !self.listed_uncertain {
            return;
        }
        self.listed_uncertain = !loose.is_empty();
        self.stats.uncertain_sent += 1;
        let msg = self.msg(
            ctx,
            Body::Uncertain {
                features: loose.to_vec(),
            },
        );
        out.push(msg);
    }

    /// Puts first into `keep` (keeping its length) the features of `d` the peer listed as
    /// loosely held ([`Body::Uncertain`]) that this node holds at least
    /// [`PROMOTE_SIGMA_RATIO`] times better, by that ratio, at most half of `keep`: the
    /// per-feature priority sees only this node's covariance, and a feature relayed to the
    /// peer as a loose cluster would otherwise wait behind every feature observed since.
    fn promote_uncertain(
        &mut self,
        d: &MapInformation,
        covariances: &HashMap<FeatureId, Matrix3<f64>>,
        keep: &mut Vec<FeatureId>,
    ) {
        if self.peer_uncertain.is_empty() || keep.is_empty() {
            return;
        }
        let mut promoted: Vec<(f64, FeatureId)> = d
            .ids
            .iter()
            .filter_map(|id| {
                let peer = *self.peer_uncertain.get(id)?;
                let own = feature_sigma(covariances.get(id)?);
                (own * PROMOTE_SIGMA_RATIO <= peer).then_some((peer / own.max(1e-9), *id))
            })
            .collect();
        if promoted.is_empty() {
            return;
        }
        promoted.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        promoted.truncate((keep.len() / 2).max(1));
        self.stats.uncertain_promoted += promoted.len() as u64;
        let n = keep.len();
        let first: Vec<FeatureId> = promoted.into_iter().map(|(_, id)| id).collect();
        keep.retain(|id| !first.contains(id));
        keep.splice(0..0, first);
        keep.truncate(n);
    }

    /// Whether this round forms the link's information message: always on a link without a
    /// byte budget; on a capacity-limited one, at most once per
    /// [`super::DdfConfig::budget_interval`] (the round's budget then covers the interval).
    /// A due round is recorded as taken.
    fn budgeted_round_due(&mut self, now: f64, cfg: &DdfConfig) -> bool {
        if self.budget.is_none() || cfg.budget_interval <= 0.0 {
            return true;
        }
        // Round times are multiples of the period up to round-off: a round 1e-6 s early
        // counts as due.
        if self
            .last_budgeted
            .is_some_and(|t| now - t < cfg.budget_interval - 1e-6)
        {
            return false;
        }
        self.last_budgeted = Some(now);
        true
    }

    fn send_delta(
        &mut self,
        lazy: &mut LazyInformation<'_>,
        ctx: &NodeCtx<'_>,
        out: &mut Vec<DdfMessage>,
    ) -> Result<(), DdfError> {
        let (current, y_max, v_max) = lazy.get_with_norms()?;
        // d = Y_i − C_ik with C_ik = S + R (design.md §4), only its blocks above the threshold.
        let rel = ctx.config.block_threshold_rel;
        let d = store::channel_delta(
            current,
            &self.sent,
            &self.received,
            rel * y_max,
            rel * v_max,
        )
        .map_err(DdfError::Internal)?;
        if d.is_empty() {
            return Ok(());
        }
        // Lossy mode: the channel records exactly what is sent (d_q ⪯ d), so the rest goes out
        // with later deltas and nothing is counted twice.
        let d = match ctx.config.delta_precision {
            super::DeltaPrecision::F64 => d,
            super::DeltaPrecision::F32 => d.quantized_f32_conservative(),
        };
        let d = match self.budget {
            Some(b) if d.block_sparse_wire_bytes() > b => {
                if self.mode != LinkMode::Sparse {
                    // The full delta does not fit: fall back to CI for good (both directions:
                    // the peer switches on our first submap or Hello).
                    self.switch_to_ci(ctx.origin);
                    return Ok(());
                }
                match self.sparsify(&d, b, y_max, lazy.source(), ctx) {
                    Some(Sparsified {
                        info: d,
                        shift,
                        recentre,
                    }) => {
                        // A gated marginal: the stale part of the books' vector is booked as
                        // sent, not left pending to fail the gate again (module `sparse`,
                        // "Re-centring").
                        self.book_beyond_wire(recentre.into_iter().map(|(id, g)| (id, 0.0, g)));
                        // Booked: D' − pad_R(δ I) (module `sparse`, "Booking"): the residual
                        // left in Y_i − C_ik is the exact Schur residual, positive
                        // semi-definite, so the regularisation never piles up into an
                        // indefinite residual block that stalls the link.
                        self.book_beyond_wire(
                            shift
                                .features
                                .iter()
                                .map(|(id, x)| (*id, -shift.delta, -shift.delta * x)),
                        );
                        self.sparse_shift += shift.delta;
                        d
                    }
                    None => return Ok(()),
                }
            }
            _ => d,
        };
        self.sent.accumulate(&d, 1.0).map_err(DdfError::Internal)?;
        if let Some(describe) = self.describe_new(&d.ids, lazy.source(), ctx) {
            out.push(describe);
        }
        self.seq_sent += 1;
        self.stats.deltas_sent += 1;
        let msg = self.msg(
            ctx,
            Body::Delta {
                seq: self.seq_sent,
                info: d,
            },
        );
        out.push(msg);
        Ok(())
    }

    /// Books (a, v) — a·I on a feature's diagonal block, v in its vector — in S beyond what
    /// goes on the wire, and records it in [`Self::booked_shift`] with the opposite sign, so
    /// that [`Self::wire_sent`] (what a Cumulative carries) stays what the peer received: the
    /// regularisation shifts and the re-centrings of sparsified marginals.
    fn book_beyond_wire(&mut self, entries: impl Iterator<Item = (FeatureId, f64, Vector3<f64>)>) {
        for (id, a, v) in entries {
            book_shift(&mut self.booked_shift, id, -a, -v);
            self.sent.add_diagonal([(id, a, v)]);
        }
    }

    /// The marginal of `d` on the features that fit `budget` (module [`crate::sparse`]), its
    /// regularisation searched up to a cap that scales with Y_i (`y_max`, its largest entry);
    /// `None` (counted) when not even one feature fits or the residual block is refused.
    /// Booked like any delta by the caller: the residual d − d' stays in Y_i − C_ik, but for
    /// the re-centring returned after [`RECENTRE_AFTER_GATED`] consecutive gated marginals
    /// ([`sparse::Marginal::recentre`]; empty otherwise).
    fn sparsify(
        &mut self,
        d: &MapInformation,
        budget: usize,
        y_max: f64,
        source: &dyn MapSource,
        ctx: &NodeCtx<'_>,
    ) -> Option<Sparsified> {
        let covariances: HashMap<FeatureId, Matrix3<f64>> =
            source.feature_covariances().into_iter().collect();
        // Blocks in f32 only when the node sends f32 deltas anyway (`delta_precision`): in the
        // SLAM radio runs, always-f32 sparsified deltas made the maps diverge (team map RMSE
        // 107× the reference at 32 kB/s): a Schur complement's large, cancelling entries lose
        // the 2⁻²² relative the conservative rounding holds back, and y (kept in f64) then
        // implies a far-off mean.
        let f32_blocks = ctx.config.delta_precision == super::DeltaPrecision::F32;
        // The sender's estimate of the delta's features (origin-relative): the Schur
        // complement is evaluated about it ([`sparse::schur_marginal_about`]).
        let about: HashMap<FeatureId, Vector3<f64>> = source
            .feature_means(&d.ids)
            .into_iter()
            .map(|(id, x)| (id, x - ctx.origin))
            .collect();
        let mut keep = sparse::select(d, &covariances, budget, f32_blocks);
        if ctx.config.uncertain_lists {
            self.promote_uncertain(d, &covariances, &mut keep);
        }
        // D_RR not positive definite: the feature of the failing pivot joins S in place of the
        // lowest-priority one, a few times, before the round is refused.
        let mut swaps = 0;
        let mut withheld = 0;
        loop {
            if keep.is_empty() {
                self.stats.budget_starved += 1;
                return None;
            }
            let m = match sparse::schur_marginal_about(d, &keep, &about, y_max) {
                Ok(m) => m,
                Err(sparse::SparsifyError::Indefinite {
                    feature: Some(f), ..
                }) if swaps < MAX_PIVOT_SWAPS && !keep.contains(&f) => {
                    swaps += 1;
                    keep.pop();
                    keep.insert(0, f);
                    continue;
                }
                Err(e) => {
                    self.stats.count_sparse_refusal(&e);
                    return None;
                }
            };
            // A feature the peer knows only from this side is sent only when what it then
            // holds on it stays positive definite with σ ≤ MAX_INTRODUCED_SIGMA_M; otherwise
            // it is held back (it stays in R).
            let (sent, received) = (&self.sent, &self.received);
            let weakest = sparse::weakest_new_feature(
                &m.info,
                |id| !received.has(*id),
                |ids| sent.joint_block(ids),
                MAX_INTRODUCED_SIGMA_M,
            );
            if let Some(f) = weakest {
                if withheld >= MAX_WITHHELD_NEW {
                    self.stats.sparse_refused += 1;
                    self.stats.sparse_refused_withheld += 1;
                    return None;
                }
                withheld += 1;
                self.stats.sparse_withheld_new += 1;
                keep.retain(|&k| k != f);
                continue;
            }
            let mut info = m.info;
            let rel = ctx.config.block_threshold_rel;
            info = info.sparsified_with(rel * d.matrix_norm_max(), rel * d.vector_norm_max());
            if f32_blocks {
                info = info.quantized_f32_conservative();
            }
            // The dense bound sized the selection, so this holds; kept as a guard.
            if info.block_sparse_wire_bytes() > budget {
                keep.pop();
                continue;
            }
            if info.is_empty() {
                return None;
            }
            self.stats.sparse_deltas += 1;
            if m.escalated {
                self.stats.sparse_regularised += 1;
            }
            if m.vector_dropped {
                self.stats.sparse_vector_dropped += 1;
                self.gated_streak += 1;
            } else {
                self.gated_streak = 0;
            }
            let recentre = if self.gated_streak >= RECENTRE_AFTER_GATED {
                self.gated_streak = 0;
                self.stats.sparse_recentred += 1;
                m.recentre
            } else {
                Vec::new()
            };
            return Some(Sparsified {
                info,
                shift: m.shift,
                recentre,
            });
        }
    }

    fn send_submap(
        &mut self,
        now: f64,
        source: &dyn MapSource,
        ctx: &NodeCtx<'_>,
        out: &mut Vec<DdfMessage>,
    ) {
        let blocks = source.feature_covariances();
        if blocks.is_empty() {
            return;
        }
        let budget = self.budget.unwrap_or(usize::MAX);
        let timeout = ctx.config.submap_ack_timeout;
        let ids = ci::select_submap(self.tracker.priorities(&blocks, now, timeout), budget);
        if ids.is_empty() {
            self.stats.budget_starved += 1;
            return;
        }
        let marginal = source.marginal(&ids);
        if marginal.ids.len() != ids.len() || marginal.covariance.llt(faer::Side::Lower).is_err() {
            // The estimator could not give a positive definite marginal of its own features.
            self.stats.ci_failures += 1;
            return;
        }
        let submap = Submap::from_marginal(&marginal, &ids, ctx.origin);
        if let Some(describe) = self.describe_new(&submap.ids, source, ctx) {
            out.push(describe);
        }
        self.submap_seq += 1;
        let seq = self.submap_seq;
        self.tracker.record_sent(seq, &submap, now, timeout);
        self.stats.submaps_sent += 1;
        let msg = self.msg(ctx, Body::Submap { seq, submap });
        out.push(msg);
    }

    pub(crate) fn on_link_up(&mut self, now: f64, ctx: &NodeCtx<'_>) -> Vec<DdfMessage> {
        self.link_up = true;
        let mut out = vec![self.hello(ctx, now)];
        if matches!(self.pair, Pair::Initiating { .. }) {
            out.push(self.sync_message(ctx));
            self.last_sync = Some(now);
        }
        out
    }

    pub(crate) fn on_link_down(&mut self) {
        self.link_up = false;
    }

    /// Validation of a received payload against the node's origin (before any state change).
    pub(crate) fn validate_payload(
        msg: &DdfMessage,
        origin: Vector3<f64>,
    ) -> Result<(), InfoError> {
        let check = |info: &MapInformation| -> Result<(), InfoError> {
            info.validate()?;
            if info.origin != origin {
                return Err(InfoError::OriginMismatch {
                    left: origin.into(),
                    right: info.origin.into(),
                });
            }
            Ok(())
        };
        let at_most = |what: &'static str, max: usize, found: usize| {
            if found > max {
                return Err(InfoError::Dimension {
                    what,
                    expected: max,
                    found,
                });
            }
            Ok(())
        };
        match &msg.body {
            // A data-sharing batch is refused by the node before this (`DdfError::Unexpected`).
            Body::Hello(_) | Body::Nack { .. } | Body::Share(_) => Ok(()),
            Body::SubmapAck { seqs } => {
                at_most("submap acknowledgements", MAX_SUBMAP_ACKS, seqs.len())
            }
            Body::Merges { merges } => {
                at_most("merges", MAX_LIST, merges.len())?;
                if let Some(m) = merges.iter().find(|m| m.into >= m.from) {
                    return Err(InfoError::DuplicateId(m.from));
                }
                Ok(())
            }
            Body::Describe { features } => at_most("descriptors", MAX_LIST, features.len()),
            Body::DescribeRequest { keys } => at_most("describe request", MAX_LIST, keys.len()),
            Body::Uncertain { features } => {
                at_most("uncertain features", MAX_UNCERTAIN, features.len())?;
                match features
                    .iter()
                    .position(|(_, sigma)| !(sigma.is_finite() && *sigma > 0.0))
                {
                    Some(row) => Err(InfoError::NonFinite {
                        what: "uncertain feature σ (not finite and positive)",
                        row,
                        col: 0,
                    }),
                    None => Ok(()),
                }
            }
            Body::Anchor { features } => {
                at_most(
                    "anchor features",
                    super::message::MAX_ANCHOR_FEATURES,
                    features.len(),
                )?;
                // A non-finite value or a covariance that is not positive definite.
                match features.iter().position(|f| !f.is_valid()) {
                    Some(row) => Err(InfoError::NonFinite {
                        what: "anchor feature (or its covariance not positive definite)",
                        row,
                        col: 0,
                    }),
                    None => Ok(()),
                }
            }
            Body::Delta { info, .. } | Body::Cumulative { info, .. } => check(info),
            Body::Sync { baseline, .. } => check(baseline),
            Body::Submap { submap: s, .. } => {
                s.validate()?;
                if Vector3::from(s.origin) != origin {
                    return Err(InfoError::OriginMismatch {
                        left: origin.into(),
                        right: s.origin,
                    });
                }
                Ok(())
            }
        }
    }
}

/// A node's loosely held features for its [`Body::Uncertain`] lists, formed at most once per
/// round whatever the number of sparsified links ([`loose_features`]).
pub(crate) type LooseFeatures = OnceCell<Vec<(FeatureId, f32)>>;

/// The features `source` holds with σ ([`feature_sigma`]) above [`UNCERTAIN_SIGMA_M`],
/// loosest first (ties: the smaller id), at most [`MAX_UNCERTAIN`].
fn loose_features(source: &dyn MapSource) -> Vec<(FeatureId, f32)> {
    let mut loose: Vec<(FeatureId, f64)> = source
        .feature_covariances()
        .iter()
        .map(|(id, p)| (*id, feature_sigma(p)))
        .filter(|(_, sigma)| *sigma > UNCERTAIN_SIGMA_M && sigma.is_finite())
        .collect();
    loose.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    loose.truncate(MAX_UNCERTAIN);
    loose
        .into_iter()
        .map(|(id, sigma)| (id, sigma as f32))
        .collect()
}

/// A feature's σ = √tr P_ff [m], the measure of both ends of a [`Body::Uncertain`] list (what
/// the peer lists and what this node compares it with, [`PROMOTE_SIGMA_RATIO`]).
fn feature_sigma(covariance: &Matrix3<f64>) -> f64 {
    covariance.trace().max(0.0).sqrt()
}

/// What [`Channel::sparsify`] sends and books: the marginal (as it goes on the wire), its
/// regularisation shift, and the re-centring of the books' vector (empty unless
/// [`RECENTRE_AFTER_GATED`] consecutive marginals were gated).
struct Sparsified {
    info: MapInformation,
    shift: sparse::Shift,
    recentre: Vec<(FeatureId, Vector3<f64>)>,
}

/// Adds (a, v) to `id`'s entry of a channel's booked shifts ([`Channel::wire_sent`]).
fn book_shift(
    book: &mut BTreeMap<FeatureId, (f64, Vector3<f64>)>,
    id: FeatureId,
    a: f64,
    v: Vector3<f64>,
) {
    let e = book.entry(id).or_insert((0.0, Vector3::zeros()));
    e.0 += a;
    e.1 += v;
}
