//! Generated teams of any size for benchmarks and scale tests (`canopy team N`).
//!
//! Vehicle `i` (1-based) flies the pattern of the built-in default's vehicle `(i − 1) mod 4`
//! (two lawnmowers splitting the area west/east, an orbit and a figure-eight crossing both),
//! its start phase shifted by `⌊(i − 1) / 4⌋ / ⌈n / 4⌉` of the pattern so vehicles sharing a
//! pattern are spread along it, and its altitude raised by 5 m per repetition so they never
//! share a point. The fusion network is a binary tree over iceoryx2 shared memory: vehicle `i`
//! (i ≥ 2) links to `⌊i / 2⌋`. The world, IMU (100 Hz), sensor and fusion rate (1 Hz) are the
//! built-in default's; every vehicle ends up holding the team's whole map (DDF shares it).

use crate::network::{LinkSpec, TransportKind};
use crate::scenario::{FaultSpec, Scenario};

/// Largest generated team (the iceoryx2 services are sized from the scenario; beyond this the
/// launcher's shared control services would need more room than is tested).
pub const MAX_TEAM: u32 = 64;

/// A tree team of `n` vehicles (1 ≤ n ≤ [`MAX_TEAM`]) simulated for `duration_s` seconds, in
/// the built-in world with `features` features if given (default: the built-in count).
pub fn team_scenario_with(n: u32, duration_s: f64, features: Option<usize>) -> Scenario {
    let mut s = team_scenario(n, duration_s);
    if let Some(f) = features {
        s.world.features.count = Some(f);
        s.world.features.density_per_km2 = None;
    }
    s
}

/// A tree team of `n` vehicles (1 ≤ n ≤ [`MAX_TEAM`]) simulated for `duration_s` seconds.
pub fn team_scenario(n: u32, duration_s: f64) -> Scenario {
    let n = n.clamp(1, MAX_TEAM);
    let base = Scenario::builtin_default();
    let patterns = base.vehicles.len() as u32;
    let reps = n.div_ceil(patterns);
    let mut s = base.clone();
    s.vehicles = (1..=n)
        .map(|id| {
            let k = (id - 1) % patterns;
            let rep = (id - 1) / patterns;
            let mut v = base.vehicles[k as usize].clone();
            v.id = id;
            v.name = Some(format!("uav{id}"));
            if let Some(t) = v.trajectory.as_mut() {
                t.phase = (t.phase + f64::from(rep) / f64::from(reps)).fract();
                t.altitude_m += 5.0 * f64::from(rep);
            }
            v
        })
        .collect();
    s.links = (2..=n)
        .map(|b| LinkSpec {
            a: b / 2,
            b,
            transport: TransportKind::Shm,
            listen: None,
            byte_budget: None,
            faults: FaultSpec::default(),
            radio: None,
        })
        .collect();
    s.run.name = Some(format!("tree-{n}"));
    s.run.duration_s = duration_s;
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_teams_validate_and_form_a_tree() {
        for n in [1, 4, 8, 16, 24] {
            let s = team_scenario(n, 60.0);
            s.validate().expect("a generated team is a valid scenario");
            assert_eq!(s.vehicles.len(), n as usize);
            // A tree over n nodes has n − 1 edges, each to a lower id (so it is connected).
            assert_eq!(s.links.len(), n as usize - 1);
            assert!(s.links.iter().all(|l| l.a < l.b && l.a >= 1));
            // Round-trips through TOML (what `canopy team` prints).
            let back = Scenario::from_toml_str(&s.to_toml_string()).expect("parses");
            assert_eq!(back, s);
        }
        let s = team_scenario_with(8, 60.0, Some(300));
        s.validate().expect("valid with a feature count");
        assert_eq!(s.world.feature_count(), 300);
        assert!(team_scenario_with(8, 60.0, Some(0)).validate().is_err());
    }
}
