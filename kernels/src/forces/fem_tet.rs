//! Tetrahedra: the stable Neo-Hookean model of Smith, de Goes and Kim (2018), with a
//! per-element activation (muscle-like volumetric actuation, a gradient target) and damping.
//!
//! Energy density, with `F = Ds Dm^-1`, `Ic = tr(F^T F)`, `J = det F`:
//! `psi = mu/2 (Ic - 3) + lambda/2 (J - alpha + a)^2 - mu/2 ln(Ic + 1)` with
//! `alpha = 1 + 3 mu / (4 lambda)`, which makes the rest shape stress-free (dFlex uses
//! `alpha = 1 + mu / lambda`, not quite at rest); `a` is the activation: it moves the volume
//! the element rests at (`J = alpha - a` for the volumetric term; `a > 0` contracts). Forces are
//! `-V0 dpsi/dx`, plus damping `kd dF/dt` in the stress and `kd dJ/dt` in the volume term.
//! `mu`, `lambda` are the model's own parameters (Pa); [`snh_lame`] maps Young's modulus and
//! Poisson's ratio to them as in the paper.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::forces::component::{real_parts, Force, ForceContext, ForcePart, Param, ParamDoc};
use crate::particles::Elements;
use crate::scene_file::reader::{sub, Checker, SceneError};
use crate::validation::{min_quality, precision};
use serde::Deserialize;

/// The force's name ([`Force::name`]): `"tets"`.
pub const NAME: &str = "tets";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::array("dm_inv", "1/m (inverse rest shape, 3x3)"),
    ParamDoc::array("rest_volume", "m³"),
    ParamDoc::array("mu", "Pa (Lamé)"),
    ParamDoc::array("lambda", "Pa (Lamé)"),
    ParamDoc::array("kd", "Pa·s (damping)"),
    ParamDoc {
        name: "activation",
        units:
            "1 (volumetric actuation, 0 = passive; `Control::tet_activation` overrides it per step)",
        array: true,
    },
];

/// Accumulates the force of tetrahedron `tid` into `f`. `mu`, `lambda` (Pa), `kd` (Pa s),
/// `activation` (dimensionless, 0 = passive).
#[diff_kernel]
pub fn eval_tetrahedra<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    tets: &Array<[u32; 4]>,
    dm_inv: &Array<Mat33<R>>,
    rest_volume: &Array<R>,
    mu: &Array<R>,
    lambda: &Array<R>,
    kd: &Array<R>,
    activation: &Array<R>,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j, k, l] = tets[t];
    let x0 = x[i];
    let v0 = v[i];
    let x10 = x[j] - x0;
    let x20 = x[k] - x0;
    let x30 = x[l] - x0;
    let v10 = v[j] - v0;
    let v20 = v[k] - v0;
    let v30 = v[l] - v0;
    let dm = dm_inv[t];
    let ff = mat33_cols(x10, x20, x30) * dm;
    let dfdt = mat33_cols(v10, v20, v30) * dm;
    let m = mu[t];
    let la = lambda[t];
    let c = kd[t];
    let ic = ddot(ff, ff);
    let alpha = 1.0 + 0.75 * m / la;
    // Deviatoric part: P = mu F (1 - 1/(Ic + 1)) + kd dF/dt, forces -V0 P Dm^-T.
    let p = ff * (m * (1.0 - 1.0 / (ic + 1.0))) + dfdt * c;
    let h = p * transpose(dm);
    // Volumetric part: dJ/dx_a from the cross products of the edges (J = det(Ds) det(Dm^-1)).
    let s = determinant(dm);
    let dj1 = cross(x20, x30) * s;
    let dj2 = cross(x30, x10) * s;
    let dj3 = cross(x10, x20) * s;
    let jac = determinant(ff);
    let jdot = dot(dj1, v10) + dot(dj2, v20) + dot(dj3, v30);
    let fv = la * (jac - alpha + activation[t]) + c * jdot;
    let vol = rest_volume[t];
    let f1 = (h * vec3(1.0, 0.0, 0.0) + dj1 * fv) * vol;
    let f2 = (h * vec3(0.0, 1.0, 0.0) + dj2 * fv) * vol;
    let f3 = (h * vec3(0.0, 0.0, 1.0) + dj3 * fv) * vol;
    f.atomic_sub(j, f1);
    f.atomic_sub(k, f2);
    f.atomic_sub(l, f3);
    f.atomic_add(i, f1 + f2 + f3);
}

/// Elastic energy of tetrahedron `tid`, `V0 psi` (J), added to its world's `energy[world[i]]`.
#[diff_kernel]
pub fn tetrahedron_energy<R: Real>(
    x: &Array<Vec3<R>>,
    tets: &Array<[u32; 4]>,
    dm_inv: &Array<Mat33<R>>,
    rest_volume: &Array<R>,
    mu: &Array<R>,
    lambda: &Array<R>,
    activation: &Array<R>,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j, k, l] = tets[t];
    let x0 = x[i];
    let ff = mat33_cols(x[j] - x0, x[k] - x0, x[l] - x0) * dm_inv[t];
    let m = mu[t];
    let la = lambda[t];
    let ic = ddot(ff, ff);
    let alpha = 1.0 + 0.75 * m / la;
    let dj = determinant(ff) - alpha + activation[t];
    let psi = 0.5 * m * (ic - 3.0) + 0.5 * la * dj * dj - 0.5 * m * ln(ic + 1.0);
    energy.atomic_add(world[i] as usize, rest_volume[t] * psi);
}

/// The tetrahedra of a model.
#[derive(Clone, Debug)]
pub struct TetFem<R: Real> {
    /// Particle indices (positively oriented at rest).
    pub tets: Array<[u32; 4]>,
    /// Inverse rest edge matrix (1/m).
    pub dm_inv: Array<Mat33<R>>,
    /// Rest volume (m^3).
    pub rest_volume: Array<R>,
    /// Stable Neo-Hookean `mu` (Pa).
    pub mu: Array<R>,
    /// Stable Neo-Hookean `lambda` (Pa).
    pub lambda: Array<R>,
    /// Damping (Pa s).
    pub kd: Array<R>,
    /// Default activation (used when the control gives none; zeros unless set).
    pub activation: Array<R>,
}

impl<R: Real> TetFem<R> {
    /// Number of tetrahedra.
    pub fn len(&self) -> usize {
        self.tets.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.tets.is_empty()
    }

    /// Records [`eval_tetrahedra`] with `activation` (or the default), accumulating into `f`.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        activation: Option<&Array<R>>,
        f: &Array<Vec3<R>>,
    ) {
        let act = activation.unwrap_or(&self.activation);
        tape.launch(
            eval_tetrahedra,
            self.len(),
            (
                x,
                v,
                &self.tets,
                &self.dm_inv,
                &self.rest_volume,
                &self.mu,
                &self.lambda,
                &self.kd,
                act,
                f,
            ),
        );
    }

    /// Records [`tetrahedron_energy`], adding into `energy[world[i]]`
    /// (`world`: each particle's world).
    pub fn energy(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        activation: Option<&Array<R>>,
        world: &Array<u32>,
        energy: &Array<R>,
    ) {
        let act = activation.unwrap_or(&self.activation);
        tape.launch(
            tetrahedron_energy,
            self.len(),
            (
                x,
                &self.tets,
                &self.dm_inv,
                &self.rest_volume,
                &self.mu,
                &self.lambda,
                act,
                world,
                energy,
            ),
        );
    }
}

/// Stable Neo-Hookean parameters `(mu, lambda)` (Pa) for Young's modulus `young` (Pa) and
/// Poisson's ratio `poisson`: the Lame parameters reparametrized as in Smith et al. 2018
/// (sec. 3.4), `mu' = 4/3 mu`, `lambda' = lambda + 5/6 mu`, so that small deformations match
/// linear elasticity.
pub fn snh_lame(young: f64, poisson: f64) -> (f64, f64) {
    let mu = young / (2.0 * (1.0 + poisson));
    let lambda = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson));
    (4.0 / 3.0 * mu, lambda + 5.0 / 6.0 * mu)
}

/// Shape quality of a tetrahedron: `6 sqrt(2) |volume| / l^3` with `l` the root mean square of
/// its six edge lengths, 1 for a regular tetrahedron, 0 for a flat one (scale-free).
pub fn tet_quality(p: [Vec3<f64>; 4]) -> f64 {
    let vol = Mat33::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]).determinant() / 6.0;
    let mut l2 = 0.0;
    for a in 0..4 {
        for b in a + 1..4 {
            l2 += (p[b] - p[a]).norm_squared();
        }
    }
    let l = (l2 / 6.0).sqrt();
    6.0 * 2f64.sqrt() * vol.abs() / (l * l * l)
}

/// Rest data of a tetrahedron with corners `p` (m): the inverse rest edge matrix and the rest
/// volume, which is negative if the corners are negatively oriented. `None` if degenerate.
pub fn tet_rest(p: [Vec3<f64>; 4]) -> Option<(Mat33<f64>, f64)> {
    let dm = Mat33::from_columns(&[p[1] - p[0], p[2] - p[0], p[3] - p[0]]);
    let vol = dm.determinant() / 6.0;
    if vol == 0.0 || !vol.is_finite() {
        return None;
    }
    Some((dm.try_inverse()?, vol))
}

impl<R: Real> Force<R> for TetFem<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    /// Reads the control's `tet_activation` if it has one, else [`TetFem::activation`].
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        let act = cx.control.and_then(|c| c.tet_activation.as_ref());
        TetFem::eval(self, tape, cx.x, cx.v, act, f);
    }
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        let act = cx.control.and_then(|c| c.tet_activation.as_ref());
        TetFem::energy(self, tape, cx.x, act, &cx.particle_worlds(), energy);
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(TetFem::<f64> {
            tets: self.tets.clone(),
            dm_inv: real_parts(&self.dm_inv),
            rest_volume: real_parts(&self.rest_volume),
            mu: real_parts(&self.mu),
            lambda: real_parts(&self.lambda),
            kd: real_parts(&self.kd),
            activation: real_parts(&self.activation),
        }))
    }

    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("dm_inv", &mut self.dm_inv);
        visit("rest_volume", &mut self.rest_volume);
        visit("mu", &mut self.mu);
        visit("lambda", &mut self.lambda);
        visit("kd", &mut self.kd);
        visit("activation", &mut self.activation);
    }
}

/// The tetrahedra of a scene description (see
/// [`ModelBuilder::add_tet`](crate::ModelBuilder::add_tet)).
#[derive(Clone, Debug)]
pub(crate) struct TetParts<R: Real> {
    tets: Vec<[u32; 4]>,
    dm_inv: Vec<Mat33<R>>,
    volume: Vec<R>,
    mu: Vec<R>,
    lambda: Vec<R>,
    kd: Vec<R>,
}

impl<R: Real> Default for TetParts<R> {
    fn default() -> Self {
        TetParts {
            tets: Vec::new(),
            dm_inv: Vec::new(),
            volume: Vec::new(),
            mu: Vec::new(),
            lambda: Vec::new(),
            kd: Vec::new(),
        }
    }
}

fn lit<R: Real>(x: f64) -> R {
    R::lit(x)
}

impl<R: Real> TetParts<R> {
    pub(crate) fn len(&self) -> usize {
        self.tets.len()
    }

    /// A tetrahedron with its rest shape from the current positions (reoriented if negative),
    /// checked not degenerate.
    pub(crate) fn add(
        &mut self,
        el: &mut Elements<'_, R>,
        [i, j, k, l]: [u32; 4],
        mu: R,
        lambda: R,
        kd: R,
    ) -> u32 {
        let e = self.tets.len();
        let mut idx = [i, j, k, l];
        let (mut dm_inv, mut vol) = (Mat33::identity(), 1.0);
        if el.distinct("tets", e, &idx) {
            let p = |i: u32| el.particles.wide(i);
            let what = format!("the tetrahedron on particles ({i}, {j}, {k}, {l})");
            match tet_rest([p(i), p(j), p(k), p(l)]) {
                None => el.check("tets", e).fail(
                    None,
                    format!(
                        "{what} is degenerate (zero or non-finite volume); move a vertex off \
                         the plane of the other three or remove it"
                    ),
                ),
                Some(r) => {
                    (dm_inv, vol) = r;
                    if vol < 0.0 {
                        idx = [i, k, j, l];
                        (dm_inv, vol) =
                            tet_rest([p(i), p(k), p(j), p(l)]).expect("reoriented tetrahedron");
                    }
                    let q = tet_quality([p(i), p(j), p(k), p(l)]);
                    let finite = dm_inv.iter().all(|v| lit::<R>(*v).to_f64().is_finite());
                    let mut c = el.check("tets", e);
                    if q < min_quality::<R>() {
                        c.fail(
                            None,
                            format!(
                                "{what} is nearly degenerate (flat): quality {q:.1e} (1 for a \
                             regular tetrahedron) is below {:.1e} in {}; move a vertex off the \
                             plane of the other three or remove it",
                                min_quality::<R>(),
                                precision::<R>()
                            ),
                        );
                    } else if !finite
                        || lit::<R>(vol).to_f64().partial_cmp(&R::tiny().to_f64())
                            != Some(std::cmp::Ordering::Greater)
                    {
                        c.fail(
                            None,
                            format!(
                                "{what} is too small or too large for {} (volume {vol:e} m^3, \
                             rest-shape inverse not finite or volume below {:e}); rescale the \
                             scene",
                                precision::<R>(),
                                R::tiny().to_f64()
                            ),
                        );
                    }
                }
            }
        }
        let mut c = el.check("tets", e);
        c.nonneg("mu", mu);
        c.positive("lambda", lambda);
        c.nonneg("kd", kd);
        self.tets.push(idx);
        self.dm_inv.push(dm_inv.map(lit));
        self.volume.push(lit(vol));
        self.mu.push(mu);
        self.lambda.push(lambda);
        self.kd.push(kd);
        (self.tets.len() - 1) as u32
    }
}

impl<R: Real> ForcePart<R> for TetParts<R> {
    fn spanning_worlds(&self, world_of: &[u32]) -> Option<(usize, Vec<u32>)> {
        super::component::first_spanning(&self.tets, world_of)
    }

    fn append(&mut self, other: &Self, offset: u32) -> Result<(), String> {
        self.tets
            .extend(super::component::shifted(&other.tets, offset));
        self.dm_inv.extend(&other.dm_inv);
        self.volume.extend(&other.volume);
        self.mu.extend(&other.mu);
        self.lambda.extend(&other.lambda);
        self.kd.extend(&other.kd);
        Ok(())
    }

    fn worlds_in(&self, particles: &std::ops::Range<u32>) -> Self {
        use super::component::{elements_in, pick};
        let (idx, tets) = elements_in(&self.tets, particles);
        TetParts {
            tets,
            dm_inv: pick(&self.dm_inv, &idx),
            volume: pick(&self.volume, &idx),
            mu: pick(&self.mu, &idx),
            lambda: pick(&self.lambda, &idx),
            kd: pick(&self.kd, &idx),
        }
    }

    fn build(&self) -> Option<Box<dyn Force<R>>> {
        (!self.tets.is_empty()).then(|| {
            Box::new(TetFem {
                tets: Array::from_vec(self.tets.clone()).named("tet_indices"),
                dm_inv: Array::from_vec(self.dm_inv.clone()).named("tet_dm_inv"),
                rest_volume: Array::from_vec(self.volume.clone()).named("tet_volume"),
                mu: Array::from_vec(self.mu.clone()).named("tet_mu"),
                lambda: Array::from_vec(self.lambda.clone()).named("tet_lambda"),
                kd: Array::from_vec(self.kd.clone()).named("tet_kd"),
                activation: Array::zeros(self.tets.len()).named("tet_activation"),
            }) as Box<dyn Force<R>>
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct TetDesc {
    indices: [u32; 4],
    mu: Option<f64>,
    lambda: Option<f64>,
    young: Option<f64>,
    poisson: Option<f64>,
    #[serde(default)]
    kd: f64,
}

/// Loads the `tets` section (Lame parameters or Young's modulus and Poisson's ratio).
pub(crate) fn load<R: Real>(
    d: &[TetDesc],
    part: &mut TetParts<R>,
    el: &mut Elements<'_, R>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, t) in d.iter().enumerate() {
        let path = |f: &str| format!("tets[{k}].{f}");
        let (mu, lambda) = match (t.mu, t.lambda, t.young, t.poisson) {
            (Some(mu), Some(lambda), None, None) => (mu, lambda),
            (None, None, Some(e), Some(nu)) => {
                c.positive(|| path("young"), e)?;
                if !(nu > -1.0 && nu < 0.5) {
                    return Err(c.err(path("poisson"), format!("must be in (-1, 0.5) (got {nu})")));
                }
                snh_lame(e, nu)
            }
            _ => {
                return Err(c.err(
                    format!("tets[{k}]"),
                    "give either `mu` and `lambda`, or `young` and `poisson`",
                ))
            }
        };
        let n0 = el.problems.len();
        part.add(el, t.indices, R::lit(mu), R::lit(lambda), R::lit(t.kd));
        c.builder(el.problems, n0, |f| sub(&format!("tets[{k}]"), f, &[]))?;
    }
    Ok(())
}
