//! Attitude conventions, stated once and kept everywhere.
//!
//! * Frames: `e` = ECEF, `n` = local-level North-East-Down, `b` = body (x forward, y right,
//!   z down), `s` = terrain sensor (x along the boresight, y right, z down in the image).
//! * Attitude is the Euler triple Ψ = (φ, θ, ψ) = (roll, pitch, yaw) of the aerospace z-y-x
//!   sequence: `nav_from_body(Ψ) = C_b^n = Rz(ψ)·Ry(θ)·Rx(φ)`.
//! * Names say which frame a matrix maps *from* and *to*: `nav_from_body` is C_b^n, so
//!   `v_nav = nav_from_body * v_body`.
//! * Angular-rate mapping E_b^n of eq. 21.8: Ψ̇ = E_b^n · ω_nb^b.
//! * Rotation vectors: [`RotationIncrement`] gives exp([φ×]) and the left Jacobian J(φ) of SO(3)
//!   (the body rotation and the specific-force integral of one IMU interval, `ins` module docs);
//!   [`rotation_vector`] is the inverse of the exponential.

use nalgebra::{Matrix3, Vector3};

/// Skew-symmetric (cross-product) matrix: `skew(a) * b == a × b`.
pub fn skew(a: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -a.z, a.y, a.z, 0.0, -a.x, -a.y, a.x, 0.0)
}

/// C_b^n for the Euler triple Ψ = (roll φ, pitch θ, yaw ψ): Rz(ψ)·Ry(θ)·Rx(φ).
pub fn nav_from_body(euler: &Vector3<f64>) -> Matrix3<f64> {
    let (sr, cr) = euler.x.sin_cos();
    let (sp, cp) = euler.y.sin_cos();
    let (sy, cy) = euler.z.sin_cos();
    Matrix3::new(
        cp * cy,
        sr * sp * cy - cr * sy,
        cr * sp * cy + sr * sy,
        cp * sy,
        sr * sp * sy + cr * cy,
        cr * sp * sy - sr * cy,
        -sp,
        sr * cp,
        cr * cp,
    )
}

/// Partial derivatives of C_b^n with respect to (φ, θ, ψ), in that order.
pub fn nav_from_body_partials(euler: &Vector3<f64>) -> [Matrix3<f64>; 3] {
    let (sr, cr) = euler.x.sin_cos();
    let (sp, cp) = euler.y.sin_cos();
    let (sy, cy) = euler.z.sin_cos();
    let d_roll = Matrix3::new(
        0.0,
        cr * sp * cy + sr * sy,
        -sr * sp * cy + cr * sy,
        0.0,
        cr * sp * sy - sr * cy,
        -sr * sp * sy - cr * cy,
        0.0,
        cr * cp,
        -sr * cp,
    );
    let d_pitch = Matrix3::new(
        -sp * cy,
        sr * cp * cy,
        cr * cp * cy,
        -sp * sy,
        sr * cp * sy,
        cr * cp * sy,
        -cp,
        -sr * sp,
        -cr * sp,
    );
    let d_yaw = Matrix3::new(
        -cp * sy,
        -sr * sp * sy - cr * cy,
        -cr * sp * sy + sr * cy,
        cp * cy,
        sr * sp * cy - cr * sy,
        cr * sp * cy + sr * sy,
        0.0,
        0.0,
        0.0,
    );
    [d_roll, d_pitch, d_yaw]
}

/// Euler triple (φ, θ, ψ) of a rotation matrix C_b^n (inverse of [`nav_from_body`]).
/// Valid away from θ = ±90°, which the chapter excludes (§21.2.2).
pub fn euler_from_nav_from_body(c: &Matrix3<f64>) -> Vector3<f64> {
    let pitch = (-c[(2, 0)]).clamp(-1.0, 1.0).asin();
    let roll = c[(2, 1)].atan2(c[(2, 2)]);
    let yaw = c[(1, 0)].atan2(c[(0, 0)]);
    Vector3::new(roll, pitch, yaw)
}

/// E_b^n of eq. 21.8: maps the body rate relative to the navigation frame to Euler rates.
pub fn euler_rate_from_body_rate(euler: &Vector3<f64>) -> Matrix3<f64> {
    let (sr, cr) = euler.x.sin_cos();
    let (tp, sec) = (euler.y.tan(), 1.0 / euler.y.cos());
    Matrix3::new(1.0, sr * tp, cr * tp, 0.0, cr, -sr, 0.0, sr * sec, cr * sec)
}

/// Partial derivatives of E_b^n (eq. 21.8) with respect to (φ, θ, ψ); ∂/∂ψ is zero.
pub fn euler_rate_from_body_rate_partials(euler: &Vector3<f64>) -> [Matrix3<f64>; 3] {
    let (sr, cr) = euler.x.sin_cos();
    let (tp, sec) = (euler.y.tan(), 1.0 / euler.y.cos());
    let sec2 = sec * sec;
    let d_roll = Matrix3::new(
        0.0,
        cr * tp,
        -sr * tp,
        0.0,
        -sr,
        -cr,
        0.0,
        cr * sec,
        -sr * sec,
    );
    let d_pitch = Matrix3::new(
        0.0,
        sr * sec2,
        cr * sec2,
        0.0,
        0.0,
        0.0,
        0.0,
        sr * sec * tp,
        cr * sec * tp,
    );
    [d_roll, d_pitch, Matrix3::zeros()]
}

/// Inverse of E_b^n: ω_nb^b = (E_b^n)⁻¹ Ψ̇.
pub fn body_rate_from_euler_rate(euler: &Vector3<f64>) -> Matrix3<f64> {
    let (sr, cr) = euler.x.sin_cos();
    let (sp, cp) = euler.y.sin_cos();
    Matrix3::new(1.0, 0.0, -sp, 0.0, cr, sr * cp, 0.0, -sr, cr * cp)
}

/// Coefficients of the SO(3) exponential and its left Jacobian at a rotation vector φ, θ = |φ|:
/// exp([φ×]) = I + s·[φ×] + a·[φ×]², J(φ) = I + a·[φ×] + b·[φ×]², with s = sin θ/θ,
/// a = (1 − cos θ)/θ², b = (θ − sin θ)/θ³; `da`, `db` are da/d(θ²), db/d(θ²), and `c` the
/// coefficient of J⁻¹ = I − ½[φ×] + c·[φ×]², c = (1 − θ sin θ / (2(1 − cos θ)))/θ². Taylor
/// series in θ² below [`SO3_SERIES_ANGLE`] (truncation below 1e-15 relative there), closed forms
/// above.
#[derive(Clone, Copy, Debug)]
struct So3Coefficients {
    s: f64,
    a: f64,
    b: f64,
    da: f64,
    db: f64,
    c: f64,
}

/// Below this angle the SO(3) coefficients come from their Taylor series [rad].
const SO3_SERIES_ANGLE: f64 = 0.25;

/// Σ c_k x^k by Horner's rule.
fn horner(coefficients: &[f64], x: f64) -> f64 {
    coefficients.iter().rev().fold(0.0, |acc, c| acc * x + c)
}

/// Coefficients of Σ k c_k x^(k−1) (the derivative of a series).
fn derivative<const N: usize, const M: usize>(c: &[f64; N]) -> [f64; M] {
    std::array::from_fn(|k| c[k + 1] * (k + 1) as f64)
}

impl So3Coefficients {
    fn new(phi: &Vector3<f64>) -> Self {
        let t2 = phi.norm_squared();
        if t2 < SO3_SERIES_ANGLE * SO3_SERIES_ANGLE {
            // sin θ/θ = Σ (−θ²)^k/(2k+1)!, (1 − cos θ)/θ² = Σ (−θ²)^k/(2k+2)!,
            // (θ − sin θ)/θ³ = Σ (−θ²)^k/(2k+3)!; c from the series of (x/2)·cot(x/2).
            const S: [f64; 7] = [
                1.0,
                -1.0 / 6.0,
                1.0 / 120.0,
                -1.0 / 5040.0,
                1.0 / 362_880.0,
                -1.0 / 39_916_800.0,
                1.0 / 6_227_020_800.0,
            ];
            const A: [f64; 7] = [
                1.0 / 2.0,
                -1.0 / 24.0,
                1.0 / 720.0,
                -1.0 / 40_320.0,
                1.0 / 3_628_800.0,
                -1.0 / 479_001_600.0,
                1.0 / 87_178_291_200.0,
            ];
            const B: [f64; 7] = [
                1.0 / 6.0,
                -1.0 / 120.0,
                1.0 / 5040.0,
                -1.0 / 362_880.0,
                1.0 / 39_916_800.0,
                -1.0 / 6_227_020_800.0,
                1.0 / 1_307_674_368_000.0,
            ];
            const C: [f64; 6] = [
                1.0 / 12.0,
                1.0 / 720.0,
                1.0 / 30_240.0,
                1.0 / 1_209_600.0,
                1.0 / 47_900_160.0,
                691.0 / 1_307_674_368_000.0,
            ];
            Self {
                s: horner(&S, t2),
                a: horner(&A, t2),
                b: horner(&B, t2),
                da: horner(&derivative::<7, 6>(&A), t2),
                db: horner(&derivative::<7, 6>(&B), t2),
                c: horner(&C, t2),
            }
        } else {
            let t = t2.sqrt();
            let (sin, cos) = t.sin_cos();
            let s = sin / t;
            let a = (1.0 - cos) / t2;
            let b = (t - sin) / (t2 * t);
            Self {
                s,
                a,
                b,
                // d/d(θ²) = (1/2θ)·d/dθ: da/dθ = (s − 2a)/θ, db/dθ = (a − 3b)/θ.
                da: (s - 2.0 * a) / (2.0 * t2),
                db: (a - 3.0 * b) / (2.0 * t2),
                c: (1.0 - s / (2.0 * a)) / t2,
            }
        }
    }
}

/// The rotation exp([φ×]) of a rotation vector φ and the left Jacobian J(φ) of SO(3), the pair
/// a strapdown step needs for one IMU interval (`ins` module docs):
///
/// * `rotation` = exp([φ×]) = I + (sin θ/θ)[φ×] + ((1 − cos θ)/θ²)[φ×]² (Rodrigues), θ = |φ|;
/// * `left_jacobian` = J(φ) = ∫₀¹ exp(τ[φ×]) dτ = I + ((1 − cos θ)/θ²)[φ×] + ((θ − sin θ)/θ³)[φ×]².
///
/// J maps a perturbation of φ to rotations: exp([(φ + δ)×]) = exp([(J(φ)δ)×]) exp([φ×]) =
/// exp([φ×]) exp([(J(φ)ᵀδ)×]) to first order in δ. For a body turning at a constant rate ω with
/// a constant specific force f over Δt, ∫ C_{b(t)}^{b(0)} f dt = J(ωΔt) f Δt.
#[derive(Clone, Copy, Debug)]
pub struct RotationIncrement {
    /// exp([φ×]).
    pub rotation: Matrix3<f64>,
    /// J(φ).
    pub left_jacobian: Matrix3<f64>,
    phi: Vector3<f64>,
    k: So3Coefficients,
}

impl RotationIncrement {
    /// exp and J at φ.
    pub fn new(phi: &Vector3<f64>) -> Self {
        let k = So3Coefficients::new(phi);
        let x = skew(phi);
        let x2 = x * x;
        Self {
            rotation: Matrix3::identity() + x * k.s + x2 * k.a,
            left_jacobian: Matrix3::identity() + x * k.a + x2 * k.b,
            phi: *phi,
            k,
        }
    }

    /// J(φ)⁻¹ = I − ½[φ×] + ((1 − (θ/2)cot(θ/2))/θ²)[φ×]² (valid for θ < 2π).
    pub fn left_jacobian_inverse(&self) -> Matrix3<f64> {
        let x = skew(&self.phi);
        Matrix3::identity() - x * 0.5 + x * x * self.k.c
    }

    /// ∂(J(φ)·v)/∂φ for a fixed vector v (3×3).
    pub fn left_jacobian_times_partial(&self, v: &Vector3<f64>) -> Matrix3<f64> {
        // J v = v + a(θ²) φ×v + b(θ²) φ×(φ×v); d(θ²)/dφ = 2φᵀ.
        let phi = &self.phi;
        let pv = phi.cross(v);
        let ppv = phi.cross(&pv);
        let (sv, sp) = (skew(v), skew(phi));
        -sv * self.k.a - (skew(&pv) + sp * sv) * self.k.b
            + (pv * (2.0 * self.k.da) + ppv * (2.0 * self.k.db)) * phi.transpose()
    }
}

/// The rotation vector φ of a rotation matrix (the inverse of exp([φ×]) for |φ| < π): θ from
/// atan2 of the antisymmetric part and the trace, so small rotations keep full relative
/// precision. Accurate to rounding for θ ≤ π/2; it degrades as θ approaches π (the
/// antisymmetric part vanishes there), which an IMU interval never comes near.
pub fn rotation_vector(c: &Matrix3<f64>) -> Vector3<f64> {
    let v = 0.5
        * Vector3::new(
            c[(2, 1)] - c[(1, 2)],
            c[(0, 2)] - c[(2, 0)],
            c[(1, 0)] - c[(0, 1)],
        );
    let cos = 0.5 * (c.trace() - 1.0);
    let theta = v.norm().atan2(cos);
    // v = (sin θ/θ)·φ.
    v / So3Coefficients::new(&Vector3::new(theta, 0.0, 0.0)).s
}

/// Wraps an angle to (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut r = a % two_pi;
    if r <= -std::f64::consts::PI {
        r += two_pi;
    } else if r > std::f64::consts::PI {
        r -= two_pi;
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fd_matrix(
        f: impl Fn(&Vector3<f64>) -> Matrix3<f64>,
        x: &Vector3<f64>,
        i: usize,
    ) -> Matrix3<f64> {
        // Central difference, step 1e-6 rad: truncation O(h²)≈1e-12, round-off ≈1e-16/1e-6=1e-10.
        let h = 1e-6;
        let mut xp = *x;
        let mut xm = *x;
        xp[i] += h;
        xm[i] -= h;
        (f(&xp) - f(&xm)) / (2.0 * h)
    }

    #[test]
    fn dcm_is_orthonormal_and_matches_elementary_rotations() {
        let e = Vector3::new(0.3, -0.2, 2.5);
        let c = nav_from_body(&e);
        assert!((c.transpose() * c - Matrix3::identity()).norm() < 1e-14);
        assert!((c.determinant() - 1.0).abs() < 1e-14);
        let rx = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), e.x);
        let ry = nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), e.y);
        let rz = nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), e.z);
        let reference = (rz * ry * rx).into_inner();
        assert!((c - reference).norm() < 1e-14);
        let back = euler_from_nav_from_body(&c);
        assert!((back - e).norm() < 1e-12);
    }

    #[test]
    fn partials_match_finite_differences() {
        let e = Vector3::new(0.4, 0.3, -1.1);
        let dc = nav_from_body_partials(&e);
        let de = euler_rate_from_body_rate_partials(&e);
        for i in 0..3 {
            assert!(
                (dc[i] - fd_matrix(nav_from_body, &e, i)).norm() < 1e-8,
                "dC/dΨ{i}"
            );
            assert!(
                (de[i] - fd_matrix(euler_rate_from_body_rate, &e, i)).norm() < 1e-8,
                "dE/dΨ{i}"
            );
        }
    }

    #[test]
    fn euler_rate_matrix_inverse_and_kinematics() {
        let e = Vector3::new(0.2, 0.5, 0.7);
        let m = euler_rate_from_body_rate(&e) * body_rate_from_euler_rate(&e);
        assert!((m - Matrix3::identity()).norm() < 1e-13);
        // Ċ_b^n = C_b^n [ω_nb^b ×]; check with Ψ̇ = E ω.
        let omega = Vector3::new(0.01, -0.02, 0.03);
        let psi_dot = euler_rate_from_body_rate(&e) * omega;
        let dc = nav_from_body_partials(&e);
        let c_dot = dc[0] * psi_dot.x + dc[1] * psi_dot.y + dc[2] * psi_dot.z;
        assert!((c_dot - nav_from_body(&e) * skew(&omega)).norm() < 1e-14);
    }

    fn sample_vectors() -> Vec<Vector3<f64>> {
        // Series branch (θ < 0.25), its boundary, and the closed forms up to near π.
        [1e-9, 1e-4, 3e-3, 0.1, 0.2499, 0.2501, 0.7, 1.9, 3.0]
            .iter()
            .map(|&t| Vector3::new(0.36, -0.48, 0.8) * t)
            .collect()
    }

    #[test]
    fn rotation_increment_matches_nalgebra_and_a_quadrature() {
        for phi in sample_vectors() {
            let inc = RotationIncrement::new(&phi);
            let reference = *nalgebra::Rotation3::from_scaled_axis(phi).matrix();
            assert!((inc.rotation - reference).norm() < 1e-15, "{phi}");
            // J(φ) = ∫₀¹ exp(τ[φ×]) dτ by composite Simpson (2000 panels: error ≈ θ⁴/180/2000⁴ ≤
            // 3e-14 at θ = 3; the sum's rounding ≈ 2000 × 1e-16).
            let n = 2000;
            let mut j = Matrix3::zeros();
            for i in 0..=n {
                let w = if i == 0 || i == n {
                    1.0
                } else if i % 2 == 1 {
                    4.0
                } else {
                    2.0
                };
                let tau = i as f64 / n as f64;
                j += *nalgebra::Rotation3::from_scaled_axis(phi * tau).matrix() * w;
            }
            j /= 3.0 * n as f64;
            assert!((inc.left_jacobian - j).norm() < 1e-12, "{phi}");
            let id = inc.left_jacobian_inverse() * inc.left_jacobian;
            assert!((id - Matrix3::identity()).norm() < 1e-14, "{phi}");
        }
    }

    #[test]
    fn rotation_vector_inverts_the_exponential() {
        for phi in sample_vectors() {
            let back = rotation_vector(&RotationIncrement::new(&phi).rotation);
            // Relative precision kept for small angles (atan2 of the antisymmetric part).
            assert!(
                (back - phi).norm() <= 1e-15 + 1e-14 * phi.norm(),
                "{phi}: {back}"
            );
        }
    }

    #[test]
    fn left_jacobian_partial_and_perturbation_identity() {
        let v = Vector3::new(0.7, -1.3, 9.6);
        for phi in sample_vectors() {
            let inc = RotationIncrement::new(&phi);
            let analytic = inc.left_jacobian_times_partial(&v);
            // Central differences, step 1e-6: truncation ≈ 1e-12, round-off ≈ 1e-16·10/1e-6.
            let h = 1e-6;
            let mut fd = Matrix3::zeros();
            for i in 0..3 {
                let mut d = Vector3::zeros();
                d[i] = h;
                let jp = RotationIncrement::new(&(phi + d)).left_jacobian * v;
                let jm = RotationIncrement::new(&(phi - d)).left_jacobian * v;
                fd.set_column(i, &((jp - jm) / (2.0 * h)));
            }
            assert!(
                (analytic - fd).norm() < 1e-8,
                "{phi}: {}",
                (analytic - fd).norm()
            );
            // exp([(φ + δ)×]) = exp([φ×]) exp([(Jᵀδ)×]) to first order: the residual is O(|δ|²).
            let delta = Vector3::new(1e-7, -2e-7, 1.5e-7);
            let lhs = RotationIncrement::new(&(phi + delta)).rotation;
            let rhs = inc.rotation
                * RotationIncrement::new(&(inc.left_jacobian.transpose() * delta)).rotation;
            assert!((lhs - rhs).norm() < 1e-13, "{phi}: {}", (lhs - rhs).norm());
        }
    }

    #[test]
    fn wrap_angle_range() {
        assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-15);
        assert!(wrap_angle(-std::f64::consts::PI) > 0.0);
    }
}
