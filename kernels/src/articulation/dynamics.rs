//! The algorithms on a tape: kinematics, inverse dynamics (RNEA), the mass matrix (CRBA),
//! forward dynamics (a Cholesky solve recorded as one custom step with its adjoint and
//! tangent) and the step by MuJoCo's integrators (the derivatives of the forward dynamics in
//! closed form are in `derivatives.rs`).

use std::sync::Arc;

use adflex_runtime::prelude::*;
use adflex_runtime::{AnyArray, Element};

use super::kernels::*;
use super::model::{ArticulationIntegrator, Articulations, JointType};
use crate::precompiled::precompiled;
use crate::solver::parts::Parts;

precompiled! {
    /// [`Articulations::step`] by code compiled in this crate for `f32` and `f64`: examples,
    /// tests and user crates link to it instead of compiling the step's kernels again.
    fn articulation_step(
        model: &Articulations<R>,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        control: Option<&ArticulationControl<R>>,
        dt: R,
    ) -> Result<ArticulationState<R>, Error> {
        model.step_generic(tape, state, control, dt)
    }
}

/// Coordinates and velocities of every articulation of a model.
#[derive(Clone, Debug)]
pub struct ArticulationState<R: Real> {
    /// Coordinates (`Articulations::n_q`; see [`JointType`] for each joint's).
    pub q: Array<R>,
    /// Velocities (`Articulations::n_dof`).
    pub qd: Array<R>,
}

impl<R: Real> adflex_runtime::checkpoint::Checkpoint for ArticulationState<R> {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        vec![&self.q, &self.qd]
    }
    fn snapshot(&self) -> Self {
        ArticulationState {
            q: self.q.deep_clone(),
            qd: self.qd.deep_clone(),
        }
    }
}

/// Actuation of the joints, per velocity: a force or torque `tau`, and the targets of the
/// joints' PD actuators (`kp (target_q - q) + kv (target_qd - qd)` on revolute and prismatic
/// joints with gains).
#[derive(Clone, Debug)]
pub struct ArticulationControl<R: Real> {
    /// Generalized forces (N or N m; a free joint's are the wrench in its link frame, force
    /// first).
    pub tau: Array<R>,
    /// PD position targets (rad or m; per velocity, used on scalar joints).
    pub target_q: Array<R>,
    /// PD velocity targets.
    pub target_qd: Array<R>,
    /// Muscle activations in `[0, 1]`, one per muscle (see
    /// [`Muscle`](super::Muscle)).
    pub activation: Array<R>,
    /// Actuator controls, one per actuator (see [`actuator`](super::actuator); MuJoCo's
    /// `ctrl`).
    pub ctrl: Array<R>,
    /// External force on each link, applied at its centre of mass (N, world frame; MuJoCo's
    /// `xfrc_applied[0..3]`), e.g. the reaction of particles on the links
    /// ([`crate::coupling`]). `None`: no force.
    pub link_f: Option<Array<Vec3<R>>>,
    /// External torque on each link (N m, world frame; MuJoCo's `xfrc_applied[3..6]`).
    /// `None`: no torque.
    pub link_t: Option<Array<Vec3<R>>>,
}

/// What [`Articulations::pass`] computes with.
struct PassInput<'a, R: Real> {
    q: &'a Array<R>,
    qd: &'a Array<R>,
    qdd: Option<&'a Array<R>>,
    tau: &'a Array<R>,
    control: Option<&'a ArticulationControl<R>>,
    contact: bool,
    /// A step's time step (0 otherwise, and in RK4's stages): violated limits are integrated
    /// implicitly, and so are the damping terms of the model's integrator.
    dt: R,
}

impl<'a, R: Real> PassInput<'a, R> {
    fn new(q: &'a Array<R>, qd: &'a Array<R>, tau: &'a Array<R>) -> Self {
        PassInput {
            q,
            qd,
            qdd: None,
            tau,
            control: None,
            contact: false,
            dt: R::lit(0.0),
        }
    }
}

/// Cholesky factors of the mass-matrix blocks, and each block's `(first velocity, size,
/// offset)`.
pub(super) type Factors = (Vec<Vec<f64>>, Vec<(usize, usize, usize)>);

/// What it gives: inverse-dynamics forces, the mass matrix, the right-hand side.
struct Pass<R: Real> {
    tau_id: Array<R>,
    m: Array<R>,
    rhs: Array<R>,
}

/// World poses of the links and the joints' motion vectors (world frame, at the origin).
#[derive(Clone, Debug)]
pub struct Kinematics<R: Real> {
    /// Link frame origins (m).
    pub link_p: Array<Vec3<R>>,
    /// Link frame rotations.
    pub link_r: Array<Quat<R>>,
    /// Angular part of each velocity's motion vector.
    pub s_w: Array<Vec3<R>>,
    /// Linear part (velocity of the point at the world origin).
    pub s_v: Array<Vec3<R>>,
}

impl<R: Real> Articulations<R> {
    /// The initial state: [`Articulations::q0`], at rest.
    pub fn state(&self) -> ArticulationState<R> {
        ArticulationState {
            q: Array::from_vec(self.q0.clone()),
            qd: Array::zeros(self.n_dof),
        }
    }

    /// A control with no actuation (PD targets 0).
    pub fn control(&self) -> ArticulationControl<R> {
        ArticulationControl {
            tau: Array::zeros(self.n_dof),
            target_q: Array::zeros(self.n_dof),
            target_qd: Array::zeros(self.n_dof),
            activation: Array::zeros(self.muscle_f_max.len()),
            ctrl: Array::zeros(self.act_gear.len()),
            link_f: None,
            link_t: None,
        }
    }

    fn check_len<T: Element>(&self, a: &Array<T>, n: usize, what: &str) {
        assert!(
            a.len() == n,
            "articulations: `{what}` has {} elements, the model needs {n}",
            a.len()
        );
    }

    /// Forward kinematics at `q`: link poses and motion vectors.
    pub fn kinematics(&self, tape: &mut Tape, q: &Array<R>) -> Kinematics<R> {
        self.kinematics_inertias(tape, q).0
    }

    /// Kinematics and the links' world spatial inertias (`h`, `J`; see the kernels' docs).
    fn kinematics_inertias(
        &self,
        tape: &mut Tape,
        q: &Array<R>,
    ) -> (Kinematics<R>, Array<Vec3<R>>, Array<Mat33<R>>) {
        self.check_len(q, self.n_q, "q");
        let (n, nd) = (self.n_links(), self.n_dof);
        let k = Kinematics {
            link_p: Array::zeros(n),
            link_r: Array::zeros(n),
            s_w: Array::zeros(nd),
            s_v: Array::zeros(nd),
        };
        let (h, j) = (Array::zeros(n), Array::zeros(n));
        tape.launch(
            articulation_kinematics,
            n,
            (
                &self.chain_start,
                &self.chain,
                &self.joint_type,
                &self.q_start,
                &self.qd_start,
                &self.joint_pos,
                &self.joint_rot,
                &self.joint_axis,
                &self.mass,
                &self.com,
                &self.inertia,
                q,
                &k.link_p,
                &k.link_r,
                &k.s_w,
                &k.s_v,
                &h,
                &j,
            ),
        );
        (k, h, j)
    }

    /// The three passes of the dynamics at `(q, qd, qdd)` (`qdd = 0` when `None`): kinematics,
    /// link dynamics (and, with `contact`, the ground's wrenches), joint space. The
    /// right-hand side is `tau - tau_id`, plus the passive and PD terms with a control.
    fn pass(&self, tape: &mut Tape, input: PassInput<'_, R>) -> Pass<R> {
        let PassInput {
            q,
            qd,
            qdd,
            tau,
            control,
            contact,
            dt,
        } = input;
        self.check_len(qd, self.n_dof, "qd");
        self.check_len(tau, self.n_dof, "tau");
        self.check_len(&self.gravity, self.n_worlds(), "gravity (one per world)");
        let (n, nd) = (self.n_links(), self.n_dof);
        let (k, h, j) = self.kinematics_inertias(tape, q);
        let zeros = || Array::<R>::zeros(nd);
        let qdd = match qdd {
            Some(a) => {
                self.check_len(a, nd, "qdd");
                a.clone()
            }
            None => zeros(),
        };
        let [w, v, ln, lf, ch] = [(); 5].map(|_| Array::<Vec3<R>>::zeros(n));
        let (cm, cj) = (Array::zeros(n), Array::zeros(n));
        tape.launch(
            articulation_link_dynamics,
            n,
            (
                &self.chain_start,
                &self.chain,
                &self.subtree_start,
                &self.subtree,
                &self.qd_start,
                &k.s_w,
                &k.s_v,
                &self.mass,
                &h,
                &j,
                qd,
                &qdd,
                &self.gravity,
                &self.link_world,
                &w,
                &v,
                &ln,
                &lf,
                &cm,
                &ch,
                &cj,
            ),
        );
        let (en, ef) = (Array::zeros(n), Array::zeros(n));
        // An implicit step's friction against the ground and links fixed to the world: its
        // dampers, per link (`GroundContact::implicit_friction`); empty arrays, never read,
        // otherwise.
        let damper_dt = match (contact, &self.ground) {
            (true, Some(g))
                if g.implicit_friction
                    && dt.to_f64() > 0.0
                    && !(self.contact_link.is_empty()
                        && self.support_link.is_empty()
                        && self.link_fixed.is_empty()) =>
            {
                dt
            }
            _ => R::lit(0.0),
        };
        let damped = damper_dt.to_f64() > 0.0;
        // (The pairs read `link_fixed` only when it is not empty.)
        let pair_damper_dt = match self.link_fixed.is_empty() {
            true => R::lit(0.0),
            false => damper_dt,
        };
        let damp = [(); 3].map(|_| Array::<Mat33<R>>::zeros(if damped { n } else { 0 }));
        if let (true, Some(g), false) = (contact, &self.ground, self.contact_link.is_empty()) {
            tape.launch(
                super::contact::articulation_ground_contact,
                self.contact_link.len(),
                (
                    &self.contact_link,
                    &self.contact_pos,
                    &self.contact_radius,
                    &self.contact_mu,
                    &k.link_p,
                    &k.link_r,
                    &w,
                    &v,
                    g.normal,
                    g.offset,
                    g.ke,
                    g.kd,
                    g.leak,
                    g.damping_depth,
                    g.onset,
                    g.stiction_tolerance,
                    damper_dt,
                    &en,
                    &ef,
                    &damp[0],
                    &damp[1],
                    &damp[2],
                ),
            );
        }
        if let (true, Some(g), false) = (contact, &self.ground, self.support_link.is_empty()) {
            tape.launch(
                super::contact::articulation_support_contact,
                self.support_link.len(),
                (
                    &self.support_link,
                    &self.support_variant,
                    &self.support_pos,
                    &self.support_rot,
                    &self.support_size,
                    &self.support_mu,
                    &k.link_p,
                    &k.link_r,
                    &w,
                    &v,
                    g.normal,
                    g.offset,
                    g.ke,
                    g.kd,
                    g.leak,
                    g.damping_depth,
                    g.onset,
                    g.stiction_tolerance,
                    damper_dt,
                    &en,
                    &ef,
                    &damp[0],
                    &damp[1],
                    &damp[2],
                ),
            );
        }
        if let (true, Some(g), false) = (contact, &self.ground, self.capsule_pairs.is_empty()) {
            tape.launch(
                super::contact::articulation_capsule_contact,
                self.capsule_pairs.len(),
                (
                    &self.capsule_pairs,
                    &self.capsule_pair_mu,
                    &self.seg_link,
                    &self.seg_a,
                    &self.seg_b,
                    &self.seg_radius,
                    &k.link_p,
                    &k.link_r,
                    &w,
                    &v,
                    g.ke,
                    g.kd,
                    g.leak,
                    g.damping_depth,
                    g.onset,
                    g.stiction_tolerance,
                    &self.link_fixed,
                    pair_damper_dt,
                    &en,
                    &ef,
                    &damp[0],
                    &damp[1],
                    &damp[2],
                ),
            );
        }
        if let (true, Some(g), false) = (contact, &self.ground, self.box_pairs.is_empty()) {
            let args = (
                &self.box_pairs,
                &self.box_pair_mu,
                &self.seg_link,
                &self.seg_a,
                &self.seg_b,
                &self.seg_radius,
                &self.box_link,
                &self.box_pos,
                &self.box_rot,
                &self.box_half,
                &k.link_p,
                &k.link_r,
                &w,
                &v,
                g.ke,
                g.kd,
                g.leak,
                g.damping_depth,
                g.onset,
                g.stiction_tolerance,
                &self.link_fixed,
                pair_damper_dt,
                &en,
                &ef,
                &damp[0],
                &damp[1],
                &damp[2],
            );
            let n = self.box_pairs.len();
            tape.launch(super::contact::articulation_box_contact, n, args);
            // (A box's edges against another box are pairs too: their threads return at once.)
            tape.launch(super::contact::articulation_capsule_box_points, 8 * n, args);
        }
        if let (true, Some(g), false) = (contact, &self.ground, self.cylinder_pairs.is_empty()) {
            tape.launch(
                super::contact::articulation_cylinder_contact,
                self.cylinder_pairs.len(),
                (
                    &self.cylinder_pairs,
                    &self.cylinder_pair_mu,
                    &self.seg_link,
                    &self.seg_a,
                    &self.seg_b,
                    &self.seg_radius,
                    &self.cylinder_link,
                    &self.cylinder_pos,
                    &self.cylinder_rot,
                    &self.cylinder_size,
                    &k.link_p,
                    &k.link_r,
                    &w,
                    &v,
                    g.ke,
                    g.kd,
                    g.leak,
                    g.damping_depth,
                    g.onset,
                    g.stiction_tolerance,
                    &self.link_fixed,
                    pair_damper_dt,
                    &en,
                    &ef,
                    &damp[0],
                    &damp[1],
                    &damp[2],
                ),
            );
        }
        if let (Some(c), false) = (control, self.muscle_f_max.is_empty()) {
            self.check_len(&c.activation, self.muscle_f_max.len(), "control.activation");
            tape.launch(
                super::muscle::articulation_muscles,
                self.muscle_f_max.len(),
                (
                    &self.muscle_origin_link,
                    &self.muscle_origin_pos,
                    &self.muscle_insertion_link,
                    &self.muscle_insertion_pos,
                    &self.muscle_f_max,
                    &self.muscle_l_opt,
                    &self.muscle_tendon_slack,
                    &self.muscle_v_max,
                    &c.activation,
                    &k.link_p,
                    &k.link_r,
                    &w,
                    &v,
                    &en,
                    &ef,
                ),
            );
        }
        if let Some(c) = control {
            self.applied_wrenches(tape, c, &k, (&en, &ef));
        }
        if let (Some(_), false) = (control, self.gravcomp_link.is_empty()) {
            tape.launch(
                super::kernels::articulation_gravcomp,
                self.gravcomp_link.len(),
                (
                    &self.gravcomp_link,
                    &self.gravcomp,
                    &self.link_world,
                    &self.gravity,
                    &self.mass,
                    &k.link_p,
                    &k.link_r,
                    &self.com,
                    &en,
                    &ef,
                ),
            );
        }
        if let (Some(_), true, false) = (control, self.fluid_on, self.fluid_link.is_empty()) {
            tape.launch(
                super::fluid::articulation_fluid,
                self.fluid_link.len(),
                (
                    &self.fluid_link,
                    &self.fluid_com,
                    &self.fluid_rot,
                    &self.fluid_box,
                    &k.link_p,
                    &k.link_r,
                    &w,
                    &v,
                    &self.fluid_density,
                    &self.fluid_viscosity,
                    &self.wind,
                    &en,
                    &ef,
                ),
            );
        }
        let act_tau = zeros();
        let act_damping = Array::<R>::zeros(self.act_gear.len());
        if let (Some(c), false) = (control, self.act_gear.is_empty()) {
            self.check_len(&c.ctrl, self.act_gear.len(), "control.ctrl");
            tape.launch(
                super::actuator::articulation_actuators,
                self.act_gear.len(),
                (
                    &self.act_start,
                    &self.act_dof,
                    &self.act_coord,
                    &self.act_coef,
                    &self.act_gear,
                    &self.act_gain,
                    &self.act_bias,
                    &self.act_limited,
                    &self.act_ctrl_lo,
                    &self.act_ctrl_hi,
                    &self.act_force_lo,
                    &self.act_force_hi,
                    &c.ctrl,
                    q,
                    qd,
                    &act_tau,
                    &act_damping,
                ),
            );
        }
        if let (Some(_), false) = (control, self.tendon_stiffness.is_empty()) {
            tape.launch(
                super::actuator::articulation_tendon_springs,
                self.tendon_stiffness.len(),
                (
                    &self.tendon_start,
                    &self.tendon_dof,
                    &self.tendon_coord,
                    &self.tendon_coef,
                    &self.tendon_stiffness,
                    &self.tendon_damping,
                    &self.tendon_rest_lo,
                    &self.tendon_rest_hi,
                    q,
                    qd,
                    &act_tau,
                ),
            );
        }
        let (tz, qz) = (zeros(), zeros());
        let (target_q, target_qd, passive) = match control {
            Some(c) => (&c.target_q, &c.target_qd, 1u32),
            None => (&tz, &qz, 0u32),
        };
        let (tau_id, m, rhs) = (zeros(), Array::zeros(self.m_len), zeros());
        tape.launch(
            articulation_joint_space,
            nd,
            (
                &self.dof_link,
                &self.dof_art_start,
                &self.dof_m_row,
                &self.chain_start,
                &self.chain,
                &self.subtree_start,
                &self.subtree,
                &self.qd_start,
                &k.s_w,
                &k.s_v,
                &ln,
                &lf,
                &en,
                &ef,
                &cm,
                &ch,
                &cj,
                &self.armature,
                passive,
                &self.dof_q,
                &self.dof_scalar,
                q,
                qd,
                tau,
                &act_tau,
                target_q,
                target_qd,
                &self.kp,
                &self.kv,
                &self.damping,
                &self.stiffness,
                &self.spring_ref,
                &self.lower,
                &self.upper,
                self.limit_ke,
                self.limit_kd,
                &self.limit_k,
                dt,
                match (self.integrator, self.implicit_damping) {
                    (ArticulationIntegrator::ImplicitFast, _) | (_, true) => dt,
                    _ => R::lit(0.0),
                },
                match self.integrator {
                    ArticulationIntegrator::ImplicitFast => dt,
                    _ => R::lit(0.0),
                },
                &tau_id,
                &m,
                &rhs,
            ),
        );
        if damped {
            let comp = [(); 3].map(|_| Array::<Mat33<R>>::zeros(n));
            tape.launch(
                super::kernels::articulation_composite_damping,
                n,
                (
                    &self.subtree_start,
                    &self.subtree,
                    &damp[0],
                    &damp[1],
                    &damp[2],
                    &comp[0],
                    &comp[1],
                    &comp[2],
                ),
            );
            tape.launch(
                super::kernels::articulation_damping_matrix,
                nd,
                (
                    &self.dof_link,
                    &self.dof_art_start,
                    &self.dof_m_row,
                    &self.chain_start,
                    &self.chain,
                    &self.subtree_start,
                    &self.subtree,
                    &self.qd_start,
                    &k.s_w,
                    &k.s_v,
                    &comp[0],
                    &comp[1],
                    &comp[2],
                    &m,
                ),
            );
        }
        // MuJoCo's implicitfast: the tendons' and actuators' damping join M too.
        if self.integrator == ArticulationIntegrator::ImplicitFast && dt.to_f64() > 0.0 {
            for (start, dof, coef, damping) in [
                (&self.act_start, &self.act_dof, &self.act_coef, &act_damping),
                (
                    &self.tendon_start,
                    &self.tendon_dof,
                    &self.tendon_coef,
                    &self.tendon_damping,
                ),
            ] {
                if !damping.is_empty() && control.is_some() {
                    tape.launch(
                        super::actuator::articulation_implicit_damping,
                        damping.len(),
                        (
                            start,
                            dof,
                            coef,
                            damping,
                            &self.dof_art_start,
                            &self.dof_m_row,
                            dt,
                            &m,
                        ),
                    );
                }
            }
        }
        Pass { tau_id, m, rhs }
    }

    /// The joint-space mass matrix `M(q)` (armature included): one row-major block of
    /// `n x n` per articulation, at [`ArticulationInfo::m_offset`](super::ArticulationInfo)
    /// (read one with [`Articulations::block`]).
    pub fn mass_matrix(&self, tape: &mut Tape, q: &Array<R>) -> Array<R> {
        let z = Array::zeros(self.n_dof);
        self.pass(tape, PassInput::new(q, &z, &z)).m
    }

    /// The bias forces `c(q, qd)` (Coriolis, centrifugal and gravity; `M qdd + c = tau`).
    pub fn bias_forces(&self, tape: &mut Tape, q: &Array<R>, qd: &Array<R>) -> Array<R> {
        let z = Array::zeros(self.n_dof);
        self.pass(tape, PassInput::new(q, qd, &z)).tau_id
    }

    /// Inverse dynamics (RNEA): `tau = M(q) qdd + c(q, qd)`, the armature's `armature qdd`
    /// included (so that it undoes [`Articulations::forward_dynamics`]), as Pinocchio's `rnea`.
    pub fn inverse_dynamics(
        &self,
        tape: &mut Tape,
        q: &Array<R>,
        qd: &Array<R>,
        qdd: &Array<R>,
    ) -> Array<R> {
        let z = Array::zeros(self.n_dof);
        let mut input = PassInput::new(q, qd, &z);
        input.qdd = Some(qdd);
        let tau_id = self.pass(tape, input).tau_id;
        let tau = Array::zeros(self.n_dof);
        tape.launch(
            articulation_armature_force,
            self.n_dof,
            (&self.armature, qdd, &tau_id, &tau),
        );
        tau
    }

    /// Forward dynamics: `qdd = M(q)^-1 (tau - c(q, qd))` (no damping, limits, PD or contact;
    /// see [`Articulations::step`] for those). The solve is a Cholesky factorization per
    /// articulation, recorded as one step whose adjoint and tangent reuse the factors.
    ///
    /// Errors if a mass matrix is not positive definite (naming the articulation).
    pub fn forward_dynamics(
        &self,
        tape: &mut Tape,
        q: &Array<R>,
        qd: &Array<R>,
        tau: &Array<R>,
    ) -> Result<Array<R>, Error> {
        let p = self.pass(tape, PassInput::new(q, qd, tau));
        self.solve(tape, &p.m, &p.rhs)
    }

    /// One step of `dt` by the model's [`integrator`](super::ArticulationBuilder::integrator),
    /// as MuJoCo's (see [`ArticulationIntegrator`]). `qdd` comes from the dynamics with the
    /// control's torques, actuators ([`actuator`](super::actuator)), PD targets and muscle
    /// activations, external link forces and torques ([`ArticulationControl::link_f`],
    /// `link_t`), joint springs, damping and limits, the fluid and the contacts. By default
    /// (`Euler`) `qd' = qd + qdd dt`, then `q'` from `qd'` (quaternions by the exponential map,
    /// renormalized), with the joint damping implicit (`dt damping` joins the mass matrix's
    /// diagonal, MuJoCo's `eulerdamp`) unless
    /// [`implicit_damping`](super::ArticulationBuilder::implicit_damping) is off, and so are
    /// violated limits; the other forces are explicit. Returns the new state; every launch is
    /// on `tape`.
    pub fn step(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        control: Option<&ArticulationControl<R>>,
        dt: R,
    ) -> Result<ArticulationState<R>, Error> {
        articulation_step(self, tape, state, control, dt)
    }

    /// [`Articulations::step`]'s body (compiled once here for `f32` and `f64`, see
    /// `crate::precompiled`).
    fn step_generic(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        control: Option<&ArticulationControl<R>>,
        dt: R,
    ) -> Result<ArticulationState<R>, Error> {
        if !(dt.to_f64() > 0.0) || !dt.to_f64().is_finite() {
            return Err(Error::InvalidInput {
                what: "dt".into(),
                message: format!("{} must be finite and positive", dt.to_f64()),
            });
        }
        let own;
        let control = match control {
            Some(c) => c,
            None => {
                own = self.control();
                &own
            }
        };
        for (name, a) in [
            ("control.link_f", &control.link_f),
            ("control.link_t", &control.link_t),
        ] {
            if let Some(a) = a.as_ref().filter(|a| a.len() != self.n_links()) {
                return Err(Error::InvalidInput {
                    what: name.into(),
                    message: format!(
                        "has {} elements, one per link ({}) is needed",
                        a.len(),
                        self.n_links()
                    ),
                });
            }
        }
        // Every array of the wrong length is an error naming it (never a panic in a pass).
        let n_act = self.act_gear.len();
        for (name, len, n) in [
            ("state.q", state.q.len(), self.n_q),
            ("state.qd", state.qd.len(), self.n_dof),
            ("control.tau", control.tau.len(), self.n_dof),
            ("control.target_q", control.target_q.len(), self.n_dof),
            ("control.target_qd", control.target_qd.len(), self.n_dof),
            (
                "control.activation",
                control.activation.len(),
                self.muscle_f_max.len(),
            ),
            ("control.ctrl", control.ctrl.len(), n_act),
        ] {
            // (Activations and actuator controls of a model without muscles or actuators
            // are not read.)
            let unread = n == 0 && name.starts_with("control.") && name != "control.tau";
            if len != n && !unread {
                return Err(Error::InvalidInput {
                    what: name.into(),
                    message: format!("has {len} elements, the model needs {n}"),
                });
            }
        }
        match self.integrator {
            ArticulationIntegrator::Rk4 => return self.rk4_step(tape, state, control, dt),
            ArticulationIntegrator::ImplicitFast => self.check_implicit_fast()?,
            ArticulationIntegrator::Euler => {}
        }
        let qdd = self.accelerations(tape, state, control, dt, dt)?;
        let next = ArticulationState {
            q: Array::zeros(self.n_q),
            qd: Array::zeros(self.n_dof),
        };
        tape.launch(
            articulation_integrate,
            self.n_links(),
            (
                &self.joint_type,
                &self.q_start,
                &self.qd_start,
                &state.q,
                &state.qd,
                &qdd,
                dt,
                &next.q,
                &next.qd,
            ),
        );
        Ok(next)
    }

    /// The rates of `stage` where the stages of a step from `start` combine
    /// ([`articulation_rates`]): velocities (rotations' in exponential coordinates at
    /// `start`'s, a free joint's linear one in the world frame) and their derivatives.
    fn rates(
        &self,
        tape: &mut Tape,
        start: &ArticulationState<R>,
        stage: &ArticulationState<R>,
        qdd: &Array<R>,
    ) -> (Array<R>, Array<R>) {
        let (vel, acc) = (Array::zeros(self.n_dof), Array::zeros(self.n_dof));
        tape.launch(
            articulation_rates,
            self.n_links(),
            (
                &self.joint_type,
                &self.q_start,
                &self.qd_start,
                &start.q,
                &stage.q,
                &stage.qd,
                qdd,
                &vel,
                &acc,
            ),
        );
        (vel, acc)
    }

    /// `start` advanced by `h` along the rates `(vel, acc)` ([`articulation_advance`]).
    fn advance(
        &self,
        tape: &mut Tape,
        start: &ArticulationState<R>,
        (vel, acc): (&Array<R>, &Array<R>),
        h: R,
    ) -> ArticulationState<R> {
        let next = ArticulationState {
            q: Array::zeros(self.n_q),
            qd: Array::zeros(self.n_dof),
        };
        tape.launch(
            articulation_advance,
            self.n_links(),
            (
                &self.joint_type,
                &self.q_start,
                &self.qd_start,
                &start.q,
                &start.qd,
                vel,
                acc,
                h,
                &next.q,
                &next.qd,
            ),
        );
        next
    }

    /// What `ImplicitFast` needs (checked by `finalize`, and by each step for a model whose
    /// `integrator` was set afterwards): no fluid (MuJoCo's implicitfast has the fluid's
    /// velocity derivative, not computed here), and each actuator's and passive tendon's
    /// joints in one articulation (their damping joins that articulation's block of `M`).
    pub(crate) fn check_implicit_fast(&self) -> Result<(), Error> {
        let refuse = |message: String| {
            Err(Error::InvalidInput {
                what: "integrator ImplicitFast".into(),
                message,
            })
        };
        if self.fluid_on {
            return refuse(
                "a fluid's velocity derivative is not computed (MuJoCo's implicitfast has it); \
                 use Euler or Rk4"
                    .into(),
            );
        }
        if self.act_dof.is_empty() && self.tendon_dof.is_empty() {
            return Ok(());
        }
        let first = self.dof_art_start.to_vec();
        let name = |what: &str, k: usize| match (what, self.actuator_names.get(k)) {
            ("actuator", Some(n)) if !n.is_empty() => format!("actuator \"{n}\" ({k})"),
            _ => format!("{what} {k}"),
        };
        for (what, start, dof) in [
            ("actuator", &self.act_start, &self.act_dof),
            ("passive tendon", &self.tendon_start, &self.tendon_dof),
        ] {
            let (start, dof) = (start.to_vec(), dof.to_vec());
            for (k, w) in start.windows(2).enumerate() {
                let dofs: Vec<u32> = (w[0]..w[1]).map(|j| dof[j as usize]).collect();
                if dofs
                    .windows(2)
                    .any(|p| first[p[0] as usize] != first[p[1] as usize])
                {
                    return refuse(format!(
                        "{} acts on joints of several articulations (degrees of freedom \
                         {dofs:?}): implicitfast couples them in one articulation's mass \
                         matrix; use Euler or Rk4",
                        name(what, k)
                    ));
                }
            }
        }
        Ok(())
    }

    /// Adds the control's external link forces and torques ([`ArticulationControl::link_f`],
    /// `link_t`) into the links' wrenches about the origin `(en, ef)`.
    fn applied_wrenches(
        &self,
        tape: &mut Tape,
        c: &ArticulationControl<R>,
        k: &Kinematics<R>,
        (en, ef): (&Array<Vec3<R>>, &Array<Vec3<R>>),
    ) {
        if c.link_f.is_none() && c.link_t.is_none() {
            return;
        }
        let n = self.n_links();
        let zeros = Array::<Vec3<R>>::zeros(n);
        let f = c.link_f.as_ref().unwrap_or(&zeros);
        let t = c.link_t.as_ref().unwrap_or(&zeros);
        self.check_len(f, n, "control.link_f (one per link)");
        self.check_len(t, n, "control.link_t (one per link)");
        tape.launch(
            articulation_applied_wrench,
            n,
            (&k.link_p, &k.link_r, &self.com, f, t, en, ef),
        );
    }

    /// `qdd` at `state` with everything a step applies; with `dt > 0` the step's implicit terms
    /// join the solve (see [`ArticulationIntegrator`]), with `dt = 0` every force is explicit.
    /// `step_dt` is the step's time step (MuJoCo's `refsafe`, RK4's stages included).
    fn accelerations(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        control: &ArticulationControl<R>,
        dt: R,
        step_dt: R,
    ) -> Result<Array<R>, Error> {
        let p = self.pass(
            tape,
            PassInput {
                control: Some(control),
                contact: true,
                dt,
                ..PassInput::new(&state.q, &state.qd, &control.tau)
            },
        );
        let side = self.violated_limits(&state.q);
        if side.iter().all(|&s| s == 0) {
            return self.solve(tape, &p.m, &p.rhs);
        }
        self.limit_constraints(tape, state, &p, side, dt, step_dt)
    }

    /// Which time-constant limits ([`Joint::limit_time_constant`](super::Joint)) `q`
    /// violates, per velocity: 1 below the lower limit, 2 above the upper, 0 neither (or a
    /// penalty limit, or no limit).
    fn violated_limits(&self, q: &Array<R>) -> Vec<u32> {
        let (q, k) = (q.to_vec(), self.limit_k.to_vec());
        let (lo, hi) = (self.lower.to_vec(), self.upper.to_vec());
        let (dof_q, scalar) = (self.dof_q.to_vec(), self.dof_scalar.to_vec());
        (0..self.n_dof)
            .map(|a| {
                let x = q[dof_q[a] as usize].to_f64();
                match scalar[a] == 1 && k[a].to_f64() != 0.0 {
                    true if x < lo[a].to_f64() => 1,
                    true if x > hi[a].to_f64() => 2,
                    _ => 0,
                }
            })
            .collect()
    }

    /// The accelerations with the violated time-constant limits `side` as MuJoCo's soft
    /// constraints, as MuJoCo's step: the constraint forces `g >= 0` (into the range) from the
    /// mass matrix `M` alone and the pass's right-hand side, then `qdd` from the pass's matrix
    /// (with a step's implicit terms) and `rhs + g` (the constraint force explicit). The forces
    /// come from one solve ([`articulation_limit_system`]); a limit whose force would pull is
    /// dropped, and a dropped one whose acceleration falls below its reference is taken back,
    /// until neither happens (MuJoCo's solver's optimum of the soft constraints' problem).
    fn limit_constraints(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        p: &Pass<R>,
        side: Vec<u32>,
        dt: R,
        step_dt: R,
    ) -> Result<Array<R>, Error> {
        let nd = self.n_dof;
        let (mu, aref) = (Array::<R>::zeros(nd), Array::<R>::zeros(nd));
        // MuJoCo's `refsafe` uses the step's `dt`, in RK4's stages too.
        let min_tc = match self.limit_refsafe {
            true => step_dt * R::lit(2.0),
            false => R::lit(0.0),
        };
        let side_a = Array::from_vec(side.clone());
        tape.launch(
            articulation_limit_constraint,
            nd,
            (
                &side_a,
                &self.dof_q,
                &state.q,
                &state.qd,
                &self.lower,
                &self.upper,
                &self.limit_k,
                &self.limit_b,
                &self.limit_m,
                &self.limit_imp,
                min_tc,
                &mu,
                &aref,
            ),
        );
        // `M` alone: a step's pass has its implicit terms on the diagonal (RK4's stages, with
        // `dt` 0, have none).
        let implicit = dt.to_f64() > 0.0;
        let m = match implicit {
            true => {
                let z = Array::zeros(nd);
                self.pass(tape, PassInput::new(&state.q, &z, &z)).m
            }
            false => p.m.clone(),
        };
        let aref_v = aref.to_vec();
        let mut on: Vec<u32> = side.iter().map(|&s| (s != 0) as u32).collect();
        for round in 0usize.. {
            // Past this many rounds (a cycle, not met in practice) limits are only dropped,
            // which ends.
            let drop_only = round > 2 * nd + 2;
            let on_a = Array::from_vec(on.clone());
            let (m_c, rhs_c) = (Array::<R>::zeros(m.len()), Array::<R>::zeros(nd));
            tape.launch(crate::tied::slice_scalar, m.len(), (&m, 0usize, &m_c));
            tape.launch(
                articulation_limit_system,
                nd,
                (
                    &on_a,
                    &self.dof_m_row,
                    &self.dof_art_start,
                    &mu,
                    &aref,
                    &p.rhs,
                    &m_c,
                    &rhs_c,
                ),
            );
            let x = self.solve(tape, &m_c, &rhs_c)?;
            let xv = x.to_vec();
            // Into the range (`s (aref - x) > 0`): a force that pushes, or a dropped limit
            // whose acceleration is below its reference.
            let next: Vec<u32> = (0..nd)
                .map(|a| {
                    let s = if side[a] == 2 { -1.0 } else { 1.0 };
                    let push = s * (aref_v[a].to_f64() - xv[a].to_f64());
                    (side[a] != 0 && push > 0.0 && (on[a] == 1 || !drop_only)) as u32
                })
                .collect();
            if next == on {
                if !implicit {
                    // The pass's matrix is `M`: `x` is the step's acceleration already.
                    return Ok(x);
                }
                let rhs_g = Array::<R>::zeros(nd);
                tape.launch(
                    articulation_limit_force,
                    nd,
                    (&on_a, &mu, &aref, &x, &p.rhs, &rhs_g),
                );
                return self.solve(tape, &p.m, &rhs_g);
            }
            on = next;
        }
        unreachable!("the rounds end once the set of limits settles")
    }

    /// MuJoCo's RK4 (`mj_RungeKutta`, as in MuJoCo 4): four explicit evaluations, each stage's
    /// rates where they combine ([`articulation_rates`]: rotations in exponential coordinates
    /// at the start, a free joint's linear velocity in the world frame) and the state advanced
    /// from the start along them ([`articulation_advance`]).
    fn rk4_step(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        control: &ArticulationControl<R>,
        dt: R,
    ) -> Result<ArticulationState<R>, Error> {
        let zero = R::lit(0.0);
        let (mut vels, mut accs) = (Vec::with_capacity(4), Vec::with_capacity(4));
        let mut stage = state.clone();
        for i in 0..4 {
            let qdd = self.accelerations(tape, &stage, control, zero, dt)?;
            let (vel, acc) = self.rates(tape, state, &stage, &qdd);
            if i < 3 {
                // MuJoCo's RK4_A: the stages at dt/2, dt/2, dt, each from the previous rates.
                let h = if i < 2 { dt * R::lit(0.5) } else { dt };
                stage = self.advance(tape, state, (&vel, &acc), h);
            }
            vels.push(vel);
            accs.push(acc);
        }
        let combine = |tape: &mut Tape, x: &[Array<R>]| {
            let out = Array::zeros(self.n_dof);
            tape.launch(
                articulation_rk4_combine,
                self.n_dof,
                (&x[0], &x[1], &x[2], &x[3], &out),
            );
            out
        };
        let (vel, acc) = (combine(tape, &vels), combine(tape, &accs));
        Ok(self.advance(tape, state, (&vel, &acc), dt))
    }

    /// A state whose worlds listed in `worlds` are `from`'s and the others `state`'s, recorded
    /// on the tape (gradients flow to both). With `from = &model.state()` it resets those
    /// worlds ([`Articulations::reset_worlds`]); with a state of random draws it restarts them
    /// there.
    ///
    /// Errors: a world index out of range, or a state of the wrong size, as
    /// [`Error::InvalidInput`] naming it.
    pub fn select_worlds(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        worlds: &[usize],
        from: &ArticulationState<R>,
    ) -> Result<ArticulationState<R>, Error> {
        let take = crate::model::world_mask(worlds, self.n_worlds())?;
        for (s, what) in [(state, "state"), (from, "from")] {
            if s.q.len() != self.n_q || s.qd.len() != self.n_dof {
                return Err(Error::InvalidInput {
                    what: format!("select_worlds: {what}"),
                    message: format!(
                        "has {} coordinates and {} velocities, the model {} and {}",
                        s.q.len(),
                        s.qd.len(),
                        self.n_q,
                        self.n_dof
                    ),
                });
            }
        }
        let next = ArticulationState {
            q: Array::zeros(self.n_q),
            qd: Array::zeros(self.n_dof),
        };
        tape.launch(
            articulation_select_worlds,
            self.n_q,
            (&self.q_world, &take, &state.q, &from.q, &next.q),
        );
        tape.launch(
            articulation_select_worlds,
            self.n_dof,
            (&self.dof_world, &take, &state.qd, &from.qd, &next.qd),
        );
        Ok(next)
    }

    /// `state` with the worlds listed in `worlds` back at [`Articulations::state`] (see
    /// [`Articulations::select_worlds`]).
    pub fn reset_worlds(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        worlds: &[usize],
    ) -> Result<ArticulationState<R>, Error> {
        self.select_worlds(tape, state, worlds, &self.state())
    }

    /// `qdd = M^-1 rhs`, one block per articulation, recorded on the tape with its adjoint
    /// (`rhs_bar += M^-1 qdd_bar`, `M_bar -= (M^-1 qdd_bar) qdd^T`) and tangent
    /// (`dqdd = M^-1 (drhs - dM qdd)`). In `Dual` the solves and the outer product carry the
    /// derivative parts ([`solve_parts`]), so a Hessian-vector product goes through it.
    fn solve(&self, tape: &mut Tape, m: &Array<R>, rhs: &Array<R>) -> Result<Array<R>, Error> {
        let (factors, blocks) = self.factor(m)?;
        let (factors, blocks) = (Arc::new(factors), Arc::new(blocks));
        // M's derivative parts, for the solves in `Dual` (nothing otherwise).
        let mv: Arc<Vec<R>> = Arc::new(if R::DUAL { m.to_vec() } else { Vec::new() });
        let x = dual_values::<R>(&solve_parts(&factors, &blocks, &mv, &rhs.to_vec()));
        let qdd = Array::<R>::zeros(self.n_dof);
        let out = qdd.clone();
        let (fb, bb, qb, mb, rb, mvb) = (
            factors.clone(),
            blocks.clone(),
            qdd.clone(),
            m.clone(),
            rhs.clone(),
            mv,
        );
        let (ft, bt, qt, mt, rt) = (factors, blocks, qdd.clone(), m.clone(), rhs.clone());
        tape.record_fn(
            "articulation_solve",
            &[m, rhs],
            &[&qdd],
            || out.assign(&x),
            move || {
                let Some(g) = qb.grad_buffer() else {
                    return Ok(());
                };
                let lam = solve_parts(&fb, &bb, &mvb, &g.to_vec());
                if let Some(rg) = rb.grad_buffer() {
                    let lam = dual_values::<R>(&lam);
                    rg.modify(|s| s.iter_mut().zip(lam).for_each(|(d, l)| *d += l));
                }
                if let Some(mg) = mb.grad_buffer() {
                    let x = qb.to_vec();
                    let eps = |v: &Option<Vec<f64>>, k: usize| v.as_ref().map_or(0.0, |e| e[k]);
                    mg.modify(|s| {
                        for &(start, n, off) in bb.iter() {
                            for a in 0..n {
                                for c in 0..n {
                                    let (i, j) = (start + a, start + c);
                                    let xj = x[j].to_f64();
                                    let d = eps(&lam.eps, i) * xj + lam.re[i] * x[j].eps();
                                    s[off + a * n + c] -= R::lit(lam.re[i] * xj).with_eps(d);
                                }
                            }
                        }
                    });
                }
                Ok(())
            },
        )
        .dual_safe()
        .with_tangent(move || {
            adflex_runtime::second_order::refuse_dual::<R>(
                "the articulations' mass-matrix solve in forward mode",
                crate::solver::parts::NO_DUAL_TANGENT,
            )?;
            let x: Vec<f64> = qt.to_vec().iter().map(|v| v.to_f64()).collect();
            let mut b = match rt.tangent_buffer() {
                Some(t) => t.to_vec().iter().map(|v| v.to_f64()).collect(),
                None => vec![0.0; x.len()],
            };
            if let Some(dm) = mt.tangent_buffer() {
                let dm = dm.to_vec();
                for &(start, n, off) in bt.iter() {
                    for a in 0..n {
                        for c in 0..n {
                            b[start + a] -= dm[off + a * n + c].to_f64() * x[start + c];
                        }
                    }
                }
            }
            let dx = solve_all(&ft, &bt, &b);
            qt.ensure_tangent()
                .assign(&dx.iter().map(|&v| R::lit(v)).collect::<Vec<_>>());
            Ok::<(), Error>(())
        });
        Ok(qdd)
    }

    fn check_slices(&self, q: &[f64], v: &[f64], what: &str) {
        assert!(
            q.len() == self.n_q && v.len() == self.n_dof,
            "Articulations::{what}: q has {} elements (the model needs {}), v {} (needs {})",
            q.len(),
            self.n_q,
            v.len(),
            self.n_dof
        );
    }

    /// The Cholesky factors of every block of the mass-matrix array `m`, and each block's
    /// `(first velocity, size, offset in m)`. A block that cannot be factored is an
    /// [`Error::InvalidInput`] naming the articulation, the joint and why (an input that
    /// cannot be computed with: an optimizer's line search backs off from it).
    fn factor(&self, m: &Array<R>) -> Result<Factors, Error> {
        self.factor_values(&m.to_vec())
    }

    /// [`Articulations::factor`] for the values of a mass-matrix array (in `R` or `f64`).
    pub(super) fn factor_values<T: Real>(&self, mv: &[T]) -> Result<Factors, Error> {
        let factors = factor_all(self, mv).map_err(|(art, d)| {
            let l = self.links[self.dof_link.get(self.articulations[art].dofs.start + d) as usize]
                .joint
                .clone();
            let finite = mv.iter().all(|x| x.to_f64().is_finite());
            Error::InvalidInput {
                what: format!(
                    "mass matrix of articulation {art}{} (joint \"{l}\", pivot {d})",
                    match self.worlds.len() {
                        1 => String::new(),
                        _ => format!(
                            " in world {}",
                            self.worlds
                                .iter()
                                .position(|w| w.articulations.contains(&art))
                                .unwrap_or(0)
                        ),
                    }
                ),
                message: if finite {
                    "is not positive definite: a joint moves no mass (a mass or inertia \
                     parameter at or below zero), or the state blew up (a step unstable at \
                     this dt: the stiffest term, e.g. the joint limits' `limit_ke`, needs a \
                     smaller dt or a softer value)"
                        .into()
                } else {
                    "is not finite: the state or a parameter is not finite".into()
                },
            }
        })?;
        let blocks = self
            .articulations
            .iter()
            .map(|a| (a.dofs.start, a.dofs.len(), a.m_offset))
            .collect();
        Ok((factors, blocks))
    }

    /// Row-major block of articulation `art` of a mass-matrix array, as rows.
    pub fn block(&self, m: &Array<R>, art: usize) -> Vec<Vec<f64>> {
        let a = &self.articulations[art];
        let n = a.dofs.len();
        let v = m.to_vec();
        (0..n)
            .map(|i| (0..n).map(|j| v[a.m_offset + i * n + j].to_f64()).collect())
            .collect()
    }

    /// The coordinates' velocity for a tangent vector `v` at `q` (the differential at 0 of
    /// [`Articulations::integrate`]): scalar joints `dq = v`; a quaternion `r` (ball, or a
    /// free joint's rotation) `dr = r (v/2, 0)` (the angular velocity is in the link frame); a
    /// free joint's position `dp = R(r) v_lin`.
    pub fn tangent_to_coords(&self, q: &[f64], v: &[f64]) -> Vec<f64> {
        self.check_slices(q, v, "tangent_to_coords");
        let mut dq = vec![0.0; self.n_q];
        for l in &self.links {
            let (s, d) = (l.q.start, l.dofs.start);
            match l.kind {
                JointType::Fixed => {}
                JointType::Revolute | JointType::Prismatic => dq[s] = v[d],
                JointType::Ball => quat_tangent(&q[s..s + 4], &v[d..d + 3], &mut dq[s..s + 4]),
                JointType::Free => {
                    let r = &q[s + 3..s + 7];
                    let p = rotate_xyzw(r, &v[d..d + 3]);
                    dq[s..s + 3].copy_from_slice(&p);
                    quat_tangent(r, &v[d + 3..d + 6], &mut dq[s + 3..s + 7]);
                }
            }
        }
        dq
    }

    /// `q (+) v`: the configuration reached from `q` along the tangent vector `v` (scalar
    /// joints add; quaternions `r exp(v/2)` renormalized; a free joint's position
    /// `p + R(r) v_lin`). Use it for finite differences on the configuration manifold.
    pub fn integrate(&self, q: &[f64], v: &[f64]) -> Vec<f64> {
        self.check_slices(q, v, "integrate");
        let mut out = q.to_vec();
        for l in &self.links {
            let (s, d) = (l.q.start, l.dofs.start);
            match l.kind {
                JointType::Fixed => {}
                JointType::Revolute | JointType::Prismatic => out[s] += v[d],
                JointType::Ball => quat_exp(&q[s..s + 4], &v[d..d + 3], &mut out[s..s + 4]),
                JointType::Free => {
                    let p = rotate_xyzw(&q[s + 3..s + 7], &v[d..d + 3]);
                    for k in 0..3 {
                        out[s + k] += p[k];
                    }
                    quat_exp(&q[s + 3..s + 7], &v[d + 3..d + 6], &mut out[s + 3..s + 7]);
                }
            }
        }
        out
    }
}

/// `r (v/2, 0)` for `r = (x, y, z, w)`.
fn quat_tangent(r: &[f64], v: &[f64], out: &mut [f64]) {
    let (x, y, z, w) = (r[0], r[1], r[2], r[3]);
    let (a, b, c) = (0.5 * v[0], 0.5 * v[1], 0.5 * v[2]);
    // (w, u) (0, h) = (-u.h, w h + u x h)
    out[0] = w * a + (y * c - z * b);
    out[1] = w * b + (z * a - x * c);
    out[2] = w * c + (x * b - y * a);
    out[3] = -(x * a + y * b + z * c);
}

/// `normalize(r exp(v/2))`.
fn quat_exp(r: &[f64], v: &[f64], out: &mut [f64]) {
    let th = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let (k, c) = if th < 1e-8 {
        (0.5, 1.0)
    } else {
        ((0.5 * th).sin() / th, (0.5 * th).cos())
    };
    let (x, y, z, w) = (r[0], r[1], r[2], r[3]);
    let (a, b, cc) = (k * v[0], k * v[1], k * v[2]);
    let mut o = [
        w * a + x * c + (y * cc - z * b),
        w * b + y * c + (z * a - x * cc),
        w * cc + z * c + (x * b - y * a),
        w * c - (x * a + y * b + z * cc),
    ];
    let n = o.iter().map(|e| e * e).sum::<f64>().sqrt();
    o.iter_mut().for_each(|e| *e /= n);
    out.copy_from_slice(&o);
}

/// `R(r) v` for a unit `r = (x, y, z, w)`.
fn rotate_xyzw(r: &[f64], v: &[f64]) -> [f64; 3] {
    let q = Quat::new(r[3], r[0], r[1], r[2]).normalize();
    let p = super::model::rotate(&q, &Vec3::new(v[0], v[1], v[2]));
    [p.x, p.y, p.z]
}

/// Blocks per parallel task of the factorization and the solves (many worlds of small
/// robots: a task must outweigh rayon's few microseconds).
const BLOCKS_PER_TASK: usize = 256;

/// Cholesky factors (lower, row-major) of every articulation's block; on failure the
/// articulation and the pivot (the first failing one). Blocks are independent: in parallel
/// over many worlds, the same bits.
pub(crate) fn factor_all<R: Real, T: Real>(
    model: &Articulations<R>,
    m: &[T],
) -> Result<Vec<Vec<f64>>, (usize, usize)> {
    use rayon::prelude::*;
    let one = |(ai, a): (usize, &super::model::ArticulationInfo)| {
        let n = a.dofs.len();
        let mut l = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..=i {
                let mut s = m[a.m_offset + i * n + j].to_f64();
                for k in 0..j {
                    s -= l[i * n + k] * l[j * n + k];
                }
                if i == j {
                    if !(s > 0.0) || !s.is_finite() {
                        return Err((ai, i));
                    }
                    l[i * n + i] = s.sqrt();
                } else {
                    l[i * n + j] = s / l[j * n + j];
                }
            }
        }
        Ok(l)
    };
    let arts = &model.articulations;
    if arts.len() < 2 * BLOCKS_PER_TASK {
        return arts.iter().enumerate().map(one).collect();
    }
    // Every block's result, then the first failure in articulation order (a parallel
    // `collect` into a `Result` could report any failing block).
    let all: Vec<Result<Vec<f64>, (usize, usize)>> = arts
        .par_iter()
        .enumerate()
        .with_min_len(BLOCKS_PER_TASK)
        .map(one)
        .collect();
    all.into_iter().collect()
}

/// `M^-1 b` for the values of `m` and `b` (`factors`: `M0`'s) and, in `Dual`, for their
/// derivative parts: `x1 = M0^-1 (b1 - M1 x0)`, the derivative of a linear solve.
fn solve_parts<R: Real>(
    factors: &[Vec<f64>],
    blocks: &[(usize, usize, usize)],
    m: &[R],
    b: &[R],
) -> Parts {
    let re: Vec<f64> = b.iter().map(|v| v.to_f64()).collect();
    let x0 = solve_all(factors, blocks, &re);
    if !R::DUAL {
        return Parts::real(x0);
    }
    let mut r: Vec<f64> = b.iter().map(|v| v.eps()).collect();
    for &(start, n, off) in blocks {
        for a in 0..n {
            for c in 0..n {
                r[start + a] -= m[off + a * n + c].eps() * x0[start + c];
            }
        }
    }
    let x1 = solve_all(factors, blocks, &r);
    Parts {
        re: x0,
        eps: Some(x1),
    }
}

/// The scalars `re + eps ε` of `p` (the values alone outside `Dual`).
fn dual_values<R: Real>(p: &Parts) -> Vec<R> {
    (0..p.re.len())
        .map(|k| R::lit(p.re[k]).with_eps(p.eps.as_ref().map_or(0.0, |e| e[k])))
        .collect()
}

/// `y <- M^-1 y` for one block from its row-major Cholesky factor `l` (`M = L L^T`).
pub(super) fn cholesky_solve(l: &[f64], y: &mut [f64]) {
    let n = y.len();
    for i in 0..n {
        let mut s = y[i];
        for k in 0..i {
            s -= l[i * n + k] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = y[i];
        for k in i + 1..n {
            s -= l[k * n + i] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
}

/// `M^-1 b` per block from the factors.
pub(super) fn solve_all(
    factors: &[Vec<f64>],
    blocks: &[(usize, usize, usize)],
    b: &[f64],
) -> Vec<f64> {
    use rayon::prelude::*;
    let mut x = b.to_vec();
    let one = |(l, y): (&Vec<f64>, &mut [f64])| cholesky_solve(l, y);
    // The blocks' slices of x (blocks are contiguous and in order).
    let mut slices = Vec::with_capacity(blocks.len());
    let mut rest = &mut x[..];
    let mut at = 0;
    for &(start, n, _) in blocks {
        let (_, tail) = std::mem::take(&mut rest).split_at_mut(start - at);
        let (y, tail) = tail.split_at_mut(n);
        slices.push(y);
        rest = tail;
        at = start + n;
    }
    if blocks.len() < 2 * BLOCKS_PER_TASK {
        factors.iter().zip(slices).for_each(one);
    } else {
        factors
            .par_iter()
            .zip(slices)
            .with_min_len(BLOCKS_PER_TASK)
            .for_each(one);
    }
    x
}
