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

use crate::{norm, Evaluate, Iteration, Observe, Params, Stop};

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
    /// The first non-finite loss or gradient (a trial point where the simulation diverged),
    /// and how many trial points were walls (see `Objective::eval`).
    non_finite: RefCell<Option<Error>>,
    walls: RefCell<usize>,
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

    /// |dL/dp| at the free variables `u`, if `u` was evaluated recently or had the lowest loss.
    fn param_grad_norm(&self, u: &[f64]) -> Option<f64> {
        let lowest = self.lowest.borrow();
        let lowest = lowest.as_ref().map(|(x, _, g)| (x, g));
        let recent = self.recent.borrow();
        let mut seen = recent.iter().rev().map(|(x, g)| (x, g)).chain(lowest);
        seen.find(|(x, _)| x.as_slice() == u).map(|(_, g)| norm(g))
    }
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
                            *self.record.walls.borrow_mut() += 1;
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

/// Runs L-BFGS from `x0`; returns the best (loss, values) and why it stopped.
pub(crate) fn run(
    params: &Params,
    x0: &[f64],
    memory: usize,
    max_iters: usize,
    start: Instant,
    evaluate: &mut Evaluate<'_>,
    observe: &mut Observe<'_>,
) -> Result<((f64, Vec<f64>), Stop), Error> {
    let u0 = params.free_of_params(x0)?;
    let record = Record::default();
    let objective = Objective {
        params,
        evaluate: RefCell::new(evaluate),
        last: RefCell::new(None),
        record: &record,
    };
    let mut problem = Problem::new(objective);
    let mut solver = LBFGS::new(MoreThuenteLineSearch::new(), memory.max(1))
        .with_tolerance_grad(0.0)
        .and_then(|s| s.with_tolerance_cost(0.0))
        .map_err(argmin_error)?;
    let state = IterState::new().param(u0).max_iters(max_iters as u64);
    // At the starting point a non-finite loss is an error (nothing better is known).
    let (mut state, _) = match solver.init(&mut problem, state) {
        Ok(s) => s,
        Err(e) => {
            let kept = record.error.borrow_mut().take();
            let kept = kept.or_else(|| record.non_finite.borrow_mut().take());
            return Err(kept.unwrap_or_else(|| argmin_error(e)));
        }
    };
    state.update();
    // The gradient w.r.t. the parameters, not the free variables: kept from the evaluation of
    // that point (dividing by dp/du would fail where a bound's change of variables saturates
    // and dp/du rounds to 0).
    let grad_norm = |s: &IterState<Vec<f64>, Vec<f64>, (), (), (), f64>| {
        s.get_param()
            .or(s.get_best_param())
            .and_then(|u| record.param_grad_norm(u))
            .unwrap_or(f64::NAN)
    };
    let iteration = |s: &IterState<Vec<f64>, Vec<f64>, (), (), (), f64>| Iteration {
        iter: s.get_iter() as usize,
        loss: s.get_cost(),
        grad_norm: grad_norm(s),
        evaluations: *record.evaluations.borrow(),
        elapsed: start.elapsed(),
    };
    let best = |s: &IterState<Vec<f64>, Vec<f64>, (), (), (), f64>| {
        let u = s.get_best_param().expect("argmin keeps the best point");
        (s.get_best_cost(), params.params_of_free(u).0)
    };
    if let Some(stop) = observe(iteration(&state)) {
        return Ok((best(&state), stop));
    }
    // argmin ends a run whose line search failed (because the loss returned an error) as
    // "terminated", or with an error: an error of the loss is the answer then, not
    // convergence. A line search that fails after meeting walls (trial points where the
    // simulation diverged) ends the run with the best point evaluated (`Stop::Diverged`).
    let loss_error = || record.error.borrow_mut().take();
    let diverged = || -> Option<((f64, Vec<f64>), Stop)> {
        let first = record.non_finite.borrow_mut().take()?;
        let lowest = record.lowest.borrow();
        let (u, l, _) = lowest.as_ref().expect("the starting point was evaluated");
        let best = (*l, params.params_of_free(u).0);
        Some((best, Stop::Diverged(first.to_string())))
    };
    loop {
        if let TerminationStatus::Terminated(reason) =
            <LBFGS<_, _, _, _> as Solver<Objective, _>>::terminate_internal(&mut solver, &state)
        {
            let stop = match state.get_iter() as usize >= max_iters {
                true => Stop::MaxIterations,
                false => Stop::Converged(reason.text().to_string()),
            };
            return Ok((best(&state), stop));
        }
        let walls = *record.walls.borrow();
        let (next, _) = match solver.next_iter(&mut problem, state) {
            Ok(s) => s,
            Err(e) => {
                if let Some(e) = loss_error() {
                    return Err(e);
                }
                if *record.walls.borrow() > walls {
                    if let Some(r) = diverged() {
                        return Ok(r);
                    }
                }
                return Err(argmin_error(e));
            }
        };
        if let Some(e) = loss_error() {
            return Err(e);
        }
        state = next;
        state.update();
        state.increment_iter();
        if let Some(stop) = observe(iteration(&state)) {
            return Ok((best(&state), stop));
        }
        if let TerminationStatus::Terminated(reason) = state.get_termination_status() {
            if *record.walls.borrow() > walls {
                if let Some(r) = diverged() {
                    return Ok(r);
                }
            }
            return Ok((best(&state), Stop::Converged(reason.text().to_string())));
        }
    }
}

fn argmin_error(e: argmin::core::Error) -> Error {
    Error::Other(format!("L-BFGS (argmin): {e}"))
}
