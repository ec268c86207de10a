//! canopy-node: the `canopy` binary's library.
//!
//! # Layout
//! - [`scenario`]: the scenario TOML (`[world]`, `[[vehicle]]`): serde structs, defaults, the
//!   built-in default scenario and validation with typed errors naming the field.
//! - [`world`]: the world simulator — seeded terrain and features, analytic trajectories with
//!   coordinated-flight attitude, IMU synthesis (discrete inverse of the mechanization or
//!   continuous), the terrain sensor, simulated appearance (descriptors, trackers; `[world.
//!   appearance]`), and per-step truth; a pure, step-able library used by the `world` process
//!   and by `canopy sim`.
//! - [`network`]: the scenario's `[run]`, `[fusion]`, `[[link]]`, `[[partition]]`, `[[event]]`,
//!   `[secrets]` tables, their validation and the fusion topology.
//! - [`radio`]: `[[link]] radio = { … }` — capacity, queue, latency and range of a radio
//!   link, its vehicles' true separation, and the per-round submap budget derived from the
//!   capacity and the outbound queue.
//! - [`deploy`]: the scenario's `[zenoh]` and `[[host]]` tables — which host runs which
//!   vehicles in a multi-host run, derived zenoh endpoints, key prefix, zenoh users.
//! - [`record`]: what a run gathers (estimates vs truth, maps, link statistics, events).
//! - [`truth`]: association against the truth (monitor and `canopy sim` only): each key's
//!   true feature, wrong associations and merges, duplicates, unmatched features.
//! - [`output`]: summary.json, TUM trajectories, CSVs and report.html.
//! - [`agent`]: the vehicle and hub agents (estimator + DDF node, sans-IO).
//! - [`sharing`]: data sharing (`[fusion] mode = "shared_data"`) — a vehicle's team filter
//!   fed its own data and every other vehicle's records relayed over the tree.
//! - [`frames`]: local SLAM in own frames — anchors, the alignment of a vehicle's frame with
//!   the team frame, joining the channel filters after it.
//! - [`sim`]: `canopy sim`, the whole scenario in one deterministic process.
//! - [`baseline`]: the centralized all-data reference EKF driver.
//! - [`replay`]: recorded sensor logs (CSV) and the sensor sources of a run.
//! - [`preflight`]: every check of a scenario and its inputs before a run (`check` and the
//!   launcher of `run`; `sim` builds the same sources and agents).
//! - [`process`]: `canopy run` — the world, vehicle, hub and monitor processes.
//! - [`team`]: generated tree teams of any size (`canopy team N`, benchmarks, scale tests).
//! - [`eval`]: trajectory evaluation against ground truth (`canopy eval EST GT`): TUM and
//!   EuRoC CSV readers, evo's timestamp association, ATE after SE(3) / position+yaw / Sim(3) /
//!   no alignment, evo's RPE and rpg_trajectory_evaluation's relative error.
//! - [`import`]: `canopy import` — a real recording (EuRoC/ASL, Kalibr calibration, feature
//!   tracks, ground truth) into a replay scenario, with the frame and time conversions.
//! - [`cli`]: the command line.

pub mod agent;
pub mod baseline;
pub mod cli;
pub mod deploy;
pub mod eval;
pub mod frames;
pub mod import;
pub mod metrics;
pub mod network;
pub mod output;
pub mod preflight;
pub mod process;
pub mod radio;
pub mod record;
pub mod replay;
pub mod scenario;
pub mod sharing;
pub mod sim;
pub mod team;
pub mod truth;
pub mod wire;
pub mod world;
