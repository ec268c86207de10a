//! Link benchmark: canopy's production link path against the raw middleware, side by side in
//! one run; prints two markdown tables (`scripts/bench.sh` parses them: keep headings and
//! column order).
//!
//! **Production path** (first table, the acceptance figures): what every fusion link of
//! `canopy run` is — an `IceoryxLink` (default `IceoryxConfig`: subscriber buffer 16, 4 lent
//! samples, 64 MiB body limit) or a `ZenohLink` (default `ZenohConfig`: receive queue 1,024)
//! boxed under the fault layer with the scenario's default (empty) fault spec, carrying real
//! channel-filter deltas (`DdfMessage::Delta` with a dense map information: every 3×3 block of
//! the upper block triangle non-zero, as a SLAM map's information is) sent with
//! `wire::send_ddf` and decoded with `wire::decode_ddf`, exactly as the vehicle does.
//! The raw baselines do the same application work the way the middleware's own examples do:
//! serialise the same message with bincode (same configuration, same bytes), publish it, and
//! deserialise it on receipt.
//! - iceoryx2 latency: ping-pong between threads, each end with its own iceoryx2 node; one-way
//!   latency = round trip / 2, median. Raw = `ipc::Service` publish-subscribe of `[u8]`
//!   (`loan_slice_uninit` + `write_from_slice` of the serialised message, event notification,
//!   listener wait, deserialise from the sample; the echo deserialises and serialises again).
//! - zenoh throughput: one thread sends K messages, another receives them, two sessions over
//!   TCP loopback; throughput = payload bytes delivered / (first send → last receipt), median of
//!   the rounds; the ratio is the median of the per-round ratios. Raw = `publisher.put` of the serialised message with `CongestionControl::Block`,
//!   deserialised in the subscriber callback (as zenoh's `z_sub` processes in its callback).
//!   canopy's receive queue is the production 1,024: messages it drops on overflow are not
//!   delivered and not counted (the "dropped" column says how many).
//!
//! **Transport only** (second table, secondary): opaque byte payloads (`WireBytesRef`, decoded
//! in place) to isolate what the links add over the raw middleware moving the same bytes (raw
//! iceoryx2 echoes by copying the sample into a new one; raw zenoh re-puts a reference-counted
//! buffer and its callback reads only the length, as `z_pub_thr` / `z_sub_thr` do). "production"
//! = the fault layer and production queue sizes as above; "bare" = the flattering rows this
//! bench printed before: a bare link, the iceoryx2 sample pool shaped like raw's, a 65,536-message
//! zenoh queue.
//!
//! Every iceoryx2 series runs interleaved with the others one round trip at a time, and every
//! zenoh series once per round, so load on the shared machine hits all alike.
//!
//! Run: `cargo bench -p canopy-node --bench links` (`-- --quick` for fewer iterations,
//! `-- --only=N` for one payload: 0 = 1 KB, 1 = 1 MB, 2 = 16 MB; `-- --iox` or `-- --zenoh`
//! for one middleware).

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Barrier};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use canopy_fusion::ddf::{Body, DdfMessage, Header as DdfHeader};
use canopy_fusion::info::MapInformation;
use canopy_node::network::FaultSpec;
use canopy_node::wire::{Compression, decode_ddf, send_ddf};
use canopy_transport::codec::{self, DEFAULT_MAX_BODY_LEN};
use canopy_transport::fault::{Clock, FaultyLink, ManualClock};
use canopy_transport::iceoryx::{
    IceoryxConfig, IceoryxLink, remove_run_leftovers, unique_run_prefix,
};
use canopy_transport::net::{ZenohConfig, ZenohTransport};
use canopy_transport::{Link, LinkConfig, MessageKind, PeerState, SendMeta, WireBytesRef};
use faer::{Col, Mat};
use iceoryx2::prelude::*;
use nalgebra::Vector3;
use zenoh::Wait;
use zenoh::bytes::ZBytes;
use zenoh::qos::CongestionControl;

const KB: usize = 1024;
const MB: usize = 1024 * 1024;
/// Generous bound for one message to arrive (a loaded 2-core machine).
const RECV_TIMEOUT: Duration = Duration::from_secs(60);

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

// ------------------------------------------------------------------ payloads

/// A channel-filter delta over `nf` features with every 3×3 block of the upper block triangle
/// non-zero (SLAM map information is dense) and values not exact in f32 (every block is sent
/// as f64, as a real delta's are).
fn ddf_delta(nf: usize) -> DdfMessage {
    let n = 3 * nf;
    let matrix = Mat::from_fn(n, n, |i, j| {
        let (a, b) = (i.min(j), i.max(j));
        if a == b {
            1e3 + a as f64 * 0.1
        } else {
            std::f64::consts::PI / (1.0 + (b - a) as f64)
        }
    });
    let info = MapInformation {
        ids: (0..nf as u64).map(|k| 1000 + 7 * k).collect(),
        origin: Vector3::new(1.5, -2.5, 0.25),
        matrix,
        vector: Col::from_fn(n, |i| (i as f64).sqrt() * 1.1),
    };
    DdfMessage {
        header: DdfHeader {
            from_epoch: 11,
            to_epoch: Some(22),
            challenge: 0,
            echo_epoch: 22,
            echo: 0,
        },
        body: Body::Delta { seq: 1, info },
    }
}

fn ddf_len(msg: &DdfMessage) -> usize {
    codec::body_len(msg).unwrap() as usize
}

/// The dense delta whose encoded body is closest to `target` bytes, and that length.
fn ddf_of_size(target: usize) -> (DdfMessage, usize) {
    // The body grows like 76·nf²/2: bisect on nf.
    let (mut lo, mut hi) = (1usize, 4096usize);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if ddf_len(&ddf_delta(mid)) < target {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    let above = ddf_delta(lo);
    let below = ddf_delta(lo.saturating_sub(1).max(1));
    let (la, lb) = (ddf_len(&above), ddf_len(&below));
    if la.abs_diff(target) <= lb.abs_diff(target) {
        (above, la)
    } else {
        (below, lb)
    }
}

fn bincode_encode(msg: &DdfMessage) -> Vec<u8> {
    bincode::serde::encode_to_vec(msg, bincode::config::standard()).unwrap()
}

fn bincode_decode(bytes: &[u8]) -> DdfMessage {
    let (m, used): (DdfMessage, usize) =
        bincode::serde::decode_from_slice(bytes, bincode::config::standard()).unwrap();
    assert_eq!(used, bytes.len());
    m
}

/// The production fault layer over `inner`: the scenario's default fault spec (no fault).
fn production(inner: Box<dyn Link>, seed: u64) -> FaultyLink<Box<dyn Link>> {
    let clock: Arc<dyn Clock> = Arc::new(ManualClock::new(0.0));
    FaultyLink::new(inner, FaultSpec::default().to_transport(seed, &[]), clock).unwrap()
}

// ------------------------------------------------------------------ iceoryx2

fn iox_config(prefix: &str) -> Config {
    let mut c = Config::default();
    c.global.prefix = FileName::new(format!("{prefix}_").as_bytes()).unwrap();
    c
}

/// One side of a raw ping-pong: publishes on `out`, listens on `inp`.
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

/// What a ping-pong series carries.
#[derive(Clone, Copy)]
enum Work<'a> {
    /// A DDF delta: serialised, sent, deserialised at each end.
    Ddf(&'a DdfMessage),
    /// Opaque bytes.
    Bytes(&'a [u8]),
}

/// One ping-pong series: `ping` does one round trip from this thread; its echo runs on its own
/// thread.
struct Series<'a> {
    ping: Box<dyn FnMut(u64) + 'a>,
    echo: JoinHandle<()>,
    one_way_us: Vec<f64>,
}

fn canopy_ping(link: &mut dyn Link, k: u64, work: Work<'_>) {
    match work {
        Work::Ddf(msg) => {
            send_ddf(link, 0.0, msg, Compression::None).unwrap();
            let m = link.recv_timeout(RECV_TIMEOUT).unwrap().expect("pong");
            let back = decode_ddf(&m).expect("a DDF kind").unwrap();
            std::hint::black_box(back);
        }
        Work::Bytes(payload) => {
            link.send(
                &SendMeta::new(MessageKind::DDF_DELTA, k, 0.0),
                &WireBytesRef(payload),
            )
            .unwrap();
            let m = link.recv_timeout(RECV_TIMEOUT).unwrap().expect("pong");
            let body: WireBytesRef<'_> = m.decode().unwrap();
            assert_eq!(body.0.len(), payload.len());
        }
    }
}

fn canopy_echo(mut link: impl Link, iters: usize, ddf: bool, ready: Arc<Barrier>) {
    ready.wait();
    for _ in 0..iters {
        let m = link.recv_timeout(RECV_TIMEOUT).unwrap().expect("ping");
        if ddf {
            let msg = decode_ddf(&m).expect("a DDF kind").unwrap();
            drop(m);
            send_ddf(&mut link, 0.0, &msg, Compression::None).unwrap();
        } else {
            let body: WireBytesRef<'_> = m.decode().unwrap();
            link.send(&m.header().meta(), &body).unwrap();
        }
    }
}

fn raw_ping(side: &RawSide, work: Work<'_>) {
    match work {
        Work::Ddf(msg) => {
            side.send(&bincode_encode(msg));
            std::hint::black_box(side.recv_and(bincode_decode));
        }
        Work::Bytes(payload) => {
            side.send(payload);
            side.recv_and(|p| assert_eq!(p.len(), payload.len()));
        }
    }
}

fn raw_echo(side: RawSide, iters: usize, ddf: bool, ready: Arc<Barrier>) {
    ready.wait();
    for _ in 0..iters {
        if ddf {
            let msg = side.recv_and(bincode_decode);
            side.send(&bincode_encode(&msg));
        } else {
            side.recv_and(|p| side.send(p));
        }
    }
}

/// iceoryx2 series for one payload, interleaved one round trip at a time; returns one-way
/// latencies (µs) of: DDF raw, DDF production, bytes raw, bytes production, bytes bare.
fn iox_round(ddf: &DdfMessage, ddf_bytes: usize, size: usize, iters: usize) -> [Vec<f64>; 5] {
    let prefix = format!("{}bio", unique_run_prefix());
    let payload = vec![0x5Au8; size];
    let total = iters + 1; // the first round trip of each warms up the sample pools
    let ready = Arc::new(Barrier::new(6));
    let prefixes: Vec<String> = (0..5).map(|i| format!("{prefix}{i}")).collect();
    let raw_max = [ddf_bytes, 0, size, 0, 0];
    let mut series: Vec<Series<'_>> = Vec::new();
    for (i, p) in prefixes.iter().enumerate() {
        let is_ddf = i < 2;
        let work = if is_ddf {
            Work::Ddf(ddf)
        } else {
            Work::Bytes(&payload)
        };
        let r = ready.clone();
        let p2 = p.clone();
        let s = match i {
            // Raw iceoryx2.
            0 | 2 => {
                let max = raw_max[i];
                // This end first: two ends creating the same services at once can see one
                // half-created (iceoryx2 `open_or_create` → `DoesNotExist`).
                let side = raw_side(p, "a2b", "b2a", max);
                let echo = std::thread::spawn(move || {
                    raw_echo(raw_side(&p2, "b2a", "a2b", max), total, is_ddf, r)
                });
                Series {
                    ping: Box::new(move |_| raw_ping(&side, work)),
                    echo,
                    one_way_us: Vec::new(),
                }
            }
            // Production path: default IceoryxConfig and body limit, fault layer.
            1 | 3 => {
                let ix = IceoryxConfig::new(p.clone());
                let l = IceoryxLink::connect(LinkConfig::new(1, 2), ix.clone()).unwrap();
                let mut link = production(Box::new(l), 1);
                let l2 = IceoryxLink::connect(LinkConfig::new(2, 1), ix).unwrap();
                let echo = std::thread::spawn(move || {
                    canopy_echo(production(Box::new(l2), 2), total, is_ddf, r)
                });
                Series {
                    ping: Box::new(move |k| canopy_ping(&mut link, k, work)),
                    echo,
                    one_way_us: Vec::new(),
                }
            }
            // Bare link, sample pool shaped like raw's (the rows this bench printed before).
            _ => {
                let mut ix = IceoryxConfig::new(p.clone());
                ix.subscriber_buffer = 4;
                ix.max_borrowed = 2;
                let max = size as u64 + 64;
                let mut link =
                    IceoryxLink::connect(LinkConfig::new(1, 2).with_max_body_len(max), ix.clone())
                        .unwrap();
                let l2 =
                    IceoryxLink::connect(LinkConfig::new(2, 1).with_max_body_len(max), ix).unwrap();
                let echo = std::thread::spawn(move || canopy_echo(l2, total, false, r));
                Series {
                    ping: Box::new(move |k| canopy_ping(&mut link, k, work)),
                    echo,
                    one_way_us: Vec::new(),
                }
            }
        };
        series.push(s);
    }
    ready.wait();
    // Let every end discover its peer's ports before timing.
    std::thread::sleep(Duration::from_millis(100));
    for k in 0..total {
        for s in &mut series {
            let t0 = Instant::now();
            (s.ping)(k as u64);
            let us = t0.elapsed().as_secs_f64() * 1e6 / 2.0;
            if k > 0 {
                s.one_way_us.push(us);
            }
        }
    }
    let out = series.map_results();
    for p in &prefixes {
        remove_run_leftovers(p);
    }
    out
}

trait JoinSeries {
    fn map_results(self) -> [Vec<f64>; 5];
}

impl JoinSeries for Vec<Series<'_>> {
    fn map_results(self) -> [Vec<f64>; 5] {
        let mut out: [Vec<f64>; 5] = Default::default();
        for (i, s) in self.into_iter().enumerate() {
            drop(s.ping);
            s.echo.join().unwrap();
            out[i] = s.one_way_us;
        }
        out
    }
}

// ------------------------------------------------------------------ zenoh

fn free_port() -> u16 {
    canopy_transport::net::free_loopback_port().expect("a free loopback port")
}

/// Payload bytes delivered per second (MB/s, 10⁶ bytes) and messages not delivered.
#[derive(Clone, Copy)]
struct Throughput {
    mbps: f64,
    dropped: usize,
}

/// Raw zenoh: `count` puts, received by a callback; DDF messages are serialised per put and
/// deserialised in the callback.
fn zenoh_raw(work: Work<'_>, count: usize) -> Throughput {
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
    let ddf = matches!(work, Work::Ddf(_));
    let _sub = sb
        .declare_subscriber(&key)
        .callback(move |s| {
            let len = if ddf {
                let b = s.payload().to_bytes();
                std::hint::black_box(bincode_decode(&b));
                b.len()
            } else {
                s.payload().len()
            };
            bytes.fetch_add(len, Ordering::Relaxed);
            if seen.fetch_add(1, Ordering::Relaxed) + 1 == count {
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
    let (per_msg, t0) = match work {
        Work::Ddf(msg) => {
            let t0 = Instant::now();
            for _ in 0..count {
                publisher
                    .put(ZBytes::from(bincode_encode(msg)))
                    .wait()
                    .unwrap();
            }
            (bincode_encode(msg).len(), t0)
        }
        Work::Bytes(b) => {
            let payload = ZBytes::from(b.to_vec());
            let t0 = Instant::now();
            for _ in 0..count {
                publisher.put(payload.clone()).wait().unwrap();
            }
            (b.len(), t0)
        }
    };
    let t1 = rx.recv_timeout(Duration::from_secs(300)).unwrap();
    drop(publisher);
    sa.close().wait().unwrap();
    sb.close().wait().unwrap();
    Throughput {
        mbps: (per_msg * count) as f64 / (t1 - t0).as_secs_f64() / 1e6,
        dropped: 0,
    }
}

/// canopy zenoh links: `production` = fault layer + default receive queue (1,024); otherwise
/// the bare link with a 65,536-message queue (the old rows).
fn zenoh_canopy(work: Work<'_>, count: usize, production_path: bool) -> Throughput {
    let prefix = format!("bench/{}", unique_run_prefix());
    let p = free_port();
    let ca = ZenohConfig::new(&prefix, vec![format!("tcp/127.0.0.1:{p}")], vec![]);
    let mut cb = ZenohConfig::new(&prefix, vec![], vec![format!("tcp/127.0.0.1:{p}")]);
    if !production_path {
        cb.receive_queue = 1 << 16;
    }
    let (ta, tb) = (
        ZenohTransport::open(1, ca).unwrap(),
        ZenohTransport::open(2, cb).unwrap(),
    );
    let wrap = |l: canopy_transport::net::ZenohLink, seed| -> Box<dyn Link> {
        if production_path {
            Box::new(production(Box::new(l), seed))
        } else {
            Box::new(l)
        }
    };
    let mut la = wrap(ta.link(2, DEFAULT_MAX_BODY_LEN).unwrap(), 1);
    let mut lb = wrap(tb.link(1, DEFAULT_MAX_BODY_LEN).unwrap(), 2);
    let deadline = Instant::now() + Duration::from_secs(20);
    while la.peer_state() != PeerState::Up || lb.peer_state() != PeerState::Up {
        la.poll_event();
        lb.poll_event();
        assert!(Instant::now() < deadline, "zenoh peers never met");
        std::thread::sleep(Duration::from_millis(10));
    }
    let ddf = matches!(work, Work::Ddf(_));
    let sent_all = Arc::new(AtomicBool::new(false));
    let sent_flag = sent_all.clone();
    let receiver = std::thread::spawn(move || {
        let (mut bytes, mut n, mut last) = (0usize, 0usize, Instant::now());
        while n < count {
            match lb.recv_timeout(Duration::from_millis(200)).unwrap() {
                Some(m) => {
                    bytes += if ddf {
                        std::hint::black_box(decode_ddf(&m).expect("a DDF kind").unwrap());
                        m.body_bytes().len()
                    } else {
                        let b: WireBytesRef<'_> = m.decode().unwrap();
                        b.0.len()
                    };
                    n += 1;
                    last = Instant::now();
                }
                // Overflow drops: everything that will come has come a second after the end.
                None if sent_flag.load(Ordering::Acquire)
                    && last.elapsed() > Duration::from_secs(1) =>
                {
                    break;
                }
                None => {}
            }
        }
        (last, bytes, n, lb)
    });
    let t0 = Instant::now();
    for k in 0..count {
        match work {
            Work::Ddf(msg) => send_ddf(&mut la, 0.0, msg, Compression::None).unwrap(),
            Work::Bytes(b) => la
                .send(
                    &SendMeta::new(MessageKind::DDF_DELTA, k as u64, 0.0),
                    &WireBytesRef(b),
                )
                .unwrap(),
        }
    }
    sent_all.store(true, Ordering::Release);
    let (t1, bytes, n, lb) = receiver.join().unwrap();
    drop((la, lb));
    ta.close().unwrap();
    tb.close().unwrap();
    Throughput {
        mbps: bytes as f64 / (t1 - t0).as_secs_f64() / 1e6,
        dropped: count - n,
    }
}

// ------------------------------------------------------------------ main

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    // Thread placement on a shared 2-core machine changes a whole round (fresh threads per
    // round), so several rounds give a steadier median than one long one.
    let rounds = if quick { 2 } else { 7 };
    // (payload, ping-pong round trips per round, zenoh messages per round: opaque bytes, DDF).
    // Each zenoh series streams for a few hundred milliseconds, well above the scheduler's time
    // slices, so one descheduling does not decide a round.
    let cases: [(usize, usize, [usize; 2]); 3] = if quick {
        [
            (KB, 200, [20_000, 10_000]),
            (MB, 20, [60, 20]),
            (16 * MB, 4, [6, 3]),
        ]
    } else {
        [
            (KB, 400, [100_000, 50_000]),
            (MB, 40, [300, 100]),
            (16 * MB, 10, [30, 10]),
        ]
    };
    // `--iox` / `--zenoh`: one middleware only (e.g. to profile it).
    let iox_only = std::env::args().any(|a| a == "--iox");
    let zenoh_only = std::env::args().any(|a| a == "--zenoh");
    let only: Option<usize> =
        std::env::args().find_map(|a| a.strip_prefix("--only=").and_then(|v| v.parse().ok()));
    let load_start = load_average();
    let mut primary = Vec::new();
    let mut secondary = Vec::new();
    for (i, (size, iters, [count, ddf_count])) in cases.into_iter().enumerate() {
        if only.is_some_and(|o| o != i) {
            continue;
        }
        let (msg, ddf_bytes) = ddf_of_size(size);
        let label = if size >= MB {
            format!("{} MB", size / MB)
        } else {
            format!("{} KB", size / KB)
        };
        eprintln!("{label}: DDF delta body {ddf_bytes} B; {rounds} rounds …");
        let mut iox: [Vec<f64>; 5] = Default::default();
        let mut zen: [Vec<Throughput>; 5] = Default::default();
        let payload = vec![0x5Au8; size];
        for round in 0..rounds {
            if !zenoh_only {
                for (acc, v) in iox.iter_mut().zip(iox_round(&msg, ddf_bytes, size, iters)) {
                    acc.extend(v);
                }
            }
            if !iox_only {
                // Series order reversed every other round, so neither side always goes first.
                let mut order = [0, 1, 2, 3, 4];
                if round % 2 == 1 {
                    order.reverse();
                }
                for s in order {
                    zen[s].push(match s {
                        0 => zenoh_raw(Work::Ddf(&msg), ddf_count),
                        1 => zenoh_canopy(Work::Ddf(&msg), ddf_count, true),
                        2 => zenoh_raw(Work::Bytes(&payload), count),
                        3 => zenoh_canopy(Work::Bytes(&payload), count, true),
                        _ => zenoh_canopy(Work::Bytes(&payload), count, false),
                    });
                }
            }
        }
        let med = |v: &mut Vec<f64>| if v.is_empty() { f64::NAN } else { median(v) };
        let lat: Vec<f64> = iox.iter_mut().map(med).collect();
        let thr: Vec<f64> = zen
            .iter()
            .map(|v| med(&mut v.iter().map(|t| t.mbps).collect()))
            .collect();
        // Throughput ratios: median of the per-round ratios (each pair ran seconds apart, so
        // slow drifts of the machine's load cancel).
        let zratio = |c: usize, r: usize| {
            med(&mut zen[c]
                .iter()
                .zip(&zen[r])
                .map(|(c, r)| c.mbps / r.mbps)
                .collect())
        };
        let dropped: usize = zen[1].iter().map(|t| t.dropped).sum();
        let dropped_bytes = format!(
            "{} of {}",
            zen[3].iter().map(|t| t.dropped).sum::<usize>(),
            count * rounds
        );
        primary.push(format!(
            "| {label} | {ddf_bytes} | {:.1} | {:.1} | {:.2} | {:.0} | {:.0} | {:.2} | {dropped} of {} |",
            lat[0],
            lat[1],
            lat[1] / lat[0],
            thr[0],
            thr[1],
            zratio(1, 0),
            ddf_count * rounds
        ));
        secondary.push(format!(
            "| {label} | {:.1} | {:.1} | {:.2} | {:.1} | {:.2} | {:.0} | {:.0} | {:.2} | {dropped_bytes} | {:.0} | {:.2} |",
            lat[2],
            lat[3],
            lat[3] / lat[2],
            lat[4],
            lat[4] / lat[2],
            thr[2],
            thr[3],
            zratio(3, 2),
            thr[4],
            zratio(4, 2),
        ));
    }
    println!(
        "canopy link benchmark: {rounds} alternating rounds per cell; load average {load_start} at start, {} at end",
        load_average()
    );
    println!();
    println!("## Production path: fault layer, production queues, DDF delta messages");
    println!(
        "| payload | DDF body bytes | iox raw p50 µs | iox canopy p50 µs | ratio (≤ 1.5) | zenoh raw MB/s | zenoh canopy MB/s | ratio (≥ 0.7) | zenoh canopy dropped |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in &primary {
        println!("{r}");
    }
    println!();
    println!("## Transport only: opaque bytes (production path, and the bare-link rows of before)");
    println!(
        "| payload | iox raw p50 µs | iox production p50 µs | ratio | iox bare p50 µs | ratio | zenoh raw MB/s | zenoh production MB/s | ratio | zenoh production dropped | zenoh bare 64k-queue MB/s | ratio |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for r in &secondary {
        println!("{r}");
    }
}
