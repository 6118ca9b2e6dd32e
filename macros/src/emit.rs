//! Emission: the SSA body becomes the forward, adjoint and tangent code.
//!
//! - Forward: the statements as written.
//! - Adjoint of a block: replay the block's forward (no stores), declaring an adjoint `a<N>`
//!   beside every value; seed; then walk the statements backward applying each op's rule
//!   (`adj_<op>` in `adflex_runtime::__codegen`). A nested `if` replays and reverses its taken
//!   branch. A dynamic loop's replay pushes each iteration's carried values (and index) on a
//!   stack; its reverse pops them, replays that iteration's body and reverses it, so no
//!   iteration is ever replayed with another iteration's values.
//! - Tangent: the forward with a tangent `d<N>` beside every value (`tan_<op>` rules).
//!
//! Forward and adjoint code is built as [`Piece`]s, rendered here for one thread id and by
//! [`crate::lanes`] for two interleaved.

use std::cell::Cell;
use std::collections::HashSet;

use proc_macro2::{Ident, Span, TokenStream};
use quote::{format_ident, quote, quote_spanned};

use crate::ir::*;

pub struct Emitter<'a> {
    pub rt: &'a TokenStream,
    /// Values some statement uses; an unused placeholder (`Op::Zero`) is not emitted, since
    /// nothing would give it a type.
    used: HashSet<ValueId>,
    /// Scatters emitted so far (numbers them).
    sites: Cell<usize>,
    /// The thread id this emitter names its locals for: `None` for the one id of a loop
    /// iteration, `Some(lane)` for one of the two ids of [`crate::lanes`] (suffix `_l<lane>`).
    lane: Option<usize>,
}

/// Generated code as a tree: straight-line statements, and the `if`s and gradient scatters
/// that code for two interleaved thread ids treats apart ([`crate::lanes`]).
pub enum Piece {
    /// Statements of one thread id (its locals named by the [`Emitter`] that made them).
    Code(TokenStream),
    /// `view.add(index, value);` into a gradient, numbered `site` in emission order.
    Scatter {
        site: usize,
        view: Ident,
        index: Ident,
        value: Ident,
        span: Span,
    },
    /// A replayed `if`: `let (outs,) = if cond { then (then_vals,) } else { else (else_vals,) };`
    Phi {
        cond: Ident,
        outs: Vec<Ident>,
        then: Vec<Piece>,
        then_vals: Vec<Ident>,
        els: Vec<Piece>,
        else_vals: Vec<Ident>,
    },
    /// A reversed `if`: `if cond { then } else { els }`.
    Branch {
        cond: Ident,
        then: Vec<Piece>,
        els: Vec<Piece>,
    },
}

/// How [`render_as`] writes a gradient scatter of one thread id.
pub trait Scatters {
    fn scatter(
        &self,
        site: usize,
        view: &Ident,
        index: &Ident,
        value: &Ident,
        span: Span,
    ) -> TokenStream;
}

/// Scatters where they stand.
struct InPlace;

impl Scatters for InPlace {
    fn scatter(&self, _: usize, view: &Ident, i: &Ident, x: &Ident, span: Span) -> TokenStream {
        quote_spanned!(span=> #view.add(#i, #x);)
    }
}

/// The code of `pieces` for one thread id.
pub fn render(pieces: &[Piece]) -> TokenStream {
    render_as(pieces, &InPlace)
}

/// The code of `pieces` for one thread id, its scatters written as `scatters` says.
pub fn render_as(pieces: &[Piece], scatters: &dyn Scatters) -> TokenStream {
    pieces
        .iter()
        .map(|p| match p {
            Piece::Code(c) => c.clone(),
            Piece::Scatter {
                site,
                view,
                index,
                value,
                span,
            } => scatters.scatter(*site, view, index, value, *span),
            Piece::Phi {
                cond,
                outs,
                then,
                then_vals,
                els,
                else_vals,
            } => {
                let (tb, eb) = (render_as(then, scatters), render_as(els, scatters));
                quote!(let (#(#outs,)*) = if #cond { #tb (#(#then_vals,)*) } else { #eb (#(#else_vals,)*) };)
            }
            Piece::Branch { cond, then, els } => {
                let (tb, eb) = (render_as(then, scatters), render_as(els, scatters));
                quote!(if #cond { #tb } else { #eb })
            }
        })
        .collect()
}

impl<'a> Emitter<'a> {
    pub fn new(rt: &'a TokenStream, body: &crate::ir::Body) -> Self {
        let mut used = HashSet::new();
        used.extend(body.ret);
        collect_uses(&body.block, &mut used);
        Emitter {
            rt,
            used,
            sites: Cell::new(0),
            lane: None,
        }
    }

    /// This emitter for thread id `lane` (0 or 1) of two per iteration ([`crate::lanes`]):
    /// every local of the thread (values, adjoints, the thread id) named with the suffix
    /// `_l<lane>`, the views shared; scatter sites numbered from 0 again, so that both ids
    /// number theirs alike.
    pub fn for_lane(&self, lane: usize) -> Self {
        Emitter {
            rt: self.rt,
            used: self.used.clone(),
            sites: Cell::new(0),
            lane: Some(lane),
        }
    }

    fn skip(&self, l: &Let) -> bool {
        matches!(l.op, Op::Zero) && !self.used.contains(&l.id)
    }
}

fn collect_uses(b: &Block, used: &mut HashSet<ValueId>) {
    for s in &b.stmts {
        match s {
            Stmt::Let(l) => used.extend(l.op.operands()),
            Stmt::Store { index, value, .. } => used.extend([*index, *value]),
            Stmt::If {
                cond,
                then_b,
                else_b,
                phis,
            } => {
                used.insert(*cond);
                for p in phis {
                    used.extend([p.then_v, p.else_v]);
                }
                collect_uses(then_b, used);
                collect_uses(else_b, used);
            }
            Stmt::Loop(l) => {
                if let Some((s, e, _)) = l.range {
                    used.extend([s, e]);
                }
                used.extend(l.exit);
                for c in &l.carried {
                    used.extend([c.init, c.next]);
                }
                collect_uses(&l.body, used);
            }
        }
    }
}

/// A local of the generated code, named `prefix` then `n` (and `_l<lane>` for one of two ids,
/// see [`Emitter::for_lane`]).
fn local(prefix: &str, n: impl std::fmt::Display, lane: Option<usize>, span: Span) -> Ident {
    let name = match lane {
        None => format!("{prefix}{n}"),
        Some(l) => format!("{prefix}{n}_l{l}"),
    };
    Ident::new(&name, Span::mixed_site().located_at(span))
}
/// The view of array parameter `p` (reader, writer or scatter; shared by both ids of a pair).
pub fn view(p: usize) -> Ident {
    local("__view", p, None, Span::call_site())
}
/// The view of the gradient of array parameter `p`.
pub fn grad_view(p: usize) -> Ident {
    local("__grad", p, None, Span::call_site())
}
/// The view of the tangent of array parameter `p`.
pub fn tangent_view(p: usize) -> Ident {
    local("__tangent", p, None, Span::call_site())
}

/// The names of one thread id's locals.
impl Emitter<'_> {
    /// A local of this emitter's thread id.
    fn local(&self, prefix: &str, n: impl std::fmt::Display) -> Ident {
        local(prefix, n, self.lane, Span::call_site())
    }
    fn v(&self, n: ValueId) -> Ident {
        self.local("v", n)
    }
    fn a(&self, n: ValueId) -> Ident {
        self.local("a", n)
    }
    fn d(&self, n: ValueId) -> Ident {
        self.local("d", n)
    }
    /// The thread id.
    pub fn tid(&self) -> Ident {
        self.local("__tid", "")
    }
    fn vs(&self, ids: &[ValueId]) -> Vec<Ident> {
        ids.iter().map(|&i| self.v(i)).collect()
    }
    fn ds(&self, ids: &[ValueId]) -> Vec<Ident> {
        ids.iter().map(|&i| self.d(i)).collect()
    }
    /// The arguments of a rule call, located at the user's expression: a type error in them
    /// (`dot(f64, Vec3)`) points there, not at the attribute.
    fn vs_at(&self, ids: &[ValueId], span: Span) -> Vec<Ident> {
        ids.iter()
            .map(|&i| local("v", i, self.lane, span))
            .collect()
    }
    fn ds_at(&self, ids: &[ValueId], span: Span) -> Vec<Ident> {
        ids.iter()
            .map(|&i| local("d", i, self.lane, span))
            .collect()
    }
    /// The identifiers of a value, its adjoint and its tangent (for the item assembly).
    pub fn names(&self, x: ValueId) -> (Ident, Ident, Ident) {
        (self.v(x), self.a(x), self.d(x))
    }
    fn pair(&self, x: ValueId) -> TokenStream {
        let (x, dx) = (self.v(x), self.d(x));
        quote!((#x, #dx))
    }
    /// `view.store(i, x)`, `view.add(i, x)` or `view.sub(i, x)`: a write of the forward
    /// (values) or of the tangent (tangents), through the matching view.
    fn store_call(
        &self,
        view: Ident,
        kind: StoreKind,
        i: Ident,
        x: Ident,
        span: Span,
    ) -> TokenStream {
        let t = self.tid();
        match kind {
            StoreKind::Store => quote_spanned!(span=> #view.store(#t, #i, #x);),
            StoreKind::AtomicAdd => quote_spanned!(span=> #view.add(#i, #x);),
            StoreKind::AtomicSub => quote_spanned!(span=> #view.sub(#i, #x);),
        }
    }
    /// `if exit { break; }` after a loop body whose `break` or `return` set the exit flag.
    fn loop_exit(&self, l: &Loop) -> TokenStream {
        match l.exit {
            Some(x) => {
                let x = self.v(x);
                quote!(if #x { break; })
            }
            None => quote!(),
        }
    }
}

/// The `DiffFunc` a call `path(..)` calls: what `path` names in the user's scope *as a type*,
/// so that a `#[diff_func]` (a unit struct) and a builtin (a braced struct of the runtime's
/// prelude, beside the function of the same name) resolve alike, and the user's own function
/// shadows the prelude's builtin where Rust says it does.
fn func_value(path: &TokenStream, span: Span) -> TokenStream {
    let path = located(path, span);
    quote_spanned!(span=> <#path as ::core::default::Default>::default())
}

/// `tokens` located at `span` (hygiene unchanged), for paths such as the runtime's.
fn located(tokens: &TokenStream, span: Span) -> TokenStream {
    tokens
        .clone()
        .into_iter()
        .map(|t| match t {
            proc_macro2::TokenTree::Group(g) => {
                let mut n = proc_macro2::Group::new(g.delimiter(), located(&g.stream(), span));
                n.set_span(g.span().located_at(span));
                proc_macro2::TokenTree::Group(n)
            }
            mut other => {
                other.set_span(other.span().located_at(span));
                other
            }
        })
        .collect()
}

#[derive(Clone, Copy, PartialEq)]
enum Replay {
    /// The kernel as written: with stores.
    Forward,
    /// Inside an adjoint, at the level being reversed: no stores, adjoints declared, loops
    /// recorded.
    Top,
    /// Inside an adjoint, nested below that level: no stores, nothing declared or recorded.
    Nested,
}

impl<'a> Emitter<'a> {
    /// The forward value of `op`.
    fn value_expr(&self, op: &Op, span: Span) -> TokenStream {
        let rt = self.rt;
        match op {
            Op::Const(t) => t.clone(),
            Op::Tid => {
                let t = self.tid();
                quote!(#t)
            }
            Op::Builtin { f, args } => {
                let f = Ident::new(f.name(), span);
                let (rt, args) = (located(rt, span), self.vs_at(args, span));
                quote_spanned!(span=> #rt::__codegen::#f(#(#args),*))
            }
            Op::Func { path, args } => {
                let args = self.vs(args);
                {
                    let f = func_value(path, span);
                    quote_spanned!(span=> #rt::func::call((#(#args,)*), &#f))
                }
            }
            Op::Cast { arg, ty } => {
                let x = self.v(*arg);
                quote_spanned!(span=> #rt::__codegen::cast::<_, #ty>(#x))
            }
            Op::Typed { src, .. } => {
                let x = self.v(*src);
                quote!(#x)
            }
            Op::NativeBinary { op, a: x, b: y } => {
                let (x, y) = (self.v(*x), self.v(*y));
                quote_spanned!(span=> (#x #op #y))
            }
            Op::NativeUnary { op, a: x } => {
                let x = self.v(*x);
                quote_spanned!(span=> (#op #x))
            }
            Op::Tuple(items) => {
                let items = self.vs(items);
                quote!((#(#items),*))
            }
            Op::Read { param, index } => {
                let (r, i) = (view(*param), self.v(*index));
                quote_spanned!(span=> #r.get(#i))
            }
            Op::StopGrad(x) => {
                let x = self.v(*x);
                quote!(#x)
            }
            Op::Zero => quote!(#rt::Value::zeroed()),
            Op::PlainCall { path, args } => {
                let args = self.vs(args);
                quote_spanned!(span=> #path(#(#args),*))
            }
            Op::PlainMethod { recv, method, args } => {
                let (r, args) = (self.v(*recv), self.vs(args));
                quote_spanned!(span=> #r.#method(#(#args),*))
            }
        }
    }

    fn let_stmt(&self, l: &Let) -> TokenStream {
        let (x, e) = (self.v(l.id), self.value_expr(&l.op, l.span));
        match &l.op {
            Op::Typed { ty, .. } => quote!(let #x: #ty = #e;),
            _ => quote!(let #x = #e;),
        }
    }

    /// The forward code of `lets` alone (the static scatter indices, see
    /// [`crate::ir::Body::static_indices`]).
    pub fn lets(&self, lets: &[&Let]) -> TokenStream {
        lets.iter().map(|l| self.let_stmt(l)).collect()
    }

    // ---- forward ---------------------------------------------------------------------

    /// The forward code of a block (with stores).
    pub fn forward(&self, b: &Block) -> TokenStream {
        render(&self.replay(b, Replay::Forward))
    }

    fn replay(&self, b: &Block, mode: Replay) -> Vec<Piece> {
        let rt = self.rt;
        let mut out = Vec::new();
        for s in &b.stmts {
            match s {
                Stmt::Let(l) if self.skip(l) => {}
                Stmt::Let(l) => {
                    let mut code = self.let_stmt(l);
                    if mode == Replay::Top {
                        let (x, ax) = (self.v(l.id), self.a(l.id));
                        code.extend(quote!(let mut #ax = #rt::zero_like(&#x);));
                    }
                    out.push(Piece::Code(code));
                }
                Stmt::Store {
                    param,
                    index,
                    value,
                    kind,
                    span,
                } => {
                    if mode == Replay::Forward {
                        let store = self.store_call(
                            view(*param),
                            *kind,
                            self.v(*index),
                            self.v(*value),
                            *span,
                        );
                        out.push(Piece::Code(store));
                    }
                }
                Stmt::If {
                    cond,
                    then_b,
                    else_b,
                    phis,
                } => {
                    let inner = if mode == Replay::Forward {
                        Replay::Forward
                    } else {
                        Replay::Nested
                    };
                    out.push(Piece::Phi {
                        cond: self.v(*cond),
                        outs: phis.iter().map(|p| self.v(p.out)).collect(),
                        then: self.replay(then_b, inner),
                        then_vals: phis.iter().map(|p| self.v(p.then_v)).collect(),
                        els: self.replay(else_b, inner),
                        else_vals: phis.iter().map(|p| self.v(p.else_v)).collect(),
                    });
                    if mode == Replay::Top {
                        let decls = phis.iter().map(|p| {
                            let (x, ax) = (self.v(p.out), self.a(p.out));
                            quote!(let mut #ax = #rt::zero_like(&#x);)
                        });
                        out.push(Piece::Code(quote!(#(#decls)*)));
                    }
                }
                Stmt::Loop(l) => out.push(Piece::Code(self.loop_forward(l, mode))),
            }
        }
        out
    }

    fn loop_header(&self, l: &Loop, k: &Ident) -> TokenStream {
        match l.range {
            Some((s, e, false)) => {
                let (s, e) = (self.v(s), self.v(e));
                quote!(for #k in #s..#e)
            }
            Some((s, e, true)) => {
                let (s, e) = (self.v(s), self.v(e));
                quote!(for #k in #s..=#e)
            }
            None => quote!(loop),
        }
    }

    fn loop_forward(&self, l: &Loop, mode: Replay) -> TokenStream {
        let rt = self.rt;
        let inner_mode = if mode == Replay::Forward {
            Replay::Forward
        } else {
            Replay::Nested
        };
        let c = self.local("__carry", l.id);
        let st = self.local("__stack", l.id);
        let k = self.local("__k", l.id);
        let inits: Vec<_> = l.carried.iter().map(|c| self.v(c.init)).collect();
        let inners: Vec<_> = l.carried.iter().map(|c| self.v(c.inner)).collect();
        let nexts: Vec<_> = l.carried.iter().map(|c| self.v(c.next)).collect();
        let outs: Vec<_> = l.carried.iter().map(|c| self.v(c.out)).collect();
        let header = self.loop_header(l, &k);
        let index = match l.index {
            Some(i) => {
                let i = self.v(i);
                quote!(let #i = #k;)
            }
            None => quote!(),
        };
        let record = if mode == Replay::Top {
            let key = if l.range.is_some() {
                quote!(#k)
            } else {
                quote!(())
            };
            quote!(#st.push((#key, #c));)
        } else {
            quote!()
        };
        let body = render(&self.replay(&l.body, inner_mode));
        let exit = self.loop_exit(l);
        let stack_decl = if mode == Replay::Top {
            quote!(let mut #st = ::std::vec::Vec::new();)
        } else {
            quote!()
        };
        let adj_outs = if mode == Replay::Top {
            let decl = l.carried.iter().map(|c| {
                let (x, ax) = (self.v(c.out), self.a(c.out));
                quote!(let mut #ax = #rt::zero_like(&#x);)
            });
            quote!(#(#decl)*)
        } else {
            quote!()
        };
        quote! {
            #stack_decl
            let mut #c = (#(#inits,)*);
            #header {
                #record
                #index
                let (#(#inners,)*) = #c;
                #body
                #c = (#(#nexts,)*);
                #exit
            }
            let (#(#outs,)*) = #c;
            #adj_outs
        }
    }

    // ---- adjoint ---------------------------------------------------------------------

    /// The adjoint of a block: replay, seed `adj(value) += seed`, reverse.
    pub fn adjoint(&self, b: &Block, seeds: &[(ValueId, TokenStream)]) -> TokenStream {
        render(&self.adjoint_pieces(b, seeds))
    }

    /// [`Emitter::adjoint`] as pieces.
    pub fn adjoint_pieces(&self, b: &Block, seeds: &[(ValueId, TokenStream)]) -> Vec<Piece> {
        let rt = self.rt;
        let mut out = self.replay(b, Replay::Top);
        let seeds = seeds.iter().map(|(x, s)| {
            let ax = self.a(*x);
            quote!(#rt::acc(&mut #ax, #s);)
        });
        out.push(Piece::Code(quote!(#(#seeds)*)));
        for s in b.stmts.iter().rev() {
            self.reverse(s, &mut out);
        }
        out
    }

    fn reverse(&self, s: &Stmt, out: &mut Vec<Piece>) {
        let rt = self.rt;
        match s {
            Stmt::Let(l) if self.skip(l) => {}
            Stmt::Let(l) => out.push(self.reverse_let(l)),
            Stmt::Store {
                param,
                index,
                value,
                kind,
                span,
            } => {
                let (g, i, ax) = (grad_view(*param), self.v(*index), self.a(*value));
                let t = self.tid();
                out.push(Piece::Code(match kind {
                    // Takes the gradient: an earlier store to the element was overwritten.
                    StoreKind::Store => {
                        quote_spanned!(*span=> #rt::acc(&mut #ax, #g.take(#t, #i));)
                    }
                    StoreKind::AtomicAdd => {
                        quote_spanned!(*span=> #rt::acc(&mut #ax, #g.get(#i));)
                    }
                    StoreKind::AtomicSub => {
                        quote_spanned!(*span=> #rt::acc_neg(&mut #ax, #g.get(#i));)
                    }
                }));
            }
            Stmt::If {
                cond,
                then_b,
                else_b,
                phis,
            } => {
                let tseeds: Vec<_> = phis
                    .iter()
                    .map(|p| (p.then_v, self.adj_tokens(p.out)))
                    .collect();
                let eseeds: Vec<_> = phis
                    .iter()
                    .map(|p| (p.else_v, self.adj_tokens(p.out)))
                    .collect();
                out.push(Piece::Branch {
                    cond: self.v(*cond),
                    then: self.adjoint_pieces(then_b, &tseeds),
                    els: self.adjoint_pieces(else_b, &eseeds),
                });
            }
            Stmt::Loop(l) => out.push(Piece::Code(self.reverse_loop(l))),
        }
    }

    fn adj_tokens(&self, x: ValueId) -> TokenStream {
        let ax = self.a(x);
        quote!(#ax)
    }

    fn reverse_let(&self, l: &Let) -> Piece {
        let rt = self.rt;
        let span = l.span;
        let an = self.a(l.id);
        if let Op::Read { param, index } = &l.op {
            let site = self.sites.get();
            self.sites.set(site + 1);
            return Piece::Scatter {
                site,
                view: grad_view(*param),
                index: self.v(*index),
                value: an,
                span,
            };
        }
        Piece::Code(match &l.op {
            Op::Builtin { args, .. } if args.is_empty() => quote!(),
            Op::Builtin { f, args } => {
                let f = format_ident!("adj_{}", f.name(), span = span);
                let xs = self.vs_at(args, span);
                let rt = &located(rt, span);
                if args.len() == 1 {
                    let ax = self.a(args[0]);
                    quote_spanned!(span=> #rt::acc(&mut #ax, #rt::__codegen::#f(#(#xs,)* #an));)
                } else {
                    let gs: Vec<_> = (0..args.len()).map(|i| self.local("__g", i)).collect();
                    let axs = args.iter().map(|&x| self.a(x));
                    quote_spanned! {span=>
                        let (#(#gs,)*) = #rt::__codegen::#f(#(#xs,)* #an);
                        #(#rt::acc(&mut #axs, #gs);)*
                    }
                }
            }
            Op::Func { path, args } => {
                let xs = self.vs(args);
                let f = func_value(path, span);
                let gs: Vec<_> = (0..args.len()).map(|i| self.local("__g", i)).collect();
                let axs = args.iter().map(|&x| self.a(x));
                quote_spanned! {span=>
                    let (#(#gs,)*) = #rt::func::call_adjoint((#(#xs,)*), #an, &#f);
                    #(#rt::acc(&mut #axs, #gs);)*
                }
            }
            Op::Cast { arg, ty } => {
                let (x, ax) = (self.v(*arg), self.a(*arg));
                quote_spanned!(span=> #rt::acc(&mut #ax, #rt::__codegen::adj_cast::<_, #ty>(#x, #an));)
            }
            Op::Typed { src, .. } => {
                let ax = self.a(*src);
                quote!(#rt::acc(&mut #ax, #an);)
            }
            _ => quote!(),
        })
    }

    fn reverse_loop(&self, l: &Loop) -> TokenStream {
        let rt = self.rt;
        let st = self.local("__stack", l.id);
        let ac = self.local("__adj_carry", l.id);
        let k = self.local("__k", l.id);
        let cin = self.local("__carry_in", l.id);
        let adj_outs: Vec<_> = l.carried.iter().map(|c| self.a(c.out)).collect();
        let inners: Vec<_> = l.carried.iter().map(|c| self.v(c.inner)).collect();
        let adj_inners: Vec<_> = l.carried.iter().map(|c| self.a(c.inner)).collect();
        let adj_inits: Vec<_> = l.carried.iter().map(|c| self.a(c.init)).collect();
        let index = match l.index {
            Some(i) => {
                let (x, ax) = (self.v(i), self.a(i));
                quote!(let #x = #k; let mut #ax = #rt::zero_like(&#x);)
            }
            None => quote!(let _ = #k;),
        };
        let seeds: Vec<_> = l
            .carried
            .iter()
            .enumerate()
            .map(|(n, c)| {
                let n = syn::Index::from(n);
                (c.next, quote!(#ac.#n))
            })
            .collect();
        let body = self.adjoint(&l.body, &seeds);
        let idx: Vec<_> = (0..l.carried.len()).map(syn::Index::from).collect();
        quote! {
            let mut #ac = (#(#adj_outs,)*);
            while let ::std::option::Option::Some((#k, #cin)) = #st.pop() {
                #index
                let (#(#inners,)*) = #cin;
                #(let mut #adj_inners = #rt::zero_like(&#inners);)*
                #body
                #ac = (#(#adj_inners,)*);
            }
            #(#rt::acc(&mut #adj_inits, #ac.#idx);)*
        }
    }

    // ---- tangent ---------------------------------------------------------------------

    /// The tangent code of a block: every value with its tangent.
    pub fn tangent(&self, b: &Block) -> TokenStream {
        let rt = self.rt;
        let mut out = TokenStream::new();
        for s in &b.stmts {
            match s {
                Stmt::Let(l) if self.skip(l) => {}
                Stmt::Let(l) => out.extend(self.tangent_let(l)),
                Stmt::Store {
                    param,
                    index,
                    value,
                    kind,
                    span,
                } => {
                    out.extend(self.store_call(
                        tangent_view(*param),
                        *kind,
                        self.v(*index),
                        self.d(*value),
                        *span,
                    ));
                }
                Stmt::If {
                    cond,
                    then_b,
                    else_b,
                    phis,
                } => {
                    let c = self.v(*cond);
                    let (tb, eb) = (self.tangent(then_b), self.tangent(else_b));
                    let outs: Vec<_> = phis.iter().map(|p| self.pair(p.out)).collect();
                    let tvs: Vec<_> = phis.iter().map(|p| self.pair(p.then_v)).collect();
                    let evs: Vec<_> = phis.iter().map(|p| self.pair(p.else_v)).collect();
                    out.extend(quote! {
                        let (#(#outs,)*) = if #c { #tb (#(#tvs,)*) } else { #eb (#(#evs,)*) };
                    });
                }
                Stmt::Loop(l) => {
                    let c = self.local("__carry", l.id);
                    let k = self.local("__k", l.id);
                    let inits: Vec<_> = l.carried.iter().map(|c| self.pair(c.init)).collect();
                    let inners: Vec<_> = l.carried.iter().map(|c| self.pair(c.inner)).collect();
                    let nexts: Vec<_> = l.carried.iter().map(|c| self.pair(c.next)).collect();
                    let outs: Vec<_> = l.carried.iter().map(|c| self.pair(c.out)).collect();
                    let header = self.loop_header(l, &k);
                    let index = match l.index {
                        Some(i) => {
                            let (x, dx) = (self.v(i), self.d(i));
                            quote!(let #x = #k; let #dx = #rt::zero_like(&#x);)
                        }
                        None => quote!(),
                    };
                    let body = self.tangent(&l.body);
                    let exit = self.loop_exit(l);
                    out.extend(quote! {
                        let mut #c = (#(#inits,)*);
                        #header {
                            #index
                            let (#(#inners,)*) = #c;
                            #body
                            #c = (#(#nexts,)*);
                            #exit
                        }
                        let (#(#outs,)*) = #c;
                    });
                }
            }
        }
        out
    }

    fn tangent_let(&self, l: &Let) -> TokenStream {
        let rt = self.rt;
        let span = l.span;
        let (x, dx) = (self.v(l.id), self.d(l.id));
        match &l.op {
            Op::Builtin { f, args } if !args.is_empty() => {
                let fwd = self.let_stmt(l);
                let f = format_ident!("tan_{}", f.name(), span = span);
                let (xs, dxs) = (self.vs_at(args, span), self.ds_at(args, span));
                let rt = &located(rt, span);
                quote_spanned!(span=> #fwd let #dx = #rt::__codegen::#f(#(#xs,)* #(#dxs),*);)
            }
            Op::Func { path, args } => {
                let (xs, dxs) = (self.vs(args), self.ds(args));
                {
                    let f = func_value(path, span);
                    quote_spanned!(span=> let (#x, #dx) = #rt::func::call_tangent((#(#xs,)*), (#(#dxs,)*), &#f);)
                }
            }
            Op::Cast { arg, ty } => {
                let fwd = self.let_stmt(l);
                let (y, dy) = (self.v(*arg), self.d(*arg));
                quote_spanned!(span=> #fwd let #dx = #rt::__codegen::tan_cast::<_, #ty>(#y, #dy);)
            }
            Op::Typed { src, ty } => {
                let fwd = self.let_stmt(l);
                let ds = self.d(*src);
                quote!(#fwd let #dx: #ty = #ds;)
            }
            Op::Read { param, index } => {
                let fwd = self.let_stmt(l);
                let (t, i) = (tangent_view(*param), self.v(*index));
                quote_spanned!(span=> #fwd let #dx = #t.get(#i);)
            }
            _ => {
                let fwd = self.let_stmt(l);
                quote!(#fwd let #dx = #rt::zero_like(&#x);)
            }
        }
    }
}
