//! `summary.json`: the run's figures (field names documented in the README).

use crate::record::{LinkRecord, PoseSample, RunRecord, VehicleRecord};
use serde::{Deserialize, Serialize};
use statrs::distribution::{ChiSquared, ContinuousCDF};

/// Serde default of `metrics_available` (summaries written before the field existed).
fn yes() -> bool {
    true
}

/// JSON has no NaN: serde_json writes a NaN figure (a metric that is unavailable, e.g. the
/// position error of a replayed vehicle without truth) as `null`; this reads it back as NaN.
fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Option::<f64>::deserialize(d).map(|v| v.unwrap_or(f64::NAN))
}

/// Two-sided 95 % bounds of a χ² variable with `dof` degrees of freedom.
pub fn chi2_band(dof: f64) -> (f64, f64) {
    // dof > 0 by construction of the callers (3 or 6), so the distribution always exists.
    let d = ChiSquared::new(dof).expect("positive degrees of freedom");
    (d.inverse_cdf(0.025), d.inverse_cdf(0.975))
}

/// Figures of one vehicle (or of the baseline filter's estimate of that vehicle).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct VehicleSummary {
    /// Vehicle name.
    pub name: String,
    /// Whether the vehicle had truth (false for a vehicle replayed from logs: its position
    /// and NEES figures are then `null`).
    #[serde(default = "yes")]
    pub metrics_available: bool,
    /// RMS position error over the run [m].
    #[serde(deserialize_with = "null_as_nan")]
    pub position_rmse_m: f64,
    /// Position error at the end of the run [m].
    #[serde(deserialize_with = "null_as_nan")]
    pub final_position_error_m: f64,
    /// Time-averaged position NEES divided by its 3 dof (1.0 when consistent).
    #[serde(deserialize_with = "null_as_nan")]
    pub position_anees: f64,
    /// Time-averaged pose (position + attitude) NEES divided by its 6 dof.
    #[serde(deserialize_with = "null_as_nan")]
    pub pose_anees: f64,
    /// Fraction of samples whose pose NEES lies inside the per-sample χ²₆ 95 % interval.
    #[serde(deserialize_with = "null_as_nan")]
    pub pose_nees_in_band: f64,
    /// Fraction of samples whose pose NEES lies above that interval's upper bound (χ²₆ 97.5 %
    /// quantile): the over-confident samples (0.025 for an ideal filter). Samples below the
    /// band are conservative ones (e.g. after covariance intersection).
    #[serde(default, deserialize_with = "null_as_nan")]
    pub pose_nees_above_band: f64,
    /// Features in the vehicle's final map.
    pub map_features: usize,
    /// RMS error of the final map's features that have a truth [m].
    #[serde(deserialize_with = "null_as_nan")]
    pub map_rmse_m: f64,
    /// Mean per-feature map NEES divided by its 3 dof.
    #[serde(deserialize_with = "null_as_nan")]
    pub map_anees: f64,
    /// Association and final map against the truth (`crate::truth::TruthFigures`; its fields
    /// sit beside these in JSON).
    #[serde(flatten)]
    pub association: crate::truth::TruthFigures,
    /// Observations processed.
    pub observations: u64,
    /// Received fusion messages rejected.
    pub rejected_messages: u64,
    /// Process restarts.
    pub restarts: u32,
    /// Inputs the estimator rejected, by reason: `imu.<error>`, `frame.<error>` (a whole frame
    /// refused), `observation.<reason>` (one observation not used),
    /// `observation.in_rejected_frame` (observations of refused frames).
    #[serde(default)]
    pub rejections: std::collections::BTreeMap<String, u64>,
    /// Absolute trajectory error of the estimate against the truth (evo's definitions,
    /// [`crate::eval`]; `null` without truth or when no alignment can be made, e.g. too short
    /// a path).
    #[serde(default)]
    pub ate: Option<AteSummary>,
    /// Peak resident memory of the vehicle's process [MB] (`canopy run` on Linux; `null` in
    /// `canopy sim`).
    #[serde(default)]
    pub peak_rss_mb: Option<f64>,
    /// What the vehicle's zenoh access control refused, by `"<action> on <key>"` (e.g.
    /// `"Put (ingress) on canopy/run/link/3/2"`: a session without that link published on it);
    /// empty without `[secrets].zenoh_password` or when nothing was refused.
    #[serde(default)]
    pub access_refused: std::collections::BTreeMap<String, u64>,
    /// Local SLAM in own frames: how the vehicle's frame was aligned with the team frame
    /// (`crate::record::FrameAlignmentRecord`); `null` in a shared frame.
    #[serde(default)]
    pub frame_alignment: Option<crate::record::FrameAlignmentRecord>,
}

/// The ATE of one vehicle: RMS over the samples with truth, after each alignment.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct AteSummary {
    /// Translation RMSE after SE(3) alignment [m] (`evo_ape --align`).
    pub se3_m: f64,
    /// Rotation-angle RMSE after SE(3) alignment [deg].
    pub se3_deg: f64,
    /// Translation RMSE after position+yaw (4-DOF) alignment [m].
    pub posyaw_m: f64,
    /// Rotation-angle RMSE after position+yaw alignment [deg].
    pub posyaw_deg: f64,
}

/// The ATE of a vehicle's samples with truth (launch frame, z down), if an alignment can be
/// made; why not otherwise.
fn ate(name: &str, samples: &[&PoseSample]) -> Result<AteSummary, String> {
    use crate::eval::{Alignment, EvalOptions, RecordSide, Trajectory, ZAxis, evaluate};
    let with_truth = VehicleRecord {
        name: name.to_string(),
        samples: samples.iter().map(|&s| s.clone()).collect(),
        ..VehicleRecord::default()
    };
    let traj = |side| Trajectory::from_record(&with_truth, side).map_err(|e| e.to_string());
    let opts = EvalOptions {
        // The samples pair up exactly (one record, both sides).
        max_diff_s: 1e-6,
        alignments: vec![Alignment::Se3, Alignment::PosYaw],
        est_z: ZAxis::Down,
        gt_z: ZAxis::Down,
        ..EvalOptions::default()
    };
    let r = evaluate(
        &traj(RecordSide::Estimate)?,
        &traj(RecordSide::Truth)?,
        &opts,
    )
    .map_err(|e| e.to_string())?;
    let pick = |a: Alignment| {
        r.ate
            .iter()
            .find(|x| x.alignment == a)
            .map(|x| (x.translation_error_m.rmse, x.rotation_error_deg.rmse))
            .ok_or_else(|| format!("no {a:?} alignment in the evaluation"))
    };
    let (se3_m, se3_deg) = pick(Alignment::Se3)?;
    let (posyaw_m, posyaw_deg) = pick(Alignment::PosYaw)?;
    Ok(AteSummary {
        se3_m,
        se3_deg,
        posyaw_m,
        posyaw_deg,
    })
}

/// Totals of one link.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct LinkSummary {
    /// `a-b`.
    pub link: String,
    /// `shm`, `net` or `sim`.
    pub transport: String,
    /// Bytes a → b.
    pub bytes_ab: u64,
    /// Bytes b → a.
    pub bytes_ba: u64,
    /// Messages, both directions.
    pub messages: u64,
    /// Dropped messages.
    pub drops: u64,
    /// Rejected messages.
    pub rejections: u64,
    /// Whether the link fell back to covariance intersection.
    pub ci: bool,
    /// Bytes sent (both directions) / bytes of the naive dense f64 (Y, y) of the whole map per
    /// round per direction (0 when not measured).
    pub bandwidth_ratio: f64,
}

/// The whole summary.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Summary {
    /// Scenario name.
    pub scenario: String,
    /// Fusion mode.
    pub mode: String,
    /// Navigation frame.
    pub frame: String,
    /// World seed.
    pub seed: u64,
    /// Simulated time [s].
    #[serde(deserialize_with = "null_as_nan")]
    pub duration_s: f64,
    /// Wall-clock time [s].
    #[serde(deserialize_with = "null_as_nan")]
    pub wall_time_s: f64,
    /// Simulated seconds per wall-clock second.
    #[serde(deserialize_with = "null_as_nan")]
    pub real_time_factor: f64,
    /// Per-vehicle figures.
    pub vehicles: Vec<VehicleSummary>,
    /// Means over vehicles: position RMSE, map RMSE, pose ANEES, map ANEES.
    pub team: TeamSummary,
    /// Per-link totals.
    pub links: Vec<LinkSummary>,
    /// The centralized all-data EKF's figures, when it ran (under appearance it associates
    /// by the true ids: the perfect-association reference).
    pub baseline: Option<BaselineSummary>,
    /// `perfect` or `appearance` (`[world.appearance] identity`).
    #[serde(default)]
    pub identity: String,
    /// Association against the truth over the team.
    #[serde(default)]
    pub association: AssociationSummary,
    /// Number of fault and lifecycle events.
    pub events: usize,
    /// What the zenoh router's access control refused of its clients (multi-host runs in
    /// client mode), by `"<action> on <key>"`; absent when nothing was.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub router_access_refused: std::collections::BTreeMap<String, u64>,
}

/// Team means.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct TeamSummary {
    /// Mean of the vehicles' position RMSE [m].
    #[serde(deserialize_with = "null_as_nan")]
    pub position_rmse_m: f64,
    /// Mean of the vehicles' map RMSE [m].
    #[serde(deserialize_with = "null_as_nan")]
    pub map_rmse_m: f64,
    /// Mean pose ANEES.
    #[serde(deserialize_with = "null_as_nan")]
    pub pose_anees: f64,
    /// Mean map ANEES.
    #[serde(deserialize_with = "null_as_nan")]
    pub map_anees: f64,
}

/// Association against the truth over the team: sums of the vehicles' figures (map figures
/// summed over the vehicles' final maps), except `wrong_merges`.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct AssociationSummary {
    /// Observations processed.
    pub observations: u64,
    /// Wrong associations.
    pub wrong_associations: u64,
    /// Distinct wrong correspondences adopted anywhere in the team (each fact once).
    pub wrong_merges: u64,
    /// Wrong correspondences between keys of different vehicles, summed over the vehicles
    /// that adopted them.
    pub wrong_cross_vehicle_merges: u64,
    /// Correspondences adopted, summed over vehicles.
    pub merges_adopted: u64,
    /// Neighbours' correspondences refused, summed over vehicles.
    pub merges_refused: u64,
    /// Duplicate keys in the final maps.
    pub duplicate_features: u64,
    /// Mature features of the final maps.
    pub mature_features: u64,
    /// Duplicates among them.
    pub mature_duplicates: u64,
    /// `mature_duplicates / mature_features` (`null` without mature features).
    #[serde(deserialize_with = "null_as_nan")]
    pub mature_duplicate_share: f64,
    /// True features held under keys of two or more vehicles.
    pub unmatched_features: u64,
    /// Frames not judged against the truth.
    pub unaudited_frames: u64,
}

/// The team's association figures from its vehicles' and the run's distinct wrong merges.
pub fn summarize_association(vs: &[VehicleSummary], team_wrong_merges: u64) -> AssociationSummary {
    let t = |f: fn(&crate::truth::TruthFigures) -> u64| {
        vs.iter().map(|v| f(&v.association)).sum::<u64>()
    };
    let mature_features = t(|a| a.mature_features);
    let mature_duplicates = t(|a| a.mature_duplicates);
    AssociationSummary {
        observations: vs.iter().map(|v| v.observations).sum(),
        wrong_associations: t(|a| a.wrong_associations),
        wrong_merges: team_wrong_merges,
        wrong_cross_vehicle_merges: t(|a| a.wrong_cross_vehicle_merges),
        merges_adopted: t(|a| a.merges_adopted),
        merges_refused: t(|a| a.merges_refused),
        duplicate_features: t(|a| a.duplicate_features),
        mature_features,
        mature_duplicates,
        mature_duplicate_share: if mature_features > 0 {
            mature_duplicates as f64 / mature_features as f64
        } else {
            f64::NAN
        },
        unmatched_features: t(|a| a.unmatched_features),
        unaudited_frames: t(|a| a.unaudited_frames),
    }
}

/// The centralized baseline's figures.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct BaselineSummary {
    /// Per-vehicle figures of the joint filter (the map figures are those of the joint map).
    pub vehicles: Vec<VehicleSummary>,
    /// Team means.
    pub team: TeamSummary,
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { f64::NAN } else { s / n as f64 }
}

/// 1 or 0 for a per-sample test, NaN when the sample's NEES is unavailable (no truth), so the
/// fraction of a vehicle without truth is NaN (`null` in JSON) rather than 0.
fn flag(nees: f64, test: bool) -> f64 {
    if nees.is_nan() {
        f64::NAN
    } else {
        f64::from(u8::from(test))
    }
}

/// Figures of one vehicle record.
pub fn summarize_vehicle(v: &VehicleRecord) -> VehicleSummary {
    let (lo, hi) = chi2_band(6.0);
    // The samples with truth: all of a simulated vehicle's, those a replayed vehicle's ground
    // truth covers. (A NaN NEES of a sample with truth — a covariance that is not positive
    // definite — stays in and shows as NaN.)
    let truth_samples: Vec<&PoseSample> = v
        .samples
        .iter()
        .filter(|s| {
            s.truth_pos
                .iter()
                .chain(&s.truth_att)
                .all(|x| x.is_finite())
        })
        .collect();
    let samples = || truth_samples.iter().copied();
    let position_rmse_m = mean(samples().map(|s| s.position_error().powi(2))).sqrt();
    let final_position_error_m = samples().last().map_or(f64::NAN, |s| s.position_error());
    let position_anees = mean(samples().map(|s| s.nees_pos / 3.0));
    let pose_anees = mean(samples().map(|s| s.nees_pose / 6.0));
    let pose_nees_in_band =
        mean(samples().map(|s| flag(s.nees_pose, s.nees_pose >= lo && s.nees_pose <= hi)));
    let pose_nees_above_band = mean(samples().map(|s| flag(s.nees_pose, s.nees_pose > hi)));
    let with_truth: Vec<_> = v
        .map
        .iter()
        .filter_map(|f| f.truth.map(|t| (f, t)))
        .collect();
    let map_rmse_m = mean(
        with_truth
            .iter()
            .map(|(f, t)| (0..3).map(|i| (f.est[i] - t[i]).powi(2)).sum::<f64>()),
    )
    .sqrt();
    let map_anees = mean(
        with_truth
            .iter()
            .filter_map(|(f, t)| feature_nees(&f.est, &f.cov, t))
            .map(|n| n / 3.0),
    );
    let metrics_available = !truth_samples.is_empty();
    let ate = if metrics_available {
        ate(&v.name, &truth_samples)
            .inspect_err(|e| tracing::warn!(vehicle = %v.name, "no ATE: {e}"))
            .ok()
    } else {
        None
    };
    VehicleSummary {
        name: v.name.clone(),
        metrics_available,
        position_rmse_m,
        final_position_error_m,
        position_anees,
        pose_anees,
        pose_nees_in_band,
        pose_nees_above_band,
        map_features: v.map.len(),
        map_rmse_m,
        map_anees,
        association: v.association,
        observations: v.observations,
        rejected_messages: v.rejected_messages,
        restarts: v.restarts,
        rejections: v.rejections.clone(),
        ate,
        peak_rss_mb: v.peak_rss_bytes.map(|b| b as f64 / 1e6),
        access_refused: v.access_refused.clone(),
        frame_alignment: v.frame_alignment.clone(),
    }
}

/// NEES of a 3-vector error under a row-major 3×3 covariance; `None` when it is not positive
/// definite.
pub fn feature_nees(est: &[f64; 3], cov: &[f64; 9], truth: &[f64; 3]) -> Option<f64> {
    let c = nalgebra::Matrix3::from_row_slice(cov);
    let e = nalgebra::Vector3::new(est[0] - truth[0], est[1] - truth[1], est[2] - truth[2]);
    let chol = c.cholesky()?;
    Some(e.dot(&chol.solve(&e)))
}

fn team(vs: &[VehicleSummary]) -> TeamSummary {
    // Means over the vehicles where a figure is available (replayed vehicles have no truth).
    let avail = |f: fn(&VehicleSummary) -> f64| mean(vs.iter().map(f).filter(|x| x.is_finite()));
    TeamSummary {
        position_rmse_m: avail(|v| v.position_rmse_m),
        map_rmse_m: avail(|v| v.map_rmse_m),
        pose_anees: avail(|v| v.pose_anees),
        map_anees: avail(|v| v.map_anees),
    }
}

fn summarize_link(l: &LinkRecord) -> LinkSummary {
    let last = l.samples.last();
    LinkSummary {
        link: format!("{}-{}", l.a, l.b),
        transport: l.transport.clone(),
        bytes_ab: last.map_or(0, |s| s.bytes_ab),
        bytes_ba: last.map_or(0, |s| s.bytes_ba),
        messages: last.map_or(0, |s| s.messages),
        drops: last.map_or(0, |s| s.drops),
        rejections: last.map_or(0, |s| s.rejections),
        ci: l.ci,
        bandwidth_ratio: if l.naive_bytes > 0 {
            last.map_or(0, |s| s.bytes_ab + s.bytes_ba) as f64 / l.naive_bytes as f64
        } else {
            0.0
        },
    }
}

/// Computes the summary of a run.
pub fn summarize(run: &RunRecord) -> Summary {
    let vehicles: Vec<_> = run.vehicles.iter().map(summarize_vehicle).collect();
    let baseline = run.baseline.as_ref().map(|b| {
        let vs: Vec<_> = b.iter().map(summarize_vehicle).collect();
        BaselineSummary {
            team: team(&vs),
            vehicles: vs,
        }
    });
    Summary {
        scenario: run.scenario.clone(),
        mode: run.mode.clone(),
        frame: run.frame.clone(),
        seed: run.seed,
        duration_s: run.duration,
        wall_time_s: run.wall_time,
        real_time_factor: if run.wall_time > 0.0 {
            run.duration / run.wall_time
        } else {
            f64::NAN
        },
        team: team(&vehicles),
        association: summarize_association(&vehicles, run.team_wrong_merges),
        vehicles,
        links: run.links.iter().map(summarize_link).collect(),
        baseline,
        identity: run.identity.clone(),
        events: run.events.len(),
        router_access_refused: run.router_access_refused.clone(),
    }
}

/// A fixed-width text table of one or more summaries side by side (one column per summary).
pub fn table(summaries: &[(&str, &Summary)]) -> String {
    use std::fmt::Write;
    let mut rows: Vec<(String, Vec<String>)> = Vec::new();
    let mut push = |label: &str, f: &dyn Fn(&Summary) -> String| {
        rows.push((
            label.to_string(),
            summaries.iter().map(|(_, s)| f(s)).collect(),
        ));
    };
    push("mode", &|s| s.mode.clone());
    push("frame", &|s| s.frame.clone());
    push("vehicles", &|s| s.vehicles.len().to_string());
    push("sim time [s]", &|s| format!("{:.1}", s.duration_s));
    push("wall time [s]", &|s| format!("{:.1}", s.wall_time_s));
    push("real-time factor", &|s| {
        format!("{:.2}", s.real_time_factor)
    });
    push("position RMSE [m]", &|s| {
        format!("{:.3}", s.team.position_rmse_m)
    });
    push("ATE SE(3) / 4-DOF [m]", &|s| {
        let a: Vec<_> = s.vehicles.iter().filter_map(|v| v.ate).collect();
        match a.len() {
            0 => "-".into(),
            // One column per vehicle while it stays readable; a large team's range instead.
            1..=4 => a
                .iter()
                .map(|a| format!("{:.3}/{:.3}", a.se3_m, a.posyaw_m))
                .collect::<Vec<_>>()
                .join(" "),
            n => {
                let range = |f: &dyn Fn(&AteSummary) -> f64| {
                    let lo = a.iter().map(f).fold(f64::INFINITY, f64::min);
                    let hi = a.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
                    format!("{lo:.3}–{hi:.3}")
                };
                format!(
                    "{} / {} ({n} vehicles)",
                    range(&|a| a.se3_m),
                    range(&|a| a.posyaw_m)
                )
            }
        }
    });
    push("map RMSE [m]", &|s| format!("{:.3}", s.team.map_rmse_m));
    if summaries
        .iter()
        .any(|(_, s)| s.vehicles.iter().any(|v| v.frame_alignment.is_some()))
    {
        // Own frames: when each vehicle joined the team frame ("root" holds it, "-" never).
        push("frames aligned at [s]", &|s| {
            s.vehicles
                .iter()
                .map(|v| match &v.frame_alignment {
                    Some(f) if f.root => "root".to_string(),
                    Some(f) => f.aligned_at_s.map_or("-".into(), |t| format!("{t:.0}")),
                    None => "-".into(),
                })
                .collect::<Vec<_>>()
                .join(" ")
        });
    }
    push("peak RSS per vehicle [MB]", &|s| {
        s.vehicles
            .iter()
            .filter_map(|v| v.peak_rss_mb)
            .reduce(f64::max)
            .map_or("-".into(), |m| format!("{m:.0}"))
    });
    push("pose ANEES (1 = ideal)", &|s| {
        format!("{:.2}", s.team.pose_anees)
    });
    push("map ANEES (1 = ideal)", &|s| {
        format!("{:.2}", s.team.map_anees)
    });
    push("identity", &|s| {
        if s.identity.is_empty() {
            "-".into()
        } else {
            s.identity.clone()
        }
    });
    push("wrong associations", &|s| {
        format!(
            "{} of {}",
            s.association.wrong_associations, s.association.observations
        )
    });
    push("duplicate features", &|s| {
        s.association.duplicate_features.to_string()
    });
    push("mature duplicates", &|s| {
        let a = &s.association;
        format!("{} of {}", a.mature_duplicates, a.mature_features)
    });
    push("unmatched features", &|s| {
        s.association.unmatched_features.to_string()
    });
    push("merges adopted / refused", &|s| {
        let a = &s.association;
        format!("{} / {}", a.merges_adopted, a.merges_refused)
    });
    push("wrong merges (cross-vehicle)", &|s| {
        let a = &s.association;
        format!("{} ({})", a.wrong_merges, a.wrong_cross_vehicle_merges)
    });
    push("link bytes", &|s| {
        s.links
            .iter()
            .map(|l| l.bytes_ab + l.bytes_ba)
            .sum::<u64>()
            .to_string()
    });
    push("link bytes / naive dense", &|s| {
        let naive: Vec<f64> = s
            .links
            .iter()
            .filter(|l| l.bandwidth_ratio > 0.0)
            .map(|l| l.bandwidth_ratio)
            .collect();
        if naive.is_empty() {
            "-".into()
        } else {
            format!("{:.3}", naive.iter().sum::<f64>() / naive.len() as f64)
        }
    });
    push("link drops", &|s| {
        s.links.iter().map(|l| l.drops).sum::<u64>().to_string()
    });
    push("baseline position RMSE [m]", &|s| {
        s.baseline
            .as_ref()
            .map_or("-".into(), |b| format!("{:.3}", b.team.position_rmse_m))
    });
    push("baseline map RMSE [m]", &|s| {
        s.baseline
            .as_ref()
            .map_or("-".into(), |b| format!("{:.3}", b.team.map_rmse_m))
    });
    push("baseline pose ANEES", &|s| {
        s.baseline
            .as_ref()
            .map_or("-".into(), |b| format!("{:.2}", b.team.pose_anees))
    });
    let label_w = rows.iter().map(|r| r.0.len()).max().unwrap_or(0).max(8);
    let col_w: Vec<usize> = (0..summaries.len())
        .map(|i| {
            rows.iter()
                .map(|r| r.1[i].len())
                .chain([summaries[i].0.len()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let mut out = String::new();
    let _ = write!(out, "{:label_w$}", "");
    for (i, (name, _)) in summaries.iter().enumerate() {
        let _ = write!(out, "  {:>w$}", name, w = col_w[i]);
    }
    out.push('\n');
    for (label, vals) in &rows {
        let _ = write!(out, "{label:label_w$}");
        for (i, v) in vals.iter().enumerate() {
            let _ = write!(out, "  {:>w$}", v, w = col_w[i]);
        }
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chi2_band_matches_tables() {
        // Standard χ² table values (e.g. NIST/SEMATECH e-Handbook §1.3.6.7.4).
        let (lo, hi) = chi2_band(3.0);
        assert!((lo - 0.2158).abs() < 1e-3 && (hi - 9.348).abs() < 1e-3);
        let (lo, hi) = chi2_band(6.0);
        assert!((lo - 1.237).abs() < 1e-3 && (hi - 14.449).abs() < 1e-3);
    }

    #[test]
    fn feature_nees_is_mahalanobis() {
        let cov = [4.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 9.0];
        let n = feature_nees(&[2.0, 1.0, 3.0], &cov, &[0.0, 0.0, 0.0]).unwrap();
        assert!((n - 3.0).abs() < 1e-12); // 4/4 + 1/1 + 9/9
        assert!(feature_nees(&[0.0; 3], &[0.0; 9], &[0.0; 3]).is_none());
    }

    /// The ATE of a vehicle: an estimate that is the truth moved rigidly (yaw and offset, a
    /// gauge an alignment removes) has ATE 0 under both alignments; a constant 0.1 m error
    /// along the body's path normal that alternates in sign cannot be aligned away and gives
    /// 0.1 m (its mean is zero); samples without truth are left out of every figure.
    #[test]
    fn ate_of_a_record_and_samples_without_truth() {
        use crate::record::PoseSample;
        let yaw = 0.3f64;
        let (c, s) = (yaw.cos(), yaw.sin());
        let sample = |k: usize, bump: f64| {
            let t = k as f64 * 0.5;
            let truth = [10.0 * (0.2 * t).cos(), 10.0 * (0.2 * t).sin(), -0.1 * t];
            let est = [
                c * truth[0] - s * truth[1] + 3.0,
                s * truth[0] + c * truth[1] - 1.0,
                truth[2] + 0.5 + bump,
            ];
            PoseSample {
                t,
                est_pos: est,
                est_att: [0.01, -0.02, 0.2 * t + yaw],
                truth_pos: truth,
                truth_att: [0.01, -0.02, 0.2 * t],
                pos_cov: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                nees_pos: 1.0,
                nees_pose: 2.0,
            }
        };
        let mut v = VehicleRecord {
            name: "v".into(),
            samples: (0..40).map(|k| sample(k, 0.0)).collect(),
            ..Default::default()
        };
        let a = summarize_vehicle(&v).ate.expect("an ATE");
        assert!(a.se3_m < 1e-9 && a.posyaw_m < 1e-9, "{a:?}");
        assert!(a.se3_deg < 1e-6 && a.posyaw_deg < 1e-6, "{a:?}");
        // ±0.1 m alternating down the path: 0.1 m after either alignment (to 1e-3: the fit
        // may absorb a sliver of the pattern's correlation with the helix).
        v.samples = (0..40)
            .map(|k| sample(k, if k % 2 == 0 { 0.1 } else { -0.1 }))
            .collect();
        let a = summarize_vehicle(&v).ate.unwrap();
        assert!(
            (a.se3_m - 0.1).abs() < 1e-3 && (a.posyaw_m - 0.1).abs() < 1e-3,
            "{a:?}"
        );
        // Samples without truth (a replayed vehicle outside its ground truth) do not count.
        let mut no_truth = sample(40, 5.0);
        no_truth.truth_pos = [f64::NAN; 3];
        no_truth.truth_att = [f64::NAN; 3];
        no_truth.nees_pos = f64::NAN;
        no_truth.nees_pose = f64::NAN;
        v.samples.push(no_truth);
        let sum = summarize_vehicle(&v);
        assert!((sum.ate.unwrap().se3_m - 0.1).abs() < 1e-3);
        assert!(
            (sum.pose_anees - 2.0 / 6.0).abs() < 1e-12,
            "{}",
            sum.pose_anees
        );
        assert!(sum.position_rmse_m.is_finite());
    }

    /// The team's association figures are the vehicles' sums, the mature-duplicate share their
    /// ratio (null without mature features), and the distinct wrong merges the run's count.
    #[test]
    fn team_association_sums_vehicles() {
        let v = |obs, wrong, dup, mature, mdup| {
            summarize_vehicle(&VehicleRecord {
                observations: obs,
                association: crate::truth::TruthFigures {
                    wrong_associations: wrong,
                    duplicate_features: dup,
                    mature_features: mature,
                    mature_duplicates: mdup,
                    unmatched_features: dup,
                    merges_adopted: 3,
                    wrong_cross_vehicle_merges: 1,
                    ..Default::default()
                },
                ..VehicleRecord::default()
            })
        };
        let a = summarize_association(&[v(100, 2, 5, 40, 4), v(50, 0, 1, 10, 1)], 1);
        assert_eq!(
            (a.observations, a.wrong_associations, a.duplicate_features),
            (150, 2, 6)
        );
        assert_eq!((a.mature_features, a.mature_duplicates), (50, 5));
        // 5 / 50 and the literal 0.1 are the same correctly rounded double.
        assert_eq!(a.mature_duplicate_share, 0.1);
        assert_eq!(
            (a.unmatched_features, a.merges_adopted, a.wrong_merges),
            (6, 6, 1)
        );
        assert_eq!(a.wrong_cross_vehicle_merges, 2);
        assert!(
            summarize_association(&[v(1, 0, 0, 0, 0)], 0)
                .mature_duplicate_share
                .is_nan()
        );
    }
}
