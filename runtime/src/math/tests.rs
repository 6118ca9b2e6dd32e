//! Tests across the groups: generic code through the rule functions (as the macro emits it),
//! and tests of the checker itself.

use super::check::*;
use super::*;
use crate::__codegen::*;
use crate::{acc, Mat33, Quat, Real, Vec3};

/// A damped spring written the way `#[diff_func]` lowers it: every operation is a rule call,
/// generic over the scalar.
fn spring<R: Real>(xij: Vec3<R>, vij: Vec3<R>, rest: R, ke: R, kd: R) -> Vec3<R> {
    let l = length(xij);
    let d = div(xij, l);
    let c = add(mul(ke, sub(l, rest)), mul(kd, dot(d, vij)));
    mul(d, c)
}

/// The adjoint of [`spring`]: replay, then the rules' adjoints in reverse.
fn adj_spring<R: Real>(
    xij: Vec3<R>,
    vij: Vec3<R>,
    rest: R,
    ke: R,
    kd: R,
    adj: Vec3<R>,
) -> (Vec3<R>, Vec3<R>, R, R, R) {
    let l = length(xij);
    let d = div(xij, l);
    let s = sub(l, rest);
    let e = mul(ke, s);
    let dv = dot(d, vij);
    let f = mul(kd, dv);
    let c = add(e, f);

    let (mut adj_d, adj_c) = adj_mul(d, c, adj);
    let (adj_e, adj_f) = adj_add(e, f, adj_c);
    let (adj_kd, adj_dv) = adj_mul(kd, dv, adj_f);
    let (ad, adj_vij) = adj_dot(d, vij, adj_dv);
    acc(&mut adj_d, ad);
    let (adj_ke, adj_s) = adj_mul(ke, s, adj_e);
    let (mut adj_l, adj_rest) = adj_sub(l, rest, adj_s);
    let (mut adj_xij, al) = adj_div(xij, l, adj_d);
    acc(&mut adj_l, al);
    acc(&mut adj_xij, adj_length(xij, adj_l));
    (adj_xij, adj_vij, adj_rest, adj_ke, adj_kd)
}

/// The tangent of [`spring`]: the rules' tangents alongside the values.
#[allow(clippy::too_many_arguments)]
fn tan_spring<R: Real>(
    xij: Vec3<R>,
    vij: Vec3<R>,
    rest: R,
    ke: R,
    kd: R,
    dxij: Vec3<R>,
    dvij: Vec3<R>,
    drest: R,
    dke: R,
    dkd: R,
) -> Vec3<R> {
    let (l, dl) = (length(xij), tan_length(xij, dxij));
    let (d, dd) = (div(xij, l), tan_div(xij, l, dxij, dl));
    let (s, ds) = (sub(l, rest), tan_sub(l, rest, dl, drest));
    let (e, de) = (mul(ke, s), tan_mul(ke, s, dke, ds));
    let (dv, ddv) = (dot(d, vij), tan_dot(d, vij, dd, dvij));
    let (f, df) = (mul(kd, dv), tan_mul(kd, dv, dkd, ddv));
    let (c, dc) = (add(e, f), tan_add(e, f, de, df));
    tan_mul(d, c, dd, dc)
}

#[test]
fn generic_spring() {
    fn sample<R: Real>(rng: &mut Rng) -> (Vec3<R>, Vec3<R>, R, R, R) {
        (away(rng), any(rng), pos(rng), pos(rng), pos(rng))
    }
    check_rule("spring", sample::<f64>, spring, adj_spring, tan_spring);
    smoke_f32(
        "spring",
        sample::<f32>,
        sample::<f64>,
        spring,
        spring,
        adj_spring,
        adj_spring,
        tan_spring,
        tan_spring,
    );
    // instantiated at both precisions, with literals
    let f32_force: Vec3<f32> = spring(Vec3::new(2.0, 0.0, 0.0), Vec3::zeros(), 1.0, 10.0, 0.5);
    let f64_force: Vec3<f64> = spring(Vec3::new(2.0, 0.0, 0.0), Vec3::zeros(), 1.0, 10.0, 0.5);
    assert_eq!(f32_force, Vec3::new(10.0, 0.0, 0.0));
    assert_eq!(f64_force, Vec3::new(10.0, 0.0, 0.0));
}

/// More builtins from generic code: dispatch must resolve for a scalar parameter `R`.
fn generic_mix<R: Real>(q: Quat<R>, v: Vec3<R>, m: Mat33<R>, t: R) -> R {
    let r = quat_rotate(quat_normalize(q), v);
    let w = mul(m, lerp(v, r, t));
    let x = extract(w, 0);
    let y = replace(w, 1, clamp(x, R::lit(-1.0), R::lit(1.0)));
    let s = select(t > R::zero(), min(x, t), max(x, t));
    add(
        add(ddot(outer(y, v), m), s),
        mul(determinant(inverse(m)), length_sq(cross(v, y))),
    )
}

#[test]
fn generic_compiles() {
    let q = quat(0.1f32, 0.2, 0.3, 0.9);
    let v = vec3(1.0f32, -0.5, 0.25);
    let m = add(mat33_identity::<f32>(), mul(0.1f32, skew(v)));
    let a = generic_mix(q, v, m, 0.3f32);
    let b = generic_mix(
        cast_quat(q),
        v.map(cast::<_, f64>),
        m.map(cast::<_, f64>),
        0.3f32 as f64,
    );
    assert!(close(a as f64, b, 1e-5), "{a} {b}");

    fn cast_quat(q: Quat<f32>) -> Quat<f64> {
        quat(cast(q.i), cast(q.j), cast(q.k), cast(q.w))
    }
}

// --- the checker catches wrong rules -----------------------------------------------------

fn square(x: f64) -> f64 {
    x * x
}
fn adj_square_wrong(x: f64, adj: f64) -> f64 {
    adj * x // should be 2 x adj
}
fn tan_square(x: f64, dx: f64) -> f64 {
    2.0 * x * dx
}
fn adj_square(x: f64, adj: f64) -> f64 {
    2.0 * x * adj
}
fn tan_square_wrong(x: f64, dx: f64) -> f64 {
    2.0 * x * dx + 1e-4
}

#[test]
#[should_panic(expected = "adjoint component 0")]
fn checker_catches_adjoint() {
    check_rule(
        "square",
        |rng| (pos::<f64>(rng),),
        square,
        adj_square_wrong,
        tan_square,
    );
}

#[test]
#[should_panic(expected = "tangent component 0")]
fn checker_catches_tangent() {
    check_rule(
        "square",
        |rng| (pos::<f64>(rng),),
        square,
        adj_square,
        tan_square_wrong,
    );
}

#[test]
fn checker_accepts_right_rule() {
    check_rule(
        "square",
        |rng| (any::<f64>(rng),),
        square,
        adj_square,
        tan_square,
    );
}
