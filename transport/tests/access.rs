//! zenoh access control on canopy's link layout (`canopy_transport::access`): with per-node users
//! and default-deny ingress rules, a session accepts from an authenticated peer only what that
//! peer's own side of one of its links carries. An intruder holding valid credentials (another
//! team member's user) can neither publish to a node it is not linked with, nor forge a
//! neighbour's key, nor subscribe to a link that is not its own — and every refusal is counted.

use std::time::Duration;

use canopy_transport::access::{AclLink, ZenohAccess, refusals};
use canopy_transport::codec::{self, DEFAULT_MAX_BODY_LEN};
use canopy_transport::iceoryx::unique_run_prefix;
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohTransport};
use canopy_transport::{Link, MessageKind, PeerState, SendMeta, WireVector};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;

const PASSWORD: &str = "team-secret-for-tests";

fn free_port() -> u16 {
    canopy_transport::net::free_loopback_port().expect("a free loopback port")
}

fn auth(user: &str) -> ZenohAuth {
    ZenohAuth {
        user: user.into(),
        password: PASSWORD.into(),
        // Every team member may connect (authentication); what it may do is the ACL's business.
        accept: ["uav2", "uav3", "uav8"]
            .iter()
            .map(|u| (u.to_string(), PASSWORD.to_string()))
            .collect(),
    }
}

fn recv_value(l: &mut dyn Link, timeout: Duration) -> Option<f64> {
    let m = l.recv_timeout(timeout).unwrap()?;
    Some(m.decode::<WireVector>().unwrap().as_slice()[0])
}

/// uav2 listens, uav3 connects (the link 2–3); uav2's session enforces that only uav3 may use
/// the other side of the link. An intruder authenticated as uav8 connects to uav2 and (1) opens a
/// link to uav2 of its own (publishes on `link/8/2`, subscribes to `link/2/8`), (2) claims to be
/// node 3 (publishes on `link/3/2` with a forged sender, subscribes to `link/2/3`). uav2 gets
/// exactly uav3's messages, the intruder gets none of uav2's, nothing reaches uav2's application
/// to be rejected there, and zenoh's refusals are counted by action and key (messages refused,
/// not the permissions zenoh evaluates when it caches a key: the counts are exact).
#[test]
fn a_non_neighbour_is_refused_and_counted() {
    tracing_subscriber::registry()
        .with(canopy_transport::access::refusal_counter())
        .try_init()
        .expect("the only subscriber of this test binary");
    let prefix = format!("canopy/{}/acl", unique_run_prefix());
    let port = free_port();
    let ep = format!("tcp/127.0.0.1:{port}");
    let session = |node: u32, user: &str, listen: bool, peer_user: &str, peer: u32| {
        let mut c = ZenohConfig::new(
            prefix.clone(),
            if listen { vec![ep.clone()] } else { vec![] },
            if listen { vec![] } else { vec![ep.clone()] },
        );
        c.auth = Some(auth(user));
        // Only the listener enforces: it authenticated the connector's user name (zenoh's
        // user/password check is one-way, so the connector has no name for the listener).
        c.access = listen.then(|| {
            ZenohAccess::for_links(
                &prefix,
                &[AclLink {
                    user: peer_user.into(),
                    from: peer,
                    to: node,
                }],
            )
        });
        ZenohTransport::open(node, c).unwrap()
    };
    let t2 = session(2, "uav2", true, "uav3", 3);
    let t3 = session(3, "uav3", false, "uav2", 2);
    let mut l2 = t2.link(3, DEFAULT_MAX_BODY_LEN).unwrap();
    let mut l3 = t3.link(2, DEFAULT_MAX_BODY_LEN).unwrap();
    for l in [&mut l2 as &mut dyn Link, &mut l3] {
        let deadline = std::time::Instant::now() + Duration::from_secs(20);
        while l.peer_state() != PeerState::Up {
            assert!(
                std::time::Instant::now() < deadline,
                "the link 2-3 did not come up under access control; refused: {:?}",
                refusals()
            );
            while l.poll_event().is_some() {}
            std::thread::sleep(Duration::from_millis(10));
        }
    }
    let meta = |seq| SendMeta::new(MessageKind::DDF_DELTA, seq, 0.0);
    l3.send(&meta(1), &WireVector::from_slice(&[1.0])).unwrap();
    assert_eq!(recv_value(&mut l2, Duration::from_secs(10)), Some(1.0));

    // The intruder: valid credentials (user uav8), not uav2's neighbour.
    let mut c = ZenohConfig::new(prefix.clone(), vec![], vec![ep.clone()]);
    c.auth = Some(auth("uav8"));
    let as_8 = ZenohTransport::open(8, c.clone()).unwrap();
    let as_3 = ZenohTransport::open(3, c).unwrap();
    let mut own = as_8.link(2, DEFAULT_MAX_BODY_LEN).unwrap();
    let mut forged = as_3.link(2, DEFAULT_MAX_BODY_LEN).unwrap();
    // Give the connections and declarations time to arrive (there is nothing to wait for: the
    // victim's tokens are refused too, so the intruder never sees it up).
    std::thread::sleep(Duration::from_secs(2));
    for k in 0..5u64 {
        own.send(&meta(10 + k), &WireVector::from_slice(&[8.0]))
            .unwrap();
        forged
            .send(&meta(20 + k), &WireVector::from_slice(&[3.0]))
            .unwrap();
        let raw =
            codec::encode_to_vec(&meta(30 + k), 3, &WireVector::from_slice(&[33.0]), u64::MAX)
                .unwrap();
        as_3.raw_put(3, 2, raw).unwrap();
    }
    l2.send(&meta(2), &WireVector::from_slice(&[2.0])).unwrap();
    l3.send(&meta(3), &WireVector::from_slice(&[4.0])).unwrap();
    // uav3 still gets uav2's message and uav2 only uav3's.
    assert_eq!(recv_value(&mut l3, Duration::from_secs(10)), Some(2.0));
    assert_eq!(recv_value(&mut l2, Duration::from_secs(10)), Some(4.0));
    assert_eq!(recv_value(&mut l2, Duration::from_millis(500)), None);
    // The eavesdropper claiming node 3 got nothing of what uav2 sent to uav3.
    assert_eq!(recv_value(&mut forged, Duration::from_millis(300)), None);
    assert_eq!(recv_value(&mut own, Duration::from_millis(100)), None);
    // Nothing got as far as uav2's application (where a forged sender would be rejected).
    assert_eq!(l2.stats().rejected.total(), 0);
    assert_eq!(l2.stats().received_messages, 2);

    let r = refusals();
    eprintln!("refusals: {r:#?}");
    let count = |action: &str, key: &str| {
        r.get(&format!("{action} on {prefix}/{key}"))
            .copied()
            .unwrap_or(0)
    };
    // Every forged publication is sent (uav2 announces its subscriber on link/3/2) and refused:
    // 5 through the forged link, 5 raw puts.
    assert_eq!(count("Put (ingress)", "link/3/2"), 10, "{r:?}");
    // On its own link 8 → 2 nothing is even routed: uav2 subscribes to no such key, so zenoh
    // sends it nothing to refuse; its declarations there are refused.
    assert_eq!(count("Put (ingress)", "link/8/2"), 0, "{r:?}");
    assert_eq!(
        count("Declare Subscriber (ingress)", "link/2/8"),
        1,
        "{r:?}"
    );
    assert_eq!(count("Liveliness Token (ingress)", "alive/8/2"), 1, "{r:?}");
    // The eavesdropping subscription on uav2's data to uav3 was refused (so uav2 never routes
    // to it).
    assert_eq!(
        count("Declare Subscriber (ingress)", "link/2/3"),
        1,
        "{r:?}"
    );
    // The team's own traffic was never refused: uav3's puts on link/3/2 are refused exactly the
    // 10 forged times (above) and both of its messages arrived, and uav2's publications to uav3
    // on link/2/3 never met an egress refusal. (An *ingress* refusal on link/2/3 can only be
    // the intruder's: under load zenoh sometimes checks every action of an intruder's declared
    // interest in that key at once — Put, Delete, Query, Reply, Liveliness, … one each — seen
    // once in a loaded full-suite run.)
    assert!(
        !r.keys()
            .any(|k| k.ends_with("link/2/3") && k.contains("(egress)") && k.starts_with("Put")),
        "{r:?}"
    );
    drop((own, forged, as_8, as_3));
}

/// A session that connects cannot enforce access control (it would have no user name for its
/// listener and refuse its own links): a typed configuration error, not a silent dead link.
#[test]
fn access_control_on_a_connecting_session_is_a_config_error() {
    let mut c = ZenohConfig::new("canopy/acl-conf", vec![], vec!["tcp/127.0.0.1:9".into()]);
    c.auth = Some(auth("uav3"));
    c.access = Some(ZenohAccess::for_links("canopy/acl-conf", &[]));
    match ZenohTransport::open(3, c) {
        Err(canopy_transport::LinkError::Config(m)) => assert!(m.contains("only listens"), "{m}"),
        Err(e) => panic!("wrong error: {e}"),
        Ok(_) => panic!("a connecting session accepted access control"),
    }
}
