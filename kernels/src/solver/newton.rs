//! Newton's method with matrix-free Krylov solves and a line search on two merits, for a
//! nonlinear system `G(u) = 0` whose Jacobian products are passes of the force model's tangent
//! (`A u`) and adjoint (`A^T u`) kernels. [`ImplicitEuler`](crate::integrators::ImplicitEuler)
//! (unknowns: the new velocities) and [`Equilibrium`](crate::statics::Equilibrium) (unknowns:
//! the positions) are two [`NewtonSystem`]s solved by [`newton`], and differentiated by the
//! implicit function theorem with [`solve_linear`] (one transposed solve).
//!
//! # The iteration
//!
//! From `u0`, each iteration solves `A d = -G` ([`krylov::solve`]: CG, then BiCGSTAB if CG
//! meets negative curvature) and searches along `d` by halving the step until it decreases
//! either merit:
//! - the residual's `merit` (Armijo; its slope along an exact Newton direction is `-2 phi`);
//! - the potential `E` whose gradient is `G` when the forces derive from a potential: exact
//!   where the system has energies ([`NewtonSystem::energy`]), otherwise estimated by the
//!   trapezoid rule on its slopes `G . d`. With exact energies, a residual decrease that raises
//!   `E` beyond its rounding is refused (taking both merits' steps in turn can cycle).
//!
//! If neither decreases, a potential step along the CG solution truncated at negative
//! curvature, or along steepest descent ([`NewtonSystem::steepest`]), and else the best
//! residual decrease. The solve is converged when `max |residual| <= tolerance * scale`, or
//! when it is within the rounding floor ([`NewtonSystem::roundoff_floor`]).

use std::cell::RefCell;

use adflex_runtime::Error;

use super::krylov::{self, SolveInfo, SolveSettings};
pub(crate) use super::parts::Parts;

/// What one Newton solve did ([`ImplicitEuler`](crate::integrators::ImplicitEuler)'s step,
/// [`Equilibrium`](crate::statics::Equilibrium)'s solve): its cost, for the benchmarks, and
/// whether it converged.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NewtonStats {
    /// Newton iterations (linear solves).
    pub newton_iterations: usize,
    /// Matrix-vector products (tangent passes) of all the linear solves.
    pub linear_iterations: usize,
    /// Force evaluations (one per line-search trial, plus the first).
    pub force_evaluations: usize,
    /// Step halvings in the line searches.
    pub backtracks: usize,
    /// Linear solves where CG failed and BiCGSTAB took over.
    pub fallbacks: usize,
    /// Final `max |residual|` over free DOFs (in the system's units: m/s for
    /// `ImplicitEuler`, N for `Equilibrium`; NaN if the iterate is not finite).
    pub residual: f64,
    /// The tolerance `residual` was held to, `tolerance * scale`.
    pub tolerance: f64,
    /// Whether the tolerance was met (never for a NaN residual).
    pub converged: bool,
}

/// The settings of one Newton solve.
pub(crate) struct NewtonSettings<'a> {
    /// Relative tolerance on the residual (times [`NewtonSystem::scale`]).
    pub tolerance: f64,
    pub max_newton: usize,
    pub max_backtracks: usize,
    /// Off: every Newton step is full.
    pub line_search: bool,
    /// The Newton linear solves' stopping rule (inexact Newton: missing it is no error).
    pub linear: &'a SolveSettings,
}

/// A nonlinear system `G(u) = 0` over flat `f64` unknowns (three per particle), some fixed
/// (pinned: masked out of every direction). `G` is what the line search takes as the gradient
/// of the potential; the residual `e` is what the tolerance is checked on (`G = M e` for
/// implicit Euler's velocities, `G = -r` for the net force `r` of a static solve).
pub(crate) trait NewtonSystem {
    /// The forces recorded at one iterate (a scratch tape), for the Jacobian products.
    type Point;
    /// Records the forces at `u`.
    fn eval(&self, u: &[f64]) -> Self::Point;
    /// The unknowns `u` of a point.
    fn unknowns<'a>(&self, p: &'a Self::Point) -> &'a [f64];
    /// The residual at `p` (0 on fixed DOFs).
    fn residual(&self, p: &Self::Point) -> Vec<f64>;
    /// `G` from the residual.
    fn gradient(&self, e: &[f64]) -> Vec<f64>;
    /// The residual's merit (line search and progress).
    fn merit(&self, e: &[f64]) -> f64;
    /// The scale the tolerance is relative to, at `p`.
    fn scale(&self, p: &Self::Point) -> f64;
    /// The residual that rounding alone leaves, given the Newton step `d` from residual `e`.
    fn roundoff_floor(&self, e: &[f64], d: &[f64]) -> f64;
    /// The precision's epsilon (of the model's `Real`).
    fn epsilon(&self) -> f64;
    /// The Krylov solves' diagonal preconditioner, if any.
    fn precond(&self) -> Option<&[f64]>;
    /// Zeroes the fixed DOFs of `v`.
    fn mask(&self, v: &mut [f64]);
    /// `out = A u` (identity on fixed DOFs): one tangent pass at `p`. A failing pass is kept
    /// (see [`PassFailure`]) and makes `out` NaN, which stops the solve.
    fn apply(&self, p: &mut Self::Point, u: &[f64], out: &mut [f64]);
    /// `out = A^T u` (identity on fixed DOFs): one adjoint pass at `p`, failing as `apply`.
    fn apply_t(&self, p: &mut Self::Point, u: &[f64], out: &mut [f64]) {
        match self.apply_t_parts(p, u) {
            Ok(o) => out.copy_from_slice(&o.re),
            Err(e) => self.failure().fail("adjoint (reverse-mode)", e, out),
        }
    }
    /// `A^T u` for a real `u` and, at a point recorded in [`Dual`](adflex_runtime::Dual)
    /// (where `A = A0 + eps A1`), its derivative part `A1^T u`: one adjoint pass. An error is
    /// the pass's, without context.
    fn apply_t_parts(&self, p: &mut Self::Point, u: &[f64]) -> Result<Parts, Error>;
    /// Where the products keep a failing pass.
    fn failure(&self) -> &PassFailure;
    /// The failure of a pass inside the last products, if any (taken).
    fn checked(&self) -> Result<(), Error> {
        self.failure().take()
    }
    /// The steepest-descent direction of the potential from residual `e` (in the metric of
    /// the preconditioner).
    fn steepest(&self, e: &[f64]) -> Vec<f64>;
    /// The first step length along the steepest-descent direction `d` (slope `slope` of the
    /// potential), counting any product it takes in `stats`.
    fn steepest_length(
        &self,
        _p: &mut Self::Point,
        _d: &[f64],
        _slope: f64,
        _stats: &mut NewtonStats,
    ) -> f64 {
        1.0
    }
    /// The potential's exactly known part at `p` and its slope along `d`, if the system has
    /// energies: `None` if it has none (the potential is then estimated from `G` alone),
    /// `Some(Err)` if an energy pass failed (no potential: the search keeps to the residual).
    fn energy(&self, _p: &Self::Point, _d: &[f64]) -> Option<Result<(f64, f64), Error>> {
        None
    }
    /// The size of the work terms whose rounding the potential's change carries (J).
    fn work(&self, _p: &Self::Point) -> f64 {
        0.0
    }
}

/// A pass of the force model that failed inside a Krylov product (which cannot return an
/// error), e.g. a custom force step without a tangent: kept here, the product filled with NaN
/// so the solve stops, and returned by [`PassFailure::take`] after the solve.
pub(crate) struct PassFailure {
    solver: &'static str,
    first: RefCell<Option<Error>>,
}

impl PassFailure {
    pub fn new(solver: &'static str) -> Self {
        PassFailure {
            solver,
            first: RefCell::new(None),
        }
    }

    /// `e`, from the `pass` of the force model on its scratch tape, with the pass named.
    pub fn in_pass(&self, pass: &str, e: Error) -> Error {
        e.in_context(format!(
            "{}: the {pass} pass of the force model",
            self.solver
        ))
    }

    /// Keeps the first failure and makes the product NaN.
    pub fn fail(&self, pass: &str, e: Error, out: &mut [f64]) {
        let mut f = self.first.borrow_mut();
        if f.is_none() {
            *f = Some(self.in_pass(pass, e));
        }
        out.fill(f64::NAN);
    }

    /// The kept failure, if any.
    pub fn take(&self) -> Result<(), Error> {
        self.first.borrow_mut().take().map_or(Ok(()), Err)
    }
}

/// Whether a residual meets a tolerance: never if the residual is NaN or infinite (an
/// infinite tolerance, from an infinite scale, would otherwise accept an infinite residual).
pub(crate) fn within(residual: f64, tolerance: f64) -> bool {
    residual.is_finite() && (residual <= tolerance || residual == 0.0)
}

/// `max |v_k|`, NaN if any `v_k` is NaN (`f64::max` would skip it and hide a NaN residual).
pub(crate) fn max_abs(v: &[f64]) -> f64 {
    v.iter().fold(0.0, |m: f64, x| {
        if m.is_nan() || x.is_nan() {
            f64::NAN
        } else {
            m.max(x.abs())
        }
    })
}

pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(a, b)| a * b).sum()
}

/// Solves `A^T x = rhs` at `p` part by part (the adjoint solve of the implicit function
/// theorem): `A0^T x0 = rhs0`, then, at a point recorded in `Dual`, `A0^T x1 = rhs1 - A1^T x0`
/// (the theorem's second-order term: the derivative of `A^T x = rhs` along the direction).
/// `check` judges each solve's figures (an error if it missed its tolerance and the policy
/// says so).
pub(crate) fn solve_transposed<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &Parts,
    settings: &SolveSettings,
    check: impl Fn(&SolveInfo) -> Result<(), Error>,
) -> Result<Parts, Error> {
    let (re, info, _) = solve_linear(sys, p, &rhs.re, settings, true)?;
    check(&info)?;
    let eps = match &rhs.eps {
        None => None,
        Some(rhs_eps) => {
            let coupling = sys
                .apply_t_parts(p, &re)
                .map_err(|e| sys.failure().in_pass("adjoint (reverse-mode)", e))?;
            let mut r: Vec<f64> = match coupling.eps {
                Some(c) => rhs_eps.iter().zip(c).map(|(r, c)| r - c).collect(),
                None => rhs_eps.clone(),
            };
            sys.mask(&mut r);
            let (x, info, _) = solve_linear(sys, p, &r, settings, true)?;
            check(&info)?;
            Some(x)
        }
    };
    Ok(Parts { re, eps })
}

/// Solves `A x = rhs` (or `A^T x = rhs`) at `p` by [`krylov::solve`] with the system's
/// preconditioner; returns `x` (masked), the solve's figures and whether BiCGSTAB took over;
/// an error if a pass of the force model failed in it.
pub(crate) fn solve_linear<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &[f64],
    settings: &SolveSettings,
    transpose: bool,
) -> Result<(Vec<f64>, SolveInfo, bool), Error> {
    let mut x = vec![0.0; rhs.len()];
    let (info, fell_back) = krylov::solve(
        |u, out| match transpose {
            true => sys.apply_t(p, u, out),
            false => sys.apply(p, u, out),
        },
        rhs,
        &mut x,
        sys.precond(),
        settings,
    );
    sys.checked()?;
    sys.mask(&mut x);
    Ok((x, info, fell_back))
}

/// The Newton direction at `p` of residual `e`: `A d = -G`.
pub(crate) fn direction<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    e: &[f64],
    linear: &SolveSettings,
) -> Result<(Vec<f64>, SolveInfo, bool), Error> {
    let rhs: Vec<f64> = sys.gradient(e).iter().map(|g| -g).collect();
    solve_linear(sys, p, &rhs, linear, false)
}

/// The potential `E = E_c + E_r` along a search direction `d`, at one point: `E_c` the part
/// the system knows exactly ([`NewtonSystem::energy`]: inertia and the forces' energies), `E_r`
/// the rest (gravity, control, damping, friction, forces without an energy), whose slope along
/// `d` is what `G . d` leaves after `E_c`'s; `E_r`'s change is estimated by the trapezoid rule
/// on its slopes (exact for constant and linear forces).
struct Potential {
    /// `E_c` (J).
    conservative: f64,
    /// `dE_c/ds` along `d`.
    slope_c: f64,
    /// `G . d`, the slope of `E`.
    slope: f64,
    /// The size of the terms `change` cancels (J): `|E_c|`, the work terms and the slopes.
    magnitude: f64,
    /// Whether `E_c` is known (else `E` is the trapezoid estimate alone).
    exact: bool,
}

impl Potential {
    /// At point `p` of residual `e`, along `d`; `None` if an energy pass failed.
    fn at<S: NewtonSystem>(sys: &S, p: &S::Point, e: &[f64], d: &[f64]) -> Option<Self> {
        let (exact, (conservative, slope_c)) = match sys.energy(p, d) {
            None => (false, (0.0, 0.0)),
            Some(Ok(c)) => (true, c),
            Some(Err(_)) => return None,
        };
        let slope = dot(&sys.gradient(e), d);
        Some(Potential {
            conservative,
            slope_c,
            slope,
            magnitude: conservative.abs() + sys.work(p) + slope_c.abs() + slope.abs(),
            exact,
        })
    }

    /// `E(t) - E(self)` for the step of length `alpha` (along `d`) from `self` to `t`.
    fn change(&self, t: &Potential, alpha: f64) -> f64 {
        let rest = 0.5 * alpha * ((self.slope - self.slope_c) + (t.slope - t.slope_c));
        t.conservative - self.conservative + rest
    }

    /// The rounding error of [`Potential::change`] between `self` and `t` (J): the energies
    /// and slopes are sums in the model's precision, of the positions rounded in it.
    fn rounding(&self, t: &Potential, epsilon: f64) -> f64 {
        100.0 * epsilon * (self.magnitude + t.magnitude)
    }

    /// Armijo's condition for that step: `E(t) - E(self) <= 1e-4 alpha G . d`. Without an
    /// exact part, `E`'s change is `alpha` times the trapezoid of the slopes, and the test is
    /// made without the factor `alpha` (which need not be a power of two here, and whose
    /// product could round or overflow differently on the two sides).
    fn armijo(&self, t: &Potential, alpha: f64) -> bool {
        if !self.exact {
            let mean = 0.5 * (self.slope + t.slope);
            return t.slope.is_finite() && mean <= 1e-4 * self.slope;
        }
        let change = self.change(t, alpha);
        change.is_finite() && change <= 1e-4 * alpha * self.slope
    }
}

/// A line search's accepted step: its merit, point and residual.
type Accepted<P> = (f64, P, Vec<f64>);

fn along(u: &[f64], d: &[f64], alpha: f64) -> Vec<f64> {
    u.iter().zip(d).map(|(u, d)| u + alpha * d).collect()
}

/// Newton with line search from the point `first` (already evaluated, and counted here as a
/// force evaluation); returns the last iterate's unknowns, `stats` saying whether it
/// converged. Errors only if a pass of the force model failed.
pub(crate) fn newton<S: NewtonSystem>(
    sys: &S,
    first: S::Point,
    s: &NewtonSettings<'_>,
    stats: &mut NewtonStats,
) -> Result<Vec<f64>, Error> {
    let mut p = first;
    stats.force_evaluations += 1;
    let mut e = sys.residual(&p);
    let mut phi = sys.merit(&e);
    loop {
        stats.residual = max_abs(&e);
        stats.tolerance = s.tolerance * sys.scale(&p);
        // A NaN or infinite residual (or scale) is never converged.
        if within(stats.residual, stats.tolerance) {
            stats.converged = true;
            break;
        }
        if stats.newton_iterations >= s.max_newton || !phi.is_finite() {
            break;
        }
        stats.newton_iterations += 1;
        let (d, info, fell_back) = direction(sys, &mut p, &e, s.linear)?;
        stats.linear_iterations += info.iterations;
        stats.fallbacks += fell_back as usize;
        if within(stats.residual, sys.roundoff_floor(&e, &d)) {
            stats.converged = true;
            break;
        }
        // Backtracking line search: a step is accepted if it decreases either merit (module
        // docs). The potential is what makes large steps on stiff nonlinear forces and
        // through contact converge: there the residual has local minima.
        let slope0 = dot(&sys.gradient(&e), &d);
        // `None`: not computed yet; `Some(None)`: unavailable (an energy pass failed; the
        // search then keeps to the residual).
        let mut start: Option<Option<Potential>> = None;
        let mut alpha = 1.0;
        let mut best: Option<Accepted<S::Point>> = None;
        let mut accepted = None;
        for k in 0..=s.max_backtracks {
            let pt = sys.eval(&along(sys.unknowns(&p), &d, alpha));
            stats.force_evaluations += 1;
            let et = sys.residual(&pt);
            let phit = sys.merit(&et);
            let mut residual_ok = phit <= (1.0 - 2e-4 * alpha) * phi;
            let mut potential_ok = false;
            // Every trial, even one the residual accepts, is checked against the potential
            // (for implicit Euler, an energy pass and its tangent: 1.25x the time of a small
            // cloth dropped on the ground, 1.01x that of a 96-tet block, docs/performance.md).
            // Checking it only once a potential step was taken is cheaper but let a block
            // thrown at the ground at 1/60 s stall again.
            if s.line_search && slope0 < 0.0 {
                let s0 = start.get_or_insert_with(|| Potential::at(sys, &p, &e, &d));
                let t = s0.as_ref().and_then(|_| Potential::at(sys, &pt, &et, &d));
                if let (Some(s0), Some(t)) = (s0.as_ref(), t) {
                    let change = s0.change(&t, alpha);
                    potential_ok = change.is_finite() && change <= 1e-4 * alpha * slope0;
                    // A residual decrease that raises the exact potential (beyond its
                    // rounding) is refused: taking both merits' steps in turn can cycle
                    // (seen at impacts with friction).
                    if s0.exact {
                        residual_ok &= !(change > s0.rounding(&t, sys.epsilon()));
                    }
                }
            }
            if !s.line_search || (phit.is_finite() && (residual_ok || potential_ok)) {
                accepted = Some((phit, pt, et));
                break;
            }
            if phit.is_finite() && !best.as_ref().is_some_and(|b| phit >= b.0) {
                best = Some((phit, pt, et));
            }
            if k < s.max_backtracks {
                stats.backtracks += 1;
                alpha *= 0.5;
            }
        }
        // Neither merit decreases along the Newton direction (not a descent direction of the
        // potential where `A` is indefinite): a potential step, or else the best residual
        // decrease.
        let step = match accepted {
            Some(a) => Some(a),
            None => {
                let step = potential_step(sys, &mut p, &e, s, stats)?;
                sys.checked()?;
                step.or_else(|| best.filter(|b| b.0 < phi))
            }
        };
        match step {
            Some((phit, pt, et)) => {
                phi = phit;
                p = pt;
                e = et;
            }
            // No decrease either way: at the attainable precision (or stuck).
            None => {
                stats.converged = within(stats.residual, 10.0 * sys.roundoff_floor(&e, &d));
                break;
            }
        }
    }
    Ok(sys.unknowns(&p).to_vec())
}

/// A step that decreases the potential `E` (gradient `G`): along the CG solution of
/// `A d = -G` truncated at negative curvature (a descent direction of `E`), or else along
/// steepest descent, with a backtracking (Armijo) line search on `E`. Returns the merit, point
/// and residual reached, or `None`.
fn potential_step<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    e: &[f64],
    s: &NewtonSettings<'_>,
    stats: &mut NewtonStats,
) -> Result<Option<Accepted<S::Point>>, Error> {
    let g = sys.gradient(e);
    let rhs: Vec<f64> = g.iter().map(|g| -g).collect();
    let mut d = vec![0.0; g.len()];
    let info = krylov::cg(
        |u, out| sys.apply(p, u, out),
        &rhs,
        &mut d,
        sys.precond(),
        s.linear,
    );
    stats.linear_iterations += info.iterations;
    sys.mask(&mut d);
    let mut alpha = 1.0;
    let slope0 = dot(&g, &d);
    if slope0.is_nan() || slope0 >= 0.0 {
        d = sys.steepest(e);
        let slope = dot(&g, &d);
        if slope.is_nan() || slope >= 0.0 {
            return Ok(None);
        }
        alpha = sys.steepest_length(p, &d, slope, stats);
    }
    // An energy whose pass fails: no potential step (the residual's best is next).
    let Some(s0) = Potential::at(sys, p, e, &d) else {
        return Ok(None);
    };
    if s0.slope.is_nan() || s0.slope >= 0.0 {
        return Ok(None);
    }
    for _ in 0..=s.max_backtracks {
        let pt = sys.eval(&along(sys.unknowns(p), &d, alpha));
        stats.force_evaluations += 1;
        let et = sys.residual(&pt);
        let Some(t) = Potential::at(sys, &pt, &et, &d) else {
            return Ok(None);
        };
        if s0.armijo(&t, alpha) {
            return Ok(Some((sys.merit(&et), pt, et)));
        }
        stats.backtracks += 1;
        alpha *= 0.5;
    }
    Ok(None)
}
