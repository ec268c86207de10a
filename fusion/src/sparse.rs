//! Conservative sparsification of a channel-filter delta under a byte budget (issue #13).
//!
//! A capacity-limited link cannot carry the whole channel delta D = Y_i − C_ik once the map is
//! large: it is dense over every feature whose information changed. The sender picks a feature
//! set S that fits the round's budget ([`select`]) and sends the *marginal* information of D on
//! S ([`schur_marginal`], Schur complement over the rest R):
//!
//! D'_SS = D_SS − D_SR D_RR⁻¹ D_RS,   d'_S = d_S − D_SR D_RR⁻¹ d_R.
//!
//! Both ends book D' in the channel filter (C_ik += D'), so the residual D − D' stays in
//! Y_i − C_ik and goes out in later rounds: nothing is lost, nothing counted twice, and the link
//! is exact again as soon as a whole delta fits (S then covers every feature of D and D' = D).
//!
//! Why D' never claims more than D. With T = [I, −D_SR D_RR⁻¹] (rows of S):
//!
//! D − pad(D') = [[D_SR D_RR⁻¹ D_RS, D_SR], [D_RS, D_RR]] = Gᵀ D_RR⁻¹ G with G = [D_RS, D_RR],
//!
//! which is positive semi-definite whenever D_RR is positive definite — for *any* symmetric D,
//! indefinite S block included. So pad(D') ⪯ D in the PSD order. For D the information of
//! independent linear-Gaussian data (d = D x + w, cov w = D), d' = T d = D' x_S + T w exactly
//! (T D = [D', 0]: no dependence on x_R), cov(T w) = T D Tᵀ = D', and the residual
//! d − pad(d') is uncorrelated with d' (pad(T) D (I − pad(T))ᵀ = pad(D') − pad(D') = 0): the
//! sent part and the residual are two independent pieces of information that add up to D.
//!
//! Regularisation. The Cholesky is of D_RR + δI with δ = 1e-9 · max diag D_RR
//! ([`REGULARISATION_FLOOR_REL`]: a singular D_RR — a residual of low rank, common after a few
//! sparsified rounds — would otherwise amplify round-off without bound). With δ > 0,
//! D − pad(D') = Gᵀ(D_RR + δI)⁻¹G − pad_R(δI) with G = [D_RS, D_RR + δI], so
//! pad(D') ⪯ D + δ·pad_R(I): the claim can exceed D by at most δ (1e-9 of the largest
//! information change) along directions of the *unsent* features (see Booking). The marginal
//! is evaluated about the sender's estimate ([`schur_marginal_about`]) so that the term
//! δ D_SR (D_RR + δI)⁻¹ x that d' picks up is in the sender's error, not in positions ~1e3 m
//! from the origin.
//!
//! Booking. The marginal is the *exact* marginal of the shifted delta
//! (D + pad_R(δ I), d + pad_R(δ x̄_R)) ([`Shift`]). The sender books D' − pad_R(δ I) (and
//! d' − pad_R(δ x̄_R)) as sent, so the residual left in Y_i − C_ik is the exact Schur residual
//! of the shifted delta, Gᵀ(D_RR + δI)⁻¹G with G = [D_RS, D_RR + δI]: positive semi-definite
//! whatever δ was. Booked as D' alone, the residual would be that minus pad_R(δ I): negative
//! at the floor's own size, and round after round such negativity met the next floor — the
//! next D_RR + δI was near-singular (garbage marginals) or not positive definite (refused),
//! which stalled the radio links (measured on the default team at 32 kB/s, 300 s: 929 refused
//! rounds, 757 of them at λ_min(D_RR) ≥ −2e-9 · max diag; team map RMSE 25× the
//! reference; booked with the shift: none refused, 1.10×; 1.12× with the escalation rule of
//! [`MAX_REGULARISATION_REL`]). The price: the receiver holds
//! what it was sent, so the δ I it was sent beyond the delta stays with it — the team's maps
//! can exceed the centralized sum by Σ δ over the sparsified deltas (1e-9 of each one's
//! largest held-back diagonal, up to [`MAX_REGULARISATION_REL`] when D_RR needed more;
//! [`crate::ddf::ChannelView::sparse_shift`] adds them up per
//! link, and `fusion/tests/ddf_sparse.rs` asserts the bound run by run).
//!
//! A D_RR that is not positive definite at [`MAX_REGULARISATION_REL`] of its own scale, nor at
//! [`OPERAND_REGULARISATION_REL`] of Y_i's (Y_i − C is a cancellation of Y_i's size; with
//! little pending, D_RR is far smaller than Y_i), is indefinite beyond what regularisation
//! may absorb (relinearisation or a removed feature made Y_i − C indefinite) and is refused
//! ([`SparsifyError::Indefinite`], naming the feature of the failing pivot): no D' supported on
//! S alone can be ⪯ D then (take x = (0, v), v a negative direction of D_RR), and the Schur
//! complement is no marginalisation. The channel first retries with that feature moved into S
//! (a few times); then the round sends nothing on that link, counted, and the whole delta stays
//! pending ([`MAX_REGULARISATION_REL`] records what larger δ did). The consistency of the
//! scheme as a whole is checked by NEES in the Monte Carlo of `fusion/tests/ddf_sparse.rs`.
//!
//! The marginal's vector. About the sender's estimate x̄ the vector sent is d'_S = D' x̄_S + e
//! with e = d̃_S − D_SR (D_RR + δI)⁻¹ d̃_R, d̃ = d − D x̄. For linear-Gaussian data and a sender
//! whose estimate includes the delta, cov e = D' − D' P_SS D' ⪯ D': e is consistent with the
//! information it rides on. An EKF's channel books are not: every vector booked was formed
//! about the estimate of its round, so as the estimates move the residual's vector
//! d̃ = −(c − C x̄) (the estimator's own y_i = Y_i x̄ cancels) drifts by C (x̄ − x̄_then), and
//! D_RR — only the information still pending — cannot explain that drift; the solve through
//! its weak directions (the held-back features' common translation holds ~1e-8 of its scale)
//! turns it into an e that D' does not support. The receiver fuses what it is sent: in the
//! multi-process radio-32k runs such deltas moved a vehicle's pose and whole map 5–60 m per
//! round (mostly along the vertical) while its covariance stayed at metres (pose ANEES up to
//! 1415). So e is gated direction by direction: along each eigen-direction u_k of D' its
//! component c_k = u_kᵀ e must satisfy c_k² / λ_k ≤ χ²₁(1 − (1 − [`VECTOR_GATE_PROBABILITY`]) / r)
//! (r the rank of D'; Bonferroni, so consistent data passes whole with the gate's probability);
//! a component beyond it is removed from e. Sending e = 0 instead (d'_S = D' x̄_S) also stopped
//! the divergence but cost accuracy (docs/arch/ddf.md). The gated d' is booked as sent like any
//! d', so what was not sent stays in the residual; the information matrix — what
//! conservativeness is about — is untouched. For linear-Gaussian data the gate changes one delta
//! in 10⁶ (none of the Monte Carlo's 180 000).
//!
//! Re-centring. For an EKF sender y_i = Y_i x̄, so d̃ = d − D x̄ = C x̄ − c exactly: the pull of
//! the common information towards where the sender now is. For linear-Gaussian data that pull
//! is what new data did to the estimate, and e carries it consistently; for an EKF it also
//! holds the drift of vectors booked about older estimates. What the gate removes is that
//! drift, and booked as sent only as far as it went on the wire it stayed pending: the next
//! marginal found it again (through D_SR (D_RR + δI)⁻¹ d̃_R, whatever S was), and a link could
//! gate round after round for minutes (801 of 1 733 marginals in one multi-process run of
//! tree-8-radio with a two-second interval; `fusion/tests/ddf_sparse.rs`,
//! `a_gated_drift_is_recentred_not_retried`: 30 of 30 rounds). So when the gate keeps
//! removing (`crate::ddf`'s channel, `RECENTRE_AFTER_GATED` consecutive marginals), the
//! sender also books [`Marginal::recentre`] = d̃ − pad_S(e) (e as sent) as sent:
//! its books' vector is re-centred on its estimate, and what stays pending is (D − D') x̄ plus
//! the shifts — a pull towards x̄ with exactly the information still pending (its e is 0 until
//! the estimate moves again). The peer never receives the re-centring: it is recorded beside the
//! shifts ([`crate::ddf`]'s channel, `booked_shift`), so a Cumulative carries what went on
//! the wire. Only vectors move; the information booked and the argument for conservativeness
//! are untouched. The price is the pull through C of data not yet delivered on such a round:
//! the peer's means of the common features then move only with the information sent later —
//! why an isolated gate does not re-centre (the channel's constant says what it cost).

use crate::info::MapInformation;
use crate::sensor::FeatureId;
use crate::state::FEATURE_DIM;
use faer::{Col, Mat, Side};
use nalgebra::{Matrix3, Vector3};
use std::collections::HashMap;

/// Regularisation always added to D_RR, relative to max diag D_RR: bounds the amplification
/// of round-off along (near-)null directions of D_RR.
///
/// Why this value: a singular D_RR (a residual of low rank, common after a few sparsified
/// rounds) can still pass a Cholesky with pivots at round-off size (~1e-16 · max diag); its
/// inverse then multiplies the round-off of d_R (~1e-16 · |D| · |x − o| with |x − o| up to
/// ~1e3 m) by ~1e16 / |D| — an error of the size of the signal. With δ ≥ 1e-9 · max diag the
/// amplification is at most 1e9 / max diag, leaving ~1e-4 m of mean error; the claim
/// exceeds D by at most δ on unsent-feature directions (module docs), i.e. 1e-9 of the largest
/// information change.
pub const REGULARISATION_FLOOR_REL: f64 = 1e-9;

/// Largest regularisation searched, relative to max diag D_RR (beyond it: refused); δ rises
/// tenfold from the floor until D_RR + δI is positive definite, then one step more for a
/// well-conditioned solve (so the δ used is at most ten times this).
///
/// Why 1e-7: since the regularisation is booked (module docs, "Booking") a larger δ no longer
/// piles up in the residual; it only raises the bounded claim Σ δ. What is left to absorb is
/// the estimator's own round-off in Y_i (a map information formed from a strongly correlated
/// covariance): on the default team at 64 kB/s (300 s, `canopy sim`) uav1's delta to uav3 sat
/// at λ_min ≈ −1.5e-8 of its max diag for most of the run (worst −1.1e-6), refused 163 times
/// at the floor, and uav2 ended with features 20–28 m off (team map RMSE 1.47× the
/// reference); with 1e-7 (and 1e-6: the same run to the last digit) nothing was refused and it
/// was 1.12× (1.15× once the margin step above was added; 32 kB/s: 1.10× → 1.12×). Before the booking, escalating to 1e-2 was unsound (radio-8k uav2 6.5× more
/// confident than the reference: very negative D' that the receiver's estimator refused after
/// both ends booked it); that case is refused by [`MAX_NEGATIVE_REL`]. Over 300 rounds the
/// bound Σ δ stays below 3e-5 of the largest held-back diagonal.
pub const MAX_REGULARISATION_REL: f64 = 1e-7;

/// Largest regularisation searched relative to the *operand scale* of the delta (the largest
/// entry of the information Y_i it was formed from, D = Y_i − C_ik; [`schur_marginal_about`]):
/// the search stops at the larger of this · scale and [`MAX_REGULARISATION_REL`] · max diag
/// D_RR (the cap itself tried last).
///
/// Why relative to Y_i: D = Y_i − C_ik is a difference of matrices of Y_i's size, and what
/// makes it indefinite (the estimator's round-off in Y_i, an estimator whose map information
/// after fusing is not exactly Y + D': module docs) is of Y_i's size too. When little is
/// pending on the held-back features, max diag D_RR is far below Y_i's entries, and a cap
/// relative to D_RR alone refuses round after round: the whole delta stays pending and the
/// link stalls.
///
/// Why 1e-6: measured on `topologies/tree-8-radio.toml` with `radio_interval_s = 2` and
/// `heap = "lean"` as real processes (300 s, 2026-12-07). With the cap relative to D_RR alone,
/// 188 and 291 of ~1 900 sparsified rounds were refused (up to 119 of 132 at one link end),
/// 88–334 vectors gated, team map RMSE 1.56 m, two vehicles ending 1.8–2.9 m off. At the
/// refusals max diag D_RR was 0.7–25 against Y_i's largest entry of 150–190, and λ_min(D_RR)
/// between −1e-7 and −6e-7 of that entry (897 failed factorisations in one run, persisting
/// over tens of rounds), with ~150 of D_RR's ~400 eigenvalues at ±1e-8 (features with nothing
/// pending). Capped at 1e-7 of Y_i: 99 and 170 refused; at 1e-6: 1, 7 and 12 in three runs,
/// none for an indefinite D_RR (marginals too negative), team map RMSE 0.89–1.37 m (the
/// vector gate, not this cap, limits that interval: docs/benchmarks.md, fifteenth pass). On
/// radio-32k (`canopy sim`, seed 1, 300 s) nothing reaches the old cap and the run is the same
/// to the last digit. The claim it allows, δ ≤ 1e-5 · scale in a round with the margin step
/// (1.5e-3 m⁻² at scale 150, the information of a 26 m standard deviation), is booked like any
/// δ and bounded by Σ δ ([`crate::ddf::ChannelView::sparse_shift`]); rounds that escalate at
/// all are ~2 % (36 of 1 739 in that run).
pub const OPERAND_REGULARISATION_REL: f64 = 1e-6;

/// Largest information removal accepted from a marginal: λ_min(D') ≥ −`MAX_NEGATIVE_REL` ·
/// λ_max(D_SS), else refused.
///
/// Why: for positive semi-definite D the marginal is positive semi-definite, so a clearly
/// negative D' means D is indefinite along a (near-)null direction of D_RR that passed the
/// Cholesky at the floor; (D_RR + δI)⁻¹ ~ 1/δ there makes D' and d' garbage. Seen in a
/// multi-process radio-32k run without this check: uav1's map RMSE 816 m (team 198× the
/// reference) while never more confident than the reference. 1e-3 admits round-off.
pub const MAX_NEGATIVE_REL: f64 = 1e-3;

/// Probability of the χ² gate on the marginal's vector (module docs, "The marginal's
/// vector"): the components of e = d'_S − D' x̄_S along D''s eigen-directions whose χ² exceeds
/// the per-direction quantile (Bonferroni over the r directions) are not sent.
///
/// Why 1 − 1e-6: for linear-Gaussian data e is consistent with D' (cov e = D' − D' P_SS D' ⪯
/// D') and fails the gate once in 10⁶ deltas (a 90 s radio run forms ~400); removing a
/// component then is harmless (it is booked as not sent and goes out with later deltas). In
/// the SLAM radio runs the channel's books hold vectors formed about earlier estimates; after
/// some event their drift gave e with χ² of 10³–10⁷ on one link, round after round, and the
/// receiver's map and pose were moved 5–60 m per round (`radio_32k`, issue 13).
pub const VECTOR_GATE_PROBABILITY: f64 = 1.0 - 1e-6;

/// Factor between successive regularisation attempts (the floor, tenfold, up to the cap).
const REGULARISATION_STEP: f64 = 10.0;

/// Why a delta could not be sparsified (the round sends nothing on that link; counted).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SparsifyError {
    /// D_RR + δI was not positive definite even with the largest δ accepted.
    #[error("residual block not positive definite up to regularisation δ = {max_delta:.3e}")]
    Indefinite {
        /// The largest δ tried: [`MAX_REGULARISATION_REL`] · max diag D_RR or
        /// [`OPERAND_REGULARISATION_REL`] · the operand scale, whichever is larger (0 when
        /// D_RR's diagonal is zero).
        max_delta: f64,
        /// The held-back feature of the first non-positive pivot (moving it into S is the
        /// caller's next attempt).
        feature: Option<FeatureId>,
    },
    /// The marginal came out non-finite (overflow in a near-singular solve).
    #[error("marginal information not finite")]
    NonFinite,
    /// The marginal removes more information than [`MAX_NEGATIVE_REL`] of the S block's
    /// largest eigenvalue: D is indefinite along a (near-)null direction of D_RR.
    #[error("marginal too negative: λ_min {min:.3e} against λ_max(D_SS) {max:.3e}")]
    TooNegative {
        /// λ_min(D').
        min: f64,
        /// λ_max(D_SS).
        max: f64,
    },
}

/// The regularisation δ of a marginal as information: δ I on each held-back feature's
/// diagonal block and δ x̄_f in its vector (x̄ the reference the marginal was evaluated about,
/// origin-relative). The marginal is the exact marginal of (D + pad_R(δ I), d + pad_R(δ x̄_R)).
#[derive(Clone, Debug, Default)]
pub struct Shift {
    /// δ.
    pub delta: f64,
    /// The held-back features R and their reference positions x̄_f.
    pub features: Vec<(FeatureId, Vector3<f64>)>,
}

/// The marginal information of a delta on the selected features.
#[derive(Clone, Debug)]
pub struct Marginal {
    /// The shift added to the delta before marginalising (module docs); its δ is 0 only when
    /// nothing was held back.
    pub shift: Shift,
    /// (D', d') over the selected features present in the delta, in the order they were given.
    pub info: MapInformation,
    /// δ had to exceed the floor [`REGULARISATION_FLOOR_REL`] (D_RR not positive definite
    /// beyond round-off: the delta is indefinite on held-back features).
    pub escalated: bool,
    /// Features of the delta left out (R, those with any non-zero entry).
    pub held_back: usize,
    /// χ² of the marginal's vector about the reference, e = d'_S − D' x̄_S, against the
    /// marginal's information D' (0 when nothing was held back or the marginal is not gated).
    pub vector_chi2: f64,
    /// Some component of e failed its gate ([`VECTOR_GATE_PROBABILITY`]) and was removed.
    pub vector_dropped: bool,
    /// When the gate removed something ([`Marginal::vector_dropped`]): d̃ − pad_S(e) per
    /// feature of the delta (e the vector sent, after the gate), the stale part of the books'
    /// vector that the sender books as sent beside the marginal (module docs, "Re-centring");
    /// empty otherwise.
    pub recentre: Vec<(FeatureId, Vector3<f64>)>,
}

/// How many features' dense delta fits `budget` bytes
/// ([`MapInformation::dense_block_wire_bytes_as`], blocks f32 when `f32_blocks`; 0 if not even
/// one).
pub fn max_features(budget: usize, f32_blocks: bool) -> usize {
    // n(n+1)/2 · (46 or 82) bytes dominates: √(2 · budget / 46) + 2 bounds the answer.
    let mut n = ((2.0 * budget as f64 / 46.0).sqrt() as usize) + 2;
    while n > 0 && MapInformation::dense_block_wire_bytes_as(n, f32_blocks) > budget {
        n -= 1;
    }
    n
}

/// Priority of each feature of `delta`: the information gain of its diagonal block,
/// ln det(I + P_ff D_ff) = Σ ln(1 + max(μ, 0)) over the eigenvalues μ of Lᵀ D_ff L (P_ff = L Lᵀ,
/// the sender's covariance of the feature; negative μ — information removed — count 0). A
/// feature without a covariance in `covariances` (or a non-positive-definite one) uses
/// P_ff = I (m²). Returned in the order of `delta.ids`.
pub fn priorities(
    delta: &MapInformation,
    covariances: &HashMap<FeatureId, Matrix3<f64>>,
) -> Vec<(FeatureId, f64)> {
    delta
        .ids
        .iter()
        .enumerate()
        .map(|(k, &id)| {
            let b = FEATURE_DIM * k;
            let d = Matrix3::from_fn(|r, c| {
                0.5 * (delta.matrix[(b + r, b + c)] + delta.matrix[(b + c, b + r)])
            });
            let l = covariances
                .get(&id)
                .and_then(|p| p.cholesky())
                .map_or_else(Matrix3::identity, |c| c.l());
            let m = l.transpose() * d * l;
            let m = 0.5 * (m + m.transpose());
            let gain: f64 = m
                .symmetric_eigenvalues()
                .iter()
                .map(|&mu| {
                    if mu.is_finite() {
                        mu.max(0.0).ln_1p()
                    } else {
                        0.0
                    }
                })
                .sum();
            (id, gain)
        })
        .collect()
}

/// The features to send: the highest [`priorities`] first (ties: the smaller id), as many as
/// fit `budget` bytes as a dense delta ([`max_features`], f32 blocks when `f32_blocks`). Features whose gain is 0 (nothing
/// gained on their diagonal block) come last but are still eligible: their cross terms may
/// matter.
pub fn select(
    delta: &MapInformation,
    covariances: &HashMap<FeatureId, Matrix3<f64>>,
    budget: usize,
    f32_blocks: bool,
) -> Vec<FeatureId> {
    let mut p = priorities(delta, covariances);
    p.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    p.truncate(max_features(budget, f32_blocks));
    p.into_iter().map(|(id, _)| id).collect()
}

/// The marginal information of `delta` on the features `keep` (module docs): the Schur
/// complement over the features of `delta` not in `keep` that carry any non-zero entry
/// (all-zero ones contribute nothing and are skipped). Ids of `keep` absent from `delta` are
/// ignored. With nothing held back the result is `delta` restricted to `keep`, unchanged.
pub fn schur_marginal(
    delta: &MapInformation,
    keep: &[FeatureId],
) -> Result<Marginal, SparsifyError> {
    marginal(delta, keep, &HashMap::new(), false, 0.0)
}

/// [`schur_marginal`] evaluated about a reference map `about` (feature positions relative to
/// the origin, normally the sender's current estimate; features without one use 0): with
/// d̃ = d − D x̄, d'_S = d̃_S − D_SR D̃_RR⁻¹ d̃_R + D' x̄_S. Identical to [`schur_marginal`]
/// in exact arithmetic without regularisation; with δ > 0 the term d' picks up from x_R
/// shrinks from δ D_SR D̃_RR⁻¹ x_R (positions ~1e3 m from the origin) to
/// δ D_SR D̃_RR⁻¹ (x_R − x̄_R) (the sender's error, metres). Measured on radio-8k: without it
/// the team's maps diverged (module docs).
///
/// About a reference the marginal's vector is also *gated* against its information (module
/// docs, "The marginal's vector"; [`VECTOR_GATE_PROBABILITY`], [`Marginal::vector_dropped`]);
/// [`schur_marginal`] (no reference: d̃ = d carries D x itself) does not gate.
///
/// `operand_scale` is the size of what the delta was formed from (the largest entry of the
/// sender's Y_i, D = Y_i − C_ik; 0 for none): the regularisation is searched up to
/// [`OPERAND_REGULARISATION_REL`] of it when that exceeds the cap relative to D_RR.
pub fn schur_marginal_about(
    delta: &MapInformation,
    keep: &[FeatureId],
    about: &HashMap<FeatureId, Vector3<f64>>,
    operand_scale: f64,
) -> Result<Marginal, SparsifyError> {
    marginal(delta, keep, about, true, operand_scale)
}

fn marginal(
    delta: &MapInformation,
    keep: &[FeatureId],
    about: &HashMap<FeatureId, Vector3<f64>>,
    gate: bool,
    operand_scale: f64,
) -> Result<Marginal, SparsifyError> {
    let xbar = Col::from_fn(delta.vector.nrows(), |r| {
        about
            .get(&delta.ids[r / FEATURE_DIM])
            .map_or(0.0, |x| x[r % FEATURE_DIM])
    });
    // d̃ = d − D x̄.
    let shifted = &delta.vector - &delta.matrix * &xbar;
    let index: HashMap<FeatureId, usize> = delta
        .ids
        .iter()
        .enumerate()
        .map(|(k, &id)| (id, k))
        .collect();
    let mut in_s = vec![false; delta.ids.len()];
    let s_blocks: Vec<usize> = keep
        .iter()
        .filter_map(|id| index.get(id).copied())
        .filter(|&k| !std::mem::replace(&mut in_s[k], true))
        .collect();
    let nonzero = |k: usize| {
        let rows = FEATURE_DIM * k..FEATURE_DIM * (k + 1);
        rows.clone().any(|r| delta.vector[r] != 0.0)
            || rows
                .into_iter()
                .any(|c| delta.matrix.col_as_slice(c).iter().any(|&v| v != 0.0))
    };
    let r_blocks: Vec<usize> = (0..delta.ids.len())
        .filter(|&k| !in_s[k] && nonzero(k))
        .collect();
    let rows = |blocks: &[usize]| -> Vec<usize> {
        blocks
            .iter()
            .flat_map(|&k| (0..FEATURE_DIM).map(move |a| FEATURE_DIM * k + a))
            .collect()
    };
    let (sr, rr) = (rows(&s_blocks), rows(&r_blocks));
    let (ns, nr) = (sr.len(), rr.len());
    let m = &delta.matrix;
    let mut d_ss = Mat::from_fn(ns, ns, |i, j| m[(sr[i], sr[j])]);
    let mut d_s = Col::from_fn(ns, |i| shifted[sr[i]]);
    let mut regularisation = 0.0;
    let mut escalated = false;
    let (mut vector_chi2, mut vector_dropped) = (0.0, false);
    let mut recentre = Vec::new();
    // λ_min(D'), when the gate already decomposed D' (the negativity check below reuses it).
    let mut marginal_min = None;
    if nr > 0 {
        let max_diag = rr.iter().map(|&r| m[(r, r)].abs()).fold(0.0_f64, f64::max);
        regularisation = REGULARISATION_FLOOR_REL * max_diag;
        // Searched up to a cap relative to D_RR's own scale or to the operands D was formed
        // from, whichever is larger ([`OPERAND_REGULARISATION_REL`]).
        let operand_scale = if operand_scale.is_finite() {
            operand_scale.abs()
        } else {
            0.0
        };
        let cap =
            (MAX_REGULARISATION_REL * max_diag).max(OPERAND_REGULARISATION_REL * operand_scale);
        let mut margin = false;
        // L Lᵀ = D_RR + δI, gathered and factored in one nr × nr buffer (the largest of the
        // marginal: 26 MB at 600 held-back features); a retry gathers it again.
        let l = loop {
            let mut a = Mat::from_fn(nr, nr, |i, j| {
                m[(rr[i], rr[j])] + if i == j { regularisation } else { 0.0 }
            });
            match crate::info::cholesky_lower_in_place(a.as_mut()) {
                // Escalated: one more step, so that λ_min(D_RR + δI) ≥ 0.9 δ (D_RR + δI/10 was
                // positive definite) and the solve amplifies d_R's round-off by at most
                // 1/(0.9 δ), not by 1/(δ − |λ_min(D_RR)|), which may be tiny.
                Ok(()) if escalated && !margin => {
                    margin = true;
                    regularisation *= REGULARISATION_STEP;
                }
                Ok(()) => break a,
                Err(faer::linalg::solvers::LltError::NonPositivePivot { index }) => {
                    let feature = r_blocks
                        .get(index.min(nr.saturating_sub(1)) / FEATURE_DIM)
                        .map(|&k| delta.ids[k]);
                    escalated = true;
                    // Tenfold up to the cap, the cap itself tried last. `!(<)` also refuses a
                    // zero or NaN max diag.
                    if !(regularisation > 0.0 && regularisation < cap) {
                        return Err(SparsifyError::Indefinite {
                            max_delta: regularisation,
                            feature,
                        });
                    }
                    regularisation = (regularisation * REGULARISATION_STEP).min(cap);
                }
            }
        };
        // W = L⁻¹ [D_RS | d̃_R]: one triangular solve, then
        // [M | p] = W_Sᵀ W = D_SR (D_RR + δI)⁻¹ [D_RS | d̃_R] (L⁻ᵀ L⁻¹ = (D_RR + δI)⁻¹), half
        // the solve of a full (D_RR + δI)⁻¹ and no gathered copy of D_SR.
        let mut w = Mat::from_fn(nr, ns + 1, |i, j| {
            if j < ns {
                m[(rr[i], sr[j])]
            } else {
                shifted[rr[i]]
            }
        });
        faer::linalg::triangular_solve::solve_lower_triangular_in_place(
            l.as_ref(),
            w.as_mut(),
            faer::get_global_parallelism(),
        );
        drop(l);
        let prod = w.as_ref().subcols(0, ns).transpose() * &w;
        for j in 0..ns {
            for i in 0..ns {
                d_ss[(i, j)] -= prod[(i, j)];
            }
            d_s[j] -= prod[(j, ns)];
        }
        crate::info::symmetrize(&mut d_ss);
        if gate && ns > 0 {
            let g = gate_vector(&d_ss, &mut d_s)?;
            (vector_chi2, vector_dropped) = (g.chi2, g.removed > 0);
            marginal_min = Some(g.lambda_min);
            if vector_dropped {
                // d̃ − pad_S(e): what would stay pending beyond (D − D') x̄ once this marginal
                // is booked (module docs, "Re-centring").
                recentre = (0..delta.ids.len())
                    .map(|k| {
                        let b = FEATURE_DIM * k;
                        (delta.ids[k], Vector3::from_fn(|a, _| shifted[b + a]))
                    })
                    .collect();
                for (q, &k) in s_blocks.iter().enumerate() {
                    let b = FEATURE_DIM * q;
                    recentre[k].1 -= Vector3::from_fn(|a, _| d_s[b + a]);
                }
            }
        }
    }
    // Back from d̃: d'_S += D' x̄_S.
    let xbar_s = Col::from_fn(ns, |i| xbar[sr[i]]);
    let d_s = &d_s + &d_ss * &xbar_s;
    let finite =
        (0..ns).all(|j| d_s[j].is_finite() && d_ss.col_as_slice(j).iter().all(|v| v.is_finite()));
    if !finite {
        return Err(SparsifyError::NonFinite);
    }
    if nr > 0 && ns > 0 {
        let eig = |m: &Mat<f64>| -> Result<Vec<f64>, SparsifyError> {
            m.as_ref()
                .self_adjoint_eigenvalues(Side::Lower)
                .map_err(|_| SparsifyError::NonFinite)
        };
        let block = Mat::from_fn(ns, ns, |i, j| m[(sr[i], sr[j])]);
        let max = eig(&block)?.last().copied().unwrap_or(0.0).max(0.0);
        let min = match marginal_min {
            Some(min) => min,
            None => eig(&d_ss)?.first().copied().unwrap_or(0.0),
        };
        if min < -MAX_NEGATIVE_REL * max {
            return Err(SparsifyError::TooNegative { min, max });
        }
    }
    let shift = Shift {
        delta: regularisation,
        features: r_blocks
            .iter()
            .map(|&k| {
                let b = FEATURE_DIM * k;
                (
                    delta.ids[k],
                    Vector3::new(xbar[b], xbar[b + 1], xbar[b + 2]),
                )
            })
            .collect(),
    };
    Ok(Marginal {
        shift,
        info: MapInformation {
            ids: s_blocks.iter().map(|&k| delta.ids[k]).collect(),
            origin: delta.origin,
            matrix: d_ss,
            vector: d_s,
        },
        escalated,
        held_back: r_blocks.len(),
        vector_chi2,
        vector_dropped,
        recentre,
    })
}

/// Gates e against the information D' (symmetric, positive semi-definite up to round-off and
/// the small negative part [`MAX_NEGATIVE_REL`] admits) direction by direction, in place: along
/// each eigen-direction u_k the χ² c_k² / (λ_k₊ + τ) (c_k = u_kᵀ e, negative eigenvalues as 0,
/// τ = 1e-12 λ_max(D'): a component along a direction D' does not support is exactly what the
/// gate is for) must stay within χ²₁(1 − (1 − [`VECTOR_GATE_PROBABILITY`]) / r), r the
/// numerical rank of D' (at least 1); a component beyond it (or not finite) is removed.
/// Returns the total χ² before gating, the number of components removed and λ_min(D').
fn gate_vector(info: &Mat<f64>, e: &mut Col<f64>) -> Result<VectorGate, SparsifyError> {
    let n = info.nrows();
    let evd = info
        .as_ref()
        .self_adjoint_eigen(Side::Lower)
        .map_err(|_| SparsifyError::NonFinite)?;
    let lambda = evd.S().column_vector();
    let max = (0..n).map(|i| lambda[i]).fold(0.0_f64, f64::max);
    let tau = 1e-12 * max;
    let u = evd.U();
    let rank = (0..n).filter(|&k| lambda[k] > tau).count().max(1);
    // Bonferroni over the directions: the whole vector passes with probability ≥ the gate's.
    let gate =
        crate::consistency::chi2_quantile(1.0, 1.0 - (1.0 - VECTOR_GATE_PROBABILITY) / rank as f64)
            .map_err(|_| SparsifyError::NonFinite)?;
    let mut chi2 = 0.0;
    let mut removed = 0;
    for k in 0..n {
        let c: f64 = (0..n).map(|i| u[(i, k)] * e[i]).sum();
        let q = c * c / (lambda[k].max(0.0) + tau).max(f64::MIN_POSITIVE);
        chi2 += q;
        // A NaN χ² is removed too (an infinite one fails the comparison).
        if q.is_nan() || q > gate {
            for i in 0..n {
                e[i] -= c * u[(i, k)];
            }
            removed += 1;
        }
    }
    let lambda_min = (0..n).map(|k| lambda[k]).fold(f64::INFINITY, f64::min);
    Ok(VectorGate {
        chi2,
        removed,
        lambda_min: if n == 0 { 0.0 } else { lambda_min },
    })
}

/// What [`gate_vector`] found.
struct VectorGate {
    /// eᵀ (D'₊ + τI)⁻¹ e before gating.
    chi2: f64,
    /// Components of e removed.
    removed: usize,
    /// The smallest eigenvalue of D'.
    lambda_min: f64,
}

/// The feature of a sparsified delta's marginal `info` that a peer would not hold with a
/// positive definite information of σ ≤ `max_sigma_m` along its worst axis after fusing it,
/// among the features whose only information at the peer is what this side sent (`is_new`:
/// the peer never sent any on them): their information there is `sent(ids)` (the joint block
/// of everything sent on them before, zero for features never sent) plus `info`'s block. The
/// one with the smallest eigenvalue of its own 3 × 3 block below 1/`max_sigma_m`², or, when
/// every block passes, the one whose pivot fails in a Cholesky of the joint block (what the
/// receiver's fusion needs positive definite: its new features' ΔY_uu, summed over a batch of
/// deltas that introduce them). `None` when all pass. (`crate::ddf::MAX_INTRODUCED_SIGMA_M`
/// says why.)
pub fn weakest_new_feature(
    info: &MapInformation,
    is_new: impl Fn(&FeatureId) -> bool,
    sent: impl Fn(&[FeatureId]) -> Mat<f64>,
    max_sigma_m: f64,
) -> Option<FeatureId> {
    let floor = 1.0 / (max_sigma_m * max_sigma_m);
    let (blocks, ids): (Vec<usize>, Vec<FeatureId>) = info
        .ids
        .iter()
        .enumerate()
        .filter(|(_, id)| is_new(id))
        .map(|(b, &id)| (b, id))
        .unzip();
    if ids.is_empty() {
        return None;
    }
    let before = sent(&ids);
    let n = FEATURE_DIM * ids.len();
    let mut joint = Mat::from_fn(n, n, |r, c| {
        let (p, q) = (
            FEATURE_DIM * blocks[r / FEATURE_DIM] + r % FEATURE_DIM,
            FEATURE_DIM * blocks[c / FEATURE_DIM] + c % FEATURE_DIM,
        );
        0.5 * (info.matrix[(p, q)] + info.matrix[(q, p)] + before[(r, c)] + before[(c, r)])
    });
    let weakest = ids
        .iter()
        .enumerate()
        .map(|(t, &id)| {
            let block = Matrix3::from_fn(|i, j| joint[(FEATURE_DIM * t + i, FEATURE_DIM * t + j)]);
            (block.symmetric_eigenvalues().min(), id)
        })
        // NaN fails too.
        .filter(|(l, _)| l.is_nan() || *l < floor)
        .min_by(|a, b| a.0.total_cmp(&b.0));
    if let Some((_, id)) = weakest {
        return Some(id);
    }
    match crate::info::cholesky_lower_in_place(joint.as_mut()) {
        Ok(()) => None,
        Err(faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index }) => {
            Some(ids[index / FEATURE_DIM])
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::linalg::solvers::{DenseSolveCore, Solve};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_psd(n: usize, rank: usize, rng: &mut ChaCha8Rng) -> Mat<f64> {
        let g = Mat::from_fn(n, rank, |_, _| rng.random_range(-1.0..1.0));
        &g * g.transpose()
    }

    fn info(ids: &[u64], matrix: Mat<f64>, rng: &mut ChaCha8Rng) -> MapInformation {
        let n = matrix.nrows();
        MapInformation {
            ids: ids.to_vec(),
            origin: Vector3::zeros(),
            matrix,
            vector: Col::from_fn(n, |_| rng.random_range(-5.0..5.0)),
        }
    }

    /// `weakest_new_feature` against hand-built marginals (σ bound 100 m: floor 1e-4 m⁻²):
    /// three features at 1 m⁻² (σ 1 m) pass; a new feature known to 1 km along one axis
    /// (1e-6 m⁻²) is named, but not when the peer has its own information on it (not new: a
    /// weak update of a held feature harms nothing) nor when 1 m⁻² was sent on it before; a
    /// new block with a negative eigenvalue (the −2.5e-3 m⁻² of the radio tree-8 runs) is named
    /// before a merely weak one, unless what was sent before makes the sum positive; two new
    /// features whose own blocks pass but whose joint block is indefinite (correlation 1.5
    /// between their x axes: eigenvalues 1 ± 1.5) are caught by the joint Cholesky at the
    /// second one's pivot.
    #[test]
    fn a_feature_new_to_the_peer_must_arrive_positive_definite_and_known_to_100_m() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let diag =
            |d: &[f64]| Mat::from_fn(d.len(), d.len(), |i, j| if i == j { d[i] } else { 0.0 });
        let all = |_: &FeatureId| true;
        let nothing = |ids: &[FeatureId]| Mat::zeros(3 * ids.len(), 3 * ids.len());
        let unit = |ids: &[FeatureId]| Mat::identity(3 * ids.len(), 3 * ids.len());
        let good = info(&[1, 2, 3], diag(&[1.0; 9]), &mut rng);
        assert_eq!(weakest_new_feature(&good, all, nothing, 100.0), None);
        let mut d = [1.0; 9];
        d[4] = 1e-6;
        let vague = info(&[1, 2, 3], diag(&d), &mut rng);
        assert_eq!(weakest_new_feature(&vague, all, nothing, 100.0), Some(2));
        assert_eq!(
            weakest_new_feature(&vague, |id: &FeatureId| *id != 2, nothing, 100.0),
            None
        );
        assert_eq!(weakest_new_feature(&vague, all, unit, 100.0), None);
        // σ = 1 km passes a 2 km bound.
        assert_eq!(weakest_new_feature(&vague, all, nothing, 2000.0), None);
        d[8] = -2.5e-3;
        let indefinite = info(&[1, 2, 3], diag(&d), &mut rng);
        assert_eq!(
            weakest_new_feature(&indefinite, all, nothing, 100.0),
            Some(3)
        );
        assert_eq!(weakest_new_feature(&indefinite, all, unit, 100.0), None);
        let mut m = diag(&[1.0; 6]);
        m[(0, 3)] = 1.5;
        m[(3, 0)] = 1.5;
        let joint = info(&[7, 8], m, &mut rng);
        assert_eq!(weakest_new_feature(&joint, all, nothing, 100.0), Some(8));
        assert_eq!(
            weakest_new_feature(&joint, |id: &FeatureId| *id == 8, nothing, 100.0),
            None
        );
    }

    /// The Schur marginal equals an independent computation: the inverse of the S block of the
    /// covariance D⁻¹ (marginal covariance of the features kept) and its mean mapped back
    /// (d'_S = (P_SS)⁻¹ (P d)_S). Tolerance 1e-6 relative: the regularisation floor perturbs
    /// D_RR by 1e-9 of its largest diagonal entry, amplified by the condition of D_RR (≲ 1e2
    /// for these I + GGᵀ matrices) and of the result; round-off of two inverses is far below.
    #[test]
    fn schur_marginal_matches_inverse_of_marginal_covariance() {
        let mut rng = ChaCha8Rng::seed_from_u64(13);
        for trial in 0..20 {
            let nf = 6;
            let d =
                &random_psd(3 * nf, 3 * nf + 4, &mut rng) + &Mat::<f64>::identity(3 * nf, 3 * nf);
            let delta = info(&[10, 11, 12, 13, 14, 15], d, &mut rng);
            let keep = [13, 10];
            let got = schur_marginal(&delta, &keep).expect("PD");
            assert!(!got.escalated);
            assert_eq!(got.held_back, 4);
            assert_eq!(got.info.ids, keep.to_vec());
            let llt = delta.matrix.as_ref().llt(Side::Lower).expect("PD");
            let p = llt.inverse();
            let mean = llt.solve(delta.vector.as_ref());
            let rows: Vec<usize> = [13usize - 10, 0]
                .iter()
                .flat_map(|&k| (0..3).map(move |a| 3 * k + a))
                .collect();
            let p_ss = Mat::from_fn(6, 6, |i, j| p[(rows[i], rows[j])]);
            let llt_s = p_ss.as_ref().llt(Side::Lower).expect("PD");
            let want = llt_s.inverse();
            let mean_s = Col::from_fn(6, |i| mean[rows[i]]);
            let want_vec = &want * &mean_s;
            let scale = (0..6).map(|i| want[(i, i)].abs()).fold(0.0, f64::max);
            for i in 0..6 {
                for j in 0..6 {
                    let e = (got.info.matrix[(i, j)] - want[(i, j)]).abs();
                    assert!(e <= 1e-6 * scale, "trial {trial} ({i},{j}): {e}");
                }
                let e = (got.info.vector[i] - want_vec[i]).abs();
                assert!(
                    e <= 1e-6 * (1.0 + want_vec[i].abs()) * scale.max(1.0),
                    "trial {trial} y[{i}]: {e}"
                );
            }
        }
    }

    /// pad(D') ⪯ D for PSD D of low rank (singular D_RR handled by the floor; the excess is
    /// bounded by δ); a D whose S block is clearly indefinite gives a negative marginal, which
    /// is refused.
    #[test]
    fn marginal_never_exceeds_the_delta() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut refused = 0;
        for trial in 0..30 {
            let nf = 5;
            let n = 3 * nf;
            let indefinite = trial % 2 == 1;
            let mut d = random_psd(n, if indefinite { n + 2 } else { 8 }, &mut rng);
            if indefinite {
                // Indefinite only inside the S block (features 0 and 1).
                for i in 0..6 {
                    d[(i, i)] -= 3.0;
                }
            }
            let delta = info(&[1, 2, 3, 4, 5], d, &mut rng);
            let keep = [1, 2];
            let got = match schur_marginal(&delta, &keep) {
                Ok(got) => got,
                // An S block made indefinite by −3 on its diagonal may give a clearly negative
                // marginal: refused by design (MAX_NEGATIVE_REL), never for PSD D.
                Err(SparsifyError::TooNegative { .. }) if indefinite => {
                    refused += 1;
                    continue;
                }
                Err(e) => panic!("trial {trial} refused: {e}"),
            };
            let excess = got.info.psd_excess_over(&delta).expect("eig");
            // Exact Schur: round-off only (1e-9 of the largest entry); regularised: ≤ δ (plus the
            // same round-off).
            let scale = delta.matrix_norm_max();
            assert!(
                excess <= got.shift.delta + 1e-9 * scale,
                "trial {trial}: excess {excess}, δ {}",
                got.shift.delta
            );
            if indefinite {
                // D_RR is positive definite here: the floor suffices.
                assert!(!got.escalated, "trial {trial}");
            }
        }
        // −3 on the S diagonal of these matrices (eigenvalues ~0.1–30) makes every marginal
        // clearly negative: all refused, none sent.
        assert_eq!(refused, 15, "indefinite trials refused");
    }

    /// Round after round of sparsifying the same low-rank residual (singular D_RR: the floor
    /// is in use every round): booked with its shift (D' − pad_R(δ I), the channel's booking)
    /// the residual stays positive semi-definite and no round is refused; booked as D' alone
    /// the regularisation leaves a residual negative at the floor's size, which the next
    /// rounds marginalise near-singularly or refuse — what stalled the radio links
    /// (docs/arch/ddf.md, "Booking").
    #[test]
    fn booking_the_shift_keeps_the_residual_positive_semi_definite() {
        let ids = [1u64, 2, 3, 4, 5];
        let n = 3 * ids.len();
        let run = |book_shift: bool| -> (usize, f64) {
            let mut rng = ChaCha8Rng::seed_from_u64(21);
            let mut residual = info(&ids, random_psd(n, 6, &mut rng), &mut rng);
            let (mut refused, mut worst) = (0, f64::INFINITY);
            for round in 0..40 {
                let keep = [ids[round % 5], ids[(round + 2) % 5]];
                let m = match schur_marginal(&residual, &keep) {
                    Ok(m) => m,
                    Err(_) => {
                        refused += 1;
                        continue;
                    }
                };
                residual = residual.sub(&m.info).expect("same origin, kept ids");
                if book_shift {
                    for (id, x) in &m.shift.features {
                        let k = ids.iter().position(|i| i == id).expect("held-back id");
                        for a in 0..3 {
                            residual.matrix[(3 * k + a, 3 * k + a)] += m.shift.delta;
                            residual.vector[3 * k + a] += m.shift.delta * x[a];
                        }
                    }
                }
                let low = residual
                    .matrix
                    .as_ref()
                    .self_adjoint_eigenvalues(Side::Lower)
                    .expect("eig")[0];
                // Against the residual's own size: the floor δ is relative to it.
                worst = worst.min(low / residual.matrix_norm_max());
            }
            (refused, worst)
        };
        let (refused, worst) = run(true);
        // Round-off only: 1e-12 of the residual's largest entry (sums of 40 Schur complements
        // of condition ≲ 1e9 at the floor, each exact to ~1e-16 · condition on the S block).
        assert_eq!(refused, 0, "booked with the shift: nothing refused");
        assert!(worst >= -1e-12, "booked with the shift: λ_min {worst:.2e}");
        let (refused, worst) = run(false);
        // Booked as D' alone, the residual is indefinite at the floor's own size (measured:
        // λ_min −9.0e-10 of max|residual|, floor 1e-9): the next round's D_RR + δI is then
        // near-singular (condition ~1e10, garbage marginals) or, once a larger negative
        // direction meets a smaller D_RR, not positive definite (refused).
        assert!(
            refused > 0 || worst < -0.5 * REGULARISATION_FLOOR_REL,
            "without the shift: refused {refused}, λ_min {worst:.2e}"
        );
    }

    /// The marginal's vector of linear-Gaussian data passes its gate: a sender with prior
    /// (Y₀, Y₀ x₀) fuses d = D x + w (cov w = D) and marginalises about its posterior
    /// x̄ = (Y₀ + D)⁻¹ (Y₀ x₀ + d); e = d'_S − D' x̄_S is then consistent with D'
    /// (cov e = D' − D' P_SS D') and the gated marginal equals the ungated one. D is of low
    /// rank (held-back block singular up to the floor, D' singular too). 200 draws at a gate
    /// of probability 1 − 1e-6: none is expected to fail (the seed makes it deterministic).
    #[test]
    fn consistent_marginal_vector_passes_its_gate() {
        let mut rng = ChaCha8Rng::seed_from_u64(21);
        let normal = |rng: &mut ChaCha8Rng| -> f64 { rng.sample(rand_distr::StandardNormal) };
        let nf = 6;
        let n = 3 * nf;
        for trial in 0..200 {
            // D = G Gᵀ of rank 9 < 18: w = G ε has covariance D.
            let g = Mat::from_fn(n, 9, |_, _| rng.random_range(-1.0..1.0));
            let d = &g * g.transpose();
            let x = Col::from_fn(n, |_| rng.random_range(-500.0..500.0));
            let eps = Col::from_fn(9, |_| normal(&mut rng));
            let vector = &d * &x + &g * &eps;
            // Prior N(x₀, Y₀⁻¹), Y₀ = 4 I: x₀ = x + N(0, I/4).
            let y0 = Mat::<f64>::identity(n, n) * 4.0;
            let x0 = Col::from_fn(n, |i| x[i] + 0.5 * normal(&mut rng));
            let post = (&y0 + &d).llt(Side::Lower).expect("PD");
            let xbar = post.solve(&(&y0 * &x0 + &vector));
            let ids: Vec<u64> = (1..=nf as u64).collect();
            let about: HashMap<FeatureId, Vector3<f64>> = ids
                .iter()
                .enumerate()
                .map(|(k, &id)| (id, Vector3::from_fn(|a, _| xbar[3 * k + a])))
                .collect();
            let delta = MapInformation {
                ids,
                origin: Vector3::zeros(),
                matrix: d,
                vector,
            };
            let keep = [2, 5];
            let got = schur_marginal_about(&delta, &keep, &about, 0.0).expect("marginal");
            let plain = marginal(&delta, &keep, &about, false, 0.0).expect("marginal");
            assert!(!got.vector_dropped, "trial {trial}: χ² {}", got.vector_chi2);
            assert_eq!(got.info.vector, plain.info.vector, "trial {trial}");
        }
    }

    /// A held-back vector that contradicts D_RR along a near-null direction of it is amplified
    /// by the Schur complement into a marginal vector D' does not support; the gate catches it
    /// and removes the component, leaving a vector about x̄ within the bound of consistent
    /// data, |D_SR (D_RR + δI)⁻¹ d̃_R| ≤ λ_max(D_SS)^½ · 5 √n_R for whitened components
    /// within 5σ (for PSD D, D_SR (D_RR + δI)⁻¹ D_RS ⪯ D_SS). D = G Gᵀ with one column
    /// (s e, t v) tying an S state strongly (s = 1) to the common x-translation v of the
    /// held-back features weakly (t = 1e-4: D_RR v = t² v = 1e-8 v, the other R columns
    /// orthogonal to v), so
    /// D_SR v / (λ_v + δ) ≈ 7e3 (δ = 1e-9 of max diag D_RR ≈ 5e-9); d̃_R = 2 v, a whitened
    /// component of ~1.6e4. Ungated, the marginal's vector is ~1.2e4 and exceeds the bound
    /// (~42) by ~290×, so the test can fail.
    #[test]
    fn marginal_vector_contradicting_its_information_is_not_sent() {
        let mut rng = ChaCha8Rng::seed_from_u64(22);
        let (ns, nr) = (6, 12);
        let n = ns + nr;
        let (s_tie, t_tie) = (1.0, 1e-4);
        // v: the common x-translation of the four held-back features (rows 0..12), unit norm.
        let v = Col::from_fn(nr, |i| if i % 3 == 0 { 0.5 } else { 0.0 });
        let mut g = Mat::<f64>::zeros(n, 1 + 15 + 8);
        g[(nr, 0)] = s_tie;
        for i in 0..nr {
            g[(i, 0)] = t_tie * v[i];
        }
        // R columns with v projected out; S columns.
        for c in 1..16 {
            let r = Col::from_fn(nr, |_| rng.random_range(-1.0..1.0));
            let along = v.transpose() * &r;
            for i in 0..nr {
                g[(i, c)] = r[i] - along * v[i];
            }
        }
        for c in 16..24 {
            for i in nr..n {
                g[(i, c)] = rng.random_range(-1.0..1.0);
            }
        }
        let d = &g * g.transpose();
        let vector = Col::from_fn(n, |i| if i < nr { 2.0 * v[i] } else { 0.0 });
        let ids: Vec<u64> = (1..=6).collect();
        let about: HashMap<FeatureId, Vector3<f64>> =
            ids.iter().map(|&id| (id, Vector3::zeros())).collect();
        let delta = MapInformation {
            ids,
            origin: Vector3::zeros(),
            matrix: d.clone(),
            vector,
        };
        let keep = [5, 6];
        let got = schur_marginal_about(&delta, &keep, &about, 0.0).expect("marginal");
        let plain = marginal(&delta, &keep, &about, false, 0.0).expect("marginal");
        assert!(got.vector_dropped, "χ² {}", got.vector_chi2);
        assert!(!plain.vector_dropped);
        // d̃_S = 0 and x̄ = 0 here, so d'_S is minus the term.
        let d_ss = Mat::from_fn(ns, ns, |i, j| d[(nr + i, nr + j)]);
        let lmax = d_ss
            .as_ref()
            .self_adjoint_eigenvalues(Side::Lower)
            .expect("eig")
            .last()
            .copied()
            .expect("non-empty");
        let bound = lmax.sqrt() * 5.0 * (nr as f64).sqrt();
        let (gated, ungated) = (got.info.vector.norm_l2(), plain.info.vector.norm_l2());
        assert!(
            gated <= bound,
            "gated vector {gated} above the bound {bound}"
        );
        assert!(
            ungated > 100.0 * bound,
            "ungated vector {ungated} (bound {bound}): the test would not see the amplification"
        );
    }

    /// Keeping every feature returns the delta itself; all-zero features are not held back.
    #[test]
    fn keeping_everything_is_exact() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut d = random_psd(9, 9, &mut rng);
        for i in 6..9 {
            for j in 0..9 {
                d[(i, j)] = 0.0;
                d[(j, i)] = 0.0;
            }
        }
        let mut delta = info(&[4, 5, 6], d, &mut rng);
        for r in 6..9 {
            delta.vector[r] = 0.0;
        }
        let got = schur_marginal(&delta, &[4, 5]).expect("PD");
        assert_eq!(got.held_back, 0);
        assert_eq!(got.shift.delta, 0.0);
        assert!(!got.escalated);
        let want = delta.restrict(&[4, 5]);
        assert_eq!(got.info.relative_difference(&want).expect("same ids"), 0.0);
    }

    /// A strongly indefinite R block is refused, not sent.
    #[test]
    fn indefinite_residual_block_is_refused() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let mut d = random_psd(6, 6, &mut rng);
        for i in 3..6 {
            d[(i, i)] -= 50.0;
        }
        let delta = info(&[1, 2], d, &mut rng);
        assert!(matches!(
            schur_marginal(&delta, &[1]),
            Err(SparsifyError::Indefinite { .. })
        ));
    }

    /// A residual block that is only the round-off of the information it was formed from
    /// (D_RR of 1e-8 with λ_min −1e-8, what Y_i − C_ik leaves on features with nothing pending
    /// when Y_i's entries are ~150) is regularised at the operands' scale and the marginal is
    /// the S block, to the coupling's size; with the cap relative to D_RR alone (operand scale
    /// 0) the round is refused, as in the tree-8 radio runs before `OPERAND_REGULARISATION_REL`;
    /// negativity beyond that cap is refused at the operands' scale too.
    #[test]
    fn round_off_residual_is_regularised_at_the_operands_scale() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let a = random_psd(3, 3, &mut rng);
        let coupling = 1e-9;
        // D_RR: eigenvalues from −1e-8 to 1e-8 along a random orthonormal basis (round-off,
        // indefinite).
        let q = Mat::from_fn(6, 6, |_, _| rng.random_range(-1.0..1.0))
            .qr()
            .compute_Q();
        let eig = [-1e-8, 5e-9, 1e-8, 2e-9, -3e-9, 8e-9];
        let e = Mat::from_fn(6, 6, |i, j| {
            (0..6).map(|k| q[(i, k)] * eig[k] * q[(j, k)]).sum::<f64>()
        });
        let mut d = Mat::zeros(9, 9);
        for i in 0..9 {
            for j in 0..9 {
                d[(i, j)] = match (i < 3, j < 3) {
                    (true, true) => a[(i, j)],
                    (false, false) => e[(i - 3, j - 3)],
                    _ => coupling,
                };
            }
        }
        let delta = info(&[1, 2, 3], d, &mut rng);
        let about = HashMap::new();
        assert!(matches!(
            schur_marginal_about(&delta, &[1], &about, 0.0),
            Err(SparsifyError::Indefinite { .. })
        ));
        let scale = 150.0;
        let got = schur_marginal_about(&delta, &[1], &about, scale).expect("regularised");
        let delta_used = got.shift.delta;
        // Within the cap (one margin step above it at most: `MAX_REGULARISATION_REL` docs).
        assert!(
            delta_used > 1e-8 && delta_used <= 10.0 * OPERAND_REGULARISATION_REL * scale,
            "δ {delta_used:e}"
        );
        // D' = A − D_SR (D_RR + δI)⁻¹ D_RS: |D_SR|² ‖(D_RR + δI)⁻¹‖ ≤ (6 · 1e-9)² / (0.9 δ) per
        // entry (λ_min(D_RR + δI) ≥ 0.9 δ after the margin step).
        let bound = (6.0 * coupling).powi(2) / (0.9 * delta_used);
        for i in 0..3 {
            for j in 0..3 {
                let err = (got.info.matrix[(i, j)] - a[(i, j)]).abs();
                assert!(err <= bound, "({i}, {j}): {err:e} > {bound:e}");
            }
        }
        // Negativity beyond the cap (1e-6 · 150 = 1.5e-4 against λ_min −1e-3) is refused
        // at the operands' scale too.
        let mut deep = delta.clone();
        for i in 3..9 {
            for j in 3..9 {
                deep.matrix[(i, j)] = e[(i - 3, j - 3)] * 1e5;
            }
        }
        assert!(matches!(
            schur_marginal_about(&deep, &[1], &about, scale),
            Err(SparsifyError::Indefinite { .. })
        ));
    }

    /// Selection: the feature count is the largest whose dense delta fits; the order is by gain
    /// (a feature with a tenfold diagonal first), ties by id; the budget bound is tight.
    #[test]
    fn selection_by_gain_within_budget() {
        for n in [1usize, 2, 5, 26, 100] {
            let b = MapInformation::dense_block_wire_bytes(n);
            assert_eq!(max_features(b, false), n);
            assert_eq!(max_features(b - 1, false), n - 1);
            let b = MapInformation::dense_block_wire_bytes_as(n, true);
            assert_eq!(max_features(b, true), n);
            assert_eq!(max_features(b - 1, true), n - 1);
        }
        let ids = [7u64, 3, 9, 5];
        let n = 12;
        let mut d = Mat::<f64>::identity(n, n);
        for a in 0..3 {
            d[(6 + a, 6 + a)] = 10.0; // feature 9
        }
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let delta = info(&ids, d, &mut rng);
        let none = HashMap::new();
        let budget = MapInformation::dense_block_wire_bytes(3);
        let got = select(&delta, &none, budget, false);
        assert_eq!(got, vec![9, 3, 5]);
        // The sender's covariance scales the gain: feature 7 with P = 100 I comes first.
        let mut cov = HashMap::new();
        cov.insert(7, Matrix3::identity() * 100.0);
        let got = select(&delta, &cov, budget, false);
        assert_eq!(got, vec![7, 9, 3]);
        // Bytes of the selected marginal stay within the budget.
        let m = schur_marginal(&delta, &got).expect("PD");
        assert!(m.info.block_sparse_wire_bytes() <= budget);
    }
}
