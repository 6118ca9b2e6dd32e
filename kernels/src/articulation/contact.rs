//! Contact of links: spheres, capsules, boxes, cylinders and ellipsoids on links pressed into
//! a ground plane and into each other, with the library's contact law (penalty, damping
//! ramped in over `damping_depth`, Coulomb friction smoothed below the stiction tolerance,
//! optional leaky gradient, optional onset).
//!
//! Against the ground a shape touches by its lowest points, which is exact for a plane: a
//! sphere by its own, a capsule by its end spheres, a box by its corners, an ellipsoid by its
//! point whose normal is the plane's; a cylinder, tilted or on its side, by its caps' deepest
//! rim points, and upright (within 5 degrees, blended) by three rim points of each cap fixed
//! in the cylinder (see [`support_offset`]). An ellipsoid touches nothing else; a cylinder
//! touches spheres and capsules as [`articulation_cylinder_contact`] says, and nothing else:
//! a model in which one of them would touch a shape it cannot is refused when it is built
//! (exclude the pair, change the filters, or set `link_contact` to false). Between links:
//! - sphere and capsule pairs by the closest points of their axes (a sphere's is a point):
//!   exact, at any angle (capsules crossing in their middles touch);
//! - a sphere or a capsule and a box by the closest points of the axis and the box (and a
//!   capsule by more points, below): exact while the axis stays outside the box (a
//!   penetration shallower than the radius); an axis inside the box is pushed out through the
//!   face nearest the axis point found;
//! - two boxes by each one's twelve edges against the other box, as segments of radius 0: the
//!   middle of an edge's part inside the other box is pushed out through the face nearest it
//!   (edges crossing touch; a corner inside sinks the three edges that meet there, each by
//!   about half the corner's depth, and a face resting on a face rests on its four edges at
//!   full depth and the four side edges at half).
//!
//! A capsule (not a sphere) against a box touches by more than its closest point, so that it
//! rests on a box as on the ground ([`capsule_box_point`]): its two end spheres, and its axis'
//! points over the box's edges (where the axis crosses the planes of the box's faces), each a
//! sphere-box contact, and the closest point where it is on an edge or a corner of the box
//! ([`articulation_box_contact`]; over a face, the depth along the axis is linear, deepest at
//! the other points), away from the capsule's ends. A capsule lying on a face rests on its two
//! ends; half over the edge, on its end and the edge; across a narrow box, on the box's two
//! edges; and the contacts move continuously as it tilts. Pressed deeper than its radius (its
//! axis inside the box), it is pushed out by its closest point through the nearest face, as
//! before, and by its ends: the points over the edges, then on the box's side faces, fade out.
//! Then a capsule half over an edge is held by its end on the box and the middle of its part
//! inside, no longer by the edge, and tips towards the edge if its centre of mass is beyond
//! that middle.
//!
//! Two capsules whose axes are parallel within 0.3 degrees touch at the two ends of their
//! overlap (as a capsule rests on the ground on its two ends; MuJoCo too makes two contacts),
//! blended with the one contact of their closest points up to 1.7 degrees
//! ([`articulation_capsule_contact`]): a capsule lying on another resists tilting smoothly
//! and stably, where one point under the middle of the overlap would jump to the lower end.
//!
//! Which shapes touch follows MuJoCo's rule: shapes `a` and `b` touch when `a.contype &
//! b.conaffinity` or `b.contype & a.conaffinity` is non-zero ([`ContactFilter`]; the ground has
//! its own filter), and never when their links are welded together by fixed joints (links
//! fixed to the world count as welded to each other), or are parent and child after welding
//! (unless one of them is fixed to the world), or are excluded
//! ([`ArticulationBuilder::exclude_contact`](super::ArticulationBuilder::exclude_contact)).

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

use super::pose::{LinkId, Pose};
use crate::contact::law::{
    contact_damping, contact_depth, contact_force_with_stiction, contact_onset, friction_damper,
    STICTION_TOLERANCE,
};
use crate::contact::shapes::sdf_cylinder;

/// Which shapes touch which (MuJoCo's `contype` and `conaffinity` bit masks): `a` and `b`
/// touch when `a.contype & b.conaffinity != 0` or `b.contype & a.conaffinity != 0`. The
/// default (`1`, `1`) touches every other default.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ContactFilter {
    /// This shape's type bits.
    pub contype: u32,
    /// The type bits this shape accepts.
    pub conaffinity: u32,
}

impl Default for ContactFilter {
    fn default() -> Self {
        ContactFilter {
            contype: 1,
            conaffinity: 1,
        }
    }
}

impl ContactFilter {
    /// A filter that touches nothing.
    pub const NONE: ContactFilter = ContactFilter {
        contype: 0,
        conaffinity: 0,
    };

    /// Whether a shape with this filter touches one with `other`.
    pub fn touches(&self, other: &ContactFilter) -> bool {
        self.contype & other.conaffinity != 0 || other.contype & self.conaffinity != 0
    }
}

/// A contact shape on a link: a [`GeomShape::Sphere`] (centred at `pose.pos`), a
/// [`GeomShape::Capsule`] or [`GeomShape::Cylinder`] (along `pose`'s z), a [`GeomShape::Box`]
/// or a [`GeomShape::Ellipsoid`], at `pose` in the link's frame. Cylinders touch the ground,
/// particles, spheres and capsules; ellipsoids the ground only: a model in which one would
/// touch another shape is refused when it is built.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContactShape {
    /// The link it is on.
    pub link: LinkId,
    /// Its frame in the link's frame.
    pub pose: Pose,
    /// Its shape.
    pub shape: GeomShape,
    /// Which other shapes it touches.
    pub filter: ContactFilter,
    /// Its friction coefficient (`None`: the ground's [`GroundContact::mu`]). A contact's
    /// friction is the larger of its two sides', as MuJoCo's: the ground's and the shape's
    /// against the ground, the two shapes' between links.
    pub friction: Option<f64>,
}

impl ContactShape {
    /// The spheres by which it touches a plane (centre in the link frame, radius): a sphere's
    /// own, a capsule's end spheres, a box's corners (radius 0).
    pub fn ground_spheres(&self) -> Vec<(Vec3<f64>, f64)> {
        match self.shape {
            GeomShape::Sphere(r) => vec![(self.pose.pos, r)],
            GeomShape::Capsule(r, h) => vec![(self.end(-h), r), (self.end(h), r)],
            GeomShape::Box(half) => self.corners(&half).into_iter().map(|c| (c, 0.0)).collect(),
            GeomShape::Cylinder(..) | GeomShape::Ellipsoid(..) | GeomShape::Plane => Vec::new(),
        }
    }

    /// The contact points by which a cylinder or an ellipsoid touches a plane, which move on
    /// it as it turns: [`support_offset`]'s variants (an ellipsoid's one, a cylinder's eight);
    /// none for the other shapes.
    pub fn ground_supports(&self) -> &'static [u32] {
        match self.shape {
            GeomShape::Ellipsoid(..) => &[0],
            GeomShape::Cylinder(..) => &[1, 2, 3, 4, 5, 6, 7, 8],
            _ => &[],
        }
    }

    /// The size vector [`support_offset`] takes: an ellipsoid's semi-axes, a cylinder's
    /// radius and half-length (then 0).
    pub(crate) fn support_size(&self) -> Vec3<f64> {
        match self.shape {
            GeomShape::Ellipsoid(a) => a,
            GeomShape::Cylinder(r, h) => Vec3::new(r, h, 0.0),
            _ => Vec3::zeros(),
        }
    }

    /// A sphere's or capsule's axis (its ends in the link frame) and radius; `None` for a box.
    pub(crate) fn segment(&self) -> Option<(Vec3<f64>, Vec3<f64>, f64)> {
        match self.shape {
            GeomShape::Sphere(r) => Some((self.pose.pos, self.pose.pos, r)),
            GeomShape::Capsule(r, h) => Some((self.end(-h), self.end(h), r)),
            _ => None,
        }
    }

    /// A box's twelve edges (their ends) in the link frame.
    pub(crate) fn edges(&self, half: &Vec3<f64>) -> Vec<(Vec3<f64>, Vec3<f64>)> {
        let c = self.corners(half);
        // Corner `k` has bit `b` set when it is on the + side along axis `b`.
        (0..8)
            .flat_map(|k| (0..3).map(move |b| (k, b)))
            .filter(|&(k, b)| k & (1 << b) == 0)
            .map(|(k, b)| (c[k], c[k | (1 << b)]))
            .collect()
    }

    /// A box's corners in the link frame.
    pub(crate) fn corners(&self, half: &Vec3<f64>) -> Vec<Vec3<f64>> {
        (0..8)
            .map(|k| {
                let s = |b: usize| if k & (1 << b) == 0 { -1.0 } else { 1.0 };
                let corner = Vec3::new(s(0) * half.x, s(1) * half.y, s(2) * half.z);
                self.pose.transform_point(&corner)
            })
            .collect()
    }

    fn end(&self, z: f64) -> Vec3<f64> {
        self.pose.transform_point(&Vec3::new(0.0, 0.0, z))
    }
}

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
    /// An ellipsoid of these semi-axes.
    Ellipsoid(Vec3<f64>),
    /// A plane through the origin with normal z.
    Plane,
}

/// Every contact shape of the links (spheres, capsules, boxes) as particles touch them
/// ([`crate::coupling::LinkParticleContact`]), in the form of the particles' shape SDFs
/// ([`shape_sdf`](crate::contact::shapes::shape_sdf)): `kind` 0 a sphere of radius `size.x`,
/// 1 a box of half extents `size`, 2 a capsule and 3 a cylinder of radius `size.x` and half
/// length `size.y` along its frame's x axis (a [`GeomShape::Capsule`] or
/// [`GeomShape::Cylinder`] is along its z axis: its rotation here includes the turn from x to
/// z), 4 an ellipsoid of semi-axes `size` (particles do not touch ellipsoids: coupling refuses
/// one). Positions and rotations are in the link's frame.
#[derive(Clone, Debug)]
pub struct LinkShapes<R: Real> {
    /// Per shape: its link (the model's link order).
    pub link: Array<u32>,
    /// Per shape: 0 sphere, 1 box, 2 capsule, 3 cylinder, 4 ellipsoid.
    pub kind: Array<u32>,
    /// Per shape: its centre in the link frame (m).
    pub pos: Array<Vec3<R>>,
    /// Per shape: its rotation in the link frame.
    pub rot: Array<Quat<R>>,
    /// Per shape: its size (m), as `kind` says.
    pub size: Array<Vec3<R>>,
    /// Per shape: which others it touches ([`ContactShape::filter`]).
    pub filter: Vec<ContactFilter>,
    /// Per shape: its own friction coefficient, if it has one ([`ContactShape::friction`]).
    pub friction: Vec<Option<f64>>,
}

impl<R: Real> LinkShapes<R> {
    /// The shapes of `shapes`, their links renumbered by `link_of`.
    pub(crate) fn new(shapes: &[ContactShape], link_of: impl Fn(usize) -> usize) -> Self {
        let r = |x: f64| R::lit(x);
        let v3 = |x: f64, y: f64, z: f64| Vec3::new(r(x), r(y), r(z));
        let support = |s: Vec3<f64>| v3(s.x, s.y, s.z);
        // The turn by -90 degrees about y takes the SDF's x axis to the capsule's z axis.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let x_to_z = Quat::new(h, 0.0, -h, 0.0);
        let (mut link, mut kind, mut pos, mut rot, mut size) =
            (vec![], vec![], vec![], vec![], vec![]);
        let (mut filter, mut friction) = (vec![], vec![]);
        for c in shapes {
            let (k, q, s) = match c.shape {
                GeomShape::Sphere(radius) => (0, c.pose.rot, v3(radius, 0.0, 0.0)),
                GeomShape::Box(half) => (1, c.pose.rot, v3(half.x, half.y, half.z)),
                GeomShape::Capsule(radius, half) => (2, c.pose.rot * x_to_z, v3(radius, half, 0.0)),
                GeomShape::Cylinder(..) => (3, c.pose.rot * x_to_z, support(c.support_size())),
                GeomShape::Ellipsoid(..) => (4, c.pose.rot, support(c.support_size())),
                // Refused by the builder's checks.
                GeomShape::Plane => continue,
            };
            link.push(link_of(c.link.0) as u32);
            kind.push(k);
            pos.push(v3(c.pose.pos.x, c.pose.pos.y, c.pose.pos.z));
            rot.push(Quat::new(r(q.w), r(q.i), r(q.j), r(q.k)));
            size.push(s);
            filter.push(c.filter);
            friction.push(c.friction);
        }
        LinkShapes {
            link: Array::from_vec(link),
            kind: Array::from_vec(kind),
            pos: Array::from_vec(pos),
            rot: Array::from_vec(rot),
            size: Array::from_vec(size),
            filter,
            friction,
        }
    }

    /// Number of shapes.
    pub fn len(&self) -> usize {
        self.link.len()
    }

    /// Whether there is none.
    pub fn is_empty(&self) -> bool {
        self.link.is_empty()
    }
}

/// The ground plane links touch, and its contact law.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroundContact<R: Real> {
    /// Unit normal, out of the ground (default `+z`, as URDF and MJCF).
    pub normal: Vec3<R>,
    /// The plane is `dot(normal, x) = offset` (m).
    pub offset: R,
    /// Stiffness per contact (N/m; default 1e4): per sphere, capsule end or box corner on
    /// the ground; between links, per pair of spheres or capsules (two capsules lying
    /// parallel: per end of their overlap), per sphere and box, per
    /// capsule end and point over a box's edge on a box (a capsule lying on a box's face rests
    /// on its two ends, as on the ground), and per edge of a box inside another. Contacts
    /// between links use this law too, with the shapes' own friction.
    pub ke: R,
    /// Damping in contact (N s/m; default 100), ramped in over `damping_depth`.
    pub kd: R,
    /// Friction coefficient (default 0.8): the ground's, and that of every shape without its
    /// own ([`ContactShape::friction`]). Read when the model is built, into the per-contact
    /// arrays `contact_mu`, `support_mu`, `capsule_pair_mu`, `box_pair_mu` and
    /// `cylinder_pair_mu` of
    /// [`Articulations`](super::Articulations); edit those (or make them require gradients)
    /// afterwards.
    pub mu: R,
    /// Gradient leak out of contact (default 0: exact gradients; see
    /// [`contact_depth`]).
    pub leak: R,
    /// Depth over which the damping rises to `kd` (m; default 1e-3; with an [`onset`], the
    /// depth after the onset's softening, so the damping is full at about `damping_depth +
    /// onset / 2`).
    ///
    /// [`onset`]: GroundContact::onset
    pub damping_depth: R,
    /// Depth over which the penalty force rises from 0 with zero slope (m; default 0, the
    /// plain law: [`contact_onset`]). A few millimetres smooth the gradients of rollouts
    /// whose contacts begin and end often (an object rolling in and out of a cup), which the
    /// plain law makes rough at the scale of a time step; it also lowers the force of a
    /// shallow contact, so the resting depth grows by up to `onset / 2` (exactly that when
    /// the plain depth exceeds `onset / 2`). Its slope at first contact is 0, so with an
    /// onset the `leak` has no effect. 0, or at least 1e-9.
    pub onset: R,
    /// The friction's smoothing speed `vs` (m/s; default [`STICTION_TOLERANCE`], 0.01;
    /// positive; see [`contact_force_with_stiction`]): at the sliding speed `u` the friction
    /// is `mu |f| u / (u + vs)`, linear in `u` well below `vs`, half of Coulomb's at `vs`, 91%
    /// at `10 vs`. At rest it is a damper of slope `mu |f| / vs`, which an explicit step
    /// integrates stably only where `mu |f| dt / (vs m) < 2`, `m` the mass the contact moves
    /// in that direction: a light link under a heavy load (a leg's foot), or a box resting on
    /// a face, whose turn about the normal moves a third of its mass
    /// (`3 mu g dt / vs < 2`: at `mu` 1 and a 2 ms step it needs `vs` above 0.03). Past the
    /// bound the motion stays bounded (the friction saturates) but never settles (the box
    /// turns back and forth at about `vs / 2`), and a rollout's gradient grows exponentially
    /// with its steps (the quadruped's gait takes 0.1). A larger value lets a body on a slope
    /// creep at about `vs tan(a) / (mu - tan(a))`.
    ///
    /// With [`implicit_friction`](GroundContact::implicit_friction) (the default) `Euler` and
    /// `ImplicitFast` steps integrate the ground's damper implicitly, and the bound above
    /// applies only to `Rk4` (whose stages are explicit) and to the contacts between links
    /// that stay explicit (see `implicit_friction`).
    pub stiction_tolerance: R,
    /// Whether `Euler` and `ImplicitFast` steps integrate the ground friction's damper
    /// implicitly (default true): the step solves with `M + dt D`, `D` the damper
    /// `k (I - n n^T)` of each contact on the ground, and of each contact between a link and
    /// a link fixed to the world (a table, a wall, a step, a rail: the damper is on the
    /// other link) ([`friction_damper`]: the friction's slope at
    /// rest, `1 / |u|` sliding fast; at the step's start) mapped to the joints, as the joint
    /// damping is. A body at rest then settles at any step, however light it is and however
    /// hard it is pressed; without it the friction is explicit and the bound of
    /// [`stiction_tolerance`](GroundContact::stiction_tolerance) applies. The friction force
    /// itself is unchanged; a sliding contact's deceleration differs by `O(dt)`. `Rk4` and
    /// contacts between two moving links (whose damper would couple their articulations'
    /// solves) stay explicit.
    pub implicit_friction: bool,
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
            onset: 0.0,
            stiction_tolerance: STICTION_TOLERANCE,
            implicit_friction: true,
        }
    }
}

impl GroundContact<f64> {
    /// Checks: a unit normal, everything finite, coefficients non-negative, an onset of 0 or at
    /// least 1e-9 m, a stiction tolerance of at least 1e-9 m/s.
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
            (self.onset, "onset"),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{what} {v} must be finite and non-negative"));
            }
        }
        // (An onset of 1e-310 would divide 0 by an infinite slope at first contact: NaN.)
        if self.onset > 0.0 && self.onset < 1e-9 {
            let o = self.onset;
            return Err(format!("onset {o} m must be 0 (none) or at least 1e-9 m"));
        }
        // (0 would divide 0 by 0 at rest.)
        let vs = self.stiction_tolerance;
        if !(vs.is_finite() && vs >= 1e-9) {
            return Err(format!(
                "stiction_tolerance {vs} m/s must be finite and at least 1e-9 m/s (default \
                 {STICTION_TOLERANCE})"
            ));
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
            onset: r(self.onset),
            stiction_tolerance: r(self.stiction_tolerance),
            implicit_friction: self.implicit_friction,
        }
    }
}

/// The ground's law at a link's point `x` moving at `v`, against the plane `plane` (its unit
/// normal `n` and offset: `n.x = offset`; `law` and `ramp` as `link_pair_force`'s): the law
/// between links, the ground as the link `a` at rest, at the signed distance
/// `d = n.x - offset`.
#[diff_func]
fn ground_force<R: Real>(
    x: Vec3<R>,
    v: Vec3<R>,
    plane: Vec4<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
) -> Vec3<R> {
    let n = vec3(plane.x, plane.y, plane.z);
    link_pair_force(n, dot(n, x) - plane.w, v, law, ramp)
}

/// The damper `k (I - n n^T)` that an implicit step takes for [`ground_force`]'s friction at
/// the same point (arguments as there), `k` the [`friction_damper`] of its sliding velocity.
#[diff_func]
fn ground_friction_damper<R: Real>(
    x: Vec3<R>,
    v: Vec3<R>,
    plane: Vec4<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
) -> Mat33<R> {
    let n = vec3(plane.x, plane.y, plane.z);
    pair_friction_damper(n, dot(n, x) - plane.w, v, law, ramp)
}

/// The damper `k (I - n n^T)` that an implicit step takes for [`link_pair_force`]'s friction
/// (arguments as there), `k` the [`friction_damper`] of the sliding velocity.
#[diff_func]
fn pair_friction_damper<R: Real>(
    n: Vec3<R>,
    d: R,
    rel: Vec3<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
) -> Mat33<R> {
    let c = contact_onset(contact_depth(d, ramp.x), ramp.z);
    let vt = rel - n * dot(n, rel);
    (mat33_identity() - outer(n, n)) * friction_damper(c, vt, law.x, law.z, ramp.w)
}

/// Ground contact of contact sphere `tid` (centre `contact_pos` in the frame of link
/// `contact_link`, radius `contact_radius`): its lowest point `x` at signed distance
/// `d = n.x - offset` gets `f = contact_force_with_stiction(n, c, v, ke, kd', mu, vs)` with
/// `c = contact_onset(contact_depth(d, leak), onset)`, `v` the velocity of the link's point at
/// `x`, `kd'` the ramped damping and `mu` the sphere's `contact_mu`; the link receives the
/// wrench `(x x f, f)` (world frame, at the origin).
///
/// With `damper_dt > 0` (an implicit step's `dt`), the friction's damper `K`
/// (`k (I - n n^T)`, `k` the [`friction_damper`] of the sliding velocity) times `damper_dt` joins the link's damping blocks
/// `(damp_ww, damp_wv, damp_vv)` `+= (-X K X, X K, K)`, `X` the cross-product matrix of `x`:
/// the wrench's derivative in the link's angular and linear velocities (`v` that of the
/// point at the origin) is `-(ww w + wv v, wv^T w + vv v)`.
#[diff_kernel]
pub fn articulation_ground_contact<R: Real>(
    contact_link: &Array<u32>,
    contact_pos: &Array<Vec3<R>>,
    contact_radius: &Array<R>,
    contact_mu: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    ke: R,
    kd: R,
    leak: R,
    damping_depth: R,
    onset: R,
    stiction: R,
    damper_dt: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
) {
    let t = tid();
    let l = contact_link[t] as usize;
    let centre = link_p[l] + quat_rotate(link_r[l], contact_pos[t]);
    let x = centre - normal * contact_radius[t];
    let v = link_v[l] + cross(link_w[l], x);
    let law = vec3(ke, kd, contact_mu[t]);
    let plane = vec4(normal.x, normal.y, normal.z, offset);
    let ramp = vec4(leak, damping_depth, onset, stiction);
    let f = ground_force(x, v, plane, law, ramp);
    ext_n.atomic_add(l, cross(x, f));
    ext_f.atomic_add(l, f);
    if damper_dt > 0.0 {
        let k = ground_friction_damper(x, v, plane, law, ramp) * damper_dt;
        let xk = skew(x) * k;
        damp_ww.atomic_sub(l, xk * skew(x));
        damp_wv.atomic_add(l, xk);
        damp_vv.atomic_add(l, k);
    }
}

/// The offset, in the world frame, from the centre of an ellipsoid or a cylinder (its frame
/// `q` in the world, its `size`) to its contact point `variant` against a plane of unit
/// normal `n` (out of the plane), and the point's weight (`w`: the share of the contact law
/// it gets):
/// - `0`, an ellipsoid of semi-axes `size`: the point whose outward normal is `-n` (the
///   deepest, exactly), weight 1;
/// - `1` to `8`, a cylinder along z of radius `size.x` and half-length `size.y`, on the cap at
///   `+size.y` (`1..=4`) or `-size.y` (`5..=8`): the rim point deepest along `-n` (`1`, `5`),
///   and three rim points fixed in the cylinder at 0, 120 and 240 degrees from its x axis
///   (the others). A cylinder stands on its fixed points and rolls or tips on its deepest:
///   with `s` the square of the sine of its axis' tilt from `n`, the fixed points weigh
///   `u = max(1 - 130 s, 0)^2` (1 upright, 0 past a tilt of 5 degrees) and the deepest
///   `1 - u`. On its side it rests on its two caps' deepest points, and it rolls without
///   bumps; upright on its cap's three fixed points, a support that does not turn as it
///   rocks (MuJoCo places three points there too, turned with the deepest's direction).
///   Upright the deepest direction is undefined (and turns at `radius / sin(tilt)` per radian
///   of tilt): the deepest point is the rim point's direction normalized smoothly, so that it
///   moves to the cap's centre within a tilt of about 0.1 degrees, turns at most about
///   `radius / 2e-3` per radian, and is at most `radius * 2e-6 / sin(tilt)` above the exact
///   deepest depth (in the direction of the exact deepest point, so that a cylinder on its
///   side feels no torque from it).
#[diff_func]
pub fn support_offset<R: Real>(variant: u32, q: Quat<R>, size: Vec3<R>, n: Vec3<R>) -> Vec4<R> {
    let m = quat_rotate_inv(q, n);
    let mut local = vec3(0.0, 0.0, 0.0);
    let mut weight = 1.0;
    if variant == 0 {
        let w = vec3(size.x * m.x, size.y * m.y, size.z * m.z);
        local = vec3(size.x * w.x, size.y * w.y, size.z * w.z) * (-1.0 / length(w));
    } else {
        let upright = max(1.0 - 130.0 * (m.x * m.x + m.y * m.y), 0.0);
        // The deepest rim point's direction in the cap's plane, -(m.x, m.y), normalized
        // smoothly (by 2e-3): defined upright, where the point is at the cap's centre and
        // weighs nothing; never longer than 1; and along the exact direction at every tilt.
        let vx = -m.x;
        let vy = -m.y;
        let a = 1.0 / sqrt(vx * vx + vy * vy + 4e-6);
        let mut ux = vx * a;
        let mut uy = vy * a;
        weight = 1.0 - upright * upright;
        if variant != 1 && variant != 5 {
            weight = upright * upright;
            ux = 1.0;
            uy = 0.0;
            if variant == 3 || variant == 7 {
                ux = -0.5;
                uy = 0.8660254037844386;
            } else if variant == 4 || variant == 8 {
                ux = -0.5;
                uy = -0.8660254037844386;
            }
        }
        let mut z = size.y;
        if variant > 4 {
            z = -size.y;
        }
        local = vec3(size.x * ux, size.x * uy, z);
    }
    let x = quat_rotate(q, local);
    vec4(x.x, x.y, x.z, weight)
}

/// Ground contact of the cylinders' and ellipsoids' contact points: point `tid` of the shape
/// at `support_pos`, rotated by `support_rot`, in the frame of link `support_link`, of size
/// `support_size`, is [`support_offset`]'s point `support_variant` from the shape's centre;
/// it touches the ground as a contact sphere of radius 0 does in
/// [`articulation_ground_contact`], with the friction `support_mu`, its force (and its
/// friction's damper) times the point's weight.
#[diff_kernel]
pub fn articulation_support_contact<R: Real>(
    support_link: &Array<u32>,
    support_variant: &Array<u32>,
    support_pos: &Array<Vec3<R>>,
    support_rot: &Array<Quat<R>>,
    support_size: &Array<Vec3<R>>,
    support_mu: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    ke: R,
    kd: R,
    leak: R,
    damping_depth: R,
    onset: R,
    stiction: R,
    damper_dt: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
) {
    let t = tid();
    let l = support_link[t] as usize;
    let q = quat_mul(link_r[l], support_rot[t]);
    let centre = link_p[l] + quat_rotate(link_r[l], support_pos[t]);
    let o = support_offset(support_variant[t], q, support_size[t], normal);
    let x = centre + vec3(o.x, o.y, o.z);
    let v = link_v[l] + cross(link_w[l], x);
    let law = vec3(ke, kd, support_mu[t]);
    let plane = vec4(normal.x, normal.y, normal.z, offset);
    let ramp = vec4(leak, damping_depth, onset, stiction);
    let f = ground_force(x, v, plane, law, ramp) * o.w;
    ext_n.atomic_add(l, cross(x, f));
    ext_f.atomic_add(l, f);
    if damper_dt > 0.0 {
        let k = ground_friction_damper(x, v, plane, law, ramp) * (damper_dt * o.w);
        let xk = skew(x) * k;
        damp_ww.atomic_sub(l, xk * skew(x));
        damp_wv.atomic_add(l, xk);
        damp_vv.atomic_add(l, k);
    }
}

/// The parameters `(s, t)` in `[0, 1]` of the closest points `a0 + s (a1 - a0)` and `b0 + t
/// (b1 - b0)` of two segments (Ericson's, Real-Time Collision Detection 5.1.9). For parallel
/// segments, the middle of the range of `s` over which they are closest.
#[diff_func]
pub fn closest_on_segments<R: Real>(a0: Vec3<R>, a1: Vec3<R>, b0: Vec3<R>, b1: Vec3<R>) -> Vec2<R> {
    let d1 = a1 - a0;
    let d2 = b1 - b0;
    let r = a0 - b0;
    let aa = dot(d1, d1);
    let ee = dot(d2, d2);
    let f = dot(d2, r);
    let mut s = 0.0;
    let mut t = 0.0;
    if aa <= 0.0 {
        if ee > 0.0 {
            t = clamp(f / ee, 0.0, 1.0);
        }
    } else {
        let c = dot(d1, r);
        if ee <= 0.0 {
            s = clamp(-c / aa, 0.0, 1.0);
        } else {
            let b = dot(d1, d2);
            let denom = aa * ee - b * b;
            if denom > 1e-12 * aa * ee {
                s = clamp((b * f - c * ee) / denom, 0.0, 1.0);
            } else {
                // Parallel: the middle of b's shadow on a.
                s = 0.5 * (clamp(-c / aa, 0.0, 1.0) + clamp((b - c) / aa, 0.0, 1.0));
            }
            t = (b * s + f) / ee;
            if t < 0.0 {
                t = 0.0;
                s = clamp(-c / aa, 0.0, 1.0);
            } else if t > 1.0 {
                t = 1.0;
                s = clamp((b - c) / aa, 0.0, 1.0);
            }
        }
    }
    vec2(s, t)
}

/// Half the slope of `s -> dist(p0 + s d, box)^2` (convex, so its slope never decreases).
fn box_slope<R: Real>(p0: Vec3<R>, d: Vec3<R>, half: Vec3<R>, s: R) -> R {
    let mut g = R::zero();
    for k in 0..3 {
        let p = p0[k] + d[k] * s;
        if p > half[k] {
            g += (p - half[k]) * d[k];
        } else if p < -half[k] {
            g += (p + half[k]) * d[k];
        }
    }
    g
}

/// The range `[first, last]` of `s` in `[0, 1]` where `p0 + s d` is closest to the box of
/// half extents `half` centred at the origin (by bisection on the slope; not differentiated:
/// [`segment_box_contact`] takes the derivative from the closed form of the piece it lands
/// on). The range is one point unless the axis runs inside the box or parallel to a face.
pub fn closest_on_segment_to_box<R: Real>(p0: Vec3<R>, d: Vec3<R>, half: Vec3<R>) -> Vec2<R> {
    let (zero, one, two) = (R::zero(), R::one(), R::one() + R::one());
    let slope = |s: R| box_slope(p0, d, half, s);
    // The first s where the slope is >= 0, and the last where it is <= 0.
    let bisect = |up: bool| {
        let (mut lo, mut hi) = (zero, one);
        for _ in 0..60 {
            let mid = (lo + hi) / two;
            let g = slope(mid);
            if (up && g >= zero) || (!up && g > zero) {
                hi = mid;
            } else {
                lo = mid;
            }
        }
        if up {
            hi
        } else {
            lo
        }
    };
    let first = if slope(zero) >= zero {
        zero
    } else {
        bisect(true)
    };
    let last = if slope(one) <= zero {
        one
    } else {
        bisect(false)
    };
    Vec2::new(first, if last < first { first } else { last })
}

/// `e` in `[0, 1]` where `p0 + e d` crosses a face's plane, differentiably: 0 or 1 at the
/// ends, else the crossing of the plane nearest the point.
#[diff_func]
fn face_crossing<R: Real>(p0: Vec3<R>, d: Vec3<R>, half: Vec3<R>, e: R) -> R {
    let mut out = e;
    if e > 0.0 && e < 1.0 {
        let p = p0 + d * e;
        // Snap only to a plane within 1e-3 of the range's end (in s).
        let mut best = 1e-3;
        for k in 0..3 {
            if abs(d[k]) > 0.0 {
                let gap = abs(abs(p[k]) - half[k]) / abs(d[k]);
                if gap < best {
                    best = gap;
                    if p[k] < 0.0 {
                        out = (-half[k] - p0[k]) / d[k];
                    } else {
                        out = (half[k] - p0[k]) / d[k];
                    }
                }
            }
        }
    }
    clamp(out, 0.0, 1.0)
}

/// Contact of a sphere or capsule with a box, in the box's frame: `p0`, `d` the axis
/// (`p0 + s d`, `s` in `[0, 1]`), `r` its radius, `half` the box's half extents. Returns the
/// contact point midway between the surfaces, the unit normal out of the box and
/// `(signed distance, s, 0)` as its columns. `range` is [`closest_on_segment_to_box`]'s
/// answer.
#[diff_func]
pub fn segment_box_contact<R: Real>(
    p0: Vec3<R>,
    d: Vec3<R>,
    r: R,
    half: Vec3<R>,
    range: Vec2<R>,
) -> Mat33<R> {
    // Differentiable s: on the piece where the same faces are outside, the closed form.
    let sb = 0.5 * (range.x + range.y);
    let pb = p0 + d * sb;
    let mut num = 0.0;
    let mut den = 0.0;
    for k in 0..3 {
        if pb[k] > half[k] {
            num += (p0[k] - half[k]) * d[k];
            den += d[k] * d[k];
        } else if pb[k] < -half[k] {
            num += (p0[k] + half[k]) * d[k];
            den += d[k] * d[k];
        }
    }
    let mut s = sb;
    // (Narrower than 1e-6: one point, as bisection in f32 resolves it.)
    if range.y - range.x > 1e-6 {
        // A range (inside, or parallel to a face): its middle, between face crossings.
        s = 0.5 * (face_crossing(p0, d, half, range.x) + face_crossing(p0, d, half, range.y));
    } else if sb > 0.0 && sb < 1.0 && den > 1e-12 * dot(d, d) {
        s = clamp(-num / den, 0.0, 1.0);
    }
    let p = p0 + d * s;
    let q = vec3(
        clamp(p.x, -half.x, half.x),
        clamp(p.y, -half.y, half.y),
        clamp(p.z, -half.z, half.z),
    );
    let e = p - q;
    let dist = length(e);
    let mut n = vec3(0.0, 0.0, 0.0);
    let mut depth = 0.0;
    let mut at = p;
    if dist > 0.0 {
        n = e / dist;
        depth = dist - r;
        at = q + n * (0.5 * depth);
    } else {
        // The axis point is inside: out through the nearest face.
        let gap = half - vec3(abs(p.x), abs(p.y), abs(p.z));
        let mut k = 0;
        if gap.y < gap.x && gap.y <= gap.z {
            k = 1;
        } else if gap.z < gap.x && gap.z < gap.y {
            k = 2;
        }
        if p[k] < 0.0 {
            n[k] = -1.0;
        } else {
            n[k] = 1.0;
        }
        depth = -gap[k] - r;
        at = p + n * (0.5 * (gap[k] - r));
    }
    mat33_cols(at, n, vec3(depth, s, 0.0))
}

/// `t` clamped to `[0, 1]` and smoothed (`3t² - 2t³`): a weight that rises from 0 to 1 with a
/// continuous slope.
#[diff_func]
fn smooth_ramp<R: Real>(t: R) -> R {
    let u = clamp(t, 0.0, 1.0);
    u * u * (3.0 - 2.0 * u)
}

/// Contact point `c` of a capsule (axis `p0 + s d`, `s` in `[0, 1]`, radius `r > 0`,
/// `|d| > 0`) against a box of half extents `half`, in the box's frame, besides the closest
/// point: `c = 0`, `1` its end spheres (`s = 0`, `1`); `c = 2..8` the axis' crossing of the
/// plane `x_k = ±half_k` (`k = (c - 2) / 2`, `-` for even `c`), which supports the capsule
/// where the axis passes over an edge of the box. Each is a sphere-box contact
/// ([`segment_box_contact`] of a point). Returns the contact point (`xyz`), the normal out of
/// the box and `(depth, weight, 0)`: the ends weigh 1; a crossing outside the axis weighs 0,
/// one within `r` of an end fades in with its distance from the end (`smooth_ramp`), where it
/// merges with the end sphere, and one inside the face's rectangle (the axis pierces the box:
/// deeper than `r`, where the closest point pushes out) fades out over `0.1 r` inside it,
/// pushed out meanwhile through the nearest of the box's other faces, so that the contacts
/// change continuously with the pose. An axis within `1e-9 |d|` of parallel
/// to the plane does not cross it.
#[diff_func]
pub fn capsule_box_point<R: Real>(
    p0: Vec3<R>,
    d: Vec3<R>,
    r: R,
    half: Vec3<R>,
    c: u32,
) -> Mat33<R> {
    let mut p = p0;
    let mut w = 1.0;
    let mut outer = half;
    if c == 1 {
        p = p0 + d;
    } else if c >= 2 {
        let k = ((c - 2) / 2) as usize;
        let mut plane = half[k];
        if c % 2 == 0 {
            plane = -half[k];
        }
        w = 0.0;
        if abs(d[k]) > 1e-9 * length(d) {
            let s = (plane - p0[k]) / d[k];
            if s > 0.0 && s < 1.0 {
                p = p0 + d * s;
                // On the plane exactly (not to rounding): where the axis pierces the face, the
                // point is then on the box's surface with a constant normal, instead of a
                // normal `e / |e|` of an `e` of rounding's size, whose derivatives are noise.
                p[k] = plane;
                // How far inside the face's rectangle the point is (< 0: over an edge).
                let j = (k + 1) % 3;
                let l = (k + 2) % 3;
                let inside = min(half[j] - abs(p[j]), half[l] - abs(p[l]));
                w = smooth_ramp(min(s, 1.0 - s) * length(d) / r)
                    * (1.0 - smooth_ramp(inside / (0.1 * r)));
                // Inside (while it fades) out through the nearest of the other faces, as over
                // the edge beside it, not through its own plane (sideways for a capsule sunk
                // across a beam): the box is `r` longer on this axis.
                outer[k] = half[k] + r;
            }
        }
    }
    // A sphere: the segment of length 0 at `p`.
    let m = segment_box_contact(p, vec3(0.0, 0.0, 0.0), r, outer, vec2(0.0, 0.0));
    mat33_cols(
        vec3(m[(0, 0)], m[(1, 0)], m[(2, 0)]),
        vec3(m[(0, 1)], m[(1, 1)], m[(2, 1)]),
        vec3(m[(0, 2)], w, 0.0),
    )
}

/// The contact law between two links (normal `n` from `a` to `b`, signed distance `d`, `rel`
/// the velocity of `b`'s point at the contact relative to `a`'s; `law`: `ke, kd, mu`; `ramp`:
/// `leak, damping_depth, onset, stiction_tolerance`): the force on `b`,
/// `contact_force_with_stiction(n, c, rel, ke, kd', mu, vs)` with
/// `c = contact_onset(contact_depth(d, leak), onset)` and the damping `kd'` ramped in.
#[diff_func]
fn link_pair_force<R: Real>(
    n: Vec3<R>,
    d: R,
    rel: Vec3<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
) -> Vec3<R> {
    let c = contact_onset(contact_depth(d, ramp.x), ramp.z);
    let kdc = contact_damping(c, law.y, 0.0, ramp.y);
    contact_force_with_stiction(n, c, rel, law.x, kdc, law.z, ramp.w)
}

/// The contact of the points `ca` of link `a`'s axis and `cb` of link `b`'s (radii `ra`,
/// `rb`; velocities `va`, `vb`: the links' linear velocities in column 0, angular in column
/// 1), at signed distance `d = |cb - ca| - ra - rb` along `n = (cb - ca) / |cb - ca|`, at the
/// point `x` midway between the surfaces: `weight` times the wrench `(x x f, f)` on `b`
/// (columns 0 and 1).
#[diff_func]
#[allow(clippy::too_many_arguments)]
fn axis_points_wrench<R: Real>(
    ca: Vec3<R>,
    cb: Vec3<R>,
    ra: R,
    rb: R,
    va: Mat33<R>,
    vb: Mat33<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
    weight: R,
) -> Mat33<R> {
    let c = axis_contact(ca, cb, ra, rb);
    let x = vec3(c[(0, 0)], c[(1, 0)], c[(2, 0)]);
    let n = vec3(c[(0, 1)], c[(1, 1)], c[(2, 1)]);
    point_wrench(x, n, c[(0, 2)], va, vb, law, ramp, weight)
}

/// The contact of the axis points `ca` of link `a` and `cb` of link `b` (radii `ra`, `rb`):
/// the point `x` midway between the surfaces, the normal `n = (cb - ca) / |cb - ca|` and the
/// signed distance `d = |cb - ca| - ra - rb`, as the columns `(x, n, (d, 0, 0))`.
#[diff_func]
fn axis_contact<R: Real>(ca: Vec3<R>, cb: Vec3<R>, ra: R, rb: R) -> Mat33<R> {
    let n = normalize(cb - ca);
    let d = length(cb - ca) - ra - rb;
    mat33_cols(ca + n * (ra + 0.5 * d), n, vec3(d, 0.0, 0.0))
}

/// The damper `K` of the friction at the contact `c` of [`axis_contact`] (`va`, `vb`, `law`,
/// `ramp` as [`point_wrench`]'s): [`pair_friction_damper`] at its point.
#[diff_func]
fn axis_contact_damper<R: Real>(
    c: Mat33<R>,
    va: Mat33<R>,
    vb: Mat33<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
) -> Mat33<R> {
    let x = vec3(c[(0, 0)], c[(1, 0)], c[(2, 0)]);
    let n = vec3(c[(0, 1)], c[(1, 1)], c[(2, 1)]);
    pair_friction_damper(n, c[(0, 2)], relative_velocity(x, va, vb), law, ramp)
}

/// The velocity of link `b`'s point at `x` relative to link `a`'s (`va`, `vb`: the links'
/// linear velocities in column 0, angular in column 1).
#[diff_func]
fn relative_velocity<R: Real>(x: Vec3<R>, va: Mat33<R>, vb: Mat33<R>) -> Vec3<R> {
    let vla = vec3(va[(0, 0)], va[(1, 0)], va[(2, 0)]);
    let wla = vec3(va[(0, 1)], va[(1, 1)], va[(2, 1)]);
    let vlb = vec3(vb[(0, 0)], vb[(1, 0)], vb[(2, 0)]);
    let wlb = vec3(vb[(0, 1)], vb[(1, 1)], vb[(2, 1)]);
    (vlb + cross(wlb, x)) - (vla + cross(wla, x))
}

/// The wrench `weight (x x f, f, 0)` on link `b` of the contact law at the point `x` (normal
/// `n` from `a` to `b`, signed distance `d`; `va`, `vb` the links' linear velocities in column
/// 0, angular in column 1; `law`, `ramp` as [`link_pair_force`]'s).
#[diff_func]
#[allow(clippy::too_many_arguments)]
fn point_wrench<R: Real>(
    x: Vec3<R>,
    n: Vec3<R>,
    d: R,
    va: Mat33<R>,
    vb: Mat33<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
    weight: R,
) -> Mat33<R> {
    let f = link_pair_force(n, d, relative_velocity(x, va, vb), law, ramp) * weight;
    mat33_cols(cross(x, f), f, vec3(0.0, 0.0, 0.0))
}

/// How much two axes `d1`, `d2` touch along a line rather than at a point: 1 where the sine
/// of their angle is below 0.005 (0.3 degrees), 0 above 0.03 (1.7 degrees), smoothly between;
/// 0 if either is a point (a sphere).
#[diff_func]
fn parallel_weight<R: Real>(d1: Vec3<R>, d2: Vec3<R>) -> R {
    let aa = dot(d1, d1);
    let ee = dot(d2, d2);
    let both = aa * ee;
    let safe = select(both > 0.0, both, 1.0);
    let sine = length(cross(d1, d2)) / sqrt(safe);
    select(both > 0.0, 1.0 - smooth_ramp((sine - 0.005) / 0.025), 0.0)
}

/// Contact of pairs of spheres or capsules on two links (`capsule_pairs[tid]`,
/// indices of segments `seg_*`: ends in the link frame, radius): with the closest points `ca`, `cb`
/// of their axes ([`closest_on_segments`]), at signed distance `d = |cb - ca| - ra - rb`
/// along `n = (cb - ca) / |cb - ca|`, the point `x` midway between the surfaces gets the
/// ground's law with the relative velocity `v_b(x) - v_a(x)` and the pair's friction
/// `capsule_pair_mu[tid]`: `f = contact_force_with_stiction(n, c, ...)` with
/// `c = contact_onset(contact_depth(d, leak), onset)` pushes `b` (wrench `(x x f, f)`) and
/// `-f` pushes `a`.
///
/// Two capsules whose axes are parallel within 0.3 degrees touch along a line: they get, in
/// place of the closest points, the contacts at the two ends of the range of `a`'s axis that
/// `b`'s shadows (each with its closest point on `b`'s axis), as a capsule on the ground rests
/// on its two ends; between 0.3 and 1.7 degrees the two blend smoothly
/// (`parallel_weight`), so the torque about the contact changes continuously as one tilts. An
/// overlap shorter than the sum of the radii (capsules end to end) weighs the two ends half
/// each at length 0 (one contact), rising smoothly to full weight.
///
/// In an implicit step, against a link fixed to the world, each contact's friction damper
/// (times its weight) joins the other link's blocks, as in [`articulation_box_contact`].
#[diff_kernel]
pub fn articulation_capsule_contact<R: Real>(
    capsule_pairs: &Array<[u32; 2]>,
    capsule_pair_mu: &Array<R>,
    seg_link: &Array<u32>,
    seg_a: &Array<Vec3<R>>,
    seg_b: &Array<Vec3<R>>,
    seg_radius: &Array<R>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    ke: R,
    kd: R,
    leak: R,
    damping_depth: R,
    onset: R,
    stiction: R,
    link_fixed: &Array<u32>,
    damper_dt: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
) {
    let t = tid();
    let [i, j] = capsule_pairs[t];
    let la = seg_link[i as usize] as usize;
    let lb = seg_link[j as usize] as usize;
    let a0 = link_p[la] + quat_rotate(link_r[la], seg_a[i]);
    let a1 = link_p[la] + quat_rotate(link_r[la], seg_b[i]);
    let b0 = link_p[lb] + quat_rotate(link_r[lb], seg_a[j]);
    let b1 = link_p[lb] + quat_rotate(link_r[lb], seg_b[j]);
    let ra = seg_radius[i];
    let rb = seg_radius[j];
    let va = mat33_cols(link_v[la], link_w[la], vec3(0.0, 0.0, 0.0));
    let vb = mat33_cols(link_v[lb], link_w[lb], vec3(0.0, 0.0, 0.0));
    let law = vec3(ke, kd, capsule_pair_mu[t]);
    let ramp = vec4(leak, damping_depth, onset, stiction);
    let d1 = a1 - a0;
    let d2 = b1 - b0;
    let w = parallel_weight(d1, d2);
    let st = closest_on_segments(a0, a1, b0, b1);
    let ca = a0 + d1 * st.x;
    let cb = b0 + d2 * st.y;
    let mut e = axis_points_wrench(ca, cb, ra, rb, va, vb, law, ramp, 1.0 - w);
    // The parallel contacts' points (weight `we`; none unless `w > 0`).
    let mut lo = ca;
    let mut on_b_lo = cb;
    let mut hi = ca;
    let mut on_b_hi = cb;
    let mut we = 0.0;
    if w > 0.0 {
        // The ends of the range of `a`'s axis in `b`'s shadow, and their closest points on
        // `b`'s axis.
        let aa = dot(d1, d1);
        let ee = dot(d2, d2);
        let s0 = dot(d1, b0 - a0) / aa;
        let s1 = dot(d1, b1 - a0) / aa;
        let s_lo = clamp(min(s0, s1), 0.0, 1.0);
        let s_hi = clamp(max(s0, s1), 0.0, 1.0);
        lo = a0 + d1 * s_lo;
        hi = a0 + d1 * s_hi;
        on_b_lo = b0 + d2 * clamp(dot(lo - b0, d2) / ee, 0.0, 1.0);
        on_b_hi = b0 + d2 * clamp(dot(hi - b0, d2) / ee, 0.0, 1.0);
        // Two ends of an overlap shorter than the radii (capsules end to end, or touching by
        // their rounded ends) are one contact: half each.
        let overlap = (s_hi - s_lo) * sqrt(aa) / max(ra + rb, 1e-12);
        we = w * (0.5 + 0.5 * smooth_ramp(overlap));
        e = e + axis_points_wrench(lo, on_b_lo, ra, rb, va, vb, law, ramp, we);
        e = e + axis_points_wrench(hi, on_b_hi, ra, rb, va, vb, law, ramp, we);
    }
    let nb = vec3(e[(0, 0)], e[(1, 0)], e[(2, 0)]);
    let fb = vec3(e[(0, 1)], e[(1, 1)], e[(2, 1)]);
    ext_n.atomic_add(lb, nb);
    ext_f.atomic_add(lb, fb);
    ext_n.atomic_sub(la, nb);
    ext_f.atomic_sub(la, fb);
    // Against a link fixed to the world, the friction's dampers on the other link: per
    // contact `K` at `x`, the blocks `(-X K X, X K, K)`, summed.
    if damper_dt > 0.0 {
        let fixed_a = link_fixed[la];
        let fixed_b = link_fixed[lb];
        if fixed_a + fixed_b == 1 {
            let l = la * (fixed_b as usize) + lb * (fixed_a as usize);
            let c = axis_contact(ca, cb, ra, rb);
            let x = vec3(c[(0, 0)], c[(1, 0)], c[(2, 0)]);
            let k = axis_contact_damper(c, va, vb, law, ramp) * ((1.0 - w) * damper_dt);
            let mut kv = k;
            let mut kw = skew(x) * k;
            let mut kww = kw * skew(x);
            if w > 0.0 {
                let c_lo = axis_contact(lo, on_b_lo, ra, rb);
                let x_lo = vec3(c_lo[(0, 0)], c_lo[(1, 0)], c_lo[(2, 0)]);
                let k_lo = axis_contact_damper(c_lo, va, vb, law, ramp) * (we * damper_dt);
                let c_hi = axis_contact(hi, on_b_hi, ra, rb);
                let x_hi = vec3(c_hi[(0, 0)], c_hi[(1, 0)], c_hi[(2, 0)]);
                let k_hi = axis_contact_damper(c_hi, va, vb, law, ramp) * (we * damper_dt);
                kv = kv + k_lo + k_hi;
                kw = kw + skew(x_lo) * k_lo + skew(x_hi) * k_hi;
                kww = kww + skew(x_lo) * k_lo * skew(x_lo) + skew(x_hi) * k_hi * skew(x_hi);
            }
            damp_ww.atomic_sub(l, kww);
            damp_wv.atomic_add(l, kw);
            damp_vv.atomic_add(l, kv);
        }
    }
}

/// The wrench on the segment's link of a contact with a box, `weight` times the contact law:
/// `e` the contact in the box's frame (point, normal out of the box, `(depth, ..)`), the box's
/// frame `ob`, `rb` in the world, the velocities `(v, w)` of the segment's link `a` and the
/// box's `b`; `law`: `ke, kd, mu`; `ramp`: `leak, damping_depth, onset,
/// stiction_tolerance`. Returns
/// `(x x f, f, 0)`.
#[diff_func]
#[allow(clippy::too_many_arguments)]
fn box_contact_wrench<R: Real>(
    e: Mat33<R>,
    ob: Vec3<R>,
    rb: Quat<R>,
    va: Mat33<R>,
    vb: Mat33<R>,
    law: Vec3<R>,
    ramp: Vec4<R>,
    weight: R,
) -> Mat33<R> {
    let x = ob + quat_rotate(rb, vec3(e[(0, 0)], e[(1, 0)], e[(2, 0)]));
    let n = quat_rotate(rb, vec3(e[(0, 1)], e[(1, 1)], e[(2, 1)]));
    // The normal points out of the box `b`, onto the segment's link `a`.
    point_wrench(x, n, e[(0, 2)], vb, va, law, ramp, weight)
}

/// Contact of a sphere or capsule (segment `box_pairs[tid][0]`, as in
/// [`articulation_capsule_contact`]) with a box (`box_pairs[tid][1]`: its link, centre and
/// rotation in the link frame, half extents): [`segment_box_contact`] in the box's frame
/// gives the point `x` midway between the surfaces, the normal `n` out of the box and the
/// signed distance `d`; `f = contact_force_with_stiction(n, c, v_seg(x) - v_box(x),
/// ...)`, with the pair's friction `box_pair_mu[tid]`, pushes the segment's link and `-f` the
/// box's; in an implicit step, against a link fixed to the world, the friction's damper
/// ([`GroundContact::implicit_friction`]) joins the other link's blocks, as in
/// [`articulation_ground_contact`], times the weight below. For a capsule (radius and length
/// above 0; a box's edge has radius 0) the force is
/// times `max(1 - smooth_ramp((a - 0.9) / 0.1), smooth_ramp((-d - r) / (0.1 r)))` times
/// `smooth_ramp(min(s, 1 - s) |axis| / r)`, `a` the largest component of `n` in the box's
/// frame, `s` the point's place on the axis: the closest point acts where it is on an edge or
/// a corner of the box (`a` below 0.9), not where it is over a face (`a = 1`), where the depth
/// along the axis is linear and deepest at the points of [`articulation_capsule_box_points`]
/// (the capsule's ends and its axis' points over the box's edges); it acts again where the
/// axis is inside the box (deeper than `r`), and not at an end, where the end sphere is the
/// same contact.
#[diff_kernel]
pub fn articulation_box_contact<R: Real>(
    box_pairs: &Array<[u32; 2]>,
    box_pair_mu: &Array<R>,
    seg_link: &Array<u32>,
    seg_a: &Array<Vec3<R>>,
    seg_b: &Array<Vec3<R>>,
    seg_radius: &Array<R>,
    box_link: &Array<u32>,
    box_pos: &Array<Vec3<R>>,
    box_rot: &Array<Quat<R>>,
    box_half: &Array<Vec3<R>>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    ke: R,
    kd: R,
    leak: R,
    damping_depth: R,
    onset: R,
    stiction: R,
    link_fixed: &Array<u32>,
    damper_dt: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
) {
    let t = tid();
    let [i, k] = box_pairs[t];
    let la = seg_link[i as usize] as usize;
    let lb = box_link[k as usize] as usize;
    // The box's frame in the world.
    let rb = quat_mul(link_r[lb], box_rot[k]);
    let ob = link_p[lb] + quat_rotate(link_r[lb], box_pos[k]);
    let a0 = link_p[la] + quat_rotate(link_r[la], seg_a[i]);
    let a1 = link_p[la] + quat_rotate(link_r[la], seg_b[i]);
    let p0 = quat_rotate_inv(rb, a0 - ob);
    let d = quat_rotate_inv(rb, a1 - a0);
    let half = box_half[k];
    let r = seg_radius[i];
    let range = no_grad(closest_on_segment_to_box(p0, d, half));
    let m = segment_box_contact(p0, d, r, half, range);
    let mut weight = 1.0;
    if r > 0.0 && dot(d, d) > 0.0 {
        // A capsule: the points of `articulation_capsule_box_points` carry it over a face.
        let a = max(max(abs(m[(0, 1)]), abs(m[(1, 1)])), abs(m[(2, 1)]));
        let face = smooth_ramp((a - 0.9) / 0.1);
        // An axis inside the box (deeper than `r`) is pushed out through the nearest face,
        // fully once `0.1 r` inside, as the crossing points fade out.
        let deep = smooth_ramp((-m[(0, 2)] - r) / (0.1 * r));
        // At an end the end sphere is the same contact.
        let s = m[(1, 2)];
        let end = smooth_ramp(min(s, 1.0 - s) * length(d) / r);
        weight = max(1.0 - face, deep) * end;
    }
    if weight > 0.0 {
        let x = ob + quat_rotate(rb, vec3(m[(0, 0)], m[(1, 0)], m[(2, 0)]));
        let n = quat_rotate(rb, vec3(m[(0, 1)], m[(1, 1)], m[(2, 1)]));
        let rel = (link_v[la] + cross(link_w[la], x)) - (link_v[lb] + cross(link_w[lb], x));
        let law = vec3(ke, kd, box_pair_mu[t]);
        let ramp = vec4(leak, damping_depth, onset, stiction);
        let f = link_pair_force(n, m[(0, 2)], rel, law, ramp) * weight;
        ext_n.atomic_add(la, cross(x, f));
        ext_f.atomic_add(la, f);
        ext_n.atomic_sub(lb, cross(x, f));
        ext_f.atomic_sub(lb, f);
        // Against a link fixed to the world, the friction's damper on the other link.
        if damper_dt > 0.0 {
            let fa = link_fixed[la];
            let fb = link_fixed[lb];
            if fa + fb == 1 {
                let l = la * (fb as usize) + lb * (fa as usize);
                let k = pair_friction_damper(n, m[(0, 2)], rel, law, ramp) * (damper_dt * weight);
                let xk = skew(x) * k;
                damp_ww.atomic_sub(l, xk * skew(x));
                damp_wv.atomic_add(l, xk);
                damp_vv.atomic_add(l, k);
            }
        }
    }
}

/// The further contacts of a capsule with a box (a pair of `box_pairs` whose segment has a
/// radius and a length above 0; other pairs have none), thread `tid` = 8 x pair + point:
/// point `c` of [`capsule_box_point`] (its end spheres, its axis over the face's edges), with
/// the law and friction of [`articulation_box_contact`], times the point's weight; and, in an
/// implicit step against a link fixed to the world, the friction's damper as there.
#[diff_kernel]
pub fn articulation_capsule_box_points<R: Real>(
    box_pairs: &Array<[u32; 2]>,
    box_pair_mu: &Array<R>,
    seg_link: &Array<u32>,
    seg_a: &Array<Vec3<R>>,
    seg_b: &Array<Vec3<R>>,
    seg_radius: &Array<R>,
    box_link: &Array<u32>,
    box_pos: &Array<Vec3<R>>,
    box_rot: &Array<Quat<R>>,
    box_half: &Array<Vec3<R>>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    ke: R,
    kd: R,
    leak: R,
    damping_depth: R,
    onset: R,
    stiction: R,
    link_fixed: &Array<u32>,
    damper_dt: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
) {
    let t = tid() / 8;
    let c = (tid() % 8) as u32;
    let [i, k] = box_pairs[t];
    let r = seg_radius[i];
    if r > 0.0 {
        let la = seg_link[i as usize] as usize;
        let lb = box_link[k as usize] as usize;
        let rb = quat_mul(link_r[lb], box_rot[k]);
        let ob = link_p[lb] + quat_rotate(link_r[lb], box_pos[k]);
        let a0 = link_p[la] + quat_rotate(link_r[la], seg_a[i]);
        let a1 = link_p[la] + quat_rotate(link_r[la], seg_b[i]);
        let p0 = quat_rotate_inv(rb, a0 - ob);
        let d = quat_rotate_inv(rb, a1 - a0);
        if dot(d, d) > 0.0 {
            let e = capsule_box_point(p0, d, r, box_half[k], c);
            if e[(1, 2)] > 0.0 {
                let va = mat33_cols(link_v[la], link_w[la], vec3(0.0, 0.0, 0.0));
                let vb = mat33_cols(link_v[lb], link_w[lb], vec3(0.0, 0.0, 0.0));
                let law = vec3(ke, kd, box_pair_mu[t]);
                let ramp = vec4(leak, damping_depth, onset, stiction);
                let wr = box_contact_wrench(e, ob, rb, va, vb, law, ramp, e[(1, 2)]);
                let tn = vec3(wr[(0, 0)], wr[(1, 0)], wr[(2, 0)]);
                let f = vec3(wr[(0, 1)], wr[(1, 1)], wr[(2, 1)]);
                ext_n.atomic_add(la, tn);
                ext_f.atomic_add(la, f);
                ext_n.atomic_sub(lb, tn);
                ext_f.atomic_sub(lb, f);
                if damper_dt > 0.0 {
                    let fa = link_fixed[la];
                    let fb = link_fixed[lb];
                    if fa + fb == 1 {
                        let l = la * (fb as usize) + lb * (fa as usize);
                        let x = ob + quat_rotate(rb, vec3(e[(0, 0)], e[(1, 0)], e[(2, 0)]));
                        let n = quat_rotate(rb, vec3(e[(0, 1)], e[(1, 1)], e[(2, 1)]));
                        let rel = relative_velocity(x, vb, va);
                        let k = pair_friction_damper(n, e[(0, 2)], rel, law, ramp)
                            * (damper_dt * e[(1, 2)]);
                        let xk = skew(x) * k;
                        damp_ww.atomic_sub(l, xk * skew(x));
                        damp_wv.atomic_add(l, xk);
                        damp_vv.atomic_add(l, k);
                    }
                }
            }
        }
    }
}

/// Contact of a sphere or capsule (segment `cylinder_pairs[tid][0]`, as in
/// [`articulation_capsule_contact`]) with a cylinder (`cylinder_pairs[tid][1]`: its link,
/// centre and rotation in the link frame, radius and half-length): the segment's point `p`
/// closest to the cylinder's axis ([`closest_on_segments`]) is pushed out along the
/// cylinder's SDF ([`sdf_cylinder`]): at signed distance
/// `d = sdf(p) - radius` along its normal `n`, the point `x` midway between the surfaces gets
/// `f = contact_force_with_stiction(n, c, v_seg(x) - v_cyl(x), ...)` (`c` as in
/// [`articulation_capsule_contact`]) with the pair's friction `cylinder_pair_mu[tid]`; `f`
/// pushes the segment's link and `-f` the cylinder's; in an implicit step, against a link
/// fixed to the world, the friction's damper joins the other link's blocks, as in
/// [`articulation_box_contact`].
/// Exact for a sphere, for a capsule parallel to the axis or crossing it; otherwise the
/// segment's point nearest the axis stands for its nearest point to the cylinder.
#[diff_kernel]
pub fn articulation_cylinder_contact<R: Real>(
    cylinder_pairs: &Array<[u32; 2]>,
    cylinder_pair_mu: &Array<R>,
    seg_link: &Array<u32>,
    seg_a: &Array<Vec3<R>>,
    seg_b: &Array<Vec3<R>>,
    seg_radius: &Array<R>,
    cylinder_link: &Array<u32>,
    cylinder_pos: &Array<Vec3<R>>,
    cylinder_rot: &Array<Quat<R>>,
    cylinder_size: &Array<Vec3<R>>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    ke: R,
    kd: R,
    leak: R,
    damping_depth: R,
    onset: R,
    stiction: R,
    link_fixed: &Array<u32>,
    damper_dt: R,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
    damp_ww: &Array<Mat33<R>>,
    damp_wv: &Array<Mat33<R>>,
    damp_vv: &Array<Mat33<R>>,
) {
    let t = tid();
    let [i, k] = cylinder_pairs[t];
    let la = seg_link[i as usize] as usize;
    let lb = cylinder_link[k as usize] as usize;
    // The cylinder's frame in the world, and its axis.
    let rb = quat_mul(link_r[lb], cylinder_rot[k]);
    let ob = link_p[lb] + quat_rotate(link_r[lb], cylinder_pos[k]);
    let size = cylinder_size[k];
    let c0 = ob - quat_rotate(rb, vec3(0.0, 0.0, size.y));
    let c1 = ob + quat_rotate(rb, vec3(0.0, 0.0, size.y));
    let a0 = link_p[la] + quat_rotate(link_r[la], seg_a[i]);
    let a1 = link_p[la] + quat_rotate(link_r[la], seg_b[i]);
    let st = closest_on_segments(a0, a1, c0, c1);
    let p = a0 + (a1 - a0) * st.x;
    // The SDF is along x: the cylinder's (x, y, z) are its (y, z, x).
    let pl = quat_rotate_inv(rb, p - ob);
    let g = sdf_cylinder(vec3(pl.z, pl.x, pl.y), size);
    let n = quat_rotate(rb, vec3(g.y, g.z, g.x));
    let r = seg_radius[i];
    let d = g.w - r;
    let x = p - n * (r + 0.5 * d);
    let rel = (link_v[la] + cross(link_w[la], x)) - (link_v[lb] + cross(link_w[lb], x));
    let law = vec3(ke, kd, cylinder_pair_mu[t]);
    let ramp = vec4(leak, damping_depth, onset, stiction);
    let f = link_pair_force(n, d, rel, law, ramp);
    ext_n.atomic_add(la, cross(x, f));
    ext_f.atomic_add(la, f);
    ext_n.atomic_sub(lb, cross(x, f));
    ext_f.atomic_sub(lb, f);
    // Against a link fixed to the world, the friction's damper on the other link.
    if damper_dt > 0.0 {
        let fa = link_fixed[la];
        let fb = link_fixed[lb];
        if fa + fb == 1 {
            let l = la * (fb as usize) + lb * (fa as usize);
            let k = pair_friction_damper(n, d, rel, law, ramp) * damper_dt;
            let xk = skew(x) * k;
            damp_ww.atomic_sub(l, xk * skew(x));
            damp_wv.atomic_add(l, xk);
            damp_vv.atomic_add(l, k);
        }
    }
}
