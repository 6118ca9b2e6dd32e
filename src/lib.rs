//! # adflex
//!
//! Differentiable physics simulation in Rust: `#[diff_kernel]` and `#[diff_func]` turn plain
//! Rust functions into forward, adjoint (reverse-mode) and tangent (forward-mode) kernels; a
//! runtime launches them over a thread pool and records them on a tape; a physics library
//! written with the same macro provides particles, springs, cloth, FEM, contact and rigid bodies.
//!
//! Start with `docs/guide.md`.

// Generated code names this crate `::adflex`, also from inside it.
extern crate self as adflex;

pub use adflex_kernels as kernels;
pub use adflex_macros::{diff_func, diff_kernel};
pub use adflex_optim as optim;
pub use adflex_runtime as runtime;
pub use adflex_runtime::math;
pub use adflex_viz as viz;

/// `use adflex::prelude::*;` brings the macros, the types, the math builtins, arrays, launches,
/// the tape, and the physics library's builder, model, state and integrators.
pub mod prelude {
    pub use adflex_kernels::prelude::*;
    pub use adflex_macros::{diff_func, diff_kernel};
    pub use adflex_runtime::prelude::*;
}

#[doc = include_str!("../docs/guide.md")]
#[cfg(doctest)]
pub struct Guide;
