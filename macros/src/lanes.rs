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
//! The two ids' code is two emissions of the adjoint, one per id ([`Emitter::for_lane`]: every
//! local of the id named with its suffix, `v3_l0` and `v3_l1`), zipped: no token of the user's
//! is renamed, so no name of the user's can collide with the macro's.
//!
//! A kernel qualifies if it has no loop (iterations differ in number from id to id) and stores
//! only at the thread id (the adjoint of a store elsewhere takes a gradient another id may
//! take); its `if`s are emitted three times (both ids, each alone), so their nesting is
//! bounded too.

use proc_macro2::{Ident, Span, TokenStream};
use quote::{quote, quote_spanned};

use crate::emit::{render_as, Emitter, Piece, Scatters};
use crate::ir::{Block, Stmt, StoreKind};

/// `if`s nested deeper than this keep one id per iteration (code grows 2x per level).
const MAX_DEPTH: usize = 3;
/// Kernels with more `let`s than this keep one id per iteration (compile time).
const MAX_LETS: usize = 2000;
/// Statements of one id emitted before the other's: 8 or 16 ran the bending adjoint 10%
/// faster than one id per iteration, 1 (alternating every statement) 4%, 24 to 64 no faster.
const RUN: usize = 8;

/// Whether the adjoint of a kernel with body `b` runs two ids per iteration; `distinct(p)`:
/// every store into parameter `p` is at the thread id.
pub fn qualifies(b: &Block, distinct: &dyn Fn(usize) -> bool) -> bool {
    fn walk(b: &Block, depth: usize, distinct: &dyn Fn(usize) -> bool, lets: &mut usize) -> bool {
        b.stmts.iter().all(|s| match s {
            Stmt::Let(_) => {
                *lets += 1;
                true
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
    walk(b, 0, distinct, &mut lets) && lets <= MAX_LETS
}

/// The emitters of the two ids of an iteration, `tid(0)` and `tid(1) = tid(0) + 1`.
pub fn emitters<'a>(em: &Emitter<'a>) -> [Emitter<'a>; 2] {
    [em.for_lane(0), em.for_lane(1)]
}

/// The body of one iteration for both ids: each id's `prologue` and `pieces` (the same code
/// emitted for each, see [`emitters`]), interleaved.
pub fn interleaved(prologue: [&TokenStream; 2], pieces: [&[Piece]; 2]) -> TokenStream {
    let mut sites = Vec::new();
    scatter_sites(pieces[1], &mut sites);
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
    let [p0, p1] = prologue;
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

/// The code of both ids (`pieces[lane]`, alike but for their names): runs of up to [`RUN`]
/// statements for the first id, then the same for the second; `if`s by [`both_if`].
fn both(pieces: [&[Piece]; 2]) -> TokenStream {
    assert_eq!(
        pieces[0].len(),
        pieces[1].len(),
        "two emissions of one code"
    );
    let mut out = TokenStream::new();
    let mut start = 0;
    let flush = |start: &mut usize, end: usize, out: &mut TokenStream| {
        out.extend(alone(&pieces[0][*start..end], 0));
        out.extend(alone(&pieces[1][*start..end], 1));
        *start = end;
    };
    for (k, p) in pieces[0].iter().enumerate() {
        if let Piece::Code(_) | Piece::Scatter { .. } = p {
            if k + 1 - start == RUN {
                flush(&mut start, k + 1, &mut out);
            }
        } else {
            flush(&mut start, k, &mut out);
            out.extend(both_if(p, &pieces[1][k]));
            start = k + 1;
        }
    }
    flush(&mut start, pieces[0].len(), &mut out);
    out
}

/// An `if` for both ids (`p0` the first's, `p1` the second's): its branch for both if they
/// take the same, else each its own alone.
fn both_if(p0: &Piece, p1: &Piece) -> TokenStream {
    match (p0, p1) {
        (
            Piece::Phi {
                cond: c0,
                outs: o0,
                then: th0,
                then_vals: t0,
                els: el0,
                else_vals: e0,
            },
            Piece::Phi {
                cond: c1,
                outs: o1,
                then: th1,
                then_vals: t1,
                els: el1,
                else_vals: e1,
            },
        ) => {
            let (tb, eb) = (both([th0, th1]), both([el0, el1]));
            let (ta0, ta1) = (alone(th0, 0), alone(th1, 1));
            let (ea0, ea1) = (alone(el0, 0), alone(el1, 1));
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
        (
            Piece::Branch {
                cond: c0,
                then: th0,
                els: el0,
            },
            Piece::Branch {
                cond: c1,
                then: th1,
                els: el1,
            },
        ) => {
            let (tb, eb) = (both([th0, th1]), both([el0, el1]));
            let (ta0, ta1) = (alone(th0, 0), alone(th1, 1));
            let (ea0, ea1) = (alone(el0, 0), alone(el1, 1));
            quote! {
                if #c0 == #c1 {
                    if #c0 { #tb } else { #eb }
                } else {
                    if #c0 { #ta0 } else { #ea0 }
                    if #c1 { #ta1 } else { #ea1 }
                }
            }
        }
        _ => unreachable!("`both` zips two emissions of one code"),
    }
}

/// The code of one id (`lane`): the first scatters where it stands, the second keeps.
fn alone(pieces: &[Piece], lane: usize) -> TokenStream {
    render_as(pieces, &Lane(lane))
}

/// The scatters of one of the two ids.
struct Lane(usize);

impl Scatters for Lane {
    fn scatter(&self, site: usize, view: &Ident, i: &Ident, x: &Ident, span: Span) -> TokenStream {
        if self.0 == 0 {
            quote_spanned!(span=> #view.add(#i, #x);)
        } else {
            let k = kept(site);
            quote!(#k = ::std::option::Option::Some((#i, #x));)
        }
    }
}
