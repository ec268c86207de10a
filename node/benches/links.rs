//! Link benchmark: canopy's links against the raw middleware, side by side in one run; prints
//! one table.
//!
//! - iceoryx2 latency: ping-pong between threads, each end with its own iceoryx2 node; one-way
//!   latency = round trip / 2, median. Raw = `ipc::Service` publish-subscribe of the same bytes
//!   (`loan_slice_uninit` + copy, event notification, listener wait, echo by copying the
//!   received sample into a new one). canopy = `IceoryxLink` with a `WireBytesRef` body
//!   (encoded straight into the sample with the CRC, CRC-checked on receipt, decoded in place,
//!   echoed by encoding the borrowed bytes into a new sample). Raw and canopy round trips
//!   alternate one by one so load on the shared machine hits both alike; both use the same
//!   sample-pool shape.
//! - zenoh throughput: one thread puts K messages, another receives them, two sessions over
//!   TCP loopback; throughput = bytes / (first put → last receive), median of the rounds.
//!   Raw = `publisher.put` of a pre-built `ZBytes` (reference-counted: no copy per put) with
//!   `CongestionControl::Block`, the subscriber callback only reading the length (the
//!   acceptance baseline). canopy = `ZenohLink::send` (encode + CRC into a fresh buffer) and
//!   `recv_timeout` (queue hand-off to the application thread, defragment + CRC, in-place
//!   decode). The last column is raw with a subscriber that makes the payload contiguous
//!   (`to_bytes`), for context.
//!
//! Run: `cargo bench -p canopy-transport --bench links` (`-- --quick` for fewer iterations,
//! `-- --only=N` for one payload).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

use canopy_transport::iceoryx::{
    IceoryxConfig, IceoryxLink, remove_run_leftovers, unique_run_prefix,
};
use canopy_transport::net::{ZenohConfig, ZenohTransport};
use canopy_transport::{Link, LinkConfig, MessageKind, SendMeta, WireBytesRef};
use iceoryx2::prelude::*;
use zenoh::Wait;
use zenoh::qos::CongestionControl;

const KB: usize = 1024;
const MB: usize = 1024 * 1024;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

// ------------------------------------------------------------------ iceoryx2 raw

fn iox_config(prefix: &str) -> Config {
    let mut c = Config::default();
    c.global.prefix = FileName::new(format!("{prefix}_").as_bytes()).unwrap();
    c
}

/// One side of the raw ping-pong: publishes on `out`, listens on `inp`.
struct RawSide {
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, [u8], ()>,
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, [u8], ()>,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
    _node: Node<ipc::Service>,
}

fn raw_side(prefix: &str, out: &str, inp: &str, max: usize) -> RawSide {
    let node = NodeBuilder::new()
        .config(&iox_config(prefix))
        .create::<ipc::Service>()
        .unwrap();
    let open = |name: &str| {
        node.service_builder(&ServiceName::new(name).unwrap())
            .publish_subscribe::<[u8]>()
            .max_publishers(2)
            .max_subscribers(2)
            .history_size(0)
            .subscriber_max_buffer_size(4)
            .open_or_create()
            .unwrap()
    };
    let ev = |name: &str| {
        node.service_builder(&ServiceName::new(&format!("{name}/ev")).unwrap())
            .event()
            .open_or_create()
            .unwrap()
    };
    let (so, si) = (open(out), open(inp));
    let (eo, ei) = (ev(out), ev(inp));
    RawSide {
        publisher: so
            .publisher_builder()
            .initial_max_slice_len(max)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .unwrap(),
        subscriber: si.subscriber_builder().create().unwrap(),
        notifier: eo.notifier_builder().create().unwrap(),
        listener: ei.listener_builder().create().unwrap(),
        _node: node,
    }
}

impl RawSide {
    fn send(&self, bytes: &[u8]) {
        let s = self.publisher.loan_slice_uninit(bytes.len()).unwrap();
        s.write_from_slice(bytes).send().unwrap();
        self.notifier.notify().unwrap();
    }
    fn recv_and<R>(&self, f: impl FnOnce(&[u8]) -> R) -> R {
        loop {
            if let Some(s) = self.subscriber.receive().unwrap() {
                return f(s.payload());
            }
            self.listener
                .timed_wait(|_| {}, Duration::from_secs(5))
                .unwrap();
        }
    }
}

/// Raw and canopy iceoryx2 round trips, interleaved one by one (so load on the shared machine
/// hits both alike); returns one-way latencies (µs) of (raw, canopy).
fn iox_both(size: usize, iters: usize) -> (Vec<f64>, Vec<f64>) {
    let prefix = format!("{}bio", unique_run_prefix());
    let mut ix = IceoryxConfig::new(format!("{prefix}c"));
    // Same sample pool shape as the raw side (buffer 4, 2 borrowed), so both cycle through the
    // same amount of shared memory.
    ix.subscriber_buffer = 4;
    ix.max_borrowed = 2;
    let max = size as u64 + 64;
    let ready = Arc::new(Barrier::new(3));
    let (p2, r2) = (prefix.clone(), ready.clone());
    let raw_echo = std::thread::spawn(move || {
        let side = raw_side(&format!("{p2}r"), "b2a", "a2b", size);
        r2.wait();
        for _ in 0..iters + 1 {
            side.recv_and(|p| side.send(p));
        }
    });
    let (ix2, r3) = (ix.clone(), ready.clone());
    let canopy_echo = std::thread::spawn(move || {
        let mut l =
            IceoryxLink::connect(LinkConfig::new(2, 1).with_max_body_len(max), ix2).unwrap();
        r3.wait();
        for _ in 0..iters + 1 {
            let m = l
                .recv_timeout(Duration::from_secs(10))
                .unwrap()
                .expect("ping");
            let body: WireBytesRef<'_> = m.decode().unwrap();
            l.send(&m.header().meta(), &body).unwrap();
        }
    });
    let side = raw_side(&format!("{prefix}r"), "a2b", "b2a", size);
    let mut l = IceoryxLink::connect(LinkConfig::new(1, 2).with_max_body_len(max), ix).unwrap();
    ready.wait();
    // Let both ends discover each other's ports before timing.
    std::thread::sleep(Duration::from_millis(100));
    let payload = vec![0x5Au8; size];
    let (mut raw, mut can) = (Vec::with_capacity(iters), Vec::with_capacity(iters));
    for k in 0..iters + 1 {
        let t0 = Instant::now();
        side.send(&payload);
        side.recv_and(|p| assert_eq!(p.len(), size));
        let t_raw = t0.elapsed().as_secs_f64() * 1e6 / 2.0;

        let t0 = Instant::now();
        l.send(
            &SendMeta::new(MessageKind::DDF_DELTA, k as u64, 0.0),
            &WireBytesRef(&payload),
        )
        .unwrap();
        let m = l
            .recv_timeout(Duration::from_secs(10))
            .unwrap()
            .expect("pong");
        let body: WireBytesRef<'_> = m.decode().unwrap();
        assert_eq!(body.0.len(), size);
        drop(m);
        let t_can = t0.elapsed().as_secs_f64() * 1e6 / 2.0;
        // The first round trip of each warms up the sample pools.
        if k > 0 {
            raw.push(t_raw);
            can.push(t_can);
        }
    }
    raw_echo.join().unwrap();
    canopy_echo.join().unwrap();
    drop((side, l));
    remove_run_leftovers(&format!("{prefix}r"));
    remove_run_leftovers(&format!("{prefix}c"));
    (raw, can)
}

// ------------------------------------------------------------------ zenoh

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn zenoh_pair(prefix: &str) -> (ZenohTransport, ZenohTransport) {
    let p = free_port();
    let a = ZenohTransport::open(
        1,
        ZenohConfig::new(prefix, vec![format!("tcp/127.0.0.1:{p}")], vec![]),
    )
    .unwrap();
    let mut cb = ZenohConfig::new(prefix, vec![], vec![format!("tcp/127.0.0.1:{p}")]);
    // The throughput run sends bursts of up to 20,000 messages; a queue that holds a burst keeps
    // the receiving link from dropping (the default 1024 drops and counts the excess).
    cb.receive_queue = 1 << 16;
    let b = ZenohTransport::open(2, cb).unwrap();
    (a, b)
}

/// Raw zenoh put/subscribe throughput (MB/s) on its own pair of sessions. With `touch`, the
/// subscriber makes the payload contiguous (`to_bytes`, as a consumer that decodes must) instead
/// of only reading its length.
fn zenoh_raw(size: usize, count: usize, touch: bool) -> f64 {
    let cfg = |listen: Vec<String>, connect: Vec<String>| {
        let mut c = zenoh::Config::default();
        let json = |v: &[String]| {
            format!(
                "[{}]",
                v.iter()
                    .map(|s| format!("\"{s}\""))
                    .collect::<Vec<_>>()
                    .join(",")
            )
        };
        c.insert_json5("mode", "\"peer\"").unwrap();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        c.insert_json5("scouting/gossip/enabled", "false").unwrap();
        c.insert_json5("listen/endpoints", &json(&listen)).unwrap();
        c.insert_json5("connect/endpoints", &json(&connect))
            .unwrap();
        c
    };
    let p = free_port();
    let ep = format!("tcp/127.0.0.1:{p}");
    let sa = zenoh::open(cfg(vec![ep.clone()], vec![])).wait().unwrap();
    let sb = zenoh::open(cfg(vec![], vec![ep])).wait().unwrap();
    let key = format!("bench/{}/raw", unique_run_prefix());
    let (tx, rx) = mpsc::channel::<Instant>();
    let seen = AtomicUsize::new(0);
    let bytes = AtomicUsize::new(0);
    let tx = std::sync::Mutex::new(tx);
    let _sub = sb
        .declare_subscriber(&key)
        .callback(move |s| {
            let len = if touch {
                std::hint::black_box(s.payload().to_bytes()).len()
            } else {
                s.payload().len()
            };
            let b = bytes.fetch_add(len, Ordering::Relaxed) + len;
            if seen.fetch_add(1, Ordering::Relaxed) + 1 == count {
                assert_eq!(b, size * count);
                let _ = tx.lock().unwrap().send(Instant::now());
            }
        })
        .wait()
        .unwrap();
    let publisher = sa
        .declare_publisher(&key)
        .congestion_control(CongestionControl::Block)
        .wait()
        .unwrap();
    // Wait until the subscriber is known to the publishing session.
    while !publisher.matching_status().wait().unwrap().matching() {
        std::thread::sleep(Duration::from_millis(10));
    }
    let payload = zenoh::bytes::ZBytes::from(vec![0x5Au8; size]);
    let t0 = Instant::now();
    for _ in 0..count {
        publisher.put(payload.clone()).wait().unwrap();
    }
    let t1 = rx.recv_timeout(Duration::from_secs(120)).unwrap();
    let mbps = (size * count) as f64 / (t1 - t0).as_secs_f64() / 1e6;
    drop(publisher);
    sa.close().wait().unwrap();
    sb.close().wait().unwrap();
    mbps
}

/// canopy `ZenohLink` throughput (MB/s).
fn zenoh_canopy(size: usize, count: usize) -> f64 {
    let prefix = format!("bench/{}", unique_run_prefix());
    let (ta, tb) = zenoh_pair(&prefix);
    let max = size as u64 + 64;
    let mut la = ta.link(2, max).unwrap();
    let mut lb = tb.link(1, max).unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while la.peer_state() != canopy_transport::PeerState::Up
        || lb.peer_state() != canopy_transport::PeerState::Up
    {
        la.poll_event();
        lb.poll_event();
        assert!(Instant::now() < deadline, "zenoh peers never met");
        std::thread::sleep(Duration::from_millis(10));
    }
    let receiver = std::thread::spawn(move || {
        let mut bytes = 0usize;
        for _ in 0..count {
            let m = lb
                .recv_timeout(Duration::from_secs(60))
                .unwrap()
                .expect("message");
            let b: WireBytesRef<'_> = m.decode().unwrap();
            bytes += b.0.len();
        }
        assert_eq!(bytes, size * count);
        (Instant::now(), lb)
    });
    let payload = vec![0x5Au8; size];
    let t0 = Instant::now();
    for k in 0..count {
        la.send(
            &SendMeta::new(MessageKind::DDF_DELTA, k as u64, 0.0),
            &WireBytesRef(&payload),
        )
        .unwrap();
    }
    let (t1, lb) = receiver.join().unwrap();
    let mbps = (size * count) as f64 / (t1 - t0).as_secs_f64() / 1e6;
    drop((la, lb));
    ta.close().unwrap();
    tb.close().unwrap();
    mbps
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    // Thread placement on a shared 2-core machine changes a whole round (fresh threads per
    // round), so many short rounds give a steadier median than a few long ones.
    let rounds = if quick { 1 } else { 7 };
    // (payload, ping-pong iterations per round, zenoh messages per round)
    let cases: [(usize, usize, usize); 3] = if quick {
        [(KB, 300, 3000), (MB, 40, 100), (16 * MB, 8, 8)]
    } else {
        [(KB, 500, 10000), (MB, 60, 200), (16 * MB, 12, 12)]
    };
    println!("canopy-transport link benchmark ({rounds} alternating rounds per cell)");
    println!(
        "| payload | iox raw p50 µs | iox canopy p50 µs | ratio (≤ 1.5) | zenoh raw MB/s | zenoh canopy MB/s | ratio (≥ 0.7) | zenoh raw+to_bytes MB/s |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    // `--only=N` restricts the run to the N-th payload (0 = 1 KB, 1 = 1 MB, 2 = 16 MB).
    let only: Option<usize> =
        std::env::args().find_map(|a| a.strip_prefix("--only=").and_then(|v| v.parse().ok()));
    for (i, (size, iters, count)) in cases.into_iter().enumerate() {
        if only.is_some_and(|o| o != i) {
            continue;
        }
        let (mut raw, mut can) = (Vec::new(), Vec::new());
        let (mut zraw, mut zcan, mut ztouch) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..rounds {
            let (r, c) = iox_both(size, iters);
            raw.extend(r);
            can.extend(c);
            zraw.push(zenoh_raw(size, count, false));
            zcan.push(zenoh_canopy(size, count));
            ztouch.push(zenoh_raw(size, count, true));
        }
        let (r, c) = (median(&mut raw), median(&mut can));
        let (zr, zc, zt) = (median(&mut zraw), median(&mut zcan), median(&mut ztouch));
        let label = if size >= MB {
            format!("{} MB", size / MB)
        } else {
            format!("{} KB", size / KB)
        };
        println!(
            "| {label} | {r:.1} | {c:.1} | {:.2} | {zr:.0} | {zc:.0} | {:.2} | {zt:.0} |",
            c / r,
            zc / zr
        );
    }
}
