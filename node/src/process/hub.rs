//! The hub process of central mode: a [`HubAgent`] (no observations; its estimate is the sum of
//! what the vehicles sent, fed back through channel filters) with a link to every vehicle. It
//! has no sensors, so its clock is the world's simulation time, which the world publishes; it
//! acknowledges the time it has reached (`Progress`), so that the world, like for every vehicle,
//! never runs more than `[run].max_lead_s` ahead of it (a hub that fell behind the team would
//! miss the last rounds of the run: measured 40-50 s of 300 in central-4 before this).

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use canopy_fusion::topology::NodeId;
use canopy_transport::MessageKind;
use canopy_transport::link::{Link, LinkEvent};

use super::protocol::{Control, MONITOR_ID, Progress, Report, WORLD_ID, WorldMsg};
use super::{
    FusionLinks, RoleCommon, control_link, decode_body, fresh_epoch, link_report, load_resolved,
    naive_round_bytes, send_body, stop_flag,
};
use crate::agent::HubAgent;
use crate::network::topology;
use crate::world::World;

/// Runs the hub process.
pub fn run(c: &RoleCommon) -> Result<()> {
    let stop = stop_flag();
    let s = load_resolved(c)?;
    canopy_fusion::runtime::set_heap_policy(s.run.heap);
    let me = s.fusion.hub_id;
    let world = World::new(&s.world, s.world.seed).context("building the world frame")?;
    let epoch = fresh_epoch();
    let mut agent = HubAgent::new(
        NodeId(me),
        epoch,
        world.map_origin(),
        &topology(&s)?,
        s.fusion.ddf_config(),
    )
    .context("building the hub")?;
    let mut wl = control_link(&c.prefix, me, WORLD_ID, 64)?;
    let mut monitor = control_link(&c.prefix, me, MONITOR_ID, 64)?;
    let mut links = FusionLinks::open(&s, c, me, 0)?;
    if !super::wait_peer_up(&mut monitor, Duration::from_secs(120), &stop) {
        bail!("the monitor did not come up");
    }
    let hello = Report::Started {
        pid: std::process::id(),
        epoch,
        incarnation: 0,
    };
    send_body(&mut monitor, hello.kind(), 0, 0.0, &hello)?;

    let round_dt = 1.0 / s.fusion.rate_hz;
    let record_dt = s.run.record_interval_s;
    let mut t = 0.0_f64;
    let mut next_round = round_dt;
    let mut naive_bytes = 0u64;
    let mut next_report = 0.0;
    let mut finished = false;
    let mut world_seen = false;
    let started = Instant::now();
    loop {
        let mut shutdown = stop.load(Ordering::Relaxed);
        while let Ok(Some(m)) = monitor.try_recv() {
            if let Some(Control::Shutdown) = decode_body::<Control>(&m) {
                shutdown = true;
            }
        }
        let mut world_time = None;
        while let Some(m) = wl.try_recv()? {
            match decode_body::<WorldMsg>(&m) {
                Some(WorldMsg::Time { time }) => world_time = Some(time),
                Some(WorldMsg::End { time }) => {
                    world_time = Some(time);
                    finished = true;
                }
                _ => {}
            }
        }
        while let Some(e) = wl.poll_event() {
            world_seen |= e == LinkEvent::PeerUp;
        }
        if !world_seen && started.elapsed() > Duration::from_secs(120) {
            bail!("the world process did not come up");
        }
        let service = |agent: &mut HubAgent, links: &mut FusionLinks, now: f64| {
            for (peer, events, msgs) in links.poll() {
                for ev in events {
                    let out = match ev {
                        // Failures are counted by reason and logged once by the hub agent
                        // (`HubAgent::rejections`, in the hub's reports and checks.json).
                        LinkEvent::PeerUp => {
                            agent.on_link_up(now, NodeId(peer)).unwrap_or_default()
                        }
                        LinkEvent::PeerDown => {
                            let _ = agent.on_link_down(NodeId(peer));
                            Vec::new()
                        }
                    };
                    links.send(now, out);
                }
                for msg in msgs {
                    // Rejected messages are counted by reason by the hub agent.
                    let out = agent.on_message(now, NodeId(peer), msg).unwrap_or_default();
                    links.send(now, out);
                }
            }
        };
        if let Some(wt) = world_time {
            while next_round <= wt + 1e-9 {
                t = next_round;
                links.clock.set(t);
                service(&mut agent, &mut links, t);
                naive_bytes += naive_round_bytes(agent.store().ids.len());
                // A failed round sends nothing; counted by reason by the hub agent.
                let out = agent.on_round(t).unwrap_or_default();
                links.send(t, out);
                next_round += round_dt;
            }
            t = t.max(wt);
            links.clock.set(t);
            // Flow control: the world paces itself by this acknowledgement.
            let ack = Progress {
                incarnation: 0,
                time: t,
            };
            let _ = send_body(&mut wl, MessageKind::HEARTBEAT, 0, t, &ack);
        }
        service(&mut agent, &mut links, t);
        if t + 1e-9 >= next_report || shutdown || finished {
            let reports = links
                .links
                .iter()
                .map(|(&peer, l)| {
                    link_report(peer, l, agent.ddf().channel(NodeId(peer)), naive_bytes)
                })
                .collect();
            let r = Report::Hub {
                t,
                links: reports,
                rejected: agent.rejected(),
                access_refused: super::access_refusals(),
                rejections: {
                    let mut r = agent.rejections().clone();
                    r.merge(&links.send_failures.counts);
                    r.counts
                },
            };
            let _ = send_body(&mut monitor, r.kind(), 0, t, &r);
            while next_report <= t + 1e-9 {
                next_report += record_dt;
            }
        }
        if finished {
            let r = Report::Finished { t };
            let _ = send_body(&mut monitor, r.kind(), 0, t, &r);
            finished = false;
        }
        if shutdown {
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}
