//! canopy-transport: links between canopy processes. Knows bytes and envelopes, not estimation.
//!
//! # Layout
//! - [`envelope`]: the fixed 64-byte header (magic, version, kind, sender, epochs, sequence,
//!   simulation time, body length, CRC-32) and [`MessageKind`] (open set of `u16` codes).
//! - [`codec`]: the only module that names bincode. Two-pass encode straight into a caller's
//!   buffer (initialised, uninitialised shared memory, or a `Vec`), streaming the CRC; validated
//!   decode that checks the envelope before the body and runs the body's [`Validate`]. Every
//!   failure is a [`CodecError`]; no input panics.
//! - [`wire`]: validated numeric containers for bodies ([`WireVector`], [`WireMatrix`],
//!   [`WireSymMatrix`] packed upper triangle, [`WireBlockSymMatrix`] non-zero 3×3 blocks,
//!   [`WireBytes`]) with an encoding tag for later float32/compressed forms, and [`Validate`].
//! - [`link`]: the object-safe [`Link`] trait (send / receive guard / peer events / stats), the
//!   admission check (envelope + "only the configured peer gets in"), [`LinkStats`].
//! - [`memory`]: deterministic in-memory backend (a hub of endpoints) for simulation and tests.
//! - [`iceoryx`]: iceoryx2 zero-copy shared-memory backend for processes on one host.
//! - [`net`]: zenoh backend for links between hosts (peer, client or router mode, explicit
//!   endpoints, liveliness, user/password authentication).
//! - [`access`]: zenoh access control for canopy's key layout (default deny, per-user ingress
//!   rules) and the count of what zenoh refuses.
//! - [`test_certs`]: a test CA and per-user certificates (openssl) for the TLS suites.
//! - [`fault`]: seeded fault injection over any link (delay, jitter, loss, duplication,
//!   reordering, bandwidth cap, outages and partitions) with an injectable [`fault::Clock`];
//!   messages it does not hold pass through in the backend's buffer (zero-copy).
#![deny(unsafe_code)]

pub mod access;
pub mod codec;
pub mod envelope;
pub mod fault;
pub mod iceoryx;
pub mod link;
pub mod memory;
pub mod net;
pub mod test_certs;
pub mod wire;

pub use codec::{CodecError, PreEncoded, WireBody};
pub use envelope::{Header, MessageKind, NodeId, SendMeta};
pub use link::{
    Link, LinkConfig, LinkError, LinkEvent, LinkExt, LinkStats, PeerState, Received, Rejections,
};
pub use wire::{
    Validate, ValidationError, WireBlockSymMatrix, WireBytes, WireBytesRef, WireEncoding,
    WireMatrix, WireSymMatrix, WireVector,
};
