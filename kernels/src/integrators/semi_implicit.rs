//! Semi-implicit (symplectic) Euler: velocities first, then positions with the new velocities.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::common::{finish_step, step_bodies};
use super::{check_dt, Integrator};
use crate::model::Model;
use crate::state::{Control, State};

/// `v' = v + (f w + g [w > 0]) dt`, `x' = x + v' dt` for particle `tid` (`w` the inverse mass
/// in 1/kg, `g = gravity[world[tid]]` its world's gravity in m/s^2, `dt` in s), into new
/// arrays `x_new`, `v_new`.
#[diff_kernel]
pub fn integrate_particles<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    f: &Array<Vec3<R>>,
    inv_mass: &Array<R>,
    gravity: &Array<Vec3<R>>,
    world: &Array<u32>,
    dt: R,
    x_new: &Array<Vec3<R>>,
    v_new: &Array<Vec3<R>>,
) {
    let t = tid();
    let w = inv_mass[t];
    let g = gravity[world[t] as usize];
    let v1 = v[t] + (f[t] * w + select(w > 0.0, g, g * 0.0)) * dt;
    x_new[t] = x[t] + v1 * dt;
    v_new[t] = v1;
}

/// Semi-implicit Euler for particles and rigid bodies (see [`integrate_particles`] and
/// [`crate::rigid::integrate_bodies`]).
#[derive(Clone, Copy, Debug, Default)]
pub struct SemiImplicitEuler;

impl<R: Real> Integrator<R> for SemiImplicitEuler {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error> {
        check_dt("SemiImplicitEuler", dt)?;
        let first = tape.len();
        let n = model.particle_count;
        let f = model.eval_forces(tape, state, control);
        let x = Array::zeros(n).named("x");
        let v = Array::zeros(n).named("v");
        tape.launch(
            integrate_particles,
            n,
            (
                &state.x,
                &state.v,
                &f,
                &model.particle_inv_mass,
                model.gravity_per_world(),
                &model.particle_world,
                dt,
                &x,
                &v,
            ),
        );
        let bodies = step_bodies(model, tape, state, control, dt);
        let new = State { x, v, bodies };
        finish_step("SemiImplicitEuler", model, tape, first, state, control, new)
    }
}
