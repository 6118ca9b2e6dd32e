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

/// Stopping rule of the Krylov solvers.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SolveSettings {
    /// Converged when `|r| <= rel_tol |b| + abs_tol` (Euclidean norms; default `1e-10`).
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
    let n = b.len();
    assert_eq!(x.len(), n, "cg: x and b have different lengths");
    let precond = |r: &[f64], z: &mut [f64]| match inv_diag {
        Some(d) => z
            .iter_mut()
            .zip(r)
            .zip(d)
            .for_each(|((z, r), d)| *z = r * d),
        None => z.copy_from_slice(r),
    };
    let tol = s.rel_tol * norm(b) + s.abs_tol;
    let mut r = vec![0.0; n];
    let mut ap = vec![0.0; n];
    let mut iterations = 0;
    if x.iter().any(|&v| v != 0.0) {
        apply(x, &mut ap);
        iterations += 1;
        r.iter_mut()
            .zip(b)
            .zip(&ap)
            .for_each(|((r, b), a)| *r = b - a);
    } else {
        r.copy_from_slice(b);
    }
    let mut rn = norm(&r);
    let mut info = SolveInfo {
        iterations,
        residual: rn,
        tolerance: tol,
        converged: rn <= tol,
        negative_curvature: false,
    };
    if info.converged {
        return info;
    }
    let mut z = vec![0.0; n];
    precond(&r, &mut z);
    let mut p = z.clone();
    let mut rz = dot(&r, &z);
    for _ in 0..s.max_iter {
        apply(&p, &mut ap);
        info.iterations += 1;
        let pap = dot(&p, &ap);
        if pap.is_nan() || pap <= 0.0 {
            info.negative_curvature = true;
            break;
        }
        let alpha = rz / pap;
        x.iter_mut().zip(&p).for_each(|(x, p)| *x += alpha * p);
        r.iter_mut().zip(&ap).for_each(|(r, a)| *r -= alpha * a);
        rn = norm(&r);
        info.residual = rn;
        if rn <= tol {
            info.converged = true;
            break;
        }
        precond(&r, &mut z);
        let rz_new = dot(&r, &z);
        let beta = rz_new / rz;
        rz = rz_new;
        p.iter_mut().zip(&z).for_each(|(p, z)| *p = z + beta * *p);
    }
    info
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
    let n = b.len();
    assert_eq!(x.len(), n, "bicgstab: x and b have different lengths");
    let precond = |r: &[f64], z: &mut [f64]| match inv_diag {
        Some(d) => z
            .iter_mut()
            .zip(r)
            .zip(d)
            .for_each(|((z, r), d)| *z = r * d),
        None => z.copy_from_slice(r),
    };
    let tol = s.rel_tol * norm(b) + s.abs_tol;
    let mut info = SolveInfo {
        iterations: 0,
        residual: f64::INFINITY,
        tolerance: tol,
        converged: false,
        negative_curvature: false,
    };
    let mut r = vec![0.0; n];
    let mut tmp = vec![0.0; n];
    let (mut v, mut p, mut y, mut z, mut sv, mut t) = (
        vec![0.0; n],
        vec![0.0; n],
        vec![0.0; n],
        vec![0.0; n],
        vec![0.0; n],
        vec![0.0; n],
    );
    // Outer loop: (re)starts.
    while info.iterations < s.max_iter {
        apply(x, &mut tmp);
        info.iterations += 1;
        r.iter_mut()
            .zip(b)
            .zip(&tmp)
            .for_each(|((r, b), a)| *r = b - a);
        info.residual = norm(&r);
        if info.residual <= tol {
            info.converged = true;
            return info;
        }
        let r0 = r.clone();
        let (mut rho, mut alpha, mut omega) = (1.0, 1.0, 1.0);
        v.fill(0.0);
        p.fill(0.0);
        let mut restart = false;
        while info.iterations < s.max_iter {
            let rho_new = dot(&r0, &r);
            if rho_new.abs() < 1e-300 || omega == 0.0 {
                restart = true;
                break;
            }
            let beta = (rho_new / rho) * (alpha / omega);
            rho = rho_new;
            for k in 0..n {
                p[k] = r[k] + beta * (p[k] - omega * v[k]);
            }
            precond(&p, &mut y);
            apply(&y, &mut v);
            info.iterations += 1;
            let r0v = dot(&r0, &v);
            if r0v.abs() < 1e-300 {
                restart = true;
                break;
            }
            alpha = rho / r0v;
            for k in 0..n {
                sv[k] = r[k] - alpha * v[k];
            }
            if norm(&sv) <= tol {
                x.iter_mut().zip(&y).for_each(|(x, y)| *x += alpha * y);
                info.residual = norm(&sv);
                info.converged = true;
                return info;
            }
            precond(&sv, &mut z);
            apply(&z, &mut t);
            info.iterations += 1;
            let tt = dot(&t, &t);
            omega = if tt > 0.0 { dot(&t, &sv) / tt } else { 0.0 };
            for k in 0..n {
                x[k] += alpha * y[k] + omega * z[k];
                r[k] = sv[k] - omega * t[k];
            }
            info.residual = norm(&r);
            if info.residual <= tol {
                info.converged = true;
                return info;
            }
        }
        if !restart {
            break;
        }
    }
    info
}

/// Solves `A x = b` with [`cg`] first and, if CG meets negative curvature or does not
/// converge, with [`bicgstab`] from CG's iterate. Returns the info of the last solver run and
/// whether the fallback was used.
pub fn solve(
    mut apply: impl FnMut(&[f64], &mut [f64]),
    b: &[f64],
    x: &mut [f64],
    inv_diag: Option<&[f64]>,
    s: &SolveSettings,
) -> (SolveInfo, bool) {
    let info = cg(&mut apply, b, x, inv_diag, s);
    if info.converged {
        return (info, false);
    }
    let mut more = bicgstab(&mut apply, b, x, inv_diag, s);
    more.iterations += info.iterations;
    more.negative_curvature = info.negative_curvature;
    (more, true)
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
}
