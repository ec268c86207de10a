//! Two separate OS processes exchange over iceoryx2 and over zenoh.
//!
//! The test re-executes its own test binary with `CANOPY_TRANSPORT_PEER` set; in that mode the
//! same test function plays the echo peer (node 2) instead of the driver (node 1). The driver
//! exchanges messages (including a 16.8 MB matrix), kills the peer with SIGKILL, checks that
//! the loss is detected, starts a new peer process and checks that the link works again.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use canopy_transport::codec::PreEncoded;
use canopy_transport::iceoryx::{
    IceoryxConfig, IceoryxLink, remove_run_leftovers, unique_run_prefix,
};
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohTransport};
use canopy_transport::{
    Link, LinkConfig, LinkEvent, MessageKind, SendMeta, WireSymMatrix, WireVector,
};

const ROLE: &str = "CANOPY_TRANSPORT_PEER";
const PREFIX: &str = "CANOPY_TRANSPORT_PREFIX";
const PORTS: &str = "CANOPY_TRANSPORT_PORTS";
/// Generous bound for peer transitions and replies across processes on a loaded 2-core
/// machine (actual figures: milliseconds); nothing asserts a wall-clock bound.
const TIMEOUT: Duration = Duration::from_secs(30);
const STOP_SEQ: u64 = u64::MAX;

fn spawn_peer(test: &str, role: &str, prefix: &str, ports: &str) -> Child {
    Command::new(std::env::current_exe().unwrap())
        .args([test, "--exact", "--nocapture", "--test-threads=1"])
        .env(ROLE, role)
        .env(PREFIX, prefix)
        .env(PORTS, ports)
        .stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap()
}

/// Echo loop of the peer process: returns every message to its sender until told to stop.
fn echo(link: &mut dyn Link) {
    loop {
        let Some(m) = link.recv_timeout(TIMEOUT).unwrap() else {
            panic!("peer: driver went silent");
        };
        let meta = m.header().meta();
        if meta.seq == STOP_SEQ {
            return;
        }
        let body = m.body_bytes().to_vec();
        drop(m);
        link.send(&meta, &PreEncoded(&body)).unwrap();
    }
}

fn wait_event(l: &mut dyn Link, want: LinkEvent) {
    let deadline = Instant::now() + TIMEOUT;
    while Instant::now() < deadline {
        match l.poll_event() {
            Some(e) if e == want => return,
            Some(_) => {}
            None => std::thread::sleep(Duration::from_millis(10)),
        }
    }
    panic!("{want:?} not seen within {TIMEOUT:?}");
}

/// Sends vectors and one 16.8 MB matrix, checks each echo.
fn exchange(link: &mut dyn Link, round: u64) {
    for i in 0..20u64 {
        let v = WireVector::from_slice(&[round as f64, i as f64, 0.5]);
        link.send(&SendMeta::new(MessageKind::DDF_DELTA, i, i as f64), &v)
            .unwrap();
        let m = link.recv_timeout(TIMEOUT).unwrap().expect("echo");
        assert_eq!(m.header().seq, i);
        assert_eq!(m.header().sender, 2);
        assert_eq!(m.decode::<WireVector>().unwrap(), v);
    }
    let big = WireSymMatrix::from_fn(2048, |i, j| (i * 3 + j) as f64 + round as f64);
    link.send(&SendMeta::new(MessageKind::DDF_DELTA, 100, 1.0), &big)
        .unwrap();
    let m = link.recv_timeout(TIMEOUT).unwrap().expect("16 MB echo");
    assert_eq!(m.decode::<WireSymMatrix>().unwrap(), big);
}

fn stop(link: &mut dyn Link) {
    link.send(
        &SendMeta::new(MessageKind::CONTROL, STOP_SEQ, 0.0),
        &WireVector::default(),
    )
    .unwrap();
}

fn drive(link: &mut dyn Link, mut start: impl FnMut() -> Child) {
    let mut peer = start();
    wait_event(link, LinkEvent::PeerUp);
    exchange(link, 1);
    // Crash: SIGKILL, no chance to clean up.
    peer.kill().unwrap();
    peer.wait().unwrap();
    wait_event(link, LinkEvent::PeerDown);
    // Restart.
    let mut peer = start();
    wait_event(link, LinkEvent::PeerUp);
    exchange(link, 2);
    stop(link);
    let status = peer.wait().unwrap();
    assert!(status.success(), "peer process failed: {status}");
    let s = link.stats();
    assert_eq!(s.rejected.total(), 0);
    println!("driver stats: {s:?}");
}

#[test]
fn iceoryx_two_processes_crash_and_restart() {
    const TEST: &str = "iceoryx_two_processes_crash_and_restart";
    if std::env::var(ROLE).as_deref() == Ok("iceoryx") {
        let ix = IceoryxConfig::new(std::env::var(PREFIX).unwrap());
        let mut link = IceoryxLink::connect(LinkConfig::new(2, 1), ix).unwrap();
        echo(&mut link);
        return;
    }
    let prefix = format!("{}mp", unique_run_prefix());
    let _cleanup = Leftovers(prefix.clone());
    let ix = IceoryxConfig::new(prefix.clone());
    let mut link = IceoryxLink::connect(LinkConfig::new(1, 2), ix).unwrap();
    drive(&mut link, || spawn_peer(TEST, "iceoryx", &prefix, ""));
}

/// Removes the run's iceoryx2 leftovers when the test ends, pass or fail (declared before the
/// link so it drops after it).
struct Leftovers(String);

impl Drop for Leftovers {
    fn drop(&mut self) {
        remove_run_leftovers(&self.0);
    }
}

fn zenoh_cfg(prefix: &str, listen: u16, connect: Option<u16>) -> ZenohConfig {
    let mut c = ZenohConfig::new(
        prefix,
        vec![format!("tcp/127.0.0.1:{listen}")],
        connect
            .map(|p| vec![format!("tcp/127.0.0.1:{p}")])
            .unwrap_or_default(),
    );
    c.auth = Some(ZenohAuth {
        user: "canopy".into(),
        password: "multi-process-test".into(),
        accept: vec![("canopy".into(), "multi-process-test".into())],
    });
    c
}

fn free_port() -> u16 {
    canopy_transport::net::free_loopback_port().expect("a free loopback port")
}

#[test]
fn zenoh_two_processes_crash_and_restart() {
    const TEST: &str = "zenoh_two_processes_crash_and_restart";
    if std::env::var(ROLE).as_deref() == Ok("zenoh") {
        let prefix = std::env::var(PREFIX).unwrap();
        let ports: Vec<u16> = std::env::var(PORTS)
            .unwrap()
            .split(',')
            .map(|p| p.parse().unwrap())
            .collect();
        let t = ZenohTransport::open(2, zenoh_cfg(&prefix, ports[1], Some(ports[0]))).unwrap();
        let mut link = t.link(1, 64 << 20).unwrap();
        echo(&mut link);
        // Keep the session open until the driver has seen our last reply.
        std::thread::sleep(Duration::from_millis(200));
        return;
    }
    let prefix = format!("canopy/{}/mp", unique_run_prefix());
    let (p1, p2) = (free_port(), free_port());
    let t = ZenohTransport::open(1, zenoh_cfg(&prefix, p1, None)).unwrap();
    let mut link = t.link(2, 64 << 20).unwrap();
    let ports = format!("{p1},{p2}");
    drive(&mut link, || spawn_peer(TEST, "zenoh", &prefix, &ports));
}
