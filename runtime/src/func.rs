//! `DiffFunc`: how generated code calls a `#[diff_func]`.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// A differentiable function of `Args` (a tuple) returning `Out`, implemented by
/// `#[diff_func]` on the unit struct that takes the function's name.
///
/// Adjoints and tangents have the types of the values they belong to, so `adjoint` returns one
/// adjoint per argument as a tuple of the argument types.
#[diagnostic::on_unimplemented(
    message = "`{Self}` cannot be called in a kernel with arguments `{Args}`",
    label = "no builtin or #[diff_func] of this name takes these arguments",
    note = "the `help` below shows the arguments it takes; in #[diff_kernel] and #[diff_func] a \
            call must be to a builtin of adflex::math, to a #[diff_func], or wrapped in \
            no_grad(..) to have zero derivative"
)]
pub trait DiffFunc<Args, Out> {
    /// Whether the adjoint and tangent compute in the arguments' own scalar type, so that
    /// run in [`Dual`](crate::Dual) they carry derivative parts (Hessian-vector products,
    /// [`crate::second_order`]). `true` for the builtins and the generated rules; a
    /// `#[diff_func]` with a custom adjoint is `false` unless declared `dual_safe`.
    const DUAL_SAFE: bool = true;
    /// The function itself.
    fn forward(&self, args: Args) -> Out;
    /// Reverse mode: the adjoint of every argument, given the adjoint of the result.
    fn adjoint(&self, args: Args, adj_out: Out) -> Args;
    /// Forward mode: the value and its tangent, given the tangent of every argument.
    fn tangent(&self, args: Args, dots: Args) -> (Out, Out);
}

/// Calls a `#[diff_func]` (the arguments come first so a mismatch is reported once).
#[inline(always)]
pub fn call<A, O, F: DiffFunc<A, O>>(args: A, f: &F) -> O {
    f.forward(args)
}

/// The adjoint rule of a `#[diff_func]` call.
#[inline(always)]
pub fn call_adjoint<A, O: crate::Value, F: DiffFunc<A, O>>(args: A, adj_out: O, f: &F) -> A {
    if O::DUAL && !F::DUAL_SAFE {
        refuse_dual::<F>();
    }
    f.adjoint(args, adj_out)
}

/// The first refusal of a custom rule run in `Dual` since the tape last looked
/// ([`take_refusal`]). A launch cannot return an error, and a panic inside one would leave
/// its parallel region waiting for a share that never comes: the rule records the refusal
/// and runs on, and the tape's pass returns it as an error after the launch.
static REFUSED: AtomicBool = AtomicBool::new(false);
static REFUSAL: Mutex<Option<String>> = Mutex::new(None);

/// Records that a custom adjoint or tangent not declared `dual_safe` ran in `Dual`.
#[cold]
#[inline(never)]
fn refuse_dual<F>() {
    if REFUSED.swap(true, Ordering::AcqRel) {
        return;
    }
    let name = std::any::type_name::<F>();
    *REFUSAL.lock().unwrap_or_else(|e| e.into_inner()) = Some(format!(
        "the #[diff_func] `{name}` has a custom adjoint that was not declared `dual_safe`, and \
         a pass in `Dual` (a Hessian-vector product, or any backward or tangent pass of a \
         `Dual` tape) ran it: if the adjoint and the \
         tangent compute in the arguments' own scalar type (no detour through f64), declare \
         it with `#[diff_func(adjoint = .., tangent = .., dual_safe)]`; otherwise it has no \
         second-order rule and the product cannot go through it"
    ));
}

/// The refusal recorded by a custom rule since the last call, if any (taken).
pub(crate) fn take_refusal() -> Option<String> {
    if !REFUSED.load(Ordering::Acquire) {
        return None;
    }
    let message = REFUSAL.lock().unwrap_or_else(|e| e.into_inner()).take();
    REFUSED.store(false, Ordering::Release);
    message
}

/// The tangent rule of a `#[diff_func]` call.
#[inline(always)]
pub fn call_tangent<A, O: crate::Value, F: DiffFunc<A, O>>(args: A, dots: A, f: &F) -> (O, O) {
    if O::DUAL && !F::DUAL_SAFE {
        refuse_dual::<F>();
    }
    f.tangent(args, dots)
}
