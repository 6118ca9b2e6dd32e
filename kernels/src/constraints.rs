//! XPBD distance constraints with compliance (Macklin, Muller and Chentanez 2016), solved by
//! Jacobi iterations that write new arrays, so the whole solve is differentiable on a tape.
//!
//! One iteration for constraint `(i, j)` with `C = |x_i - x_j| - rest`, compliance `alpha`
//! (m/N) and `alpha~ = alpha / dt^2`: `dlambda = (-C - alpha~ lambda) / (w_i + w_j + alpha~)`,
//! `x_i += w_i n dlambda`, `x_j -= w_j n dlambda` (`n` the unit direction `i - j`); the
//! corrections of all constraints are summed per particle, then applied scaled by a
//! relaxation factor ([`DistanceConstraints::iterate`]) or, the stable default of
//! [`Xpbd`](crate::integrators::Xpbd), averaged: divided by the number of constraints touching
//! the particle, then scaled by the relaxation ([`DistanceConstraints::iterate_averaged`],
//! the averaging of Macklin et al. 2014, "Unified particle physics for real-time
//! applications", section 4.2). Summed Jacobi corrections overshoot by up to the number of
//! constraints per particle and diverge on cloth (8 per particle); averaged ones do not.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::particles::Elements;
use crate::scene_file::reader::{sub, Checker, SceneError};
use serde::Deserialize;

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

/// `x_out = x + dx * (relaxation * scale[t])`: the averaged Jacobi update, `scale[t]` the
/// inverse of the number of constraints touching particle `t` (1 if none).
#[diff_kernel]
pub fn apply_averaged_corrections<R: Real>(
    x: &Array<Vec3<R>>,
    dx: &Array<Vec3<R>>,
    scale: &Array<R>,
    relaxation: R,
    x_out: &Array<Vec3<R>>,
) {
    let t = tid();
    x_out[t] = x[t] + dx[t] * (relaxation * scale[t]);
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

    /// Per particle of `n`, the inverse of the number of constraints touching it (1 for a
    /// particle in none): the `scale` of [`DistanceConstraints::iterate_averaged`]. Not a
    /// gradient target (a count).
    pub fn inverse_counts(&self, n: usize) -> Array<R> {
        let mut count = vec![0usize; n];
        for [i, j] in self.pairs.to_vec() {
            count[i as usize] += 1;
            count[j as usize] += 1;
        }
        Array::from_vec(
            count
                .iter()
                .map(|&c| R::lit(1.0 / c.max(1) as f64))
                .collect(),
        )
        .named("xpbd_inverse_counts")
    }

    /// Records one averaged Jacobi iteration: each particle's summed correction divided by its
    /// number of constraints (`inverse_counts`, from [`DistanceConstraints::inverse_counts`]),
    /// times `relaxation` (1 by default; stable in (0, 2) as over-relaxation of the averaged
    /// update, 1 to 1.5 usual). Returns the corrected positions and the new multipliers.
    /// Launches [`solve_distance_constraints`] and [`apply_averaged_corrections`].
    #[allow(clippy::too_many_arguments)]
    pub fn iterate_averaged(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        inv_mass: &Array<R>,
        lambda: &Array<R>,
        dt: R,
        relaxation: R,
        inverse_counts: &Array<R>,
    ) -> (Array<Vec3<R>>, Array<R>) {
        let (dx, lambda_out) = self.corrections(tape, x, inv_mass, lambda, dt);
        let x_out = Array::zeros(x.len()).named("x");
        tape.launch(
            apply_averaged_corrections,
            x.len(),
            (x, &dx, inverse_counts, relaxation, &x_out),
        );
        (x_out, lambda_out)
    }

    /// The summed corrections and new multipliers of one Jacobi pass.
    fn corrections(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        inv_mass: &Array<R>,
        lambda: &Array<R>,
        dt: R,
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
        (dx, lambda_out)
    }

    /// The largest relative violation `|C| / rest` over the constraints at positions `x`
    /// (`|C|` for a rest length of 0; NaN if any is NaN).
    pub fn max_relative_violation(&self, x: &[Vec3<R>]) -> f64 {
        let rest = self.rest.to_vec();
        let mut worst = 0.0f64;
        for (k, [i, j]) in self.pairs.to_vec().into_iter().enumerate() {
            let d = x[i as usize] - x[j as usize];
            let len = (d.x * d.x + d.y * d.y + d.z * d.z).to_f64().sqrt();
            let r = rest[k].to_f64();
            let c = (len - r).abs() / if r > 0.0 { r } else { 1.0 };
            if c.is_nan() {
                return f64::NAN;
            }
            worst = worst.max(c);
        }
        worst
    }

    /// Records one Jacobi iteration with summed corrections: returns the corrected positions
    /// and the new multipliers. `relaxation` in (0, 1] damps the summed corrections; with many
    /// constraints per particle (cloth: 8) it must be well below 1 or the iteration diverges
    /// (prefer [`DistanceConstraints::iterate_averaged`]).
    pub fn iterate(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        inv_mass: &Array<R>,
        lambda: &Array<R>,
        dt: R,
        relaxation: R,
    ) -> (Array<Vec3<R>>, Array<R>) {
        let (dx, lambda_out) = self.corrections(tape, x, inv_mass, lambda, dt);
        let x_out = Array::zeros(x.len()).named("x");
        tape.launch(apply_corrections, x.len(), (x, &dx, relaxation, &x_out));
        (x_out, lambda_out)
    }
}

/// The distance constraints of a scene description (see
/// [`ModelBuilder::add_distance_constraint`](crate::ModelBuilder::add_distance_constraint)).
#[derive(Clone, Debug)]
pub(crate) struct ConstraintParts<R: Real> {
    pairs: Vec<[u32; 2]>,
    rest: Vec<R>,
    compliance: Vec<R>,
}

impl<R: Real> Default for ConstraintParts<R> {
    fn default() -> Self {
        ConstraintParts {
            pairs: Vec::new(),
            rest: Vec::new(),
            compliance: Vec::new(),
        }
    }
}

impl<R: Real> ConstraintParts<R> {
    /// A constraint at the particles' current distance, checked.
    pub(crate) fn add(&mut self, el: &mut Elements<'_, R>, i: u32, j: u32, compliance: R) -> u32 {
        let k = self.pairs.len();
        let rest = if el.distinct("distance_constraints", k, &[i, j]) {
            let d = el.particles.x[i as usize] - el.particles.x[j as usize];
            el.rest("distance_constraints", k, [i, j], d.norm(), true);
            d.norm()
        } else {
            R::lit(1.0)
        };
        el.check("distance_constraints", k)
            .nonneg("compliance", compliance);
        self.pairs.push([i, j]);
        self.rest.push(rest);
        self.compliance.push(compliance);
        (self.pairs.len() - 1) as u32
    }

    /// The first constraint whose particles are in different worlds.
    pub(crate) fn spanning_worlds(&self, world_of: &[u32]) -> Option<(usize, Vec<u32>)> {
        crate::forces::component::first_spanning(&self.pairs, world_of)
    }

    /// Appends `other`'s constraints as a new world's (particle indices shifted by `offset`).
    pub(crate) fn append(&mut self, other: &Self, offset: u32) {
        self.pairs
            .extend(crate::forces::component::shifted(&other.pairs, offset));
        self.rest.extend(&other.rest);
        self.compliance.extend(&other.compliance);
    }

    /// The constraints among the particles `range` (one share of the worlds), indices shifted
    /// down by `range.start`.
    pub(crate) fn worlds_in(&self, range: &std::ops::Range<u32>) -> Self {
        use crate::forces::component::{elements_in, pick};
        let (idx, pairs) = elements_in(&self.pairs, range);
        ConstraintParts {
            pairs,
            rest: pick(&self.rest, &idx),
            compliance: pick(&self.compliance, &idx),
        }
    }

    /// The model's constraints, if the scene has any.
    pub(crate) fn build(&self) -> Option<DistanceConstraints<R>> {
        (!self.pairs.is_empty()).then(|| DistanceConstraints {
            pairs: Array::from_vec(self.pairs.clone()).named("dist_pairs"),
            rest: Array::from_vec(self.rest.clone()).named("dist_rest"),
            compliance: Array::from_vec(self.compliance.clone()).named("dist_compliance"),
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct DistanceDesc {
    i: u32,
    j: u32,
    #[serde(default)]
    compliance: f64,
}

/// Loads the `distance_constraints` section.
pub(crate) fn load<R: Real>(
    d: &[DistanceDesc],
    part: &mut ConstraintParts<R>,
    el: &mut Elements<'_, R>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, dc) in d.iter().enumerate() {
        let n0 = el.problems.len();
        part.add(el, dc.i, dc.j, R::lit(dc.compliance));
        c.builder(el.problems, n0, |f| {
            sub(&format!("distance_constraints[{k}]"), f, &["indices"])
        })?;
    }
    Ok(())
}
