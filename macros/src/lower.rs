//! Lowering: a fn body (syn) becomes SSA ([`crate::ir`]), and every construct outside the
//! kernel language becomes an error at its span.
//!
//! Locals are bindings in a scope stack; assigning a `let mut` local rebinds it to a new value.
//! `if` merges what its branches assigned through phis; a dynamic loop carries what its body
//! assigns. `break`, `continue` and `return` set flags (`#brk`, `#cont`, `#ret`), which are
//! ordinary bindings: the statements after one that may exit run under `if !(flags) { .. }`,
//! and a loop ends after an iteration whose exit flag is set. So no block ends early, which is
//! what keeps the adjoint of loops with `break` and `while` correct.

use std::collections::{HashMap, HashSet};

use proc_macro2::{Span, TokenStream};
use quote::{quote, quote_spanned, ToTokens};
use syn::spanned::Spanned;
use syn::visit::Visit;
use syn::{BinOp, Expr, Lit, Pat, UnOp};

use crate::builtins;
use crate::ir::*;
use crate::signature::{ParamKind, Signature};
use crate::{Errors, Kind};

/// Loops with constant bounds and at most this many iterations are unrolled...
const UNROLL_MAX: u64 = 16;
/// ...as long as the bodies of a nest of unrolled loops stay at most this many copies (a
/// 16 x 16 nest unrolled to 256 bodies overflowed rustc's stack in a debug build): an inner
/// loop that would exceed it stays a loop.
const UNROLL_TOTAL_MAX: u64 = 64;

/// A control flag: set by `break`, `continue` or `return`, it guards what follows.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
enum Flag {
    Break,
    Continue,
    Return,
}

/// What a binding binds: a local (or value parameter) by its name, a control flag, or the value
/// a `return` has set (funcs).
#[derive(Clone, PartialEq, Eq, Hash, Debug)]
enum Name {
    Var(String),
    Flag(Flag),
    ReturnValue,
}

impl From<&str> for Name {
    fn from(s: &str) -> Name {
        Name::Var(s.to_string())
    }
}
impl From<&String> for Name {
    fn from(s: &String) -> Name {
        Name::Var(s.clone())
    }
}
impl From<Flag> for Name {
    fn from(f: Flag) -> Name {
        Name::Flag(f)
    }
}

#[derive(Clone)]
struct Binding {
    name: Name,
    value: ValueId,
    mutable: bool,
}

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
    env: Vec<Vec<Binding>>,
    const_bool: HashMap<ValueId, bool>,
    no_grad: usize,
    loop_depth: usize,
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
            loop_depth: 0,
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

    // ---- values and bindings -------------------------------------------------------------

    fn fresh(&mut self) -> ValueId {
        self.next_value += 1;
        self.next_value - 1
    }

    fn push(&mut self, out: &mut Block, op: Op, span: Span) -> ValueId {
        let id = self.fresh();
        out.stmts.push(Stmt::Let(Let { id, op, span }));
        id
    }

    fn const_flag(&mut self, b: bool, out: &mut Block) -> ValueId {
        let v = self.push(
            out,
            Op::Const(if b { quote!(true) } else { quote!(false) }),
            Span::call_site(),
        );
        self.const_bool.insert(v, b);
        v
    }

    fn bind(&mut self, name: impl Into<Name>, value: ValueId, mutable: bool) {
        self.env.last_mut().unwrap().push(Binding {
            name: name.into(),
            value,
            mutable,
        });
    }

    fn lookup(&self, name: impl Into<Name>) -> Option<&Binding> {
        let name = name.into();
        self.env
            .iter()
            .rev()
            .flat_map(|s| s.iter().rev())
            .find(|b| b.name == name)
    }

    fn lookup_mut(&mut self, name: impl Into<Name>) -> Option<&mut Binding> {
        let name = name.into();
        self.env
            .iter_mut()
            .rev()
            .flat_map(|s| s.iter_mut().rev())
            .find(|b| b.name == name)
    }

    fn assign(&mut self, name: impl Into<Name>, value: ValueId) {
        self.lookup_mut(name).expect("assign to a bound name").value = value;
    }

    fn error_value(
        &mut self,
        out: &mut Block,
        span: Span,
        msg: impl std::fmt::Display,
    ) -> Option<ValueId> {
        self.errors.push(span, msg);
        Some(self.push(out, Op::Zero, span))
    }

    fn array_param(&self, e: &Expr) -> Option<usize> {
        let Expr::Path(p) = e else { return None };
        let id = p.path.get_ident()?;
        if self.lookup(&id.to_string()).is_some() {
            return None; // shadowed by a local
        }
        let i = self.sig.param_index(&id.to_string())?;
        self.sig.params[i].is_array().then_some(i)
    }

    // ---- blocks and control flow -------------------------------------------------------

    /// Lowers statements in order; returns the value of a tail expression.
    fn lower_block_value(&mut self, stmts: &[syn::Stmt], out: &mut Block) -> Option<ValueId> {
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
    fn lower_guarded(&mut self, stmts: &[syn::Stmt], out: &mut Block) -> Option<ValueId> {
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
    fn branches(
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

    fn lower_stmt(&mut self, st: &syn::Stmt, out: &mut Block) {
        match st {
            syn::Stmt::Local(l) => self.lower_let(l, out),
            syn::Stmt::Expr(e, _) => {
                self.lower_expr(e, out);
            }
            syn::Stmt::Item(i) => self.errors.push(
                i.span(),
                "items (fn, use, const, struct ..) cannot be declared inside a kernel; declare \
                 them outside (a helper function as a #[diff_func])",
            ),
            syn::Stmt::Macro(m) => self.errors.push(m.span(), macro_message(&m.mac)),
        }
    }

    fn lower_let(&mut self, l: &syn::Local, out: &mut Block) {
        let Some(init) = &l.init else {
            self.errors
                .push(l.span(), "declare locals with a value: `let x = ...;`");
            return;
        };
        if let Some((_, d)) = &init.diverge {
            self.errors
                .push(d.span(), "`let .. else` is not supported in kernels");
            return;
        }
        let (pat, ty) = match &l.pat {
            Pat::Type(pt) => (&*pt.pat, Some(&*pt.ty)),
            p => (p, None),
        };
        let before = self.errors.len();
        let v = match self.lower_expr(&init.expr, out) {
            Some(v) => v,
            None => {
                if self.errors.len() == before {
                    let msg = if diverges(&init.expr) {
                        "a `let` cannot bind an `if` whose branch leaves with `continue`, `break` \
                         or `return` in a kernel; leave before the `let`: \
                         `if c { continue; } let x = ..;`"
                    } else {
                        "this expression has no value to bind"
                    };
                    self.errors.push(init.expr.span(), msg);
                }
                // Bind the names anyway, so that their uses give no follow-on errors.
                self.push(out, Op::Zero, init.expr.span())
            }
        };
        match pat {
            Pat::Ident(pi) if pi.by_ref.is_none() && pi.subpat.is_none() => {
                let v = match ty {
                    Some(ty) => self.push(out, Op::Typed { src: v, ty: ty.to_token_stream() }, l.span()),
                    None => v,
                };
                self.bind(&pi.ident.to_string(), v, pi.mutability.is_some());
            }
            Pat::Wild(_) => {}
            Pat::Slice(s) => {
                for (k, p) in s.elems.iter().enumerate() {
                    match p {
                        Pat::Ident(pi) if pi.by_ref.is_none() && pi.subpat.is_none() => {
                            let kv = self.push(out, Op::Const(quote!(#k)), p.span());
                            let e = self.push(out, Op::Builtin { f: Builtin::Extract, args: vec![v, kv] }, p.span());
                            self.bind(&pi.ident.to_string(), e, pi.mutability.is_some());
                        }
                        Pat::Wild(_) => {}
                        other => self.errors.push(other.span(), "destructure into names or `_` only: `let [i, j] = pairs[t];`"),
                    }
                }
            }
            other => self.errors.push(
                other.span(),
                "this pattern is not supported; bind a name (`let x = ..`) or destructure an index array (`let [i, j] = pairs[t];`)",
            ),
        }
    }

    // ---- expressions -------------------------------------------------------------------

    fn lower_expr(&mut self, e: &Expr, out: &mut Block) -> Option<ValueId> {
        let span = e.span();
        match e {
            Expr::Lit(l) => self.lower_lit(&l.lit, out),
            Expr::Path(p) => self.lower_path(p, out),
            Expr::Paren(p) => self.lower_expr(&p.expr, out),
            Expr::Group(g) => self.lower_expr(&g.expr, out),
            Expr::Binary(b) => self.lower_binary(b, out),
            Expr::Unary(u) => {
                let a = self.lower_value(&u.expr, out)?;
                match u.op {
                    UnOp::Neg(_) => Some(self.push(
                        out,
                        Op::Builtin {
                            f: Builtin::Neg,
                            args: vec![a],
                        },
                        span,
                    )),
                    UnOp::Not(_) => {
                        Some(self.push(out, Op::NativeUnary { op: quote!(!), a }, span))
                    }
                    _ => self.error_value(
                        out,
                        span,
                        "references and pointers are not supported in kernels (`*x`)",
                    ),
                }
            }
            Expr::Call(c) => self.lower_call(c, out),
            Expr::MethodCall(m) => self.lower_method(m, out),
            Expr::Index(i) => {
                if let Some(p) = self.array_param(&i.expr) {
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
                let k = match component_index(&f.member) {
                    Some(k) => k,
                    None => return self.error_value(out, f.member.span(), "only the components `.x`, `.y`, `.z`, `.w` of vectors and quaternions can be read"),
                };
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
            Expr::Block(b) => {
                if let Some(l) = &b.label {
                    return self.error_value(
                        out,
                        l.span(),
                        "labelled blocks are not supported in kernels",
                    );
                }
                self.env.push(Vec::new());
                let v = self.lower_block_value(&b.block.stmts, out);
                self.env.pop();
                v
            }
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
                if let Some(l) = &w.label {
                    self.errors
                        .push(l.span(), "loop labels are not supported in kernels");
                }
                if let Expr::Let(l) = &*w.cond {
                    self.errors
                        .push(l.span(), "`while let` is not supported in kernels");
                    return None;
                }
                self.lower_loop(None, None, &w.body, Some(&w.cond), out);
                None
            }
            Expr::Loop(l) => {
                if let Some(lb) = &l.label {
                    self.errors
                        .push(lb.span(), "loop labels are not supported in kernels");
                }
                if !exits_loop(&l.body) {
                    self.errors.push(
                        l.loop_token.span(),
                        "`loop` without `break` or `return` never ends; add a `break`, or use `for i in 0..n`",
                    );
                    return None;
                }
                self.lower_loop(None, None, &l.body, None, out);
                None
            }
            Expr::Break(b) => {
                if let Some(v) = &b.expr {
                    self.errors
                        .push(v.span(), "`break` with a value is not supported in kernels");
                    return None;
                }
                self.lower_loop_exit("break", b.label.as_ref(), Flag::Break, span, out);
                None
            }
            Expr::Continue(c) => {
                self.lower_loop_exit("continue", c.label.as_ref(), Flag::Continue, span, out);
                None
            }
            Expr::Return(r) => {
                match (&r.expr, self.kind) {
                    (Some(v), Kind::Kernel) => self
                        .errors
                        .push(v.span(), "a #[diff_kernel] returns no value; use `return;`"),
                    (None, Kind::Func) => self
                        .errors
                        .push(span, "a #[diff_func] must return a value: `return x;`"),
                    (Some(v), Kind::Func) => {
                        if let Some(v) = self.lower_value(v, out) {
                            self.assign(Name::ReturnValue, v);
                        }
                    }
                    (None, Kind::Kernel) => {}
                }
                let t = self.const_flag(true, out);
                self.assign(Flag::Return, t);
                None
            }
            Expr::Closure(c) => self.error_value(
                out,
                c.span(),
                "closures are not supported in kernels; write a #[diff_func] instead",
            ),
            Expr::Reference(r) => self.error_value(
                out,
                r.span(),
                "references are not supported in kernels; values are passed by copy",
            ),
            Expr::Macro(m) => {
                let msg = macro_message(&m.mac);
                self.error_value(out, m.span(), msg)
            }
            Expr::Tuple(t) if t.elems.is_empty() => None,
            Expr::Tuple(t) => self.error_value(
                out,
                t.span(),
                "tuples are not supported in kernels (except as a matrix index `m[(r, c)]`)",
            ),
            Expr::Array(_) | Expr::Repeat(_) => self.error_value(
                out,
                span,
                "array literals are not supported in kernels; build vectors with vec2/vec3/vec4",
            ),
            Expr::Struct(s) => self.error_value(
                out,
                s.span(),
                "struct literals are not supported in kernels",
            ),
            Expr::Range(r) => self.error_value(
                out,
                r.span(),
                "ranges are only supported as the bounds of a `for` loop",
            ),
            Expr::Let(l) => self.error_value(out, l.span(), "`if let` is not supported in kernels"),
            Expr::Try(t) => self.error_value(out, t.span(), "`?` is not supported in kernels"),
            Expr::Unsafe(u) => self.error_value(
                out,
                u.span(),
                "`unsafe` blocks are not supported in kernels",
            ),
            Expr::Async(a) => {
                self.error_value(out, a.span(), "`async` is not supported in kernels")
            }
            Expr::Await(a) => {
                self.error_value(out, a.span(), "`.await` is not supported in kernels")
            }
            other => self.error_value(
                out,
                other.span(),
                "this expression is not supported in kernels",
            ),
        }
    }

    /// Lowers an expression that must produce a value.
    fn lower_value(&mut self, e: &Expr, out: &mut Block) -> Option<ValueId> {
        let v = self.lower_expr(e, out);
        if v.is_none() {
            return self.error_value(out, e.span(), "this expression has no value");
        }
        v
    }

    fn lower_lit(&mut self, lit: &Lit, out: &mut Block) -> Option<ValueId> {
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

    fn lower_path(&mut self, p: &syn::ExprPath, out: &mut Block) -> Option<ValueId> {
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

    fn lower_binary(&mut self, b: &syn::ExprBinary, out: &mut Block) -> Option<ValueId> {
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
            BinOp::AddAssign(_)
            | BinOp::SubAssign(_)
            | BinOp::MulAssign(_)
            | BinOp::DivAssign(_)
            | BinOp::RemAssign(_)
            | BinOp::BitAndAssign(_)
            | BinOp::BitOrAssign(_)
            | BinOp::BitXorAssign(_)
            | BinOp::ShlAssign(_)
            | BinOp::ShrAssign(_) => {
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

    fn lower_call(&mut self, c: &syn::ExprCall, out: &mut Block) -> Option<ValueId> {
        let span = c.span();
        let Expr::Path(fp) = &*c.func else {
            return self.error_value(
                out,
                c.func.span(),
                "only named functions can be called in kernels",
            );
        };
        if fp.qself.is_some() {
            return self.error_value(out, fp.span(), "qualified paths (`<T as Trait>::f`) cannot be called in kernels; wrap the call in no_grad(..) if it needs no derivative");
        }
        let single = fp.path.get_ident().map(|i| i.to_string());
        match single.as_deref() {
            Some("tid") => {
                if self.kind == Kind::Func {
                    return self.error_value(out, span, "`tid()` is only available in a #[diff_kernel]; pass the index to the function");
                }
                if !c.args.is_empty() {
                    return self.error_value(out, c.args.span(), "`tid()` takes no arguments");
                }
                return Some(self.push(out, Op::Tid, span));
            }
            Some("no_grad") => {
                if c.args.len() != 1 {
                    return self.error_value(
                        out,
                        span,
                        "`no_grad` takes one expression: `no_grad(expr)`",
                    );
                }
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
        if single.is_none() {
            if c.args.is_empty() {
                // `R::zero()`, `Vec3::zeros()`: constants.
                return Some(self.push(out, Op::Const(c.to_token_stream()), span));
            }
            let first = fp
                .path
                .segments
                .first()
                .map(|s| s.ident.to_string())
                .unwrap_or_default();
            if first.chars().next().is_some_and(|ch| ch.is_uppercase()) {
                return self.error_value(
                    out,
                    span,
                    format!(
                        "`{}` is not differentiable: build values with the builtins (vec2, vec3, \
                         vec4, mat22, mat33, quat, ..), or wrap the call in no_grad(..)",
                        fp.to_token_stream().to_string().replace(' ', "")
                    ),
                );
            }
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

    fn lower_args(
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

    fn lower_method(&mut self, m: &syn::ExprMethodCall, out: &mut Block) -> Option<ValueId> {
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
        let hint = match builtins::method_hint(&method) {
            Some(h) => format!("call the builtin `{h}` instead"),
            None => "call a builtin function (see adflex::math) or wrap the call in no_grad(..)"
                .to_string(),
        };
        self.error_value(
            out,
            m.method.span(),
            format!("method calls are not differentiable in kernels: `.{method}(..)`; {hint}"),
        )
    }

    /// `break` or `continue`: sets the loop's `flag`, which guards what follows.
    fn lower_loop_exit(
        &mut self,
        keyword: &str,
        label: Option<&syn::Lifetime>,
        flag: Flag,
        span: Span,
        out: &mut Block,
    ) {
        if let Some(l) = label {
            self.errors.push(
                l.span(),
                format!("labelled `{keyword}` is not supported in kernels"),
            );
        } else if self.loop_depth == 0 {
            self.errors
                .push(span, format!("`{keyword}` outside of a loop"));
        } else {
            let t = self.const_flag(true, out);
            self.assign(flag, t);
        }
    }

    fn lower_if(&mut self, i: &syn::ExprIf, out: &mut Block) -> Option<ValueId> {
        if let Expr::Let(l) = &*i.cond {
            return self.error_value(out, l.span(), "`if let` is not supported in kernels");
        }
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

    fn lower_match(&mut self, m: &syn::ExprMatch, out: &mut Block) -> Option<ValueId> {
        let s = self.lower_value(&m.expr, out)?;
        match m.arms.last() {
            Some(a) if is_catch_all(&a.pat) && a.guard.is_none() => {}
            Some(a) => {
                return self.error_value(
                    out,
                    a.pat.span(),
                    "a `match` in a kernel must end with a `_ =>` arm",
                );
            }
            None => return self.error_value(out, m.span(), "empty `match`"),
        }
        self.lower_arms(s, &m.arms, out)
    }

    fn lower_arms(&mut self, s: ValueId, arms: &[syn::Arm], out: &mut Block) -> Option<ValueId> {
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

    fn pattern_cond(&mut self, p: &Pat, s: ValueId, out: &mut Block) -> Option<ValueId> {
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
                    return self.error_value(out, span, "match ranges need both bounds: `a..=b`");
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
            _ => self.error_value(
                out,
                span,
                "`match` in kernels takes integer literals, ranges (`a..=b`), `|` and a final `_`",
            ),
        }
    }

    // ---- assignments -------------------------------------------------------------------

    /// The index of a local's component: `v[k]`, or a matrix's `m[(r, c)]` (the one place a
    /// tuple is allowed), read or assigned.
    fn lower_component_index(&mut self, index: &Expr, out: &mut Block) -> Option<ValueId> {
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

    fn lower_assign(&mut self, lhs: &Expr, op: Option<&BinOp>, rhs: &Expr, out: &mut Block) {
        let span = lhs.span();
        let op_name = op.map(|o| match o {
            BinOp::AddAssign(_) => Ok(Builtin::Add),
            BinOp::SubAssign(_) => Ok(Builtin::Sub),
            BinOp::MulAssign(_) => Ok(Builtin::Mul),
            BinOp::DivAssign(_) => Ok(Builtin::Div),
            BinOp::RemAssign(_) => Ok(Builtin::Rem),
            other => Err(other.to_token_stream()),
        });
        // Array element stores.
        if let Expr::Index(ix) = lhs {
            if let Some(p) = self.array_param(&ix.expr) {
                let kind = match op_name {
                    None => StoreKind::Store,
                    Some(Ok(Builtin::Add)) => StoreKind::AtomicAdd,
                    Some(Ok(Builtin::Sub)) => StoreKind::AtomicSub,
                    Some(_) => {
                        let o = op.unwrap().to_token_stream();
                        self.errors.push(
                            op.unwrap().span(),
                            format!(
                                "`{o}` on an array element is not supported: it would read and \
                                 write the array; compute the new value and store it into a \
                                 separate output array (`out[i] = x[i] * s`)"
                            ),
                        );
                        return;
                    }
                };
                let Some(index) = self.lower_value(&ix.index, out) else {
                    return;
                };
                let Some(value) = self.lower_value(rhs, out) else {
                    return;
                };
                if kind == StoreKind::Store {
                    self.uses[p].store.get_or_insert(span);
                } else {
                    self.uses[p].atomic.get_or_insert(span);
                }
                out.stmts.push(Stmt::Store {
                    param: p,
                    index,
                    value,
                    kind,
                    span,
                });
                return;
            }
        }
        if let Expr::Field(f) = lhs {
            if let Expr::Index(ix) = &*f.base {
                if self.array_param(&ix.expr).is_some() {
                    self.errors.push(span, "store whole elements into arrays (`a[i] = v`); a component cannot be stored alone");
                    return;
                }
            }
        }
        // Local (or component of a local) assignments.
        let (root, component) = match lhs {
            Expr::Path(p) if p.path.get_ident().is_some() => {
                (p.path.get_ident().unwrap().clone(), None)
            }
            Expr::Field(f) => match (&*f.base, component_index(&f.member)) {
                (Expr::Path(p), Some(k)) if p.path.get_ident().is_some() => (
                    p.path.get_ident().unwrap().clone(),
                    Some(Component::Const(k, f.member.span())),
                ),
                _ => {
                    self.errors.push(
                        span,
                        "only `.x`, `.y`, `.z`, `.w` of a local vector can be assigned",
                    );
                    return;
                }
            },
            Expr::Index(ix) => match &*ix.expr {
                Expr::Path(p) if p.path.get_ident().is_some() => (
                    p.path.get_ident().unwrap().clone(),
                    Some(Component::Expr(&ix.index)),
                ),
                _ => {
                    self.errors
                        .push(span, "only components of a local vector can be assigned");
                    return;
                }
            },
            _ => {
                self.errors
                    .push(span, "cannot assign to this expression in a kernel");
                return;
            }
        };
        let name = root.to_string();
        let Some(b) = self.lookup(&name).cloned() else {
            if let Some(i) = self.sig.param_index(&name) {
                let msg = if self.sig.params[i].is_array() {
                    format!("cannot assign to array `{name}`; store elements with `{name}[i] = v`")
                } else {
                    format!("cannot store to `{name}`: it is a value parameter, not an `&Array`")
                };
                self.errors.push(span, msg);
            } else {
                self.errors
                    .push(span, format!("cannot find value `{name}` in this kernel"));
            }
            return;
        };
        if !b.mutable {
            let is_param = self.sig.param_index(&name).is_some()
                && self.env[0]
                    .iter()
                    .any(|x| x.name == Name::from(&name) && x.value == b.value);
            let msg = if is_param && component.is_some() {
                format!("cannot store to `{name}`: it is a value parameter, not an `&Array`")
            } else if is_param {
                format!(
                    "cannot assign to parameter `{name}`; declare it `mut {name}` or use a local"
                )
            } else {
                format!("cannot assign twice to immutable variable `{name}`; declare it with `let mut {name}`")
            };
            self.errors.push(span, msg);
            return;
        }
        let k = match &component {
            None => None,
            Some(Component::Const(k, s)) => Some(self.push(out, Op::Const(quote!(#k)), *s)),
            Some(Component::Expr(e)) => match self.lower_component_index(e, out) {
                Some(v) => Some(v),
                None => return,
            },
        };
        let Some(r) = self.lower_value(rhs, out) else {
            return;
        };
        let current = match k {
            None => b.value,
            Some(k) => self.push(
                out,
                Op::Builtin {
                    f: Builtin::Extract,
                    args: vec![b.value, k],
                },
                span,
            ),
        };
        let new = match op_name {
            None => r,
            Some(Ok(f)) => self.push(
                out,
                Op::Builtin {
                    f,
                    args: vec![current, r],
                },
                span,
            ),
            Some(Err(native)) => {
                let native: TokenStream = {
                    let s = native.to_string();
                    s.trim_end_matches('=').parse().unwrap()
                };
                self.push(
                    out,
                    Op::NativeBinary {
                        op: native,
                        a: current,
                        b: r,
                    },
                    span,
                )
            }
        };
        let new = match k {
            None => new,
            Some(k) => self.push(
                out,
                Op::Builtin {
                    f: Builtin::Replace,
                    args: vec![b.value, k, new],
                },
                span,
            ),
        };
        self.assign(&name, new);
    }

    // ---- loops -------------------------------------------------------------------------

    fn lower_for(&mut self, f: &syn::ExprForLoop, out: &mut Block) {
        if let Some(l) = &f.label {
            self.errors
                .push(l.span(), "loop labels are not supported in kernels");
        }
        let index_name = match &*f.pat {
            Pat::Ident(pi)
                if pi.by_ref.is_none() && pi.subpat.is_none() && pi.mutability.is_none() =>
            {
                Some(pi.ident.to_string())
            }
            Pat::Wild(_) => None,
            other => {
                self.errors.push(
                    other.span(),
                    "a `for` loop in a kernel binds a plain name: `for i in a..b`",
                );
                return;
            }
        };
        let Expr::Range(r) = &*f.expr else {
            self.errors.push(
                f.expr.span(),
                "kernels loop over integer ranges only: `for i in a..b` or `for i in a..=b`",
            );
            return;
        };
        let (Some(start), Some(end)) = (&r.start, &r.end) else {
            self.errors.push(
                r.span(),
                "a `for` range in a kernel needs both bounds: `a..b`",
            );
            return;
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

    fn lower_unrolled(
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
                s.loop_depth += 1;
                s.lower_block_value(&body.stmts, b);
                s.loop_depth -= 1;
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

    fn lower_loop(
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
        self.loop_depth += 1;
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
        self.loop_depth -= 1;
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

enum Component<'e> {
    Const(usize, Span),
    Expr(&'e Expr),
}

fn component_index(m: &syn::Member) -> Option<usize> {
    match m {
        syn::Member::Named(id) => match id.to_string().as_str() {
            "x" => Some(0),
            "y" => Some(1),
            "z" => Some(2),
            "w" => Some(3),
            _ => None,
        },
        syn::Member::Unnamed(_) => None,
    }
}

fn is_catch_all(p: &Pat) -> bool {
    matches!(p, Pat::Wild(_)) || matches!(p, Pat::Ident(pi) if pi.subpat.is_none())
}

fn int_literal(e: &Expr) -> Option<u64> {
    match e {
        Expr::Lit(syn::ExprLit {
            lit: Lit::Int(i), ..
        }) => i.base10_parse().ok(),
        Expr::Paren(p) => int_literal(&p.expr),
        Expr::Group(g) => int_literal(&g.expr),
        _ => None,
    }
}

fn macro_message(m: &syn::Macro) -> String {
    let name = m.path.to_token_stream().to_string();
    format!(
        "macro calls are not supported in kernels (`{name}!`): kernels are compiled to adjoint \
         and tangent code, which a macro would escape"
    )
}

/// Whether `stmt` may leave its block early: a `return` anywhere, or a `break`/`continue`
/// that is not inside a loop of its own.
fn may_exit(stmt: &syn::Stmt) -> bool {
    let mut v = Exits {
        depth: 0,
        found: false,
        returns: true,
    };
    v.visit_stmt(stmt);
    v.found
}

/// Whether a loop body can end its loop: a `break` for this loop or a `return`.
fn exits_loop(body: &syn::Block) -> bool {
    let mut v = Exits {
        depth: 0,
        found: false,
        returns: true,
    };
    v.visit_block(body);
    v.found
}

fn contains_return(body: &syn::Block) -> bool {
    let mut v = Returns(false);
    v.visit_block(body);
    v.0
}

struct Exits {
    depth: usize,
    found: bool,
    returns: bool,
}

impl<'ast> Visit<'ast> for Exits {
    fn visit_expr_break(&mut self, _: &'ast syn::ExprBreak) {
        if self.depth == 0 {
            self.found = true;
        }
    }
    fn visit_expr_continue(&mut self, _: &'ast syn::ExprContinue) {
        if self.depth == 0 {
            self.found = true;
        }
    }
    fn visit_expr_return(&mut self, _: &'ast syn::ExprReturn) {
        if self.returns {
            self.found = true;
        }
    }
    fn visit_expr_for_loop(&mut self, f: &'ast syn::ExprForLoop) {
        self.depth += 1;
        syn::visit::visit_expr_for_loop(self, f);
        self.depth -= 1;
    }
    fn visit_expr_while(&mut self, f: &'ast syn::ExprWhile) {
        self.depth += 1;
        syn::visit::visit_expr_while(self, f);
        self.depth -= 1;
    }
    fn visit_expr_loop(&mut self, f: &'ast syn::ExprLoop) {
        self.depth += 1;
        syn::visit::visit_expr_loop(self, f);
        self.depth -= 1;
    }
    fn visit_expr_closure(&mut self, _: &'ast syn::ExprClosure) {}
}

struct Returns(bool);
impl<'ast> Visit<'ast> for Returns {
    fn visit_expr_return(&mut self, _: &'ast syn::ExprReturn) {
        self.0 = true;
    }
    fn visit_expr_closure(&mut self, _: &'ast syn::ExprClosure) {}
}

/// Names a loop body assigns (its carried values); the return flag and value if it returns.
fn assigned_names(body: &syn::Block) -> HashSet<Name> {
    let mut v = Assigned::default();
    v.visit_block(body);
    v.names
}

#[derive(Default)]
struct Assigned {
    names: HashSet<Name>,
}

impl Assigned {
    fn root(&mut self, e: &Expr) {
        match e {
            Expr::Path(p) => {
                if let Some(id) = p.path.get_ident() {
                    self.names.insert(Name::Var(id.to_string()));
                }
            }
            Expr::Field(f) => self.root(&f.base),
            Expr::Index(i) => self.root(&i.expr),
            Expr::Paren(p) => self.root(&p.expr),
            _ => {}
        }
    }
}

impl<'ast> Visit<'ast> for Assigned {
    fn visit_expr_assign(&mut self, a: &'ast syn::ExprAssign) {
        self.root(&a.left);
        syn::visit::visit_expr_assign(self, a);
    }
    fn visit_expr_binary(&mut self, b: &'ast syn::ExprBinary) {
        if matches!(
            b.op,
            BinOp::AddAssign(_)
                | BinOp::SubAssign(_)
                | BinOp::MulAssign(_)
                | BinOp::DivAssign(_)
                | BinOp::RemAssign(_)
                | BinOp::BitAndAssign(_)
                | BinOp::BitOrAssign(_)
                | BinOp::BitXorAssign(_)
                | BinOp::ShlAssign(_)
                | BinOp::ShrAssign(_)
        ) {
            self.root(&b.left);
        }
        syn::visit::visit_expr_binary(self, b);
    }
    fn visit_expr_return(&mut self, r: &'ast syn::ExprReturn) {
        self.names.insert(Name::Flag(Flag::Return));
        self.names.insert(Name::ReturnValue);
        syn::visit::visit_expr_return(self, r);
    }
    fn visit_expr_closure(&mut self, _: &'ast syn::ExprClosure) {}
}

/// Whether a branch of this `if` (or block) ends by leaving: `continue`, `break`, `return`.
fn diverges(e: &Expr) -> bool {
    fn block_leaves(b: &syn::Block) -> bool {
        match b.stmts.last() {
            Some(syn::Stmt::Expr(e, _)) => {
                matches!(e, Expr::Continue(_) | Expr::Break(_) | Expr::Return(_)) || diverges(e)
            }
            _ => false,
        }
    }
    match e {
        Expr::If(i) => {
            block_leaves(&i.then_branch)
                || i.else_branch.as_ref().is_some_and(|(_, e)| {
                    diverges(e) || matches!(&**e, Expr::Block(b) if block_leaves(&b.block))
                })
        }
        Expr::Block(b) => block_leaves(&b.block),
        Expr::Paren(p) => diverges(&p.expr),
        _ => false,
    }
}
