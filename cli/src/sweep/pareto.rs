//! `pareto.png`: error (FLIP) against wall time, a point per setting labelled by its knob
//! values, the exact render at error 0, and the Pareto front drawn as a line.
//!
//! Drawn with plotters' bitmap backend into a buffer and encoded with `image`, and text
//! with a TrueType font read at run time (plotters' `ab_glyph`), so the plot needs no
//! system font library. Without a font the plot is drawn without text: a sweep never
//! fails for want of one.

use std::path::Path;

use anyhow::{Context, Result};
use plotters::prelude::*;

/// One setting on the plot.
#[derive(Clone, Debug, PartialEq)]
pub struct Point {
    pub label: String,
    pub wall_s: f64,
    pub error: f64,
}

/// Which points are on the Pareto front: those no other point beats on both time and
/// error (at most equal on both and better on one). Exact duplicates are all on it.
pub fn front(points: &[Point]) -> Vec<bool> {
    points
        .iter()
        .map(|p| {
            !points.iter().any(|q| {
                q.wall_s <= p.wall_s
                    && q.error <= p.error
                    && (q.wall_s < p.wall_s || q.error < p.error)
            })
        })
        .collect()
}

/// Short labels for the plot from the settings' names (`key=value` words, or `exact`):
/// a word every setting shares says nothing and is left out, and a knob's flag prefix
/// (`ray-cache.`, `phm.`) is dropped, so `ray-cache.radius=0.002 ray-cache.coarse=256`
/// beside `ray-cache.radius=0.004 ray-cache.coarse=256` reads `radius=0.002`.
pub fn labels(settings: &[String]) -> Vec<String> {
    let varied: Vec<Vec<&str>> = settings
        .iter()
        .filter(|s| *s != "exact")
        .map(|s| s.split_whitespace().collect())
        .collect();
    let shared = |w: &str| varied.len() > 1 && varied.iter().all(|v| v.contains(&w));
    settings
        .iter()
        .map(|s| {
            if s == "exact" {
                return s.clone();
            }
            let words: Vec<&str> = s
                .split_whitespace()
                .filter(|w| !shared(w))
                .map(|w| {
                    w.strip_prefix("ray-cache.")
                        .or_else(|| w.strip_prefix("phm."))
                        .unwrap_or(w)
                })
                .collect();
            if words.is_empty() {
                s.clone()
            } else {
                words.join(" ")
            }
        })
        .collect()
}

/// Fonts tried in order when `DRAY_FONT` is not set (Debian/Ubuntu, Fedora, Arch, macOS,
/// Windows).
const FONT_PATHS: [&str; 8] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/freefont/FreeSans.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// A TrueType font for the plot's text: the file `DRAY_FONT` names (and only it, when
/// set), else the first of [`FONT_PATHS`] that exists. Leaked: plotters keeps fonts for
/// the life of the process, and a sweep registers one.
pub fn find_font() -> Option<&'static [u8]> {
    let paths: Vec<std::path::PathBuf> = match std::env::var_os("DRAY_FONT") {
        Some(p) => vec![p.into()],
        None => FONT_PATHS.iter().map(Into::into).collect(),
    };
    paths
        .iter()
        .find_map(|p| std::fs::read(p).ok())
        .map(|b| &*Box::leak(b.into_boxed_slice()))
}

/// Draw the plot into `path` (`font`: TrueType bytes for the text, None for none).
pub fn draw(points: &[Point], font: Option<&'static [u8]>, path: &Path) -> Result<()> {
    let with_text = font.is_some_and(|f| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, f).is_ok()
    });
    let (w, h) = (1000u32, 700u32);
    let mut buf = vec![0u8; w as usize * h as usize * 3];
    plot(points, with_text, &mut buf, (w, h))
        .map_err(|e| anyhow::anyhow!("cannot draw the plot: {e}"))?;
    image::save_buffer(path, &buf, w, h, image::ExtendedColorType::Rgb8)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// Axis ranges: from 0 to a little past the largest value, never empty.
fn upper(values: impl Iterator<Item = f64>, least: f64) -> f64 {
    let m = values.filter(|v| v.is_finite()).fold(0.0f64, f64::max);
    (m * 1.15).max(least)
}

fn plot(
    points: &[Point],
    text: bool,
    buf: &mut [u8],
    size: (u32, u32),
) -> Result<(), Box<dyn std::error::Error>> {
    let root = BitMapBackend::with_buffer(buf, size).into_drawing_area();
    root.fill(&WHITE)?;
    let on_front = front(points);
    let x_max = upper(points.iter().map(|p| p.wall_s), 1e-3);
    let y_max = upper(points.iter().map(|p| p.error), 1e-3);
    // A little room below 0, so the exact render's point (error 0) is seen whole.
    let y_min = -0.02 * y_max;
    let mut builder = ChartBuilder::on(&root);
    builder.margin(30);
    if text {
        builder
            .caption("dray sweep: error against wall time", ("sans-serif", 24))
            .x_label_area_size(50)
            .y_label_area_size(70);
    }
    let mut chart = builder.build_cartesian_2d(0f64..x_max, y_min..y_max)?;
    if text {
        chart
            .configure_mesh()
            .x_desc("wall time (s)")
            .y_desc("FLIP (mean, vs exact)")
            .label_style(("sans-serif", 15))
            .axis_desc_style(("sans-serif", 17))
            .draw()?;
    } else {
        // A frame, no mesh: tick labels need a font.
        chart.plotting_area().draw(&Rectangle::new(
            [(0.0, y_min), (x_max, y_max)],
            BLACK.stroke_width(1),
        ))?;
    }
    let mut line: Vec<(f64, f64)> = points
        .iter()
        .zip(&on_front)
        .filter(|(_, f)| **f)
        .map(|(p, _)| (p.wall_s, p.error))
        .collect();
    line.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
    let front_color = RGBColor(214, 39, 40);
    let series = chart.draw_series(LineSeries::new(line, front_color.stroke_width(2)))?;
    if text {
        series.label("Pareto front").legend(move |(x, y)| {
            PathElement::new([(x, y), (x + 20, y)], front_color.stroke_width(2))
        });
    }
    let other = RGBColor(31, 119, 180);
    chart.draw_series(points.iter().zip(&on_front).map(|(p, f)| {
        let c = if *f { front_color } else { other };
        Circle::new((p.wall_s, p.error), 5, c.filled())
    }))?;
    if text {
        let font = ("sans-serif", 13).into_font().color(&BLACK);
        let (right, bottom) = chart.backend_coord(&(x_max, y_min));
        let top = chart.backend_coord(&(0.0, y_max)).1;
        let mut placed: Vec<(i32, i32, i32, i32)> = Vec::new();
        for p in points {
            let (w, h) = root.estimate_text_size(&p.label, &font)?;
            let (w, h) = (w as i32, h as i32);
            let (px, py) = chart.backend_coord(&(p.wall_s, p.error));
            // Right of the point, or left of it near the right edge; moved down (then
            // up) past labels already placed, so coinciding points stay readable.
            let x = if px + 8 + w > right {
                px - 8 - w
            } else {
                px + 8
            };
            let overlaps = |y: i32| {
                placed
                    .iter()
                    .any(|&(x0, y0, x1, y1)| x < x1 && x + w > x0 && y < y1 && y + h > y0)
            };
            let y = (0..40i32)
                .map(|k| {
                    let shift = if k % 2 == 1 { (k + 1) / 2 } else { -(k / 2) };
                    py - h / 2 + (h + 2) * shift
                })
                .find(|&y| y >= top && y + h <= bottom && !overlaps(y))
                .unwrap_or(py - h / 2);
            placed.push((x, y, x + w, y + h));
            root.draw(&Text::new(p.label.clone(), (x, y), font.clone()))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 15))
            .draw()?;
    }
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(label: &str, wall_s: f64, error: f64) -> Point {
        Point {
            label: label.into(),
            wall_s,
            error,
        }
    }

    #[test]
    fn labels_leave_out_what_every_setting_shares() {
        let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
        assert_eq!(
            labels(&s(&[
                "exact",
                "ray-cache.radius=1 ray-cache.coarse=256 phm.miss=0.1",
                "ray-cache.radius=2 ray-cache.coarse=256 phm.miss=0.2",
            ])),
            s(&["exact", "radius=1 miss=0.1", "radius=2 miss=0.2"])
        );
        // One setting: nothing is left out; a setting of shared words keeps its name.
        assert_eq!(
            labels(&s(&["exact", "spp=4 ray-cache.fill=false"])),
            s(&["exact", "spp=4 fill=false"])
        );
    }

    #[test]
    fn the_front_is_what_nothing_beats() {
        let pts = [
            p("exact", 10.0, 0.0),
            p("a", 5.0, 0.1),
            p("b", 6.0, 0.2), // beaten by a
            p("c", 4.0, 0.3),
            p("d", 4.0, 0.3),  // a tie with c: both stay
            p("e", 12.0, 0.0), // slower than exact at the same error
        ];
        assert_eq!(front(&pts), [true, true, false, true, true, false]);
    }

    #[test]
    fn plots_with_and_without_text() {
        let dir = std::env::temp_dir().join(format!("dray-pareto-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let pts = [
            p("exact", 2.0, 0.0),
            p("radius=0.1", 1.0, 0.05),
            p("radius=0.2", 1.5, 0.2),
        ];
        let plain = dir.join("plain.png");
        draw(&pts, None, &plain).unwrap();
        let img = image::open(&plain).unwrap().to_rgb8();
        assert_eq!(img.dimensions(), (1000, 700));
        // The front line is drawn: some pixels have its red.
        assert!(img.pixels().any(|px| px.0 == [214, 39, 40]));
        if let Some(font) = find_font() {
            let labelled = dir.join("labelled.png");
            draw(&pts, Some(font), &labelled).unwrap();
            assert_ne!(
                std::fs::read(&labelled).unwrap(),
                std::fs::read(&plain).unwrap()
            );
        }
        // One point, all at zero: the ranges are not empty.
        draw(&[p("exact", 0.0, 0.0)], None, &dir.join("one.png")).unwrap();
        let _ = std::fs::remove_dir_all(&dir);
    }
}
