//! What a picture shows besides the state: targets and goals, trails of chosen particles, a
//! ghost of another state (the first guess, a target shape), colours by a value with a
//! colour bar, and a caption. Pass an [`Overlay`] to [`render_png_with`](crate::render::render_png_with)
//! or [`render_gif_with`](crate::render::render_gif_with).
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_runtime::{Tape, Vec3};
//! use adflex_viz::overlay::{ColorBy, Colormap, Ghost, Marker, Overlay, Trail, Values};
//! use adflex_viz::render::{render_gif_with, RenderOptions, Rgba};
//!
//! let mut b = ModelBuilder::<f64>::new();
//! let a = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
//! let c = b.add_particle(Vec3::new(0.5, 1.0, 0.0), Vec3::zeros(), 1.0);
//! b.add_spring(a, c, 200.0, 0.5);
//! let model = b.finalize();
//! let mut states = vec![model.state()];
//! for _ in 0..20 {
//!     let s = SemiImplicitEuler.step(&model, &mut Tape::new(), states.last().unwrap(), None, 0.02).unwrap();
//!     states.push(s);
//! }
//! let overlay = Overlay {
//!     markers: vec![Marker::target(Vec3::new(0.5, 0.6, 0.0), "goal")],
//!     trails: vec![Trail::of(c as usize)],
//!     ghosts: vec![Ghost::of(&states[0], "start")],
//!     color_by: Some(ColorBy::new(Values::Speed, (0.0, 3.0), Colormap::Sequential, "speed (m/s)")),
//!     captions: (0..states.len()).map(|k| format!("t = {:.2} s", k as f64 * 0.02)).collect(),
//!     ..Overlay::default()
//! };
//! let opts = RenderOptions { width: 200, height: 150, ..RenderOptions::default() };
//! let path = std::env::temp_dir().join(format!("adflex-viz-doc-overlay-{}.gif", std::process::id()));
//! render_gif_with(&path, &model, &states, &opts, &overlay, 10.0, 5).unwrap();
//! # std::fs::remove_file(&path).ok();
//! ```

use adflex_kernels::model::State;
use adflex_runtime::{Real, Vec3};
use tiny_skia::{Pixmap, Rect, Transform};

use crate::color::Rgba;
use crate::scene::{wide, Frame, Topology};

/// A point to mark (a target, a goal, a destination): a ring with a cross, and a label.
#[derive(Clone, Debug, PartialEq)]
pub struct Marker {
    /// World position (m).
    pub position: Vec3<f64>,
    /// Colour.
    pub color: Rgba,
    /// Radius of the ring (px).
    pub radius: f32,
    /// Text beside it (may be empty).
    pub label: String,
}

impl Marker {
    /// A red target marker with a label.
    pub fn target(position: Vec3<f64>, label: &str) -> Self {
        Marker {
            position,
            color: Rgba::rgb(210, 40, 40),
            radius: 9.0,
            label: label.to_string(),
        }
    }
}

/// The path of one particle, drawn from the first state to the one shown.
#[derive(Clone, Debug, PartialEq)]
pub struct Trail {
    /// Particle index.
    pub particle: usize,
    /// Colour.
    pub color: Rgba,
    /// Line width (px).
    pub width: f32,
}

impl Trail {
    /// The path of `particle` in orange, 2 px wide.
    pub fn of(particle: usize) -> Self {
        Trail {
            particle,
            color: Rgba::rgb(235, 130, 20),
            width: 2.0,
        }
    }
}

/// Another state of the same model drawn faintly behind the one shown: the first guess under
/// the optimized result, a target shape.
#[derive(Clone, Debug, PartialEq)]
pub struct Ghost {
    /// Particle positions (m).
    pub x: Vec<Vec3<f64>>,
    /// Rigid body poses: centre (m) and orientation `(w, x, y, z)`.
    pub bodies: Vec<(Vec3<f64>, [f64; 4])>,
    /// Colour (its alpha sets how faint).
    pub color: Rgba,
    /// Text in the picture's key (may be empty).
    pub label: String,
}

impl Ghost {
    /// `state` in translucent grey, with a label.
    pub fn of<R: Real>(state: &State<R>, label: &str) -> Self {
        let f = Frame::of(state);
        Ghost {
            x: f.x,
            bodies: f.bodies,
            color: Rgba {
                r: 120,
                g: 120,
                b: 130,
                a: 110,
            },
            label: label.to_string(),
        }
    }

    pub(crate) fn frame(&self) -> Frame {
        Frame {
            x: self.x.clone(),
            bodies: self.bodies.clone(),
        }
    }
}

/// A map from `[0, 1]` to colours.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Colormap {
    /// Blue (0), white (0.5), red (1): signed quantities such as strain or actuation
    /// (DiffTaichi's "red = extension, blue = contraction" with a range symmetric about 0).
    Diverging,
    /// Dark blue through green to yellow (viridis-like): magnitudes such as speed.
    Sequential,
}

impl Colormap {
    /// The colour at `t` (clamped to `[0, 1]`; NaN is grey).
    ///
    /// ```
    /// use adflex_viz::overlay::Colormap;
    /// use adflex_viz::render::Rgba;
    /// assert_eq!(Colormap::Diverging.at(0.5), Rgba::rgb(245, 245, 245));
    /// assert!(Colormap::Diverging.at(1.0).r > 150 && Colormap::Diverging.at(0.0).b > 150);
    /// ```
    pub fn at(self, t: f64) -> Rgba {
        if t.is_nan() {
            return Rgba::rgb(150, 150, 150);
        }
        let stops: &[(f64, [f64; 3])] = match self {
            Colormap::Diverging => &[
                (0.0, [33.0, 102.0, 172.0]),
                (0.25, [103.0, 169.0, 207.0]),
                (0.5, [245.0, 245.0, 245.0]),
                (0.75, [239.0, 138.0, 98.0]),
                (1.0, [178.0, 24.0, 43.0]),
            ],
            Colormap::Sequential => &[
                (0.0, [68.0, 1.0, 84.0]),
                (0.25, [59.0, 82.0, 139.0]),
                (0.5, [33.0, 145.0, 140.0]),
                (0.75, [94.0, 201.0, 98.0]),
                (1.0, [253.0, 231.0, 37.0]),
            ],
        };
        let t = t.clamp(0.0, 1.0);
        let k = stops
            .windows(2)
            .position(|w| t <= w[1].0)
            .unwrap_or(stops.len() - 2);
        let (a, b) = (stops[k], stops[k + 1]);
        let s = (t - a.0) / (b.0 - a.0);
        let c = |i: usize| (a.1[i] + s * (b.1[i] - a.1[i])).round() as u8;
        Rgba::rgb(c(0), c(1), c(2))
    }
}

/// Which value colours the picture.
#[derive(Clone, Debug, PartialEq)]
pub enum Values {
    /// Each particle's speed `|v|` (m/s), from the state drawn.
    Speed,
    /// Each spring's (and distance constraint's) strain `(l - l0) / l0`, `l0` its rest length:
    /// positive stretched, negative compressed.
    EdgeStrain,
    /// A value per particle for each state of the rollout (`values[k][i]`: state `k`,
    /// particle `i`; a single picture uses `values[0]`), e.g. an actuation.
    Particles(Vec<Vec<f64>>),
}

/// Colouring by a value: particles (and faces, by the mean of their vertices) for
/// per-particle values, edges for strain; a colour bar with the range and `label`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColorBy {
    /// The value.
    pub values: Values,
    /// The values mapped to the colour map's ends.
    pub range: (f64, f64),
    /// The colour map.
    pub map: Colormap,
    /// The colour bar's title (what and unit).
    pub label: String,
}

impl ColorBy {
    /// Colouring by `values` over `range` with `map`, titled `label`.
    pub fn new(values: Values, range: (f64, f64), map: Colormap, label: &str) -> Self {
        ColorBy {
            values,
            range,
            map,
            label: label.to_string(),
        }
    }

    /// The colour of value `v`.
    pub fn color(&self, v: f64) -> Rgba {
        let (lo, hi) = self.range;
        let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.5 };
        self.map.at(t)
    }

    /// Per-particle values of state `k` (`state` is that state), if the values are per
    /// particle.
    pub(crate) fn particle_values<R: Real>(&self, k: usize, state: &State<R>) -> Option<Vec<f64>> {
        match &self.values {
            Values::Speed => Some(
                state
                    .v
                    .to_vec()
                    .into_iter()
                    .map(|v| wide(v).norm())
                    .collect(),
            ),
            Values::Particles(all) => all.get(k).or(all.last()).cloned(),
            Values::EdgeStrain => None,
        }
    }
}

/// A flat region drawn under the scene (a table, a landing zone), as a filled polygon.
#[derive(Clone, Debug, PartialEq)]
pub struct Region {
    /// Corners (m), in order.
    pub corners: Vec<Vec3<f64>>,
    /// Fill colour.
    pub color: Rgba,
}

impl Region {
    /// The rectangle `[x0, x1] x [z0, z1]` at height `y` (m), in `color`.
    pub fn rect_xz(x: (f64, f64), z: (f64, f64), y: f64, color: Rgba) -> Self {
        Region {
            corners: vec![
                Vec3::new(x.0, y, z.0),
                Vec3::new(x.1, y, z.0),
                Vec3::new(x.1, y, z.1),
                Vec3::new(x.0, y, z.1),
            ],
            color,
        }
    }
}

/// Everything drawn over the state; `Overlay::default()` draws nothing extra.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overlay {
    /// Points to mark (targets), drawn on top.
    pub markers: Vec<Marker>,
    /// Particle paths up to the state shown.
    pub trails: Vec<Trail>,
    /// Regions drawn under everything (after the ground).
    pub regions: Vec<Region>,
    /// Other states drawn faintly behind.
    pub ghosts: Vec<Ghost>,
    /// Colouring by a value, with a colour bar.
    pub color_by: Option<ColorBy>,
    /// A caption per state of the rollout (`captions[k]` over state `k`; the last repeats;
    /// none: no caption), drawn at the top left: iteration, loss, time.
    pub captions: Vec<String>,
}

impl Overlay {
    /// Every world point the overlay draws (markers, ghosts), to fit a camera to.
    pub(crate) fn points(&self, topo: &Topology) -> Vec<Vec3<f64>> {
        let mut out: Vec<Vec3<f64>> = self.markers.iter().map(|m| m.position).collect();
        out.extend(self.regions.iter().flat_map(|r| r.corners.iter().copied()));
        for g in &self.ghosts {
            out.extend(g.frame().all_points(topo));
        }
        out
    }

    pub(crate) fn caption(&self, k: usize) -> Option<&str> {
        self.captions
            .get(k)
            .or(self.captions.last())
            .map(String::as_str)
    }
}

// ---------------------------------------------------------------- text and keys

/// Pixels per font pixel.
const SCALE: f32 = 2.0;
/// Height of a line of text (px).
pub(crate) const LINE: f32 = 8.0 * SCALE + 4.0;

/// Width of `text` (px) as [`text`] draws it.
pub(crate) fn text_width(text: &str) -> f32 {
    text.chars().count() as f32 * 8.0 * SCALE
}

/// Draws `text` (ASCII; other characters as `?`) with its top left at `(x, y)`, on a
/// translucent white box so that it reads over anything.
pub(crate) fn text(pm: &mut Pixmap, x: f32, y: f32, text: &str, color: Rgba) {
    if text.is_empty() {
        return;
    }
    if let Some(r) = Rect::from_xywh(x - 3.0, y - 2.0, text_width(text) + 6.0, LINE) {
        let mut bg = tiny_skia::Paint::default();
        bg.set_color_rgba8(255, 255, 255, 190);
        pm.fill_rect(r, &bg, Transform::identity(), None);
    }
    let mut paint = tiny_skia::Paint::default();
    paint.set_color_rgba8(color.r, color.g, color.b, color.a);
    for (col, row) in glyph_pixels(text) {
        let (px, py) = (x + col as f32 * SCALE, y + row as f32 * SCALE);
        if let Some(r) = Rect::from_xywh(px, py, SCALE, SCALE) {
            pm.fill_rect(r, &paint, Transform::identity(), None);
        }
    }
}

/// The set pixels of `text` in the 8x8 font (ASCII; other characters as `?`), as `(column,
/// row)` in font pixels from the text's top left.
pub(crate) fn glyph_pixels(text: &str) -> impl Iterator<Item = (i32, i32)> + '_ {
    text.chars().enumerate().flat_map(|(k, ch)| {
        let code = if ch.is_ascii() {
            ch as usize
        } else {
            '?' as usize
        };
        let glyph = font8x8::legacy::BASIC_LEGACY[code];
        (0..8usize).flat_map(move |row| {
            (0..8i32)
                .filter(move |col| glyph[row] & (1 << col) != 0)
                .map(move |col| (k as i32 * 8 + col, row as i32))
        })
    })
}

/// A short number for a key: 3 significant digits.
pub(crate) fn short(v: f64) -> String {
    let a = v.abs();
    if a != 0.0 && !(1e-2..1e4).contains(&a) {
        format!("{v:.2e}")
    } else {
        let s = format!("{v:.3}");
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// The colour bar at the bottom left: the colour map with its range and title.
pub(crate) fn color_bar(pm: &mut Pixmap, c: &ColorBy) {
    let (w, h) = (pm.width() as f32, pm.height() as f32);
    let bar_w = (0.3 * w).clamp(60.0, 240.0);
    let (x, y) = (10.0, h - 10.0 - 14.0 - LINE);
    text(pm, x, y - LINE, &c.label, Rgba::rgb(30, 30, 30));
    let steps = bar_w.max(1.0) as usize;
    for s in 0..steps {
        let t = s as f64 / (steps - 1).max(1) as f64;
        let col = c.map.at(t);
        let mut p = tiny_skia::Paint::default();
        p.set_color_rgba8(col.r, col.g, col.b, 255);
        if let Some(r) = Rect::from_xywh(x + s as f32, y, 1.0, 14.0) {
            pm.fill_rect(r, &p, Transform::identity(), None);
        }
    }
    let lo = short(c.range.0);
    let hi = short(c.range.1);
    text(pm, x, y + 16.0, &lo, Rgba::rgb(30, 30, 30));
    let hx = (x + bar_w - text_width(&hi)).max(x + text_width(&lo) + 8.0);
    text(pm, hx, y + 16.0, &hi, Rgba::rgb(30, 30, 30));
    let _ = w;
}

/// The key at the top right, under the caption: one line per labelled marker and ghost, in
/// its colour.
pub(crate) fn key(pm: &mut Pixmap, o: &Overlay) {
    let w = pm.width() as f32;
    let mut y = 8.0 + LINE;
    let entries = o
        .ghosts
        .iter()
        .map(|g| (&g.label, Rgba { a: 255, ..g.color }))
        .chain(o.markers.iter().map(|m| (&m.label, m.color)))
        .filter(|(l, _)| !l.is_empty());
    for (label, color) in entries {
        let line = format!("# {label}");
        text(pm, w - text_width(&line) - 10.0, y, &line, color);
        y += LINE;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colormaps_run_from_end_to_end() {
        for map in [Colormap::Diverging, Colormap::Sequential] {
            assert_ne!(map.at(0.0), map.at(1.0));
            assert_eq!(map.at(-5.0), map.at(0.0));
            assert_eq!(map.at(5.0), map.at(1.0));
        }
        let c = ColorBy::new(Values::Speed, (-1.0, 1.0), Colormap::Diverging, "");
        assert!(c.color(1.0).r > c.color(1.0).b, "extension is red");
        assert!(c.color(-1.0).b > c.color(-1.0).r, "contraction is blue");
    }

    #[test]
    fn text_draws_pixels_and_short_numbers_are_short() {
        let mut pm = Pixmap::new(100, 30).unwrap();
        text(&mut pm, 2.0, 2.0, "A1", Rgba::rgb(0, 0, 0));
        let dark = pm
            .pixels()
            .iter()
            .filter(|p| p.red() < 50 && p.alpha() > 200)
            .count();
        assert!(dark > 20, "{dark}");
        assert_eq!(short(0.5), "0.5");
        assert_eq!(short(1e-23), "1.00e-23");
        assert_eq!(short(-0.12345), "-0.123");
    }
}
