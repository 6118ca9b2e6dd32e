//! The contact law every contact of the library uses (particles against the ground, each
//! other and shapes; rigid bodies' points against the ground): the penetration depth with its
//! optional leaky gradient, the penalty force with damping and dFlex's smoothed Coulomb
//! friction, its potential, the damping ramp at first contact, and the onset that softens the
//! depth at first contact.

use adflex_macros::diff_func;
use adflex_runtime::prelude::*;

/// Penetration depth `min(d, 0)` (m) with a leaky derivative: `1` for `d < 0` (in contact),
/// `leak` for `d >= 0` (out of contact, where the true derivative is 0).
///
/// The forward value is exactly `min(d, 0)`; only the adjoint and tangent differ. With
/// `leak = 0` the derivative is the exact one (`min`'s tie at `d = 0` goes to the constant, so
/// 0 there). A small leak (e.g. 0.01: a contact 1 cm away pulls with 1% of the stiffness)
/// gives a nonzero gradient for a particle above the ground, the standard remedy for the
/// vanishing gradients of penalty contact (cf. "leaky" contact in DiffTaichi/gradSim). The
/// gradient is then not the derivative of the simulation: gradient checks must use `leak = 0`.
/// The rules compute in `R`, so they run in `Dual` (`dual_safe`): second-order passes go through.
#[diff_func(adjoint = contact_depth_adjoint, tangent = contact_depth_tangent, dual_safe)]
pub fn contact_depth<R: Real>(d: R, leak: R) -> R {
    min(d, 0.0)
}

/// The slope [`contact_depth`] uses in place of the derivative of `min(d, 0)`.
#[inline]
pub fn contact_depth_slope<R: Real>(d: R, leak: R) -> R {
    if d < R::lit(0.0) {
        R::lit(1.0)
    } else {
        leak
    }
}

/// Adjoint of [`contact_depth`] (the leak factor itself gets no gradient).
pub fn contact_depth_adjoint<R: Real>(d: R, leak: R, adj: R) -> (R, R) {
    (contact_depth_slope(d, leak) * adj, R::lit(0.0))
}

/// Tangent of [`contact_depth`].
pub fn contact_depth_tangent<R: Real>(d: R, leak: R, dd: R, _dleak: R) -> R {
    contact_depth_slope(d, leak) * dd
}

/// Penalty contact force of a point against a surface of unit normal `n`: the force the point
/// receives, `-(fn + fd - ft)` with `c` the (non-positive) penetration depth (m), `v` the
/// point's velocity relative to the surface (m/s):
/// `fn = n c ke`, `fd = n min(v.n, 0) kd`, `ft = vt (mu c ke / (|vt| + 0.01))` with
/// `vt = v - n (v.n)`; `ke` (N/m), `kd` (N s/m), `mu` (friction coefficient). It is
/// [`contact_force_with_stiction`] with the stiction tolerance
/// [`STICTION_TOLERANCE`] (0.01 m/s).
///
/// As in dFlex, the damping `fd` acts whenever the point approaches the surface, even out of
/// contact; the friction is Coulomb's `mu |fn|` smoothed near `vt = 0` (so `|vt| = 0` is
/// regular: `length`'s gradient there is 0).
#[diff_func]
pub fn contact_force<R: Real>(n: Vec3<R>, c: R, v: Vec3<R>, ke: R, kd: R, mu: R) -> Vec3<R> {
    contact_force_with_stiction(n, c, v, ke, kd, mu, 0.01)
}

/// The stiction tolerance of [`contact_force`] (m/s): the sliding speed below which its
/// friction grows linearly with the speed (the default of
/// [`GroundContact::stiction_tolerance`](crate::articulation::GroundContact::stiction_tolerance)).
pub const STICTION_TOLERANCE: f64 = 0.01;

/// [`contact_force`] with the friction smoothed over the sliding speed `vs` (m/s, > 0, the
/// stiction tolerance, Drake's name): `ft = vt (mu c ke / (|vt| + vs))`.
///
/// At rest the friction is a damper of slope `mu |fn| / vs` (N s/m). An explicit step of
/// length `dt` integrates it stably where `mu |fn| dt / (vs m) < 2`, `m` the mass the contact
/// moves (a light shin under a heavy torso: small `m`, large `|fn|`); beyond, a rollout's
/// motion stays bounded (the friction saturates at `mu |fn|`) but its gradient grows
/// exponentially with the steps. A larger `vs` keeps the gradient bounded; the price is a
/// creep of up to `vs tan(a) / (mu - tan(a))` on a slope `a` where Coulomb's law holds still.
///
/// ```
/// use adflex_kernels::contact::law::{contact_force_with_stiction, STICTION_TOLERANCE};
/// use adflex_runtime::prelude::Vec3;
/// let (n, v) = (Vec3::z(), Vec3::new(2e-3, 0.0, 0.0)); // sliding at 2 mm/s along x
/// let f = |vs: f64| contact_force_with_stiction::call(n, -1e-3, v, 1e4, 0.0, 0.5, vs);
/// // 10 N pressing; the friction is 0.5 x 10 N x 2 / (2 + 10) mm/s or x 2 / (2 + 100).
/// assert!((f(STICTION_TOLERANCE).x + 5.0 / 6.0).abs() < 1e-12);
/// assert!((f(0.1).x + 5.0 / 51.0).abs() < 1e-12);
/// assert!((f(0.1).z - 10.0).abs() < 1e-12);
/// ```
#[diff_func]
pub fn contact_force_with_stiction<R: Real>(
    n: Vec3<R>,
    c: R,
    v: Vec3<R>,
    ke: R,
    kd: R,
    mu: R,
    vs: R,
) -> Vec3<R> {
    let vn = dot(n, v);
    let vt = v - n * vn;
    let fnormal = n * c * ke;
    let fd = n * min(vn, 0.0) * kd;
    (fnormal + fd + vt * friction_coefficient(c, vt, ke, mu, vs)) * -1.0
}

/// The coefficient `k = mu |fn| / (|vt| + vs) >= 0` (N s/m, `|fn| = -c ke`) of
/// [`contact_force_with_stiction`]'s friction `-k vt`: a damper on the sliding velocity `vt`,
/// whose coefficient falls as the speed grows.
///
/// ```
/// use adflex_kernels::contact::law::friction_coefficient;
/// use adflex_runtime::prelude::Vec3;
/// // 10 N pressing (1 mm deep at 1e4 N/m), sliding at 2 mm/s, mu 0.5, vs 1 cm/s.
/// let k: f64 = friction_coefficient::call(-1e-3, Vec3::new(2e-3, 0.0, 0.0), 1e4, 0.5, 0.01);
/// assert!((k - 5.0 / 0.012).abs() < 1e-9);
/// ```
#[diff_func]
pub fn friction_coefficient<R: Real>(c: R, vt: Vec3<R>, ke: R, mu: R, vs: R) -> R {
    mu * -c * ke / (length(vt) + vs)
}

/// The damper an implicit step takes for [`contact_force_with_stiction`]'s friction
/// ([`GroundContact::implicit_friction`](crate::articulation::GroundContact)):
/// `mu |fn| / sqrt(|vt|^2 + vs^2)` (N s/m). At rest it is the friction's slope `mu |fn| / vs`
/// (so a body at rest is damped implicitly at exactly its rate), and sliding fast it falls as
/// `1 / |vt|`, as [`friction_coefficient`] does (so a sliding body decelerates at Coulomb's
/// rate, to `O(dt)`). Unlike that coefficient it is smooth at rest (`|vt|` has a kink there,
/// which would make a rollout's derivative jump each time a contact comes to rest).
///
/// ```
/// use adflex_kernels::contact::law::{friction_coefficient, friction_damper};
/// use adflex_runtime::prelude::Vec3;
/// let (rest, fast): (Vec3<f64>, _) = (Vec3::zeros(), Vec3::new(3.0, 4.0, 0.0));
/// let k = |v| friction_damper::call(-1e-3, v, 1e4, 0.5, 0.01);
/// assert_eq!(k(rest), friction_coefficient::call(-1e-3, rest, 1e4, 0.5, 0.01));
/// assert!((k(fast) - 1.0).abs() < 1e-5); // 5 N over 5 m/s
/// ```
#[diff_func]
pub fn friction_damper<R: Real>(c: R, vt: Vec3<R>, ke: R, mu: R, vs: R) -> R {
    mu * -c * ke / sqrt(dot(vt, vt) + vs * vs)
}

/// The potential of [`contact_force`]'s normal (penalty) part at signed distance `d` (m):
/// `ke/2 min(d, 0)^2` (J). Its gradient is exactly the penalty force (the leak of
/// [`contact_depth`] shapes only the gradients of the force, not this energy); damping and
/// friction have no potential.
#[diff_func]
pub fn penalty_energy<R: Real>(d: R, ke: R) -> R {
    let c = min(d, 0.0);
    0.5 * ke * c * c
}

/// The penetration `c <= 0` (m, from [`contact_depth`]) softened over its first `onset`
/// metres: `-c^2 / (2 onset)` down to `c = -onset`, `c + onset / 2` deeper. The penalty force
/// `ke c` then rises from 0 with zero slope (continuous with its derivative), where the plain
/// law has a kink: a contact that begins or ends between two time steps changes a rollout's
/// result by a kink per step, and a loss through many such steps (a ball rolling out of a cup)
/// is rough at the scale of a step, its gradient dominated by the steps and not by the trend.
/// With `onset = 0` the result is `c`, exactly.
///
/// ```
/// use adflex_kernels::contact::law::contact_onset;
/// assert_eq!(contact_onset::call(-0.3, 0.0), -0.3); // no onset: the depth itself
/// let near = |a: f64, b: f64| (a - b).abs() < 1e-15;
/// assert!(near(contact_onset::call(-1e-3, 2e-3), -0.25e-3)); // quadratic within the onset
/// assert!(near(contact_onset::call(-3e-3, 2e-3), -2e-3)); // then shifted by onset / 2
/// ```
#[diff_func]
pub fn contact_onset<R: Real>(c: R, onset: R) -> R {
    // Both branches of a select are differentiated: no division by a zero onset.
    let safe = select(onset > 0.0, onset, 1.0);
    let b = max(c, onset * -1.0);
    let soft = b * b * (-0.5 / safe) + (c - b);
    select(onset > 0.0, soft, c)
}

/// The damping of a contact at depth `c <= 0` (m): `kd_free` out of contact, rising linearly
/// to `kd` over the first `depth` metres of penetration (`depth = 0`: a switch at contact), so
/// that the force is continuous where the damping differs in and out of contact (implicit
/// solvers do not converge through a jump). With `kd_free = kd` it is exactly `kd`.
#[diff_func]
pub fn contact_damping<R: Real>(c: R, kd: R, kd_free: R, depth: R) -> R {
    // Both branches of a select are differentiated: no division by a zero depth.
    let safe = select(depth > 0.0, depth, 1.0);
    let ramp = select(
        depth > 0.0,
        min(c * -1.0 / safe, 1.0),
        select(c < 0.0, 1.0, 0.0),
    );
    kd_free + (kd - kd_free) * ramp
}
