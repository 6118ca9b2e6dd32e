//! The step of an MPM model: the launches of its three kernels per dimension ([`Launches`])
//! and [`Mpm::step`] over them.

use adflex_runtime::prelude::*;

use super::dim::{Dim, D2, D3};
use super::kernels::{mpm3_g2p, mpm3_grid_update, mpm3_p2g, mpm_g2p, mpm_grid_update, mpm_p2g};
use super::model::{invalid, Mpm, MpmState};
use crate::precompiled::precompiled;

/// The launches of one step in a dimension ([`D2`], [`D3`]): the same three kernels, each
/// written per dimension.
pub trait Launches: Dim {
    /// Records the three kernels of one step on `tape` and returns the new state (inputs
    /// already checked).
    fn launch_step<R: Real>(
        mpm: &Mpm<R, Self>,
        tape: &mut Tape,
        state: &MpmState<R, Self>,
        actuation: &Array<R>,
        dt: f64,
    ) -> MpmState<R, Self>;
}

/// The grid arrays of a step: momentum, mass, velocity.
type Grid<R, D> = (Array<<D as Dim>::V<R>>, Array<R>, Array<<D as Dim>::V<R>>);

/// The fresh arrays of a step: the next state and the grid.
fn fresh<R: Real, D: Dim>(n: usize, ng: usize) -> (MpmState<R, D>, Grid<R, D>) {
    let cells = ng.pow(D::D as u32);
    (
        MpmState {
            x: Array::zeros(n).named("mpm.x"),
            v: Array::zeros(n).named("mpm.v"),
            c: Array::zeros(n).named("mpm.C"),
            f: Array::zeros(n).named("mpm.F"),
            jp: Array::zeros(n).named("mpm.Jp"),
        },
        (
            Array::zeros(cells).named("mpm.grid_mv"),
            Array::zeros(cells).named("mpm.grid_m"),
            Array::zeros(cells).named("mpm.grid_v"),
        ),
    )
}

/// [`Launches`] for a dimension, through the function `$name`: the same three launches in 2D
/// and 3D but for the kernels, and the 3D kernels' `stencil` bound. Compiled in this crate for
/// `f32` and `f64` (`crate::precompiled`): examples, tests and user crates link to it instead
/// of compiling the three kernels' forward, adjoint and tangent again.
macro_rules! launch_step {
    ($name:ident, $d:ty, $p2g:ident, $grid:ident, $g2p:ident $(, $stencil:expr)?) => {
        precompiled! {
            fn $name(
                mpm: &Mpm<R, $d>,
                tape: &mut Tape,
                s: &MpmState<R, $d>,
                actuation: &Array<R>,
                dt: f64,
            ) -> MpmState<R, $d> {
                let (n, ng) = (mpm.particle_count(), mpm.n_grid);
                let (dx, dtr) = (R::lit(mpm.dx), R::lit(dt));
                let (next, (mv, m, gv)) = fresh::<R, $d>(n, ng);
                let p = (&mpm.mass, &mpm.volume, &mpm.mu, &mpm.lambda, &mpm.kind);
                let y = (&mpm.compression, &mpm.stretch, &mpm.hardening);
                let a = (&mpm.actuator, &mpm.act_gain, &mpm.fiber);
                tape.launch(
                    $p2g,
                    n,
                    (
                        &s.x, &s.v, &s.c, &s.f, &s.jp, p.0, p.1, p.2, p.3, p.4, y.0, y.1, y.2,
                        a.0, a.1, a.2, actuation, ng, $($stencil,)? dx, dtr, &next.f, &next.jp,
                        &mv, &m,
                    ),
                );
                let (cells, friction) = (ng.pow(<$d as Dim>::D as u32), R::lit(mpm.friction));
                let grid = (&mv, &m, &mpm.gravity, ng, mpm.bound, friction, dtr, &gv);
                tape.launch($grid, cells, grid);
                tape.launch(
                    $g2p,
                    n,
                    (&s.x, &gv, ng, $($stencil,)? dx, dtr, &next.x, &next.v, &next.c),
                );
                next
            }
        }

        impl Launches for $d {
            fn launch_step<R: Real>(
                mpm: &Mpm<R, Self>,
                tape: &mut Tape,
                state: &MpmState<R, Self>,
                actuation: &Array<R>,
                dt: f64,
            ) -> MpmState<R, Self> {
                $name(mpm, tape, state, actuation, dt)
            }
        }
    };
}

launch_step!(launch_step2, D2, mpm_p2g, mpm_grid_update, mpm_g2p);
launch_step!(
    launch_step3,
    D3,
    mpm3_p2g,
    mpm3_grid_update,
    mpm3_g2p,
    3usize
);

impl<R: Real, D: Launches> Mpm<R, D> {
    /// One MLS-MPM step of `dt`: particle to grid ([`mpm_p2g`](super::kernels::mpm_p2g)),
    /// grid update ([`mpm_grid_update`](super::kernels::mpm_grid_update)), grid to particle
    /// ([`mpm_g2p`](super::kernels::mpm_g2p); the `mpm3_*` kernels in 3D), all on `tape`;
    /// returns the new state. `actuation` holds one value per actuator (`None`: all zero).
    ///
    /// Errors ([`Error::InvalidInput`]) instead of a panic or a NaN later: a `dt` that is not
    /// finite and positive, an actuation array or a state array of the wrong length, and, in
    /// the input state or the one the step produced, a particle that is not finite, has left
    /// the domain inside the walls, has a plastic volume ratio `Jp` that is not finite and
    /// positive, or is inverted where its material needs `det F > 0`; a snow particle's yield
    /// strains or hardening out of range
    /// (naming it; the step was unstable: reduce `dt` below [`Mpm::stable_dt`]).
    pub fn step(
        &self,
        tape: &mut Tape,
        state: &MpmState<R, D>,
        actuation: Option<&Array<R>>,
        dt: f64,
    ) -> Result<MpmState<R, D>, Error> {
        if !(dt.is_finite() && dt > 0.0) {
            return Err(invalid("dt", format!("{dt} must be finite and positive")));
        }
        let actuation = match actuation {
            None => &self.no_actuation,
            Some(a) if a.len() == self.n_actuators && self.n_actuators > 0 => a,
            Some(a) if a.is_empty() && self.n_actuators == 0 => &self.no_actuation,
            Some(a) => {
                return Err(invalid(
                    &a.label(),
                    format!(
                        "the actuation array has {} elements; the model has {} actuators",
                        a.len(),
                        self.n_actuators
                    ),
                ));
            }
        };
        self.check_state(state, "the step's input")?;
        let next = D::launch_step(self, tape, state, actuation, dt);
        // The new state is checked too, so that the last step of a rollout cannot hand on a
        // NaN or an inverted particle without an error.
        self.check_state(&next, "the step's result")?;
        Ok(next)
    }
}
