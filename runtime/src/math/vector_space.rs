//! The vector-space structure shared by the differentiable value types, and the markers that
//! say which builtins a type takes. Generic rules (`add`, `lerp`, `R * v`, ...) are written once
//! over these traits.
//!
//! The methods have prefixed names (`lin_*`) so that bringing the traits into scope (the prelude
//! does) never makes a method call like `x.sin()` or `a.dot(&b)` ambiguous.

use nalgebra::{Matrix2, Matrix3, Quaternion, Vector2, Vector3, Vector4};

use crate::{Real, Value};

/// A differentiable value that is a vector space over its scalar: `R`, `Vec2/3/4<R>`,
/// `Mat22/33<R>`, `Quat<R>`. `lin_inner` is the Euclidean inner product of the components
/// (the Frobenius product for matrices), the one adjoints are taken against.
#[diagnostic::on_unimplemented(
    message = "`{Self}` is not a differentiable value of a kernel",
    label = "this builtin takes a float scalar, vector, matrix or quaternion here",
    note = "kernel values are f32, f64 or `R: Real`, `Vec2/3/4`, `Mat22/33`, `Quat` of one scalar type; integers are indices"
)]
pub trait Linear: Value {
    /// The scalar type (`f32` or `f64`).
    type Scalar: Real;
    /// `self + o`.
    fn lin_add(self, o: Self) -> Self;
    /// `self - o`.
    fn lin_sub(self, o: Self) -> Self;
    /// `-self`.
    fn lin_neg(self) -> Self;
    /// `self * s`.
    fn lin_scale(self, s: Self::Scalar) -> Self;
    /// `self / s`.
    fn lin_div(self, s: Self::Scalar) -> Self;
    /// Sum over components of `self_k * o_k`.
    fn lin_inner(self, o: Self) -> Self::Scalar;
}

impl<R: Real> Linear for R {
    type Scalar = R;
    #[inline(always)]
    fn lin_add(self, o: Self) -> Self {
        self + o
    }
    #[inline(always)]
    fn lin_sub(self, o: Self) -> Self {
        self - o
    }
    #[inline(always)]
    fn lin_neg(self) -> Self {
        -self
    }
    #[inline(always)]
    fn lin_scale(self, s: R) -> Self {
        self * s
    }
    #[inline(always)]
    fn lin_div(self, s: R) -> Self {
        self / s
    }
    #[inline(always)]
    fn lin_inner(self, o: Self) -> R {
        self * o
    }
}

macro_rules! linear_matrix {
    ($($t:ident),*) => {$(
        impl<R: Real> Linear for $t<R> {
            type Scalar = R;
            #[inline(always)]
            fn lin_add(self, o: Self) -> Self {
                self + o
            }
            #[inline(always)]
            fn lin_sub(self, o: Self) -> Self {
                self - o
            }
            #[inline(always)]
            fn lin_neg(self) -> Self {
                -self
            }
            #[inline(always)]
            fn lin_scale(self, s: R) -> Self {
                self * s
            }
            #[inline(always)]
            fn lin_div(self, s: R) -> Self {
                self / s
            }
            #[inline(always)]
            fn lin_inner(self, o: Self) -> R {
                self.dot(&o)
            }
        }
    )*};
}
linear_matrix!(Vector2, Vector3, Vector4, Matrix2, Matrix3);

impl<R: Real> Linear for Quaternion<R> {
    type Scalar = R;
    #[inline(always)]
    fn lin_add(self, o: Self) -> Self {
        Quaternion::from(self.coords + o.coords)
    }
    #[inline(always)]
    fn lin_sub(self, o: Self) -> Self {
        Quaternion::from(self.coords - o.coords)
    }
    #[inline(always)]
    fn lin_neg(self) -> Self {
        Quaternion::from(-self.coords)
    }
    #[inline(always)]
    fn lin_scale(self, s: R) -> Self {
        Quaternion::from(self.coords * s)
    }
    #[inline(always)]
    fn lin_div(self, s: R) -> Self {
        Quaternion::from(self.coords / s)
    }
    #[inline(always)]
    fn lin_inner(self, o: Self) -> R {
        self.coords.dot(&o.coords)
    }
}

/// The vector types `Vec2/3/4<R>`: what `dot`, `length`, `length_sq` and `normalize` take.
#[diagnostic::on_unimplemented(
    message = "`{Self}` is not a vector: this builtin takes `Vec2`, `Vec3` or `Vec4`",
    label = "expected a vector here",
    note = "`dot`, `length`, `length_sq` and `normalize` take vectors of one scalar type (both arguments the same)"
)]
pub trait VectorValue: Linear {}
impl<R: Real> VectorValue for Vector2<R> {}
impl<R: Real> VectorValue for Vector3<R> {}
impl<R: Real> VectorValue for Vector4<R> {}

/// Totally ordered scalars: `R` and the integer types. What `min`, `max` and `clamp` take.
#[diagnostic::on_unimplemented(
    message = "`{Self}` is not an ordered scalar: `min`, `max` and `clamp` take two scalars of one type",
    label = "expected a scalar (f32, f64, `R`, or an integer) here"
)]
pub trait Ordered: Value + PartialOrd {}
impl<R: Real> Ordered for R {}
macro_rules! ordered_int {
    ($($t:ty),*) => {$( impl Ordered for $t {} )*};
}
ordered_int!(u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);

/// `0` of a scalar reached through an associated type (where `R::zero()` is out of scope).
#[inline(always)]
pub(crate) fn zero<R: Real>() -> R {
    R::zero()
}

/// `1` of a scalar reached through an associated type.
#[inline(always)]
pub(crate) fn one<R: Real>() -> R {
    R::one()
}
