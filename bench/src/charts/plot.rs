//! A small line-chart helper over plotters' SVG backend: log or linear axes, one series per
//! curve (line with markers, markers only, or dashed reference line), a legend.

use plotters::prelude::*;

/// How a series is drawn.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Style {
    /// Line through the points with a marker at each.
    Line,
    /// Markers only.
    Points,
    /// A dashed line without markers (a reference or theory line).
    Dashed,
}

/// One curve.
#[derive(Clone, Debug)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
    pub style: Style,
    /// Index into [`PALETTE`].
    pub color: usize,
}

impl Series {
    pub fn new(
        name: impl Into<String>,
        points: Vec<(f64, f64)>,
        style: Style,
        color: usize,
    ) -> Self {
        Series {
            name: name.into(),
            points,
            style,
            color,
        }
    }
}

/// A chart: title, axis labels, log axes, series.
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub log_x: bool,
    pub log_y: bool,
    pub series: Vec<Series>,
    /// A note under the chart (e.g. what was skipped).
    pub note: Option<String>,
    /// Fixed axis ranges (otherwise from the data).
    pub x_range: Option<(f64, f64)>,
    pub y_range: Option<(f64, f64)>,
}

/// Splits `text` into lines of at most about `width` characters, at spaces.
fn wrap(text: &str, width: usize) -> Vec<String> {
    let mut lines = Vec::new();
    let mut cur = String::new();
    for word in text.split_whitespace() {
        if !cur.is_empty() && cur.len() + 1 + word.len() > width {
            lines.push(std::mem::take(&mut cur));
        }
        if !cur.is_empty() {
            cur.push(' ');
        }
        cur.push_str(word);
    }
    if !cur.is_empty() {
        lines.push(cur);
    }
    lines
}

/// Colour-blind-safe palette (Okabe-Ito) plus grey.
pub const PALETTE: [RGBColor; 9] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(0, 0, 0),
    RGBColor(240, 228, 66),
    RGBColor(128, 128, 128),
];

fn bounds(vals: impl Iterator<Item = f64>, log: bool) -> (f64, f64) {
    let v: Vec<f64> = vals
        .filter(|v| v.is_finite() && (!log || *v > 0.0))
        .collect();
    let (mut lo, mut hi) = v
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| {
            (a.min(x), b.max(x))
        });
    if !lo.is_finite() {
        return (1.0, 10.0);
    }
    if log {
        lo = 10f64.powf((lo.log10() - 0.15).floor());
        hi = 10f64.powf((hi.log10() + 0.15).ceil());
        if hi <= lo {
            hi = lo * 10.0;
        }
    } else {
        let pad = ((hi - lo) * 0.05).max(hi.abs() * 0.05).max(1e-12);
        lo -= pad;
        hi += pad;
        if lo > 0.0 && lo < pad * 4.0 {
            lo = 0.0;
        }
    }
    (lo, hi)
}

fn fmt_tick(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if (1e-3..1e4).contains(&a) {
        let s = format!("{v:.3}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        s.to_string()
    } else {
        format!("{v:.0e}")
    }
}

impl Chart {
    pub fn new(
        title: impl Into<String>,
        x_label: impl Into<String>,
        y_label: impl Into<String>,
    ) -> Self {
        Chart {
            title: title.into(),
            x_label: x_label.into(),
            y_label: y_label.into(),
            log_x: false,
            log_y: false,
            series: Vec::new(),
            note: None,
            x_range: None,
            y_range: None,
        }
    }

    pub fn log_log(mut self) -> Self {
        self.log_x = true;
        self.log_y = true;
        self
    }

    /// Writes the chart to `path` as SVG: the plot on the left, the legend on the right, the
    /// note (wrapped) underneath.
    pub fn write(&self, path: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
        let all = || self.series.iter().flat_map(|s| s.points.iter());
        let (mut x0, mut x1) = bounds(all().map(|p| p.0), self.log_x);
        let (mut y0, mut y1) = bounds(all().map(|p| p.1), self.log_y);
        if let Some((a, b)) = self.x_range {
            (x0, x1) = (a, b);
        }
        if let Some((a, b)) = self.y_range {
            (y0, y1) = (a, b);
        }
        let note_lines = self
            .note
            .as_deref()
            .map(|n| wrap(n, 150))
            .unwrap_or_default();
        let (w, h) = (1040u32, 560 + 18 * note_lines.len() as u32);
        let root = SVGBackend::new(path, (w, h)).into_drawing_area();
        root.fill(&WHITE)?;
        let (top, bottom) = root.split_vertically(560);
        for (k, line) in note_lines.iter().enumerate() {
            bottom.draw(&Text::new(
                line.clone(),
                (14, 2 + 18 * k as i32),
                ("sans-serif", 13).into_font().color(&RGBColor(90, 90, 90)),
            ))?;
        }
        let (plot, legend) = top.split_horizontally(770);
        let mut y = 60;
        for s in &self.series {
            let c = PALETTE[s.color % PALETTE.len()];
            let lines = wrap(&s.name, 32);
            match s.style {
                Style::Line => {
                    legend.draw(&PathElement::new(vec![(6, y), (34, y)], c.stroke_width(2)))?;
                    legend.draw(&Circle::new((20, y), 3, c.filled()))?;
                }
                Style::Points => legend.draw(&Circle::new((20, y), 4, c.filled()))?,
                Style::Dashed => {
                    legend.draw(&PathElement::new(vec![(6, y), (15, y)], c.stroke_width(2)))?;
                    legend.draw(&PathElement::new(vec![(22, y), (34, y)], c.stroke_width(2)))?;
                }
            }
            for (k, l) in lines.iter().enumerate() {
                legend.draw(&Text::new(
                    l.clone(),
                    (42, y - 7 + 16 * k as i32),
                    ("sans-serif", 13).into_font(),
                ))?;
            }
            y += 16 * lines.len() as i32 + 8;
        }
        macro_rules! draw {
            ($xr:expr, $yr:expr) => {{
                let mut chart = ChartBuilder::on(&plot)
                    .caption(&self.title, ("sans-serif", 18))
                    .margin(12)
                    .x_label_area_size(48)
                    .y_label_area_size(72)
                    .build_cartesian_2d($xr, $yr)?;
                chart
                    .configure_mesh()
                    .x_desc(&self.x_label)
                    .y_desc(&self.y_label)
                    .x_label_formatter(&|v| fmt_tick(*v))
                    .y_label_formatter(&|v| fmt_tick(*v))
                    .light_line_style(RGBColor(235, 235, 235))
                    .label_style(("sans-serif", 13))
                    .draw()?;
                for s in &self.series {
                    let c = PALETTE[s.color % PALETTE.len()];
                    let pts: Vec<(f64, f64)> = s
                        .points
                        .iter()
                        .copied()
                        .filter(|(x, y)| {
                            x.is_finite()
                                && y.is_finite()
                                && (!self.log_x || *x > 0.0)
                                && (!self.log_y || *y > 0.0)
                        })
                        .collect();
                    if pts.is_empty() {
                        continue;
                    }
                    match s.style {
                        Style::Line => {
                            chart.draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))?;
                            chart
                                .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))?;
                        }
                        Style::Dashed => {
                            chart.draw_series(DashedLineSeries::new(
                                pts.clone(),
                                6,
                                4,
                                c.stroke_width(2),
                            ))?;
                        }
                        Style::Points => {
                            chart
                                .draw_series(pts.iter().map(|&p| Circle::new(p, 4, c.filled())))?;
                        }
                    }
                }
            }};
        }
        match (self.log_x, self.log_y) {
            (true, true) => draw!((x0..x1).log_scale(), (y0..y1).log_scale()),
            (true, false) => draw!((x0..x1).log_scale(), y0..y1),
            (false, true) => draw!(x0..x1, (y0..y1).log_scale()),
            (false, false) => draw!(x0..x1, y0..y1),
        }
        root.present()?;
        Ok(())
    }
}
