//! The scene description ([`ModelBuilder`]), the simulation model it produces ([`Model`]),
//! the time-varying [`State`] and the per-step actuation [`Control`].
//!
//! A `Model` holds arrays only for the components the scene has (its forces are a list of
//! [`Force`] components, see [`crate::forces`]), and [`Model::eval_forces`] launches only
//! their kernels: a scene costs only what it contains.

use adflex_runtime::{AnyArray, Array, Element, Error, Mat22, Mat33, Quat, Real, Tape, Vec3};

use crate::constraints::DistanceConstraints;
use crate::contact::ground::Ground;
use crate::contact::particle::ParticleContact;
use crate::contact::shapes::{Shape, Shapes};
use crate::forces::bending::{bending_edges, dihedral_angle, Bending, RestAngle};
use crate::forces::fem_tet::{tet_quality, tet_rest, TetFem};
use crate::forces::fem_tri::{triangle_quality, triangle_rest, TriangleFem};
use crate::forces::particle::{accelerations, add_forces, Drag};
use crate::forces::spring::Springs;
use crate::forces::{Force, ForceContext};
use crate::precompiled::precompiled;
use crate::rigid::RigidBodies;
use crate::state::BodyState;
pub use crate::state::{BodyForces, Control, State};
use crate::validation::{
    max_of, min_quality, overflow_hint, precision, Check, ModelError, Problem,
};

fn lit<R: Real>(x: f64) -> R {
    R::lit(x)
}

fn wide<R: Real>(v: Vec3<R>) -> Vec3<f64> {
    Vec3::new(v.x.to_f64(), v.y.to_f64(), v.z.to_f64())
}

/// A rigid body as the builder records it.
#[derive(Clone, Copy, Debug)]
struct BodyDesc<R: Real> {
    x: Vec3<R>,
    q: Quat<R>,
    v: Vec3<R>,
    w: Vec3<R>,
    mass: R,
    inertia: Mat33<R>,
}

/// Describes a scene element by element; [`ModelBuilder::finalize`] makes the [`Model`].
///
/// Indices returned by the `add_*` methods are what later elements refer to.
///
/// Every method checks its inputs and what it derives from them (see
/// [`crate::validation`]): bad input (an index out of range, a NaN or negative mass, a
/// degenerate element, a coordinate that overflows `R`) is recorded as a [`Problem`] naming
/// the item and parameter, never silently accepted and never a panic inside the method;
/// [`ModelBuilder::try_finalize`] returns them all, [`ModelBuilder::finalize`] panics with
/// the list.
#[derive(Clone, Debug)]
pub struct ModelBuilder<R: Real> {
    /// Gravity (m/s^2); default `(0, -9.8, 0)`.
    pub gravity: Vec3<R>,
    /// Radius for contact (m) of every particle not given its own radius
    /// ([`ModelBuilder::set_particle_radius`]); default 0.01.
    pub particle_radius: R,
    particle_x: Vec<Vec3<R>>,
    particle_radii: Vec<Option<R>>,
    particle_v: Vec<Vec3<R>>,
    particle_inv_mass: Vec<R>,
    spring_pairs: Vec<[u32; 2]>,
    spring_rest: Vec<R>,
    spring_ke: Vec<R>,
    spring_kd: Vec<R>,
    triangles: Vec<[u32; 3]>,
    tri_fem: Vec<[u32; 3]>,
    tri_dm_inv: Vec<Mat22<R>>,
    tri_area: Vec<R>,
    tri_mu: Vec<R>,
    tri_lambda: Vec<R>,
    tri_kd: Vec<R>,
    bend_quads: Vec<[u32; 4]>,
    bend_rest: Vec<R>,
    bend_ke: Vec<R>,
    bend_kd: Vec<R>,
    tets: Vec<[u32; 4]>,
    tet_dm_inv: Vec<Mat33<R>>,
    tet_volume: Vec<R>,
    tet_mu: Vec<R>,
    tet_lambda: Vec<R>,
    tet_kd: Vec<R>,
    ground: Option<Ground<R>>,
    drag: Option<Drag<R>>,
    particle_contact: Option<ParticleContact<R>>,
    shapes: Vec<Shape<R>>,
    shape_contact: ParticleContact<R>,
    bodies: Vec<BodyDesc<R>>,
    body_contacts: Vec<(u32, Vec3<R>)>,
    dist_pairs: Vec<[u32; 2]>,
    dist_rest: Vec<R>,
    dist_compliance: Vec<R>,
    forces: AddedForces<R>,
    problems: Vec<Problem>,
}

/// The forces added with [`ModelBuilder::add_force`]. The builder only clones them (array
/// handles), so a panic inside a builder method cannot leave them half-updated: the builder
/// stays unwind-safe (as it was before forces held arrays, whose `UnsafeCell` is not).
#[derive(Clone, Debug, Default)]
struct AddedForces<R: Real>(Vec<Box<dyn Force<R>>>);

impl<R: Real> std::panic::UnwindSafe for AddedForces<R> {}
impl<R: Real> std::panic::RefUnwindSafe for AddedForces<R> {}

impl<R: Real> Default for ModelBuilder<R> {
    fn default() -> Self {
        Self::new()
    }
}

impl<R: Real> ModelBuilder<R> {
    /// An empty scene with gravity `(0, -9.8, 0)` m/s^2 and particle radius 0.01 m.
    pub fn new() -> Self {
        ModelBuilder {
            gravity: Vec3::new(lit(0.0), lit(-9.8), lit(0.0)),
            particle_radius: lit(0.01),
            particle_x: Vec::new(),
            particle_radii: Vec::new(),
            particle_v: Vec::new(),
            particle_inv_mass: Vec::new(),
            spring_pairs: Vec::new(),
            spring_rest: Vec::new(),
            spring_ke: Vec::new(),
            spring_kd: Vec::new(),
            triangles: Vec::new(),
            tri_fem: Vec::new(),
            tri_dm_inv: Vec::new(),
            tri_area: Vec::new(),
            tri_mu: Vec::new(),
            tri_lambda: Vec::new(),
            tri_kd: Vec::new(),
            bend_quads: Vec::new(),
            bend_rest: Vec::new(),
            bend_ke: Vec::new(),
            bend_kd: Vec::new(),
            tets: Vec::new(),
            tet_dm_inv: Vec::new(),
            tet_volume: Vec::new(),
            tet_mu: Vec::new(),
            tet_lambda: Vec::new(),
            tet_kd: Vec::new(),
            ground: None,
            drag: None,
            particle_contact: None,
            shapes: Vec::new(),
            shape_contact: ParticleContact::default(),
            bodies: Vec::new(),
            body_contacts: Vec::new(),
            dist_pairs: Vec::new(),
            dist_rest: Vec::new(),
            dist_compliance: Vec::new(),
            forces: AddedForces::default(),
            problems: Vec::new(),
        }
    }

    /// Number of particles added so far.
    pub fn particle_count(&self) -> usize {
        self.particle_x.len()
    }

    /// Position (m) of particle `i`. Panics if there is no particle `i`.
    pub fn particle_position(&self, i: u32) -> Vec3<R> {
        self.particle_x[i as usize]
    }

    /// The problems recorded so far by the builder methods, in call order (see
    /// [`crate::validation`]).
    pub fn problems(&self) -> &[Problem] {
        &self.problems
    }

    /// The checks of item `kind[index]`.
    fn check(&mut self, kind: &'static str, index: usize) -> Check<'_> {
        Check {
            out: &mut self.problems,
            kind,
            index: Some(index),
        }
    }

    /// Adds a particle at `x` (m) with velocity `v` (m/s) and mass `mass` (kg, finite and
    /// `>= 0`; 0 = pinned: inverse mass 0, so no force and no gravity moves it). Returns its
    /// index. `x`, `v` and the inverse mass `1 / mass` must be finite in `R` (a mass below
    /// `1 / R::MAX`, e.g. 1e-320 kg, is a problem, not a pinned particle).
    pub fn add_particle(&mut self, x: Vec3<R>, v: Vec3<R>, mass: R) -> u32 {
        let k = self.particle_count();
        let m = mass.to_f64();
        let inv = if m > 0.0 { 1.0 / m } else { 0.0 };
        let inv_r: R = lit(inv);
        let mut c = self.check("particles", k);
        if c.nonneg("mass", mass) && !inv_r.to_f64().is_finite() {
            c.fail(
                Some("mass"),
                format!(
                    "the inverse mass 1/{m:e} is not finite in {}: give a mass of at least \
                     {:.1e} kg, or 0 to pin the particle",
                    precision::<R>(),
                    1.0 / max_of::<R>()
                ),
            );
        }
        self.push_particle(x, v, inv_r, false)
    }

    /// Adds a particle with inverse mass `inv_mass` (1/kg, finite and `>= 0`; 0 = pinned).
    /// Returns its index.
    pub fn add_particle_inv_mass(&mut self, x: Vec3<R>, v: Vec3<R>, inv_mass: R) -> u32 {
        self.push_particle(x, v, inv_mass, true)
    }

    fn push_particle(&mut self, x: Vec3<R>, v: Vec3<R>, inv_mass: R, check_inv: bool) -> u32 {
        let k = self.particle_count();
        let mut c = self.check("particles", k);
        c.finite3("x", &x);
        c.finite3("v", &v);
        if check_inv {
            c.nonneg("inv_mass", inv_mass);
        }
        self.particle_x.push(x);
        self.particle_radii.push(None);
        self.particle_v.push(v);
        self.particle_inv_mass.push(inv_mass);
        k as u32
    }

    /// Adds a particle like [`ModelBuilder::add_particle`] with its own contact radius
    /// `radius` (m, finite and `>= 0`; see [`ModelBuilder::set_particle_radius`]).
    pub fn add_particle_with_radius(&mut self, x: Vec3<R>, v: Vec3<R>, mass: R, radius: R) -> u32 {
        let i = self.add_particle(x, v, mass);
        self.set_particle_radius(i, radius);
        i
    }

    /// Gives particle `i` its own contact radius `radius` (m, finite and `>= 0`), used by the
    /// ground and shape contact (`r_i`) and particle contact (`r_i + r_j`) in place of
    /// [`ModelBuilder::particle_radius`]. The model keeps an array of radii
    /// ([`Model::particle_radii`]) only if some particle's radius differs from
    /// `particle_radius`.
    pub fn set_particle_radius(&mut self, i: u32, radius: R) {
        let n = self.particle_count();
        let mut c = self.check("particles", i as usize);
        if (i as usize) >= n {
            c.fail(
                None,
                format!("set_particle_radius: particle index {i} out of range ({n} particles)"),
            );
        } else if c.nonneg("radius", radius) {
            self.particle_radii[i as usize] = Some(radius);
        }
    }

    /// The contact radius (m) of particle `i`: its own, or [`ModelBuilder::particle_radius`].
    /// Panics if there is no particle `i`.
    pub fn particle_radius_of(&self, i: u32) -> R {
        self.particle_radii[i as usize].unwrap_or(self.particle_radius)
    }

    /// Sets the inverse mass (1/kg, finite and `>= 0`) of particle `i` (0 pins it).
    pub fn set_particle_inv_mass(&mut self, i: u32, inv_mass: R) {
        let n = self.particle_count();
        let mut c = self.check("particles", i as usize);
        if (i as usize) >= n {
            c.fail(
                None,
                format!("set_particle_inv_mass: particle index {i} out of range ({n} particles)"),
            );
        } else if c.nonneg("inv_mass", inv_mass) {
            self.particle_inv_mass[i as usize] = inv_mass;
        }
    }

    /// Checks that `idx` are distinct particles of the scene (recording a problem of
    /// `kind[index]` if not).
    fn check_particles(&mut self, kind: &'static str, index: usize, idx: &[u32]) -> bool {
        let n = self.particle_count();
        self.check(kind, index).particles(n, idx)
    }

    /// `rest` (m) of `kind[index]` between particles `i`, `j`: finite and `> 0`.
    fn check_rest(
        &mut self,
        kind: &'static str,
        index: usize,
        ij: [u32; 2],
        rest: R,
        derived: bool,
    ) {
        let r = rest.to_f64();
        if r.is_finite() && r > 0.0 {
            return;
        }
        let [i, j] = ij;
        let why = if !derived {
            String::new()
        } else if r == 0.0 {
            format!(": particles {i} and {j} are at the same position; move one")
        } else {
            format!(
                ": the distance between particles {i} and {j} overflows{}",
                overflow_hint::<R>()
            )
        };
        self.check(kind, index).fail(
            if derived { None } else { Some("rest") },
            format!("the rest length must be finite and > 0 (got {r}){why}"),
        );
    }

    /// Adds a spring between distinct particles `i` and `j` with rest length their current
    /// distance (computed in `R`; it must be finite and `> 0`), stiffness `ke` (N/m) and
    /// damping `kd` (N s/m), both finite and `>= 0`. Returns its index.
    pub fn add_spring(&mut self, i: u32, j: u32, ke: R, kd: R) -> u32 {
        let k = self.spring_count();
        let rest = if self.check_particles("springs", k, &[i, j]) {
            let d = self.particle_x[i as usize] - self.particle_x[j as usize];
            // The same sum order as numpy's norm of a 3-vector (the reference scene's rest
            // lengths).
            let rest = (d.x * d.x + d.y * d.y + d.z * d.z).sqrt();
            self.check_rest("springs", k, [i, j], rest, true);
            rest
        } else {
            lit(1.0)
        };
        self.push_spring(i, j, rest, ke, kd)
    }

    /// Adds a spring with an explicit rest length (m, finite and `> 0`). Returns its index.
    pub fn add_spring_with_rest(&mut self, i: u32, j: u32, rest: R, ke: R, kd: R) -> u32 {
        let k = self.spring_count();
        self.check_particles("springs", k, &[i, j]);
        self.check_rest("springs", k, [i, j], rest, false);
        self.push_spring(i, j, rest, ke, kd)
    }

    fn push_spring(&mut self, i: u32, j: u32, rest: R, ke: R, kd: R) -> u32 {
        let mut c = self.check("springs", self.spring_pairs.len());
        c.nonneg("ke", ke);
        c.nonneg("kd", kd);
        self.spring_pairs.push([i, j]);
        self.spring_rest.push(rest);
        self.spring_ke.push(ke);
        self.spring_kd.push(kd);
        (self.spring_pairs.len() - 1) as u32
    }

    /// Number of springs added so far.
    pub fn spring_count(&self) -> usize {
        self.spring_pairs.len()
    }

    /// Adds a triangle to the surface topology (used by [`ModelBuilder::add_bending_edges`]);
    /// it exerts no force of its own (see [`ModelBuilder::add_triangle_fem`]).
    /// Its vertices must be distinct particles.
    pub fn add_triangle(&mut self, i: u32, j: u32, k: u32) -> u32 {
        self.check_particles("triangles", self.triangles.len(), &[i, j, k]);
        self.triangles.push([i, j, k]);
        (self.triangles.len() - 1) as u32
    }

    /// The surface triangles added so far.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    /// Adds a StVK membrane triangle (also to the surface topology), rest shape from the current
    /// positions; `mu` (N/m, `>= 0`), `lambda` (N/m, finite), `kd` (N s/m, `>= 0`). The
    /// triangle must not be degenerate: quality (see
    /// [`crate::forces::fem_tri::triangle_quality`]) at least
    /// [`crate::validation::min_quality`], `Dm^-1` finite and area above `R::tiny()` in `R`;
    /// otherwise a problem of `triangle_fem[k]` is recorded.
    pub fn add_triangle_fem(&mut self, i: u32, j: u32, k: u32, mu: R, lambda: R, kd: R) -> u32 {
        let e = self.tri_fem.len();
        let ok = self.check_particles("triangle_fem", e, &[i, j, k]);
        self.triangles.push([i, j, k]);
        let (dm_inv, area) =
            if ok {
                let p = |i: u32| wide(self.particle_x[i as usize]);
                let (a, b, c) = (p(i), p(j), p(k));
                match triangle_rest(a, b, c) {
                    Some((dm_inv, area)) => {
                        let dm_inv = dm_inv.map(lit::<R>);
                        let q = triangle_quality(a, b, c);
                        let what = format!("the triangle on particles ({i}, {j}, {k})");
                        let mut c = self.check("triangle_fem", e);
                        if q < min_quality::<R>() {
                            c.fail(
                                None,
                                format!(
                            "{what} is nearly degenerate (flat): quality {q:.1e} (1 for an \
                             equilateral triangle) is below {:.1e} in {}; move its vertices \
                             apart or remove it",
                            min_quality::<R>(), precision::<R>()),
                            );
                        } else if !dm_inv.iter().all(|v| v.to_f64().is_finite())
                            || lit::<R>(area).to_f64().partial_cmp(&R::tiny().to_f64())
                                != Some(std::cmp::Ordering::Greater)
                        {
                            c.fail(
                                None,
                                format!(
                                    "{what} is too small or too large for {} (area {area:e} m^2, \
                             rest-shape inverse not finite or area below {:e}); rescale the scene",
                                    precision::<R>(),
                                    R::tiny().to_f64()
                                ),
                            );
                        }
                        (dm_inv, lit(area))
                    }
                    None => {
                        self.check("triangle_fem", e).fail(
                            None,
                            format!(
                                "the triangle on particles ({i}, {j}, {k}) is degenerate (zero or \
                             non-finite area); move its vertices apart or remove it"
                            ),
                        );
                        (Mat22::identity(), lit(1.0))
                    }
                }
            } else {
                (Mat22::identity(), lit(1.0))
            };
        let mut c = self.check("triangle_fem", e);
        c.nonneg("mu", mu);
        c.finite("lambda", &[lambda]);
        c.nonneg("kd", kd);
        self.tri_fem.push([i, j, k]);
        self.tri_dm_inv.push(dm_inv);
        self.tri_area.push(area);
        self.tri_mu.push(mu);
        self.tri_lambda.push(lambda);
        self.tri_kd.push(kd);
        (self.tri_fem.len() - 1) as u32
    }

    /// Adds a bending element `(o1, o2, e0, e1)` (opposite vertices, then the shared edge) with
    /// rest angle `rest` (rad, finite), stiffness `ke` (N m/rad) and damping `kd` (N m s/rad),
    /// both finite and `>= 0`; the four particles must be distinct.
    pub fn add_bending(&mut self, quad: [u32; 4], rest: R, ke: R, kd: R) -> u32 {
        let k = self.bend_quads.len();
        self.check_particles("bending", k, &quad);
        let mut c = self.check("bending", k);
        c.finite("rest", &[rest]);
        c.nonneg("ke", ke);
        c.nonneg("kd", kd);
        self.bend_quads.push(quad);
        self.bend_rest.push(rest);
        self.bend_ke.push(ke);
        self.bend_kd.push(kd);
        (self.bend_quads.len() - 1) as u32
    }

    /// Adds a bending element on every edge shared by two of the triangles added so far, in
    /// dFlex/Warp order (see [`bending_edges`]); returns how many. Call it once, after the
    /// triangles.
    pub fn add_bending_edges(&mut self, ke: R, kd: R, rest: RestAngle) -> usize {
        let quads = bending_edges(&self.triangles);
        let xs: Vec<Vec3<f64>> = self.particle_x.iter().map(|&p| wide(p)).collect();
        for &q in &quads {
            let angle = match rest {
                RestAngle::Flat => 0.0,
                RestAngle::Initial => dihedral_angle(&xs, q),
            };
            self.add_bending(q, lit(angle), ke, kd);
        }
        quads.len()
    }

    /// Adds a stable Neo-Hookean tetrahedron, rest shape from the current positions; `mu`,
    /// `lambda` (Pa, see [`crate::forces::fem_tet::snh_lame`]), `kd` (Pa s): `mu`, `kd` finite
    /// and `>= 0`, `lambda` finite and `> 0`. A negatively oriented tetrahedron is stored as
    /// `(i, k, j, l)`. The four particles must be distinct and the tetrahedron not degenerate:
    /// quality (see [`crate::forces::fem_tet::tet_quality`]) at least
    /// [`crate::validation::min_quality`], `Dm^-1` finite and volume above `R::tiny()` in `R`;
    /// otherwise a problem of `tets[k]` is recorded.
    #[allow(clippy::too_many_arguments)]
    pub fn add_tet(&mut self, i: u32, j: u32, k: u32, l: u32, mu: R, lambda: R, kd: R) -> u32 {
        let e = self.tets.len();
        let mut idx = [i, j, k, l];
        let (mut dm_inv, mut vol) = (Mat33::identity(), 1.0);
        if self.check_particles("tets", e, &idx) {
            let p = |i: u32| wide(self.particle_x[i as usize]);
            let what = format!("the tetrahedron on particles ({i}, {j}, {k}, {l})");
            match tet_rest([p(i), p(j), p(k), p(l)]) {
                None => self.check("tets", e).fail(
                    None,
                    format!(
                        "{what} is degenerate (zero or non-finite volume); move a vertex off \
                         the plane of the other three or remove it"
                    ),
                ),
                Some(r) => {
                    (dm_inv, vol) = r;
                    if vol < 0.0 {
                        idx = [i, k, j, l];
                        (dm_inv, vol) =
                            tet_rest([p(i), p(k), p(j), p(l)]).expect("reoriented tetrahedron");
                    }
                    let q = tet_quality([p(i), p(j), p(k), p(l)]);
                    let finite = dm_inv.iter().all(|v| lit::<R>(*v).to_f64().is_finite());
                    let mut c = self.check("tets", e);
                    if q < min_quality::<R>() {
                        c.fail(
                            None,
                            format!(
                                "{what} is nearly degenerate (flat): quality {q:.1e} (1 for a \
                             regular tetrahedron) is below {:.1e} in {}; move a vertex off the \
                             plane of the other three or remove it",
                                min_quality::<R>(),
                                precision::<R>()
                            ),
                        );
                    } else if !finite
                        || lit::<R>(vol).to_f64().partial_cmp(&R::tiny().to_f64())
                            != Some(std::cmp::Ordering::Greater)
                    {
                        c.fail(
                            None,
                            format!(
                                "{what} is too small or too large for {} (volume {vol:e} m^3, \
                             rest-shape inverse not finite or volume below {:e}); rescale the \
                             scene",
                                precision::<R>(),
                                R::tiny().to_f64()
                            ),
                        );
                    }
                }
            }
        }
        let mut c = self.check("tets", e);
        c.nonneg("mu", mu);
        c.positive("lambda", lambda);
        c.nonneg("kd", kd);
        self.tets.push(idx);
        self.tet_dm_inv.push(dm_inv.map(lit));
        self.tet_volume.push(lit(vol));
        self.tet_mu.push(mu);
        self.tet_lambda.push(lambda);
        self.tet_kd.push(kd);
        (self.tets.len() - 1) as u32
    }

    /// Number of tetrahedra added so far.
    pub fn tet_count(&self) -> usize {
        self.tets.len()
    }

    /// The checks of the single item `kind`.
    pub(crate) fn check_one(&mut self, kind: &'static str) -> Check<'_> {
        Check {
            out: &mut self.problems,
            kind,
            index: None,
        }
    }

    /// Sets the ground plane for particle and body contact (unit normal; `ke`, `kd`, `mu`,
    /// `leak` finite and `>= 0`).
    pub fn set_ground(&mut self, ground: Ground<R>) {
        ground.check(&mut self.check_one("ground"));
        self.ground = Some(ground);
    }

    /// Sets linear drag / wind on every particle (`kd` finite and `>= 0`, `wind` finite).
    pub fn set_drag(&mut self, drag: Drag<R>) {
        drag.check(&mut self.check_one("drag"));
        self.drag = Some(drag);
    }

    /// Enables particle-particle contact (every parameter finite and `>= 0`).
    pub fn set_particle_contact(&mut self, contact: ParticleContact<R>) {
        contact.check(&mut self.check_one("particle_contact"));
        self.particle_contact = Some(contact);
    }

    /// Adds a static analytic shape that particles collide with (finite position, unit
    /// orientation, sizes `> 0`). Returns its index.
    pub fn add_shape(&mut self, shape: Shape<R>) -> u32 {
        let k = self.shapes.len();
        shape.check(&mut self.check("shapes", k));
        self.shapes.push(shape);
        k as u32
    }

    /// Sets the contact parameters of particles against shapes (`margin` is unused; every
    /// parameter finite and `>= 0`).
    pub fn set_shape_contact(&mut self, contact: ParticleContact<R>) {
        contact.check(&mut self.check_one("shape_contact"));
        self.shape_contact = contact;
    }

    /// Adds a rigid body: centre of mass at `x` (m), orientation `q`, velocity `v` (m/s),
    /// angular velocity `w` (rad/s, world frame), mass (kg; 0 = static) and inertia about the
    /// centre of mass in body frame (kg m^2). Returns its index. `x`, `v`, `w`, `q` (nonzero)
    /// and `inertia` must be finite, `mass` finite and `>= 0`; a dynamic body (`mass > 0`)
    /// needs `1 / mass` finite in `R` and an invertible inertia with a finite inverse.
    pub fn add_body(
        &mut self,
        x: Vec3<R>,
        q: Quat<R>,
        v: Vec3<R>,
        w: Vec3<R>,
        mass: R,
        inertia: Mat33<R>,
    ) -> u32 {
        let mut c = self.check("bodies", self.bodies.len());
        c.finite3("x", &x);
        c.finite3("v", &v);
        c.finite3("w", &w);
        if c.finite("q", &[q.i, q.j, q.k, q.w]) && q.norm().to_f64() == 0.0 {
            c.fail(Some("q"), "must be a nonzero quaternion".into());
        }
        let inertia_ok = c.finite("inertia", inertia.as_slice());
        if c.nonneg("mass", mass) && mass.to_f64() > 0.0 {
            if !(lit::<R>(1.0) / mass).to_f64().is_finite() {
                c.fail(
                    Some("mass"),
                    format!(
                        "the inverse mass 1/{:e} is not finite in {}; give a mass of at least \
                         {:.1e} kg, or 0 for a static body",
                        mass.to_f64(),
                        precision::<R>(),
                        1.0 / max_of::<R>()
                    ),
                );
            }
            let inv_ok = inertia
                .try_inverse()
                .is_some_and(|m| m.iter().all(|v| v.to_f64().is_finite()));
            if inertia_ok && !inv_ok {
                c.fail(
                    Some("inertia"),
                    "must be invertible (with a finite inverse) for a body with mass > 0".into(),
                );
            }
        }
        self.bodies.push(BodyDesc {
            x,
            q: q.normalize(),
            v,
            w,
            mass,
            inertia,
        });
        (self.bodies.len() - 1) as u32
    }

    /// Adds a contact point `p` (m, body frame) to body `body`, which then touches the ground.
    /// `body` must exist and `p` be finite.
    pub fn add_body_contact_point(&mut self, body: u32, p: Vec3<R>) {
        let nb = self.bodies.len();
        let mut c = self.check("body_contact_points", self.body_contacts.len());
        if (body as usize) >= nb {
            c.fail(
                Some("body"),
                format!("body {body} out of range ({nb} bodies)"),
            );
        }
        c.finite3("p", &p);
        self.body_contacts.push((body, p));
    }

    /// Adds an XPBD distance constraint between particles `i` and `j`, rest distance their
    /// current distance (finite and `> 0`), compliance `compliance` (m/N, finite and `>= 0`;
    /// 0 = rigid). Returns its index.
    pub fn add_distance_constraint(&mut self, i: u32, j: u32, compliance: R) -> u32 {
        let k = self.dist_pairs.len();
        let rest = if self.check_particles("distance_constraints", k, &[i, j]) {
            let d = self.particle_x[i as usize] - self.particle_x[j as usize];
            self.check_rest("distance_constraints", k, [i, j], d.norm(), true);
            d.norm()
        } else {
            lit(1.0)
        };
        self.check("distance_constraints", k)
            .nonneg("compliance", compliance);
        self.dist_pairs.push([i, j]);
        self.dist_rest.push(rest);
        self.dist_compliance.push(compliance);
        (self.dist_pairs.len() - 1) as u32
    }

    /// Adds a force component (see [`crate::forces`]): a force of the library built by hand,
    /// or one written outside it. The model evaluates it after the library's forces, in the
    /// order added; every integrator steps it, and its parameter arrays
    /// ([`Force::params_mut`]) get gradients like the library's. Returns its index among the
    /// added forces.
    pub fn add_force(&mut self, force: impl Force<R> + 'static) -> usize {
        self.add_force_boxed(Box::new(force))
    }

    /// [`ModelBuilder::add_force`] for a boxed force.
    pub fn add_force_boxed(&mut self, force: Box<dyn Force<R>>) -> usize {
        self.forces.0.push(force);
        self.forces.0.len() - 1
    }

    /// Builds the model: arrays for what the scene contains, nothing for the rest. Panics
    /// with the full list of problems (see [`ModelBuilder::try_finalize`]) if there are any.
    pub fn finalize(&self) -> Model<R> {
        self.try_finalize().unwrap_or_else(|e| panic!("{e}"))
    }

    /// Every problem of the scene: those the builder methods recorded, and those of `gravity`
    /// (must be finite) and `particle_radius` (finite and `>= 0`), set directly.
    pub fn validate(&self) -> Result<(), ModelError> {
        let mut problems = self.problems.clone();
        Check {
            out: &mut problems,
            kind: "gravity",
            index: None,
        }
        .finite3("gravity", &self.gravity);
        Check {
            out: &mut problems,
            kind: "particle_radius",
            index: None,
        }
        .nonneg("particle_radius", self.particle_radius);
        for p in &mut problems[self.problems.len()..] {
            p.param = None; // `gravity.gravity` reads as `gravity`
        }
        if problems.is_empty() {
            Ok(())
        } else {
            Err(ModelError { problems })
        }
    }

    /// Builds the model, or returns every problem of the scene (see [`crate::validation`]):
    /// bad inputs of the builder methods and bad derived values (inverse masses, rest lengths,
    /// rest shapes), each naming its item (`springs[3]`, `tets[0]`) and parameter.
    ///
    /// Panics for a scalar type `R` other than `f32` and `f64`, which the library's forces are
    /// compiled for (`Real` is implemented for those two only).
    pub fn try_finalize(&self) -> Result<Model<R>, ModelError> {
        self.validate()?;
        // Compiled in this crate (`precompiled`): a user crate does not code-generate the
        // library's kernels again.
        Ok(build_model(self))
    }

    pub(crate) fn build_model(&self) -> Model<R> {
        let n = self.particle_count();
        let springs = (!self.spring_pairs.is_empty()).then(|| Springs {
            pairs: Array::from_vec(self.spring_pairs.clone()).named("spring_pairs"),
            rest: Array::from_vec(self.spring_rest.clone()).named("spring_rest"),
            ke: Array::from_vec(self.spring_ke.clone()).named("spring_ke"),
            kd: Array::from_vec(self.spring_kd.clone()).named("spring_kd"),
        });
        let bending = (!self.bend_quads.is_empty()).then(|| Bending {
            quads: Array::from_vec(self.bend_quads.clone()).named("bend_quads"),
            rest: Array::from_vec(self.bend_rest.clone()).named("bend_rest"),
            ke: Array::from_vec(self.bend_ke.clone()).named("bend_ke"),
            kd: Array::from_vec(self.bend_kd.clone()).named("bend_kd"),
        });
        let triangles = (!self.tri_fem.is_empty()).then(|| TriangleFem {
            tris: Array::from_vec(self.tri_fem.clone()).named("tri_indices"),
            dm_inv: Array::from_vec(self.tri_dm_inv.clone()).named("tri_dm_inv"),
            area: Array::from_vec(self.tri_area.clone()).named("tri_area"),
            mu: Array::from_vec(self.tri_mu.clone()).named("tri_mu"),
            lambda: Array::from_vec(self.tri_lambda.clone()).named("tri_lambda"),
            kd: Array::from_vec(self.tri_kd.clone()).named("tri_kd"),
        });
        let tets = (!self.tets.is_empty()).then(|| TetFem {
            tets: Array::from_vec(self.tets.clone()).named("tet_indices"),
            dm_inv: Array::from_vec(self.tet_dm_inv.clone()).named("tet_dm_inv"),
            rest_volume: Array::from_vec(self.tet_volume.clone()).named("tet_volume"),
            mu: Array::from_vec(self.tet_mu.clone()).named("tet_mu"),
            lambda: Array::from_vec(self.tet_lambda.clone()).named("tet_lambda"),
            kd: Array::from_vec(self.tet_kd.clone()).named("tet_kd"),
            activation: Array::zeros(self.tets.len()).named("tet_activation"),
        });
        let shapes = (!self.shapes.is_empty()).then(|| {
            let codes: Vec<(u32, Vec3<R>)> = self.shapes.iter().map(|s| s.kind.code()).collect();
            Shapes {
                kind: Array::from_vec(codes.iter().map(|c| c.0).collect()).named("shape_kind"),
                pos: Array::from_vec(self.shapes.iter().map(|s| s.pos).collect())
                    .named("shape_pos"),
                rot: Array::from_vec(self.shapes.iter().map(|s| s.rot).collect())
                    .named("shape_rot"),
                size: Array::from_vec(codes.iter().map(|c| c.1).collect()).named("shape_size"),
                ke: self.shape_contact.ke,
                kd: self.shape_contact.kd,
                damping_depth: self.shape_contact.damping_depth,
                mu: self.shape_contact.mu,
                leak: self.shape_contact.leak,
            }
        });
        let bodies = (!self.bodies.is_empty()).then(|| {
            let b = &self.bodies;
            let inv_mass: Vec<R> = b
                .iter()
                .map(|b| {
                    if b.mass > lit(0.0) {
                        lit::<R>(1.0) / b.mass
                    } else {
                        lit(0.0)
                    }
                })
                .collect();
            let inv_inertia: Vec<Mat33<R>> = b
                .iter()
                .map(|b| {
                    if b.mass > lit(0.0) {
                        b.inertia.try_inverse().unwrap_or_else(Mat33::zeros)
                    } else {
                        Mat33::zeros()
                    }
                })
                .collect();
            let (cb, cp): (Vec<u32>, Vec<Vec3<R>>) = self.body_contacts.iter().copied().unzip();
            RigidBodies {
                inv_mass: Array::from_vec(inv_mass).named("body_inv_mass"),
                inertia: Array::from_vec(b.iter().map(|b| b.inertia).collect())
                    .named("body_inertia"),
                inv_inertia: Array::from_vec(inv_inertia).named("body_inv_inertia"),
                initial: BodyState {
                    x: Array::from_vec(b.iter().map(|b| b.x).collect()).named("body_x"),
                    q: Array::from_vec(b.iter().map(|b| b.q).collect()).named("body_q"),
                    v: Array::from_vec(b.iter().map(|b| b.v).collect()).named("body_v"),
                    w: Array::from_vec(b.iter().map(|b| b.w).collect()).named("body_w"),
                },
                contact_body: (!cb.is_empty())
                    .then(|| Array::from_vec(cb).named("body_contact_body")),
                contact_point: (!cp.is_empty())
                    .then(|| Array::from_vec(cp).named("body_contact_point")),
            }
        });
        let distance_constraints = (!self.dist_pairs.is_empty()).then(|| DistanceConstraints {
            pairs: Array::from_vec(self.dist_pairs.clone()).named("dist_pairs"),
            rest: Array::from_vec(self.dist_rest.clone()).named("dist_rest"),
            compliance: Array::from_vec(self.dist_compliance.clone()).named("dist_compliance"),
        });
        // The library's forces, in the order of `forces::BUILTIN_FORCES`, then the added ones.
        let ground = self.ground;
        let particle_contact = self.particle_contact;
        let drag = self.drag;
        let builtin: [Option<Box<dyn Force<R>>>; 8] = [
            springs.map(|f| Box::new(f) as Box<dyn Force<R>>),
            bending.map(|f| Box::new(f) as Box<dyn Force<R>>),
            triangles.map(|f| Box::new(f) as Box<dyn Force<R>>),
            tets.map(|f| Box::new(f) as Box<dyn Force<R>>),
            ground.map(|f| Box::new(f) as Box<dyn Force<R>>),
            particle_contact.map(|f| Box::new(f) as Box<dyn Force<R>>),
            shapes.map(|f| Box::new(f) as Box<dyn Force<R>>),
            drag.map(|f| Box::new(f) as Box<dyn Force<R>>),
        ];
        let forces = builtin
            .into_iter()
            .flatten()
            .chain(self.forces.0.iter().cloned())
            .collect();
        Model {
            particle_count: n,
            particle_x: Array::from_vec(self.particle_x.clone()).named("x0"),
            particle_v: Array::from_vec(self.particle_v.clone()).named("v0"),
            particle_inv_mass: Array::from_vec(self.particle_inv_mass.clone()).named("inv_mass"),
            gravity: self.gravity,
            particle_radius: self.particle_radius,
            particle_radii: self
                .particle_radii
                .iter()
                .any(|r| r.is_some_and(|r| r != self.particle_radius))
                .then(|| {
                    let radii = (0..n as u32).map(|i| self.particle_radius_of(i)).collect();
                    Array::from_vec(radii).named("particle_radius")
                }),
            triangles: self.triangles.clone(),
            forces,
            bodies,
            distance_constraints,
        }
    }
}

/// A simulation model: constant arrays of the scene's components (only those it has) and the
/// kernels that evaluate them.
#[derive(Clone, Debug)]
pub struct Model<R: Real> {
    /// Number of particles.
    pub particle_count: usize,
    /// Initial particle positions (m); [`Model::state`] copies them.
    pub particle_x: Array<Vec3<R>>,
    /// Initial particle velocities (m/s).
    pub particle_v: Array<Vec3<R>>,
    /// Inverse masses (1/kg; 0 = pinned).
    pub particle_inv_mass: Array<R>,
    /// Gravity (m/s^2).
    pub gravity: Vec3<R>,
    /// Particle radius for contact (m): every particle's, unless [`Model::particle_radii`]
    /// is present.
    pub particle_radius: R,
    /// Per-particle contact radii (m), present only if some particle was given a radius other
    /// than [`Model::particle_radius`] ([`ModelBuilder::set_particle_radius`]); the contact
    /// kernels then read `r_i` from it (not a gradient target).
    pub particle_radii: Option<Array<R>>,
    /// The surface triangles (topology, for output and bending; host only).
    pub triangles: Vec<[u32; 3]>,
    /// The forces on the particles (see [`crate::forces`]): the library's the scene has, in
    /// the order of [`crate::forces::BUILTIN_FORCES`], then those added with
    /// [`ModelBuilder::add_force`]. [`Model::eval_forces`], [`Model::elastic_energy`],
    /// [`Model::params`] and the integrators iterate this list.
    pub forces: Vec<Box<dyn Force<R>>>,
    /// Rigid bodies.
    pub bodies: Option<RigidBodies<R>>,
    /// XPBD distance constraints (used by position-based integrators; no force).
    pub distance_constraints: Option<DistanceConstraints<R>>,
}

impl<R: Real> Model<R> {
    /// The initial state: fresh copies of the initial arrays (gradients of a rollout from it
    /// land in its arrays; mark them with `requires_grad` first).
    pub fn state(&self) -> State<R> {
        State {
            x: self.particle_x.deep_clone().named("x"),
            v: self.particle_v.deep_clone().named("v"),
            bodies: self.bodies.as_ref().map(|b| b.initial.deep_clone()),
        }
    }

    /// The first force of type `T`, if the model has one (`model.force::<Springs<f64>>()`).
    pub fn force<T: 'static>(&self) -> Option<&T> {
        self.forces.iter().find_map(|f| f.downcast_ref::<T>())
    }

    /// The first force named `name` ([`Force::name`]), if any; downcast it to its type with
    /// `downcast_ref` (or use [`Model::force`]).
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::Vec3;
    /// let mut b = ModelBuilder::<f64>::new();
    /// b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
    /// b.set_drag(Drag { kd: 0.2, ..Drag::default() });
    /// let model = b.finalize();
    /// let drag = model.force_named("drag").unwrap().downcast_ref::<Drag<f64>>().unwrap();
    /// assert_eq!(drag.kd, 0.2);
    /// assert_eq!(model.force::<Drag<f64>>().unwrap().kd, 0.2);
    /// ```
    pub fn force_named(&self, name: &str) -> Option<&(dyn Force<R> + 'static)> {
        self.forces.iter().find(|f| f.name() == name).map(|f| &**f)
    }

    /// The springs, if the model has any.
    pub fn springs(&self) -> Option<&Springs<R>> {
        self.force()
    }
    /// The dihedral bending elements, if any.
    pub fn bending(&self) -> Option<&Bending<R>> {
        self.force()
    }
    /// The StVK membrane triangles, if any.
    pub fn tri_fem(&self) -> Option<&TriangleFem<R>> {
        self.force()
    }
    /// The stable Neo-Hookean tetrahedra, if any.
    pub fn tets(&self) -> Option<&TetFem<R>> {
        self.force()
    }
    /// The ground plane (particle and body contact), if any.
    pub fn ground(&self) -> Option<Ground<R>> {
        self.force().copied()
    }
    /// Drag / wind, if set.
    pub fn drag(&self) -> Option<Drag<R>> {
        self.force().copied()
    }
    /// Particle-particle contact, if enabled.
    pub fn particle_contact(&self) -> Option<ParticleContact<R>> {
        self.force().copied()
    }
    /// The analytic shapes, if any.
    pub fn shapes(&self) -> Option<&Shapes<R>> {
        self.force()
    }

    /// Every differentiable parameter array of the forces, as `(force, parameter, array)`
    /// (handles sharing the model's data): the forces' [`Force::params_mut`] visitors in the
    /// order of [`Model::forces`].
    pub fn params(&self) -> Vec<(&'static str, &'static str, Box<dyn AnyArray>)> {
        self.forces
            .iter()
            .flat_map(|f| {
                let force = f.name();
                f.params().into_iter().map(move |(p, a)| (force, p, a))
            })
            .collect()
    }

    /// The parameter array `param` of the force named `force` (a handle sharing the model's
    /// data: the simulation reads what you write into it), for an optimizer
    /// (`adflex::optim::Params`) or to read its gradient. The first such force if several
    /// have the name. `docs/guide.md` lists every force's parameters and units.
    ///
    /// Errors: [`Error::InvalidInput`] naming the parameters the model has if there is no such
    /// parameter, or if its element type is not `T`.
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::Vec3;
    /// let mut b = ModelBuilder::<f64>::new();
    /// let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let c = b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// b.add_spring(a, c, 100.0, 0.1);
    /// let model = b.finalize();
    /// let rest = model.param::<f64>("springs", "rest").unwrap();
    /// assert_eq!(rest.to_vec(), vec![1.0]);
    /// let err = model.param::<f64>("springs", "length").unwrap_err();
    /// assert!(err.to_string().contains("springs.rest"));
    /// ```
    pub fn param<T: Element>(&self, force: &str, param: &str) -> Result<Array<T>, Error> {
        let all = self.params();
        let Some((_, _, array)) = all.iter().find(|(f, p, _)| *f == force && *p == param) else {
            return Err(Error::InvalidInput {
                what: format!("{force}.{param}"),
                message: format!(
                    "the model has no such parameter array; it has: {}",
                    self.param_names()
                ),
            });
        };
        array
            .as_any()
            .downcast_ref::<Array<T>>()
            .cloned()
            .ok_or_else(|| Error::InvalidInput {
                what: format!("{force}.{param}"),
                message: format!(
                    "is an array of {} components per element, not of `{}`",
                    array.element_dim(),
                    std::any::type_name::<T>()
                ),
            })
    }

    /// Marks parameter `param` of every force named `force` as requiring a gradient (see
    /// [`Model::params`]); returns how many arrays it marked (at least 1).
    ///
    /// Errors: [`Error::InvalidInput`] naming the parameters the model has if no force named
    /// `force` has an array `param` (a misspelt name would otherwise mark nothing, and the
    /// gradient would be missing much later). [`Model::param`] returns the array itself.
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::Vec3;
    /// let mut b = ModelBuilder::<f64>::new();
    /// let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let c = b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// b.add_spring(a, c, 100.0, 0.1);
    /// let model = b.finalize();
    /// assert_eq!(model.requires_grad("springs", "ke").unwrap(), 1);
    /// let err = model.requires_grad("springs", "stiffness").unwrap_err();
    /// assert!(err.to_string().contains("springs.ke"));
    /// ```
    pub fn requires_grad(&self, force: &str, param: &str) -> Result<usize, Error> {
        let mut marked = 0;
        for f in &self.forces {
            if f.name() != force {
                continue;
            }
            let mut handle = f.clone();
            handle.params_mut(&mut |name, p| {
                if name == param {
                    p.set_requires_grad();
                    marked += 1;
                }
            });
        }
        if marked == 0 {
            return Err(Error::InvalidInput {
                what: format!("{force}.{param}"),
                message: format!(
                    "Model::requires_grad: the model has no such parameter array; it has: {}",
                    self.param_names()
                ),
            });
        }
        Ok(marked)
    }

    /// `force.param` of every parameter array, for messages ("none" if there is none).
    fn param_names(&self) -> String {
        let names: Vec<String> = self
            .params()
            .iter()
            .map(|(f, p, _)| format!("{f}.{p}"))
            .collect();
        match names.is_empty() {
            true => "none".to_string(),
            false => names.join(", "),
        }
    }

    /// Records the force kernels of every force of the model ([`Model::forces`], in order)
    /// and returns the total force on each particle (N), in a new array, with the control's
    /// external forces. Gravity is not a force here (see [`Model::eval_accelerations`]).
    pub fn eval_forces(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
    ) -> Array<Vec3<R>> {
        let f = Array::zeros(self.particle_count).named("f");
        let cx = self.context(state, control);
        for force in &self.forces {
            force.eval(&cx, tape, &f);
        }
        if let Some(fext) = control.and_then(|c| c.particle_f.as_ref()) {
            tape.launch(add_forces, self.particle_count, (fext, &f));
        }
        f
    }

    /// Accelerations (m/s^2) of the particles: `f w + g [w > 0]` with `f` from
    /// [`Model::eval_forces`] (`w` the inverse mass, `g` gravity), in a new array.
    pub fn eval_accelerations(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
    ) -> Array<Vec3<R>> {
        let f = self.eval_forces(tape, state, control);
        let a = Array::zeros(self.particle_count).named("a");
        tape.launch(
            accelerations,
            self.particle_count,
            (&f, &self.particle_inv_mass, self.gravity, &a),
        );
        a
    }

    /// Records the forces and torques on the rigid bodies (ground contact of their contact
    /// points, the control's `body_f`, `body_t`) and returns them (N, N m; world frame), or
    /// `None` if the model has no bodies. Gravity is applied by the integrator.
    pub fn eval_body_forces(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
    ) -> Option<BodyForces<R>> {
        let bodies = self.bodies.as_ref()?;
        let s = state
            .bodies
            .as_ref()
            .expect("the model has rigid bodies but the state has none");
        let n = bodies.len();
        let f = Array::zeros(n).named("body_f");
        let t = Array::zeros(n).named("body_t");
        if let Some(g) = &self.ground() {
            bodies.eval_ground(tape, s, g, &f, &t);
        }
        if let Some(c) = control {
            if let Some(bf) = &c.body_f {
                tape.launch(add_forces, n, (bf, &f));
            }
            if let Some(bt) = &c.body_t {
                tape.launch(add_forces, n, (bt, &t));
            }
        }
        Some((f, t))
    }

    /// The contact radius (m) of particle `i`. Panics if there is no particle `i`.
    pub fn particle_radius_of(&self, i: usize) -> R {
        assert!(i < self.particle_count, "no particle {i}");
        match &self.particle_radii {
            Some(r) => r.get(i),
            None => self.particle_radius,
        }
    }

    /// What the forces read: the state, the control, the particle radii.
    pub fn context<'a>(
        &'a self,
        state: &'a State<R>,
        control: Option<&'a Control<R>>,
    ) -> ForceContext<'a, R> {
        ForceContext {
            x: &state.x,
            v: &state.v,
            control,
            particle_radius: self.particle_radius,
            particle_radii: self.particle_radii.as_ref(),
        }
    }

    /// Records the elastic potential energy of the forces that have one ([`Force::energy`]:
    /// springs, membranes, tetrahedra, bending, the contact penalties, and any added force
    /// with a potential) (J) and returns it as a one-element array (for tests and
    /// energy-based integrators).
    pub fn elastic_energy(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
    ) -> Array<R> {
        let e = Array::zeros(1).named("energy");
        let cx = self.context(state, control);
        for force in &self.forces {
            force.energy(&cx, tape, &e);
        }
        e
    }
}

precompiled! {
    /// [`ModelBuilder::build_model`], which boxes the library's forces.
    fn build_model(builder: &ModelBuilder<R>) -> Model<R> {
        builder.build_model()
    }
}
