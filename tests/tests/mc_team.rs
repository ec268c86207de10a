//! Full multi-vehicle SLAM, 4-vehicle tree (the default scenario), default noise, 10 seeds
//! (issue: decentralized data fusion core). Each seed draws a new world and new noise; the
//! decentralized run has the centralized all-data EKF alongside (fed the same IMU samples and
//! observation frames), and the same seed is also run isolated (no fusion).

use canopy_node::network::FusionMode;
use canopy_node::output::summary::summarize_vehicle;
use canopy_node::record::VehicleRecord;
use canopy_node::scenario::Scenario;
use canopy_node::sim::{SimOptions, SimOutcome, simulate};
use canopy_tests::montecarlo::{map_consistency, pose_consistency};

const SEEDS: u64 = 10;
/// Simulated seconds per run: every UAV's map overlaps its neighbours' within the first minute.
const DURATION: f64 = 120.0;

fn run(seed: u64, mode: FusionMode) -> SimOutcome {
    let mut s = Scenario::builtin_default();
    s.world.seed = seed;
    s.run.duration_s = DURATION;
    s.fusion.mode = mode;
    s.run.baseline = mode == FusionMode::Decentralized;
    if mode == FusionMode::Isolated {
        s.links.clear();
    }
    simulate(&s, SimOptions::default()).expect("simulation runs")
}

fn pooled_map_rmse(records: &[&VehicleRecord]) -> f64 {
    map_consistency(records).rmse
}

/// Decentralized fusion matches the centralized all-data EKF: map RMSE within 5 %, vehicle pose
/// ANEES within 20 % (the vehicles fuse map marginals with up to `diameter` rounds of delay
/// instead of one joint filter; double counting would inflate ANEES far beyond that), no vehicle
/// ever more confident about a feature than the reference by more than 20 % (linearisation
/// points differ between the filters; counting information twice would show as ≈ 2), zero wrong
/// associations; and isolated vehicles are measurably worse (the benefit of fusion).
#[test]
fn decentralized_matches_central_and_beats_isolated() {
    let dec: Vec<SimOutcome> = (1..=SEEDS)
        .map(|s| run(s, FusionMode::Decentralized))
        .collect();
    let iso: Vec<SimOutcome> = (1..=SEEDS).map(|s| run(s, FusionMode::Isolated)).collect();
    let dec_v: Vec<&VehicleRecord> = dec.iter().flat_map(|o| o.record.vehicles.iter()).collect();
    let iso_v: Vec<&VehicleRecord> = iso.iter().flat_map(|o| o.record.vehicles.iter()).collect();
    // The reference's map is one joint map: count it once per seed.
    let cen_map: Vec<&VehicleRecord> = dec
        .iter()
        .map(|o| &o.record.baseline.as_ref().expect("baseline ran")[0])
        .collect();
    let cen_v: Vec<&VehicleRecord> = dec
        .iter()
        .flat_map(|o| o.record.baseline.as_ref().expect("baseline ran").iter())
        .collect();

    let map_dec = pooled_map_rmse(&dec_v);
    let map_cen = pooled_map_rmse(&cen_map);
    let map_iso = pooled_map_rmse(&iso_v);
    let anees = |rs: &[&VehicleRecord]| {
        rs.iter()
            .map(|r| summarize_vehicle(r).pose_anees)
            .sum::<f64>()
            / rs.len() as f64
    };
    let pos = |rs: &[&VehicleRecord]| pose_consistency(rs, 0.0).position_rmse;
    let (anees_dec, anees_cen, anees_iso) = (anees(&dec_v), anees(&cen_v), anees(&iso_v));
    let (pos_dec, pos_cen, pos_iso) = (pos(&dec_v), pos(&cen_v), pos(&iso_v));
    let ratio = dec
        .iter()
        .flat_map(|o| o.checks.confidence_ratio.iter().map(|p| p.1))
        .fold(0.0, f64::max);
    let wrong: u64 = dec_v.iter().map(|r| r.association.wrong_associations).sum();
    let bytes: u64 = dec
        .iter()
        .flat_map(|o| o.record.links.iter())
        .map(|l| l.samples.last().map_or(0, |s| s.bytes_ab + s.bytes_ba))
        .sum();
    let rounds = SEEDS as f64 * DURATION * 3.0; // 3 links, 1 round/s
    println!("{SEEDS} seeds × {DURATION} s, 4-UAV tree:");
    println!(
        "  map RMSE  decentralized {map_dec:.3} m, central {map_cen:.3} m (ratio {:.3}), isolated {map_iso:.3} m",
        map_dec / map_cen
    );
    println!(
        "  position RMSE decentralized {pos_dec:.3} m, central {pos_cen:.3} m, isolated {pos_iso:.3} m"
    );
    println!(
        "  pose ANEES/6 decentralized {anees_dec:.3}, central {anees_cen:.3}, isolated {anees_iso:.3}"
    );
    println!("  max feature confidence ratio vs central {ratio:.3}; wrong associations {wrong}");
    println!(
        "  link bytes per round per link {:.0}",
        bytes as f64 / rounds
    );
    assert!(
        map_dec <= 1.05 * map_cen,
        "map RMSE {map_dec} > 1.05 × {map_cen}"
    );
    assert!(
        anees_dec <= 1.2 * anees_cen,
        "pose ANEES {anees_dec} > 1.2 × {anees_cen}"
    );
    assert!(
        ratio <= 1.2,
        "a vehicle is {ratio}× more confident than the centralized EKF"
    );
    assert_eq!(wrong, 0);
    // Benefit of fusion: isolated maps and positions at least 30 % worse.
    assert!(
        map_iso >= 1.3 * map_dec,
        "isolated map RMSE {map_iso} not clearly worse than {map_dec}"
    );
    assert!(
        pos_iso >= 1.3 * pos_dec,
        "isolated position RMSE {pos_iso} not clearly worse than {pos_dec}"
    );
}

/// Lossy mode: f32 deltas (deflated so they never carry more information than exact) keep the
/// team consistent — pose ANEES of 5 seeds × 4 UAVs in the χ² band for that many runs, map
/// ANEES no higher than the exact mode's by more than 10 % — and accurate (map RMSE within 5 %
/// of the exact mode on the same seeds), at fewer bytes.
#[test]
fn f32_deltas_stay_consistent() {
    use canopy_fusion::ddf::DeltaPrecision;
    let run_with = |seed: u64, precision: DeltaPrecision| {
        let mut s = Scenario::builtin_default();
        s.world.seed = seed;
        s.run.duration_s = DURATION;
        s.run.baseline = false;
        s.fusion.delta_precision = precision;
        simulate(&s, SimOptions::default()).expect("simulation runs")
    };
    let seeds = 1..=5u64;
    let exact: Vec<SimOutcome> = seeds
        .clone()
        .map(|s| run_with(s, DeltaPrecision::F64))
        .collect();
    let lossy: Vec<SimOutcome> = seeds.map(|s| run_with(s, DeltaPrecision::F32)).collect();
    let bytes = |o: &[SimOutcome]| -> u64 {
        o.iter()
            .flat_map(|o| o.record.links.iter())
            .map(|l| l.samples.last().map_or(0, |s| s.bytes_ab + s.bytes_ba))
            .sum()
    };
    fn recs(o: &[SimOutcome]) -> Vec<&VehicleRecord> {
        o.iter().flat_map(|o| o.record.vehicles.iter()).collect()
    }
    let (re, rl) = (recs(&exact), recs(&lossy));
    let pose = pose_consistency(&rl, 0.0);
    let (me, ml) = (map_consistency(&re), map_consistency(&rl));
    println!(
        "f32 vs f64 deltas, 5 seeds × {DURATION} s: pose ANEES/6 {:.3} (band [{:.3}, {:.3}]); map ANEES/3 {:.3} vs {:.3}; \
         map RMSE {:.3} vs {:.3} m; link bytes {} vs {} ({:.2}×)",
        pose.time_mean,
        pose.band.0,
        pose.band.1,
        ml.anees,
        me.anees,
        ml.rmse,
        me.rmse,
        bytes(&lossy),
        bytes(&exact),
        bytes(&lossy) as f64 / bytes(&exact) as f64
    );
    assert!(
        pose.time_mean >= pose.band.0 && pose.time_mean <= pose.band.1,
        "pose ANEES {:.3} outside {:?}",
        pose.time_mean,
        pose.band
    );
    assert!(
        ml.anees <= 1.1 * me.anees,
        "map ANEES {:.3} vs exact {:.3}",
        ml.anees,
        me.anees
    );
    assert!(
        ml.rmse <= 1.05 * me.rmse,
        "map RMSE {:.3} vs exact {:.3}",
        ml.rmse,
        me.rmse
    );
    assert!(bytes(&lossy) < bytes(&exact));
}
