//! Decoder robustness: ≥ 100,000 random and mutated messages (plain and zstd-compressed), zero panics, every input either
//! decoded into a valid body or rejected with a typed `CodecError` (each outcome counted and
//! printed). Plus property tests: every container round-trips exactly.

use std::collections::BTreeMap;
use std::panic::{AssertUnwindSafe, catch_unwind};

use canopy_transport::codec::{self, CodecError, PreEncoded};
use canopy_transport::envelope::{HEADER_LEN, OFF_CHECKSUM};
use canopy_transport::{
    MessageKind, SendMeta, Validate, ValidationError, WireBlockSymMatrix, WireBytes, WireMatrix,
    WireSymMatrix, WireVector,
};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

const MAX: u64 = 1 << 20;

/// A composite body like the node crate's DDF delta.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Delta {
    feature_ids: Vec<u64>,
    dy: WireVector,
    dyy: WireBlockSymMatrix,
    note: String,
}

impl Validate for Delta {
    fn validate(&self) -> Result<(), ValidationError> {
        self.dy.validate()?;
        self.dyy.validate()?;
        if self.dy.len() != self.dyy.dim() || self.feature_ids.len() * 3 != self.dy.len() {
            return Err(ValidationError::Other("delta dimensions disagree".into()));
        }
        Ok(())
    }
}

fn sample_bodies(rng: &mut ChaCha8Rng) -> Vec<(u8, Vec<u8>)> {
    let n = rng.random_range(1..6u32);
    let sym = WireSymMatrix::from_fn(n, |i, j| (i + j) as f64 + rng.random::<f64>());
    let mat = WireMatrix::from_fn(n, n + 1, |i, j| (i * 7 + j) as f64);
    let vec = WireVector::from_slice(&[1.0, -2.0, 3.5]);
    let b = [1.0, 0.5, 0.25, 0.5, 2.0, 0.75, 0.25, 0.75, 3.0];
    let blk = WireBlockSymMatrix::from_blocks(2, [(0, 0, b), (0, 1, [0.1; 9]), (1, 1, b)]).unwrap();
    let delta = Delta {
        feature_ids: vec![4, 9],
        dy: WireVector::from_slice(&[0.5; 6]),
        dyy: blk.clone(),
        note: "delta".into(),
    };
    let enc = |x: &dyn codec::WireBody| codec::encode_body_to_vec(x).unwrap();
    vec![
        (0, enc(&sym)),
        (1, enc(&mat)),
        (2, enc(&vec)),
        (3, enc(&blk)),
        (4, enc(&WireBytes(vec![7; 40]))),
        (5, enc(&delta)),
    ]
}

fn meta(rng: &mut ChaCha8Rng) -> SendMeta {
    SendMeta {
        kind: MessageKind(rng.random_range(0..12)),
        sender_epoch: rng.random(),
        receiver_epoch: rng.random(),
        seq: rng.random(),
        sim_time: rng.random_range(-1e3..1e3),
        compressed: false,
    }
}

/// Re-seals a header whose fields were edited: recomputes the CRC so the mutation reaches the
/// checks behind the checksum.
fn reseal(msg: &mut [u8]) {
    if msg.len() < HEADER_LEN {
        return;
    }
    let mut h = crc32fast::Hasher::new();
    h.update(&msg[..OFF_CHECKSUM]);
    h.update(&msg[HEADER_LEN..]);
    let c = h.finalize();
    msg[OFF_CHECKSUM..OFF_CHECKSUM + 4].copy_from_slice(&c.to_le_bytes());
}

fn variant(e: &CodecError) -> String {
    let s = format!("{e:?}");
    let end = s.find(['(', ' ', '{']).unwrap_or(s.len());
    match e {
        CodecError::Header(h) => {
            let hs = format!("{h:?}");
            let he = hs.find(['(', ' ', '{']).unwrap_or(hs.len());
            format!("Header::{}", &hs[..he])
        }
        _ => s[..end].to_string(),
    }
}

/// Decodes as the type tagged `t` (decompressing a flagged body first); returns Ok if it
/// decoded *and* validated.
fn decode_as(t: u8, msg: &[u8]) -> Result<(), CodecError> {
    match t {
        0 => codec::decode_owned::<WireSymMatrix>(msg, MAX).map(|_| ()),
        1 => codec::decode_owned::<WireMatrix>(msg, MAX).map(|_| ()),
        2 => codec::decode_owned::<WireVector>(msg, MAX).map(|_| ()),
        3 => codec::decode_owned::<WireBlockSymMatrix>(msg, MAX).map(|_| ()),
        4 => codec::decode_owned::<WireBytes>(msg, MAX).map(|_| ()),
        _ => codec::decode_owned::<Delta>(msg, MAX).map(|_| ()),
    }
}

/// 150,000 inputs in 10 families (two of them zstd-compressed bodies, intact and mutated).
/// Every decode runs under `catch_unwind`; the test fails on any panic, and on a family that
/// never reaches the outcome it exists to exercise.
#[test]
fn decoder_survives_150k_random_and_mutated_messages() {
    let mut rng = ChaCha8Rng::seed_from_u64(0x5eed_cafe);
    let mut outcomes: BTreeMap<String, u64> = BTreeMap::new();
    let mut per_family: BTreeMap<&str, BTreeMap<String, u64>> = BTreeMap::new();
    let mut panics = 0u64;
    const N: usize = 150_000;
    for i in 0..N {
        let bodies = sample_bodies(&mut rng);
        let (t, body) = bodies[rng.random_range(0..bodies.len())].clone();
        let m = meta(&mut rng);
        let valid = codec::encode_to_vec(&m, rng.random(), &PreEncoded(&body), MAX).unwrap();
        let family = [
            "valid", "random", "bitflip", "truncate", "extend", "header", "body", "junkbody",
            "zstd", "zstdmut",
        ][i % 10];
        let compressed = || {
            let frame = codec::compress_body(&PreEncoded(&body)).unwrap();
            let mut cm = m;
            cm.compressed = true;
            codec::encode_to_vec(&cm, 2, &PreEncoded(&frame), MAX).unwrap()
        };
        let msg: Vec<u8> = match family {
            "valid" => valid,
            "random" => {
                let len = rng.random_range(0..300);
                let mut v: Vec<u8> = (0..len).map(|_| rng.random()).collect();
                if rng.random_bool(0.5) && v.len() >= 4 {
                    v[..4].copy_from_slice(b"CNPY");
                }
                v
            }
            "bitflip" => {
                let mut v = valid;
                for _ in 0..rng.random_range(1..4) {
                    let k = rng.random_range(0..v.len());
                    v[k] ^= 1 << rng.random_range(0..8);
                }
                v
            }
            "truncate" => {
                let k = rng.random_range(0..valid.len());
                valid[..k].to_vec()
            }
            "extend" => {
                let mut v = valid;
                let extra = rng.random_range(1..16);
                v.extend((0..extra).map(|_| rng.random::<u8>()));
                v
            }
            "header" => {
                // Edit one header byte (version, kind, flags, time, length...) and re-seal.
                let mut v = valid;
                let k = rng.random_range(4..OFF_CHECKSUM);
                v[k] = rng.random();
                reseal(&mut v);
                v
            }
            "body" => {
                // Edit body bytes and re-seal: reaches bincode and the validators.
                let mut v = valid;
                if v.len() > HEADER_LEN {
                    for _ in 0..rng.random_range(1..4) {
                        let k = rng.random_range(HEADER_LEN..v.len());
                        v[k] = rng.random();
                    }
                }
                reseal(&mut v);
                v
            }
            "zstd" => compressed(),
            "zstdmut" => {
                // A compressed body with 1–3 bytes of the frame edited, re-sealed: reaches the
                // frame parser, the declared-size check and the decompressor.
                let mut v = compressed();
                for _ in 0..rng.random_range(1..4) {
                    let k = rng.random_range(HEADER_LEN..v.len());
                    v[k] = rng.random();
                }
                reseal(&mut v);
                v
            }
            _ => {
                // A well-formed envelope around random body bytes.
                let len = rng.random_range(0..200);
                let junk: Vec<u8> = (0..len).map(|_| rng.random()).collect();
                codec::encode_to_vec(&m, 1, &PreEncoded(&junk), MAX).unwrap()
            }
        };
        let out = match catch_unwind(AssertUnwindSafe(|| decode_as(t, &msg))) {
            Err(_) => {
                panics += 1;
                "PANIC".to_string()
            }
            Ok(Ok(())) => "decoded+valid".to_string(),
            Ok(Err(e)) => variant(&e),
        };
        *outcomes.entry(out.clone()).or_default() += 1;
        *per_family
            .entry(family)
            .or_default()
            .entry(out)
            .or_default() += 1;
    }
    println!("decoder fuzz: {N} inputs");
    for (k, v) in &outcomes {
        println!("  {k:<28} {v:>7}");
    }
    for (f, m) in &per_family {
        println!("  family {f:<9} {m:?}");
    }
    assert_eq!(panics, 0, "decoder panicked");
    assert_eq!(outcomes.values().sum::<u64>(), N as u64);
    // Each family must reach what it is designed to exercise (so the test cannot silently
    // degrade into feeding only garbage).
    let fam = |f: &str, k: &str| per_family[f].get(k).copied().unwrap_or(0);
    assert_eq!(fam("valid", "decoded+valid"), (N / 10) as u64);
    assert_eq!(fam("zstd", "decoded+valid"), (N / 10) as u64);
    assert!(fam("zstdmut", "Decompress") > 0);
    assert!(fam("random", "Header::BadMagic") > 0);
    assert!(fam("bitflip", "Checksum") > 0);
    assert!(fam("truncate", "Truncated") + fam("truncate", "Header::Truncated") > 0);
    assert!(fam("extend", "TrailingBytes") > 0);
    assert!(fam("header", "Header::UnsupportedVersion") > 0);
    assert!(fam("body", "BodyDecode") + fam("body", "Invalid") > 0);
    assert!(fam("junkbody", "BodyDecode") > 0);
}

fn finite() -> impl Strategy<Value = f64> {
    -1e12..1e12f64
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, rng_algorithm: proptest::test_runner::RngAlgorithm::ChaCha, ..ProptestConfig::default() })]

    /// Packed symmetric matrices round-trip bit-exactly and mirror.
    #[test]
    fn sym_round_trip(n in 0u32..12, vals in proptest::collection::vec(finite(), 78)) {
        let m = WireSymMatrix::from_fn(n, |i, j| vals[(i * 12 + j) % vals.len()]);
        let msg = codec::encode_to_vec(&SendMeta::new(MessageKind::DDF_DELTA, 1, 0.0), 1, &m, MAX).unwrap();
        let (_, back) = codec::decode::<WireSymMatrix>(&msg, MAX).unwrap();
        prop_assert_eq!(&back, &m);
        let d = back.to_dense_row_major();
        for i in 0..n as usize { for j in 0..n as usize {
            prop_assert_eq!(d[i * n as usize + j].to_bits(), d[j * n as usize + i].to_bits());
        }}
    }

    /// Block-sparse matrices built from any symmetric dense matrix reproduce it exactly.
    #[test]
    fn block_sparse_round_trip(nb in 1u32..5, vals in proptest::collection::vec(finite(), 144), zero_mask in any::<u16>()) {
        let n = nb as usize * 3;
        let mut d = vec![0.0; n * n];
        for i in 0..n { for j in i..n {
            let (bi, bj) = (i / 3, j / 3);
            if zero_mask & (1 << ((bi * 4 + bj) % 16)) != 0 { continue; }
            let v = vals[(i * n + j) % vals.len()];
            d[i * n + j] = v; d[j * n + i] = v;
        }}
        let m = WireBlockSymMatrix::from_dense(nb, &d).unwrap();
        let msg = codec::encode_to_vec(&SendMeta::new(MessageKind::DDF_DELTA, 1, 0.0), 1, &m, MAX).unwrap();
        let (_, back) = codec::decode::<WireBlockSymMatrix>(&msg, MAX).unwrap();
        prop_assert_eq!(back.to_dense_row_major(), d);
    }
}
