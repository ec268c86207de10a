//! Map information in information form, keyed by global feature id (eqs. 21.86, 21.87).
//!
//! Block `i` of a map vector or matrix (rows `3i..3i+3`) belongs to feature `ids[i]`.
//!
//! # Origin convention
//! ECEF coordinates are ~6.4e6 m; forming y = Y·x with them and subtracting such vectors across
//! vehicles would lose digits. Every [`MapInformation`] therefore carries a team-wide `origin`
//! o (the ECEF launch site in global SLAM, zero in local SLAM) and stores y = Y·(x_m − o) with the
//! origin subtracted from every feature. All nodes of a team share the same origin.

use crate::sensor::FeatureId;
use crate::state::FEATURE_DIM;
use faer::linalg::solvers::{DenseSolveCore, LltError, Solve};
use faer::{Col, Mat, Side};
use nalgebra::Vector3;
use std::collections::{HashMap, HashSet};

/// A vehicle's map marginal (x_m, P_mm) of eqs. 21.84, 21.85, keyed by feature id.
#[derive(Clone, Debug)]
pub struct MapMarginal {
    /// Feature ids, one per 3-block.
    pub ids: Vec<FeatureId>,
    /// Feature positions x_m in absolute frame coordinates (ECEF or local NED) [m].
    pub mean: Col<f64>,
    /// Covariance P_mm, 3n × 3n, symmetric positive definite.
    pub covariance: Mat<f64>,
}

/// Map information (Y, y) = (P_mm⁻¹, P_mm⁻¹ (x_m − o)) (eqs. 21.86, 21.87, origin convention
/// above), or a difference of two such (a delta, which may be indefinite).
#[derive(Clone, Debug)]
pub struct MapInformation {
    /// Feature ids, one per 3-block.
    pub ids: Vec<FeatureId>,
    /// The team-wide origin o subtracted from feature positions in `vector`.
    pub origin: Vector3<f64>,
    /// Y, 3n × 3n, symmetric.
    pub matrix: Mat<f64>,
    /// y, 3n.
    pub vector: Col<f64>,
}

/// Relative tolerance of the symmetry check: |a_ij − a_ji| ≤ `SYMMETRY_RTOL` · max_kl |a_kl|.
///
/// Why this value: matrices produced by Cholesky inverses or Joseph-form EKF updates are
/// symmetric to a few ulps times the condition number (~1e-12 relative for the 3N ≤ 1000 maps
/// here); 1e-9 accepts those with margin and still rejects any matrix that is not meant to be
/// symmetric (a hostile or corrupted one differs at O(1) relative).
pub const SYMMETRY_RTOL: f64 = 1e-9;

/// Size in bytes of one f64 on the wire.
const F64_BYTES: usize = std::mem::size_of::<f64>();
/// Bytes of an f32 entry on the wire.
const F32_BYTES: usize = std::mem::size_of::<f32>();
/// Size in bytes of one feature id on the wire (upper bound: bincode varint ≤ 9 bytes for u64;
/// we count the fixed 8 of a plain u64 plus one for the varint tag).
const ID_BYTES: usize = 9;
/// Upper bound of a length prefix (bincode varint of a usize).
const LEN_BYTES: usize = 9;
/// Upper bound of one block index (bincode varint of a u32: ≤ 5 bytes).
const BLOCK_INDEX_BYTES: usize = 5;

/// Errors of the map-information algebra.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InfoError {
    /// An array has the wrong size for the number of features.
    #[error("dimension mismatch in {what}: expected {expected}, found {found}")]
    Dimension {
        /// Which array.
        what: &'static str,
        /// Expected size (3 × number of features, or rows of a square matrix).
        expected: usize,
        /// Actual size.
        found: usize,
    },
    /// A feature id occurs twice in one id list.
    #[error("feature id {0} occurs twice")]
    DuplicateId(FeatureId),
    /// NaN or ±∞ in a matrix or vector.
    #[error("non-finite value in {what} at row {row}, column {col}")]
    NonFinite {
        /// Which array.
        what: &'static str,
        /// Row index.
        row: usize,
        /// Column index (0 for vectors).
        col: usize,
    },
    /// A matrix that must be symmetric is not (to [`SYMMETRY_RTOL`]).
    #[error(
        "{what} is not symmetric at ({row}, {col}): |a_ij - a_ji| = {asymmetry:e} > tolerance {tolerance:e}"
    )]
    NotSymmetric {
        /// Which matrix.
        what: &'static str,
        /// Row of the worst entry.
        row: usize,
        /// Column of the worst entry.
        col: usize,
        /// |a_ij − a_ji|.
        asymmetry: f64,
        /// The absolute tolerance it was compared with.
        tolerance: f64,
    },
    /// A Cholesky factorisation met a non-positive pivot.
    #[error(
        "{what} is not positive definite: Cholesky pivot {pivot} (feature {feature}, axis {axis}) is not positive"
    )]
    NotPositiveDefinite {
        /// Which matrix.
        what: &'static str,
        /// Index of the failing pivot (row of the 3N × 3N matrix).
        pivot: usize,
        /// Feature owning that row.
        feature: FeatureId,
        /// Axis (0, 1, 2) of that row within the feature block.
        axis: usize,
    },
    /// Two map informations with different team origins were combined.
    #[error("origin mismatch: {left:?} vs {right:?}")]
    OriginMismatch {
        /// Origin of the left operand.
        left: [f64; 3],
        /// Origin of the right operand.
        right: [f64; 3],
    },
    /// The symmetric eigenvalue solver did not converge.
    #[error("symmetric eigenvalue solver did not converge")]
    Eigen,
    /// The estimator could not form its map information (e.g. a map covariance that is not
    /// positive definite); the message says why.
    #[error("estimator: {0}")]
    Estimator(String),
}

/// Which 3 × 3 feature blocks of a (delta) map information are non-zero beyond a threshold.
///
/// Only the upper block triangle (`row ≤ col`) is listed: the matrix is symmetric.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BlockSparsity {
    /// Number of features (block rows).
    pub features: usize,
    /// Non-zero matrix blocks `(row, col)` with `row ≤ col`, in column-major block order.
    pub matrix_blocks: Vec<(usize, usize)>,
    /// Feature blocks of the vector y that are non-zero.
    pub vector_blocks: Vec<usize>,
}

impl BlockSparsity {
    /// Number of blocks in the upper block triangle of a dense matrix of this size.
    pub fn dense_upper_blocks(&self) -> usize {
        self.features * (self.features + 1) / 2
    }

    /// Fraction of the upper block triangle that is non-zero (0 for an empty map).
    pub fn density(&self) -> f64 {
        let total = self.dense_upper_blocks();
        if total == 0 {
            0.0
        } else {
            self.matrix_blocks.len() as f64 / total as f64
        }
    }

    /// True when no block is non-zero.
    pub fn is_empty(&self) -> bool {
        self.matrix_blocks.is_empty() && self.vector_blocks.is_empty()
    }
}

fn col_slice(c: &Col<f64>) -> &[f64] {
    c.try_as_col_major()
        .expect("an owned Col is contiguous")
        .as_slice()
}

fn col_slice_mut(c: &mut Col<f64>) -> &mut [f64] {
    c.try_as_col_major_mut()
        .expect("an owned Col is contiguous")
        .as_slice_mut()
}

/// Largest |entry| of a matrix (0 for an empty one; NaN entries are ignored — finiteness is
/// checked separately).
fn mat_norm_max(m: &Mat<f64>) -> f64 {
    (0..m.ncols())
        .map(|j| slice_norm_max(m.col_as_slice(j)))
        .fold(0.0, |a, b| if b > a { b } else { a })
}

/// Largest |entry| of a slice, written with plain comparisons so that it vectorises.
fn slice_norm_max(v: &[f64]) -> f64 {
    let mut best = [0.0_f64; 4];
    let chunks = v.chunks_exact(4);
    let rest = chunks.remainder();
    for c in chunks {
        for k in 0..4 {
            let a = c[k].abs();
            if a > best[k] {
                best[k] = a;
            }
        }
    }
    for &x in rest {
        let a = x.abs();
        if a > best[0] {
            best[0] = a;
        }
    }
    best.into_iter().fold(0.0, |a, b| if b > a { b } else { a })
}

/// Side of the square tiles in which the transposed-access loops run (two 32 × 32 f64 tiles
/// are 16 KiB: they stay in L1 while a tile pair is compared).
const TILE: usize = 32;

/// Largest |a_ij − a_ji| and where (i > j), visiting the matrix tile pair by tile pair so that
/// the transposed accesses stay in cache.
pub(crate) fn max_asymmetry(m: &Mat<f64>) -> (f64, usize, usize) {
    let n = m.nrows();
    let mut worst = (0.0_f64, 0, 0);
    for tj in (0..n).step_by(TILE) {
        let j1 = (tj + TILE).min(n);
        for ti in (tj..n).step_by(TILE) {
            let i1 = (ti + TILE).min(n);
            // Columns ti..i1 hold the transposed entries a_ji for rows j in tj..j1.
            let cols_i: Vec<&[f64]> = (ti..i1).map(|i| m.col_as_slice(i)).collect();
            for j in tj..j1 {
                let colj = m.col_as_slice(j);
                for (i, col_i) in cols_i.iter().enumerate().map(|(k, c)| (ti + k, c)) {
                    if i <= j {
                        continue;
                    }
                    let d = (colj[i] - col_i[j]).abs();
                    if d > worst.0 {
                        worst = (d, i, j);
                    }
                }
            }
        }
    }
    worst
}

fn check_ids(ids: &[FeatureId]) -> Result<(), InfoError> {
    let mut seen = HashSet::with_capacity(ids.len());
    for &id in ids {
        if !seen.insert(id) {
            return Err(InfoError::DuplicateId(id));
        }
    }
    Ok(())
}

/// True when every entry is finite (NaN and ±∞ have all exponent bits set), branch-free so
/// that it vectorises.
fn all_finite(v: &[f64]) -> bool {
    const EXP: u64 = 0x7ff0_0000_0000_0000;
    v.iter()
        .fold(true, |ok, &x| ok & (x.to_bits() & EXP != EXP))
}

fn check_finite_mat(what: &'static str, m: &Mat<f64>) -> Result<(), InfoError> {
    for j in 0..m.ncols() {
        let col = m.col_as_slice(j);
        if all_finite(col) {
            continue;
        }
        if let Some(i) = col.iter().position(|v| !v.is_finite()) {
            return Err(InfoError::NonFinite {
                what,
                row: i,
                col: j,
            });
        }
    }
    Ok(())
}

fn check_finite_col(what: &'static str, c: &Col<f64>) -> Result<(), InfoError> {
    match col_slice(c).iter().position(|v| !v.is_finite()) {
        Some(i) => Err(InfoError::NonFinite {
            what,
            row: i,
            col: 0,
        }),
        None => Ok(()),
    }
}

/// Whether every entry of `m` is finite, and its largest |entry| (NaN ignored): one pass
/// instead of [`check_finite_mat`] and [`mat_norm_max`] each reading the whole matrix.
pub(crate) fn finite_and_norm_max(m: &Mat<f64>) -> (bool, f64) {
    const EXP: u64 = 0x7ff0_0000_0000_0000;
    let mut finite = true;
    let mut best = [0.0_f64; 4];
    let mut tail = 0.0_f64;
    for j in 0..m.ncols() {
        let col = m.col_as_slice(j);
        let chunks = col.chunks_exact(4);
        let rest = chunks.remainder();
        for c in chunks {
            for k in 0..4 {
                finite &= c[k].to_bits() & EXP != EXP;
                let a = c[k].abs();
                if a > best[k] {
                    best[k] = a;
                }
            }
        }
        for &x in rest {
            finite &= x.to_bits() & EXP != EXP;
            let a = x.abs();
            if a > tail {
                tail = a;
            }
        }
    }
    let norm = best
        .into_iter()
        .fold(tail, |a, b| if b > a { b } else { a });
    (finite, norm)
}

/// Checks squareness against `n` and symmetry to [`SYMMETRY_RTOL`] relative to the largest entry.
fn check_square_symmetric(what: &'static str, m: &Mat<f64>, n: usize) -> Result<(), InfoError> {
    check_square_symmetric_scaled(what, m, n, mat_norm_max(m))
}

/// [`check_square_symmetric`] with the largest |entry| known.
fn check_square_symmetric_scaled(
    what: &'static str,
    m: &Mat<f64>,
    n: usize,
    norm_max: f64,
) -> Result<(), InfoError> {
    if m.nrows() != n {
        return Err(InfoError::Dimension {
            what,
            expected: n,
            found: m.nrows(),
        });
    }
    if m.ncols() != n {
        return Err(InfoError::Dimension {
            what,
            expected: n,
            found: m.ncols(),
        });
    }
    let tolerance = SYMMETRY_RTOL * norm_max;
    let worst = max_asymmetry(m);
    if worst.0 > tolerance {
        return Err(InfoError::NotSymmetric {
            what,
            row: worst.1,
            col: worst.2,
            asymmetry: worst.0,
            tolerance,
        });
    }
    Ok(())
}

/// Replaces `m` by (m + mᵀ)/2 (makes a numerically symmetric matrix exactly symmetric), tile
/// pair by tile pair (both halves of a tile pair stay in L1; the one implementation the crate
/// uses).
pub(crate) fn symmetrize(m: &mut Mat<f64>) {
    let n = m.nrows();
    let mut buf = vec![0.0; TILE * TILE];
    for tj in (0..n).step_by(TILE) {
        let j1 = (tj + TILE).min(n);
        for ti in (tj..n).step_by(TILE) {
            let i1 = (ti + TILE).min(n);
            // Average the lower-tile entries (i, j) with their transposes into buf…
            for j in tj..j1 {
                for i in ti.max(j + 1)..i1 {
                    buf[(j - tj) * TILE + (i - ti)] = m.col_as_slice(j)[i];
                }
            }
            for i in ti..i1 {
                let coli = m.col_as_slice(i);
                for j in tj..j1.min(i) {
                    let b = &mut buf[(j - tj) * TILE + (i - ti)];
                    *b = 0.5 * (*b + coli[j]);
                }
            }
            // …and write them back to both places.
            for j in tj..j1 {
                let colj = m.col_as_slice_mut(j);
                for i in ti.max(j + 1)..i1 {
                    colj[i] = buf[(j - tj) * TILE + (i - ti)];
                }
            }
            for i in ti..i1 {
                let coli = m.col_as_slice_mut(i);
                for j in tj..j1.min(i) {
                    coli[j] = buf[(j - tj) * TILE + (i - ti)];
                }
            }
        }
    }
}

/// (A)⁻¹ of a symmetric positive definite `a` (lower triangle read) by Cholesky, in one k × k
/// buffer besides `a` ([`spd_inverse_in`]; faer's `llt().inverse()` holds a, L, L⁻¹ and the
/// result). At 615 features one such buffer is 27 MB.
pub(crate) fn spd_inverse(a: faer::MatRef<'_, f64>) -> Result<Mat<f64>, LltError> {
    let n = a.nrows();
    let mut l = Mat::<f64>::zeros(n, n);
    l.copy_from_triangular_lower(a);
    spd_inverse_in(l)
}

/// (A + B)⁻¹ of symmetric `a` and `b` whose sum is positive definite (lower triangles read):
/// [`spd_inverse`] of the sum, bit for bit, with the sum formed straight into the factor's
/// buffer (no k × k buffer for it, and neither input changes).
pub(crate) fn spd_inverse_of_sum(
    a: faer::MatRef<'_, f64>,
    b: faer::MatRef<'_, f64>,
) -> Result<Mat<f64>, LltError> {
    let n = a.nrows();
    assert!(b.nrows() == n && a.ncols() == n && b.ncols() == n);
    let mut l = Mat::<f64>::zeros(n, n);
    for j in 0..n {
        let (ca, cb) = (a.col(j), b.col(j));
        let dst = &mut l.col_as_slice_mut(j)[j..];
        for (k, d) in dst.iter_mut().enumerate() {
            *d = ca[j + k] + cb[j + k];
        }
    }
    spd_inverse_in(l)
}

/// [`spd_inverse_of_sum`] with the sum formed in `a`'s own buffer (`a` is consumed, also on
/// an error): bit for bit the same (the same sums a + b, the same factorisation), one k × k
/// buffer fewer.
pub(crate) fn spd_inverse_of_sum_into(
    mut a: Mat<f64>,
    b: faer::MatRef<'_, f64>,
) -> Result<Mat<f64>, LltError> {
    let n = a.nrows();
    assert!(b.nrows() == n && a.ncols() == n && b.ncols() == n);
    for j in 0..n {
        let cb = b.col(j);
        let dst = &mut a.col_as_slice_mut(j)[j..];
        for (k, d) in dst.iter_mut().enumerate() {
            *d += cb[j + k];
        }
    }
    spd_inverse_in(a)
}

/// [`spd_inverse`] from `l` holding the matrix's lower triangle (its upper one ignored),
/// computed in `l`'s own buffer: A = L Lᵀ (Cholesky in place), X = L⁻¹ in place (blocked, as
/// LAPACK's `dtrtri`), A⁻¹ = Xᵀ X in place (blocked, as `dlauum`), mirrored. One k × k buffer
/// where the textbook route (factor, triangular inverse, product) holds two at a time: at
/// 620 features that is 27 MB less at the peak of every vehicle's fusion round. The same
/// n³ flops as faer's `llt().inverse()`, in gemm-sized blocks; it agrees with it to round-off
/// (test `in_place_spd_inverse_matches_faer`), not bit for bit.
fn spd_inverse_in(mut l: Mat<f64>) -> Result<Mat<f64>, LltError> {
    let n = l.nrows();
    let par = faer::get_global_parallelism();
    cholesky_lower_in_place(l.as_mut())?;
    for j in 0..n {
        for v in &mut l.col_as_slice_mut(j)[..j] {
            *v = 0.0;
        }
    }
    invert_lower_in_place(l.as_mut(), par);
    lower_gram_in_place(l.as_mut(), par);
    for j in 0..n {
        for i in 0..j {
            l[(i, j)] = l[(j, i)];
        }
    }
    Ok(l)
}

/// L with L Lᵀ = A in A's own buffer (faer's blocked Cholesky, no copy): reads the lower
/// triangle of `a` and overwrites it with L; the strict upper triangle is left as it was
/// (neither read nor cleared).
pub(crate) fn cholesky_lower_in_place(a: faer::MatMut<'_, f64>) -> Result<(), LltError> {
    use faer::dyn_stack::{MemBuffer, MemStack};
    use faer::linalg::cholesky::llt::factor;
    let par = faer::get_global_parallelism();
    let mut mem = MemBuffer::new(factor::cholesky_in_place_scratch::<f64>(
        a.nrows(),
        par,
        Default::default(),
    ));
    factor::cholesky_in_place(
        a,
        Default::default(),
        par,
        MemStack::new(&mut mem),
        Default::default(),
    )?;
    Ok(())
}

/// Block size of the in-place triangular inverse and Gram product: the diagonal blocks are
/// done by small kernels, everything else by gemm-shaped products of this width.
const INV_BLOCK: usize = 64;

/// X = L⁻¹ in place for lower triangular `a` (strict upper triangle zero, stays zero): LAPACK's
/// blocked `dtrtri` ('L', non-unit), right to left: with the blocks below and right of
/// diagonal block j already inverted (X₂₂), the block column below j becomes
/// −X₂₂ L_{2j} L_jj⁻¹, then L_jj is inverted.
fn invert_lower_in_place(mut a: faer::MatMut<'_, f64>, par: faer::Par) {
    use faer::linalg::matmul::triangular::{self, BlockStructure};
    let n = a.nrows();
    let mut j_end = n;
    while j_end > 0 {
        let j = (j_end - 1) / INV_BLOCK * INV_BLOCK;
        let jb = j_end - j;
        let mut inv_jj = Mat::<f64>::zeros(jb, jb);
        faer::linalg::triangular_inverse::invert_lower_triangular(
            inv_jj.as_mut(),
            a.as_ref().submatrix(j, j, jb, jb),
            par,
        );
        let m = n - j_end;
        if m > 0 {
            let (left, right) = a.as_mut().split_at_col_mut(j_end);
            let mut panel = left.submatrix_mut(j_end, j, m, jb);
            // T = L_{2j} L_jj⁻¹ (rectangular × lower triangular), then panel = −X₂₂ T.
            let mut t = Mat::<f64>::zeros(m, jb);
            triangular::matmul(
                t.as_mut(),
                BlockStructure::Rectangular,
                faer::Accum::Replace,
                panel.as_ref(),
                BlockStructure::Rectangular,
                inv_jj.as_ref(),
                BlockStructure::TriangularLower,
                1.0,
                par,
            );
            triangular::matmul(
                panel.as_mut(),
                BlockStructure::Rectangular,
                faer::Accum::Replace,
                right.as_ref().submatrix(j_end, 0, m, m),
                BlockStructure::TriangularLower,
                t.as_ref(),
                BlockStructure::Rectangular,
                -1.0,
                par,
            );
        }
        a.as_mut().submatrix_mut(j, j, jb, jb).copy_from(&inv_jj);
        j_end = j;
    }
}

/// Xᵀ X into the lower triangle of `a`, in place, for lower triangular X in `a` (strict upper
/// triangle zero): LAPACK's blocked `dlauum` ('L'), left to right; block row i is final once
/// X_iiᵀ times it plus the blocks below have been summed, and rows below i still hold X.
fn lower_gram_in_place(mut a: faer::MatMut<'_, f64>, par: faer::Par) {
    use faer::linalg::matmul::matmul;
    use faer::linalg::matmul::triangular::{self, BlockStructure};
    let n = a.nrows();
    let mut i = 0;
    while i < n {
        let ib = INV_BLOCK.min(n - i);
        let rest = n - i - ib;
        let (left, right) = a.as_mut().split_at_col_mut(i);
        let (left_top, left_below) = left.split_at_row_mut(i + ib);
        let (right_top, right_below) = right.split_at_row_mut(i + ib);
        let mut row = left_top.submatrix_mut(i, 0, ib, i); // X_{i,0..i}
        let mut diag = right_top.submatrix_mut(i, 0, ib, ib); // X_ii
        let x_ii = diag.as_ref().to_owned();
        if i > 0 {
            // row = X_iiᵀ row.
            let row_x = row.as_ref().to_owned();
            triangular::matmul(
                row.as_mut(),
                BlockStructure::Rectangular,
                faer::Accum::Replace,
                x_ii.transpose(),
                BlockStructure::TriangularUpper,
                row_x.as_ref(),
                BlockStructure::Rectangular,
                1.0,
                par,
            );
        }
        // diag = X_iiᵀ X_ii (lower triangle).
        triangular::matmul(
            diag.as_mut(),
            BlockStructure::TriangularLower,
            faer::Accum::Replace,
            x_ii.transpose(),
            BlockStructure::TriangularUpper,
            x_ii.as_ref(),
            BlockStructure::TriangularLower,
            1.0,
            par,
        );
        if rest > 0 {
            let below = right_below.as_ref().submatrix(0, 0, rest, ib); // X_{i+1.., i}
            if i > 0 {
                matmul(
                    row.as_mut(),
                    faer::Accum::Add,
                    below.transpose(),
                    left_below.as_ref(),
                    1.0,
                    par,
                );
            }
            triangular::matmul(
                diag.as_mut(),
                BlockStructure::TriangularLower,
                faer::Accum::Add,
                below.transpose(),
                BlockStructure::Rectangular,
                below,
                BlockStructure::Rectangular,
                1.0,
                par,
            );
        }
        i += ib;
    }
}

fn llt_error(what: &'static str, e: LltError, ids: &[FeatureId]) -> InfoError {
    let LltError::NonPositivePivot { index } = e;
    let block = index / FEATURE_DIM;
    InfoError::NotPositiveDefinite {
        what,
        pivot: index,
        feature: ids.get(block).copied().unwrap_or(FeatureId::MAX),
        axis: index % FEATURE_DIM,
    }
}

impl MapMarginal {
    /// Number of features.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True when the marginal holds no feature.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Checks dimensions, unique ids, finiteness and symmetry of P_mm (to [`SYMMETRY_RTOL`]).
    /// Positive definiteness is checked where it is needed (by the Cholesky of
    /// [`MapInformation::from_marginal`]).
    pub fn validate(&self) -> Result<(), InfoError> {
        check_ids(&self.ids)?;
        let n = FEATURE_DIM * self.ids.len();
        if self.mean.nrows() != n {
            return Err(InfoError::Dimension {
                what: "marginal mean",
                expected: n,
                found: self.mean.nrows(),
            });
        }
        check_finite_col("marginal mean", &self.mean)?;
        check_square_symmetric("marginal covariance", &self.covariance, n)?;
        check_finite_mat("marginal covariance", &self.covariance)
    }

    /// The marginal of a subset of features, in the order of `ids`; ids absent here are skipped.
    pub fn restrict(&self, ids: &[FeatureId]) -> MapMarginal {
        let index: HashMap<FeatureId, usize> = self
            .ids
            .iter()
            .enumerate()
            .map(|(k, &id)| (id, k))
            .collect();
        let picked: Vec<(FeatureId, usize)> = ids
            .iter()
            .filter_map(|id| index.get(id).map(|&k| (*id, k)))
            .collect();
        let n = FEATURE_DIM * picked.len();
        let rows: Vec<usize> = picked
            .iter()
            .flat_map(|&(_, k)| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * k + a))
            .collect();
        MapMarginal {
            ids: picked.iter().map(|&(id, _)| id).collect(),
            mean: Col::from_fn(n, |r| self.mean[rows[r]]),
            covariance: Mat::from_fn(n, n, |r, c| self.covariance[(rows[r], rows[c])]),
        }
    }
}

impl MapInformation {
    /// The empty map information (no features) with team origin `origin`: the neutral element of
    /// [`add`](Self::add).
    pub fn zero(origin: Vector3<f64>) -> Self {
        Self {
            ids: Vec::new(),
            origin,
            matrix: Mat::zeros(0, 0),
            vector: Col::zeros(0),
        }
    }

    /// Zero information over the given features (ids must be unique).
    pub fn zeros_over(ids: &[FeatureId], origin: Vector3<f64>) -> Result<Self, InfoError> {
        check_ids(ids)?;
        let n = FEATURE_DIM * ids.len();
        Ok(Self {
            ids: ids.to_vec(),
            origin,
            matrix: Mat::zeros(n, n),
            vector: Col::zeros(n),
        })
    }

    /// Number of features.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// True when no feature is present (the information is then zero).
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Block index of a feature id.
    pub fn index_of(&self, id: FeatureId) -> Option<usize> {
        self.ids.iter().position(|&k| k == id)
    }

    /// Information form of a map marginal (eqs. 21.86, 21.87 with the origin convention of this
    /// module): Y = P_mm⁻¹ by a Cholesky factorisation and its inverse, y = Y (x_m − o) by a
    /// solve against the same factor. Y is returned exactly symmetric.
    ///
    /// Errors: [`InfoError::NotPositiveDefinite`] naming the failing pivot and its feature, or
    /// any validation error of [`MapMarginal::validate`].
    pub fn from_marginal(marginal: &MapMarginal, origin: Vector3<f64>) -> Result<Self, InfoError> {
        marginal.validate()?;
        let n = FEATURE_DIM * marginal.ids.len();
        let llt = marginal
            .covariance
            .as_ref()
            .llt(Side::Lower)
            .map_err(|e| llt_error("marginal covariance", e, &marginal.ids))?;
        let mut matrix = llt.inverse();
        symmetrize(&mut matrix);
        let mut vector = Col::from_fn(n, |r| marginal.mean[r] - origin[r % FEATURE_DIM]);
        llt.solve_in_place(vector.as_mut());
        Ok(Self {
            ids: marginal.ids.clone(),
            origin,
            matrix,
            vector,
        })
    }

    /// Covariance form (eqs. 21.98, 21.99; 21.90, 21.91 at the hub): P_mm = Y⁻¹ by Cholesky,
    /// x_m = P_mm y + o (a solve against the same factor). P_mm is returned exactly symmetric.
    ///
    /// Errors: [`InfoError::NotPositiveDefinite`] naming the failing pivot (row of Y, its feature
    /// and axis) when Y is not positive definite, or a validation error.
    pub fn to_marginal(&self) -> Result<MapMarginal, InfoError> {
        self.validate()?;
        let llt = self
            .matrix
            .as_ref()
            .llt(Side::Lower)
            .map_err(|e| llt_error("information matrix", e, &self.ids))?;
        let mut covariance = llt.inverse();
        symmetrize(&mut covariance);
        let mut mean = self.vector.clone();
        llt.solve_in_place(mean.as_mut());
        for (r, m) in col_slice_mut(&mut mean).iter_mut().enumerate() {
            *m += self.origin[r % FEATURE_DIM];
        }
        Ok(MapMarginal {
            ids: self.ids.clone(),
            mean,
            covariance,
        })
    }

    /// Checks dimensions (Y is 3N × 3N, y is 3N), unique ids, finiteness of Y, y and the origin,
    /// and symmetry of Y to [`SYMMETRY_RTOL`]. Indefinite matrices pass: deltas may be
    /// indefinite (design.md §4); positive definiteness is checked on fused results.
    pub fn validate(&self) -> Result<(), InfoError> {
        check_ids(&self.ids)?;
        let n = FEATURE_DIM * self.ids.len();
        if let Some(i) = self.origin.iter().position(|v| !v.is_finite()) {
            return Err(InfoError::NonFinite {
                what: "origin",
                row: i,
                col: 0,
            });
        }
        if self.vector.nrows() != n {
            return Err(InfoError::Dimension {
                what: "information vector",
                expected: n,
                found: self.vector.nrows(),
            });
        }
        check_finite_col("information vector", &self.vector)?;
        // Finiteness and the scale in one pass (the error, if any, from the column scan).
        let (finite, norm_max) = finite_and_norm_max(&self.matrix);
        if !finite {
            check_finite_mat("information matrix", &self.matrix)?;
        }
        check_square_symmetric_scaled("information matrix", &self.matrix, n, norm_max)
    }

    fn check_origin(&self, other: &MapInformation) -> Result<(), InfoError> {
        if self.origin != other.origin {
            return Err(InfoError::OriginMismatch {
                left: self.origin.into(),
                right: other.origin.into(),
            });
        }
        Ok(())
    }

    fn check_shape(&self) -> Result<(), InfoError> {
        let n = FEATURE_DIM * self.ids.len();
        for (what, found) in [
            ("information matrix rows", self.matrix.nrows()),
            ("information matrix columns", self.matrix.ncols()),
            ("information vector", self.vector.nrows()),
        ] {
            if found != n {
                return Err(InfoError::Dimension {
                    what,
                    expected: n,
                    found,
                });
            }
        }
        Ok(())
    }

    /// Block positions of `other`'s features in `self`, appending the ids `self` lacks (in
    /// `other`'s order) and growing Y and y with zeros for them.
    fn align_to(&mut self, other: &MapInformation) -> Vec<usize> {
        let mut index: HashMap<FeatureId, usize> = self
            .ids
            .iter()
            .enumerate()
            .map(|(k, &id)| (id, k))
            .collect();
        let old = self.ids.len();
        let map: Vec<usize> = other
            .ids
            .iter()
            .map(|&id| {
                *index.entry(id).or_insert_with(|| {
                    self.ids.push(id);
                    self.ids.len() - 1
                })
            })
            .collect();
        if self.ids.len() != old {
            let (n_old, n_new) = (FEATURE_DIM * old, FEATURE_DIM * self.ids.len());
            let mut matrix = Mat::zeros(n_new, n_new);
            matrix
                .as_mut()
                .submatrix_mut(0, 0, n_old, n_old)
                .copy_from(self.matrix.as_ref());
            let mut vector = Col::zeros(n_new);
            col_slice_mut(&mut vector)[..n_old].copy_from_slice(col_slice(&self.vector));
            self.matrix = matrix;
            self.vector = vector;
        }
        map
    }

    /// self += sign · other over the union of ids (order-stable: self's ids, then other's new
    /// ones in other's order).
    fn accumulate(&mut self, other: &MapInformation, sign: f64) -> Result<(), InfoError> {
        self.check_origin(other)?;
        self.check_shape()?;
        other.check_shape()?;
        if self.ids == other.ids {
            for j in 0..self.matrix.ncols() {
                let src = other.matrix.col_as_slice(j);
                for (d, s) in self.matrix.col_as_slice_mut(j).iter_mut().zip(src) {
                    *d += sign * s;
                }
            }
            for (d, s) in col_slice_mut(&mut self.vector)
                .iter_mut()
                .zip(col_slice(&other.vector))
            {
                *d += sign * s;
            }
            return Ok(());
        }
        let map = self.align_to(other);
        let rows: Vec<usize> = map
            .iter()
            .flat_map(|&k| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * k + a))
            .collect();
        for (j, &tj) in rows.iter().enumerate() {
            let src = other.matrix.col_as_slice(j);
            let dst = self.matrix.col_as_slice_mut(tj);
            for (&ti, s) in rows.iter().zip(src) {
                dst[ti] += sign * s;
            }
        }
        let dst = col_slice_mut(&mut self.vector);
        for (&ti, s) in rows.iter().zip(col_slice(&other.vector)) {
            dst[ti] += sign * s;
        }
        Ok(())
    }

    /// (Y, y) += (Y_o, y_o), aligned by feature id over the union (order-stable: this map's ids
    /// first, then `other`'s new ids in `other`'s order). Errors on an origin or shape mismatch
    /// before touching `self`.
    pub fn add_assign(&mut self, other: &MapInformation) -> Result<(), InfoError> {
        self.accumulate(other, 1.0)
    }

    /// (Y, y) −= (Y_o, y_o), aligned like [`add_assign`](Self::add_assign).
    pub fn sub_assign(&mut self, other: &MapInformation) -> Result<(), InfoError> {
        self.accumulate(other, -1.0)
    }

    /// self + other over the union of ids (see [`add_assign`](Self::add_assign)).
    pub fn add(&self, other: &MapInformation) -> Result<MapInformation, InfoError> {
        let mut out = self.clone();
        out.accumulate(other, 1.0)?;
        Ok(out)
    }

    /// self − other over the union of ids (see [`add_assign`](Self::add_assign)).
    pub fn sub(&self, other: &MapInformation) -> Result<MapInformation, InfoError> {
        let mut out = self.clone();
        out.accumulate(other, -1.0)?;
        Ok(out)
    }

    /// self − a − b over the union of ids, in one pass when all three have the same ids (the
    /// channel filter's d = Y_i − S − R, eq. 21.94 per link).
    pub fn sub_both(
        &self,
        a: &MapInformation,
        b: &MapInformation,
    ) -> Result<MapInformation, InfoError> {
        if self.ids != a.ids || self.ids != b.ids {
            let mut out = self.sub(a)?;
            out.sub_assign(b)?;
            return Ok(out);
        }
        self.check_origin(a)?;
        self.check_origin(b)?;
        self.check_shape()?;
        a.check_shape()?;
        b.check_shape()?;
        let n = self.matrix.nrows();
        let mut matrix = Mat::zeros(n, n);
        for j in 0..n {
            let (x, y, z) = (
                self.matrix.col_as_slice(j),
                a.matrix.col_as_slice(j),
                b.matrix.col_as_slice(j),
            );
            for (((d, x), y), z) in matrix.col_as_slice_mut(j).iter_mut().zip(x).zip(y).zip(z) {
                *d = x - y - z;
            }
        }
        let (x, y, z) = (
            col_slice(&self.vector),
            col_slice(&a.vector),
            col_slice(&b.vector),
        );
        let vector = Col::from_fn(n, |r| x[r] - y[r] - z[r]);
        Ok(MapInformation {
            ids: self.ids.clone(),
            origin: self.origin,
            matrix,
            vector,
        })
    }

    /// s · (Y, y).
    pub fn scaled(&self, s: f64) -> MapInformation {
        let mut out = self.clone();
        out.matrix *= s;
        out.vector *= s;
        out
    }

    /// The blocks of the given features, in the order of `ids`; ids absent here are skipped.
    ///
    /// This is block *extraction* (the information of the features conditioned on all others),
    /// not marginalisation: the marginal information of a subset is the inverse of the
    /// corresponding block of P_mm (see [`MapMarginal::restrict`]).
    pub fn restrict(&self, ids: &[FeatureId]) -> MapInformation {
        let index: HashMap<FeatureId, usize> = self
            .ids
            .iter()
            .enumerate()
            .map(|(k, &id)| (id, k))
            .collect();
        let picked: Vec<(FeatureId, usize)> = ids
            .iter()
            .filter_map(|id| index.get(id).map(|&k| (*id, k)))
            .collect();
        let n = FEATURE_DIM * picked.len();
        let rows: Vec<usize> = picked
            .iter()
            .flat_map(|&(_, k)| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * k + a))
            .collect();
        MapInformation {
            ids: picked.iter().map(|&(id, _)| id).collect(),
            origin: self.origin,
            matrix: Mat::from_fn(n, n, |r, c| self.matrix[(rows[r], rows[c])]),
            vector: Col::from_fn(n, |r| self.vector[rows[r]]),
        }
    }

    /// The same information in the key space of `keys` (module [`crate::keys`]): Y′ = Tᵀ Y T,
    /// y′ = Tᵀ y, i.e. the rows and columns of every merged key are added to those of its
    /// canonical key. Blocks keep their first-appearance order; a map no merge touches is
    /// returned as is.
    pub fn rekeyed(&self, keys: &crate::keys::KeyMap) -> MapInformation {
        if !keys.touches(&self.ids) {
            return self.clone();
        }
        let (ids, _, target) = rekey_targets(&self.ids, keys);
        let n = FEATURE_DIM * ids.len();
        let mut matrix = Mat::zeros(n, n);
        let mut vector = Col::zeros(n);
        let d = FEATURE_DIM;
        for (bj, &tj) in target.iter().enumerate() {
            for a in 0..d {
                vector[d * tj + a] += self.vector[d * bj + a];
            }
            for (bi, &ti) in target.iter().enumerate() {
                for c in 0..d {
                    for r in 0..d {
                        matrix[(d * ti + r, d * tj + c)] += self.matrix[(d * bi + r, d * bj + c)];
                    }
                }
            }
        }
        MapInformation {
            ids,
            origin: self.origin,
            matrix,
            vector,
        }
    }

    /// [`rekeyed`](Self::rekeyed) in place: nothing is copied when no merge touches this map.
    pub fn rekey(&mut self, keys: &crate::keys::KeyMap) {
        if keys.touches(&self.ids) {
            *self = self.rekeyed(keys);
        }
    }

    /// Largest |entry| of Y.
    pub fn matrix_norm_max(&self) -> f64 {
        mat_norm_max(&self.matrix)
    }

    /// Largest |entry| of y.
    pub fn vector_norm_max(&self) -> f64 {
        slice_norm_max(col_slice(&self.vector))
    }

    /// Frobenius norm of Y.
    pub fn matrix_norm_frobenius(&self) -> f64 {
        self.matrix.norm_l2()
    }

    /// Euclidean norm of y.
    pub fn vector_norm(&self) -> f64 {
        self.vector.norm_l2()
    }

    /// True when every entry of Y and y is at most `threshold` in magnitude.
    pub fn is_zero(&self, threshold: f64) -> bool {
        self.matrix_norm_max() <= threshold && self.vector_norm_max() <= threshold
    }

    /// Largest eigenvalue of the symmetric Y (−∞ for an empty map). For the PSD order:
    /// A ⪯ B ⇔ `A.sub(&B)?.max_eigenvalue()? ≤ 0` (see [`psd_excess_over`](Self::psd_excess_over)).
    pub fn max_eigenvalue(&self) -> Result<f64, InfoError> {
        Ok(self
            .eigenvalues()?
            .last()
            .copied()
            .unwrap_or(f64::NEG_INFINITY))
    }

    /// Smallest eigenvalue of the symmetric Y (+∞ for an empty map).
    pub fn min_eigenvalue(&self) -> Result<f64, InfoError> {
        Ok(self
            .eigenvalues()?
            .first()
            .copied()
            .unwrap_or(f64::INFINITY))
    }

    /// Eigenvalues of Y in non-decreasing order (Y must be symmetric; only the lower triangle is
    /// read).
    pub fn eigenvalues(&self) -> Result<Vec<f64>, InfoError> {
        self.check_shape()?;
        if self.ids.is_empty() {
            return Ok(Vec::new());
        }
        self.matrix
            .as_ref()
            .self_adjoint_eigenvalues(Side::Lower)
            .map_err(|_| InfoError::Eigen)
    }

    /// λ_max(Y_self − Y_other) over the union of ids: ≤ 0 iff self ⪯ other in the PSD order
    /// (this map holds no more information than `other` in any direction).
    pub fn psd_excess_over(&self, other: &MapInformation) -> Result<f64, InfoError> {
        self.sub(other)?.max_eigenvalue()
    }

    /// Largest relative difference to a reference over the union of ids:
    /// max(max|Y − Y_ref| / max|Y_ref|, max|y − y_ref| / max|y_ref|) (a zero reference norm
    /// counts as 1 so that the measure stays finite).
    pub fn relative_difference(&self, reference: &MapInformation) -> Result<f64, InfoError> {
        let d = self.sub(reference)?;
        let ym = reference.matrix_norm_max();
        let yv = reference.vector_norm_max();
        let ym = if ym > 0.0 { ym } else { 1.0 };
        let yv = if yv > 0.0 { yv } else { 1.0 };
        Ok((d.matrix_norm_max() / ym).max(d.vector_norm_max() / yv))
    }

    /// Which 3 × 3 blocks of Y (upper block triangle) and 3-blocks of y exceed `threshold` in
    /// max-abs. With `threshold = 0` exactly the blocks holding a non-zero entry are listed.
    pub fn block_sparsity(&self, threshold: f64) -> BlockSparsity {
        self.block_sparsity_with(threshold, threshold)
    }

    /// [`block_sparsity`](Self::block_sparsity) with separate thresholds for Y and y (they have
    /// different units: y = Y (x − o) carries an extra length).
    pub fn block_sparsity_with(
        &self,
        matrix_threshold: f64,
        vector_threshold: f64,
    ) -> BlockSparsity {
        let nf = self.ids.len();
        let mut matrix_blocks = Vec::new();
        for bc in 0..nf {
            for br in 0..=bc {
                if self.block_max(br, bc) > matrix_threshold {
                    matrix_blocks.push((br, bc));
                }
            }
        }
        let y = col_slice(&self.vector);
        let vector_blocks = (0..nf)
            .filter(|&b| {
                y[FEATURE_DIM * b..FEATURE_DIM * (b + 1)]
                    .iter()
                    .any(|v| v.abs() > vector_threshold)
            })
            .collect();
        BlockSparsity {
            features: nf,
            matrix_blocks,
            vector_blocks,
        }
    }

    /// Max-abs of the 3 × 3 block (br, bc) of Y.
    fn block_max(&self, br: usize, bc: usize) -> f64 {
        let mut m = 0.0_f64;
        for c in 0..FEATURE_DIM {
            let col = self.matrix.col_as_slice(FEATURE_DIM * bc + c);
            for v in &col[FEATURE_DIM * br..FEATURE_DIM * (br + 1)] {
                let a = v.abs();
                if a > m {
                    m = a;
                }
            }
        }
        m
    }

    /// A copy with every block at or below `threshold` (see
    /// [`block_sparsity`](Self::block_sparsity)) set to zero, symmetric blocks together, and the
    /// features whose row blocks and vector block are then all zero removed. With
    /// `threshold = 0` this only drops features that carry nothing, losslessly.
    pub fn sparsified(&self, threshold: f64) -> MapInformation {
        self.sparsified_with(threshold, threshold)
    }

    /// [`sparsified`](Self::sparsified) with separate thresholds for Y and y.
    pub fn sparsified_with(&self, matrix_threshold: f64, vector_threshold: f64) -> MapInformation {
        let sparsity = self.block_sparsity_with(matrix_threshold, vector_threshold);
        let nf = self.ids.len();
        let mut keep = vec![false; nf];
        for &(br, bc) in &sparsity.matrix_blocks {
            keep[br] = true;
            keep[bc] = true;
        }
        for &b in &sparsity.vector_blocks {
            keep[b] = true;
        }
        let kept: Vec<usize> = (0..nf).filter(|&b| keep[b]).collect();
        // Which (row block, column block) pairs are copied, both triangles.
        let mut copy = vec![false; nf * nf];
        for &(br, bc) in &sparsity.matrix_blocks {
            copy[br + nf * bc] = true;
            copy[bc + nf * br] = true;
        }
        let n = FEATURE_DIM * kept.len();
        let mut out = MapInformation {
            ids: kept.iter().map(|&b| self.ids[b]).collect(),
            origin: self.origin,
            matrix: Mat::zeros(n, n),
            vector: Col::zeros(n),
        };
        // Column by column, 3-entry runs: contiguous reads and writes (column-major).
        for (tc, &bc) in kept.iter().enumerate() {
            for c in 0..FEATURE_DIM {
                let src = self.matrix.col_as_slice(FEATURE_DIM * bc + c);
                let dst = out.matrix.col_as_slice_mut(FEATURE_DIM * tc + c);
                for (tr, &br) in kept.iter().enumerate() {
                    if copy[br + nf * bc] {
                        dst[FEATURE_DIM * tr..FEATURE_DIM * (tr + 1)]
                            .copy_from_slice(&src[FEATURE_DIM * br..FEATURE_DIM * (br + 1)]);
                    }
                }
            }
        }
        let mut is_vector_block = vec![false; nf];
        for &b in &sparsity.vector_blocks {
            is_vector_block[b] = true;
        }
        for (t, &b) in kept.iter().enumerate() {
            if is_vector_block[b] {
                for a in 0..FEATURE_DIM {
                    out.vector[FEATURE_DIM * t + a] = self.vector[FEATURE_DIM * b + a];
                }
            }
        }
        out
    }

    /// Bytes of a dense encoding: ids, origin, every entry of Y and y as f64 (length prefixes
    /// included as upper bounds).
    pub fn dense_wire_bytes(&self) -> usize {
        let n = FEATURE_DIM * self.ids.len();
        3 * LEN_BYTES + ID_BYTES * self.ids.len() + F64_BYTES * (3 + n * n + n)
    }

    /// An upper bound of the bytes of this information in the block-sparse serde encoding of
    /// this type (ids, origin, y, and the non-zero upper-triangle 3 × 3 blocks of Y with their
    /// block indices), as produced by bincode's standard configuration.
    pub fn block_sparse_wire_bytes(&self) -> usize {
        let blocks = self.block_sparsity(0.0).matrix_blocks;
        let f32_blocks = blocks
            .iter()
            .filter(|&&(br, bc)| self.block_is_f32(br, bc))
            .count();
        let n = FEATURE_DIM * self.ids.len();
        4 * LEN_BYTES
            + ID_BYTES * self.ids.len()
            + F64_BYTES * (3 + n)
            + (blocks.len() - f32_blocks)
                * (2 * BLOCK_INDEX_BYTES + F64_BYTES * FEATURE_DIM * FEATURE_DIM)
            + f32_blocks * (2 * BLOCK_INDEX_BYTES + F32_BYTES * FEATURE_DIM * FEATURE_DIM)
    }

    /// The bound of [`block_sparse_wire_bytes`](Self::block_sparse_wire_bytes) for information
    /// over `n` features whose every upper-triangle block is non-zero and f64 (the largest a
    /// delta over `n` features can be): what a sparsified delta's feature count is sized by.
    pub fn dense_block_wire_bytes(n: usize) -> usize {
        Self::dense_block_wire_bytes_as(n, false)
    }

    /// [`dense_block_wire_bytes`](Self::dense_block_wire_bytes) with every block f32 when
    /// `f32_blocks` (as after [`quantized_f32_conservative`](Self::quantized_f32_conservative);
    /// y stays f64).
    pub fn dense_block_wire_bytes_as(n: usize, f32_blocks: bool) -> usize {
        let dim = FEATURE_DIM * n;
        let entry = if f32_blocks { F32_BYTES } else { F64_BYTES };
        4 * LEN_BYTES
            + ID_BYTES * n
            + F64_BYTES * (3 + dim)
            + n * (n + 1) / 2 * (2 * BLOCK_INDEX_BYTES + entry * FEATURE_DIM * FEATURE_DIM)
    }

    /// Whether every entry of the 3 × 3 block (br, bc) of Y is exactly representable as f32
    /// (the wire form then carries it in 4 bytes per entry, losslessly).
    fn block_is_f32(&self, br: usize, bc: usize) -> bool {
        (0..FEATURE_DIM).all(|c| {
            (0..FEATURE_DIM).all(|r| {
                let v = self.matrix[(FEATURE_DIM * br + r, FEATURE_DIM * bc + c)];
                f64::from(v as f32) == v
            })
        })
    }

    /// A conservative single-precision version of this (symmetric) information: every entry of
    /// Y exactly representable as f32, and Y_q ⪯ Y in PSD order, so a receiver fusing it never
    /// gains more information than was sent; y is kept in f64.
    ///
    /// Y' = Y − Λ with Λ_ii = 2⁻²² Σ_j |Y_ij|, then Y_q = fl32(Y'). Each rounding error is at most
    /// 2⁻²⁴ |Y'_ij|, so row i of Y' − Y_q sums to at most 2⁻²⁴ (Σ_j |Y_ij| + Λ_ii) < Λ_ii: the
    /// difference Y − Y_q = Λ + (Y' − Y_q) is diagonally dominant with a positive diagonal, hence
    /// positive semi-definite (Gershgorin). The information held back (≈ 2⁻²² relative) stays in
    /// the sender's channel difference Y − C and is sent with later deltas. The implied mean
    /// moves by O(2⁻²²) relative, far below any estimate's σ (consistency is checked by NEES).
    pub fn quantized_f32_conservative(&self) -> MapInformation {
        let n = self.matrix.nrows();
        let mut m = self.matrix.clone();
        for i in 0..n {
            let row: f64 = (0..n).map(|j| self.matrix[(i, j)].abs()).sum();
            m[(i, i)] -= row * 2f64.powi(-22);
        }
        for j in 0..n {
            for i in 0..n {
                m[(i, j)] = f64::from(m[(i, j)] as f32);
            }
        }
        MapInformation {
            ids: self.ids.clone(),
            origin: self.origin,
            matrix: m,
            vector: self.vector.clone(),
        }
    }
}

/// One non-zero 3 × 3 block of Y in the wire form (upper block triangle, column-major entries).
#[derive(serde::Serialize, serde::Deserialize)]
struct WireBlock {
    row: u32,
    col: u32,
    entries: [f64; FEATURE_DIM * FEATURE_DIM],
}

/// A block whose entries are all exactly representable as f32 (half the bytes, lossless).
#[derive(serde::Serialize, serde::Deserialize)]
struct WireBlock32 {
    row: u32,
    col: u32,
    entries: [f32; FEATURE_DIM * FEATURE_DIM],
}

/// Block-sparse wire form of [`MapInformation`]: lossless for exactly symmetric Y. Blocks whose
/// entries are all exact in f32 (e.g. after [`MapInformation::quantized_f32_conservative`]) go in
/// `blocks32`.
#[derive(serde::Serialize, serde::Deserialize)]
struct WireInformation {
    ids: Vec<FeatureId>,
    origin: [f64; 3],
    vector: Vec<f64>,
    blocks: Vec<WireBlock>,
    blocks32: Vec<WireBlock32>,
}

impl serde::Serialize for MapInformation {
    /// Serialises the block-sparse form: the upper block triangle's non-zero 3 × 3 blocks of Y
    /// (Y is symmetric by construction; the lower triangle is restored by symmetry), y, ids and
    /// the origin. The bytes of [`WireInformation`]'s derived form, with each block written as
    /// it is read from Y: no list of the blocks is built beside Y and the output (at 620
    /// features that list was 15 MB on top of the 27 MB matrix and the 14 MB encoding).
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeStruct;
        let nonzero = self.block_sparsity(0.0).matrix_blocks;
        let narrow: Vec<bool> = nonzero
            .iter()
            .map(|&(br, bc)| self.block_is_f32(br, bc))
            .collect();
        let mut st = serializer.serialize_struct("WireInformation", 5)?;
        st.serialize_field("ids", &self.ids)?;
        st.serialize_field("origin", &<[f64; 3]>::from(self.origin))?;
        st.serialize_field("vector", col_slice(&self.vector))?;
        st.serialize_field(
            "blocks",
            &WireBlocks {
                info: self,
                blocks: &nonzero,
                narrow: &narrow,
                f32: false,
            },
        )?;
        st.serialize_field(
            "blocks32",
            &WireBlocks {
                info: self,
                blocks: &nonzero,
                narrow: &narrow,
                f32: true,
            },
        )?;
        st.end()
    }
}

/// The `blocks` (`f32 == false`) or `blocks32` field of [`WireInformation`], serialised from
/// Y block by block: the blocks of `blocks` whose `narrow` flag equals `f32`.
struct WireBlocks<'a> {
    info: &'a MapInformation,
    blocks: &'a [(usize, usize)],
    narrow: &'a [bool],
    f32: bool,
}

impl serde::Serialize for WireBlocks<'_> {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeSeq;
        let len = self.narrow.iter().filter(|&&n| n == self.f32).count();
        let mut seq = serializer.serialize_seq(Some(len))?;
        let m = &self.info.matrix;
        let entry = |br: usize, bc: usize, k: usize| {
            let (c, r) = (k / FEATURE_DIM, k % FEATURE_DIM);
            m[(FEATURE_DIM * br + r, FEATURE_DIM * bc + c)]
        };
        for (&(br, bc), _) in self
            .blocks
            .iter()
            .zip(self.narrow)
            .filter(|&(_, &n)| n == self.f32)
        {
            let (row, col) = (br as u32, bc as u32);
            if self.f32 {
                let entries = std::array::from_fn(|k| entry(br, bc, k) as f32);
                seq.serialize_element(&WireBlock32 { row, col, entries })?;
            } else {
                let entries = std::array::from_fn(|k| entry(br, bc, k));
                seq.serialize_element(&WireBlock { row, col, entries })?;
            }
        }
        seq.end()
    }
}

/// Most features a received map information may name. Decoding allocates the dense 3N × 3N
/// matrix before its blocks are read, so a hostile id list must not size it: 8 192 features is
/// 4.8 GB dense, far beyond any team map this dense design runs (tree-8 ends at ~620, the
/// 1 000-feature benchmark is the largest measured).
pub const MAX_WIRE_FEATURES: usize = 8192;

impl<'de> serde::Deserialize<'de> for MapInformation {
    /// Decodes the block-sparse form, rejecting (as a deserialisation error, never a panic)
    /// duplicate ids, more than [`MAX_WIRE_FEATURES`], a y of the wrong length, block indices
    /// out of range or below the diagonal, repeated blocks, and non-finite values. Blocks are
    /// written into the matrix as they are read (a compact format such as bincode streams them):
    /// no list of every block is built beside the matrix (15 MB at 615 features).
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        const FIELDS: &[&str] = &["ids", "origin", "vector", "blocks", "blocks32"];
        let info = deserializer.deserialize_struct("WireInformation", FIELDS, WireVisitor)?;
        info.validate().map_err(D::Error::custom)?;
        Ok(info)
    }
}

/// The dense matrix a wire form is decoded into, with the blocks seen so far.
struct BlockFill {
    nf: usize,
    matrix: Mat<f64>,
    /// One bit per block (row, col), row-major over nf × nf.
    seen: Vec<u64>,
}

impl BlockFill {
    /// The fill of a map information on `ids` with `vector`, checked first (ids, their number,
    /// the vector's length), so that nothing of a size the sender chose is allocated before.
    fn new(ids: &[FeatureId], vector_len: usize) -> Result<Self, String> {
        let nf = ids.len();
        if nf > MAX_WIRE_FEATURES {
            return Err(format!(
                "map information on {nf} features (at most {MAX_WIRE_FEATURES})"
            ));
        }
        check_ids(ids).map_err(|e| e.to_string())?;
        let n = FEATURE_DIM * nf;
        if vector_len != n {
            return Err(InfoError::Dimension {
                what: "information vector",
                expected: n,
                found: vector_len,
            }
            .to_string());
        }
        Ok(Self {
            nf,
            matrix: Mat::zeros(n, n),
            seen: vec![0; (nf * nf).div_ceil(64)],
        })
    }

    /// Writes block (br, bc) (upper block triangle, entries column-major) and its mirror.
    fn put(
        &mut self,
        br: u32,
        bc: u32,
        entries: &[f64; FEATURE_DIM * FEATURE_DIM],
    ) -> Result<(), String> {
        let (br, bc) = (br as usize, bc as usize);
        let nf = self.nf;
        let fresh = br <= bc && bc < nf && {
            let bit = br * nf + bc;
            let (word, mask) = (bit / 64, 1u64 << (bit % 64));
            let fresh = self.seen[word] & mask == 0;
            self.seen[word] |= mask;
            fresh
        };
        if !fresh {
            return Err(format!(
                "invalid or repeated information block ({br}, {bc}) for {nf} features"
            ));
        }
        for c in 0..FEATURE_DIM {
            for r in 0..FEATURE_DIM {
                let v = entries[FEATURE_DIM * c + r];
                self.matrix[(FEATURE_DIM * br + r, FEATURE_DIM * bc + c)] = v;
                self.matrix[(FEATURE_DIM * bc + c, FEATURE_DIM * br + r)] = v;
            }
        }
        Ok(())
    }

    fn finish(self, ids: Vec<FeatureId>, origin: [f64; 3], vector: &[f64]) -> MapInformation {
        let n = FEATURE_DIM * ids.len();
        MapInformation {
            ids,
            origin: Vector3::from(origin),
            matrix: self.matrix,
            vector: Col::from_fn(n, |r| vector[r]),
        }
    }
}

/// Decodes [`WireInformation`] into [`MapInformation`], streaming the block lists of a
/// sequence-shaped format (bincode) and collecting them only from a map-shaped one (JSON).
struct WireVisitor;

impl<'de> serde::de::Visitor<'de> for WireVisitor {
    type Value = MapInformation;

    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("map information in block-sparse form")
    }

    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Self::Value, A::Error> {
        use serde::de::Error;
        let missing = |i: usize| A::Error::invalid_length(i, &"5 fields of map information");
        let ids: Vec<FeatureId> = seq.next_element()?.ok_or_else(|| missing(0))?;
        let origin: [f64; 3] = seq.next_element()?.ok_or_else(|| missing(1))?;
        let vector: Vec<f64> = seq.next_element()?.ok_or_else(|| missing(2))?;
        let mut fill = BlockFill::new(&ids, vector.len()).map_err(A::Error::custom)?;
        for (field, narrow) in [(3, false), (4, true)] {
            seq.next_element_seed(BlocksSeed {
                fill: &mut fill,
                narrow,
            })?
            .ok_or_else(|| missing(field))?;
        }
        Ok(fill.finish(ids, origin, &vector))
    }

    fn visit_map<A: serde::de::MapAccess<'de>>(self, map: A) -> Result<Self::Value, A::Error> {
        use serde::de::Error;
        let wire = <WireInformation as serde::Deserialize>::deserialize(
            serde::de::value::MapAccessDeserializer::new(map),
        )?;
        let mut fill = BlockFill::new(&wire.ids, wire.vector.len()).map_err(A::Error::custom)?;
        for b in &wire.blocks {
            fill.put(b.row, b.col, &b.entries)
                .map_err(A::Error::custom)?;
        }
        for b in &wire.blocks32 {
            fill.put(b.row, b.col, &b.entries.map(f64::from))
                .map_err(A::Error::custom)?;
        }
        Ok(fill.finish(wire.ids, wire.origin, &wire.vector))
    }
}

/// One block list (`blocks`, or `blocks32` when `narrow`) written into `fill` as it is read.
struct BlocksSeed<'a> {
    fill: &'a mut BlockFill,
    narrow: bool,
}

impl<'de> serde::de::DeserializeSeed<'de> for BlocksSeed<'_> {
    type Value = ();

    fn deserialize<D: serde::Deserializer<'de>>(self, deserializer: D) -> Result<(), D::Error> {
        deserializer.deserialize_seq(self)
    }
}

impl<'de> serde::de::Visitor<'de> for BlocksSeed<'_> {
    type Value = ();

    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a list of 3 × 3 information blocks")
    }

    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        use serde::de::Error;
        if self.narrow {
            while let Some(b) = seq.next_element::<WireBlock32>()? {
                self.fill
                    .put(b.row, b.col, &b.entries.map(f64::from))
                    .map_err(A::Error::custom)?;
            }
        } else {
            while let Some(b) = seq.next_element::<WireBlock>()? {
                self.fill
                    .put(b.row, b.col, &b.entries)
                    .map_err(A::Error::custom)?;
            }
        }
        Ok(())
    }
}

/// The key space of `keys` for a list of feature ids: the canonical ids in order of first
/// occurrence, their positions, and each listed id's position among them.
pub(crate) fn rekey_targets(
    ids: &[FeatureId],
    keys: &crate::keys::KeyMap,
) -> (Vec<FeatureId>, HashMap<FeatureId, usize>, Vec<usize>) {
    let mut out: Vec<FeatureId> = Vec::new();
    let mut index: HashMap<FeatureId, usize> = HashMap::new();
    let target = ids
        .iter()
        .map(|&k| {
            let c = keys.canonical(k);
            *index.entry(c).or_insert_with(|| {
                out.push(c);
                out.len() - 1
            })
        })
        .collect();
    (out, index, target)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{DMatrix, DVector};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Random SPD matrix B Bᵀ + n·I (condition number O(10)) of size 3·nf.
    fn random_spd(rng: &mut ChaCha8Rng, nf: usize) -> Mat<f64> {
        let n = FEATURE_DIM * nf;
        let b = Mat::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        let mut a = &b * b.transpose();
        for i in 0..n {
            a[(i, i)] += n as f64;
        }
        symmetrize(&mut a);
        a
    }

    fn random_marginal(rng: &mut ChaCha8Rng, ids: &[FeatureId], centre: f64) -> MapMarginal {
        let n = FEATURE_DIM * ids.len();
        MapMarginal {
            ids: ids.to_vec(),
            mean: Col::from_fn(n, |_| centre + rng.random_range(-100.0..100.0)),
            covariance: random_spd(rng, ids.len()),
        }
    }

    fn to_dmatrix(m: &Mat<f64>) -> DMatrix<f64> {
        DMatrix::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)])
    }

    type KeyedMatrix = HashMap<(u64, usize, u64, usize), f64>;
    type KeyedVector = HashMap<(u64, usize), f64>;

    /// Dense reference of a map information keyed by (feature id, axis): an independent
    /// representation to check the aligned algebra against.
    fn keyed(info: &MapInformation) -> (KeyedMatrix, KeyedVector) {
        let mut m = HashMap::new();
        let mut v = HashMap::new();
        for (bi, &fi) in info.ids.iter().enumerate() {
            for a in 0..3 {
                v.insert((fi, a), info.vector[3 * bi + a]);
                for (bj, &fj) in info.ids.iter().enumerate() {
                    for b in 0..3 {
                        m.insert((fi, a, fj, b), info.matrix[(3 * bi + a, 3 * bj + b)]);
                    }
                }
            }
        }
        (m, v)
    }

    #[test]
    fn from_marginal_matches_independent_nalgebra_inverse() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let origin = Vector3::new(-2.7e6, 4.3e6, 3.9e6);
        let ids: Vec<FeatureId> = vec![42, 7, 1000, 3, 99];
        let marg = random_marginal(&mut rng, &ids, 4.0e6);
        let info = MapInformation::from_marginal(&marg, origin).unwrap();
        // Independent reference: nalgebra's own Cholesky inverse and a dense product.
        let p = to_dmatrix(&marg.covariance);
        let y_ref = p.clone().cholesky().unwrap().inverse();
        let x = DVector::from_fn(15, |r, _| marg.mean[r] - origin[r % 3]);
        let yv_ref = &y_ref * x;
        let y = to_dmatrix(&info.matrix);
        // Condition number is O(10): both inverses agree to ~1e-15 relative; 1e-12 leaves margin.
        assert!((&y - &y_ref).amax() <= 1e-12 * y_ref.amax());
        for r in 0..15 {
            assert!((info.vector[r] - yv_ref[r]).abs() <= 1e-12 * yv_ref.amax());
        }
        assert_eq!(info.ids, ids);
        // Exactly symmetric output.
        assert_eq!(y, y.transpose());
    }

    /// The in-place inverse agrees with faer's `llt().inverse()` (an independent route: factor,
    /// triangular inverse, product in separate buffers) to round-off, on sizes below, at and
    /// across several of its blocks (3 to 210 states; blocks of 64), is exactly symmetric, is
    /// an inverse (A X = I to round-off), and refuses what is not positive definite.
    ///
    /// Tolerance: both routes err by O(n ε κ) relative to max |A⁻¹|; these matrices
    /// (B Bᵀ + n I) have κ < 3, so at n = 210 that is ≈ 7e-14: 1e-12 leaves a 15× margin and
    /// still fails on any wrong block (an error of order one).
    #[test]
    fn in_place_spd_inverse_matches_faer() {
        let mut rng = ChaCha8Rng::seed_from_u64(15);
        for nf in [1, 7, 21, 22, 40, 70] {
            let a = random_spd(&mut rng, nf);
            let n = a.nrows();
            let want = a.llt(Side::Lower).unwrap().inverse();
            let got = spd_inverse(a.as_ref()).unwrap();
            let scale = mat_norm_max(&want);
            let diff = mat_norm_max(&(&got - &want));
            assert!(
                diff <= 1e-12 * scale,
                "{nf} features: |X − faer| = {diff:e} of {scale:e}"
            );
            assert_eq!(got, got.transpose().to_owned());
            let residual = mat_norm_max(&(&a * &got - Mat::<f64>::identity(n, n)));
            assert!(residual <= 1e-12, "{nf} features: |A X − I| = {residual:e}");
        }
        let mut bad = random_spd(&mut rng, 3);
        bad[(4, 4)] = -1.0;
        assert!(spd_inverse(bad.as_ref()).is_err());
    }

    /// The inverse of a sum formed in the factor's buffer (a fresh one, or the first summand's)
    /// is the inverse of the summed matrix, bit for bit (the same additions), and a sum that is
    /// not positive definite is refused.
    #[test]
    fn spd_inverse_of_sum_equals_the_inverse_of_the_sum() {
        let mut rng = ChaCha8Rng::seed_from_u64(16);
        for nf in [1, 7, 40] {
            let (a, b) = (random_spd(&mut rng, nf), random_spd(&mut rng, nf));
            let sum = &a + &b;
            let want = spd_inverse(sum.as_ref()).unwrap();
            assert_eq!(spd_inverse_of_sum(a.as_ref(), b.as_ref()).unwrap(), want);
            let bits = |m: &Mat<f64>| -> Vec<u64> {
                (0..m.ncols())
                    .flat_map(|j| (0..m.nrows()).map(move |i| (i, j)))
                    .map(|(i, j)| m[(i, j)].to_bits())
                    .collect()
            };
            // In a's buffer, whatever its upper triangle holds.
            let mut a_junk = a.clone();
            for j in 0..a_junk.ncols() {
                for i in 0..j {
                    a_junk[(i, j)] = f64::NAN;
                }
            }
            let into = spd_inverse_of_sum_into(a_junk, b.as_ref()).unwrap();
            assert_eq!(bits(&into), bits(&want));
        }
        let a = random_spd(&mut rng, 3);
        let minus = Mat::from_fn(9, 9, |i, j| -2.0 * a[(i, j)]);
        assert!(spd_inverse_of_sum(a.as_ref(), minus.as_ref()).is_err());
        assert!(spd_inverse_of_sum_into(a.clone(), minus.as_ref()).is_err());
    }

    /// One pass for finiteness and the largest entry agrees with the separate checks.
    #[test]
    fn finite_and_norm_max_agree_with_the_separate_scans() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let mut m = random_spd(&mut rng, 5);
        m[(13, 2)] = -77.0;
        assert_eq!(finite_and_norm_max(&m), (true, mat_norm_max(&m)));
        assert_eq!(mat_norm_max(&m), 77.0);
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let mut n = m.clone();
            n[(14, 14)] = bad;
            assert!(!finite_and_norm_max(&n).0);
            assert!(check_finite_mat("m", &n).is_err());
        }
    }

    #[test]
    fn to_marginal_inverts_from_marginal() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let origin = Vector3::new(10.0, -20.0, 5.0);
        let marg = random_marginal(&mut rng, &[5, 6, 7, 8], 0.0);
        let back = MapInformation::from_marginal(&marg, origin)
            .unwrap()
            .to_marginal()
            .unwrap();
        // Two well-conditioned (κ ~ 10) inversions: round-off ~1e-14 relative; 1e-11 margin.
        let pm = to_dmatrix(&marg.covariance).amax();
        for i in 0..12 {
            assert!((back.mean[i] - marg.mean[i]).abs() <= 1e-11 * 100.0);
            for j in 0..12 {
                assert!((back.covariance[(i, j)] - marg.covariance[(i, j)]).abs() <= 1e-11 * pm);
            }
        }
    }

    #[test]
    fn not_positive_definite_names_the_pivot() {
        let ids = vec![10, 20, 30];
        let mut y = Mat::<f64>::identity(9, 9);
        y[(7, 7)] = -1.0; // row 7 = feature index 2 (id 30), axis 1
        let info = MapInformation {
            ids,
            origin: Vector3::zeros(),
            matrix: y,
            vector: Col::zeros(9),
        };
        match info.to_marginal() {
            Err(InfoError::NotPositiveDefinite {
                pivot,
                feature,
                axis,
                ..
            }) => {
                assert_eq!((pivot, feature, axis), (7, 30, 1));
            }
            other => panic!("expected NotPositiveDefinite, got {other:?}"),
        }
        let msg = info.to_marginal().unwrap_err().to_string();
        assert!(
            msg.contains("pivot 7") && msg.contains("feature 30"),
            "{msg}"
        );
        // The same for a covariance that is not positive definite.
        let marg = MapMarginal {
            ids: vec![1, 2],
            mean: Col::zeros(6),
            covariance: Mat::from_fn(6, 6, |i, j| {
                if i == j {
                    if i == 4 { 0.0 } else { 1.0 }
                } else {
                    0.0
                }
            }),
        };
        assert!(matches!(
            MapInformation::from_marginal(&marg, Vector3::zeros()),
            Err(InfoError::NotPositiveDefinite {
                pivot: 4,
                feature: 2,
                axis: 1,
                ..
            })
        ));
    }

    #[test]
    fn aligned_add_and_sub_match_keyed_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let o = Vector3::new(1.0, 2.0, 3.0);
        let a = MapInformation::from_marginal(&random_marginal(&mut rng, &[1, 2, 3, 4], 0.0), o)
            .unwrap();
        let b = MapInformation::from_marginal(&random_marginal(&mut rng, &[9, 3, 1, 8], 0.0), o)
            .unwrap();
        let sum = a.add(&b).unwrap();
        let diff = a.sub(&b).unwrap();
        // Order-stable union: a's ids, then b's new ones in b's order.
        assert_eq!(sum.ids, vec![1, 2, 3, 4, 9, 8]);
        assert_eq!(diff.ids, sum.ids);
        let (am, av) = keyed(&a);
        let (bm, bv) = keyed(&b);
        let (sm, sv) = keyed(&sum);
        let (dm, dv) = keyed(&diff);
        for (k, &s) in &sm {
            let (x, y) = (
                am.get(k).copied().unwrap_or(0.0),
                bm.get(k).copied().unwrap_or(0.0),
            );
            // One f64 addition: exact up to one rounding (≤ 1 ulp of the operands).
            assert!((s - (x + y)).abs() <= 1e-15 * (x.abs() + y.abs()));
            assert!((dm[k] - (x - y)).abs() <= 1e-15 * (x.abs() + y.abs()));
        }
        for (k, &s) in &sv {
            let (x, y) = (
                av.get(k).copied().unwrap_or(0.0),
                bv.get(k).copied().unwrap_or(0.0),
            );
            assert!((s - (x + y)).abs() <= 1e-15 * (x.abs() + y.abs()));
            assert!((dv[k] - (x - y)).abs() <= 1e-15 * (x.abs() + y.abs()));
        }
        // add_assign then sub_assign returns to a (over the union, b's new features zero).
        let mut c = a.clone();
        c.add_assign(&b).unwrap();
        c.sub_assign(&b).unwrap();
        // Two roundings per entry: ≤ 2 ulp of the largest operand.
        assert!(c.relative_difference(&a).unwrap() <= 1e-14);
        assert!(c.restrict(&[9, 8]).is_zero(1e-14 * b.matrix_norm_max()));
        // Adding to the empty map yields the operand.
        let z = MapInformation::zero(o).add(&a).unwrap();
        assert_eq!(z.ids, a.ids);
        assert_eq!(z.relative_difference(&a).unwrap(), 0.0);
    }

    #[test]
    fn origin_mismatch_is_an_error_and_leaves_operand_untouched() {
        let mut a = MapInformation::zeros_over(&[1], Vector3::zeros()).unwrap();
        let b = MapInformation::zeros_over(&[2], Vector3::new(1.0, 0.0, 0.0)).unwrap();
        assert!(matches!(
            a.add_assign(&b),
            Err(InfoError::OriginMismatch { .. })
        ));
        assert_eq!(a.ids, vec![1]);
    }

    #[test]
    fn validation_rejects_bad_input_and_accepts_indefinite() {
        let good = || MapInformation {
            ids: vec![1, 2],
            origin: Vector3::zeros(),
            matrix: Mat::from_fn(6, 6, |i, j| {
                if i == j {
                    if i % 2 == 0 { 1.0 } else { -2.0 }
                } else {
                    0.5
                }
            }),
            vector: Col::from_fn(6, |i| i as f64),
        };
        assert!(
            good().validate().is_ok(),
            "symmetric indefinite delta must pass"
        );
        let mut nan = good();
        nan.matrix[(3, 4)] = f64::NAN;
        assert!(matches!(
            nan.validate(),
            Err(InfoError::NonFinite { row: 3, col: 4, .. })
        ));
        let mut inf = good();
        inf.vector[5] = f64::INFINITY;
        assert!(matches!(
            inf.validate(),
            Err(InfoError::NonFinite { row: 5, .. })
        ));
        let mut asym = good();
        asym.matrix[(0, 5)] += 1e-6; // relative asymmetry 5e-7 ≫ SYMMETRY_RTOL
        assert!(matches!(
            asym.validate(),
            Err(InfoError::NotSymmetric { row: 5, col: 0, .. })
        ));
        let mut tiny = good();
        tiny.matrix[(0, 5)] += 1e-13; // 5e-14 relative: round-off level, accepted
        assert!(tiny.validate().is_ok());
        let mut dup = good();
        dup.ids = vec![2, 2];
        assert!(matches!(dup.validate(), Err(InfoError::DuplicateId(2))));
        let mut short = good();
        short.vector = Col::zeros(5);
        assert!(matches!(
            short.validate(),
            Err(InfoError::Dimension {
                expected: 6,
                found: 5,
                ..
            })
        ));
        let mut nonsquare = good();
        nonsquare.matrix = Mat::zeros(6, 3);
        assert!(matches!(
            nonsquare.validate(),
            Err(InfoError::Dimension { .. })
        ));
        let mut bad_origin = good();
        bad_origin.origin.x = f64::NAN;
        assert!(bad_origin.validate().is_err());
    }

    #[test]
    fn tiled_symmetry_helpers_match_the_naive_loops() {
        // 3·35 = 105 rows: several 32-tiles and a partial one.
        let mut rng = ChaCha8Rng::seed_from_u64(40);
        let n = 105;
        let m = Mat::<f64>::from_fn(n, n, |_, _| rng.random_range(-1.0..1.0));
        let mut naive = (0.0_f64, 0, 0);
        for j in 0..n {
            for i in (j + 1)..n {
                let d = (m[(i, j)] - m[(j, i)]).abs();
                if d > naive.0 {
                    naive = (d, i, j);
                }
            }
        }
        assert_eq!(max_asymmetry(&m), naive);
        let mut s = m.clone();
        symmetrize(&mut s);
        for i in 0..n {
            for j in 0..n {
                assert_eq!(s[(i, j)], 0.5 * (m[(i, j)] + m[(j, i)]));
            }
        }
        assert_eq!(max_asymmetry(&s).0, 0.0);
        // One asymmetric entry deep in an off-diagonal tile is found.
        let mut t = s.clone();
        t[(100, 40)] += 1.0;
        assert_eq!(max_asymmetry(&t), (1.0, 100, 40));
        assert!(!all_finite(&[1.0, f64::NAN]) && !all_finite(&[f64::NEG_INFINITY]));
        assert!(all_finite(&[0.0, -1e308, 5e-324]));
    }

    #[test]
    fn restrict_extracts_blocks_in_requested_order() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let a = MapInformation::from_marginal(
            &random_marginal(&mut rng, &[1, 2, 3], 0.0),
            Vector3::zeros(),
        )
        .unwrap();
        let r = a.restrict(&[3, 77, 1]);
        assert_eq!(r.ids, vec![3, 1]);
        for (bi, si) in [(0, 2), (1, 0)] {
            for (bj, sj) in [(0, 2), (1, 0)] {
                for p in 0..3 {
                    for q in 0..3 {
                        assert_eq!(
                            r.matrix[(3 * bi + p, 3 * bj + q)],
                            a.matrix[(3 * si + p, 3 * sj + q)]
                        );
                    }
                }
            }
            for p in 0..3 {
                assert_eq!(r.vector[3 * bi + p], a.vector[3 * si + p]);
            }
        }
    }

    #[test]
    fn psd_order_helpers_match_closed_form() {
        let o = Vector3::zeros();
        let diag = |d: [f64; 3]| MapInformation {
            ids: vec![1],
            origin: o,
            matrix: Mat::from_fn(3, 3, |i, j| if i == j { d[i] } else { 0.0 }),
            vector: Col::zeros(3),
        };
        let a = diag([1.0, 2.0, 3.0]);
        let b = diag([2.0, 2.0, 2.5]);
        // A − B = diag(−1, 0, 0.5): λ_max = 0.5, λ_min = −1.
        // Tridiagonal QR on a diagonal matrix is exact to round-off: 1e-14.
        assert!((a.psd_excess_over(&b).unwrap() - 0.5).abs() < 1e-14);
        assert!((a.sub(&b).unwrap().min_eigenvalue().unwrap() + 1.0).abs() < 1e-14);
        assert!((b.psd_excess_over(&a).unwrap() - 1.0).abs() < 1e-14);
        // Over a union: a feature only in B makes A − B negative there, not positive.
        let mut c = diag([1.0, 1.0, 1.0]);
        c.ids = vec![2];
        let bc = b.add(&c).unwrap();
        assert!((b.psd_excess_over(&bc).unwrap() - 0.0).abs() < 1e-14);
        assert!((bc.psd_excess_over(&b).unwrap() - 1.0).abs() < 1e-14);
        assert_eq!(
            MapInformation::zero(o).max_eigenvalue().unwrap(),
            f64::NEG_INFINITY
        );
    }

    #[test]
    fn block_sparsity_and_sparsified() {
        let o = Vector3::zeros();
        let mut d = MapInformation::zeros_over(&[1, 2, 3, 4], o).unwrap();
        // Non-zero blocks: (0,0), (0,2)/(2,0); vector block 3; feature 2 (block 1) carries nothing.
        d.matrix[(0, 0)] = 1.0;
        d.matrix[(1, 7)] = 0.5;
        d.matrix[(7, 1)] = 0.5;
        d.vector[10] = -3.0;
        d.matrix[(4, 4)] = 1e-20; // below a threshold of 1e-12
        let s0 = d.block_sparsity(0.0);
        assert_eq!(s0.matrix_blocks, vec![(0, 0), (1, 1), (0, 2)]);
        assert_eq!(s0.vector_blocks, vec![3]);
        let s = d.block_sparsity(1e-12);
        assert_eq!(s.matrix_blocks, vec![(0, 0), (0, 2)]);
        assert_eq!(s.dense_upper_blocks(), 10);
        assert!((s.density() - 0.2).abs() < 1e-15);
        let sp = d.sparsified(1e-12);
        assert_eq!(sp.ids, vec![1, 3, 4]);
        // Lossless apart from the dropped 1e-20 block.
        assert!(sp.sub(&d).unwrap().is_zero(1e-20));
        assert_eq!(sp.matrix[(1, 4)], 0.5);
        assert_eq!(sp.matrix[(4, 1)], 0.5);
        // Lossless at threshold 0 except for dropped all-zero features.
        let z = d.sparsified(0.0);
        assert_eq!(z.ids, vec![1, 2, 3, 4]);
        assert!(z.sub(&d).unwrap().is_zero(0.0));
        assert!(
            MapInformation::zeros_over(&[5, 6], o)
                .unwrap()
                .sparsified(0.0)
                .is_empty()
        );
        assert!(d.block_sparse_wire_bytes() < d.dense_wire_bytes());
    }

    fn encode(info: &MapInformation) -> Vec<u8> {
        bincode::serde::encode_to_vec(info, bincode::config::standard()).unwrap()
    }

    fn decode(bytes: &[u8]) -> Result<MapInformation, bincode::error::DecodeError> {
        bincode::serde::decode_from_slice(bytes, bincode::config::standard()).map(|(v, _)| v)
    }

    #[test]
    fn wire_round_trip_is_lossless_and_within_the_stated_bound() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let info = MapInformation::from_marginal(
            &random_marginal(&mut rng, &[4, 8, 15, 16, 23, 42], 1e6),
            Vector3::new(1e6, 1e6, 1e6),
        )
        .unwrap();
        let bytes = encode(&info);
        let back = decode(&bytes).unwrap();
        assert_eq!(back.ids, info.ids);
        assert_eq!(back.origin, info.origin);
        assert!(
            back.sub(&info).unwrap().is_zero(0.0),
            "bit-exact round trip"
        );
        assert!(bytes.len() <= info.block_sparse_wire_bytes());
        assert!(bytes.len() <= info.dense_wire_bytes());
        // A block-sparse delta is much smaller on the wire.
        let mut delta = MapInformation::zeros_over(&info.ids, info.origin).unwrap();
        delta.matrix[(0, 0)] = 2.0;
        delta.vector[0] = 1.0;
        let small = encode(&delta.sparsified(0.0));
        assert!(small.len() <= delta.sparsified(0.0).block_sparse_wire_bytes());
        assert!(small.len() < 200, "{}", small.len());
    }

    /// The streamed encoding is byte for byte the derived encoding of the block list
    /// ([`WireInformation`], which the decoder reads): with f64 blocks, f32-exact blocks, zero
    /// blocks and a feature that carries nothing, and with no block at all.
    #[test]
    fn streamed_encoding_equals_the_block_list_encoding() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut info = MapInformation::from_marginal(
            &random_marginal(&mut rng, &[3, 1, 4, 9, 5], 1e3),
            Vector3::new(10.0, -20.0, 5.0),
        )
        .unwrap();
        // Block (1, 3) and (3, 1) zero, block (0, 2) f32-exact, feature 4 carries nothing.
        for r in 0..3 {
            for c in 0..3 {
                for (br, bc) in [(1, 3), (0, 2), (4, 0), (4, 1), (4, 2), (4, 3), (4, 4)] {
                    info.matrix[(3 * br + r, 3 * bc + c)] = 0.0;
                    info.matrix[(3 * bc + c, 3 * br + r)] = 0.0;
                }
                info.matrix[(r, 6 + c)] = 0.25 * (r + 3 * c) as f64;
                info.matrix[(6 + c, r)] = 0.25 * (r + 3 * c) as f64;
            }
        }
        let reference = |info: &MapInformation| {
            let block = |br: usize, bc: usize| -> [f64; 9] {
                std::array::from_fn(|k| info.matrix[(3 * br + k % 3, 3 * bc + k / 3)])
            };
            let nonzero = info.block_sparsity(0.0).matrix_blocks;
            let (narrow, wide): (Vec<_>, Vec<_>) = nonzero
                .into_iter()
                .partition(|&(br, bc)| info.block_is_f32(br, bc));
            let w = WireInformation {
                ids: info.ids.clone(),
                origin: info.origin.into(),
                vector: col_slice(&info.vector).to_vec(),
                blocks: wide
                    .into_iter()
                    .map(|(br, bc)| WireBlock {
                        row: br as u32,
                        col: bc as u32,
                        entries: block(br, bc),
                    })
                    .collect(),
                blocks32: narrow
                    .into_iter()
                    .map(|(br, bc)| WireBlock32 {
                        row: br as u32,
                        col: bc as u32,
                        entries: block(br, bc).map(|v| v as f32),
                    })
                    .collect(),
            };
            bincode::serde::encode_to_vec(&w, bincode::config::standard()).unwrap()
        };
        let got = encode(&info);
        assert_eq!(got, reference(&info));
        assert!(decode(&got).unwrap().sub(&info).unwrap().is_zero(0.0));
        let empty = MapInformation::zeros_over(&[1, 2], info.origin).unwrap();
        assert_eq!(encode(&empty), reference(&empty));
    }

    #[test]
    fn hostile_wire_input_is_an_error_not_a_panic() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let info = MapInformation::from_marginal(
            &random_marginal(&mut rng, &[1, 2, 3], 0.0),
            Vector3::zeros(),
        )
        .unwrap();
        let bytes = encode(&info);
        for cut in 0..bytes.len() {
            assert!(decode(&bytes[..cut]).is_err(), "truncated at {cut}");
        }
        // Out-of-range block, below-diagonal block, repeated block, wrong y length, NaN.
        let mk = |ids: Vec<u64>, vector: Vec<f64>, blocks: Vec<(u32, u32, f64)>| {
            let w = WireInformation {
                ids,
                origin: [0.0; 3],
                vector,
                blocks: blocks
                    .into_iter()
                    .map(|(row, col, v)| WireBlock {
                        row,
                        col,
                        entries: [v; 9],
                    })
                    .collect(),
                blocks32: Vec::new(),
            };
            bincode::serde::encode_to_vec(&w, bincode::config::standard()).unwrap()
        };
        assert!(decode(&mk(vec![1], vec![0.0; 3], vec![(0, 0, 1.0)])).is_ok());
        assert!(decode(&mk(vec![1], vec![0.0; 3], vec![(0, 1, 1.0)])).is_err());
        assert!(decode(&mk(vec![1, 2], vec![0.0; 6], vec![(1, 0, 1.0)])).is_err());
        assert!(
            decode(&mk(
                vec![1, 2],
                vec![0.0; 6],
                vec![(0, 1, 1.0), (0, 1, 1.0)]
            ))
            .is_err()
        );
        assert!(decode(&mk(vec![1], vec![0.0; 2], vec![])).is_err());
        assert!(decode(&mk(vec![1], vec![0.0; 3], vec![(0, 0, f64::NAN)])).is_err());
        assert!(decode(&mk(vec![1, 1], vec![0.0; 6], vec![])).is_err());
        assert!(
            decode(&mk(
                vec![u32::MAX as u64],
                vec![0.0; 3],
                vec![(u32::MAX, u32::MAX, 1.0)]
            ))
            .is_err()
        );
        // An id list that would size a dense matrix beyond any team map: refused before the
        // matrix is allocated (8 193 features: 4.8 GB; the error names the bound).
        let many: Vec<u64> = (0..MAX_WIRE_FEATURES as u64 + 1).collect();
        let err = decode(&mk(many.clone(), vec![0.0; 3 * many.len()], vec![]))
            .unwrap_err()
            .to_string();
        assert!(err.contains("at most 8192"), "{err}");
        // A block repeated across the f64 and the f32 list.
        let mut w = mk(vec![1, 2], vec![0.0; 6], vec![(0, 1, 0.5)]);
        let narrow = bincode::serde::encode_to_vec(
            vec![WireBlock32 {
                row: 0,
                col: 1,
                entries: [0.5; 9],
            }],
            bincode::config::standard(),
        )
        .unwrap();
        w.pop(); // the empty f32 list's length
        w.extend_from_slice(&narrow);
        let err = decode(&w).unwrap_err().to_string();
        assert!(err.contains("repeated information block (0, 1)"), "{err}");
    }

    /// A map-shaped format (JSON: fields by name, decoded by collecting the block lists) gives
    /// the same information as bincode's streamed decoding, bit for bit.
    #[test]
    fn map_shaped_formats_decode_as_bincode_does() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let mut info = MapInformation::from_marginal(
            &random_marginal(&mut rng, &[2, 7, 1, 8], 1e3),
            Vector3::new(3.0, 1.0, -4.0),
        )
        .unwrap();
        // Numbers with short exact decimals (serde_json's default float parsing is only within
        // an ulp otherwise), one f32-exact block so that both lists are used.
        let short = |v: f64| (v * 1024.0).round() / 1024.0;
        let n = info.matrix.nrows();
        info.matrix = Mat::from_fn(n, n, |i, j| short(info.matrix[(i, j)]));
        info.vector = Col::from_fn(n, |i| short(info.vector[i]));
        for r in 0..3 {
            for c in 0..3 {
                info.matrix[(r, 3 + c)] = 0.5 * (r + c) as f64;
                info.matrix[(3 + c, r)] = 0.5 * (r + c) as f64;
            }
        }
        let from_bincode = decode(&encode(&info)).unwrap();
        let json = serde_json::to_string(&info).unwrap();
        let from_json: MapInformation = serde_json::from_str(&json).unwrap();
        assert_eq!(from_json.ids, from_bincode.ids);
        assert_eq!(from_json.origin, from_bincode.origin);
        assert!(from_json.sub(&from_bincode).unwrap().is_zero(0.0));
        assert!(from_json.sub(&info).unwrap().is_zero(0.0));
        let repeated = json.replacen(
            "\"blocks32\":[",
            "\"blocks32\":[{\"row\":0,\"col\":1,\"entries\":[0,0,0,0,0,0,0,0,0]},",
            1,
        );
        assert!(repeated != json && serde_json::from_str::<MapInformation>(&repeated).is_err());
    }

    /// The conservative f32 form is exactly single precision, never more informative than the
    /// original (Y − Y_q ⪰ 0, checked by its smallest eigenvalue from an independent nalgebra
    /// decomposition), within 2⁻²⁰ of it, and the wire form carries it losslessly in about
    /// half the bytes.
    #[test]
    fn f32_quantization_is_conservative_and_lossless_on_the_wire() {
        let mut rng = ChaCha8Rng::seed_from_u64(32);
        for case in 0..20 {
            let nf = 2 + case % 7;
            let ids: Vec<FeatureId> = (0..nf as u64).map(|i| 10 + i).collect();
            let mut m = random_spd(&mut rng, nf);
            if case % 3 == 0 {
                // Indefinite deltas (after CI upstream) must be handled too.
                for i in 0..FEATURE_DIM * nf {
                    m[(i, i)] -= FEATURE_DIM as f64 * nf as f64 * 1.5;
                }
            }
            let scale = 10f64.powi(rng.random_range(-4..6));
            let info = MapInformation {
                ids,
                origin: Vector3::new(1.0, 2.0, 3.0),
                matrix: Mat::from_fn(m.nrows(), m.ncols(), |i, j| m[(i, j)] * scale),
                vector: Col::from_fn(m.nrows(), |_| rng.random_range(-1.0..1.0)),
            };
            let q = info.quantized_f32_conservative();
            let n = q.matrix.nrows();
            for j in 0..n {
                for i in 0..n {
                    assert_eq!(f64::from(q.matrix[(i, j)] as f32), q.matrix[(i, j)]);
                    assert_eq!(q.matrix[(i, j)], q.matrix[(j, i)], "symmetric");
                }
            }
            let diff = DMatrix::from_fn(n, n, |i, j| info.matrix[(i, j)] - q.matrix[(i, j)]);
            let min_eig = diff.clone().symmetric_eigenvalues().min();
            let max_abs = info.matrix_norm_max();
            // Eigenvalues of the difference are ≥ 0 up to the decomposition's round-off.
            assert!(
                min_eig >= -1e-13 * max_abs,
                "case {case}: λ_min {min_eig:e}"
            );
            assert!(
                diff.abs().max() <= 2f64.powi(-20) * max_abs * n as f64,
                "case {case}: too lossy"
            );
            let bytes = encode(&q);
            let back = decode(&bytes).unwrap();
            assert_eq!(back.matrix, q.matrix, "lossless");
            assert!(bytes.len() < encode(&info).len(), "smaller on the wire");
        }
    }
}
