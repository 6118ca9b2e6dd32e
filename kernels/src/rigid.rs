//! Rigid bodies: position, orientation (unit quaternion), linear and angular velocity (world
//! frame), mass and body-frame inertia; forces and torques from gravity, contact of body
//! points with the ground, and control; a semi-implicit Euler step with the gyroscopic term
//! `w x I w` and quaternion renormalisation.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::contact::ground::Ground;
use crate::contact::law::{contact_depth, contact_force};
use crate::particles::check;
use crate::scene_file::reader::{identity_quat, sub, v3, zero3, Checker, SceneError};
pub use crate::state::BodyState;
use crate::validation::{max_of, precision, Problem};
use serde::Deserialize;

/// Ground contact of contact point `tid`, a point `contact_point` (m, body frame) of body
/// `contact_body`: with `r` the point relative to the centre of mass in world frame,
/// `c = contact_depth(dot(normal, x + r) - offset, leak)`, the body gets the force
/// `fc = contact_force(normal, c, v + w x r, ke, kd [c < 0], mu)` (N) and the torque `r x fc`
/// (N m). Damping acts only in contact.
#[diff_kernel]
pub fn eval_body_ground<R: Real>(
    body_x: &Array<Vec3<R>>,
    body_q: &Array<Quat<R>>,
    body_v: &Array<Vec3<R>>,
    body_w: &Array<Vec3<R>>,
    contact_body: &Array<u32>,
    contact_point: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    ke: R,
    kd: R,
    mu: R,
    leak: R,
    body_f: &Array<Vec3<R>>,
    body_t: &Array<Vec3<R>>,
) {
    let t = tid();
    let b = contact_body[t];
    let r = quat_rotate(body_q[b], contact_point[t]);
    let vp = body_v[b] + cross(body_w[b], r);
    let c = contact_depth(dot(normal, body_x[b] + r) - offset, leak);
    let kdc = select(c < 0.0, kd, 0.0);
    let fc = contact_force(normal, c, vp, ke, kdc, mu);
    body_f.atomic_add(b, fc);
    body_t.atomic_add(b, cross(r, fc));
}

/// Semi-implicit Euler step of body `tid`:
/// `v' = v + (f m^-1 + g [m^-1 > 0]) dt` (`g = gravity[world[tid]]`), `x' = x + v' dt`; in the
/// body frame
/// `w_b' = w_b + I^-1 (tau_b - w_b x I w_b) dt` (explicit gyroscopic term), `w' = q w_b'`;
/// `q' = normalize(q + (w', 0) q dt/2)`. `f` (N), `tau` (N m), `w` (rad/s) in world frame.
#[diff_kernel]
pub fn integrate_bodies<R: Real>(
    x: &Array<Vec3<R>>,
    q: &Array<Quat<R>>,
    v: &Array<Vec3<R>>,
    w: &Array<Vec3<R>>,
    f: &Array<Vec3<R>>,
    tau: &Array<Vec3<R>>,
    inv_mass: &Array<R>,
    inertia: &Array<Mat33<R>>,
    inv_inertia: &Array<Mat33<R>>,
    gravity: &Array<Vec3<R>>,
    world: &Array<u32>,
    dt: R,
    x_new: &Array<Vec3<R>>,
    q_new: &Array<Quat<R>>,
    v_new: &Array<Vec3<R>>,
    w_new: &Array<Vec3<R>>,
) {
    let t = tid();
    let im = inv_mass[t];
    let g = gravity[world[t] as usize];
    let v1 = v[t] + (f[t] * im + select(im > 0.0, g, g * 0.0)) * dt;
    let r = q[t];
    let wb = quat_rotate_inv(r, w[t]);
    let tb = quat_rotate_inv(r, tau[t]);
    let wb1 = wb + inv_inertia[t] * (tb - cross(wb, inertia[t] * wb)) * dt;
    let w1 = quat_rotate(r, wb1);
    let r1 = quat_normalize(r + quat(w1.x, w1.y, w1.z, 0.0) * r * (0.5 * dt));
    x_new[t] = x[t] + v1 * dt;
    q_new[t] = r1;
    v_new[t] = v1;
    w_new[t] = w1;
}

/// Kinetic energy of body `tid`, `m |v|^2 / 2 + w_b . I w_b / 2` (J), added to `energy[0]`.
#[diff_kernel]
pub fn body_kinetic_energy<R: Real>(
    q: &Array<Quat<R>>,
    v: &Array<Vec3<R>>,
    w: &Array<Vec3<R>>,
    inv_mass: &Array<R>,
    inertia: &Array<Mat33<R>>,
    energy: &Array<R>,
) {
    let t = tid();
    let im = inv_mass[t];
    let wb = quat_rotate_inv(q[t], w[t]);
    let lin = select(im > 0.0, 0.5 * dot(v[t], v[t]) / im, 0.0);
    energy.atomic_add(0, lin + 0.5 * dot(wb, inertia[t] * wb));
}

/// The rigid bodies of a model: mass properties, initial state and contact points.
#[derive(Clone, Debug)]
pub struct RigidBodies<R: Real> {
    /// Inverse mass (1/kg; 0 = static).
    pub inv_mass: Array<R>,
    /// Inertia about the centre of mass, body frame (kg m^2).
    pub inertia: Array<Mat33<R>>,
    /// Its inverse (0 = no rotation from torques).
    pub inv_inertia: Array<Mat33<R>>,
    /// Initial state.
    pub initial: BodyState<R>,
    /// The body of each contact point (absent if there are none).
    pub contact_body: Option<Array<u32>>,
    /// Contact points in body frame (m).
    pub contact_point: Option<Array<Vec3<R>>>,
}

impl<R: Real> RigidBodies<R> {
    /// Number of bodies.
    pub fn len(&self) -> usize {
        self.inv_mass.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.inv_mass.is_empty()
    }

    /// Records the contact of the body points with `ground` (if both exist), accumulating into
    /// `body_f` and `body_t`.
    pub fn eval_ground(
        &self,
        tape: &mut Tape,
        s: &BodyState<R>,
        ground: &Ground<R>,
        body_f: &Array<Vec3<R>>,
        body_t: &Array<Vec3<R>>,
    ) {
        if let (Some(cb), Some(cp)) = (&self.contact_body, &self.contact_point) {
            tape.launch(
                eval_body_ground,
                cb.len(),
                (
                    &s.x,
                    &s.q,
                    &s.v,
                    &s.w,
                    cb,
                    cp,
                    ground.normal,
                    ground.offset,
                    ground.ke,
                    ground.kd,
                    ground.mu,
                    ground.leak,
                    body_f,
                    body_t,
                ),
            );
        }
    }

    /// Records [`integrate_bodies`]: the next body state from forces `f` and torques `tau`,
    /// body `k` under `gravity[world[k]]`.
    #[allow(clippy::too_many_arguments)]
    pub fn integrate(
        &self,
        tape: &mut Tape,
        s: &BodyState<R>,
        f: &Array<Vec3<R>>,
        tau: &Array<Vec3<R>>,
        gravity: &Array<Vec3<R>>,
        world: &Array<u32>,
        dt: R,
    ) -> BodyState<R> {
        let n = self.len();
        let next = BodyState {
            x: Array::zeros(n).named("body_x"),
            q: Array::zeros(n).named("body_q"),
            v: Array::zeros(n).named("body_v"),
            w: Array::zeros(n).named("body_w"),
        };
        tape.launch(
            integrate_bodies,
            n,
            (
                &s.x,
                &s.q,
                &s.v,
                &s.w,
                f,
                tau,
                &self.inv_mass,
                &self.inertia,
                &self.inv_inertia,
                gravity,
                world,
                dt,
                &next.x,
                &next.q,
                &next.v,
                &next.w,
            ),
        );
        next
    }

    /// Records [`body_kinetic_energy`], adding into `energy[0]`.
    pub fn kinetic_energy(&self, tape: &mut Tape, s: &BodyState<R>, energy: &Array<R>) {
        tape.launch(
            body_kinetic_energy,
            self.len(),
            (&s.q, &s.v, &s.w, &self.inv_mass, &self.inertia, energy),
        );
    }
}

/// A rigid body as the builder records it (see
/// [`ModelBuilder::add_body`](crate::ModelBuilder::add_body) for the fields).
#[derive(Clone, Copy, Debug)]
pub(crate) struct BodyRecord<R: Real> {
    pub(crate) x: Vec3<R>,
    pub(crate) q: Quat<R>,
    pub(crate) v: Vec3<R>,
    pub(crate) w: Vec3<R>,
    pub(crate) mass: R,
    pub(crate) inertia: Mat33<R>,
}

/// The rigid bodies of a scene description (see
/// [`ModelBuilder::add_body`](crate::ModelBuilder::add_body)).
#[derive(Clone, Debug)]
pub(crate) struct BodyParts<R: Real> {
    bodies: Vec<BodyRecord<R>>,
    contacts: Vec<(u32, Vec3<R>)>,
}

impl<R: Real> Default for BodyParts<R> {
    fn default() -> Self {
        BodyParts {
            bodies: Vec::new(),
            contacts: Vec::new(),
        }
    }
}

fn lit<R: Real>(x: f64) -> R {
    R::lit(x)
}

impl<R: Real> BodyParts<R> {
    /// A body, checked (its orientation normalized).
    pub(crate) fn add(&mut self, problems: &mut Vec<Problem>, body: BodyRecord<R>) -> u32 {
        let BodyRecord {
            x,
            q,
            v,
            w,
            mass,
            inertia,
        } = body;
        let mut c = check(problems, "bodies", self.bodies.len());
        c.finite3("x", &x);
        c.finite3("v", &v);
        c.finite3("w", &w);
        if c.finite("q", &[q.i, q.j, q.k, q.w]) && q.norm().to_f64() == 0.0 {
            c.fail(Some("q"), "must be a nonzero quaternion".into());
        }
        let inertia_ok = c.finite("inertia", inertia.as_slice());
        if c.nonneg("mass", mass) && mass.to_f64() > 0.0 {
            if !(lit::<R>(1.0) / mass).to_f64().is_finite() {
                c.fail(
                    Some("mass"),
                    format!(
                        "the inverse mass 1/{:e} is not finite in {}; give a mass of at least \
                         {:.1e} kg, or 0 for a static body",
                        mass.to_f64(),
                        precision::<R>(),
                        1.0 / max_of::<R>()
                    ),
                );
            }
            let inv_ok = inertia
                .try_inverse()
                .is_some_and(|m| m.iter().all(|v| v.to_f64().is_finite()));
            if inertia_ok && !inv_ok {
                c.fail(
                    Some("inertia"),
                    "must be invertible (with a finite inverse) for a body with mass > 0".into(),
                );
            }
        }
        self.bodies.push(BodyRecord {
            x,
            q: q.normalize(),
            v,
            w,
            mass,
            inertia,
        });
        (self.bodies.len() - 1) as u32
    }

    /// A contact point of a body, checked.
    pub(crate) fn add_contact_point(&mut self, problems: &mut Vec<Problem>, body: u32, p: Vec3<R>) {
        let nb = self.bodies.len();
        let mut c = check(problems, "body_contact_points", self.contacts.len());
        if (body as usize) >= nb {
            c.fail(
                Some("body"),
                format!("body {body} out of range ({nb} bodies)"),
            );
        }
        c.finite3("p", &p);
        self.contacts.push((body, p));
    }

    /// Number of bodies.
    pub(crate) fn len(&self) -> usize {
        self.bodies.len()
    }

    /// Appends `other`'s bodies and contact points as a new world's.
    pub(crate) fn append(&mut self, other: &Self) {
        let offset = self.bodies.len() as u32;
        self.bodies.extend(other.bodies.iter().cloned());
        self.contacts
            .extend(other.contacts.iter().map(|&(b, p)| (b + offset, p)));
    }

    /// The bodies `range` (one share of the worlds) and their contact points, body indices
    /// shifted down by `range.start`.
    pub(crate) fn worlds_in(&self, range: &std::ops::Range<u32>) -> Self {
        BodyParts {
            bodies: self.bodies[range.start as usize..range.end as usize].to_vec(),
            contacts: self
                .contacts
                .iter()
                .filter(|c| range.contains(&c.0))
                .map(|&(b, p)| (b - range.start, p))
                .collect(),
        }
    }

    /// The model's bodies, if the scene has any.
    pub(crate) fn build(&self) -> Option<RigidBodies<R>> {
        (!self.bodies.is_empty()).then(|| {
            let b = &self.bodies;
            let inv_mass: Vec<R> = b
                .iter()
                .map(|b| {
                    if b.mass > lit(0.0) {
                        lit::<R>(1.0) / b.mass
                    } else {
                        lit(0.0)
                    }
                })
                .collect();
            let inv_inertia: Vec<Mat33<R>> = b
                .iter()
                .map(|b| {
                    if b.mass > lit(0.0) {
                        b.inertia.try_inverse().unwrap_or_else(Mat33::zeros)
                    } else {
                        Mat33::zeros()
                    }
                })
                .collect();
            let (cb, cp): (Vec<u32>, Vec<Vec3<R>>) = self.contacts.iter().copied().unzip();
            RigidBodies {
                inv_mass: Array::from_vec(inv_mass).named("body_inv_mass"),
                inertia: Array::from_vec(b.iter().map(|b| b.inertia).collect())
                    .named("body_inertia"),
                inv_inertia: Array::from_vec(inv_inertia).named("body_inv_inertia"),
                initial: BodyState {
                    x: Array::from_vec(b.iter().map(|b| b.x).collect()).named("body_x"),
                    q: Array::from_vec(b.iter().map(|b| b.q).collect()).named("body_q"),
                    v: Array::from_vec(b.iter().map(|b| b.v).collect()).named("body_v"),
                    w: Array::from_vec(b.iter().map(|b| b.w).collect()).named("body_w"),
                },
                contact_body: (!cb.is_empty())
                    .then(|| Array::from_vec(cb).named("body_contact_body")),
                contact_point: (!cp.is_empty())
                    .then(|| Array::from_vec(cp).named("body_contact_point")),
            }
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct BodySection {
    x: [f64; 3],
    #[serde(default = "identity_quat")]
    q: [f64; 4],
    #[serde(default = "zero3")]
    v: [f64; 3],
    #[serde(default = "zero3")]
    w: [f64; 3],
    mass: f64,
    inertia: [f64; 3],
    #[serde(default)]
    contact_points: Vec<[f64; 3]>,
}

/// Loads the `bodies` section (quaternions normalized, diagonal inertia).
pub(crate) fn load<R: Real>(
    d: &[BodySection],
    part: &mut BodyParts<R>,
    problems: &mut Vec<Problem>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, bd) in d.iter().enumerate() {
        let path = |f: &str| format!("bodies[{k}].{f}");
        c.finite(|| path("q"), &bd.q)?;
        c.no_underflow::<R>(|| path("mass"), bd.mass)?;
        let q = Quat::new(bd.q[3], bd.q[0], bd.q[1], bd.q[2]);
        if !q.norm().is_normal() {
            return Err(c.err(path("q"), "must be a nonzero quaternion [x, y, z, w]"));
        }
        for v in bd.inertia {
            if bd.mass > 0.0 {
                c.positive(|| path("inertia"), v)?;
            } else {
                c.nonneg(|| path("inertia"), v)?;
            }
        }
        let q = q / q.norm();
        let n0 = problems.len();
        let body = BodyRecord {
            x: v3(bd.x),
            q: Quat::new(R::lit(q.w), R::lit(q.i), R::lit(q.j), R::lit(q.k)),
            v: v3(bd.v),
            w: v3(bd.w),
            mass: R::lit(bd.mass),
            inertia: Mat33::from_diagonal(&v3(bd.inertia)),
        };
        let id = part.add(problems, body);
        c.builder(problems, n0, |f| sub(&format!("bodies[{k}]"), f, &[]))?;
        for (m, p) in bd.contact_points.iter().enumerate() {
            let n0 = problems.len();
            part.add_contact_point(problems, id, v3(*p));
            c.builder(problems, n0, |_| format!("bodies[{k}].contact_points[{m}]"))?;
        }
    }
    Ok(())
}
