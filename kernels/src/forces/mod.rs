//! Forces on particles, as components: every force is one type implementing [`Force`], in its
//! own file, and a [`Model`](crate::Model) holds a list of them
//! ([`Model::forces`](crate::Model::forces)). The model's force evaluation, its elastic
//! energy, the private parameter copies of
//! [`ImplicitEuler`](crate::integrators::ImplicitEuler) (and so its implicit-function-theorem
//! gradient) and gradient checks all iterate that list and each force's parameter visitor
//! ([`Force::params_mut`]): a force written outside this crate and added with
//! [`ModelBuilder::add_force`](crate::ModelBuilder::add_force) works with every integrator.
//!
//! The library's forces: springs, dihedral bending, triangle membranes (StVK), stable
//! Neo-Hookean tetrahedra, drag / wind ([`particle`]), and the contact forces of
//! [`crate::contact`] (ground, particle-particle, analytic shapes). [`BUILTIN_FORCES`] lists
//! their names.
//!
//! Each component is a struct holding its arrays; its `eval` records its kernel on a tape and
//! accumulates into a force array (`atomic_add`), and its `energy` (where the force derives
//! from a potential) adds its energy (tests check `force = -dE/dx` through them).
//!
//! # Adding a force
//!
//! ```
//! use adflex_kernels::forces::{Force, ForceContext, Param};
//! use adflex_kernels::prelude::*;
//! use adflex_macros::diff_kernel;
//! use adflex_runtime::prelude::*;
//!
//! /// A constant force `f0[i]` on each particle (N).
//! #[diff_kernel]
//! fn push<R: Real>(f0: &Array<Vec3<R>>, f: &Array<Vec3<R>>) {
//!     let i = tid();
//!     f.atomic_add(i, f0[i]);
//! }
//!
//! #[derive(Clone, Debug)]
//! struct Push<R: Real> {
//!     f0: Array<Vec3<R>>,
//! }
//!
//! impl<R: Real> Force<R> for Push<R> {
//!     fn name(&self) -> &'static str {
//!         "push"
//!     }
//!     fn eval(&self, _cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
//!         tape.launch(push, self.f0.len(), (&self.f0, f));
//!     }
//!     fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
//!         visit("f0", &mut self.f0);
//!     }
//! }
//!
//! let mut b = ModelBuilder::<f64>::new();
//! b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
//! b.gravity = Vec3::zeros();
//! b.add_force(Push { f0: Array::from_vec(vec![Vec3::new(2.0, 0.0, 0.0)]) });
//! let model = b.finalize();
//! let mut tape = Tape::new();
//! let s = SemiImplicitEuler.step(&model, &mut tape, &model.state(), None, 0.5).unwrap();
//! assert_eq!(s.v.get(0).x, 1.0);
//! let (force, param, _) = &model.params()[0];
//! assert_eq!((*force, *param), ("push", "f0"));
//! assert_eq!(model.requires_grad("push", "f0").unwrap(), 1);
//! ```

use adflex_runtime::Real;

use crate::contact::{ground, particle as contact, shapes};

pub mod bending;
pub mod component;
pub mod fem_tet;
pub mod fem_tri;
pub mod particle;
pub mod spring;

pub(crate) use component::ForcePart;
pub use component::{real_parts, Force, ForceClone, ForceContext, Param, ParamCopy, ParamDoc};

/// The library's forces, listed once: each line gives the builder's field for the force's
/// part, the part's type, the name constant, and the module whose `NAME` ([`Force::name`])
/// and `PARAMS` (its rows of the guide's parameter table) it takes. The list
/// makes [`BUILTIN_FORCES`], [`LIBRARY_PARAMS`], the name constants and the builder's parts, and its order is the
/// order in which a model evaluates the forces (which fixes the bits of the total force).
macro_rules! library_forces {
    ($($(#[$doc:meta])* $field:ident: $part:ty, $NAME:ident = $module:ident;)*) => {
        /// The names ([`Force::name`]) of every force type the library has, in the order
        /// [`ModelBuilder::finalize`](crate::ModelBuilder::finalize) adds them to a model.
        /// Each library force's `name` returns its entry here (tests check that a scene with
        /// every force lists exactly these).
        pub const BUILTIN_FORCES: &[&str] = &[$($NAME),*];

        $($(#[$doc])* pub const $NAME: &str = $module::NAME;)*

        /// Every library force's parameters (its `PARAMS`, the guide's table), in the order
        /// of [`BUILTIN_FORCES`].
        pub const LIBRARY_PARAMS: &[(&str, &[ParamDoc])] = &[$(($module::NAME, $module::PARAMS)),*];

        /// The library forces' parts of a scene description, in the order of
        /// [`BUILTIN_FORCES`].
        #[derive(Clone, Debug)]
        pub(crate) struct ForceParts<R: Real> {
            $(pub(crate) $field: $part,)*
        }

        impl<R: Real> Default for ForceParts<R> {
            fn default() -> Self {
                ForceParts { $($field: Default::default(),)* }
            }
        }

        impl<R: Real> ForceParts<R> {
            /// The forces the scene has, in the order of [`BUILTIN_FORCES`].
            pub(crate) fn build(&self) -> Vec<Box<dyn Force<R>>> {
                let mut forces = Vec::new();
                $(forces.extend(ForcePart::<R>::build(&self.$field));)*
                forces
            }

            /// The first element of a library force whose particles are in different
            /// worlds: the force's name, the element and its particles.
            pub(crate) fn spanning_worlds(&self, world_of: &[u32]) -> Option<(&'static str, usize, Vec<u32>)> {
                $(if let Some((k, p)) = ForcePart::<R>::spanning_worlds(&self.$field, world_of) {
                    return Some(($NAME, k, p));
                })*
                None
            }

            /// The forces' parts of the worlds whose particles are `particles` (see
            /// [`ForcePart::worlds_in`]).
            pub(crate) fn worlds_in(&self, particles: &std::ops::Range<u32>) -> Self {
                ForceParts { $($field: ForcePart::<R>::worlds_in(&self.$field, particles),)* }
            }

            /// Appends `other`'s forces as a new world's (see [`ForcePart::append`]); the
            /// first force that cannot be, by name, with why.
            pub(crate) fn append(&mut self, other: &Self, offset: u32) -> Result<(), (&'static str, String)> {
                $(ForcePart::<R>::append(&mut self.$field, &other.$field, offset)
                    .map_err(|e| ($NAME, e))?;)*
                Ok(())
            }
        }
    };
}

library_forces! {
    /// [`spring::Springs`].
    springs: spring::SpringParts<R>, SPRINGS = spring;
    /// [`bending::Bending`].
    bending: bending::BendingParts<R>, BENDING = bending;
    /// [`fem_tri::TriangleFem`].
    triangle_fem: fem_tri::TriangleParts<R>, TRIANGLE_FEM = fem_tri;
    /// [`fem_tet::TetFem`].
    tets: fem_tet::TetParts<R>, TETS = fem_tet;
    /// [`crate::contact::ground::Ground`].
    ground: Option<ground::Ground<R>>, GROUND = ground;
    /// [`crate::contact::particle::ParticleContact`].
    particle_contact: Option<contact::ParticleContact<R>>, PARTICLE_CONTACT = contact;
    /// [`crate::contact::shapes::Shapes`].
    shape_contact: shapes::ShapeParts<R>, SHAPE_CONTACT = shapes;
    /// [`particle::Drag`].
    drag: Option<particle::Drag<R>>, DRAG = particle;
}
