//! Line charts drawn with `plotters`: an optimization's loss curve ([`loss_curve`]) or several
//! named curves, e.g. energy against time for several integrators or the loss of several
//! optimizers ([`curves`]).
//!
//! The path's extension picks the format: `.png` draws the chart in pixels (with the 8x8
//! bitmap font of the overlays, so no font file or system library is needed), anything else
//! writes SVG, whose text the viewer renders. Draw both for a report (`loss.svg` to zoom,
//! `loss.png` to paste).
//!
//! ```
//! let dir = std::env::temp_dir().join(format!("adflex-viz-doc-plot-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let losses: Vec<f64> = (0..50).map(|k| 10.0 * 0.8f64.powi(k)).collect();
//! adflex_viz::plot::loss_curve(dir.join("loss.svg"), &losses, "cloth: fitting ke").unwrap();
//! # std::fs::remove_dir_all(&dir).ok();
//! ```

use std::ops::Range;
use std::path::Path;

use plotters::coord::combinators::BindKeyPoints;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::prelude::*;

use plotters::coord::Shift;

use crate::raster::PixmapBackend;
use crate::{Error, Result};

/// Width and height (px) of the charts.
pub const SIZE: (u32, u32) = (800, 500);

/// Line colours, in order of the series (repeating after 8).
const PALETTE: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(23, 190, 207),
];

type Series = (String, Vec<(f64, f64)>);

/// Writes the losses of an optimization, one per iteration (x = 0, 1, ...), as a line chart
/// titled `title` (PNG for a `.png` path, SVG otherwise). The y axis is logarithmic when every loss is positive and they span
/// more than two decades (max / min > 100), linear otherwise. Non-finite losses are left
/// out; none finite (or none at all) is an [`Error::Empty`].
///
/// ```
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-loss-{}.svg", std::process::id()));
/// adflex_viz::plot::loss_curve(&path, &[4.0, 2.0, 1.0, 0.5], "loss").unwrap();
/// assert!(std::fs::read_to_string(&path).unwrap().contains("<svg"));
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn loss_curve(path: impl AsRef<Path>, losses: &[f64], title: &str) -> Result<()> {
    let pts: Vec<(f64, f64)> = losses
        .iter()
        .enumerate()
        .map(|(k, &l)| (k as f64, l))
        .collect();
    chart(
        path.as_ref(),
        title,
        "iteration",
        "loss",
        vec![("loss".to_string(), pts)],
        false,
    )
}

/// Writes several named curves (`(name, points)`, points as `(x, y)`) as one line chart with
/// axis labels and a legend (PNG for a `.png` path, SVG otherwise); the y axis is logarithmic under the same rule as
/// [`loss_curve`]. Non-finite points are left out; no finite point at all is an
/// [`Error::Empty`].
///
/// ```
/// let t: Vec<f64> = (0..100).map(|k| k as f64 * 0.01).collect();
/// let a: Vec<(f64, f64)> = t.iter().map(|&t| (t, 1.0)).collect();
/// let b: Vec<(f64, f64)> = t.iter().map(|&t| (t, 1.0 + 0.3 * t)).collect();
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-curves-{}.svg", std::process::id()));
/// adflex_viz::plot::curves(
///     &path,
///     "energy",
///     "time (s)",
///     "energy (J)",
///     &[("semi-implicit", &a[..]), ("explicit", &b[..])],
/// )
/// .unwrap();
/// assert!(std::fs::read_to_string(&path).unwrap().contains("explicit"));
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn curves(
    path: impl AsRef<Path>,
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[(&str, &[(f64, f64)])],
) -> Result<()> {
    let series = series
        .iter()
        .map(|(n, p)| (n.to_string(), p.to_vec()))
        .collect();
    chart(path.as_ref(), title, x_label, y_label, series, true)
}

/// A short axis label: integers as integers, up to 4 significant digits, or scientific.
fn tick(x: f64) -> String {
    let a = x.abs();
    if a == 0.0 {
        "0".into()
    } else if (1e-3..1e6).contains(&a) {
        if (x - x.round()).abs() <= 1e-9 * a {
            format!("{x:.0}")
        } else {
            let decimals = (3 - a.log10().floor() as i32).clamp(0, 6) as usize;
            let s = format!("{x:.decimals$}");
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        }
    } else {
        format!("{x:.1e}")
    }
}

/// The powers of ten in `[lo, hi]` (`0 < lo < hi`), every one for up to 12 decades, then every
/// second, third, ... so that at most 12 are labelled: a log axis labelled over its whole range
/// (plotters' own choice left the bottom decades of a 1e0..1e-23 loss unlabelled).
fn decades(lo: f64, hi: f64) -> Vec<f64> {
    let (a, b) = (lo.log10().ceil() as i32, hi.log10().floor() as i32);
    let n = (b - a + 1).max(1);
    let step = ((n + 11) / 12).max(1);
    // From the top down, so that the largest decade is always labelled.
    let mut v: Vec<f64> = (0..n)
        .step_by(step as usize)
        .map(|k| 10f64.powi(b - k))
        .collect();
    v.reverse();
    v
}

fn padded(lo: f64, hi: f64) -> Range<f64> {
    if hi > lo {
        let pad = 0.04 * (hi - lo);
        (lo - pad)..(hi + pad)
    } else {
        let pad = if lo == 0.0 { 1.0 } else { 0.1 * lo.abs() };
        (lo - pad)..(hi + pad)
    }
}

fn chart(
    path: &Path,
    title: &str,
    x_label: &str,
    y_label: &str,
    mut series: Vec<Series>,
    legend: bool,
) -> Result<()> {
    for (_, pts) in &mut series {
        pts.retain(|(x, y)| x.is_finite() && y.is_finite());
    }
    let all = || series.iter().flat_map(|s| s.1.iter());
    if all().next().is_none() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            what: "no finite point to plot",
        });
    }
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in all() {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    let xr = if x1 > x0 { x0..x1 } else { padded(x0, x1) };
    let log = y0 > 0.0 && y1 / y0 > 100.0;
    let labels = (title, x_label, y_label);
    let encode = |message| Error::Encode {
        path: path.to_path_buf(),
        message,
    };
    let png = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if png {
        let mut pm = tiny_skia::Pixmap::new(SIZE.0, SIZE.1).expect("a nonzero chart size");
        let root = PixmapBackend::new(&mut pm).into_drawing_area();
        on(root, labels, xr, (y0, y1, log), &series, legend).map_err(encode)?;
        let bytes = pm.encode_png().map_err(|e| encode(e.to_string()))?;
        std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
    } else {
        let mut svg = String::new();
        let root = SVGBackend::with_string(&mut svg, SIZE).into_drawing_area();
        on(root, labels, xr, (y0, y1, log), &series, legend).map_err(encode)?;
        std::fs::write(path, svg).map_err(|e| Error::io(path, e))
    }
}

/// Draws the chart on `root`, the y axis over `[y0, y1]`, logarithmic if `log`.
fn on<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    (title, x_label, y_label): (&str, &str, &str),
    xr: Range<f64>,
    (y0, y1, log): (f64, f64, bool),
    series: &[Series],
    legend: bool,
) -> std::result::Result<(), String> {
    if log {
        let (lo, hi) = (y0 / 1.5, y1 * 1.5);
        let yr = (lo..hi).log_scale().with_key_points(decades(lo, hi));
        draw(root, title, x_label, y_label, xr, (yr, 0.0), series, legend)
    } else {
        let yr = padded(y0, y1);
        // A tick within rounding of zero (e.g. -5.6e-17) is zero, on either linear axis.
        let zero = 1e-9 * (yr.end - yr.start);
        draw(
            root,
            title,
            x_label,
            y_label,
            xr,
            (yr, zero),
            series,
            legend,
        )
    }
}

#[allow(clippy::too_many_arguments)]
fn draw<DB: DrawingBackend, Y>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    x_label: &str,
    y_label: &str,
    xr: Range<f64>,
    (yr, y_zero): (Y, f64),
    series: &[Series],
    legend: bool,
) -> std::result::Result<(), String>
where
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    let e = |e: &dyn std::fmt::Display| e.to_string();
    // The x axis is linear: a tick within rounding of zero (e.g. -5.6e-17) is zero.
    let x_zero = 1e-9 * (xr.end - xr.start).abs();
    root.fill(&WHITE).map_err(|x| e(&x))?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(90)
        .build_cartesian_2d::<Range<f64>, Y>(xr, yr)
        .map_err(|x| e(&x))?;
    chart
        .configure_mesh()
        .x_desc(x_label)
        .y_desc(y_label)
        .light_line_style(RGBColor(235, 235, 235))
        .x_label_formatter(&|x| tick(if x.abs() < x_zero { 0.0 } else { *x }))
        .y_label_formatter(&|y| tick(if y.abs() < y_zero { 0.0 } else { *y }))
        .draw()
        .map_err(|x| e(&x))?;
    for (k, (name, pts)) in series.iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let drawn = chart
            .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))
            .map_err(|x| e(&x))?;
        if legend {
            drawn.label(name.as_str()).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        }
    }
    if legend {
        chart
            .configure_series_labels()
            // 18 px: plotters' width estimate of a label then fits the PNG's 8 px glyphs.
            .label_font(("sans-serif", 18))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .position(SeriesLabelPosition::UpperRight)
            .draw()
            .map_err(|x| e(&x))?;
    }
    root.present().map_err(|x| e(&x))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn ticks_are_short() {
        use super::tick;
        assert_eq!(tick(0.0), "0");
        assert_eq!(tick(20.0), "20");
        assert_eq!(tick(0.30000000000000004), "0.3");
        assert_eq!(tick(0.001), "0.001");
        assert_eq!(tick(2.5e-5), "2.5e-5");
        assert_eq!(tick(-1.25), "-1.25");
    }

    #[test]
    fn a_tick_within_rounding_of_zero_reads_zero_on_either_axis() {
        // A sag profile from 0 (up to sin(pi)'s rounding) down to -0.316, against -0.3..0.
        let pts: Vec<(f64, f64)> = (0..=30)
            .map(|j| {
                let v = j as f64 / 30.0;
                (v - 0.3, -0.316 * (std::f64::consts::PI * v).sin())
            })
            .collect();
        let path = std::env::temp_dir().join(format!("adflex-viz-zero-{}.svg", std::process::id()));
        super::curves(&path, "sag", "v", "height", &[("sag", &pts[..])]).unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        std::fs::remove_file(&path).ok();
        let labels: Vec<&str> = svg
            .split("</text>")
            .filter_map(|t| t.rsplit('>').next().map(str::trim))
            .collect();
        assert!(!labels.iter().any(|l| l.contains("e-1")), "{labels:?}");
        assert_eq!(
            labels.iter().filter(|l| **l == "0").count(),
            2,
            "{labels:?}"
        );
    }

    #[test]
    fn log_axes_are_labelled_over_the_whole_range() {
        use super::decades;
        // The cage's loss: 6.6e-2 down to 1e-23.
        let d = decades(1e-23 / 1.5, 6.6e-2 * 1.5);
        assert!(d.len() <= 12 && d.len() >= 10, "{d:?}");
        assert_eq!(*d.last().unwrap(), 1e-2);
        assert!(d[0] <= 1e-21, "{d:?}");
        assert_eq!(decades(0.5, 2e3), vec![1.0, 10.0, 100.0, 1000.0]);
    }
}
