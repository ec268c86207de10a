//! One conformance suite run against every backend (in-memory, iceoryx2, zenoh), bare and
//! under the fault layer with no fault configured (the production path of fusion links).
//!
//! Each test is generic over [`Backend`], a factory that creates (and re-creates) the endpoints of
//! a link and can inject raw bytes into one direction. Every test uses its own iceoryx2 prefix /
//! zenoh key prefix and ports, so tests run in parallel. Liveness waits use generous timeouts
//! (documented at [`LIVENESS_TIMEOUT`]); nothing asserts a wall-clock bound.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use std::sync::Arc;

use canopy_transport::codec::{self, CodecError, DEFAULT_MAX_BODY_LEN, PreEncoded};
use canopy_transport::envelope::HEADER_LEN;
use canopy_transport::fault::{Clock, FaultConfig, FaultyLink, ManualClock};
use canopy_transport::iceoryx::{IceoryxConfig, IceoryxLink, IceoryxRawSender, unique_run_prefix};
use canopy_transport::memory::{InMemoryHub, InMemoryLink};
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohLink, ZenohTransport};
use canopy_transport::{
    Link, LinkConfig, LinkEvent, LinkExt, MessageKind, NodeId, PeerState, SendMeta, WireBytes,
    WireSymMatrix, WireVector,
};

/// Upper bound for a peer transition to be noticed. Real figures are milliseconds (iceoryx2
/// liveness check every 50 ms; zenoh liveliness on TCP close); 20 s leaves room for a loaded
/// 2-core CI machine and zenoh's reconnection back-off (200 ms doubling to 1.6 s).
const LIVENESS_TIMEOUT: Duration = Duration::from_secs(20);
/// Upper bound to receive one message that was sent (same reasoning as above).
const RECV_TIMEOUT: Duration = Duration::from_secs(20);

const A: NodeId = 1;
const B: NodeId = 2;
const INTRUDER: NodeId = 99;

trait Backend {
    type L: Link + 'static;
    fn new(test: &str) -> Self;
    /// Creates (or, if it existed and was dropped, re-creates) the endpoint `local → peer`.
    fn endpoint(&mut self, local: NodeId, peer: NodeId) -> Self::L;
    /// Forgets the backend-side resources of a dropped endpoint (e.g. its zenoh session).
    fn release(&mut self, _local: NodeId) {}
    /// Delivers `bytes` verbatim over the direction `from → to` (as an intruder would).
    fn inject(&mut self, from: NodeId, to: NodeId, bytes: Vec<u8>);
}

// ---------------------------------------------------------------- in-memory

struct Memory {
    hub: InMemoryHub,
}

impl Backend for Memory {
    type L = InMemoryLink;
    fn new(_: &str) -> Self {
        Self {
            hub: InMemoryHub::new(),
        }
    }
    fn endpoint(&mut self, local: NodeId, peer: NodeId) -> InMemoryLink {
        self.hub.connect(LinkConfig::new(local, peer))
    }
    fn inject(&mut self, from: NodeId, to: NodeId, bytes: Vec<u8>) {
        assert!(self.hub.inject_raw(from, to, bytes));
    }
}

// ---------------------------------------------------------------- iceoryx2

struct Iceoryx {
    ix: IceoryxConfig,
    raw: HashMap<(NodeId, NodeId), IceoryxRawSender>,
}

impl Backend for Iceoryx {
    type L = IceoryxLink;
    fn new(test: &str) -> Self {
        Self {
            ix: IceoryxConfig::new(format!("{}{}", unique_run_prefix(), short(test))),
            raw: HashMap::new(),
        }
    }
    fn endpoint(&mut self, local: NodeId, peer: NodeId) -> IceoryxLink {
        IceoryxLink::connect(LinkConfig::new(local, peer), self.ix.clone()).unwrap()
    }
    fn inject(&mut self, from: NodeId, to: NodeId, bytes: Vec<u8>) {
        let ix = &self.ix;
        let raw = self.raw.entry((from, to)).or_insert_with(|| {
            IceoryxRawSender::open(ix, from, to, INTRUDER, DEFAULT_MAX_BODY_LEN).unwrap()
        });
        assert_eq!(
            raw.send_raw(&bytes).unwrap(),
            1,
            "the victim must be subscribed"
        );
    }
}

impl Drop for Iceoryx {
    fn drop(&mut self) {
        self.raw.clear();
        canopy_transport::iceoryx::remove_run_leftovers(&self.ix.run_prefix);
    }
}

fn short(test: &str) -> String {
    test.chars()
        .filter(|c| c.is_ascii_alphanumeric())
        .take(12)
        .collect()
}

// ---------------------------------------------------------------- zenoh

fn free_port() -> u16 {
    // Bind-and-release: the OS hands out distinct ephemeral ports, so parallel tests do not
    // collide (a race with unrelated processes is possible but not observed in practice).
    canopy_transport::net::free_loopback_port().expect("a free loopback port")
}

fn endpoint_of(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

fn test_auth() -> ZenohAuth {
    ZenohAuth {
        user: "canopy-node".into(),
        password: "s3cret-for-tests".into(),
        accept: vec![("canopy-node".into(), "s3cret-for-tests".into())],
    }
}

struct Zenoh {
    prefix: String,
    ports: HashMap<NodeId, u16>,
    transports: HashMap<NodeId, ZenohTransport>,
    intruders: Vec<ZenohTransport>,
}

impl Zenoh {
    fn port(&mut self, n: NodeId) -> u16 {
        *self.ports.entry(n).or_insert_with(free_port)
    }
    fn config(&mut self, local: NodeId, connect_to: &[NodeId]) -> ZenohConfig {
        let listen = vec![endpoint_of(self.port(local))];
        let connect = connect_to
            .iter()
            .map(|&n| endpoint_of(self.port(n)))
            .collect();
        let mut c = ZenohConfig::new(self.prefix.clone(), listen, connect);
        c.auth = Some(test_auth());
        c
    }
}

impl Backend for Zenoh {
    type L = ZenohLink;
    fn new(test: &str) -> Self {
        Self {
            prefix: format!("canopy/{}/{}", unique_run_prefix(), short(test)),
            ports: HashMap::new(),
            transports: HashMap::new(),
            intruders: Vec::new(),
        }
    }
    fn endpoint(&mut self, local: NodeId, peer: NodeId) -> ZenohLink {
        // The lower id connects, the higher one listens: restarting B exercises the
        // connector's automatic reconnection.
        let connect: Vec<NodeId> = if local < peer { vec![peer] } else { vec![] };
        let cfg = self.config(local, &connect);
        self.transports.remove(&local);
        let t = ZenohTransport::open(local, cfg).unwrap();
        let l = t.link(peer, DEFAULT_MAX_BODY_LEN).unwrap();
        self.transports.insert(local, t);
        l
    }
    fn release(&mut self, local: NodeId) {
        self.transports.remove(&local);
    }
    fn inject(&mut self, from: NodeId, to: NodeId, bytes: Vec<u8>) {
        if self.intruders.is_empty() {
            let cfg = self.config(INTRUDER, &[to]);
            let t = ZenohTransport::open(INTRUDER, cfg).unwrap();
            assert!(
                t.wait_for_node(to, LIVENESS_TIMEOUT),
                "intruder never saw the victim"
            );
            self.intruders.push(t);
        }
        self.intruders[0].raw_put(from, to, bytes).unwrap();
    }
}

// ---------------------------------------------------------------- production path

/// A backend's links under the fault layer with no fault configured: what every fusion link of
/// `canopy run` and `canopy sim` is. The whole suite runs on it too, so the zero-copy hand-over
/// through the layer behaves like the bare link.
struct Faulty<B>(B);

impl<B: Backend> Backend for Faulty<B> {
    type L = FaultyLink<B::L>;
    fn new(test: &str) -> Self {
        Self(B::new(test))
    }
    fn endpoint(&mut self, local: NodeId, peer: NodeId) -> FaultyLink<B::L> {
        let clock: Arc<dyn Clock> = Arc::new(ManualClock::new(0.0));
        FaultyLink::new(
            self.0.endpoint(local, peer),
            FaultConfig::none(u64::from(local)),
            clock,
        )
        .unwrap()
    }
    fn release(&mut self, local: NodeId) {
        self.0.release(local);
    }
    fn inject(&mut self, from: NodeId, to: NodeId, bytes: Vec<u8>) {
        self.0.inject(from, to, bytes);
    }
}

// ---------------------------------------------------------------- helpers

fn wait_event(l: &mut dyn Link, want: LinkEvent) {
    let deadline = Instant::now() + LIVENESS_TIMEOUT;
    while Instant::now() < deadline {
        if let Some(e) = l.poll_event() {
            if e == want {
                return;
            }
            continue;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    panic!("{want:?} not seen within {LIVENESS_TIMEOUT:?}");
}

fn connected_pair<B: Backend>(b: &mut B) -> (B::L, B::L) {
    let mut la = b.endpoint(A, B);
    let mut lb = b.endpoint(B, A);
    wait_event(&mut la, LinkEvent::PeerUp);
    wait_event(&mut lb, LinkEvent::PeerUp);
    (la, lb)
}

fn meta(seq: u64) -> SendMeta {
    SendMeta {
        kind: MessageKind::DDF_DELTA,
        sender_epoch: 1,
        receiver_epoch: 2,
        seq,
        sim_time: seq as f64 * 0.01,
        compressed: false,
    }
}

fn recv_vec(l: &mut dyn Link) -> (u64, Vec<f64>) {
    let m = l
        .recv_timeout(RECV_TIMEOUT)
        .unwrap()
        .expect("message not received in time");
    let v: WireVector = m.decode().unwrap();
    (m.header().seq, v.into_vec())
}

// ---------------------------------------------------------------- the suite

/// 300 messages each way arrive complete, in order, with their header fields intact, and the
/// counters agree.
fn in_order_delivery<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    const N: u64 = 300;
    // Interleave sending and receiving so bounded queues never overflow.
    for i in 0..N {
        la.send(&meta(i), &WireVector::from_slice(&[i as f64, -(i as f64)]))
            .unwrap();
        lb.send(&meta(i + 1000), &WireVector::from_slice(&[i as f64]))
            .unwrap();
        let (seq, v) = recv_vec(&mut lb);
        assert_eq!((seq, v), (i, vec![i as f64, -(i as f64)]));
        let m = la.recv_timeout(RECV_TIMEOUT).unwrap().unwrap();
        assert_eq!(m.header().sender, B);
        assert_eq!(m.header().meta(), meta(i + 1000));
    }
    let (sa, sb) = (la.stats(), lb.stats());
    assert_eq!((sa.sent_messages, sb.received_messages), (N, N));
    assert_eq!((sb.sent_messages, sa.received_messages), (N, N));
    assert_eq!(sa.sent_bytes, sb.received_bytes);
    assert_eq!(sa.rejected.total() + sb.rejected.total(), 0);
    assert_eq!(sa.dropped_overflow + sa.dropped_no_peer, 0);
}

/// A 16.8 MB symmetric matrix (order 2048, packed) crosses intact and decodes to the same values.
fn large_payload<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    let m = WireSymMatrix::from_fn(2048, |i, j| (i as f64) * 1e-3 - (j as f64) * 0.5 + 0.25);
    let len = codec::encoded_len(&m).unwrap();
    assert!(len >= 16 << 20, "payload must be at least 16 MiB, is {len}");
    la.send(&meta(7), &m).unwrap();
    let got = lb
        .recv_timeout(RECV_TIMEOUT)
        .unwrap()
        .expect("16 MB message");
    assert_eq!(got.message_bytes().len() as u64, len);
    let back: WireSymMatrix = got.decode().unwrap();
    assert_eq!(back, m);
}

/// Dropping B is reported as `PeerDown` at A; a new B is reported as `PeerUp` and both
/// directions work again (reconnection after a restart).
fn peer_loss_and_reconnection<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, lb) = connected_pair(&mut b);
    drop(lb);
    b.release(B);
    wait_event(&mut la, LinkEvent::PeerDown);
    assert_eq!(la.peer_state(), PeerState::Down);

    let mut lb = b.endpoint(B, A);
    wait_event(&mut la, LinkEvent::PeerUp);
    wait_event(&mut lb, LinkEvent::PeerUp);
    la.send(&meta(1), &WireVector::from_slice(&[1.0])).unwrap();
    assert_eq!(recv_vec(&mut lb), (1, vec![1.0]));
    lb.send(&meta(2), &WireVector::from_slice(&[2.0])).unwrap();
    assert_eq!(recv_vec(&mut la), (2, vec![2.0]));
}

/// Garbage, truncated, corrupted, wrong-version, oversize and non-neighbour messages are
/// rejected and counted by reason; valid messages around them still arrive, in order.
fn hostile_input_rejected<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    let valid =
        codec::encode_to_vec(&meta(5), A, &WireVector::from_slice(&[5.0]), u64::MAX).unwrap();

    // Garbage.
    b.inject(
        A,
        B,
        b"definitely not a canopy message, just bytes".repeat(3),
    );
    // Truncated: header only, and half a header.
    b.inject(A, B, valid[..HEADER_LEN].to_vec());
    b.inject(A, B, valid[..HEADER_LEN / 2].to_vec());
    // Corrupted body byte.
    let mut c = valid.clone();
    let last = c.len() - 1;
    c[last] ^= 0x01;
    b.inject(A, B, c);
    // Unknown format version.
    let mut v = valid.clone();
    v[4] = 99;
    b.inject(A, B, v);
    // Declared body larger than the link's limit.
    let mut big = valid.clone();
    big[48..56].copy_from_slice(&(DEFAULT_MAX_BODY_LEN + 1).to_le_bytes());
    b.inject(A, B, big);
    // Perfectly valid message, but from a node that is not B's peer.
    let forged = codec::encode_to_vec(
        &meta(6),
        INTRUDER,
        &WireVector::from_slice(&[6.0]),
        u64::MAX,
    )
    .unwrap();
    b.inject(A, B, forged);
    // Valid envelope whose body fails validation (NaN in a vector).
    let nan_body = codec::encode_body_to_vec(&WireVector::from_slice(&[f64::NAN])).unwrap();
    let nan = codec::encode_to_vec(&meta(8), A, &PreEncoded(&nan_body), u64::MAX).unwrap();
    b.inject(A, B, nan);
    // Then the real peer sends a valid one.
    la.send(&meta(9), &WireVector::from_slice(&[9.0])).unwrap();

    // Two messages get through: the NaN one (its envelope is fine and it claims to be from A)
    // and A's. Injected bytes travel on another port (iceoryx2 publisher, zenoh session) than
    // A's, so their relative order is not defined.
    let mut got: Vec<_> = (0..2)
        .map(|_| lb.recv_timeout(RECV_TIMEOUT).unwrap().expect("message"))
        .collect();
    got.sort_by_key(|m| m.header().seq);
    assert_eq!(got[0].header().seq, 8);
    assert!(got[0].decode::<WireVector>().is_err());
    assert_eq!(got[1].header().seq, 9);
    assert_eq!(got[1].decode::<WireVector>().unwrap().as_slice(), &[9.0]);
    drop(got);

    let r = lb.stats().rejected;
    assert_eq!(r.bad_magic, 1, "{r:?}");
    assert_eq!(r.truncated, 2, "{r:?}");
    assert_eq!(r.checksum, 1, "{r:?}");
    assert_eq!(r.bad_version, 1, "{r:?}");
    assert_eq!(r.too_large, 1, "{r:?}");
    assert_eq!(r.wrong_sender, 1, "{r:?}");
    assert_eq!(r.body, 1, "{r:?}");
    assert_eq!(r.total(), 8, "{r:?}");
    assert_eq!(lb.stats().received_messages, 2);
    // Nothing leaked into the other direction.
    assert!(la.try_recv().unwrap().is_none());
}

/// A body sent compressed (zstd frame, envelope flag) arrives smaller and decodes to the same
/// value with `decode_owned`; a borrowed `decode` is refused with a typed error; a compressed
/// body that is garbage, or declares more than the link's limit once decompressed, is
/// rejected with a typed error and counted, and nothing panics.
fn compressed_body_round_trips<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    let m = WireSymMatrix::from_fn(512, |i, j| ((i * j) % 7) as f64 * 0.5);
    let plain = codec::encoded_len(&m).unwrap();
    let frame = codec::compress_body(&m).unwrap();
    let mut cm = meta(8);
    cm.compressed = true;
    let mut exchange = |body: &[u8], what: &str| {
        la.send(&cm, &PreEncoded(body)).unwrap();
        lb.recv_timeout(RECV_TIMEOUT).unwrap().expect(what)
    };
    let got = exchange(&frame, "compressed message");
    assert!(got.header().compressed);
    assert!(
        (got.message_bytes().len() as u64) < plain / 4,
        "not smaller"
    );
    assert_eq!(got.decode_owned::<WireSymMatrix>().unwrap(), m);
    assert_eq!(
        got.decode::<WireSymMatrix>().unwrap_err(),
        CodecError::CompressedBorrow
    );
    // Garbage behind the flag.
    let bad = exchange(&[1, 2, 3, 4, 5, 6, 7, 8], "garbage message");
    assert!(matches!(
        bad.decode_owned::<WireSymMatrix>(),
        Err(CodecError::Decompress(_))
    ));
    // A frame that would decompress beyond the limit (a decompression bomb): zeros compress
    // ~10⁴:1, so the frame is small and the declared size is rejected before decompressing.
    let bomb =
        codec::compress_body(&WireBytes(vec![0u8; (DEFAULT_MAX_BODY_LEN + 1) as usize])).unwrap();
    let big = exchange(&bomb, "bomb message");
    assert!(matches!(
        big.decode_owned::<WireBytes>(),
        Err(CodecError::TooLarge { .. })
    ));
    assert!(lb.stats().rejected.body >= 3);
}

/// The application may hold more received messages at once than iceoryx2 lends samples (4 by
/// default): every one arrives, in order, and decodes while the others are still held.
fn many_messages_held_at_once<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    // Above iceoryx2's default lending limit, within its subscriber buffer (16).
    const N: u64 = 10;
    for i in 0..N {
        la.send(&meta(i), &WireVector::from_slice(&[i as f64]))
            .unwrap();
    }
    let held: Vec<_> = (0..N)
        .map(|_| lb.recv_timeout(RECV_TIMEOUT).unwrap().expect("message"))
        .collect();
    for (i, m) in held.iter().enumerate() {
        assert_eq!(m.header().seq, i as u64);
        assert_eq!(m.decode::<WireVector>().unwrap().as_slice(), &[i as f64]);
    }
    assert_eq!(lb.stats().received_messages, N);
}

/// Opaque kinds this build does not know are passed up, not rejected.
fn unknown_kind_passed_up<B: Backend>(test: &str) {
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    let mut m = meta(3);
    m.kind = MessageKind(0x7777);
    la.send(&m, &WireBytes(vec![1, 2, 3])).unwrap();
    let got = lb.recv_timeout(RECV_TIMEOUT).unwrap().unwrap();
    assert_eq!(got.header().kind, MessageKind(0x7777));
    assert_eq!(got.decode::<WireBytes>().unwrap().0, vec![1, 2, 3]);
    // recv_with decodes from the borrowed bytes.
    la.send(&meta(4), &WireVector::from_slice(&[4.0])).unwrap();
    let v = lb
        .recv_with(RECV_TIMEOUT, |h, body| {
            (h.seq, codec::decode_body::<WireVector>(body).unwrap())
        })
        .unwrap()
        .unwrap();
    assert_eq!((v.0, v.1.as_slice()), (4, &[4.0][..]));
}

/// Signals the Ctrl-C handler of [`signal_during_wait`] received.
static SIGNALS_HANDLED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// A wait interrupted by signals is not a link failure: `recv_timeout` returns at its
/// deadline with nothing, then receives what is sent. The test installs the handler a vehicle
/// process installs (`ctrlc`, for SIGINT, SIGTERM and SIGHUP) and sends SIGHUP to the waiting
/// thread every 2 ms: a handled signal makes a blocking call on a socket with a receive
/// timeout fail with EINTR (never restarted on Linux; SIGSTOP/SIGCONT and a debugger
/// attaching do the same), and the iceoryx2 link's wait passed that up as an error, which
/// ended the vehicle process. The handler counts what it received, so the test cannot pass
/// without signals delivered.
fn signal_during_wait<B: Backend>(test: &str) {
    use nix::sys::pthread::{pthread_kill, pthread_self};
    use nix::sys::signal::Signal;
    use std::sync::atomic::{AtomicBool, Ordering};
    static HANDLER: std::sync::Once = std::sync::Once::new();
    HANDLER.call_once(|| {
        ctrlc::set_handler(|| {
            SIGNALS_HANDLED.fetch_add(1, Ordering::Relaxed);
        })
        .expect("installing the Ctrl-C handler");
    });
    let mut b = B::new(test);
    let (mut la, mut lb) = connected_pair(&mut b);
    let waiter = pthread_self();
    let stop = Arc::new(AtomicBool::new(false));
    let before = SIGNALS_HANDLED.load(Ordering::Relaxed);
    let signaller = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut sent = 0u64;
            while !stop.load(Ordering::Relaxed) {
                // The waiting thread is alive until this thread is joined.
                pthread_kill(waiter, Signal::SIGHUP).expect("signalling the waiting thread");
                sent += 1;
                std::thread::sleep(Duration::from_millis(2));
            }
            sent
        })
    };
    // Nothing is sent meanwhile: the wait ends at its deadline, empty, not with an error.
    let got = lb.recv_timeout(Duration::from_millis(400));
    stop.store(true, Ordering::Relaxed);
    let sent = signaller.join().unwrap();
    // The handler runs on ctrlc's own thread: give the last signals time to be counted.
    let deadline = Instant::now() + RECV_TIMEOUT;
    while SIGNALS_HANDLED.load(Ordering::Relaxed) == before && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(5));
    }
    let handled = SIGNALS_HANDLED.load(Ordering::Relaxed) - before;
    assert!(
        matches!(got, Ok(None)),
        "a wait interrupted by signals returned {:?}",
        got.map(|m| m.map(|m| m.header().seq))
    );
    assert!(sent > 0 && handled > 0, "no signal delivered ({sent} sent)");
    la.send(&meta(7), &WireVector::from_slice(&[7.0])).unwrap();
    assert_eq!(recv_vec(&mut lb), (7, vec![7.0]));
}

macro_rules! conformance {
    ($module:ident, $backend:ty) => {
        mod $module {
            use super::*;
            #[test]
            fn in_order_delivery() {
                super::in_order_delivery::<$backend>(concat!(stringify!($module), "order"));
            }
            #[test]
            fn large_payload_16mb() {
                super::large_payload::<$backend>(concat!(stringify!($module), "large"));
            }
            #[test]
            fn peer_loss_and_reconnection() {
                super::peer_loss_and_reconnection::<$backend>(concat!(stringify!($module), "loss"));
            }
            #[test]
            fn hostile_input_rejected() {
                super::hostile_input_rejected::<$backend>(concat!(stringify!($module), "hostile"));
            }
            #[test]
            fn compressed_body_round_trips() {
                super::compressed_body_round_trips::<$backend>(concat!(
                    stringify!($module),
                    "zstd"
                ));
            }
            #[test]
            fn many_messages_held_at_once() {
                super::many_messages_held_at_once::<$backend>(concat!(stringify!($module), "held"));
            }
            #[test]
            fn signal_during_wait() {
                super::signal_during_wait::<$backend>(concat!(stringify!($module), "signal"));
            }
            #[test]
            fn unknown_kind_passed_up() {
                super::unknown_kind_passed_up::<$backend>(concat!(stringify!($module), "kind"));
            }
        }
    };
}

conformance!(memory, Memory);
conformance!(iceoryx, Iceoryx);
conformance!(zenoh, Zenoh);
conformance!(memory_faulty, Faulty<Memory>);
conformance!(iceoryx_faulty, Faulty<Iceoryx>);
conformance!(zenoh_faulty, Faulty<Zenoh>);

/// zenoh access control: a session without the right credentials cannot connect, so nothing it
/// publishes reaches the victim (who still talks to its real peer).
#[test]
fn zenoh_rejects_unauthenticated_sessions() {
    let mut b = Zenoh::new("zenohauth");
    let (mut la, mut lb) = connected_pair(&mut b);
    let mut cfg = b.config(INTRUDER, &[B]);
    cfg.auth = Some(ZenohAuth {
        user: "canopy-node".into(),
        password: "wrong".into(),
        accept: vec![("x".into(), "y".into())],
    });
    let intruder = ZenohTransport::open(INTRUDER, cfg).unwrap();
    // The victim's token is never visible: the transport was refused at the handshake.
    assert!(!intruder.wait_for_node(B, Duration::from_secs(2)));
    let forged =
        codec::encode_to_vec(&meta(1), A, &WireVector::from_slice(&[1.0]), u64::MAX).unwrap();
    intruder.raw_put(A, B, forged).unwrap();
    la.send(&meta(2), &WireVector::from_slice(&[2.0])).unwrap();
    assert_eq!(recv_vec(&mut lb), (2, vec![2.0]));
    assert!(
        lb.recv_timeout(Duration::from_millis(300))
            .unwrap()
            .is_none()
    );
    assert_eq!(lb.stats().received_messages, 1);
}
