//! The builtins of the kernel language, each with its forward, adjoint and tangent rule.
//!
//! For a builtin `f(a, b)` there are three functions:
//! - `f(a, b) -> out`, the function;
//! - `adj_f(a, b, adj_out) -> (adj_a, adj_b)`, its reverse-mode rule (a single adjoint, not a
//!   tuple, for one-argument builtins);
//! - `tan_f(a, b, dot_a, dot_b) -> dot_out`, its forward-mode rule.
//!
//! Only `f` is here: the rules are the code-generation contract, called by the code
//! `#[diff_kernel]` emits (and by the finite-difference tests), not by users; they live on a
//! hidden path of their own (`adflex_runtime::__codegen`). Each builtin's item (its
//! [`DiffFunc`](crate::DiffFunc)) runs all three.
//!
//! Adjoints and tangents have the type of the value they belong to. Arguments that are not
//! differentiable (indices, booleans) get a zero adjoint of their own type. Zero-argument
//! builtins (the identities) are constants and have no rules.
//!
//! Builtins that take several types (`mul`, `length`, `extract`, ...) dispatch through one
//! trait per operation (`MulRule`, `VectorValue`, `ComponentRule`, ...), implemented for every
//! type (pair) from a table, generically over the scalar `R: Real`; so the same call works in
//! `f32`, `f64` and in kernels generic over `R`. Every rule is checked against central finite
//! differences in `f64` next to where it is defined.
//!
//! Rules are finite at their singular points wherever the function is; each function's docs
//! give its convention (they follow NVIDIA Warp). Below, `R` is a scalar (`f32`, `f64`),
//! `V` a vector (`Vec2`, `Vec3`, `Vec4`), `M` a matrix (`Mat22`, `Mat33`), `Q` a quaternion,
//! `I` an integer type.
//!
//! # Operators
//! - [`add`]`(a, b)`, [`sub`]`(a, b)`: `+`, `-` on same-type `R`, `V`, `M`, `Q`, `I`.
//! - [`mul`]`(a, b)`: `*` on `R*R`, `R*V`, `V*R`, `R*M`, `M*R`, `R*Q`, `Q*R`, `Mat22*Vec2`,
//!   `Mat33*Vec3`, `M*M`, `Q*Q` (Hamilton product), `I*I`.
//! - [`div`]`(a, b)`: `/` on `R/R`, `V/R`, `M/R`, `Q/R`, `I/I`.
//! - [`neg`]`(a)`: unary `-` on `R`, `V`, `M`, `Q`, signed `I`.
//! - [`rem`]`(a, b)`: `%` on integers only (no float `%`, so no wrong gradient).
//!
//! # Scalar functions
//! - [`sqrt`](fn@sqrt), [`sin`](fn@sin), [`cos`](fn@cos), [`tan`](fn@tan), [`asin`](fn@asin), [`acos`](fn@acos), [`atan`](fn@atan), [`sinh`](fn@sinh), [`cosh`](fn@cosh),
//!   [`tanh`](fn@tanh), [`exp`](fn@exp), [`ln`](fn@ln), [`log2`](fn@log2), [`log10`](fn@log10)`(x)`: the elementary functions
//!   (`sqrt'(0) = 0`; `asin`, `acos` clamp to `[-1, 1]` and have derivative 0 at `|x| >= 1`).
//! - [`atan2`](fn@atan2)`(y, x)`: angle of `(x, y)`, zero gradient at the origin.
//! - [`pow`](fn@pow)`(x, y)`: `x^y` for real `y`; [`powi`](fn@powi)`(x, n)`: `x^n` for `n: i32`.
//! - [`abs`](fn@abs)`(x)`, [`sign`](fn@sign)`(x)`: absolute value (`abs'(0) = 0`) and sign (`sign(0) = 0`,
//!   zero derivative); also for signed integers.
//! - [`floor`](fn@floor), [`ceil`](fn@ceil), [`round`](fn@round)`(x)`: rounding, zero derivative.
//! - [`min`](fn@min)`(a, b)`, [`max`](fn@max)`(a, b)`, [`clamp`](fn@clamp)`(x, lo, hi)`: ties send the gradient to `b`,
//!   `b`, `x`; also for integers.
//! - [`lerp`](fn@lerp)`(a, b, t)`: `a (1 - t) + b t` for `a`, `b` of type `R`, `V`, `M` or `Q`.
//! - [`select`](fn@select)`(c, a, b)`: `a` if `c` else `b`, any value type.
//! - [`step`](fn@step)`(x)`: 1 if `x >= 0` else 0; [`smoothstep`](fn@smoothstep)`(e0, e1, x)`: Hermite smoothstep.
//!
//! # Vectors
//! - [`dot`](fn@dot)`(a, b)`: inner product of two `V`.
//! - [`cross`](fn@cross)`(a, b)`: cross product of two `Vec3`.
//! - [`length`](fn@length)`(v)`, [`length_sq`](fn@length_sq)`(v)`: norm and squared norm (`length` has gradient 0 at 0).
//! - [`normalize`](fn@normalize)`(v)`: `v / |v|`, the zero vector (gradient 0) at 0.
//! - [`outer`](fn@outer)`(a, b)`: `a b^T`, `Vec2 -> Mat22`, `Vec3 -> Mat33`.
//! - [`cw_mul`](fn@cw_mul)`(a, b)`, [`cw_div`](fn@cw_div)`(a, b)`: componentwise product and quotient of `V` or `M`.
//!
//! # Matrices
//! - [`transpose`](fn@transpose)`(m)`, [`trace`](fn@trace)`(m)`, [`determinant`](fn@determinant)`(m)`: the usual (determinant's
//!   gradient is the cofactor matrix, finite everywhere).
//! - [`inverse`](fn@inverse)`(m)`: `m^-1`, the zero matrix (gradient 0) when `det(m) == 0`.
//! - [`ddot`](fn@ddot)`(a, b)`: the Frobenius inner product `sum a_ij b_ij`.
//! - [`skew`](fn@skew)`(a)`: the `Mat33` with `skew(a) * b == cross(a, b)`.
//! - [`diag`](fn@diag)`(v)`: the diagonal matrix of `Vec2` or `Vec3`.
//!
//! # Constructors
//! - [`vec2`](fn@vec2)`(x, y)`, [`vec3`](fn@vec3)`(x, y, z)`, [`vec4`](fn@vec4)`(x, y, z, w)`: vectors from scalars.
//! - [`mat22`](fn@mat22)`(4 scalars)`, [`mat33`](fn@mat33)`(9 scalars)`: matrices from entries, row-major.
//! - [`mat22_cols`](fn@mat22_cols)`(c0, c1)`, [`mat33_cols`](fn@mat33_cols)`(c0, c1, c2)`: matrices from columns.
//! - [`mat22_rows`](fn@mat22_rows)`(r0, r1)`, [`mat33_rows`](fn@mat33_rows)`(r0, r1, r2)`: matrices from rows.
//! - [`quat`](fn@quat)`(x, y, z, w)`: a quaternion from its components.
//! - [`mat22_identity`](fn@mat22_identity)`()`, [`mat33_identity`](fn@mat33_identity)`()`, [`quat_identity`](fn@quat_identity)`()`: constants.
//!
//! # Quaternions
//! - [`quat_mul`](fn@quat_mul)`(p, q)`: Hamilton product (same as `mul(p, q)`).
//! - [`quat_conjugate`](fn@quat_conjugate)`(q)`, [`quat_inverse`](fn@quat_inverse)`(q)`: conjugate, and `conj(q) / |q|^2` (zero
//!   at `q == 0`).
//! - [`quat_length`](fn@quat_length)`(q)`, [`quat_normalize`](fn@quat_normalize)`(q)`: norm, and `q / |q|` (zero at `q == 0`).
//! - [`quat_rotate`](fn@quat_rotate)`(q, v)`, [`quat_rotate_inv`](fn@quat_rotate_inv)`(q, v)`: rotate a `Vec3` by a unit `q`, or by
//!   its conjugate.
//! - [`quat_from_axis_angle`](fn@quat_from_axis_angle)`(axis, angle)`: rotation about a unit axis.
//! - [`quat_to_mat33`](fn@quat_to_mat33)`(q)`: rotation matrix of a unit `q`.
//!
//! # Components
//! - [`extract`]`(v, k)`: component `k` of a `V`, `Q` (x, y, z, w) or `[T; N]` (`k: usize`),
//!   or of an `M` (`k: (row, col)`). What `v.x`, `v[k]`, `m[(r, c)]` lower to.
//! - [`replace`]`(v, k, x)`: `v` with component `k` set to `x`. What `v.x = e` lowers to.
//!
//! # Casts
//! - [`cast`](fn@cast)`::<_, T>(x)`: `x as T` between floats (gradient flows) and integers (zero
//!   gradient).

// The builtins with their rules; `crate::__codegen` re-exports all of them.
pub(crate) mod cast;
pub(crate) mod component;
pub(crate) mod construct;
pub mod items;
pub(crate) mod matrix;
pub(crate) mod ops;
pub(crate) mod quaternion;
pub(crate) mod scalar;
pub(crate) mod vector;
pub(crate) mod vector_space;

#[cfg(test)]
pub(crate) mod check;
#[cfg(test)]
mod tests;

// Every builtin function (with its item, in the type namespace), the operators, and the
// traits that say which types each takes; no rule.
pub use cast::{cast, CastRule};
pub use component::{extract, replace, ComponentRule};
pub use items::builtins_prelude::*;
pub use matrix::{DiagRule, MatrixValue};
pub use ops::{add, div, mul, neg, rem, sub, AddRule, DivRule, MulRule, NegRule, RemRule, SubRule};
pub use scalar::SignedRule;
pub use vector::{Componentwise, OuterRule};
pub use vector_space::{Linear, Ordered, VectorValue};
