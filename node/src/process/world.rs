//! The world process: steps every vehicle's sensor source (the simulator, or a replayed log) in
//! simulation time and streams each vehicle's IMU samples and frames to it over iceoryx2.
//!
//! Pacing: the world steps the source whose next sample is earliest (as `canopy sim` does) up
//! to a limit L = min(acknowledged time of the live vehicles) + `[run].max_lead_s`, and, with
//! `[run].real_time_factor` r > 0, also L ≤ r × wall time. A vehicle is live from its
//! initialisation request until its link reports it gone, so a dead vehicle does not stall the
//! others. Samples are sent in batches of [`BATCH_S`] simulated seconds (or earlier when the
//! limit stops the world), so at most `max_lead_s / BATCH_S + 1` batches are in flight per
//! vehicle and the subscriber buffers are sized for that.
//!
//! (Re)starts: a vehicle process asks for initialisation with a [`Progress`] of negative time
//! carrying its incarnation; the world answers with [`InitMsg`] — the initial estimate at t = 0
//! for a first start, [`SensorSource::restart_estimate`] at the current time for a restart (an
//! external fix) — and streams from the current time on.
//!
//! Truth (per vehicle at record times) and the true feature ids of every frame go only to the
//! monitor, never to a vehicle.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use canopy_transport::link::{Link, LinkEvent, PeerState};
use canopy_transport::{MessageKind, NodeId};

use super::protocol::{
    Control, FrameTruth, InitMsg, MONITOR_ID, Progress, Report, SensorItem, TruthReport, WORLD_ID,
    WorldMsg,
};
use super::{RoleCommon, control_link, decode_body, load_resolved, send_body, stop_flag};
use crate::metrics::truth_state;
use crate::network::FusionMode;
use crate::replay::SensorSource;
use crate::world::{InitialEstimate, TruthSample};
use canopy_fusion::ins::VehicleState;
use canopy_fusion::state::VEHICLE_DIM;

/// Simulated seconds of sensor data per batch.
pub const BATCH_S: f64 = 0.1;

/// How long the world waits for every vehicle (and the hub) to come up.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(120);

/// How long the world holds the streams for a scheduled restart.
const RESTART_TIMEOUT: Duration = Duration::from_secs(60);

/// How long the world may go without advancing while nothing holds it before it gives up.
const STUCK_TIMEOUT: Duration = Duration::from_secs(3);

/// Without any live vehicle the world runs at this many simulated seconds per wall second, so
/// the monitor can restart crashed vehicles close to their scheduled time.
const IDLE_PACE: f64 = 50.0;

/// Subscriber buffer of a sensor link: the batches flow control lets be in flight, plus slack.
pub fn stream_buffer(max_lead_s: f64) -> usize {
    ((max_lead_s / BATCH_S).ceil() as usize + 16).min(1024)
}

struct Slot {
    id: NodeId,
    link: canopy_transport::iceoryx::IceoryxLink,
    /// Streaming to it (initialised and not seen gone).
    active: bool,
    /// Incarnation last initialised.
    incarnation: Option<u32>,
    acked: f64,
    seq: u64,
    pending: Vec<SensorItem>,
    next_record: f64,
    ended: bool,
}

fn state_vec(e: &InitialEstimate) -> Vec<f64> {
    VehicleState {
        position: e.position,
        velocity: e.velocity,
        attitude: e.attitude,
        accel_bias: e.accel_bias,
        gyro_bias: e.gyro_bias,
    }
    .to_vector()
    .as_slice()
    .to_vec()
}

fn truth_report(vehicle: NodeId, t: &TruthSample) -> TruthReport {
    let mut nav = [0.0; VEHICLE_DIM];
    nav.copy_from_slice(truth_state(t).to_vector().as_slice());
    let mut launch = [0.0; 9];
    for (k, v) in [t.launch_position, t.launch_velocity, t.launch_attitude]
        .iter()
        .enumerate()
    {
        launch[3 * k..3 * k + 3].copy_from_slice(v.as_slice());
    }
    TruthReport {
        vehicle,
        t: t.time,
        nav,
        launch,
    }
}

/// Runs the world process.
pub fn run(c: &RoleCommon) -> Result<()> {
    let stop = stop_flag();
    let s = load_resolved(c)?;
    let (_world, all_sources) =
        SensorSource::for_scenario(&s).context("building the world and its sensor sources")?;
    // A host's world (multi-host run): only that host's vehicles, and the hub if the host runs
    // it. Every vehicle's source is seeded by its own id (`world::vehicle_seed`), so a vehicle's
    // sensor stream is the same whichever host simulates it.
    let host = match &c.host {
        None => None,
        Some(name) => Some(
            crate::deploy::host_named(&s, name)
                .map(|(_, h)| h.clone())
                .with_context(|| format!("--host {name}: no such [[host]] in the scenario"))?,
        ),
    };
    let local = |id: NodeId| host.as_ref().is_none_or(|h| h.vehicles.contains(&id));
    let local_vehicles: Vec<&crate::scenario::VehicleConfig> =
        s.vehicles.iter().filter(|v| local(v.id)).collect();
    let mut sources: Vec<SensorSource> = s
        .vehicles
        .iter()
        .zip(all_sources)
        .filter(|(v, _)| local(v.id))
        .map(|(_, src)| src)
        .collect();
    let duration = s.run.duration_s;
    let record_dt = s.run.record_interval_s;
    let eps = 1e-9;
    let buffer = stream_buffer(s.run.max_lead_s);

    let mut monitor = control_link(&c.prefix, WORLD_ID, MONITOR_ID, 64)?;
    let mut slots: Vec<Slot> = Vec::new();
    for v in &local_vehicles {
        slots.push(Slot {
            id: v.id,
            link: control_link(&c.prefix, WORLD_ID, v.id, buffer)?,
            active: false,
            incarnation: None,
            acked: 0.0,
            seq: 0,
            pending: Vec::new(),
            next_record: 0.0,
            ended: false,
        });
    }
    let hub_here = host.as_ref().is_none_or(|h| h.hub);
    let mut hub = match s.fusion.mode {
        FusionMode::Central if hub_here => {
            Some(control_link(&c.prefix, WORLD_ID, s.fusion.hub_id, 64)?)
        }
        _ => None,
    };
    let report = |monitor: &mut dyn Link, r: &Report, t: f64| {
        let _ = send_body(monitor, r.kind(), 0, t, r);
    };
    if !super::wait_peer_up(&mut monitor, STARTUP_TIMEOUT, &stop) {
        bail!("the monitor did not come up");
    }
    report(
        &mut monitor,
        &Report::Started {
            pid: std::process::id(),
            epoch: 0,
            incarnation: 0,
        },
        0.0,
    );

    let mut t_world = 0.0_f64;
    let mut truth_buf: Vec<TruthReport> = Vec::new();
    let mut frame_buf: Vec<FrameTruth> = Vec::new();
    // Truth at t = 0 for every simulated vehicle.
    for (slot, src) in slots.iter_mut().zip(&sources) {
        if let Some(t) = src.truth() {
            truth_buf.push(truth_report(slot.id, t));
        }
        slot.next_record = record_dt;
    }

    let mut started = false;
    let startup_deadline = Instant::now() + STARTUP_TIMEOUT;
    let mut wall_start = Instant::now();
    let mut idle_since: Option<(Instant, f64)> = None;
    let mut next_batch = BATCH_S;
    let mut finished_sent = false;
    let mut hub_time_sent = f64::NEG_INFINITY;
    // The hub's acknowledged time (central mode): it paces the world like a vehicle's while
    // the hub is alive.
    let mut hub_acked = 0.0_f64;
    // Scheduled restarts: the world holds every stream at the restart time until the new
    // process asks for initialisation, so the restart happens at exactly that time (as in
    // `canopy sim`, and as the reference assumes).
    // On a host (multi-host run): the restarts of its own vehicles, by their slot here.
    let mut restarts: Vec<(f64, usize, u32)> = crate::baseline::restarts(&s)
        .into_iter()
        .filter_map(|(t, i, inc)| {
            let id = s.vehicles[i].id;
            let slot = local_vehicles.iter().position(|v| v.id == id)?;
            Some((t, slot, inc))
        })
        .collect();
    let mut waiting_since: Option<Instant> = None;
    let mut end_reached = false;
    let mut shutdown = false;
    let mut stuck_since: Option<Instant> = None;
    let mut last_status = Instant::now();

    // A host's world (multi-host run) also steps no further than the team's pace, which the
    // monitor sends through the host launcher (`Control::Pace`): nothing before the first.
    let mut pace = if host.is_some() { 0.0 } else { f64::INFINITY };
    while !stop.load(Ordering::Relaxed) && !shutdown {
        let mut busy = false;
        // Monitor control.
        while let Ok(Some(m)) = monitor.try_recv() {
            match decode_body::<Control>(&m) {
                Some(Control::Shutdown) => shutdown = true,
                Some(Control::Pace { until }) => pace = pace.max(until),
                _ => {}
            }
        }
        if monitor.drain_gone() {
            bail!("the monitor is gone");
        }
        // Vehicles: liveness and flow control.
        for (i, slot) in slots.iter_mut().enumerate() {
            while let Some(ev) = slot.link.poll_event() {
                if ev == LinkEvent::PeerDown {
                    slot.active = false;
                    slot.pending.clear();
                }
            }
            while let Ok(Some(m)) = slot.link.try_recv() {
                busy = true;
                let Some(p) = decode_body::<Progress>(&m) else {
                    continue;
                };
                if p.time < 0.0 {
                    if slot.incarnation == Some(p.incarnation) {
                        continue; // A repeated request: already answered.
                    }
                    let src = &sources[i];
                    let est = if p.incarnation == 0 && t_world == 0.0 {
                        Some(src.initial_estimate())
                    } else {
                        src.restart_estimate(u64::from(p.incarnation.max(1)))
                    };
                    let Some(est) = est else {
                        tracing::warn!(vehicle = slot.id, "a replayed vehicle cannot restart");
                        continue;
                    };
                    let init = WorldMsg::Init(InitMsg {
                        incarnation: p.incarnation,
                        time: t_world,
                        state: state_vec(&est),
                        covariance: est.covariance.transpose().as_slice().to_vec(),
                    });
                    send_body(&mut slot.link, MessageKind::IMU_BATCH, 0, t_world, &init)?;
                    tracing::info!(
                        vehicle = slot.id,
                        incarnation = p.incarnation,
                        t = t_world,
                        "initialised"
                    );
                    slot.incarnation = Some(p.incarnation);
                    slot.active = true;
                    slot.acked = t_world;
                    slot.seq = 0;
                    slot.pending.clear();
                    slot.ended = false;
                    report(
                        &mut monitor,
                        &Report::Initialized {
                            vehicle: slot.id,
                            incarnation: p.incarnation,
                            t: t_world,
                        },
                        t_world,
                    );
                } else if slot.active && slot.incarnation == Some(p.incarnation) {
                    slot.acked = slot.acked.max(p.time);
                }
            }
        }
        if let Some(h) = hub.as_mut() {
            while h.poll_event().is_some() {}
            while let Ok(Some(m)) = h.try_recv() {
                if let Some(p) = decode_body::<Progress>(&m) {
                    hub_acked = hub_acked.max(p.time);
                }
            }
        }
        if !started {
            if last_status.elapsed() >= super::vehicle::STATUS_INTERVAL {
                let missing: Vec<String> = slots
                    .iter()
                    .filter(|s| !s.active)
                    .map(|s| s.id.to_string())
                    .collect();
                report(
                    &mut monitor,
                    &Report::Status {
                        t: 0.0,
                        state: format!("starting: waiting for vehicles [{}]", missing.join(", ")),
                        bounded_wait: true,
                    },
                    0.0,
                );
                last_status = Instant::now();
            }
            let all = slots.iter().all(|s| s.active)
                && hub.as_ref().is_none_or(|h| h.peer_state() == PeerState::Up);
            if all {
                started = true;
                wall_start = Instant::now();
            } else if Instant::now() > startup_deadline {
                let missing: Vec<String> = slots
                    .iter()
                    .filter(|s| !s.active)
                    .map(|s| s.id.to_string())
                    .collect();
                let reason = format!("vehicles [{}] did not come up", missing.join(", "));
                report(
                    &mut monitor,
                    &Report::Failed {
                        reason: reason.clone(),
                    },
                    0.0,
                );
                bail!(reason);
            } else {
                std::thread::sleep(Duration::from_millis(2));
                continue;
            }
        }

        // The stepping limit: the slowest live vehicle, and the hub while it is alive.
        let mut active: Vec<f64> = slots.iter().filter(|s| s.active).map(|s| s.acked).collect();
        if let Some(h) = hub.as_ref()
            && h.peer_state() == PeerState::Up
            && !active.is_empty()
        {
            active.push(hub_acked);
        }
        let mut limit = duration;
        if active.is_empty() {
            let (since, t0) = *idle_since.get_or_insert((Instant::now(), t_world));
            limit = limit.min(t0 + IDLE_PACE * since.elapsed().as_secs_f64());
        } else {
            idle_since = None;
            let slowest = active.iter().copied().fold(f64::INFINITY, f64::min);
            limit = limit.min(slowest + s.run.max_lead_s);
        }
        let paced_by_team = pace < limit;
        limit = limit.min(pace);
        if let Some(r) = s.run.real_time_factor.filter(|r| *r > 0.0) {
            // Quantized to whole batches: a limit that stops the world flushes a partial batch,
            // and the wall-clock limit moves every pass, so unquantized it sent one tiny batch
            // per pass and a vehicle that fell a second behind (a zenoh put blocking on a cut
            // network link) overflowed its stream buffer, sized for max_lead_s / BATCH_S + 1
            // batches.
            let paced = r * wall_start.elapsed().as_secs_f64();
            limit = limit.min((paced / BATCH_S).floor() * BATCH_S);
        }

        // Step up to the limit, at most one batch per pass so links stay serviced.
        let pass_end = next_batch;
        let mut blocked = false;
        // The time of the next sample when it lies beyond this batch: the batch is complete even
        // though no sample fell on its end (recorded timestamps jitter around the batch grid;
        // before this, t_world never reached next_batch and the world stepped nothing forever).
        let mut beyond_batch: Option<f64> = None;
        let t_before = t_world;
        loop {
            let Some((vi, t)) = sources
                .iter()
                .enumerate()
                .filter_map(|(i, v)| v.next_time().map(|t| (i, t)))
                .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
            else {
                end_reached = true;
                break;
            };
            if t > duration + eps {
                end_reached = true;
                break;
            }
            if t > limit + eps {
                blocked = true;
                break;
            }
            if t > pass_end + eps {
                beyond_batch = Some(t);
                break;
            }
            if let Some(&(tr, idx, inc)) = restarts.first()
                && t + eps >= tr
            {
                if slots[idx].incarnation == Some(inc) {
                    restarts.remove(0);
                    waiting_since = None;
                    continue;
                }
                let since = *waiting_since.get_or_insert_with(|| {
                    tracing::info!(
                        vehicle = slots[idx].id,
                        t = tr,
                        "holding the streams for a restart"
                    );
                    report(
                        &mut monitor,
                        &Report::Waiting {
                            vehicle: slots[idx].id,
                            incarnation: inc,
                            t: tr,
                        },
                        t_world,
                    );
                    Instant::now()
                });
                if since.elapsed() > RESTART_TIMEOUT {
                    tracing::warn!(vehicle = slots[idx].id, "restart did not come; going on");
                    restarts.remove(0);
                    waiting_since = None;
                    continue;
                }
                blocked = true;
                break;
            }
            let Some(step) = sources[vi].step() else {
                continue;
            };
            busy = true;
            t_world = t_world.max(t);
            let slot = &mut slots[vi];
            if slot.active {
                slot.pending.push(SensorItem::Imu(step.imu));
            }
            if let Some((frame, ids)) = step.frame {
                if let Some(ids) = ids {
                    frame_buf.push(FrameTruth {
                        vehicle: slot.id,
                        t: frame.time,
                        ids,
                    });
                }
                if slot.active {
                    slot.pending.push(SensorItem::Frame(frame));
                }
            }
            if sources[vi].time() + eps >= slot.next_record {
                if let Some(truth) = &step.truth {
                    truth_buf.push(truth_report(slot.id, truth));
                }
                slot.next_record += record_dt;
            }
        }
        let batch_done = t_world + eps >= next_batch || beyond_batch.is_some();
        if batch_done {
            next_batch += BATCH_S;
            // A gap in the recording: the next batch is the one holding the next sample.
            if let Some(t_next) = beyond_batch {
                while next_batch + eps < t_next {
                    next_batch += BATCH_S;
                }
            }
        }
        // Watchdog: a pass that is neither held (flow control, real-time pacing, a restart)
        // nor finished must advance the world. If it cannot for STUCK_TIMEOUT, say why and
        // give up instead of spinning silently.
        if t_world > t_before || blocked || end_reached || batch_done {
            stuck_since = None;
        } else {
            let since = *stuck_since.get_or_insert_with(Instant::now);
            if since.elapsed() > STUCK_TIMEOUT {
                let next = sources
                    .iter()
                    .enumerate()
                    .filter_map(|(i, v)| v.next_time().map(|t| (i, t)))
                    .min_by(|a, b| a.1.total_cmp(&b.1));
                let reason = format!(
                    "the world cannot advance at t = {t_world}: next sample {next:?} (vehicle \
                     index, time), batch end {next_batch}, limit {limit}"
                );
                report(
                    &mut monitor,
                    &Report::Failed {
                        reason: reason.clone(),
                    },
                    t_world,
                );
                bail!(reason);
            }
        }
        if last_status.elapsed() >= super::vehicle::STATUS_INTERVAL {
            let state = if blocked && paced_by_team && limit <= pace {
                format!(
                    "held by the team's pace at t = {pace} (the monitor's slowest vehicle on \
                     any host + max_lead_s)"
                )
            } else {
                world_state(
                    &s,
                    &slots,
                    hub_acked,
                    hub.as_ref()
                        .is_some_and(|h| h.peer_state() == PeerState::Up),
                    limit,
                    blocked,
                    end_reached,
                    waiting_since.is_some(),
                )
            };
            report(
                &mut monitor,
                &Report::Status {
                    t: t_world,
                    state,
                    bounded_wait: waiting_since.is_some(),
                },
                t_world,
            );
            last_status = Instant::now();
        }
        if batch_done || blocked || end_reached {
            for slot in slots
                .iter_mut()
                .filter(|s| s.active && !s.pending.is_empty())
            {
                slot.seq += 1;
                let msg = WorldMsg::Batch {
                    seq: slot.seq,
                    items: std::mem::take(&mut slot.pending),
                };
                send_body(
                    &mut slot.link,
                    MessageKind::IMU_BATCH,
                    slot.seq,
                    t_world,
                    &msg,
                )?;
            }
            if let Some(h) = hub.as_mut()
                && t_world > hub_time_sent
            {
                send_body(
                    h,
                    MessageKind::IMU_BATCH,
                    0,
                    t_world,
                    &WorldMsg::Time { time: t_world },
                )?;
                hub_time_sent = t_world;
            }
            if !truth_buf.is_empty() || !frame_buf.is_empty() {
                let live: Vec<NodeId> = slots.iter().filter(|s| s.active).map(|s| s.id).collect();
                report(
                    &mut monitor,
                    &Report::Truth {
                        t: t_world,
                        samples: std::mem::take(&mut truth_buf),
                        frames: std::mem::take(&mut frame_buf),
                        live,
                    },
                    t_world,
                );
            }
        }
        if end_reached {
            let end = WorldMsg::End { time: t_world };
            for slot in slots.iter_mut().filter(|s| s.active && !s.ended) {
                send_body(&mut slot.link, MessageKind::IMU_BATCH, 0, t_world, &end)?;
                slot.ended = true;
            }
            if !finished_sent {
                if let Some(h) = hub.as_mut() {
                    send_body(h, MessageKind::IMU_BATCH, 0, t_world, &end)?;
                }
                report(&mut monitor, &Report::Finished { t: t_world }, t_world);
                finished_sent = true;
            }
        }
        if !busy {
            std::thread::sleep(Duration::from_micros(500));
        }
    }
    Ok(())
}

/// The world's state in words for the monitor's watchdog: what holds it, if anything.
#[allow(clippy::too_many_arguments)]
fn world_state(
    s: &crate::scenario::Scenario,
    slots: &[Slot],
    hub_acked: f64,
    hub_live: bool,
    limit: f64,
    blocked: bool,
    end_reached: bool,
    restart_hold: bool,
) -> String {
    if end_reached {
        return "reached the end of the run".into();
    }
    if restart_hold {
        return "holding the streams for a scheduled restart".into();
    }
    if !blocked {
        return "stepping".into();
    }
    let name = |id: NodeId| {
        s.vehicles
            .iter()
            .find(|v| v.id == id)
            .map_or_else(|| id.to_string(), |v| v.display_name())
    };
    let slowest = slots
        .iter()
        .filter(|x| x.active)
        .min_by(|a, b| a.acked.total_cmp(&b.acked));
    match slowest {
        Some(x) if hub_live && hub_acked < x.acked => format!(
            "held by flow control at the limit t = {limit}: the hub acknowledged only t = {hub_acked}"
        ),
        Some(x) => format!(
            "held by flow control at the limit t = {limit}: {} acknowledged only t = {}",
            name(x.id),
            x.acked
        ),
        None => format!("paced (no live vehicle) up to t = {limit}"),
    }
}

/// Peer-gone detection on a control link.
trait GoneExt {
    /// Drains events; true when the peer went down.
    fn drain_gone(&mut self) -> bool;
}

impl<L: Link + ?Sized> GoneExt for L {
    fn drain_gone(&mut self) -> bool {
        let mut gone = false;
        while let Some(e) = self.poll_event() {
            gone = e == LinkEvent::PeerDown;
        }
        gone
    }
}
