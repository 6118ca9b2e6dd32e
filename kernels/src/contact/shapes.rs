//! Contact of particles with static analytic shapes given by signed distance functions:
//! sphere, box, capsule. Each shape has a position and an orientation (both arrays, so they can
//! be gradient targets); the SDF and its outward normal are evaluated in the shape's frame.

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

use super::particle::ContactDesc;
use super::particle::ParticleContact;
use crate::forces::component::{real_parts, Force, ForceContext, ForcePart, Param, ParamDoc};
use crate::particles::Elements;
use crate::scene_file::reader::{identity_quat, sub, v3, Checker, SceneError};
use serde::Deserialize;

use super::law::{contact_damping, contact_depth, contact_force, penalty_energy};

/// The force's name ([`Force::name`]): `"shape_contact"`.
pub const NAME: &str = "shape_contact";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::array("pos", "m (shape position)"),
    ParamDoc::array("rot", "unit quaternion (shape orientation)"),
    ParamDoc::array(
        "size",
        "m (sphere radius, box half extents, capsule radius and half length)",
    ),
    ParamDoc::scalar("ke", "N/m"),
    ParamDoc::scalar("kd", "N·s/m"),
    ParamDoc::scalar("damping_depth", "m"),
    ParamDoc::scalar("mu", "1 (friction coefficient)"),
    ParamDoc::scalar("leak", "1 (gradient leak out of contact)"),
];

/// SDF of a sphere of radius `size.x` (m) at the origin: `(n, d)` packed as `(n.x, n.y, n.z, d)`
/// with `n` the outward normal (zero at the centre).
#[diff_func]
pub fn sdf_sphere<R: Real>(p: Vec3<R>, size: Vec3<R>) -> Vec4<R> {
    let n = normalize(p);
    vec4(n.x, n.y, n.z, length(p) - size.x)
}

/// SDF of a box of half-extents `size` (m) centred at the origin, packed like [`sdf_sphere`].
/// Outside, the normal points from the closest point of the box; inside, along the axis of the
/// closest face.
#[diff_func]
pub fn sdf_box<R: Real>(p: Vec3<R>, size: Vec3<R>) -> Vec4<R> {
    let qx = abs(p.x) - size.x;
    let qy = abs(p.y) - size.y;
    let qz = abs(p.z) - size.z;
    let qo = vec3(max(qx, 0.0), max(qy, 0.0), max(qz, 0.0));
    let outside = length(qo);
    let d = outside + min(max(qx, max(qy, qz)), 0.0);
    if outside > 0.0 {
        let no = normalize(qo);
        return vec4(no.x * sign(p.x), no.y * sign(p.y), no.z * sign(p.z), d);
    }
    if qx >= qy && qx >= qz {
        return vec4(sign(p.x), 0.0, 0.0, d);
    }
    if qy >= qz {
        return vec4(0.0, sign(p.y), 0.0, d);
    }
    vec4(0.0, 0.0, sign(p.z), d)
}

/// SDF of a capsule of radius `size.x` around the segment from `(-size.y, 0, 0)` to
/// `(size.y, 0, 0)` (m), packed like [`sdf_sphere`].
#[diff_func]
pub fn sdf_capsule<R: Real>(p: Vec3<R>, size: Vec3<R>) -> Vec4<R> {
    let h = size.y;
    let s = clamp(p.x, 0.0 - h, h);
    let dv = p - vec3(s, 0.0, 0.0);
    let n = normalize(dv);
    vec4(n.x, n.y, n.z, length(dv) - size.x)
}

/// SDF of a solid cylinder of radius `size.x` along the x axis from `-size.y` to `size.y`
/// (m), packed like [`sdf_sphere`]. Outside, the normal points from the closest point;
/// inside, out through the nearest of the side and the caps.
#[diff_func]
pub fn sdf_cylinder<R: Real>(p: Vec3<R>, size: Vec3<R>) -> Vec4<R> {
    let radial = normalize(vec3(0.0, p.y, p.z));
    let dr = length(vec3(0.0, p.y, p.z)) - size.x;
    let dh = abs(p.x) - size.y;
    let axial = vec3(sign(p.x), 0.0, 0.0);
    let mut g = vec4(radial.x, radial.y, radial.z, dr);
    if dr > 0.0 || dh > 0.0 {
        let out = axial * max(dh, 0.0) + radial * max(dr, 0.0);
        let n = normalize(out);
        g = vec4(n.x, n.y, n.z, length(out));
    } else if dh > dr {
        g = vec4(axial.x, 0.0, 0.0, dh);
    }
    g
}

/// The SDF of a shape of kind `k` (0 sphere, 1 box, 2 capsule, 3 cylinder: the last only for
/// articulations' shapes, [`LinkShapes`](crate::articulation::LinkShapes)) at `pos`, rotated
/// by `q`, of size `size`, at the point `x`: `(n, d)` as in [`sdf_sphere`], `n` in the shape's
/// frame.
#[diff_func]
pub fn shape_sdf<R: Real>(x: Vec3<R>, k: u32, pos: Vec3<R>, q: Quat<R>, size: Vec3<R>) -> Vec4<R> {
    let pl = quat_rotate_inv(q, x - pos);
    let mut g = sdf_sphere(pl, size);
    if k == 1 {
        g = sdf_box(pl, size);
    } else if k == 2 {
        g = sdf_capsule(pl, size);
    } else if k == 3 {
        g = sdf_cylinder(pl, size);
    }
    g
}

/// The signed distance (m) of a particle at `x` of radius `radius` from a shape (negative in
/// contact), as [`shape_contact_force`] measures it.
#[diff_func]
pub fn shape_gap<R: Real>(
    x: Vec3<R>,
    k: u32,
    pos: Vec3<R>,
    q: Quat<R>,
    size: Vec3<R>,
    radius: R,
) -> R {
    shape_sdf(x, k, pos, q, size).w - radius
}

/// The contact force (N) on a particle at `x` with velocity `v` and radius `radius` from a
/// shape of kind `k` (0 sphere, 1 box, 2 capsule) at `pos`, rotated by `q`, of size `size`:
/// what both shape-contact kernels compute. The damping `kd` ramps in over the first `depth`
/// metres of penetration ([`contact_damping`]).
#[diff_func]
#[allow(clippy::too_many_arguments)]
pub fn shape_contact_force<R: Real>(
    x: Vec3<R>,
    v: Vec3<R>,
    k: u32,
    pos: Vec3<R>,
    q: Quat<R>,
    size: Vec3<R>,
    radius: R,
    ke: R,
    kd: R,
    depth: R,
    mu: R,
    leak: R,
) -> Vec3<R> {
    let g = shape_sdf(x, k, pos, q, size);
    let n = quat_rotate(q, vec3(g.x, g.y, g.z));
    let c = contact_depth(g.w - radius, leak);
    // The ramp sees the true depth (no leaky slope through it), as the ground's does.
    let kdc = contact_damping(min(g.w - radius, 0.0), kd, 0.0, depth);
    contact_force(n, c, v, ke, kdc, mu)
}

/// Penalty energy of particle `tid / num_shapes` against shape `tid % num_shapes`:
/// `penalty_energy(shape_gap(..), ke)` (J), added to its world's `energy[world[i]]`; `radius` per
/// particle.
#[diff_kernel]
pub fn shape_contact_energy<R: Real>(
    x: &Array<Vec3<R>>,
    kind: &Array<u32>,
    pos: &Array<Vec3<R>>,
    rot: &Array<Quat<R>>,
    size: &Array<Vec3<R>>,
    num_shapes: usize,
    radius: &Array<R>,
    ke: R,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let p = t / num_shapes;
    let s = t % num_shapes;
    let d = shape_gap(x[p], kind[s], pos[s], rot[s], size[s], radius[p]);
    energy.atomic_add(world[p] as usize, penalty_energy(d, ke));
}

/// Contact of particle `tid / num_shapes` with shape `tid % num_shapes`: kind 0 sphere, 1 box,
/// 2 capsule (sizes as in [`sdf_sphere`], [`sdf_box`], [`sdf_capsule`]). With `(n, d)` the SDF
/// at the particle and `c = contact_depth(d - radius, leak)`, the particle gets
/// `contact_force(n, c, v, ke, contact_damping(c, kd, 0, depth), mu)` (damping only in contact,
/// ramped in over `depth` m).
#[diff_kernel]
pub fn eval_shape_contact<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    kind: &Array<u32>,
    pos: &Array<Vec3<R>>,
    rot: &Array<Quat<R>>,
    size: &Array<Vec3<R>>,
    num_shapes: usize,
    radius: R,
    ke: R,
    kd: R,
    depth: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let p = t / num_shapes;
    let s = t % num_shapes;
    let fc = shape_contact_force(
        x[p], v[p], kind[s], pos[s], rot[s], size[s], radius, ke, kd, depth, mu, leak,
    );
    f.atomic_add(p, fc);
}

/// [`eval_shape_contact`] with a radius per particle: `radius[tid / num_shapes]` (m).
#[diff_kernel]
pub fn eval_shape_contact_radii<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    kind: &Array<u32>,
    pos: &Array<Vec3<R>>,
    rot: &Array<Quat<R>>,
    size: &Array<Vec3<R>>,
    num_shapes: usize,
    radius: &Array<R>,
    ke: R,
    kd: R,
    depth: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let p = t / num_shapes;
    let s = t % num_shapes;
    let fc = shape_contact_force(
        x[p], v[p], kind[s], pos[s], rot[s], size[s], radius[p], ke, kd, depth, mu, leak,
    );
    f.atomic_add(p, fc);
}

/// The geometry of an analytic shape.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ShapeKind<R: Real> {
    /// A ball.
    Sphere {
        /// Radius (m).
        radius: R,
    },
    /// A box.
    Box {
        /// Half the side lengths along the shape's axes (m).
        half_extents: Vec3<R>,
    },
    /// A capsule along the shape's x axis.
    Capsule {
        /// Radius (m).
        radius: R,
        /// Half the length of the axis segment (m).
        half_length: R,
    },
}

impl<R: Real> ShapeKind<R> {
    /// The kind code and size vector the kernel takes.
    pub fn code(&self) -> (u32, Vec3<R>) {
        let z = R::lit(0.0);
        match *self {
            ShapeKind::Sphere { radius } => (0, Vec3::new(radius, z, z)),
            ShapeKind::Box { half_extents } => (1, half_extents),
            ShapeKind::Capsule {
                radius,
                half_length,
            } => (2, Vec3::new(radius, half_length, z)),
        }
    }
}

/// A static analytic shape in the world. No `Default`: the geometry has to be given
/// ([`Shape::new`] sets the identity orientation); the contact parameters of all shapes are
/// one [`ParticleContact`] ([`crate::ModelBuilder::set_shape_contact`], default
/// [`ParticleContact::default`](crate::contact::particle::ParticleContact)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shape<R: Real> {
    /// Geometry.
    pub kind: ShapeKind<R>,
    /// Position of the shape's origin (m).
    pub pos: Vec3<R>,
    /// Orientation (unit quaternion; [`Shape::new`]: the identity).
    pub rot: Quat<R>,
}

impl<R: Real> Shape<R> {
    /// The builder's checks: a finite position, a finite unit orientation (norm within 1e-3
    /// of 1), sizes (radius, half extents, half length) finite and `> 0`.
    pub(crate) fn check(&self, c: &mut crate::validation::Check) {
        c.finite3("pos", &self.pos);
        let q = &self.rot;
        if c.finite("rot", &[q.i, q.j, q.k, q.w]) {
            let l = q.norm().to_f64();
            if (l - 1.0).abs() > 1e-3 {
                c.fail(
                    Some("rot"),
                    format!("must be a unit quaternion (norm {l}); normalize it"),
                );
            }
        }
        match self.kind {
            ShapeKind::Sphere { radius } => {
                c.positive("radius", radius);
            }
            ShapeKind::Box { half_extents: h } => {
                for v in [h.x, h.y, h.z] {
                    if !c.positive("half_extents", v) {
                        break;
                    }
                }
            }
            ShapeKind::Capsule {
                radius,
                half_length,
            } => {
                c.positive("radius", radius);
                c.positive("half_length", half_length);
            }
        }
    }

    /// A shape at `pos` with the identity orientation.
    pub fn new(kind: ShapeKind<R>, pos: Vec3<R>) -> Self {
        Shape {
            kind,
            pos,
            rot: Quat::identity(),
        }
    }
}

/// The shapes of a model and the contact parameters they share.
#[derive(Clone, Debug)]
pub struct Shapes<R: Real> {
    /// Kind code per shape (0 sphere, 1 box, 2 capsule).
    pub kind: Array<u32>,
    /// Position (m).
    pub pos: Array<Vec3<R>>,
    /// Orientation (unit quaternion).
    pub rot: Array<Quat<R>>,
    /// Size vector (m), see [`ShapeKind::code`].
    pub size: Array<Vec3<R>>,
    /// Contact stiffness (N/m; default 1000, [`ParticleContact`]'s default, as are the
    /// others).
    pub ke: R,
    /// Contact damping (N s/m; default 1), only in contact and while approaching, ramped in
    /// over `damping_depth`.
    pub kd: R,
    /// The penetration depth (m; default 1e-4) over which the damping rises from 0 to `kd`
    /// (see [`ParticleContact::damping_depth`](crate::contact::particle::ParticleContact)).
    pub damping_depth: R,
    /// Friction coefficient (dimensionless; default 0.5).
    pub mu: R,
    /// Gradient leak out of contact (dimensionless; default 0: exact gradients).
    pub leak: R,
}

impl<R: Real> Shapes<R> {
    /// Records [`eval_shape_contact`] for every (particle, shape) pair, accumulating into `f`.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radius: R,
        f: &Array<Vec3<R>>,
    ) {
        let ns = self.kind.len();
        tape.launch(
            eval_shape_contact,
            x.len() * ns,
            (
                x,
                v,
                &self.kind,
                &self.pos,
                &self.rot,
                &self.size,
                ns,
                radius,
                self.ke,
                self.kd,
                self.damping_depth,
                self.mu,
                self.leak,
                f,
            ),
        );
    }
}

impl<R: Real> Shapes<R> {
    /// Records [`eval_shape_contact_radii`] for particles of radii `radii` (m).
    pub fn eval_radii(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radii: &Array<R>,
        f: &Array<Vec3<R>>,
    ) {
        let ns = self.kind.len();
        tape.launch(
            eval_shape_contact_radii,
            x.len() * ns,
            (
                x,
                v,
                &self.kind,
                &self.pos,
                &self.rot,
                &self.size,
                ns,
                radii,
                self.ke,
                self.kd,
                self.damping_depth,
                self.mu,
                self.leak,
                f,
            ),
        );
    }
}

/// Contact of the particles with the shapes; the shapes' poses and sizes are differentiable.
impl<R: Real> Force<R> for Shapes<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        match cx.particle_radii {
            Some(r) => self.eval_radii(tape, cx.x, cx.v, r, f),
            None => Shapes::eval(self, tape, cx.x, cx.v, cx.particle_radius, f),
        }
    }
    /// The penalty's potential ([`shape_contact_energy`]); damping and friction have none.
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        let ns = self.kind.len();
        let radii = match cx.particle_radii {
            Some(r) => r.clone(),
            None => Array::from_vec(vec![cx.particle_radius; cx.x.len()]),
        };
        tape.launch(
            shape_contact_energy,
            cx.x.len() * ns,
            (
                cx.x,
                &self.kind,
                &self.pos,
                &self.rot,
                &self.size,
                ns,
                &radii,
                self.ke,
                &cx.particle_worlds(),
                energy,
            ),
        );
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(Shapes::<f64> {
            kind: self.kind.clone(),
            pos: real_parts(&self.pos),
            rot: real_parts(&self.rot),
            size: real_parts(&self.size),
            ke: self.ke.to_f64(),
            kd: self.kd.to_f64(),
            damping_depth: self.damping_depth.to_f64(),
            mu: self.mu.to_f64(),
            leak: self.leak.to_f64(),
        }))
    }

    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("pos", &mut self.pos);
        visit("rot", &mut self.rot);
        visit("size", &mut self.size);
    }
}

/// The shapes of a scene description and their contact parameters (see
/// [`ModelBuilder::add_shape`](crate::ModelBuilder::add_shape),
/// [`ModelBuilder::set_shape_contact`](crate::ModelBuilder::set_shape_contact)).
#[derive(Clone, Debug)]
pub(crate) struct ShapeParts<R: Real> {
    shapes: Vec<Shape<R>>,
    contact: ParticleContact<R>,
}

impl<R: Real> Default for ShapeParts<R> {
    fn default() -> Self {
        ShapeParts {
            shapes: Vec::new(),
            contact: ParticleContact::default(),
        }
    }
}

impl<R: Real> ShapeParts<R> {
    pub(crate) fn add(&mut self, el: &mut Elements<'_, R>, shape: Shape<R>) -> u32 {
        let k = self.shapes.len();
        shape.check(&mut el.check("shapes", k));
        self.shapes.push(shape);
        k as u32
    }

    pub(crate) fn set_contact(&mut self, el: &mut Elements<'_, R>, contact: ParticleContact<R>) {
        contact.check(&mut el.check_one("shape_contact"));
        self.contact = contact;
    }
}

impl<R: Real> ForcePart<R> for ShapeParts<R> {
    fn append(&mut self, other: &Self, _offset: u32) -> Result<(), String> {
        // The shapes are the worlds' shared environment.
        let mut mine = (!self.shapes.is_empty()).then(|| self.clone());
        let theirs = (!other.shapes.is_empty()).then(|| other.clone());
        crate::forces::component::shared(&mut mine, &theirs)?;
        if let Some(m) = mine {
            *self = m;
        }
        Ok(())
    }

    fn worlds_in(&self, _particles: &std::ops::Range<u32>) -> Self {
        self.clone()
    }

    fn build(&self) -> Option<Box<dyn Force<R>>> {
        (!self.shapes.is_empty()).then(|| {
            let codes: Vec<(u32, Vec3<R>)> = self.shapes.iter().map(|s| s.kind.code()).collect();
            let c = &self.contact;
            Box::new(Shapes {
                kind: Array::from_vec(codes.iter().map(|c| c.0).collect()).named("shape_kind"),
                pos: Array::from_vec(self.shapes.iter().map(|s| s.pos).collect())
                    .named("shape_pos"),
                rot: Array::from_vec(self.shapes.iter().map(|s| s.rot).collect())
                    .named("shape_rot"),
                size: Array::from_vec(codes.iter().map(|c| c.1).collect()).named("shape_size"),
                ke: c.ke,
                kd: c.kd,
                damping_depth: c.damping_depth,
                mu: c.mu,
                leak: c.leak,
            }) as Box<dyn Force<R>>
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize, Clone, Copy, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub(crate) enum ShapeKindDesc {
    Sphere,
    Box,
    Capsule,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ShapeDesc {
    kind: ShapeKindDesc,
    pos: [f64; 3],
    #[serde(default = "identity_quat")]
    rot: [f64; 4],
    radius: Option<f64>,
    half_extents: Option<[f64; 3]>,
    half_length: Option<f64>,
}

/// Loads the `shape_contact` section.
pub(crate) fn load_contact<R: Real>(
    cd: &ContactDesc,
    part: &mut ShapeParts<R>,
    el: &mut Elements<'_, R>,
    c: &Checker,
) -> Result<(), SceneError> {
    let n0 = el.problems.len();
    part.set_contact(el, cd.to_contact());
    c.builder(el.problems, n0, |f| sub("shape_contact", f, &[]))
}

/// Loads the `shapes` section (quaternions normalized).
pub(crate) fn load<R: Real>(
    d: &[ShapeDesc],
    part: &mut ShapeParts<R>,
    el: &mut Elements<'_, R>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, s) in d.iter().enumerate() {
        let path = |f: &str| format!("shapes[{k}].{f}");
        c.finite(|| path("rot"), &s.rot)?;
        let q = Quat::new(s.rot[3], s.rot[0], s.rot[1], s.rot[2]);
        if !q.norm().is_normal() {
            return Err(c.err(path("rot"), "must be a nonzero quaternion [x, y, z, w]"));
        }
        let need = |v: Option<f64>, f: &str| -> Result<f64, SceneError> {
            v.ok_or_else(|| c.err(format!("shapes[{k}]"), format!("missing field `{f}`")))
        };
        let kind = match s.kind {
            ShapeKindDesc::Sphere => ShapeKind::Sphere {
                radius: R::lit(need(s.radius, "radius")?),
            },
            ShapeKindDesc::Box => {
                let h = s
                    .half_extents
                    .ok_or_else(|| c.err(format!("shapes[{k}]"), "missing field `half_extents`"))?;
                ShapeKind::Box {
                    half_extents: v3(h),
                }
            }
            ShapeKindDesc::Capsule => ShapeKind::Capsule {
                radius: R::lit(need(s.radius, "radius")?),
                half_length: R::lit(need(s.half_length, "half_length")?),
            },
        };
        let q = q / q.norm();
        let n0 = el.problems.len();
        part.add(
            el,
            Shape {
                kind,
                pos: v3(s.pos),
                rot: Quat::new(R::lit(q.w), R::lit(q.i), R::lit(q.j), R::lit(q.k)),
            },
        );
        c.builder(el.problems, n0, |f| sub(&format!("shapes[{k}]"), f, &[]))?;
    }
    Ok(())
}
