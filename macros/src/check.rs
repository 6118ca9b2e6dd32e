//! Checking: every construct of a fn body outside the kernel language becomes an error at its
//! span, before anything is lowered.
//!
//! The kernel language is a subset of Rust expressions; this pass walks the body once (a
//! [`syn::visit::Visit`]) and refuses what the subset leaves out: closures, macros, references,
//! tuples (except a matrix index `m[(r, c)]`), struct and array literals, ranges outside a `for`,
//! `if let`/`while let`/`let .. else`, labels, `break` with a value or outside a loop, a `loop`
//! that never leaves, method calls outside `no_grad(..)`, `tid()` in a func, patterns other than
//! names, `_` and index arrays, and so on. It descends into what it accepts and not into what it
//! refuses, so that one mistake gives one error.
//!
//! What needs names resolved (is `x` a local, an array parameter, a builtin?) is left to
//! [`crate::lower`], which runs only on a body this pass accepts.

use syn::spanned::Spanned;
use syn::visit::Visit;
use syn::{Expr, Lit, Pat, UnOp};

use crate::syntax::{component_index, exits_loop, is_catch_all, macro_message};
use crate::{Errors, Kind};

/// Checks `body` of a kernel or function (`kind`); returns whether it is in the language.
pub fn check_body(body: &syn::Block, kind: Kind, errors: &mut Errors) -> bool {
    let before = errors.len();
    let mut c = Checker {
        kind,
        errors,
        loop_depth: 0,
        no_grad: 0,
    };
    c.visit_block(body);
    c.errors.len() == before
}

struct Checker<'a> {
    kind: Kind,
    errors: &'a mut Errors,
    /// How many loops enclose the current expression (`break` and `continue` need one).
    loop_depth: usize,
    /// How many `no_grad(..)` enclose it (plain calls and method calls are allowed there).
    no_grad: usize,
}

impl Checker<'_> {
    fn error(&mut self, span: proc_macro2::Span, msg: impl std::fmt::Display) {
        self.errors.push(span, msg);
    }

    /// The body of a loop.
    fn loop_body(&mut self, body: &syn::Block) {
        self.loop_depth += 1;
        self.visit_block(body);
        self.loop_depth -= 1;
    }

    fn loop_label(&mut self, label: &Option<syn::Label>) {
        if let Some(l) = label {
            self.error(l.span(), "loop labels are not supported in kernels");
        }
    }

    /// The index of a local's component: `v[k]`, or a matrix's `m[(r, c)]` (the one place a
    /// tuple is allowed).
    fn component_index(&mut self, index: &Expr) {
        match index {
            Expr::Tuple(t) => t.elems.iter().for_each(|e| self.visit_expr(e)),
            e => self.visit_expr(e),
        }
    }

    /// The left side of an assignment: what is assigned is resolved by lowering; here only
    /// the expressions inside it are checked.
    fn assignee(&mut self, lhs: &Expr) {
        match lhs {
            Expr::Index(ix) => self.component_index(&ix.index),
            Expr::Field(f) => {
                if let Expr::Index(ix) = &*f.base {
                    self.component_index(&ix.index);
                }
            }
            _ => {}
        }
    }

    /// `break` or `continue`.
    fn loop_exit(&mut self, keyword: &str, label: Option<&syn::Lifetime>, span: proc_macro2::Span) {
        if let Some(l) = label {
            self.error(
                l.span(),
                format!("labelled `{keyword}` is not supported in kernels"),
            );
        } else if self.loop_depth == 0 {
            self.error(span, format!("`{keyword}` outside of a loop"));
        }
    }

    fn call(&mut self, c: &syn::ExprCall) {
        let span = c.span();
        let Expr::Path(fp) = &*c.func else {
            return self.error(
                c.func.span(),
                "only named functions can be called in kernels",
            );
        };
        if fp.qself.is_some() {
            return self.error(fp.span(), "qualified paths (`<T as Trait>::f`) cannot be called in kernels; wrap the call in no_grad(..) if it needs no derivative");
        }
        match fp.path.get_ident().map(|i| i.to_string()).as_deref() {
            Some("tid") => {
                if self.kind == Kind::Func {
                    self.error(span, "`tid()` is only available in a #[diff_kernel]; pass the index to the function");
                } else if !c.args.is_empty() {
                    self.error(c.args.span(), "`tid()` takes no arguments");
                }
                return;
            }
            Some("no_grad") => {
                if c.args.len() != 1 {
                    return self.error(span, "`no_grad` takes one expression: `no_grad(expr)`");
                }
                self.no_grad += 1;
                self.visit_expr(&c.args[0]);
                self.no_grad -= 1;
                return;
            }
            // A builtin or a #[diff_func]: lowering resolves which.
            Some(_) => {}
            None if self.no_grad > 0 || c.args.is_empty() => {}
            None => {
                let first = fp
                    .path
                    .segments
                    .first()
                    .map(|s| s.ident.to_string())
                    .unwrap_or_default();
                if first.chars().next().is_some_and(|ch| ch.is_uppercase()) {
                    return self.error(
                        span,
                        format!(
                            "`{}` is not differentiable: build values with the builtins (vec2, \
                             vec3, vec4, mat22, mat33, quat, ..), or wrap the call in no_grad(..)",
                            quote::ToTokens::to_token_stream(fp)
                                .to_string()
                                .replace(' ', "")
                        ),
                    );
                }
            }
        }
        c.args.iter().for_each(|a| self.visit_expr(a));
    }

    fn method(&mut self, m: &syn::ExprMethodCall) {
        let method = m.method.to_string();
        // `a.atomic_add(i, v)`: lowering checks that `a` is an array and the arguments.
        if method == "atomic_add" || method == "atomic_sub" || self.no_grad > 0 {
            self.visit_expr(&m.receiver);
            m.args.iter().for_each(|a| self.visit_expr(a));
            return;
        }
        let hint = match crate::builtins::method_hint(&method) {
            Some(h) => format!("call the builtin `{h}` instead"),
            None => "call a builtin function (see adflex::math) or wrap the call in no_grad(..)"
                .to_string(),
        };
        self.error(
            m.method.span(),
            format!("method calls are not differentiable in kernels: `.{method}(..)`; {hint}"),
        );
    }

    fn match_expr(&mut self, m: &syn::ExprMatch) {
        self.visit_expr(&m.expr);
        match m.arms.last() {
            Some(a) if is_catch_all(&a.pat) && a.guard.is_none() => {}
            Some(a) => {
                return self.error(
                    a.pat.span(),
                    "a `match` in a kernel must end with a `_ =>` arm",
                )
            }
            None => return self.error(m.span(), "empty `match`"),
        }
        // The arms up to the first catch-all (the later ones are never reached).
        for arm in &m.arms {
            if is_catch_all(&arm.pat) && arm.guard.is_none() {
                self.visit_expr(&arm.body);
                return;
            }
            self.match_pattern(&arm.pat);
            if let Some((_, g)) = &arm.guard {
                self.visit_expr(g);
            }
            self.visit_expr(&arm.body);
        }
    }

    fn match_pattern(&mut self, p: &Pat) {
        match p {
            Pat::Lit(_) => {}
            Pat::Range(r) if r.start.is_none() || r.end.is_none() => {
                self.error(p.span(), "match ranges need both bounds: `a..=b`")
            }
            Pat::Range(_) => {}
            Pat::Or(o) => o.cases.iter().for_each(|c| self.match_pattern(c)),
            Pat::Paren(pp) => self.match_pattern(&pp.pat),
            _ => self.error(
                p.span(),
                "`match` in kernels takes integer literals, ranges (`a..=b`), `|` and a final `_`",
            ),
        }
    }

    fn for_loop(&mut self, f: &syn::ExprForLoop) {
        self.loop_label(&f.label);
        match &*f.pat {
            Pat::Ident(pi)
                if pi.by_ref.is_none() && pi.subpat.is_none() && pi.mutability.is_none() => {}
            Pat::Wild(_) => {}
            other => {
                return self.error(
                    other.span(),
                    "a `for` loop in a kernel binds a plain name: `for i in a..b`",
                )
            }
        }
        let Expr::Range(r) = &*f.expr else {
            return self.error(
                f.expr.span(),
                "kernels loop over integer ranges only: `for i in a..b` or `for i in a..=b`",
            );
        };
        let (Some(start), Some(end)) = (&r.start, &r.end) else {
            return self.error(
                r.span(),
                "a `for` range in a kernel needs both bounds: `a..b`",
            );
        };
        self.visit_expr(start);
        self.visit_expr(end);
        self.loop_body(&f.body);
    }
}

impl<'ast> Visit<'ast> for Checker<'_> {
    fn visit_stmt(&mut self, st: &'ast syn::Stmt) {
        match st {
            syn::Stmt::Local(l) => self.visit_local(l),
            syn::Stmt::Expr(e, _) => self.visit_expr(e),
            syn::Stmt::Item(i) => self.error(
                i.span(),
                "items (fn, use, const, struct ..) cannot be declared inside a kernel; declare \
                 them outside (a helper function as a #[diff_func])",
            ),
            syn::Stmt::Macro(m) => self.error(m.span(), macro_message(&m.mac)),
        }
    }

    fn visit_local(&mut self, l: &'ast syn::Local) {
        let Some(init) = &l.init else {
            return self.error(l.span(), "declare locals with a value: `let x = ...;`");
        };
        if let Some((_, d)) = &init.diverge {
            return self.error(d.span(), "`let .. else` is not supported in kernels");
        }
        self.visit_expr(&init.expr);
        let pat = match &l.pat {
            Pat::Type(pt) => &*pt.pat,
            p => p,
        };
        match pat {
            Pat::Ident(pi) if pi.by_ref.is_none() && pi.subpat.is_none() => {}
            Pat::Wild(_) => {}
            Pat::Slice(s) => {
                for p in &s.elems {
                    match p {
                        Pat::Ident(pi) if pi.by_ref.is_none() && pi.subpat.is_none() => {}
                        Pat::Wild(_) => {}
                        other => self.error(
                            other.span(),
                            "destructure into names or `_` only: `let [i, j] = pairs[t];`",
                        ),
                    }
                }
            }
            other => self.error(
                other.span(),
                "this pattern is not supported; bind a name (`let x = ..`) or destructure an index array (`let [i, j] = pairs[t];`)",
            ),
        }
    }

    fn visit_expr(&mut self, e: &'ast Expr) {
        let span = e.span();
        match e {
            Expr::Lit(l) => match &l.lit {
                Lit::Float(_) | Lit::Int(_) | Lit::Bool(_) => {}
                lit => self.error(
                    lit.span(),
                    "only numeric and boolean literals are supported in kernels",
                ),
            },
            Expr::Path(_) => {} // resolved by lowering
            Expr::Paren(p) => self.visit_expr(&p.expr),
            Expr::Group(g) => self.visit_expr(&g.expr),
            Expr::Binary(b) if crate::syntax::is_compound_assign(&b.op) => {
                self.assignee(&b.left);
                self.visit_expr(&b.right);
            }
            Expr::Binary(b) => {
                self.visit_expr(&b.left);
                self.visit_expr(&b.right);
            }
            Expr::Unary(u) => {
                self.visit_expr(&u.expr);
                if !matches!(u.op, UnOp::Neg(_) | UnOp::Not(_)) {
                    self.error(
                        span,
                        "references and pointers are not supported in kernels (`*x`)",
                    );
                }
            }
            Expr::Call(c) => self.call(c),
            Expr::MethodCall(m) => self.method(m),
            Expr::Index(i) => {
                self.visit_expr(&i.expr);
                self.component_index(&i.index);
            }
            Expr::Field(f) => match component_index(&f.member) {
                Some(_) => self.visit_expr(&f.base),
                None => self.error(
                    f.member.span(),
                    "only the components `.x`, `.y`, `.z`, `.w` of vectors and quaternions can be read",
                ),
            },
            Expr::Cast(c) => self.visit_expr(&c.expr),
            Expr::If(i) => {
                if let Expr::Let(l) = &*i.cond {
                    return self.error(l.span(), "`if let` is not supported in kernels");
                }
                self.visit_expr(&i.cond);
                self.visit_block(&i.then_branch);
                if let Some((_, e)) = &i.else_branch {
                    self.visit_expr(e);
                }
            }
            Expr::Block(b) => match &b.label {
                Some(l) => self.error(l.span(), "labelled blocks are not supported in kernels"),
                None => self.visit_block(&b.block),
            },
            Expr::Match(m) => self.match_expr(m),
            Expr::Assign(a) => {
                self.assignee(&a.left);
                self.visit_expr(&a.right);
            }
            Expr::ForLoop(f) => self.for_loop(f),
            Expr::While(w) => {
                self.loop_label(&w.label);
                if let Expr::Let(l) = &*w.cond {
                    return self.error(l.span(), "`while let` is not supported in kernels");
                }
                self.loop_depth += 1;
                self.visit_expr(&w.cond);
                self.loop_depth -= 1;
                self.loop_body(&w.body);
            }
            Expr::Loop(l) => {
                self.loop_label(&l.label);
                if !exits_loop(&l.body) {
                    return self.error(
                        l.loop_token.span(),
                        "`loop` without `break` or `return` never ends; add a `break`, or use `for i in 0..n`",
                    );
                }
                self.loop_body(&l.body);
            }
            Expr::Break(b) => match &b.expr {
                Some(v) => self.error(
                    v.span(),
                    "`break` with a value is not supported in kernels",
                ),
                None => self.loop_exit("break", b.label.as_ref(), span),
            },
            Expr::Continue(c) => self.loop_exit("continue", c.label.as_ref(), span),
            Expr::Return(r) => match (&r.expr, self.kind) {
                (Some(v), Kind::Kernel) => {
                    self.error(v.span(), "a #[diff_kernel] returns no value; use `return;`")
                }
                (None, Kind::Func) => {
                    self.error(span, "a #[diff_func] must return a value: `return x;`")
                }
                (Some(v), Kind::Func) => self.visit_expr(v),
                (None, Kind::Kernel) => {}
            },
            Expr::Closure(c) => self.error(
                c.span(),
                "closures are not supported in kernels; write a #[diff_func] instead",
            ),
            Expr::Reference(r) => self.error(
                r.span(),
                "references are not supported in kernels; values are passed by copy",
            ),
            Expr::Macro(m) => self.error(m.span(), macro_message(&m.mac)),
            Expr::Tuple(t) if t.elems.is_empty() => {}
            Expr::Tuple(t) => self.error(
                t.span(),
                "tuples are not supported in kernels (except as a matrix index `m[(r, c)]`)",
            ),
            Expr::Array(_) | Expr::Repeat(_) => self.error(
                span,
                "array literals are not supported in kernels; build vectors with vec2/vec3/vec4",
            ),
            Expr::Struct(s) => {
                self.error(s.span(), "struct literals are not supported in kernels")
            }
            Expr::Range(r) => self.error(
                r.span(),
                "ranges are only supported as the bounds of a `for` loop",
            ),
            Expr::Let(l) => self.error(l.span(), "`if let` is not supported in kernels"),
            Expr::Try(t) => self.error(t.span(), "`?` is not supported in kernels"),
            Expr::Unsafe(u) => {
                self.error(u.span(), "`unsafe` blocks are not supported in kernels")
            }
            Expr::Async(a) => self.error(a.span(), "`async` is not supported in kernels"),
            Expr::Await(a) => self.error(a.span(), "`.await` is not supported in kernels"),
            other => self.error(other.span(), "this expression is not supported in kernels"),
        }
    }
}
