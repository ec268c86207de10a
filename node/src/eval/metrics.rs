//! Timestamp association, error statistics, absolute and relative errors — evo's and
//! rpg_trajectory_evaluation's definitions, each cited where it is implemented.

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

/// evo's `matching_time_indices` (evo.core.sync, sorted-stamps branch): for every stamp of
/// `short`, the nearest stamp of `long + offset` if it lies within `max_diff` (ties: the earlier
/// one). Returns (index in `short`, index in `long`) in `short`'s order; a stamp of `long` may
/// serve twice.
fn matching_time_indices(
    short: &[f64],
    long: &[f64],
    max_diff: f64,
    offset: f64,
) -> Vec<(usize, usize)> {
    let long: Vec<f64> = long.iter().map(|t| t + offset).collect();
    let (Some(&first), Some(&last)) = (long.first(), long.last()) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for (i, &s) in short.iter().enumerate() {
        if s < first - max_diff || s > last + max_diff {
            continue;
        }
        // numpy.searchsorted(side="right"), clamped to the last index.
        let upper = long.partition_point(|&t| t <= s).min(long.len() - 1);
        let diff_upper = long[upper] - s;
        let diff_lower = if upper > 0 {
            s - long[upper - 1]
        } else {
            f64::INFINITY
        };
        if diff_upper <= max_diff && diff_upper < diff_lower {
            out.push((i, upper));
        } else if diff_lower <= max_diff && diff_lower <= diff_upper {
            out.push((i, upper - 1));
        }
    }
    out
}

/// evo's `associate_trajectories(gt, est, max_diff, offset_2=offset)` (nearest-time sync, as
/// `evo_ape tum GT EST --t_max_diff max_diff --t_offset offset`): it starts from the trajectory
/// with fewer poses (the estimate on a tie) so none of its poses is lost, and shifts the
/// estimate's stamps by `offset`. Returns (ground-truth index, estimate index) pairs.
pub fn associate(gt: &[f64], est: &[f64], max_diff: f64, offset: f64) -> Vec<(usize, usize)> {
    if est.len() > gt.len() {
        matching_time_indices(gt, est, max_diff, offset)
    } else {
        matching_time_indices(est, gt, max_diff, -offset)
            .into_iter()
            .map(|(e, g)| (g, e))
            .collect()
    }
}

/// Summary statistics of an error series (evo's `get_all_statistics`, rpg's
/// `compute_statistics`: population standard deviation, median of the two middle values for an
/// even count).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Number of errors.
    pub n: usize,
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// Standard deviation (population, ddof = 0).
    pub std: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
    /// Sum of squares.
    pub sse: f64,
}

impl Stats {
    /// The statistics of `errors`; `None` when there are none.
    pub fn of(errors: &[f64]) -> Option<Self> {
        let n = errors.len();
        if n == 0 {
            return None;
        }
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let nf = n as f64;
        let mean = errors.iter().sum::<f64>() / nf;
        let sse = errors.iter().map(|e| e * e).sum::<f64>();
        let var = errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / nf;
        let median = if n % 2 == 1 {
            sorted[n / 2]
        } else {
            0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
        };
        Some(Self {
            n,
            rmse: (sse / nf).sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: sorted[0],
            max: sorted[n - 1],
            sse,
        })
    }
}

/// The angle of a rotation [deg], 2·atan2(|v|, |w|) of its unit quaternion: the norm of the
/// SO(3) logarithm (evo's `so3_log_angle`), accurate near 0 where acos((tr R − 1)/2) is not.
pub fn rotation_angle_deg(q: &UnitQuaternion<f64>) -> f64 {
    (2.0 * q.imag().norm().atan2(q.w.abs())).to_degrees()
}

/// Absolute errors of matched, aligned poses (evo's APE: E_i = G_i⁻¹·P_i): translation
/// |p_est − p_gt| [m] (`--pose_relation trans_part`) and rotation angle of E_i [deg]
/// (`--pose_relation angle_deg`).
pub fn absolute_errors(gt: &[Isometry3<f64>], est: &[Isometry3<f64>]) -> (Vec<f64>, Vec<f64>) {
    gt.iter()
        .zip(est)
        .map(|(g, p)| {
            let e = g.inverse() * p;
            (e.translation.vector.norm(), rotation_angle_deg(&e.rotation))
        })
        .unzip()
}

/// evo's `filter_pairs_by_path` with `all_pairs` off: walking the positions, a new pair ends
/// wherever the path travelled since the last pair's end reaches `delta` [m]; consecutive
/// pairs (0, i₁), (i₁, i₂), …
pub fn pairs_by_path(positions: &[Vector3<f64>], delta: f64) -> Vec<(usize, usize)> {
    let mut ids = vec![0];
    let mut path = 0.0;
    for i in 1..positions.len() {
        path += (positions[i] - positions[i - 1]).norm();
        if path >= delta {
            ids.push(i);
            path = 0.0;
        }
    }
    ids.windows(2).map(|w| (w[0], w[1])).collect()
}

/// evo's relative pose error of a pair: E = (G_i⁻¹G_j)⁻¹·(P_i⁻¹P_j); translation |t_E| [m] and
/// rotation angle of E [deg].
pub fn relative_pose_errors(
    gt: &[Isometry3<f64>],
    est: &[Isometry3<f64>],
    pairs: &[(usize, usize)],
) -> (Vec<f64>, Vec<f64>) {
    pairs
        .iter()
        .map(|&(i, j)| {
            let gt_rel = gt[i].inverse() * gt[j];
            let est_rel = est[i].inverse() * est[j];
            let e = gt_rel.inverse() * est_rel;
            (e.translation.vector.norm(), rotation_angle_deg(&e.rotation))
        })
        .unzip()
}

/// Distance travelled from the first position to each one [m] (rpg's
/// `get_distance_from_start`).
pub fn distances_from_start(positions: &[Vector3<f64>]) -> Vec<f64> {
    let mut d = Vec::with_capacity(positions.len());
    let mut sum = 0.0;
    for (i, p) in positions.iter().enumerate() {
        if i > 0 {
            sum += (p - positions[i - 1]).norm();
        }
        d.push(sum);
    }
    d
}

/// rpg_trajectory_evaluation's sub-trajectory pairs (`compute_comparison_indices_length`): for
/// every start i, the end j ≥ i whose distance from the start is nearest to D_i + `dist`,
/// strictly within 0.2·`dist` (rpg's default `max_dist_diff`; ties: the earlier j).
///
/// rpg lists only the ends it found and pairs the k-th of them with start k; the two agree
/// whenever the starts that have an end come first, which holds when consecutive ground-truth
/// poses are less than 0.4·`dist` apart. Here every end stays with its own start.
pub fn pairs_by_distance(distances: &[f64], dist: f64) -> Vec<(usize, usize)> {
    let tol = 0.2 * dist;
    let mut out = Vec::new();
    for (i, &d) in distances.iter().enumerate() {
        let target = d + dist;
        let tail = &distances[i..];
        // Distances are non-decreasing: the nearest is the first at or above the target, or
        // the first of the run of equal values just below it.
        let above = tail.partition_point(|&x| x < target);
        let mut best: Option<(usize, f64)> = None;
        if above > 0 {
            let below_value = tail[above - 1];
            let first_equal = tail.partition_point(|&x| x < below_value);
            let err = (below_value - target).abs();
            if err < tol {
                best = Some((first_equal, err));
            }
        }
        if above < tail.len() {
            let err = (tail[above] - target).abs();
            if err < best.map_or(tol, |(_, e)| e) {
                best = Some((above, err));
            }
        }
        if let Some((k, _)) = best {
            out.push((i, i + k));
        }
    }
    out
}

/// rpg's relative errors at one sub-trajectory length, per pair.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RelativeErrors {
    /// |t| of the error [m].
    pub translation_m: Vec<f64>,
    /// |t| as a percentage of the length.
    pub translation_pct: Vec<f64>,
    /// Rotation angle of the error [deg].
    pub rotation_deg: Vec<f64>,
    /// |yaw| of the error re-expressed in the estimate's world frame [deg].
    pub yaw_deg: Vec<f64>,
}

/// rpg_trajectory_evaluation's `compute_relative_error` (T_cm = I): for a pair (i, j) with the
/// estimate's relative translation times `scale` (the Sim(3) scale, else 1),
/// E = (G_i⁻¹G_j)⁻¹·(P_i⁻¹P_j); translation |t_E| [m] and its percentage of `dist`, rotation
/// angle, and |yaw| (first angle of the z-y-x Euler decomposition, rpg's `rzyx`) of
/// R_j·R_E·R_jᵀ with R_j the estimate's (unaligned) attitude at j.
pub fn relative_errors(
    gt: &[Isometry3<f64>],
    est: &[Isometry3<f64>],
    pairs: &[(usize, usize)],
    dist: f64,
    scale: f64,
) -> RelativeErrors {
    let mut out = RelativeErrors::default();
    for &(i, j) in pairs {
        let gt_rel = gt[i].inverse() * gt[j];
        let mut est_rel = est[i].inverse() * est[j];
        est_rel.translation.vector *= scale;
        let e = gt_rel.inverse() * est_rel;
        let t = e.translation.vector.norm();
        out.translation_m.push(t);
        out.translation_pct.push(t / dist * 100.0);
        out.rotation_deg.push(rotation_angle_deg(&e.rotation));
        let r_j = est[j].rotation;
        let in_world = (r_j * e.rotation * r_j.inverse()).to_rotation_matrix();
        out.yaw_deg
            .push(yaw_rzyx(in_world.matrix()).abs().to_degrees());
    }
    out
}

/// The first angle of transformations.py's `euler_from_matrix(M, 'rzyx')`: atan2(M₁₀, M₀₀),
/// and 0 at gimbal lock (cos pitch ≤ 4ε), as that function does.
fn yaw_rzyx(m: &nalgebra::Matrix3<f64>) -> f64 {
    let cos_pitch = m[(0, 0)].hypot(m[(1, 0)]);
    if cos_pitch > 4.0 * f64::EPSILON {
        m[(1, 0)].atan2(m[(0, 0)])
    } else {
        0.0
    }
}

/// rpg's default sub-trajectory lengths: `fractions` of the path length, truncated to
/// centimetres (`Trajectory.truncate(pct * traj_length, 2)`); lengths that truncate to zero are
/// dropped.
pub fn default_distances(path_length: f64, fractions: &[f64]) -> Vec<f64> {
    fractions
        .iter()
        .map(|f| (f * path_length * 100.0).trunc() / 100.0)
        .filter(|d| *d > 0.0)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The association against hand-worked cases: the nearest within max_diff, ties to the
    /// earlier stamp, the offset applied to the estimate, and the shorter trajectory leading.
    #[test]
    fn association_follows_evo() {
        let gt = [0.0, 0.1, 0.2, 0.3, 0.4];
        // Estimate shorter: each estimate stamp looks for its gt neighbour.
        let est = [0.004, 0.15, 0.205, 0.5];
        // 0.004 → 0.0; 0.15 is 0.05 from both (ties: earlier, but beyond 0.01 → none);
        // 0.205 → 0.2; 0.5 is beyond 0.4 + 0.01.
        assert_eq!(associate(&gt, &est, 0.01, 0.0), vec![(0, 0), (2, 2)]);
        // Ties go to the earlier stamp: 0.15 with max_diff 0.05.
        assert_eq!(
            associate(&gt, &est, 0.05, 0.0),
            vec![(0, 0), (1, 1), (2, 2)]
        );
        // Offset: estimate stamps 10 s early, shifted by +10.
        let shifted: Vec<f64> = est.iter().map(|t| t - 10.0).collect();
        assert_eq!(associate(&gt, &shifted, 0.01, 10.0), vec![(0, 0), (2, 2)]);
        // Estimate longer than the ground truth: gt stamps lead, both keep their own order.
        let dense: Vec<f64> = (0..50).map(|k| k as f64 * 0.01 + 0.003).collect();
        let pairs = associate(&[0.1, 0.2], &dense, 0.01, 0.0);
        assert_eq!(pairs, vec![(0, 10), (1, 20)]);
    }

    #[test]
    fn stats_match_hand_computed_values() {
        let s = Stats::of(&[3.0, 1.0, 4.0, 2.0]).unwrap();
        assert_eq!(s.n, 4);
        assert_eq!(s.median, 2.5);
        assert_eq!(s.mean, 2.5);
        assert_eq!(s.sse, 30.0);
        assert_eq!(s.rmse, 7.5_f64.sqrt());
        assert_eq!(s.std, 1.25_f64.sqrt());
        assert_eq!((s.min, s.max), (1.0, 4.0));
        assert_eq!(Stats::of(&[5.0, 1.0, 3.0]).unwrap().median, 3.0);
        assert!(Stats::of(&[]).is_none());
    }

    #[test]
    fn path_pairs_restart_the_count_at_each_end() {
        // Steps of 0.4 m: 1 m is reached after 3 steps (1.2 m), counting from each end.
        let p: Vec<_> = (0..10)
            .map(|k| Vector3::new(0.4 * k as f64, 0.0, 0.0))
            .collect();
        assert_eq!(pairs_by_path(&p, 1.0), vec![(0, 3), (3, 6), (6, 9)]);
    }

    /// The binary search equals rpg's scan (strict improvement, upward) on distances with
    /// stationary runs and ties.
    #[test]
    fn distance_pairs_equal_the_linear_scan() {
        let d: [f64; 13] = [
            0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 1.5, 2.5, 2.5, 3.0, 3.9, 4.0, 4.0,
        ];
        for dist in [0.5, 1.0, 1.25, 2.0, 3.0] {
            let mut scan = Vec::new();
            for (i, di) in d.iter().enumerate() {
                let (mut best, mut err) = (None, 0.2 * dist);
                for (j, dj) in d.iter().enumerate().skip(i) {
                    let e = (dj - (di + dist)).abs();
                    if e < err {
                        best = Some(j);
                        err = e;
                    }
                }
                if let Some(j) = best {
                    scan.push((i, j));
                }
            }
            assert_eq!(pairs_by_distance(&d, dist), scan, "dist {dist}");
        }
    }

    #[test]
    fn default_distances_truncate_to_centimetres() {
        assert_eq!(
            default_distances(23.638, &[0.1, 0.2, 0.3, 0.4, 0.5]),
            vec![2.36, 4.72, 7.09, 9.45, 11.81]
        );
        assert_eq!(default_distances(0.05, &[0.1, 0.5]), vec![0.02]);
    }
}
