//! The fusion network part of a scenario: `[run]`, `[fusion]`, `[[link]]`, `[[partition]]`,
//! `[[event]]` and `[secrets]`, next to the `[world]` and `[[vehicle]]` tables of
//! [`crate::scenario`].
//!
//! # Example
//! ```toml
//! [run]
//! name = "tree-4"
//! duration_s = 300.0
//!
//! [fusion]
//! mode = "decentralized"        # or "central" (a hub process) or "isolated" (no fusion)
//! rate_hz = 1.0
//!
//! [[link]]
//! a = 1
//! b = 2                          # transport = "shm" (iceoryx2, same host) by default
//!
//! [[link]]
//! a = 2
//! b = 3
//! transport = "net"              # zenoh over TCP
//! faults = { loss = 0.2, outages = [[60.0, 120.0]] }
//!
//! [[event]]
//! kind = "crash"
//! vehicle = 3
//! at_s = 100.0
//! restart_after_s = 20.0
//! ```

use std::collections::{BTreeMap, BTreeSet};

use canopy_fusion::ci::{CiCriterion, Submap};
pub use canopy_fusion::ddf::DeltaPrecision;
use canopy_fusion::ddf::{DdfConfig, Mode};
use canopy_fusion::slam::{AssociationConfig, AssociationMode, DEFAULT_NEW_FEATURE_PROBABILITY};
use canopy_fusion::topology::{NodeId, Topology, TopologyError};
use serde::{Deserialize, Serialize};

use crate::scenario::{AppearanceConfig, Identity, Scenario, ScenarioError};

/// `[run]`: how long and how a run goes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RunConfig {
    /// Scenario name used in reports (default: the file name, or `default`).
    pub name: Option<String>,
    /// Simulated duration [s] (default 300).
    pub duration_s: f64,
    /// Interval between estimate-vs-truth samples in the record [s] (default 1).
    pub record_interval_s: f64,
    /// Run the centralized all-data EKF alongside as the reference (default true).
    pub baseline: bool,
    /// Pacing of the multi-process run: simulated seconds per wall second; absent or 0 = as fast
    /// as the slowest vehicle allows (default).
    pub real_time_factor: Option<f64>,
    /// How far the world may run ahead of the slowest live vehicle, and of a live hub
    /// [simulated s] (default 2): the flow-control window of the multi-process run.
    pub max_lead_s: f64,
    /// The instant of a recording's own clock that is simulated t = 0 [ns] (replayed
    /// recordings, `canopy import`); outputs stamp their times with origin + t, exactly, in
    /// the recording's time base. Absent: outputs use t itself.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_origin_ns: Option<u64>,
    /// What each vehicle (and hub) process's heap keeps between fusion rounds: `lean`
    /// (default: least resident memory) or `warm` (the round's large temporaries reused
    /// instead of faulted in afresh: less CPU, more memory;
    /// [`canopy_fusion::runtime::HeapPolicy`]). `canopy sim` applies it to its one process.
    pub heap: canopy_fusion::runtime::HeapPolicy,
}

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            name: None,
            duration_s: 300.0,
            record_interval_s: 1.0,
            baseline: true,
            real_time_factor: None,
            max_lead_s: 2.0,
            time_origin_ns: None,
            heap: canopy_fusion::runtime::HeapPolicy::Lean,
        }
    }
}

/// Fusion architecture (chapter §21.5).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum FusionMode {
    /// Channel filters on a tree of vehicles (§21.5.3, corrected).
    #[default]
    Decentralized,
    /// A hub process without observations, channel filters on every vehicle–hub link (§21.5.2,
    /// the independent opinion pool with local feedback, corrected).
    Central,
    /// No fusion: every vehicle runs its own SLAM (the baseline that shows the benefit).
    Isolated,
    /// Data sharing: every vehicle's data (IMU increments, frames) relayed over the tree, and
    /// every vehicle runs the team's EKF on all of it (`crate::sharing`).
    SharedData,
}

impl std::fmt::Display for FusionMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FusionMode::Decentralized => "decentralized",
            FusionMode::Central => "central",
            FusionMode::Isolated => "isolated",
            FusionMode::SharedData => "shared_data",
        })
    }
}

/// Data association inside a vehicle.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum AssociationKind {
    /// Descriptor candidate verified by the χ² gate (default: like a real feature descriptor
    /// with geometric verification).
    #[default]
    Descriptor,
    /// Descriptors ignored: greedy nearest neighbour over gated pairs.
    NearestNeighbour,
    /// Descriptors ignored: joint compatibility branch and bound.
    Jcbb,
    /// Track ids as hints, appearance descriptors within `[world.appearance] max_distance`
    /// bits as candidates, chosen by the gate and JCBB (`jcbb_max_nodes`); needs
    /// `[world.appearance] identity = "appearance"`.
    Appearance,
}

/// What covariance intersection's ω minimises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum CiCriterionConfig {
    /// tr P (default).
    #[default]
    Trace,
    /// det P.
    Determinant,
}

/// `[fusion]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionConfig {
    /// Architecture (default `decentralized`).
    pub mode: FusionMode,
    /// Fusion rounds per simulated second (default 1).
    pub rate_hz: f64,
    /// Data association inside each vehicle. Default: `descriptor` with perfect identities,
    /// `appearance` with `[world.appearance] identity = "appearance"`
    /// ([`crate::scenario::Scenario::association_config`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub association: Option<AssociationKind>,
    /// χ² gate probability (default 0.95, eq. 21.55).
    pub gate_probability: f64,
    /// JCBB search budget per frame (default 2000 nodes).
    pub jcbb_max_nodes: usize,
    /// Default per-link byte budget of one round's delta; absent = unlimited (exact channel
    /// filters). A link whose delta does not fit falls back to covariance intersection for good.
    pub byte_budget: Option<usize>,
    /// What CI's ω minimises (default `trace`).
    pub ci_criterion: CiCriterionConfig,
    /// Precision of delta information blocks on the wire: `f64` (exact, default) or `f32`
    /// (half the bytes per block, deflated so it never carries more information than exact).
    pub delta_precision: DeltaPrecision,
    /// Compression of information-carrying DDF messages on the wire: `none` (default) or
    /// `zstd`.
    pub delta_compression: crate::wire::Compression,
    /// Node id of the hub in central mode (default 0; must differ from every vehicle id).
    pub hub_id: u32,
    /// Interval between DDF Hellos on each link [s] (default 1).
    pub hello_interval_s: f64,
    /// How long a sequence gap may persist before a Nack [s] (default 2).
    pub gap_timeout_s: f64,
    /// Appearance association only: after each fusion every vehicle searches its map for keys
    /// that name one feature (a neighbour's and its own, or two of its own) and adopts them as
    /// correspondences (`canopy_fusion::slam::SlamFilter::find_correspondences`). Default true;
    /// false is the ablation in which a feature two vehicles initialised before exchanging
    /// stays two features.
    pub map_correspondences: bool,
    /// Appearance association only: the largest σ [m] along its worst axis of the difference
    /// of two keys' estimates for the correspondence search to decide whether they are one
    /// feature (`canopy_fusion::slam::CorrespondenceConfig::max_difference_sigma_m`; default
    /// 20). A pair known worse than this waits for more information: the χ² gate cannot tell a
    /// lookalike hundreds of metres away from the same feature when σ is that large.
    pub correspondence_max_sigma_m: f64,
    /// When a vehicle process applies a neighbour's DDF message (`canopy run`; `canopy sim`
    /// is deterministic either way): `arrival` (default: as soon as it arrives) or
    /// `simulation_time` (at the receiver's first round one round period after the message's
    /// simulation time, waiting for it if needed: the run no longer depends on process timing;
    /// decentralized mode, fault-free links; `process::delivery`).
    pub delivery: Delivery,
    /// Capacity-limited links (radio, `byte_budget`): the shortest time [s] between two rounds
    /// that form a link's delta or CI submap (default 0: every round). Each such round gets
    /// the budget of the whole interval ([`FusionConfig::budget_rate_hz`]), so the bytes per
    /// second are the same; what waits stays in the channel filter's residual. Forming a
    /// sparsified delta costs a Schur complement over the map (O(k³) per link), so on large
    /// maps a longer interval is what keeps the fusion within real time
    /// (`canopy_fusion::ddf::DdfConfig::budget_interval`).
    pub radio_interval_s: f64,
    /// Sparsified links: each vehicle lists its loosely held features (σ > 10 m) to its
    /// radio neighbours, which put the ones they hold far better first into their next
    /// marginals (default true; `false` is the ablation:
    /// `canopy_fusion::ddf::DdfConfig::uncertain_lists`).
    pub uncertain_lists: bool,
    /// Data sharing: the rate [Hz] of the IMU increments a vehicle publishes (its IMU summed
    /// over 1/`share_imu_hz`; default 10). A frame closes the increment before it.
    pub share_imu_hz: f64,
}

/// When a vehicle process applies what its neighbours send (`[fusion] delivery`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Delivery {
    /// As it arrives: the round that fuses a message is the first after its arrival in wall
    /// time, so the outcome depends on process scheduling (the runs of one scenario spread).
    #[default]
    Arrival,
    /// At simulation-time boundaries: a message stamped `t` (its sender's round time) is
    /// applied at the receiver's first round at or after `t + 1/rate_hz`, and a vehicle waits
    /// at each round until every neighbour on a fault-free link has sent everything it stamps up
    /// to then. Every vehicle then sees the same messages at the same simulated instants, run
    /// after run and on one host or several (`process::delivery`).
    SimulationTime,
}

impl Default for FusionConfig {
    fn default() -> Self {
        Self {
            mode: FusionMode::Decentralized,
            rate_hz: 1.0,
            association: None,
            gate_probability: 0.95,
            jcbb_max_nodes: 2000,
            byte_budget: None,
            ci_criterion: CiCriterionConfig::Trace,
            delta_precision: DeltaPrecision::F64,
            delta_compression: crate::wire::Compression::None,
            hub_id: 0,
            hello_interval_s: 1.0,
            gap_timeout_s: 2.0,
            delivery: Delivery::Arrival,
            map_correspondences: true,
            correspondence_max_sigma_m: canopy_fusion::slam::CorrespondenceConfig::default()
                .max_difference_sigma_m,
            radio_interval_s: 0.0,
            uncertain_lists: true,
            share_imu_hz: 10.0,
        }
    }
}

impl FusionConfig {
    /// How often a capacity-limited link forms its delta [1/s]: every round, or once per
    /// `radio_interval_s` when that is longer. Radio budgets are sized per delta at this rate
    /// (`crate::radio::round_budget`). Data sharing sends a batch every round, so its rate is
    /// the round rate whatever `radio_interval_s` (a channel-filter setting) says.
    pub fn budget_rate_hz(&self) -> f64 {
        if self.mode != FusionMode::SharedData && self.radio_interval_s * self.rate_hz > 1.0 {
            1.0 / self.radio_interval_s
        } else {
            self.rate_hz
        }
    }

    /// The vehicles' association options given the world's identity model: `association`,
    /// or its default for `identity` (descriptor for perfect identities, appearance otherwise);
    /// appearance association takes its candidate distance from `appearance`.
    pub fn association_config(&self, appearance: &AppearanceConfig) -> AssociationConfig {
        self.association_config_for(appearance, false)
    }

    /// [`association_config`](Self::association_config) for one vehicle: a vehicle replayed
    /// from logs gets its descriptors from the log (track ids of a recording or of a recorded
    /// run), not from the simulator's identity model, so its default is `descriptor`.
    pub fn association_config_for(
        &self,
        appearance: &AppearanceConfig,
        replayed: bool,
    ) -> AssociationConfig {
        let identity = if replayed {
            Identity::Perfect
        } else {
            appearance.identity
        };
        AssociationConfig {
            mode: match self.association_kind(identity) {
                AssociationKind::Descriptor => AssociationMode::Descriptor,
                AssociationKind::NearestNeighbour => AssociationMode::NearestNeighbour,
                AssociationKind::Jcbb => AssociationMode::Jcbb {
                    max_nodes: self.jcbb_max_nodes,
                },
                AssociationKind::Appearance => AssociationMode::Appearance {
                    max_distance: appearance.association_distance(),
                    max_nodes: self.jcbb_max_nodes,
                },
            },
            gate_probability: self.gate_probability,
            new_feature_probability: DEFAULT_NEW_FEATURE_PROBABILITY,
        }
    }

    /// `association`, or its default for the identity model.
    pub fn association_kind(&self, identity: Identity) -> AssociationKind {
        self.association.unwrap_or(match identity {
            Identity::Perfect => AssociationKind::Descriptor,
            Identity::Appearance => AssociationKind::Appearance,
        })
    }

    /// The DDF protocol parameters (times in simulated seconds).
    pub fn ddf_config(&self) -> DdfConfig {
        DdfConfig {
            hello_interval: self.hello_interval_s,
            gap_timeout: self.gap_timeout_s,
            sync_resend_interval: self.hello_interval_s,
            byte_budget: self.byte_budget,
            // Three rounds: a submap is acknowledged with the receiver's next round.
            submap_ack_timeout: 3.0 / self.rate_hz,
            delta_precision: self.delta_precision,
            budget_interval: self.radio_interval_s,
            uncertain_lists: self.uncertain_lists,
            ci_criterion: match self.ci_criterion {
                CiCriterionConfig::Trace => CiCriterion::Trace,
                CiCriterionConfig::Determinant => CiCriterion::Determinant,
            },
            ..DdfConfig::default()
        }
    }

    /// The DDF mode.
    pub fn ddf_mode(&self) -> Mode {
        match self.mode {
            FusionMode::Decentralized => Mode::Decentralized,
            FusionMode::Central => Mode::Central {
                hub: NodeId(self.hub_id),
            },
            // Data sharing runs no channel filters (the agent's sharing half takes over).
            FusionMode::Isolated | FusionMode::SharedData => Mode::Isolated,
        }
    }
}

/// How a link is carried between processes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default, Hash)]
#[serde(rename_all = "snake_case")]
pub enum TransportKind {
    /// iceoryx2 zero-copy shared memory (both ends on this host; default).
    #[default]
    Shm,
    /// zenoh over TCP (ends may be on different hosts or network namespaces).
    Net,
}

/// What happens to messages that meet an outage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum OutagePolicyConfig {
    /// Dropped (default).
    #[default]
    Drop,
    /// Held and delivered when the outage ends (up to `queue_max_messages`).
    Queue,
}

/// Injected faults of one link (both directions), in simulated time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FaultSpec {
    /// Fixed delay [s].
    pub delay_s: f64,
    /// Extra uniform delay in [0, jitter) [s].
    pub jitter_s: f64,
    /// Loss probability per message.
    pub loss: f64,
    /// Duplication probability per message.
    pub duplicate: f64,
    /// Probability of holding a message back by `reorder_delay_s` (reordering).
    pub reorder: f64,
    /// Hold-back of a reordered message [s].
    pub reorder_delay_s: f64,
    /// Outage windows `[start_s, end_s]`.
    pub outages: Vec<[f64; 2]>,
    /// Drop or queue messages during outages (default drop).
    pub outage_policy: OutagePolicyConfig,
    /// Bound on messages held during an outage with the `queue` policy (default 64).
    pub queue_max_messages: usize,
    /// Bandwidth cap [bytes/s]; absent = unlimited.
    pub bandwidth_bytes_per_s: Option<f64>,
    /// Bytes allowed to wait behind the bandwidth cap (default 1 MiB).
    pub bandwidth_queue_bytes: u64,
}

impl Default for FaultSpec {
    fn default() -> Self {
        Self {
            delay_s: 0.0,
            jitter_s: 0.0,
            loss: 0.0,
            duplicate: 0.0,
            reorder: 0.0,
            reorder_delay_s: 0.0,
            outages: Vec::new(),
            outage_policy: OutagePolicyConfig::Drop,
            queue_max_messages: 64,
            bandwidth_bytes_per_s: None,
            bandwidth_queue_bytes: 1 << 20,
        }
    }
}

impl FaultSpec {
    /// Whether any fault is configured.
    pub fn is_none(&self) -> bool {
        self == &FaultSpec::default()
    }

    /// The transport fault layer's configuration for one endpoint (its inbound direction),
    /// with the scenario's partitions that cut this link.
    pub fn to_transport(
        &self,
        seed: u64,
        partitions: &[PartitionSpec],
    ) -> canopy_transport::fault::FaultConfig {
        use canopy_transport::fault::{Bandwidth, FaultConfig, OutagePolicy, Partition, Window};
        FaultConfig {
            seed,
            delay: self.delay_s,
            jitter: self.jitter_s,
            loss: self.loss,
            duplicate: self.duplicate,
            reorder: self.reorder,
            reorder_delay: self.reorder_delay_s,
            outages: self
                .outages
                .iter()
                .map(|w| Window::new(w[0], w[1]))
                .collect(),
            partitions: partitions
                .iter()
                .map(|p| Partition {
                    window: Window::new(p.start_s, p.end_s),
                    side: p.side.clone(),
                })
                .collect(),
            outage_policy: match self.outage_policy {
                OutagePolicyConfig::Drop => OutagePolicy::Drop,
                OutagePolicyConfig::Queue => OutagePolicy::Queue {
                    max_messages: self.queue_max_messages,
                },
            },
            bandwidth: self.bandwidth_bytes_per_s.map(|b| Bandwidth {
                bytes_per_s: b,
                queue_bytes: self.bandwidth_queue_bytes,
            }),
            radio: None,
            signal_outages: true,
        }
    }

    fn validate(&self, field: &str, duration: f64) -> Result<(), ScenarioError> {
        for (name, v) in [
            ("delay_s", self.delay_s),
            ("jitter_s", self.jitter_s),
            ("reorder_delay_s", self.reorder_delay_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(ScenarioError::invalid(
                    format!("{field}.{name}"),
                    format!("must be a finite number ≥ 0, got {v}"),
                ));
            }
        }
        for (name, v) in [
            ("loss", self.loss),
            ("duplicate", self.duplicate),
            ("reorder", self.reorder),
        ] {
            if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                return Err(ScenarioError::invalid(
                    format!("{field}.{name}"),
                    format!("a probability must be in [0, 1], got {v}"),
                ));
            }
        }
        for (i, w) in self.outages.iter().enumerate() {
            if !(w[0].is_finite() && w[1].is_finite() && w[0] >= 0.0 && w[1] > w[0]) {
                return Err(ScenarioError::invalid(
                    format!("{field}.outages[{i}]"),
                    format!(
                        "an outage is [start_s, end_s] with 0 ≤ start < end, got [{}, {}]",
                        w[0], w[1]
                    ),
                ));
            }
            if w[0] >= duration {
                return Err(ScenarioError::invalid(
                    format!("{field}.outages[{i}]"),
                    format!("starts at {} s, after the run ends ({duration} s)", w[0]),
                ));
            }
        }
        if let Some(b) = self.bandwidth_bytes_per_s
            && !(b.is_finite() && b > 0.0)
        {
            return Err(ScenarioError::invalid(
                format!("{field}.bandwidth_bytes_per_s"),
                format!("must be > 0, got {b}"),
            ));
        }
        if self.outage_policy == OutagePolicyConfig::Queue && self.queue_max_messages == 0 {
            return Err(ScenarioError::invalid(
                format!("{field}.queue_max_messages"),
                "must be ≥ 1 with the queue policy",
            ));
        }
        Ok(())
    }
}

/// `[[link]]`: one edge of the fusion network.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinkSpec {
    /// One end: a vehicle id (or the hub id in central mode) (*required*).
    pub a: u32,
    /// The other end (*required*).
    pub b: u32,
    /// `shm` (iceoryx2, default) or `net` (zenoh over TCP).
    #[serde(default)]
    pub transport: TransportKind,
    /// `net` only: the zenoh endpoint end `a` listens on, e.g. `tcp/127.0.0.1:7447`; `b`
    /// connects to it. Absent: a free loopback port is chosen at launch.
    #[serde(default)]
    pub listen: Option<String>,
    /// Byte budget of one round's delta on this link (overrides `[fusion].byte_budget`).
    #[serde(default)]
    pub byte_budget: Option<usize>,
    /// Injected faults.
    #[serde(default)]
    pub faults: FaultSpec,
    /// A radio link: capacity, queue, latency and optional range (both directions).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radio: Option<crate::radio::RadioSpec>,
}

impl LinkSpec {
    /// The transport fault layer's configuration for one end's inbound direction: the
    /// injected faults, the scenario's partitions that cut this link, and the radio model
    /// (its range evaluated from both vehicles' true trajectories).
    pub fn fault_config(
        &self,
        s: &Scenario,
        seed: u64,
    ) -> Result<canopy_transport::fault::FaultConfig, ScenarioError> {
        let mut cfg = self.faults.to_transport(seed, &s.partitions);
        cfg.radio = match &self.radio {
            Some(r) => Some(r.to_transport(s, [self.a, self.b])?),
            None => None,
        };
        Ok(cfg)
    }

    /// `a-b` with node names.
    pub fn label(&self, names: &BTreeMap<u32, String>) -> String {
        let n = |id: u32| names.get(&id).cloned().unwrap_or_else(|| id.to_string());
        format!("{}-{}", n(self.a), n(self.b))
    }
}

/// `[[partition]]`: the network is cut between `side` and everybody else.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PartitionSpec {
    /// Start [s].
    pub start_s: f64,
    /// End (heal) [s].
    pub end_s: f64,
    /// Node ids on one side of the cut.
    pub side: Vec<u32>,
}

/// Kinds of lifecycle events.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    /// The vehicle's process is killed (SIGKILL in multi-process runs); with
    /// `restart_after_s` it is restarted and rejoins with a new epoch.
    Crash,
    /// The hub process is killed (central mode); vehicles continue on their local SLAM.
    HubLoss,
}

/// `[[event]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventSpec {
    /// What happens.
    pub kind: EventKind,
    /// Which vehicle (`crash`).
    #[serde(default)]
    pub vehicle: Option<u32>,
    /// When [s].
    pub at_s: f64,
    /// Restart after this long [s] (`crash`); absent = stays down.
    #[serde(default)]
    pub restart_after_s: Option<f64>,
}

/// `[secrets]`: the team's zenoh credential.
///
/// With `zenoh_password`, every zenoh session of a run authenticates (zenoh `auth_usrpwd`) as
/// the user of its own node — the node's name (`uav3`, `hub`), a host launcher `host-NAME`, the
/// monitor `monitor` — with this password, and every session that listens enforces access
/// control built from the topology: an authenticated session may only publish and subscribe on
/// its own side of its links with the listening node (`canopy_transport::access`; design in
/// docs/arch/deploy.md). Without it, sessions are neither authenticated nor access-controlled.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct SecretsConfig {
    /// The team's zenoh password.
    pub zenoh_password: Option<String>,
}

/// Node ids from this one up are reserved for the processes of a run that are not fusion nodes
/// (the world and the monitor, see `crate::process`).
pub const FIRST_RESERVED_NODE_ID: u32 = u32::MAX - 15;

/// Names of every node of the scenario (vehicles and, in central mode, the hub).
pub fn node_names(s: &Scenario) -> BTreeMap<u32, String> {
    let mut names: BTreeMap<u32, String> = s
        .vehicles
        .iter()
        .map(|v| (v.id, v.display_name()))
        .collect();
    if s.fusion.mode == FusionMode::Central {
        names.insert(s.fusion.hub_id, "hub".to_string());
    }
    names
}

/// The links the run uses: the configured ones, or in central mode without `[[link]]` a star of
/// default (shm, fault-free) links to the hub; none in isolated mode.
pub fn effective_links(s: &Scenario) -> Vec<LinkSpec> {
    match s.fusion.mode {
        FusionMode::Isolated => Vec::new(),
        FusionMode::Central if s.links.is_empty() => s
            .vehicles
            .iter()
            .map(|v| LinkSpec {
                a: s.fusion.hub_id,
                b: v.id,
                // Shared memory on one host; zenoh to a vehicle on another host than the hub's.
                transport: if crate::deploy::host_of(s, v.id).map(|h| h.0)
                    == crate::deploy::host_of(s, s.fusion.hub_id).map(|h| h.0)
                {
                    TransportKind::Shm
                } else {
                    TransportKind::Net
                },
                listen: None,
                byte_budget: None,
                faults: FaultSpec::default(),
                radio: None,
            })
            .collect(),
        _ => s.links.clone(),
    }
}

/// The fusion topology (a tree; the star around the hub in central mode).
pub fn topology(s: &Scenario) -> Result<Topology, ScenarioError> {
    let mut nodes: Vec<NodeId> = s.vehicles.iter().map(|v| NodeId(v.id)).collect();
    if s.fusion.mode == FusionMode::Central {
        nodes.push(NodeId(s.fusion.hub_id));
    }
    let links: Vec<(NodeId, NodeId)> = effective_links(s)
        .iter()
        .map(|l| (NodeId(l.a), NodeId(l.b)))
        .collect();
    if s.fusion.mode == FusionMode::Isolated {
        return Topology::new(nodes, links).map_err(|e| topology_error(s, e));
    }
    let t = Topology::tree(nodes, links).map_err(|e| topology_error(s, e))?;
    if s.fusion.mode == FusionMode::Central {
        t.require_star(NodeId(s.fusion.hub_id))
            .map_err(|e| topology_error(s, e))?;
    }
    Ok(t)
}

fn topology_error(s: &Scenario, e: TopologyError) -> ScenarioError {
    let names = node_names(s);
    let name = |n: &NodeId| {
        names
            .get(&n.0)
            .cloned()
            .unwrap_or_else(|| format!("node {}", n.0))
    };
    let reason = match &e {
        TopologyError::Cycle(cycle) => {
            let mut path: Vec<String> = cycle.iter().map(name).collect();
            if let Some(first) = path.first().cloned() {
                path.push(first);
            }
            format!(
                "links form a cycle {}; channel filters need a tree (information would reach a node twice)",
                path.join(" -> ")
            )
        }
        other => other.to_string(),
    };
    ScenarioError::invalid("link", reason)
}

/// Validates the network part of a scenario against its vehicles.
pub fn validate(s: &Scenario) -> Result<(), ScenarioError> {
    let run = &s.run;
    if !(run.duration_s.is_finite() && run.duration_s > 0.0) {
        return Err(ScenarioError::invalid(
            "run.duration_s",
            format!("must be a finite number > 0, got {}", run.duration_s),
        ));
    }
    if !(run.record_interval_s.is_finite() && run.record_interval_s > 0.0) {
        return Err(ScenarioError::invalid(
            "run.record_interval_s",
            format!("must be > 0, got {}", run.record_interval_s),
        ));
    }
    if let Some(r) = run.real_time_factor
        && !(r.is_finite() && r >= 0.0)
    {
        return Err(ScenarioError::invalid(
            "run.real_time_factor",
            format!("must be ≥ 0 (0 = as fast as possible), got {r}"),
        ));
    }
    if run.time_origin_ns.is_some_and(|o| o > i64::MAX as u64) {
        return Err(ScenarioError::invalid(
            "run.time_origin_ns",
            "must be below 2⁶³ (TOML integers are signed 64-bit)",
        ));
    }
    if !(run.max_lead_s.is_finite() && run.max_lead_s > 0.0) {
        return Err(ScenarioError::invalid(
            "run.max_lead_s",
            format!("must be > 0, got {}", run.max_lead_s),
        ));
    }
    let f = &s.fusion;
    if !(f.rate_hz.is_finite() && f.rate_hz > 0.0 && f.rate_hz <= 100.0) {
        return Err(ScenarioError::invalid(
            "fusion.rate_hz",
            format!("must be in (0, 100], got {}", f.rate_hz),
        ));
    }
    if !(f.gate_probability > 0.0 && f.gate_probability < 1.0) {
        return Err(ScenarioError::invalid(
            "fusion.gate_probability",
            format!("must be in (0, 1), got {}", f.gate_probability),
        ));
    }
    for (name, v) in [
        ("hello_interval_s", f.hello_interval_s),
        ("gap_timeout_s", f.gap_timeout_s),
        ("correspondence_max_sigma_m", f.correspondence_max_sigma_m),
    ] {
        if !(v.is_finite() && v > 0.0) {
            return Err(ScenarioError::invalid(
                format!("fusion.{name}"),
                format!("must be > 0, got {v}"),
            ));
        }
    }
    if !(f.radio_interval_s.is_finite() && (0.0..=3600.0).contains(&f.radio_interval_s)) {
        return Err(ScenarioError::invalid(
            "fusion.radio_interval_s",
            format!("must be in [0, 3600] s, got {}", f.radio_interval_s),
        ));
    }
    if !(f.share_imu_hz.is_finite() && f.share_imu_hz > 0.0 && f.share_imu_hz <= 1000.0) {
        return Err(ScenarioError::invalid(
            "fusion.share_imu_hz",
            format!("must be in (0, 1000] Hz, got {}", f.share_imu_hz),
        ));
    }
    let identity = s.world.appearance.identity;
    let kind = f.association_kind(identity);
    if kind == AssociationKind::Appearance && identity == Identity::Perfect {
        return Err(ScenarioError::invalid(
            "fusion.association",
            "\"appearance\" needs [world.appearance] identity = \"appearance\" (perfect \
             identities carry no appearance descriptors)",
        ));
    }
    if identity == Identity::Appearance
        && let Some(i) = s
            .vehicles
            .iter()
            .position(|v| v.replay.is_none() && v.sensor.mismatch_probability > 0.0)
    {
        return Err(ScenarioError::invalid(
            format!("vehicle[{i}].sensor.mismatch_probability"),
            "descriptor mismatches model wrong identities; with identity = \"appearance\" the \
             errors are [world.appearance]'s bit flips, confusable features and track breaks",
        ));
    }
    if matches!(kind, AssociationKind::Jcbb | AssociationKind::Appearance) && f.jcbb_max_nodes == 0
    {
        return Err(ScenarioError::invalid(
            "fusion.jcbb_max_nodes",
            "must be ≥ 1",
        ));
    }
    let ids: BTreeSet<u32> = s.vehicles.iter().map(|v| v.id).collect();
    if let Some(i) = s
        .vehicles
        .iter()
        .position(|v| v.id >= FIRST_RESERVED_NODE_ID)
    {
        return Err(ScenarioError::invalid(
            format!("vehicle[{i}].id"),
            format!(
                "ids from {FIRST_RESERVED_NODE_ID} up are reserved for the world and monitor processes"
            ),
        ));
    }
    if f.mode == FusionMode::Central && f.hub_id >= FIRST_RESERVED_NODE_ID {
        return Err(ScenarioError::invalid(
            "fusion.hub_id",
            format!(
                "ids from {FIRST_RESERVED_NODE_ID} up are reserved for the world and monitor processes"
            ),
        ));
    }
    if f.delivery == Delivery::SimulationTime && f.mode != FusionMode::Decentralized {
        return Err(ScenarioError::invalid(
            "fusion.delivery",
            format!(
                "simulation_time delivery is built for decentralized mode (the hub of central \
                 mode applies messages as they arrive); this scenario is {}",
                f.mode
            ),
        ));
    }
    if f.mode == FusionMode::Central && ids.contains(&f.hub_id) {
        return Err(ScenarioError::invalid(
            "fusion.hub_id",
            format!("{} is also a vehicle id", f.hub_id),
        ));
    }
    let min_budget = Submap::wire_bytes_for(1);
    let budget_ok = |field: String, b: Option<usize>| match b {
        Some(b) if b < min_budget => Err(ScenarioError::invalid(
            field,
            format!(
                "a budget of {b} bytes cannot carry even one feature's submap ({min_budget} bytes)"
            ),
        )),
        _ => Ok(()),
    };
    budget_ok("fusion.byte_budget".into(), f.byte_budget)?;
    let mut listens: BTreeMap<&str, usize> = BTreeMap::new();
    let known = |id: u32| ids.contains(&id) || (f.mode == FusionMode::Central && id == f.hub_id);
    for (i, l) in s.links.iter().enumerate() {
        let field = format!("link[{i}]");
        for (end, id) in [("a", l.a), ("b", l.b)] {
            if !known(id) {
                return Err(ScenarioError::invalid(
                    format!("{field}.{end}"),
                    format!(
                        "node {id} is not a vehicle of this scenario{}",
                        if f.mode == FusionMode::Central {
                            " nor the hub"
                        } else {
                            ""
                        }
                    ),
                ));
            }
        }
        if l.a == l.b {
            return Err(ScenarioError::invalid(
                field,
                format!("self-link on node {}", l.a),
            ));
        }
        if let Some((j, _)) = s.links[..i]
            .iter()
            .enumerate()
            .find(|(_, o)| (o.a, o.b) == (l.a, l.b) || (o.a, o.b) == (l.b, l.a))
        {
            return Err(ScenarioError::invalid(
                field,
                format!("duplicate of link[{j}] ({}-{})", l.a, l.b),
            ));
        }
        budget_ok(format!("{field}.byte_budget"), l.byte_budget)?;
        l.faults
            .validate(&format!("{field}.faults"), run.duration_s)?;
        if let Some(r) = &l.radio {
            r.validate(&format!("{field}.radio"), s, [l.a, l.b])?;
            if !matches!(f.mode, FusionMode::Decentralized | FusionMode::SharedData) {
                return Err(ScenarioError::invalid(
                    format!("{field}.radio"),
                    "radio links need fusion.mode = \"decentralized\" or \"shared_data\" (the \
                     hub keeps only information, so it cannot fuse the CI submaps a radio link \
                     carries)",
                ));
            }
            if l.faults.bandwidth_bytes_per_s.is_some() {
                return Err(ScenarioError::invalid(
                    format!("{field}.faults.bandwidth_bytes_per_s"),
                    "a radio link has its capacity (radio.bytes_per_s); give one or the other",
                ));
            }
            if l.byte_budget.is_some() {
                return Err(ScenarioError::invalid(
                    format!("{field}.byte_budget"),
                    "a radio link derives its per-round budget from its capacity; remove byte_budget",
                ));
            }
        }
        match (&l.transport, &l.listen) {
            (TransportKind::Shm, Some(_)) => {
                return Err(ScenarioError::invalid(
                    format!("{field}.listen"),
                    "only `net` links have a listen endpoint",
                ));
            }
            (TransportKind::Net, Some(ep)) => {
                let port_ok = ep
                    .strip_prefix("tcp/")
                    .or_else(|| ep.strip_prefix("tls/"))
                    .and_then(|rest| rest.rsplit_once(':'))
                    .and_then(|(_, port)| port.parse::<u16>().ok());
                if port_ok.is_none() {
                    return Err(ScenarioError::invalid(
                        format!("{field}.listen"),
                        format!(
                            "`{ep}` is not a zenoh TCP or TLS endpoint like tcp/127.0.0.1:7447"
                        ),
                    ));
                }
                if let Some(j) = listens.insert(ep.as_str(), i) {
                    return Err(ScenarioError::invalid(
                        format!("{field}.listen"),
                        format!("port clash: link[{j}] already listens on {ep}"),
                    ));
                }
            }
            _ => {}
        }
    }
    if f.mode == FusionMode::Isolated && !s.links.is_empty() {
        return Err(ScenarioError::invalid(
            "link",
            "isolated mode uses no links; remove the [[link]] tables or choose another mode",
        ));
    }
    if f.mode == FusionMode::Decentralized && s.vehicles.len() > 1 && s.links.is_empty() {
        return Err(ScenarioError::invalid(
            "link",
            "decentralized mode needs [[link]] tables forming a tree over the vehicles",
        ));
    }
    topology(s)?;
    for (i, p) in s.partitions.iter().enumerate() {
        let field = format!("partition[{i}]");
        if !(p.start_s.is_finite()
            && p.end_s.is_finite()
            && p.start_s >= 0.0
            && p.end_s > p.start_s)
        {
            return Err(ScenarioError::invalid(
                field,
                format!(
                    "needs 0 ≤ start_s < end_s, got [{}, {}]",
                    p.start_s, p.end_s
                ),
            ));
        }
        if p.side.is_empty() {
            return Err(ScenarioError::invalid(
                format!("{field}.side"),
                "names no node",
            ));
        }
        if let Some(bad) = p.side.iter().find(|&&id| !known(id)) {
            return Err(ScenarioError::invalid(
                format!("{field}.side"),
                format!("node {bad} is not in this scenario"),
            ));
        }
    }
    for (i, e) in s.events.iter().enumerate() {
        let field = format!("event[{i}]");
        if !(e.at_s.is_finite() && e.at_s >= 0.0 && e.at_s < run.duration_s) {
            return Err(ScenarioError::invalid(
                format!("{field}.at_s"),
                format!(
                    "must be in [0, duration_s = {}), got {}",
                    run.duration_s, e.at_s
                ),
            ));
        }
        match e.kind {
            EventKind::Crash => match e.vehicle {
                Some(v) if ids.contains(&v) => {}
                Some(v) => {
                    return Err(ScenarioError::invalid(
                        format!("{field}.vehicle"),
                        format!("vehicle {v} is not in this scenario"),
                    ));
                }
                None => {
                    return Err(ScenarioError::invalid(
                        format!("{field}.vehicle"),
                        "a crash names the vehicle that crashes",
                    ));
                }
            },
            EventKind::HubLoss => {
                if f.mode != FusionMode::Central {
                    return Err(ScenarioError::invalid(
                        format!("{field}.kind"),
                        "hub_loss needs fusion.mode = \"central\"",
                    ));
                }
                if e.restart_after_s.is_some() {
                    return Err(ScenarioError::invalid(
                        format!("{field}.restart_after_s"),
                        "the hub is not restarted",
                    ));
                }
            }
        }
        if e.restart_after_s.is_some()
            && let Some(v) = e.vehicle
            && s.vehicles.iter().any(|x| x.id == v && x.replay.is_some())
        {
            return Err(ScenarioError::invalid(
                format!("{field}.restart_after_s"),
                format!(
                    "vehicle {v} is replayed from logs, which hold no external fix to restart from"
                ),
            ));
        }
        if let Some(r) = e.restart_after_s
            && !(r.is_finite() && r > 0.0)
        {
            return Err(ScenarioError::invalid(
                format!("{field}.restart_after_s"),
                format!("must be > 0, got {r}"),
            ));
        }
    }
    if let Some(p) = &s.secrets.zenoh_password {
        if p.is_empty() || p.contains(['\n', '\r']) {
            return Err(ScenarioError::invalid(
                "secrets.zenoh_password",
                "must be non-empty and on one line",
            ));
        }
        // Each node's name is its zenoh user.
        if let Some((id, n)) = node_names(s)
            .into_iter()
            .find(|(_, n)| n.is_empty() || n.contains([':', '\n', '\r']))
        {
            return Err(ScenarioError::invalid(
                format!("vehicle {id}.name"),
                format!("{n:?} is its zenoh user: non-empty, without ':' or line breaks"),
            ));
        }
    }
    Ok(())
}
