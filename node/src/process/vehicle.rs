//! The vehicle process: one [`VehicleAgent`] (inertial SLAM + DDF node) fed by its sensor
//! stream from the world, fusing over its configured links.
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
use canopy_fusion::ddf::DdfMessage;
use canopy_fusion::ins::{VehicleState, VehicleVector};
use canopy_fusion::slam::{ObservationOutcome, SlamConfig};
use canopy_fusion::state::VEHICLE_DIM;
use canopy_fusion::topology::NodeId;
use canopy_transport::link::{Link, LinkEvent};
use canopy_transport::{MessageKind, NodeId as WireId};
use nalgebra::{SMatrix, Vector3};

use super::protocol::{
    Control, EstimateReport, FeatureReport, FrameAssociations, InitMsg, MONITOR_ID, MapReport,
    Outcome, Progress, Report, SensorItem, VehicleCounters, WORLD_ID, WorldMsg,
};
use super::world::stream_buffer;
use super::{
    FusionLinks, RoleCommon, control_link, decode_body, fresh_epoch, link_report, load_resolved,
    naive_round_bytes, send_body, stop_flag,
};
use crate::agent::VehicleAgent;
use crate::baseline::estimator_setup;
use crate::network::{effective_links, topology};
use crate::scenario::{Scenario, VehicleConfig};
use crate::world::{InitialEstimate, World};

/// How long a vehicle waits for its initialisation.
const INIT_TIMEOUT: Duration = Duration::from_secs(120);
/// After the end of its stream, how long a vehicle keeps serving its links without hearing
/// from the monitor.
const LINGER_TIMEOUT: Duration = Duration::from_secs(120);

struct Vehicle<'s> {
    s: &'s Scenario,
    /// This vehicle's IMU rate [Hz].
    cfg_imu_rate: f64,
    incarnation: u32,
    agent: VehicleAgent,
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
    /// A round whose fusion half ran at the previous IMU sample and whose exchange half is due.
    round_due: Option<f64>,
}

/// How long fusion work (rounds, fusing received deltas) holds up the estimator: the time
/// spent in it between two consecutive IMU samples, one figure per IMU interval that saw any,
/// as wall time (includes waiting for a core while other processes run) and as this thread's
/// CPU time (the work itself). Printed to the vehicle's log at the end (`fusion stall: …`,
/// read by `scripts/bench.sh`).
#[derive(Debug, Default)]
struct StallMeter {
    /// Fusion (wall, CPU) time since the last IMU sample [s].
    pending: (f64, f64),
    /// One (wall, CPU) entry per IMU interval with fusion work [s].
    stalls: Vec<(f64, f64)>,
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
    fn add(&mut self, since: Mark) {
        self.pending.0 += since.0.elapsed().as_secs_f64();
        self.pending.1 += (thread_cpu_s() - since.1).max(0.0);
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
            let mut v: Vec<f64> = self.stalls.iter().map(pick).collect();
            v.sort_by(f64::total_cmp);
            let q = |p: f64| {
                if v.is_empty() {
                    0.0
                } else {
                    v[((v.len() - 1) as f64 * p).round() as usize] * 1e3
                }
            };
            (
                q(1.0),
                q(0.99),
                q(0.5),
                v.iter().filter(|&&x| x > imu_period).count(),
            )
        };
        let c = stats(|x| x.1);
        let w = stats(|x| x.0);
        format!(
            "fusion stall: n={} cpu_max_ms={:.3} cpu_p99_ms={:.3} cpu_p50_ms={:.3} \
             cpu_over_imu_period={} wall_max_ms={:.3} wall_p99_ms={:.3} wall_p50_ms={:.3} \
             wall_over_imu_period={} imu_period_ms={:.1} features={features}",
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
        )
    }
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
    epoch: u64,
) -> Result<VehicleAgent> {
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
            Some((NodeId(peer), l.byte_budget))
        })
        .collect();
    let slam = SlamConfig {
        frame: world.frame(),
        origin: world.map_origin(),
        association: s.fusion.association_config(),
        fresh_id_namespace: cfg.id,
    };
    VehicleAgent::new(
        NodeId(cfg.id),
        epoch,
        slam,
        estimator_setup(cfg, &initial_from(init)),
        s.fusion.ddf_mode(),
        &topology(s)?,
        s.fusion.ddf_config(),
        &budgets,
    )
    .with_context(|| format!("building the estimator of {}", cfg.display_name()))
}

impl Vehicle<'_> {
    fn report(&mut self, r: &Report) {
        let _ = send_body(&mut self.monitor, r.kind(), 0, self.t, r);
    }

    /// Link events and DDF messages waiting now.
    fn service_links(&mut self) {
        let now = self.t;
        let polled = self.links.poll();
        let start = StallMeter::mark();
        let busy = !polled.is_empty();
        for (peer, events, msgs) in polled {
            for ev in events {
                let out = match ev {
                    LinkEvent::PeerUp => {
                        self.agent.on_link_up(now, NodeId(peer)).unwrap_or_default()
                    }
                    LinkEvent::PeerDown => {
                        let _ = self.agent.on_link_down(NodeId(peer));
                        Vec::new()
                    }
                };
                self.links.send(now, out);
            }
            for msg in msgs {
                self.on_message(now, peer, msg);
            }
        }
        if busy {
            self.stall.add(start);
        }
    }

    fn on_message(&mut self, now: f64, peer: WireId, msg: DdfMessage) {
        // A rejected message is counted by the agent; the estimate is unchanged.
        let out = self
            .agent
            .on_message(now, NodeId(peer), msg)
            .unwrap_or_default();
        self.links.send(now, out);
    }

    fn counters(&self) -> VehicleCounters {
        let c = self.agent.counters();
        VehicleCounters {
            imu_samples: c.imu_samples,
            inputs_rejected: self.counters.inputs_rejected,
            frames: c.frames,
            observations: c.observations,
            rounds: c.rounds,
            fused: c.fused,
            fuse_refused: c.fuse_refused,
            messages_rejected: c.messages_rejected,
            ci_fused: c.ci_fused,
            stream_gaps: self.counters.stream_gaps,
        }
    }

    fn estimate_report(&mut self) {
        let f = self.agent.filter();
        let (Ok(x), Ok(p)) = (f.vehicle_state(0), f.vehicle_covariance(0)) else {
            return;
        };
        let links = self
            .links
            .links
            .iter()
            .map(|(&peer, l)| {
                link_report(
                    peer,
                    l,
                    self.agent.ddf().and_then(|d| d.channel(NodeId(peer))),
                    self.naive_bytes,
                )
            })
            .collect();
        let r = Report::Estimate(EstimateReport {
            t: self.t,
            state: x.to_vector().as_slice().to_vec(),
            covariance: p.transpose().as_slice().to_vec(),
            counters: self.counters(),
            links,
            associations: std::mem::take(&mut self.associations),
        });
        self.report(&r);
        self.last_report = self.t;
    }

    fn map_report(&mut self, last: bool) {
        let f = self.agent.filter();
        let features = f
            .features()
            .into_iter()
            .filter_map(|(id, m): (u64, Vector3<f64>)| {
                let c = f.feature_covariance(id)?;
                Some(FeatureReport {
                    id,
                    mean: [m.x, m.y, m.z],
                    cov: [
                        c[(0, 0)],
                        c[(0, 1)],
                        c[(0, 2)],
                        c[(1, 1)],
                        c[(1, 2)],
                        c[(2, 2)],
                    ],
                })
            })
            .collect();
        let r = Report::Map(MapReport {
            t: self.t,
            last,
            features,
        });
        self.report(&r);
    }

    fn on_imu(&mut self, imu: &canopy_fusion::sensor::ImuSample) {
        let eps = 1e-9;
        let round_dt = 1.0 / self.s.fusion.rate_hz;
        // A round is split over two IMU intervals so that its two costly halves never hold up
        // the same sample: at the first sample at or after the round time the received
        // information is fused into the EKF (`flush_fusion`); at the next sample the map
        // information is formed and the DDF's deltas are computed and sent (`on_round`, whose
        // own flush then has nothing, or only what arrived in between, to fuse).
        if let Some(now) = self.round_due.take() {
            self.exchange(now.max(self.t));
        }
        // Rounds due before this sample (rate as in `canopy sim`).
        while self.next_round <= imu.time + eps {
            let now = self.next_round;
            if let Some(prev) = self.round_due.take() {
                // Only when rounds are closer than one IMU period: no interval to spare.
                self.exchange(prev);
            }
            self.t = self.t.max(now);
            self.links.clock.set(now);
            self.service_links();
            self.naive_bytes += naive_round_bytes(self.agent.filter().num_features());
            let start = StallMeter::mark();
            self.agent.flush_fusion();
            self.stall.add(start);
            self.round_due = Some(now);
            self.next_round += round_dt;
        }
        self.t = imu.time;
        self.links.clock.set(imu.time);
        self.stall.on_imu();
        if self.agent.on_imu(imu).is_err() {
            self.counters.inputs_rejected += 1;
        }
    }

    /// The second half of a round (see `on_imu`): the deltas out. Replies are read with the
    /// links' next service (after every stream batch).
    fn exchange(&mut self, now: f64) {
        let start = StallMeter::mark();
        let out = self.agent.on_round(now).unwrap_or_default();
        self.links.send(now, out);
        self.stall.add(start);
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
        match self.agent.on_frame(frame) {
            Ok(rep) => self.associations.push(FrameAssociations {
                t: frame.time,
                outcomes: rep
                    .outcomes
                    .iter()
                    .map(|o| match *o {
                        ObservationOutcome::Associated { feature, .. } => {
                            Outcome::Associated(feature)
                        }
                        ObservationOutcome::Initialized { feature } => {
                            Outcome::Initialized(feature)
                        }
                        ObservationOutcome::Stored { track } => Outcome::Stored(track),
                        ObservationOutcome::Rejected(_) => Outcome::Rejected,
                    })
                    .collect(),
                initialized_tracks: rep.initialized_tracks.clone(),
            }),
            Err(_) => self.counters.inputs_rejected += 1,
        }
    }

    fn finish(&mut self) {
        if let Some(now) = self.round_due.take() {
            self.exchange(now.max(self.t));
        }
        if self.last_report < self.t {
            self.estimate_report();
        }
        self.map_report(true);
        let t = self.t;
        self.report(&Report::Finished { t });
        eprintln!(
            "{}",
            self.stall
                .summary(1.0 / self.cfg_imu_rate, self.agent.filter().num_features())
        );
    }
}

/// Runs a vehicle process.
pub fn run(c: &RoleCommon, id: WireId, incarnation: u32) -> Result<()> {
    let stop = stop_flag();
    let s = load_resolved(c)?;
    let cfg = s
        .vehicles
        .iter()
        .find(|v| v.id == id)
        .with_context(|| format!("vehicle {id} is not in the scenario"))?
        .clone();
    let world = Arc::new(World::new(&s.world, s.world.seed).context("building the world frame")?);
    let mut wl = control_link(&c.prefix, id, WORLD_ID, stream_buffer(s.run.max_lead_s))?;
    let mut monitor = control_link(&c.prefix, id, MONITOR_ID, 64)?;
    let links = FusionLinks::open(&s, &c.prefix, id, incarnation)?;
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
    let agent = build_agent(&s, &cfg, &world, &init, epoch)?;
    let record_dt = s.run.record_interval_s;
    let round_dt = 1.0 / s.fusion.rate_hz;
    let mut v = Vehicle {
        s: &s,
        cfg_imu_rate: cfg.imu.rate_hz,
        stall: StallMeter::default(),
        round_due: None,
        incarnation,
        agent,
        links,
        monitor,
        counters: VehicleCounters::default(),
        associations: Vec::new(),
        t: init.time,
        // The first round and record times at or after the start.
        next_round: ((init.time / round_dt).floor() + 1.0) * round_dt,
        naive_bytes: 0,
        next_record: (init.time / record_dt - 1e-9).ceil() * record_dt,
        last_report: f64::NEG_INFINITY,
    };
    v.links.clock.set(init.time);
    v.after_sample();

    let mut last_seq = 0u64;
    let mut ended = false;
    let mut linger_since: Option<Instant> = None;
    loop {
        let mut shutdown = stop.load(Ordering::Relaxed);
        while let Ok(Some(m)) = v.monitor.try_recv() {
            if let Some(Control::Shutdown) = decode_body::<Control>(&m) {
                shutdown = true;
            }
        }
        if shutdown {
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
            ended = v.on_world(&mut wl, &m, &mut last_seq)?;
        }
        if ended && linger_since.is_none() {
            linger_since = Some(Instant::now());
        }
        // Keep fusing while waiting (neighbours' messages) and after the end (the links stay
        // answered until the monitor shuts the run down).
        v.service_links();
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
                for it in &items {
                    match it {
                        SensorItem::Imu(s) => {
                            self.on_imu(s);
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
