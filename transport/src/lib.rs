//! canopy-transport: links between canopy processes.
//!
//! # Layout
//! - [`envelope`]: the fixed 64-byte header (magic, version, kind, sender, epochs, sequence,
//!   simulation time, body length, CRC-32) and [`MessageKind`].
//! - [`codec`]: the only module that names bincode: two-pass encode straight into a caller's
//!   buffer (initialised or not), validated decode; every failure a [`CodecError`].
//! - [`wire`]: validated numeric containers for bodies ([`WireVector`], [`WireMatrix`],
//!   [`WireSymMatrix`], [`WireBlockSymMatrix`], [`WireBytes`]) and the [`Validate`] trait.
#![deny(unsafe_code)]

pub mod codec;
pub mod envelope;
pub mod fault;
pub mod iceoryx;
pub mod link;
pub mod memory;
pub mod net;
pub mod wire;

pub use codec::{CodecError, PreEncoded, WireBody};
pub use link::{
    Link, LinkConfig, LinkError, LinkEvent, LinkExt, LinkStats, PeerState, Received, Rejections,
};
pub use envelope::{Header, MessageKind, NodeId, SendMeta};
pub use wire::{
    Validate, ValidationError, WireBlockSymMatrix, WireBytes, WireBytesRef, WireEncoding,
    WireMatrix, WireSymMatrix, WireVector,
};
