//! Association against the truth (the harness only: the monitor and `canopy sim`; no vehicle
//! ever sees a true id).
//!
//! Every vehicle reports, per frame, which feature key each observation went to
//! ([`FrameAssociations`]); the world gives the true id of each observation. From these:
//!
//! - **The truth of a key** is the majority true id (ties: the smaller id) of the observations
//!   its *owner* associated to it or initialized it with; the owner is the vehicle that first
//!   initialized the key (earliest frame time, then smallest vehicle id). A key a vehicle holds
//!   from a neighbour thus inherits the neighbour's assignment, and a vehicle that wrongly took
//!   a key over cannot move that key's truth with its own observations. A key nobody
//!   initialized (e.g. a replayed vehicle's) takes the majority over every vehicle's
//!   observations of it, and has no truth when nobody observed it. Bearing-only observations
//!   stored with a track vote for the feature the track initializes.
//! - **Wrong associations** of a vehicle: its observations associated to a key whose truth is
//!   another true feature (and stored observations whose track follows another one).
//! - **Merges** (a vehicle's adopted correspondences, `DdfNode::keys()`, each merged key →
//!   its canonical key) are *wrong* when both keys have a truth and the truths differ, and
//!   *cross-vehicle* when the keys' owners differ. The team figure counts each wrong fact once
//!   however many vehicles adopted it.
//! - **Duplicates** in a final map: keys beyond the first for one true feature (Σ (n_t − 1)),
//!   also among the *mature* features (held at least [`MATURE_S`] before the end). A true
//!   feature held under keys of two or more owners is *unmatched* (a cross-vehicle
//!   correspondence never found; keys of one owner are that vehicle's own duplicate, e.g. a
//!   missed loop closure).
//!
//! A restarted vehicle names its features afresh; keys that collide with its earlier
//! incarnation's count as one key here.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use canopy_fusion::keys::Merge;
use canopy_fusion::sensor::FeatureId;
use serde::{Deserialize, Serialize};

use crate::process::protocol::{FrameAssociations, Outcome};
use crate::record::{MapFeatureRecord, VehicleRecord};

/// A feature held this long before the end of a run is *mature* [s].
pub const MATURE_S: f64 = 10.0;

/// Observation counts by true id.
type Votes = BTreeMap<FeatureId, u64>;

fn add(votes: &mut Votes, truth: FeatureId, n: u64) {
    *votes.entry(truth).or_insert(0) += n;
}

/// The majority of some vote tables (ties: the smaller true id).
fn majority<'a>(tables: impl IntoIterator<Item = &'a Votes>) -> Option<FeatureId> {
    let mut sum = Votes::new();
    for t in tables {
        for (&id, &n) in t {
            add(&mut sum, id, n);
        }
    }
    // Ascending ids: `max_by_key` keeps the last maximum, so iterate in reverse.
    sum.iter().rev().max_by_key(|(_, n)| **n).map(|(id, _)| *id)
}

/// Gathers what vehicles did with their observations, and their adopted merges.
#[derive(Clone, Debug, Default)]
pub struct TruthAudit {
    /// (vehicle, key) → true ids of the observations associated to the key.
    associated: HashMap<(u32, FeatureId), Votes>,
    /// (vehicle, key) → true ids of the observations that initialized it.
    initialized: HashMap<(u32, FeatureId), Votes>,
    /// (vehicle, track) → true ids of the observations stored with a bearing-only track.
    stored: HashMap<(u32, u64), Votes>,
    /// (vehicle, track) → the feature it initialized.
    track_feature: HashMap<(u32, u64), FeatureId>,
    /// key → (time, vehicle) of its first initialization.
    owner: HashMap<FeatureId, (f64, u32)>,
    /// Observations per vehicle.
    observations: BTreeMap<u32, u64>,
    /// Frames whose true ids were missing or did not match the outcomes, per vehicle.
    unaudited_frames: BTreeMap<u32, u64>,
    /// Each vehicle's adopted merges.
    merges: BTreeMap<u32, Vec<Merge>>,
}

impl TruthAudit {
    /// One frame of `vehicle`: its outcomes and the true id of each observation (`None` when
    /// the source has no truth, e.g. a replayed vehicle).
    pub fn frame(&mut self, vehicle: u32, fa: &FrameAssociations, true_ids: Option<&[FeatureId]>) {
        *self.observations.entry(vehicle).or_insert(0) += fa.outcomes.len() as u64;
        let Some(ids) = true_ids.filter(|ids| ids.len() == fa.outcomes.len()) else {
            *self.unaudited_frames.entry(vehicle).or_insert(0) += 1;
            return;
        };
        let mut own = |key: FeatureId| {
            let e = self.owner.entry(key).or_insert((fa.t, vehicle));
            if (fa.t, vehicle) < *e {
                *e = (fa.t, vehicle);
            }
        };
        for (o, &truth) in fa.outcomes.iter().zip(ids) {
            match *o {
                Outcome::Associated(k) => {
                    add(self.associated.entry((vehicle, k)).or_default(), truth, 1);
                }
                Outcome::Initialized(k) => {
                    own(k);
                    add(self.initialized.entry((vehicle, k)).or_default(), truth, 1);
                }
                Outcome::Stored(track) => {
                    add(self.stored.entry((vehicle, track)).or_default(), truth, 1);
                }
                Outcome::Rejected => {}
            }
        }
        for &(track, k) in &fa.initialized_tracks {
            own(k);
            self.track_feature.insert((vehicle, track), k);
            if let Some(v) = self.stored.get(&(vehicle, track)).cloned() {
                let e = self.initialized.entry((vehicle, k)).or_default();
                for (id, n) in v {
                    add(e, id, n);
                }
            }
        }
    }

    /// The merges `vehicle` has adopted (its key map: each merged key → canonical key),
    /// replacing what it reported before.
    pub fn set_merges(&mut self, vehicle: u32, merges: Vec<Merge>) {
        self.merges.insert(vehicle, merges);
    }

    /// Observations of `vehicle` whose frames had no usable truth.
    pub fn unaudited_frames(&self, vehicle: u32) -> u64 {
        self.unaudited_frames.get(&vehicle).copied().unwrap_or(0)
    }

    /// The true feature key `k` stands for so far (module docs, "The truth of a key"): the
    /// majority of its owner's observations, or of everyone's when nobody initialized it.
    pub fn truth_of(&self, k: FeatureId) -> Option<FeatureId> {
        match self.owner.get(&k) {
            Some(&(_, o)) => majority(
                [self.associated.get(&(o, k)), self.initialized.get(&(o, k))]
                    .into_iter()
                    .flatten(),
            ),
            None => majority(
                self.associated
                    .iter()
                    .filter(|((_, key), _)| *key == k)
                    .map(|(_, v)| v),
            ),
        }
    }

    /// Assigns every key its truth and judges associations and merges.
    pub fn finish(&self) -> KeyTruth {
        let mut keys: BTreeSet<FeatureId> = BTreeSet::new();
        keys.extend(self.associated.keys().map(|k| k.1));
        keys.extend(self.initialized.keys().map(|k| k.1));
        let truth: HashMap<FeatureId, FeatureId> = keys
            .iter()
            .filter_map(|&k| self.truth_of(k).map(|t| (k, t)))
            .collect();
        let owner: HashMap<FeatureId, u32> =
            self.owner.iter().map(|(&k, &(_, o))| (k, o)).collect();
        let mut out = KeyTruth {
            truth,
            owner,
            vehicles: BTreeMap::new(),
            team_wrong_merges: BTreeSet::new(),
        };
        for (&v, &n) in &self.observations {
            out.vehicles.entry(v).or_default().observations = n;
        }
        for (&v, &n) in &self.unaudited_frames {
            out.vehicles.entry(v).or_default().unaudited_frames = n;
        }
        for (&(v, k), votes) in &self.associated {
            if let Some(&t) = out.truth.get(&k) {
                let wrong: u64 = votes.iter().filter(|(id, _)| **id != t).map(|e| e.1).sum();
                out.vehicles.entry(v).or_default().wrong_associations += wrong;
            }
        }
        for (&(v, track), votes) in &self.stored {
            let reference = match self.track_feature.get(&(v, track)) {
                Some(k) => out.truth.get(k).copied(),
                None => majority([votes]),
            };
            if let Some(t) = reference {
                let wrong: u64 = votes.iter().filter(|(id, _)| **id != t).map(|e| e.1).sum();
                out.vehicles.entry(v).or_default().wrong_associations += wrong;
            }
        }
        for (&v, merges) in &self.merges {
            let mut c = AssociationTruth::default();
            for m in merges {
                c.merges_adopted += 1;
                let cross = out.owner.get(&m.from) != out.owner.get(&m.into);
                c.merges_cross_vehicle += u64::from(cross);
                if let (Some(a), Some(b)) = (out.truth.get(&m.from), out.truth.get(&m.into))
                    && a != b
                {
                    c.wrong_merges += 1;
                    c.wrong_cross_vehicle_merges += u64::from(cross);
                    out.team_wrong_merges.insert(*m);
                }
            }
            let e = out.vehicles.entry(v).or_default();
            e.merges_adopted = c.merges_adopted;
            e.merges_cross_vehicle = c.merges_cross_vehicle;
            e.wrong_merges = c.wrong_merges;
            e.wrong_cross_vehicle_merges = c.wrong_cross_vehicle_merges;
        }
        out
    }
}

/// One vehicle's association figures against the truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct AssociationTruth {
    /// Observations processed.
    pub observations: u64,
    /// Observations associated to a key whose truth is another feature.
    pub wrong_associations: u64,
    /// Merges adopted (its key map's entries).
    pub merges_adopted: u64,
    /// Of them, between keys of different owners.
    pub merges_cross_vehicle: u64,
    /// Merges whose keys' truths differ.
    pub wrong_merges: u64,
    /// Of them, between keys of different owners.
    pub wrong_cross_vehicle_merges: u64,
    /// Frames whose true ids were missing or did not match the outcomes (not judged).
    pub unaudited_frames: u64,
}

/// A final map judged against the truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MapTruth {
    /// Keys beyond the first for one true feature.
    pub duplicates: u64,
    /// Features held at least [`MATURE_S`] before the end.
    pub mature_features: u64,
    /// Duplicates among the mature features.
    pub mature_duplicates: u64,
    /// True features held under keys of two or more owners (never matched).
    pub unmatched: u64,
}

/// One vehicle's association and final map against the truth, as a run records and
/// summarizes them (flattened into `VehicleRecord` and `summary.json`'s `vehicles[]`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct TruthFigures {
    /// Observations associated to a key that stands for another true feature.
    pub wrong_associations: u64,
    /// Keys of the final map beyond the first for one true feature.
    pub duplicate_features: u64,
    /// Features of the final map held at least [`MATURE_S`] before the end.
    pub mature_features: u64,
    /// Duplicates among them.
    pub mature_duplicates: u64,
    /// True features the final map holds under keys first made by two or more vehicles (a
    /// cross-vehicle correspondence never found).
    pub unmatched_features: u64,
    /// Correspondences (key merges) the vehicle adopted.
    pub merges_adopted: u64,
    /// Of them, between keys first made by different vehicles.
    pub merges_cross_vehicle: u64,
    /// Adopted merges whose keys stand for different true features.
    pub wrong_merges: u64,
    /// Of them, between keys first made by different vehicles.
    pub wrong_cross_vehicle_merges: u64,
    /// Neighbours' correspondences the vehicle refused (its estimate had evidence against
    /// them: rejected candidate correspondences).
    pub merges_refused: u64,
    /// Frames whose true ids were missing or did not match the estimator's outcomes (not
    /// judged: 0 for every simulated vehicle).
    pub unaudited_frames: u64,
}

/// The truth of every key, and the figures of each vehicle.
#[derive(Clone, Debug, Default)]
pub struct KeyTruth {
    truth: HashMap<FeatureId, FeatureId>,
    owner: HashMap<FeatureId, u32>,
    vehicles: BTreeMap<u32, AssociationTruth>,
    team_wrong_merges: BTreeSet<Merge>,
}

impl KeyTruth {
    /// The true feature key `k` stands for, if known.
    pub fn truth(&self, k: FeatureId) -> Option<FeatureId> {
        self.truth.get(&k).copied()
    }

    /// The vehicle that first initialized key `k`.
    pub fn owner(&self, k: FeatureId) -> Option<u32> {
        self.owner.get(&k).copied()
    }

    /// The figures of `vehicle`.
    pub fn vehicle(&self, vehicle: u32) -> AssociationTruth {
        self.vehicles.get(&vehicle).copied().unwrap_or_default()
    }

    /// Distinct wrong merge facts over the team.
    pub fn team_wrong_merges(&self) -> u64 {
        self.team_wrong_merges.len() as u64
    }

    /// Duplicates, mature features and unmatched features of a final map taken at `end`
    /// (records with their truth filled in: `truth_id`).
    pub fn judge_map(&self, map: &[MapFeatureRecord], end: f64) -> MapTruth {
        let mut by_truth: BTreeMap<FeatureId, Vec<&MapFeatureRecord>> = BTreeMap::new();
        for f in map {
            if let Some(t) = f.truth_id {
                by_truth.entry(t).or_default().push(f);
            }
        }
        let mature = |f: &MapFeatureRecord| f.held_since.is_some_and(|h| h <= end - MATURE_S);
        let mut out = MapTruth {
            mature_features: map.iter().filter(|f| mature(f)).count() as u64,
            ..MapTruth::default()
        };
        for keys in by_truth.values() {
            out.duplicates += keys.len() as u64 - 1;
            let m = keys.iter().filter(|f| mature(f)).count() as u64;
            out.mature_duplicates += m.saturating_sub(1);
            let owners: BTreeSet<Option<u32>> = keys.iter().map(|f| self.owner(f.id)).collect();
            if keys.len() >= 2 && owners.len() >= 2 {
                out.unmatched += 1;
            }
        }
        out
    }
}

/// The figures of `vehicle` whose final map `map` (records with `truth_id` and `held_since`)
/// was taken at `end`; `merges_refused` is left to the caller (a DDF counter).
pub fn figures(truth: &KeyTruth, vehicle: u32, map: &[MapFeatureRecord], end: f64) -> TruthFigures {
    let a = truth.vehicle(vehicle);
    let m = truth.judge_map(map, end);
    TruthFigures {
        wrong_associations: a.wrong_associations,
        duplicate_features: m.duplicates,
        mature_features: m.mature_features,
        mature_duplicates: m.mature_duplicates,
        unmatched_features: m.unmatched,
        merges_adopted: a.merges_adopted,
        merges_cross_vehicle: a.merges_cross_vehicle,
        wrong_merges: a.wrong_merges,
        wrong_cross_vehicle_merges: a.wrong_cross_vehicle_merges,
        merges_refused: 0,
        unaudited_frames: a.unaudited_frames,
    }
}

/// Fills `rec`'s figures for `vehicle` ([`figures`] of its final map taken at `end`), keeping
/// its `merges_refused`.
pub fn fill_record(truth: &KeyTruth, vehicle: u32, rec: &mut VehicleRecord, end: f64) {
    rec.association = TruthFigures {
        merges_refused: rec.association.merges_refused,
        ..figures(truth, vehicle, &rec.map, end)
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(t: f64, outcomes: Vec<Outcome>) -> FrameAssociations {
        FrameAssociations {
            t,
            outcomes,
            initialized_tracks: Vec::new(),
            origin: None,
        }
    }

    fn feature(id: FeatureId, truth_id: Option<FeatureId>, held: f64) -> MapFeatureRecord {
        MapFeatureRecord {
            id,
            truth_id,
            est: [0.0; 3],
            cov: [0.0; 9],
            truth: None,
            held_since: Some(held),
        }
    }

    /// Two vehicles. Vehicle 1 owns keys 101 (true 7) and 102 (true 8); vehicle 2 owns 201
    /// (true 7) and 202 (true 9). Vehicle 2 adopts 201 ≡ 101 (right) and 202 ≡ 102 (wrong:
    /// 9 ≠ 8), and associates one observation of 9 to 102 after that merge, plus one
    /// observation of 8 to its own 202 (wrong). Vehicle 1 ends with 101 and a duplicate 103
    /// of true 7, and 201 received from vehicle 2 (another duplicate of 7, never matched).
    #[test]
    fn a_wrong_merge_wrong_associations_and_duplicates_are_counted() {
        use Outcome::*;
        let mut a = TruthAudit::default();
        a.frame(
            1,
            &frame(1.0, vec![Initialized(101), Initialized(102)]),
            Some(&[7, 8]),
        );
        a.frame(
            1,
            &frame(2.0, vec![Associated(101), Associated(102), Rejected]),
            Some(&[7, 8, 9]),
        );
        a.frame(
            2,
            &frame(1.5, vec![Initialized(201), Initialized(202)]),
            Some(&[7, 9]),
        );
        // Vehicle 2 re-observes 9 on its 202, so 202's truth is 9 by a clear majority.
        a.frame(2, &frame(2.5, vec![Associated(202)]), Some(&[9]));
        a.frame(
            2,
            &frame(3.0, vec![Associated(202), Associated(102), Associated(101)]),
            Some(&[8, 9, 7]),
        );
        a.frame(1, &frame(4.0, vec![Initialized(103)]), Some(&[7]));
        // A frame whose truth is missing is counted, not judged.
        a.frame(1, &frame(5.0, vec![Associated(101)]), None);
        a.set_merges(
            2,
            vec![
                Merge {
                    from: 201,
                    into: 101,
                },
                Merge {
                    from: 202,
                    into: 102,
                },
            ],
        );
        let k = a.finish();
        assert_eq!(
            (
                k.truth(101),
                k.truth(102),
                k.truth(201),
                k.truth(202),
                k.truth(103)
            ),
            (Some(7), Some(8), Some(7), Some(9), Some(7))
        );
        // Vehicle 2's observation of 9 on 102 does not move 102's truth (owner: vehicle 1).
        assert_eq!(k.owner(102), Some(1));
        let v1 = k.vehicle(1);
        let v2 = k.vehicle(2);
        assert_eq!(v1.observations, 7);
        assert_eq!(v1.wrong_associations, 0);
        assert_eq!(v2.observations, 6);
        // 8 on 202 (true 9) and 9 on 102 (true 8).
        assert_eq!(v2.wrong_associations, 2);
        assert_eq!(
            (v2.merges_adopted, v2.merges_cross_vehicle, v2.wrong_merges),
            (2, 2, 1)
        );
        assert_eq!(v2.wrong_cross_vehicle_merges, 1);
        assert_eq!(k.team_wrong_merges(), 1);
        assert_eq!(a.unaudited_frames(1), 1);
        assert_eq!((v1.unaudited_frames, v2.unaudited_frames), (1, 0));

        // Vehicle 1's final map at t = 30: 101, 102, 103 (own duplicate of 7, mature), 201
        // (vehicle 2's key for 7, held only since 25: not mature).
        let map: Vec<MapFeatureRecord> = [(101, 1.0), (102, 1.0), (103, 4.0), (201, 25.0)]
            .into_iter()
            .map(|(id, held)| feature(id, k.truth(id), held))
            .collect();
        let m = k.judge_map(&map, 30.0);
        assert_eq!(m.duplicates, 2); // 101, 103, 201 all stand for 7
        assert_eq!(m.mature_features, 3);
        assert_eq!(m.mature_duplicates, 1); // 101 and 103
        assert_eq!(m.unmatched, 1); // 7 under keys of vehicles 1 and 2
    }

    #[test]
    fn bearing_tracks_vote_for_the_feature_they_initialize() {
        use Outcome::*;
        let mut a = TruthAudit::default();
        a.frame(3, &frame(1.0, vec![Stored(5), Stored(6)]), Some(&[4, 4]));
        a.frame(3, &frame(2.0, vec![Stored(5), Stored(6)]), Some(&[4, 2]));
        let mut f = frame(3.0, vec![Initialized(900)]);
        f.initialized_tracks = vec![(5, 900)];
        a.frame(3, &f, Some(&[4]));
        let k = a.finish();
        assert_eq!(k.truth(900), Some(4));
        assert_eq!(k.owner(900), Some(3));
        // Track 6 followed 4 then 2: one of its two observations is wrong (tie → smaller
        // id 2 is the track's truth, so the observation of 4 is the wrong one).
        assert_eq!(k.vehicle(3).wrong_associations, 1);
    }

    /// Keys of one owner for one true feature are that vehicle's own duplicates, not
    /// unmatched; a key nobody initialized (a replayed neighbour's) takes the majority of
    /// every vehicle's observations of it; with perfect identities (key = true id) nothing is
    /// wrong, duplicated or unmatched.
    #[test]
    fn own_duplicates_foreign_keys_and_perfect_identities() {
        use Outcome::*;
        let mut a = TruthAudit::default();
        a.frame(
            1,
            &frame(1.0, vec![Initialized(11), Initialized(12)]),
            Some(&[3, 3]),
        );
        // Key 77 was never initialized here: vehicles 1 and 2 saw 5, 5 and 6 on it.
        a.frame(
            1,
            &frame(2.0, vec![Associated(77), Associated(77)]),
            Some(&[5, 6]),
        );
        a.frame(2, &frame(2.0, vec![Associated(77)]), Some(&[5]));
        let k = a.finish();
        assert_eq!(
            (k.truth(11), k.truth(12), k.truth(77)),
            (Some(3), Some(3), Some(5))
        );
        assert_eq!(k.owner(77), None);
        assert_eq!(k.vehicle(1).wrong_associations, 1);
        assert_eq!(k.vehicle(2).wrong_associations, 0);
        let map: Vec<MapFeatureRecord> = [11, 12, 77]
            .into_iter()
            .map(|id| feature(id, k.truth(id), 0.0))
            .collect();
        let m = k.judge_map(&map, 5.0);
        assert_eq!(
            m,
            MapTruth {
                duplicates: 1,
                mature_features: 0,
                mature_duplicates: 0,
                unmatched: 0
            }
        );

        let mut p = TruthAudit::default();
        p.frame(
            1,
            &frame(1.0, vec![Initialized(3), Initialized(4)]),
            Some(&[3, 4]),
        );
        p.frame(2, &frame(1.0, vec![Initialized(3)]), Some(&[3]));
        p.frame(
            2,
            &frame(2.0, vec![Associated(4), Associated(3)]),
            Some(&[4, 3]),
        );
        let k = p.finish();
        let map: Vec<MapFeatureRecord> = [3, 4]
            .into_iter()
            .map(|id| feature(id, k.truth(id), 0.0))
            .collect();
        assert_eq!(k.vehicle(2).wrong_associations, 0);
        assert_eq!(
            k.judge_map(&map, 20.0),
            MapTruth {
                duplicates: 0,
                mature_features: 2,
                mature_duplicates: 0,
                unmatched: 0
            }
        );
    }
}
