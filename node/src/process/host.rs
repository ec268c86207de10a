//! `canopy run SCENARIO --host NAME`: one host's share of a multi-host run (issue #14).
//!
//! 1. Resolves the scenario as every host and the monitor do (`deploy::resolve_endpoints`: a
//!    `net` link without `listen` listens on `tcp/<address of the host of its end a>:<port_base
//!    + link index>`), checks its inputs, writes it to `OUT/scenario.toml`.
//! 2. Opens the control plane: a zenoh session (node = the host's index) under
//!    `deploy::control_prefix`, connected to `[zenoh].monitor` (peer mode) or the routers
//!    (client mode). Sends `Hello` (host name, duration, seed) until the monitor answers
//!    `Welcome`; a monitor that does not answer within `--monitor-wait` seconds ends the host
//!    launcher with an error naming the endpoint, before any process starts.
//! 3. Starts the host's world (`canopy role world --host NAME`: only this host's vehicles,
//!    simulated from the scenario's seed or replayed, paced on this host's vehicles only), its
//!    vehicles and, with `hub = true`, the hub. They find "the monitor" on iceoryx2 as in a
//!    single-host run: this launcher, which relays every report to the real monitor over zenoh
//!    ([`HostMsg::Report`]) and the monitor's `Shutdown` back. Fusion links: `shm` inside the
//!    host, `net` (zenoh, key prefix `deploy::key_prefix`) to the other hosts.
//! 4. Ends when the monitor says the run ended (or Ctrl-C, or the monitor is lost): Shutdown to
//!    every local process (their final reports are still relayed), then SIGTERM, SIGKILL; every
//!    process's end goes to the monitor ([`HostMsg::Process`]), then [`HostMsg::Done`]. Children
//!    also get SIGTERM if this launcher dies (`PR_SET_PDEATHSIG`), so none is left behind.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use canopy_transport::iceoryx::{IceoryxLink, remove_run_leftovers, unique_run_prefix};
use canopy_transport::link::{Link, PeerState};
use canopy_transport::net::ZenohLink;
use canopy_transport::{MessageKind, NodeId};

use super::monitor::{
    LaunchOptions, Proc, ProcessRecord, Spawner, check_multi_host, control_session, describe,
    resolve,
};
use super::protocol::{Control, HostMsg, MONITOR_ID, Report, WORLD_ID};
use super::{control_link, decode_body, send_body};
use crate::network::FusionMode;
use crate::scenario::Scenario;

/// Options of `canopy run SCENARIO --host NAME`.
#[derive(Debug, Clone)]
pub struct HostOptions {
    /// Output directory of this host (its `scenario.toml` and `logs/`).
    pub out: PathBuf,
    /// Override of `[run].duration_s` (the monitor and every host must use the same).
    pub duration: Option<f64>,
    /// No progress lines.
    pub quiet: bool,
    /// The `canopy` executable to spawn (default: this executable).
    pub exe: Option<PathBuf>,
    /// Set to stop early (Ctrl-C).
    pub stop: Arc<AtomicBool>,
    /// How long to wait for the monitor to answer before giving up.
    pub monitor_wait: Duration,
}

/// How a host's share ended.
#[derive(Debug)]
pub struct HostOutcome {
    /// Every process it started, with how it ended.
    pub processes: Vec<ProcessRecord>,
    /// Why it failed, if it did.
    pub failure: Option<String>,
    /// It was interrupted (Ctrl-C).
    pub interrupted: bool,
}

/// How long local processes get for their final reports after Shutdown.
const LOCAL_SHUTDOWN: Duration = Duration::from_secs(10);

struct Relay {
    link: ZenohLink,
    local: BTreeMap<NodeId, IceoryxLink>,
    relayed: u64,
}

impl Relay {
    fn send(&mut self, msg: &HostMsg) {
        // Delivery failures are counted by the link; the monitor judges what it received.
        let kind = match msg {
            HostMsg::Report { report, .. } => report.kind(),
            _ => MessageKind::ESTIMATE_REPORT,
        };
        let _ = send_body(&mut self.link, kind, self.relayed, 0.0, msg);
        self.relayed += 1;
    }

    /// Relays every local report to the monitor; returns (something moved, the world's time
    /// if it reported one, the world finished).
    fn pump(&mut self) -> (bool, Option<f64>, bool) {
        let mut any = false;
        let mut world_t = None;
        let mut world_done = false;
        let ids: Vec<NodeId> = self.local.keys().copied().collect();
        for id in ids {
            let mut got = Vec::new();
            {
                let l = self.local.get_mut(&id).expect("listed");
                while l.poll_event().is_some() {}
                for _ in 0..256 {
                    match l.try_recv() {
                        Ok(Some(m)) => {
                            if let Some(r) = decode_body::<Report>(&m) {
                                got.push(r);
                            }
                        }
                        _ => break,
                    }
                }
            }
            for report in got {
                any = true;
                if id == WORLD_ID {
                    match &report {
                        Report::Status { t, .. } | Report::Truth { t, .. } => world_t = Some(*t),
                        Report::Finished { t } => {
                            world_t = Some(*t);
                            world_done = true;
                        }
                        _ => {}
                    }
                }
                self.send(&HostMsg::Report { from: id, report });
            }
        }
        (any, world_t, world_done)
    }

    /// The monitor's controls waiting now.
    fn controls(&mut self) -> Vec<Control> {
        super::controls(&mut self.link)
    }
}

/// Runs this host's share of a multi-host run until the monitor ends it.
pub fn run_host(s: Scenario, name: &str, opts: &HostOptions) -> Result<HostOutcome> {
    check_multi_host(&s, "--host")?;
    let Some((index, host)) = crate::deploy::host_named(&s, name) else {
        let names: Vec<&str> = s.hosts.iter().map(|h| h.name.as_str()).collect();
        bail!(
            "--host {name}: the scenario has no such [[host]] (hosts: {})",
            names.join(", ")
        );
    };
    let host = host.clone();
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    let mut s = s;
    if !crate::deploy::client_mode(&s) {
        crate::deploy::resolve_endpoints(&mut s).context("deriving the net links' endpoints")?;
    }
    let launch = LaunchOptions {
        out: opts.out.clone(),
        duration: opts.duration,
        baseline: Some(false),
        quiet: opts.quiet,
        netns: BTreeMap::new(),
        exe: opts.exe.clone(),
        stop: opts.stop.clone(),
        monitor_only: None,
    };
    let (s, secret) = resolve(s, &launch)?;
    crate::preflight::preflight(&s).context("checking the scenario's inputs")?;
    std::fs::write(opts.out.join("scenario.toml"), s.to_toml_string())
        .with_context(|| format!("writing {}", opts.out.join("scenario.toml").display()))?;
    let exe = match &opts.exe {
        Some(e) => e.clone(),
        None => std::env::current_exe().context("locating the canopy executable")?,
    };
    let endpoint = s
        .zenoh
        .monitor
        .clone()
        .unwrap_or_else(|| s.zenoh.connect.join(", "));
    let say = |line: String| {
        if !opts.quiet {
            eprintln!("host {name}: {line}");
        }
    };

    // The monitor first: nothing starts on this host without it.
    let session = control_session(&s, index as NodeId, &secret, opts.monitor_wait)?;
    let link = session
        .link(MONITOR_ID, super::CONTROL_MAX_BODY)
        .context("opening the control link to the monitor")?;
    let mut relay = Relay {
        link,
        local: BTreeMap::new(),
        relayed: 0,
    };
    say(format!("waiting for the monitor at {endpoint}"));
    let hello = HostMsg::Hello {
        host: name.to_string(),
        duration_s: s.run.duration_s,
        seed: s.world.seed,
    };
    let deadline = Instant::now() + opts.monitor_wait;
    let mut last_hello: Option<Instant> = None;
    let mut welcomed = false;
    while !welcomed {
        if opts.stop.load(Ordering::Relaxed) {
            return Ok(HostOutcome {
                processes: Vec::new(),
                failure: None,
                interrupted: true,
            });
        }
        if Instant::now() > deadline {
            bail!(
                "no monitor answered at {endpoint} within {:.0} s: start `canopy run SCENARIO \
                 --monitor` on the monitor's machine first, and check that this host can reach \
                 that address (and that both use the same scenario)",
                opts.monitor_wait.as_secs_f64()
            );
        }
        if relay.link.peer_state() == PeerState::Up
            && last_hello.is_none_or(|t| t.elapsed() > Duration::from_millis(500))
        {
            relay.send(&hello);
            last_hello = Some(Instant::now());
        }
        for c in relay.controls() {
            match c {
                Control::Welcome => welcomed = true,
                // Nothing runs yet: no pace to pass on, no process to kill or restart.
                Control::Pace { .. } | Control::Kill { .. } | Control::Restart { .. } => {}
                Control::Shutdown => {
                    say("the monitor ended the run before it started".into());
                    return Ok(HostOutcome {
                        processes: Vec::new(),
                        failure: Some("the monitor ended the run before it started".into()),
                        interrupted: false,
                    });
                }
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    say("connected to the monitor; starting the host's processes".into());

    // Local processes: they see this launcher as their monitor.
    let prefix = unique_run_prefix();
    let hub_here = host.hub && s.fusion.mode == FusionMode::Central;
    relay
        .local
        .insert(WORLD_ID, control_link(&prefix, MONITOR_ID, WORLD_ID, 256)?);
    let local_vehicles: Vec<(u32, String)> = s
        .vehicles
        .iter()
        .filter(|v| host.vehicles.contains(&v.id))
        .map(|v| (v.id, v.display_name()))
        .collect();
    for (id, _) in &local_vehicles {
        relay
            .local
            .insert(*id, control_link(&prefix, MONITOR_ID, *id, 256)?);
    }
    if hub_here {
        relay.local.insert(
            s.fusion.hub_id,
            control_link(&prefix, MONITOR_ID, s.fusion.hub_id, 256)?,
        );
    }
    let extra = vec![
        "--net-prefix".to_string(),
        crate::deploy::key_prefix(&s),
        "--host".to_string(),
        name.to_string(),
    ];
    let no_netns = BTreeMap::new();
    let spawner = Spawner {
        out: &opts.out,
        prefix: &prefix,
        exe: &exe,
        netns: &no_netns,
        extra: &extra,
    };
    let mut procs: Vec<Proc> = Vec::new();
    let mut failure: Option<String> = None;
    let spawn = |n: &str, v: Option<u32>, inc: u32, procs: &mut Vec<Proc>| -> Result<()> {
        procs.push(spawner.spawn(n, v, inc, &secret)?);
        Ok(())
    };
    let spawned = (|| -> Result<()> {
        spawn("world", None, 0, &mut procs)?;
        if hub_here {
            spawn("hub", None, 0, &mut procs)?;
        }
        for (id, n) in &local_vehicles {
            spawn(n, Some(*id), 0, &mut procs)?;
        }
        Ok(())
    })();
    if let Err(e) = spawned {
        failure = Some(format!("{e:#}"));
    }

    let mut sent_records = vec![false; 0];
    let mut world_finished = false;
    let mut world_t = 0.0_f64;
    let mut next_plain = 10.0;
    let mut interrupted = false;
    let mut shutdown_asked = false;
    let mut monitor_down: Option<Instant> = None;
    while failure.is_none() {
        if opts.stop.load(Ordering::Relaxed) {
            interrupted = true;
            break;
        }
        let (busy, wt, done) = relay.pump();
        if let Some(t) = wt {
            world_t = world_t.max(t);
        }
        world_finished |= done;
        if world_t >= next_plain {
            say(format!("t = {world_t:.1} s of {:.1} s", s.run.duration_s));
            next_plain += 10.0;
        }
        for c in relay.controls() {
            match c {
                Control::Shutdown => shutdown_asked = true,
                // The team's pace: for this host's world.
                Control::Pace { .. } => {
                    if let Some(l) = relay.local.get_mut(&WORLD_ID) {
                        let _ = send_body(l, MessageKind::CONTROL, 0, 0.0, &c);
                    }
                }
                Control::Welcome => {}
                // A scheduled crash or hub loss (the monitor runs the scenario's events).
                Control::Kill { name: who } => {
                    let mut killed = false;
                    for p in procs
                        .iter_mut()
                        .filter(|p| p.name == who && p.status.is_none())
                    {
                        p.planned_kill = true;
                        p.ended_at = world_t;
                        let pid = nix::unistd::Pid::from_raw(p.child.id() as i32);
                        let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGKILL);
                        killed = true;
                    }
                    if killed {
                        say(format!(
                            "{who} killed with SIGKILL (scheduled by the monitor)"
                        ));
                    } else {
                        eprintln!(
                            "host {name}: the monitor asked to kill {who}, which does not run \
                             here (ignored)"
                        );
                    }
                }
                Control::Restart {
                    vehicle,
                    incarnation,
                } => {
                    let Some((_, vname)) = local_vehicles.iter().find(|(id, _)| *id == vehicle)
                    else {
                        eprintln!(
                            "host {name}: the monitor asked to restart vehicle {vehicle}, which \
                             does not run here (ignored)"
                        );
                        continue;
                    };
                    let started = procs
                        .iter()
                        .any(|p| p.vehicle == Some(vehicle) && p.incarnation >= incarnation);
                    if started {
                        continue;
                    }
                    match spawn(vname, Some(vehicle), incarnation, &mut procs) {
                        Ok(()) => say(format!("{vname} restarted (incarnation {incarnation})")),
                        Err(e) => {
                            failure = Some(format!("restarting {vname}: {e:#}"));
                        }
                    }
                }
            }
        }
        if failure.is_some() {
            break;
        }
        if shutdown_asked {
            break;
        }
        // The monitor out of reach: a network cut heals (zenoh reconnects; meanwhile the team's
        // pace holds every world), a dead monitor does not.
        if relay.link.peer_state() == PeerState::Up {
            monitor_down = None;
        } else {
            let since = *monitor_down.get_or_insert_with(|| {
                eprintln!("host {name}: the monitor at {endpoint} is out of reach");
                Instant::now()
            });
            if since.elapsed() > super::monitor::LOST_GRACE {
                failure = Some(format!(
                    "lost the monitor at {endpoint} (its zenoh session went away and did not \
                     come back within {} s)",
                    super::monitor::LOST_GRACE.as_secs()
                ));
                break;
            }
        }
        // Reap: every end goes to the monitor at once.
        sent_records.resize(procs.len(), false);
        for (k, p) in procs.iter_mut().enumerate() {
            if p.status.is_none()
                && let Ok(Some(st)) = p.child.try_wait()
            {
                p.status = Some(st);
                p.ended_at = world_t;
                let expected = p.planned_kill || (st.success() && world_finished);
                if !expected {
                    eprintln!(
                        "host {name}: process {} (pid {}) ended unexpectedly: {}; see {}",
                        p.name,
                        p.child.id(),
                        describe(&st),
                        p.log.display()
                    );
                    if p.name == "world" {
                        failure = Some(format!("the world process ended: {}", describe(&st)));
                    }
                }
                relay.send(&HostMsg::Process(p.record()));
                sent_records[k] = true;
            }
        }
        if !busy {
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    // Shutdown: vehicles and hub first (their final reports), then the world.
    let local_ids: Vec<NodeId> = relay.local.keys().copied().collect();
    for id in local_ids.iter().filter(|&&i| i != WORLD_ID) {
        if let Some(l) = relay.local.get_mut(id) {
            let _ = send_body(l, MessageKind::CONTROL, 0, 0.0, &Control::Shutdown);
        }
    }
    if let Some(l) = relay.local.get_mut(&WORLD_ID) {
        let _ = send_body(l, MessageKind::CONTROL, 0, 0.0, &Control::Shutdown);
    }
    let running = |procs: &mut Vec<Proc>| {
        for p in procs.iter_mut().filter(|p| p.status.is_none()) {
            if let Ok(Some(st)) = p.child.try_wait() {
                p.status = Some(st);
                p.ended_at = world_t;
            }
        }
        procs.iter().filter(|p| p.status.is_none()).count()
    };
    let end = Instant::now() + LOCAL_SHUTDOWN;
    while running(&mut procs) > 0 && Instant::now() < end {
        relay.pump();
        std::thread::sleep(Duration::from_millis(5));
    }
    for sig in [
        nix::sys::signal::Signal::SIGTERM,
        nix::sys::signal::Signal::SIGKILL,
    ] {
        if running(&mut procs) == 0 {
            break;
        }
        for p in procs.iter_mut().filter(|p| p.status.is_none()) {
            eprintln!("host {name}: {} did not stop; sending {sig}", p.name);
            p.planned_kill = true;
            let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(p.child.id() as i32), sig);
        }
        let end = Instant::now() + Duration::from_secs(3);
        while running(&mut procs) > 0 && Instant::now() < end {
            relay.pump();
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    for p in procs.iter_mut().filter(|p| p.status.is_none()) {
        p.status = p.child.wait().ok();
    }
    relay.pump();
    sent_records.resize(procs.len(), false);
    for (k, p) in procs.iter().enumerate() {
        if !sent_records[k] {
            relay.send(&HostMsg::Process(p.record()));
        }
    }
    if interrupted {
        failure.get_or_insert("interrupted on this host (Ctrl-C)".into());
    }
    relay.send(&HostMsg::Done {
        failure: failure.clone(),
    });
    // Give zenoh a moment to hand the last messages to TCP before the session closes.
    std::thread::sleep(Duration::from_millis(300));
    drop(relay);
    let _ = session.close();
    let removed = remove_run_leftovers(&prefix);
    tracing::debug!(removed, "iceoryx2 leftovers removed");
    let processes = procs.iter().map(Proc::record).collect();
    Ok(HostOutcome {
        processes,
        failure,
        interrupted,
    })
}
