//! Data sharing at a vehicle (`[fusion] mode = "shared_data"`, docs/arch/sharing.md).
//!
//! Instead of map information, the team's *data* travels: each vehicle publishes its initial
//! estimate, its IMU summed into increments of [`crate::network::FusionConfig::share_imu_hz`]
//! and its terrain frames as records of its stream; the relay
//! ([`canopy_fusion::share::Relay`]) carries every stream over the tree to every node, once and
//! in order, within each link's byte budget. Every vehicle runs one EKF over the whole team
//! (M = N vehicles, the centralized reference's filter): its own samples as they come, every
//! other vehicle's records as they arrive. A static map makes the order across vehicles
//! immaterial (each vehicle's records stay in their order), so each node holds the centralized
//! estimate of the data it has received: consistent as the reference is, and equal to it up to
//! the linearisation points once the data is through.
//!
//! Tracker ids are per vehicle: a remote frame's descriptors are moved into its origin's
//! namespace before association (under appearance identities; with perfect identities the
//! descriptors are the true ids, the ablation, and stay as they are).

use std::collections::BTreeMap;

use canopy_fusion::ddf::{Body, DdfMessage, Header, Outgoing};
use canopy_fusion::sensor::{ImuSample, ObservationFrame};
use canopy_fusion::share::{Item, Relay, RelayConfig, ShareError};
use canopy_fusion::slam::{FrameReport, SlamConfig, SlamError, SlamFilter, VehicleSetup};
use canopy_fusion::topology::{NodeId, Topology};
use nalgebra::Vector3;

use crate::agent::{Rejections, variant_key};

/// A round's batch budget on a link without a radio (shared memory, zenoh): large enough for
/// any backlog of a team's data without being unbounded.
pub const UNLIMITED_ROUND_BYTES: usize = 4 << 20;

/// A remote frame the team filter processed: what the monitor audits against the truth.
#[derive(Clone, Debug)]
pub struct RemoteFrame {
    /// The vehicle that observed it.
    pub origin: NodeId,
    /// Its time.
    pub time: f64,
    /// What the filter did with it.
    pub report: FrameReport,
}

/// Counters of data sharing at one vehicle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct SharingCounters {
    /// Records of other vehicles applied to the team filter.
    pub applied: u64,
    /// Records the team filter refused (counted by reason in the rejections).
    pub refused: u64,
    /// The relay's counters.
    pub relay: canopy_fusion::share::RelayCounters,
}

/// Sums IMU samples into one increment: the mean specific force and rate over its Δt
/// (Δv / Δt, Δθ / Δt), ending at the last sample's time.
#[derive(Clone, Debug, Default)]
pub struct Increment {
    sum: Option<ImuSample>,
}

impl Increment {
    /// Adds a sample.
    pub fn add(&mut self, s: &ImuSample) {
        let a = self.sum.get_or_insert(ImuSample {
            time: s.time,
            dt: 0.0,
            specific_force: Vector3::zeros(),
            angular_rate: Vector3::zeros(),
        });
        a.time = s.time;
        a.dt += s.dt;
        a.specific_force += s.specific_force * s.dt;
        a.angular_rate += s.angular_rate * s.dt;
    }

    /// The time it spans so far [s].
    pub fn dt(&self) -> f64 {
        self.sum.as_ref().map_or(0.0, |a| a.dt)
    }

    /// The increment as one sample, and a fresh start (`None` when empty).
    pub fn take(&mut self) -> Option<ImuSample> {
        let mut a = self.sum.take()?;
        a.specific_force /= a.dt;
        a.angular_rate /= a.dt;
        Some(a)
    }
}

/// The frame of vehicle `index` as the team filter takes it: with `namespaced` (appearance
/// identities) its tracker ids moved into the vehicle's own namespace, so that the team filter
/// never takes one vehicle's track for another's; as it is otherwise (perfect identities: the
/// descriptors are the true ids).
pub fn for_team_filter(
    index: usize,
    frame: &ObservationFrame,
    namespaced: bool,
) -> ObservationFrame {
    let mut f = frame.clone();
    if namespaced {
        for o in &mut f.observations {
            o.descriptor ^= (index as u64 + 1) << 48;
        }
    }
    f
}

/// The estimator's side of data sharing: this vehicle's index in the team filter and the
/// records it publishes (its IMU summed into increments, its frames), handed to the relay at
/// each round.
#[derive(Clone, Debug)]
pub struct OwnRecords {
    index: usize,
    increment: Increment,
    increment_s: f64,
    namespaced: bool,
    outbox: Vec<Item>,
}

impl OwnRecords {
    /// This vehicle's index in the team filter.
    pub fn index(&self) -> usize {
        self.index
    }

    /// An own IMU sample the filter took: summed into the increment, published when it spans
    /// 1/`share_imu_hz`.
    pub fn on_imu(&mut self, imu: &ImuSample) {
        self.increment.add(imu);
        if self.increment.dt() >= self.increment_s - 1e-9
            && let Some(inc) = self.increment.take()
        {
            self.outbox.push(Item::Imu(inc));
        }
    }

    /// An own frame (before the filter takes it): the increment up to it is published first,
    /// then the frame as the sensor gave it. Returns the frame the team filter takes.
    pub fn on_frame(&mut self, frame: &ObservationFrame) -> ObservationFrame {
        if let Some(inc) = self.increment.take() {
            self.outbox.push(Item::Imu(inc));
        }
        self.outbox.push(Item::Frame(frame.clone()));
        for_team_filter(self.index, frame, self.namespaced)
    }

    /// The records published since the last call.
    pub fn take(&mut self) -> Vec<Item> {
        std::mem::take(&mut self.outbox)
    }
}

/// The fusion side of data sharing: the relay, and the other vehicles' records applied to the
/// team filter at each round.
#[derive(Debug)]
pub struct Relaying {
    me: NodeId,
    epoch: u64,
    /// Team order (the scenario's): index in the team filter.
    team: Vec<NodeId>,
    relay: Relay<Item>,
    /// Per vehicle, the stream whose records the team filter takes (`None` before its first
    /// start): the latest incarnation's.
    active: Vec<Option<u64>>,
    namespaced: bool,
    budgets: BTreeMap<NodeId, usize>,
    neighbours: Vec<NodeId>,
    remote_frames: Vec<RemoteFrame>,
    counters: SharingCounters,
}

/// The stream epoch of a process start: its incarnation in the top 16 bits, so that a
/// vehicle's streams order by incarnation ([`canopy_fusion::share::StreamId`] orders by epoch),
/// and the process's fresh epoch below.
pub fn stream_epoch(incarnation: u32, epoch: u64) -> u64 {
    (u64::from(incarnation & 0xFFFF) << 48) | (epoch & 0xFFFF_FFFF_FFFF)
}

/// Data sharing for vehicle `me` (process start `incarnation`, fresh `epoch`): its team filter,
/// over every vehicle of `team` (scenario order) with the models of `setups` — the state and
/// covariance of each vehicle but `me` are placeholders until its stream's start record arrives
/// (nothing touches a vehicle before) — the estimator's side and the relay's. `namespaced`: tracker ids are
/// moved into their vehicle's namespace (appearance identities).
#[allow(clippy::too_many_arguments)]
pub fn build(
    me: NodeId,
    incarnation: u32,
    epoch: u64,
    slam: SlamConfig,
    team: &[NodeId],
    setups: &[VehicleSetup],
    topology: &Topology,
    share_imu_hz: f64,
    namespaced: bool,
) -> Result<(SlamFilter, OwnRecords, Relaying), SharingError> {
    let index = team
        .iter()
        .position(|&v| v == me)
        .ok_or(SharingError::NotInTeam(me))?;
    if setups.len() != team.len() {
        return Err(SharingError::Setup(format!(
            "{} setups for {} vehicles",
            setups.len(),
            team.len()
        )));
    }
    if !(share_imu_hz.is_finite() && share_imu_hz > 0.0) {
        return Err(SharingError::Setup(format!(
            "share_imu_hz {share_imu_hz} must be positive"
        )));
    }
    let filter = SlamFilter::new(slam, setups)?;
    let epoch = stream_epoch(incarnation, epoch);
    let mut relay = Relay::new(me, epoch, topology, RelayConfig::default())?;
    let own = &setups[index];
    relay.publish(Item::Start {
        state: own.state,
        covariance: Box::new(own.covariance),
    })?;
    let mut active = vec![None; team.len()];
    active[index] = Some(epoch);
    let records = OwnRecords {
        index,
        increment: Increment::default(),
        increment_s: 1.0 / share_imu_hz,
        namespaced,
        outbox: Vec::new(),
    };
    let relaying = Relaying {
        me,
        epoch,
        team: team.to_vec(),
        relay,
        active,
        namespaced,
        budgets: BTreeMap::new(),
        neighbours: topology.neighbours(me).unwrap_or_default().to_vec(),
        remote_frames: Vec::new(),
        counters: SharingCounters::default(),
    };
    Ok((filter, records, relaying))
}

impl Relaying {
    /// Counters of sharing.
    pub fn counters(&self) -> SharingCounters {
        SharingCounters {
            relay: self.relay.counters(),
            ..self.counters
        }
    }

    /// The other vehicles' frames processed since the last call.
    pub fn take_remote_frames(&mut self) -> Vec<RemoteFrame> {
        std::mem::take(&mut self.remote_frames)
    }

    /// The relay (what it holds).
    pub fn relay(&self) -> &Relay<Item> {
        &self.relay
    }

    /// This vehicle's records since the last round, into its stream.
    pub fn publish(&mut self, records: Vec<Item>, rejections: &mut Rejections) {
        for r in records {
            if let Err(e) = self.relay.publish(r) {
                rejections.add(format!("share.publish.{}", e.reason()), 1, &e);
            }
        }
    }

    /// The byte budgets of the next round, per link (links not listed:
    /// [`UNLIMITED_ROUND_BYTES`]).
    pub fn set_link_budgets(&mut self, budgets: &[(NodeId, usize)]) {
        self.budgets = budgets.iter().copied().collect();
    }

    /// A round on the team filter: applies what arrived, then a batch for every neighbour
    /// whose link is up, each handed to `emit`.
    pub fn round(
        &mut self,
        filter: &mut SlamFilter,
        now: f64,
        rejections: &mut Rejections,
        emit: &mut dyn FnMut(Outgoing),
    ) {
        self.apply_ready(filter, rejections);
        for peer in self.neighbours.clone() {
            let budget = self
                .budgets
                .get(&peer)
                .copied()
                .unwrap_or(UNLIMITED_ROUND_BYTES);
            if let Some(batch) = self.relay.outgoing(peer, budget, now) {
                emit(Outgoing {
                    to: peer,
                    message: DdfMessage {
                        header: Header {
                            from_epoch: self.epoch,
                            to_epoch: None,
                            challenge: 0,
                            echo_epoch: 0,
                            echo: 0,
                        },
                        body: Body::Share(batch),
                    },
                });
            }
        }
    }

    /// A message from a neighbour: a batch is taken by the relay (refused records counted by
    /// reason); any other kind is refused (a neighbour in another fusion mode). What it
    /// brought is applied at the next round, as the channel filters fuse their batch.
    pub fn on_message(
        &mut self,
        now: f64,
        from: NodeId,
        msg: DdfMessage,
        rejections: &mut Rejections,
    ) {
        let kind = msg.kind();
        let Body::Share(batch) = msg.body else {
            let e = SharingError::Unexpected { from, kind };
            rejections.add(
                format!("share.message.{}", variant_key(&format!("{e:?}"))),
                1,
                &e,
            );
            return;
        };
        match self.relay.on_batch(from, batch, now) {
            Ok(got) => {
                for e in &got.refused {
                    rejections.add(format!("share.record.{}", e.reason()), 1, e);
                }
            }
            Err(e) => rejections.add(format!("share.batch.{}", e.reason()), 1, &e),
        }
    }

    /// The link to `peer` came up.
    pub fn on_link_up(&mut self, now: f64, peer: NodeId) {
        self.relay.on_link_up(peer, now);
    }

    /// The link to `peer` went down.
    pub fn on_link_down(&mut self, peer: NodeId) {
        self.relay.on_link_down(peer);
    }

    /// Applies every record that is ready, in each stream's order; a vehicle's streams come in
    /// incarnation order ([`stream_epoch`]). A start of a later incarnation than the one
    /// applied restarts the vehicle in the team filter ([`SlamFilter::restart_vehicle`]: its old
    /// state marginalised out, the new start uncorrelated); records of an earlier incarnation
    /// after that are refused (`stale_incarnation`), as are this vehicle's own earlier streams
    /// (`earlier_incarnation`: their vehicle state is gone with the process that had it).
    fn apply_ready(&mut self, filter: &mut SlamFilter, rejections: &mut Rejections) {
        for (stream, _seq, item) in self.relay.take_ready() {
            if stream.origin == self.me {
                if stream.epoch != self.epoch {
                    self.refuse(
                        rejections,
                        "earlier_incarnation",
                        &"this vehicle's own earlier process",
                    );
                }
                continue;
            }
            let Some(index) = self.team.iter().position(|&v| v == stream.origin) else {
                self.refuse(rejections, "not_in_team", &"origin not in the team");
                continue;
            };
            let active = self.active[index];
            match item {
                Item::Start { state, covariance } => {
                    let result = match active {
                        None => filter.start_vehicle(index, &state, &covariance),
                        Some(e) if stream.epoch > e => {
                            filter.restart_vehicle(index, &state, &covariance)
                        }
                        Some(_) => {
                            self.refuse(
                                rejections,
                                "stale_incarnation",
                                &"a start of an earlier incarnation",
                            );
                            continue;
                        }
                    };
                    match result {
                        Ok(()) => {
                            self.active[index] = Some(stream.epoch);
                            self.counters.applied += 1;
                        }
                        Err(e) => self.refuse(rejections, "start", &e),
                    }
                }
                _ if active.is_none() => self.refuse(
                    rejections,
                    "before_start",
                    &"a record before its stream's start",
                ),
                _ if active != Some(stream.epoch) => self.refuse(
                    rejections,
                    "stale_incarnation",
                    &"a record of an earlier incarnation after a later one started",
                ),
                Item::Imu(imu) => match filter.predict(index, &imu) {
                    Ok(()) => self.counters.applied += 1,
                    Err(e) => {
                        let key = format!("imu.{}", variant_key(&format!("{e:?}")));
                        self.refuse(rejections, &key, &e);
                    }
                },
                Item::Frame(frame) => {
                    let f = for_team_filter(index, &frame, self.namespaced);
                    match filter.process_frame(index, &f) {
                        Ok(report) => {
                            self.counters.applied += 1;
                            self.remote_frames.push(RemoteFrame {
                                origin: stream.origin,
                                time: frame.time,
                                report,
                            });
                        }
                        Err(e) => {
                            let key = format!("frame.{}", variant_key(&format!("{e:?}")));
                            self.refuse(rejections, &key, &e);
                        }
                    }
                }
            }
        }
    }

    fn refuse(&mut self, rejections: &mut Rejections, reason: &str, cause: &dyn std::fmt::Display) {
        self.counters.refused += 1;
        rejections.add(format!("share.apply.{reason}"), 1, cause);
    }
}

/// Errors of data sharing at a vehicle.
#[derive(Debug, thiserror::Error)]
pub enum SharingError {
    /// The vehicle is not in the team.
    #[error("vehicle {0} is not in the team")]
    NotInTeam(NodeId),
    /// The setup is unusable.
    #[error("data sharing: {0}")]
    Setup(String),
    /// The team filter could not be built.
    #[error(transparent)]
    Filter(#[from] SlamError),
    /// The relay could not be built.
    #[error(transparent)]
    Relay(#[from] ShareError),
    /// A message kind data sharing does not take.
    #[error("a {kind} message from node {from}: data sharing takes batches only")]
    Unexpected {
        /// The sender.
        from: NodeId,
        /// Its kind.
        kind: &'static str,
    },
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::network::FusionMode;
    use crate::scenario::Scenario;
    use canopy_fusion::ins::VehicleCovariance;
    use canopy_fusion::share::{Batch, ShareRecord, StreamId};

    /// The built-in team (tree 1 − 3, 2 − 3, 3 − 4) in data-sharing mode, and uav3's and
    /// uav1's agents (uav3 is index 2, the hub; uav1 a leaf).
    fn agents() -> (
        Scenario,
        crate::agent::VehicleAgent,
        crate::agent::VehicleAgent,
    ) {
        let mut s = Scenario::builtin_default();
        s.fusion.mode = FusionMode::SharedData;
        let (world, sources) = crate::replay::SensorSource::for_scenario(&s).unwrap();
        let build = |i: usize| {
            crate::sim::vehicle_agent(
                &s,
                &s.vehicles[i],
                &world,
                &sources[i].initial_estimate(),
                0,
                11 + i as u64,
            )
            .unwrap()
        };
        let (hub, leaf) = (build(2), build(0));
        (s, hub, leaf)
    }

    fn batch(records: Vec<(StreamId, u64, Item)>) -> DdfMessage {
        DdfMessage {
            header: Header {
                from_epoch: 99,
                to_epoch: None,
                challenge: 0,
                echo_epoch: 0,
                echo: 0,
            },
            body: Body::Share(Batch {
                epoch: 99,
                number: 1,
                have: Vec::new(),
                records,
            }),
        }
    }

    /// What it proves: a scenario that data sharing cannot run is refused at validation with
    /// the field and the reason (vehicles in own frames), and the shipped default validates
    /// in the mode (restarts are shared).
    #[test]
    fn own_frames_are_refused_at_validation() {
        let mut s = Scenario::builtin_default();
        s.fusion.mode = FusionMode::SharedData;
        s.validate().unwrap();
        let local =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../topologies/local-4.toml");
        let mut s = Scenario::load(&local).unwrap();
        assert_eq!(s.world.frames, crate::scenario::Frames::Own);
        s.fusion.mode = FusionMode::SharedData;
        let e = s.validate().unwrap_err().to_string();
        assert!(
            e.contains("world.frames") && e.contains("decentralized"),
            "{e}"
        );
    }

    /// Stream epochs order a vehicle's process starts by incarnation, whatever the fresh
    /// epochs drawn.
    #[test]
    fn stream_epochs_order_by_incarnation() {
        assert!(stream_epoch(1, 0) > stream_epoch(0, u64::MAX));
        assert!(stream_epoch(2, 5) > stream_epoch(1, u64::MAX));
        assert_eq!(stream_epoch(0, 7), 7);
    }

    /// What it proves: a vehicle publishes its start, then its IMU as increments at
    /// `share_imu_hz` (10 per second of 100-Hz samples), a frame closing the increment before
    /// it; each increment's Δt sums its samples'.
    #[test]
    fn own_data_goes_out_as_a_start_and_ten_increments_per_second() {
        let (s, _, mut leaf) = agents();
        let (_, mut sources) = crate::replay::SensorSource::for_scenario(&s).unwrap();
        let mut frames = 0;
        let mut imu_dt = 0.0;
        for _ in 0..100 {
            let st = sources[0].step().unwrap();
            imu_dt += st.imu.dt;
            leaf.on_imu(&st.imu).unwrap();
            if let Some((f, _)) = &st.frame {
                frames += 1;
                let _ = leaf.on_frame(f);
            }
        }
        // Published into the stream at the round.
        leaf.on_round(1.0).unwrap();
        let sharing = leaf.sharing().unwrap();
        let own = sharing.relay().own_stream();
        let records = sharing.relay().records(own);
        assert!(matches!(records[0], Item::Start { .. }));
        let increments: Vec<&ImuSample> = records
            .iter()
            .filter_map(|r| match r {
                Item::Imu(i) => Some(i),
                _ => None,
            })
            .collect();
        let shared_frames = records
            .iter()
            .filter(|r| matches!(r, Item::Frame(_)))
            .count();
        assert_eq!(shared_frames, frames);
        // 1 s of samples: 10 increments, plus one more per frame that closed one early.
        assert!(
            (10..=10 + frames).contains(&increments.len()),
            "{} increments, {frames} frames",
            increments.len()
        );
        let summed: f64 = increments.iter().map(|i| i.dt).sum();
        assert!((summed - imu_dt).abs() < 1e-9, "{summed} vs {imu_dt}");
        assert!(records.iter().all(|r| r.validate().is_ok()));
    }

    /// What it proves: hostile or misdirected input is refused, counted by reason, and leaves
    /// the team filter as it was: a channel-filter message at a data-sharing vehicle, a batch
    /// from a vehicle that is not a neighbour, a start record whose covariance is not positive
    /// definite, and frames of a vehicle whose start has not arrived; and a data-sharing batch
    /// at a channel-filter vehicle is refused there by its DDF node.
    #[test]
    fn hostile_input_is_refused_by_reason_and_harmless() {
        let (s, mut hub, _) = agents();
        let uav1 = NodeId(s.vehicles[0].id);
        let uav2 = NodeId(s.vehicles[1].id);
        let stream = StreamId {
            origin: uav1,
            epoch: 5,
        };
        let features = hub.filter().num_features();
        let state = hub.filter().vehicle_state(0).unwrap();
        let mut hello = batch(Vec::new());
        hello.body = Body::Nack { applied: 0 };
        hub.on_message(0.0, uav1, hello).unwrap();
        hub.on_message(0.0, NodeId(77), batch(Vec::new())).unwrap();
        let mut not_pd = VehicleCovariance::identity();
        not_pd[(4, 4)] = -1.0;
        hub.on_message(
            0.0,
            uav1,
            batch(vec![(
                stream,
                0,
                Item::Start {
                    state,
                    covariance: Box::new(not_pd),
                },
            )]),
        )
        .unwrap();
        let frame = ObservationFrame {
            time: 0.5,
            observations: Vec::new(),
        };
        hub.on_message(
            0.0,
            uav2,
            batch(vec![(
                StreamId {
                    origin: uav2,
                    epoch: 6,
                },
                0,
                Item::Frame(frame.clone()),
            )]),
        )
        .unwrap();
        hub.on_round(1.0).unwrap();
        let r = hub.rejections().counts;
        assert_eq!(r.get("share.message.unexpected"), Some(&1), "{r:?}");
        assert_eq!(r.get("share.batch.not_neighbour"), Some(&1), "{r:?}");
        assert_eq!(r.get("share.record.invalid_record"), Some(&1), "{r:?}");
        assert_eq!(r.get("share.apply.before_start"), Some(&1), "{r:?}");
        assert_eq!(hub.filter().num_features(), features);
        assert_eq!(hub.filter().vehicle_state(0).unwrap(), state);

        // A channel-filter vehicle refuses a data-sharing batch.
        let mut ddf = s.clone();
        ddf.fusion.mode = FusionMode::Decentralized;
        let (world, sources) = crate::replay::SensorSource::for_scenario(&ddf).unwrap();
        let mut dec = crate::sim::vehicle_agent(
            &ddf,
            &ddf.vehicles[2],
            &world,
            &sources[2].initial_estimate(),
            0,
            3,
        )
        .unwrap();
        assert!(dec.on_message(0.0, uav1, batch(Vec::new())).is_err());
        assert_eq!(dec.counters().fusion.messages_rejected, 1);
    }
}
