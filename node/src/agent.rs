//! The vehicle and hub agents: the estimator and the DDF state machine of one process, wired
//! together, without any I/O. The deterministic simulation ([`crate::sim`]) and the vehicle and
//! hub processes ([`crate::process`]) drive the same agents; only the transport differs.
//!
//! A vehicle agent has two halves: a [`VehicleEstimator`] (an M = 1 [`SlamFilter`]) and a
//! [`VehicleFusion`] (unless the mode is isolated, a [`DdfNode`], and the batch of received
//! information). Each fusion round the fusion half fuses the batch into the filter, reads its
//! map information (Y_i, y_i) (eqs. 21.86, 21.87), lets the DDF node form the per-link deltas,
//! and fuses a CI change (eqs. 21.92, 21.93 as corrected by the channel filters, design.md §4).
//! [`VehicleAgent`] runs both halves on one thread (`canopy sim`); the vehicle process runs
//! them on two, the fusion half on the filter the estimator hands it for each round.

use canopy_fusion::ci::{CiCriterion, Submap};
use canopy_fusion::ddf::{
    Body, DdfConfig, DdfError, DdfMessage, DdfNode, FuseRejected, FuseTarget, InformationStore,
    MapSource, Mode, Outgoing, PackedInformation,
};
use canopy_fusion::info::{InfoError, MapInformation, MapMarginal};
use canopy_fusion::keys::{KeyMap, Merge};
use canopy_fusion::sensor::{FeatureId, ImuSample, ObservationFrame};
use canopy_fusion::slam::{
    AssociationMode, CorrespondenceConfig, FrameReport, ObservationOutcome, SlamConfig, SlamError,
    SlamFilter, VehicleSetup,
};
use canopy_fusion::topology::{NodeId, Topology};
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeSet;

/// Counters of a vehicle agent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AgentCounters {
    /// IMU samples applied.
    pub imu_samples: u64,
    /// IMU samples rejected by the estimator (non-finite, bad Δt).
    pub imu_rejected: u64,
    /// Observation frames processed.
    pub frames: u64,
    /// Frames rejected whole by the estimator.
    pub frames_rejected: u64,
    /// Observations processed.
    pub observations: u64,
    /// Observations associated to a feature.
    pub associated: u64,
    /// Observations that initialized a feature.
    pub initialized: u64,
    /// Observations rejected (gate, ambiguity, …).
    pub rejected_observations: u64,
    /// The fusion half's counters ([`VehicleFusion`]).
    pub fusion: FusionCounters,
}

/// Inputs an estimator rejected, counted by reason. The keys are generic over the filter's error
/// and reject types (new variants flow through without a change here): `imu.<error>`,
/// `frame.<error>` (a whole frame refused), `observation.<reason>` (one observation of a
/// frame not used, [`ObservationOutcome::Rejected`]) and `observation.in_rejected_frame` (the
/// observations a refused frame carried), each `<…>` the snake_case variant path of the
/// error ([`variant_key`]). Each reason is logged once, with its first cause, when first seen.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Rejections {
    /// Count per reason key.
    pub counts: std::collections::BTreeMap<String, u64>,
}

impl Rejections {
    /// Counts `n` rejections for `key`; the first one of a key is logged with its `cause`.
    pub fn add(&mut self, key: String, n: u64, cause: &dyn std::fmt::Display) {
        if n == 0 {
            return;
        }
        if !self.counts.contains_key(&key) {
            // Logged once per reason: the counts are in the outputs.
            tracing::warn!(reason = %key, cause = %cause, "estimator input rejected (first of its reason)");
        }
        let count = self.counts.entry(key).or_insert(0);
        *count += n;
    }

    /// An IMU sample refused by the filter.
    pub fn imu(&mut self, e: &SlamError) {
        self.add(format!("imu.{}", variant_key(&format!("{e:?}"))), 1, e);
    }

    /// A whole frame refused by the filter, carrying `observations` observations.
    pub fn frame(&mut self, e: &SlamError, observations: usize) {
        let cause = format!("frame: {e}");
        self.add(
            format!("frame.{}", variant_key(&format!("{e:?}"))),
            1,
            &cause,
        );
        self.add(
            "observation.in_rejected_frame".into(),
            observations as u64,
            &cause,
        );
    }

    /// The rejected observations of a processed frame.
    pub fn outcomes(&mut self, report: &FrameReport) {
        for o in &report.outcomes {
            if let ObservationOutcome::Rejected(r) = o {
                let cause = format!("observation: {r:?}");
                self.add(
                    format!("observation.{}", variant_key(&format!("{r:?}"))),
                    1,
                    &cause,
                );
            }
        }
    }

    /// Adds another set of counts.
    pub fn merge(&mut self, other: &std::collections::BTreeMap<String, u64>) {
        for (k, v) in other {
            *self.counts.entry(k.clone()).or_insert(0) += v;
        }
    }
}

/// The variant path of an enum value from its `Debug` text, in snake_case: the leading variant
/// name, then the variant of a wrapped error (`Ins(InvalidInterval(0.0))` →
/// `ins.invalid_interval`; `Observation { index: 3, source: OutsideImage { .. } }` →
/// `observation.outside_image`). Field values other than a wrapped `source`/tuple error are
/// dropped, so the key names the reason, not the instance.
pub fn variant_key(debug: &str) -> String {
    fn ident(s: &str) -> Option<(&str, &str)> {
        let s = s.trim_start();
        let end = s
            .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
            .unwrap_or(s.len());
        let id = &s[..end];
        id.starts_with(|c: char| c.is_ascii_uppercase())
            .then_some((id, &s[end..]))
    }
    fn snake(id: &str) -> String {
        let mut out = String::new();
        for (i, c) in id.chars().enumerate() {
            if c.is_ascii_uppercase() {
                if i > 0 {
                    out.push('_');
                }
                out.push(c.to_ascii_lowercase());
            } else {
                out.push(c);
            }
        }
        out
    }
    let mut parts = Vec::new();
    let mut rest = debug;
    while let Some((id, after)) = ident(rest) {
        parts.push(snake(id));
        // A wrapped error: `Variant(Inner…)` or `Variant { …, source: Inner… }`.
        let after = after.trim_start();
        rest = if let Some(inner) = after.strip_prefix('(') {
            inner
        } else if let Some(pos) = after.find("source: ") {
            &after[pos + "source: ".len()..]
        } else {
            break;
        };
    }
    if parts.is_empty() {
        "unknown".into()
    } else {
        parts.join(".")
    }
}

/// Adapter: the EKF as the DDF's fuse target.
///
/// Received deltas are batched: they are summed (information adds, aligned by id) and fused into
/// the EKF in one go before the next round reads the map information, so a round costs one
/// fusion whatever the number of neighbours. The sum is kept packed ([`PackedInformation`]:
/// half the dense matrix, and a delta's new features append block columns instead of
/// re-allocating the whole sum beside the delta being added) and unpacked once, in the
/// filter's order, when the round fuses it. The DDF validated each delta (finite, symmetric,
/// right origin) before handing it over and its channels booked it as received. A batch the
/// EKF then refuses (a non positive definite result) is kept and tried again at the next round
/// with what arrived meanwhile (information on a new feature may come in parts), at most
/// [`MAX_FUSE_ATTEMPTS`] times; meanwhile the channels read the estimate as the filter's map
/// information plus the batch ([`WithHeldBatch`]), because a delta formed without it would take
/// it back from its sender (d = Y_i − S − R, R holding the batch). After the last attempt it is
/// dropped and counted: information lost, never counted twice.
///
/// Submaps of CI links and adopted key merges wait for the round the same way, in arrival order
/// (a submap the EKF then refuses is counted in `ci_refused`; it was acknowledged on arrival).
struct EkfTarget<'a> {
    pending: &'a mut Pending,
}

/// Rounds a refused batch is tried before it is dropped ([`EkfTarget`]): the first refusal
/// and two retries with what arrives in the next two rounds.
pub const MAX_FUSE_ATTEMPTS: u32 = 3;

/// What a vehicle received since its last round.
#[derive(Debug, Default)]
struct Pending {
    /// Sum of the received deltas (packed: [`EkfTarget`]).
    sum: Option<PackedInformation>,
    count: u64,
    /// Rounds in a row the estimator refused `sum` (kept for a retry while below
    /// [`MAX_FUSE_ATTEMPTS`]).
    refused_rounds: u32,
    /// Submaps of CI links, in arrival order.
    submaps: Vec<(Submap, CiCriterion)>,
    /// Key merges adopted by the DDF node, in order.
    merges: Vec<Merge>,
    /// Appearance descriptors neighbours sent with keys new to their link.
    described: Vec<(FeatureId, canopy_fusion::sensor::Appearance)>,
}

impl FuseTarget for EkfTarget<'_> {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        let rejected = |e: InfoError| FuseRejected {
            reason: e.to_string(),
        };
        match self.pending.sum.as_mut() {
            None => {
                // Kept only once the delta is in it (an error changes nothing).
                let mut sum = PackedInformation::zero(delta.origin);
                sum.accumulate(delta, 1.0).map_err(rejected)?;
                self.pending.sum = Some(sum);
            }
            Some(sum) => sum.accumulate(delta, 1.0).map_err(rejected)?,
        }
        self.pending.count += 1;
        Ok(())
    }

    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected> {
        self.pending.submaps.push((submap.clone(), criterion));
        Ok(())
    }

    fn merge(&mut self, merge: &Merge) -> Result<(), FuseRejected> {
        self.pending.merges.push(*merge);
        Ok(())
    }

    fn describe(&mut self, features: &[(FeatureId, canopy_fusion::sensor::Appearance)]) {
        self.pending.described.extend_from_slice(features);
    }
}

/// The estimate as the channels see it while a refused batch waits for its retry
/// ([`EkfTarget`]): the filter's map information plus the batch, which the channels booked as
/// received. The filter keeps its maintained Y (a copy is handed out: rare).
struct WithHeldBatch<'a> {
    filter: &'a mut SlamFilter,
    held: &'a PackedInformation,
}

impl MapSource for WithHeldBatch<'_> {
    fn information(&mut self) -> Result<MapInformation, InfoError> {
        let y = self.filter.information()?;
        let mut with_held = y.clone();
        self.filter.restore_information(y);
        // Unpacked for the sum (a refused batch waiting for its retry: rare).
        with_held.add_assign(&self.held.to_dense())?;
        Ok(with_held)
    }

    fn feature_covariances(&self) -> Vec<(FeatureId, Matrix3<f64>)> {
        self.filter.feature_covariances()
    }

    fn marginal(&self, ids: &[FeatureId]) -> MapMarginal {
        self.filter.marginal(ids)
    }

    fn feature_means(&self, ids: &[FeatureId]) -> Vec<(FeatureId, nalgebra::Vector3<f64>)> {
        self.filter.feature_means(ids)
    }

    fn descriptors(
        &self,
        ids: &[FeatureId],
    ) -> Vec<(FeatureId, canopy_fusion::sensor::Appearance)> {
        self.filter.descriptors(ids)
    }
}

/// The filter itself as the DDF node's target, for a correspondence this vehicle adopts in
/// its round (applied at once; the error, if any, is kept for counting).
struct DirectTarget<'a> {
    filter: &'a mut SlamFilter,
    error: Option<SlamError>,
}

impl FuseTarget for DirectTarget<'_> {
    fn fuse(&mut self, delta: &MapInformation) -> Result<(), FuseRejected> {
        self.filter.fuse(delta)
    }

    fn fuse_submap(&mut self, submap: &Submap, criterion: CiCriterion) -> Result<(), FuseRejected> {
        self.filter.fuse_submap(submap, criterion)
    }

    fn merge(&mut self, merge: &Merge) -> Result<(), FuseRejected> {
        self.filter.merge_features(merge).map_err(|e| {
            let r = FuseRejected {
                reason: e.to_string(),
            };
            self.error = Some(e);
            r
        })
    }
}

/// Errors of an agent.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    /// The estimator refused an input.
    #[error(transparent)]
    Slam(#[from] SlamError),
    /// The DDF state machine refused an input.
    #[error(transparent)]
    Ddf(#[from] DdfError),
}

/// Counters of a vehicle's fusion half ([`VehicleFusion`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FusionCounters {
    /// Fusion rounds run.
    pub rounds: u64,
    /// Received deltas fused into the estimator (data sharing: other vehicles' records
    /// applied to the team filter).
    pub fused: u64,
    /// Received deltas the estimator refused (non-PD result, …).
    pub fuse_refused: u64,
    /// Received DDF messages rejected (unknown sender, invalid payload, bad time).
    pub messages_rejected: u64,
    /// Submaps fused by covariance intersection (bandwidth-limited links).
    pub ci_fused: u64,
    /// Submaps the estimator refused at the round (CI failed numerically).
    pub ci_refused: u64,
    /// Key merges the estimator could not apply.
    pub merges_refused: u64,
    /// Features removed because fused information left them with none (a neighbour's restart
    /// took back what only its lost process had observed).
    pub features_forgotten: u64,
    /// Rounds that failed (the DDF could not read the map or form its messages); nothing was
    /// sent and the channels are unchanged.
    pub rounds_failed: u64,
    /// Correspondences this vehicle found in its own map and adopted (cross-vehicle keys or
    /// its own duplicates; [`SlamFilter::find_correspondences`]).
    pub correspondences_found: u64,
}

/// The fusion half of a vehicle: its DDF node and the information received but not yet fused
/// into the EKF. It works on whichever filter it is handed: the vehicle's own
/// ([`VehicleAgent`], one thread, as in `canopy sim`) or the one the vehicle process hands to
/// its fusion thread for a round (`crate::process::vehicle`, [`VehicleEstimator::lend`]).
#[derive(Debug)]
pub struct VehicleFusion {
    ddf: Option<DdfNode>,
    /// Received information not yet fused into the EKF (see [`EkfTarget`]).
    pending: Pending,
    counters: FusionCounters,
    /// Every failure on the fusion path, by reason (`fusion.<step>.<error>`), logged once.
    rejections: Rejections,
    /// Correspondence search in the map after each fusion (appearance association only).
    correspondence: Option<CorrespondenceConfig>,
    /// Candidate correspondences already counted as rejected, by (reason, pair): each pair is
    /// counted once per reason, not once per round it is re-examined.
    candidates_rejected: BTreeSet<(&'static str, FeatureId, FeatureId)>,
    /// Correspondences adopted without a DDF node (isolated mode: own duplicates only).
    own_keys: KeyMap,
    /// Local SLAM in own frames: this vehicle's side of the team frame (`None`: one frame for
    /// the whole team, the shared launch frame or ECEF).
    team_frame: Option<crate::frames::TeamFrame>,
    /// An alignment taken whose frame change waits for the neighbour's first information
    /// (module [`crate::frames`], step 4): the frame and the team frame's owner.
    awaiting_rebase: Option<canopy_fusion::frames::Frame4>,
    /// Own frames: neighbours whose link came up again while this vehicle is in the team
    /// frame. One that restarted is in its own frame again, but this side's channel stays
    /// paired with its dead incarnation until it speaks (and it says nothing before it has
    /// aligned): it gets anchors until its information arrives.
    reanchor: BTreeSet<NodeId>,
    /// Data sharing (`[fusion] mode = "shared_data"`): the relay, and the other vehicles'
    /// records applied at each round instead of channel filters.
    sharing: Option<Box<crate::sharing::Relaying>>,
}

impl VehicleFusion {
    /// The fusion half of vehicle `id` (no DDF node in isolated mode). `epoch` must be fresh
    /// for every process start (a random u64).
    pub fn new(
        id: NodeId,
        epoch: u64,
        origin: Vector3<f64>,
        mode: Mode,
        topology: &Topology,
        ddf: DdfConfig,
        link_budgets: &[(NodeId, Option<usize>)],
    ) -> Result<Self, DdfError> {
        let ddf = match mode {
            Mode::Isolated => None,
            _ => {
                let mut node = DdfNode::for_mode(mode, id, epoch, topology, origin, ddf)?;
                for &(peer, budget) in link_budgets {
                    if budget.is_some() {
                        node.set_link_budget(peer, budget)?;
                    }
                }
                Some(node)
            }
        };
        Ok(Self {
            ddf,
            pending: Pending::default(),
            counters: FusionCounters::default(),
            rejections: Rejections::default(),
            correspondence: None,
            candidates_rejected: BTreeSet::new(),
            own_keys: KeyMap::default(),
            team_frame: None,
            awaiting_rebase: None,
            reanchor: BTreeSet::new(),
            sharing: None,
        })
    }

    /// Data sharing: `relaying` takes the messages and the rounds.
    pub fn use_sharing(&mut self, relaying: crate::sharing::Relaying) {
        self.sharing = Some(Box::new(relaying));
    }

    /// The data-sharing half, when the vehicle shares data.
    pub fn sharing(&self) -> Option<&crate::sharing::Relaying> {
        self.sharing.as_deref()
    }

    /// Data sharing: this vehicle's records into its stream (nothing otherwise).
    pub fn publish_own(&mut self, records: Vec<canopy_fusion::share::Item>) {
        if let Some(s) = self.sharing.as_mut() {
            s.publish(records, &mut self.rejections);
        }
    }

    /// Data sharing: the other vehicles' frames processed since the last call.
    pub fn take_remote_frames(&mut self) -> Vec<crate::sharing::RemoteFrame> {
        self.sharing
            .as_mut()
            .map_or_else(Vec::new, |s| s.take_remote_frames())
    }

    /// Local SLAM with every vehicle in its own frame (module [`crate::frames`]): this vehicle
    /// joins the team frame of `root` through its neighbours' anchors; `max_distance` is the
    /// descriptor distance of a candidate correspondence. Until then it takes no part in the
    /// channel filters.
    pub fn use_own_frame(&mut self, id: NodeId, root: NodeId, max_distance: Option<u32>) {
        self.team_frame = Some(crate::frames::TeamFrame::new(id, root, max_distance));
    }

    /// This vehicle's side of the team frame (own frames only).
    pub fn team_frame(&self) -> Option<&crate::frames::TeamFrame> {
        self.team_frame.as_ref()
    }

    /// Whose own frame the filter this half fuses is in (`None`: the team's shared frame):
    /// this vehicle's until the round that moves it into the team frame, the root's after.
    pub fn frame_owner(&self) -> Option<NodeId> {
        let tf = self.team_frame.as_ref()?;
        Some(if tf.in_team() && self.awaiting_rebase.is_none() {
            tf.root()
        } else {
            tf.id()
        })
    }

    /// Whether this vehicle still waits to join the team frame.
    fn outside_team(&self) -> bool {
        self.team_frame.as_ref().is_some_and(|f| !f.in_team())
    }

    /// A round outside the team frame: own duplicates merged, an attempt to align with the
    /// neighbours' anchors; on success the correspondences are adopted and the frame change is
    /// handed to the caller. Nothing is sent.
    fn round_outside_team(&mut self, filter: &mut SlamFilter, now: f64) {
        self.correspond(filter);
        let Some(tf) = self.team_frame.as_mut() else {
            return;
        };
        let Some((frame, merges)) = tf.try_align(filter, now) else {
            return;
        };
        // The correspondences are keys only: adopted now, in this frame. The estimate stays in
        // its own frame until the neighbour's information arrives (`round_awaiting_rebase`).
        let mut errors = Vec::new();
        if let Some(ddf) = self.ddf.as_mut() {
            for m in merges {
                let mut direct = DirectTarget {
                    filter,
                    error: None,
                };
                if ddf.adopt_merge(m.from, m.into, &mut direct).is_some() {
                    self.counters.correspondences_found += 1;
                }
                if let Some(e) = direct.error {
                    self.counters.merges_refused += 1;
                    errors.push(e);
                }
            }
        }
        for e in errors {
            self.reject("merge", &e, 1, &e);
        }
        self.awaiting_rebase = Some(frame);
    }

    /// A round between the alignment and the neighbour's first information (own frames): the
    /// channels pair (Sync and Hello only: no channel of this vehicle is synced yet, or it
    /// waits), nothing in this frame is sent. When the batch holds information (it is in the
    /// team frame), the filter moves into the team frame with the wide gauge prior and the
    /// batch is fused at once, with no filter step between: the gauge prior is a
    /// linearisation at the aligned estimate for one linear step only (an EKF running with
    /// 30° of yaw uncertainty gains spurious information on it). Returns `None` while waiting.
    fn round_awaiting_rebase(
        &mut self,
        filter: &mut SlamFilter,
        now: f64,
    ) -> Option<Result<Vec<Outgoing>, AgentError>> {
        let frame = self.awaiting_rebase?;
        if self.pending.sum.is_none() {
            let ddf = self.ddf.as_mut()?;
            if ddf.channels().any(|c| c.synced) {
                return Some(Ok(Vec::new()));
            }
            return Some(match ddf.on_round(now, filter) {
                Ok(out) => Ok(out.messages),
                Err(e) => {
                    self.counters.rounds_failed += 1;
                    self.reject("round", &e, 1, &e);
                    Err(e.into())
                }
            });
        }
        if let Err(e) = filter.rebase(&frame, &canopy_fusion::slam::default_gauge()) {
            // Not applied: the batch (team frame) waits; counted, tried again next round.
            self.reject("rebase", &e, 1, &e);
            return Some(Ok(Vec::new()));
        }
        self.awaiting_rebase = None;
        None
    }

    /// Anchors for the neighbours not paired yet (this vehicle in the team frame, own frames).
    fn anchors(&mut self, filter: &SlamFilter, out: &mut Vec<Outgoing>) {
        let (Some(tf), Some(ddf)) = (self.team_frame.as_ref(), self.ddf.as_mut()) else {
            return;
        };
        if !tf.in_team() {
            return;
        }
        let waiting: Vec<NodeId> = ddf
            .channels()
            .filter(|c| (!c.synced || self.reanchor.contains(&c.peer)) && c.link_up)
            .map(|c| c.peer)
            .collect();
        if waiting.is_empty() {
            return;
        }
        let body = tf.anchor(filter);
        let mut errors = Vec::new();
        for peer in waiting {
            match ddf.message_to(peer, body.clone()) {
                Ok(o) => out.push(o),
                Err(e) => errors.push(e),
            }
        }
        for e in errors {
            self.reject("anchor", &e, 1, &e);
        }
    }

    /// Searches the map for correspondences after every fusion (`Some`) or not. Set for
    /// appearance association, where keys are the vehicles' own and one physical feature
    /// can be held under several.
    pub fn set_correspondence(&mut self, cfg: Option<CorrespondenceConfig>) {
        self.correspondence = cfg;
    }

    /// The correspondence search's options (`None`: no search).
    pub fn correspondence(&self) -> Option<CorrespondenceConfig> {
        self.correspondence
    }

    /// The correspondences this vehicle adopted (its DDF node's, or in isolated mode its own).
    pub fn merges(&self) -> Vec<Merge> {
        match &self.ddf {
            Some(d) => d.keys().merges(),
            None => self.own_keys.merges(),
        }
    }

    /// Finds correspondences in `filter`'s map and adopts them: through the DDF node, which
    /// re-keys its channel filters and tells the neighbours (module `canopy_fusion::keys`),
    /// or directly in isolated mode. Rejected candidates are counted once per pair and reason
    /// (`fusion.correspondence.<reason>`).
    fn correspond(&mut self, filter: &mut SlamFilter) {
        let Some(cfg) = self.correspondence else {
            return;
        };
        let report = filter.find_correspondences(&cfg);
        for (reason, pairs) in [
            ("incompatible", &report.incompatible_pairs),
            ("ambiguous", &report.ambiguous_pairs),
            ("undetermined", &report.undetermined_pairs),
            ("joint", &report.joint_rejected_pairs),
        ] {
            for &(a, b) in pairs {
                if self.candidates_rejected.insert((reason, a, b)) {
                    self.rejections.add(
                        format!("fusion.correspondence.{reason}"),
                        1,
                        &format!("candidate correspondence {a:#x} = {b:#x} left apart ({reason})"),
                    );
                }
            }
        }
        for m in report.merges {
            let applied = match self.ddf.as_mut() {
                Some(ddf) => {
                    let mut direct = DirectTarget {
                        filter,
                        error: None,
                    };
                    let adopted = ddf.adopt_merge(m.from, m.into, &mut direct).is_some();
                    match direct.error {
                        Some(e) => Err(e),
                        None => Ok(adopted),
                    }
                }
                None => match self.own_keys.adopt(m.from, m.into) {
                    Some(eff) => filter.merge_features(&eff).map(|()| true),
                    None => Ok(false),
                },
            };
            match applied {
                Ok(true) => self.counters.correspondences_found += 1,
                Ok(false) => {}
                Err(e) => {
                    self.counters.merges_refused += 1;
                    self.reject("merge", &e, 1, &e);
                }
            }
        }
    }

    /// The failures on the fusion path, by reason: `fusion.fuse_retry.<error>` (a batch of
    /// deltas the estimator refused, kept for the next round; per refusal),
    /// `fusion.fuse.<error>` (a batch dropped after [`MAX_FUSE_ATTEMPTS`] refusals, counted
    /// per delta), `fusion.merge.<error>`, `fusion.ci.<error>`,
    /// `fusion.round.<error>`, `fusion.message.<error>` (a received message rejected) and
    /// `fusion.link_up.<error>`.
    pub fn rejections(&self) -> &Rejections {
        &self.rejections
    }

    fn reject(
        &mut self,
        step: &str,
        e: &dyn std::fmt::Debug,
        n: u64,
        cause: &dyn std::fmt::Display,
    ) {
        let key = format!("fusion.{step}.{}", variant_key(&format!("{e:?}")));
        self.rejections.add(key, n, cause);
    }

    /// The DDF node (None in isolated mode).
    pub fn ddf(&self) -> Option<&DdfNode> {
        self.ddf.as_ref()
    }

    /// Counters.
    pub fn counters(&self) -> FusionCounters {
        match &self.sharing {
            Some(s) => FusionCounters {
                fused: s.counters().applied,
                ..self.counters
            },
            None => self.counters,
        }
    }

    /// Fuses the received information batched since the last call into `filter`.
    pub fn flush(&mut self, filter: &mut SlamFilter) {
        // Descriptors first: they are of keys the batch may bring.
        let described = std::mem::take(&mut self.pending.described);
        if !described.is_empty() {
            FuseTarget::describe(filter, &described);
        }
        if let Some(mut packed) = self.pending.sum.take() {
            // A batch kept from an earlier round may name features merged since.
            if self.pending.refused_rounds > 0
                && let Some(ddf) = self.ddf.as_ref()
            {
                packed.rekey(ddf.keys());
            }
            // Room for its new features first (a re-allocation of P or Y then copies beside
            // the packed batch, not the dense one), then unpacked once, straight into the
            // filter's order (one dense k × k, not the dense sum and its permuted copy).
            filter.reserve_for_information(packed.ids());
            let sum = filter.dense_in_filter_order(&packed);
            drop(packed);
            // The packed batch's block columns are heap chunks below the mmap threshold: freed,
            // they stay resident until trimmed, which would otherwise wait for the round's end,
            // past the fusion's k × k temporaries.
            canopy_fusion::runtime::trim_heap(canopy_fusion::runtime::heap_slack(
                filter.num_features(),
            ));
            // Features whose information the batch cancels exactly (a resynchronisation after a
            // neighbour restarted) are removed, not refused
            // (`SlamFilter::fuse_map_information_forgetting`).
            // By value: the batch is fused in its own buffer (k × k less at the round's peak).
            match filter.fuse_map_information_forgetting_owned(sum) {
                Ok(r) => {
                    self.counters.fused += std::mem::take(&mut self.pending.count);
                    self.counters.features_forgotten += r.forgotten.len() as u64;
                    self.pending.refused_rounds = 0;
                }
                Err(refused) => {
                    let (e, back) = *refused;
                    self.pending.refused_rounds += 1;
                    // Packed again for the retry; `from_dense` fails only on a shape the filter's
                    // own unpacked batch cannot have (then dropped like a last attempt).
                    let kept = back
                        .filter(|_| self.pending.refused_rounds < MAX_FUSE_ATTEMPTS)
                        .map(|batch| PackedInformation::from_dense(&batch));
                    match kept {
                        Some(Ok(batch)) => {
                            let cause = format!(
                                "{e}; kept for attempt {} of {MAX_FUSE_ATTEMPTS} with what \
                                 arrives meanwhile",
                                self.pending.refused_rounds + 1
                            );
                            self.reject("fuse_retry", &e, 1, &cause);
                            self.pending.sum = Some(batch);
                        }
                        _ => {
                            let n = std::mem::take(&mut self.pending.count);
                            self.counters.fuse_refused += n;
                            self.pending.refused_rounds = 0;
                            let cause = match kept {
                                Some(Err(pack)) => format!(
                                    "{e}; {n} deltas dropped: the batch could not be kept for \
                                     a retry ({pack})"
                                ),
                                _ => format!(
                                    "{e}; {n} deltas dropped after {MAX_FUSE_ATTEMPTS} \
                                     attempts (their information is lost to this vehicle)"
                                ),
                            };
                            self.reject("fuse", &e, n, &cause);
                        }
                    }
                }
            }
        }
        for m in std::mem::take(&mut self.pending.merges) {
            // A neighbour's correspondence this estimate contradicts (both features held, their
            // difference outside the wide gate) is kept apart in the estimate: the DDF node's
            // bookkeeping is merged anyway, which stays exact (module `canopy_fusion::keys`).
            if let Some(cfg) = self.correspondence
                && filter.merge_contradicted(&m, cfg.ambiguity_probability)
            {
                self.counters.merges_refused += 1;
                self.rejections.add(
                    "fusion.merge.contradicted".into(),
                    1,
                    &format!(
                        "neighbour's correspondence {:#x} = {:#x} contradicts this estimate",
                        m.from, m.into
                    ),
                );
                continue;
            }
            if let Err(e) = filter.merge_features(&m) {
                self.counters.merges_refused += 1;
                self.reject("merge", &e, 1, &e);
            }
        }
        for (submap, criterion) in std::mem::take(&mut self.pending.submaps) {
            match filter.fuse_submap_ci(&submap, criterion) {
                Ok(_) => self.counters.ci_fused += 1,
                Err(e) => {
                    self.counters.ci_refused += 1;
                    self.reject("ci", &e, 1, &e);
                }
            }
        }
    }

    /// Makes the link to `peer` covariance intersection from the start (a capacity-limited
    /// link: see [`crate::radio`]).
    pub fn use_ci(&mut self, peer: NodeId) -> Result<(), AgentError> {
        if let Some(d) = self.ddf.as_mut() {
            d.use_ci(peer)?;
        }
        Ok(())
    }

    /// Makes the link to `peer` a sparsified channel filter (a capacity-limited link: exact
    /// deltas while they fit, their conservative marginal on the features that fit otherwise;
    /// [`canopy_fusion::sparse`]).
    pub fn use_sparse(&mut self, peer: NodeId) -> Result<(), AgentError> {
        if let Some(d) = self.ddf.as_mut() {
            d.use_sparse(peer)?;
        }
        Ok(())
    }

    /// Sets the submap byte budgets of the next round, per link (capacity-limited links: the
    /// driver derives them from each link's capacity and outbound queue, [`crate::radio`]).
    pub fn set_link_budgets(&mut self, budgets: &[(NodeId, usize)]) -> Result<(), AgentError> {
        if let Some(s) = self.sharing.as_mut() {
            s.set_link_budgets(budgets);
            return Ok(());
        }
        if let Some(d) = self.ddf.as_mut() {
            for &(peer, b) in budgets {
                if let Err(e) = d.set_link_budget(peer, Some(b)) {
                    self.reject("budget", &e, 1, &format!("peer {peer:?}: {e}"));
                    return Err(e.into());
                }
            }
        }
        Ok(())
    }

    /// A fusion round at time `now` on `filter`: the batch fused in, the map information read
    /// (eqs. 21.86, 21.87), the DDF's deltas formed, a CI change fused. The messages to send.
    pub fn round(
        &mut self,
        filter: &mut SlamFilter,
        now: f64,
    ) -> Result<Vec<Outgoing>, AgentError> {
        let mut out = Vec::new();
        self.round_each(filter, now, &mut |o| out.push(o))?;
        Ok(out)
    }

    /// [`VehicleFusion::round`], handing each message to `emit` as soon as it is formed
    /// ([`DdfNode::on_round_each`]: a caller that encodes each one there holds one dense delta
    /// at a time, not one per neighbour). On an error (counted and logged here) the messages
    /// already emitted are booked in their channels and are to be sent.
    pub fn round_each(
        &mut self,
        filter: &mut SlamFilter,
        now: f64,
        emit: &mut dyn FnMut(Outgoing),
    ) -> Result<(), AgentError> {
        if let Some(s) = self.sharing.as_mut() {
            self.counters.rounds += 1;
            s.round(filter, now, &mut self.rejections, emit);
            return Ok(());
        }
        if self.ddf.is_none() {
            // Isolated: no neighbours, but the vehicle's own duplicates are still merged.
            self.correspond(filter);
            return Ok(());
        }
        self.counters.rounds += 1;
        if self.outside_team() {
            self.round_outside_team(filter, now);
            return Ok(());
        }
        if let Some(waiting) = self.round_awaiting_rebase(filter, now) {
            return waiting.map(|out| out.into_iter().for_each(&mut *emit));
        }
        self.flush(filter);
        self.correspond(filter);
        if self.correspondence.is_some() {
            let missing = filter.undescribed_features();
            if !missing.is_empty()
                && let Some(ddf) = self.ddf.as_mut()
            {
                ddf.request_descriptors(&missing);
            }
        }
        // The DDF reads Y only if an exact link sends a delta, and covariance blocks for CI
        // links; with a refused batch kept for a retry, Y plus that batch.
        let ddf = self.ddf.as_mut().expect("checked above");
        let out = match self.pending.sum.as_ref() {
            Some(held) if self.pending.refused_rounds > 0 => {
                ddf.on_round_each(now, &mut WithHeldBatch { filter, held }, emit)
            }
            _ => ddf.on_round_each(now, filter, emit),
        };
        if let Err(e) = out {
            self.counters.rounds_failed += 1;
            self.reject("round", &e, 1, &e);
            return Err(e.into());
        }
        let mut anchors = Vec::new();
        self.anchors(filter, &mut anchors);
        anchors.into_iter().for_each(emit);
        Ok(())
    }

    /// A DDF message from `from`: what it carries joins the batch; returns replies. An error
    /// means the message was rejected and counted; nothing changed.
    pub fn on_message(
        &mut self,
        now: f64,
        from: NodeId,
        msg: DdfMessage,
    ) -> Result<Vec<Outgoing>, AgentError> {
        if let Some(s) = self.sharing.as_mut() {
            s.on_message(now, from, msg, &mut self.rejections);
            return Ok(Vec::new());
        }
        let outside = self.outside_team();
        if !outside && matches!(msg.body, Body::Delta { .. } | Body::Cumulative { .. }) {
            // Information from it: it is in the team frame.
            self.reanchor.remove(&from);
        }
        let Some(ddf) = self.ddf.as_mut() else {
            let e = DdfError::UnknownSender(from);
            self.counters.messages_rejected += 1;
            self.reject("message", &e, 1, &e);
            return Err(AgentError::Ddf(e));
        };
        if outside || matches!(msg.body, Body::Anchor { .. }) {
            let validated = ddf.validate(from, &msg);
            return self.on_message_outside_team(from, msg, validated);
        }
        let mut target = EkfTarget {
            pending: &mut self.pending,
        };
        let r = ddf.on_message(now, from, msg, &mut target);
        r.map_err(|e| {
            if !matches!(e, DdfError::FuseRejected { .. }) {
                self.counters.messages_rejected += 1;
            }
            self.reject("message", &e, 1, &format!("from {from:?}: {e}"));
            AgentError::Ddf(e)
        })
    }

    /// An anchor (kept while this vehicle is outside the team frame), or any other message
    /// while it is outside (dropped and counted: it takes no part in the channel filters yet);
    /// `validated` is the DDF node's verdict on the message.
    fn on_message_outside_team(
        &mut self,
        from: NodeId,
        msg: DdfMessage,
        validated: Result<(), DdfError>,
    ) -> Result<Vec<Outgoing>, AgentError> {
        if let Err(e) = validated {
            self.counters.messages_rejected += 1;
            self.reject("message", &e, 1, &format!("from {from:?}: {e}"));
            return Err(AgentError::Ddf(e));
        }
        match (msg.body, self.team_frame.as_mut()) {
            (Body::Anchor { features }, Some(tf)) => tf.on_anchor(from, features),
            (Body::Anchor { .. }, None) => {
                self.rejections.add(
                    "fusion.message.anchor_without_own_frames".into(),
                    1,
                    &format!("from {from:?}: anchors are for local SLAM in own frames"),
                );
            }
            (body, _) => {
                let kind = DdfMessage {
                    header: msg.header,
                    body,
                }
                .kind();
                self.rejections.add(
                    "fusion.message.outside_team_frame".into(),
                    1,
                    &format!(
                        "{kind} from {from:?} dropped: this vehicle has not aligned its own \
                         frame with the team's yet"
                    ),
                );
            }
        }
        Ok(Vec::new())
    }

    /// The link to `peer` came up.
    pub fn on_link_up(&mut self, now: f64, peer: NodeId) -> Result<Vec<Outgoing>, AgentError> {
        if let Some(s) = self.sharing.as_mut() {
            s.on_link_up(now, peer);
            return Ok(Vec::new());
        }
        // Outside the team frame the channel learns the link state but sends nothing yet.
        let outside = self.outside_team();
        if self.team_frame.is_some() && !outside {
            self.reanchor.insert(peer);
        }
        match self.ddf.as_mut().map(|d| d.on_link_up(now, peer)) {
            Some(Ok(out)) => Ok(if outside { Vec::new() } else { out }),
            Some(Err(e)) => {
                self.reject("link_up", &e, 1, &format!("peer {peer:?}: {e}"));
                Err(e.into())
            }
            None => Ok(Vec::new()),
        }
    }

    /// The link to `peer` went down.
    pub fn on_link_down(&mut self, peer: NodeId) -> Result<(), AgentError> {
        if let Some(s) = self.sharing.as_mut() {
            s.on_link_down(peer);
            return Ok(());
        }
        match self.ddf.as_mut().map(|d| d.on_link_down(peer)) {
            Some(Err(e)) => {
                self.reject("link_down", &e, 1, &format!("peer {peer:?}: {e}"));
                Err(e.into())
            }
            Some(Ok(())) | None => Ok(()),
        }
    }
}

/// The estimator half of a vehicle: its M = 1 filter and what it counted.
#[derive(Debug)]
pub struct VehicleEstimator {
    /// The filter; while it is lent out ([`VehicleEstimator::lend`]), its vehicle part.
    filter: SlamFilter,
    counters: AgentCounters,
    rejections: Rejections,
    /// While the filter is lent out: what is replayed on it when it comes back.
    lent: Option<Lent>,
    /// Zero-velocity updates over a known rest period.
    rest: Option<RestUpdates>,
    /// Whose own frame the estimate is in (local SLAM in own frames; `None`: the frame shared
    /// by the team, the launch frame or ECEF).
    frame_owner: Option<NodeId>,
    /// Data sharing: the filter is the team's and this vehicle publishes its records
    /// ([`crate::sharing::OwnRecords`]).
    own: Option<crate::sharing::OwnRecords>,
}

/// A filter lent out for a fusion round ([`VehicleEstimator::lend`]).
#[derive(Debug)]
struct Lent {
    /// The IMU samples applied (to the vehicle part) since: applied again to the fused filter.
    samples: Vec<ImuSample>,
    /// The map as it was lent (prediction does not change it), for map reports meanwhile.
    map: Vec<MapFeature>,
}

/// One map feature of an estimate: id, mean and 3 × 3 covariance.
pub type MapFeature = (FeatureId, Vector3<f64>, Matrix3<f64>);

/// Zero-velocity updates while the vehicle is known to rest
/// ([`crate::replay::ZeroVelocityConfig`]).
#[derive(Clone, Copy, Debug)]
struct RestUpdates {
    config: crate::replay::ZeroVelocityConfig,
    /// Time of the next update.
    next: f64,
    /// Updates applied so far.
    applied: u64,
}

impl VehicleEstimator {
    /// An estimator with an empty map.
    pub fn new(slam: SlamConfig, setup: VehicleSetup) -> Result<Self, SlamError> {
        Ok(Self {
            filter: SlamFilter::new(slam, &[setup])?,
            counters: AgentCounters::default(),
            rejections: Rejections::default(),
            lent: None,
            rest: None,
            frame_owner: None,
            own: None,
        })
    }

    /// Data sharing: `filter` (the team's, over every vehicle) replaces the vehicle's own, and
    /// the records it takes are published through `own`.
    pub fn use_sharing(&mut self, filter: SlamFilter, own: crate::sharing::OwnRecords) {
        self.filter = filter;
        self.own = Some(own);
    }

    /// This vehicle's index in its filter (0, or its place in the team filter).
    pub fn vehicle_index(&self) -> usize {
        self.own.as_ref().map_or(0, |o| o.index())
    }

    /// Data sharing: the records this vehicle published since the last call (empty otherwise).
    pub fn take_records(&mut self) -> Vec<canopy_fusion::share::Item> {
        self.own.as_mut().map_or_else(Vec::new, |o| o.take())
    }

    /// Applies zero-velocity updates from the first IMU sample on until `z.until_s`.
    pub fn set_zero_velocity(&mut self, z: crate::replay::ZeroVelocityConfig) {
        self.rest = Some(RestUpdates {
            config: z,
            next: f64::NEG_INFINITY,
            applied: 0,
        });
    }

    /// A zero-velocity update at the frame at `t`, when one is due within the rest period.
    /// Updates go with frames, which only come while no copy is lent out (a frame in between
    /// makes the give back fail safe, as for the frame's own update), so that `canopy sim` and
    /// `canopy run` apply the same ones.
    fn rest_update(&mut self, t: f64) {
        let Some(r) = &mut self.rest else {
            return;
        };
        if t > r.config.until_s {
            tracing::info!(
                applied = r.applied,
                until_s = r.config.until_s,
                "rest period over: zero-velocity updates applied"
            );
            self.rest = None;
            return;
        }
        if t < r.next {
            return;
        }
        let index = self.own.as_ref().map_or(0, |o| o.index());
        match self.filter.zero_velocity_update(index, r.config.sigma_mps) {
            Ok(_nis) => r.applied += 1,
            Err(e) => self.rejections.add(
                format!("zero_velocity.{}", variant_key(&format!("{e:?}"))),
                1,
                &e,
            ),
        }
        r.next = t + 1.0 / r.config.rate_hz;
    }

    /// The filter.
    pub fn filter(&self) -> &SlamFilter {
        &self.filter
    }

    /// The filter, to fuse into.
    pub fn filter_mut(&mut self) -> &mut SlamFilter {
        &mut self.filter
    }

    /// Counters of the estimator's own inputs (the fusion fields are left at zero).
    pub fn counters(&self) -> AgentCounters {
        self.counters
    }

    /// The inputs it rejected, by reason.
    pub fn rejections(&self) -> &Rejections {
        &self.rejections
    }

    /// One IMU sample (eqs. 21.46/21.47). A rejected sample leaves the estimate unchanged.
    pub fn on_imu(&mut self, imu: &ImuSample) -> Result<(), SlamError> {
        match self.filter.predict(self.vehicle_index(), imu) {
            Ok(()) => {
                self.counters.imu_samples += 1;
                if let Some(o) = self.own.as_mut() {
                    o.on_imu(imu);
                }
                if let Some(l) = self.lent.as_mut() {
                    l.samples.push(*imu);
                }
                Ok(())
            }
            Err(e) => {
                self.counters.imu_rejected += 1;
                self.rejections.imu(&e);
                Err(e)
            }
        }
    }

    /// Hands the filter over for fusion work elsewhere (the vehicle process's fusion thread)
    /// instead of copying it (a copy of P per round was the largest transient of a vehicle's
    /// memory and an O(n²) stall of this thread). Until [`give_back`](Self::give_back) the
    /// estimator keeps the vehicle part ([`SlamFilter::vehicle_only`]): IMU samples go on
    /// (reports read the vehicle's estimate from it, [`map`](Self::map) the map as lent) and
    /// are applied again to the fused filter when it comes back; frames must wait (they are
    /// refused meanwhile). An error if the filter is already out.
    pub fn lend(&mut self) -> Result<SlamFilter, SlamError> {
        if self.lent.is_some() {
            return Err(SlamError::InvalidConfig(
                "the filter is already lent out".into(),
            ));
        }
        let map = map_of(&self.filter);
        let part = self.filter.vehicle_only();
        self.lent = Some(Lent {
            samples: Vec::new(),
            map,
        });
        Ok(std::mem::replace(&mut self.filter, part))
    }

    /// Whether the filter is out ([`lend`](Self::lend)).
    pub fn is_lent(&self) -> bool {
        self.lent.is_some()
    }

    /// Whose own frame the estimate is in (`None`: the team's shared frame).
    pub fn frame_owner(&self) -> Option<NodeId> {
        self.frame_owner
    }

    /// Starts in vehicle `owner`'s own frame (local SLAM in own frames: its own id).
    pub fn set_frame_owner(&mut self, owner: Option<NodeId>) {
        self.frame_owner = owner;
    }

    /// Takes the fused filter back and applies to it the IMU samples predicted since it was
    /// lent: the estimate one thread fusing at the round time and predicting afterwards would
    /// have (the predictions are O(1) each, `canopy_fusion::slam` module docs). A sample the
    /// fused filter refuses (a state-dependent failure; the vehicle part took it) is counted
    /// under `fusion.give_back.<error>` and skipped. An error, with the filter unchanged, if
    /// nothing was lent.
    pub fn give_back(&mut self, mut fused: SlamFilter) -> Result<(), SlamError> {
        let Some(lent) = self.lent.take() else {
            let e = SlamError::InvalidConfig("give_back without a lent filter".into());
            self.rejections.add(
                format!("fusion.give_back.{}", variant_key(&format!("{e:?}"))),
                1,
                &e,
            );
            return Err(e);
        };
        let index = self.vehicle_index();
        for imu in &lent.samples {
            if let Err(e) = fused.predict(index, imu) {
                self.rejections.add(
                    format!("fusion.give_back.{}", variant_key(&format!("{e:?}"))),
                    1,
                    &e,
                );
            }
        }
        self.filter = fused;
        Ok(())
    }

    /// Every map feature with its mean and 3 × 3 covariance: the filter's, or while it is lent
    /// out the map as it was lent (prediction does not change the map).
    pub fn map(&self) -> std::borrow::Cow<'_, [MapFeature]> {
        match &self.lent {
            Some(l) => std::borrow::Cow::Borrowed(&l.map),
            None => std::borrow::Cow::Owned(map_of(&self.filter)),
        }
    }

    /// Number of map features (of the map as lent while the filter is out).
    pub fn num_features(&self) -> usize {
        match &self.lent {
            Some(l) => l.map.len(),
            None => self.filter.num_features(),
        }
    }

    /// One terrain-sensor frame (association, update, initialization). Refused while the
    /// filter is lent out (the frame would change a map that is being fused elsewhere).
    pub fn on_frame(&mut self, frame: &ObservationFrame) -> Result<FrameReport, SlamError> {
        if self.lent.is_some() {
            let e = SlamError::InvalidConfig("a frame while the filter is lent out".into());
            self.counters.frames_rejected += 1;
            self.rejections.frame(&e, frame.observations.len());
            return Err(e);
        }
        self.rest_update(frame.time);
        let index = self.vehicle_index();
        let shared;
        let frame = match self.own.as_mut() {
            Some(o) => {
                shared = o.on_frame(frame);
                &shared
            }
            None => frame,
        };
        match self.filter.process_frame(index, frame) {
            Ok(report) => {
                self.counters.frames += 1;
                self.counters.observations += report.outcomes.len() as u64;
                self.counters.associated += report.associated() as u64;
                self.counters.initialized += report.initialized() as u64;
                self.counters.rejected_observations += report.rejected() as u64;
                self.rejections.outcomes(&report);
                Ok(report)
            }
            Err(e) => {
                self.counters.frames_rejected += 1;
                self.rejections.frame(&e, frame.observations.len());
                Err(e)
            }
        }
    }
}

/// Every map feature of `f` with its mean and 3 × 3 covariance, in map order.
fn map_of(f: &SlamFilter) -> Vec<MapFeature> {
    f.features()
        .into_iter()
        .filter_map(|(id, m)| f.feature_covariance(id).map(|c| (id, m, c)))
        .collect()
}

/// One vehicle in one thread: the estimator and the fusion half side by side (`canopy sim`).
#[derive(Debug)]
pub struct VehicleAgent {
    id: NodeId,
    estimator: VehicleEstimator,
    fusion: VehicleFusion,
}

impl VehicleAgent {
    /// A vehicle agent. `epoch` must be fresh for every process start (a random u64).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        id: NodeId,
        epoch: u64,
        slam: SlamConfig,
        setup: VehicleSetup,
        mode: Mode,
        topology: &Topology,
        ddf: DdfConfig,
        link_budgets: &[(NodeId, Option<usize>)],
    ) -> Result<Self, AgentError> {
        let estimator = VehicleEstimator::new(slam, setup)?;
        let mut fusion =
            VehicleFusion::new(id, epoch, slam.origin, mode, topology, ddf, link_budgets)?;
        if let AssociationMode::Appearance { max_distance, .. } = slam.association.mode {
            fusion.set_correspondence(Some(CorrespondenceConfig {
                max_distance,
                ..CorrespondenceConfig::default()
            }));
        }
        Ok(Self {
            id,
            estimator,
            fusion,
        })
    }

    /// Switches the agent to data sharing ([`crate::sharing::build`]): the estimator runs the
    /// team filter and publishes its own records, the fusion half relays them and applies the
    /// other vehicles' records at each round.
    pub fn use_sharing(
        &mut self,
        filter: SlamFilter,
        own: crate::sharing::OwnRecords,
        relaying: crate::sharing::Relaying,
    ) {
        self.estimator.use_sharing(filter, own);
        self.fusion.use_sharing(relaying);
    }

    /// Whether the agent shares data.
    pub fn is_sharing(&self) -> bool {
        self.fusion.sharing().is_some()
    }

    /// The data-sharing relay half (data sharing only).
    pub fn sharing(&self) -> Option<&crate::sharing::Relaying> {
        self.fusion.sharing()
    }

    /// This vehicle's index in [`filter`](Self::filter) (0, or its place in the team filter
    /// of data sharing).
    pub fn vehicle_index(&self) -> usize {
        self.estimator.vehicle_index()
    }

    /// The other vehicles' frames the team filter processed since the last call (data
    /// sharing; empty otherwise).
    pub fn take_remote_frames(&mut self) -> Vec<crate::sharing::RemoteFrame> {
        self.fusion.take_remote_frames()
    }

    /// Bearing-only initialization options and zero-velocity updates of the vehicle's
    /// configuration (`[vehicle.bearing]`, `[vehicle.replay] zero_velocity`).
    pub fn configure(
        &mut self,
        bearing: canopy_fusion::slam::BearingConfig,
        zero_velocity: Option<crate::replay::ZeroVelocityConfig>,
    ) -> Result<(), AgentError> {
        self.estimator.filter.set_bearing_config(bearing)?;
        if let Some(z) = zero_velocity {
            self.estimator.set_zero_velocity(z);
        }
        Ok(())
    }

    /// Splits the agent into its estimator and fusion halves (the vehicle process runs them on
    /// two threads).
    pub fn into_parts(self) -> (VehicleEstimator, VehicleFusion) {
        (self.estimator, self.fusion)
    }

    /// Fuses the received information batched since the last call into the EKF (done at the
    /// start of every round; call it before reading a final map).
    pub fn flush_fusion(&mut self) {
        self.fusion.flush(self.estimator.filter_mut());
    }

    /// Searches the map for correspondences after every fusion (`Some`, the default under
    /// appearance association) or not ([`VehicleFusion::set_correspondence`]).
    pub fn set_correspondence(&mut self, cfg: Option<CorrespondenceConfig>) {
        self.fusion.set_correspondence(cfg);
    }

    /// The correspondence search's options ([`VehicleFusion::correspondence`]).
    pub fn correspondence(&self) -> Option<CorrespondenceConfig> {
        self.fusion.correspondence()
    }

    /// The correspondences this vehicle adopted ([`VehicleFusion::merges`]).
    pub fn merges(&self) -> Vec<Merge> {
        self.fusion.merges()
    }

    /// This node's id.
    pub fn id(&self) -> NodeId {
        self.id
    }

    /// The estimator.
    pub fn filter(&self) -> &SlamFilter {
        self.estimator.filter()
    }

    /// The DDF node (None in isolated mode and with data sharing).
    pub fn ddf(&self) -> Option<&DdfNode> {
        self.fusion.ddf()
    }

    /// The inputs its estimator rejected and the failures of its fusion half, by reason.
    pub fn rejections(&self) -> Rejections {
        let mut r = self.estimator.rejections().clone();
        r.merge(&self.fusion.rejections().counts);
        r
    }

    /// Counters of both halves.
    pub fn counters(&self) -> AgentCounters {
        self.estimator
            .counters()
            .with_fusion(self.fusion.counters())
    }

    /// One IMU sample (eqs. 21.46/21.47). A rejected sample leaves the estimate unchanged.
    pub fn on_imu(&mut self, imu: &ImuSample) -> Result<(), SlamError> {
        self.estimator.on_imu(imu)
    }

    /// One terrain-sensor frame (association, update, initialization).
    pub fn on_frame(&mut self, frame: &ObservationFrame) -> Result<FrameReport, SlamError> {
        self.estimator.on_frame(frame)
    }

    /// Makes the link to `peer` covariance intersection from the start.
    pub fn use_ci(&mut self, peer: NodeId) -> Result<(), AgentError> {
        self.fusion.use_ci(peer)
    }

    /// Makes the link to `peer` a sparsified channel filter from the start.
    pub fn use_sparse(&mut self, peer: NodeId) -> Result<(), AgentError> {
        self.fusion.use_sparse(peer)
    }

    /// Sets the byte budgets (delta or submap) of the next round, per link.
    pub fn set_link_budgets(&mut self, budgets: &[(NodeId, usize)]) -> Result<(), AgentError> {
        self.fusion.set_link_budgets(budgets)
    }

    /// A fusion round at time `now`: the messages to send.
    pub fn on_round(&mut self, now: f64) -> Result<Vec<Outgoing>, AgentError> {
        // Data sharing: this vehicle's records since the last round go into its stream.
        self.fusion.publish_own(self.estimator.take_records());
        let out = self.fusion.round(self.estimator.filter_mut(), now);
        // The round may have moved the filter into the team frame (own frames).
        self.estimator.set_frame_owner(self.fusion.frame_owner());
        out
    }

    /// Local SLAM in own frames: starts in this vehicle's own frame and joins the team frame
    /// of `root` ([`VehicleFusion::use_own_frame`]).
    pub fn use_own_frame(&mut self, root: NodeId, max_distance: Option<u32>) {
        self.estimator.set_frame_owner(Some(self.id));
        self.fusion.use_own_frame(self.id, root, max_distance);
    }

    /// Whose own frame the estimate is in (`None`: the team's shared frame).
    pub fn frame_owner(&self) -> Option<NodeId> {
        self.estimator.frame_owner()
    }

    /// The team frame state (own frames only).
    pub fn team_frame(&self) -> Option<&crate::frames::TeamFrame> {
        self.fusion.team_frame()
    }

    /// A DDF message from `from`: fuses what it carries, returns replies. An error means the
    /// message was rejected and counted; the estimate is unchanged.
    pub fn on_message(
        &mut self,
        now: f64,
        from: NodeId,
        msg: DdfMessage,
    ) -> Result<Vec<Outgoing>, AgentError> {
        self.fusion.on_message(now, from, msg)
    }

    /// The link to `peer` came up.
    pub fn on_link_up(&mut self, now: f64, peer: NodeId) -> Result<Vec<Outgoing>, AgentError> {
        self.fusion.on_link_up(now, peer)
    }

    /// The link to `peer` went down.
    pub fn on_link_down(&mut self, peer: NodeId) -> Result<(), AgentError> {
        self.fusion.on_link_down(peer)
    }
}

impl AgentCounters {
    /// These estimator counters with the fusion half's.
    pub fn with_fusion(self, fusion: FusionCounters) -> Self {
        Self { fusion, ..self }
    }
}

/// The hub of central mode: no observations; its estimate is the sum of what it received
/// (the independent opinion pool, eqs. 21.88–21.91), fed back through channel filters.
#[derive(Debug)]
pub struct HubAgent {
    store: InformationStore,
    ddf: DdfNode,
    rejected: u64,
    /// Every failure on the hub's fusion path, by reason (`fusion.<step>.<error>` as in
    /// [`VehicleFusion::rejections`]), logged once.
    rejections: Rejections,
}

impl HubAgent {
    /// A hub with node id `id` in the star `topology`.
    pub fn new(
        id: NodeId,
        epoch: u64,
        origin: Vector3<f64>,
        topology: &Topology,
        ddf: DdfConfig,
    ) -> Result<Self, DdfError> {
        let node = DdfNode::for_mode(Mode::Central { hub: id }, id, epoch, topology, origin, ddf)?;
        Ok(Self {
            store: InformationStore::new(origin),
            ddf: node,
            rejected: 0,
            rejections: Rejections::default(),
        })
    }

    /// The hub's map information.
    pub fn store(&self) -> &MapInformation {
        &self.store.info
    }

    /// The DDF node.
    pub fn ddf(&self) -> &DdfNode {
        &self.ddf
    }

    /// Rejected messages.
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// The failures on the hub's fusion path, by reason: `fusion.message.<error>` (a received
    /// message rejected or refused), `fusion.round.<error>`, `fusion.link_up.<error>`,
    /// `fusion.link_down.<error>`.
    pub fn rejections(&self) -> &Rejections {
        &self.rejections
    }

    fn reject<T>(&mut self, step: &str, r: Result<T, DdfError>) -> Result<T, DdfError> {
        if let Err(e) = &r {
            let key = format!("fusion.{step}.{}", variant_key(&format!("{e:?}")));
            self.rejections.add(key, 1, e);
        }
        r
    }

    /// A fusion round (keys the hub holds without a descriptor are asked for again: it passes
    /// descriptors on between the vehicles).
    pub fn on_round(&mut self, now: f64) -> Result<Vec<Outgoing>, DdfError> {
        let missing = self.store.undescribed();
        if !missing.is_empty() {
            self.ddf.request_descriptors(&missing);
        }
        let r = self.ddf.on_round(now, &mut self.store).map(|o| o.messages);
        self.reject("round", r)
    }

    /// A DDF message.
    pub fn on_message(
        &mut self,
        now: f64,
        from: NodeId,
        msg: DdfMessage,
    ) -> Result<Vec<Outgoing>, DdfError> {
        let r = self
            .ddf
            .on_message(now, from, msg, &mut self.store)
            .inspect_err(|_| self.rejected += 1);
        self.reject("message", r)
    }

    /// Link events.
    pub fn on_link_up(&mut self, now: f64, peer: NodeId) -> Result<Vec<Outgoing>, DdfError> {
        let r = self.ddf.on_link_up(now, peer);
        self.reject("link_up", r)
    }

    /// Link events.
    pub fn on_link_down(&mut self, peer: NodeId) -> Result<(), DdfError> {
        let r = self.ddf.on_link_down(peer);
        self.reject("link_down", r)
    }
}

/// A minimal Hello from epoch `from_epoch` of its sender (nothing sent, nothing applied, no
/// history): test input wherever a well-formed DDF message of any kind will do.
#[cfg(test)]
pub(crate) fn test_hello(from_epoch: u64) -> DdfMessage {
    use canopy_fusion::ddf::{Header, Hello};
    DdfMessage {
        header: Header {
            from_epoch,
            to_epoch: None,
            challenge: 1,
            echo_epoch: 0,
            echo: 0,
        },
        body: Body::Hello(Hello {
            seq_sent: 0,
            applied: 0,
            history: false,
            synced: false,
            ci: false,
        }),
    }
}

#[cfg(test)]
mod rejection_tests {
    use super::*;
    use canopy_fusion::ins::InsError;
    use canopy_fusion::observation::ObservationError;
    use canopy_fusion::slam::RejectReason;

    /// A message from a node that is not a neighbour is rejected, counted under its reason
    /// (`fusion.message.<error>`) in the fusion half's rejections, and reaches the agent's
    /// combined table; a second one adds to the same key.
    #[test]
    fn fusion_failures_are_counted_by_reason() {
        let topo = Topology::tree([NodeId(1), NodeId(2)], [(NodeId(1), NodeId(2))]).unwrap();
        let mut f = VehicleFusion::new(
            NodeId(1),
            7,
            Vector3::zeros(),
            Mode::Decentralized,
            &topo,
            DdfConfig::default(),
            &[],
        )
        .unwrap();
        for _ in 0..2 {
            assert!(f.on_message(0.0, NodeId(9), test_hello(3)).is_err());
        }
        let counts = &f.rejections().counts;
        assert_eq!(counts.len(), 1, "{counts:?}");
        let (key, n) = counts.iter().next().unwrap();
        assert!(key.starts_with("fusion.message."), "{key}");
        assert_eq!(*n, 2);
        assert_eq!(f.counters().messages_rejected, 2);
    }

    /// The vehicle process's hand-over (`VehicleEstimator::lend`/`give_back`): the filter
    /// handed over and fused elsewhere comes back with the IMU samples of the meantime applied
    /// again, bit for bit what one thread fusing at the round time and predicting afterwards
    /// computes (`canopy sim`); meanwhile the estimate is the vehicle part's, reports read the
    /// map as lent, frames and a second lend are refused (counted), and a give-back with
    /// nothing out is an error that changes nothing.
    #[test]
    fn a_lent_filter_comes_back_with_the_predictions_of_the_meantime() {
        let s = crate::scenario::Scenario::builtin_default();
        let (world, mut sources) = crate::replay::SensorSource::for_scenario(&s).unwrap();
        let est = sources[0].initial_estimate();
        let build = || {
            crate::sim::vehicle_agent(&s, &s.vehicles[0], &world, &est, 0, 7)
                .unwrap()
                .into_parts()
                .0
        };
        let (mut handed, mut sequential) = (build(), build());
        // 4 s of the stream on both (frames build a map), then a round.
        let mut steps = std::iter::from_fn(|| sources[0].step());
        for st in steps.by_ref().take(400) {
            for e in [&mut handed, &mut sequential] {
                e.on_imu(&st.imu).unwrap();
                if let Some((f, _)) = &st.frame {
                    let _ = e.on_frame(f);
                }
            }
        }
        assert!(handed.num_features() > 0, "the stream built a map");
        let map_at_lend = handed.map().into_owned();
        let mut lent = handed.lend().unwrap();
        assert!(handed.lend().is_err(), "one filter, lent once");
        // Fused elsewhere (here: a round's worth of a neighbour's information, the map itself).
        let info = lent.map_information().unwrap();
        let round = |f: &mut SlamFilter| {
            let mut d = info.clone();
            d.matrix *= 0.5;
            d.vector *= 0.5;
            f.fuse_map_information(&d).unwrap();
        };
        round(&mut lent);
        round(sequential.filter_mut());
        // IMU samples only (the vehicle process holds frames back until the filter is back).
        let mut refused = 0;
        for st in steps.take(60) {
            handed.on_imu(&st.imu).unwrap();
            sequential.on_imu(&st.imu).unwrap();
            if let Some((f, _)) = &st.frame
                && refused == 0
            {
                let before = handed.counters().frames_rejected;
                assert!(handed.on_frame(f).is_err(), "a frame while lent is refused");
                assert_eq!(handed.counters().frames_rejected, before + 1);
                refused += 1;
            }
            assert_eq!(&*handed.map(), &map_at_lend[..], "the map as lent");
        }
        assert_eq!(refused, 1, "60 samples at 100 Hz span a 2 Hz frame");
        handed.give_back(lent).unwrap();
        assert!(!handed.is_lent());
        let (a, b) = (handed.filter(), sequential.filter());
        assert_eq!(a.state_vector(), b.state_vector());
        assert_eq!(a.joint_covariance(), b.joint_covariance());
        // Nothing out: refused, counted, the filter kept.
        let before = handed.filter().state_vector();
        assert!(handed.give_back(sequential.filter().clone()).is_err());
        assert_eq!(handed.filter().state_vector(), before);
        assert!(
            handed
                .rejections()
                .counts
                .keys()
                .any(|k| k.starts_with("fusion.give_back."))
        );
    }

    #[test]
    fn reason_keys_name_the_variant_path_not_the_instance() {
        let k = |e: &dyn std::fmt::Debug| variant_key(&format!("{e:?}"));
        assert_eq!(
            k(&SlamError::Ins(InsError::InvalidInterval(0.0))),
            "ins.invalid_interval"
        );
        assert_eq!(
            k(&SlamError::Observation {
                index: 3,
                source: ObservationError::OutsideImage { u: -1.0, v: 2.0 }
            }),
            "observation.outside_image"
        );
        assert_eq!(k(&SlamError::NonFiniteTime), "non_finite_time");
        assert_eq!(
            k(&RejectReason::GateFailed {
                feature: 7,
                nis: 99.0
            }),
            "gate_failed"
        );
        assert_eq!(k(&RejectReason::Ambiguous), "ambiguous");
        assert_eq!(variant_key("42"), "unknown");
    }

    #[test]
    fn rejections_count_by_reason() {
        let mut r = Rejections::default();
        r.imu(&SlamError::Ins(InsError::NonFiniteSample));
        r.imu(&SlamError::Ins(InsError::NonFiniteSample));
        r.frame(&SlamError::NonFiniteTime, 4);
        r.outcomes(&FrameReport {
            outcomes: vec![
                ObservationOutcome::Rejected(RejectReason::Ambiguous),
                ObservationOutcome::Initialized { feature: 1 },
                ObservationOutcome::Rejected(RejectReason::Ambiguous),
            ],
            ..FrameReport::default()
        });
        let want: Vec<(&str, u64)> = vec![
            ("frame.non_finite_time", 1),
            ("imu.ins.non_finite_sample", 2),
            ("observation.ambiguous", 2),
            ("observation.in_rejected_frame", 4),
        ];
        let got: Vec<(&str, u64)> = r.counts.iter().map(|(k, v)| (k.as_str(), *v)).collect();
        assert_eq!(got, want);
    }
}

#[cfg(test)]
mod held_batch_tests {
    use super::*;

    const F: FeatureId = 7_001;
    const G: FeatureId = 7_002;

    /// Node 1 is a vehicle (`VehicleFusion` over a real `SlamFilter`), node 2 a bare DDF node
    /// whose estimate is an information accumulator the test writes into: it can send what no
    /// EKF would, a new feature whose information is indefinite.
    struct Pair {
        fusion: VehicleFusion,
        filter: SlamFilter,
        peer: DdfNode,
        peer_estimate: MapInformation,
        now: f64,
        /// Deltas node 1 sent node 2.
        sent_to_peer: Vec<MapInformation>,
    }

    impl Pair {
        fn new() -> Self {
            let s = crate::scenario::Scenario::builtin_default();
            let (world, sources) = crate::replay::SensorSource::for_scenario(&s).unwrap();
            let est = sources[0].initial_estimate();
            let filter = crate::sim::vehicle_agent(&s, &s.vehicles[0], &world, &est, 0, 7)
                .unwrap()
                .into_parts()
                .0
                .filter()
                .clone();
            let origin = filter.origin();
            let topo = Topology::tree([NodeId(1), NodeId(2)], [(NodeId(1), NodeId(2))]).unwrap();
            let cfg = DdfConfig::default();
            let fusion = VehicleFusion::new(
                NodeId(1),
                11,
                origin,
                Mode::Decentralized,
                &topo,
                cfg.clone(),
                &[],
            )
            .unwrap();
            let peer =
                DdfNode::for_mode(Mode::Decentralized, NodeId(2), 22, &topo, origin, cfg).unwrap();
            let mut pair = Pair {
                fusion,
                filter,
                peer,
                peer_estimate: MapInformation::zero(origin),
                now: 0.0,
                sent_to_peer: Vec::new(),
            };
            let out = pair.fusion.on_link_up(0.0, NodeId(2)).unwrap();
            pair.deliver_to_peer(out);
            let out = pair.peer.on_link_up(0.0, NodeId(1)).unwrap();
            pair.deliver_to_vehicle(out);
            for _ in 0..5 {
                pair.round();
            }
            assert!(
                pair.peer.channel(NodeId(1)).unwrap().synced,
                "the pair did not synchronise"
            );
            pair
        }

        fn deliver_to_peer(&mut self, out: Vec<Outgoing>) {
            let mut queue = out;
            while !queue.is_empty() {
                let mut back = Vec::new();
                for o in queue {
                    if let Body::Delta { info, .. } = &o.message.body {
                        self.sent_to_peer.push(info.clone());
                    }
                    back.extend(
                        self.peer
                            .on_message(self.now, NodeId(1), o.message, &mut self.peer_estimate)
                            .unwrap(),
                    );
                }
                queue = Vec::new();
                for o in back {
                    queue.extend(
                        self.fusion
                            .on_message(self.now, NodeId(2), o.message)
                            .unwrap(),
                    );
                }
            }
        }

        fn deliver_to_vehicle(&mut self, out: Vec<Outgoing>) {
            let mut replies = Vec::new();
            for o in out {
                replies.extend(
                    self.fusion
                        .on_message(self.now, NodeId(2), o.message)
                        .unwrap(),
                );
            }
            self.deliver_to_peer(replies);
        }

        /// One round at both ends (the peer first: what it sends is fused at the vehicle's).
        fn round(&mut self) {
            self.now += 1.0;
            let out = self
                .peer
                .on_round(self.now, &mut self.peer_estimate)
                .unwrap()
                .messages;
            self.deliver_to_vehicle(out);
            let out = self.fusion.round(&mut self.filter, self.now).unwrap();
            self.deliver_to_peer(out);
        }

        /// The peer's estimate gains `diag` on `id`'s diagonal block (and the matching vector
        /// for a feature at `at`, origin-relative).
        fn peer_gains(&mut self, id: FeatureId, diag: [f64; 3], at: Vector3<f64>) {
            let m = Matrix3::from_diagonal(&Vector3::from(diag));
            let v = m * at;
            let origin = self.peer_estimate.origin;
            self.peer_estimate
                .add_assign(&MapInformation {
                    ids: vec![id],
                    origin,
                    matrix: faer::Mat::from_fn(3, 3, |i, j| m[(i, j)]),
                    vector: faer::Col::from_fn(3, |i| v[i]),
                })
                .unwrap();
        }

        fn retries(&self) -> u64 {
            self.fusion
                .rejections()
                .counts
                .iter()
                .filter(|(k, _)| k.starts_with("fusion.fuse_retry."))
                .map(|(_, n)| n)
                .sum()
        }
    }

    /// A batch the EKF refuses is kept and fused when the rest of its information arrives, and
    /// meanwhile the vehicle's deltas do not take it back from its sender: the peer sends a new
    /// feature with information diag(1, 1, −0.5) (indefinite: refused), then diag(0, 0, 1); the
    /// vehicle fuses the sum diag(1, 1, 0.5) one round later (covariance diag(1, 1, 2), a
    /// closed form), nothing is counted lost, and no delta it sent carried the feature.
    /// Dropped before (the design until 2026-12-05), the batch was lost and the next delta
    /// carried −diag(1, 1, −0.5) back to the peer.
    #[test]
    fn a_refused_batch_is_retried_and_not_taken_back_from_its_sender() {
        let mut p = Pair::new();
        let at = Vector3::new(40.0, -25.0, 3.0);
        p.peer_gains(F, [1.0, 1.0, -0.5], at);
        p.round();
        assert_eq!(p.retries(), 1, "{:?}", p.fusion.rejections().counts);
        assert_eq!(p.fusion.counters().fuse_refused, 0);
        assert!(
            p.filter.feature(F).is_none(),
            "an indefinite batch was fused"
        );
        p.peer_gains(F, [0.0, 0.0, 1.0], at);
        p.round();
        assert!(
            p.filter.feature(F).is_some(),
            "the completed batch was not fused"
        );
        assert_eq!(p.fusion.counters().fuse_refused, 0);
        assert_eq!(p.retries(), 1);
        let m = p.filter.marginal(&[F]);
        let at_abs = p.filter.origin() + at;
        for (i, want) in [1.0, 1.0, 2.0].into_iter().enumerate() {
            // 1e-9: the inversion of a 3 × 3 block beside a vehicle block it is not coupled to.
            assert!(
                (m.covariance[(i, i)] - want).abs() < 1e-9,
                "σ²[{i}] = {} (want {want})",
                m.covariance[(i, i)]
            );
            // 1e-6 m: coordinates of ~6e6 m (the marginal's mean is absolute).
            assert!((m.mean[i] - at_abs[i]).abs() < 1e-6, "mean {:?}", m.mean);
        }
        for d in &p.sent_to_peer {
            if let Some(k) = d.ids.iter().position(|&id| id == F) {
                let block_max = (0..3)
                    .flat_map(|i| (0..3).map(move |j| (i, j)))
                    .map(|(i, j)| d.matrix[(3 * k + i, 3 * k + j)].abs())
                    .fold(0.0, f64::max);
                assert!(block_max < 1e-9, "a delta carried F back: {block_max:.3e}");
            }
        }
    }

    /// A batch that stays refused is dropped after [`MAX_FUSE_ATTEMPTS`] rounds, counted in
    /// `fuse_refused` (per delta) and under `fusion.fuse.<reason>` with its cause, and fusion
    /// goes on: a later, positive definite feature is fused.
    #[test]
    fn a_batch_refused_at_every_attempt_is_dropped_and_counted() {
        let mut p = Pair::new();
        let at = Vector3::new(-30.0, 10.0, 2.0);
        p.peer_gains(G, [1.0, -1.0, 1.0], at);
        for _ in 0..MAX_FUSE_ATTEMPTS {
            p.round();
        }
        assert_eq!(p.fusion.counters().fuse_refused, 1);
        assert_eq!(p.retries(), u64::from(MAX_FUSE_ATTEMPTS - 1));
        assert_eq!(
            p.fusion
                .rejections()
                .counts
                .get("fusion.fuse.not_positive_definite"),
            Some(&1),
            "{:?}",
            p.fusion.rejections().counts
        );
        assert!(p.filter.feature(G).is_none());
        p.peer_gains(F, [2.0, 2.0, 2.0], at);
        p.round();
        assert!(
            p.filter.feature(F).is_some(),
            "fusion stopped after a dropped batch"
        );
    }
}
