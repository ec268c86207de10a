//! Attitude conventions, stated once and kept everywhere.
//!
//! * Frames: `e` = ECEF, `n` = local-level North-East-Down, `b` = body (x forward, y right,
//!   z down), `s` = terrain sensor (x along the boresight, y right, z down in the image).
//! * Attitude is the Euler triple Ψ = (φ, θ, ψ) = (roll, pitch, yaw) of the aerospace z-y-x
//!   sequence: `nav_from_body(Ψ) = C_b^n = Rz(ψ)·Ry(θ)·Rx(φ)`.
//! * Names say which frame a matrix maps *from* and *to*: `nav_from_body` is C_b^n, so
//!   `v_nav = nav_from_body * v_body`.
//! * Angular-rate mapping E_b^n of eq. 21.8: Ψ̇ = E_b^n · ω_nb^b.

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

    #[test]
    fn wrap_angle_range() {
        assert!((wrap_angle(3.0 * std::f64::consts::PI) - std::f64::consts::PI).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-15);
        assert!(wrap_angle(-std::f64::consts::PI) > 0.0);
    }
}
