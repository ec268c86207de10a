//! The world simulator: terrain features, trajectories, IMU and terrain-sensor synthesis, truth.
//!
//! A pure, seeded, step-able library: [`World::new`] draws the terrain and features,
//! [`VehicleSim::new`] sets up one vehicle, and [`VehicleSim::step`] advances it by one IMU
//! period, returning the measured [`ImuSample`](canopy_fusion::sensor::ImuSample), an
//! [`ObservationFrame`](canopy_fusion::sensor::ObservationFrame) when the terrain sensor fires
//! (with the true feature ids kept beside it), and the truth. The estimator never calls this
//! module; it receives the messages.
//!
//! # Frames
//! Trajectories are defined in the launch site's NED frame n0 (origin `[world.origin]`).
//! - Global (earth model `wgs84`): p, v are ECEF (p^e = o^e + C_{n0}^e p^{n0}, v^e = C_{n0}^e v^{n0});
//!   Ψ is relative to the local-level frame at the vehicle's *current* position:
//!   C_b^n = C_e^n(p) C_{n0}^e C_b^{n0}. Features are ECEF. The Earth rotates; gravity is WGS-84.
//! - Local (earth model `flat`): everything is in n0, the world is flat and non-rotating with
//!   gravity [0, 0, g] (§21.2.2.1), g = `[world] gravity_mps2` or WGS-84 normal gravity at the
//!   launch site ([`World::local_gravity`]).
//!
//! # Seeds
//! The world draws terrain and features from streams of its seed; each vehicle's seed
//! ([`vehicle_seed`]) feeds independent streams for IMU white noise, IMU bias walk, sensor noise,
//! descriptor mismatches and the initial-estimate offset (and, with appearance, descriptor
//! noise and track breaks), so changing one setting does not reshuffle the other draws.
//!
//! # Identity
//! With `[world.appearance] identity = "perfect"` an observation's descriptor is the true
//! feature id; with `"appearance"` it is a per-vehicle tracker's track id and the observation
//! carries a noisy 256-bit descriptor ([`appearance`]). Either way the true ids travel beside
//! the frame ([`SensedFrame::true_ids`]) for the monitor only.

pub mod appearance;
pub mod imu;
pub mod sensor;
pub mod terrain;
pub mod trajectory;
mod vehicle;

pub use imu::{
    BodyMotion, ImuErrors, ImuIdeal, ImuStreams, NavTruth, SensorErrors, continuous_ideal,
    discrete_ideal, exact_increments,
};
pub use sensor::{
    RANDOM_ID_BASE, SensedFrame, TerrainSensor, feature_in_sensor, measure, with_true_ids,
};
pub use terrain::Terrain;
pub use trajectory::{FlightState, Kinematics, Trajectory, coordinated_attitude};
pub use vehicle::{
    FrameEstimate, InitialEstimate, StepOutput, TruthSample, VehicleSim, launch_from_own,
};

use std::sync::Arc;

use canopy_fusion::geodesy::{
    Geodetic, LocalFrame, ecef_from_ned, ecef_to_geodetic, normal_gravity,
};
use canopy_fusion::ins::Mechanization;
use canopy_fusion::rotation::{euler_from_nav_from_body, nav_from_body};
use canopy_fusion::sensor::FeatureId;
use canopy_fusion::state::NavFrame;
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::scenario::{Identity, Scenario, ScenarioError, WorldConfig};

/// Random stream of the terrain surface (world seed).
const STREAM_TERRAIN: u64 = 1;
/// Random stream of the feature placement (world seed).
const STREAM_FEATURES: u64 = 2;
/// Random stream of the features' appearance descriptors (world seed).
pub const STREAM_APPEARANCE: u64 = 3;

/// A ChaCha8 generator on stream `stream` of `seed`.
pub fn rng_stream(seed: u64, stream: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    rng
}

/// SplitMix64 finaliser (Steele, Lea, Flood 2014): a bijective 64-bit mix.
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The seed of vehicle `vehicle_id` in a world seeded with `world_seed`.
pub fn vehicle_seed(world_seed: u64, vehicle_id: u32) -> u64 {
    splitmix64(splitmix64(world_seed) ^ u64::from(vehicle_id).wrapping_mul(0xd1b5_4a32_d192_ed03))
}

/// A terrain feature: its global id (the simulated descriptor) and true position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Feature {
    /// Global id, 1..=count.
    pub id: FeatureId,
    /// Position in the launch NED frame [m].
    pub position_ned: Vector3<f64>,
    /// Position in ECEF [m].
    pub position_ecef: Vector3<f64>,
}

impl Feature {
    /// Position in a vehicle frame's coordinates (ECEF for global, launch NED for local).
    pub fn position(&self, frame: NavFrame) -> Vector3<f64> {
        match frame {
            NavFrame::Global => self.position_ecef,
            NavFrame::Local => self.position_ned,
        }
    }
}

/// The simulated world: launch frame, terrain, features.
#[derive(Clone, Debug)]
pub struct World {
    frame: NavFrame,
    mechanization: Mechanization,
    seed: u64,
    launch: LocalFrame,
    terrain: Terrain,
    features: Vec<Feature>,
    /// The features' descriptors (`identity = "appearance"` only).
    appearance: Option<appearance::AppearanceTable>,
    /// `[world] frames = "own"`: each vehicle's estimate starts in its own frame.
    own_frames: bool,
}

impl World {
    /// Validates `cfg` and draws the terrain and features from `seed` (usually `cfg.seed`).
    pub fn new(cfg: &WorldConfig, seed: u64) -> Result<Self, ScenarioError> {
        cfg.validate().map_err(|e| e.within("world"))?;
        let launch = LocalFrame::new(Geodetic::from_degrees(
            cfg.origin.lat_deg,
            cfg.origin.lon_deg,
            cfg.origin.height_m,
        ));
        let terrain = Terrain::new(&cfg.terrain, &mut rng_stream(seed, STREAM_TERRAIN));
        let mut rng = rng_stream(seed, STREAM_FEATURES);
        let a = &cfg.area;
        let features: Vec<Feature> = (0..cfg.feature_count())
            .map(|i| {
                let n = a.centre_north_m + a.size_north_m * (rng.random::<f64>() - 0.5);
                let e = a.centre_east_m + a.size_east_m * (rng.random::<f64>() - 0.5);
                let up = terrain.height(n, e)
                    + cfg.features.max_height_above_ground_m * rng.random::<f64>();
                let position_ned = Vector3::new(n, e, -up);
                Feature {
                    id: i as FeatureId + 1,
                    position_ned,
                    position_ecef: launch.ecef_from_local(&position_ned),
                }
            })
            .collect();
        let frame = cfg.earth_model.frame();
        let mechanization = Mechanization::new(frame, cfg.local_gravity())
            .map_err(|e| ScenarioError::invalid("gravity_mps2", e.to_string()))?;
        let appearance = (cfg.appearance.identity == Identity::Appearance).then(|| {
            appearance::AppearanceTable::new(
                features.len(),
                &cfg.appearance,
                &mut rng_stream(seed, STREAM_APPEARANCE),
            )
        });
        Ok(Self {
            frame,
            mechanization,
            seed,
            launch,
            terrain,
            features,
            appearance,
            own_frames: cfg.frames == crate::scenario::Frames::Own,
        })
    }

    /// The features' appearance descriptors (`None` with perfect identities).
    pub fn appearance(&self) -> Option<&appearance::AppearanceTable> {
        self.appearance.as_ref()
    }

    /// Whether each vehicle's estimate starts in its own frame (`[world] frames = "own"`).
    pub fn own_frames(&self) -> bool {
        self.own_frames
    }

    /// The vehicles' navigation frame.
    pub fn frame(&self) -> NavFrame {
        self.frame
    }

    /// The world's physics as the mechanization describes it: rotating WGS-84 Earth, or the flat
    /// world with its gravity.
    pub fn mechanization(&self) -> &Mechanization {
        &self.mechanization
    }

    /// Gravity magnitude of the launch site [m/s²]: `[world] gravity_mps2`, or WGS-84 normal
    /// gravity at `[world.origin]` (the flat world's g; what a local-frame estimator is given).
    pub fn local_gravity(&self) -> f64 {
        self.mechanization
            .local_gravity()
            .unwrap_or_else(|| normal_gravity(self.launch.origin.lat, self.launch.origin.height))
    }

    /// The world seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// The launch site's NED frame n0.
    pub fn launch_frame(&self) -> &LocalFrame {
        &self.launch
    }

    /// The terrain surface.
    pub fn terrain(&self) -> &Terrain {
        &self.terrain
    }

    /// All features, in id order.
    pub fn features(&self) -> &[Feature] {
        &self.features
    }

    /// The feature with global id `id`, if it exists.
    pub fn feature(&self, id: FeatureId) -> Option<&Feature> {
        let i = usize::try_from(id.checked_sub(1)?).ok()?;
        self.features.get(i)
    }

    /// The team-wide origin of map information (`fusion::info`): the launch site's ECEF position
    /// in global SLAM, zero in local SLAM.
    pub fn map_origin(&self) -> Vector3<f64> {
        match self.frame {
            NavFrame::Global => self.launch.origin_ecef,
            NavFrame::Local => Vector3::zeros(),
        }
    }

    /// Navigation truth in the world's frame from a launch-frame flight state at simulation
    /// time `time` (module doc, "Frames").
    pub fn nav_truth(&self, time: f64, s: &FlightState) -> NavTruth {
        let k = &s.kinematics;
        match self.frame {
            NavFrame::Local => NavTruth {
                time,
                position: k.position,
                velocity: k.velocity,
                attitude: s.attitude,
            },
            NavFrame::Global => {
                let position = self.launch.ecef_from_local(&k.position);
                let g = ecef_to_geodetic(&position);
                let nav_from_body = ecef_from_ned(g.lat, g.lon).transpose()
                    * self.launch.ecef_from_ned
                    * nav_from_body(&s.attitude);
                NavTruth {
                    time,
                    position,
                    velocity: self.launch.ecef_from_ned * k.velocity,
                    attitude: euler_from_nav_from_body(&nav_from_body),
                }
            }
        }
    }

    /// The body's motion ([`BodyMotion`]) in the world's frame at simulation time `time` from a
    /// launch-frame flight state: C_b^e = C_{n0}^e C_b^{n0} (global) or C_b^{n0} (local).
    pub fn body_motion(&self, time: f64, s: &FlightState) -> BodyMotion {
        let (position, velocity) = self.translation(&s.kinematics);
        let launch_from_body = nav_from_body(&s.attitude);
        BodyMotion {
            time,
            position,
            velocity,
            world_from_body: match self.frame {
                NavFrame::Local => launch_from_body,
                NavFrame::Global => self.launch.ecef_from_ned * launch_from_body,
            },
        }
    }

    /// Position and velocity in the world's frame of launch-frame kinematics.
    pub fn translation(&self, k: &Kinematics) -> (Vector3<f64>, Vector3<f64>) {
        match self.frame {
            NavFrame::Local => (k.position, k.velocity),
            NavFrame::Global => (
                self.launch.ecef_from_local(&k.position),
                self.launch.ecef_from_ned * k.velocity,
            ),
        }
    }

    /// C_b^w of a truth pose: C_b^n (local) or C_b^e = C_n^e(p) C_b^n (global, eq. 21.45).
    pub fn world_from_body(&self, truth: &NavTruth) -> Matrix3<f64> {
        match self.frame {
            NavFrame::Local => nav_from_body(&truth.attitude),
            NavFrame::Global => {
                let g = ecef_to_geodetic(&truth.position);
                ecef_from_ned(g.lat, g.lon) * nav_from_body(&truth.attitude)
            }
        }
    }

    /// Launch-NED coordinates of a position in the world's frame (for outputs and plots).
    pub fn to_launch(&self, position: &Vector3<f64>) -> Vector3<f64> {
        match self.frame {
            NavFrame::Local => *position,
            NavFrame::Global => self.launch.local_from_ecef(position),
        }
    }
}

/// Builds a scenario's world (seeded with `[world].seed`) and its simulated vehicles (seeded
/// with [`vehicle_seed`]; `None` for a vehicle replayed from logs, which the simulator does not
/// touch), after validating the whole scenario.
pub fn build_parts(
    scenario: &Scenario,
) -> Result<(Arc<World>, Vec<Option<VehicleSim>>), ScenarioError> {
    scenario.validate()?;
    let world = Arc::new(World::new(&scenario.world, scenario.world.seed)?);
    let vehicles = scenario
        .vehicles
        .iter()
        .enumerate()
        .map(|(i, v)| {
            if v.replay.is_some() {
                return Ok(None);
            }
            VehicleSim::new(
                v,
                Arc::clone(&world),
                vehicle_seed(scenario.world.seed, v.id),
            )
            .map(Some)
            .map_err(|e| e.within(&format!("vehicle[{i}]")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((world, vehicles))
}

/// [`build_parts`] for a scenario whose vehicles are all simulated (an error naming the first
/// replayed vehicle otherwise).
pub fn build(scenario: &Scenario) -> Result<(Arc<World>, Vec<VehicleSim>), ScenarioError> {
    let (world, parts) = build_parts(scenario)?;
    let sims = parts
        .into_iter()
        .enumerate()
        .map(|(i, v)| {
            v.ok_or_else(|| {
                ScenarioError::invalid(
                    format!("vehicle[{i}].replay"),
                    "this needs every vehicle simulated",
                )
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((world, sims))
}

#[cfg(test)]
mod tests;
