//! Integrators: advance a [`State`] by one step on a tape, returning a new state (new arrays).
//!
//! An integrator gets everything from the [`Model`]: [`Model::eval_forces`] (particle forces),
//! [`Model::eval_accelerations`] (with gravity and inverse masses),
//! [`Model::eval_body_forces`] (rigid bodies), and the components' own arrays (e.g.
//! `model.distance_constraints` for position-based methods).
//!
//! # Errors
//!
//! [`Integrator::step`] and [`Integrator::rollout`] return a `Result`: no integrator hands back
//! a state it knows to be wrong.
//!
//! - [`Error::InvalidInput`] (every integrator): `dt` is NaN, infinite, zero or negative; or
//!   a parameter, the control or the state holds a NaN/Inf, named with its array label and
//!   index (e.g. `spring_ke[3]`, `v[1]`). Fix the input. Implicit Euler checks before it
//!   solves; the others find it when the new state is not finite (every step checks it).
//!   Implicit Euler (and [`crate::statics::Equilibrium`]) also refuse a force that reads an
//!   array requiring a gradient which its [`Force::params_mut`](crate::forces::Force::params_mut)
//!   does not visit (the error names the force, kernel and array): they differentiate private
//!   copies of the visited parameters, so a forgotten one would get a wrong gradient.
//! - [`Error::NonFinite`] (every integrator): the new state is not finite although every input
//!   is (the forces overflowed: a `dt` beyond the method's stability limit), naming the state
//!   array and index; or, with [`Tape::check_finite`] on, the first kernel of the step that
//!   wrote a NaN/Inf (its name, array, index). `rollout` adds the step (`rollout step k of
//!   n`).
//! - [`Error::NotConverged`]: an iterative solve stopped short of its tolerance.
//!   [`ImplicitEuler`]'s Newton iteration (solver `"ImplicitEuler Newton"`): raise
//!   `max_newton`, loosen `tolerance`, take a smaller `dt`, or accept the unconverged step
//!   with [`ImplicitEuler::on_failure`] ([`SolverPolicy`]). Its adjoint linear solve (solver
//!   `"ImplicitEuler adjoint linear solve"`) is reported by `tape.backward`: raise
//!   `linear.max_iter` / loosen `linear.rel_tol` (or `adjoint_linear`). [`Xpbd`]'s
//!   constraint solve diverging (solver `"Xpbd constraint solve"`, naming the substep and the
//!   kernel): lower `relaxation`, or use more substeps.

pub(crate) mod common;
pub mod explicit;
pub mod implicit;
pub mod midpoint;
pub mod rk4;
pub mod semi_implicit;
pub mod xpbd;

use adflex_runtime::{Error, Real, Tape};

use crate::model::Model;
use crate::state::{Control, State};

pub(crate) use common::check_dt;
pub use explicit::ExplicitEuler;
pub use implicit::{ImplicitEuler, NewtonStats};
pub use midpoint::Midpoint;
pub use rk4::Rk4;
pub use semi_implicit::SemiImplicitEuler;
pub use xpbd::Xpbd;

/// What an integrator with an iterative solve ([`ImplicitEuler`]) does when the solve stops
/// before meeting its tolerance (iteration cap reached, no descent, non-finite iterate).
///
/// Invalid input ([`Error::InvalidInput`]: NaN `dt`, NaN parameter) is an error under every
/// policy.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SolverPolicy {
    /// Return [`Error::NotConverged`] (from `step`, or from `tape.backward` for the adjoint
    /// solve). The default: a result that missed its tolerance is never used silently.
    #[default]
    Error,
    /// Print the solver, the step and the figures (iterations, residual, tolerance) to
    /// stderr, once per failing solve, and use the unconverged result.
    Warn,
    /// Use the unconverged result silently (e.g. a fixed iteration budget on purpose; check
    /// the figures with [`ImplicitEuler::step_with_stats`]).
    Continue,
}

impl SolverPolicy {
    /// Applies the policy to a solve's failure `err`: the error, or a warning, or nothing.
    pub(crate) fn handle(self, err: Error) -> Result<(), Error> {
        match self {
            SolverPolicy::Error => Err(err),
            SolverPolicy::Warn => {
                eprintln!("warning: {err} [continuing: on_failure = SolverPolicy::Warn]");
                Ok(())
            }
            SolverPolicy::Continue => Ok(()),
        }
    }
}

/// A time stepping scheme.
pub trait Integrator<R: Real> {
    /// Records one step of `dt` seconds (finite, `> 0`) from `state` on `tape` and returns the
    /// new state, whose arrays are new (the tape keeps the old ones for backward).
    ///
    /// Errors (see the [module docs](self)): [`Error::InvalidInput`] for a NaN, infinite or
    /// non-positive `dt` (every integrator) or a non-finite parameter; [`Error::NotConverged`]
    /// if the integrator's solve failed (implicit Euler's Newton under
    /// [`SolverPolicy::Error`], XPBD's constraint solve diverging).
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error>;

    /// Records `steps` steps from `state` with the same control; returns the final state, or
    /// the first step's error with `rollout step k of n` added to its context.
    fn rollout(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
        steps: usize,
    ) -> Result<State<R>, Error> {
        let mut s = state.clone();
        for k in 0..steps {
            s = self
                .step(model, tape, &s, control, dt)
                .map_err(|e| e.in_context(format!("rollout step {k} of {steps}")))?;
        }
        Ok(s)
    }
}
