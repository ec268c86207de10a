//! Simulated appearance instead of identity (`[world.appearance] identity = "appearance"`):
//! what a real feature tracker and descriptor extractor give an estimator, with the true
//! feature ids kept for the monitor only.
//!
//! # Model
//! - **Descriptors.** Every true feature gets a seeded 256-bit binary descriptor (uniform
//!   random bits, world seed stream [`STREAM_APPEARANCE`](super::STREAM_APPEARANCE)). A share
//!   `confusable_share` of the features (chosen uniformly, rounded to a count) are *confusable*:
//!   each copies the descriptor of another, non-confusable feature (uniform) with exactly
//!   `confusable_bits` distinct bits flipped — repeated texture that the descriptor alone
//!   cannot tell apart.
//! - **Noise per observation.** An observation carries the feature's descriptor with each bit
//!   flipped independently with probability
//!   p = p_min + (p_max − p_min)·(1 − (1 − s_r)(1 − s_v)),
//!   s_r = clamp((ρ − ρ_min)/(ρ_max − ρ_min), 0, 1) the true range ρ within the sensor's range
//!   limits, s_v = clamp(Δθ / `viewpoint_full_deg`, 0, 1) with Δθ the angle between the current
//!   line of sight to the feature and the one at which this vehicle first saw it. Both
//!   degradations are independent: p = p_min close by from the first viewpoint, p_max at the
//!   far range limit or from `viewpoint_full_deg` away. p_min = `bit_flip_min`, p_max =
//!   `bit_flip_max`.
//! - **Tracker.** Each vehicle's tracker gives every observation a track id: a feature keeps
//!   its track while it is observed in consecutive frames; its track breaks when it was missed
//!   in the previous frame (occlusion, out of view, beyond the observation cap) and, each
//!   frame, with probability `track_break_probability`. A broken track gets a fresh id; ids
//!   count up from 1 per vehicle and are never reused.
//! - **Association distance.** The default largest descriptor distance of an association
//!   candidate ([`default_max_distance`]) is the 99.9 % quantile of the Hamming distance
//!   between two independent noisy copies of one descriptor at p_max: per bit they differ with
//!   probability q = 2 p_max (1 − p_max), so the distance is Binomial(256, q). It covers an
//!   observation against a feature known from a single observation at the worst range and
//!   viewpoint (against a feature seen many times, whose bitwise majority approaches the true
//!   descriptor, the distance is only Binomial(256, p_max)).

use std::collections::HashMap;

use canopy_fusion::sensor::{Appearance, FeatureId};
use nalgebra::Vector3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use statrs::distribution::{Binomial, DiscreteCDF};

use crate::scenario::AppearanceConfig;

/// Bits of a descriptor.
pub const DESCRIPTOR_BITS: u32 = 256;

/// Quantile of the true-match distance the default association distance covers.
pub const MAX_DISTANCE_QUANTILE: f64 = 0.999;

/// The default `max_distance` of appearance association for a worst-case bit-flip
/// probability `bit_flip_max` (module docs, "Association distance").
pub fn default_max_distance(bit_flip_max: f64) -> u32 {
    let q = (2.0 * bit_flip_max * (1.0 - bit_flip_max)).clamp(0.0, 1.0);
    if q <= 0.0 {
        return 0;
    }
    // `q` is in (0, 1] and n > 0: the distribution exists.
    let d = Binomial::new(q, u64::from(DESCRIPTOR_BITS)).expect("valid binomial parameters");
    (0..=u64::from(DESCRIPTOR_BITS))
        .find(|&k| d.cdf(k) >= MAX_DISTANCE_QUANTILE)
        .map_or(DESCRIPTOR_BITS, |k| k as u32)
}

/// Flips bit `bit` (0–255) of a descriptor.
fn flip(a: &mut Appearance, bit: usize) {
    a[bit / 64] ^= 1 << (bit % 64);
}

/// The world's descriptors: one per feature, in feature order.
#[derive(Clone, Debug, PartialEq)]
pub struct AppearanceTable {
    descriptors: Vec<Appearance>,
    /// For a confusable feature, the index of the feature it is a near-copy of.
    copy_of: Vec<Option<usize>>,
    /// The configuration it was drawn with (the trackers' noise parameters).
    config: AppearanceConfig,
}

impl AppearanceTable {
    /// Draws the descriptors of `count` features (module docs, "Descriptors").
    pub fn new(count: usize, cfg: &AppearanceConfig, rng: &mut ChaCha8Rng) -> Self {
        let mut descriptors: Vec<Appearance> = (0..count).map(|_| rng.random()).collect();
        let mut copy_of = vec![None; count];
        let copies = ((cfg.confusable_share * count as f64).round() as usize).min(count / 2);
        if copies > 0 {
            // A uniform subset of `copies` features (partial Fisher–Yates), in index order.
            let mut order: Vec<usize> = (0..count).collect();
            for i in 0..copies {
                let j = rng.random_range(i..count);
                order.swap(i, j);
            }
            let mut chosen = order[..copies].to_vec();
            chosen.sort_unstable();
            let originals: Vec<usize> = order[copies..].to_vec();
            for &c in &chosen {
                let source = originals[rng.random_range(0..originals.len())];
                let mut a = descriptors[source];
                // `confusable_bits` distinct bits (partial Fisher–Yates over the 256).
                let mut bits: Vec<usize> = (0..DESCRIPTOR_BITS as usize).collect();
                for i in 0..cfg.confusable_bits as usize {
                    let j = rng.random_range(i..bits.len());
                    bits.swap(i, j);
                    flip(&mut a, bits[i]);
                }
                descriptors[c] = a;
                copy_of[c] = Some(source);
            }
        }
        Self {
            descriptors,
            copy_of,
            config: *cfg,
        }
    }

    /// The configuration it was drawn with.
    pub fn config(&self) -> &AppearanceConfig {
        &self.config
    }

    /// The descriptor of feature index `i` (id − 1).
    pub fn descriptor(&self, i: usize) -> Option<&Appearance> {
        self.descriptors.get(i)
    }

    /// The confusable features: (index, index of the feature it nearly copies).
    pub fn confusable_pairs(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.copy_of
            .iter()
            .enumerate()
            .filter_map(|(i, c)| c.map(|s| (i, s)))
    }

    /// Number of features.
    pub fn len(&self) -> usize {
        self.descriptors.len()
    }

    /// Whether the table is empty.
    pub fn is_empty(&self) -> bool {
        self.descriptors.is_empty()
    }
}

/// What a vehicle's tracker remembers of a feature.
#[derive(Clone, Copy, Debug)]
struct Seen {
    /// Its current track.
    track: u64,
    /// The frame it was last observed in.
    last_frame: u64,
    /// Unit line of sight (sensor → feature, world frame) when this vehicle first saw it.
    first_sight: Vector3<f64>,
}

/// One vehicle's descriptor extractor and tracker (module docs, "Noise per observation",
/// "Tracker").
#[derive(Clone, Debug)]
pub struct Tracker {
    bit_flip_min: f64,
    bit_flip_max: f64,
    viewpoint_full: f64,
    break_probability: f64,
    min_range: f64,
    max_range: f64,
    /// Frames seen so far (the current frame's number once [`Tracker::begin_frame`] ran).
    frame: u64,
    /// The last track id given (ids start at 1).
    last_track: u64,
    seen: HashMap<FeatureId, Seen>,
    flips: ChaCha8Rng,
    breaks: ChaCha8Rng,
}

/// A tracked, described observation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Described {
    /// The track id (the observation's descriptor for the estimator).
    pub track: u64,
    /// The noisy descriptor.
    pub appearance: Appearance,
    /// The bit-flip probability it was drawn with.
    pub flip_probability: f64,
}

impl Tracker {
    /// A tracker for a sensor with range limits [`min_range`, `max_range`] [m]; `flips` draws
    /// the descriptor noise, `breaks` the random track breaks.
    pub fn new(
        cfg: &AppearanceConfig,
        min_range: f64,
        max_range: f64,
        flips: ChaCha8Rng,
        breaks: ChaCha8Rng,
    ) -> Self {
        Self {
            bit_flip_min: cfg.bit_flip_min,
            bit_flip_max: cfg.bit_flip_max,
            viewpoint_full: cfg.viewpoint_full_deg.to_radians(),
            break_probability: cfg.track_break_probability,
            min_range,
            max_range,
            frame: 0,
            last_track: 0,
            seen: HashMap::new(),
            flips,
            breaks,
        }
    }

    /// Starts a new frame (call once per frame, before its observations).
    pub fn begin_frame(&mut self) {
        self.frame += 1;
    }

    /// The bit-flip probability at true range `range` [m] and viewpoint change `dtheta` [rad]
    /// (module docs).
    pub fn flip_probability(&self, range: f64, dtheta: f64) -> f64 {
        let span = self.max_range - self.min_range;
        let s_r = if span > 0.0 {
            ((range - self.min_range) / span).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let s_v = if self.viewpoint_full > 0.0 {
            (dtheta / self.viewpoint_full).clamp(0.0, 1.0)
        } else {
            1.0
        };
        self.bit_flip_min
            + (self.bit_flip_max - self.bit_flip_min) * (1.0 - (1.0 - s_r) * (1.0 - s_v))
    }

    /// A noisy copy of `a`: each bit flipped with probability `p`.
    pub fn noisy_copy(&mut self, a: &Appearance, p: f64) -> Appearance {
        let mut out = *a;
        if p > 0.0 {
            for bit in 0..DESCRIPTOR_BITS as usize {
                if self.flips.random::<f64>() < p {
                    flip(&mut out, bit);
                }
            }
        }
        out
    }

    /// The track of feature `id` in the current frame: kept when it was observed in the
    /// previous frame and no random break happens, a fresh id otherwise.
    pub fn track(&mut self, id: FeatureId, line_of_sight: &Vector3<f64>) -> (u64, Vector3<f64>) {
        let frame = self.frame;
        let p_break = self.break_probability;
        // The break is drawn for every continuing track, so the draws do not depend on
        // which tracks happen to continue.
        let continues = match self.seen.get(&id) {
            Some(s) if s.last_frame + 1 == frame => {
                !(p_break > 0.0 && self.breaks.random::<f64>() < p_break)
            }
            _ => false,
        };
        let fresh = if continues {
            None
        } else {
            self.last_track += 1;
            Some(self.last_track)
        };
        let entry = self.seen.entry(id).or_insert(Seen {
            track: 0,
            last_frame: 0,
            first_sight: *line_of_sight,
        });
        if let Some(t) = fresh {
            entry.track = t;
        }
        entry.last_frame = frame;
        (entry.track, entry.first_sight)
    }

    /// Describes one observation of feature `id` (descriptor `truth`) at true range `range`
    /// along the unit line of sight `line_of_sight` (world frame): its track and noisy
    /// descriptor.
    pub fn describe(
        &mut self,
        id: FeatureId,
        truth: &Appearance,
        range: f64,
        line_of_sight: &Vector3<f64>,
    ) -> Described {
        let (track, first) = self.track(id, line_of_sight);
        let dtheta = first.dot(line_of_sight).clamp(-1.0, 1.0).acos();
        let p = self.flip_probability(range, dtheta);
        Described {
            track,
            appearance: self.noisy_copy(truth, p),
            flip_probability: p,
        }
    }
}

#[cfg(test)]
mod tests {
    //! References: the binomial law of Hamming distances written out here by its own pmf
    //! recurrence (not statrs, which the code under test uses), exact corner values of the
    //! noise formula, and the tracker's id rules followed by hand.

    use std::collections::BTreeSet;

    use canopy_fusion::sensor::hamming;

    use super::*;
    use crate::scenario::Identity;
    use crate::world::rng_stream;

    fn cfg() -> AppearanceConfig {
        AppearanceConfig {
            identity: Identity::Appearance,
            ..AppearanceConfig::default()
        }
    }

    fn tracker(cfg: &AppearanceConfig, seed: u64) -> Tracker {
        Tracker::new(cfg, 10.0, 410.0, rng_stream(seed, 1), rng_stream(seed, 2))
    }

    /// The cdf of Binomial(n, q) at 0..=n by the pmf recurrence
    /// pmf(k+1) = pmf(k)·(n−k)/(k+1)·q/(1−q), pmf(0) = (1−q)ⁿ (0 < q < 1).
    fn binomial_cdf(n: u32, q: f64) -> Vec<f64> {
        let mut pmf = (1.0 - q).powi(n as i32);
        let mut acc = 0.0;
        let mut out = Vec::with_capacity(n as usize + 1);
        for k in 0..=n {
            acc += pmf;
            out.push(acc);
            pmf *= f64::from(n - k) / f64::from(k + 1) * q / (1.0 - q);
        }
        out
    }

    /// Kolmogorov–Smirnov distance between the empirical cdf of `samples` (values 0..=256)
    /// and `cdf`.
    fn ks_distance(samples: &[u32], cdf: &[f64]) -> f64 {
        let mut counts = vec![0usize; cdf.len()];
        for &s in samples {
            counts[s as usize] += 1;
        }
        let mut acc = 0usize;
        let mut worst = 0.0f64;
        for (k, c) in counts.iter().enumerate() {
            acc += c;
            worst = worst.max((acc as f64 / samples.len() as f64 - cdf[k]).abs());
        }
        worst
    }

    /// The distance between two independent noisy copies of one descriptor at flip probability
    /// p follows Binomial(256, 2p(1−p)) (a bit differs when exactly one copy flipped it), and
    /// one copy's distance from the original Binomial(256, p).
    #[test]
    fn noisy_copy_distances_follow_the_binomial_closed_form() {
        let p = 0.1;
        let mut t = tracker(&cfg(), 11);
        let mut rng = rng_stream(12, 0);
        let n = 20_000;
        let (mut pair, mut single) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for _ in 0..n {
            let truth: Appearance = rng.random();
            let a = t.noisy_copy(&truth, p);
            let b = t.noisy_copy(&truth, p);
            pair.push(hamming(&a, &b));
            single.push(hamming(&a, &truth));
        }
        let d_pair = ks_distance(&pair, &binomial_cdf(DESCRIPTOR_BITS, 2.0 * p * (1.0 - p)));
        let d_single = ks_distance(&single, &binomial_cdf(DESCRIPTOR_BITS, p));
        let mean = pair.iter().map(|&d| f64::from(d)).sum::<f64>() / n as f64;
        eprintln!(
            "KS pair {d_pair:.4}, single {d_single:.4}; mean pair distance {mean:.2} \
             (closed form {:.2})",
            256.0 * 2.0 * p * (1.0 - p)
        );
        // 1.95/√n: the KS critical value at α = 0.001 (conservative for a discrete law).
        let bound = 1.95 / (n as f64).sqrt();
        assert!(d_pair < bound, "{d_pair} ≥ {bound}");
        assert!(d_single < bound, "{d_single} ≥ {bound}");
        // A far law must fail the same test: the pair distance is not Binomial(256, p).
        assert!(ks_distance(&pair, &binomial_cdf(DESCRIPTOR_BITS, p)) > bound);
    }

    /// The default candidate distance is the 99.9 % quantile of Binomial(256, 2p(1−p)).
    #[test]
    fn default_max_distance_is_the_binomial_quantile() {
        assert_eq!(default_max_distance(0.0), 0);
        for p in [0.02, 0.1, 0.2, 0.3] {
            let cdf = binomial_cdf(DESCRIPTOR_BITS, 2.0 * p * (1.0 - p));
            let d = default_max_distance(p);
            eprintln!("p = {p}: max distance {d}");
            assert!(cdf[d as usize] >= MAX_DISTANCE_QUANTILE, "p = {p}");
            assert!(cdf[d as usize - 1] < MAX_DISTANCE_QUANTILE, "p = {p}");
        }
    }

    /// p = p_min near and head-on, p_max at the far limit or a full viewpoint change, and
    /// 1 − (1 − s_r)(1 − s_v) in between.
    #[test]
    fn flip_probability_grows_with_range_and_viewpoint() {
        let c = cfg(); // p_min 0.02, p_max 0.10, 60° full viewpoint
        let t = tracker(&c, 1);
        let full = 60f64.to_radians();
        assert_eq!(t.flip_probability(10.0, 0.0), 0.02);
        assert_eq!(t.flip_probability(5.0, 0.0), 0.02); // below the range limit: clamped
        assert!((t.flip_probability(410.0, 0.0) - 0.10).abs() < 1e-15); // 1 ulp-level round-off
        assert!((t.flip_probability(10.0, full) - 0.10).abs() < 1e-15);
        assert!((t.flip_probability(10.0, 2.0 * full) - 0.10).abs() < 1e-15);
        // s_r = s_v = ½: 0.02 + 0.08·(1 − ¼) = 0.08.
        assert!((t.flip_probability(210.0, full / 2.0) - 0.08).abs() < 1e-15);
    }

    /// Without random breaks a feature keeps its track while seen in consecutive frames; a
    /// missed frame breaks it; ids count up from 1 and are never reused.
    #[test]
    fn tracks_continue_break_on_a_miss_and_are_never_reused() {
        let c = AppearanceConfig {
            track_break_probability: 0.0,
            ..cfg()
        };
        let mut t = tracker(&c, 2);
        let los = Vector3::new(0.0, 0.0, 1.0);
        let frame = |t: &mut Tracker, ids: &[FeatureId]| -> Vec<u64> {
            t.begin_frame();
            ids.iter().map(|&id| t.track(id, &los).0).collect()
        };
        assert_eq!(frame(&mut t, &[5, 9]), vec![1, 2]);
        assert_eq!(frame(&mut t, &[9, 5]), vec![2, 1]);
        // 5 missed in frame 3: it comes back with a fresh id in frame 4; 9 continues.
        assert_eq!(frame(&mut t, &[9, 4]), vec![2, 3]);
        assert_eq!(frame(&mut t, &[5, 9, 4]), vec![4, 2, 3]);
        // Everything missed for a frame: all fresh, none reused.
        assert_eq!(frame(&mut t, &[]), Vec::<u64>::new());
        assert_eq!(frame(&mut t, &[4, 5, 9]), vec![5, 6, 7]);
    }

    /// With break probability b a continuing track breaks in a share b of the frames (within
    /// 5 binomial standard errors), and the first line of sight is kept across breaks.
    #[test]
    fn random_track_breaks_happen_at_the_configured_rate() {
        let b = 0.2;
        let c = AppearanceConfig {
            track_break_probability: b,
            ..cfg()
        };
        let mut t = tracker(&c, 3);
        let first = Vector3::new(1.0, 0.0, 0.0);
        let later = Vector3::new(0.0, 1.0, 0.0);
        t.begin_frame();
        let (mut track, sight) = t.track(1, &first);
        assert_eq!(sight, first);
        let (mut breaks, n) = (0usize, 20_000usize);
        for _ in 0..n {
            t.begin_frame();
            let (now, sight) = t.track(1, &later);
            assert_eq!(sight, first);
            if now != track {
                assert!(now > track, "ids count up");
                breaks += 1;
            }
            track = now;
        }
        let rate = breaks as f64 / n as f64;
        eprintln!("break rate {rate:.4} ({b})");
        assert!((rate - b).abs() < 5.0 * (b * (1.0 - b) / n as f64).sqrt());
    }

    /// A described observation takes its flip probability from range and viewpoint change: a
    /// perpendicular second view is beyond the 60° full change, so p = p_max.
    #[test]
    fn describe_uses_the_viewpoint_change_since_the_first_sight() {
        let mut t = tracker(&cfg(), 4);
        let truth = [7u64; 4];
        t.begin_frame();
        let d1 = t.describe(3, &truth, 10.0, &Vector3::new(1.0, 0.0, 0.0));
        assert_eq!(d1.flip_probability, 0.02);
        t.begin_frame();
        let d2 = t.describe(3, &truth, 10.0, &Vector3::new(0.0, 1.0, 0.0));
        assert!((d2.flip_probability - 0.10).abs() < 1e-15);
        assert_eq!(d1.track, d2.track);
    }

    /// The table: round(share·count) confusable features, each exactly `confusable_bits` from a
    /// non-confusable source; unrelated descriptors are far apart (Binomial(256, ½): mean 128,
    /// sd 8, so < 64 bits has probability ~1e-16 per pair); the same seed gives the same table.
    #[test]
    fn confusable_features_copy_a_source_within_the_configured_bits() {
        let c = AppearanceConfig {
            confusable_share: 0.1,
            confusable_bits: 8,
            ..cfg()
        };
        let table = AppearanceTable::new(200, &c, &mut rng_stream(9, 3));
        assert_eq!(table, AppearanceTable::new(200, &c, &mut rng_stream(9, 3)));
        let pairs: Vec<(usize, usize)> = table.confusable_pairs().collect();
        assert_eq!(pairs.len(), 20);
        let confusable: BTreeSet<usize> = pairs.iter().map(|p| p.0).collect();
        for &(i, s) in &pairs {
            assert!(!confusable.contains(&s), "a source is not itself a copy");
            let d = hamming(table.descriptor(i).unwrap(), table.descriptor(s).unwrap());
            assert_eq!(d, 8);
        }
        // Descriptors of one root (a source and its copies) are near; all others unrelated.
        let root = |i: usize| pairs.iter().find(|p| p.0 == i).map_or(i, |p| p.1);
        for i in 0..table.len() {
            for j in i + 1..table.len() {
                if root(i) != root(j) {
                    let d = hamming(table.descriptor(i).unwrap(), table.descriptor(j).unwrap());
                    assert!(d >= 64, "{i}, {j}: {d}");
                }
            }
        }
        // The share is capped at half the features.
        let all = AppearanceConfig {
            confusable_share: 0.5,
            ..c
        };
        assert_eq!(
            AppearanceTable::new(7, &all, &mut rng_stream(9, 3))
                .confusable_pairs()
                .count(),
            3
        );
    }
}
