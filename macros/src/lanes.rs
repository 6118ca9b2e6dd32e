//! Two thread ids per iteration of an adjoint loop, their code interleaved statement by
//! statement.
//!
//! An adjoint replays its thread's forward, then runs it backward: one long chain of dependent
//! operations (square roots, divisions, `acos`) whose latency sets its speed more than the
//! number of its operations does. The code of two ids interleaved gives the processor two
//! independent chains to overlap: the cloth's bending adjoint takes 10% less time, its spring
//! adjoint 12% (docs/performance.md). (A hand-written bending adjoint four ids at a time was
//! slower than one: their values no longer fit in registers.)
//!
//! The result is bitwise that of the two ids one after the other: every value is computed by
//! the same operations, the first id's gradient scatters are made where they stand, and the
//! second id's are kept and made after the pair's code, in the order that id makes them, so
//! every element receives its additions in thread-id order. Where an `if` goes different ways
//! for the two ids, each runs its branch alone, the first id first.
//!
//! A kernel qualifies if it has no loop (iterations differ in number from id to id) and stores
//! only at the thread id (the adjoint of a store elsewhere takes a gradient another id may
//! take); its `if`s are emitted three times (both ids, each alone), so their nesting is
//! bounded too.

use proc_macro2::{Group, Ident, Span, TokenStream, TokenTree};
use quote::{quote, quote_spanned};

use crate::emit::{render_as, Names, Piece};
use crate::ir::{Block, Op, Stmt, StoreKind};

/// `if`s nested deeper than this keep one id per iteration (code grows 2x per level).
const MAX_DEPTH: usize = 3;
/// Kernels with more `let`s than this keep one id per iteration (compile time).
const MAX_LETS: usize = 2000;
/// Statements of one id emitted before the other's: 8 or 16 ran the bending adjoint 10%
/// faster than one id per iteration, 1 (alternating every statement) 4%, 24 to 64 no faster.
const RUN: usize = 8;

/// Whether the adjoint of a kernel with body `b` runs two ids per iteration; `distinct(p)`:
/// every store into parameter `p` is at the thread id; `rt`: the path of the runtime crate.
pub fn qualifies(b: &Block, distinct: &dyn Fn(usize) -> bool, rt: &TokenStream) -> bool {
    fn walk(b: &Block, depth: usize, distinct: &dyn Fn(usize) -> bool, lets: &mut usize) -> bool {
        b.stmts.iter().all(|s| match s {
            Stmt::Let(l) => {
                *lets += 1;
                !user_tokens(&l.op).is_some_and(names_a_local)
            }
            Stmt::Store { param, kind, .. } => *kind != StoreKind::Store || distinct(*param),
            Stmt::If { then_b, else_b, .. } => {
                depth < MAX_DEPTH
                    && walk(then_b, depth + 1, distinct, lets)
                    && walk(else_b, depth + 1, distinct, lets)
            }
            Stmt::Loop(_) => false,
        })
    }
    let mut lets = 0;
    walk(b, 0, distinct, &mut lets) && lets <= MAX_LETS && !names_a_local(rt)
}

/// The user's tokens `op` carries into the generated code.
fn user_tokens(op: &Op) -> Option<&TokenStream> {
    match op {
        Op::Const(t)
        | Op::Func { path: t, .. }
        | Op::Cast { ty: t, .. }
        | Op::Typed { ty: t, .. }
        | Op::NativeBinary { op: t, .. }
        | Op::NativeUnary { op: t, .. }
        | Op::PlainCall { path: t, .. }
        | Op::PlainMethod { method: t, .. } => Some(t),
        Op::Tid
        | Op::Builtin { .. }
        | Op::Tuple(_)
        | Op::Read { .. }
        | Op::StopGrad(_)
        | Op::Zero => None,
    }
}

/// Whether `code` contains an identifier named like a generated local (a constant `a1`, a
/// function `v2`), which [`rename`] would rename: such a kernel keeps one id per iteration.
fn names_a_local(code: &TokenStream) -> bool {
    code.clone().into_iter().any(|t| match t {
        TokenTree::Ident(i) => is_local(&i.to_string()),
        TokenTree::Group(g) => names_a_local(&g.stream()),
        _ => false,
    })
}

/// The thread id of `lane` (0 or 1), named as [`rename`] names the id inside the code.
pub fn tid(lane: usize) -> Ident {
    lane_ident(&crate::emit::tid(), lane)
}

/// The body of one iteration for ids `tid(0)` and `tid(1) = tid(0) + 1`: `prologue` and
/// `pieces` (the code of one id) for both, interleaved.
pub fn interleaved(prologue: &TokenStream, pieces: &[Piece]) -> TokenStream {
    let mut sites = Vec::new();
    scatter_sites(pieces, &mut sites);
    let decls = sites.iter().map(|&(site, ..)| {
        let k = kept(site);
        quote!(let mut #k = ::std::option::Option::None;)
    });
    // In the order the second id made them (depth first: an `if`'s branches in order, one
    // taken).
    let made = sites.iter().map(|&(site, view, span)| {
        let k = kept(site);
        quote_spanned! {span=>
            if let ::std::option::Option::Some((__i, __x)) = #k { #view.add(__i, __x); }
        }
    });
    let (p0, p1) = (rename(prologue, 0), rename(prologue, 1));
    let code = both(pieces);
    quote! {
        #(#decls)*
        #p0
        #p1
        #code
        #(#made)*
    }
}

fn scatter_sites<'p>(pieces: &'p [Piece], out: &mut Vec<(usize, &'p Ident, Span)>) {
    for p in pieces {
        match p {
            Piece::Code(_) => {}
            Piece::Scatter {
                site, view, span, ..
            } => out.push((*site, view, *span)),
            Piece::Phi { then, els, .. } | Piece::Branch { then, els, .. } => {
                scatter_sites(then, out);
                scatter_sites(els, out);
            }
        }
    }
}

/// The second id's scatter at `site`, kept until the end of the pair's code.
fn kept(site: usize) -> Ident {
    Ident::new(&format!("__kept{site}"), Span::mixed_site())
}

/// The code of both ids: runs of up to [`RUN`] statements for the first id, then the same for
/// the second; `if`s by [`both_if`].
fn both(pieces: &[Piece]) -> TokenStream {
    let mut out = TokenStream::new();
    let mut run: &[Piece] = &[];
    let flush = |run: &mut &[Piece], out: &mut TokenStream| {
        out.extend(alone(run, 0));
        out.extend(alone(run, 1));
        *run = &[];
    };
    for (k, p) in pieces.iter().enumerate() {
        if let Piece::Code(_) | Piece::Scatter { .. } = p {
            run = &pieces[k - run.len()..=k];
            if run.len() == RUN {
                flush(&mut run, &mut out);
            }
        } else {
            flush(&mut run, &mut out);
            out.extend(both_if(p));
        }
    }
    flush(&mut run, &mut out);
    out
}

/// An `if` for both ids: its branch for both if they take the same, else each its own alone.
fn both_if(p: &Piece) -> TokenStream {
    match p {
        Piece::Phi {
            cond,
            outs,
            then,
            then_vals,
            els,
            else_vals,
        } => {
            let [c0, c1] = [0, 1].map(|l| lane_ident(cond, l));
            let [o0, o1] = [0, 1].map(|l| lane_idents(outs, l));
            let [t0, t1] = [0, 1].map(|l| lane_idents(then_vals, l));
            let [e0, e1] = [0, 1].map(|l| lane_idents(else_vals, l));
            let (tb, eb) = (both(then), both(els));
            let [ta0, ta1] = [0, 1].map(|l| alone(then, l));
            let [ea0, ea1] = [0, 1].map(|l| alone(els, l));
            quote! {
                let ((#(#o0,)*), (#(#o1,)*)) = if #c0 == #c1 {
                    if #c0 {
                        #tb ((#(#t0,)*), (#(#t1,)*))
                    } else {
                        #eb ((#(#e0,)*), (#(#e1,)*))
                    }
                } else {
                    (
                        if #c0 { #ta0 (#(#t0,)*) } else { #ea0 (#(#e0,)*) },
                        if #c1 { #ta1 (#(#t1,)*) } else { #ea1 (#(#e1,)*) },
                    )
                };
            }
        }
        Piece::Branch { cond, then, els } => {
            let [c0, c1] = [0, 1].map(|l| lane_ident(cond, l));
            let (tb, eb) = (both(then), both(els));
            let [ta0, ta1] = [0, 1].map(|l| alone(then, l));
            let [ea0, ea1] = [0, 1].map(|l| alone(els, l));
            quote! {
                if #c0 == #c1 {
                    if #c0 { #tb } else { #eb }
                } else {
                    if #c0 { #ta0 } else { #ea0 }
                    if #c1 { #ta1 } else { #ea1 }
                }
            }
        }
        Piece::Code(_) | Piece::Scatter { .. } => unreachable!("`both` renders statements"),
    }
}

/// The code of one id (`lane`): the first scatters where it stands, the second keeps.
fn alone(pieces: &[Piece], lane: usize) -> TokenStream {
    render_as(pieces, &Lane(lane))
}

/// The names of one of the two ids.
struct Lane(usize);

impl Names for Lane {
    fn name(&self, i: &Ident) -> Ident {
        lane_ident(i, self.0)
    }
    fn code(&self, c: &TokenStream) -> TokenStream {
        rename(c, self.0)
    }
    fn scatter(&self, site: usize, view: &Ident, i: Ident, x: Ident, span: Span) -> TokenStream {
        if self.0 == 0 {
            quote_spanned!(span=> #view.add(#i, #x);)
        } else {
            let k = kept(site);
            quote!(#k = ::std::option::Option::Some((#i, #x));)
        }
    }
}

/// `code` with the names of one id's locals (`v<N>`, `a<N>`, `__g<N>`, `__tid`) given the
/// suffix of `lane`.
fn rename(code: &TokenStream, lane: usize) -> TokenStream {
    code.clone()
        .into_iter()
        .map(|t| match t {
            TokenTree::Ident(i) if is_local(&i.to_string()) => {
                TokenTree::Ident(lane_ident(&i, lane))
            }
            TokenTree::Group(g) => {
                let mut n = Group::new(g.delimiter(), rename(&g.stream(), lane));
                n.set_span(g.span());
                TokenTree::Group(n)
            }
            other => other,
        })
        .collect()
}

fn is_local(name: &str) -> bool {
    let numbered = |prefix: &str| {
        name.strip_prefix(prefix)
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    };
    name == "__tid" || numbered("v") || numbered("a") || numbered("__g")
}

fn lane_ident(i: &Ident, lane: usize) -> Ident {
    Ident::new(&format!("{i}_l{lane}"), i.span())
}

fn lane_idents(is: &[Ident], lane: usize) -> Vec<Ident> {
    is.iter().map(|i| lane_ident(i, lane)).collect()
}
