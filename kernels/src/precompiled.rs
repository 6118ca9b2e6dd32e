//! Generic entry points whose bodies are compiled in this crate, for `f32` and `f64`.
//!
//! A release build does not share generic instantiations between crates, so a user crate that
//! calls a generic function of this one code-generates it again, with everything it reaches:
//! [`ModelBuilder::finalize`](crate::ModelBuilder::finalize) reaches every library force's
//! kernels (forward, adjoint and tangent of springs, bending, membranes, tetrahedra and every
//! contact) through the `Box<dyn Force<R>>` it makes, and every integrator's step reaches the
//! rigid bodies' kernels. That was about three quarters of a small user crate's code and of its
//! rebuild time after an edit (`docs/performance.md`, "The edit-compile cycle"). The functions
//! here are generic shims: they call a non-generic instantiation compiled once, in this crate,
//! for the scalar type at hand.

use std::any::TypeId;
use std::mem::ManuallyDrop;

use adflex_runtime::{Error, Real, Tape};

use crate::integrators::implicit::{ImplicitEuler, NewtonStats};
use crate::model::{Control, Model, ModelBuilder, State};
use crate::rigid::BodyState;

/// Defines `pub(crate) fn $name<R: Real>(args) -> out` running `body` with `R = f32` or
/// `R = f64`, each compiled once in this crate (in the modules `$name::{f32, f64}`).
macro_rules! precompiled {
    ($(#[$m:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?) -> $out:ty $body:block) => {
        mod $name {
            pub(crate) mod f32 {
                #[allow(unused_imports)]
                use super::super::*;
                type R = f32;
                pub(crate) fn call($($arg: $ty),*) -> $out $body
            }
            pub(crate) mod f64 {
                #[allow(unused_imports)]
                use super::super::*;
                type R = f64;
                pub(crate) fn call($($arg: $ty),*) -> $out $body
            }
        }

        $(#[$m])*
        pub(crate) fn $name<R: Real>($($arg: $ty),*) -> $out {
            // The result must not borrow from the arguments: `same` would not see the lifetime.
            fn owned<T: 'static>() {}
            owned::<$out>();
            if TypeId::of::<R>() == TypeId::of::<f64>() {
                // SAFETY: `R` is `f64`, so every argument's type and the result's are those of
                // `$name::f64::call`.
                unsafe { same($name::f64::call($(same($arg)),*)) }
            } else if TypeId::of::<R>() == TypeId::of::<f32>() {
                // SAFETY: as above, with `f32`.
                unsafe { same($name::f32::call($(same($arg)),*)) }
            } else {
                unsupported::<R>()
            }
        }
    };
}

/// `a` as the type `B`.
///
/// # Safety
///
/// `A` and `B` must be the same type (up to lifetimes that the caller keeps).
unsafe fn same<A, B>(a: A) -> B {
    assert_eq!(std::mem::size_of::<A>(), std::mem::size_of::<B>());
    let a = ManuallyDrop::new(a);
    // SAFETY: the caller's contract; `a` is not dropped, its bits move into the result.
    unsafe { std::mem::transmute_copy(&*a) }
}

/// Panics for a scalar type other than `f32` and `f64`, which the library is compiled for.
fn unsupported<R>() -> ! {
    panic!(
        "adflex's library (models, forces, integrators) is compiled for f32 and f64, not for {}",
        std::any::type_name::<R>()
    )
}

precompiled! {
    /// [`ModelBuilder::build_model`], which boxes the library's forces.
    fn build_model(builder: &ModelBuilder<R>) -> Model<R> {
        builder.build_model()
    }
}

precompiled! {
    /// The rigid bodies' step of every integrator
    /// ([`step_bodies_generic`](crate::integrators::common::step_bodies_generic)).
    fn step_bodies(
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Option<BodyState<R>> {
        crate::integrators::common::step_bodies_generic(model, tape, state, control, dt)
    }
}

precompiled! {
    /// [`ImplicitEuler::step_with_stats`].
    fn implicit_euler_step(
        this: &ImplicitEuler,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<(State<R>, NewtonStats), Error> {
        this.step_with_stats_generic(model, tape, state, control, dt)
    }
}
