//! canopy's message bodies on top of the transport's envelope and codec.
//!
//! The transport knows bytes and envelopes; this module knows what canopy puts in them. Bodies
//! implement the transport's [`Validate`]; the DDF state machine and the estimator validate the
//! numbers again (finite, symmetric, positive definite where needed) before anything changes.

use canopy_fusion::ddf::{Body, DdfMessage, MAX_SUBMAP_ACKS, Outgoing};
use canopy_fusion::topology::NodeId;
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
        Body::Hello(_) | Body::Nack { .. } | Body::SubmapAck { .. } | Body::Uncertain { .. } => {
            MessageKind::DDF_CONTROL
        }
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

/// A DDF message encoded for its link: the body's bytes (compressed when asked) and what the
/// envelope needs besides the send time. Encoding where a message is formed lets its dense
/// form go at once: a delta's block-sparse wire form is about half of its dense k × k matrix
/// (`process::fusion_thread`).
#[derive(Debug)]
pub struct EncodedDdf {
    kind: MessageKind,
    sender_epoch: u64,
    receiver_epoch: u64,
    seq: u64,
    compressed: bool,
    body: Vec<u8>,
}

impl EncodedDdf {
    /// Encodes `msg`, compressed when `compression` asks for it and the message carries
    /// information (control messages are a few bytes).
    pub fn encode(msg: &DdfMessage, compression: Compression) -> Result<Self, CodecError> {
        let seq = match &msg.body {
            Body::Delta { seq, .. } => *seq,
            Body::Cumulative { upto, .. } => *upto,
            _ => 0,
        };
        let kind = ddf_kind(msg);
        // Serialised once here, then copied into the link's buffer: a link measures a body
        // before it encodes it (two passes), and a map information's `Serialize`
        // (block-sparsity scan of the dense Y, block gathering) costs far more than copying
        // its bytes. `DdfBody` is serde-transparent: the message itself encodes to the same
        // bytes.
        let mut body = canopy_transport::codec::encode_body_to_vec(msg)?;
        let compressed = compression == Compression::Zstd && kind == MessageKind::DDF_DELTA;
        if compressed {
            body = canopy_transport::codec::compress_body(&PreEncoded(&body))?;
        }
        Ok(Self {
            kind,
            sender_epoch: msg.header.from_epoch,
            receiver_epoch: msg.header.to_epoch.unwrap_or(0),
            seq,
            compressed,
            body,
        })
    }

    /// Sends it over `link`, stamped with simulation time `now` [s].
    pub fn send(&self, link: &mut dyn Link, now: f64) -> Result<(), LinkError> {
        let meta = SendMeta {
            kind: self.kind,
            sender_epoch: self.sender_epoch,
            receiver_epoch: self.receiver_epoch,
            seq: self.seq,
            sim_time: now,
            compressed: self.compressed,
        };
        link.send(&meta, &PreEncoded(&self.body))
    }
}

/// Sends a DDF message over a link ([`EncodedDdf::encode`], then [`EncodedDdf::send`]).
pub fn send_ddf(
    link: &mut dyn Link,
    now: f64,
    msg: &DdfMessage,
    compression: Compression,
) -> Result<(), LinkError> {
    EncodedDdf::encode(msg, compression)?.send(link, now)
}

/// A message for neighbour `to`, encoded where it was formed ([`EncodedDdf`]); an encoding
/// failure travels with it to be counted where messages are sent.
#[derive(Debug)]
pub struct WireOutgoing {
    /// Destination.
    pub to: NodeId,
    /// The encoded message, or why it could not be encoded.
    pub encoded: Result<EncodedDdf, CodecError>,
}

impl WireOutgoing {
    /// Encodes `o` (its dense form can go once this returns).
    pub fn encode(o: &Outgoing, compression: Compression) -> Self {
        Self {
            to: o.to,
            encoded: EncodedDdf::encode(&o.message, compression),
        }
    }
}

/// Decodes a received DDF message (None for other kinds).
pub fn decode_ddf(m: &Received) -> Option<Result<DdfMessage, CodecError>> {
    let k = m.header().kind;
    (k == MessageKind::DDF_DELTA || k == MessageKind::DDF_CONTROL)
        .then(|| m.decode_owned::<DdfBody>().map(|b| b.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_fusion::ddf::Header;
    use canopy_fusion::info::MapInformation;
    use canopy_transport::memory::InMemoryHub;
    use faer::{Col, Mat};
    use nalgebra::Vector3;

    /// A delta encoded where it is formed and sent later arrives with the envelope the DDF
    /// expects (kind, seq, both epochs, the send time, compression) and decodes to the message
    /// as formed, bit for bit, compressed or not.
    #[test]
    fn a_message_encoded_where_it_is_formed_arrives_as_formed() {
        let (a, b) = (NodeId(1), NodeId(2));
        let n = 3 * 4;
        let m = Mat::<f64>::from_fn(n, n, |i, j| 1.0 / (1.0 + i as f64 + j as f64));
        let info = MapInformation {
            ids: vec![7, 8, 9, 10],
            origin: Vector3::new(1.0, -2.0, 0.5),
            matrix: m,
            vector: Col::from_fn(n, |i| i as f64 - 3.25),
        };
        let message = DdfMessage {
            header: Header {
                from_epoch: 11,
                to_epoch: Some(12),
                challenge: 3,
                echo_epoch: 0,
                echo: 0,
            },
            body: Body::Delta { seq: 41, info },
        };
        for compression in [Compression::None, Compression::Zstd] {
            let (mut la, mut lb) = InMemoryHub::pair(a.0, b.0);
            let w = WireOutgoing::encode(
                &Outgoing {
                    to: b,
                    message: message.clone(),
                },
                compression,
            );
            assert_eq!(w.to, b);
            w.encoded.unwrap().send(&mut la, 17.5).unwrap();
            let got = lb.try_recv().unwrap().expect("delivered");
            let h = got.header();
            assert_eq!(h.kind, MessageKind::DDF_DELTA);
            assert_eq!((h.seq, h.sender_epoch, h.receiver_epoch), (41, 11, 12));
            assert_eq!(h.sim_time, 17.5);
            assert_eq!(h.compressed, compression == Compression::Zstd);
            let decoded = decode_ddf(&got).unwrap().unwrap();
            assert_eq!(decoded.header, message.header);
            let (Body::Delta { seq, info }, Body::Delta { info: want, .. }) =
                (&decoded.body, &message.body)
            else {
                panic!("not a delta: {:?}", decoded.body);
            };
            assert_eq!(*seq, 41);
            assert_eq!(info.ids, want.ids);
            assert_eq!(info.origin, want.origin);
            assert_eq!(info.matrix, want.matrix);
            assert_eq!(info.vector, want.vector);
        }
    }
}
