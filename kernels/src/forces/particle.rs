//! Per-particle forces: linear drag and wind, external (control) forces, and the conversion of
//! forces to accelerations with gravity.
//!
//! Gravity is an acceleration, not a force: integrators add `g` to every particle with inverse
//! mass > 0 (so pinned particles, of inverse mass 0, stay put), see [`accelerations`].

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::forces::component::{Force, ForceContext, Param, ParamDoc};
use crate::particles::check_one;
use crate::scene_file::reader::{sub, v3, zero3, Checker, SceneError};
use crate::validation::Problem;
use serde::Deserialize;

/// The force's name ([`Force::name`]): `"drag"`.
pub const NAME: &str = "drag";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::scalar("kd", "N·s/m"),
    ParamDoc::scalar("wind", "m/s"),
];

/// Linear drag relative to the air: `f -= kd (v - v_air)` (`kd` in N s/m, `v_air` in m/s).
/// With `v_air = 0` it is plain linear drag; otherwise wind.
#[diff_kernel]
pub fn eval_drag<R: Real>(v: &Array<Vec3<R>>, kd: R, v_air: Vec3<R>, f: &Array<Vec3<R>>) {
    let t = tid();
    f.atomic_sub(t, (v[t] - v_air) * kd);
}

/// Adds the external force `fext[tid]` (N) to `f[tid]`.
#[diff_kernel]
pub fn add_forces<R: Real>(fext: &Array<Vec3<R>>, f: &Array<Vec3<R>>) {
    let t = tid();
    f.atomic_add(t, fext[t]);
}

/// `a = f w + g [w > 0]` (m/s^2), `w` the inverse mass (1/kg), `g = gravity[world[tid]]`
/// the particle's world's gravity (m/s^2).
#[diff_kernel]
pub fn accelerations<R: Real>(
    f: &Array<Vec3<R>>,
    inv_mass: &Array<R>,
    gravity: &Array<Vec3<R>>,
    world: &Array<u32>,
    a: &Array<Vec3<R>>,
) {
    let t = tid();
    let w = inv_mass[t];
    let g = gravity[world[t] as usize];
    a[t] = f[t] * w + select(w > 0.0, g, g * 0.0);
}

/// Gravity as a force, `f += g / w` on particles with `w > 0` (`g = gravity[world[tid]]`): for
/// integrators that want the total force rather than [`accelerations`].
#[diff_kernel]
pub fn add_gravity_force<R: Real>(
    inv_mass: &Array<R>,
    gravity: &Array<Vec3<R>>,
    world: &Array<u32>,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let w = inv_mass[t];
    if w > 0.0 {
        f.atomic_add(t, gravity[world[t] as usize] / w);
    }
}

/// Linear drag / wind on every particle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Drag<R: Real> {
    /// Drag coefficient (N s/m; default 0.1).
    pub kd: R,
    /// Air velocity (m/s; default 0): zero for plain drag, nonzero for wind.
    pub wind: Vec3<R>,
}

/// Plain drag `kd = 0.1` N s/m (a light air resistance for particles of about 10 g), no wind.
impl<R: Real> Default for Drag<R> {
    fn default() -> Self {
        Drag {
            kd: R::lit(0.1),
            wind: Vec3::zeros(),
        }
    }
}

impl<R: Real> Drag<R> {
    /// The builder's checks: `kd` finite and `>= 0`, `wind` finite.
    pub(crate) fn check(&self, c: &mut crate::validation::Check) {
        c.nonneg("kd", self.kd);
        c.finite3("wind", &self.wind);
    }
}

impl<R: Real> Drag<R> {
    /// Records [`eval_drag`] on `tape`, accumulating into `f`.
    pub fn eval(&self, tape: &mut Tape, v: &Array<Vec3<R>>, f: &Array<Vec3<R>>) {
        tape.launch(eval_drag, v.len(), (v, self.kd, self.wind, f));
    }
}

/// Drag has no parameter arrays (`kd` and `wind` are scalars, not differentiable).
impl<R: Real> Force<R> for Drag<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        Drag::eval(self, tape, cx.v, f);
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(Drag::<f64> {
            kd: self.kd.to_f64(),
            wind: self.wind.map(|c| c.to_f64()),
        }))
    }

    fn params_mut(&mut self, _visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {}
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct DragDesc {
    kd: f64,
    #[serde(default = "zero3")]
    wind: [f64; 3],
}

/// Loads the `drag` section.
pub(crate) fn load<R: Real>(
    dr: &DragDesc,
    part: &mut Option<Drag<R>>,
    problems: &mut Vec<Problem>,
    c: &Checker,
) -> Result<(), SceneError> {
    let n0 = problems.len();
    let drag = Drag {
        kd: R::lit(dr.kd),
        wind: v3(dr.wind),
    };
    set(part, problems, drag);
    c.builder(problems, n0, |f| sub("drag", f, &[]))
}

/// Sets the drag after its checks (the builder's `set_drag` and the loader).
pub(crate) fn set<R: Real>(part: &mut Option<Drag<R>>, problems: &mut Vec<Problem>, drag: Drag<R>) {
    drag.check(&mut check_one(problems, NAME));
    *part = Some(drag);
}
