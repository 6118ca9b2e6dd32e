//! Damped springs between particle pairs (Hooke along the spring plus damping of the
//! relative velocity along it).

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

use crate::forces::component::{real_parts, Force, ForceContext, ForcePart, Param, ParamDoc};
use crate::particles::Elements;
use crate::scene_file::reader::{sub, Checker, SceneError};
use serde::Deserialize;

/// The force's name ([`Force::name`]): `"springs"`.
pub const NAME: &str = "springs";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::array("rest", "m (rest length)"),
    ParamDoc::array("ke", "N/m"),
    ParamDoc::array("kd", "N·s/m"),
];

/// Force of one damped spring on its second particle (the first gets the opposite).
///
/// `xij = x_i - x_j`, `vij = v_i - v_j` (m, m/s); `rest` (m), `ke` (N/m), `kd` (N s/m). The
/// direction is `normalize(xij)`, which is bitwise `xij / |xij|` except at a zero-length spring,
/// where the force is zero (and so is its gradient) instead of NaN.
#[diff_func]
pub fn spring_force<R: Real>(xij: Vec3<R>, vij: Vec3<R>, rest: R, ke: R, kd: R) -> Vec3<R> {
    let l = length(xij);
    let d = normalize(xij);
    d * (ke * (l - rest) + kd * dot(d, vij))
}

/// Accumulates the force of spring `tid` into `f`: `f_i -= fs`, `f_j += fs`, with `fs` from
/// [`spring_force`].
#[diff_kernel]
pub fn eval_springs<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    rest: &Array<R>,
    ke: &Array<R>,
    kd: &Array<R>,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let fs = spring_force(x[i] - x[j], v[i] - v[j], rest[t], ke[t], kd[t]);
    f.atomic_sub(i, fs);
    f.atomic_add(j, fs);
}

/// Elastic energy of spring `tid`, `ke/2 (|x_i - x_j| - rest)^2` (J), added to its world's
/// `energy[world[i]]`.
#[diff_kernel]
pub fn spring_energy<R: Real>(
    x: &Array<Vec3<R>>,
    pairs: &Array<[u32; 2]>,
    rest: &Array<R>,
    ke: &Array<R>,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j] = pairs[t];
    let c = length(x[i] - x[j]) - rest[t];
    energy.atomic_add(world[i] as usize, 0.5 * ke[t] * c * c);
}

/// The springs of a model: index pairs and per-spring parameters (each array a possible
/// gradient target).
#[derive(Clone, Debug)]
pub struct Springs<R: Real> {
    /// Particle indices `(i, j)` of each spring.
    pub pairs: Array<[u32; 2]>,
    /// Rest length (m).
    pub rest: Array<R>,
    /// Stiffness (N/m).
    pub ke: Array<R>,
    /// Damping along the spring (N s/m).
    pub kd: Array<R>,
}

impl<R: Real> Springs<R> {
    /// Number of springs.
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// Records [`eval_springs`] on `tape`, accumulating into `f`.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        f: &Array<Vec3<R>>,
    ) {
        tape.launch(
            eval_springs,
            self.len(),
            (x, v, &self.pairs, &self.rest, &self.ke, &self.kd, f),
        );
    }

    /// Records [`spring_energy`] on `tape`, adding into `energy[world[i]]`
    /// (`world`: each particle's world).
    pub fn energy(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        world: &Array<u32>,
        energy: &Array<R>,
    ) {
        tape.launch(
            spring_energy,
            self.len(),
            (x, &self.pairs, &self.rest, &self.ke, world, energy),
        );
    }
}

impl<R: Real> Force<R> for Springs<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        Springs::eval(self, tape, cx.x, cx.v, f);
    }
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        Springs::energy(self, tape, cx.x, &cx.particle_worlds(), energy);
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(Springs::<f64> {
            pairs: self.pairs.clone(),
            rest: real_parts(&self.rest),
            ke: real_parts(&self.ke),
            kd: real_parts(&self.kd),
        }))
    }

    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("rest", &mut self.rest);
        visit("ke", &mut self.ke);
        visit("kd", &mut self.kd);
    }
}

/// The springs of a scene description (see [`ModelBuilder::add_spring`](crate::ModelBuilder::add_spring)).
#[derive(Clone, Debug)]
pub(crate) struct SpringParts<R: Real> {
    pairs: Vec<[u32; 2]>,
    rest: Vec<R>,
    ke: Vec<R>,
    kd: Vec<R>,
}

impl<R: Real> Default for SpringParts<R> {
    fn default() -> Self {
        SpringParts {
            pairs: Vec::new(),
            rest: Vec::new(),
            ke: Vec::new(),
            kd: Vec::new(),
        }
    }
}

impl<R: Real> SpringParts<R> {
    pub(crate) fn len(&self) -> usize {
        self.pairs.len()
    }

    /// A spring with the particles' current distance as rest length.
    pub(crate) fn add(&mut self, el: &mut Elements<'_, R>, i: u32, j: u32, ke: R, kd: R) -> u32 {
        let k = self.len();
        let rest = if el.distinct("springs", k, &[i, j]) {
            let rest = el.distance(i, j);
            el.rest("springs", k, [i, j], rest, true);
            rest
        } else {
            R::lit(1.0)
        };
        self.push(el, i, j, rest, ke, kd)
    }

    /// A spring with an explicit rest length.
    pub(crate) fn add_with_rest(
        &mut self,
        el: &mut Elements<'_, R>,
        i: u32,
        j: u32,
        rest: R,
        ke: R,
        kd: R,
    ) -> u32 {
        let k = self.len();
        el.distinct("springs", k, &[i, j]);
        el.rest("springs", k, [i, j], rest, false);
        self.push(el, i, j, rest, ke, kd)
    }

    fn push(&mut self, el: &mut Elements<'_, R>, i: u32, j: u32, rest: R, ke: R, kd: R) -> u32 {
        let mut c = el.check("springs", self.len());
        c.nonneg("ke", ke);
        c.nonneg("kd", kd);
        self.pairs.push([i, j]);
        self.rest.push(rest);
        self.ke.push(ke);
        self.kd.push(kd);
        (self.len() - 1) as u32
    }
}

impl<R: Real> ForcePart<R> for SpringParts<R> {
    fn spanning_worlds(&self, world_of: &[u32]) -> Option<(usize, Vec<u32>)> {
        super::component::first_spanning(&self.pairs, world_of)
    }

    fn append(&mut self, other: &Self, offset: u32) -> Result<(), String> {
        self.pairs
            .extend(super::component::shifted(&other.pairs, offset));
        self.rest.extend(&other.rest);
        self.ke.extend(&other.ke);
        self.kd.extend(&other.kd);
        Ok(())
    }

    fn worlds_in(&self, particles: &std::ops::Range<u32>) -> Self {
        use super::component::{elements_in, pick};
        let (idx, pairs) = elements_in(&self.pairs, particles);
        SpringParts {
            pairs,
            rest: pick(&self.rest, &idx),
            ke: pick(&self.ke, &idx),
            kd: pick(&self.kd, &idx),
        }
    }

    fn build(&self) -> Option<Box<dyn Force<R>>> {
        (!self.pairs.is_empty()).then(|| {
            Box::new(Springs {
                pairs: Array::from_vec(self.pairs.clone()).named("spring_pairs"),
                rest: Array::from_vec(self.rest.clone()).named("spring_rest"),
                ke: Array::from_vec(self.ke.clone()).named("spring_ke"),
                kd: Array::from_vec(self.kd.clone()).named("spring_kd"),
            }) as Box<dyn Force<R>>
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SpringDesc {
    i: u32,
    j: u32,
    ke: f64,
    #[serde(default)]
    kd: f64,
    rest: Option<f64>,
}

/// Loads the `springs` section.
pub(crate) fn load<R: Real>(
    d: &[SpringDesc],
    part: &mut SpringParts<R>,
    el: &mut Elements<'_, R>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, s) in d.iter().enumerate() {
        let n0 = el.problems.len();
        match s.rest {
            Some(r) => part.add_with_rest(el, s.i, s.j, R::lit(r), R::lit(s.ke), R::lit(s.kd)),
            None => part.add(el, s.i, s.j, R::lit(s.ke), R::lit(s.kd)),
        };
        c.builder(el.problems, n0, |f| {
            sub(&format!("springs[{k}]"), f, &["indices"])
        })?;
    }
    Ok(())
}
