//! `canopy sim`: the whole scenario in one deterministic process.
//!
//! The same agents as the multi-process run ([`crate::agent`]), every vehicle's sensor source
//! (the world simulator, or a replayed log: [`crate::replay::SensorSource`]) stepped in
//! simulation time, and a simulated network made of the transport's in-memory links wrapped in
//! its fault layer ([`canopy_transport::fault`]) on a manual clock: delay, jitter, loss,
//! duplication, reordering, outages, partitions and bandwidth caps from the scenario, in
//! simulated time, seeded. Messages really are encoded, checksummed, decoded and validated, so
//! byte counts are the real ones. Alongside runs the centralized all-data EKF (one filter over
//! all vehicles and the whole map, fed the same IMU samples and observation frames) as the
//! reference. Same scenario and seed ⇒ bit-identical record.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use canopy_fusion::ddf::Outgoing;
use canopy_fusion::slam::{CorrespondenceConfig, SlamConfig, SlamFilter};
use canopy_fusion::topology::NodeId;
use canopy_transport::fault::{Clock, FaultyLink, ManualClock};
use canopy_transport::link::{Link, LinkEvent, PeerState};
use canopy_transport::memory::{InMemoryHub, InMemoryLink};

use crate::agent::{AgentError, HubAgent, VehicleAgent};
use crate::baseline::estimator_setup;
use crate::metrics::{
    HeldSince, confidence_ratio_in, estimate_sample, map_records, map_records_in, pose_sample,
    state_in,
};
use crate::network::{EventKind, FusionMode, effective_links, node_names, topology};
use crate::process::protocol::FrameAssociations;
use crate::record::{EventRecord, LinkRecord, LinkSample, RunRecord, VehicleRecord};
use crate::replay::{ReplayError, SensorSource};
use crate::scenario::Identity;
use crate::scenario::{Scenario, ScenarioError};
use crate::truth::{TruthAudit, fill_record};
use crate::wire::decode_ddf;
use crate::world::{self, InitialEstimate, World};
use canopy_fusion::frames::Frame4;

/// Options of a simulation run.
#[derive(Default)]
pub struct SimOptions<'a> {
    /// Override of `[run].duration_s`.
    pub duration: Option<f64>,
    /// Override of `[run].baseline`.
    pub baseline: Option<bool>,
    /// Called with (simulated time, duration) about every simulated second.
    pub progress: Option<&'a mut dyn FnMut(f64, f64)>,
    /// Set to stop early; the record gathered so far is returned.
    pub stop: Option<Arc<AtomicBool>>,
}

impl std::fmt::Debug for SimOptions<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimOptions")
            .field("duration", &self.duration)
            .field("baseline", &self.baseline)
            .finish()
    }
}

/// Errors of a simulation run.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The scenario is invalid.
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    /// A replay log is malformed or unreadable.
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// An agent could not be built.
    #[error("building {node}: {source}")]
    Agent {
        /// Node name.
        node: String,
        /// Cause.
        source: AgentError,
    },
    /// The reference filter could not be built.
    #[error("building the centralized reference: {0}")]
    Baseline(canopy_fusion::slam::SlamError),
    /// The data-sharing half could not be built.
    #[error("building {node}: {source}")]
    Sharing {
        /// Node name.
        node: String,
        /// Cause.
        source: crate::sharing::SharingError,
    },
    /// The simulated network could not be built.
    #[error("building link {link}: {reason}")]
    Link {
        /// Link label.
        link: String,
        /// Cause.
        reason: String,
    },
}

/// What a simulation returns beyond the record: checks that need the filters themselves.
#[derive(Debug, Default, Clone)]
pub struct SimChecks {
    /// Per record time, the largest over vehicles and common features of
    /// λ_max(P_central · P_vehicle⁻¹) (≤ 1 when no vehicle is more confident about a feature
    /// than the centralized all-data EKF); empty without baseline.
    pub confidence_ratio: Vec<(f64, f64)>,
    /// DDF messages rejected per vehicle name (invalid, unknown sender, …).
    pub rejected_messages: BTreeMap<String, u64>,
    /// Received deltas the estimators refused, all vehicles.
    pub fuse_refused: u64,
    /// Every vehicle's DDF channels at the end: (vehicle name, neighbour name, counters).
    pub link_ends: Vec<(String, String, canopy_fusion::ddf::ChannelStats)>,
    /// Frames or IMU samples the estimators rejected, all vehicles.
    pub inputs_rejected: u64,
}

/// The outcome of a simulation.
#[derive(Debug)]
pub struct SimOutcome {
    /// The run record (outputs are written from it).
    pub record: RunRecord,
    /// Extra checks.
    pub checks: SimChecks,
}

type SimLink = FaultyLink<InMemoryLink>;

enum Agent {
    Vehicle(Box<VehicleAgent>),
    Hub(Box<HubAgent>),
}

struct Node {
    name: String,
    agent: Option<Agent>,
    links: BTreeMap<NodeId, SimLink>,
    restarts: u32,
    /// Compression of information-carrying messages (`[fusion] delta_compression`).
    compression: crate::wire::Compression,
    /// Sends refused, by reason (`link.send.<error>`, as in the vehicle process), reported with
    /// the vehicle's rejections.
    send_failures: crate::agent::Rejections,
}

impl Node {
    // An error from an agent was counted by reason and logged once by the agent itself
    // (`VehicleFusion::reject`, `HubAgent::reject`) and changed nothing: nothing to send.
    fn on_message(
        &mut self,
        now: f64,
        from: NodeId,
        msg: canopy_fusion::ddf::DdfMessage,
    ) -> Vec<Outgoing> {
        match self.agent.as_mut() {
            Some(Agent::Vehicle(a)) => a.on_message(now, from, msg).unwrap_or_default(),
            Some(Agent::Hub(h)) => h.on_message(now, from, msg).unwrap_or_default(),
            None => Vec::new(),
        }
    }
    fn on_link(&mut self, now: f64, peer: NodeId, up: bool) -> Vec<Outgoing> {
        match (self.agent.as_mut(), up) {
            (Some(Agent::Vehicle(a)), true) => a.on_link_up(now, peer).unwrap_or_default(),
            (Some(Agent::Vehicle(a)), false) => {
                let _ = a.on_link_down(peer);
                Vec::new()
            }
            (Some(Agent::Hub(h)), true) => h.on_link_up(now, peer).unwrap_or_default(),
            (Some(Agent::Hub(h)), false) => {
                let _ = h.on_link_down(peer);
                Vec::new()
            }
            (None, _) => Vec::new(),
        }
    }
    /// Sends DDF messages, each encoded just before it is sent, counted as the vehicle process
    /// counts them ([`crate::process::send_counted`]); the DDF recovers from every loss.
    fn send(&mut self, now: f64, out: Vec<Outgoing>) {
        for o in out {
            let w = crate::wire::WireOutgoing::encode(&o, self.compression);
            drop(o);
            let link = self.links.get_mut(&w.to).map(|l| l as &mut dyn Link);
            crate::process::send_counted(link, now, w, &mut self.send_failures);
        }
    }
}

/// The agent of vehicle `cfg` of scenario `s` from an initial estimate, as every driver builds
/// it (`canopy sim`, the vehicle process, the pre-run checks): its filter (frame and origin of
/// `world`, the scenario's association, fresh ids in the vehicle's namespace), its DDF node on
/// the scenario's topology with each link's byte budget.
/// Largest vehicle id: a vehicle's feature keys carry its id in 20 bits beside its
/// incarnation ([`key_namespace`]).
pub const MAX_VEHICLE_ID: u32 = (1 << 20) - 1;

/// The namespace of the feature keys a vehicle process makes (`SlamConfig::fresh_id_namespace`):
/// its id and its incarnation (the process start: 0, then one more per restart, 11 bits). A
/// restarted process counts its keys from 0 again; with the incarnation in the key, none of
/// them can name a feature its dead predecessor named, which its neighbours still hold.
pub fn key_namespace(id: u32, incarnation: u32) -> u32 {
    ((incarnation & 0x7FF) << 20) | (id & MAX_VEHICLE_ID)
}

/// The estimator and DDF agent of vehicle `cfg` (process start `incarnation`, DDF `epoch`).
pub fn vehicle_agent(
    s: &Scenario,
    cfg: &crate::scenario::VehicleConfig,
    world: &World,
    estimate: &InitialEstimate,
    incarnation: u32,
    epoch: u64,
) -> Result<VehicleAgent, SimError> {
    let topo = topology(s)?;
    let budgets: Vec<(NodeId, Option<usize>)> = effective_links(s)
        .iter()
        .filter_map(|l| {
            let peer = if l.a == cfg.id {
                l.b
            } else if l.b == cfg.id {
                l.a
            } else {
                return None;
            };
            // A radio link starts with a full round's budget; each round then sets it from
            // the link's capacity and queue (`crate::radio::capacity_budgets`).
            let budget = match &l.radio {
                Some(r) => Some(r.delta_budget(&s.fusion)),
                None => l.byte_budget,
            };
            Some((NodeId(peer), budget))
        })
        .collect();
    let radio_peers: Vec<(NodeId, crate::radio::RadioFusion)> = effective_links(s)
        .iter()
        .filter_map(|l| {
            let fusion = l.radio.as_ref()?.fusion;
            match (l.a == cfg.id, l.b == cfg.id) {
                (true, _) => Some((NodeId(l.b), fusion)),
                (_, true) => Some((NodeId(l.a), fusion)),
                _ => None,
            }
        })
        .collect();
    let slam = SlamConfig {
        frame: world.frame(),
        local_gravity_mps2: world.local_gravity(),
        origin: world.map_origin(),
        association: s
            .fusion
            .association_config_for(&s.world.appearance, cfg.replay.is_some()),
        fresh_id_namespace: key_namespace(cfg.id, incarnation),
    };
    let agent_error = |source| SimError::Agent {
        node: cfg.display_name(),
        source,
    };
    let mut agent = VehicleAgent::new(
        NodeId(cfg.id),
        epoch,
        slam,
        estimator_setup(cfg, estimate),
        s.fusion.ddf_mode(),
        &topo,
        s.fusion.ddf_config(),
        &budgets,
    )
    .map_err(agent_error)?;
    agent
        .configure(
            cfg.bearing.config(),
            cfg.replay.as_ref().and_then(|r| r.zero_velocity),
        )
        .map_err(agent_error)?;
    match agent.correspondence() {
        Some(_) if !s.fusion.map_correspondences => agent.set_correspondence(None),
        Some(c) => agent.set_correspondence(Some(CorrespondenceConfig {
            max_difference_sigma_m: s.fusion.correspondence_max_sigma_m,
            ..c
        })),
        None => {}
    }
    if s.world.frames == crate::scenario::Frames::Own {
        let root = crate::frames::team_root(s).map_or(cfg.id, |r| r.0);
        // Perfect identities (the ablation) pair the maps' features by key.
        let distance = (s.world.appearance.identity == Identity::Appearance)
            .then(|| s.world.appearance.association_distance());
        agent.use_own_frame(NodeId(root), distance);
    }
    if s.fusion.mode == crate::network::FusionMode::SharedData {
        // The team filter: every vehicle's models from the scenario; the others' estimates are
        // placeholders (this vehicle's) until their streams' start records arrive.
        let team: Vec<NodeId> = s.vehicles.iter().map(|v| NodeId(v.id)).collect();
        let setups: Vec<_> = s
            .vehicles
            .iter()
            .map(|v| estimator_setup(v, estimate))
            .collect();
        let sharing_error = |source| SimError::Sharing {
            node: cfg.display_name(),
            source,
        };
        let (mut filter, own, relaying) = crate::sharing::build(
            NodeId(cfg.id),
            incarnation,
            epoch,
            slam,
            &team,
            &setups,
            &topo,
            s.fusion.share_imu_hz,
            s.world.appearance.identity == Identity::Appearance,
        )
        .map_err(sharing_error)?;
        crate::baseline::set_team_bearing(s, &mut filter, "the team filter of data sharing", "")
            .map_err(|e| sharing_error(e.into()))?;
        agent.use_sharing(filter, own, relaying);
        return Ok(agent);
    }
    // Capacity-limited links: sparsified channel filters (default) or CI submaps from the
    // first round (`fusion = "ci"`).
    for &(peer, fusion) in &radio_peers {
        match fusion {
            crate::radio::RadioFusion::Sparse => agent.use_sparse(peer),
            crate::radio::RadioFusion::Ci => agent.use_ci(peer),
        }
        .map_err(agent_error)?;
    }
    Ok(agent)
}

/// A fresh epoch for a (re)started node: deterministic in the simulation.
fn epoch_for(seed: u64, node: u32, incarnation: u32) -> u64 {
    world::vehicle_seed(seed ^ 0x5eed_e90c, node)
        .wrapping_add(u64::from(incarnation).wrapping_mul(0x9e37_79b9_7f4a_7c15))
        | 1
}

struct Sim<'s> {
    s: &'s Scenario,
    world: Arc<World>,
    vehicles: Vec<SensorSource>,
    nodes: BTreeMap<NodeId, Node>,
    clock: Arc<ManualClock>,
    baseline: Option<SlamFilter>,
    records: Vec<VehicleRecord>,
    baseline_records: Vec<VehicleRecord>,
    /// Since when each vehicle's map (scenario order) has held its features.
    held: Vec<HeldSince>,
    /// The same for the reference's map.
    baseline_held: HeldSince,
    links: Vec<(NodeId, NodeId, LinkRecord)>,
    checks: SimChecks,
    /// What the vehicles did with their observations, against the truth.
    audit: TruthAudit,
    /// The same for the reference.
    baseline_audit: TruthAudit,
    /// `[world] frames = "own"`: each vehicle's own frame in the launch frame (truth, for the
    /// metrics only); empty with shared frames.
    launch_from_own: BTreeMap<NodeId, Frame4>,
    /// Data sharing: the true ids of every vehicle's frames by (vehicle, time bits), for the
    /// audit of the frames other vehicles' team filters process (truth, metrics only).
    frame_truth: BTreeMap<(u32, u64), Vec<canopy_fusion::sensor::FeatureId>>,
}

impl<'s> Sim<'s> {
    /// The launch-frame transform of an estimate in `owner`'s own frame (identity with shared
    /// frames).
    fn launch_from(&self, owner: Option<NodeId>) -> Frame4 {
        owner
            .and_then(|o| self.launch_from_own.get(&o).copied())
            .unwrap_or_else(Frame4::identity)
    }

    fn vehicle_agent(
        &self,
        index: usize,
        estimate: &InitialEstimate,
        incarnation: u32,
    ) -> Result<VehicleAgent, SimError> {
        let s = self.s;
        let cfg = &s.vehicles[index];
        vehicle_agent(
            s,
            cfg,
            &self.world,
            estimate,
            incarnation,
            epoch_for(s.world.seed, cfg.id, incarnation),
        )
    }

    fn poll_network(&mut self, now: f64) {
        // Deliver until quiet: replies produced now may be due now (zero-delay links).
        for _ in 0..8 {
            let mut any = false;
            let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
            for id in ids {
                let node = self.nodes.get_mut(&id).expect("node exists");
                let peers: Vec<NodeId> = node.links.keys().copied().collect();
                for peer in peers {
                    let mut events = Vec::new();
                    let mut msgs = Vec::new();
                    {
                        let link = node.links.get_mut(&peer).expect("link exists");
                        while let Some(ev) = link.poll_event() {
                            events.push(ev);
                        }
                        while let Ok(Some(m)) = link.try_recv() {
                            // Rejected bodies are counted by the link (`rejected.body`).
                            if let Some(Ok(msg)) = decode_ddf(&m) {
                                msgs.push(msg);
                            }
                        }
                    }
                    any |= !events.is_empty() || !msgs.is_empty();
                    for ev in events {
                        let up = matches!(ev, LinkEvent::PeerUp);
                        let out = node.on_link(now, peer, up);
                        node.send(now, out);
                    }
                    for msg in msgs {
                        let out = node.on_message(now, peer, msg);
                        node.send(now, out);
                    }
                }
            }
            if !any {
                break;
            }
        }
    }

    fn round(&mut self, now: f64) {
        // The naive scheme's bytes: each end's whole map information, dense f64, per round.
        for (a, b, rec) in &mut self.links {
            for x in [*a, *b] {
                let n = match self.nodes.get(&x).and_then(|n| n.agent.as_ref()) {
                    Some(Agent::Vehicle(v)) => v.filter().num_features() as u64,
                    Some(Agent::Hub(h)) => h.store().ids.len() as u64,
                    None => 0,
                };
                rec.naive_bytes += 8 * (9 * n * n + 3 * n);
            }
        }
        let ids: Vec<NodeId> = self.nodes.keys().copied().collect();
        for id in ids {
            let node = self.nodes.get_mut(&id).expect("node exists");
            let out = match node.agent.as_mut() {
                Some(Agent::Vehicle(a)) => {
                    let budgets = crate::radio::capacity_budgets(
                        node.links.iter().map(|(&p, l)| (p, l)),
                        self.s.fusion.budget_rate_hz(),
                    );
                    // A refused budget is counted by reason by the fusion half.
                    let _ = a.set_link_budgets(&budgets);
                    a.on_round(now).unwrap_or_default()
                }
                Some(Agent::Hub(h)) => h.on_round(now).unwrap_or_default(),
                None => Vec::new(),
            };
            node.send(now, out);
        }
        self.poll_network(now);
        self.audit_remote_frames();
    }

    /// Data sharing: the other vehicles' frames each team filter processed, audited against
    /// their true ids under the processing vehicle's keys.
    fn audit_remote_frames(&mut self) {
        for (id, node) in &mut self.nodes {
            let Some(Agent::Vehicle(a)) = node.agent.as_mut() else {
                continue;
            };
            for f in a.take_remote_frames() {
                let truth = self.frame_truth.get(&(f.origin.0, f.time.to_bits()));
                self.audit.frame(
                    id.0,
                    &FrameAssociations::from_report(f.time, &f.report),
                    truth.map(Vec::as_slice),
                );
            }
        }
    }

    fn record(&mut self, now: f64) {
        for (i, sim) in self.vehicles.iter().enumerate() {
            let id = NodeId(self.s.vehicles[i].id);
            if let Some(Agent::Vehicle(a)) = self.nodes.get(&id).and_then(|n| n.agent.as_ref()) {
                let f = a.filter();
                self.held[i].observe(now, f.features().into_iter().map(|x| x.0));
                let v = a.vehicle_index();
                if let (Ok(est), Ok(cov)) = (f.vehicle_state(v), f.vehicle_covariance(v)) {
                    let (est, cov) = state_in(&self.launch_from(a.frame_owner()), &est, &cov);
                    self.records[i].samples.push(match sim.truth() {
                        Some(truth) => pose_sample(&self.world, &est, &cov, truth),
                        None => estimate_sample(&self.world, sim.time(), &est, &cov),
                    });
                }
            }
            if let Some(b) = &self.baseline
                && let (Ok(est), Ok(cov)) = (b.vehicle_state(i), b.vehicle_covariance(i))
            {
                self.baseline_records[i].samples.push(match sim.truth() {
                    Some(truth) => pose_sample(&self.world, &est, &cov, truth),
                    None => estimate_sample(&self.world, sim.time(), &est, &cov),
                });
            }
        }
        if let Some(b) = &self.baseline {
            let identity = self.s.world.appearance.identity;
            self.baseline_held
                .observe(now, b.features().into_iter().map(|x| x.0));
            let worst = self
                .nodes
                .values()
                .filter_map(|n| match n.agent.as_ref() {
                    Some(Agent::Vehicle(a)) => {
                        let r = self.launch_from(a.frame_owner()).rotation();
                        match identity {
                            Identity::Perfect => confidence_ratio_in(&r, a.filter(), b, Some),
                            Identity::Appearance => {
                                confidence_ratio_in(&r, a.filter(), b, |k| self.audit.truth_of(k))
                            }
                        }
                    }
                    .map(|r| r.0),
                    _ => None,
                })
                .fold(f64::NAN, f64::max);
            if worst.is_finite() {
                self.checks.confidence_ratio.push((now, worst));
            }
        }
        for (a, b, rec) in &mut self.links {
            let sample = |n: &BTreeMap<NodeId, Node>, x: NodeId, y: NodeId| {
                n.get(&x)
                    .and_then(|node| node.links.get(&y))
                    .map(|l| (l.stats(), l.fault_stats(), l.peer_state()))
            };
            let (Some((sa, fa, pa)), Some((sb, fb, pb))) =
                (sample(&self.nodes, *a, *b), sample(&self.nodes, *b, *a))
            else {
                continue;
            };
            let chan_rejected =
                |x: NodeId, y: NodeId| match self.nodes.get(&x).and_then(|n| n.agent.as_ref()) {
                    Some(Agent::Vehicle(v)) => v
                        .ddf()
                        .and_then(|d| d.channel(y))
                        .map_or(0, |c| c.stats.rejected),
                    Some(Agent::Hub(h)) => h.ddf().channel(y).map_or(0, |c| c.stats.rejected),
                    None => 0,
                };
            let ci = |x: NodeId, y: NodeId| match self.nodes.get(&x).and_then(|n| n.agent.as_ref())
            {
                Some(Agent::Vehicle(v)) => v
                    .ddf()
                    .and_then(|d| d.channel(y))
                    .is_some_and(|c| c.mode == canopy_fusion::ddf::LinkMode::Ci),
                Some(Agent::Hub(h)) => h
                    .ddf()
                    .channel(y)
                    .is_some_and(|c| c.mode == canopy_fusion::ddf::LinkMode::Ci),
                None => false,
            };
            rec.ci |= ci(*a, *b) || ci(*b, *a);
            rec.samples.push(LinkSample {
                t: now,
                bytes_ab: sa.sent_bytes,
                bytes_ba: sb.sent_bytes,
                messages: sa.sent_messages + sb.sent_messages,
                drops: fa.dropped()
                    + fb.dropped()
                    + sa.dropped_no_peer
                    + sb.dropped_no_peer
                    + sa.dropped_overflow
                    + sb.dropped_overflow,
                rejections: sa.rejected.total()
                    + sb.rejected.total()
                    + chan_rejected(*a, *b)
                    + chan_rejected(*b, *a),
                // The simulated network's links are symmetric: both ends see the same state.
                up: pa == PeerState::Up,
                a_up: pa == PeerState::Up,
                b_up: pb == PeerState::Up,
            });
        }
    }
}

/// Runs a scenario in one deterministic process.
pub fn simulate(s: &Scenario, mut opts: SimOptions<'_>) -> Result<SimOutcome, SimError> {
    s.validate()?;
    let started = std::time::Instant::now();
    let duration = opts.duration.unwrap_or(s.run.duration_s);
    let (world, vehicles) = SensorSource::for_scenario(s)?;
    let names = node_names(s);
    let clock = Arc::new(ManualClock::new(0.0));
    let dyn_clock: Arc<dyn Clock> = clock.clone();
    let with_baseline = opts.baseline.unwrap_or(s.run.baseline);

    let launch_from_own: BTreeMap<NodeId, Frame4> = if world.own_frames() {
        s.vehicles
            .iter()
            .zip(&vehicles)
            .filter_map(|(cfg, v)| match v {
                SensorSource::Sim(v) => Some((NodeId(cfg.id), v.launch_from_own())),
                SensorSource::Replay(_) => None,
            })
            .collect()
    } else {
        BTreeMap::new()
    };
    let mut sim = Sim {
        launch_from_own,
        frame_truth: BTreeMap::new(),
        s,
        world: world.clone(),
        vehicles,
        nodes: BTreeMap::new(),
        clock: clock.clone(),
        baseline: None,
        records: s
            .vehicles
            .iter()
            .map(|v| VehicleRecord {
                name: v.display_name(),
                ..Default::default()
            })
            .collect(),
        baseline_records: s
            .vehicles
            .iter()
            .map(|v| VehicleRecord {
                name: v.display_name(),
                ..Default::default()
            })
            .collect(),
        held: vec![HeldSince::default(); s.vehicles.len()],
        baseline_held: HeldSince::default(),
        links: Vec::new(),
        checks: SimChecks::default(),
        audit: TruthAudit::default(),
        baseline_audit: TruthAudit::default(),
    };

    // Agents.
    for i in 0..s.vehicles.len() {
        let est = sim.vehicles[i].initial_estimate();
        let agent = sim.vehicle_agent(i, &est, 0)?;
        sim.nodes.insert(
            NodeId(s.vehicles[i].id),
            Node {
                name: s.vehicles[i].display_name(),
                agent: Some(Agent::Vehicle(Box::new(agent))),
                links: BTreeMap::new(),
                restarts: 0,
                compression: s.fusion.delta_compression,
                send_failures: crate::agent::Rejections::default(),
            },
        );
    }
    if s.fusion.mode == FusionMode::Central {
        let hub_id = NodeId(s.fusion.hub_id);
        let hub = HubAgent::new(
            hub_id,
            epoch_for(s.world.seed, s.fusion.hub_id, 0),
            world.map_origin(),
            &topology(s)?,
            s.fusion.ddf_config(),
        )
        .map_err(|e| SimError::Agent {
            node: "hub".into(),
            source: AgentError::Ddf(e),
        })?;
        sim.nodes.insert(
            hub_id,
            Node {
                name: "hub".into(),
                agent: Some(Agent::Hub(Box::new(hub))),
                links: BTreeMap::new(),
                restarts: 0,
                compression: s.fusion.delta_compression,
                send_failures: crate::agent::Rejections::default(),
            },
        );
    }

    // The simulated network: each end's inbound direction through the fault layer.
    for (li, l) in effective_links(s).iter().enumerate() {
        let label = l.label(&names);
        let (la, lb) = InMemoryHub::pair(l.a, l.b);
        let seed =
            |end: u64| world::vehicle_seed(s.world.seed ^ 0xfa017, (li as u32) << 1 | end as u32);
        let wrap = |inner: InMemoryLink, end: u64| {
            let cfg = l.fault_config(s, seed(end)).map_err(|e| SimError::Link {
                link: label.clone(),
                reason: e.to_string(),
            })?;
            FaultyLink::new(inner, cfg, dyn_clock.clone()).map_err(|e| SimError::Link {
                link: label.clone(),
                reason: e.to_string(),
            })
        };
        let fa = wrap(la, 0)?;
        let fb = wrap(lb, 1)?;
        sim.nodes
            .get_mut(&NodeId(l.a))
            .expect("validated")
            .links
            .insert(NodeId(l.b), fa);
        sim.nodes
            .get_mut(&NodeId(l.b))
            .expect("validated")
            .links
            .insert(NodeId(l.a), fb);
        sim.links.push((
            NodeId(l.a),
            NodeId(l.b),
            LinkRecord {
                a: names[&l.a].clone(),
                b: names[&l.b].clone(),
                transport: "sim".into(),
                naive_bytes: 0,
                ci: false,
                samples: Vec::new(),
            },
        ));
    }

    // The centralized all-data reference EKF.
    if with_baseline {
        let setups = crate::baseline::reference_setups(s, &sim.vehicles);
        // The reference associates by descriptor, verified by the gate (shared with the
        // monitor of multi-process runs).
        sim.baseline = Some(
            crate::baseline::reference_filter(s, &world, &setups).map_err(SimError::Baseline)?,
        );
    }

    // Events: crash/restart/hub loss in time order.
    let mut pending: Vec<(f64, usize, bool)> = Vec::new(); // (time, event index, is_restart)
    let mut events = Vec::new();
    for l in effective_links(s) {
        for w in &l.faults.outages {
            events.push(EventRecord {
                t: w[0],
                until: Some(w[1].min(duration)),
                kind: "outage".into(),
                subject: l.label(&names),
            });
        }
    }
    for p in &s.partitions {
        let side: Vec<String> = p
            .side
            .iter()
            .map(|id| names.get(id).cloned().unwrap_or_default())
            .collect();
        events.push(EventRecord {
            t: p.start_s,
            until: Some(p.end_s.min(duration)),
            kind: "partition".into(),
            subject: side.join("+"),
        });
    }
    for (i, e) in s.events.iter().enumerate() {
        pending.push((e.at_s, i, false));
        if let Some(r) = e.restart_after_s {
            pending.push((e.at_s + r, i, true));
        }
    }
    pending.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut pending = pending.into_iter().peekable();

    let round_dt = 1.0 / s.fusion.rate_hz;
    let mut next_round = round_dt;
    let record_dt = s.run.record_interval_s;
    let mut next_record = 0.0;
    let poll_dt = 0.01;
    let mut next_poll = poll_dt;
    let mut next_progress = 1.0;
    let eps = 1e-9;
    sim.record(0.0);
    next_record += record_dt;

    loop {
        if opts
            .stop
            .as_ref()
            .is_some_and(|f| f.load(Ordering::Relaxed))
        {
            break;
        }
        // The vehicle whose next sample is earliest (a replayed log may end before the run).
        let Some((vi, t)) = sim
            .vehicles
            .iter()
            .enumerate()
            .filter_map(|(i, v)| v.next_time().map(|t| (i, t)))
            .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
        else {
            break;
        };
        if t > duration + eps {
            break;
        }
        while next_round <= t + eps {
            sim.clock.set(next_round);
            sim.poll_network(next_round);
            sim.round(next_round);
            next_round += round_dt;
        }
        while pending.peek().is_some_and(|p| p.0 <= t + eps) {
            let (at, ei, restart) = pending.next().expect("peeked");
            sim.clock.set(at);
            let e = &s.events[ei];
            let target = match e.kind {
                EventKind::Crash => NodeId(e.vehicle.expect("validated")),
                EventKind::HubLoss => NodeId(s.fusion.hub_id),
            };
            let label = sim
                .nodes
                .get(&target)
                .map(|n| n.name.clone())
                .unwrap_or_default();
            let neighbours: Vec<NodeId> = sim
                .nodes
                .get(&target)
                .map(|n| n.links.keys().copied().collect())
                .unwrap_or_default();
            if restart {
                let idx = s
                    .vehicles
                    .iter()
                    .position(|v| NodeId(v.id) == target)
                    .expect("validated");
                let node = sim.nodes.get_mut(&target).expect("exists");
                node.restarts += 1;
                let inc = node.restarts;
                // Replayed vehicles cannot restart (scenario validation).
                let Some(est) = sim.vehicles[idx].restart_estimate(u64::from(inc)) else {
                    continue;
                };
                // The reference gets the same external fix, so it still holds all the data.
                if let Some(b) = sim.baseline.as_mut()
                    && let Some(fix) = sim.vehicles[idx].reference_restart_estimate(u64::from(inc))
                {
                    let _ = crate::baseline::apply_restart_fix(b, idx, &fix);
                }
                let agent = sim.vehicle_agent(idx, &est, inc)?;
                sim.nodes.get_mut(&target).expect("exists").agent =
                    Some(Agent::Vehicle(Box::new(agent)));
                sim.records[idx].restarts += 1;
                events.push(EventRecord {
                    t: at,
                    until: None,
                    kind: "restart".into(),
                    subject: label,
                });
                for n in neighbours {
                    for (x, y) in [(target, n), (n, target)] {
                        if let Some(node) = sim.nodes.get_mut(&x) {
                            let out = node.on_link(at, y, true);
                            node.send(at, out);
                        }
                    }
                }
            } else {
                if let Some(node) = sim.nodes.get_mut(&target) {
                    node.agent = None;
                }
                let until = e.restart_after_s.map(|r| at + r);
                let kind = if e.kind == EventKind::HubLoss {
                    "hub-loss"
                } else {
                    "crash"
                };
                events.push(EventRecord {
                    t: at,
                    until,
                    kind: kind.into(),
                    subject: label,
                });
                for n in neighbours {
                    if let Some(node) = sim.nodes.get_mut(&n) {
                        let out = node.on_link(at, target, false);
                        node.send(at, out);
                    }
                }
            }
        }
        sim.clock.set(t);
        let id = NodeId(s.vehicles[vi].id);
        let Some(out) = sim.vehicles[vi].step() else {
            continue;
        };
        if let Some(Agent::Vehicle(a)) = sim.nodes.get_mut(&id).and_then(|n| n.agent.as_mut()) {
            if a.on_imu(&out.imu).is_err() {
                sim.checks.inputs_rejected += 1;
            }
            if let Some((frame, true_ids)) = &out.frame {
                if a.is_sharing()
                    && let Some(ids) = true_ids
                {
                    sim.frame_truth
                        .insert((id.0, frame.time.to_bits()), ids.clone());
                }
                match a.on_frame(frame) {
                    Ok(report) => {
                        sim.audit.frame(
                            id.0,
                            &FrameAssociations::from_report(frame.time, &report),
                            true_ids.as_deref(),
                        );
                        sim.records[vi].observations += frame.observations.len() as u64;
                    }
                    Err(_) => sim.checks.inputs_rejected += 1,
                }
            }
        }
        if let Some(b) = sim.baseline.as_mut() {
            let _ = b.predict(vi, &out.imu);
            if let Some((frame, true_ids)) = &out.frame {
                // With appearance the reference still associates by the true ids.
                let perfect = match true_ids {
                    Some(ids) if s.world.appearance.identity == Identity::Appearance => {
                        Some(world::with_true_ids(frame, ids))
                    }
                    _ => None,
                };
                if let Ok(report) = b.process_frame(vi, perfect.as_ref().unwrap_or(frame)) {
                    sim.baseline_audit.frame(
                        id.0,
                        &FrameAssociations::from_report(frame.time, &report),
                        true_ids.as_deref(),
                    );
                    sim.baseline_records[vi].observations += frame.observations.len() as u64;
                }
            }
        }
        if t + eps >= next_poll {
            sim.poll_network(t);
            next_poll += poll_dt;
        }
        // Time reached by every source that still has data (an ended log holds no one back).
        let tmin = sim
            .vehicles
            .iter()
            .filter(|v| v.next_time().is_some())
            .map(SensorSource::time)
            .fold(f64::INFINITY, f64::min);
        let tmin = if tmin.is_finite() { tmin } else { t };
        if tmin + eps >= next_record {
            sim.record(tmin);
            next_record += record_dt;
        }
        if tmin >= next_progress {
            if let Some(p) = opts.progress.as_mut() {
                p(tmin, duration);
            }
            next_progress += 1.0;
        }
    }

    // Final maps and counters.
    for node in sim.nodes.values_mut() {
        if let Some(Agent::Vehicle(a)) = node.agent.as_mut() {
            a.flush_fusion();
        }
    }
    let end = sim
        .vehicles
        .iter()
        .map(|v| v.time())
        .fold(f64::INFINITY, f64::min);
    let have_truth = crate::metrics::maps_have_truth(s);
    for cfg in &s.vehicles {
        if let Some(Agent::Vehicle(a)) = sim
            .nodes
            .get(&NodeId(cfg.id))
            .and_then(|n| n.agent.as_ref())
        {
            sim.audit.set_merges(cfg.id, a.merges());
        }
    }
    let truth = sim.audit.finish();
    let key_truth = |k| if have_truth { truth.truth(k) } else { None };
    for (i, cfg) in s.vehicles.iter().enumerate() {
        if let Some(node) = sim.nodes.get(&NodeId(cfg.id))
            && let Some(Agent::Vehicle(a)) = node.agent.as_ref()
        {
            let frame = sim.launch_from(a.frame_owner());
            let mut map = map_records_in(&world, &frame, a.filter(), key_truth);
            sim.held[i].stamp(end, &mut map);
            sim.records[i].map = map;
            let c = a.counters();
            sim.records[i].rejected_messages = c.fusion.messages_rejected;
            let mut rejections = a.rejections();
            rejections.merge(&node.send_failures.counts);
            sim.records[i].rejections = rejections.counts;
            sim.records[i].frame_alignment = a.team_frame().map(|tf| {
                // The true own → team frame: own → launch, then launch → the root's own.
                let truth = sim
                    .launch_from(Some(tf.root()))
                    .inverse()
                    .compose(&sim.launch_from(Some(NodeId(cfg.id))));
                crate::frames::alignment_record(&tf.report(), &truth)
            });
            sim.records[i].association.merges_refused =
                a.ddf().map_or(0, |d| d.stats().merges_refused);
            sim.checks
                .rejected_messages
                .insert(node.name.clone(), c.fusion.messages_rejected);
            sim.checks.fuse_refused += c.fusion.fuse_refused;
            if let Some(d) = a.ddf() {
                for ch in d.channels() {
                    let peer = names
                        .get(&ch.peer.0)
                        .cloned()
                        .unwrap_or_else(|| ch.peer.to_string());
                    sim.checks
                        .link_ends
                        .push((node.name.clone(), peer, ch.stats));
                }
            }
        }
        fill_record(&truth, cfg.id, &mut sim.records[i], end);
    }
    if let Some(b) = &sim.baseline {
        let reference = sim.baseline_audit.finish();
        let mut map = map_records(&world, b, |k| {
            if have_truth { reference.truth(k) } else { None }
        });
        sim.baseline_held.stamp(end, &mut map);
        for (r, cfg) in sim.baseline_records.iter_mut().zip(&s.vehicles) {
            r.map = map.clone();
            fill_record(&reference, cfg.id, r, end);
        }
    }
    let mut record = RunRecord {
        scenario: s.run.name.clone().unwrap_or_else(|| "scenario".into()),
        mode: s.fusion.mode.to_string(),
        frame: world.frame().to_string(),
        seed: s.world.seed,
        duration: end.min(duration),
        wall_time: started.elapsed().as_secs_f64(),
        vehicles: std::mem::take(&mut sim.records),
        links: sim.links.drain(..).map(|l| l.2).collect(),
        events,
        baseline: with_baseline.then(|| std::mem::take(&mut sim.baseline_records)),
        truth_features: truth_features(s, &world),
        time_origin_ns: s.run.time_origin_ns,
        team_wrong_merges: truth.team_wrong_merges(),
        identity: s.world.appearance.identity.to_string(),
        router_access_refused: Default::default(),
    };
    record.events.sort_by(|a, b| a.t.total_cmp(&b.t));
    Ok(SimOutcome {
        record,
        checks: sim.checks,
    })
}

/// True feature positions for the map plot: the world's features when some vehicle is
/// simulated, none when every vehicle is replayed (the simulated world then has nothing to do
/// with what the vehicles saw).
pub fn truth_features(s: &Scenario, world: &World) -> Vec<(u64, [f64; 3])> {
    if s.vehicles.iter().all(|v| v.replay.is_some()) {
        return Vec::new();
    }
    world
        .features()
        .iter()
        .map(|f| (f.id, [f.position_ned.x, f.position_ned.y, f.position_ned.z]))
        .collect()
}
