//! Correspondences within one map: keys that name one physical feature.
//!
//! Without the simulator's identities a feature seen by two vehicles enters a fused map twice —
//! once under each vehicle's key — and a vehicle whose track broke and whose association failed
//! may hold a feature twice under its own keys. Both are *duplicates of this map*, and both are
//! found the same way, after the neighbours' information has been fused in, with the joint
//! covariance the filter holds for the two (no independence assumed):
//!
//! 1. **Candidates by appearance**: pairs whose descriptors (the majority of a feature's
//!    observations, or the one a neighbour described) are within `max_distance` bits.
//! 2. **Geometric compatibility** of a candidate pair (a, b): the difference
//!    δ = x_a − x_b has covariance D = P_aa + P_bb − P_ab − P_ba, and the pair is compatible
//!    at probability p when δᵀ D⁻¹ δ ≤ χ²₃(p) (the validation gate of eq. 21.55 applied to the
//!    constraint x_a = x_b).
//! 3. **Ambiguity is refused**: candidates compatible at the wide probability
//!    (`ambiguity_probability`) form a graph; a connected group is adopted only when every
//!    pair in it is a descriptor candidate compatible at the strict probability
//!    (`accept_probability`) — one physical feature under several keys. A group with a
//!    member that fits two others that do not fit each other (two near-identical features close
//!    together, a repeated texture) is left apart: no fusion rather than a wrong one.
//! 4. **Joint compatibility** of everything adopted in one search: the stacked constraints
//!    x_k = x_{k₀} of all groups, with their joint covariance from P, must pass
//!    χ²_{3c}(`accept_probability`) (Neira & Tardós' joint test); while it fails, the group
//!    with the largest individual distance is dropped.
//!
//! A merge applied to the filter ([`SlamFilter::merge_features`]) is the Kalman update of
//! x_a − x_b = 0 with R = 0 (eqs. 21.56–21.60) followed by marginalising `from`: in information
//! form Tᵀ Y T, the re-keying the channel filters apply (module [`crate::keys`]). It cannot be
//! undone, hence the conservative rules. A neighbour's correspondence reaches this filter as a
//! fact; [`SlamFilter::merge_contradicted`] says whether this filter's own estimate contradicts it.

use super::SlamFilter;
use crate::consistency::chi2_quantile;
use crate::keys::Merge;
use crate::sensor::{Appearance, FeatureId, hamming};
use faer::linalg::solvers::Solve;
use faer::{Col, Mat};
use nalgebra::{Matrix3, Vector3};
use std::collections::BTreeMap;

/// Options of [`SlamFilter::find_correspondences`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CorrespondenceConfig {
    /// Largest descriptor distance [bits of 256] of a candidate pair.
    pub max_distance: u32,
    /// Largest standard deviation [m] of the difference x_a − x_b along its worst axis
    /// (√λ_max(D)) for a pair to be decided (module docs, step 2). A pair known worse than
    /// this is *undetermined*: not adopted, and its group left apart until more information
    /// arrives. The χ² gate alone judges an estimate against its own uncertainty; a lookalike
    /// hundreds of metres away passes it when σ is hundreds of metres (as for a feature that
    /// reached this map only through a neighbour's sparsified marginal), and the descriptor
    /// cannot tell repeated texture apart. The gate's radius along the worst axis is
    /// √χ²₃(p) σ ≈ 3.4 σ at p = 0.99: at the default 20 m, 67 m, within the mean feature
    /// spacing of the shipped scenarios (~110 m: 700 features on 3 km × 3 km), so the gate
    /// holds about one feature's share of the ground and a lookalike (2 % of the features)
    /// falls in it with a few per cent probability, against near-certainty for the wrong merges
    /// measured (σ ≥ 1.6 km). 10 m delayed a correct merge of radio-32k's seed 1 (σ between
    /// 10 and 20 m) and cost 6 % of its map accuracy (docs/arch/association.md).
    pub max_difference_sigma_m: f64,
    /// Probability of the χ² gate a pair (and the joint test) must pass to be adopted.
    pub accept_probability: f64,
    /// Probability of the wider gate that defines ambiguity: two candidates of one key within
    /// it that are not one feature together make the whole group ambiguous.
    pub ambiguity_probability: f64,
}

impl Default for CorrespondenceConfig {
    fn default() -> Self {
        Self {
            max_distance: 66,
            max_difference_sigma_m: 20.0,
            accept_probability: 0.99,
            ambiguity_probability: 0.9999,
        }
    }
}

/// What one search found and left.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CorrespondenceReport {
    /// Correspondences to adopt (each `into` the smallest key of its group).
    pub merges: Vec<Merge>,
    /// Candidate pairs (descriptor within `max_distance`) examined.
    pub candidates: u64,
    /// Candidate pairs (smaller key first) outside the wide gate: different features that look
    /// alike.
    pub incompatible_pairs: Vec<(FeatureId, FeatureId)>,
    /// Candidate pairs within the wide gate in ambiguous groups (left apart).
    pub ambiguous_pairs: Vec<(FeatureId, FeatureId)>,
    /// Candidate pairs within the wide gate in groups that would be adopted but for a pair
    /// whose difference is not yet known well enough (`max_difference_sigma_m`; left apart).
    pub undetermined_pairs: Vec<(FeatureId, FeatureId)>,
    /// Pairs of groups dropped by the joint test.
    pub joint_rejected_pairs: Vec<(FeatureId, FeatureId)>,
}

fn ordered(a: FeatureId, b: FeatureId) -> (FeatureId, FeatureId) {
    (a.min(b), a.max(b))
}

/// A candidate pair: two keys whose descriptors are close, with their squared Mahalanobis
/// distance under the joint covariance and whether that covariance is tight enough to decide.
#[derive(Clone, Copy, Debug)]
struct Pair {
    a: usize,
    b: usize,
    d2: f64,
    determined: bool,
}

fn find(parent: &mut [usize], mut i: usize) -> usize {
    while parent[i] != i {
        parent[i] = parent[parent[i]];
        i = parent[i];
    }
    i
}

impl SlamFilter {
    /// δᵀ D⁻¹ δ for the constraint x_a = x_b of two features at state offsets `a`, `b`
    /// (∞ when D is not positive definite: such a pair is never taken for one feature), and
    /// D, the covariance of the difference.
    fn pair_distance(&self, a: usize, b: usize) -> (f64, Matrix3<f64>) {
        let d: Vector3<f64> = self.vec3_at(a) - self.vec3_at(b);
        let cov: Matrix3<f64> =
            self.mat3_at(a, a) + self.mat3_at(b, b) - self.mat3_at(a, b) - self.mat3_at(b, a);
        let cov = 0.5 * (cov + cov.transpose());
        match cov.cholesky() {
            Some(c) => (d.dot(&c.solve(&d)), cov),
            None => (f64::INFINITY, cov),
        }
    }

    /// Correspondences between this map's features (module docs): candidates by descriptor,
    /// geometric compatibility with the joint covariance, ambiguous groups refused, the rest
    /// jointly tested. Nothing is changed: adopt the merges through the DDF node (which
    /// re-keys its channel filters and tells the neighbours) or [`SlamFilter::merge_features`].
    pub fn find_correspondences(&self, cfg: &CorrespondenceConfig) -> CorrespondenceReport {
        let mut report = CorrespondenceReport::default();
        let (Ok(strict), Ok(wide)) = (
            chi2_quantile(3.0, cfg.accept_probability),
            chi2_quantile(3.0, cfg.ambiguity_probability),
        ) else {
            return report;
        };
        let described: Vec<(FeatureId, usize, Appearance)> = self
            .layout
            .features()
            .filter_map(|(id, off)| self.appearance.of(id).map(|a| (id, off, a)))
            .collect();
        let n = described.len();
        let mut pairs: Vec<Pair> = Vec::new();
        for i in 0..n {
            for j in i + 1..n {
                if hamming(&described[i].2, &described[j].2) > cfg.max_distance {
                    continue;
                }
                report.candidates += 1;
                let (d2, cov) = self.pair_distance(described[i].1, described[j].1);
                if d2 <= wide {
                    // σ of the difference along its worst axis: √λ_max(D).
                    let determined =
                        cov.symmetric_eigenvalues().max().sqrt() <= cfg.max_difference_sigma_m;
                    pairs.push(Pair {
                        a: i,
                        b: j,
                        d2,
                        determined,
                    });
                } else {
                    report
                        .incompatible_pairs
                        .push(ordered(described[i].0, described[j].0));
                }
            }
        }
        // Groups: connected components of the wide-gate graph.
        let mut parent: Vec<usize> = (0..n).collect();
        for p in &pairs {
            let (ra, rb) = (find(&mut parent, p.a), find(&mut parent, p.b));
            if ra != rb {
                parent[ra.max(rb)] = ra.min(rb);
            }
        }
        let mut groups: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        let mut edges: BTreeMap<usize, Vec<Pair>> = BTreeMap::new();
        for p in &pairs {
            let r = find(&mut parent, p.a);
            edges.entry(r).or_default().push(*p);
        }
        for i in 0..n {
            let r = find(&mut parent, i);
            if edges.contains_key(&r) {
                groups.entry(r).or_default().push(i);
            }
        }
        // A group is one feature when it is a clique of strict-gate candidate pairs, each
        // known well enough to decide.
        let mut accepted: Vec<(Vec<usize>, f64)> = Vec::new();
        for (r, members) in groups {
            let group_edges = &edges[&r];
            let k = members.len();
            let clique = group_edges.len() == k * (k - 1) / 2;
            let strict_ok = group_edges.iter().all(|p| p.d2 <= strict);
            let determined = group_edges.iter().all(|p| p.determined);
            let left_apart = match (clique && strict_ok, determined) {
                (true, true) => {
                    let worst = group_edges.iter().map(|p| p.d2).fold(0.0, f64::max);
                    accepted.push((members, worst));
                    continue;
                }
                (true, false) => &mut report.undetermined_pairs,
                (false, _) => &mut report.ambiguous_pairs,
            };
            left_apart.extend(
                group_edges
                    .iter()
                    .map(|p| ordered(described[p.a].0, described[p.b].0)),
            );
        }
        // Joint compatibility of all groups adopted in this search.
        loop {
            if accepted.is_empty() || self.jointly_compatible(&accepted, &described, cfg) {
                break;
            }
            let worst = accepted
                .iter()
                .enumerate()
                .max_by(|x, y| x.1.1.total_cmp(&y.1.1))
                .map(|(i, _)| i)
                .expect("not empty");
            let (members, _) = accepted.swap_remove(worst);
            for (x, &i) in members.iter().enumerate() {
                for &j in &members[x + 1..] {
                    report
                        .joint_rejected_pairs
                        .push(ordered(described[i].0, described[j].0));
                }
            }
        }
        for (members, _) in accepted {
            let mut keys: Vec<FeatureId> = members.iter().map(|&i| described[i].0).collect();
            keys.sort_unstable();
            for &k in &keys[1..] {
                report.merges.extend(Merge::of(keys[0], k));
            }
        }
        report.merges.sort_unstable();
        report
    }

    /// The joint test of [`find_correspondences`](Self::find_correspondences): the stacked
    /// constraints x_k − x_{k₀} of every group, ν = H x, S = H P Hᵀ, νᵀ S⁻¹ ν ≤ χ²_{3c}.
    fn jointly_compatible(
        &self,
        groups: &[(Vec<usize>, f64)],
        described: &[(FeatureId, usize, Appearance)],
        cfg: &CorrespondenceConfig,
    ) -> bool {
        // Constraint c: (offset of k, offset of k₀).
        let rows: Vec<(usize, usize)> = groups
            .iter()
            .flat_map(|(m, _)| m[1..].iter().map(|&k| (described[k].1, described[m[0]].1)))
            .collect();
        let c = rows.len();
        if c <= 1 {
            return true;
        }
        let Ok(gate) = chi2_quantile(3.0 * c as f64, cfg.accept_probability) else {
            return false;
        };
        let nu = Col::from_fn(3 * c, |r| {
            let (a, b) = rows[r / 3];
            self.x[a + r % 3] - self.x[b + r % 3]
        });
        // S_{rs} = P_aa' − P_ab' − P_ba' + P_bb' for constraints (a, b), (a', b').
        let s = Mat::from_fn(3 * c, 3 * c, |r, q| {
            let ((a, b), (a2, b2)) = (rows[r / 3], rows[q / 3]);
            let (i, j) = (r % 3, q % 3);
            self.p[(a + i, a2 + j)] - self.p[(a + i, b2 + j)] - self.p[(b + i, a2 + j)]
                + self.p[(b + i, b2 + j)]
        });
        let Ok(llt) = s.llt(faer::Side::Lower) else {
            return false;
        };
        let w = llt.solve(&nu);
        let d2: f64 = (0..3 * c).map(|r| nu[r] * w[r]).sum();
        d2 <= gate
    }

    /// Map features without an appearance descriptor (appearance association only; empty
    /// otherwise): keys whose `Describe` was lost or never came, to be asked for again
    /// ([`crate::ddf::DdfNode::request_descriptors`]).
    pub fn undescribed_features(&self) -> Vec<FeatureId> {
        if !matches!(
            self.config.association.mode,
            super::AssociationMode::Appearance { .. }
        ) {
            return Vec::new();
        }
        self.layout
            .features()
            .filter(|&(id, _)| !self.appearance.knows(id))
            .map(|(id, _)| id)
            .collect()
    }

    /// Whether this filter's own estimate contradicts a neighbour's correspondence: both keys
    /// held and their difference outside the wide gate χ²₃(`probability`) with the joint
    /// covariance. `false` when either key is not held (nothing to contradict).
    pub fn merge_contradicted(&self, merge: &Merge, probability: f64) -> bool {
        let (Some(a), Some(b)) = (
            self.layout.feature_offset(merge.from),
            self.layout.feature_offset(merge.into),
        ) else {
            return false;
        };
        let Ok(gate) = chi2_quantile(3.0, probability) else {
            return false;
        };
        self.pair_distance(a, b).0 > gate
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ddf::FuseTarget;
    use crate::slam::AssociationMode;
    use crate::slam::tests::{config, delta, vehicle};
    use crate::state::NavFrame;
    use nalgebra::{DMatrix, DVector};

    const LOOK: Appearance = [0x0123_4567_89AB_CDEF, 0xFEDC_BA98_7654_3210, 0x5555, 0xAAAA];
    const OTHER: Appearance = [!0x0123_4567_89AB_CDEF, 0x0F0F, u64::MAX, 0];

    /// A filter holding `features` (key, position, descriptor), each with covariance σ² I
    /// (σ = 1 m) and the cross-covariance `rho`·σ² I between consecutive keys of `coupled`.
    fn filter_with(
        features: &[(FeatureId, [f64; 3], Appearance)],
        coupled: &[(usize, usize, f64)],
    ) -> SlamFilter {
        filter_with_sigma(features, coupled, 1.0)
    }

    /// [`filter_with`] with σ = `sigma` [m].
    fn filter_with_sigma(
        features: &[(FeatureId, [f64; 3], Appearance)],
        coupled: &[(usize, usize, f64)],
        sigma: f64,
    ) -> SlamFilter {
        let mode = AssociationMode::Appearance {
            max_distance: 20,
            max_nodes: 100,
        };
        let mut f = SlamFilter::new(
            config(NavFrame::Local, mode),
            &[vehicle(Vector3::new(0.0, 0.0, -100.0))],
        )
        .unwrap();
        let k = 3 * features.len();
        let mut cov = DMatrix::<f64>::identity(k, k);
        for &(i, j, rho) in coupled {
            for a in 0..3 {
                cov[(3 * i + a, 3 * j + a)] = rho;
                cov[(3 * j + a, 3 * i + a)] = rho;
            }
        }
        let y = (cov * (sigma * sigma)).try_inverse().unwrap();
        let target = DVector::from_fn(k, |r, _| features[r / 3].1[r % 3]);
        let ids = features.iter().map(|x| x.0).collect();
        f.fuse_map_information(&delta(ids, y, &target, f.origin()))
            .unwrap();
        let described: Vec<(FeatureId, Appearance)> = features.iter().map(|x| (x.0, x.2)).collect();
        f.describe(&described);
        f
    }

    fn merge(from: FeatureId, into: FeatureId) -> Merge {
        Merge { from, into }
    }

    /// Two keys 0.62 m apart (σ = 1 m each, independent: d² = 0.385/2 ≈ 0.19) with one
    /// descriptor are one feature; a third key of the same look 10 m away (d² = 50 > χ²₃(0.9999)
    /// = 21.1) is another feature that looks alike; a key 1 m away with an unrelated look is
    /// not a candidate at all.
    #[test]
    fn one_feature_under_two_keys_is_merged_and_a_lookalike_far_away_is_not() {
        let f = filter_with(
            &[
                (10, [0.0, 0.0, 0.0], LOOK),
                (20, [0.5, 0.3, -0.2], LOOK),
                (40, [10.0, 0.0, 0.0], LOOK),
                (30, [1.0, 0.0, 0.0], OTHER),
            ],
            &[],
        );
        let r = f.find_correspondences(&CorrespondenceConfig::default());
        assert_eq!(r.merges, vec![merge(20, 10)]);
        assert_eq!(r.candidates, 3);
        assert_eq!(r.incompatible_pairs, vec![(10, 40), (20, 40)]);
        assert!(r.ambiguous_pairs.is_empty() && r.joint_rejected_pairs.is_empty());
    }

    /// Three keys of one feature merge into the smallest.
    #[test]
    fn three_keys_of_one_feature_merge_into_the_smallest() {
        let f = filter_with(
            &[
                (7, [0.3, 0.0, 0.0], LOOK),
                (5, [0.0, 0.2, 0.0], LOOK),
                (6, [0.0, 0.0, 0.4], LOOK),
            ],
            &[],
        );
        let r = f.find_correspondences(&CorrespondenceConfig::default());
        assert_eq!(r.merges, vec![merge(6, 5), merge(7, 5)]);
    }

    /// A chain 3 m apart: 1–2 and 2–3 fit (d² = 9/2 = 4.5 < 11.34), 1–3 does not at the strict
    /// gate (d² = 36/2 = 18 > χ²₃(0.99) = 11.34) but does at the wide one (18 < 21.1): which
    /// of 1 and 3 is 2? Nobody knows, so nothing is merged and all three pairs are ambiguous.
    #[test]
    fn an_ambiguous_group_is_left_apart() {
        let f = filter_with(
            &[
                (1, [0.0, 0.0, 0.0], LOOK),
                (2, [3.0, 0.0, 0.0], LOOK),
                (3, [6.0, 0.0, 0.0], LOOK),
            ],
            &[],
        );
        let r = f.find_correspondences(&CorrespondenceConfig::default());
        assert!(r.merges.is_empty());
        let mut amb = r.ambiguous_pairs.clone();
        amb.sort_unstable();
        assert_eq!(amb, vec![(1, 2), (1, 3), (2, 3)]);
    }

    /// Two groups, each alone inside the strict gate (d² = 10.0 and 9.5 < 11.34), together
    /// outside the joint one (19.5 > χ²₆(0.99) = 16.81): the worse group is dropped.
    #[test]
    fn the_joint_test_drops_the_worst_group() {
        let a = (20.0f64).sqrt(); // |δ|² = 2 d²: d² = 10
        let b = (19.0f64).sqrt(); // d² = 9.5
        let f = filter_with(
            &[
                (1, [0.0, 0.0, 0.0], LOOK),
                (2, [a, 0.0, 0.0], LOOK),
                (3, [100.0, 0.0, 0.0], OTHER),
                (4, [100.0, b, 0.0], OTHER),
            ],
            &[],
        );
        let r = f.find_correspondences(&CorrespondenceConfig::default());
        assert_eq!(r.merges, vec![merge(4, 3)]);
        assert_eq!(r.joint_rejected_pairs, vec![(1, 2)]);
    }

    /// The joint covariance decides, not the marginals: two keys 2 m apart whose errors are
    /// correlated 0.99 have a difference of variance 2(1 − 0.99) = 0.02 m² per axis, so
    /// d² = 4/0.02 = 200: incompatible, although independent estimates (d² = 2) would pass.
    /// The same pair uncorrelated is merged.
    #[test]
    fn correlated_estimates_are_judged_by_their_difference() {
        let feats = [(1, [0.0, 0.0, 0.0], LOOK), (2, [2.0, 0.0, 0.0], LOOK)];
        let r = filter_with(&feats, &[(0, 1, 0.99)]).find_correspondences(&Default::default());
        assert!(r.merges.is_empty());
        assert_eq!(r.incompatible_pairs, vec![(1, 2)]);
        let r = filter_with(&feats, &[]).find_correspondences(&Default::default());
        assert_eq!(r.merges, vec![merge(2, 1)]);
    }

    /// A lookalike 547 m away from a feature known to σ = 300 m per axis (as one received only
    /// through a neighbour's sparsified marginal can be) passes the χ² gate — d² = 547²/(2·300²)
    /// ≈ 1.66 < χ²₃(0.99) = 11.34 — which is how an eight-vehicle team on 128 kB/s radios
    /// adopted a wrong correspondence and diverged. Its difference's σ along the worst axis,
    /// √2·300 ≈ 424 m, is over the 20 m bound: undetermined, left apart. Without the bound
    /// (∞) the χ² gate alone merges it; the same geometry at σ = 1 m is incompatible.
    #[test]
    fn a_pair_known_too_loosely_is_left_undetermined() {
        let feats = [(1, [0.0, 0.0, 0.0], LOOK), (2, [547.0, 0.0, 0.0], LOOK)];
        let vague = filter_with_sigma(&feats, &[], 300.0);
        let r = vague.find_correspondences(&CorrespondenceConfig::default());
        assert!(r.merges.is_empty());
        assert_eq!(r.undetermined_pairs, vec![(1, 2)]);
        assert!(r.ambiguous_pairs.is_empty() && r.incompatible_pairs.is_empty());
        let unbounded = CorrespondenceConfig {
            max_difference_sigma_m: f64::INFINITY,
            ..Default::default()
        };
        assert_eq!(
            vague.find_correspondences(&unbounded).merges,
            vec![merge(2, 1)]
        );
        let precise = filter_with(&feats, &[]).find_correspondences(&Default::default());
        assert!(precise.merges.is_empty());
        assert_eq!(precise.incompatible_pairs, vec![(1, 2)]);
        // At the bound's edge: σ = 14 m per axis gives √2·14 ≈ 19.8 m ≤ 20 m, decided (two
        // keys 3 m apart: d² = 9/392 ≈ 0.02, one feature); σ = 14.2 m gives 20.08 m,
        // undetermined.
        let near = [(1, [0.0, 0.0, 0.0], LOOK), (2, [3.0, 0.0, 0.0], LOOK)];
        let r = filter_with_sigma(&near, &[], 14.0).find_correspondences(&Default::default());
        assert_eq!(r.merges, vec![merge(2, 1)]);
        let r = filter_with_sigma(&near, &[], 14.2).find_correspondences(&Default::default());
        assert_eq!(r.undetermined_pairs, vec![(1, 2)]);
    }

    /// A neighbour's correspondence is contradicted only when both keys are held and far
    /// apart in this estimate.
    #[test]
    fn a_contradicted_merge_is_recognised() {
        let f = filter_with(
            &[(1, [0.0, 0.0, 0.0], LOOK), (2, [10.0, 0.0, 0.0], LOOK)],
            &[],
        );
        assert!(f.merge_contradicted(&merge(2, 1), 0.9999));
        assert!(!f.merge_contradicted(&merge(9, 1), 0.9999));
        let g = filter_with(
            &[(1, [0.0, 0.0, 0.0], LOOK), (2, [0.5, 0.0, 0.0], LOOK)],
            &[],
        );
        assert!(!g.merge_contradicted(&merge(2, 1), 0.9999));
    }
}
