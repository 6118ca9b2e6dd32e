//! Pictures of 2D continua: particle systems (the [MPM](adflex_kernels::mpm) family) as
//! frames side by side in one PNG, each particle a dot of its own colour
//! ([`render_strip_png`]), and grid fields (the [fluids](adflex_kernels::fluid)) as grey
//! levels ([`render_fields_png`]).
//!
//! ```
//! use adflex_viz::points::{actuation_color, render_strip_png, Frame2d, StripOptions};
//! use adflex_viz::render::Rgba;
//!
//! let frame = |dx: f64, a: f64| Frame2d {
//!     points: vec![[0.3 + dx, 0.2], [0.4 + dx, 0.2]],
//!     colors: vec![Rgba::rgb(20, 20, 20), actuation_color(a)],
//!     caption: format!("a = {a}"),
//! };
//! let path = std::env::temp_dir().join(format!("adflex-points-{}.png", std::process::id()));
//! render_strip_png(&path, &[frame(0.0, 0.5), frame(0.1, -0.5)], &StripOptions::default())
//!     .unwrap();
//! # std::fs::remove_file(&path).ok();
//! ```

use std::path::Path;

use tiny_skia::{Paint, PathBuilder, Pixmap, Rect, Stroke, Transform};

use crate::color::Rgba;
use crate::overlay::text;
use crate::{Error, Result};

/// One frame: particle positions, their colours (one each) and a caption.
#[derive(Clone, Debug, Default)]
pub struct Frame2d {
    /// Positions in the simulation's units.
    pub points: Vec<[f64; 2]>,
    /// One colour per point.
    pub colors: Vec<Rgba>,
    /// Drawn at the frame's top left (may be empty).
    pub caption: String,
}

/// How to draw a strip of frames.
#[derive(Clone, Debug)]
#[non_exhaustive]
pub struct StripOptions {
    /// The region shown in each panel, `(min, max)` corners (default the unit square).
    pub region: ([f64; 2], [f64; 2]),
    /// Width of a panel in pixels (its height follows the region's aspect ratio).
    pub panel_width: u32,
    /// Radius of a dot in pixels.
    pub radius: f32,
    /// A floor line drawn at this height, if any.
    pub floor: Option<f64>,
}

impl Default for StripOptions {
    fn default() -> Self {
        StripOptions {
            region: ([0.0, 0.0], [1.0, 1.0]),
            panel_width: 320,
            radius: 1.5,
            floor: None,
        }
    }
}

/// DiffTaichi's colour of an actuated particle: red when the actuation extends it
/// (`a < 0`), blue when it contracts it (`a > 0`), grey at rest: `(0.5 - a, 0.5 - |a|,
/// 0.5 + a)`, clamped.
pub fn actuation_color(a: f64) -> Rgba {
    let c = |v: f64| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    Rgba::rgb(c(0.5 - a), c(0.5 - a.abs()), c(0.5 + a))
}

/// Draws `frames` left to right into one PNG at `path`.
///
/// Errors: [`Error::Empty`] for no frames, [`Error::Invalid`] for a frame whose colours do
/// not match its points or a bad region or size, [`Error::Io`] / [`Error::Encode`] naming
/// `path`.
pub fn render_strip_png(
    path: impl AsRef<Path>,
    frames: &[Frame2d],
    opts: &StripOptions,
) -> Result<()> {
    let path = path.as_ref();
    if frames.is_empty() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            what: "no frames",
        });
    }
    let (lo, hi) = opts.region;
    let (w, h) = (hi[0] - lo[0], hi[1] - lo[1]);
    if !(w > 0.0 && h > 0.0 && w.is_finite() && h.is_finite()) {
        return Err(Error::Invalid(format!(
            "region {:?} must have a finite positive size",
            opts.region
        )));
    }
    let pw = opts.panel_width;
    let ph = ((pw as f64) * h / w).round() as u32;
    let total = pw as u64 * frames.len() as u64;
    if pw == 0 || ph == 0 || total > 65_535 || ph > 65_535 {
        return Err(Error::Invalid(format!(
            "{} panels of {pw} x {ph} px: each side must be 1 to 65535 px",
            frames.len()
        )));
    }
    for (k, f) in frames.iter().enumerate() {
        if f.colors.len() != f.points.len() {
            return Err(Error::Invalid(format!(
                "frame {k} has {} points and {} colours",
                f.points.len(),
                f.colors.len()
            )));
        }
    }
    let mut pm =
        Pixmap::new(total as u32, ph).ok_or_else(|| Error::Invalid("picture too large".into()))?;
    pm.fill(tiny_skia::Color::WHITE);
    let scale = pw as f64 / w;
    let to_px = |k: usize, p: [f64; 2]| {
        (
            (k as f64 * pw as f64 + (p[0] - lo[0]) * scale) as f32,
            ((hi[1] - p[1]) * scale) as f32,
        )
    };
    let mut line = Paint::default();
    line.set_color_rgba8(0, 0, 0, 255);
    line.anti_alias = true;
    for (k, f) in frames.iter().enumerate() {
        if let Some(y) = opts.floor {
            let mut b = PathBuilder::new();
            let (x0, y0) = to_px(k, [lo[0], y]);
            let (x1, _) = to_px(k, [hi[0], y]);
            b.move_to(x0, y0);
            b.line_to(x1, y0);
            if let Some(p) = b.finish() {
                let stroke = Stroke {
                    width: 2.0,
                    ..Stroke::default()
                };
                pm.stroke_path(&p, &line, &stroke, Transform::identity(), None);
            }
        }
        for (p, c) in f.points.iter().zip(&f.colors) {
            let (x, y) = to_px(k, *p);
            if let Some(circle) = PathBuilder::from_circle(x, y, opts.radius) {
                pm.fill_path(
                    &circle,
                    &c.paint(),
                    tiny_skia::FillRule::Winding,
                    Transform::identity(),
                    None,
                );
            }
        }
        separator(&mut pm, k, (k as u32 * pw) as f32, ph as f32);
        text(
            &mut pm,
            (k as u32 * pw) as f32 + 6.0,
            6.0,
            &f.caption,
            Rgba::rgb(0, 0, 0),
        );
    }
    save(&pm, path)
}

/// Draws square scalar fields (`n x n`, cell `(i, j)` at index `i * n + j`, `i` along `x`,
/// `j` up) left to right into one PNG at `path`, each cell a `cell_px` square, white at 0 and
/// black at `max` (clamped), with a caption each.
///
/// Errors: [`Error::Empty`] for no fields, [`Error::Invalid`] for a field whose length is not
/// a square or a size out of range, [`Error::Io`] / [`Error::Encode`] naming `path`.
///
/// ```
/// use adflex_viz::points::render_fields_png;
/// let ramp: Vec<f64> = (0..16).map(|t| t as f64 / 15.0).collect();
/// let path = std::env::temp_dir().join(format!("adflex-fields-{}.png", std::process::id()));
/// render_fields_png(&path, &[(&ramp[..], "ramp"), (&ramp[..], "again")], 1.0, 8).unwrap();
/// assert!(render_fields_png(&path, &[(&ramp[..3], "not square")], 1.0, 8).is_err());
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn render_fields_png(
    path: impl AsRef<Path>,
    fields: &[(&[f64], &str)],
    max: f64,
    cell_px: u32,
) -> Result<()> {
    let path = path.as_ref();
    let Some(first) = fields.first() else {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            what: "no fields",
        });
    };
    let n = (first.0.len() as f64).sqrt().round() as usize;
    if n == 0 || fields.iter().any(|f| f.0.len() != n * n) {
        return Err(Error::Invalid(
            "every field must hold n x n values for one n >= 1".into(),
        ));
    }
    let side = n as u64 * cell_px as u64;
    if cell_px == 0 || side * fields.len() as u64 > 65_535 || max.is_nan() || max <= 0.0 {
        return Err(Error::Invalid(format!(
            "{} fields of {side} px (and max {max} > 0)",
            fields.len()
        )));
    }
    let mut pm = Pixmap::new((side * fields.len() as u64) as u32, side as u32)
        .ok_or_else(|| Error::Invalid("picture too large".into()))?;
    pm.fill(tiny_skia::Color::WHITE);
    for (k, (field, caption)) in fields.iter().enumerate() {
        for (t, &value) in field.iter().enumerate() {
            let (i, j) = (t / n, t % n);
            let g = (255.0 * (1.0 - (value / max).clamp(0.0, 1.0))).round() as u8;
            let x = (k as u64 * side + i as u64 * cell_px as u64) as f32;
            let y = ((n - 1 - j) as u64 * cell_px as u64) as f32;
            if let Some(r) = Rect::from_xywh(x, y, cell_px as f32, cell_px as f32) {
                let mut paint = Paint::default();
                paint.set_color_rgba8(g, g, g, 255);
                pm.fill_rect(r, &paint, Transform::identity(), None);
            }
        }
        separator(&mut pm, k, (k as u64 * side) as f32, side as f32);
        text(
            &mut pm,
            (k as u64 * side) as f32 + 6.0,
            6.0,
            caption,
            Rgba::rgb(0, 0, 0),
        );
    }
    save(&pm, path)
}

/// A grey line on the left edge of panel `k` (none before the first).
fn separator(pm: &mut Pixmap, k: usize, x: f32, height: f32) {
    if k == 0 {
        return;
    }
    if let Some(r) = Rect::from_xywh(x, 0.0, 1.0, height) {
        let mut sep = Paint::default();
        sep.set_color_rgba8(160, 160, 160, 255);
        pm.fill_rect(r, &sep, Transform::identity(), None);
    }
}

fn save(pm: &Pixmap, path: &Path) -> Result<()> {
    let bytes = pm.encode_png().map_err(|e| Error::Encode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}
