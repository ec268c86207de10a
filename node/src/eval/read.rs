//! Trajectory files: TUM (`timestamp tx ty tz qx qy qz qw`) and the EuRoC/ASL ground-truth CSV
//! (`state_groundtruth_estimate0/data.csv`: `timestamp [ns], p_RS_R xyz, q_RS wxyz, …`).
//!
//! The rules are evo's (`evo.tools.file_interface.read_tum_trajectory_file`,
//! `read_euroc_csv_trajectory`), stated here once:
//! * a line whose first non-blank character is `#` is a comment; blank lines are skipped (evo
//!   rejects them; accepting them changes no file evo accepts);
//! * TUM: exactly 8 fields separated by white space (evo: single spaces; any run of spaces or
//!   tabs is accepted here), timestamp in seconds, position, quaternion x y z w (Hamilton);
//! * EuRoC CSV: at least 8 comma-separated fields, timestamp in integer nanoseconds, position,
//!   quaternion **w x y z**; the columns after the 8th (velocity, biases) are not read;
//! * a UTF-8 byte-order mark at the start is skipped (as evo does).
//!
//! What evo accepts silently but is rejected here with the file, the line and the reason: a
//! truncated line, a field that is not a number, NaN or infinity, a timestamp not after the
//! previous one (evo's `check()` wants strictly ascending stamps too), and a quaternion whose
//! norm is off 1 by more than [`QUATERNION_NORM_TOLERANCE`] (evo normalises whatever it reads).
//! Quaternions within the tolerance are normalised. Timestamps stay in the file's own time base.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use super::{StampedPose, Trajectory};

/// How far a quaternion's norm may be from 1 before the line is rejected. Files printed with
/// four or more decimals per component stay within 2e-4; a typo, a swapped column or an
/// unnormalised quaternion is off by far more.
pub const QUATERNION_NORM_TOLERANCE: f64 = 1e-3;

/// The two file layouts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrajectoryFormat {
    /// `timestamp tx ty tz qx qy qz qw`, space separated, seconds.
    Tum,
    /// EuRoC/ASL CSV: `timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z, …`.
    EurocCsv,
}

impl TrajectoryFormat {
    /// The field names of a line, in file order (the first 8).
    fn fields(self) -> [&'static str; 8] {
        match self {
            Self::Tum => ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"],
            Self::EurocCsv => [
                "timestamp [ns]",
                "p_RS_R_x",
                "p_RS_R_y",
                "p_RS_R_z",
                "q_RS_w",
                "q_RS_x",
                "q_RS_y",
                "q_RS_z",
            ],
        }
    }

    fn layout(self) -> &'static str {
        match self {
            Self::Tum => "TUM: timestamp tx ty tz qx qy qz qw",
            Self::EurocCsv => "EuRoC CSV: timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z, …",
        }
    }
}

/// What is wrong with one line (or one pose given through the API).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LineProblem {
    /// Fewer fields than the layout needs.
    #[error("truncated line: {found} of {expected} fields ({layout})")]
    Truncated {
        /// Fields found.
        found: usize,
        /// Fields needed.
        expected: usize,
        /// The layout.
        layout: &'static str,
    },
    /// More fields than a TUM line has.
    #[error("{found} fields, a TUM line has exactly 8 ({layout})")]
    TooManyFields {
        /// Fields found.
        found: usize,
        /// The layout.
        layout: &'static str,
    },
    /// A field that does not parse as a number.
    #[error("{field} `{text}` is not a number")]
    NotANumber {
        /// The field's name.
        field: &'static str,
        /// Its text.
        text: String,
    },
    /// NaN or infinite.
    #[error("{field} is {value}, not a finite number")]
    NotFinite {
        /// The field's name.
        field: &'static str,
        /// Its value.
        value: f64,
    },
    /// A timestamp not after the previous pose's.
    #[error(
        "timestamp {t} s is not after the previous pose's {previous} s (timestamps must \
         increase strictly)"
    )]
    NotIncreasing {
        /// This pose's timestamp [s].
        t: f64,
        /// The previous pose's [s].
        previous: f64,
    },
    /// A quaternion too far from unit norm.
    #[error(
        "quaternion (w {w}, x {x}, y {y}, z {z}) has norm {norm}, more than {tolerance} from 1"
    )]
    NotUnitQuaternion {
        /// Scalar part.
        w: f64,
        /// Vector part x.
        x: f64,
        /// Vector part y.
        y: f64,
        /// Vector part z.
        z: f64,
        /// Its norm.
        norm: f64,
        /// The tolerance ([`QUATERNION_NORM_TOLERANCE`]).
        tolerance: f64,
    },
}

/// A trajectory file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// The file cannot be read.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// A bad line.
    #[error("{}:{line}: {problem}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        problem: LineProblem,
    },
    /// No pose at all.
    #[error("{}: no poses (only comments or blank lines)", path.display())]
    Empty {
        /// The file.
        path: PathBuf,
    },
}

/// Reads a trajectory file, TUM or EuRoC CSV ([`detect_format`]).
pub fn load(path: &Path) -> Result<Trajectory, ReadError> {
    let text = std::fs::read_to_string(path).map_err(|source| ReadError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse(&text, path, None)
}

/// The layout of a file's text: EuRoC CSV if its first non-comment line has a comma, else TUM.
pub fn detect_format(text: &str) -> TrajectoryFormat {
    match data_lines(text).next() {
        Some((_, line)) if line.contains(',') => TrajectoryFormat::EurocCsv,
        _ => TrajectoryFormat::Tum,
    }
}

/// The non-comment, non-blank lines with their 1-based numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    text.lines().enumerate().filter_map(|(i, line)| {
        let t = line.trim();
        (!t.is_empty() && !t.starts_with('#')).then_some((i + 1, t))
    })
}

/// Parses a trajectory from text; `path` names it in errors; `format` `None` detects it.
pub fn parse(
    text: &str,
    path: &Path,
    format: Option<TrajectoryFormat>,
) -> Result<Trajectory, ReadError> {
    let format = format.unwrap_or_else(|| detect_format(text));
    let mut poses: Vec<StampedPose> = Vec::new();
    for (line, content) in data_lines(text) {
        let err = |problem| ReadError::Line {
            path: path.to_path_buf(),
            line,
            problem,
        };
        let pose = parse_line(content, format).map_err(err)?;
        if let Some(prev) = poses.last()
            && pose.t <= prev.t
        {
            return Err(err(LineProblem::NotIncreasing {
                t: pose.t,
                previous: prev.t,
            }));
        }
        poses.push(pose);
    }
    if poses.is_empty() {
        return Err(ReadError::Empty {
            path: path.to_path_buf(),
        });
    }
    Ok(Trajectory::from_checked(poses))
}

/// One data line → a pose.
fn parse_line(line: &str, format: TrajectoryFormat) -> Result<StampedPose, LineProblem> {
    let fields: Vec<&str> = match format {
        TrajectoryFormat::Tum => line.split_ascii_whitespace().collect(),
        TrajectoryFormat::EurocCsv => line.split(',').map(str::trim).collect(),
    };
    let names = format.fields();
    if fields.len() < names.len() {
        return Err(LineProblem::Truncated {
            found: fields.len(),
            expected: names.len(),
            layout: format.layout(),
        });
    }
    if format == TrajectoryFormat::Tum && fields.len() > names.len() {
        return Err(LineProblem::TooManyFields {
            found: fields.len(),
            layout: format.layout(),
        });
    }
    let t = match format {
        TrajectoryFormat::Tum => number(names[0], fields[0])?,
        TrajectoryFormat::EurocCsv => nanoseconds_to_seconds(names[0], fields[0])?,
    };
    let mut v = [0.0; 7];
    for (k, slot) in v.iter_mut().enumerate() {
        *slot = number(names[k + 1], fields[k + 1])?;
    }
    let [x, y, z, q0, q1, q2, q3] = v;
    let (w, qx, qy, qz) = match format {
        TrajectoryFormat::Tum => (q3, q0, q1, q2),
        TrajectoryFormat::EurocCsv => (q0, q1, q2, q3),
    };
    let world_from_body = isometry(x, y, z, w, qx, qy, qz)?;
    Ok(StampedPose { t, world_from_body })
}

/// A finite number.
fn number(field: &'static str, text: &str) -> Result<f64, LineProblem> {
    let value: f64 = text.parse().map_err(|_| LineProblem::NotANumber {
        field,
        text: text.to_string(),
    })?;
    finite(field, value)
}

fn finite(field: &'static str, value: f64) -> Result<f64, LineProblem> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(LineProblem::NotFinite { field, value })
    }
}

/// EuRoC nanoseconds → seconds. Integer stamps (~1.4e18 ns, beyond f64's 2^53) are split into
/// whole seconds and the remainder so the seconds keep every digit f64 can hold; a decimal or
/// exponent form is read as a float (evo reads every stamp as a float).
fn nanoseconds_to_seconds(field: &'static str, text: &str) -> Result<f64, LineProblem> {
    match text.parse::<i64>() {
        Ok(ns) => {
            let (s, rem) = (ns.div_euclid(1_000_000_000), ns.rem_euclid(1_000_000_000));
            Ok(s as f64 + rem as f64 * 1e-9)
        }
        Err(_) => number(field, text).map(|ns| ns * 1e-9),
    }
}

/// A pose from a position and a quaternion within [`QUATERNION_NORM_TOLERANCE`] of unit norm
/// (normalised).
pub(super) fn isometry(
    x: f64,
    y: f64,
    z: f64,
    w: f64,
    qx: f64,
    qy: f64,
    qz: f64,
) -> Result<Isometry3<f64>, LineProblem> {
    let q = Quaternion::new(w, qx, qy, qz);
    let norm = q.norm();
    // The components are finite; an overflowing norm (inf) fails this too.
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(LineProblem::NotUnitQuaternion {
            w,
            x: qx,
            y: qy,
            z: qz,
            norm,
            tolerance: QUATERNION_NORM_TOLERANCE,
        });
    }
    Ok(Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_quaternion(q),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn problem(text: &str) -> (usize, LineProblem) {
        match parse(text, Path::new("f.tum"), None) {
            Err(ReadError::Line { line, problem, .. }) => (line, problem),
            other => panic!("expected a line error, got {other:?}"),
        }
    }

    #[test]
    fn tum_lines_comments_and_quaternion_order() {
        let text = "\u{feff}# header\n\n1.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n  \
                    # indented comment\n2.5\t4 5 6   0 0 0 1\n";
        let tr = parse(text, Path::new("a.tum"), None).unwrap();
        assert_eq!(tr.len(), 2);
        let p = &tr.poses()[0];
        assert_eq!(p.t, 1.5);
        assert_eq!(
            p.world_from_body.translation.vector.as_slice(),
            &[1.0, 2.0, 3.0]
        );
        // qz = qw = √½: 90° about z (x y z w order); the body x axis points along world y.
        let x_body = p.world_from_body.rotation * nalgebra::Vector3::x();
        assert!((x_body - nalgebra::Vector3::y()).norm() < 1e-15, "{x_body}"); // round-off only
        assert_eq!(tr.poses()[1].t, 2.5);
    }

    #[test]
    fn euroc_nanoseconds_and_wxyz() {
        let text = "#timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z, v_x\n\
                    1403715273262142000,1,2,3,0.7071067811865476,0.7071067811865476,0,0,9\n\
                    1403715273312142000,1,2,3,1,0,0,0,9\n";
        assert_eq!(detect_format(text), TrajectoryFormat::EurocCsv);
        let tr = parse(text, Path::new("data.csv"), None).unwrap();
        // Whole seconds and the remainder: exact to f64's spacing at 1.4e9 s (2.4e-7 s).
        assert!((tr.poses()[0].t - 1_403_715_273.262_142).abs() < 3e-7);
        assert!((tr.poses()[1].t - tr.poses()[0].t - 0.05).abs() < 5e-7);
        // w first: 90° about x; the body y axis points along world z.
        let y_body = tr.poses()[0].world_from_body.rotation * nalgebra::Vector3::y();
        assert!((y_body - nalgebra::Vector3::z()).norm() < 1e-15, "{y_body}"); // round-off only
    }

    #[test]
    fn bad_lines_name_the_line_and_the_reason() {
        let ok = "1 0 0 0 0 0 0 1\n";
        let (line, p) = problem(&format!("{ok}2 0 0 0 0 0 1\n"));
        assert_eq!(line, 2);
        assert!(
            matches!(
                p,
                LineProblem::Truncated {
                    found: 7,
                    expected: 8,
                    ..
                }
            ),
            "{p}"
        );
        let (_, p) = problem("1 0 0 0 0 0 0 1 9\n");
        assert!(
            matches!(p, LineProblem::TooManyFields { found: 9, .. }),
            "{p}"
        );
        let (_, p) = problem("1 0 0 x 0 0 0 1\n");
        assert_eq!(
            p,
            LineProblem::NotANumber {
                field: "tz",
                text: "x".into()
            }
        );
        let (_, p) = problem("1 0 NaN 0 0 0 0 1\n");
        assert!(
            matches!(p, LineProblem::NotFinite { field: "ty", .. }),
            "{p}"
        );
        let (line, p) = problem(&format!("# c\n{ok}1 0 0 0 0 0 0 1\n"));
        assert_eq!(line, 3);
        assert_eq!(
            p,
            LineProblem::NotIncreasing {
                t: 1.0,
                previous: 1.0
            }
        );
        let (_, p) = problem("1 0 0 0 0 0 0 1.01\n");
        assert!(matches!(p, LineProblem::NotUnitQuaternion { .. }), "{p}");
        // Within the tolerance: accepted and normalised.
        let tr = parse("1 0 0 0 0 0 0 1.0005\n", Path::new("f"), None).unwrap();
        assert!((tr.poses()[0].world_from_body.rotation.norm() - 1.0).abs() < 1e-15);
        let msg = parse("# only\n\n", Path::new("e.tum"), None)
            .unwrap_err()
            .to_string();
        assert_eq!(msg, "e.tum: no poses (only comments or blank lines)");
        let msg = parse("1,0,0,0,1,0,0\n", Path::new("gt.csv"), None)
            .unwrap_err()
            .to_string();
        assert!(
            msg.starts_with("gt.csv:1: truncated line: 7 of 8 fields (EuRoC CSV"),
            "{msg}"
        );
    }
}
