//! A `plotters` drawing backend on a `tiny-skia` pixmap, for the PNG charts of
//! [`crate::plot`]: lines, paths, rectangles, circles and polygons are drawn anti-aliased by
//! tiny-skia, and text with the 8x8 bitmap font the overlays use (scaled to the style's size,
//! rotated for the y axis), so a PNG chart needs no font file and no system library.

use plotters_backend::text_anchor::{HPos, VPos};
use plotters_backend::{
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingBackend, DrawingErrorKind,
    FontTransform,
};
use tiny_skia::{FillRule, LineCap, Paint, PathBuilder, Pixmap, Rect, Stroke, Transform};

use crate::color::Rgba;
use crate::overlay::glyph_pixels;

/// Never returned: drawing on a pixmap cannot fail (a shape off the pixmap is clipped).
#[derive(Debug)]
pub(crate) struct NoError;

impl std::fmt::Display for NoError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("no error")
    }
}

impl std::error::Error for NoError {}

type Drawn = Result<(), DrawingErrorKind<NoError>>;

/// Draws on a borrowed pixmap.
pub(crate) struct PixmapBackend<'a> {
    pm: &'a mut Pixmap,
}

impl<'a> PixmapBackend<'a> {
    pub(crate) fn new(pm: &'a mut Pixmap) -> Self {
        PixmapBackend { pm }
    }
}

fn paint(c: BackendColor) -> Option<Paint<'static>> {
    if c.alpha <= 0.0 {
        return None;
    }
    let a = (c.alpha.clamp(0.0, 1.0) * 255.0).round() as u8;
    let (r, g, b) = c.rgb;
    Some(Rgba { r, g, b, a }.paint())
}

/// Font pixels per 8x8 glyph pixel for a text style of `size` (px): 1 up to 19 px (8 px per
/// character, what plotters' own estimate gives an 18 px label, so that legend boxes fit),
/// 2 for 20 to 31 px (titles), and so on.
fn scale(size: f64) -> i32 {
    (((size + 4.0) / 12.0).floor() as i32).max(1)
}

/// A path through `points` (pixel centres).
fn polyline(points: &[BackendCoord], close: bool) -> Option<tiny_skia::Path> {
    let mut b = PathBuilder::new();
    let (first, rest) = points.split_first()?;
    b.move_to(first.0 as f32 + 0.5, first.1 as f32 + 0.5);
    for p in rest {
        b.line_to(p.0 as f32 + 0.5, p.1 as f32 + 0.5);
    }
    if close {
        b.close();
    }
    b.finish()
}

impl PixmapBackend<'_> {
    fn stroke(&mut self, points: &[BackendCoord], color: BackendColor, width: u32) {
        let (Some(p), Some(path)) = (paint(color), polyline(points, false)) else {
            return;
        };
        let stroke = Stroke {
            width: width.max(1) as f32,
            line_cap: LineCap::Round,
            ..Stroke::default()
        };
        self.pm
            .stroke_path(&path, &p, &stroke, Transform::identity(), None);
    }

    fn fill_rect(&mut self, x: f32, y: f32, w: f32, h: f32, p: &Paint) {
        if let Some(r) = Rect::from_xywh(x, y, w, h) {
            self.pm.fill_rect(r, p, Transform::identity(), None);
        }
    }
}

impl DrawingBackend for PixmapBackend<'_> {
    type ErrorType = NoError;

    fn get_size(&self) -> (u32, u32) {
        (self.pm.width(), self.pm.height())
    }

    fn ensure_prepared(&mut self) -> Drawn {
        Ok(())
    }

    fn present(&mut self) -> Drawn {
        Ok(())
    }

    fn draw_pixel(&mut self, point: BackendCoord, color: BackendColor) -> Drawn {
        if let Some(p) = paint(color) {
            self.fill_rect(point.0 as f32, point.1 as f32, 1.0, 1.0, &p);
        }
        Ok(())
    }

    fn draw_line<S: BackendStyle>(&mut self, from: BackendCoord, to: BackendCoord, s: &S) -> Drawn {
        self.stroke(&[from, to], s.color(), s.stroke_width());
        Ok(())
    }

    fn draw_rect<S: BackendStyle>(
        &mut self,
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        s: &S,
        fill: bool,
    ) -> Drawn {
        let (x0, y0) = upper_left;
        let (x1, y1) = bottom_right;
        if fill {
            if let Some(p) = paint(s.color()) {
                let (w, h) = ((x1 - x0 + 1) as f32, (y1 - y0 + 1) as f32);
                self.fill_rect(x0 as f32, y0 as f32, w, h, &p);
            }
        } else {
            let corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)];
            self.stroke(&corners, s.color(), s.stroke_width());
        }
        Ok(())
    }

    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        s: &S,
    ) -> Drawn {
        let points: Vec<BackendCoord> = path.into_iter().collect();
        self.stroke(&points, s.color(), s.stroke_width());
        Ok(())
    }

    fn draw_circle<S: BackendStyle>(
        &mut self,
        center: BackendCoord,
        radius: u32,
        s: &S,
        fill: bool,
    ) -> Drawn {
        let (Some(p), Some(path)) = (
            paint(s.color()),
            PathBuilder::from_circle(center.0 as f32 + 0.5, center.1 as f32 + 0.5, radius as f32),
        ) else {
            return Ok(());
        };
        if fill {
            self.pm
                .fill_path(&path, &p, FillRule::Winding, Transform::identity(), None);
        } else {
            let stroke = Stroke {
                width: s.stroke_width().max(1) as f32,
                ..Stroke::default()
            };
            self.pm
                .stroke_path(&path, &p, &stroke, Transform::identity(), None);
        }
        Ok(())
    }

    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        s: &S,
    ) -> Drawn {
        let points: Vec<BackendCoord> = vert.into_iter().collect();
        if let (Some(p), Some(path)) = (paint(s.color()), polyline(&points, true)) {
            self.pm
                .fill_path(&path, &p, FillRule::Winding, Transform::identity(), None);
        }
        Ok(())
    }

    fn estimate_text_size<T: BackendTextStyle>(
        &self,
        text: &str,
        style: &T,
    ) -> Result<(u32, u32), DrawingErrorKind<NoError>> {
        let k = scale(style.size()) as u32;
        let (w, h) = (text.chars().count() as u32 * 8 * k, 8 * k);
        Ok(match style.transform() {
            FontTransform::Rotate90 | FontTransform::Rotate270 => (h, w),
            _ => (w, h),
        })
    }

    fn draw_text<T: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &T,
        pos: BackendCoord,
    ) -> Drawn {
        let Some(p) = paint(style.color()) else {
            return Ok(());
        };
        // A smaller scale where the text would not fit the pixmap (a long title).
        let chars = text.chars().count() as i32;
        let room = self.pm.width().max(self.pm.height()) as i32 - 16;
        let mut k = scale(style.size());
        while k > 1 && chars * 8 * k > room {
            k -= 1;
        }
        // The text's extent along its own direction, then the anchor's offset.
        let (w, h) = (chars * 8 * k, 8 * k);
        let anchor = style.anchor();
        let dx = match anchor.h_pos {
            HPos::Left => 0,
            HPos::Center => -w / 2,
            HPos::Right => -w,
        };
        let dy = match anchor.v_pos {
            VPos::Top => 0,
            VPos::Center => -h / 2,
            VPos::Bottom => -h,
        };
        let transform = style.transform();
        for (col, row) in glyph_pixels(text) {
            // The font pixel's top left in the text's own frame, from the anchor.
            let (u, v) = (dx + col * k, dy + row * k);
            let (x, y) = match transform {
                FontTransform::None => (pos.0 + u, pos.1 + v),
                FontTransform::Rotate90 => (pos.0 - v - k, pos.1 + u),
                FontTransform::Rotate180 => (pos.0 - u - k, pos.1 - v - k),
                FontTransform::Rotate270 => (pos.0 + v, pos.1 - u - k),
            };
            self.fill_rect(x as f32, y as f32, k as f32, k as f32, &p);
        }
        Ok(())
    }
}
