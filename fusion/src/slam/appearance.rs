//! Appearance bookkeeping of [`AssociationMode::Appearance`](super::AssociationMode): what each
//! feature looks like (a bitwise majority of the 256-bit descriptors it was observed with) and
//! which tracker id currently follows which feature.
//!
//! A tracker id is short-lived (it breaks on occlusion and is never reused by an honest
//! tracker), so it is only a hint: an observation whose track follows a feature is tried against
//! that feature first, and everything else is associated by descriptor distance plus the χ² gate
//! (eq. 21.55) and joint compatibility over the frame.

use crate::sensor::{Appearance, FeatureId, hamming};
use std::collections::HashMap;

/// Counts of set bits over the descriptors a feature was seen with, and their bitwise majority
/// (kept current by [`Vote::add`] and [`Vote::absorb`]: it is read for every feature at every
/// fusion round and correspondence step, far more often than a vote changes).
#[derive(Clone, Debug)]
pub(super) struct Vote {
    counts: [u16; 256],
    n: u16,
    major: Appearance,
}

impl Vote {
    fn new() -> Self {
        Self {
            counts: [0; 256],
            n: 0,
            major: [0; 4],
        }
    }

    fn add(&mut self, a: &Appearance) {
        if self.n == u16::MAX {
            // Keep the proportions, forget half the history.
            for c in &mut self.counts {
                *c /= 2;
            }
            self.n /= 2;
        }
        self.n += 1;
        for (bit, c) in self.counts.iter_mut().enumerate() {
            if a[bit / 64] >> (bit % 64) & 1 == 1 {
                *c += 1;
            }
        }
        self.major = self.majority();
    }

    fn absorb(&mut self, other: &Vote) {
        for (c, o) in self.counts.iter_mut().zip(&other.counts) {
            *c = c.saturating_add(*o);
        }
        self.n = self.n.saturating_add(other.n);
        self.major = self.majority();
    }

    /// Bitwise majority (ties: set).
    fn majority(&self) -> Appearance {
        let mut a = [0u64; 4];
        for (bit, &c) in self.counts.iter().enumerate() {
            if 2 * u32::from(c) >= u32::from(self.n) && self.n > 0 {
                a[bit / 64] |= 1 << (bit % 64);
            }
        }
        a
    }
}

/// The filter's appearance book.
#[derive(Clone, Debug, Default)]
pub(super) struct AppearanceBook {
    /// Feature → its votes (own observations), or a descriptor a neighbour described.
    features: HashMap<FeatureId, Vote>,
    /// (vehicle, tracker id) → the feature the track follows.
    tracks: HashMap<(usize, u64), FeatureId>,
    /// Votes of tracks not (yet) linked to a feature (bearing-only tracks waiting to
    /// initialize).
    pending: HashMap<(usize, u64), Vote>,
}

impl AppearanceBook {
    /// What feature `f` looks like, if known.
    pub(super) fn of(&self, f: FeatureId) -> Option<Appearance> {
        self.features.get(&f).map(|v| v.major)
    }

    /// Whether feature `f` has a known appearance.
    pub(super) fn knows(&self, f: FeatureId) -> bool {
        self.features.contains_key(&f)
    }

    /// Hamming distance between an observation's descriptor and feature `f`'s (`None` when
    /// either is unknown).
    pub(super) fn distance(&self, a: &Option<Appearance>, f: FeatureId) -> Option<u32> {
        Some(hamming(a.as_ref()?, &self.of(f)?))
    }

    /// The feature track `(vehicle, track)` follows.
    pub(super) fn linked(&self, vehicle: usize, track: u64) -> Option<FeatureId> {
        self.tracks.get(&(vehicle, track)).copied()
    }

    /// An observation of `f` by track `(vehicle, track)`: links the track, counts the vote
    /// (and what the track saw before it was linked).
    pub(super) fn observed(
        &mut self,
        vehicle: usize,
        track: u64,
        f: FeatureId,
        a: &Option<Appearance>,
    ) {
        self.tracks.insert((vehicle, track), f);
        let vote = self.features.entry(f).or_insert_with(Vote::new);
        if let Some(p) = self.pending.remove(&(vehicle, track)) {
            vote.absorb(&p);
        }
        if let Some(a) = a {
            vote.add(a);
        }
    }

    /// An observation stored with a bearing-only track that is not a feature yet.
    pub(super) fn pending(&mut self, vehicle: usize, track: u64, a: &Option<Appearance>) {
        if let Some(a) = a {
            self.pending
                .entry((vehicle, track))
                .or_insert_with(Vote::new)
                .add(a);
        }
    }

    /// A neighbour's descriptor of `f`: kept unless this filter has its own votes for it.
    pub(super) fn described(&mut self, f: FeatureId, a: &Appearance) {
        self.features.entry(f).or_insert_with(|| {
            let mut v = Vote::new();
            v.add(a);
            v
        });
    }

    /// `from` merged into `into`: votes add, tracks follow.
    pub(super) fn merge(&mut self, from: FeatureId, into: FeatureId) {
        if let Some(v) = self.features.remove(&from) {
            self.features
                .entry(into)
                .or_insert_with(Vote::new)
                .absorb(&v);
        }
        for f in self.tracks.values_mut() {
            if *f == from {
                *f = into;
            }
        }
    }

    /// Forgets features no longer in the map, and tracks that follow them.
    pub(super) fn retain(&mut self, keep: impl Fn(FeatureId) -> bool) {
        self.features.retain(|f, _| keep(*f));
        self.tracks.retain(|_, f| keep(*f));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn majority_recovers_a_descriptor_from_noisy_copies() {
        let truth: Appearance = [0xDEAD_BEEF_0123_4567, 0x0F0F_0F0F_F0F0_F0F0, 7, u64::MAX];
        let mut book = AppearanceBook::default();
        // Five copies, each with a different 20 bits flipped: every bit is right in ≥ 4 of 5.
        for k in 0..5u32 {
            let mut a = truth;
            for j in 0..20u32 {
                let bit = (k * 20 + j) as usize;
                a[bit / 64] ^= 1 << (bit % 64);
            }
            book.observed(0, 9, 42, &Some(a));
        }
        assert_eq!(book.of(42), Some(truth));
        assert_eq!(book.linked(0, 9), Some(42));
        assert_eq!(book.distance(&Some(truth), 42), Some(0));
        book.merge(42, 7);
        assert_eq!(book.of(7), Some(truth));
        assert_eq!(book.linked(0, 9), Some(7));
        book.retain(|f| f != 7);
        assert_eq!((book.of(7), book.linked(0, 9)), (None, None));
    }
}
