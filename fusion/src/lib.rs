//! canopy-fusion: the estimation maths of canopy. Pure: no I/O, threads, async or clocks.
//!
//! Equation numbers refer to Bryson & Sukkarieh, "Inertial Sensor-Based SLAM for UAVs"
//! (`shared/seed/inertial-slam-chapter.txt`).
//!
//! # Layout
//! - [`rotation`]: attitude conventions (Euler z-y-x, C_b^n, E_b^n of eq. 21.8), rotation
//!   vectors (exp, the SO(3) left Jacobian of an IMU interval, log).
//! - [`geodesy`]: WGS-84, C_n^e (21.12), Earth and transport rates (21.6, 21.7), gravity (21.9).
//! - [`state`]: state layout and named index constants.
//! - [`sensor`]: the estimator's inputs (IMU samples, terrain observations, sensor models).
//! - [`imu`]: IMU error model and grades (21.13–21.17).
//! - [`alignment`]: initial alignment from a rest period (levelling, gyro bias) and rest
//!   detection, for starting on real recordings.
//! - [`frames`]: relative frames of vehicles in local SLAM (4-DOF given gravity), their
//!   robust estimation from common features.
//! - [`consistency`]: NEES, χ² quantiles, ANEES bands, angle-aware errors.
//! - [`ins`]: INS mechanization in both frames with ∇F, ∇G and Q (21.19–21.38).
//! - [`observation`]: terrain observation models, J_1 initialization and their Jacobians (21.41–21.50).
//! - [`slam`]: the EKF-SLAM filter with M ≥ 1 vehicles: lazy INS prediction, association
//!   (descriptor, NN, JCBB), Joseph updates, feature initialization (range-bearing, and
//!   bearing-only with stored poses and delayed triangulation), fuse-back of map information.
//! - [`info`]: map information keyed by feature id (21.86, 21.87), its algebra, (21.98, 21.99).
//! - [`keys`]: feature keys and correspondences (merges as linear re-keyings of information).
//! - [`ci`]: covariance intersection for bandwidth-limited links (full and submap forms).
//! - [`ddf`]: the channel-filter protocol as a sans-IO state machine (decentralized, central).
//! - [`share`]: data sharing: every vehicle's records relayed over the tree, once and in order
//!   (sans-IO; the alternative to map information on links of tens of kB/s).
//! - [`topology`]: fusion-network graphs and tree validation (channel filters need a tree).
//! - [`runtime`]: process set-up for this maths (subnormals flushed to zero, heap kept mapped; the
//!   lean or warm heap policy, `[run] heap`).

pub mod alignment;
pub mod ci;
pub mod consistency;
pub mod ddf;
pub mod frames;
pub mod geodesy;
pub mod imu;
pub mod info;
pub mod ins;
pub mod keys;
pub mod observation;
pub mod rotation;
pub mod runtime;
pub mod sensor;
pub mod share;
pub mod slam;
pub mod sparse;
pub mod state;
pub mod topology;
