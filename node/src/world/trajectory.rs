//! Analytic flight paths in the launch site's NED frame and their coordinated-flight attitude.
//!
//! A [`Trajectory`] gives position, velocity, acceleration and jerk at any time, at constant
//! horizontal speed: closed forms for the orbit; Gauss–Legendre quadrature of a closed-form
//! heading for the lawnmower's turns; an arc-length parametrisation (quadrature plus Newton) of
//! the figure-eight — all accurate to ~1e-10 m or better. Then [`coordinated_attitude`] turns (v, a, j) into the Euler attitude Ψ and its rate
//! Ψ̇. The horizontal pattern is C³ (lawnmower: the curvature ramps with a quintic smootherstep,
//! so curvature is C² in arc length; orbit and figure-eight are C^∞), hence the attitude is C¹ and
//! the body rates are continuous.
//!
//! # Coordinated flight
//! - yaw ψ = heading of the velocity, atan2(v_E, v_N);
//! - pitch θ = flight-path angle, atan2(−v_D, |v_H|) (zero in level flight);
//! - roll φ such that the specific force f = a − g has no body-y component (no sideslip):
//!   with f' = (R_z(ψ)R_y(θ))ᵀ f, φ = atan2(f'_y, −f'_z), so a right turn banks right (φ > 0).
//!
//! The design gravity is [`DESIGN_GRAVITY`] straight down the launch frame's z; the IMU
//! synthesis later uses the exact gravity of the world, so this only shapes the flight.

use canopy_fusion::rotation::skew;
use nalgebra::{Matrix2, Matrix3, Rotation3, Vector2, Vector3};
use std::f64::consts::{PI, TAU};

use crate::scenario::{ScenarioError, ShapeConfig, TrajectoryConfig, in_range, positive_at_most};

/// Gravity [m/s²] that shapes coordinated flight (the bank angle of a turn). The IMU synthesis
/// uses the world's own gravity; at a site where it differs (9.78–9.83 m/s²) a turn has a
/// sideslip specific force of at most |a|·0.3 %, which is a valid flight all the same.
pub const DESIGN_GRAVITY: f64 = 9.81;

/// Largest bank angle a trajectory may require [rad] (60°: 2 g turns).
pub const MAX_BANK: f64 = 60.0 * PI / 180.0;

/// Samples over a period used to find the bank and rate envelope.
pub const ENVELOPE_SAMPLES: usize = 4096;

/// Position and its first three time derivatives in the launch NED frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Kinematics {
    /// p^{n0} [m].
    pub position: Vector3<f64>,
    /// v^{n0} [m/s].
    pub velocity: Vector3<f64>,
    /// a^{n0} [m/s²].
    pub acceleration: Vector3<f64>,
    /// Jerk da/dt [m/s³].
    pub jerk: Vector3<f64>,
}

/// Kinematics plus coordinated-flight attitude, all relative to the launch NED frame n0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FlightState {
    /// Trajectory time (simulation time plus the phase offset) [s].
    pub time: f64,
    /// Position and derivatives.
    pub kinematics: Kinematics,
    /// Ψ = (φ, θ, ψ) of C_b^{n0}; yaw in (−π, π] [rad].
    pub attitude: Vector3<f64>,
    /// Ψ̇ [rad/s].
    pub attitude_rate: Vector3<f64>,
}

/// Coordinated-flight attitude Ψ and its exact time derivative Ψ̇ from velocity, acceleration
/// and jerk in a NED frame with gravity `gravity` along +z (see the module doc).
pub fn coordinated_attitude(
    v: &Vector3<f64>,
    a: &Vector3<f64>,
    j: &Vector3<f64>,
    gravity: f64,
) -> (Vector3<f64>, Vector3<f64>) {
    let vh2 = v.x * v.x + v.y * v.y;
    let vh = vh2.sqrt();
    let yaw = v.y.atan2(v.x);
    let yaw_rate = (v.x * a.y - v.y * a.x) / vh2;
    let pitch = (-v.z).atan2(vh);
    let vh_dot = (v.x * a.x + v.y * a.y) / vh;
    let pitch_rate = (vh * (-a.z) - (-v.z) * vh_dot) / (vh2 + v.z * v.z);

    let rz = *Rotation3::from_axis_angle(&Vector3::z_axis(), yaw).matrix();
    let ry = *Rotation3::from_axis_angle(&Vector3::y_axis(), pitch).matrix();
    let m = (rz * ry).transpose();
    let m_dot = (yaw_rate * rz * skew(&Vector3::z()) * ry
        + pitch_rate * rz * ry * skew(&Vector3::y()))
    .transpose();
    let f = a - Vector3::new(0.0, 0.0, gravity);
    let fp = m * f;
    let fp_dot = m_dot * f + m * j;
    let roll = fp.y.atan2(-fp.z);
    let roll_rate = (-fp.z * fp_dot.y + fp.y * fp_dot.z) / (fp.y * fp.y + fp.z * fp.z);
    (
        Vector3::new(roll, pitch, yaw),
        Vector3::new(roll_rate, pitch_rate, yaw_rate),
    )
}

/// Horizontal kinematics in a 2-D frame.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Planar {
    p: Vector2<f64>,
    v: Vector2<f64>,
    a: Vector2<f64>,
    j: Vector2<f64>,
}

/// A flight path: a horizontal pattern, its placement, altitude and climb profile.
#[derive(Clone, Debug)]
pub struct Trajectory {
    shape: Shape,
    centre: Vector2<f64>,
    pattern_to_ned: Matrix2<f64>,
    altitude: f64,
    climb_amplitude: f64,
    climb_omega: f64,
    time_offset: f64,
    period: f64,
    max_bank: f64,
    max_rates: Vector3<f64>,
}

#[derive(Clone, Debug)]
enum Shape {
    Lawnmower(Lawnmower),
    Orbit { radius: f64, rate: f64 },
    FigureEight(Gerono),
}

impl Trajectory {
    /// Builds and checks a trajectory (error field paths are relative to the trajectory table).
    pub fn new(cfg: &TrajectoryConfig) -> Result<Self, ScenarioError> {
        in_range(
            "centre_ne_m[0]",
            cfg.centre_ne_m[0],
            -1e6,
            1e6,
            "pattern centre",
        )?;
        in_range(
            "centre_ne_m[1]",
            cfg.centre_ne_m[1],
            -1e6,
            1e6,
            "pattern centre",
        )?;
        positive_at_most("altitude_m", cfg.altitude_m, 20_000.0)?;
        positive_at_most("speed_mps", cfg.speed_mps, 150.0)?;
        if !(cfg.phase >= 0.0 && cfg.phase < 1.0) {
            return Err(ScenarioError::invalid(
                "phase",
                format!("must be in [0, 1), got {}", cfg.phase),
            ));
        }
        in_range(
            "heading_deg",
            cfg.heading_deg,
            -360.0,
            360.0,
            "pattern heading",
        )?;
        if !(cfg.climb_amplitude_m.is_finite()
            && cfg.climb_amplitude_m >= 0.0
            && cfg.climb_amplitude_m < cfg.altitude_m)
        {
            return Err(ScenarioError::invalid(
                "climb_amplitude_m",
                "must be in [0, altitude_m)",
            ));
        }
        positive_at_most("climb_period_s", cfg.climb_period_s, 1e6)?;
        let speed = cfg.speed_mps;
        let (shape, period) = match cfg.shape {
            ShapeConfig::Lawnmower {
                leg_length_m,
                leg_spacing_m,
                legs,
                turn_ramp_fraction,
            } => {
                positive_at_most("shape.leg_length_m", leg_length_m, 1e6)?;
                positive_at_most("shape.leg_spacing_m", leg_spacing_m, 1e6)?;
                if !(2..=1000).contains(&legs) {
                    return Err(ScenarioError::invalid("shape.legs", "must be in 2..=1000"));
                }
                if !(turn_ramp_fraction > 0.0 && turn_ramp_fraction <= 0.5) {
                    return Err(ScenarioError::invalid(
                        "shape.turn_ramp_fraction",
                        "must be in (0, 0.5]",
                    ));
                }
                let lm = Lawnmower::new(
                    speed,
                    leg_length_m,
                    leg_spacing_m,
                    legs as usize,
                    turn_ramp_fraction,
                );
                let period = lm.total_length / speed;
                (Shape::Lawnmower(lm), period)
            }
            ShapeConfig::Orbit {
                radius_m,
                clockwise,
            } => {
                positive_at_most("shape.radius_m", radius_m, 1e6)?;
                let sign = if clockwise { 1.0 } else { -1.0 };
                let rate = sign * speed / radius_m;
                (
                    Shape::Orbit {
                        radius: radius_m,
                        rate,
                    },
                    TAU * radius_m / speed,
                )
            }
            ShapeConfig::FigureEight { length_m, width_m } => {
                positive_at_most("shape.length_m", length_m, 1e6)?;
                positive_at_most("shape.width_m", width_m, 1e6)?;
                let g = Gerono::new(speed, 0.5 * length_m, 0.5 * width_m);
                let period = g.perimeter() / speed;
                (Shape::FigureEight(g), period)
            }
        };
        let h = cfg.heading_deg.to_radians();
        let mut traj = Self {
            shape,
            centre: Vector2::from(cfg.centre_ne_m),
            pattern_to_ned: Matrix2::new(h.cos(), -h.sin(), h.sin(), h.cos()),
            altitude: cfg.altitude_m,
            climb_amplitude: cfg.climb_amplitude_m,
            climb_omega: TAU / cfg.climb_period_s,
            time_offset: cfg.phase * period,
            period,
            max_bank: 0.0,
            max_rates: Vector3::zeros(),
        };
        // Survey one period (and one climb period) finely for the bank and rate envelope.
        let span = period.max(cfg.climb_period_s);
        let n = ENVELOPE_SAMPLES;
        let (mut bank, mut pitch, mut rates) = (0.0f64, 0.0f64, Vector3::<f64>::zeros());
        for i in 0..n {
            let s = traj.state(span * i as f64 / n as f64 - traj.time_offset);
            bank = bank.max(s.attitude.x.abs());
            pitch = pitch.max(s.attitude.y.abs());
            rates = rates.sup(&s.attitude_rate.abs());
        }
        traj.max_bank = bank;
        traj.max_rates = rates;
        if bank > MAX_BANK {
            let field = match cfg.shape {
                ShapeConfig::Lawnmower { .. } => "shape.leg_spacing_m",
                ShapeConfig::Orbit { .. } => "shape.radius_m",
                ShapeConfig::FigureEight { .. } => "shape.width_m",
            };
            return Err(ScenarioError::invalid(
                field,
                format!(
                    "the turns need a {:.1}° bank at {} m/s (limit {:.0}°): widen the pattern or slow down",
                    bank.to_degrees(),
                    speed,
                    MAX_BANK.to_degrees()
                ),
            ));
        }
        if pitch > MAX_BANK {
            return Err(ScenarioError::invalid(
                "climb_amplitude_m",
                format!(
                    "the climb needs a {:.1}° flight-path angle (limit {:.0}°)",
                    pitch.to_degrees(),
                    MAX_BANK.to_degrees()
                ),
            ));
        }
        Ok(traj)
    }

    /// Period of the horizontal pattern [s].
    pub fn period(&self) -> f64 {
        self.period
    }

    /// Largest |roll| over a period [rad].
    pub fn max_bank(&self) -> f64 {
        self.max_bank
    }

    /// Largest |φ̇|, |θ̇|, |ψ̇| over a period [rad/s] (sampled at [`ENVELOPE_SAMPLES`] points).
    pub fn max_attitude_rates(&self) -> Vector3<f64> {
        self.max_rates
    }

    /// Kinematics at simulation time `t` (the phase offset is applied here).
    pub fn kinematics(&self, t: f64) -> Kinematics {
        let tau = t + self.time_offset;
        let pl = match &self.shape {
            Shape::Lawnmower(lm) => lm.planar(tau),
            Shape::Orbit { radius, rate } => {
                let b = rate * tau;
                let (s, c) = b.sin_cos();
                let (r, w) = (*radius, *rate);
                Planar {
                    p: Vector2::new(r * c, r * s),
                    v: Vector2::new(-r * w * s, r * w * c),
                    a: Vector2::new(-r * w * w * c, -r * w * w * s),
                    j: Vector2::new(r * w * w * w * s, -r * w * w * w * c),
                }
            }
            Shape::FigureEight(g) => g.planar(tau),
        };
        let r = &self.pattern_to_ned;
        let p = self.centre + r * pl.p;
        let (v, a, j) = (r * pl.v, r * pl.a, r * pl.j);
        let (amp, om) = (self.climb_amplitude, self.climb_omega);
        let (s, c) = (om * tau).sin_cos();
        // down = −altitude − A sin(ωτ)
        Kinematics {
            position: Vector3::new(p.x, p.y, -self.altitude - amp * s),
            velocity: Vector3::new(v.x, v.y, -amp * om * c),
            acceleration: Vector3::new(a.x, a.y, amp * om * om * s),
            jerk: Vector3::new(j.x, j.y, amp * om * om * om * c),
        }
    }

    /// Kinematics and coordinated-flight attitude at simulation time `t`.
    pub fn state(&self, t: f64) -> FlightState {
        let k = self.kinematics(t);
        let (attitude, attitude_rate) =
            coordinated_attitude(&k.velocity, &k.acceleration, &k.jerk, DESIGN_GRAVITY);
        FlightState {
            time: t + self.time_offset,
            kinematics: k,
            attitude,
            attitude_rate,
        }
    }
}

/// Quintic smootherstep P(x) = 6x⁵ − 15x⁴ + 10x³ on [0, 1]: P, P′, P″ continuous with
/// P(0) = 0, P(1) = 1, P′ = P″ = 0 at both ends.
fn smootherstep(x: f64) -> f64 {
    x * x * x * (x * (6.0 * x - 15.0) + 10.0)
}

/// P′(x) = 30x⁴ − 60x³ + 30x².
fn smootherstep_slope(x: f64) -> f64 {
    30.0 * x * x * (x * (x - 2.0) + 1.0)
}

/// ∫₀ˣ P = x⁶ − 3x⁵ + 2.5x⁴.
fn smootherstep_integral(x: f64) -> f64 {
    x * x * x * x * (x * (x - 3.0) + 2.5)
}

/// The lawnmower: straight legs and 180° turns with curvature κ(s) = ±κ_max·shape(s/S), where
/// shape ramps 0→1 over the first `ramp` fraction of the turn's arc length S (smootherstep),
/// stays 1, and ramps back down symmetrically. The heading change is κ_max·S·(1 − ramp) = π, and
/// by the turn's mirror symmetry it ends level with where it started along the legs.
#[derive(Clone, Debug)]
struct Lawnmower {
    speed: f64,
    ramp: f64,
    turn_length: f64,
    /// κ_max·S = π/(1 − ramp) (dimensionless).
    turn_angle_scale: f64,
    /// Canonical unit turn (S = 1, start heading 0, turning right): displacement at the start
    /// of its three pieces (x = 0, ramp, 1 − ramp).
    piece_start: [Vector2<f64>; 3],
    segments: Vec<Segment>,
    total_length: f64,
}

#[derive(Clone, Copy, Debug)]
struct Segment {
    /// Arc length at which the segment starts.
    s0: f64,
    /// Its length.
    length: f64,
    /// Start point (pattern frame).
    start: Vector2<f64>,
    /// Start heading in the pattern frame (0 or π).
    heading: f64,
    /// 0 for a leg; ±1 for a turn (+1: right, heading increasing).
    turn: f64,
}

impl Lawnmower {
    fn new(speed: f64, leg_length: f64, spacing: f64, legs: usize, ramp: f64) -> Self {
        let mut lm = Self {
            speed,
            ramp,
            turn_length: 1.0,
            turn_angle_scale: PI / (1.0 - ramp),
            piece_start: [Vector2::zeros(); 3],
            segments: Vec::new(),
            total_length: 0.0,
        };
        // Canonical unit turn displacements at its piece boundaries.
        let r = ramp;
        lm.piece_start[1] = lm.unit_turn_piece(0.0, r);
        lm.piece_start[2] = lm.piece_start[1] + lm.unit_turn_piece(r, 1.0 - r);
        let unit_end = lm.piece_start[2] + lm.unit_turn_piece(1.0 - r, 1.0);
        lm.turn_length = spacing / unit_end.y;

        // One period: legs 0, 1, …, n−1, n−2, …, 1 (2(n−1) legs), each followed by a turn.
        let n = legs;
        let cycle = 2 * (n - 1);
        let lateral = |j: usize| (j as f64 - (n as f64 - 1.0) / 2.0) * spacing;
        let leg_index = |m: usize| if m < n { m } else { cycle - m };
        let mut s0 = 0.0;
        for m in 0..cycle {
            let j = leg_index(m);
            let next = leg_index((m + 1) % cycle);
            let dir_x = if m % 2 == 0 { 1.0 } else { -1.0 };
            let dir_y = if next > j { 1.0 } else { -1.0 };
            let heading = if dir_x > 0.0 { 0.0 } else { PI };
            lm.segments.push(Segment {
                s0,
                length: leg_length,
                start: Vector2::new(-dir_x * 0.5 * leg_length, lateral(j)),
                heading,
                turn: 0.0,
            });
            s0 += leg_length;
            lm.segments.push(Segment {
                s0,
                length: lm.turn_length,
                start: Vector2::new(dir_x * 0.5 * leg_length, lateral(j)),
                heading,
                turn: dir_x * dir_y,
            });
            s0 += lm.turn_length;
        }
        lm.total_length = s0;
        lm
    }

    /// Curvature shape on the unit turn, its slope, and its integral from 0.
    fn shape(&self, x: f64) -> (f64, f64, f64) {
        let r = self.ramp;
        if x <= r {
            let y = x / r;
            (
                smootherstep(y),
                smootherstep_slope(y) / r,
                r * smootherstep_integral(y),
            )
        } else if x < 1.0 - r {
            (1.0, 0.0, 0.5 * r + (x - r))
        } else {
            let y = ((1.0 - x) / r).max(0.0);
            (
                smootherstep(y),
                -smootherstep_slope(y) / r,
                (1.0 - r) - r * smootherstep_integral(y),
            )
        }
    }

    /// Heading of the canonical unit turn at x.
    fn unit_heading(&self, x: f64) -> f64 {
        self.turn_angle_scale * self.shape(x).2
    }

    /// ∫ (cos χ, sin χ) dx over [x0, x1] of the canonical unit turn, inside one smooth piece
    /// (Gauss–Legendre, 16 nodes: the integrand is entire and turns by at most π, so the rule
    /// is exact to rounding).
    fn unit_turn_piece(&self, x0: f64, x1: f64) -> Vector2<f64> {
        gauss_legendre_16(x0, x1, |x| {
            let c = self.unit_heading(x);
            Vector2::new(c.cos(), c.sin())
        })
    }

    fn planar(&self, tau: f64) -> Planar {
        let s = (self.speed * tau).rem_euclid(self.total_length);
        // Segment containing s (segments are sorted by s0).
        let idx = self
            .segments
            .partition_point(|seg| seg.s0 <= s)
            .saturating_sub(1);
        let seg = self.segments[idx];
        let u = (s - seg.s0).min(seg.length);
        let v0 = self.speed;
        let rot = |h: f64| Matrix2::new(h.cos(), -h.sin(), h.sin(), h.cos());
        if seg.turn == 0.0 {
            let dir = Vector2::new(seg.heading.cos(), seg.heading.sin());
            return Planar {
                p: seg.start + dir * u,
                v: dir * v0,
                a: Vector2::zeros(),
                j: Vector2::zeros(),
            };
        }
        let big_s = self.turn_length;
        let x = u / big_s;
        let r = self.ramp;
        let (piece, x_start) = if x <= r {
            (0, 0.0)
        } else if x < 1.0 - r {
            (1, r)
        } else {
            (2, 1.0 - r)
        };
        let unit_disp = self.piece_start[piece] + self.unit_turn_piece(x_start, x);
        let sigma = seg.turn;
        let frame = rot(seg.heading) * Matrix2::new(1.0, 0.0, 0.0, sigma);
        let (shape, shape_slope, _) = self.shape(x);
        let chi = seg.heading + sigma * self.unit_heading(x);
        let kappa = sigma * self.turn_angle_scale * shape / big_s;
        let kappa_s = sigma * self.turn_angle_scale * shape_slope / (big_s * big_s);
        let t = Vector2::new(chi.cos(), chi.sin());
        let nrm = Vector2::new(-chi.sin(), chi.cos());
        Planar {
            p: seg.start + frame * unit_disp * big_s,
            v: t * v0,
            a: nrm * (v0 * v0 * kappa),
            j: nrm * (v0 * v0 * v0 * kappa_s) - t * (v0 * v0 * v0 * kappa * kappa),
        }
    }
}

/// Lemniscate of Gerono r(θ) = (L/2·sin θ, W/2·sin 2θ) flown at constant speed: the arc length
/// s(θ) = ∫|r′| is tabulated at 256 nodes and completed by Gauss–Legendre quadrature, θ(s) is
/// found by Newton's method, and the curvature κ = (r′ × r″)/|r′|³ and dκ/ds follow from the
/// closed-form derivatives of r, giving v = V·T, a = V²κ·N, j = V³(κ_s·N − κ²·T).
#[derive(Clone, Debug)]
struct Gerono {
    speed: f64,
    half_length: f64,
    half_width: f64,
    /// s at θ_k = 2πk/K, k = 0..=K.
    arc: Vec<f64>,
}

/// Nodes of the arc-length table of [`Gerono`].
const GERONO_NODES: usize = 256;

impl Gerono {
    fn new(speed: f64, half_length: f64, half_width: f64) -> Self {
        let mut g = Self {
            speed,
            half_length,
            half_width,
            arc: vec![0.0; GERONO_NODES + 1],
        };
        let step = TAU / GERONO_NODES as f64;
        for k in 0..GERONO_NODES {
            let th = step * k as f64;
            g.arc[k + 1] = g.arc[k] + g.arc_piece(th, th + step);
        }
        g
    }

    fn perimeter(&self) -> f64 {
        self.arc[GERONO_NODES]
    }

    /// r′(θ), r″(θ), r‴(θ).
    fn derivatives(&self, th: f64) -> [Vector2<f64>; 3] {
        let (l, h) = (self.half_length, self.half_width);
        let (s1, c1) = th.sin_cos();
        let (s2, c2) = (2.0 * th).sin_cos();
        [
            Vector2::new(l * c1, 2.0 * h * c2),
            Vector2::new(-l * s1, -4.0 * h * s2),
            Vector2::new(-l * c1, -8.0 * h * c2),
        ]
    }

    /// ∫ |r′| dθ over [a, b] (one table piece or less: the integrand is smooth, 16 nodes give
    /// rounding-level accuracy).
    fn arc_piece(&self, a: f64, b: f64) -> f64 {
        gauss_legendre_16(a, b, |th| Vector2::new(self.derivatives(th)[0].norm(), 0.0)).x
    }

    /// θ ∈ [0, 2π) at arc length s ∈ [0, perimeter).
    fn theta_at(&self, s: f64) -> f64 {
        let k = self.arc.partition_point(|&a| a <= s).clamp(1, GERONO_NODES) - 1;
        let step = TAU / GERONO_NODES as f64;
        let th0 = step * k as f64;
        let frac = (s - self.arc[k]) / (self.arc[k + 1] - self.arc[k]);
        let mut th = th0 + step * frac;
        for _ in 0..20 {
            let err = self.arc[k] + self.arc_piece(th0, th) - s;
            let d = err / self.derivatives(th)[0].norm();
            th -= d;
            // |r′| ≥ min speed scale > 0, so Newton converges quadratically from the linear guess.
            if d.abs() < 1e-14 {
                break;
            }
        }
        th
    }

    fn planar(&self, tau: f64) -> Planar {
        let s = (self.speed * tau).rem_euclid(self.perimeter());
        let th = self.theta_at(s);
        let [d1, d2, d3] = self.derivatives(th);
        let (l, h) = (self.half_length, self.half_width);
        let q = d1.norm();
        let cross = d1.x * d2.y - d1.y * d2.x;
        let kappa = cross / q.powi(3);
        let q_dot = d1.dot(&d2) / q;
        let cross_dot = d1.x * d3.y - d1.y * d3.x;
        let kappa_theta = (cross_dot * q - 3.0 * cross * q_dot) / q.powi(4);
        let kappa_s = kappa_theta / q;
        let t = d1 / q;
        let n = Vector2::new(-t.y, t.x);
        let v0 = self.speed;
        Planar {
            p: Vector2::new(l * th.sin(), h * (2.0 * th).sin()),
            v: t * v0,
            a: n * (v0 * v0 * kappa),
            j: n * (v0 * v0 * v0 * kappa_s) - t * (v0 * v0 * v0 * kappa * kappa),
        }
    }
}

/// 16-point Gauss–Legendre nodes on [−1, 1] and weights, by Newton iteration on P₁₆.
fn gauss_legendre_nodes() -> &'static ([f64; 16], [f64; 16]) {
    static NODES: std::sync::OnceLock<([f64; 16], [f64; 16])> = std::sync::OnceLock::new();
    NODES.get_or_init(|| {
        const N: usize = 16;
        let mut x = [0.0; N];
        let mut w = [0.0; N];
        for i in 0..N {
            let mut z = (PI * (i as f64 + 0.75) / (N as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                // Legendre recurrence for P_N(z) and P_{N−1}(z).
                let (mut p0, mut p1) = (1.0, z);
                for k in 2..=N {
                    let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = N as f64 * (z * p1 - p0) / (z * z - 1.0);
                let dz = p1 / dp;
                z -= dz;
                if dz.abs() < 1e-16 {
                    break;
                }
            }
            x[i] = z;
            w[i] = 2.0 / ((1.0 - z * z) * dp * dp);
        }
        (x, w)
    })
}

/// ∫_{a}^{b} f with the 16-point Gauss–Legendre rule (vector-valued).
fn gauss_legendre_16(a: f64, b: f64, f: impl Fn(f64) -> Vector2<f64>) -> Vector2<f64> {
    let (x, w) = gauss_legendre_nodes();
    let (mid, half) = (0.5 * (a + b), 0.5 * (b - a));
    let mut sum = Vector2::zeros();
    for i in 0..16 {
        sum += f(mid + half * x[i]) * w[i];
    }
    sum * half
}

/// Body rate relative to the launch frame from Ψ and Ψ̇ (inverse of eq. 21.8), for callers that
/// want ω_{n0 b}^b without the Euler-rate matrix.
pub fn body_rate(state: &FlightState) -> Vector3<f64> {
    canopy_fusion::rotation::body_rate_from_euler_rate(&state.attitude) * state.attitude_rate
}

/// The rotation C_b^{n0} of a flight state.
pub fn launch_from_body(state: &FlightState) -> Matrix3<f64> {
    canopy_fusion::rotation::nav_from_body(&state.attitude)
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_fusion::rotation::{nav_from_body, wrap_angle};

    fn lawnmower_cfg() -> TrajectoryConfig {
        TrajectoryConfig {
            centre_ne_m: [100.0, -300.0],
            altitude_m: 150.0,
            speed_mps: 25.0,
            phase: 0.1,
            heading_deg: 30.0,
            climb_amplitude_m: 10.0,
            climb_period_s: 90.0,
            shape: ShapeConfig::Lawnmower {
                leg_length_m: 800.0,
                leg_spacing_m: 220.0,
                legs: 4,
                turn_ramp_fraction: 0.4,
            },
        }
    }

    fn all_cfgs() -> Vec<(&'static str, TrajectoryConfig)> {
        let mut orbit = lawnmower_cfg();
        orbit.shape = ShapeConfig::Orbit {
            radius_m: 400.0,
            clockwise: false,
        };
        let mut eight = lawnmower_cfg();
        eight.shape = ShapeConfig::FigureEight {
            length_m: 1500.0,
            width_m: 700.0,
        };
        let mut level = lawnmower_cfg();
        level.climb_amplitude_m = 0.0;
        vec![
            ("lawnmower", lawnmower_cfg()),
            ("lawnmower-level", level),
            ("orbit", orbit),
            ("figure-eight", eight),
        ]
    }

    #[test]
    fn gauss_legendre_is_exact_for_degree_31_and_accurate_for_cosine() {
        // 16 nodes integrate polynomials up to degree 31 exactly: ∫₀¹ x³¹ = 1/32.
        let v = gauss_legendre_16(0.0, 1.0, |x| Vector2::new(x.powi(31), x.powi(10)));
        // Rounding of 16 terms near 1: a few ulps.
        assert!((v.x - 1.0 / 32.0).abs() < 1e-15, "{}", v.x - 1.0 / 32.0);
        assert!((v.y - 1.0 / 11.0).abs() < 1e-15);
        // ∫₀^π cos x dx = 0, ∫₀^π sin x dx = 2 (closed forms).
        let c = gauss_legendre_16(0.0, PI, |x| Vector2::new(x.cos(), x.sin()));
        assert!(c.x.abs() < 1e-14 && (c.y - 2.0).abs() < 1e-14, "{c:?}");
    }

    #[test]
    fn smootherstep_closed_forms_match_finite_differences() {
        // Step 1e-6: central-difference truncation ~1e-12·P‴ (≤ 60), round-off ~1e-10.
        let h = 1e-6;
        for &x in &[0.1, 0.37, 0.5, 0.81] {
            let fd = (smootherstep(x + h) - smootherstep(x - h)) / (2.0 * h);
            assert!((fd - smootherstep_slope(x)).abs() < 1e-8);
            let fi = (smootherstep_integral(x + h) - smootherstep_integral(x - h)) / (2.0 * h);
            assert!((fi - smootherstep(x)).abs() < 1e-8);
        }
        assert_eq!(smootherstep(1.0), 1.0);
        assert!((smootherstep_integral(1.0) - 0.5).abs() < 1e-15);
    }

    /// Central differences of p, v, a and Ψ reproduce v, a, j and Ψ̇ at many times, including
    /// the lawnmower's segment joins (where only continuity of the derivatives is guaranteed).
    #[test]
    fn derivatives_are_consistent_with_finite_differences() {
        for (name, cfg) in all_cfgs() {
            let traj = Trajectory::new(&cfg).unwrap();
            let n = 4000;
            // h = 1 ms: truncation h²/6·(next derivative) with |snap| ≲ 1 m/s⁴ → ~2e-7; round-off
            // of positions ~1e3 m: 1e-13/1e-3 = 1e-10.
            let h = 1e-3;
            let (mut ev, mut ea, mut ej, mut er) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
            for i in 0..n {
                let t = traj.period() * i as f64 / n as f64 + 0.0137;
                let (kp, km, k0) = (
                    traj.kinematics(t + h),
                    traj.kinematics(t - h),
                    traj.kinematics(t),
                );
                ev = ev.max(((kp.position - km.position) / (2.0 * h) - k0.velocity).norm());
                ea = ea.max(((kp.velocity - km.velocity) / (2.0 * h) - k0.acceleration).norm());
                ej = ej.max(((kp.acceleration - km.acceleration) / (2.0 * h) - k0.jerk).norm());
                let (sp, sm, s0) = (traj.state(t + h), traj.state(t - h), traj.state(t));
                let d = (sp.attitude - sm.attitude).map(wrap_angle) / (2.0 * h);
                er = er.max((d - s0.attitude_rate).norm());
            }
            eprintln!("{name}: max FD error v {ev:.2e} a {ea:.2e} j {ej:.2e} Ψ̇ {er:.2e}");
            // Bounds: 1e-5 leaves > 10× margin over the truncation estimates above (the snap is
            // continuous too: the smootherstep's second derivative vanishes at the ramp ends).
            assert!(ev < 1e-5, "{name}: v {ev}");
            assert!(ea < 1e-5, "{name}: a {ea}");
            assert!(ej < 1e-5, "{name}: j {ej}");
            assert!(er < 1e-5, "{name}: Ψ̇ {er}");
        }
    }

    /// Attitude is continuous with bounded rates: over a period, no step of 10 ms changes Ψ by
    /// more than the largest rate allows, and Ψ̇ itself has no jumps (body rates continuous).
    #[test]
    fn attitude_is_continuous_with_bounded_rates() {
        for (name, cfg) in all_cfgs() {
            let traj = Trajectory::new(&cfg).unwrap();
            let dt = 0.01;
            let n = (traj.period() / dt) as usize;
            let max_rate = traj.max_attitude_rates();
            // A coordinated UAV turn: roll rate and yaw rate well below 1 rad/s.
            assert!(max_rate.max() < 0.6, "{name}: rates {max_rate:?}");
            assert!(traj.max_bank() < MAX_BANK);
            let mut prev = traj.state(0.0);
            let mut max_rate_jump = 0.0f64;
            for i in 1..=n {
                let s = traj.state(i as f64 * dt);
                let d = (s.attitude - prev.attitude).map(wrap_angle);
                for k in 0..3 {
                    // Mean-value bound with 10 % slack for the sampled envelope.
                    assert!(
                        d[k].abs() <= 1.1 * max_rate[k] * dt + 1e-12,
                        "{name} step {i} axis {k}: {d}"
                    );
                }
                max_rate_jump = max_rate_jump.max((s.attitude_rate - prev.attitude_rate).norm());
                prev = s;
            }
            eprintln!(
                "{name}: period {:.1} s, max bank {:.1}°, max |Ψ̇| {:?} rad/s, max Ψ̇ jump per 10 ms {max_rate_jump:.2e}",
                traj.period(),
                traj.max_bank().to_degrees(),
                max_rate.as_slice()
            );
            // Continuous Ψ̇ with |Ψ̈| ≲ 0.5 rad/s² changes by < 5e-3 rad/s in 10 ms; a jump from a
            // curvature step (0.3 rad/s bank-rate step) would exceed it.
            assert!(max_rate_jump < 5e-3, "{name}: Ψ̇ jump {max_rate_jump}");
        }
    }

    /// The lawnmower is periodic and flies the configured legs: after one period the state
    /// repeats, and straight flight happens on the lines y = (j − (n−1)/2)·spacing.
    #[test]
    fn lawnmower_geometry_and_periodicity() {
        let mut cfg = lawnmower_cfg();
        cfg.phase = 0.0;
        cfg.climb_amplitude_m = 0.0;
        cfg.heading_deg = 0.0;
        cfg.centre_ne_m = [0.0, 0.0];
        let traj = Trajectory::new(&cfg).unwrap();
        let (a, b) = (traj.state(3.0), traj.state(3.0 + traj.period()));
        // Rounding of p = V·t mod total length over ~10³ m: 1e-9 m.
        assert!((a.kinematics.position - b.kinematics.position).norm() < 1e-9);
        // Leg 0 at t = 1 s: heading north at y = −1.5·220, x = −400 + 25.
        let k = traj.kinematics(1.0);
        assert!((k.position - Vector3::new(-375.0, -330.0, -150.0)).norm() < 1e-9);
        // End of the first turn (start of leg 1): x = 400, y = −110, heading south. Quadrature
        // of the turn is exact to rounding; 1e-9 m.
        let Shape::Lawnmower(lm) = &traj.shape else {
            unreachable!()
        };
        let t_leg1 = (800.0 + lm.turn_length) / 25.0;
        let k = traj.kinematics(t_leg1 + 0.5);
        assert!(
            (k.position - Vector3::new(400.0 - 12.5, -110.0, -150.0)).norm() < 1e-9,
            "{:?}",
            k.position
        );
        assert!((k.velocity - Vector3::new(-25.0, 0.0, 0.0)).norm() < 1e-9);
        // Mid-turn the heading is east (the turn is a right turn from north) and the curvature
        // is κ_max = π/((1 − r)S).
        let mid = traj.state(t_leg1 - 0.5 * lm.turn_length / 25.0);
        assert!((mid.attitude.z - PI / 2.0).abs() < 1e-9);
        let kappa = PI / (0.6 * lm.turn_length);
        assert!((mid.kinematics.acceleration.norm() - 625.0 * kappa).abs() < 1e-9);
        assert!(mid.attitude.x > 0.0, "right turn banks right");
    }

    /// Orbit: closed-form coordinated turn — bank tan φ = V²/(R g), yaw rate ∓V/R, and the body
    /// y axis carries no specific force.
    #[test]
    fn orbit_matches_the_closed_form_coordinated_turn() {
        let cfg = TrajectoryConfig {
            climb_amplitude_m: 0.0,
            shape: ShapeConfig::Orbit {
                radius_m: 300.0,
                clockwise: false,
            },
            ..TrajectoryConfig::default()
        };
        let traj = Trajectory::new(&cfg).unwrap();
        let s = traj.state(17.0);
        let bank = (25.0f64 * 25.0 / (300.0 * DESIGN_GRAVITY)).atan();
        assert!((s.attitude.x + bank).abs() < 1e-12, "left turn banks left");
        assert!((s.attitude_rate.z + 25.0 / 300.0).abs() < 1e-12);
        assert!(s.attitude.y.abs() < 1e-15 && s.attitude_rate.x.abs() < 1e-12);
        let f = s.kinematics.acceleration - Vector3::new(0.0, 0.0, DESIGN_GRAVITY);
        let fb = nav_from_body(&s.attitude).transpose() * f;
        assert!(
            fb.x.abs() < 1e-12 && fb.y.abs() < 1e-12 && fb.z < 0.0,
            "{fb:?}"
        );
        assert!((traj.period() - TAU * 300.0 / 25.0).abs() < 1e-9);
    }

    /// The figure-eight is flown at the configured constant speed along the lemniscate of
    /// Gerono: |v| = V everywhere, the positions lie on the curve, the chord sum over a period
    /// equals V·period, and it crosses itself at the centre.
    #[test]
    fn figure_eight_has_constant_speed_on_the_lemniscate() {
        let mut cfg = all_cfgs().remove(3).1;
        cfg.heading_deg = 0.0;
        cfg.centre_ne_m = [0.0, 0.0];
        cfg.phase = 0.0;
        let traj = Trajectory::new(&cfg).unwrap();
        let n = 20_000;
        let mut dist = 0.0;
        let mut prev = traj.kinematics(0.0).position;
        let (hl, hw) = (750.0, 350.0);
        for i in 1..=n {
            let k = traj.kinematics(traj.period() * i as f64 / n as f64);
            assert!((k.velocity.xy().norm() - 25.0).abs() < 1e-12);
            // On the curve: y = W/2·sin 2θ = 2·(W/2)·(x/(L/2))·cos θ ⇒ y² = W²x²(1 − x²/(L/2)²)/(L/2)².
            let (x, y) = (k.position.x, k.position.y);
            let u = x / hl;
            assert!(
                (y * y - 4.0 * hw * hw * u * u * (1.0 - u * u)).abs() < 1e-6,
                "{x} {y}"
            );
            dist += (k.position - prev).xy().norm();
            prev = k.position;
        }
        // The chord sum underestimates the arc by ~(chord κ)²/24 ≈ 1e-8 relative.
        assert!(
            (dist / traj.period() - 25.0).abs() < 1e-5,
            "{}",
            dist / traj.period()
        );
        assert!(
            traj.kinematics(0.0).position.xy().norm() < 1e-9,
            "starts at the crossing"
        );
        assert!(traj.kinematics(0.5 * traj.period()).position.xy().norm() < 1e-9);
    }

    #[test]
    fn too_tight_turns_are_rejected_naming_the_field() {
        let mut cfg = lawnmower_cfg();
        cfg.shape = ShapeConfig::Lawnmower {
            leg_length_m: 800.0,
            leg_spacing_m: 40.0,
            legs: 3,
            turn_ramp_fraction: 0.4,
        };
        match Trajectory::new(&cfg) {
            Err(ScenarioError::Invalid { field, reason }) => {
                assert_eq!(field, "shape.leg_spacing_m");
                assert!(reason.contains("bank"), "{reason}");
            }
            other => panic!("expected a bank error, got {other:?}"),
        }
        let mut cfg = lawnmower_cfg();
        cfg.speed_mps = f64::NAN;
        assert!(
            matches!(Trajectory::new(&cfg), Err(ScenarioError::Invalid { field, .. }) if field == "speed_mps")
        );
    }
}
