//! Feature keys and correspondences between them.
//!
//! Without the simulator's identities every vehicle names its features with its own keys
//! (its namespace in the high bits, a counter below), and two keys may later turn out to name
//! one physical feature: a neighbour's key the receiver associates with its own feature, or two
//! features of one map found to be one (a duplicate). A correspondence is a [`Merge`]: the key
//! `from` is renamed `into` (the smaller of the two, so every node that learns the same fact
//! ends with the same name).
//!
//! # Why a merge keeps the channel filters exact
//! A merge is a linear map of the state: x = T x′, where T copies the coordinates of `into`
//! into the slots of `from` (design.md §8). Information transforms as Y′ = Tᵀ Y T, y′ = Tᵀ y
//! ([`crate::info::MapInformation::rekeyed`]): the rows and columns of `from` are added to
//! those of `into` and removed — conditioning on x_from = x_into, then marginalising x_from.
//! Every channel-filter operation is a sum, and sums commute with T, so a node that applies T
//! to its estimate *and to every channel filter it holds* (S, R, R_total, buffered deltas,
//! baselines), and to every matrix that reaches it afterwards in the old key space, keeps each
//! link's bookkeeping equal, in the merged key space, to its neighbour's. T is idempotent on
//! merged-space matrices, so the order in which a node learns a fact and receives deltas that
//! already use it does not matter; a node that never learns (or refuses) a fact is still exact,
//! only less merged. The linear-Gaussian Monte Carlo in `fusion/tests/ddf_keys.rs` checks it.
//! T has no inverse: a wrong merge cannot be undone, so whoever proposes one must be
//! conservative.

use crate::sensor::FeatureId;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// `from` and `into` name one feature; `from` is renamed `into` (`into < from`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Merge {
    /// The key that disappears.
    pub from: FeatureId,
    /// The key that stays (the smaller one).
    pub into: FeatureId,
}

impl Merge {
    /// The merge that names `a` and `b` one feature (`None` when they are equal).
    pub fn of(a: FeatureId, b: FeatureId) -> Option<Self> {
        match a.cmp(&b) {
            std::cmp::Ordering::Equal => None,
            std::cmp::Ordering::Less => Some(Self { from: b, into: a }),
            std::cmp::Ordering::Greater => Some(Self { from: a, into: b }),
        }
    }
}

/// The correspondences a node has adopted: each merged key → its canonical key (the smallest
/// key of its class). Lookups are O(log n); every stored entry points at a canonical key.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct KeyMap {
    canonical: BTreeMap<FeatureId, FeatureId>,
}

impl KeyMap {
    /// The canonical key of `k` (itself when never merged).
    pub fn canonical(&self, k: FeatureId) -> FeatureId {
        self.canonical.get(&k).copied().unwrap_or(k)
    }

    /// Whether no merge was adopted.
    pub fn is_empty(&self) -> bool {
        self.canonical.is_empty()
    }

    /// Adopts "a and b are one feature". Returns the effective merge between their canonical
    /// keys (what must be applied to matrices already in the merged space), or `None` when they
    /// were one already.
    pub fn adopt(&mut self, a: FeatureId, b: FeatureId) -> Option<Merge> {
        let m = Merge::of(self.canonical(a), self.canonical(b))?;
        for c in self.canonical.values_mut() {
            if *c == m.from {
                *c = m.into;
            }
        }
        self.canonical.insert(m.from, m.into);
        Some(m)
    }

    /// Every merged key with its canonical key (what a restarted neighbour must be told).
    pub fn merges(&self) -> Vec<Merge> {
        self.canonical
            .iter()
            .map(|(&from, &into)| Merge { from, into })
            .collect()
    }

    /// Whether `ids` contains a key that is not canonical.
    pub fn touches(&self, ids: &[FeatureId]) -> bool {
        !self.canonical.is_empty() && ids.iter().any(|k| self.canonical.contains_key(k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn merges_are_canonical_and_transitive() {
        let mut k = KeyMap::default();
        assert_eq!(k.adopt(7, 7), None);
        assert_eq!(k.adopt(9, 4), Some(Merge { from: 9, into: 4 }));
        // 12 ≡ 9 ≡ 4: the effective merge is between canonical keys.
        assert_eq!(k.adopt(12, 9), Some(Merge { from: 12, into: 4 }));
        assert_eq!(k.adopt(12, 4), None);
        // 2 ≡ 12: the whole class moves to 2.
        assert_eq!(k.adopt(2, 12), Some(Merge { from: 4, into: 2 }));
        for key in [2, 4, 9, 12] {
            assert_eq!(k.canonical(key), 2);
        }
        assert_eq!(k.canonical(5), 5);
        assert!(k.touches(&[5, 9]));
        assert!(!k.touches(&[2, 5]));
        assert_eq!(k.merges().len(), 3);
    }
}
