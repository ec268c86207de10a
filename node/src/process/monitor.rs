//! `canopy run`: the launcher, which is also the monitor of the run.
//!
//! 1. Resolves the scenario (duration and baseline overrides, a free loopback port for every
//!    `net` link without `listen`, absolute replay paths, secrets removed — they reach the
//!    children through the environment) and writes it to `OUT/scenario.toml`; chooses a fresh
//!    iceoryx2 prefix for the run.
//! 2. Opens its links to every process, then spawns the world, one process per vehicle and, in
//!    central mode, the hub (`canopy role …`, each in its own process group so a terminal's
//!    Ctrl-C reaches only the monitor; output to `OUT/logs/`).
//! 3. Gathers reports (estimates, maps, truth, link statistics), shows progress over simulated
//!    time, runs the scenario's `[[event]]`s (SIGKILL a vehicle when its reported time reaches
//!    `at_s`, restart it with a new incarnation once the team reaches `at_s + restart_after_s`;
//!    kill the hub), reaps children and reports any that exit unexpectedly (status or signal).
//! 4. Meanwhile runs the centralized reference in a thread ([`crate::baseline`]).
//! 5. At the end (or on Ctrl-C, or when the world fails) asks every process to shut down,
//!    waits (then SIGTERM, then SIGKILL), removes the run's iceoryx2 leftovers, and builds the
//!    [`RunRecord`] and [`RunChecks`] from what was gathered.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use canopy_fusion::ddf::ChannelStats;
use canopy_fusion::frames::Frame4;
use canopy_fusion::ins::{VehicleCovariance, VehicleState, VehicleVector};
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::state::VEHICLE_DIM;
use canopy_transport::iceoryx::{IceoryxLink, remove_run_leftovers, unique_run_prefix};
use canopy_transport::link::{Link, PeerState};
use canopy_transport::{MessageKind, NodeId};
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::protocol::{
    Control, EstimateReport, FeatureReport, FrameAssociations, HostMsg, LinkReport, MONITOR_ID,
    Report, TruthReport, VehicleCounters, WORLD_ID,
};
use super::{ENV_ZENOH_PASSWORD, control_link, decode_body, send_body};
use crate::baseline::{BaselineRun, run_reference};
use crate::metrics::{
    HeldSince, estimate_sample, feature_confidence_ratio, feature_record, pose_sample,
};
use crate::network::{EventKind, FusionMode, TransportKind, effective_links, node_names};
use crate::record::{EventRecord, LinkRecord, LinkSample, RunRecord, VehicleRecord};
use crate::scenario::Scenario;
use crate::truth::{KeyTruth, TruthAudit, fill_record};
use crate::world::{TruthSample, World};

/// Options of a multi-process run.
#[derive(Debug, Clone)]
pub struct LaunchOptions {
    /// Output directory (created).
    pub out: PathBuf,
    /// Override of `[run].duration_s`.
    pub duration: Option<f64>,
    /// Override of `[run].baseline`.
    pub baseline: Option<bool>,
    /// No progress display.
    pub quiet: bool,
    /// Network namespace per vehicle id: the vehicle process runs under `ip netns exec NS`.
    pub netns: BTreeMap<u32, String>,
    /// The `canopy` executable to spawn (default: this executable).
    pub exe: Option<PathBuf>,
    /// Set to stop the run early (Ctrl-C); outputs are still written.
    pub stop: Arc<AtomicBool>,
    /// `canopy run --monitor`: start no process here; gather every `[[host]]` launcher's
    /// reports over zenoh (`[zenoh].monitor`), waiting this long for all of them to connect.
    pub monitor_only: Option<Duration>,
}

/// How a process of the run ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ProcessRecord {
    /// `world`, `hub` or the vehicle's name.
    pub name: String,
    /// Incarnation (restarts of a vehicle).
    pub incarnation: u32,
    /// OS process id.
    pub pid: u32,
    /// Exit code, when it exited.
    pub exit_code: Option<i32>,
    /// Signal that ended it, when one did.
    pub signal: Option<i32>,
    /// It was killed on purpose (a scheduled crash or hub loss, or a straggler at shutdown).
    pub killed_by_monitor: bool,
    /// Its output contains a Rust panic message.
    pub panicked: bool,
    /// Simulated time when it ended (team time) [s].
    pub ended_at: f64,
    /// Its log file.
    pub log: PathBuf,
}

impl ProcessRecord {
    /// Exited with status 0.
    pub fn clean_exit(&self) -> bool {
        self.exit_code == Some(0)
    }
}

/// One confidence check of a vehicle's map report against the centralized reference.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ConfidenceSample {
    /// Vehicle name.
    pub vehicle: String,
    /// Time of the map report [s].
    pub t: f64,
    /// Time of the reference snapshot it was compared with [s] (t + the flow-control lead,
    /// capped at the end: no vehicle can hold information gathered after that).
    pub reference_t: f64,
    /// Largest λ_max(P_ref · P_i⁻¹) over the features common to both (≤ 1 when the vehicle is
    /// never more confident than all the team's data allows).
    pub ratio: f64,
    /// The feature where it occurred.
    pub feature: FeatureId,
    /// Features compared.
    pub features: usize,
}

/// Counters of one vehicle, summed over its incarnations.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VehicleCheck {
    /// Vehicle name.
    pub name: String,
    /// Final counters per incarnation.
    pub counters: Vec<VehicleCounters>,
    /// Estimate reports received.
    pub estimate_reports: usize,
    /// Map reports received.
    pub map_reports: usize,
    /// Time of the last estimate report [s].
    pub last_report_t: f64,
    /// Features in the last map.
    pub final_map_features: usize,
    /// Map size at every map report: (t, features).
    pub map_sizes: Vec<(f64, usize)>,
    /// Times it was initialised (1 + restarts).
    pub initialisations: usize,
    /// Its association and final map against the truth (`crate::truth`; as in
    /// `summary.json`).
    #[serde(default)]
    pub association: crate::truth::TruthFigures,
    /// Inputs its estimator rejected, by reason, summed over incarnations (as in
    /// `summary.json`).
    #[serde(default)]
    pub rejections: BTreeMap<String, u64>,
    /// Peak resident memory of its process [MB] (the largest over its incarnations; absent
    /// where the kernel does not report it).
    #[serde(default)]
    pub peak_rss_mb: Option<f64>,
    /// What its zenoh access control refused, by `"<action> on <key>"`, summed over its
    /// incarnations (as in `summary.json`).
    #[serde(default)]
    pub access_refused: BTreeMap<String, u64>,
}

/// One end of a fusion link at the end of the run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LinkEndCheck {
    /// This end's node name.
    pub node: String,
    /// The other end's node name.
    pub peer: String,
    /// Incarnation of this end's last report.
    pub incarnation: u32,
    /// Counters.
    pub report: LinkReport,
}

/// What `checks.json` holds: process exits, consistency checks against the reference, counters.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunChecks {
    /// Every process started, with how it ended.
    pub processes: Vec<ProcessRecord>,
    /// Confidence of every map report against the reference (empty without baseline).
    pub confidence: Vec<ConfidenceSample>,
    /// Largest of `confidence[].ratio`.
    pub max_confidence_ratio: Option<f64>,
    /// Flow-control lead used for the reference time [s].
    pub lead_s: f64,
    /// Per vehicle.
    pub vehicles: Vec<VehicleCheck>,
    /// The last report of each end of each fusion link (counters summed over incarnations,
    /// channel statistics of the current one).
    pub link_ends: Vec<LinkEndCheck>,
    /// Hub: DDF messages it rejected.
    pub hub_rejected: u64,
    /// Hub: what its zenoh access control refused, by `"<action> on <key>"`.
    #[serde(default)]
    pub hub_access_refused: BTreeMap<String, u64>,
    /// `--monitor`: what the monitor's control-plane session refused of the host launchers'
    /// sessions (a session using a host's control link that is not that host's).
    #[serde(default)]
    pub control_access_refused: BTreeMap<String, u64>,
    /// `--monitor` in client mode: what the zenoh router's access control refused of its
    /// clients (every session of the run: vehicles, hub, host launchers, the monitor, and
    /// anyone else with a credential), by `"<action> on <key>"`, as it last reported.
    #[serde(default)]
    pub router_access_refused: BTreeMap<String, u64>,
    /// Hub: every failure on its fusion path, by reason (rejected messages, refused
    /// information, failed rounds, link events).
    #[serde(default)]
    pub hub_rejections: BTreeMap<String, u64>,
    /// The run was interrupted (Ctrl-C).
    pub interrupted: bool,
    /// Why the run failed, if it did.
    pub failure: Option<String>,
    /// iceoryx2 prefix of the run.
    pub prefix: String,
}

/// The outcome of a multi-process run.
#[derive(Debug)]
pub struct LaunchOutcome {
    /// What was gathered.
    pub record: RunRecord,
    /// Process and consistency checks.
    pub checks: RunChecks,
}

fn ms(t: f64) -> i64 {
    (t * 1000.0).round() as i64
}

pub(crate) struct Proc {
    pub(crate) name: String,
    pub(crate) vehicle: Option<u32>,
    pub(crate) incarnation: u32,
    pub(crate) child: Child,
    pub(crate) planned_kill: bool,
    pub(crate) status: Option<ExitStatus>,
    pub(crate) ended_at: f64,
    pub(crate) log: PathBuf,
}

impl Proc {
    /// How it ended, for `checks.json` (its log is read for a panic message).
    pub(crate) fn record(&self) -> ProcessRecord {
        use std::os::unix::process::ExitStatusExt;
        let log = std::fs::read_to_string(&self.log).unwrap_or_default();
        ProcessRecord {
            name: self.name.clone(),
            incarnation: self.incarnation,
            pid: self.child.id(),
            exit_code: self.status.and_then(|s| s.code()),
            signal: self.status.and_then(|s| s.signal()),
            killed_by_monitor: self.planned_kill,
            panicked: log.contains("panicked at"),
            ended_at: self.ended_at,
            log: self.log.clone(),
        }
    }
}

/// Where and how the processes of a run are started.
pub(crate) struct Spawner<'a> {
    /// Output directory (its `scenario.toml`, `logs/`).
    pub out: &'a Path,
    /// iceoryx2 prefix.
    pub prefix: &'a str,
    /// The canopy executable.
    pub exe: &'a Path,
    /// Network namespace per vehicle.
    pub netns: &'a BTreeMap<u32, String>,
    /// Extra `canopy role` options (`--net-prefix`, `--host` of a multi-host run).
    pub extra: &'a [String],
}

impl Spawner<'_> {
    /// Starts `canopy role …` for `name` (`world`, `hub` or a vehicle) in its own process
    /// group, its output to `OUT/logs/NAME[.INCARNATION].log`.
    pub(crate) fn spawn(
        &self,
        name: &str,
        vehicle: Option<u32>,
        incarnation: u32,
        secret: &Option<String>,
    ) -> Result<Proc> {
        let logs = self.out.join("logs");
        std::fs::create_dir_all(&logs)?;
        let log = logs.join(if incarnation == 0 {
            format!("{name}.log")
        } else {
            format!("{name}.{incarnation}.log")
        });
        let file =
            std::fs::File::create(&log).with_context(|| format!("creating {}", log.display()))?;
        let scenario = self.out.join("scenario.toml");
        let mut args: Vec<String> = vec!["role".into()];
        match (name, vehicle) {
            ("world", _) => args.push("world".into()),
            ("hub", _) => args.push("hub".into()),
            (_, Some(id)) => {
                args.extend(["vehicle".into(), "--id".into(), id.to_string()]);
                args.extend(["--incarnation".into(), incarnation.to_string()]);
            }
            _ => unreachable!("a role without vehicle id is the world or the hub"),
        }
        args.extend([
            "--scenario".into(),
            scenario.display().to_string(),
            "--prefix".into(),
            self.prefix.to_string(),
        ]);
        args.extend(self.extra.iter().cloned());
        let mut cmd = match vehicle.and_then(|id| self.netns.get(&id)) {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns]).arg(self.exe);
                c
            }
            None => Command::new(self.exe),
        };
        cmd.args(&args)
            .stdin(Stdio::null())
            .stdout(file.try_clone()?)
            .stderr(file)
            .process_group(0);
        if let Some(p) = secret {
            cmd.env(ENV_ZENOH_PASSWORD, p);
        }
        let child = cmd
            .spawn()
            .with_context(|| format!("spawning the {name} process ({})", self.exe.display()))?;
        Ok(Proc {
            name: name.to_string(),
            vehicle,
            incarnation,
            child,
            planned_kill: false,
            status: None,
            ended_at: 0.0,
            log,
        })
    }
}

#[derive(Default)]
struct LinkStream {
    incarnation: u32,
    base: LinkReport,
    last: LinkReport,
    /// (t, cumulative over incarnations)
    samples: Vec<(f64, LinkReport)>,
}

fn add(a: &LinkReport, b: &LinkReport) -> LinkReport {
    LinkReport {
        peer: b.peer,
        sent_messages: a.sent_messages + b.sent_messages,
        sent_bytes: a.sent_bytes + b.sent_bytes,
        received_messages: a.received_messages + b.received_messages,
        received_bytes: a.received_bytes + b.received_bytes,
        dropped_send: a.dropped_send + b.dropped_send,
        dropped_faults: a.dropped_faults + b.dropped_faults,
        rejected_transport: a.rejected_transport + b.rejected_transport,
        rejected_channel: a.rejected_channel + b.rejected_channel,
        up: b.up,
        ci: a.ci || b.ci,
        channel: b.channel,
        naive_bytes: a.naive_bytes + b.naive_bytes,
    }
}

impl LinkStream {
    fn push(&mut self, t: f64, incarnation: u32, r: LinkReport) {
        if incarnation != self.incarnation {
            self.base = add(&self.base, &self.last);
            self.incarnation = incarnation;
        }
        self.last = r;
        self.samples.push((t, add(&self.base, &r)));
    }
    fn at(&self, t: f64) -> Option<&LinkReport> {
        let k = self.samples.partition_point(|(ts, _)| *ts <= t + 1e-6);
        k.checked_sub(1).map(|k| &self.samples[k].1)
    }
}

#[derive(Default)]
struct Gathered {
    name: String,
    replay: bool,
    incarnation: u32,
    alive: bool,
    last_t: f64,
    finished: bool,
    estimates: Vec<(f64, Vec<f64>, Vec<f64>)>,
    maps: Vec<(f64, Vec<FeatureReport>)>,
    last_map: Option<(f64, Vec<FeatureReport>)>,
    associations: Vec<FrameAssociations>,
    /// The correspondences of its latest map report.
    merges: Vec<canopy_fusion::keys::Merge>,
    counters: BTreeMap<u32, VehicleCounters>,
    initialisations: usize,
    restarts: u32,
}

struct Monitor {
    s: Scenario,
    /// Local SLAM in own frames: each simulated vehicle's own frame in the launch frame (truth,
    /// from its true start), to express the estimates reported in it there. Empty otherwise.
    launch_from_own: BTreeMap<u32, Frame4>,
    out: PathBuf,
    prefix: String,
    exe: PathBuf,
    netns: BTreeMap<u32, String>,
    names: BTreeMap<u32, String>,
    links: BTreeMap<NodeId, IceoryxLink>,
    procs: Vec<Proc>,
    vehicles: BTreeMap<u32, Gathered>,
    truth: BTreeMap<(u32, i64), TruthReport>,
    true_ids: BTreeMap<(u32, i64), Vec<FeatureId>>,
    link_streams: BTreeMap<(NodeId, NodeId), LinkStream>,
    events: Vec<EventRecord>,
    world_t: f64,
    world_finished: bool,
    /// Per world (one per host in a multi-host run, by host index): its time and whether it
    /// reached the end. `world_t` is the earliest, `world_finished` all of them.
    worlds: BTreeMap<usize, (f64, bool)>,
    /// Names of the hosts whose worlds make the run (`["local"]` for a single-host run).
    world_hosts: Vec<String>,
    /// The host whose reports are being handled.
    current_host: usize,
    /// `--monitor`: the control plane to the host launchers.
    remote: Option<Remote>,
    /// How the host launchers' processes ended (`--monitor`).
    remote_procs: Vec<ProcessRecord>,
    hub_rejected: u64,
    /// What the hub's zenoh access control refused (its last report).
    hub_access_refused: BTreeMap<String, u64>,
    /// What the zenoh router's access control refused (its last report; client mode).
    router_access_refused: BTreeMap<String, u64>,
    hub_rejections: BTreeMap<String, u64>,
    hub_alive: bool,
    /// Vehicles the world holds its streams for (a scheduled restart).
    restart_requests: BTreeMap<u32, f64>,
    failure: Option<String>,
    /// The last `Report::Status` of each process (by name): when, its time, what it said,
    /// whether it is a bounded wait.
    statuses: BTreeMap<String, (Instant, f64, String, bool)>,
}

/// Resolves a scenario for a run: overrides, free ports for `net` links without `listen`,
/// absolute replay paths. Returns it and the team's zenoh password (removed from it: it reaches
/// the processes through their environment, never a file).
pub fn resolve(mut s: Scenario, opts: &LaunchOptions) -> Result<(Scenario, Option<String>)> {
    if let Some(d) = opts.duration {
        s.run.duration_s = d;
    }
    if let Some(b) = opts.baseline {
        s.run.baseline = b;
    }
    let proto = crate::deploy::endpoint_protocol(&s);
    // Ports the file names (`listen = "tcp/127.0.0.1:7447"`) are not handed out again.
    let named: Vec<u16> = s
        .links
        .iter()
        .filter_map(|l| l.listen.as_deref()?.rsplit_once(':')?.1.parse().ok())
        .collect();
    let needs_port =
        |l: &crate::scenario::LinkSpec| l.transport == TransportKind::Net && l.listen.is_none();
    let unnamed = s.links.iter().filter(|l| needs_port(l)).count();
    let ports = canopy_transport::net::free_loopback_ports(unnamed, &named)
        .context("finding free loopback ports for the net links")?;
    for (l, port) in s.links.iter_mut().filter(|l| needs_port(l)).zip(ports) {
        l.listen = Some(format!("{proto}/127.0.0.1:{port}"));
    }
    // TLS files: absolute, so the processes find them from the run directory.
    if let Some(t) = s.zenoh.tls.as_mut() {
        let cwd = std::env::current_dir().context("the current directory")?;
        t.resolve(&cwd);
    }
    for v in &mut s.vehicles {
        if let Some(r) = v.replay.as_mut() {
            for p in r.paths_mut() {
                *p = std::fs::canonicalize(&*p)
                    .with_context(|| format!("replay log {}", p.display()))?;
            }
        }
    }
    let secret = s.secrets.zenoh_password.take();
    s.validate().context("the resolved scenario")?;
    Ok((s, secret))
}

impl Monitor {
    fn spawn(
        &mut self,
        name: &str,
        vehicle: Option<u32>,
        incarnation: u32,
        secret: &Option<String>,
    ) -> Result<()> {
        let p = Spawner {
            out: &self.out,
            prefix: &self.prefix,
            exe: &self.exe,
            netns: &self.netns,
            extra: &[],
        }
        .spawn(name, vehicle, incarnation, secret)?;
        self.procs.push(p);
        Ok(())
    }

    fn team_time(&self) -> f64 {
        let live: Vec<f64> = self
            .vehicles
            .values()
            .filter(|v| v.alive)
            .map(|v| v.last_t)
            .collect();
        if live.is_empty() {
            self.world_t
        } else {
            live.into_iter().fold(f64::INFINITY, f64::min)
        }
    }

    /// The world whose reports are being handled: `world`, or `world@HOST` in a multi-host run.
    fn world_name(&self) -> String {
        if self.remote.is_some() {
            let host = self.world_hosts.get(self.current_host);
            format!("world@{}", host.map_or("?", String::as_str))
        } else {
            "world".into()
        }
    }

    /// The current host's world reached `t` (and the end, if `finished`).
    fn world_at(&mut self, t: f64, finished: bool) {
        let w = self.worlds.entry(self.current_host).or_insert((0.0, false));
        w.0 = w.0.max(t);
        w.1 |= finished;
        let n = self.world_hosts.len().max(1);
        self.world_t = (0..n)
            .map(|h| self.worlds.get(&h).map_or(0.0, |w| w.0))
            .fold(f64::INFINITY, f64::min);
        self.world_finished = (0..n).all(|h| self.worlds.get(&h).is_some_and(|w| w.1));
    }

    fn on_report(&mut self, from: NodeId, r: Report) {
        if let Report::Status {
            t,
            state,
            bounded_wait,
        } = &r
        {
            let name = if from == WORLD_ID {
                self.world_name()
            } else if let Some(v) = self.vehicles.get_mut(&from) {
                v.last_t = v.last_t.max(*t);
                v.name.clone()
            } else {
                self.names
                    .get(&from)
                    .cloned()
                    .unwrap_or_else(|| from.to_string())
            };
            if from == WORLD_ID {
                self.world_at(*t, false);
            }
            self.statuses
                .insert(name, (Instant::now(), *t, state.clone(), *bounded_wait));
            return;
        }
        if from == WORLD_ID {
            match r {
                Report::Truth {
                    t, samples, frames, ..
                } => {
                    self.world_at(t, false);
                    for s in samples {
                        self.truth.insert((s.vehicle, ms(s.t)), s);
                    }
                    for f in frames {
                        self.true_ids.insert((f.vehicle, ms(f.t)), f.ids);
                    }
                }
                Report::Initialized {
                    vehicle,
                    incarnation,
                    t,
                } => {
                    if let Some(v) = self.vehicles.get_mut(&vehicle) {
                        v.initialisations += 1;
                        v.incarnation = incarnation;
                        v.last_t = t;
                    }
                }
                Report::Finished { t } => {
                    self.world_at(t, true);
                }
                Report::Waiting { vehicle, t, .. } => {
                    self.world_at(t, false);
                    self.restart_requests.insert(vehicle, t);
                }
                Report::Failed { reason } => {
                    let who = self.world_name();
                    self.failure.get_or_insert(format!("{who}: {reason}"));
                }
                _ => {}
            }
            return;
        }
        if from == self.s.fusion.hub_id && self.s.fusion.mode == FusionMode::Central {
            if let Report::Hub {
                t,
                links,
                rejected,
                access_refused,
                rejections,
            } = r
            {
                self.hub_rejected = rejected;
                self.hub_access_refused = access_refused;
                self.hub_rejections = rejections;
                for l in links {
                    self.link_streams
                        .entry((from, l.peer))
                        .or_default()
                        .push(t, 0, l);
                }
            }
            return;
        }
        let Some(v) = self.vehicles.get_mut(&from) else {
            return;
        };
        match r {
            Report::Estimate(EstimateReport {
                t,
                state,
                covariance,
                counters,
                links,
                associations,
                frame_owner,
            }) => {
                let (state, covariance) =
                    in_launch_frame(&self.launch_from_own, frame_owner, state, covariance);
                v.last_t = v.last_t.max(t);
                // A final report at the time of the last one (the vehicle's end of stream)
                // replaces it: one estimate per time.
                if v.estimates.last().is_some_and(|e| e.0 == t) {
                    v.estimates.pop();
                }
                v.estimates.push((t, state, covariance));
                v.counters.insert(v.incarnation, counters);
                v.associations.extend(associations);
                for l in links {
                    self.link_streams
                        .entry((from, l.peer))
                        .or_default()
                        .push(t, v.incarnation, l);
                }
            }
            Report::Map(mut m) => {
                if let Some(frame) = m.frame_owner.and_then(|o| self.launch_from_own.get(&o)) {
                    let r = frame.rotation();
                    for f in &mut m.features {
                        let mean = frame.apply(&Vector3::from(f.mean));
                        let c = r * f.covariance() * r.transpose();
                        f.mean = [mean.x, mean.y, mean.z];
                        f.cov = canopy_fusion::ddf::upper_triangle(&c);
                    }
                }
                v.last_t = v.last_t.max(m.t);
                v.maps.push((m.t, m.features.clone()));
                v.last_map = Some((m.t, m.features));
                v.merges = m.merges;
            }
            Report::Finished { t } => {
                v.last_t = v.last_t.max(t);
                v.finished = true;
            }
            Report::Failed { reason } => {
                eprintln!("{}: {reason}", v.name);
            }
            _ => {}
        }
    }

    fn poll_links(&mut self) -> bool {
        let mut any = false;
        let ids: Vec<NodeId> = self.links.keys().copied().collect();
        for id in ids {
            let mut got = Vec::new();
            {
                let link = self.links.get_mut(&id).expect("exists");
                while link.poll_event().is_some() {}
                for _ in 0..256 {
                    match link.try_recv() {
                        Ok(Some(m)) => {
                            if let Some(r) = decode_body::<Report>(&m) {
                                got.push(r);
                            }
                        }
                        _ => break,
                    }
                }
            }
            any |= !got.is_empty();
            for r in got {
                self.on_report(id, r);
            }
        }
        any |= self.poll_remote();
        any
    }

    fn send_control(&mut self, to: NodeId) {
        if let Some(l) = self.links.get_mut(&to) {
            let _ = send_body(l, MessageKind::CONTROL, 0, 0.0, &Control::Shutdown);
        }
    }

    fn kill(&mut self, name: &str, signal: nix::sys::signal::Signal, planned: bool) {
        let t = self.team_time();
        for p in self
            .procs
            .iter_mut()
            .filter(|p| p.name == name && p.status.is_none())
        {
            p.planned_kill |= planned;
            p.ended_at = t;
            let _ = nix::sys::signal::kill(nix::unistd::Pid::from_raw(p.child.id() as i32), signal);
        }
    }

    /// Reaps exited children; reports unexpected exits.
    fn reap(&mut self) {
        let t = self.team_time();
        for p in &mut self.procs {
            if p.status.is_some() {
                continue;
            }
            if let Ok(Some(st)) = p.child.try_wait() {
                p.status = Some(st);
                if p.ended_at == 0.0 {
                    p.ended_at = t;
                }
                let expected = p.planned_kill
                    || (st.success() && (self.world_finished || self.failure.is_some()));
                if !expected {
                    eprintln!(
                        "process {} (incarnation {}, pid {}) ended unexpectedly: {}; see {}",
                        p.name,
                        p.incarnation,
                        p.child.id(),
                        describe(&st),
                        p.log.display()
                    );
                    self.events.push(EventRecord {
                        t,
                        until: None,
                        kind: "process-exit".into(),
                        subject: format!("{} ({})", p.name, describe(&st)),
                    });
                }
                if let Some(id) = p.vehicle
                    && let Some(v) = self.vehicles.get_mut(&id)
                    && v.incarnation == p.incarnation
                {
                    v.alive = false;
                }
                if p.name == "hub" {
                    self.hub_alive = false;
                }
                if p.name == "world" && !st.success() {
                    self.failure
                        .get_or_insert(format!("the world process ended: {}", describe(&st)));
                }
            }
        }
    }

    fn running(&self) -> usize {
        self.procs.iter().filter(|p| p.status.is_none()).count()
    }

    /// Shuts everything down: Shutdown, then SIGTERM, then SIGKILL.
    fn shutdown(&mut self) {
        if self.remote.is_some() {
            self.shutdown_remote();
            return;
        }
        let ids: Vec<NodeId> = self.links.keys().copied().collect();
        // Vehicles and hub first (they send final reports), then the world.
        for id in ids.iter().filter(|&&i| i != WORLD_ID) {
            self.send_control(*id);
        }
        self.send_control(WORLD_ID);
        // Processes are given STOP_GRACE to stop, and STOP_GRACE more every time one of them
        // stops or a final report arrives: a machine that is only slow (66 processes ending at
        // once under a load of 40 took longer than a fixed 10 s, and the world was killed)
        // keeps making that progress, while a hung process makes none and is signalled.
        // The first window also grows with the number of processes: the world closes one
        // iceoryx2 node per vehicle link on its way out and sends nothing meanwhile.
        let mut left = self.running();
        let mut deadline = Instant::now() + STOP_GRACE + STOP_GRACE_PER_PROCESS * left as u32;
        while left > 0 && Instant::now() < deadline {
            let reported = self.poll_links();
            self.reap();
            let now_running = self.running();
            if now_running < left || reported {
                deadline = deadline.max(Instant::now() + STOP_GRACE);
                left = now_running;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        for sig in [
            nix::sys::signal::Signal::SIGTERM,
            nix::sys::signal::Signal::SIGKILL,
        ] {
            if self.running() == 0 {
                break;
            }
            let names: Vec<String> = self
                .procs
                .iter()
                .filter(|p| p.status.is_none())
                .map(|p| p.name.clone())
                .collect();
            for n in names {
                eprintln!("{n} did not stop; sending {sig}");
                self.kill(&n, sig, true);
            }
            let deadline = Instant::now() + Duration::from_secs(3);
            while self.running() > 0 && Instant::now() < deadline {
                self.poll_links();
                self.reap();
                std::thread::sleep(Duration::from_millis(5));
            }
        }
        // Anything still there is waited for (SIGKILL cannot be ignored).
        for p in &mut self.procs {
            if p.status.is_none() {
                p.status = p.child.wait().ok();
            }
        }
        self.poll_links();
    }
}

/// Refuses what a multi-host run (`--host`, `--monitor`) does not support.
pub(crate) fn check_multi_host(s: &Scenario, flag: &str) -> Result<()> {
    if s.hosts.is_empty() {
        anyhow::bail!(
            "{flag} needs [[host]] tables in the scenario (which host runs which vehicles; \
             see docs/arch/deploy.md)"
        );
    }
    Ok(())
}

/// The zenoh session of the control plane of a multi-host run (host launchers ↔ monitor):
/// under `deploy::control_prefix`, the monitor node [`MONITOR_ID`] and host `i` as node `i`.
/// Peer mode: the monitor listens, every host launcher connects to it.
///
/// With the team's password (`[secrets].zenoh_password`) each session authenticates as its own
/// user (`monitor`, `host-NAME`), and the monitor's session, which only listens, accepts every
/// host's user and enforces access control: host `i` may only use its own side of the control
/// link `i` ↔ monitor (`canopy_transport::access`). A host launcher only connects (zenoh's
/// user/password check is one-way: it has no user name for the monitor to enforce rules by);
/// what reaches it comes from the monitor's session, whose egress rules send it only its own
/// control link.
///
/// Client mode: every session is a client of the router(s) in `[zenoh].connect`, which enforces
/// the access control (`canopy router`); opening waits up to `wait` for a router to answer.
pub(crate) fn control_session(
    s: &Scenario,
    local: NodeId,
    secret: &Option<String>,
    wait: Duration,
) -> Result<canopy_transport::net::ZenohTransport> {
    use crate::deploy::ZenohModeConfig;
    use canopy_transport::access::{AclLink, ZenohAccess};
    use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohMode, ZenohTransport};
    let monitor = s.zenoh.monitor.clone();
    let is_monitor = local == MONITOR_ID;
    let (mode, listen, connect) = match (s.zenoh.mode, is_monitor) {
        (ZenohModeConfig::Client, _) => (ZenohMode::Client, vec![], s.zenoh.connect.clone()),
        (ZenohModeConfig::Peer, true) => (ZenohMode::Peer, monitor.into_iter().collect(), vec![]),
        (ZenohModeConfig::Peer, false) => (ZenohMode::Peer, vec![], monitor.into_iter().collect()),
    };
    let prefix = crate::deploy::control_prefix(s);
    let mut cfg = ZenohConfig::new(prefix.clone(), listen, connect);
    cfg.mode = mode;
    cfg.multicast_scouting = s.zenoh.multicast_scouting;
    cfg.connect_timeout = Some(wait);
    let user = if is_monitor {
        crate::deploy::MONITOR_USER.to_string()
    } else {
        s.hosts
            .get(local as usize)
            .map(crate::deploy::host_user)
            .context("the control plane's node is no [[host]]")?
    };
    cfg.tls = s.zenoh.tls.as_ref().map(|t| t.for_user(&user));
    if let Some(p) = secret {
        let listens = !cfg.listen.is_empty();
        let hosts: Vec<(NodeId, String)> = s
            .hosts
            .iter()
            .enumerate()
            .map(|(i, h)| (i as NodeId, crate::deploy::host_user(h)))
            .collect();
        cfg.auth = Some(ZenohAuth {
            user,
            password: p.clone(),
            accept: if listens {
                hosts.iter().map(|(_, u)| (u.clone(), p.clone())).collect()
            } else {
                Vec::new()
            },
        });
        if listens {
            let links: Vec<AclLink> = hosts
                .into_iter()
                .map(|(from, user)| AclLink {
                    user,
                    from,
                    to: MONITOR_ID,
                })
                .collect();
            cfg.access = Some(ZenohAccess::for_links(&prefix, &links));
        }
    }
    ZenohTransport::open(local, cfg).with_context(|| {
        if mode == ZenohMode::Client {
            format!(
                "opening the control plane's zenoh session: no zenoh router answered at {} \
                 within {:.0} s (start `canopy router SCENARIO` on the router's machine first)",
                s.zenoh.connect.join(", "),
                wait.as_secs_f64()
            )
        } else {
            "opening the control plane's zenoh session".to_string()
        }
    })
}

/// One host launcher (or, in client mode, the zenoh router) as the monitor sees it.
struct RemoteHost {
    name: String,
    /// It is the zenoh router (`canopy router`), not a host launcher: it runs no process and
    /// reports what its access control refused ([`HostMsg::Refusals`]).
    router: bool,
    link: canopy_transport::net::ZenohLink,
    /// Its `Hello` was accepted.
    welcomed: bool,
    /// Its connection was printed.
    announced: bool,
    /// It said it is done (all its processes ended).
    done: bool,
    /// Its session went away before it was done and did not come back within [`LOST_GRACE`].
    lost: bool,
    /// Since when its session is away.
    down_since: Option<Instant>,
}

/// How long the monitor and a host launcher wait for each other's zenoh session to come back
/// before giving up: a network cut that heals within it costs a pause of the team (every
/// world is held by the team's pace meanwhile), not the run. zenoh declares a silent peer lost
/// after its 3 s lease and reconnects within ~1–5 s of the network's return
/// (docs/arch/system.md).
pub(crate) const LOST_GRACE: Duration = Duration::from_secs(20);

/// The monitor's side of the control plane of a multi-host run.
struct Remote {
    endpoint: String,
    hosts: Vec<RemoteHost>,
    since: Instant,
    wait: Duration,
    _session: canopy_transport::net::ZenohTransport,
}

impl Remote {
    fn open(s: &Scenario, secret: &Option<String>, wait: Duration) -> Result<Self> {
        let session = control_session(s, MONITOR_ID, secret, wait)?;
        let hosts = s
            .hosts
            .iter()
            .enumerate()
            .map(|(i, h)| {
                Ok(RemoteHost {
                    name: h.name.clone(),
                    router: false,
                    link: session
                        .link(i as NodeId, super::CONTROL_MAX_BODY)
                        .with_context(|| format!("opening the control link to host {}", h.name))?,
                    welcomed: false,
                    announced: false,
                    done: false,
                    lost: false,
                    down_since: None,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let mut hosts = hosts;
        if crate::deploy::client_mode(s) {
            // The router reports its refusals on a control link of its own.
            hosts.push(RemoteHost {
                name: crate::deploy::ROUTER_USER.to_string(),
                router: true,
                link: session
                    .link(super::protocol::ROUTER_ID, super::CONTROL_MAX_BODY)
                    .context("opening the control link to the zenoh router")?,
                welcomed: false,
                announced: false,
                done: false,
                lost: false,
                down_since: None,
            });
        }
        Ok(Self {
            endpoint: s
                .zenoh
                .monitor
                .clone()
                .unwrap_or_else(|| s.zenoh.connect.join(", ")),
            hosts,
            since: Instant::now(),
            wait,
            _session: session,
        })
    }

    /// Why the run cannot start: hosts that did not connect in time.
    fn startup_failure(&self) -> Option<String> {
        let missing: Vec<&str> = self
            .hosts
            .iter()
            .filter(|h| !h.welcomed)
            .map(|h| h.name.as_str())
            .collect();
        (!missing.is_empty() && self.since.elapsed() > self.wait).then(|| {
            format!(
                "host(s) [{}] did not connect to the monitor at {} within {:.0} s (is `canopy \
                 run SCENARIO --host NAME` running there — in client mode also `canopy router \
                 SCENARIO` on the router's machine — and can it reach this address?)",
                missing.join(", "),
                self.endpoint,
                self.wait.as_secs_f64()
            )
        })
    }
}

impl Monitor {
    /// Gathers what the host launchers sent (`--monitor`).
    fn poll_remote(&mut self) -> bool {
        let Some(mut remote) = self.remote.take() else {
            return false;
        };
        let mut any = false;
        for h in 0..remote.hosts.len() {
            let mut got = Vec::new();
            {
                let rh = &mut remote.hosts[h];
                while rh.link.poll_event().is_some() {}
                for _ in 0..1024 {
                    match rh.link.try_recv() {
                        Ok(Some(m)) => {
                            if let Some(x) = decode_body::<HostMsg>(&m) {
                                got.push(x);
                            }
                        }
                        _ => break,
                    }
                }
            }
            any |= !got.is_empty();
            for msg in got {
                match msg {
                    HostMsg::Hello {
                        host,
                        duration_s,
                        seed,
                    } => {
                        let rh = &mut remote.hosts[h];
                        let (d, sd) = (self.s.run.duration_s, self.s.world.seed);
                        if host != rh.name {
                            self.failure.get_or_insert(format!(
                                "the launcher of host {} says it is `{host}`",
                                rh.name
                            ));
                        } else if (duration_s - d).abs() > 1e-9 || seed != sd {
                            self.failure.get_or_insert(format!(
                                "host {host} runs duration {duration_s} s, seed {seed}; the \
                                 monitor runs duration {d} s, seed {sd} (give every host and \
                                 the monitor the same scenario and --duration)"
                            ));
                        } else {
                            rh.welcomed = true;
                            let _ = send_body(
                                &mut rh.link,
                                MessageKind::CONTROL,
                                0,
                                0.0,
                                &Control::Welcome,
                            );
                        }
                    }
                    HostMsg::Report { from, report } => {
                        self.current_host = h;
                        self.on_report(from, report);
                    }
                    HostMsg::Process(p) => {
                        let expected = p.killed_by_monitor
                            || (p.clean_exit() && (self.world_finished || self.failure.is_some()));
                        if !expected {
                            eprintln!(
                                "host {}: process {} (pid {}) ended unexpectedly (code {:?}, \
                                 signal {:?}); see {} on that host",
                                remote.hosts[h].name,
                                p.name,
                                p.pid,
                                p.exit_code,
                                p.signal,
                                p.log.display()
                            );
                            if let Some(v) = self.vehicles.values_mut().find(|v| v.name == p.name) {
                                v.alive = false;
                            }
                        }
                        self.remote_procs.push(p);
                    }
                    HostMsg::Refusals(refused) => {
                        if remote.hosts[h].router {
                            self.router_access_refused = refused;
                        }
                    }
                    HostMsg::Done { failure } => {
                        remote.hosts[h].done = true;
                        if let Some(f) = failure {
                            let name = &remote.hosts[h].name;
                            self.failure.get_or_insert(format!("host {name}: {f}"));
                        }
                    }
                }
            }
            let rh = &mut remote.hosts[h];
            if rh.welcomed && !rh.done && rh.link.peer_state() != PeerState::Up {
                let since = *rh.down_since.get_or_insert_with(|| {
                    eprintln!("host {} is out of reach", rh.name);
                    Instant::now()
                });
                rh.lost |= since.elapsed() > LOST_GRACE;
            } else {
                rh.down_since = None;
            }
        }
        self.remote = Some(remote);
        any
    }

    /// Sends the team's pace to every host (`Control::Pace`): the slowest live vehicle of the
    /// whole team plus `[run].max_lead_s`, once every vehicle has been initialised (before
    /// that, nothing: a host started early waits for the others). Sent when it moves by a
    /// batch, and at least twice a wall second (a host that connects late, a lost message).
    ///
    /// `hold`: the time of a scheduled restart whose vehicle is down. No host steps past it
    /// until the vehicle is back, as the single-host world holds every stream there: the
    /// restart happens at exactly that time for the whole team (what the reference assumes),
    /// however far the vehicles of other hosts could otherwise run while it is down.
    fn send_pace(&mut self, last: &mut (f64, Option<Instant>), hold: Option<f64>) {
        if self.vehicles.values().any(|v| v.initialisations == 0) {
            return;
        }
        let until = (self.team_time() + self.s.run.max_lead_s)
            .min(self.s.run.duration_s)
            .min(hold.unwrap_or(f64::INFINITY));
        let moved = until >= last.0 + super::world::BATCH_S;
        let stale = last
            .1
            .is_none_or(|t| t.elapsed() > Duration::from_millis(500));
        if !(moved || stale) {
            return;
        }
        if let Some(r) = self.remote.as_mut() {
            for h in r.hosts.iter_mut().filter(|h| !h.router) {
                let _ = send_body(
                    &mut h.link,
                    MessageKind::CONTROL,
                    0,
                    until,
                    &Control::Pace { until },
                );
            }
        }
        *last = (until, Some(Instant::now()));
    }

    /// Sends a scheduled event's order (kill, restart) to the host launcher running `node`
    /// (`--monitor`). The control link is reliable (zenoh over TCP); an order the host cannot
    /// receive (its session away) fails the run with the reason, as a lost host does.
    fn order_host(&mut self, node: u32, order: Control) {
        let host = crate::deploy::host_of(&self.s, node).map(|(i, _)| i);
        let Some(r) = self.remote.as_mut() else {
            return;
        };
        let Some(h) = host.and_then(|i| r.hosts.get_mut(i)) else {
            self.failure.get_or_insert(format!(
                "node {node} runs on no host: cannot send {order:?}"
            ));
            return;
        };
        if h.link.peer_state() != PeerState::Up {
            self.failure.get_or_insert(format!(
                "host {} is out of reach: cannot send it {order:?}",
                h.name
            ));
            return;
        }
        if let Err(e) = send_body(&mut h.link, MessageKind::CONTROL, 0, 0.0, &order) {
            self.failure
                .get_or_insert(format!("sending {order:?} to host {}: {e:#}", h.name));
        }
    }

    /// Asks every host launcher to end its share and waits for them to say they are done; then
    /// (client mode) the router, for its final refusals — last, because everything the hosts
    /// send goes through it.
    fn shutdown_remote(&mut self) {
        self.shutdown_remote_part(false, REMOTE_SHUTDOWN);
        self.shutdown_remote_part(true, ROUTER_SHUTDOWN);
    }

    /// [`Monitor::shutdown_remote`] of the host launchers (`router` false) or the router.
    fn shutdown_remote_part(&mut self, router: bool, wait: Duration) {
        let deadline = Instant::now() + wait;
        let mut last_sent: Option<Instant> = None;
        loop {
            if last_sent.is_none_or(|t| t.elapsed() > Duration::from_secs(1)) {
                if let Some(r) = self.remote.as_mut() {
                    for h in r.hosts.iter_mut().filter(|h| !h.done && h.router == router) {
                        let _ = send_body(
                            &mut h.link,
                            MessageKind::CONTROL,
                            0,
                            0.0,
                            &Control::Shutdown,
                        );
                    }
                }
                last_sent = Some(Instant::now());
            }
            self.poll_links();
            let Some(r) = self.remote.as_ref() else {
                return;
            };
            let open: Vec<&str> = r
                .hosts
                .iter()
                .filter(|h| h.router == router)
                .filter(|h| !h.done && !h.lost && h.link.peer_state() == PeerState::Up)
                .map(|h| h.name.as_str())
                .collect();
            if open.is_empty() {
                return;
            }
            if Instant::now() > deadline {
                eprintln!(
                    "{} [{}] did not confirm the end of the run within {} s",
                    if router { "the router" } else { "host(s)" },
                    open.join(", "),
                    wait.as_secs()
                );
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }
}

/// How long the processes of a run get to stop after the Shutdown control message, counted
/// afresh whenever one of them stops ([`Monitor::shutdown`]); then SIGTERM, then SIGKILL.
const STOP_GRACE: Duration = Duration::from_secs(10);
/// Added to the first [`STOP_GRACE`] window per running process (66 processes: 43 s).
const STOP_GRACE_PER_PROCESS: Duration = Duration::from_millis(500);

/// How long the monitor waits for the host launchers to end their shares: their own shutdown
/// (10 s for the processes' final reports, then 3 s per signal) and some slack.
const REMOTE_SHUTDOWN: Duration = Duration::from_secs(30);
/// How long the monitor waits for the router's final refusals (one message on a live link).
const ROUTER_SHUTDOWN: Duration = Duration::from_secs(5);

/// No progress for this long: the monitor says who holds the run up and why.
const STALL_WARN: Duration = Duration::from_secs(5);
/// No progress for this long: the run fails with that diagnosis.
const STALL_FAIL: Duration = Duration::from_secs(60);

/// The monitor's stall watchdog: progress is any process's simulation time moving (every
/// process reports its time about once a wall second, `Report::Status`); a wait with its own
/// deadline (start-up, a scheduled restart) is not a stall.
struct Watchdog {
    progress_t: f64,
    since: Instant,
    warned: bool,
}

enum WatchdogVerdict {
    Fine,
    Warn(String),
    Fail(String),
}

impl Watchdog {
    fn new() -> Self {
        Self {
            progress_t: f64::NEG_INFINITY,
            since: Instant::now(),
            warned: false,
        }
    }

    fn check(&mut self, m: &Monitor) -> WatchdogVerdict {
        let t = m
            .statuses
            .values()
            .map(|s| s.1)
            .fold(m.world_t.max(m.team_time()), f64::max);
        let bounded = m
            .statuses
            .values()
            .any(|s| s.3 && s.0.elapsed() < STALL_WARN);
        if t > self.progress_t || bounded || m.world_finished {
            self.progress_t = self.progress_t.max(t);
            self.since = Instant::now();
            self.warned = false;
            return WatchdogVerdict::Fine;
        }
        let idle = self.since.elapsed();
        if idle > STALL_FAIL {
            return WatchdogVerdict::Fail(format!(
                "no progress for {} s: {}",
                STALL_FAIL.as_secs(),
                stall_diagnosis(m, self.progress_t)
            ));
        }
        if idle > STALL_WARN && !self.warned {
            self.warned = true;
            return WatchdogVerdict::Warn(format!(
                "no progress for {} s: {}",
                STALL_WARN.as_secs(),
                stall_diagnosis(m, self.progress_t)
            ));
        }
        WatchdogVerdict::Fine
    }
}

/// Who holds a stalled run up: every process's last status and its age.
fn stall_diagnosis(m: &Monitor, t: f64) -> String {
    let mut names: Vec<String> = if m.remote.is_some() {
        m.world_hosts.iter().map(|h| format!("world@{h}")).collect()
    } else {
        vec!["world".into()]
    };
    names.extend(
        m.vehicles
            .values()
            .filter(|v| v.alive)
            .map(|v| v.name.clone()),
    );
    let parts: Vec<String> = names
        .iter()
        .map(|n| match m.statuses.get(n) {
            Some((at, _, state, _)) => {
                format!("{n}: {state} ({:.1} s ago)", at.elapsed().as_secs_f64())
            }
            None => format!("{n}: no status received (busy, hung, or not started)"),
        })
        .collect();
    format!("stuck at t = {t}; {}", parts.join("; "))
}

pub(crate) fn describe(st: &ExitStatus) -> String {
    use std::os::unix::process::ExitStatusExt;
    match (st.code(), st.signal()) {
        (Some(c), _) => format!("exit status {c}"),
        (None, Some(s)) => {
            let name = nix::sys::signal::Signal::try_from(s)
                .map_or_else(|_| s.to_string(), |x| x.to_string());
            format!("killed by signal {name}")
        }
        _ => "unknown status".into(),
    }
}

/// Runs a scenario as real processes and gathers the run. The scenario must be valid.
pub fn launch(mut s: Scenario, opts: &LaunchOptions) -> Result<LaunchOutcome> {
    let started = Instant::now();
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("creating {}", opts.out.display()))?;
    if opts.monitor_only.is_some() {
        check_multi_host(&s, "--monitor")?;
        if !crate::deploy::client_mode(&s) {
            crate::deploy::resolve_endpoints(&mut s)
                .context("deriving the net links' endpoints")?;
        }
    }
    let (s, secret) = resolve(s, opts)?;
    // Every check `canopy check` makes, here in the launcher: a bad input fails the run before
    // any process starts, with the file, line and reason.
    crate::preflight::preflight(&s).context("checking the scenario's inputs")?;
    std::fs::write(opts.out.join("scenario.toml"), s.to_toml_string())
        .with_context(|| format!("writing {}", opts.out.join("scenario.toml").display()))?;
    let world = World::new(&s.world, s.world.seed).context("building the world")?;
    let exe = match &opts.exe {
        Some(e) => e.clone(),
        None => std::env::current_exe().context("locating the canopy executable")?,
    };
    let prefix = unique_run_prefix();
    let names = node_names(&s);
    let duration = s.run.duration_s;

    let launch_from_own = if world.own_frames() {
        let (_, sims) = crate::world::build_parts(&s).context("building the vehicles' starts")?;
        s.vehicles
            .iter()
            .zip(sims)
            .filter_map(|(cfg, v)| Some((cfg.id, v?.launch_from_own())))
            .collect()
    } else {
        BTreeMap::new()
    };
    let mut m = Monitor {
        s: s.clone(),
        launch_from_own,
        out: opts.out.clone(),
        prefix: prefix.clone(),
        exe,
        netns: opts.netns.clone(),
        names: names.clone(),
        links: BTreeMap::new(),
        procs: Vec::new(),
        vehicles: s
            .vehicles
            .iter()
            .map(|v| {
                (
                    v.id,
                    Gathered {
                        name: v.display_name(),
                        replay: v.replay.is_some(),
                        alive: true,
                        ..Default::default()
                    },
                )
            })
            .collect(),
        truth: BTreeMap::new(),
        true_ids: BTreeMap::new(),
        link_streams: BTreeMap::new(),
        events: Vec::new(),
        world_t: 0.0,
        world_finished: false,
        worlds: BTreeMap::new(),
        world_hosts: if opts.monitor_only.is_some() {
            s.hosts.iter().map(|h| h.name.clone()).collect()
        } else {
            vec!["local".into()]
        },
        current_host: 0,
        remote: None,
        remote_procs: Vec::new(),
        hub_rejected: 0,
        hub_access_refused: BTreeMap::new(),
        router_access_refused: BTreeMap::new(),
        hub_rejections: BTreeMap::new(),
        hub_alive: s.fusion.mode == FusionMode::Central,
        restart_requests: Default::default(),
        failure: None,
        statuses: BTreeMap::new(),
    };
    if let Some(wait) = opts.monitor_only {
        m.remote = Some(Remote::open(&s, &secret, wait)?);
    } else {
        // Links first, so the children find the monitor.
        m.links
            .insert(WORLD_ID, control_link(&prefix, MONITOR_ID, WORLD_ID, 256)?);
        for v in &s.vehicles {
            m.links
                .insert(v.id, control_link(&prefix, MONITOR_ID, v.id, 256)?);
        }
    }
    if s.fusion.mode == FusionMode::Central && opts.monitor_only.is_none() {
        m.links.insert(
            s.fusion.hub_id,
            control_link(&prefix, MONITOR_ID, s.fusion.hub_id, 256)?,
        );
    }

    // The centralized reference, in a thread.
    let base_stop = Arc::new(AtomicBool::new(false));
    let base_progress = Arc::new(AtomicU64::new(0f64.to_bits()));
    let baseline = s.run.baseline.then(|| {
        let (sc, st, pr) = (s.clone(), base_stop.clone(), base_progress.clone());
        std::thread::Builder::new()
            .name("baseline".into())
            .spawn(move || run_reference(&sc, duration, Some(&st), Some(&pr)))
    });
    let baseline = baseline
        .transpose()
        .context("starting the reference thread")?;

    let spawn_all = |m: &mut Monitor| -> Result<()> {
        m.spawn("world", None, 0, &secret)?;
        if s.fusion.mode == FusionMode::Central {
            m.spawn("hub", None, 0, &secret)?;
        }
        for v in &s.vehicles {
            m.spawn(&v.display_name(), Some(v.id), 0, &secret)?;
        }
        Ok(())
    };
    let spawned = if opts.monitor_only.is_some() {
        Ok(())
    } else {
        spawn_all(&mut m)
    };
    if let Err(e) = &spawned {
        m.failure = Some(format!("{e:#}"));
    }

    // Scheduled events: (index, stage) with stage 0 = kill, 1 = restart.
    let mut pending: Vec<(usize, u8)> = s
        .events
        .iter()
        .enumerate()
        .flat_map(|(i, e)| {
            let mut v = vec![(i, 0u8)];
            if e.restart_after_s.is_some() {
                v.push((i, 1));
            }
            v
        })
        .collect();
    let pb = if opts.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        crate::cli::progress_bar(duration, false)
    };
    let plain_progress = !opts.quiet && !std::io::stderr().is_terminal();
    // Event lines: above the progress bar, or plain lines when stderr is not a terminal.
    let say = |pb: &indicatif::ProgressBar, line: String| {
        if plain_progress {
            eprintln!("{line}");
        } else if !opts.quiet {
            pb.println(line);
        }
    };
    let mut next_plain = 10.0;
    let mut interrupted = false;
    let mut watchdog = Watchdog::new();
    let mut last_pace: (f64, Option<Instant>) = (f64::NEG_INFINITY, None);

    while m.failure.is_none() {
        if opts.stop.load(Ordering::Relaxed) {
            interrupted = true;
            break;
        }
        let busy = m.poll_links();
        m.reap();
        if let Some(r) = &m.remote {
            if let Some(reason) = r.startup_failure() {
                m.failure = Some(reason);
                break;
            }
            if let Some(h) = r.hosts.iter().find(|h| h.lost) {
                m.failure.get_or_insert(format!(
                    "lost {}: its zenoh session to the monitor went away before the run \
                     ended and did not come back within {} s",
                    if h.router {
                        "the zenoh router".to_string()
                    } else {
                        format!("the host launcher `{}`", h.name)
                    },
                    LOST_GRACE.as_secs()
                ));
                break;
            }
            for h in r.hosts.iter().filter(|h| h.welcomed && !h.announced) {
                say(&pb, format!("host {} connected", h.name));
            }
            let all = r.hosts.iter().all(|h| h.welcomed);
            if let Some(r) = m.remote.as_mut() {
                for h in r.hosts.iter_mut() {
                    h.announced |= h.welcomed;
                }
            }
            if !all {
                // Waiting for the hosts has its own deadline: not a stall.
                watchdog = Watchdog::new();
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
            // A restart due while its vehicle is down holds the team at its time.
            let hold = pending
                .iter()
                .filter(|&&(i, stage)| stage == 1 && !pending.contains(&(i, 0)))
                .map(|&(i, _)| s.events[i].at_s + s.events[i].restart_after_s.unwrap_or(0.0))
                .reduce(f64::min);
            m.send_pace(&mut last_pace, hold);
        }
        let team = m.team_time();
        pb.set_position(team.max(0.0) as u64);
        if plain_progress && team >= next_plain {
            eprintln!("progress: t = {team:.1} s of {duration:.1} s");
            next_plain += 10.0;
        }
        // Events.
        let mut fired = Vec::new();
        for (k, &(i, stage)) in pending.iter().enumerate() {
            let e = &s.events[i];
            let due = match (e.kind, stage) {
                (EventKind::Crash, 0) => {
                    let id = e.vehicle.expect("validated");
                    m.vehicles
                        .get(&id)
                        .is_some_and(|v| v.alive && v.last_t >= e.at_s)
                        || m.restart_requests.contains_key(&id)
                }
                (EventKind::HubLoss, _) => team >= e.at_s,
                (_, _) => {
                    // Restart once crashed, when the team reaches the restart time or the world
                    // holds its streams for it (which it does at exactly that time).
                    let id = e.vehicle.expect("validated");
                    let crashed = !pending.iter().any(|&(j, st)| j == i && st == 0);
                    crashed
                        && (team >= e.at_s + e.restart_after_s.unwrap_or(0.0)
                            || m.restart_requests.contains_key(&id))
                }
            };
            if due {
                fired.push(k);
            }
        }
        for k in fired.into_iter().rev() {
            let (i, stage) = pending.remove(k);
            let e = s.events[i].clone();
            let t = m.team_time();
            match (e.kind, stage) {
                (EventKind::Crash, 0) => {
                    let id = e.vehicle.expect("validated");
                    let name = names[&id].clone();
                    let t = m.vehicles.get(&id).map_or(t, |v| v.last_t);
                    if m.remote.is_some() {
                        m.order_host(id, Control::Kill { name: name.clone() });
                    } else {
                        m.kill(&name, nix::sys::signal::Signal::SIGKILL, true);
                    }
                    if let Some(v) = m.vehicles.get_mut(&id) {
                        v.alive = false;
                    }
                    say(
                        &pb,
                        format!("t = {t:.1} s: {name} killed with SIGKILL (scheduled crash)"),
                    );
                    m.events.push(EventRecord {
                        t,
                        until: e.restart_after_s.map(|r| e.at_s + r),
                        kind: "crash".into(),
                        subject: name,
                    });
                }
                (EventKind::Crash, _) => {
                    let id = e.vehicle.expect("validated");
                    let name = names[&id].clone();
                    // The world restarts it at exactly the scheduled time when it holds the
                    // streams for it.
                    let t = m.restart_requests.get(&id).copied().unwrap_or(t);
                    let inc = {
                        let v = m.vehicles.get_mut(&id).expect("validated");
                        v.restarts += 1;
                        v.alive = true;
                        v.last_t = t;
                        v.restarts
                    };
                    m.vehicles.get_mut(&id).expect("validated").incarnation = inc;
                    m.restart_requests.remove(&id);
                    if m.remote.is_some() {
                        m.order_host(
                            id,
                            Control::Restart {
                                vehicle: id,
                                incarnation: inc,
                            },
                        );
                    } else if let Err(err) = m.spawn(&name, Some(id), inc, &secret) {
                        m.failure = Some(format!("restarting {name}: {err:#}"));
                    }
                    say(
                        &pb,
                        format!("t = {t:.1} s: {name} restarted (incarnation {inc})"),
                    );
                    m.events.push(EventRecord {
                        t,
                        until: None,
                        kind: "restart".into(),
                        subject: name,
                    });
                }
                (EventKind::HubLoss, _) => {
                    if m.remote.is_some() {
                        let hub = m.s.fusion.hub_id;
                        m.order_host(hub, Control::Kill { name: "hub".into() });
                    } else {
                        m.kill("hub", nix::sys::signal::Signal::SIGKILL, true);
                    }
                    m.hub_alive = false;
                    say(
                        &pb,
                        format!("t = {t:.1} s: hub killed with SIGKILL (hub loss)"),
                    );
                    m.events.push(EventRecord {
                        t,
                        until: None,
                        kind: "hub-loss".into(),
                        subject: "hub".into(),
                    });
                }
            }
        }
        // Done: the world reached the end and every live vehicle finished its stream.
        let vehicles_done = m.vehicles.values().all(|v| !v.alive || v.finished);
        if m.world_finished && vehicles_done {
            break;
        }
        if m.procs
            .iter()
            .any(|p| p.name == "world" && p.status.is_some())
            && !m.world_finished
        {
            m.failure
                .get_or_insert("the world process ended before the end of the run".into());
        }
        match watchdog.check(&m) {
            WatchdogVerdict::Fine => {}
            WatchdogVerdict::Warn(line) => say(&pb, line),
            WatchdogVerdict::Fail(reason) => m.failure = Some(reason),
        }
        if !busy {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
    pb.finish_and_clear();
    m.shutdown();
    let removed = remove_run_leftovers(&prefix);
    tracing::debug!(removed, "iceoryx2 leftovers removed");

    let team_end = m.team_time().max(m.world_t.min(duration));
    if interrupted || m.failure.is_some() {
        base_stop.store(true, Ordering::Relaxed);
    }
    let baseline: Option<BaselineRun> = match baseline {
        None => None,
        Some(h) => match h.join() {
            Ok(Ok(b)) => Some(b),
            Ok(Err(e)) => {
                eprintln!("the centralized reference failed: {e}");
                None
            }
            Err(_) => {
                eprintln!("the centralized reference thread panicked");
                None
            }
        },
    };
    let record_end = if interrupted || m.failure.is_some() {
        team_end.min(duration)
    } else {
        duration
    };
    let (record, checks) = assemble(&m, &world, baseline, record_end, started, interrupted);
    Ok(LaunchOutcome { record, checks })
}

fn assemble(
    m: &Monitor,
    world: &World,
    baseline: Option<BaselineRun>,
    end: f64,
    started: Instant,
    interrupted: bool,
) -> (RunRecord, RunChecks) {
    let s = &m.s;
    let lead = s.run.max_lead_s;
    let truth = audit(m);
    let have_truth = crate::metrics::maps_have_truth(s);
    let mut vehicles = Vec::new();
    let mut vchecks = Vec::new();
    let mut confidence = Vec::new();
    for cfg in &s.vehicles {
        let v = &m.vehicles[&cfg.id];
        let mut rec = VehicleRecord {
            name: v.name.clone(),
            restarts: v.restarts,
            ..Default::default()
        };
        let mut est = v.estimates.clone();
        est.sort_by(|a, b| a.0.total_cmp(&b.0));
        for (t, x, p) in &est {
            if *t > end + 1e-6 {
                continue;
            }
            let state = VehicleState::from_vector(&VehicleVector::from_column_slice(x));
            let cov = VehicleCovariance::from_row_slice(p);
            // A replayed vehicle has truth where its ground truth covers the time.
            if let Some(tr) = m.truth.get(&(cfg.id, ms(*t))) {
                rec.samples
                    .push(pose_sample(world, &state, &cov, &truth_sample(world, tr)));
            } else if v.replay {
                rec.samples.push(estimate_sample(world, *t, &state, &cov));
            }
        }
        if let Some((t_last, feats)) = &v.last_map {
            rec.map = feats
                .iter()
                .map(|f| {
                    feature_record(
                        world,
                        f.id,
                        truth.truth(f.id).filter(|_| have_truth),
                        &Vector3::from(f.mean),
                        &f.covariance(),
                    )
                })
                .collect();
            let mut held = HeldSince::default();
            let mut reports: Vec<_> = v.maps.iter().collect();
            reports.sort_by(|a, b| a.0.total_cmp(&b.0));
            for (t, f) in reports {
                held.observe(*t, f.iter().map(|x| x.id));
            }
            held.stamp(*t_last, &mut rec.map);
            fill_record(&truth, cfg.id, &mut rec, *t_last);
        } else {
            fill_record(&truth, cfg.id, &mut rec, end);
        }
        rec.observations = truth.vehicle(cfg.id).observations;
        rec.association.merges_refused = v.counters.values().map(|c| c.merges_refused).sum();
        rec.rejected_messages = v.counters.values().map(|c| c.messages_rejected).sum();
        for c in v.counters.values() {
            for (k, n) in &c.rejections {
                *rec.rejections.entry(k.clone()).or_insert(0) += n;
            }
        }
        rec.peak_rss_bytes = v.counters.values().filter_map(|c| c.peak_rss_bytes).max();
        // Own frames: the latest incarnation's alignment, judged against the true frames.
        if let Some(a) = v
            .counters
            .values()
            .next_back()
            .and_then(|c| c.alignment.as_ref())
        {
            let root = crate::frames::team_root(s).map_or(cfg.id, |r| r.0);
            let own = |id: u32| {
                m.launch_from_own
                    .get(&id)
                    .copied()
                    .unwrap_or(Frame4::identity())
            };
            let truth = own(root).inverse().compose(&own(cfg.id));
            rec.frame_alignment = Some(crate::frames::alignment_record(a, &truth));
        }
        for c in v.counters.values() {
            for (k, n) in &c.access_refused {
                *rec.access_refused.entry(k.clone()).or_insert(0) += n;
            }
        }
        if !rec.access_refused.is_empty() {
            eprintln!(
                "{}: zenoh access control refused {} message(s) of other sessions: {:?}",
                v.name,
                rec.access_refused.values().sum::<u64>(),
                rec.access_refused
            );
        }
        let rec_rejections = rec.rejections.clone();
        let rec_peak_rss = rec.peak_rss_bytes;
        let rec_access_refused = rec.access_refused.clone();
        let association = rec.association;
        vehicles.push(rec);
        if let Some(b) = &baseline {
            for (t, feats) in &v.maps {
                let ref_t = (t + lead).min(b.duration);
                let Some(snap) = b.snapshot_at_or_after(ref_t) else {
                    continue;
                };
                let mut worst: Option<(f64, FeatureId)> = None;
                let mut n = 0;
                for f in feats {
                    // The reference keys features by their true ids under appearance.
                    let Some(pr) = snap
                        .covariances
                        .get(&f.id)
                        .or_else(|| truth.truth(f.id).and_then(|t| snap.covariances.get(&t)))
                    else {
                        continue;
                    };
                    let pi: Matrix3<f64> = f.covariance();
                    if let Some(r) = feature_confidence_ratio(&pi, pr) {
                        n += 1;
                        if worst.is_none_or(|(w, _)| r > w) {
                            worst = Some((r, f.id));
                        }
                    }
                }
                if let Some((ratio, feature)) = worst {
                    confidence.push(ConfidenceSample {
                        vehicle: v.name.clone(),
                        t: *t,
                        reference_t: snap.t,
                        ratio,
                        feature,
                        features: n,
                    });
                }
            }
        }
        vchecks.push(VehicleCheck {
            name: v.name.clone(),
            counters: v.counters.values().cloned().collect(),
            rejections: rec_rejections,
            peak_rss_mb: rec_peak_rss.map(|b| b as f64 / 1e6),
            access_refused: rec_access_refused,
            estimate_reports: v.estimates.len(),
            map_reports: v.maps.len(),
            last_report_t: v.estimates.iter().map(|e| e.0).fold(f64::NAN, f64::max),
            final_map_features: v.last_map.as_ref().map_or(0, |m| m.1.len()),
            map_sizes: v.maps.iter().map(|(t, f)| (*t, f.len())).collect(),
            initialisations: v.initialisations,
            association,
        });
    }
    // Links: both ends' counters at every record time.
    let mut links = Vec::new();
    let record_dt = s.run.record_interval_s;
    for l in effective_links(s) {
        let (a, b) = (l.a, l.b);
        let mut rec = LinkRecord {
            a: m.names[&a].clone(),
            b: m.names[&b].clone(),
            transport: match l.transport {
                TransportKind::Shm => "shm".into(),
                TransportKind::Net => "net".into(),
            },
            ci: false,
            naive_bytes: 0,
            samples: Vec::new(),
        };
        let sa = m.link_streams.get(&(a, b));
        let sb = m.link_streams.get(&(b, a));
        let mut k = 0u64;
        loop {
            let t = (k as f64 * record_dt).min(end);
            let ra = sa.and_then(|x| x.at(t)).copied().unwrap_or_default();
            let rb = sb.and_then(|x| x.at(t)).copied().unwrap_or_default();
            rec.ci |= ra.ci || rb.ci;
            rec.naive_bytes = ra.naive_bytes + rb.naive_bytes;
            rec.samples.push(LinkSample {
                t,
                bytes_ab: ra.sent_bytes,
                bytes_ba: rb.sent_bytes,
                messages: ra.sent_messages + rb.sent_messages,
                drops: ra.dropped_send + rb.dropped_send + ra.dropped_faults + rb.dropped_faults,
                rejections: ra.rejected_transport
                    + rb.rejected_transport
                    + ra.rejected_channel
                    + rb.rejected_channel,
                up: ra.up && rb.up,
                a_up: ra.up,
                b_up: rb.up,
            });
            if t >= end {
                break;
            }
            k += 1;
        }
        links.push(rec);
    }
    // Events: configured outages and partitions, then what happened.
    let mut events = Vec::new();
    for l in effective_links(s) {
        for w in &l.faults.outages {
            if w[0] < end {
                events.push(EventRecord {
                    t: w[0],
                    until: Some(w[1].min(end)),
                    kind: "outage".into(),
                    subject: l.label(&m.names),
                });
            }
        }
    }
    for p in &s.partitions {
        if p.start_s < end {
            let side: Vec<String> = p
                .side
                .iter()
                .map(|id| m.names.get(id).cloned().unwrap_or_default())
                .collect();
            events.push(EventRecord {
                t: p.start_s,
                until: Some(p.end_s.min(end)),
                kind: "partition".into(),
                subject: side.join("+"),
            });
        }
    }
    events.extend(m.events.iter().cloned());
    events.sort_by(|a, b| a.t.total_cmp(&b.t));
    let record = RunRecord {
        scenario: s.run.name.clone().unwrap_or_else(|| "scenario".into()),
        mode: s.fusion.mode.to_string(),
        frame: world.frame().to_string(),
        seed: s.world.seed,
        duration: end,
        wall_time: started.elapsed().as_secs_f64(),
        vehicles,
        links,
        events,
        baseline: baseline.map(|b| {
            let mut v = b.vehicles;
            for r in &mut v {
                r.samples.retain(|x| x.t <= end + 1e-6);
            }
            v
        }),
        truth_features: crate::sim::truth_features(s, world),
        time_origin_ns: s.run.time_origin_ns,
        team_wrong_merges: truth.team_wrong_merges(),
        identity: s.world.appearance.identity.to_string(),
        router_access_refused: m.router_access_refused.clone(),
    };
    if !m.router_access_refused.is_empty() {
        eprintln!(
            "the zenoh router's access control refused {} message(s) of its clients: {:?}",
            m.router_access_refused.values().sum::<u64>(),
            m.router_access_refused
        );
    }
    let processes = m
        .procs
        .iter()
        .map(Proc::record)
        .chain(m.remote_procs.iter().cloned())
        .collect();
    let max_confidence_ratio = confidence.iter().map(|c| c.ratio).reduce(f64::max);
    let link_ends = m
        .link_streams
        .iter()
        .filter_map(|((node, peer), st)| {
            Some(LinkEndCheck {
                node: m.names.get(node)?.clone(),
                peer: m.names.get(peer)?.clone(),
                incarnation: st.incarnation,
                report: st.samples.last()?.1,
            })
        })
        .collect();
    let checks = RunChecks {
        processes,
        confidence,
        max_confidence_ratio,
        lead_s: lead,
        vehicles: vchecks,
        link_ends,
        hub_rejected: m.hub_rejected,
        hub_access_refused: m.hub_access_refused.clone(),
        control_access_refused: super::access_refusals(),
        router_access_refused: m.router_access_refused.clone(),
        hub_rejections: m.hub_rejections.clone(),
        interrupted,
        failure: m.failure.clone(),
        prefix: m.prefix.clone(),
    };
    (record, checks)
}

/// Judges every vehicle's association outcomes and adopted merges against the world's true
/// ids ([`crate::truth`]).
fn audit(m: &Monitor) -> KeyTruth {
    let mut audit = TruthAudit::default();
    for (&id, v) in &m.vehicles {
        for fa in &v.associations {
            // A frame another vehicle observed (data sharing) has that vehicle's true ids.
            let observer = fa.origin.unwrap_or(id);
            audit.frame(
                id,
                fa,
                m.true_ids.get(&(observer, ms(fa.t))).map(Vec::as_slice),
            );
        }
        audit.set_merges(id, v.merges.clone());
    }
    audit.finish()
}

/// A reported estimate (state, row-major covariance) in the launch frame: converted from the
/// own frame of `owner` (local SLAM in own frames), unchanged in a shared frame.
fn in_launch_frame(
    launch_from_own: &BTreeMap<u32, Frame4>,
    owner: Option<NodeId>,
    state: Vec<f64>,
    covariance: Vec<f64>,
) -> (Vec<f64>, Vec<f64>) {
    let Some(frame) = owner.and_then(|o| launch_from_own.get(&o)) else {
        return (state, covariance);
    };
    if state.len() != VEHICLE_DIM || covariance.len() != VEHICLE_DIM * VEHICLE_DIM {
        // Malformed: left as it is (the report's own validation judges it).
        return (state, covariance);
    }
    let x = VehicleState::from_vector(&VehicleVector::from_column_slice(&state));
    let p = VehicleCovariance::from_row_slice(&covariance);
    let (x, p) = crate::metrics::state_in(frame, &x, &p);
    (
        x.to_vector().as_slice().to_vec(),
        p.transpose().as_slice().to_vec(),
    )
}

fn truth_sample(world: &World, r: &TruthReport) -> TruthSample {
    let x = VehicleState::from_vector(&VehicleVector::from_column_slice(&r.nav));
    let v3 = |k: usize| Vector3::new(r.launch[3 * k], r.launch[3 * k + 1], r.launch[3 * k + 2]);
    TruthSample {
        time: r.t,
        frame: world.frame(),
        position: x.position,
        velocity: x.velocity,
        attitude: x.attitude,
        accel_bias: x.accel_bias,
        gyro_bias: x.gyro_bias,
        launch_position: v3(0),
        launch_velocity: v3(1),
        launch_attitude: v3(2),
    }
}

/// One line on the sparsified (capacity-limited) links of a run, for the text summary: how many
/// deltas went out as conservative marginals, how many rounds sent nothing (their delta stayed
/// pending, `canopy_fusion::sparse::SparsifyError`), how many had their vector gated, and the
/// link end worst at each; then the re-centrings and the features sent first because a peer
/// listed them as loosely held (`canopy_fusion::ddf::Body::Uncertain`), when there were any.
/// `ends` holds (this end's name, the peer's name, its channel's counters). `None` when no
/// link end sparsified anything.
///
/// Why a user needs it: a sparsified link that keeps refusing or gating its rounds holds its
/// information back for good — the run still ends cleanly, but the far vehicles' maps lag
/// (docs/benchmarks.md, fourteenth pass: tree-8-radio with a two-second interval, 71 of 133
/// rounds refused on uav3→uav7, and uav7 and uav8 ending with 439 and 432 of ~600 features).
pub fn sparsified_health(ends: &[(&str, &str, &ChannelStats)]) -> Option<String> {
    let sparse: u64 = ends.iter().map(|e| e.2.sparse_deltas).sum();
    let refused: u64 = ends.iter().map(|e| e.2.sparse_refused).sum();
    if sparse == 0 && refused == 0 {
        return None;
    }
    let gated: u64 = ends.iter().map(|e| e.2.sparse_vector_dropped).sum();
    let worst = |count: fn(&ChannelStats) -> u64| -> String {
        ends.iter()
            .filter(|e| count(e.2) > 0)
            .max_by_key(|e| count(e.2))
            .map_or(String::new(), |(node, peer, c)| {
                format!(
                    " (most: {node}→{peer}, {} of {})",
                    count(c),
                    c.sparse_deltas + c.sparse_refused
                )
            })
    };
    let refused_worst = worst(|c| c.sparse_refused);
    let gated_worst = worst(|c| c.sparse_vector_dropped);
    let recentred: u64 = ends.iter().map(|e| e.2.sparse_recentred).sum();
    let recentred = if recentred > 0 {
        format!(", {recentred} re-centrings")
    } else {
        String::new()
    };
    let promoted: u64 = ends.iter().map(|e| e.2.uncertain_promoted).sum();
    let promoted = if promoted > 0 {
        format!("; {promoted} features a peer held loosely sent first")
    } else {
        String::new()
    };
    Some(format!(
        "sparsified links: {sparse} marginal deltas sent; {refused} rounds refused{refused_worst}; \
         {gated} vectors gated{gated_worst}{recentred}{promoted}"
    ))
}

/// [`sparsified_health`] of a multi-process run's link ends (`checks.json`).
pub fn sparsified_health_of(link_ends: &[LinkEndCheck]) -> Option<String> {
    let ends: Vec<(&str, &str, &ChannelStats)> = link_ends
        .iter()
        .map(|e| (e.node.as_str(), e.peer.as_str(), &e.report.channel))
        .collect();
    sparsified_health(&ends)
}

/// Writes `checks.json` into `dir`.
pub fn write_checks(checks: &RunChecks, dir: &Path) -> Result<()> {
    let p = dir.join("checks.json");
    let text = serde_json::to_string_pretty(checks).context("serialising checks.json")?;
    std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn end(node: &str, peer: &str, sparse: u64, refused: u64, gated: u64) -> LinkEndCheck {
        let mut report = LinkReport::default();
        report.channel.sparse_deltas = sparse;
        report.channel.sparse_refused = refused;
        report.channel.sparse_vector_dropped = gated;
        report.channel.sparse_recentred = gated / 3;
        LinkEndCheck {
            node: node.into(),
            peer: peer.into(),
            incarnation: 0,
            report,
        }
    }

    /// The line adds every end's counters and names the end with the most refused rounds and
    /// the most gated vectors, each out of that end's sparsified rounds (sent + refused), and
    /// the re-centrings (here a third of each end's gated count: 5 + 1) and the features sent
    /// first because the peer listed them as loosely held (4 + 7).
    #[test]
    fn sparsified_health_totals_and_names_the_worst_end() {
        let mut ends = [
            end("uav3", "uav7", 79, 54, 17),
            end("uav4", "uav3", 103, 0, 3),
            end("uav2", "uav3", 102, 25, 0),
        ];
        ends[0].report.channel.uncertain_promoted = 4;
        ends[2].report.channel.uncertain_promoted = 7;
        assert_eq!(
            sparsified_health_of(&ends).as_deref(),
            Some(
                "sparsified links: 284 marginal deltas sent; 79 rounds refused \
                 (most: uav3→uav7, 54 of 133); 20 vectors gated (most: uav3→uav7, 17 of 133), \
                 6 re-centrings; 11 features a peer held loosely sent first"
            )
        );
    }

    /// Exact links (nothing sparsified) print nothing; a clean sparsified run prints zeros
    /// without a "most".
    #[test]
    fn sparsified_health_is_silent_on_exact_links() {
        assert_eq!(sparsified_health_of(&[end("a", "b", 0, 0, 0)]), None);
        assert_eq!(sparsified_health_of(&[]), None);
        assert_eq!(
            sparsified_health_of(&[end("a", "b", 5, 0, 0)]).as_deref(),
            Some("sparsified links: 5 marginal deltas sent; 0 rounds refused; 0 vectors gated")
        );
    }
}
