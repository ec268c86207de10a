//! The shipped appearance scenario (`topologies/appearance-4.toml`) under `canopy sim`, beside
//! the same seed with perfect identities: the estimators never see a true feature id, every
//! observation is judged against the truth, the association figures reach the summary, and the
//! vehicles are never more confident than the centralized all-data reference (which associates
//! by the true ids). The figures of both runs are printed; issue 12's bars are compared in the
//! printout, not asserted, while cross-vehicle association is missing (docs/arch/association.md).
//!
//! Runtime (release): 2 × 60 s of the 4-UAV team with the reference, ≈ 15 s.

use std::path::Path;

use canopy_node::output::summary::summarize;
use canopy_node::scenario::{Identity, Scenario};
use canopy_node::sim::{SimOptions, simulate};

const DURATION: f64 = 60.0;

fn shipped() -> Scenario {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../topologies/appearance-4.toml");
    Scenario::load(&path).expect("the shipped appearance scenario loads")
}

#[test]
fn appearance_scenario_runs_without_true_ids_and_reports_its_association() {
    let s = shipped();
    assert_eq!(s.world.appearance.identity, Identity::Appearance);
    let mut perfect = s.clone();
    perfect.world.appearance.identity = Identity::Perfect;
    let opts = || SimOptions {
        duration: Some(DURATION),
        ..SimOptions::default()
    };
    let app = simulate(&s, opts()).expect("appearance run");
    let per = simulate(&perfect, opts()).expect("perfect-identity run");
    let (sa, sp) = (summarize(&app.record), summarize(&per.record));
    let max_ratio = |c: &[(f64, f64)]| c.iter().map(|x| x.1).fold(f64::NAN, f64::max);
    for (name, sm, out) in [("appearance", &sa, &app), ("perfect", &sp, &per)] {
        let a = &sm.association;
        println!(
            "{name}: map RMSE {:.3} m, position RMSE {:.3} m, pose ANEES {:.2}, map ANEES {:.2}; \
             wrong associations {} of {}; duplicates {} (mature {} of {}, share {:.3}); \
             unmatched {}; merges {} (wrong {}); max confidence ratio {:.3} over {} record times",
            sm.team.map_rmse_m,
            sm.team.position_rmse_m,
            sm.team.pose_anees,
            sm.team.map_anees,
            a.wrong_associations,
            a.observations,
            a.duplicate_features,
            a.mature_duplicates,
            a.mature_features,
            a.mature_duplicate_share,
            a.unmatched_features,
            a.merges_adopted,
            a.wrong_merges,
            max_ratio(&out.checks.confidence_ratio),
            out.checks.confidence_ratio.len(),
        );
    }
    println!(
        "appearance / perfect: map RMSE × {:.2}, pose ANEES × {:.2}, map ANEES × {:.2}",
        sa.team.map_rmse_m / sp.team.map_rmse_m,
        sa.team.pose_anees / sp.team.pose_anees,
        sa.team.map_anees / sp.team.map_anees
    );

    assert_eq!(sa.identity, "appearance");
    assert_eq!(sp.identity, "perfect");
    // The same world and noise: both runs saw the same observations.
    assert_eq!(sa.association.observations, sp.association.observations);
    assert!(sa.association.observations > 0);
    // Every frame had its true ids: nothing escaped the audit.
    assert_eq!(sa.association.unaudited_frames, 0);
    // No estimator saw a true id: every key of every final map is a vehicle's own key (no
    // world feature has it), and every key has the true feature its observations name.
    for v in &app.record.vehicles {
        assert!(!v.map.is_empty(), "{}: empty map", v.name);
        for f in &v.map {
            assert!(f.id > 1 << 32, "{}: key {} is a feature id", v.name, f.id);
            assert!(
                f.truth_id.is_some(),
                "{}: key {} has no truth",
                v.name,
                f.id
            );
        }
    }
    // With perfect identities the keys are the true ids: nothing is duplicated or unmatched.
    for v in &per.record.vehicles {
        assert!(v.map.iter().all(|f| f.truth_id == Some(f.id)), "{}", v.name);
    }
    assert_eq!(
        (
            sp.association.duplicate_features,
            sp.association.unmatched_features
        ),
        (0, 0)
    );
    // Without cross-vehicle association the fused maps hold shared features twice: the audit
    // must see it (a check that cannot fail would report 0 here).
    assert!(sa.association.unmatched_features > 0);
    assert!(sa.association.unmatched_features <= sa.association.duplicate_features);
    // Within a vehicle, association by track, descriptor and gate: measured 0 wrong of 5607
    // observations at 120 s; 1 % leaves room for another seed's confusable pair, not for a
    // broken association.
    let a = &sa.association;
    assert!(
        (a.wrong_associations as f64) < 0.01 * a.observations as f64,
        "{} wrong of {}",
        a.wrong_associations,
        a.observations
    );
    // Never more confident than the all-data reference; the check compared features under
    // appearance too (keys mapped to their true features). 1.05: the perfect-identity run of
    // this seed reaches 1.0005 by linearisation (vehicles and reference linearise at different
    // estimates), while information counted twice would give about 2.
    assert_eq!(
        app.checks.confidence_ratio.len(),
        per.checks.confidence_ratio.len()
    );
    let r = max_ratio(&app.checks.confidence_ratio);
    assert!(r <= 1.05, "confidence ratio {r}");
}
