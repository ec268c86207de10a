//! canopy's zenoh links through a zenoh **router** (`ZenohMode::Router`) whose access control is
//! built from the link layout (`ZenohAccess::for_links` over both directions of every link):
//! every node is a client of the router (`ZenohMode::Client`), listens nowhere and enforces
//! nothing; the router knows every client's user (each one connected to it and authenticated)
//! and is the one place that refuses — and counts — what a client is not entitled to.
//!
//! The team here is the chain uav1 – uav2 – uav3, all clients of one router: the sessions of a
//! host's vehicles meet at the router, and they must not be able to talk to each other through
//! it except on their own links.

use std::time::{Duration, Instant};

use canopy_transport::access::{AclLink, ZenohAccess, refusals};
use canopy_transport::codec::{self, DEFAULT_MAX_BODY_LEN};
use canopy_transport::iceoryx::unique_run_prefix;
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohLink, ZenohMode, ZenohTransport};
use canopy_transport::{Link, MessageKind, PeerState, SendMeta, WireVector};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;

const PASSWORD: &str = "team-secret-for-router-tests";
const USERS: [&str; 3] = ["uav1", "uav2", "uav3"];

fn recv_value(l: &mut dyn Link, timeout: Duration) -> Option<f64> {
    let m = l.recv_timeout(timeout).unwrap()?;
    Some(m.decode::<WireVector>().unwrap().as_slice()[0])
}

fn wait_up(l: &mut ZenohLink, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(20);
    while l.peer_state() != PeerState::Up {
        assert!(
            Instant::now() < deadline,
            "{what} did not come up through the router; refused: {:?}",
            refusals()
        );
        while l.poll_event().is_some() {}
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// A client of the router at `ep` authenticated as `user` (node `node`).
fn client(prefix: &str, ep: &str, node: u32, user: &str) -> ZenohTransport {
    let mut c = ZenohConfig::new(prefix, vec![], vec![ep.to_string()]);
    c.mode = ZenohMode::Client;
    c.auth = Some(ZenohAuth {
        user: user.into(),
        password: PASSWORD.into(),
        accept: Vec::new(),
    });
    ZenohTransport::open(node, c).expect("a client session opens")
}

/// The router enforces the chain's links: uav1–uav2 and uav2–uav3 carry their traffic both ways;
/// uav1 and uav3 (no link between them) cannot open one through the router, uav1 cannot forge
/// uav2's publications to uav3, and uav3 cannot eavesdrop on uav1–uav2. Every refusal happens at
/// the router, counted by action and key (exact for the forged puts), and nothing forged reaches
/// an application.
#[test]
fn a_router_lets_clients_talk_only_on_their_links() {
    tracing_subscriber::registry()
        .with(canopy_transport::access::refusal_counter())
        .try_init()
        .expect("the only subscriber of this test binary");
    let prefix = format!("canopy/{}/router", unique_run_prefix());
    let port = canopy_transport::net::free_loopback_port().expect("a free loopback port");
    let ep = format!("tcp/127.0.0.1:{port}");
    let link = |user: &str, from: u32, to: u32| AclLink {
        user: user.into(),
        from,
        to,
    };
    let mut rc = ZenohConfig::new(prefix.clone(), vec![ep.clone()], vec![]);
    rc.mode = ZenohMode::Router;
    rc.auth = Some(ZenohAuth {
        user: "router".into(),
        password: PASSWORD.into(),
        accept: USERS
            .iter()
            .map(|u| (u.to_string(), PASSWORD.to_string()))
            .collect(),
    });
    rc.access = Some(ZenohAccess::for_links(
        &prefix,
        &[
            link("uav1", 1, 2),
            link("uav2", 2, 1),
            link("uav2", 2, 3),
            link("uav3", 3, 2),
        ],
    ));
    let router = ZenohTransport::open(u32::MAX - 2, rc).expect("the router opens");

    let t1 = client(&prefix, &ep, 1, "uav1");
    let t2 = client(&prefix, &ep, 2, "uav2");
    let t3 = client(&prefix, &ep, 3, "uav3");
    let mut l12 = t1.link(2, DEFAULT_MAX_BODY_LEN).unwrap();
    let mut l21 = t2.link(1, DEFAULT_MAX_BODY_LEN).unwrap();
    let mut l23 = t2.link(3, DEFAULT_MAX_BODY_LEN).unwrap();
    let mut l32 = t3.link(2, DEFAULT_MAX_BODY_LEN).unwrap();
    for (l, what) in [
        (&mut l12, "uav1 -> uav2"),
        (&mut l21, "uav2 -> uav1"),
        (&mut l23, "uav2 -> uav3"),
        (&mut l32, "uav3 -> uav2"),
    ] {
        wait_up(l, what);
    }
    let meta = |seq| SendMeta::new(MessageKind::DDF_DELTA, seq, 0.0);
    l12.send(&meta(1), &WireVector::from_slice(&[12.0]))
        .unwrap();
    l21.send(&meta(1), &WireVector::from_slice(&[21.0]))
        .unwrap();
    l23.send(&meta(2), &WireVector::from_slice(&[23.0]))
        .unwrap();
    l32.send(&meta(1), &WireVector::from_slice(&[32.0]))
        .unwrap();
    let wait = Duration::from_secs(10);
    assert_eq!(recv_value(&mut l21, wait), Some(12.0));
    assert_eq!(recv_value(&mut l12, wait), Some(21.0));
    assert_eq!(recv_value(&mut l32, wait), Some(23.0));
    assert_eq!(recv_value(&mut l23, wait), Some(32.0));

    // uav1 and uav3 have no link: through the router they never see each other.
    let mut l13 = t1.link(3, DEFAULT_MAX_BODY_LEN).unwrap();
    let mut l31 = t3.link(1, DEFAULT_MAX_BODY_LEN).unwrap();
    // uav3, a neighbour of uav2, eavesdrops on uav1 – uav2 (as node 1 towards 2).
    let eaves = client(&prefix, &ep, 1, "uav3");
    let mut spy = eaves.link(2, DEFAULT_MAX_BODY_LEN).unwrap();
    // Give the declarations time to reach the router (there is nothing to wait for: they are
    // refused, so neither side ever sees the other up).
    std::thread::sleep(Duration::from_secs(2));
    const FORGED: u64 = 5;
    for k in 0..FORGED {
        l13.send(&meta(10 + k), &WireVector::from_slice(&[13.0]))
            .unwrap();
        l31.send(&meta(10 + k), &WireVector::from_slice(&[31.0]))
            .unwrap();
        // uav1 claims to be uav2 towards uav3 (uav3 subscribes to link/2/3, which the router
        // announces to every client, so these puts are sent and refused on arrival).
        let raw =
            codec::encode_to_vec(&meta(20 + k), 2, &WireVector::from_slice(&[99.0]), u64::MAX)
                .unwrap();
        t1.raw_put(2, 3, raw).unwrap();
    }
    l12.send(&meta(2), &WireVector::from_slice(&[120.0]))
        .unwrap();
    l21.send(&meta(2), &WireVector::from_slice(&[210.0]))
        .unwrap();
    assert_eq!(recv_value(&mut l21, wait), Some(120.0));
    assert_eq!(recv_value(&mut l12, wait), Some(210.0));
    for l in [&mut l13, &mut l31] {
        while l.poll_event().is_some() {}
        assert_eq!(
            l.peer_state(),
            PeerState::Down,
            "a link that is not in the layout"
        );
    }
    assert_eq!(recv_value(&mut l31, Duration::from_millis(500)), None);
    assert_eq!(recv_value(&mut l13, Duration::from_millis(100)), None);
    // uav3 received nothing forged: uav2's one message only.
    assert_eq!(recv_value(&mut l32, Duration::from_millis(300)), None);
    assert_eq!(l32.stats().received_messages, 1);
    assert_eq!(l32.stats().rejected.total(), 0);
    // The eavesdropper got nothing of uav2's traffic to uav1.
    assert_eq!(recv_value(&mut spy, Duration::from_millis(100)), None);

    let r = refusals();
    eprintln!("refused at the router: {r:#?}");
    let count = |action: &str, key: &str| {
        r.get(&format!("{action} on {prefix}/{key}"))
            .copied()
            .unwrap_or(0)
    };
    // Exactly the forged puts.
    assert_eq!(count("Put (ingress)", "link/2/3"), FORGED, "{r:?}");
    // The links 1–3 and 3–1: their declarations refused, so their data never even routed.
    for (action, key) in [
        ("Declare Subscriber (ingress)", "link/3/1"),
        ("Declare Subscriber (ingress)", "link/1/3"),
        ("Liveliness Token (ingress)", "alive/1/3"),
        ("Liveliness Token (ingress)", "alive/3/1"),
        // The eavesdropper's subscription to uav2's data for uav1.
        ("Declare Subscriber (ingress)", "link/2/1"),
    ] {
        assert!(count(action, key) >= 1, "{action} on {key}: {r:?}");
    }
    assert_eq!(count("Put (ingress)", "link/1/3"), 0, "{r:?}");
    assert_eq!(count("Put (ingress)", "link/3/1"), 0, "{r:?}");
    // The links of the layout were never refused (link/2/3: only the forgeries above).
    for key in ["link/1/2", "link/2/1", "link/3/2"] {
        assert_eq!(count("Put (ingress)", key), 0, "{key}: {r:?}");
    }
    drop((l13, l31, spy, eaves, l12, l21, l23, l32, t1, t2, t3));
    let _ = router.close();
}
