//! Frames and rollouts as files other tools open.
//!
//! - **PLY** ([`write_ply`]) and **OBJ** ([`write_obj`]): one mesh per state, for Blender,
//!   MeshLab or ParaView; [`write_sequence`] writes `frame_0000.ply`, `frame_0001.ply`, ...
//!   which those tools load as an animated sequence (Blender: a mesh-sequence add-on or
//!   *Stop-motion OBJ*; ParaView: open the numbered files as a group).
//! - **USD** ([`write_usda`]): a whole rollout in one ASCII stage with time-sampled points,
//!   for Omniverse, Blender (File > Import > Universal Scene Description) or usdview.
//!
//! What a frame holds: the vertices are the particle positions (m), in particle order, then,
//! for each rigid body, its contact points in world coordinates (bodies have no mesh in
//! adflex: their contact points, joined by edges, show the pose: each point to the nearest
//! point of its body in each body-axis direction that shares its other two coordinates, so
//! contact points at a box's corners give the box's 12 edges; points that share no such
//! line are each joined to their two nearest instead). Faces are the model's triangles, then the boundary faces of its tetrahedra
//! (those not already among the triangles), oriented outwards. Edges are the springs, then
//! the XPBD distance constraints, then the body edges.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_runtime::Vec3;
//! use adflex_viz::export::{self, Format};
//!
//! let mut b = ModelBuilder::<f64>::new();
//! let p0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 1.0);
//! let p1 = b.add_particle(Vec3::new(1.0, 1.0, 0.0), Vec3::zeros(), 1.0);
//! let p2 = b.add_particle(Vec3::new(0.0, 1.0, 1.0), Vec3::zeros(), 1.0);
//! b.add_spring(p0, p1, 100.0, 0.1);
//! b.add_triangle(p0, p1, p2);
//! let model = b.finalize();
//! let states = vec![model.state(), model.state()];
//!
//! let dir = std::env::temp_dir().join(format!("adflex-viz-doc-export-{}", std::process::id()));
//! let files = export::write_sequence(&dir, &model, &states, Format::Obj).unwrap();
//! assert_eq!(files.len(), 2);
//! assert!(files[0].ends_with("frame_0000.obj"));
//! # std::fs::remove_dir_all(&dir).ok();
//! ```

use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use adflex_kernels::model::{Model, State};
use adflex_runtime::{Real, Vec3};

use crate::scene::{Frame, Topology};
use crate::{Error, Result};

/// The file format of [`write_sequence`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Format {
    /// ASCII PLY ([`write_ply`]), extension `.ply`.
    #[default]
    Ply,
    /// Binary little-endian PLY ([`write_ply_binary`]), extension `.ply`: smaller and faster
    /// to load for large scenes.
    PlyBinary,
    /// Wavefront OBJ ([`write_obj`]), extension `.obj`.
    Obj,
}

impl Format {
    /// The file extension, without the dot.
    ///
    /// ```
    /// assert_eq!(adflex_viz::export::Format::Obj.extension(), "obj");
    /// ```
    pub fn extension(self) -> &'static str {
        match self {
            Format::Ply | Format::PlyBinary => "ply",
            Format::Obj => "obj",
        }
    }
}

/// One frame's mesh: vertices, faces and edges, as every format writes it.
struct Mesh {
    vertices: Vec<Vec3<f64>>,
    faces: Vec<[u32; 3]>,
    edges: Vec<[u32; 2]>,
}

impl Mesh {
    fn new(topo: &Topology, frame: &Frame, index: Option<usize>) -> Result<Self> {
        frame.check(topo, index)?;
        let mut vertices = frame.x.clone();
        let first = vertices.len() as u32;
        vertices.extend(frame.body_world_points(topo));
        let mut edges = topo.edges.clone();
        edges.extend(
            topo.body_edges()
                .into_iter()
                .map(|[a, b]| [a + first, b + first]),
        );
        Ok(Mesh {
            vertices,
            faces: topo.faces.clone(),
            edges,
        })
    }
}

fn create(path: &Path) -> Result<BufWriter<File>> {
    File::create(path)
        .map(BufWriter::new)
        .map_err(|e| Error::io(path, e))
}

fn finish(path: &Path, w: BufWriter<File>) -> Result<()> {
    w.into_inner()
        .map_err(|e| Error::io(path, e.into_error()))?
        .sync_all()
        .map_err(|e| Error::io(path, e))
}

fn ply_header(mesh: &Mesh, format: &str) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "ply\nformat {format} 1.0\ncomment written by adflex-viz\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         element face {}\nproperty list uchar int vertex_indices\n\
         element edge {}\nproperty int vertex1\nproperty int vertex2\nend_header\n",
        mesh.vertices.len(),
        mesh.faces.len(),
        mesh.edges.len()
    );
    h
}

fn write_ply_mesh(path: &Path, mesh: &Mesh, binary: bool) -> Result<()> {
    let mut w = create(path)?;
    let io = |e| Error::io(path, e);
    if binary {
        w.write_all(ply_header(mesh, "binary_little_endian").as_bytes())
            .map_err(io)?;
        for v in &mesh.vertices {
            for c in v.iter() {
                w.write_all(&(*c as f32).to_le_bytes()).map_err(io)?;
            }
        }
        for f in &mesh.faces {
            w.write_all(&[3u8]).map_err(io)?;
            for &i in f {
                w.write_all(&(i as i32).to_le_bytes()).map_err(io)?;
            }
        }
        for e in &mesh.edges {
            for &i in e {
                w.write_all(&(i as i32).to_le_bytes()).map_err(io)?;
            }
        }
    } else {
        w.write_all(ply_header(mesh, "ascii").as_bytes())
            .map_err(io)?;
        for v in &mesh.vertices {
            writeln!(
                w,
                "{} {} {}",
                Num(v.x as f32),
                Num(v.y as f32),
                Num(v.z as f32)
            )
            .map_err(io)?;
        }
        for f in &mesh.faces {
            writeln!(w, "3 {} {} {}", f[0], f[1], f[2]).map_err(io)?;
        }
        for e in &mesh.edges {
            writeln!(w, "{} {}", e[0], e[1]).map_err(io)?;
        }
    }
    finish(path, w)
}

fn write_obj_mesh(path: &Path, mesh: &Mesh) -> Result<()> {
    let mut w = create(path)?;
    let io = |e| Error::io(path, e);
    writeln!(
        w,
        "# written by adflex-viz: {} vertices, {} faces, {} lines",
        mesh.vertices.len(),
        mesh.faces.len(),
        mesh.edges.len()
    )
    .map_err(io)?;
    writeln!(w, "o adflex").map_err(io)?;
    for v in &mesh.vertices {
        writeln!(w, "v {} {} {}", v.x, v.y, v.z).map_err(io)?;
    }
    for f in &mesh.faces {
        writeln!(w, "f {} {} {}", f[0] + 1, f[1] + 1, f[2] + 1).map_err(io)?;
    }
    for e in &mesh.edges {
        writeln!(w, "l {} {}", e[0] + 1, e[1] + 1).map_err(io)?;
    }
    finish(path, w)
}

/// Writes `state` as an ASCII PLY file: `vertex` (x, y, z as float), `face`
/// (`vertex_indices`, triangles) and `edge` (`vertex1`, `vertex2`) elements; see the
/// [module docs](self) for what they hold.
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::Vec3;
/// let mut b = ModelBuilder::<f64>::new();
/// let p = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 1.0);
/// let q = b.add_particle(Vec3::new(1.0, 1.0, 0.0), Vec3::zeros(), 1.0);
/// b.add_spring(p, q, 100.0, 0.0);
/// let model = b.finalize();
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}.ply", std::process::id()));
/// adflex_viz::export::write_ply(&path, &model, &model.state()).unwrap();
/// let text = std::fs::read_to_string(&path).unwrap();
/// assert!(text.contains("element vertex 2") && text.contains("element edge 1"));
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn write_ply<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    state: &State<R>,
) -> Result<()> {
    let mesh = Mesh::new(&Topology::of(model), &Frame::of(state), None)?;
    write_ply_mesh(path.as_ref(), &mesh, false)
}

/// Writes `state` as a binary little-endian PLY file, with the same elements as
/// [`write_ply`] (positions as 32-bit floats, indices as 32-bit ints).
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::Vec3;
/// let mut b = ModelBuilder::<f64>::new();
/// b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 1.0);
/// let model = b.finalize();
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}-b.ply", std::process::id()));
/// adflex_viz::export::write_ply_binary(&path, &model, &model.state()).unwrap();
/// let bytes = std::fs::read(&path).unwrap();
/// assert!(bytes.starts_with(b"ply\nformat binary_little_endian 1.0"));
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn write_ply_binary<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    state: &State<R>,
) -> Result<()> {
    let mesh = Mesh::new(&Topology::of(model), &Frame::of(state), None)?;
    write_ply_mesh(path.as_ref(), &mesh, true)
}

/// Writes `state` as a Wavefront OBJ file: `v` lines (vertices), `f` lines (triangles) and
/// `l` lines (edges), 1-based; see the [module docs](self) for what they hold.
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::Vec3;
/// let mut b = ModelBuilder::<f64>::new();
/// let p = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 1.0);
/// let q = b.add_particle(Vec3::new(1.0, 1.0, 0.0), Vec3::zeros(), 1.0);
/// b.add_spring(p, q, 100.0, 0.0);
/// let model = b.finalize();
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}.obj", std::process::id()));
/// adflex_viz::export::write_obj(&path, &model, &model.state()).unwrap();
/// let text = std::fs::read_to_string(&path).unwrap();
/// assert!(text.contains("\nl 1 2\n"));
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn write_obj<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    state: &State<R>,
) -> Result<()> {
    let mesh = Mesh::new(&Topology::of(model), &Frame::of(state), None)?;
    write_obj_mesh(path.as_ref(), &mesh)
}

/// Writes each state to `dir/frame_0000.<ext>`, `dir/frame_0001.<ext>`, ... (creating `dir`
/// if needed; more than 10000 states give longer numbers) and returns the paths in order.
/// An empty `states` is an [`Error::Empty`].
///
/// See the [module docs](self) for an example.
pub fn write_sequence<R: Real>(
    dir: impl AsRef<Path>,
    model: &Model<R>,
    states: &[State<R>],
    format: Format,
) -> Result<Vec<PathBuf>> {
    let dir = dir.as_ref();
    if states.is_empty() {
        return Err(Error::Empty {
            path: dir.to_path_buf(),
            what: "the list of states is empty",
        });
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let topo = Topology::of(model);
    let mut paths = Vec::with_capacity(states.len());
    for (k, s) in states.iter().enumerate() {
        let path = dir.join(format!("frame_{k:04}.{}", format.extension()));
        let mesh = Mesh::new(&topo, &Frame::of(s), Some(k))?;
        match format {
            Format::Ply => write_ply_mesh(&path, &mesh, false)?,
            Format::PlyBinary => write_ply_mesh(&path, &mesh, true)?,
            Format::Obj => write_obj_mesh(&path, &mesh)?,
        }
        paths.push(path);
    }
    Ok(paths)
}

/// The checks every rollout file makes (states, `fps` finite and `> 0`, each state fits the
/// model), then the model's topology and the states' frames.
pub(crate) fn rollout<R: Real>(
    path: &Path,
    model: &Model<R>,
    states: &[State<R>],
    fps: f64,
) -> Result<(Topology, Vec<Frame>)> {
    if states.is_empty() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            what: "the list of states is empty",
        });
    }
    if !(fps.is_finite() && fps > 0.0) {
        return Err(Error::Invalid(format!(
            "fps must be finite and > 0 (got {fps}) for {}",
            path.display()
        )));
    }
    let topo = Topology::of(model);
    let frames: Vec<Frame> = states.iter().map(Frame::of).collect();
    for (k, f) in frames.iter().enumerate() {
        f.check(&topo, Some(k))?;
    }
    Ok((topo, frames))
}

/// A coordinate as USD and PLY readers parse it (`nan`, `inf`, `-inf` for non-finite values;
/// Rust writes `NaN`).
struct Num(f32);

impl std::fmt::Display for Num {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            v if v.is_nan() => f.write_str("nan"),
            v if v.is_infinite() => f.write_str(if v > 0.0 { "inf" } else { "-inf" }),
            v => write!(f, "{v}"),
        }
    }
}

fn point(out: &mut String, p: Vec3<f64>) {
    let _ = write!(
        out,
        "({}, {}, {})",
        Num(p.x as f32),
        Num(p.y as f32),
        Num(p.z as f32)
    );
}

fn point_list(out: &mut String, pts: impl IntoIterator<Item = Vec3<f64>>) {
    out.push('[');
    for (k, p) in pts.into_iter().enumerate() {
        if k > 0 {
            out.push_str(", ");
        }
        point(out, p);
    }
    out.push(']');
}

fn int_list(out: &mut String, v: impl IntoIterator<Item = u32>) {
    out.push('[');
    for (k, i) in v.into_iter().enumerate() {
        if k > 0 {
            out.push_str(", ");
        }
        let _ = write!(out, "{i}");
    }
    out.push(']');
}

/// Half the width (m) of point `i` of a prim: what USD's extent computation grows it by.
type Pad<'a> = &'a dyn Fn(usize) -> f64;

/// The bounding box `[min, max]` of the finite points, point `i` grown by `pad(i)` (m) on every
/// side, as USD's own extent computation does; `None` if no point is finite.
fn bounds(pts: &[Vec3<f64>], pad: Pad) -> Option<[Vec3<f64>; 2]> {
    let mut it = pts
        .iter()
        .enumerate()
        .filter(|(_, p)| p.iter().all(|c| c.is_finite()))
        .map(|(i, p)| (p - Vec3::repeat(pad(i)), p + Vec3::repeat(pad(i))));
    let first = it.next()?;
    let (lo, hi) = it.fold(first, |(lo, hi), (a, b)| (lo.inf(&a), hi.sup(&b)));
    Some([lo, hi])
}

/// Time-sampled points and their extent (`pad`: see [`bounds`]):
/// `point3f[] points.timeSamples = { 0: [...], ... }` and
/// `float3[] extent.timeSamples = { 0: [(min), (max)], ... }`, which a boundable prim should
/// author (renderers and `usdview` cull by it).
fn sampled_points(out: &mut String, indent: &str, frames: &[Vec<Vec3<f64>>], pad: Pad) {
    let _ = writeln!(out, "{indent}point3f[] points.timeSamples = {{");
    for (k, pts) in frames.iter().enumerate() {
        let _ = write!(out, "{indent}    {k}: ");
        point_list(out, pts.iter().copied());
        out.push_str(",\n");
    }
    let _ = writeln!(out, "{indent}}}");
    let _ = writeln!(out, "{indent}float3[] extent.timeSamples = {{");
    for (k, pts) in frames.iter().enumerate() {
        if let Some(b) = bounds(pts, pad) {
            let _ = write!(out, "{indent}    {k}: ");
            point_list(out, b);
            out.push_str(",\n");
        }
    }
    let _ = writeln!(out, "{indent}}}");
}

/// A static extent (see [`sampled_points`]): `float3[] extent = [(min), (max)]`.
fn static_extent(out: &mut String, indent: &str, pts: &[Vec3<f64>], pad: Pad) {
    if let Some(b) = bounds(pts, pad) {
        let _ = write!(out, "{indent}float3[] extent = ");
        point_list(out, b);
        out.push('\n');
    }
}

/// Writes a rollout as a USD ASCII stage (`.usda`): time code `k` is `states[k]`, played at
/// `fps` time codes per second (`startTimeCode = 0`, `endTimeCode = states.len() - 1`,
/// `upAxis = "Y"`, `metersPerUnit = 1`).
///
/// Under the default prim `/World`:
/// - `Mesh "mesh"` when the model has faces (triangles, tetrahedron boundaries): all the
///   particle positions as time-sampled `points`, the faces as
///   `faceVertexCounts`/`faceVertexIndices`;
/// - otherwise `Points "particles"` (time-sampled `points`, `widths` = particle diameter,
///   one per point if the model has per-particle radii)
///   and, when the model has springs or distance constraints, `BasisCurves "springs"`
///   (linear, two time-sampled points per edge);
/// - `Xform "body_<i>"` per rigid body with time-sampled `xformOp:translate` and
///   `xformOp:orient` (`quatf`, `(w, x, y, z)`), a child `Points "contacts"` holding its
///   contact points in body frame and a child `BasisCurves "edges"` joining them (see the
///   [module docs](self)).
///
/// An empty `states` is an [`Error::Empty`]; `fps` must be finite and `> 0`.
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::Vec3;
/// let mut b = ModelBuilder::<f64>::new();
/// b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 1.0);
/// let model = b.finalize();
/// let states = vec![model.state(); 3];
/// let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}.usda", std::process::id()));
/// adflex_viz::export::write_usda(&path, &model, &states, 30.0).unwrap();
/// let text = std::fs::read_to_string(&path).unwrap();
/// assert!(text.starts_with("#usda 1.0") && text.contains("endTimeCode = 2"));
/// # std::fs::remove_file(&path).ok();
/// ```
pub fn write_usda<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    states: &[State<R>],
    fps: f64,
) -> Result<()> {
    let path = path.as_ref();
    let (topo, frames) = rollout(path, model, states, fps)?;
    let mut s = String::new();
    let _ = write!(
        s,
        "#usda 1.0\n(\n    doc = \"adflex rollout: {} frames\"\n    defaultPrim = \"World\"\n    \
         startTimeCode = 0\n    endTimeCode = {}\n    timeCodesPerSecond = {fps}\n    \
         framesPerSecond = {fps}\n    upAxis = \"Y\"\n    metersPerUnit = 1\n)\n\n\
         def Xform \"World\"\n{{\n",
        frames.len(),
        frames.len() - 1
    );
    let width = 2.0 * topo.radius;
    let ind = "        ";
    if !topo.faces.is_empty() {
        s.push_str("    def Mesh \"mesh\"\n    {\n");
        s.push_str(ind);
        s.push_str("int[] faceVertexCounts = ");
        int_list(&mut s, topo.faces.iter().map(|_| 3));
        s.push('\n');
        s.push_str(ind);
        s.push_str("int[] faceVertexIndices = ");
        int_list(&mut s, topo.faces.iter().flatten().copied());
        s.push('\n');
        let xs: Vec<Vec<Vec3<f64>>> = frames.iter().map(|f| f.x.clone()).collect();
        sampled_points(&mut s, ind, &xs, &|_| 0.0);
        let _ = writeln!(s, "{ind}uniform token subdivisionScheme = \"none\"");
        let _ = writeln!(s, "{ind}uniform bool doubleSided = 1");
        let _ = writeln!(
            s,
            "{ind}color3f[] primvars:displayColor = [(0.35, 0.55, 0.8)]"
        );
        s.push_str("    }\n");
    } else if topo.particles > 0 {
        s.push_str("    def Points \"particles\"\n    {\n");
        let xs: Vec<Vec<Vec3<f64>>> = frames.iter().map(|f| f.x.clone()).collect();
        // Half the widths written below, in their f32 rounding.
        let half = |i: usize| {
            let r = if topo.radii.is_empty() {
                topo.radius
            } else {
                topo.radius_of(i)
            };
            0.5 * (2.0 * r) as f32 as f64
        };
        sampled_points(&mut s, ind, &xs, &half);
        if topo.radii.is_empty() {
            let _ = writeln!(
                s,
                "{ind}float[] widths = [{}] (\n{ind}    interpolation = \"constant\"\n{ind})",
                width as f32
            );
        } else {
            // Per-particle radii: one width per point.
            let widths: Vec<String> = (0..topo.particles)
                .map(|i| Num((2.0 * topo.radius_of(i)) as f32).to_string())
                .collect();
            let _ = writeln!(
                s,
                "{ind}float[] widths = [{}] (\n{ind}    interpolation = \"vertex\"\n{ind})",
                widths.join(", ")
            );
        }
        let _ = writeln!(
            s,
            "{ind}color3f[] primvars:displayColor = [(0.2, 0.3, 0.5)]"
        );
        s.push_str("    }\n");
        if !topo.edges.is_empty() {
            s.push_str("    def BasisCurves \"springs\"\n    {\n");
            let _ = writeln!(s, "{ind}uniform token type = \"linear\"");
            s.push_str(ind);
            s.push_str("int[] curveVertexCounts = ");
            int_list(&mut s, topo.edges.iter().map(|_| 2));
            s.push('\n');
            let ends: Vec<Vec<Vec3<f64>>> = frames
                .iter()
                .map(|f| {
                    topo.edges
                        .iter()
                        .flat_map(|e| [f.x[e[0] as usize], f.x[e[1] as usize]])
                        .collect()
                })
                .collect();
            let half = 0.5 * (width * 0.3) as f32 as f64;
            sampled_points(&mut s, ind, &ends, &|_| half);
            let _ = writeln!(
                s,
                "{ind}float[] widths = [{}] (\n{ind}    interpolation = \"constant\"\n{ind})",
                (width * 0.3) as f32
            );
            let _ = writeln!(
                s,
                "{ind}color3f[] primvars:displayColor = [(0.4, 0.4, 0.45)]"
            );
            s.push_str("    }\n");
        }
    }
    for (b, pts) in topo.body_points.iter().enumerate() {
        let _ = writeln!(s, "    def Xform \"body_{b}\"\n    {{");
        let _ = writeln!(s, "{ind}double3 xformOp:translate.timeSamples = {{");
        for (k, f) in frames.iter().enumerate() {
            let c = f.bodies.get(b).map_or(Vec3::zeros(), |b| b.0);
            let _ = writeln!(s, "{ind}    {k}: ({}, {}, {}),", c.x, c.y, c.z);
        }
        let _ = writeln!(s, "{ind}}}");
        let _ = writeln!(s, "{ind}quatf xformOp:orient.timeSamples = {{");
        for (k, f) in frames.iter().enumerate() {
            let q = f.bodies.get(b).map_or([1.0, 0.0, 0.0, 0.0], |b| b.1);
            let q = q.map(|c| c as f32);
            let _ = writeln!(s, "{ind}    {k}: ({}, {}, {}, {}),", q[0], q[1], q[2], q[3]);
        }
        let _ = writeln!(s, "{ind}}}");
        let _ = writeln!(
            s,
            "{ind}uniform token[] xformOpOrder = [\"xformOp:translate\", \"xformOp:orient\"]"
        );
        if !pts.is_empty() {
            let _ = writeln!(s, "\n{ind}def Points \"contacts\"\n{ind}{{");
            let _ = write!(s, "{ind}    point3f[] points = ");
            point_list(&mut s, pts.iter().copied());
            s.push('\n');
            let contact_width = (width.max(1e-3) * 2.0) as f32 as f64;
            static_extent(&mut s, &format!("{ind}    "), pts, &|_| 0.5 * contact_width);
            let _ = writeln!(
                s,
                "{ind}    float[] widths = [{}] (\n{ind}        interpolation = \"constant\"\n{ind}    )",
                (width.max(1e-3) * 2.0) as f32
            );
            let _ = writeln!(
                s,
                "{ind}    color3f[] primvars:displayColor = [(0.8, 0.4, 0.2)]"
            );
            let _ = writeln!(s, "{ind}}}");
        }
        let edges = topo.body_edges_of(b);
        if !edges.is_empty() {
            let _ = writeln!(s, "\n{ind}def BasisCurves \"edges\"\n{ind}{{");
            let _ = writeln!(s, "{ind}    uniform token type = \"linear\"");
            let _ = write!(s, "{ind}    int[] curveVertexCounts = ");
            int_list(&mut s, edges.iter().map(|_| 2));
            s.push('\n');
            let _ = write!(s, "{ind}    point3f[] points = ");
            let ends: Vec<Vec3<f64>> = edges
                .iter()
                .flat_map(|e| [pts[e[0] as usize], pts[e[1] as usize]])
                .collect();
            point_list(&mut s, ends.iter().copied());
            s.push('\n');
            let edge_width = (width.max(1e-3) * 0.5) as f32 as f64;
            static_extent(&mut s, &format!("{ind}    "), &ends, &|_| 0.5 * edge_width);
            let _ = writeln!(
                s,
                "{ind}    float[] widths = [{}] (\n{ind}        interpolation = \"constant\"\n{ind}    )",
                (width.max(1e-3) * 0.5) as f32
            );
            let _ = writeln!(
                s,
                "{ind}    color3f[] primvars:displayColor = [(0.8, 0.4, 0.2)]"
            );
            let _ = writeln!(s, "{ind}}}");
        }
        s.push_str("    }\n");
    }
    s.push_str("}\n");
    let mut w = create(path)?;
    w.write_all(s.as_bytes()).map_err(|e| Error::io(path, e))?;
    finish(path, w)
}
