//! `#[diff_kernel]` and `#[diff_func]`: plain Rust functions become a forward kernel, its
//! adjoint (reverse mode) and its tangent (forward mode).
//!
//! The pipeline, each step a module: [`attr`] and [`signature`] parse what is around the body;
//! [`lower`] validates the body against the kernel language (collecting every error at its
//! span) and lowers it to the SSA of [`ir`]; [`emit`] writes the three bodies; [`expand`]
//! assembles the items. The macro knows no types: every operation is a call to a rule in
//! `adflex_runtime::math`, which type inference resolves.
//!
//! The language and its errors are documented in docs/guide.md of the repository.

use proc_macro2::Span;

mod attr;
mod builtins;
mod check;
mod emit;
mod expand;
mod ir;
mod lower;
mod signature;
mod syntax;

/// Compiles a kernel: a fn whose body runs once per thread id (`tid()`), reading `&Array<T>`
/// parameters (`x[i]`), storing (`y[i] = v`) and accumulating (`f.atomic_add(i, v)`).
///
/// The fn becomes a unit struct of the same name that `launch` and `Tape::launch` accept,
/// with a forward, an adjoint and a tangent kernel. See the guide (docs/guide.md).
#[proc_macro_attribute]
pub fn diff_kernel(
    args: proc_macro::TokenStream,
    item: proc_macro::TokenStream,
) -> proc_macro::TokenStream {
    expand::expand(args.into(), item.into(), Kind::Kernel).into()
}

/// Compiles a differentiable function that kernels (and other functions) can call.
///
/// The fn becomes a unit struct of the same name implementing `adflex::DiffFunc`; kernels call
/// it as written (`f(x, y)`), plain Rust as `f::call(x, y)`. `#[diff_func(adjoint = a,
/// tangent = t)]` replaces the generated derivatives with hand-written ones:
/// `fn a(x1, .., xn, adj_out) -> (adj_x1, .., adj_xn,)` and `fn t(x1, .., xn, dx1, .., dxn) -> dout`.
#[proc_macro_attribute]
pub fn diff_func(
    args: proc_macro::TokenStream,
    item: proc_macro::TokenStream,
) -> proc_macro::TokenStream {
    expand::expand(args.into(), item.into(), Kind::Func).into()
}

/// What the attribute compiles: a kernel (`#[diff_kernel]`, launched once per thread id) or a
/// differentiable function (`#[diff_func]`, called from kernels and functions).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(crate) enum Kind {
    Kernel,
    Func,
}

impl Kind {
    /// The attribute as messages name it.
    pub fn attr(self) -> &'static str {
        match self {
            Kind::Kernel => "#[diff_kernel]",
            Kind::Func => "#[diff_func]",
        }
    }
}

/// Errors collected while expanding, each at its span.
#[derive(Default)]
pub(crate) struct Errors(Vec<syn::Error>);

impl Errors {
    pub fn push(&mut self, span: Span, msg: impl std::fmt::Display) {
        self.0.push(syn::Error::new(span, msg));
    }
    pub fn push_error(&mut self, e: syn::Error) {
        self.0.push(e);
    }
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
    pub fn len(&self) -> usize {
        self.0.len()
    }
    pub fn to_compile_errors(&self) -> proc_macro2::TokenStream {
        self.0.iter().map(syn::Error::to_compile_error).collect()
    }
}

#[cfg(test)]
mod tests;
