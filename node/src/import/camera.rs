//! Camera models of the calibrations the importer reads: pinhole intrinsics with radial-
//! tangential (OpenCV / Kalibr `radtan`, EuRoC `radial-tangential`) or equidistant (Kalibr
//! `equidistant`, OpenCV fisheye) distortion, and their inversion (undistortion) by Newton
//! iterations checked against the forward model.

use nalgebra::{Matrix2, Vector2};

/// Lens distortion of normalized image coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Distortion {
    /// None: the coordinates are already undistorted.
    None,
    /// Radial-tangential: (k1, k2, p1, p2).
    RadTan([f64; 4]),
    /// Equidistant (Kannala–Brandt): θ_d = θ(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸).
    Equidistant([f64; 4]),
}

/// A calibrated camera: pinhole intrinsics of the raw image and its distortion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Focal lengths and principal point [px]: (f_u, f_v, c_u, c_v).
    pub intrinsics: [f64; 4],
    /// Raw image size [px]: (width, height).
    pub resolution: [f64; 2],
    /// Distortion model.
    pub distortion: Distortion,
}

impl Distortion {
    /// Distorts undistorted normalized coordinates (x, y) = (X/Z, Y/Z).
    pub fn distort(&self, p: Vector2<f64>) -> Vector2<f64> {
        match *self {
            Distortion::None => p,
            Distortion::RadTan([k1, k2, p1, p2]) => {
                let (x, y) = (p.x, p.y);
                let r2 = x * x + y * y;
                let radial = 1.0 + k1 * r2 + k2 * r2 * r2;
                Vector2::new(
                    x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                    y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
                )
            }
            Distortion::Equidistant([k1, k2, k3, k4]) => {
                let r = p.norm();
                if r < 1e-12 {
                    return p;
                }
                let th = r.atan();
                let th2 = th * th;
                let thd = th * (1.0 + th2 * (k1 + th2 * (k2 + th2 * (k3 + th2 * k4))));
                p * (thd / r)
            }
        }
    }

    /// Undistorts distorted normalized coordinates; `None` when the iteration does not reproduce
    /// `d` to 1e-10 (outside the model's invertible range).
    pub fn undistort(&self, d: Vector2<f64>) -> Option<Vector2<f64>> {
        if !(d.x.is_finite() && d.y.is_finite()) {
            return None;
        }
        if let Distortion::None = self {
            return Some(d);
        }
        // Newton on distort(p) = d from p = d, with a central-difference Jacobian.
        let mut p = d;
        for _ in 0..50 {
            let r = self.distort(p) - d;
            if r.norm() < 1e-14 {
                break;
            }
            let h = 1e-7;
            let mut j = Matrix2::zeros();
            for c in 0..2 {
                let mut a = p;
                let mut b = p;
                a[c] += h;
                b[c] -= h;
                let col = (self.distort(a) - self.distort(b)) / (2.0 * h);
                j.set_column(c, &col);
            }
            let step = j.try_inverse()? * r;
            p -= step;
            if !(p.x.is_finite() && p.y.is_finite()) {
                return None;
            }
        }
        // Tolerance: well above the Newton iteration's final accuracy (≈ 1e-14), far below a
        // pixel (1e-10 normalized ≈ 5e-8 px at f = 500 px).
        ((self.distort(p) - d).norm() < 1e-10).then_some(p)
    }
}

impl Camera {
    /// Undistorted normalized coordinates of a raw-image pixel (u, v).
    pub fn normalized_from_pixel(&self, uv: Vector2<f64>) -> Option<Vector2<f64>> {
        let [fu, fv, cu, cv] = self.intrinsics;
        self.distortion
            .undistort(Vector2::new((uv.x - cu) / fu, (uv.y - cv) / fv))
    }

    /// The rectangle [x_min, x_max] × [y_min, y_max] of undistorted normalized coordinates
    /// that holds every pixel of the raw image (its border sampled every pixel; border pixels
    /// the model cannot invert are left out).
    pub fn undistorted_bounds(&self) -> Option<[f64; 4]> {
        let [w, h] = self.resolution;
        let mut b = [
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let mut any = false;
        let mut add = |u: f64, v: f64| {
            if let Some(p) = self.normalized_from_pixel(Vector2::new(u, v)) {
                b[0] = b[0].min(p.x);
                b[1] = b[1].max(p.x);
                b[2] = b[2].min(p.y);
                b[3] = b[3].max(p.y);
                any = true;
            }
        };
        let (nu, nv) = (w.ceil() as usize, h.ceil() as usize);
        for i in 0..=nu {
            let u = (i as f64).min(w);
            add(u, 0.0);
            add(u, h);
        }
        for i in 0..=nv {
            let v = (i as f64).min(h);
            add(0.0, v);
            add(w, v);
        }
        any.then_some(b)
    }
}

/// The undistorted pinhole camera the importer writes into the scenario (eq. 21.43 intrinsics):
/// the calibration's focal lengths and a principal point and image size chosen so the image
/// [0, width) × [0, height) holds every undistorted pixel of the raw image (plus a margin of
/// `margin_px`), so no observation of a real pixel lies outside it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VirtualPinhole {
    /// f_u, f_v [px].
    pub focal: [f64; 2],
    /// u_0, v_0 [px].
    pub principal: [f64; 2],
    /// Width, height [px].
    pub size: [f64; 2],
}

impl VirtualPinhole {
    /// The virtual camera of `cam` (`None` when no border pixel can be undistorted).
    pub fn of(cam: &Camera, margin_px: f64) -> Option<Self> {
        Self::covering(cam, std::iter::empty(), margin_px)
    }

    /// The virtual camera of `cam` whose image also holds the undistorted normalized points
    /// `extra` (observations a feature tracker reported beyond the raw image's undistorted
    /// border: the filter would otherwise refuse them as outside the image).
    pub fn covering(
        cam: &Camera,
        extra: impl Iterator<Item = Vector2<f64>>,
        margin_px: f64,
    ) -> Option<Self> {
        let [mut x0, mut x1, mut y0, mut y1] = cam.undistorted_bounds()?;
        for p in extra {
            x0 = x0.min(p.x);
            x1 = x1.max(p.x);
            y0 = y0.min(p.y);
            y1 = y1.max(p.y);
        }
        let [fu, fv, _, _] = cam.intrinsics;
        let u0 = -fu * x0 + margin_px;
        let v0 = -fv * y0 + margin_px;
        Some(Self {
            focal: [fu, fv],
            principal: [u0, v0],
            size: [
                (fu * (x1 - x0) + 2.0 * margin_px).ceil(),
                (fv * (y1 - y0) + 2.0 * margin_px).ceil(),
            ],
        })
    }

    /// The pixel of undistorted normalized coordinates (eq. 21.43: u = f_u·y^s/x^s + u_0 with
    /// y^s/x^s = X_c/Z_c).
    pub fn pixel(&self, p: Vector2<f64>) -> Vector2<f64> {
        Vector2::new(
            self.focal[0] * p.x + self.principal[0],
            self.focal[1] * p.y + self.principal[1],
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// EuRoC cam0's radial-tangential calibration.
    fn euroc() -> Camera {
        Camera {
            intrinsics: [458.654, 457.296, 367.215, 248.375],
            resolution: [752.0, 480.0],
            distortion: Distortion::RadTan([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]),
        }
    }

    #[test]
    fn radtan_matches_the_opencv_formula_at_a_hand_computed_point() {
        // x = 0.3, y = −0.2: r² = 0.13, radial = 1 − 0.28340811·0.13 + 0.07395907·0.0169
        // = 0.96440687…; by hand (independent of the code's arrangement of the terms).
        let d = euroc().distortion.distort(Vector2::new(0.3, -0.2));
        let (k1, k2, p1, p2) = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05);
        let radial: f64 = 1.0 + k1 * 0.13 + k2 * 0.0169;
        let xd = 0.3 * radial + 2.0 * p1 * 0.3 * -0.2 + p2 * (0.13 + 2.0 * 0.09);
        let yd = -0.2 * radial + p1 * (0.13 + 2.0 * 0.04) + 2.0 * p2 * 0.3 * -0.2;
        assert!((d.x - xd).abs() < 1e-15 && (d.y - yd).abs() < 1e-15);
    }

    #[test]
    fn undistortion_inverts_both_models_across_the_image() {
        // Corners at θ_d ≈ 256·√2/300 = 1.2 rad: inside the hemisphere a pinhole can hold.
        let fish = Camera {
            intrinsics: [300.0, 300.0, 254.0, 256.0],
            resolution: [512.0, 512.0],
            distortion: Distortion::Equidistant([0.003, 0.002, -0.001, 0.0002]),
        };
        for cam in [euroc(), fish] {
            for i in 0..=10 {
                for j in 0..=10 {
                    let u = cam.resolution[0] * i as f64 / 10.0;
                    let v = cam.resolution[1] * j as f64 / 10.0;
                    let p = cam.normalized_from_pixel(Vector2::new(u, v)).unwrap();
                    let [fu, fv, cu, cv] = cam.intrinsics;
                    let back = cam.distortion.distort(p);
                    // The forward model reproduces the pixel to well below 1e-6 px.
                    assert!((fu * back.x + cu - u).abs() < 1e-6, "{u} {v}");
                    assert!((fv * back.y + cv - v).abs() < 1e-6, "{u} {v}");
                }
            }
        }
    }

    #[test]
    fn the_virtual_pinhole_holds_every_undistorted_raw_pixel() {
        let cam = euroc();
        let vp = VirtualPinhole::of(&cam, 1.0).unwrap();
        // Barrel distortion (k1 < 0): the undistorted image is larger than the raw one.
        assert!(vp.size[0] > 752.0 && vp.size[1] > 480.0, "{vp:?}");
        for i in 0..=40 {
            for j in 0..=40 {
                let uv = Vector2::new(752.0 * i as f64 / 40.0, 480.0 * j as f64 / 40.0);
                let px = vp.pixel(cam.normalized_from_pixel(uv).unwrap());
                assert!(px.x >= 0.0 && px.x < vp.size[0] && px.y >= 0.0 && px.y < vp.size[1]);
            }
        }
    }
}
