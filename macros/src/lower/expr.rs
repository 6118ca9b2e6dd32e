//! Lowering of expressions: literals, names, operators, calls of builtins and `#[diff_func]`s,
//! array reads, and components of vectors and matrices.

use quote::{quote, quote_spanned, ToTokens};
use syn::spanned::Spanned;
use syn::{BinOp, Expr, Lit, UnOp};

use super::scope::Flag;
use super::Lowerer;
use crate::builtins;
use crate::ir::*;
use crate::syntax::{component_index, is_compound_assign};

impl Lowerer<'_> {
    /// Lowers an expression; `None` if it has no value (an assignment, a loop, `if` without
    /// `else`, ..).
    pub(super) fn lower_expr(&mut self, e: &Expr, out: &mut Block) -> Option<ValueId> {
        let span = e.span();
        match e {
            Expr::Lit(l) => self.lower_lit(&l.lit, out),
            Expr::Path(p) => self.lower_path(p, out),
            Expr::Paren(p) => self.lower_expr(&p.expr, out),
            Expr::Group(g) => self.lower_expr(&g.expr, out),
            Expr::Binary(b) => self.lower_binary(b, out),
            Expr::Unary(u) => {
                let a = self.lower_value(&u.expr, out)?;
                let op = match u.op {
                    UnOp::Neg(_) => Op::Builtin {
                        f: Builtin::Neg,
                        args: vec![a],
                    },
                    _ => Op::NativeUnary { op: quote!(!), a }, // `*x` was refused by check
                };
                Some(self.push(out, op, span))
            }
            Expr::Call(c) => self.lower_call(c, out),
            Expr::MethodCall(m) => self.lower_method(m, out),
            Expr::Index(i) => {
                if let Some(p) = self.array_param(&i.expr) {
                    if let Expr::Tuple(t) = &*i.index {
                        // Check allows a tuple index for matrices; an array takes one index.
                        return self.error_value(
                            out,
                            t.span(),
                            "tuples are not supported in kernels (except as a matrix index `m[(r, c)]`)",
                        );
                    }
                    let index = self.lower_value(&i.index, out)?;
                    self.uses[p].read.get_or_insert(span);
                    return Some(self.push(out, Op::Read { param: p, index }, span));
                }
                let base = self.lower_value(&i.expr, out)?;
                let index = self.lower_component_index(&i.index, out)?;
                Some(self.push(
                    out,
                    Op::Builtin {
                        f: Builtin::Extract,
                        args: vec![base, index],
                    },
                    span,
                ))
            }
            Expr::Field(f) => {
                let k = component_index(&f.member).expect("check: a component `.x` .. `.w`");
                let base = self.lower_value(&f.base, out)?;
                let kv = self.push(out, Op::Const(quote!(#k)), f.member.span());
                Some(self.push(
                    out,
                    Op::Builtin {
                        f: Builtin::Extract,
                        args: vec![base, kv],
                    },
                    span,
                ))
            }
            Expr::Cast(c) => {
                let arg = self.lower_value(&c.expr, out)?;
                Some(self.push(
                    out,
                    Op::Cast {
                        arg,
                        ty: c.ty.to_token_stream(),
                    },
                    span,
                ))
            }
            Expr::If(i) => self.lower_if(i, out),
            Expr::Block(b) => self.scoped(|s| s.lower_block_value(&b.block.stmts, out)),
            Expr::Match(m) => self.lower_match(m, out),
            Expr::Assign(a) => {
                self.lower_assign(&a.left, None, &a.right, out);
                None
            }
            Expr::ForLoop(f) => {
                self.lower_for(f, out);
                None
            }
            Expr::While(w) => {
                self.lower_loop(None, None, &w.body, Some(&w.cond), out);
                None
            }
            Expr::Loop(l) => {
                self.lower_loop(None, None, &l.body, None, out);
                None
            }
            Expr::Break(_) => {
                self.set_flag(Flag::Break, out);
                None
            }
            Expr::Continue(_) => {
                self.set_flag(Flag::Continue, out);
                None
            }
            Expr::Return(r) => {
                self.lower_return(r, out);
                None
            }
            Expr::Tuple(t) if t.elems.is_empty() => None,
            // Everything else was refused by check.
            other => self.error_value(
                out,
                other.span(),
                "this expression is not supported in kernels",
            ),
        }
    }

    /// Lowers an expression that must produce a value.
    pub(super) fn lower_value(&mut self, e: &Expr, out: &mut Block) -> Option<ValueId> {
        let v = self.lower_expr(e, out);
        if v.is_none() {
            return self.error_value(out, e.span(), "this expression has no value");
        }
        v
    }

    pub(super) fn lower_lit(&mut self, lit: &Lit, out: &mut Block) -> Option<ValueId> {
        let span = lit.span();
        let tokens = match lit {
            Lit::Float(f) if f.suffix().is_empty() => match &self.sig.real {
                Some(r) => {
                    let rt = self.rt;
                    quote_spanned!(span=> <#r as #rt::Real>::lit(#f))
                }
                None => f.to_token_stream(),
            },
            Lit::Float(_) | Lit::Int(_) | Lit::Bool(_) => lit.to_token_stream(),
            _ => {
                return self.error_value(
                    out,
                    span,
                    "only numeric and boolean literals are supported in kernels",
                )
            }
        };
        let v = self.push(out, Op::Const(tokens), span);
        if let Lit::Bool(b) = lit {
            self.const_bool.insert(v, b.value);
        }
        Some(v)
    }

    pub(super) fn lower_path(&mut self, p: &syn::ExprPath, out: &mut Block) -> Option<ValueId> {
        let span = p.span();
        if let Some(id) = p.path.get_ident() {
            let name = id.to_string();
            if let Some(b) = self.lookup(&name) {
                return Some(b.value);
            }
            if let Some(i) = self.sig.param_index(&name) {
                if self.sig.params[i].is_array() {
                    return self.error_value(
                        out,
                        span,
                        format!("array `{name}` cannot be used as a value: read an element (`{name}[i]`)"),
                    );
                }
            }
            let is_const_like = name.chars().next().is_some_and(|c| c.is_uppercase());
            if !is_const_like {
                return self.error_value(
                    out,
                    span,
                    format!("cannot find value `{name}` in this kernel"),
                );
            }
        }
        // A constant: `PI`, `std::f32::consts::PI`, `MY_CONST`.
        Some(self.push(out, Op::Const(p.to_token_stream()), span))
    }

    pub(super) fn lower_binary(&mut self, b: &syn::ExprBinary, out: &mut Block) -> Option<ValueId> {
        let span = b.span();
        let arith = |op: &BinOp| match op {
            BinOp::Add(_) | BinOp::AddAssign(_) => Some(Builtin::Add),
            BinOp::Sub(_) | BinOp::SubAssign(_) => Some(Builtin::Sub),
            BinOp::Mul(_) | BinOp::MulAssign(_) => Some(Builtin::Mul),
            BinOp::Div(_) | BinOp::DivAssign(_) => Some(Builtin::Div),
            BinOp::Rem(_) | BinOp::RemAssign(_) => Some(Builtin::Rem),
            _ => None,
        };
        match b.op {
            ref op if is_compound_assign(op) => {
                self.lower_assign(&b.left, Some(&b.op), &b.right, out);
                None
            }
            BinOp::And(_) | BinOp::Or(_) => {
                let a = self.lower_value(&b.left, out)?;
                let is_and = matches!(b.op, BinOp::And(_));
                let right = &*b.right;
                Some(if is_and {
                    self.branches(
                        a,
                        out,
                        span,
                        |s, blk| s.lower_value(right, blk),
                        |s, blk| Some(s.const_flag(false, blk)),
                    )?
                } else {
                    self.branches(
                        a,
                        out,
                        span,
                        |s, blk| Some(s.const_flag(true, blk)),
                        |s, blk| s.lower_value(right, blk),
                    )?
                })
            }
            ref op => {
                let a = self.lower_value(&b.left, out)?;
                let c = self.lower_value(&b.right, out)?;
                match arith(op) {
                    Some(f) => Some(self.push(
                        out,
                        Op::Builtin {
                            f,
                            args: vec![a, c],
                        },
                        span,
                    )),
                    None => Some(self.push(
                        out,
                        Op::NativeBinary {
                            op: op.to_token_stream(),
                            a,
                            b: c,
                        },
                        span,
                    )),
                }
            }
        }
    }

    /// A call: `tid()`, `no_grad(..)`, a builtin, a `#[diff_func]`, a constant (`R::zero()`), or
    /// a plain call inside `no_grad(..)`.
    pub(super) fn lower_call(&mut self, c: &syn::ExprCall, out: &mut Block) -> Option<ValueId> {
        let span = c.span();
        let Expr::Path(fp) = &*c.func else {
            // Refused by check.
            return self.error_value(out, span, "only named functions can be called in kernels");
        };
        let single = fp.path.get_ident().map(|i| i.to_string());
        match single.as_deref() {
            Some("tid") => return Some(self.push(out, Op::Tid, span)),
            Some("no_grad") => {
                self.no_grad += 1;
                let v = self.lower_value(&c.args[0], out);
                self.no_grad -= 1;
                return Some(self.push(out, Op::StopGrad(v?), span));
            }
            Some(name) if self.lookup(name).is_none() => {
                if let Some(arity) = builtins::arity(name) {
                    if c.args.len() != arity {
                        return self.error_value(
                            out,
                            span,
                            format!(
                                "builtin `{name}` takes {arity} argument{} but {} {} given",
                                if arity == 1 { "" } else { "s" },
                                c.args.len(),
                                if c.args.len() == 1 { "was" } else { "were" }
                            ),
                        );
                    }
                    let args = self.lower_args(&c.args, out)?;
                    return Some(self.push(
                        out,
                        Op::Builtin {
                            f: Builtin::Named(name.into()),
                            args,
                        },
                        span,
                    ));
                }
            }
            _ => {}
        }
        if self.no_grad > 0 {
            let args = self.lower_args(&c.args, out)?;
            return Some(self.push(
                out,
                Op::PlainCall {
                    path: fp.to_token_stream(),
                    args,
                },
                span,
            ));
        }
        if single.is_none() && c.args.is_empty() {
            // `R::zero()`, `Vec3::zeros()`: constants.
            return Some(self.push(out, Op::Const(c.to_token_stream()), span));
        }
        let args = self.lower_args(&c.args, out)?;
        Some(self.push(
            out,
            Op::Func {
                path: fp.to_token_stream(),
                args,
            },
            span,
        ))
    }

    pub(super) fn lower_args(
        &mut self,
        args: &syn::punctuated::Punctuated<Expr, syn::Token![,]>,
        out: &mut Block,
    ) -> Option<Vec<ValueId>> {
        let mut vs = Vec::new();
        for a in args {
            vs.push(self.lower_value(a, out)?);
        }
        Some(vs)
    }

    pub(super) fn lower_method(
        &mut self,
        m: &syn::ExprMethodCall,
        out: &mut Block,
    ) -> Option<ValueId> {
        let span = m.span();
        let method = m.method.to_string();
        if method == "atomic_add" || method == "atomic_sub" {
            let Some(p) = self.array_param(&m.receiver) else {
                return self.error_value(
                    out,
                    m.receiver.span(),
                    format!("`{method}` accumulates into an `&Array` parameter; this is not one"),
                );
            };
            if m.args.len() != 2 {
                return self.error_value(
                    out,
                    span,
                    format!("`{method}` takes an index and a value: `a.{method}(i, v)`"),
                );
            }
            let index = self.lower_value(&m.args[0], out)?;
            let value = self.lower_value(&m.args[1], out)?;
            self.uses[p].atomic.get_or_insert(span);
            let kind = if method == "atomic_add" {
                StoreKind::AtomicAdd
            } else {
                StoreKind::AtomicSub
            };
            out.stmts.push(Stmt::Store {
                param: p,
                index,
                value,
                kind,
                span,
            });
            return None;
        }
        if self.no_grad > 0 {
            let recv = self.lower_value(&m.receiver, out)?;
            let args = self.lower_args(&m.args, out)?;
            let name = &m.method;
            let turbofish = m.turbofish.to_token_stream();
            return Some(self.push(
                out,
                Op::PlainMethod {
                    recv,
                    method: quote!(#name #turbofish),
                    args,
                },
                span,
            ));
        }
        // Refused by check (a method call outside no_grad(..)).
        self.error_value(out, span, "method calls are not differentiable in kernels")
    }

    /// The index of a local's component: `v[k]`, or a matrix's `m[(r, c)]` (the one place a
    /// tuple is allowed), read or assigned.
    pub(super) fn lower_component_index(
        &mut self,
        index: &Expr,
        out: &mut Block,
    ) -> Option<ValueId> {
        match index {
            Expr::Tuple(t) => {
                let mut items = Vec::new();
                for el in &t.elems {
                    items.push(self.lower_value(el, out)?);
                }
                Some(self.push(out, Op::Tuple(items), t.span()))
            }
            idx => self.lower_value(idx, out),
        }
    }
}
