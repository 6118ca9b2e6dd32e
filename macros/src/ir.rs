//! The SSA form a kernel or function body is lowered to.
//!
//! Every expression becomes a [`Let`] of a fresh value; reassigned locals become new values.
//! Control flow stays structured: an [`Stmt::If`] merges the values its branches assign through
//! phis, a [`Loop`] carries the values its body reassigns from one iteration to the next.
//! `break`, `continue` and `return` have already become flags that guard what follows them, so
//! a block always runs to its end and a loop leaves only between iterations.

use std::collections::{HashMap, HashSet};

use proc_macro2::{Span, TokenStream};

/// A value: emitted as `v<N>` (its adjoint `a<N>`, its tangent `d<N>`).
pub type ValueId = u32;

/// What a value is computed from.
#[derive(Clone)]
pub enum Op {
    /// A literal or a constant path: no derivative.
    Const(TokenStream),
    /// The thread id of a kernel.
    Tid,
    /// A builtin of `adflex::math` (rules `name`, `adj_name`, `tan_name`).
    Builtin { f: Builtin, args: Vec<ValueId> },
    /// A call to a `#[diff_func]` (through `adflex::DiffFunc`).
    Func {
        path: TokenStream,
        args: Vec<ValueId>,
    },
    /// `x as T`, through the cast rules.
    Cast { arg: ValueId, ty: TokenStream },
    /// `let x: T = e;` (a copy that pins the type).
    Typed { src: ValueId, ty: TokenStream },
    /// A comparison, a logical or bitwise operator: emitted as written, no derivative.
    NativeBinary {
        op: TokenStream,
        a: ValueId,
        b: ValueId,
    },
    /// `!x`: no derivative.
    NativeUnary { op: TokenStream, a: ValueId },
    /// A tuple of indices (for `m[(r, c)]`): no derivative.
    Tuple(Vec<ValueId>),
    /// `a[i]` of an array parameter.
    Read { param: usize, index: ValueId },
    /// The result of `no_grad(..)`: the value, with zero derivative.
    StopGrad(ValueId),
    /// The zero of a type inferred from its use (placeholder for a not-yet-returned value).
    Zero,
    /// A plain call inside `no_grad(..)`.
    PlainCall {
        path: TokenStream,
        args: Vec<ValueId>,
    },
    /// A method call inside `no_grad(..)`.
    PlainMethod {
        recv: ValueId,
        method: TokenStream,
        args: Vec<ValueId>,
    },
}

impl Op {
    /// The values this operation uses.
    pub fn operands(&self) -> Vec<ValueId> {
        match self {
            Op::Builtin { args, .. }
            | Op::Func { args, .. }
            | Op::Tuple(args)
            | Op::PlainCall { args, .. } => args.clone(),
            Op::PlainMethod { recv, args, .. } => {
                std::iter::once(*recv).chain(args.iter().copied()).collect()
            }
            Op::Cast { arg: x, .. }
            | Op::Typed { src: x, .. }
            | Op::NativeUnary { a: x, .. }
            | Op::StopGrad(x)
            | Op::Read { index: x, .. } => vec![*x],
            Op::NativeBinary { a, b, .. } => vec![*a, *b],
            Op::Const(_) | Op::Tid | Op::Zero => Vec::new(),
        }
    }
}

/// A builtin rule of `adflex_runtime::__codegen`: the operations the macro itself lowers to, or a
/// builtin the user calls by name. Emitted as `name(..)`, `adj_name(..)` and `tan_name(..)`.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Builtin {
    /// `a + b` and `a += b`.
    Add,
    /// `a - b` and `a -= b`.
    Sub,
    /// `a * b` and `a *= b`.
    Mul,
    /// `a / b` and `a /= b`.
    Div,
    /// `a % b` and `a %= b`.
    Rem,
    /// `-a`.
    Neg,
    /// A component of a vector, matrix or index array: `v.x`, `v[k]`, `m[(r, c)]`,
    /// `let [i, j] = pairs[t];`.
    Extract,
    /// A vector with one component replaced: `v.x = e`, `v[k] = e`.
    Replace,
    /// A builtin called by name in the kernel (`dot(a, b)`); see [`crate::builtins`].
    Named(String),
}

impl Builtin {
    /// The name of the rule in `adflex_runtime::__codegen`.
    pub fn name(&self) -> &str {
        match self {
            Builtin::Add => "add",
            Builtin::Sub => "sub",
            Builtin::Mul => "mul",
            Builtin::Div => "div",
            Builtin::Rem => "rem",
            Builtin::Neg => "neg",
            Builtin::Extract => "extract",
            Builtin::Replace => "replace",
            Builtin::Named(name) => name,
        }
    }
}

/// `let v<id> = op;`
#[derive(Clone)]
pub struct Let {
    pub id: ValueId,
    pub op: Op,
    pub span: Span,
}

/// How a kernel writes an array element.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum StoreKind {
    Store,
    AtomicAdd,
    AtomicSub,
}

/// A phi: `out` is `then_v` after the then-branch, `else_v` after the else-branch.
#[derive(Clone)]
pub struct Phi {
    pub out: ValueId,
    pub then_v: ValueId,
    pub else_v: ValueId,
}

/// A value a loop carries: `inner` is `init` in the first iteration and the previous
/// iteration's `next` after that; `out` is the value after the loop.
#[derive(Clone)]
pub struct Carry {
    pub init: ValueId,
    pub inner: ValueId,
    pub next: ValueId,
    pub out: ValueId,
}

/// A dynamic loop: `for index in start..end` (or `..=`), or `loop` when `range` is `None`.
/// After the body, the loop ends if `exit` is true.
#[derive(Clone)]
pub struct Loop {
    pub id: usize,
    pub range: Option<(ValueId, ValueId, bool)>,
    pub index: Option<ValueId>,
    pub carried: Vec<Carry>,
    pub body: Block,
    pub exit: Option<ValueId>,
}

/// A statement.
#[derive(Clone)]
pub enum Stmt {
    Let(Let),
    Store {
        param: usize,
        index: ValueId,
        value: ValueId,
        kind: StoreKind,
        span: Span,
    },
    If {
        cond: ValueId,
        then_b: Block,
        else_b: Block,
        phis: Vec<Phi>,
    },
    Loop(Loop),
}

/// A straight-line sequence of statements.
#[derive(Clone, Default)]
pub struct Block {
    pub stmts: Vec<Stmt>,
}

/// Per parameter: whether every store, read, or atomic into it indexes with the thread id
/// (see [`Body::at_tid`]).
pub struct AtTid {
    pub stores: Vec<bool>,
    pub reads: Vec<bool>,
    pub atomics: Vec<bool>,
}

/// Scatter indices a launch can compute before it runs (see [`Body::static_indices`]).
pub struct StaticIndices<'b> {
    /// The top-level statements, in order.
    top: Vec<&'b Let>,
    /// Per parameter: the indices of every read of it, if all are static.
    pub reads: Vec<Option<Vec<ValueId>>>,
    /// Per parameter: the indices of every atomic into it, if all are static.
    pub atomics: Vec<Option<Vec<ValueId>>>,
}

impl<'b> StaticIndices<'b> {
    /// The top-level `let`s that compute `roots`, in body order, and the array parameters
    /// they read.
    pub fn closure(&self, roots: &[ValueId]) -> (Vec<&'b Let>, Vec<usize>) {
        let by_id: HashMap<ValueId, &Let> = self.top.iter().map(|l| (l.id, *l)).collect();
        let mut need: HashSet<ValueId> = HashSet::new();
        let mut stack = roots.to_vec();
        while let Some(id) = stack.pop() {
            if need.insert(id) {
                if let Some(l) = by_id.get(&id) {
                    stack.extend(l.op.operands());
                }
            }
        }
        let lets: Vec<&Let> = self
            .top
            .iter()
            .copied()
            .filter(|l| need.contains(&l.id))
            .collect();
        let mut deps = Vec::new();
        for l in &lets {
            if let Op::Read { param, .. } = l.op {
                if !deps.contains(&param) {
                    deps.push(param);
                }
            }
        }
        (lets, deps)
    }
}

/// A lowered body: its parameters' values, the body, and the returned value (funcs).
pub struct Body {
    /// The value of each parameter, `None` for an array (read through its view, not a value).
    pub params: Vec<Option<ValueId>>,
    pub block: Block,
    pub ret: Option<ValueId>,
}

impl Body {
    /// For each of `params` parameters, whether every access of each kind indexes with the
    /// thread id itself (`tid()`, or a `let` bound to it), so that no two threads of a launch
    /// touch one element through it. Stores elsewhere are checked at run time; reads and
    /// atomics at the thread id let the scatter of the adjoint (reads) or of the forward and
    /// tangent (atomics) write directly in every chunk of a parallel launch.
    pub fn at_tid(&self, params: usize) -> AtTid {
        fn tids(b: &Block, out: &mut Vec<ValueId>) {
            for s in &b.stmts {
                match s {
                    Stmt::Let(Let {
                        id, op: Op::Tid, ..
                    }) => out.push(*id),
                    Stmt::If { then_b, else_b, .. } => {
                        tids(then_b, out);
                        tids(else_b, out);
                    }
                    Stmt::Loop(l) => tids(&l.body, out),
                    _ => {}
                }
            }
        }
        fn check(b: &Block, tid: &[ValueId], ok: &mut AtTid) {
            for s in &b.stmts {
                match s {
                    Stmt::Let(Let {
                        op: Op::Read { param, index },
                        ..
                    }) if !tid.contains(index) => ok.reads[*param] = false,
                    Stmt::Store {
                        param, index, kind, ..
                    } if !tid.contains(index) => match kind {
                        StoreKind::Store => ok.stores[*param] = false,
                        StoreKind::AtomicAdd | StoreKind::AtomicSub => ok.atomics[*param] = false,
                    },
                    Stmt::If { then_b, else_b, .. } => {
                        check(then_b, tid, ok);
                        check(else_b, tid, ok);
                    }
                    Stmt::Loop(l) => check(&l.body, tid, ok),
                    _ => {}
                }
            }
        }
        let mut tid = Vec::new();
        tids(&self.block, &mut tid);
        let mut ok = AtTid {
            stores: vec![true; params],
            reads: vec![true; params],
            atomics: vec![true; params],
        };
        check(&self.block, &tid, &mut ok);
        ok
    }

    /// The scatter indices of each parameter that are *static*: computed at the top level of
    /// the body (so for every thread, whatever branch it takes later) from the thread id,
    /// constants and array reads by the same rule, through component extraction, arithmetic,
    /// comparisons and casts. Such indices depend only on the arrays read on the way (index
    /// arrays such as a mesh's elements), so the runtime can compute them ahead of a launch
    /// and know the first thread id that touches each target element (`runtime/src/split.rs`).
    /// A parameter with any other access of the kind (an index from a dynamic loop, a value
    /// parameter, a builtin call or a branch) gets `None`.
    pub fn static_indices(&self, params: usize) -> StaticIndices<'_> {
        fn is_static(
            id: ValueId,
            top: &HashMap<ValueId, &Let>,
            memo: &mut HashMap<ValueId, bool>,
        ) -> bool {
            if let Some(&m) = memo.get(&id) {
                return m;
            }
            let Some(l) = top.get(&id) else {
                return false; // a parameter value, a phi, or a value defined in a branch
            };
            let ok = match &l.op {
                Op::Tid | Op::Const(_) => true,
                Op::Read { index, .. } => is_static(*index, top, memo),
                Op::Builtin { f, args } => {
                    matches!(
                        f,
                        Builtin::Add
                            | Builtin::Sub
                            | Builtin::Mul
                            | Builtin::Div
                            | Builtin::Rem
                            | Builtin::Extract
                    ) && args.iter().all(|a| is_static(*a, top, memo))
                }
                Op::Cast { arg, .. } | Op::Typed { src: arg, .. } => is_static(*arg, top, memo),
                Op::NativeBinary { a, b, .. } => {
                    is_static(*a, top, memo) && is_static(*b, top, memo)
                }
                Op::NativeUnary { a, .. } => is_static(*a, top, memo),
                Op::Tuple(items) => items.iter().all(|a| is_static(*a, top, memo)),
                _ => false,
            };
            memo.insert(id, ok);
            ok
        }
        fn accesses(
            b: &Block,
            reads: &mut Vec<(usize, ValueId)>,
            atomics: &mut Vec<(usize, ValueId)>,
        ) {
            for s in &b.stmts {
                match s {
                    Stmt::Let(Let {
                        op: Op::Read { param, index },
                        ..
                    }) => reads.push((*param, *index)),
                    Stmt::Store {
                        param,
                        index,
                        kind: StoreKind::AtomicAdd | StoreKind::AtomicSub,
                        ..
                    } => atomics.push((*param, *index)),
                    Stmt::If { then_b, else_b, .. } => {
                        accesses(then_b, reads, atomics);
                        accesses(else_b, reads, atomics);
                    }
                    Stmt::Loop(l) => accesses(&l.body, reads, atomics),
                    _ => {}
                }
            }
        }
        let top: HashMap<ValueId, &Let> = self
            .block
            .stmts
            .iter()
            .filter_map(|s| match s {
                Stmt::Let(l) => Some((l.id, l)),
                _ => None,
            })
            .collect();
        let mut memo = HashMap::new();
        let (mut reads, mut atomics) = (Vec::new(), Vec::new());
        accesses(&self.block, &mut reads, &mut atomics);
        let per_param = |acc: &[(usize, ValueId)], memo: &mut HashMap<ValueId, bool>| {
            let mut out: Vec<Option<Vec<ValueId>>> = vec![Some(Vec::new()); params];
            for &(p, i) in acc {
                if !is_static(i, &top, memo) {
                    out[p] = None;
                } else if let Some(v) = &mut out[p] {
                    if !v.contains(&i) {
                        v.push(i);
                    }
                }
            }
            out
        };
        let reads = per_param(&reads, &mut memo);
        let atomics = per_param(&atomics, &mut memo);
        StaticIndices {
            top: self
                .block
                .stmts
                .iter()
                .filter_map(|s| match s {
                    Stmt::Let(l) => Some(l),
                    _ => None,
                })
                .collect(),
            reads,
            atomics,
        }
    }
}
