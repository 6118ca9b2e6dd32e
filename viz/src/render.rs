//! Pictures of a state or a rollout, drawn on the CPU with `tiny-skia` (antialiased, no
//! system library, no GPU): [`render_png`] for one state, [`render_gif`] for an animated GIF
//! of a rollout, [`render_frame`] for the pixels.
//!
//! What is drawn: particles as filled circles, springs (and distance constraints) as thin
//! lines, triangles (and the boundary faces of tetrahedra) flat-shaded by a directional
//! light (two-sided Lambert), rigid bodies as their contact points joined by edges (as in
//! [`crate::export`]: a box's corners give its edges) plus a small axis frame (x red, y
//! green, z blue) at the centre of mass, and the ground plane, if the model has one, as a
//! grid. Everything is depth-sorted back to front (painter's algorithm), which is right for
//! the light scenes adflex simulates but may draw intersecting triangles in the wrong
//! order.
//!
//! The [`Camera`] is either given in [`RenderOptions::camera`] or fitted to the scene
//! ([`Camera::fit`]); a GIF fits one camera to the whole rollout so the view stays still.
//!
//! ```
//! use adflex_kernels::scenes::cloth;
//! use adflex_viz::render::{render_frame, RenderOptions};
//!
//! let scene = cloth::build::<f64>(4);
//! let opts = RenderOptions { width: 160, height: 120, ..RenderOptions::default() };
//! let pixmap = render_frame(&scene.model, &scene.initial, &opts).unwrap();
//! assert_eq!((pixmap.width(), pixmap.height()), (160, 120));
//! ```

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use adflex_kernels::model::{Model, State};
use adflex_runtime::{Real, Vec3};
use tiny_skia::{FillRule, LineCap, PathBuilder, Stroke, Transform};

pub use tiny_skia::Pixmap;

pub use crate::color::Rgba;
use crate::overlay::{self, Overlay, Values};
use crate::scene::{wide, Frame, Topology};
use crate::{Error, Result};

/// How a camera maps the scene onto the picture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// Perspective, with this field of view (degrees, in `(0, 180)`) across the shorter side
    /// of the picture.
    Perspective {
        /// Field of view (degrees).
        fov_degrees: f64,
    },
    /// Orthographic, showing this extent of the scene (m) across the shorter side of the
    /// picture.
    Orthographic {
        /// Visible extent (m).
        view_size: f64,
    },
}

/// Where the scene is seen from: the camera sits at `eye`, looks at `target`, and `up`
/// points up in the picture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Camera position (m).
    pub eye: Vec3<f64>,
    /// The point at the centre of the picture (m).
    pub target: Vec3<f64>,
    /// The direction that is up in the picture (need not be orthogonal to the view).
    pub up: Vec3<f64>,
    /// Perspective or orthographic.
    pub projection: Projection,
}

/// The field of view (degrees) of [`Camera::fit`].
pub const FIT_FOV_DEGREES: f64 = 35.0;

impl Camera {
    /// A perspective camera at `eye` looking at `target` with `fov_degrees` across the
    /// shorter side of the picture.
    ///
    /// ```
    /// use adflex_runtime::Vec3;
    /// use adflex_viz::render::Camera;
    /// let cam = Camera::looking_at(
    ///     Vec3::new(0.0, 1.0, 3.0),
    ///     Vec3::new(0.0, 0.0, 0.0),
    ///     Vec3::new(0.0, 1.0, 0.0),
    ///     40.0,
    /// );
    /// // The target lands in the middle of the picture.
    /// let (x, y) = cam.project(Vec3::zeros(), 200, 100).unwrap();
    /// assert!((x - 100.0).abs() < 1e-3 && (y - 50.0).abs() < 1e-3);
    /// ```
    pub fn looking_at(eye: Vec3<f64>, target: Vec3<f64>, up: Vec3<f64>, fov_degrees: f64) -> Self {
        Camera {
            eye,
            target,
            up,
            projection: Projection::Perspective { fov_degrees },
        }
    }

    /// An orthographic camera at `eye` looking at `target`, showing `view_size` metres across
    /// the shorter side of the picture.
    ///
    /// ```
    /// use adflex_runtime::Vec3;
    /// use adflex_viz::render::Camera;
    /// // Looking down the -z axis at a 2 m wide view.
    /// let cam = Camera::orthographic(Vec3::new(0.0, 0.0, 5.0), Vec3::zeros(), Vec3::y(), 2.0);
    /// let (x, _) = cam.project(Vec3::new(1.0, 0.0, 0.0), 100, 100).unwrap();
    /// assert!((x - 100.0).abs() < 1e-3);
    /// ```
    pub fn orthographic(eye: Vec3<f64>, target: Vec3<f64>, up: Vec3<f64>, view_size: f64) -> Self {
        Camera {
            eye,
            target,
            up,
            projection: Projection::Orthographic { view_size },
        }
    }

    /// A perspective camera ([`FIT_FOV_DEGREES`]) framing every particle and rigid body of
    /// every state, seen from above and in front: up is the ground normal if the model has
    /// a ground, else against gravity, else `+y`; the eye sits along `0.8 up + 0.6 a + b`
    /// from the centre, where `a`, `b` complete `up` to a right-handed frame (for up `+y`:
    /// `a = +x`, `b = +z`).
    ///
    /// ```
    /// use adflex_kernels::scenes::cloth;
    /// use adflex_viz::render::Camera;
    /// let scene = cloth::build::<f64>(4);
    /// let cam = Camera::fit(&scene.model, std::slice::from_ref(&scene.initial));
    /// assert!(cam.eye.y > cam.target.y);
    /// ```
    pub fn fit<R: Real>(model: &Model<R>, states: &[State<R>]) -> Self {
        Self::fit_from(model, states, default_direction(up_of(model)), up_of(model))
    }

    /// Like [`Camera::fit`] with the eye along `direction` (from the scene's centre) and
    /// `up` up in the picture.
    ///
    /// ```
    /// use adflex_kernels::scenes::cloth;
    /// use adflex_runtime::Vec3;
    /// use adflex_viz::render::Camera;
    /// let scene = cloth::build::<f64>(4);
    /// // Straight from above, +z up in the picture.
    /// let cam = Camera::fit_from(&scene.model, std::slice::from_ref(&scene.initial), Vec3::y(), Vec3::z());
    /// assert!(cam.eye.y > 1.0);
    /// ```
    pub fn fit_from<R: Real>(
        model: &Model<R>,
        states: &[State<R>],
        direction: Vec3<f64>,
        up: Vec3<f64>,
    ) -> Self {
        let topo = Topology::of(model);
        let frames: Vec<Frame> = states.iter().map(Frame::of).collect();
        let (c, r) = bounds(&topo, &frames, &[]);
        Self::fit_sphere(c, r, direction, up)
    }

    /// Like [`Camera::fit_from`], fitted to the overlay's markers, regions and ghosts too
    /// (so that a target off the path stays in the picture).
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::Vec3;
    /// use adflex_viz::overlay::{Marker, Overlay};
    /// use adflex_viz::render::Camera;
    /// let mut b = ModelBuilder::<f64>::new();
    /// b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
    /// let model = b.finalize();
    /// let far = Vec3::new(5.0, 0.0, 0.0);
    /// let overlay = Overlay { markers: vec![Marker::target(far, "goal")], ..Overlay::default() };
    /// let cam = Camera::fit_with(&model, &[model.state()], &overlay, Vec3::y(), Vec3::z());
    /// let (x, _) = cam.project(far, 640, 480).unwrap();
    /// assert!((0.0..640.0).contains(&x));
    /// ```
    pub fn fit_with<R: Real>(
        model: &Model<R>,
        states: &[State<R>],
        overlay: &Overlay,
        direction: Vec3<f64>,
        up: Vec3<f64>,
    ) -> Self {
        let topo = Topology::of(model);
        let frames: Vec<Frame> = states.iter().map(Frame::of).collect();
        let (c, r) = bounds(&topo, &frames, &overlay.points(&topo));
        Self::fit_sphere(c, r, direction, up)
    }

    /// A camera along `direction` from `c` that sees the sphere of radius `r` around it.
    fn fit_sphere(c: Vec3<f64>, r: f64, direction: Vec3<f64>, up: Vec3<f64>) -> Self {
        let dir = if direction.norm() > 0.0 && direction.iter().all(|v| v.is_finite()) {
            direction.normalize()
        } else {
            Vec3::z()
        };
        let half = (FIT_FOV_DEGREES.to_radians() * 0.5).sin();
        let dist = r / half * 1.05;
        Camera::looking_at(c + dir * dist, c, up, FIT_FOV_DEGREES)
    }

    /// The camera frame: right, up, forward (unit vectors), or `None` if degenerate.
    fn basis(&self) -> Option<[Vec3<f64>; 3]> {
        let f = (self.target - self.eye).try_normalize(1e-12)?;
        let r = f.cross(&self.up).try_normalize(1e-12)?;
        let u = r.cross(&f);
        Some([r, u, f])
    }

    fn view(&self, width: u32, height: u32) -> Option<View> {
        let [r, u, f] = self.basis()?;
        let short = width.min(height) as f64;
        let (scale, perspective) = match self.projection {
            Projection::Perspective { fov_degrees } => {
                if !(fov_degrees > 0.0 && fov_degrees < 180.0) {
                    return None;
                }
                (0.5 * short / (fov_degrees.to_radians() * 0.5).tan(), true)
            }
            Projection::Orthographic { view_size } => {
                if !(view_size > 0.0 && view_size.is_finite()) {
                    return None;
                }
                (short / view_size, false)
            }
        };
        let dist = (self.target - self.eye).norm();
        Some(View {
            eye: self.eye,
            r,
            u,
            f,
            scale,
            perspective,
            near: if perspective { 1e-3 * dist } else { f64::MIN },
            cx: width as f64 * 0.5,
            cy: height as f64 * 0.5,
        })
    }

    /// Where the world point `p` lands in a `width` x `height` picture (pixels from the
    /// top-left corner), or `None` if it is behind a perspective camera (or the camera is
    /// degenerate). See [`Camera::looking_at`] for an example.
    pub fn project(&self, p: Vec3<f64>, width: u32, height: u32) -> Option<(f32, f32)> {
        let v = self.view(width, height)?;
        let c = v.cam(p);
        if c.z <= v.near {
            return None;
        }
        let s = v.screen(c);
        Some((s.0 as f32, s.1 as f32))
    }
}

/// Up for the scene: the ground normal, else against gravity, else `+y`.
/// The direction [`Camera::fit`] looks from: above and to the side of the scene, `up` up.
fn default_direction(up: Vec3<f64>) -> Vec3<f64> {
    let a = if up.z.abs() < 0.9 {
        let b0 = Vec3::z() - up * up.z;
        let b = b0.normalize();
        (up.cross(&b), b)
    } else {
        let b0 = Vec3::x() - up * up.x;
        let b = b0.normalize();
        (up.cross(&b), b)
    };
    (up * 0.8 + a.0 * 0.6 + a.1).normalize()
}

fn up_of<R: Real>(model: &Model<R>) -> Vec3<f64> {
    if let Some(g) = model.ground() {
        if let Some(n) = wide(g.normal).try_normalize(1e-12) {
            return n;
        }
    }
    (-wide(model.gravity.get(0)))
        .try_normalize(1e-12)
        .filter(|v| v.iter().all(|c| c.is_finite()))
        .unwrap_or(Vec3::y())
}

/// The centre and radius of a sphere around every finite point of the frames (radius at
/// least a small fraction of the centre's size, and 0.5 m if there is nothing to frame).
fn bounds(topo: &Topology, frames: &[Frame], extra: &[Vec3<f64>]) -> (Vec3<f64>, f64) {
    let mut lo = Vec3::repeat(f64::MAX);
    let mut hi = Vec3::repeat(f64::MIN);
    let mut any = false;
    let finite_extra = extra.iter().filter(|p| p.iter().all(|c| c.is_finite()));
    for p in frames
        .iter()
        .flat_map(|f| f.all_points(topo))
        .chain(finite_extra.copied())
    {
        lo = lo.inf(&p);
        hi = hi.sup(&p);
        any = true;
    }
    if !any {
        return (Vec3::zeros(), 0.5);
    }
    let c = (lo + hi) * 0.5;
    let r = (hi - lo).norm() * 0.5 + topo.max_radius().max(0.0);
    let r = if r > 1e-9 { r } else { 0.5 };
    (c, r)
}

/// A camera set up for one picture size.
struct View {
    eye: Vec3<f64>,
    r: Vec3<f64>,
    u: Vec3<f64>,
    f: Vec3<f64>,
    scale: f64,
    perspective: bool,
    near: f64,
    cx: f64,
    cy: f64,
}

impl View {
    /// Camera coordinates (right, up, depth).
    fn cam(&self, p: Vec3<f64>) -> Vec3<f64> {
        let d = p - self.eye;
        Vec3::new(d.dot(&self.r), d.dot(&self.u), d.dot(&self.f))
    }
    /// Pixels of camera coordinates in front of the near plane.
    fn screen(&self, c: Vec3<f64>) -> (f64, f64) {
        let k = if self.perspective {
            self.scale / c.z
        } else {
            self.scale
        };
        (self.cx + c.x * k, self.cy - c.y * k)
    }
    /// Pixels per metre at depth `z`.
    fn pixels_per_metre(&self, z: f64) -> f64 {
        if self.perspective {
            self.scale / z
        } else {
            self.scale
        }
    }
    /// The point in pixels with its depth, if in front of the camera and finite.
    fn point(&self, p: Vec3<f64>) -> Option<((f32, f32), f64)> {
        let c = self.cam(p);
        if !c.iter().all(|v| v.is_finite()) || c.z <= self.near {
            return None;
        }
        let (x, y) = self.screen(c);
        Some(((x as f32, y as f32), c.z))
    }
    /// The segment in pixels, clipped to the near plane, with its mean depth.
    fn segment(&self, a: Vec3<f64>, b: Vec3<f64>) -> Option<([(f32, f32); 2], f64)> {
        let (mut ca, mut cb) = (self.cam(a), self.cam(b));
        if !ca.iter().chain(cb.iter()).all(|v| v.is_finite()) {
            return None;
        }
        if ca.z <= self.near && cb.z <= self.near {
            return None;
        }
        let near = self.near + 1e-9 * (ca.z.abs() + cb.z.abs());
        if ca.z <= near {
            ca = cb + (ca - cb) * ((cb.z - near) / (cb.z - ca.z));
        } else if cb.z <= near {
            cb = ca + (cb - ca) * ((ca.z - near) / (ca.z - cb.z));
        }
        let s = |c: Vec3<f64>| {
            let (x, y) = self.screen(c);
            (x as f32, y as f32)
        };
        Some(([s(ca), s(cb)], 0.5 * (ca.z + cb.z)))
    }
}

/// The size of the particles' circles.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PointRadius {
    /// Each particle's radius (the model's `particle_radius`, or its own) seen through the
    /// camera, at least 1.5 px.
    World,
    /// A fixed radius in pixels.
    Pixels(f32),
}

/// What to draw and how; `RenderOptions::default()` gives a 640 x 480 picture with
/// everything drawn and a fitted camera.
///
/// ```
/// use adflex_viz::render::{PointRadius, RenderOptions, Rgba};
/// let opts = RenderOptions {
///     width: 800,
///     height: 600,
///     point_radius: PointRadius::Pixels(2.0),
///     face_color: Rgba::rgb(200, 80, 80),
///     ..RenderOptions::default()
/// };
/// assert!(opts.draw_faces);
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Picture width (px, > 0; at most 65535 for a GIF).
    pub width: u32,
    /// Picture height (px, > 0; at most 65535 for a GIF).
    pub height: u32,
    /// The camera; `None` fits one to the states drawn ([`Camera::fit`]).
    pub camera: Option<Camera>,
    /// Background colour.
    pub background: Rgba,
    /// Draw the particles as circles.
    pub draw_points: bool,
    /// Draw springs and distance constraints as lines.
    pub draw_edges: bool,
    /// Draw triangles and tetrahedron boundary faces, shaded.
    pub draw_faces: bool,
    /// Draw rigid bodies (contact points, edges, axis frame).
    pub draw_bodies: bool,
    /// Draw the ground plane (if the model has one) as a grid.
    pub draw_ground: bool,
    /// Radius of the particles' circles.
    pub point_radius: PointRadius,
    /// Width of the edge lines (px).
    pub edge_width: f32,
    /// Direction towards the light (world frame; need not be unit).
    pub light: Vec3<f64>,
    /// Particle colour.
    pub point_color: Rgba,
    /// Edge colour.
    pub edge_color: Rgba,
    /// Face colour when fully lit.
    pub face_color: Rgba,
    /// Rigid body colour.
    pub body_color: Rgba,
    /// Ground colour (grid lines are drawn darker).
    pub ground_color: Rgba,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 640,
            height: 480,
            camera: None,
            background: Rgba::rgb(250, 250, 247),
            draw_points: true,
            draw_edges: true,
            draw_faces: true,
            draw_bodies: true,
            draw_ground: true,
            point_radius: PointRadius::World,
            edge_width: 1.0,
            light: Vec3::new(0.4, 1.0, 0.6),
            point_color: Rgba::rgb(40, 60, 110),
            edge_color: Rgba::rgb(70, 80, 100),
            face_color: Rgba::rgb(110, 160, 220),
            body_color: Rgba::rgb(215, 110, 45),
            ground_color: Rgba::rgb(226, 228, 224),
        }
    }
}

enum Shape {
    Tri([(f32, f32); 3], Rgba),
    Line([(f32, f32); 2], Rgba, f32),
    Disc((f32, f32), f32, Rgba),
    Ring((f32, f32), f32, Rgba),
}

/// What one picture draws besides the state: the overlay at state `k` of `history`, the
/// per-particle or per-edge values of that state, and where the ground is drawn (fixed for a
/// whole animation, so it does not move between frames).
struct Decor<'a> {
    overlay: &'a Overlay,
    k: usize,
    history: &'a [Frame],
    particle_values: Option<Vec<f64>>,
    edge_values: Option<Vec<f64>>,
    ground_box: (Vec3<f64>, f64),
}

/// The rest length (m) of each edge of [`Topology::of`]: the springs' and distance
/// constraints' own (so that an optimized rest length shows its true strain).
fn rest_lengths<R: Real>(model: &Model<R>) -> Vec<f64> {
    let mut out: Vec<f64> = Vec::new();
    if let Some(s) = model.springs() {
        out.extend(s.rest.to_vec().into_iter().map(|r| r.to_f64()));
    }
    if let Some(d) = &model.distance_constraints {
        out.extend(d.rest.to_vec().into_iter().map(|r| r.to_f64()));
    }
    out
}

/// Per-edge strain `(l - l0) / l0` at `frame`, `l0` from `rest` ([`rest_lengths`]).
fn edge_strain(topo: &Topology, rest: &[f64], frame: &Frame) -> Vec<f64> {
    topo.edges
        .iter()
        .zip(rest)
        .map(|(e, &l0)| {
            let (i, j) = (e[0] as usize, e[1] as usize);
            let l = (frame.x[i] - frame.x[j]).norm();
            if l0 > 0.0 {
                (l - l0) / l0
            } else {
                0.0
            }
        })
        .collect()
}

/// Draws one state with the given camera into a new pixmap.
fn draw(
    topo: &Topology,
    frame: &Frame,
    ground: Option<(Vec3<f64>, f64)>,
    cam: &Camera,
    o: &RenderOptions,
    decor: &Decor,
) -> Result<Pixmap> {
    if o.width == 0 || o.height == 0 {
        return Err(Error::Invalid(format!(
            "picture size {} x {} must be positive",
            o.width, o.height
        )));
    }
    let mut pm = Pixmap::new(o.width, o.height).ok_or_else(|| {
        Error::Invalid(format!(
            "picture size {} x {} is too large",
            o.width, o.height
        ))
    })?;
    frame.check(topo, None)?;
    let bg = o.background;
    pm.fill(tiny_skia::Color::from_rgba8(bg.r, bg.g, bg.b, bg.a));
    let view = cam.view(o.width, o.height).ok_or_else(|| {
        Error::Invalid(format!(
            "degenerate camera {cam:?} (eye at target, up along the view, bad field of view or size)"
        ))
    })?;
    let (centre, radius) = decor.ground_box;
    let bias = 0.02 * radius;

    if let (true, Some((n, offset))) = (o.draw_ground, ground) {
        draw_ground(&mut pm, &view, n, offset, centre, radius, o.ground_color);
    }
    for r in &decor.overlay.regions {
        let corners: Option<Vec<(f32, f32)>> = r
            .corners
            .iter()
            .map(|&p| view.point(p).map(|c| c.0))
            .collect();
        if let Some(path) = corners.as_deref().and_then(polygon) {
            let paint = r.color.paint();
            pm.fill_path(
                &path,
                &paint,
                FillRule::Winding,
                Transform::identity(),
                None,
            );
        }
    }
    for g in &decor.overlay.ghosts {
        draw_ghost(&mut pm, &view, topo, &g.frame(), g.color);
    }

    let mut shapes: Vec<(f64, Shape)> = Vec::new();
    let light = o.light.try_normalize(1e-12).unwrap_or(Vec3::y());
    if o.draw_faces {
        for f in &topo.faces {
            let p = f.map(|i| frame.x[i as usize]);
            let (Some(a), Some(b), Some(c)) =
                (view.point(p[0]), view.point(p[1]), view.point(p[2]))
            else {
                continue;
            };
            let n = (p[1] - p[0]).cross(&(p[2] - p[0]));
            let lambert = n.try_normalize(1e-300).map_or(0.0, |n| n.dot(&light).abs());
            let color = match (&decor.particle_values, &decor.overlay.color_by) {
                (Some(v), Some(c)) => {
                    let mean = f
                        .iter()
                        .map(|&i| v.get(i as usize).copied().unwrap_or(f64::NAN));
                    c.color(mean.sum::<f64>() / 3.0)
                        .scaled(0.65 + 0.35 * lambert)
                }
                _ => o.face_color.scaled(0.4 + 0.6 * lambert),
            };
            shapes.push(((a.1 + b.1 + c.1) / 3.0, Shape::Tri([a.0, b.0, c.0], color)));
        }
    }
    if o.draw_edges {
        for (k, e) in topo.edges.iter().enumerate() {
            if let Some((s, z)) = view.segment(frame.x[e[0] as usize], frame.x[e[1] as usize]) {
                let line = match (&decor.edge_values, &decor.overlay.color_by) {
                    (Some(v), Some(c)) => Shape::Line(s, c.color(v[k]), o.edge_width.max(2.0)),
                    _ => Shape::Line(s, o.edge_color, o.edge_width),
                };
                shapes.push((z - bias, line));
            }
        }
    }
    let disc = |z: f64, world: f64| match o.point_radius {
        PointRadius::Pixels(px) => px,
        PointRadius::World => ((world * view.pixels_per_metre(z)) as f32).max(1.5),
    };
    if o.draw_points {
        for (i, &p) in frame.x.iter().enumerate() {
            if let Some((s, z)) = view.point(p) {
                let color = match (&decor.particle_values, &decor.overlay.color_by) {
                    (Some(v), Some(c)) => c.color(v.get(i).copied().unwrap_or(f64::NAN)),
                    _ => o.point_color,
                };
                shapes.push((
                    z - 2.0 * bias,
                    Shape::Disc(s, disc(z, topo.radius_of(i)), color),
                ));
            }
        }
    }
    if o.draw_bodies {
        let world = frame.body_world_points(topo);
        for [a, b] in topo.body_edges() {
            if let Some((s, z)) = view.segment(world[a as usize], world[b as usize]) {
                shapes.push((z - bias, Shape::Line(s, o.body_color.scaled(0.8), 1.5)));
            }
        }
        for &p in &world {
            if let Some((s, z)) = view.point(p) {
                shapes.push((
                    z - 2.0 * bias,
                    Shape::Disc(s, disc(z, topo.radius).max(2.5), o.body_color),
                ));
            }
        }
        for (b, &(c, q)) in frame.bodies.iter().enumerate() {
            let pts = topo.body_points.get(b).map_or(&[][..], |v| &v[..]);
            let size = pts.iter().map(|p| p.norm()).fold(0.0, f64::max);
            let len = if size > 0.0 { 0.5 * size } else { 0.1 * radius };
            let axes = [
                (Vec3::x(), Rgba::rgb(220, 50, 50)),
                (Vec3::y(), Rgba::rgb(40, 170, 60)),
                (Vec3::z(), Rgba::rgb(50, 90, 220)),
            ];
            for (axis, color) in axes {
                let tip = c + crate::scene::rotate(q, axis * len);
                if let Some((s, z)) = view.segment(c, tip) {
                    shapes.push((z - 2.0 * bias, Shape::Line(s, color, 2.0)));
                }
            }
        }
    }
    // Back to front; stable, so equal depths keep faces < edges < points order.
    shapes.sort_by(|a, b| b.0.total_cmp(&a.0));
    // Trails, markers and keys on top of everything.
    for t in &decor.overlay.trails {
        let path: Vec<Vec3<f64>> = decor.history[..=decor.k]
            .iter()
            .filter_map(|f| f.x.get(t.particle).copied())
            .collect();
        for w in path.windows(2) {
            if let Some((s, _)) = view.segment(w[0], w[1]) {
                shapes.push((f64::MIN, Shape::Line(s, t.color, t.width)));
            }
        }
    }
    for m in &decor.overlay.markers {
        if let Some((c, _)) = view.point(m.position) {
            let r = m.radius;
            for (a, b) in [((-r, 0.0), (r, 0.0)), ((0.0, -r), (0.0, r))] {
                let seg = [(c.0 + a.0, c.1 + a.1), (c.0 + b.0, c.1 + b.1)];
                shapes.push((f64::MIN, Shape::Line(seg, m.color, 2.0)));
            }
            shapes.push((f64::MIN, Shape::Ring(c, r, m.color)));
        }
    }
    for (_, s) in shapes {
        match s {
            Shape::Tri(p, color) => {
                if let Some(path) = polygon(&p) {
                    let paint = color.paint();
                    pm.fill_path(
                        &path,
                        &paint,
                        FillRule::Winding,
                        Transform::identity(),
                        None,
                    );
                    // A thin outline of the same colour hides the seams between neighbours.
                    let stroke = Stroke {
                        width: 0.75,
                        ..Stroke::default()
                    };
                    pm.stroke_path(&path, &paint, &stroke, Transform::identity(), None);
                }
            }
            Shape::Line(p, color, width) => {
                let mut pb = PathBuilder::new();
                pb.move_to(p[0].0, p[0].1);
                pb.line_to(p[1].0, p[1].1);
                if let Some(path) = pb.finish() {
                    let stroke = Stroke {
                        width,
                        line_cap: LineCap::Round,
                        ..Stroke::default()
                    };
                    pm.stroke_path(&path, &color.paint(), &stroke, Transform::identity(), None);
                }
            }
            Shape::Ring(c, r, color) => {
                if let Some(path) = PathBuilder::from_circle(c.0, c.1, r) {
                    let stroke = Stroke {
                        width: 2.5,
                        ..Stroke::default()
                    };
                    pm.stroke_path(&path, &color.paint(), &stroke, Transform::identity(), None);
                }
            }
            Shape::Disc(c, r, color) => {
                if let Some(path) = PathBuilder::from_circle(c.0, c.1, r) {
                    pm.fill_path(
                        &path,
                        &color.paint(),
                        FillRule::Winding,
                        Transform::identity(),
                        None,
                    );
                    if r >= 2.5 {
                        let stroke = Stroke {
                            width: 0.8,
                            ..Stroke::default()
                        };
                        pm.stroke_path(
                            &path,
                            &color.scaled(0.6).paint(),
                            &stroke,
                            Transform::identity(),
                            None,
                        );
                    }
                }
            }
        }
    }
    if let Some(c) = &decor.overlay.color_by {
        overlay::color_bar(&mut pm, c);
    }
    overlay::key(&mut pm, decor.overlay);
    if let Some(caption) = decor.overlay.caption(decor.k) {
        overlay::text(&mut pm, 10.0, 8.0, caption, Rgba::rgb(20, 20, 20));
    }
    Ok(pm)
}

/// The closed polygon through `pts` (px), or `None` for fewer than three points.
fn polygon(pts: &[(f32, f32)]) -> Option<tiny_skia::Path> {
    let (first, rest) = pts.split_first()?;
    if rest.len() < 2 {
        return None;
    }
    let mut pb = PathBuilder::new();
    pb.move_to(first.0, first.1);
    for p in rest {
        pb.line_to(p.0, p.1);
    }
    pb.close();
    pb.finish()
}

/// `frame` faintly: its faces, edges and particles in `color` (translucent), under the state.
fn draw_ghost(pm: &mut Pixmap, view: &View, topo: &Topology, frame: &Frame, color: Rgba) {
    if frame.check(topo, None).is_err() {
        return;
    }
    let paint = color.paint();
    let stroke = Stroke {
        width: 1.5,
        line_cap: LineCap::Round,
        ..Stroke::default()
    };
    for f in &topo.faces {
        let p = f.map(|i| view.point(frame.x[i as usize]));
        if let [Some(a), Some(b), Some(c)] = p {
            if let Some(path) = polygon(&[a.0, b.0, c.0]) {
                pm.fill_path(
                    &path,
                    &paint,
                    FillRule::Winding,
                    Transform::identity(),
                    None,
                );
            }
        }
    }
    let mut segments: Vec<(Vec3<f64>, Vec3<f64>)> = topo
        .edges
        .iter()
        .map(|e| (frame.x[e[0] as usize], frame.x[e[1] as usize]))
        .collect();
    let world = frame.body_world_points(topo);
    segments.extend(
        topo.body_edges()
            .iter()
            .map(|e| (world[e[0] as usize], world[e[1] as usize])),
    );
    for (a, b) in segments {
        if let Some((s, _)) = view.segment(a, b) {
            let mut pb = PathBuilder::new();
            pb.move_to(s[0].0, s[0].1);
            pb.line_to(s[1].0, s[1].1);
            if let Some(path) = pb.finish() {
                pm.stroke_path(&path, &paint, &stroke, Transform::identity(), None);
            }
        }
    }
    if topo.faces.is_empty() {
        for i in 0..topo.particles {
            if let Some((c, z)) = view.point(frame.x[i]) {
                let r = ((topo.radius_of(i) * view.pixels_per_metre(z)) as f32).max(1.5);
                if let Some(path) = PathBuilder::from_circle(c.0, c.1, r) {
                    pm.fill_path(
                        &path,
                        &paint,
                        FillRule::Winding,
                        Transform::identity(),
                        None,
                    );
                }
            }
        }
    }
}

/// The ground plane `dot(n, x) = offset` around the scene: a filled square with a grid.
fn draw_ground(
    pm: &mut Pixmap,
    view: &View,
    n: Vec3<f64>,
    offset: f64,
    centre: Vec3<f64>,
    radius: f64,
    color: Rgba,
) {
    let Some(n) = n.try_normalize(1e-12) else {
        return;
    };
    let o = centre - n * (n.dot(&centre) - offset);
    let a = if n.x.abs() < 0.9 {
        Vec3::x()
    } else {
        Vec3::z()
    };
    let a = (a - n * n.dot(&a)).normalize();
    let b = n.cross(&a);
    let half = 1.3 * radius;
    let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .map(|(s, t)| view.point(o + a * (s * half) + b * (t * half)));
    if corners.iter().all(Option::is_some) {
        let mut pb = PathBuilder::new();
        for (k, c) in corners.iter().flatten().enumerate() {
            if k == 0 {
                pb.move_to(c.0 .0, c.0 .1);
            } else {
                pb.line_to(c.0 .0, c.0 .1);
            }
        }
        pb.close();
        if let Some(path) = pb.finish() {
            pm.fill_path(
                &path,
                &color.paint(),
                FillRule::Winding,
                Transform::identity(),
                None,
            );
        }
    }
    // A grid step of 1, 2 or 5 times a power of ten, about 10 lines across.
    let raw = 2.0 * half / 10.0;
    let p10 = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * p10)
        .find(|s| *s >= raw)
        .unwrap_or(raw);
    let k = (half / step).floor() as i64;
    let stroke = Stroke {
        width: 1.0,
        ..Stroke::default()
    };
    let paint = color.scaled(0.85).paint();
    for i in -k..=k {
        let t = i as f64 * step;
        for (p, q) in [
            (o + a * t - b * half, o + a * t + b * half),
            (o + b * t - a * half, o + b * t + a * half),
        ] {
            if let Some((s, _)) = view.segment(p, q) {
                let mut pb = PathBuilder::new();
                pb.move_to(s[0].0, s[0].1);
                pb.line_to(s[1].0, s[1].1);
                if let Some(path) = pb.finish() {
                    pm.stroke_path(&path, &paint, &stroke, Transform::identity(), None);
                }
            }
        }
    }
}

fn ground_of<R: Real>(model: &Model<R>) -> Option<(Vec3<f64>, f64)> {
    model.ground().map(|g| (wide(g.normal), g.offset.to_f64()))
}

/// Draws `state` into a new `width` x `height` pixmap (premultiplied RGBA; see
/// [`Pixmap::data`], [`Pixmap::take_demultiplied`]), with `options.camera` or a camera
/// fitted to this state.
///
/// Errors: [`Error::Invalid`] for a zero size or a degenerate camera.
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::{Tape, Vec3};
/// use adflex_viz::render::{render_frame, RenderOptions};
/// let mut b = ModelBuilder::<f64>::new();
/// let p = b.add_particle(Vec3::new(0.0, 0.0, 0.0), Vec3::zeros(), 1.0);
/// let q = b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
/// b.add_spring(p, q, 10.0, 0.0);
/// let model = b.finalize();
/// let opts = RenderOptions { width: 64, height: 48, ..Default::default() };
/// let pm = render_frame(&model, &model.state(), &opts).unwrap();
/// assert_eq!(pm.width(), 64);
/// ```
pub fn render_frame<R: Real>(
    model: &Model<R>,
    state: &State<R>,
    options: &RenderOptions,
) -> Result<Pixmap> {
    render_frame_with(
        model,
        std::slice::from_ref(state),
        0,
        options,
        &Overlay::default(),
    )
}

/// Everything a rollout's pictures share: its frames, the camera (`options.camera` or one
/// fitted to every state and the overlay's markers, regions and ghosts) and the ground's extent.
struct Framing {
    topo: Topology,
    frames: Vec<Frame>,
    /// The edges' rest lengths ([`rest_lengths`]), for strain colours.
    rest: Vec<f64>,
    camera: Camera,
    ground_box: (Vec3<f64>, f64),
}

impl Framing {
    fn of<R: Real>(
        model: &Model<R>,
        states: &[State<R>],
        options: &RenderOptions,
        overlay: &Overlay,
    ) -> Result<Self> {
        let topo = Topology::of(model);
        let frames: Vec<Frame> = states.iter().map(Frame::of).collect();
        for (k, f) in frames.iter().enumerate() {
            f.check(&topo, Some(k))?;
        }
        let ground_box = bounds(&topo, &frames, &overlay.points(&topo));
        let up = up_of(model);
        let camera = options.camera.unwrap_or_else(|| {
            Camera::fit_sphere(ground_box.0, ground_box.1, default_direction(up), up)
        });
        Ok(Framing {
            topo,
            frames,
            rest: rest_lengths(model),
            camera,
            ground_box,
        })
    }

    /// Draws state `k`.
    fn draw<R: Real>(
        &self,
        model: &Model<R>,
        states: &[State<R>],
        k: usize,
        options: &RenderOptions,
        overlay: &Overlay,
    ) -> Result<Pixmap> {
        let color_by = overlay.color_by.as_ref();
        let edge_values = match color_by.map(|c| &c.values) {
            Some(Values::EdgeStrain) => Some(edge_strain(&self.topo, &self.rest, &self.frames[k])),
            _ => None,
        };
        let decor = Decor {
            overlay,
            k,
            history: &self.frames,
            particle_values: color_by.and_then(|c| c.particle_values(k, &states[k])),
            edge_values,
            ground_box: self.ground_box,
        };
        draw(
            &self.topo,
            &self.frames[k],
            ground_of(model),
            &self.camera,
            options,
            &decor,
        )
    }
}

/// Draws state `k` of the rollout `states` with `overlay` (its trails run over
/// `states[..=k]`, its caption is `captions[k]`) into a new pixmap; the camera is
/// `options.camera` or one fitted to all of `states` and to the overlay's markers, regions and
/// ghosts,
/// so that every picture of one rollout is framed alike.
///
/// Errors: [`Error::Invalid`] for `k` outside `states` (or a state that does not fit the
/// model), otherwise as
/// [`render_frame`].
pub fn render_frame_with<R: Real>(
    model: &Model<R>,
    states: &[State<R>],
    k: usize,
    options: &RenderOptions,
    overlay: &Overlay,
) -> Result<Pixmap> {
    if k >= states.len() {
        return Err(Error::Invalid(format!(
            "state {k} asked of a rollout of {} states",
            states.len()
        )));
    }
    Framing::of(model, states, options, overlay)?.draw(model, states, k, options, overlay)
}

/// Draws `state` ([`render_frame`]) and writes it to `path` as a PNG.
///
/// ```
/// use adflex_kernels::scenes::cloth;
/// use adflex_viz::render::{render_png, RenderOptions};
/// let scene = cloth::build::<f64>(4);
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}.png", std::process::id()));
/// render_png(&path, &scene.model, &scene.initial, &RenderOptions::default()).unwrap();
/// assert!(std::fs::metadata(&path).unwrap().len() > 0);
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn render_png<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    state: &State<R>,
    options: &RenderOptions,
) -> Result<()> {
    let pm = render_frame(model, state, options)?;
    write_png(path.as_ref(), &pm)
}

/// Draws state `k` of `states` with `overlay` ([`render_frame_with`]) and writes it to `path`
/// as a PNG: e.g. the last state of an optimized rollout with the target marked, the trail of
/// the particle that had to reach it and the first guess as a ghost.
pub fn render_png_with<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    states: &[State<R>],
    k: usize,
    options: &RenderOptions,
    overlay: &Overlay,
) -> Result<()> {
    let pm = render_frame_with(model, states, k, options, overlay)?;
    write_png(path.as_ref(), &pm)
}

fn write_png(path: &Path, pm: &Pixmap) -> Result<()> {
    let bytes = pm.encode_png().map_err(|e| Error::Encode {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}

/// Draws every `every_nth` state (the first, then every `every_nth`-th after it: `ceil(n /
/// every_nth)` frames; 0 counts as 1) and writes them to `path` as an animated GIF that
/// plays `fps` frames per second and loops. The camera is `options.camera` or one fitted
/// to all the states, so the view stays still.
///
/// GIF delays are whole hundredths of a second, at least 2 (browsers slow down shorter
/// ones), so `fps` above 50 plays at 50. Colours are quantized to 256 per frame (NeuQuant).
///
/// Errors: [`Error::Empty`] for no states, [`Error::Invalid`] for a bad size (0 or above
/// 65535), camera or `fps`, [`Error::Io`] / [`Error::Encode`] naming `path`.
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::{Tape, Vec3};
/// use adflex_viz::render::{render_gif, RenderOptions};
/// let mut b = ModelBuilder::<f64>::new();
/// b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0), 1.0);
/// let model = b.finalize();
/// let mut tape = Tape::new();
/// let mut states = vec![model.state()];
/// for _ in 0..10 {
///     let s = SemiImplicitEuler.step(&model, &mut tape, states.last().unwrap(), None, 0.05).unwrap();
///     states.push(s);
/// }
/// let opts = RenderOptions { width: 80, height: 60, ..Default::default() };
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}.gif", std::process::id()));
/// render_gif(&path, &model, &states, &opts, 10.0, 2).unwrap();
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn render_gif<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    states: &[State<R>],
    options: &RenderOptions,
    fps: f64,
    every_nth: usize,
) -> Result<()> {
    let none = Overlay::default();
    render_gif_with(path, model, states, options, &none, fps, every_nth)
}

/// [`render_gif`] with an [`Overlay`]: each frame `k` shows the trails up to state `k` and
/// caption `k`; one camera and one ground for the whole animation.
pub fn render_gif_with<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    states: &[State<R>],
    options: &RenderOptions,
    overlay: &Overlay,
    fps: f64,
    every_nth: usize,
) -> Result<()> {
    let path = path.as_ref();
    if states.is_empty() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            what: "the list of states is empty",
        });
    }
    if !(fps.is_finite() && fps > 0.0) {
        return Err(Error::Invalid(format!(
            "fps must be finite and > 0 (got {fps})"
        )));
    }
    let (Ok(w), Ok(h)) = (u16::try_from(options.width), u16::try_from(options.height)) else {
        return Err(Error::Invalid(format!(
            "a GIF is at most 65535 x 65535 px (asked {} x {})",
            options.width, options.height
        )));
    };
    let framing = Framing::of(model, states, options, overlay)?;
    let delay = (100.0 / fps).round().clamp(2.0, u16::MAX as f64) as u16;
    let file = File::create(path).map_err(|e| Error::io(path, e))?;
    let encode = |e: gif::EncodingError| match e {
        gif::EncodingError::Io(e) => Error::io(path, e),
        e => Error::Encode {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
    };
    let mut enc = gif::Encoder::new(BufWriter::new(file), w, h, &[]).map_err(encode)?;
    enc.set_repeat(gif::Repeat::Infinite).map_err(encode)?;
    for k in (0..states.len()).step_by(every_nth.max(1)) {
        let pm = framing.draw(model, states, k, options, overlay)?;
        let mut rgba = pm.take_demultiplied();
        let mut frame = gif::Frame::from_rgba_speed(w, h, &mut rgba, 10);
        frame.delay = delay;
        enc.write_frame(&frame).map_err(encode)?;
    }
    let w = enc.into_inner().map_err(encode)?;
    w.into_inner()
        .map_err(|e| Error::io(path, e.into_error()))?
        .sync_all()
        .map_err(|e| Error::io(path, e))
}
