//! Soft bodies: a box of stable Neo-Hookean tetrahedra ([`TetGrid`]), the solid a scene needs
//! most often.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! let mut b = ModelBuilder::<f64>::new();
//! let block = TetGrid { dims: [2, 1, 1], ..TetGrid::default() }.add_to(&mut b);
//! assert_eq!(block.particles.len(), 3 * 2 * 2);
//! assert_eq!(block.tets.len(), 2 * 6);
//! assert_eq!(block.surface_triangles().len(), 2 * 2 * (2 + 1 + 2));
//! let model = b.finalize();
//! assert_eq!(model.tets().unwrap().len(), 12);
//! ```

use std::collections::HashMap;
use std::ops::Range;

use adflex_runtime::prelude::*;

use crate::forces::fem_tet::snh_lame;
use crate::model::ModelBuilder;

/// A box of `dims[0] x dims[1] x dims[2]` cubic cells of side `cell`, each split into six
/// tetrahedra (Kuhn's subdivision along the cell's `(0,0,0)`-`(1,1,1)` diagonal, the same in
/// every cell, so neighbouring cells share their faces' diagonals: a conforming mesh), all of
/// rest volume `cell^3 / 6` and positively oriented.
///
/// Vertex `(i, j, k)` (`i <= dims[0]`, ...) is at `origin + cell (i, j, k)`, with index
/// `first + (i (dims[1] + 1) + j) (dims[2] + 1) + k` ([`TetBlock::particle`]). Masses are
/// lumped: each tetrahedron gives a quarter of `density x volume` to each of its vertices, so
/// the total mass is `density x` the box's volume.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TetGrid<R: Real> {
    /// Number of cells along x, y, z (each `>= 1`; default `[4, 2, 2]`).
    pub dims: [usize; 3],
    /// Side of a cell (m; default 0.05).
    pub cell: R,
    /// Position of vertex `(0, 0, 0)`, the box's minimum corner (m; default `(0, 0.1, 0)`).
    pub origin: Vec3<R>,
    /// Density (kg/m^3; default 1000, water, so a cell of 5 cm weighs 0.125 kg).
    pub density: R,
    /// Stable Neo-Hookean `mu` (Pa; default from [`snh_lame`]`(1e5, 0.3)`, Young's modulus
    /// 0.1 MPa and Poisson's ratio 0.3, a soft rubber: 51282 Pa).
    pub mu: R,
    /// Stable Neo-Hookean `lambda` (Pa; default from [`snh_lame`]`(1e5, 0.3)`: 89744 Pa).
    pub lambda: R,
    /// Damping (Pa s; default 0.1).
    pub kd: R,
}

/// See the fields: 4 x 2 x 2 cells of 5 cm at `(0, 0.1, 0)`, 1000 kg/m^3, Young's modulus
/// 0.1 MPa, Poisson's ratio 0.3, `kd = 0.1` Pa s.
impl<R: Real> Default for TetGrid<R> {
    fn default() -> Self {
        let (mu, lambda) = snh_lame(1.0e5, 0.3);
        TetGrid {
            dims: [4, 2, 2],
            cell: R::lit(0.05),
            origin: Vec3::new(R::lit(0.0), R::lit(0.1), R::lit(0.0)),
            density: R::lit(1000.0),
            mu: R::lit(mu),
            lambda: R::lit(lambda),
            kd: R::lit(0.1),
        }
    }
}

/// What [`TetGrid::add_to`] added: index ranges and the boundary surface.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TetBlock {
    /// The grid's particles (vertices), in the order of [`TetBlock::particle`].
    pub particles: Range<u32>,
    /// The grid's tetrahedra (indices into the model's tets), six per cell, cells in the order
    /// `(i, j, k)` row-major.
    pub tets: Range<u32>,
    /// Number of cells along x, y, z.
    pub dims: [usize; 3],
    surface: Vec<[u32; 3]>,
}

impl TetBlock {
    /// The particle of vertex `(i, j, k)` (`i <= dims[0]`, `j <= dims[1]`, `k <= dims[2]`).
    /// Panics if the vertex is outside the grid.
    pub fn particle(&self, i: usize, j: usize, k: usize) -> u32 {
        let [nx, ny, nz] = self.dims;
        assert!(
            i <= nx && j <= ny && k <= nz,
            "vertex ({i}, {j}, {k}) is outside the grid of {nx} x {ny} x {nz} cells"
        );
        self.particles.start + ((i * (ny + 1) + j) * (nz + 1) + k) as u32
    }

    /// The boundary faces (particle indices), each counter-clockwise seen from outside (the
    /// normal `(b - a) x (c - a)` points out): two triangles per boundary cell face. For
    /// rendering; add them with [`ModelBuilder::add_triangle`] to have them in
    /// [`crate::Model::triangles`].
    pub fn surface_triangles(&self) -> &[[u32; 3]] {
        &self.surface
    }
}

/// The six tetrahedra of the unit cube (corner `(a, b, c)` numbered `4a + 2b + c`): the paths
/// from corner 0 to corner 7 along the axes in each order.
const KUHN: [[usize; 4]; 6] = [
    [0, 4, 6, 7], // x, y, z
    [0, 4, 5, 7], // x, z, y
    [0, 2, 6, 7], // y, x, z
    [0, 2, 3, 7], // y, z, x
    [0, 1, 5, 7], // z, x, y
    [0, 1, 3, 7], // z, y, x
];

impl<R: Real> TetGrid<R> {
    /// Adds the grid's particles and tetrahedra to `b` (see [`TetGrid`]); returns their ranges
    /// and boundary. Bad parameters are recorded as problems of item `tet_grid` (a `dims`
    /// entry of 0, a non-positive or non-finite `cell` or `density`: the grid then adds
    /// nothing) or by the builder's checks of each tetrahedron (bad `mu`, `lambda`, `kd`), and
    /// [`ModelBuilder::try_finalize`] reports them.
    pub fn add_to(&self, b: &mut ModelBuilder<R>) -> TetBlock {
        let [nx, ny, nz] = self.dims;
        let first = b.particle_count() as u32;
        let first_tet = b.tet_count() as u32;
        let mut c = b.check_one("tet_grid");
        if self.dims.contains(&0) {
            c.fail(
                Some("dims"),
                format!(
                    "needs at least one cell along each axis (got {:?})",
                    self.dims
                ),
            );
        }
        let sized = c.positive("cell", self.cell) & c.positive("density", self.density);
        if nx == 0 || ny == 0 || nz == 0 || !sized {
            return TetBlock {
                particles: first..first,
                tets: first_tet..first_tet,
                dims: self.dims,
                surface: Vec::new(),
            };
        }
        let vid = |i: usize, j: usize, k: usize| ((i * (ny + 1) + j) * (nz + 1) + k) as u32;
        let h = self.cell.to_f64();
        let o = [self.origin.x, self.origin.y, self.origin.z].map(|v| v.to_f64());
        let pos = |v: u32| {
            let v = v as usize;
            let (i, j, k) = (
                v / ((ny + 1) * (nz + 1)),
                (v / (nz + 1)) % (ny + 1),
                v % (nz + 1),
            );
            Vec3::new(
                o[0] + i as f64 * h,
                o[1] + j as f64 * h,
                o[2] + k as f64 * h,
            )
        };
        // Tetrahedra (local vertex ids), positively oriented.
        let mut tets = Vec::with_capacity(6 * nx * ny * nz);
        for i in 0..nx {
            for j in 0..ny {
                for k in 0..nz {
                    let corner = |c: usize| vid(i + (c >> 2), j + ((c >> 1) & 1), k + (c & 1));
                    for t in KUHN {
                        let [a, bb, c, d] = t.map(corner);
                        let (pa, pb, pc, pd) = (pos(a), pos(bb), pos(c), pos(d));
                        let vol = (pb - pa).cross(&(pc - pa)).dot(&(pd - pa));
                        tets.push(if vol < 0.0 {
                            [a, c, bb, d]
                        } else {
                            [a, bb, c, d]
                        });
                    }
                }
            }
        }
        // Lumped masses: a quarter of each tetrahedron's mass to each vertex.
        let nv = (nx + 1) * (ny + 1) * (nz + 1);
        let quarter = self.density.to_f64() * h * h * h / 24.0;
        let mut mass = vec![0.0; nv];
        for t in &tets {
            for &v in t {
                mass[v as usize] += quarter;
            }
        }
        for (v, m) in mass.iter().enumerate() {
            let p = pos(v as u32);
            b.add_particle(
                Vec3::new(R::lit(p.x), R::lit(p.y), R::lit(p.z)),
                Vec3::zeros(),
                R::lit(*m),
            );
        }
        for t in &tets {
            let [a, bb, c, d] = t.map(|v| first + v);
            b.add_tet(a, bb, c, d, self.mu, self.lambda, self.kd);
        }
        // Boundary: the faces of one tetrahedron only, outward (see `TetBlock::surface`).
        let mut faces: HashMap<[u32; 3], ([u32; 3], u32)> = HashMap::new();
        for t in &tets {
            let [a, bb, c, d] = *t;
            for f in [[bb, c, d], [a, d, c], [a, bb, d], [a, c, bb]] {
                let mut key = f;
                key.sort_unstable();
                faces.entry(key).or_insert((f, 0)).1 += 1;
            }
        }
        let mut surface: Vec<[u32; 3]> = faces
            .into_values()
            .filter(|(_, n)| *n == 1)
            .map(|(f, _)| f.map(|v| first + v))
            .collect();
        surface.sort_unstable();
        TetBlock {
            particles: first..first + nv as u32,
            tets: first_tet..first_tet + tets.len() as u32,
            dims: self.dims,
            surface,
        }
    }
}

impl<R: Real> ModelBuilder<R> {
    /// Adds a [`TetGrid`] (see [`TetGrid::add_to`]).
    pub fn add_tet_grid(&mut self, grid: &TetGrid<R>) -> TetBlock {
        grid.add_to(self)
    }
}
