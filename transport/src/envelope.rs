//! The envelope: a fixed 64-byte little-endian header in front of every message body.
//!
//! The header is hand-laid-out (not bincode) so that a receiver can check magic, version, size
//! and checksum before touching the body, and so that the checksum sits at a fixed offset that an
//! encoder can fill in after streaming the body into a shared-memory sample.
//!
//! ```text
//! offset size field
//!  0      4   magic            b"CNPY"
//!  4      2   format version   u16  (FORMAT_VERSION; any other value is rejected)
//!  6      2   kind             u16  (MessageKind; open set, unknown kinds are passed up)
//!  8      4   sender           u32  (NodeId of the sending node)
//! 12      4   flags            u32  (bit 0: the body is a zstd frame of the encoded body,
//!                                   FLAG_ZSTD; every other bit must be 0)
//! 16      8   sender epoch     u64  (incarnation of the sender)
//! 24      8   receiver epoch   u64  (incarnation of the receiver as known by the sender)
//! 32      8   sequence         u64
//! 40      8   sim time         f64  (simulation time stamp, seconds; must be finite)
//! 48      8   body length      u64  (bytes after the header)
//! 56      4   reserved         u32  (must be 0 in version 1)
//! 60      4   checksum         u32  CRC-32 (IEEE) over bytes 0..60 followed by the body
//! ```

use std::fmt;

use serde::{Deserialize, Serialize};

/// Identifies a canopy node (a vehicle, the hub, the world process...).
pub type NodeId = u32;

/// First four bytes of every canopy message.
pub const MAGIC: [u8; 4] = *b"CNPY";
/// The only envelope/body format version this build understands (2: flags bit 0 defined).
pub const FORMAT_VERSION: u16 = 2;
/// Flags bit: the body is a zstd frame of the encoded body ([`crate::codec::compress_body`]).
pub const FLAG_ZSTD: u32 = 1;
/// Size of the fixed header in bytes.
pub const HEADER_LEN: usize = 64;

const OFF_MAGIC: usize = 0;
const OFF_VERSION: usize = 4;
const OFF_KIND: usize = 6;
const OFF_SENDER: usize = 8;
const OFF_FLAGS: usize = 12;
const OFF_SENDER_EPOCH: usize = 16;
const OFF_RECEIVER_EPOCH: usize = 24;
const OFF_SEQ: usize = 32;
const OFF_SIM_TIME: usize = 40;
const OFF_BODY_LEN: usize = 48;
const OFF_RESERVED: usize = 56;
/// Offset of the CRC-32; the checksum covers `[0, OFF_CHECKSUM)` and then the body.
pub const OFF_CHECKSUM: usize = 60;

/// Kind of a message: an open set of `u16` codes. Unknown codes are not an error: they are passed
/// up to the application so the schema can grow without breaking older receivers' links.
#[derive(Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct MessageKind(pub u16);

impl MessageKind {
    /// Information-form map delta (ΔY, Δy) of the channel filter.
    pub const DDF_DELTA: Self = Self(1);
    /// DDF protocol control (resync requests, cumulative-sent summaries, CI switch...).
    pub const DDF_CONTROL: Self = Self(2);
    /// A batch of IMU samples.
    pub const IMU_BATCH: Self = Self(3);
    /// A frame of terrain-feature observations.
    pub const OBSERVATION_FRAME: Self = Self(4);
    /// A vehicle's estimate report (to the monitor).
    pub const ESTIMATE_REPORT: Self = Self(5);
    /// A map report (to the monitor).
    pub const MAP_REPORT: Self = Self(6);
    /// Process control (start, stop, step...).
    pub const CONTROL: Self = Self(7);
    /// Liveness heartbeat.
    pub const HEARTBEAT: Self = Self(8);
    /// A simulation-time marker on a fusion link (empty body): the sender has sent everything
    /// it stamps with a time up to the header's (simulation-time delivery, canopy-node).
    pub const TIME_MARKER: Self = Self(9);

    /// Name of a known kind, `None` for codes this build does not know.
    pub fn name(self) -> Option<&'static str> {
        Some(match self {
            Self::DDF_DELTA => "ddf-delta",
            Self::DDF_CONTROL => "ddf-control",
            Self::IMU_BATCH => "imu-batch",
            Self::OBSERVATION_FRAME => "observation-frame",
            Self::ESTIMATE_REPORT => "estimate-report",
            Self::MAP_REPORT => "map-report",
            Self::CONTROL => "control",
            Self::HEARTBEAT => "heartbeat",
            Self::TIME_MARKER => "time-marker",
            _ => return None,
        })
    }
}

impl fmt::Debug for MessageKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.name() {
            Some(n) => write!(f, "MessageKind({n})"),
            None => write!(f, "MessageKind(unknown {})", self.0),
        }
    }
}

/// Header fields the application chooses for each message it sends. The sender id and body
/// length are filled in by the link.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SendMeta {
    /// What the body is.
    pub kind: MessageKind,
    /// Incarnation of the sending node.
    pub sender_epoch: u64,
    /// Incarnation of the receiving node as last known by the sender (0 = unknown).
    pub receiver_epoch: u64,
    /// Sequence number (the application's, e.g. per-link DDF sequence).
    pub seq: u64,
    /// Simulation time stamp in seconds; must be finite.
    pub sim_time: f64,
    /// The body passed to `send` is a zstd frame of the encoded body (sets [`FLAG_ZSTD`]).
    pub compressed: bool,
}

impl SendMeta {
    /// Meta with epochs 0 and the given kind, sequence number and time.
    pub fn new(kind: MessageKind, seq: u64, sim_time: f64) -> Self {
        Self {
            kind,
            sender_epoch: 0,
            receiver_epoch: 0,
            seq,
            sim_time,
            compressed: false,
        }
    }
}

/// A decoded and validated header.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Header {
    /// Message kind (possibly unknown to this build).
    pub kind: MessageKind,
    /// Sending node.
    pub sender: NodeId,
    /// Incarnation of the sender.
    pub sender_epoch: u64,
    /// Incarnation of the receiver as known by the sender.
    pub receiver_epoch: u64,
    /// Sequence number.
    pub seq: u64,
    /// Simulation time stamp (seconds, finite).
    pub sim_time: f64,
    /// Body length in bytes.
    pub body_len: u64,
    /// CRC-32 over header bytes 0..60 and the body.
    pub checksum: u32,
    /// The body is a zstd frame ([`FLAG_ZSTD`]).
    pub compressed: bool,
}

impl Header {
    /// Header for `meta` sent by `sender` with a body of `body_len` bytes (checksum still 0).
    pub fn new(meta: &SendMeta, sender: NodeId, body_len: u64) -> Self {
        Self {
            kind: meta.kind,
            sender,
            sender_epoch: meta.sender_epoch,
            receiver_epoch: meta.receiver_epoch,
            seq: meta.seq,
            sim_time: meta.sim_time,
            body_len,
            checksum: 0,
            compressed: meta.compressed,
        }
    }

    /// The application-chosen fields of this header.
    pub fn meta(&self) -> SendMeta {
        SendMeta {
            kind: self.kind,
            sender_epoch: self.sender_epoch,
            receiver_epoch: self.receiver_epoch,
            seq: self.seq,
            sim_time: self.sim_time,
            compressed: self.compressed,
        }
    }

    /// Writes the fixed layout into `out` (including the current `checksum` field).
    pub fn write_to(&self, out: &mut [u8; HEADER_LEN]) {
        out[OFF_MAGIC..OFF_MAGIC + 4].copy_from_slice(&MAGIC);
        out[OFF_VERSION..OFF_VERSION + 2].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        out[OFF_KIND..OFF_KIND + 2].copy_from_slice(&self.kind.0.to_le_bytes());
        out[OFF_SENDER..OFF_SENDER + 4].copy_from_slice(&self.sender.to_le_bytes());
        let flags = if self.compressed { FLAG_ZSTD } else { 0 };
        out[OFF_FLAGS..OFF_FLAGS + 4].copy_from_slice(&flags.to_le_bytes());
        out[OFF_SENDER_EPOCH..OFF_SENDER_EPOCH + 8]
            .copy_from_slice(&self.sender_epoch.to_le_bytes());
        out[OFF_RECEIVER_EPOCH..OFF_RECEIVER_EPOCH + 8]
            .copy_from_slice(&self.receiver_epoch.to_le_bytes());
        out[OFF_SEQ..OFF_SEQ + 8].copy_from_slice(&self.seq.to_le_bytes());
        out[OFF_SIM_TIME..OFF_SIM_TIME + 8].copy_from_slice(&self.sim_time.to_le_bytes());
        out[OFF_BODY_LEN..OFF_BODY_LEN + 8].copy_from_slice(&self.body_len.to_le_bytes());
        out[OFF_RESERVED..OFF_RESERVED + 4].copy_from_slice(&0u32.to_le_bytes());
        out[OFF_CHECKSUM..OFF_CHECKSUM + 4].copy_from_slice(&self.checksum.to_le_bytes());
    }
}

/// Why a header could not be parsed. (The checksum is checked by the codec, which sees the body.)
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum HeaderError {
    /// Fewer than [`HEADER_LEN`] bytes.
    #[error("message of {len} bytes is shorter than the {HEADER_LEN}-byte header")]
    Truncated {
        /// Bytes available.
        len: usize,
    },
    /// The first four bytes are not [`MAGIC`].
    #[error("bad magic {found:02x?}")]
    BadMagic {
        /// What was found.
        found: [u8; 4],
    },
    /// A format version other than [`FORMAT_VERSION`].
    #[error("unsupported format version {found} (this build speaks {FORMAT_VERSION})")]
    UnsupportedVersion {
        /// What was found.
        found: u16,
    },
    /// Flags or reserved bits set that version 1 does not define.
    #[error("reserved header bits set (flags {flags:#x}, reserved {reserved:#x})")]
    ReservedBits {
        /// The flags word.
        flags: u32,
        /// The reserved word.
        reserved: u32,
    },
    /// The simulation time stamp is NaN or infinite.
    #[error("non-finite simulation time stamp")]
    NonFiniteTime,
}

fn le_u16(b: &[u8], off: usize) -> u16 {
    u16::from_le_bytes([b[off], b[off + 1]])
}
fn le_u32(b: &[u8], off: usize) -> u32 {
    u32::from_le_bytes([b[off], b[off + 1], b[off + 2], b[off + 3]])
}
fn le_u64(b: &[u8], off: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[off..off + 8]);
    u64::from_le_bytes(a)
}

/// Parses and validates the header at the start of `bytes` (magic, version, reserved bits, finite
/// time). Does not check the body length against `bytes` nor the checksum: see
/// [`crate::codec::open_envelope`].
pub fn parse_header(bytes: &[u8]) -> Result<Header, HeaderError> {
    if bytes.len() < HEADER_LEN {
        return Err(HeaderError::Truncated { len: bytes.len() });
    }
    let mut magic = [0u8; 4];
    magic.copy_from_slice(&bytes[OFF_MAGIC..OFF_MAGIC + 4]);
    if magic != MAGIC {
        return Err(HeaderError::BadMagic { found: magic });
    }
    let version = le_u16(bytes, OFF_VERSION);
    if version != FORMAT_VERSION {
        return Err(HeaderError::UnsupportedVersion { found: version });
    }
    let flags = le_u32(bytes, OFF_FLAGS);
    let reserved = le_u32(bytes, OFF_RESERVED);
    if flags & !FLAG_ZSTD != 0 || reserved != 0 {
        return Err(HeaderError::ReservedBits { flags, reserved });
    }
    let sim_time = f64::from_bits(le_u64(bytes, OFF_SIM_TIME));
    if !sim_time.is_finite() {
        return Err(HeaderError::NonFiniteTime);
    }
    Ok(Header {
        kind: MessageKind(le_u16(bytes, OFF_KIND)),
        sender: le_u32(bytes, OFF_SENDER),
        sender_epoch: le_u64(bytes, OFF_SENDER_EPOCH),
        receiver_epoch: le_u64(bytes, OFF_RECEIVER_EPOCH),
        seq: le_u64(bytes, OFF_SEQ),
        sim_time,
        body_len: le_u64(bytes, OFF_BODY_LEN),
        checksum: le_u32(bytes, OFF_CHECKSUM),
        compressed: flags & FLAG_ZSTD != 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_round_trips_every_field() {
        let h = Header {
            kind: MessageKind(0xBEEF),
            sender: 0xDEAD_BEEF,
            sender_epoch: u64::MAX - 1,
            receiver_epoch: 7,
            seq: 1 << 40,
            sim_time: -12.5,
            body_len: 123_456,
            checksum: 0x0102_0304,
            compressed: true,
        };
        let mut buf = [0u8; HEADER_LEN];
        h.write_to(&mut buf);
        assert_eq!(&buf[..4], b"CNPY");
        assert_eq!(parse_header(&buf).unwrap(), h);
    }

    #[test]
    fn header_rejections_are_typed() {
        let h = Header::new(&SendMeta::new(MessageKind::HEARTBEAT, 1, 0.0), 3, 0);
        let mut buf = [0u8; HEADER_LEN];
        h.write_to(&mut buf);
        assert_eq!(
            parse_header(&buf[..10]),
            Err(HeaderError::Truncated { len: 10 })
        );
        let mut b = buf;
        b[0] = b'X';
        assert!(matches!(
            parse_header(&b),
            Err(HeaderError::BadMagic { .. })
        ));
        let mut b = buf;
        b[OFF_VERSION] = 1;
        assert_eq!(
            parse_header(&b),
            Err(HeaderError::UnsupportedVersion { found: 1 })
        );
        let mut b = buf;
        b[OFF_FLAGS] = 2;
        assert!(matches!(
            parse_header(&b),
            Err(HeaderError::ReservedBits { .. })
        ));
        // The compression flag is the one defined bit.
        let mut b = buf;
        b[OFF_FLAGS] = 1;
        assert!(parse_header(&b).unwrap().compressed);
        let mut b = buf;
        b[OFF_SIM_TIME..OFF_SIM_TIME + 8].copy_from_slice(&f64::NAN.to_le_bytes());
        assert_eq!(parse_header(&b), Err(HeaderError::NonFiniteTime));
    }

    #[test]
    fn unknown_kinds_have_no_name_but_are_representable() {
        assert_eq!(MessageKind::DDF_DELTA.name(), Some("ddf-delta"));
        assert_eq!(MessageKind(999).name(), None);
        assert_eq!(
            format!("{:?}", MessageKind(999)),
            "MessageKind(unknown 999)"
        );
    }
}
