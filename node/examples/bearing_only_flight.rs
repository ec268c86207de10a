//! A 10-minute bearing-only flight: the world simulator's default survey vehicle with a
//! bearing-only (or pixel) sensor, driving one `SlamFilter`. Prints the state size over time
//! (map features, stored poses, uninitialized tracks) and the wall time per camera frame at the
//! end of the run, to show that stored poses stay bounded.
//!
//! ```sh
//! cargo run --release -p canopy-node --example bearing_only_flight [-- pixel|bearing [SECONDS]]
//! ```

use canopy_fusion::ins::VehicleState;
use canopy_fusion::slam::{
    AssociationConfig, AssociationMode, SlamConfig, SlamFilter, VehicleSetup,
};
use canopy_node::scenario::{Scenario, SensorModelConfig};
use canopy_node::world;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let kind = args.get(1).map(String::as_str).unwrap_or("bearing");
    let duration: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(600.0);
    let mut scn = Scenario::builtin_default();
    scn.vehicles.truncate(1);
    scn.vehicles[0].sensor.model = match kind {
        "pixel" => SensorModelConfig::vga_camera(1.0),
        _ => SensorModelConfig::Bearing {
            sigma_bearing_deg: 0.2,
        },
    };
    let (world, mut sims) = world::build(&scn).expect("valid scenario");
    let sim = &mut sims[0];
    let init = sim.initial_estimate().clone();
    let setup = VehicleSetup {
        state: VehicleState {
            position: init.position,
            velocity: init.velocity,
            attitude: init.attitude,
            accel_bias: init.accel_bias,
            gyro_bias: init.gyro_bias,
        },
        covariance: init.covariance,
        imu_noise: scn.vehicles[0].imu.noise_model(),
        sensor: sim.sensor_model(),
        mount: sim.sensor_mount(),
    };
    let mut filter = SlamFilter::new(
        SlamConfig {
            frame: world.frame(),
            local_gravity_mps2: world.local_gravity(),
            origin: world.map_origin(),
            association: AssociationConfig {
                mode: AssociationMode::Descriptor,
                gate_probability: 0.95,
                ..AssociationConfig::default()
            },
            fresh_id_namespace: 1,
        },
        &[setup],
    )
    .expect("valid filter");
    println!(
        "{kind} sensor, {} frame, {duration} s, bearing config {:?}",
        world.frame(),
        filter.bearing_config()
    );
    println!("   t [s]  features  poses  tracks  dim  frame [ms] (mean of the last minute)");
    let steps = (duration / sim.imu_dt()).round() as u64;
    let (mut frame_time, mut frames, mut last_max) = (0.0, 0u32, 0.0f64);
    let mut predict_time = 0.0;
    let mut predicts = 0u32;
    for k in 1..=steps {
        let out = sim.step();
        let t0 = Instant::now();
        filter.predict(0, &out.imu).expect("valid IMU sample");
        predict_time += t0.elapsed().as_secs_f64();
        predicts += 1;
        if let Some(sf) = out.frame {
            let t0 = Instant::now();
            filter.process_frame(0, &sf.frame).expect("valid frame");
            let dt = t0.elapsed().as_secs_f64();
            frame_time += dt;
            frames += 1;
            last_max = last_max.max(dt);
        }
        let t = k as f64 * sim.imu_dt();
        if k % (60.0 / sim.imu_dt()).round() as u64 == 0 || k == steps {
            println!(
                "{t:8.1}  {:8}  {:5}  {:6}  {:4}  {:.3} (max {:.3}), predict {:.1} µs",
                filter.num_features(),
                filter.num_stored_poses(),
                filter.num_tracks(),
                filter.dim(),
                1e3 * frame_time / frames.max(1) as f64,
                1e3 * last_max,
                1e6 * predict_time / predicts.max(1) as f64,
            );
            (frame_time, frames, last_max, predict_time, predicts) = (0.0, 0, 0.0, 0.0, 0);
        }
    }
    let s = filter.bearing_stats();
    println!(
        "max stored poses {} (cap {})",
        s.max_stored_poses,
        filter.bearing_config().max_stored_poses
    );
    println!("{s:#?}");
}
