//! The physics families, listed once, and what every family offers: a model, a state it
//! advances by one step recorded on a tape, and a control the step reads.
//!
//! A family is a folder (or file) under `kernels/src/` that owns its builder, model, state,
//! kernels and checks; [`Family`] is the common face the rest of the library (and a user's
//! generic code) steps it through, and [`families`] is the one list of them (the architecture
//! table in `docs/architecture.md` is checked against it by a test). Families with models of
//! their own meet in [`coupling`](crate::coupling) through their control inputs.
//!
//! | family | model | state | control |
//! |---|---|---|---|
//! | particles (cloth, soft bodies, rigid bodies, XPBD) | [`ParticleSystem`]: a [`Model`] and its [`Integrator`] | [`State`] | [`Control`] |
//! | articulations | [`Articulations`] | [`ArticulationState`] | [`ArticulationControl`] |
//! | MPM | [`Mpm`] (2D or 3D) | [`MpmState`] | actuation, one value per actuator |
//! | grid fluids | [`FluidGrid`] (2D or 3D) | [`FluidState`] | [`Pressure`] (the projection's solve) |
//!
//! Generic code over families is written once: [`rollout`] steps any family on one tape,
//! [`checkpointed_rollout`] differentiates a long rollout of any family with memory that does
//! not grow with its length.
//!
//! ```
//! use adflex_kernels::family::{self, Family};
//! use adflex_kernels::mpm::{Material, MpmBuilder};
//! use adflex_runtime::prelude::*;
//!
//! // Any family: here an elastic MPM block falling for 20 steps, then the same code for a
//! // robot would only change the model.
//! fn fall<F: Family<f64>>(model: &F, steps: usize, dt: f64) -> Result<F::State, Error> {
//!     let mut tape = Tape::new();
//!     let control = model.default_control();
//!     family::rollout(model, &mut tape, &model.initial_state(), &control, steps, dt)
//! }
//! let mut b = MpmBuilder::new(32, 1.0 / 32.0);
//! let (mu, lambda) = Material::lame(1e4, 0.2);
//! let block = Material::Corotated { mu, lambda };
//! b.add_rect([0.4, 0.4].into(), [0.1, 0.1].into(), 1e-3, 1e-3, block);
//! let mpm = b.finalize::<f64>().unwrap();
//! let end = fall(&mpm, 20, 1e-4)?;
//! assert!(end.v.to_vec().iter().all(|v| v[1] < 0.0));
//! # Ok::<(), Error>(())
//! ```

use adflex_runtime::checkpoint::{checkpointed, Checkpoint, Rollout};
use adflex_runtime::prelude::*;
use adflex_runtime::Element;

use crate::articulation::{ArticulationControl, ArticulationState, Articulations};
use crate::fluid::{FluidGrid, FluidState, Pressure};
use crate::integrators::Integrator;
use crate::model::Model;
use crate::mpm::{Launches, Mpm, MpmState};
use crate::state::{Control, State};

/// What every physics family offers: its initial state, a control, and one step recorded on
/// a tape. Implemented by [`ParticleSystem`], [`Articulations`], [`Mpm`] and [`FluidGrid`].
pub trait Family<R: Real> {
    /// The family's name in [`families`], errors and docs.
    const NAME: &'static str;
    /// What a step advances; checkpointable, so long rollouts of any family can be
    /// differentiated with [`checkpointed_rollout`].
    type State: Checkpoint;
    /// What a step reads besides the state (forces, actuation, targets, settings).
    type Control;

    /// The state the model was built with (new arrays).
    fn initial_state(&self) -> Self::State;
    /// The control a step uses when nothing drives the model (new arrays where it has any).
    fn default_control(&self) -> Self::Control;
    /// Number of worlds (see the "many worlds" sections of the guide; 1 for a family without
    /// them).
    fn n_worlds(&self) -> usize {
        1
    }
    /// One step of `dt` seconds from `state`, recorded on `tape`; the new state.
    ///
    /// Errors: the family's own (an invalid `dt`, a state or control array of the wrong
    /// length, a solve that did not converge, an unstable step; see its `step`).
    fn step(
        &self,
        tape: &mut Tape,
        state: &Self::State,
        control: &Self::Control,
        dt: f64,
    ) -> Result<Self::State, Error>;
}

/// A family in the list: its name and where it lives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FamilyInfo {
    /// [`Family::NAME`].
    pub name: &'static str,
    /// Its folder or file under `kernels/src/`.
    pub path: &'static str,
}

/// Every physics family of the library, in one place: adding a family is its folder, its
/// [`Family`] impl and its line here (and its row in `docs/architecture.md`, checked by a test).
pub fn families() -> Vec<FamilyInfo> {
    vec![
        info::<ParticleSystem<'static, f64>>("model.rs"),
        info::<Articulations<f64>>("articulation/"),
        info::<Mpm<f64>>("mpm/"),
        info::<FluidGrid>("fluid/"),
    ]
}

fn info<F: Family<f64>>(path: &'static str) -> FamilyInfo {
    FamilyInfo {
        name: F::NAME,
        path,
    }
}

/// `steps` steps (at least one) of `family` from `initial` with `control`, on `tape`; the last
/// state. An error names the family and the step it came from (`articulations rollout step k
/// of n`, counted from 0 as [`Integrator::rollout`] does).
pub fn rollout<R: Real, F: Family<R>>(
    family: &F,
    tape: &mut Tape,
    initial: &F::State,
    control: &F::Control,
    steps: usize,
    dt: f64,
) -> Result<F::State, Error> {
    if steps == 0 {
        return Err(Error::InvalidInput {
            what: format!("rollout of {}", F::NAME),
            message: "steps must be at least 1".into(),
        });
    }
    let mut state = family
        .step(tape, initial, control, dt)
        .map_err(|e| at::<R, F>(e, 0, steps))?;
    for k in 1..steps {
        state = family
            .step(tape, &state, control, dt)
            .map_err(|e| at::<R, F>(e, k, steps))?;
    }
    Ok(state)
}

/// A rollout of `steps` steps (at least one) of `family`, differentiated with a checkpoint
/// every `every` steps: the loss `loss(tape, final state)` and the gradients of the arrays
/// that require them (the model's parameters, the control's, the initial state's), with the
/// memory of `every` steps' intermediates and `steps / every` states instead of the whole
/// tape (as [`Checkpointed`]; an error names its step).
pub fn checkpointed_rollout<R: Real, F: Family<R>, L: Element>(
    family: &F,
    initial: &F::State,
    control: &F::Control,
    steps: usize,
    every: usize,
    dt: f64,
    mut loss: impl FnMut(&mut Tape, &F::State) -> Result<Array<L>, Error>,
) -> Result<Rollout<L>, Error> {
    if steps == 0 || every == 0 {
        return Err(Error::InvalidInput {
            what: format!("checkpointed_rollout of {}", F::NAME),
            message: format!("steps ({steps}) and every ({every}) must be at least 1"),
        });
    }
    checkpointed(
        initial,
        steps,
        every,
        |tape, s| family.step(tape, s, control, dt),
        |tape, s| loss(tape, s),
    )
}

fn at<R: Real, F: Family<R>>(e: Error, k: usize, n: usize) -> Error {
    e.in_context(format!("{} rollout step {k} of {n}", F::NAME))
}

/// The particle family (particles with their forces, rigid bodies, XPBD constraints, all in
/// one [`Model`]) stepped by an [`Integrator`].
pub struct ParticleSystem<'a, R: Real> {
    /// The model.
    pub model: &'a Model<R>,
    /// How it is stepped.
    pub integrator: &'a dyn Integrator<R>,
}

impl<'a, R: Real> ParticleSystem<'a, R> {
    /// `model` stepped by `integrator`.
    pub fn new(model: &'a Model<R>, integrator: &'a dyn Integrator<R>) -> Self {
        ParticleSystem { model, integrator }
    }
}

impl<R: Real> Family<R> for ParticleSystem<'_, R> {
    const NAME: &'static str = "particles";
    type State = State<R>;
    type Control = Control<R>;

    fn initial_state(&self) -> State<R> {
        self.model.state()
    }
    fn default_control(&self) -> Control<R> {
        Control::default()
    }
    fn n_worlds(&self) -> usize {
        self.model.worlds.len()
    }
    fn step(
        &self,
        tape: &mut Tape,
        state: &State<R>,
        control: &Control<R>,
        dt: f64,
    ) -> Result<State<R>, Error> {
        self.integrator
            .step(self.model, tape, state, Some(control), R::lit(dt))
    }
}

impl<R: Real> Family<R> for Articulations<R> {
    const NAME: &'static str = "articulations";
    type State = ArticulationState<R>;
    type Control = ArticulationControl<R>;

    fn initial_state(&self) -> ArticulationState<R> {
        self.state()
    }
    fn default_control(&self) -> ArticulationControl<R> {
        self.control()
    }
    fn n_worlds(&self) -> usize {
        Articulations::n_worlds(self)
    }
    fn step(
        &self,
        tape: &mut Tape,
        state: &ArticulationState<R>,
        control: &ArticulationControl<R>,
        dt: f64,
    ) -> Result<ArticulationState<R>, Error> {
        Articulations::step(self, tape, state, Some(control), R::lit(dt))
    }
}

impl<R: Real, D: Launches> Family<R> for Mpm<R, D> {
    const NAME: &'static str = "mpm";
    type State = MpmState<R, D>;
    /// One actuation value per actuator (empty for a model without actuators).
    type Control = Array<R>;

    fn initial_state(&self) -> MpmState<R, D> {
        self.state()
    }
    fn default_control(&self) -> Array<R> {
        Array::zeros(self.n_actuators).named("mpm.actuation")
    }
    fn step(
        &self,
        tape: &mut Tape,
        state: &MpmState<R, D>,
        actuation: &Array<R>,
        dt: f64,
    ) -> Result<MpmState<R, D>, Error> {
        Mpm::step(self, tape, state, Some(actuation), dt)
    }
}

impl<R: Real> Family<R> for FluidGrid {
    const NAME: &'static str = "fluid";
    type State = FluidState<R>;
    /// The pressure solve of each step's projection.
    type Control = Pressure;

    /// At rest, without density: a fixed point of the step (set the velocity or the density
    /// before rolling out).
    fn initial_state(&self) -> FluidState<R> {
        FluidState {
            velocity: (0..self.dim())
                .map(|_| Array::zeros(self.cells()).named("velocity"))
                .collect(),
            density: Array::zeros(self.cells()).named("density"),
        }
    }
    /// Conjugate gradients ([`Pressure::cg`]).
    fn default_control(&self) -> Pressure {
        Pressure::cg()
    }
    fn step(
        &self,
        tape: &mut Tape,
        state: &FluidState<R>,
        pressure: &Pressure,
        dt: f64,
    ) -> Result<FluidState<R>, Error> {
        if state.velocity.len() != self.dim() {
            return Err(Error::InvalidInput {
                what: "FluidState::velocity".into(),
                message: format!(
                    "has {} components; the grid is {}D",
                    state.velocity.len(),
                    self.dim()
                ),
            });
        }
        if self.dim() == 2 {
            let (u, v) = (&state.velocity[0], &state.velocity[1]);
            let (u, v, d) = FluidGrid::step(self, tape, u, v, &state.density, dt, pressure)?;
            Ok(FluidState {
                velocity: vec![u, v],
                density: d,
            })
        } else {
            let vel = [&state.velocity[0], &state.velocity[1], &state.velocity[2]];
            let (vel, d) = self.step_3d(tape, vel, &state.density, dt, pressure)?;
            Ok(FluidState {
                velocity: vel.into(),
                density: d,
            })
        }
    }
}
