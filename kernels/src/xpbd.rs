//! XPBD distance constraints with compliance (Macklin, Muller and Chentanez 2016), solved by
//! Jacobi iterations that write new arrays, so the whole solve is differentiable on a tape.
//!
//! One iteration for constraint `(i, j)` with `C = |x_i - x_j| - rest`, compliance `alpha`
//! (m/N) and `alpha~ = alpha / dt^2`: `dlambda = (-C - alpha~ lambda) / (w_i + w_j + alpha~)`,
//! `x_i += w_i n dlambda`, `x_j -= w_j n dlambda` (`n` the unit direction `i - j`); the
//! corrections of all constraints are summed, then applied scaled by a relaxation factor.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

/// One Jacobi pass over the constraints: reads positions `x` and multipliers `lambda`,
/// accumulates position corrections into `dx` and writes the new multipliers `lambda_out`.
/// A constraint between two particles of inverse mass 0 is left as is.
#[diff_kernel]
pub fn solve_distance_constraints<R: Real>(
    x: &Array<Vec3<R>>,
    inv_mass: &Array<R>,
    pairs: &Array<[u32; 2]>,
    rest: &Array<R>,
    compliance: &Array<R>,
    lambda: &Array<R>,
    dt: R,
    dx: &Array<Vec3<R>>,
    lambda_out: &Array<R>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let wi = inv_mass[i];
    let wj = inv_mass[j];
    let d = x[i] - x[j];
    let c = length(d) - rest[t];
    let n = normalize(d);
    let at = compliance[t] / (dt * dt);
    let denom = wi + wj + at;
    let lam = lambda[t];
    if denom <= 0.0 {
        lambda_out[t] = lam;
        return;
    }
    let dl = (0.0 - c - at * lam) / denom;
    lambda_out[t] = lam + dl;
    dx.atomic_add(i, n * (wi * dl));
    dx.atomic_sub(j, n * (wj * dl));
}

/// `x_out = x + dx * relaxation`.
#[diff_kernel]
pub fn apply_corrections<R: Real>(
    x: &Array<Vec3<R>>,
    dx: &Array<Vec3<R>>,
    relaxation: R,
    x_out: &Array<Vec3<R>>,
) {
    let t = tid();
    x_out[t] = x[t] + dx[t] * relaxation;
}

/// `v = (x - x_prev) / dt`: the velocity XPBD derives from the corrected positions.
#[diff_kernel]
pub fn velocity_from_positions<R: Real>(
    x_prev: &Array<Vec3<R>>,
    x: &Array<Vec3<R>>,
    dt: R,
    v: &Array<Vec3<R>>,
) {
    let t = tid();
    v[t] = (x[t] - x_prev[t]) / dt;
}

/// Elastic energy of the constraints, `C^2 / (2 alpha)` (J), added to `energy[0]`
/// (constraints of zero compliance are skipped).
#[diff_kernel]
pub fn distance_constraint_energy<R: Real>(
    x: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    rest: &Array<R>,
    compliance: &Array<R>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let c = length(x[i] - x[j]) - rest[t];
    let a = compliance[t];
    if a > 0.0 {
        energy.atomic_add(0, 0.5 * c * c / a);
    }
}

/// The distance constraints of a model.
#[derive(Clone, Debug)]
pub struct DistanceConstraints<R: Real> {
    /// Particle indices.
    pub pairs: Array<[u32; 2]>,
    /// Rest distance (m).
    pub rest: Array<R>,
    /// Compliance (m/N; 0 = rigid), the inverse of a stiffness.
    pub compliance: Array<R>,
}

impl<R: Real> DistanceConstraints<R> {
    /// Number of constraints.
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// Zero multipliers, one per constraint (start of a substep).
    pub fn zero_lambda(&self) -> Array<R> {
        Array::zeros(self.len()).named("xpbd_lambda")
    }

    /// Records one Jacobi iteration: returns the corrected positions and the new multipliers.
    /// `relaxation` in (0, 1] damps the summed corrections (0.5 to 1 is usual for Jacobi).
    pub fn iterate(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        inv_mass: &Array<R>,
        lambda: &Array<R>,
        dt: R,
        relaxation: R,
    ) -> (Array<Vec3<R>>, Array<R>) {
        let dx = Array::zeros(x.len()).named("xpbd_dx");
        let lambda_out = Array::zeros(self.len()).named("xpbd_lambda");
        tape.launch(
            solve_distance_constraints,
            self.len(),
            (
                x,
                inv_mass,
                &self.pairs,
                &self.rest,
                &self.compliance,
                lambda,
                dt,
                &dx,
                &lambda_out,
            ),
        );
        let x_out = Array::zeros(x.len()).named("x");
        tape.launch(apply_corrections, x.len(), (x, &dx, relaxation, &x_out));
        (x_out, lambda_out)
    }
}
