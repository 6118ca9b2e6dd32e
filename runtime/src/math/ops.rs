//! The arithmetic operators: `add` (`+`), `sub` (`-`), `mul` (`*`), `div` (`/`), `neg` (unary
//! `-`) and `rem` (`%`, integers only), each over every pair of types it is defined for.
//!
//! Each operator is a trait implemented per type pair (generated from the tables below), and the
//! free functions dispatch to it, so `mul(s, v)`, `mul(m, v)` and `mul(p, q)` are one name.
//! Integer operations have zero adjoints and tangents.

use nalgebra::{Matrix2, Matrix3, Quaternion, Vector2, Vector3, Vector4};

use super::quaternion::{adj_quat_mul, quat_mul, tan_quat_mul};
use super::vector_space::Linear;
use crate::Real;

// ---------------------------------------------------------------------------------------------
// add, sub, neg: every `Linear` type, and integers.

/// Rule of `a + b` (same types).
#[diagnostic::on_unimplemented(
    message = "cannot add these in a kernel: both sides of `+` must have the same type",
    label = "`{Self}` + a different type",
    note = "write float literals with a point (`x + 1.0`, not `x + 1`); in a kernel generic over `R: Real`, both sides are `R` (or vectors/matrices of `R`)"
)]
pub trait AddRule: Sized {
    /// `a + b`.
    fn add_fwd(self, b: Self) -> Self;
    /// `(adj, adj)`.
    fn add_adj(self, b: Self, adj: Self) -> (Self, Self);
    /// `da + db`.
    fn add_tan(self, b: Self, da: Self, db: Self) -> Self;
}

/// Rule of `a - b` (same types).
#[diagnostic::on_unimplemented(
    message = "cannot subtract these in a kernel: both sides of `-` must have the same type",
    label = "`{Self}` - a different type",
    note = "write float literals with a point (`x - 1.0`, not `x - 1`); in a kernel generic over `R: Real`, both sides are `R` (or vectors/matrices of `R`)"
)]
pub trait SubRule: Sized {
    /// `a - b`.
    fn sub_fwd(self, b: Self) -> Self;
    /// `(adj, -adj)`.
    fn sub_adj(self, b: Self, adj: Self) -> (Self, Self);
    /// `da - db`.
    fn sub_tan(self, b: Self, da: Self, db: Self) -> Self;
}

/// Rule of `-a`.
pub trait NegRule: Sized {
    /// `-a`.
    fn neg_fwd(self) -> Self;
    /// `-adj`.
    fn neg_adj(self, adj: Self) -> Self;
    /// `-da`.
    fn neg_tan(self, da: Self) -> Self;
}

impl<T: Linear> AddRule for T {
    #[inline(always)]
    fn add_fwd(self, b: Self) -> Self {
        self.lin_add(b)
    }
    #[inline]
    fn add_adj(self, _b: Self, adj: Self) -> (Self, Self) {
        (adj, adj)
    }
    #[inline]
    fn add_tan(self, _b: Self, da: Self, db: Self) -> Self {
        da.lin_add(db)
    }
}

impl<T: Linear> SubRule for T {
    #[inline(always)]
    fn sub_fwd(self, b: Self) -> Self {
        self.lin_sub(b)
    }
    #[inline]
    fn sub_adj(self, _b: Self, adj: Self) -> (Self, Self) {
        (adj, adj.lin_neg())
    }
    #[inline]
    fn sub_tan(self, _b: Self, da: Self, db: Self) -> Self {
        da.lin_sub(db)
    }
}

impl<T: Linear> NegRule for T {
    #[inline(always)]
    fn neg_fwd(self) -> Self {
        self.lin_neg()
    }
    #[inline]
    fn neg_adj(self, adj: Self) -> Self {
        adj.lin_neg()
    }
    #[inline]
    fn neg_tan(self, da: Self) -> Self {
        da.lin_neg()
    }
}

/// `a + b`: same-type pairs of scalars, vectors, matrices, quaternions and integers. No
/// singular points.
#[inline(always)]
pub fn add<T: AddRule>(a: T, b: T) -> T {
    a.add_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`add`]: `(adj, adj)`.
#[inline(always)]
pub fn adj_add<T: AddRule>(a: T, b: T, adj: T) -> (T, T) {
    a.add_adj(b, adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`add`]: `da + db`.
#[inline(always)]
pub fn tan_add<T: AddRule>(a: T, b: T, da: T, db: T) -> T {
    a.add_tan(b, da, db)
}

/// `a - b`: same-type pairs of scalars, vectors, matrices, quaternions and integers. No
/// singular points.
#[inline(always)]
pub fn sub<T: SubRule>(a: T, b: T) -> T {
    a.sub_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`sub`]: `(adj, -adj)`.
#[inline(always)]
pub fn adj_sub<T: SubRule>(a: T, b: T, adj: T) -> (T, T) {
    a.sub_adj(b, adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`sub`]: `da - db`.
#[inline(always)]
pub fn tan_sub<T: SubRule>(a: T, b: T, da: T, db: T) -> T {
    a.sub_tan(b, da, db)
}

/// `-a`: scalars, vectors, matrices, quaternions and signed integers. No singular points.
#[inline(always)]
pub fn neg<T: NegRule>(a: T) -> T {
    a.neg_fwd()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`neg`]: `-adj`.
#[inline(always)]
pub fn adj_neg<T: NegRule>(a: T, adj: T) -> T {
    a.neg_adj(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`neg`]: `-da`.
#[inline(always)]
pub fn tan_neg<T: NegRule>(a: T, da: T) -> T {
    a.neg_tan(da)
}

// ---------------------------------------------------------------------------------------------
// mul

/// Rule of `a * b` for one pair of types.
#[diagnostic::on_unimplemented(
    message = "cannot multiply `{Self}` by `{B}` in a kernel",
    label = "no rule for `{Self}` * `{B}`",
    note = "`*` takes two scalars of one type, a vector or matrix and its scalar, a matrix and a vector or matrix, or two quaternions; write float literals with a point (`2.0 * x`, not `2 * x`), and in a kernel generic over `R: Real` use `R` throughout (an `f64` value times `R` has no rule: use a literal, a parameter of type `R`, or `cast`)"
)]
pub trait MulRule<B>: Sized {
    /// The product's type.
    type Out;
    /// `a * b`.
    fn mul_fwd(self, b: B) -> Self::Out;
    /// `(adj_a, adj_b)` given the adjoint of the product.
    fn mul_adj(self, b: B, adj: Self::Out) -> (Self, B);
    /// `da * b + a * db`.
    fn mul_tan(self, b: B, da: Self, db: B) -> Self::Out;
}

impl<R: Real> MulRule<R> for R {
    type Out = R;
    #[inline(always)]
    fn mul_fwd(self, b: R) -> R {
        self * b
    }
    #[inline]
    fn mul_adj(self, b: R, adj: R) -> (R, R) {
        (adj * b, adj * self)
    }
    #[inline]
    fn mul_tan(self, b: R, da: R, db: R) -> R {
        da * b + self * db
    }
}

/// Scalar times a vector, matrix or quaternion, on either side.
macro_rules! mul_scalar {
    ($($t:ident),*) => {$(
        impl<R: Real> MulRule<$t<R>> for R {
            type Out = $t<R>;
            #[inline(always)]
            fn mul_fwd(self, b: $t<R>) -> $t<R> {
                b.lin_scale(self)
            }
            #[inline]
            fn mul_adj(self, b: $t<R>, adj: $t<R>) -> (R, $t<R>) {
                (adj.lin_inner(b), adj.lin_scale(self))
            }
            #[inline]
            fn mul_tan(self, b: $t<R>, da: R, db: $t<R>) -> $t<R> {
                b.lin_scale(da).lin_add(db.lin_scale(self))
            }
        }
        impl<R: Real> MulRule<R> for $t<R> {
            type Out = $t<R>;
            #[inline(always)]
            fn mul_fwd(self, b: R) -> $t<R> {
                self.lin_scale(b)
            }
            #[inline]
            fn mul_adj(self, b: R, adj: $t<R>) -> ($t<R>, R) {
                (adj.lin_scale(b), adj.lin_inner(self))
            }
            #[inline]
            fn mul_tan(self, b: R, da: $t<R>, db: R) -> $t<R> {
                da.lin_scale(b).lin_add(self.lin_scale(db))
            }
        }
    )*};
}
mul_scalar!(Vector2, Vector3, Vector4, Matrix2, Matrix3, Quaternion);

/// Matrix times vector and matrix times matrix: `adj_a = adj b^T`, `adj_b = a^T adj`.
macro_rules! mul_matrix {
    ($(($a:ident, $b:ident)),*) => {$(
        impl<R: Real> MulRule<$b<R>> for $a<R> {
            type Out = $b<R>;
            #[inline(always)]
            fn mul_fwd(self, b: $b<R>) -> $b<R> {
                self * b
            }
            #[inline]
            fn mul_adj(self, b: $b<R>, adj: $b<R>) -> ($a<R>, $b<R>) {
                (adj * b.transpose(), self.tr_mul(&adj))
            }
            #[inline]
            fn mul_tan(self, b: $b<R>, da: $a<R>, db: $b<R>) -> $b<R> {
                da * b + self * db
            }
        }
    )*};
}
mul_matrix!(
    (Matrix2, Vector2),
    (Matrix3, Vector3),
    (Matrix2, Matrix2),
    (Matrix3, Matrix3)
);

/// Quaternion times quaternion: the Hamilton product, the rule of [`quat_mul`](fn@quat_mul).
impl<R: Real> MulRule<Quaternion<R>> for Quaternion<R> {
    type Out = Quaternion<R>;
    #[inline(always)]
    fn mul_fwd(self, b: Self) -> Self {
        quat_mul(self, b)
    }
    #[inline]
    fn mul_adj(self, b: Self, adj: Self) -> (Self, Self) {
        adj_quat_mul(self, b, adj)
    }
    #[inline]
    fn mul_tan(self, b: Self, da: Self, db: Self) -> Self {
        tan_quat_mul(self, b, da, db)
    }
}

/// `a * b`: scalar * scalar; scalar * vector/matrix/quaternion and back; `Mat22 * Vec2`,
/// `Mat33 * Vec3`; matrix * matrix; quaternion * quaternion (Hamilton product); integers. No
/// singular points.
#[inline(always)]
pub fn mul<A: MulRule<B>, B>(a: A, b: B) -> A::Out {
    a.mul_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mul`]: `(adj b^T, a^T adj)` in general (inner products for scalar factors).
#[inline(always)]
pub fn adj_mul<A: MulRule<B>, B>(a: A, b: B, adj: A::Out) -> (A, B) {
    a.mul_adj(b, adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mul`]: `da b + a db`.
#[inline(always)]
pub fn tan_mul<A: MulRule<B>, B>(a: A, b: B, da: A, db: B) -> A::Out {
    a.mul_tan(b, da, db)
}

// ---------------------------------------------------------------------------------------------
// div

/// Rule of `a / b` for one pair of types.
#[diagnostic::on_unimplemented(
    message = "cannot divide `{Self}` by `{B}` in a kernel",
    label = "no rule for `{Self}` / `{B}`",
    note = "`/` takes two scalars of one type, or a vector or matrix and its scalar; write float literals with a point (`x / 2.0`)"
)]
pub trait DivRule<B>: Sized {
    /// The quotient's type.
    type Out;
    /// `a / b`.
    fn div_fwd(self, b: B) -> Self::Out;
    /// `(adj / b, -<adj, a> / b^2)`.
    fn div_adj(self, b: B, adj: Self::Out) -> (Self, B);
    /// `(da - a db / b) / b`.
    fn div_tan(self, b: B, da: Self, db: B) -> Self::Out;
}

/// Scalar, vector, matrix or quaternion divided by a scalar. `b == 0` gives inf/NaN like the
/// division itself.
macro_rules! div_scalar {
    ($($t:ty),*) => {$(
        impl<R: Real> DivRule<R> for $t {
            type Out = $t;
            #[inline(always)]
            fn div_fwd(self, b: R) -> $t {
                self.lin_div(b)
            }
            #[inline]
            fn div_adj(self, b: R, adj: $t) -> ($t, R) {
                // One division (a gradient need not round like the quotient it differentiates).
                let r = R::lit(1.0) / b;
                let ab = adj.lin_scale(r);
                (ab, -ab.lin_inner(self) * r)
            }
            #[inline]
            fn div_tan(self, b: R, da: $t, db: R) -> $t {
                da.lin_sub(self.lin_scale(db / b)).lin_div(b)
            }
        }
    )*};
}
div_scalar!(
    R,
    Vector2<R>,
    Vector3<R>,
    Vector4<R>,
    Matrix2<R>,
    Matrix3<R>,
    Quaternion<R>
);

/// `a / b`: scalar, vector, matrix or quaternion by a scalar; integers (truncating). At
/// `b == 0` value and derivatives are inf/NaN like the division itself (integers panic).
#[inline(always)]
pub fn div<A: DivRule<B>, B>(a: A, b: B) -> A::Out {
    a.div_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`div`]: `(adj / b, -<adj, a> / b^2)`.
#[inline(always)]
pub fn adj_div<A: DivRule<B>, B>(a: A, b: B, adj: A::Out) -> (A, B) {
    a.div_adj(b, adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`div`]: `(da - a db / b) / b`.
#[inline(always)]
pub fn tan_div<A: DivRule<B>, B>(a: A, b: B, da: A, db: B) -> A::Out {
    a.div_tan(b, da, db)
}

// ---------------------------------------------------------------------------------------------
// rem (integers only)

/// Rule of `a % b`: integers only, so that `%` on floats is a compile error rather than a
/// silently wrong gradient.
#[diagnostic::on_unimplemented(
    message = "`%` on `{Self}`: in a kernel `%` is for integers (indices) only",
    label = "`%` of a non-integer",
    note = "a float remainder has a jump where its gradient is undefined; if you need a wrap, write it explicitly (`if x >= m {{ x - m }} else {{ x }}`)"
)]
pub trait RemRule: Sized {
    /// `a % b`.
    fn rem_fwd(self, b: Self) -> Self;
}

/// `a % b` for integers (zero adjoint and tangent; there is no float `rem`).
#[inline(always)]
pub fn rem<T: RemRule>(a: T, b: T) -> T {
    a.rem_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`rem`]: zero.
#[inline(always)]
pub fn adj_rem<T: RemRule + Default>(_a: T, _b: T, _adj: T) -> (T, T) {
    (T::default(), T::default())
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`rem`]: zero.
#[inline(always)]
pub fn tan_rem<T: RemRule + Default>(_a: T, _b: T, _da: T, _db: T) -> T {
    T::default()
}

// ---------------------------------------------------------------------------------------------
// integers: no derivatives.

macro_rules! int_ops {
    ($($t:ty),*) => {$(
        impl AddRule for $t {
            #[inline(always)]
            fn add_fwd(self, b: Self) -> Self { self + b }
            #[inline(always)]
            fn add_adj(self, _: Self, _: Self) -> (Self, Self) { (0, 0) }
            #[inline(always)]
            fn add_tan(self, _: Self, _: Self, _: Self) -> Self { 0 }
        }
        impl SubRule for $t {
            #[inline(always)]
            fn sub_fwd(self, b: Self) -> Self { self - b }
            #[inline(always)]
            fn sub_adj(self, _: Self, _: Self) -> (Self, Self) { (0, 0) }
            #[inline(always)]
            fn sub_tan(self, _: Self, _: Self, _: Self) -> Self { 0 }
        }
        impl MulRule<$t> for $t {
            type Out = $t;
            #[inline(always)]
            fn mul_fwd(self, b: Self) -> Self { self * b }
            #[inline(always)]
            fn mul_adj(self, _: Self, _: Self) -> (Self, Self) { (0, 0) }
            #[inline(always)]
            fn mul_tan(self, _: Self, _: Self, _: Self) -> Self { 0 }
        }
        impl DivRule<$t> for $t {
            type Out = $t;
            #[inline(always)]
            fn div_fwd(self, b: Self) -> Self { self / b }
            #[inline(always)]
            fn div_adj(self, _: Self, _: Self) -> (Self, Self) { (0, 0) }
            #[inline(always)]
            fn div_tan(self, _: Self, _: Self, _: Self) -> Self { 0 }
        }
        impl RemRule for $t {
            #[inline(always)]
            fn rem_fwd(self, b: Self) -> Self { self % b }
        }
    )*};
}
int_ops!(u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);

macro_rules! int_neg {
    ($($t:ty),*) => {$(
        impl NegRule for $t {
            #[inline(always)]
            fn neg_fwd(self) -> Self { -self }
            #[inline(always)]
            fn neg_adj(self, _: Self) -> Self { 0 }
            #[inline(always)]
            fn neg_tan(self, _: Self) -> Self { 0 }
        }
    )*};
}
int_neg!(i8, i16, i32, i64, isize);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;
    use crate::{Mat22, Mat33, Quat, Vec2, Vec3, Vec4};

    fd_tests! {
        add_r: add, adj_add, tan_add [R = any, R = any];
        add_v2: add, adj_add, tan_add [Vec2<R> = any, Vec2<R> = any];
        add_v3: add, adj_add, tan_add [Vec3<R> = any, Vec3<R> = any];
        add_v4: add, adj_add, tan_add [Vec4<R> = any, Vec4<R> = any];
        add_m22: add, adj_add, tan_add [Mat22<R> = any, Mat22<R> = any];
        add_m33: add, adj_add, tan_add [Mat33<R> = any, Mat33<R> = any];
        add_q: add, adj_add, tan_add [Quat<R> = any, Quat<R> = any];

        sub_r: sub, adj_sub, tan_sub [R = any, R = any];
        sub_v2: sub, adj_sub, tan_sub [Vec2<R> = any, Vec2<R> = any];
        sub_v3: sub, adj_sub, tan_sub [Vec3<R> = any, Vec3<R> = any];
        sub_v4: sub, adj_sub, tan_sub [Vec4<R> = any, Vec4<R> = any];
        sub_m22: sub, adj_sub, tan_sub [Mat22<R> = any, Mat22<R> = any];
        sub_m33: sub, adj_sub, tan_sub [Mat33<R> = any, Mat33<R> = any];
        sub_q: sub, adj_sub, tan_sub [Quat<R> = any, Quat<R> = any];

        neg_r: neg, adj_neg, tan_neg [R = any];
        neg_v2: neg, adj_neg, tan_neg [Vec2<R> = any];
        neg_v3: neg, adj_neg, tan_neg [Vec3<R> = any];
        neg_v4: neg, adj_neg, tan_neg [Vec4<R> = any];
        neg_m22: neg, adj_neg, tan_neg [Mat22<R> = any];
        neg_m33: neg, adj_neg, tan_neg [Mat33<R> = any];
        neg_q: neg, adj_neg, tan_neg [Quat<R> = any];

        mul_r_r: mul, adj_mul, tan_mul [R = any, R = any];
        mul_r_v2: mul, adj_mul, tan_mul [R = any, Vec2<R> = any];
        mul_r_v3: mul, adj_mul, tan_mul [R = any, Vec3<R> = any];
        mul_r_v4: mul, adj_mul, tan_mul [R = any, Vec4<R> = any];
        mul_r_m22: mul, adj_mul, tan_mul [R = any, Mat22<R> = any];
        mul_r_m33: mul, adj_mul, tan_mul [R = any, Mat33<R> = any];
        mul_r_q: mul, adj_mul, tan_mul [R = any, Quat<R> = any];
        mul_v2_r: mul, adj_mul, tan_mul [Vec2<R> = any, R = any];
        mul_v3_r: mul, adj_mul, tan_mul [Vec3<R> = any, R = any];
        mul_v4_r: mul, adj_mul, tan_mul [Vec4<R> = any, R = any];
        mul_m22_r: mul, adj_mul, tan_mul [Mat22<R> = any, R = any];
        mul_m33_r: mul, adj_mul, tan_mul [Mat33<R> = any, R = any];
        mul_q_r: mul, adj_mul, tan_mul [Quat<R> = any, R = any];
        mul_m22_v2: mul, adj_mul, tan_mul [Mat22<R> = any, Vec2<R> = any];
        mul_m33_v3: mul, adj_mul, tan_mul [Mat33<R> = any, Vec3<R> = any];
        mul_m22_m22: mul, adj_mul, tan_mul [Mat22<R> = any, Mat22<R> = any];
        mul_m33_m33: mul, adj_mul, tan_mul [Mat33<R> = any, Mat33<R> = any];
        mul_q_q: mul, adj_mul, tan_mul [Quat<R> = any, Quat<R> = any];

        div_r_r: div, adj_div, tan_div [R = any, R = away];
        div_v2_r: div, adj_div, tan_div [Vec2<R> = any, R = away];
        div_v3_r: div, adj_div, tan_div [Vec3<R> = any, R = away];
        div_v4_r: div, adj_div, tan_div [Vec4<R> = any, R = away];
        div_m22_r: div, adj_div, tan_div [Mat22<R> = any, R = away];
        div_m33_r: div, adj_div, tan_div [Mat33<R> = any, R = away];
        div_q_r: div, adj_div, tan_div [Quat<R> = any, R = away];
    }

    macro_rules! int_cases {
        ($($t:ty),*) => {$(
            assert_eq!(add(7 as $t, 2), 9);
            assert_eq!(sub(7 as $t, 2), 5);
            assert_eq!(mul(7 as $t, 2), 14);
            assert_eq!(div(7 as $t, 2), 3);
            assert_eq!(rem(7 as $t, 2), 1);
            assert_eq!(adj_add(7 as $t, 2, 1), (0, 0));
            assert_eq!(adj_sub(7 as $t, 2, 1), (0, 0));
            assert_eq!(adj_mul(7 as $t, 2, 1), (0, 0));
            assert_eq!(adj_div(7 as $t, 2, 1), (0, 0));
            assert_eq!(adj_rem(7 as $t, 2, 1), (0, 0));
            assert_eq!(tan_add(7 as $t, 2, 1, 1), 0);
            assert_eq!(tan_sub(7 as $t, 2, 1, 1), 0);
            assert_eq!(tan_mul(7 as $t, 2, 1, 1), 0);
            assert_eq!(tan_div(7 as $t, 2, 1, 1), 0);
            assert_eq!(tan_rem(7 as $t, 2, 1, 1), 0);
        )*};
    }

    #[test]
    fn integers() {
        int_cases!(u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);
        assert_eq!(neg(3i32), -3);
        assert_eq!(neg(3i64), -3);
        assert_eq!(neg(3isize), -3);
        assert_eq!(adj_neg(3i32, 1), 0);
        assert_eq!(tan_neg(3i32, 1), 0);
        assert_eq!(rem(-7i32, 3), -1);
    }

    #[test]
    fn values() {
        let v = Vec3::new(1.0f32, 2.0, 3.0);
        assert_eq!(mul(2.0, v), Vec3::new(2.0, 4.0, 6.0));
        assert_eq!(mul(v, 2.0), Vec3::new(2.0, 4.0, 6.0));
        assert_eq!(div(v, 2.0), Vec3::new(0.5, 1.0, 1.5));
        let m = Mat33::new(1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0);
        let w = Vec3::new(1.0, 0.0, -1.0);
        assert_eq!(mul(m, w), m * w);
        assert_eq!(mul(m, m), m * m);
        let (p, q) = (
            Quat::new(1.0, 2.0, 3.0, 4.0),
            Quat::new(0.5, -1.0, 0.25, 2.0),
        );
        assert_eq!(mul(p, q), p * q);
        // i * j == k
        let (i, j) = (
            Quat::new(0.0f64, 1.0, 0.0, 0.0),
            Quat::new(0.0, 0.0, 1.0, 0.0),
        );
        assert_eq!(mul(i, j), Quat::new(0.0, 0.0, 0.0, 1.0));
    }
}
