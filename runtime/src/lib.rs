//! Runtime of adflex: the math rules every generated kernel calls, arrays with gradients,
//! parallel deterministic launches, the tape, checkpointing and gradient checking.
//!
//! Most users reach this crate through `adflex::prelude`. The guide (docs/guide.md) has the
//! tour; each module's docs have the details.

// Generated code names this crate `::adflex_runtime`, also from inside it.
extern crate self as adflex_runtime;

pub mod array;
pub mod checkpoint;
mod chunk_order;
mod dual;
mod error;
pub mod func;
pub mod gradcheck;
/// The code-generation contract (what `#[diff_kernel]` emits calls to): views of arrays that
/// exist only inside a launch. Not for users; hidden from the docs.
#[doc(hidden)]
pub mod kernel;
pub mod launch;
mod linger;
pub mod math;
/// The code-generation path: every builtin of [`math`] with its adjoint (`adj_*`) and tangent
/// (`tan_*`) rules, which only the code `#[diff_kernel]` and `#[diff_func]` emit calls. Not for
/// users; hidden from the docs.
#[doc(hidden)]
pub mod __codegen {
    pub use crate::math::cast::*;
    pub use crate::math::component::*;
    pub use crate::math::construct::*;
    pub use crate::math::items::*;
    pub use crate::math::matrix::*;
    pub use crate::math::ops::*;
    pub use crate::math::quaternion::*;
    pub use crate::math::scalar::*;
    pub use crate::math::vector::*;
    pub use crate::math::vector_space::*;
}
pub mod products;
mod real;
mod region;
mod scatter_log;
pub mod second_order;
pub mod settings;
mod split;
mod subnormals;
pub mod tape;
mod value;

/// Counters for the runtime's own tests (which path a launch took, whether workers linger):
/// not part of the API; hidden from the docs.
#[doc(hidden)]
pub mod __test {
    /// Lingering jobs spawned and not yet started, and workers lingering now.
    pub fn lingerers() -> (usize, usize) {
        crate::linger::lingerers()
    }

    /// Times a launching thread, done with its share of a parallel launch, waited for the
    /// other shares.
    pub fn leader_waits() -> usize {
        crate::linger::leader_waits()
    }

    /// How many launches so far ran as a static split (see `docs/performance.md`, "How a
    /// parallel launch scatters").
    pub fn split_launches() -> u64 {
        crate::split::launches()
    }
}

pub use array::{AnyArray, Array, Element};
pub use dual::Dual;
pub use error::Error;
pub use func::DiffFunc;
pub use kernel::{Kernel, KernelBody, Mode};
pub use launch::{
    launch, launch_adjoint, launch_mode, launch_serial, launch_tangent, with_threads,
};
pub use real::{Mat22, Mat33, Quat, Real, Vec2, Vec3, Vec4};
pub use tape::{BackwardStats, CustomStep, StepOutcome, Tape, TapeInput};
pub use value::{acc, acc_neg, zero_like, Value};

/// Everything a kernel author needs: types, math builtins, arrays, launches, the tape.
pub mod prelude {
    pub use crate::checkpoint::{checkpointed, Checkpoint, Checkpointed};
    pub use crate::gradcheck::{gradcheck, gradcheck_kernel, GradCheck};
    pub use crate::math::items::builtins_prelude::*;
    pub use crate::{launch, launch_adjoint, launch_mode, launch_tangent, with_threads, Mode};
    pub use crate::{AnyArray, Dual, Tape};
    pub use crate::{Array, DiffFunc, Error, Mat22, Mat33, Quat, Real, Value, Vec2, Vec3, Vec4};
}
