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
//! A [`Radio`] models a radio link's direction with the same pipeline: its capacity is the
//! serialiser of step 4 (drop-tail behind `queue_bytes`), its latency adds to the delay of
//! step 5, and a [`RangeLimit`] makes the link available only while the two ends are within
//! range (out of range: every message is dropped and the peer reported down, like an outage;
//! near the edge: an extra loss probability rising linearly to `edge_loss` at the range).
//! The radio's channel takes each message at its send time stamp (the envelope's `sim_time`,
//! the sender's clock), not when the receiving end polls: the queue it models is the sender's,
//! and in a multi-process run the two ends' clocks differ by up to the flow-control lead.
//! Faults still act on the inbound direction only; so that a sender can keep its offered load
//! within the capacity, the layer also keeps a *mirror* of its outbound direction — the same
//! serialiser fed with what this end sends, on the same time stamps
//! ([`FaultyLink::outbound`]): the bytes still waiting for the channel, as the peer's inbound
//! layer will see them.
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

/// Distance between the two ends of a link over time, for [`RangeLimit`] (the node crate
/// evaluates the vehicles' true trajectories; the transport knows no geometry).
pub trait Separation: Send + Sync + std::fmt::Debug {
    /// Distance [m] between the two ends at clock time `t` [s].
    fn distance_m(&self, t: f64) -> f64;
}

/// Range-limited availability of a radio link: up while the two ends are within `range_m`,
/// with an extra loss probability rising linearly from 0 at `(1 − edge_fraction)·range_m` to
/// `edge_loss` at `range_m`.
#[derive(Clone, Debug)]
pub struct RangeLimit {
    /// Range [m], > 0.
    pub range_m: f64,
    /// Outer fraction of the range in which loss rises, in [0, 1].
    pub edge_fraction: f64,
    /// Loss probability at the range, in [0, 1].
    pub edge_loss: f64,
    /// Distance of the two ends over time.
    pub separation: Arc<dyn Separation>,
}

impl PartialEq for RangeLimit {
    fn eq(&self, o: &Self) -> bool {
        self.range_m == o.range_m
            && self.edge_fraction == o.edge_fraction
            && self.edge_loss == o.edge_loss
            && std::ptr::addr_eq(Arc::as_ptr(&self.separation), Arc::as_ptr(&o.separation))
    }
}

impl RangeLimit {
    /// Whether the two ends are within range at `t`.
    pub fn in_range(&self, t: f64) -> bool {
        self.separation.distance_m(t) <= self.range_m
    }

    /// The edge loss probability at distance `d` [m] (0 well inside, `edge_loss` at the range;
    /// beyond the range the link is down, which is not a loss probability).
    pub fn edge_loss_at(&self, d: f64) -> f64 {
        let inner = (1.0 - self.edge_fraction) * self.range_m;
        if d <= inner || self.edge_fraction <= 0.0 {
            0.0
        } else {
            let x = ((d - inner) / (self.edge_fraction * self.range_m)).min(1.0);
            self.edge_loss * x
        }
    }
}

/// One direction of a radio link: a channel of `bytes_per_s` behind a drop-tail queue of
/// `queue_bytes`, a fixed latency, and optionally range-limited availability.
#[derive(Debug, Clone, PartialEq)]
pub struct Radio {
    /// Capacity of this direction [bytes/s], > 0 (the envelope's 64 bytes count).
    pub bytes_per_s: f64,
    /// Bytes allowed to wait for the channel; a message that finds more ahead of it is dropped
    /// (drop-tail, counted in [`FaultStats::dropped_bandwidth`]).
    pub queue_bytes: u64,
    /// Latency after the last byte left [s], ≥ 0.
    pub latency: f64,
    /// Range-limited availability (`None`: always in range).
    pub range: Option<RangeLimit>,
}

/// The outbound direction of a radio link as this end sees it ([`FaultyLink::outbound`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutboundRadio {
    /// Capacity of the direction [bytes/s].
    pub bytes_per_s: f64,
    /// Bytes sent that are still waiting for the channel now.
    pub queued_bytes: f64,
    /// The queue bound of the direction.
    pub queue_bytes: u64,
    /// Largest `queued_bytes` right after a send so far.
    pub peak_queued_bytes: f64,
    /// Sends that found the mirrored queue full (the peer's layer drops them).
    pub over_queue: u64,
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
    /// Optional radio model (capacity, latency, range); exclusive with `bandwidth`.
    pub radio: Option<Radio>,
    /// Report `PeerDown` / `PeerUp` at the edges of outage windows (and of range).
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
            radio: None,
            signal_outages: true,
        }
    }

    /// The serialiser of step 4: the bandwidth cap or the radio's capacity.
    fn channel(&self) -> Option<Bandwidth> {
        self.bandwidth.or(self.radio.as_ref().map(|r| Bandwidth {
            bytes_per_s: r.bytes_per_s,
            queue_bytes: r.queue_bytes,
        }))
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
        if let Some(r) = &self.radio {
            if self.bandwidth.is_some() {
                return bad("a radio link has its capacity; give a bandwidth cap or a radio");
            }
            if !(r.bytes_per_s.is_finite() && r.bytes_per_s > 0.0) {
                return bad("radio capacity must be finite and > 0");
            }
            if !(r.latency.is_finite() && r.latency >= 0.0) {
                return bad("radio latency must be finite and >= 0");
            }
            if let Some(g) = &r.range {
                if !(g.range_m.is_finite() && g.range_m > 0.0) {
                    return bad("radio range must be finite and > 0");
                }
                for (name, p) in [
                    ("edge_fraction", g.edge_fraction),
                    ("edge_loss", g.edge_loss),
                ] {
                    if !(0.0..=1.0).contains(&p) {
                        return bad(&format!("radio {name} = {p} is not in [0, 1]"));
                    }
                }
            }
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
    /// Dropped by the queue bound of the bandwidth cap or the radio's capacity (drop-tail).
    pub dropped_bandwidth: u64,
    /// Dropped because the radio's ends were out of range.
    pub dropped_range: u64,
    /// Dropped by the radio's edge loss (near the end of its range).
    pub dropped_edge: u64,
    /// Bytes of the messages handed to the application.
    pub delivered_bytes: u64,
    /// Largest backlog the bandwidth cap or radio queue held ahead of an arriving message
    /// [bytes].
    pub peak_queue_bytes: u64,
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
            + self.dropped_range
            + self.dropped_edge
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
    /// The radio's outbound mirror: when the channel is free of what this end sent.
    out_free_at: f64,
    out_peak: f64,
    out_over_queue: u64,
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
            out_free_at: f64::NEG_INFINITY,
            out_peak: 0.0,
            out_over_queue: 0,
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

    /// The outbound direction of a radio link now (`None` without a radio): what this end has
    /// sent that is still waiting for the channel, mirrored on this end's clock. An upper
    /// bound of the peer's inbound queue: messages the peer's layer drops before the channel
    /// (loss, outage, out of range) do not occupy it there but are counted here, so a sender
    /// that keeps this mirror within bounds never over-offers.
    pub fn outbound(&self) -> Option<OutboundRadio> {
        let r = self.cfg.radio.as_ref()?;
        let now = self.clock.now();
        Some(OutboundRadio {
            bytes_per_s: r.bytes_per_s,
            queued_bytes: ((self.out_free_at - now) * r.bytes_per_s).max(0.0),
            queue_bytes: r.queue_bytes,
            peak_queued_bytes: self.out_peak,
            over_queue: self.out_over_queue,
        })
    }

    /// Distance of the two ends now, for a range-limited radio.
    pub fn distance_m(&self) -> Option<f64> {
        let g = self.cfg.radio.as_ref()?.range.as_ref()?;
        Some(g.separation.distance_m(self.clock.now()))
    }

    /// The radio's range limit, if any.
    fn range(&self) -> Option<&RangeLimit> {
        self.cfg.radio.as_ref().and_then(|r| r.range.as_ref())
    }

    /// Whether a range-limited radio is out of range at `t`.
    fn out_of_range(&self, t: f64) -> bool {
        self.range().is_some_and(|g| !g.in_range(t))
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
        let cut = self.outage_end(now).is_some() || self.out_of_range(now);
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
        // One more draw only with a range limit, so other configurations keep their streams.
        let u_edge: Option<f64> = self.range().is_some().then(|| self.rng.random());
        if u_loss < self.cfg.loss {
            self.stats.dropped_loss += 1;
            return [None, None];
        }
        if let (Some(g), Some(u)) = (self.range(), u_edge) {
            let d = g.separation.distance_m(t);
            if d > g.range_m {
                self.stats.dropped_range += 1;
                return [None, None];
            }
            if u < g.edge_loss_at(d) {
                self.stats.dropped_edge += 1;
                return [None, None];
            }
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
            if let Some(bw) = self.cfg.channel() {
                let start = t.max(self.link_free_at);
                let backlog = (start - t) * bw.bytes_per_s;
                let len = m.message_bytes().len() as f64;
                if backlog > bw.queue_bytes as f64 {
                    self.stats.dropped_bandwidth += 1;
                    continue;
                }
                self.stats.peak_queue_bytes = self.stats.peak_queue_bytes.max(backlog as u64);
                self.link_free_at = start + len / bw.bytes_per_s;
                done = self.link_free_at;
            }
            let latency = self.cfg.radio.as_ref().map_or(0.0, |r| r.latency);
            let mut due = done + self.cfg.delay + latency + u_jit[k] * self.cfg.jitter;
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
                let entry = self.entry_time(now, &msg);
                for (due, m) in self.route(entry, msg).into_iter().flatten() {
                    let first = self.scheduled.peek().is_none_or(|Reverse(s)| s.due > due);
                    if now_out.is_none() && due <= now && first {
                        now_out = Some(m);
                    } else {
                        self.schedule(due, m);
                    }
                }
                if let Some(m) = &now_out {
                    self.stats.delivered += 1;
                    self.stats.delivered_bytes += m.message_bytes().len() as u64;
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

    /// When a message taken from the inner link at `now` enters steps 2–5: `now`, except on a
    /// radio, whose channel takes it at its send time stamp (the envelope's `sim_time`, on the
    /// sender's clock) — the radio's queue is the sender's, so the drop-tail decisions do not
    /// depend on when this end happens to poll, and they agree with the sender's
    /// [`outbound`](Self::outbound) mirror whatever the skew between the two ends' clocks. A
    /// message stamped ahead of `now` is held until its arrival time on this end's clock.
    fn entry_time(&self, now: f64, msg: &Received) -> f64 {
        let stamp = msg.header().sim_time;
        if self.cfg.radio.is_some() && stamp.is_finite() {
            stamp
        } else {
            now
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
            self.stats.delivered_bytes += s.msg.message_bytes().len() as u64;
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
        let Some(rate) = self.cfg.radio.as_ref().map(|r| r.bytes_per_s) else {
            return self.inner.send(meta, body);
        };
        // The outbound mirror: the bytes the backend took, through the same serialiser.
        let before = self.inner.stats().sent_bytes;
        let result = self.inner.send(meta, body);
        let len = self.inner.stats().sent_bytes.saturating_sub(before);
        if len > 0 {
            // On the send time stamp, as the peer's inbound radio takes it (`entry_time`).
            let now = if meta.sim_time.is_finite() {
                meta.sim_time
            } else {
                self.clock.now()
            };
            let start = now.max(self.out_free_at);
            let queue = self.cfg.radio.as_ref().map_or(0, |r| r.queue_bytes) as f64;
            if (start - now) * rate > queue {
                // The peer's layer drops it; the channel stays as it was.
                self.out_over_queue += 1;
            } else {
                self.out_free_at = start + len as f64 / rate;
                self.out_peak = self.out_peak.max((self.out_free_at - now) * rate);
            }
        }
        result
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
