//! canopy's message bodies on top of the transport's envelope and codec.
//!
//! The transport knows bytes and envelopes; this module knows what canopy puts in them. Bodies
//! implement the transport's [`Validate`]; the DDF state machine and the estimator validate the
//! numbers again (finite, symmetric, positive definite where needed) before anything changes.

use canopy_fusion::ddf::{Body, DdfMessage, MAX_SUBMAP_ACKS};
use canopy_transport::codec::PreEncoded;
use canopy_transport::link::{Link, LinkError, Received};
use canopy_transport::wire::{Validate, ValidationError};
use canopy_transport::{CodecError, MessageKind, SendMeta};
use serde::{Deserialize, Serialize};

/// A DDF protocol message as a message body.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(transparent)]
pub struct DdfBody(pub DdfMessage);

impl Validate for DdfBody {
    fn validate(&self) -> Result<(), ValidationError> {
        // Map information decodes through its validating block-sparse serde form (sizes, ids,
        // finiteness, symmetry); submaps are checked here.
        match &self.0.body {
            Body::Submap { submap, .. } => submap
                .validate()
                .map_err(|e| ValidationError::Other(e.to_string())),
            Body::SubmapAck { seqs } if seqs.len() > MAX_SUBMAP_ACKS => {
                Err(ValidationError::Other(format!(
                    "{} submap acknowledgements (at most {MAX_SUBMAP_ACKS})",
                    seqs.len()
                )))
            }
            _ => Ok(()),
        }
    }
}

/// The envelope kind of a DDF message: deltas and everything carrying information are
/// `DDF_DELTA`, heartbeats and Nacks `DDF_CONTROL`.
pub fn ddf_kind(msg: &DdfMessage) -> MessageKind {
    match msg.body {
        Body::Hello(_) | Body::Nack { .. } | Body::SubmapAck { .. } => MessageKind::DDF_CONTROL,
        _ => MessageKind::DDF_DELTA,
    }
}

/// Compression of the information-carrying DDF messages on the wire (`[fusion]
/// delta_compression`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Compression {
    /// As encoded (default).
    #[default]
    None,
    /// One zstd frame per message (level [`canopy_transport::codec::ZSTD_LEVEL`]), flagged in
    /// the envelope; measured 0.94 of the bytes on f64 information deltas (mantissas are
    /// nearly incompressible).
    Zstd,
}

/// Sends a DDF message over a link, compressed when `compression` asks for it and the message
/// carries information (control messages are a few bytes).
pub fn send_ddf(
    link: &mut dyn Link,
    now: f64,
    msg: &DdfMessage,
    compression: Compression,
) -> Result<(), LinkError> {
    let seq = match &msg.body {
        Body::Delta { seq, .. } => *seq,
        Body::Cumulative { upto, .. } => *upto,
        _ => 0,
    };
    let kind = ddf_kind(msg);
    let mut meta = SendMeta {
        kind,
        sender_epoch: msg.header.from_epoch,
        receiver_epoch: msg.header.to_epoch.unwrap_or(0),
        seq,
        sim_time: now,
        compressed: false,
    };
    // Serialised once here, then copied into the link's buffer: a link measures a body before
    // it encodes it (two passes), and a map information's `Serialize` (block-sparsity scan of
    // the dense Y, block gathering) costs far more than copying its bytes.
    // `DdfBody` is serde-transparent: the message itself encodes to the same bytes.
    let body = canopy_transport::codec::encode_body_to_vec(msg).map_err(LinkError::Encode)?;
    if compression == Compression::Zstd && kind == MessageKind::DDF_DELTA {
        let frame = canopy_transport::codec::compress_body(&PreEncoded(&body))
            .map_err(LinkError::Encode)?;
        meta.compressed = true;
        return link.send(&meta, &PreEncoded(&frame));
    }
    link.send(&meta, &PreEncoded(&body))
}

/// Decodes a received DDF message (None for other kinds).
pub fn decode_ddf(m: &Received) -> Option<Result<DdfMessage, CodecError>> {
    let k = m.header().kind;
    (k == MessageKind::DDF_DELTA || k == MessageKind::DDF_CONTROL)
        .then(|| m.decode_owned::<DdfBody>().map(|b| b.0))
}
