//! Lowering: a checked fn body (syn) becomes SSA ([`crate::ir`]).
//!
//! [`crate::check`] has already refused every construct outside the kernel language, so this
//! pass only builds values. What it still reports needs names or values resolved: unknown names,
//! assignments to immutables or parameters, stores into arrays, builtin arities, expressions
//! without a value, and a kernel reading and writing one array.
//!
//! - [`scope`]: the environment, a stack of scopes binding locals, control flags and the
//!   return value to SSA values.
//! - [`expr`]: expressions (operators, calls, reads, components).
//! - [`stmt`]: `let`, assignments and array stores.
//! - [`control`]: blocks, `if`, `match`, loops, and the `break`/`continue`/`return` flags.
//!
//! Locals are bindings in the scope stack; assigning a `let mut` local rebinds it to a new value.
//! `if` merges what its branches assigned through phis; a dynamic loop carries what its body
//! assigns. `break`, `continue` and `return` set flags ([`scope::Flag`]), which are ordinary
//! bindings: the statements after one that may exit run under `if !(flags) { .. }`, and a loop
//! ends after an iteration whose exit flag is set. So no block ends early, which is what keeps
//! the adjoint of loops with `break` and `while` correct.

mod control;
mod expr;
mod scope;
mod stmt;

use std::collections::HashMap;

use proc_macro2::{Span, TokenStream};
use quote::quote;
use syn::spanned::Spanned;
use syn::Expr;

use crate::ir::*;
use crate::signature::{ParamKind, Signature};
use crate::syntax::contains_return;
use crate::{Errors, Kind};
use scope::{Binding, Flag, Name};

/// How a kernel uses one array parameter (spans of the first read, store, accumulation).
#[derive(Default, Clone)]
pub struct ArrayUse {
    pub read: Option<Span>,
    pub store: Option<Span>,
    pub atomic: Option<Span>,
}

pub struct Lowerer<'a> {
    sig: &'a Signature,
    rt: &'a TokenStream,
    kind: Kind,
    errors: &'a mut Errors,
    next_value: ValueId,
    next_loop: usize,
    /// How many copies of the current statement the enclosing unrolled loops make (1 outside
    /// them).
    unrolled_copies: u64,
    /// The scopes, innermost last (see [`scope`]).
    env: Vec<Vec<Binding>>,
    /// Values known to be a constant `true` or `false` (flags that are surely set or unset).
    const_bool: HashMap<ValueId, bool>,
    /// How many `no_grad(..)` enclose the current expression.
    no_grad: usize,
    uses: Vec<ArrayUse>,
}

impl<'a> Lowerer<'a> {
    pub fn new(
        sig: &'a Signature,
        rt: &'a TokenStream,
        kind: Kind,
        errors: &'a mut Errors,
    ) -> Self {
        Lowerer {
            sig,
            rt,
            kind,
            errors,
            next_value: 0,
            next_loop: 0,
            unrolled_copies: 1,
            env: vec![Vec::new()],
            const_bool: HashMap::new(),
            no_grad: 0,
            uses: vec![ArrayUse::default(); sig.params.len()],
        }
    }

    /// Lowers the whole body; also returns how the kernel uses each array parameter.
    pub fn lower_body(mut self, body: &syn::Block) -> (Body, Vec<ArrayUse>) {
        let mut params = Vec::new();
        for p in &self.sig.params {
            match &p.kind {
                ParamKind::Array { .. } => params.push(None),
                ParamKind::Value { mutable, .. } => {
                    let v = self.fresh();
                    self.bind(&p.name.to_string(), v, *mutable);
                    params.push(Some(v));
                }
            }
        }
        let has_return = contains_return(body);
        let mut block = Block::default();
        if has_return {
            let f = self.const_flag(false, &mut block);
            self.bind(Flag::Return, f, true);
            if self.kind == Kind::Func {
                let z = self.push(&mut block, Op::Zero, Span::call_site());
                self.bind(Name::ReturnValue, z, true);
            }
        }
        let tail = self.lower_block_value(&body.stmts, &mut block);
        let ret = if self.kind == Kind::Kernel {
            None
        } else if has_return {
            let flag = self.lookup(Flag::Return).unwrap().value;
            let retval = self.lookup(Name::ReturnValue).unwrap().value;
            match tail {
                Some(t) => self.branches(
                    flag,
                    &mut block,
                    Span::call_site(),
                    |_, _| Some(retval),
                    |_, _| Some(t),
                ),
                None => {
                    let ends_with_return =
                        matches!(body.stmts.last(), Some(syn::Stmt::Expr(Expr::Return(_), _)));
                    if !ends_with_return {
                        self.errors.push(
                            body.span(),
                            "a #[diff_func] must end with a value or a `return` on every path",
                        );
                    }
                    Some(retval)
                }
            }
        } else {
            if tail.is_none() && self.sig.ret.is_some() {
                self.errors.push(
                    body.span(),
                    "a #[diff_func] must end with the value it returns",
                );
            }
            tail
        };
        if self.kind == Kind::Kernel {
            self.check_array_uses();
        }
        (Body { params, block, ret }, self.uses)
    }

    fn check_array_uses(&mut self) {
        for (i, u) in self.uses.iter().enumerate() {
            let name = &self.sig.params[i].name;
            let kernel = &self.sig.name;
            if let (Some(_), Some(w)) = (u.read, u.store.or(u.atomic)) {
                self.errors.push(
                    w,
                    format!(
                        "kernel `{kernel}` reads array `{name}` and also writes it; a kernel may \
                         read an array or write it, not both (threads would see each other's \
                         writes, and the adjoint could not replay the reads): write into a \
                         separate output array"
                    ),
                );
            }
            if let (Some(_), Some(a)) = (u.store, u.atomic) {
                self.errors.push(
                    a,
                    format!(
                        "kernel `{kernel}` both stores into array `{name}` and accumulates into \
                         it; use one kind of write per array"
                    ),
                );
            }
        }
    }

    // ---- values -----------------------------------------------------------------------

    pub(super) fn fresh(&mut self) -> ValueId {
        self.next_value += 1;
        self.next_value - 1
    }

    pub(super) fn push(&mut self, out: &mut Block, op: Op, span: Span) -> ValueId {
        let id = self.fresh();
        out.stmts.push(Stmt::Let(Let { id, op, span }));
        id
    }

    pub(super) fn const_flag(&mut self, b: bool, out: &mut Block) -> ValueId {
        let v = self.push(
            out,
            Op::Const(if b { quote!(true) } else { quote!(false) }),
            Span::call_site(),
        );
        self.const_bool.insert(v, b);
        v
    }

    /// Reports an error and stands in a zero for the value, so that lowering goes on.
    pub(super) fn error_value(
        &mut self,
        out: &mut Block,
        span: Span,
        msg: impl std::fmt::Display,
    ) -> Option<ValueId> {
        self.errors.push(span, msg);
        Some(self.push(out, Op::Zero, span))
    }
}
