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
/// outer iteration converges slowly and tight once it converges fast; safeguarded against
/// falling too quickly, and at most `max`.
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

/// The most numbers the pairs hold together (64 MB): fewer pairs for millions of parameters.
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
    pairs: VecDeque<(Vec<f64>, Vec<f64>)>,
    capacity: usize,
}

impl Curvature {
    /// An empty memory for `n` parameters.
    pub(crate) fn new(n: usize) -> Self {
        Curvature {
            pairs: VecDeque::new(),
            capacity: (MEMORY_FLOATS / (2 * n.max(1))).clamp(1, MEMORY),
        }
    }

    /// Keeps `(s, JᵀJ s)` (without the damping), dropping the oldest pair when full.
    pub(crate) fn push(&mut self, s: &[f64], y: &[f64]) {
        if self.pairs.len() == self.capacity {
            self.pairs.pop_front();
        }
        self.pairs.push_back((s.to_vec(), y.to_vec()));
    }

    /// `H r`, `H` the L-BFGS inverse of the pairs `(s, y + shift s)` (two-loop recursion,
    /// scaled by the newest pair); the identity while there are none. Pairs of no positive
    /// curvature are skipped, so `H` is symmetric positive definite.
    fn apply(&self, r: &[f64], shift: f64) -> Vec<f64> {
        let shifted = |s: &[f64], y: &[f64]| -> Vec<f64> {
            y.iter().zip(s).map(|(y, s)| y + shift * s).collect()
        };
        let used: Vec<(&[f64], Vec<f64>, f64)> = self
            .pairs
            .iter()
            .filter_map(|(s, y)| {
                let y = shifted(s, y);
                let sy = dot(s, &y);
                (sy > 0.0 && sy.is_finite()).then_some((s.as_slice(), y, 1.0 / sy))
            })
            .collect();
        let mut q = r.to_vec();
        let mut alpha = vec![0.0; used.len()];
        for (k, (s, y, rho)) in used.iter().enumerate().rev() {
            alpha[k] = rho * dot(s, &q);
            for (q, y) in q.iter_mut().zip(y) {
                *q -= alpha[k] * y;
            }
        }
        if let Some((s, y, _)) = used.last() {
            let gamma = dot(s, y) / dot(y, y);
            for q in &mut q {
                *q *= gamma;
            }
        }
        for (k, (s, y, rho)) in used.iter().enumerate() {
            let beta = rho * dot(y, &q);
            for (q, s) in q.iter_mut().zip(*s) {
                *q += (alpha[k] - beta) * s;
            }
        }
        q
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
    let mask = |v: &mut [f64]| {
        for (v, _) in v.iter_mut().zip(pinned.unwrap_or(&[])).filter(|(_, p)| **p) {
            *v = 0.0;
        }
    };
    let mut d = vec![0.0; n];
    let mut r: Vec<f64> = g.iter().map(|x| -x).collect();
    mask(&mut r);
    let steepest = r.clone();
    let stop = tol * tol * dot(&r, &r);
    // The preconditioner of this solve is the memory as it was before it (fixed, as PCG needs).
    let before = Curvature {
        pairs: memory.pairs.clone(),
        capacity: memory.capacity,
    };
    let mut z = before.apply(&r, shift);
    mask(&mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    for _ in 0..iters.max(1) {
        let mut ap = apply(&p)?;
        mask(&mut ap);
        memory.push(&p, &ap);
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
        z = before.apply(&r, shift);
        mask(&mut z);
        let rz1 = dot(&r, &z);
        let beta = rz1 / rz;
        rz = rz1;
        for k in 0..n {
            p[k] = z[k] + beta * p[k];
        }
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
        let mut products = 0;
        let d = cg(g, shift, 100, tol, None, memory, &mut |v| {
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

    /// Without pairs the preconditioner is the identity: plain CG, to the bit.
    #[test]
    fn an_empty_memory_is_plain_conjugate_gradients() {
        let r = [1.0, -2.0, 0.5];
        assert_eq!(Curvature::new(3).apply(&r, 0.7), r.to_vec());
        assert_eq!(Curvature::new(10_000_000).capacity, 1);
        assert_eq!(Curvature::new(1_000_000).capacity, 4);
    }
}
