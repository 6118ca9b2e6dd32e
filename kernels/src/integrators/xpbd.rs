//! Extended position-based dynamics (XPBD, Macklin, Muller and Chentanez 2016) with substeps
//! ("small steps", Macklin et al. 2019): each step of `dt` is `substeps` substeps of
//! `h = dt / substeps`, each one
//!
//! 1. a prediction with the forces of the model and gravity: `v* = v + a(x, v) h`,
//!    `x* = x + v* h` ([`xpbd_predict`]);
//! 2. `iterations` Jacobi passes over the model's distance constraints
//!    ([`crate::xpbd::DistanceConstraints::iterate`]), the multipliers starting from zero;
//! 3. the velocity from the corrected positions, `v = (x - x_prev) / h`.
//!
//! Every pass is a kernel launch on the tape, so the step is differentiable in both modes.
//! The constraint kernels are those of [`crate::xpbd`]; this module only schedules them.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::common::{particles, step_bodies};
use super::Integrator;
use crate::model::{Control, Model, State};
use crate::xpbd::velocity_from_positions;

/// Prediction of particle `tid` (a semi-implicit Euler step): `x_pred = x + (v + a h) h`
/// (`a` in m/s^2, `h` in s).
#[diff_kernel]
pub fn xpbd_predict<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    a: &Array<Vec3<R>>,
    h: R,
    x_pred: &Array<Vec3<R>>,
) {
    let t = tid();
    x_pred[t] = x[t] + (v[t] + a[t] * h) * h;
}

/// XPBD with substeps: forces of the model (springs, contact, gravity, ...) in a semi-implicit
/// prediction, then the model's distance constraints (`ModelBuilder::add_distance_constraint`,
/// compliance `alpha` in m/N, 0 = rigid) solved on positions.
///
/// Unconditionally stable for the constraints whatever their stiffness (a compliance of 0 is
/// an inextensible rod), so it suits the stiffest parts of a scene: inextensible cloth,
/// ropes, pendulums, where penalty springs would need a tiny `dt`. The constraint error left
/// after a substep shrinks with more substeps (about quadratically) or iterations; the
/// forces other than constraints are integrated semi-implicitly per substep, so springs keep
/// the stability limit `omega h < 2` of [`SemiImplicitEuler`](crate::integrators::SemiImplicitEuler)
/// with `h = dt / substeps`. Without constraints it is semi-implicit Euler with substeps.
///
/// Jacobi passes sum the corrections of all constraints of a particle; for particles in many
/// constraints (cloth) lower `relaxation` (e.g. 0.5) if the solve oscillates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Xpbd {
    /// Substeps per step (default 8).
    pub substeps: usize,
    /// Jacobi passes over the constraints per substep (default 2).
    pub iterations: usize,
    /// Scale of the summed corrections, in (0, 1] (default 1).
    pub relaxation: f64,
}

impl Default for Xpbd {
    fn default() -> Self {
        Xpbd {
            substeps: 8,
            iterations: 2,
            relaxation: 1.0,
        }
    }
}

impl Xpbd {
    /// XPBD with `substeps` substeps of one Jacobi pass each, relaxation 1.
    pub fn new(substeps: usize) -> Self {
        Xpbd {
            substeps,
            iterations: 1,
            relaxation: 1.0,
        }
    }
}

impl<R: Real> Integrator<R> for Xpbd {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> State<R> {
        assert!(self.substeps > 0, "Xpbd: substeps must be at least 1");
        let n = model.particle_count;
        let h = dt / R::lit(self.substeps as f64);
        let relax = R::lit(self.relaxation);
        let (mut x, mut v) = (state.x.clone(), state.v.clone());
        for _ in 0..self.substeps {
            let a = model.eval_accelerations(tape, &particles(&x, &v), control);
            let mut xc = Array::zeros(n).named("x_pred");
            tape.launch(xpbd_predict, n, (&x, &v, &a, h, &xc));
            if let Some(c) = &model.distance_constraints {
                let mut lambda = c.zero_lambda();
                for _ in 0..self.iterations {
                    (xc, lambda) =
                        c.iterate(tape, &xc, &model.particle_inv_mass, &lambda, h, relax);
                }
            }
            let vn = Array::zeros(n).named("v");
            tape.launch(velocity_from_positions, n, (&x, &xc, h, &vn));
            x = xc;
            v = vn;
        }
        let x_out = x.named("x");
        let bodies = step_bodies(model, tape, state, control, dt);
        State {
            x: x_out,
            v,
            bodies,
        }
    }
}
