//! Implicit (backward) Euler: `v' = v + a(x', v') dt`, `x' = x + v' dt`, solved by Newton's
//! method with a matrix-free conjugate-gradient solve and a backtracking line search, and
//! differentiated with the implicit function theorem (one adjoint linear solve per step).
//!
//! # The solve
//!
//! The unknown is the new velocity `v'` of the free particles (inverse mass `w > 0`; pinned
//! particles keep `v' = v`). With `M` the mass matrix and `a = w f + g` the accelerations of
//! [`Model::eval_accelerations`], the residual is
//!
//! `G(v') = M (v' - v - dt a(x + dt v', v'))`,
//!
//! and its Jacobian `A = M - dt^2 df/dx - dt df/dv` (symmetric for springs, membranes,
//! tetrahedra, bending and drag). Each Newton iteration solves `A d = -G` by
//! [`cg`](crate::solver::krylov::cg) (falling back to BiCGSTAB if CG meets negative curvature, e.g. from
//! compressed springs, or from friction, which makes `A` unsymmetric). The matrix is never
//! formed: `A u` is one pass of the **tangent** kernels of the force model, recorded once per
//! iterate on a scratch tape, with the tangents `dt u` on `x'` and `u` on `v'`
//! ([`Tape::tangent`]): `A u = M u - dt M a_dot`. A backtracking (Armijo) line search makes
//! the iteration robust far from the solution (large `dt`, stiff forces, impacts). It accepts a
//! step that decreases the **incremental potential**
//! `E(v') = 0.5 (v' - v)^T M (v' - v) + U(x + dt v') - (work of the other forces)`, whose
//! gradient is `G` when the forces derive from a potential: `U` is the sum of the forces'
//! energies ([`Force::energy`]: springs, membranes, tetrahedra, bending, and the penalty of
//! every contact), computed exactly, and the work of the forces without one (gravity, control,
//! damping, friction, a user force without an energy) is estimated by the trapezoid rule on
//! its slopes. A step may also be accepted for decreasing the residual's merit
//! `0.5 (v' - v - dt a)^T M (v' - v - dt a)`, but not if it raises `E` beyond `E`'s rounding
//! along a descent direction of `E`: alternating the two merits can cycle (it did, at a
//! block's impact with friction). Friction and damping make `E`'s estimate depend on the
//! path, and the two merits could still go round a cycle (a cloth landing on the ground at
//! 1/60 s went round three iterates for hundreds of iterations): a world whose new iterate
//! comes back near one of its last four searches on the residual alone from there. Of 100
//! landings of cloths and soft blocks at 1/60 and 1/30 s, 95 converge within the default 30
//! iterations (91 before the watchdog); stiff springs (80 cases up to `omega dt` of about 600)
//! take the same iterations as before.
//! An energy whose tangent pass fails leaves the search to the residual.
//!
//! # The gradient
//!
//! The step is one custom step on the caller's tape ([`Tape::record_fn`]): the Newton
//! iterations are **not** recorded. Its backward uses the implicit function theorem: with the
//! incoming adjoints `x'_bar`, `v'_bar` and `b = v'_bar + dt x'_bar`, it solves the transposed
//! system `A^T lambda = b` matrix-free with the **adjoint** kernels of the force model
//! (`A^T u = M u - dt (dt df/dx^T u + df/dv^T u)`, one backward pass of the scratch tape
//! seeded with `M u` on the accelerations), then one more adjoint pass seeded with
//! `dt M lambda` gives every input its gradient: `x_bar += x'_bar + dt df/dx^T lambda`,
//! `v_bar += M lambda`, and the parameters of the model (stiffnesses, rest lengths, masses,
//! control forces, ...) `+= dt df/dtheta^T lambda`. Forward mode ([`Tape::tangent`]) is the
//! same with one tangent pass for the right-hand side and a solve with `A`.
//!
//! The scratch evaluations run on private copies of the model's parameter arrays, so the
//! matrix-vector products never touch the gradients or tangents of the real ones.
//!
//! In [`Dual`] (Hessian-vector products, [`adflex_runtime::second_order`]) the step gives the
//! new velocities their derivative part by the forward rule (one more solve with `A`), and
//! the backward runs at the new state with its derivative part: `A^T lambda = b` is solved
//! part by part, `A0^T lambda0 = b0`, then `A0^T lambda1 = b1 - A1^T lambda0` (the theorem's
//! second-order term, `A` moving along the direction), and every map after it acts on both
//! parts. A direction on the inverse masses needs no more (`M` cancels in the solve). Newton's
//! iterations and these linear solves need only the real parts of `A`: they run on a copy of
//! the model in `f64` ([`Force::to_f64`], which every library force has; a force without it
//! keeps them in `Dual`, the same result at a few times the cost), and only the passes that
//! carry the direction (`b1`'s and the right-hand side's derivative parts, `A1^T lambda0`) run
//! in `Dual`. The [linearized](ImplicitEuler::linearized) step refuses `Dual`.
//!
//! # Failures
//!
//! A step whose Newton iteration stops short of its tolerance, or whose adjoint (or tangent)
//! linear solve does, is handled by [`ImplicitEuler::on_failure`]: by default
//! ([`SolverPolicy::Error`]) `step` returns [`Error::NotConverged`] naming
//! `"ImplicitEuler Newton"` (and records nothing), and `tape.backward` returns it naming
//! `"ImplicitEuler adjoint linear solve"` and the tape step. A NaN residual never counts as
//! converged. A NaN, infinite or non-positive `dt`, or a NaN/Inf in the state or in a
//! parameter array the forces read, is [`Error::InvalidInput`] naming the array and index,
//! whatever the policy.
//!
//! # Linearized implicit Euler
//!
//! [`ImplicitEuler::linearized`] (Baraff and Witkin 1998) takes one Newton step from
//! `v' = v` and stops: one linear solve `A d = -G(v)` with the force Jacobians at
//! `(x + dt v, v)`, no line search. On forces linear in `x` and `v` (zero-rest-length springs,
//! a 1-D spring along its axis, linear damping) it is exactly implicit Euler, so unconditionally
//! stable (energy factor `1 / (1 + (omega dt)^2)` per step); on nonlinear forces it is first
//! order like implicit Euler, cheaper (one solve instead of several), and its error grows with
//! the nonlinearity over the step (it does not converge to the implicit solution and can
//! overshoot where the full method would not).
//!
//! Its gradient is that of the step it made, not of the implicit solution: with
//! `B = I - dt (dt da/dx + da/dv)` the step solves `B d = dt (a + a_e)`, so its reverse mode needs
//! `A^T lambda = b` (as above) and, because `B` depends on the inputs, the second-order term
//! `dt (M lambda)^T d(J w)` with `w = (dt d, d)` (how the Jacobian along the step changes with
//! each input). That term is a central difference of two adjoint passes at
//! `(x, v) +- eps w`, with `eps` the step that balances truncation and rounding
//! (`eps_R^(1/3)` relative): in f64 the gradient agrees with central differences of the
//! rollout to about 1e-8 relative (the tests check it); in f32 to about 1e-3. Forward mode
//! ([`Tape::tangent`]) does the same with two tangent passes.
//!
//! # Implicit-explicit splits
//!
//! [`ImplicitEuler::explicit`] (or [`ImplicitEuler::with_explicit`]) names forces treated
//! explicitly: they are evaluated once at the start of the step, `a_e = w f_e(x, v)`, recorded
//! on the caller's tape as ordinary launches, and held constant in the solve of
//! `G(v') = M (v' - v - dt (a_I(x + dt v', v') + a_e))`, where `a_I` holds gravity, the
//! control and the other (implicit) forces. The gradient is exact as before: the adjoint
//! solve gives `a_e` the gradient `dt M lambda` and the tape carries it through the explicit
//! forces' own adjoints. Typical split: stiff springs, membranes and bending implicit; drag,
//! wind, friction or a user force without a tangent explicit. The explicit part keeps its
//! explicit stability limit: for an implicit spring (`omega`) with explicit linear damping
//! (`gamma = c / m`) a step is stable for `gamma dt < 2 + (omega dt)^2 / 2` (tests and
//! `docs/charts/integrators_stability.svg` check it).

use std::ops::Range;
use std::sync::Arc;

use adflex_runtime::prelude::*;

use super::common::{
    acceleration_tangent, add_into, check_inputs, check_visited, copies, epsilon, finish_step,
    flat, flat_parts, forces_only, is_f32, particles, pull, record, step_bodies, unflat,
    unflat_parts, Copies, Dofs, Needs, Point, Through, Twin,
};
use super::{check_dt, Integrator, SolverPolicy};
use crate::forces::particle::accelerations;
use crate::forces::Force;
use crate::model::Model;
use crate::precompiled::precompiled;
use crate::solver::krylov::SolveSettings;
use crate::solver::newton::{
    direction, linear_solve, max_abs, newton, solve_linear, solve_transposed_on, with_world,
    world_context, LinearSolve, NewtonSettings, NewtonSystem, Parts, PassFailure,
};
pub use crate::solver::NewtonStats;
use crate::state::{Control, State};

/// Implicit (backward) Euler, solved by Newton-CG with a line search; first order,
/// unconditionally stable, differentiable through the implicit function theorem.
///
/// Suits stiff systems (stiff springs, cloth, FEM with `omega dt >> 1`) where the explicit
/// methods need tiny steps: it stays bounded for any `dt` (on an undamped spring it
/// dissipates energy by the factor `1 / (1 + (omega dt)^2)` per step, the numerical damping
/// that makes it stable and also less accurate than [`Rk4`](crate::integrators::Rk4) on
/// smooth, soft problems). A step costs a few Newton iterations, each one force evaluation and
/// a CG solve of tangent passes; its gradient costs one more solve of adjoint passes.
///
/// Each step records a single custom step (see the module docs) plus, for rigid bodies, the
/// semi-implicit body step. The tape records a step per call, however many Newton iterations
/// it took. Penalty contact is continuous but not smooth (a kink where a contact starts; the
/// ground's damping ramps in over [`Ground::damping_depth`](crate::contact::ground::Ground)
/// rather than jumping): Newton with its line search on the incremental potential (module
/// docs) converges through impacts (`kernels/tests/integrators.rs` throws soft blocks at the
/// ground at steps of 1 ms to 1/30 s and drops a bending cloth on it at 1/60 and 1/30 s), and
/// the gradient is that of the
/// active contact set. The particle-particle and shape contacts' damping ramps in the same way
/// (`damping_depth`); a dense pile of stiff frictional particles (`kernels/tests/integrators.rs`:
/// converged at 2 and 4 ms, not at 8 ms) can still stall it. A force that jumps (a user's
/// switch) can too: the error then says Newton stalled, and a smaller `dt` or an explicit
/// treatment of that force ([`ImplicitEuler::explicit`]) is the remedy.
///
/// A solve that misses its tolerance is an error by default (see [`ImplicitEuler::on_failure`]
/// and the module's "Failures").
#[derive(Clone, Debug, PartialEq)]
pub struct ImplicitEuler {
    /// Maximum Newton iterations per step (default 30), per world.
    pub max_newton: usize,
    /// Newton stops when `max |v' - v - dt (a + a_e)| <= tolerance * scale` (m/s), `scale`
    /// the largest of `|v|`, `|v'|`, `dt |a|`, `dt |a_e|` (`a_e`: the explicit forces' part),
    /// each over one world's particles (each world is solved by its own iteration). `None`
    /// (default): `1e-10` in f64, `1e-4` in f32.
    pub tolerance: Option<f64>,
    /// Stopping rule of the linear solves (Newton, and adjoint/tangent unless
    /// `adjoint_linear` is set; default: relative `1e-10`, 1000 iterations). A Newton linear
    /// solve that misses it is not an error by itself (inexact Newton): the Newton residual
    /// decides.
    pub linear: SolveSettings,
    /// Stopping rule of the gradient's linear solves (the IFT adjoint solve of
    /// `tape.backward` and the tangent solve of `tape.tangent`); `None` (default): `linear`.
    /// Their error is the gradient's error, so a solve that misses it fails per `on_failure`.
    pub adjoint_linear: Option<SolveSettings>,
    /// Backtracking line search on the residual (default on). Off, every Newton step is full.
    pub line_search: bool,
    /// Maximum halvings of the step in the line search (default 20).
    pub max_backtracks: usize,
    /// What a solve that misses its tolerance does (default [`SolverPolicy::Error`]): the
    /// Newton iteration of `step` (an [`Error::NotConverged`] from `step`, nothing recorded),
    /// the adjoint solve of `tape.backward` (an error from `backward`), the tangent solve of
    /// `tape.tangent` (an error from `tangent`).
    /// [`SolverPolicy::Warn`] prints the figures to stderr and uses the result;
    /// [`SolverPolicy::Continue`] uses it silently.
    pub on_failure: SolverPolicy,
    /// **Linearized** implicit Euler (default off), a variant of Baraff and Witkin's: one
    /// Newton step from `v' = v` (one linear solve with the force Jacobians at the predicted
    /// state `(x + dt v, v)`; Baraff and Witkin take them at `(x, v)`, the same on linear
    /// forces), no iteration, no line search. See the module's "Linearized implicit Euler".
    pub linearized: bool,
    /// Names ([`Force::name`]) of the forces treated
    /// **explicitly** (default none): evaluated once at the start of the step and held
    /// constant in the implicit solve (an implicit-explicit split). Every force of the model
    /// with such a name is explicit; an unknown name is an [`Error::InvalidInput`] listing
    /// the model's forces. See the module's "Implicit-explicit splits".
    pub explicit: Vec<String>,
}

impl Default for ImplicitEuler {
    fn default() -> Self {
        ImplicitEuler {
            max_newton: 30,
            tolerance: None,
            linear: SolveSettings::default(),
            line_search: true,
            max_backtracks: 20,
            adjoint_linear: None,
            on_failure: SolverPolicy::Error,
            linearized: false,
            explicit: Vec::new(),
        }
    }
}

impl ImplicitEuler {
    /// Baraff and Witkin's linearized implicit Euler: the defaults with
    /// [`ImplicitEuler::linearized`] on (one linear solve per step).
    ///
    /// ```
    /// use adflex_kernels::integrators::{ImplicitEuler, Integrator};
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::{Tape, Vec3};
    ///
    /// // A stiff spring (omega dt = 100): one linear solve per step, and stable.
    /// let mut b = ModelBuilder::<f64>::new();
    /// let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let c = b.add_particle(Vec3::new(1.1, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// b.add_spring_with_rest(a, c, 1.0, 1e6, 0.0);
    /// b.gravity = Vec3::zeros();
    /// let model = b.finalize();
    /// let (s, stats) = ImplicitEuler::linearized()
    ///     .step_with_stats(&model, &mut Tape::new(), &model.state(), None, 0.1)
    ///     .unwrap();
    /// assert_eq!(stats.newton_iterations, 1);
    /// assert!((s.x.get(1).x - 1.0).abs() < 1e-3); // pulled almost to the rest length
    /// ```
    pub fn linearized() -> Self {
        ImplicitEuler {
            linearized: true,
            ..ImplicitEuler::default()
        }
    }

    /// The same integrator with the forces named in `forces` treated explicitly (added to
    /// [`ImplicitEuler::explicit`]).
    ///
    /// ```
    /// use adflex_kernels::integrators::{ImplicitEuler, Integrator};
    /// use adflex_kernels::prelude::*;
    /// use adflex_runtime::{Tape, Vec3};
    ///
    /// let mut b = ModelBuilder::<f64>::new();
    /// let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let c = b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// b.add_spring(a, c, 1e5, 0.0);
    /// b.set_drag(Drag { kd: 0.5, ..Drag::default() });
    /// let model = b.finalize();
    /// // Stiff springs implicit, drag explicit.
    /// let imex = ImplicitEuler::default().with_explicit(["drag"]);
    /// let s = imex.step(&model, &mut Tape::new(), &model.state(), None, 0.01).unwrap();
    /// assert!(s.x.get(1).y < 0.0);
    /// // A name the model does not have is an error naming the forces it has.
    /// let typo = ImplicitEuler::default().with_explicit(["drags"]);
    /// let err = typo.step(&model, &mut Tape::new(), &model.state(), None, 0.01).unwrap_err();
    /// assert!(err.to_string().contains("springs, drag"), "{err}");
    /// ```
    pub fn with_explicit<S: Into<String>>(mut self, forces: impl IntoIterator<Item = S>) -> Self {
        self.explicit.extend(forces.into_iter().map(Into::into));
        self
    }

    /// The model without its explicit forces (what the implicit solve evaluates), and the
    /// explicit forces; an error for an explicit name no force of the model has.
    fn split<R: Real>(&self, model: &Model<R>) -> Result<(Model<R>, Forces<R>), Error> {
        let names: Vec<&str> = model.forces.iter().map(|f| f.name()).collect();
        if let Some(bad) = self.explicit.iter().find(|e| !names.contains(&e.as_str())) {
            return Err(Error::InvalidInput {
                what: format!("ImplicitEuler::explicit: \"{bad}\""),
                message: format!(
                    "the model has no force of that name; its forces are: {}",
                    if names.is_empty() {
                        "none".to_string()
                    } else {
                        names.join(", ")
                    }
                ),
            });
        }
        let mut implicit = forces_only(model);
        let (exp, imp): (Vec<_>, Vec<_>) = std::mem::take(&mut implicit.forces)
            .into_iter()
            .partition(|f| self.explicit.iter().any(|e| e == f.name()));
        implicit.forces = imp;
        Ok((implicit, exp))
    }
}

/// A list of forces (the explicit part of a split).
type Forces<R> = Vec<Box<dyn Force<R>>>;

/// Records the explicit forces' accelerations `w f_e` (m/s^2, no gravity) at `state` on `tape`.
fn explicit_accelerations<R: Real>(
    model: &Model<R>,
    forces: &[Box<dyn Force<R>>],
    tape: &mut Tape,
    state: &State<R>,
    control: Option<&Control<R>>,
) -> Array<Vec3<R>> {
    let n = model.particle_count;
    let f = Array::zeros(n).named("f_explicit");
    let cx = model.context(state, control);
    for force in forces {
        force.eval(&cx, tape, &f);
    }
    let a = Array::zeros(n).named("a_explicit");
    tape.launch(
        accelerations,
        n,
        (
            &f,
            &model.particle_inv_mass,
            &Array::zeros(model.worlds.len()),
            &model.particle_world,
            &a,
        ),
    );
    a
}

/// The step's system on `twin` (the real parts of the start and of the explicit
/// accelerations).
fn twin_system(twin: &Twin, x0: &Parts, v0: &[f64], dt: f64, a_e: &[f64]) -> System<f64> {
    let x0 = Parts::real(x0.re.clone());
    System::new(
        twin.copies(),
        x0,
        v0.to_vec(),
        &twin.inv_mass,
        dt,
        a_e.to_vec(),
    )
}

// ---------------------------------------------------------------------------------------------
// The nonlinear system of one step.

/// One step's system: `G(v') = M (v' - v0 - dt a(x0 + dt v', v'))` over the free DOFs.
struct System<R: Real> {
    c: Copies<R>,
    /// The positions at the start of the step, with their derivative parts in `Dual`.
    x0: Parts,
    v0: Vec<f64>,
    dofs: Dofs,
    /// Per DOF: the inverse mass on free DOFs, 1 on pinned ones (the CG preconditioner).
    precond: Vec<f64>,
    dt: f64,
    /// The explicit forces' accelerations (m/s^2), constant over the solve (zeros without an
    /// implicit-explicit split).
    a_e: Vec<f64>,
    failure: PassFailure,
}

impl<R: Real> System<R> {
    fn new(c: Copies<R>, x0: Parts, v0: Vec<f64>, inv_mass: &[R], dt: f64, a_e: Vec<f64>) -> Self {
        let w: Vec<f64> = inv_mass.iter().flat_map(|w| [w.to_f64(); 3]).collect();
        System {
            a_e,
            dofs: Dofs::new(&c.model, inv_mass),
            c,
            x0,
            v0,
            precond: w.iter().map(|&w| if w > 0.0 { w } else { 1.0 }).collect(),
            dt,
            failure: PassFailure::new("ImplicitEuler"),
        }
    }

    /// Records the accelerations at `v'` (`x' = x0 + dt v'`) on a new tape; with derivative
    /// parts, at the point of a Hessian-vector product's sweeps.
    fn eval_at(&self, v: &Parts, grads: bool) -> Point<R> {
        let x = self.x0.zip(v, |x, v| {
            x.iter().zip(v).map(|(x, v)| x + self.dt * v).collect()
        });
        let mut xs = Array::from_vec(unflat_parts::<R>(&x)).named("x_implicit");
        let mut vs = Array::from_vec(unflat_parts::<R>(v)).named("v_implicit");
        if grads {
            xs = xs.requires_grad();
            vs = vs.requires_grad();
        }
        record(&self.c, xs, vs, &v.re)
    }

    /// See [`check_visited`]: every array the forces read at `p` that needs a derivative is
    /// the state or a private copy.
    fn check_visited(&self, p: &Point<R>, needs: Needs) -> Result<(), Error> {
        check_visited("ImplicitEuler", &self.c, &p.tape, &p.x, &p.v, needs)
    }
}

impl<R: Real> NewtonSystem for System<R> {
    type Point = Point<R>;

    fn eval(&self, v: &[f64]) -> Point<R> {
        self.eval_at(&Parts::real(v.to_vec()), false)
    }

    fn unknowns<'a>(&self, p: &'a Point<R>) -> &'a [f64] {
        &p.u
    }

    /// `v' - v0 - dt a` on free DOFs, 0 on pinned ones (m/s).
    fn residual(&self, p: &Point<R>) -> Vec<f64> {
        (0..self.v0.len())
            .map(|k| {
                if self.dofs.free[k] {
                    p.u[k] - self.v0[k] - self.dt * (p.a_val[k] + self.a_e[k])
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// `G = M e`, the incremental potential's gradient for conservative forces.
    fn gradient(&self, e: &[f64]) -> Vec<f64> {
        e.iter().zip(&self.dofs.mass).map(|(e, m)| m * e).collect()
    }

    fn worlds(&self) -> &[Range<usize>] {
        &self.dofs.worlds
    }

    /// `0.5 e^T M e` (J).
    fn merit(&self, e: &[f64], w: Range<usize>) -> f64 {
        0.5 * e[w.clone()]
            .iter()
            .zip(&self.dofs.mass[w])
            .map(|(e, m)| m * e * e)
            .sum::<f64>()
    }

    /// The largest of `|v0|`, `|v'|`, `dt |a|`, `dt |a_e|` over free DOFs (m/s).
    fn scale(&self, p: &Point<R>, w: Range<usize>) -> f64 {
        let free_max = |v: &[f64]| {
            v[w.clone()]
                .iter()
                .zip(&self.dofs.free[w.clone()])
                .filter(|(_, &f)| f)
                .fold(0.0f64, |m, (x, _)| m.max(x.abs()))
        };
        free_max(&self.v0)
            .max(free_max(&p.u))
            .max(self.dt * free_max(&p.a_val))
            .max(self.dt * free_max(&self.a_e))
    }

    /// The rounding of the positions, `eps |x|`, times the stiffness `dt |da/dx| ~ s / dt`,
    /// with `s = |M^-1 A d| / |d| = |e| / |d|` the stiffness ratio along the Newton step `d`
    /// (times a safety factor of 100).
    fn roundoff_floor(&self, e: &[f64], d: &[f64], w: Range<usize>) -> f64 {
        let dn = max_abs(&d[w.clone()]);
        let s = if dn > 0.0 {
            (max_abs(&e[w.clone()]) / dn).max(1.0)
        } else {
            1.0
        };
        100.0 * epsilon::<R>() * s * max_abs(&self.x0.re[w]).max(1.0) / self.dt
    }

    fn epsilon(&self) -> f64 {
        epsilon::<R>()
    }

    fn precond(&self) -> Option<&[f64]> {
        Some(&self.precond)
    }

    fn mask(&self, v: &mut [f64]) {
        self.dofs.mask(v)
    }

    /// `out = A u = M (u - dt (dt J_x + J_v) u)` (identity on pinned DOFs).
    fn apply(&self, p: &mut Point<R>, u: &[f64], out: &mut [f64]) {
        let ux: Vec<f64> = u
            .iter()
            .zip(&self.dofs.free)
            .map(|(&u, &f)| if f { u } else { 0.0 })
            .collect();
        let dx: Vec<f64> = ux.iter().map(|u| self.dt * u).collect();
        p.x.ensure_tangent().assign(&unflat::<R>(&dx));
        p.v.ensure_tangent().assign(&unflat::<R>(&ux));
        if let Err(e) = p.tape.tangent() {
            return self.failure.fail("tangent (forward-mode)", e, out);
        }
        let ad =
            p.a.tangent_buffer()
                .map_or_else(|| vec![0.0; out.len()], |t| flat(&t));
        for k in 0..out.len() {
            out[k] = if self.dofs.free[k] {
                self.dofs.mass[k] * (u[k] - self.dt * ad[k])
            } else {
                u[k]
            };
        }
    }

    /// `A^T u = M u - dt (dt J_x + J_v)^T M u` (identity on pinned DOFs).
    fn apply_t_parts(&self, p: &mut Point<R>, u: &[f64]) -> Result<Parts, Error> {
        // M is a constant of the host arithmetic, so `M u` is real.
        let mu = self.dofs.mass_product(&Parts::real(u.to_vec()), 1.0, false);
        let (gx, gv) = pull(p, &mu)?;
        let mut out = gx.zip(&gv, |gx, gv| {
            (0..gx.len())
                .map(|k| match self.dofs.free[k] {
                    true => -self.dt * (self.dt * gx[k] + gv[k]),
                    false => 0.0,
                })
                .collect()
        });
        // M u on free DOFs, the identity on pinned ones.
        for ((o, m), &free) in out.re.iter_mut().zip(&mu.re).zip(&self.dofs.free) {
            if free {
                *o += m;
            }
        }
        self.dofs.pinned_identity(&mut out.re, u);
        Ok(out)
    }

    fn failure(&self) -> &PassFailure {
        &self.failure
    }

    /// `-e = -M^-1 G`; its first step (length 1) is the explicit update `v0 + dt a`.
    fn steepest(&self, e: &[f64]) -> Vec<f64> {
        e.iter().map(|e| -e).collect()
    }

    /// Per world, the incremental potential's conservative part at `p` and its slope along
    /// `d`: `E_c = 0.5 (v' - v0)^T M (v' - v0) + U(x0 + dt v')` (J), with `U` the energies of
    /// the forces that have one ([`Force::energy`]), and `dE_c/ds = (M (v' - v0) + dt dU/dx)
    /// . d` (one tangent pass of the energy kernels).
    fn energy(&self, p: &Point<R>, d: &[f64]) -> Option<Result<Vec<(f64, f64)>, Error>> {
        let mut tape = Tape::new();
        let energy =
            self.c
                .model
                .elastic_energy(&mut tape, &particles(&p.x, &p.v), self.c.control.as_ref());
        let dx: Vec<f64> = d
            .iter()
            .zip(&self.dofs.free)
            .map(|(&d, &f)| if f { self.dt * d } else { 0.0 })
            .collect();
        p.x.ensure_tangent().assign(&unflat::<R>(&dx));
        p.v.ensure_tangent().assign(&vec![Vec3::zeros(); p.v.len()]);
        if let Err(e) = tape.tangent() {
            return Some(Err(self.failure.in_pass("energy tangent", e)));
        }
        let du = energy.tangent_buffer().map(|t| t.to_vec());
        let worlds = self.dofs.worlds.iter().enumerate().map(|(w, r)| {
            let (mut kinetic, mut slope) = (0.0, 0.0);
            for k in r.clone() {
                if self.dofs.free[k] {
                    let m_dv = self.dofs.mass[k] * (p.u[k] - self.v0[k]);
                    kinetic += 0.5 * m_dv * (p.u[k] - self.v0[k]);
                    slope += m_dv * d[k];
                }
            }
            let du = du.as_ref().map_or(0.0, |t| t[w].to_f64());
            (kinetic + energy.get(w).to_f64(), slope + du)
        });
        Some(Ok(worlds.collect()))
    }

    /// `sum m |a (x0 + dt v')|` over free DOFs: the forces times the positions, whose
    /// rounding the energies carry.
    fn work(&self, p: &Point<R>, w: Range<usize>) -> f64 {
        w.filter(|&k| self.dofs.free[k])
            .map(|k| self.dofs.mass[k] * (p.a_val[k] * (self.x0.re[k] + self.dt * p.u[k])).abs())
            .sum()
    }
}

impl ImplicitEuler {
    fn tolerance<R: Real>(&self) -> f64 {
        self.tolerance
            .unwrap_or_else(|| if is_f32::<R>() { 1e-4 } else { 1e-10 })
    }

    /// Newton with line search from `v' = v0` ([`newton`]); returns the solution `v'`.
    fn newton<R: Real>(&self, sys: &System<R>, stats: &mut NewtonStats) -> Result<Vec<f64>, Error> {
        let first = sys.eval(&sys.v0);
        sys.check_visited(&first, Needs::Gradient)?;
        let settings = NewtonSettings {
            tolerance: self.tolerance::<R>(),
            max_newton: self.max_newton,
            max_backtracks: self.max_backtracks,
            line_search: self.line_search,
            linear: &self.linear,
        };
        newton(sys, first, &settings, stats)
    }

    /// One step like [`Integrator::step`], also returning what the solve did.
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_kernels::integrators::ImplicitEuler;
    /// use adflex_runtime::{Tape, Vec3};
    ///
    /// // A very stiff spring (omega dt = 100) swinging under gravity: implicit Euler stays
    /// // bounded, and the spring barely stretches.
    /// let mut b = ModelBuilder::<f64>::new();
    /// let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    /// let c = b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    /// b.add_spring(a, c, 1e6, 0.0);
    /// let model = b.finalize();
    /// let mut tape = Tape::new();
    /// let (s, stats) = ImplicitEuler::default()
    ///     .step_with_stats(&model, &mut tape, &model.state(), None, 0.1)
    ///     .unwrap();
    /// assert!(stats.converged);
    /// assert!((s.x.get(1).norm() - 1.0).abs() < 1e-3);
    /// assert_eq!(tape.len(), 1); // one custom step, however many Newton iterations
    ///
    /// // One Newton iteration is not enough: an error by default, naming the solve.
    /// let capped = ImplicitEuler { max_newton: 1, ..ImplicitEuler::default() };
    /// let err = capped.step_with_stats(&model, &mut tape, &model.state(), None, 0.1).unwrap_err();
    /// assert!(err.to_string().contains("ImplicitEuler Newton did not converge"));
    /// ```
    ///
    /// Errors as [`Integrator::step`]: [`Error::InvalidInput`] for a bad `dt` or a NaN/Inf in
    /// the state or a parameter (any policy), [`Error::NotConverged`] if Newton stopped short of
    /// its tolerance under [`SolverPolicy::Error`] (under `Warn`/`Continue` the step is recorded
    /// and `stats.converged` is false).
    pub fn step_with_stats<R: Real>(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<(State<R>, NewtonStats), Error> {
        // Compiled in this crate (`precompiled`), not in the caller's.
        implicit_euler_step(self, model, tape, state, control, dt)
    }

    pub(crate) fn step_with_stats_generic<R: Real>(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<(State<R>, NewtonStats), Error> {
        if self.linearized {
            adflex_runtime::second_order::refuse_dual::<R>(
                "linearized implicit Euler's step",
                "use the full implicit Euler (`ImplicitEuler::default()`), whose \
                 implicit-function-theorem adjoint has its second-order term",
            )?;
        }
        let n = model.particle_count;
        let mut stats = NewtonStats::default();
        let dtf = check_dt("ImplicitEuler", dt)?;
        let first = tape.len();
        let (implicit, explicit) = self.split(model)?;
        let inv_mass = model.particle_inv_mass.to_vec();
        let (x0, v0) = (flat_parts(&state.x), flat_parts(&state.v));
        // The explicit forces' accelerations, for the solve (recorded on `tape` only once the
        // step succeeds: a failed step records nothing).
        let a_e = if explicit.is_empty() {
            Parts::real(vec![0.0; 3 * n])
        } else {
            flat_parts(&explicit_accelerations(
                model,
                &explicit,
                &mut Tape::new(),
                state,
                control,
            ))
        };
        let sys = System::new(
            copies(&implicit, control, false),
            x0.clone(),
            v0.re.clone(),
            &inv_mass,
            dtf,
            a_e.re.clone(),
        );
        let twin = Twin::of(&implicit, control).map(Arc::new);
        let explicit_params: Vec<Box<dyn AnyArray>> = explicit
            .iter()
            .flat_map(|f| f.params().into_iter().map(|(_, a)| a))
            .collect();
        let mut checked: Vec<&dyn AnyArray> = vec![&state.x, &state.v];
        checked.extend(explicit_params.iter().map(|a| &**a));
        check_inputs("ImplicitEuler", model, &checked, &sys.c.links)?;
        let v1 = if n == 0 {
            stats.converged = true;
            Vec::new()
        } else if self.linearized {
            self.linear_step(&sys, &mut stats)?
        } else if let Some(t) = &twin {
            // The forces read the copies where they must (checked in `R`); Newton on the twin.
            sys.check_visited(&sys.eval(&sys.v0), Needs::Gradient)?;
            self.newton(&twin_system(t, &x0, &v0.re, dtf, &a_e.re), &mut stats)?
        } else {
            self.newton(&sys, &mut stats)?
        };
        if !stats.converged {
            self.on_failure
                .handle(self.step_failure(dtf, &stats, model.worlds.len()))?;
        }

        let a_e_arr = (!explicit.is_empty())
            .then(|| explicit_accelerations(model, &explicit, tape, state, control));
        let x1 = Array::zeros(n).named("x");
        let v1a = Array::zeros(n).named("v");
        let mut shared = Shared {
            integrator: self.clone(),
            model: implicit,
            control: control.cloned(),
            x0: state.x.clone(),
            v0: state.v.clone(),
            x1: x1.clone(),
            v1: v1a.clone(),
            a_e: a_e_arr.clone(),
            a_e_val: sys.a_e.clone(),
            x0_val: x0,
            v0_val: v0.re,
            v1_val: Parts::real(v1),
            inv_mass,
            dt: dtf,
            twin,
        };
        if let (Some(dx0), Some(dv0)) = (&shared.x0_val.eps, &v0.eps) {
            // A Hessian-vector product's first sweep: the new velocities' derivative part
            // along the inputs' (the theorem's tangent).
            let dae = a_e.eps.unwrap_or_else(|| vec![0.0; 3 * n]);
            let dv1 = shared.velocity_tangent(dx0, dv0, &dae, Through::DerivativeParts)?;
            shared.v1_val.eps = Some(dv1);
        }
        let shared = Arc::new(shared);
        let v1_value = unflat_parts::<R>(&shared.v1_val);
        let x1_value = unflat_parts::<R>(&shared.x0_val.zip(&shared.v1_val, |x, v| {
            x.iter().zip(v).map(|(x, v)| x + dtf * v).collect()
        }));
        let originals = sys.c.links;
        let mut inputs: Vec<&dyn AnyArray> = vec![&state.x, &state.v];
        inputs.extend(originals.iter().map(|l| l.original()));
        if let Some(a) = &a_e_arr {
            inputs.push(a);
        }
        let (sb, st) = (shared.clone(), shared);
        tape.record_fn(
            if self.linearized {
                "linearized_implicit_euler"
            } else {
                "implicit_euler"
            },
            &inputs,
            &[&x1, &v1a],
            || {
                x1.assign(&x1_value);
                v1a.assign(&v1_value);
            },
            move || sb.backward(),
        )
        .dual_safe()
        .with_tangent(move || st.tangent());
        let bodies = step_bodies(model, tape, state, control, dt);
        let new = State {
            x: x1,
            v: v1a,
            bodies,
        };
        Ok((
            finish_step("ImplicitEuler", model, tape, first, state, control, new)?,
            stats,
        ))
    }

    /// The error of a step whose solve missed its tolerance, with advice that fits what
    /// stopped it.
    fn step_failure(&self, dt: f64, stats: &NewtonStats, worlds: usize) -> Error {
        let policy = "or set `on_failure` to SolverPolicy::Warn or Continue to accept the \
                      unconverged step";
        let (solver, hint) = if self.linearized && !stats.residual.is_finite() {
            (
                "ImplicitEuler (linearized) linear solve",
                "the solve's iterate is not finite: the state or a force overflowed or is NaN \
                 at the predicted state (a rollout that diverged in earlier steps, or a force \
                 that is singular there); take a smaller dt or check the forces"
                    .to_string(),
            )
        } else if self.linearized {
            (
                "ImplicitEuler (linearized) linear solve",
                format!(
                    "raise `linear.max_iter` (now {}) or loosen `linear.rel_tol` (now {:e}), \
                     take a smaller dt, {policy}",
                    self.linear.max_iter, self.linear.rel_tol
                ),
            )
        } else if !(stats.residual * stats.residual).is_finite() {
            (
                "ImplicitEuler Newton",
                format!(
                    "the residual (or its square) is not finite after {} iterations: the state \
                     or a force overflowed or is NaN (a rollout that diverged in earlier steps, \
                     or a force that is singular here); take a smaller dt or check the forces",
                    stats.newton_iterations
                ),
            )
        } else if stats.newton_iterations >= self.max_newton {
            (
                "ImplicitEuler Newton",
                format!(
                    "all {} Newton iterations ran: raise `max_newton`, loosen `tolerance`, \
                     take a smaller dt, {policy}",
                    self.max_newton
                ),
            )
        } else {
            (
                "ImplicitEuler Newton",
                format!(
                    "Newton stalled after {} of {} iterations (no step along the Newton or \
                     descent direction reduced the residual or the potential; raising \
                     `max_newton` will not help): take a smaller dt, check the forces for \
                     discontinuities (contact without smoothing), {policy}",
                    stats.newton_iterations, self.max_newton
                ),
            )
        };
        Error::NotConverged {
            solver: solver.into(),
            context: format!(
                "time step of dt = {dt} s{}; {} force evaluations, {} line-search halvings, \
                 {} BiCGSTAB fallbacks",
                with_world(stats.world, worlds),
                stats.force_evaluations,
                stats.backtracks,
                stats.fallbacks
            ),
            iterations: stats.newton_iterations,
            residual: stats.residual,
            tolerance: stats.tolerance,
            hint,
        }
    }

    /// The linearized step: one Newton step from `v' = v0`, `A d = -M e`; returns `v0 + d`.
    /// `stats` holds the linear solve's figures (its residual, tolerance and convergence).
    fn linear_step<R: Real>(
        &self,
        sys: &System<R>,
        stats: &mut NewtonStats,
    ) -> Result<Vec<f64>, Error> {
        let mut p = sys.eval(&sys.v0);
        sys.check_visited(&p, Needs::Gradient)?;
        stats.force_evaluations = 1;
        let e = sys.residual(&p);
        let active = vec![true; sys.dofs.worlds.len()];
        let (d, solved) = direction(sys, &mut p, &e, &self.linear, &active)?;
        let solve = linear_solve(&solved.into_iter().flatten().collect::<Vec<_>>());
        let (world, info) = solve.worst();
        stats.newton_iterations = 1;
        stats.linear_iterations = solve.products;
        stats.fallbacks = solve.fallbacks;
        stats.residual = info.residual;
        stats.tolerance = info.tolerance;
        stats.world = world;
        stats.converged = solve.failed().is_none() && d.iter().all(|d| d.is_finite());
        Ok(sys.v0.iter().zip(&d).map(|(v, d)| v + d).collect())
    }

    /// The settings of the adjoint and tangent solves.
    fn gradient_settings(&self) -> &SolveSettings {
        self.adjoint_linear.as_ref().unwrap_or(&self.linear)
    }

    /// Checks a gradient solve (adjoint or tangent) per the policy.
    fn check_gradient_solve(&self, what: &str, solve: &LinearSolve) -> Result<(), Error> {
        let Some((world, info)) = solve.failed() else {
            return Ok(());
        };
        let s = self.gradient_settings();
        self.on_failure.handle(Error::NotConverged {
            solver: format!("ImplicitEuler {what} linear solve (CG, then BiCGSTAB)"),
            context: world_context(world, solve.infos.len()),
            iterations: info.iterations,
            residual: info.residual,
            tolerance: info.tolerance,
            hint: format!(
                "raise `max_iter` (now {}) or loosen `rel_tol` (now {:e}) of \
                 `adjoint_linear` (or `linear`), take a smaller dt, or set `on_failure` to \
                 SolverPolicy::Warn or Continue to accept the approximate gradient",
                s.max_iter, s.rel_tol
            ),
        })
    }
}

/// The system, the point and `lambda` of an adjoint solve.
type AdjointSolve<R> = (System<R>, Point<R>, Parts);

/// What the backward and tangent of a step need.
struct Shared<R: Real> {
    integrator: ImplicitEuler,
    model: Model<R>,
    control: Option<Control<R>>,
    x0: Array<Vec3<R>>,
    v0: Array<Vec3<R>>,
    x1: Array<Vec3<R>>,
    v1: Array<Vec3<R>>,
    /// The explicit forces' accelerations on the caller's tape (an implicit-explicit split).
    a_e: Option<Array<Vec3<R>>>,
    a_e_val: Vec<f64>,
    /// The positions at the start, with their derivative parts in `Dual`.
    x0_val: Parts,
    v0_val: Vec<f64>,
    /// The new velocities, with their derivative parts in `Dual`.
    v1_val: Parts,
    inv_mass: Vec<R>,
    dt: f64,
    /// In `Dual`, the model in `f64` that the linear solves run on.
    twin: Option<Arc<Twin>>,
}

impl<R: Real> Shared<R> {
    /// The system on the twin, if there is one.
    fn twin_system(&self) -> Option<System<f64>> {
        let t = self.twin.as_ref()?;
        Some(twin_system(
            t,
            &self.x0_val,
            &self.v0_val,
            self.dt,
            &self.a_e_val,
        ))
    }

    fn system(&self, grads: bool) -> System<R> {
        System::new(
            copies(&self.model, self.control.as_ref(), grads),
            self.x0_val.clone(),
            self.v0_val.clone(),
            &self.inv_mass,
            self.dt,
            self.a_e_val.clone(),
        )
    }

    /// The incoming adjoints of the step: `(x'_bar, v'_bar)`, or `None` if neither has one.
    fn incoming(&self) -> Option<(Parts, Parts)> {
        let (gx1, gv1) = (self.x1.grad_buffer(), self.v1.grad_buffer());
        if gx1.is_none() && gv1.is_none() {
            return None;
        }
        let zeros = self.x0_val.map(|x| vec![0.0; x.len()]);
        Some((
            gx1.map_or_else(|| zeros.clone(), |g| flat_parts(&g)),
            gv1.map_or_else(|| zeros.clone(), |g| flat_parts(&g)),
        ))
    }

    /// The input tangents: `(dx, dv, da_e)` (zeros where an input has none).
    fn input_tangents(&self) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let m = self.v0_val.len();
        let t = |a: Option<&Array<Vec3<R>>>| {
            a.and_then(|a| a.tangent_buffer())
                .map_or_else(|| vec![0.0; m], |t| flat(&t))
        };
        (t(Some(&self.x0)), t(Some(&self.v0)), t(self.a_e.as_ref()))
    }

    /// Writes the output tangents `dx' = dx + dt dv'`, `dv'`.
    fn set_output_tangents(&self, dx0: &[f64], dv1: &[f64]) {
        let dx1: Vec<f64> = (0..dv1.len()).map(|k| dx0[k] + self.dt * dv1[k]).collect();
        if let Some(t) = self.x1.tangent_buffer() {
            t.assign(&unflat::<R>(&dx1));
        }
        if let Some(t) = self.v1.tangent_buffer() {
            t.assign(&unflat::<R>(dv1));
        }
    }

    /// The step `d = v' - v0` of the linearized method, and per DOF the scale `eps` of the
    /// perturbations `v0 +- eps d` (positions `+- eps dt d`) whose central difference gives
    /// the second-order term: per world, `eps_R^(1/3)` relative to the world's state, on the
    /// positions (`eps dt |d| <= eps_R^(1/3) max(1, |x0|)`) and on the velocities
    /// (`eps |d| <= eps_R^(1/3) max(|v0|, |d|)`: contact and friction change over small
    /// velocities), the step that balances truncation and rounding; 0 in a world where
    /// `d = 0` (no second-order term there). `None` if `d = 0` everywhere.
    fn linear_direction(&self) -> Option<(Vec<f64>, Vec<f64>)> {
        let d: Vec<f64> = self
            .v1_val
            .re
            .iter()
            .zip(&self.v0_val)
            .map(|(a, b)| a - b)
            .collect();
        let mut eps = vec![0.0; d.len()];
        for w in Dofs::new(&self.model, &self.inv_mass).worlds {
            let dn = max_abs(&d[w.clone()]);
            if !(dn > 0.0) {
                continue;
            }
            let on_x = max_abs(&self.x0_val.re[w.clone()]).max(1.0) / (self.dt * dn);
            let on_v = max_abs(&self.v0_val[w.clone()]).max(dn) / dn;
            eps[w].fill(epsilon::<R>().cbrt() * on_x.min(on_v));
        }
        eps.iter().any(|&e| e > 0.0).then_some((d, eps))
    }

    /// `v0 + s eps d`, per DOF.
    fn shifted(&self, d: &[f64], eps: &[f64], s: f64) -> Vec<f64> {
        (0..d.len())
            .map(|k| self.v0_val[k] + s * eps[k] * d[k])
            .collect()
    }

    /// The adjoint solve of both methods: the system with gradient-carrying copies, the forces
    /// recorded at `v` (`x = x0 + dt v`), and `lambda` with `A^T lambda = b` there (masked;
    /// in `Dual`, with the theorem's second-order term, see
    /// [`solve_transposed`](crate::solver::newton::solve_transposed)); the
    /// copies' gradients zeroed (the solve's products accumulated into them).
    fn adjoint_solve(&self, v: &Parts, b: &Parts) -> Result<AdjointSolve<R>, Error> {
        let sys = self.system(true);
        let mut p = sys.eval_at(v, true);
        sys.check_visited(&p, Needs::Gradient)?;
        let rhs = b.map(|b| {
            let mut r = b.to_vec();
            sys.mask(&mut r);
            r
        });
        let settings = self.integrator.gradient_settings();
        let check = |info: &LinearSolve| self.integrator.check_gradient_solve("adjoint", info);
        let twin = self.twin_system();
        let mut tp = twin
            .as_ref()
            .map(|t| t.eval_at(&Parts::real(v.re.clone()), true));
        let twin = twin.as_ref().zip(tp.as_mut());
        let lambda = solve_transposed_on(&sys, &mut p, &rhs, twin, settings, check)?;
        for l in &sys.c.links {
            l.zero_copy_grad();
        }
        Ok((sys, p, lambda))
    }

    /// Adds a backward's results into the inputs' gradients: `x0`, `v0`, the explicit
    /// accelerations (`dt M lambda`, `a_e_bar`) and the parameters (from their copies).
    fn accumulate(&self, sys: &System<R>, gx0: &Parts, gv0: &Parts, a_e_bar: &Parts) {
        add_into(&self.x0, gx0);
        add_into(&self.v0, gv0);
        if let Some(a) = &self.a_e {
            add_into(a, a_e_bar);
        }
        for l in &sys.c.links {
            l.add_grad();
        }
    }

    fn backward(&self) -> Result<(), Error> {
        match self.integrator.linearized {
            true => self.backward_linearized(),
            false => self.backward_newton(),
        }
    }

    fn tangent(&self) -> Result<(), Error> {
        adflex_runtime::second_order::refuse_dual::<R>(
            "implicit Euler's forward mode",
            crate::solver::parts::NO_DUAL_TANGENT,
        )?;
        match self.integrator.linearized {
            true => self.tangent_linearized(),
            false => self.tangent_newton(),
        }
    }

    /// Reverse mode of the linearized step `v' = v0 + d`, `B d = dt (a(p) + a_e)` with
    /// `B = I - dt (dt J_x + J_v)` at `p = (x0 + dt v0, v0)` (see the module docs): with
    /// `b = v'_bar + dt x'_bar` and `A^T lambda = b` (`A = M B`), `mu = M lambda`, the inputs
    /// get `dt mu^T da` (one adjoint pass at `p`) plus the second-order term
    /// `dt mu^T d(J w)`, `w = (dt d, d)`, by a central difference of two adjoint passes at
    /// `p +- eps w`.
    /// Real parts only: the linearized step refuses `Dual`.
    fn backward_linearized(&self) -> Result<(), Error> {
        let Some((gx1, gv1)) = self.incoming() else {
            return Ok(());
        };
        let (gx1, gv1) = (gx1.re, gv1.re);
        let (m, dt) = (self.v0_val.len(), self.dt);
        let b: Vec<f64> = (0..m).map(|k| gv1[k] + dt * gx1[k]).collect();
        let v0 = Parts::real(self.v0_val.clone());
        let (sys, mut p, lambda) = self.adjoint_solve(&v0, &Parts::real(b.clone()))?;
        let mu: Vec<f64> = (0..m).map(|k| sys.dofs.mass[k] * lambda.re[k]).collect();
        let seed = Parts::real(mu.iter().map(|u| dt * u).collect());
        let adjoint = |e| sys.failure.in_pass("adjoint (reverse-mode)", e);
        let (gx, gv) = pull(&mut p, &seed).map_err(adjoint)?;
        let (mut gx, mut gv) = (gx.re, gv.re);
        if let Some((d, eps)) = self.linear_direction() {
            let c = |k: usize| match eps[k] > 0.0 {
                true => dt / (2.0 * eps[k]),
                false => 0.0,
            };
            for s in [1.0, -1.0] {
                let mut q = sys.eval_at(&Parts::real(self.shifted(&d, &eps, s)), true);
                let seed = Parts::real((0..m).map(|k| s * c(k) * mu[k]).collect());
                let (qx, qv) = pull(&mut q, &seed).map_err(adjoint)?;
                gx.iter_mut().zip(qx.re).for_each(|(g, q)| *g += q);
                gv.iter_mut().zip(qv.re).for_each(|(g, q)| *g += q);
            }
        }
        let gx0: Vec<f64> = (0..m).map(|k| gx1[k] + gx[k]).collect();
        let gv0: Vec<f64> = (0..m).map(|k| b[k] + dt * gx[k] + gv[k]).collect();
        self.accumulate(&sys, &Parts::real(gx0), &Parts::real(gv0), &seed);
        Ok(())
    }

    /// Forward mode of the linearized step: `A dd = M dt (a_dot + da_e + (J w)_dot)`, the
    /// last term by a central difference of two tangent passes at `p +- eps w`.
    fn tangent_linearized(&self) -> Result<(), Error> {
        let (m, dt) = (self.v0_val.len(), self.dt);
        let (dx0, dv0, dae) = self.input_tangents();
        let sys = self.system(false);
        let dxp: Vec<f64> = (0..m).map(|k| dx0[k] + dt * dv0[k]).collect();
        let direction = self.linear_direction();
        let mut points = vec![(vec![1.0; m], sys.eval(&self.v0_val))];
        sys.check_visited(&points[0].1, Needs::Tangent)?;
        if let Some((d, eps)) = &direction {
            for s in [1.0, -1.0] {
                let c = eps.iter().map(|&e| match e > 0.0 {
                    true => s * (1.0 / (2.0 * e)),
                    false => 0.0,
                });
                points.push((c.collect(), sys.eval(&self.shifted(d, eps, s))));
            }
        }
        for l in &sys.c.links {
            l.share_tangent(true);
        }
        let mut rhs: Vec<f64> = (0..m).map(|k| dt * dae[k]).collect();
        let mut ran = Ok(());
        for (c, q) in &mut points {
            q.x.ensure_tangent().assign(&unflat::<R>(&dxp));
            q.v.ensure_tangent().assign(&unflat::<R>(&dv0));
            ran = ran.and(q.tape.tangent());
            if let Some(t) = q.a.tangent_buffer() {
                let ad = flat(&t);
                (0..m).for_each(|k| rhs[k] += c[k] * dt * ad[k]);
            }
        }
        for l in &sys.c.links {
            l.share_tangent(false);
        }
        ran.map_err(|e| sys.failure.in_pass("tangent (forward-mode)", e))?;
        let mut rhs: Vec<f64> = (0..m).map(|k| sys.dofs.mass[k] * rhs[k]).collect();
        sys.mask(&mut rhs);
        let mut p = points.swap_remove(0).1;
        let settings = self.integrator.gradient_settings();
        let (dd, solve) = solve_linear(&sys, &mut p, &rhs, settings, false)?;
        self.integrator.check_gradient_solve("tangent", &solve)?;
        let dv1: Vec<f64> = (0..m).map(|k| dv0[k] + dd[k]).collect();
        self.set_output_tangents(&dx0, &dv1);
        Ok(())
    }

    /// Reverse mode by the implicit function theorem (see the module docs). Fails per the
    /// policy if the adjoint solve misses its tolerance (nothing is accumulated then). In
    /// `Dual`, at the new state with its derivative part, every map below acts on both parts.
    fn backward_newton(&self) -> Result<(), Error> {
        let Some((gx1, gv1)) = self.incoming() else {
            return Ok(());
        };
        let dt = self.dt;
        let b = gv1.zip(&gx1, |gv, gx| {
            gv.iter().zip(gx).map(|(v, x)| v + dt * x).collect()
        });
        let (sys, mut p, lambda) = self.adjoint_solve(&self.v1_val, &b)?;
        let free = &sys.dofs.free;
        let seed = sys.dofs.mass_product(&lambda, dt, false);
        let (gx, gv) =
            pull(&mut p, &seed).map_err(|e| sys.failure.in_pass("adjoint (reverse-mode)", e))?;
        let gx0 = gx1.zip(&gx, |a, b| a.iter().zip(b).map(|(a, b)| a + b).collect());
        // On pinned DOFs v' = v, which also moves x' = x + dt v.
        let pinned = b.zip(&gx, |b, gx| {
            (0..b.len()).map(|k| b[k] + dt * gx[k]).collect()
        });
        let pinned = pinned.zip(&gv, |p, gv| p.iter().zip(gv).map(|(p, g)| p + g).collect());
        let gv0 = sys
            .dofs
            .mass_product(&lambda, 1.0, false)
            .zip(&pinned, |ml, p| {
                (0..ml.len())
                    .map(|k| if free[k] { ml[k] } else { p[k] })
                    .collect()
            });
        self.accumulate(&sys, &gx0, &gv0, &seed);
        Ok(())
    }

    /// Forward mode (see [`Shared::velocity_tangent`]).
    fn tangent_newton(&self) -> Result<(), Error> {
        let (dx0, dv0, dae) = self.input_tangents();
        let dv1 = self.velocity_tangent(&dx0, &dv0, &dae, Through::Tangents)?;
        self.set_output_tangents(&dx0, &dv1);
        Ok(())
    }

    /// The new velocities' derivative: `A dv' = M (dv + dt (a_dot + da_e))`, `a_dot` the
    /// derivative of the accelerations at fixed `v'` for the inputs' (`dx`, `dv`, the
    /// parameters'), taken `through` their tangents or their derivative parts. Fails per the
    /// policy if the solve misses its tolerance.
    fn velocity_tangent(
        &self,
        dx0: &[f64],
        dv0: &[f64],
        dae: &[f64],
        through: Through,
    ) -> Result<Vec<f64>, Error> {
        let (m, dt) = (self.v0_val.len(), self.dt);
        let sys = self.system(false);
        let dvp: Vec<f64> = (0..m)
            .map(|k| if sys.dofs.free[k] { 0.0 } else { dv0[k] })
            .collect();
        let v1 = Parts::real(self.v1_val.re.clone());
        let (mut p, ad) = match through {
            Through::Tangents => {
                let mut p = sys.eval_at(&v1, false);
                sys.check_visited(&p, Needs::Tangent)?;
                let dxp: Vec<f64> = (0..m).map(|k| dx0[k] + dt * dvp[k]).collect();
                let ad = acceleration_tangent(&sys.c, &mut p, &dxp, &dvp, &sys.failure)?;
                (p, ad)
            }
            Through::DerivativeParts => {
                // The positions' derivative part is `dx0 + dt dvp` (the system's `x0`'s).
                let p = sys.eval_at(
                    &Parts {
                        eps: Some(dvp),
                        ..v1.clone()
                    },
                    false,
                );
                let ad = flat_parts(&p.a).eps.unwrap_or_else(|| vec![0.0; m]);
                (p, ad)
            }
        };
        let mut rhs: Vec<f64> = (0..m)
            .map(|k| sys.dofs.mass[k] * (dv0[k] + dt * (ad[k] + dae[k])))
            .collect();
        sys.mask(&mut rhs);
        let settings = self.integrator.gradient_settings();
        let (mut dv1, solve) = match self.twin_system() {
            Some(twin) => solve_linear(&twin, &mut twin.eval(&v1.re), &rhs, settings, false)?,
            None => solve_linear(&sys, &mut p, &rhs, settings, false)?,
        };
        self.integrator.check_gradient_solve("tangent", &solve)?;
        for k in 0..m {
            if !sys.dofs.free[k] {
                dv1[k] = dv0[k];
            }
        }
        Ok(dv1)
    }
}

impl<R: Real> Integrator<R> for ImplicitEuler {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error> {
        Ok(self.step_with_stats(model, tape, state, control, dt)?.0)
    }
}

precompiled! {
    /// [`ImplicitEuler::step_with_stats`].
    fn implicit_euler_step(
        this: &ImplicitEuler,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<(State<R>, NewtonStats), Error> {
        this.step_with_stats_generic(model, tape, state, control, dt)
    }
}
