//! Fault injection: a [`Link`] wrapper that delays, jitters, loses, duplicates, reorders,
//! rate-limits and cuts the messages *arriving* at the wrapped endpoint.
//!
//! Faults act on the inbound direction of the endpoint they wrap (that is where a synchronous
//! receiver can hold messages back and release them on time without a helper thread); wrap both
//! ends of a link with the same windows to cut both directions. Sending passes straight through.
//!
//! Every message taken from the inner link at time `t` (from the injectable [`Clock`]) goes
//! through, in order:
//! 1. outage / partition windows `[start, end)` containing `t`: with [`OutagePolicy::Drop`] the
//!    message is dropped; with [`OutagePolicy::Queue`] it is held (up to a bound, beyond which
//!    it is dropped) and re-enters the pipeline at the end of the window;
//! 2. loss with probability `loss`;
//! 3. duplication with probability `duplicate` (the copy follows the same path);
//! 4. bandwidth cap: each copy occupies the link for `len / bytes_per_s`; a copy that would
//!    find more than `queue_bytes` waiting ahead of it is dropped;
//! 5. delivery at `done + delay + U[0, jitter)` plus `reorder_delay` with probability
//!    `reorder` (jitter and reorder both permute the order).
//!
//! Zero-copy: the layer takes messages from the inner link one at a time, when the application
//! asks and nothing it already holds is due. A message that comes out of the pipeline due at
//! once (no delay, jitter, reordering or bandwidth cap configured, outside outage windows) is
//! handed to the application as the backend gave it — an iceoryx2 sample or a zenoh buffer,
//! decoded in place. Only a message the layer must hold (and a duplicate) is copied out of the
//! backend's buffer, since the layer may hold more messages, for longer, than a shared-memory
//! backend lends; [`FaultStats::copied`] counts those copies.
//!
//! Randomness comes from a `ChaCha8Rng` seeded from [`FaultConfig::seed`] with a fixed number of
//! draws per message, so a run is reproducible under a simulated clock. [`FaultStats`] always
//! balance: `offered + duplicated = delivered + dropped() + in_flight`.

use std::cmp::Reverse;
use std::collections::{BinaryHeap, VecDeque};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::codec::WireBody;
use crate::envelope::{NodeId, SendMeta};
use crate::link::{Link, LinkError, LinkEvent, LinkStats, PeerState, Received};

/// Source of time for the fault layer, in seconds.
pub trait Clock: Send + Sync + std::fmt::Debug {
    /// Current time (seconds; monotone non-decreasing).
    fn now(&self) -> f64;
}

/// Wall time since the clock was created.
#[derive(Debug, Clone)]
pub struct WallClock {
    start: Instant,
}

impl WallClock {
    /// Starts at 0 now.
    pub fn new() -> Self {
        Self {
            start: Instant::now(),
        }
    }
}

impl Default for WallClock {
    fn default() -> Self {
        Self::new()
    }
}

impl Clock for WallClock {
    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }
}

/// Simulation time set by the simulator. Cheap to clone (shared).
#[derive(Debug, Clone, Default)]
pub struct ManualClock {
    bits: Arc<AtomicU64>,
}

impl ManualClock {
    /// Starts at `t0` seconds.
    pub fn new(t0: f64) -> Self {
        Self {
            bits: Arc::new(AtomicU64::new(t0.to_bits())),
        }
    }
    /// Sets the time (ignored if it would go backwards or is not finite).
    pub fn set(&self, t: f64) {
        if t.is_finite() && t >= self.now() {
            self.bits.store(t.to_bits(), Ordering::Release);
        }
    }
    /// Advances by `dt` seconds.
    pub fn advance(&self, dt: f64) {
        self.set(self.now() + dt);
    }
}

impl Clock for ManualClock {
    fn now(&self) -> f64 {
        f64::from_bits(self.bits.load(Ordering::Acquire))
    }
}

/// A time window `[start, end)` in clock seconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Window {
    /// Inclusive start.
    pub start: f64,
    /// Exclusive end.
    pub end: f64,
}

impl Window {
    /// `[start, end)`.
    pub fn new(start: f64, end: f64) -> Self {
        Self { start, end }
    }
    /// True if `t` is inside.
    pub fn contains(&self, t: f64) -> bool {
        t >= self.start && t < self.end
    }
}

/// During `window`, nodes in `side` cannot talk to nodes outside it. A link is cut by the
/// partition when exactly one of its two ends is in `side`.
#[derive(Debug, Clone, PartialEq)]
pub struct Partition {
    /// When.
    pub window: Window,
    /// One side of the cut.
    pub side: Vec<NodeId>,
}

/// What happens to messages arriving during an outage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutagePolicy {
    /// Dropped (counted as `dropped_outage`).
    Drop,
    /// Held and delivered after the outage; beyond `max_messages` held at once the extra ones
    /// are dropped (counted as `dropped_outage_overflow`).
    Queue {
        /// Bound on held messages.
        max_messages: usize,
    },
}

/// A bandwidth cap with a byte-bounded queue.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bandwidth {
    /// Service rate.
    pub bytes_per_s: f64,
    /// Bytes allowed to wait ahead of a message; more and it is dropped.
    pub queue_bytes: u64,
}

/// Fault model of one endpoint's inbound direction.
#[derive(Debug, Clone, PartialEq)]
pub struct FaultConfig {
    /// Seed of the fault RNG.
    pub seed: u64,
    /// Fixed delay (s).
    pub delay: f64,
    /// Extra uniform delay in `[0, jitter)` (s).
    pub jitter: f64,
    /// Loss probability.
    pub loss: f64,
    /// Duplication probability.
    pub duplicate: f64,
    /// Probability of holding a message back by `reorder_delay`.
    pub reorder: f64,
    /// Hold-back of a reordered message (s).
    pub reorder_delay: f64,
    /// Windows in which the link is cut.
    pub outages: Vec<Window>,
    /// Partitions (applied when they cut this link).
    pub partitions: Vec<Partition>,
    /// Drop or queue during outages.
    pub outage_policy: OutagePolicy,
    /// Optional bandwidth cap.
    pub bandwidth: Option<Bandwidth>,
    /// Report `PeerDown` / `PeerUp` at the edges of outage windows.
    pub signal_outages: bool,
}

impl FaultConfig {
    /// No faults (every message delivered at once), with the given seed.
    pub fn none(seed: u64) -> Self {
        Self {
            seed,
            delay: 0.0,
            jitter: 0.0,
            loss: 0.0,
            duplicate: 0.0,
            reorder: 0.0,
            reorder_delay: 0.0,
            outages: Vec::new(),
            partitions: Vec::new(),
            outage_policy: OutagePolicy::Drop,
            bandwidth: None,
            signal_outages: true,
        }
    }

    /// Checks ranges (probabilities in [0, 1], finite non-negative times, ordered windows).
    pub fn validate(&self) -> Result<(), LinkError> {
        let bad = |m: &str| Err(LinkError::Config(format!("fault config: {m}")));
        for (name, p) in [
            ("loss", self.loss),
            ("duplicate", self.duplicate),
            ("reorder", self.reorder),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(&format!("{name} = {p} is not a probability"));
            }
        }
        for (name, t) in [
            ("delay", self.delay),
            ("jitter", self.jitter),
            ("reorder_delay", self.reorder_delay),
        ] {
            if !t.is_finite() || t < 0.0 {
                return bad(&format!("{name} = {t} must be finite and >= 0"));
            }
        }
        let windows = self
            .outages
            .iter()
            .chain(self.partitions.iter().map(|p| &p.window));
        for w in windows {
            if !(w.start.is_finite() && w.end.is_finite() && w.start <= w.end) {
                return bad(&format!("window [{}, {}) is not ordered", w.start, w.end));
            }
        }
        if let Some(b) = self.bandwidth
            && !(b.bytes_per_s.is_finite() && b.bytes_per_s > 0.0)
        {
            return bad("bandwidth must be finite and > 0");
        }
        Ok(())
    }
}

/// Fault-layer counters.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultStats {
    /// Messages taken from the inner link.
    pub offered: u64,
    /// Extra copies created by duplication.
    pub duplicated: u64,
    /// Messages handed to the application.
    pub delivered: u64,
    /// Dropped by random loss.
    pub dropped_loss: u64,
    /// Dropped because they arrived during an outage (policy `Drop`).
    pub dropped_outage: u64,
    /// Dropped because the outage queue was full (policy `Queue`).
    pub dropped_outage_overflow: u64,
    /// Dropped by the bandwidth cap's queue bound.
    pub dropped_bandwidth: u64,
    /// Held now (outage queue + scheduled).
    pub in_flight: u64,
    /// Messages the layer copied out of a backend's lent buffer because it had to hold them
    /// (delay, jitter, reordering, bandwidth cap, queued outage, a duplicate); every other
    /// delivered message was handed over in the backend's buffer, uncopied.
    pub copied: u64,
}

impl FaultStats {
    /// All drops.
    pub fn dropped(&self) -> u64 {
        self.dropped_loss
            + self.dropped_outage
            + self.dropped_outage_overflow
            + self.dropped_bandwidth
    }
    /// `offered + duplicated == delivered + dropped() + in_flight`.
    pub fn balanced(&self) -> bool {
        self.offered + self.duplicated == self.delivered + self.dropped() + self.in_flight
    }
}

struct Scheduled {
    due: f64,
    order: u64,
    msg: Received,
}

impl PartialEq for Scheduled {
    fn eq(&self, o: &Self) -> bool {
        self.due.total_cmp(&o.due).is_eq() && self.order == o.order
    }
}
impl Eq for Scheduled {}
impl PartialOrd for Scheduled {
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(o))
    }
}
impl Ord for Scheduled {
    fn cmp(&self, o: &Self) -> std::cmp::Ordering {
        self.due.total_cmp(&o.due).then(self.order.cmp(&o.order))
    }
}

/// A [`Link`] with injected inbound faults.
pub struct FaultyLink<L: Link> {
    inner: L,
    cfg: FaultConfig,
    clock: Arc<dyn Clock>,
    rng: ChaCha8Rng,
    order: u64,
    scheduled: BinaryHeap<Reverse<Scheduled>>,
    /// Held during an outage: (release time, message).
    held: VecDeque<(f64, Received)>,
    link_free_at: f64,
    stats: FaultStats,
    in_outage: bool,
    events: VecDeque<LinkEvent>,
}

impl<L: Link> std::fmt::Debug for FaultyLink<L> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FaultyLink")
            .field("cfg", &self.cfg)
            .field("stats", &self.stats)
            .finish_non_exhaustive()
    }
}

impl<L: Link> FaultyLink<L> {
    /// Wraps `inner`. `Err` if the configuration is out of range.
    pub fn new(inner: L, cfg: FaultConfig, clock: Arc<dyn Clock>) -> Result<Self, LinkError> {
        cfg.validate()?;
        Ok(Self {
            inner,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            cfg,
            clock,
            order: 0,
            scheduled: BinaryHeap::new(),
            held: VecDeque::new(),
            link_free_at: f64::NEG_INFINITY,
            stats: FaultStats::default(),
            in_outage: false,
            events: VecDeque::new(),
        })
    }

    /// Fault-layer counters (`in_flight` is current).
    pub fn fault_stats(&self) -> FaultStats {
        FaultStats {
            in_flight: (self.scheduled.len() + self.held.len()) as u64,
            ..self.stats
        }
    }

    /// The wrapped link.
    pub fn inner(&self) -> &L {
        &self.inner
    }

    /// End of the outage window containing `t` on this link, if any.
    fn outage_end(&self, t: f64) -> Option<f64> {
        let (a, b) = (self.inner.local_id(), self.inner.peer_id());
        let cuts = |p: &Partition| p.side.contains(&a) != p.side.contains(&b);
        self.cfg
            .outages
            .iter()
            .chain(
                self.cfg
                    .partitions
                    .iter()
                    .filter(|p| cuts(p))
                    .map(|p| &p.window),
            )
            .filter(|w| w.contains(t))
            .map(|w| w.end)
            .reduce(f64::max)
    }

    /// Outage state edges → synthetic peer events.
    fn update_outage_events(&mut self, now: f64) {
        let cut = self.outage_end(now).is_some();
        if cut != self.in_outage {
            self.in_outage = cut;
            if self.cfg.signal_outages {
                self.events.push_back(if cut {
                    LinkEvent::PeerDown
                } else {
                    LinkEvent::PeerUp
                });
            }
        }
    }

    /// Steps 2–5 of the pipeline for a message entering at `t`: the copies that survive, each
    /// with its due time (the second only when the message is duplicated).
    fn route(&mut self, t: f64, msg: Received) -> [Option<(f64, Received)>; 2] {
        // Fixed draws per message keep the random stream aligned across configurations.
        let u_loss: f64 = self.rng.random();
        let u_dup: f64 = self.rng.random();
        let u_jit: [f64; 2] = [self.rng.random(), self.rng.random()];
        let u_reo: [f64; 2] = [self.rng.random(), self.rng.random()];
        if u_loss < self.cfg.loss {
            self.stats.dropped_loss += 1;
            return [None, None];
        }
        let copies = if u_dup < self.cfg.duplicate {
            self.stats.duplicated += 1;
            let dup = Received::clone_owned(&msg);
            [Some(msg), Some(dup)]
        } else {
            [Some(msg), None]
        };
        let mut out = [None, None];
        for (k, m) in copies.into_iter().enumerate() {
            let Some(m) = m else { continue };
            let mut done = t;
            if let Some(bw) = self.cfg.bandwidth {
                let start = t.max(self.link_free_at);
                let backlog = (start - t) * bw.bytes_per_s;
                let len = m.message_bytes().len() as f64;
                if backlog > bw.queue_bytes as f64 {
                    self.stats.dropped_bandwidth += 1;
                    continue;
                }
                self.link_free_at = start + len / bw.bytes_per_s;
                done = self.link_free_at;
            }
            let mut due = done + self.cfg.delay + u_jit[k] * self.cfg.jitter;
            if u_reo[k] < self.cfg.reorder {
                due += self.cfg.reorder_delay;
            }
            out[k] = Some((due, m));
        }
        out
    }

    /// Holds `msg` until `due`: the one place the layer copies a message out of a backend
    /// buffer (it may hold more messages, for longer, than a backend lends).
    fn schedule(&mut self, due: f64, msg: Received) {
        if msg.is_borrowed() {
            self.stats.copied += 1;
        }
        self.order += 1;
        self.scheduled.push(Reverse(Scheduled {
            due,
            order: self.order,
            msg: msg.into_owned(),
        }));
    }

    /// Step 1 for a message taken from the inner link at `now`. Returns it when it is due now
    /// and nothing held is due before it — handed over as the backend gave it (zero-copy);
    /// whatever must wait is held (copied).
    fn offer(&mut self, now: f64, msg: Received) -> Option<Received> {
        self.stats.offered += 1;
        match (self.outage_end(now), self.cfg.outage_policy) {
            (None, _) => {
                let mut now_out = None;
                for (due, m) in self.route(now, msg).into_iter().flatten() {
                    let first = self.scheduled.peek().is_none_or(|Reverse(s)| s.due > due);
                    if now_out.is_none() && due <= now && first {
                        now_out = Some(m);
                    } else {
                        self.schedule(due, m);
                    }
                }
                if now_out.is_some() {
                    self.stats.delivered += 1;
                }
                now_out
            }
            (Some(_), OutagePolicy::Drop) => {
                self.stats.dropped_outage += 1;
                None
            }
            (Some(end), OutagePolicy::Queue { max_messages }) => {
                if self.held.len() >= max_messages {
                    self.stats.dropped_outage_overflow += 1;
                } else {
                    if msg.is_borrowed() {
                        self.stats.copied += 1;
                    }
                    self.held.push_back((end, msg.into_owned()));
                }
                None
            }
        }
    }

    /// Moves held messages whose outage ended back into the pipeline.
    fn release_held(&mut self, now: f64) {
        let mut keep = VecDeque::new();
        while let Some((end, m)) = self.held.pop_front() {
            if end <= now {
                // A later window may have started at `end`: re-check at the release time.
                match self.outage_end(end) {
                    Some(e2) if e2 > end => keep.push_back((e2, m)),
                    _ => {
                        for (due, c) in self.route(end, m).into_iter().flatten() {
                            self.schedule(due, c);
                        }
                    }
                }
            } else {
                keep.push_back((end, m));
            }
        }
        self.held = keep;
    }

    fn pop_due(&mut self, now: f64) -> Option<Received> {
        if self.scheduled.peek().is_some_and(|Reverse(s)| s.due <= now) {
            let Reverse(s) = self.scheduled.pop()?;
            self.stats.delivered += 1;
            return Some(s.msg);
        }
        None
    }

    /// The next message due now: one already held, else the next one from the inner link that
    /// is due at once (taken one at a time, so it is handed over zero-copy; messages that must
    /// wait are held and the next is taken).
    fn step(&mut self) -> Result<Option<Received>, LinkError> {
        let now = self.clock.now();
        self.update_outage_events(now);
        self.release_held(now);
        if let Some(m) = self.pop_due(now) {
            return Ok(Some(m));
        }
        while let Some(m) = self.inner.try_recv()? {
            if let Some(m) = self.offer(now, m) {
                return Ok(Some(m));
            }
        }
        Ok(None)
    }

    fn next_due(&self) -> Option<f64> {
        let s = self.scheduled.peek().map(|Reverse(s)| s.due);
        let h = self.held.iter().map(|(e, _)| *e).reduce(f64::min);
        match (s, h) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }
}

impl<L: Link> Link for FaultyLink<L> {
    fn local_id(&self) -> NodeId {
        self.inner.local_id()
    }
    fn peer_id(&self) -> NodeId {
        self.inner.peer_id()
    }
    fn send(&mut self, meta: &SendMeta, body: &dyn WireBody) -> Result<(), LinkError> {
        self.inner.send(meta, body)
    }
    fn try_recv(&mut self) -> Result<Option<Received>, LinkError> {
        self.step()
    }
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(m) = self.step()? {
                return Ok(Some(m));
            }
            let now_wall = Instant::now();
            if now_wall >= deadline {
                return Ok(None);
            }
            let mut wait = deadline - now_wall;
            if let Some(due) = self.next_due() {
                let dt = (due - self.clock.now()).max(0.0);
                // Wake for the next release (at least 100 µs to avoid spinning).
                wait = wait.min(Duration::from_secs_f64(dt).max(Duration::from_micros(100)));
            }
            if let Some(m) = self.inner.recv_timeout(wait)? {
                let now = self.clock.now();
                self.update_outage_events(now);
                self.release_held(now);
                if let Some(m) = self.offer(now, m) {
                    return Ok(Some(m));
                }
            }
        }
    }
    fn poll_event(&mut self) -> Option<LinkEvent> {
        let now = self.clock.now();
        self.update_outage_events(now);
        if let Some(e) = self.events.pop_front() {
            return Some(e);
        }
        self.inner.poll_event()
    }
    fn peer_state(&self) -> PeerState {
        if self.in_outage && self.cfg.signal_outages {
            PeerState::Down
        } else {
            self.inner.peer_state()
        }
    }
    fn stats(&self) -> LinkStats {
        self.inner.stats()
    }
}
