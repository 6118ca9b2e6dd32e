//! The launch-strategy analyses of a lowered body: which accesses index with the thread id
//! (stores proven distinct; scatters a parallel launch may write directly) and which scatter
//! indices are static (computed ahead of a launch, for a split launch). They decide how the
//! runtime may run a kernel; the emitter does not depend on them.

use std::collections::{HashMap, HashSet};

use crate::ir::{Block, Body, Builtin, Let, Op, Stmt, StoreKind, ValueId};

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
