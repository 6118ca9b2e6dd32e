//! The particle family's part of a scene description: positions, velocities, inverse masses,
//! contact radii and the surface triangles (topology), as [`ModelBuilder`](crate::ModelBuilder)
//! records them; and [`Elements`], what every force's builder part checks its elements
//! against (the particles so far, and the list of problems it records into).

use adflex_runtime::{Array, Real, Vec3};

use crate::validation::{max_of, overflow_hint, precision, Check, Problem};
use serde::Deserialize;

use crate::scene_file::reader::{sub, v3, zero3, Checker, SceneError};

fn lit<R: Real>(x: f64) -> R {
    R::lit(x)
}

/// The particles of a scene description.
#[derive(Clone, Debug)]
pub(crate) struct Particles<R: Real> {
    pub(crate) x: Vec<Vec3<R>>,
    /// Each particle's own contact radius, if it was given one.
    pub(crate) radii: Vec<Option<R>>,
    pub(crate) v: Vec<Vec3<R>>,
    pub(crate) inv_mass: Vec<R>,
    /// The surface triangles (for output and bending edges; no force of their own).
    pub(crate) triangles: Vec<[u32; 3]>,
}

impl<R: Real> Default for Particles<R> {
    fn default() -> Self {
        Particles {
            x: Vec::new(),
            radii: Vec::new(),
            v: Vec::new(),
            inv_mass: Vec::new(),
            triangles: Vec::new(),
        }
    }
}

/// The arrays of a model's particles (see [`crate::Model`]'s fields of the same names).
pub(crate) struct ParticleArrays<R: Real> {
    pub(crate) x: Array<Vec3<R>>,
    pub(crate) v: Array<Vec3<R>>,
    pub(crate) inv_mass: Array<R>,
    pub(crate) radii: Option<Array<R>>,
}

impl<R: Real> Particles<R> {
    pub(crate) fn len(&self) -> usize {
        self.x.len()
    }

    /// Appends `other`'s particles and triangles as a new world's; its particles without a
    /// radius of their own get `other_radius` if it is not this scene's `radius`.
    pub(crate) fn append(&mut self, other: &Self, radius: R, other_radius: R) {
        let offset = self.len() as u32;
        self.x.extend(&other.x);
        self.v.extend(&other.v);
        self.inv_mass.extend(&other.inv_mass);
        let own = (other_radius != radius).then_some(other_radius);
        self.radii.extend(other.radii.iter().map(|r| r.or(own)));
        self.triangles
            .extend(crate::forces::component::shifted(&other.triangles, offset));
    }

    /// The particles `range` (one share of the worlds) and the triangles among them, indices
    /// shifted down by `range.start`.
    pub(crate) fn worlds_in(&self, range: &std::ops::Range<u32>) -> Self {
        let r = range.start as usize..range.end as usize;
        Particles {
            x: self.x[r.clone()].to_vec(),
            radii: self.radii[r.clone()].to_vec(),
            v: self.v[r.clone()].to_vec(),
            inv_mass: self.inv_mass[r].to_vec(),
            triangles: crate::forces::component::elements_in(&self.triangles, range).1,
        }
    }

    /// Particle `i`'s position in `f64` (m).
    pub(crate) fn wide(&self, i: u32) -> Vec3<f64> {
        let p = self.x[i as usize];
        Vec3::new(p.x.to_f64(), p.y.to_f64(), p.z.to_f64())
    }

    /// Every position in `f64` (m).
    pub(crate) fn wide_all(&self) -> Vec<Vec3<f64>> {
        (0..self.len() as u32).map(|i| self.wide(i)).collect()
    }

    /// The contact radius of particle `i`: its own, or `default`.
    pub(crate) fn radius_of(&self, i: u32, default: R) -> R {
        self.radii[i as usize].unwrap_or(default)
    }

    /// Adds a particle of mass `mass` (kg; 0 pins it), checking that its inverse mass is
    /// finite in `R`.
    pub(crate) fn add(
        &mut self,
        problems: &mut Vec<Problem>,
        x: Vec3<R>,
        v: Vec3<R>,
        mass: R,
    ) -> u32 {
        let k = self.len();
        let m = mass.to_f64();
        let inv = if m > 0.0 { 1.0 / m } else { 0.0 };
        let inv_r: R = lit(inv);
        let mut c = check(problems, "particles", k);
        if c.nonneg("mass", mass) && !inv_r.to_f64().is_finite() {
            c.fail(
                Some("mass"),
                format!(
                    "the inverse mass 1/{m:e} is not finite in {}: give a mass of at least \
                     {:.1e} kg, or 0 to pin the particle",
                    precision::<R>(),
                    1.0 / max_of::<R>()
                ),
            );
        }
        self.push(problems, x, v, inv_r, false)
    }

    /// Adds a particle of inverse mass `inv_mass` (checked finite and `>= 0` if `check_inv`).
    pub(crate) fn push(
        &mut self,
        problems: &mut Vec<Problem>,
        x: Vec3<R>,
        v: Vec3<R>,
        inv_mass: R,
        check_inv: bool,
    ) -> u32 {
        let k = self.len();
        let mut c = check(problems, "particles", k);
        c.finite3("x", &x);
        c.finite3("v", &v);
        if check_inv {
            c.nonneg("inv_mass", inv_mass);
        }
        self.x.push(x);
        self.radii.push(None);
        self.v.push(v);
        self.inv_mass.push(inv_mass);
        k as u32
    }

    /// Gives particle `i` its own contact radius (finite and `>= 0`).
    pub(crate) fn set_radius(&mut self, problems: &mut Vec<Problem>, i: u32, radius: R) {
        let n = self.len();
        let mut c = check(problems, "particles", i as usize);
        if (i as usize) >= n {
            c.fail(
                None,
                format!("set_particle_radius: particle index {i} out of range ({n} particles)"),
            );
        } else if c.nonneg("radius", radius) {
            self.radii[i as usize] = Some(radius);
        }
    }

    /// Sets the inverse mass of particle `i` (finite and `>= 0`).
    pub(crate) fn set_inv_mass(&mut self, problems: &mut Vec<Problem>, i: u32, inv_mass: R) {
        let n = self.len();
        let mut c = check(problems, "particles", i as usize);
        if (i as usize) >= n {
            c.fail(
                None,
                format!("set_particle_inv_mass: particle index {i} out of range ({n} particles)"),
            );
        } else if c.nonneg("inv_mass", inv_mass) {
            self.inv_mass[i as usize] = inv_mass;
        }
    }

    /// Adds a surface triangle (topology) on distinct particles.
    pub(crate) fn add_triangle(&mut self, problems: &mut Vec<Problem>, ijk: [u32; 3]) -> u32 {
        let n = self.len();
        check(problems, "triangles", self.triangles.len()).particles(n, &ijk);
        self.triangles.push(ijk);
        (self.triangles.len() - 1) as u32
    }

    /// The model's particle arrays; per-particle radii only if some particle's radius differs
    /// from `radius`.
    pub(crate) fn build(&self, radius: R) -> ParticleArrays<R> {
        let n = self.len();
        ParticleArrays {
            x: Array::from_vec(self.x.clone()).named("x0"),
            v: Array::from_vec(self.v.clone()).named("v0"),
            inv_mass: Array::from_vec(self.inv_mass.clone()).named("inv_mass"),
            radii: self
                .radii
                .iter()
                .any(|r| r.is_some_and(|r| r != radius))
                .then(|| {
                    let radii = (0..n as u32).map(|i| self.radius_of(i, radius)).collect();
                    Array::from_vec(radii).named("particle_radius")
                }),
        }
    }
}

/// The checks of the single item `kind`, recording into `problems`.
pub(crate) fn check_one<'a>(problems: &'a mut Vec<Problem>, kind: &'static str) -> Check<'a> {
    Check {
        out: problems,
        kind,
        index: None,
    }
}

/// The checks of item `kind[index]`, recording into `problems`.
pub(crate) fn check<'a>(
    problems: &'a mut Vec<Problem>,
    kind: &'static str,
    index: usize,
) -> Check<'a> {
    Check {
        out: problems,
        kind,
        index: Some(index),
    }
}

/// What a force's builder part checks its elements against: the particles added so far, and
/// the scene's list of problems (see [`crate::validation`]).
pub(crate) struct Elements<'a, R: Real> {
    pub(crate) particles: &'a Particles<R>,
    pub(crate) problems: &'a mut Vec<Problem>,
}

impl<R: Real> Elements<'_, R> {
    /// The checks of item `kind[index]`.
    pub(crate) fn check(&mut self, kind: &'static str, index: usize) -> Check<'_> {
        check(self.problems, kind, index)
    }

    /// The checks of the single item `kind`.
    pub(crate) fn check_one(&mut self, kind: &'static str) -> Check<'_> {
        check_one(self.problems, kind)
    }

    /// Checks that `idx` are distinct particles of the scene (recording a problem of
    /// `kind[index]` if not).
    pub(crate) fn distinct(&mut self, kind: &'static str, index: usize, idx: &[u32]) -> bool {
        let n = self.particles.len();
        self.check(kind, index).particles(n, idx)
    }

    /// The distance between particles `i` and `j`, computed in `R` (with the same sum order as
    /// numpy's norm of a 3-vector: the reference scenes' rest lengths).
    pub(crate) fn distance(&self, i: u32, j: u32) -> R {
        let d = self.particles.x[i as usize] - self.particles.x[j as usize];
        (d.x * d.x + d.y * d.y + d.z * d.z).sqrt()
    }

    /// `rest` (m) of `kind[index]` between particles `i`, `j`: finite and `> 0` (`derived`:
    /// computed from the positions, so a problem of the element, not of a `rest` parameter).
    pub(crate) fn rest(
        &mut self,
        kind: &'static str,
        index: usize,
        ij: [u32; 2],
        rest: R,
        derived: bool,
    ) {
        let r = rest.to_f64();
        if r.is_finite() && r > 0.0 {
            return;
        }
        let [i, j] = ij;
        let why = if !derived {
            String::new()
        } else if r == 0.0 {
            format!(": particles {i} and {j} are at the same position; move one")
        } else {
            format!(
                ": the distance between particles {i} and {j} overflows{}",
                overflow_hint::<R>()
            )
        };
        self.check(kind, index).fail(
            if derived { None } else { Some("rest") },
            format!("the rest length must be finite and > 0 (got {r}){why}"),
        );
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ParticleDesc {
    x: [f64; 3],
    #[serde(default = "zero3")]
    v: [f64; 3],
    mass: f64,
    radius: Option<f64>,
}

/// Loads the `particles` section.
pub(crate) fn load<R: Real>(
    d: &[ParticleDesc],
    p: &mut Particles<R>,
    problems: &mut Vec<Problem>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, pd) in d.iter().enumerate() {
        let n0 = problems.len();
        c.no_underflow::<R>(|| format!("particles[{k}].mass"), pd.mass)?;
        let i = p.add(problems, v3(pd.x), v3(pd.v), R::lit(pd.mass));
        if let Some(r) = pd.radius {
            p.set_radius(problems, i, R::lit(r));
        }
        c.builder(problems, n0, |f| sub(&format!("particles[{k}]"), f, &[]))?;
    }
    Ok(())
}
