//! Statics: the equilibrium `x*(p)` of a model under its forces and gravity, `f(x*; p) = 0`
//! for every free particle (pinned particles stay where they are), and its gradient with
//! respect to every parameter by the implicit function theorem.
//!
//! # The solve
//!
//! The unknowns are the positions of the free particles (inverse mass `w > 0`). With
//! `a = w f + g` the accelerations of [`Model::eval_accelerations`] at zero velocity, the
//! residual is the net force `r(x) = M a(x) = f(x) + M g` (N) and its Jacobian is `-K`, `K =
//! -dr/dx` the stiffness matrix (symmetric for springs, membranes, tetrahedra). Each Newton
//! iteration solves `K d = r` by [`krylov::solve`](crate::solver::krylov::solve) (CG, then BiCGSTAB if CG meets negative
//! curvature, e.g. from compressed springs) and moves `x += alpha d`, with a backtracking line
//! search on `|r|^2` (or on the potential energy, whose gradient is `-r`, when the residual
//! does not decrease along `d`). `K` is never formed: `K u` is one pass of the **tangent**
//! kernels of the force model, recorded once per iterate on a scratch tape, exactly as
//! [`ImplicitEuler`](crate::integrators::ImplicitEuler) does, with private copies of the
//! parameter arrays ([`Force::params_mut`](crate::forces::Force::params_mut),
//! [`Param::substitute`](crate::forces::Param::substitute)).
//!
//! # The gradient
//!
//! [`Equilibrium::solve`] records **one** custom step on the caller's tape
//! ([`Tape::record_fn`]); the Newton iterations are not recorded. Since `r(x*(p), p) = 0`,
//! `dx*/dp = K^-1 dr/dp`, so with the incoming adjoint `x*_bar` the backward solves the
//! transposed system `K^T lambda = x*_bar` (free DOFs) matrix-free with the **adjoint** kernels
//! and adds `lambda^T dr/dp` into the gradient of every parameter array of the forces (rest
//! lengths, stiffnesses, ...) and of the inverse masses (at equilibrium `a = 0`, so
//! `lambda^T dr/dp = (M lambda)^T da/dp`: one adjoint pass seeded with `M lambda`). The pinned
//! particles' positions are inputs too: their gradient is `x*_bar + lambda^T dr/dx_pinned`,
//! added into the guess's `x` at the pinned particles. The free particles' entries of the
//! guess are only a starting point and get nothing.
//!
//! Forward mode (for [`Tape::tangent`], `Tape::jvp` and Gauss-Newton products) is the same
//! theorem the other way: `K dx* = M da`, `da` the tangent of the accelerations at `x*` for
//! the parameters' and the pins' tangents, one linear solve with the tangent kernels.
//!
//! In [`Dual`] (Hessian-vector products, [`adflex_runtime::second_order`]) the solve gives
//! `x*` its derivative part by that forward rule, and the backward runs at `x*` with its
//! derivative part, solving `K^T lambda = x*_bar` part by part (`K0^T lambda1 = x*_bar1 -
//! K1^T lambda0`: the theorem's second-order term). A direction on the inverse masses needs no
//! more (`M` cancels in the solve). Newton's iterations and the linear solves run on a copy of
//! the model in `f64` ([`Force::to_f64`](crate::forces::Force::to_f64)), as implicit Euler's
//! do.
//!
//! The equilibrium found is the one Newton reaches from the guess: a structure can have
//! several (a cable hanging or standing as an arch). Start near the one you mean (and warm
//! start from the previous solution in an optimization loop).
//!
//! # Failures
//!
//! A Newton iteration that stops above its tolerance is [`Error::NotConverged`] naming
//! `"Equilibrium Newton"` (nothing is recorded), and an adjoint solve that does is
//! `tape.backward`'s error naming `"Equilibrium adjoint linear solve"` (a tangent solve's,
//! `tape.tangent`'s naming `"Equilibrium tangent linear solve"`), unless
//! [`Equilibrium::on_failure`] says otherwise. A NaN or infinite position or parameter, or a
//! model with rigid bodies (which this solve does not handle), is [`Error::InvalidInput`]. A
//! force whose tangent or adjoint pass fails (a custom step without a tangent) is that pass's
//! error, naming the force and `"Equilibrium"`, from `solve` or from `tape.backward`.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_kernels::statics::Equilibrium;
//! use adflex_macros::diff_kernel;
//! use adflex_runtime::prelude::*;
//!
//! // A mass of 1 kg hanging from a pinned point on a spring of 100 N/m, rest length 1 m:
//! // it rests 1 + 9.8 / 100 m below the pin.
//! let mut b = ModelBuilder::<f64>::new();
//! let pin = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
//! let m = b.add_particle(Vec3::new(0.0, -1.0, 0.0), Vec3::zeros(), 1.0);
//! b.add_spring(pin, m, 100.0, 0.0);
//! let model = b.finalize();
//! let rest = model.param::<f64>("springs", "rest").unwrap().requires_grad();
//!
//! let mut tape = Tape::new();
//! let eq = Equilibrium::default().solve(&model, &mut tape, &model.state()).unwrap();
//! assert!((eq.x.get(1).y + 1.098).abs() < 1e-12);
//! assert_eq!(tape.len(), 1); // one custom step, however many Newton iterations
//!
//! // d(height)/d(rest) = -1: a longer spring hangs lower.
//! #[diff_kernel]
//! fn height(x: &Array<Vec3<f64>>, out: &Array<f64>) {
//!     out[0] = x[1].y;
//! }
//! let h = Array::zeros(1);
//! tape.launch(height, 1, (&eq.x, &h));
//! tape.backward(&h).unwrap();
//! assert!((rest.grad().unwrap().get(0) + 1.0).abs() < 1e-9);
//! ```

use std::ops::Range;
use std::sync::Arc;

use adflex_runtime::prelude::*;

use crate::integrators::common::{
    acceleration_tangent, add_into, check_inputs, check_visited, copies, epsilon, flat, flat_parts,
    forces_only, is_f32, pull, record, unflat, unflat_parts, Copies, Dofs, Needs, Point, Through,
    Twin,
};
use crate::integrators::SolverPolicy;
use crate::model::Model;
use crate::solver::krylov::SolveSettings;
use crate::solver::newton::{
    dot, max_abs, newton, solve_linear, solve_transposed_on, with_world, world_context,
    LinearSolve, NewtonSettings, NewtonSystem, Parts, PassFailure,
};
pub use crate::solver::NewtonStats;
use crate::state::State;

/// A static equilibrium solver: Newton with matrix-free Krylov solves and a line search,
/// differentiated by the implicit function theorem (see the [module docs](self)).
#[derive(Clone, Debug, PartialEq)]
pub struct Equilibrium {
    /// Newton stops when `max |r_k| <= tolerance * scale` (N) over the free DOFs, `scale` the
    /// largest of the particles' weights `m |g|` and the forces `|f|` on them, each over one
    /// world's particles (each world is solved by its own iteration). `None` (default):
    /// `1e-10` in f64, `1e-4` in f32.
    pub tolerance: Option<f64>,
    /// Maximum Newton iterations (default 50).
    pub max_newton: usize,
    /// Stopping rule of the Newton linear solves, and of the adjoint solve unless
    /// `adjoint_linear` is set (default: relative `1e-10`, 1000 iterations). A Newton linear
    /// solve that misses it is not an error by itself (inexact Newton).
    pub linear: SolveSettings,
    /// Stopping rule of the gradient's linear solve (`K^T lambda = x_bar`); `None` (default):
    /// `linear`. A solve that misses it fails per `on_failure`.
    pub adjoint_linear: Option<SolveSettings>,
    /// Maximum halvings of the step in the line search (default 30).
    pub max_backtracks: usize,
    /// What a solve that misses its tolerance does (default [`SolverPolicy::Error`]): the
    /// Newton iteration ([`Error::NotConverged`] from `solve`, nothing recorded) and the
    /// adjoint solve (an error from `tape.backward`). `Warn` prints the figures and uses the
    /// result, `Continue` uses it silently.
    pub on_failure: SolverPolicy,
}

impl Default for Equilibrium {
    fn default() -> Self {
        Equilibrium {
            tolerance: None,
            max_newton: 50,
            linear: SolveSettings::default(),
            adjoint_linear: None,
            max_backtracks: 30,
            on_failure: SolverPolicy::Error,
        }
    }
}

/// What one [`Equilibrium`] solve did (the shared Newton solver's figures; `residual` and
/// `tolerance` in N).
pub type EquilibriumStats = NewtonStats;

/// The nonlinear system `r(x) = M a(x) = 0` over the free DOFs.
struct System<R: Real> {
    c: Copies<R>,
    /// The guess (pinned DOFs: the pins).
    x0: Vec<f64>,
    dofs: Dofs,
    /// Gravity per DOF (m/s^2).
    g: Vec<f64>,
    failure: PassFailure,
}

impl<R: Real> System<R> {
    fn new(c: Copies<R>, x0: Vec<f64>, inv_mass: &[R]) -> Self {
        // Each particle's world's gravity.
        let gravity = c.model.gravity_per_world().to_vec();
        let world = c.model.particle_world.to_vec();
        let g = (0..x0.len()).map(|k| gravity[world[k / 3] as usize][k % 3].to_f64());
        System {
            dofs: Dofs::new(&c.model, inv_mass),
            g: g.collect(),
            c,
            x0,
            failure: PassFailure::new("Equilibrium"),
        }
    }

    /// Records the accelerations at `x` (zero velocities) on a new tape; with derivative
    /// parts, at the point of a Hessian-vector product's second sweep.
    fn eval_at(&self, x: &Parts, grads: bool) -> Point<R> {
        let n = x.re.len() / 3;
        let mut xs = Array::from_vec(unflat_parts::<R>(x)).named("x_equilibrium");
        let vs = Array::zeros(n).named("v_equilibrium");
        if grads {
            xs = xs.requires_grad();
        }
        record(&self.c, xs, vs, &x.re)
    }
}

impl<R: Real> NewtonSystem for System<R> {
    type Point = Point<R>;

    fn eval(&self, x: &[f64]) -> Point<R> {
        self.eval_at(&Parts::real(x.to_vec()), false)
    }

    fn unknowns<'a>(&self, p: &'a Point<R>) -> &'a [f64] {
        &p.u
    }

    /// `r = M a` on free DOFs, 0 on pinned ones (N).
    fn residual(&self, p: &Point<R>) -> Vec<f64> {
        (0..self.dofs.mass.len())
            .map(|k| {
                if self.dofs.free[k] {
                    self.dofs.mass[k] * p.a_val[k]
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// `-r`, the gradient of the potential energy.
    fn gradient(&self, r: &[f64]) -> Vec<f64> {
        r.iter().map(|r| -r).collect()
    }

    fn worlds(&self) -> &[Range<usize>] {
        &self.dofs.worlds
    }

    /// `0.5 |r|^2` (N^2).
    fn merit(&self, r: &[f64], w: Range<usize>) -> f64 {
        0.5 * dot(&r[w.clone()], &r[w])
    }

    /// The force scale at `p`: the largest weight `m |g|` and force `|f| = |m (a - g)|` (N).
    fn scale(&self, p: &Point<R>, w: Range<usize>) -> f64 {
        w.filter(|&k| self.dofs.free[k]).fold(0.0f64, |s, k| {
            let m = self.dofs.mass[k];
            s.max((m * self.g[k]).abs())
                .max((m * (p.a_val[k] - self.g[k])).abs())
        })
    }

    /// `eps |x|` times the stiffness `|K d| / |d|` along the Newton step `d` (with `K d = r`),
    /// times a safety factor of 100 (N).
    fn roundoff_floor(&self, r: &[f64], d: &[f64], w: Range<usize>) -> f64 {
        let dn = max_abs(&d[w.clone()]);
        let k = if dn > 0.0 {
            max_abs(&r[w.clone()]) / dn
        } else {
            0.0
        };
        100.0 * epsilon::<R>() * k * max_abs(&self.x0[w]).max(1.0)
    }

    fn epsilon(&self) -> f64 {
        epsilon::<R>()
    }

    fn precond(&self) -> Option<&[f64]> {
        None
    }

    fn mask(&self, v: &mut [f64]) {
        self.dofs.mask(v)
    }

    /// `out = K u = -M da/dx u` (identity on pinned DOFs) by one tangent pass.
    fn apply(&self, p: &mut Point<R>, u: &[f64], out: &mut [f64]) {
        let ux: Vec<f64> = u
            .iter()
            .zip(&self.dofs.free)
            .map(|(&u, &f)| if f { u } else { 0.0 })
            .collect();
        p.x.ensure_tangent().assign(&unflat::<R>(&ux));
        p.v.ensure_tangent(); // zero: the velocities stay 0
        if let Err(e) = p.tape.tangent() {
            return self.failure.fail("tangent (forward-mode)", e, out);
        }
        let ad =
            p.a.tangent_buffer()
                .map_or_else(|| vec![0.0; out.len()], |t| flat(&t));
        for k in 0..out.len() {
            out[k] = if self.dofs.free[k] {
                -self.dofs.mass[k] * ad[k]
            } else {
                u[k]
            };
        }
    }

    /// `K^T u = -(da/dx)^T M u` (identity on pinned DOFs) by one adjoint pass.
    fn apply_t_parts(&self, p: &mut Point<R>, u: &[f64]) -> Result<Parts, Error> {
        let (gx, _) = pull(
            p,
            &self.dofs.mass_product(&Parts::real(u.to_vec()), 1.0, true),
        )?;
        let mut out = gx.map(|g| {
            (0..g.len())
                .map(|k| if self.dofs.free[k] { -g[k] } else { 0.0 })
                .collect()
        });
        self.dofs.pinned_identity(&mut out.re, u);
        Ok(out)
    }

    fn failure(&self) -> &PassFailure {
        &self.failure
    }

    /// The net force `r = -G`.
    fn steepest(&self, r: &[f64]) -> Vec<f64> {
        r.to_vec()
    }

    /// Per world, the step of the quadratic model where `K` is positive along `d` (one
    /// tangent pass for all worlds), else a tenth of the world's size.
    fn steepest_lengths(
        &self,
        p: &mut Point<R>,
        d: &[f64],
        slopes: &[Option<f64>],
        stats: &mut NewtonStats,
    ) -> Vec<f64> {
        let mut kd = vec![0.0; d.len()];
        self.apply(p, d, &mut kd);
        stats.linear_iterations += 1;
        self.mask(&mut kd);
        let lengths = self.dofs.worlds.iter().zip(slopes).map(|(w, slope)| {
            let Some(slope) = slope else {
                return 1.0;
            };
            let curvature = dot(&d[w.clone()], &kd[w.clone()]);
            if curvature > 0.0 {
                -slope / curvature
            } else {
                0.1 * max_abs(&self.x0[w.clone()]).max(1.0) / max_abs(&d[w.clone()])
            }
        });
        lengths.collect()
    }
}

impl Equilibrium {
    fn tolerance<R: Real>(&self) -> f64 {
        self.tolerance
            .unwrap_or_else(|| if is_f32::<R>() { 1e-4 } else { 1e-10 })
    }

    /// The settings of the adjoint solve.
    fn gradient_settings(&self) -> &SolveSettings {
        self.adjoint_linear.as_ref().unwrap_or(&self.linear)
    }

    /// Solves for the equilibrium from `guess` (its free particles' positions are the starting
    /// point; its pinned particles' positions are the pins) and records it on `tape` as one
    /// custom step whose backward is the implicit function theorem (see the
    /// [module docs](self)). The state returned has the equilibrium positions and zero
    /// velocities (new arrays).
    ///
    /// Errors: [`Error::InvalidInput`] for a NaN/Inf in the guess or a parameter, or a model
    /// with rigid bodies; [`Error::NotConverged`] (`"Equilibrium Newton"`) if Newton stopped
    /// above its tolerance under [`SolverPolicy::Error`].
    pub fn solve<R: Real>(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        guess: &State<R>,
    ) -> Result<State<R>, Error> {
        Ok(self.solve_with_stats(model, tape, guess)?.0)
    }

    /// [`Equilibrium::solve`], also returning what the solve did.
    pub fn solve_with_stats<R: Real>(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        guess: &State<R>,
    ) -> Result<(State<R>, EquilibriumStats), Error> {
        let n = model.particle_count;
        if model.bodies.is_some() {
            return Err(Error::InvalidInput {
                what: "model.bodies".into(),
                message: "Equilibrium: the model has rigid bodies, which the static solve does \
                          not handle (it solves for the particles only)"
                    .into(),
            });
        }
        if guess.x.len() != n {
            return Err(Error::InvalidInput {
                what: "guess.x".into(),
                message: format!(
                    "Equilibrium: the guess has {} positions, the model {n} particles",
                    guess.x.len()
                ),
            });
        }
        let inv_mass = model.particle_inv_mass.to_vec();
        let x0 = flat(&guess.x);
        let sys = System::new(copies(model, None, false), x0, &inv_mass);
        check_inputs("Equilibrium", model, &[&guess.x], &sys.c.links)?;
        let twin = Twin::of(model, None).map(Arc::new);
        let mut stats = EquilibriumStats::default();
        let x1 = if n == 0 {
            stats.converged = true;
            Vec::new()
        } else {
            let first = sys.eval(&sys.x0);
            check_visited(
                "Equilibrium",
                &sys.c,
                &first.tape,
                &first.x,
                &first.v,
                Needs::Gradient,
            )?;
            let settings = NewtonSettings {
                tolerance: self.tolerance::<R>(),
                max_newton: self.max_newton,
                max_backtracks: self.max_backtracks,
                line_search: true,
                linear: &self.linear,
            };
            match &twin {
                // In `Dual`, Newton on the real parts in `f64` (see `Twin`).
                Some(t) => {
                    let real = System::new(t.copies(), sys.x0.clone(), &t.inv_mass);
                    let first = real.eval(&real.x0);
                    newton(&real, first, &settings, &mut stats)?
                }
                None => newton(&sys, first, &settings, &mut stats)?,
            }
        };
        if !stats.converged {
            self.on_failure.handle(Error::NotConverged {
                solver: "Equilibrium Newton".into(),
                context: format!(
                    "static equilibrium that would be step #{} on the tape{}; {} force \
                     evaluations, {} line-search halvings",
                    tape.len(),
                    with_world(stats.world, model.worlds.len()),
                    stats.force_evaluations,
                    stats.backtracks
                ),
                iterations: stats.newton_iterations,
                residual: stats.residual,
                tolerance: stats.tolerance,
                hint: format!(
                    "raise `max_newton` (now {}), loosen `tolerance`, start from a guess nearer \
                     the equilibrium, check that one exists (enough pins, no free mechanism), \
                     or set `on_failure` to SolverPolicy::Warn or Continue",
                    self.max_newton
                ),
            })?;
        }

        let x = Array::zeros(n).named("x");
        let mut shared = Shared {
            solver: self.clone(),
            model: forces_only(model),
            guess: guess.x.clone(),
            x: x.clone(),
            x_val: Parts::real(x1),
            inv_mass,
            twin,
        };
        if R::DUAL {
            // A Hessian-vector product's first sweep: the solution's derivative part along
            // the parameters' and the pins' (the theorem's tangent).
            let dguess = flat_parts(&guess.x).eps.unwrap_or_default();
            shared.x_val.eps = Some(shared.solution_tangent(&dguess, Through::DerivativeParts)?);
        }
        let shared = Arc::new(shared);
        let value = unflat_parts::<R>(&shared.x_val);
        let originals = sys.c.links;
        let mut inputs: Vec<&dyn AnyArray> = vec![&guess.x];
        inputs.extend(originals.iter().map(|l| l.original()));
        tape.record_fn("equilibrium", &inputs, &[&x], || x.assign(&value), {
            let shared = shared.clone();
            move || shared.backward()
        })
        .dual_safe()
        .with_tangent(move || shared.tangent());
        Ok((
            State {
                x,
                v: Array::zeros(n).named("v"),
                bodies: None,
            },
            stats,
        ))
    }
}

/// `out[i] = a[i] / w[i]` (the net force `f + m g`) on free particles, `x[i] - pin[i]` on
/// pinned ones.
#[adflex_macros::diff_kernel]
fn net_force_kernel<R: Real>(
    a: &Array<Vec3<R>>,
    inv_mass: &Array<R>,
    x: &Array<Vec3<R>>,
    pin: &Array<Vec3<R>>,
    out: &Array<Vec3<R>>,
) {
    let i = tid();
    let w = inv_mass[i];
    if w > 0.0 {
        out[i] = a[i] / w;
    } else {
        out[i] = x[i] - pin[i];
    }
}

/// Records the equilibrium's constraint `c(x, p) = 0` at the positions `x` (zero velocities)
/// on `tape` and returns it: the net force `f(x; p) + m g` (N) on each free particle, and
/// `x - pin` (m) on each pinned one, `pin` the positions `x` holds now (held constant). Its
/// Jacobian with respect to `x` is `-K` on the free rows and the identity on the pinned ones,
/// nonsingular wherever [`Equilibrium::solve`]'s gradient exists.
///
/// This is the constraint of Gauss-Newton by the KKT system
/// (`adflex_optim::Optimizer::least_squares_kkt`): with `x` a leaf (a copy of a solved
/// equilibrium), one tangent pass over the tape gives `dc/dx u + dc/dp v` and one adjoint pass
/// `(dc/dx)^T w`, `(dc/dp)^T w`, for every parameter array the forces read (rest lengths,
/// stiffnesses, inverse masses, gravity).
///
/// Errors: [`Error::InvalidInput`] if `x` does not have one position per particle, or the
/// model has rigid bodies (as for [`Equilibrium::solve`]).
pub fn net_force<R: Real>(
    model: &Model<R>,
    tape: &mut Tape,
    x: &Array<Vec3<R>>,
) -> Result<Array<Vec3<R>>, Error> {
    let n = model.particle_count;
    if model.bodies.is_some() {
        return Err(Error::InvalidInput {
            what: "model.bodies".into(),
            message: "statics::net_force: the model has rigid bodies, which the static \
                      constraint does not cover (it is over the particles only)"
                .into(),
        });
    }
    if x.len() != n {
        return Err(Error::InvalidInput {
            what: "x".into(),
            message: format!(
                "statics::net_force: {} positions for a model of {n} particles",
                x.len()
            ),
        });
    }
    let v = Array::zeros(n).named("v_equilibrium");
    let state = State {
        x: x.clone(),
        v,
        bodies: None,
    };
    let a = model.eval_accelerations(tape, &state, None);
    let pin = Array::from_vec(x.to_vec()).named("pins");
    let out = Array::zeros(n).named("net_force");
    tape.launch(
        net_force_kernel,
        n,
        (&a, &model.particle_inv_mass, x, &pin, &out),
    );
    Ok(out)
}

/// What the backward needs.
struct Shared<R: Real> {
    solver: Equilibrium,
    model: Model<R>,
    guess: Array<Vec3<R>>,
    x: Array<Vec3<R>>,
    /// The solution, with its derivative part in `Dual`.
    x_val: Parts,
    inv_mass: Vec<R>,
    /// In `Dual`, the model in `f64` that the linear solves run on.
    twin: Option<Arc<Twin>>,
}

impl<R: Real> Shared<R> {
    fn system(&self, grads: bool) -> System<R> {
        System::new(
            copies(&self.model, None, grads),
            self.x_val.re.clone(),
            &self.inv_mass,
        )
    }

    /// The system on the twin, if there is one.
    fn twin_system(&self) -> Option<System<f64>> {
        let t = self.twin.as_ref()?;
        Some(System::new(t.copies(), self.x_val.re.clone(), &t.inv_mass))
    }

    /// Reverse mode by the implicit function theorem. Fails per the policy if the adjoint
    /// solve misses its tolerance (nothing is accumulated then). In `Dual`, every product is
    /// taken at the solution with its derivative part, and the transposed solve has its
    /// second-order term ([`solve_transposed`](crate::solver::newton::solve_transposed)).
    fn backward(&self) -> Result<(), Error> {
        let Some(gx) = self.x.grad_buffer() else {
            return Ok(());
        };
        let xbar = flat_parts(&gx);
        let m = xbar.re.len();
        let sys = self.system(true);
        let mut p = sys.eval_at(&self.x_val, true);
        check_visited("Equilibrium", &sys.c, &p.tape, &p.x, &p.v, Needs::Gradient)?;
        let rhs = xbar.map(|b| {
            let mut r = b.to_vec();
            sys.mask(&mut r);
            r
        });
        let settings = self.solver.gradient_settings();
        let check = |info: &LinearSolve| self.check_gradient_solve("adjoint", info);
        let twin = self.twin_system();
        let mut tp = twin
            .as_ref()
            .map(|t| t.eval_at(&Parts::real(self.x_val.re.clone()), true));
        let twin = twin.as_ref().zip(tp.as_mut());
        let lambda = solve_transposed_on(&sys, &mut p, &rhs, twin, settings, check)?;
        for l in &sys.c.links {
            l.zero_copy_grad();
        }
        let (gx, _) = pull(&mut p, &sys.dofs.mass_product(&lambda, 1.0, true))
            .map_err(|e| sys.failure.in_pass("adjoint (reverse-mode)", e))?;
        // Pinned DOFs: x* = pin, which also moves the free particles' equilibrium.
        let gpin = xbar.zip(&gx, |xbar, gx| {
            (0..m)
                .map(|k| {
                    if sys.dofs.free[k] {
                        0.0
                    } else {
                        xbar[k] + gx[k]
                    }
                })
                .collect()
        });
        add_into(&self.guess, &gpin);
        for l in &sys.c.links {
            l.add_grad();
        }
        Ok(())
    }

    /// Forward mode by the implicit function theorem (see [`Shared::solution_tangent`]).
    fn tangent(&self) -> Result<(), Error> {
        let Some(out) = self.x.tangent_buffer() else {
            return Ok(());
        };
        adflex_runtime::second_order::refuse_dual::<R>(
            "Equilibrium's forward mode",
            crate::solver::parts::NO_DUAL_TANGENT,
        )?;
        let m = self.x_val.re.len();
        let dguess = self
            .guess
            .tangent_buffer()
            .map_or_else(|| vec![0.0; m], |t| flat(&t));
        let dx = self.solution_tangent(&dguess, Through::Tangents)?;
        out.assign(&unflat::<R>(&dx));
        Ok(())
    }

    /// The solution's derivative `dx*`: `K dx* = M da` on the free DOFs, `da` the derivative
    /// of the accelerations at `x*` for the inputs' (the parameters', and the guess's
    /// `dguess` at the pinned DOFs, which `x*` follows), taken `through` their tangents or
    /// their derivative parts. Fails per the policy if the solve misses its tolerance.
    fn solution_tangent(&self, dguess: &[f64], through: Through) -> Result<Vec<f64>, Error> {
        let m = self.x_val.re.len();
        let sys = self.system(false);
        let dpin: Vec<f64> = (0..m)
            .map(|k| if sys.dofs.free[k] { 0.0 } else { dguess[k] })
            .collect();
        let x = Parts::real(self.x_val.re.clone());
        let (mut p, ad) = match through {
            Through::Tangents => {
                let mut p = sys.eval_at(&x, false);
                check_visited("Equilibrium", &sys.c, &p.tape, &p.x, &p.v, Needs::Tangent)?;
                // The velocities stay 0.
                let ad = acceleration_tangent(&sys.c, &mut p, &dpin, &vec![0.0; m], &sys.failure)?;
                (p, ad)
            }
            Through::DerivativeParts => {
                let p = sys.eval_at(
                    &Parts {
                        eps: Some(dpin.clone()),
                        ..x.clone()
                    },
                    false,
                );
                let ad = flat_parts(&p.a).eps.unwrap_or_else(|| vec![0.0; m]);
                (p, ad)
            }
        };
        let mut rhs: Vec<f64> = (0..m).map(|k| sys.dofs.mass[k] * ad[k]).collect();
        sys.mask(&mut rhs);
        let settings = self.solver.gradient_settings();
        let (mut dx, solve) = match self.twin_system() {
            Some(twin) => solve_linear(&twin, &mut twin.eval(&x.re), &rhs, settings, false)?,
            None => solve_linear(&sys, &mut p, &rhs, settings, false)?,
        };
        self.check_gradient_solve("tangent", &solve)?;
        for k in 0..m {
            if !sys.dofs.free[k] {
                dx[k] = dpin[k];
            }
        }
        Ok(dx)
    }

    /// The policy's answer to a gradient solve (`which`: adjoint or tangent) that missed its
    /// tolerance.
    fn check_gradient_solve(&self, which: &str, solve: &LinearSolve) -> Result<(), Error> {
        let Some((world, info)) = solve.failed() else {
            return Ok(());
        };
        let s = self.solver.gradient_settings();
        self.solver.on_failure.handle(Error::NotConverged {
            solver: format!("Equilibrium {which} linear solve (CG, then BiCGSTAB)"),
            context: world_context(world, solve.infos.len()),
            iterations: info.iterations,
            residual: info.residual,
            tolerance: info.tolerance,
            hint: format!(
                "raise `max_iter` (now {}) or loosen `rel_tol` (now {:e}) of `adjoint_linear` \
                 (or `linear`); a singular stiffness (a free mechanism, a slack structure) has \
                 no unique gradient; or set `on_failure` to SolverPolicy::Warn or Continue",
                s.max_iter, s.rel_tol
            ),
        })
    }
}
