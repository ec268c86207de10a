//! Validated numeric containers for message bodies, and the [`Validate`] trait.
//!
//! The node crate builds its message bodies (DDF deltas, IMU batches...) from these containers
//! plus plain serde types, and implements [`Validate`] for each body by validating its fields.
//! The codec runs `validate` after every decode, so a body that reaches the application has
//! consistent dimensions, finite values and exact symmetry where the form does not guarantee it.
//!
//! Float data travels as one length-prefixed byte run preceded by a [`WireEncoding`] tag, so
//! bulk matrices cost one `memcpy` to encode (little-endian `f64`, cast with `bytemuck` on
//! little-endian hosts) and a later float32 or compressed encoding only needs a new tag; unknown
//! tags are rejected by the decoder.

use std::borrow::Cow;
use std::fmt;

use serde::de::{self, SeqAccess, Visitor};
use serde::ser::SerializeTuple;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Why a decoded body is not acceptable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ValidationError {
    /// Element count does not match the declared dimensions.
    #[error("{what}: expected {expected} elements, found {found}")]
    Dimension {
        /// Which container or field.
        what: &'static str,
        /// Elements implied by the dimensions.
        expected: u64,
        /// Elements present.
        found: u64,
    },
    /// A NaN or infinite value.
    #[error("{what}: non-finite value at element {index}")]
    NonFinite {
        /// Which container or field.
        what: &'static str,
        /// Index of the first offending element.
        index: u64,
    },
    /// A block that must be symmetric is not (exactly).
    #[error("{what}: block ({row}, {col}) is not symmetric")]
    Asymmetric {
        /// Which container or field.
        what: &'static str,
        /// Block row.
        row: u32,
        /// Block column.
        col: u32,
    },
    /// A block index is out of range, below the diagonal, or out of order / duplicated.
    #[error("{what}: bad block index ({row}, {col}): {reason}")]
    BlockIndex {
        /// Which container or field.
        what: &'static str,
        /// Block row.
        row: u32,
        /// Block column.
        col: u32,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A body-specific rule (used by the node crate's bodies).
    #[error("{0}")]
    Other(String),
}

/// Checks a decoded value's invariants. The codec calls it after every body decode.
pub trait Validate {
    /// `Ok(())` if the value is acceptable.
    fn validate(&self) -> Result<(), ValidationError>;
}

macro_rules! always_valid {
    ($($t:ty),*) => {$(
        impl Validate for $t {
            fn validate(&self) -> Result<(), ValidationError> { Ok(()) }
        }
    )*};
}
always_valid!(
    (),
    bool,
    u8,
    u16,
    u32,
    u64,
    u128,
    usize,
    i8,
    i16,
    i32,
    i64,
    i128,
    isize,
    char,
    String,
    str,
    crate::envelope::MessageKind
);

impl Validate for f64 {
    fn validate(&self) -> Result<(), ValidationError> {
        check_finite("f64", std::slice::from_ref(self))
    }
}
impl Validate for f32 {
    fn validate(&self) -> Result<(), ValidationError> {
        if self.is_finite() {
            Ok(())
        } else {
            Err(ValidationError::NonFinite {
                what: "f32",
                index: 0,
            })
        }
    }
}
impl<T: Validate> Validate for Vec<T> {
    fn validate(&self) -> Result<(), ValidationError> {
        self.iter().try_for_each(Validate::validate)
    }
}
impl<T: Validate> Validate for [T] {
    fn validate(&self) -> Result<(), ValidationError> {
        self.iter().try_for_each(Validate::validate)
    }
}
impl<T: Validate, const N: usize> Validate for [T; N] {
    fn validate(&self) -> Result<(), ValidationError> {
        self.iter().try_for_each(Validate::validate)
    }
}
impl<T: Validate> Validate for Option<T> {
    fn validate(&self) -> Result<(), ValidationError> {
        self.as_ref().map_or(Ok(()), Validate::validate)
    }
}
impl<T: Validate + ?Sized> Validate for Box<T> {
    fn validate(&self) -> Result<(), ValidationError> {
        (**self).validate()
    }
}
impl<T: Validate + ?Sized> Validate for &T {
    fn validate(&self) -> Result<(), ValidationError> {
        (**self).validate()
    }
}
impl<A: Validate, B: Validate> Validate for (A, B) {
    fn validate(&self) -> Result<(), ValidationError> {
        self.0.validate()?;
        self.1.validate()
    }
}
impl<A: Validate, B: Validate, C: Validate> Validate for (A, B, C) {
    fn validate(&self) -> Result<(), ValidationError> {
        self.0.validate()?;
        self.1.validate()?;
        self.2.validate()
    }
}

fn check_finite(what: &'static str, data: &[f64]) -> Result<(), ValidationError> {
    match data.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => Err(ValidationError::NonFinite {
            what,
            index: i as u64,
        }),
    }
}

fn check_len(
    what: &'static str,
    expected: Option<u64>,
    found: usize,
) -> Result<(), ValidationError> {
    match expected {
        Some(e) if e == found as u64 => Ok(()),
        _ => Err(ValidationError::Dimension {
            what,
            expected: expected.unwrap_or(u64::MAX),
            found: found as u64,
        }),
    }
}

/// How the floats of a container are laid out on the wire. Only `F64Le` exists in format
/// version 1; the tag leaves room for float32 or compressed encodings.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[repr(u8)]
pub enum WireEncoding {
    /// IEEE-754 binary64, little endian, 8 bytes per element.
    #[default]
    F64Le = 0,
}

impl WireEncoding {
    /// Tag byte on the wire.
    pub fn tag(self) -> u8 {
        self as u8
    }
    /// Encoding for a tag byte, `None` if unknown to this build.
    pub fn from_tag(tag: u8) -> Option<Self> {
        match tag {
            0 => Some(Self::F64Le),
            _ => None,
        }
    }
}

/// A float array in memory, `(tag, byte run)` on the wire.
#[derive(Clone, PartialEq, Default)]
struct F64Array {
    encoding: WireEncoding,
    values: Vec<f64>,
}

impl fmt::Debug for F64Array {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_list().entries(&self.values).finish()
    }
}

struct RawBytes<'a>(&'a [u8]);
impl Serialize for RawBytes<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(self.0)
    }
}

impl Serialize for F64Array {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut t = s.serialize_tuple(2)?;
        t.serialize_element(&self.encoding.tag())?;
        match self.encoding {
            WireEncoding::F64Le => {
                #[cfg(target_endian = "little")]
                t.serialize_element(&RawBytes(bytemuck::cast_slice(&self.values)))?;
                #[cfg(not(target_endian = "little"))]
                {
                    let le: Vec<u8> = self.values.iter().flat_map(|v| v.to_le_bytes()).collect();
                    t.serialize_element(&RawBytes(&le))?;
                }
            }
        }
        t.end()
    }
}

/// Byte run that borrows from the input when the deserializer allows it.
struct ByteRun<'de>(Cow<'de, [u8]>);

impl<'de> Deserialize<'de> for ByteRun<'de> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = ByteRun<'de>;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a byte run")
            }
            fn visit_borrowed_bytes<E: de::Error>(self, v: &'de [u8]) -> Result<Self::Value, E> {
                Ok(ByteRun(Cow::Borrowed(v)))
            }
            fn visit_bytes<E: de::Error>(self, v: &[u8]) -> Result<Self::Value, E> {
                Ok(ByteRun(Cow::Owned(v.to_vec())))
            }
            fn visit_byte_buf<E: de::Error>(self, v: Vec<u8>) -> Result<Self::Value, E> {
                Ok(ByteRun(Cow::Owned(v)))
            }
        }
        d.deserialize_bytes(V)
    }
}

impl<'de> Deserialize<'de> for F64Array {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = F64Array;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("an encoding tag and a byte run")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<F64Array, A::Error> {
                let tag: u8 = seq
                    .next_element()?
                    .ok_or_else(|| de::Error::invalid_length(0, &self))?;
                let encoding = WireEncoding::from_tag(tag).ok_or_else(|| {
                    de::Error::custom(format_args!("unknown float encoding tag {tag}"))
                })?;
                let bytes: ByteRun<'de> = seq
                    .next_element()?
                    .ok_or_else(|| de::Error::invalid_length(1, &self))?;
                let values = match encoding {
                    WireEncoding::F64Le => {
                        if !bytes.0.len().is_multiple_of(8) {
                            return Err(de::Error::custom(format_args!(
                                "f64 byte run of {} bytes is not a multiple of 8",
                                bytes.0.len()
                            )));
                        }
                        bytes
                            .0
                            .chunks_exact(8)
                            .map(|c| {
                                let mut a = [0u8; 8];
                                a.copy_from_slice(c);
                                f64::from_le_bytes(a)
                            })
                            .collect()
                    }
                };
                Ok(F64Array { encoding, values })
            }
        }
        d.deserialize_tuple(2, V)
    }
}

/// A dense vector of `f64`.
#[derive(Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct WireVector {
    data: F64Array,
}

impl fmt::Debug for WireVector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "WireVector({:?})", self.data)
    }
}

impl WireVector {
    /// Wraps `values` (not validated here; [`Validate`] checks finiteness).
    pub fn new(values: Vec<f64>) -> Self {
        Self {
            data: F64Array {
                encoding: WireEncoding::F64Le,
                values,
            },
        }
    }
    /// Copies `values`.
    pub fn from_slice(values: &[f64]) -> Self {
        Self::new(values.to_vec())
    }
    /// The elements.
    pub fn as_slice(&self) -> &[f64] {
        &self.data.values
    }
    /// Takes the elements.
    pub fn into_vec(self) -> Vec<f64> {
        self.data.values
    }
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.data.values.len()
    }
    /// True if empty.
    pub fn is_empty(&self) -> bool {
        self.data.values.is_empty()
    }
    /// Wire encoding of the elements.
    pub fn encoding(&self) -> WireEncoding {
        self.data.encoding
    }
}

impl Validate for WireVector {
    fn validate(&self) -> Result<(), ValidationError> {
        check_finite("WireVector", &self.data.values)
    }
}

/// A dense row-major `rows × cols` matrix of `f64`.
#[derive(Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct WireMatrix {
    rows: u32,
    cols: u32,
    data: F64Array,
}

impl fmt::Debug for WireMatrix {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "WireMatrix({}x{}, {:?})",
            self.rows, self.cols, self.data
        )
    }
}

impl WireMatrix {
    /// From row-major data; `Err` if `data.len() != rows * cols` or a value is not finite.
    pub fn from_row_major(rows: u32, cols: u32, data: Vec<f64>) -> Result<Self, ValidationError> {
        let m = Self {
            rows,
            cols,
            data: F64Array {
                encoding: WireEncoding::F64Le,
                values: data,
            },
        };
        m.validate()?;
        Ok(m)
    }
    /// Element `(i, j)` computed by `f`.
    pub fn from_fn(rows: u32, cols: u32, mut f: impl FnMut(usize, usize) -> f64) -> Self {
        let (r, c) = (rows as usize, cols as usize);
        let mut values = Vec::with_capacity(r * c);
        for i in 0..r {
            for j in 0..c {
                values.push(f(i, j));
            }
        }
        Self {
            rows,
            cols,
            data: F64Array {
                encoding: WireEncoding::F64Le,
                values,
            },
        }
    }
    /// Number of rows.
    pub fn rows(&self) -> usize {
        self.rows as usize
    }
    /// Number of columns.
    pub fn cols(&self) -> usize {
        self.cols as usize
    }
    /// Row-major elements.
    pub fn as_row_major(&self) -> &[f64] {
        &self.data.values
    }
    /// Takes the row-major elements.
    pub fn into_row_major(self) -> Vec<f64> {
        self.data.values
    }
    /// Element `(i, j)`, `None` out of range.
    pub fn get(&self, i: usize, j: usize) -> Option<f64> {
        if i < self.rows() && j < self.cols() {
            self.data.values.get(i * self.cols() + j).copied()
        } else {
            None
        }
    }
    /// Wire encoding of the elements.
    pub fn encoding(&self) -> WireEncoding {
        self.data.encoding
    }
}

impl Validate for WireMatrix {
    fn validate(&self) -> Result<(), ValidationError> {
        let expected = (self.rows as u64).checked_mul(self.cols as u64);
        check_len("WireMatrix", expected, self.data.values.len())?;
        check_finite("WireMatrix", &self.data.values)
    }
}

/// Index of `(i, j)`, `i <= j`, in a row-major packed upper triangle of order `n`.
fn packed_index(n: usize, i: usize, j: usize) -> usize {
    // Row i starts after rows 0..i, which hold n, n-1, ..., n-i+1 elements: i*n - i(i-1)/2.
    i * n - i * i.saturating_sub(1) / 2 + (j - i)
}

/// A dense symmetric `n × n` matrix stored as its packed upper triangle (row-major:
/// `(0,0) (0,1) … (0,n-1) (1,1) … (n-1,n-1)`), so symmetry holds by construction.
#[derive(Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct WireSymMatrix {
    dim: u32,
    data: F64Array,
}

impl fmt::Debug for WireSymMatrix {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "WireSymMatrix({}, {:?})", self.dim, self.data)
    }
}

impl WireSymMatrix {
    /// Number of packed elements for order `n`: n(n+1)/2.
    pub fn packed_len(n: u32) -> u64 {
        let n = n as u64;
        n * (n + 1) / 2
    }
    /// From the packed upper triangle; `Err` on a length mismatch or a non-finite value.
    pub fn from_packed_upper(dim: u32, packed: Vec<f64>) -> Result<Self, ValidationError> {
        let m = Self {
            dim,
            data: F64Array {
                encoding: WireEncoding::F64Le,
                values: packed,
            },
        };
        m.validate()?;
        Ok(m)
    }
    /// Element `(i, j)` for `i <= j` computed by `f` (the lower triangle mirrors it).
    pub fn from_fn(dim: u32, mut f: impl FnMut(usize, usize) -> f64) -> Self {
        let n = dim as usize;
        let mut values = Vec::with_capacity(n * (n + 1) / 2);
        for i in 0..n {
            for j in i..n {
                values.push(f(i, j));
            }
        }
        Self {
            dim,
            data: F64Array {
                encoding: WireEncoding::F64Le,
                values,
            },
        }
    }
    /// Takes the upper triangle of a dense row-major `dim × dim` matrix (the lower triangle is
    /// ignored; symmetrise before if it matters). `Err` on a length mismatch or non-finite value.
    pub fn from_dense_upper(dim: u32, dense_row_major: &[f64]) -> Result<Self, ValidationError> {
        let n = dim as usize;
        check_len(
            "WireSymMatrix dense input",
            (n as u64).checked_mul(n as u64),
            dense_row_major.len(),
        )?;
        let m = Self::from_fn(dim, |i, j| dense_row_major[i * n + j]);
        m.validate()?;
        Ok(m)
    }
    /// Order of the matrix.
    pub fn dim(&self) -> usize {
        self.dim as usize
    }
    /// The packed upper triangle.
    pub fn packed_upper(&self) -> &[f64] {
        &self.data.values
    }
    /// Element `(i, j)` (either triangle), `None` out of range.
    pub fn get(&self, i: usize, j: usize) -> Option<f64> {
        let n = self.dim();
        if i >= n || j >= n {
            return None;
        }
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        self.data.values.get(packed_index(n, i, j)).copied()
    }
    /// The full matrix, row-major.
    pub fn to_dense_row_major(&self) -> Vec<f64> {
        let n = self.dim();
        let mut out = vec![0.0; n * n];
        let mut k = 0;
        for i in 0..n {
            for j in i..n {
                let v = self.data.values.get(k).copied().unwrap_or(f64::NAN);
                out[i * n + j] = v;
                out[j * n + i] = v;
                k += 1;
            }
        }
        out
    }
    /// Wire encoding of the elements.
    pub fn encoding(&self) -> WireEncoding {
        self.data.encoding
    }
}

impl Validate for WireSymMatrix {
    fn validate(&self) -> Result<(), ValidationError> {
        check_len(
            "WireSymMatrix",
            Some(Self::packed_len(self.dim)),
            self.data.values.len(),
        )?;
        check_finite("WireSymMatrix", &self.data.values)
    }
}

/// Side of the blocks of [`WireBlockSymMatrix`] (3-D terrain features: 3 × 3 blocks).
pub const BLOCK_DIM: usize = 3;
const BLOCK_LEN: usize = BLOCK_DIM * BLOCK_DIM;

/// A block-sparse symmetric matrix of `n_blocks × n_blocks` blocks of 3 × 3, listing only the
/// non-zero blocks of the upper block triangle: block `(r, c)` with `r <= c`, strictly increasing
/// in `(r, c)` order (no duplicates), each as 9 row-major values. The lower triangle mirrors the
/// upper one; diagonal blocks must be exactly symmetric. Compact form for map deltas whose
/// non-zeros follow the features a vehicle observed.
#[derive(Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct WireBlockSymMatrix {
    n_blocks: u32,
    index: Vec<(u32, u32)>,
    data: F64Array,
}

impl fmt::Debug for WireBlockSymMatrix {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "WireBlockSymMatrix({} blocks, {} stored)",
            self.n_blocks,
            self.index.len()
        )
    }
}

impl WireBlockSymMatrix {
    /// From `(block_row, block_col, 9 row-major values)` triples in any order. Blocks below the
    /// diagonal are transposed into the upper triangle. `Err` on duplicates, out-of-range indices,
    /// non-finite values or an asymmetric diagonal block.
    pub fn from_blocks(
        n_blocks: u32,
        blocks: impl IntoIterator<Item = (u32, u32, [f64; BLOCK_LEN])>,
    ) -> Result<Self, ValidationError> {
        let mut v: Vec<(u32, u32, [f64; BLOCK_LEN])> = blocks
            .into_iter()
            .map(|(r, c, b)| {
                if r <= c {
                    (r, c, b)
                } else {
                    let mut t = [0.0; BLOCK_LEN];
                    for i in 0..BLOCK_DIM {
                        for j in 0..BLOCK_DIM {
                            t[j * BLOCK_DIM + i] = b[i * BLOCK_DIM + j];
                        }
                    }
                    (c, r, t)
                }
            })
            .collect();
        v.sort_by_key(|&(r, c, _)| (r, c));
        let mut values = Vec::with_capacity(v.len() * BLOCK_LEN);
        let mut index = Vec::with_capacity(v.len());
        for (r, c, b) in v {
            index.push((r, c));
            values.extend_from_slice(&b);
        }
        let m = Self {
            n_blocks,
            index,
            data: F64Array {
                encoding: WireEncoding::F64Le,
                values,
            },
        };
        m.validate()?;
        Ok(m)
    }

    /// From a dense row-major symmetric matrix of order `3 * n_blocks`, keeping the upper-triangle
    /// blocks with any non-zero entry. Diagonal blocks are taken from their upper triangle and
    /// mirrored, so they are exactly symmetric.
    pub fn from_dense(n_blocks: u32, dense_row_major: &[f64]) -> Result<Self, ValidationError> {
        let n = n_blocks as usize * BLOCK_DIM;
        check_len(
            "WireBlockSymMatrix dense input",
            (n as u64).checked_mul(n as u64),
            dense_row_major.len(),
        )?;
        let mut blocks = Vec::new();
        for br in 0..n_blocks as usize {
            for bc in br..n_blocks as usize {
                let mut b = [0.0; BLOCK_LEN];
                for i in 0..BLOCK_DIM {
                    for j in 0..BLOCK_DIM {
                        let (gi, gj) = (br * BLOCK_DIM + i, bc * BLOCK_DIM + j);
                        let (gi, gj) = if br == bc && i > j {
                            (gj, gi)
                        } else {
                            (gi, gj)
                        };
                        b[i * BLOCK_DIM + j] = dense_row_major[gi * n + gj];
                    }
                }
                if b.iter().any(|&x| x != 0.0) {
                    blocks.push((br as u32, bc as u32, b));
                }
            }
        }
        Self::from_blocks(n_blocks, blocks)
    }

    /// Number of block rows (= block columns).
    pub fn n_blocks(&self) -> usize {
        self.n_blocks as usize
    }
    /// Order of the full matrix (`3 * n_blocks`).
    pub fn dim(&self) -> usize {
        self.n_blocks as usize * BLOCK_DIM
    }
    /// Number of stored (upper-triangle, non-zero) blocks.
    pub fn stored_blocks(&self) -> usize {
        self.index.len()
    }
    /// The stored blocks: `(block_row, block_col, 9 row-major values)`, `block_row <= block_col`.
    pub fn blocks(&self) -> impl Iterator<Item = (u32, u32, &[f64])> + '_ {
        self.index
            .iter()
            .zip(self.data.values.chunks_exact(BLOCK_LEN))
            .map(|(&(r, c), b)| (r, c, b))
    }
    /// Element `(i, j)` of the full matrix, `None` out of range.
    pub fn get(&self, i: usize, j: usize) -> Option<f64> {
        if i >= self.dim() || j >= self.dim() {
            return None;
        }
        let (i, j) = if i / BLOCK_DIM <= j / BLOCK_DIM {
            (i, j)
        } else {
            (j, i)
        };
        let key = ((i / BLOCK_DIM) as u32, (j / BLOCK_DIM) as u32);
        match self.index.binary_search(&key) {
            Ok(k) => self
                .data
                .values
                .get(k * BLOCK_LEN + (i % BLOCK_DIM) * BLOCK_DIM + j % BLOCK_DIM)
                .copied(),
            Err(_) => Some(0.0),
        }
    }
    /// The full matrix, row-major.
    pub fn to_dense_row_major(&self) -> Vec<f64> {
        let n = self.dim();
        let mut out = vec![0.0; n * n];
        for (r, c, b) in self.blocks() {
            for i in 0..BLOCK_DIM {
                for j in 0..BLOCK_DIM {
                    let (gi, gj) = (r as usize * BLOCK_DIM + i, c as usize * BLOCK_DIM + j);
                    // Out-of-range blocks only exist in values that skipped `validate` (e.g.
                    // deserialised with another serde format); ignore them rather than panic.
                    if gi < n && gj < n {
                        out[gi * n + gj] = b[i * BLOCK_DIM + j];
                        out[gj * n + gi] = b[i * BLOCK_DIM + j];
                    }
                }
            }
        }
        out
    }
    /// Wire encoding of the elements.
    pub fn encoding(&self) -> WireEncoding {
        self.data.encoding
    }
}

impl Validate for WireBlockSymMatrix {
    fn validate(&self) -> Result<(), ValidationError> {
        const WHAT: &str = "WireBlockSymMatrix";
        check_len(
            WHAT,
            (self.index.len() as u64).checked_mul(BLOCK_LEN as u64),
            self.data.values.len(),
        )?;
        check_finite(WHAT, &self.data.values)?;
        let mut prev: Option<(u32, u32)> = None;
        for (k, &(r, c)) in self.index.iter().enumerate() {
            let bad = |reason| ValidationError::BlockIndex {
                what: WHAT,
                row: r,
                col: c,
                reason,
            };
            if r >= self.n_blocks || c >= self.n_blocks {
                return Err(bad("out of range"));
            }
            if r > c {
                return Err(bad("below the diagonal"));
            }
            if prev.is_some_and(|p| p >= (r, c)) {
                return Err(bad("out of order or duplicated"));
            }
            prev = Some((r, c));
            if r == c {
                let b = &self.data.values[k * BLOCK_LEN..(k + 1) * BLOCK_LEN];
                for i in 0..BLOCK_DIM {
                    for j in i + 1..BLOCK_DIM {
                        // Exact equality: constructors mirror the upper triangle, so a well-formed
                        // sender never produces rounding asymmetry.
                        if b[i * BLOCK_DIM + j] != b[j * BLOCK_DIM + i] {
                            return Err(ValidationError::Asymmetric {
                                what: WHAT,
                                row: r,
                                col: c,
                            });
                        }
                    }
                }
            }
        }
        Ok(())
    }
}

/// An opaque byte payload (one `memcpy` to encode).
#[derive(Clone, PartialEq, Eq, Default)]
pub struct WireBytes(pub Vec<u8>);

impl fmt::Debug for WireBytes {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "WireBytes({} bytes)", self.0.len())
    }
}

impl Serialize for WireBytes {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(&self.0)
    }
}
impl<'de> Deserialize<'de> for WireBytes {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        Ok(Self(ByteRun::deserialize(d)?.0.into_owned()))
    }
}
impl Validate for WireBytes {
    fn validate(&self) -> Result<(), ValidationError> {
        Ok(())
    }
}

/// An opaque byte payload borrowed from the received message (zero-copy decode).
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct WireBytesRef<'a>(pub &'a [u8]);

impl fmt::Debug for WireBytesRef<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "WireBytesRef({} bytes)", self.0.len())
    }
}

impl Serialize for WireBytesRef<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_bytes(self.0)
    }
}
impl<'de> Deserialize<'de> for WireBytesRef<'de> {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        match ByteRun::deserialize(d)?.0 {
            Cow::Borrowed(b) => Ok(Self(b)),
            Cow::Owned(_) => Err(de::Error::custom(
                "WireBytesRef needs a deserializer that lends its input",
            )),
        }
    }
}
impl Validate for WireBytesRef<'_> {
    fn validate(&self) -> Result<(), ValidationError> {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::{DEFAULT_MAX_BODY_LEN, decode, encode_to_vec};
    use crate::envelope::{Header, MessageKind, SendMeta};

    fn round_trip<T>(v: &T) -> T
    where
        T: Serialize + for<'a> Deserialize<'a> + Validate,
    {
        let meta = SendMeta::new(MessageKind::DDF_DELTA, 1, 0.0);
        let bytes = encode_to_vec(&meta, 1, v, DEFAULT_MAX_BODY_LEN).unwrap();
        let (_, back): (Header, T) = decode(&bytes, DEFAULT_MAX_BODY_LEN).unwrap();
        back
    }

    #[test]
    fn packed_index_enumerates_the_upper_triangle_in_order() {
        for n in 0..9 {
            let mut k = 0;
            for i in 0..n {
                for j in i..n {
                    assert_eq!(packed_index(n, i, j), k, "n={n} i={i} j={j}");
                    k += 1;
                }
            }
            assert_eq!(k as u64, WireSymMatrix::packed_len(n as u32));
        }
    }

    #[test]
    fn sym_matrix_round_trips_and_mirrors() {
        let n = 7;
        let dense: Vec<f64> = (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                (i.min(j) * 100 + i.max(j)) as f64 * 0.25
            })
            .collect();
        let m = WireSymMatrix::from_dense_upper(n as u32, &dense).unwrap();
        assert_eq!(m.to_dense_row_major(), dense);
        assert_eq!(m.get(6, 2), Some(dense[6 * n + 2]));
        assert_eq!(m.get(7, 0), None);
        assert_eq!(round_trip(&m), m);
    }

    #[test]
    fn block_sparse_matrix_matches_its_dense_source() {
        // Dense 4-block symmetric matrix with blocks (0,0), (0,2), (3,3) non-zero.
        let nb = 4u32;
        let n = 12;
        let mut dense = vec![0.0; n * n];
        let mut set = |i: usize, j: usize, v: f64| {
            dense[i * n + j] = v;
            dense[j * n + i] = v;
        };
        for i in 0..3 {
            for j in i..3 {
                set(i, j, 1.0 + (i * 3 + j) as f64);
                set(9 + i, 9 + j, -2.0 - (i + j) as f64);
            }
            for j in 0..3 {
                set(i, 6 + j, 0.5 * (i as f64 - j as f64) + 0.125);
            }
        }
        let m = WireBlockSymMatrix::from_dense(nb, &dense).unwrap();
        assert_eq!(m.stored_blocks(), 3);
        assert_eq!(m.to_dense_row_major(), dense);
        for i in 0..n {
            for j in 0..n {
                assert_eq!(m.get(i, j), Some(dense[i * n + j]));
            }
        }
        assert_eq!(round_trip(&m), m);
    }

    #[test]
    fn block_sparse_validation_rejects_bad_forms() {
        let sym = [1.0, 2.0, 3.0, 2.0, 4.0, 5.0, 3.0, 5.0, 6.0];
        let asym = [1.0, 2.0, 3.0, 2.5, 4.0, 5.0, 3.0, 5.0, 6.0];
        assert!(WireBlockSymMatrix::from_blocks(2, [(0, 0, sym), (1, 1, sym)]).is_ok());
        assert!(matches!(
            WireBlockSymMatrix::from_blocks(2, [(0, 0, asym)]),
            Err(ValidationError::Asymmetric { .. })
        ));
        assert!(matches!(
            WireBlockSymMatrix::from_blocks(2, [(0, 2, sym)]),
            Err(ValidationError::BlockIndex { .. })
        ));
        assert!(matches!(
            WireBlockSymMatrix::from_blocks(2, [(0, 1, sym), (1, 0, sym)]),
            Err(ValidationError::BlockIndex { .. })
        ));
        let mut nan = sym;
        nan[4] = f64::NAN;
        assert!(matches!(
            WireBlockSymMatrix::from_blocks(2, [(0, 1, nan)]),
            Err(ValidationError::NonFinite { .. })
        ));
        // Lower-triangle blocks are transposed into the upper triangle.
        let m = WireBlockSymMatrix::from_blocks(2, [(1, 0, asym)]).unwrap();
        // Full element (3 + i, j) is the given block's (i, j); (j, 3 + i) mirrors it.
        assert_eq!(m.get(3, 1), Some(asym[1]));
        assert_eq!(m.get(1, 3), Some(asym[1]));
        assert_eq!(m.get(4, 0), Some(asym[3]));
        assert_eq!(m.get(0, 4), Some(asym[3]));
    }

    #[test]
    fn dense_matrix_and_vector_validate_dimensions_and_finiteness() {
        assert!(WireMatrix::from_row_major(2, 3, vec![0.0; 6]).is_ok());
        assert!(matches!(
            WireMatrix::from_row_major(2, 3, vec![0.0; 5]),
            Err(ValidationError::Dimension {
                expected: 6,
                found: 5,
                ..
            })
        ));
        assert!(matches!(
            WireMatrix::from_row_major(1, 2, vec![0.0, f64::INFINITY]),
            Err(ValidationError::NonFinite { index: 1, .. })
        ));
        let m = WireMatrix::from_fn(3, 2, |i, j| (i * 2 + j) as f64);
        assert_eq!(m.get(2, 1), Some(5.0));
        assert_eq!(round_trip(&m), m);
        let v = WireVector::from_slice(&[1.5, -2.0]);
        assert_eq!(round_trip(&v), v);
        assert!(WireVector::from_slice(&[f64::NAN]).validate().is_err());
    }

    #[test]
    fn unknown_encoding_tag_is_rejected_by_the_decoder() {
        let v = WireVector::from_slice(&[1.0, 2.0]);
        let meta = SendMeta::new(MessageKind::DDF_DELTA, 1, 0.0);
        let mut body = crate::codec::encode_body_to_vec(&v).unwrap();
        // Layout: tuple(tag u8, bytes) -> first byte is the tag.
        assert_eq!(body[0], WireEncoding::F64Le.tag());
        body[0] = 7;
        let msg = encode_to_vec(
            &meta,
            1,
            &crate::codec::PreEncoded(&body),
            DEFAULT_MAX_BODY_LEN,
        )
        .unwrap();
        let err = decode::<WireVector>(&msg, DEFAULT_MAX_BODY_LEN).unwrap_err();
        assert!(
            err.to_string().contains("unknown float encoding tag 7"),
            "{err}"
        );
    }

    #[test]
    fn borrowed_bytes_decode_without_copy() {
        let payload = vec![3u8; 1000];
        let meta = SendMeta::new(MessageKind::CONTROL, 1, 0.0);
        let msg =
            encode_to_vec(&meta, 1, &WireBytes(payload.clone()), DEFAULT_MAX_BODY_LEN).unwrap();
        let (_, b): (Header, WireBytesRef<'_>) = decode(&msg, DEFAULT_MAX_BODY_LEN).unwrap();
        assert_eq!(b.0, &payload[..]);
        // The borrowed slice points into the message buffer.
        let range = msg.as_ptr_range();
        assert!(range.contains(&b.0.as_ptr()));
    }
}
