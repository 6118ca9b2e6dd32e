//! The SSA form a kernel or function body is lowered to.
//!
//! Every expression becomes a [`Let`] of a fresh value; reassigned locals become new values.
//! Control flow stays structured: an [`Stmt::If`] merges the values its branches assign through
//! phis, a [`Loop`] carries the values its body reassigns from one iteration to the next.
//! `break`, `continue` and `return` have already become flags that guard what follows them, so
//! a block always runs to its end and a loop leaves only between iterations.
//!
//! What a launch may do with a body (stores proven distinct, scatters at the thread id,
//! static scatter indices) is analysed in [`crate::strategy`].

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

/// A lowered body: its parameters' values, the body, and the returned value (funcs).
pub struct Body {
    /// The value of each parameter, `None` for an array (read through its view, not a value).
    pub params: Vec<Option<ValueId>>,
    pub block: Block,
    pub ret: Option<ValueId>,
}
