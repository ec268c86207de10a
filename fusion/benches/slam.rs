//! SLAM cost table (a `harness = false` bench printing one table per measurement):
//!
//! 0. The INS step alone (mean and Jacobians of one sample) in the global and local frames.
//! 1. IMU prediction per sample at N = 50, 100, 200, 400 features: the filter's lazy prediction
//!    (flushed once per 20 samples, i.e. a 5 Hz terrain frame at 100 Hz IMU), the eager variant
//!    (flushed every sample), and the naive dense ∇F P ∇Fᵀ + ∇G Q ∇Gᵀ measured side by side.
//! 2. EKF update cost per observation vs N (descriptor association, 10 observations per frame),
//!    and association + update per 20-observation frame for descriptor, NN and JCBB.
//! 3. Fuse-back of received map information vs a raw faer Cholesky inverse of the 3N×3N map
//!    covariance, for a delta on 10 features and on the whole map, and one fusion round
//!    (map information from the filter → delta → fuse back), for both delta sizes.
//!
//! Run: `cargo bench -p canopy-fusion --bench slam`. Times are medians of repeated runs, with
//! the process set-up of every canopy process (`canopy_fusion::runtime`: subnormals flushed to
//! zero, heap kept mapped) for both sides of each ratio.

use canopy_fusion::ddf::{DdfConfig, DdfNode, FuseTarget, Outgoing};
use canopy_fusion::imu::ImuGrade;
use canopy_fusion::info::MapInformation;
use canopy_fusion::ins::{self, VehicleCovariance, VehicleState};
use canopy_fusion::sensor::{
    FeatureId, ImuSample, Measurement, Observation, ObservationFrame, SensorModel, SensorMount,
};
use canopy_fusion::slam::{
    AssociationConfig, AssociationMode, SlamConfig, SlamFilter, VehicleSetup,
};
use canopy_fusion::state::{NavFrame, VEHICLE_DIM};
use canopy_fusion::topology::NodeId;
use faer::linalg::solvers::DenseSolveCore;
use faer::{Col, Mat, Side};
use nalgebra::Vector3;
use std::hint::black_box;
use std::time::Instant;

/// A DDF node of the vehicle with one neighbour, the channel synchronised, so that every
/// `on_round` computes and encodes the delta Y − C for the neighbour (the round's DDF step).
fn synced_channel(origin: Vector3<f64>) -> DdfNode {
    let (a_id, b_id) = (NodeId(1), NodeId(2));
    let mut a = DdfNode::new(a_id, 11, [b_id], origin, DdfConfig::default());
    let mut b = DdfNode::new(b_id, 22, [a_id], origin, DdfConfig::default());
    let mut ya = MapInformation::zero(origin);
    let mut yb = MapInformation::zero(origin);
    let mut queue: Vec<(NodeId, Outgoing)> = Vec::new();
    queue.extend(
        a.on_link_up(0.0, b_id)
            .unwrap()
            .into_iter()
            .map(|o| (a_id, o)),
    );
    queue.extend(
        b.on_link_up(0.0, a_id)
            .unwrap()
            .into_iter()
            .map(|o| (b_id, o)),
    );
    while let Some((from, o)) = queue.pop() {
        let (node, est): (&mut DdfNode, &mut dyn FuseTarget) = if o.to == a_id {
            (&mut a, &mut ya)
        } else {
            (&mut b, &mut yb)
        };
        let replies = node.on_message(0.0, from, o.message, est).unwrap();
        queue.extend(replies.into_iter().map(|r| (o.to, r)));
    }
    assert!(a.channel(b_id).unwrap().synced);
    a
}

fn median_time(reps: usize, mut f: impl FnMut()) -> f64 {
    let mut t: Vec<f64> = (0..reps)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn setup() -> VehicleSetup {
    // 1 m position, 0.1 m/s velocity, 1 mrad attitude, tactical-grade biases (1-σ).
    let diag = [
        1.0, 1.0, 1.0, 0.01, 0.01, 0.01, 1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4, 1e-10, 1e-10, 1e-10,
    ];
    let cov =
        VehicleCovariance::from_diagonal(&nalgebra::SVector::<f64, 15>::from_column_slice(&diag));
    VehicleSetup {
        state: VehicleState {
            position: Vector3::new(0.0, 0.0, -100.0),
            velocity: Vector3::new(20.0, 0.0, 0.0),
            attitude: Vector3::new(0.01, 0.02, 0.3),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        },
        covariance: cov,
        imu_noise: ImuGrade::Tactical.noise(),
        sensor: SensorModel::RangeBearing {
            sigma_range: 0.5,
            sigma_bearing: 0.002,
        },
        mount: SensorMount::downward(Vector3::new(0.3, 0.0, 0.2)),
    }
}

/// A filter with `n` features below the vehicle, with a dense correlated map covariance (the
/// features are fused in as one dense information delta).
fn filter(n: usize) -> SlamFilter {
    filter_with(n, AssociationMode::Descriptor)
}

fn filter_with(n: usize, mode: AssociationMode) -> SlamFilter {
    let cfg = SlamConfig {
        frame: NavFrame::Local,
        local_gravity_mps2: 9.81,
        origin: Vector3::zeros(),
        association: AssociationConfig {
            mode,
            gate_probability: 0.95,
            ..AssociationConfig::default()
        },
        fresh_id_namespace: 0,
    };
    let mut f = SlamFilter::new(cfg, &[setup()]).unwrap();
    let k = 3 * n;
    // Y = 4 I + 0.5 · (ones-ish coupling): SPD and dense.
    let y = Mat::from_fn(k, k, |i, j| {
        if i == j {
            4.0
        } else {
            0.5 / (1.0 + (i as f64 - j as f64).abs())
        }
    });
    let target = Col::from_fn(k, |i| match i % 3 {
        0 => ((i / 3) % 20) as f64 * 5.0 - 50.0,
        1 => ((i / 3) / 20) as f64 * 5.0 - 50.0,
        _ => 0.0,
    });
    let vector = &y * &target;
    let delta = MapInformation {
        ids: (0..n as FeatureId).collect(),
        origin: Vector3::zeros(),
        matrix: y,
        vector,
    };
    f.fuse_map_information(&delta).unwrap();
    f
}

fn imu() -> ImuSample {
    ImuSample {
        time: 0.0,
        dt: 0.01,
        specific_force: Vector3::new(0.1, 0.0, -9.81),
        angular_rate: Vector3::new(0.0, 0.0, 0.01),
    }
}

fn main() {
    // As every canopy process does (`canopy_fusion::runtime`), for canopy's code and the raw
    // faer reference alike.
    canopy_fusion::runtime::tune_allocator();
    canopy_fusion::runtime::flush_subnormals_to_zero();
    println!("## INS step alone: mean, ∇F and ∇G of one IMU sample");
    println!("| frame | per sample [µs] |");
    println!("|---|---|");
    let site = canopy_fusion::geodesy::Geodetic::from_degrees(58.0, 14.0, 100.0);
    let turning = ImuSample {
        angular_rate: Vector3::new(0.02, -0.01, 0.1),
        ..imu()
    };
    for (name, m, position) in [
        (
            "global",
            ins::Mechanization::global(),
            canopy_fusion::geodesy::geodetic_to_ecef(&site),
        ),
        (
            "local",
            ins::Mechanization::local(9.81).unwrap(),
            Vector3::new(10.0, -20.0, -150.0),
        ),
    ] {
        let x = VehicleState {
            position,
            velocity: Vector3::new(14.0, 3.0, -1.0),
            attitude: Vector3::new(0.1, 0.05, 1.2),
            accel_bias: Vector3::zeros(),
            gyro_bias: Vector3::zeros(),
        };
        let per = median_time(15, || {
            for _ in 0..1000 {
                black_box(ins::propagate_with_jacobians(&m, black_box(&x), &turning).unwrap());
            }
        }) / 1000.0;
        println!("| {name} | {:.3} |", per * 1e6);
    }
    let sizes = [50usize, 100, 200, 400];
    println!("## IMU prediction per sample (N features, n = 15 + 3N states)");
    println!(
        "| N | n | lazy (flush/20) [µs] | eager (flush/1) [µs] | naive dense [ms] | dense / lazy | dense / eager |"
    );
    println!("|---|---|---|---|---|---|---|");
    for &n_feat in &sizes {
        let mut f = filter(n_feat);
        let n = f.dim();
        let sample = imu();
        // Lazy: 20 predictions then the flush a frame would trigger, per sample.
        let lazy = median_time(15, || {
            for _ in 0..20 {
                f.predict(0, &sample).unwrap();
            }
            f.flush();
        }) / 20.0;
        let eager = median_time(15, || {
            for _ in 0..20 {
                f.predict(0, &sample).unwrap();
                f.flush();
            }
        }) / 20.0;
        // Naive: full n×n ∇F and n×12 ∇G, dense products.
        let prop =
            ins::propagate_with_jacobians(f.mechanization(), &f.vehicle_state(0).unwrap(), &sample)
                .unwrap();
        let q = ins::process_noise(&ImuGrade::Tactical.noise(), sample.dt);
        let mut ff = Mat::<f64>::identity(n, n);
        let mut gg = Mat::<f64>::zeros(n, 12);
        for i in 0..VEHICLE_DIM {
            for j in 0..VEHICLE_DIM {
                ff[(i, j)] = prop.transition[(i, j)];
            }
            for j in 0..12 {
                gg[(i, j)] = prop.noise[(i, j)];
            }
        }
        let qf = Mat::from_fn(12, 12, |i, j| q[(i, j)]);
        let p = f.joint_covariance();
        let reps = if n_feat >= 200 { 3 } else { 5 };
        let dense = median_time(reps, || {
            let out = &ff * &p * ff.transpose() + &gg * &qf * gg.transpose();
            black_box(out);
        });
        println!(
            "| {n_feat} | {n} | {:.2} | {:.1} | {:.2} | {:.0} | {:.0} |",
            lazy * 1e6,
            eager * 1e6,
            dense * 1e3,
            dense / lazy,
            dense / eager
        );
    }

    println!("\n## EKF update per observation (10 observations per frame, stacked Joseph update)");
    println!("| N | n | per frame [ms] | per observation [ms] |");
    println!("|---|---|---|---|");
    for &n_feat in &[50usize, 100, 200, 400, 800] {
        let mut f = filter(n_feat);
        let model = *f.observation_model(0).unwrap();
        let ids: Vec<FeatureId> = (0..10).map(|i| (i * 7 % n_feat) as FeatureId).collect();
        let frame_for = |f: &SlamFilter| {
            let s = f.vehicle_state(0).unwrap();
            let pose = model.sensor_pose(&s.position, &s.attitude);
            let observations = ids
                .iter()
                .map(|id| {
                    let z = model.predict(&pose, &f.feature(*id).unwrap()).unwrap().z;
                    Observation {
                        descriptor: *id,
                        z: Measurement::RangeBearing(Vector3::new(z[0] + 0.1, z[1], z[2])),
                        appearance: None,
                    }
                })
                .collect();
            ObservationFrame {
                time: 0.0,
                observations,
            }
        };
        let t = median_time(9, || {
            let fr = frame_for(&f);
            let r = f.process_frame(0, &fr).unwrap();
            assert_eq!(r.associated(), 10);
        });
        println!(
            "| {n_feat} | {} | {:.3} | {:.3} |",
            f.dim(),
            t * 1e3,
            t * 1e3 / 10.0
        );
    }

    println!("\n## Association + update per frame of 20 observations (descriptor vs NN vs JCBB)");
    println!("| N | descriptor [ms] | nearest neighbour [ms] | JCBB [ms] | JCBB nodes |");
    println!("|---|---|---|---|---|");
    for &n_feat in &[100usize, 400] {
        let mut row = Vec::new();
        let mut nodes = 0;
        for mode in [
            AssociationMode::Descriptor,
            AssociationMode::NearestNeighbour,
            AssociationMode::Jcbb { max_nodes: 100_000 },
        ] {
            let mut f = filter_with(n_feat, mode);
            let model = *f.observation_model(0).unwrap();
            let ids: Vec<FeatureId> = (0..20).map(|i| (i * 5 % n_feat) as FeatureId).collect();
            let s = f.vehicle_state(0).unwrap();
            let pose = model.sensor_pose(&s.position, &s.attitude);
            let observations: Vec<Observation> = ids
                .iter()
                .map(|id| {
                    let z = model.predict(&pose, &f.feature(*id).unwrap()).unwrap().z;
                    Observation {
                        descriptor: *id,
                        z: Measurement::RangeBearing(Vector3::new(z[0] + 0.1, z[1], z[2])),
                        appearance: None,
                    }
                })
                .collect();
            let frame = ObservationFrame {
                time: 0.0,
                observations,
            };
            let t = median_time(5, || {
                let mut g = f.clone();
                let r = g.process_frame(0, &frame).unwrap();
                nodes = r.jcbb_nodes;
                black_box(r);
            });
            // Subtract the clone so only association + update is timed.
            let c = median_time(5, || {
                black_box(f.clone());
            });
            row.push((t - c) * 1e3);
            f.flush();
        }
        println!(
            "| {n_feat} | {:.2} | {:.2} | {:.2} | {nodes} |",
            row[0], row[1], row[2]
        );
    }

    println!(
        "\n## One fusion round with the EKF vs a raw faer Cholesky inverse of the 3N×3N map covariance"
    );
    println!(
        "Between rounds the vehicle processes 2 frames of 8 observations (untimed); a round is \
         `map_information()` (Y_mm) + the DDF channel's delta Y − C for one neighbour + fusing a \
         neighbour's delta back. `maintained`: Y_mm \
         kept current through the updates (Woodbury, bordered inverse, Y + ΔY); `re-inverted`: the \
         cache dropped before the round (two inversions per round)."
    );
    println!(
        "| N | Cholesky inverse [ms] | round, 10-feature delta, maintained [ms] | / inverse | round, whole-map delta, maintained [ms] | / inverse | round, whole-map, re-inverted [ms] | / inverse | frame with Y maintained [ms] | frame without [ms] |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for &n_feat in &[100usize, 300] {
        let mut f = filter(n_feat);
        let model = *f.observation_model(0).unwrap();
        let make_delta = |f: &SlamFilter, ids: Vec<FeatureId>| {
            let r = 3 * ids.len();
            let y = Mat::from_fn(r, r, |i, j| {
                if i == j {
                    0.05
                } else {
                    0.005 / (1.0 + (i as f64 - j as f64).abs())
                }
            });
            let x = Col::from_fn(r, |i| f.feature(ids[i / 3]).unwrap()[i % 3]);
            let vector = &y * &x;
            MapInformation {
                ids,
                origin: Vector3::zeros(),
                matrix: y,
                vector,
            }
        };
        let frame_for = |f: &SlamFilter, k: usize| {
            let s = f.vehicle_state(0).unwrap();
            let pose = model.sensor_pose(&s.position, &s.attitude);
            let observations = (0..8)
                .map(|i| {
                    let id = ((k * 8 + i) * 7 % n_feat) as FeatureId;
                    let z = model.predict(&pose, &f.feature(id).unwrap()).unwrap().z;
                    Observation {
                        descriptor: id,
                        z: Measurement::RangeBearing(Vector3::new(z[0] + 0.05, z[1], z[2])),
                        appearance: None,
                    }
                })
                .collect();
            ObservationFrame {
                time: 0.0,
                observations,
            }
        };
        let small_ids: Vec<FeatureId> = (0..10).map(|i| (i * 13 % n_feat) as FeatureId).collect();
        let all_ids: Vec<FeatureId> = (0..n_feat as FeatureId).collect();
        let time = |g: &mut dyn FnMut()| {
            let s = Instant::now();
            g();
            s.elapsed().as_secs_f64()
        };
        let reps = 7;
        // Interleaved rep by rep on the shared machine; medians per column.
        let mut t = vec![Vec::new(); 6];
        f.map_information().unwrap();
        let mut node = synced_channel(f.config().origin);
        for rep in 0..reps {
            let mm = f.map_marginal();
            t[0].push(time(&mut || {
                black_box(mm.covariance.llt(Side::Lower).unwrap().inverse());
            }));
            for (col, ids, forget) in [
                (1, &small_ids, false),
                (2, &all_ids, false),
                (3, &all_ids, true),
            ] {
                if forget {
                    f.forget_map_information();
                }
                for k in 0..2 {
                    let fr = frame_for(&f, rep * 2 + k);
                    let dt = time(&mut || {
                        f.process_frame(0, &fr).unwrap();
                    });
                    t[if forget { 5 } else { 4 }].push(dt);
                }
                let d = make_delta(&f, ids.clone());
                let now = (3 * rep + col) as f64;
                t[col].push(time(&mut || {
                    black_box(node.on_round(now, &mut f).unwrap());
                    f.fuse_map_information(&d).unwrap();
                }));
            }
        }
        let med: Vec<f64> = t
            .into_iter()
            .map(|mut v| {
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            })
            .collect();
        println!(
            "| {n_feat} (3N = {}) | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {:.3} |",
            3 * n_feat,
            med[0] * 1e3,
            med[1] * 1e3,
            med[1] / med[0],
            med[2] * 1e3,
            med[2] / med[0],
            med[3] * 1e3,
            med[3] / med[0],
            med[4] * 1e3,
            med[5] * 1e3,
        );
    }
}
