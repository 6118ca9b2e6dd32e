//! The explicit midpoint method (second-order Runge-Kutta) on the first-order system `x' = v`,
//! `v' = a(x, v)`.
//!
//! Two force evaluations per step; global error `O(dt^2)`, between
//! [`ExplicitEuler`](super::ExplicitEuler) (one evaluation, first order) and
//! [`Rk4`](super::Rk4) (four, fourth order). On an undamped oscillator of angular frequency
//! `omega` one step multiplies the complex amplitude by `1 + i omega dt - (omega dt)^2 / 2`,
//! of modulus `sqrt(1 + (omega dt)^4 / 4) > 1`: the energy grows by the factor
//! `1 + (omega dt)^4 / 4` per step, for every `dt` (slowly where `omega dt` is small; no
//! damping-free bound as for symplectic Euler). With damping `zeta` it is stable where the
//! damping outweighs that growth.

use adflex_runtime::prelude::*;

use super::common::{finish_step, new_xv, particles, step_bodies};
use super::rk4::rk_stage;
use super::{check_dt, Integrator};
use crate::model::Model;
use crate::state::{Control, State};

/// The explicit midpoint method (RK2): `a1 = a(x0, v0)`, the half step
/// `x_h = x0 + v0 dt/2`, `v_h = v0 + a1 dt/2`, then `x = x0 + v_h dt`, `v = v0 + a(x_h, v_h) dt`.
/// Two evaluations of [`Model::eval_accelerations`] and two [`rk_stage`] launches per step, all
/// on the tape (differentiable in reverse and forward mode).
///
/// Second order at twice the cost of an Euler step: more accurate than the Euler methods per
/// unit of work on smooth problems, less than [`Rk4`](super::Rk4) when `omega dt` is small.
/// The control is held constant over the step; rigid bodies, if any, are advanced by the
/// semi-implicit body step.
///
/// ```
/// use adflex_kernels::integrators::{Integrator, Midpoint};
/// use adflex_kernels::prelude::*;
/// use adflex_runtime::{Tape, Vec3};
///
/// // Free fall from rest: midpoint is exact for a constant acceleration.
/// let mut b = ModelBuilder::<f64>::new();
/// b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
/// let model = b.finalize();
/// let s = Midpoint.step(&model, &mut Tape::new(), &model.state(), None, 0.5).unwrap();
/// assert!((s.x.get(0).y - 0.5 * model.gravity.get(0).y * 0.25).abs() < 1e-12);
/// ```
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Midpoint;

impl<R: Real> Integrator<R> for Midpoint {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error> {
        check_dt("Midpoint", dt)?;
        let first = tape.len();
        let n = model.particle_count;
        let (x0, v0) = (&state.x, &state.v);
        let a1 = model.eval_accelerations(tape, state, control);
        let xh = Array::zeros(n).named("midpoint_x");
        let vh = Array::zeros(n).named("midpoint_v");
        tape.launch(rk_stage, n, (x0, v0, v0, &a1, dt * R::lit(0.5), &xh, &vh));
        let a2 = model.eval_accelerations(tape, &particles(&xh, &vh), control);
        let (x, v) = new_xv(n);
        tape.launch(rk_stage, n, (x0, v0, &vh, &a2, dt, &x, &v));
        let bodies = step_bodies(model, tape, state, control, dt);
        let new = State { x, v, bodies };
        finish_step("Midpoint", model, tape, first, state, control, new)
    }
}
