//! `[fusion] delta_compression = "zstd"` is lossless: the same scenario simulated with and
//! without it gives bit-for-bit the same estimates, maps and message counts, with fewer bytes
//! on every link (measured, printed).

use canopy_node::scenario::Scenario;
use canopy_node::sim::{SimOptions, simulate};
use canopy_node::wire::Compression;

#[test]
fn zstd_deltas_change_nothing_but_the_bytes() {
    let run = |c: Compression| {
        let mut s = Scenario::builtin_default();
        s.run.duration_s = 30.0;
        s.run.baseline = false;
        s.fusion.delta_compression = c;
        simulate(&s, SimOptions::default()).expect("simulation runs")
    };
    let plain = run(Compression::None);
    let zstd = run(Compression::Zstd);
    // Estimates: identical time series and final maps (PartialEq on f64: bit for bit but NaN).
    assert_eq!(plain.record.vehicles, zstd.record.vehicles);
    let (mut bytes_plain, mut bytes_zstd) = (0u64, 0u64);
    for (a, b) in plain.record.links.iter().zip(&zstd.record.links) {
        let (la, lb) = (a.samples.last().unwrap(), b.samples.last().unwrap());
        assert_eq!(la.messages, lb.messages, "{}-{}: message count", a.a, a.b);
        assert!(
            lb.bytes_ab < la.bytes_ab && lb.bytes_ba < la.bytes_ba,
            "{}-{}: zstd sent no fewer bytes",
            a.a,
            a.b
        );
        bytes_plain += la.bytes_ab + la.bytes_ba;
        bytes_zstd += lb.bytes_ab + lb.bytes_ba;
    }
    println!(
        "zstd deltas: {bytes_zstd} of {bytes_plain} bytes ({:.3})",
        bytes_zstd as f64 / bytes_plain as f64
    );
}
