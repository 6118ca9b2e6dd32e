//! Optimization with the tape's gradients: parameters given as arrays ([`Params`]), gradient
//! descent and Adam built in, L-BFGS through [argmin](https://docs.rs/argmin), bounds, a
//! per-iteration callback and a progress bar.
//!
//! The loss is a closure that records a simulation on a fresh [`Tape`] and returns the loss
//! array ([`Optimizer::minimize`]); the optimizer writes the parameters, zeroes their
//! gradients, runs the closure and `backward`, and reads the gradients. A loss computed some
//! other way (a [`checkpointed`](adflex_runtime::checkpoint::checkpointed) rollout, which runs
//! its own backward) goes through [`Optimizer::minimize_with`]. When the optimizer returns,
//! the parameter arrays hold the best values it found, and the [`Report`] says what happened:
//! converged (by which test), stalled, a failed line search, diverged, a budget spent or the
//! callback's stop ([`Stop`]); [`Report::converged`] is `true` only for a minimum, decided by
//! the numbers (the gradient norm against the initial one, the loss change).
//!
//! ```
//! use adflex_optim::{Optimizer, Params};
//! use adflex_runtime::prelude::*;
//!
//! #[adflex_macros::diff_kernel]
//! fn rosenbrock<R: Real>(p: &Array<R>, loss: &Array<R>) {
//!     let x = p[0];
//!     let y = p[1];
//!     loss.atomic_add(0, (1.0 - x) * (1.0 - x) + 100.0 * (y - x * x) * (y - x * x));
//! }
//!
//! let p = Array::from_vec(vec![-1.2f64, 1.0]);
//! let report = Optimizer::lbfgs()
//!     .max_iters(100)
//!     .progress(false)
//!     .minimize(&Params::new().with(&p), |tape| {
//!         let loss = Array::zeros(1);
//!         tape.launch(rosenbrock, 1, (&p, &loss));
//!         Ok(loss)
//!     })
//!     .unwrap();
//! // Why it stopped, in words ("converged: ..." or "NOT converged, ...").
//! println!("{report}");
//! assert!(report.converged(), "{report}");
//! assert!(report.loss < 1e-10, "{report}");
//! assert!((p.get(0) - 1.0).abs() < 1e-4 && (p.get(1) - 1.0).abs() < 1e-4);
//! ```

use std::cell::{Cell, RefCell};
use std::fmt;
use std::ops::ControlFlow;
use std::time::{Duration, Instant};

use adflex_runtime::{Array, Element, Error, Tape};

mod cg;
mod kkt;
mod lbfgs;
mod newton;
mod params;

pub use newton::Residuals;
pub use params::{Bounds, Params};

/// The update rule.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Method {
    /// `p -= lr * g`.
    GradientDescent {
        /// Learning rate (step per unit gradient).
        lr: f64,
    },
    /// Adam (Kingma and Ba 2015), with bias correction.
    Adam {
        /// Learning rate (about the step size per iteration, in parameter units).
        lr: f64,
        /// Decay of the first moment (0.9).
        beta1: f64,
        /// Decay of the second moment (0.999).
        beta2: f64,
        /// Denominator guard (1e-8).
        eps: f64,
    },
    /// Limited-memory BFGS with a More-Thuente line search (argmin's).
    Lbfgs {
        /// Correction pairs kept (7).
        memory: usize,
    },
    /// Gauss-Newton for a least-squares loss `½|r|²` ([`Optimizer::least_squares`]): each
    /// step solves `JᵀJ d = -Jᵀr` by conjugate gradients on Gauss-Newton products (matrix
    /// free: a tangent and an adjoint pass each), preconditioned by the products of the
    /// earlier steps, then backtracks along `d` until the loss falls enough (Armijo).
    GaussNewton {
        /// Conjugate-gradient iterations per step at most (20).
        cg_iters: usize,
    },
    /// Levenberg-Marquardt for a least-squares loss ([`Optimizer::least_squares`]): each step
    /// solves `(JᵀJ + λ I) d = -Jᵀr` by conjugate gradients on Gauss-Newton products
    /// (preconditioned as Gauss-Newton's); a step
    /// whose decrease matches the model's is taken and `λ` shrinks (Nielsen's rule); one that
    /// overshoots is backtracked along `d` (Armijo, a forward pass per halving) and `λ` grows;
    /// if that fails too, the step is solved again with a larger `λ`.
    LevenbergMarquardt {
        /// The initial `λ` relative to the curvature `gᵀJᵀJg / gᵀg` at the start (1e-6).
        lambda: f64,
        /// Conjugate-gradient iterations per step at most (20).
        cg_iters: usize,
    },
    /// Newton-CG with a trust region (Steihaug's truncated conjugate gradients) on
    /// Hessian-vector products by forward over reverse ([`Optimizer::minimize_newton`],
    /// simulation in [`Dual`](adflex_runtime::Dual)): negative curvature and steps leaving
    /// the region stop on its boundary.
    NewtonCg {
        /// Conjugate-gradient iterations per step at most (20).
        cg_iters: usize,
    },
    /// Gauss-Newton for a least-squares loss whose state solves a constraint, e.g. a static
    /// equilibrium ([`Optimizer::least_squares_kkt`]): each step solves the KKT system over
    /// the state, the parameters and the constraint's multipliers at once (the formulation
    /// of Zehnder et al.'s sparse Gauss-Newton, 2021), assembled sparse from tangent passes
    /// over one evaluation of the constraint and the residuals (compressed by a colouring of
    /// the columns) and factorized by sparse LU, instead of conjugate gradients whose every
    /// product is a linear solve through the constraint; then backtracks along the step
    /// (Armijo).
    KktGaussNewton {
        /// The largest KKT system assembled (rows: the residuals, twice the state's scalars
        /// and the parameters; 2,000,000); a larger one is an error.
        largest: usize,
    },
}

/// One iteration, as the callback and [`Report::history`] see it (iteration 0 is the
/// starting point).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Iteration {
    /// Iterations done (0: the starting point).
    pub iter: usize,
    /// The loss at the iterate.
    pub loss: f64,
    /// Euclidean norm of the gradient at the iterate (w.r.t. the parameters).
    pub grad_norm: f64,
    /// Loss evaluations so far (line searches take several per iteration).
    pub evaluations: usize,
    /// Passes over the simulation so far: forward, backward (adjoint) and tangent sweeps,
    /// each counted once (a gradient evaluation is 2; a Gauss-Newton product 2; a
    /// Hessian-vector product 2 sweeps in `Dual`). The cost axis for comparing methods.
    pub passes: usize,
    /// Sweeps over one evaluation of a constraint so far (not the simulation: per step of
    /// [`Optimizer::least_squares_kkt`], the recording of `constrained` and the tangent
    /// passes that give the columns of its KKT system: at the first step, the probes that find
    /// the pattern (or one per unknown for a small or dense system, after the probes of one
    /// round for a dense one); one per colour of the columns, one adjoint pass per dense row
    /// and two for the check at every step, and one per unknown again when the check finds
    /// the pattern changed; 0 for the other methods). Counted apart from
    /// `passes`, being far cheaper.
    pub sweeps: usize,
    /// Time since the start.
    pub elapsed: Duration,
}

/// Which test a converged run met (see [`Stop::Converged`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Convergence {
    /// The gradient norm fell to [`Optimizer::grad_tol`] (absolute) or to
    /// [`Optimizer::grad_tol_rel`] times the initial one.
    GradientTolerance,
    /// The loss reached [`Optimizer::target_loss`].
    TargetLoss,
    /// The loss changed by at most [`Optimizer::loss_tol`] (relative) in an iteration, at a
    /// stationary point (gradient norm at most [`Optimizer::stationary_tol`] times the initial
    /// one).
    LossChange,
    /// L-BFGS's line search found no lower point, at a stationary point (gradient norm at most
    /// [`Optimizer::stationary_tol`] times the initial one): the loss cannot be lowered in
    /// floating point any more. Elsewhere the same failure is [`Stop::LineSearchFailed`].
    NoProgress,
}

/// Why an optimization stopped. Only [`Stop::Converged`] says that the parameters are at a
/// minimum (as far as the numbers tell); [`Report::converged`] checks for it.
///
/// "Converged" is decided from the numbers (the gradient norm relative to the initial one,
/// the loss and its change), never from a method's own wording: a line search that fails
/// where the gradient is still large is [`Stop::LineSearchFailed`], however argmin words it.
#[derive(Clone, Debug, PartialEq)]
pub enum Stop {
    /// A minimum, by the test named.
    Converged(Convergence),
    /// The loss changed by at most [`Optimizer::loss_tol`] (relative) in an iteration while
    /// the gradient norm is more than [`Optimizer::stationary_tol`] times the initial one: no
    /// progress, and not at a minimum (a kink, a wrong gradient, a noisy loss, a learning rate
    /// too small). The message gives the numbers.
    Stalled(String),
    /// L-BFGS's line search failed (argmin's message, and the trial points where the loss was
    /// not finite, if any) at a point that is not stationary: the gradient does not lead
    /// down (a kink or a non-smooth minimum, a gradient inconsistent with the loss, a loss
    /// too noisy at the step sizes tried, or the edge of a region where the simulation
    /// diverges).
    LineSearchFailed(String),
    /// A second-order method ([`Optimizer::gauss_newton`], [`Optimizer::levenberg_marquardt`],
    /// [`Optimizer::newton_cg`]) found no step lowering the loss (its backtracking, its
    /// damping or its trust region gave out; the message says which) at a point that is not
    /// stationary: the same causes as [`Stop::LineSearchFailed`].
    StepFailed(String),
    /// The run diverged (the message names the evaluation): gradient descent or Adam reached a
    /// non-finite loss or gradient, or a gradient `1e8` times the initial one at a loss above
    /// the initial one (lower the learning rate); or L-BFGS ran away, its line search meeting
    /// non-finite trial points after the loss fell far below any scale (an unbounded loss) or
    /// the gradient grew `1e8` times. A non-finite trial point of a line search near a
    /// stationary point is not divergence: that run is [`Convergence::NoProgress`].
    /// The best finite point found is kept.
    Diverged(String),
    /// [`Optimizer::max_iters`] iterations ran (the budget is spent, whatever the gradient).
    MaxIterations,
    /// [`Optimizer::max_evals`] loss evaluations ran.
    MaxEvaluations,
    /// The callback returned `ControlFlow::Break`.
    Callback,
}

impl fmt::Display for Convergence {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Convergence::GradientTolerance => "the gradient norm reached its tolerance",
            Convergence::TargetLoss => "the loss reached its target",
            Convergence::LossChange => {
                "the loss stopped changing (below its tolerance) at a stationary point"
            }
            Convergence::NoProgress => {
                "no lower point can be found (the line search failed) at a stationary point"
            }
        })
    }
}

impl fmt::Display for Stop {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Stop::Converged(c) => write!(f, "converged: {c}"),
            Stop::Stalled(m) => write!(f, "NOT converged, stalled: {m}"),
            Stop::LineSearchFailed(m) => write!(
                f,
                "NOT converged, the line search failed where the gradient is not small: {m}"
            ),
            Stop::StepFailed(m) => write!(
                f,
                "NOT converged, no step lowered the loss where the gradient is not small: {m}"
            ),
            Stop::Diverged(m) => write!(f, "NOT converged, diverged: {m}"),
            Stop::MaxIterations => {
                write!(
                    f,
                    "NOT converged, stopped after the maximum number of iterations"
                )
            }
            Stop::MaxEvaluations => write!(
                f,
                "NOT converged, stopped after the maximum number of loss evaluations"
            ),
            Stop::Callback => write!(f, "stopped by the callback"),
        }
    }
}

/// What [`Optimizer::minimize`] returns. The parameter arrays hold the best values found.
#[derive(Clone, Debug)]
pub struct Report {
    /// The best loss found (the parameters' current values give it).
    pub loss: f64,
    /// The loss at the start.
    pub initial_loss: f64,
    /// The gradient norm at the best point (w.r.t. the parameters).
    pub grad_norm: f64,
    /// The gradient norm at the start.
    pub initial_grad_norm: f64,
    /// Iterations run.
    pub iterations: usize,
    /// Loss and gradient evaluations.
    pub evaluations: usize,
    /// Passes over the simulation (see [`Iteration::passes`]).
    pub passes: usize,
    /// Sweeps over one evaluation of a constraint (see [`Iteration::sweeps`]).
    pub sweeps: usize,
    /// Every iteration, the starting point first.
    pub history: Vec<Iteration>,
    /// Why it stopped.
    pub stop: Stop,
    /// Wall time.
    pub elapsed: Duration,
}

impl Report {
    /// The loss of each iteration (for a plot).
    pub fn losses(&self) -> Vec<f64> {
        self.history.iter().map(|i| i.loss).collect()
    }

    /// Whether the run converged ([`Stop::Converged`], by any test). A budget spent, a stall,
    /// a failed line search, a divergence or a callback's stop is not convergence.
    pub fn converged(&self) -> bool {
        matches!(self.stop, Stop::Converged(_))
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}; loss {:.6e} -> {:.6e}, gradient norm {:.3e} -> {:.3e}, in {} iterations ({} \
             evaluations, {} passes{}, {:.2} s)",
            self.stop,
            self.initial_loss,
            self.loss,
            self.initial_grad_norm,
            self.grad_norm,
            self.iterations,
            self.evaluations,
            self.passes,
            match self.sweeps {
                0 => String::new(),
                s => format!(", {s} sweeps of a constraint"),
            },
            self.elapsed.as_secs_f64(),
        )
    }
}

type Callback<'a> = Box<dyn FnMut(&Iteration) -> ControlFlow<()> + 'a>;

/// How much the gradient may grow (relative to the initial one, with the loss above the
/// initial one) before gradient descent or Adam counts as diverged; and before L-BFGS, meeting
/// non-finite trial points, does.
const DIVERGENCE_GROWTH: f64 = 1e8;
/// How far below the scale of the initial loss (`-RUNAWAY * max(|initial loss|, ..)`) the loss
/// of L-BFGS must fall, while its line search meets non-finite trial points, for the run to
/// count as diverged (a loss unbounded below).
const RUNAWAY: f64 = 1e12;

/// An optimizer: a [`Method`] and when to stop. Build with [`Optimizer::lbfgs`],
/// [`Optimizer::adam`] or [`Optimizer::gradient_descent`], then run
/// [`Optimizer::minimize`].
pub struct Optimizer<'a> {
    method: Method,
    max_iters: usize,
    max_evals: usize,
    grad_tol: f64,
    grad_tol_rel: f64,
    loss_tol: f64,
    stationary_tol: f64,
    target_loss: f64,
    progress: bool,
    callback: Option<Callback<'a>>,
}

impl fmt::Debug for Optimizer<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Optimizer")
            .field("method", &self.method)
            .field("max_iters", &self.max_iters)
            .field("max_evals", &self.max_evals)
            .field("grad_tol", &self.grad_tol)
            .field("grad_tol_rel", &self.grad_tol_rel)
            .field("loss_tol", &self.loss_tol)
            .field("stationary_tol", &self.stationary_tol)
            .field("target_loss", &self.target_loss)
            .field("progress", &self.progress)
            .finish()
    }
}

impl<'a> Optimizer<'a> {
    /// An optimizer with `method`, 100 iterations at most, no limit on evaluations,
    /// `grad_tol = grad_tol_rel = loss_tol = 0` and no target loss (stop only on the budget,
    /// or when L-BFGS can make no more progress), `stationary_tol = 1e-3`, and a progress bar.
    pub fn new(method: Method) -> Self {
        Optimizer {
            method,
            max_iters: 100,
            max_evals: usize::MAX,
            grad_tol: 0.0,
            grad_tol_rel: 0.0,
            loss_tol: 0.0,
            stationary_tol: 1e-3,
            target_loss: f64::NEG_INFINITY,
            progress: true,
            callback: None,
        }
    }
    /// L-BFGS with 7 correction pairs.
    pub fn lbfgs() -> Self {
        Self::new(Method::Lbfgs { memory: 7 })
    }
    /// Adam with learning rate `lr` and the usual moments (0.9, 0.999, 1e-8).
    pub fn adam(lr: f64) -> Self {
        Self::new(Method::Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        })
    }
    /// Gradient descent with learning rate `lr`.
    pub fn gradient_descent(lr: f64) -> Self {
        Self::new(Method::GradientDescent { lr })
    }
    /// At most `n` iterations (default 100; [`Stop::MaxIterations`]).
    pub fn max_iters(mut self, n: usize) -> Self {
        self.max_iters = n;
        self
    }
    /// At most `n` loss evaluations (default: no limit; [`Stop::MaxEvaluations`]). L-BFGS's
    /// line searches take several per iteration; a line search cut short by the limit ends
    /// the run with the best point evaluated. The second-order methods count their trial
    /// points; the products inside their conjugate gradients (Gauss-Newton products,
    /// Newton-CG's Hessian-vector products, each also a run of the loss closure) count as
    /// [`Report::passes`], which `max_iters` and their CG limits bound.
    pub fn max_evals(mut self, n: usize) -> Self {
        self.max_evals = n;
        self
    }
    /// Converged when the gradient norm is at most `tol` (default 0: never).
    pub fn grad_tol(mut self, tol: f64) -> Self {
        self.grad_tol = tol;
        self
    }
    /// Converged when the gradient norm is at most `rel` times the initial one (default 0:
    /// never). For bounded parameters the norm is that of the projected gradient (gradient
    /// descent, Adam, Gauss-Newton, Levenberg-Marquardt) or of the gradient in L-BFGS's free
    /// variables.
    pub fn grad_tol_rel(mut self, rel: f64) -> Self {
        self.grad_tol_rel = rel;
        self
    }
    /// Stop when the loss changes by at most `tol` relative to its magnitude in an iteration
    /// (default 0: never): [`Convergence::LossChange`] at a stationary point, [`Stop::Stalled`]
    /// elsewhere (see [`Optimizer::stationary_tol`]).
    pub fn loss_tol(mut self, tol: f64) -> Self {
        self.loss_tol = tol;
        self
    }
    /// Where the loss stops changing (or L-BFGS's line search fails), the run counts as
    /// converged if the gradient norm is at most `rel` times the initial one, or at most
    /// [`Optimizer::grad_tol`] (default `1e-3`); otherwise it stalled.
    pub fn stationary_tol(mut self, rel: f64) -> Self {
        self.stationary_tol = rel;
        self
    }
    /// Converged when the loss is at most `target` (default: never).
    pub fn target_loss(mut self, target: f64) -> Self {
        self.target_loss = target;
        self
    }
    /// Shows a progress bar with the loss on the terminal (stderr; default on, and hidden
    /// anyway when stderr is not a terminal).
    pub fn progress(mut self, on: bool) -> Self {
        self.progress = on;
        self
    }
    /// Calls `f` after every iteration (and once at the start); `ControlFlow::Break(())`
    /// stops the optimization ([`Stop::Callback`]).
    pub fn on_iteration(mut self, f: impl FnMut(&Iteration) -> ControlFlow<()> + 'a) -> Self {
        self.callback = Some(Box::new(f));
        self
    }

    /// Minimizes the loss that `loss(tape)` records on a fresh tape (the sum of the returned
    /// array's components) over `params`.
    ///
    /// Errors: the closure's errors and `backward`'s; [`Error::InvalidInput`] naming the
    /// parameter if the recorded loss does not depend on it (checked at the first
    /// evaluation), naming the evaluation and component if the loss or a gradient is not
    /// finite at the starting point (later, the run ends with [`Stop::Diverged`] or, for a
    /// trial point of a line search, backs off), or if L-BFGS starts a bounded parameter on
    /// its bound. After an error the arrays hold the best values evaluated before it (the
    /// starting values if none), never the failing ones.
    ///
    /// A run that returns `Ok` may still not have converged: check [`Report::converged`] (or
    /// print the report, which says why it stopped).
    pub fn minimize<L: Element>(
        self,
        params: &Params,
        mut loss: impl FnMut(&mut Tape) -> Result<Array<L>, Error>,
    ) -> Result<Report, Error> {
        let mut first = true;
        self.minimize_with(params, || {
            let mut tape = Tape::new();
            let l = loss(&mut tape)?;
            if std::mem::take(&mut first) {
                params.check_used(&tape, &[&l])?;
            }
            tape.backward(&l)?;
            let dim = l.len() * L::DIM;
            Ok((0..dim)
                .map(|k| adflex_runtime::AnyArray::scalar(&l, k))
                .sum())
        })
    }

    /// Minimizes a loss that `eval()` computes *and backpropagates* itself (e.g. with
    /// [`checkpointed`](adflex_runtime::checkpoint::checkpointed)), returning its value; the
    /// optimizer zeroes the parameters' gradients before each call and reads them after.
    ///
    /// Errors as [`Optimizer::minimize`], except that a parameter the loss does not depend on
    /// cannot be told from one whose gradient is zero (there is no tape to look at): it just
    /// keeps its value.
    pub fn minimize_with(
        self,
        params: &Params,
        mut eval: impl FnMut() -> Result<f64, Error>,
    ) -> Result<Report, Error> {
        let start = Instant::now();
        let counts = Counts::default();
        let mut evaluate = |values: &[f64]| -> Result<Evaluation, Error> {
            let evaluations = counts.evaluations.get();
            params.set_values(values);
            params.zero_grads();
            let loss = match eval() {
                Ok(loss) => loss,
                // After the first evaluation, a simulation that refuses the trial's values (a
                // state that overflowed, a NaN parameter, a solve that failed there: the
                // integrators' errors instead of a NaN loss) is a non-finite evaluation,
                // which the methods handle (a wall for a line search, divergence for gradient
                // descent and Adam).
                Err(
                    e @ (Error::NonFinite { .. }
                    | Error::InvalidInput { .. }
                    | Error::NotConverged { .. }),
                ) if evaluations > 0 => {
                    counts.evaluated(2);
                    return Ok(Evaluation {
                        loss: f64::NAN,
                        grad: vec![0.0; values.len()],
                        non_finite: Some(e.in_context(format!("evaluation {}", evaluations + 1))),
                    });
                }
                Err(e) => return Err(e),
            };
            counts.evaluated(2);
            let grad = params.grads()?;
            let non_finite = check_finite(params, evaluations + 1, loss, &grad).err();
            if non_finite.is_none() {
                counts.offer(loss, values);
            }
            Ok(Evaluation {
                loss,
                grad,
                non_finite,
            })
        };
        let x0 = params.values();
        let (method, max_iters, max_evals) = (self.method, self.max_iters, self.max_evals);
        let restart = lbfgs::Restart {
            stationary_tol: self.stationary_tol,
            grad_tol: self.grad_tol,
        };
        self.drive(params, start, &counts, &mut |observe| match method {
            Method::Lbfgs { memory } => lbfgs::run(
                params,
                &x0,
                memory,
                max_iters,
                max_evals,
                restart,
                start,
                &mut evaluate,
                observe,
            ),
            Method::GradientDescent { .. } | Method::Adam { .. } => first_order_run(
                method,
                params,
                x0.clone(),
                max_iters,
                start,
                &mut evaluate,
                observe,
            ),
            Method::GaussNewton { .. }
            | Method::LevenbergMarquardt { .. }
            | Method::NewtonCg { .. }
            | Method::KktGaussNewton { .. } => Err(Error::InvalidInput {
                what: format!("{method:?}"),
                message: "this method needs more than a gradient: run it with \
                          `Optimizer::least_squares` (Gauss-Newton, Levenberg-Marquardt), \
                          `Optimizer::minimize_newton` (Newton-CG) or \
                          `Optimizer::least_squares_kkt` (Gauss-Newton by the KKT system)"
                    .into(),
            }),
        })
    }

    /// Runs a method (`run`, given the per-iteration observer) and writes its report: the
    /// stopping tests, the progress bar, the callback, and the classification of how it ended.
    /// After an error the arrays get the lowest finite loss's values from `counts` (the
    /// starting ones if none).
    pub(crate) fn drive(
        mut self,
        params: &Params,
        start: Instant,
        counts: &Counts,
        run: &mut Run<'_>,
    ) -> Result<Report, Error> {
        let bar = self.progress.then(|| progress_bar(self.max_iters));
        let mut history: Vec<Iteration> = Vec::new();
        // The initial loss and stationarity measure (see `Observe`).
        let mut initial: Option<(f64, f64)> = None;
        let (grad_tol, grad_tol_rel, loss_tol, stationary_tol, target_loss, max_evals) = (
            self.grad_tol,
            self.grad_tol_rel,
            self.loss_tol,
            self.stationary_tol,
            self.target_loss,
            self.max_evals,
        );
        let first_order = matches!(
            self.method,
            Method::GradientDescent { .. } | Method::Adam { .. }
        );
        let mut observe = |it: Iteration, stationarity: f64| {
            if let Some(b) = &bar {
                b.set_position(it.iter as u64);
                b.set_message(format!("loss {:.4e} |grad| {:.2e}", it.loss, it.grad_norm));
            }
            let prev = history.last().map(|p| p.loss);
            history.push(it);
            let (l0, s0) = *initial.get_or_insert((it.loss, stationarity));
            if let Some(cb) = &mut self.callback {
                if cb(&it).is_break() {
                    return Some(Stop::Callback);
                }
            }
            let g0 = history[0].grad_norm;
            if it.loss <= target_loss {
                return Some(Stop::Converged(Convergence::TargetLoss));
            }
            if it.grad_norm <= grad_tol || stationarity <= grad_tol_rel * s0 {
                return Some(Stop::Converged(Convergence::GradientTolerance));
            }
            if first_order && it.grad_norm > DIVERGENCE_GROWTH * g0 && it.loss > l0 {
                return Some(Stop::Diverged(format!(
                    "at iteration {} the gradient norm is {:.3e}, {:.1e} times the initial \
                     one, and the loss {:.6e} is above the initial {:.6e} (lower the learning \
                     rate)",
                    it.iter,
                    it.grad_norm,
                    it.grad_norm / g0,
                    it.loss,
                    l0
                )));
            }
            if let Some(prev) = prev {
                let change = (prev - it.loss).abs();
                if loss_tol > 0.0 && change <= loss_tol * prev.abs().max(it.loss.abs()) {
                    let ratio = stationarity / s0;
                    return Some(if ratio <= stationary_tol || it.grad_norm <= grad_tol {
                        Stop::Converged(Convergence::LossChange)
                    } else {
                        Stop::Stalled(format!(
                            "the loss changed by {change:.3e} (relative {:.3e}, tolerance \
                             {loss_tol:.1e}) at iteration {} while the gradient norm is \
                             {ratio:.3e} times the initial one (stationary below \
                             {stationary_tol:.1e})",
                            change / prev.abs().max(it.loss.abs()),
                            it.iter
                        ))
                    });
                }
            }
            if it.evaluations >= max_evals {
                return Some(Stop::MaxEvaluations);
            }
            None
        };
        let x0 = params.values();
        let result = run(&mut observe);
        let (best, end) = match result {
            Ok(r) => r,
            Err(e) => {
                if let Some(b) = &bar {
                    b.finish_and_clear();
                }
                params.set_values(counts.lowest.borrow().as_ref().map_or(&x0, |(_, x)| x));
                return Err(e);
            }
        };
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        params.set_values(&best.values);
        let (initial_loss, initial_grad_norm) = history
            .first()
            .map_or((best.loss, best.grad_norm), |i| (i.loss, i.grad_norm));
        let (l0, s0) = initial.unwrap_or((best.loss, best.stationarity));
        let stop = match end {
            End::Stop(stop) => stop,
            End::NoProgress {
                message,
                non_finite,
            } => {
                let ratio = best.stationarity / s0;
                let runaway = best.loss < -RUNAWAY * l0.abs().max(f64::MIN_POSITIVE)
                    || best.grad_norm > DIVERGENCE_GROWTH * initial_grad_norm;
                if ratio <= self.stationary_tol
                    || best.grad_norm <= self.grad_tol
                    || best.stationarity == 0.0
                {
                    Stop::Converged(Convergence::NoProgress)
                } else if let (Some(nf), true) = (&non_finite, runaway) {
                    Stop::Diverged(format!(
                        "the loss fell to {:.6e} (from {l0:.6e}) with a gradient norm {:.3e} \
                         times the initial one, and then {nf}",
                        best.loss,
                        best.grad_norm / initial_grad_norm
                    ))
                } else {
                    let mut m = format!(
                        "{message} (gradient norm {ratio:.3e} times the initial one, \
                         stationary below {:.1e})",
                        self.stationary_tol
                    );
                    if let Some(nf) = non_finite {
                        m.push_str(&format!("; a trial point was not finite: {nf}"));
                    }
                    match self.method {
                        Method::GaussNewton { .. }
                        | Method::LevenbergMarquardt { .. }
                        | Method::NewtonCg { .. }
                        | Method::KktGaussNewton { .. } => Stop::StepFailed(m),
                        _ => Stop::LineSearchFailed(m),
                    }
                }
            }
        };
        Ok(Report {
            loss: best.loss,
            initial_loss,
            grad_norm: best.grad_norm,
            initial_grad_norm,
            iterations: history.len().saturating_sub(1),
            evaluations: counts.evaluations.get(),
            passes: counts.passes.get(),
            sweeps: counts.sweeps.get(),
            history,
            stop,
            elapsed: start.elapsed(),
        })
    }
}

/// What the evaluations of a run left: their number, the passes over the simulation, and
/// the lowest finite loss with its values (what the arrays hold after an error).
#[derive(Default)]
pub(crate) struct Counts {
    pub evaluations: Cell<usize>,
    pub passes: Cell<usize>,
    pub sweeps: Cell<usize>,
    pub lowest: RefCell<Option<(f64, Vec<f64>)>>,
}

impl Counts {
    /// One more evaluation, of `passes` passes.
    pub fn evaluated(&self, passes: usize) {
        self.evaluations.set(self.evaluations.get() + 1);
        self.passes.set(self.passes.get() + passes);
    }

    /// Passes that are not an evaluation (products).
    pub fn passed(&self, passes: usize) {
        self.passes.set(self.passes.get() + passes);
    }

    /// Iteration `iter` at `loss` and gradient norm `grad_norm`, with the counts so far.
    pub fn iteration(&self, iter: usize, loss: f64, grad_norm: f64, start: Instant) -> Iteration {
        Iteration {
            iter,
            loss,
            grad_norm,
            evaluations: self.evaluations.get(),
            passes: self.passes.get(),
            sweeps: self.sweeps.get(),
            elapsed: start.elapsed(),
        }
    }

    /// Keeps `values` if `loss` is the lowest finite one so far.
    pub fn offer(&self, loss: f64, values: &[f64]) {
        if loss.is_finite() && !matches!(&*self.lowest.borrow(), Some((l, _)) if loss >= *l) {
            *self.lowest.borrow_mut() = Some((loss, values.to_vec()));
        }
    }
}

/// One evaluation of the loss: its value, its gradient, and why they are not finite (an
/// error naming the evaluation and component), which each method handles its own way.
pub(crate) struct Evaluation {
    pub loss: f64,
    pub grad: Vec<f64>,
    pub non_finite: Option<Error>,
}

/// The loss evaluation the methods call: values -> loss and gradient.
pub(crate) type Evaluate<'e> = dyn FnMut(&[f64]) -> Result<Evaluation, Error> + 'e;

/// The per-iteration observer, given the iteration and the method's stationarity measure
/// (the norm of the projected gradient, or of the gradient in L-BFGS's free variables):
/// `Some(stop)` ends the run.
pub(crate) type Observe<'e> = dyn FnMut(Iteration, f64) -> Option<Stop> + 'e;

/// A method's run, given the observer: its best point and how it ended.
pub(crate) type Run<'r> = dyn FnMut(&mut Observe<'_>) -> Result<(Best, End), Error> + 'r;

/// The best point a method found.
pub(crate) struct Best {
    pub loss: f64,
    pub values: Vec<f64>,
    /// |dL/dp| there.
    pub grad_norm: f64,
    /// The method's stationarity measure there (see [`Observe`]).
    pub stationarity: f64,
}

/// How a method ended: a decided stop, or no more progress (L-BFGS's line search failed),
/// which [`Optimizer::minimize_with`] classifies by the numbers.
pub(crate) enum End {
    Stop(Stop),
    NoProgress {
        /// argmin's message.
        message: String,
        /// The first non-finite trial point of the failing line search, if any.
        non_finite: Option<String>,
    },
}

fn norm(g: &[f64]) -> f64 {
    g.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn check_finite(params: &Params, evaluation: usize, loss: f64, g: &[f64]) -> Result<(), Error> {
    if !loss.is_finite() {
        return Err(Error::InvalidInput {
            what: format!("loss (evaluation {evaluation})"),
            message: format!("is {loss}: the simulation diverged at these parameter values"),
        });
    }
    if let Some(i) = g.iter().position(|x| !x.is_finite()) {
        return Err(Error::InvalidInput {
            what: format!(
                "gradient of {} (evaluation {evaluation})",
                params.component_name(i)
            ),
            message: format!("is {}", g[i]),
        });
    }
    Ok(())
}

fn progress_bar(len: usize) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len as u64);
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("optimize [{bar:30}] {pos}/{len} {msg} {elapsed}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar
}

/// Gradient descent and Adam, with bounds by projection. Returns the best point and how the
/// run ended. A non-finite loss or gradient at the start is an error; later, it ends the run
/// ([`Stop::Diverged`]).
fn first_order_run(
    method: Method,
    params: &Params,
    mut x: Vec<f64>,
    max_iters: usize,
    start: Instant,
    evaluate: &mut Evaluate<'_>,
    observe: &mut Observe<'_>,
) -> Result<(Best, End), Error> {
    params.project(&mut x);
    let (mut m, mut v) = (vec![0.0; x.len()], vec![0.0; x.len()]);
    let first = evaluate(&x)?;
    if let Some(err) = first.non_finite {
        return Err(err);
    }
    let (mut l, mut g) = (first.loss, first.grad);
    let point = |l: f64, x: &[f64], g: &[f64]| Best {
        loss: l,
        values: x.to_vec(),
        grad_norm: norm(g),
        stationarity: params.projected_grad_norm(x, g),
    };
    let mut best = point(l, &x, &g);
    for (iter, evaluations) in (0..).zip(1..) {
        let it = Iteration {
            iter,
            loss: l,
            grad_norm: norm(&g),
            evaluations,
            passes: 2 * evaluations,
            sweeps: 0,
            elapsed: start.elapsed(),
        };
        if let Some(stop) = observe(it, params.projected_grad_norm(&x, &g)) {
            return Ok((best, End::Stop(stop)));
        }
        if iter == max_iters {
            return Ok((best, End::Stop(Stop::MaxIterations)));
        }
        match method {
            Method::GradientDescent { lr } => {
                for (x, g) in x.iter_mut().zip(&g) {
                    *x -= lr * g;
                }
            }
            Method::Adam {
                lr,
                beta1,
                beta2,
                eps,
            } => {
                let t = (iter + 1) as i32;
                let (c1, c2) = (1.0 - beta1.powi(t), 1.0 - beta2.powi(t));
                for k in 0..x.len() {
                    m[k] = beta1 * m[k] + (1.0 - beta1) * g[k];
                    v[k] = beta2 * v[k] + (1.0 - beta2) * g[k] * g[k];
                    x[k] -= lr * (m[k] / c1) / ((v[k] / c2).sqrt() + eps);
                }
            }
            _ => unreachable!("only gradient descent and Adam run here"),
        }
        params.project(&mut x);
        let e = evaluate(&x)?;
        if let Some(err) = e.non_finite {
            let stop = Stop::Diverged(format!(
                "{err}, at iteration {} (lower the learning rate, or bound the parameters)",
                iter + 1
            ));
            return Ok((best, End::Stop(stop)));
        }
        (l, g) = (e.loss, e.grad);
        if l < best.loss {
            best = point(l, &x, &g);
        }
    }
    unreachable!("the loop returns")
}
