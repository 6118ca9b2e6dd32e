//! `DiffFunc`: how generated code calls a `#[diff_func]`.

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
pub fn call_adjoint<A, O, F: DiffFunc<A, O>>(args: A, adj_out: O, f: &F) -> A {
    f.adjoint(args, adj_out)
}

/// The tangent rule of a `#[diff_func]` call.
#[inline(always)]
pub fn call_tangent<A, O, F: DiffFunc<A, O>>(args: A, dots: A, f: &F) -> (O, O) {
    f.tangent(args, dots)
}
