//! The interface between `#[diff_kernel]`'s output and the runtime: the kernel traits (here),
//! the `Exec` of a launch (`exec.rs`), the per-chunk views of arrays that generated code
//! reads and writes through (`views.rs`: `Reader`, `OptReader`, `Writer`), the
//! deterministic scatters behind `atomic_add` (`scatter.rs`: `Scatter`), and the index
//! checks they share (`place.rs`). The logs that scatters keep are `crate::scatter_log`'s.
//!
//! Users do not implement these traits by hand; the macro does.

use std::ops::Range;

use crate::array::{AnyArray, Array, Element};

mod exec;
mod place;
mod scatter;
mod views;

pub use crate::scatter_log::ScatterLog;
pub use exec::Exec;
pub(crate) use exec::Halo;
pub use place::{Site, ToIndex};
pub use scatter::{grad_scatter, scatter, tangent_scatter, DirectScatter, Scatter};
pub use views::{
    grad_reader, grad_taker, reader, tangent_reader, tangent_writer, writer, OptReader, Reader,
    Writer,
};

/// How a kernel uses one of its parameters (decided by the macro from the source).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// A value parameter (scalar, vector, index): not an array.
    Value,
    /// An array the kernel reads.
    Read,
    /// An array the kernel stores to (`a[i] = v`).
    Store,
    /// An array the kernel accumulates into (`a.atomic_add(i, v)`).
    Atomic,
    /// An array passed but not used.
    Unused,
}

impl Access {
    /// Whether the kernel writes the array.
    pub fn writes(self) -> bool {
        matches!(self, Access::Store | Access::Atomic)
    }
}

/// One kernel parameter: its name in the source and how the kernel uses it.
#[derive(Debug, Clone, Copy)]
pub struct ParamInfo {
    /// Name in the source.
    pub name: &'static str,
    /// How the kernel uses it.
    pub access: Access,
}

/// Which of the three generated kernels to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Mode {
    /// The kernel as written.
    Forward,
    /// Reverse mode: reads adjoints of outputs from their gradient buffers, accumulates adjoints
    /// of inputs into theirs.
    Adjoint,
    /// Forward mode: reads tangents of inputs from their tangent buffers, writes tangents of
    /// outputs into theirs.
    Tangent,
}

/// A `#[diff_kernel]` that can be launched with the borrowed argument tuple `Args`
/// (e.g. `(&Array<Vec3>, f32, &Array<Vec3>)`).
#[diagnostic::on_unimplemented(
    message = "kernel `{Self}` cannot be launched with arguments `{Args}`",
    label = "these arguments do not match the kernel's parameters",
    note = "pass a tuple with one element per kernel parameter, in order: `&array` for each \
            `&Array<T>` parameter (with the same element type) and a value for each value parameter"
)]
pub trait Kernel<Args>: Copy + Send + Sync + 'static {
    /// The arguments with every `&Array` replaced by a handle (what a tape keeps).
    type Owned: Send + Sync + 'static;
    /// Takes handles of the arrays in `args`.
    fn to_owned(args: &Args) -> Self::Owned;
}

/// The body of a kernel over its owned arguments: what a launch or a tape runs.
///
/// `#[diff_kernel]` implements it; a hand-written implementation must keep the contract below,
/// which the launch relies on for memory safety.
///
/// # Safety
///
/// - [`run`](Self::run) and [`scatter_indices`](Self::scatter_indices) make views
///   ([`reader`], [`writer`], [`scatter`](fn@scatter), ...) only from the `exec` they are given, and every
///   view (and anything borrowed from one, such as a [`DirectScatter`]) is dropped before the
///   call returns, on the thread that made it: none is stored (in a static, a thread-local,
///   the kernel value, the arguments) or sent to another thread. A view points into buffers
///   that the launch holds locked only for the duration of the call.
/// - Views are made over the arrays of `args` (those [`arrays`](Self::arrays) lists), never
///   over another array: a view keeps a pointer to its array's name, which the arguments
///   keep alive for the call.
/// - The logs [`run`](Self::run) returns are those of the scatters it made from `exec`
///   ([`Scatter::finish`]).
/// - If [`static_scatters`](Self::static_scatters) returns `Some`, then
///   [`scatter_indices`](Self::scatter_indices) reports, for each thread id, the index of every
///   scatter that [`run`](Self::run) may make into those targets (other than scatters through
///   a view made with `AT_TID`, which the view checks), and the indices depend only on the
///   thread id, constants and the arrays listed in [`StaticScatters::deps`]. A split launch
///   (`crate::split`) lets two threads write different elements of one target directly on
///   the strength of these indices: a scatter left out or mis-reported would be a data race.
pub unsafe trait KernelBody<Owned>: Copy + Send + Sync + 'static {
    /// The kernel's name (its fn name).
    const NAME: &'static str;
    /// Its parameters in order.
    const PARAMS: &'static [ParamInfo];
    /// The array passed for each parameter (`None` for value parameters).
    fn arrays(args: &Owned) -> Vec<Option<&dyn AnyArray>>;
    /// Runs thread ids `range` in `mode`; returns the scatter logs to apply (empty when `exec`
    /// writes directly).
    fn run(&self, mode: Mode, args: &Owned, range: Range<usize>, exec: &Exec) -> Vec<ScatterLog>;
    /// The scatters of `mode` (other than those at the thread id), if the indices of every
    /// one are static: computed at the top of the body from the thread id, constants and
    /// reads of arrays, so a launch can know them before it runs (see `crate::split`).
    fn static_scatters(mode: Mode) -> Option<StaticScatters> {
        let _ = mode;
        None
    }
    /// Calls `sink(slot, tid, index)` for every static scatter of `mode` of each thread id in
    /// `range`, in order: `slot` is the scattered parameter's place in
    /// [`StaticScatters::targets`]. A thread reports each scatter it may make, whatever
    /// branch it takes later.
    fn scatter_indices(
        &self,
        mode: Mode,
        args: &Owned,
        range: Range<usize>,
        exec: &Exec,
        sink: &mut dyn FnMut(usize, usize, i128),
    ) {
        let _ = (mode, args, range, exec, sink);
    }
}

/// The static scatters of a kernel in one mode (see [`KernelBody::static_scatters`]).
#[derive(Clone, Copy, Debug)]
pub struct StaticScatters {
    /// The parameters scattered into (in the adjoint: whose gradients are).
    pub targets: &'static [usize],
    /// The array parameters the indices read (index arrays such as a mesh's elements).
    pub deps: &'static [usize],
}

/// Converts one launch argument into what the tape keeps.
pub trait LaunchArg {
    /// The owned form.
    type Owned: Send + Sync + 'static;
    /// Takes a handle or copies the value.
    fn to_owned_arg(&self) -> Self::Owned;
}

impl<T: Element> LaunchArg for &Array<T> {
    type Owned = Array<T>;
    #[inline]
    fn to_owned_arg(&self) -> Array<T> {
        (*self).clone()
    }
}

impl<T: crate::Value> LaunchArg for T {
    type Owned = T;
    #[inline]
    fn to_owned_arg(&self) -> T {
        *self
    }
}
