//! A rogue zenoh session for the multi-host suite (`tests/tests/hosts.rs`), run as its own
//! process so it can sit on an emulated machine (a network namespace the test process is not
//! in). It holds a valid credential of the team (user and password), connects to one endpoint
//! (a vehicle's listener in peer mode, the router in client mode), opens a link of its own to
//! node `--peer` (its subscriber and liveliness token: declarations a non-neighbour must not
//! make), and once a subscriber of the data key `link/FROM/TO` is known to it publishes `--count`
//! well-formed envelopes there claiming to be node FROM.
//!
//! ```text
//! zenoh-rogue --connect tcp/10.0.0.3:7447 --client --prefix canopy/two-hosts --user uav4 \
//!     --node 4 --peer 2 --forge 3:2 --count 5 --wait 60      # password in CANOPY_ZENOH_PASSWORD
//! ```
//!
//! Prints `forged N on link/FROM/TO` and exits 0 when it published them; exits 1 with the
//! reason when the subscriber never became visible within `--wait` seconds (nothing to forge
//! against) or the session could not open.

use std::time::Duration;

use canopy_transport::codec::{DEFAULT_MAX_BODY_LEN, encode_to_vec};
use canopy_transport::net::{ZenohAuth, ZenohConfig, ZenohMode, ZenohTransport};
use canopy_transport::{MessageKind, SendMeta, WireVector};

#[derive(Debug)]
struct Args {
    connect: String,
    client: bool,
    prefix: String,
    user: String,
    node: u32,
    peer: u32,
    forge: (u32, u32),
    count: u64,
    wait: Duration,
}

fn parse() -> Result<Args, String> {
    let mut a = std::env::args().skip(1);
    let mut get = |what: &str| a.next().ok_or(format!("{what} needs a value"));
    let mut connect = None;
    let mut client = false;
    let mut prefix = None;
    let mut user = None;
    let mut node = None;
    let mut peer = None;
    let mut forge = None;
    let mut count = 5;
    let mut wait = Duration::from_secs(60);
    let num = |v: String| v.parse::<u64>().map_err(|e| format!("{v}: {e}"));
    while let Ok(flag) = get("") {
        match flag.as_str() {
            "--connect" => connect = Some(get(&flag)?),
            "--client" => client = true,
            "--prefix" => prefix = Some(get(&flag)?),
            "--user" => user = Some(get(&flag)?),
            "--node" => node = Some(num(get(&flag)?)? as u32),
            "--peer" => peer = Some(num(get(&flag)?)? as u32),
            "--forge" => {
                let v = get(&flag)?;
                let (f, t) = v.split_once(':').ok_or(format!("--forge {v}: FROM:TO"))?;
                forge = Some((num(f.into())? as u32, num(t.into())? as u32));
            }
            "--count" => count = num(get(&flag)?)?,
            "--wait" => wait = Duration::from_secs(num(get(&flag)?)?),
            other => return Err(format!("unknown argument {other:?}")),
        }
    }
    Ok(Args {
        connect: connect.ok_or("--connect is required")?,
        client,
        prefix: prefix.ok_or("--prefix is required")?,
        user: user.ok_or("--user is required")?,
        node: node.ok_or("--node is required")?,
        peer: peer.ok_or("--peer is required")?,
        forge: forge.ok_or("--forge is required")?,
        count,
        wait,
    })
}

fn run(a: &Args) -> Result<(), String> {
    let password = std::env::var("CANOPY_ZENOH_PASSWORD")
        .map_err(|_| "CANOPY_ZENOH_PASSWORD is not set".to_string())?;
    let mut cfg = ZenohConfig::new(a.prefix.clone(), vec![], vec![a.connect.clone()]);
    if a.client {
        cfg.mode = ZenohMode::Client;
        cfg.connect_timeout = Some(a.wait);
    }
    cfg.auth = Some(ZenohAuth {
        user: a.user.clone(),
        password,
        accept: vec![],
    });
    let session = ZenohTransport::open(a.node, cfg).map_err(|e| format!("opening: {e}"))?;
    let own = session
        .link(a.peer, DEFAULT_MAX_BODY_LEN)
        .map_err(|e| format!("its own link: {e}"))?;
    let (from, to) = a.forge;
    let routed = session
        .wait_for_subscriber(from, to, a.wait)
        .map_err(|e| format!("matching status: {e}"))?;
    if !routed {
        return Err(format!(
            "no subscriber of link/{from}/{to} became visible within {} s",
            a.wait.as_secs()
        ));
    }
    for k in 0..a.count {
        let meta = SendMeta::new(MessageKind::DDF_DELTA, 1_000 + k, 1.0);
        let bytes = encode_to_vec(&meta, from, &WireVector::from_slice(&[3.0]), u64::MAX)
            .map_err(|e| format!("an envelope: {e}"))?;
        session
            .raw_put(from, to, bytes)
            .map_err(|e| format!("put: {e}"))?;
    }
    // Time for the puts to leave before the session closes.
    std::thread::sleep(Duration::from_secs(1));
    drop(own);
    let _ = session.close();
    println!("forged {} on link/{from}/{to}", a.count);
    Ok(())
}

fn main() {
    let result = parse().and_then(|a| run(&a));
    if let Err(e) = result {
        eprintln!("zenoh-rogue: {e}");
        std::process::exit(1);
    }
}
