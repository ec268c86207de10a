//! `canopy router SCENARIO`: the zenoh router of a multi-host run in client mode
//! (`[zenoh].mode = "client"`, issue #14).
//!
//! Every zenoh session of the run — the vehicles' and the hub's `net` links, the host launchers,
//! the monitor — is a client of this router: it connects to `[zenoh].connect` and listens
//! nowhere, and the router routes between them. With the team's password
//! (`[secrets].zenoh_password`) each client authenticates as its own user (node name,
//! `host-NAME`, `monitor`), and the router — the one session that knows every client's user —
//! enforces the access control built from the scenario's key layout
//! ([`crate::deploy::router_access`]): default deny; a node may publish, subscribe and hold or
//! watch liveliness only on its own side of its `net` links, a host launcher only on its
//! control link to the monitor. Whatever else a client attempts (a non-neighbour, a node
//! claiming another's key, two vehicles of one host trying to talk through the router without a
//! `net` link between them) is refused at the router and counted here
//! ([`super::access_refusals`], ingress only: egress refusals are the router withholding one
//! client's declarations from another, which is routine).
//!
//! The router joins the run's control plane as [`ROUTER_ID`]: it says `Hello` to the monitor
//! (same scenario: duration and seed), sends its refusals whenever they change
//! ([`HostMsg::Refusals`]; the monitor writes the last ones to `checks.json`, `summary.json` and
//! `report.html`), and when the monitor ends the run (after every host is done: their messages
//! go through the router) sends its final refusals and `Done`, then stays until the monitor's
//! session has gone, and exits 0. It fails when no monitor answers within `--monitor-wait`, or
//! when the monitor goes away before ending the run and does not come back within
//! [`LOST_GRACE`].

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use canopy_transport::MessageKind;
use canopy_transport::link::{Link, PeerState};
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohLink, ZenohMode, ZenohTransport};

use super::monitor::{LOST_GRACE, LaunchOptions, check_multi_host, resolve};
use super::protocol::{Control, HostMsg, MONITOR_ID, ROUTER_ID};
use super::{access_refusals, send_body};
use crate::deploy::{ROUTER_USER, client_mode, control_prefix, router_access, team_users};
use crate::scenario::Scenario;

/// Options of `canopy router SCENARIO`.
#[derive(Debug, Clone)]
pub struct RouterOptions {
    /// Endpoints to listen on (default: every endpoint of `[zenoh].connect`).
    pub listen: Vec<String>,
    /// Override of `[run].duration_s` (as the monitor's and every host's).
    pub duration: Option<f64>,
    /// How long to wait for the monitor before giving up.
    pub monitor_wait: Duration,
    /// No progress lines.
    pub quiet: bool,
    /// Set to stop (Ctrl-C).
    pub stop: Arc<AtomicBool>,
}

/// How often the router looks at its refusal count (and sends it when it changed).
const REPORT_EVERY: Duration = Duration::from_millis(250);
/// After the monitor ended the run, how long the router waits for the monitor's session to go
/// before it exits anyway.
const LINGER: Duration = Duration::from_secs(30);

/// The router's control link to the monitor.
struct ToMonitor {
    link: ZenohLink,
    seq: u64,
}

impl ToMonitor {
    fn send(&mut self, msg: &HostMsg) {
        // Delivery failures are counted by the link; the monitor judges what it received.
        let _ = send_body(&mut self.link, MessageKind::CONTROL, self.seq, 0.0, msg);
        self.seq += 1;
    }

    fn controls(&mut self) -> Vec<Control> {
        super::controls(&mut self.link)
    }
}

/// The zenoh configuration of the router of `s` (resolved; `password` the team's).
pub fn router_config(s: &Scenario, listen: Vec<String>, password: Option<String>) -> ZenohConfig {
    let mut cfg = ZenohConfig::new(control_prefix(s), listen, Vec::new());
    cfg.mode = ZenohMode::Router;
    cfg.multicast_scouting = s.zenoh.multicast_scouting;
    cfg.tls = s.zenoh.tls.as_ref().map(|t| t.for_user(ROUTER_USER));
    if let Some(p) = password {
        cfg.auth = Some(ZenohAuth {
            user: ROUTER_USER.to_string(),
            password: p.clone(),
            accept: team_users(s).into_iter().map(|u| (u, p.clone())).collect(),
        });
        cfg.access = Some(router_access(s));
    }
    cfg
}

/// Runs the router of a client-mode multi-host run until the monitor has ended the run.
pub fn run_router(s: Scenario, opts: &RouterOptions) -> Result<()> {
    check_multi_host(&s, "canopy router")?;
    if !client_mode(&s) {
        bail!(
            "canopy router: the scenario's [zenoh].mode is \"peer\" (its sessions connect to each \
             other, not to a router); set mode = \"client\" and connect = [\"tcp/ROUTER:PORT\"]"
        );
    }
    let launch = LaunchOptions {
        out: std::env::temp_dir(),
        duration: opts.duration,
        baseline: Some(false),
        quiet: opts.quiet,
        netns: BTreeMap::new(),
        exe: None,
        stop: opts.stop.clone(),
        monitor_only: None,
    };
    let (s, secret) = resolve(s, &launch)?;
    let listen = if opts.listen.is_empty() {
        s.zenoh.connect.clone()
    } else {
        opts.listen.clone()
    };
    let say = |line: String| {
        if !opts.quiet {
            eprintln!("router: {line}");
        }
    };
    if secret.is_none() {
        say(
            "no [secrets].zenoh_password: clients are not authenticated and the router enforces \
             no access control"
                .into(),
        );
    }
    let session = ZenohTransport::open(ROUTER_ID, router_config(&s, listen.clone(), secret))
        .with_context(|| format!("opening the zenoh router on {}", listen.join(", ")))?;
    let control = session.scoped(ROUTER_ID, &control_prefix(&s))?;
    let mut monitor = ToMonitor {
        link: control
            .link(MONITOR_ID, super::CONTROL_MAX_BODY)
            .context("opening the router's control link to the monitor")?,
        seq: 0,
    };
    say(format!(
        "listening on {}; waiting for the monitor",
        listen.join(", ")
    ));

    let hello = HostMsg::Hello {
        host: ROUTER_USER.to_string(),
        duration_s: s.run.duration_s,
        seed: s.world.seed,
    };
    let deadline = Instant::now() + opts.monitor_wait;
    let mut last_hello: Option<Instant> = None;
    let mut welcomed = false;
    let mut ended: Option<Instant> = None;
    let mut sent: Option<BTreeMap<String, u64>> = None;
    let mut last_look = Instant::now();
    let mut monitor_down: Option<Instant> = None;
    let failure = loop {
        if opts.stop.load(Ordering::Relaxed) {
            break Some("interrupted (Ctrl-C)".to_string());
        }
        let up = monitor.link.peer_state() == PeerState::Up;
        if !welcomed {
            if Instant::now() > deadline {
                break Some(format!(
                    "no monitor answered within {:.0} s: start `canopy run SCENARIO --monitor` \
                     (and every `--host`) with [zenoh].connect reaching this router",
                    opts.monitor_wait.as_secs_f64()
                ));
            }
            if up && last_hello.is_none_or(|t| t.elapsed() > Duration::from_millis(500)) {
                monitor.send(&hello);
                last_hello = Some(Instant::now());
            }
        }
        for c in monitor.controls() {
            match c {
                Control::Welcome if !welcomed => {
                    welcomed = true;
                    say("the monitor accepted this router".into());
                }
                Control::Shutdown if ended.is_none() => {
                    monitor.send(&HostMsg::Refusals(access_refusals()));
                    monitor.send(&HostMsg::Done { failure: None });
                    ended = Some(Instant::now());
                    say("the monitor ended the run".into());
                }
                _ => {}
            }
        }
        if let Some(since) = ended {
            // The monitor closes its session once it has written the outputs.
            if !up || since.elapsed() > LINGER {
                break None;
            }
        } else if welcomed {
            if last_look.elapsed() >= REPORT_EVERY {
                last_look = Instant::now();
                let now = access_refusals();
                if sent.as_ref() != Some(&now) {
                    monitor.send(&HostMsg::Refusals(now.clone()));
                    sent = Some(now);
                }
            }
            if up {
                monitor_down = None;
            } else {
                let since = *monitor_down.get_or_insert_with(|| {
                    say("the monitor is out of reach".into());
                    Instant::now()
                });
                if since.elapsed() > LOST_GRACE {
                    break Some(format!(
                        "lost the monitor (its zenoh session went away before the end of the \
                         run and did not come back within {} s)",
                        LOST_GRACE.as_secs()
                    ));
                }
            }
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let refused = access_refusals();
    say(format!(
        "refused {} message(s) of its clients{}",
        refused.values().sum::<u64>(),
        if refused.is_empty() {
            String::new()
        } else {
            format!(": {refused:?}")
        }
    ));
    // Give zenoh a moment to hand the last messages to TCP before the session closes.
    std::thread::sleep(Duration::from_millis(300));
    drop(monitor);
    drop(control);
    let _ = session.close();
    match failure {
        None => Ok(()),
        Some(f) => bail!("canopy router: {f}"),
    }
}
