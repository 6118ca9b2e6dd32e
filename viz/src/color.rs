//! Colours: [`Rgba`], shared by the renderer, the overlays and the charts' pixel backend.

use tiny_skia::Paint;

/// An 8-bit colour with alpha (not premultiplied).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Rgba {
    /// Red.
    pub r: u8,
    /// Green.
    pub g: u8,
    /// Blue.
    pub b: u8,
    /// Alpha (255 = opaque).
    pub a: u8,
}

impl Rgba {
    /// An opaque colour.
    ///
    /// ```
    /// let c = adflex_viz::render::Rgba::rgb(255, 128, 0);
    /// assert_eq!(c.a, 255);
    /// ```
    pub const fn rgb(r: u8, g: u8, b: u8) -> Self {
        Rgba { r, g, b, a: 255 }
    }

    /// The colour with each channel scaled by `k` (clamped to `0..=1`), alpha kept.
    ///
    /// ```
    /// use adflex_viz::render::Rgba;
    /// assert_eq!(Rgba::rgb(200, 100, 0).scaled(0.5), Rgba::rgb(100, 50, 0));
    /// ```
    pub fn scaled(self, k: f64) -> Self {
        let k = k.clamp(0.0, 1.0);
        let s = |c: u8| (c as f64 * k).round() as u8;
        Rgba {
            r: s(self.r),
            g: s(self.g),
            b: s(self.b),
            a: self.a,
        }
    }

    pub(crate) fn paint(self) -> Paint<'static> {
        let mut p = Paint::default();
        p.set_color_rgba8(self.r, self.g, self.b, self.a);
        p.anti_alias = true;
        p
    }
}
