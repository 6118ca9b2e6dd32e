//! Articulated bodies in reduced coordinates: trees of links joined by revolute, prismatic,
//! ball, fixed and free joints, with the dynamics of Featherstone's algorithms written as
//! kernels (forward kinematics, RNEA, CRBA) and a Cholesky solve with its own adjoint and
//! tangent, so that whole rollouts differentiate on a [`Tape`](adflex_runtime::Tape).
//!
//! - [`ArticulationBuilder`] describes links, joints and mass properties;
//!   [`urdf`] and [`mjcf`] read robot files into one.
//! - [`Articulations`] is the model; [`ArticulationState`] holds `q` and `qd`;
//!   [`ArticulationControl`] the joint torques, PD targets, actuator controls
//!   ([`actuator`]) and muscle activations.
//! - [`Articulations::mass_matrix`], [`Articulations::bias_forces`],
//!   [`Articulations::inverse_dynamics`], [`Articulations::forward_dynamics`] and
//!   [`Articulations::step`] record their launches on a tape;
//!   [`Articulations::forward_dynamics_derivatives`] gives `d qdd / d (q, qd, tau)` and
//!   [`Articulations::inverse_dynamics_derivatives`] `d tau / d (q, qd, qdd)`, in closed form.
//!
//! **Conventions** (Pinocchio's): quaternions are stored `x, y, z, w`; a ball joint's
//! velocity is the angular velocity in the child link's frame; a free joint's coordinates are
//! the position in the parent frame and the quaternion, its velocities the linear velocity of
//! the link origin and the angular velocity, both in the link frame. Derivatives with respect
//! to `q` are taken in the tangent space: along `v`, `q` moves by
//! [`Articulations::tangent_to_coords`] (quaternions by `r (v/2, 0)`).
//!
//! ```
//! use adflex_kernels::articulation::*;
//! use adflex_runtime::{Tape, Vec3};
//!
//! // A cart on a rail with a pole hinged on it.
//! let mut b = ArticulationBuilder::new();
//! let cart = b.add_link("cart", None, Joint::prismatic(Vec3::x()),
//!     Inertial::cuboid(1.0, Vec3::new(0.2, 0.1, 0.1), Vec3::zeros()));
//! b.add_link("pole", Some(cart), Joint::revolute(Vec3::y()),
//!     Inertial::point(0.1, Vec3::new(0.0, 0.0, 0.5)));
//! let model = b.finalize::<f64>().unwrap();
//!
//! let mut tape = Tape::new();
//! let mut state = model.state();
//! state.q.set(1, 0.1); // tilt the pole
//! for _ in 0..100 {
//!     state = model.step(&mut tape, &state, None, 1e-3).unwrap();
//! }
//! assert!(state.q.get(1) > 0.1); // it falls
//! ```

pub mod actuator;
mod build;
pub mod contact;
mod derivatives;
mod dynamics;
pub mod fluid;
pub mod kernels;
pub mod mjcf;
mod model;
pub mod muscle;
mod pose;
pub mod urdf;
mod xml;

pub use actuator::{Actuator, TendonSpring};
pub use contact::{ContactFilter, ContactShape, GroundContact, LinkShapes};
pub use derivatives::{QddDerivatives, TauDerivatives};
pub use dynamics::{ArticulationControl, ArticulationState, Kinematics};
pub use fluid::Fluid;
pub use model::{
    ArticulationBuilder, ArticulationError, ArticulationInfo, ArticulationIntegrator,
    Articulations, Inertial, Joint, JointType, LinkDesc, LinkId, LinkInfo, Muscle, Pose, WorldInfo,
};
