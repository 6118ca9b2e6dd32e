//! Hill-type muscle-tendon units between two links: force-length, force-velocity and passive
//! elasticity, with a rigid tendon, driven by an activation in `[0, 1]`.
//!
//! With `l` the distance between the attachment points, `l~ = (l - tendon_slack) / l_opt` the
//! normalized fibre length and `v~ = (dl/dt) / (v_max l_opt)` the normalized lengthening
//! speed, the unit pulls its two points together with
//! `F = F_max (a f_L(l~) f_V(v~) + f_PE(l~))`:
//! - `f_L = exp(-((l~ - 1) / 0.45)^2)` (active force-length, Gaussian);
//! - `f_V = (1 + v~) / (1 - 4 v~)` when shortening (Hill's hyperbola, 0 at `v~ = -1` and
//!   below), `1.8 - 0.8 (1 - v~) / (1 + 30.24 v~)` when lengthening (to 1.8 F_max);
//! - `f_PE = (exp(4 (l~ - 1) / 0.6) - 1) / (exp(4) - 1)` beyond the optimal length, 0 before.
//!
//! The curves are those of Thelen (2003) in simplified form; `f_V` is continuous with a kink
//! at `v~ = 0` (its two one-sided slopes are 5 and 25).

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

/// The unit's force (N) at normalized length `lt`, speed `vt` and activation `a`.
#[diff_func]
pub fn muscle_force<R: Real>(lt: R, vt: R, a: R, f_max: R) -> R {
    let x = (lt - 1.0) / 0.45;
    let fl = exp(-(x * x));
    let v = max(vt, -1.0);
    let mut fv = (1.0 + v) / (1.0 - 4.0 * v);
    if v > 0.0 {
        fv = 1.8 - 0.8 * (1.0 - v) / (1.0 + 30.24 * v);
    }
    let mut fpe = lt * 0.0;
    if lt > 1.0 {
        fpe = (exp(4.0 * (lt - 1.0) / 0.6) - 1.0) / (exp(4.0) - 1.0);
    }
    f_max * (a * fl * fv + fpe)
}

/// Muscle `tid` from point `origin_pos` of link `origin_link` to point `insertion_pos` of
/// link `insertion_link` (link frames): the force `F` of [`muscle_force`] along the line
/// between them pulls each toward the other (wrenches `(x x f, f)` added to `ext_n`, `ext_f`).
/// The activation is clamped to `[0, 1]`.
#[diff_kernel]
pub fn articulation_muscles<R: Real>(
    origin_link: &Array<u32>,
    origin_pos: &Array<Vec3<R>>,
    insertion_link: &Array<u32>,
    insertion_pos: &Array<Vec3<R>>,
    f_max: &Array<R>,
    l_opt: &Array<R>,
    tendon_slack: &Array<R>,
    v_max: &Array<R>,
    activation: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
) {
    let t = tid();
    let la = origin_link[t] as usize;
    let lb = insertion_link[t] as usize;
    let pa = link_p[la] + quat_rotate(link_r[la], origin_pos[t]);
    let pb = link_p[lb] + quat_rotate(link_r[lb], insertion_pos[t]);
    let u = normalize(pb - pa);
    let l = length(pb - pa);
    let va = link_v[la] + cross(link_w[la], pa);
    let vb = link_v[lb] + cross(link_w[lb], pb);
    let lt = (l - tendon_slack[t]) / l_opt[t];
    let vt = dot(vb - va, u) / (v_max[t] * l_opt[t]);
    let f = u * muscle_force(lt, vt, clamp(activation[t], 0.0, 1.0), f_max[t]);
    ext_n.atomic_add(la, cross(pa, f));
    ext_f.atomic_add(la, f);
    ext_n.atomic_sub(lb, cross(pb, f));
    ext_f.atomic_sub(lb, f);
}
