//! Lowering of statements that bind or write: `let` (names and index-array destructuring),
//! assignments to locals and their components, and stores into array parameters.

use proc_macro2::{Span, TokenStream};
use quote::{quote, ToTokens};
use syn::spanned::Spanned;
use syn::{BinOp, Expr, Pat};

use super::scope::Name;
use super::Lowerer;
use crate::ir::*;
use crate::syntax::{component_index, diverges};

impl Lowerer<'_> {
    pub(super) fn lower_stmt(&mut self, st: &syn::Stmt, out: &mut Block) {
        match st {
            syn::Stmt::Local(l) => self.lower_let(l, out),
            syn::Stmt::Expr(e, _) => {
                self.lower_expr(e, out);
            }
            // Items and macros were refused by check.
            syn::Stmt::Item(_) | syn::Stmt::Macro(_) => {}
        }
    }

    /// `let x = e;`, `let x: T = e;`, `let [i, j] = e;` (check refused the other patterns).
    pub(super) fn lower_let(&mut self, l: &syn::Local, out: &mut Block) {
        let Some(init) = &l.init else { return }; // refused by check
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
            Pat::Ident(pi) => {
                let v = match ty {
                    Some(ty) => self.push(
                        out,
                        Op::Typed {
                            src: v,
                            ty: ty.to_token_stream(),
                        },
                        l.span(),
                    ),
                    None => v,
                };
                self.bind(&pi.ident.to_string(), v, pi.mutability.is_some());
            }
            Pat::Slice(s) => {
                for (k, p) in s.elems.iter().enumerate() {
                    if let Pat::Ident(pi) = p {
                        let kv = self.push(out, Op::Const(quote!(#k)), p.span());
                        let e = self.push(
                            out,
                            Op::Builtin {
                                f: Builtin::Extract,
                                args: vec![v, kv],
                            },
                            p.span(),
                        );
                        self.bind(&pi.ident.to_string(), e, pi.mutability.is_some());
                    }
                }
            }
            _ => {} // `_`
        }
    }

    /// `lhs = rhs` (`op` is `None`) or `lhs op= rhs`: a store into an array element, or a
    /// new value for a local or one of its components.
    pub(super) fn lower_assign(
        &mut self,
        lhs: &Expr,
        op: Option<&BinOp>,
        rhs: &Expr,
        out: &mut Block,
    ) {
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
                    .any(|x| matches!(&x.name, Name::Var(n) if *n == name) && x.value == b.value);
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
}

enum Component<'e> {
    Const(usize, Span),
    Expr(&'e Expr),
}
