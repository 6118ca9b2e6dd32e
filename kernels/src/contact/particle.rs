//! Particle-particle contact: a uniform-grid broad phase on the host finds the pairs closer
//! than two radii, then a kernel applies a penalty force with smoothed friction to each pair.
//!
//! The broad phase is not differentiated (which pairs touch is piecewise constant in the
//! positions); it is recomputed from the current positions at every evaluation, so a
//! checkpointed segment replays it identically.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::forces::{Force, ForceContext, Param};

use super::ground::{contact_depth, contact_force};

/// Contact force of pair `tid = (i, j)` of particles of radius `radius` (m): with
/// `n = normalize(x_i - x_j)` and `c = contact_depth(|x_i - x_j| - 2 radius, leak)`, particle
/// `i` gets `contact_force(n, c, v_i - v_j, ke, kd [c < 0], mu)`, particle `j` the opposite.
/// Unlike the ground's, the damping acts only in contact.
#[diff_kernel]
pub fn eval_particle_contact<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    radius: R,
    ke: R,
    kd: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let xij = x[i] - x[j];
    let n = normalize(xij);
    let c = contact_depth(length(xij) - 2.0 * radius, leak);
    let kdc = select(c < 0.0, kd, 0.0);
    let fc = contact_force(n, c, v[i] - v[j], ke, kdc, mu);
    f.atomic_add(i, fc);
    f.atomic_sub(j, fc);
}

/// Particle-particle contact parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParticleContact<R: Real> {
    /// Contact stiffness (N/m).
    pub ke: R,
    /// Contact damping (N s/m).
    pub kd: R,
    /// Friction coefficient.
    pub mu: R,
    /// Gradient leak out of contact (see [`contact_depth`]); 0 = exact.
    pub leak: R,
    /// Extra distance (m) within which the broad phase reports pairs (0: exactly those closer
    /// than two radii; a positive margin lets a leaky gradient see near misses).
    pub margin: R,
}

/// `ke = 1000` N/m, `kd = 1` N s/m, `mu = 0.5`, `leak = 0` (exact gradients), `margin = 0` m
/// (the scene file's defaults are these).
impl<R: Real> Default for ParticleContact<R> {
    fn default() -> Self {
        ParticleContact {
            ke: R::lit(1000.0),
            kd: R::lit(1.0),
            mu: R::lit(0.5),
            leak: R::lit(0.0),
            margin: R::lit(0.0),
        }
    }
}

impl<R: Real> ParticleContact<R> {
    /// The builder's checks: `ke`, `kd`, `mu`, `leak`, `margin` finite and `>= 0`.
    pub(crate) fn check(&self, c: &mut crate::validation::Check) {
        for (p, v) in [
            ("ke", self.ke),
            ("kd", self.kd),
            ("mu", self.mu),
            ("leak", self.leak),
            ("margin", self.margin),
        ] {
            c.nonneg(p, v);
        }
    }
}

impl<R: Real> ParticleContact<R> {
    /// Finds the pairs and records [`eval_particle_contact`] on them, accumulating into `f`.
    /// Returns the number of pairs.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radius: R,
        f: &Array<Vec3<R>>,
    ) -> usize {
        let pairs = find_pairs(&x.to_vec(), radius + radius + self.margin);
        if pairs.is_empty() {
            return 0;
        }
        let n = pairs.len();
        let pairs = Array::from_vec(pairs).named("contact_pairs");
        tape.launch(
            eval_particle_contact,
            n,
            (
                x, v, &pairs, radius, self.ke, self.kd, self.mu, self.leak, f,
            ),
        );
        n
    }
}

/// The pairs `(i, j)`, `i < j`, of points closer than `cutoff` (m), sorted, by a uniform grid
/// of cell size `cutoff`: each point is compared only with the points of its 27 neighbouring
/// cells. O(n log n) for bounded density. Non-finite points are ignored.
pub fn find_pairs<R: Real>(x: &[Vec3<R>], cutoff: R) -> Vec<[u32; 2]> {
    let h = cutoff.to_f64();
    if h.is_nan() || h <= 0.0 || x.len() < 2 {
        return Vec::new();
    }
    let cell = |p: &Vec3<R>| -> Option<[i64; 3]> {
        let c = [p.x, p.y, p.z].map(|v| (v.to_f64() / h).floor());
        c.iter()
            .all(|v| v.is_finite() && v.abs() < 1e15)
            .then(|| c.map(|v| v as i64))
    };
    // Points sorted by cell (then index): each cell is a contiguous run.
    let mut sorted: Vec<([i64; 3], u32)> = x
        .iter()
        .enumerate()
        .filter_map(|(i, p)| Some((cell(p)?, i as u32)))
        .collect();
    sorted.sort_unstable();
    let h2 = h * h;
    let mut pairs = Vec::new();
    for &(c, i) in &sorted {
        let pi = x[i as usize];
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let key = [c[0] + dx, c[1] + dy, c[2] + dz];
                    let start = sorted.partition_point(|(k, _)| *k < key);
                    for &(k, j) in &sorted[start..] {
                        if k != key {
                            break;
                        }
                        if j <= i {
                            continue;
                        }
                        let d = pi - x[j as usize];
                        let d2 = d.x.to_f64().powi(2) + d.y.to_f64().powi(2) + d.z.to_f64().powi(2);
                        if d2 < h2 {
                            pairs.push([i, j]);
                        }
                    }
                }
            }
        }
    }
    pairs.sort_unstable();
    pairs
}

/// Particle-particle contact. Its parameters are scalars (not differentiable), so it has no
/// parameter arrays.
impl<R: Real> Force<R> for ParticleContact<R> {
    fn name(&self) -> &'static str {
        crate::forces::PARTICLE_CONTACT
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        ParticleContact::eval(self, tape, cx.x, cx.v, cx.particle_radius, f);
    }
    fn params_mut(&mut self, _visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {}
}
