//! The KKT system of one Gauss-Newton step, assembled sparse and factorized by faer's sparse
//! LU with partial pivoting.
//!
//! Unknowns `(s, d, λ)`: `s` the linearized residuals, `d = (dx, dp)` the step, `λ` the
//! constraint's multipliers:
//!
//! ```text
//! [ -I   J    0  ] [ s ]   [ -r ]
//! [ Jᵀ   0    Cᵀ ] [ d ] = [  0 ]
//! [  0   C    0  ] [ λ ]   [  0 ]
//! ```
//!
//! Eliminating `s = J d + r` leaves `Jᵀ J d + Cᵀ λ = -Jᵀ r`, `C d = 0`: the Gauss-Newton step
//! through the constraint. Keeping `s` leaves `J` as sparse as it is (`Jᵀ J` fills in where a
//! residual reads many unknowns).

use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};

use super::jacobian::Sparse;

/// Why the system has no solution.
pub(super) enum Failure {
    /// Singular to working precision.
    Singular,
    /// The factorization itself failed (memory, index overflow): faer's reason.
    Factorization(String),
}

/// The step `d` (state, then parameters) for the Jacobian `jc` (rows: the `nr` residuals,
/// then the `n` constraint equations; columns: the `n` state scalars, then the parameters) and
/// the residuals `r`. The system is equilibrated first (every row and column's largest entry
/// near 1, whatever the units); it is singular to working precision if its condition number
/// exceeds `1 / epsilon`.
pub(super) fn step(jc: &Sparse, nr: usize, r: &[f64], epsilon: f64) -> Result<Vec<f64>, Failure> {
    let k = jc.cols();
    let n = jc.rows - nr;
    let dim = nr + k + n;
    // The upper triangle's entries and their mirrors.
    let mut entries: Vec<(usize, usize, f64)> = (0..nr).map(|i| (i, i, -1.0)).collect();
    for j in 0..k {
        let (rows, vals) = jc.col(j);
        for (&i, &v) in rows.iter().zip(vals) {
            // J's entry (i, j) sits at (i, nr + j); C's (i - nr, j) at (nr + k + i - nr, nr + j).
            let row = if i < nr { i } else { k + i };
            entries.push((row, nr + j, v));
            entries.push((nr + j, row, v));
        }
    }
    let mut b = vec![0.0; dim];
    for (bi, ri) in b.iter_mut().zip(r) {
        *bi = -ri;
    }
    let scale = equilibrate(dim, &entries);
    let triplets: Vec<Triplet<usize, usize, f64>> = entries
        .iter()
        .map(|&(i, j, v)| Triplet::new(i, j, v * scale[i] * scale[j]))
        .collect();
    let a = SparseColMat::<usize, f64>::try_new_from_triplets(dim, dim, &triplets)
        .map_err(|e| Failure::Factorization(format!("{e:?}")))?;
    let lu = a.sp_lu().map_err(|e| match e {
        faer::sparse::linalg::LuError::SymbolicSingular { .. } => Failure::Singular,
        e => Failure::Factorization(format!("{e:?}")),
    })?;
    let solve = |rhs: &[f64]| -> Vec<f64> {
        let x = lu.solve(faer::Col::<f64>::from_fn(dim, |i| rhs[i]));
        (0..dim).map(|i| x[i]).collect()
    };
    let product = |x: &[f64]| -> Vec<f64> {
        let mut out = vec![0.0; dim];
        for t in &triplets {
            out[t.row] += t.val * x[t.col];
        }
        out
    };
    // (D A D) y = D b, one step of iterative refinement.
    let db: Vec<f64> = b.iter().zip(&scale).map(|(b, s)| b * s).collect();
    let mut y = solve(&db);
    let ay = product(&y);
    let residual: Vec<f64> = db.iter().zip(&ay).map(|(b, a)| b - a).collect();
    for (y, c) in y.iter_mut().zip(solve(&residual)) {
        *y += c;
    }
    if !y.iter().all(|v| v.is_finite()) || condition(dim, &product, &solve) * epsilon > 1.0 {
        return Err(Failure::Singular);
    }
    Ok((0..k).map(|j| y[nr + j] * scale[nr + j]).collect())
}

/// An estimate of the 2-norm condition number of the symmetric matrix whose product and
/// solve are given: a few steps of the power method on it and on its inverse, from a fixed
/// pseudo-random start (a singular matrix's inverse blows any start up).
fn condition(
    dim: usize,
    product: &dyn Fn(&[f64]) -> Vec<f64>,
    solve: &dyn Fn(&[f64]) -> Vec<f64>,
) -> f64 {
    let start: Vec<f64> = (0..dim)
        .map(|i| 1.0 + 0.5 * ((i as f64 * 0.618_033_988_75).fract() - 0.5))
        .collect();
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let power = |f: &dyn Fn(&[f64]) -> Vec<f64>| {
        let mut v = start.clone();
        let mut grow = 0.0;
        for _ in 0..3 {
            let size = norm(&v);
            if !(size > 0.0 && size.is_finite()) {
                return f64::INFINITY;
            }
            v.iter_mut().for_each(|x| *x /= size);
            v = f(&v);
            grow = norm(&v);
        }
        if grow.is_finite() {
            grow
        } else {
            f64::INFINITY
        }
    };
    power(product) * power(solve)
}

/// Ruiz's symmetric equilibration of the symmetric matrix of `entries` (both triangles): the
/// scales `D` such that every row and column of `D A D` has its largest magnitude within 10%
/// of 1 (a zero row keeps scale 1), after at most 20 sweeps.
fn equilibrate(dim: usize, entries: &[(usize, usize, f64)]) -> Vec<f64> {
    let mut d = vec![1.0; dim];
    for _ in 0..20 {
        let mut largest = vec![0.0f64; dim];
        for &(i, j, v) in entries {
            largest[i] = largest[i].max((d[i] * v * d[j]).abs());
        }
        let mut balanced = true;
        for (di, &r) in d.iter_mut().zip(&largest) {
            if r > 0.0 {
                *di /= r.sqrt();
                balanced &= (r - 1.0).abs() <= 0.1;
            }
        }
        if balanced {
            break;
        }
    }
    d
}
