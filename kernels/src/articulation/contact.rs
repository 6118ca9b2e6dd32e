//! Contact of links with the ground: spheres on links (boxes by their corners, capsules by
//! their end spheres) pressed into a plane, with the library's contact law (penalty, damping
//! ramped in over `damping_depth`, smoothed Coulomb friction, optional leaky gradient).

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::contact::law::{contact_damping, contact_depth, contact_force};

/// The shape of a geom (MJCF) or collision element (URDF), in its own frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GeomShape {
    /// A sphere of this radius.
    Sphere(f64),
    /// A capsule along z: radius, half-length of the cylinder.
    Capsule(f64, f64),
    /// A cylinder along z: radius, half-length.
    Cylinder(f64, f64),
    /// A box of these half extents.
    Box(Vec3<f64>),
    /// A plane through the origin with normal z.
    Plane,
}

/// The ground plane links touch, and its contact law.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundContact<R: Real> {
    /// Unit normal, out of the ground (default `+z`, as URDF and MJCF).
    pub normal: Vec3<R>,
    /// The plane is `dot(normal, x) = offset` (m).
    pub offset: R,
    /// Stiffness per contact sphere (N/m; default 1e4).
    pub ke: R,
    /// Damping in contact (N s/m; default 100), ramped in over `damping_depth`.
    pub kd: R,
    /// Friction coefficient (default 0.8).
    pub mu: R,
    /// Gradient leak out of contact (default 0: exact gradients; see
    /// [`contact_depth`]).
    pub leak: R,
    /// Depth over which the damping rises to `kd` (m; default 1e-3).
    pub damping_depth: R,
}

impl Default for GroundContact<f64> {
    fn default() -> Self {
        GroundContact {
            normal: Vec3::z(),
            offset: 0.0,
            ke: 1e4,
            kd: 100.0,
            mu: 0.8,
            leak: 0.0,
            damping_depth: 1e-3,
        }
    }
}

impl GroundContact<f64> {
    /// Checks: a unit normal, everything finite, coefficients non-negative.
    pub(crate) fn check(&self) -> Result<(), String> {
        let n = self.normal.norm();
        if !(n.is_finite() && (n - 1.0).abs() < 1e-3) {
            return Err(format!("normal must be a unit vector, has length {n}"));
        }
        if !self.offset.is_finite() {
            return Err("offset must be finite".into());
        }
        for (v, what) in [
            (self.ke, "ke"),
            (self.kd, "kd"),
            (self.mu, "mu"),
            (self.leak, "leak"),
            (self.damping_depth, "damping_depth"),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{what} {v} must be finite and non-negative"));
            }
        }
        Ok(())
    }

    pub(crate) fn to<R: Real>(&self) -> GroundContact<R> {
        let r = |x: f64| R::lit(x);
        GroundContact {
            normal: Vec3::new(r(self.normal.x), r(self.normal.y), r(self.normal.z)),
            offset: r(self.offset),
            ke: r(self.ke),
            kd: r(self.kd),
            mu: r(self.mu),
            leak: r(self.leak),
            damping_depth: r(self.damping_depth),
        }
    }
}

/// Ground contact of contact sphere `tid` (centre `contact_pos` in the frame of link
/// `contact_link`, radius `contact_radius`): its lowest point `x` at signed distance
/// `d = n.x - offset` gets `f = contact_force(n, contact_depth(d, leak), v, ke, kd', mu)`,
/// `v` the velocity of the link's point at `x` and `kd'` the ramped damping; the link
/// receives the wrench `(x x f, f)` (world frame, at the origin).
#[diff_kernel]
pub fn articulation_ground_contact<R: Real>(
    contact_link: &Array<u32>,
    contact_pos: &Array<Vec3<R>>,
    contact_radius: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    ke: R,
    kd: R,
    mu: R,
    leak: R,
    damping_depth: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
) {
    let t = tid();
    let l = contact_link[t] as usize;
    let centre = link_p[l] + quat_rotate(link_r[l], contact_pos[t]);
    let x = centre - normal * contact_radius[t];
    let v = link_v[l] + cross(link_w[l], x);
    let c = contact_depth(dot(normal, x) - offset, leak);
    let kdc = contact_damping(c, kd, 0.0, damping_depth);
    let f = contact_force(normal, c, v, ke, kdc, mu);
    ext_n.atomic_add(l, cross(x, f));
    ext_f.atomic_add(l, f);
}

/// Contact of a pair of contact spheres on two links (`pair_a[tid]`, `pair_b[tid]`, indices
/// of contact spheres): at signed distance `d = |cb - ca| - ra - rb` along `n = (cb - ca) /
/// |cb - ca|`, the point `x` midway between the surfaces gets the ground's law with the
/// relative velocity `v_b(x) - v_a(x)`: `f = contact_force(n, contact_depth(d, leak), ...)`
/// pushes `b` (wrench `(x x f, f)`) and `-f` pushes `a`.
#[diff_kernel]
pub fn articulation_pair_contact<R: Real>(
    pair_a: &Array<u32>,
    pair_b: &Array<u32>,
    contact_link: &Array<u32>,
    contact_pos: &Array<Vec3<R>>,
    contact_radius: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    ke: R,
    kd: R,
    mu: R,
    leak: R,
    damping_depth: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
) {
    let t = tid();
    let i = pair_a[t] as usize;
    let j = pair_b[t] as usize;
    let la = contact_link[i] as usize;
    let lb = contact_link[j] as usize;
    let ca = link_p[la] + quat_rotate(link_r[la], contact_pos[i]);
    let cb = link_p[lb] + quat_rotate(link_r[lb], contact_pos[j]);
    let n = normalize(cb - ca);
    let ra = contact_radius[i];
    let rb = contact_radius[j];
    let d = length(cb - ca) - ra - rb;
    let x = ca + n * (ra + 0.5 * d);
    let va = link_v[la] + cross(link_w[la], x);
    let vb = link_v[lb] + cross(link_w[lb], x);
    let c = contact_depth(d, leak);
    let kdc = contact_damping(c, kd, 0.0, damping_depth);
    let f = contact_force(n, c, vb - va, ke, kdc, mu);
    ext_n.atomic_add(lb, cross(x, f));
    ext_f.atomic_add(lb, f);
    ext_n.atomic_sub(la, cross(x, f));
    ext_f.atomic_sub(la, f);
}
