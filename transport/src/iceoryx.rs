//! iceoryx2 backend: same-host links between processes over zero-copy shared memory.
//!
//! Per link and direction `a → b` there are two iceoryx2 services:
//! - `canopy/link/{a}-{b}/data`: publish-subscribe of dynamic `[u8]` slices. The publisher
//!   measures the encoded size, loans an uninitialised sample of exactly that length and the
//!   codec encodes header and body straight into it (no intermediate heap copy); the subscriber
//!   decodes straight from the received sample, which the [`Received`] guard keeps borrowed
//!   (while the application holds `max_borrowed - 1` samples, further messages arrive as
//!   owned copies, so `receive` never runs out of loans).
//! - `canopy/link/{a}-{b}/wake`: an event service; the sender notifies after each sample so a
//!   receiver blocked in [`Link::recv_timeout`] wakes up without polling.
//!
//! Isolation: every resource lives under the iceoryx2 global prefix `"{run_prefix}_"`, so
//! parallel runs and tests with distinct prefixes never see each other.
//!
//! Stale resources: each link creates its own iceoryx2 node named `canopy-{local}-{peer}`; the
//! first link a process opens under a run prefix removes what crashed processes left behind
//! (`try_cleanup_dead_nodes`: node monitors, ports, connections), and a link that sees its
//! peer die cleans that node. iceoryx2's own cleanup on every node creation and service open
//! is off: each lists every node of the run (O(nodes²) to start a team).
//!
//! Peer liveness: the peer is up while the incoming data service has a publisher port named
//! `n{peer}` whose iceoryx2 node also subscribes to our outgoing data service and is alive
//! (iceoryx2's process monitor: a crashed process is reported dead at once). The check runs at
//! most every `liveness_interval`, from [`Link::poll_event`] and the receive calls; a dead
//! peer's ports are cleaned on detection.
//!
//! Cost: the port lists are shared-memory reads; the node's state is read from its own
//! monitor (one file-lock query, the monitor kept open while the candidate stays the same).
//! `iceoryx2::Node::state_of` is *not* used on the hot path: it lists every node of the run
//! and parses each node's TOML details file until it finds the one asked for, which made the
//! check O(nodes) and dominated the CPU of a multi-process run (see docs/benchmarks.md). It is
//! used only to clean a node found dead (rare). A hung but living peer process is *not* detected (use
//! application heartbeats for that).
//!
//! Memory: the publisher preallocates `max_subscribers × (buffer + max_borrowed) + history +
//! max_loaned` samples of `HEADER_LEN + max_body_len` bytes; `AllocationStrategy::PowerOfTwo`
//! lets it grow beyond that if a larger limit is configured later. Shared memory on Linux
//! (tmpfs) only commits the pages that are written.
//!
//! Delivery: safe overflow is off and the publisher discards a sample for a subscriber whose
//! buffer is full; such drops are counted as `dropped_overflow` (sender side).

use std::mem::MaybeUninit;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use iceoryx2::identifiers::UniqueNodeId;
use iceoryx2::port::listener::{Listener, ListenerWaitError};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2_cal::monitoring::{
    Monitoring, MonitoringBuilder, MonitoringMonitor, NamedConceptBuilder, NamedConceptMgmt,
    State as MonitorState,
};
use iceoryx2_cal::named_concept::NamedConceptConfiguration;

use crate::codec::{self, WireBody};
use crate::envelope::{HEADER_LEN, NodeId, SendMeta};
use crate::link::{
    Link, LinkConfig, LinkError, LinkEvent, LinkStats, MessageBytes, PeerState, PeerTracker,
    Received, StatsCell, admit,
};

type Svc = ipc_threadsafe::Service;
type PubSub = iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, [u8], ()>;
type EventSvc = iceoryx2::service::port_factory::event::PortFactory<Svc>;
/// iceoryx2's node monitoring concept for [`Svc`] (a file lock per node).
type NodeMonitoring = <Svc as iceoryx2::service::Service>::Monitoring;
type NodeMonitor = <NodeMonitoring as Monitoring>::Monitor;

const BACKEND: &str = "iceoryx2";

/// iceoryx2-specific options.
#[derive(Debug, Clone, PartialEq)]
pub struct IceoryxConfig {
    /// Per-run prefix (letters, digits, `_`, `-`); both ends of a link must use the same one.
    pub run_prefix: String,
    /// Samples a subscriber can hold before the publisher discards (per direction).
    pub subscriber_buffer: usize,
    /// Samples the subscriber may lend at once. The link lends the application at most
    /// `max_borrowed - 1` samples as zero-copy [`Received`] guards (one stays free so the next
    /// receive can proceed); messages received while that many are held arrive as owned copies.
    pub max_borrowed: usize,
    /// Publishers per direction service: the peer, plus headroom for a restarting peer or a
    /// diagnostic tool (and the intruder in the conformance tests).
    pub max_publishers: usize,
    /// Subscribers per direction service (the peer, plus headroom for a restarting peer).
    pub max_subscribers: usize,
    /// iceoryx2 nodes per service (default iceoryx2 limit is 20; a link needs 2).
    pub max_nodes: usize,
    /// How often (at most) peer liveness is re-checked.
    pub liveness_interval: Duration,
}

impl IceoryxConfig {
    /// Defaults under the given run prefix.
    pub fn new(run_prefix: impl Into<String>) -> Self {
        Self {
            run_prefix: run_prefix.into(),
            subscriber_buffer: 16,
            max_borrowed: 4,
            max_publishers: 3,
            max_subscribers: 2,
            max_nodes: 8,
            liveness_interval: Duration::from_millis(50),
        }
    }
}

/// A unique-enough prefix for one run: `canopy{pid}x{nanos}`.
pub fn unique_run_prefix() -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0);
    format!("canopy{}x{:x}", std::process::id(), nanos)
}

fn err(e: impl std::fmt::Debug) -> LinkError {
    LinkError::backend(BACKEND, format!("{e:?}"))
}

fn iox_config(prefix: &str) -> Result<Config, LinkError> {
    if prefix.is_empty()
        || !prefix
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
    {
        return Err(LinkError::Config(format!(
            "iceoryx2 run prefix {prefix:?} must be non-empty [A-Za-z0-9_-]"
        )));
    }
    let mut cfg = Config::default();
    cfg.global.prefix = FileName::new(format!("{prefix}_").as_bytes())
        .map_err(|e| LinkError::Config(format!("iceoryx2 prefix: {e:?}")))?;
    if let Some(root) = tmpfs_root() {
        cfg.global.set_root_path(root);
    }
    // Dead nodes are cleaned once per process and prefix (`create_node`), not on every node
    // creation and service open: each of those lists every node of the run and parses its
    // details file, which made starting a team O(nodes²) (6 listings per link).
    cfg.global.node.cleanup_dead_nodes_on_creation = false;
    cfg.global.node.cleanup_dead_nodes_on_destruction = false;
    cfg.global.service.cleanup_dead_nodes_on_open = false;
    Ok(cfg)
}

/// Where iceoryx2 keeps its node and service files: `/dev/shm/iceoryx2/` (tmpfs, beside the
/// shared-memory segments themselves) where `/dev/shm` is a directory, else iceoryx2's default
/// (`/tmp/iceoryx2/` on Linux). Starting a team creates a few files per link end (node details,
/// monitor, static service configs, event sockets); on an ext4 `/tmp` that had seen many files
/// come and go, inode allocation (`ext4_create` → `recently_deleted`) took ≈ 0.7 s of CPU to
/// start 24 vehicles (docs/benchmarks.md). Every process of a host derives the same root.
fn tmpfs_root() -> Option<&'static Path> {
    static ROOT: std::sync::OnceLock<Option<Path>> = std::sync::OnceLock::new();
    ROOT.get_or_init(|| {
        std::path::Path::new("/dev/shm")
            .is_dir()
            .then(|| Path::new(b"/dev/shm/iceoryx2/").ok())
            .flatten()
    })
    .as_ref()
}

/// Run prefixes whose dead nodes this process has cleaned ([`create_node`]).
static CLEANED_PREFIXES: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());

fn data_service_name(from: NodeId, to: NodeId) -> String {
    format!("canopy/link/{from}-{to}/data")
}
fn wake_service_name(from: NodeId, to: NodeId) -> String {
    format!("canopy/link/{from}-{to}/wake")
}
fn port_name(node: NodeId) -> String {
    format!("n{node}")
}

/// Opens (or creates) the data and wake services of direction `from → to` with the settings
/// every participant must agree on.
fn open_direction(
    node: &Node<Svc>,
    ix: &IceoryxConfig,
    from: NodeId,
    to: NodeId,
) -> Result<(PubSub, EventSvc), LinkError> {
    let data = node
        .service_builder(&ServiceName::new(&data_service_name(from, to)).map_err(err)?)
        .publish_subscribe::<[u8]>()
        .max_publishers(ix.max_publishers)
        .max_subscribers(ix.max_subscribers)
        .max_nodes(ix.max_nodes)
        .history_size(0)
        .subscriber_max_buffer_size(ix.subscriber_buffer)
        .subscriber_max_borrowed_samples(ix.max_borrowed)
        .enable_safe_overflow(false)
        .open_or_create()
        .map_err(err)?;
    let wake = node
        .service_builder(&ServiceName::new(&wake_service_name(from, to)).map_err(err)?)
        .event()
        .max_notifiers(ix.max_publishers)
        .max_listeners(ix.max_subscribers)
        .max_nodes(ix.max_nodes)
        .open_or_create()
        .map_err(err)?;
    Ok((data, wake))
}

fn create_node(ix: &IceoryxConfig, name: &str) -> Result<Node<Svc>, LinkError> {
    let cfg = iox_config(&ix.run_prefix)?;
    let node = NodeBuilder::new()
        .name(&NodeName::new(name).map_err(err)?)
        .config(&cfg)
        // canopy handles SIGINT/SIGTERM itself (ctrlc in the node crate).
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Svc>()
        .map_err(err)?;
    // What crashed processes left behind (a restarted vehicle's predecessor) is removed by
    // the first link this process opens under the prefix, before it opens any service; a
    // peer that dies later is cleaned by the link that sees it die (`clean_dead`).
    let first = {
        let mut done = CLEANED_PREFIXES.lock().unwrap_or_else(|e| e.into_inner());
        let first = !done.contains(&ix.run_prefix);
        if first {
            done.push(ix.run_prefix.clone());
        }
        first
    };
    if first {
        let cleaned = node.try_cleanup_dead_nodes();
        if cleaned.cleanups > 0 || cleaned.failed_cleanups > 0 {
            tracing::info!(
                cleanups = cleaned.cleanups,
                failed = cleaned.failed_cleanups,
                "iceoryx2: removed stale resources of dead nodes"
            );
        }
    }
    Ok(node)
}

fn make_publisher(
    data: &PubSub,
    max_body_len: u64,
    name: NodeId,
) -> Result<Publisher<Svc, [u8], ()>, LinkError> {
    let max_len = usize::try_from(max_body_len)
        .map_err(|_| LinkError::Config("max_body_len does not fit in memory".into()))?
        .saturating_add(HEADER_LEN);
    data.publisher_builder()
        .name(&PortName::new(&port_name(name)).map_err(err)?)
        .initial_max_slice_len(max_len)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .max_loaned_samples(2)
        .backpressure_strategy(BackpressureStrategy::DiscardData)
        .create()
        .map_err(err)
}

/// A received sample lent to the application; counted in `lent` while it lives.
struct SampleBytes {
    sample: Sample<Svc, [u8], ()>,
    lent: Arc<AtomicUsize>,
}

impl SampleBytes {
    fn new(sample: Sample<Svc, [u8], ()>, lent: &Arc<AtomicUsize>) -> Self {
        lent.fetch_add(1, Ordering::Relaxed);
        Self {
            sample,
            lent: lent.clone(),
        }
    }
}

impl Drop for SampleBytes {
    fn drop(&mut self) {
        self.lent.fetch_sub(1, Ordering::Relaxed);
    }
}

impl MessageBytes for SampleBytes {
    fn bytes(&self) -> &[u8] {
        self.sample.payload()
    }
}

/// One endpoint of an iceoryx2 link.
pub struct IceoryxLink {
    cfg: LinkConfig,
    ix: IceoryxConfig,
    publisher: Publisher<Svc, [u8], ()>,
    notifier: Notifier<Svc>,
    subscriber: Subscriber<Svc, [u8], ()>,
    listener: Listener<Svc>,
    out_data: PubSub,
    in_data: PubSub,
    _out_wake: EventSvc,
    _in_wake: EventSvc,
    stats: Arc<StatsCell>,
    /// Samples lent to the application as [`Received`] guards right now.
    lent: Arc<AtomicUsize>,
    tracker: PeerTracker,
    last_liveness: Option<Instant>,
    /// A sample was taken since the last liveness check.
    heard_since_check: bool,
    iox_config: Config,
    /// Where iceoryx2 keeps the node monitors of this run.
    monitoring_config: <NodeMonitoring as NamedConceptMgmt>::Configuration,
    /// The monitor of the last candidate peer node (kept open between checks).
    peer_monitor: Option<(UniqueNodeId, NodeMonitor)>,
    node: Node<Svc>,
}

/// iceoryx2's node monitoring configuration under `cfg` (as iceoryx2 derives it internally:
/// global prefix, node monitor suffix, node directory).
fn node_monitoring_config(cfg: &Config) -> <NodeMonitoring as NamedConceptMgmt>::Configuration {
    <<NodeMonitoring as NamedConceptMgmt>::Configuration>::default()
        .prefix(&cfg.global.prefix)
        .suffix(&cfg.global.node.monitor_suffix)
        .path_hint(&cfg.global.node_dir())
}

impl std::fmt::Debug for IceoryxLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IceoryxLink")
            .field("cfg", &self.cfg)
            .field("ix", &self.ix)
            .finish_non_exhaustive()
    }
}

impl IceoryxLink {
    /// Opens this node's end of the link to `cfg.peer` under `ix.run_prefix`. The peer may come
    /// later (or restart): liveness and delivery follow it.
    pub fn connect(cfg: LinkConfig, ix: IceoryxConfig) -> Result<Self, LinkError> {
        let node = create_node(&ix, &format!("canopy-{}-{}", cfg.local, cfg.peer))?;
        let (out_data, out_wake) = open_direction(&node, &ix, cfg.local, cfg.peer)?;
        let (in_data, in_wake) = open_direction(&node, &ix, cfg.peer, cfg.local)?;
        // Receiving ports first: the peer takes our publisher as the sign that we are up, so
        // by then our subscriber must exist or its first messages would find nobody.
        let subscriber = in_data
            .subscriber_builder()
            .buffer_size(ix.subscriber_buffer)
            .create()
            .map_err(err)?;
        let listener = in_wake.listener_builder().create().map_err(err)?;
        let notifier = out_wake
            .notifier_builder()
            .name(&PortName::new(&port_name(cfg.local)).map_err(err)?)
            .create()
            .map_err(err)?;
        let publisher = make_publisher(&out_data, cfg.max_body_len, cfg.local)?;
        let iox_config = iox_config(&ix.run_prefix)?;
        let monitoring_config = node_monitoring_config(&iox_config);
        Ok(Self {
            cfg,
            ix,
            publisher,
            notifier,
            subscriber,
            listener,
            out_data,
            in_data,
            _out_wake: out_wake,
            _in_wake: in_wake,
            stats: StatsCell::new(),
            lent: Arc::new(AtomicUsize::new(0)),
            tracker: PeerTracker::new(),
            last_liveness: None,
            heard_since_check: false,
            iox_config,
            monitoring_config,
            peer_monitor: None,
            node,
        })
    }

    /// Re-checks peer liveness if the last check is older than `liveness_interval` (or `force`).
    fn check_liveness(&mut self, force: bool) {
        let now = Instant::now();
        if !force
            && self
                .last_liveness
                .is_some_and(|t| now.duration_since(t) < self.ix.liveness_interval)
        {
            return;
        }
        self.last_liveness = Some(now);
        let want = port_name(self.cfg.peer);
        let mut candidates = Vec::new();
        self.in_data.dynamic_config().list_publishers(|d| {
            if d.publisher_name.as_str() == want {
                candidates.push(d.node_id);
            }
            CallbackProgression::Continue
        });
        // The peer must also be subscribed to our direction (same iceoryx2 node), otherwise
        // what we send now would find nobody.
        let mut subscribed = Vec::new();
        self.out_data.dynamic_config().list_subscribers(|d| {
            subscribed.push(d.node_id);
            CallbackProgression::Continue
        });
        candidates.retain(|id| subscribed.contains(id));
        let mut present = None;
        // A sample from the peer node that is up since the last check shows it alive; its
        // monitor is read (two file opens and a lock query) only when nothing came or the
        // candidates changed. Death is still seen within one interval of the last sample.
        let heard = std::mem::take(&mut self.heard_since_check);
        if heard
            && let ([id], Some((known, _))) = (candidates.as_slice(), &self.peer_monitor)
            && id == known
            && self.tracker.state() == PeerState::Up
        {
            self.tracker
                .observe(Some(id.value() as u64 ^ (id.value() >> 64) as u64));
            return;
        }
        for id in candidates {
            match self.node_state(id) {
                MonitorState::Alive => {
                    present = Some(id.value() as u64 ^ (id.value() >> 64) as u64);
                }
                MonitorState::Dead => self.clean_dead(id),
                MonitorState::DoesNotExist => {}
            }
        }
        self.tracker.observe(present);
    }

    /// State of the node `id` from its monitor (one file-lock query). A node whose monitor
    /// cannot be opened or read counts as not existing (the next check retries).
    fn node_state(&mut self, id: UniqueNodeId) -> MonitorState {
        if self.peer_monitor.as_ref().is_none_or(|(m, _)| *m != id) {
            let name = match FileName::new(id.value().to_string().as_bytes()) {
                Ok(n) => n,
                Err(_) => return MonitorState::DoesNotExist,
            };
            match <NodeMonitoring as Monitoring>::Builder::new(&name)
                .config(&self.monitoring_config)
                .monitor()
            {
                Ok(m) => self.peer_monitor = Some((id, m)),
                Err(e) => {
                    tracing::debug!(error = ?e, "iceoryx2: cannot open a node monitor");
                    return MonitorState::DoesNotExist;
                }
            }
        }
        let Some((_, m)) = &self.peer_monitor else {
            return MonitorState::DoesNotExist;
        };
        m.state().unwrap_or(MonitorState::DoesNotExist)
    }

    /// Removes the stale resources of the dead node `id` (through iceoryx2's node listing,
    /// which is slow but only runs once per dead node).
    fn clean_dead(&mut self, id: UniqueNodeId) {
        if self.peer_monitor.as_ref().is_some_and(|(m, _)| *m == id) {
            self.peer_monitor = None;
        }
        if let Ok(Some(NodeState::Dead(view))) = Node::<Svc>::state_of(&self.iox_config, id) {
            tracing::info!(
                peer = self.cfg.peer,
                "iceoryx2: peer node is dead, cleaning"
            );
            if let Err(e) = view.try_remove_stale_resources() {
                tracing::warn!(error = ?e, "iceoryx2: stale resource cleanup failed");
            }
        }
    }

    fn take(&mut self) -> Result<Option<Received>, LinkError> {
        loop {
            let Some(sample) = self.subscriber.receive().map_err(err)? else {
                return Ok(None);
            };
            // Lend the sample itself (zero-copy) while that leaves one borrow free for the next
            // receive; otherwise copy it out and give the sample back at once, so holding any
            // number of guards never makes `receive` fail.
            let admitted = if self.lent.load(Ordering::Relaxed) + 1 < self.ix.max_borrowed {
                admit(SampleBytes::new(sample, &self.lent), &self.cfg, &self.stats)
            } else {
                admit(sample.payload().to_vec(), &self.cfg, &self.stats)
            };
            self.heard_since_check = true;
            if let Some(r) = admitted {
                return Ok(Some(r));
            }
        }
    }

    /// The iceoryx2 node of this link (e.g. for diagnostics).
    pub fn iceoryx_node(&self) -> &Node<Svc> {
        &self.node
    }
}

impl Link for IceoryxLink {
    fn local_id(&self) -> NodeId {
        self.cfg.local
    }
    fn peer_id(&self) -> NodeId {
        self.cfg.peer
    }

    fn send(&mut self, meta: &SendMeta, body: &dyn WireBody) -> Result<(), LinkError> {
        let body_len = codec::body_len(body)?;
        if body_len > self.cfg.max_body_len {
            return Err(codec::CodecError::TooLarge {
                len: body_len,
                max: self.cfg.max_body_len,
            }
            .into());
        }
        let total = HEADER_LEN + body_len as usize;
        let mut sample = self.publisher.loan_slice_uninit(total).map_err(err)?;
        let payload: &mut [MaybeUninit<u8>] = sample.payload_mut();
        let encoded = codec::encode_into_uninit(
            meta,
            self.cfg.local,
            body,
            body_len,
            self.cfg.max_body_len,
            payload,
        );
        #[allow(unsafe_code)]
        // SAFETY: `encode_into_uninit` initialises every element of the slice it is given — the
        // message, then a zero fill of the rest — on success and on error alike (see its docs),
        // and `payload` is the whole payload of the sample.
        let sample = unsafe { sample.assume_init() };
        encoded?;
        let delivered = sample.send().map_err(err)?;
        self.stats.on_sent(total);
        if delivered == 0 {
            if self.out_data.dynamic_config().number_of_subscribers() == 0 {
                self.stats.on_dropped_no_peer();
            } else {
                self.stats.on_dropped_overflow();
            }
        }
        // A failed wake-up only delays the receiver until its next timeout; not an error.
        if let Err(e) = self.notifier.notify() {
            tracing::debug!(error = ?e, "iceoryx2: notify failed");
        }
        Ok(())
    }

    fn try_recv(&mut self) -> Result<Option<Received>, LinkError> {
        self.check_liveness(false);
        self.take()
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        let deadline = Instant::now() + timeout;
        loop {
            self.check_liveness(false);
            if let Some(r) = self.take()? {
                return Ok(Some(r));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            // Wake on the peer's notification, or at least every liveness interval so peer
            // transitions are still noticed while waiting.
            let wait = (deadline - now).min(self.ix.liveness_interval);
            match self.listener.timed_wait(|_| {}, wait) {
                // A signal interrupted the wait (EINTR: the socket's receive timeout makes
                // Linux never restart it — SIGSTOP/SIGCONT, a debugger or profiler attaching,
                // the Ctrl-C handler whose flag the caller checks between waits): a spurious
                // wake-up, not a link failure. It ended a vehicle process before.
                Ok(_) | Err(ListenerWaitError::InterruptSignal) => {}
                Err(e) => return Err(err(e)),
            }
        }
    }

    fn poll_event(&mut self) -> Option<LinkEvent> {
        self.check_liveness(false);
        self.tracker.pop()
    }

    fn peer_state(&self) -> PeerState {
        self.tracker.state()
    }

    fn stats(&self) -> LinkStats {
        self.stats.snapshot()
    }
}

/// Raw access to one direction's data service, for tests and tools: publishes arbitrary bytes
/// (garbage, truncated or forged messages) as if they came over the link `from → to`.
pub struct IceoryxRawSender {
    publisher: Publisher<Svc, [u8], ()>,
    notifier: Notifier<Svc>,
    _data: PubSub,
    _wake: EventSvc,
    _node: Node<Svc>,
}

impl std::fmt::Debug for IceoryxRawSender {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IceoryxRawSender").finish_non_exhaustive()
    }
}

impl IceoryxRawSender {
    /// Opens the direction `from → to` under `ix.run_prefix` with a publisher named after
    /// `port_as` (use a node id other than `from` to act as an intruder).
    pub fn open(
        ix: &IceoryxConfig,
        from: NodeId,
        to: NodeId,
        port_as: NodeId,
        max_body_len: u64,
    ) -> Result<Self, LinkError> {
        let node = create_node(ix, &format!("canopy-raw-{from}-{to}"))?;
        let (data, wake) = open_direction(&node, ix, from, to)?;
        let publisher = make_publisher(&data, max_body_len, port_as)?;
        let notifier = wake.notifier_builder().create().map_err(err)?;
        Ok(Self {
            publisher,
            notifier,
            _data: data,
            _wake: wake,
            _node: node,
        })
    }

    /// Publishes `bytes` verbatim. Returns the number of subscribers reached.
    pub fn send_raw(&self, bytes: &[u8]) -> Result<usize, LinkError> {
        let sample = self.publisher.loan_slice_uninit(bytes.len()).map_err(err)?;
        let n = sample.write_from_slice(bytes).send().map_err(err)?;
        let _ = self.notifier.notify();
        Ok(n)
    }
}

/// Removes what iceoryx2 keeps per prefix after the last node of a run is gone: the resources
/// of nodes whose process was killed (nodes do not clean dead ones when they end, see
/// [`iox_config`]) and a 16-byte global management segment in `/dev/shm`. Call it once a run
/// is over and none of its processes is alive (the launcher, or a test); returns the number of
/// `/dev/shm` files removed.
pub fn remove_run_leftovers(run_prefix: &str) -> usize {
    if let Ok(cfg) = iox_config(run_prefix) {
        let listed = Node::<Svc>::list(&cfg, |state| {
            if let NodeState::Dead(view) = state
                && let Err(e) = view.try_remove_stale_resources()
            {
                tracing::warn!(error = ?e, "iceoryx2: stale resource cleanup failed");
            }
            CallbackProgression::Continue
        });
        if let Err(e) = listed {
            tracing::debug!(error = ?e, "iceoryx2: cannot list the run's nodes");
        }
    }
    let Ok(dir) = std::fs::read_dir("/dev/shm") else {
        return 0;
    };
    let want = format!("{run_prefix}_");
    dir.filter_map(Result::ok)
        .filter(|e| e.file_name().to_string_lossy().starts_with(&want))
        .filter(|e| std::fs::remove_file(e.path()).is_ok())
        .count()
}
