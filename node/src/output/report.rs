//! `report.html`: one self-contained page with SVG plots (plotters' SVG backend, no fonts or
//! scripts needed): trajectories and map against truth, position error with ±3σ, NEES with χ²
//! bounds, per-link bandwidth, and the fault timeline.

use super::summary::{Summary, chi2_band, table};
use crate::record::RunRecord;
use plotters::prelude::*;

type PlotResult = Result<(), Box<dyn std::error::Error>>;

const W: u32 = 900;
const H: u32 = 380;

fn palette(i: usize) -> RGBColor {
    const C: [RGBColor; 8] = [
        RGBColor(31, 119, 180),
        RGBColor(255, 127, 14),
        RGBColor(44, 160, 44),
        RGBColor(214, 39, 40),
        RGBColor(148, 103, 189),
        RGBColor(140, 86, 75),
        RGBColor(227, 119, 194),
        RGBColor(23, 190, 207),
    ];
    C[i % C.len()]
}

fn range(vals: impl Iterator<Item = f64>) -> (f64, f64) {
    let (lo, hi) = vals
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-6);
    (lo - pad, hi + pad)
}

fn svg(
    draw: impl FnOnce(DrawingArea<SVGBackend<'_>, plotters::coord::Shift>) -> PlotResult,
    h: u32,
) -> String {
    let mut s = String::new();
    {
        let root = SVGBackend::with_string(&mut s, (W, h)).into_drawing_area();
        if let Err(e) = root
            .fill(&WHITE)
            .map_err(|e| e.to_string())
            .and_then(|_| draw(root.clone()).map_err(|e| e.to_string()))
        {
            return format!("<p>plot failed: {e}</p>");
        }
        let _ = root.present();
    }
    s
}

fn trajectories(run: &RunRecord) -> String {
    svg(
        |root| {
            let xs = run.vehicles.iter().flat_map(|v| {
                v.samples
                    .iter()
                    .flat_map(|s| [s.truth_pos[1], s.est_pos[1]])
            });
            let ys = run.vehicles.iter().flat_map(|v| {
                v.samples
                    .iter()
                    .flat_map(|s| [s.truth_pos[0], s.est_pos[0]])
            });
            let fx = run.truth_features.iter().map(|f| f.1[1]);
            let fy = run.truth_features.iter().map(|f| f.1[0]);
            let (x0, x1) = range(xs.chain(fx));
            let (y0, y1) = range(ys.chain(fy));
            let mut c = ChartBuilder::on(&root)
                .caption("Trajectories and map (east–north, launch frame): solid = estimate, thin = truth; × = true feature, o = estimated feature", ("sans-serif", 14))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(55)
                .build_cartesian_2d(x0..x1, y0..y1)?;
            c.configure_mesh()
                .x_desc("east [m]")
                .y_desc("north [m]")
                .draw()?;
            c.draw_series(
                run.truth_features
                    .iter()
                    .map(|f| Cross::new((f.1[1], f.1[0]), 3, BLACK.mix(0.5))),
            )?;
            for (i, v) in run.vehicles.iter().enumerate() {
                let col = palette(i);
                c.draw_series(LineSeries::new(
                    v.samples.iter().map(|s| (s.truth_pos[1], s.truth_pos[0])),
                    col.mix(0.35),
                ))?;
                c.draw_series(LineSeries::new(
                    v.samples.iter().map(|s| (s.est_pos[1], s.est_pos[0])),
                    col.stroke_width(2),
                ))?
                .label(v.name.clone())
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], col.stroke_width(2))
                });
                c.draw_series(
                    v.map
                        .iter()
                        .map(|f| Circle::new((f.est[1], f.est[0]), 2, col.mix(0.8))),
                )?;
            }
            c.configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()?;
            Ok(())
        },
        560,
    )
}

fn errors(run: &RunRecord) -> String {
    let mut out = String::new();
    for v in &run.vehicles {
        out.push_str(&svg(
            |root| {
                let t1 = v.samples.last().map_or(1.0, |s| s.t);
                let t0 = v.samples.first().map_or(0.0, |s| s.t);
                let bound = v
                    .samples
                    .iter()
                    .flat_map(|s| (0..3).map(move |i| 3.0 * s.sigma(i)));
                let errs = v
                    .samples
                    .iter()
                    .flat_map(|s| (0..3).map(move |i| (s.est_pos[i] - s.truth_pos[i]).abs()));
                let (_, m) = range(bound.chain(errs));
                let mut c = ChartBuilder::on(&root)
                    .caption(
                        format!(
                            "{}: position error per axis (solid) and ±3σ (dashed)",
                            v.name
                        ),
                        ("sans-serif", 14),
                    )
                    .margin(10)
                    .x_label_area_size(35)
                    .y_label_area_size(55)
                    .build_cartesian_2d(t0..t1.max(t0 + 1e-3), -m..m)?;
                c.configure_mesh()
                    .x_desc("t [s]")
                    .y_desc("error [m]")
                    .draw()?;
                for (i, axis) in ["north", "east", "down"].iter().enumerate() {
                    let col = palette(i);
                    c.draw_series(LineSeries::new(
                        v.samples
                            .iter()
                            .map(|s| (s.t, s.est_pos[i] - s.truth_pos[i])),
                        col,
                    ))?
                    .label(*axis)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], col));
                    for sign in [-1.0, 1.0] {
                        c.draw_series(DashedLineSeries::new(
                            v.samples.iter().map(|s| (s.t, sign * 3.0 * s.sigma(i))),
                            4,
                            4,
                            col.mix(0.6).into(),
                        ))?;
                    }
                }
                c.configure_series_labels()
                    .background_style(WHITE.mix(0.8))
                    .border_style(BLACK)
                    .draw()?;
                Ok(())
            },
            H,
        ));
    }
    out
}

fn nees(run: &RunRecord) -> String {
    svg(
        |root| {
            let (lo, hi) = chi2_band(6.0);
            let all = run.vehicles.iter().chain(run.baseline.iter().flatten());
            let t1 = all
                .clone()
                .filter_map(|v| v.samples.last())
                .map(|s| s.t)
                .fold(1.0, f64::max);
            let ymax = all
                .flat_map(|v| v.samples.iter().map(|s| s.nees_pose))
                .fold(hi * 1.5, f64::max)
                .min(hi * 20.0);
            let mut c = ChartBuilder::on(&root)
                .caption("Pose NEES (6 dof) with the per-sample χ²₆ 95 % interval (dashed); clipped at 20× the upper bound", ("sans-serif", 14))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(55)
                .build_cartesian_2d(0.0..t1, 0.0..ymax)?;
            c.configure_mesh().x_desc("t [s]").y_desc("NEES").draw()?;
            for b in [lo, hi] {
                c.draw_series(DashedLineSeries::new(
                    [(0.0, b), (t1, b)],
                    6,
                    4,
                    BLACK.into(),
                ))?;
            }
            for (i, v) in run.vehicles.iter().enumerate() {
                let col = palette(i);
                c.draw_series(LineSeries::new(
                    v.samples.iter().map(|s| (s.t, s.nees_pose.min(ymax))),
                    col,
                ))?
                .label(v.name.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], col));
            }
            for (i, v) in run.baseline.iter().flatten().enumerate() {
                let col = palette(i).mix(0.4);
                c.draw_series(LineSeries::new(
                    v.samples.iter().map(|s| (s.t, s.nees_pose.min(ymax))),
                    col,
                ))?
                .label(format!("{} (central EKF)", v.name))
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], col));
            }
            c.configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()?;
            Ok(())
        },
        H,
    )
}

fn bandwidth(run: &RunRecord) -> String {
    svg(
        |root| {
            let rates: Vec<(String, Vec<(f64, f64)>)> = run
                .links
                .iter()
                .map(|l| {
                    let pts = l
                        .samples
                        .windows(2)
                        .map(|w| {
                            let dt = (w[1].t - w[0].t).max(1e-9);
                            let db = (w[1].bytes_ab + w[1].bytes_ba)
                                .saturating_sub(w[0].bytes_ab + w[0].bytes_ba);
                            (w[1].t, db as f64 / dt / 1024.0)
                        })
                        .collect();
                    (format!("{}-{}", l.a, l.b), pts)
                })
                .collect();
            let t1 = rates
                .iter()
                .flat_map(|r| r.1.iter().map(|p| p.0))
                .fold(1.0, f64::max);
            let (_, ymax) = range(
                rates
                    .iter()
                    .flat_map(|r| r.1.iter().map(|p| p.1))
                    .chain([0.0]),
            );
            let mut c = ChartBuilder::on(&root)
                .caption(
                    "Per-link bandwidth, both directions [KiB/s of simulated time]",
                    ("sans-serif", 14),
                )
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(55)
                .build_cartesian_2d(0.0..t1, 0.0..ymax.max(1e-3))?;
            c.configure_mesh().x_desc("t [s]").y_desc("KiB/s").draw()?;
            for (i, (name, pts)) in rates.into_iter().enumerate() {
                let col = palette(i);
                c.draw_series(LineSeries::new(pts, col))?
                    .label(name)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], col));
            }
            c.configure_series_labels()
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()?;
            Ok(())
        },
        H,
    )
}

fn timeline(run: &RunRecord) -> String {
    let mut rows: Vec<String> = run
        .links
        .iter()
        .map(|l| format!("{}-{}", l.a, l.b))
        .collect();
    for e in &run.events {
        if !rows.contains(&e.subject) {
            rows.push(e.subject.clone());
        }
    }
    let h = (80 + 28 * rows.len() as u32).max(160);
    svg(
        |root| {
            let t1 = run.duration.max(1.0);
            let n = rows.len().max(1) as f64;
            let mut c = ChartBuilder::on(&root)
                .caption("Fault timeline: link down (red), events (orange bars / markers); green = link up", ("sans-serif", 14))
                .margin(10)
                .x_label_area_size(35)
                .y_label_area_size(110)
                .build_cartesian_2d(0.0..t1, 0.0..n)?;
            let labels = rows.clone();
            c.configure_mesh()
                .x_desc("t [s]")
                // Ticks every half row; a row's name goes on the tick at its centre (y + 0.5),
                // where its bar is drawn.
                .y_labels(2 * rows.len().max(1) + 1)
                .y_label_formatter(&move |y| {
                    let centre = (y - y.floor() - 0.5).abs() < 1e-6;
                    match (centre, labels.get(y.floor() as usize)) {
                        (true, Some(l)) => l.clone(),
                        _ => String::new(),
                    }
                })
                .disable_y_mesh()
                .draw()?;
            for (row, l) in run.links.iter().enumerate() {
                let y = row as f64;
                for w in l.samples.windows(2) {
                    let col = if w[0].up {
                        GREEN.mix(0.5)
                    } else {
                        RED.mix(0.8)
                    };
                    c.draw_series([Rectangle::new(
                        [(w[0].t, y + 0.3), (w[1].t, y + 0.7)],
                        col.filled(),
                    )])?;
                }
            }
            for e in &run.events {
                let row = rows.iter().position(|r| r == &e.subject).unwrap_or(0) as f64;
                let until = e.until.unwrap_or(e.t + t1 * 0.004);
                c.draw_series([Rectangle::new(
                    [(e.t, row + 0.15), (until, row + 0.85)],
                    RGBColor(255, 140, 0).mix(0.6).filled(),
                )])?;
                c.draw_series([Text::new(
                    e.kind.clone(),
                    (e.t, row + 0.95),
                    ("sans-serif", 11),
                )])?;
            }
            Ok(())
        },
        h,
    )
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// The table of rejected estimator inputs by reason and vehicle (nothing when none were).
fn rejections(summary: &Summary) -> String {
    let reasons: std::collections::BTreeSet<&String> = summary
        .vehicles
        .iter()
        .flat_map(|v| v.rejections.keys())
        .collect();
    if reasons.is_empty() {
        return String::new();
    }
    let mut html = String::from("<h2>Rejected inputs by reason</h2><table><tr><th>reason</th>");
    for v in &summary.vehicles {
        html.push_str(&format!("<th>{}</th>", escape(&v.name)));
    }
    html.push_str("</tr>");
    for r in reasons {
        html.push_str(&format!("<tr><td><code>{}</code></td>", escape(r)));
        for v in &summary.vehicles {
            html.push_str(&format!(
                "<td style=\"text-align:right\">{}</td>",
                v.rejections.get(r).copied().unwrap_or(0)
            ));
        }
        html.push_str("</tr>");
    }
    html.push_str("</table>");
    html
}

/// The table of what zenoh access control refused — the vehicles' listening sessions, and the
/// router in client mode (nothing when nothing was).
fn access_refused(summary: &Summary) -> String {
    let mut rows = String::new();
    let router = ("router".to_string(), &summary.router_access_refused);
    for (name, refused) in summary
        .vehicles
        .iter()
        .map(|v| (v.name.clone(), &v.access_refused))
        .chain(std::iter::once(router))
    {
        for (what, n) in refused {
            rows.push_str(&format!(
                "<tr><td>{}</td><td><code>{}</code></td><td style=\"text-align:right\">{n}</td></tr>",
                escape(&name),
                escape(what)
            ));
        }
    }
    if rows.is_empty() {
        return String::new();
    }
    format!(
        "<h2>Refused by zenoh access control</h2><p>Messages and declarations of sessions \
         using a key of a link they are not part of (a non-neighbour, or a forged sender), \
         refused by the vehicle's listening session or, in client mode, by the zenoh router.\
         </p><table><tr><th>refused at</th><th>refused</th><th>count</th></tr>{rows}</table>"
    )
}

/// The table of association against the truth, per vehicle (`crate::truth`).
fn association(summary: &Summary) -> String {
    let mut html = format!(
        "<h2>Association against the truth</h2><p>identity <b>{}</b>; a key stands for the \
         majority true feature of its first owner's observations; a feature is mature when held \
         ≥ {} s before the end.</p><table><tr><th>vehicle</th><th>observations</th>\
         <th>wrong associations</th><th>duplicates</th><th>mature duplicates / mature</th>\
         <th>unmatched</th><th>merges adopted (cross-vehicle)</th><th>wrong merges \
         (cross-vehicle)</th><th>merges refused</th><th>unaudited frames</th></tr>",
        escape(if summary.identity.is_empty() {
            "-"
        } else {
            &summary.identity
        }),
        crate::truth::MATURE_S
    );
    let cell = |v: String| format!("<td style=\"text-align:right\">{v}</td>");
    for v in &summary.vehicles {
        html.push_str(&format!("<tr><td>{}</td>", escape(&v.name)));
        let (obs, v) = (v.observations, &v.association);
        for c in [
            obs.to_string(),
            v.wrong_associations.to_string(),
            v.duplicate_features.to_string(),
            format!("{} / {}", v.mature_duplicates, v.mature_features),
            v.unmatched_features.to_string(),
            format!("{} ({})", v.merges_adopted, v.merges_cross_vehicle),
            format!("{} ({})", v.wrong_merges, v.wrong_cross_vehicle_merges),
            v.merges_refused.to_string(),
            v.unaudited_frames.to_string(),
        ] {
            html.push_str(&cell(c));
        }
        html.push_str("</tr>");
    }
    html.push_str("</table>");
    html
}

/// Renders the report page.
pub fn render(run: &RunRecord, summary: &Summary) -> String {
    let mut html = String::from(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>canopy report</title>",
    );
    html.push_str("<style>body{font-family:sans-serif;max-width:940px;margin:auto}pre{background:#f4f4f4;padding:8px}</style></head><body>");
    html.push_str(&format!(
        "<h1>canopy: {}</h1><p>mode <b>{}</b>, frame <b>{}</b>, seed {}, {:.1} s simulated in {:.1} s wall time.</p>",
        escape(&summary.scenario),
        escape(&summary.mode),
        escape(&summary.frame),
        summary.seed,
        summary.duration_s,
        summary.wall_time_s
    ));
    html.push_str(&format!(
        "<h2>Summary</h2><pre>{}</pre>",
        escape(&table(&[("this run", summary)]))
    ));
    html.push_str(&association(summary));
    html.push_str(&rejections(summary));
    html.push_str(&access_refused(summary));
    html.push_str("<h2>Trajectories and map</h2>");
    html.push_str(&trajectories(run));
    html.push_str("<h2>Position error with ±3σ</h2>");
    html.push_str(&errors(run));
    html.push_str("<h2>Consistency</h2>");
    html.push_str(&nees(run));
    html.push_str("<h2>Links</h2>");
    html.push_str(&bandwidth(run));
    html.push_str(&timeline(run));
    html.push_str("</body></html>\n");
    html
}
