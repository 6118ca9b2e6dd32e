//! The builtins as items: the one list of the kernel language's builtin functions.
//!
//! Each builtin `f` is, besides the function `math::f` (which plain Rust calls), a type `f` in
//! the **type** namespace (a braced struct, so it takes no name from the value namespace)
//! implementing [`DiffFunc`] with the function and its `adj_f` and `tan_f` rules, exactly as
//! a `#[diff_func]` does. Inside a kernel, the macro emits a call `f(..)` as a call of the
//! `DiffFunc` that the name `f` resolves to **in the user's scope**: the prelude's builtin, or
//! the user's own `#[diff_func] fn f`, which shadows it where Rust says it does. So a builtin
//! added later cannot change what existing user code means.
//!
//! [`BUILTINS`] lists them (the guide's table is tested against it). Operators (`+`, `-`, `*`,
//! `/`, `%`, unary `-`) and component access are not items: they keep a fixed table in the
//! macro.

#![allow(non_camel_case_types)]

use super::matrix::{DiagRule, MatrixValue};
use super::scalar::SignedRule;
use super::vector::{Componentwise, OuterRule};
use super::vector_space::{Linear, Ordered, VectorValue};
use crate::func::DiffFunc;
use crate::{Mat22, Mat33, Quat, Real, Value, Vec2, Vec3, Vec4};

/// The adjoint call of a builtin as the tuple `DiffFunc::adjoint` returns.
macro_rules! adjoint_tuple {
    ($adj:ident, [], $g:ident) => {{
        let _ = $g;
    }};
    ($adj:ident, [$a:ident], $g:ident) => {
        (crate::__codegen::$adj($a, $g),)
    };
    ($adj:ident, [$($a:ident),+], $g:ident) => {
        crate::__codegen::$adj($($a,)+ $g)
    };
}

macro_rules! items {
    ($(
        $f:ident, $adj:ident, $tan:ident [$($gen:tt)*] ($($a:ident $da:ident : $t:ty),*) -> $o:ty;
    )*) => {
        $(
            #[doc = concat!("The builtin [`", stringify!($f), "`](fn@super::", stringify!($f),
                ") as an item: its `DiffFunc` (forward, adjoint, tangent) for kernels.")]
            #[derive(Clone, Copy, Debug, Default)]
            pub struct $f {}

            impl<$($gen)*> DiffFunc<($($t,)*), $o> for $f {
                #[inline(always)]
                fn forward(&self, ($($a,)*): ($($t,)*)) -> $o {
                    crate::__codegen::$f($($a),*)
                }
                #[inline(always)]
                #[allow(unused_variables, clippy::unused_unit)]
                fn adjoint(&self, ($($a,)*): ($($t,)*), adj: $o) -> ($($t,)*) {
                    adjoint_tuple!($adj, [$($a),*], adj)
                }
                #[inline(always)]
                fn tangent(&self, ($($a,)*): ($($t,)*), ($($da,)*): ($($t,)*)) -> ($o, $o) {
                    (crate::__codegen::$f($($a),*), crate::__codegen::$tan($($a,)* $($da),*))
                }
            }
        )*

        /// Every builtin function of the kernel language (operators excepted), in the order of
        /// the guide's table.
        pub const BUILTINS: &[&str] = &[$(stringify!($f)),*];

        /// What the prelude brings of the math: each builtin's function (for plain Rust) and
        /// item (for kernels), and nothing of the rules (`adj_*`, `tan_*`, the rule traits),
        /// which only generated code calls.
        pub mod builtins_prelude {
            $(pub use crate::__codegen::$f;)*
            pub use super::constants_prelude::*;
        }
    };
}

/// A zero-argument builtin (a constant): no rules.
macro_rules! constants {
    ($($f:ident [$($gen:tt)*] -> $o:ty;)*) => {
        mod constants_prelude {
            $(pub use crate::__codegen::$f;)*
        }
        $(
        #[doc = concat!("The builtin [`", stringify!($f), "`](fn@super::", stringify!($f),
            ") as an item (a constant).")]
        #[derive(Clone, Copy, Debug, Default)]
        pub struct $f {}

        impl<$($gen)*> DiffFunc<(), $o> for $f {
            #[inline(always)]
            fn forward(&self, _: ()) -> $o {
                crate::__codegen::$f()
            }
            #[inline(always)]
            fn adjoint(&self, _: (), _: $o) {}
            #[inline(always)]
            fn tangent(&self, _: (), _: ()) -> ($o, $o) {
                let v = crate::__codegen::$f();
                (v, crate::zero_like(&v))
            }
        }
    )*};
}

items! {
    sqrt, adj_sqrt, tan_sqrt [R: Real] (x dx: R) -> R;
    sin, adj_sin, tan_sin [R: Real] (x dx: R) -> R;
    cos, adj_cos, tan_cos [R: Real] (x dx: R) -> R;
    tan, adj_tan, tan_tan [R: Real] (x dx: R) -> R;
    asin, adj_asin, tan_asin [R: Real] (x dx: R) -> R;
    acos, adj_acos, tan_acos [R: Real] (x dx: R) -> R;
    atan, adj_atan, tan_atan [R: Real] (x dx: R) -> R;
    atan2, adj_atan2, tan_atan2 [R: Real] (y dy: R, x dx: R) -> R;
    sinh, adj_sinh, tan_sinh [R: Real] (x dx: R) -> R;
    cosh, adj_cosh, tan_cosh [R: Real] (x dx: R) -> R;
    tanh, adj_tanh, tan_tanh [R: Real] (x dx: R) -> R;
    exp, adj_exp, tan_exp [R: Real] (x dx: R) -> R;
    ln, adj_ln, tan_ln [R: Real] (x dx: R) -> R;
    log2, adj_log2, tan_log2 [R: Real] (x dx: R) -> R;
    log10, adj_log10, tan_log10 [R: Real] (x dx: R) -> R;
    pow, adj_pow, tan_pow [R: Real] (x dx: R, y dy: R) -> R;
    powi, adj_powi, tan_powi [R: Real] (x dx: R, n dn: i32) -> R;
    abs, adj_abs, tan_abs [T: SignedRule] (x dx: T) -> T;
    sign, adj_sign, tan_sign [T: SignedRule] (x dx: T) -> T;
    floor, adj_floor, tan_floor [R: Real] (x dx: R) -> R;
    ceil, adj_ceil, tan_ceil [R: Real] (x dx: R) -> R;
    round, adj_round, tan_round [R: Real] (x dx: R) -> R;
    min, adj_min, tan_min [T: Ordered] (a da: T, b db: T) -> T;
    max, adj_max, tan_max [T: Ordered] (a da: T, b db: T) -> T;
    clamp, adj_clamp, tan_clamp [T: Ordered] (x dx: T, lo dlo: T, hi dhi: T) -> T;
    lerp, adj_lerp, tan_lerp [T: Linear] (a da: T, b db: T, t dt: T::Scalar) -> T;
    select, adj_select, tan_select [T: Value] (c dc: bool, a da: T, b db: T) -> T;
    step, adj_step, tan_step [R: Real] (x dx: R) -> R;
    smoothstep, adj_smoothstep, tan_smoothstep [R: Real] (e0 de0: R, e1 de1: R, x dx: R) -> R;
    dot, adj_dot, tan_dot [V: VectorValue] (a da: V, b db: V) -> V::Scalar;
    cross, adj_cross, tan_cross [R: Real] (a da: Vec3<R>, b db: Vec3<R>) -> Vec3<R>;
    length, adj_length, tan_length [V: VectorValue] (v dv: V) -> V::Scalar;
    length_sq, adj_length_sq, tan_length_sq [V: VectorValue] (v dv: V) -> V::Scalar;
    normalize, adj_normalize, tan_normalize [V: VectorValue] (v dv: V) -> V;
    outer, adj_outer, tan_outer [V: OuterRule] (a da: V, b db: V) -> V::Out;
    cw_mul, adj_cw_mul, tan_cw_mul [T: Componentwise] (a da: T, b db: T) -> T;
    cw_div, adj_cw_div, tan_cw_div [T: Componentwise] (a da: T, b db: T) -> T;
    transpose, adj_transpose, tan_transpose [M: MatrixValue] (m dm: M) -> M;
    determinant, adj_determinant, tan_determinant [M: MatrixValue] (m dm: M) -> M::Scalar;
    inverse, adj_inverse, tan_inverse [M: MatrixValue] (m dm: M) -> M;
    trace, adj_trace, tan_trace [M: MatrixValue] (m dm: M) -> M::Scalar;
    ddot, adj_ddot, tan_ddot [M: MatrixValue] (a da: M, b db: M) -> M::Scalar;
    skew, adj_skew, tan_skew [R: Real] (a da: Vec3<R>) -> Mat33<R>;
    diag, adj_diag, tan_diag [V: DiagRule] (v dv: V) -> V::Out;
    vec2, adj_vec2, tan_vec2 [R: Real] (x dx: R, y dy: R) -> Vec2<R>;
    vec3, adj_vec3, tan_vec3 [R: Real] (x dx: R, y dy: R, z dz: R) -> Vec3<R>;
    vec4, adj_vec4, tan_vec4 [R: Real] (x dx: R, y dy: R, z dz: R, w dw: R) -> Vec4<R>;
    mat22, adj_mat22, tan_mat22 [R: Real] (a da: R, b db: R, c dc: R, d dd: R) -> Mat22<R>;
    mat33, adj_mat33, tan_mat33 [R: Real] (a da: R, b db: R, c dc: R, d dd: R, e de: R,
        f df: R, g dg: R, h dh: R, i di: R) -> Mat33<R>;
    mat22_cols, adj_mat22_cols, tan_mat22_cols [R: Real] (a da: Vec2<R>, b db: Vec2<R>) -> Mat22<R>;
    mat33_cols, adj_mat33_cols, tan_mat33_cols [R: Real] (a da: Vec3<R>, b db: Vec3<R>,
        c dc: Vec3<R>) -> Mat33<R>;
    mat22_rows, adj_mat22_rows, tan_mat22_rows [R: Real] (a da: Vec2<R>, b db: Vec2<R>) -> Mat22<R>;
    mat33_rows, adj_mat33_rows, tan_mat33_rows [R: Real] (a da: Vec3<R>, b db: Vec3<R>,
        c dc: Vec3<R>) -> Mat33<R>;
    quat, adj_quat, tan_quat [R: Real] (x dx: R, y dy: R, z dz: R, w dw: R) -> Quat<R>;
    quat_mul, adj_quat_mul, tan_quat_mul [R: Real] (p dp: Quat<R>, q dq: Quat<R>) -> Quat<R>;
    quat_conjugate, adj_quat_conjugate, tan_quat_conjugate [R: Real] (q dq: Quat<R>) -> Quat<R>;
    quat_inverse, adj_quat_inverse, tan_quat_inverse [R: Real] (q dq: Quat<R>) -> Quat<R>;
    quat_normalize, adj_quat_normalize, tan_quat_normalize [R: Real] (q dq: Quat<R>) -> Quat<R>;
    quat_rotate, adj_quat_rotate, tan_quat_rotate [R: Real] (q dq: Quat<R>, v dv: Vec3<R>) -> Vec3<R>;
    quat_rotate_inv, adj_quat_rotate_inv, tan_quat_rotate_inv [R: Real] (q dq: Quat<R>,
        v dv: Vec3<R>) -> Vec3<R>;
    quat_from_axis_angle, adj_quat_from_axis_angle, tan_quat_from_axis_angle [R: Real]
        (axis daxis: Vec3<R>, angle dangle: R) -> Quat<R>;
    quat_to_mat33, adj_quat_to_mat33, tan_quat_to_mat33 [R: Real] (q dq: Quat<R>) -> Mat33<R>;
    quat_length, adj_quat_length, tan_quat_length [R: Real] (q dq: Quat<R>) -> R;
}

constants! {
    mat22_identity [R: Real] -> Mat22<R>;
    mat33_identity [R: Real] -> Mat33<R>;
    quat_identity [R: Real] -> Quat<R>;
}

/// The zero-argument builtins (constants), after [`BUILTINS`] in the guide's table.
pub const CONSTANTS: &[&str] = &["mat22_identity", "mat33_identity", "quat_identity"];
