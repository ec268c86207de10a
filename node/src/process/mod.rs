//! The multi-process system: `canopy run` launches a world process, one process per vehicle
//! and, in central mode, the hub, and monitors them; each of those runs one of the roles here.
//!
//! # Layout
//! - [`protocol`]: message bodies between the processes (sensor stream, flow control, reports,
//!   control), validated on receipt.
//! - [`world`]: the world process — steps the simulator (or replays logs) in simulation time and
//!   streams each vehicle's IMU samples and frames over iceoryx2, paced by flow control.
//! - [`vehicle`]: the vehicle process — a [`crate::agent::VehicleEstimator`] fed by the
//!   stream, fusing over its configured links (iceoryx2 or zenoh, behind the fault layer on the
//!   vehicle's simulation clock), reporting estimates and maps to the monitor.
//! - `fusion_thread`: the vehicle's [`crate::agent::VehicleFusion`] on its own thread, fusing
//!   rounds on lent copies of the filter, so that fusion never holds up IMU processing.
//! - [`hub`]: the hub of central mode — a [`crate::agent::HubAgent`] on world time.
//! - [`host`]: `canopy run --host NAME` — one host's share of a multi-host run, relaying its
//!   processes' reports to the monitor over zenoh.
//! - [`router`]: `canopy router` — the zenoh router of a multi-host run in client mode,
//!   enforcing the run's access control and reporting its refusals to the monitor.
//! - [`monitor`]: the launcher — spawns, paces events (crash, restart, hub loss), reaps, gathers
//!   reports into a [`crate::record::RunRecord`], runs the centralized reference, writes outputs.
//!
//! # Links of a run (all under one iceoryx2 prefix per run)
//! ```text
//!             ┌──────── monitor (MONITOR_ID) ────────┐   reports ↑, control ↓
//!             │                 │                     │
//!   world (WORLD_ID) ──stream──▶ vehicle i ◀──DDF──▶ vehicle j  (shm: iceoryx2, net: zenoh)
//!             └──────time──────▶ hub (central mode) ◀──DDF──┘
//! ```

mod fusion_thread;

/// This process's peak resident set size [bytes]: `VmHWM` of `/proc/self/status`; `None` where
/// the kernel does not report it (not Linux) or the line cannot be read.
pub fn peak_rss_bytes() -> Option<u64> {
    parse_vm_hwm(&std::fs::read_to_string("/proc/self/status").ok()?)
}

/// `VmHWM:  <n> kB` of a `/proc/<pid>/status` text, in bytes.
fn parse_vm_hwm(status: &str) -> Option<u64> {
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let mut parts = line["VmHWM:".len()..].split_whitespace();
    let kb: u64 = parts.next()?.parse().ok()?;
    (parts.next()? == "kB").then_some(kb * 1024)
}
pub(crate) mod delivery;
pub mod host;
pub mod hub;
pub mod monitor;
pub mod protocol;
pub mod router;
pub mod vehicle;
pub mod world;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result};
use canopy_fusion::ddf::{DdfMessage, Outgoing};
use canopy_transport::fault::{Clock, FaultyLink, ManualClock};
use canopy_transport::iceoryx::{IceoryxConfig, IceoryxLink};
use canopy_transport::link::{Link, LinkConfig, LinkEvent, PeerState};
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohTransport};
use canopy_transport::wire::Validate;
use canopy_transport::{MessageKind, NodeId, Received, SendMeta};
use clap::{Args, Subcommand};
use serde::Deserialize;

use crate::network::{TransportKind, effective_links};
use crate::scenario::Scenario;
use crate::wire::{WireOutgoing, decode_ddf};
use crate::world::vehicle_seed;

/// Environment variable carrying the team's zenoh password (`[secrets].zenoh_password`) to
/// child processes (kept out of files).
pub const ENV_ZENOH_PASSWORD: &str = "CANOPY_ZENOH_PASSWORD";

/// Largest body on a control link (reports, sensor batches): a map report of 16 MiB holds
/// ~200 000 features.
pub const CONTROL_MAX_BODY: u64 = 16 << 20;

/// `canopy role …`: the processes `canopy run` spawns (internal).
#[derive(Debug, Args)]
pub struct RoleArgs {
    /// Which role.
    #[command(subcommand)]
    pub role: Role,
}

/// Options every role takes.
#[derive(Debug, Args, Clone)]
pub struct RoleCommon {
    /// The run's resolved scenario file.
    #[arg(long)]
    pub scenario: PathBuf,
    /// The run's iceoryx2 prefix (also the zenoh key prefix of the fusion links unless
    /// `--net-prefix` is given).
    #[arg(long)]
    pub prefix: String,
    /// The zenoh key prefix of the fusion links (multi-host runs: the same on every host,
    /// whose iceoryx2 prefixes differ).
    #[arg(long)]
    pub net_prefix: Option<String>,
    /// Multi-host runs: this process belongs to `[[host]]` NAME (the world streams to that
    /// host's vehicles only).
    #[arg(long)]
    pub host: Option<String>,
}

impl RoleCommon {
    /// The zenoh key prefix of this run's fusion links.
    pub fn zenoh_prefix(&self) -> String {
        self.net_prefix
            .clone()
            .unwrap_or_else(|| zenoh_prefix(&self.prefix))
    }
}

/// The roles.
#[derive(Debug, Subcommand)]
pub enum Role {
    /// The world simulator / log player.
    World(RoleCommon),
    /// One vehicle.
    Vehicle {
        /// Common options.
        #[command(flatten)]
        common: RoleCommon,
        /// Vehicle id.
        #[arg(long)]
        id: u32,
        /// Process incarnation (0 = first start, then restarts).
        #[arg(long, default_value_t = 0)]
        incarnation: u32,
    },
    /// The hub of central mode.
    Hub(RoleCommon),
}

/// Runs a role (the body of `canopy role …`).
pub fn run_role(args: RoleArgs) -> Result<()> {
    init_child_process();
    match args.role {
        Role::World(c) => world::run(&c),
        Role::Vehicle {
            common,
            id,
            incarnation,
        } => vehicle::run(&common, id, incarnation),
        Role::Hub(c) => hub::run(&c),
    }
}

/// Child-process setup: die with the monitor (SIGTERM when it exits), log to stderr.
fn init_child_process() {
    #[cfg(target_os = "linux")]
    {
        let _ = nix::sys::prctl::set_pdeathsig(nix::sys::signal::Signal::SIGTERM);
    }
    crate::cli::init_tracing();
}

/// A flag set by SIGINT/SIGTERM (a child asked to stop by a signal finishes cleanly).
pub(crate) fn stop_flag() -> Arc<AtomicBool> {
    crate::cli::ctrl_c_flag()
}

/// Loads the run's resolved scenario.
pub(crate) fn load_resolved(c: &RoleCommon) -> Result<Scenario> {
    // The launcher validated it in full before writing it (`monitor::resolve`).
    let mut s = Scenario::load_prevalidated(&c.scenario)
        .with_context(|| format!("loading the run's scenario {}", c.scenario.display()))?;
    if let Ok(p) = std::env::var(ENV_ZENOH_PASSWORD) {
        s.secrets.zenoh_password = Some(p);
    }
    Ok(s)
}

/// An iceoryx2 link between this process and a non-fusion peer (world, monitor), with room for
/// `buffer` messages in flight per direction.
pub(crate) fn control_link(
    prefix: &str,
    local: NodeId,
    peer: NodeId,
    buffer: usize,
) -> Result<IceoryxLink> {
    let mut ix = IceoryxConfig::new(prefix);
    ix.subscriber_buffer = buffer.max(4);
    IceoryxLink::connect(
        LinkConfig::new(local, peer).with_max_body_len(CONTROL_MAX_BODY),
        ix,
    )
    .with_context(|| format!("opening the iceoryx2 link {local} -> {peer}"))
}

/// Sends a typed body. Delivery failures are counted by the link (datagram semantics).
pub(crate) fn send_body(
    link: &mut dyn Link,
    kind: MessageKind,
    seq: u64,
    time: f64,
    body: &impl serde::Serialize,
) -> Result<()> {
    link.send(&SendMeta::new(kind, seq, time), body)
        .context("sending on a control link")
}

/// Decodes a received typed body; `None` (counted as a body rejection) when invalid.
pub(crate) fn decode_body<B: for<'a> Deserialize<'a> + Validate>(m: &Received) -> Option<B> {
    m.decode::<B>().ok()
}

/// The controls waiting on `link` now (its peer events drained); bodies that fail to decode are
/// counted by the link.
pub(crate) fn controls(link: &mut dyn Link) -> Vec<protocol::Control> {
    let mut out = Vec::new();
    while link.poll_event().is_some() {}
    while let Ok(Some(m)) = link.try_recv() {
        if let Some(c) = decode_body::<protocol::Control>(&m) {
            out.push(c);
        }
    }
    out
}

/// Waits until `link` reports its peer up (or `timeout`, or `stop`).
pub(crate) fn wait_peer_up(link: &mut dyn Link, timeout: Duration, stop: &AtomicBool) -> bool {
    let deadline = std::time::Instant::now() + timeout;
    while std::time::Instant::now() < deadline && !stop.load(Ordering::Relaxed) {
        while link.poll_event().is_some() {}
        if link.peer_state() == PeerState::Up {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    false
}

/// A fusion link: iceoryx2 or zenoh under the fault layer on this process's simulation clock.
pub(crate) type FusionLink = FaultyLink<Box<dyn Link>>;

/// This process's fusion links (DDF neighbours), the zenoh session they share, and the
/// simulation clock of their fault layers.
pub(crate) struct FusionLinks {
    /// Links by neighbour.
    pub links: BTreeMap<NodeId, FusionLink>,
    /// Simulation clock of the fault layer.
    pub clock: Arc<ManualClock>,
    /// Compression of information-carrying messages (`[fusion] delta_compression`).
    compression: crate::wire::Compression,
    /// Messages a link refused to send (`link.send.<error>`: too large to encode, a backend
    /// failure), counted by reason and logged once; the DDF repairs the gap a lost delta leaves
    /// (Nack, Cumulative), these counts say why it had to. In the node's reported rejections.
    pub send_failures: crate::agent::Rejections,
    _zenoh: NetSessions,
}

impl std::fmt::Debug for FusionLinks {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FusionLinks")
            .field("peers", &self.links.keys().collect::<Vec<_>>())
            .finish_non_exhaustive()
    }
}

/// The zenoh sessions of a node's `net` links.
///
/// Without the team's password: one session, listening on the endpoints of the links whose end
/// `a` the node is and connecting to the others, neither authenticated nor access-controlled.
///
/// With it (`[secrets].zenoh_password`), the node's user is its name and it opens up to two
/// sessions, because zenoh's user/password check is one-way (only a listener learns who
/// connected, so only a session that does not connect can enforce rules by user):
/// - a **listening** session for its links as end `a`: it accepts every node of the team
///   (authentication = holding the team's password) and enforces access control by user,
///   default deny: the user of neighbour `b` may only publish on `link/b/me`, subscribe to
///   `link/me/b` and hold / watch the liveliness tokens of that link
///   (`ZenohAccess::for_links`). Any other publication or declaration — a non-neighbour, or a
///   neighbour forging another node's key — is refused by zenoh and counted
///   (`canopy_transport::access::refusals`, reported to the monitor);
/// - a **connecting** session for its links as end `b`, which listens nowhere: only the
///   listeners it connects to reach it, and each of them sends it only its own link's traffic
///   (their egress rules).
///
/// In client mode (`[zenoh].mode = "client"`, multi-host runs): one **client** session of the
/// router(s) in `[zenoh].connect` for every net link, listening nowhere and enforcing nothing;
/// with the team's password it authenticates as the node's user and the router enforces the
/// ACL of every link (`deploy::router_access`, `canopy router`).
struct NetSessions {
    /// The session serving links whose end `a` this node is (and, without a password, all).
    listening: Option<ZenohTransport>,
    /// With a password: the session serving links whose end `b` this node is.
    connecting: Option<ZenohTransport>,
}

impl NetSessions {
    fn open(
        s: &Scenario,
        c: &RoleCommon,
        me: NodeId,
        mine: &[(usize, crate::network::LinkSpec)],
        listen: Vec<String>,
        connect: Vec<String>,
    ) -> Result<Self> {
        use canopy_transport::access::{AclLink, ZenohAccess};
        let prefix = c.zenoh_prefix();
        let names = crate::network::node_names(s);
        let user = |id: NodeId| {
            names
                .get(&id)
                .cloned()
                .with_context(|| format!("node {id} has no name (zenoh user)"))
        };
        let me_user = user(me)?;
        let tls = s.zenoh.tls.as_ref().map(|t| t.for_user(&me_user));
        if c.host.is_some() && crate::deploy::client_mode(s) {
            // Through the router: one client session for every net link, listening nowhere;
            // the router authenticates it as this node's user and enforces the ACL.
            if !mine.iter().any(|(_, l)| l.transport == TransportKind::Net) {
                return Ok(Self {
                    listening: None,
                    connecting: None,
                });
            }
            let mut cfg = ZenohConfig::new(prefix, Vec::new(), s.zenoh.connect.clone());
            cfg.mode = canopy_transport::net::ZenohMode::Client;
            cfg.multicast_scouting = s.zenoh.multicast_scouting;
            cfg.auth = s.secrets.zenoh_password.clone().map(|password| ZenohAuth {
                user: me_user,
                password,
                accept: Vec::new(),
            });
            cfg.tls = tls;
            return Ok(Self {
                listening: None,
                connecting: Some(
                    ZenohTransport::open(me, cfg)
                        .context("opening the zenoh client session (through the router)")?,
                ),
            });
        }
        let Some(password) = s.secrets.zenoh_password.clone() else {
            if listen.is_empty() && connect.is_empty() {
                return Ok(Self {
                    listening: None,
                    connecting: None,
                });
            }
            let mut cfg = ZenohConfig::new(prefix, listen, connect);
            cfg.tls = tls;
            return Ok(Self {
                listening: Some(
                    ZenohTransport::open(me, cfg).context("opening the zenoh session")?,
                ),
                connecting: None,
            });
        };
        let listening = if listen.is_empty() {
            None
        } else {
            let acl: Vec<AclLink> = mine
                .iter()
                .filter(|(_, l)| l.transport == TransportKind::Net && l.a == me)
                .map(|(_, l)| {
                    Ok(AclLink {
                        user: user(l.b)?,
                        from: l.b,
                        to: me,
                    })
                })
                .collect::<Result<_>>()?;
            let mut cfg = ZenohConfig::new(prefix.clone(), listen, Vec::new());
            cfg.auth = Some(ZenohAuth {
                user: me_user.clone(),
                password: password.clone(),
                accept: names
                    .values()
                    .filter(|n| **n != me_user)
                    .map(|n| (n.clone(), password.clone()))
                    .collect(),
            });
            cfg.access = Some(ZenohAccess::for_links(&prefix, &acl));
            cfg.tls = tls.clone();
            Some(
                ZenohTransport::open(me, cfg)
                    .context("opening the listening zenoh session (access-controlled)")?,
            )
        };
        let connecting = if connect.is_empty() {
            None
        } else {
            let mut cfg = ZenohConfig::new(prefix, Vec::new(), connect);
            cfg.auth = Some(ZenohAuth {
                user: me_user,
                password,
                accept: Vec::new(),
            });
            cfg.tls = tls;
            Some(ZenohTransport::open(me, cfg).context("opening the connecting zenoh session")?)
        };
        Ok(Self {
            listening,
            connecting,
        })
    }

    /// The session of a link whose end `a` this node is (`as_a`) or not.
    fn for_link(&self, as_a: bool) -> Option<&ZenohTransport> {
        if as_a {
            self.listening.as_ref().or(self.connecting.as_ref())
        } else {
            self.connecting.as_ref().or(self.listening.as_ref())
        }
    }
}

/// What this process's zenoh access control has refused of other sessions so far, by
/// `"<action> on <key>"` ([`canopy_transport::access::refusals`], ingress only). Each new kind
/// of refusal is logged once, with its cause.
///
/// Egress refusals are left out: they are this node's own declarations withheld from a peer
/// not entitled to them — zenoh offers e.g. the liveliness token of each of a node's links to
/// every connected session, and the rules send it only to that link's neighbour — so they
/// occur in normal operation whenever a session serves two neighbours, and say nothing about
/// what a peer attempted.
pub(crate) fn access_refusals() -> BTreeMap<String, u64> {
    static LOGGED: std::sync::Mutex<std::collections::BTreeSet<String>> =
        std::sync::Mutex::new(std::collections::BTreeSet::new());
    let refused: BTreeMap<String, u64> = canopy_transport::access::refusals()
        .into_iter()
        .filter(|(what, _)| what.contains("(ingress)"))
        .collect();
    // A panic while logging cannot leave the set half-updated (one insert).
    let mut logged = LOGGED.lock().unwrap_or_else(|p| p.into_inner());
    for (what, n) in &refused {
        if logged.insert(what.clone()) {
            tracing::warn!(
                refused = %what,
                count = n,
                "zenoh access control refused a message: the session that sent it is not \
                 allowed that key (a non-neighbour, or a key of a link it is not part of); \
                 dropped and counted, logged once per key"
            );
        }
    }
    refused
}

/// The zenoh key prefix of a run.
pub(crate) fn zenoh_prefix(prefix: &str) -> String {
    format!("canopy/{prefix}")
}

impl FusionLinks {
    /// Opens the links of node `me` as configured in `s` (listen endpoints already resolved by
    /// the launcher). Fault schedules are in simulated seconds on `clock`.
    pub fn open(s: &Scenario, c: &RoleCommon, me: NodeId, incarnation: u32) -> Result<Self> {
        let prefix = c.prefix.as_str();
        let clock = Arc::new(ManualClock::new(0.0));
        let dyn_clock: Arc<dyn Clock> = clock.clone();
        let mine: Vec<(usize, crate::network::LinkSpec)> = effective_links(s)
            .into_iter()
            .enumerate()
            .filter(|(_, l)| l.a == me || l.b == me)
            .collect();
        let mut listen = Vec::new();
        let mut connect = Vec::new();
        // Through a router, no link has endpoints of its own.
        let through_router = c.host.is_some() && crate::deploy::client_mode(s);
        for (i, l) in &mine {
            if l.transport == TransportKind::Net && !through_router {
                let ep = l
                    .listen
                    .clone()
                    .with_context(|| format!("link[{i}] has no resolved listen endpoint"))?;
                if l.a == me {
                    listen.push(ep);
                } else {
                    connect.push(ep);
                }
            }
        }
        let sessions = NetSessions::open(s, c, me, &mine, listen, connect)?;
        let mut links = BTreeMap::new();
        for (li, l) in &mine {
            let (peer, end) = if l.a == me { (l.b, 0u32) } else { (l.a, 1u32) };
            let inner: Box<dyn Link> = match l.transport {
                TransportKind::Shm => Box::new(
                    IceoryxLink::connect(LinkConfig::new(me, peer), IceoryxConfig::new(prefix))
                        .with_context(|| format!("opening the iceoryx2 link {me}-{peer}"))?,
                ),
                TransportKind::Net => Box::new(
                    sessions
                        .for_link(l.a == me)
                        .context("no zenoh session for a net link")?
                        .link(peer, canopy_transport::codec::DEFAULT_MAX_BODY_LEN)
                        .with_context(|| format!("opening the zenoh link {me}-{peer}"))?,
                ),
            };
            // Same seeds as `canopy sim` for a first start; a restarted process draws anew.
            let seed = vehicle_seed(s.world.seed ^ 0xfa017, ((*li as u32) << 1) | end)
                ^ u64::from(incarnation).wrapping_mul(0x9e37_79b9_7f4a_7c15);
            let cfg = l
                .fault_config(s, seed)
                .with_context(|| format!("radio of link {me}-{peer}"))?;
            let faulty = FaultyLink::new(inner, cfg, dyn_clock.clone())
                .with_context(|| format!("fault layer of link {me}-{peer}"))?;
            links.insert(peer, faulty);
        }
        Ok(Self {
            links,
            clock,
            compression: s.fusion.delta_compression,
            send_failures: crate::agent::Rejections::default(),
            _zenoh: sessions,
        })
    }

    /// Sends DDF messages, each encoded just before it is sent. Undeliverable ones are counted
    /// by the link (no peer, full queue); ones a link refuses to send are counted here by
    /// reason ([`FusionLinks::send_failures`]); the DDF recovers from both.
    pub fn send(&mut self, now: f64, out: Vec<Outgoing>) {
        for o in out {
            let w = WireOutgoing::encode(&o, self.compression);
            drop(o);
            self.send_one(now, w);
        }
    }

    /// [`FusionLinks::send`] for messages encoded where they were formed (the vehicle's fusion
    /// thread); an encoding failure is counted like any refused send.
    pub fn send_wire(&mut self, now: f64, out: Vec<WireOutgoing>) {
        for w in out {
            self.send_one(now, w);
        }
    }

    fn send_one(&mut self, now: f64, w: WireOutgoing) {
        let link = self.links.get_mut(&w.to.0).map(|l| l as &mut dyn Link);
        send_counted(link, now, w, &mut self.send_failures);
    }

    /// Everything waiting on the links now: peer events and decoded DDF messages, per peer in
    /// arrival order (events first).
    pub fn poll(&mut self) -> Vec<(NodeId, Vec<LinkEvent>, Vec<DdfMessage>)> {
        self.poll_stamped()
            .into_iter()
            .map(|p| (p.peer, p.events, p.msgs.into_iter().map(|m| m.1).collect()))
            .collect()
    }

    /// [`FusionLinks::poll`] without decoding: the received messages as they came (their
    /// bytes, out of the links' buffers), to be decoded with [`decode_ddf`] where they are
    /// used.
    pub fn poll_raw(&mut self) -> Vec<(NodeId, Vec<LinkEvent>, Vec<Received>)> {
        let mut out = Vec::new();
        for (&peer, link) in &mut self.links {
            let mut events = Vec::new();
            while let Some(e) = link.poll_event() {
                events.push(e);
            }
            let mut msgs = Vec::new();
            while let Ok(Some(m)) = link.try_recv() {
                msgs.push(m);
            }
            if !events.is_empty() || !msgs.is_empty() {
                out.push((peer, events, msgs));
            }
        }
        out
    }

    /// [`FusionLinks::poll`] with each message's simulation time (its envelope's: the sender's
    /// time when it sent it) and each link's latest time marker
    /// ([`MessageKind::TIME_MARKER`], simulation-time delivery).
    pub fn poll_stamped(&mut self) -> Vec<Polled> {
        let mut out = Vec::new();
        for (&peer, link) in &mut self.links {
            let mut p = Polled {
                peer,
                events: Vec::new(),
                msgs: Vec::new(),
                marker: None,
            };
            while let Some(e) = link.poll_event() {
                p.events.push(e);
            }
            while let Ok(Some(m)) = link.try_recv() {
                let t = m.header().sim_time;
                if m.header().kind == MessageKind::TIME_MARKER {
                    p.marker = Some(p.marker.map_or(t, |x: f64| x.max(t)));
                // Bodies that fail to decode are counted by the link (`rejected.body`).
                } else if let Some(Ok(msg)) = decode_ddf(&m) {
                    p.msgs.push((t, msg));
                }
            }
            if !p.events.is_empty() || !p.msgs.is_empty() || p.marker.is_some() {
                out.push(p);
            }
        }
        out
    }

    /// Sends a time marker stamped `now` on every link (simulation-time delivery: everything
    /// this node stamps up to `now` has been sent). Undeliverable ones are counted by the link.
    pub fn send_marker(&mut self, now: f64) {
        for (&peer, link) in self.links.iter_mut() {
            if let Err(e) = link.send(&SendMeta::new(MessageKind::TIME_MARKER, 0, now), &()) {
                count_send_failure(&mut self.send_failures, peer, &e);
            }
        }
    }
}

/// Sends `w` over `link`, its neighbour's link (`None`: no link to it). A message the link
/// refuses (or that could not be encoded) is counted in `failures` by reason, `link.send.
/// <error>`, and one without a link as `link.send.no_link`, each logged once per reason;
/// undeliverable ones (no peer, full queue) are counted by the link itself.
pub(crate) fn send_counted(
    link: Option<&mut dyn Link>,
    now: f64,
    w: WireOutgoing,
    failures: &mut crate::agent::Rejections,
) {
    let peer = w.to.0;
    let Some(link) = link else {
        let e = format!("no link to node {peer}");
        failures.add("link.send.no_link".into(), 1, &e);
        return;
    };
    let sent = w
        .encoded
        .map_err(canopy_transport::link::LinkError::Encode)
        .and_then(|m| m.send(link, now));
    if let Err(e) = sent {
        count_send_failure(failures, peer, &e);
    }
}

/// Counts a message a link refused to send under `link.send.<error>` (logged once per reason).
fn count_send_failure(
    failures: &mut crate::agent::Rejections,
    peer: NodeId,
    e: &canopy_transport::link::LinkError,
) {
    let key = format!("link.send.{}", crate::agent::variant_key(&format!("{e:?}")));
    failures.add(key, 1, &format!("to node {peer}: {e}"));
}

/// What one fusion link delivered ([`FusionLinks::poll_stamped`]).
#[derive(Debug)]
pub(crate) struct Polled {
    /// The neighbour.
    pub peer: NodeId,
    /// Its link events, in order.
    pub events: Vec<LinkEvent>,
    /// Its DDF messages with their simulation times, in arrival order.
    pub msgs: Vec<(f64, DdfMessage)>,
    /// Its latest time marker, if one arrived.
    pub marker: Option<f64>,
}

/// The monitor-facing report of one fusion link.
pub(crate) fn link_report(
    peer: NodeId,
    link: &FusionLink,
    channel: Option<canopy_fusion::ddf::ChannelView>,
    naive_bytes: u64,
) -> protocol::LinkReport {
    let st = link.stats();
    let fs = link.fault_stats();
    protocol::LinkReport {
        peer,
        sent_messages: st.sent_messages,
        sent_bytes: st.sent_bytes,
        received_messages: st.received_messages,
        received_bytes: st.received_bytes,
        dropped_send: st.dropped_no_peer + st.dropped_overflow,
        dropped_faults: fs.dropped(),
        rejected_transport: st.rejected.total(),
        rejected_channel: channel.map_or(0, |c| c.stats.rejected),
        up: link.peer_state() == PeerState::Up,
        ci: channel.is_some_and(|c| c.mode == canopy_fusion::ddf::LinkMode::Ci),
        channel: channel.map(|c| c.stats).unwrap_or_default(),
        naive_bytes,
    }
}

/// Bytes of one naive round from a node holding `features` features: its whole map information
/// (Y, y) as dense f64 (the reference of the bandwidth ratio, as in `canopy sim`).
pub(crate) fn naive_round_bytes(features: usize) -> u64 {
    let n = features as u64;
    8 * (9 * n * n + 3 * n)
}

/// A fresh random DDF epoch for this process start (never 0).
pub(crate) fn fresh_epoch() -> u64 {
    rand::random::<u64>() | 1
}

#[cfg(test)]
mod rss_tests {
    use super::*;

    /// `VmHWM` is read in kB and given in bytes; a status without it, or in another unit, gives
    /// none; on Linux this process's own figure is there and at least the 1 MB its test
    /// harness holds.
    #[test]
    fn peak_rss_reads_vm_hwm() {
        let status = "Name:\tcanopy\nVmPeak:\t  900 kB\nVmHWM:\t  2048 kB\nVmRSS:\t 1024 kB\n";
        assert_eq!(parse_vm_hwm(status), Some(2048 * 1024));
        assert_eq!(parse_vm_hwm("VmRSS:\t 1024 kB\n"), None);
        assert_eq!(parse_vm_hwm("VmHWM:\t 1024 MB\n"), None);
        if cfg!(target_os = "linux") {
            assert!(peak_rss_bytes().is_some_and(|b| b > 1 << 20));
        }
    }
}

#[cfg(test)]
mod send_tests {
    use super::*;
    use canopy_transport::memory::InMemoryHub;

    fn hello() -> Outgoing {
        Outgoing {
            to: canopy_fusion::topology::NodeId(2),
            message: crate::agent::test_hello(1),
        }
    }

    /// A message a link refuses to send (here: larger than the link's body limit of 4 bytes)
    /// and one for a node without a link are counted by reason (`link.send.<error>`), not
    /// dropped silently; what the link does send is not counted.
    #[test]
    fn refused_sends_are_counted_by_reason() {
        let hub = InMemoryHub::new();
        let mut tight = LinkConfig::new(1, 2);
        tight.max_body_len = 4;
        let clock = Arc::new(ManualClock::new(0.0));
        let faulty = |cfg: LinkConfig| {
            let inner: Box<dyn Link> = Box::new(hub.connect(cfg));
            FaultyLink::new(
                inner,
                canopy_transport::fault::FaultConfig::none(1),
                clock.clone(),
            )
            .expect("no faults")
        };
        let mut links = FusionLinks {
            links: BTreeMap::from([(2, faulty(tight))]),
            clock: clock.clone(),
            compression: crate::wire::Compression::None,
            send_failures: crate::agent::Rejections::default(),
            _zenoh: NetSessions {
                listening: None,
                connecting: None,
            },
        };
        let mut to_nobody = hello();
        to_nobody.to = canopy_fusion::topology::NodeId(9);
        links.send(0.0, vec![hello(), hello(), to_nobody]);
        links.send_marker(0.0);
        let counts = &links.send_failures.counts;
        let too_large: u64 = counts
            .iter()
            .filter(|(k, _)| k.starts_with("link.send.encode"))
            .map(|(_, v)| v)
            .sum();
        assert_eq!(too_large, 2, "{counts:?}");
        assert_eq!(counts.get("link.send.no_link"), Some(&1), "{counts:?}");
        // The time marker has an empty body: it fits, and is not counted.
        assert_eq!(counts.values().sum::<u64>(), 3, "{counts:?}");
    }
}
