//! The MPM builder, model and state.

use std::ops::Range;

use adflex_runtime::checkpoint::Checkpoint;
use adflex_runtime::prelude::*;
use adflex_runtime::AnyArray;

use super::dim::{Dim, D2, D3};
use super::kernels::{COROTATED, FLUID, NEO_HOOKEAN, SNOW};
use crate::validation::{ModelError, Problem};

/// The constitutive model of a particle, with its Lame parameters (Pa, in the model's units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Material {
    /// Fixed corotated elasticity (Stomakhin et al. 2012): robust to large rotations (and to
    /// inversion in 2D; a 3D particle that inverts makes the step fail); the model of
    /// DiffTaichi's `diffmpm`.
    Corotated {
        /// Shear modulus.
        mu: f64,
        /// Lame's first parameter.
        lambda: f64,
    },
    /// Compressible neo-Hookean elasticity; a particle that inverts (`det F <= 0`) makes the
    /// step fail (an error naming it).
    NeoHookean {
        /// Shear modulus.
        mu: f64,
        /// Lame's first parameter.
        lambda: f64,
    },
    /// A weakly compressible fluid: pressure from the volume change alone, `bulk (J - 1) J`
    /// in the Kirchhoff stress.
    Fluid {
        /// Bulk modulus.
        bulk: f64,
    },
    /// Snow (Stomakhin et al. 2013, as in Taichi's `mpm99`): fixed corotated elasticity
    /// whose deformation yields: each step the singular values of `F` are clamped to
    /// `[1 - compression, 1 + stretch]`, the excess becoming plastic deformation (its volume
    /// ratio `Jp` is in [`MpmState::jp`]), and the moduli harden as the snow is packed:
    /// `mu` and `lambda` times `exp(hardening (1 - Jp))`. [`Material::snow`] gives the
    /// usual values. `hardening = 0` is perfect plasticity (a clay-like material).
    Snow {
        /// Shear modulus (before hardening).
        mu: f64,
        /// Lame's first parameter (before hardening).
        lambda: f64,
        /// Critical compression `theta_c` (in `[0, 1)`; 2.5e-2 for snow).
        compression: f64,
        /// Critical stretch `theta_s` (`>= 0`; 4.5e-3 in `mpm99`, 7.5e-3 in the paper).
        stretch: f64,
        /// Hardening coefficient `xi` (`>= 0`; 10 for snow).
        hardening: f64,
    },
}

impl Material {
    /// Lame parameters from Young's modulus `e` and Poisson's ratio `nu` (`-1 < nu < 0.5`).
    pub fn lame(e: f64, nu: f64) -> (f64, f64) {
        (
            e / (2.0 * (1.0 + nu)),
            e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
        )
    }

    /// Snow with Young's modulus `e` and Poisson's ratio `nu`, and the plasticity of Taichi's
    /// `mpm99`: critical compression 2.5e-2, critical stretch 4.5e-3, hardening 10.
    pub fn snow(e: f64, nu: f64) -> Material {
        let (mu, lambda) = Material::lame(e, nu);
        Material::Snow {
            mu,
            lambda,
            compression: 2.5e-2,
            stretch: 4.5e-3,
            hardening: 10.0,
        }
    }

    fn params(&self) -> (u32, f64, f64) {
        match *self {
            Material::Corotated { mu, lambda } => (COROTATED, mu, lambda),
            Material::NeoHookean { mu, lambda } => (NEO_HOOKEAN, mu, lambda),
            Material::Fluid { bulk } => (FLUID, 0.0, bulk),
            Material::Snow { mu, lambda, .. } => (SNOW, mu, lambda),
        }
    }

    /// Critical compression, critical stretch and hardening (zeros: no plasticity).
    fn plasticity(&self) -> [f64; 3] {
        match *self {
            Material::Snow {
                compression,
                stretch,
                hardening,
                ..
            } => [compression, stretch, hardening],
            _ => [0.0; 3],
        }
    }

    /// The speed of the fastest wave at density `rho`: `sqrt((lambda + 2 mu) / rho)`.
    fn wave_speed(&self, rho: f64) -> f64 {
        let (_, mu, lambda) = self.params();
        ((lambda + 2.0 * mu) / rho).sqrt()
    }
}

/// What the floor does to the grid velocity of nodes within `bound` of it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Floor {
    /// A velocity into the floor is zeroed entirely (what DiffTaichi's `diffmpm` does).
    Sticky,
    /// The normal velocity into the floor is removed and the tangential one reduced by
    /// Coulomb friction with this coefficient (`>= 0`).
    Coulomb(f64),
}

/// Describes an MLS-MPM scene in 2D: the grid, its walls, gravity and the particles with
/// their materials and actuators. [`MpmBuilder::finalize`] checks it and returns an [`Mpm`].
///
/// The domain is `[0, n_grid dx]^D`; the `bound` nodes next to each low wall and the
/// `bound - 1` next to each high wall are wall nodes (DiffTaichi's convention; see
/// [`Floor`] and [`mpm_grid_update`](super::kernels::mpm_grid_update)); particles must start
/// at least `bound` cells away from the walls.
///
/// ```
/// use adflex_kernels::mpm::*;
/// use adflex_runtime::{Tape, Vec2};
///
/// // A jelly block dropped on the floor.
/// let mut b = MpmBuilder::new(32, 1.0 / 32.0);
/// b.add_rect(Vec2::new(0.3, 0.3), Vec2::new(0.2, 0.2), 1.0, 1.0,
///     Material::Corotated { mu: 10.0, lambda: 10.0 });
/// let mpm = b.finalize::<f64>().unwrap();
/// let mut tape = Tape::new();
/// let mut s = mpm.state();
/// for _ in 0..100 {
///     s = mpm.step(&mut tape, &s, None, 1e-3).unwrap();
/// }
/// assert!(s.x.get(0).y < 0.3 + 1.0 / 128.0); // it fell
/// ```
#[derive(Clone, Debug)]
pub struct MpmBuilder<D: Dim = D2> {
    n_grid: usize,
    dx: f64,
    bound: usize,
    floor: Floor,
    gravity: D::V<f64>,
    x: Vec<D::V<f64>>,
    v: Vec<D::V<f64>>,
    mass: Vec<f64>,
    volume: Vec<f64>,
    material: Vec<Material>,
    actuator: Vec<Option<Drive<D::V<f64>>>>,
    n_actuators: usize,
    problems: Vec<Problem>,
}

impl MpmBuilder<D2> {
    /// An empty 2D scene on an `n_grid x n_grid` grid of spacing `dx`, with walls 3 nodes
    /// thick, a sticky floor and gravity `(0, -3.8)` (DiffTaichi's `diffmpm` settings).
    pub fn new(n_grid: usize, dx: f64) -> Self {
        Self::with_dim(n_grid, dx)
    }
}

impl MpmBuilder<D3> {
    /// An empty 3D scene on an `n_grid^3` grid of spacing `dx`, with walls 3 nodes thick, a
    /// sticky floor at `y = 0` and gravity `(0, -3.8, 0)`.
    pub fn new_3d(n_grid: usize, dx: f64) -> Self {
        Self::with_dim(n_grid, dx)
    }
}

impl<D: Dim> MpmBuilder<D> {
    /// An empty scene in `D` dimensions ([`MpmBuilder::new`], [`MpmBuilder::new_3d`]).
    pub fn with_dim(n_grid: usize, dx: f64) -> Self {
        let mut problems = Vec::new();
        if n_grid < 8 {
            problems.push(problem(
                "grid",
                Some("n_grid"),
                format!("must be at least 8 (got {n_grid})"),
            ));
        }
        if !(dx.is_finite() && dx > 0.0) {
            problems.push(problem(
                "grid",
                Some("dx"),
                format!("must be finite and > 0 (got {dx})"),
            ));
        }
        MpmBuilder {
            n_grid,
            dx,
            bound: 3,
            floor: Floor::Sticky,
            gravity: D::vector(&[0.0, -3.8, 0.0][..D::D]),
            x: Vec::new(),
            v: Vec::new(),
            mass: Vec::new(),
            volume: Vec::new(),
            material: Vec::new(),
            actuator: Vec::new(),
            n_actuators: 0,
            problems,
        }
    }

    /// Wall thickness in nodes (default 3; at least 2, so that a particle's stencil never
    /// leaves the grid while it is inside the walls).
    pub fn set_bound(&mut self, bound: usize) -> &mut Self {
        self.bound = bound;
        self
    }

    /// What the floor does (default [`Floor::Sticky`]).
    pub fn set_floor(&mut self, floor: Floor) -> &mut Self {
        self.floor = floor;
        self
    }

    /// Gravity (m/s^2; default `(0, -3.8)`).
    pub fn set_gravity(&mut self, g: D::V<f64>) -> &mut Self {
        self.gravity = g;
        self
    }

    /// Adds a particle at rest at `x` with `mass`, `volume` (its share of the body's rest
    /// volume) and `material`; returns its index.
    pub fn add_particle(
        &mut self,
        x: D::V<f64>,
        mass: f64,
        volume: f64,
        material: Material,
    ) -> usize {
        let i = self.x.len();
        self.x.push(x);
        self.v.push(D::vector(&[0.0; 3][..D::D]));
        self.mass.push(mass);
        self.volume.push(volume);
        self.material.push(material);
        self.actuator.push(None);
        i
    }

    /// Fills the box `[min, min + size]` (a rectangle in 2D) with particles, two per cell
    /// along each axis (`floor(size / dx) * 2` per axis, evenly spaced, as DiffTaichi's
    /// `diffmpm`), each of `mass`, `volume` and `material`; returns their indices.
    pub fn add_rect(
        &mut self,
        min: D::V<f64>,
        size: D::V<f64>,
        mass: f64,
        volume: f64,
        material: Material,
    ) -> Range<usize> {
        let start = self.x.len();
        let (lo, len) = (D::components(&min), D::components(&size));
        let counts: Vec<usize> = len
            .iter()
            .map(|&l| ((l / self.dx).floor().max(0.0) as usize) * 2)
            .collect();
        if counts.contains(&0) {
            self.problems.push(problem(
                "rect",
                Some("size"),
                format!(
                    "{size:?} holds no particle: each side must be at least dx = {}",
                    self.dx
                ),
            ));
            return start..start;
        }
        let total: usize = counts.iter().product();
        for k in 0..total {
            // The first axis varies slowest.
            let mut rest = k;
            let mut c = vec![0.0; D::D];
            for a in (0..D::D).rev() {
                let i = rest % counts[a];
                rest /= counts[a];
                c[a] = lo[a] + (i as f64 + 0.5) * len[a] / counts[a] as f64;
            }
            self.add_particle(D::vector(&c), mass, volume, material);
        }
        start..self.x.len()
    }

    /// Sets the initial velocity of particle `i`.
    pub fn set_velocity(&mut self, i: usize, v: D::V<f64>) -> &mut Self {
        match self.v.get_mut(i) {
            Some(slot) => *slot = v,
            None => self.problems.push(problem_at(
                "particles",
                i,
                Some("index"),
                "no such particle".into(),
            )),
        }
        self
    }

    /// Drives `particles` by actuator `actuator`: an active Kirchhoff stress
    /// `a strength F d d^T F^T`, where `a` is the actuator's value in the step's actuation
    /// array and `d` the fiber direction in the rest frame (normalized). DiffTaichi's
    /// `diffmpm` uses `strength = 4` and `d = (0, 1)`.
    pub fn actuate(
        &mut self,
        particles: Range<usize>,
        actuator: usize,
        strength: f64,
        fiber: D::V<f64>,
    ) -> &mut Self {
        let c = D::components(&fiber);
        let n = c.iter().map(|v| v * v).sum::<f64>().sqrt();
        let unit = D::vector(&c.iter().map(|v| v / n).collect::<Vec<_>>());
        if !(n.is_finite() && n > 0.0) {
            self.problems.push(problem(
                "actuators",
                Some("fiber"),
                format!("{fiber:?} must be finite and not zero"),
            ));
        }
        if !strength.is_finite() {
            self.problems.push(problem(
                "actuators",
                Some("strength"),
                format!("{strength} must be finite"),
            ));
        }
        for p in particles {
            match self.actuator.get_mut(p) {
                Some(slot) => {
                    *slot = Some(Drive {
                        actuator,
                        strength,
                        fiber: unit,
                    })
                }
                None => {
                    self.problems.push(problem_at(
                        "particles",
                        p,
                        Some("index"),
                        "no such particle".into(),
                    ));
                    break;
                }
            }
        }
        self.n_actuators = self.n_actuators.max(actuator + 1);
        self
    }

    /// Number of particles so far.
    pub fn particle_count(&self) -> usize {
        self.x.len()
    }

    /// Checks the scene and builds the model in precision `R`, or returns every problem:
    /// a grid too small for its walls, particles outside the walls, non-finite or
    /// non-positive masses and volumes, negative or non-finite Lame parameters.
    pub fn finalize<R: Real>(&self) -> Result<Mpm<R, D>, ModelError> {
        let mut problems = self.problems.clone();
        let (n, dx, bound) = (self.n_grid, self.dx, self.bound);
        if bound < 2 || 2 * bound + 3 > n {
            problems.push(problem(
                "grid",
                Some("bound"),
                format!(
                    "{bound} must be at least 2 and leave room inside a grid of {n} nodes per axis"
                ),
            ));
        }
        if !D::components(&self.gravity).iter().all(|g| g.is_finite()) {
            problems.push(problem(
                "gravity",
                None,
                format!("{:?} must be finite", self.gravity),
            ));
        }
        if let Floor::Coulomb(mu) = self.floor {
            if !(mu.is_finite() && mu >= 0.0) {
                problems.push(problem(
                    "floor",
                    Some("friction"),
                    format!("{mu} must be finite and >= 0"),
                ));
            }
        }
        let (lo, hi) = (bound as f64 * dx, (n - bound.min(n)) as f64 * dx);
        for (i, x) in self.x.iter().enumerate() {
            if !D::components(x).iter().all(|&c| c >= lo && c < hi) {
                problems.push(problem_at(
                    "particles",
                    i,
                    Some("x"),
                    format!(
                        "{x:?} is outside the domain inside the walls, [{lo}, {hi}]^{}",
                        D::D
                    ),
                ));
            }
            if !(self.mass[i].is_finite() && self.mass[i] > 0.0) {
                problems.push(problem_at(
                    "particles",
                    i,
                    Some("mass"),
                    format!("{} must be finite and > 0", self.mass[i]),
                ));
            }
            if !(self.volume[i].is_finite() && self.volume[i] > 0.0) {
                problems.push(problem_at(
                    "particles",
                    i,
                    Some("volume"),
                    format!("{} must be finite and > 0", self.volume[i]),
                ));
            }
            let (_, mu, lambda) = self.material[i].params();
            if !(mu.is_finite() && mu >= 0.0 && lambda.is_finite() && lambda >= 0.0) {
                problems.push(problem_at(
                    "particles",
                    i,
                    Some("material"),
                    format!("{:?}: the moduli must be finite and >= 0", self.material[i]),
                ));
            }
            if let Some(message) = plasticity_problem(self.material[i].plasticity()) {
                problems.push(problem_at(
                    "particles",
                    i,
                    Some("material"),
                    format!("{:?}: {message}", self.material[i]),
                ));
            }
            if !D::components(&self.v[i]).iter().all(|c| c.is_finite()) {
                problems.push(problem_at(
                    "particles",
                    i,
                    Some("v"),
                    format!("{:?} must be finite", self.v[i]),
                ));
            }
        }
        if self.x.is_empty() {
            problems.push(problem(
                "particles",
                None,
                "the scene has no particle".into(),
            ));
        }
        if !problems.is_empty() {
            return Err(ModelError { problems });
        }
        let lit = |v: f64| R::lit(v);
        let vec2 = |v: &D::V<f64>| D::vector::<R>(&D::components(v));
        let np = self.x.len();
        let params: Vec<_> = self.material.iter().map(Material::params).collect();
        let plastic = |k: usize| {
            Array::from_vec(
                self.material
                    .iter()
                    .map(|m| lit(m.plasticity()[k]))
                    .collect(),
            )
        };
        let stable_dt = (0..np)
            .map(|i| dx / self.material[i].wave_speed(self.mass[i] / self.volume[i]))
            .fold(f64::INFINITY, f64::min);
        Ok(Mpm {
            n_grid: n,
            dx,
            bound,
            friction: match self.floor {
                Floor::Sticky => -1.0,
                Floor::Coulomb(mu) => mu,
            },
            gravity: Array::from_vec(vec![vec2(&self.gravity)]).named("mpm.gravity"),
            mass: Array::from_vec(self.mass.iter().map(|&m| lit(m)).collect()).named("mpm.mass"),
            volume: Array::from_vec(self.volume.iter().map(|&m| lit(m)).collect())
                .named("mpm.volume"),
            mu: Array::from_vec(params.iter().map(|p| lit(p.1)).collect()).named("mpm.mu"),
            lambda: Array::from_vec(params.iter().map(|p| lit(p.2)).collect()).named("mpm.lambda"),
            kind: Array::from_vec(params.iter().map(|p| p.0).collect()).named("mpm.kind"),
            compression: plastic(0).named("mpm.compression"),
            stretch: plastic(1).named("mpm.stretch"),
            hardening: plastic(2).named("mpm.hardening"),
            actuator: Array::from_vec(
                self.actuator
                    .iter()
                    .map(|a| a.map_or(0, |a| a.actuator as u32))
                    .collect(),
            )
            .named("mpm.actuator"),
            act_gain: Array::from_vec(
                self.actuator
                    .iter()
                    .map(|a| lit(a.map_or(0.0, |a| a.strength)))
                    .collect(),
            )
            .named("mpm.act_gain"),
            fiber: Array::from_vec(
                self.actuator
                    .iter()
                    .map(|a| vec2(&a.map_or(D::vector(&[0.0, 1.0, 0.0][..D::D]), |a| a.fiber)))
                    .collect(),
            )
            .named("mpm.fiber"),
            n_actuators: self.n_actuators,
            no_actuation: Array::zeros(self.n_actuators.max(1)).named("mpm.no_actuation"),
            x0: self.x.iter().map(vec2).collect(),
            v0: self.v.iter().map(vec2).collect(),
            stable_dt,
        })
    }
}

/// What is wrong with snow's `[compression, stretch, hardening]`, if anything (all zero: not
/// snow). `compression + stretch > 0`: with both 0 the clamp is a constant, whose derivative
/// the rules would not give.
fn plasticity_problem([compression, stretch, hardening]: [f64; 3]) -> Option<String> {
    if [compression, stretch, hardening] == [0.0; 3] {
        return None;
    }
    let ok = (0.0..1.0).contains(&compression)
        && stretch.is_finite()
        && stretch >= 0.0
        && compression + stretch > 0.0
        && hardening.is_finite()
        && hardening >= 0.0;
    (!ok).then(|| {
        format!(
            "compression ({compression}) must be in [0, 1), stretch ({stretch}) finite and >= 0, \
             not both 0, hardening ({hardening}) finite and >= 0"
        )
    })
}

/// How a particle is driven: its actuator, the strength and the unit fiber direction.
#[derive(Clone, Copy, Debug)]
struct Drive<V> {
    actuator: usize,
    strength: f64,
    fiber: V,
}

fn problem(item: &str, param: Option<&'static str>, message: String) -> Problem {
    Problem {
        item: item.into(),
        param,
        message,
    }
}

fn problem_at(kind: &str, i: usize, param: Option<&'static str>, message: String) -> Problem {
    problem(&format!("{kind}[{i}]"), param, message)
}

/// An MLS-MPM model in `D` dimensions (see the [module docs](super)): the grid and
/// per-particle arrays, each a possible gradient target.
#[derive(Clone, Debug)]
pub struct Mpm<R: Real, D: Dim = D2> {
    /// Nodes per axis.
    pub n_grid: usize,
    /// Grid spacing.
    pub dx: f64,
    /// Wall thickness in nodes.
    pub bound: usize,
    /// Floor friction (negative: sticky).
    pub friction: f64,
    /// Gravity (one element).
    pub gravity: Array<D::V<R>>,
    /// Particle masses.
    pub mass: Array<R>,
    /// Particle volumes.
    pub volume: Array<R>,
    /// Shear moduli.
    pub mu: Array<R>,
    /// Lame's first parameters (the bulk modulus of fluid particles).
    pub lambda: Array<R>,
    /// Material of each particle (the constants of [`super::kernels`]).
    pub kind: Array<u32>,
    /// Critical compression of each snow particle (0 for the other materials).
    pub compression: Array<R>,
    /// Critical stretch of each snow particle (0 for the other materials).
    pub stretch: Array<R>,
    /// Hardening coefficient of each snow particle (0 for the other materials).
    pub hardening: Array<R>,
    /// Actuator of each particle (0 for passive ones, whose gain is 0).
    pub actuator: Array<u32>,
    /// Actuation strength of each particle (0: passive).
    pub act_gain: Array<R>,
    /// Fiber direction of each particle in the rest frame.
    pub fiber: Array<D::V<R>>,
    /// Number of actuators: the length of a step's actuation array.
    pub n_actuators: usize,
    pub(super) no_actuation: Array<R>,
    x0: Vec<D::V<R>>,
    v0: Vec<D::V<R>>,
    stable_dt: f64,
}

/// The state of the particles: positions, velocities, APIC matrices `C`, deformation
/// gradients `F` (the elastic part, for snow) and plastic volume ratios `Jp`.
#[derive(Clone, Debug)]
pub struct MpmState<R: Real, D: Dim = D2> {
    /// Positions.
    pub x: Array<D::V<R>>,
    /// Velocities.
    pub v: Array<D::V<R>>,
    /// APIC affine velocity matrices.
    pub c: Array<D::M<R>>,
    /// Deformation gradients (for snow, the elastic part `F_E`).
    pub f: Array<D::M<R>>,
    /// Plastic volume ratios `Jp = det F_P` (below 1: packed); 1 and unchanged for the
    /// materials other than [`Material::Snow`].
    pub jp: Array<R>,
}

impl<R: Real, D: Dim> Checkpoint for MpmState<R, D> {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        vec![&self.x, &self.v, &self.c, &self.f, &self.jp]
    }
    fn snapshot(&self) -> Self {
        MpmState {
            x: self.x.deep_clone(),
            v: self.v.deep_clone(),
            c: self.c.deep_clone(),
            f: self.f.deep_clone(),
            jp: self.jp.deep_clone(),
        }
    }
}

impl<R: Real, D: Dim> Mpm<R, D> {
    /// Number of particles.
    pub fn particle_count(&self) -> usize {
        self.mass.len()
    }

    /// The initial state: the builder's positions and velocities, `C = 0`, `F = I`, `Jp = 1`.
    pub fn state(&self) -> MpmState<R, D> {
        let n = self.particle_count();
        MpmState {
            x: Array::from_vec(self.x0.clone()).named("mpm.x"),
            v: Array::from_vec(self.v0.clone()).named("mpm.v"),
            c: Array::zeros(n).named("mpm.C"),
            f: Array::from_vec(vec![D::identity::<R>(); n]).named("mpm.F"),
            jp: Array::from_vec(vec![R::lit(1.0); n]).named("mpm.Jp"),
        }
    }

    /// The largest time step the elastic waves allow: `dx / c` with `c = sqrt((lambda +
    /// 2 mu) / rho)` the fastest wave speed over the particles (`rho = mass / volume`), from
    /// the builder's values (changing the `mu`, `lambda`, `mass` or `volume` arrays later
    /// does not update it). Measured, steps stay stable up to 1.1 to 1.9 times it
    /// (`docs/performance.md`, "MPM stability against stiffness") and fail beyond; the
    /// particles' own speed must also stay below `dx / dt`. Snow's moduli harden as it is
    /// packed (`exp(hardening (1 - Jp))`, 7.4 times at `Jp = 0.8` with hardening 10), which
    /// divides the limit by the square root of that factor: it is not counted here.
    pub fn stable_dt(&self) -> f64 {
        self.stable_dt
    }

    /// The mean position of the particles (one element), recorded on `tape` (DiffTaichi's
    /// `diffmpm` loss is minus its `x`).
    pub fn mean_position(&self, tape: &mut Tape, state: &MpmState<R, D>) -> Array<D::V<R>> {
        let out = Array::zeros(1).named("mpm.mean_position");
        let n = self.particle_count();
        D::launch_weighted_sum(tape, &state.x, R::lit(1.0 / n as f64), &out);
        out
    }

    /// Every array of the model's length; snow's parameters in range; every particle finite
    /// and inside the walls (so that its stencil is on the grid), `Jp` finite and positive;
    /// `det F > 0` where the material needs it (all but the 2D corotated one, whose
    /// closed-form rotation handles inversion).
    pub(super) fn check_state(&self, state: &MpmState<R, D>, which: &str) -> Result<(), Error> {
        let n = self.particle_count();
        let lens = [
            (state.x.len(), state.x.label()),
            (state.v.len(), state.v.label()),
            (state.c.len(), state.c.label()),
            (state.f.len(), state.f.label()),
            (state.jp.len(), state.jp.label()),
        ];
        for (len, label) in lens {
            if len != n {
                return Err(invalid(
                    &label,
                    format!("{len} values for a model of {n} particles ({which})"),
                ));
            }
        }
        // The stencil of x spans nodes floor(x / dx - 0.5) + 0..3.
        let lo = self.dx;
        let hi = (self.n_grid - 2) as f64 * self.dx;
        let unstable = || {
            format!(
                "the simulation is unstable: reduce dt below the model's stable_dt ({:.3e}) or \
                 the speeds so that |v| dt < dx",
                self.stable_dt
            )
        };
        for (i, x) in state.x.to_vec().iter().enumerate() {
            if !D::inside(x, lo, hi) {
                let c = D::components(x);
                return Err(invalid(
                    &format!("{}[{i}]", state.x.label()),
                    format!(
                        "particle {i} at {c:?} is not finite or has left the grid [{lo}, {hi})^{} \
                         ({which}): {}",
                        D::D,
                        unstable()
                    ),
                ));
            }
        }
        let kinds = self.kind.to_vec();
        // Snow's parameters are gradient targets an optimizer may have moved out of range.
        let plastic = [&self.compression, &self.stretch, &self.hardening].map(|a| a.to_vec());
        for (i, &k) in kinds.iter().enumerate() {
            if k != SNOW {
                continue;
            }
            let p = [0, 1, 2].map(|a| plastic[a][i].to_f64());
            if let Some(message) = plasticity_problem(p) {
                return Err(invalid(
                    &format!("mpm.compression[{i}], mpm.stretch[{i}], mpm.hardening[{i}]"),
                    format!("particle {i}: {message} ({which})"),
                ));
            }
        }
        for (i, jp) in state.jp.to_vec().iter().enumerate() {
            let jp = jp.to_f64();
            if !(jp.is_finite() && jp > 0.0) {
                return Err(invalid(
                    &format!("{}[{i}]", state.jp.label()),
                    format!(
                        "particle {i}'s plastic volume ratio Jp = {jp:e} must be finite and > 0 \
                         ({which}; a snow particle whose F inverted within a step ends here): {}",
                        unstable()
                    ),
                ));
            }
        }
        for (i, f) in state.f.to_vec().iter().enumerate() {
            let needs_positive = !(D::D == 2 && kinds[i] == COROTATED);
            let det = D::determinant(f);
            if needs_positive && !(det > 0.0) {
                return Err(invalid(
                    &format!("{}[{i}]", state.f.label()),
                    format!(
                        "particle {i} is inverted or degenerate (det F = {det:e}, {which}); its \
                         material needs det F > 0: {}",
                        unstable()
                    ),
                ));
            }
        }
        Ok(())
    }
}

pub(super) fn invalid(what: &str, message: String) -> Error {
    Error::InvalidInput {
        what: what.into(),
        message,
    }
}
