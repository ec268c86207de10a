//! zenoh backend: links between hosts (zenoh 1.10, `transport_tcp`, `transport_tls` +
//! `auth_usrpwd`).
//!
//! One [`ZenohTransport`] per process = one zenoh session in **peer** mode with explicit
//! `listen` / `connect` endpoints (those of the node's configured links), multicast scouting and
//! gossip disabled — so the session only ever talks to the configured neighbours and the network
//! stays the configured tree (peers do not relay; multi-hop propagation is the DDF's job) — or
//! in **client** mode, connected only to the zenoh router(s) in `connect`, which route between
//! the clients and enforce the access control ([`ZenohMode`]; a **router** is a session in
//! router mode that only listens).
//! [`ZenohTransport::link`] then opens one [`ZenohLink`] per neighbour:
//! - data `a → b` is published on `{prefix}/link/{a}/{b}` with `CongestionControl::Block`
//!   (the default `Drop` loses fragments of large messages) over zenoh's default reliable
//!   channel; `b`
//!   subscribes to it and queues samples (bounded; a full queue holds zenoh's receive task for
//!   up to `overflow_wait`, slowing the sender through TCP, before it drops) for the
//!   synchronous receive calls;
//! - liveliness: each link declares the token `{prefix}/alive/{a}/{b}` *after* its subscriber,
//!   and watches `{prefix}/alive/{b}/{a}` with history: `Put` = peer up, `Delete` = peer down
//!   (session closed, process died, or transport lease expired).
//!
//! Runtime: the session runs on zenoh's own multi-thread tokio runtime (zenoh-runtime);
//! this backend calls zenoh's synchronous `Wait` API, so callers stay synchronous. Do not call it
//! from inside a *current-thread* tokio runtime. Sessions are closed with `close()` on
//! [`ZenohTransport::close`] or drop.
//!
//! Access control: with [`ZenohAuth`] set, the session uses zenoh's user/password handshake
//! (`transport/auth/usrpwd`): connecting peers must present a user and password listed in the
//! dictionary, otherwise the transport is refused before any message flows. See
//! `docs/arch/transport.md` for the limits (no encryption on plain TCP, one-way check).
//!
//! TLS: with [`ZenohTls`] every link is TLS (`tls/` endpoints), encrypted and mutually
//! authenticated against the team's CA (each node presents its own certificate).

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::time::Duration;

use zenoh::Wait;
use zenoh::bytes::ZBytes;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;
use zenoh::{Config, Session};

use crate::access::{ZenohAccess, json_list, json_str};
use crate::codec::{self, WireBody};
use crate::envelope::{NodeId, SendMeta};
use crate::link::{
    Link, LinkConfig, LinkError, LinkEvent, LinkStats, MessageBytes, PeerState, PeerTracker,
    Received, StatsCell, admit_with_crc,
};

const BACKEND: &str = "zenoh";

/// User/password authentication (zenoh `auth_usrpwd`).
#[derive(Clone, PartialEq, Eq)]
pub struct ZenohAuth {
    /// Credentials this node presents when it connects.
    pub user: String,
    /// Password this node presents when it connects.
    pub password: String,
    /// `(user, password)` pairs this node accepts from connecting peers.
    pub accept: Vec<(String, String)>,
}

impl std::fmt::Debug for ZenohAuth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohAuth")
            .field("user", &self.user)
            .field("password", &"***")
            .field(
                "accept",
                &self.accept.iter().map(|(u, _)| u).collect::<Vec<_>>(),
            )
            .finish()
    }
}

/// TLS on a session's links (zenoh `transport_tls`, rustls): every link is encrypted and
/// **mutually** authenticated against the team's certificate authority — the listener checks
/// the connecting node's certificate, the connecting node checks the listener's (and that it
/// names the address it dialled). Endpoints are then `tls/HOST:PORT`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ZenohTls {
    /// PEM certificate of the CA that signed every node's certificate.
    pub root_ca: PathBuf,
    /// PEM certificate of this node (signed by `root_ca`; its subject alternative names hold
    /// the addresses this node listens on).
    pub certificate: PathBuf,
    /// PEM (PKCS#8) private key of `certificate`.
    pub private_key: PathBuf,
}

/// zenoh-specific options of one process's session.
#[derive(Debug, Clone, PartialEq)]
pub struct ZenohConfig {
    /// Key prefix of the run (letters, digits, `_`, `-`, `/`); all nodes of a run share it.
    pub key_prefix: String,
    /// Endpoints to listen on, e.g. `tcp/127.0.0.1:7447` (`:0` picks a free port).
    pub listen: Vec<String>,
    /// Endpoints of neighbours to connect to (retried in the background until they answer).
    pub connect: Vec<String>,
    /// Optional user/password authentication.
    pub auth: Option<ZenohAuth>,
    /// Messages queued per link for the application. When the queue is full, zenoh's receive
    /// task waits up to `overflow_wait` for room (so a fast sender is slowed down through
    /// TCP, as zenoh's own FIFO handler does, instead of losing messages) and then drops the
    /// message (counted as overflow).
    pub receive_queue: usize,
    /// How long a message waits for room in a full receive queue before it is dropped. Kept far
    /// below `lease`: zenoh's receive task reads nothing else from that peer meanwhile.
    pub overflow_wait: Duration,
    /// Transport lease: a silent peer is declared lost after this long.
    pub lease: Duration,
    /// First reconnection delay to a `connect` endpoint (doubles up to 8×).
    pub reconnect_period: Duration,
    /// What the session is: a peer (default; talks to the nodes of its `listen` / `connect`
    /// endpoints), a client of zenoh routers (`connect` = the routers), or a router.
    pub mode: ZenohMode,
    /// zenoh's multicast scouting (off by default: sessions only talk to configured endpoints).
    pub multicast_scouting: bool,
    /// Access control enforced by this session (or router) on what connected peers send it;
    /// `None` = none. Needs [`ZenohConfig::auth`] (the rules are per user) and no `connect`
    /// endpoints (only a listener knows its peers' user names).
    pub access: Option<ZenohAccess>,
    /// TLS on every link (`tls/` endpoints only); `None` = plain TCP.
    pub tls: Option<ZenohTls>,
    /// Client mode: how long opening the session waits for a router of `connect` to answer
    /// (retrying every `reconnect_period`, doubling up to 8×); `None` = until one does.
    pub connect_timeout: Option<Duration>,
}

/// The role of a zenoh session.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ZenohMode {
    /// Peer-to-peer with explicit endpoints (gossip off: peers do not relay).
    #[default]
    Peer,
    /// A client of the zenoh router(s) in `connect`, which route between clients.
    Client,
    /// A zenoh router: listens, routes between the clients and peers that connect.
    Router,
}

impl ZenohMode {
    fn zenoh_name(self) -> &'static str {
        match self {
            ZenohMode::Peer => "peer",
            ZenohMode::Client => "client",
            ZenohMode::Router => "router",
        }
    }
}

impl ZenohConfig {
    /// Defaults under `key_prefix` with the given endpoints.
    pub fn new(key_prefix: impl Into<String>, listen: Vec<String>, connect: Vec<String>) -> Self {
        Self {
            key_prefix: key_prefix.into(),
            listen,
            connect,
            auth: None,
            receive_queue: 1024,
            overflow_wait: Duration::from_millis(100),
            lease: Duration::from_secs(3),
            reconnect_period: Duration::from_millis(200),
            mode: ZenohMode::Peer,
            multicast_scouting: false,
            access: None,
            tls: None,
            connect_timeout: None,
        }
    }
}

/// A TCP port on 127.0.0.1 that is free now (bind port 0, read it back, release it), for
/// endpoints of processes on one host. Another process may take it before the caller binds it.
pub fn free_loopback_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// `n` distinct TCP ports on 127.0.0.1 that are free now, none of them in `avoid` (ports
/// other endpoints of the caller will listen on). All `n` are held bound until every one is
/// chosen: ports chosen one [`free_loopback_port`] at a time can repeat, since each is released
/// before the next is asked for and the kernel may hand it out again. Another process may
/// still take one before the caller binds it.
pub fn free_loopback_ports(n: usize, avoid: &[u16]) -> std::io::Result<Vec<u16>> {
    let mut held = Vec::with_capacity(n);
    let mut ports = Vec::with_capacity(n);
    while ports.len() < n {
        let listener = std::net::TcpListener::bind("127.0.0.1:0")?;
        let port = listener.local_addr()?.port();
        held.push(listener);
        if !avoid.contains(&port) {
            ports.push(port);
        } else if held.len() > n + avoid.len() {
            // Each ephemeral port handed out is bound meanwhile, so at most `avoid.len()`
            // draws can be refused: more means the kernel repeats ports it holds.
            return Err(std::io::Error::other(format!(
                "the kernel handed out {} ports for {n} free ones",
                held.len()
            )));
        }
    }
    Ok(ports)
}

fn err(e: impl std::fmt::Display) -> LinkError {
    LinkError::backend(BACKEND, e)
}

/// A private file holding the accepted credentials while the session opens (zenoh reads the
/// dictionary from a file); removed as soon as the session is open.
struct DictionaryFile(PathBuf);

impl DictionaryFile {
    fn write(accept: &[(String, String)]) -> Result<Self, LinkError> {
        use std::os::unix::fs::OpenOptionsExt;
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let path = std::env::temp_dir().join(format!(
            "canopy-zenoh-users-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(&path)
            .map_err(|e| LinkError::Config(format!("credentials file {}: {e}", path.display())))?;
        for (u, p) in accept {
            if u.is_empty() || p.is_empty() || u.contains([':', '\n']) || p.contains('\n') {
                let _ = std::fs::remove_file(&path);
                return Err(LinkError::Config(
                    "zenoh users and passwords must be non-empty, users without ':' or newline"
                        .into(),
                ));
            }
            writeln!(f, "{u}:{p}").map_err(|e| LinkError::Config(e.to_string()))?;
        }
        Ok(Self(path))
    }
}

impl Drop for DictionaryFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

fn check_prefix(p: &str) -> Result<(), LinkError> {
    let ok = !p.is_empty()
        && !p.starts_with('/')
        && !p.ends_with('/')
        && p.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-' || b == b'/');
    if ok {
        Ok(())
    } else {
        Err(LinkError::Config(format!(
            "zenoh key prefix {p:?} must be [A-Za-z0-9_/-], not starting or ending with '/'"
        )))
    }
}

/// Closes the session when the transport handle and every link opened from it are gone.
struct SessionOwner(Session);

impl Drop for SessionOwner {
    fn drop(&mut self) {
        if !self.0.is_closed()
            && let Err(e) = self.0.close().wait()
        {
            tracing::warn!(error = %e, "zenoh: closing the session failed");
        }
    }
}

/// This process's zenoh session. Links opened from it share the session and keep it open; it is
/// closed when the transport and all its links are dropped, or at once by
/// [`ZenohTransport::close`].
pub struct ZenohTransport {
    local: NodeId,
    cfg: ZenohConfig,
    session: Arc<SessionOwner>,
}

impl std::fmt::Debug for ZenohTransport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohTransport")
            .field("local", &self.local)
            .field("cfg", &self.cfg)
            .finish_non_exhaustive()
    }
}

impl ZenohTransport {
    /// Opens the session of node `local`.
    pub fn open(local: NodeId, cfg: ZenohConfig) -> Result<Self, LinkError> {
        check_prefix(&cfg.key_prefix)?;
        let mut zc = Config::default();
        let set = |zc: &mut Config, k: &str, v: String| {
            zc.insert_json5(k, &v)
                .map_err(|e| LinkError::Config(format!("zenoh config {k} = {v}: {e}")))
        };
        set(&mut zc, "mode", json_str(cfg.mode.zenoh_name()))?;
        set(
            &mut zc,
            "scouting/multicast/enabled",
            cfg.multicast_scouting.to_string(),
        )?;
        set(&mut zc, "scouting/gossip/enabled", "false".into())?;
        if cfg.mode == ZenohMode::Client {
            // A client retries its routers while it opens (zenoh's client default is one
            // attempt: `timeout_ms` 0), for `connect_timeout` or (-1) until one answers.
            let ms = cfg.connect_timeout.map_or(-1, |d| {
                i64::try_from(d.as_millis().max(1)).unwrap_or(i64::MAX)
            });
            set(&mut zc, "connect/timeout_ms", ms.to_string())?;
        }
        set(&mut zc, "listen/endpoints", json_list(&cfg.listen))?;
        set(&mut zc, "connect/endpoints", json_list(&cfg.connect))?;
        let period = cfg.reconnect_period.as_millis().max(1);
        set(
            &mut zc,
            "connect/retry",
            format!(
                "{{period_init_ms: {period}, period_max_ms: {}, period_increase_factor: 2}}",
                period * 8
            ),
        )?;
        let wanted = if cfg.tls.is_some() { "tls/" } else { "tcp/" };
        if let Some(ep) = cfg
            .listen
            .iter()
            .chain(&cfg.connect)
            .find(|e| !e.starts_with(wanted))
        {
            return Err(LinkError::Config(format!(
                "zenoh endpoint {ep:?}: this session uses {wanted} endpoints only ({})",
                if cfg.tls.is_some() {
                    "TLS is configured"
                } else {
                    "TLS is not configured"
                }
            )));
        }
        if let Some(t) = &cfg.tls {
            for (what, path) in [
                ("root CA certificate", &t.root_ca),
                ("certificate", &t.certificate),
                ("private key", &t.private_key),
            ] {
                if !path.is_file() {
                    return Err(LinkError::Config(format!(
                        "TLS {what} {}: no such file",
                        path.display()
                    )));
                }
            }
            let file = |p: &PathBuf| json_str(&p.to_string_lossy());
            for (k, v) in [
                ("root_ca_certificate", file(&t.root_ca)),
                ("listen_certificate", file(&t.certificate)),
                ("listen_private_key", file(&t.private_key)),
                ("connect_certificate", file(&t.certificate)),
                ("connect_private_key", file(&t.private_key)),
                ("enable_mtls", "true".into()),
                ("verify_name_on_connect", "true".into()),
            ] {
                set(&mut zc, &format!("transport/link/tls/{k}"), v)?;
            }
        }
        let lease = cfg.lease.as_millis().max(100);
        set(&mut zc, "transport/link/tx/lease", lease.to_string())?;
        let _dict = match &cfg.auth {
            None => None,
            Some(a) => {
                set(&mut zc, "transport/auth/usrpwd/user", json_str(&a.user))?;
                set(
                    &mut zc,
                    "transport/auth/usrpwd/password",
                    json_str(&a.password),
                )?;
                // A session that accepts nobody (it only connects) needs no dictionary; one that
                // listens without one would let anybody in.
                if a.accept.is_empty() && !cfg.listen.is_empty() {
                    return Err(LinkError::Config(
                        "a listening zenoh session with authentication needs the users it \
                         accepts"
                            .into(),
                    ));
                }
                if a.accept.is_empty() {
                    None
                } else {
                    let d = DictionaryFile::write(&a.accept)?;
                    set(
                        &mut zc,
                        "transport/auth/usrpwd/dictionary_file",
                        json_str(&d.0.to_string_lossy()),
                    )?;
                    Some(d)
                }
            }
        };
        if let Some(access) = &cfg.access {
            if !cfg.connect.is_empty() {
                // zenoh's user/password check is one-way: a connecting session has no user
                // name for what it connects to, so default deny would refuse its own links.
                return Err(LinkError::Config(
                    "zenoh access control is enforced by a session that only listens (or a \
                     router): this one also connects"
                        .into(),
                ));
            }
            if cfg.auth.is_none() {
                return Err(LinkError::Config(
                    "zenoh access control needs user/password authentication (its rules are \
                     per user)"
                        .into(),
                ));
            }
            let accepted: Vec<&str> = cfg
                .auth
                .iter()
                .flat_map(|a| a.accept.iter().map(|(u, _)| u.as_str()))
                .collect();
            set(&mut zc, "access_control", access.to_json5(&accepted))?;
        }
        let session = zenoh::open(zc).wait().map_err(err)?;
        Ok(Self {
            local,
            cfg,
            session: Arc::new(SessionOwner(session)),
        })
    }

    /// This node.
    pub fn local_id(&self) -> NodeId {
        self.local
    }

    /// The same session as node `local` under another key prefix (a router's own links on a
    /// run's control plane, next to the fusion links it routes). It shares the session: closing
    /// either closes both.
    pub fn scoped(&self, local: NodeId, key_prefix: &str) -> Result<ZenohTransport, LinkError> {
        check_prefix(key_prefix)?;
        let mut cfg = self.cfg.clone();
        cfg.key_prefix = key_prefix.to_string();
        Ok(Self {
            local,
            cfg,
            session: self.session.clone(),
        })
    }

    fn data_key(&self, from: NodeId, to: NodeId) -> String {
        format!("{}/link/{from}/{to}", self.cfg.key_prefix)
    }
    fn alive_key(&self, from: NodeId, to: NodeId) -> String {
        format!("{}/alive/{from}/{to}", self.cfg.key_prefix)
    }

    /// Opens the link to `peer` (the session must be configured to reach it).
    pub fn link(&self, peer: NodeId, max_body_len: u64) -> Result<ZenohLink, LinkError> {
        let cfg = LinkConfig::new(self.local, peer).with_max_body_len(max_body_len);
        let stats = StatsCell::new();
        let publisher = self
            .session
            .0
            .declare_publisher(self.data_key(self.local, peer))
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(err)?;
        let (data_tx, data_rx) = mpsc::sync_channel::<ZBytes>(self.cfg.receive_queue.max(1));
        let overflow_stats = stats.clone();
        let overflow_wait = self.cfg.overflow_wait;
        let subscriber = self
            .session
            .0
            .declare_subscriber(self.data_key(peer, self.local))
            .callback(move |sample| {
                enqueue(&data_tx, sample.payload().clone(), overflow_wait, || {
                    overflow_stats.on_dropped_overflow()
                })
            })
            .wait()
            .map_err(err)?;
        let (live_tx, live_rx) = mpsc::channel::<bool>();
        let liveliness = self
            .session
            .0
            .liveliness()
            .declare_subscriber(self.alive_key(peer, self.local))
            .history(true)
            .callback(move |sample| {
                let _ = live_tx.send(sample.kind() == SampleKind::Put);
            })
            .wait()
            .map_err(err)?;
        // Declared last: when the peer sees this token, our subscriber is already declared.
        let token = self
            .session
            .0
            .liveliness()
            .declare_token(self.alive_key(self.local, peer))
            .wait()
            .map_err(err)?;
        Ok(ZenohLink {
            _session: self.session.clone(),
            cfg,
            publisher,
            _subscriber: subscriber,
            _liveliness: liveliness,
            _token: token,
            data_rx,
            live_rx,
            stats,
            tracker: PeerTracker::new(),
            incarnation: 0,
        })
    }

    /// Publishes `bytes` verbatim on the data key `from → to` (tests and tools: garbage,
    /// truncated or forged messages).
    pub fn raw_put(&self, from: NodeId, to: NodeId, bytes: Vec<u8>) -> Result<(), LinkError> {
        self.session
            .0
            .put(self.data_key(from, to), ZBytes::from(bytes))
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(err)
    }

    /// Waits up to `timeout` until a link of node `node` is visible through its liveliness
    /// token (i.e. this session is connected to it and has its declarations). For tests and
    /// tools that publish with [`ZenohTransport::raw_put`].
    pub fn wait_for_node(&self, node: NodeId, timeout: Duration) -> bool {
        let deadline = std::time::Instant::now() + timeout;
        let key = format!("{}/alive/{node}/*", self.cfg.key_prefix);
        while std::time::Instant::now() < deadline {
            if let Ok(replies) = self
                .session
                .0
                .liveliness()
                .get(&key)
                .timeout(Duration::from_millis(200))
                .wait()
                && replies.recv().is_ok()
            {
                return true;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        false
    }

    /// Waits up to `timeout` until a subscriber to the data key `from → to` is known to this
    /// session (so a [`ZenohTransport::raw_put`] on it is routed, not dropped for want of a
    /// subscriber). For tests and tools.
    pub fn wait_for_subscriber(
        &self,
        from: NodeId,
        to: NodeId,
        timeout: Duration,
    ) -> Result<bool, LinkError> {
        let publisher = self
            .session
            .0
            .declare_publisher(self.data_key(from, to))
            .wait()
            .map_err(err)?;
        let deadline = std::time::Instant::now() + timeout;
        while std::time::Instant::now() < deadline {
            if publisher.matching_status().wait().map_err(err)?.matching() {
                return Ok(true);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        Ok(false)
    }

    /// Closes the session now (links opened from it stop working).
    pub fn close(self) -> Result<(), LinkError> {
        self.session.0.close().wait().map_err(err)
    }
}

/// How often a callback facing a full receive queue looks for room again.
const OVERFLOW_POLL: Duration = Duration::from_micros(20);

/// Queues a received payload for the application; when the queue is full, waits up to `wait`
/// for room (polling every [`OVERFLOW_POLL`]), then drops it and calls `on_drop`.
fn enqueue(tx: &SyncSender<ZBytes>, z: ZBytes, wait: Duration, on_drop: impl FnOnce()) {
    let mut z = match tx.try_send(z) {
        Ok(()) | Err(TrySendError::Disconnected(_)) => return,
        Err(TrySendError::Full(z)) => z,
    };
    let deadline = std::time::Instant::now() + wait;
    loop {
        if std::time::Instant::now() >= deadline {
            on_drop();
            return;
        }
        std::thread::sleep(OVERFLOW_POLL);
        z = match tx.try_send(z) {
            Ok(()) | Err(TrySendError::Disconnected(_)) => return,
            Err(TrySendError::Full(z)) => z,
        };
    }
}

/// A received zenoh payload: kept as is when contiguous (decoded in place), else flattened.
enum ZPayload {
    Contiguous(ZBytes),
    Flat(Vec<u8>),
}

impl MessageBytes for ZPayload {
    fn bytes(&self) -> &[u8] {
        match self {
            // Constructed only when `slices()` yields exactly one slice.
            ZPayload::Contiguous(z) => z.slices().next().unwrap_or(&[]),
            ZPayload::Flat(v) => v,
        }
    }
    fn is_borrowed(&self) -> bool {
        matches!(self, ZPayload::Contiguous(_))
    }
    fn into_vec(self: Box<Self>) -> Vec<u8> {
        match *self {
            ZPayload::Contiguous(z) => z.slices().next().unwrap_or(&[]).to_vec(),
            ZPayload::Flat(v) => v,
        }
    }
}

/// Takes a received payload: kept as is when contiguous (the envelope check then reads it once);
/// a fragmented one (zenoh delivers large messages as many slices) is flattened with the CRC
/// computed during the copy, slice by slice while each slice is in cache, so the envelope check
/// does not read the 16 MB again.
fn payload(z: ZBytes) -> (ZPayload, Option<u32>) {
    if z.slices().count() == 1 {
        return (ZPayload::Contiguous(z), None);
    }
    let mut v = Vec::with_capacity(z.len());
    let mut crc = codec::EnvelopeCrc::new();
    for s in z.slices() {
        let start = v.len();
        v.extend_from_slice(s);
        crc.update(start, &v[start..]);
    }
    (ZPayload::Flat(v), Some(crc.finalize()))
}

/// How long `recv_timeout` spins on an empty queue before it parks.
const SPIN: Duration = Duration::from_micros(50);

/// One endpoint of a zenoh link.
pub struct ZenohLink {
    cfg: LinkConfig,
    publisher: Publisher<'static>,
    _subscriber: Subscriber<()>,
    _liveliness: Subscriber<()>,
    _token: LivelinessToken,
    data_rx: Receiver<ZBytes>,
    live_rx: Receiver<bool>,
    stats: Arc<StatsCell>,
    tracker: PeerTracker,
    incarnation: u64,
    /// Last: dropped after the ports above are undeclared.
    _session: Arc<SessionOwner>,
}

impl std::fmt::Debug for ZenohLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohLink")
            .field("cfg", &self.cfg)
            .finish_non_exhaustive()
    }
}

impl ZenohLink {
    fn update_liveness(&mut self) {
        while let Ok(up) = self.live_rx.try_recv() {
            if up {
                self.incarnation += 1;
                self.tracker.observe(Some(self.incarnation));
            } else {
                self.tracker.observe(None);
            }
        }
    }

    fn admit(&self, z: ZBytes) -> Option<Received> {
        let (p, crc) = payload(z);
        admit_with_crc(p, crc, &self.cfg, &self.stats)
    }
}

impl Link for ZenohLink {
    fn local_id(&self) -> NodeId {
        self.cfg.local
    }
    fn peer_id(&self) -> NodeId {
        self.cfg.peer
    }

    fn send(&mut self, meta: &SendMeta, body: &dyn WireBody) -> Result<(), LinkError> {
        let bytes = codec::encode_to_vec(meta, self.cfg.local, body, self.cfg.max_body_len)?;
        let n = bytes.len();
        self.update_liveness();
        self.publisher
            .put(ZBytes::from(bytes))
            .wait()
            .map_err(err)?;
        self.stats.on_sent(n);
        if self.tracker.state() == PeerState::Down {
            // zenoh gives no per-put delivery report; with the peer's liveliness token absent
            // the message had no subscriber to go to.
            self.stats.on_dropped_no_peer();
        }
        Ok(())
    }

    fn try_recv(&mut self) -> Result<Option<Received>, LinkError> {
        self.update_liveness();
        while let Ok(z) = self.data_rx.try_recv() {
            if let Some(r) = self.admit(z) {
                return Ok(Some(r));
            }
        }
        Ok(None)
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        self.update_liveness();
        let deadline = std::time::Instant::now() + timeout;
        // Messages that stream arrive within microseconds of each other: a short spin catches the
        // next one without parking this thread and waking it per message.
        let spin_until = std::time::Instant::now() + SPIN.min(timeout);
        let mut polls = 0u32;
        loop {
            match self.data_rx.try_recv() {
                Ok(z) => {
                    if let Some(r) = self.admit(z) {
                        return Ok(Some(r));
                    }
                    continue;
                }
                Err(_) => {
                    // The clock is read every 16 polls, not on every one.
                    polls += 1;
                    if polls.is_multiple_of(16) && std::time::Instant::now() >= spin_until {
                        break;
                    }
                    std::hint::spin_loop();
                }
            }
        }
        loop {
            let now = std::time::Instant::now();
            let wait = deadline.saturating_duration_since(now);
            match self.data_rx.recv_timeout(wait) {
                Ok(z) => {
                    if let Some(r) = self.admit(z) {
                        return Ok(Some(r));
                    }
                }
                Err(RecvTimeoutError::Timeout) => return Ok(None),
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(err("subscriber closed (session closed?)"));
                }
            }
        }
    }

    fn poll_event(&mut self) -> Option<LinkEvent> {
        self.update_liveness();
        self.tracker.pop()
    }

    fn peer_state(&self) -> PeerState {
        self.tracker.state()
    }

    fn stats(&self) -> LinkStats {
        self.stats.snapshot()
    }
}

#[cfg(test)]
mod port_tests {
    /// 200 ports asked for at once are distinct and avoid the ones named: drawn one at a time
    /// and released, they repeated (two links of one run got one port; the launcher refused the
    /// run with "port clash").
    #[test]
    fn free_ports_are_distinct_and_avoid_the_named() {
        let first = super::free_loopback_ports(1, &[]).unwrap()[0];
        let ports = super::free_loopback_ports(200, &[first]).unwrap();
        let distinct: std::collections::BTreeSet<u16> = ports.iter().copied().collect();
        assert_eq!(distinct.len(), 200);
        assert!(!distinct.contains(&first));
    }
}
