//! What a run gathers: estimate and truth time series per vehicle, final maps, link statistics,
//! fault events, and the centralized baseline. Written by the simulation or the monitor process,
//! read by [`crate::output`].
//!
//! Positions are metres in the launch site's local NED frame (global-frame runs are converted
//! from ECEF) and attitudes are the Euler triple of C_b^{n0} relative to that same frame, so every
//! output of a run shares one frame whatever the estimator's navigation frame was.

use serde::{Deserialize, Serialize};

/// One estimate-vs-truth sample of a vehicle.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct PoseSample {
    /// Simulation time [s].
    pub t: f64,
    /// Estimated position, launch NED [m].
    pub est_pos: [f64; 3],
    /// Estimated attitude (roll, pitch, yaw) relative to launch NED [rad].
    pub est_att: [f64; 3],
    /// True position, launch NED [m].
    pub truth_pos: [f64; 3],
    /// True attitude (roll, pitch, yaw) relative to launch NED [rad].
    pub truth_att: [f64; 3],
    /// Position covariance, launch NED, row-major 3×3 [m²].
    pub pos_cov: [f64; 9],
    /// Normalised estimation error squared of the position (3 dof).
    pub nees_pos: f64,
    /// NEES of the pose (position and attitude, 6 dof).
    pub nees_pose: f64,
}

impl PoseSample {
    /// Euclidean position error [m].
    pub fn position_error(&self) -> f64 {
        (0..3)
            .map(|i| (self.est_pos[i] - self.truth_pos[i]).powi(2))
            .sum::<f64>()
            .sqrt()
    }

    /// 1-σ position standard deviation of axis `i` [m].
    pub fn sigma(&self, i: usize) -> f64 {
        self.pos_cov[4 * i].max(0.0).sqrt()
    }
}

/// One feature of a final map.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct MapFeatureRecord {
    /// The feature's key in the map (the true id with perfect identities; the filter's own
    /// key with appearance).
    pub id: u64,
    /// The true feature the key stands for (`crate::truth`), when known.
    #[serde(default)]
    pub truth_id: Option<u64>,
    /// Estimated position, launch NED [m].
    pub est: [f64; 3],
    /// Covariance, launch NED, row-major 3×3 [m²].
    pub cov: [f64; 9],
    /// True position of `truth_id`, launch NED [m].
    pub truth: Option<[f64; 3]>,
    /// Since when this map has held the feature [s]: the first record time of the latest
    /// unbroken stretch of record times at which it was in the map (the end of the run for a
    /// feature that arrived after the last record time). Against the reference's figure it
    /// says how long the feature took to reach this vehicle.
    #[serde(default)]
    pub held_since: Option<f64>,
}

/// A vehicle's record.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct VehicleRecord {
    /// Vehicle name.
    pub name: String,
    /// Estimate-vs-truth samples in time order.
    pub samples: Vec<PoseSample>,
    /// The vehicle's map at the end of the run.
    pub map: Vec<MapFeatureRecord>,
    /// Association and final map against the truth (`crate::truth`; known to the harness
    /// only). Flattened: its fields sit beside these in JSON.
    #[serde(flatten)]
    pub association: crate::truth::TruthFigures,
    /// Observations processed.
    pub observations: u64,
    /// Received fusion messages rejected (malformed, non-neighbour, non-PD result, …).
    pub rejected_messages: u64,
    /// Times this vehicle's process was restarted.
    pub restarts: u32,
    /// Inputs its estimator rejected, by reason (`crate::agent::Rejections` keys), summed over
    /// its incarnations.
    #[serde(default)]
    pub rejections: std::collections::BTreeMap<String, u64>,
    /// Peak resident memory of its process [bytes] (`canopy run`; absent in `canopy sim`,
    /// where every vehicle shares one process).
    #[serde(default)]
    pub peak_rss_bytes: Option<u64>,
    /// Messages and declarations of other zenoh sessions its access control refused, by
    /// `"<action> on <key>"`, summed over its incarnations (`canopy run` with
    /// `[secrets].zenoh_password`; empty otherwise).
    #[serde(default)]
    pub access_refused: std::collections::BTreeMap<String, u64>,
    /// Local SLAM in own frames (`[world] frames = "own"`): how this vehicle joined the team
    /// frame; `None` in a shared frame.
    #[serde(default)]
    pub frame_alignment: Option<FrameAlignmentRecord>,
}

/// How a vehicle's own frame was aligned with the team frame (`crate::frames`), and the
/// alignment's error against the true relative frame (known to the harness only).
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct FrameAlignmentRecord {
    /// The vehicle holds the team frame (its own frame is the team's: nothing to align).
    pub root: bool,
    /// Simulation time the alignment was taken [s] (`None`: never, or the root).
    pub aligned_at_s: Option<f64>,
    /// The alignment's σ of the yaw [deg].
    pub sigma_yaw_deg: Option<f64>,
    /// The alignment's σ of the horizontal translation [m].
    pub sigma_translation_m: Option<f64>,
    /// Inlier correspondences of the alignment.
    pub inliers: Option<usize>,
    /// Yaw of the alignment minus the true one [deg] (truth).
    pub yaw_error_deg: Option<f64>,
    /// Horizontal translation of the alignment minus the true one [m] (truth).
    pub translation_error_m: Option<f64>,
    /// Attempts that gave no alignment, by reason (`too_few_candidates`, `no_consensus`,
    /// `ambiguous`, `not_converged`, `singular`, `unconfirmed`: two consecutive rounds
    /// disagreed).
    pub attempts_failed: std::collections::BTreeMap<String, u64>,
}

impl FrameAlignmentRecord {
    /// A vehicle that is not the root aligned, and its alignment's errors against the true
    /// frame are within `k` σ of its own covariance (yaw, and horizontal translation against
    /// the horizontal σ): its time if so, what is wrong otherwise.
    pub fn consistent_within(&self, k: f64) -> Result<f64, String> {
        let (Some(t), Some(sy), Some(st), Some(ey), Some(et)) = (
            self.aligned_at_s,
            self.sigma_yaw_deg,
            self.sigma_translation_m,
            self.yaw_error_deg,
            self.translation_error_m,
        ) else {
            return Err(format!("never aligned ({:?})", self.attempts_failed));
        };
        if ey.abs() > k * sy {
            return Err(format!("yaw error {ey}° against σ {sy}°"));
        }
        if et > k * st {
            return Err(format!("translation error {et} m against σ {st} m"));
        }
        Ok(t)
    }
}

/// One statistics sample of a link (cumulative counters at time `t`).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct LinkSample {
    /// Simulation time [s].
    pub t: f64,
    /// Bytes sent a → b so far.
    pub bytes_ab: u64,
    /// Bytes sent b → a so far.
    pub bytes_ba: u64,
    /// Messages sent in both directions so far.
    pub messages: u64,
    /// Messages dropped (loss, outage, bandwidth) so far.
    pub drops: u64,
    /// Messages rejected by a receiver so far.
    pub rejections: u64,
    /// Whether the link was up at `t` (both ends report it up).
    pub up: bool,
    /// Whether end a reported the link up at `t`.
    #[serde(default)]
    pub a_up: bool,
    /// Whether end b reported the link up at `t`.
    #[serde(default)]
    pub b_up: bool,
}

/// A link's record.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct LinkRecord {
    /// One end.
    pub a: String,
    /// The other end.
    pub b: String,
    /// `shm`, `net` or `sim`.
    pub transport: String,
    /// Whether the link has fallen back to covariance intersection.
    pub ci: bool,
    /// What the naive scheme would have sent on this link: each round, both ends' whole map
    /// information (Y, y) as dense f64 (8·(9n² + 3n) bytes for n features), the reference of
    /// the bandwidth ratio.
    #[serde(default)]
    pub naive_bytes: u64,
    /// Cumulative statistics over time.
    pub samples: Vec<LinkSample>,
}

/// A fault or lifecycle event.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct EventRecord {
    /// Start time [s].
    pub t: f64,
    /// End time [s], for events with a duration (outages, partitions).
    pub until: Option<f64>,
    /// `outage`, `partition`, `crash`, `restart`, `hub-loss`, `ci-fallback`, ….
    pub kind: String,
    /// What it concerns (a link `a-b` or a vehicle name).
    pub subject: String,
}

/// Everything a run gathered.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct RunRecord {
    /// Scenario name.
    pub scenario: String,
    /// Fusion mode.
    pub mode: String,
    /// Estimator navigation frame (`global` or `local`).
    pub frame: String,
    /// World seed.
    pub seed: u64,
    /// Simulated duration [s].
    pub duration: f64,
    /// Wall-clock time of the run [s].
    pub wall_time: f64,
    /// Vehicles.
    pub vehicles: Vec<VehicleRecord>,
    /// Links.
    pub links: Vec<LinkRecord>,
    /// Fault and lifecycle events.
    pub events: Vec<EventRecord>,
    /// The centralized all-data EKF fed the same observations, when it was run.
    pub baseline: Option<Vec<VehicleRecord>>,
    /// True feature positions (launch NED) by id, for the map plot.
    pub truth_features: Vec<(u64, [f64; 3])>,
    /// Distinct wrong merge facts adopted anywhere in the team (`crate::truth`).
    #[serde(default)]
    pub team_wrong_merges: u64,
    /// What the sensors told the estimators about identity: `perfect` (descriptor = true
    /// id) or `appearance` (`[world.appearance] identity`).
    #[serde(default)]
    pub identity: String,
    /// The recording's clock at t = 0 [ns] (`[run] time_origin_ns`): output timestamps are
    /// origin + t, in the recording's time base.
    #[serde(default)]
    pub time_origin_ns: Option<u64>,
    /// What the zenoh router's access control refused of its clients (multi-host runs in
    /// client mode, `canopy router`), by `"<action> on <key>"`; empty otherwise.
    #[serde(default)]
    pub router_access_refused: std::collections::BTreeMap<String, u64>,
}
