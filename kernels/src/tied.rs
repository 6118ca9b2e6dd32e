//! Parameters an optimizer sees other than the model's per-element arrays: **tied** parameters
//! (one value for all elements of a force's parameter, or one per group of elements) and
//! **control sequences** (a control per time step). Both are small arrays of their own that an
//! optimizer updates; a launch recorded on the tape spreads them onto what the simulation reads,
//! so gradients flow back to them through every integrator (implicit Euler included) and the
//! [`Model`] is never cloned or rebuilt.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_kernels::tied::Tied;
//! use adflex_runtime::prelude::*;
//!
//! // Three springs sharing one stiffness.
//! let mut b = ModelBuilder::<f64>::new();
//! let p: Vec<u32> = (0..4)
//!     .map(|k| b.add_particle(Vec3::new(k as f64, 0.0, 0.0), Vec3::zeros(), if k == 0 { 0.0 } else { 1.0 }))
//!     .collect();
//! for k in 0..3 {
//!     b.add_spring(p[k], p[k + 1], 100.0 + k as f64, 0.0);
//! }
//! let model = b.finalize();
//! let ke = Tied::all(&model, "springs", "ke").unwrap(); // starts at the mean, 101
//! assert_eq!(ke.values.to_vec(), vec![101.0]);
//!
//! let mut tape = Tape::new();
//! ke.apply(&mut tape); // every spring's ke is now ke.values[0], on the tape
//! let s = SemiImplicitEuler.rollout(&model, &mut tape, &model.state(), None, 1e-2, 10).unwrap();
//! let loss = Array::zeros(1);
//! adflex_kernels::losses::distance_to_target(&mut tape, &s.x, &[3], Vec3::new(3.0, -0.1, 0.0), 1.0, &loss);
//! tape.backward(&loss).unwrap();
//! assert!(ke.values.grad().unwrap().get(0) != 0.0); // the sum over the three springs
//! ```

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::integrators::Integrator;
use crate::model::Model;
use crate::state::{Control, State};

/// `target[tid] = values[group[tid]]`.
#[diff_kernel]
pub fn spread<R: Real>(values: &Array<R>, group: &Array<u32>, target: &Array<R>) {
    let t = tid();
    target[t] = values[group[t]];
}

/// `out[tid] = seq[offset + tid]` (a step's slice of a sequence).
#[diff_kernel]
pub fn slice_vec3<R: Real>(seq: &Array<Vec3<R>>, offset: usize, out: &Array<Vec3<R>>) {
    let t = tid();
    out[t] = seq[offset + t];
}

/// `out[tid] = seq[offset + tid]` (a step's slice of a sequence).
#[diff_kernel]
pub fn slice_scalar<R: Real>(seq: &Array<R>, offset: usize, out: &Array<R>) {
    let t = tid();
    out[t] = seq[offset + t];
}

/// A force's scalar parameter array tied to fewer values: element `k` of the force's array
/// takes `values[group[k]]` whenever [`Tied::apply`] is recorded. Optimize
/// [`Tied::values`]; its gradient is the sum over the elements of each group.
#[derive(Clone, Debug)]
pub struct Tied<R: Real> {
    /// The free values (one per group), requiring a gradient.
    pub values: Array<R>,
    /// The group of each element of the force's array.
    pub group: Array<u32>,
    /// The force's parameter array (a handle sharing the model's data).
    pub target: Array<R>,
}

impl<R: Real> Tied<R> {
    /// One value for every element of parameter `param` of force `force` (e.g. `"tets"`,
    /// `"mu"`), starting at their mean.
    ///
    /// Errors: [`Error::InvalidInput`] if the model has no such scalar parameter array (the
    /// message lists those it has), or if it is empty.
    pub fn all(model: &Model<R>, force: &str, param: &str) -> Result<Self, Error> {
        let n = model.param::<R>(force, param)?.len();
        Self::groups(model, force, param, &vec![0; n])
    }

    /// One value per group: element `k` of parameter `param` of force `force` belongs to group
    /// `group[k]` (groups `0..G`, each used); each value starts at its group's mean.
    ///
    /// Errors: [`Error::InvalidInput`] if there is no such parameter array, if `group` does not
    /// have one entry per element, or if a group in `0..G` has no element.
    pub fn groups(
        model: &Model<R>,
        force: &str,
        param: &str,
        group: &[u32],
    ) -> Result<Self, Error> {
        let target = model.param::<R>(force, param)?;
        let what = format!("{force}.{param}");
        let invalid = |message: String| Error::InvalidInput {
            what: what.clone(),
            message,
        };
        if target.is_empty() {
            return Err(invalid("the array is empty: nothing to tie".into()));
        }
        if group.len() != target.len() {
            return Err(invalid(format!(
                "{} group indices for {} elements: give one per element",
                group.len(),
                target.len()
            )));
        }
        if let Some((k, &g)) = group
            .iter()
            .enumerate()
            .find(|(_, &g)| g as usize >= group.len())
        {
            return Err(invalid(format!(
                "group index {g} of element {k} is not below the number of elements {}",
                group.len()
            )));
        }
        let count = group.iter().max().map_or(0, |&g| g as usize + 1);
        let (mut sum, mut members) = (vec![0.0; count], vec![0usize; count]);
        for (k, &g) in group.iter().enumerate() {
            sum[g as usize] += target.get(k).to_f64();
            members[g as usize] += 1;
        }
        if let Some(g) = members.iter().position(|&m| m == 0) {
            return Err(invalid(format!(
                "group {g} has no element (groups must be 0..{count}, each used)"
            )));
        }
        let values: Vec<R> = sum
            .iter()
            .zip(&members)
            .map(|(s, &m)| R::lit(s / m as f64))
            .collect();
        Ok(Tied {
            values: Array::from_vec(values)
                .named(format!("{what} (tied)"))
                .requires_grad(),
            group: Array::from_vec(group.to_vec()),
            target,
        })
    }

    /// Records [`spread`] on `tape`: the force's array takes the tied values. Record it before
    /// the steps that read them (each evaluation of a loss, on its tape).
    pub fn apply(&self, tape: &mut Tape) {
        tape.launch(
            spread,
            self.target.len(),
            (&self.values, &self.group, &self.target),
        );
    }
}

/// A control per time step: the external particle forces and/or the tetrahedra's activations
/// of every step in one array each (step-major), requiring a gradient, for an optimizer.
/// [`ControlSequence::control`] records the slice of step `k` on the tape.
///
/// ```
/// use adflex_kernels::prelude::*;
/// use adflex_kernels::tied::ControlSequence;
/// use adflex_runtime::prelude::*;
///
/// let mut b = ModelBuilder::<f64>::new();
/// b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
/// b.gravity = Vec3::zeros();
/// let model = b.finalize();
/// let seq = ControlSequence::new(&model, 4).with_particle_forces();
/// seq.particle_f.as_ref().unwrap().set(2, Vec3::new(1.0, 0.0, 0.0)); // step 2 pushes
/// let mut tape = Tape::new();
/// let s = seq.rollout(&SemiImplicitEuler, &model, &mut tape, &model.state(), 0.5).unwrap();
/// assert_eq!(s.v.get(0).x, 0.5); // one push of 1 N for 0.5 s
/// ```
#[derive(Clone, Debug)]
pub struct ControlSequence<R: Real> {
    /// Number of steps.
    pub steps: usize,
    /// Particles per step (the model's).
    pub particles: usize,
    /// Tetrahedra per step (the model's).
    pub tets: usize,
    /// External particle forces (N), `steps x particles`, step-major, if controlled.
    pub particle_f: Option<Array<Vec3<R>>>,
    /// Tetrahedron activations, `steps x tets`, step-major, if controlled.
    pub tet_activation: Option<Array<R>>,
}

impl<R: Real> ControlSequence<R> {
    /// A sequence of `steps` controls for `model`, controlling nothing yet.
    pub fn new(model: &Model<R>, steps: usize) -> Self {
        let tets = model.tets().map_or(0, |t| t.len());
        ControlSequence {
            steps,
            particles: model.particle_count,
            tets,
            particle_f: None,
            tet_activation: None,
        }
    }

    /// Controls the external force on every particle, starting at zero.
    pub fn with_particle_forces(mut self) -> Self {
        self.particle_f = Some(
            Array::zeros(self.steps * self.particles)
                .named("control_particle_f")
                .requires_grad(),
        );
        self
    }

    /// Controls the activation of every tetrahedron, starting at zero (passive).
    pub fn with_tet_activation(mut self) -> Self {
        self.tet_activation = Some(
            Array::zeros(self.steps * self.tets)
                .named("control_tet_activation")
                .requires_grad(),
        );
        self
    }

    /// The control of step `k`, its arrays recorded on `tape` as slices of the sequence.
    ///
    /// Errors: [`Error::InvalidInput`] if `k` is not below [`ControlSequence::steps`].
    pub fn control(&self, tape: &mut Tape, k: usize) -> Result<Control<R>, Error> {
        if k >= self.steps {
            return Err(Error::InvalidInput {
                what: "ControlSequence step".into(),
                message: format!("step {k} of a sequence of {} steps", self.steps),
            });
        }
        let particle_f = self.particle_f.as_ref().map(|seq| {
            let out = Array::zeros(self.particles).named("particle_f");
            tape.launch(slice_vec3, self.particles, (seq, k * self.particles, &out));
            out
        });
        let tet_activation = self.tet_activation.as_ref().map(|seq| {
            let out = Array::zeros(self.tets).named("tet_activation");
            tape.launch(slice_scalar, self.tets, (seq, k * self.tets, &out));
            out
        });
        Ok(Control {
            particle_f,
            tet_activation,
            ..Control::default()
        })
    }

    /// Records [`ControlSequence::steps`] steps of `dt` from `state` with `integrator`, step
    /// `k` under control `k`; returns the final state or the first error (with the step in its
    /// context).
    pub fn rollout<I: Integrator<R> + ?Sized>(
        &self,
        integrator: &I,
        model: &Model<R>,
        tape: &mut Tape,
        state: &State<R>,
        dt: R,
    ) -> Result<State<R>, Error> {
        let mut s = state.clone();
        for k in 0..self.steps {
            let c = self.control(tape, k)?;
            s = integrator
                .step(model, tape, &s, Some(&c), dt)
                .map_err(|e| e.in_context(format!("rollout step {k} of {}", self.steps)))?;
        }
        Ok(s)
    }
}
