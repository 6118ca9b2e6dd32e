//! What the exporters and the renderer draw, taken out of a `Model` and its `State`s once:
//! topology (faces, edges, body points) and, per state, positions in `f64`.

use std::collections::HashMap;

use adflex_kernels::model::{Model, State};
use adflex_runtime::{Quat, Real, Vec3};

/// Bodies with at most this many contact points get edges between them.
pub(crate) const MAX_BODY_POINTS_FOR_EDGES: usize = 64;
/// Points of a body that share no axis line are joined to this many nearest points.
pub(crate) const BODY_NEIGHBOURS: usize = 2;

pub(crate) fn wide<R: Real>(v: Vec3<R>) -> Vec3<f64> {
    Vec3::new(v.x.to_f64(), v.y.to_f64(), v.z.to_f64())
}

/// Rotates `p` by the (normalized) quaternion `q`.
pub(crate) fn rotate(q: [f64; 4], p: Vec3<f64>) -> Vec3<f64> {
    // q = (w, x, y, z); p' = p + 2 w (u x p) + 2 u x (u x p)
    let u = Vec3::new(q[1], q[2], q[3]);
    let t = u.cross(&p) * 2.0;
    p + t * q[0] + u.cross(&t)
}

/// `(w, x, y, z)` normalized (identity if zero or not finite).
pub(crate) fn quat<R: Real>(q: Quat<R>) -> [f64; 4] {
    let v = [q.w.to_f64(), q.i.to_f64(), q.j.to_f64(), q.k.to_f64()];
    let n = v.iter().map(|c| c * c).sum::<f64>().sqrt();
    if n > 0.0 && n.is_finite() {
        v.map(|c| c / n)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// The topology of a model, host side.
#[derive(Clone, Debug, Default)]
pub(crate) struct Topology {
    pub particles: usize,
    /// Triangles, then the boundary faces of the tetrahedra not already among them.
    pub faces: Vec<[u32; 3]>,
    /// Springs, then distance constraints (particle indices).
    pub edges: Vec<[u32; 2]>,
    /// Contact points (body frame) of each body.
    pub body_points: Vec<Vec<Vec3<f64>>>,
    /// Particle radius (m): the model's `particle_radius`.
    pub radius: f64,
    /// Each particle's own radius (m), if the model has per-particle radii (else empty).
    pub radii: Vec<f64>,
}

impl Topology {
    pub fn of<R: Real>(model: &Model<R>) -> Self {
        let mut faces: Vec<[u32; 3]> = model.triangles.clone();
        if let Some(t) = model.tets() {
            let rest: Vec<Vec3<f64>> = model.particle_x.to_vec().into_iter().map(wide).collect();
            faces.extend(tet_boundary(&t.tets.to_vec(), &rest, &model.triangles));
        }
        let mut edges: Vec<[u32; 2]> = Vec::new();
        if let Some(s) = model.springs() {
            edges.extend(s.pairs.to_vec());
        }
        if let Some(d) = &model.distance_constraints {
            edges.extend(d.pairs.to_vec());
        }
        let mut body_points = Vec::new();
        if let Some(b) = &model.bodies {
            body_points = vec![Vec::new(); b.len()];
            if let (Some(cb), Some(cp)) = (&b.contact_body, &b.contact_point) {
                for (i, p) in cb.to_vec().into_iter().zip(cp.to_vec()) {
                    if let Some(v) = body_points.get_mut(i as usize) {
                        v.push(wide(p));
                    }
                }
            }
        }
        let n = model.particle_count as u32;
        faces.retain(|f| f.iter().all(|&i| i < n));
        edges.retain(|e| e.iter().all(|&i| i < n));
        Topology {
            particles: model.particle_count,
            faces,
            edges,
            body_points,
            radius: model.particle_radius.to_f64(),
            radii: model
                .particle_radii
                .as_ref()
                .map(|r| r.to_vec().into_iter().map(|v| v.to_f64()).collect())
                .unwrap_or_default(),
        }
    }

    /// The radius (m) of particle `i`.
    pub fn radius_of(&self, i: usize) -> f64 {
        self.radii.get(i).copied().unwrap_or(self.radius)
    }

    /// The largest particle radius (m).
    pub fn max_radius(&self) -> f64 {
        self.radii.iter().copied().fold(self.radius, f64::max)
    }

    /// Edges between the contact points of each body, as indices into
    /// [`Frame::body_world_points`] order (body by body); see [`Topology::body_edges_of`].
    pub fn body_edges(&self) -> Vec<[u32; 2]> {
        let mut out = Vec::new();
        let mut first = 0u32;
        for (b, pts) in self.body_points.iter().enumerate() {
            out.extend(
                self.body_edges_of(b)
                    .into_iter()
                    .map(|[i, j]| [first + i, first + j]),
            );
            first += pts.len() as u32;
        }
        out
    }

    /// The edges of body `b`, as indices into its own points: each point joined to the
    /// nearest point in each body-axis direction (+ and -) whose other two coordinates are
    /// the same (box corners give the box's edges, a lattice its lines); if that finds none,
    /// each point joined to its [`BODY_NEIGHBOURS`] nearest. Bodies with more than
    /// [`MAX_BODY_POINTS_FOR_EDGES`] points get none.
    pub fn body_edges_of(&self, b: usize) -> Vec<[u32; 2]> {
        let pts = &self.body_points[b];
        let n = pts.len();
        if n > MAX_BODY_POINTS_FOR_EDGES {
            return Vec::new();
        }
        let size = pts.iter().map(|p| p.amax()).fold(0.0, f64::max);
        let tol = 1e-6 * size.max(1e-12);
        let mut pairs = std::collections::BTreeSet::new();
        let key = |a: usize, j: usize| [a.min(j) as u32, a.max(j) as u32];
        for a in 0..n {
            for axis in 0..3 {
                for sign in [-1.0, 1.0] {
                    let best = (0..n)
                        .filter(|&j| {
                            let d = pts[j] - pts[a];
                            (0..3).all(|c| c == axis || d[c].abs() <= tol) && sign * d[axis] > tol
                        })
                        .min_by(|&i, &j| {
                            (pts[i][axis] - pts[a][axis])
                                .abs()
                                .total_cmp(&(pts[j][axis] - pts[a][axis]).abs())
                        });
                    if let Some(j) = best {
                        pairs.insert(key(a, j));
                    }
                }
            }
        }
        if pairs.is_empty() {
            for a in 0..n {
                let mut near: Vec<usize> = (0..n).filter(|&j| j != a).collect();
                near.sort_by(|&i, &j| {
                    (pts[i] - pts[a])
                        .norm_squared()
                        .total_cmp(&(pts[j] - pts[a]).norm_squared())
                });
                for &j in near.iter().take(BODY_NEIGHBOURS) {
                    pairs.insert(key(a, j));
                }
            }
        }
        pairs.into_iter().collect()
    }
}

/// The faces of the tetrahedra that belong to one tetrahedron only, oriented away from it
/// (at the rest positions), leaving out those already in `triangles`.
fn tet_boundary(tets: &[[u32; 4]], rest: &[Vec3<f64>], triangles: &[[u32; 3]]) -> Vec<[u32; 3]> {
    let key = |f: [u32; 3]| {
        let mut k = f;
        k.sort_unstable();
        k
    };
    let mut count: HashMap<[u32; 3], ([u32; 3], usize)> = HashMap::new();
    for t in tets {
        if t.iter().any(|&i| i as usize >= rest.len()) {
            continue;
        }
        for (skip, f) in [
            (0, [t[1], t[2], t[3]]),
            (1, [t[0], t[2], t[3]]),
            (2, [t[0], t[1], t[3]]),
            (3, [t[0], t[1], t[2]]),
        ] {
            let p = |i: u32| rest[i as usize];
            let n = (p(f[1]) - p(f[0])).cross(&(p(f[2]) - p(f[0])));
            let out = if n.dot(&(p(f[0]) - p(t[skip]))) < 0.0 {
                [f[0], f[2], f[1]]
            } else {
                f
            };
            count.entry(key(f)).or_insert((out, 0)).1 += 1;
        }
    }
    let existing: std::collections::HashSet<[u32; 3]> = triangles.iter().map(|&f| key(f)).collect();
    let mut faces: Vec<([u32; 3], [u32; 3])> = count
        .into_iter()
        .filter(|(k, (_, c))| *c == 1 && !existing.contains(k))
        .map(|(k, (f, _))| (k, f))
        .collect();
    faces.sort_unstable_by_key(|(k, _)| *k);
    faces.into_iter().map(|(_, f)| f).collect()
}

/// Positions of one state, in `f64`.
#[derive(Clone, Debug, Default)]
pub(crate) struct Frame {
    pub x: Vec<Vec3<f64>>,
    /// Body centre of mass and orientation `(w, x, y, z)`.
    pub bodies: Vec<(Vec3<f64>, [f64; 4])>,
}

impl Frame {
    pub fn of<R: Real>(state: &State<R>) -> Self {
        let x = state.x.to_vec().into_iter().map(wide).collect();
        let bodies = match &state.bodies {
            Some(b) => {
                b.x.to_vec()
                    .into_iter()
                    .zip(b.q.to_vec())
                    .map(|(x, q)| (wide(x), quat(q)))
                    .collect()
            }
            None => Vec::new(),
        };
        Frame { x, bodies }
    }

    /// An [`crate::Error::Invalid`] if the state does not fit the model (fewer particles
    /// than the model has), naming the state by `index` if given.
    pub fn check(&self, topo: &Topology, index: Option<usize>) -> crate::Result<()> {
        if self.x.len() < topo.particles {
            let which = index.map_or("the state".to_string(), |k| format!("state {k}"));
            return Err(crate::Error::Invalid(format!(
                "{which} has {} particles, the model {}: is it a state of this model?",
                self.x.len(),
                topo.particles
            )));
        }
        Ok(())
    }

    /// The contact points of every body in world coordinates, body by body.
    pub fn body_world_points(&self, topo: &Topology) -> Vec<Vec3<f64>> {
        let mut out = Vec::new();
        for (b, pts) in topo.body_points.iter().enumerate() {
            let (c, q) = self
                .bodies
                .get(b)
                .copied()
                .unwrap_or((Vec3::zeros(), [1.0, 0.0, 0.0, 0.0]));
            out.extend(pts.iter().map(|&p| c + rotate(q, p)));
        }
        out
    }

    /// Every position worth framing: particles, body centres, body points.
    pub fn all_points(&self, topo: &Topology) -> Vec<Vec3<f64>> {
        let mut out = self.x.clone();
        out.extend(self.bodies.iter().map(|b| b.0));
        out.extend(self.body_world_points(topo));
        out.retain(|p| p.iter().all(|c| c.is_finite()));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_corners_get_the_twelve_box_edges() {
        let mut pts = Vec::new();
        for x in [-0.2, 0.2] {
            for y in [-0.1, 0.1] {
                for z in [-0.15, 0.15] {
                    pts.push(Vec3::new(x, y, z));
                }
            }
        }
        let topo = Topology {
            body_points: vec![vec![Vec3::zeros()], pts.clone()],
            ..Topology::default()
        };
        let e = topo.body_edges();
        assert_eq!(e.len(), 12);
        for [a, b] in e {
            // Offset by the first body's single point; box edges change one coordinate.
            let d = pts[a as usize - 1] - pts[b as usize - 1];
            assert_eq!(d.iter().filter(|c| c.abs() > 1e-12).count(), 1);
        }
    }

    #[test]
    fn rotation_quarter_turn_about_z() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let p = rotate([h, 0.0, 0.0, h], Vec3::new(1.0, 0.0, 0.0));
        assert!((p - Vec3::new(0.0, 1.0, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn one_tet_has_four_outward_faces() {
        let rest = vec![
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, 1.0),
        ];
        let faces = tet_boundary(&[[0, 1, 2, 3]], &rest, &[]);
        assert_eq!(faces.len(), 4);
        let centre = Vec3::new(0.25, 0.25, 0.25);
        for f in faces {
            let p = |i: u32| rest[i as usize];
            let n = (p(f[1]) - p(f[0])).cross(&(p(f[2]) - p(f[0])));
            assert!(n.dot(&(p(f[0]) - centre)) > 0.0);
        }
    }
}
