//! The cloth force kernels of `bench/peers/warp_cloth.py` written with `#[diff_kernel]`, with
//! Warp's signatures (scalar `kd`, bending `ke` and `kd`), for the comparison with the
//! hand-written kernels of [`crate::hand`].

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

/// `eval_springs` of warp_cloth.py.
#[diff_kernel]
pub fn eval_springs<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    rest: &Array<R>,
    ke: &Array<R>,
    kd: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let xij = x[i] - x[j];
    let vij = v[i] - v[j];
    let l = length(xij);
    let d = xij / l;
    let c = l - rest[t];
    let dcdt = dot(d, vij);
    let fs = d * (ke[t] * c + kd * dcdt);
    f.atomic_sub(i, fs);
    f.atomic_add(j, fs);
}

/// `eval_bending` of warp_cloth.py.
#[diff_kernel]
pub fn eval_bending<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    quads: &Array<[u32; 4]>,
    rest: &Array<R>,
    ke: R,
    kd: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j, k, l] = quads[t];
    let x1 = x[i];
    let x2 = x[j];
    let x3 = x[k];
    let x4 = x[l];
    let v1 = v[i];
    let v2 = v[j];
    let v3 = v[k];
    let v4 = v[l];
    let n1 = cross(x3 - x1, x4 - x1);
    let n2 = cross(x4 - x2, x3 - x2);
    let n1_length = length(n1);
    let n2_length = length(n2);
    let rcp_n1 = 1.0 / n1_length;
    let rcp_n2 = 1.0 / n2_length;
    let m1 = n1 * rcp_n1 * rcp_n1;
    let m2 = n2 * rcp_n2 * rcp_n2;
    let e = x4 - x3;
    let e_hat = normalize(e);
    let e_length = length(e);
    let cos_theta = dot(n1, n2) * rcp_n1 * rcp_n2;
    let sin_theta = dot(cross(n2, n1), e_hat) * rcp_n1 * rcp_n2;
    let angle = atan2(sin_theta, cos_theta);
    let d1 = m1 * e_length;
    let d2 = m2 * e_length;
    let d3 = m1 * dot(x1 - x4, e_hat) + m2 * dot(x2 - x4, e_hat);
    let d4 = m1 * dot(x3 - x1, e_hat) + m2 * dot(x3 - x2, e_hat);
    let f_elastic = ke * (angle - rest[t]);
    let f_damp = kd * (dot(d1, v1) + dot(d2, v2) + dot(d3, v3) + dot(d4, v4));
    let f_total = 0.0 - e_length * (f_elastic + f_damp);
    f.atomic_add(i, d1 * f_total);
    f.atomic_add(j, d2 * f_total);
    f.atomic_add(k, d3 * f_total);
    f.atomic_add(l, d4 * f_total);
}
