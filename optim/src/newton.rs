//! Second-order methods: Gauss-Newton and Levenberg-Marquardt on a least-squares loss, with
//! matrix-free Gauss-Newton products (`Tape::gauss_newton`: a tangent and an adjoint pass),
//! and Newton-CG with a trust region on Hessian-vector products by forward over reverse
//! (`adflex_runtime::second_order`). Each step solves its linear system by conjugate
//! gradients, so nothing of size `n²` is formed.

use std::time::Instant;

use adflex_runtime::second_order::{hvp, Hvp};
use adflex_runtime::{AnyArray, Array, Element, Error, Tape};

use crate::cg::{cg, zero_pinned, Curvature, Forcing, LEAST_SQUARES_FORCING, NEWTON_FORCING};
use crate::{norm, Best, Counts, End, Method, Observe, Optimizer, Params, Stop};

impl Optimizer<'_> {
    /// Gauss-Newton ([`Method::GaussNewton`]) with 20 conjugate-gradient iterations per step;
    /// run it with [`Optimizer::least_squares`].
    pub fn gauss_newton() -> Self {
        Self::new(Method::GaussNewton { cg_iters: 20 })
    }

    /// Levenberg-Marquardt ([`Method::LevenbergMarquardt`]) with `λ` starting at 1e-6 times
    /// the curvature along the gradient and 20 conjugate-gradient iterations per step; run it
    /// with [`Optimizer::least_squares`].
    pub fn levenberg_marquardt() -> Self {
        Self::new(Method::LevenbergMarquardt {
            lambda: 1e-6,
            cg_iters: 20,
        })
    }

    /// Newton-CG with a trust region ([`Method::NewtonCg`]) and 20 conjugate-gradient
    /// iterations per step; run it with [`Optimizer::minimize_newton`].
    pub fn newton_cg() -> Self {
        Self::new(Method::NewtonCg { cg_iters: 20 })
    }

    /// Minimizes `½ |r(p)|²` over `params` with [`Method::GaussNewton`] or
    /// [`Method::LevenbergMarquardt`], where `residuals(tape)` records the simulation on a
    /// fresh tape and returns the residual array (every differentiable component is one
    /// residual). The reported loss is `½ |r|²`.
    ///
    /// One iteration records the residuals once (a forward pass), takes the gradient `Jᵀr`
    /// (an adjoint pass), and runs conjugate gradients on `JᵀJ (+ λ I)` with one
    /// Gauss-Newton product (a tangent and an adjoint pass) per CG iteration, to a relative
    /// residual set by Eisenstat and Walker's forcing term (at most 0.1); then one forward
    /// pass per trial point. The CG is preconditioned by the products of the earlier steps
    /// (up to the last 20, kept as a limited-memory BFGS inverse: Morales and Nocedal's
    /// automatic preconditioning), so that a later step takes a few products where the first
    /// may take one per parameter (at most `cg_iters`).
    ///
    /// Bounds ([`Params::bounded`]) are kept by projection: a parameter at a bound whose
    /// gradient pushes it out stays there for the step, which solves for the others, and each
    /// trial point is projected into the bounds (Armijo's test along the projected path;
    /// Levenberg-Marquardt's predicted decrease is the model's along the projected step, one
    /// more product when the projection cuts it; a cut step that no longer descends is
    /// shortened). `grad_tol_rel` measures the projected gradient; `grad_tol` measures the
    /// whole gradient, which does not vanish at an active bound, so a bounded run should set
    /// `grad_tol_rel`. A parameter may start on its bound, not outside it.
    ///
    /// Errors: as [`Optimizer::minimize`]; [`Error::InvalidInput`] for another method, or
    /// naming a parameter that starts outside its bounds.
    ///
    /// ```
    /// use adflex_optim::{Optimizer, Params};
    /// use adflex_runtime::prelude::*;
    ///
    /// // Fit y = a exp(b t) to samples of 2 exp(-1.5 t).
    /// #[adflex_macros::diff_kernel]
    /// fn residual<R: Real>(p: &Array<R>, r: &Array<R>) {
    ///     let i = tid();
    ///     let t = 0.1 * (i as R);
    ///     r[i] = p[0] * exp(p[1] * t) - 2.0 * exp(-1.5 * t);
    /// }
    ///
    /// let p = Array::from_vec(vec![1.0f64, 0.0]);
    /// let report = Optimizer::levenberg_marquardt()
    ///     .grad_tol(1e-12)
    ///     .progress(false)
    ///     .least_squares(&Params::new().with(&p), |tape| {
    ///         let r = Array::zeros(20);
    ///         tape.launch(residual, 20, (&p, &r));
    ///         Ok(r)
    ///     })
    ///     .unwrap();
    /// assert!(report.converged(), "{report}");
    /// assert!((p.get(0) - 2.0).abs() < 1e-8 && (p.get(1) + 1.5).abs() < 1e-8);
    /// ```
    pub fn least_squares<Rs: Residuals>(
        self,
        params: &Params,
        mut residuals: impl FnMut(&mut Tape) -> Result<Rs, Error>,
    ) -> Result<Report, Error> {
        let (cg_iters, lambda) = match self.method {
            Method::GaussNewton { cg_iters } => (cg_iters, None),
            Method::LevenbergMarquardt { lambda, cg_iters } => (cg_iters, Some(lambda)),
            m => {
                return Err(Error::InvalidInput {
                    what: format!("{m:?}"),
                    message: "`least_squares` runs Gauss-Newton or Levenberg-Marquardt \
                              (`Optimizer::gauss_newton`, `Optimizer::levenberg_marquardt`); \
                              minimize a loss with `Optimizer::minimize`"
                        .into(),
                })
            }
        };
        let config = LeastSquares {
            cg_iters,
            lambda,
            max_iters: self.max_iters,
            max_evals: self.max_evals,
        };
        self.run_least_squares(
            params,
            config,
            |tape| Ok((None, residuals(tape)?.into_arrays())),
            None,
        )
    }

    /// The loop of [`Optimizer::least_squares`] and [`Optimizer::least_squares_kkt`]:
    /// `residuals` records the simulation (and returns the solved state, if any, for
    /// `direction`); `direction` replaces the conjugate gradients on Gauss-Newton products.
    pub(crate) fn run_least_squares(
        self,
        params: &Params,
        config: LeastSquares,
        mut residuals: impl FnMut(&mut Tape) -> Result<Solved, Error>,
        mut direction: Option<&mut Direction<'_>>,
    ) -> Result<Report, Error> {
        let start = Instant::now();
        let counts = Counts::default();
        let mut first = true;
        let mut record = |x: &[f64]| -> Result<Recorded, Error> {
            params.set_values(x);
            params.zero_grads();
            let mut tape = Tape::new();
            let (state, r) = residuals(&mut tape)?;
            counts.evaluated(1);
            let outputs: Vec<&dyn AnyArray> = r.iter().map(|a| &**a).collect();
            if std::mem::take(&mut first) {
                params.check_used(&tape, &outputs)?;
            }
            let mut rv = Vec::new();
            for a in &r {
                for k in 0..a.n_scalars() {
                    let v = a.scalar(k);
                    if !v.is_finite() {
                        return Err(Error::InvalidInput {
                            what: format!(
                                "residual `{}` component {k} (evaluation {})",
                                a.label(),
                                counts.evaluations.get()
                            ),
                            message: format!(
                                "is {v}: the simulation diverged at these parameter values"
                            ),
                        });
                    }
                    rv.push(v);
                }
            }
            let loss = 0.5 * rv.iter().map(|x| x * x).sum::<f64>();
            counts.offer(loss, x);
            Ok(Recorded {
                tape,
                r,
                rv,
                loss,
                state,
            })
        };
        self.drive(params, start, &counts, &mut |observe| {
            least_squares_run(
                params,
                &config,
                start,
                &counts,
                &mut record,
                direction.as_deref_mut(),
                observe,
            )
        })
    }

    /// Minimizes the loss `loss(tape)` records (the sum of the returned array's components)
    /// over `params` with [`Method::NewtonCg`]: the simulation and the parameters must be in
    /// [`Dual`](adflex_runtime::Dual) (see [`adflex_runtime::second_order`]), each
    /// Hessian-vector product being one forward and one backward pass in `Dual`.
    ///
    /// An iteration runs Steihaug's truncated conjugate gradients inside the trust region
    /// until a relative residual set by Eisenstat and Walker's forcing term (loose while the
    /// outer iteration converges slowly, tight once it converges fast), a negative curvature
    /// or the region's boundary; then it evaluates the trial point, and the ratio of actual to
    /// predicted decrease accepts it and resizes the region.
    ///
    /// Errors: as [`Optimizer::minimize_with`] (a parameter the loss does not read is not
    /// detected: it keeps its value); those of [`hvp`] (a parameter not `Dual`, a step that
    /// cannot run in `Dual`, a non-finite product at an accepted point);
    /// [`Error::InvalidInput`] for another method or a bounded parameter.
    ///
    /// ```
    /// use adflex_optim::{Optimizer, Params};
    /// use adflex_runtime::prelude::*;
    ///
    /// #[adflex_macros::diff_kernel]
    /// fn rosenbrock<R: Real>(p: &Array<R>, loss: &Array<R>) {
    ///     let x = p[0];
    ///     let y = p[1];
    ///     loss.atomic_add(0, (1.0 - x) * (1.0 - x) + 100.0 * (y - x * x) * (y - x * x));
    /// }
    ///
    /// let p = Array::from_vec(vec![Dual::constant(-1.2), Dual::constant(1.0)]);
    /// let report = Optimizer::newton_cg()
    ///     .grad_tol(1e-9)
    ///     .progress(false)
    ///     .minimize_newton(&Params::new().with(&p), |tape| {
    ///         let loss = Array::<Dual>::zeros(1);
    ///         tape.launch(rosenbrock, 1, (&p, &loss));
    ///         Ok(loss)
    ///     })
    ///     .unwrap();
    /// assert!(report.converged(), "{report}");
    /// assert!((p.get(0).re - 1.0).abs() < 1e-8 && (p.get(1).re - 1.0).abs() < 1e-8);
    /// ```
    pub fn minimize_newton<L: Element>(
        self,
        params: &Params,
        mut loss: impl FnMut(&mut Tape) -> Result<Array<L>, Error>,
    ) -> Result<Report, Error> {
        let Method::NewtonCg { cg_iters } = self.method else {
            return Err(Error::InvalidInput {
                what: format!("{:?}", self.method),
                message: "`minimize_newton` runs Newton-CG (`Optimizer::newton_cg`); minimize \
                          with `Optimizer::minimize` or `Optimizer::least_squares`"
                    .into(),
            });
        };
        params.check_unbounded("Newton-CG")?;
        let start = Instant::now();
        let counts = Counts::default();
        let arrays = params.arrays();
        let mut product = |x: &[f64], v: &[f64], evaluation: bool| -> Result<Hvp, Error> {
            params.set_values(x);
            let n = counts.evaluations.get() + 1;
            let out = hvp(&arrays, v, &mut loss)
                .map_err(|e| e.in_context(format!("Newton-CG, evaluation {n}")))?;
            if evaluation {
                counts.evaluated(2);
                counts.offer(out.loss, x);
            } else {
                counts.passed(2);
            }
            Ok(out)
        };
        let (max_iters, max_evals) = (self.max_iters, self.max_evals);
        self.drive(params, start, &counts, &mut |observe| {
            newton_cg_run(
                params,
                cg_iters,
                max_iters,
                max_evals,
                start,
                &counts,
                &mut product,
                observe,
            )
        })
    }
}

use crate::Report;

/// What [`Optimizer::least_squares`]'s closure returns: one residual array, or several
/// (every differentiable component of each is one residual).
pub trait Residuals {
    /// The arrays, in order.
    fn into_arrays(self) -> Vec<Box<dyn AnyArray>>;
}

impl<T: Element> Residuals for Array<T> {
    fn into_arrays(self) -> Vec<Box<dyn AnyArray>> {
        vec![Box::new(self)]
    }
}

impl<T: Element> Residuals for Vec<Array<T>> {
    fn into_arrays(self) -> Vec<Box<dyn AnyArray>> {
        self.into_iter()
            .map(|a| Box::new(a) as Box<dyn AnyArray>)
            .collect()
    }
}

/// Residuals of two kinds, e.g. positions (`Vec3`) and a regularization of scalar parameters.
impl<A: Residuals, B: Residuals> Residuals for (A, B) {
    fn into_arrays(self) -> Vec<Box<dyn AnyArray>> {
        let mut arrays = self.0.into_arrays();
        arrays.extend(self.1.into_arrays());
        arrays
    }
}

/// A linear operator on flat vectors (a product that can fail).
pub(crate) type Apply<'a> = dyn FnMut(&[f64]) -> Result<Vec<f64>, Error> + 'a;

/// `(x, v, is an evaluation)` -> the loss, gradient and `H v` at `x`.
type Product<'a> = dyn FnMut(&[f64], &[f64], bool) -> Result<Hvp, Error> + 'a;

/// A recorded residual: the tape, the residual arrays, their values and `½ |r|²`, and the
/// solved state the residuals were taken at (for [`Optimizer::least_squares_kkt`]).
pub(crate) struct Recorded {
    pub tape: Tape,
    pub r: Vec<Box<dyn AnyArray>>,
    pub rv: Vec<f64>,
    pub loss: f64,
    pub state: Option<Box<dyn AnyArray>>,
}

/// What a least-squares closure recorded: the solved state (if any) and the residual arrays.
pub(crate) type Solved = (Option<Box<dyn AnyArray>>, Vec<Box<dyn AnyArray>>);

/// A step's direction at a recorded point, given the gradient and the forcing term's relative
/// tolerance (for [`Optimizer::least_squares_kkt`]).
pub(crate) type Direction<'a> =
    dyn FnMut(&Recorded, &[f64], f64, &Counts) -> Result<Vec<f64>, Error> + 'a;

pub(crate) struct LeastSquares {
    pub cg_iters: usize,
    pub lambda: Option<f64>,
    pub max_iters: usize,
    pub max_evals: usize,
}

/// Whether the evaluation budget is spent: the inner loops (backtracking, damping, a trust
/// region's retries) stop there too, not only between iterations.
fn spent(counts: &Counts, max_evals: usize) -> bool {
    counts.evaluations.get() >= max_evals
}

/// Whether a failed evaluation at a trial point is one the methods step back from (the
/// simulation refused the values) rather than an error to return.
fn trial_failure(e: &Error) -> bool {
    matches!(
        e,
        Error::NonFinite { .. } | Error::InvalidInput { .. } | Error::NotConverged { .. }
    )
}

pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn least_squares_run(
    params: &Params,
    config: &LeastSquares,
    start: Instant,
    counts: &Counts,
    record: &mut dyn FnMut(&[f64]) -> Result<Recorded, Error>,
    mut direction: Option<&mut Direction<'_>>,
    observe: &mut Observe<'_>,
) -> Result<(Best, End), Error> {
    let arrays = params.arrays();
    let mut x = params.values();
    // Bounds are kept by projection: a step leaves the parameters pinned at a bound (see
    // `Params::pinned`) where they are and solves for the others, and the trial points are
    // projected into the bounds. Without bounds every step is the unbounded method's.
    let bounded = params.is_bounded();
    if bounded {
        params.check_inside(&x, "Gauss-Newton or Levenberg-Marquardt")?;
    }
    let stationarity = |x: &[f64], g: &[f64]| match bounded {
        true => params.projected_grad_norm(x, g),
        false => norm(g),
    };
    // The point `t` along `d` from `x`, projected, and its first-order change of the loss.
    let along = |x: &[f64], g: &[f64], d: &[f64], t: f64| -> (Vec<f64>, f64) {
        let mut y: Vec<f64> = x.iter().zip(d).map(|(a, b)| a + t * b).collect();
        if !bounded {
            return (y, t * dot(g, d));
        }
        params.project(&mut y);
        let s: Vec<f64> = y.iter().zip(x).map(|(y, x)| y - x).collect();
        let change = dot(g, &s);
        (y, change)
    };
    let mut cur = record(&x)?;
    let gradient = |cur: &mut Recorded| -> Result<Vec<f64>, Error> {
        let Recorded { tape, r, rv, .. } = cur;
        let out: Vec<&dyn AnyArray> = r.iter().map(|a| &**a).collect();
        let g = tape.vjp(&out, rv, &arrays)?;
        counts.passed(1);
        Ok(g)
    };
    let mut g = gradient(&mut cur)?;
    crate::check_finite(params, counts.evaluations.get(), cur.loss, &g)?;
    let point = |loss: f64, x: &[f64], g: &[f64]| Best {
        loss,
        values: x.to_vec(),
        grad_norm: norm(g),
        stationarity: stationarity(x, g),
    };
    let mut best = point(cur.loss, &x, &g);
    let mut forcing = Forcing::new(LEAST_SQUARES_FORCING);
    let mut memory = Curvature::new(x.len());
    // Levenberg-Marquardt's damping (set from the curvature at the first step) and Nielsen's
    // growth factor.
    let mut lambda: Option<f64> = None;
    let mut nu = 2.0;
    for iter in 0.. {
        let it = counts.iteration(iter, cur.loss, norm(&g), start);
        if let Some(stop) = observe(it, stationarity(&x, &g)) {
            // The iterate that passed a convergence test is the answer when its loss ties
            // the lowest one to rounding (at a fit with a residual the last steps change the
            // loss by an ulp either way; the lowest may be an earlier, less converged point).
            let tie = cur.loss - best.loss <= 8.0 * f64::EPSILON * best.loss.abs();
            if matches!(stop, Stop::Converged(_)) && tie {
                best = point(cur.loss, &x, &g);
            }
            return Ok((best, End::Stop(stop)));
        }
        if iter == config.max_iters {
            return Ok((best, End::Stop(Stop::MaxIterations)));
        }
        let tol = forcing.next(stationarity(&x, &g));
        let pinned = bounded.then(|| params.pinned(&x, &g));
        let gn = |rec: &mut Recorded, v: &[f64]| -> Result<Vec<f64>, Error> {
            let Recorded { tape, r, .. } = rec;
            let out: Vec<&dyn AnyArray> = r.iter().map(|a| &**a).collect();
            let p = tape.gauss_newton(&arrays, &out, v)?;
            counts.passed(2);
            Ok(p)
        };
        match config.lambda {
            None => {
                let d = match direction.as_deref_mut() {
                    Some(direction) => direction(&cur, &g, tol, counts)?,
                    None => {
                        let pinned = pinned.as_deref();
                        cg(
                            &g,
                            0.0,
                            config.cg_iters,
                            tol,
                            pinned,
                            &mut memory,
                            &mut |v| gn(&mut cur, v),
                        )?
                    }
                };
                let slope = dot(&g, &d);
                // Backtracking (Armijo) along d.
                let mut t = 1.0;
                let mut failure = None;
                let accepted = loop {
                    if spent(counts, config.max_evals) {
                        return Ok((best, End::Stop(Stop::MaxEvaluations)));
                    }
                    let (trial, change) = along(&x, &g, &d, t);
                    // A projection can cut a step until it no longer descends: shorter then.
                    if bounded && change >= 0.0 {
                        t *= 0.5;
                        if t < 1e-10 {
                            break None;
                        }
                        continue;
                    }
                    match record(&trial) {
                        Ok(rec) if rec.loss <= cur.loss + 1e-4 * change => {
                            break Some((trial, rec))
                        }
                        Ok(_) => {}
                        Err(e) if trial_failure(&e) => failure = Some(e.to_string()),
                        Err(e) => return Err(e),
                    }
                    t *= 0.5;
                    if t < 1e-10 {
                        break None;
                    }
                };
                let Some((trial, rec)) = accepted else {
                    params.set_values(&best.values);
                    return Ok((
                        best,
                        End::NoProgress {
                            message: format!(
                                "no step along the Gauss-Newton direction lowered the loss \
                                 (slope {slope:.3e})"
                            ),
                            non_finite: failure,
                        },
                    ));
                };
                x = trial;
                cur = rec;
            }
            Some(rel) => loop {
                let lam = match lambda {
                    Some(l) => l,
                    None => {
                        // The curvature along the gradient (of the parameters not pinned at a
                        // bound) sets the damping's scale.
                        let mut g = g.clone();
                        zero_pinned(&mut g, pinned.as_deref());
                        let mut jg = gn(&mut cur, &g)?;
                        zero_pinned(&mut jg, pinned.as_deref());
                        memory.push(&g, &jg);
                        let q = dot(&g, &jg) / dot(&g, &g).max(f64::MIN_POSITIVE);
                        (rel * q).max(f64::MIN_POSITIVE)
                    }
                };
                let pin = pinned.as_deref();
                let d = cg(&g, lam, config.cg_iters, tol, pin, &mut memory, &mut |v| {
                    gn(&mut cur, v)
                })?;
                // The Gauss-Newton model's decrease: CG's iterate is A-conjugate to its
                // residual, so dᵀ(JᵀJ + λI)d = -gᵀd.
                let mut predicted = -0.5 * dot(&g, &d) + 0.5 * lam * dot(&d, &d);
                let (trial, _) = along(&x, &g, &d, 1.0);
                if bounded && trial.iter().zip(&x).zip(&d).any(|((y, x), d)| *y != x + d) {
                    // The projection cut the step `s`: the model's decrease along it, by one
                    // more product.
                    let s: Vec<f64> = trial.iter().zip(&x).map(|(y, x)| y - x).collect();
                    let js = gn(&mut cur, &s)?;
                    predicted = -dot(&g, &s) - 0.5 * dot(&s, &js);
                }
                if spent(counts, config.max_evals) {
                    return Ok((best, End::Stop(Stop::MaxEvaluations)));
                }
                let (rho, rec) = match predicted > 0.0 {
                    // No decrease predicted (a cut step): no evaluation, backtrack below.
                    false => (f64::NEG_INFINITY, None),
                    true => match record(&trial) {
                        Ok(rec) => ((cur.loss - rec.loss) / predicted, Some(rec)),
                        Err(e) if trial_failure(&e) => (f64::NEG_INFINITY, None),
                        Err(e) => return Err(e),
                    },
                };
                match rec {
                    Some(rec) if rho > 1e-4 => {
                        lambda = Some(lam * (1.0 - (2.0 * rho - 1.0).powi(3)).max(1.0 / 3.0));
                        nu = 2.0;
                        x = trial;
                        cur = rec;
                        break;
                    }
                    _ => {
                        // The model overshot: first backtrack along d (a forward pass per
                        // halving, no new solve), then damp the next step more.
                        let slope = dot(&g, &d);
                        let mut t = 0.5;
                        let mut taken = None;
                        while slope < 0.0 && t >= 1.0 / 64.0 {
                            if spent(counts, config.max_evals) {
                                return Ok((best, End::Stop(Stop::MaxEvaluations)));
                            }
                            let (trial, change) = along(&x, &g, &d, t);
                            if bounded && change >= 0.0 {
                                t *= 0.5;
                                continue;
                            }
                            match record(&trial) {
                                Ok(rec) if rec.loss <= cur.loss + 1e-4 * change => {
                                    taken = Some((trial, rec));
                                    break;
                                }
                                Ok(_) => {}
                                Err(e) if trial_failure(&e) => {}
                                Err(e) => return Err(e),
                            }
                            t *= 0.5;
                        }
                        if let Some((trial, rec)) = taken {
                            lambda = Some(lam * nu);
                            nu *= 2.0;
                            x = trial;
                            cur = rec;
                            break;
                        }
                        let l = lam * nu;
                        nu *= 2.0;
                        if l > 1e16 * lam.max(f64::MIN_POSITIVE) || !l.is_finite() || nu > 1e30 {
                            params.set_values(&best.values);
                            return Ok((
                                best,
                                End::NoProgress {
                                    message: "Levenberg-Marquardt's damping grew without a \
                                              step lowering the loss"
                                        .into(),
                                    non_finite: None,
                                },
                            ));
                        }
                        lambda = Some(l);
                        if spent(counts, config.max_evals) {
                            return Ok((best, End::Stop(Stop::MaxEvaluations)));
                        }
                        // The trial moved the parameters: record the tape at x again.
                        cur = record(&x)?;
                    }
                }
            },
        }
        g = gradient(&mut cur)?;
        if let Err(e) = crate::check_finite(params, counts.evaluations.get(), cur.loss, &g) {
            return Ok((best, End::Stop(Stop::Diverged(e.to_string()))));
        }
        if cur.loss < best.loss {
            best = point(cur.loss, &x, &g);
        }
    }
    unreachable!("the loop returns")
}

#[allow(clippy::too_many_arguments)]
fn newton_cg_run(
    params: &Params,
    cg_iters: usize,
    max_iters: usize,
    max_evals: usize,
    start: Instant,
    counts: &Counts,
    product: &mut Product<'_>,
    observe: &mut Observe<'_>,
) -> Result<(Best, End), Error> {
    let mut x = params.values();
    let n = x.len();
    let zero = vec![0.0; n];
    let mut cur = product(&x, &zero, true)?;
    crate::check_finite(params, 1, cur.loss, &cur.grad)?;
    let point = |h: &Hvp, x: &[f64]| Best {
        loss: h.loss,
        values: x.to_vec(),
        grad_norm: norm(&h.grad),
        stationarity: norm(&h.grad),
    };
    let mut best = point(&cur, &x);
    let mut forcing = Forcing::new(NEWTON_FORCING);
    let mut radius: Option<f64> = None;
    for iter in 0.. {
        let g = cur.grad.clone();
        let it = counts.iteration(iter, cur.loss, norm(&g), start);
        if let Some(stop) = observe(it, norm(&g)) {
            params.set_values(&best.values);
            return Ok((best, End::Stop(stop)));
        }
        if iter == max_iters {
            params.set_values(&best.values);
            return Ok((best, End::Stop(Stop::MaxIterations)));
        }
        let tol = forcing.next(norm(&g));
        let mut rejected = 0;
        loop {
            // Steihaug's truncated CG on H s = -g inside |s| <= radius.
            let (mut s, mut hs) = (vec![0.0; n], vec![0.0; n]);
            let mut r = g.clone();
            let mut d: Vec<f64> = g.iter().map(|x| -x).collect();
            let stop = tol * tol * dot(&r, &r);
            for _ in 0..cg_iters.max(1) {
                let hd = product(&x, &d, false)?.hv;
                let dhd = dot(&d, &hd);
                let rr = dot(&r, &r);
                let delta = *radius.get_or_insert_with(|| {
                    // The first region: ten Cauchy steps (the minimum along -g), or |g|.
                    if dhd > 0.0 {
                        10.0 * rr / dhd * rr.sqrt()
                    } else {
                        rr.sqrt()
                    }
                });
                let to_boundary = |s: &[f64], d: &[f64]| {
                    let (a, b, c) = (dot(d, d), 2.0 * dot(s, d), dot(s, s) - delta * delta);
                    (-b + (b * b - 4.0 * a * c).max(0.0).sqrt()) / (2.0 * a)
                };
                let alpha = rr / dhd;
                let inside = dhd > 0.0 && {
                    let s1: Vec<f64> = s.iter().zip(&d).map(|(a, b)| a + alpha * b).collect();
                    norm(&s1) < delta
                };
                if !inside {
                    let tau = to_boundary(&s, &d);
                    for k in 0..n {
                        s[k] += tau * d[k];
                        hs[k] += tau * hd[k];
                    }
                    break;
                }
                for k in 0..n {
                    s[k] += alpha * d[k];
                    hs[k] += alpha * hd[k];
                    r[k] += alpha * hd[k];
                }
                let rr1 = dot(&r, &r);
                if rr1 <= stop {
                    break;
                }
                let beta = rr1 / rr;
                for k in 0..n {
                    d[k] = -r[k] + beta * d[k];
                }
            }
            let delta = radius.expect("set by the first product");
            let predicted = -(dot(&g, &s) + 0.5 * dot(&s, &hs));
            let trial: Vec<f64> = x.iter().zip(&s).map(|(a, b)| a + b).collect();
            let (rho, next) = match product(&trial, &zero, true) {
                Ok(h) if h.loss.is_finite() && h.grad.iter().all(|v| v.is_finite()) => {
                    ((cur.loss - h.loss) / predicted, Some(h))
                }
                Ok(_) => (f64::NEG_INFINITY, None),
                Err(e) if trial_failure(&e) => (f64::NEG_INFINITY, None),
                Err(e) => return Err(e),
            };
            let step = norm(&s);
            radius = Some(if rho < 0.25 {
                0.25 * step
            } else if rho > 0.75 && step >= 0.99 * delta {
                2.0 * delta
            } else {
                delta
            });
            match next {
                Some(h) if rho > 1e-4 && predicted > 0.0 => {
                    x = trial;
                    cur = h;
                    if cur.loss < best.loss {
                        best = point(&cur, &x);
                    }
                    break;
                }
                _ => {
                    rejected += 1;
                    let no_model = predicted.is_nan() || predicted <= 0.0;
                    // A step too small to move x in floating point ends the retries too.
                    let tiny = x.iter().zip(&s).all(|(x, s)| x + s == *x);
                    if rejected > 60 || tiny || no_model && rejected > 1 {
                        params.set_values(&best.values);
                        return Ok((
                            best,
                            End::NoProgress {
                                message: format!(
                                    "the trust region shrank to {:.3e} without a step lowering \
                                 the loss",
                                    radius.unwrap_or(0.0)
                                ),
                                non_finite: None,
                            },
                        ));
                    }
                    if spent(counts, max_evals) {
                        return Ok((best, End::Stop(Stop::MaxEvaluations)));
                    }
                    // Again from x, in the smaller region.
                }
            }
        }
    }
    unreachable!("the loop returns")
}
