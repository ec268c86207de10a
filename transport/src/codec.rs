//! The wire codec: envelope + bincode 2.0.1 body. This is the only module that names bincode.
//!
//! Encoding is two-pass so a backend can encode straight into memory it owns (a shared-memory
//! sample, a pre-sized `Vec`): [`body_len`] measures the body with bincode's size writer, the
//! backend obtains `HEADER_LEN + body_len` bytes, and [`encode_into`] / [`encode_into_uninit`]
//! write header and body there while streaming the CRC-32. Decoding ([`open_envelope`],
//! [`decode_body`]) validates magic, version, size limits and the checksum before the body is
//! touched, then decodes the body with bincode and runs its [`Validate`] impl. No input makes
//! these functions panic; every failure is a [`CodecError`] variant.

use std::mem::MaybeUninit;

use bincode::enc::write::{SizeWriter, Writer};
use bincode::error::{DecodeError, EncodeError};
use serde::{Deserialize, Serialize};

use crate::envelope::{
    HEADER_LEN, Header, HeaderError, NodeId, OFF_CHECKSUM, SendMeta, parse_header,
};
use crate::wire::{Validate, ValidationError};

/// Hard cap on any body, independent of configuration (bincode's own allocation limit too).
pub const HARD_MAX_BODY_LEN: u64 = 1 << 32;
/// Default configured cap on a body (links override it with their `max_message_len`).
pub const DEFAULT_MAX_BODY_LEN: u64 = 64 << 20;

type BincodeConfig = bincode::config::Configuration<
    bincode::config::LittleEndian,
    bincode::config::Varint,
    bincode::config::Limit<{ HARD_MAX_BODY_LEN as usize }>,
>;

const BINCODE: BincodeConfig = bincode::config::standard()
    .with_little_endian()
    .with_variable_int_encoding()
    .with_limit::<{ HARD_MAX_BODY_LEN as usize }>();

/// Every way encoding or decoding can fail.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodecError {
    /// The header is malformed (truncated, bad magic, unknown version, reserved bits, NaN time).
    #[error("bad header: {0}")]
    Header(#[from] HeaderError),
    /// The declared body is larger than the configured limit.
    #[error("body of {len} bytes exceeds the limit of {max}")]
    TooLarge {
        /// Declared body length.
        len: u64,
        /// Configured limit.
        max: u64,
    },
    /// Fewer bytes than the header declares.
    #[error("truncated: header declares {declared} body bytes, {available} present")]
    Truncated {
        /// Declared body length.
        declared: u64,
        /// Bytes present after the header.
        available: u64,
    },
    /// More bytes than the header declares.
    #[error("{extra} trailing bytes after the declared body")]
    TrailingBytes {
        /// Bytes beyond header + declared body.
        extra: u64,
    },
    /// CRC-32 mismatch: the bytes were corrupted.
    #[error("checksum mismatch: header says {expected:#010x}, bytes give {computed:#010x}")]
    Checksum {
        /// Checksum in the header.
        expected: u32,
        /// Checksum of the bytes.
        computed: u32,
    },
    /// bincode could not decode the body into the requested type.
    #[error("body does not decode: {0}")]
    BodyDecode(String),
    /// The body decoded but did not consume all body bytes.
    #[error("body decoded from {used} of {len} bytes")]
    BodyNotConsumed {
        /// Bytes consumed by the decoder.
        used: u64,
        /// Body length.
        len: u64,
    },
    /// The body decoded but its [`Validate`] impl rejected it.
    #[error("body is invalid: {0}")]
    Invalid(#[from] ValidationError),
    /// The body could not be encoded (serde error or buffer too small).
    #[error("body does not encode: {0}")]
    Encode(String),
    /// The output buffer is smaller than the encoded message.
    #[error("buffer of {have} bytes cannot hold a {need}-byte message")]
    BufferTooSmall {
        /// Bytes needed.
        need: u64,
        /// Bytes available.
        have: u64,
    },
    /// A compressed body (FLAG_ZSTD) that is not a valid zstd frame, does not declare its
    /// size, or would decompress beyond the limit.
    #[error("compressed body: {0}")]
    Decompress(String),
    /// A compressed body asked for as a borrowed decode ([`decode_body`]); use
    /// [`decode_body_owned`].
    #[error("the body is compressed: decode it into an owned value")]
    CompressedBorrow,
    /// The body serialised to a different length in the second pass (non-deterministic
    /// `Serialize` impl).
    #[error("body measured {measured} bytes but encoded to {written}")]
    LengthChanged {
        /// First pass.
        measured: u64,
        /// Second pass.
        written: u64,
    },
}

/// Something that can be encoded as a message body. Implemented for every `serde::Serialize`
/// type, and for [`PreEncoded`] bytes. Object safe, so links take `&dyn WireBody`.
pub trait WireBody {
    /// Streams the body into `w`.
    fn encode_body(&self, w: &mut BodyWriter<'_>) -> Result<(), CodecError>;
}

impl<T: Serialize + ?Sized> WireBody for T {
    fn encode_body(&self, w: &mut BodyWriter<'_>) -> Result<(), CodecError> {
        bincode::serde::encode_into_writer(self, w, BINCODE).map_err(encode_error)
    }
}

/// A body that is already encoded (e.g. held back by the fault layer, or forwarded verbatim):
/// its bytes are written as they are.
#[derive(Debug, Clone, Copy)]
pub struct PreEncoded<'a>(pub &'a [u8]);

impl WireBody for PreEncoded<'_> {
    fn encode_body(&self, w: &mut BodyWriter<'_>) -> Result<(), CodecError> {
        w.write(self.0).map_err(encode_error)
    }
}

fn encode_error(e: EncodeError) -> CodecError {
    CodecError::Encode(e.to_string())
}

enum Sink<'a> {
    Count,
    Init(&'a mut [u8]),
    Uninit(&'a mut [MaybeUninit<u8>]),
    /// Appends (no zero-fill pass over a fresh buffer).
    Append(&'a mut Vec<u8>),
}

/// Where encoded bytes go, with the CRC-32 streamed over them.
struct Out<'a> {
    sink: Sink<'a>,
    pos: usize,
    crc: Option<crc32fast::Hasher>,
}

/// Destination of a body encoding: counts, or writes into initialised or uninitialised memory,
/// streaming the CRC-32 as it goes. Small writes are gathered first (see [`STAGE`]).
pub struct BodyWriter<'a> {
    out: Out<'a>,
    stage: [u8; STAGE],
    staged: usize,
}

impl std::fmt::Debug for BodyWriter<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BodyWriter")
            .field("pos", &(self.out.pos + self.staged))
            .finish()
    }
}

/// Large writes are copied and checksummed in chunks of this size (well inside a core's L2), so
/// the source is read from memory once and checksummed while still in cache: 16 MB encode went
/// from 4.3 ms to 1.8 ms on the development machine (`examples/codec_cost.rs`).
const FUSED_CHUNK: usize = 128 * 1024;

/// Writes up to [`SMALL_WRITE`] bytes (bincode writes each field on its own: 8 bytes per f64)
/// are gathered in a buffer of this size and copied and checksummed a buffer at a time: a CRC
/// update per 8-byte write costs more than the bytes do (`examples/codec_cost.rs`, structured
/// body).
const STAGE: usize = 2048;
/// Largest write that is gathered rather than copied through at once.
const SMALL_WRITE: usize = 256;

impl Out<'_> {
    #[inline]
    fn write_chunk(&mut self, bytes: &[u8]) -> Result<(), EncodeError> {
        let end = self.pos + bytes.len();
        match &mut self.sink {
            Sink::Count => {}
            Sink::Init(dst) => {
                let Some(d) = dst.get_mut(self.pos..end) else {
                    return Err(EncodeError::UnexpectedEnd);
                };
                d.copy_from_slice(bytes);
            }
            Sink::Uninit(dst) => {
                let Some(d) = dst.get_mut(self.pos..end) else {
                    return Err(EncodeError::UnexpectedEnd);
                };
                d.write_copy_of_slice(bytes);
            }
            Sink::Append(v) => v.extend_from_slice(bytes),
        }
        if let Some(h) = &mut self.crc {
            h.update(bytes);
        }
        self.pos = end;
        Ok(())
    }
}

impl<'a> BodyWriter<'a> {
    fn new(sink: Sink<'a>, crc: Option<crc32fast::Hasher>) -> Self {
        Self {
            out: Out { sink, pos: 0, crc },
            stage: [0; STAGE],
            staged: 0,
        }
    }

    /// Writes out what is gathered.
    fn flush(&mut self) -> Result<(), EncodeError> {
        if self.staged > 0 {
            let n = std::mem::take(&mut self.staged);
            self.out.write_chunk(&self.stage[..n])?;
        }
        Ok(())
    }

    /// Flushes and returns the bytes written and the CRC.
    fn finish(mut self) -> Result<(usize, Option<crc32fast::Hasher>), EncodeError> {
        self.flush()?;
        Ok((self.out.pos, self.out.crc))
    }
}

impl Writer for BodyWriter<'_> {
    #[inline]
    fn write(&mut self, bytes: &[u8]) -> Result<(), EncodeError> {
        if matches!(self.out.sink, Sink::Count) {
            self.out.pos += bytes.len();
            return Ok(());
        }
        if bytes.len() <= SMALL_WRITE {
            if self.staged + bytes.len() > STAGE {
                self.flush()?;
            }
            self.stage[self.staged..self.staged + bytes.len()].copy_from_slice(bytes);
            self.staged += bytes.len();
            return Ok(());
        }
        self.flush()?;
        for chunk in bytes.chunks(FUSED_CHUNK) {
            self.out.write_chunk(chunk)?;
        }
        Ok(())
    }
}

/// Length in bytes of `body` once encoded (without the header).
pub fn body_len(body: &dyn WireBody) -> Result<u64, CodecError> {
    // bincode's own size writer for `Serialize` bodies; PreEncoded bodies report their length
    // through the same counting writer.
    let mut w = BodyWriter::new(Sink::Count, None);
    body.encode_body(&mut w)?;
    let (len, _) = w.finish().map_err(encode_error)?;
    Ok(len as u64)
}

/// `HEADER_LEN + body_len(body)`.
pub fn encoded_len(body: &dyn WireBody) -> Result<u64, CodecError> {
    Ok(HEADER_LEN as u64 + body_len(body)?)
}

/// Measures a `Serialize` value with bincode's [`SizeWriter`] (used by benchmarks and tests to
/// cross-check [`body_len`]).
pub fn serde_len<T: Serialize + ?Sized>(value: &T) -> Result<u64, CodecError> {
    let mut w = SizeWriter::default();
    bincode::serde::encode_into_writer(value, &mut w, BINCODE).map_err(encode_error)?;
    Ok(w.bytes_written as u64)
}

fn header_for(
    meta: &SendMeta,
    sender: NodeId,
    body_len: u64,
    max_body_len: u64,
) -> Result<Header, CodecError> {
    if !meta.sim_time.is_finite() {
        return Err(HeaderError::NonFiniteTime.into());
    }
    let max = max_body_len.min(HARD_MAX_BODY_LEN);
    if body_len > max {
        return Err(CodecError::TooLarge { len: body_len, max });
    }
    Ok(Header::new(meta, sender, body_len))
}

fn finish(
    mut header: Header,
    w: BodyWriter<'_>,
    measured: u64,
) -> Result<(Header, [u8; 4]), CodecError> {
    let (written, crc) = w.finish().map_err(encode_error)?;
    if written as u64 != measured {
        return Err(CodecError::LengthChanged {
            measured,
            written: written as u64,
        });
    }
    header.checksum = crc.map(|h| h.finalize()).unwrap_or(0);
    Ok((header, header.checksum.to_le_bytes()))
}

/// Encodes header and body into `out[..HEADER_LEN + body_len]` where `body_len` was measured
/// with [`body_len`]. Returns the number of bytes written.
pub fn encode_into(
    meta: &SendMeta,
    sender: NodeId,
    body: &dyn WireBody,
    body_len: u64,
    max_body_len: u64,
    out: &mut [u8],
) -> Result<usize, CodecError> {
    let header = header_for(meta, sender, body_len, max_body_len)?;
    let total = HEADER_LEN + body_len as usize;
    if out.len() < total {
        return Err(CodecError::BufferTooSmall {
            need: total as u64,
            have: out.len() as u64,
        });
    }
    let (head, rest) = out.split_at_mut(HEADER_LEN);
    let head: &mut [u8; HEADER_LEN] = head
        .try_into()
        .map_err(|_| CodecError::Encode("header split".into()))?;
    header.write_to(head);
    let mut crc = crc32fast::Hasher::new();
    crc.update(&head[..OFF_CHECKSUM]);
    let mut w = BodyWriter::new(Sink::Init(&mut rest[..body_len as usize]), Some(crc));
    body.encode_body(&mut w)?;
    let (_, sum) = finish(header, w, body_len)?;
    head[OFF_CHECKSUM..OFF_CHECKSUM + 4].copy_from_slice(&sum);
    Ok(total)
}

/// Like [`encode_into`] but into uninitialised memory (a freshly loaned shared-memory sample).
/// On success every byte of `out[..HEADER_LEN + body_len]` is initialised and bytes beyond are
/// set to zero, so the caller may treat all of `out` as initialised. On error the contents are
/// unspecified but still fully initialised (zero-filled) for the same reason.
pub fn encode_into_uninit(
    meta: &SendMeta,
    sender: NodeId,
    body: &dyn WireBody,
    body_len: u64,
    max_body_len: u64,
    out: &mut [MaybeUninit<u8>],
) -> Result<usize, CodecError> {
    let result = encode_into_uninit_inner(meta, sender, body, body_len, max_body_len, out);
    let initialised = match &result {
        Ok(n) => *n,
        Err(_) => 0,
    };
    for b in &mut out[initialised..] {
        b.write(0);
    }
    result
}

fn encode_into_uninit_inner(
    meta: &SendMeta,
    sender: NodeId,
    body: &dyn WireBody,
    body_len: u64,
    max_body_len: u64,
    out: &mut [MaybeUninit<u8>],
) -> Result<usize, CodecError> {
    let header = header_for(meta, sender, body_len, max_body_len)?;
    let total = HEADER_LEN + body_len as usize;
    if out.len() < total {
        return Err(CodecError::BufferTooSmall {
            need: total as u64,
            have: out.len() as u64,
        });
    }
    let mut head = [0u8; HEADER_LEN];
    header.write_to(&mut head);
    let mut crc = crc32fast::Hasher::new();
    crc.update(&head[..OFF_CHECKSUM]);
    let (out_head, rest) = out.split_at_mut(HEADER_LEN);
    let mut w = BodyWriter::new(Sink::Uninit(&mut rest[..body_len as usize]), Some(crc));
    if let Err(e) = body.encode_body(&mut w) {
        out_head.write_copy_of_slice(&head);
        return Err(e);
    }
    let (_, sum) = finish(header, w, body_len).inspect_err(|_| {
        out_head.write_copy_of_slice(&head);
    })?;
    head[OFF_CHECKSUM..OFF_CHECKSUM + 4].copy_from_slice(&sum);
    out_head.write_copy_of_slice(&head);
    Ok(total)
}

/// Encodes a whole message into a new `Vec` (allocated once at the exact size, filled by
/// appending, so there is no zero-fill pass).
pub fn encode_to_vec(
    meta: &SendMeta,
    sender: NodeId,
    body: &dyn WireBody,
    max_body_len: u64,
) -> Result<Vec<u8>, CodecError> {
    let len = body_len(body)?;
    let header = header_for(meta, sender, len, max_body_len)?;
    let mut head = [0u8; HEADER_LEN];
    header.write_to(&mut head);
    let mut crc = crc32fast::Hasher::new();
    crc.update(&head[..OFF_CHECKSUM]);
    let mut out = Vec::with_capacity(HEADER_LEN + len as usize);
    out.extend_from_slice(&head);
    let mut w = BodyWriter::new(Sink::Append(&mut out), Some(crc));
    body.encode_body(&mut w)?;
    let (_, sum) = finish(header, w, len)?;
    out[OFF_CHECKSUM..OFF_CHECKSUM + 4].copy_from_slice(&sum);
    Ok(out)
}

/// Encodes only the body (no header, no checksum) into a new `Vec`, in one pass (the body's
/// `Serialize` runs once; the `Vec` grows as needed) — e.g. to send it as [`PreEncoded`]
/// when serialising is dearer than copying, or to hold it back.
pub fn encode_body_to_vec(body: &dyn WireBody) -> Result<Vec<u8>, CodecError> {
    // Room for a small message at once; a large one grows by doubling.
    let mut out = Vec::with_capacity(4096);
    let mut w = BodyWriter::new(Sink::Append(&mut out), None);
    body.encode_body(&mut w)?;
    w.finish().map_err(encode_error)?;
    Ok(out)
}

/// The zstd level of [`compress_body`]: level 1 compresses an f64 information delta at
/// ~600 MB/s on the development machine; higher levels gained < 1 % on such data.
pub const ZSTD_LEVEL: i32 = 1;

/// Encodes `body` and compresses it into one zstd frame (its content size declared, so the
/// receiver can bound it before decompressing). Send the result as [`PreEncoded`] with
/// [`SendMeta::compressed`] set.
pub fn compress_body(body: &dyn WireBody) -> Result<Vec<u8>, CodecError> {
    let raw = encode_body_to_vec(body)?;
    zstd::bulk::compress(&raw, ZSTD_LEVEL).map_err(|e| CodecError::Encode(e.to_string()))
}

/// Decompresses a [`FLAG_ZSTD`](crate::envelope::FLAG_ZSTD) body: one zstd frame whose
/// declared content size is at most `max_len` (a frame without a declared size, or declaring
/// more, is rejected before any allocation: no decompression bomb gets through).
pub fn decompress_body(frame: &[u8], max_len: u64) -> Result<Vec<u8>, CodecError> {
    let size = match zstd::zstd_safe::get_frame_content_size(frame) {
        Ok(Some(n)) => n,
        Ok(None) => return Err(CodecError::Decompress("no declared content size".into())),
        Err(_) => return Err(CodecError::Decompress("not a zstd frame".into())),
    };
    let max = max_len.min(HARD_MAX_BODY_LEN);
    if size > max {
        return Err(CodecError::TooLarge { len: size, max });
    }
    let out = zstd::bulk::decompress(frame, size as usize)
        .map_err(|e| CodecError::Decompress(e.to_string()))?;
    if out.len() as u64 != size {
        return Err(CodecError::Decompress(format!(
            "declared {size} bytes, decompressed {}",
            out.len()
        )));
    }
    Ok(out)
}

/// Decodes a body into an owned `B`, decompressing it first when the header says it is
/// compressed (then at most `max_len` bytes once decompressed), and validates it.
pub fn decode_body_owned<B: serde::de::DeserializeOwned + Validate>(
    header: &Header,
    body: &[u8],
    max_len: u64,
) -> Result<B, CodecError> {
    if header.compressed {
        let raw = decompress_body(body, max_len)?;
        decode_body(&raw)
    } else {
        decode_body(body)
    }
}

/// Incremental envelope CRC over a message arriving in pieces: covers bytes `0..60` and
/// `64..`, i.e. everything but the checksum field itself.
#[derive(Debug, Clone, Default)]
pub struct EnvelopeCrc(crc32fast::Hasher);

impl EnvelopeCrc {
    /// Empty.
    pub fn new() -> Self {
        Self::default()
    }
    /// Adds `piece`, which sits at byte offset `at` of the message (pieces in order).
    pub fn update(&mut self, at: usize, piece: &[u8]) {
        let end = at + piece.len();
        if at < OFF_CHECKSUM {
            self.0.update(&piece[..end.min(OFF_CHECKSUM) - at]);
        }
        if end > HEADER_LEN {
            self.0.update(&piece[HEADER_LEN.max(at) - at..]);
        }
    }
    /// The CRC.
    pub fn finalize(self) -> u32 {
        self.0.finalize()
    }
}

/// Validates the envelope of a received message: header, size limit, exact length and
/// checksum. Returns the header and the body bytes (borrowed from `bytes`).
pub fn open_envelope(bytes: &[u8], max_body_len: u64) -> Result<(Header, &[u8]), CodecError> {
    open_envelope_with_crc(bytes, max_body_len, None)
}

/// [`open_envelope`] with the CRC of `bytes` (as [`EnvelopeCrc`] computes it) already known, e.g.
/// computed while the message was copied; `None` computes it here.
pub fn open_envelope_with_crc(
    bytes: &[u8],
    max_body_len: u64,
    crc: Option<u32>,
) -> Result<(Header, &[u8]), CodecError> {
    let header = parse_header(bytes)?;
    let max = max_body_len.min(HARD_MAX_BODY_LEN);
    if header.body_len > max {
        return Err(CodecError::TooLarge {
            len: header.body_len,
            max,
        });
    }
    let available = (bytes.len() - HEADER_LEN) as u64;
    if available < header.body_len {
        return Err(CodecError::Truncated {
            declared: header.body_len,
            available,
        });
    }
    if available > header.body_len {
        return Err(CodecError::TrailingBytes {
            extra: available - header.body_len,
        });
    }
    let body = &bytes[HEADER_LEN..];
    let computed = crc.unwrap_or_else(|| {
        let mut h = crc32fast::Hasher::new();
        h.update(&bytes[..OFF_CHECKSUM]);
        h.update(body);
        h.finalize()
    });
    if computed != header.checksum {
        return Err(CodecError::Checksum {
            expected: header.checksum,
            computed,
        });
    }
    Ok((header, body))
}

/// Decodes a body (from [`open_envelope`]) into `B` with bincode, requires that it consumes
/// every byte, then runs `B::validate`.
pub fn decode_body<'a, B: Deserialize<'a> + Validate>(body: &'a [u8]) -> Result<B, CodecError> {
    let (value, used): (B, usize) =
        bincode::serde::borrow_decode_from_slice(body, BINCODE).map_err(decode_error)?;
    if used != body.len() {
        return Err(CodecError::BodyNotConsumed {
            used: used as u64,
            len: body.len() as u64,
        });
    }
    value.validate()?;
    Ok(value)
}

/// [`open_envelope`] then [`decode_body`] (a compressed body is [`CodecError::CompressedBorrow`]:
/// use [`decode_owned`]).
pub fn decode<'a, B: Deserialize<'a> + Validate>(
    bytes: &'a [u8],
    max_body_len: u64,
) -> Result<(Header, B), CodecError> {
    let (header, body) = open_envelope(bytes, max_body_len)?;
    if header.compressed {
        return Err(CodecError::CompressedBorrow);
    }
    Ok((header, decode_body(body)?))
}

/// [`open_envelope`] then [`decode_body_owned`]: compressed bodies are decompressed (to at
/// most `max_body_len` bytes).
pub fn decode_owned<B: serde::de::DeserializeOwned + Validate>(
    bytes: &[u8],
    max_body_len: u64,
) -> Result<(Header, B), CodecError> {
    let (header, body) = open_envelope(bytes, max_body_len)?;
    let value = decode_body_owned(&header, body, max_body_len)?;
    Ok((header, value))
}

fn decode_error(e: DecodeError) -> CodecError {
    CodecError::BodyDecode(e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envelope::MessageKind;
    use crate::wire::{WireBytes, WireSymMatrix, WireVector};

    fn meta() -> SendMeta {
        SendMeta {
            kind: MessageKind::DDF_DELTA,
            sender_epoch: 3,
            receiver_epoch: 4,
            seq: 99,
            sim_time: 12.25,
            compressed: false,
        }
    }

    #[test]
    fn round_trip_through_vec_slice_and_uninit_agree() {
        let body = WireSymMatrix::from_fn(5, |i, j| (i * 10 + j) as f64 + 0.5);
        let v = encode_to_vec(&meta(), 7, &body, DEFAULT_MAX_BODY_LEN).unwrap();
        let len = body_len(&body).unwrap();
        assert_eq!(len, serde_len(&body).unwrap());
        assert_eq!(v.len() as u64, HEADER_LEN as u64 + len);

        let mut buf = vec![0xAAu8; v.len() + 10];
        let n = encode_into(&meta(), 7, &body, len, DEFAULT_MAX_BODY_LEN, &mut buf).unwrap();
        assert_eq!(&buf[..n], &v[..]);

        let mut un = vec![MaybeUninit::<u8>::uninit(); v.len() + 10];
        let n = encode_into_uninit(&meta(), 7, &body, len, DEFAULT_MAX_BODY_LEN, &mut un).unwrap();
        let bytes: Vec<u8> = un.iter().map(init_byte).collect();
        assert_eq!(&bytes[..n], &v[..]);
        assert!(bytes[n..].iter().all(|&b| b == 0));

        let (h, back): (Header, WireSymMatrix) = decode(&v, DEFAULT_MAX_BODY_LEN).unwrap();
        assert_eq!(h.meta(), meta());
        assert_eq!(h.sender, 7);
        assert_eq!(back, body);
    }

    /// Reads a byte that `encode_into_uninit` documents as initialised (it writes the message
    /// and zero-fills the tail of the buffer it is given).
    #[allow(unsafe_code)]
    fn init_byte(b: &MaybeUninit<u8>) -> u8 {
        // SAFETY: `encode_into_uninit` initialises every element of the slice it is given (the
        // message then a zero fill), on success and on error alike.
        unsafe { b.assume_init() }
    }

    #[test]
    fn every_corruption_is_a_typed_error() {
        let body = WireVector::from_slice(&[1.0, 2.0, 3.0]);
        let v = encode_to_vec(&meta(), 1, &body, DEFAULT_MAX_BODY_LEN).unwrap();
        // Truncated body.
        assert!(matches!(
            open_envelope(&v[..v.len() - 1], DEFAULT_MAX_BODY_LEN),
            Err(CodecError::Truncated { .. })
        ));
        // Trailing bytes.
        let mut t = v.clone();
        t.push(0);
        assert!(matches!(
            open_envelope(&t, DEFAULT_MAX_BODY_LEN),
            Err(CodecError::TrailingBytes { extra: 1 })
        ));
        // Flipped bit in the body.
        let mut c = v.clone();
        let last = c.len() - 1;
        c[last] ^= 0x10;
        assert!(matches!(
            open_envelope(&c, DEFAULT_MAX_BODY_LEN),
            Err(CodecError::Checksum { .. })
        ));
        // Flipped bit in a header field covered by the checksum.
        let mut c = v.clone();
        c[33] ^= 1;
        assert!(matches!(
            open_envelope(&c, DEFAULT_MAX_BODY_LEN),
            Err(CodecError::Checksum { .. })
        ));
        // Size limit.
        assert!(matches!(
            open_envelope(&v, 4),
            Err(CodecError::TooLarge { max: 4, .. })
        ));
        // Wrong body type: a byte blob is not a vector of floats.
        let raw =
            encode_to_vec(&meta(), 1, &WireBytes(vec![1, 2, 3]), DEFAULT_MAX_BODY_LEN).unwrap();
        assert!(decode::<WireVector>(&raw, DEFAULT_MAX_BODY_LEN).is_err());
        // Non-finite time is refused at encode time.
        let mut m = meta();
        m.sim_time = f64::INFINITY;
        assert_eq!(
            encode_to_vec(&m, 1, &body, DEFAULT_MAX_BODY_LEN),
            Err(CodecError::Header(HeaderError::NonFiniteTime))
        );
        // Too-small output buffer.
        let len = body_len(&body).unwrap();
        let mut small = [0u8; 10];
        assert!(matches!(
            encode_into(&meta(), 1, &body, len, DEFAULT_MAX_BODY_LEN, &mut small),
            Err(CodecError::BufferTooSmall { .. })
        ));
    }

    #[test]
    fn piecewise_envelope_crc_matches_the_whole_message_crc() {
        let body = WireBytes((0..5000u32).map(|i| (i * 7) as u8).collect());
        let v = encode_to_vec(&meta(), 2, &body, DEFAULT_MAX_BODY_LEN).unwrap();
        let expected = parse_header_checksum(&v);
        // Every split pattern, including pieces that straddle the checksum field.
        for piece in [1usize, 3, 7, 59, 60, 61, 63, 64, 65, 100, 4096, v.len()] {
            let mut c = EnvelopeCrc::new();
            let mut at = 0;
            for p in v.chunks(piece) {
                c.update(at, p);
                at += p.len();
            }
            let got = c.finalize();
            assert_eq!(got, expected, "piece {piece}");
            assert!(open_envelope_with_crc(&v, DEFAULT_MAX_BODY_LEN, Some(got)).is_ok());
        }
        assert!(matches!(
            open_envelope_with_crc(&v, DEFAULT_MAX_BODY_LEN, Some(expected ^ 1)),
            Err(CodecError::Checksum { .. })
        ));
    }

    fn parse_header_checksum(v: &[u8]) -> u32 {
        crate::envelope::parse_header(v).unwrap().checksum
    }

    #[test]
    fn pre_encoded_body_reproduces_the_original_message() {
        let body = WireVector::from_slice(&[4.0, -5.5]);
        let direct = encode_to_vec(&meta(), 2, &body, DEFAULT_MAX_BODY_LEN).unwrap();
        let b = encode_body_to_vec(&body).unwrap();
        let again = encode_to_vec(&meta(), 2, &PreEncoded(&b), DEFAULT_MAX_BODY_LEN).unwrap();
        assert_eq!(direct, again);
    }

    #[test]
    fn unknown_kind_decodes_and_is_passed_up() {
        let mut m = meta();
        m.kind = MessageKind(4242);
        let v = encode_to_vec(&m, 2, &WireBytes(vec![9; 5]), DEFAULT_MAX_BODY_LEN).unwrap();
        let (h, b): (Header, WireBytes) = decode(&v, DEFAULT_MAX_BODY_LEN).unwrap();
        assert_eq!(h.kind, MessageKind(4242));
        assert_eq!(b.0, vec![9; 5]);
    }
}
