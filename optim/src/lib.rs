//! Optimization with the tape's gradients: parameters given as arrays ([`Params`]), gradient
//! descent and Adam built in, L-BFGS through [argmin](https://docs.rs/argmin), bounds, a
//! per-iteration callback and a progress bar.
//!
//! The loss is a closure that records a simulation on a fresh [`Tape`] and returns the loss
//! array ([`Optimizer::minimize`]); the optimizer writes the parameters, zeroes their
//! gradients, runs the closure and `backward`, and reads the gradients. A loss computed some
//! other way (a [`checkpointed`](adflex_runtime::checkpoint::checkpointed) rollout, which runs
//! its own backward) goes through [`Optimizer::minimize_with`]. When the optimizer returns,
//! the parameter arrays hold the best values it found.
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
//! assert!(report.loss < 1e-10, "{report}");
//! assert!((p.get(0) - 1.0).abs() < 1e-4 && (p.get(1) - 1.0).abs() < 1e-4);
//! ```

use std::cell::RefCell;
use std::fmt;
use std::ops::ControlFlow;
use std::time::{Duration, Instant};

use adflex_runtime::{Array, Element, Error, Tape};

mod lbfgs;
mod params;

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
    /// Time since the start.
    pub elapsed: Duration,
}

/// Why an optimization stopped.
#[derive(Clone, Debug, PartialEq)]
pub enum Stop {
    /// [`Optimizer::max_iters`] iterations ran.
    MaxIterations,
    /// The gradient norm fell below [`Optimizer::grad_tol`].
    GradientTolerance,
    /// The loss reached [`Optimizer::target_loss`].
    TargetLoss,
    /// The callback returned `ControlFlow::Break`.
    Callback,
    /// The method's own criterion (e.g. L-BFGS: no change in the loss), as argmin words it.
    Converged(String),
    /// A trial point of L-BFGS's line search gave a non-finite loss or gradient (the
    /// simulation diverged there; the message names the evaluation). The best point found is
    /// kept: a line search may overshoot far from a good iterate, typically after the loss
    /// has converged. At the starting point, or for gradient descent and Adam (whose every
    /// evaluation is an iterate), a non-finite loss is an error instead.
    Diverged(String),
}

/// What [`Optimizer::minimize`] returns. The parameter arrays hold the best values found.
#[derive(Clone, Debug)]
pub struct Report {
    /// The best loss found (the parameters' current values give it).
    pub loss: f64,
    /// The loss at the start.
    pub initial_loss: f64,
    /// Iterations run.
    pub iterations: usize,
    /// Loss and gradient evaluations.
    pub evaluations: usize,
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
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "loss {:.6e} -> {:.6e} in {} iterations ({} evaluations, {:.2} s), stopped: {:?}",
            self.initial_loss,
            self.loss,
            self.iterations,
            self.evaluations,
            self.elapsed.as_secs_f64(),
            self.stop
        )
    }
}

type Callback<'a> = Box<dyn FnMut(&Iteration) -> ControlFlow<()> + 'a>;

/// An optimizer: a [`Method`] and when to stop. Build with [`Optimizer::lbfgs`],
/// [`Optimizer::adam`] or [`Optimizer::gradient_descent`], then run
/// [`Optimizer::minimize`].
pub struct Optimizer<'a> {
    method: Method,
    max_iters: usize,
    grad_tol: f64,
    target_loss: f64,
    progress: bool,
    callback: Option<Callback<'a>>,
}

impl fmt::Debug for Optimizer<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Optimizer")
            .field("method", &self.method)
            .field("max_iters", &self.max_iters)
            .field("grad_tol", &self.grad_tol)
            .field("target_loss", &self.target_loss)
            .field("progress", &self.progress)
            .finish()
    }
}

impl<'a> Optimizer<'a> {
    /// An optimizer with `method`, 100 iterations at most, `grad_tol = 0` and no target loss
    /// (stop only on the iteration count or the method's own criterion), and a progress bar.
    pub fn new(method: Method) -> Self {
        Optimizer {
            method,
            max_iters: 100,
            grad_tol: 0.0,
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
    /// At most `n` iterations (default 100).
    pub fn max_iters(mut self, n: usize) -> Self {
        self.max_iters = n;
        self
    }
    /// Stop when the gradient norm is at most `tol` (default 0: never).
    pub fn grad_tol(mut self, tol: f64) -> Self {
        self.grad_tol = tol;
        self
    }
    /// Stop when the loss is at most `target` (default: never).
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
    /// finite (but see [`Stop::Diverged`]), or if L-BFGS starts a bounded parameter on its
    /// bound. After an error the arrays hold the best values evaluated before it (the
    /// starting values if none), never the failing ones.
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
                params.check_used(&tape, &l)?;
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
        mut self,
        params: &Params,
        mut eval: impl FnMut() -> Result<f64, Error>,
    ) -> Result<Report, Error> {
        let start = Instant::now();
        let mut evaluations = 0;
        // The lowest finite loss evaluated and its values: what the arrays hold after an error.
        let lowest: RefCell<Option<(f64, Vec<f64>)>> = RefCell::new(None);
        let mut evaluate = |values: &[f64]| -> Result<Evaluation, Error> {
            params.set_values(values);
            params.zero_grads();
            let loss = eval()?;
            evaluations += 1;
            let grad = params.grads()?;
            let non_finite = check_finite(params, evaluations, loss, &grad).err();
            if non_finite.is_none() && !matches!(&*lowest.borrow(), Some((l, _)) if loss >= *l) {
                *lowest.borrow_mut() = Some((loss, values.to_vec()));
            }
            Ok(Evaluation {
                loss,
                grad,
                non_finite,
            })
        };
        let bar = self.progress.then(|| progress_bar(self.max_iters));
        let mut history = Vec::new();
        let mut observe = |it: Iteration| {
            if let Some(b) = &bar {
                b.set_position(it.iter as u64);
                b.set_message(format!("loss {:.4e} |grad| {:.2e}", it.loss, it.grad_norm));
            }
            history.push(it);
            if let Some(cb) = &mut self.callback {
                if cb(&it).is_break() {
                    return Some(Stop::Callback);
                }
            }
            if it.loss <= self.target_loss {
                Some(Stop::TargetLoss)
            } else if it.grad_norm <= self.grad_tol {
                Some(Stop::GradientTolerance)
            } else {
                None
            }
        };
        let x0 = params.values();
        let result = match self.method {
            Method::Lbfgs { memory } => lbfgs::run(
                params,
                &x0,
                memory,
                self.max_iters,
                start,
                &mut evaluate,
                &mut observe,
            ),
            Method::GradientDescent { .. } | Method::Adam { .. } => first_order(
                self.method,
                params,
                x0.clone(),
                self.max_iters,
                start,
                &mut evaluate,
                &mut observe,
            ),
        };
        let (best, stop) = match result {
            Ok(r) => r,
            Err(e) => {
                if let Some(b) = &bar {
                    b.finish_and_clear();
                }
                params.set_values(lowest.borrow().as_ref().map_or(&x0, |(_, x)| x));
                return Err(e);
            }
        };
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        params.set_values(&best.1);
        let initial_loss = history.first().map_or(best.0, |i| i.loss);
        Ok(Report {
            loss: best.0,
            initial_loss,
            iterations: history.len().saturating_sub(1),
            evaluations,
            history,
            stop,
            elapsed: start.elapsed(),
        })
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

/// The loss and gradient of an evaluation that must be finite (an iterate).
fn finite(e: Evaluation) -> Result<(f64, Vec<f64>), Error> {
    match e.non_finite {
        Some(err) => Err(err),
        None => Ok((e.loss, e.grad)),
    }
}
/// The per-iteration observer: `Some(stop)` ends the run.
pub(crate) type Observe<'e> = dyn FnMut(Iteration) -> Option<Stop> + 'e;

fn norm(g: &[f64]) -> f64 {
    g.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn check_finite(params: &Params, evaluation: usize, loss: f64, g: &[f64]) -> Result<(), Error> {
    if !loss.is_finite() {
        return Err(Error::InvalidInput {
            what: format!("loss (evaluation {evaluation})"),
            message: format!(
                "is {loss}: the simulation diverged at these parameter values (lower the \
                 learning rate or the time step, or bound the parameters)"
            ),
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

/// Gradient descent and Adam, with bounds by projection. Returns the best (loss, values).
fn first_order(
    method: Method,
    params: &Params,
    mut x: Vec<f64>,
    max_iters: usize,
    start: Instant,
    evaluate: &mut Evaluate<'_>,
    observe: &mut Observe<'_>,
) -> Result<((f64, Vec<f64>), Stop), Error> {
    params.project(&mut x);
    let (mut m, mut v) = (vec![0.0; x.len()], vec![0.0; x.len()]);
    let (mut l, mut g) = finite(evaluate(&x)?)?;
    let mut best = (l, x.clone());
    for (iter, evaluations) in (0..).zip(1..) {
        let it = Iteration {
            iter,
            loss: l,
            grad_norm: norm(&g),
            evaluations,
            elapsed: start.elapsed(),
        };
        if let Some(stop) = observe(it) {
            return Ok((best, stop));
        }
        if iter == max_iters {
            return Ok((best, Stop::MaxIterations));
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
            Method::Lbfgs { .. } => unreachable!("L-BFGS runs through argmin"),
        }
        params.project(&mut x);
        (l, g) = finite(evaluate(&x)?)?;
        if l < best.0 {
            best = (l, x.clone());
        }
    }
    unreachable!("the loop returns")
}
