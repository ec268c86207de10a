//! zenoh's TLS link under traffic in both directions at once.
//!
//! zenoh-link-tls 1.10.2 read and wrote one rustls `TlsStream` from its RX and TX tasks at
//! the same time through an `UnsafeCell` (eclipse-zenoh/zenoh#2557). rustls does not allow
//! that: while the reader processes a record it swaps the connection state out for
//! `Err(HandshakeNotComplete)`, and a write that lands meanwhile fails with "handshake not
//! complete" and closes the transport. canopy's TLS runs lost their links that way, at random,
//! mid-run (`hosts::central_mode_across_two_hosts_over_tls` failed in CI on the information the
//! lost deltas carried); `third_party/zenoh-link-tls` is the crate with the stream split
//! properly (see its `CANOPY.md`).

use std::path::Path;
use std::time::{Duration, Instant};

use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohLink, ZenohTls, ZenohTransport};
use canopy_transport::{Link, LinkEvent, MessageKind, NodeId, PeerState, SendMeta, WireBytes};

const A: NodeId = 1;
const B: NodeId = 2;
/// Messages each side sends. With the unsound stream the transport broke after 3–52 of them
/// in 5 runs of 5 here (see [`tls_link_carries_traffic_both_ways_at_once`]); 3000 leaves a
/// wide margin.
const MESSAGES: u64 = 3000;
/// 48 kB: one zenoh batch each (a map delta of ~40 features), so both tasks are busy with
/// records all the time.
const PAYLOAD: usize = 48 * 1024;
/// Messages a side may have in flight beyond what it has received from the peer (keeps both
/// directions busy without an unbounded backlog).
const WINDOW: u64 = 32;
/// Generous bound for the link to come up and for each message (loaded 2-core machine).
const TIMEOUT: Duration = Duration::from_secs(30);

fn session(
    dir: &Path,
    me: &str,
    id: NodeId,
    prefix: &str,
    listen: Vec<String>,
    connect: Vec<String>,
) -> ZenohTransport {
    let mut cfg = ZenohConfig::new(prefix, listen, connect);
    cfg.tls = Some(ZenohTls {
        root_ca: dir.join("ca.pem"),
        certificate: dir.join(format!("{me}.pem")),
        private_key: dir.join(format!("{me}.key")),
    });
    cfg.auth = Some(ZenohAuth {
        user: me.into(),
        password: "tls-test".into(),
        accept: vec![
            ("a".into(), "tls-test".into()),
            ("b".into(), "tls-test".into()),
        ],
    });
    ZenohTransport::open(id, cfg).expect("TLS session opens")
}

/// Sends `MESSAGES` payloads (sequence numbers in the header) while receiving the peer's: a
/// message is sent whenever fewer than `WINDOW` of ours are unanswered by the peer's progress,
/// and what has arrived is drained in between. `Err` on a lost peer, a gap or a timeout.
fn exchange(link: &mut ZenohLink) -> Result<(), String> {
    let body = WireBytes(vec![0x5a; PAYLOAD]);
    let (mut sent, mut next) = (0u64, 1u64);
    let mut last_progress = Instant::now();
    while next <= MESSAGES || sent < MESSAGES {
        while let Some(e) = link.poll_event() {
            if e == LinkEvent::PeerDown {
                return Err(format!(
                    "peer down after {} messages received, {sent} sent",
                    next - 1
                ));
            }
        }
        if sent < MESSAGES && sent < next - 1 + WINDOW {
            sent += 1;
            link.send(&SendMeta::new(MessageKind::DDF_DELTA, sent, 0.0), &body)
                .map_err(|e| format!("send {sent}: {e}"))?;
        }
        loop {
            match link.try_recv() {
                Ok(Some(m)) => {
                    let seq = m.header().seq;
                    if seq != next {
                        return Err(format!("message {seq} where {next} was due (lost)"));
                    }
                    next += 1;
                    last_progress = Instant::now();
                }
                Ok(None) => break,
                Err(e) => return Err(format!("receive: {e}")),
            }
        }
        if last_progress.elapsed() > TIMEOUT {
            return Err(format!("nothing for {TIMEOUT:?} after {}", next - 1));
        }
        if sent >= MESSAGES || sent >= next - 1 + WINDOW {
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    Ok(())
}

fn wait_up(link: &mut ZenohLink) {
    let deadline = Instant::now() + TIMEOUT;
    while link.peer_state() != PeerState::Up {
        while link.poll_event().is_some() {}
        assert!(Instant::now() < deadline, "the TLS link did not come up");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Two sessions on one TLS link send each other 3000 messages of 48 kB at the same time (each
/// side on its own thread, sending while it receives): every message arrives, in order, and neither side ever sees
/// its peer go down. With zenoh-link-tls 1.10.2 as published (concurrent reads and writes of
/// one rustls stream) this failed in 5 runs of 5 here ("peer down after …", the zenoh debug
/// log saying "TX task failed: handshake not complete").
#[test]
fn tls_link_carries_traffic_both_ways_at_once() {
    let dir = tempfile::tempdir().expect("temporary directory");
    canopy_transport::test_certs::make_certs(dir.path(), "tls-both-ways", &["a", "b"]);
    let port = canopy_transport::net::free_loopback_port().expect("free port");
    let endpoint = format!("tls/127.0.0.1:{port}");
    let prefix = format!(
        "canopy/{}/tls-both-ways",
        canopy_transport::iceoryx::unique_run_prefix()
    );
    let sa = session(dir.path(), "a", A, &prefix, vec![endpoint.clone()], vec![]);
    let sb = session(dir.path(), "b", B, &prefix, vec![], vec![endpoint]);
    let mut la = sa.link(B, 1 << 20).expect("link a→b");
    let mut lb = sb.link(A, 1 << 20).expect("link b→a");
    wait_up(&mut la);
    wait_up(&mut lb);
    let results = std::thread::scope(|s| {
        let ra = s.spawn(|| exchange(&mut la));
        let rb = s.spawn(|| exchange(&mut lb));
        [ra.join().expect("side a"), rb.join().expect("side b")]
    });
    for (side, r) in ["a (from b)", "b (from a)"].iter().zip(results) {
        if let Err(e) = r {
            panic!("{side}: {e}");
        }
    }
}
