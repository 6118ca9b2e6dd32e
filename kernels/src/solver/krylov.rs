//! Matrix-free Krylov solvers for the implicit integrators: preconditioned conjugate gradients
//! ([`cg`], for symmetric positive definite systems) and BiCGSTAB ([`bicgstab`], for general
//! nonsingular ones, the fallback when CG meets negative curvature or stalls).
//!
//! The matrix is never formed: a solver only calls `apply(u, out)`, which writes `A u` into
//! `out`. [`crate::integrators::ImplicitEuler`] and [`crate::statics::Equilibrium`] (through
//! [`crate::solver`]'s Newton iteration) compute those products with the tangent
//! kernels of the force model (`A u`) or with its adjoint kernels (`A^T u`). Vectors are flat
//! `f64` slices (three components per particle), whatever the scalar of the model.
//!
//! A model of several worlds is block diagonal, one block per world: the library solves each
//! block by its own iteration (its own dot products, step lengths and stopping test), all of
//! them sharing each product `A u` (one pass of the kernels for every world), so that a
//! world's solution has the same bits alone or among others.
//!
//! ```
//! use adflex_kernels::solver::krylov::{cg, SolveSettings};
//! // A = [[4, 1], [1, 3]], b = [1, 2]: x = [1/11, 7/11].
//! let a = |u: &[f64], out: &mut [f64]| {
//!     out[0] = 4.0 * u[0] + u[1];
//!     out[1] = u[0] + 3.0 * u[1];
//! };
//! let mut x = vec![0.0; 2];
//! let info = cg(a, &[1.0, 2.0], &mut x, None, &SolveSettings::default());
//! assert!(info.converged);
//! assert!((x[0] - 1.0 / 11.0).abs() < 1e-12 && (x[1] - 7.0 / 11.0).abs() < 1e-12);
//! ```

use std::ops::Range;

/// Stopping rule of the Krylov solvers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveSettings {
    /// Converged when `|r| <= rel_tol |b| + abs_tol` (Euclidean norms; default `1e-10`; in
    /// the library's solves over several worlds, each world's norms).
    pub rel_tol: f64,
    /// Absolute floor of the tolerance (default `1e-14`).
    pub abs_tol: f64,
    /// Iteration cap (default 1000).
    pub max_iter: usize,
}

impl Default for SolveSettings {
    fn default() -> Self {
        SolveSettings {
            rel_tol: 1e-10,
            abs_tol: 1e-14,
            max_iter: 1000,
        }
    }
}

/// What a solve did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveInfo {
    /// Iterations run (matrix-vector products, plus one for the initial residual in CG; two
    /// per iteration in BiCGSTAB).
    pub iterations: usize,
    /// Final residual norm `|b - A x|` (as the recurrence tracks it; NaN if the iterate is
    /// not finite).
    pub residual: f64,
    /// The tolerance `rel_tol |b| + abs_tol` it had to meet.
    pub tolerance: f64,
    /// Whether the tolerance was met.
    pub converged: bool,
    /// CG only: a direction of non-positive curvature `p^T A p <= 0` was met (the matrix is
    /// not positive definite). `x` holds the last iterate before it.
    pub negative_curvature: bool,
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn norm(a: &[f64]) -> f64 {
    dot(a, a).sqrt()
}

/// `z = D r` for a diagonal preconditioner `D` (the identity without one).
fn precondition(inv_diag: Option<&[f64]>, r: &[f64], z: &mut [f64]) {
    match inv_diag {
        Some(d) => z
            .iter_mut()
            .zip(r)
            .zip(d)
            .for_each(|((z, r), d)| *z = r * d),
        None => z.copy_from_slice(r),
    }
}

/// One block's solve, advanced one product at a time: it says which vector it needs `A`
/// applied to next ([`Iteration::wants`]) and continues when given the product
/// ([`Iteration::take`]), so that the solves of several blocks can share each product.
trait Iteration {
    /// The vector to multiply next, or `None` once the solve is over.
    fn wants(&self) -> Option<&[f64]>;
    /// Continues with `A u`, `u` the vector [`Iteration::wants`] gave.
    fn take(&mut self, product: &[f64]);
}

/// Runs the solves `blocks` (each on its range of the unknowns, the ranges disjoint) with
/// one product `apply(u, out)` per round for all of them; a block's `u` is its wanted vector
/// (zeros on the ranges of the blocks that want none).
fn run_blocks(
    apply: &mut impl FnMut(&[f64], &mut [f64]),
    n: usize,
    blocks: &mut [(Range<usize>, &mut dyn Iteration)],
) {
    let mut u = vec![0.0; n];
    let mut out = vec![0.0; n];
    // One block over every unknown: its vector is multiplied as it is.
    let whole = blocks.len() == 1 && blocks[0].0 == (0..n);
    loop {
        if whole {
            let it = &mut blocks[0].1;
            match it.wants() {
                Some(w) => apply(w, &mut out),
                None => return,
            }
            it.take(&out);
            continue;
        }
        let mut any = false;
        for (range, it) in blocks.iter() {
            match it.wants() {
                Some(w) => {
                    u[range.clone()].copy_from_slice(w);
                    any = true;
                }
                None => u[range.clone()].fill(0.0),
            }
        }
        if !any {
            return;
        }
        apply(&u, &mut out);
        for (range, it) in blocks.iter_mut() {
            if it.wants().is_some() {
                it.take(&out[range.clone()]);
            }
        }
    }
}

/// What a [`CgIteration`] multiplies next.
#[derive(Clone, Copy, PartialEq)]
enum CgNeeds {
    /// `A x`, for the first residual of a warm start.
    Residual,
    /// `A p`, the search direction's.
    Direction,
    Nothing,
}

/// Preconditioned conjugate gradients ([`cg`]), one product at a time.
struct CgIteration<'a> {
    b: &'a [f64],
    x: Vec<f64>,
    inv_diag: Option<&'a [f64]>,
    max_iter: usize,
    r: Vec<f64>,
    z: Vec<f64>,
    p: Vec<f64>,
    rz: f64,
    /// Passes of the main loop (products of search directions).
    loops: usize,
    info: SolveInfo,
    needs: CgNeeds,
}

impl<'a> CgIteration<'a> {
    fn new(b: &'a [f64], x: Vec<f64>, inv_diag: Option<&'a [f64]>, s: &SolveSettings) -> Self {
        let n = b.len();
        assert_eq!(x.len(), n, "cg: x and b have different lengths");
        let mut it = CgIteration {
            b,
            x,
            inv_diag,
            max_iter: s.max_iter,
            r: vec![0.0; n],
            z: Vec::new(),
            p: Vec::new(),
            rz: 0.0,
            loops: 0,
            info: SolveInfo {
                iterations: 0,
                residual: 0.0,
                tolerance: s.rel_tol * norm(b) + s.abs_tol,
                converged: false,
                negative_curvature: false,
            },
            needs: CgNeeds::Nothing,
        };
        if it.x.iter().any(|&v| v != 0.0) {
            it.needs = CgNeeds::Residual;
        } else {
            it.r.copy_from_slice(b);
            it.start();
        }
        it
    }

    /// From the first residual `r`.
    fn start(&mut self) {
        let rn = norm(&self.r);
        self.info.residual = rn;
        self.info.converged = rn <= self.info.tolerance;
        if self.info.converged {
            self.needs = CgNeeds::Nothing;
            return;
        }
        self.z = vec![0.0; self.r.len()];
        precondition(self.inv_diag, &self.r, &mut self.z);
        self.p = self.z.clone();
        self.rz = dot(&self.r, &self.z);
        self.next();
    }

    fn next(&mut self) {
        self.needs = match self.loops < self.max_iter {
            true => CgNeeds::Direction,
            false => CgNeeds::Nothing,
        };
    }
}

impl Iteration for CgIteration<'_> {
    fn wants(&self) -> Option<&[f64]> {
        match self.needs {
            CgNeeds::Residual => Some(&self.x),
            CgNeeds::Direction => Some(&self.p),
            CgNeeds::Nothing => None,
        }
    }

    fn take(&mut self, ap: &[f64]) {
        self.info.iterations += 1;
        if self.needs == CgNeeds::Residual {
            self.r
                .iter_mut()
                .zip(self.b)
                .zip(ap)
                .for_each(|((r, b), a)| *r = b - a);
            return self.start();
        }
        self.loops += 1;
        self.needs = CgNeeds::Nothing;
        let pap = dot(&self.p, ap);
        if pap.is_nan() || pap <= 0.0 {
            self.info.negative_curvature = true;
            return;
        }
        let alpha = self.rz / pap;
        self.x
            .iter_mut()
            .zip(&self.p)
            .for_each(|(x, p)| *x += alpha * p);
        self.r.iter_mut().zip(ap).for_each(|(r, a)| *r -= alpha * a);
        let rn = norm(&self.r);
        self.info.residual = rn;
        if rn <= self.info.tolerance {
            self.info.converged = true;
            return;
        }
        precondition(self.inv_diag, &self.r, &mut self.z);
        let rz_new = dot(&self.r, &self.z);
        let beta = rz_new / self.rz;
        self.rz = rz_new;
        self.p
            .iter_mut()
            .zip(&self.z)
            .for_each(|(p, z)| *p = z + beta * *p);
        self.next();
    }
}

/// What a [`BicgIteration`] multiplies next.
#[derive(Clone, Copy, PartialEq)]
enum BicgNeeds {
    /// `A x`, at a (re)start.
    Residual,
    /// `A y`, `y` the preconditioned direction.
    Direction,
    /// `A z`, `z` the preconditioned intermediate residual.
    Stabilizer,
    Nothing,
}

/// BiCGSTAB ([`bicgstab`]), one product at a time.
struct BicgIteration<'a> {
    b: &'a [f64],
    x: Vec<f64>,
    inv_diag: Option<&'a [f64]>,
    max_iter: usize,
    r: Vec<f64>,
    r0: Vec<f64>,
    v: Vec<f64>,
    p: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    sv: Vec<f64>,
    rho: f64,
    alpha: f64,
    omega: f64,
    info: SolveInfo,
    needs: BicgNeeds,
}

impl<'a> BicgIteration<'a> {
    fn new(b: &'a [f64], x: Vec<f64>, inv_diag: Option<&'a [f64]>, s: &SolveSettings) -> Self {
        let n = b.len();
        assert_eq!(x.len(), n, "bicgstab: x and b have different lengths");
        let mut it = BicgIteration {
            b,
            x,
            inv_diag,
            max_iter: s.max_iter,
            r: vec![0.0; n],
            r0: Vec::new(),
            v: vec![0.0; n],
            p: vec![0.0; n],
            y: vec![0.0; n],
            z: vec![0.0; n],
            sv: vec![0.0; n],
            rho: 1.0,
            alpha: 1.0,
            omega: 1.0,
            info: SolveInfo {
                iterations: 0,
                residual: f64::INFINITY,
                tolerance: s.rel_tol * norm(b) + s.abs_tol,
                converged: false,
                negative_curvature: false,
            },
            needs: BicgNeeds::Nothing,
        };
        it.restart();
        it
    }

    /// A (re)start from the current iterate, if iterations remain.
    fn restart(&mut self) {
        self.needs = match self.info.iterations < self.max_iter {
            true => BicgNeeds::Residual,
            false => BicgNeeds::Nothing,
        };
    }

    fn converged(&mut self, residual: f64) {
        self.info.residual = residual;
        self.info.converged = true;
        self.needs = BicgNeeds::Nothing;
    }

    /// The top of an iteration: the new direction, or a restart if the recurrence broke
    /// down.
    fn iterate(&mut self) {
        if self.info.iterations >= self.max_iter {
            self.needs = BicgNeeds::Nothing;
            return;
        }
        let rho_new = dot(&self.r0, &self.r);
        if rho_new.abs() < 1e-300 || self.omega == 0.0 {
            return self.restart();
        }
        let beta = (rho_new / self.rho) * (self.alpha / self.omega);
        self.rho = rho_new;
        for k in 0..self.p.len() {
            self.p[k] = self.r[k] + beta * (self.p[k] - self.omega * self.v[k]);
        }
        precondition(self.inv_diag, &self.p, &mut self.y);
        self.needs = BicgNeeds::Direction;
    }
}

impl Iteration for BicgIteration<'_> {
    fn wants(&self) -> Option<&[f64]> {
        match self.needs {
            BicgNeeds::Residual => Some(&self.x),
            BicgNeeds::Direction => Some(&self.y),
            BicgNeeds::Stabilizer => Some(&self.z),
            BicgNeeds::Nothing => None,
        }
    }

    fn take(&mut self, product: &[f64]) {
        self.info.iterations += 1;
        let tol = self.info.tolerance;
        match self.needs {
            BicgNeeds::Residual => {
                self.r
                    .iter_mut()
                    .zip(self.b)
                    .zip(product)
                    .for_each(|((r, b), a)| *r = b - a);
                self.info.residual = norm(&self.r);
                if self.info.residual <= tol {
                    return self.converged(self.info.residual);
                }
                self.r0 = self.r.clone();
                (self.rho, self.alpha, self.omega) = (1.0, 1.0, 1.0);
                self.v.fill(0.0);
                self.p.fill(0.0);
                self.iterate();
            }
            BicgNeeds::Direction => {
                self.v.copy_from_slice(product);
                let r0v = dot(&self.r0, &self.v);
                if r0v.abs() < 1e-300 {
                    return self.restart();
                }
                self.alpha = self.rho / r0v;
                for k in 0..self.sv.len() {
                    self.sv[k] = self.r[k] - self.alpha * self.v[k];
                }
                if norm(&self.sv) <= tol {
                    let alpha = self.alpha;
                    self.x
                        .iter_mut()
                        .zip(&self.y)
                        .for_each(|(x, y)| *x += alpha * y);
                    return self.converged(norm(&self.sv));
                }
                precondition(self.inv_diag, &self.sv, &mut self.z);
                self.needs = BicgNeeds::Stabilizer;
            }
            BicgNeeds::Stabilizer => {
                let t = product;
                let tt = dot(t, t);
                self.omega = if tt > 0.0 { dot(t, &self.sv) / tt } else { 0.0 };
                let (alpha, omega) = (self.alpha, self.omega);
                for (k, t) in t.iter().enumerate() {
                    self.x[k] += alpha * self.y[k] + omega * self.z[k];
                    self.r[k] = self.sv[k] - omega * t;
                }
                self.info.residual = norm(&self.r);
                if self.info.residual <= tol {
                    return self.converged(self.info.residual);
                }
                self.iterate();
            }
            BicgNeeds::Nothing => unreachable!("bicgstab: a product it did not ask for"),
        }
    }
}

/// CG, then BiCGSTAB from CG's iterate if CG did not converge ([`solve`]), one product at a
/// time.
struct CgThenBicg<'a> {
    cg: CgIteration<'a>,
    bicg: Option<BicgIteration<'a>>,
    settings: SolveSettings,
    /// Whether BiCGSTAB may take over (else CG alone).
    may_fall_back: bool,
}

impl<'a> CgThenBicg<'a> {
    fn new(
        b: &'a [f64],
        x: Vec<f64>,
        inv_diag: Option<&'a [f64]>,
        s: &SolveSettings,
        may_fall_back: bool,
    ) -> Self {
        let mut it = CgThenBicg {
            cg: CgIteration::new(b, x, inv_diag, s),
            bicg: None,
            settings: *s,
            may_fall_back,
        };
        it.fall_back();
        it
    }

    /// BiCGSTAB takes over once CG ended without converging.
    fn fall_back(&mut self) {
        let cg_ended = self.cg.needs == CgNeeds::Nothing && !self.cg.info.converged;
        if self.may_fall_back && self.bicg.is_none() && cg_ended {
            let (b, x) = (self.cg.b, self.cg.x.clone());
            self.bicg = Some(BicgIteration::new(b, x, self.cg.inv_diag, &self.settings));
        }
    }

    /// The iterate, the info of the last solver run (iterations of both) and whether
    /// BiCGSTAB took over.
    fn finish(self) -> (Vec<f64>, SolveInfo, bool) {
        match self.bicg {
            None => (self.cg.x, self.cg.info, false),
            Some(b) => {
                let mut info = b.info;
                info.iterations += self.cg.info.iterations;
                info.negative_curvature = self.cg.info.negative_curvature;
                (b.x, info, true)
            }
        }
    }
}

impl Iteration for CgThenBicg<'_> {
    fn wants(&self) -> Option<&[f64]> {
        match &self.bicg {
            Some(b) => b.wants(),
            None => self.cg.wants(),
        }
    }

    fn take(&mut self, product: &[f64]) {
        match &mut self.bicg {
            Some(b) => b.take(product),
            None => {
                self.cg.take(product);
                self.fall_back();
            }
        }
    }
}

/// Preconditioned conjugate gradients for `A x = b`, `A` symmetric positive definite, starting
/// from the `x` given (pass zeros for a cold start).
///
/// `apply(u, out)` writes `A u`; `inv_diag` (optional) is a diagonal (Jacobi) preconditioner,
/// the inverse of an approximation of `A`'s diagonal (e.g. the inverse masses). Stops on
/// convergence, after `max_iter` iterations, or at a direction of non-positive curvature
/// ([`SolveInfo::negative_curvature`]; `x` then holds the last iterate, which for a first
/// iteration from zero is zero: callers fall back to [`bicgstab`] or to the gradient).
pub fn cg(
    mut apply: impl FnMut(&[f64], &mut [f64]),
    b: &[f64],
    x: &mut [f64],
    inv_diag: Option<&[f64]>,
    s: &SolveSettings,
) -> SolveInfo {
    let mut it = CgIteration::new(b, x.to_vec(), inv_diag, s);
    run_blocks(&mut apply, b.len(), &mut [(0..b.len(), &mut it)]);
    x.copy_from_slice(&it.x);
    it.info
}

/// BiCGSTAB (van der Vorst) for a general nonsingular `A x = b`, starting from the `x` given.
/// Two products `A u` per iteration; `inv_diag` is an optional diagonal (right)
/// preconditioner. Restarts from the current iterate if the recurrence breaks down.
pub fn bicgstab(
    mut apply: impl FnMut(&[f64], &mut [f64]),
    b: &[f64],
    x: &mut [f64],
    inv_diag: Option<&[f64]>,
    s: &SolveSettings,
) -> SolveInfo {
    let mut it = BicgIteration::new(b, x.to_vec(), inv_diag, s);
    run_blocks(&mut apply, b.len(), &mut [(0..b.len(), &mut it)]);
    x.copy_from_slice(&it.x);
    it.info
}

/// Solves `A x = b` with [`cg`] first and, if CG meets negative curvature or does not
/// converge, with [`bicgstab`] from CG's iterate. Returns the info of the last solver run and
/// whether the fallback was used.
pub fn solve(
    apply: impl FnMut(&[f64], &mut [f64]),
    b: &[f64],
    x: &mut [f64],
    inv_diag: Option<&[f64]>,
    s: &SolveSettings,
) -> (SolveInfo, bool) {
    let n = b.len();
    let (info, fell_back) = solve_blocks(
        apply,
        b,
        x,
        inv_diag,
        s,
        std::slice::from_ref(&(0..n)),
        &[true],
        true,
    )
    .pop()
    .flatten()
    .expect("one block, solved");
    (info, fell_back)
}

/// Solves the blocks of a block-diagonal `A x = b` marked `active` (`blocks`: disjoint ranges
/// of the unknowns, e.g. the worlds of a model), each by its own [`cg`] (and [`bicgstab`] if
/// `fall_back` and CG does not converge), every round of products one `apply` for all: a
/// block's `x`, info and fallback are the bits it would get solved alone. `x` is left as it
/// is outside the active blocks; an inactive block's entry is `None`.
#[allow(clippy::too_many_arguments)]
pub(crate) fn solve_blocks(
    mut apply: impl FnMut(&[f64], &mut [f64]),
    b: &[f64],
    x: &mut [f64],
    inv_diag: Option<&[f64]>,
    s: &SolveSettings,
    blocks: &[Range<usize>],
    active: &[bool],
    fall_back: bool,
) -> Vec<Option<(SolveInfo, bool)>> {
    assert_eq!(x.len(), b.len(), "solve: x and b have different lengths");
    let mut its: Vec<(Range<usize>, CgThenBicg<'_>)> = blocks
        .iter()
        .zip(active)
        .filter(|(_, &a)| a)
        .map(|(r, _)| {
            let d = inv_diag.map(|d| &d[r.clone()]);
            let it = CgThenBicg::new(&b[r.clone()], x[r.clone()].to_vec(), d, s, fall_back);
            (r.clone(), it)
        })
        .collect();
    {
        let mut refs: Vec<(Range<usize>, &mut dyn Iteration)> = its
            .iter_mut()
            .map(|(r, it)| (r.clone(), it as &mut dyn Iteration))
            .collect();
        run_blocks(&mut apply, b.len(), &mut refs);
    }
    let mut solved = its.into_iter().map(|(r, it)| (r, it.finish()));
    let mut next = solved.next();
    active
        .iter()
        .map(|&a| {
            if !a {
                return None;
            }
            let (r, (xb, info, fell_back)) = next.take().expect("an active block");
            x[r].copy_from_slice(&xb);
            next = solved.next();
            Some((info, fell_back))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn matvec(a: &[Vec<f64>]) -> impl FnMut(&[f64], &mut [f64]) + '_ {
        move |u, out| {
            for (o, row) in out.iter_mut().zip(a) {
                *o = dot(row, u);
            }
        }
    }

    #[test]
    fn cg_solves_spd() {
        let n = 20;
        let a: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| match (i as i64 - j as i64).abs() {
                        0 => 4.0 + i as f64 * 0.1,
                        1 => -1.0,
                        _ => 0.0,
                    })
                    .collect()
            })
            .collect();
        let b: Vec<f64> = (0..n).map(|i| (i as f64).sin()).collect();
        let diag: Vec<f64> = (0..n).map(|i| 1.0 / a[i][i]).collect();
        let mut x = vec![0.0; n];
        let info = cg(
            matvec(&a),
            &b,
            &mut x,
            Some(&diag),
            &SolveSettings::default(),
        );
        assert!(info.converged && !info.negative_curvature, "{info:?}");
        let mut ax = vec![0.0; n];
        matvec(&a)(&x, &mut ax);
        let err = ax
            .iter()
            .zip(&b)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-9, "{err}");
    }

    #[test]
    fn cg_reports_negative_curvature_and_solve_falls_back() {
        let a = vec![vec![1.0, 0.0], vec![0.0, -2.0]];
        let b = [1.0, 1.0];
        let mut x = vec![0.0; 2];
        let info = cg(matvec(&a), &b, &mut x, None, &SolveSettings::default());
        assert!(info.negative_curvature);
        let mut x = vec![0.0; 2];
        let (info, fell_back) = solve(matvec(&a), &b, &mut x, None, &SolveSettings::default());
        assert!(fell_back && info.converged, "{info:?}");
        assert!(
            (x[0] - 1.0).abs() < 1e-9 && (x[1] + 0.5).abs() < 1e-9,
            "{x:?}"
        );
    }

    #[test]
    fn bicgstab_solves_nonsymmetric() {
        let n = 15;
        let a: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| {
                        if i == j {
                            5.0
                        } else if j == i + 1 {
                            -2.0
                        } else if i == j + 1 {
                            0.5
                        } else {
                            0.0
                        }
                    })
                    .collect()
            })
            .collect();
        let b: Vec<f64> = (0..n).map(|i| 1.0 + i as f64).collect();
        let mut x = vec![0.0; n];
        let info = bicgstab(matvec(&a), &b, &mut x, None, &SolveSettings::default());
        assert!(info.converged, "{info:?}");
        let mut ax = vec![0.0; n];
        matvec(&a)(&x, &mut ax);
        let err = ax
            .iter()
            .zip(&b)
            .map(|(p, q)| (p - q).abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-8, "{err}");
    }

    /// Blocks solved together: each block's solution, figures and fallback are the bits it
    /// gets alone (its own dot products and stopping test), whatever its neighbours.
    #[test]
    fn blocks_are_solved_as_alone() {
        // Block 0 SPD (slow to converge), block 1 indefinite (BiCGSTAB takes over), block 2
        // SPD and easy, block 3 a zero right-hand side.
        let spd = |n: usize, d: f64| -> Vec<Vec<f64>> {
            (0..n)
                .map(|i| {
                    (0..n)
                        .map(|j| match (i as i64 - j as i64).abs() {
                            0 => d + i as f64 * 0.3,
                            1 => -1.0,
                            _ => 0.0,
                        })
                        .collect()
                })
                .collect()
        };
        let blocks: Vec<Vec<Vec<f64>>> = vec![
            spd(12, 2.05),
            vec![vec![1.0, 0.2], vec![0.2, -2.0]],
            spd(5, 6.0),
            spd(3, 4.0),
        ];
        let rhs: Vec<Vec<f64>> = vec![
            (0..12).map(|i| (i as f64 * 0.7).cos()).collect(),
            vec![1.0, 1.0],
            (0..5).map(|i| 1.0 + i as f64).collect(),
            vec![0.0; 3],
        ];
        let mut ranges = Vec::new();
        let mut start = 0;
        for b in &blocks {
            ranges.push(start..start + b.len());
            start += b.len();
        }
        let n = start;
        let whole = |u: &[f64], out: &mut [f64]| {
            for (r, a) in ranges.iter().zip(&blocks) {
                matvec(a)(&u[r.clone()], &mut out[r.clone()]);
            }
        };
        let b: Vec<f64> = rhs.concat();
        let s = SolveSettings::default();
        for order in [[true, true, true, true], [true, false, true, true]] {
            let mut x = vec![0.0; n];
            let solved = solve_blocks(whole, &b, &mut x, None, &s, &ranges, &order, true);
            for (k, r) in ranges.iter().enumerate() {
                let Some(got) = solved[k] else {
                    assert!(!order[k] && x[r.clone()].iter().all(|&v| v == 0.0));
                    continue;
                };
                let mut alone = vec![0.0; r.len()];
                let want = solve(matvec(&blocks[k]), &rhs[k], &mut alone, None, &s);
                assert_eq!(got, want, "block {k}");
                assert_eq!(x[r.clone()].to_vec(), alone, "block {k}");
                assert!(got.0.converged, "block {k}: {got:?}");
            }
            assert!(solved[1].is_none_or(|i| i.1), "BiCGSTAB took block 1 over");
        }
    }
}
