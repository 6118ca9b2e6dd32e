//! The inner linear solves of the Gauss-Newton methods: conjugate gradients on `(JᵀJ + λI) d
//! = -g`, to a tolerance set by Eisenstat and Walker's forcing term, preconditioned by the
//! curvature that earlier solves measured (Morales and Nocedal's automatic preconditioning).

use std::collections::VecDeque;

use adflex_runtime::Error;

use crate::newton::{dot, Apply};

/// The forcing term's largest value for Newton-CG (Steihaug's CG in a trust region, not
/// preconditioned).
pub(crate) const NEWTON_FORCING: f64 = 0.5;

/// The forcing term's largest value for Gauss-Newton and Levenberg-Marquardt. Their solves are
/// preconditioned by the earlier products ([`Curvature`]), so a tighter solve costs few
/// products, while each outer step saves a forward and an adjoint pass (measured on
/// `examples/second_order.rs`, passes to 1e-10 of the initial loss, 0.5 to 0.1: the net's
/// identification 148 to 130, the cable's design 72 to 56).
pub(crate) const LEAST_SQUARES_FORCING: f64 = 0.1;

/// The relative tolerance of the inner conjugate gradients (Eisenstat and Walker's second
/// forcing term): `max` at the first step, then `0.9 (|g_k| / |g_{k-1}|)²`, so loose while the
/// outer iteration converges slowly and tight once it converges fast; at most `max`, and
/// safeguarded against falling too quickly (while `0.9 η²` is above 0.1: with `max` 0.5).
pub(crate) struct Forcing {
    eta: f64,
    max: f64,
    last: Option<f64>,
}

impl Forcing {
    pub(crate) fn new(max: f64) -> Self {
        Forcing {
            eta: max,
            max,
            last: None,
        }
    }

    /// The tolerance for the step at gradient norm `g`.
    pub(crate) fn next(&mut self, g: f64) -> f64 {
        if let Some(prev) = self.last.filter(|p| *p > 0.0) {
            let mut eta = 0.9 * (g / prev).powi(2);
            let floor = 0.9 * self.eta * self.eta;
            if floor > 0.1 {
                eta = eta.max(floor);
            }
            self.eta = eta.min(self.max);
        }
        self.last = Some(g);
        self.eta
    }
}

/// The most curvature pairs a [`Curvature`] keeps (a run's Gauss-Newton steps each add up to
/// the CG iterations they took; the oldest are dropped).
const MEMORY: usize = 20;

/// The most numbers the pairs hold together (64 MB): fewer pairs for millions of parameters,
/// none (plain CG) past 4 million.
const MEMORY_FLOATS: usize = 8 << 20;

/// Curvature pairs `(p, JᵀJ p)` measured by the conjugate gradients of earlier steps (every
/// product CG computes is one), kept as a limited-memory BFGS approximation of `(JᵀJ + λI)⁻¹`
/// that preconditions the next solves (Morales and Nocedal, SIAM J. Optim. 10(4), 2000).
///
/// Why: the Gauss-Newton matrix changes little from one step to the next, so the directions
/// one solve explored are most of what the next needs, and its CG converges in a few
/// products instead of starting from nothing. Each product is a tangent and an adjoint pass
/// over the simulation, so this is the methods' cost. The pairs are stored without the
/// damping `λ`, which Levenberg-Marquardt changes between solves.
pub(crate) struct Curvature {
    pairs: VecDeque<Pair>,
    capacity: usize,
}

/// `(s, y = JᵀJ s)` and their products `sᵀy`, `sᵀs`, `yᵀy` (for any damping, `y + λ s`'s
/// follow without a pass over the vectors).
struct Pair {
    s: Vec<f64>,
    y: Vec<f64>,
    sy: f64,
    ss: f64,
    yy: f64,
}

impl Curvature {
    /// An empty memory for `n` parameters.
    pub(crate) fn new(n: usize) -> Self {
        Curvature {
            pairs: VecDeque::new(),
            capacity: (MEMORY_FLOATS / (2 * n.max(1))).min(MEMORY),
        }
    }

    /// Keeps `(s, JᵀJ s)` (without the damping), dropping the oldest pair when full. A pair
    /// of no clear positive curvature (`sᵀy <= 1e-12 |s| |y|`: a direction `JᵀJ` nearly
    /// annuls) or not finite is not kept, so the preconditioner stays finite and positive
    /// definite.
    pub(crate) fn push(&mut self, s: &[f64], y: &[f64]) {
        let (sy, ss, yy) = (dot(s, y), dot(s, s), dot(y, y));
        let kept = sy.is_finite() && ss.is_finite() && yy.is_finite();
        if self.capacity == 0 || !kept || sy <= 1e-12 * (ss * yy).sqrt() {
            return;
        }
        if self.pairs.len() == self.capacity {
            self.pairs.pop_front();
        }
        let (s, y) = (s.to_vec(), y.to_vec());
        self.pairs.push_back(Pair { s, y, sy, ss, yy });
    }

    /// `H r`, `H` the L-BFGS inverse of the pairs `(s, y + shift s)` (two-loop recursion,
    /// scaled by the newest pair); the identity while there are none. Every pair has
    /// `sᵀy > 0`, and `shift >= 0`, so `H` is symmetric positive definite.
    fn apply(&self, r: &[f64], shift: f64) -> Vec<f64> {
        // `rho = 1 / sᵀ(y + shift s)`; `(y + shift s)ᵀ q` without forming the vector.
        let rho: Vec<f64> = self
            .pairs
            .iter()
            .map(|p| 1.0 / (p.sy + shift * p.ss))
            .collect();
        let yq = |p: &Pair, q: &[f64]| dot(&p.y, q) + shift * dot(&p.s, q);
        let mut q = r.to_vec();
        let mut alpha = vec![0.0; self.pairs.len()];
        for (k, p) in self.pairs.iter().enumerate().rev() {
            alpha[k] = rho[k] * dot(&p.s, &q);
            for ((q, y), s) in q.iter_mut().zip(&p.y).zip(&p.s) {
                *q -= alpha[k] * (y + shift * s);
            }
        }
        if let Some(p) = self.pairs.back() {
            let sy = p.sy + shift * p.ss;
            let yy = p.yy + 2.0 * shift * p.sy + shift * shift * p.ss;
            for q in &mut q {
                *q *= sy / yy;
            }
        }
        for (k, p) in self.pairs.iter().enumerate() {
            let beta = rho[k] * yq(p, &q);
            for (q, s) in q.iter_mut().zip(&p.s) {
                *q += (alpha[k] - beta) * s;
            }
        }
        q
    }
}

/// Zeroes the components of `v` marked in `pinned` (parameters held at a bound).
pub(crate) fn zero_pinned(v: &mut [f64], pinned: Option<&[bool]>) {
    for (v, _) in v.iter_mut().zip(pinned.unwrap_or(&[])).filter(|(_, p)| **p) {
        *v = 0.0;
    }
}

/// Preconditioned conjugate gradients on `(A + shift I) d = -g`, `A v` given by `apply`
/// (symmetric positive semidefinite), preconditioned by `memory` and adding the products it
/// computes to it: at most `iters` iterations, to `|(A + shift I) d + g| <= tol |g|`; stops
/// early at a direction of non-positive curvature (keeping the iterate). Components marked in
/// `pinned` (parameters held at a bound) are left out: `d` is 0 there and the system is the
/// others' rows and columns. Returns `d` (`-g` if no iteration could run).
pub(crate) fn cg(
    g: &[f64],
    shift: f64,
    iters: usize,
    tol: f64,
    pinned: Option<&[bool]>,
    memory: &mut Curvature,
    apply: &mut Apply<'_>,
) -> Result<Vec<f64>, Error> {
    let n = g.len();
    let mask = |v: &mut [f64]| zero_pinned(v, pinned);
    let mut d = vec![0.0; n];
    let mut r: Vec<f64> = g.iter().map(|x| -x).collect();
    mask(&mut r);
    let steepest = r.clone();
    let stop = tol * tol * dot(&r, &r);
    // The preconditioner of this solve is the memory as it was before it (fixed, as PCG
    // needs): the solve's own products join it afterwards.
    let mut fresh: Vec<(Vec<f64>, Vec<f64>)> = Vec::new();
    let mut z = memory.apply(&r, shift);
    mask(&mut z);
    let mut rz = dot(&r, &z);
    // A preconditioner that does not give a finite, positive `rᵀz` (rounding in the pairs)
    // is dropped for this solve: plain CG.
    let plain = !(rz.is_finite() && rz > 0.0);
    if plain {
        z = r.clone();
        rz = dot(&r, &z);
    }
    let mut p = z.clone();
    for _ in 0..iters.max(1) {
        let mut ap = apply(&p)?;
        mask(&mut ap);
        if memory.capacity > 0 {
            if fresh.len() == memory.capacity {
                fresh.remove(0);
            }
            fresh.push((p.clone(), ap.clone()));
        }
        let ap: Vec<f64> = ap.iter().zip(&p).map(|(a, p)| a + shift * p).collect();
        let pap = dot(&p, &ap);
        if pap.is_nan() || pap <= 0.0 {
            break;
        }
        let alpha = rz / pap;
        for k in 0..n {
            d[k] += alpha * p[k];
            r[k] -= alpha * ap[k];
        }
        if dot(&r, &r) <= stop {
            break;
        }
        z = match plain {
            true => r.clone(),
            false => memory.apply(&r, shift),
        };
        mask(&mut z);
        let rz1 = dot(&r, &z);
        if !(rz1.is_finite() && rz1 > 0.0) {
            break;
        }
        let beta = rz1 / rz;
        rz = rz1;
        for k in 0..n {
            p[k] = z[k] + beta * p[k];
        }
    }
    for (s, y) in &fresh {
        memory.push(s, y);
    }
    if d.iter().all(|x| *x == 0.0) {
        d = steepest;
    }
    Ok(d)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A symmetric positive definite matrix with eigenvalues spread over four decades.
    fn matrix(n: usize, seed: f64) -> Vec<Vec<f64>> {
        let b: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| ((i * 7 + j * 3) as f64 * 0.37 + seed).sin())
                    .collect()
            })
            .collect();
        (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| {
                        let bb: f64 = (0..n).map(|k| b[k][i] * b[k][j]).sum();
                        bb + if i == j {
                            10f64.powf(4.0 * i as f64 / n as f64)
                        } else {
                            0.0
                        }
                    })
                    .collect()
            })
            .collect()
    }

    fn solve(
        a: &[Vec<f64>],
        g: &[f64],
        shift: f64,
        tol: f64,
        memory: &mut Curvature,
    ) -> (Vec<f64>, usize) {
        solve_in(a, g, shift, tol, 100, memory)
    }

    fn solve_in(
        a: &[Vec<f64>],
        g: &[f64],
        shift: f64,
        tol: f64,
        iters: usize,
        memory: &mut Curvature,
    ) -> (Vec<f64>, usize) {
        let mut products = 0;
        let d = cg(g, shift, iters, tol, None, memory, &mut |v| {
            products += 1;
            Ok(a.iter().map(|row| dot(row, v)).collect())
        })
        .unwrap();
        (d, products)
    }

    fn residual(a: &[Vec<f64>], g: &[f64], shift: f64, d: &[f64]) -> f64 {
        let r: Vec<f64> = a
            .iter()
            .zip(g)
            .zip(d)
            .map(|((row, g), di)| dot(row, d) + shift * di + g)
            .collect();
        dot(&r, &r).sqrt() / dot(g, g).sqrt()
    }

    /// A second solve with a nearby matrix (the next Gauss-Newton step), preconditioned by
    /// the first solve's products, reaches the same tolerance in a fraction of the products,
    /// with and without a changed damping; the solution meets the tolerance either way.
    #[test]
    fn earlier_products_precondition_the_next_solve() {
        let n = 20;
        let (a, next) = (matrix(n, 0.0), matrix(n, 0.05));
        let g: Vec<f64> = (0..n).map(|i| (i as f64 * 1.3).cos()).collect();
        let g2: Vec<f64> = (0..n).map(|i| (i as f64 * 0.7).sin()).collect();
        for shift in [0.0, 0.3] {
            let mut memory = Curvature::new(n);
            let (d, first) = solve(&a, &g, 0.0, 1e-8, &mut memory);
            assert!(residual(&a, &g, 0.0, &d) <= 1e-8);
            let (d, cold) = solve(&next, &g2, shift, 1e-8, &mut Curvature::new(n));
            assert!(residual(&next, &g2, shift, &d) <= 1e-8);
            let (d, warm) = solve(&next, &g2, shift, 1e-8, &mut memory);
            assert!(residual(&next, &g2, shift, &d) <= 1e-8);
            assert!(
                2 * warm <= cold,
                "shift {shift}: {warm} products preconditioned, {cold} without ({first} first)"
            );
        }
    }

    /// Levenberg-Marquardt's predicted decrease relies on `dᵀ(A + λI)d = -gᵀd` for CG's
    /// iterate: it holds at every exit (tolerance met, iterations spent), preconditioned or
    /// not, for a damping small or large beside the matrix's eigenvalues (1 to 1e4 and more),
    /// to the rounding of CG's conjugacy on a matrix of condition 1e4 (a few 1e-5 relative).
    #[test]
    fn every_iterate_meets_the_model_identity() {
        let n = 20;
        let (a, next) = (matrix(n, 0.0), matrix(n, 0.05));
        let g: Vec<f64> = (0..n).map(|i| (i as f64 * 1.3).cos()).collect();
        for shift in [0.0, 0.3, 1e3, 1e6] {
            for (tol, iters) in [(0.1, 100), (1e-8, 2), (1e-8, 100)] {
                for warm in [false, true] {
                    let mut memory = Curvature::new(n);
                    if warm {
                        solve(&a, &g, 0.0, 1e-8, &mut memory);
                    }
                    let (d, _) = solve_in(&next, &g, shift, tol, iters, &mut memory);
                    let ad: Vec<f64> = next.iter().map(|row| dot(row, &d)).collect();
                    let dad = dot(&d, &ad) + shift * dot(&d, &d);
                    let gd = dot(&g, &d);
                    assert!(
                        (dad + gd).abs() <= 1e-3 * gd.abs(),
                        "shift {shift}, tol {tol}, {iters} iterations, warm {warm}: \
                         dᵀ(A + λI)d = {dad:e}, gᵀd = {gd:e}"
                    );
                    if tol == 1e-8 && iters == 100 {
                        assert!(residual(&next, &g, shift, &d) <= 1e-8);
                    }
                }
            }
        }
    }

    /// Without pairs the preconditioner is the identity (plain CG); pairs of no positive
    /// curvature or not finite are not kept; millions of parameters keep fewer pairs, none
    /// past the memory's cap.
    #[test]
    fn the_memory_keeps_only_finite_positive_pairs_within_its_cap() {
        let r = [1.0, -2.0, 0.5];
        let mut m = Curvature::new(3);
        assert_eq!(m.apply(&r, 0.7), r.to_vec());
        m.push(&[1.0, 0.0, 0.0], &[-1.0, 0.0, 0.0]);
        m.push(&[1.0, 0.0, 0.0], &[0.0, 1.0, 0.0]);
        m.push(&[1.0, 0.0, 0.0], &[f64::NAN, 0.0, 0.0]);
        m.push(&[f64::INFINITY, 0.0, 0.0], &[1.0, 0.0, 0.0]);
        m.push(&[1e-300, 0.0, 0.0], &[1e-300, 0.0, 0.0]);
        assert_eq!(m.pairs.len(), 0);
        assert_eq!(m.apply(&r, 0.7), r.to_vec());
        m.push(&[1.0, 0.0, 0.0], &[2.0, 0.0, 0.0]);
        let z = m.apply(&r, 0.0);
        assert!(
            z.iter().all(|z| z.is_finite()) && dot(&z, &r) > 0.0,
            "{z:?}"
        );
        assert_eq!(Curvature::new(1_000_000).capacity, 4);
        assert_eq!(Curvature::new(10_000_000).capacity, 0);
        let mut big = Curvature::new(10_000_000);
        big.push(&[1.0], &[1.0]);
        assert!(big.pairs.is_empty());
    }
}
