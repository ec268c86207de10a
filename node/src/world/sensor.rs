//! The terrain sensor: which features are visible from the true pose, their noisy measurements
//! (eqs. 21.41–21.43 of the relative position of eq. 21.45), and descriptor mismatches.
//!
//! Visibility of a feature uses its noise-free relative position p^s = (x, y, z) in the sensor
//! frame: in front (x > 0), true range in [min, max], |azimuth| = |atan(y/x)| and |elevation| =
//! |atan(z/√(x²+y²))| within the half fields of view, and for a camera the noise-free pixel
//! inside the image; the noisy pixel must also fall inside the image (a detector cannot report
//! outside it), otherwise the observation is dropped. The nearest `max_observations` visible
//! features are kept. Terrain occlusion is not modelled.
//!
//! With perfect identities an observation's descriptor is the feature's true id (or, with the
//! configured probability, a wrong one); with appearance ([`super::appearance`]) it is the
//! vehicle's tracker's track id and the observation carries a noisy descriptor. The true ids
//! travel beside the frame ([`SensedFrame::true_ids`]) and must reach the monitor only.

use canopy_fusion::sensor::{
    FeatureId, Measurement, Observation, ObservationFrame, SensorModel, SensorMount,
};
use nalgebra::{Matrix3, Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::Feature;
use super::appearance::{AppearanceTable, Tracker};
use crate::scenario::SensorConfig;

/// Random (wrong) descriptors are drawn from [RANDOM_ID_BASE, 2·RANDOM_ID_BASE), a range no
/// real feature id (1..=count) reaches.
pub const RANDOM_ID_BASE: FeatureId = 1 << 40;

/// Relative position of a feature in the sensor frame, eq. 21.45:
/// p^s = C_b^s C_w^b [m^w − p^w − C_b^w p_sb^b], for any world frame w (n or e).
pub fn feature_in_sensor(
    mount: &SensorMount,
    world_from_body: &Matrix3<f64>,
    position: &Vector3<f64>,
    feature: &Vector3<f64>,
) -> Vector3<f64> {
    mount.sensor_from_body
        * world_from_body.transpose()
        * (feature - position - world_from_body * mount.lever_arm_body)
}

/// Noise-free measurement of a sensor-frame position: eq. 21.41 (range, azimuth, elevation),
/// 21.42 (azimuth, elevation) or 21.43 (pixels).
pub fn measure(model: &SensorModel, p: &Vector3<f64>) -> Measurement {
    let horiz = (p.x * p.x + p.y * p.y).sqrt();
    let az = p.y.atan2(p.x);
    let el = p.z.atan2(horiz);
    match model {
        SensorModel::RangeBearing { .. } => {
            Measurement::RangeBearing(Vector3::new(p.norm(), az, el))
        }
        SensorModel::Bearing { .. } => Measurement::Bearing(Vector2::new(az, el)),
        SensorModel::Pixel { camera, .. } => Measurement::Pixel(Vector2::new(
            camera.fu * p.y / p.x + camera.u0,
            camera.fv * p.z / p.x + camera.v0,
        )),
    }
}

/// One sensor frame with the truth the estimator must not see.
#[derive(Clone, Debug, PartialEq)]
pub struct SensedFrame {
    /// What the estimator receives.
    pub frame: ObservationFrame,
    /// True feature id of each observation, index-aligned with `frame.observations` (differs
    /// from the descriptor when a mismatch was injected).
    pub true_ids: Vec<FeatureId>,
}

/// `frame` with perfect identities: each descriptor the observation's true id, no appearance
/// (what the centralized reference is fed when the vehicles see appearance only: the
/// all-data EKF with perfect association).
pub fn with_true_ids(frame: &ObservationFrame, true_ids: &[FeatureId]) -> ObservationFrame {
    ObservationFrame {
        time: frame.time,
        observations: frame
            .observations
            .iter()
            .zip(true_ids)
            .map(|(o, &id)| Observation {
                descriptor: id,
                z: o.z,
                appearance: None,
            })
            .collect(),
    }
}

/// A vehicle's terrain sensor with its random streams.
#[derive(Clone, Debug)]
pub struct TerrainSensor {
    model: SensorModel,
    mount: SensorMount,
    min_range: f64,
    max_range: f64,
    half_fov_az: f64,
    half_fov_el: f64,
    max_observations: usize,
    mismatch_probability: f64,
    random_id_fraction: f64,
    noise: ChaCha8Rng,
    mismatch: ChaCha8Rng,
    /// Tracker and descriptor extractor (`identity = "appearance"`).
    tracker: Option<Tracker>,
}

impl TerrainSensor {
    /// A sensor from its (validated) configuration; `noise` draws measurement noise, `mismatch`
    /// the descriptor errors (separate so that turning mismatches on keeps the noise path);
    /// `tracker` gives track ids and noisy descriptors instead of true ids (appearance).
    pub fn new(
        cfg: &SensorConfig,
        noise: ChaCha8Rng,
        mismatch: ChaCha8Rng,
        tracker: Option<Tracker>,
    ) -> Self {
        Self {
            model: cfg.model(),
            mount: cfg.mount(),
            min_range: cfg.min_range_m,
            max_range: cfg.max_range_m,
            half_fov_az: cfg.half_fov_azimuth_deg.to_radians(),
            half_fov_el: cfg.half_fov_elevation_deg.to_radians(),
            max_observations: cfg.max_observations,
            mismatch_probability: cfg.mismatch_probability,
            random_id_fraction: cfg.mismatch_random_id_fraction,
            noise,
            mismatch,
            tracker,
        }
    }

    /// The measurement model.
    pub fn model(&self) -> &SensorModel {
        &self.model
    }

    /// The mount.
    pub fn mount(&self) -> &SensorMount {
        &self.mount
    }

    /// Whether a noise-free sensor-frame position is inside range and field of view (and the
    /// image, for a camera).
    pub fn visible(&self, p: &Vector3<f64>) -> bool {
        if p.x <= 0.0 {
            return false;
        }
        let range = p.norm();
        let az = p.y.atan2(p.x);
        let el = p.z.atan2((p.x * p.x + p.y * p.y).sqrt());
        let in_image = match (&self.model, measure(&self.model, p)) {
            (SensorModel::Pixel { camera, .. }, Measurement::Pixel(uv)) => {
                inside_image(camera, &uv)
            }
            _ => true,
        };
        range >= self.min_range
            && range <= self.max_range
            && az.abs() <= self.half_fov_az
            && el.abs() <= self.half_fov_el
            && in_image
    }

    /// Observes `features` (positions in the world frame w) from the true pose
    /// (`world_from_body` = C_b^w, `position` = p^w) at `time`. `appearance` holds the
    /// features' descriptors when the sensor has a tracker (index-aligned with `features`).
    pub fn observe(
        &mut self,
        time: f64,
        world_from_body: &Matrix3<f64>,
        position: &Vector3<f64>,
        features: &[Feature],
        appearance: Option<&AppearanceTable>,
        feature_position: impl Fn(&Feature) -> Vector3<f64>,
    ) -> SensedFrame {
        if let Some(t) = self.tracker.as_mut() {
            t.begin_frame();
        }
        let mut visible: Vec<(f64, usize, Vector3<f64>)> = features
            .iter()
            .enumerate()
            .filter_map(|(i, f)| {
                let p =
                    feature_in_sensor(&self.mount, world_from_body, position, &feature_position(f));
                self.visible(&p).then(|| (p.norm(), i, p))
            })
            .collect();
        visible.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        visible.truncate(self.max_observations);
        let mut observations = Vec::with_capacity(visible.len());
        let mut true_ids = Vec::with_capacity(visible.len());
        for (_, i, p) in visible {
            let Some(z) = self.noisy(&measure(&self.model, &p)) else {
                continue;
            };
            let id = features[i].id;
            let described = match (self.tracker.as_mut(), appearance) {
                (Some(tracker), Some(table)) => table.descriptor(i).map(|truth| {
                    // Unit line of sight sensor → feature in the world frame.
                    let los = world_from_body * self.mount.sensor_from_body.transpose() * p;
                    tracker.describe(id, truth, p.norm(), &los.normalize())
                }),
                _ => None,
            };
            observations.push(match described {
                Some(d) => Observation {
                    descriptor: d.track,
                    z,
                    appearance: Some(d.appearance),
                },
                None => Observation {
                    descriptor: self.descriptor(id, features),
                    z,
                    appearance: None,
                },
            });
            true_ids.push(id);
        }
        SensedFrame {
            frame: ObservationFrame { time, observations },
            true_ids,
        }
    }

    /// Adds measurement noise; `None` when a noisy pixel leaves the image.
    fn noisy(&mut self, z: &Measurement) -> Option<Measurement> {
        let mut n = || -> f64 { self.noise.sample(StandardNormal) };
        match (z, &self.model) {
            (
                Measurement::RangeBearing(m),
                SensorModel::RangeBearing {
                    sigma_range,
                    sigma_bearing,
                },
            ) => Some(Measurement::RangeBearing(
                m + Vector3::new(n() * sigma_range, n() * sigma_bearing, n() * sigma_bearing),
            )),
            (Measurement::Bearing(m), SensorModel::Bearing { sigma_bearing }) => Some(
                Measurement::Bearing(m + Vector2::new(n() * sigma_bearing, n() * sigma_bearing)),
            ),
            (
                Measurement::Pixel(m),
                SensorModel::Pixel {
                    camera,
                    sigma_pixel,
                },
            ) => {
                let uv = m + Vector2::new(n() * sigma_pixel, n() * sigma_pixel);
                inside_image(camera, &uv).then_some(Measurement::Pixel(uv))
            }
            // `measure` always returns the variant of the model.
            _ => unreachable!("measurement kind differs from the sensor model"),
        }
    }

    /// The descriptor the sensor reports for feature `id`: right, or (with the configured
    /// probability) another feature's id or a random id naming no feature.
    fn descriptor(&mut self, id: FeatureId, features: &[Feature]) -> FeatureId {
        if self.mismatch_probability <= 0.0
            || self.mismatch.random::<f64>() >= self.mismatch_probability
        {
            return id;
        }
        let random_id =
            features.len() < 2 || self.mismatch.random::<f64>() < self.random_id_fraction;
        if random_id {
            return RANDOM_ID_BASE + self.mismatch.random_range(0..RANDOM_ID_BASE);
        }
        // Uniform over the other features.
        let own = features.iter().position(|f| f.id == id).unwrap_or(0);
        let mut k = self.mismatch.random_range(0..features.len() - 1);
        if k >= own {
            k += 1;
        }
        features[k].id
    }
}

fn inside_image(camera: &canopy_fusion::sensor::CameraIntrinsics, uv: &Vector2<f64>) -> bool {
    uv.x >= 0.0 && uv.x < camera.width && uv.y >= 0.0 && uv.y < camera.height
}
