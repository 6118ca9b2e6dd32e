//! Physics kernels of adflex, written with `#[diff_kernel]`: forces (springs, dihedral bending,
//! triangle and tetrahedral FEM, drag and wind), contact (ground, particle-particle, analytic
//! shapes), rigid bodies, XPBD constraints, integrators, losses, and the model builder.
//!
//! A [`ModelBuilder`] describes a scene; [`ModelBuilder::finalize`] turns it into a [`Model`]
//! that holds arrays only for what the scene contains, and whose [`Model::eval_forces`]
//! launches only the kernels the scene needs. An [`Integrator`] steps a [`State`] on a
//! [`Tape`](adflex_runtime::Tape), writing new state arrays every step, so the whole rollout
//! can be differentiated with `tape.backward`.
//!
//! Units are SI throughout: metres, seconds, kilograms, newtons. Every kernel is generic over
//! the scalar `R: Real`, so a scene runs in `f32` for speed and in `f64` for gradient checks.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_runtime::{Tape, Vec3};
//!
//! // Two particles joined by a spring, one pinned, falling onto the ground.
//! let mut b = ModelBuilder::<f64>::new();
//! let a = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
//! let c = b.add_particle(Vec3::new(0.5, 1.0, 0.0), Vec3::zeros(), 1.0);
//! b.add_spring(a, c, 100.0, 0.1);
//! b.set_ground(Ground::default());
//! let model = b.finalize();
//! let mut tape = Tape::new();
//! let mut state = model.state();
//! for _ in 0..10 {
//!     state = SemiImplicitEuler.step(&model, &mut tape, &state, None, 1e-3).unwrap();
//! }
//! assert!(state.x.get(1).y < 1.0);
//! ```

// `!(residual <= tolerance)` is how a NaN residual counts as a failure, on purpose.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
#![warn(missing_docs)]

pub mod articulation;
pub mod constraints;
pub mod contact;
pub mod coupling;
pub mod family;
pub mod fluid;
pub mod forces;
pub mod integrators;
pub mod losses;
pub mod model;
pub mod mpm;
mod particles;
mod precompiled;
pub mod rigid;
pub mod scene_file;
pub mod scenes;
pub mod solver;
pub mod state;
pub mod statics;
pub mod tied;
pub mod validation;

pub use integrators::{Integrator, SemiImplicitEuler};
pub use model::{Model, ModelBuilder, WorldRanges};
pub use state::{BodyState, Control, State};
pub use validation::{ModelError, Problem};

/// The builder, model, state, integrators and component types in one import.
pub mod prelude {
    pub use crate::contact::ground::Ground;
    pub use crate::contact::particle::ParticleContact;
    pub use crate::contact::shapes::{Shape, ShapeKind};
    pub use crate::forces::bending::RestAngle;
    pub use crate::forces::particle::Drag;
    pub use crate::integrators::{
        ExplicitEuler, ImplicitEuler, Integrator, Midpoint, Rk4, SemiImplicitEuler, SolverPolicy,
        Xpbd,
    };
    pub use crate::model::{Model, ModelBuilder};
    pub use crate::scenes::cloth::{ClothEdge, ClothGrid};
    pub use crate::scenes::soft::{TetBlock, TetGrid};
    pub use crate::state::{BodyState, Control, State};
}
