//! Trajectory evaluation against ground truth: `canopy eval EST GT` and [`evaluate`].
//!
//! The definitions are evo's (github.com/MichaelGrupp/evo) and rpg_trajectory_evaluation's
//! (github.com/uzh-rpg/rpg_trajectory_evaluation), so figures can be checked with either tool;
//! `node/tests/eval.rs` compares them with evo's own output on fixtures.
//!
//! 1. **Association** ([`metrics::associate`]): evo's nearest-timestamp matching,
//!    `max_diff` 0.01 s by default, an optional offset added to the estimate's stamps.
//! 2. **ATE** per alignment ([`align`]): SE(3) Umeyama (`evo_ape --align`), position+yaw
//!    (rpg's `posyaw`), Sim(3) (`evo_ape --align --correct_scale`), none; statistics of the
//!    translation error [m] (`--pose_relation trans_part`) and of the rotation angle [deg]
//!    (`--pose_relation angle_deg`).
//! 3. **RPE** ([`metrics::relative_pose_errors`]): `evo_rpe --delta D --delta_unit m`, pairs
//!    chosen by path length along the estimate (evo's default; `--pairs_from_reference`: along
//!    the ground truth), translation and rotation angle. With Sim(3) among the alignments the
//!    estimate is scaled first, as `evo_rpe --align --correct_scale` does (a rigid alignment
//!    changes no relative pose).
//! 4. **Relative error** ([`metrics::relative_errors`]): rpg_trajectory_evaluation's, over
//!    sub-trajectories of the given lengths measured along the ground truth (default 10, 20,
//!    30, 40, 50 % of the matched ground truth's path length, truncated to centimetres):
//!    translation [m] and [%], rotation and yaw [deg].
//!
//! Timestamps are used in the files' own time base (a recording's UNIX seconds stay so).

pub mod align;
pub mod metrics;
pub mod read;

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

pub use align::{AlignError, Alignment, GtFromEst, ZAxis};
pub use metrics::Stats;
pub use read::{LineProblem, ReadError, TrajectoryFormat};

use crate::record::VehicleRecord;

/// One pose of a trajectory.
#[derive(Clone, Debug, PartialEq)]
pub struct StampedPose {
    /// Timestamp [s], in the trajectory's own time base.
    pub t: f64,
    /// The body's pose in the trajectory's world frame (position [m], attitude).
    pub world_from_body: Isometry3<f64>,
}

/// A trajectory: at least one pose, finite, timestamps strictly increasing.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    poses: Vec<StampedPose>,
}

/// A trajectory given through the API that breaks [`Trajectory`]'s invariants.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TrajectoryError {
    /// No pose.
    #[error("the trajectory has no poses")]
    Empty,
    /// A bad pose.
    #[error("pose {index}: {problem}")]
    Pose {
        /// 0-based index.
        index: usize,
        /// What is wrong.
        problem: LineProblem,
    },
}

/// Which side of a vehicle's record a trajectory is built from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RecordSide {
    /// The vehicle's estimate.
    Estimate,
    /// The simulator's truth.
    Truth,
}

impl Trajectory {
    /// A trajectory from poses; rejects none, non-finite values and stamps that do not increase.
    pub fn new(poses: Vec<StampedPose>) -> Result<Self, TrajectoryError> {
        if poses.is_empty() {
            return Err(TrajectoryError::Empty);
        }
        for (index, p) in poses.iter().enumerate() {
            let err = |problem| TrajectoryError::Pose { index, problem };
            let fields = [
                ("timestamp", p.t),
                ("x", p.world_from_body.translation.x),
                ("y", p.world_from_body.translation.y),
                ("z", p.world_from_body.translation.z),
                ("qw", p.world_from_body.rotation.w),
                ("qx", p.world_from_body.rotation.i),
                ("qy", p.world_from_body.rotation.j),
                ("qz", p.world_from_body.rotation.k),
            ];
            for (field, value) in fields {
                if !value.is_finite() {
                    return Err(err(LineProblem::NotFinite { field, value }));
                }
            }
            if index > 0 && p.t <= poses[index - 1].t {
                return Err(err(LineProblem::NotIncreasing {
                    t: p.t,
                    previous: poses[index - 1].t,
                }));
            }
        }
        Ok(Self { poses })
    }

    /// Poses the reader has already checked.
    fn from_checked(poses: Vec<StampedPose>) -> Self {
        debug_assert!(!poses.is_empty());
        Self { poses }
    }

    /// Reads a TUM or EuRoC CSV file ([`read`]).
    pub fn load(path: &Path) -> Result<Self, ReadError> {
        read::load(path)
    }

    /// A run's vehicle record as a trajectory (launch-site NED frame: z down; simulation time),
    /// e.g. to evaluate a vehicle against a ground-truth file.
    pub fn from_record(v: &VehicleRecord, side: RecordSide) -> Result<Self, TrajectoryError> {
        let mut poses = Vec::with_capacity(v.samples.len());
        for s in &v.samples {
            let (p, att) = match side {
                RecordSide::Estimate => (s.est_pos, s.est_att),
                RecordSide::Truth => (s.truth_pos, s.truth_att),
            };
            let [qx, qy, qz, qw] = crate::output::files::quaternion_from_euler(&att);
            let rotation = UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(qw, qx, qy, qz));
            poses.push(StampedPose {
                t: s.t,
                world_from_body: Isometry3::from_parts(
                    Translation3::new(p[0], p[1], p[2]),
                    rotation,
                ),
            });
        }
        Self::new(poses)
    }

    /// The poses, in time order.
    pub fn poses(&self) -> &[StampedPose] {
        &self.poses
    }

    /// Number of poses (at least 1).
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// Always false (a trajectory has at least one pose); for clippy's `len_without_is_empty`.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// First and last timestamp [s].
    pub fn span(&self) -> [f64; 2] {
        [self.poses[0].t, self.poses[self.poses.len() - 1].t]
    }

    fn stamps(&self) -> Vec<f64> {
        self.poses.iter().map(|p| p.t).collect()
    }
}

/// rpg_trajectory_evaluation's default sub-trajectory lengths, as fractions of the path.
pub const DEFAULT_DISTANCE_FRACTIONS: [f64; 5] = [0.1, 0.2, 0.3, 0.4, 0.5];

/// What [`evaluate`] computes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalOptions {
    /// Largest timestamp difference of a matched pair [s] (evo's `--t_max_diff`, 0.01).
    pub max_diff_s: f64,
    /// Added to the estimate's timestamps before matching [s] (evo's `--t_offset`).
    pub offset_s: f64,
    /// Alignments for the ATE, in report order.
    pub alignments: Vec<Alignment>,
    /// Where the estimate's z axis points (position+yaw alignment).
    pub est_z: ZAxis,
    /// Where the ground truth's z axis points (position+yaw alignment).
    pub gt_z: ZAxis,
    /// RPE and relative-error distances [m]; empty: [`DEFAULT_DISTANCE_FRACTIONS`] of the
    /// matched ground truth's path length, truncated to centimetres (rpg's rule).
    pub distances_m: Vec<f64>,
    /// RPE pairs by the ground truth's path instead of the estimate's
    /// (`evo_rpe --pairs_from_reference`).
    pub pairs_from_reference: bool,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            max_diff_s: 0.01,
            offset_s: 0.0,
            alignments: vec![Alignment::Se3, Alignment::PosYaw],
            est_z: ZAxis::Up,
            gt_z: ZAxis::Up,
            distances_m: Vec::new(),
            pairs_from_reference: false,
        }
    }
}

/// How the two trajectories were matched.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Association {
    /// Poses in the estimate.
    pub est_poses: usize,
    /// Poses in the ground truth.
    pub gt_poses: usize,
    /// Matched pairs.
    pub matched: usize,
    /// Largest |t_gt − (t_est + offset)| among them [s].
    pub max_abs_dt_s: f64,
    /// The estimate's first and last stamp [s] (its own time base).
    pub est_span_s: [f64; 2],
    /// The ground truth's first and last stamp [s].
    pub gt_span_s: [f64; 2],
}

/// The absolute trajectory error after one alignment.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ate {
    /// The alignment.
    pub alignment: Alignment,
    /// Its rotation, ground-truth frame from estimate frame, row-major.
    pub rotation_gt_from_est: [[f64; 3]; 3],
    /// Its translation [m].
    pub translation_m: [f64; 3],
    /// Its scale (1 unless Sim(3)).
    pub scale: f64,
    /// Position+yaw only: the rotation about the ground truth's up axis [deg],
    /// counter-clockwise seen from above.
    pub yaw_deg: Option<f64>,
    /// Translation error [m].
    pub translation_error_m: Stats,
    /// Rotation error angle [deg].
    pub rotation_error_deg: Stats,
}

/// evo's relative pose error at one distance.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Rpe {
    /// Path distance between the poses of a pair [m].
    pub delta_m: f64,
    /// Pairs found.
    pub pairs: usize,
    /// Translation error [m] (none without pairs).
    pub translation_m: Option<Stats>,
    /// Rotation error angle [deg].
    pub rotation_deg: Option<Stats>,
}

/// rpg's relative error at one sub-trajectory length (no statistics below two samples, as rpg).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RelativeError {
    /// Sub-trajectory length along the ground truth [m].
    pub distance_m: f64,
    /// Sub-trajectories found.
    pub samples: usize,
    /// Translation error [m].
    pub translation_m: Option<Stats>,
    /// Translation error as a percentage of the length.
    pub translation_pct: Option<Stats>,
    /// Rotation error angle [deg].
    pub rotation_deg: Option<Stats>,
    /// |yaw| of the rotation error [deg].
    pub yaw_deg: Option<Stats>,
}

/// Everything [`evaluate`] computed (serialisable; `canopy eval --json` writes it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// The options used.
    pub options: EvalOptions,
    /// The timestamp association.
    pub association: Association,
    /// Path length of the matched ground truth [m].
    pub gt_path_length_m: f64,
    /// Path length of the matched estimate, as given (unscaled) [m].
    pub est_path_length_m: f64,
    /// ATE, one per requested alignment.
    pub ate: Vec<Ate>,
    /// Scale applied to the estimate for the RPE and relative errors (the Sim(3) scale when
    /// Sim(3) is requested, else 1).
    pub rpe_scale: f64,
    /// The distances used [m].
    pub distances_m: Vec<f64>,
    /// evo's RPE per distance.
    pub rpe: Vec<Rpe>,
    /// rpg's relative error per distance.
    pub relative: Vec<RelativeError>,
}

/// Why an evaluation could not be made.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum EvalError {
    /// An option out of range.
    #[error("invalid option: {0}")]
    InvalidOption(String),
    /// No pose pair matched.
    #[error("{0}")]
    NoMatches(NoMatches),
    /// An alignment cannot be computed.
    #[error(transparent)]
    Align(#[from] AlignError),
}

/// The two time ranges when no pair matched.
#[derive(Clone, Debug, PartialEq)]
pub struct NoMatches {
    /// The estimate's first and last stamp [s].
    pub est_span_s: [f64; 2],
    /// Its poses.
    pub est_poses: usize,
    /// The ground truth's first and last stamp [s].
    pub gt_span_s: [f64; 2],
    /// Its poses.
    pub gt_poses: usize,
    /// The largest difference allowed [s].
    pub max_diff_s: f64,
    /// The offset added to the estimate's stamps [s].
    pub offset_s: f64,
}

impl std::fmt::Display for NoMatches {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [e0, e1] = self.est_span_s;
        let [g0, g1] = self.gt_span_s;
        write!(
            f,
            "no matching timestamps: no estimate pose is within {} s of a ground-truth pose \
             (estimate: {} poses, {e0} … {e1} s; ground truth: {} poses, {g0} … {g1} s; offset \
             added to the estimate {} s)",
            self.max_diff_s, self.est_poses, self.gt_poses, self.offset_s
        )?;
        let (s0, s1) = (e0 + self.offset_s, e1 + self.offset_s);
        if s1 < g0 || s0 > g1 {
            write!(
                f,
                "; the time ranges do not overlap (another time base? the starts differ by {} s)",
                g0 - s0
            )?;
        }
        Ok(())
    }
}

/// Evaluates `est` against `gt` (see the module documentation for the definitions).
pub fn evaluate(
    est: &Trajectory,
    gt: &Trajectory,
    opts: &EvalOptions,
) -> Result<EvalReport, EvalError> {
    validate(opts)?;
    let pairs = metrics::associate(&gt.stamps(), &est.stamps(), opts.max_diff_s, opts.offset_s);
    if pairs.is_empty() {
        return Err(EvalError::NoMatches(NoMatches {
            est_span_s: est.span(),
            est_poses: est.len(),
            gt_span_s: gt.span(),
            gt_poses: gt.len(),
            max_diff_s: opts.max_diff_s,
            offset_s: opts.offset_s,
        }));
    }
    let gt_m: Vec<Isometry3<f64>> = pairs
        .iter()
        .map(|&(g, _)| gt.poses[g].world_from_body)
        .collect();
    let est_m: Vec<Isometry3<f64>> = pairs
        .iter()
        .map(|&(_, e)| est.poses[e].world_from_body)
        .collect();
    let gt_pos: Vec<Vector3<f64>> = gt_m.iter().map(|p| p.translation.vector).collect();
    let est_pos: Vec<Vector3<f64>> = est_m.iter().map(|p| p.translation.vector).collect();
    let association = Association {
        est_poses: est.len(),
        gt_poses: gt.len(),
        matched: pairs.len(),
        max_abs_dt_s: pairs
            .iter()
            .map(|&(g, e)| (gt.poses[g].t - (est.poses[e].t + opts.offset_s)).abs())
            .fold(0.0, f64::max),
        est_span_s: est.span(),
        gt_span_s: gt.span(),
    };

    let mut alignments = opts.alignments.clone();
    dedup_in_order(&mut alignments);
    let mut ate = Vec::with_capacity(alignments.len());
    let mut rpe_scale = 1.0;
    let mut rpe_transform = GtFromEst::identity();
    for &alignment in &alignments {
        let (transform, yaw) = match alignment {
            Alignment::Se3 => (align::umeyama(&est_pos, &gt_pos, false)?, None),
            Alignment::Sim3 => (align::umeyama(&est_pos, &gt_pos, true)?, None),
            Alignment::PosYaw => {
                let (t, yaw) = align::position_yaw(&est_pos, &gt_pos, opts.est_z, opts.gt_z)?;
                (t, Some(yaw.to_degrees()))
            }
            Alignment::Unaligned => (GtFromEst::identity(), None),
        };
        let aligned: Vec<Isometry3<f64>> = est_m.iter().map(|p| transform.apply(p)).collect();
        let (trans, rot) = metrics::absolute_errors(&gt_m, &aligned);
        if alignment == Alignment::Sim3 {
            rpe_scale = transform.scale;
            rpe_transform = transform.clone();
        }
        let m = transform.rotation.matrix();
        ate.push(Ate {
            alignment,
            rotation_gt_from_est: std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)])),
            translation_m: transform.translation.into(),
            scale: transform.scale,
            yaw_deg: yaw,
            translation_error_m: Stats::of(&trans).expect("at least one matched pair"),
            rotation_error_deg: Stats::of(&rot).expect("at least one matched pair"),
        });
    }

    let gt_distances = metrics::distances_from_start(&gt_pos);
    let gt_path_length_m = *gt_distances.last().expect("at least one matched pair");
    let est_path_length_m = *metrics::distances_from_start(&est_pos)
        .last()
        .expect("at least one matched pair");
    let distances_m = if opts.distances_m.is_empty() {
        metrics::default_distances(gt_path_length_m, &DEFAULT_DISTANCE_FRACTIONS)
    } else {
        opts.distances_m.clone()
    };

    // evo's RPE on the estimate as evo_rpe sees it: scaled (Sim(3)) or as given.
    let est_rpe: Vec<Isometry3<f64>> = est_m.iter().map(|p| rpe_transform.apply(p)).collect();
    let rpe_path: Vec<Vector3<f64>> = if opts.pairs_from_reference {
        gt_pos.clone()
    } else {
        est_rpe.iter().map(|p| p.translation.vector).collect()
    };
    let rpe = distances_m
        .iter()
        .map(|&delta_m| {
            let pairs = metrics::pairs_by_path(&rpe_path, delta_m);
            let (trans, rot) = metrics::relative_pose_errors(&gt_m, &est_rpe, &pairs);
            Rpe {
                delta_m,
                pairs: pairs.len(),
                translation_m: Stats::of(&trans),
                rotation_deg: Stats::of(&rot),
            }
        })
        .collect();
    let relative = distances_m
        .iter()
        .map(|&distance_m| {
            let pairs = metrics::pairs_by_distance(&gt_distances, distance_m);
            // rpg computes nothing from fewer than two sub-trajectories.
            let e = if pairs.len() >= 2 {
                metrics::relative_errors(&gt_m, &est_m, &pairs, distance_m, rpe_scale)
            } else {
                metrics::RelativeErrors::default()
            };
            RelativeError {
                distance_m,
                samples: pairs.len(),
                translation_m: Stats::of(&e.translation_m),
                translation_pct: Stats::of(&e.translation_pct),
                rotation_deg: Stats::of(&e.rotation_deg),
                yaw_deg: Stats::of(&e.yaw_deg),
            }
        })
        .collect();

    Ok(EvalReport {
        options: opts.clone(),
        association,
        gt_path_length_m,
        est_path_length_m,
        ate,
        rpe_scale,
        distances_m,
        rpe,
        relative,
    })
}

fn validate(opts: &EvalOptions) -> Result<(), EvalError> {
    let bad = |s: String| Err(EvalError::InvalidOption(s));
    if !(opts.max_diff_s >= 0.0 && opts.max_diff_s.is_finite()) {
        return bad(format!(
            "max_diff {} s: must be finite and ≥ 0",
            opts.max_diff_s
        ));
    }
    if !opts.offset_s.is_finite() {
        return bad(format!("offset {} s: must be finite", opts.offset_s));
    }
    if let Some(d) = opts
        .distances_m
        .iter()
        .find(|d| !(d.is_finite() && **d > 0.0))
    {
        return bad(format!("distance {d} m: must be finite and > 0"));
    }
    Ok(())
}

fn dedup_in_order(v: &mut Vec<Alignment>) {
    let mut seen = Vec::with_capacity(v.len());
    v.retain(|a| {
        let new = !seen.contains(a);
        seen.push(*a);
        new
    });
}

/// The report as a text table: how the trajectories matched, each alignment, then one row per
/// error series (n, rmse, mean, median, std, min, max; six decimals, as evo prints).
pub fn table(report: &EvalReport, est_name: &str, gt_name: &str) -> String {
    let mut out = String::new();
    let a = &report.association;
    let o = &report.options;
    let _ = writeln!(
        out,
        "estimate:     {est_name} ({} poses, {} … {} s)",
        a.est_poses, a.est_span_s[0], a.est_span_s[1]
    );
    let _ = writeln!(
        out,
        "ground truth: {gt_name} ({} poses, {} … {} s)",
        a.gt_poses, a.gt_span_s[0], a.gt_span_s[1]
    );
    let _ = writeln!(
        out,
        "matched {} pose pairs (largest |Δt| {:.6} s; max_diff {} s, offset {} s); matched \
         path {:.3} m (ground truth), {:.3} m (estimate)",
        a.matched,
        a.max_abs_dt_s,
        o.max_diff_s,
        o.offset_s,
        report.gt_path_length_m,
        report.est_path_length_m
    );
    for ate in &report.ate {
        let r = nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_fn(|i, j| {
            ate.rotation_gt_from_est[i][j]
        }));
        let t = ate.translation_m;
        let _ = write!(
            out,
            "alignment {:<6} rotation {:.4}°, translation ({:.4}, {:.4}, {:.4}) m, scale {:.6}",
            ate.alignment.to_string(),
            r.angle().to_degrees(),
            t[0],
            t[1],
            t[2],
            ate.scale
        );
        if let Some(yaw) = ate.yaw_deg {
            let _ = write!(
                out,
                ", yaw {yaw:.4}° about the ground truth's up (est z {}, gt z {})",
                o.est_z, o.gt_z
            );
        }
        out.push('\n');
    }
    let pairs_from = if o.pairs_from_reference {
        "ground truth"
    } else {
        "estimate"
    };
    let _ = writeln!(
        out,
        "RPE: evo_rpe, consecutive pairs by the {pairs_from}'s path, scale {:.6}; RE: \
         rpg_trajectory_evaluation's relative error over sub-trajectories of the ground truth",
        report.rpe_scale
    );
    out.push('\n');
    let _ = writeln!(
        out,
        "{:<30} {:>6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10}",
        "error", "n", "rmse", "mean", "median", "std", "min", "max"
    );
    let mut row = |label: String, stats: Option<&Stats>, n: usize, why: &str| match stats {
        Some(s) => {
            let _ = writeln!(
                out,
                "{label:<30} {:>6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>10.6}",
                s.n, s.rmse, s.mean, s.median, s.std, s.min, s.max
            );
        }
        None => {
            let _ = writeln!(out, "{label:<30} {n:>6} {why}");
        }
    };
    for ate in &report.ate {
        let name = ate.alignment.to_string();
        row(
            format!("ATE {name} translation [m]"),
            Some(&ate.translation_error_m),
            0,
            "",
        );
        row(
            format!("ATE {name} rotation [deg]"),
            Some(&ate.rotation_error_deg),
            0,
            "",
        );
    }
    for r in &report.rpe {
        let why = format!("no pair: the path is shorter than {} m", r.delta_m);
        let d = r.delta_m;
        row(
            format!("RPE {d} m translation [m]"),
            r.translation_m.as_ref(),
            r.pairs,
            &why,
        );
        row(
            format!("RPE {d} m rotation [deg]"),
            r.rotation_deg.as_ref(),
            r.pairs,
            &why,
        );
    }
    for r in &report.relative {
        let why = "fewer than 2 sub-trajectories of this length (rpg computes none)";
        let d = r.distance_m;
        row(
            format!("RE {d} m translation [m]"),
            r.translation_m.as_ref(),
            r.samples,
            why,
        );
        row(
            format!("RE {d} m translation [%]"),
            r.translation_pct.as_ref(),
            r.samples,
            why,
        );
        row(
            format!("RE {d} m rotation [deg]"),
            r.rotation_deg.as_ref(),
            r.samples,
            why,
        );
        row(
            format!("RE {d} m yaw [deg]"),
            r.yaw_deg.as_ref(),
            r.samples,
            why,
        );
    }
    out
}
