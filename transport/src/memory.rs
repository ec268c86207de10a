//! In-memory backend: deterministic, for simulation and unit tests.
//!
//! An [`InMemoryHub`] holds one mailbox per directed pair of nodes. [`InMemoryHub::connect`]
//! attaches an endpoint `(local → peer)`; the peer is "up" while its reverse endpoint is
//! attached. Dropping an endpoint detaches it and discards what was queued for it (a dead
//! process loses its inbox); attaching again is a restart (new incarnation). Messages are fully
//! encoded, so the in-memory link exercises the same codec and admission checks as the others.
//! Delivery order is FIFO per direction and nothing depends on wall time, so a simulation that
//! drives the links in a fixed order is reproducible.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use crate::codec::{self, WireBody};
use crate::envelope::{NodeId, SendMeta};
use crate::link::{
    Link, LinkConfig, LinkError, LinkEvent, LinkStats, PeerState, PeerTracker, Received, StatsCell,
    admit,
};

/// Default bound of a mailbox, in messages.
pub const DEFAULT_MAILBOX_CAPACITY: usize = 4096;

#[derive(Debug, Default)]
struct Mailbox {
    queue: VecDeque<Vec<u8>>,
}

#[derive(Debug, Default)]
struct HubState {
    /// (from, to) → queued messages for `to`.
    mailboxes: HashMap<(NodeId, NodeId), Mailbox>,
    /// Attached endpoints (local, peer) → incarnation.
    attached: HashMap<(NodeId, NodeId), u64>,
    next_incarnation: u64,
}

#[derive(Debug)]
struct HubInner {
    state: Mutex<HubState>,
    changed: Condvar,
    capacity: usize,
}

/// A set of in-memory endpoints that can reach each other. Cheap to clone (shared).
#[derive(Debug, Clone)]
pub struct InMemoryHub {
    inner: Arc<HubInner>,
}

impl Default for InMemoryHub {
    fn default() -> Self {
        Self::new()
    }
}

fn lock(inner: &HubInner) -> MutexGuard<'_, HubState> {
    // A panic while holding the lock cannot leave the maps inconsistent (every update is a
    // single insert/remove/push), so a poisoned lock is safe to keep using.
    inner.state.lock().unwrap_or_else(|p| p.into_inner())
}

impl InMemoryHub {
    /// An empty hub with the default mailbox capacity.
    pub fn new() -> Self {
        Self::with_capacity(DEFAULT_MAILBOX_CAPACITY)
    }
    /// An empty hub whose mailboxes hold at most `capacity` messages (further sends are dropped
    /// and counted as overflow).
    pub fn with_capacity(capacity: usize) -> Self {
        Self {
            inner: Arc::new(HubInner {
                state: Mutex::new(HubState::default()),
                changed: Condvar::new(),
                capacity,
            }),
        }
    }

    /// Attaches the endpoint `cfg.local → cfg.peer`. Replaces (restarts) an endpoint already
    /// attached under the same pair.
    pub fn connect(&self, cfg: LinkConfig) -> InMemoryLink {
        let mut st = lock(&self.inner);
        st.next_incarnation += 1;
        let inc = st.next_incarnation;
        st.attached.insert((cfg.local, cfg.peer), inc);
        st.mailboxes.remove(&(cfg.peer, cfg.local));
        drop(st);
        self.inner.changed.notify_all();
        InMemoryLink {
            hub: self.inner.clone(),
            cfg,
            incarnation: inc,
            stats: StatsCell::new(),
            tracker: PeerTracker::new(),
        }
    }

    /// A connected pair `a ↔ b` on a fresh hub.
    pub fn pair(a: NodeId, b: NodeId) -> (InMemoryLink, InMemoryLink) {
        let hub = Self::new();
        (
            hub.connect(LinkConfig::new(a, b)),
            hub.connect(LinkConfig::new(b, a)),
        )
    }

    /// Puts raw bytes into the mailbox `from → to` as if `from` had sent them (for tests and
    /// fuzzing: garbage, truncated or forged messages). Returns false if `to` has no endpoint
    /// listening to `from`.
    pub fn inject_raw(&self, from: NodeId, to: NodeId, bytes: Vec<u8>) -> bool {
        let mut st = lock(&self.inner);
        if !st.attached.contains_key(&(to, from)) {
            return false;
        }
        st.mailboxes
            .entry((from, to))
            .or_default()
            .queue
            .push_back(bytes);
        drop(st);
        self.inner.changed.notify_all();
        true
    }
}

/// One endpoint of an in-memory link.
#[derive(Debug)]
pub struct InMemoryLink {
    hub: Arc<HubInner>,
    cfg: LinkConfig,
    incarnation: u64,
    stats: Arc<StatsCell>,
    tracker: PeerTracker,
}

impl InMemoryLink {
    fn observe_peer(&mut self, st: &HubState) {
        let present = st.attached.get(&(self.cfg.peer, self.cfg.local)).copied();
        self.tracker.observe(present);
    }

    fn take(&mut self, st: &mut HubState) -> Option<Received> {
        loop {
            let msg = st
                .mailboxes
                .get_mut(&(self.cfg.peer, self.cfg.local))?
                .queue
                .pop_front()?;
            if let Some(r) = admit(msg, &self.cfg, &self.stats) {
                return Some(r);
            }
        }
    }
}

impl Drop for InMemoryLink {
    fn drop(&mut self) {
        let mut st = lock(&self.hub);
        let key = (self.cfg.local, self.cfg.peer);
        if st.attached.get(&key) == Some(&self.incarnation) {
            st.attached.remove(&key);
            st.mailboxes.remove(&(self.cfg.peer, self.cfg.local));
        }
        drop(st);
        self.hub.changed.notify_all();
    }
}

impl Link for InMemoryLink {
    fn local_id(&self) -> NodeId {
        self.cfg.local
    }
    fn peer_id(&self) -> NodeId {
        self.cfg.peer
    }

    fn send(&mut self, meta: &SendMeta, body: &dyn WireBody) -> Result<(), LinkError> {
        let bytes = codec::encode_to_vec(meta, self.cfg.local, body, self.cfg.max_body_len)?;
        let n = bytes.len();
        let hub = self.hub.clone();
        let mut st = lock(&hub);
        self.observe_peer(&st);
        self.stats.on_sent(n);
        if !st.attached.contains_key(&(self.cfg.peer, self.cfg.local)) {
            self.stats.on_dropped_no_peer();
            return Ok(());
        }
        let q = &mut st
            .mailboxes
            .entry((self.cfg.local, self.cfg.peer))
            .or_default()
            .queue;
        if q.len() >= hub.capacity {
            self.stats.on_dropped_overflow();
            return Ok(());
        }
        q.push_back(bytes);
        drop(st);
        hub.changed.notify_all();
        Ok(())
    }

    fn try_recv(&mut self) -> Result<Option<Received>, LinkError> {
        let hub = self.hub.clone();
        let mut st = lock(&hub);
        self.observe_peer(&st);
        Ok(self.take(&mut st))
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        let deadline = Instant::now() + timeout;
        let hub = self.hub.clone();
        let mut st = lock(&hub);
        loop {
            self.observe_peer(&st);
            if let Some(r) = self.take(&mut st) {
                return Ok(Some(r));
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            st = hub
                .changed
                .wait_timeout(st, deadline - now)
                .map(|(g, _)| g)
                .unwrap_or_else(|p| p.into_inner().0);
        }
    }

    fn poll_event(&mut self) -> Option<LinkEvent> {
        let hub = self.hub.clone();
        let st = lock(&hub);
        self.observe_peer(&st);
        drop(st);
        self.tracker.pop()
    }

    fn peer_state(&self) -> PeerState {
        self.tracker.state()
    }

    fn stats(&self) -> LinkStats {
        self.stats.snapshot()
    }
}
