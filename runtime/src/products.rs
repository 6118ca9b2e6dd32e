//! Jacobian products of what a tape recorded: with `J` the Jacobian of chosen output arrays
//! with respect to chosen input arrays (through every recorded step: kernels, custom steps,
//! implicit solves, a whole rollout),
//! - [`Tape::jvp`]: `J v`, one tangent (forward-mode) pass;
//! - [`Tape::vjp`]: `J^T w`, one adjoint (reverse-mode) pass;
//! - [`Tape::gauss_newton`]: `J^T (J v)`, both: the Gauss-Newton approximation of the Hessian
//!   of `0.5 |r|^2` times `v`, for residuals `r` (the outputs), what a matrix-free
//!   Gauss-Newton or Levenberg-Marquardt solver needs;
//! - [`rollout_jvp`]: `J v` of a rollout run one step on a tape at a time (memory of one step).
//!
//! Vectors are flat `f64`: each array's scalars in order (an `Array<Vec3<R>>` of `n` elements
//! gives `3 n`: `x0, y0, z0, x1, ..`), the arrays one after the other in the order given.
//! The inputs must be leaves of the tape (no recorded step writes them: parameters, an initial
//! state); every other array the tape reads is held constant. The passes overwrite the
//! tangent and gradient buffers of the arrays on the tape (as `tangent` and `backward` do), so
//! call them apart from a gradient you still need.
//!
//! ```
//! use adflex_runtime::prelude::*;
//! use adflex_macros::diff_kernel;
//!
//! #[diff_kernel]
//! fn square(x: &Array<f64>, k: &Array<f64>, y: &Array<f64>) {
//!     let i = tid();
//!     y[i] = k[0] * x[i] * x[i];
//! }
//!
//! let x = Array::from_vec(vec![1.0, 2.0]);
//! let k = Array::from_vec(vec![3.0]);
//! let y = Array::zeros(2);
//! let mut tape = Tape::new();
//! tape.launch(square, 2, (&x, &k, &y));
//! // y = k x^2: J = [[2 k x0, 0, x0^2], [0, 2 k x1, x1^2]] over (x0, x1, k).
//! let jv = tape.jvp(&[&x, &k], &[1.0, 0.0, 1.0], &[&y]).unwrap();
//! assert_eq!(jv, vec![6.0 + 1.0, 4.0]);
//! let jtw = tape.vjp(&[&y], &[1.0, 1.0], &[&x, &k]).unwrap();
//! assert_eq!(jtw, vec![6.0, 12.0, 5.0]);
//! let gn = tape.gauss_newton(&[&x, &k], &[&y], &[1.0, 0.0, 1.0]).unwrap();
//! assert_eq!(gn, vec![6.0 * 7.0, 12.0 * 4.0, 7.0 + 4.0 * 4.0]);
//! ```

use std::collections::HashSet;

use crate::array::AnyArray;
use crate::checkpoint::Checkpoint;
use crate::error::Error;
use crate::tape::Tape;

/// `v`'s length against the arrays' scalars, or an error naming `what` and the arrays.
fn check_len(what: &str, arrays: &[&dyn AnyArray], v: &[f64]) -> Result<(), Error> {
    let n: usize = arrays.iter().map(|&a| a.n_scalars()).sum();
    if v.len() == n {
        return Ok(());
    }
    let names: Vec<String> = arrays
        .iter()
        .map(|a| format!("{} ({} scalars)", a.label(), a.n_scalars()))
        .collect();
    Err(Error::InvalidInput {
        what: what.to_string(),
        message: format!(
            "has {} entries, the arrays {} have {n} scalars together",
            v.len(),
            names.join(", ")
        ),
    })
}

/// An error naming `what[k]` for the first entry that is not finite.
fn check_finite(what: &str, v: &[f64]) -> Result<(), Error> {
    match v.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(k) => Err(Error::InvalidInput {
            what: format!("{what}[{k}]"),
            message: format!("{} is not finite", v[k]),
        }),
    }
}

/// The arrays' scalars of `buffer` (their tangent or gradient), zeros where there is none.
fn flat(
    arrays: &[&dyn AnyArray],
    buffer: impl Fn(&dyn AnyArray) -> Option<Box<dyn AnyArray>>,
) -> Vec<f64> {
    let mut out = Vec::new();
    for &a in arrays {
        match buffer(a) {
            Some(b) => out.extend((0..a.n_scalars()).map(|k| b.scalar(k))),
            None => out.resize(out.len() + a.n_scalars(), 0.0),
        }
    }
    out
}

impl Tape {
    /// The inputs must be distinct leaves (an input a recorded step writes would have its
    /// tangent computed, not given), and every output written by a recorded step or one of the inputs
    /// (an array the tape never wrote, from another tape say, would silently give zeros):
    /// an error naming the first that is not.
    fn check_arrays(
        &self,
        what: &str,
        inputs: &[&dyn AnyArray],
        outputs: &[&dyn AnyArray],
    ) -> Result<(), Error> {
        self.require_recording(what)?;
        let written = self.written_ids();
        if let Some(a) = inputs.iter().find(|a| written.contains(&a.id())) {
            return Err(Error::InvalidInput {
                what: format!("{what}: input `{}`", a.label()),
                message: "is written by a recorded step; Jacobian products are with respect \
                          to the tape's leaves (parameters, an initial state), not to an \
                          intermediate array"
                    .into(),
            });
        }
        let mut given = HashSet::new();
        if let Some(a) = inputs.iter().find(|a| !given.insert(a.id())) {
            return Err(Error::InvalidInput {
                what: format!("{what}: input `{}`", a.label()),
                message: "is given twice; give each input array once".into(),
            });
        }
        match outputs
            .iter()
            .find(|o| !written.contains(&o.id()) && !given.contains(&o.id()))
        {
            None => Ok(()),
            Some(o) => Err(Error::InvalidInput {
                what: format!("{what}: output `{}`", o.label()),
                message: "no step recorded on this tape writes it (is it from another tape?)"
                    .into(),
            }),
        }
    }

    /// `J v`, `J` the Jacobian of `outputs` with respect to `inputs` (leaves of the tape), by
    /// one tangent pass ([`Tape::tangent`]) with `v` on the inputs and zero on every other
    /// array the tape reads. `v` has the inputs' scalars, the result the outputs' (see the
    /// [module docs](crate::products)).
    ///
    /// Errors: [`Error::InvalidInput`] if `v` has the wrong length, an input is written by a
    /// recorded step, or an output is neither written by one nor an input; the errors of
    /// [`Tape::tangent`] (a custom step without a tangent, an
    /// array changed since it was recorded).
    pub fn jvp(
        &mut self,
        inputs: &[&dyn AnyArray],
        v: &[f64],
        outputs: &[&dyn AnyArray],
    ) -> Result<Vec<f64>, Error> {
        check_len("Tape::jvp: v", inputs, v)?;
        check_finite("Tape::jvp: v", v)?;
        self.check_arrays("Tape::jvp", inputs, outputs)?;
        let chosen: HashSet<u64> = inputs.iter().map(|a| a.id()).collect();
        // The tape's other leaves count as constant: no tangent buffer (a zeroed one would
        // stay on the model's arrays, and solvers refuse tangents on arrays they do not
        // differentiate).
        for input in self.inputs() {
            if !chosen.contains(&input.array.id()) {
                input.array.clear_tangent();
            }
        }
        let mut k = 0;
        for &a in inputs {
            a.reset_tangent();
            let t = a.tangent_any().expect("reset_tangent allocates it");
            for i in 0..a.n_scalars() {
                t.set_scalar(i, v[k]);
                k += 1;
            }
        }
        self.tangent()?;
        Ok(flat(outputs, |a| a.tangent_any()))
    }

    /// `J^T w`, `J` the Jacobian of `outputs` with respect to `inputs` (leaves of the tape), by
    /// one adjoint pass seeded with `w` on the outputs. `w` has the outputs' scalars, the
    /// result the inputs'. An output listed twice gets the sum of its seeds (`J^T (w1 + w2)`).
    /// The inputs need not require grad; the gradient buffers on the tape are zeroed first and
    /// hold the pass's results after.
    ///
    /// Errors: [`Error::InvalidInput`] as for [`Tape::jvp`]; the errors of [`Tape::backward`].
    pub fn vjp(
        &mut self,
        outputs: &[&dyn AnyArray],
        w: &[f64],
        inputs: &[&dyn AnyArray],
    ) -> Result<Vec<f64>, Error> {
        check_len("Tape::vjp: w", outputs, w)?;
        check_finite("Tape::vjp: w", w)?;
        self.check_arrays("Tape::vjp", inputs, outputs)?;
        self.zero();
        for &a in inputs.iter().chain(outputs) {
            a.zero_grad();
        }
        let mut k = 0;
        let mut seeded = HashSet::new();
        let mut unique: Vec<&dyn AnyArray> = Vec::new();
        for &o in outputs {
            o.ensure_grad();
            let g = o.grad_any().expect("ensure_grad allocates it");
            for i in 0..o.n_scalars() {
                g.set_scalar(i, g.scalar(i) + w[k]);
                k += 1;
            }
            if seeded.insert(o.id()) {
                unique.push(o);
            }
        }
        let sources = inputs.iter().map(|a| a.id()).collect();
        self.backward_seeded(&unique, &sources)?;
        Ok(flat(inputs, |a| a.grad_any()))
    }

    /// The Gauss-Newton product `J^T (J v)`: [`Tape::jvp`], then [`Tape::vjp`] seeded with its
    /// result. For residuals `r` (the outputs) of a least-squares loss `0.5 |r|^2`, the
    /// Gauss-Newton approximation of the loss's Hessian (with respect to the inputs) times
    /// `v`, at the cost of one tangent and one adjoint pass, without forming `J`.
    pub fn gauss_newton(
        &mut self,
        inputs: &[&dyn AnyArray],
        outputs: &[&dyn AnyArray],
        v: &[f64],
    ) -> Result<Vec<f64>, Error> {
        let jv = self.jvp(inputs, v, outputs)?;
        self.vjp(outputs, &jv, inputs)
    }
}

/// `J v` of a rollout without keeping it on a tape: the rollout runs step by step, each step
/// recorded on a fresh tape and its tangent pass run at once with the tangents the previous
/// step left on the state, so memory is one step's, whatever the number of steps (forward
/// mode needs no checkpoints). `step(tape, state, k)` records step `k` and returns the new
/// state (as for [`crate::checkpoint::checkpointed`]); `params` are the leaves every step
/// reads (stiffnesses, controls), with tangent `v_params`, and `v_init` is the tangent of
/// `init` (its [`Checkpoint::arrays`] in order). Returns the final state and its tangent
/// (flat over its arrays): bit for bit what [`Tape::jvp`] gives on a tape of the whole
/// rollout.
///
/// Errors: [`Error::InvalidInput`] for a vector of the wrong length; a step's error, or
/// its tangent pass's, with the step's index.
pub fn rollout_jvp<S: Checkpoint>(
    init: &S,
    steps: usize,
    mut step: impl FnMut(&mut Tape, &S, usize) -> Result<S, Error>,
    params: &[&dyn AnyArray],
    v_params: &[f64],
    v_init: &[f64],
) -> Result<(S, Vec<f64>), Error> {
    check_len("rollout_jvp: v_params", params, v_params)?;
    check_len("rollout_jvp: v_init", &init.arrays(), v_init)?;
    let mut state = init.snapshot();
    let mut v_state = v_init.to_vec();
    for k in 0..steps {
        let mut tape = Tape::new();
        let next =
            step(&mut tape, &state, k).map_err(|e| e.in_context(format!("rollout step {k}")))?;
        let mut inputs: Vec<&dyn AnyArray> = params.to_vec();
        inputs.extend(state.arrays());
        let mut v = v_params.to_vec();
        v.extend_from_slice(&v_state);
        v_state = tape
            .jvp(&inputs, &v, &next.arrays())
            .map_err(|e| e.in_context(format!("rollout step {k}")))?;
        state = next;
    }
    Ok((state, v_state))
}
