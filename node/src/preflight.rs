//! The checks every run makes of a scenario and its inputs before it starts, shared by
//! `canopy check` and `canopy run` (in the launcher, before any process is spawned; `canopy
//! sim` builds the same sources and agents, so it fails on the same inputs): the scenario's
//! fields, the simulated vehicles (trajectory, clearance over the terrain), the replay logs
//! (parsed and checked line by line, the static alignment made), the fusion topology, and every
//! vehicle's estimator built from its initial estimate.

use anyhow::{Context, Result};

use crate::replay::{ReplayLog, SensorSource};
use crate::scenario::Scenario;

/// What the checks found about one vehicle's input.
#[derive(Debug, Clone)]
pub enum VehicleInput {
    /// Simulated by the world.
    Simulated,
    /// Replayed from logs.
    Replayed {
        /// IMU samples logged.
        imu_samples: usize,
        /// Frames logged.
        frames: usize,
        /// Observations in them.
        observations: usize,
        /// IMU samples split at a frame time.
        split_samples: usize,
        /// Time of the initial estimate [s].
        start: f64,
        /// Time of the last sample [s].
        end: f64,
        /// Samples and duration of the static alignment, when it made the initial estimate.
        alignment: Option<(usize, f64)>,
    },
}

impl VehicleInput {
    fn of(log: &ReplayLog) -> Self {
        VehicleInput::Replayed {
            imu_samples: log.imu.len(),
            frames: log.frames.len(),
            observations: log.frames.iter().map(|f| f.observations.len()).sum(),
            split_samples: log.steps.len() - log.imu.len(),
            start: log.initial.time,
            end: log.imu.last().map_or(log.initial.time, |s| s.time),
            alignment: log.alignment.as_ref().map(|a| (a.samples, a.duration)),
        }
    }
}

/// Runs every check; the findings per vehicle (scenario order).
pub fn preflight(s: &Scenario) -> Result<Vec<VehicleInput>> {
    s.validate()?;
    let (world, sources) = SensorSource::for_scenario(s)?;
    let mut out = Vec::with_capacity(sources.len());
    for (i, (cfg, src)) in s.vehicles.iter().zip(&sources).enumerate() {
        crate::sim::vehicle_agent(s, cfg, &world, &src.initial_estimate(), 0, 1)
            .with_context(|| format!("vehicle[{i}] `{}`: its estimator", cfg.display_name()))?;
        out.push(match src {
            SensorSource::Sim(_) => VehicleInput::Simulated,
            SensorSource::Replay(r) => VehicleInput::of(r.log()),
        });
    }
    Ok(out)
}
