//! Coupling between physics families: particles (cloth, soft bodies, loose particles of a
//! [`Model`]) against the contact shapes of articulated links ([`Articulations`]).
//!
//! The two families step with their own integrators; what joins them is one force law at the
//! start of each step, equal and opposite: [`LinkParticleContact::forces`] gives each particle
//! its contact force from every sphere, capsule and box of the links
//! ([`ArticulationBuilder::add_contact_shape`](crate::articulation::ArticulationBuilder::add_contact_shape)
//! and the robot files' geoms), and each link the opposite forces, as an external force at its
//! centre of mass and a torque ([`ArticulationControl::link_f`], `link_t`). The force is the
//! one particles get from static shapes ([`shape_contact_force`]: penalty, damping ramped in,
//! dFlex's smoothed Coulomb friction, the optional gradient leak) with the velocity of the
//! particle relative to the link's point where it is. The link's share acts on the particle's
//! centre, so momentum and angular momentum pass from one family to the other exactly.
//!
//! The coupling force is explicit (evaluated once, at the start of the step), whatever the
//! families' integrators: even with [`ImplicitEuler`](crate::integrators::ImplicitEuler) for
//! the particles, the contact with links limits the step as an explicit penalty does (about
//! `dt < 2 sqrt(m / ke)` for a particle of mass `m`).
//!
//! [`LinkParticleContact::step`] records both steps on one tape, so a loss on either family
//! differentiates with respect to the other's states and parameters (a robot arm pushing
//! cloth, cloth dropped on a robot).
//!
//! Which shapes particles touch follows MuJoCo's filters: the particles have
//! [`LinkParticleContact::filter`] (default `contype = conaffinity = 1`) and touch a shape
//! whose [`ContactFilter`] accepts it (a visual geom, `contype = conaffinity = 0`, touches
//! nothing). A contact's friction is the larger of the law's `mu` and the shape's own
//! ([`ContactShape::friction`](crate::articulation::ContactShape::friction), MJCF's geom
//! `friction`), as MuJoCo combines two geoms'.
//!
//! Only a particle and a link of the same world touch (the world of a particle is its
//! [`Model::particle_world`], of a link its [`Articulations::link_world`]), but the launch
//! covers every particle against every shape that touches particles, of all worlds: the cost
//! is particles x shapes per step, which grows with the square of the number of worlds. Both
//! families must have the same number of worlds and fall the same way (equal gravity where
//! both have one): particle scenes are often built with y up (`ModelBuilder`'s default
//! gravity is `-y`) and robots with z up, so a difference is refused rather than simulated.
//!
//! ```
//! use adflex_kernels::articulation::*;
//! use adflex_kernels::coupling::LinkParticleContact;
//! use adflex_kernels::prelude::*;
//! use adflex_runtime::{Tape, Vec3};
//!
//! // A ball on a slider (z up), and a particle falling onto it.
//! let mut b = ArticulationBuilder::new();
//! let ball = b.add_link("ball", None, Joint::prismatic(Vec3::z()),
//!     Inertial::sphere(1.0, 0.1, Vec3::zeros()));
//! b.add_contact_sphere(ball, Vec3::zeros(), 0.1);
//! b.gravity = Vec3::zeros();
//! let robot = b.finalize::<f64>().unwrap();
//!
//! let mut pb = ModelBuilder::<f64>::new();
//! pb.gravity = Vec3::zeros();
//! pb.particle_radius = 0.01;
//! pb.add_particle(Vec3::new(0.0, 0.0, 0.2), Vec3::new(0.0, 0.0, -1.0), 0.1);
//! let particles = pb.finalize();
//!
//! let coupling = LinkParticleContact::default();
//! let mut tape = Tape::new();
//! let (mut state, mut robot_state) = (particles.state(), robot.state());
//! for _ in 0..400 {
//!     (state, robot_state) = coupling
//!         .step(&mut tape, (&particles, &SemiImplicitEuler), &state, None,
//!               &robot, &robot_state, None, 1e-3)
//!         .unwrap();
//! }
//! // The particle bounced up and pushed the ball down; momentum is shared exactly.
//! let (vp, vb) = (state.v.get(0).z, robot_state.qd.get(0));
//! assert!(vp > 0.0 && vb < 0.0);
//! assert!((0.1 * vp + 1.0 * vb - 0.1 * -1.0).abs() < 1e-12);
//! ```

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::articulation::kernels::articulation_link_twist;
use crate::articulation::{ArticulationControl, ArticulationState, Articulations, ContactFilter};
use crate::contact::shapes::shape_contact_force;
use crate::{Control, Integrator, Model, State};

/// The contact law between particles and links' shapes (the defaults of
/// [`ParticleContact`](crate::contact::particle::ParticleContact)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinkParticleContact<R: Real> {
    /// Contact stiffness (N/m; default 1000).
    pub ke: R,
    /// Contact damping (N s/m; default 1), only in contact and while approaching, ramped in
    /// over `damping_depth`.
    pub kd: R,
    /// Penetration depth (m; default 1e-4) over which the damping rises from 0 to `kd`.
    pub damping_depth: R,
    /// Friction coefficient (default 0.5); a contact's is the larger of this and its shape's
    /// own, if the shape has one.
    pub mu: R,
    /// Gradient leak out of contact (default 0: exact gradients; see
    /// [`contact_depth`](crate::contact::law::contact_depth)).
    pub leak: R,
    /// The particles' contact filter (default `contype = conaffinity = 1`, MuJoCo's default
    /// geom's): a shape touches them if its filter and this one accept each other.
    pub filter: ContactFilter,
}

impl<R: Real> Default for LinkParticleContact<R> {
    fn default() -> Self {
        LinkParticleContact {
            ke: R::lit(1000.0),
            kd: R::lit(1.0),
            damping_depth: R::lit(1e-4),
            mu: R::lit(0.5),
            leak: R::lit(0.0),
            filter: ContactFilter::default(),
        }
    }
}

/// What [`LinkParticleContact::forces`] gives: the particles' contact forces (N), and the
/// links' reactions as a force at each link's centre of mass (N) and a torque (N m), all in the
/// world frame.
#[derive(Clone, Debug)]
pub struct CouplingForces<R: Real> {
    /// Per particle.
    pub particle_f: Array<Vec3<R>>,
    /// Per link, at its centre of mass.
    pub link_f: Array<Vec3<R>>,
    /// Per link.
    pub link_t: Array<Vec3<R>>,
}

/// Contact of particle `tid / num_shapes` with link shape `tid % num_shapes` (the same world
/// only): the particle gets `fc = shape_contact_force(x, v - v_link(x), ..)` with the shape at
/// its link's pose, the link `-fc` at the particle's centre, i.e. `-fc` at its centre of mass
/// `c` and the torque `(x - c) x -fc`.
#[diff_kernel]
pub fn link_particle_contact<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    radius: &Array<R>,
    particle_world: &Array<u32>,
    shape_link: &Array<u32>,
    shape_kind: &Array<u32>,
    shape_pos: &Array<Vec3<R>>,
    shape_rot: &Array<Quat<R>>,
    shape_size: &Array<Vec3<R>>,
    shape_mu: &Array<R>,
    num_shapes: usize,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    link_com: &Array<Vec3<R>>,
    link_world: &Array<u32>,
    law: Vec3<R>,
    leak: R,
    particle_f: &Array<Vec3<R>>,
    link_f: &Array<Vec3<R>>,
    link_t: &Array<Vec3<R>>,
) {
    let t = tid();
    let p = t / num_shapes;
    let s = t % num_shapes;
    let l = shape_link[s] as usize;
    if particle_world[p] != link_world[l] {
        return;
    }
    let r = link_r[l];
    let pos = link_p[l] + quat_rotate(r, shape_pos[s]);
    let q = quat_mul(r, shape_rot[s]);
    let xp = x[p];
    let rel = v[p] - (link_v[l] + cross(link_w[l], xp));
    // law = (ke, kd, damping depth).
    let fc = shape_contact_force(
        xp,
        rel,
        shape_kind[s],
        pos,
        q,
        shape_size[s],
        radius[p],
        law.x,
        law.y,
        law.z,
        shape_mu[s],
        leak,
    );
    particle_f.atomic_add(p, fc);
    let c = link_p[l] + quat_rotate(r, link_com[l]);
    link_f.atomic_sub(l, fc);
    link_t.atomic_sub(l, cross(xp - c, fc));
}

/// The shapes of the links that touch particles (see [`LinkParticleContact::forces`]).
struct Touching<R: Real> {
    link: Array<u32>,
    kind: Array<u32>,
    pos: Array<Vec3<R>>,
    rot: Array<Quat<R>>,
    size: Array<Vec3<R>>,
    mu: Array<R>,
}

impl<R: Real> Touching<R> {
    fn len(&self) -> usize {
        self.link.len()
    }
    fn is_empty(&self) -> bool {
        self.link.is_empty()
    }
}

/// `out[tid] = a[tid] + b[tid]`.
#[diff_kernel]
pub fn add_vec3<R: Real>(a: &Array<Vec3<R>>, b: &Array<Vec3<R>>, out: &Array<Vec3<R>>) {
    let t = tid();
    out[t] = a[t] + b[t];
}

fn invalid(what: &str, message: String) -> Error {
    Error::InvalidInput {
        what: what.into(),
        message,
    }
}

/// `a + b`, recorded; `a` alone when `b` is `None`. `what` names `b` in the error for a
/// length that is not `a`'s.
fn plus<R: Real>(
    tape: &mut Tape,
    a: &Array<Vec3<R>>,
    b: Option<&Array<Vec3<R>>>,
    what: &str,
) -> Result<Array<Vec3<R>>, Error> {
    match b {
        None => Ok(a.clone()),
        Some(b) if b.len() != a.len() => Err(invalid(
            what,
            format!("has {} elements, the model needs {}", b.len(), a.len()),
        )),
        Some(b) => {
            let out = Array::zeros(a.len());
            tape.launch(add_vec3, a.len(), (a, b, &out));
            Ok(out)
        }
    }
}

impl<R: Real> LinkParticleContact<R> {
    /// The links' shapes that touch the particles, with each one's friction. Errors: an
    /// ellipsoid among them (kind 4: particles do not touch ellipsoids).
    fn touching(&self, arts: &Articulations<R>) -> Result<Touching<R>, Error> {
        let s = &arts.shapes;
        let keep: Vec<usize> = (0..s.len())
            .filter(|&k| s.filter[k].touches(&self.filter))
            .collect();
        let (links, kinds) = (s.link.to_vec(), s.kind.to_vec());
        if let Some(&k) = keep.iter().find(|&&k| kinds[k] == 4) {
            return Err(invalid(
                &format!(
                    "LinkParticleContact shape {k} (an ellipsoid on link \"{}\")",
                    arts.links[links[k] as usize].name
                ),
                "particles do not touch ellipsoids; give it a filter that does not touch \
                 `LinkParticleContact::filter` (ContactFilter::NONE), or use a sphere, capsule, \
                 box or cylinder"
                    .into(),
            ));
        }
        let pick = |a: &[u32]| Array::from_vec(keep.iter().map(|&k| a[k]).collect());
        let (link, kind) = (pick(&links), pick(&kinds));
        let (pos, rot, size) = (s.pos.to_vec(), s.rot.to_vec(), s.size.to_vec());
        let mu = self.mu.to_f64();
        Ok(Touching {
            link,
            kind,
            pos: Array::from_vec(keep.iter().map(|&k| pos[k]).collect()),
            rot: Array::from_vec(keep.iter().map(|&k| rot[k]).collect()),
            size: Array::from_vec(keep.iter().map(|&k| size[k]).collect()),
            mu: Array::from_vec(
                keep.iter()
                    .map(|&k| R::lit(s.friction[k].map_or(mu, |f| f.max(mu))))
                    .collect(),
            ),
        })
    }

    /// The checks [`LinkParticleContact::forces`] makes: the law's parameters, the worlds and
    /// the gravities.
    fn check(&self, model: &Model<R>, arts: &Articulations<R>) -> Result<(), Error> {
        let ok = |x: R| x.to_f64().is_finite() && x.to_f64() >= 0.0;
        for (name, x) in [
            ("ke", self.ke),
            ("kd", self.kd),
            ("damping_depth", self.damping_depth),
            ("mu", self.mu),
            ("leak", self.leak),
        ] {
            if !ok(x) {
                return Err(invalid(
                    &format!("LinkParticleContact::{name}"),
                    format!("{} must be finite and non-negative", x.to_f64()),
                ));
            }
        }
        let (wp, wa) = (model.worlds.len(), arts.n_worlds());
        if wp != wa {
            return Err(invalid(
                "LinkParticleContact worlds",
                format!(
                    "the particles' model has {wp} worlds and the articulations {wa}; couple \
                     models built with the same worlds"
                ),
            ));
        }
        for w in 0..wp {
            let (gp, ga) = (model.gravity.get(w), arts.gravity.get(w));
            let zero = |g: Vec3<R>| g.iter().all(|c| c.to_f64() == 0.0);
            if !zero(gp) && !zero(ga) && gp != ga {
                let f = |g: Vec3<R>| [g.x.to_f64(), g.y.to_f64(), g.z.to_f64()];
                return Err(invalid(
                    "LinkParticleContact gravity",
                    format!(
                        "in world {w} the particles fall along {:?} and the links along {:?}: \
                         set `ModelBuilder::gravity` and `ArticulationBuilder::gravity` to the \
                         same vector (robot files are z up, particle scenes often y up)",
                        f(gp),
                        f(ga)
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The contact forces between the particles of `model` at `state` and the links of `arts`
    /// at `astate`, recorded on `tape` (see the [module docs](self)).
    ///
    /// Errors: [`Error::InvalidInput`] for a negative or non-finite parameter of the law,
    /// models with different numbers of worlds, different gravities, or an ellipsoid the
    /// particles would touch.
    pub fn forces(
        &self,
        tape: &mut Tape,
        model: &Model<R>,
        state: &State<R>,
        arts: &Articulations<R>,
        astate: &ArticulationState<R>,
    ) -> Result<CouplingForces<R>, Error> {
        self.check(model, arts)?;
        let (np, nl) = (model.particle_count, arts.n_links());
        for (a, n, what) in [(&astate.q, arts.n_q, "q"), (&astate.qd, arts.n_dof, "qd")] {
            if a.len() != n {
                return Err(invalid(
                    "LinkParticleContact articulation state",
                    format!("`{what}` has {} elements, the model needs {n}", a.len()),
                ));
            }
        }
        if state.x.len() != np || state.v.len() != np {
            return Err(invalid(
                "LinkParticleContact state",
                format!(
                    "the state has {} positions and {} velocities, the model {np} particles",
                    state.x.len(),
                    state.v.len()
                ),
            ));
        }
        let out = CouplingForces {
            particle_f: Array::zeros(np),
            link_f: Array::zeros(nl),
            link_t: Array::zeros(nl),
        };
        let shapes = self.touching(arts)?;
        if np == 0 || shapes.is_empty() {
            return Ok(out);
        }
        let k = arts.kinematics(tape, &astate.q);
        let (w, v) = (Array::zeros(nl), Array::zeros(nl));
        tape.launch(
            articulation_link_twist,
            nl,
            (
                &arts.chain_start,
                &arts.chain,
                &arts.qd_start,
                &k.s_w,
                &k.s_v,
                &astate.qd,
                &w,
                &v,
            ),
        );
        let radius = match &model.particle_radii {
            Some(r) => r.clone(),
            None => Array::from_vec(vec![model.particle_radius; np]),
        };
        let law = Vec3::new(self.ke, self.kd, self.damping_depth);
        tape.launch(
            link_particle_contact,
            np * shapes.len(),
            (
                &state.x,
                &state.v,
                &radius,
                &model.particle_world,
                &shapes.link,
                &shapes.kind,
                &shapes.pos,
                &shapes.rot,
                &shapes.size,
                &shapes.mu,
                shapes.len(),
                &k.link_p,
                &k.link_r,
                &w,
                &v,
                &arts.com,
                &arts.link_world,
                law,
                self.leak,
                &out.particle_f,
                &out.link_f,
                &out.link_t,
            ),
        );
        Ok(out)
    }

    /// One step of both families: the contact [`forces`](Self::forces) at the start of the
    /// step join the particles' external forces ([`Control::particle_f`]) and the links'
    /// ([`ArticulationControl::link_f`], `link_t`), added to those the controls already have;
    /// then the particles step by `integrator` and the articulations by their own
    /// ([`Articulations::step`]). Returns both new states.
    ///
    /// Errors: those of [`forces`](Self::forces), of the particles' integrator and of
    /// [`Articulations::step`].
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &self,
        tape: &mut Tape,
        (model, integrator): (&Model<R>, &dyn Integrator<R>),
        state: &State<R>,
        control: Option<&Control<R>>,
        arts: &Articulations<R>,
        astate: &ArticulationState<R>,
        acontrol: Option<&ArticulationControl<R>>,
        dt: R,
    ) -> Result<(State<R>, ArticulationState<R>), Error> {
        let f = self.forces(tape, model, state, arts, astate)?;
        let mut pc = control.cloned().unwrap_or_default();
        pc.particle_f = Some(plus(
            tape,
            &f.particle_f,
            pc.particle_f.as_ref(),
            "control.particle_f",
        )?);
        let mut ac = match acontrol {
            Some(c) => c.clone(),
            None => arts.control(),
        };
        ac.link_f = Some(plus(tape, &f.link_f, ac.link_f.as_ref(), "control.link_f")?);
        ac.link_t = Some(plus(tape, &f.link_t, ac.link_t.as_ref(), "control.link_t")?);
        let next = integrator.step(model, tape, state, Some(&pc), dt)?;
        let anext = arts.step(tape, astate, Some(&ac), dt)?;
        Ok((next, anext))
    }
}
