//! The vehicle process: one [`VehicleEstimator`] (inertial SLAM) fed by its sensor stream from
//! the world, and its [`crate::agent::VehicleFusion`] (DDF node) on a fusion thread, fusing over its
//! configured links.
//!
//! Threads: the estimator thread (this one) applies IMU samples and frames, owns the links and
//! reports; at each round time it hands its filter to the fusion thread and goes on predicting
//! the vehicle's part of it, and takes the fused filter back when it is done, applying the IMU
//! samples of the meantime to it again (`fusion_thread` module docs). A frame that arrives
//! while a round is out waits for it (a frame changes the map, which is being fused). Rounds of the vehicles of a team are spread over the round
//! period (`round_phase`).
//!
//! Time is the vehicle's simulation time: the time of the last IMU sample applied. It drives
//! the fusion rounds (`[fusion].rate_hz`), the record times (`[run].record_interval_s`), the DDF
//! timers and the fault layer of every link (so fault schedules are in simulated seconds, as in
//! `canopy sim`). Each process start draws a fresh random DDF epoch; a restarted vehicle
//! re-initialises from the world's external fix and its neighbours resynchronise it.
//!
//! Reports to the monitor: at every record time the estimate (state, 15×15 covariance,
//! counters, link statistics, the associations of the frames since the last report) and the
//! map (ids, means, 3×3 covariances); the last map at the end of the stream or at shutdown.
//! Estimator inputs that fail validation are counted, never fatal.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use canopy_fusion::ins::{VehicleState, VehicleVector};
use canopy_fusion::state::VEHICLE_DIM;
use canopy_fusion::topology::NodeId;
use canopy_transport::link::{Link, LinkEvent, PeerState};
use canopy_transport::{MessageKind, NodeId as WireId};
use nalgebra::SMatrix;

use super::delivery::{Due, SimTimeDelivery};
use super::fusion_thread::{Done, FusionThread, FusionView, Job};
use super::protocol::{
    Control, EstimateReport, FeatureReport, FrameAssociations, InitMsg, MONITOR_ID, MapReport,
    Progress, Report, SensorItem, VehicleCounters, WORLD_ID, WorldMsg,
};
use super::world::stream_buffer;
use super::{
    FusionLinks, RoleCommon, control_link, decode_body, fresh_epoch, link_report, load_resolved,
    naive_round_bytes, send_body, stop_flag,
};
use crate::agent::{VehicleAgent, VehicleEstimator};
use crate::scenario::{Scenario, VehicleConfig};
use crate::world::{InitialEstimate, World};

/// How long a vehicle waits for its initialisation.
const INIT_TIMEOUT: Duration = Duration::from_secs(120);
/// How often a process tells the monitor what it is doing (`Report::Status`).
pub(crate) const STATUS_INTERVAL: Duration = Duration::from_secs(1);
/// Arrival delivery: how long the first round waits for the vehicle's fault-free links to come
/// up (zenoh links connect within seconds; a team running at many times real time would
/// otherwise fuse over them only from whenever that happened to be in simulated time).
const LINK_WAIT: Duration = Duration::from_secs(60);
/// After the end of its stream, how long a vehicle keeps serving its links without hearing
/// from the monitor.
const LINGER_TIMEOUT: Duration = Duration::from_secs(120);

struct Vehicle<'s> {
    s: &'s Scenario,
    /// This vehicle's IMU rate [Hz].
    cfg_imu_rate: f64,
    incarnation: u32,
    estimator: VehicleEstimator,
    fusion: FusionThread,
    /// The fusion thread's counters and channels, as of its last finished job.
    view: FusionView,
    links: FusionLinks,
    monitor: canopy_transport::iceoryx::IceoryxLink,
    counters: VehicleCounters,
    associations: Vec<FrameAssociations>,
    t: f64,
    next_round: f64,
    next_record: f64,
    last_report: f64,
    /// Bytes the naive scheme would have sent per link so far (`naive_round_bytes`).
    naive_bytes: u64,
    /// Stall of the estimator by fusion work (see [`StallMeter`]).
    stall: StallMeter,
    /// Fused copies the estimator could not take back (the contract of deferred fusion broken;
    /// the round's fusion is lost, never applied twice).
    give_back_failed: u64,
    /// A round found due at the last IMU sample, not yet sent to the fusion thread.
    round_due: Option<f64>,
    /// The fusion thread ended while it held the filter (a bug): the process fails.
    fusion_lost: bool,
    /// `[fusion] delivery = "simulation_time"`: what the links deliver waits for its round.
    delivery: Option<SimTimeDelivery>,
    /// SIGTERM / Ctrl-C.
    stop: Arc<std::sync::atomic::AtomicBool>,
    /// The monitor's Shutdown arrived while waiting for the neighbours.
    shutdown: bool,
    /// Neighbours on fault-free links without radio model: waited for (their link up at the
    /// first round; with simulation-time delivery, their time markers at every round).
    gated: Vec<WireId>,
    /// The first round has been dispatched.
    first_round_done: bool,
}

/// How long fusion work holds up the estimator thread: the time spent on it between two
/// consecutive IMU samples, one figure per IMU interval that saw any, as wall time (includes
/// waiting for a core while other processes run, and waiting for the fusion thread) and as this
/// thread's CPU time (the work itself). The estimator thread's share of fusion is moving
/// messages between the links and the fusion thread, handing the filter over and taking the
/// fused filter back, and waiting for a round a frame needs. Printed to the vehicle's log at
/// the end (`fusion stall: …`, read by `scripts/bench.sh`).
#[derive(Debug, Default)]
struct StallMeter {
    /// Fusion (wall, CPU) time since the last IMU sample [s].
    pending: (f64, f64),
    /// One (wall, CPU) entry per IMU interval with fusion work [s].
    stalls: Vec<(f64, f64)>,
    /// CPU time of every piece of fusion work, by kind [s] (where the stall goes).
    pieces: [Vec<f64>; 3],
}

/// What a piece of fusion work on the estimator thread was, for [`StallMeter`]'s breakdown.
#[derive(Debug, Clone, Copy)]
enum Work {
    /// Link events and DDF messages to and from the fusion thread (decoding, encoding).
    Messages = 0,
    /// Handing the filter over for a round, and taking the fused filter back.
    Lend = 1,
    /// Waiting for a round that a frame (or the end of the stream) needs.
    Wait = 2,
}

/// A start mark: wall clock and this thread's CPU clock.
#[derive(Debug, Clone, Copy)]
struct Mark(Instant, f64);

/// This thread's CPU time [s] (0 where the clock is unavailable).
fn thread_cpu_s() -> f64 {
    use nix::time::{ClockId, clock_gettime};
    clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID)
        .map(|t| t.tv_sec() as f64 + 1e-9 * t.tv_nsec() as f64)
        .unwrap_or(0.0)
}

impl StallMeter {
    fn mark() -> Mark {
        Mark(Instant::now(), thread_cpu_s())
    }
    fn add(&mut self, since: Mark, work: Work) {
        let cpu = (thread_cpu_s() - since.1).max(0.0);
        self.pending.0 += since.0.elapsed().as_secs_f64();
        self.pending.1 += cpu;
        self.pieces[work as usize].push(cpu);
    }
    fn on_imu(&mut self) {
        if self.pending.0 > 0.0 {
            self.stalls.push(self.pending);
            self.pending = (0.0, 0.0);
        }
    }
    /// `fusion stall: n=… cpu_max_ms=… cpu_p99_ms=… cpu_p50_ms=… cpu_over_imu_period=…
    /// wall_max_ms=… wall_p99_ms=… wall_p50_ms=… wall_over_imu_period=… imu_period_ms=…
    /// features=…` (`imu_period` in s).
    fn summary(&self, imu_period: f64, features: usize) -> String {
        let stats = |pick: fn(&(f64, f64)) -> f64| {
            let v = sorted(self.stalls.iter().map(pick));
            (
                quantile_ms(&v, 1.0),
                quantile_ms(&v, 0.99),
                quantile_ms(&v, 0.5),
                v.iter().filter(|&&x| x > imu_period).count(),
            )
        };
        let c = stats(|x| x.1);
        let w = stats(|x| x.0);
        let pieces: Vec<String> = ["messages", "lend", "wait"]
            .iter()
            .zip(&self.pieces)
            .map(|(name, v)| {
                let v = sorted(v.iter().copied());
                format!(
                    "{name}_cpu_max_ms={:.3} {name}_cpu_p99_ms={:.3}",
                    quantile_ms(&v, 1.0),
                    quantile_ms(&v, 0.99)
                )
            })
            .collect();
        format!(
            "fusion stall: n={} cpu_max_ms={:.3} cpu_p99_ms={:.3} cpu_p50_ms={:.3} \
             cpu_over_imu_period={} wall_max_ms={:.3} wall_p99_ms={:.3} wall_p50_ms={:.3} \
             wall_over_imu_period={} imu_period_ms={:.1} features={features} {}",
            self.stalls.len(),
            c.0,
            c.1,
            c.2,
            c.3,
            w.0,
            w.1,
            w.2,
            w.3,
            imu_period * 1e3,
            pieces.join(" "),
        )
    }
}

/// The values in ascending order.
fn sorted(values: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut v: Vec<f64> = values.collect();
    v.sort_by(f64::total_cmp);
    v
}

/// The `p` quantile (nearest rank) of ascending times in s, in ms; 0 when there are none.
fn quantile_ms(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        0.0
    } else {
        sorted[((sorted.len() - 1) as f64 * p).round() as usize] * 1e3
    }
}

/// Where in the round period this vehicle's rounds fall, as a fraction of the period: the
/// vehicles of a scenario spread evenly over it (scenario order). Rounds at the same instant
/// would make every vehicle process want a core at once; spread out, the processes of a
/// team take turns (measured with rounds still on the estimator thread, 1 Hz, four vehicles on
/// two cores at real time: the longest wall-clock stall of the estimator by fusion work fell
/// from ~12 ms, twice its CPU time, to its CPU time). The DDF does not care when a node's
/// round falls: deltas commute.
fn round_phase(s: &Scenario, id: WireId) -> f64 {
    let n = s.vehicles.len().max(1);
    let i = s.vehicles.iter().position(|v| v.id == id).unwrap_or(0);
    i as f64 / n as f64
}

fn initial_from(m: &InitMsg) -> InitialEstimate {
    let x = VehicleState::from_vector(&VehicleVector::from_column_slice(&m.state));
    InitialEstimate {
        time: m.time,
        position: x.position,
        velocity: x.velocity,
        attitude: x.attitude,
        accel_bias: x.accel_bias,
        gyro_bias: x.gyro_bias,
        covariance: SMatrix::<f64, VEHICLE_DIM, VEHICLE_DIM>::from_row_slice(&m.covariance),
    }
}

fn build_agent(
    s: &Scenario,
    cfg: &VehicleConfig,
    world: &World,
    init: &InitMsg,
    incarnation: u32,
    epoch: u64,
) -> Result<VehicleAgent> {
    crate::sim::vehicle_agent(s, cfg, world, &initial_from(init), incarnation, epoch)
        .with_context(|| format!("building the estimator of {}", cfg.display_name()))
}

impl Vehicle<'_> {
    fn report(&mut self, r: &Report) {
        let _ = send_body(&mut self.monitor, r.kind(), 0, self.t, r);
    }

    /// Link events and DDF messages waiting now go to the fusion thread; what it has finished
    /// comes back (replies sent, a fused round taken back).
    fn service_links(&mut self) {
        if let Some(d) = self.delivery.as_mut() {
            // Simulation-time delivery: everything waits for its round (`dispatch_round`), and
            // the fused copy is taken back at the next frame, not when it happens to be ready.
            for p in self.links.poll_stamped() {
                d.push(p.peer, p.events, p.msgs, p.marker);
            }
            return;
        }
        let now = self.t;
        // Messages go to the fusion thread as received (their wire bytes, about half the dense
        // form) and are decoded there one at a time when it takes them: decoded here, the
        // dense deltas that arrive during a round waited in the job queue beside the round's
        // own k × k matrices (tree-8, three neighbours: 65–130 MB at the memory peak). They
        // are still taken off the links at once: a sample left in an iceoryx2 subscriber's
        // buffer makes the sender write its next ones into further slots of its pool, each of
        // which then stays resident.
        let polled = self.links.poll_raw();
        let start = StallMeter::mark();
        let busy = !polled.is_empty();
        for (peer, events, msgs) in polled {
            for ev in events {
                self.fusion.submit(match ev {
                    LinkEvent::PeerUp => Job::LinkUp {
                        now,
                        peer: NodeId(peer),
                    },
                    LinkEvent::PeerDown => Job::LinkDown { peer: NodeId(peer) },
                });
            }
            for msg in msgs {
                self.fusion.submit(Job::Received {
                    now,
                    from: NodeId(peer),
                    msg,
                });
            }
        }
        if busy {
            self.stall.add(start, Work::Messages);
        }
        while let Some(done) = self.fusion.try_done() {
            self.on_done(done);
        }
    }

    /// A finished job of the fusion thread.
    fn on_done(&mut self, done: Done) {
        let start = StallMeter::mark();
        match done {
            Done::Replies { now, out, view } => {
                self.view = view;
                self.links
                    .send_wire(if now.is_finite() { now } else { self.t }, out);
                self.stall.add(start, Work::Messages);
            }
            Done::Send { now, out } => {
                self.links.send_wire(now, vec![out]);
                self.stall.add(start, Work::Messages);
            }
            Done::Round {
                now,
                filter,
                remote,
                view,
            } => {
                self.view = view;
                // Data sharing: the other vehicles' frames the round processed, audited by the
                // monitor against their own true ids.
                self.associations.extend(remote.into_iter().map(|f| {
                    FrameAssociations::from_report(f.time, &f.report).from_origin(f.origin.0)
                }));
                if self.estimator.give_back(*filter).is_err() {
                    self.give_back_failed += 1;
                }
                // The round may have moved the filter into the team frame (own frames).
                self.estimator.set_frame_owner(self.view.frame_owner);
                self.stall.add(start, Work::Lend);
                if self.delivery.is_some() {
                    // Everything this vehicle stamps up to `now` has gone (the round's
                    // messages came ahead of it, `Done::Send`).
                    let start = StallMeter::mark();
                    self.links.send_marker(now);
                    self.stall.add(start, Work::Messages);
                }
            }
        }
    }

    /// Waits until the round lent out (if any) is back.
    fn wait_for_round(&mut self) {
        while self.estimator.is_lent() {
            let start = StallMeter::mark();
            let done = self.fusion.wait_done();
            self.stall.add(start, Work::Wait);
            match done {
                Some(d) => self.on_done(d),
                // The fusion thread is gone (it cannot be, short of a bug), and the filter
                // lent to it with it: the run loop ends this process with that reason.
                None => {
                    self.fusion_lost = true;
                    break;
                }
            }
        }
    }

    fn counters(&self) -> VehicleCounters {
        let c = self.estimator.counters().with_fusion(self.view.counters);
        VehicleCounters {
            imu_samples: c.imu_samples,
            inputs_rejected: self.counters.inputs_rejected,
            frames: c.frames,
            observations: c.observations,
            rounds: c.fusion.rounds,
            fused: c.fusion.fused,
            fuse_refused: c.fusion.fuse_refused + self.give_back_failed,
            messages_rejected: c.fusion.messages_rejected,
            ci_fused: c.fusion.ci_fused,
            stream_gaps: self.counters.stream_gaps,
            rejections: {
                let mut r = self.estimator.rejections().clone();
                r.merge(&self.view.rejections);
                r.merge(&self.links.send_failures.counts);
                r.counts
            },
            merges_adopted: self.view.node.merges_adopted,
            merges_refused: self.view.node.merges_refused,
            peak_rss_bytes: super::peak_rss_bytes(),
            access_refused: super::access_refusals(),
            alignment: self.view.alignment.clone().map(Box::new),
        }
    }

    fn estimate_report(&mut self) {
        let f = self.estimator.filter();
        let v = self.estimator.vehicle_index();
        let (Ok(x), Ok(p)) = (f.vehicle_state(v), f.vehicle_covariance(v)) else {
            return;
        };
        let links = self
            .links
            .links
            .iter()
            .map(|(&peer, l)| {
                link_report(peer, l, self.view.channel(NodeId(peer)), self.naive_bytes)
            })
            .collect();
        let r = Report::Estimate(EstimateReport {
            t: self.t,
            state: x.to_vector().as_slice().to_vec(),
            covariance: p.transpose().as_slice().to_vec(),
            counters: self.counters(),
            links,
            associations: std::mem::take(&mut self.associations),
            frame_owner: self.estimator.frame_owner().map(|o| o.0),
        });
        self.report(&r);
        self.last_report = self.t;
    }

    fn map_report(&mut self, last: bool) {
        // The map as lent while a round is out (prediction does not change it).
        let features = self
            .estimator
            .map()
            .iter()
            .map(|(id, m, c)| FeatureReport {
                id: *id,
                mean: [m.x, m.y, m.z],
                cov: canopy_fusion::ddf::upper_triangle(c),
            })
            .collect();
        let r = Report::Map(MapReport {
            t: self.t,
            last,
            features,
            merges: self.view.merges.clone(),
            frame_owner: self.estimator.frame_owner().map(|o| o.0),
        });
        self.report(&r);
    }

    /// Hands the filter to the fusion thread for the round due at `now`.
    fn dispatch_round(&mut self, now: f64) {
        // Rounds closer than the fusion thread takes: one at a time.
        self.wait_for_round();
        self.links.clock.set(now.max(self.t));
        self.service_links();
        self.deliver_due(now);
        self.naive_bytes += naive_round_bytes(self.estimator.num_features());
        let start = StallMeter::mark();
        let filter = match self.estimator.lend() {
            Ok(f) => Box::new(f),
            // Out already: only if the fusion thread is gone (`fusion_lost`, a bug); counted.
            Err(_) => return,
        };
        let budgets = crate::radio::capacity_budgets(
            self.links.links.iter().map(|(&p, l)| (NodeId(p), l)),
            self.s.fusion.budget_rate_hz(),
        );
        self.fusion.submit(Job::Round {
            now,
            filter,
            budgets,
            records: self.estimator.take_records(),
        });
        self.stall.add(start, Work::Lend);
    }

    /// Before the round at `round`. Simulation-time delivery: waits until every gated neighbour
    /// has sent what it stamps up to `round` − one period (`delivery`), then hands the fusion
    /// thread what is due, in order. Arrival delivery: before the first round only, waits (up to
    /// [`LINK_WAIT`]) for the gated links to come up, so the team starts fusing over them at the
    /// same simulated time whatever the time zenoh takes to connect.
    fn deliver_due(&mut self, round: f64) {
        if self.delivery.is_none() {
            // Arrival delivery: the first round waits for the links to come up (below).
            if !std::mem::replace(&mut self.first_round_done, true) {
                self.wait_for_neighbours(
                    None,
                    |v| v.links_down(),
                    |w| {
                        format!(
                            "waiting for the link(s) to {w:?} to come up before the first round"
                        )
                    },
                );
            }
            return;
        }
        let period = 1.0 / self.s.fusion.rate_hz;
        self.wait_for_neighbours(
            Some(round),
            |v| {
                v.delivery
                    .as_ref()
                    .map(|d| d.waiting_for(round))
                    .unwrap_or_default()
            },
            |w| {
                format!(
                    "waiting for neighbour(s) {w:?} to send what they stamp up to t = {:.3} \
                     (simulation-time delivery, round at t = {round:.3})",
                    round - period
                )
            },
        );
        let due = self
            .delivery
            .as_mut()
            .map(|d| d.due(round))
            .unwrap_or_default();
        for d in due {
            self.fusion.submit(match d {
                Due::Event(peer, LinkEvent::PeerUp) => Job::LinkUp {
                    now: round,
                    peer: NodeId(peer),
                },
                Due::Event(peer, LinkEvent::PeerDown) => Job::LinkDown { peer: NodeId(peer) },
                Due::Message(peer, msg) => Job::Message {
                    now: round,
                    from: NodeId(peer),
                    msg,
                },
            });
        }
    }

    /// The gated neighbours (fault-free links, no radio) whose link is not up now.
    fn links_down(&self) -> Vec<WireId> {
        self.gated
            .iter()
            .copied()
            .filter(|p| {
                self.links
                    .links
                    .get(p)
                    .is_some_and(|l| l.peer_state() != PeerState::Up)
            })
            .collect()
    }

    /// Waits (servicing the links) until `waiting(self)` is empty, a shutdown or a stop — or,
    /// without simulation-time delivery (`round` None), [`LINK_WAIT`] has passed, which is
    /// logged: a link that never comes up must not hold the vehicle forever. Tells the monitor
    /// what it waits for once a wall second (`describe`); the monitor's watchdog judges a wait
    /// that makes no progress anywhere.
    fn wait_for_neighbours(
        &mut self,
        round: Option<f64>,
        waiting: impl Fn(&Self) -> Vec<WireId>,
        describe: impl Fn(&[WireId]) -> String,
    ) {
        let since = Instant::now();
        let mut last_status: Option<Instant> = None;
        loop {
            let w = waiting(self);
            if w.is_empty() || self.shutdown || self.stop.load(Ordering::Relaxed) {
                return;
            }
            if round.is_none() && since.elapsed() > LINK_WAIT {
                tracing::warn!(
                    down = ?w,
                    "links still down after {} s: starting the first round without them",
                    LINK_WAIT.as_secs()
                );
                return;
            }
            if last_status.is_none_or(|t| t.elapsed() >= STATUS_INTERVAL) {
                let st = Report::Status {
                    t: self.t,
                    state: describe(&w),
                    // The first round's wait for the links has its own deadline.
                    bounded_wait: round.is_none(),
                };
                self.report(&st);
                last_status = Some(Instant::now());
            }
            self.shutdown |= super::controls(&mut self.monitor)
                .iter()
                .any(|c| matches!(c, Control::Shutdown));
            std::thread::sleep(Duration::from_millis(1));
            self.service_links();
        }
    }

    fn on_imu(&mut self, imu: &canopy_fusion::sensor::ImuSample) {
        let eps = 1e-9;
        let round_dt = 1.0 / self.s.fusion.rate_hz;
        // A round found due at the previous sample goes out now (no frame followed it).
        if let Some(now) = self.round_due.take() {
            self.dispatch_round(now);
        }
        // Rounds due before this sample (rate as in `canopy sim`, phase per vehicle). The last
        // one goes out after this sample's frame, if it has one (`on_frame`), else with the
        // next sample: a frame right after the round would otherwise wait for it.
        while self.next_round <= imu.time + eps {
            if let Some(now) = self.round_due.take() {
                self.dispatch_round(now);
            }
            self.t = self.t.max(self.next_round);
            self.round_due = Some(self.next_round);
            self.next_round += round_dt;
        }
        self.t = imu.time;
        self.links.clock.set(imu.time);
        self.stall.on_imu();
        if self.estimator.on_imu(imu).is_err() {
            self.counters.inputs_rejected += 1;
        }
    }

    fn after_sample(&mut self) {
        if self.t + 1e-9 >= self.next_record {
            self.estimate_report();
            self.map_report(false);
            while self.next_record <= self.t + 1e-9 {
                self.next_record += self.s.run.record_interval_s;
            }
        }
    }

    fn on_frame(&mut self, frame: &canopy_fusion::sensor::ObservationFrame) {
        // The frame changes the map: the round lent out must be back first.
        self.wait_for_round();
        match self.estimator.on_frame(frame) {
            Ok(rep) => self
                .associations
                .push(FrameAssociations::from_report(frame.time, &rep)),
            // Counted by reason in the estimator (`Rejections`), logged once per reason.
            Err(_) => self.counters.inputs_rejected += 1,
        }
        if let Some(now) = self.round_due.take() {
            self.dispatch_round(now);
        }
    }

    fn finish(&mut self) {
        if let Some(now) = self.round_due.take() {
            self.dispatch_round(now);
        }
        self.wait_for_round();
        if self.delivery.is_some() {
            // Simulation-time delivery: this vehicle applies nothing more and sends nothing
            // more, so its neighbours need not wait for it (a replayed log may end early).
            self.links.send_marker(f64::MAX);
        }
        // Always: the counters must include what came after the last record time (a frame
        // follows the sample that triggered that report); the monitor keeps one estimate per
        // time.
        self.estimate_report();
        self.map_report(true);
        let t = self.t;
        self.report(&Report::Finished { t });
        eprintln!(
            "{}",
            self.stall
                .summary(1.0 / self.cfg_imu_rate, self.estimator.num_features())
        );
    }
}

/// Runs a vehicle process.
pub fn run(c: &RoleCommon, id: WireId, incarnation: u32) -> Result<()> {
    let stop = stop_flag();
    let s = load_resolved(c)?;
    // Before the fusion thread starts allocating the round's matrices.
    canopy_fusion::runtime::set_heap_policy(s.run.heap);
    let cfg = s
        .vehicles
        .iter()
        .find(|v| v.id == id)
        .with_context(|| format!("vehicle {id} is not in the scenario"))?
        .clone();
    let world = Arc::new(World::new(&s.world, s.world.seed).context("building the world frame")?);
    let mut wl = control_link(&c.prefix, id, WORLD_ID, stream_buffer(s.run.max_lead_s))?;
    let mut monitor = control_link(&c.prefix, id, MONITOR_ID, 64)?;
    let links = FusionLinks::open(&s, c, id, incarnation)?;
    let epoch = fresh_epoch();
    if !super::wait_peer_up(&mut monitor, INIT_TIMEOUT, &stop) {
        bail!("the monitor did not come up");
    }
    let started = Report::Started {
        pid: std::process::id(),
        epoch,
        incarnation,
    };
    send_body(&mut monitor, started.kind(), 0, 0.0, &started)?;

    // Ask the world for the initial estimate until it answers.
    let deadline = Instant::now() + INIT_TIMEOUT;
    let mut last_ask: Option<Instant> = None;
    let init = loop {
        if stop.load(Ordering::Relaxed) || Instant::now() > deadline {
            bail!("no initialisation from the world");
        }
        while let Ok(Some(m)) = monitor.try_recv() {
            if let Some(Control::Shutdown) = decode_body::<Control>(&m) {
                return Ok(());
            }
        }
        if last_ask.is_none_or(|t| t.elapsed() > Duration::from_millis(100)) {
            let ask = Progress {
                incarnation,
                time: -1.0,
            };
            send_body(&mut wl, MessageKind::HEARTBEAT, 0, 0.0, &ask)?;
            last_ask = Some(Instant::now());
        }
        if let Some(m) = wl.recv_timeout(Duration::from_millis(10))?
            && let Some(WorldMsg::Init(i)) = decode_body::<WorldMsg>(&m)
            && i.incarnation == incarnation
        {
            break i;
        }
    };
    let (estimator, fusion) =
        build_agent(&s, &cfg, &world, &init, incarnation, epoch)?.into_parts();
    // Gated: the links on which nothing is lost or held back (no faults, no radio).
    let peers: Vec<(WireId, bool)> = crate::network::effective_links(&s)
        .into_iter()
        .filter(|l| l.a == id || l.b == id)
        .map(|l| {
            let peer = if l.a == id { l.b } else { l.a };
            (peer, l.faults.is_none() && l.radio.is_none())
        })
        .collect();
    let gated = peers.iter().filter(|p| p.1).map(|p| p.0).collect();
    let delivery = (s.fusion.delivery == crate::network::Delivery::SimulationTime)
        .then(|| SimTimeDelivery::new(1.0 / s.fusion.rate_hz, init.time, peers));
    let fusion = FusionThread::spawn(fusion, s.fusion.delta_compression)
        .context("starting the fusion thread")?;
    let record_dt = s.run.record_interval_s;
    let round_dt = 1.0 / s.fusion.rate_hz;
    let mut v = Vehicle {
        s: &s,
        cfg_imu_rate: cfg.imu.rate_hz,
        stall: StallMeter::default(),
        give_back_failed: 0,
        round_due: None,
        fusion_lost: false,
        delivery,
        stop: stop.clone(),
        shutdown: false,
        gated,
        first_round_done: false,
        incarnation,
        estimator,
        fusion,
        view: FusionView::default(),
        links,
        monitor,
        counters: VehicleCounters::default(),
        associations: Vec::new(),
        t: init.time,
        // The first round and record times at or after the start.
        next_round: {
            let phase = round_phase(&s, id) * round_dt;
            (((init.time - phase) / round_dt).floor() + 1.0) * round_dt + phase
        },
        naive_bytes: 0,
        next_record: (init.time / record_dt - 1e-9).ceil() * record_dt,
        last_report: f64::NEG_INFINITY,
    };
    v.links.clock.set(init.time);
    v.after_sample();

    let mut last_seq = 0u64;
    let mut ended = false;
    let mut linger_since: Option<Instant> = None;
    let mut last_status = Instant::now();
    let mut stream_idle_since = Instant::now();
    loop {
        let mut shutdown = stop.load(Ordering::Relaxed) || v.shutdown;
        while let Ok(Some(m)) = v.monitor.try_recv() {
            if let Some(Control::Shutdown) = decode_body::<Control>(&m) {
                shutdown = true;
            }
        }
        if shutdown {
            // No waiting for the neighbours any more (simulation-time delivery).
            v.shutdown = true;
            if !ended {
                v.finish();
            }
            return Ok(());
        }
        let mut world_gone = false;
        while let Some(e) = wl.poll_event() {
            world_gone = e == LinkEvent::PeerDown;
        }
        if world_gone && !ended {
            v.report(&Report::Failed {
                reason: "the world process is gone".into(),
            });
            bail!("the world process is gone");
        }
        // What this process is doing, about once a wall second, for the monitor's watchdog.
        if last_status.elapsed() >= STATUS_INTERVAL {
            let state = if ended {
                format!("finished its stream at t = {}; serving its links", v.t)
            } else if stream_idle_since.elapsed() >= STATUS_INTERVAL {
                format!(
                    "waiting for sensor data from the world (applied everything up to t = {}, \
                     batch {last_seq}, acknowledged)",
                    v.t
                )
            } else {
                format!("estimating (t = {})", v.t)
            };
            let st = Report::Status {
                t: v.t,
                state,
                bounded_wait: false,
            };
            v.report(&st);
            last_status = Instant::now();
        }
        // The sensor stream: wait briefly for a batch (woken by the world's notification),
        // then take what is waiting, a few at a time so the links stay serviced.
        let mut n = 0;
        while n < 8 && !ended {
            let m = if n == 0 {
                wl.recv_timeout(Duration::from_millis(1))?
            } else {
                wl.try_recv()?
            };
            let Some(m) = m else { break };
            n += 1;
            stream_idle_since = Instant::now();
            ended = v.on_world(&mut wl, &m, &mut last_seq)?;
        }
        if ended && linger_since.is_none() {
            linger_since = Some(Instant::now());
        }
        // Keep fusing while waiting (neighbours' messages) and after the end (the links stay
        // answered until the monitor shuts the run down).
        v.service_links();
        if v.fusion_lost {
            let reason = "the fusion thread ended while it held the filter".to_string();
            v.report(&Report::Failed {
                reason: reason.clone(),
            });
            bail!(reason);
        }
        if let Some(since) = linger_since {
            if since.elapsed() > LINGER_TIMEOUT {
                bail!("no shutdown from the monitor after the end of the stream");
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

impl Vehicle<'_> {
    /// One message of the sensor stream; true at its end.
    fn on_world(
        &mut self,
        wl: &mut dyn Link,
        m: &canopy_transport::Received,
        last_seq: &mut u64,
    ) -> Result<bool> {
        match decode_body::<WorldMsg>(m) {
            Some(WorldMsg::Batch { seq, items }) => {
                if seq > *last_seq + 1 {
                    self.counters.stream_gaps += seq - *last_seq - 1;
                }
                *last_seq = seq;
                let mut items = items.iter().peekable();
                while let Some(it) = items.next() {
                    match it {
                        SensorItem::Imu(s) => {
                            self.on_imu(s);
                            // The frame that follows this sample belongs to the same step: the
                            // record of this time comes after it, as in `canopy sim`.
                            if let Some(SensorItem::Frame(f)) = items
                                .next_if(|n| matches!(n, SensorItem::Frame(f) if f.time == s.time))
                            {
                                self.on_frame(f);
                            }
                            self.after_sample();
                        }
                        SensorItem::Frame(f) => self.on_frame(f),
                    }
                }
                self.service_links();
                let ack = Progress {
                    incarnation: self.incarnation,
                    time: self.t,
                };
                send_body(wl, MessageKind::HEARTBEAT, 0, self.t, &ack)?;
                Ok(false)
            }
            Some(WorldMsg::End { .. }) => {
                self.service_links();
                self.finish();
                Ok(true)
            }
            // A late duplicate Init or a message for the hub: not for a running vehicle.
            Some(_) | None => Ok(false),
        }
    }
}
