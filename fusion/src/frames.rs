//! Relative frames of vehicles in local SLAM (chapter §21.5.1: aligning independently chosen
//! local frames from common features).
//!
//! In local SLAM every vehicle starts in its *own* frame: the local-level NED frame whose
//! origin is where it started and whose north is its initial heading. Gravity fixes roll and
//! pitch, so two such frames differ by four degrees of freedom: a translation t and a rotation
//! ψ about the down axis,
//!
//! ```text
//! x_team = Rz(ψ) · x_own + t,          Rz(ψ) = [[cos ψ, −sin ψ, 0], [sin ψ, cos ψ, 0], [0, 0, 1]].
//! ```
//!
//! [`align`] estimates (t, ψ) with its covariance from features both maps hold — found by
//! appearance, since the keys differ — robustly (two-point hypotheses scored by their
//! Mahalanobis inliers; a second, different hypothesis with comparable support is refused as
//! ambiguous) and then by weighted least squares over the inliers (Gauss–Newton; the
//! covariance is the inverse of the information Σ Jᵀ S⁻¹ J). A vehicle whose alignment to a
//! neighbour already in the team frame has converged re-expresses its whole filter in the team
//! frame ([`crate::slam::SlamFilter::rebase`]).

use crate::consistency::chi2_quantile;
use crate::rotation::wrap_angle;
use nalgebra::{Matrix3, Matrix3x4, Matrix4, Vector3, Vector4};

/// A 4-DOF transform between two gravity-aligned NED frames: x_to = Rz(yaw)·x_from + translation.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Frame4 {
    /// Rotation about the down axis [rad].
    pub yaw: f64,
    /// Translation [m].
    pub translation: Vector3<f64>,
}

impl Frame4 {
    /// The identity.
    pub fn identity() -> Self {
        Self {
            yaw: 0.0,
            translation: Vector3::zeros(),
        }
    }

    /// Rz(yaw).
    pub fn rotation(&self) -> Matrix3<f64> {
        let (s, c) = self.yaw.sin_cos();
        Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
    }

    /// Rz(yaw)·p + t.
    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.rotation() * p + self.translation
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let r = self.rotation();
        Self {
            yaw: wrap_angle(-self.yaw),
            translation: -(r.transpose() * self.translation),
        }
    }

    /// `self` after `first`: x ↦ self(first(x)).
    pub fn compose(&self, first: &Frame4) -> Self {
        Self {
            yaw: wrap_angle(self.yaw + first.yaw),
            translation: self.rotation() * first.translation + self.translation,
        }
    }

    /// ∂(Rz(yaw)·p + t)/∂(t, yaw) at `p` (3 × 4): [I | e_z × Rz(yaw)·p].
    pub fn jacobian(&self, p: &Vector3<f64>) -> Matrix3x4<f64> {
        let q = self.rotation() * p;
        let mut j = Matrix3x4::zeros();
        j.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&Matrix3::identity());
        j[(0, 3)] = -q.y;
        j[(1, 3)] = q.x;
        j
    }
}

/// One candidate correspondence: a feature of the own map and one of the other (team-frame)
/// map that look alike, each with its marginal covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// Position in the own frame.
    pub own: Vector3<f64>,
    /// Its covariance.
    pub own_cov: Matrix3<f64>,
    /// Position in the other frame.
    pub other: Vector3<f64>,
    /// Its covariance.
    pub other_cov: Matrix3<f64>,
}

/// Options of [`align`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AlignConfig {
    /// Fewest inliers of an accepted alignment.
    pub min_inliers: usize,
    /// χ² probability of the inlier gate of a refined alignment (3 dof per candidate).
    pub inlier_probability: f64,
    /// χ² probability of the wider gate that scores a two-point hypothesis (whose own error is
    /// not in the residual covariance).
    pub hypothesis_probability: f64,
    /// Largest accepted σ of the yaw [rad].
    pub max_sigma_yaw: f64,
    /// Largest accepted σ of the horizontal translation [m].
    pub max_sigma_translation: f64,
    /// Shortest horizontal baseline of a two-point hypothesis [m] (shorter ones fix the yaw
    /// poorly).
    pub min_baseline: f64,
}

impl Default for AlignConfig {
    fn default() -> Self {
        Self {
            min_inliers: 6,
            inlier_probability: 0.99,
            hypothesis_probability: 0.9999,
            max_sigma_yaw: 1f64.to_radians(),
            max_sigma_translation: 1.0,
            min_baseline: 20.0,
        }
    }
}

/// A converged alignment.
#[derive(Clone, Debug, PartialEq)]
pub struct Alignment {
    /// x_other = frame(x_own).
    pub frame: Frame4,
    /// Covariance of (t, yaw) (4 × 4, t first).
    pub covariance: Matrix4<f64>,
    /// Indices of the candidates that are inliers.
    pub inliers: Vec<usize>,
    /// Σ of the inliers' squared Mahalanobis residuals.
    pub chi2: f64,
}

/// Why no alignment was accepted (the caller tries again with more features later).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AlignError {
    /// Fewer candidates than `min_inliers`.
    #[error("{0} candidate correspondences, too few")]
    TooFewCandidates(usize),
    /// The best hypothesis has fewer than `min_inliers` inliers.
    #[error("best hypothesis has {0} inliers, too few")]
    NoConsensus(usize),
    /// Two different hypotheses are both well supported (repeated structure).
    #[error("two different alignments are supported by {best} and {second} candidates")]
    Ambiguous {
        /// Support of the best.
        best: usize,
        /// Support of a different one.
        second: usize,
    },
    /// The alignment is not yet certain enough.
    #[error(
        "alignment not converged: sigma yaw {sigma_yaw_deg:.2} deg, translation {sigma_translation_m:.2} m"
    )]
    NotConverged {
        /// σ of the yaw [deg].
        sigma_yaw_deg: f64,
        /// σ of the horizontal translation [m].
        sigma_translation_m: f64,
    },
    /// The least squares were singular.
    #[error("alignment information is singular")]
    Singular,
}

/// Squared Mahalanobis residual of candidate `c` under `f` (∞ if its covariance is singular).
fn residual(f: &Frame4, c: &Candidate) -> (Vector3<f64>, Matrix3<f64>, f64) {
    let r = f.rotation();
    let res = c.other - f.apply(&c.own);
    let s = c.other_cov + r * c.own_cov * r.transpose();
    let d2 = s
        .cholesky()
        .map_or(f64::INFINITY, |ch| res.dot(&ch.solve(&res)));
    (res, s, d2)
}

fn inliers(f: &Frame4, cands: &[Candidate], gate: f64) -> Vec<usize> {
    (0..cands.len())
        .filter(|&k| residual(f, &cands[k]).2 <= gate)
        .collect()
}

/// The hypothesis of two candidates: the yaw from their horizontal baselines, the translation
/// from their centroids.
fn two_point(a: &Candidate, b: &Candidate, min_baseline: f64) -> Option<Frame4> {
    let u = b.own - a.own;
    let v = b.other - a.other;
    let (lu, lv) = (u.xy().norm(), v.xy().norm());
    if lu < min_baseline || lv < min_baseline {
        return None;
    }
    let yaw = wrap_angle(v.y.atan2(v.x) - u.y.atan2(u.x));
    let mut f = Frame4 {
        yaw,
        translation: Vector3::zeros(),
    };
    f.translation = 0.5 * (a.other + b.other) - f.rotation() * (0.5 * (a.own + b.own));
    Some(f)
}

/// Gauss–Newton over the inliers: θ = (t, yaw), r_k = other_k − (Rz(yaw) own_k + t),
/// J_k = ∂r_k/∂θ = −[I | e_z × Rz own_k], minimising Σ r_kᵀ S_k⁻¹ r_k. Returns the refined
/// frame and the inverse of the information Σ J_kᵀ S_k⁻¹ J_k.
fn refine(mut f: Frame4, cands: &[Candidate], idx: &[usize]) -> Option<(Frame4, Matrix4<f64>)> {
    let mut cov = Matrix4::zeros();
    for _ in 0..10 {
        let mut info = Matrix4::zeros();
        let mut g = Vector4::zeros();
        for &k in idx {
            let (res, s, _) = residual(&f, &cands[k]);
            let s_inv = s.try_inverse()?;
            let j = -f.jacobian(&cands[k].own);
            info += j.transpose() * s_inv * j;
            g += j.transpose() * s_inv * res;
        }
        let ch = info.cholesky()?;
        let step = -ch.solve(&g);
        f.translation += step.fixed_rows::<3>(0);
        f.yaw = wrap_angle(f.yaw + step[3]);
        cov = ch.inverse();
        if step.norm() < 1e-9 {
            break;
        }
    }
    Some((f, cov))
}

/// Estimates the frame that maps the own map onto the other from candidate correspondences
/// (module docs). Deterministic: hypotheses from every pair of candidates in order (at most
/// `MAX_HYPOTHESES`).
pub fn align(cands: &[Candidate], cfg: &AlignConfig) -> Result<Alignment, AlignError> {
    const MAX_HYPOTHESES: usize = 20_000;
    if cands.len() < cfg.min_inliers {
        return Err(AlignError::TooFewCandidates(cands.len()));
    }
    let wide = chi2_quantile(3.0, cfg.hypothesis_probability).map_err(|_| AlignError::Singular)?;
    let strict = chi2_quantile(3.0, cfg.inlier_probability).map_err(|_| AlignError::Singular)?;
    // Score every two-point hypothesis; keep the best and the best that is *different* from it
    // (its inliers overlap the best's by less than half).
    let mut scored: Vec<(usize, Frame4, Vec<usize>)> = Vec::new();
    let mut tried = 0usize;
    'outer: for a in 0..cands.len() {
        for b in a + 1..cands.len() {
            if tried >= MAX_HYPOTHESES {
                break 'outer;
            }
            let Some(f) = two_point(&cands[a], &cands[b], cfg.min_baseline) else {
                continue;
            };
            tried += 1;
            let inl = inliers(&f, cands, wide);
            scored.push((inl.len(), f, inl));
        }
    }
    scored.sort_by_key(|x| std::cmp::Reverse(x.0));
    let Some((best_n, best_f, best_inl)) = scored.first().cloned() else {
        return Err(AlignError::NoConsensus(0));
    };
    if best_n < cfg.min_inliers {
        return Err(AlignError::NoConsensus(best_n));
    }
    if let Some((second, _, _)) = scored.iter().find(|(_, _, inl)| {
        let common = inl.iter().filter(|k| best_inl.contains(k)).count();
        2 * common < inl.len()
    }) && 2 * second >= best_n
        && *second >= cfg.min_inliers
    {
        return Err(AlignError::Ambiguous {
            best: best_n,
            second: *second,
        });
    }
    // Refine, re-gate at the strict probability, refine again until the inlier set settles.
    let mut f = best_f;
    let mut idx = best_inl;
    let mut rounds = 0;
    loop {
        f = refine(f, cands, &idx).ok_or(AlignError::Singular)?.0;
        let next = inliers(&f, cands, strict);
        rounds += 1;
        if next == idx || rounds >= 5 {
            idx = next;
            break;
        }
        idx = next;
        if idx.len() < cfg.min_inliers {
            return Err(AlignError::NoConsensus(idx.len()));
        }
    }
    if idx.len() < cfg.min_inliers {
        return Err(AlignError::NoConsensus(idx.len()));
    }
    let (f, cov) = refine(f, cands, &idx).ok_or(AlignError::Singular)?;
    let sigma_yaw = cov[(3, 3)].max(0.0).sqrt();
    let sigma_t = (cov[(0, 0)] + cov[(1, 1)]).max(0.0).sqrt();
    if sigma_yaw > cfg.max_sigma_yaw || sigma_t > cfg.max_sigma_translation {
        return Err(AlignError::NotConverged {
            sigma_yaw_deg: sigma_yaw.to_degrees(),
            sigma_translation_m: sigma_t,
        });
    }
    let chi2 = idx.iter().map(|&k| residual(&f, &cands[k]).2).sum();
    Ok(Alignment {
        frame: f,
        covariance: cov,
        inliers: idx,
        chi2,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, StandardNormal};

    fn gauss(rng: &mut ChaCha8Rng, sigma: f64) -> Vector3<f64> {
        Vector3::from_fn(|_, _| {
            sigma * <StandardNormal as Distribution<f64>>::sample(&StandardNormal, rng)
        })
    }

    #[test]
    fn frame_algebra() {
        let f = Frame4 {
            yaw: 0.7,
            translation: Vector3::new(3.0, -2.0, 1.0),
        };
        let g = Frame4 {
            yaw: -2.9,
            translation: Vector3::new(-10.0, 4.0, 0.5),
        };
        let p = Vector3::new(12.0, -5.0, 3.0);
        assert!((f.inverse().apply(&f.apply(&p)) - p).norm() < 1e-12);
        assert!((g.compose(&f).apply(&p) - g.apply(&f.apply(&p))).norm() < 1e-12);
        // The Jacobian against central differences (step 1e-6; error O(h²) ≈ 1e-10).
        let j = f.jacobian(&p);
        let h = 1e-6;
        for k in 0..4 {
            let (mut fp, mut fm) = (f, f);
            if k < 3 {
                fp.translation[k] += h;
                fm.translation[k] -= h;
            } else {
                fp.yaw += h;
                fm.yaw -= h;
            }
            let d = (fp.apply(&p) - fm.apply(&p)) / (2.0 * h);
            assert!((d - j.column(k)).norm() < 1e-7, "column {k}");
        }
    }

    /// `n` features scattered over 400 m, seen by both maps with independent noise σ; a share
    /// `outliers` of the candidates pair unrelated features.
    fn scene(
        rng: &mut ChaCha8Rng,
        truth: &Frame4,
        n: usize,
        sigma: f64,
        outliers: f64,
    ) -> Vec<Candidate> {
        let cov = Matrix3::identity() * sigma * sigma;
        (0..n)
            .map(|_| {
                let own = Vector3::new(
                    rng.random_range(-200.0..200.0),
                    rng.random_range(-200.0..200.0),
                    rng.random_range(-20.0..5.0),
                );
                let other_true = if rng.random::<f64>() < outliers {
                    Vector3::new(
                        rng.random_range(-300.0..300.0),
                        rng.random_range(-300.0..300.0),
                        0.0,
                    )
                } else {
                    truth.apply(&own)
                };
                Candidate {
                    own: own + gauss(rng, sigma),
                    own_cov: cov,
                    other: other_true + gauss(rng, sigma),
                    other_cov: cov,
                }
            })
            .collect()
    }

    /// Monte Carlo: 300 scenes of 15 candidates (σ = 1 m, 30 % outliers) under a 40° / 80 m
    /// transform. Every alignment holds only true pairs' inliers (an outlier inlier would need
    /// a random point within ≈ 4σ of its image), and the NEES of (t, yaw) averages 4 (its χ²₄
    /// mean; 95 % band of a 300-sample mean [3.69, 4.33]) — the covariance is honest.
    #[test]
    fn alignment_is_consistent_and_rejects_outliers() {
        let truth = Frame4 {
            yaw: 40f64.to_radians(),
            translation: Vector3::new(80.0, -55.0, 3.0),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let mut nees = 0.0;
        let runs = 300;
        for _ in 0..runs {
            let cands = scene(&mut rng, &truth, 15, 1.0, 0.3);
            let a = align(&cands, &AlignConfig::default()).expect("aligns");
            for &k in &a.inliers {
                let r = (cands[k].other - truth.apply(&cands[k].own)).norm();
                assert!(r < 10.0, "an outlier was taken as inlier ({r:.1} m)");
            }
            let e = Vector4::new(
                a.frame.translation.x - truth.translation.x,
                a.frame.translation.y - truth.translation.y,
                a.frame.translation.z - truth.translation.z,
                wrap_angle(a.frame.yaw - truth.yaw),
            );
            nees += e.dot(&(a.covariance.try_inverse().unwrap() * e));
        }
        let mean = nees / runs as f64;
        assert!((3.69..=4.33).contains(&mean), "NEES {mean:.3}");
    }

    /// Too few candidates, no consensus among random pairs, and a repeated structure (the same
    /// features seen under two transforms) are refused.
    #[test]
    fn what_cannot_be_aligned_is_refused() {
        let truth = Frame4 {
            yaw: 1.0,
            translation: Vector3::new(10.0, 20.0, 0.0),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let few = scene(&mut rng, &truth, 4, 1.0, 0.0);
        assert_eq!(
            align(&few, &AlignConfig::default()),
            Err(AlignError::TooFewCandidates(4))
        );
        let random = scene(&mut rng, &truth, 20, 1.0, 1.0);
        assert!(matches!(
            align(&random, &AlignConfig::default()),
            Err(AlignError::NoConsensus(_))
        ));
        let other = Frame4 {
            yaw: -0.5,
            translation: Vector3::new(-150.0, 60.0, 0.0),
        };
        let mut twin = scene(&mut rng, &truth, 10, 0.5, 0.0);
        twin.extend(scene(&mut rng, &other, 10, 0.5, 0.0));
        assert!(matches!(
            align(&twin, &AlignConfig::default()),
            Err(AlignError::Ambiguous { .. })
        ));
    }
}
