//! Where the time of one 16 MB message goes in the codec (encode, envelope check, decode), for
//! a byte-run body (one large write) and a structured body (bincode writes every f64 on its
//! own, like a DDF delta's 3×3 information blocks).
use std::mem::MaybeUninit;
use std::time::Instant;

use canopy_transport::codec;
use canopy_transport::{MessageKind, SendMeta, WireBytesRef};

fn main() {
    let n = 16 << 20;
    let src = vec![0x5Au8; n];
    let meta = SendMeta::new(MessageKind::DDF_DELTA, 1, 0.0);
    let body = WireBytesRef(&src);
    let len = codec::body_len(&body).unwrap();
    let mut un = vec![MaybeUninit::<u8>::uninit(); n + 128];
    let mut init = vec![0u8; n + 128];
    // Like a DDF delta's information blocks: row, column, nine f64 entries.
    let blocks: Vec<(u32, u32, [f64; 9])> = (0..n / 84)
        .map(|k| (k as u32, k as u32 + 1, [k as f64 * 0.1 + 0.3; 9]))
        .collect();
    let blocks_len = codec::body_len(&blocks).unwrap();
    for _ in 0..3 {
        let t = Instant::now();
        for _ in 0..10 {
            codec::encode_into_uninit(&meta, 1, &body, len, u64::MAX, &mut un).unwrap();
        }
        let enc_un = t.elapsed().as_secs_f64() / 10.0;
        let t = Instant::now();
        for _ in 0..10 {
            codec::encode_into(&meta, 1, &body, len, u64::MAX, &mut init).unwrap();
        }
        let enc = t.elapsed().as_secs_f64() / 10.0;
        let msg = &init[..64 + len as usize];
        let t = Instant::now();
        for _ in 0..10 {
            let (_, b) = codec::open_envelope(msg, u64::MAX).unwrap();
            let r: WireBytesRef<'_> = codec::decode_body(b).unwrap();
            std::hint::black_box(r);
        }
        let dec = t.elapsed().as_secs_f64() / 10.0;
        let t = Instant::now();
        for _ in 0..10 {
            let v = codec::encode_to_vec(&meta, 1, &body, u64::MAX).unwrap();
            std::hint::black_box(&v);
        }
        let to_vec = t.elapsed().as_secs_f64() / 10.0;
        let t = Instant::now();
        for _ in 0..10 {
            let mut v: Vec<u8> = Vec::with_capacity(n + 64);
            v.extend_from_slice(&src);
            std::hint::black_box(&v);
        }
        let copy_vec = t.elapsed().as_secs_f64() / 10.0;
        println!(
            "16 MB: encode_to_vec (fresh Vec) {:.2} ms, plain copy into fresh Vec {:.2} ms",
            to_vec * 1e3,
            copy_vec * 1e3
        );
        println!(
            "16 MB: encode→uninit {:.2} ms, encode→init {:.2} ms, open+decode {:.2} ms",
            enc_un * 1e3,
            enc * 1e3,
            dec * 1e3
        );
        let t = Instant::now();
        for _ in 0..10 {
            codec::encode_into(&meta, 1, &blocks, blocks_len, u64::MAX, &mut init).unwrap();
        }
        let enc_blocks = t.elapsed().as_secs_f64() / 10.0;
        let t = Instant::now();
        for _ in 0..10 {
            std::hint::black_box(codec::encode_body_to_vec(&blocks).unwrap());
        }
        let body_vec = t.elapsed().as_secs_f64() / 10.0;
        println!(
            "{:.1} MB of (u32, u32, [f64; 9]) blocks: encode→init {:.2} ms, body to Vec {:.2} ms",
            blocks_len as f64 / 1e6,
            enc_blocks * 1e3,
            body_vec * 1e3
        );
    }
}
