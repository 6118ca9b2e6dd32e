//! Matrix builtins (`Mat22`, `Mat33`): `transpose`, `determinant`, `inverse`, `trace`, `ddot`,
//! and the constructors from vectors `skew` and `diag`.

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};

use super::vector_space::{zero, Linear};
use crate::{Mat33, Real, Vec3};

/// The square matrix types `Mat22<R>`, `Mat33<R>`.
#[diagnostic::on_unimplemented(
    message = "`{Self}` is not a square matrix: this builtin takes `Mat22` or `Mat33`",
    label = "expected a matrix here"
)]
pub trait MatrixValue: Linear {
    /// `m^T`.
    fn mat_transpose(self) -> Self;
    /// `m * o`.
    fn mat_mul(self, o: Self) -> Self;
    /// Sum of the diagonal.
    fn mat_trace(self) -> Self::Scalar;
    /// The identity.
    fn mat_identity() -> Self;
    /// The determinant.
    fn mat_det(self) -> Self::Scalar;
    /// The cofactor matrix `d det / d m` (`det * m^-T` when invertible; finite always).
    fn mat_cofactor(self) -> Self;
}

impl<R: Real> MatrixValue for Matrix2<R> {
    #[inline(always)]
    fn mat_transpose(self) -> Self {
        self.transpose()
    }
    #[inline(always)]
    fn mat_mul(self, o: Self) -> Self {
        self * o
    }
    #[inline(always)]
    fn mat_trace(self) -> R {
        self[(0, 0)] + self[(1, 1)]
    }
    #[inline(always)]
    fn mat_identity() -> Self {
        Matrix2::identity()
    }
    #[inline(always)]
    fn mat_det(self) -> R {
        self[(0, 0)] * self[(1, 1)] - self[(0, 1)] * self[(1, 0)]
    }
    #[inline(always)]
    fn mat_cofactor(self) -> Self {
        Matrix2::new(self[(1, 1)], -self[(1, 0)], -self[(0, 1)], self[(0, 0)])
    }
}

impl<R: Real> MatrixValue for Matrix3<R> {
    #[inline(always)]
    fn mat_transpose(self) -> Self {
        self.transpose()
    }
    #[inline(always)]
    fn mat_mul(self, o: Self) -> Self {
        self * o
    }
    #[inline(always)]
    fn mat_trace(self) -> R {
        self[(0, 0)] + self[(1, 1)] + self[(2, 2)]
    }
    #[inline(always)]
    fn mat_identity() -> Self {
        Matrix3::identity()
    }
    #[inline(always)]
    fn mat_det(self) -> R {
        let (c0, c1, c2): (Vector3<R>, Vector3<R>, Vector3<R>) = (
            self.column(0).into(),
            self.column(1).into(),
            self.column(2).into(),
        );
        c0.dot(&c1.cross(&c2))
    }
    #[inline(always)]
    fn mat_cofactor(self) -> Self {
        let (c0, c1, c2): (Vector3<R>, Vector3<R>, Vector3<R>) = (
            self.column(0).into(),
            self.column(1).into(),
            self.column(2).into(),
        );
        Matrix3::from_columns(&[c1.cross(&c2), c2.cross(&c0), c0.cross(&c1)])
    }
}

/// `m^T`. No singular points.
#[inline(always)]
pub fn transpose<M: MatrixValue>(m: M) -> M {
    m.mat_transpose()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`transpose`](fn@transpose): `adj^T`.
#[inline]
pub fn adj_transpose<M: MatrixValue>(_m: M, adj: M) -> M {
    adj.mat_transpose()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`transpose`](fn@transpose): `dm^T`.
#[inline]
pub fn tan_transpose<M: MatrixValue>(_m: M, dm: M) -> M {
    dm.mat_transpose()
}

/// `det(m)`. Its gradient is the cofactor matrix, finite everywhere (also for singular `m`).
#[inline(always)]
pub fn determinant<M: MatrixValue>(m: M) -> M::Scalar {
    m.mat_det()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`determinant`](fn@determinant): `adj * cof(m)` (`= adj det(m) m^-T` when invertible).
#[inline]
pub fn adj_determinant<M: MatrixValue>(m: M, adj: M::Scalar) -> M {
    m.mat_cofactor().lin_scale(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`determinant`](fn@determinant): `cof(m) : dm`.
#[inline]
pub fn tan_determinant<M: MatrixValue>(m: M, dm: M) -> M::Scalar {
    m.mat_cofactor().lin_inner(dm)
}

/// `m^-1 = cof(m)^T / det(m)`. Singular point: for `det(m) == 0` the result is the zero
/// matrix with zero gradient (Warp's convention).
#[inline(always)]
pub fn inverse<M: MatrixValue>(m: M) -> M {
    let d = m.mat_det();
    if d != zero() {
        m.mat_cofactor().mat_transpose().lin_div(d)
    } else {
        M::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`inverse`](fn@inverse): `-B^T adj B^T` with `B = m^-1`; zero for singular `m`.
#[inline]
pub fn adj_inverse<M: MatrixValue>(m: M, adj: M) -> M {
    let b = inverse(m).mat_transpose();
    b.mat_mul(adj).mat_mul(b).lin_neg()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`inverse`](fn@inverse): `-B dm B` with `B = m^-1`; zero for singular `m`.
#[inline]
pub fn tan_inverse<M: MatrixValue>(m: M, dm: M) -> M {
    let b = inverse(m);
    b.mat_mul(dm).mat_mul(b).lin_neg()
}

/// `tr(m)`, the sum of the diagonal. No singular points.
#[inline(always)]
pub fn trace<M: MatrixValue>(m: M) -> M::Scalar {
    m.mat_trace()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`trace`](fn@trace): `adj I`.
#[inline]
pub fn adj_trace<M: MatrixValue>(_m: M, adj: M::Scalar) -> M {
    M::mat_identity().lin_scale(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`trace`](fn@trace): `tr(dm)`.
#[inline]
pub fn tan_trace<M: MatrixValue>(_m: M, dm: M) -> M::Scalar {
    dm.mat_trace()
}

/// `a : b`, the Frobenius inner product `sum_ij a_ij b_ij`. No singular points.
#[inline(always)]
pub fn ddot<M: MatrixValue>(a: M, b: M) -> M::Scalar {
    a.lin_inner(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`ddot`](fn@ddot): `(adj b, adj a)`.
#[inline]
pub fn adj_ddot<M: MatrixValue>(a: M, b: M, adj: M::Scalar) -> (M, M) {
    (b.lin_scale(adj), a.lin_scale(adj))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`ddot`](fn@ddot): `da : b + a : db`.
#[inline]
pub fn tan_ddot<M: MatrixValue>(a: M, b: M, da: M, db: M) -> M::Scalar {
    da.lin_inner(b) + a.lin_inner(db)
}

/// The vector `w` with `<g, skew(w)> = g . w` for every 3x3 `g`: the adjoint of [`skew`](fn@skew).
#[inline]
pub(crate) fn unskew<R: Real>(g: Mat33<R>) -> Vec3<R> {
    Vec3::new(
        g[(2, 1)] - g[(1, 2)],
        g[(0, 2)] - g[(2, 0)],
        g[(1, 0)] - g[(0, 1)],
    )
}

/// The cross-product matrix of `a`: `skew(a) * b == cross(a, b)`. No singular points.
#[inline(always)]
pub fn skew<R: Real>(a: Vec3<R>) -> Mat33<R> {
    let z = R::zero();
    Mat33::new(z, -a.z, a.y, a.z, z, -a.x, -a.y, a.x, z)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`skew`](fn@skew): `(adj_21 - adj_12, adj_02 - adj_20, adj_10 - adj_01)`.
#[inline]
pub fn adj_skew<R: Real>(_a: Vec3<R>, adj: Mat33<R>) -> Vec3<R> {
    unskew(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`skew`](fn@skew): `skew(da)`.
#[inline]
pub fn tan_skew<R: Real>(_a: Vec3<R>, da: Vec3<R>) -> Mat33<R> {
    skew(da)
}

/// Rule of `diag(v)`: `Vec2 -> Mat22`, `Vec3 -> Mat33`.
pub trait DiagRule: Linear {
    /// The matrix type.
    type Out;
    /// The diagonal matrix with diagonal `self`.
    fn diag_fwd(self) -> Self::Out;
    /// The diagonal of `m`.
    fn diag_of(m: Self::Out) -> Self;
}

macro_rules! diag_impl {
    ($(($v:ident, $m:ident)),*) => {$(
        impl<R: Real> DiagRule for $v<R> {
            type Out = $m<R>;
            #[inline(always)]
            fn diag_fwd(self) -> $m<R> {
                $m::from_diagonal(&self)
            }
            #[inline(always)]
            fn diag_of(m: $m<R>) -> Self {
                m.diagonal()
            }
        }
    )*};
}
diag_impl!((Vector2, Matrix2), (Vector3, Matrix3));

/// The diagonal matrix with diagonal `v`: `Vec2 -> Mat22`, `Vec3 -> Mat33`. No singular points.
#[inline(always)]
pub fn diag<V: DiagRule>(v: V) -> V::Out {
    v.diag_fwd()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`diag`](fn@diag): the diagonal of `adj`.
#[inline]
pub fn adj_diag<V: DiagRule>(_v: V, adj: V::Out) -> V {
    V::diag_of(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`diag`](fn@diag): `diag(dv)`.
#[inline]
pub fn tan_diag<V: DiagRule>(_v: V, dv: V) -> V::Out {
    dv.diag_fwd()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;
    use crate::math::cross;
    use crate::{Mat22, Vec2};

    fd_tests! {
        transpose_m22: transpose, adj_transpose, tan_transpose [Mat22<R> = any];
        transpose_m33: transpose, adj_transpose, tan_transpose [Mat33<R> = any];
        determinant_m22: determinant, adj_determinant, tan_determinant [Mat22<R> = any];
        determinant_m33: determinant, adj_determinant, tan_determinant [Mat33<R> = any];
        inverse_m22: inverse, adj_inverse, tan_inverse [Mat22<R> = wellcond];
        inverse_m33: inverse, adj_inverse, tan_inverse [Mat33<R> = wellcond];
        trace_m22: trace, adj_trace, tan_trace [Mat22<R> = any];
        trace_m33: trace, adj_trace, tan_trace [Mat33<R> = any];
        ddot_m22: ddot, adj_ddot, tan_ddot [Mat22<R> = any, Mat22<R> = any];
        ddot_m33: ddot, adj_ddot, tan_ddot [Mat33<R> = any, Mat33<R> = any];
        skew_v3: skew, adj_skew, tan_skew [Vec3<R> = any];
        diag_v2: diag, adj_diag, tan_diag [Vec2<R> = any];
        diag_v3: diag, adj_diag, tan_diag [Vec3<R> = any];
    }

    #[test]
    fn values() {
        let m = Mat33::new(2.0f64, 1.0, 0.5, -1.0, 3.0, 0.25, 0.0, 1.0, 4.0);
        assert!((determinant(m) - m.determinant()).abs() < 1e-12);
        assert!((inverse(m) - m.try_inverse().unwrap()).norm() < 1e-12);
        let m2 = Mat22::new(2.0f64, 1.0, -1.0, 3.0);
        assert!((determinant(m2) - 7.0).abs() < 1e-15);
        assert!((inverse(m2) * m2 - Mat22::identity()).norm() < 1e-15);
        assert_eq!(trace(m), 9.0);
        assert_eq!(ddot(m2, Mat22::identity()), 5.0);
        let (a, b) = (Vec3::new(1.0f64, 2.0, 3.0), Vec3::new(-1.0, 0.5, 2.0));
        assert_eq!(skew(a) * b, cross(a, b));
        assert_eq!(diag(Vec2::new(1.0f32, 2.0)), Mat22::new(1.0, 0.0, 0.0, 2.0));
        assert_eq!(transpose(m), m.transpose());
    }

    #[test]
    fn singular_points() {
        // singular matrix: inverse is zero with zero gradient; determinant's gradient finite
        let s = Mat33::new(1.0f64, 2.0, 3.0, 2.0, 4.0, 6.0, 0.0, 1.0, 1.0);
        assert_eq!(determinant(s), 0.0);
        assert_eq!(inverse(s), Mat33::zeros());
        assert_eq!(adj_inverse(s, Mat33::identity()), Mat33::zeros());
        assert_eq!(tan_inverse(s, Mat33::identity()), Mat33::zeros());
        assert!(adj_determinant(s, 1.0).iter().all(|x| x.is_finite()));
        let z = Mat22::<f32>::zeros();
        assert_eq!(inverse(z), z);
        assert_eq!(adj_determinant(z, 1.0), z);
    }
}
