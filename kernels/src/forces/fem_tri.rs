//! Triangle membranes: St. Venant-Kirchhoff on the 2D Green strain of each triangle, with
//! viscous damping of the strain rate.
//!
//! Each triangle keeps the inverse of its rest edge matrix `Dm` (2x2, in a frame of its rest
//! plane) and its rest area `A`. With `e1 = x_j - x_i`, `e2 = x_k - x_i`, the deformation
//! gradient is the 3x2 matrix `F = [e1 e2] Dm^-1` (held as its two columns), the Green strain
//! `E = (F^T F - I) / 2`, the energy `A (mu E:E + lambda/2 tr(E)^2)`, the second Piola stress
//! `S = 2 mu E + lambda tr(E) I + kd dE/dt`, and the forces `-A F S Dm^-T`.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::forces::component::{real_parts, Force, ForceContext, ForcePart, Param, ParamDoc};
use crate::particles::Elements;
use crate::particles::Particles;
use crate::scene_file::reader::{sub, Checker, SceneError};
use crate::validation::Problem;
use crate::validation::{min_quality, precision};
use serde::Deserialize;

/// The force's name ([`Force::name`]): `"triangle_fem"`.
pub const NAME: &str = "triangle_fem";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::array("dm_inv", "1/m (inverse rest shape, 2x2)"),
    ParamDoc::array("area", "m² (rest area)"),
    ParamDoc::array("mu", "Pa·m (Lamé, membrane)"),
    ParamDoc::array("lambda", "Pa·m (Lamé, membrane)"),
    ParamDoc::array("kd", "Pa·m·s (damping)"),
];

/// Accumulates the membrane force of triangle `tid` into `f`. `mu`, `lambda` (Pa m, i.e.
/// N/m: 2D Lame parameters), `kd` (N s/m: strain-rate damping).
#[diff_kernel]
pub fn eval_triangles<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    tris: &Array<[u32; 3]>,
    dm_inv: &Array<Mat22<R>>,
    area: &Array<R>,
    mu: &Array<R>,
    lambda: &Array<R>,
    kd: &Array<R>,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j, k] = tris[t];
    let e1 = x[j] - x[i];
    let e2 = x[k] - x[i];
    let u1 = v[j] - v[i];
    let u2 = v[k] - v[i];
    let d = dm_inv[t];
    let d00 = d[(0, 0)];
    let d01 = d[(0, 1)];
    let d10 = d[(1, 0)];
    let d11 = d[(1, 1)];
    // Columns of F and of dF/dt.
    let f1 = e1 * d00 + e2 * d10;
    let f2 = e1 * d01 + e2 * d11;
    let g1 = u1 * d00 + u2 * d10;
    let g2 = u1 * d01 + u2 * d11;
    let e00 = 0.5 * (dot(f1, f1) - 1.0);
    let e11 = 0.5 * (dot(f2, f2) - 1.0);
    let e01 = 0.5 * dot(f1, f2);
    let r00 = dot(f1, g1);
    let r11 = dot(f2, g2);
    let r01 = 0.5 * (dot(f1, g2) + dot(g1, f2));
    let m = mu[t];
    let la = lambda[t];
    let c = kd[t];
    let tr = e00 + e11;
    let s00 = 2.0 * m * e00 + la * tr + c * r00;
    let s11 = 2.0 * m * e11 + la * tr + c * r11;
    let s01 = 2.0 * m * e01 + c * r01;
    // P = F S (columns), forces on j and k: -A P Dm^-T.
    let p1 = f1 * s00 + f2 * s01;
    let p2 = f1 * s01 + f2 * s11;
    let a = area[t];
    let fj = (p1 * d00 + p2 * d01) * a;
    let fk = (p1 * d10 + p2 * d11) * a;
    f.atomic_sub(j, fj);
    f.atomic_sub(k, fk);
    f.atomic_add(i, fj + fk);
}

/// Elastic energy of triangle `tid`, `A (mu E:E + lambda/2 tr(E)^2)` (J), added to
/// its world's `energy[world[i]]`.
#[diff_kernel]
pub fn triangle_energy<R: Real>(
    x: &Array<Vec3<R>>,
    tris: &Array<[u32; 3]>,
    dm_inv: &Array<Mat22<R>>,
    area: &Array<R>,
    mu: &Array<R>,
    lambda: &Array<R>,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j, k] = tris[t];
    let e1 = x[j] - x[i];
    let e2 = x[k] - x[i];
    let d = dm_inv[t];
    let f1 = e1 * d[(0, 0)] + e2 * d[(1, 0)];
    let f2 = e1 * d[(0, 1)] + e2 * d[(1, 1)];
    let e00 = 0.5 * (dot(f1, f1) - 1.0);
    let e11 = 0.5 * (dot(f2, f2) - 1.0);
    let e01 = 0.5 * dot(f1, f2);
    let tr = e00 + e11;
    let psi = mu[t] * (e00 * e00 + e11 * e11 + 2.0 * e01 * e01) + 0.5 * lambda[t] * tr * tr;
    energy.atomic_add(world[i] as usize, area[t] * psi);
}

/// The FEM triangles of a model.
#[derive(Clone, Debug)]
pub struct TriangleFem<R: Real> {
    /// Particle indices.
    pub tris: Array<[u32; 3]>,
    /// Inverse rest edge matrix (1/m).
    pub dm_inv: Array<Mat22<R>>,
    /// Rest area (m^2).
    pub area: Array<R>,
    /// First Lame parameter of the membrane (N/m).
    pub mu: Array<R>,
    /// Second Lame parameter of the membrane (N/m).
    pub lambda: Array<R>,
    /// Strain-rate damping (N s/m).
    pub kd: Array<R>,
}

impl<R: Real> TriangleFem<R> {
    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.tris.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.tris.is_empty()
    }

    /// Records [`eval_triangles`], accumulating into `f`.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        f: &Array<Vec3<R>>,
    ) {
        tape.launch(
            eval_triangles,
            self.len(),
            (
                x,
                v,
                &self.tris,
                &self.dm_inv,
                &self.area,
                &self.mu,
                &self.lambda,
                &self.kd,
                f,
            ),
        );
    }

    /// Records [`triangle_energy`], adding into `energy[world[i]]`
    /// (`world`: each particle's world).
    pub fn energy(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        world: &Array<u32>,
        energy: &Array<R>,
    ) {
        tape.launch(
            triangle_energy,
            self.len(),
            (
                x,
                &self.tris,
                &self.dm_inv,
                &self.area,
                &self.mu,
                &self.lambda,
                world,
                energy,
            ),
        );
    }
}

/// Shape quality of a triangle: `4 sqrt(3) area / (sum of squared edge lengths)`, 1 for an
/// equilateral triangle, 0 for a degenerate one (scale-free).
pub fn triangle_quality(p0: Vec3<f64>, p1: Vec3<f64>, p2: Vec3<f64>) -> f64 {
    let area = 0.5 * (p1 - p0).cross(&(p2 - p0)).norm();
    let l2 = (p1 - p0).norm_squared() + (p2 - p1).norm_squared() + (p0 - p2).norm_squared();
    4.0 * 3f64.sqrt() * area / l2
}

/// Rest data of a triangle with corners `p0, p1, p2` (m): the inverse of its edge matrix in an
/// orthonormal frame of its plane (first axis along `p1 - p0`) and its area. `None` if the
/// triangle is degenerate (zero area).
pub fn triangle_rest(p0: Vec3<f64>, p1: Vec3<f64>, p2: Vec3<f64>) -> Option<(Mat22<f64>, f64)> {
    let (e1, e2) = (p1 - p0, p2 - p0);
    let n = e1.cross(&e2);
    let area = 0.5 * n.norm();
    if area <= 0.0 || !area.is_finite() {
        return None;
    }
    let u = e1.normalize();
    let w = n.cross(&e1).normalize();
    let dm = Mat22::new(e1.dot(&u), e2.dot(&u), e1.dot(&w), e2.dot(&w));
    Some((dm.try_inverse()?, area))
}

impl<R: Real> Force<R> for TriangleFem<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        TriangleFem::eval(self, tape, cx.x, cx.v, f);
    }
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        TriangleFem::energy(self, tape, cx.x, &cx.particle_worlds(), energy);
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(TriangleFem::<f64> {
            tris: self.tris.clone(),
            dm_inv: real_parts(&self.dm_inv),
            area: real_parts(&self.area),
            mu: real_parts(&self.mu),
            lambda: real_parts(&self.lambda),
            kd: real_parts(&self.kd),
        }))
    }

    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("dm_inv", &mut self.dm_inv);
        visit("area", &mut self.area);
        visit("mu", &mut self.mu);
        visit("lambda", &mut self.lambda);
        visit("kd", &mut self.kd);
    }
}

/// The membrane triangles of a scene description (see
/// [`ModelBuilder::add_triangle_fem`](crate::ModelBuilder::add_triangle_fem)).
#[derive(Clone, Debug)]
pub(crate) struct TriangleParts<R: Real> {
    tris: Vec<[u32; 3]>,
    dm_inv: Vec<Mat22<R>>,
    area: Vec<R>,
    mu: Vec<R>,
    lambda: Vec<R>,
    kd: Vec<R>,
}

impl<R: Real> Default for TriangleParts<R> {
    fn default() -> Self {
        TriangleParts {
            tris: Vec::new(),
            dm_inv: Vec::new(),
            area: Vec::new(),
            mu: Vec::new(),
            lambda: Vec::new(),
            kd: Vec::new(),
        }
    }
}

fn lit<R: Real>(x: f64) -> R {
    R::lit(x)
}

impl<R: Real> TriangleParts<R> {
    /// A membrane triangle with its rest shape from the current positions, checked not
    /// degenerate.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn add(
        &mut self,
        el: &mut Elements<'_, R>,
        i: u32,
        j: u32,
        k: u32,
        mu: R,
        lambda: R,
        kd: R,
    ) -> u32 {
        let e = self.tris.len();
        let ok = el.distinct("triangle_fem", e, &[i, j, k]);
        let (dm_inv, area) =
            if ok {
                let p = |i: u32| el.particles.wide(i);
                let (a, b, c) = (p(i), p(j), p(k));
                match triangle_rest(a, b, c) {
                    Some((dm_inv, area)) => {
                        let dm_inv = dm_inv.map(lit::<R>);
                        let q = triangle_quality(a, b, c);
                        let what = format!("the triangle on particles ({i}, {j}, {k})");
                        let mut c = el.check("triangle_fem", e);
                        if q < min_quality::<R>() {
                            c.fail(
                                None,
                                format!(
                            "{what} is nearly degenerate (flat): quality {q:.1e} (1 for an \
                             equilateral triangle) is below {:.1e} in {}; move its vertices \
                             apart or remove it",
                            min_quality::<R>(), precision::<R>()),
                            );
                        } else if !dm_inv.iter().all(|v| v.to_f64().is_finite())
                            || lit::<R>(area).to_f64().partial_cmp(&R::tiny().to_f64())
                                != Some(std::cmp::Ordering::Greater)
                        {
                            c.fail(
                                None,
                                format!(
                                    "{what} is too small or too large for {} (area {area:e} m^2, \
                             rest-shape inverse not finite or area below {:e}); rescale the scene",
                                    precision::<R>(),
                                    R::tiny().to_f64()
                                ),
                            );
                        }
                        (dm_inv, lit(area))
                    }
                    None => {
                        el.check("triangle_fem", e).fail(
                            None,
                            format!(
                                "the triangle on particles ({i}, {j}, {k}) is degenerate (zero or \
                             non-finite area); move its vertices apart or remove it"
                            ),
                        );
                        (Mat22::identity(), lit(1.0))
                    }
                }
            } else {
                (Mat22::identity(), lit(1.0))
            };
        let mut c = el.check("triangle_fem", e);
        c.nonneg("mu", mu);
        c.finite("lambda", &[lambda]);
        c.nonneg("kd", kd);
        self.tris.push([i, j, k]);
        self.dm_inv.push(dm_inv);
        self.area.push(area);
        self.mu.push(mu);
        self.lambda.push(lambda);
        self.kd.push(kd);
        (self.tris.len() - 1) as u32
    }
}

impl<R: Real> ForcePart<R> for TriangleParts<R> {
    fn spanning_worlds(&self, world_of: &[u32]) -> Option<(usize, Vec<u32>)> {
        super::component::first_spanning(&self.tris, world_of)
    }

    fn append(&mut self, other: &Self, offset: u32) -> Result<(), String> {
        self.tris
            .extend(super::component::shifted(&other.tris, offset));
        self.dm_inv.extend(&other.dm_inv);
        self.area.extend(&other.area);
        self.mu.extend(&other.mu);
        self.lambda.extend(&other.lambda);
        self.kd.extend(&other.kd);
        Ok(())
    }

    fn worlds_in(&self, particles: &std::ops::Range<u32>) -> Self {
        use super::component::{elements_in, pick};
        let (idx, tris) = elements_in(&self.tris, particles);
        TriangleParts {
            tris,
            dm_inv: pick(&self.dm_inv, &idx),
            area: pick(&self.area, &idx),
            mu: pick(&self.mu, &idx),
            lambda: pick(&self.lambda, &idx),
            kd: pick(&self.kd, &idx),
        }
    }

    fn build(&self) -> Option<Box<dyn Force<R>>> {
        (!self.tris.is_empty()).then(|| {
            Box::new(TriangleFem {
                tris: Array::from_vec(self.tris.clone()).named("tri_indices"),
                dm_inv: Array::from_vec(self.dm_inv.clone()).named("tri_dm_inv"),
                area: Array::from_vec(self.area.clone()).named("tri_area"),
                mu: Array::from_vec(self.mu.clone()).named("tri_mu"),
                lambda: Array::from_vec(self.lambda.clone()).named("tri_lambda"),
                kd: Array::from_vec(self.kd.clone()).named("tri_kd"),
            }) as Box<dyn Force<R>>
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct TriangleDesc {
    indices: [u32; 3],
    mu: Option<f64>,
    lambda: Option<f64>,
    #[serde(default)]
    kd: f64,
}

/// Adds a membrane triangle (`[mu, lambda, kd]`), which is also a surface triangle of the
/// topology (the builder's `add_triangle_fem` and the loader).
pub(crate) fn add_membrane<R: Real>(
    part: &mut TriangleParts<R>,
    particles: &mut Particles<R>,
    problems: &mut Vec<Problem>,
    [i, j, k]: [u32; 3],
    [mu, lambda, kd]: [R; 3],
) -> u32 {
    let mut el = Elements {
        particles,
        problems,
    };
    let e = part.add(&mut el, i, j, k, mu, lambda, kd);
    particles.triangles.push([i, j, k]);
    e
}

/// Loads the `triangles` section: membranes (with `mu` and `lambda`) and topology.
pub(crate) fn load<R: Real>(
    d: &[TriangleDesc],
    part: &mut TriangleParts<R>,
    particles: &mut Particles<R>,
    problems: &mut Vec<Problem>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, t) in d.iter().enumerate() {
        let [i, j, l] = t.indices;
        let n0 = problems.len();
        match (t.mu, t.lambda) {
            (Some(mu), Some(lambda)) => {
                let params = [R::lit(mu), R::lit(lambda), R::lit(t.kd)];
                add_membrane(part, particles, problems, [i, j, l], params);
            }
            (None, None) => {
                particles.add_triangle(problems, [i, j, l]);
            }
            (Some(_), None) => {
                return Err(c.err(
                    format!("triangles[{k}]"),
                    "`mu` without `lambda`: a membrane needs both",
                ))
            }
            (None, Some(_)) => {
                return Err(c.err(
                    format!("triangles[{k}]"),
                    "`lambda` without `mu`: a membrane needs both",
                ))
            }
        }
        c.builder(problems, n0, |f| sub(&format!("triangles[{k}]"), f, &[]))?;
    }
    Ok(())
}
