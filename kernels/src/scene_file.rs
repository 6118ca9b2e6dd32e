//! Scene files: a [`ModelBuilder`] from JSON ([`ModelBuilder::from_json_str`]) or TOML
//! ([`ModelBuilder::from_toml_str`]).
//!
//! A malformed file gives a [`SceneError`] naming the field (a path such as
//! `springs[3].ke`) and its line; nothing in a file can make the reader panic. Every section
//! is optional; unknown fields are errors (a typo is not silently ignored). Particles are
//! numbered in file order: first `particles`, then the particles of each `cloth_grids` entry.
//!
//! Reading costs what the parser costs (`serde_json`, `toml`; the field path comes from
//! `serde_path_to_error`, the line of a semantic error from one scan of the text when it is
//! reported): linear in the size of the file. Nesting of `[` and `{` is bounded (JSON:
//! [`MAX_NESTING`]; TOML: the `toml` crate's limit, 80), and since no part of the schema is
//! nested more than five deep, deeper input is an error as soon as the parser reaches the first
//! level the schema does not allow.
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
//! assert_eq!(model.springs().unwrap().len(), 1);
//!
//! let bad = "[[particles]]\nx = [0, 1, 0]\nmass = \"heavy\"\n";
//! let err = ModelBuilder::<f32>::from_toml_str(bad).unwrap_err();
//! assert_eq!(err.line, Some(3));
//! assert_eq!(err.field.as_deref(), Some("particles[0].mass"));
//! ```
//!
//! The schema (units as in the rest of the crate; defaults in parentheses):
//! - `gravity`: `[x, y, z]` (m/s^2; `[0, -9.8, 0]`); `particle_radius` (m; 0.01).
//! - `particles`: `{ x, v ([0,0,0]), mass, radius (particle_radius) }` (m, m/s, kg, m;
//!   mass 0 pins; see [`ModelBuilder::set_particle_radius`]).
//! - `cloth_grids`: `{ ni, nj, origin, spacing, mass, pinned ([]: [[i, j], ...]), spring_ke,
//!   spring_kd (0), bend_ke, bend_kd (0), bend_rest ("flat" | "initial"), rotation
//!   ([0,0,0,1] as x, y, z, w) }`, see
//!   [`crate::scenes::cloth::ClothGrid`] (no bending without `bend_ke`).
//! - `springs`: `{ i, j, ke, kd (0), rest (current distance) }`.
//! - `triangles`: `{ indices: [i, j, k], mu, lambda, kd (0) }`: a StVK membrane if `mu` and
//!   `lambda` are given, otherwise topology only.
//! - `bending`: `{ ke, kd (0), rest ("flat") }`: elements on the edges shared by two of the
//!   file's `triangles`.
//! - `tets`: `{ indices: [i, j, k, l], mu, lambda, kd (0) }` or with `young`, `poisson` in
//!   place of `mu`, `lambda` (see [`crate::forces::fem_tet::snh_lame`]).
//! - `ground`: `{ normal ([0,1,0]), offset (0), ke (1000), kd (1), mu (0.5), leak (0),
//!   damp_approach (false), damping_depth (1e-4) }`.
//! - `drag`: `{ kd, wind ([0,0,0]) }`.
//! - `particle_contact`, `shape_contact`: `{ ke (1000), kd (1), damping_depth (1e-4), mu (0.5),
//!   leak (0), margin (0) }`.
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
use crate::forces::fem_tet::snh_lame;
use crate::forces::particle::Drag;
use crate::model::ModelBuilder;
use crate::scenes::cloth::ClothGrid;
use crate::validation::precision;

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
// The defaults of the components' `Default` impls (one source).
fn ground_ke() -> f64 {
    Ground::<f64>::default().ke
}
fn ground_kd() -> f64 {
    Ground::<f64>::default().kd
}
fn ground_damp_approach() -> bool {
    Ground::<f64>::default().damp_approach
}
fn contact_damping_depth() -> f64 {
    ParticleContact::<f64>::default().damping_depth
}

fn ground_damping_depth() -> f64 {
    Ground::<f64>::default().damping_depth
}
fn ground_mu() -> f64 {
    Ground::<f64>::default().mu
}
fn contact_ke() -> f64 {
    ParticleContact::<f64>::default().ke
}
fn contact_kd() -> f64 {
    ParticleContact::<f64>::default().kd
}
fn contact_mu() -> f64 {
    ParticleContact::<f64>::default().mu
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
    radius: Option<f64>,
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
    #[serde(default = "identity_quat")]
    rotation: [f64; 4],
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
    #[serde(default = "ground_ke")]
    ke: f64,
    #[serde(default = "ground_kd")]
    kd: f64,
    #[serde(default = "ground_mu")]
    mu: f64,
    #[serde(default)]
    leak: f64,
    #[serde(default = "ground_damp_approach")]
    damp_approach: bool,
    #[serde(default = "ground_damping_depth")]
    damping_depth: f64,
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
    #[serde(default = "contact_ke")]
    ke: f64,
    #[serde(default = "contact_kd")]
    kd: f64,
    #[serde(default = "contact_damping_depth")]
    damping_depth: f64,
    #[serde(default = "contact_mu")]
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
//
// Nothing is indexed up front: serde (through `serde_path_to_error`) gives the field path and
// the parser the line of a deserialization error, and the semantic checks of `build`, which
// know the path of what they reject, find it in the text only when they report an error (one
// linear scan per error).

/// How deep `[` and `{` may nest (serde_json's recursion limit; toml's is lower). Deeper input
/// is rejected as soon as the parser reaches that depth.
pub const MAX_NESTING: usize = 128;

#[derive(Clone, Copy)]
enum Format {
    Json,
    Toml,
}

/// One step of a field path: a key or an index.
#[derive(PartialEq, Eq, Debug)]
enum Seg<'a> {
    Key(&'a str),
    Index(usize),
}

/// `springs[3].ke` as `[Key(springs), Index(3), Key(ke)]`.
fn segments(path: &str) -> Vec<Seg<'_>> {
    let mut out = Vec::new();
    for part in path.split('.') {
        let (key, mut rest) = match part.find('[') {
            Some(k) => (&part[..k], &part[k..]),
            None => (part, ""),
        };
        if !key.is_empty() {
            out.push(Seg::Key(key));
        }
        while let Some(r) = rest.strip_prefix('[') {
            let close = r.find(']').unwrap_or(r.len());
            out.push(Seg::Index(r[..close].parse().unwrap_or(usize::MAX)));
            rest = r.get(close + 1..).unwrap_or("");
        }
    }
    out
}

enum Frame<'a> {
    /// An object and its current key.
    Object(Option<&'a str>),
    /// An array and the current index.
    Array(usize),
}

fn frames_match(stack: &[Frame], key: Option<&str>, target: &[Seg]) -> bool {
    let depth = stack
        .iter()
        .filter(|f| !matches!(f, Frame::Object(None)))
        .count();
    if depth + usize::from(key.is_some()) != target.len() {
        return false;
    }
    let mut t = target.iter();
    for f in stack {
        let ok = match f {
            Frame::Object(Some(k)) => t.next() == Some(&Seg::Key(k)),
            Frame::Object(None) => true,
            Frame::Array(i) => t.next() == Some(&Seg::Index(*i)),
        };
        if !ok {
            return false;
        }
    }
    match key {
        Some(k) => t.next() == Some(&Seg::Key(k)),
        None => true,
    }
}

/// The byte offset in a JSON text of the field `target` (of its key if it has one, else of
/// its value), if it is there. One pass; tolerant of malformed text. Only called on the error
/// path, after serde has accepted the text (so the nesting is at most [`MAX_NESTING`]).
fn json_locate(src: &str, target: &[Seg]) -> Option<usize> {
    let b = src.as_bytes();
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
                if frames_match(&stack, None, target) {
                    return Some(i);
                }
                if stack.len() > MAX_NESTING {
                    return None;
                }
                stack.push(if c == b'{' {
                    Frame::Object(None)
                } else {
                    Frame::Array(0)
                });
                expect_key = c == b'{';
                i += 1;
            }
            b'}' | b']' => {
                stack.pop();
                expect_key = false;
                i += 1;
            }
            b'"' => {
                let start = i;
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    i += if b[i] == b'\\' { 2 } else { 1 };
                }
                let text = src.get(start + 1..i.min(b.len())).unwrap_or("");
                i += 1;
                if expect_key {
                    expect_key = false;
                    if frames_match(&stack, Some(text), target) {
                        return Some(start);
                    }
                    if let Some(Frame::Object(k)) = stack.last_mut() {
                        *k = Some(text);
                    }
                } else if frames_match(&stack, None, target) {
                    return Some(start);
                }
            }
            _ => {
                if frames_match(&stack, None, target) {
                    return Some(i);
                }
                while i < b.len() && !b",]} \t\r\n".contains(&b[i]) {
                    i += 1;
                }
            }
        }
    }
    None
}

fn toml_header(name: &str) -> Vec<Seg<'_>> {
    name.trim()
        .split('.')
        .map(|k| Seg::Key(k.trim().trim_matches('"')))
        .collect()
}

/// The byte offset in a TOML text of the field `target`: a table header (`[a]`, `[[a]]`
/// counted per name) or a `key = value` line under the current table. Values inside inline
/// tables and arrays are located at their key (their parent is found instead).
fn toml_locate(src: &str, target: &[Seg]) -> Option<usize> {
    let mut counts: std::collections::HashMap<&str, usize> = Default::default();
    let mut prefix: Vec<Seg> = Vec::new();
    let mut offset = 0;
    for line in src.split_inclusive('\n') {
        let t = line.trim();
        let at = offset + line.len() - line.trim_start().len();
        offset += line.len();
        if let Some(name) = t.strip_prefix("[[").and_then(|r| r.split("]]").next()) {
            let n = counts.entry(name.trim()).or_insert(0);
            *n += 1;
            prefix = toml_header(name);
            prefix.push(Seg::Index(*n - 1));
            if prefix == target {
                return Some(at);
            }
        } else if let Some(name) = t.strip_prefix('[').and_then(|r| r.split(']').next()) {
            prefix = toml_header(name);
            if prefix == target {
                return Some(at);
            }
        } else if let Some((key, _)) = t.split_once('=') {
            let key = key.trim().trim_matches('"');
            if !key.is_empty()
                && !key.starts_with('#')
                && target.len() == prefix.len() + 1
                && target[..prefix.len()] == prefix[..]
                && target[prefix.len()] == Seg::Key(key)
            {
                return Some(at);
            }
        }
    }
    None
}

/// Line and column (1-based) of a byte offset.
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

/// A semantic error about `path`, located in the text at the field or, if it is not written
/// there (a default), at its nearest parent that is.
fn at(src: &str, format: Format, path: String, message: impl Into<String>) -> SceneError {
    let segs = segments(&path);
    let found = (1..=segs.len()).rev().find_map(|n| match format {
        Format::Json => json_locate(src, &segs[..n]),
        Format::Toml => toml_locate(src, &segs[..n]),
    });
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
    format: Format,
}

impl Checker<'_> {
    fn err(&self, path: String, message: impl Into<String>) -> SceneError {
        at(self.src, self.format, path, message)
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

    /// A mass (kg) that is not 0 in the file must not round to 0 in `R` (that would pin the
    /// particle or make the body static).
    fn no_underflow<R: Real>(&self, path: impl Fn() -> String, v: f64) -> Result<(), SceneError> {
        if v > 0.0 && R::lit(v).to_f64() == 0.0 {
            Err(self.err(
                path(),
                format!(
                    "{v:e} rounds to 0 in {} (which would pin it); give at least {:.1e}, or 0",
                    precision::<R>(),
                    min_positive::<R>()
                ),
            ))
        } else {
            Ok(())
        }
    }

    /// The first problem the builder recorded since it had `from`, as an error at the path
    /// `path(param)` gives.
    fn builder<R: Real>(
        &self,
        b: &ModelBuilder<R>,
        from: usize,
        path: impl Fn(Option<&str>) -> String,
    ) -> Result<(), SceneError> {
        match b.problems().get(from) {
            None => Ok(()),
            Some(p) => Err(self.err(path(p.param), p.message.clone())),
        }
    }
}

fn min_positive<R: Real>() -> f64 {
    if precision::<R>() == "f32" {
        f32::from_bits(1) as f64
    } else {
        f64::from_bits(1)
    }
}

/// `item.param`, or `item` for the element as a whole (and for `whole` parameters).
fn sub(item: &str, param: Option<&str>, whole: &[&str]) -> String {
    match param {
        Some(p) if !whole.contains(&p) => format!("{item}.{p}"),
        _ => item.to_string(),
    }
}

/// Builds the scene with the builder, whose checks (see [`crate::validation`]) are the
/// reader's: each builder problem is reported at the field of the file it comes from. Only
/// what the builder cannot see is checked here (the file's own structure, values lost in the
/// conversion to `R`, quaternions and normals before they are normalized).
fn build<R: Real>(d: SceneDesc, src: &str, format: Format) -> Result<ModelBuilder<R>, SceneError> {
    let c = Checker { src, format };
    let mut b = ModelBuilder::<R>::new();
    if let Some(g) = d.gravity {
        b.gravity = v3(g);
    }
    if let Some(r) = d.particle_radius {
        b.particle_radius = R::lit(r);
    }
    if let Err(e) = b.validate() {
        let p = &e.problems[0];
        return Err(c.err(p.item.clone(), p.message.clone()));
    }
    for (k, p) in d.particles.iter().enumerate() {
        let n0 = b.problems().len();
        c.no_underflow::<R>(|| format!("particles[{k}].mass"), p.mass)?;
        let i = b.add_particle(v3(p.x), v3(p.v), R::lit(p.mass));
        if let Some(r) = p.radius {
            b.set_particle_radius(i, R::lit(r));
        }
        c.builder(&b, n0, |f| sub(&format!("particles[{k}]"), f, &[]))?;
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
        c.no_underflow::<R>(|| path("mass"), g.mass)?;
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
        let n0 = b.problems().len();
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
            rotation: Quat::new(
                R::lit(g.rotation[3]),
                R::lit(g.rotation[0]),
                R::lit(g.rotation[1]),
                R::lit(g.rotation[2]),
            ),
        });
        if let Some(p) = b.problems().get(n0) {
            return Err(c.err(format!("cloth_grids[{k}]"), p.to_string()));
        }
    }
    let n = b.particle_count();
    for (k, s) in d.springs.iter().enumerate() {
        let n0 = b.problems().len();
        match s.rest {
            Some(r) => b.add_spring_with_rest(s.i, s.j, R::lit(r), R::lit(s.ke), R::lit(s.kd)),
            None => b.add_spring(s.i, s.j, R::lit(s.ke), R::lit(s.kd)),
        };
        c.builder(&b, n0, |f| sub(&format!("springs[{k}]"), f, &["indices"]))?;
    }
    let first_file_triangle = b.triangles().len();
    for (k, t) in d.triangles.iter().enumerate() {
        let [i, j, l] = t.indices;
        let n0 = b.problems().len();
        match (t.mu, t.lambda) {
            (Some(mu), Some(lambda)) => {
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
        c.builder(&b, n0, |f| sub(&format!("triangles[{k}]"), f, &[]))?;
    }
    if let Some(bd) = &d.bending {
        // Only the file's triangles (cloth grids have their own bending settings).
        let tris = b.triangles()[first_file_triangle..].to_vec();
        let xs: Vec<Vec3<f64>> = (0..n as u32)
            .map(|i| {
                let p = b.particle_position(i);
                Vec3::new(p.x.to_f64(), p.y.to_f64(), p.z.to_f64())
            })
            .collect();
        let n0 = b.problems().len();
        for q in crate::forces::bending::bending_edges(&tris) {
            let rest = match bd.rest {
                RestDesc::Flat => 0.0,
                RestDesc::Initial => crate::forces::bending::dihedral_angle(&xs, q),
            };
            b.add_bending(q, R::lit(rest), R::lit(bd.ke), R::lit(bd.kd));
        }
        c.builder(&b, n0, |f| sub("bending", f, &["indices"]))?;
    }
    for (k, t) in d.tets.iter().enumerate() {
        let path = |f: &str| format!("tets[{k}].{f}");
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
        let [i, j, l, m] = t.indices;
        let n0 = b.problems().len();
        b.add_tet(i, j, l, m, R::lit(mu), R::lit(lambda), R::lit(t.kd));
        c.builder(&b, n0, |f| sub(&format!("tets[{k}]"), f, &[]))?;
    }
    if let Some(g) = &d.ground {
        c.finite(|| "ground.normal".into(), &g.normal)?;
        let nrm = Vec3::new(g.normal[0], g.normal[1], g.normal[2]);
        if !nrm.norm().is_normal() {
            return Err(c.err("ground.normal".into(), "must be a nonzero vector"));
        }
        let nrm = nrm.normalize();
        let n0 = b.problems().len();
        b.set_ground(Ground {
            normal: v3([nrm.x, nrm.y, nrm.z]),
            offset: R::lit(g.offset),
            ke: R::lit(g.ke),
            kd: R::lit(g.kd),
            mu: R::lit(g.mu),
            leak: R::lit(g.leak),
            damp_approach: g.damp_approach,
            damping_depth: R::lit(g.damping_depth),
        });
        c.builder(&b, n0, |f| sub("ground", f, &[]))?;
    }
    if let Some(dr) = &d.drag {
        let n0 = b.problems().len();
        b.set_drag(Drag {
            kd: R::lit(dr.kd),
            wind: v3(dr.wind),
        });
        c.builder(&b, n0, |f| sub("drag", f, &[]))?;
    }
    let contact = |cd: &ContactDesc| ParticleContact {
        ke: R::lit(cd.ke),
        kd: R::lit(cd.kd),
        damping_depth: R::lit(cd.damping_depth),
        mu: R::lit(cd.mu),
        leak: R::lit(cd.leak),
        margin: R::lit(cd.margin),
    };
    if let Some(cd) = &d.particle_contact {
        let n0 = b.problems().len();
        b.set_particle_contact(contact(cd));
        c.builder(&b, n0, |f| sub("particle_contact", f, &[]))?;
    }
    if let Some(cd) = &d.shape_contact {
        let n0 = b.problems().len();
        b.set_shape_contact(contact(cd));
        c.builder(&b, n0, |f| sub("shape_contact", f, &[]))?;
    }
    for (k, s) in d.shapes.iter().enumerate() {
        let path = |f: &str| format!("shapes[{k}].{f}");
        c.finite(|| path("rot"), &s.rot)?;
        let q = Quat::new(s.rot[3], s.rot[0], s.rot[1], s.rot[2]);
        if !q.norm().is_normal() {
            return Err(c.err(path("rot"), "must be a nonzero quaternion [x, y, z, w]"));
        }
        let need = |v: Option<f64>, f: &str| -> Result<f64, SceneError> {
            v.ok_or_else(|| c.err(format!("shapes[{k}]"), format!("missing field `{f}`")))
        };
        let kind = match s.kind {
            ShapeKindDesc::Sphere => ShapeKind::Sphere {
                radius: R::lit(need(s.radius, "radius")?),
            },
            ShapeKindDesc::Box => {
                let h = s
                    .half_extents
                    .ok_or_else(|| c.err(format!("shapes[{k}]"), "missing field `half_extents`"))?;
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
        let n0 = b.problems().len();
        b.add_shape(Shape {
            kind,
            pos: v3(s.pos),
            rot: Quat::new(R::lit(q.w), R::lit(q.i), R::lit(q.j), R::lit(q.k)),
        });
        c.builder(&b, n0, |f| sub(&format!("shapes[{k}]"), f, &[]))?;
    }
    for (k, bd) in d.bodies.iter().enumerate() {
        let path = |f: &str| format!("bodies[{k}].{f}");
        c.finite(|| path("q"), &bd.q)?;
        c.no_underflow::<R>(|| path("mass"), bd.mass)?;
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
        let n0 = b.problems().len();
        let id = b.add_body(
            v3(bd.x),
            Quat::new(R::lit(q.w), R::lit(q.i), R::lit(q.j), R::lit(q.k)),
            v3(bd.v),
            v3(bd.w),
            R::lit(bd.mass),
            Mat33::from_diagonal(&v3(bd.inertia)),
        );
        c.builder(&b, n0, |f| sub(&format!("bodies[{k}]"), f, &[]))?;
        for (m, p) in bd.contact_points.iter().enumerate() {
            let n0 = b.problems().len();
            b.add_body_contact_point(id, v3(*p));
            c.builder(&b, n0, |_| format!("bodies[{k}].contact_points[{m}]"))?;
        }
    }
    for (k, dc) in d.distance_constraints.iter().enumerate() {
        let n0 = b.problems().len();
        b.add_distance_constraint(dc.i, dc.j, R::lit(dc.compliance));
        c.builder(&b, n0, |f| {
            sub(&format!("distance_constraints[{k}]"), f, &["indices"])
        })?;
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

/// The field path of a deserialization error (`None` at the root).
fn field_of(path: &serde_path_to_error::Path) -> Option<String> {
    let p = path.to_string();
    (p != ".").then_some(p)
}

fn json_error(field: Option<String>, e: serde_json::Error) -> SceneError {
    let mut message = strip_position(&e.to_string());
    if message == "recursion limit exceeded" {
        message = format!("nested deeper than {MAX_NESTING} levels of `[` and `{{`");
    }
    let line = e.line();
    SceneError {
        message,
        field,
        line: (line > 0).then_some(line),
        column: (line > 0).then_some(e.column()),
    }
}

fn toml_error(src: &str, field: Option<String>, e: &toml::de::Error) -> SceneError {
    let mut message = e.message().trim().to_string();
    if message.contains("max recursion depth") {
        message = format!("{message} (arrays and inline tables nested too deep)");
    }
    let (line, column) = match e.span() {
        Some(span) => {
            let (l, c) = line_col(src, span.start);
            (Some(l), Some(c))
        }
        None => (None, None),
    };
    SceneError {
        message,
        field,
        line,
        column,
    }
}

impl<R: Real> ModelBuilder<R> {
    /// Reads a scene from JSON (schema in [`crate::scene_file`]). Time and memory are those of
    /// `serde_json` on the file; `[` and `{` nested deeper than [`MAX_NESTING`] are an error.
    pub fn from_json_str(src: &str) -> Result<Self, SceneError> {
        let mut de = serde_json::Deserializer::from_str(src);
        let desc: SceneDesc = serde_path_to_error::deserialize(&mut de)
            .map_err(|e| json_error(field_of(e.path()), e.into_inner()))?;
        de.end().map_err(|e| json_error(None, e))?;
        build(desc, src, Format::Json)
    }

    /// Reads a scene from TOML (schema in [`crate::scene_file`]). Arrays and inline tables
    /// nested deeper than the `toml` crate's limit (80) are an error.
    pub fn from_toml_str(src: &str) -> Result<Self, SceneError> {
        let de = toml::Deserializer::parse(src).map_err(|e| toml_error(src, None, &e))?;
        let desc: SceneDesc = serde_path_to_error::deserialize(de).map_err(|e| {
            let field = field_of(e.path());
            toml_error(src, field, e.inner())
        })?;
        build(desc, src, Format::Toml)
    }
}
