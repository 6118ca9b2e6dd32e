//! The solvers shared by the implicit methods: matrix-free Krylov solves ([`krylov`]) and
//! Newton's method on a nonlinear system whose Jacobian products are passes of the force
//! model's tangent and adjoint kernels, with its implicit-function-theorem adjoint
//! (`newton`, used by [`ImplicitEuler`](crate::integrators::ImplicitEuler) and
//! [`Equilibrium`](crate::statics::Equilibrium)). A new implicit method (a pressure solve, an
//! articulation's constraints) implements the crate's `NewtonSystem` for its unknowns and
//! gets the iteration, the line search, the failure handling and the adjoint solve.

pub mod krylov;
pub(crate) mod newton;
pub(crate) mod parts;

pub use newton::NewtonStats;
