//! Runtime of adflex: the math rules every generated kernel calls, arrays with gradients,
//! parallel deterministic launches, the tape, checkpointing and gradient checking.
//!
//! Most users reach this crate through `adflex::prelude`. The guide (docs/guide.md) has the
//! tour; each module's docs have the details.

// Generated code names this crate `::adflex_runtime`, also from inside it.
extern crate self as adflex_runtime;

pub mod array;
mod error;
pub mod func;
pub mod kernel;
pub mod launch;
pub mod math;
mod real;
mod value;

pub use array::{AnyArray, Array, Element};
pub use error::Error;
pub use func::DiffFunc;
pub use kernel::{Kernel, KernelBody, Mode};
pub use launch::{launch, launch_adjoint, launch_tangent, with_threads};
pub use real::{Mat22, Mat33, Quat, Real, Vec2, Vec3, Vec4};
pub use value::{acc, acc_neg, zero_like, Value};

/// Everything a kernel author needs: types, math builtins, arrays, launches, the tape.
pub mod prelude {
    pub use crate::math::*;
    pub use crate::{launch, launch_adjoint, launch_tangent, with_threads};
    pub use crate::{Array, Error, Mat22, Mat33, Quat, Real, Value, Vec2, Vec3, Vec4};
}
