//! Penalty contact of particles with a ground plane, with dFlex's smoothed Coulomb friction,
//! and an optional "leaky" gradient that lets optimizers see contacts that are not active yet.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::law::{contact_damping, contact_depth, contact_force, penalty_energy};
use crate::forces::component::{Force, ForceContext, Param, ParamDoc};
use crate::particles::check_one;
use crate::scene_file::reader::{sub, v3, Checker, SceneError};
use crate::validation::Problem;
use serde::Deserialize;

/// The force's name ([`Force::name`]): `"ground"`.
pub const NAME: &str = "ground";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::scalar("normal", "1 (unit normal)"),
    ParamDoc::scalar("offset", "m"),
    ParamDoc::scalar("ke", "N/m"),
    ParamDoc::scalar("kd", "N·s/m"),
    ParamDoc::scalar("mu", "1 (friction coefficient)"),
    ParamDoc::scalar("leak", "1 (gradient leak out of contact)"),
    ParamDoc::scalar("damp_approach", "bool"),
    ParamDoc::scalar("damping_depth", "m"),
];

/// Ground contact of particle `tid`: the plane `dot(normal, x) = offset` (m), particles of
/// radius `radius` (m); `c = contact_depth(dot(normal, x) - offset - radius, leak)` and
/// `f += contact_force(normal, c, v, ke, contact_damping(c, kd, kd_free, depth), mu)`:
/// `kd_free` is the damping of particles approaching the plane out of contact
/// ([`Ground::damp_approach`]), `depth` the [`Ground::damping_depth`].
#[diff_kernel]
pub fn eval_ground<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    radius: R,
    ke: R,
    kd: R,
    kd_free: R,
    depth: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let d = dot(normal, x[t]) - offset - radius;
    let c = contact_depth(d, leak);
    // The ramp sees the true depth: a leaky slope through it would be `kd / depth` times
    // the leak, far above the intended `leak ke`.
    let kdc = contact_damping(min(d, 0.0), kd, kd_free, depth);
    f.atomic_add(t, contact_force(normal, c, v[t], ke, kdc, mu));
}

/// [`eval_ground`] with a radius per particle: `radius[tid]` (m).
#[diff_kernel]
pub fn eval_ground_radii<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    radius: &Array<R>,
    ke: R,
    kd: R,
    kd_free: R,
    depth: R,
    mu: R,
    leak: R,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let d = dot(normal, x[t]) - offset - radius[t];
    let c = contact_depth(d, leak);
    // The ramp sees the true depth: a leaky slope through it would be `kd / depth` times
    // the leak, far above the intended `leak ke`.
    let kdc = contact_damping(min(d, 0.0), kd, kd_free, depth);
    f.atomic_add(t, contact_force(normal, c, v[t], ke, kdc, mu));
}

/// Penalty energy of particle `tid` against the ground of [`eval_ground`]:
/// `penalty_energy(dot(normal, x) - offset - radius, ke)`, added to its world's
/// `energy[world[tid]]`.
#[diff_kernel]
pub fn ground_energy<R: Real>(
    x: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    radius: R,
    ke: R,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    energy.atomic_add(
        world[t] as usize,
        penalty_energy(dot(normal, x[t]) - offset - radius, ke),
    );
}

/// [`ground_energy`] with a radius per particle: `radius[tid]` (m).
#[diff_kernel]
pub fn ground_energy_radii<R: Real>(
    x: &Array<Vec3<R>>,
    normal: Vec3<R>,
    offset: R,
    radius: &Array<R>,
    ke: R,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    energy.atomic_add(
        world[t] as usize,
        penalty_energy(dot(normal, x[t]) - offset - radius[t], ke),
    );
}

/// A ground plane for particle (and rigid body point) contact.
///
/// By default ([`Ground::damp_approach`] `= false`) its damping `kd` acts only in contact
/// (ramped in over [`Ground::damping_depth`]), and
/// [`crate::contact::particle::ParticleContact::restitution_damping`] (with `m_eff` the
/// particle's mass) gives the ground a coefficient of restitution; with `kd = 0` a bounce is
/// elastic up to the integrator's error. With `damp_approach = true` (dFlex's and Warp's
/// choice, which the benchmark `cloth` scene reproduces) it acts on every particle moving
/// towards the plane, in contact or not (see [`contact_force`]): a falling particle is braked
/// by `kd v` before it lands, which for light particles (cloth) is a strong air drag (a 10 g
/// particle under `kd = 1` falls at 0.1 m/s).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ground<R: Real> {
    /// Unit normal, pointing out of the ground (default `+y`).
    pub normal: Vec3<R>,
    /// The plane is `dot(normal, x) = offset` (m; default 0).
    pub offset: R,
    /// Contact stiffness (N/m; default 1000).
    pub ke: R,
    /// Contact damping (N s/m; default 1).
    pub kd: R,
    /// Friction coefficient (default 0.5).
    pub mu: R,
    /// Gradient leak of [`contact_depth`] out of contact (default 0: exact gradients).
    pub leak: R,
    /// Whether `kd` also damps particles approaching the plane out of contact (default false:
    /// damping in contact only; true as in dFlex and Warp, an air drag on falling particles). Rigid-body points are damped in
    /// contact only either way.
    pub damp_approach: bool,
    /// With `damp_approach = false`: the penetration depth (m; default 1e-4) over which the
    /// damping rises from 0 to `kd` ([`contact_damping`]), so that the contact force has no
    /// jump (implicit Euler's Newton cannot converge through one); 0 switches it on at contact.
    /// Without effect when `damp_approach` is true (the damping is `kd` everywhere).
    pub damping_depth: R,
}

impl<R: Real> Ground<R> {
    /// The builder's checks: a finite unit normal (length within 1e-3 of 1), a finite
    /// offset, and `ke`, `kd`, `mu`, `leak`, `damping_depth` finite and `>= 0`.
    pub(crate) fn check(&self, c: &mut crate::validation::Check) {
        if c.finite3("normal", &self.normal) {
            let l = self.normal.norm().to_f64();
            if (l - 1.0).abs() > 1e-3 {
                c.fail(
                    Some("normal"),
                    format!("must be a unit vector (length {l}); normalize it"),
                );
            }
        }
        c.finite("offset", &[self.offset]);
        for (p, v) in [
            ("ke", self.ke),
            ("kd", self.kd),
            ("mu", self.mu),
            ("leak", self.leak),
            ("damping_depth", self.damping_depth),
        ] {
            c.nonneg(p, v);
        }
    }
}

impl<R: Real> Default for Ground<R> {
    fn default() -> Self {
        Ground {
            normal: Vec3::new(R::lit(0.0), R::lit(1.0), R::lit(0.0)),
            offset: R::lit(0.0),
            ke: R::lit(1000.0),
            kd: R::lit(1.0),
            mu: R::lit(0.5),
            leak: R::lit(0.0),
            damp_approach: false,
            damping_depth: R::lit(1e-4),
        }
    }
}

impl<R: Real> Ground<R> {
    /// The damping out of contact the kernels get: `kd` or 0 ([`Ground::damp_approach`]).
    fn kd_free(&self) -> R {
        if self.damp_approach {
            self.kd
        } else {
            R::lit(0.0)
        }
    }

    /// Records [`eval_ground`] for particles of radius `radius` (m), accumulating into `f`.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radius: R,
        f: &Array<Vec3<R>>,
    ) {
        tape.launch(
            eval_ground,
            x.len(),
            (
                x,
                v,
                self.normal,
                self.offset,
                radius,
                self.ke,
                self.kd,
                self.kd_free(),
                self.damping_depth,
                self.mu,
                self.leak,
                f,
            ),
        );
    }
}

impl<R: Real> Ground<R> {
    /// Records [`eval_ground_radii`] for particles of radii `radii` (m), accumulating into `f`.
    pub fn eval_radii(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        radii: &Array<R>,
        f: &Array<Vec3<R>>,
    ) {
        tape.launch(
            eval_ground_radii,
            x.len(),
            (
                x,
                v,
                self.normal,
                self.offset,
                radii,
                self.ke,
                self.kd,
                self.kd_free(),
                self.damping_depth,
                self.mu,
                self.leak,
                f,
            ),
        );
    }
}

/// Ground contact of the particles. Its parameters are scalars (not differentiable), so it has
/// no parameter arrays.
impl<R: Real> Force<R> for Ground<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        match cx.particle_radii {
            Some(r) => self.eval_radii(tape, cx.x, cx.v, r, f),
            None => Ground::eval(self, tape, cx.x, cx.v, cx.particle_radius, f),
        }
    }
    /// The penalty's potential ([`ground_energy`]); damping and friction have none.
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        let (n, off, ke) = (self.normal, self.offset, self.ke);
        let w = &cx.particle_worlds();
        match cx.particle_radii {
            Some(r) => tape.launch(
                ground_energy_radii,
                cx.x.len(),
                (cx.x, n, off, r, ke, w, energy),
            ),
            None => {
                let r = cx.particle_radius;
                tape.launch(ground_energy, cx.x.len(), (cx.x, n, off, r, ke, w, energy))
            }
        }
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(Ground::<f64> {
            normal: self.normal.map(|c| c.to_f64()),
            offset: self.offset.to_f64(),
            ke: self.ke.to_f64(),
            kd: self.kd.to_f64(),
            mu: self.mu.to_f64(),
            leak: self.leak.to_f64(),
            damp_approach: self.damp_approach,
            damping_depth: self.damping_depth.to_f64(),
        }))
    }

    fn params_mut(&mut self, _visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {}
}

// ---- its scene-file section ------------------------------------------------------------

// The defaults of `Ground::default` (one source).
fn ground_ke() -> f64 {
    Ground::<f64>::default().ke
}
fn ground_kd() -> f64 {
    Ground::<f64>::default().kd
}
fn ground_damp_approach() -> bool {
    Ground::<f64>::default().damp_approach
}
fn ground_damping_depth() -> f64 {
    Ground::<f64>::default().damping_depth
}
fn ground_mu() -> f64 {
    Ground::<f64>::default().mu
}
fn up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct GroundDesc {
    #[serde(default = "up")]
    normal: [f64; 3],
    #[serde(default)]
    offset: f64,
    #[serde(default = "ground_ke")]
    ke: f64,
    #[serde(default = "ground_kd")]
    kd: f64,
    #[serde(default = "ground_mu")]
    mu: f64,
    #[serde(default)]
    leak: f64,
    #[serde(default = "ground_damp_approach")]
    damp_approach: bool,
    #[serde(default = "ground_damping_depth")]
    damping_depth: f64,
}

/// Loads the `ground` section (its normal normalized).
pub(crate) fn load<R: Real>(
    g: &GroundDesc,
    part: &mut Option<Ground<R>>,
    problems: &mut Vec<Problem>,
    c: &Checker,
) -> Result<(), SceneError> {
    c.finite(|| "ground.normal".into(), &g.normal)?;
    let nrm = Vec3::new(g.normal[0], g.normal[1], g.normal[2]);
    if !nrm.norm().is_normal() {
        return Err(c.err("ground.normal".into(), "must be a nonzero vector"));
    }
    let nrm = nrm.normalize();
    let n0 = problems.len();
    let ground = Ground {
        normal: v3([nrm.x, nrm.y, nrm.z]),
        offset: R::lit(g.offset),
        ke: R::lit(g.ke),
        kd: R::lit(g.kd),
        mu: R::lit(g.mu),
        leak: R::lit(g.leak),
        damp_approach: g.damp_approach,
        damping_depth: R::lit(g.damping_depth),
    };
    set(part, problems, ground);
    c.builder(problems, n0, |f| sub("ground", f, &[]))
}

/// Sets the ground after its checks (the builder's `set_ground` and the loader).
pub(crate) fn set<R: Real>(
    part: &mut Option<Ground<R>>,
    problems: &mut Vec<Problem>,
    ground: Ground<R>,
) {
    ground.check(&mut check_one(problems, NAME));
    *part = Some(ground);
}
