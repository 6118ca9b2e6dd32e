//! `#[diff_kernel]` and `#[diff_func]`: plain Rust functions become a forward kernel, its
//! adjoint (reverse mode) and its tangent (forward mode).
//!
//! The pipeline, one module per step ([`expand`] runs them in order):
//!
//! 1. **parse**: [`attr`] reads the attribute's arguments, [`signature`] the fn's parameters
//!    (arrays or values), generics and return type.
//! 2. **check**: [`check`] walks the body once and refuses every construct outside the kernel
//!    language (closures, macros, references, labels, ..), each at its span.
//! 3. **lower**: [`lower`] turns a checked body into the SSA of [`ir`]: locals become values,
//!    `if`/`match` merge through phis, loops carry values, and `break`/`continue`/`return`
//!    become flags. It reports what needs names resolved (unknown names, assignments to
//!    immutables, array stores, builtin arities).
//! 4. **emit**: [`emit`] writes the forward, adjoint and tangent code of the SSA; [`expand`]
//!    assembles it into the items (a unit struct implementing the runtime's traits).
//!
//! Errors from every step are collected in one [`Errors`] and become `compile_error!`s beside
//! a stub of the item, so that the user's other code still type-checks. [`Kind`] says whether a
//! kernel or a function is compiled. [`builtins`] lists the builtin functions, [`syntax`] holds
//! the syntactic queries check and lower share.
//!
//! The macro knows no types: every operation is a call to a rule in `adflex_runtime::__codegen`
//! (`add`, `adj_add`, `tan_add`, ..), which type inference resolves.
//!
//! The language and its errors are documented in docs/guide.md of the repository.

// The overview above links the internal modules, for contributors reading
// `cargo doc --document-private-items`.
#![allow(rustdoc::private_intra_doc_links)]

use proc_macro2::Span;

mod attr;
mod builtins;
mod check;
mod emit;
mod expand;
mod ir;
mod lanes;
mod lower;
mod signature;
mod strategy;
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

/// Errors collected while expanding, each at its span: the one error context of every step.
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
