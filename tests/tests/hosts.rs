//! A team across hosts (issue #14): scenarios run as `canopy run --host NAME` launchers (one
//! per host) and one `canopy run --monitor`, each its own OS process tree, on this machine:
//!
//! - on loopback addresses standing in for the machines (alpha 127.0.0.1, beta 127.0.0.2, the
//!   monitor on 127.0.0.1), with a copy of the scenario whose addresses are replaced and whose
//!   port bases are moved to free ports (other runs may hold 7450–7462 on a shared machine):
//!   two-hosts, central mode, a monitor killed mid-run, a host without its monitor;
//! - on emulated machines ([`Machines`]: a network namespace each, joined by a bridge, every
//!   process with its own tmpfs on /dev/shm and /tmp, so nothing passes through shared memory
//!   between hosts): `two-hosts.toml` unchanged, and tree-8 over three machines. These FAIL
//!   where namespaces cannot be created, unless `CANOPY_TEST_NO_NAMESPACES=1` (README).
//!
//! Each host runs its own world (its vehicles' sensor input simulated from the scenario's
//! seed), its vehicles and their `shm` links; the links between hosts are zenoh on the
//! endpoints `deploy::resolve_endpoints` derives, and every report reaches the monitor over
//! zenoh (the host launchers relay them).

mod procs;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use procs::{assert_sound, canopy_bin, collect, run, serial, topology};

/// Simulated seconds of the runs: long enough for the two cross-host links to carry every
/// round's deltas both ways for 30 rounds and for the maps to mature (`procs::MATURE_S`).
const DURATION: &str = "30";

/// A wall-clock ceiling per process, only to turn a hang into a failure with the logs (the
/// single-host run of this scenario took 7.6 s wall on a loaded 2-core machine; 40× that).
const HANG: Duration = Duration::from_secs(300);

/// Calls of [`free_ports`] in this test process (two tests must not pick the same base).
static PICKS: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);

/// `n` consecutive free TCP ports on `addr` from a pseudo-random base (checked by binding
/// each), different for every call in this process.
fn free_ports(addr: &str, n: u16) -> u16 {
    for _ in 0..200u32 {
        let pick = PICKS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let seed =
            std::process::id().wrapping_mul(2_654_435_761) ^ pick.wrapping_mul(40_503) ^ nanos;
        let base = 20_000 + (seed % 30_000) as u16;
        let ok = (0..n).all(|k| std::net::TcpListener::bind((addr, base + k)).is_ok());
        if ok {
            return base;
        }
    }
    panic!("no {n} consecutive free ports on {addr}");
}

/// The shipped two-hosts scenario with loopback addresses and free ports, written into `dir`.
fn loopback_copy(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(topology("two-hosts.toml")).expect("two-hosts.toml");
    // Links 1 and 2 (indices in the file) are the net ones: port_base + 0..3 must be free.
    let alpha = free_ports("127.0.0.1", 3);
    let beta = free_ports("127.0.0.2", 3);
    let monitor = free_ports("127.0.0.1", 1);
    let text = text
        .replace(
            "monitor = \"tcp/10.0.0.1:7450\"",
            // A key prefix of its own: no other run's session can match this run's keys.
            &format!(
                "monitor = \"tcp/127.0.0.1:{monitor}\"\nkey_prefix = \"canopy/test-{}-{monitor}\"",
                std::process::id()
            ),
        )
        .replace(
            "address = \"10.0.0.1\"",
            &format!("address = \"127.0.0.1\"\nport_base = {alpha}"),
        )
        .replace(
            "address = \"10.0.0.2\"",
            &format!("address = \"127.0.0.2\"\nport_base = {beta}"),
        );
    assert!(text.contains("127.0.0.2") && text.contains(&format!(":{monitor}")));
    let path = dir.join("two-hosts-loopback.toml");
    std::fs::write(&path, text).expect("write the scenario copy");
    path
}

/// Starts `canopy run SCENARIO ARGS…` here with its output in files under `logs`.
fn start(scenario: &Path, args: &[&str], logs: &Path, label: &str) -> Child {
    start_on(None, scenario, args, logs, label)
}

/// Waits for every child (killing all of them at the hang ceiling) and returns their outputs.
fn wait_all(children: Vec<(String, Child)>, logs: &Path) -> Vec<(String, Output)> {
    let start = Instant::now();
    let mut children: Vec<(String, Child, Option<std::process::ExitStatus>)> =
        children.into_iter().map(|(l, c)| (l, c, None)).collect();
    while children.iter().any(|c| c.2.is_none()) {
        for c in children.iter_mut().filter(|c| c.2.is_none()) {
            c.2 = c.1.try_wait().expect("try_wait");
        }
        if start.elapsed() > HANG {
            for c in children.iter_mut().filter(|c| c.2.is_none()) {
                let _ = c.1.kill();
                let _ = c.1.wait();
            }
            let logs: Vec<String> = children
                .iter()
                .map(|c| read_log(logs, &c.0))
                .collect::<Vec<_>>();
            panic!("the multi-host run hung:\n{}", logs.join("\n"));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    children
        .into_iter()
        .map(|(l, _, st)| {
            let output = Output {
                status: st.expect("waited"),
                stdout: std::fs::read(logs.join(format!("{l}.out"))).unwrap_or_default(),
                stderr: std::fs::read(logs.join(format!("{l}.err"))).unwrap_or_default(),
            };
            (l, output)
        })
        .collect()
}

fn read_log(logs: &Path, label: &str) -> String {
    format!(
        "--- {label} ---\n{}{}",
        std::fs::read_to_string(logs.join(format!("{label}.out"))).unwrap_or_default(),
        std::fs::read_to_string(logs.join(format!("{label}.err"))).unwrap_or_default()
    )
}

/// Processes whose command line mentions `needle` (a run's temporary directory): what a run
/// left behind.
fn processes_mentioning(needle: &str) -> Vec<String> {
    let mut out = Vec::new();
    for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        if pid == std::process::id() {
            continue;
        }
        if let Ok(cmd) = std::fs::read(e.path().join("cmdline")) {
            let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
            if cmd.contains(needle) {
                out.push(format!("{pid}: {cmd}"));
            }
        }
    }
    out
}

/// Emulated machines: one network namespace per host, joined by a bridge in the first one
/// (the host addresses `10.0.0.1`, `10.0.0.2`, … of the shipped scenarios, `/24`), every
/// process of a host started under `unshare --mount` with its own tmpfs on `/dev/shm` and
/// `/tmp`, so iceoryx2 (shared memory and its service files) cannot reach another host: only
/// the zenoh links (TCP over the bridge) do. Removed on drop.
struct Machines {
    ns: Vec<String>,
    /// Machine k's end of its veth to the bridge (k ≥ 1): (namespace, device).
    veths: Vec<(String, String)>,
}

impl Drop for Machines {
    fn drop(&mut self) {
        for ns in &self.ns {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// Opt-out of the namespace tests on machines without network namespaces (not root, no
/// iproute2, a container without CAP_SYS_ADMIN): set to `1` and they pass without running,
/// saying so. Unset, a test that cannot create its namespaces FAILS.
const NO_NAMESPACES: &str = "CANOPY_TEST_NO_NAMESPACES";

fn opted_out() -> bool {
    if std::env::var(NO_NAMESPACES).is_ok_and(|v| v == "1") {
        eprintln!("{NO_NAMESPACES}=1: the multi-host namespace test is opted out (NOT run)");
        return true;
    }
    false
}

fn ip(args: &[&str]) -> Result<(), String> {
    let out = Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("cannot run `ip`: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "`ip {}` failed: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

impl Machines {
    /// `n` machines: namespace k has address 10.0.0.(k+1)/24.
    fn new(n: usize) -> Result<Self, String> {
        let tag = format!("{}", std::process::id() % 100_000);
        let mut m = Self {
            ns: (0..n).map(|k| format!("cnh{tag}m{k}")).collect(),
            veths: Vec::new(),
        };
        for ns in &m.ns {
            ip(&["netns", "add", ns])?;
            ip(&["-n", ns, "link", "set", "lo", "up"])?;
        }
        let first = &m.ns[0];
        ip(&["-n", first, "link", "add", "br0", "type", "bridge"])?;
        ip(&["-n", first, "addr", "add", "10.0.0.1/24", "dev", "br0"])?;
        ip(&["-n", first, "link", "set", "br0", "up"])?;
        for (k, ns) in m.ns.iter().enumerate().skip(1) {
            let (here, there) = (format!("cnh{tag}b{k}"), format!("cnh{tag}v{k}"));
            ip(&["link", "add", &here, "type", "veth", "peer", "name", &there])?;
            ip(&["link", "set", &here, "netns", first])?;
            ip(&["link", "set", &there, "netns", ns])?;
            ip(&["-n", first, "link", "set", &here, "master", "br0"])?;
            ip(&["-n", first, "link", "set", &here, "up"])?;
            let addr = format!("10.0.0.{}/24", k + 1);
            ip(&["-n", ns, "addr", "add", &addr, "dev", &there])?;
            ip(&["-n", ns, "link", "set", &there, "up"])?;
            m.veths.push((ns.clone(), there));
        }
        // A process on a machine: its network namespace and a private /dev/shm and /tmp.
        let probe = m.command(0, Path::new("/bin/true"));
        let st = Command::new(probe.get_program())
            .args(probe.get_args())
            .status()
            .map_err(|e| format!("cannot run `ip netns exec … unshare --mount`: {e}"))?;
        if !st.success() {
            return Err(format!(
                "`ip netns exec … unshare --mount` with tmpfs on /dev/shm and /tmp failed ({st})"
            ));
        }
        Ok(m)
    }

    /// Cuts (`up = false`) or restores machine `k`'s (k ≥ 1) cable to the others.
    fn cable(&self, k: usize, up: bool) {
        let (ns, dev) = &self.veths[k - 1];
        ip(&["-n", ns, "link", "set", dev, if up { "up" } else { "down" }]).expect("ip link set");
    }

    /// `program` on machine `k`.
    fn command(&self, k: usize, program: &Path) -> Command {
        let mut c = Command::new("ip");
        c.args([
            "netns",
            "exec",
            &self.ns[k],
            "unshare",
            "--mount",
            "--",
            "sh",
            "-c",
        ])
        .arg(
            "mount -t tmpfs canopy-shm /dev/shm && mount -t tmpfs canopy-tmp /tmp \
                 && exec \"$0\" \"$@\"",
        )
        .arg(program);
        c
    }
}

/// Starts `canopy run SCENARIO ARGS…` (on machine `k` of `machines` if given) with its output
/// in files under `logs`.
fn start_on(
    machines: Option<(&Machines, usize)>,
    scenario: &Path,
    args: &[&str],
    logs: &Path,
    label: &str,
) -> Child {
    let mut cmd = match machines {
        Some((m, k)) => m.command(k, &canopy_bin()),
        None => Command::new(canopy_bin()),
    };
    cmd.arg("run")
        .arg(scenario)
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .stdin(Stdio::null())
        .stdout(std::fs::File::create(logs.join(format!("{label}.out"))).expect("log file"))
        .stderr(std::fs::File::create(logs.join(format!("{label}.err"))).expect("log file"))
        .spawn()
        .expect("the canopy binary runs")
}

/// The network and mount namespaces of process `pid` once it runs `canopy` (the wrapper
/// `ip netns exec … unshare … sh -c 'exec canopy'` keeps the pid).
fn namespaces_of(pid: u32, wait_for_canopy: bool) -> (String, String) {
    let proc_dir = PathBuf::from(format!("/proc/{pid}"));
    let start = Instant::now();
    while wait_for_canopy
        && std::fs::read_to_string(proc_dir.join("comm")).is_ok_and(|c| c.trim() != "canopy")
    {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "{pid} never became canopy"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    let link = |n: &str| {
        std::fs::read_link(proc_dir.join("ns").join(n))
            .map(|p| p.display().to_string())
            .unwrap_or_default()
    };
    (link("net"), link("mnt"))
}

/// A multi-host run: the monitor (on machine 0 with the first host, as the shipped
/// scenarios place it) and one `--host` launcher per host, waited for; the monitor's outputs.
/// With `machines`, host k runs on machine k and its processes' namespaces are checked to be
/// their own.
fn run_hosts(
    machines: Option<&Machines>,
    scenario: &Path,
    hosts: &[&str],
    duration: &str,
    work: &Path,
) -> procs::Run {
    run_hosts_with(machines, scenario, hosts, duration, work, |_| {})
}

/// [`run_hosts`] with `during(launcher logs directory)` called while the run goes on (the
/// host launchers are not quiet: their progress lines "t = … s of …" are in their logs).
fn run_hosts_with(
    machines: Option<&Machines>,
    scenario: &Path,
    hosts: &[&str],
    duration: &str,
    work: &Path,
    during: impl FnOnce(&Path),
) -> procs::Run {
    let logs = work.join("launchers");
    std::fs::create_dir_all(&logs).unwrap();
    let mon_out = tempfile::tempdir_in(work).expect("monitor output");
    let mon_dir = mon_out.path().display().to_string();
    let on = |k: usize| machines.map(|m| (m, k));
    let mut children = vec![(
        "monitor".to_string(),
        start_on(
            on(0),
            scenario,
            &[
                "--monitor",
                "--quiet",
                "--duration",
                duration,
                "--out",
                &mon_dir,
            ],
            &logs,
            "monitor",
        ),
    )];
    for (k, h) in hosts.iter().enumerate() {
        let out = work.join(h).display().to_string();
        children.push((
            h.to_string(),
            start_on(
                on(k),
                scenario,
                &["--host", h, "--duration", duration, "--out", &out],
                &logs,
                h,
            ),
        ));
    }
    if machines.is_some() {
        // Every host launcher in a network and mount namespace of its own (and not this
        // test's): nothing can pass between them through /dev/shm or /tmp.
        let own = namespaces_of(std::process::id(), false);
        let mut seen = vec![own];
        for (label, c) in children.iter().skip(1) {
            let ns = namespaces_of(c.id(), true);
            assert!(
                seen.iter().all(|s| s.0 != ns.0 && s.1 != ns.1),
                "{label} shares a namespace: {ns:?} among {seen:?}"
            );
            seen.push(ns);
        }
    }
    during(&logs);
    let outputs = wait_all(children, &logs);
    let labels: Vec<&str> = std::iter::once("monitor")
        .chain(hosts.iter().copied())
        .collect();
    let all_logs = labels
        .iter()
        .map(|l| read_log(&logs, l))
        .collect::<Vec<_>>()
        .join("\n");
    for (label, out) in &outputs {
        assert!(
            out.status.success(),
            "{label} failed ({}):\n{all_logs}",
            out.status
        );
    }
    let left = processes_mentioning(&work.display().to_string());
    assert!(left.is_empty(), "processes left behind: {left:?}");
    let mon_output = outputs
        .into_iter()
        .find(|(l, _)| l == "monitor")
        .expect("monitor")
        .1;
    let r = collect(mon_out, mon_output, scenario);
    assert_sound(&r);
    r
}

/// Every `net` link of the run is zenoh and carried fusion traffic both ways on both ends with
/// no transport rejection; every `shm` link too (inside a host).
fn assert_links_carried_traffic(r: &procs::Run) {
    let mut net = 0;
    for row in r.csv("links.csv") {
        if row["t"].parse::<f64>().expect("t") < r.summary.duration_s - 1e-6 {
            continue;
        }
        let (a, b) = row["link"].split_once('-').expect("a-b");
        net += usize::from(row["transport"] == "net");
        for (node, peer) in [(a, b), (b, a)] {
            let end = r
                .checks
                .link_ends
                .iter()
                .find(|l| l.node == node && l.peer == peer)
                .unwrap_or_else(|| panic!("no link end {node}->{peer}"));
            eprintln!(
                "{node}->{peer} ({}): sent {} messages ({} B), received {}",
                row["transport"],
                end.report.sent_messages,
                end.report.sent_bytes,
                end.report.received_messages
            );
            assert!(
                end.report.received_messages > 0 && end.report.sent_messages > 0,
                "{node}->{peer}: {:?}",
                end.report
            );
            assert_eq!(end.report.rejected_transport, 0, "{node}->{peer}");
        }
    }
    assert!(net > 0, "no net link in the run");
}

/// Coverage and information share of every vehicle as in the single-host run of the same
/// scenario (system.rs): features first seen in the last rounds have not crossed the tree yet
/// (coverage ≥ 0.8); share within 0.05 of the reference's information (linearisation
/// differences only).
fn assert_converged(r: &procs::Run, label: &str) {
    for (name, s) in r.print_standing(label) {
        assert!(s.coverage >= 0.8, "{name}: coverage {:.2}", s.coverage);
        assert!(
            (s.share - 1.0).abs() <= 0.05,
            "{name}: information share {:.2}",
            s.share
        );
    }
}

/// The team's map RMSE across hosts against the same scenario run on one host (`canopy run`).
/// Both runs fuse the same sensor data (same seeds) to the same information (share ≈ 1); what
/// differs is when each delta arrives relative to each vehicle's own measurements (process
/// scheduling, the worlds pacing per host under the team's pace), i.e. the linearisation
/// points. `tol`: relative.
fn assert_rmse_close(r: &procs::Run, single: &Path, duration: &str, tol: f64) {
    let one = run(single, &["--quiet", "--duration", duration]);
    assert_sound(&one);
    one.print_standing("one host");
    let (multi_rmse, one_rmse) = (r.summary.team.map_rmse_m, one.summary.team.map_rmse_m);
    let reference = r
        .summary
        .baseline
        .as_ref()
        .map_or(f64::NAN, |b| b.team.map_rmse_m);
    eprintln!(
        "team map RMSE: across hosts {multi_rmse:.3} m, one host {one_rmse:.3} m ({:+.1} %), \
         centralized reference {reference:.3} m",
        100.0 * (multi_rmse / one_rmse - 1.0)
    );
    assert!(
        (multi_rmse - one_rmse).abs() <= tol * one_rmse,
        "team map RMSE {multi_rmse:.3} m across hosts vs {one_rmse:.3} m on one"
    );
}

/// Each host's own logs: a world per host and that host's vehicles only.
fn assert_hosts_ran_their_share(work: &Path, shares: &[(&str, &[&str])], all: &[&str]) {
    for (host, mine) in shares {
        let logs = work.join(host).join("logs");
        assert!(logs.join("world.log").is_file(), "{host}: no world");
        for v in all {
            assert_eq!(
                logs.join(format!("{v}.log")).is_file(),
                mine.contains(v),
                "{host} and {v}"
            );
        }
    }
}

/// Two host launchers and the monitor on loopback addresses (alpha 127.0.0.1, beta 127.0.0.2):
/// the outputs are sound (`assert_sound`: every process of both hosts exited cleanly,
/// confidence against the reference, NEES), both cross-host links are zenoh and carried fusion
/// traffic both ways on every end with no transport rejection, each host ran its own world,
/// no process is left behind, and the team's map RMSE is within 5 % of the same scenario's
/// single-host run (5 %: measured 1.0 % apart; repeated single-host runs of this scenario
/// spread by ~1 %, doubled for two independently scheduled runs, plus slack).
#[test]
fn two_hosts_and_a_monitor_run_the_team() {
    let _g = serial();
    let tmp = tempfile::tempdir().expect("temporary directory");
    let scenario = loopback_copy(tmp.path());
    let r = run_hosts(None, &scenario, &["alpha", "beta"], DURATION, tmp.path());
    let mut names: Vec<&str> = r.checks.processes.iter().map(|p| p.name.as_str()).collect();
    names.sort();
    assert_eq!(
        names,
        ["uav1", "uav2", "uav3", "uav4", "world", "world"],
        "every process of both hosts"
    );
    let all = ["uav1", "uav2", "uav3", "uav4"];
    assert_hosts_ran_their_share(
        tmp.path(),
        &[("alpha", &["uav1", "uav3"]), ("beta", &["uav2", "uav4"])],
        &all,
    );
    assert_links_carried_traffic(&r);
    assert_converged(&r, "two hosts");
    assert_rmse_close(&r, &topology("two-hosts.toml"), DURATION, 0.05);
}

/// The shipped `two-hosts.toml` unchanged (alpha 10.0.0.1 with the monitor, beta 10.0.0.2)
/// on two emulated machines ([`Machines`]: own network namespace, private /dev/shm and /tmp),
/// with the same checks as on loopback. Fails where namespaces cannot be created unless
/// `CANOPY_TEST_NO_NAMESPACES=1`.
#[test]
fn two_hosts_on_machines_with_private_shm() {
    if opted_out() {
        return;
    }
    let _g = serial();
    let machines = Machines::new(2).unwrap_or_else(|e| {
        panic!(
            "cannot emulate two machines: {e}. Run as root with iproute2 and util-linux \
             (unshare), or set {NO_NAMESPACES}=1 to opt out on a machine without namespaces"
        )
    });
    // Not under /tmp: every machine mounts its own tmpfs there.
    let work = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).expect("work directory");
    let scenario = topology("two-hosts.toml");
    let r = run_hosts(
        Some(&machines),
        &scenario,
        &["alpha", "beta"],
        DURATION,
        work.path(),
    );
    let all = ["uav1", "uav2", "uav3", "uav4"];
    assert_hosts_ran_their_share(
        work.path(),
        &[("alpha", &["uav1", "uav3"]), ("beta", &["uav2", "uav4"])],
        &all,
    );
    assert_links_carried_traffic(&r);
    assert_converged(&r, "two machines");
    assert_rmse_close(&r, &scenario, DURATION, 0.05);
}

/// `topologies/central-4.toml` over two hosts on loopback addresses: alpha (127.0.0.1) runs the
/// hub, uav1 and uav2 (their star links stay `shm`), beta (127.0.0.2) runs uav3 and uav4, whose
/// links to the hub become `net`. Free ports as in [`loopback_copy`].
fn central_on_two_hosts(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(topology("central-4.toml")).expect("central-4.toml");
    let mut parts = text.split("[[link]]");
    let mut out = parts.next().expect("head").to_string();
    for p in parts {
        let crosses = p.contains("b = 3\n") || p.contains("b = 4\n");
        out.push_str("[[link]]");
        out.push_str(&if crosses {
            p.replace("transport = \"shm\"", "transport = \"net\"")
        } else {
            p.to_string()
        });
    }
    let alpha = free_ports("127.0.0.1", 5);
    let beta = free_ports("127.0.0.2", 5);
    let monitor = free_ports("127.0.0.1", 1);
    out.push_str(&format!(
        r#"
[zenoh]
mode = "peer"
monitor = "tcp/127.0.0.1:{monitor}"
key_prefix = "canopy/test-{pid}-{monitor}"

[[host]]
name = "alpha"
address = "127.0.0.1"
port_base = {alpha}
vehicles = [1, 2]
hub = true

[[host]]
name = "beta"
address = "127.0.0.2"
port_base = {beta}
vehicles = [3, 4]
"#,
        pid = std::process::id()
    ));
    let path = dir.join("central-two-hosts.toml");
    std::fs::write(&path, out).expect("write the scenario");
    path
}

/// Central mode across two hosts (loopback addresses): the hub runs on alpha and its host's
/// world paces it; uav3 and uav4 reach it over zenoh from beta. Sound, every star link carried
/// traffic both ways, the hub is among alpha's processes, and the team's map RMSE within 5 %
/// of central-4 on one host (the reason of [`two_hosts_and_a_monitor_run_the_team`]'s 5 %).
#[test]
fn central_mode_across_two_hosts() {
    let _g = serial();
    let tmp = tempfile::tempdir().expect("temporary directory");
    let scenario = central_on_two_hosts(tmp.path());
    let r = run_hosts(None, &scenario, &["alpha", "beta"], DURATION, tmp.path());
    assert!(
        tmp.path().join("alpha/logs/hub.log").is_file(),
        "the hub runs on alpha"
    );
    assert!(!tmp.path().join("beta/logs/hub.log").exists());
    assert!(r.checks.processes.iter().any(|p| p.name == "hub"));
    assert_eq!(r.checks.hub_rejected, 0);
    assert_links_carried_traffic(&r);
    assert_converged(&r, "central, two hosts");
    assert_rmse_close(&r, &topology("central-4.toml"), DURATION, 0.05);
}

/// Simulated seconds of the tree-8 run: 60 fusion rounds over a tree of diameter 5, so the
/// features seen in the first half have crossed it (`procs::MATURE_S` judges the rest).
const TREE8_DURATION: &str = "60";

/// `topologies/tree-8.toml` laid out over three machines as in `deploy.rs`'s unit tests: its
/// `shm` pairs kept inside a host (alpha: uav1–uav2; beta: uav3, uav4, uav7; gamma: uav5,
/// uav6, uav8), its three `net` links crossing hosts, their endpoints derived (the explicit
/// loopback `listen` of uav2–uav3 removed).
fn tree8_on_three_hosts(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(topology("tree-8.toml")).expect("tree-8.toml");
    let listen = "listen = \"tcp/127.0.0.1:7461\"";
    assert!(
        text.contains(listen),
        "tree-8.toml changed: update this test"
    );
    let mut text: String = text
        .lines()
        .filter(|l| !l.starts_with(listen))
        .collect::<Vec<_>>()
        .join("\n");
    text.push_str(
        r#"

[zenoh]
mode = "peer"
monitor = "tcp/10.0.0.1:7450"

[[host]]
name = "alpha"
address = "10.0.0.1"
vehicles = [1, 2]

[[host]]
name = "beta"
address = "10.0.0.2"
vehicles = [3, 4, 7]

[[host]]
name = "gamma"
address = "10.0.0.3"
vehicles = [5, 6, 8]
"#,
    );
    let path = dir.join("tree-8-three-hosts.toml");
    std::fs::write(&path, text).expect("write the scenario");
    path
}

/// tree-8 across three emulated machines (own netns, private /dev/shm and /tmp): sound, every
/// link (three `net` across machines, four `shm` inside them) carried traffic both ways, each
/// machine ran its own world and its vehicles only, and the team's map RMSE is within 5 % of
/// tree-8 on one host. Issue #14's acceptance figure is 2 % (measured −1.9 % to +0.8 % over
/// five runs: docs/arch/deploy.md); the test allows 5 % because the single-host figure itself
/// spread 3 % over five runs on a loaded machine (process timing decides when deltas arrive),
/// so a 2 % bound would judge the machine's load, not the deployment. Fails where namespaces
/// cannot be created unless `CANOPY_TEST_NO_NAMESPACES=1`.
#[test]
fn tree8_on_three_machines_with_private_shm() {
    if opted_out() {
        return;
    }
    let _g = serial();
    let machines = Machines::new(3).unwrap_or_else(|e| {
        panic!(
            "cannot emulate three machines: {e}. Run as root with iproute2 and util-linux \
             (unshare), or set {NO_NAMESPACES}=1 to opt out on a machine without namespaces"
        )
    });
    let work = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).expect("work directory");
    let scenario = tree8_on_three_hosts(work.path());
    let r = run_hosts(
        Some(&machines),
        &scenario,
        &["alpha", "beta", "gamma"],
        TREE8_DURATION,
        work.path(),
    );
    let all = [
        "uav1", "uav2", "uav3", "uav4", "uav5", "uav6", "uav7", "uav8",
    ];
    assert_hosts_ran_their_share(
        work.path(),
        &[
            ("alpha", &["uav1", "uav2"]),
            ("beta", &["uav3", "uav4", "uav7"]),
            ("gamma", &["uav5", "uav6", "uav8"]),
        ],
        &all,
    );
    let worlds = r
        .checks
        .processes
        .iter()
        .filter(|p| p.name == "world")
        .count();
    assert_eq!(worlds, 3, "one world per machine");
    assert_links_carried_traffic(&r);
    // Coverage only: over 60 s on a tree of diameter 5 the information share of the vehicles
    // far from a feature's observers is still ~0.8 on one host too (measured 0.79–0.98 single
    // host, 0.77–0.99 across machines), and which vehicles lag depends on scheduling.
    for (name, s) in r.print_standing("tree-8 on three machines") {
        assert!(s.coverage >= 0.8, "{name}: coverage {:.2}", s.coverage);
    }
    assert_rmse_close(&r, &topology("tree-8.toml"), TREE8_DURATION, 0.05);
}

/// A host launcher whose monitor never appears says so, naming the endpoint, within seconds
/// (`--monitor-wait 2`), exits non-zero and starts no process.
#[test]
fn a_host_without_its_monitor_fails_fast_and_clearly() {
    let _g = serial();
    let tmp = tempfile::tempdir().expect("temporary directory");
    let scenario = loopback_copy(tmp.path());
    let text = std::fs::read_to_string(&scenario).unwrap();
    let monitor = text
        .lines()
        .find_map(|l| l.strip_prefix("monitor = \""))
        .and_then(|l| l.split('"').next())
        .expect("monitor endpoint")
        .to_string();
    let logs = tmp.path().join("launchers");
    std::fs::create_dir_all(&logs).unwrap();
    let out = tmp.path().join("alpha").display().to_string();
    let alpha = start(
        &scenario,
        &["--host", "alpha", "--monitor-wait", "2", "--out", &out],
        &logs,
        "alpha",
    );
    let outputs = wait_all(vec![("alpha".into(), alpha)], &logs);
    let (_, o) = &outputs[0];
    let text = read_log(&logs, "alpha");
    assert!(!o.status.success(), "it must fail:\n{text}");
    assert!(
        text.contains(&format!("no monitor answered at {monitor} within 2 s")),
        "{text}"
    );
    assert!(
        !tmp.path().join("alpha/logs").exists(),
        "no process may start without the monitor"
    );
    let left = processes_mentioning(&tmp.path().display().to_string());
    assert!(left.is_empty(), "processes left behind: {left:?}");
}

/// The monitor killed (SIGKILL) mid-run: every host launcher notices that its monitor's zenoh
/// session went away, stops its processes, exits non-zero saying so, and leaves no process
/// behind.
#[test]
fn hosts_end_cleanly_when_the_monitor_dies() {
    let _g = serial();
    let tmp = tempfile::tempdir().expect("temporary directory");
    let scenario = loopback_copy(tmp.path());
    let logs = tmp.path().join("launchers");
    std::fs::create_dir_all(&logs).unwrap();
    let mon = tmp.path().join("monitor").display().to_string();
    // Long enough (simulated) that the run is still going when the monitor is killed.
    let long = "600";
    let mut monitor = start(
        &scenario,
        &["--monitor", "--quiet", "--duration", long, "--out", &mon],
        &logs,
        "monitor",
    );
    let mut hosts = Vec::new();
    for h in ["alpha", "beta"] {
        let out = tmp.path().join(h).display().to_string();
        hosts.push((
            h.to_string(),
            start(
                &scenario,
                &["--host", h, "--duration", long, "--out", &out],
                &logs,
                h,
            ),
        ));
    }
    // Both hosts connected and stepping (their progress lines), then the monitor dies.
    let started = Instant::now();
    while !["alpha", "beta"]
        .iter()
        .all(|h| read_log(&logs, h).contains(" s of 600.0 s"))
    {
        assert!(
            started.elapsed() < HANG,
            "the hosts never got going:\n{}",
            read_log(&logs, "alpha")
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    monitor.kill().expect("SIGKILL the monitor");
    let _ = monitor.wait();
    let outputs = wait_all(hosts, &logs);
    for (h, o) in &outputs {
        let text = read_log(&logs, h);
        assert!(!o.status.success(), "{h} must fail:\n{text}");
        assert!(
            text.contains("lost the monitor at tcp/127.0.0.1:"),
            "{text}"
        );
    }
    let left = processes_mentioning(&tmp.path().display().to_string());
    assert!(left.is_empty(), "processes left behind: {left:?}");
}

/// beta's cable cut for 8 s wall mid-run and restored, on two emulated machines: the monitor
/// and beta each see the other out of reach (control plane), the team pauses on the team's pace
/// and resumes when zenoh reconnects, and the run ends sound (`assert_sound`), every link having
/// carried traffic both ways, every vehicle holding the mature features (coverage ≥ 0.8, as
/// `assert_converged`). Paced at 2× real time so the cut falls inside the run. Fails where
/// namespaces cannot be created unless `CANOPY_TEST_NO_NAMESPACES=1`.
#[test]
fn two_machines_survive_a_cut_cable() {
    if opted_out() {
        return;
    }
    let _g = serial();
    let machines = Machines::new(2).unwrap_or_else(|e| {
        panic!(
            "cannot emulate two machines: {e}. Run as root with iproute2 and util-linux \
             (unshare), or set {NO_NAMESPACES}=1 to opt out on a machine without namespaces"
        )
    });
    let work = tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).expect("work directory");
    let text = std::fs::read_to_string(topology("two-hosts.toml")).expect("two-hosts.toml");
    let text = text.replacen(
        "max_lead_s = 2.0",
        "max_lead_s = 2.0\nreal_time_factor = 2.0",
        1,
    );
    let scenario = work.path().join("two-hosts-paced.toml");
    std::fs::write(&scenario, text).unwrap();
    let r = run_hosts_with(
        Some(&machines),
        &scenario,
        &["alpha", "beta"],
        "60",
        work.path(),
        |logs| {
            let started = Instant::now();
            while !read_log(logs, "beta").contains(" s of 60.0 s") {
                assert!(started.elapsed() < HANG, "{}", read_log(logs, "beta"));
                std::thread::sleep(Duration::from_millis(50));
            }
            machines.cable(1, false);
            eprintln!("beta's cable cut");
            std::thread::sleep(Duration::from_secs(8));
            machines.cable(1, true);
            eprintln!("beta's cable restored");
        },
    );
    let logs = work.path().join("launchers");
    assert!(
        read_log(&logs, "monitor").contains("host beta is out of reach"),
        "the monitor never lost beta: was the cable cut inside the run?\n{}",
        read_log(&logs, "monitor")
    );
    assert!(read_log(&logs, "beta").contains("is out of reach"));
    for l in ["monitor", "beta"] {
        for line in read_log(&logs, l)
            .lines()
            .filter(|x| x.contains("out of reach"))
        {
            eprintln!("{l}: {line}");
        }
    }
    // For the log: the simulated seconds each cross-host link was reported down (the team is
    // paused on the team's pace during most of the cut, so few or none).
    for link in ["uav2-uav3", "uav3-uav4"] {
        let down: Vec<f64> = r
            .link_up(link)
            .into_iter()
            .filter(|(_, up)| !up)
            .map(|(t, _)| t)
            .collect();
        eprintln!("{link}: reported down at t = {down:?}");
    }
    assert_links_carried_traffic(&r);
    for (name, s) in r.print_standing("cut and healed") {
        assert!(s.coverage >= 0.8, "{name}: coverage {:.2}", s.coverage);
    }
}
