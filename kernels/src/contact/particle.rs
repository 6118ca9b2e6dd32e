//! Particle-particle contact: a uniform-grid broad phase on the host finds the pairs closer
//! than two radii, then a kernel applies a penalty force with smoothed friction to each pair.
//!
//! The broad phase is not differentiated (which pairs touch is piecewise constant in the
//! positions); it is recomputed from the current positions at every evaluation, so a
//! checkpointed segment replays it identically.

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

use crate::forces::component::{Force, ForceContext, Param, ParamDoc};
use crate::particles::check_one;
use crate::scene_file::reader::{sub, Checker, SceneError};
use crate::validation::Problem;
use serde::Deserialize;

use super::law::{contact_damping, contact_depth, contact_force, penalty_energy};

/// The force's name ([`Force::name`]): `"particle_contact"`.
pub const NAME: &str = "particle_contact";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::scalar("ke", "N/m"),
    ParamDoc::scalar("kd", "N·s/m"),
    ParamDoc::scalar("damping_depth", "m"),
    ParamDoc::scalar("mu", "1 (friction coefficient)"),
    ParamDoc::scalar("leak", "1 (gradient leak out of contact)"),
    ParamDoc::scalar("margin", "m"),
];

/// The contact force (N) on particle `i` of a pair at `xij = x_i - x_j`, `vij = v_i - v_j`,
/// whose surfaces are `gap` apart (m; negative in contact): what both pair kernels compute.
/// The damping `kd` ramps in over the first `depth` metres of penetration
/// ([`contact_damping`]; `depth = 0`: a switch at contact).
#[diff_func]
#[allow(clippy::too_many_arguments)]
pub fn pair_contact_force<R: Real>(
    xij: Vec3<R>,
    vij: Vec3<R>,
    gap: R,
    ke: R,
    kd: R,
    depth: R,
    mu: R,
    leak: R,
) -> Vec3<R> {
    let n = normalize(xij);
    let c = contact_depth(gap, leak);
    // The ramp sees the true depth (no leaky slope through it), as the ground's does.
    let kdc = contact_damping(min(gap, 0.0), kd, 0.0, depth);
    contact_force(n, c, vij, ke, kdc, mu)
}

/// Contact force of pair `tid = (i, j)` of particles of radius `radius` (m): with
/// `n = normalize(x_i - x_j)` and `c = contact_depth(|x_i - x_j| - 2 radius, leak)`, particle
/// `i` gets `contact_force(n, c, v_i - v_j, ke, contact_damping(c, kd, 0, depth), mu)`,
/// particle `j` the opposite: the damping acts only in contact, ramped in over `depth` (m).
#[diff_kernel]
pub fn eval_particle_contact<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    radius: R,
    ke: R,
    kd: R,
    depth: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let xij = x[i] - x[j];
    let fc = pair_contact_force(
        xij,
        v[i] - v[j],
        length(xij) - 2.0 * radius,
        ke,
        kd,
        depth,
        mu,
        leak,
    );
    f.atomic_add(i, fc);
    f.atomic_sub(j, fc);
}

/// [`eval_particle_contact`] with a radius per particle: the pair touches at
/// `radius[i] + radius[j]` (m).
#[diff_kernel]
pub fn eval_particle_contact_radii<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    radius: &Array<R>,
    ke: R,
    kd: R,
    depth: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let xij = x[i] - x[j];
    let fc = pair_contact_force(
        xij,
        v[i] - v[j],
        length(xij) - radius[i] - radius[j],
        ke,
        kd,
        depth,
        mu,
        leak,
    );
    f.atomic_add(i, fc);
    f.atomic_sub(j, fc);
}

/// Penalty energy of pair `tid = (i, j)` of [`eval_particle_contact`]:
/// `penalty_energy(|x_i - x_j| - 2 radius, ke)` (J), added to its world's `energy[world[i]]`.
#[diff_kernel]
pub fn particle_contact_energy<R: Real>(
    x: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    radius: R,
    ke: R,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    energy.atomic_add(
        world[i] as usize,
        penalty_energy(length(x[i] - x[j]) - 2.0 * radius, ke),
    );
}

/// [`particle_contact_energy`] with a radius per particle: the pair touches at
/// `radius[i] + radius[j]` (m).
#[diff_kernel]
pub fn particle_contact_energy_radii<R: Real>(
    x: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    radius: &Array<R>,
    ke: R,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    energy.atomic_add(
        world[i] as usize,
        penalty_energy(length(x[i] - x[j]) - radius[i] - radius[j], ke),
    );
}

/// Particle-particle contact parameters (also those of particles against shapes,
/// [`crate::ModelBuilder::set_shape_contact`], which ignores `margin`).
///
/// For a coefficient of restitution see [`ParticleContact::with_restitution`]; for gradients
/// that see contacts before they begin, [`ParticleContact::leaky`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ParticleContact<R: Real> {
    /// Contact stiffness (N/m; default 1000).
    pub ke: R,
    /// Contact damping (N s/m; default 1), acting only in contact and only while the
    /// particles approach, ramped in over [`ParticleContact::damping_depth`].
    pub kd: R,
    /// The penetration depth (m; default 1e-4) over which the damping rises from 0 to `kd`
    /// ([`contact_damping`]), so that the contact force has no jump (implicit Euler's Newton
    /// cannot converge through one); 0 switches it on at contact.
    pub damping_depth: R,
    /// Friction coefficient (dimensionless; default 0.5).
    pub mu: R,
    /// Gradient leak out of contact (dimensionless, see [`contact_depth`]; default 0: exact
    /// gradients).
    pub leak: R,
    /// Extra distance (m; default 0) within which the broad phase reports pairs (0: exactly
    /// those closer than the sum of their radii; a positive margin lets a leaky gradient see
    /// near misses).
    pub margin: R,
}

/// `ke = 1000` N/m, `kd = 1` N s/m, `damping_depth = 1e-4` m, `mu = 0.5`, `leak = 0` (exact
/// gradients), `margin = 0` m (the scene file's defaults are these).
impl<R: Real> Default for ParticleContact<R> {
    fn default() -> Self {
        ParticleContact {
            ke: R::lit(1000.0),
            kd: R::lit(1.0),
            damping_depth: R::lit(1e-4),
            mu: R::lit(0.5),
            leak: R::lit(0.0),
            margin: R::lit(0.0),
        }
    }
}

impl<R: Real> ParticleContact<R> {
    /// The damping `kd` (N s/m) that gives a head-on contact of stiffness `ke` (N/m) between
    /// bodies of effective mass `m_eff` (kg) the coefficient of restitution `e` (ratio of the
    /// separation to the approach speed, `0 < e <= 1`): `kd = 2 zeta sqrt(ke m_eff)` with
    /// `zeta` = [`restitution_damping_ratio`]`(e)`. For two particles of masses `m_i`, `m_j`,
    /// `m_eff = m_i m_j / (m_i + m_j)` (`m / 2` for equal masses); for a particle against a
    /// static shape, `m_eff = m`. `e = 1` gives `kd = 0` (no loss; the integrator's own error
    /// remains: semi-implicit Euler gains a little energy per contact at large `dt`).
    ///
    /// The relation is exact for the contact of [`eval_particle_contact`] and
    /// [`crate::contact::shapes::eval_shape_contact`] in the limit of a small time step (and of
    /// a [`ParticleContact::damping_depth`] small against the penetration): their
    /// damping acts only in contact *and only while the particles approach*
    /// (`min(v.n, 0) kd`), so only the compression half of the contact is damped. The textbook
    /// linear spring-dashpot relation (`zeta = -ln e / sqrt(pi^2 + ln^2 e)`, damping in both
    /// halves) would give a restitution far above `e` here (0.74 for `e = 0.5`). It is not valid
    /// for the ground, whose damping also brakes a particle approaching it out of contact (see
    /// [`crate::contact::ground::Ground`]). Friction and a leak do not enter (head-on).
    ///
    /// Panics unless `ke > 0`, `m_eff > 0` and `0 < e <= 1` (all finite).
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// let kd = ParticleContact::<f64>::restitution_damping(1.0e4, 0.5, 0.5);
    /// let c = ParticleContact::<f64> { ke: 1.0e4, kd, ..ParticleContact::default() };
    /// assert!((c.restitution(0.5) - 0.5).abs() < 1e-12);
    /// assert_eq!(ParticleContact::<f64>::restitution_damping(1.0e4, 1.0, 0.5), 0.0);
    /// ```
    pub fn restitution_damping(ke: R, e: R, m_eff: R) -> R {
        let (k, m) = (ke.to_f64(), m_eff.to_f64());
        assert!(
            k.is_finite() && k > 0.0 && m.is_finite() && m > 0.0,
            "restitution_damping: ke ({k}) and m_eff ({m}) must be finite and > 0"
        );
        let zeta = restitution_damping_ratio(e.to_f64());
        R::lit(2.0 * zeta * (k * m).sqrt())
    }

    /// This contact with `kd` set by [`ParticleContact::restitution_damping`]`(self.ke, e,
    /// m_eff)`: restitution `e` for bodies of effective mass `m_eff` (kg).
    pub fn with_restitution(self, e: R, m_eff: R) -> Self {
        ParticleContact {
            kd: Self::restitution_damping(self.ke, e, m_eff),
            ..self
        }
    }

    /// The coefficient of restitution of a head-on contact between bodies of effective mass
    /// `m_eff` (kg) with this `ke` and `kd` (small-time-step limit; the inverse of
    /// [`ParticleContact::restitution_damping`]).
    pub fn restitution(&self, m_eff: R) -> R {
        let zeta = self.kd.to_f64() / (2.0 * (self.ke.to_f64() * m_eff.to_f64()).sqrt());
        R::lit(restitution_of_damping_ratio(zeta))
    }

    /// This contact with a leaky gradient tuned to a scene: `margin = 0.1 radius` (near
    /// misses closer than a tenth of the radius are seen) and `leak = m_eff / (ke horizon^2)`,
    /// so that the fictitious stiffness `leak ke` the adjoint gives every pair within the
    /// margin has `omega horizon = 1` over the rollout's duration `horizon` (s): it points the
    /// gradient towards contacts that have not begun without swamping the true derivative.
    /// `radius` (m) is the particles' radius, `m_eff` (kg) the effective mass of a pair (see
    /// [`ParticleContact::restitution_damping`]).
    ///
    /// The gradient is then biased (it is not the derivative of the simulation): on the
    /// billiards scene of `kernels/tests/contact_leak.rs` (rack of 6 balls of 57 mm, 0.17 kg,
    /// `ke = 1e5` N/m, 0.25 s) this preset (`leak = 1.4e-5`, `margin = 2.9` mm) keeps the
    /// sign of the derivative of a final position with respect to the cue velocity, with a
    /// relative error of about 0.2%, where `leak = 1e-3`, `margin = 5` mm errs by 24% and
    /// `leak = 1e-2`, `margin = 5` cm flips its sign. Gradient checks must use `leak = 0`
    /// (the default).
    pub fn leaky(self, radius: R, m_eff: R, horizon: R) -> Self {
        let (k, t) = (self.ke.to_f64(), horizon.to_f64());
        ParticleContact {
            leak: R::lit(m_eff.to_f64() / (k * t * t)),
            margin: R::lit(0.1 * radius.to_f64()),
            ..self
        }
    }

    /// The builder's checks: `ke`, `kd`, `damping_depth`, `mu`, `leak`, `margin` finite and
    /// `>= 0`.
    pub(crate) fn check(&self, c: &mut crate::validation::Check) {
        for (p, v) in [
            ("ke", self.ke),
            ("kd", self.kd),
            ("damping_depth", self.damping_depth),
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
        self.eval_in_worlds(tape, x, v, radius, None, f)
    }

    /// [`ParticleContact::eval`] on the pairs of particles of one world (`world[i]`: particle
    /// `i`'s; `None`: all one world).
    pub fn eval_in_worlds(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radius: R,
        world: Option<&Array<u32>>,
        f: &Array<Vec3<R>>,
    ) -> usize {
        let pairs = self.pairs(x, radius, world);
        if pairs.is_empty() {
            return 0;
        }
        let n = pairs.len();
        let pairs = Array::from_vec(pairs).named("contact_pairs");
        tape.launch(
            eval_particle_contact,
            n,
            (
                x,
                v,
                &pairs,
                radius,
                self.ke,
                self.kd,
                self.damping_depth,
                self.mu,
                self.leak,
                f,
            ),
        );
        n
    }
}

/// The coefficient of restitution of a linear contact spring whose dashpot (damping ratio
/// `zeta = kd / (2 sqrt(ke m_eff))`) acts only while the bodies approach: the compression half
/// ends at `x_max = v0 / omega exp(-zeta g(zeta))`, and the undamped rebound gives back
/// `omega x_max`, so `e = exp(-zeta g(zeta))` with `g = acos(zeta) / sqrt(1 - zeta^2)`
/// (`zeta < 1`), 1 (`zeta = 1`, critical damping: `e = exp(-1) = 0.368`), `acosh(zeta) / sqrt(zeta^2 - 1)`
/// (`zeta > 1`). Decreasing from 1 (`zeta = 0`) towards 0 (`zeta -> inf`).
pub fn restitution_of_damping_ratio(zeta: f64) -> f64 {
    if zeta.is_nan() || zeta < 0.0 {
        return f64::NAN;
    }
    let g = if (zeta - 1.0).abs() < 1e-6 {
        1.0 - (zeta - 1.0) / 3.0
    } else if zeta < 1.0 {
        zeta.acos() / (1.0 - zeta * zeta).sqrt()
    } else {
        // `zeta sqrt(1 - 1/zeta^2)`, not `sqrt(zeta^2 - 1)`, which overflows past 1e154.
        zeta.acosh() / (zeta * (1.0 - 1.0 / (zeta * zeta)).sqrt())
    };
    (-zeta * g).exp()
}

/// The damping ratio `zeta` whose one-sided dashpot gives restitution `e` (the inverse of
/// [`restitution_of_damping_ratio`], by bisection to machine precision): 0 for `e = 1`,
/// 0.597 for `e = 0.5`, 0.070 for `e = 0.9`, 1 for `e = exp(-1)`. Panics unless `0 < e <= 1`.
pub fn restitution_damping_ratio(e: f64) -> f64 {
    assert!(
        e > 0.0 && e <= 1.0,
        "the coefficient of restitution must be in (0, 1] (got {e})"
    );
    if e == 1.0 {
        return 0.0;
    }
    let mut hi = 1.0;
    while restitution_of_damping_ratio(hi) > e {
        hi *= 2.0;
        // e(zeta) ~ 1/(2 zeta): every e > 0 in f64 has a finite zeta.
        assert!(hi.is_finite(), "no damping ratio gives restitution {e}");
    }
    let mut lo = 0.0;
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if restitution_of_damping_ratio(mid) > e {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

impl<R: Real> ParticleContact<R> {
    /// [`ParticleContact::eval`] with a radius per particle (m): the broad phase's cells are
    /// `2 max(radii) + margin` wide, and it keeps the pairs closer than
    /// `radii[i] + radii[j] + margin`; records [`eval_particle_contact_radii`] on them.
    /// Returns the number of pairs.
    pub fn eval_radii(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radii: &Array<R>,
        f: &Array<Vec3<R>>,
    ) -> usize {
        self.eval_radii_in_worlds(tape, x, v, radii, None, f)
    }

    /// [`ParticleContact::eval_radii`] on the pairs of particles of one world (see
    /// [`ParticleContact::eval_in_worlds`]).
    pub fn eval_radii_in_worlds(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radii: &Array<R>,
        world: Option<&Array<u32>>,
        f: &Array<Vec3<R>>,
    ) -> usize {
        let pairs = self.pairs_radii(x, radii, world);
        if pairs.is_empty() {
            return 0;
        }
        let n = pairs.len();
        let pairs = Array::from_vec(pairs).named("contact_pairs");
        tape.launch(
            eval_particle_contact_radii,
            n,
            (
                x,
                v,
                &pairs,
                radii,
                self.ke,
                self.kd,
                self.damping_depth,
                self.mu,
                self.leak,
                f,
            ),
        );
        n
    }
}

impl<R: Real> ParticleContact<R> {
    /// The broad phase of [`ParticleContact::eval`]: pairs of one world closer than
    /// `2 radius + margin`.
    fn pairs(&self, x: &Array<Vec3<R>>, radius: R, world: Option<&Array<u32>>) -> Vec<[u32; 2]> {
        let world = world.map(|w| w.to_vec());
        find_pairs_in_worlds(&x.to_vec(), world.as_deref(), radius + radius + self.margin)
    }

    /// The broad phase of [`ParticleContact::eval_radii`].
    fn pairs_radii(
        &self,
        x: &Array<Vec3<R>>,
        radii: &Array<R>,
        world: Option<&Array<u32>>,
    ) -> Vec<[u32; 2]> {
        let r = radii.to_vec();
        let xs = x.to_vec();
        let rmax = r.iter().map(|r| r.to_f64()).fold(0.0, f64::max);
        let margin = self.margin.to_f64();
        let world = world.map(|w| w.to_vec());
        find_pairs_in_worlds(&xs, world.as_deref(), R::lit(2.0 * rmax + margin))
            .into_iter()
            .filter(|&[i, j]| {
                let (i, j) = (i as usize, j as usize);
                let d = xs[i] - xs[j];
                let d2: f64 = d.iter().map(|c| c.to_f64().powi(2)).sum();
                let cut = r[i].to_f64() + r[j].to_f64() + margin;
                d2 < cut * cut
            })
            .collect()
    }
}

/// The pairs `(i, j)`, `i < j`, of points closer than `cutoff` (m), sorted, by a uniform grid
/// of cell size `cutoff`: each point is compared only with the points of its 27 neighbouring
/// cells. O(n log n) for bounded density. Non-finite points are ignored.
pub fn find_pairs<R: Real>(x: &[Vec3<R>], cutoff: R) -> Vec<[u32; 2]> {
    find_pairs_in_worlds(x, None, cutoff)
}

/// [`find_pairs`] among the points of one world (`world[i]`: point `i`'s; `None`: all one
/// world): the grid's cells are per world, so worlds that overlap in space cost no more than
/// worlds apart, and a world's pairs are those it has alone, in the same order.
pub fn find_pairs_in_worlds<R: Real>(
    x: &[Vec3<R>],
    world: Option<&[u32]>,
    cutoff: R,
) -> Vec<[u32; 2]> {
    let h = cutoff.to_f64();
    if h.is_nan() || h <= 0.0 || x.len() < 2 {
        return Vec::new();
    }
    let cell = |i: usize, p: &Vec3<R>| -> Option<[i64; 4]> {
        let c = [p.x, p.y, p.z].map(|v| (v.to_f64() / h).floor());
        let w = world.map_or(0, |w| w[i] as i64);
        c.iter()
            .all(|v| v.is_finite() && v.abs() < 1e15)
            .then(|| [w, c[0] as i64, c[1] as i64, c[2] as i64])
    };
    // Points sorted by world and cell (then index): each cell is a contiguous run.
    let mut sorted: Vec<([i64; 4], u32)> = x
        .iter()
        .enumerate()
        .filter_map(|(i, p)| Some((cell(i, p)?, i as u32)))
        .collect();
    sorted.sort_unstable();
    let h2 = h * h;
    let mut pairs = Vec::new();
    for &(c, i) in &sorted {
        let pi = x[i as usize];
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    let key = [c[0], c[1] + dx, c[2] + dy, c[3] + dz];
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
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        let world = cx.particle_world;
        match cx.particle_radii {
            Some(r) => self.eval_radii_in_worlds(tape, cx.x, cx.v, r, world, f),
            None => self.eval_in_worlds(tape, cx.x, cx.v, cx.particle_radius, world, f),
        };
    }
    /// The penalty's potential on the pairs the broad phase finds at `cx.x`
    /// ([`particle_contact_energy`]); damping and friction have none.
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        let (x, ke) = (cx.x, self.ke);
        let pairs = match cx.particle_radii {
            Some(r) => self.pairs_radii(x, r, cx.particle_world),
            None => self.pairs(x, cx.particle_radius, cx.particle_world),
        };
        if !pairs.is_empty() {
            let n = pairs.len();
            let pairs = Array::from_vec(pairs).named("contact_pairs");
            let w = &cx.particle_worlds();
            match cx.particle_radii {
                Some(r) => tape.launch(
                    particle_contact_energy_radii,
                    n,
                    (x, &pairs, r, ke, w, energy),
                ),
                None => {
                    let r = cx.particle_radius;
                    tape.launch(particle_contact_energy, n, (x, &pairs, r, ke, w, energy))
                }
            }
        }
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(ParticleContact::<f64> {
            ke: self.ke.to_f64(),
            kd: self.kd.to_f64(),
            damping_depth: self.damping_depth.to_f64(),
            mu: self.mu.to_f64(),
            leak: self.leak.to_f64(),
            margin: self.margin.to_f64(),
        }))
    }

    fn params_mut(&mut self, _visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {}
}

// ---- its scene-file section ------------------------------------------------------------

// The defaults of `ParticleContact::default` (one source).
fn contact_ke() -> f64 {
    ParticleContact::<f64>::default().ke
}
fn contact_kd() -> f64 {
    ParticleContact::<f64>::default().kd
}
fn contact_mu() -> f64 {
    ParticleContact::<f64>::default().mu
}
fn contact_damping_depth() -> f64 {
    ParticleContact::<f64>::default().damping_depth
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ContactDesc {
    #[serde(default = "contact_ke")]
    ke: f64,
    #[serde(default = "contact_kd")]
    kd: f64,
    #[serde(default = "contact_damping_depth")]
    damping_depth: f64,
    #[serde(default = "contact_mu")]
    mu: f64,
    #[serde(default)]
    leak: f64,
    #[serde(default)]
    margin: f64,
}

impl ContactDesc {
    /// The contact parameters in `R`.
    pub(crate) fn to_contact<R: Real>(&self) -> ParticleContact<R> {
        ParticleContact {
            ke: R::lit(self.ke),
            kd: R::lit(self.kd),
            damping_depth: R::lit(self.damping_depth),
            mu: R::lit(self.mu),
            leak: R::lit(self.leak),
            margin: R::lit(self.margin),
        }
    }
}

/// Loads the `particle_contact` section.
pub(crate) fn load<R: Real>(
    cd: &ContactDesc,
    part: &mut Option<ParticleContact<R>>,
    problems: &mut Vec<Problem>,
    c: &Checker,
) -> Result<(), SceneError> {
    let n0 = problems.len();
    set(part, problems, cd.to_contact());
    c.builder(problems, n0, |f| sub("particle_contact", f, &[]))
}

/// Enables particle contact after its checks (the builder's `set_particle_contact` and the
/// loader).
pub(crate) fn set<R: Real>(
    part: &mut Option<ParticleContact<R>>,
    problems: &mut Vec<Problem>,
    contact: ParticleContact<R>,
) {
    contact.check(&mut check_one(problems, NAME));
    *part = Some(contact);
}
