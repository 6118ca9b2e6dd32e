//! Explicit (forward) Euler: `x' = x + v dt`, `v' = v + a(x, v) dt`.
//!
//! First order, one force evaluation per step, and **unconditionally unstable** on an undamped
//! oscillator: the energy of a spring of angular frequency `omega` grows by the factor
//! `1 + (omega dt)^2` every step, whatever `dt`. It is here as the baseline of the accuracy and
//! stability charts, and for heavily damped scenes; prefer
//! [`SemiImplicitEuler`](crate::integrators::SemiImplicitEuler) for the same cost.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::common::{finish_step, new_xv, step_bodies};
use super::{check_dt, Integrator};
use crate::model::Model;
use crate::state::{Control, State};

/// Explicit Euler update of particle `tid`: `x_new = x + v dt`, `v_new = v + a dt` (`a` in
/// m/s^2, `dt` in s). The position moves with the *old* velocity.
#[diff_kernel]
pub fn explicit_euler_update<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    a: &Array<Vec3<R>>,
    dt: R,
    x_new: &Array<Vec3<R>>,
    v_new: &Array<Vec3<R>>,
) {
    let t = tid();
    x_new[t] = x[t] + v[t] * dt;
    v_new[t] = v[t] + a[t] * dt;
}

/// Explicit (forward) Euler, first order, one force evaluation per step.
///
/// Each step records [`Model::eval_accelerations`] at the current state and one
/// [`explicit_euler_update`] launch on the tape, so it is differentiable in both modes
/// (reverse with `tape.backward`, forward with `tape.tangent`). Energy grows every step on an
/// undamped oscillator (by `1 + (omega dt)^2`): only suited to heavily damped or very soft
/// systems, with `dt` well below `1 / omega`. Rigid bodies, if any, are advanced by the
/// semi-implicit body step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ExplicitEuler;

impl<R: Real> Integrator<R> for ExplicitEuler {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error> {
        check_dt("ExplicitEuler", dt)?;
        let first = tape.len();
        let a = model.eval_accelerations(tape, state, control);
        let (x, v) = new_xv(model.particle_count);
        tape.launch(
            explicit_euler_update,
            model.particle_count,
            (&state.x, &state.v, &a, dt, &x, &v),
        );
        let bodies = step_bodies(model, tape, state, control, dt);
        let new = State { x, v, bodies };
        finish_step("ExplicitEuler", model, tape, first, state, control, new)
    }
}
