//! Storage of a channel's map information (S, R and R_total of [`super::channel`]).
//!
//! A channel records sums of deltas over the features the link has carried. Dense 3N × 3N
//! copies of such sums (three per neighbour) were most of a vehicle process's memory, and
//! growing them re-allocated N² on every new feature. [`PackedInformation`] keeps the same
//! numbers exactly, in half the space and without re-allocation:
//!
//! * only the upper block triangle is stored (the information is symmetric: every delta is
//!   exactly symmetric, so is every sum of them; the wire form carries the same blocks);
//! * block column `c` (feature `ids[c]`) is its own allocation holding the 3 × 3 blocks
//!   (0, c) … (c, c), each column-major, so a new feature appends one block column and never
//!   moves the others.
//!
//! [`channel_delta`] forms the channel's outgoing delta d = Y_i − S − R directly from the dense
//! estimate and the two packed sums, block by block, keeping only the blocks above the
//! threshold: the same numbers, in the same order, as forming Y_i − S − R densely and then
//! [`MapInformation::sparsified_with`] (tested against that below), without the dense
//! temporaries.

use crate::info::{InfoError, MapInformation};
use crate::keys::KeyMap;
use crate::sensor::FeatureId;
use crate::state::FEATURE_DIM;
use faer::{Col, Mat};
use nalgebra::Vector3;
use std::collections::HashMap;

/// Entries of one 3 × 3 block.
const BLOCK: usize = FEATURE_DIM * FEATURE_DIM;

/// Symmetric map information in packed upper-block-triangle form (module docs). Also a
/// vehicle's batch of received deltas between two fusion rounds: half the memory of the dense
/// sum, and growing over a delta's new features appends block columns instead of copying the
/// whole matrix (`canopy-node`'s agent).
#[derive(Clone, Debug)]
pub struct PackedInformation {
    ids: Vec<FeatureId>,
    index: HashMap<FeatureId, usize>,
    origin: Vector3<f64>,
    /// `cols[c][BLOCK * r..BLOCK * (r + 1)]`: block (r, c), r ≤ c, column-major.
    cols: Vec<Vec<f64>>,
    /// y, 3 entries per feature.
    vector: Vec<f64>,
}

impl PackedInformation {
    /// No information, no features.
    pub fn zero(origin: Vector3<f64>) -> Self {
        Self {
            ids: Vec::new(),
            index: HashMap::new(),
            origin,
            cols: Vec::new(),
            vector: Vec::new(),
        }
    }

    /// True when every number held is exactly zero (or none is held).
    pub(crate) fn is_zero(&self) -> bool {
        self.vector.iter().all(|v| *v == 0.0) && self.cols.iter().flatten().all(|v| *v == 0.0)
    }

    /// Bytes held by the numbers (upper block triangle and y).
    #[cfg(test)]
    pub(crate) fn heap_bytes(&self) -> usize {
        std::mem::size_of::<f64>()
            * (self.cols.iter().map(Vec::len).sum::<usize>() + self.vector.len())
    }

    /// Block position of `id`, appending an all-zero feature when it is new.
    fn slot(&mut self, id: FeatureId) -> usize {
        if let Some(&k) = self.index.get(&id) {
            return k;
        }
        let k = self.ids.len();
        self.ids.push(id);
        self.index.insert(id, k);
        self.cols.push(vec![0.0; BLOCK * (k + 1)]);
        self.vector.extend_from_slice(&[0.0; FEATURE_DIM]);
        k
    }

    /// Entry (a, b) (axis within block) of block (p, q) of the full symmetric matrix.
    #[inline]
    fn entry(&self, p: usize, q: usize, a: usize, b: usize) -> f64 {
        if p <= q {
            self.cols[q][BLOCK * p + FEATURE_DIM * b + a]
        } else {
            self.cols[p][BLOCK * q + FEATURE_DIM * a + b]
        }
    }

    /// self += sign · info over the union of ids (order-stable: self's ids, then info's new
    /// ones in info's order), reading the upper block triangle of `info` in self's order (the
    /// diagonal blocks whole). Errors on an origin or shape mismatch before changing anything.
    pub fn accumulate(&mut self, info: &MapInformation, sign: f64) -> Result<(), InfoError> {
        check_origin(self.origin, info.origin)?;
        let n = FEATURE_DIM * info.ids.len();
        for (what, found) in [
            ("information matrix rows", info.matrix.nrows()),
            ("information matrix columns", info.matrix.ncols()),
            ("information vector", info.vector.nrows()),
        ] {
            if found != n {
                return Err(InfoError::Dimension {
                    what,
                    expected: n,
                    found,
                });
            }
        }
        let pos: Vec<usize> = info.ids.iter().map(|&id| self.slot(id)).collect();
        for (bj, &pj) in pos.iter().enumerate() {
            for (bi, &pi) in pos.iter().enumerate() {
                // Each stored block (min, max) once: from info's block at those positions.
                if pi > pj {
                    continue;
                }
                let dst = &mut self.cols[pj][BLOCK * pi..BLOCK * (pi + 1)];
                for b in 0..FEATURE_DIM {
                    let src = &info.matrix.col_as_slice(FEATURE_DIM * bj + b)
                        [FEATURE_DIM * bi..FEATURE_DIM * (bi + 1)];
                    for a in 0..FEATURE_DIM {
                        dst[FEATURE_DIM * b + a] += sign * src[a];
                    }
                }
            }
            for a in 0..FEATURE_DIM {
                self.vector[FEATURE_DIM * pj + a] += sign * info.vector[FEATURE_DIM * bj + a];
            }
        }
        Ok(())
    }

    /// Adds `(id, a, v)`: a·I to the feature's diagonal block and v to its vector (ids appended
    /// when new). The shifts of regularised sparsified marginals
    /// ([`crate::sparse::Marginal::shift`]: a = ∓δ, v = ∓δ x̄) are booked with it.
    pub(crate) fn add_diagonal(
        &mut self,
        entries: impl IntoIterator<Item = (FeatureId, f64, Vector3<f64>)>,
    ) {
        for (id, a, v) in entries {
            let k = self.slot(id);
            let diag = &mut self.cols[k][BLOCK * k..BLOCK * (k + 1)];
            for i in 0..FEATURE_DIM {
                diag[FEATURE_DIM * i + i] += a;
                self.vector[FEATURE_DIM * k + i] += v[i];
            }
        }
    }

    /// self += sign · other over the union of ids (order-stable like
    /// [`accumulate`](Self::accumulate)). Both must hold the same origin (every sum of one
    /// channel does: they are built from the node's own and validated received information).
    pub(crate) fn add_packed(&mut self, other: &PackedInformation, sign: f64) {
        debug_assert_eq!(
            self.origin, other.origin,
            "channel sums share the node's origin"
        );
        let pos: Vec<usize> = other.ids.iter().map(|&id| self.slot(id)).collect();
        for (q, &pq) in pos.iter().enumerate() {
            for (p, &pp) in pos.iter().enumerate().take(q + 1) {
                for b in 0..FEATURE_DIM {
                    for a in 0..FEATURE_DIM {
                        let v = other.entry(p, q, a, b);
                        let (r, c, ra, cb) = if pp <= pq {
                            (pp, pq, a, b)
                        } else {
                            (pq, pp, b, a)
                        };
                        self.cols[c][BLOCK * r + FEATURE_DIM * cb + ra] += sign * v;
                    }
                }
            }
            for a in 0..FEATURE_DIM {
                self.vector[FEATURE_DIM * pq + a] += sign * other.vector[FEATURE_DIM * q + a];
            }
        }
    }

    /// The packed form of (symmetric) `info`: its upper block triangle and y.
    pub fn from_dense(info: &MapInformation) -> Result<Self, InfoError> {
        let mut out = Self::zero(info.origin);
        out.accumulate(info, 1.0)?;
        Ok(out)
    }

    /// Feature ids, one per 3-block, in storage order.
    pub fn ids(&self) -> &[FeatureId] {
        &self.ids
    }

    /// Whether `id` has a block here.
    pub fn has(&self, id: FeatureId) -> bool {
        self.index.contains_key(&id)
    }

    /// The dense joint block (3n × 3n, both triangles) of `ids`, zero for ids without one.
    pub fn joint_block(&self, ids: &[FeatureId]) -> Mat<f64> {
        let blocks: Vec<(FeatureId, Option<usize>)> = ids
            .iter()
            .map(|&id| (id, self.index.get(&id).copied()))
            .collect();
        self.to_dense_gathered(&blocks).matrix
    }

    /// The dense form with its 3-blocks in the order of `blocks`: entry i is (id, Some(b)) for
    /// this information's block b, or (id, None) for a feature given zero information. The
    /// same numbers as the dense form followed by a gather of those blocks, with one dense
    /// matrix instead of two.
    pub fn to_dense_gathered(&self, blocks: &[(FeatureId, Option<usize>)]) -> MapInformation {
        let n = FEATURE_DIM * blocks.len();
        let mut matrix = Mat::<f64>::zeros(n, n);
        for (tj, &(_, q)) in blocks.iter().enumerate() {
            let Some(q) = q else { continue };
            for b in 0..FEATURE_DIM {
                let col = matrix.col_as_slice_mut(FEATURE_DIM * tj + b);
                for (ti, &(_, p)) in blocks.iter().enumerate() {
                    let Some(p) = p else { continue };
                    for a in 0..FEATURE_DIM {
                        col[FEATURE_DIM * ti + a] = self.entry(p, q, a, b);
                    }
                }
            }
        }
        let mut vector = Col::<f64>::zeros(n);
        for (t, &(_, b)) in blocks.iter().enumerate() {
            if let Some(b) = b {
                for a in 0..FEATURE_DIM {
                    vector[FEATURE_DIM * t + a] = self.vector[FEATURE_DIM * b + a];
                }
            }
        }
        MapInformation {
            ids: blocks.iter().map(|&(id, _)| id).collect(),
            origin: self.origin,
            matrix,
            vector,
        }
    }

    /// The dense form (both triangles), for the recovery messages that carry a whole sum.
    pub fn to_dense(&self) -> MapInformation {
        let blocks: Vec<(FeatureId, Option<usize>)> = self
            .ids
            .iter()
            .enumerate()
            .map(|(b, &id)| (id, Some(b)))
            .collect();
        self.to_dense_gathered(&blocks)
    }

    /// The same information in the key space of `keys` ([`MapInformation::rekeyed`]), in
    /// place: nothing moves when no merge touches these ids (every channel re-keys its sums on
    /// every merge the node adopts). Otherwise the merged sums are formed block by block in the
    /// packed form, with the same additions in the same order as re-keying the dense form and
    /// packing it (tested bit for bit), without its two dense k × k copies (54 MB each at
    /// 615 features).
    pub fn rekey(&mut self, keys: &KeyMap) {
        if !keys.touches(&self.ids) {
            return;
        }
        let (ids, index, target) = crate::info::rekey_targets(&self.ids, keys);
        let mut cols: Vec<Vec<f64>> = (0..ids.len()).map(|t| vec![0.0; BLOCK * (t + 1)]).collect();
        let mut vector = vec![0.0; FEATURE_DIM * ids.len()];
        // Source blocks (bi, bj) over the whole symmetric matrix, bj outer and bi inner as
        // `MapInformation::rekeyed` adds them; only target blocks of the upper block triangle
        // (diagonal blocks whole) are kept, as `from_dense` would keep them.
        for (bj, &tj) in target.iter().enumerate() {
            for a in 0..FEATURE_DIM {
                vector[FEATURE_DIM * tj + a] += self.vector[FEATURE_DIM * bj + a];
            }
            for (bi, &ti) in target.iter().enumerate() {
                if ti > tj {
                    continue;
                }
                let dst = &mut cols[tj][BLOCK * ti..BLOCK * (ti + 1)];
                for c in 0..FEATURE_DIM {
                    for r in 0..FEATURE_DIM {
                        dst[FEATURE_DIM * c + r] += self.entry(bi, bj, r, c);
                    }
                }
            }
        }
        self.ids = ids;
        self.index = index;
        self.cols = cols;
        self.vector = vector;
    }
}

fn check_origin(left: Vector3<f64>, right: Vector3<f64>) -> Result<(), InfoError> {
    if left != right {
        return Err(InfoError::OriginMismatch {
            left: left.into(),
            right: right.into(),
        });
    }
    Ok(())
}

/// Position of one feature of the union in Y (dense) and in the two packed sums.
#[derive(Clone, Copy)]
struct Where {
    y: Option<usize>,
    s: Option<usize>,
    r: Option<usize>,
}

/// The channel's outgoing delta d = Y − S − R over the union of ids (Y's, then S's new ones,
/// then R's), with every upper 3 × 3 block whose max-abs is at most `matrix_threshold`, and
/// every 3-block of y at most `vector_threshold`, left out, and the features that then carry
/// nothing dropped: exactly `y.sub(S).sub(R).sparsified_with(..)` of the dense forms (same
/// entries, same rounding: each is (Y − S) − R), without forming the dense difference.
pub(crate) fn channel_delta(
    y: &MapInformation,
    s: &PackedInformation,
    r: &PackedInformation,
    matrix_threshold: f64,
    vector_threshold: f64,
) -> Result<MapInformation, InfoError> {
    check_origin(y.origin, s.origin)?;
    check_origin(y.origin, r.origin)?;
    let ny = y.ids.len();
    if y.matrix.nrows() != FEATURE_DIM * ny
        || y.matrix.ncols() != FEATURE_DIM * ny
        || y.vector.nrows() != FEATURE_DIM * ny
    {
        return Err(InfoError::Dimension {
            what: "information matrix",
            expected: FEATURE_DIM * ny,
            found: y.matrix.nrows(),
        });
    }
    // The union, order-stable.
    let mut ids: Vec<FeatureId> = y.ids.clone();
    let mut at: HashMap<FeatureId, usize> = ids.iter().enumerate().map(|(k, &f)| (f, k)).collect();
    let mut places: Vec<Where> = (0..ny)
        .map(|k| Where {
            y: Some(k),
            s: None,
            r: None,
        })
        .collect();
    for (sum, is_s) in [(s, true), (r, false)] {
        for (k, &f) in sum.ids.iter().enumerate() {
            let u = *at.entry(f).or_insert_with(|| {
                ids.push(f);
                places.push(Where {
                    y: None,
                    s: None,
                    r: None,
                });
                ids.len() - 1
            });
            if is_s {
                places[u].s = Some(k);
            } else {
                places[u].r = Some(k);
            }
        }
    }
    let nf = ids.len();
    // Block (p, q) of d in union order, p ≤ q (diagonal blocks whole), into `out`.
    let block = |p: usize, q: usize, out: &mut [f64; BLOCK]| {
        let (wp, wq) = (places[p], places[q]);
        match (wp.y, wq.y) {
            (Some(yp), Some(yq)) => {
                for b in 0..FEATURE_DIM {
                    let col = y.matrix.col_as_slice(FEATURE_DIM * yq + b);
                    out[FEATURE_DIM * b..FEATURE_DIM * (b + 1)]
                        .copy_from_slice(&col[FEATURE_DIM * yp..FEATURE_DIM * (yp + 1)]);
                }
            }
            _ => *out = [0.0; BLOCK],
        }
        for (sum, (sp, sq)) in [(s, (wp.s, wq.s)), (r, (wp.r, wq.r))] {
            if let (Some(sp), Some(sq)) = (sp, sq) {
                if sp <= sq {
                    let src = &sum.cols[sq][BLOCK * sp..BLOCK * (sp + 1)];
                    for (o, v) in out.iter_mut().zip(src) {
                        *o -= v;
                    }
                } else {
                    let src = &sum.cols[sp][BLOCK * sq..BLOCK * (sq + 1)];
                    for b in 0..FEATURE_DIM {
                        for a in 0..FEATURE_DIM {
                            out[FEATURE_DIM * b + a] -= src[FEATURE_DIM * a + b];
                        }
                    }
                }
            }
        }
    };
    let vblock = |u: usize| -> [f64; FEATURE_DIM] {
        let w = places[u];
        let mut v = [0.0; FEATURE_DIM];
        if let Some(k) = w.y {
            for (a, x) in v.iter_mut().enumerate() {
                *x = y.vector[FEATURE_DIM * k + a];
            }
        }
        for (sum, k) in [(s, w.s), (r, w.r)] {
            if let Some(k) = k {
                for (a, x) in v.iter_mut().enumerate() {
                    *x -= sum.vector[FEATURE_DIM * k + a];
                }
            }
        }
        v
    };
    // One pass: every block above the threshold written at its place in the union (both
    // triangles), the features it joins kept. A block is kept only between kept features, so
    // dropping the features that carry nothing afterwards moves no kept entry.
    let n_all = FEATURE_DIM * nf;
    let mut matrix = Mat::<f64>::zeros(n_all, n_all);
    let mut vector = Col::<f64>::zeros(n_all);
    let mut keep = vec![false; nf];
    let mut buf = [0.0; BLOCK];
    for q in 0..nf {
        for p in 0..=q {
            block(p, q, &mut buf);
            let m = buf.iter().fold(0.0_f64, |m, v| m.max(v.abs()));
            if m > matrix_threshold {
                keep[p] = true;
                keep[q] = true;
                for b in 0..FEATURE_DIM {
                    let col = matrix.col_as_slice_mut(FEATURE_DIM * q + b);
                    col[FEATURE_DIM * p..FEATURE_DIM * (p + 1)]
                        .copy_from_slice(&buf[FEATURE_DIM * b..FEATURE_DIM * (b + 1)]);
                }
                if p != q {
                    for b in 0..FEATURE_DIM {
                        for a in 0..FEATURE_DIM {
                            matrix[(FEATURE_DIM * q + b, FEATURE_DIM * p + a)] =
                                buf[FEATURE_DIM * b + a];
                        }
                    }
                }
            }
        }
    }
    for (u, k) in keep.iter_mut().enumerate() {
        let v = vblock(u);
        if v.iter().any(|v| v.abs() > vector_threshold) {
            *k = true;
            for (a, x) in v.iter().enumerate() {
                vector[FEATURE_DIM * u + a] = *x;
            }
        }
    }
    if keep.iter().all(|k| *k) {
        return Ok(MapInformation {
            ids,
            origin: y.origin,
            matrix,
            vector,
        });
    }
    // Some features carry nothing: the kept rows and columns only (their blocks as written).
    let kept: Vec<usize> = (0..nf).filter(|&u| keep[u]).collect();
    let rows: Vec<usize> = kept
        .iter()
        .flat_map(|&u| FEATURE_DIM * u..FEATURE_DIM * (u + 1))
        .collect();
    let n = rows.len();
    // Gathered into a fresh k × k. An in-place compaction (equal bit for bit) was withdrawn
    // when the radio-32k team diverged more often with it (16 of 418 multi-process runs,
    // against 4 of 360); the divergence itself was the sparsified marginal's vector, now gated
    // (`sparse::VECTOR_GATE_PROBABILITY`; docs/benchmarks.md, "Seventh pass").
    let matrix = Mat::from_fn(n, n, |i, j| matrix[(rows[i], rows[j])]);
    let vector = Col::from_fn(n, |i| vector[rows[i]]);
    Ok(MapInformation {
        ids: kept.iter().map(|&u| ids[u]).collect(),
        origin: y.origin,
        matrix,
        vector,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// A random exactly symmetric information over `ids`, with some blocks exactly zero.
    fn random_info(rng: &mut ChaCha8Rng, ids: &[FeatureId]) -> MapInformation {
        let n = FEATURE_DIM * ids.len();
        let mut m = Mat::<f64>::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        for q in 0..ids.len() {
            for p in 0..ids.len() {
                if (p + 2 * q) % 5 == 0 && p != q {
                    for a in 0..FEATURE_DIM {
                        for b in 0..FEATURE_DIM {
                            m[(FEATURE_DIM * p + a, FEATURE_DIM * q + b)] = 0.0;
                        }
                    }
                }
            }
        }
        let sym = Mat::from_fn(n, n, |i, j| {
            if i / FEATURE_DIM <= j / FEATURE_DIM {
                m[(i, j)]
            } else {
                m[(j, i)]
            }
        });
        MapInformation {
            ids: ids.to_vec(),
            origin: Vector3::new(1.0, -2.0, 3.0),
            matrix: sym,
            vector: Col::from_fn(n, |_| rng.random_range(-1.0..1.0)),
        }
    }

    /// Packed sums equal the dense sums entry for entry (the same additions in the same order),
    /// the dense round trip is lossless, and the packed form holds about half the numbers.
    #[test]
    fn packed_sums_equal_dense_sums_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(151);
        let o = Vector3::new(1.0, -2.0, 3.0);
        let mut dense = MapInformation::zero(o);
        let mut packed = PackedInformation::zero(o);
        for step in 0..12 {
            let ids: Vec<FeatureId> = (0..(2 + step % 5))
                .map(|k| ((step * 7 + k * 3) % 17) as FeatureId)
                .collect();
            let mut ids = ids;
            ids.dedup();
            let mut seen = std::collections::HashSet::new();
            ids.retain(|k| seen.insert(*k));
            let d = random_info(&mut rng, &ids);
            let sign = if step % 3 == 2 { -1.0 } else { 1.0 };
            if sign > 0.0 {
                dense.add_assign(&d).unwrap();
            } else {
                dense.sub_assign(&d).unwrap();
            }
            packed.accumulate(&d, sign).unwrap();
            let back = packed.to_dense();
            assert_eq!(back.ids, dense.ids);
            assert_eq!(back.matrix, dense.matrix, "step {step}");
            assert_eq!(back.vector, dense.vector);
        }
        let round = PackedInformation::from_dense(&dense).unwrap().to_dense();
        assert_eq!(round.matrix, dense.matrix);
        let nf = dense.ids.len();
        let full = 8 * (FEATURE_DIM * nf) * (FEATURE_DIM * nf + 1);
        assert!(
            packed.heap_bytes() * 10 < full * 6,
            "{}",
            packed.heap_bytes()
        );
        // add_packed is accumulate of the dense form.
        let mut twice = packed.clone();
        twice.add_packed(&packed, 1.0);
        let mut dense2 = dense.clone();
        dense2.add_assign(&dense).unwrap();
        assert_eq!(twice.to_dense().matrix, dense2.matrix);
        // Origin and shape mismatches are errors and change nothing.
        let mut other = random_info(&mut rng, &[1, 2]);
        other.origin = Vector3::zeros();
        assert!(packed.accumulate(&other, 1.0).is_err());
        let mut short = random_info(&mut rng, &[1, 2]);
        short.vector = Col::zeros(5);
        assert!(packed.accumulate(&short, 1.0).is_err());
        assert_eq!(packed.to_dense().matrix, dense.matrix);
    }

    /// Re-keying in packed form gives the packed form of the re-keyed dense information, bit
    /// for bit: merges of two and of three features, into a key held or not, and a merge that
    /// touches none of the ids (nothing changes).
    #[test]
    fn packed_rekey_equals_the_dense_rekey_bit_for_bit() {
        let mut rng = ChaCha8Rng::seed_from_u64(153);
        let ids: Vec<FeatureId> = vec![5, 1, 9, 3, 7, 2];
        let bits = |m: &MapInformation| -> Vec<u64> {
            let n = m.matrix.nrows();
            (0..n)
                .flat_map(|j| (0..n).map(move |i| (i, j)))
                .map(|(i, j)| m.matrix[(i, j)].to_bits())
                .chain((0..n).map(|i| m.vector[i].to_bits()))
                .collect()
        };
        let merge_sets: [&[(FeatureId, FeatureId)]; 4] =
            [&[(9, 1)], &[(3, 5), (7, 5)], &[(2, 40)], &[(100, 101)]];
        for merges in merge_sets {
            let mut keys = KeyMap::default();
            for &(a, b) in merges {
                keys.adopt(a, b);
            }
            let info = random_info(&mut rng, &ids);
            let mut packed = PackedInformation::from_dense(&info).unwrap();
            let want = PackedInformation::from_dense(&packed.to_dense().rekeyed(&keys))
                .unwrap()
                .to_dense();
            packed.rekey(&keys);
            let got = packed.to_dense();
            assert_eq!(got.ids, want.ids, "{merges:?}");
            assert_eq!(bits(&got), bits(&want), "{merges:?}");
            assert_eq!(packed.index.len(), packed.ids.len());
        }
    }

    /// The delta formed from the packed sums is the dense Y − S − R, sparsified, bit for bit,
    /// with the union in the same order; with thresholds that drop blocks too.
    #[test]
    fn channel_delta_matches_the_dense_difference() {
        let mut rng = ChaCha8Rng::seed_from_u64(152);
        for case in 0..20 {
            let y_ids: Vec<FeatureId> = (0..(3 + case % 6)).map(|k| k as FeatureId).collect();
            // S over a subset of Y plus a feature Y no longer holds; R in another order.
            let s_ids: Vec<FeatureId> = vec![2, 0, 40, 1];
            let r_ids: Vec<FeatureId> = vec![41, 1, 3, 2];
            let y = random_info(&mut rng, &y_ids);
            let s = random_info(&mut rng, &s_ids);
            let mut r = random_info(&mut rng, &r_ids);
            // Make a few blocks of the difference vanish or become tiny.
            if case % 2 == 0 {
                r.matrix.as_mut().fill(0.0);
            }
            let (ps, pr) = (
                PackedInformation::from_dense(&s).unwrap(),
                PackedInformation::from_dense(&r).unwrap(),
            );
            let threshold = if case % 3 == 0 { 0.0 } else { 0.5 };
            let got = channel_delta(&y, &ps, &pr, threshold, 0.9 * threshold).unwrap();
            let mut dense = y.sub(&s).unwrap();
            dense.sub_assign(&r).unwrap();
            let want = dense.sparsified_with(threshold, 0.9 * threshold);
            assert_eq!(got.ids, want.ids, "case {case}");
            assert_eq!(got.matrix, want.matrix, "case {case}");
            assert_eq!(got.vector, want.vector, "case {case}");
        }
    }
}
