//! Estimate-vs-truth metrics in the launch frame: pose samples with NEES, map records, and the
//! per-feature confidence check against the centralized reference. Used by the simulation and
//! by the monitor of multi-process runs.

use std::collections::{HashMap, HashSet};

use canopy_fusion::consistency::vehicle_error;
use canopy_fusion::frames::Frame4;
use canopy_fusion::geodesy::{ecef_from_ned, ecef_to_geodetic};
use canopy_fusion::ins::{VehicleCovariance, VehicleState};
use canopy_fusion::rotation::{euler_from_nav_from_body, nav_from_body};
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::slam::SlamFilter;
use canopy_fusion::state::{ATT, NavFrame, POS, VEL};
use nalgebra::{Matrix3, Matrix6, Vector3, Vector6};

use crate::record::{MapFeatureRecord, PoseSample};
use crate::world::{TruthSample, World};

/// Rotation from the estimator's frame to the launch NED frame (C_e^{n0} in global SLAM).
pub fn launch_from_nav(world: &World) -> Matrix3<f64> {
    match world.frame() {
        NavFrame::Local => Matrix3::identity(),
        NavFrame::Global => world.launch_frame().ecef_from_ned.transpose(),
    }
}

/// Attitude relative to the launch frame of an attitude Ψ relative to the local level at
/// `position` (global) or to the launch frame itself (local).
pub fn launch_attitude(
    world: &World,
    position: &Vector3<f64>,
    attitude: &Vector3<f64>,
) -> Vector3<f64> {
    match world.frame() {
        NavFrame::Local => *attitude,
        NavFrame::Global => {
            let g = ecef_to_geodetic(position);
            let c = launch_from_nav(world) * ecef_from_ned(g.lat, g.lon) * nav_from_body(attitude);
            euler_from_nav_from_body(&c)
        }
    }
}

/// Whether a scenario's map features have truth: only when no vehicle is replayed (replayed
/// descriptors name no simulated feature, and fusion mixes them into every map).
pub fn maps_have_truth(s: &crate::scenario::Scenario) -> bool {
    s.vehicles.iter().all(|v| v.replay.is_none())
}

/// The truth as an estimator state (biases in effect for the last sample).
pub fn truth_state(t: &TruthSample) -> VehicleState {
    VehicleState {
        position: t.position,
        velocity: t.velocity,
        attitude: t.attitude,
        accel_bias: t.accel_bias,
        gyro_bias: t.gyro_bias,
    }
}

fn arr(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn arr9(m: &Matrix3<f64>) -> [f64; 9] {
    let mut a = [0.0; 9];
    for r in 0..3 {
        for c in 0..3 {
            a[3 * r + c] = m[(r, c)];
        }
    }
    a
}

/// NEES of a small error/covariance pair; NaN when the covariance is not positive definite.
fn nees6(e: &Vector6<f64>, p: &Matrix6<f64>) -> f64 {
    p.cholesky().map_or(f64::NAN, |c| e.dot(&c.solve(e)))
}

/// An estimate (state and covariance) re-expressed by the 4-DOF transform `frame`
/// (x' = Rz(ψ)·x + t): positions and velocities rotate, the yaw shifts, roll, pitch and biases
/// stay; the covariance is J P Jᵀ with J = blockdiag(R, R, I, I, I) (exact: the transform is
/// known, `[world] frames = "own"`'s truth-side conversion to the launch frame).
pub fn state_in(
    frame: &Frame4,
    est: &VehicleState,
    cov: &VehicleCovariance,
) -> (VehicleState, VehicleCovariance) {
    let r = frame.rotation();
    let mut j = VehicleCovariance::identity();
    j.fixed_view_mut::<3, 3>(POS, POS).copy_from(&r);
    j.fixed_view_mut::<3, 3>(VEL, VEL).copy_from(&r);
    let mut attitude = est.attitude;
    attitude.z = canopy_fusion::rotation::wrap_angle(attitude.z + frame.yaw);
    (
        VehicleState {
            position: frame.apply(&est.position),
            velocity: r * est.velocity,
            attitude,
            accel_bias: est.accel_bias,
            gyro_bias: est.gyro_bias,
        },
        j * cov * j.transpose(),
    )
}

/// One estimate-vs-truth sample. NEES is computed in the estimator's own frame (position error
/// and wrapped Euler-angle error with the filter's covariance of p and Ψ).
pub fn pose_sample(
    world: &World,
    est: &VehicleState,
    cov: &VehicleCovariance,
    truth: &TruthSample,
) -> PoseSample {
    let e = vehicle_error(est, &truth_state(truth));
    let mut e6 = Vector6::zeros();
    let mut p6 = Matrix6::zeros();
    let idx = [POS, POS + 1, POS + 2, ATT, ATT + 1, ATT + 2];
    for (i, &a) in idx.iter().enumerate() {
        e6[i] = e[a];
        for (j, &b) in idx.iter().enumerate() {
            p6[(i, j)] = cov[(a, b)];
        }
    }
    let p3: Matrix3<f64> = p6.fixed_view::<3, 3>(0, 0).into();
    let e3: Vector3<f64> = e6.fixed_rows::<3>(0).into();
    let nees_pos = p3.cholesky().map_or(f64::NAN, |c| e3.dot(&c.solve(&e3)));
    let r = launch_from_nav(world);
    PoseSample {
        t: truth.time,
        est_pos: arr(&world.to_launch(&est.position)),
        est_att: arr(&launch_attitude(world, &est.position, &est.attitude)),
        truth_pos: arr(&truth.launch_position),
        truth_att: arr(&truth.launch_attitude),
        pos_cov: arr9(&(r * p3 * r.transpose())),
        nees_pos,
        nees_pose: nees6(&e6, &p6),
    }
}

/// An estimate sample of a vehicle without truth (a replayed vehicle): truth fields and NEES
/// are NaN, the estimate is in the launch frame as in [`pose_sample`].
pub fn estimate_sample(
    world: &World,
    t: f64,
    est: &VehicleState,
    cov: &VehicleCovariance,
) -> PoseSample {
    let r = launch_from_nav(world);
    let p3: Matrix3<f64> = cov.fixed_view::<3, 3>(POS, POS).into();
    PoseSample {
        t,
        est_pos: arr(&world.to_launch(&est.position)),
        est_att: arr(&launch_attitude(world, &est.position, &est.attitude)),
        truth_pos: [f64::NAN; 3],
        truth_att: [f64::NAN; 3],
        pos_cov: arr9(&(r * p3 * r.transpose())),
        nees_pos: f64::NAN,
        nees_pose: f64::NAN,
    }
}

/// One feature (mean and covariance in the estimator's frame) as a launch-frame record, with
/// the true feature its key stands for (`truth_id`, [`crate::truth::KeyTruth`]) and that
/// feature's position.
pub fn feature_record(
    world: &World,
    id: FeatureId,
    truth_id: Option<FeatureId>,
    mean: &Vector3<f64>,
    cov: &Matrix3<f64>,
) -> MapFeatureRecord {
    let r = launch_from_nav(world);
    let truth = truth_id.and_then(|t| world.feature(t));
    MapFeatureRecord {
        id,
        truth_id: truth.map(|f| f.id),
        est: arr(&world.to_launch(mean)),
        cov: arr9(&(r * cov * r.transpose())),
        truth: truth.map(|f| arr(&f.position_ned)),
        held_since: None,
    }
}

/// Since when a map has held each of its features, from the maps of consecutive record
/// times: a feature's time is the first record time of its latest unbroken stretch in the map
/// (a feature removed and later fused again starts a new stretch).
#[derive(Clone, Debug, Default)]
pub struct HeldSince(HashMap<FeatureId, f64>);

impl HeldSince {
    /// The map at record time `t` held exactly `ids`.
    pub fn observe(&mut self, t: f64, ids: impl IntoIterator<Item = FeatureId>) {
        let now: HashSet<FeatureId> = ids.into_iter().collect();
        self.0.retain(|id, _| now.contains(id));
        for id in now {
            self.0.entry(id).or_insert(t);
        }
    }

    /// Fills `held_since` of a final map taken at time `end` (a feature not seen at any
    /// earlier record time gets `end`).
    pub fn stamp(&mut self, end: f64, map: &mut [MapFeatureRecord]) {
        self.observe(end, map.iter().map(|f| f.id));
        for f in map {
            f.held_since = self.0.get(&f.id).copied();
        }
    }
}

/// The filter's map in the launch frame, each key with the true feature `truth` assigns it.
pub fn map_records(
    world: &World,
    filter: &SlamFilter,
    truth: impl Fn(FeatureId) -> Option<FeatureId>,
) -> Vec<MapFeatureRecord> {
    map_records_in(world, &Frame4::identity(), filter, truth)
}

/// [`map_records`] of a filter whose frame is `launch_from_est` in the launch frame (own
/// frames: the frame owner's true start).
pub fn map_records_in(
    world: &World,
    launch_from_est: &Frame4,
    filter: &SlamFilter,
    truth: impl Fn(FeatureId) -> Option<FeatureId>,
) -> Vec<MapFeatureRecord> {
    let r = launch_from_est.rotation();
    filter
        .features()
        .into_iter()
        .filter_map(|(id, m)| {
            let cov = filter.feature_covariance(id)?;
            let (m, cov) = (launch_from_est.apply(&m), r * cov * r.transpose());
            Some(feature_record(world, id, truth(id), &m, &cov))
        })
        .collect()
}

/// λ_max(P_ref · P_i⁻¹) of one feature: how much more confident covariance `p_i` is than the
/// reference `p_ref` in its most confident direction (rotation invariant, so any common frame
/// will do). `None` when `p_i` is not positive definite.
pub fn feature_confidence_ratio(p_i: &Matrix3<f64>, p_ref: &Matrix3<f64>) -> Option<f64> {
    // Eigenvalues of P_i^{-1/2} P_ref P_i^{-1/2} via the Cholesky factor of P_i.
    let l = p_i.cholesky()?.l();
    let linv = l.try_inverse()?;
    let m = linv * p_ref * linv.transpose();
    let m = (m + m.transpose()) * 0.5;
    Some(m.symmetric_eigenvalues().max())
}

/// Largest over common features of λ_max(P_ref · P_i⁻¹): how much more confident the vehicle
/// is about a feature than the reference filter (≤ 1 when it is never more confident). With a
/// centralized all-data reference, a value well above 1 means information was counted twice.
/// `reference_key` names the reference's feature for a key of `filter` (the key itself with
/// perfect identities; its true feature, `crate::truth`, with appearance, where the reference
/// keys features by their true ids).
pub fn confidence_ratio(
    filter: &SlamFilter,
    reference: &SlamFilter,
    reference_key: impl Fn(FeatureId) -> Option<FeatureId>,
) -> Option<(f64, FeatureId)> {
    confidence_ratio_in(&Matrix3::identity(), filter, reference, reference_key)
}

/// [`confidence_ratio`] of a filter whose frame is rotated by `reference_from_est` from the
/// reference's (own frames).
pub fn confidence_ratio_in(
    reference_from_est: &Matrix3<f64>,
    filter: &SlamFilter,
    reference: &SlamFilter,
    reference_key: impl Fn(FeatureId) -> Option<FeatureId>,
) -> Option<(f64, FeatureId)> {
    let r = reference_from_est;
    let mut worst: Option<(f64, FeatureId)> = None;
    for (id, _) in filter.features() {
        let (Some(pi), Some(pr)) = (
            filter.feature_covariance(id).map(|p| r * p * r.transpose()),
            reference_key(id).and_then(|r| reference.feature_covariance(r)),
        ) else {
            continue;
        };
        let Some(lmax) = feature_confidence_ratio(&pi, &pr) else {
            continue;
        };
        if worst.is_none_or(|(w, _)| lmax > w) {
            worst = Some((lmax, id));
        }
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn feature_confidence_ratio_is_the_largest_generalised_eigenvalue() {
        // Diagonal pair: the generalised eigenvalues are the ratios of the diagonals.
        let pi = Matrix3::from_diagonal(&Vector3::new(1.0, 2.0, 4.0));
        let pr = Matrix3::from_diagonal(&Vector3::new(2.0, 2.0, 1.0));
        let r = feature_confidence_ratio(&pi, &pr).unwrap();
        assert!((r - 2.0).abs() < 1e-12); // max(2/1, 2/2, 1/4)
        // Invariant under a common rotation.
        let rot = nalgebra::Rotation3::from_euler_angles(0.3, -0.4, 1.1).into_inner();
        let r2 =
            feature_confidence_ratio(&(rot * pi * rot.transpose()), &(rot * pr * rot.transpose()))
                .unwrap();
        assert!((r2 - 2.0).abs() < 1e-12);
        assert!(feature_confidence_ratio(&Matrix3::zeros(), &pr).is_none());
    }
}
