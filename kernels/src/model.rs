//! The scene description ([`ModelBuilder`]), the simulation model it produces ([`Model`]),
//! the time-varying [`State`] and the per-step actuation [`Control`].
//!
//! A `Model` holds arrays only for the components the scene has (its forces are a list of
//! [`Force`] components, see [`crate::forces`]), and [`Model::eval_forces`] launches only
//! their kernels: a scene costs only what it contains.

use adflex_runtime::{AnyArray, Array, Element, Error, Mat33, Quat, Real, Tape, Vec3};

use crate::constraints::{ConstraintParts, DistanceConstraints};
use crate::contact::ground::Ground;
use crate::contact::particle::ParticleContact;
use crate::contact::shapes::{Shape, Shapes};
use crate::forces::bending::{Bending, RestAngle};
use crate::forces::fem_tet::TetFem;
use crate::forces::fem_tri::TriangleFem;
use crate::forces::particle::{accelerations, add_forces, Drag};
use crate::forces::spring::Springs;
use crate::forces::{Force, ForceContext, ForceParts};
use crate::particles::{Elements, Particles};
use crate::precompiled::precompiled;
use crate::rigid::{BodyParts, BodyRecord, RigidBodies};
pub use crate::state::{BodyForces, BodyState, Control, State};
use crate::validation::{Check, ModelError, Problem};

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
    /// Gravity (m/s^2) of the worlds not added by [`ModelBuilder::add_world`] (which keep
    /// their own); default `(0, -9.8, 0)`.
    pub gravity: Vec3<R>,
    /// Radius for contact (m) of every particle not given its own radius
    /// ([`ModelBuilder::set_particle_radius`]); default 0.01.
    pub particle_radius: R,
    // The families' and the library forces' parts, each owned by its module.
    pub(crate) particles: Particles<R>,
    pub(crate) forces: ForceParts<R>,
    pub(crate) bodies: BodyParts<R>,
    pub(crate) constraints: ConstraintParts<R>,
    added: AddedForces<R>,
    pub(crate) problems: Vec<Problem>,
    /// Where each world's particles and bodies start, and its gravity (`None`:
    /// [`ModelBuilder::gravity`]; [`ModelBuilder::add_world`]).
    worlds: Vec<(usize, usize, Option<Vec3<R>>)>,
    /// Whether `add_world` was called (see the articulations' builder).
    world_added: bool,
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
            gravity: Vec3::new(R::lit(0.0), R::lit(-9.8), R::lit(0.0)),
            particle_radius: R::lit(0.01),
            particles: Particles::default(),
            forces: ForceParts::default(),
            bodies: BodyParts::default(),
            constraints: ConstraintParts::default(),
            added: AddedForces::default(),
            problems: Vec::new(),
            worlds: vec![(0, 0, None)],
            world_added: false,
        }
    }

    /// Adds the scene `other` as a new world (an empty builder's first `add_world` fills
    /// world 0); returns its index. Its particles, elements and bodies are appended with their
    /// indices shifted, and it keeps its gravity (`other.gravity`; [`Model::gravity`] has one
    /// per world: setting [`ModelBuilder::gravity`] afterwards changes no added world). Worlds
    /// never interact, and each is simulated in its own frame: they need no spacing, and with
    /// every integrator (`ImplicitEuler` and `Equilibrium` solve each world by its own Newton
    /// iteration) a world's results are the same bits whatever the other worlds
    /// (`kernels/tests/worlds.rs`).
    ///
    /// The ground, drag, shapes and particle-particle contact are the environment every world
    /// shares (a world without one takes the model's; two different ones are a problem at
    /// finalize); particle-particle contact touches only particles of one world. Not with
    /// worlds: forces added with [`ModelBuilder::add_force`] to `other` (add them to the
    /// combined builder, over all particles;
    /// [`ForceContext::particle_world`](crate::forces::ForceContext::particle_world) tells a
    /// force between particles which world each is in); a problem at finalize.
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::Vec3;
    ///
    /// let mut pendulum = ModelBuilder::<f64>::new();
    /// let pin = pendulum.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let bob = pendulum.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// pendulum.add_spring(pin, bob, 1e3, 0.0);
    /// let model = pendulum.replicate(4).finalize();
    /// assert_eq!(model.worlds.len(), 4);
    /// assert_eq!(model.worlds[2].particles, 4..6);
    /// assert_eq!(model.particle_world.to_vec(), vec![0, 0, 1, 1, 2, 2, 3, 3]);
    ///
    /// // A fifth world on the Moon.
    /// let mut moon = pendulum.clone();
    /// moon.gravity = Vec3::new(0.0, -1.62, 0.0);
    /// let mut b = pendulum.replicate(4);
    /// assert_eq!(b.add_world(&moon), 4);
    /// let model = b.finalize();
    /// assert_eq!(model.gravity.get(4).y, -1.62);
    /// assert_eq!(model.gravity.get(0).y, -9.8);
    /// ```
    pub fn add_world(&mut self, other: &ModelBuilder<R>) -> usize {
        let empty = self.particles.len() == 0 && self.bodies.len() == 0 && !self.world_added;
        self.world_added = true;
        if empty {
            self.worlds.clear();
            self.gravity = other.gravity;
            self.particle_radius = other.particle_radius;
        }
        let first = self.worlds.len();
        for &(p0, b0, g) in &other.worlds {
            self.worlds.push((
                self.particles.len() + p0,
                self.bodies.len() + b0,
                Some(g.unwrap_or(other.gravity)),
            ));
        }
        let offset = self.particles.len() as u32;
        self.particles.append(
            &other.particles,
            self.particle_radius,
            other.particle_radius,
        );
        self.bodies.append(&other.bodies);
        self.constraints.append(&other.constraints, offset);
        self.problems.extend(other.problems.iter().cloned());
        if let Err((force, why)) = self.forces.append(&other.forces, offset) {
            self.check_one("worlds")
                .fail(None, format!("`{force}` {why}"));
        }
        if !other.added.0.is_empty() {
            let names: Vec<&str> = other.added.0.iter().map(|f| f.name()).collect();
            self.check_one("worlds").fail(
                None,
                format!(
                    "the world added has forces added with add_force ({names:?}), which cannot \
                     be replicated: add them to the combined builder, over all particles"
                ),
            );
        }
        first
    }

    /// `n` copies of this scene as `n` worlds ([`ModelBuilder::add_world`] `n` times).
    ///
    /// # Panics
    /// If `n` is 0.
    pub fn replicate(&self, n: usize) -> ModelBuilder<R> {
        assert!(n > 0, "ModelBuilder::replicate(0): a model needs a world");
        let mut b = ModelBuilder::new();
        for _ in 0..n {
            b.add_world(self);
        }
        b
    }

    /// A builder with only the worlds in `worlds` (their particles, elements, bodies,
    /// constraints and gravity; the same shared environment: ground, drag, shapes, contact
    /// laws): one process's or thread's share of a scene whose worlds are spread over several
    /// (`adflex-distributed`). World `worlds.start` of this builder is world 0 of the new one;
    /// each world's results are the same bits in either (worlds never interact).
    ///
    /// Forces added with [`ModelBuilder::add_force`] act over all particles and cannot be
    /// split: a share of a builder that has some records a problem (add them to each share),
    /// and so does one of a builder whose elements span worlds. Surface triangles (output
    /// only) that span worlds are left out, and problems the builder had already recorded are
    /// kept as they were (their indices are the whole builder's).
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::Vec3;
    ///
    /// let mut net = ModelBuilder::<f64>::new();
    /// let pin = net.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let bob = net.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// net.add_spring(pin, bob, 1e3, 0.0);
    /// let all = net.replicate(10);
    /// let share = all.worlds_in(4..7).finalize();
    /// assert_eq!(share.worlds.len(), 3);
    /// assert_eq!(share.springs().unwrap().pairs.to_vec(), vec![[0, 1], [2, 3], [4, 5]]);
    /// ```
    ///
    /// # Panics
    /// If the range is empty or past the last world.
    pub fn worlds_in(&self, worlds: std::ops::Range<usize>) -> ModelBuilder<R> {
        let n = self.worlds.len();
        assert!(
            !worlds.is_empty() && worlds.end <= n,
            "ModelBuilder::worlds_in({worlds:?}): the builder has {n} worlds"
        );
        let start = |k: usize| match self.worlds.get(k) {
            Some(&(p, b, _)) => (p as u32, b as u32),
            None => (self.particles.len() as u32, self.bodies.len() as u32),
        };
        let ((p0, b0), (p1, b1)) = (start(worlds.start), start(worlds.end));
        let particles = p0..p1;
        let mut share = ModelBuilder {
            gravity: self.gravity,
            particle_radius: self.particle_radius,
            particles: self.particles.worlds_in(&particles),
            forces: self.forces.worlds_in(&particles),
            bodies: self.bodies.worlds_in(&(b0..b1)),
            constraints: self.constraints.worlds_in(&particles),
            added: AddedForces::default(),
            problems: self.problems.clone(),
            worlds: self.worlds[worlds]
                .iter()
                .map(|&(p, b, g)| (p - p0 as usize, b - b0 as usize, g))
                .collect(),
            world_added: true,
        };
        if !self.added.0.is_empty() {
            let names: Vec<&str> = self.added.0.iter().map(|f| f.name()).collect();
            share.check_one("worlds").fail(
                None,
                format!(
                    "worlds_in: the builder has forces added with add_force ({names:?}), which \
                     act over all particles and cannot be split by world: add them to the share"
                ),
            );
        }
        if let Some((force, k, p, worlds)) = self.spanning_element() {
            share.check_one("worlds").fail(
                None,
                format!(
                    "worlds_in: `{force}` element {k} joins particles {p:?} of worlds \
                     {worlds:?}, so the worlds cannot be split"
                ),
            );
        }
        share
    }

    /// The first element (of a library force or a constraint) whose particles are in
    /// different worlds: its force's name, its index, its particles and their worlds.
    fn spanning_element(&self) -> Option<(&'static str, usize, Vec<u32>, Vec<u32>)> {
        if self.worlds.len() < 2 {
            return None;
        }
        let n = self.particles.len();
        let mut world_of = vec![0u32; n];
        for (k, &(p0, ..)) in self.worlds.iter().enumerate() {
            let p1 = self.worlds.get(k + 1).map_or(n, |w| w.0);
            world_of[p0..p1].fill(k as u32);
        }
        let (force, k, p) = self.forces.spanning_worlds(&world_of).or_else(|| {
            self.constraints
                .spanning_worlds(&world_of)
                .map(|(k, p)| ("distance_constraints", k, p))
        })?;
        let worlds = p.iter().map(|&i| world_of[i as usize]).collect();
        Some((force, k, p, worlds))
    }

    /// Number of worlds (1 unless [`ModelBuilder::add_world`] added more).
    pub fn world_count(&self) -> usize {
        self.worlds.len()
    }

    /// The library forces' parts, and what their elements are checked against.
    pub(crate) fn parts(&mut self) -> (&mut ForceParts<R>, Elements<'_, R>) {
        let el = Elements {
            particles: &self.particles,
            problems: &mut self.problems,
        };
        (&mut self.forces, el)
    }

    /// The checks of the single item `kind`.
    pub(crate) fn check_one(&mut self, kind: &'static str) -> Check<'_> {
        Check {
            out: &mut self.problems,
            kind,
            index: None,
        }
    }

    /// Number of particles added so far.
    pub fn particle_count(&self) -> usize {
        self.particles.len()
    }

    /// Position (m) of particle `i`. Panics if there is no particle `i`.
    pub fn particle_position(&self, i: u32) -> Vec3<R> {
        self.particles.x[i as usize]
    }

    /// The problems recorded so far by the builder methods, in call order (see
    /// [`crate::validation`]).
    pub fn problems(&self) -> &[Problem] {
        &self.problems
    }

    /// Adds a particle at `x` (m) with velocity `v` (m/s) and mass `mass` (kg, finite and
    /// `>= 0`; 0 = pinned: inverse mass 0, so no force and no gravity moves it). Returns its
    /// index. `x`, `v` and the inverse mass `1 / mass` must be finite in `R` (a mass below
    /// `1 / R::MAX`, e.g. 1e-320 kg, is a problem, not a pinned particle).
    pub fn add_particle(&mut self, x: Vec3<R>, v: Vec3<R>, mass: R) -> u32 {
        self.particles.add(&mut self.problems, x, v, mass)
    }

    /// Adds a particle with inverse mass `inv_mass` (1/kg, finite and `>= 0`; 0 = pinned).
    /// Returns its index.
    pub fn add_particle_inv_mass(&mut self, x: Vec3<R>, v: Vec3<R>, inv_mass: R) -> u32 {
        self.particles
            .push(&mut self.problems, x, v, inv_mass, true)
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
        self.particles.set_radius(&mut self.problems, i, radius)
    }

    /// The contact radius (m) of particle `i`: its own, or [`ModelBuilder::particle_radius`].
    /// Panics if there is no particle `i`.
    pub fn particle_radius_of(&self, i: u32) -> R {
        self.particles.radius_of(i, self.particle_radius)
    }

    /// Sets the inverse mass (1/kg, finite and `>= 0`) of particle `i` (0 pins it).
    pub fn set_particle_inv_mass(&mut self, i: u32, inv_mass: R) {
        self.particles.set_inv_mass(&mut self.problems, i, inv_mass)
    }

    /// Adds a spring between distinct particles `i` and `j` with rest length their current
    /// distance (computed in `R`; it must be finite and `> 0`), stiffness `ke` (N/m) and
    /// damping `kd` (N s/m), both finite and `>= 0`. Returns its index.
    pub fn add_spring(&mut self, i: u32, j: u32, ke: R, kd: R) -> u32 {
        let (f, mut el) = self.parts();
        f.springs.add(&mut el, i, j, ke, kd)
    }

    /// Adds a spring with an explicit rest length (m, finite and `> 0`). Returns its index.
    pub fn add_spring_with_rest(&mut self, i: u32, j: u32, rest: R, ke: R, kd: R) -> u32 {
        let (f, mut el) = self.parts();
        f.springs.add_with_rest(&mut el, i, j, rest, ke, kd)
    }

    /// Number of springs added so far.
    pub fn spring_count(&self) -> usize {
        self.forces.springs.len()
    }

    /// Adds a triangle to the surface topology (used by [`ModelBuilder::add_bending_edges`]);
    /// it exerts no force of its own (see [`ModelBuilder::add_triangle_fem`]).
    /// Its vertices must be distinct particles.
    pub fn add_triangle(&mut self, i: u32, j: u32, k: u32) -> u32 {
        self.particles.add_triangle(&mut self.problems, [i, j, k])
    }

    /// The surface triangles added so far.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.particles.triangles
    }

    /// Adds a StVK membrane triangle (also to the surface topology), rest shape from the current
    /// positions; `mu` (N/m, `>= 0`), `lambda` (N/m, finite), `kd` (N s/m, `>= 0`). The
    /// triangle must not be degenerate: quality (see
    /// [`crate::forces::fem_tri::triangle_quality`]) at least
    /// [`crate::validation::min_quality`], `Dm^-1` finite and area above `R::tiny()` in `R`;
    /// otherwise a problem of `triangle_fem[k]` is recorded.
    pub fn add_triangle_fem(&mut self, i: u32, j: u32, k: u32, mu: R, lambda: R, kd: R) -> u32 {
        let part = &mut self.forces.triangle_fem;
        let (particles, problems) = (&mut self.particles, &mut self.problems);
        crate::forces::fem_tri::add_membrane(part, particles, problems, [i, j, k], [mu, lambda, kd])
    }

    /// Adds a bending element `(o1, o2, e0, e1)` (opposite vertices, then the shared edge) with
    /// rest angle `rest` (rad, finite), stiffness `ke` (N m/rad) and damping `kd` (N m s/rad),
    /// both finite and `>= 0`; the four particles must be distinct.
    pub fn add_bending(&mut self, quad: [u32; 4], rest: R, ke: R, kd: R) -> u32 {
        let (f, mut el) = self.parts();
        f.bending.add(&mut el, quad, rest, ke, kd)
    }

    /// Adds a bending element on every edge shared by two of the triangles added so far, in
    /// dFlex/Warp order (see [`bending_edges`](crate::forces::bending::bending_edges)); returns how
    /// many. A triangle added more than once (in any order of its particles, e.g. a cloth
    /// grid's triangles given again to [`ModelBuilder::add_triangle_fem`]) counts once. Call it
    /// once, after the triangles.
    pub fn add_bending_edges(&mut self, ke: R, kd: R, rest: RestAngle) -> usize {
        let (f, mut el) = self.parts();
        let triangles = el.particles.triangles.clone();
        f.bending.add_edges(&mut el, &triangles, ke, kd, rest)
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
        let (f, mut el) = self.parts();
        f.tets.add(&mut el, [i, j, k, l], mu, lambda, kd)
    }

    /// Number of tetrahedra added so far.
    pub fn tet_count(&self) -> usize {
        self.forces.tets.len()
    }

    /// Sets the ground plane for particle and body contact (unit normal; `ke`, `kd`, `mu`,
    /// `leak` finite and `>= 0`).
    pub fn set_ground(&mut self, ground: Ground<R>) {
        crate::contact::ground::set(&mut self.forces.ground, &mut self.problems, ground)
    }

    /// Sets linear drag / wind on every particle (`kd` finite and `>= 0`, `wind` finite).
    pub fn set_drag(&mut self, drag: Drag<R>) {
        crate::forces::particle::set(&mut self.forces.drag, &mut self.problems, drag)
    }

    /// Enables particle-particle contact (every parameter finite and `>= 0`).
    pub fn set_particle_contact(&mut self, contact: ParticleContact<R>) {
        let part = &mut self.forces.particle_contact;
        crate::contact::particle::set(part, &mut self.problems, contact)
    }

    /// Adds a static analytic shape that particles collide with (finite position, unit
    /// orientation, sizes `> 0`). Returns its index.
    pub fn add_shape(&mut self, shape: Shape<R>) -> u32 {
        let (f, mut el) = self.parts();
        f.shape_contact.add(&mut el, shape)
    }

    /// Sets the contact parameters of particles against shapes (`margin` is unused; every
    /// parameter finite and `>= 0`).
    pub fn set_shape_contact(&mut self, contact: ParticleContact<R>) {
        let (f, mut el) = self.parts();
        f.shape_contact.set_contact(&mut el, contact)
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
        let body = BodyRecord {
            x,
            q,
            v,
            w,
            mass,
            inertia,
        };
        self.bodies.add(&mut self.problems, body)
    }

    /// Adds a contact point `p` (m, body frame) to body `body`, which then touches the ground.
    /// `body` must exist and `p` be finite.
    pub fn add_body_contact_point(&mut self, body: u32, p: Vec3<R>) {
        self.bodies.add_contact_point(&mut self.problems, body, p)
    }

    /// Adds an XPBD distance constraint between particles `i` and `j`, rest distance their
    /// current distance (finite and `> 0`), compliance `compliance` (m/N, finite and `>= 0`;
    /// 0 = rigid). Returns its index.
    pub fn add_distance_constraint(&mut self, i: u32, j: u32, compliance: R) -> u32 {
        let mut el = Elements {
            particles: &self.particles,
            problems: &mut self.problems,
        };
        self.constraints.add(&mut el, i, j, compliance)
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
        self.added.0.push(force);
        self.added.0.len() - 1
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
        for (k, g) in self.worlds.iter().enumerate() {
            if let Some(g) = &g.2 {
                Check {
                    out: &mut problems,
                    kind: "gravity",
                    index: Some(k),
                }
                .finite3("gravity", g);
            }
        }
        Check {
            out: &mut problems,
            kind: "particle_radius",
            index: None,
        }
        .nonneg("particle_radius", self.particle_radius);
        for p in &mut problems[self.problems.len()..] {
            p.param = None; // `gravity.gravity` reads as `gravity`
        }
        if let Some((force, k, p, worlds)) = self.spanning_element() {
            Check {
                out: &mut problems,
                kind: force,
                index: Some(k),
            }
            .fail(
                None,
                format!(
                    "joins particles {p:?} of worlds {worlds:?}: worlds must not share \
                     elements (add each world's elements to its own builder before \
                     add_world)"
                ),
            );
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
        let particles = self.particles.build(self.particle_radius);
        // The library's forces, in the order of `forces::BUILTIN_FORCES`, then the added ones.
        let forces = self
            .forces
            .build()
            .into_iter()
            .chain(self.added.0.iter().cloned())
            .collect();
        let n = self.particles.len();
        let nb = self.bodies.len();
        let worlds: Vec<WorldRanges> = self
            .worlds
            .iter()
            .enumerate()
            .map(|(k, &(p0, b0, _))| {
                let (p1, b1) = self.worlds.get(k + 1).map_or((n, nb), |w| (w.0, w.1));
                WorldRanges {
                    particles: p0..p1,
                    bodies: b0..b1,
                }
            })
            .collect();
        let (mut particle_world, mut body_world) = (vec![0u32; n], vec![0u32; nb]);
        for (k, w) in worlds.iter().enumerate() {
            particle_world[w.particles.clone()].fill(k as u32);
            body_world[w.bodies.clone()].fill(k as u32);
        }
        let gravity = self.worlds.iter().map(|w| w.2.unwrap_or(self.gravity));
        Model {
            worlds,
            particle_world: Array::from_vec(particle_world).named("particle_world"),
            body_world: Array::from_vec(body_world).named("body_world"),
            gravity: Array::from_vec(gravity.collect()).named("gravity"),
            particle_count: self.particles.len(),
            particle_x: particles.x,
            particle_v: particles.v,
            particle_inv_mass: particles.inv_mass,
            particle_radius: self.particle_radius,
            particle_radii: particles.radii,
            triangles: self.particles.triangles.clone(),
            forces,
            bodies: self.bodies.build(),
            distance_constraints: self.constraints.build(),
        }
    }
}

/// Where a world's particles and bodies are in a [`Model`]'s arrays.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WorldRanges {
    /// Its particles.
    pub particles: std::ops::Range<usize>,
    /// Its rigid bodies.
    pub bodies: std::ops::Range<usize>,
}

/// A simulation model: constant arrays of the scene's components (only those it has) and the
/// kernels that evaluate them.
#[derive(Clone, Debug)]
pub struct Model<R: Real> {
    /// The worlds ([`ModelBuilder::add_world`]; one unless it added more).
    pub worlds: Vec<WorldRanges>,
    /// Per particle: its world (for per-world losses, and its gravity).
    pub particle_world: Array<u32>,
    /// Per rigid body: its world.
    pub body_world: Array<u32>,
    /// Number of particles.
    pub particle_count: usize,
    /// Initial particle positions (m); [`Model::state`] copies them.
    pub particle_x: Array<Vec3<R>>,
    /// Initial particle velocities (m/s).
    pub particle_v: Array<Vec3<R>>,
    /// Inverse masses (1/kg; 0 = pinned).
    pub particle_inv_mass: Array<R>,
    /// Gravity (m/s^2), one per world ([`ModelBuilder::gravity`], or the one of the builder
    /// each world was added from). It can require gradients, like any parameter array.
    pub gravity: Array<Vec3<R>>,
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

/// 1 for each world listed in `worlds`, 0 for the others (of `n`): which worlds a
/// `select_worlds` takes. A world out of range is an [`Error::InvalidInput`] naming it.
pub(crate) fn world_mask(worlds: &[usize], n: usize) -> Result<Array<u32>, Error> {
    let mut take = vec![0u32; n];
    for &w in worlds {
        if w >= n {
            return Err(Error::InvalidInput {
                what: format!("select_worlds: world {w}"),
                message: format!("the model has {n} worlds"),
            });
        }
        take[w] = 1;
    }
    Ok(Array::from_vec(take))
}

/// `out[tid]` is `from[tid]` in the worlds `take` marks (indexed by `world[tid]`), `keep[tid]`
/// elsewhere: resetting some worlds of a state.
#[adflex_macros::diff_kernel]
pub fn select_worlds_vec3<R: Real>(
    world: &Array<u32>,
    take: &Array<u32>,
    keep: &Array<Vec3<R>>,
    from: &Array<Vec3<R>>,
    out: &Array<Vec3<R>>,
) {
    let t = tid();
    if take[world[t] as usize] != 0 {
        out[t] = from[t];
    } else {
        out[t] = keep[t];
    }
}

/// [`select_worlds_vec3`] for orientations.
#[adflex_macros::diff_kernel]
pub fn select_worlds_quat<R: Real>(
    world: &Array<u32>,
    take: &Array<u32>,
    keep: &Array<Quat<R>>,
    from: &Array<Quat<R>>,
    out: &Array<Quat<R>>,
) {
    let t = tid();
    if take[world[t] as usize] != 0 {
        out[t] = from[t];
    } else {
        out[t] = keep[t];
    }
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

    /// A state whose worlds listed in `worlds` are `from`'s and the others `state`'s (the
    /// particles' positions and velocities, the rigid bodies' positions, orientations and
    /// velocities), recorded on the tape; with `from = &model.state()` it resets them.
    ///
    /// Errors ([`Error::InvalidInput`]): a world out of range, or states of the wrong size.
    pub fn select_worlds(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        worlds: &[usize],
        from: &State<R>,
    ) -> Result<State<R>, Error> {
        let invalid = |what: String, message: String| Error::InvalidInput { what, message };
        let take = world_mask(worlds, self.worlds.len())?;
        for (s, what) in [(state, "state"), (from, "from")] {
            if s.x.len() != self.particle_count || s.v.len() != self.particle_count {
                return Err(invalid(
                    format!("select_worlds: {what}"),
                    format!(
                        "has {} positions and {} velocities, the model {} particles",
                        s.x.len(),
                        s.v.len(),
                        self.particle_count
                    ),
                ));
            }
            let bodies = self.bodies.as_ref().map_or(0, |b| b.len());
            let sizes = s
                .bodies
                .as_ref()
                .map_or([0; 4], |b| [b.x.len(), b.q.len(), b.v.len(), b.w.len()]);
            if sizes != [bodies; 4] {
                return Err(invalid(
                    format!("select_worlds: {what}.bodies"),
                    format!("does not have the model's {bodies} rigid bodies"),
                ));
            }
        }
        let bodies = match (&state.bodies, &from.bodies) {
            (Some(keep), Some(take_from)) => {
                Some(self.select_body_worlds(tape, &take, keep, take_from))
            }
            _ => None,
        };
        let next = State {
            x: Array::zeros(self.particle_count).named("x"),
            v: Array::zeros(self.particle_count).named("v"),
            bodies,
        };
        let n = self.particle_count;
        tape.launch(
            select_worlds_vec3,
            n,
            (&self.particle_world, &take, &state.x, &from.x, &next.x),
        );
        tape.launch(
            select_worlds_vec3,
            n,
            (&self.particle_world, &take, &state.v, &from.v, &next.v),
        );
        Ok(next)
    }

    /// The bodies' part of [`Model::select_worlds`].
    fn select_body_worlds(
        &self,
        tape: &mut Tape,
        take: &Array<u32>,
        keep: &BodyState<R>,
        from: &BodyState<R>,
    ) -> BodyState<R> {
        let n = keep.x.len();
        let world = &self.body_world;
        let next = BodyState {
            x: Array::zeros(n).named("body_x"),
            q: Array::zeros(n).named("body_q"),
            v: Array::zeros(n).named("body_v"),
            w: Array::zeros(n).named("body_w"),
        };
        for (a, b, out) in [
            (&keep.x, &from.x, &next.x),
            (&keep.v, &from.v, &next.v),
            (&keep.w, &from.w, &next.w),
        ] {
            tape.launch(select_worlds_vec3, n, (world, take, a, b, out));
        }
        tape.launch(
            select_worlds_quat,
            n,
            (world, take, &keep.q, &from.q, &next.q),
        );
        next
    }

    /// `state` with the worlds listed in `worlds` back at [`Model::state`] (see
    /// [`Model::select_worlds`]).
    pub fn reset_worlds(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        worlds: &[usize],
    ) -> Result<State<R>, Error> {
        self.select_worlds(tape, state, worlds, &self.state())
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

    /// [`Model::gravity`], checked to have one entry per world.
    ///
    /// # Panics
    /// If it has not (an array set by hand of the wrong length), naming it.
    pub(crate) fn gravity_per_world(&self) -> &Array<Vec3<R>> {
        let (n, w) = (self.gravity.len(), self.worlds.len());
        assert!(
            n == w,
            "model: `gravity` (one per world) has {n} elements, the model has {w} worlds"
        );
        &self.gravity
    }

    /// Accelerations (m/s^2) of the particles: `f w + g [w > 0]` with `f` from
    /// [`Model::eval_forces`] (`w` the inverse mass, `g` its world's gravity), in a new array.
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
            (
                &f,
                &self.particle_inv_mass,
                self.gravity_per_world(),
                &self.particle_world,
                &a,
            ),
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
            particle_world: (self.worlds.len() > 1).then_some(&self.particle_world),
            particle_world_ids: &self.particle_world,
        }
    }

    /// Records the elastic potential energy of the forces that have one ([`Force::energy`]:
    /// springs, membranes, tetrahedra, bending, the contact penalties, and any added force
    /// with a potential) (J) and returns it with one entry per world (one for a model of one
    /// world), for tests and energy-based integrators.
    pub fn elastic_energy(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
    ) -> Array<R> {
        let e = Array::zeros(self.worlds.len().max(1)).named("energy");
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
