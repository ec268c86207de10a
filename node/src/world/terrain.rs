//! A smooth seeded terrain surface over the launch site's NED plane.
//!
//! h(n, e) = Σᵢ aᵢ cos(kᵢ·(n, e) + φᵢ) − h₀, with wavelengths 2π/|kᵢ| log-uniform in
//! [min, max], directions and phases uniform, amplitudes ∝ wavelength (every component has the
//! same slope), scaled so the RMS over the plane is `relief_m` (random-phase cosines:
//! RMS² = Σ aᵢ²/2), and h₀ chosen so the launch site is at height 0. C^∞ everywhere.

use nalgebra::Vector2;
use rand::Rng;
use std::f64::consts::TAU;

use crate::scenario::TerrainConfig;

#[derive(Clone, Copy, Debug)]
struct Wave {
    wavenumber: Vector2<f64>,
    amplitude: f64,
    phase: f64,
}

/// The terrain height field, in metres above the launch site.
#[derive(Clone, Debug)]
pub struct Terrain {
    waves: Vec<Wave>,
    offset: f64,
}

impl Terrain {
    /// Draws a surface from `rng` (a terrain-only stream, so feature draws do not shift it).
    pub fn new(cfg: &TerrainConfig, rng: &mut impl Rng) -> Self {
        let (lo, hi) = (cfg.min_wavelength_m.ln(), cfg.max_wavelength_m.ln());
        let mut waves: Vec<Wave> = (0..cfg.components)
            .map(|_| {
                let wavelength = (lo + (hi - lo) * rng.random::<f64>()).exp();
                let dir = TAU * rng.random::<f64>();
                Wave {
                    wavenumber: Vector2::new(dir.cos(), dir.sin()) * (TAU / wavelength),
                    amplitude: wavelength,
                    phase: TAU * rng.random::<f64>(),
                }
            })
            .collect();
        let rms = (waves.iter().map(|w| w.amplitude * w.amplitude).sum::<f64>() / 2.0).sqrt();
        for w in &mut waves {
            w.amplitude *= cfg.relief_m / rms;
        }
        let mut t = Self { waves, offset: 0.0 };
        t.offset = t.height(0.0, 0.0);
        t
    }

    /// Height above the launch site at (north, east) [m].
    pub fn height(&self, north: f64, east: f64) -> f64 {
        let x = Vector2::new(north, east);
        self.waves
            .iter()
            .map(|w| w.amplitude * (w.wavenumber.dot(&x) + w.phase).cos())
            .sum::<f64>()
            - self.offset
    }

    /// Gradient (∂h/∂north, ∂h/∂east).
    pub fn gradient(&self, north: f64, east: f64) -> Vector2<f64> {
        let x = Vector2::new(north, east);
        self.waves
            .iter()
            .map(|w| -w.wavenumber * (w.amplitude * (w.wavenumber.dot(&x) + w.phase).sin()))
            .sum()
    }

    /// An upper bound on |h| anywhere: Σ|aᵢ| + |h₀|.
    pub fn height_bound(&self) -> f64 {
        self.waves.iter().map(|w| w.amplitude.abs()).sum::<f64>() + self.offset.abs()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn terrain_is_anchored_smooth_and_has_the_requested_relief() {
        let cfg = TerrainConfig {
            relief_m: 20.0,
            min_wavelength_m: 100.0,
            max_wavelength_m: 2000.0,
            components: 32,
        };
        let t = Terrain::new(&cfg, &mut ChaCha8Rng::seed_from_u64(3));
        assert_eq!(t.height(0.0, 0.0), 0.0);
        // Gradient against central differences (h = 1e-3 m: truncation ≲ 1e-6·|h‴| ≈ 1e-9).
        for &(n, e) in &[(120.0, -40.0), (-900.0, 700.0)] {
            let d = 1e-3;
            let fd = Vector2::new(
                (t.height(n + d, e) - t.height(n - d, e)) / (2.0 * d),
                (t.height(n, e + d) - t.height(n, e - d)) / (2.0 * d),
            );
            assert!((fd - t.gradient(n, e)).norm() < 1e-7);
        }
        // Spatial RMS about the mean over a 20 km square: the Σa²/2 identity holds up to the
        // finite window and the sampling (a few % for the longest 2 km waves).
        let (mut s, mut s2, mut m) = (0.0, 0.0, 0.0f64);
        let n = 200;
        for i in 0..n {
            for j in 0..n {
                let h = t.height(-10_000.0 + 100.0 * i as f64, -10_000.0 + 100.0 * j as f64);
                s += h;
                s2 += h * h;
                m = m.max(h.abs());
            }
        }
        let cnt = (n * n) as f64;
        let rms = (s2 / cnt - (s / cnt).powi(2)).sqrt();
        assert!((rms / 20.0 - 1.0).abs() < 0.1, "rms {rms}");
        assert!(m <= t.height_bound());
    }
}
