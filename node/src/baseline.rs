//! The centralized all-data reference: one EKF over every vehicle and the whole map, fed the
//! same IMU samples and observation frames as the vehicles, in the same order as `canopy sim`
//! feeds its reference. It is deterministic given the scenario, so the monitor of a
//! multi-process run computes it itself (in a thread) instead of receiving it over the network.
//!
//! Besides the per-vehicle estimate-vs-truth samples it keeps, at every record time, each
//! feature's covariance: the bound a vehicle's map report is checked against (a vehicle holding
//! more information about a feature than all the data of the team has counted some twice).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use canopy_fusion::ins::VehicleState;
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::slam::{
    AssociationConfig, AssociationMode, SlamConfig, SlamError, SlamFilter, VehicleSetup,
};
use nalgebra::{Matrix3, Vector3};

use crate::metrics::{HeldSince, estimate_sample, map_records, pose_sample};
use crate::process::protocol::FrameAssociations;
use crate::record::VehicleRecord;
use crate::replay::{ReplayError, SensorSource};
use crate::scenario::Identity;
use crate::scenario::{Scenario, VehicleConfig};
use crate::truth::{TruthAudit, fill_record};
use crate::world::{InitialEstimate, World};

/// The estimator setup of a vehicle from its configuration and an initial estimate (the same as
/// [`crate::sim::vehicle_setup`], which reads the sensor model and mount from the simulator
/// that was built from this configuration; σ floors keep a perfect IMU's zero bias variances
/// positive definite: 1e-12 is far below any grade's turn-on bias²).
pub fn estimator_setup(cfg: &VehicleConfig, estimate: &InitialEstimate) -> VehicleSetup {
    let mut covariance = estimate.covariance;
    for i in 0..covariance.nrows() {
        covariance[(i, i)] = covariance[(i, i)].max(1e-12);
    }
    VehicleSetup {
        state: VehicleState {
            position: estimate.position,
            velocity: estimate.velocity,
            attitude: estimate.attitude,
            accel_bias: estimate.accel_bias,
            gyro_bias: estimate.gyro_bias,
        },
        covariance,
        imu_noise: cfg.imu.noise_model(),
        sensor: cfg.sensor.model(),
        mount: cfg.sensor.mount(),
    }
}

/// The reference filter's configuration: descriptor association verified by the gate.
pub fn reference_config(s: &Scenario, world: &World) -> SlamConfig {
    SlamConfig {
        frame: world.frame(),
        local_gravity_mps2: world.local_gravity(),
        origin: world.map_origin(),
        association: AssociationConfig {
            mode: AssociationMode::Descriptor,
            gate_probability: s.fusion.gate_probability,
            ..AssociationConfig::default()
        },
        fresh_id_namespace: u32::MAX,
    }
}

/// Every vehicle's estimator setup from the initial estimate the reference starts it from
/// (scenario order).
pub fn reference_setups(s: &Scenario, sources: &[SensorSource]) -> Vec<VehicleSetup> {
    s.vehicles
        .iter()
        .zip(sources)
        .map(|(cfg, src)| estimator_setup(cfg, &src.reference_initial_estimate()))
        .collect()
}

/// Gives `filter`, one filter over the whole team, the vehicles' bearing options: one filter,
/// one set of options, so they must agree (the error names the filter, `what`, and ends with
/// `way_out`).
pub fn set_team_bearing(
    s: &Scenario,
    filter: &mut SlamFilter,
    what: &str,
    way_out: &str,
) -> Result<(), SlamError> {
    let Some(first) = s.vehicles.first() else {
        return Ok(());
    };
    if s.vehicles.iter().any(|v| v.bearing != first.bearing) {
        return Err(SlamError::InvalidConfig(format!(
            "{what} is one filter: every vehicle needs the same [vehicle.bearing] options{way_out}"
        )));
    }
    filter.set_bearing_config(first.bearing.config())
}

/// The reference filter over `setups` (one per vehicle, in scenario order).
pub fn reference_filter(
    s: &Scenario,
    world: &World,
    setups: &[VehicleSetup],
) -> Result<SlamFilter, SlamError> {
    let mut filter = SlamFilter::new(reference_config(s, world), setups)?;
    set_team_bearing(
        s,
        &mut filter,
        "the centralized reference",
        " (or run without the baseline)",
    )?;
    Ok(filter)
}

/// The restarts of a scenario in time order: (time, vehicle index, incarnation). A vehicle
/// crashed by an `[[event]]` with `restart_after_s` is re-initialised at exactly
/// `at_s + restart_after_s`, before any sample at or after that time (in `canopy sim` and, by
/// the world's pacing, in `canopy run`), with incarnation 1, 2, … per vehicle.
pub fn restarts(s: &Scenario) -> Vec<(f64, usize, u32)> {
    let mut r: Vec<(f64, usize)> = s
        .events
        .iter()
        .filter_map(|e| {
            let v = e.vehicle?;
            let at = e.at_s + e.restart_after_s?;
            let i = s.vehicles.iter().position(|x| x.id == v)?;
            Some((at, i))
        })
        .collect();
    r.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut count = vec![0u32; s.vehicles.len()];
    r.into_iter()
        .map(|(t, i)| {
            count[i] += 1;
            (t, i, count[i])
        })
        .collect()
}

/// Applies the external fix a restarted vehicle re-initialises from (its position, velocity and
/// attitude with their covariance; the bias part restates the turn-on prior the reference
/// already holds, so it is not used) to the reference, which then still holds every piece of
/// information any vehicle has.
pub fn apply_restart_fix(
    filter: &mut SlamFilter,
    vehicle: usize,
    estimate: &InitialEstimate,
) -> Result<(), SlamError> {
    let mut fix = [0.0; 9];
    for k in 0..3 {
        fix[k] = estimate.position[k];
        fix[3 + k] = estimate.velocity[k];
        fix[6 + k] = estimate.attitude[k];
    }
    use canopy_fusion::state::POS;
    let cov: nalgebra::SMatrix<f64, 9, 9> = estimate.covariance.fixed_view::<9, 9>(POS, POS).into();
    filter.vehicle_fix(vehicle, &fix, &cov)
}

/// Errors of the reference run.
#[derive(Debug, thiserror::Error)]
pub enum BaselineError {
    /// The scenario or its logs cannot be used.
    #[error(transparent)]
    Replay(#[from] ReplayError),
    /// The filter could not be built.
    #[error("building the centralized reference: {0}")]
    Filter(#[from] SlamError),
}

/// Per-feature covariances of the reference at one record time (estimator frame).
#[derive(Clone, Debug, Default)]
pub struct FeatureSnapshot {
    /// Record time [s].
    pub t: f64,
    /// Covariance of every feature of the reference map.
    pub covariances: BTreeMap<FeatureId, Matrix3<f64>>,
    /// Means (estimator frame).
    pub means: BTreeMap<FeatureId, Vector3<f64>>,
}

/// What the reference run produces.
#[derive(Clone, Debug, Default)]
pub struct BaselineRun {
    /// Per vehicle: estimate-vs-truth samples of the joint filter's estimate of that vehicle,
    /// the joint final map, wrong associations and observations.
    pub vehicles: Vec<VehicleRecord>,
    /// Per-feature covariances at every record time, in time order.
    pub snapshots: Vec<FeatureSnapshot>,
    /// Simulated time reached [s].
    pub duration: f64,
    /// Whether it was stopped before the end.
    pub interrupted: bool,
}

impl BaselineRun {
    /// The snapshot at the first record time ≥ `t` (or the last one).
    pub fn snapshot_at_or_after(&self, t: f64) -> Option<&FeatureSnapshot> {
        let k = self.snapshots.partition_point(|s| s.t < t - 1e-6);
        self.snapshots.get(k).or(self.snapshots.last())
    }
}

/// Runs the reference over the scenario's sensor sources up to `duration`, recording every
/// `[run].record_interval_s`. `stop` ends it early; `progress` receives the simulated time
/// reached (f64 bits) about every simulated second.
pub fn run_reference(
    s: &Scenario,
    duration: f64,
    stop: Option<&AtomicBool>,
    progress: Option<&AtomicU64>,
) -> Result<BaselineRun, BaselineError> {
    let (world, mut sources) = SensorSource::for_scenario(s)?;
    let setups = reference_setups(s, &sources);
    let mut filter = reference_filter(s, &world, &setups)?;
    let mut run = BaselineRun {
        vehicles: s
            .vehicles
            .iter()
            .map(|v| VehicleRecord {
                name: v.display_name(),
                ..Default::default()
            })
            .collect(),
        ..Default::default()
    };
    let record_dt = s.run.record_interval_s;
    let eps = 1e-9;
    let mut next_record = 0.0;
    let mut next_progress = 1.0;
    let mut audit = TruthAudit::default();
    let mut fixes = restarts(s).into_iter().peekable();
    let record = |run: &mut BaselineRun, filter: &SlamFilter, sources: &[SensorSource], t: f64| {
        for (i, src) in sources.iter().enumerate() {
            if let (Ok(est), Ok(cov)) = (filter.vehicle_state(i), filter.vehicle_covariance(i)) {
                let sample = match src.truth() {
                    Some(truth) => pose_sample(&world, &est, &cov, truth),
                    None => estimate_sample(&world, src.time(), &est, &cov),
                };
                run.vehicles[i].samples.push(sample);
            }
        }
        let mut snap = FeatureSnapshot {
            t,
            ..Default::default()
        };
        for (id, m) in filter.features() {
            if let Some(c) = filter.feature_covariance(id) {
                snap.covariances.insert(id, c);
                snap.means.insert(id, m);
            }
        }
        run.snapshots.push(snap);
    };
    record(&mut run, &filter, &sources, 0.0);
    next_record += record_dt;
    loop {
        if stop.is_some_and(|f| f.load(Ordering::Relaxed)) {
            run.interrupted = true;
            break;
        }
        // The source whose next sample is earliest (ties: scenario order), as in `canopy sim`.
        let Some((vi, t)) = sources
            .iter()
            .enumerate()
            .filter_map(|(i, v)| v.next_time().map(|t| (i, t)))
            .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
        else {
            break;
        };
        if t > duration + eps {
            break;
        }
        while let Some(&(tf, fi, inc)) = fixes.peek()
            && t + eps >= tf
        {
            fixes.next();
            if let Some(est) = sources[fi].reference_restart_estimate(u64::from(inc)) {
                // A refused fix leaves the reference as it was (it then lacks that fix).
                let _ = apply_restart_fix(&mut filter, fi, &est);
            }
        }
        let Some(step) = sources[vi].step() else {
            break;
        };
        let _ = filter.predict(vi, &step.imu);
        if let Some((frame, true_ids)) = &step.frame {
            // With appearance the reference still associates by the true ids.
            let perfect = match true_ids {
                Some(ids) if s.world.appearance.identity == Identity::Appearance => {
                    Some(crate::world::with_true_ids(frame, ids))
                }
                _ => None,
            };
            if let Ok(report) = filter.process_frame(vi, perfect.as_ref().unwrap_or(frame)) {
                audit.frame(
                    s.vehicles[vi].id,
                    &FrameAssociations::from_report(frame.time, &report),
                    true_ids.as_deref(),
                );
                run.vehicles[vi].observations += frame.observations.len() as u64;
            }
        }
        let tmin = sources
            .iter()
            .filter(|v| v.next_time().is_some())
            .map(SensorSource::time)
            .fold(f64::INFINITY, f64::min);
        if tmin + eps >= next_record {
            record(&mut run, &filter, &sources, tmin);
            next_record += record_dt;
        }
        if tmin >= next_progress {
            if let Some(p) = progress {
                p.store(tmin.to_bits(), Ordering::Relaxed);
            }
            next_progress += 1.0;
        }
    }
    run.duration = sources
        .iter()
        .map(SensorSource::time)
        .fold(f64::INFINITY, f64::min)
        .min(duration);
    let have_truth = crate::metrics::maps_have_truth(s);
    let truth = audit.finish();
    let mut map = map_records(&world, &filter, |k| {
        if have_truth { truth.truth(k) } else { None }
    });
    let mut held = HeldSince::default();
    for snap in &run.snapshots {
        held.observe(snap.t, snap.covariances.keys().copied());
    }
    held.stamp(run.duration, &mut map);
    for (r, cfg) in run.vehicles.iter_mut().zip(&s.vehicles) {
        r.map = map.clone();
        fill_record(&truth, cfg.id, r, run.duration);
    }
    if let Some(p) = progress {
        p.store(run.duration.to_bits(), Ordering::Relaxed);
    }
    Ok(run)
}
