//! Dihedral bending between pairs of triangles sharing an edge: dFlex's bending force, that
//! of `eval_bending` in NVIDIA Warp (Bridson et al. 2003 style gradients of the dihedral
//! angle), with the angle computed by `atan2` (full precision near flat, where Warp's `acos`
//! has an error of `sqrt(eps)` rad).

use std::collections::HashMap;

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::forces::component::{real_parts, Force, ForceContext, ForcePart, Param, ParamDoc};
use crate::particles::Elements;
use crate::scene_file::reader::{sub, Checker, SceneError};
use serde::Deserialize;

/// The force's name ([`Force::name`]): `"bending"`.
pub const NAME: &str = "bending";

/// The force's rows of the guide's parameter table (see [`ParamDoc`]).
pub const PARAMS: &[ParamDoc] = &[
    ParamDoc::array("rest", "rad (rest dihedral angle)"),
    ParamDoc::array("ke", "N·m/rad"),
    ParamDoc::array("kd", "N·m·s/rad"),
];

/// Accumulates the bending force of element `tid` into `f`.
///
/// Element `(i, j, k, l)`: `i`, `j` the vertices opposite the shared edge, `k`, `l` the edge.
/// The angle is `atan2(sin_theta, cos_theta)` of the triangles' normals `n1`, `n2` and the
/// unit edge `e_hat`, `sin_theta = dot(cross(n2, n1), e_hat) / (|n1| |n2|)` (Warp's
/// `acos(clamp(cos_theta, -1, 1))` signed by the sine, without its round-off near flat);
/// `ke` (N m/rad) and `kd` (N m s/rad) are the stiffness and damping, `rest` (rad) the rest
/// angle. An element with a degenerate triangle (zero normal) exerts no force.
#[diff_kernel]
pub fn eval_bending<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    quads: &Array<[u32; 4]>,
    rest: &Array<R>,
    ke: &Array<R>,
    kd: &Array<R>,
    f: &Array<Vec3<R>>,
) {
    let t = tid();
    let [i, j, k, l] = quads[t];
    let x1 = x[i];
    let x2 = x[j];
    let x3 = x[k];
    let x4 = x[l];
    let n1 = cross(x3 - x1, x4 - x1);
    let n2 = cross(x4 - x2, x3 - x2);
    let n1_length = length(n1);
    let n2_length = length(n2);
    if n1_length <= 0.0 || n2_length <= 0.0 {
        return;
    }
    let rcp_n1 = 1.0 / n1_length;
    let rcp_n2 = 1.0 / n2_length;
    let m1 = n1 * rcp_n1 * rcp_n1;
    let m2 = n2 * rcp_n2 * rcp_n2;
    let e = x4 - x3;
    let e_hat = normalize(e);
    let e_length = length(e);
    // atan2 of the sine and cosine, both to full relative precision: acos of the cosine
    // (Warp's form) loses half the digits near a flat angle (an error of sqrt(eps) rad).
    let cos_theta = dot(n1, n2) * rcp_n1 * rcp_n2;
    let sin_theta = dot(cross(n2, n1), e_hat) * rcp_n1 * rcp_n2;
    let angle = atan2(sin_theta, cos_theta);
    let d1 = m1 * e_length;
    let d2 = m2 * e_length;
    let d3 = m1 * dot(x1 - x4, e_hat) + m2 * dot(x2 - x4, e_hat);
    let d4 = m1 * dot(x3 - x1, e_hat) + m2 * dot(x3 - x2, e_hat);
    let f_elastic = ke[t] * (angle - rest[t]);
    let f_damp = kd[t] * (dot(d1, v[i]) + dot(d2, v[j]) + dot(d3, v[k]) + dot(d4, v[l]));
    let f_total = 0.0 - e_length * (f_elastic + f_damp);
    f.atomic_add(i, d1 * f_total);
    f.atomic_add(j, d2 * f_total);
    f.atomic_add(k, d3 * f_total);
    f.atomic_add(l, d4 * f_total);
}

/// Bending energy of element `tid`, `ke/2 |e| (angle - rest)^2` (J) with `|e|` the shared edge's
/// length, added to its world's `energy[world[i]]`: the discrete-shells energy whose gradient is
/// [`eval_bending`]'s elastic force up to the edge length's own variation, which dFlex's force
/// leaves out (the difference, `ke/2 (angle - rest)^2 d|e|/dx`, is second order in the bend). A
/// degenerate element has no energy, as it has no force.
#[diff_kernel]
pub fn bending_energy<R: Real>(
    x: &Array<Vec3<R>>,
    quads: &Array<[u32; 4]>,
    rest: &Array<R>,
    ke: &Array<R>,
    world: &Array<u32>,
    energy: &Array<R>,
) {
    let t = tid();
    let [i, j, k, l] = quads[t];
    let x1 = x[i];
    let x2 = x[j];
    let x3 = x[k];
    let x4 = x[l];
    let n1 = cross(x3 - x1, x4 - x1);
    let n2 = cross(x4 - x2, x3 - x2);
    let n1_length = length(n1);
    let n2_length = length(n2);
    if n1_length <= 0.0 || n2_length <= 0.0 {
        return;
    }
    let e = x4 - x3;
    let e_hat = normalize(e);
    let rcp = 1.0 / (n1_length * n2_length);
    let angle = atan2(dot(cross(n2, n1), e_hat) * rcp, dot(n1, n2) * rcp);
    let c = angle - rest[t];
    energy.atomic_add(world[i] as usize, 0.5 * ke[t] * length(e) * c * c);
}

/// The bending elements of a model.
#[derive(Clone, Debug)]
pub struct Bending<R: Real> {
    /// `(o1, o2, e0, e1)`: the two opposite vertices, then the shared edge.
    pub quads: Array<[u32; 4]>,
    /// Rest angle (rad).
    pub rest: Array<R>,
    /// Stiffness (N m/rad).
    pub ke: Array<R>,
    /// Damping (N m s/rad).
    pub kd: Array<R>,
}

impl<R: Real> Bending<R> {
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.quads.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.quads.is_empty()
    }

    /// Records [`eval_bending`] on `tape`, accumulating into `f`.
    pub fn eval(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        v: &Array<Vec3<R>>,
        f: &Array<Vec3<R>>,
    ) {
        tape.launch(
            eval_bending,
            self.len(),
            (x, v, &self.quads, &self.rest, &self.ke, &self.kd, f),
        );
    }

    /// Records [`bending_energy`] on `tape`, adding into `energy[world[i]]`
    /// (`world`: each particle's world).
    pub fn energy(
        &self,
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        world: &Array<u32>,
        energy: &Array<R>,
    ) {
        tape.launch(
            bending_energy,
            self.len(),
            (x, &self.quads, &self.rest, &self.ke, world, energy),
        );
    }
}

/// The rest angle given to new bending elements.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RestAngle {
    /// Zero: the rest shape is flat (the `cloth` benchmark scene).
    #[default]
    Flat,
    /// The dihedral angle of the initial positions.
    Initial,
}

/// Every edge shared by two triangles, as `(o1, o2, e0, e1)`, in the order of dFlex and of
/// `warp_cloth_scene.py`: edges in order of first appearance (triangle by triangle, edges
/// `(t0,t1)`, `(t1,t2)`, `(t2,t0)`), the edge's vertices in the orientation of the first
/// triangle that has it, `o1` opposite in that triangle. Edges on one triangle only (the
/// boundary) and on more than two (non-manifold) get no element.
pub fn bending_edges(triangles: &[[u32; 3]]) -> Vec<[u32; 4]> {
    // (first-seen order, [(opposite, u, w)]) per undirected edge
    let mut order: Vec<(u32, u32)> = Vec::new();
    let mut map: HashMap<(u32, u32), Vec<[u32; 3]>> = HashMap::new();
    for t in triangles {
        for e in 0..3 {
            let (u, w, o) = (t[e], t[(e + 1) % 3], t[(e + 2) % 3]);
            let key = (u.min(w), u.max(w));
            let list = map.entry(key).or_insert_with(|| {
                order.push(key);
                Vec::new()
            });
            list.push([o, u, w]);
        }
    }
    order
        .iter()
        .filter_map(|key| {
            let l = &map[key];
            (l.len() == 2).then(|| [l[0][0], l[1][0], l[0][1], l[0][2]])
        })
        .collect()
}

/// The dihedral angle of element `(o1, o2, e0, e1)` at positions `x`, as [`eval_bending`]
/// computes it (in f64 on the host; rad).
pub fn dihedral_angle(x: &[Vec3<f64>], q: [u32; 4]) -> f64 {
    let [x1, x2, x3, x4] = q.map(|i| x[i as usize]);
    let n1 = (x3 - x1).cross(&(x4 - x1));
    let n2 = (x4 - x2).cross(&(x3 - x2));
    let (l1, l2) = (n1.norm(), n2.norm());
    if l1 == 0.0 || l2 == 0.0 {
        return 0.0;
    }
    let c = (n1.dot(&n2) / (l1 * l2)).clamp(-1.0, 1.0);
    let e = (x4 - x3).normalize();
    let s = if n2.cross(&n1).dot(&e) < 0.0 {
        -1.0
    } else {
        1.0
    };
    c.acos() * s
}

impl<R: Real> Force<R> for Bending<R> {
    fn name(&self) -> &'static str {
        NAME
    }
    fn eval(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, f: &Array<Vec3<R>>) {
        Bending::eval(self, tape, cx.x, cx.v, f);
    }
    fn energy(&self, cx: &ForceContext<'_, R>, tape: &mut Tape, energy: &Array<R>) -> bool {
        Bending::energy(self, tape, cx.x, &cx.particle_worlds(), energy);
        true
    }
    fn to_f64(&self) -> Option<Box<dyn Force<f64>>> {
        Some(Box::new(Bending::<f64> {
            quads: self.quads.clone(),
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

/// The bending elements of a scene description (see
/// [`ModelBuilder::add_bending`](crate::ModelBuilder::add_bending)).
#[derive(Clone, Debug)]
pub(crate) struct BendingParts<R: Real> {
    quads: Vec<[u32; 4]>,
    rest: Vec<R>,
    ke: Vec<R>,
    kd: Vec<R>,
}

impl<R: Real> Default for BendingParts<R> {
    fn default() -> Self {
        BendingParts {
            quads: Vec::new(),
            rest: Vec::new(),
            ke: Vec::new(),
            kd: Vec::new(),
        }
    }
}

impl<R: Real> BendingParts<R> {
    pub(crate) fn add(
        &mut self,
        el: &mut Elements<'_, R>,
        quad: [u32; 4],
        rest: R,
        ke: R,
        kd: R,
    ) -> u32 {
        let k = self.quads.len();
        el.distinct("bending", k, &quad);
        let mut c = el.check("bending", k);
        c.finite("rest", &[rest]);
        c.nonneg("ke", ke);
        c.nonneg("kd", kd);
        self.quads.push(quad);
        self.rest.push(rest);
        self.ke.push(ke);
        self.kd.push(kd);
        (self.quads.len() - 1) as u32
    }

    /// An element on every edge shared by two of `triangles`; returns how many.
    pub(crate) fn add_edges(
        &mut self,
        el: &mut Elements<'_, R>,
        triangles: &[[u32; 3]],
        ke: R,
        kd: R,
        rest: RestAngle,
    ) -> usize {
        // A triangle added twice (e.g. a cloth grid's triangles given again as membranes)
        // is one face: its copies would pair into quads with a repeated particle.
        let mut seen = std::collections::HashSet::new();
        let faces: Vec<[u32; 3]> = triangles
            .iter()
            .filter(|t| {
                let mut key = **t;
                key.sort_unstable();
                seen.insert(key)
            })
            .copied()
            .collect();
        let quads = bending_edges(&faces);
        let xs = el.particles.wide_all();
        for &q in &quads {
            let angle = match rest {
                RestAngle::Flat => 0.0,
                RestAngle::Initial => dihedral_angle(&xs, q),
            };
            self.add(el, q, R::lit(angle), ke, kd);
        }
        quads.len()
    }
}

impl<R: Real> ForcePart<R> for BendingParts<R> {
    fn spanning_worlds(&self, world_of: &[u32]) -> Option<(usize, Vec<u32>)> {
        super::component::first_spanning(&self.quads, world_of)
    }

    fn append(&mut self, other: &Self, offset: u32) -> Result<(), String> {
        self.quads
            .extend(super::component::shifted(&other.quads, offset));
        self.rest.extend(&other.rest);
        self.ke.extend(&other.ke);
        self.kd.extend(&other.kd);
        Ok(())
    }

    fn worlds_in(&self, particles: &std::ops::Range<u32>) -> Self {
        use super::component::{elements_in, pick};
        let (idx, quads) = elements_in(&self.quads, particles);
        BendingParts {
            quads,
            rest: pick(&self.rest, &idx),
            ke: pick(&self.ke, &idx),
            kd: pick(&self.kd, &idx),
        }
    }

    fn build(&self) -> Option<Box<dyn Force<R>>> {
        (!self.quads.is_empty()).then(|| {
            Box::new(Bending {
                quads: Array::from_vec(self.quads.clone()).named("bend_quads"),
                rest: Array::from_vec(self.rest.clone()).named("bend_rest"),
                ke: Array::from_vec(self.ke.clone()).named("bend_ke"),
                kd: Array::from_vec(self.kd.clone()).named("bend_kd"),
            }) as Box<dyn Force<R>>
        })
    }
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize, Default, Clone, Copy)]
#[serde(rename_all = "lowercase")]
pub(crate) enum RestDesc {
    #[default]
    Flat,
    Initial,
}

impl From<RestDesc> for RestAngle {
    fn from(r: RestDesc) -> Self {
        match r {
            RestDesc::Flat => RestAngle::Flat,
            RestDesc::Initial => RestAngle::Initial,
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct BendingDesc {
    ke: f64,
    #[serde(default)]
    kd: f64,
    #[serde(default)]
    rest: RestDesc,
}

/// Loads the `bending` section: elements on the edges shared by two of `triangles` (the
/// file's own).
pub(crate) fn load<R: Real>(
    bd: &BendingDesc,
    triangles: &[[u32; 3]],
    part: &mut BendingParts<R>,
    el: &mut Elements<'_, R>,
    c: &Checker,
) -> Result<(), SceneError> {
    let n0 = el.problems.len();
    part.add_edges(el, triangles, R::lit(bd.ke), R::lit(bd.kd), bd.rest.into());
    c.builder(el.problems, n0, |f| sub("bending", f, &["indices"]))
}
