//! The classical fourth-order Runge-Kutta method on the first-order system `x' = v`,
//! `v' = a(x, v)`.
//!
//! Four force evaluations per step; global error `O(dt^4)`. Conditionally stable: on an
//! undamped oscillator of angular frequency `omega` the energy decays slowly (by
//! `O((omega dt)^6)` per step) for `omega dt < 2 sqrt(2)` and blows up beyond. The method of
//! choice for smooth, moderately stiff systems where accuracy per unit of work matters
//! (it is the most accurate integrator here at a given cost when `omega dt` is small); contact
//! and other non-smooth forces reduce it to low order.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::common::{finish_step, new_xv, particles, step_bodies};
use super::{check_dt, Integrator};
use crate::model::Model;
use crate::state::{Control, State};

/// A Runge-Kutta stage of particle `tid`: `xs = x0 + vk c`, `vs = v0 + ak c` (`c` in s).
#[diff_kernel]
pub fn rk_stage<R: Real>(
    x0: &Array<Vec3<R>>,
    v0: &Array<Vec3<R>>,
    vk: &Array<Vec3<R>>,
    ak: &Array<Vec3<R>>,
    c: R,
    xs: &Array<Vec3<R>>,
    vs: &Array<Vec3<R>>,
) {
    let t = tid();
    xs[t] = x0[t] + vk[t] * c;
    vs[t] = v0[t] + ak[t] * c;
}

/// The RK4 combination for particle `tid`:
/// `x = x0 + dt/6 (v0 + 2 v2 + 2 v3 + v4)`, `v = v0 + dt/6 (a1 + 2 a2 + 2 a3 + a4)`, where
/// `(v_k, a_k)` is the slope at stage `k` (`v1 = v0`).
#[diff_kernel]
pub fn rk4_combine<R: Real>(
    x0: &Array<Vec3<R>>,
    v0: &Array<Vec3<R>>,
    v2: &Array<Vec3<R>>,
    v3: &Array<Vec3<R>>,
    v4: &Array<Vec3<R>>,
    a1: &Array<Vec3<R>>,
    a2: &Array<Vec3<R>>,
    a3: &Array<Vec3<R>>,
    a4: &Array<Vec3<R>>,
    dt: R,
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
) {
    let t = tid();
    let h = dt / 6.0;
    x[t] = x0[t] + (v0[t] + (v2[t] + v3[t]) * 2.0 + v4[t]) * h;
    v[t] = v0[t] + (a1[t] + (a2[t] + a3[t]) * 2.0 + a4[t]) * h;
}

/// Classical fourth-order Runge-Kutta: four evaluations of [`Model::eval_accelerations`], three
/// [`rk_stage`] launches and one [`rk4_combine`] per step, all on the tape (differentiable in
/// reverse and forward mode).
///
/// Error `O(dt^4)` on smooth problems at four times the cost of an Euler step; stable on an
/// undamped spring for `omega dt < 2.83` (where it slowly dissipates energy). Suits smooth,
/// soft to moderately stiff systems (`omega dt` up to about 1) where accuracy matters; for
/// stiff systems use [`ImplicitEuler`](crate::integrators::ImplicitEuler), for hard
/// constraints [`Xpbd`](crate::integrators::Xpbd). The control is held constant over the
/// step. Rigid bodies, if any, are advanced by the semi-implicit body step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Rk4;

impl<R: Real> Integrator<R> for Rk4 {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error> {
        check_dt("Rk4", dt)?;
        let first = tape.len();
        let n = model.particle_count;
        let half = dt * R::lit(0.5);
        let (x0, v0) = (&state.x, &state.v);
        let stage = |tape: &mut Tape, vk: &Array<Vec3<R>>, ak: &Array<Vec3<R>>, c: R| {
            let xs = Array::zeros(n).named("rk_x");
            let vs = Array::zeros(n).named("rk_v");
            tape.launch(rk_stage, n, (x0, v0, vk, ak, c, &xs, &vs));
            (xs, vs)
        };
        let a1 = model.eval_accelerations(tape, state, control);
        let (x2, v2) = stage(tape, v0, &a1, half);
        let a2 = model.eval_accelerations(tape, &particles(&x2, &v2), control);
        let (x3, v3) = stage(tape, &v2, &a2, half);
        let a3 = model.eval_accelerations(tape, &particles(&x3, &v3), control);
        let (x4, v4) = stage(tape, &v3, &a3, dt);
        let a4 = model.eval_accelerations(tape, &particles(&x4, &v4), control);
        let (x, v) = new_xv(n);
        tape.launch(
            rk4_combine,
            n,
            (x0, v0, &v2, &v3, &v4, &a1, &a2, &a3, &a4, dt, &x, &v),
        );
        let bodies = step_bodies(model, tape, state, control, dt);
        let new = State { x, v, bodies };
        finish_step("Rk4", model, tape, first, state, control, new)
    }
}
