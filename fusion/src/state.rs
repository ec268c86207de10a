//! State layout of the inertial SLAM filter (design.md §3), with named index constants.
//!
//! One vehicle block is 15 states, in the order of eq. 21.1:
//! `p` (3), `v` (3), `Ψ = (φ, θ, ψ)` (3), `δf^b` (3, accelerometer bias), `δω^b_ib` (3, gyro bias).
//! In the global frame `p` and `v` are ECEF (eq. 21.1); in the local frame they are NED in the
//! shared local-level frame (eq. 21.26). A filter may carry several vehicle blocks (the
//! centralized reference filter), then map features `m_1..m_N` (3 each), then stored poses of
//! bearing-only SLAM (6 each: `p^n`, `Ψ^n`, eq. 21.66).

/// Offset of the position within a vehicle block.
pub const POS: usize = 0;
/// Offset of the velocity within a vehicle block.
pub const VEL: usize = 3;
/// Offset of the Euler attitude Ψ = (φ, θ, ψ) within a vehicle block.
pub const ATT: usize = 6;
/// Offset of the accelerometer bias δf^b within a vehicle block.
pub const ACC_BIAS: usize = 9;
/// Offset of the gyro bias δω^b_ib within a vehicle block.
pub const GYRO_BIAS: usize = 12;
/// Size of a vehicle block.
pub const VEHICLE_DIM: usize = 15;
/// Size of a map feature block.
pub const FEATURE_DIM: usize = 3;
/// Size of a stored pose block (position, attitude).
pub const POSE_DIM: usize = 6;
/// Offset of the position within a stored pose block.
pub const POSE_POS: usize = 0;
/// Offset of the attitude within a stored pose block.
pub const POSE_ATT: usize = 3;

/// Size of the process-noise vector w of eq. 21.17: accel, gyro, accel-bias drift, gyro-bias drift.
pub const NOISE_DIM: usize = 12;
/// Offset of w_accel in w.
pub const W_ACCEL: usize = 0;
/// Offset of w_gyro in w.
pub const W_GYRO: usize = 3;
/// Offset of w_b,accel in w.
pub const W_ACC_BIAS: usize = 6;
/// Offset of w_b,gyro in w (eq. 21.16 misprints it as w_b,accel).
pub const W_GYRO_BIAS: usize = 9;

/// Which navigation frame the filter's positions, velocities and map live in (§21.2.1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NavFrame {
    /// Global SLAM: ECEF positions and map, WGS-84 rotating Earth (eqs. 21.1–21.25).
    Global,
    /// Local SLAM: NED positions and map in a shared local-level frame, non-rotating flat Earth
    /// with constant gravity (eqs. 21.26–21.38).
    Local,
}

impl std::fmt::Display for NavFrame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            NavFrame::Global => "global",
            NavFrame::Local => "local",
        })
    }
}
