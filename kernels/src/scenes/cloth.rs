//! The `cloth` benchmark scene (`bench/SCENES.md`): a square sheet falling onto the ground,
//! pinned at two corners; springs, dihedral bending, ground contact with friction, gravity,
//! semi-implicit Euler. Topology and ordering match the reference `warp_cloth_scene.py`.
//!
//! ```
//! use adflex_kernels::scenes::cloth;
//! let scene = cloth::build::<f64>(4);
//! let out = cloth::rollout(&scene, 3, true).unwrap();
//! assert!(out.loss > 0.0 && out.grad_v0_norm > 0.0);
//! ```

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::contact::ground::Ground;
use crate::forces::bending::RestDesc;
use crate::forces::bending::{bending_edges, dihedral_angle, RestAngle};
use crate::integrators::{Integrator, SemiImplicitEuler};
use crate::model::{Model, ModelBuilder};
use crate::scene_file::reader::{identity_quat, v3, Checker, SceneError};
use crate::state::State;
use serde::Deserialize;

/// A rectangular cloth: a grid of particles joined by structural and shear springs, split into
/// triangles, with bending elements on every interior edge.
///
/// Particle `(i, j)` (`i < ni`, `j < nj`) is at `origin + rotation (i h, 0, j h)` with index
/// `first + i nj + j`. Springs, for each `(i, j)` in row-major order: `(p(i,j), p(i+1,j))`,
/// `(p(i,j), p(i,j+1))`, then if both exist `(p(i,j), p(i+1,j+1))` and `(p(i+1,j), p(i,j+1))`.
/// Each quad `a = p(i,j)`, `b = p(i+1,j)`, `c = p(i+1,j+1)`, `d = p(i,j+1)` gives the triangles
/// `(a, b, c)`, `(a, c, d)`; bending elements follow [`bending_edges`].
#[derive(Clone, Debug)]
pub struct ClothGrid<R: Real> {
    /// Particles along the first axis (x; at least 2; default 16).
    pub ni: usize,
    /// Particles along the second axis (z; at least 2; default 16).
    pub nj: usize,
    /// Position of particle `(0, 0)` (m; default `(0, 0.03, 0)`).
    pub origin: Vec3<R>,
    /// Distance between neighbouring particles (m; default `1/15`: a sheet of 1 m).
    pub spacing: f64,
    /// Mass of each particle (kg; default 0.01).
    pub mass: R,
    /// Particles `(i, j)` to pin (inverse mass 0; default the corners `(0, 0)`, `(ni-1, 0)`).
    pub pinned: Vec<(usize, usize)>,
    /// Spring stiffness (N/m; default 50).
    pub spring_ke: R,
    /// Spring damping (N s/m; default 0.1).
    pub spring_kd: R,
    /// Bending stiffness `ke` (N m/rad) and damping `kd` (N m s/rad); no bending elements if
    /// `None` (default `Some((0.01, 0))`).
    pub bend: Option<(R, R)>,
    /// Rest angle of the bending elements (default [`RestAngle::Flat`]).
    pub bend_rest: RestAngle,
    /// Orientation of the sheet about `origin` (a unit quaternion `(x, y, z, w)`; default the
    /// identity: horizontal, in the x-z plane). E.g. a quarter turn about x,
    /// `Quat::new(0.5f64.sqrt(), 0.5f64.sqrt(), 0.0, 0.0)` (nalgebra's `(w, i, j, k)` order),
    /// hangs it in the x-y plane like a flag.
    pub rotation: Quat<R>,
}

/// An edge of a [`ClothGrid`], for [`ClothGrid::pin_edge`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ClothEdge {
    /// The particles `(0, j)`.
    IMin,
    /// The particles `(ni - 1, j)`.
    IMax,
    /// The particles `(i, 0)`.
    JMin,
    /// The particles `(i, nj - 1)`.
    JMax,
}

/// [`ClothGrid::benchmark`]`(16)`: a 16 x 16 sheet of 1 m, at 0.03 m, 0.01 kg per particle,
/// pinned at two corners, springs `ke = 50` N/m, `kd = 0.1` N s/m, bending `ke = 0.01`.
impl<R: Real> Default for ClothGrid<R> {
    fn default() -> Self {
        ClothGrid::benchmark(16)
    }
}

impl<R: Real> ClothGrid<R> {
    /// The `cloth` scene's sheet with `n` particles per side: spacing `1/(n-1)`, at height
    /// 0.03 m, mass 0.01 kg, pinned at `(0, 0)` and `(n-1, 0)`, springs `ke = 50`, `kd = 0.1`,
    /// bending `ke = 0.01`, `kd = 0`, flat rest.
    pub fn benchmark(n: usize) -> Self {
        assert!(n >= 2, "a cloth needs at least 2 particles per side");
        ClothGrid {
            ni: n,
            nj: n,
            origin: Vec3::new(R::lit(0.0), R::lit(0.03), R::lit(0.0)),
            spacing: 1.0 / (n - 1) as f64,
            mass: R::lit(0.01),
            pinned: vec![(0, 0), (n - 1, 0)],
            spring_ke: R::lit(50.0),
            spring_kd: R::lit(0.1),
            bend: Some((R::lit(0.01), R::lit(0.0))),
            bend_rest: RestAngle::Flat,
            rotation: Quat::identity(),
        }
    }

    /// The grid with every particle of `edge` pinned too (Warp's `fix_left` etc.).
    ///
    /// ```
    /// use adflex_kernels::prelude::*;
    /// use adflex_kernels::scenes::cloth::ClothEdge;
    /// use adflex_runtime::{Quat, Vec3};
    ///
    /// // A flag: 8 x 6, hanging in the x-y plane, held along its edge i = 0.
    /// let h = 0.5f64.sqrt();
    /// let flag = ClothGrid::<f64> {
    ///     ni: 8,
    ///     nj: 6,
    ///     pinned: vec![],
    ///     origin: Vec3::new(0.0, 1.0, 0.0),
    ///     rotation: Quat::new(h, h, 0.0, 0.0), // a quarter turn about x: j runs along -y
    ///     ..ClothGrid::benchmark(8)
    /// }
    /// .pin_edge(ClothEdge::IMin);
    /// let mut b = ModelBuilder::<f64>::new();
    /// b.add_cloth_grid(&flag);
    /// let model = b.finalize();
    /// let w = model.particle_inv_mass.to_vec();
    /// assert_eq!(w.iter().filter(|&&w| w == 0.0).count(), 6);
    /// let last = model.particle_x.get(5); // particle (0, 5)
    /// assert!((last - Vec3::new(0.0, 1.0 - 5.0 / 7.0, 0.0)).norm() < 1e-12);
    /// ```
    pub fn pin_edge(mut self, edge: ClothEdge) -> Self {
        let (ni, nj) = (self.ni, self.nj);
        let cells: Vec<(usize, usize)> = match edge {
            ClothEdge::IMin => (0..nj).map(|j| (0, j)).collect(),
            ClothEdge::IMax => (0..nj).map(|j| (ni.saturating_sub(1), j)).collect(),
            ClothEdge::JMin => (0..ni).map(|i| (i, 0)).collect(),
            ClothEdge::JMax => (0..ni).map(|i| (i, nj.saturating_sub(1))).collect(),
        };
        for c in cells {
            if !self.pinned.contains(&c) {
                self.pinned.push(c);
            }
        }
        self
    }
}

impl<R: Real> ModelBuilder<R> {
    /// Adds a [`ClothGrid`]; returns the index of its first particle.
    ///
    /// Bad parameters are recorded as problems of item `cloth_grid` that
    /// [`ModelBuilder::try_finalize`] reports: fewer than 2 particles along a side (nothing is
    /// added then), a pinned particle outside the grid; a bad `spacing`, `mass` or stiffness
    /// is reported by the checks of the particles and springs.
    pub fn add_cloth_grid(&mut self, c: &ClothGrid<R>) -> u32 {
        let first = self.particle_count() as u32;
        let (ni, nj) = (c.ni, c.nj);
        let mut check = self.check_one("cloth_grid");
        if ni < 2 || nj < 2 {
            check.fail(
                Some("ni"),
                format!("a cloth needs at least 2 x 2 particles (got ni = {ni}, nj = {nj})"),
            );
            return first;
        }
        for &(i, j) in &c.pinned {
            if i >= ni || j >= nj {
                check.fail(
                    Some("pinned"),
                    format!("particle ({i}, {j}) is outside the {ni} x {nj} grid"),
                );
            }
        }
        let o = Vec3::new(
            c.origin.x.to_f64(),
            c.origin.y.to_f64(),
            c.origin.z.to_f64(),
        );
        let q = c.rotation;
        let q = Quat::new(q.w.to_f64(), q.i.to_f64(), q.j.to_f64(), q.k.to_f64());
        let rotated = q != Quat::identity();
        if rotated && (q.norm() - 1.0).abs() > 1e-3 {
            check.fail(
                Some("rotation"),
                format!(
                    "must be a unit quaternion (length {}); normalize it",
                    q.norm()
                ),
            );
            return first;
        }
        for i in 0..ni {
            for j in 0..nj {
                // Positions in f64, rounded once (as the reference builds them).
                let d = Vec3::new(i as f64 * c.spacing, 0.0, j as f64 * c.spacing);
                // Unrotated, the sum as the reference builds it (the same bits).
                let p = if rotated {
                    o + adflex_runtime::math::quat_rotate(q, d)
                } else {
                    Vec3::new(o.x + d.x, o.y, o.z + d.z)
                };
                let p = Vec3::new(R::lit(p.x), R::lit(p.y), R::lit(p.z));
                let mass = if c.pinned.contains(&(i, j)) {
                    R::lit(0.0)
                } else {
                    c.mass
                };
                self.add_particle(p, Vec3::zeros(), mass);
            }
        }
        let pid = |i: usize, j: usize| first + (i * nj + j) as u32;
        for i in 0..ni {
            for j in 0..nj {
                if i + 1 < ni {
                    self.add_spring(pid(i, j), pid(i + 1, j), c.spring_ke, c.spring_kd);
                }
                if j + 1 < nj {
                    self.add_spring(pid(i, j), pid(i, j + 1), c.spring_ke, c.spring_kd);
                }
                if i + 1 < ni && j + 1 < nj {
                    self.add_spring(pid(i, j), pid(i + 1, j + 1), c.spring_ke, c.spring_kd);
                    self.add_spring(pid(i + 1, j), pid(i, j + 1), c.spring_ke, c.spring_kd);
                }
            }
        }
        let mut tris = Vec::new();
        for i in 0..ni.saturating_sub(1) {
            for j in 0..nj.saturating_sub(1) {
                let (a, b, cc, d) = (pid(i, j), pid(i + 1, j), pid(i + 1, j + 1), pid(i, j + 1));
                tris.push([a, b, cc]);
                tris.push([a, cc, d]);
            }
        }
        for t in &tris {
            self.add_triangle(t[0], t[1], t[2]);
        }
        if let Some((ke, kd)) = c.bend {
            let xs: Vec<Vec3<f64>> = (0..self.particle_count() as u32)
                .map(|i| {
                    let p = self.particle_position(i);
                    Vec3::new(p.x.to_f64(), p.y.to_f64(), p.z.to_f64())
                })
                .collect();
            for q in bending_edges(&tris) {
                let rest = match c.bend_rest {
                    RestAngle::Flat => 0.0,
                    RestAngle::Initial => dihedral_angle(&xs, q),
                };
                self.add_bending(q, R::lit(rest), ke, kd);
            }
        }
        first
    }
}

/// Time step of the scene (s).
pub const DT: f64 = 1e-3;

/// The `cloth` scene, ready to roll out: its model and initial state. The initial velocities
/// and the spring stiffnesses require grad (the scene's gradient targets).
#[derive(Clone, Debug)]
pub struct Cloth<R: Real> {
    /// Particles per side.
    pub n: usize,
    /// The model (springs, bending, ground; gravity).
    pub model: Model<R>,
    /// The initial state (`x0`, `v0`).
    pub initial: State<R>,
}

/// Builds the `cloth` scene with `n` particles per side.
pub fn build<R: Real>(n: usize) -> Cloth<R> {
    let mut b = ModelBuilder::<R>::new();
    b.particle_radius = R::lit(0.01);
    b.add_cloth_grid(&ClothGrid::benchmark(n));
    // Warp's and dFlex's ground, which damps particles approaching it (the peers' scene).
    b.set_ground(Ground {
        damp_approach: true,
        ..Ground::default()
    });
    let model = b.finalize();
    let initial = model.state();
    let _ = initial.v.clone().requires_grad();
    let _ = model.springs().expect("springs").ke.clone().requires_grad();
    Cloth { n, model, initial }
}

/// The scene's loss: `loss[0] += scale |x - x0 - target|^2` for particle `tid`.
#[diff_kernel]
pub fn displacement_loss<R: Real>(
    x: &Array<Vec3<R>>,
    x0: &Array<Vec3<R>>,
    target: Vec3<R>,
    scale: R,
    loss: &Array<R>,
) {
    let t = tid();
    let d = x[t] - x0[t] - target;
    loss.atomic_add(0, dot(d, d) * scale);
}

/// Records `steps` semi-implicit Euler steps of `dt = 1e-3` s from the initial state and the
/// loss `(1/N^2) sum |x_T - x_0 - (0, -0.1, 0)|^2`; returns the final state and the loss array.
pub fn forward<R: Real>(
    scene: &Cloth<R>,
    tape: &mut Tape,
    steps: usize,
) -> Result<(State<R>, Array<R>), Error> {
    forward_by(scene, tape, steps, &SemiImplicitEuler)
}

/// [`forward`] by another integrator (the same `dt`).
pub fn forward_by<R: Real>(
    scene: &Cloth<R>,
    tape: &mut Tape,
    steps: usize,
    integrator: &dyn Integrator<R>,
) -> Result<(State<R>, Array<R>), Error> {
    let dt = R::lit(DT);
    let s = integrator.rollout(&scene.model, tape, &scene.initial, None, dt, steps)?;
    let loss = Array::zeros(1).named("loss");
    let n2 = (scene.n * scene.n) as f64;
    let target = Vec3::new(R::lit(0.0), R::lit(-0.1), R::lit(0.0));
    tape.launch(
        displacement_loss,
        s.x.len(),
        (&s.x, &scene.initial.x, target, R::lit(1.0 / n2), &loss),
    );
    Ok((s, loss))
}

/// What [`rollout`] returns.
#[derive(Clone, Debug)]
pub struct ClothResult<R: Real> {
    /// The loss.
    pub loss: f64,
    /// `dL/dv0` per particle (empty without backward).
    pub grad_v0: Vec<Vec3<R>>,
    /// `dL/dke` per spring (empty without backward).
    pub grad_ke: Vec<R>,
    /// Euclidean norm of `grad_v0` (over all components).
    pub grad_v0_norm: f64,
    /// Euclidean norm of `grad_ke`.
    pub grad_ke_norm: f64,
}

/// Runs the scene for `steps` steps on a fresh tape and, if `backward`, differentiates the
/// loss with respect to the initial velocities and the spring stiffnesses (gradients from
/// earlier calls are cleared first). The entry point of the benchmark.
pub fn rollout<R: Real>(
    scene: &Cloth<R>,
    steps: usize,
    backward: bool,
) -> Result<ClothResult<R>, Error> {
    let mut tape = Tape::new();
    let (_, loss) = forward(scene, &mut tape, steps)?;
    let mut out = ClothResult {
        loss: loss.get(0).to_f64(),
        grad_v0: Vec::new(),
        grad_ke: Vec::new(),
        grad_v0_norm: 0.0,
        grad_ke_norm: 0.0,
    };
    if backward {
        let ke = &scene.model.springs().expect("springs").ke;
        scene.initial.v.zero_grad();
        ke.zero_grad();
        tape.backward(&loss)?;
        out.grad_v0 = scene.initial.v.grad()?.to_vec();
        out.grad_ke = ke.grad()?.to_vec();
        out.grad_v0_norm = out
            .grad_v0
            .iter()
            .map(|g| g.iter().map(|c| c.to_f64().powi(2)).sum::<f64>())
            .sum::<f64>()
            .sqrt();
        out.grad_ke_norm = out
            .grad_ke
            .iter()
            .map(|g| g.to_f64().powi(2))
            .sum::<f64>()
            .sqrt();
    }
    Ok(out)
}

// ---- its scene-file section ------------------------------------------------------------

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ClothGridDesc {
    ni: usize,
    nj: usize,
    origin: [f64; 3],
    spacing: f64,
    mass: f64,
    #[serde(default)]
    pinned: Vec<[usize; 2]>,
    spring_ke: f64,
    #[serde(default)]
    spring_kd: f64,
    bend_ke: Option<f64>,
    #[serde(default)]
    bend_kd: f64,
    #[serde(default)]
    bend_rest: RestDesc,
    #[serde(default = "identity_quat")]
    rotation: [f64; 4],
}

/// Loads the `cloth_grids` section.
pub(crate) fn load<R: Real>(
    d: &[ClothGridDesc],
    b: &mut ModelBuilder<R>,
    c: &Checker,
) -> Result<(), SceneError> {
    for (k, g) in d.iter().enumerate() {
        let path = |f: &str| format!("cloth_grids[{k}].{f}");
        if g.ni < 2 || g.nj < 2 || g.ni.saturating_mul(g.nj) > 1 << 26 {
            return Err(c.err(
                path("ni"),
                format!(
                    "a grid needs 2 to 2^26 particles with at least 2 per side (got {} x {})",
                    g.ni, g.nj
                ),
            ));
        }
        c.finite(|| path("origin"), &g.origin)?;
        c.positive(|| path("spacing"), g.spacing)?;
        c.nonneg(|| path("mass"), g.mass)?;
        c.no_underflow::<R>(|| path("mass"), g.mass)?;
        c.nonneg(|| path("spring_ke"), g.spring_ke)?;
        c.nonneg(|| path("spring_kd"), g.spring_kd)?;
        c.nonneg(|| path("bend_kd"), g.bend_kd)?;
        if let Some(ke) = g.bend_ke {
            c.nonneg(|| path("bend_ke"), ke)?;
        }
        for (m, p) in g.pinned.iter().enumerate() {
            if p[0] >= g.ni || p[1] >= g.nj {
                return Err(c.err(
                    format!("cloth_grids[{k}].pinned[{m}]"),
                    format!(
                        "({}, {}) is outside the {} x {} grid",
                        p[0], p[1], g.ni, g.nj
                    ),
                ));
            }
        }
        let n0 = b.problems().len();
        b.add_cloth_grid(&ClothGrid {
            ni: g.ni,
            nj: g.nj,
            origin: v3(g.origin),
            spacing: g.spacing,
            mass: R::lit(g.mass),
            pinned: g.pinned.iter().map(|p| (p[0], p[1])).collect(),
            spring_ke: R::lit(g.spring_ke),
            spring_kd: R::lit(g.spring_kd),
            bend: g.bend_ke.map(|ke| (R::lit(ke), R::lit(g.bend_kd))),
            bend_rest: g.bend_rest.into(),
            rotation: Quat::new(
                R::lit(g.rotation[3]),
                R::lit(g.rotation[0]),
                R::lit(g.rotation[1]),
                R::lit(g.rotation[2]),
            ),
        });
        if let Some(p) = b.problems().get(n0) {
            return Err(c.err(format!("cloth_grids[{k}]"), p.to_string()));
        }
    }
    Ok(())
}
