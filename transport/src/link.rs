//! The [`Link`] trait every backend implements, and what links share: statistics, received
//! messages, peer events, the receive-side admission check.
//!
//! A link joins this node to exactly one configured peer. Sending encodes the body straight into
//! the backend's buffer; receiving returns a [`Received`] guard that owns the backend's buffer
//! (a shared-memory sample, a zenoh payload, a `Vec`) and decodes the body from it in place.
//! Only messages that pass the envelope checks *and* come from the configured peer are returned;
//! everything else is dropped and counted in [`LinkStats::rejected`] by reason.

use std::fmt;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use serde::Deserialize;

use crate::codec::{self, CodecError, WireBody};
use crate::envelope::{Header, HeaderError, NodeId, SendMeta};
use crate::wire::Validate;

/// Options every backend understands.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkConfig {
    /// This node.
    pub local: NodeId,
    /// The only node whose messages this link accepts.
    pub peer: NodeId,
    /// Largest body accepted or sent (bytes). Shared memory is sized from it.
    pub max_body_len: u64,
}

impl LinkConfig {
    /// Link from `local` to `peer` with the default 64 MiB body limit.
    pub fn new(local: NodeId, peer: NodeId) -> Self {
        Self {
            local,
            peer,
            max_body_len: codec::DEFAULT_MAX_BODY_LEN,
        }
    }
    /// Same, with another body limit.
    pub fn with_max_body_len(mut self, max_body_len: u64) -> Self {
        self.max_body_len = max_body_len;
        self
    }
}

/// Why a link failed (not why a message was rejected: rejections are counted, not returned).
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The body could not be encoded (too large, non-finite time, serde error).
    #[error("encode: {0}")]
    Encode(#[from] CodecError),
    /// The backend failed (iceoryx2 or zenoh error, closed session...).
    #[error("{backend}: {detail}")]
    Backend {
        /// Which backend.
        backend: &'static str,
        /// What went wrong.
        detail: String,
    },
    /// Invalid configuration (bad name, endpoint, prefix...).
    #[error("configuration: {0}")]
    Config(String),
}

impl LinkError {
    pub(crate) fn backend(backend: &'static str, detail: impl fmt::Display) -> Self {
        Self::Backend {
            backend,
            detail: detail.to_string(),
        }
    }
}

/// What a link knows about its peer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PeerState {
    /// The peer has not been seen yet, or is gone.
    Down,
    /// The peer is present.
    Up,
}

/// Peer transitions, reported once each by [`Link::poll_event`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkEvent {
    /// The peer appeared (first time, or again after a restart or an outage).
    PeerUp,
    /// The peer disappeared (process exit or crash, session loss, injected outage).
    PeerDown,
}

/// Rejection counters, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rejections {
    /// Shorter than the header, or than the declared body.
    pub truncated: u64,
    /// Bad magic (garbage).
    pub bad_magic: u64,
    /// Unknown format version.
    pub bad_version: u64,
    /// Reserved bits set, non-finite time, trailing bytes.
    pub bad_header: u64,
    /// Declared body larger than the link's limit.
    pub too_large: u64,
    /// CRC-32 mismatch.
    pub checksum: u64,
    /// Valid envelope from a node that is not this link's peer.
    pub wrong_sender: u64,
    /// Envelope fine, body failed to decode or validate (counted by [`Received::decode`]).
    pub body: u64,
}

impl Rejections {
    /// Sum over all reasons.
    pub fn total(&self) -> u64 {
        self.truncated
            + self.bad_magic
            + self.bad_version
            + self.bad_header
            + self.too_large
            + self.checksum
            + self.wrong_sender
            + self.body
    }
}

/// Counters of one link (a snapshot).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Messages handed to the backend.
    pub sent_messages: u64,
    /// Bytes handed to the backend (header + body).
    pub sent_bytes: u64,
    /// Messages the backend could not deliver because no peer was attached.
    pub dropped_no_peer: u64,
    /// Messages the backend dropped because the peer's receive queue was full.
    pub dropped_overflow: u64,
    /// Messages accepted and returned to the application.
    pub received_messages: u64,
    /// Bytes of accepted messages.
    pub received_bytes: u64,
    /// Messages rejected on receive, by reason.
    pub rejected: Rejections,
}

/// Why a received message was rejected.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RejectReason {
    /// See [`Rejections::truncated`].
    Truncated,
    /// See [`Rejections::bad_magic`].
    BadMagic,
    /// See [`Rejections::bad_version`].
    BadVersion,
    /// See [`Rejections::bad_header`].
    BadHeader,
    /// See [`Rejections::too_large`].
    TooLarge,
    /// See [`Rejections::checksum`].
    Checksum,
    /// See [`Rejections::wrong_sender`].
    WrongSender,
    /// See [`Rejections::body`].
    Body,
}

impl RejectReason {
    /// Classifies a codec error.
    pub fn of(e: &CodecError) -> Self {
        match e {
            CodecError::Header(HeaderError::Truncated { .. }) | CodecError::Truncated { .. } => {
                Self::Truncated
            }
            CodecError::Header(HeaderError::BadMagic { .. }) => Self::BadMagic,
            CodecError::Header(HeaderError::UnsupportedVersion { .. }) => Self::BadVersion,
            CodecError::Header(_) | CodecError::TrailingBytes { .. } => Self::BadHeader,
            CodecError::TooLarge { .. } => Self::TooLarge,
            CodecError::Checksum { .. } => Self::Checksum,
            _ => Self::Body,
        }
    }
}

/// Thread-safe counters behind [`LinkStats`], shared with [`Received`] guards.
#[derive(Debug, Default)]
pub struct StatsCell {
    sent_messages: AtomicU64,
    sent_bytes: AtomicU64,
    dropped_no_peer: AtomicU64,
    dropped_overflow: AtomicU64,
    received_messages: AtomicU64,
    received_bytes: AtomicU64,
    rejected: [AtomicU64; 8],
}

fn add(a: &AtomicU64, n: u64) {
    a.fetch_add(n, Ordering::Relaxed);
}

impl StatsCell {
    /// New zeroed counters.
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }
    /// Counts a message handed to the backend.
    pub fn on_sent(&self, bytes: usize) {
        add(&self.sent_messages, 1);
        add(&self.sent_bytes, bytes as u64);
    }
    /// Counts a message the backend could not deliver (no peer).
    pub fn on_dropped_no_peer(&self) {
        add(&self.dropped_no_peer, 1);
    }
    /// Counts a message dropped on a full queue.
    pub fn on_dropped_overflow(&self) {
        add(&self.dropped_overflow, 1);
    }
    /// Counts an accepted message.
    pub fn on_received(&self, bytes: usize) {
        add(&self.received_messages, 1);
        add(&self.received_bytes, bytes as u64);
    }
    /// Counts a rejection.
    pub fn on_rejected(&self, r: RejectReason) {
        add(&self.rejected[r as usize], 1);
    }
    /// A snapshot.
    pub fn snapshot(&self) -> LinkStats {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let r = |x: RejectReason| g(&self.rejected[x as usize]);
        LinkStats {
            sent_messages: g(&self.sent_messages),
            sent_bytes: g(&self.sent_bytes),
            dropped_no_peer: g(&self.dropped_no_peer),
            dropped_overflow: g(&self.dropped_overflow),
            received_messages: g(&self.received_messages),
            received_bytes: g(&self.received_bytes),
            rejected: Rejections {
                truncated: r(RejectReason::Truncated),
                bad_magic: r(RejectReason::BadMagic),
                bad_version: r(RejectReason::BadVersion),
                bad_header: r(RejectReason::BadHeader),
                too_large: r(RejectReason::TooLarge),
                checksum: r(RejectReason::Checksum),
                wrong_sender: r(RejectReason::WrongSender),
                body: r(RejectReason::Body),
            },
        }
    }
}

/// Storage of a received message (the backend's own buffer).
pub trait MessageBytes: Send {
    /// The whole message: header then body.
    fn bytes(&self) -> &[u8];
    /// True when the bytes are lent by the backend (a shared-memory sample, a zenoh buffer) and
    /// holding them ties up backend resources; false for an owned heap buffer.
    fn is_borrowed(&self) -> bool {
        true
    }
    /// The bytes as an owned `Vec`: a copy, unless they already are one.
    fn into_vec(self: Box<Self>) -> Vec<u8> {
        self.bytes().to_vec()
    }
}

impl MessageBytes for Vec<u8> {
    fn bytes(&self) -> &[u8] {
        self
    }
    fn is_borrowed(&self) -> bool {
        false
    }
    fn into_vec(self: Box<Self>) -> Vec<u8> {
        *self
    }
}

/// A received message whose envelope passed every check and whose sender is the link's peer.
/// It owns the backend buffer (an iceoryx2 sample, a zenoh payload, a `Vec`) and gives it back
/// when dropped; [`Received::decode`] / [`Received::decode_owned`] decode the body straight from
/// it, without copying the message. Backends that lend a bounded number of buffers (iceoryx2)
/// hand out owned copies once the application holds all but one of them, so holding many
/// guards is allowed, only no longer zero-copy.
pub struct Received {
    header: Header,
    storage: Box<dyn MessageBytes>,
    stats: Arc<StatsCell>,
    /// The link's body limit, also the limit of a decompressed body.
    max_body_len: u64,
}

impl fmt::Debug for Received {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Received")
            .field("header", &self.header)
            .finish_non_exhaustive()
    }
}

impl Received {
    /// The validated header.
    pub fn header(&self) -> &Header {
        &self.header
    }
    /// The body bytes (checksum already verified).
    pub fn body_bytes(&self) -> &[u8] {
        self.storage
            .bytes()
            .get(crate::envelope::HEADER_LEN..)
            .unwrap_or(&[])
    }
    /// The whole message (header + body), e.g. to forward or store it.
    pub fn message_bytes(&self) -> &[u8] {
        self.storage.bytes()
    }
    /// True while the bytes are the backend's own buffer (zero-copy: a shared-memory sample,
    /// a zenoh payload), false once they are an owned heap copy.
    pub fn is_borrowed(&self) -> bool {
        self.storage.is_borrowed()
    }
    /// Copies the message out of the backend buffer (releasing e.g. the shared-memory sample)
    /// so it can be held for long; an owned message is moved, not copied. The decode-rejection
    /// counter stays attached to the link.
    pub fn into_owned(self) -> Received {
        let bytes = self.storage.into_vec();
        Received {
            header: self.header,
            storage: Box::new(bytes),
            stats: self.stats,
            max_body_len: self.max_body_len,
        }
    }
    /// An owned copy of this message (used by the fault layer to duplicate).
    pub fn clone_owned(&self) -> Received {
        Received {
            header: self.header,
            storage: Box::new(self.storage.bytes().to_vec()),
            stats: self.stats.clone(),
            max_body_len: self.max_body_len,
        }
    }
    /// Decodes the body as `B` and validates it. A failure is counted as a body rejection on the
    /// link that received the message.
    /// A compressed body cannot be borrowed from: it is [`CodecError::CompressedBorrow`]
    /// (use [`Received::decode_owned`]).
    pub fn decode<'a, B: Deserialize<'a> + Validate>(&'a self) -> Result<B, CodecError> {
        let r = if self.header.compressed {
            Err(CodecError::CompressedBorrow)
        } else {
            codec::decode_body(self.body_bytes())
        };
        r.inspect_err(|_| {
            self.stats.on_rejected(RejectReason::Body);
        })
    }

    /// Decodes the body as an owned `B`, decompressing it first if it was sent compressed (to
    /// at most the link's body limit), and validates it. A failure is counted as a body
    /// rejection.
    pub fn decode_owned<B: serde::de::DeserializeOwned + Validate>(&self) -> Result<B, CodecError> {
        codec::decode_body_owned(&self.header, self.body_bytes(), self.max_body_len).inspect_err(
            |_| {
                self.stats.on_rejected(RejectReason::Body);
            },
        )
    }
}

/// Checks a received buffer: envelope, limit, checksum, sender. On success counts it as received
/// and wraps it; on failure counts the rejection and returns `None`.
pub fn admit<S: MessageBytes + 'static>(
    storage: S,
    cfg: &LinkConfig,
    stats: &Arc<StatsCell>,
) -> Option<Received> {
    admit_with_crc(storage, None, cfg, stats)
}

/// [`admit`] with the envelope CRC already computed while the bytes were copied (see
/// [`codec::EnvelopeCrc`]); `None` computes it here.
pub fn admit_with_crc<S: MessageBytes + 'static>(
    storage: S,
    crc: Option<u32>,
    cfg: &LinkConfig,
    stats: &Arc<StatsCell>,
) -> Option<Received> {
    let bytes = storage.bytes();
    let header = match codec::open_envelope_with_crc(bytes, cfg.max_body_len, crc) {
        Ok((h, _)) => h,
        Err(e) => {
            tracing::debug!(local = cfg.local, peer = cfg.peer, error = %e, "rejected message");
            stats.on_rejected(RejectReason::of(&e));
            return None;
        }
    };
    if header.sender != cfg.peer {
        tracing::debug!(
            local = cfg.local,
            peer = cfg.peer,
            sender = header.sender,
            "rejected message from a node that is not this link's peer"
        );
        stats.on_rejected(RejectReason::WrongSender);
        return None;
    }
    stats.on_received(bytes.len());
    Some(Received {
        header,
        storage: Box::new(storage),
        stats: stats.clone(),
        max_body_len: cfg.max_body_len,
    })
}

/// A bidirectional link from this node to one configured peer.
///
/// Single-owner and synchronous: call it from one thread (it is `Send`, so it can move to a
/// worker). Call [`Link::poll_event`] or one of the receive methods regularly: backends detect
/// peer transitions there.
pub trait Link: Send {
    /// This node.
    fn local_id(&self) -> NodeId;
    /// The configured peer.
    fn peer_id(&self) -> NodeId;
    /// Encodes `body` with the header fields in `meta` (sender = [`Link::local_id`]) straight into
    /// the backend's buffer and sends it. A message that the backend cannot deliver (no peer
    /// attached, queue full) is counted in the statistics, not returned as an error: links are
    /// datagram-like and the application's sequence numbers detect losses.
    fn send(&mut self, meta: &SendMeta, body: &dyn WireBody) -> Result<(), LinkError>;
    /// The next accepted message if one is waiting.
    fn try_recv(&mut self) -> Result<Option<Received>, LinkError>;
    /// Waits up to `timeout` for the next accepted message.
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError>;
    /// The next peer transition, if any.
    fn poll_event(&mut self) -> Option<LinkEvent>;
    /// Current view of the peer.
    fn peer_state(&self) -> PeerState;
    /// Counters.
    fn stats(&self) -> LinkStats;
}

impl<L: Link + ?Sized> Link for Box<L> {
    fn local_id(&self) -> NodeId {
        (**self).local_id()
    }
    fn peer_id(&self) -> NodeId {
        (**self).peer_id()
    }
    fn send(&mut self, meta: &SendMeta, body: &dyn WireBody) -> Result<(), LinkError> {
        (**self).send(meta, body)
    }
    fn try_recv(&mut self) -> Result<Option<Received>, LinkError> {
        (**self).try_recv()
    }
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<Received>, LinkError> {
        (**self).recv_timeout(timeout)
    }
    fn poll_event(&mut self) -> Option<LinkEvent> {
        (**self).poll_event()
    }
    fn peer_state(&self) -> PeerState {
        (**self).peer_state()
    }
    fn stats(&self) -> LinkStats {
        (**self).stats()
    }
}

/// Conveniences over any [`Link`].
pub trait LinkExt: Link {
    /// Waits up to `timeout` for a message and hands its header and body bytes to `f` (which
    /// typically decodes with [`codec::decode_body`]) without copying them.
    fn recv_with<R>(
        &mut self,
        timeout: Duration,
        f: impl FnOnce(&Header, &[u8]) -> R,
    ) -> Result<Option<R>, LinkError> {
        Ok(self
            .recv_timeout(timeout)?
            .map(|m| f(m.header(), m.body_bytes())))
    }
    /// Drains every peer event waiting now.
    fn drain_events(&mut self) -> Vec<LinkEvent> {
        std::iter::from_fn(|| self.poll_event()).collect()
    }
}

impl<L: Link + ?Sized> LinkExt for L {}

/// Tracks peer presence and turns observations into [`LinkEvent`]s (used by backends).
#[derive(Debug, Clone)]
pub struct PeerTracker {
    state: PeerState,
    incarnation: Option<u64>,
    pending: std::collections::VecDeque<LinkEvent>,
}

impl Default for PeerTracker {
    fn default() -> Self {
        Self::new()
    }
}

impl PeerTracker {
    /// Peer initially down (not yet seen).
    pub fn new() -> Self {
        Self {
            state: PeerState::Down,
            incarnation: None,
            pending: Default::default(),
        }
    }
    /// Records an observation: `Some(id)` = a peer incarnation `id` is present, `None` = absent.
    /// A changed incarnation without an observed absence yields `PeerDown` then `PeerUp`.
    pub fn observe(&mut self, present: Option<u64>) {
        match (self.incarnation, present) {
            (None, Some(id)) => {
                self.pending.push_back(LinkEvent::PeerUp);
                self.state = PeerState::Up;
                self.incarnation = Some(id);
            }
            (Some(_), None) => {
                self.pending.push_back(LinkEvent::PeerDown);
                self.state = PeerState::Down;
                self.incarnation = None;
            }
            (Some(old), Some(new)) if old != new => {
                self.pending.push_back(LinkEvent::PeerDown);
                self.pending.push_back(LinkEvent::PeerUp);
                self.incarnation = Some(new);
            }
            _ => {}
        }
    }
    /// Current state.
    pub fn state(&self) -> PeerState {
        self.state
    }
    /// Next pending event.
    pub fn pop(&mut self) -> Option<LinkEvent> {
        self.pending.pop_front()
    }
}
