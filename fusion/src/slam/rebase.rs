//! Re-expressing a local-SLAM filter in another frame (module [`crate::frames`]).
//!
//! A vehicle that starts in its own frame and has aligned its map with a neighbour's in the
//! team frame, x_team = Rz(ψ) x_own + t, moves its whole estimate there: positions (vehicle,
//! features, stored poses) p ↦ Rz p + t, velocities v ↦ Rz v, yaws (vehicle and stored poses)
//! ψ_b ↦ ψ_b + ψ (roll and pitch are relative to gravity and do not change), biases unchanged
//! (body axes). With J the Jacobian of that map (Rz on position and velocity blocks, identity
//! elsewhere; the Euler-angle errors are unchanged because Rz(ψ) premultiplies C_b^n), the
//! covariance becomes
//!
//! ```text
//! P' = J P Jᵀ + G Σ_g Gᵀ,        G = ∂x'/∂(t, ψ) = [I | e_z × Rz p] on positions, [0 | e_z × Rz v]
//!                                      on velocities, [0 | 1] on yaws,
//! ```
//!
//! where Σ_g is a *gauge prior*: the vehicle knew its own start exactly, which in the team frame
//! it knows only through the alignment — and the alignment was computed from the neighbour's
//! features, whose information the neighbour will send it again. Σ_g is therefore chosen far
//! wider than the alignment's covariance (a prior of negligible information, below), so the
//! vehicle's map carries almost no information about where the team frame is: that comes from
//! its neighbours' information once it arrives, counted once. The linearisation point is the
//! aligned estimate (accurate to the alignment's σ), so the wide prior costs no linearisation
//! error. How little it claims: with the defaults below (σ_t = 100 m, σ_ψ = 30°) and an
//! accepted alignment (σ_t ≤ 1 m, σ_ψ ≤ 1°), the gauge information the vehicle keeps is at most
//! 1/10⁴ (translation) and 1/900 (yaw) of what the alignment measured.

use super::{SlamError, SlamFilter, SlotKind};
use crate::frames::Frame4;
use crate::rotation::wrap_angle;
use crate::state::{ATT, NavFrame, POS, POSE_ATT, POSE_POS, VEL};
use faer::Mat;
use nalgebra::{Matrix3, Matrix4, Vector3};

/// Default gauge prior σ of the translation [m] ([`SlamFilter::rebase`]).
pub const GAUGE_SIGMA_TRANSLATION_M: f64 = 100.0;
/// Default gauge prior σ of the yaw [rad].
pub const GAUGE_SIGMA_YAW_RAD: f64 = std::f64::consts::PI / 6.0;

/// Σ_g of the defaults: diag(σ_t², σ_t², σ_t², σ_ψ²).
pub fn default_gauge() -> Matrix4<f64> {
    let t = GAUGE_SIGMA_TRANSLATION_M * GAUGE_SIGMA_TRANSLATION_M;
    Matrix4::from_diagonal(&nalgebra::Vector4::new(
        t,
        t,
        t,
        GAUGE_SIGMA_YAW_RAD * GAUGE_SIGMA_YAW_RAD,
    ))
}

/// What a state index carries under a frame change.
#[derive(Clone, Copy)]
enum Part {
    /// First index of a position block.
    Position(usize),
    /// First index of a velocity block.
    Velocity(usize),
    /// A yaw.
    Yaw(usize),
}

impl SlamFilter {
    fn frame_parts(&self) -> Vec<Part> {
        let mut parts = Vec::new();
        for slot in self.layout.slots() {
            let o = slot.offset;
            match slot.kind {
                SlotKind::Vehicle(_) => {
                    parts.push(Part::Position(o + POS));
                    parts.push(Part::Velocity(o + VEL));
                    parts.push(Part::Yaw(o + ATT + 2));
                }
                SlotKind::Feature(_) => parts.push(Part::Position(o)),
                SlotKind::Pose(_) => {
                    parts.push(Part::Position(o + POSE_POS));
                    parts.push(Part::Yaw(o + POSE_ATT + 2));
                }
            }
        }
        parts
    }

    /// Moves the whole estimate into the frame `to` maps it to (module docs): x' = f(x),
    /// P' = J P Jᵀ + G Σ_g Gᵀ with `gauge` = Σ_g (4 × 4, translation first). Local SLAM only;
    /// bearing-only range hypotheses of pending tracks move with it.
    pub fn rebase(&mut self, to: &Frame4, gauge: &Matrix4<f64>) -> Result<(), SlamError> {
        if self.config.frame != NavFrame::Local {
            return Err(SlamError::InvalidConfig(
                "only a local-SLAM filter can change its frame".into(),
            ));
        }
        let finite = to.yaw.is_finite()
            && to.translation.iter().all(|v| v.is_finite())
            && gauge.iter().all(|v| v.is_finite());
        if !finite || gauge.cholesky().is_none() {
            return Err(SlamError::InvalidConfig(
                "frame change or gauge prior not finite / not positive definite".into(),
            ));
        }
        self.flush();
        let r = to.rotation();
        let n = self.x.nrows();
        let parts = self.frame_parts();
        // x' and G at x'.
        let mut g = Mat::<f64>::zeros(n, 4);
        for &part in &parts {
            match part {
                Part::Position(i) => {
                    let p = to.apply(&self.vec3_at(i));
                    for k in 0..3 {
                        self.x[i + k] = p[k];
                        g[(i + k, k)] = 1.0;
                    }
                    g[(i, 3)] = -(p.y - to.translation.y);
                    g[(i + 1, 3)] = p.x - to.translation.x;
                }
                Part::Velocity(i) => {
                    let v = r * self.vec3_at(i);
                    for k in 0..3 {
                        self.x[i + k] = v[k];
                    }
                    g[(i, 3)] = -v.y;
                    g[(i + 1, 3)] = v.x;
                }
                Part::Yaw(i) => {
                    self.x[i] = wrap_angle(self.x[i] + to.yaw);
                    g[(i, 3)] = 1.0;
                }
            }
        }
        // J P Jᵀ: rotate the rows, then the columns, of every position and velocity block.
        let blocks: Vec<usize> = parts
            .iter()
            .filter_map(|p| match p {
                Part::Position(i) | Part::Velocity(i) => Some(*i),
                Part::Yaw(_) => None,
            })
            .collect();
        for &i in &blocks {
            for c in 0..n {
                let v = r * Vector3::new(self.p[(i, c)], self.p[(i + 1, c)], self.p[(i + 2, c)]);
                for k in 0..3 {
                    self.p[(i + k, c)] = v[k];
                }
            }
        }
        for &i in &blocks {
            for row in 0..n {
                let v =
                    r * Vector3::new(self.p[(row, i)], self.p[(row, i + 1)], self.p[(row, i + 2)]);
                for k in 0..3 {
                    self.p[(row, i + k)] = v[k];
                }
            }
        }
        // + G Σ_g Gᵀ.
        let sg = Mat::<f64>::from_fn(4, 4, |a, b| gauge[(a, b)]);
        let gs = &g * &sg;
        self.p += &gs * g.transpose();
        crate::info::symmetrize(&mut self.p);
        self.bearing.rebase(&r, to);
        self.bump_map_generation(false);
        Ok(())
    }
}

impl super::bearing::BearingState {
    /// Range hypotheses of pending tracks (kept outside the state, in the filter frame) move
    /// with a frame change.
    pub(super) fn rebase(&mut self, r: &Matrix3<f64>, to: &Frame4) {
        self.transform_hypotheses(|m, c| (to.apply(m), r * c * r.transpose()));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::slam::AssociationMode;
    use crate::slam::tests::{config, delta, vehicle};
    use nalgebra::{DMatrix, DVector};

    /// The rebase against an independent dense computation: x' = f(x) with f the frame change
    /// applied block by block, P' = J P Jᵀ + G Σ_g Gᵀ with J and G from central differences of
    /// f (step 1e-6: f is affine in x and in (t, ψ) up to the rotation, whose O(h²) error is
    /// ~1e-10 against entries of order 10³).
    #[test]
    fn rebase_matches_a_dense_reference() {
        let mut f = SlamFilter::new(
            config(NavFrame::Local, AssociationMode::Descriptor),
            &[vehicle(Vector3::new(5.0, -3.0, -100.0))],
        )
        .unwrap();
        // Two correlated features.
        let y = DMatrix::from_row_slice(
            6,
            6,
            &[
                2.0, 0.1, 0.0, 0.5, 0.0, 0.0, //
                0.1, 2.0, 0.0, 0.0, 0.5, 0.0, //
                0.0, 0.0, 1.0, 0.0, 0.0, 0.2, //
                0.5, 0.0, 0.0, 1.5, 0.0, 0.0, //
                0.0, 0.5, 0.0, 0.0, 1.5, 0.0, //
                0.0, 0.0, 0.2, 0.0, 0.0, 1.0,
            ],
        );
        let target = DVector::from_vec(vec![40.0, 10.0, 5.0, -60.0, 80.0, 3.0]);
        f.fuse_map_information(&delta(vec![3, 4], y, &target, f.origin()))
            .unwrap();
        f.flush();
        let x0 = f.state_vector();
        let p0 = f.joint_covariance();
        let n = x0.nrows();
        let to = Frame4 {
            yaw: 0.6,
            translation: Vector3::new(-120.0, 55.0, 2.0),
        };
        let gauge = Matrix4::from_diagonal(&nalgebra::Vector4::new(4.0, 9.0, 1.0, 0.01));
        // f(x; t, ψ) applied by hand to the vehicle (p, v, yaw) and the two features.
        let apply = |x: &DVector<f64>, fr: &Frame4| -> DVector<f64> {
            let mut y = x.clone();
            let rot = fr.rotation();
            let pos = |i: usize, y: &mut DVector<f64>| {
                let p = fr.apply(&Vector3::new(x[i], x[i + 1], x[i + 2]));
                y.rows_mut(i, 3).copy_from(&p);
            };
            pos(POS, &mut y);
            pos(15, &mut y);
            pos(18, &mut y);
            let v = rot * Vector3::new(x[VEL], x[VEL + 1], x[VEL + 2]);
            y.rows_mut(VEL, 3).copy_from(&v);
            y[ATT + 2] = x[ATT + 2] + fr.yaw;
            y
        };
        let xd = DVector::from_fn(n, |i, _| x0[i]);
        let pd = DMatrix::from_fn(n, n, |i, j| p0[(i, j)]);
        let h = 1e-6;
        let jx = DMatrix::from_fn(n, n, |i, j| {
            let (mut a, mut b) = (xd.clone(), xd.clone());
            a[j] += h;
            b[j] -= h;
            (apply(&a, &to)[i] - apply(&b, &to)[i]) / (2.0 * h)
        });
        let jg = DMatrix::from_fn(n, 4, |i, k| {
            let (mut a, mut b) = (to, to);
            if k < 3 {
                a.translation[k] += h;
                b.translation[k] -= h;
            } else {
                a.yaw += h;
                b.yaw -= h;
            }
            (apply(&xd, &a)[i] - apply(&xd, &b)[i]) / (2.0 * h)
        });
        let sg = DMatrix::from_fn(4, 4, |a, b| gauge[(a, b)]);
        let want_p = &jx * &pd * jx.transpose() + &jg * sg * jg.transpose();
        let want_x = apply(&xd, &to);
        f.rebase(&to, &gauge).unwrap();
        let (x1, p1) = (f.state_vector(), f.joint_covariance());
        for i in 0..n {
            assert!((x1[i] - want_x[i]).abs() < 1e-9, "x[{i}]");
            for j in 0..n {
                assert!(
                    (p1[(i, j)] - want_p[(i, j)]).abs() < 1e-6 * (1.0 + want_p[(i, j)].abs()),
                    "P[{i},{j}] {} vs {}",
                    p1[(i, j)],
                    want_p[(i, j)]
                );
            }
        }
        // Global SLAM has no frame to change.
        let mut g = SlamFilter::new(
            config(NavFrame::Global, AssociationMode::Descriptor),
            &[vehicle(Vector3::new(-4.6e6, 2.5e6, -3.5e6))],
        )
        .unwrap();
        assert!(g.rebase(&to, &gauge).is_err());
    }
}
