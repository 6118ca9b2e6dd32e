//! Lowering of control flow: blocks (and the guards after a statement that may leave), `if`
//! and `match` (branches merged through phis), `for`/`while`/`loop` (unrolled or carried), and
//! the flags `break`, `continue` and `return` set.

use std::collections::HashSet;

use proc_macro2::Span;
use quote::{quote, ToTokens};
use syn::spanned::Spanned;
use syn::visit::Visit;
use syn::{Expr, Pat};

use super::scope::{assigned_names, Assigned, Flag, Name};
use super::Lowerer;
use crate::ir::*;
use crate::syntax::{contains_return, exits_loop, int_literal, is_catch_all, may_exit};
use crate::Kind;

/// Loops with constant bounds and at most this many iterations are unrolled...
const UNROLL_MAX: u64 = 16;
/// ...as long as the bodies of a nest of unrolled loops stay at most this many copies (a
/// 16 x 16 nest unrolled to 256 bodies overflowed rustc's stack in a debug build): an inner
/// loop that would exceed it stays a loop.
const UNROLL_TOTAL_MAX: u64 = 64;

impl Lowerer<'_> {
    /// Lowers statements in order; returns the value of a tail expression.
    pub(super) fn lower_block_value(
        &mut self,
        stmts: &[syn::Stmt],
        out: &mut Block,
    ) -> Option<ValueId> {
        for (i, st) in stmts.iter().enumerate() {
            let last = i + 1 == stmts.len();
            if let (true, syn::Stmt::Expr(e, None)) = (last, st) {
                return self.lower_expr(e, out);
            }
            self.lower_stmt(st, out);
            if !last && may_exit(st) {
                return self.lower_guarded(&stmts[i + 1..], out);
            }
        }
        None
    }

    /// Lowers `stmts` under `if !(break || continue || return) { .. }`.
    pub(super) fn lower_guarded(
        &mut self,
        stmts: &[syn::Stmt],
        out: &mut Block,
    ) -> Option<ValueId> {
        match self.active_condition(out) {
            Active::Always => self.lower_block_value(stmts, out),
            Active::Never => {
                // Unreachable: lower for its errors only.
                let mut dead = Block::default();
                self.env.push(Vec::new());
                let v = self.lower_block_value(stmts, &mut dead);
                self.env.pop();
                v.map(|_| self.push(out, Op::Zero, Span::call_site()))
            }
            Active::If(c) => {
                let has_tail = matches!(stmts.last(), Some(syn::Stmt::Expr(_, None)));
                self.branches(
                    c,
                    out,
                    Span::call_site(),
                    |s, b| s.lower_block_value(stmts, b),
                    |s, b| has_tail.then(|| s.push(b, Op::Zero, Span::call_site())),
                )
            }
        }
    }

    fn active_condition(&mut self, out: &mut Block) -> Active {
        let mut terms = Vec::new();
        for flag in [Flag::Break, Flag::Continue, Flag::Return] {
            if let Some(b) = self.lookup(flag) {
                match self.const_bool.get(&b.value) {
                    Some(false) => {}
                    Some(true) => return Active::Never,
                    None => terms.push(b.value),
                }
            }
        }
        let Some(first) = terms.first().copied() else {
            return Active::Always;
        };
        let any = terms[1..].iter().fold(first, |acc, &t| {
            self.push(
                out,
                Op::NativeBinary {
                    op: quote!(||),
                    a: acc,
                    b: t,
                },
                Span::call_site(),
            )
        });
        Active::If(self.push(
            out,
            Op::NativeUnary {
                op: quote!(!),
                a: any,
            },
            Span::call_site(),
        ))
    }

    /// Lowers an if/else whose branches are given as closures; merges the bindings they change
    /// through phis and returns the merged value if both branches have one.
    pub(super) fn branches(
        &mut self,
        cond: ValueId,
        out: &mut Block,
        _span: Span,
        then_f: impl FnOnce(&mut Self, &mut Block) -> Option<ValueId>,
        else_f: impl FnOnce(&mut Self, &mut Block) -> Option<ValueId>,
    ) -> Option<ValueId> {
        let before = self.env.clone();
        let mut then_b = Block::default();
        self.env.push(Vec::new());
        let tv = then_f(self, &mut then_b);
        self.env.pop();
        let after_then = std::mem::replace(&mut self.env, before);
        let mut else_b = Block::default();
        self.env.push(Vec::new());
        let ev = else_f(self, &mut else_b);
        self.env.pop();
        let after_else = self.env.clone();
        let mut phis = Vec::new();
        for si in 0..self.env.len() {
            for bi in 0..self.env[si].len() {
                let (t, e) = (after_then[si][bi].value, after_else[si][bi].value);
                let merged = if t == e {
                    t
                } else {
                    let o = self.fresh();
                    if let (Some(a), Some(b)) = (self.const_bool.get(&t), self.const_bool.get(&e)) {
                        if a == b {
                            let a = *a;
                            self.const_bool.insert(o, a);
                        }
                    }
                    phis.push(Phi {
                        out: o,
                        then_v: t,
                        else_v: e,
                    });
                    o
                };
                self.env[si][bi].value = merged;
            }
        }
        let value = match (tv, ev) {
            (Some(t), Some(e)) => {
                let o = self.fresh();
                phis.push(Phi {
                    out: o,
                    then_v: t,
                    else_v: e,
                });
                Some(o)
            }
            _ => None,
        };
        out.stmts.push(Stmt::If {
            cond,
            then_b,
            else_b,
            phis,
        });
        value
    }

    /// `break` or `continue` (check made sure it is in a loop): sets the loop's `flag`, which
    /// guards what follows.
    pub(super) fn set_flag(&mut self, flag: Flag, out: &mut Block) {
        let t = self.const_flag(true, out);
        self.assign(flag, t);
    }

    /// `return` or `return x` (funcs): sets the return flag, and the return value.
    pub(super) fn lower_return(&mut self, r: &syn::ExprReturn, out: &mut Block) {
        if let (Some(v), Kind::Func) = (&r.expr, self.kind) {
            if let Some(v) = self.lower_value(v, out) {
                self.assign(Name::ReturnValue, v);
            }
        }
        self.set_flag(Flag::Return, out);
    }

    pub(super) fn lower_if(&mut self, i: &syn::ExprIf, out: &mut Block) -> Option<ValueId> {
        let c = self.lower_value(&i.cond, out)?;
        let then = &i.then_branch;
        let els = i.else_branch.as_ref().map(|(_, e)| &**e);
        self.branches(
            c,
            out,
            i.span(),
            |s, b| s.lower_block_value(&then.stmts, b),
            |s, b| match els {
                None => None,
                Some(Expr::If(ei)) => s.lower_if(ei, b),
                Some(Expr::Block(eb)) => s.lower_block_value(&eb.block.stmts, b),
                Some(other) => s.lower_expr(other, b),
            },
        )
    }

    pub(super) fn lower_match(&mut self, m: &syn::ExprMatch, out: &mut Block) -> Option<ValueId> {
        let s = self.lower_value(&m.expr, out)?;
        self.lower_arms(s, &m.arms, out)
    }

    /// The arms of a `match` on `s`, as a chain of ifs; check made sure the last arm is `_`.
    pub(super) fn lower_arms(
        &mut self,
        s: ValueId,
        arms: &[syn::Arm],
        out: &mut Block,
    ) -> Option<ValueId> {
        let arm = &arms[0];
        if is_catch_all(&arm.pat) && arm.guard.is_none() {
            self.env.push(Vec::new());
            if let Pat::Ident(pi) = &arm.pat {
                self.bind(&pi.ident.to_string(), s, false);
            }
            let v = self.lower_expr(&arm.body, out);
            self.env.pop();
            return v;
        }
        let mut cond = self.pattern_cond(&arm.pat, s, out)?;
        if let Some((_, g)) = &arm.guard {
            let pc = cond;
            cond = self.branches(
                pc,
                out,
                g.span(),
                |st, b| st.lower_value(g, b),
                |st, b| Some(st.const_flag(false, b)),
            )?;
        }
        let rest = &arms[1..];
        self.branches(
            cond,
            out,
            arm.span(),
            |st, b| st.lower_expr(&arm.body, b),
            |st, b| st.lower_arms(s, rest, b),
        )
    }

    pub(super) fn pattern_cond(&mut self, p: &Pat, s: ValueId, out: &mut Block) -> Option<ValueId> {
        let span = p.span();
        match p {
            Pat::Lit(l) => {
                let c = self.push(out, Op::Const(l.to_token_stream()), span);
                Some(self.push(
                    out,
                    Op::NativeBinary {
                        op: quote!(==),
                        a: s,
                        b: c,
                    },
                    span,
                ))
            }
            Pat::Range(r) => {
                let (Some(lo), Some(hi)) = (&r.start, &r.end) else {
                    unreachable!("check: match ranges have both bounds")
                };
                let lo = self.push(out, Op::Const(lo.to_token_stream()), span);
                let hi = self.push(out, Op::Const(hi.to_token_stream()), span);
                let upper = match r.limits {
                    syn::RangeLimits::Closed(_) => quote!(<=),
                    syn::RangeLimits::HalfOpen(_) => quote!(<),
                };
                let a = self.push(
                    out,
                    Op::NativeBinary {
                        op: quote!(>=),
                        a: s,
                        b: lo,
                    },
                    span,
                );
                let b = self.push(
                    out,
                    Op::NativeBinary {
                        op: upper,
                        a: s,
                        b: hi,
                    },
                    span,
                );
                Some(self.push(
                    out,
                    Op::NativeBinary {
                        op: quote!(&),
                        a,
                        b,
                    },
                    span,
                ))
            }
            Pat::Or(o) => {
                let mut acc = None;
                for c in &o.cases {
                    let v = self.pattern_cond(c, s, out)?;
                    acc = Some(match acc {
                        None => v,
                        Some(a) => self.push(
                            out,
                            Op::NativeBinary {
                                op: quote!(|),
                                a,
                                b: v,
                            },
                            span,
                        ),
                    });
                }
                acc
            }
            Pat::Paren(pp) => self.pattern_cond(&pp.pat, s, out),
            // Refused by check.
            _ => self.error_value(out, span, "this pattern is not supported in kernels"),
        }
    }

    // ---- loops -------------------------------------------------------------------------

    /// `for i in a..b` (or `a..=b`): unrolled if the bounds are small literals, else a loop.
    pub(super) fn lower_for(&mut self, f: &syn::ExprForLoop, out: &mut Block) {
        let index_name = match &*f.pat {
            Pat::Ident(pi) => Some(pi.ident.to_string()),
            _ => None, // `_`
        };
        let Expr::Range(r) = &*f.expr else {
            unreachable!("check: `for` loops over ranges")
        };
        let (Some(start), Some(end)) = (&r.start, &r.end) else {
            unreachable!("check: `for` ranges have both bounds")
        };
        let inclusive = matches!(r.limits, syn::RangeLimits::Closed(_));
        if let (Some(lo), Some(hi)) = (int_literal(start), int_literal(end)) {
            let hi = if inclusive { hi + 1 } else { hi };
            let n = hi.saturating_sub(lo);
            let total = self.unrolled_copies.saturating_mul(n);
            if n <= UNROLL_MAX && total <= UNROLL_TOTAL_MAX {
                let outer = std::mem::replace(&mut self.unrolled_copies, total.max(1));
                self.lower_unrolled(lo, hi, index_name.as_deref(), &f.body, out);
                self.unrolled_copies = outer;
                return;
            }
        }
        let Some(s) = self.lower_value(start, out) else {
            return;
        };
        let Some(e) = self.lower_value(end, out) else {
            return;
        };
        self.lower_loop(
            Some((s, e, inclusive)),
            index_name.as_deref(),
            &f.body,
            None,
            out,
        );
    }

    pub(super) fn lower_unrolled(
        &mut self,
        lo: u64,
        hi: u64,
        index: Option<&str>,
        body: &syn::Block,
        out: &mut Block,
    ) {
        let may_leave = exits_loop(body) || contains_return(body);
        self.env.push(Vec::new());
        let f = self.const_flag(false, out);
        self.bind(Flag::Break, f, true);
        for k in lo..hi {
            let iteration = |s: &mut Self, b: &mut Block| {
                s.env.push(Vec::new());
                if let Some(name) = index {
                    let lit = proc_macro2::Literal::u64_unsuffixed(k);
                    let kv = s.push(b, Op::Const(quote!(#lit)), body.span());
                    s.bind(name, kv, false);
                }
                let c = s.const_flag(false, b);
                s.bind(Flag::Continue, c, true);
                s.lower_block_value(&body.stmts, b);
                s.env.pop();
                None
            };
            if k > lo && may_leave {
                match self.active_condition(out) {
                    Active::Always => {
                        iteration(self, out);
                    }
                    Active::Never => break,
                    Active::If(c) => {
                        self.branches(c, out, body.span(), iteration, |_, _| None);
                    }
                }
            } else {
                iteration(self, out);
            }
        }
        self.env.pop();
    }

    pub(super) fn lower_loop(
        &mut self,
        range: Option<(ValueId, ValueId, bool)>,
        index_name: Option<&str>,
        body: &syn::Block,
        cond: Option<&Expr>,
        out: &mut Block,
    ) {
        let id = self.next_loop;
        self.next_loop += 1;
        let mut assigned = assigned_names(body);
        if let Some(c) = cond {
            let mut v = Assigned::default();
            v.visit_expr(c);
            assigned.extend(v.names);
        }
        // The innermost binding of every name the body assigns is carried.
        let mut positions = Vec::new();
        let mut seen = HashSet::new();
        for si in (0..self.env.len()).rev() {
            for bi in (0..self.env[si].len()).rev() {
                let name = self.env[si][bi].name.clone();
                if seen.insert(name.clone()) && assigned.contains(&name) {
                    positions.push((si, bi));
                }
            }
        }
        let mut carried = Vec::new();
        for &(si, bi) in &positions {
            let init = self.env[si][bi].value;
            let inner = self.fresh();
            self.env[si][bi].value = inner;
            carried.push(Carry {
                init,
                inner,
                next: inner,
                out: inner,
            });
        }
        let mut body_b = Block::default();
        self.env.push(Vec::new());
        let index = range.map(|_| {
            let v = self.fresh();
            if let Some(n) = index_name {
                self.bind(n, v, false);
            }
            v
        });
        let f = self.const_flag(false, &mut body_b);
        self.bind(Flag::Break, f, true);
        let f = self.const_flag(false, &mut body_b);
        self.bind(Flag::Continue, f, true);
        if let Some(c) = cond {
            if let Some(cv) = self.lower_value(c, &mut body_b) {
                let nb = self.push(
                    &mut body_b,
                    Op::NativeUnary {
                        op: quote!(!),
                        a: cv,
                    },
                    c.span(),
                );
                self.assign(Flag::Break, nb);
            }
            self.lower_guarded(&body.stmts, &mut body_b);
        } else {
            self.lower_block_value(&body.stmts, &mut body_b);
        }
        let mut exit_terms = Vec::new();
        for flag in [Flag::Break, Flag::Return] {
            if let Some(b) = self.lookup(flag) {
                if self.const_bool.get(&b.value) != Some(&false) {
                    exit_terms.push(b.value);
                }
            }
        }
        let exit = exit_terms.first().copied().map(|first| {
            exit_terms[1..].iter().fold(first, |acc, &t| {
                self.push(
                    &mut body_b,
                    Op::NativeBinary {
                        op: quote!(||),
                        a: acc,
                        b: t,
                    },
                    Span::call_site(),
                )
            })
        });
        self.env.pop();
        for (c, &(si, bi)) in carried.iter_mut().zip(&positions) {
            c.next = self.env[si][bi].value;
            c.out = self.fresh();
            self.env[si][bi].value = c.out;
        }
        out.stmts.push(Stmt::Loop(Loop {
            id,
            range,
            index,
            carried,
            body: body_b,
            exit,
        }));
    }
}

enum Active {
    Always,
    Never,
    If(ValueId),
}
