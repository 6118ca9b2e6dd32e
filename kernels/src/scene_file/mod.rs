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

use adflex_runtime::Real;
use serde::Deserialize;

use crate::constraints::{self, DistanceDesc};
use crate::contact::ground::{self, GroundDesc};
use crate::contact::particle::{self, ContactDesc};
use crate::contact::shapes::{self, ShapeDesc};
use crate::forces::bending::{self, BendingDesc};
use crate::forces::fem_tet::{self, TetDesc};
use crate::forces::fem_tri::{self, TriangleDesc};
use crate::forces::particle::{self as drag, DragDesc};
use crate::forces::spring::{self, SpringDesc};
use crate::model::ModelBuilder;
use crate::particles::{self, Elements, ParticleDesc};
use crate::rigid::{self, BodySection};
use crate::scenes::cloth::{self, ClothGridDesc};

pub(crate) mod reader;

use reader::{field_of, json_error, toml_error, v3, Checker, Format};
pub use reader::{SceneError, MAX_NESTING};

/// The sections of a scene file, in the order they are loaded. Each section's description
/// and loader live with what they describe (a family or a force).
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
    bodies: Vec<BodySection>,
    #[serde(default)]
    distance_constraints: Vec<DistanceDesc>,
}

/// Builds the scene with the builder's parts, whose checks (see [`crate::validation`]) are
/// the reader's: each builder problem is reported at the field of the file it comes from. Only
/// what the builder cannot see is checked by the loaders themselves (the file's own
/// structure, values lost in the conversion to `R`, quaternions and normals before they are
/// normalized).
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
    particles::load(&d.particles, &mut b.particles, &mut b.problems, &c)?;
    cloth::load(&d.cloth_grids, &mut b, &c)?;
    let (f, mut el) = b.parts();
    spring::load(&d.springs, &mut f.springs, &mut el, &c)?;
    // Bending is on the file's own triangles (cloth grids have their own bending settings).
    let first_file_triangle = b.particles.triangles.len();
    fem_tri::load(
        &d.triangles,
        &mut b.forces.triangle_fem,
        &mut b.particles,
        &mut b.problems,
        &c,
    )?;
    let (f, mut el) = b.parts();
    if let Some(bd) = &d.bending {
        let tris = el.particles.triangles[first_file_triangle..].to_vec();
        bending::load(bd, &tris, &mut f.bending, &mut el, &c)?;
    }
    fem_tet::load(&d.tets, &mut f.tets, &mut el, &c)?;
    if let Some(g) = &d.ground {
        ground::load(g, &mut f.ground, el.problems, &c)?;
    }
    if let Some(dr) = &d.drag {
        drag::load(dr, &mut f.drag, el.problems, &c)?;
    }
    if let Some(cd) = &d.particle_contact {
        particle::load(cd, &mut f.particle_contact, el.problems, &c)?;
    }
    if let Some(cd) = &d.shape_contact {
        shapes::load_contact(cd, &mut f.shape_contact, &mut el, &c)?;
    }
    shapes::load(&d.shapes, &mut f.shape_contact, &mut el, &c)?;
    rigid::load(&d.bodies, &mut b.bodies, &mut b.problems, &c)?;
    let mut el = Elements {
        particles: &b.particles,
        problems: &mut b.problems,
    };
    constraints::load(&d.distance_constraints, &mut b.constraints, &mut el, &c)?;
    Ok(b)
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
