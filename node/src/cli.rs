//! The `canopy` command line (clap). `main.rs` only parses and calls [`run_cli`].

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};

use crate::network::{FusionMode, effective_links, node_names, topology};
use crate::output::{Summary, table, write_all};
use crate::scenario::Scenario;
use crate::sim::{SimOptions, simulate};

/// Decentralized multi-vehicle inertial SLAM.
#[derive(Debug, Parser)]
#[command(name = "canopy", version, about, long_about = None)]
pub struct Cli {
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Sub-commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run a scenario as real processes (world, one per vehicle, hub) on this host.
    Run(LaunchArgs),
    /// Run a scenario in one deterministic process (simulated network).
    Sim(RunArgs),
    /// The zenoh router of a multi-host run in client mode (`[zenoh].mode = "client"`): every
    /// session of the run connects to it; it enforces the scenario's access control and
    /// reports what it refused to the monitor. Start it first; it ends after the run.
    Router(RouterArgs),
    /// Validate a scenario and explain what it will run.
    Check {
        /// Scenario TOML file.
        scenario: PathBuf,
    },
    /// Print the built-in default scenario as TOML (a starting point for your own).
    Default,
    /// Turn a real recording (EuRoC/ASL or flat files, EuRoC or Kalibr calibration, feature
    /// tracks, optional ground truth) into a replay scenario.
    Import(Box<crate::import::ImportArgs>),
    /// Print a generated tree team of N vehicles as TOML (benchmarks, scale tests).
    Team {
        /// Number of vehicles (1–64).
        #[arg(value_parser = clap::value_parser!(u32).range(1..=i64::from(crate::team::MAX_TEAM)))]
        vehicles: u32,
        /// Simulated duration [s].
        #[arg(long, default_value_t = 60.0)]
        duration: f64,
        /// Features in the world (default: the built-in world's).
        #[arg(long)]
        features: Option<usize>,
    },
    /// Print the summaries of finished runs side by side.
    Compare {
        /// Output directories (each with a summary.json).
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
    },
    /// Evaluate an estimated trajectory against ground truth: ATE after alignment, RPE (evo's
    /// definitions) and relative error (rpg_trajectory_evaluation's).
    Eval(EvalArgs),
    /// The processes `canopy run` spawns (internal).
    #[command(hide = true)]
    Role(crate::process::RoleArgs),
}

/// Arguments of `run`.
#[derive(Debug, Args)]
pub struct LaunchArgs {
    /// What `run` shares with `sim`.
    #[command(flatten)]
    pub run: RunArgs,
    /// Run a vehicle's process in a network namespace: `VEHICLE=NAMESPACE` (vehicle id or
    /// name; the process is started with `ip netns exec NAMESPACE`). Repeatable.
    #[arg(long, value_name = "VEHICLE=NS")]
    pub netns: Vec<String>,
    /// Multi-host run: start only the share of `[[host]]` NAME (its world, vehicles and, with
    /// `hub = true`, the hub), reporting to the monitor over zenoh at `[zenoh].monitor`.
    #[arg(long, value_name = "NAME", conflicts_with_all = ["monitor", "netns"])]
    pub host: Option<String>,
    /// Multi-host run: be the monitor only (no local vehicles): gather every host's reports over
    /// zenoh (listening on `[zenoh].monitor`) and write the outputs.
    #[arg(long, conflicts_with = "netns")]
    pub monitor: bool,
    /// `--host`: seconds to wait for the monitor to answer before giving up.
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0)]
    pub monitor_wait: f64,
    /// `--monitor`: seconds to wait for every host to connect before giving up.
    #[arg(long, value_name = "SECONDS", default_value_t = 300.0)]
    pub wait_hosts: f64,
}

/// Arguments of `router`.
#[derive(Debug, Args)]
pub struct RouterArgs {
    /// Scenario TOML file (the same as the monitor's and every host's).
    pub scenario: PathBuf,
    /// Endpoint to listen on, e.g. `tcp/0.0.0.0:7447` (repeatable; default: every endpoint of
    /// `[zenoh].connect`).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Override the simulated duration [s] (the same as the monitor's).
    #[arg(long)]
    pub duration: Option<f64>,
    /// Seconds to wait for the monitor to answer before giving up.
    #[arg(long, value_name = "SECONDS", default_value_t = 300.0)]
    pub monitor_wait: f64,
    /// No progress lines.
    #[arg(long)]
    pub quiet: bool,
}

/// Arguments of `run` and `sim`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// Scenario TOML file (default: the built-in 4-UAV decentralized tree).
    pub scenario: Option<PathBuf>,
    /// Output directory (default: out/<scenario name>).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Override the simulated duration [s].
    #[arg(long)]
    pub duration: Option<f64>,
    /// Do not run the centralized all-data EKF reference.
    #[arg(long)]
    pub no_baseline: bool,
    /// Do not show a progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// Also write every simulated vehicle's sensor stream as replay logs (CSV) into this
    /// directory (see the README, "Replay logs").
    #[arg(long, value_name = "DIR")]
    pub record_logs: Option<PathBuf>,
}

/// Arguments of `eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Estimated trajectory: TUM (`timestamp tx ty tz qx qy qz qw`) or EuRoC CSV.
    pub est: PathBuf,
    /// Ground truth: TUM, or EuRoC/ASL CSV (`state_groundtruth_estimate0/data.csv`).
    pub gt: PathBuf,
    /// Alignments before the ATE (comma separated or repeated).
    #[arg(long, value_enum, value_delimiter = ',', default_values = ["se3", "posyaw"])]
    pub align: Vec<crate::eval::Alignment>,
    /// RPE and relative-error distances [m] (comma separated or repeated); default 10, 20, 30,
    /// 40, 50 % of the matched ground truth's path length, truncated to centimetres.
    #[arg(long, value_delimiter = ',')]
    pub delta: Vec<f64>,
    /// Largest timestamp difference of a matched pair [s].
    #[arg(long, default_value_t = 0.01)]
    pub max_diff: f64,
    /// Added to the estimate's timestamps before matching [s].
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub offset: f64,
    /// Where the estimate's z axis points (position+yaw alignment; canopy's outputs: down).
    #[arg(long, value_enum, default_value = "up")]
    pub est_z: crate::eval::ZAxis,
    /// Where the ground truth's z axis points (position+yaw alignment; EuRoC: up).
    #[arg(long, value_enum, default_value = "up")]
    pub gt_z: crate::eval::ZAxis,
    /// Choose the RPE pairs along the ground truth's path (evo's `--pairs_from_reference`).
    #[arg(long)]
    pub pairs_from_reference: bool,
    /// Also write the figures as JSON to this file.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

/// Loads the scenario named on the command line, or the built-in default.
pub fn load_scenario(path: Option<&Path>) -> Result<Scenario> {
    let mut s = match path {
        Some(p) => {
            Scenario::load(p).with_context(|| format!("loading scenario {}", p.display()))?
        }
        None => Scenario::builtin_default(),
    };
    if s.run.name.is_none() {
        s.run.name = Some(path.and_then(|p| p.file_stem()).map_or_else(
            || "default".to_string(),
            |n| n.to_string_lossy().into_owned(),
        ));
    }
    Ok(s)
}

fn out_dir(args: &RunArgs, s: &Scenario) -> PathBuf {
    args.out.clone().unwrap_or_else(|| {
        PathBuf::from("out").join(dir_name(s.run.name.as_deref().unwrap_or("default")))
    })
}

/// A directory name for a scenario name: ASCII letters, digits, `-` and `_` kept, every run of
/// other characters one `-`, none at the ends (`default (tree-4)` → `default-tree-4`).
fn dir_name(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    for c in name.chars() {
        if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
            out.push(c);
        } else if !out.is_empty() && !out.ends_with('-') {
            out.push('-');
        }
    }
    let out = out.trim_end_matches('-');
    if out.is_empty() {
        "run".to_string()
    } else {
        out.to_string()
    }
}

/// A Ctrl-C flag: the first Ctrl-C asks for a clean stop (outputs are still written).
pub fn ctrl_c_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    // If a handler is already installed (tests calling twice), keep going without one.
    let _ = ctrlc::set_handler(move || f.store(true, Ordering::SeqCst));
    flag
}

/// A progress bar over simulated time.
pub fn progress_bar(duration: f64, quiet: bool) -> indicatif::ProgressBar {
    if quiet {
        return indicatif::ProgressBar::hidden();
    }
    let pb = indicatif::ProgressBar::new(duration.ceil().max(1.0) as u64);
    pb.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} s simulated {msg}",
        )
        .expect("static template")
        .progress_chars("=> "),
    );
    pb
}

fn record_logs(args: &RunArgs, s: &Scenario) -> Result<()> {
    if let Some(dir) = &args.record_logs {
        let duration = args.duration.unwrap_or(s.run.duration_s);
        let written = crate::replay::record_logs(s, dir, duration)
            .with_context(|| format!("writing replay logs to {}", dir.display()))?;
        println!(
            "replay logs of {} vehicle(s) in {}",
            written.len(),
            dir.display()
        );
    }
    Ok(())
}

fn cmd_sim(args: &RunArgs) -> Result<()> {
    let s = load_scenario(args.scenario.as_deref())?;
    canopy_fusion::runtime::set_heap_policy(s.run.heap);
    let out = out_dir(args, &s);
    record_logs(args, &s)?;
    let duration = args.duration.unwrap_or(s.run.duration_s);
    let pb = progress_bar(duration, args.quiet);
    let stop = ctrl_c_flag();
    let mut progress = |t: f64, _d: f64| pb.set_position(t as u64);
    let outcome = simulate(
        &s,
        SimOptions {
            duration: args.duration,
            baseline: args.no_baseline.then_some(false),
            progress: Some(&mut progress),
            stop: Some(stop.clone()),
        },
    )
    .context("simulation failed")?;
    pb.finish_and_clear();
    if stop.load(Ordering::Relaxed) {
        eprintln!(
            "interrupted: writing what was gathered up to t = {:.1} s",
            outcome.record.duration
        );
    }
    let summary = write_all(&outcome.record, &out)
        .with_context(|| format!("writing outputs to {}", out.display()))?;
    print!(
        "{}",
        table(&[(s.run.name.as_deref().unwrap_or("run"), &summary)])
    );
    let ends: Vec<_> = outcome
        .checks
        .link_ends
        .iter()
        .map(|(node, peer, c)| (node.as_str(), peer.as_str(), c))
        .collect();
    if let Some(line) = crate::process::monitor::sparsified_health(&ends) {
        println!("{line}");
    }
    println!("outputs in {}", out.display());
    Ok(())
}

/// Seconds from the command line as a duration (finite, ≥ 0).
fn seconds(flag: &str, v: f64) -> Result<std::time::Duration> {
    std::time::Duration::try_from_secs_f64(v)
        .map_err(|_| anyhow::anyhow!("{flag} {v}: expected a number of seconds ≥ 0"))
}

/// `canopy run SCENARIO --host NAME`: this host's share of a multi-host run.
fn cmd_run_host(args: &LaunchArgs, s: Scenario, name: &str) -> Result<()> {
    let out = args
        .run
        .out
        .clone()
        .unwrap_or_else(|| out_dir(&args.run, &s).join(format!("host-{}", dir_name(name))));
    let opts = crate::process::host::HostOptions {
        out: out.clone(),
        duration: args.run.duration,
        quiet: args.run.quiet,
        exe: None,
        stop: ctrl_c_flag(),
        monitor_wait: seconds("--monitor-wait", args.monitor_wait)?,
    };
    let outcome = crate::process::host::run_host(s, name, &opts)
        .with_context(|| format!("canopy run --host {name} failed"))?;
    for p in &outcome.processes {
        if !p.clean_exit() && !p.killed_by_monitor {
            println!(
                "process {} did not exit cleanly (code {:?}, signal {:?}); log {}",
                p.name,
                p.exit_code,
                p.signal,
                p.log.display()
            );
        }
    }
    println!(
        "host {name}: {} process(es) ended; logs in {}",
        outcome.processes.len(),
        out.join("logs").display()
    );
    if let Some(f) = &outcome.failure {
        anyhow::bail!("host {name}: {f}");
    }
    Ok(())
}

fn cmd_router(args: &RouterArgs) -> Result<()> {
    let s = load_scenario(Some(&args.scenario))?;
    let opts = crate::process::router::RouterOptions {
        listen: args.listen.clone(),
        duration: args.duration,
        monitor_wait: seconds("--monitor-wait", args.monitor_wait)?,
        quiet: args.quiet,
        stop: ctrl_c_flag(),
    };
    crate::process::router::run_router(s, &opts)
}

fn cmd_run(args: &LaunchArgs) -> Result<()> {
    let s = load_scenario(args.run.scenario.as_deref())?;
    if let Some(name) = &args.host {
        return cmd_run_host(args, s, name);
    }
    let out = out_dir(&args.run, &s);
    record_logs(&args.run, &s)?;
    let mut netns = std::collections::BTreeMap::new();
    for spec in &args.netns {
        let (who, ns) = spec
            .split_once('=')
            .with_context(|| format!("--netns {spec}: expected VEHICLE=NAMESPACE"))?;
        let v = s
            .vehicles
            .iter()
            .find(|v| v.display_name() == who || v.id.to_string() == who)
            .with_context(|| format!("--netns {spec}: no vehicle `{who}` in the scenario"))?;
        netns.insert(v.id, ns.to_string());
    }
    let opts = crate::process::monitor::LaunchOptions {
        out: out.clone(),
        duration: args.run.duration,
        baseline: args.run.no_baseline.then_some(false),
        quiet: args.run.quiet,
        netns,
        exe: None,
        stop: ctrl_c_flag(),
        monitor_only: if args.monitor {
            Some(seconds("--wait-hosts", args.wait_hosts)?)
        } else {
            None
        },
    };
    let outcome = crate::process::monitor::launch(s.clone(), &opts).context("canopy run failed")?;
    if outcome.checks.interrupted {
        eprintln!(
            "interrupted: writing what was gathered up to t = {:.1} s",
            outcome.record.duration
        );
    }
    let summary = write_all(&outcome.record, &out)
        .with_context(|| format!("writing outputs to {}", out.display()))?;
    crate::process::monitor::write_checks(&outcome.checks, &out)?;
    print!(
        "{}",
        table(&[(s.run.name.as_deref().unwrap_or("run"), &summary)])
    );
    if let Some(r) = outcome.checks.max_confidence_ratio {
        println!("largest confidence ratio vs the centralized reference: {r:.3} (≤ 1 ideal)");
    }
    if let Some(line) = crate::process::monitor::sparsified_health_of(&outcome.checks.link_ends) {
        println!("{line}");
    }
    for p in &outcome.checks.processes {
        if !p.clean_exit() && !p.killed_by_monitor {
            println!(
                "process {} (incarnation {}) did not exit cleanly (code {:?}, signal {:?}); log {}",
                p.name,
                p.incarnation,
                p.exit_code,
                p.signal,
                p.log.display()
            );
        }
    }
    println!("outputs in {}", out.display());
    if let Some(f) = &outcome.checks.failure {
        anyhow::bail!("the run failed: {f}");
    }
    Ok(())
}

fn cmd_check(path: &Path) -> Result<()> {
    let s = load_scenario(Some(path))?;
    let inputs =
        crate::preflight::preflight(&s).with_context(|| format!("checking {}", path.display()))?;
    let names = node_names(&s);
    println!("{}: valid", path.display());
    if s.vehicles.iter().any(|v| v.replay.is_none()) {
        println!(
            "  world: seed {}, {} frame, {} features over {:.0} m × {:.0} m, identity {}",
            s.world.seed,
            s.world.earth_model.frame(),
            s.world.feature_count(),
            s.world.area.size_north_m,
            s.world.area.size_east_m,
            s.world.appearance.identity
        );
        if let (crate::scenario::Frames::Own, Some(root)) =
            (s.world.frames, crate::frames::team_root(&s))
        {
            println!(
                "  frames: each vehicle starts in its own frame; the team frame is `{}`'s, the \
                 others join it by aligning their maps with a neighbour's",
                names.get(&root.0).map_or("?", String::as_str)
            );
        }
    } else {
        println!(
            "  world: {} frame, origin {}°, {}°, {} m (every vehicle replayed: nothing simulated)",
            s.world.earth_model.frame(),
            s.world.origin.lat_deg,
            s.world.origin.lon_deg,
            s.world.origin.height_m
        );
    }
    for (v, input) in s.vehicles.iter().zip(&inputs) {
        match (input, &v.trajectory) {
            (
                crate::preflight::VehicleInput::Replayed {
                    imu_samples,
                    frames,
                    observations,
                    split_samples,
                    start,
                    end,
                    alignment,
                },
                _,
            ) => {
                println!(
                    "  vehicle {} `{}` replays {imu_samples} IMU samples and {frames} frames \
                     ({observations} observations; {split_samples} samples split at a frame \
                     time) from t = {start} s to {end} s; sensor {:?}",
                    v.id,
                    v.display_name(),
                    v.sensor.model,
                );
                if let Some((n, d)) = alignment {
                    println!("    initial estimate: static alignment over {n} samples ({d:.2} s)");
                }
            }
            (_, Some(t)) => println!(
                "  vehicle {} `{}`: {:?} at {:.0} m, {:.0} m/s; sensor {:?} at {} Hz; IMU {:?} at {} Hz",
                v.id,
                v.display_name(),
                t.shape,
                t.altitude_m,
                t.speed_mps,
                v.sensor.model,
                v.sensor.rate_hz,
                v.imu.grade,
                v.imu.rate_hz
            ),
            (_, None) => {}
        }
    }
    println!(
        "  fusion: {} at {} Hz, association {:?}",
        s.fusion.mode,
        s.fusion.rate_hz,
        s.fusion.association_kind(s.world.appearance.identity)
    );
    let topo = topology(&s)?;
    if s.fusion.mode != FusionMode::Isolated {
        println!(
            "  topology: tree of {} nodes, diameter {}",
            names.len(),
            topo.diameter().unwrap_or(0)
        );
    }
    // With [[host]] tables, the endpoints a multi-host run derives (validated already).
    let mut deployed = s.clone();
    if !s.hosts.is_empty() && s.zenoh.mode == crate::deploy::ZenohModeConfig::Peer {
        crate::deploy::resolve_endpoints(&mut deployed)?;
    }
    for l in effective_links(&deployed) {
        let faults = if l.faults.is_none() {
            "no faults".to_string()
        } else {
            format!("faults {:?}", l.faults)
        };
        let radio = match &l.radio {
            Some(r) => format!(
                ", radio {} B/s ({} of ≤ {} bytes per round), queue {} B, latency {} s{}",
                r.bytes_per_s,
                match (s.fusion.mode, r.fusion) {
                    (FusionMode::SharedData, _) => "data batches",
                    (_, crate::radio::RadioFusion::Sparse) => "sparsified deltas",
                    (_, crate::radio::RadioFusion::Ci) => "CI submaps",
                },
                r.delta_budget(&s.fusion),
                r.queue_bytes(&s.fusion),
                r.latency_s,
                r.range_m
                    .map(|m| format!(", range {m} m"))
                    .unwrap_or_default()
            ),
            None => String::new(),
        };
        let listen = l
            .listen
            .as_deref()
            .map(|ep| {
                let a = names.get(&l.a).map_or("?", String::as_str);
                format!(", {a} listens on {ep}")
            })
            .unwrap_or_default();
        println!(
            "  link {}: {:?}, {}{radio}{listen}",
            l.label(&names),
            l.transport,
            faults
        );
    }
    for h in &s.hosts {
        let nodes: Vec<&str> = crate::deploy::local_nodes(&s, h)
            .iter()
            .filter_map(|id| names.get(id).map(String::as_str))
            .collect();
        println!(
            "  host {} ({}): {}",
            h.name,
            h.address.as_deref().unwrap_or("no address"),
            nodes.join(", ")
        );
    }
    if !s.hosts.is_empty() && crate::deploy::client_mode(&s) {
        println!(
            "  hosts (client mode): `canopy router SCENARIO` first on the router's machine \
             (listening on {}), then `canopy run SCENARIO --monitor` and `canopy run SCENARIO \
             --host NAME` on each host, all connecting to it; plain `canopy run` runs every \
             host's share on this machine, peer to peer (docs/arch/deploy.md)",
            s.zenoh.connect.join(", ")
        );
    } else if !s.hosts.is_empty() {
        println!(
            "  hosts: `canopy run SCENARIO --monitor` on the monitor's machine ({}), then \
             `canopy run SCENARIO --host NAME` on each host; plain `canopy run` runs every \
             host's share on this machine (docs/arch/deploy.md)",
            s.zenoh.monitor.as_deref().unwrap_or("?")
        );
    }
    for e in &s.events {
        println!(
            "  event: {:?} {:?} at {} s (restart after {:?} s)",
            e.kind, e.vehicle, e.at_s, e.restart_after_s
        );
    }
    println!("  run: {} s, baseline {}", s.run.duration_s, s.run.baseline);
    if let Some(o) = s.run.time_origin_ns {
        println!("  time origin: t = 0 is {o} ns of the recording's clock");
    }
    Ok(())
}

fn cmd_import(args: &crate::import::ImportArgs) -> Result<()> {
    let r = crate::import::import(args).context("canopy import failed")?;
    println!("scenario: {}", r.scenario.display());
    println!(
        "  {} IMU samples, {} frames with {} observations; time origin {} ns",
        r.imu_samples, r.frames, r.observations, r.time_origin_ns
    );
    println!("  initial estimate: {:?}", r.initial);
    if let Some(rest) = r.rest_s {
        println!("  at rest for the first {rest:.3} s");
    }
    let c = r.imu_from_body;
    println!(
        "  body frame: C_b^S = [{:.6} {:.6} {:.6}; {:.6} {:.6} {:.6}; {:.6} {:.6} {:.6}]",
        c[(0, 0)],
        c[(0, 1)],
        c[(0, 2)],
        c[(1, 0)],
        c[(1, 1)],
        c[(1, 2)],
        c[(2, 0)],
        c[(2, 1)],
        c[(2, 2)]
    );
    println!(
        "  camera: virtual undistorted pinhole f = ({:.3}, {:.3}) px, principal point ({:.3}, {:.3}) px, {} × {} px",
        r.pinhole.focal[0],
        r.pinhole.focal[1],
        r.pinhole.principal[0],
        r.pinhole.principal[1],
        r.pinhole.size[0],
        r.pinhole.size[1]
    );
    if let Some(g) = &r.groundtruth {
        println!(
            "  ground truth (navigation frame, recording time base): {}",
            g.display()
        );
    }
    for n in &r.notes {
        println!("  note: {n}");
    }
    println!(
        "next: canopy check {0}; canopy run {0}",
        r.scenario.display()
    );
    Ok(())
}

fn cmd_compare(dirs: &[PathBuf]) -> Result<()> {
    let mut loaded: Vec<(String, Summary)> = Vec::new();
    for d in dirs {
        let p = d.join("summary.json");
        let text =
            std::fs::read_to_string(&p).with_context(|| format!("reading {}", p.display()))?;
        let s: Summary =
            serde_json::from_str(&text).with_context(|| format!("parsing {}", p.display()))?;
        loaded.push((
            d.file_name().map_or_else(
                || d.display().to_string(),
                |n| n.to_string_lossy().into_owned(),
            ),
            s,
        ));
    }
    let refs: Vec<(&str, &Summary)> = loaded.iter().map(|(n, s)| (n.as_str(), s)).collect();
    print!("{}", table(&refs));
    Ok(())
}

fn cmd_eval(args: &EvalArgs) -> Result<()> {
    use crate::eval::{EvalOptions, Trajectory, evaluate, table};
    let est = Trajectory::load(&args.est).context("reading the estimate")?;
    let gt = Trajectory::load(&args.gt).context("reading the ground truth")?;
    let opts = EvalOptions {
        max_diff_s: args.max_diff,
        offset_s: args.offset,
        alignments: args.align.clone(),
        est_z: args.est_z,
        gt_z: args.gt_z,
        distances_m: args.delta.clone(),
        pairs_from_reference: args.pairs_from_reference,
    };
    let report = evaluate(&est, &gt, &opts).with_context(|| {
        format!(
            "evaluating {} against {}",
            args.est.display(),
            args.gt.display()
        )
    })?;
    print!(
        "{}",
        table(
            &report,
            &args.est.display().to_string(),
            &args.gt.display().to_string()
        )
    );
    if let Some(path) = &args.json {
        let text = serde_json::to_string_pretty(&report).context("serialising the report")?;
        std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
        println!("figures in {}", path.display());
    }
    Ok(())
}

/// Log lines to stderr, `RUST_LOG` or warnings and above.
pub fn init_tracing() {
    use tracing_subscriber::Layer as _;
    use tracing_subscriber::layer::SubscriberExt as _;
    use tracing_subscriber::util::SubscriberInitExt as _;
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    // The log's filter is its own (per layer), so the counter of zenoh's access-control
    // refusals sees zenoh's trace events whatever RUST_LOG says.
    let _ = tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_filter(filter),
        )
        .with(canopy_transport::access::refusal_counter())
        .try_init();
}

/// Runs the parsed command line.
pub fn run_cli(cli: Cli) -> Result<()> {
    // Warnings (e.g. the first rejected input of each reason) to stderr; the role processes
    // set theirs up with their process (`process::run_role`).
    if !matches!(cli.command, Command::Role(_)) {
        init_tracing();
    }
    canopy_fusion::runtime::tune_allocator();
    canopy_fusion::runtime::flush_subnormals_to_zero();
    match cli.command {
        Command::Sim(args) => cmd_sim(&args),
        Command::Run(args) => cmd_run(&args),
        Command::Router(args) => cmd_router(&args),
        Command::Role(args) => crate::process::run_role(args),
        Command::Check { scenario } => cmd_check(&scenario),
        Command::Compare { dirs } => cmd_compare(&dirs),
        Command::Eval(args) => cmd_eval(&args),
        Command::Import(args) => cmd_import(&args),
        Command::Team {
            vehicles,
            duration,
            features,
        } => {
            let s = crate::team::team_scenario_with(vehicles, duration, features);
            s.validate().context("the generated team")?;
            print!("{}", s.to_toml_string());
            Ok(())
        }
        Command::Default => {
            print!("{}", Scenario::builtin_default().to_toml_string());
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn output_directory_names_are_tidy() {
        assert_eq!(super::dir_name("default (tree-4)"), "default-tree-4");
        assert_eq!(super::dir_name("central-4"), "central-4");
        assert_eq!(super::dir_name("  ((a b))  "), "a-b");
        assert_eq!(super::dir_name("→"), "run");
    }
}
