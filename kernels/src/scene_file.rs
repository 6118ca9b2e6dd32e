//! Scene files: a [`ModelBuilder`] from JSON ([`ModelBuilder::from_json_str`]) or TOML
//! ([`ModelBuilder::from_toml_str`]).
//!
//! A malformed file gives a [`SceneError`] naming the field (a path such as
//! `springs[3].ke`) and its line; nothing in a file can make the reader panic. Every section
//! is optional; unknown fields are errors (a typo is not silently ignored). Particles are
//! numbered in file order: first `particles`, then the particles of each `cloth_grids` entry.
//!
//! ```
//! use adflex_kernels::ModelBuilder;
//! let json = r#"{
//!     "gravity": [0, -9.8, 0],
//!     "particles": [
//!         { "x": [0, 1, 0], "mass": 0 },
//!         { "x": [0.5, 1, 0], "mass": 0.1 }
//!     ],
//!     "springs": [ { "i": 0, "j": 1, "ke": 100, "kd": 0.1 } ],
//!     "ground": {}
//! }"#;
//! let model = ModelBuilder::<f32>::from_json_str(json).unwrap().finalize();
//! assert_eq!(model.springs.unwrap().len(), 1);
//!
//! let bad = "[[particles]]\nx = [0, 1, 0]\nmass = \"heavy\"\n";
//! let err = ModelBuilder::<f32>::from_toml_str(bad).unwrap_err();
//! assert_eq!(err.line, Some(3));
//! assert_eq!(err.field.as_deref(), Some("particles[0].mass"));
//! ```
//!
//! The schema (units as in the rest of the crate; defaults in parentheses):
//! - `gravity`: `[x, y, z]` (m/s^2; `[0, -9.8, 0]`); `particle_radius` (m; 0.01).
//! - `particles`: `{ x, v ([0,0,0]), mass }` (m, m/s, kg; mass 0 pins).
//! - `cloth_grids`: `{ ni, nj, origin, spacing, mass, pinned ([]: [[i, j], ...]), spring_ke,
//!   spring_kd (0), bend_ke, bend_kd (0), bend_rest ("flat" | "initial") }`, see
//!   [`crate::scenes::cloth::ClothGrid`] (no bending without `bend_ke`).
//! - `springs`: `{ i, j, ke, kd (0), rest (current distance) }`.
//! - `triangles`: `{ indices: [i, j, k], mu, lambda, kd (0) }`: a StVK membrane if `mu` and
//!   `lambda` are given, otherwise topology only.
//! - `bending`: `{ ke, kd (0), rest ("flat") }`: elements on the edges shared by two of the
//!   file's `triangles`.
//! - `tets`: `{ indices: [i, j, k, l], mu, lambda, kd (0) }` or with `young`, `poisson` in
//!   place of `mu`, `lambda` (see [`crate::forces::fem_tet::snh_lame`]).
//! - `ground`: `{ normal ([0,1,0]), offset (0), ke (1000), kd (1), mu (0.5), leak (0) }`.
//! - `drag`: `{ kd, wind ([0,0,0]) }`.
//! - `particle_contact`, `shape_contact`: `{ ke (1000), kd (1), mu (0.5), leak (0), margin (0) }`.
//! - `shapes`: `{ kind: "sphere" | "box" | "capsule", pos, rot ([0,0,0,1] as x, y, z, w),
//!   radius, half_extents, half_length }`.
//! - `bodies`: `{ x, q ([0,0,0,1]), v, w, mass, inertia: [Ixx, Iyy, Izz] (body frame),
//!   contact_points ([]) }`.
//! - `distance_constraints`: `{ i, j, compliance (0) }`.

use std::fmt;

use adflex_runtime::{Mat33, Quat, Real, Vec3};
use serde::Deserialize;

use crate::contact::ground::Ground;
use crate::contact::particle::ParticleContact;
use crate::contact::shapes::{Shape, ShapeKind};
use crate::forces::bending::RestAngle;
use crate::forces::fem_tet::{snh_lame, tet_rest};
use crate::forces::fem_tri::triangle_rest;
use crate::forces::particle::Drag;
use crate::model::ModelBuilder;
use crate::scenes::cloth::ClothGrid;

/// An error reading a scene file: what is wrong, where (line and column, 1-based, when
/// known) and in which field (a path like `particles[2].mass`, when known).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SceneError {
    /// What is wrong.
    pub message: String,
    /// The field, as a path from the root (`springs[3].ke`).
    pub field: Option<String>,
    /// Line (1-based).
    pub line: Option<usize>,
    /// Column (1-based).
    pub column: Option<usize>,
}

impl fmt::Display for SceneError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("scene file")?;
        if let Some(l) = self.line {
            write!(f, ", line {l}")?;
            if let Some(c) = self.column {
                write!(f, ", column {c}")?;
            }
        }
        if let Some(p) = &self.field {
            write!(f, ", field `{p}`")?;
        }
        write!(f, ": {}", self.message)
    }
}

impl std::error::Error for SceneError {}

// ---- the schema -------------------------------------------------------------------------

fn zero3() -> [f64; 3] {
    [0.0; 3]
}
fn up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}
fn identity_quat() -> [f64; 4] {
    [0.0, 0.0, 0.0, 1.0]
}
fn d1000() -> f64 {
    1000.0
}
fn d1() -> f64 {
    1.0
}
fn d05() -> f64 {
    0.5
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneDesc {
    gravity: Option<[f64; 3]>,
    particle_radius: Option<f64>,
    #[serde(default)]
    particles: Vec<ParticleDesc>,
    #[serde(default)]
    cloth_grids: Vec<ClothGridDesc>,
    #[serde(default)]
    springs: Vec<SpringDesc>,
    #[serde(default)]
    triangles: Vec<TriangleDesc>,
    bending: Option<BendingDesc>,
    #[serde(default)]
    tets: Vec<TetDesc>,
    ground: Option<GroundDesc>,
    drag: Option<DragDesc>,
    particle_contact: Option<ContactDesc>,
    shape_contact: Option<ContactDesc>,
    #[serde(default)]
    shapes: Vec<ShapeDesc>,
    #[serde(default)]
    bodies: Vec<BodyDesc>,
    #[serde(default)]
    distance_constraints: Vec<DistanceDesc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ParticleDesc {
    x: [f64; 3],
    #[serde(default = "zero3")]
    v: [f64; 3],
    mass: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ClothGridDesc {
    ni: usize,
    nj: usize,
    origin: [f64; 3],
    spacing: f64,
    mass: f64,
    #[serde(default)]
    pinned: Vec<[usize; 2]>,
    spring_ke: f64,
    #[serde(default)]
    spring_kd: f64,
    bend_ke: Option<f64>,
    #[serde(default)]
    bend_kd: f64,
    #[serde(default)]
    bend_rest: RestDesc,
}

#[derive(Deserialize, Default, Clone, Copy)]
#[serde(rename_all = "lowercase")]
enum RestDesc {
    #[default]
    Flat,
    Initial,
}

impl From<RestDesc> for RestAngle {
    fn from(r: RestDesc) -> Self {
        match r {
            RestDesc::Flat => RestAngle::Flat,
            RestDesc::Initial => RestAngle::Initial,
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SpringDesc {
    i: u32,
    j: u32,
    ke: f64,
    #[serde(default)]
    kd: f64,
    rest: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TriangleDesc {
    indices: [u32; 3],
    mu: Option<f64>,
    lambda: Option<f64>,
    #[serde(default)]
    kd: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BendingDesc {
    ke: f64,
    #[serde(default)]
    kd: f64,
    #[serde(default)]
    rest: RestDesc,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TetDesc {
    indices: [u32; 4],
    mu: Option<f64>,
    lambda: Option<f64>,
    young: Option<f64>,
    poisson: Option<f64>,
    #[serde(default)]
    kd: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GroundDesc {
    #[serde(default = "up")]
    normal: [f64; 3],
    #[serde(default)]
    offset: f64,
    #[serde(default = "d1000")]
    ke: f64,
    #[serde(default = "d1")]
    kd: f64,
    #[serde(default = "d05")]
    mu: f64,
    #[serde(default)]
    leak: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct DragDesc {
    kd: f64,
    #[serde(default = "zero3")]
    wind: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ContactDesc {
    #[serde(default = "d1000")]
    ke: f64,
    #[serde(default = "d1")]
    kd: f64,
    #[serde(default = "d05")]
    mu: f64,
    #[serde(default)]
    leak: f64,
    #[serde(default)]
    margin: f64,
}

#[derive(Deserialize, Clone, Copy, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
enum ShapeKindDesc {
    Sphere,
    Box,
    Capsule,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ShapeDesc {
    kind: ShapeKindDesc,
    pos: [f64; 3],
    #[serde(default = "identity_quat")]
    rot: [f64; 4],
    radius: Option<f64>,
    half_extents: Option<[f64; 3]>,
    half_length: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BodyDesc {
    x: [f64; 3],
    #[serde(default = "identity_quat")]
    q: [f64; 4],
    #[serde(default = "zero3")]
    v: [f64; 3],
    #[serde(default = "zero3")]
    w: [f64; 3],
    mass: f64,
    inertia: [f64; 3],
    #[serde(default)]
    contact_points: Vec<[f64; 3]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct DistanceDesc {
    i: u32,
    j: u32,
    #[serde(default)]
    compliance: f64,
}

// ---- where things are in the text ----------------------------------------------------------

/// The byte offset of every key and value of a text, by path (`a.b[2].c`), in document order.
type Paths = Vec<(String, usize)>;

fn join(stack: &[Frame]) -> String {
    let mut s = String::new();
    for f in stack {
        match f {
            Frame::Object(Some(k)) => {
                if !s.is_empty() {
                    s.push('.');
                }
                s.push_str(k);
            }
            Frame::Object(None) => {}
            Frame::Array(i) => s.push_str(&format!("[{i}]")),
        }
    }
    s
}

enum Frame {
    /// An object and its current key.
    Object(Option<String>),
    /// An array and the current index.
    Array(usize),
}

/// Paths of a JSON text (tolerant of malformed input: it only reads up to where it can), and
/// the span `(path, start, end, is_object)` of every object and array.
fn json_paths(src: &str) -> (Paths, Vec<(String, usize, usize, bool)>) {
    let b = src.as_bytes();
    let mut out = Vec::new();
    let mut objects = Vec::new();
    let mut open: Vec<(String, usize)> = Vec::new();
    let mut stack: Vec<Frame> = Vec::new();
    let mut expect_key = false;
    let mut i = 0;
    while i < b.len() {
        let c = b[i];
        match c {
            b' ' | b'\t' | b'\n' | b'\r' | b':' => i += 1,
            b',' => {
                match stack.last_mut() {
                    Some(Frame::Array(k)) => *k += 1,
                    Some(Frame::Object(_)) => expect_key = true,
                    None => {}
                }
                i += 1;
            }
            b'{' | b'[' => {
                out.push((join(&stack), i));
                open.push((join(&stack), i));
                stack.push(if c == b'{' {
                    Frame::Object(None)
                } else {
                    Frame::Array(0)
                });
                expect_key = c == b'{';
                i += 1;
            }
            b'}' | b']' => {
                let is_object = matches!(stack.last(), Some(Frame::Object(_)));
                if let Some((p, start)) = open.pop() {
                    objects.push((p, start, i, is_object));
                }
                stack.pop();
                expect_key = false;
                i += 1;
            }
            b'"' => {
                let start = i;
                i += 1;
                let mut s = Vec::new();
                while i < b.len() && b[i] != b'"' {
                    if b[i] == b'\\' {
                        i += 1;
                    }
                    if i < b.len() {
                        s.push(b[i]);
                    }
                    i += 1;
                }
                i += 1;
                if expect_key {
                    if let Some(Frame::Object(k)) = stack.last_mut() {
                        *k = Some(String::from_utf8_lossy(&s).into_owned());
                    }
                    expect_key = false;
                }
                out.push((join(&stack), start));
            }
            _ => {
                out.push((join(&stack), i));
                while i < b.len() && !b",]} \t\r\n".contains(&b[i]) {
                    i += 1;
                }
            }
        }
    }
    (out, objects)
}

/// Paths of a TOML text: table headers (`[a]`, `[[a]]` counted per name) and `key = value`
/// lines (the key path under the current table). Values inside inline tables and arrays are
/// located at their key.
fn toml_paths(src: &str) -> Paths {
    let mut out = Vec::new();
    let mut counts: Vec<(String, usize)> = Vec::new();
    let mut prefix = String::new();
    let mut offset = 0;
    for line in src.split_inclusive('\n') {
        let t = line.trim();
        let lead = line.len() - line.trim_start().len();
        if let Some(name) = t.strip_prefix("[[").and_then(|r| r.split("]]").next()) {
            let name = name.trim().to_string();
            let n = match counts.iter_mut().find(|(k, _)| *k == name) {
                Some((_, n)) => {
                    *n += 1;
                    *n - 1
                }
                None => {
                    counts.push((name.clone(), 1));
                    0
                }
            };
            prefix = format!("{name}[{n}]");
            out.push((prefix.clone(), offset + lead));
        } else if let Some(name) = t.strip_prefix('[').and_then(|r| r.split(']').next()) {
            prefix = name.trim().to_string();
            out.push((prefix.clone(), offset + lead));
        } else if let Some((key, _)) = t.split_once('=') {
            let key = key.trim().trim_matches('"');
            if !key.is_empty() && !key.starts_with('#') {
                let path = if prefix.is_empty() {
                    key.to_string()
                } else {
                    format!("{prefix}.{key}")
                };
                out.push((path, offset + lead));
            }
        }
        offset += line.len();
    }
    out
}

fn line_col(src: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(src.len());
    let before = &src.as_bytes()[..offset];
    let line = before.iter().filter(|&&c| c == b'\n').count() + 1;
    let col = offset
        - before
            .iter()
            .rposition(|&c| c == b'\n')
            .map_or(0, |p| p + 1)
        + 1;
    (line, col)
}

fn offset_of(src: &str, line: usize, col: usize) -> usize {
    let mut off = 0;
    for (n, l) in src.split_inclusive('\n').enumerate() {
        if n + 1 == line {
            return (off + col.saturating_sub(1)).min(src.len());
        }
        off += l.len();
    }
    src.len()
}

/// The path of the field an error at `offset` is about: the last key or value that starts at
/// or before it. For a missing field, the object that lacks it.
fn field_at(paths: &Paths, offset: usize, message: &str) -> Option<String> {
    let p = paths.iter().rev().find(|(_, o)| *o <= offset)?.0.clone();
    if message.starts_with("missing field") {
        // The error points at the end of the object: name the object.
        return Some(match (p.rfind('.'), p.rfind('[')) {
            (Some(d), Some(b)) if b > d => p,
            (Some(d), _) => p[..d].to_string(),
            _ => p,
        });
    }
    Some(p)
}

/// A semantic error about `path`, located in the text if the path (or its nearest parent) is
/// there.
fn at(src: &str, paths: &Paths, path: String, message: impl Into<String>) -> SceneError {
    let mut probe = path.as_str();
    let found = loop {
        if let Some((_, o)) = paths.iter().find(|(p, _)| p == probe) {
            break Some(*o);
        }
        match probe.rfind(['.', '[']) {
            Some(k) => probe = &probe[..k],
            None => break None,
        }
    };
    let (line, column) = match found.map(|o| line_col(src, o)) {
        Some((l, c)) => (Some(l), Some(c)),
        None => (None, None),
    };
    SceneError {
        message: message.into(),
        field: Some(path),
        line,
        column,
    }
}

// ---- building ------------------------------------------------------------------------------

fn v3<R: Real>(a: [f64; 3]) -> Vec3<R> {
    Vec3::new(R::lit(a[0]), R::lit(a[1]), R::lit(a[2]))
}

struct Checker<'a> {
    src: &'a str,
    paths: &'a Paths,
}

impl Checker<'_> {
    fn err(&self, path: String, message: impl Into<String>) -> SceneError {
        at(self.src, self.paths, path, message)
    }

    fn finite(&self, path: impl Fn() -> String, vals: &[f64]) -> Result<(), SceneError> {
        if vals.iter().all(|v| v.is_finite()) {
            Ok(())
        } else {
            Err(self.err(path(), "must be finite"))
        }
    }

    fn nonneg(&self, path: impl Fn() -> String, v: f64) -> Result<(), SceneError> {
        if v.is_finite() && v >= 0.0 {
            Ok(())
        } else {
            Err(self.err(path(), format!("must be a finite number >= 0 (got {v})")))
        }
    }

    fn positive(&self, path: impl Fn() -> String, v: f64) -> Result<(), SceneError> {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(self.err(path(), format!("must be a finite number > 0 (got {v})")))
        }
    }

    fn indices(&self, path: impl Fn() -> String, idx: &[u32], n: usize) -> Result<(), SceneError> {
        for (k, &i) in idx.iter().enumerate() {
            if i as usize >= n {
                return Err(self.err(
                    path(),
                    format!("particle index {i} out of range ({n} particles)"),
                ));
            }
            if idx[..k].contains(&i) {
                return Err(self.err(path(), format!("particle {i} appears twice")));
            }
        }
        Ok(())
    }
}

fn build<R: Real>(d: SceneDesc, src: &str, paths: &Paths) -> Result<ModelBuilder<R>, SceneError> {
    let c = Checker { src, paths };
    let mut b = ModelBuilder::<R>::new();
    if let Some(g) = d.gravity {
        c.finite(|| "gravity".into(), &g)?;
        b.gravity = v3(g);
    }
    if let Some(r) = d.particle_radius {
        c.nonneg(|| "particle_radius".into(), r)?;
        b.particle_radius = R::lit(r);
    }
    for (k, p) in d.particles.iter().enumerate() {
        c.finite(|| format!("particles[{k}].x"), &p.x)?;
        c.finite(|| format!("particles[{k}].v"), &p.v)?;
        c.nonneg(|| format!("particles[{k}].mass"), p.mass)?;
        b.add_particle(v3(p.x), v3(p.v), R::lit(p.mass));
    }
    for (k, g) in d.cloth_grids.iter().enumerate() {
        let path = |f: &str| format!("cloth_grids[{k}].{f}");
        if g.ni < 2 || g.nj < 2 || g.ni.saturating_mul(g.nj) > 1 << 26 {
            return Err(c.err(
                path("ni"),
                format!(
                    "a grid needs 2 to 2^26 particles with at least 2 per side (got {} x {})",
                    g.ni, g.nj
                ),
            ));
        }
        c.finite(|| path("origin"), &g.origin)?;
        c.positive(|| path("spacing"), g.spacing)?;
        c.nonneg(|| path("mass"), g.mass)?;
        c.nonneg(|| path("spring_ke"), g.spring_ke)?;
        c.nonneg(|| path("spring_kd"), g.spring_kd)?;
        c.nonneg(|| path("bend_kd"), g.bend_kd)?;
        if let Some(ke) = g.bend_ke {
            c.nonneg(|| path("bend_ke"), ke)?;
        }
        for (m, p) in g.pinned.iter().enumerate() {
            if p[0] >= g.ni || p[1] >= g.nj {
                return Err(c.err(
                    format!("cloth_grids[{k}].pinned[{m}]"),
                    format!(
                        "({}, {}) is outside the {} x {} grid",
                        p[0], p[1], g.ni, g.nj
                    ),
                ));
            }
        }
        b.add_cloth_grid(&ClothGrid {
            ni: g.ni,
            nj: g.nj,
            origin: v3(g.origin),
            spacing: g.spacing,
            mass: R::lit(g.mass),
            pinned: g.pinned.iter().map(|p| (p[0], p[1])).collect(),
            spring_ke: R::lit(g.spring_ke),
            spring_kd: R::lit(g.spring_kd),
            bend: g.bend_ke.map(|ke| (R::lit(ke), R::lit(g.bend_kd))),
            bend_rest: g.bend_rest.into(),
        });
    }
    let n = b.particle_count();
    for (k, s) in d.springs.iter().enumerate() {
        c.indices(|| format!("springs[{k}]"), &[s.i, s.j], n)?;
        c.nonneg(|| format!("springs[{k}].ke"), s.ke)?;
        c.nonneg(|| format!("springs[{k}].kd"), s.kd)?;
        match s.rest {
            Some(r) => {
                c.nonneg(|| format!("springs[{k}].rest"), r)?;
                b.add_spring_with_rest(s.i, s.j, R::lit(r), R::lit(s.ke), R::lit(s.kd));
            }
            None => {
                b.add_spring(s.i, s.j, R::lit(s.ke), R::lit(s.kd));
            }
        }
    }
    let first_file_triangle = b.triangles().len();
    let pos = |i: u32, b: &ModelBuilder<R>| {
        let p = b.particle_position(i);
        Vec3::new(p.x.to_f64(), p.y.to_f64(), p.z.to_f64())
    };
    for (k, t) in d.triangles.iter().enumerate() {
        let [i, j, l] = t.indices;
        c.indices(|| format!("triangles[{k}].indices"), &t.indices, n)?;
        match (t.mu, t.lambda) {
            (Some(mu), Some(lambda)) => {
                c.nonneg(|| format!("triangles[{k}].mu"), mu)?;
                c.finite(|| format!("triangles[{k}].lambda"), &[lambda])?;
                c.nonneg(|| format!("triangles[{k}].kd"), t.kd)?;
                if triangle_rest(pos(i, &b), pos(j, &b), pos(l, &b)).is_none() {
                    return Err(c.err(
                        format!("triangles[{k}]"),
                        "the triangle is degenerate (zero area)",
                    ));
                }
                b.add_triangle_fem(i, j, l, R::lit(mu), R::lit(lambda), R::lit(t.kd));
            }
            (None, None) => {
                b.add_triangle(i, j, l);
            }
            (Some(_), None) => {
                return Err(c.err(
                    format!("triangles[{k}]"),
                    "`mu` without `lambda`: a membrane needs both",
                ))
            }
            (None, Some(_)) => {
                return Err(c.err(
                    format!("triangles[{k}]"),
                    "`lambda` without `mu`: a membrane needs both",
                ))
            }
        }
    }
    if let Some(bd) = &d.bending {
        c.nonneg(|| "bending.ke".into(), bd.ke)?;
        c.nonneg(|| "bending.kd".into(), bd.kd)?;
        // Only the file's triangles (cloth grids have their own bending settings).
        let tris = b.triangles()[first_file_triangle..].to_vec();
        let xs: Vec<Vec3<f64>> = (0..n as u32).map(|i| pos(i, &b)).collect();
        for q in crate::forces::bending::bending_edges(&tris) {
            let rest = match bd.rest {
                RestDesc::Flat => 0.0,
                RestDesc::Initial => crate::forces::bending::dihedral_angle(&xs, q),
            };
            b.add_bending(q, R::lit(rest), R::lit(bd.ke), R::lit(bd.kd));
        }
    }
    for (k, t) in d.tets.iter().enumerate() {
        let path = |f: &str| format!("tets[{k}].{f}");
        c.indices(|| path("indices"), &t.indices, n)?;
        let (mu, lambda) = match (t.mu, t.lambda, t.young, t.poisson) {
            (Some(mu), Some(lambda), None, None) => (mu, lambda),
            (None, None, Some(e), Some(nu)) => {
                c.positive(|| path("young"), e)?;
                if !(nu > -1.0 && nu < 0.5) {
                    return Err(c.err(path("poisson"), format!("must be in (-1, 0.5) (got {nu})")));
                }
                snh_lame(e, nu)
            }
            _ => {
                return Err(c.err(
                    format!("tets[{k}]"),
                    "give either `mu` and `lambda`, or `young` and `poisson`",
                ))
            }
        };
        c.nonneg(|| path("mu"), mu)?;
        c.positive(|| path("lambda"), lambda)?;
        c.nonneg(|| path("kd"), t.kd)?;
        if tet_rest(t.indices.map(|i| pos(i, &b))).is_none() {
            return Err(c.err(
                format!("tets[{k}]"),
                "the tetrahedron is degenerate (zero volume)",
            ));
        }
        let [i, j, l, m] = t.indices;
        b.add_tet(i, j, l, m, R::lit(mu), R::lit(lambda), R::lit(t.kd));
    }
    if let Some(g) = &d.ground {
        c.finite(|| "ground.normal".into(), &g.normal)?;
        let nrm = Vec3::new(g.normal[0], g.normal[1], g.normal[2]);
        if !nrm.norm().is_normal() {
            return Err(c.err("ground.normal".into(), "must be a nonzero vector"));
        }
        c.finite(|| "ground.offset".into(), &[g.offset])?;
        for (f, v) in [("ke", g.ke), ("kd", g.kd), ("mu", g.mu), ("leak", g.leak)] {
            c.nonneg(|| format!("ground.{f}"), v)?;
        }
        let nrm = nrm.normalize();
        b.set_ground(Ground {
            normal: v3([nrm.x, nrm.y, nrm.z]),
            offset: R::lit(g.offset),
            ke: R::lit(g.ke),
            kd: R::lit(g.kd),
            mu: R::lit(g.mu),
            leak: R::lit(g.leak),
        });
    }
    if let Some(dr) = &d.drag {
        c.nonneg(|| "drag.kd".into(), dr.kd)?;
        c.finite(|| "drag.wind".into(), &dr.wind)?;
        b.set_drag(Drag {
            kd: R::lit(dr.kd),
            wind: v3(dr.wind),
        });
    }
    let contact = |name: &str, cd: &ContactDesc| -> Result<ParticleContact<R>, SceneError> {
        for (f, v) in [
            ("ke", cd.ke),
            ("kd", cd.kd),
            ("mu", cd.mu),
            ("leak", cd.leak),
            ("margin", cd.margin),
        ] {
            c.nonneg(|| format!("{name}.{f}"), v)?;
        }
        Ok(ParticleContact {
            ke: R::lit(cd.ke),
            kd: R::lit(cd.kd),
            mu: R::lit(cd.mu),
            leak: R::lit(cd.leak),
            margin: R::lit(cd.margin),
        })
    };
    if let Some(cd) = &d.particle_contact {
        b.set_particle_contact(contact("particle_contact", cd)?);
    }
    if let Some(cd) = &d.shape_contact {
        b.set_shape_contact(contact("shape_contact", cd)?);
    }
    for (k, s) in d.shapes.iter().enumerate() {
        let path = |f: &str| format!("shapes[{k}].{f}");
        c.finite(|| path("pos"), &s.pos)?;
        c.finite(|| path("rot"), &s.rot)?;
        let q = Quat::new(s.rot[3], s.rot[0], s.rot[1], s.rot[2]);
        if !q.norm().is_normal() {
            return Err(c.err(path("rot"), "must be a nonzero quaternion [x, y, z, w]"));
        }
        let need = |v: Option<f64>, f: &str| -> Result<f64, SceneError> {
            let v =
                v.ok_or_else(|| c.err(format!("shapes[{k}]"), format!("missing field `{f}`")))?;
            c.positive(|| path(f), v)?;
            Ok(v)
        };
        let kind = match s.kind {
            ShapeKindDesc::Sphere => ShapeKind::Sphere {
                radius: R::lit(need(s.radius, "radius")?),
            },
            ShapeKindDesc::Box => {
                let h = s
                    .half_extents
                    .ok_or_else(|| c.err(format!("shapes[{k}]"), "missing field `half_extents`"))?;
                for v in h {
                    c.positive(|| path("half_extents"), v)?;
                }
                ShapeKind::Box {
                    half_extents: v3(h),
                }
            }
            ShapeKindDesc::Capsule => ShapeKind::Capsule {
                radius: R::lit(need(s.radius, "radius")?),
                half_length: R::lit(need(s.half_length, "half_length")?),
            },
        };
        let q = q / q.norm();
        b.add_shape(Shape {
            kind,
            pos: v3(s.pos),
            rot: Quat::new(R::lit(q.w), R::lit(q.i), R::lit(q.j), R::lit(q.k)),
        });
    }
    for (k, bd) in d.bodies.iter().enumerate() {
        let path = |f: &str| format!("bodies[{k}].{f}");
        c.finite(|| path("x"), &bd.x)?;
        c.finite(|| path("v"), &bd.v)?;
        c.finite(|| path("w"), &bd.w)?;
        c.finite(|| path("q"), &bd.q)?;
        c.nonneg(|| path("mass"), bd.mass)?;
        let q = Quat::new(bd.q[3], bd.q[0], bd.q[1], bd.q[2]);
        if !q.norm().is_normal() {
            return Err(c.err(path("q"), "must be a nonzero quaternion [x, y, z, w]"));
        }
        for v in bd.inertia {
            if bd.mass > 0.0 {
                c.positive(|| path("inertia"), v)?;
            } else {
                c.nonneg(|| path("inertia"), v)?;
            }
        }
        let q = q / q.norm();
        let id = b.add_body(
            v3(bd.x),
            Quat::new(R::lit(q.w), R::lit(q.i), R::lit(q.j), R::lit(q.k)),
            v3(bd.v),
            v3(bd.w),
            R::lit(bd.mass),
            Mat33::from_diagonal(&v3(bd.inertia)),
        );
        for (m, p) in bd.contact_points.iter().enumerate() {
            c.finite(|| format!("bodies[{k}].contact_points[{m}]"), p)?;
            b.add_body_contact_point(id, v3(*p));
        }
    }
    for (k, dc) in d.distance_constraints.iter().enumerate() {
        c.indices(|| format!("distance_constraints[{k}]"), &[dc.i, dc.j], n)?;
        c.nonneg(
            || format!("distance_constraints[{k}].compliance"),
            dc.compliance,
        )?;
        b.add_distance_constraint(dc.i, dc.j, R::lit(dc.compliance));
    }
    Ok(b)
}

/// Strips serde_json's " at line L column C" suffix (the error carries them separately).
fn strip_position(msg: &str) -> String {
    match msg.rfind(" at line ") {
        Some(k) => msg[..k].to_string(),
        None => msg.to_string(),
    }
}

impl<R: Real> ModelBuilder<R> {
    /// Reads a scene from JSON (schema in [`crate::scene_file`]).
    pub fn from_json_str(src: &str) -> Result<Self, SceneError> {
        let (paths, objects) = json_paths(src);
        let desc: SceneDesc = serde_json::from_str(src).map_err(|e| {
            let message = strip_position(&e.to_string());
            let (line, column) = (e.line(), e.column());
            let offset = offset_of(src, line, column).saturating_sub(1);
            let field = if line == 0 {
                None
            } else if message.starts_with("missing field") || message.starts_with("invalid length")
            {
                // The error is at the end of the object (array) that lacks a field (an
                // element): name the innermost one around it.
                let object = message.starts_with("missing field");
                objects
                    .iter()
                    .filter(|(_, s, e, o)| *s <= offset && offset <= *e && (*o || !object))
                    .max_by_key(|(_, s, _, _)| *s)
                    .map(|o| o.0.clone())
            } else {
                field_at(&paths, offset, &message)
            };
            SceneError {
                message,
                field: field.filter(|f| !f.is_empty()),
                line: (line > 0).then_some(line),
                column: (line > 0).then_some(column),
            }
        })?;
        build(desc, src, &paths)
    }

    /// Reads a scene from TOML (schema in [`crate::scene_file`]).
    pub fn from_toml_str(src: &str) -> Result<Self, SceneError> {
        let paths = toml_paths(src);
        let desc: SceneDesc = toml::from_str(src).map_err(|e| {
            let message = e.message().trim().to_string();
            let (mut line, mut column, mut field) = (None, None, None);
            if let Some(span) = e.span() {
                let (l, c) = line_col(src, span.start);
                line = Some(l);
                column = Some(c);
                field = field_at(&paths, span.start, &message).filter(|f| !f.is_empty());
            }
            SceneError {
                message,
                field,
                line,
                column,
            }
        })?;
        build(desc, src, &paths)
    }
}
