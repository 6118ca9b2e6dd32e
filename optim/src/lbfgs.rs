//! L-BFGS through argmin: the loss is argmin's cost function (in the free variables of the
//! bounds' change of variables), and the iterations are driven here so that every iteration
//! reaches the observer (argmin's observers must be `'static`).

use std::cell::RefCell;
use std::collections::VecDeque;
use std::time::Instant;

use adflex_runtime::Error;
use argmin::core::{CostFunction, Gradient, IterState, Problem, Solver, State, TerminationStatus};
use argmin::solver::linesearch::MoreThuenteLineSearch;
use argmin::solver::quasinewton::LBFGS;

use crate::{norm, Best, End, Evaluate, Iteration, Observe, Params, Stop};

/// A point, its loss and gradient.
type Cached = (Vec<f64>, f64, Vec<f64>);

/// How many evaluated points keep their gradient w.r.t. the parameters (for the reported
/// gradient norm: the accepted point of a line search is one of its last evaluations).
const KEPT_PARAM_GRADIENTS: usize = 16;

/// What the evaluations left behind, owned outside argmin's `Problem` (which argmin may leave
/// empty when a line search ends early): the first error, the count, and the gradients w.r.t.
/// the parameters of the last points and of the lowest loss (for the reported gradient norm).
#[derive(Default)]
struct Record {
    error: RefCell<Option<Error>>,
    /// The first non-finite loss or gradient of the current iteration (a trial point where
    /// the simulation diverged, made a wall: see `Objective::eval`).
    non_finite: RefCell<Option<Error>>,
    /// The evaluation budget (`Optimizer::max_evals`) and whether a line search hit it.
    max_evals: usize,
    budget_spent: RefCell<bool>,
    evaluations: RefCell<usize>,
    recent: RefCell<VecDeque<(Vec<f64>, Vec<f64>)>>,
    lowest: RefCell<Option<Cached>>,
}

impl Record {
    fn keep(&self, u: &[f64], l: f64, g: Vec<f64>) {
        *self.evaluations.borrow_mut() += 1;
        let mut lowest = self.lowest.borrow_mut();
        if !matches!(&*lowest, Some((_, best, _)) if l > *best) {
            *lowest = Some((u.to_vec(), l, g.clone()));
        }
        let mut recent = self.recent.borrow_mut();
        if recent.len() == KEPT_PARAM_GRADIENTS {
            recent.pop_front();
        }
        recent.push_back((u.to_vec(), g));
    }

    /// dL/dp at the free variables `u`, if `u` was evaluated recently or had the lowest loss.
    fn param_grad(&self, u: &[f64]) -> Option<Vec<f64>> {
        let lowest = self.lowest.borrow();
        let lowest = lowest.as_ref().map(|(x, _, g)| (x, g));
        let recent = self.recent.borrow();
        let mut seen = recent.iter().rev().map(|(x, g)| (x, g)).chain(lowest);
        seen.find(|(x, _)| x.as_slice() == u)
            .map(|(_, g)| g.clone())
    }
}

/// |dL/dp| and |dL/du| (the stationarity measure in the free variables) from dL/dp at `u`.
fn norms(params: &Params, u: &[f64], g: &[f64]) -> (f64, f64) {
    let (_, dp) = params.params_of_free(u);
    let gu: Vec<f64> = g.iter().zip(&dp).map(|(g, d)| g * d).collect();
    (norm(g), norm(&gu))
}

/// The loss in the free variables, with the last evaluation cached (argmin asks for the cost
/// and the gradient of one point separately).
struct Objective<'p, 'e> {
    params: &'p Params,
    evaluate: RefCell<&'p mut Evaluate<'e>>,
    last: RefCell<Option<Cached>>,
    record: &'p Record,
}

impl Objective<'_, '_> {
    fn eval(&self, u: &[f64]) -> Result<(f64, Vec<f64>), argmin::core::Error> {
        if let Some((x, l, g)) = &*self.last.borrow() {
            if x == u {
                return Ok((*l, g.clone()));
            }
        }
        if *self.record.evaluations.borrow() >= self.record.max_evals.max(1) {
            *self.record.budget_spent.borrow_mut() = true;
            return Err(argmin::core::Error::msg("the evaluation budget is spent"));
        }
        let (p, dp) = self.params.params_of_free(u);
        let result = (self.evaluate.borrow_mut())(&p);
        match result {
            Ok(e) => match e.non_finite {
                None => {
                    let gu: Vec<f64> = e.grad.iter().zip(&dp).map(|(g, d)| g * d).collect();
                    *self.last.borrow_mut() = Some((u.to_vec(), e.loss, gu.clone()));
                    self.record.keep(u, e.loss, e.grad);
                    Ok((e.loss, gu))
                }
                Some(err) => {
                    let lowest = self.record.lowest.borrow().as_ref().map(|(_, l, _)| *l);
                    match lowest {
                        // A trial point of a line search where the simulation diverged: a
                        // wall (a loss far above the best, no slope), so that the line search
                        // backtracks instead of failing.
                        Some(best) => {
                            self.record.non_finite.borrow_mut().get_or_insert(err);
                            let wall = best + 1e6 * (1.0 + best.abs());
                            Ok((wall, vec![0.0; u.len()]))
                        }
                        None => {
                            let msg = err.to_string();
                            self.record.non_finite.borrow_mut().get_or_insert(err);
                            Err(argmin::core::Error::msg(msg))
                        }
                    }
                }
            },
            Err(e) => {
                let msg = e.to_string();
                self.record.error.borrow_mut().get_or_insert(e);
                Err(argmin::core::Error::msg(msg))
            }
        }
    }
}

impl CostFunction for Objective<'_, '_> {
    type Param = Vec<f64>;
    type Output = f64;
    fn cost(&self, u: &Vec<f64>) -> Result<f64, argmin::core::Error> {
        self.eval(u).map(|(l, _)| l)
    }
}

impl Gradient for Objective<'_, '_> {
    type Param = Vec<f64>;
    type Gradient = Vec<f64>;
    fn gradient(&self, u: &Vec<f64>) -> Result<Vec<f64>, argmin::core::Error> {
        self.eval(u).map(|(_, g)| g)
    }
}

/// When the line search of L-BFGS fails: a restart (fresh memory, from the best point) is
/// tried if the point is not stationary by these tolerances (see `Optimizer::stationary_tol`
/// and `Optimizer::grad_tol`) and the loss fell since the last (re)start.
#[derive(Clone, Copy)]
pub(crate) struct Restart {
    pub stationary_tol: f64,
    pub grad_tol: f64,
}

type Iterate = IterState<Vec<f64>, Vec<f64>, (), (), (), f64>;

/// Runs L-BFGS from `x0`; returns the best point evaluated and how the run ended.
///
/// argmin's L-BFGS keeps its correction pairs after a line search that met walls (zero
/// gradients) or rounding, and may then propose a direction that is not a descent direction:
/// where that happens away from a stationary point, the run restarts from the best point with
/// an empty memory (steepest descent first), as long as each restart lowers the loss and an
/// iteration was accepted since the last one.
#[allow(clippy::too_many_arguments)]
pub(crate) fn run(
    params: &Params,
    x0: &[f64],
    memory: usize,
    max_iters: usize,
    max_evals: usize,
    restart: Restart,
    start: Instant,
    evaluate: &mut Evaluate<'_>,
    observe: &mut Observe<'_>,
) -> Result<(Best, End), Error> {
    let mut u_start = params.free_of_params(x0)?;
    let record = Record {
        max_evals,
        ..Record::default()
    };
    // The gradient w.r.t. the parameters, not the free variables: kept from the evaluation of
    // that point (dividing by dp/du would fail where a bound's change of variables saturates
    // and dp/du rounds to 0).
    let norms_at = |s: &Iterate| {
        s.get_param()
            .or(s.get_best_param())
            .and_then(|u| record.param_grad(u).map(|g| norms(params, u, &g)))
            .unwrap_or((f64::NAN, f64::NAN))
    };
    let iteration = |s: &Iterate, iter: usize| {
        let (grad_norm, stationarity) = norms_at(s);
        let it = Iteration {
            iter,
            loss: s.get_cost(),
            grad_norm,
            evaluations: *record.evaluations.borrow(),
            passes: 2 * *record.evaluations.borrow(),
            sweeps: 0,
            elapsed: start.elapsed(),
        };
        (it, stationarity)
    };
    // The lowest loss evaluated (argmin's best iterate, or a lower trial point).
    let best = || {
        let lowest = record.lowest.borrow();
        let (u, l, g) = lowest.as_ref().expect("the starting point was evaluated");
        let (grad_norm, stationarity) = norms(params, u, g);
        Best {
            loss: *l,
            values: params.params_of_free(u).0,
            grad_norm,
            stationarity,
        }
    };
    // argmin ends a run whose line search failed (because the loss returned an error, or
    // the budget was spent, or no point met its conditions) as "terminated", or with an
    // error. An error of the loss is the answer then; a spent budget is
    // `Stop::MaxEvaluations`; otherwise the run made no more progress, which the caller
    // judges by the numbers (converged at a stationary point, or a failed line search, or a
    // divergence), with the first non-finite trial point of that line search, if any.
    let loss_error = || record.error.borrow_mut().take();
    let no_progress = |message: String| {
        if *record.budget_spent.borrow() {
            return End::Stop(Stop::MaxEvaluations);
        }
        let non_finite = record.non_finite.borrow_mut().take();
        End::NoProgress {
            message,
            non_finite: non_finite.map(|e| e.to_string()),
        }
    };
    let mut iter = 0;
    // The initial stationarity measure, and the loss at the last (re)start.
    let mut s0 = f64::NAN;
    let mut restart_loss = f64::INFINITY;
    // The iteration of the last restart: a restart needs an accepted iteration since.
    let mut restarted_at: Option<usize> = None;
    loop {
        let objective = Objective {
            params,
            evaluate: RefCell::new(&mut *evaluate),
            last: RefCell::new(None),
            record: &record,
        };
        let mut problem = Problem::new(objective);
        let mut solver = LBFGS::new(MoreThuenteLineSearch::new(), memory.max(1))
            .with_tolerance_grad(0.0)
            .and_then(|s| s.with_tolerance_cost(0.0))
            .map_err(argmin_error)?;
        let mut state = IterState::new()
            .param(u_start.clone())
            .max_iters(max_iters as u64);
        for _ in 0..iter {
            state.increment_iter();
        }
        // At the starting point a non-finite loss is an error (nothing better is known).
        state = match solver.init(&mut problem, state) {
            Ok((s, _)) => s,
            Err(e) => {
                if let Some(e) = loss_error() {
                    return Err(e);
                }
                if iter > 0 {
                    return Ok((best(), no_progress(format!("L-BFGS (argmin): {e}"))));
                }
                let kept = record.non_finite.borrow_mut().take();
                return Err(kept.unwrap_or_else(|| argmin_error(e)));
            }
        };
        state.update();
        restart_loss = restart_loss.min(state.get_cost());
        if iter == 0 {
            let (it, stationarity) = iteration(&state, iter);
            s0 = stationarity;
            if let Some(stop) = observe(it, stationarity) {
                return Ok((best(), End::Stop(stop)));
            }
        }
        let end = loop {
            if let TerminationStatus::Terminated(reason) =
                <LBFGS<_, _, _, _> as Solver<Objective, _>>::terminate_internal(&mut solver, &state)
            {
                break match iter >= max_iters {
                    true => End::Stop(Stop::MaxIterations),
                    false => no_progress(format!("L-BFGS (argmin): {}", reason.text())),
                };
            }
            record.non_finite.borrow_mut().take();
            let (next, _) = match solver.next_iter(&mut problem, state) {
                Ok(s) => s,
                Err(e) => {
                    if let Some(e) = loss_error() {
                        return Err(e);
                    }
                    break no_progress(format!("L-BFGS (argmin): {e}"));
                }
            };
            if let Some(e) = loss_error() {
                return Err(e);
            }
            state = next;
            if let TerminationStatus::Terminated(reason) = state.get_termination_status() {
                break no_progress(format!("L-BFGS (argmin): {}", reason.text()));
            }
            state.update();
            state.increment_iter();
            iter += 1;
            let (it, stationarity) = iteration(&state, iter);
            if let Some(stop) = observe(it, stationarity) {
                return Ok((best(), End::Stop(stop)));
            }
        };
        let b = best();
        let stationary = b.stationarity <= restart.stationary_tol * s0
            || b.grad_norm <= restart.grad_tol
            || b.stationarity == 0.0;
        let moved = !matches!(restarted_at, Some(at) if iter <= at);
        if matches!(end, End::NoProgress { .. }) && !stationary && b.loss < restart_loss && moved {
            let lowest = record.lowest.borrow();
            u_start = lowest.as_ref().expect("evaluated").0.clone();
            restart_loss = b.loss;
            restarted_at = Some(iter);
            continue;
        }
        return Ok((b, end));
    }
}

fn argmin_error(e: argmin::core::Error) -> Error {
    Error::Other(format!("L-BFGS (argmin): {e}"))
}
