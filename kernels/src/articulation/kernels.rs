//! The articulation kernels: forward kinematics, joint motion vectors, velocities and
//! accelerations, link inertias and forces, the joint-space mass matrix and the
//! steps by MuJoCo's integrators.
//!
//! Everything is in the world frame, with spatial vectors at the world origin: a twist is
//! `(w, v)` (angular velocity; velocity of the body point at the origin), a wrench `(n, f)`
//! (moment about the origin; force). A link's spatial inertia is `(m, h, J)`: mass, first
//! moment `h = m c` (c the world centre of mass) and the rotational inertia about the origin
//! `J = R I R^T + m (|c|^2 1 - c c^T)`; it maps a twist to the momentum
//! `(J w + h x v, m v - h x w)`. These three add, so a subtree's composite inertia is a sum.
//!
//! Each kernel runs one thread per link or per degree of freedom and walks the link's chain
//! of ancestors (or its subtree) itself, `O(links x depth)` in all: the threads of one launch
//! are independent, so every pass is one launch, whatever the depth of the tree.

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

/// Kinematics of link `tid`: its world pose, the motion vectors of its joint's velocities and
/// its world spatial inertia.
///
/// **Pose.** From the root, for each joint `j` on the link's chain, the parent frame moves to
/// the joint frame (`joint_pos[j]`, `joint_rot[j]`) and then by the joint's motion: revolute,
/// a rotation by `q` about `joint_axis[j]`; prismatic, a translation by `q` along it; ball, the
/// rotation `normalize(q[s..s+4])` (x, y, z, w); free, the translation `q[s..s+3]` (in the
/// joint frame) then the rotation `normalize(q[s+3..s+7])`.
///
/// **Motion vectors** (columns of the joint's motion subspace, world frame, at the origin):
/// for a rotation axis `u` through the link origin `p`, `(u, p x u)`; for a translation along
/// `u`, `(0, u)`. The axes are the joint's axis (revolute, prismatic), the link frame's axes
/// (ball: angular velocity in the link frame), or, for a free joint, the link frame's axes for
/// the linear velocity (first three) and then the angular velocity (Pinocchio's convention).
///
/// **Inertia** (see the module docs): `h = m c`, `J = R I R^T + m (|c|^2 1 - c c^T)` with
/// `c = p + R com`.
#[diff_kernel]
pub fn articulation_kinematics<R: Real>(
    chain_start: &Array<u32>,
    chain: &Array<u32>,
    joint_type: &Array<u32>,
    q_start: &Array<u32>,
    qd_start: &Array<u32>,
    joint_pos: &Array<Vec3<R>>,
    joint_rot: &Array<Quat<R>>,
    joint_axis: &Array<Vec3<R>>,
    mass: &Array<R>,
    com: &Array<Vec3<R>>,
    inertia: &Array<Mat33<R>>,
    q: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    s_w: &Array<Vec3<R>>,
    s_v: &Array<Vec3<R>>,
    link_h: &Array<Vec3<R>>,
    link_j: &Array<Mat33<R>>,
) {
    let l = tid();
    let mut p = vec3(0.0, 0.0, 0.0);
    let mut r = quat_identity();
    let c0 = chain_start[l] as usize;
    let c1 = chain_start[l + 1] as usize;
    for k in c0..c1 {
        let j = chain[k] as usize;
        p = p + quat_rotate(r, joint_pos[j]);
        // Normalized here, so that an optimized placement or axis stays a rotation and a unit.
        r = r * quat_normalize(joint_rot[j]);
        let axis = normalize(joint_axis[j]);
        let jt = joint_type[j];
        let s = q_start[j] as usize;
        // 1 revolute, 2 prismatic, 3 ball, 4 free (`JointType`); 0 fixed moves nothing.
        if jt == 1 {
            r = r * quat_from_axis_angle(axis, q[s]);
        } else if jt == 2 {
            p = p + quat_rotate(r, axis * q[s]);
        } else if jt == 3 {
            r = r * quat_normalize(quat(q[s], q[s + 1], q[s + 2], q[s + 3]));
        } else if jt == 4 {
            p = p + quat_rotate(r, vec3(q[s], q[s + 1], q[s + 2]));
            r = r * quat_normalize(quat(q[s + 3], q[s + 4], q[s + 5], q[s + 6]));
        }
    }
    link_p[l] = p;
    link_r[l] = r;
    let jt = joint_type[l];
    let d0 = qd_start[l] as usize;
    let d1 = qd_start[l + 1] as usize;
    for d in d0..d1 {
        let k = d - d0;
        let mut e = normalize(joint_axis[l]);
        let mut angular = jt != 2;
        let mut kk = k;
        if jt == 4 {
            angular = k >= 3;
            if k >= 3 {
                kk = k - 3;
            }
        }
        if jt == 3 || jt == 4 {
            e = vec3(
                select(kk == 0, 1.0, 0.0),
                select(kk == 1, 1.0, 0.0),
                select(kk == 2, 1.0, 0.0),
            );
        }
        let u = quat_rotate(r, e);
        if angular {
            s_w[d] = u;
            s_v[d] = cross(p, u);
        } else {
            s_w[d] = u * 0.0;
            s_v[d] = u;
        }
    }
    let rm = quat_to_mat33(r);
    let c = p + rm * com[l];
    let m = mass[l];
    link_h[l] = c * m;
    // The symmetric part of the inertia: an optimized one stays symmetric in effect.
    let ic = (inertia[l] + transpose(inertia[l])) * 0.5;
    link_j[l] = rm * ic * transpose(rm) + (mat33_identity() * dot(c, c) - outer(c, c)) * m;
}

/// Dynamics of link `tid`: its twist `(w, v)`, the wrench `(n, f)` its motion needs, and the
/// composite inertia of its subtree.
///
/// Along the chain, `v_j = v_parent + S_j qd_j` and `a_j = a_parent + S_j qdd_j + v_parent x
/// S_j qd_j` (the motion cross product `(w1, v1) x (w2, v2) = (w1 x w2, w1 x v2 + v1 x w2)`),
/// from `a_root = (0, -g)` (`g` the link's world's gravity): gravity enters as an upward acceleration of the world. The wrench is
/// `I a + v x* I v` with the force cross product `(w, v) x* (n, f) = (w x n + v x f, w x f)`;
/// the composite inertia is the sum of the subtree's `(m, h, J)`.
#[diff_kernel]
pub fn articulation_link_dynamics<R: Real>(
    chain_start: &Array<u32>,
    chain: &Array<u32>,
    subtree_start: &Array<u32>,
    subtree: &Array<u32>,
    qd_start: &Array<u32>,
    s_w: &Array<Vec3<R>>,
    s_v: &Array<Vec3<R>>,
    mass: &Array<R>,
    link_h: &Array<Vec3<R>>,
    link_j: &Array<Mat33<R>>,
    qd: &Array<R>,
    qdd: &Array<R>,
    gravity: &Array<Vec3<R>>,
    link_world: &Array<u32>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    link_n: &Array<Vec3<R>>,
    link_f: &Array<Vec3<R>>,
    comp_m: &Array<R>,
    comp_h: &Array<Vec3<R>>,
    comp_j: &Array<Mat33<R>>,
) {
    let l = tid();
    let g = gravity[link_world[l] as usize];
    let mut w = g * 0.0;
    let mut v = g * 0.0;
    let mut aw = g * 0.0;
    let mut av = -g;
    let c0 = chain_start[l] as usize;
    let c1 = chain_start[l + 1] as usize;
    for k in c0..c1 {
        let j = chain[k] as usize;
        let d0 = qd_start[j] as usize;
        let d1 = qd_start[j + 1] as usize;
        let mut dw = g * 0.0;
        let mut dv = g * 0.0;
        for d in d0..d1 {
            dw = dw + s_w[d] * qd[d];
            dv = dv + s_v[d] * qd[d];
            aw = aw + s_w[d] * qdd[d];
            av = av + s_v[d] * qdd[d];
        }
        aw = aw + cross(w, dw);
        av = av + cross(w, dv) + cross(v, dw);
        w = w + dw;
        v = v + dv;
    }
    link_w[l] = w;
    link_v[l] = v;
    let m = mass[l];
    let h = link_h[l];
    let jm = link_j[l];
    let pn = jm * w + cross(h, v);
    let pf = v * m - cross(h, w);
    let an = jm * aw + cross(h, av);
    let af = av * m - cross(h, aw);
    link_n[l] = an + cross(w, pn) + cross(v, pf);
    link_f[l] = af + cross(w, pf);
    let mut cm = m * 0.0;
    let mut ch = h * 0.0;
    let mut cj = jm * 0.0;
    let s0 = subtree_start[l] as usize;
    let s1 = subtree_start[l + 1] as usize;
    for k in s0..s1 {
        let i = subtree[k] as usize;
        cm = cm + mass[i];
        ch = ch + link_h[i];
        cj = cj + link_j[i];
    }
    comp_m[l] = cm;
    comp_h[l] = ch;
    comp_j[l] = cj;
}

/// The joint-space quantities of degree of freedom `tid`: its generalized force, its row of
/// the mass matrix, and its right-hand side of the forward dynamics.
///
/// **Force** `tau_id = S^T F`, `F` the sum over the subtree of its link of the links' wrenches
/// less the external ones (`ext_n`, `ext_f`, e.g. contact): inverse dynamics with the `qdd` of
/// [`articulation_link_dynamics`], the bias forces with `qdd = 0`.
///
/// **Mass matrix** (CRBA in the world frame): for degrees of freedom `a`, `b` of one
/// articulation, `M[a][b] = S_a . Ic_i S_b` with `i` the deeper of their links when one is an
/// ancestor of (or is) the other, and 0 otherwise; armature on the diagonal. Row `a` starts at
/// `m_row[a]` of `m`; `art_start[a]` is the articulation's first degree of freedom.
///
/// **Right-hand side** `tau + act_tau - tau_id` (`act_tau` the actuators' forces), and when
/// `passive` is 1 also
/// `+ kp (q_target - q) + kv (qd_target - qd) - damping qd - stiffness (q - spring_ref) +
/// limit` (PD, spring and limit terms on revolute and prismatic joints, `dof_q[d]` their
/// coordinate; the limit pushes back by `ke (lower - q) - kd qd` below `lower`, likewise above
/// `upper`, with `ke = limit_ke`, `kd = limit_kd`, where `limit_k[a]` is 0: the other limits
/// are MuJoCo's constraint, [`articulation_limit_constraint`], solved after).
/// With `dt > 0` (a step), a violated limit is integrated implicitly: `dt kd + dt^2 ke` joins
/// `M[a][a]` and `-dt ke qd` the right-hand side (backward Euler of the limit's spring and
/// damper, linearized). The joint damping is implicit too when `damp_dt` is the step's `dt`
/// (MuJoCo's Euler and implicitfast integrators): `damp_dt damping` joins `M[a][a]`, and the
/// PD's `kv_dt kv` (implicitfast: the PD is an actuator's speed term).
#[diff_kernel]
pub fn articulation_joint_space<R: Real>(
    dof_link: &Array<u32>,
    art_start: &Array<u32>,
    m_row: &Array<u32>,
    chain_start: &Array<u32>,
    chain: &Array<u32>,
    subtree_start: &Array<u32>,
    subtree: &Array<u32>,
    qd_start: &Array<u32>,
    s_w: &Array<Vec3<R>>,
    s_v: &Array<Vec3<R>>,
    link_n: &Array<Vec3<R>>,
    link_f: &Array<Vec3<R>>,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    comp_m: &Array<R>,
    comp_h: &Array<Vec3<R>>,
    comp_j: &Array<Mat33<R>>,
    armature: &Array<R>,
    passive: u32,
    dof_q: &Array<u32>,
    dof_scalar: &Array<u32>,
    q: &Array<R>,
    qd: &Array<R>,
    tau: &Array<R>,
    act_tau: &Array<R>,
    target_q: &Array<R>,
    target_qd: &Array<R>,
    kp: &Array<R>,
    kv: &Array<R>,
    damping: &Array<R>,
    stiffness: &Array<R>,
    spring_ref: &Array<R>,
    lower: &Array<R>,
    upper: &Array<R>,
    limit_ke: R,
    limit_kd: R,
    limit_k: &Array<R>,
    dt: R,
    damp_dt: R,
    kv_dt: R,
    tau_id: &Array<R>,
    m: &Array<R>,
    rhs: &Array<R>,
) {
    let a = tid();
    let la = dof_link[a] as usize;
    let wa = s_w[a];
    let va = s_v[a];
    // Generalized force.
    let mut fn_ = wa * 0.0;
    let mut ff = wa * 0.0;
    let s0 = subtree_start[la] as usize;
    let s1 = subtree_start[la + 1] as usize;
    for k in s0..s1 {
        let i = subtree[k] as usize;
        fn_ = fn_ + link_n[i] - ext_n[i];
        ff = ff + link_f[i] - ext_f[i];
    }
    let tid_a = dot(wa, fn_) + dot(va, ff);
    tau_id[a] = tid_a;
    // Row of the mass matrix: Ic_la S_a against the ancestors' motion vectors.
    let row = m_row[a] as usize;
    let first = art_start[a] as usize;
    let mc = comp_m[la];
    let hc = comp_h[la];
    let na = comp_j[la] * wa + cross(hc, va);
    let fa = va * mc - cross(hc, wa);
    let c0 = chain_start[la] as usize;
    let c1 = chain_start[la + 1] as usize;
    // The diagonal entry is stored last: a step's implicit limit adds to it.
    let mut m_aa = mc * 0.0;
    for k in c0..c1 {
        let j = chain[k] as usize;
        let d0 = qd_start[j] as usize;
        let d1 = qd_start[j + 1] as usize;
        for b in d0..d1 {
            let e = dot(s_w[b], na) + dot(s_v[b], fa);
            if b == a {
                m_aa = e + armature[a];
            } else {
                m[row + b - first] = e;
            }
        }
    }
    // Strict descendants (the subtree list starts with the link itself): Ic_i S_a.
    for k in s0 + 1..s1 {
        let i = subtree[k] as usize;
        let mi = comp_m[i];
        let hi = comp_h[i];
        let ni = comp_j[i] * wa + cross(hi, va);
        let fi = va * mi - cross(hi, wa);
        let d0 = qd_start[i] as usize;
        let d1 = qd_start[i + 1] as usize;
        for b in d0..d1 {
            m[row + b - first] = dot(s_w[b], ni) + dot(s_v[b], fi);
        }
    }
    // Right-hand side.
    let mut f = tau[a] + act_tau[a] - tid_a;
    let mut extra = m_aa * 0.0;
    if passive == 1 {
        let v = qd[a];
        f = f - damping[a] * v;
        extra = damping[a] * damp_dt;
        if dof_scalar[a] == 1 {
            let x = q[dof_q[a] as usize];
            f = f + kp[a] * (target_q[a] - x) + kv[a] * (target_qd[a] - v)
                - stiffness[a] * (x - spring_ref[a]);
            extra = extra + kv[a] * kv_dt;
            if limit_k[a] == 0.0 && (x < lower[a] || x > upper[a]) {
                let past = select(x < lower[a], lower[a], upper[a]);
                f = f + limit_ke * (past - x) - limit_kd * v - limit_ke * v * dt;
                extra = extra + (limit_kd + limit_ke * dt) * dt;
            }
        }
    }
    m[row + a - first] = m_aa + extra;
    rhs[a] = f;
}

/// The damping blocks of link `tid`'s subtree (`(ww, wv, vv)`, summed from each link's
/// `damp_*`, e.g. [`articulation_ground_contact`](super::contact::articulation_ground_contact)'s
/// friction): the composite damping, as `comp_*` is the composite inertia.
#[diff_kernel]
pub fn articulation_composite_damping<R: Real>(
    subtree_start: &Array<u32>,
    subtree: &Array<u32>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
    comp_ww: &Array<Mat33<R>>,
    comp_wv: &Array<Mat33<R>>,
    comp_vv: &Array<Mat33<R>>,
) {
    let l = tid();
    let mut ww = damp_ww[l] * 0.0;
    let mut wv = ww;
    let mut vv = ww;
    let s0 = subtree_start[l] as usize;
    let s1 = subtree_start[l + 1] as usize;
    for k in s0..s1 {
        let i = subtree[k] as usize;
        ww = ww + damp_ww[i];
        wv = wv + damp_wv[i];
        vv = vv + damp_vv[i];
    }
    comp_ww[l] = ww;
    comp_wv[l] = wv;
    comp_vv[l] = vv;
}

/// Adds the links' damping (composite blocks `comp_*` of
/// [`articulation_composite_damping`]) to row `tid` of the mass matrix, as
/// [`articulation_joint_space`] adds their inertia: `D[a][b] = S_b . Dc_i S_a`, `i` the deeper
/// of the two velocities' links, `Dc S = (ww w + wv v, wv^T w + vv v)` for `S = (w, v)`. With
/// blocks already scaled by a step's `dt`, the step solves with `M + dt D`: the dampers are
/// implicit.
#[diff_kernel]
pub fn articulation_damping_matrix<R: Real>(
    dof_link: &Array<u32>,
    art_start: &Array<u32>,
    m_row: &Array<u32>,
    chain_start: &Array<u32>,
    chain: &Array<u32>,
    subtree_start: &Array<u32>,
    subtree: &Array<u32>,
    qd_start: &Array<u32>,
    s_w: &Array<Vec3<R>>,
    s_v: &Array<Vec3<R>>,
    comp_ww: &Array<Mat33<R>>,
    comp_wv: &Array<Mat33<R>>,
    comp_vv: &Array<Mat33<R>>,
    m: &Array<R>,
) {
    let a = tid();
    let la = dof_link[a] as usize;
    let wa = s_w[a];
    let va = s_v[a];
    let row = m_row[a] as usize;
    let first = art_start[a] as usize;
    let na = comp_ww[la] * wa + comp_wv[la] * va;
    let fa = transpose(comp_wv[la]) * wa + comp_vv[la] * va;
    let c0 = chain_start[la] as usize;
    let c1 = chain_start[la + 1] as usize;
    for k in c0..c1 {
        let j = chain[k] as usize;
        let d0 = qd_start[j] as usize;
        let d1 = qd_start[j + 1] as usize;
        for b in d0..d1 {
            m.atomic_add(row + b - first, dot(s_w[b], na) + dot(s_v[b], fa));
        }
    }
    let s0 = subtree_start[la] as usize;
    let s1 = subtree_start[la + 1] as usize;
    for k in s0 + 1..s1 {
        let i = subtree[k] as usize;
        let ni = comp_ww[i] * wa + comp_wv[i] * va;
        let fi = transpose(comp_wv[i]) * wa + comp_vv[i] * va;
        let d0 = qd_start[i] as usize;
        let d1 = qd_start[i + 1] as usize;
        for b in d0..d1 {
            m.atomic_add(row + b - first, dot(s_w[b], ni) + dot(s_v[b], fi));
        }
    }
}

/// MuJoCo's soft limit constraint of velocity `tid`, for a time-constant limit
/// ([`Joint::limit_time_constant`](super::Joint::limit_time_constant)) that `side` says is
/// violated (1 below `lower`, 2 above `upper`, 0 none): its regularization's inverse `mu = 1 /
/// R = d m / (1 - d)` and its reference acceleration `aref = s (-b s qd - k d r)` in the
/// joint's direction (`s` +1 at the lower limit, -1 at the upper; `r = s (q - limit) < 0`;
/// `k = limit_k / m`, `b = limit_b / m`, `m = limit_m`; `d` the impedance at depth `r`,
/// MuJoCo's `solimp` function of `limit_imp = (dmin, dmax, width)`, midpoint 0.5 and power 2).
/// With `min_tc > 0` (MuJoCo's `refsafe`), a time constant `2 / (dmax b)` under `min_tc` is
/// raised to it (`b` scaled by their ratio, `k` by its square). 0 and 0 where `side` is 0.
#[diff_kernel]
pub fn articulation_limit_constraint<R: Real>(
    side: &Array<u32>,
    dof_q: &Array<u32>,
    q: &Array<R>,
    qd: &Array<R>,
    lower: &Array<R>,
    upper: &Array<R>,
    limit_k: &Array<R>,
    limit_b: &Array<R>,
    limit_m: &Array<R>,
    limit_imp: &Array<Vec3<R>>,
    min_tc: R,
    mu: &Array<R>,
    aref: &Array<R>,
) {
    let a = tid();
    let which = side[a];
    if which != 0 {
        let x = q[dof_q[a] as usize];
        let mut s = x * 0.0 + 1.0;
        let mut r = x - lower[a];
        if which == 2 {
            s = x * 0.0 - 1.0;
            r = upper[a] - x;
        }
        let imp = limit_imp[a];
        // The impedance: from dmin at the limit to dmax at `width` past it.
        let w = min(abs(r) / imp.z, 1.0);
        let mut y = 2.0 * w * w;
        if w > 0.5 {
            y = 1.0 - 2.0 * (1.0 - w) * (1.0 - w);
        }
        let d = imp.x + y * (imp.y - imp.x);
        let m = limit_m[a];
        let mut k = limit_k[a] / m;
        let mut b = limit_b[a] / m;
        // The time constant is 2 / (dmax b); compared without dividing by b (it may be 0).
        if min_tc * imp.y * b > 2.0 {
            let ratio = 2.0 / (min_tc * imp.y * b);
            b = b * ratio;
            k = k * ratio * ratio;
        }
        mu[a] = d * m / (1.0 - d);
        aref[a] = s * (0.0 - b * s * qd[a] - k * d * r);
    }
}

/// The system of a constraint solve, for velocity `tid`: `m_c = m + mu` on the diagonal and
/// `rhs_c = rhs + mu aref` where `on[tid]` is 1 (`m_c` holds a copy of `m`; its row `tid`
/// starts at `m_row[tid]`, its articulation's first velocity is `art_start[tid]`). By the
/// Woodbury identity the solution `x` of `m_c x = rhs_c` is `m^-1 (rhs + g)` with the
/// constraint forces `g = mu (aref - x)` of [`articulation_limit_force`].
#[diff_kernel]
pub fn articulation_limit_system<R: Real>(
    on: &Array<u32>,
    m_row: &Array<u32>,
    art_start: &Array<u32>,
    mu: &Array<R>,
    aref: &Array<R>,
    rhs: &Array<R>,
    m_c: &Array<R>,
    rhs_c: &Array<R>,
) {
    let a = tid();
    if on[a] == 1 {
        m_c.atomic_add(m_row[a] as usize + a - art_start[a] as usize, mu[a]);
        rhs_c[a] = rhs[a] + mu[a] * aref[a];
    } else {
        rhs_c[a] = rhs[a];
    }
}

/// The constraint force of velocity `tid` from a constraint solve's `x`
/// ([`articulation_limit_system`]): `g = mu (aref - x)` where `on[tid]` is 1, else 0, and
/// `rhs_g = rhs + g`.
#[diff_kernel]
pub fn articulation_limit_force<R: Real>(
    on: &Array<u32>,
    mu: &Array<R>,
    aref: &Array<R>,
    x: &Array<R>,
    rhs: &Array<R>,
    rhs_g: &Array<R>,
) {
    let a = tid();
    let mut g = rhs[a] * 0.0;
    if on[a] == 1 {
        g = mu[a] * (aref[a] - x[a]);
    }
    rhs_g[a] = rhs[a] + g;
}

/// The inverse dynamics' force of velocity `tid`: the links' `tau_id` plus the armature's
/// `armature qdd` (the armature is on the mass matrix's diagonal, not on a link).
#[diff_kernel]
pub fn articulation_armature_force<R: Real>(
    armature: &Array<R>,
    qdd: &Array<R>,
    tau_id: &Array<R>,
    tau: &Array<R>,
) {
    let a = tid();
    tau[a] = tau_id[a] + armature[a] * qdd[a];
}

/// Semi-implicit Euler step of the joint of link `tid`: `qd' = qd + qdd dt`, then
/// revolute/prismatic `q' = q + qd' dt`; ball `quat' = normalize(quat exp(w' dt))` with the
/// angular velocity `w'` in the link frame. A free joint's linear velocity is stepped in the
/// world frame, where a body without force keeps it exactly: `u' = R (v + (a + w x v) dt)`
/// (`a` its `qdd`, `w x v` the frame's rotation it contains), `p' = p + u' dt`, and
/// `v' = R'^T u'` in the new link frame. The quaternion stays on the unit sphere, and `exp`
/// uses its series near zero rotation (no division by `|w|`).
#[diff_kernel]
pub fn articulation_integrate<R: Real>(
    joint_type: &Array<u32>,
    q_start: &Array<u32>,
    qd_start: &Array<u32>,
    q: &Array<R>,
    qd: &Array<R>,
    qdd: &Array<R>,
    dt: R,
    q_new: &Array<R>,
    qd_new: &Array<R>,
) {
    let l = tid();
    let jt = joint_type[l];
    let s = q_start[l] as usize;
    let d0 = qd_start[l] as usize;
    let d1 = qd_start[l + 1] as usize;
    if jt == 1 || jt == 2 {
        let v = qd[d0] + qdd[d0] * dt;
        qd_new[d0] = v;
        q_new[s] = q[s] + v * dt;
    } else if jt == 3 || jt == 4 {
        // The rotation's velocities are the joint's last three.
        let a = d1 - 3;
        let w1 = vec3(
            qd[a] + qdd[a] * dt,
            qd[a + 1] + qdd[a + 1] * dt,
            qd[a + 2] + qdd[a + 2] * dt,
        );
        qd_new[a] = w1.x;
        qd_new[a + 1] = w1.y;
        qd_new[a + 2] = w1.z;
        let mut rs = s;
        if jt == 4 {
            rs = s + 3;
        }
        let r = quat_normalize(quat(q[rs], q[rs + 1], q[rs + 2], q[rs + 3]));
        let r1 = quat_step(r, w1 * dt);
        q_new[rs] = r1.x;
        q_new[rs + 1] = r1.y;
        q_new[rs + 2] = r1.z;
        q_new[rs + 3] = r1.w;
        if jt == 4 {
            let v = vec3(qd[d0], qd[d0 + 1], qd[d0 + 2]);
            let acc = vec3(qdd[d0], qdd[d0 + 1], qdd[d0 + 2]);
            let w0 = vec3(qd[a], qd[a + 1], qd[a + 2]);
            let u = quat_rotate(r, v + (acc + cross(w0, v)) * dt);
            q_new[s] = q[s] + u.x * dt;
            q_new[s + 1] = q[s + 1] + u.y * dt;
            q_new[s + 2] = q[s + 2] + u.z * dt;
            let v1 = quat_rotate_inv(r1, u);
            qd_new[d0] = v1.x;
            qd_new[d0 + 1] = v1.y;
            qd_new[d0 + 2] = v1.z;
        }
    }
}

/// `normalize(r exp(w))`: the unit quaternion `r` turned by the rotation vector `w` in its own
/// frame (MuJoCo's `mju_quatIntegrate`); `exp` uses its series near zero rotation (no division
/// by `|w|`).
#[diff_func]
pub fn quat_step<R: Real>(r: Quat<R>, w: Vec3<R>) -> Quat<R> {
    let th2 = dot(w, w);
    let mut k = 0.5 - th2 / 48.0;
    let mut c = 1.0 - th2 / 8.0;
    if th2 > 1e-8 {
        let th = sqrt(th2);
        k = sin(th * 0.5) / th;
        c = cos(th * 0.5);
    }
    quat_normalize(r * quat(w.x * k, w.y * k, w.z * k, c))
}

/// The rate of a rotation in exponential coordinates at `r0`: with `r = r0 exp(phi)`, a body
/// angular velocity `w` moves `phi` at `J_r(phi)^-1 w = w + phi x w / 2 + c phi x (phi x w)`,
/// `c = 1/t^2 - (1 + cos t) / (2 t sin t)`, `t = |phi|` (the right Jacobian's inverse; the
/// series near `t = 0`). Runge-Kutta stages of a rotation combine these rates (the
/// Runge-Kutta-Munthe-Kaas method, MuJoCo 4's RK4).
#[diff_func]
pub fn rotation_rate<R: Real>(r0: Quat<R>, r: Quat<R>, w: Vec3<R>) -> Vec3<R> {
    let mut e = quat_normalize(quat_conjugate(r0) * r);
    if e.w < 0.0 {
        e = quat(-e.x, -e.y, -e.z, -e.w);
    }
    let u = vec3(e.x, e.y, e.z);
    let s = sqrt(dot(u, u));
    // phi = u t / s, t = 2 atan2(s, w); near s = 0, t / s = 2 / w.
    let mut k = 2.0 / e.w;
    if s > 1e-6 {
        k = 2.0 * atan2(s, e.w) / s;
    }
    let phi = u * k;
    let t2 = dot(phi, phi);
    // The closed form cancels badly for small t (its derivative worse, and in f32): the
    // series to t^4 is exact to rounding below t^2 = 1e-2.
    let mut c = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0;
    if t2 > 1e-2 {
        let t = sqrt(t2);
        c = 1.0 / t2 - (1.0 + cos(t)) / (2.0 * t * sin(t));
    }
    let pw = cross(phi, w);
    w + pw * 0.5 + cross(phi, pw) * c
}

/// The rates of the joint of link `tid` where the stages of a Runge-Kutta step from `q0`
/// combine, as MuJoCo 4's RK4: `vel`, the velocities (except a rotation's, its
/// [`rotation_rate`] at `q0`'s, and a free joint's linear part, in the world frame: `R v`),
/// and `acc`, their derivatives (`qdd`, except a free joint's linear part, in the world
/// frame, as its local frame turns between stages: `R (a + w x v)`).
#[diff_kernel]
pub fn articulation_rates<R: Real>(
    joint_type: &Array<u32>,
    q_start: &Array<u32>,
    qd_start: &Array<u32>,
    q0: &Array<R>,
    q: &Array<R>,
    qd: &Array<R>,
    qdd: &Array<R>,
    vel: &Array<R>,
    acc: &Array<R>,
) {
    let l = tid();
    let jt = joint_type[l];
    let d0 = qd_start[l] as usize;
    let d1 = qd_start[l + 1] as usize;
    for d in d0..d1 {
        vel[d] = qd[d];
        acc[d] = qdd[d];
    }
    if jt == 3 || jt == 4 {
        let s = q_start[l] as usize;
        let a = d1 - 3;
        let mut rs = s;
        if jt == 4 {
            rs = s + 3;
        }
        let r0 = quat_normalize(quat(q0[rs], q0[rs + 1], q0[rs + 2], q0[rs + 3]));
        let r = quat_normalize(quat(q[rs], q[rs + 1], q[rs + 2], q[rs + 3]));
        let w = vec3(qd[a], qd[a + 1], qd[a + 2]);
        let rw = rotation_rate(r0, r, w);
        vel[a] = rw.x;
        vel[a + 1] = rw.y;
        vel[a + 2] = rw.z;
        if jt == 4 {
            let v = vec3(qd[d0], qd[d0 + 1], qd[d0 + 2]);
            let dv = vec3(qdd[d0], qdd[d0 + 1], qdd[d0 + 2]);
            let u = quat_rotate(r, v);
            let du = quat_rotate(r, dv + cross(w, v));
            vel[d0] = u.x;
            vel[d0 + 1] = u.y;
            vel[d0 + 2] = u.z;
            acc[d0] = du.x;
            acc[d0 + 1] = du.y;
            acc[d0 + 2] = du.z;
        }
    }
}

/// The state `(q0, qd0)` advanced by `h` along the rates `(vel, acc)` of
/// [`articulation_rates`] (a Runge-Kutta stage or its final combination, MuJoCo's `X0 + h
/// dX`), joint of link `tid`: `q' = q0 + h vel` (a quaternion `r0 exp(h vel)`, [`quat_step`]),
/// `qd' = qd0 + h acc`, a free joint's linear velocity in the world frame (`R0 v0 + h acc`)
/// and back to the new link frame. (The Euler step, [`articulation_integrate`], is this with
/// the positions moved by the new velocities, in one kernel.)
#[diff_kernel]
pub fn articulation_advance<R: Real>(
    joint_type: &Array<u32>,
    q_start: &Array<u32>,
    qd_start: &Array<u32>,
    q0: &Array<R>,
    qd0: &Array<R>,
    vel: &Array<R>,
    acc: &Array<R>,
    h: R,
    q_new: &Array<R>,
    qd_new: &Array<R>,
) {
    let l = tid();
    let jt = joint_type[l];
    let s = q_start[l] as usize;
    let d0 = qd_start[l] as usize;
    let d1 = qd_start[l + 1] as usize;
    for d in d0..d1 {
        qd_new[d] = qd0[d] + acc[d] * h;
    }
    if jt == 1 || jt == 2 {
        q_new[s] = q0[s] + vel[d0] * h;
    } else if jt == 3 || jt == 4 {
        let a = d1 - 3;
        let mut rs = s;
        if jt == 4 {
            rs = s + 3;
        }
        let r0 = quat_normalize(quat(q0[rs], q0[rs + 1], q0[rs + 2], q0[rs + 3]));
        let r1 = quat_step(r0, vec3(vel[a], vel[a + 1], vel[a + 2]) * h);
        q_new[rs] = r1.x;
        q_new[rs + 1] = r1.y;
        q_new[rs + 2] = r1.z;
        q_new[rs + 3] = r1.w;
        if jt == 4 {
            let v0 = vec3(qd0[d0], qd0[d0 + 1], qd0[d0 + 2]);
            let u = quat_rotate(r0, v0) + vec3(acc[d0], acc[d0 + 1], acc[d0 + 2]) * h;
            q_new[s] = q0[s] + vel[d0] * h;
            q_new[s + 1] = q0[s + 1] + vel[d0 + 1] * h;
            q_new[s + 2] = q0[s + 2] + vel[d0 + 2] * h;
            let v1 = quat_rotate_inv(r1, u);
            qd_new[d0] = v1.x;
            qd_new[d0 + 1] = v1.y;
            qd_new[d0 + 2] = v1.z;
        }
    }
}

/// Entry `tid` of the classic Runge-Kutta combination of four stages' rates: `out = (x1 + 2
/// x2 + 2 x3 + x4) / 6` (MuJoCo's `RK4_B`).
#[diff_kernel]
pub fn articulation_rk4_combine<R: Real>(
    x1: &Array<R>,
    x2: &Array<R>,
    x3: &Array<R>,
    x4: &Array<R>,
    out: &Array<R>,
) {
    let d = tid();
    let b1 = 1.0 / 6.0;
    let b2 = 1.0 / 3.0;
    out[d] = x1[d] * b1 + x2[d] * b2 + x3[d] * b2 + x4[d] * b1;
}

/// `out[tid]` is `from[tid]` in the worlds `take` marks (non-zero, indexed by `world[tid]`),
/// `keep[tid]` elsewhere: resetting some worlds of a state.
#[diff_kernel]
pub fn articulation_select_worlds<R: Real>(
    world: &Array<u32>,
    take: &Array<u32>,
    keep: &Array<R>,
    from: &Array<R>,
    out: &Array<R>,
) {
    let t = tid();
    if take[world[t] as usize] != 0 {
        out[t] = from[t];
    } else {
        out[t] = keep[t];
    }
}

/// The external force `force[tid]` at link `tid`'s centre of mass (`com`, link frame) and
/// torque `torque[tid]` (world frame) as a wrench about the world origin, added into the
/// link's `(ext_n, ext_f)`.
#[diff_kernel]
pub fn articulation_applied_wrench<R: Real>(
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    com: &Array<Vec3<R>>,
    force: &Array<Vec3<R>>,
    torque: &Array<Vec3<R>>,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
) {
    let l = tid();
    let c = link_p[l] + quat_rotate(link_r[l], com[l]);
    let f = force[l];
    ext_n.atomic_add(l, torque[l] + cross(c, f));
    ext_f.atomic_add(l, f);
}

/// Gravity compensation ([`LinkDesc::gravcomp`](super::LinkDesc)): an upward force of
/// `gravcomp[tid]` times the weight of link `gravcomp_link[tid]` (its world's gravity) at its
/// centre of mass, as a wrench about the world origin added into the link's `(ext_n, ext_f)`.
#[diff_kernel]
pub fn articulation_gravcomp<R: Real>(
    gravcomp_link: &Array<u32>,
    gravcomp: &Array<R>,
    link_world: &Array<u32>,
    gravity: &Array<Vec3<R>>,
    mass: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    com: &Array<Vec3<R>>,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
) {
    let k = tid();
    let l = gravcomp_link[k] as usize;
    let f = gravity[link_world[l] as usize] * (-(gravcomp[k] * mass[l]));
    let c = link_p[l] + quat_rotate(link_r[l], com[l]);
    ext_n.atomic_add(l, cross(c, f));
    ext_f.atomic_add(l, f);
}

/// The twist of link `tid`, world frame: its angular velocity `link_w` and the velocity
/// `link_v` of the body point at the world origin (a point `x` of the link moves at `link_v +
/// link_w x x`), the sum of `S_j qd_j` over the joints of its chain.
#[diff_kernel]
pub fn articulation_link_twist<R: Real>(
    chain_start: &Array<u32>,
    chain: &Array<u32>,
    qd_start: &Array<u32>,
    s_w: &Array<Vec3<R>>,
    s_v: &Array<Vec3<R>>,
    qd: &Array<R>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
) {
    let l = tid();
    let mut w = vec3(0.0, 0.0, 0.0);
    let mut v = vec3(0.0, 0.0, 0.0);
    let c0 = chain_start[l] as usize;
    let c1 = chain_start[l + 1] as usize;
    for k in c0..c1 {
        let j = chain[k] as usize;
        let d0 = qd_start[j] as usize;
        let d1 = qd_start[j + 1] as usize;
        for d in d0..d1 {
            w = w + s_w[d] * qd[d];
            v = v + s_v[d] * qd[d];
        }
    }
    link_w[l] = w;
    link_v[l] = v;
}
