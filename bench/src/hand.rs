//! The cloth spring and bending kernels written by hand, with hand-derived adjoints: the
//! baseline that the generated kernels of [`crate::gen`] are measured against.
//!
//! Same formulas as `eval_springs` and `eval_bending` of `bench/peers/warp_cloth.py`. The
//! adjoints recompute the forward quantities they need and run the chain rule by hand,
//! simplified where a human would (e.g. the adjoint of `d = xij / |xij|` in one expression).
//! Plain loops over slices, one thread.

use adflex_runtime::{Real, Vec3};

/// Springs: `f_i -= fs`, `f_j += fs`.
pub fn springs_fwd<R: Real>(
    x: &[Vec3<R>],
    v: &[Vec3<R>],
    pairs: &[[u32; 2]],
    rest: &[R],
    ke: &[R],
    kd: R,
    f: &mut [Vec3<R>],
) {
    for (t, &[i, j]) in pairs.iter().enumerate() {
        let (i, j) = (i as usize, j as usize);
        let xij = x[i] - x[j];
        let vij = v[i] - v[j];
        let l = xij.norm();
        let d = xij / l;
        let fs = d * (ke[t] * (l - rest[t]) + kd * d.dot(&vij));
        f[i] -= fs;
        f[j] += fs;
    }
}

/// Adjoint of [`springs_fwd`]: from `adj_f`, accumulates into `adj_x`, `adj_v`, `adj_ke`.
#[allow(clippy::too_many_arguments)]
pub fn springs_adj<R: Real>(
    x: &[Vec3<R>],
    v: &[Vec3<R>],
    pairs: &[[u32; 2]],
    rest: &[R],
    ke: &[R],
    kd: R,
    adj_f: &[Vec3<R>],
    adj_x: &mut [Vec3<R>],
    adj_v: &mut [Vec3<R>],
    adj_ke: &mut [R],
) {
    for (t, &[i, j]) in pairs.iter().enumerate() {
        let (i, j) = (i as usize, j as usize);
        let xij = x[i] - x[j];
        let vij = v[i] - v[j];
        let l = xij.norm();
        let d = xij / l;
        let c = l - rest[t];
        let s = ke[t] * c + kd * d.dot(&vij);
        let adj_fs = adj_f[j] - adj_f[i];
        let adj_s = adj_fs.dot(&d);
        adj_ke[t] += adj_s * c;
        let adj_d = adj_fs * s + vij * (adj_s * kd);
        let adj_vij = d * (adj_s * kd);
        // d = xij / l, l = |xij|, and l enters s through ke * (l - rest)
        let adj_xij = (adj_d - d * adj_d.dot(&d)) / l + d * (adj_s * ke[t]);
        adj_x[i] += adj_xij;
        adj_x[j] -= adj_xij;
        adj_v[i] += adj_vij;
        adj_v[j] -= adj_vij;
    }
}

/// The forward quantities of one bending element that both passes use.
struct Bend<R: Real> {
    x: [Vec3<R>; 4],
    n1: Vec3<R>,
    n2: Vec3<R>,
    r1: R,
    r2: R,
    cos: R,
    m1: Vec3<R>,
    m2: Vec3<R>,
    eh: Vec3<R>,
    el: R,
    sin: R,
    /// `(n2 x n1) . eh`: the sine times `|n1| |n2|`.
    q: R,
    p: [R; 4], // (x1-x4).eh, (x2-x4).eh, (x3-x1).eh, (x3-x2).eh
    d: [Vec3<R>; 4],
    fe: R,
    fd: R,
    ft: R,
}

#[inline(always)]
fn bend<R: Real>(x: &[Vec3<R>], v: &[Vec3<R>], q: [usize; 4], rest: R, ke: R, kd: R) -> Bend<R> {
    let [x1, x2, x3, x4] = q.map(|k| x[k]);
    let n1 = (x3 - x1).cross(&(x4 - x1));
    let n2 = (x4 - x2).cross(&(x3 - x2));
    let r1 = R::one() / n1.norm();
    let r2 = R::one() / n2.norm();
    let cos = n1.dot(&n2) * r1 * r2;
    let m1 = n1 * r1 * r1;
    let m2 = n2 * r2 * r2;
    let e = x4 - x3;
    let el = e.norm();
    let eh = if el > R::zero() {
        e / el
    } else {
        Vec3::zeros()
    };
    let q_ = n2.cross(&n1).dot(&eh);
    let sin = q_ * r1 * r2;
    let angle = sin.atan2(cos);
    let p = [
        (x1 - x4).dot(&eh),
        (x2 - x4).dot(&eh),
        (x3 - x1).dot(&eh),
        (x3 - x2).dot(&eh),
    ];
    let d = [
        m1 * el,
        m2 * el,
        m1 * p[0] + m2 * p[1],
        m1 * p[2] + m2 * p[3],
    ];
    let fe = ke * (angle - rest);
    let fd =
        kd * (d[0].dot(&v[q[0]]) + d[1].dot(&v[q[1]]) + d[2].dot(&v[q[2]]) + d[3].dot(&v[q[3]]));
    let ft = -(el * (fe + fd));
    Bend {
        x: [x1, x2, x3, x4],
        n1,
        n2,
        r1,
        r2,
        cos,
        m1,
        m2,
        eh,
        el,
        sin,
        q: q_,
        p,
        d,
        fe,
        fd,
        ft,
    }
}

/// Dihedral bending: adds `d_k * f_total` to the four particles.
pub fn bending_fwd<R: Real>(
    x: &[Vec3<R>],
    v: &[Vec3<R>],
    quads: &[[u32; 4]],
    rest: &[R],
    ke: R,
    kd: R,
    f: &mut [Vec3<R>],
) {
    for (t, q) in quads.iter().enumerate() {
        let q = q.map(|k| k as usize);
        let b = bend(x, v, q, rest[t], ke, kd);
        for k in 0..4 {
            f[q[k]] += b.d[k] * b.ft;
        }
    }
}

/// Adjoint of [`bending_fwd`]: from `adj_f`, accumulates into `adj_x` and `adj_v`.
#[allow(clippy::too_many_arguments)]
pub fn bending_adj<R: Real>(
    x: &[Vec3<R>],
    v: &[Vec3<R>],
    quads: &[[u32; 4]],
    rest: &[R],
    ke: R,
    kd: R,
    adj_f: &[Vec3<R>],
    adj_x: &mut [Vec3<R>],
    adj_v: &mut [Vec3<R>],
) {
    let two = R::one() + R::one();
    for (t, q) in quads.iter().enumerate() {
        let q = q.map(|k| k as usize);
        let b = bend(x, v, q, rest[t], ke, kd);
        let [x1, x2, x3, x4] = b.x;
        let g = q.map(|k| adj_f[k]);
        // f_k += d_k * ft
        let adj_ft = g[0].dot(&b.d[0]) + g[1].dot(&b.d[1]) + g[2].dot(&b.d[2]) + g[3].dot(&b.d[3]);
        let mut adj_d = g.map(|gk| gk * b.ft);
        // ft = -el (fe + fd)
        let mut adj_el = -adj_ft * (b.fe + b.fd);
        let adj_sum = -adj_ft * b.el;
        // fd = kd sum_k d_k . v_k
        let kfd = adj_sum * kd;
        for k in 0..4 {
            adj_d[k] += v[q[k]] * kfd;
            adj_v[q[k]] += b.d[k] * kfd;
        }
        // fe = ke (angle - rest), angle = atan2(sin, cos)
        let adj_angle = adj_sum * ke;
        let h = b.cos * b.cos + b.sin * b.sin;
        let adj_cos = -adj_angle * b.sin / h;
        let adj_sin = adj_angle * b.cos / h;
        // sin = q r1 r2, q = (n2 x n1) . eh
        let adj_q = adj_sin * b.r1 * b.r2;
        // d1 = m1 el, d2 = m2 el, d3 = m1 p0 + m2 p1, d4 = m1 p2 + m2 p3
        let adj_m1 = adj_d[0] * b.el + adj_d[2] * b.p[0] + adj_d[3] * b.p[2];
        let adj_m2 = adj_d[1] * b.el + adj_d[2] * b.p[1] + adj_d[3] * b.p[3];
        adj_el += adj_d[0].dot(&b.m1) + adj_d[1].dot(&b.m2);
        let ap = [
            adj_d[2].dot(&b.m1),
            adj_d[2].dot(&b.m2),
            adj_d[3].dot(&b.m1),
            adj_d[3].dot(&b.m2),
        ];
        let mut ax1 = b.eh * (ap[0] - ap[2]);
        let mut ax2 = b.eh * (ap[1] - ap[3]);
        let mut ax3 = b.eh * (ap[2] + ap[3]);
        let mut ax4 = -(b.eh * (ap[0] + ap[1]));
        let adj_eh = (x1 - x4) * ap[0]
            + (x2 - x4) * ap[1]
            + (x3 - x1) * ap[2]
            + (x3 - x2) * ap[3]
            + b.n2.cross(&b.n1) * adj_q;
        // eh = e / el, el = |e|, e = x4 - x3
        if b.el > R::zero() {
            let adj_e = (adj_eh - b.eh * b.eh.dot(&adj_eh)) / b.el + b.eh * adj_el;
            ax4 += adj_e;
            ax3 -= adj_e;
        }
        // m1 = n1 r1^2, m2 = n2 r2^2, cos = (n1 . n2) r1 r2, r = 1 / |n|
        let pn = b.n1.dot(&b.n2);
        let adj_r1 = two * b.r1 * adj_m1.dot(&b.n1) + (adj_cos * pn + adj_sin * b.q) * b.r2;
        let adj_r2 = two * b.r2 * adj_m2.dot(&b.n2) + (adj_cos * pn + adj_sin * b.q) * b.r1;
        let adj_pn = adj_cos * b.r1 * b.r2;
        let adj_n1 = adj_m1 * (b.r1 * b.r1) + b.n2 * adj_pn - b.n1 * (adj_r1 * b.r1 * b.r1 * b.r1)
            + b.eh.cross(&b.n2) * adj_q;
        let adj_n2 = adj_m2 * (b.r2 * b.r2) + b.n1 * adj_pn - b.n2 * (adj_r2 * b.r2 * b.r2 * b.r2)
            + b.n1.cross(&b.eh) * adj_q;
        // n1 = (x3 - x1) x (x4 - x1), n2 = (x4 - x2) x (x3 - x2)
        let adj_a = (x4 - x1).cross(&adj_n1);
        let adj_b = adj_n1.cross(&(x3 - x1));
        ax3 += adj_a;
        ax4 += adj_b;
        ax1 -= adj_a + adj_b;
        let adj_c = (x3 - x2).cross(&adj_n2);
        let adj_dd = adj_n2.cross(&(x4 - x2));
        ax4 += adj_c;
        ax3 += adj_dd;
        ax2 -= adj_c + adj_dd;
        adj_x[q[0]] += ax1;
        adj_x[q[1]] += ax2;
        adj_x[q[2]] += ax3;
        adj_x[q[3]] += ax4;
    }
}
