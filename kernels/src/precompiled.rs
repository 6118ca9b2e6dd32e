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
//!
//! The macro is invoked next to the entry point it serves (`model.rs`: the model's build;
//! `integrators/common.rs`: the rigid bodies' step; `integrators/implicit.rs`: implicit Euler's
//! step; `articulation/dynamics.rs`: the robots' step; `mpm/step.rs`: the MPM step in 2D and
//! 3D), so this module depends on none of them.
//! Test, example and debug builds share generic instantiations with their dependencies, but
//! only those a dependency made itself: the robots' step, generic in every caller, was compiled
//! again by every example and test crate that stepped a robot (about 2 minutes each).

use std::mem::ManuallyDrop;

/// Defines `pub(crate) fn $name<R: Real>(args) -> out` running `body` with `R = f32` or
/// `R = f64`, each compiled once in this crate (in the modules `$name::{f32, f64}`), in the
/// module that invokes it; any other `R` runs the generic body (`$name::generic`).
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
            // Any other scalar (`Dual`, for second-order passes): compiled where it is used.
            pub(crate) mod generic {
                #[allow(unused_imports)]
                use super::super::*;
                pub(crate) fn call<R: Real>($($arg: $ty),*) -> $out $body
            }
        }

        $(#[$m])*
        pub(crate) fn $name<R: Real>($($arg: $ty),*) -> $out {
            // The result must not borrow from the arguments: `same` would not see the lifetime.
            fn owned<T: 'static>() {}
            owned::<$out>();
            use ::std::any::TypeId;
            use $crate::precompiled::same;
            if TypeId::of::<R>() == TypeId::of::<f64>() {
                // SAFETY: `R` is `f64`, so every argument's type and the result's are those of
                // `$name::f64::call`.
                unsafe { same($name::f64::call($(same($arg)),*)) }
            } else if TypeId::of::<R>() == TypeId::of::<f32>() {
                // SAFETY: as above, with `f32`.
                unsafe { same($name::f32::call($(same($arg)),*)) }
            } else {
                $name::generic::call::<R>($($arg),*)
            }
        }
    };
}

/// `a` as the type `B`.
///
/// # Safety
///
/// `A` and `B` must be the same type (up to lifetimes that the caller keeps).
pub(crate) unsafe fn same<A, B>(a: A) -> B {
    assert_eq!(std::mem::size_of::<A>(), std::mem::size_of::<B>());
    let a = ManuallyDrop::new(a);
    // SAFETY: the caller's contract; `a` is not dropped, its bits move into the result.
    unsafe { std::mem::transmute_copy(&*a) }
}

pub(crate) use precompiled;
