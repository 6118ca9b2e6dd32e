//! Vector builtins: `dot`, `cross`, `length`, `length_sq`, `normalize`, `outer`, and the
//! componentwise `cw_mul` / `cw_div` (vectors and matrices).

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3, Vector4};

use super::vector_space::{zero, Linear, VectorValue};
use crate::{Real, Vec3};

/// `a . b` for `Vec2/3/4`. No singular points.
#[inline(always)]
pub fn dot<V: VectorValue>(a: V, b: V) -> V::Scalar {
    a.lin_inner(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`dot`](fn@dot): `(adj b, adj a)`.
#[inline]
pub fn adj_dot<V: VectorValue>(a: V, b: V, adj: V::Scalar) -> (V, V) {
    (b.lin_scale(adj), a.lin_scale(adj))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`dot`](fn@dot): `da . b + a . db`.
#[inline]
pub fn tan_dot<V: VectorValue>(a: V, b: V, da: V, db: V) -> V::Scalar {
    da.lin_inner(b) + a.lin_inner(db)
}

/// `a x b` for `Vec3`. No singular points.
#[inline(always)]
pub fn cross<R: Real>(a: Vec3<R>, b: Vec3<R>) -> Vec3<R> {
    a.cross(&b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`cross`](fn@cross): `(b x adj, adj x a)`.
#[inline]
pub fn adj_cross<R: Real>(a: Vec3<R>, b: Vec3<R>, adj: Vec3<R>) -> (Vec3<R>, Vec3<R>) {
    (b.cross(&adj), adj.cross(&a))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`cross`](fn@cross): `da x b + a x db`.
#[inline]
pub fn tan_cross<R: Real>(a: Vec3<R>, b: Vec3<R>, da: Vec3<R>, db: Vec3<R>) -> Vec3<R> {
    da.cross(&b) + a.cross(&db)
}

/// `sqrt(v . v)` for `Vec2/3/4`. Singular point: at `v == 0` (any `|v| <= R::tiny()`) the
/// gradient is 0.
#[inline(always)]
pub fn length<V: VectorValue>(v: V) -> V::Scalar {
    super::scalar::sqrt(v.lin_inner(v))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`length`](fn@length): `adj v / |v|`, 0 for `|v| <= R::tiny()`.
#[inline]
pub fn adj_length<V: VectorValue>(v: V, adj: V::Scalar) -> V {
    let l = length(v);
    if l > V::Scalar::tiny() {
        v.lin_scale(adj / l)
    } else {
        V::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`length`](fn@length): `v . dv / |v|`, 0 for `|v| <= R::tiny()`.
#[inline]
pub fn tan_length<V: VectorValue>(v: V, dv: V) -> V::Scalar {
    let l = length(v);
    if l > V::Scalar::tiny() {
        v.lin_inner(dv) / l
    } else {
        zero()
    }
}

/// `v . v` for `Vec2/3/4`. No singular points.
#[inline(always)]
pub fn length_sq<V: VectorValue>(v: V) -> V::Scalar {
    v.lin_inner(v)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`length_sq`](fn@length_sq): `2 adj v`.
#[inline]
pub fn adj_length_sq<V: VectorValue>(v: V, adj: V::Scalar) -> V {
    v.lin_scale(adj + adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`length_sq`](fn@length_sq): `2 v . dv`.
#[inline]
pub fn tan_length_sq<V: VectorValue>(v: V, dv: V) -> V::Scalar {
    let d = v.lin_inner(dv);
    d + d
}

/// `v / |v|` for `Vec2/3/4`. Singular point: for `|v| <= R::tiny()` (1e-18 in f32, 1e-150 in
/// f64) the result is the zero vector, with zero gradient.
#[inline(always)]
pub fn normalize<V: VectorValue>(v: V) -> V {
    let l = length(v);
    if l > V::Scalar::tiny() {
        v.lin_div(l)
    } else {
        V::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`normalize`](fn@normalize): `(adj - n (n . adj)) / |v|` with `n = v / |v|`; 0 for
/// `|v| <= R::tiny()`.
#[inline]
pub fn adj_normalize<V: VectorValue>(v: V, adj: V) -> V {
    let l = length(v);
    if l > V::Scalar::tiny() {
        let n = v.lin_div(l); // as the forward computes it (so the two are one)
        let r = V::Scalar::lit(1.0) / l;
        adj.lin_sub(n.lin_scale(n.lin_inner(adj))).lin_scale(r)
    } else {
        V::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`normalize`](fn@normalize): `(dv - n (n . dv)) / |v|`; 0 for `|v| <= R::tiny()`.
#[inline]
pub fn tan_normalize<V: VectorValue>(v: V, dv: V) -> V {
    adj_normalize(v, dv)
}

/// Rule of `outer(a, b) = a b^T`: `Vec2 -> Mat22`, `Vec3 -> Mat33`.
pub trait OuterRule: Linear {
    /// The matrix type.
    type Out;
    /// `a b^T`.
    fn outer_fwd(self, b: Self) -> Self::Out;
    /// `(adj b, adj^T a)`.
    fn outer_adj(self, b: Self, adj: Self::Out) -> (Self, Self);
    /// `da b^T + a db^T`.
    fn outer_tan(self, b: Self, da: Self, db: Self) -> Self::Out;
}

macro_rules! outer_impl {
    ($(($v:ident, $m:ident)),*) => {$(
        impl<R: Real> OuterRule for $v<R> {
            type Out = $m<R>;
            #[inline(always)]
            fn outer_fwd(self, b: Self) -> $m<R> {
                self * b.transpose()
            }
            #[inline]
            fn outer_adj(self, b: Self, adj: $m<R>) -> (Self, Self) {
                (adj * b, adj.tr_mul(&self))
            }
            #[inline]
            fn outer_tan(self, b: Self, da: Self, db: Self) -> $m<R> {
                da * b.transpose() + self * db.transpose()
            }
        }
    )*};
}
outer_impl!((Vector2, Matrix2), (Vector3, Matrix3));

/// Outer product `a b^T`: `Vec2 x Vec2 -> Mat22`, `Vec3 x Vec3 -> Mat33`. No singular points.
#[inline(always)]
pub fn outer<V: OuterRule>(a: V, b: V) -> V::Out {
    a.outer_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`outer`](fn@outer): `(adj b, adj^T a)`.
#[inline]
pub fn adj_outer<V: OuterRule>(a: V, b: V, adj: V::Out) -> (V, V) {
    a.outer_adj(b, adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`outer`](fn@outer): `da b^T + a db^T`.
#[inline]
pub fn tan_outer<V: OuterRule>(a: V, b: V, da: V, db: V) -> V::Out {
    a.outer_tan(b, da, db)
}

/// Componentwise products and quotients: `Vec2/3/4`, `Mat22/33`.
pub trait Componentwise: Linear {
    /// `a_k * b_k`.
    fn cw_mul_fwd(self, b: Self) -> Self;
    /// `a_k / b_k`.
    fn cw_div_fwd(self, b: Self) -> Self;
}

macro_rules! componentwise_impl {
    ($($t:ident),*) => {$(
        impl<R: Real> Componentwise for $t<R> {
            #[inline(always)]
            fn cw_mul_fwd(self, b: Self) -> Self {
                self.component_mul(&b)
            }
            #[inline(always)]
            fn cw_div_fwd(self, b: Self) -> Self {
                self.component_div(&b)
            }
        }
    )*};
}
componentwise_impl!(Vector2, Vector3, Vector4, Matrix2, Matrix3);

/// Componentwise product `a_k b_k` (vectors, matrices). No singular points.
#[inline(always)]
pub fn cw_mul<T: Componentwise>(a: T, b: T) -> T {
    a.cw_mul_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`cw_mul`](fn@cw_mul): `(adj * b, adj * a)` componentwise.
#[inline]
pub fn adj_cw_mul<T: Componentwise>(a: T, b: T, adj: T) -> (T, T) {
    (adj.cw_mul_fwd(b), adj.cw_mul_fwd(a))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`cw_mul`](fn@cw_mul): `da * b + a * db` componentwise.
#[inline]
pub fn tan_cw_mul<T: Componentwise>(a: T, b: T, da: T, db: T) -> T {
    da.cw_mul_fwd(b).lin_add(a.cw_mul_fwd(db))
}

/// Componentwise quotient `a_k / b_k` (vectors, matrices). `b_k == 0` gives inf/NaN like the
/// division itself.
#[inline(always)]
pub fn cw_div<T: Componentwise>(a: T, b: T) -> T {
    a.cw_div_fwd(b)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`cw_div`](fn@cw_div): `(adj / b, -adj * a / b^2)` componentwise.
#[inline]
pub fn adj_cw_div<T: Componentwise>(a: T, b: T, adj: T) -> (T, T) {
    let ab = adj.cw_div_fwd(b);
    (ab, ab.cw_mul_fwd(a.cw_div_fwd(b)).lin_neg())
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`cw_div`](fn@cw_div): `(da - a * db / b) / b` componentwise.
#[inline]
pub fn tan_cw_div<T: Componentwise>(a: T, b: T, da: T, db: T) -> T {
    da.lin_sub(a.cw_mul_fwd(db).cw_div_fwd(b)).cw_div_fwd(b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;
    use crate::{Mat22, Mat33, Value, Vec2, Vec4};

    fd_tests! {
        dot_v2: dot, adj_dot, tan_dot [Vec2<R> = any, Vec2<R> = any];
        dot_v3: dot, adj_dot, tan_dot [Vec3<R> = any, Vec3<R> = any];
        dot_v4: dot, adj_dot, tan_dot [Vec4<R> = any, Vec4<R> = any];
        cross_v3: cross, adj_cross, tan_cross [Vec3<R> = any, Vec3<R> = any];
        length_v2: length, adj_length, tan_length [Vec2<R> = away];
        length_v3: length, adj_length, tan_length [Vec3<R> = away];
        length_v4: length, adj_length, tan_length [Vec4<R> = away];
        length_sq_v2: length_sq, adj_length_sq, tan_length_sq [Vec2<R> = any];
        length_sq_v3: length_sq, adj_length_sq, tan_length_sq [Vec3<R> = any];
        length_sq_v4: length_sq, adj_length_sq, tan_length_sq [Vec4<R> = any];
        normalize_v2: normalize, adj_normalize, tan_normalize [Vec2<R> = away];
        normalize_v3: normalize, adj_normalize, tan_normalize [Vec3<R> = away];
        normalize_v4: normalize, adj_normalize, tan_normalize [Vec4<R> = away];
        outer_v2: outer, adj_outer, tan_outer [Vec2<R> = any, Vec2<R> = any];
        outer_v3: outer, adj_outer, tan_outer [Vec3<R> = any, Vec3<R> = any];
        cw_mul_v2: cw_mul, adj_cw_mul, tan_cw_mul [Vec2<R> = any, Vec2<R> = any];
        cw_mul_v3: cw_mul, adj_cw_mul, tan_cw_mul [Vec3<R> = any, Vec3<R> = any];
        cw_mul_v4: cw_mul, adj_cw_mul, tan_cw_mul [Vec4<R> = any, Vec4<R> = any];
        cw_mul_m22: cw_mul, adj_cw_mul, tan_cw_mul [Mat22<R> = any, Mat22<R> = any];
        cw_mul_m33: cw_mul, adj_cw_mul, tan_cw_mul [Mat33<R> = any, Mat33<R> = any];
        cw_div_v2: cw_div, adj_cw_div, tan_cw_div [Vec2<R> = any, Vec2<R> = away];
        cw_div_v3: cw_div, adj_cw_div, tan_cw_div [Vec3<R> = any, Vec3<R> = away];
        cw_div_v4: cw_div, adj_cw_div, tan_cw_div [Vec4<R> = any, Vec4<R> = away];
        cw_div_m22: cw_div, adj_cw_div, tan_cw_div [Mat22<R> = any, Mat22<R> = away];
        cw_div_m33: cw_div, adj_cw_div, tan_cw_div [Mat33<R> = any, Mat33<R> = away];
    }

    #[test]
    fn singular_points() {
        let z = Vec3::<f64>::zeros();
        let one = Vec3::new(1.0, 1.0, 1.0);
        assert_eq!(length(z), 0.0);
        assert_eq!(adj_length(z, 1.0), z);
        assert_eq!(tan_length(z, one), 0.0);
        assert_eq!(normalize(z), z);
        assert_eq!(adj_normalize(z, one), z);
        assert_eq!(tan_normalize(z, one), z);
        // f32, below R::tiny(): treated as zero, never inf/NaN
        let t = Vec2::new(1e-20f32, 0.0);
        assert_eq!(normalize(t), Vec2::zeros());
        assert_eq!(adj_length(t, 1.0), Vec2::zeros());
        assert_eq!(adj_normalize(t, Vec2::new(1.0, 1.0)), Vec2::zeros());
        // just above: finite
        let s = Vec4::new(1e-17f32, 0.0, 0.0, 0.0);
        assert_eq!(normalize(s), Vec4::new(1.0, 0.0, 0.0, 0.0));
        let g = adj_normalize(s, Vec4::new(1.0, 1.0, 1.0, 1.0));
        assert!((0..4).all(|k| g.component(k).is_finite()));
    }

    #[test]
    fn values() {
        let (a, b) = (Vec3::new(1.0f64, 2.0, 3.0), Vec3::new(-1.0, 0.5, 2.0));
        assert_eq!(dot(a, b), a.dot(&b));
        assert_eq!(cross(a, b), a.cross(&b));
        assert_eq!(length(Vec2::new(3.0f32, 4.0)), 5.0);
        assert_eq!(length_sq(Vec2::new(3.0f32, 4.0)), 25.0);
        assert_eq!(outer(a, b), a * b.transpose());
        assert_eq!(cw_mul(a, b), Vec3::new(-1.0, 1.0, 6.0));
        assert_eq!(cw_div(a, b), Vec3::new(-1.0, 4.0, 1.5));
    }
}
