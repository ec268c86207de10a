//! Message bodies between the processes of a run (not the DDF messages, which are
//! [`crate::wire::DdfBody`]). Every body is validated on receipt (sizes, finite numbers) by the
//! transport's codec before a process looks at it; a message that fails is counted by the link
//! as a body rejection and dropped.
//!
//! | channel | body | envelope kind |
//! |---|---|---|
//! | world → vehicle | [`WorldMsg`] (`Init`, `Batch`, `End`) | `IMU_BATCH` |
//! | world → hub | [`WorldMsg`] (`Time`, `End`) | `IMU_BATCH` |
//! | vehicle → world | [`Progress`] | `HEARTBEAT` |
//! | every process → monitor | [`Report`] | `ESTIMATE_REPORT` / `MAP_REPORT` |
//! | monitor → every process | [`Control`] | `CONTROL` |
//! | host launcher → monitor (zenoh, multi-host runs) | [`HostMsg`] | `ESTIMATE_REPORT` |
//! | monitor → host launcher (zenoh) | [`Control`] | `CONTROL` |

use canopy_fusion::ddf::ChannelStats;
use canopy_fusion::sensor::{FeatureId, ImuSample, Measurement, ObservationFrame};
use canopy_fusion::state::VEHICLE_DIM;
use canopy_transport::wire::{Validate, ValidationError};
use canopy_transport::{MessageKind, NodeId};
use serde::{Deserialize, Serialize};

use crate::network::FIRST_RESERVED_NODE_ID;

/// Node id of the world process on its links.
pub const WORLD_ID: NodeId = u32::MAX;
/// Node id of the monitor (launcher) on its links.
pub const MONITOR_ID: NodeId = u32::MAX - 1;
const _: () = assert!(MONITOR_ID >= FIRST_RESERVED_NODE_ID);
/// Node id of the zenoh router (`canopy router`) on the control plane of a multi-host run in
/// client mode (its link to the monitor carries [`HostMsg::Refusals`]).
pub const ROUTER_ID: NodeId = u32::MAX - 2;
const _: () = assert!(ROUTER_ID >= FIRST_RESERVED_NODE_ID);

fn finite(what: &'static str, v: impl IntoIterator<Item = f64>) -> Result<(), ValidationError> {
    match v.into_iter().position(|x| !x.is_finite()) {
        Some(index) => Err(ValidationError::NonFinite {
            what,
            index: index as u64,
        }),
        None => Ok(()),
    }
}

fn dim(what: &'static str, expected: usize, found: usize) -> Result<(), ValidationError> {
    if expected == found {
        Ok(())
    } else {
        Err(ValidationError::Dimension {
            what,
            expected: expected as u64,
            found: found as u64,
        })
    }
}

fn imu_values(s: &ImuSample) -> [f64; 8] {
    [
        s.time,
        s.dt,
        s.specific_force.x,
        s.specific_force.y,
        s.specific_force.z,
        s.angular_rate.x,
        s.angular_rate.y,
        s.angular_rate.z,
    ]
}

fn frame_values(f: &ObservationFrame) -> impl Iterator<Item = f64> + '_ {
    std::iter::once(f.time).chain(f.observations.iter().flat_map(|o| match o.z {
        Measurement::RangeBearing(z) => vec![z.x, z.y, z.z],
        Measurement::Bearing(z) | Measurement::Pixel(z) => vec![z.x, z.y],
    }))
}

/// One element of a vehicle's sensor stream, in time order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum SensorItem {
    /// An IMU sample.
    Imu(ImuSample),
    /// A terrain-sensor frame (follows the IMU sample of the same time).
    Frame(ObservationFrame),
}

/// The initial estimate a (re)started vehicle process starts from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InitMsg {
    /// Process incarnation this is for (0 = first start).
    pub incarnation: u32,
    /// Time of the estimate [s]; the stream continues after it.
    pub time: f64,
    /// State p, v, Ψ, δf^b, δω^b (estimator frame).
    pub state: Vec<f64>,
    /// 15×15 covariance, row-major.
    pub covariance: Vec<f64>,
}

/// World → vehicle (sensor stream) and world → hub (simulation time).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum WorldMsg {
    /// Start (or restart) from this estimate; the stream follows.
    Init(InitMsg),
    /// Sensor data, in time order. `seq` counts batches per incarnation from 1, so the vehicle
    /// can tell a lost batch (which it reports).
    Batch {
        /// Batch number.
        seq: u64,
        /// Samples and frames.
        items: Vec<SensorItem>,
    },
    /// Simulation time reached by the world (to the hub).
    Time {
        /// [s].
        time: f64,
    },
    /// The stream is over at this time.
    End {
        /// [s].
        time: f64,
    },
}

impl Validate for WorldMsg {
    fn validate(&self) -> Result<(), ValidationError> {
        match self {
            WorldMsg::Init(m) => {
                dim("init.state", VEHICLE_DIM, m.state.len())?;
                dim(
                    "init.covariance",
                    VEHICLE_DIM * VEHICLE_DIM,
                    m.covariance.len(),
                )?;
                finite("init.time", [m.time])?;
                finite("init.state", m.state.iter().copied())?;
                finite("init.covariance", m.covariance.iter().copied())
            }
            WorldMsg::Batch { items, .. } => {
                for it in items {
                    match it {
                        SensorItem::Imu(s) => finite("batch.imu", imu_values(s))?,
                        SensorItem::Frame(f) => finite("batch.frame", frame_values(f))?,
                    }
                }
                Ok(())
            }
            WorldMsg::Time { time } | WorldMsg::End { time } => finite("time", [*time]),
        }
    }
}

/// Vehicle → world: the sensor stream has been processed up to `time` (flow control).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Incarnation of the sender.
    pub incarnation: u32,
    /// Simulation time processed [s].
    pub time: f64,
}

impl Validate for Progress {
    fn validate(&self) -> Result<(), ValidationError> {
        finite("progress.time", [self.time])
    }
}

/// Monitor → process.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Control {
    /// Finish: send final reports if not done yet, close links, exit 0.
    Shutdown,
    /// Monitor → host launcher (multi-host runs): the monitor has accepted the host's `Hello`.
    Welcome,
    /// Monitor → host launcher → the host's world (multi-host runs): the team's pace — the
    /// world may step up to `until` (the slowest live vehicle of the whole team, as the monitor
    /// last heard, plus `[run].max_lead_s`), so no host runs ahead of the others by more than
    /// the flow-control lead on simulation time. Hosts need no shared wall clock.
    Pace {
        /// Simulation time [s].
        until: f64,
    },
    /// Monitor → host launcher (multi-host runs): a scheduled `[[event]]` — SIGKILL the live
    /// process called `name` (a vehicle's name, or `hub`) on this host.
    Kill {
        /// The process (`[[vehicle]]` name or `hub`).
        name: String,
    },
    /// Monitor → host launcher (multi-host runs): start vehicle `vehicle` again as
    /// `incarnation` (a scheduled restart; the host's world holds its streams at the restart
    /// time until the new process asks to be initialised). Repeated orders of an incarnation
    /// already started are ignored.
    Restart {
        /// Vehicle id.
        vehicle: u32,
        /// Its new incarnation (1 for the first restart).
        incarnation: u32,
    },
}

impl Validate for Control {
    fn validate(&self) -> Result<(), ValidationError> {
        match self {
            Control::Pace { until } => finite("pace.until", [*until]),
            Control::Kill { name } if name.is_empty() || name.len() > 256 => Err(
                ValidationError::Other("kill.name: empty or longer than 256 bytes".into()),
            ),
            Control::Restart { incarnation, .. } if *incarnation == 0 => Err(
                ValidationError::Other("restart.incarnation: a restart's is ≥ 1".into()),
            ),
            _ => Ok(()),
        }
    }
}

/// One end's view of a fusion link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LinkReport {
    /// The neighbour.
    pub peer: NodeId,
    /// Messages sent.
    pub sent_messages: u64,
    /// Bytes sent (header + body).
    pub sent_bytes: u64,
    /// Messages received and accepted by the transport.
    pub received_messages: u64,
    /// Bytes received.
    pub received_bytes: u64,
    /// Sends the backend could not deliver (no peer attached, receiver queue full).
    pub dropped_send: u64,
    /// Inbound messages dropped by injected faults (loss, outage, bandwidth).
    pub dropped_faults: u64,
    /// Inbound messages rejected by the transport (envelope, checksum, sender, body).
    pub rejected_transport: u64,
    /// Inbound DDF messages the channel rejected (invalid payload).
    pub rejected_channel: u64,
    /// The link (transport and injected outages) sees the peer up.
    pub up: bool,
    /// The link has fallen back to covariance intersection.
    pub ci: bool,
    /// The DDF channel's counters.
    pub channel: ChannelStats,
    /// What the naive scheme would have sent on this link from this end so far: this node's
    /// whole map information (Y, y), dense f64, every round (8·(9n² + 3n) bytes for n features).
    pub naive_bytes: u64,
}

/// Counters of a vehicle process.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VehicleCounters {
    /// IMU samples applied.
    pub imu_samples: u64,
    /// IMU samples or frames the estimator rejected.
    pub inputs_rejected: u64,
    /// Frames processed.
    pub frames: u64,
    /// Observations processed.
    pub observations: u64,
    /// Fusion rounds.
    pub rounds: u64,
    /// Received deltas fused.
    pub fused: u64,
    /// Received deltas the estimator refused (kept pending by the channel).
    pub fuse_refused: u64,
    /// DDF messages rejected.
    pub messages_rejected: u64,
    /// CI changes fused.
    pub ci_fused: u64,
    /// Sensor batches missing from the stream (should stay 0: flow control sizes the buffers).
    pub stream_gaps: u64,
    /// Inputs the estimator rejected, by reason (`crate::agent::Rejections` keys): IMU
    /// samples, whole frames and single observations.
    #[serde(default)]
    pub rejections: std::collections::BTreeMap<String, u64>,
    /// Correspondences adopted by the DDF node (`NodeStats::merges_adopted`).
    #[serde(default)]
    pub merges_adopted: u64,
    /// Neighbours' correspondences refused (`NodeStats::merges_refused`).
    #[serde(default)]
    pub merges_refused: u64,
    /// Peak resident memory of the process so far [bytes] (Linux `VmHWM`; absent where the
    /// kernel does not report it).
    #[serde(default)]
    pub peak_rss_bytes: Option<u64>,
    /// Messages and declarations of other sessions that this process's zenoh access control
    /// refused, by `"<action> on <key>"` (`canopy_transport::access::refusals`): a
    /// non-neighbour, or a session using a key of a link it is not part of.
    #[serde(default)]
    pub access_refused: std::collections::BTreeMap<String, u64>,
    /// Local SLAM in own frames: this vehicle's side of the team frame.
    #[serde(default)]
    pub alignment: Option<Box<crate::frames::AlignmentReport>>,
}

/// What the estimator did with one observation (the monitor audits it against the truth).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Outcome {
    /// Associated to this feature.
    Associated(FeatureId),
    /// Initialized this feature.
    Initialized(FeatureId),
    /// Stored with this bearing-only track.
    Stored(u64),
    /// Not used.
    Rejected,
}

/// The outcomes of one frame, in the frame's order, and the bearing-only tracks that
/// initialized a feature in it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameAssociations {
    /// Frame time [s].
    pub t: f64,
    /// Per observation.
    pub outcomes: Vec<Outcome>,
    /// (track, feature) pairs.
    pub initialized_tracks: Vec<(u64, FeatureId)>,
    /// Data sharing: the vehicle that observed the frame, when another than the reporting one
    /// (its team filter processed it); the monitor audits it against that vehicle's true ids.
    #[serde(default)]
    pub origin: Option<u32>,
}

impl FrameAssociations {
    /// The outcomes of a frame at time `t` as the estimator reported them.
    pub fn from_report(t: f64, report: &canopy_fusion::slam::FrameReport) -> Self {
        use canopy_fusion::slam::ObservationOutcome;
        Self {
            t,
            outcomes: report
                .outcomes
                .iter()
                .map(|o| match *o {
                    ObservationOutcome::Associated { feature, .. } => Outcome::Associated(feature),
                    ObservationOutcome::Initialized { feature } => Outcome::Initialized(feature),
                    ObservationOutcome::Stored { track } => Outcome::Stored(track),
                    ObservationOutcome::Rejected(_) => Outcome::Rejected,
                })
                .collect(),
            initialized_tracks: report.initialized_tracks.clone(),
            origin: None,
        }
    }

    /// The same, for a frame another vehicle observed (data sharing).
    pub fn from_origin(self, origin: u32) -> Self {
        Self {
            origin: Some(origin),
            ..self
        }
    }
}

/// A vehicle's estimate at a record time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EstimateReport {
    /// Simulation time [s].
    pub t: f64,
    /// State p, v, Ψ, δf^b, δω^b (estimator frame).
    pub state: Vec<f64>,
    /// 15×15 covariance, row-major.
    pub covariance: Vec<f64>,
    /// Counters so far (this incarnation).
    pub counters: VehicleCounters,
    /// Links.
    pub links: Vec<LinkReport>,
    /// Frames processed since the previous report.
    pub associations: Vec<FrameAssociations>,
    /// Whose own frame the estimate is in (local SLAM in own frames; `None`: the team's
    /// shared frame).
    #[serde(default)]
    pub frame_owner: Option<NodeId>,
}

/// One feature of a map report (estimator frame).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeatureReport {
    /// Feature id.
    pub id: FeatureId,
    /// Mean.
    pub mean: [f64; 3],
    /// Covariance, upper triangle row by row (xx, xy, xz, yy, yz, zz).
    pub cov: [f64; 6],
}

impl FeatureReport {
    /// The full 3×3 covariance.
    pub fn covariance(&self) -> nalgebra::Matrix3<f64> {
        canopy_fusion::ddf::from_upper_triangle(&self.cov)
    }
}

/// A vehicle's map at a record time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MapReport {
    /// Simulation time [s].
    pub t: f64,
    /// The last map of the run (sent at the end of the stream or at shutdown).
    pub last: bool,
    /// Features.
    pub features: Vec<FeatureReport>,
    /// The correspondences the vehicle has adopted so far (each merged key → its canonical
    /// key), for the monitor's truth metrics.
    #[serde(default)]
    pub merges: Vec<canopy_fusion::keys::Merge>,
    /// Whose own frame the map is in (`None`: the team's shared frame).
    #[serde(default)]
    pub frame_owner: Option<NodeId>,
}

/// Truth of one vehicle at a record time (world → monitor only).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TruthReport {
    /// Vehicle.
    pub vehicle: NodeId,
    /// Time [s].
    pub t: f64,
    /// p, v, Ψ, δf^b, δω^b in the estimator's frame (biases in effect).
    pub nav: [f64; 15],
    /// Launch-frame position, velocity and attitude.
    pub launch: [f64; 9],
}

/// True feature ids of one frame (world → monitor only).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameTruth {
    /// Vehicle.
    pub vehicle: NodeId,
    /// Frame time [s].
    pub t: f64,
    /// True id per observation.
    pub ids: Vec<FeatureId>,
}

/// Anything → monitor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Report {
    /// The process is up (after its links are open).
    Started {
        /// OS process id.
        pid: u32,
        /// DDF epoch (vehicles and hub; 0 for the world).
        epoch: u64,
        /// Incarnation (vehicles; 0 otherwise).
        incarnation: u32,
    },
    /// A vehicle's estimate.
    Estimate(EstimateReport),
    /// A vehicle's map.
    Map(MapReport),
    /// The hub's link statistics at its time `t`.
    Hub {
        /// World time [s].
        t: f64,
        /// Links.
        links: Vec<LinkReport>,
        /// Messages rejected by the hub's DDF node.
        rejected: u64,
        /// What its zenoh access control refused (as [`VehicleCounters::access_refused`]).
        access_refused: std::collections::BTreeMap<String, u64>,
        /// Every failure on the hub's fusion path, by reason (`HubAgent::rejections`).
        #[serde(default)]
        rejections: std::collections::BTreeMap<String, u64>,
    },
    /// Truth (world only), at record times.
    Truth {
        /// World time [s].
        t: f64,
        /// Per vehicle at its record times since the previous report.
        samples: Vec<TruthReport>,
        /// True ids of the frames since the previous report.
        frames: Vec<FrameTruth>,
        /// Vehicles the world is streaming to (live).
        live: Vec<NodeId>,
    },
    /// A vehicle (re)started at `t` from this initial estimate (world only).
    Initialized {
        /// Vehicle.
        vehicle: NodeId,
        /// Incarnation.
        incarnation: u32,
        /// Time [s].
        t: f64,
    },
    /// The world holds the stream at the restart time `t` of `vehicle` until its new process
    /// asks for initialisation (world only).
    Waiting {
        /// Vehicle.
        vehicle: NodeId,
        /// Incarnation it waits for.
        incarnation: u32,
        /// Restart time [s].
        t: f64,
    },
    /// The sender's work is done (vehicle: end of stream processed; world: end reached).
    Finished {
        /// Simulation time [s].
        t: f64,
    },
    /// The process is giving up (it exits non-zero after this).
    Failed {
        /// Why.
        reason: String,
    },
    /// What the process is doing, sent about once a wall-clock second (the monitor's
    /// watchdog names who holds a stalled run up, and why).
    Status {
        /// Its simulation time [s].
        t: f64,
        /// What it is doing or waiting for, in words.
        state: String,
        /// It waits for something that has its own deadline (start-up, a scheduled restart):
        /// not a stall.
        bounded_wait: bool,
    },
}

impl Report {
    /// The envelope kind this report travels with.
    pub fn kind(&self) -> MessageKind {
        match self {
            Report::Map(_) => MessageKind::MAP_REPORT,
            _ => MessageKind::ESTIMATE_REPORT,
        }
    }
}

fn links_finite(_links: &[LinkReport]) -> Result<(), ValidationError> {
    // Integer counters and flags only.
    Ok(())
}

impl Validate for Report {
    fn validate(&self) -> Result<(), ValidationError> {
        match self {
            Report::Started { .. } | Report::Failed { .. } => Ok(()),
            Report::Estimate(e) => {
                dim("estimate.state", VEHICLE_DIM, e.state.len())?;
                dim(
                    "estimate.covariance",
                    VEHICLE_DIM * VEHICLE_DIM,
                    e.covariance.len(),
                )?;
                finite("estimate.t", [e.t])?;
                finite("estimate.state", e.state.iter().copied())?;
                finite("estimate.covariance", e.covariance.iter().copied())?;
                finite("estimate.associations", e.associations.iter().map(|a| a.t))?;
                links_finite(&e.links)
            }
            Report::Map(m) => {
                finite("map.t", [m.t])?;
                finite(
                    "map.features",
                    m.features
                        .iter()
                        .flat_map(|f| f.mean.iter().chain(f.cov.iter()).copied()),
                )
            }
            Report::Hub { t, links, .. } => {
                finite("hub.t", [*t])?;
                links_finite(links)
            }
            Report::Truth {
                t, samples, frames, ..
            } => {
                finite("truth.t", [*t])?;
                finite(
                    "truth.samples",
                    samples
                        .iter()
                        .flat_map(|s| std::iter::once(s.t).chain(s.nav).chain(s.launch)),
                )?;
                finite("truth.frames", frames.iter().map(|f| f.t))
            }
            Report::Initialized { t, .. }
            | Report::Waiting { t, .. }
            | Report::Finished { t }
            | Report::Status { t, .. } => finite("t", [*t]),
        }
    }
}

/// Host launcher → monitor over the control plane of a multi-host run (zenoh, under
/// `deploy::control_prefix`): the host's local processes' reports, relayed as they came, and
/// how its processes ended. The monitor → host direction carries [`Control`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum HostMsg {
    /// The host launcher is up and runs this share of the run (sent until the monitor answers
    /// with [`Control::Welcome`]).
    Hello {
        /// `[[host]].name`.
        host: String,
        /// Its resolved `[run].duration_s` (every host and the monitor must agree).
        duration_s: f64,
        /// `[world].seed` (the same check).
        seed: u64,
    },
    /// A report of one of the host's processes (`from`: vehicle id, hub id or [`WORLD_ID`]).
    Report {
        /// Sender on the host.
        from: NodeId,
        /// Its report.
        report: Report,
    },
    /// One of the host's processes ended.
    Process(super::monitor::ProcessRecord),
    /// The host launcher is done (all its processes ended); `failure` says why it failed.
    Done {
        /// Why the host's share failed, if it did.
        failure: Option<String>,
    },
    /// The zenoh router (`canopy router`, client mode) → monitor: everything its access control
    /// has refused of the clients so far, by `"<action> on <key>"` (ingress: what a client
    /// attempted), sent whenever it changes and when the monitor ends the run.
    Refusals(std::collections::BTreeMap<String, u64>),
}

impl Validate for HostMsg {
    fn validate(&self) -> Result<(), ValidationError> {
        match self {
            HostMsg::Hello { duration_s, .. } => finite("hello.duration_s", [*duration_s]),
            HostMsg::Report { report, .. } => report.validate(),
            HostMsg::Process(p) => finite("process.ended_at", [p.ended_at]),
            HostMsg::Done { .. } | HostMsg::Refusals(_) => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_transport::codec::{decode, encode_to_vec};
    use canopy_transport::{CodecError, SendMeta};
    use nalgebra::Vector3;

    fn round_trip<
        B: Serialize + for<'a> Deserialize<'a> + Validate + PartialEq + std::fmt::Debug,
    >(
        b: &B,
    ) -> Result<B, CodecError> {
        let bytes =
            encode_to_vec(&SendMeta::new(MessageKind::CONTROL, 1, 0.0), 7, b, 1 << 20).unwrap();
        decode::<B>(&bytes, 1 << 20).map(|(_, b)| b)
    }

    #[test]
    fn bodies_round_trip_through_the_codec() {
        let batch = WorldMsg::Batch {
            seq: 3,
            items: vec![
                SensorItem::Imu(ImuSample {
                    time: 0.01,
                    dt: 0.01,
                    specific_force: Vector3::new(0.0, 0.1, -9.8),
                    angular_rate: Vector3::new(1e-3, 0.0, 0.0),
                }),
                SensorItem::Frame(ObservationFrame {
                    time: 0.01,
                    observations: vec![],
                }),
            ],
        };
        assert_eq!(round_trip(&batch).unwrap(), batch);
        let report = Report::Map(MapReport {
            t: 2.0,
            last: true,
            features: vec![FeatureReport {
                id: 9,
                mean: [1.0, 2.0, 3.0],
                cov: [1.0, 0.1, 0.0, 2.0, 0.0, 3.0],
            }],
            merges: vec![canopy_fusion::keys::Merge { from: 9, into: 4 }],
            frame_owner: Some(3),
        });
        assert_eq!(round_trip(&report).unwrap(), report);
        assert_eq!(round_trip(&Control::Shutdown).unwrap(), Control::Shutdown);
    }

    #[test]
    fn invalid_bodies_are_rejected_not_accepted() {
        let bad_init = WorldMsg::Init(InitMsg {
            incarnation: 0,
            time: 0.0,
            state: vec![0.0; 14],
            covariance: vec![0.0; 225],
        });
        assert!(matches!(
            round_trip(&bad_init),
            Err(CodecError::Invalid(ValidationError::Dimension { .. }))
        ));
        let nan = Report::Map(MapReport {
            t: 1.0,
            last: false,
            features: vec![FeatureReport {
                id: 1,
                mean: [f64::NAN, 0.0, 0.0],
                cov: [1.0, 0.0, 0.0, 1.0, 0.0, 1.0],
            }],
            merges: Vec::new(),
            frame_owner: None,
        });
        assert!(matches!(
            round_trip(&nan),
            Err(CodecError::Invalid(ValidationError::NonFinite { .. }))
        ));
        let nan_imu = WorldMsg::Batch {
            seq: 1,
            items: vec![SensorItem::Imu(ImuSample {
                time: 0.01,
                dt: 0.01,
                specific_force: Vector3::new(f64::INFINITY, 0.0, 0.0),
                angular_rate: Vector3::zeros(),
            })],
        };
        assert!(round_trip(&nan_imu).is_err());
    }

    /// The monitor's orders to a host launcher (scheduled events across hosts) survive the
    /// codec; an empty process name or a restart as incarnation 0 (the first start) is
    /// refused.
    #[test]
    fn event_orders_round_trip_and_bad_ones_are_refused() {
        let kill = Control::Kill {
            name: "uav3".into(),
        };
        assert_eq!(round_trip(&kill).unwrap(), kill);
        let restart = Control::Restart {
            vehicle: 3,
            incarnation: 1,
        };
        assert_eq!(round_trip(&restart).unwrap(), restart);
        for bad in [
            Control::Kill {
                name: String::new(),
            },
            Control::Restart {
                vehicle: 3,
                incarnation: 0,
            },
        ] {
            assert!(
                matches!(
                    round_trip(&bad),
                    Err(CodecError::Invalid(ValidationError::Other(_)))
                ),
                "{bad:?} accepted"
            );
        }
    }
}
