//! Where the time of one message goes on the production iceoryx2 path (an `IceoryxLink` with
//! the default `IceoryxConfig` under the fault layer with no fault): `send` (encode into the
//! loaned sample, CRC fused), `recv_timeout` up to the admitted message (wake-up, envelope and
//! CRC check), the in-place decode; ping-pong between two threads, medians over N round trips.
//!
//! Run: `cargo run --release -p canopy-transport --example link_cost -- [MiB] [N]`.
use std::sync::Arc;
use std::time::{Duration, Instant};

use canopy_transport::fault::{Clock, FaultConfig, FaultyLink, ManualClock};
use canopy_transport::iceoryx::{
    IceoryxConfig, IceoryxLink, remove_run_leftovers, unique_run_prefix,
};
use canopy_transport::{Link, LinkConfig, MessageKind, SendMeta, WireBytesRef};

fn production(local: u32, peer: u32, ix: &IceoryxConfig) -> FaultyLink<IceoryxLink> {
    let clock: Arc<dyn Clock> = Arc::new(ManualClock::new(0.0));
    let inner = IceoryxLink::connect(LinkConfig::new(local, peer), ix.clone()).unwrap();
    FaultyLink::new(inner, FaultConfig::none(1), clock).unwrap()
}

fn median_ms(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2] * 1e3
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let mib: usize = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(16);
    let n: usize = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(50);
    let ix = IceoryxConfig::new(format!("{}cost", unique_run_prefix()));
    let payload = vec![0x5Au8; mib << 20];
    let ix2 = ix.clone();
    let echo = std::thread::spawn(move || {
        let mut l = production(2, 1, &ix2);
        for _ in 0..n + 1 {
            let m = l.recv_timeout(Duration::from_secs(30)).unwrap().unwrap();
            let b: WireBytesRef<'_> = m.decode().unwrap();
            l.send(&m.header().meta(), &b).unwrap();
        }
    });
    let mut l = production(1, 2, &ix);
    std::thread::sleep(Duration::from_millis(200));
    let (mut send, mut wait, mut decode, mut total) = (vec![], vec![], vec![], vec![]);
    for k in 0..n + 1 {
        let t0 = Instant::now();
        l.send(
            &SendMeta::new(MessageKind::DDF_DELTA, k as u64, 0.0),
            &WireBytesRef(&payload),
        )
        .unwrap();
        let t1 = Instant::now();
        let m = l.recv_timeout(Duration::from_secs(30)).unwrap().unwrap();
        let t2 = Instant::now();
        let b: WireBytesRef<'_> = m.decode().unwrap();
        assert_eq!(b.0.len(), payload.len());
        let t3 = Instant::now();
        if k > 0 {
            send.push((t1 - t0).as_secs_f64());
            wait.push((t2 - t1).as_secs_f64());
            decode.push((t3 - t2).as_secs_f64());
            total.push((t3 - t0).as_secs_f64());
        }
    }
    echo.join().unwrap();
    println!(
        "{mib} MiB, {n} round trips: send {:.3} ms, until received and admitted {:.3} ms (includes the echo's receive + send), decode {:.3} ms, round trip {:.3} ms",
        median_ms(&mut send),
        median_ms(&mut wait),
        median_ms(&mut decode),
        median_ms(&mut total)
    );
    drop(l);
    remove_run_leftovers(&ix.run_prefix);
}
