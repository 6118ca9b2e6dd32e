//! Integrators: advance a [`State`] by one step on a tape, returning a new state (new arrays).
//!
//! An integrator gets everything from the [`Model`]: [`Model::eval_forces`] (particle forces),
//! [`Model::eval_accelerations`] (with gravity and inverse masses),
//! [`Model::eval_body_forces`] (rigid bodies), and the components' own arrays (e.g.
//! `model.distance_constraints` for position-based methods).

mod common;
pub mod explicit;
pub mod implicit;
pub mod linsolve;
pub mod oscillator;
pub mod rk4;
pub mod semi_implicit;
pub mod xpbd;

use adflex_runtime::{Real, Tape};

use crate::model::{Control, Model, State};

pub use explicit::ExplicitEuler;
pub use implicit::{ImplicitEuler, NewtonStats};
pub use rk4::Rk4;
pub use semi_implicit::SemiImplicitEuler;
pub use xpbd::Xpbd;

/// A time stepping scheme.
pub trait Integrator<R: Real> {
    /// Records one step of `dt` seconds from `state` on `tape` and returns the new state, whose
    /// arrays are new (the tape keeps the old ones for backward).
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> State<R>;

    /// Records `steps` steps from `state` with the same control; returns the final state.
    fn rollout(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
        steps: usize,
    ) -> State<R> {
        let mut s = state.clone();
        for _ in 0..steps {
            s = self.step(model, tape, &s, control, dt);
        }
        s
    }
}
