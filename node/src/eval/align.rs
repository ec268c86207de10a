//! Aligning an estimated trajectory to the ground truth before the absolute error.
//!
//! Every alignment is a similarity `gt ≈ s·R·est + t` found from the matched positions only
//! (all of them), applied to the estimate's whole poses: position `s·R·p + t`, attitude `R·C`.
//!
//! * SE(3) and Sim(3): Umeyama, "Least-squares estimation of transformation parameters between
//!   two point patterns", IEEE PAMI 13(4), 1991 (equation numbers below are the paper's) — what
//!   `evo_ape --align` and `--align --correct_scale` compute (`evo.core.geometry`).
//! * Position and yaw (4-DOF): the least-squares rotation about the vertical axis and
//!   translation, rpg_trajectory_evaluation's `posyaw` over all poses (`align_num_frames: -1`).
//!   Both frames must be gravity aligned; each one's z axis points up or down ([`ZAxis`]). When
//!   they differ, the estimate is first turned upside down about x (F = diag(1, −1, −1); any
//!   rotation taking its up to the ground truth's serves, the yaw absorbs the choice).

use nalgebra::{Isometry3, Matrix3, Rotation3, SVD, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// Which alignment precedes the absolute trajectory error.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
pub enum Alignment {
    /// Rotation and translation (Umeyama, no scale): `evo_ape --align`.
    #[serde(rename = "se3")]
    #[value(name = "se3")]
    Se3,
    /// Yaw about the vertical and translation (rpg_trajectory_evaluation's `posyaw`).
    #[serde(rename = "posyaw")]
    #[value(name = "posyaw")]
    PosYaw,
    /// Rotation, translation and scale (Umeyama): `evo_ape --align --correct_scale`.
    #[serde(rename = "sim3")]
    #[value(name = "sim3")]
    Sim3,
    /// None: the estimate as it is (`evo_ape` without `--align`).
    #[serde(rename = "none")]
    #[value(name = "none")]
    Unaligned,
}

impl std::fmt::Display for Alignment {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Se3 => "se3",
            Self::PosYaw => "posyaw",
            Self::Sim3 => "sim3",
            Self::Unaligned => "none",
        })
    }
}

impl Alignment {
    /// Matched poses the alignment needs at the least (three points span a plane; the yaw
    /// needs two at different horizontal places).
    pub fn min_poses(self) -> usize {
        match self {
            Self::Se3 | Self::Sim3 => 3,
            Self::PosYaw => 2,
            Self::Unaligned => 1,
        }
    }
}

/// Which way a gravity-aligned frame's z axis points (position+yaw alignment only).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ZAxis {
    /// z up (ENU, EuRoC's motion-capture frame, rpg_trajectory_evaluation's assumption).
    Up,
    /// z down (NED: canopy's own outputs).
    Down,
}

impl std::fmt::Display for ZAxis {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Up => "up",
            Self::Down => "down",
        })
    }
}

/// A degenerate alignment problem.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AlignError {
    /// Too few matched poses.
    #[error("{alignment} alignment needs at least {needed} matched poses, got {got}")]
    TooFewPoses {
        /// The alignment.
        alignment: Alignment,
        /// Poses needed.
        needed: usize,
        /// Poses given.
        got: usize,
    },
    /// The positions do not determine the transform.
    #[error("{alignment} alignment is degenerate: {reason}")]
    Degenerate {
        /// The alignment.
        alignment: Alignment,
        /// Why.
        reason: &'static str,
    },
}

/// A similarity `gt ≈ scale · rotation · est + translation` (ground-truth frame from estimate
/// frame).
#[derive(Clone, Debug, PartialEq)]
pub struct GtFromEst {
    /// Rotation.
    pub rotation: Rotation3<f64>,
    /// Translation [m, ground-truth frame].
    pub translation: Vector3<f64>,
    /// Scale (1 unless Sim(3)).
    pub scale: f64,
}

impl GtFromEst {
    /// No change.
    pub fn identity() -> Self {
        Self {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// An estimated pose in the ground-truth frame: position `s·R·p + t`, attitude `R·C`.
    pub fn apply(&self, est_world_from_body: &Isometry3<f64>) -> Isometry3<f64> {
        let p = est_world_from_body.translation.vector;
        Isometry3::from_parts(
            Translation3::from(self.scale * (self.rotation * p) + self.translation),
            UnitQuaternion::from_rotation_matrix(&self.rotation) * est_world_from_body.rotation,
        )
    }
}

/// Relative threshold on the second singular value of the cross-covariance below which the
/// points are taken as collinear (evo: fewer than two singular values above machine epsilon,
/// absolute). Relative, so it does not depend on the trajectory's size in metres.
const RANK_TOLERANCE: f64 = 1e-12;

/// 1/n and the means of the estimate's and the ground truth's positions, once there are enough
/// of them for `alignment`.
fn means(
    alignment: Alignment,
    est: &[Vector3<f64>],
    gt: &[Vector3<f64>],
) -> Result<(f64, Vector3<f64>, Vector3<f64>), AlignError> {
    let n = est.len().min(gt.len());
    if n < alignment.min_poses() {
        return Err(AlignError::TooFewPoses {
            alignment,
            needed: alignment.min_poses(),
            got: n,
        });
    }
    let inv_n = 1.0 / n as f64;
    let mean = |p: &[Vector3<f64>]| p[..n].iter().sum::<Vector3<f64>>() * inv_n;
    Ok((inv_n, mean(est), mean(gt)))
}

/// Umeyama's least-squares similarity (with `with_scale`) or rigid transform from the estimate's
/// positions to the ground truth's (eqs. 34–43).
pub fn umeyama(
    est: &[Vector3<f64>],
    gt: &[Vector3<f64>],
    with_scale: bool,
) -> Result<GtFromEst, AlignError> {
    let alignment = if with_scale {
        Alignment::Sim3
    } else {
        Alignment::Se3
    };
    // Means (eqs. 34, 35).
    let (inv_n, mean_est, mean_gt) = means(alignment, est, gt)?;
    // Variance of the estimate's points (eq. 36) and the cross-covariance Σ_gt,est (eq. 38).
    let mut var_est = 0.0;
    let mut cov = Matrix3::zeros();
    for (e, g) in est.iter().zip(gt) {
        let (de, dg) = (e - mean_est, g - mean_gt);
        var_est += de.norm_squared();
        cov += dg * de.transpose();
    }
    var_est *= inv_n;
    cov *= inv_n;
    let svd = SVD::try_new(cov, true, true, f64::EPSILON, 0).ok_or(AlignError::Degenerate {
        alignment,
        reason: "the singular value decomposition did not converge",
    })?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(AlignError::Degenerate {
            alignment,
            reason: "the singular value decomposition did not return its vectors",
        });
    };
    let d = svd.singular_values; // descending
    // Finite inputs (the readers and Trajectory::new reject others): no NaN here.
    if d[1] <= RANK_TOLERANCE * d[0] {
        return Err(AlignError::Degenerate {
            alignment,
            reason: "the matched positions are collinear or coincide",
        });
    }
    // S (eq. 43): flip the smallest singular direction if U·Vᵀ would be a reflection.
    let mut s = Vector3::new(1.0, 1.0, 1.0);
    if u.determinant() * v_t.determinant() < 0.0 {
        s[2] = -1.0;
    }
    // Rotation (eq. 40), scale (eq. 42), translation (eq. 41).
    let rotation = Rotation3::from_matrix_unchecked(u * Matrix3::from_diagonal(&s) * v_t);
    let scale = if with_scale { d.dot(&s) / var_est } else { 1.0 };
    let translation = mean_gt - scale * (rotation * mean_est);
    Ok(GtFromEst {
        rotation,
        translation,
        scale,
    })
}

/// The least-squares rotation about the vertical and translation from the estimate's positions
/// to the ground truth's (rpg_trajectory_evaluation's `posyaw` over all poses).
///
/// With F the fixed turn that brings the estimate's up to the ground truth's (identity when
/// both z axes point the same way) and e_i = F·p_est,i, minimising Σ|g_i − R_z(θ)·e_i − t|²
/// gives t = ḡ − R_z(θ)·ē, then maximises Σ g̃_iᵀ R_z(θ) ẽ_i = B cos θ + A sin θ + const over
/// the centred points, A = Σ(ẽ_x g̃_y − ẽ_y g̃_x), B = Σ(ẽ_x g̃_x + ẽ_y g̃_y): θ = atan2(A, B).
/// The rotation about the ground truth's z axis is θ; about its up axis, θ with z up and −θ
/// with z down (returned second, in radians).
pub fn position_yaw(
    est: &[Vector3<f64>],
    gt: &[Vector3<f64>],
    est_z: ZAxis,
    gt_z: ZAxis,
) -> Result<(GtFromEst, f64), AlignError> {
    let alignment = Alignment::PosYaw;
    let (_, mean_est, mean_gt) = means(alignment, est, gt)?;
    let flip = if est_z == gt_z {
        Rotation3::identity()
    } else {
        Rotation3::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
    };
    let (mut a, mut b, mut scale_ab) = (0.0, 0.0, 0.0);
    for (p, g) in est.iter().zip(gt) {
        let e = flip * (p - mean_est);
        let g = g - mean_gt;
        a += e.x * g.y - e.y * g.x;
        b += e.x * g.x + e.y * g.y;
        scale_ab += e.xy().norm() * g.xy().norm();
    }
    // |(A, B)| is at most Σ|ẽ_xy||g̃_xy|; far below it the yaw is round-off (all poses on one
    // vertical line, or no horizontal motion).
    if a.hypot(b) <= RANK_TOLERANCE * scale_ab || scale_ab == 0.0 {
        return Err(AlignError::Degenerate {
            alignment,
            reason: "the matched positions have no horizontal extent",
        });
    }
    let theta = a.atan2(b);
    let rotation = Rotation3::from_axis_angle(&Vector3::z_axis(), theta) * flip;
    let translation = mean_gt - rotation * mean_est;
    let yaw_about_up = match gt_z {
        ZAxis::Up => theta,
        ZAxis::Down => -theta,
    };
    Ok((
        GtFromEst {
            rotation,
            translation,
            scale: 1.0,
        },
        yaw_about_up,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn cloud(n: usize, seed: u64) -> Vec<Vector3<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                Vector3::new(
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-2.0..2.0),
                )
            })
            .collect()
    }

    /// Umeyama on exact copies recovers a known transform: rigid (scale fixed at 1) and
    /// similarity (scale 0.37), both with a rotation that has roll, pitch and yaw.
    #[test]
    fn umeyama_recovers_a_known_transform() {
        let est = cloud(50, 1);
        let rotation = Rotation3::from_euler_angles(0.4, -0.7, 2.5);
        let translation = Vector3::new(10.0, -4.0, 3.0);
        for (with_scale, scale) in [(false, 1.0), (true, 0.37)] {
            let gt: Vec<_> = est
                .iter()
                .map(|p| scale * (rotation * p) + translation)
                .collect();
            let got = umeyama(&est, &gt, with_scale).unwrap();
            // Exact data: only round-off separates the recovered transform from the true one.
            assert!((got.rotation.matrix() - rotation.matrix()).norm() < 1e-12);
            assert!((got.translation - translation).norm() < 1e-12);
            assert!((got.scale - scale).abs() < 1e-12);
        }
    }

    /// A mirror image is not a rotation: S (eq. 43) makes the result a proper rotation anyway.
    #[test]
    fn umeyama_never_returns_a_reflection() {
        let est = cloud(40, 2);
        let gt: Vec<_> = est.iter().map(|p| Vector3::new(p.x, p.y, -p.z)).collect();
        let got = umeyama(&est, &gt, false).unwrap();
        assert!((got.rotation.matrix().determinant() - 1.0).abs() < 1e-12); // round-off only
    }

    #[test]
    fn degenerate_inputs_are_rejected() {
        let line: Vec<_> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(matches!(
            umeyama(&line, &line, false),
            Err(AlignError::Degenerate { .. })
        ));
        let vertical: Vec<_> = (0..10).map(|i| Vector3::new(1.0, 2.0, i as f64)).collect();
        assert!(matches!(
            position_yaw(&vertical, &vertical, ZAxis::Up, ZAxis::Up),
            Err(AlignError::Degenerate { .. })
        ));
        assert!(matches!(
            umeyama(&line[..2], &line[..2], true),
            Err(AlignError::TooFewPoses {
                needed: 3,
                got: 2,
                ..
            })
        ));
    }

    /// Position+yaw alignment of a yaw-rotated, translated copy leaves zero error, and the yaw
    /// it reports is the one applied; the same copy in a z-down frame (x, −y, −z) aligns as
    /// well once its z axis is declared down, and does not when it is declared up.
    #[test]
    fn position_yaw_of_a_yaw_rotated_translated_copy_is_exact() {
        let est = cloud(60, 3);
        let yaw = 1.234_f64;
        let gt_from_est = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw);
        let translation = Vector3::new(-3.0, 7.0, 0.5);
        let gt: Vec<_> = est.iter().map(|p| gt_from_est * p + translation).collect();
        let (t, got_yaw) = position_yaw(&est, &gt, ZAxis::Up, ZAxis::Up).unwrap();
        let worst = |t: &GtFromEst, est: &[Vector3<f64>]| {
            est.iter()
                .zip(&gt)
                .map(|(p, g)| (t.rotation * p + t.translation - g).norm())
                .fold(0.0, f64::max)
        };
        assert!(worst(&t, &est) < 1e-12, "{}", worst(&t, &est)); // round-off only
        assert!((got_yaw - yaw).abs() < 1e-12);
        // The estimate in a z-down frame.
        let est_down: Vec<_> = est.iter().map(|p| Vector3::new(p.x, -p.y, -p.z)).collect();
        let (t, got_yaw) = position_yaw(&est_down, &gt, ZAxis::Down, ZAxis::Up).unwrap();
        assert!(worst(&t, &est_down) < 1e-12); // round-off only
        assert!((got_yaw - yaw).abs() < 1e-12);
        let (t, _) = position_yaw(&est_down, &gt, ZAxis::Up, ZAxis::Up).unwrap();
        assert!(worst(&t, &est_down) > 1.0, "a wrong up axis must show");
        // Ground truth declared z down: the same fit, the yaw about the up axis changes sign.
        let (t, got_yaw) = position_yaw(&est, &gt, ZAxis::Down, ZAxis::Down).unwrap();
        assert!(worst(&t, &est) < 1e-12); // round-off only
        assert!((got_yaw + yaw).abs() < 1e-12);
    }
}
