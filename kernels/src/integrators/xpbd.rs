//! Extended position-based dynamics (XPBD, Macklin, Muller and Chentanez 2016) with substeps
//! ("small steps", Macklin et al. 2019): each step of `dt` is `substeps` substeps of
//! `h = dt / substeps`, each one
//!
//! 1. a prediction with the forces of the model and gravity: `v* = v + a(x, v) h`,
//!    `x* = x + v* h` ([`xpbd_predict`]);
//! 2. `iterations` Jacobi passes over the model's distance constraints, the multipliers
//!    starting from zero: averaged ([`crate::constraints::DistanceConstraints::iterate_averaged`],
//!    the default) or summed ([`crate::constraints::DistanceConstraints::iterate`]);
//! 3. a check that the solve did not diverge (on the host, not on the tape);
//! 4. the velocity from the corrected positions, `v = (x - x_prev) / h`.
//!
//! Every pass is a kernel launch on the tape, so the step is differentiable in both modes.
//! The constraint kernels are those of [`crate::constraints`]; this module only schedules them.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::common::{finish_step, particles, step_bodies};
use super::{check_dt, Integrator};
use crate::constraints::velocity_from_positions;
use crate::model::Model;
use crate::state::{Control, State};

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
/// The constraints are solved by Jacobi passes (every constraint reads the same positions,
/// so a pass is one parallel launch). By default (`averaging: true`) each particle's summed
/// correction is divided by the number of constraints touching it, then scaled by
/// `relaxation`: stable with any number of constraints per particle (cloth, 8 per particle)
/// for `relaxation` in (0, 2). Summed corrections (`averaging: false`) converge faster on
/// chains (2 per particle) but overshoot by up to the number of constraints per particle: on
/// cloth they diverge unless `relaxation` is about 0.5 or less.
///
/// After each substep's constraint solve the step checks, on the host, that the solve did
/// not increase the largest relative constraint violation `|C| / rest` past
/// `max(2 x its value before the solve, 0.1)` and that it is finite; otherwise it returns
/// [`Error::NotConverged`] naming `"Xpbd constraint solve"`, the substep and the kernels
/// (lower `relaxation`, turn `averaging` on, or use more substeps). A non-finite prediction
/// (the forces blowing up: more substeps) is reported as `"Xpbd prediction"`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Xpbd {
    /// Substeps per step (default 8, at least 1).
    pub substeps: usize,
    /// Jacobi passes over the constraints per substep (default 2).
    pub iterations: usize,
    /// Scale of the corrections, finite and `> 0` (default 1): of the averaged corrections,
    /// stable in (0, 2) (over-relaxation above 1); of the summed ones, stable only below
    /// about 2 / (constraints per particle).
    pub relaxation: f64,
    /// Divide each particle's summed correction by its number of constraints (default true;
    /// see the type's docs). The counts are constants: gradients are unaffected in kind.
    pub averaging: bool,
}

impl Default for Xpbd {
    fn default() -> Self {
        Xpbd {
            substeps: 8,
            iterations: 2,
            relaxation: 1.0,
            averaging: true,
        }
    }
}

impl Xpbd {
    /// XPBD with `substeps` substeps of one averaged Jacobi pass each, relaxation 1.
    pub fn new(substeps: usize) -> Self {
        Xpbd {
            substeps,
            iterations: 1,
            ..Xpbd::default()
        }
    }
}

/// The relative violation the constraint solve may reach without counting as diverging:
/// `max(2 before, 0.1)` (see [`Xpbd`]).
fn divergence_threshold(before: f64) -> f64 {
    (2.0 * before).max(0.1)
}

impl<R: Real> Integrator<R> for Xpbd {
    fn step(
        &self,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        control: Option<&Control<R>>,
        dt: R,
    ) -> Result<State<R>, Error> {
        check_dt("Xpbd", dt)?;
        let step_first = tape.len();
        if self.substeps == 0 {
            return Err(Error::InvalidInput {
                what: "Xpbd::substeps".into(),
                message: "at least 1 substep per step".into(),
            });
        }
        if !(self.relaxation.is_finite() && self.relaxation > 0.0) {
            return Err(Error::InvalidInput {
                what: "Xpbd::relaxation".into(),
                message: format!(
                    "must be finite and > 0 (default 1; stable in (0, 2) with averaging), got {}",
                    self.relaxation
                ),
            });
        }
        let n = model.particle_count;
        let h = dt / R::lit(self.substeps as f64);
        let relax = R::lit(self.relaxation);
        let constraints = model
            .distance_constraints
            .as_ref()
            .filter(|c| !c.is_empty());
        let counts = constraints
            .filter(|_| self.averaging)
            .map(|c| c.inverse_counts(n));
        let (mut x, mut v) = (state.x.clone(), state.v.clone());
        for sub in 0..self.substeps {
            let a = model.eval_accelerations(tape, &particles(&x, &v), control);
            let mut xc = Array::zeros(n).named("x_pred");
            tape.launch(xpbd_predict, n, (&x, &v, &a, h, &xc));
            if let Some(c) = constraints {
                let before = c.max_relative_violation(&xc.to_vec());
                if !before.is_finite() {
                    return Err(Error::NotConverged {
                        solver: "Xpbd prediction".into(),
                        context: format!(
                            "substep {sub} of {}, kernel `xpbd_predict` (#{} on the tape): the \
                             predicted positions are not finite",
                            self.substeps,
                            tape.len() - 1
                        ),
                        iterations: 0,
                        residual: before,
                        tolerance: 0.0,
                        hint: "the forces of the model blew up in the semi-implicit prediction: \
                               use more substeps (omega dt / substeps < 2) or a smaller dt"
                            .into(),
                    });
                }
                let first = tape.len();
                let mut lambda = c.zero_lambda();
                for _ in 0..self.iterations {
                    (xc, lambda) = match &counts {
                        Some(k) => c.iterate_averaged(
                            tape,
                            &xc,
                            &model.particle_inv_mass,
                            &lambda,
                            h,
                            relax,
                            k,
                        ),
                        None => c.iterate(tape, &xc, &model.particle_inv_mass, &lambda, h, relax),
                    };
                }
                let after = c.max_relative_violation(&xc.to_vec());
                let limit = divergence_threshold(before);
                if !(after <= limit) {
                    return Err(Error::NotConverged {
                        solver: "Xpbd constraint solve".into(),
                        context: format!(
                            "substep {sub} of {}, kernels `solve_distance_constraints` and \
                             `{}` (#{first} to #{} on the tape): the largest relative \
                             constraint violation went from {before:.3e} to {after:.3e} (it \
                             diverges)",
                            self.substeps,
                            if counts.is_some() {
                                "apply_averaged_corrections"
                            } else {
                                "apply_corrections"
                            },
                            tape.len() - 1
                        ),
                        iterations: self.iterations,
                        residual: after,
                        tolerance: limit,
                        hint: format!(
                            "lower `relaxation` (now {}), keep `averaging` on (now {}), or use \
                             more substeps",
                            self.relaxation, self.averaging
                        ),
                    });
                }
            }
            let vn = Array::zeros(n).named("v");
            tape.launch(velocity_from_positions, n, (&x, &xc, h, &vn));
            x = xc;
            v = vn;
        }
        let x_out = x.named("x");
        let bodies = step_bodies(model, tape, state, control, dt);
        let new = State {
            x: x_out,
            v,
            bodies,
        };
        finish_step("Xpbd", model, tape, step_first, state, control, new)
    }
}
