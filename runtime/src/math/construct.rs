//! Constructors: vectors and matrices from scalars (`vec2`, `vec3`, `vec4`, `mat22`, `mat33`,
//! row-major), matrices from columns or rows (`mat22_cols`, ...), quaternions (`quat`), and the
//! constants `mat22_identity`, `mat33_identity`, `quat_identity`. All are linear, with no
//! singular points: adjoints take the components apart again, tangents build the same value
//! from the tangents.

use crate::{Mat22, Mat33, Quat, Real, Vec2, Vec3, Vec4};

/// `(x, y)`.
///
/// No singular points (linear).
#[inline(always)]
pub fn vec2<R: Real>(x: R, y: R) -> Vec2<R> {
    Vec2::new(x, y)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`vec2`](fn@vec2): the components of `adj`.
#[inline]
pub fn adj_vec2<R: Real>(_x: R, _y: R, adj: Vec2<R>) -> (R, R) {
    (adj.x, adj.y)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`vec2`](fn@vec2): `(dx, dy)`.
#[inline]
pub fn tan_vec2<R: Real>(_x: R, _y: R, dx: R, dy: R) -> Vec2<R> {
    Vec2::new(dx, dy)
}

/// `(x, y, z)`.
///
/// No singular points (linear).
#[inline(always)]
pub fn vec3<R: Real>(x: R, y: R, z: R) -> Vec3<R> {
    Vec3::new(x, y, z)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`vec3`](fn@vec3): the components of `adj`.
#[inline]
pub fn adj_vec3<R: Real>(_x: R, _y: R, _z: R, adj: Vec3<R>) -> (R, R, R) {
    (adj.x, adj.y, adj.z)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`vec3`](fn@vec3): `(dx, dy, dz)`.
#[inline]
pub fn tan_vec3<R: Real>(_x: R, _y: R, _z: R, dx: R, dy: R, dz: R) -> Vec3<R> {
    Vec3::new(dx, dy, dz)
}

/// `(x, y, z, w)`.
///
/// No singular points (linear).
#[inline(always)]
pub fn vec4<R: Real>(x: R, y: R, z: R, w: R) -> Vec4<R> {
    Vec4::new(x, y, z, w)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`vec4`](fn@vec4): the components of `adj`.
#[inline]
pub fn adj_vec4<R: Real>(_x: R, _y: R, _z: R, _w: R, adj: Vec4<R>) -> (R, R, R, R) {
    (adj.x, adj.y, adj.z, adj.w)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`vec4`](fn@vec4): `(dx, dy, dz, dw)`.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn tan_vec4<R: Real>(_x: R, _y: R, _z: R, _w: R, dx: R, dy: R, dz: R, dw: R) -> Vec4<R> {
    Vec4::new(dx, dy, dz, dw)
}

/// The 2x2 matrix `[[m00, m01], [m10, m11]]` (arguments in row-major order).
///
/// No singular points (linear).
#[inline(always)]
pub fn mat22<R: Real>(m00: R, m01: R, m10: R, m11: R) -> Mat22<R> {
    Mat22::new(m00, m01, m10, m11)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mat22`](fn@mat22): the entries of `adj`, row-major.
#[inline]
pub fn adj_mat22<R: Real>(_m00: R, _m01: R, _m10: R, _m11: R, adj: Mat22<R>) -> (R, R, R, R) {
    (adj[(0, 0)], adj[(0, 1)], adj[(1, 0)], adj[(1, 1)])
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mat22`](fn@mat22): the matrix of the tangents.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn tan_mat22<R: Real>(
    _m00: R,
    _m01: R,
    _m10: R,
    _m11: R,
    d00: R,
    d01: R,
    d10: R,
    d11: R,
) -> Mat22<R> {
    Mat22::new(d00, d01, d10, d11)
}

/// The 3x3 matrix with rows `(m00, m01, m02)`, `(m10, m11, m12)`, `(m20, m21, m22)`
/// (arguments in row-major order).
///
/// No singular points (linear).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub fn mat33<R: Real>(
    m00: R,
    m01: R,
    m02: R,
    m10: R,
    m11: R,
    m12: R,
    m20: R,
    m21: R,
    m22: R,
) -> Mat33<R> {
    Mat33::new(m00, m01, m02, m10, m11, m12, m20, m21, m22)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mat33`](fn@mat33): the entries of `adj`, row-major.
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
#[inline]
pub fn adj_mat33<R: Real>(
    _m00: R,
    _m01: R,
    _m02: R,
    _m10: R,
    _m11: R,
    _m12: R,
    _m20: R,
    _m21: R,
    _m22: R,
    adj: Mat33<R>,
) -> (R, R, R, R, R, R, R, R, R) {
    (
        adj[(0, 0)],
        adj[(0, 1)],
        adj[(0, 2)],
        adj[(1, 0)],
        adj[(1, 1)],
        adj[(1, 2)],
        adj[(2, 0)],
        adj[(2, 1)],
        adj[(2, 2)],
    )
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mat33`](fn@mat33): the matrix of the tangents.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn tan_mat33<R: Real>(
    _m00: R,
    _m01: R,
    _m02: R,
    _m10: R,
    _m11: R,
    _m12: R,
    _m20: R,
    _m21: R,
    _m22: R,
    d00: R,
    d01: R,
    d02: R,
    d10: R,
    d11: R,
    d12: R,
    d20: R,
    d21: R,
    d22: R,
) -> Mat33<R> {
    Mat33::new(d00, d01, d02, d10, d11, d12, d20, d21, d22)
}

/// The 2x2 matrix with columns `c0`, `c1`.
///
/// No singular points (linear).
#[inline(always)]
pub fn mat22_cols<R: Real>(c0: Vec2<R>, c1: Vec2<R>) -> Mat22<R> {
    Mat22::from_columns(&[c0, c1])
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mat22_cols`](fn@mat22_cols): the columns of `adj`.
#[inline]
pub fn adj_mat22_cols<R: Real>(_c0: Vec2<R>, _c1: Vec2<R>, adj: Mat22<R>) -> (Vec2<R>, Vec2<R>) {
    (adj.column(0).into(), adj.column(1).into())
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mat22_cols`](fn@mat22_cols): the matrix with columns `dc0`, `dc1`.
#[inline]
pub fn tan_mat22_cols<R: Real>(_c0: Vec2<R>, _c1: Vec2<R>, d0: Vec2<R>, d1: Vec2<R>) -> Mat22<R> {
    mat22_cols(d0, d1)
}

/// The 3x3 matrix with columns `c0`, `c1`, `c2`.
///
/// No singular points (linear).
#[inline(always)]
pub fn mat33_cols<R: Real>(c0: Vec3<R>, c1: Vec3<R>, c2: Vec3<R>) -> Mat33<R> {
    Mat33::from_columns(&[c0, c1, c2])
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mat33_cols`](fn@mat33_cols): the columns of `adj`.
#[inline]
pub fn adj_mat33_cols<R: Real>(
    _c0: Vec3<R>,
    _c1: Vec3<R>,
    _c2: Vec3<R>,
    adj: Mat33<R>,
) -> (Vec3<R>, Vec3<R>, Vec3<R>) {
    (
        adj.column(0).into(),
        adj.column(1).into(),
        adj.column(2).into(),
    )
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mat33_cols`](fn@mat33_cols): the matrix with columns `dc0`, `dc1`, `dc2`.
#[inline]
pub fn tan_mat33_cols<R: Real>(
    _c0: Vec3<R>,
    _c1: Vec3<R>,
    _c2: Vec3<R>,
    d0: Vec3<R>,
    d1: Vec3<R>,
    d2: Vec3<R>,
) -> Mat33<R> {
    mat33_cols(d0, d1, d2)
}

/// The 2x2 matrix with rows `r0`, `r1` (given as vectors).
///
/// No singular points (linear).
#[inline(always)]
pub fn mat22_rows<R: Real>(r0: Vec2<R>, r1: Vec2<R>) -> Mat22<R> {
    Mat22::from_rows(&[r0.transpose(), r1.transpose()])
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mat22_rows`](fn@mat22_rows): the rows of `adj`.
#[inline]
pub fn adj_mat22_rows<R: Real>(_r0: Vec2<R>, _r1: Vec2<R>, adj: Mat22<R>) -> (Vec2<R>, Vec2<R>) {
    (adj.row(0).transpose(), adj.row(1).transpose())
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mat22_rows`](fn@mat22_rows): the matrix with rows `dr0`, `dr1`.
#[inline]
pub fn tan_mat22_rows<R: Real>(_r0: Vec2<R>, _r1: Vec2<R>, d0: Vec2<R>, d1: Vec2<R>) -> Mat22<R> {
    mat22_rows(d0, d1)
}

/// The 3x3 matrix with rows `r0`, `r1`, `r2` (given as vectors).
///
/// No singular points (linear).
#[inline(always)]
pub fn mat33_rows<R: Real>(r0: Vec3<R>, r1: Vec3<R>, r2: Vec3<R>) -> Mat33<R> {
    Mat33::from_rows(&[r0.transpose(), r1.transpose(), r2.transpose()])
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`mat33_rows`](fn@mat33_rows): the rows of `adj`.
#[inline]
pub fn adj_mat33_rows<R: Real>(
    _r0: Vec3<R>,
    _r1: Vec3<R>,
    _r2: Vec3<R>,
    adj: Mat33<R>,
) -> (Vec3<R>, Vec3<R>, Vec3<R>) {
    (
        adj.row(0).transpose(),
        adj.row(1).transpose(),
        adj.row(2).transpose(),
    )
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`mat33_rows`](fn@mat33_rows): the matrix with rows `dr0`, `dr1`, `dr2`.
#[inline]
pub fn tan_mat33_rows<R: Real>(
    _r0: Vec3<R>,
    _r1: Vec3<R>,
    _r2: Vec3<R>,
    d0: Vec3<R>,
    d1: Vec3<R>,
    d2: Vec3<R>,
) -> Mat33<R> {
    mat33_rows(d0, d1, d2)
}

/// The quaternion `x i + y j + z k + w` (arguments in storage order x, y, z, w).
///
/// No singular points (linear).
#[inline(always)]
pub fn quat<R: Real>(x: R, y: R, z: R, w: R) -> Quat<R> {
    Quat::new(w, x, y, z)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat`](fn@quat): the components of `adj` (x, y, z, w).
#[inline]
pub fn adj_quat<R: Real>(_x: R, _y: R, _z: R, _w: R, adj: Quat<R>) -> (R, R, R, R) {
    (adj.i, adj.j, adj.k, adj.w)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat`](fn@quat): the quaternion of the tangents.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn tan_quat<R: Real>(_x: R, _y: R, _z: R, _w: R, dx: R, dy: R, dz: R, dw: R) -> Quat<R> {
    quat(dx, dy, dz, dw)
}

/// The 2x2 identity (a constant).
#[inline(always)]
pub fn mat22_identity<R: Real>() -> Mat22<R> {
    Mat22::identity()
}
/// The 3x3 identity (a constant).
#[inline(always)]
pub fn mat33_identity<R: Real>() -> Mat33<R> {
    Mat33::identity()
}
/// The identity rotation `(0, 0, 0, 1)` (a constant).
#[inline(always)]
pub fn quat_identity<R: Real>() -> Quat<R> {
    Quat::identity()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;

    fd_tests! {
        vec2_r: vec2, adj_vec2, tan_vec2 [R = any, R = any];
        vec3_r: vec3, adj_vec3, tan_vec3 [R = any, R = any, R = any];
        vec4_r: vec4, adj_vec4, tan_vec4 [R = any, R = any, R = any, R = any];
        mat22_r: mat22, adj_mat22, tan_mat22 [R = any, R = any, R = any, R = any];
        mat33_r: mat33, adj_mat33, tan_mat33
            [R = any, R = any, R = any, R = any, R = any, R = any, R = any, R = any, R = any];
        mat22_cols_v2: mat22_cols, adj_mat22_cols, tan_mat22_cols [Vec2<R> = any, Vec2<R> = any];
        mat33_cols_v3: mat33_cols, adj_mat33_cols, tan_mat33_cols
            [Vec3<R> = any, Vec3<R> = any, Vec3<R> = any];
        mat22_rows_v2: mat22_rows, adj_mat22_rows, tan_mat22_rows [Vec2<R> = any, Vec2<R> = any];
        mat33_rows_v3: mat33_rows, adj_mat33_rows, tan_mat33_rows
            [Vec3<R> = any, Vec3<R> = any, Vec3<R> = any];
        quat_r: quat, adj_quat, tan_quat [R = any, R = any, R = any, R = any];
    }

    #[test]
    fn values() {
        let m = mat33(1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0);
        assert_eq!(m[(0, 1)], 2.0); // row-major arguments
        assert_eq!(m[(1, 0)], 4.0);
        assert_eq!(mat22(1.0f32, 2.0, 3.0, 4.0)[(0, 1)], 2.0);
        let (a, b, c) = (
            vec3(1.0f64, 2.0, 3.0),
            vec3(4.0, 5.0, 6.0),
            vec3(7.0, 8.0, 9.0),
        );
        assert_eq!(mat33_rows(a, b, c), m);
        assert_eq!(mat33_cols(a, b, c), m.transpose());
        let (p, q) = (vec2(1.0f64, 2.0), vec2(3.0, 4.0));
        assert_eq!(mat22_rows(p, q), mat22(1.0, 2.0, 3.0, 4.0));
        assert_eq!(mat22_cols(p, q), mat22(1.0, 3.0, 2.0, 4.0));
        let r = quat(1.0f64, 2.0, 3.0, 4.0);
        assert_eq!((r.i, r.j, r.k, r.w), (1.0, 2.0, 3.0, 4.0));
        assert_eq!(r.coords, vec4(1.0, 2.0, 3.0, 4.0));
        let i: Mat33<f32> = mat33_identity();
        assert_eq!(i, Mat33::identity());
        assert_eq!(mat22_identity::<f64>(), Mat22::identity());
        assert_eq!(quat_identity::<f64>(), quat(0.0, 0.0, 0.0, 1.0));
    }
}
