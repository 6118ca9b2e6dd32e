//! The builtins of the kernel language, each with its forward, adjoint and tangent rule.
//!
//! For a builtin `f(a, b)` there are three functions:
//! - `f(a, b) -> out`, the function;
//! - `adj_f(a, b, adj_out) -> (adj_a, adj_b)`, its reverse-mode rule (a single adjoint, not a
//!   tuple, for one-argument builtins);
//! - `tan_f(a, b, dot_a, dot_b) -> dot_out`, its forward-mode rule.
//!
//! Adjoints and tangents have the type of the value they belong to. Arguments that are not
//! differentiable (indices, booleans) get a zero adjoint of their own type.
