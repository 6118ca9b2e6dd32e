//! Pieces shared by the integrators of this crate: the rigid body step (every particle
//! integrator advances the bodies with the semi-implicit kernel of [`crate::rigid`]) and a
//! state built from new particle arrays.

use adflex_runtime::{Array, Error, Real, Tape, Vec3};

use crate::model::{Control, Model, State};
use crate::rigid::BodyState;

/// Advances the rigid bodies of `state` (if any) by `dt` (s) with
/// [`crate::rigid::RigidBodies::integrate`] (semi-implicit Euler), recording on `tape`.
pub(crate) fn step_bodies<R: Real>(
    model: &Model<R>,
    tape: &mut Tape,
    state: &State<R>,
    control: Option<&Control<R>>,
    dt: R,
) -> Option<BodyState<R>> {
    let bodies = model.bodies.as_ref()?;
    let s = state
        .bodies
        .as_ref()
        .expect("the model has rigid bodies but the state has none");
    let (f, t) = model
        .eval_body_forces(tape, state, control)
        .expect("the model has rigid bodies");
    Some(bodies.integrate(tape, s, &f, &t, model.gravity, dt))
}

/// A state with particle arrays `x`, `v` and no bodies (for intermediate stages).
pub(crate) fn particles<R: Real>(x: &Array<Vec3<R>>, v: &Array<Vec3<R>>) -> State<R> {
    State {
        x: x.clone(),
        v: v.clone(),
        bodies: None,
    }
}

/// New, zeroed particle arrays named `x` and `v`, for a step's output.
pub(crate) fn new_xv<R: Real>(n: usize) -> (Array<Vec3<R>>, Array<Vec3<R>>) {
    (Array::zeros(n).named("x"), Array::zeros(n).named("v"))
}

/// Checks a step's `dt` (s): finite and positive, or [`Error::InvalidInput`] naming
/// `integrator`. Returns it in f64.
pub(crate) fn check_dt<R: Real>(integrator: &str, dt: R) -> Result<f64, Error> {
    let d = dt.to_f64();
    if d.is_finite() && d > 0.0 {
        Ok(d)
    } else {
        Err(Error::InvalidInput {
            what: "dt".into(),
            message: format!(
                "{integrator}: the time step must be finite and positive (seconds), got {d}"
            ),
        })
    }
}
