//! Internal forces on particles: springs, dihedral bending, triangle membranes (StVK), stable
//! Neo-Hookean tetrahedra, and per-particle forces (drag, wind, external forces, gravity).
//!
//! Each component is a struct holding its arrays, with an `eval` method that records its
//! kernel on a tape and accumulates into a force array (`atomic_add`), and `energy` kernels
//! where the force derives from a potential (tests check `force = -dE/dx` through them).

pub mod bending;
pub mod fem_tet;
pub mod fem_tri;
pub mod particle;
pub mod spring;
