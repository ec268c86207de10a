//! Association without the simulator's identities on the shipped scenarios, under `canopy sim`
//! (issue 12): the default team (`topologies/tree-4.toml`, simulated appearance), its
//! perfect-identity ablation (`topologies/perfect-4.toml`, same seed, same observations) and the
//! hard variant (`topologies/appearance-hard-4.toml`: 10 % confusable features, bit flips up to
//! 20 %, tracks breaking every few frames).
//!
//! What it proves:
//! * the estimators never see a true id (every map key is a vehicle's own key) and every frame
//!   is judged against the truth;
//! * with the vehicles finding their correspondences themselves, both appearance runs meet
//!   issue 12's bars against the perfect-identity run: team map RMSE ≤ 1.10×, pose and map
//!   ANEES ≤ 1.1×, no wrong correspondence fused, mature duplicates ≤ 2 %, and no vehicle more
//!   confident than the centralized all-data reference;
//! * the hard run counts the candidate correspondences it refused;
//! * where correspondences have to be found — `topologies/partition-heal.toml`, whose two
//!   halves map the same ground apart for 35 s — they are (every one right), and the same bars
//!   hold against that scenario's perfect-identity run;
//! * the audit can fail: with the correspondence search switched off (`[fusion]
//!   map_correspondences = false`, the ablation) the features the halves initialised apart
//!   stay duplicated, and the audit reports them.
//!
//! Runtime (release): 3 × 120 s and 3 × 90 s of the 4-UAV team with the reference, ≈ 1 min on
//! an idle 2-core machine.

use std::path::Path;

use canopy_node::output::summary::{Summary as RunSummary, summarize};
use canopy_node::scenario::{Identity, Scenario};
use canopy_node::sim::{SimOptions, SimOutcome, simulate};

/// Long enough that every vehicle's map overlaps its neighbours' and features mature (held
/// ≥ 10 s).
const DURATION: f64 = 120.0;

fn shipped(name: &str) -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../topologies/{name}.toml"));
    Scenario::load(&path).unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn sim(s: &Scenario) -> (SimOutcome, RunSummary) {
    let out = simulate(
        s,
        SimOptions {
            duration: Some(DURATION.min(s.run.duration_s)),
            ..SimOptions::default()
        },
    )
    .expect("simulation runs");
    let summary = summarize(&out.record);
    (out, summary)
}

fn max_ratio(out: &SimOutcome) -> f64 {
    out.checks
        .confidence_ratio
        .iter()
        .map(|x| x.1)
        .fold(f64::NAN, f64::max)
}

fn print(name: &str, out: &SimOutcome, sm: &RunSummary) {
    let a = &sm.association;
    println!(
        "{name}: map RMSE {:.3} m, position RMSE {:.3} m, pose ANEES {:.2}, map ANEES {:.2}; \
         wrong associations {} of {}; correspondences adopted {} (wrong {}, cross-vehicle wrong \
         {}); duplicates {} (mature {} of {}, share {:.3}); unmatched {}; max confidence ratio \
         {:.3}",
        sm.team.map_rmse_m,
        sm.team.position_rmse_m,
        sm.team.pose_anees,
        sm.team.map_anees,
        a.wrong_associations,
        a.observations,
        a.merges_adopted,
        a.wrong_merges,
        a.wrong_cross_vehicle_merges,
        a.duplicate_features,
        a.mature_duplicates,
        a.mature_features,
        a.mature_duplicate_share,
        a.unmatched_features,
        max_ratio(out),
    );
}

/// Candidate correspondences a run refused, summed over the vehicles (`fusion.correspondence.*`).
fn refused_candidates(out: &SimOutcome) -> u64 {
    out.record
        .vehicles
        .iter()
        .flat_map(|v| v.rejections.iter())
        .filter(|(k, _)| k.starts_with("fusion.correspondence."))
        .map(|(_, n)| n)
        .sum()
}

/// Issue 12's bars for an appearance run against the perfect-identity run of the same seed;
/// `confidence` is the run's confidence ratio against the reference (`max_ratio`, or
/// `sustained_ratio` where a fresh feature's first second is left out).
fn assert_bars(
    name: &str,
    out: &SimOutcome,
    sm: &RunSummary,
    perfect: &RunSummary,
    confidence: f64,
) {
    assert_eq!(sm.identity, "appearance", "{name}");
    // The same world and noise: both runs saw the same observations.
    assert_eq!(
        sm.association.observations, perfect.association.observations,
        "{name}"
    );
    assert_eq!(sm.association.unaudited_frames, 0, "{name}");
    // No estimator saw a true id: every key is a vehicle's own (ids of world features are
    // below 2³²), and every key stands for a true feature.
    for v in &out.record.vehicles {
        assert!(!v.map.is_empty(), "{name} {}: empty map", v.name);
        for f in &v.map {
            assert!(
                f.id > 1 << 32,
                "{name} {}: key {} is a feature id",
                v.name,
                f.id
            );
            assert!(
                f.truth_id.is_some(),
                "{name} {}: key {} has no truth",
                v.name,
                f.id
            );
        }
    }
    let a = &sm.association;
    assert_eq!(
        a.wrong_cross_vehicle_merges, 0,
        "{name}: wrong correspondence fused"
    );
    assert_eq!(a.wrong_merges, 0, "{name}: wrong correspondence adopted");
    // Within a vehicle (track, descriptor, gate, JCBB): 0 wrong of 5607 measured on both
    // runs; a wrong association is a real failure, but one in 1000 observations (a confusable
    // pair close together on another seed) is not a broken association.
    assert!(
        (a.wrong_associations as f64) <= 1e-3 * a.observations as f64,
        "{name}: {} wrong associations of {}",
        a.wrong_associations,
        a.observations
    );
    let share = a.mature_duplicate_share;
    assert!(a.mature_features > 0, "{name}: no mature features");
    assert!(share <= 0.02, "{name}: mature duplicate share {share:.3}");
    let ratio = |x: f64, y: f64| x / y;
    let map = ratio(sm.team.map_rmse_m, perfect.team.map_rmse_m);
    let pose = ratio(sm.team.pose_anees, perfect.team.pose_anees);
    let mapn = ratio(sm.team.map_anees, perfect.team.map_anees);
    println!(
        "{name} / perfect: map RMSE × {map:.3}, pose ANEES × {pose:.3}, map ANEES × {mapn:.3}"
    );
    assert!(
        map <= 1.10,
        "{name}: team map RMSE {map:.3}× the perfect-identity run's"
    );
    assert!(
        pose <= 1.1,
        "{name}: pose ANEES {pose:.3}× the perfect-identity run's"
    );
    assert!(
        mapn <= 1.1,
        "{name}: map ANEES {mapn:.3}× the perfect-identity run's"
    );
    // Never more confident than the all-data reference, which associates by true ids (keys
    // mapped to their true features). 1.05: the perfect-identity run reaches 1.0005 by
    // linearisation, information counted twice would give about 2.
    assert!(confidence <= 1.05, "{name}: confidence ratio {confidence}");
}

/// The largest confidence ratio held over two consecutive record times (1 s apart): a fresh
/// feature's first second is left out. local-4's perfect-identity run has one such instant —
/// uav2 at 11 s, alone on a feature it has just initialised, 1.785, and 1.040 a second later,
/// every other sample of every vehicle 1.000 ± 0.002 — where the reference, the same filter
/// on the same observations, took its observations of that feature differently. Information
/// counted twice stays near 2 for as long as it is held.
fn sustained_ratio(out: &SimOutcome) -> f64 {
    out.checks
        .confidence_ratio
        .windows(2)
        .map(|w| w[0].1.min(w[1].1))
        .fold(f64::NAN, f64::max)
}

#[test]
fn shipped_appearance_scenarios_meet_the_perfect_identity_bars() {
    let default = Scenario::builtin_default();
    assert_eq!(default.world.appearance.identity, Identity::Appearance);
    let perfect = shipped("perfect-4");
    assert_eq!(perfect.world.appearance.identity, Identity::Perfect);
    let hard = shipped("appearance-hard-4");
    assert_eq!(hard.world.seed, default.world.seed);

    let (per_out, per) = sim(&perfect);
    let (app_out, app) = sim(&default);
    let (hard_out, hard_sm) = sim(&hard);
    for (name, out, sm) in [
        ("perfect", &per_out, &per),
        ("appearance", &app_out, &app),
        ("hard", &hard_out, &hard_sm),
    ] {
        print(name, out, sm);
    }
    println!(
        "refused candidate correspondences: appearance {}, hard {}",
        refused_candidates(&app_out),
        refused_candidates(&hard_out)
    );

    // With perfect identities the keys are the true ids: nothing duplicated or unmatched.
    for v in &per_out.record.vehicles {
        assert!(v.map.iter().all(|f| f.truth_id == Some(f.id)), "{}", v.name);
    }
    assert_eq!(
        (
            per.association.duplicate_features,
            per.association.unmatched_features
        ),
        (0, 0)
    );
    assert_bars("appearance", &app_out, &app, &per, max_ratio(&app_out));
    assert_bars("hard", &hard_out, &hard_sm, &per, max_ratio(&hard_out));
    // The hard run's descriptors bring many look-alike candidates; each one refused is counted
    // (10 % confusable features and 20 % bit flips: hundreds of pairs over the team).
    assert!(refused_candidates(&hard_out) > refused_candidates(&app_out));
}

#[test]
fn correspondences_are_found_after_a_partition_and_the_audit_sees_them_missing() {
    let app = shipped("partition-heal");
    assert_eq!(app.world.appearance.identity, Identity::Appearance);
    let mut perfect = app.clone();
    perfect.world.appearance.identity = Identity::Perfect;
    let mut ablation = app.clone();
    ablation.fusion.map_correspondences = false;
    let (per_out, per) = sim(&perfect);
    let (app_out, app_sm) = sim(&app);
    let (abl_out, abl) = sim(&ablation);
    for (name, out, sm) in [
        ("partition-heal perfect", &per_out, &per),
        ("partition-heal appearance", &app_out, &app_sm),
        (
            "partition-heal without correspondence search",
            &abl_out,
            &abl,
        ),
    ] {
        print(name, out, sm);
    }
    assert_bars(
        "partition-heal",
        &app_out,
        &app_sm,
        &per,
        max_ratio(&app_out),
    );
    // The halves initialised shared features apart: correspondences had to be found (28 on
    // the shipped seed), and none was wrong (asserted above).
    assert!(app_sm.association.merges_adopted > 0);
    // The ablation leaves them duplicated, and the audit reports it: the duplicate figures
    // are not a check that cannot fail.
    assert_eq!(abl.association.merges_adopted, 0);
    assert!(
        abl.association.unmatched_features > 0 && abl.association.duplicate_features > 0,
        "the audit must see the duplicates the ablation leaves"
    );
}

/// No vehicle's estimate ever jumps: every position error below 10 m (vehicle σ < 1 m in these
/// runs; the move into the team frame before its fix jumped by 172 m).
fn assert_no_jump(name: &str, out: &SimOutcome) {
    for v in &out.record.vehicles {
        let worst = v
            .samples
            .iter()
            .map(|s| s.position_error())
            .fold(0.0, f64::max);
        assert!(
            worst < 10.0,
            "{name} {}: position error {worst:.1} m",
            v.name
        );
    }
}

/// The true own frames of `s`'s vehicles in the launch frame (their true starts).
fn true_starts(s: &Scenario) -> Vec<canopy_fusion::frames::Frame4> {
    let (_, sims) = canopy_node::world::build(s).expect("world builds");
    sims.iter().map(|v| v.launch_from_own()).collect()
}

/// Local SLAM in own frames (`topologies/local-4.toml`, issue 12 item 4): every vehicle starts
/// in its own frame (position and yaw unknown to the others), aligns with a neighbour in the
/// team frame from corresponding features, and only then fuses.
///
/// What it proves:
/// * the premise: the starts are ≥ 50 m and ≥ 30° of yaw apart (pairwise, from the truth);
/// * the alignment converges: every vehicle but the root takes one, each consistent with the
///   true relative frame (yaw and translation errors within 3σ of its own covariance);
/// * the same bars as in the shared frame hold against the own-frame perfect-identity run
///   (same seed, same observations): map RMSE ≤ 1.10×, pose and map ANEES ≤ 1.1×, no wrong
///   correspondence, mature duplicates ≤ 2 %, never more confident than the reference beyond
///   a fresh feature's first second (`sustained_ratio`; the reference knows every start
///   exactly, the team only the root's);
/// * and absolutely, so that a fault shared by both runs cannot hide behind the ratio: team
///   pose and map ANEES ≤ 1.5 (the isolated vehicles' EKF-SLAM measures 1.16 on this world;
///   the move into the team frame before its fix gave 2.07), and no estimate ever jumps — every
///   position error below 10 m (vehicle σ < 1 m; the unfixed move gave 172 m).
///
/// Runtime (release): 2 × 200 s of the 4-UAV team with the reference, ≈ 50 s on 2 cores.
#[test]
fn own_frames_align_and_meet_the_perfect_identity_bars() {
    const OWN_DURATION: f64 = 200.0;
    let app = shipped("local-4");
    assert_eq!(app.world.frames, canopy_node::scenario::Frames::Own);
    assert_eq!(app.world.appearance.identity, Identity::Appearance);
    let starts = true_starts(&app);
    for (v, f) in app.vehicles.iter().zip(&starts) {
        println!(
            "{} starts at {:.0} m N, {:.0} m E, heading {:.0}°",
            v.display_name(),
            f.translation.x,
            f.translation.y,
            f.yaw.to_degrees()
        );
    }
    for (i, a) in starts.iter().enumerate() {
        for b in &starts[i + 1..] {
            let d = a.translation - b.translation;
            let yaw = canopy_fusion::rotation::wrap_angle(a.yaw - b.yaw).abs();
            assert!(d.x.hypot(d.y) >= 50.0, "starts {:.0} m apart", d.norm());
            assert!(
                yaw >= 30f64.to_radians(),
                "starts {:.0}° apart: {a:?} {b:?}",
                yaw.to_degrees()
            );
        }
    }
    let mut perfect = app.clone();
    perfect.world.appearance.identity = Identity::Perfect;
    let run = |s: &Scenario| {
        let out = simulate(
            s,
            SimOptions {
                duration: Some(OWN_DURATION),
                ..SimOptions::default()
            },
        )
        .expect("simulation runs");
        let sm = summarize(&out.record);
        (out, sm)
    };
    let (per_out, per) = run(&perfect);
    let (app_out, app_sm) = run(&app);
    for (name, out, sm) in [
        ("local-4 perfect", &per_out, &per),
        ("local-4 appearance", &app_out, &app_sm),
    ] {
        print(name, out, sm);
        for v in &sm.vehicles {
            let f = v.frame_alignment.as_ref().expect("own frames report it");
            println!("{name} {}: {f:?}", v.name);
            if f.root {
                assert_eq!(
                    v.name, "uav1",
                    "{name}: the smallest id holds the team frame"
                );
                continue;
            }
            let t = f
                .consistent_within(3.0)
                .unwrap_or_else(|e| panic!("{name} {}: {e}", v.name));
            assert!(t < OWN_DURATION, "{name} {}", v.name);
        }
        assert!(
            sm.team.pose_anees <= 1.5,
            "{name}: pose ANEES {}",
            sm.team.pose_anees
        );
        assert!(
            sm.team.map_anees <= 1.5,
            "{name}: map ANEES {}",
            sm.team.map_anees
        );
        assert_no_jump(name, out);
    }
    // A transient of a fresh feature is allowed (`sustained_ratio`), not a doubled one.
    for (name, out) in [("perfect", &per_out), ("appearance", &app_out)] {
        let (max, held) = (max_ratio(out), sustained_ratio(out));
        println!("local-4 {name}: confidence ratio max {max:.3}, held {held:.3}");
        assert!(max < 2.0, "local-4 {name}: confidence ratio {max}");
    }
    assert_bars(
        "local-4",
        &app_out,
        &app_sm,
        &per,
        sustained_ratio(&app_out),
    );
}

/// local-4 with uav4 killed at 150 s and restarted 10 s later (the crash fault of
/// `topologies/crash-restart.toml`, here in own frames), 250 s.
///
/// What it proves: a vehicle that restarts in own frames — back in its own frame from a drawn
/// fix, its neighbour's channel still paired with its dead incarnation — gets anchors again
/// (the neighbour re-anchors a peer whose link came back until that peer's information
/// arrives), aligns again after its restart, and the team stays consistent: no wrong
/// correspondence, team pose and map ANEES ≤ 1.5 (as above), every position error below 10 m.
/// Without the re-anchoring uav4 never aligned again (its map error 4.9 m, map ANEES 1.88).
#[test]
fn own_frames_realign_after_a_crash() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../topologies/local-4.toml");
    let text = std::fs::read_to_string(&path).expect("local-4.toml");
    let crash =
        "\n[[event]]\nkind = \"crash\"\nvehicle = 4\nat_s = 150.0\nrestart_after_s = 10.0\n";
    let s = Scenario::from_toml_str(&format!("{text}{crash}")).expect("scenario");
    let out = simulate(
        &s,
        SimOptions {
            duration: Some(250.0),
            ..SimOptions::default()
        },
    )
    .expect("simulation runs");
    let sm = summarize(&out.record);
    print("local-4 crash", &out, &sm);
    let uav4 = sm.vehicles.iter().find(|v| v.name == "uav4").expect("uav4");
    assert_eq!(uav4.restarts, 1);
    let f = uav4.frame_alignment.as_ref().expect("own frames report it");
    println!("uav4 after its restart: {f:?}");
    let t = f.aligned_at_s.expect("uav4 aligned again");
    assert!(
        t > 160.0,
        "uav4's alignment at {t} s is not after its restart"
    );
    assert_eq!(sm.association.wrong_merges, 0);
    assert!(
        sm.team.pose_anees <= 1.5,
        "pose ANEES {}",
        sm.team.pose_anees
    );
    assert!(sm.team.map_anees <= 1.5, "map ANEES {}", sm.team.map_anees);
    assert_no_jump("local-4 crash", &out);
}
