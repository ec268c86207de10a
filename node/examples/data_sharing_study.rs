//! Study: what would each vehicle hold if the team shared its *data* (IMU increments and
//! observation frames) over the tree instead of map information?
//!
//! For every vehicle k of a scenario it runs one EKF over the whole team, as the centralized
//! reference does, but fed the way a node of a data-sharing team would be:
//!
//! - vehicle k's own samples as they happen, every other vehicle's `hop_delay_s` × (hops from
//!   k) later (the order of the team's samples at k is their arrival order; each vehicle's own
//!   samples stay in their order);
//! - the other vehicles' IMU decimated to increments of `decimation` samples (Δv and Δθ summed,
//!   a frame closes the increment so it is applied at its own time);
//! - associated as the vehicles associate (appearance, no true ids unless `ids` = `true`; the
//!   tracker ids of different vehicles kept apart).
//!
//! It prints each node's final map RMSE and map ANEES against the truth (the metrics of
//! `canopy run`'s report) and the bytes per second each vehicle's stream would take on the wire:
//! an IMU increment 36 B (t f64, Δt f32, Δv and Δθ 3 × f32); a frame 10 B plus per observation a
//! tracker id (8), a kind (1), z (12 or 8) and its 32-byte appearance descriptor.
//!
//! ```text
//! cargo run --release -p canopy-node --example data_sharing_study -- \
//!     topologies/radio-32k.toml 300 1 10 appearance
//! ```
//!
//! The figures it printed are in docs/benchmarks.md ("Eighteenth pass") and the design they
//! led to in docs/arch/sharing.md.
use std::collections::VecDeque;

use anyhow::{Context, bail};
use canopy_fusion::sensor::{ImuSample, Measurement};
use canopy_fusion::slam::SlamFilter;
use canopy_node::baseline::{reference_config, reference_setups, set_team_bearing};
use canopy_node::process::protocol::FrameAssociations;
use canopy_node::replay::SensorSource;
use canopy_node::scenario::{Identity, Scenario};
use canopy_node::truth::TruthAudit;
use nalgebra::{Matrix3, Vector3};

/// Tree hops from vehicle index `from` to every vehicle (u32::MAX: not connected).
fn hops(s: &Scenario, from: usize) -> Vec<u32> {
    let mut d = vec![u32::MAX; s.vehicles.len()];
    d[from] = 0;
    let mut queue = VecDeque::from([from]);
    while let Some(u) = queue.pop_front() {
        let uid = s.vehicles[u].id;
        for l in &s.links {
            let other = match (l.a == uid, l.b == uid) {
                (true, _) => l.b,
                (_, true) => l.a,
                _ => continue,
            };
            if let Some(v) = s.vehicles.iter().position(|x| x.id == other)
                && d[v] == u32::MAX
            {
                d[v] = d[u] + 1;
                queue.push_back(v);
            }
        }
    }
    d
}

/// An increment ([`canopy_node::sharing::Increment`]) closed after `count` samples.
#[derive(Default)]
struct Increment {
    sum: canopy_node::sharing::Increment,
    count: usize,
}

impl Increment {
    fn add(&mut self, s: &ImuSample) {
        self.sum.add(s);
        self.count += 1;
    }

    fn take(&mut self) -> Option<ImuSample> {
        self.count = 0;
        self.sum.take()
    }
}

struct Outcome {
    features: usize,
    squared_error: f64,
    nees: f64,
    bytes: Vec<usize>,
    bytes_appearance: Vec<usize>,
}

fn run_node(
    s: &Scenario,
    node: usize,
    hop_delay_s: f64,
    decimation: usize,
    true_ids: bool,
) -> anyhow::Result<Outcome> {
    let n = s.vehicles.len();
    let duration = s.run.duration_s;
    let d = hops(s, node);
    if d.contains(&u32::MAX) {
        bail!("the scenario's links do not connect every vehicle");
    }
    let (world, mut sources) = SensorSource::for_scenario(s)?;
    let setups = reference_setups(s, &sources);
    let mut cfg = reference_config(s, &world);
    if !true_ids {
        cfg.association = s.fusion.association_config(&s.world.appearance);
    }
    let mut filter = SlamFilter::new(cfg, &setups)?;
    set_team_bearing(s, &mut filter, "the study's team filter", "")?;
    let mut audit = TruthAudit::default();
    let mut applied: Vec<Increment> = (0..n).map(|_| Increment::default()).collect();
    let mut wire: Vec<Increment> = (0..n).map(|_| Increment::default()).collect();
    let mut bytes = vec![0usize; n];
    let mut bytes_appearance = vec![0usize; n];
    // The next sample to arrive at `node` (ties: scenario order).
    while let Some((vi, _)) = sources
        .iter()
        .enumerate()
        .filter_map(|(i, v)| {
            v.next_time()
                .filter(|t| *t <= duration + 1e-9)
                .map(|t| (i, t + hop_delay_s * f64::from(d[i])))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
    {
        let Some(step) = sources[vi].step() else {
            break;
        };
        let k = if vi == node { 1 } else { decimation };
        applied[vi].add(&step.imu);
        if (applied[vi].count >= k || step.frame.is_some())
            && let Some(inc) = applied[vi].take()
        {
            // A refused sample is the reference's behaviour too (it stays unapplied).
            let _ = filter.predict(vi, &inc);
        }
        wire[vi].add(&step.imu);
        if wire[vi].count >= decimation || step.frame.is_some() {
            wire[vi].take();
            bytes[vi] += 36;
        }
        let Some((frame, ids)) = &step.frame else {
            continue;
        };
        bytes[vi] += 10;
        for o in &frame.observations {
            bytes[vi] += 9 + match o.z {
                Measurement::RangeBearing(_) => 12,
                _ => 8,
            };
            if o.appearance.is_some() {
                bytes_appearance[vi] += 32;
            }
        }
        let perfect = match ids {
            Some(ids) if true_ids && s.world.appearance.identity == Identity::Appearance => {
                Some(canopy_node::world::with_true_ids(frame, ids))
            }
            _ => None,
        };
        let mut spaced = frame.clone();
        if !true_ids {
            // Tracker ids are per vehicle: keep them apart in the team filter.
            for o in &mut spaced.observations {
                o.descriptor ^= (vi as u64 + 1) << 48;
            }
        }
        if let Ok(report) = filter.process_frame(vi, perfect.as_ref().unwrap_or(&spaced)) {
            audit.frame(
                s.vehicles[vi].id,
                &FrameAssociations::from_report(frame.time, &report),
                ids.as_deref(),
            );
        }
    }
    let truth = audit.finish();
    let map = canopy_node::metrics::map_records(&world, &filter, |k| truth.truth(k));
    let mut out = Outcome {
        features: 0,
        squared_error: 0.0,
        nees: 0.0,
        bytes,
        bytes_appearance,
    };
    for f in &map {
        let Some(t) = f.truth else { continue };
        let e = Vector3::from(f.est) - Vector3::from(t);
        let cov = Matrix3::from_row_slice(&f.cov);
        let inv = cov
            .try_inverse()
            .with_context(|| format!("feature {}: covariance not invertible", f.id))?;
        out.features += 1;
        out.squared_error += e.norm_squared();
        out.nees += e.dot(&(inv * e)) / 3.0;
    }
    Ok(out)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 6 {
        bail!(
            "usage: data_sharing_study SCENARIO DURATION_S HOP_DELAY_S DECIMATION \
             (appearance|ids) [NODE_INDEX]"
        );
    }
    let mut s = Scenario::load(std::path::Path::new(&args[1]))?;
    s.run.duration_s = args[2].parse().context("DURATION_S")?;
    let hop_delay_s: f64 = args[3].parse().context("HOP_DELAY_S")?;
    let decimation: usize = args[4].parse().context("DECIMATION")?;
    if decimation == 0 {
        bail!("DECIMATION must be at least 1");
    }
    let true_ids = match args[5].as_str() {
        "ids" => true,
        "appearance" => false,
        other => bail!("association {other:?}: appearance or ids"),
    };
    let only: Option<usize> = args.get(6).map(|a| a.parse()).transpose()?;
    let t = s.run.duration_s;
    let (mut se, mut nees, mut m) = (0.0, 0.0, 0usize);
    for node in 0..s.vehicles.len() {
        if only.is_some_and(|k| k != node) {
            continue;
        }
        let o = run_node(&s, node, hop_delay_s, decimation, true_ids)?;
        let per_s = |v: &[usize]| {
            v.iter()
                .map(|b| (*b as f64 / t).round())
                .collect::<Vec<_>>()
        };
        println!(
            "{}: {} features, map RMSE {:.3} m, map ANEES {:.3}; stream B/s per vehicle {:?} \
             + appearance {:?}",
            s.vehicles[node].display_name(),
            o.features,
            (o.squared_error / o.features as f64).sqrt(),
            o.nees / o.features as f64,
            per_s(&o.bytes),
            per_s(&o.bytes_appearance),
        );
        se += o.squared_error;
        nees += o.nees;
        m += o.features;
    }
    println!(
        "pooled: map RMSE {:.3} m, map ANEES {:.3}",
        (se / m as f64).sqrt(),
        nees / m as f64
    );
    Ok(())
}
