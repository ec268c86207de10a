//! Radio links of a scenario: `[[link]] radio = { bytes_per_s, … }` (issue #13).
//!
//! A radio link is a channel of `bytes_per_s` in each direction behind a drop-tail queue of
//! `queue_bytes`, with a fixed latency and optionally range-limited availability (up while the
//! two vehicles' true positions are within `range_m`, with loss rising near the edge). It maps
//! onto the transport's [`canopy_transport::fault::Radio`] for the inbound direction of both
//! ends; the separation of the two ends is evaluated from their analytic trajectories
//! ([`TrueSeparation`]), in the launch NED frame every trajectory shares.
//!
//! # Example
//! ```toml
//! [[link]]
//! a = 3
//! b = 4
//! radio = { bytes_per_s = 32000.0, latency_s = 0.02, range_m = 2500.0, edge_fraction = 0.2, edge_loss = 0.5 }
//! ```
//!
//! `fusion = "sparse"` (default) runs the channel filter with conservative sparsification
//! under the round's budget ([`canopy_fusion::sparse`]); `fusion = "ci"` sends covariance-
//! intersection submaps from the first round instead.

use std::sync::Arc;

use canopy_fusion::topology::NodeId;
use canopy_transport::fault::{FaultyLink, Radio, RangeLimit, Separation};
use canopy_transport::link::Link;
use serde::{Deserialize, Serialize};

use crate::network::{FusionConfig, FusionMode};
use crate::scenario::{Scenario, ScenarioError};
use crate::world::Trajectory;

/// Default share of the link's outer range over which loss rises (with `range_m`).
pub const DEFAULT_EDGE_FRACTION: f64 = 0.2;
/// Default loss probability at the range (with `range_m`).
pub const DEFAULT_EDGE_LOSS: f64 = 0.5;

/// `radio = { … }` of a `[[link]]`: both directions alike.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RadioSpec {
    /// Capacity of each direction [bytes/s], envelope included (*required*).
    pub bytes_per_s: f64,
    /// Bytes allowed to wait for the channel; a message that finds more ahead of it is dropped
    /// (drop-tail). Default: one second of capacity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub queue_bytes: Option<u64>,
    /// Latency after the last byte left [s] (default 0).
    #[serde(default)]
    pub latency_s: f64,
    /// Range [m]: the link is up while the two vehicles are within it (default: unlimited).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_m: Option<f64>,
    /// Outer fraction of the range over which loss rises linearly from 0 to `edge_loss`
    /// (with `range_m` only; default [`DEFAULT_EDGE_FRACTION`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_fraction: Option<f64>,
    /// Loss probability at the range (with `range_m` only; default [`DEFAULT_EDGE_LOSS`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_loss: Option<f64>,
    /// How the link fuses under its capacity (default `"sparse"`).
    #[serde(default, skip_serializing_if = "RadioFusion::is_default")]
    pub fusion: RadioFusion,
}

/// Fusion on a capacity-limited link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RadioFusion {
    /// Channel filter with conservative sparsification booked in the channel filter: exact
    /// deltas while they fit the round's budget, otherwise the marginal information of the
    /// delta on the features that fit; the rest goes out in later rounds
    /// ([`canopy_fusion::sparse`]).
    #[default]
    Sparse,
    /// Covariance intersection of budgeted submaps from the first round (one-way).
    Ci,
}

impl RadioFusion {
    fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

impl RadioSpec {
    /// The queue bound [bytes] under fusion settings `f`: by default the capacity of one
    /// interval between deltas ([`FusionConfig::budget_rate_hz`]), and at least one second of
    /// it (a delta is queued at once).
    pub fn queue_bytes(&self, f: &FusionConfig) -> u64 {
        let interval_s = 1.0 / f.budget_rate_hz();
        self.queue_bytes
            .unwrap_or_else(|| (self.bytes_per_s * interval_s.max(1.0)).ceil() as u64)
    }

    /// The budget of a delta on an idle link of this radio under fusion settings `f`
    /// ([`queued_round_budget`] with nothing queued).
    pub fn delta_budget(&self, f: &FusionConfig) -> usize {
        queued_round_budget(
            self.bytes_per_s,
            f.budget_rate_hz(),
            0.0,
            self.queue_bytes(f),
        )
    }

    /// Field checks (`field` is the radio table's path); `ends` are the link's two node ids,
    /// which must both be simulated vehicles when `range_m` is given.
    pub fn validate(&self, field: &str, s: &Scenario, ends: [u32; 2]) -> Result<(), ScenarioError> {
        let bad = |name: &str, reason: String| {
            Err(ScenarioError::invalid(format!("{field}.{name}"), reason))
        };
        if !(self.bytes_per_s.is_finite() && self.bytes_per_s > 0.0) {
            return bad(
                "bytes_per_s",
                format!("must be a finite number > 0, got {}", self.bytes_per_s),
            );
        }
        let per_round = self.delta_budget(&s.fusion);
        let min = min_useful_budget();
        if per_round < min {
            return bad(
                "bytes_per_s",
                format!(
                    "{} bytes/s at {} rounds/s leaves {per_round} bytes per round after the \
                     headroom, less than one feature's submap ({min} bytes)",
                    self.bytes_per_s,
                    s.fusion.budget_rate_hz()
                ),
            );
        }
        if !(self.latency_s.is_finite() && self.latency_s >= 0.0) {
            return bad(
                "latency_s",
                format!("must be a finite number ≥ 0, got {}", self.latency_s),
            );
        }
        let Some(range) = self.range_m else {
            for (name, v) in [
                ("edge_fraction", self.edge_fraction),
                ("edge_loss", self.edge_loss),
            ] {
                if v.is_some() {
                    return bad(name, "only applies to a radio with range_m".into());
                }
            }
            return Ok(());
        };
        if !(range.is_finite() && range > 0.0) {
            return bad(
                "range_m",
                format!("must be a finite number > 0, got {range}"),
            );
        }
        for (name, v) in [
            ("edge_fraction", self.edge_fraction),
            ("edge_loss", self.edge_loss),
        ] {
            if let Some(p) = v
                && !(0.0..=1.0).contains(&p)
            {
                return bad(name, format!("must be in [0, 1], got {p}"));
            }
        }
        for id in ends {
            let flies = s
                .vehicles
                .iter()
                .any(|v| v.id == id && v.trajectory.is_some());
            if !flies {
                let what = if s.fusion.mode == FusionMode::Central && id == s.fusion.hub_id {
                    "the hub has no position".to_string()
                } else {
                    format!("node {id} has no simulated trajectory (replayed or not a vehicle)")
                };
                return bad(
                    "range_m",
                    format!("a range needs both ends' true positions: {what}"),
                );
            }
        }
        Ok(())
    }

    /// The transport's radio model of one direction of link `ends` of scenario `s` (validated).
    pub fn to_transport(&self, s: &Scenario, ends: [u32; 2]) -> Result<Radio, ScenarioError> {
        let range = match self.range_m {
            None => None,
            Some(range_m) => Some(RangeLimit {
                range_m,
                edge_fraction: self.edge_fraction.unwrap_or(DEFAULT_EDGE_FRACTION),
                edge_loss: self.edge_loss.unwrap_or(DEFAULT_EDGE_LOSS),
                separation: Arc::new(TrueSeparation::new(s, ends)?),
            }),
        };
        Ok(Radio {
            bytes_per_s: self.bytes_per_s,
            queue_bytes: self.queue_bytes(&s.fusion),
            latency: self.latency_s,
            range,
        })
    }
}

/// Distance between two vehicles' true positions, from their analytic trajectories (launch
/// NED frame, simulated time).
#[derive(Debug)]
pub struct TrueSeparation {
    ends: [Trajectory; 2],
}

impl TrueSeparation {
    /// The separation of vehicles `ends` of `s` (both must have a trajectory).
    pub fn new(s: &Scenario, ends: [u32; 2]) -> Result<Self, ScenarioError> {
        let traj = |id: u32| -> Result<Trajectory, ScenarioError> {
            let (i, v) = s
                .vehicles
                .iter()
                .enumerate()
                .find(|(_, v)| v.id == id)
                .ok_or_else(|| {
                    ScenarioError::invalid("link", format!("node {id} is not a vehicle"))
                })?;
            Trajectory::new(
                v.trajectory()
                    .map_err(|e| e.within(&format!("vehicle[{i}]")))?,
            )
            .map_err(|e| e.within(&format!("vehicle[{i}].trajectory")))
        };
        Ok(Self {
            ends: [traj(ends[0])?, traj(ends[1])?],
        })
    }
}

impl Separation for TrueSeparation {
    fn distance_m(&self, t: f64) -> f64 {
        (self.ends[0].kinematics(t).position - self.ends[1].kinematics(t).position).norm()
    }
}

/// Share of a round's capacity a radio link keeps free of submaps: the submap budget bounds the
/// submap alone, and the same round also sends the Describe of the submap's new features
/// (≤ 45 bytes each: at 32 kB/s a ~29-feature submap, ≤ 1.3 kB = 4 %; at 8 kB/s ~13 features,
/// ≤ 0.6 kB = 8 %), acknowledgements, and each message's 64-byte envelope.
pub const HEADROOM_FRACTION: f64 = 0.1;

/// Bytes per round a radio link keeps free whatever its capacity: the once-a-second Hello and
/// the envelopes of a round's few messages (4 × 64 bytes), rounded up.
pub const HEADROOM_BYTES: f64 = 512.0;

/// The byte budget of one round's submap on a radio link of `bytes_per_s` at `rate_hz` fusion
/// rounds per second, when `queued_bytes` this end sent still wait for the channel (the
/// transport's outbound mirror): a round's share of the capacity, less the headroom, less the
/// backlog. A round never offers more than the channel drains in one round period, and a
/// backlog left by the previous rounds is paid back before new bytes are offered, so the
/// queue stays below a round's worth and the offered load never exceeds the capacity.
/// 0 when the backlog eats the round (the round sends no submap).
pub fn round_budget(bytes_per_s: f64, rate_hz: f64, queued_bytes: f64) -> usize {
    whole_bytes((1.0 - HEADROOM_FRACTION) * bytes_per_s / rate_hz - HEADROOM_BYTES - queued_bytes)
}

/// A byte budget from its real-valued bound: whole bytes, 0 when negative or not finite.
fn whole_bytes(b: f64) -> usize {
    if b.is_finite() && b > 0.0 {
        b.floor() as usize
    } else {
        0
    }
}

/// [`round_budget`], and no more than the room left in the link's queue of `queue_bytes` (less
/// the same headroom): a delta sent once per several rounds would otherwise be offered whole
/// to a queue that holds less than the interval's capacity, and be dropped.
pub fn queued_round_budget(
    bytes_per_s: f64,
    rate_hz: f64,
    queued_bytes: f64,
    queue_bytes: u64,
) -> usize {
    let room = (1.0 - HEADROOM_FRACTION) * queue_bytes as f64 - HEADROOM_BYTES - queued_bytes;
    round_budget(bytes_per_s, rate_hz, queued_bytes).min(whole_bytes(room))
}

/// The submap budgets of the next round on a node's capacity-limited (radio) links, from each
/// link's outbound mirror now ([`queued_round_budget`]); links without a radio are left out.
pub fn capacity_budgets<'a, L: Link + 'a>(
    links: impl IntoIterator<Item = (NodeId, &'a FaultyLink<L>)>,
    rate_hz: f64,
) -> Vec<(NodeId, usize)> {
    links
        .into_iter()
        .filter_map(|(peer, link)| {
            let o = link.outbound()?;
            Some((
                peer,
                queued_round_budget(o.bytes_per_s, rate_hz, o.queued_bytes, o.queue_bytes),
            ))
        })
        .collect()
}

/// The smallest useful submap budget: one feature's submap.
pub fn min_useful_budget() -> usize {
    canopy_fusion::ci::Submap::wire_bytes_for(1)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::LinkSpec;
    use crate::scenario::ShapeConfig;

    /// The rule restated by hand: 32 kB/s at 1 round/s keeps 10 % + 512 bytes free
    /// (0.9 · 32000 − 512 = 28288), pays a backlog back byte for byte, never goes negative,
    /// and halves (less the fixed headroom) at 2 rounds/s (0.9 · 16000 − 512 = 13888).
    #[test]
    fn round_budget_is_the_capacity_share_less_headroom_and_backlog() {
        assert_eq!(round_budget(32_000.0, 1.0, 0.0), 28_288);
        assert_eq!(round_budget(32_000.0, 1.0, 10_000.0), 18_288);
        assert_eq!(round_budget(32_000.0, 1.0, 40_000.0), 0);
        assert_eq!(round_budget(32_000.0, 2.0, 0.0), 13_888);
        assert_eq!(round_budget(8_000.0, 1.0, 0.0), 6_688);
        // Offered per round (budget + headroom + what still waits) never exceeds a round's
        // capacity.
        for q in [0.0, 1.0, 5_000.0, 27_000.0, 1e6] {
            let b = round_budget(32_000.0, 1.0, q) as f64;
            assert!(
                b + 0.1 * 32_000.0 + 512.0 + q <= 32_000.0 || b == 0.0,
                "{q}"
            );
        }
    }

    /// The budget of a delta formed once per interval, restated by hand: 32 kB/s with a
    /// 2-s interval offers the interval's share (0.9 · 64 000 − 512 = 57 088) when the queue
    /// holds it (the default queue is one interval: 64 000 bytes), the queue's room when an
    /// explicit one-second queue is smaller (0.9 · 32 000 − 512 = 28 288), less what still
    /// waits in it; every round at 1 Hz keeps the one-round budget (28 288).
    #[test]
    fn a_delta_per_interval_gets_the_interval_budget_within_the_queue() {
        let mut s = Scenario::builtin_default();
        let radio = |queue_bytes| RadioSpec {
            bytes_per_s: 32_000.0,
            queue_bytes,
            latency_s: 0.0,
            range_m: None,
            edge_fraction: None,
            edge_loss: None,
            fusion: RadioFusion::Sparse,
        };
        assert_eq!(radio(None).delta_budget(&s.fusion), 28_288);
        s.fusion.radio_interval_s = 2.0;
        assert_eq!(s.fusion.budget_rate_hz(), 0.5);
        assert_eq!(radio(None).queue_bytes(&s.fusion), 64_000);
        assert_eq!(radio(None).delta_budget(&s.fusion), 57_088);
        assert_eq!(radio(Some(32_000)).delta_budget(&s.fusion), 28_288);
        assert_eq!(queued_round_budget(32_000.0, 0.5, 10_000.0, 64_000), 47_088);
        assert_eq!(queued_round_budget(32_000.0, 0.5, 10_000.0, 32_000), 18_288);
        assert_eq!(queued_round_budget(32_000.0, 0.5, 40_000.0, 32_000), 0);
        // An interval shorter than the round period changes nothing.
        s.fusion.radio_interval_s = 0.5;
        assert_eq!(s.fusion.budget_rate_hz(), 1.0);
        // Data sharing sends every round: the interval, a channel-filter setting, does not
        // apply (one round's budget and a one-second queue).
        s.fusion.mode = crate::network::FusionMode::SharedData;
        s.fusion.radio_interval_s = 2.0;
        assert_eq!(s.fusion.budget_rate_hz(), 1.0);
        assert_eq!(radio(None).queue_bytes(&s.fusion), 32_000);
        assert_eq!(radio(None).delta_budget(&s.fusion), 28_288);
    }

    /// Two vehicles on the same orbit (radius 650 m), half a period apart, at 120 m and 160 m
    /// with no climb: always diametrically opposite, so the separation is √(1300² + 40²).
    #[test]
    fn true_separation_of_opposite_orbits() {
        let mut s = Scenario::builtin_default();
        for (i, (alt, phase)) in [(120.0, 0.0), (160.0, 0.5)].into_iter().enumerate() {
            let t = s.vehicles[i].trajectory.as_mut().expect("simulated");
            t.centre_ne_m = [0.0, 0.0];
            t.altitude_m = alt;
            t.phase = phase;
            t.heading_deg = 0.0;
            t.climb_amplitude_m = 0.0;
            t.shape = ShapeConfig::Orbit {
                radius_m: 650.0,
                clockwise: true,
            };
        }
        let (a, b) = (s.vehicles[0].id, s.vehicles[1].id);
        let link = LinkSpec {
            a,
            b,
            transport: Default::default(),
            listen: None,
            byte_budget: None,
            faults: Default::default(),
            radio: Some(RadioSpec {
                bytes_per_s: 32_000.0,
                queue_bytes: None,
                latency_s: 0.05,
                range_m: Some(1000.0),
                edge_fraction: None,
                edge_loss: Some(0.3),
                fusion: RadioFusion::Ci,
            }),
        };
        let cfg = link.fault_config(&s, 7).expect("maps");
        let radio = cfg.radio.expect("radio");
        assert_eq!(radio.bytes_per_s, 32_000.0);
        assert_eq!(radio.queue_bytes, 32_000);
        assert_eq!(radio.latency, 0.05);
        let g = radio.range.expect("range");
        assert_eq!((g.edge_fraction, g.edge_loss), (DEFAULT_EDGE_FRACTION, 0.3));
        let want = (1300.0_f64.powi(2) + 40.0_f64.powi(2)).sqrt();
        for t in [0.0, 3.7, 41.0, 250.0] {
            // 1e-6 m: sums of a few hundred-metre terms in f64.
            assert!((g.separation.distance_m(t) - want).abs() < 1e-6, "t = {t}");
            assert!(!g.in_range(t));
        }
    }

    /// Radio links are refused outside decentralized mode (the hub cannot fuse CI submaps),
    /// naming the link's radio field.
    #[test]
    fn radio_outside_decentralized_mode_is_refused() {
        let mut s = Scenario::builtin_default();
        s.links[0].radio = Some(RadioSpec {
            bytes_per_s: 32_000.0,
            queue_bytes: None,
            latency_s: 0.0,
            range_m: None,
            edge_fraction: None,
            edge_loss: None,
            fusion: RadioFusion::Sparse,
        });
        assert!(crate::network::validate(&s).is_ok());
        s.fusion.mode = FusionMode::Central;
        match crate::network::validate(&s) {
            Err(ScenarioError::Invalid { field, reason }) => {
                assert_eq!(field, "link[0].radio");
                assert!(reason.contains("decentralized"), "{reason}");
            }
            other => panic!("{other:?}"),
        }
    }
}
