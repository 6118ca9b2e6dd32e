//! Second order: Hessian-vector products of a scalar loss, by forward mode over reverse.
//!
//! Build the simulation in [`Dual`] (every kernel and model generic over `R: Real` runs in it),
//! with the parameters as `Dual` arrays that require grad. [`hvp`] sets the parameters'
//! derivative parts to `v`, records the loss on a fresh tape, runs the backward pass, and
//! reads the gradients: their values are `∇L`, their derivative parts `H v`, the derivative of
//! the whole backward pass along `v` (the adjoint code differentiated forward, rule by rule).
//! One product costs one forward and one backward pass in `Dual` arithmetic: 3.8 to 4.2
//! gradients on the cloth benchmark (`adflex-bench second-order`, `docs/performance.md`).
//!
//! It goes through whatever runs in the scalar type: loops, `atomic_add`, stores, every
//! builtin, `#[diff_func]`s with generated rules, checkpointed rollouts ([`hvp_with`]), and
//! the library's solvers, whose custom steps carry the derivative parts through their `f64`
//! solves (implicit Euler's and `Equilibrium`'s implicit-function-theorem adjoints with the
//! theorem's second-order term, the fluids' CG pressure, the articulations' factorization).
//! It refuses what would silently drop the derivative parts: a custom step
//! ([`Tape::record_fn`]) or a `#[diff_func]` custom adjoint not declared dual-safe, and a
//! solver step without a second-order rule ([`refuse_dual`]) says so with an error.
//!
//! ```
//! use adflex_runtime::prelude::*;
//! use adflex_runtime::second_order::hvp;
//!
//! // L(x) = sum_i x_i^2 x_{i+1}: H is tridiagonal.
//! #[adflex_macros::diff_kernel]
//! fn chain<R: Real>(x: &Array<R>, loss: &Array<R>) {
//!     let i = tid();
//!     loss.atomic_add(0, x[i] * x[i] * x[i + 1]);
//! }
//!
//! let x = Array::from_vec(vec![Dual::constant(1.0), Dual::constant(2.0), Dual::constant(3.0)])
//!     .requires_grad();
//! let out = hvp(&[&x], &[1.0, 0.0, 0.0], |tape| {
//!     let loss = Array::<Dual>::zeros(1);
//!     tape.launch(chain, 2, (&x, &loss));
//!     Ok(loss)
//! })?;
//! // L = x0^2 x1 + x1^2 x2: H e0 = (2 x1, 2 x0, 0) = (4, 2, 0).
//! assert_eq!(out.hv, vec![4.0, 2.0, 0.0]);
//! assert_eq!(out.grad, vec![4.0, 1.0 + 12.0, 4.0]);
//! assert_eq!(out.loss, 14.0);
//! # Ok::<(), Error>(())
//! ```

use crate::{AnyArray, Array, Dual, Element, Error, Tape};

/// One Hessian-vector product, with the loss and gradient that came with it.
#[derive(Clone, Debug, PartialEq)]
pub struct Hvp {
    /// The loss `L(p)`.
    pub loss: f64,
    /// `∇L(p)`, the parameters' components in order.
    pub grad: Vec<f64>,
    /// `H v = ∇²L(p) v`.
    pub hv: Vec<f64>,
    /// `∇L · v`, the loss's derivative along `v` (a check on `grad`).
    pub slope: f64,
}

/// `H v` of the loss `loss(tape)` records on a fresh tape (the sum of the returned array's
/// components), over `params`, by one forward and one backward pass in [`Dual`] (see the
/// module's docs). `v` has one entry per scalar component of the parameters, in order.
///
/// Errors: [`Error::InvalidInput`] naming the parameter if one is not a `Dual` array or does
/// not require grad, or if `v` has the wrong length or a non-finite entry, or if the loss is
/// not `Dual`, or if an array is given twice; the closure's and `backward`'s errors (among
/// them a custom step not declared dual-safe). The parameters' derivative parts are zero again
/// on return, also after an error.
pub fn hvp<L: Element>(
    params: &[&dyn AnyArray],
    v: &[f64],
    loss: impl FnOnce(&mut Tape) -> Result<Array<L>, Error>,
) -> Result<Hvp, Error> {
    hvp_with(params, v, || {
        if !L::DUAL {
            return Err(Error::InvalidInput {
                what: "the loss".into(),
                message: format!(
                    "it is an array of `{}`; a second-order pass needs the simulation and its \
                     loss computed in `Dual`",
                    std::any::type_name::<L>()
                ),
            });
        }
        let mut tape = Tape::new();
        let l = loss(&mut tape)?;
        tape.backward(&l)?;
        let n = l.len() * L::DIM;
        Ok(Dual::new(
            (0..n).map(|k| l.scalar(k)).sum(),
            (0..n).map(|k| l.eps_scalar(k)).sum(),
        ))
    })
}

/// [`hvp`] for a loss that `eval()` computes *and backpropagates* itself (e.g. a
/// [`checkpointed`](crate::checkpoint::checkpointed) rollout in `Dual`), returning its value
/// (whose derivative part is `∇L · v`). The parameters' gradients are zeroed before the call.
pub fn hvp_with(
    params: &[&dyn AnyArray],
    v: &[f64],
    eval: impl FnOnce() -> Result<Dual, Error>,
) -> Result<Hvp, Error> {
    let n = check_params(params)?;
    if v.len() != n {
        return Err(Error::InvalidInput {
            what: "v".into(),
            message: format!(
                "it has {} entries; the parameters have {n} scalar components",
                v.len()
            ),
        });
    }
    if let Some(k) = v.iter().position(|x| !x.is_finite()) {
        return Err(Error::InvalidInput {
            what: format!("v[{k}]"),
            message: format!("{} is not finite", v[k]),
        });
    }
    set_direction(params, Some(v));
    // The direction is cleared on every exit, a panic in `eval` included.
    struct Clear<'a, 'b>(&'a [&'b dyn AnyArray]);
    impl Drop for Clear<'_, '_> {
        fn drop(&mut self) {
            set_direction(self.0, None);
        }
    }
    let clear = Clear(params);
    for p in params {
        p.reset_grad();
    }
    let out = eval();
    drop(clear);
    let l = out?;
    if !l.re.is_finite() {
        return Err(Error::InvalidInput {
            what: "the loss".into(),
            message: format!(
                "is {}: the simulation diverged at these parameter values",
                l.re
            ),
        });
    }
    let (mut grad, mut hv) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for p in params {
        let g = p.grad_any().expect("reset_grad allocated it");
        for k in 0..g.n_scalars() {
            let (x, h) = (g.scalar(k), g.eps_scalar(k));
            if !x.is_finite() || !h.is_finite() {
                return Err(Error::NonFinite {
                    kernel: "Hessian-vector product".into(),
                    launch: 0,
                    param: if x.is_finite() { "H v" } else { "gradient" }.into(),
                    array: p.label(),
                    index: k / g.element_dim().max(1),
                    pass: "second-order",
                });
            }
            grad.push(x);
            hv.push(h);
        }
    }
    Ok(Hvp {
        loss: l.re,
        grad,
        hv,
        slope: l.eps,
    })
}

/// The dense Hessian, column by column (`n` products of [`hvp`] with unit vectors): for
/// small parameter counts and tests.
pub fn hessian<L: Element>(
    params: &[&dyn AnyArray],
    mut loss: impl FnMut(&mut Tape) -> Result<Array<L>, Error>,
) -> Result<Vec<Vec<f64>>, Error> {
    let n = check_params(params)?;
    (0..n)
        .map(|j| {
            let e: Vec<f64> = (0..n).map(|i| if i == j { 1.0 } else { 0.0 }).collect();
            hvp(params, &e, &mut loss).map(|h| h.hv)
        })
        .collect()
}

/// The number of scalar components, after checking every parameter is a `Dual` array that
/// requires grad.
fn check_params(params: &[&dyn AnyArray]) -> Result<usize, Error> {
    let mut n = 0;
    let mut given = std::collections::HashSet::new();
    for (i, p) in params.iter().enumerate() {
        let what = || format!("parameter {i} (`{}`)", p.label());
        // One direction per array: a second copy's would overwrite the first's.
        if !given.insert(p.id()) {
            return Err(Error::InvalidInput {
                what: what(),
                message: "is given twice; give each parameter array once".into(),
            });
        }
        if !p.is_dual() {
            return Err(Error::InvalidInput {
                what: what(),
                message: "it is not an array of `Dual` (or of vectors of `Dual`): a second-order \
                          pass needs the simulation built with `R = Dual`"
                    .into(),
            });
        }
        if !p.is_requires_grad() {
            return Err(Error::InvalidInput {
                what: what(),
                message: "it does not require grad: call `.requires_grad()` on it".into(),
            });
        }
        n += p.n_scalars();
    }
    Ok(n)
}

/// Sets the parameters' derivative parts to `v` (zero for `None`).
fn set_direction(params: &[&dyn AnyArray], v: Option<&[f64]>) {
    let mut k = 0;
    for p in params {
        for j in 0..p.n_scalars() {
            p.set_eps_scalar(j, v.map_or(0.0, |v| v[k]));
            k += 1;
        }
    }
}

/// `Err` naming `step` when `R` is [`Dual`]: for host code that computes in `f64` and would
/// drop the derivative parts (a solver, a factorization), so that a second-order pass through
/// it is an error, not a silently wrong product. `instead` says what to use.
pub fn refuse_dual<R: crate::Real>(step: &str, instead: &str) -> Result<(), Error> {
    if R::DUAL {
        return Err(Error::InvalidInput {
            what: step.into(),
            message: format!(
                "it computes in f64 and has no second-order rule, so a Hessian-vector product \
                 (`Dual` scalar) cannot go through it; {instead}"
            ),
        });
    }
    Ok(())
}
