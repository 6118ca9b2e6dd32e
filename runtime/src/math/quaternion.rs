//! Quaternion builtins: `quat_mul`, `quat_conjugate`, `quat_inverse`, `quat_normalize`,
//! `quat_length`, `quat_rotate`, `quat_rotate_inv`, `quat_from_axis_angle`, `quat_to_mat33`.
//!
//! Quaternions are stored `(x, y, z, w)` (nalgebra's `i, j, k, w`), `u = (x, y, z)` being the
//! vector part. Rules that assume a unit quaternion (`quat_rotate`, `quat_to_mat33`) are
//! polynomials in the components and are differentiated as written, so their gradients are
//! exact for any quaternion; for a non-unit `q` they are just not rotations.

use super::matrix::{skew, unskew};
use super::vector_space::Linear;
use crate::{Mat33, Quat, Real, Value, Vec3};

#[inline(always)]
fn conj<R: Real>(q: Quat<R>) -> Quat<R> {
    q.conjugate()
}

/// The Hamilton product `p q`. No singular points. (`mul(p, q)` is the same rule.)
#[inline(always)]
pub fn quat_mul<R: Real>(p: Quat<R>, q: Quat<R>) -> Quat<R> {
    p * q
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_mul`](fn@quat_mul): `(adj conj(q), conj(p) adj)`.
#[inline]
pub fn adj_quat_mul<R: Real>(p: Quat<R>, q: Quat<R>, adj: Quat<R>) -> (Quat<R>, Quat<R>) {
    (adj * conj(q), conj(p) * adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_mul`](fn@quat_mul): `dp q + p dq`.
#[inline]
pub fn tan_quat_mul<R: Real>(p: Quat<R>, q: Quat<R>, dp: Quat<R>, dq: Quat<R>) -> Quat<R> {
    dp * q + p * dq
}

/// The conjugate `(-x, -y, -z, w)`. No singular points.
#[inline(always)]
pub fn quat_conjugate<R: Real>(q: Quat<R>) -> Quat<R> {
    conj(q)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_conjugate`](fn@quat_conjugate): `conj(adj)`.
#[inline]
pub fn adj_quat_conjugate<R: Real>(_q: Quat<R>, adj: Quat<R>) -> Quat<R> {
    conj(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_conjugate`](fn@quat_conjugate): `conj(dq)`.
#[inline]
pub fn tan_quat_conjugate<R: Real>(_q: Quat<R>, dq: Quat<R>) -> Quat<R> {
    conj(dq)
}

/// `|q|`, the Euclidean norm of the four components. Singular point: zero gradient for
/// `|q| <= R::tiny()`.
#[inline(always)]
pub fn quat_length<R: Real>(q: Quat<R>) -> R {
    q.coords.norm()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_length`](fn@quat_length): `adj q / |q|`; 0 for `|q| <= R::tiny()`.
#[inline]
pub fn adj_quat_length<R: Real>(q: Quat<R>, adj: R) -> Quat<R> {
    let l = quat_length(q);
    if l > R::tiny() {
        q.lin_scale(adj / l)
    } else {
        Quat::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_length`](fn@quat_length): `q . dq / |q|`; 0 for `|q| <= R::tiny()`.
#[inline]
pub fn tan_quat_length<R: Real>(q: Quat<R>, dq: Quat<R>) -> R {
    let l = quat_length(q);
    if l > R::tiny() {
        q.lin_inner(dq) / l
    } else {
        R::zero()
    }
}

/// `q / |q|`. Singular point: for `|q| <= R::tiny()` the result is the zero quaternion with
/// zero gradient.
#[inline(always)]
pub fn quat_normalize<R: Real>(q: Quat<R>) -> Quat<R> {
    let l = quat_length(q);
    if l > R::tiny() {
        q.lin_div(l)
    } else {
        Quat::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_normalize`](fn@quat_normalize): `(adj - n (n . adj)) / |q|`; 0 for `|q| <= R::tiny()`.
#[inline]
pub fn adj_quat_normalize<R: Real>(q: Quat<R>, adj: Quat<R>) -> Quat<R> {
    let l = quat_length(q);
    if l > R::tiny() {
        let n = q.lin_div(l);
        adj.lin_sub(n.lin_scale(n.lin_inner(adj))).lin_div(l)
    } else {
        Quat::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_normalize`](fn@quat_normalize): `(dq - n (n . dq)) / |q|`; 0 for `|q| <= R::tiny()`.
#[inline]
pub fn tan_quat_normalize<R: Real>(q: Quat<R>, dq: Quat<R>) -> Quat<R> {
    adj_quat_normalize(q, dq)
}

/// `conj(q) / |q|^2`. Singular point: for `|q| <= R::tiny()` the result is the zero
/// quaternion with zero gradient.
#[inline(always)]
pub fn quat_inverse<R: Real>(q: Quat<R>) -> Quat<R> {
    let n = q.lin_inner(q);
    if n > R::tiny() * R::tiny() {
        conj(q).lin_div(n)
    } else {
        Quat::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_inverse`](fn@quat_inverse): `conj(adj) / n - 2 (adj . conj(q)) q / n^2` with `n = |q|^2`;
/// 0 for `|q| <= R::tiny()`.
#[inline]
pub fn adj_quat_inverse<R: Real>(q: Quat<R>, adj: Quat<R>) -> Quat<R> {
    let n = q.lin_inner(q);
    if n > R::tiny() * R::tiny() {
        let s = (adj.lin_inner(conj(q)) + adj.lin_inner(conj(q))) / (n * n);
        conj(adj).lin_div(n).lin_sub(q.lin_scale(s))
    } else {
        Quat::zeroed()
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_inverse`](fn@quat_inverse): `conj(dq) / n - 2 (q . dq) conj(q) / n^2`; 0 for
/// `|q| <= R::tiny()`.
#[inline]
pub fn tan_quat_inverse<R: Real>(q: Quat<R>, dq: Quat<R>) -> Quat<R> {
    let n = q.lin_inner(q);
    if n > R::tiny() * R::tiny() {
        let s = (q.lin_inner(dq) + q.lin_inner(dq)) / (n * n);
        conj(dq).lin_div(n).lin_sub(conj(q).lin_scale(s))
    } else {
        Quat::zeroed()
    }
}

/// Rotates `v` by the unit quaternion `q`: `v + 2w (u x v) + 2 u x (u x v)`. The formula is
/// differentiated as written (`q` is not normalized; for a non-unit `q` it is not a rotation,
/// and it differs from Warp's `v (2w^2 - 1) + 2w (u x v) + 2u (u . v)` there). No singular
/// points.
#[inline(always)]
pub fn quat_rotate<R: Real>(q: Quat<R>, v: Vec3<R>) -> Vec3<R> {
    let (u, w) = (q.imag(), q.w);
    let a = u.cross(&v);
    let t = a * w + u.cross(&a);
    v + t + t
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_rotate`](fn@quat_rotate) (of the formula as written, any `q`).
#[inline]
pub fn adj_quat_rotate<R: Real>(q: Quat<R>, v: Vec3<R>, adj: Vec3<R>) -> (Quat<R>, Vec3<R>) {
    let (u, w) = (q.imag(), q.w);
    let two = R::lit(2.0);
    let a = u.cross(&v);
    // adjoint of a = u x v
    let adj_a = (adj * w + adj.cross(&u)) * two;
    let adj_w = adj.dot(&a) * two;
    let adj_u = a.cross(&adj) * two + v.cross(&adj_a);
    let adj_v = adj + adj_a.cross(&u);
    (Quat::from_parts(adj_w, adj_u), adj_v)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_rotate`](fn@quat_rotate) (of the formula as written, any `q`).
#[inline]
pub fn tan_quat_rotate<R: Real>(q: Quat<R>, v: Vec3<R>, dq: Quat<R>, dv: Vec3<R>) -> Vec3<R> {
    let (u, w) = (q.imag(), q.w);
    let (du, dw) = (dq.imag(), dq.w);
    let a = u.cross(&v);
    let da = du.cross(&v) + u.cross(&dv);
    let t = a * dw + da * w + du.cross(&a) + u.cross(&da);
    dv + t + t
}

/// Rotates `v` by the conjugate of `q` (the inverse rotation for a unit `q`): exactly
/// `quat_rotate(quat_conjugate(q), v)`, with the same conventions.
#[inline(always)]
pub fn quat_rotate_inv<R: Real>(q: Quat<R>, v: Vec3<R>) -> Vec3<R> {
    quat_rotate(conj(q), v)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_rotate_inv`](fn@quat_rotate_inv).
#[inline]
pub fn adj_quat_rotate_inv<R: Real>(q: Quat<R>, v: Vec3<R>, adj: Vec3<R>) -> (Quat<R>, Vec3<R>) {
    let (aq, av) = adj_quat_rotate(conj(q), v, adj);
    (conj(aq), av)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_rotate_inv`](fn@quat_rotate_inv).
#[inline]
pub fn tan_quat_rotate_inv<R: Real>(q: Quat<R>, v: Vec3<R>, dq: Quat<R>, dv: Vec3<R>) -> Vec3<R> {
    tan_quat_rotate(conj(q), v, conj(dq), dv)
}

/// The rotation by `angle` (radians) about the unit vector `axis`:
/// `(axis sin(angle/2), cos(angle/2))`. `axis` is not normalized. No singular points.
#[inline(always)]
pub fn quat_from_axis_angle<R: Real>(axis: Vec3<R>, angle: R) -> Quat<R> {
    let h = angle * R::lit(0.5);
    Quat::from_parts(h.cos(), axis * h.sin())
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_from_axis_angle`](fn@quat_from_axis_angle): `(s adj_u, (c axis . adj_u - s adj_w) / 2)` with
/// `s, c = sin, cos(angle/2)`.
#[inline]
pub fn adj_quat_from_axis_angle<R: Real>(axis: Vec3<R>, angle: R, adj: Quat<R>) -> (Vec3<R>, R) {
    let h = angle * R::lit(0.5);
    let (s, c) = (h.sin(), h.cos());
    let au = adj.imag();
    (au * s, (c * axis.dot(&au) - s * adj.w) * R::lit(0.5))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_from_axis_angle`](fn@quat_from_axis_angle): `(daxis s + axis c dangle/2, -s dangle/2)`.
#[inline]
pub fn tan_quat_from_axis_angle<R: Real>(
    axis: Vec3<R>,
    angle: R,
    daxis: Vec3<R>,
    dangle: R,
) -> Quat<R> {
    let h = angle * R::lit(0.5);
    let (s, c) = (h.sin(), h.cos());
    let dh = dangle * R::lit(0.5);
    Quat::from_parts(-s * dh, daxis * s + axis * (c * dh))
}

/// The rotation matrix of the unit quaternion `q`:
/// `(1 - 2|u|^2) I + 2 u u^T + 2w skew(u)`, i.e. the usual `[[1 - 2(y^2 + z^2), ..], ..]`.
/// `quat_to_mat33(q) * v == quat_rotate(q, v)` for every `q`. Differentiated as written
/// (`q` is not normalized). No singular points.
#[inline(always)]
pub fn quat_to_mat33<R: Real>(q: Quat<R>) -> Mat33<R> {
    let (u, w) = (q.imag(), q.w);
    let two = R::lit(2.0);
    Mat33::from_diagonal_element(R::one() - two * u.norm_squared())
        + u * u.transpose() * two
        + skew(u) * (two * w)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`quat_to_mat33`](fn@quat_to_mat33) (of the formula as written, any `q`).
#[inline]
pub fn adj_quat_to_mat33<R: Real>(q: Quat<R>, adj: Mat33<R>) -> Quat<R> {
    let (u, w) = (q.imag(), q.w);
    let two = R::lit(2.0);
    let s = unskew(adj);
    let adj_u =
        u * (R::lit(-4.0) * adj.trace()) + (adj + adj.transpose()) * u * two + s * (two * w);
    Quat::from_parts(two * u.dot(&s), adj_u)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`quat_to_mat33`](fn@quat_to_mat33) (of the formula as written, any `q`).
#[inline]
pub fn tan_quat_to_mat33<R: Real>(q: Quat<R>, dq: Quat<R>) -> Mat33<R> {
    let (u, w) = (q.imag(), q.w);
    let (du, dw) = (dq.imag(), dq.w);
    let two = R::lit(2.0);
    let uu = du * u.transpose();
    Mat33::from_diagonal_element(R::lit(-4.0) * u.dot(&du))
        + (uu + uu.transpose()) * two
        + skew(u) * (two * dw)
        + skew(du) * (two * w)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;
    use crate::math::{cross, dot, normalize};

    fd_tests! {
        quat_mul_q: quat_mul, adj_quat_mul, tan_quat_mul [Quat<R> = any, Quat<R> = any];
        quat_conjugate_q: quat_conjugate, adj_quat_conjugate, tan_quat_conjugate [Quat<R> = any];
        quat_inverse_q: quat_inverse, adj_quat_inverse, tan_quat_inverse [Quat<R> = away];
        quat_normalize_q: quat_normalize, adj_quat_normalize, tan_quat_normalize [Quat<R> = away];
        quat_length_q: quat_length, adj_quat_length, tan_quat_length [Quat<R> = away];
        quat_rotate_q: quat_rotate, adj_quat_rotate, tan_quat_rotate [Quat<R> = any, Vec3<R> = any];
        quat_rotate_inv_q: quat_rotate_inv, adj_quat_rotate_inv, tan_quat_rotate_inv
            [Quat<R> = any, Vec3<R> = any];
        quat_from_axis_angle_q: quat_from_axis_angle, adj_quat_from_axis_angle,
            tan_quat_from_axis_angle [Vec3<R> = any, R = wide];
        quat_to_mat33_q: quat_to_mat33, adj_quat_to_mat33, tan_quat_to_mat33 [Quat<R> = any];
    }

    #[test]
    fn rotations() {
        let mut rng = Rng::new(7);
        for _ in 0..20 {
            let axis = normalize(any::<Vec3<f64>>(&mut rng));
            let angle = rng.range(-3.0, 3.0);
            let q = quat_from_axis_angle(axis, angle);
            let v: Vec3<f64> = any(&mut rng);
            // against nalgebra's rotation
            let rot = nalgebra::UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(axis),
                angle,
            );
            assert!((quat_rotate(q, v) - rot * v).norm() < 1e-12);
            assert!((quat_to_mat33(q) - rot.to_rotation_matrix().into_inner()).norm() < 1e-12);
            assert!((quat_rotate_inv(q, quat_rotate(q, v)) - v).norm() < 1e-12);
            assert!((quat_length(q) - 1.0).abs() < 1e-12);
            // rotating preserves length and dot products
            let w: Vec3<f64> = any(&mut rng);
            assert!((dot(quat_rotate(q, v), quat_rotate(q, w)) - dot(v, w)).abs() < 1e-12);
            assert!(
                (quat_rotate(q, cross(v, w)) - cross(quat_rotate(q, v), quat_rotate(q, w))).norm()
                    < 1e-12
            );
            // composition
            let p = quat_from_axis_angle(normalize(any::<Vec3<f64>>(&mut rng)), 0.7);
            assert!(
                (quat_rotate(quat_mul(p, q), v) - quat_rotate(p, quat_rotate(q, v))).norm() < 1e-12
            );
            // inverse
            let r: Quat<f64> = any(&mut rng);
            assert!((quat_mul(r, quat_inverse(r)).coords - Quat::identity().coords).norm() < 1e-12);
        }
        // for any (non-unit) q the matrix and the rotate formula agree
        for _ in 0..20 {
            let (q, v): (Quat<f64>, Vec3<f64>) = (wide(&mut rng), any(&mut rng));
            assert!((quat_to_mat33(q) * v - quat_rotate(q, v)).norm() < 1e-12);
        }
    }

    #[test]
    fn singular_points() {
        let z = Quat::<f64>::zeroed();
        let one = Quat::new(1.0, 1.0, 1.0, 1.0);
        assert_eq!(quat_length(z), 0.0);
        assert_eq!(adj_quat_length(z, 1.0), z);
        assert_eq!(tan_quat_length(z, one), 0.0);
        assert_eq!(quat_normalize(z), z);
        assert_eq!(adj_quat_normalize(z, one), z);
        assert_eq!(tan_quat_normalize(z, one), z);
        assert_eq!(quat_inverse(z), z);
        assert_eq!(adj_quat_inverse(z, one), z);
        assert_eq!(tan_quat_inverse(z, one), z);
        let t = Quat::new(0.0f32, 1e-20, 0.0, 0.0);
        assert_eq!(quat_normalize(t), Quat::zeroed());
        assert_eq!(quat_inverse(t), Quat::zeroed());
    }
}
