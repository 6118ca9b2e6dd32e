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
//!
//! # Worlds
//!
//! A model of several worlds ([`crate::ModelBuilder::add_world`]) is a block-diagonal system,
//! one block per world ([`NewtonSystem::worlds`]). Each world has its own iteration: its own
//! tolerance (relative to its own scale), Krylov solves ([`krylov::solve_blocks`]), line search
//! and stopping test; a world that is done waits for the others. Every pass of the force model
//! (an evaluation, a tangent or adjoint product) covers all worlds at once, each world's part
//! of it being what that world needs next. A world's iterates, solution and gradients are so
//! the bits it has alone, whatever its neighbours (`kernels/tests/worlds.rs`).

use std::cell::RefCell;
use std::ops::Range;

use adflex_runtime::Error;

use super::krylov::{self, SolveInfo, SolveSettings};
pub(crate) use super::parts::Parts;

/// What one Newton solve did ([`ImplicitEuler`](crate::integrators::ImplicitEuler)'s step,
/// [`Equilibrium`](crate::statics::Equilibrium)'s solve): its cost, for the benchmarks, and
/// whether it converged.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NewtonStats {
    /// Newton iterations (linear solves); with several worlds, the rounds (the most any world
    /// ran).
    pub newton_iterations: usize,
    /// Matrix-vector products (tangent passes) of all the linear solves.
    pub linear_iterations: usize,
    /// Force evaluations (one per line-search trial, plus the first).
    pub force_evaluations: usize,
    /// Step halvings in the line searches.
    pub backtracks: usize,
    /// Linear solves where CG failed and BiCGSTAB took over (one per world that fell back).
    pub fallbacks: usize,
    /// Final `max |residual|` over free DOFs (in the system's units: m/s for
    /// `ImplicitEuler`, N for `Equilibrium`; NaN if the iterate is not finite).
    pub residual: f64,
    /// The tolerance `residual` was held to, `tolerance * scale`.
    pub tolerance: f64,
    /// Whether the tolerance was met (never for a NaN residual), in every world.
    pub converged: bool,
    /// The world `residual` and `tolerance` are of: the one farthest from its tolerance
    /// (0 in a model of one world). Each world is solved by its own iteration (its residual
    /// held to its own scale), so that its result has the same bits alone or among others;
    /// the products and force evaluations above count the shared passes, each covering every
    /// world.
    pub world: usize,
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
    /// The unknowns of each world: disjoint ranges covering them all. The system is block
    /// diagonal over them (a world's residual depends on its unknowns alone), and each world
    /// is solved by its own iteration.
    fn worlds(&self) -> &[Range<usize>];
    /// The residual at `p` (0 on fixed DOFs).
    fn residual(&self, p: &Self::Point) -> Vec<f64>;
    /// `G` from the residual.
    fn gradient(&self, e: &[f64]) -> Vec<f64>;
    /// The residual's merit over the unknowns `w` (line search and progress).
    fn merit(&self, e: &[f64], w: Range<usize>) -> f64;
    /// The scale the tolerance of the unknowns `w` is relative to, at `p`.
    fn scale(&self, p: &Self::Point, w: Range<usize>) -> f64;
    /// The residual that rounding alone leaves on the unknowns `w`, given the Newton step `d`
    /// from residual `e`.
    fn roundoff_floor(&self, e: &[f64], d: &[f64], w: Range<usize>) -> f64;
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
    /// The first step lengths along the steepest-descent direction `d` of the worlds with a
    /// slope (`slopes[w]`, that of the potential along `d`; the other worlds' lengths are
    /// not used), counting any product it takes in `stats`.
    fn steepest_lengths(
        &self,
        _p: &mut Self::Point,
        _d: &[f64],
        slopes: &[Option<f64>],
        _stats: &mut NewtonStats,
    ) -> Vec<f64> {
        vec![1.0; slopes.len()]
    }
    /// Per world, the potential's exactly known part at `p` and its slope along `d`, if the
    /// system has energies: `None` if it has none (the potential is then estimated from `G`
    /// alone), `Some(Err)` if an energy pass failed (no potential: the search keeps to the
    /// residual).
    fn energy(&self, _p: &Self::Point, _d: &[f64]) -> Option<Result<Vec<(f64, f64)>, Error>> {
        None
    }
    /// The size of the work terms on the unknowns `w` whose rounding the potential's change
    /// carries (J).
    fn work(&self, _p: &Self::Point, _w: Range<usize>) -> f64 {
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

/// Per world, the figures of its linear solve and whether BiCGSTAB took over (`None` for a
/// world not solved).
type Solved = Vec<Option<(SolveInfo, bool)>>;

/// The figures of a linear solve per world, and how many of them BiCGSTAB took over.
pub(crate) struct LinearSolve {
    /// Per world.
    pub infos: Vec<SolveInfo>,
    /// Products of the whole system (each covers every world).
    pub products: usize,
    pub fallbacks: usize,
}

impl LinearSolve {
    /// The first world (in order) that missed its tolerance, if any.
    pub fn failed(&self) -> Option<(usize, &SolveInfo)> {
        self.infos.iter().enumerate().find(|(_, i)| !i.converged)
    }

    /// The figures of the world farthest from its tolerance, and that world.
    pub fn worst(&self) -> (usize, SolveInfo) {
        let i = &self.infos;
        let w = farthest(i.len(), |w| (i[w].converged, i[w].residual, i[w].tolerance));
        let converged = SolveInfo {
            iterations: 0,
            residual: 0.0,
            tolerance: 0.0,
            converged: true,
            negative_curvature: false,
        };
        (w, i.get(w).copied().unwrap_or(converged))
    }
}

/// Of `n` worlds with `figures(w) = (converged, residual, tolerance)`, the one farthest from
/// its tolerance: unconverged before converged, then the largest `residual / tolerance` (a
/// NaN one counts as infinite, a zero residual as 0), the first of equals; 0 if `n = 0`.
fn farthest(n: usize, figures: impl Fn(usize) -> (bool, f64, f64)) -> usize {
    let key = |w: usize| {
        let (converged, residual, tolerance) = figures(w);
        let ratio = match residual / tolerance {
            _ if residual == 0.0 => 0.0,
            r if r.is_nan() => f64::INFINITY,
            r => r,
        };
        (!converged, ratio)
    };
    (0..n)
        .max_by(|&a, &b| {
            key(a)
                .partial_cmp(&key(b))
                .expect("not NaN")
                .then(b.cmp(&a))
        })
        .unwrap_or(0)
}

/// Solves `A^T x = rhs` at `p` part by part (the adjoint solve of the implicit function
/// theorem): `A0^T x0 = rhs0`, then, at a point recorded in `Dual`, `A0^T x1 = rhs1 - A1^T x0`
/// (the theorem's second-order term: the derivative of `A^T x = rhs` along the direction).
/// `check` judges each solve's figures (an error if a world missed its tolerance and the
/// policy says so).
pub(crate) fn solve_transposed<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &Parts,
    settings: &SolveSettings,
    check: impl Fn(&LinearSolve) -> Result<(), Error>,
) -> Result<Parts, Error> {
    solve_transposed_with(sys, p, rhs, |p, r| {
        let (x, solve) = solve_linear(sys, p, r, settings, true)?;
        check(&solve)?;
        Ok(x)
    })
}

/// [`solve_transposed`], its solves `A0^T x = r` on `twin` when there is one: the system in
/// `f64` (whose `A` is `A0`) at its point, while `A1^T x0` comes from `p` in `Dual`.
pub(crate) fn solve_transposed_on<S: NewtonSystem, T: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &Parts,
    twin: Option<(&T, &mut T::Point)>,
    settings: &SolveSettings,
    check: impl Fn(&LinearSolve) -> Result<(), Error>,
) -> Result<Parts, Error> {
    match twin {
        Some((twin, tp)) => solve_transposed_with(sys, p, rhs, |_, r| {
            let (x, solve) = solve_linear(twin, tp, r, settings, true)?;
            check(&solve)?;
            Ok(x)
        }),
        None => solve_transposed(sys, p, rhs, settings, check),
    }
}

/// [`solve_transposed`] with the solves `A0^T x = r` by `solve` (given `p`): e.g. on a twin
/// of the system in `f64`, whose `A` is `A0`, while `A1^T x0` comes from `p` in `Dual`.
pub(crate) fn solve_transposed_with<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &Parts,
    mut solve: impl FnMut(&mut S::Point, &[f64]) -> Result<Vec<f64>, Error>,
) -> Result<Parts, Error> {
    let re = solve(p, &rhs.re)?;
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
            Some(solve(p, &r)?)
        }
    };
    Ok(Parts { re, eps })
}

/// Solves `A x = rhs` (or `A^T x = rhs`) at `p` in every world by [`krylov::solve_blocks`]
/// with the system's preconditioner; returns `x` (masked) and the solve's figures; an error
/// if a pass of the force model failed in it.
pub(crate) fn solve_linear<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &[f64],
    settings: &SolveSettings,
    transpose: bool,
) -> Result<(Vec<f64>, LinearSolve), Error> {
    let active = vec![true; sys.worlds().len()];
    let (x, solved) = solve_worlds(sys, p, rhs, settings, transpose, &active, true)?;
    let infos: Vec<(SolveInfo, bool)> = solved.into_iter().flatten().collect();
    Ok((x, linear_solve(&infos)))
}

/// The figures of the per-world solves `infos` (with whether BiCGSTAB took over).
pub(crate) fn linear_solve(infos: &[(SolveInfo, bool)]) -> LinearSolve {
    LinearSolve {
        products: infos.iter().map(|i| i.0.iterations).max().unwrap_or(0),
        fallbacks: infos.iter().filter(|i| i.1).count(),
        infos: infos.iter().map(|i| i.0).collect(),
    }
}

/// Solves the `active` worlds' blocks of `A x = rhs` (or `A^T x = rhs`) at `p` (CG, then
/// BiCGSTAB if `fall_back`); `x` is masked, and zero in the other worlds.
fn solve_worlds<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    rhs: &[f64],
    settings: &SolveSettings,
    transpose: bool,
    active: &[bool],
    fall_back: bool,
) -> Result<(Vec<f64>, Solved), Error> {
    let mut x = vec![0.0; rhs.len()];
    let solved = krylov::solve_blocks(
        |u, out| match transpose {
            true => sys.apply_t(p, u, out),
            false => sys.apply(p, u, out),
        },
        rhs,
        &mut x,
        sys.precond(),
        settings,
        sys.worlds(),
        active,
        fall_back,
    );
    sys.checked()?;
    sys.mask(&mut x);
    Ok((x, solved))
}

/// The Newton direction at `p` of residual `e` in the `active` worlds: `A d = -G` (zero in
/// the others), with each active world's solve.
pub(crate) fn direction<S: NewtonSystem>(
    sys: &S,
    p: &mut S::Point,
    e: &[f64],
    linear: &SolveSettings,
    active: &[bool],
) -> Result<(Vec<f64>, Solved), Error> {
    let rhs: Vec<f64> = sys.gradient(e).iter().map(|g| -g).collect();
    solve_worlds(sys, p, &rhs, linear, false, active, true)
}

/// The potential `E = E_c + E_r` of one world along a search direction `d`, at one point:
/// `E_c` the part the system knows exactly ([`NewtonSystem::energy`]: inertia and the forces'
/// energies), `E_r` the rest (gravity, control, damping, friction, forces without an energy),
/// whose slope along `d` is what `G . d` leaves after `E_c`'s; `E_r`'s change is estimated by
/// the trapezoid rule on its slopes (exact for constant and linear forces).
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
    /// Each world's, at point `p` of residual `e`, along `d`; `None` if an energy pass
    /// failed.
    fn at<S: NewtonSystem>(sys: &S, p: &S::Point, e: &[f64], d: &[f64]) -> Option<Vec<Self>> {
        let worlds = sys.worlds();
        let (exact, energies) = match sys.energy(p, d) {
            None => (false, vec![(0.0, 0.0); worlds.len()]),
            Some(Ok(c)) => (true, c),
            Some(Err(_)) => return None,
        };
        let g = sys.gradient(e);
        let potentials = worlds
            .iter()
            .zip(energies)
            .map(|(w, (conservative, slope_c))| {
                let slope = dot(&g[w.clone()], &d[w.clone()]);
                Potential {
                    conservative,
                    slope_c,
                    slope,
                    magnitude: conservative.abs()
                        + sys.work(p, w.clone())
                        + slope_c.abs()
                        + slope.abs(),
                    exact,
                }
            });
        Some(potentials.collect())
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

/// A world's accepted step: its merit and its unknowns.
type Accepted = (f64, Vec<f64>);

/// An evaluated point of the whole system: the point, its residual and its unknowns.
struct Evaluated<P> {
    point: P,
    residual: Vec<f64>,
    unknowns: Vec<f64>,
}

impl<P> Evaluated<P> {
    fn at<S: NewtonSystem<Point = P>>(sys: &S, u: Vec<f64>, stats: &mut NewtonStats) -> Self {
        let point = sys.eval(&u);
        stats.force_evaluations += 1;
        Evaluated {
            residual: sys.residual(&point),
            point,
            unknowns: u,
        }
    }
}

/// `u + alpha d` on the unknowns `w`.
fn along(u: &[f64], d: &[f64], alpha: f64, w: Range<usize>) -> Vec<f64> {
    u[w.clone()]
        .iter()
        .zip(&d[w])
        .map(|(u, d)| u + alpha * d)
        .collect()
}

fn same_bits(a: &[f64], b: &[f64]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits())
}

/// Where a world is in a line search.
#[derive(Clone, Copy, PartialEq)]
enum Search {
    /// Not searching (solved, stopped, or not in this search).
    Idle,
    Trying,
    Accepted,
    Failed,
}

/// Newton with line search from the point `first` (already evaluated, and counted here as a
/// force evaluation), each world by its own iteration (its own directions, step lengths and
/// stopping tests; a world that is done waits): every pass covers all worlds, and a world's
/// iterates have the bits it would have alone. Returns the last iterate's unknowns, `stats`
/// saying whether every world converged. Errors only if a pass of the force model failed.
pub(crate) fn newton<S: NewtonSystem>(
    sys: &S,
    first: S::Point,
    s: &NewtonSettings<'_>,
    stats: &mut NewtonStats,
) -> Result<Vec<f64>, Error> {
    let worlds = sys.worlds().to_vec();
    let nw = worlds.len();
    stats.force_evaluations += 1;
    let e = sys.residual(&first);
    let mut at = Evaluated {
        unknowns: sys.unknowns(&first).to_vec(),
        point: first,
        residual: e,
    };
    let mut phi: Vec<f64> = worlds
        .iter()
        .map(|w| sys.merit(&at.residual, w.clone()))
        .collect();
    let mut iterations = vec![0; nw];
    // The cycle watchdog (see `CYCLE`): each world's last iterates before the current one,
    // and whether it now searches on the residual alone.
    let mut history: Vec<std::collections::VecDeque<Vec<f64>>> = vec![Default::default(); nw];
    let mut residual_only = vec![false; nw];
    let mut done = vec![false; nw];
    let mut converged = vec![false; nw];
    let (mut residual, mut tolerance) = (vec![0.0; nw], vec![0.0; nw]);
    loop {
        for (w, r) in worlds.iter().enumerate() {
            if done[w] {
                continue;
            }
            residual[w] = max_abs(&at.residual[r.clone()]);
            tolerance[w] = s.tolerance * sys.scale(&at.point, r.clone());
            // A NaN or infinite residual (or scale) is never converged.
            if within(residual[w], tolerance[w]) {
                (converged[w], done[w]) = (true, true);
            } else if iterations[w] >= s.max_newton || !phi[w].is_finite() {
                done[w] = true;
            }
        }
        let mut active: Vec<bool> = done.iter().map(|d| !d).collect();
        if !active.contains(&true) {
            break;
        }
        stats.newton_iterations += 1;
        for (n, _) in iterations.iter_mut().zip(&active).filter(|(_, &a)| a) {
            *n += 1;
        }
        let (d, solved) = direction(sys, &mut at.point, &at.residual, s.linear, &active)?;
        let infos: Vec<(SolveInfo, bool)> = solved.into_iter().flatten().collect();
        let solve = linear_solve(&infos);
        stats.linear_iterations += solve.products;
        stats.fallbacks += solve.fallbacks;
        for (w, r) in worlds.iter().enumerate() {
            if active[w] && within(residual[w], sys.roundoff_floor(&at.residual, &d, r.clone())) {
                (converged[w], done[w], active[w]) = (true, true, false);
            }
        }
        if !active.contains(&true) {
            break;
        }
        let steps = line_search(sys, &mut at, &d, &phi, (&active, &residual_only), s, stats)?;
        // The next iterate: each searching world's step, the others' unknowns as they are.
        let mut next = at.unknowns.clone();
        for (w, r) in worlds.iter().enumerate() {
            if !active[w] {
                continue;
            }
            match &steps.steps[w] {
                Some((phit, u)) => {
                    phi[w] = *phit;
                    next[r.clone()].copy_from_slice(u);
                    let current = &at.unknowns[r.clone()];
                    residual_only[w] |= cycles(u, current, &history[w]);
                    history[w].push_front(current.to_vec());
                    history[w].truncate(CYCLE);
                }
                // No decrease either way: at the attainable precision (or stuck).
                None => {
                    let floor = 10.0 * sys.roundoff_floor(&at.residual, &d, r.clone());
                    (converged[w], done[w]) = (within(residual[w], floor), true);
                }
            }
        }
        if same_bits(&next, &at.unknowns) {
            continue; // no world moved (each is done)
        }
        at = match steps
            .points
            .into_iter()
            .find(|p| same_bits(&p.unknowns, &next))
        {
            Some(p) => p,
            None => Evaluated::at(sys, next, stats),
        };
    }
    // The figures of the world farthest from its tolerance.
    let worst = farthest(nw, |w| (converged[w], residual[w], tolerance[w]));
    stats.world = worst;
    stats.residual = residual.get(worst).copied().unwrap_or(0.0);
    stats.tolerance = tolerance.get(worst).copied().unwrap_or(0.0);
    stats.converged = converged.iter().all(|&c| c);
    Ok(at.unknowns)
}

/// How many earlier iterates the cycle watchdog compares a new one with. With
/// non-conservative forces (friction, contact damping) the line search's two merits can pull
/// in turn and go round a cycle: a cloth landing on the ground at 1/60 s went round three
/// iterates at a residual of 2 m/s for hundreds of iterations. A world whose new iterate comes
/// back to one of its last `CYCLE` (closer to it than a tenth of the step just taken) searches
/// on the residual alone from there (monotone; along an exact Newton direction the residual
/// decreases for a short enough step wherever the forces are smooth).
const CYCLE: usize = 4;

/// Whether the step from `current` to `next` comes back near one of the `earlier` iterates.
fn cycles(next: &[f64], current: &[f64], earlier: &std::collections::VecDeque<Vec<f64>>) -> bool {
    let dist = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt()
    };
    let step = dist(next, current);
    step > 0.0 && earlier.iter().any(|e| dist(next, e) <= 0.1 * step)
}

/// What a line search found: per world its step (`None`: none decreases either merit, or
/// not searching), and the points it evaluated that the next iterate may be.
struct Steps<P> {
    steps: Vec<Option<Accepted>>,
    points: Vec<Evaluated<P>>,
}

/// Backtracking line searches along `d` from `at` for the `active` worlds: a step is accepted
/// if it decreases either merit (module docs). The potential is what makes large steps on
/// stiff nonlinear forces and through contact converge: there the residual has local minima.
/// A world where neither merit decreases along the Newton direction (not a descent direction
/// of the potential where `A` is indefinite) takes a potential step, or else its best
/// residual decrease.
fn line_search<S: NewtonSystem>(
    sys: &S,
    at: &mut Evaluated<S::Point>,
    d: &[f64],
    phi: &[f64],
    (active, residual_only): (&[bool], &[bool]),
    s: &NewtonSettings<'_>,
    stats: &mut NewtonStats,
) -> Result<Steps<S::Point>, Error> {
    let worlds = sys.worlds();
    let nw = worlds.len();
    let g = sys.gradient(&at.residual);
    let slope0: Vec<f64> = worlds
        .iter()
        .map(|w| dot(&g[w.clone()], &d[w.clone()]))
        .collect();
    let mut state: Vec<Search> = active
        .iter()
        .map(|&a| if a { Search::Trying } else { Search::Idle })
        .collect();
    // Which worlds check the potential; their potentials at the start (`None`: an energy
    // pass failed, and the search keeps to the residual).
    let with_potential: Vec<bool> = (0..nw)
        .map(|w| active[w] && s.line_search && slope0[w] < 0.0 && !residual_only[w])
        .collect();
    let start = match with_potential.contains(&true) {
        true => Potential::at(sys, &at.point, &at.residual, d),
        false => None,
    };
    let mut alpha = vec![1.0; nw];
    let mut steps: Vec<Option<Accepted>> = vec![None; nw];
    let mut best: Vec<Option<Accepted>> = vec![None; nw];
    // The trial where a best was last found, and the last trial.
    let (mut best_point, mut last) = (None, None);
    // The accepted worlds' unknowns stay in the later trials (the same bits there).
    let mut target = at.unknowns.clone();
    for k in 0..=s.max_backtracks {
        if !state.contains(&Search::Trying) {
            break;
        }
        let mut u = target.clone();
        for (w, r) in worlds.iter().enumerate() {
            if state[w] == Search::Trying {
                u[r.clone()].copy_from_slice(&along(&at.unknowns, d, alpha[w], r.clone()));
            }
        }
        let t = Evaluated::at(sys, u, stats);
        // Every trial, even one the residual accepts, is checked against the potential
        // (for implicit Euler, an energy pass and its tangent: 1.25x the time of a small
        // cloth dropped on the ground, 1.01x that of a 96-tet block, docs/performance.md).
        // Checking it only once a potential step was taken is cheaper but let a block
        // thrown at the ground at 1/60 s stall again.
        let checks = (0..nw).any(|w| state[w] == Search::Trying && with_potential[w]);
        let trial = match (&start, checks) {
            (Some(_), true) => Potential::at(sys, &t.point, &t.residual, d),
            _ => None,
        };
        let (mut halved, mut found) = (false, false);
        for (w, r) in worlds.iter().enumerate() {
            if state[w] != Search::Trying {
                continue;
            }
            let phit = sys.merit(&t.residual, r.clone());
            let mut residual_ok = phit <= (1.0 - 2e-4 * alpha[w]) * phi[w];
            let mut potential_ok = false;
            if let (true, Some(s0), Some(tp)) = (with_potential[w], &start, &trial) {
                let (s0, tp) = (&s0[w], &tp[w]);
                let change = s0.change(tp, alpha[w]);
                potential_ok = change.is_finite() && change <= 1e-4 * alpha[w] * slope0[w];
                // A residual decrease that raises the exact potential (beyond its
                // rounding) is refused: taking both merits' steps in turn can cycle
                // (seen at impacts with friction).
                if s0.exact {
                    residual_ok &= !(change > s0.rounding(tp, sys.epsilon()));
                }
            }
            if !s.line_search || (phit.is_finite() && (residual_ok || potential_ok)) {
                state[w] = Search::Accepted;
                steps[w] = Some((phit, t.unknowns[r.clone()].to_vec()));
                target[r.clone()].copy_from_slice(&t.unknowns[r.clone()]);
                continue;
            }
            if phit.is_finite() && !best[w].as_ref().is_some_and(|b| phit >= b.0) {
                best[w] = Some((phit, t.unknowns[r.clone()].to_vec()));
                found = true;
            }
            if k < s.max_backtracks {
                halved = true;
                alpha[w] *= 0.5;
            } else {
                state[w] = Search::Failed;
            }
        }
        stats.backtracks += halved as usize;
        match found {
            true => best_point = Some(t),
            false => last = Some(t),
        }
    }
    let failed: Vec<bool> = state.iter().map(|&s| s == Search::Failed).collect();
    let mut points: Vec<Evaluated<S::Point>> = Vec::new();
    if failed.contains(&true) {
        let (potential, point) = potential_step(sys, at, &target, &failed, s, stats)?;
        sys.checked()?;
        for w in (0..nw).filter(|&w| failed[w]) {
            steps[w] = potential[w]
                .clone()
                .or_else(|| best[w].take().filter(|b| b.0 < phi[w]));
        }
        points.extend(point);
    }
    points.extend(last);
    points.extend(best_point);
    Ok(Steps { steps, points })
}

/// Steps that decrease the potential `E` (gradient `G`) in the worlds `which`: along the CG
/// solution of `A d = -G` truncated at negative curvature (a descent direction of `E`), or
/// else along steepest descent, with a backtracking (Armijo) line search on `E`. The other
/// worlds stay at their unknowns in `others` in the trials (their next iterate's, so that the
/// last trial can be it). Returns per world the merit and unknowns reached, or `None`, and
/// the last point evaluated.
#[allow(clippy::type_complexity)]
fn potential_step<S: NewtonSystem>(
    sys: &S,
    at: &mut Evaluated<S::Point>,
    others: &[f64],
    which: &[bool],
    s: &NewtonSettings<'_>,
    stats: &mut NewtonStats,
) -> Result<(Vec<Option<Accepted>>, Option<Evaluated<S::Point>>), Error> {
    let worlds = sys.worlds();
    let nw = worlds.len();
    let mut found: Vec<Option<Accepted>> = vec![None; nw];
    let g = sys.gradient(&at.residual);
    let rhs: Vec<f64> = g.iter().map(|g| -g).collect();
    let (mut d, solved) = solve_worlds(sys, &mut at.point, &rhs, s.linear, false, which, false)?;
    let infos: Vec<(SolveInfo, bool)> = solved.into_iter().flatten().collect();
    stats.linear_iterations += linear_solve(&infos).products;
    let mut alpha = vec![1.0; nw];
    let mut searching = which.to_vec();
    // Worlds where the truncated CG direction does not descend: steepest descent.
    let mut slopes: Vec<Option<f64>> = vec![None; nw];
    let mut steepest = None;
    for (w, r) in worlds.iter().enumerate() {
        let slope0 = dot(&g[r.clone()], &d[r.clone()]);
        if !which[w] || !(slope0.is_nan() || slope0 >= 0.0) {
            continue;
        }
        let sd = steepest.get_or_insert_with(|| sys.steepest(&at.residual));
        d[r.clone()].copy_from_slice(&sd[r.clone()]);
        let slope = dot(&g[r.clone()], &d[r.clone()]);
        match slope.is_nan() || slope >= 0.0 {
            true => searching[w] = false,
            false => slopes[w] = Some(slope),
        }
    }
    if slopes.iter().any(Option::is_some) {
        let lengths = sys.steepest_lengths(&mut at.point, &d, &slopes, stats);
        for w in (0..nw).filter(|&w| slopes[w].is_some()) {
            alpha[w] = lengths[w];
        }
    }
    // An energy whose pass fails: no potential step (the residual's best is next).
    let Some(start) = Potential::at(sys, &at.point, &at.residual, &d) else {
        return Ok((found, None));
    };
    for (w, s0) in start.iter().enumerate() {
        if s0.slope.is_nan() || s0.slope >= 0.0 {
            searching[w] = false;
        }
    }
    let mut last = None;
    for _ in 0..=s.max_backtracks {
        if !searching.contains(&true) {
            break;
        }
        let mut u = others.to_vec();
        for (w, r) in worlds.iter().enumerate() {
            if which[w] {
                let uw = match (searching[w], &found[w]) {
                    (true, _) => along(&at.unknowns, &d, alpha[w], r.clone()),
                    (false, Some((_, uw))) => uw.clone(),
                    (false, None) => at.unknowns[r.clone()].to_vec(),
                };
                u[r.clone()].copy_from_slice(&uw);
            }
        }
        let t = Evaluated::at(sys, u, stats);
        let Some(trial) = Potential::at(sys, &t.point, &t.residual, &d) else {
            return Ok((found, None));
        };
        let mut halved = false;
        for (w, r) in worlds.iter().enumerate() {
            if !searching[w] {
                continue;
            }
            if start[w].armijo(&trial[w], alpha[w]) {
                let merit = sys.merit(&t.residual, r.clone());
                found[w] = Some((merit, t.unknowns[r.clone()].to_vec()));
                searching[w] = false;
            } else {
                halved = true;
                alpha[w] *= 0.5;
            }
        }
        stats.backtracks += halved as usize;
        last = Some(t);
    }
    Ok((found, last))
}

/// Names world `world` in an error's context, in a model of more than one.
pub(crate) fn world_context(world: usize, worlds: usize) -> String {
    match worlds > 1 {
        true => format!("in world {world} of {worlds} (each world is solved apart)"),
        false => String::new(),
    }
}

/// `", in world w of n ..."` for a context that goes on, in a model of more than one world.
pub(crate) fn with_world(world: usize, worlds: usize) -> String {
    match worlds > 1 {
        true => format!(", {}", world_context(world, worlds)),
        false => String::new(),
    }
}
