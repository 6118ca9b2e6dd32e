//! Gauss-Newton through a constraint by its KKT system ([`Optimizer::least_squares_kkt`]).

mod jacobian;
mod system;

use adflex_runtime::{AnyArray, Array, Element, Error, Tape};

use crate::newton::{dot, Direction, LeastSquares, Recorded};
use crate::{Counts, Method, Optimizer, Params, Report, Residuals};

impl Optimizer<'_> {
    /// Gauss-Newton by the KKT system ([`Method::KktGaussNewton`]), for systems of up to
    /// 2,000,000 rows (the residuals, twice the state's scalars and the parameters); run it
    /// with [`Optimizer::least_squares_kkt`]. Its first step takes one tangent sweep per
    /// unknown (state scalars and parameters), the later ones one per colour of the columns.
    pub fn kkt_gauss_newton() -> Self {
        Self::new(Method::KktGaussNewton { largest: 2_000_000 })
    }

    /// Gauss-Newton through a constraint by its KKT system, the formulation of sparse Gauss-Newton
    /// (Zehnder, Coros and Thomaszewski, "SGN: Sparse Gauss-Newton for Accelerated Sensitivity
    /// Analysis", 2021), for a least-squares loss `½ |r(x, p)|²` whose state `x` solves a
    /// constraint `c(x, p) = 0` (a static equilibrium).
    ///
    /// Gauss-Newton through the constraint needs the sensitivity `S = dx/dp = -c_x⁻¹ c_p`: done
    /// matrix free ([`Optimizer::least_squares`] on a tape through the solve), each Gauss-Newton
    /// product `Jᵀ J v` is a linear solve with `c_x` forward and one backward, and a step takes
    /// several. Instead, the step `(dx, dp)` and the multipliers `λ` of the linearized constraint
    /// solve one symmetric, indefinite KKT system,
    ///
    /// ```text
    /// [ Jᵀ J    Cᵀ ] [ (dx, dp) ]   [ -Jᵀ r ]
    /// [ C      0  ] [    λ     ] = [   0   ]
    /// ```
    ///
    /// `J = [r_x r_p]`, `C = [c_x c_p]`; its `dp` is the
    /// Gauss-Newton step (eliminate `dx = S dp`), found without forming `S` and without an inner
    /// iterative solve, so its cost does not grow with the stiffness's condition number.
    ///
    /// The system is sparse, and so is its solve: it is assembled with the linearized residuals
    /// `s = J d + r` as unknowns too (`[-I J 0; Jᵀ 0 Cᵀ; 0 C 0]`, so `Jᵀ J` is never formed and
    /// a residual that reads many unknowns fills nothing in), equilibrated (Ruiz's symmetric
    /// scaling: every row and column of the scaled system has its largest entry near 1,
    /// whatever the units of the state, the parameters and the constraint) and factorized by
    /// faer's sparse LU with partial pivoting, with one step of iterative refinement. `J` and
    /// `C` come from tangent passes over a tape that holds one evaluation of the constraint and
    /// the residuals at `x`. At the first step the sparsity pattern is found by probing:
    /// rounds of 32 passes, each seeded on a random group of the unknowns' elements (an
    /// equation a probe leaves at zero reads none of them), until a round rules out nothing
    /// (a system of fewer than 512 unknowns or 128 elements, or one the probes find dense,
    /// takes one pass per unknown instead). Then one pass per colour of the columns (columns that share no row
    /// are seeded together: a few dozen for a cloth, whatever its size), checked by two more
    /// passes along random directions. If the check fails (the pattern changed: a contact
    /// started touching), the step takes the columns one by one again and the pattern grows.
    /// A residual or constraint scalar that reads many unknowns (more than 64 and an eighth of
    /// them: a sum, a mean) is left out of the colouring, which it would make one colour per
    /// column, and taken by one adjoint pass.
    ///
    /// # The closures
    ///
    /// - `residuals(tape)` solves for the state and records the residuals on a fresh tape,
    ///   differentiably (the constraint's solve recorded with its implicit-function-theorem
    ///   gradient, e.g. `Equilibrium::solve`), and returns the state and the residuals: it
    ///   gives the loss and its gradient, as in [`Optimizer::least_squares`].
    /// - `constrained(tape, x)` records, at the state `x` (a leaf: a copy of the state that
    ///   `residuals` returned), the constraint `c(x, p)` (one scalar per scalar of `x`, e.g.
    ///   `statics::net_force`) and the same residuals, now as functions of `x` and `p`. The
    ///   KKT products run over this tape.
    ///
    /// An iteration is the `residuals` evaluation, its gradient (an adjoint pass through the
    /// solve), one recording of `constrained` and the tangent passes of that small tape (sweeps
    /// over one evaluation of the constraint, far cheaper than a pass through the solve:
    /// counted in [`Report::sweeps`], not in `passes`), the sparse LU solve, and an Armijo
    /// backtracking along the step (one `residuals` evaluation per trial).
    ///
    /// Errors: as [`Optimizer::least_squares`] (an error at a later step ends the run with it,
    /// the parameters holding the lowest-loss values); [`Error::InvalidInput`] naming what is
    /// wrong if the constraint's scalars are not the state's; at the first step, if the
    /// residuals of `constrained` differ from those of `residuals` (relative 1e-6; the array
    /// and component) or their derivatives disagree with the gradient through the solve
    /// (`gᵀdp = -|J d|²` to 1e-3: the closures read the parameters differently); if a
    /// parameter moves neither the constraint nor the residuals of `constrained` (named); if
    /// the KKT system is singular to working precision (its estimated condition number, by
    /// three steps of the power method on the system and on its factorization, above `1e13`,
    /// `1e6` when an input or output is in f32; an estimate from below, so a system just short
    /// of singular can pass: a state the constraint does not determine, or
    /// parameters the residuals cannot tell apart; the estimate is of the equilibrated system,
    /// so parameters of very different units do not look singular); if it has more rows than
    /// [`Method::KktGaussNewton`]'s `largest`; or if a derivative is not finite (naming its
    /// input).
    ///
    /// The constraint holds the parameters the tape of `constrained` reads; with
    /// `statics::net_force`, the pins are held where they are (not parameters here).
    ///
    /// ```
    /// use adflex_optim::{Optimizer, Params};
    /// use adflex_runtime::prelude::*;
    ///
    /// // The state x solves c(x, p) = x³ + x - p = 0 (per component); fit p so that x
    /// // matches a target.
    /// #[adflex_macros::diff_kernel]
    /// fn constraint<R: Real>(x: &Array<R>, p: &Array<R>, c: &Array<R>) {
    ///     let i = tid();
    ///     c[i] = x[i] * x[i] * x[i] + x[i] - p[i];
    /// }
    /// #[adflex_macros::diff_kernel]
    /// fn miss<R: Real>(x: &Array<R>, target: &Array<R>, r: &Array<R>) {
    ///     let i = tid();
    ///     r[i] = x[i] - target[i];
    /// }
    /// // x(p) by Newton, recorded with its gradient dx/dp = 1 / (3 x² + 1).
    /// #[adflex_macros::diff_kernel]
    /// fn solved<R: Real>(p: &Array<R>, x0: &Array<R>, x: &Array<R>) {
    ///     let i = tid();
    ///     let s = x0[i]; // the root, a constant
    ///     // one Newton step from the root: the value stays the root, the derivative is exact
    ///     x[i] = s - (s * s * s + s - p[i]) / (3.0 * s * s + 1.0);
    /// }
    /// fn root(p: f64) -> f64 {
    ///     let mut x = 0.0f64;
    ///     for _ in 0..60 {
    ///         x -= (x * x * x + x - p) / (3.0 * x * x + 1.0);
    ///     }
    ///     x
    /// }
    ///
    /// let n = 4;
    /// let p = Array::from_vec(vec![0.0f64; n]);
    /// let target = Array::from_vec(vec![0.5, -1.0, 1.5, 2.0]);
    /// let residuals = |tape: &mut Tape, x: &Array<f64>| {
    ///     let r = Array::zeros(n);
    ///     tape.launch(miss, n, (x, &target, &r));
    ///     r
    /// };
    /// let report = Optimizer::kkt_gauss_newton()
    ///     .grad_tol(1e-12)
    ///     .progress(false)
    ///     .least_squares_kkt(
    ///         &Params::new().with(&p),
    ///         |tape| {
    ///             let x0 = Array::from_vec(p.to_vec().into_iter().map(root).collect());
    ///             let x = Array::zeros(n);
    ///             tape.launch(solved, n, (&p, &x0, &x));
    ///             let r = residuals(tape, &x);
    ///             Ok((x, r))
    ///         },
    ///         |tape, x| {
    ///             let c = Array::zeros(n);
    ///             tape.launch(constraint, n, (x, &p, &c));
    ///             Ok((c, residuals(tape, x)))
    ///         },
    ///     )
    ///     .unwrap();
    /// assert!(report.converged(), "{report}");
    /// // p = x³ + x at the target.
    /// for (p, t) in p.to_vec().iter().zip(target.to_vec()) {
    ///     assert!((p - (t * t * t + t)).abs() < 1e-8);
    /// }
    /// ```
    pub fn least_squares_kkt<X: Element, C: Element, Rs: Residuals, Rc: Residuals>(
        self,
        params: &Params,
        mut residuals: impl FnMut(&mut Tape) -> Result<(Array<X>, Rs), Error>,
        mut constrained: impl FnMut(&mut Tape, &Array<X>) -> Result<(Array<C>, Rc), Error>,
    ) -> Result<Report, Error> {
        let Method::KktGaussNewton { largest } = self.method else {
            return Err(Error::InvalidInput {
                what: format!("{:?}", self.method),
                message: "`least_squares_kkt` runs Gauss-Newton by the KKT system \
                          (`Optimizer::kkt_gauss_newton`); without a constraint use \
                          `Optimizer::least_squares`"
                    .into(),
            });
        };
        params.check_unbounded("Gauss-Newton by the KKT system")?;
        let config = LeastSquares {
            cg_iters: 0,
            lambda: None,
            max_iters: self.max_iters,
            max_evals: self.max_evals,
        };
        let arrays = params.arrays();
        // The closures' agreement is checked at the first step (later, near a zero-residual
        // fit, rounding would dominate the comparison).
        let mut first = true;
        // The Jacobian's sparsity pattern and colouring, kept from step to step.
        let mut pattern = None;
        let mut direction = |cur: &Recorded, g: &[f64], _tol: f64, counts: &Counts| {
            let state = cur
                .state
                .as_deref()
                .expect("least_squares_kkt's records keep the state");
            let x = Array::<X>::zeros(state.len()).named("state (KKT)");
            for k in 0..state.n_scalars() {
                x.set_scalar(k, state.scalar(k));
            }
            let mut tape = Tape::new();
            let (c, rc) = constrained(&mut tape, &x)?;
            counts.sweeps.set(counts.sweeps.get() + 1);
            let rc = rc.into_arrays();
            let kkt = Kkt::new(&mut tape, &x, &c, &rc, &arrays, cur, first)?;
            let d = kkt.step(largest, counts, &mut pattern, g, first, params)?;
            first = false;
            Ok(d)
        };
        let direction: &mut Direction<'_> = &mut direction;
        self.run_least_squares(
            params,
            config,
            |tape| {
                let (x, r) = residuals(tape)?;
                Ok((Some(Box::new(x) as Box<dyn AnyArray>), r.into_arrays()))
            },
            Some(direction),
        )
    }
}

/// The scalars of `arrays`, in order.
fn values(arrays: &[&dyn AnyArray]) -> Vec<f64> {
    arrays
        .iter()
        .flat_map(|a| (0..a.n_scalars()).map(|k| a.scalar(k)))
        .collect()
}

/// The KKT system of one step, over the tape of `constrained` at the state `x`.
struct Kkt<'t, 'a> {
    tape: &'t mut Tape,
    /// The state, then the parameters.
    inputs: Vec<&'a dyn AnyArray>,
    /// The residuals, then the constraint.
    outputs: Vec<&'a dyn AnyArray>,
    /// Scalars of the state, of the parameters, of the residuals.
    n: usize,
    m: usize,
    nr: usize,
    /// The residuals' values at `x`.
    r: Vec<f64>,
    /// The relative rounding of the derivatives: f32's if any input or output (state,
    /// parameters, constraint, residuals) is in f32.
    epsilon: f64,
}

impl<'t, 'a> Kkt<'t, 'a> {
    /// Checks the constraint's size and that the residuals are those of the recorded point.
    fn new<X: Element, C: Element>(
        tape: &'t mut Tape,
        x: &'a Array<X>,
        c: &'a Array<C>,
        rc: &'a [Box<dyn AnyArray>],
        params: &[&'a dyn AnyArray],
        cur: &Recorded,
        first: bool,
    ) -> Result<Self, Error> {
        let n = x.n_scalars();
        if c.n_scalars() != n {
            return Err(Error::InvalidInput {
                what: format!("least_squares_kkt: constraint `{}`", c.label()),
                message: format!(
                    "has {} scalars and the state {n}: the KKT system needs one equation of the \
                     constraint per unknown of the state",
                    c.n_scalars()
                ),
            });
        }
        let mut outputs: Vec<&dyn AnyArray> = rc.iter().map(|a| &**a).collect();
        let r = values(&outputs);
        if r.len() != cur.rv.len() {
            return Err(Error::InvalidInput {
                what: "least_squares_kkt: the residuals of `constrained`".into(),
                message: format!(
                    "have {} scalars and those of `residuals` {}: both closures must return \
                     the same residuals",
                    r.len(),
                    cur.rv.len()
                ),
            });
        }
        let scale = cur.rv.iter().fold(f64::MIN_POSITIVE, |s, v| s.max(v.abs()));
        // At the first step any difference; at every step a value that is not finite (NaN
        // never compares equal).
        let differs =
            |k: &usize| !r[*k].is_finite() || (first && (r[*k] - cur.rv[*k]).abs() > 1e-6 * scale);
        if let Some(k) = (0..r.len()).find(differs) {
            let (array, index) = locate(&outputs, k);
            return Err(Error::InvalidInput {
                what: format!(
                    "least_squares_kkt: residual `{}` component {index} of `constrained`",
                    array.label()
                ),
                message: format!(
                    "is {:e} at the state `residuals` returned, where `residuals` gave {:e}: \
                     both closures must compute the same residuals (at that state, from the \
                     same parameters)",
                    r[k], cur.rv[k]
                ),
            });
        }
        outputs.push(c);
        let mut inputs: Vec<&dyn AnyArray> = vec![x];
        inputs.extend(params.iter().copied());
        let m = inputs[1..].iter().map(|a| a.n_scalars()).sum();
        let f32s = inputs
            .iter()
            .chain(&outputs)
            .any(|a| a.scalar_epsilon() > f64::EPSILON);
        Ok(Kkt {
            epsilon: if f32s { 1e-6 } else { 1e-13 },
            tape,
            inputs,
            outputs,
            n,
            m,
            nr: r.len(),
            r,
        })
    }

    /// The Gauss-Newton step over the parameters: the KKT system assembled sparse from tangent
    /// passes (the columns of `J` and `C`, coloured once their pattern is known:
    /// [`jacobian`]) and solved by sparse LU ([`system`]). An error if the system has more
    /// than `largest` rows or is singular (no unique Gauss-Newton step).
    fn step(
        self,
        largest: usize,
        counts: &Counts,
        pattern: &mut Option<jacobian::Pattern>,
        g: &[f64],
        first: bool,
        params: &Params,
    ) -> Result<Vec<f64>, Error> {
        let (n, m, nr) = (self.n, self.m, self.nr);
        let k = n + m;
        let dim = nr + 2 * n + m;
        if dim > largest {
            return Err(Error::InvalidInput {
                what: "least_squares_kkt: the KKT system".into(),
                message: format!(
                    "has {dim} rows ({nr} residuals + 2 x {n} state scalars + {m} parameters), \
                     above `Method::KktGaussNewton`'s `largest` ({largest}): raise `largest` if \
                     the memory is there (the factors of a sparse LU), or use \
                     `Optimizer::gauss_newton` with `least_squares`"
                ),
            });
        }
        let mut passes = 0;
        let tol = 100.0 * self.epsilon;
        let starts = |arrays: &[&dyn AnyArray]| -> Vec<usize> {
            let mut starts = vec![0];
            for a in arrays {
                let (dim, at) = (a.element_dim(), starts[starts.len() - 1]);
                starts.extend((1..=a.len()).map(|e| at + e * dim));
            }
            starts
        };
        let (cols, rows) = (starts(&self.inputs), starts(&self.outputs));
        let elements = jacobian::Elements {
            cols: &cols,
            rows: &rows,
        };
        // Tangent passes for the columns, adjoint passes for the dense rows, on one tape.
        let (inputs, outputs) = (&self.inputs, &self.outputs);
        let tape = std::cell::RefCell::new(&mut *self.tape);
        let jc = jacobian::jacobian(
            &mut |v| tape.borrow_mut().jvp(inputs, v, outputs),
            &mut |w| tape.borrow_mut().vjp(outputs, w, inputs),
            &elements,
            pattern,
            tol,
            &mut passes,
        );
        counts.sweeps.set(counts.sweeps.get() + passes);
        let jc = jc?;
        if let Some(j) = (0..k).find(|&j| !jc.col(j).1.iter().all(|v| v.is_finite())) {
            let (array, index) = locate(&self.inputs, j);
            return Err(Error::InvalidInput {
                what: format!("least_squares_kkt: `{}` component {index}", array.label()),
                message: "the derivative of the constraint or the residuals of `constrained` \
                          with respect to it is not finite (at the solved state)"
                    .into(),
            });
        }
        // A parameter neither the constraint nor the residuals of `constrained` read.
        if let Some(j) = (n..k).find(|&j| jc.col(j).1.iter().all(|v| *v == 0.0)) {
            return Err(Error::InvalidInput {
                what: format!(
                    "least_squares_kkt: parameter {}",
                    params.component_name(j - n)
                ),
                message: "moves neither the constraint nor the residuals `constrained` \
                          records (its column of the KKT system is zero): record what depends \
                          on it on `constrained`'s tape too"
                    .into(),
            });
        }
        let d = match system::step(&jc, nr, &self.r, self.epsilon) {
            Ok(d) => d,
            Err(system::Failure::Factorization(why)) => {
                return Err(Error::InvalidInput {
                    what: "least_squares_kkt: the KKT system".into(),
                    message: format!(
                        "could not be factorized ({dim} rows, {} entries): {why}",
                        2 * jc.val.len() + nr
                    ),
                })
            }
            Err(system::Failure::Singular) => {
                return Err(Error::InvalidInput {
                    what: "least_squares_kkt: the KKT system".into(),
                    message: format!(
                    "is singular to working precision ({n} state scalars, {m} parameters, {nr} \
                     residuals): the \
                     constraint's Jacobian in the state is singular (the state is not \
                     determined, e.g. a free mechanism), or the residuals do not determine \
                     the parameters (fewer independent residuals than parameters)"
                ),
                })
            }
        };
        let dp = d[n..].to_vec();
        // At the solution, gᵀdp = -|J d|² (C d = 0): a gradient through `residuals` that
        // disagrees says the two closures differentiate differently.
        let jd = jc.mul(&d);
        let (slope, model) = (dot(g, &dp), jd[..nr].iter().map(|v| v * v).sum::<f64>());
        if first && (slope + model).abs() > 1e-3 * slope.abs().max(model) {
            return Err(Error::InvalidInput {
                what: "least_squares_kkt: the derivatives of `constrained`".into(),
                message: format!(
                    "disagree with the gradient of `residuals`: along the first step the \
                     gradient gives a slope {slope:.6e}, the KKT system's model {:.6e}; both \
                     closures must depend on the parameters alike (a parameter the solve in \
                     `residuals` reads must be read by the constraint in `constrained`, and \
                     the constraint must be the one the solve meets)",
                    -model
                ),
            });
        }
        Ok(dp)
    }
}

/// The array and component of flat index `k` over `arrays`.
fn locate<'a>(arrays: &[&'a dyn AnyArray], mut k: usize) -> (&'a dyn AnyArray, usize) {
    for &a in arrays {
        if k < a.n_scalars() {
            return (a, k);
        }
        k -= a.n_scalars();
    }
    unreachable!("k is within the arrays' scalars")
}
