//! The derivatives of the forward dynamics `qdd(q, qd, tau)` in closed form (as Pinocchio's
//! `computeABADerivatives`): `d qdd / d x = -M^-1 d tau_id / d x` with the inverse dynamics'
//! derivatives taken at the solution's `qdd`, and `d qdd / d tau = M^-1`.
//!
//! The inverse dynamics' derivatives follow Carpentier and Mansard's analytical RNEA
//! derivatives, written in this module's world frame (spatial vectors at the origin, as the
//! kernels'). Moving along tangent direction `k` (the motion vector `S_k` of a joint on link
//! `b`, parent `p`) moves everything at or below `b` rigidly by `S_k`, except that the
//! velocity and acceleration below `b` also lose what `p`'s own motion contributed:
//! `u_k = S_k x v_p` and `w_k = S_k x a_p - u_k x v_p`. With `Ic`, `Bc` and `F` the subtree
//! sums of the links' inertias, of `B(x) = I (x x v) + x x* (I v) + v x* (I x)` and of the
//! wrenches, for velocities `j` at or below `b`:
//!
//! - `d tau_j / d q_k = -S_j . (Ic w_k + Bc u_k)` and
//!   `d tau_j / d qd_k = S_j . (Ic (v_b x S_k - u_k) + Bc S_k)` (sums over `j`'s subtree);
//!
//! and for `j` strictly above `b`, the same brackets over `b`'s subtree, with `S_k x* F_b`
//! added to the first. Every pair of velocities on one chain costs a few dot products; the
//! vectors are formed once per velocity. The kernels' recorded dynamics are the reference
//! (`kernels/tests/articulation.rs` compares the two to 1e-10, and both with Pinocchio).

use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector3, Vector6};

use adflex_runtime::prelude::*;

use super::dynamics::{cholesky_solve, solve_all};
use super::model::{Articulations, JointType};

type V3 = Vector3<f64>;
type V6 = Vector6<f64>;
type M6 = Matrix6<f64>;

fn join(a: V3, b: V3) -> V6 {
    V6::new(a.x, a.y, a.z, b.x, b.y, b.z)
}

fn top(m: &V6) -> V3 {
    V3::new(m[0], m[1], m[2])
}

fn bottom(m: &V6) -> V3 {
    V3::new(m[3], m[4], m[5])
}

/// The 6 x 6 matrix of blocks `[a b; c d]`.
fn blocks(a: Matrix3<f64>, b: Matrix3<f64>, c: Matrix3<f64>, d: Matrix3<f64>) -> M6 {
    let mut m = M6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&a);
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&b);
    m.fixed_view_mut::<3, 3>(3, 0).copy_from(&c);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&d);
    m
}

/// Motion cross product `(w1, v1) x (w2, v2) = (w1 x w2, w1 x v2 + v1 x w2)`.
fn cross_m(a: &V6, b: &V6) -> V6 {
    let (aw, av, bw, bv) = (top(a), bottom(a), top(b), bottom(b));
    join(aw.cross(&bw), aw.cross(&bv) + av.cross(&bw))
}

/// Force cross product `(w, v) x* (n, f) = (w x n + v x f, w x f)`.
fn cross_f(a: &V6, f: &V6) -> V6 {
    let (aw, av, n, ff) = (top(a), bottom(a), top(f), bottom(f));
    join(aw.cross(&n) + av.cross(&ff), aw.cross(&ff))
}

/// The derivatives of the forward dynamics `qdd(q, qd, tau)`, as Pinocchio's
/// `computeABADerivatives` gives them: `dq[i][j]` is the derivative of `qdd[i]` along the
/// `j`-th tangent direction of the configuration (see [`Articulations::tangent_to_coords`]).
#[derive(Clone, Debug, PartialEq)]
pub struct QddDerivatives {
    /// `d qdd / d q` (tangent space), `n_dof x n_dof`.
    pub dq: Vec<Vec<f64>>,
    /// `d qdd / d qd`.
    pub dqd: Vec<Vec<f64>>,
    /// `d qdd / d tau` (the inverse mass matrix).
    pub dtau: Vec<Vec<f64>>,
}

/// The derivatives of the inverse dynamics `tau(q, qd, qdd)`, as Pinocchio's
/// `computeRNEADerivatives` gives them (`dq` along the tangent directions, as
/// [`QddDerivatives::dq`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TauDerivatives {
    /// `d tau / d q` (tangent space), `n_dof x n_dof`.
    pub dq: Vec<Vec<f64>>,
    /// `d tau / d qd`.
    pub dqd: Vec<Vec<f64>>,
    /// `d tau / d qdd`: the mass matrix (zero between articulations).
    pub dqdd: Vec<Vec<f64>>,
}

/// What one evaluation of the dynamics leaves for the derivatives: per link its spatial
/// inertia, twist, acceleration, and the subtree sums; per velocity its motion vector.
struct Rnea {
    /// Each velocity's link.
    link_of: Vec<usize>,
    /// Motion vectors, one per velocity.
    s: Vec<V6>,
    /// Each link's world's acceleration: `(0, -g)` (gravity as an upward acceleration).
    world_a: Vec<V6>,
    /// Link inertias (world frame, at the origin), then their subtree sums.
    inertia: Vec<M6>,
    composite: Vec<M6>,
    /// Twists and accelerations (gravity as the world's upward acceleration).
    v: Vec<V6>,
    a: Vec<V6>,
    /// Wrenches, summed over subtrees.
    f: Vec<V6>,
}

/// The model's parameters in `f64`, checked once per call (finite, quaternions and axes
/// that can be normalized, one gravity per world).
struct PlainModel {
    joint_pos: Vec<V3>,
    joint_rot: Vec<UnitQuaternion<f64>>,
    joint_axis: Vec<V3>,
    mass: Vec<f64>,
    com: Vec<V3>,
    /// The inertias' symmetric parts (as the kernels read them).
    inertia: Vec<Matrix3<f64>>,
    /// Per link, its world's gravity.
    gravity: Vec<V3>,
    armature: Vec<f64>,
}

/// A norm below which a quaternion or an axis has no direction to normalize to.
const TINY_NORM: f64 = 1e-12;

impl<R: Real> Articulations<R> {
    /// The derivatives of the forward dynamics at `(q, qd, tau)` (as Pinocchio's
    /// `computeABADerivatives`; the model's plain dynamics, as [`Articulations::forward_dynamics`]:
    /// no damping, limits, PD or contact): `d qdd / d q` (along the tangent directions),
    /// `d qdd / d qd` and `d qdd / d tau = M^-1`, in closed form (the inverse dynamics'
    /// analytical derivatives and the mass matrix's Cholesky factors), without a tape.
    ///
    /// Errors, as [`Error::InvalidInput`] naming the input, the model field or the
    /// articulation: an input of the wrong length or not finite, a ball or free joint's
    /// quaternion in `q` of norm (near) 0, a model parameter that is not finite (or a zero
    /// `joint_rot` or `joint_axis`), a mass matrix that is not positive definite.
    ///
    /// ```
    /// use adflex_kernels::articulation::*;
    /// use adflex_runtime::Vec3;
    ///
    /// let mut b = ArticulationBuilder::new();
    /// b.add_link("pendulum", None, Joint::revolute(Vec3::y()),
    ///     Inertial::point(2.0, Vec3::new(0.0, 0.0, -0.5)));
    /// let model = b.finalize::<f64>().unwrap();
    /// let d = model.forward_dynamics_derivatives(&[0.3], &[0.0], &[0.0]).unwrap();
    /// // qdd = -(g / l) sin q, so d qdd / d q = -(g / l) cos q and d qdd / d tau = 1 / (m l^2).
    /// let g = model.gravity.get(0).norm();
    /// assert!((d.dq[0][0] + g / 0.5 * 0.3f64.cos()).abs() < 1e-12);
    /// assert!((d.dtau[0][0] - 1.0 / (2.0 * 0.25)).abs() < 1e-12);
    /// ```
    pub fn forward_dynamics_derivatives(
        &self,
        q: &[R],
        qd: &[R],
        tau: &[R],
    ) -> Result<QddDerivatives, Error> {
        let method = "forward_dynamics_derivatives";
        let [q, qd, tau] = self.plain_inputs(method, [q, qd, tau])?;
        let model = self.plain_model(method)?;
        let n = self.n_dof;
        let mut rnea = self.rnea_bias(&model, &q, &qd);
        let (m, ic_s) = self.mass_matrix_values(&model, &rnea);
        let (factors, blocks) = self.factor_values(&m)?;
        // qdd = M^-1 (tau - c), then the inverse dynamics at that qdd.
        let rhs: Vec<f64> = (0..n)
            .map(|j| tau[j] - rnea.s[j].dot(&rnea.f[rnea.link_of[j]]))
            .collect();
        let qdd = solve_all(&factors, &blocks, &rhs);
        self.rnea_accelerate(&mut rnea, &qdd);
        let (mut dq, mut dqd) = self.tau_derivatives(&rnea, &ic_s);
        // Per block, in place: the columns of -M^-1 d tau_id, and M^-1's.
        let mut dtau = vec![vec![0.0; n]; n];
        for (art, l) in self.articulations.iter().zip(&factors) {
            let d = art.dofs.clone();
            let mut y = vec![0.0; d.len()];
            for k in d.clone() {
                for (mat, identity) in [(&mut dq, false), (&mut dqd, false), (&mut dtau, true)] {
                    for (i, yi) in d.clone().zip(y.iter_mut()) {
                        *yi = match identity {
                            false => -mat[i][k],
                            true => f64::from(u8::from(i == k)),
                        };
                    }
                    cholesky_solve(l, &mut y);
                    for (i, yi) in d.clone().zip(&y) {
                        mat[i][k] = *yi;
                    }
                }
            }
        }
        check_finite(method, [("dq", &dq), ("dqd", &dqd), ("dtau", &dtau)])?;
        Ok(QddDerivatives { dq, dqd, dtau })
    }

    /// The derivatives of the inverse dynamics `tau = M(q) qdd + c(q, qd)` at `(q, qd, qdd)`
    /// (as Pinocchio's `computeRNEADerivatives`, armature included): `d tau / d q` (along the
    /// tangent directions, see [`Articulations::tangent_to_coords`]), `d tau / d qd` and
    /// `d tau / d qdd = M(q)`, in closed form, without a tape. As for
    /// [`Articulations::inverse_dynamics`], the model's plain dynamics (no damping, limits,
    /// PD or contact).
    ///
    /// Errors, as [`Error::InvalidInput`] naming the input or the model field: an input of
    /// the wrong length or not finite, a ball or free joint's quaternion in `q` of norm (near)
    /// 0, a model parameter that is not finite (or a zero `joint_rot` or `joint_axis`).
    ///
    /// ```
    /// use adflex_kernels::articulation::*;
    /// use adflex_runtime::Vec3;
    ///
    /// let mut b = ArticulationBuilder::new();
    /// b.add_link("pendulum", None, Joint::revolute(Vec3::y()),
    ///     Inertial::point(2.0, Vec3::new(0.0, 0.0, -0.5)));
    /// let model = b.finalize::<f64>().unwrap();
    /// let d = model.inverse_dynamics_derivatives(&[0.3], &[1.0], &[0.0]).unwrap();
    /// // tau = m l^2 qdd + m g l sin q: d tau / d q = m g l cos q, d tau / d qdd = m l^2.
    /// let g = model.gravity.get(0).norm();
    /// assert!((d.dq[0][0] - 2.0 * g * 0.5 * 0.3f64.cos()).abs() < 1e-12);
    /// assert!(d.dqd[0][0].abs() < 1e-12);
    /// assert!((d.dqdd[0][0] - 2.0 * 0.25).abs() < 1e-12);
    /// ```
    pub fn inverse_dynamics_derivatives(
        &self,
        q: &[R],
        qd: &[R],
        qdd: &[R],
    ) -> Result<TauDerivatives, Error> {
        let method = "inverse_dynamics_derivatives";
        let [q, qd, qdd] = self.plain_inputs(method, [q, qd, qdd])?;
        let model = self.plain_model(method)?;
        let mut rnea = self.rnea_bias(&model, &q, &qd);
        let (m, ic_s) = self.mass_matrix_values(&model, &rnea);
        self.rnea_accelerate(&mut rnea, &qdd);
        let (dq, dqd) = self.tau_derivatives(&rnea, &ic_s);
        let mut dqdd = vec![vec![0.0; self.n_dof]; self.n_dof];
        for art in &self.articulations {
            let (first, len) = (art.dofs.start, art.dofs.len());
            for i in art.dofs.clone() {
                for j in art.dofs.clone() {
                    dqdd[i][j] = m[art.m_offset + (i - first) * len + (j - first)];
                }
            }
        }
        check_finite(method, [("dq", &dq), ("dqd", &dqd), ("dqdd", &dqdd)])?;
        Ok(TauDerivatives { dq, dqd, dqdd })
    }

    /// The three inputs `(q, velocities, velocities)` in `f64`, or an error naming `method`'s
    /// input that has the wrong length or is not finite.
    fn plain_inputs(&self, method: &str, inputs: [&[R]; 3]) -> Result<[Vec<f64>; 3], Error> {
        let names = match method {
            "forward_dynamics_derivatives" => ["q", "qd", "tau"],
            _ => ["q", "qd", "qdd"],
        };
        let mut out: [Vec<f64>; 3] = Default::default();
        for (k, v) in inputs.into_iter().enumerate() {
            let what = format!("{method}: {}", names[k]);
            let n = if k == 0 { self.n_q } else { self.n_dof };
            if v.len() != n {
                return Err(Error::InvalidInput {
                    what,
                    message: format!("has {} elements, the model needs {n}", v.len()),
                });
            }
            out[k] = v.iter().map(|x| x.to_f64()).collect();
            if let Some(i) = out[k].iter().position(|x| !x.is_finite()) {
                return Err(Error::InvalidInput {
                    what: format!("{what}[{i}]"),
                    message: format!("is {}: every input must be finite", out[k][i]),
                });
            }
        }
        for link in &self.links {
            let r = match link.kind {
                JointType::Ball => link.q.start..link.q.start + 4,
                JointType::Free => link.q.start + 3..link.q.start + 7,
                _ => continue,
            };
            let norm = out[0][r.clone()].iter().map(|x| x * x).sum::<f64>().sqrt();
            if norm < TINY_NORM {
                return Err(Error::InvalidInput {
                    what: format!("{method}: q[{}..{}]", r.start, r.end),
                    message: format!(
                        "(the quaternion of joint \"{}\") has norm {norm:e}: a rotation needs a \
                         unit quaternion (x, y, z, w), e.g. (0, 0, 0, 1)",
                        link.joint
                    ),
                });
            }
        }
        Ok(out)
    }

    /// The model's parameters in `f64`, or an error naming the field (and link) that has the
    /// wrong length or is not finite, a `joint_rot` or `joint_axis` that cannot be normalized,
    /// or a `gravity` array without one value per world.
    fn plain_model(&self, method: &str) -> Result<PlainModel, Error> {
        let n = self.links.len();
        let error = |what: String, message: String| Error::InvalidInput {
            what: format!("{method}: model.{what}"),
            message,
        };
        let at = |field: &str, l: usize| format!("{field}[{l}] (link \"{}\")", self.links[l].name);
        let not_finite = || "is not finite: every model parameter must be finite".to_string();
        let world = self.link_world.to_vec();
        for (field, len, want, per) in [
            ("joint_pos", self.joint_pos.len(), n, "link"),
            ("joint_rot", self.joint_rot.len(), n, "link"),
            ("joint_axis", self.joint_axis.len(), n, "link"),
            ("mass", self.mass.len(), n, "link"),
            ("com", self.com.len(), n, "link"),
            ("inertia", self.inertia.len(), n, "link"),
            ("armature", self.armature.len(), self.n_dof, "velocity"),
            ("gravity", self.gravity.len(), self.n_worlds(), "world"),
        ] {
            if len < want {
                return Err(error(
                    field.into(),
                    format!("has {len} elements, the model needs {want} (one per {per})"),
                ));
            }
        }
        let f3 = |v: &Vector3<R>| v.map(|x| x.to_f64());
        let finite3 = |v: &V3| v.iter().all(|x| x.is_finite());
        let gravity: Vec<V3> = self.gravity.to_vec().iter().map(f3).collect();
        if let Some(w) = gravity.iter().position(|g| !finite3(g)) {
            return Err(error(format!("gravity[{w}]"), not_finite()));
        }
        let mut out = PlainModel {
            joint_pos: self.joint_pos.to_vec().iter().map(f3).collect(),
            joint_rot: Vec::with_capacity(n),
            joint_axis: Vec::with_capacity(n),
            mass: self.mass.to_vec().iter().map(|x| x.to_f64()).collect(),
            com: self.com.to_vec().iter().map(f3).collect(),
            inertia: Vec::with_capacity(n),
            gravity: world.iter().map(|&w| gravity[w as usize]).collect(),
            armature: self.armature.to_vec().iter().map(|x| x.to_f64()).collect(),
        };
        let (rot, axis, inertia) = (
            self.joint_rot.to_vec(),
            self.joint_axis.to_vec(),
            self.inertia.to_vec(),
        );
        for l in 0..n {
            let r = nalgebra::Quaternion::from(rot[l].coords.map(|x| x.to_f64()));
            let a = f3(&axis[l]);
            let i3 = inertia[l].map(|x| x.to_f64());
            let finite = [
                ("joint_pos", finite3(&out.joint_pos[l])),
                ("joint_rot", r.coords.iter().all(|x| x.is_finite())),
                ("joint_axis", finite3(&a)),
                ("mass", out.mass[l].is_finite()),
                ("com", finite3(&out.com[l])),
                ("inertia", i3.iter().all(|x| x.is_finite())),
            ];
            if let Some((field, _)) = finite.iter().find(|(_, ok)| !ok) {
                return Err(error(at(field, l), not_finite()));
            }
            // The kernels normalize both; a zero one has no direction (an axis only matters
            // for a revolute or prismatic joint).
            let uses_axis = matches!(
                self.links[l].kind,
                JointType::Revolute | JointType::Prismatic
            );
            for (field, norm, used) in [
                ("joint_rot", r.norm(), true),
                ("joint_axis", a.norm(), uses_axis),
            ] {
                if used && norm < TINY_NORM {
                    return Err(error(
                        at(field, l),
                        format!("has norm {norm:e}: it has no direction to normalize to"),
                    ));
                }
            }
            out.joint_rot.push(UnitQuaternion::from_quaternion(r));
            out.joint_axis
                .push(if uses_axis { a.normalize() } else { a });
            out.inertia.push((i3 + i3.transpose()) * 0.5);
        }
        if let Some(j) = out.armature.iter().position(|x| !x.is_finite()) {
            return Err(error(format!("armature[{j}]"), not_finite()));
        }
        Ok(out)
    }

    /// The mass matrix's blocks (CRBA: `M[j][k] = S_k . Ic S_j` for `k` at or above `j`,
    /// armature on the diagonal) in the layout of [`Articulations::mass_matrix`], and `Ic S_j`
    /// per velocity.
    fn mass_matrix_values(&self, model: &PlainModel, rnea: &Rnea) -> (Vec<f64>, Vec<V6>) {
        let ic_s: Vec<V6> = (0..self.n_dof)
            .map(|j| rnea.composite[rnea.link_of[j]] * rnea.s[j])
            .collect();
        let armature = &model.armature;
        let mut m = vec![0.0; self.m_len];
        for art in &self.articulations {
            let (first, len) = (art.dofs.start, art.dofs.len());
            for j in art.dofs.clone() {
                self.for_dofs_above(rnea, j, |k| {
                    let e = rnea.s[k].dot(&ic_s[j]);
                    m[art.m_offset + (j - first) * len + (k - first)] = e;
                    m[art.m_offset + (k - first) * len + (j - first)] = e;
                });
                m[art.m_offset + (j - first) * (len + 1)] += armature[j];
            }
        }
        (m, ic_s)
    }

    /// Calls `f(k)` for every velocity `k` of `j`'s link and of its ancestors' joints.
    fn for_dofs_above(&self, rnea: &Rnea, j: usize, mut f: impl FnMut(usize)) {
        let mut link = Some(rnea.link_of[j]);
        while let Some(l) = link {
            self.links[l].dofs.clone().for_each(&mut f);
            link = self.links[l].parent;
        }
    }

    /// Kinematics, inertias, twists, the bias accelerations (`qdd = 0`) and their wrenches,
    /// summed over subtrees, in the kernels' conventions
    /// ([`articulation_kinematics`](super::kernels::articulation_kinematics),
    /// [`articulation_link_dynamics`](super::kernels::articulation_link_dynamics)).
    fn rnea_bias(&self, model: &PlainModel, q: &[f64], qd: &[f64]) -> Rnea {
        let unit = |x: f64, y: f64, z: f64, w: f64| {
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z))
        };
        let nl = self.links.len();
        let mut rnea = Rnea {
            link_of: vec![0; self.n_dof],
            s: vec![V6::zeros(); self.n_dof],
            world_a: Vec::with_capacity(nl),
            inertia: Vec::with_capacity(nl),
            composite: Vec::with_capacity(nl),
            v: Vec::with_capacity(nl),
            a: Vec::with_capacity(nl),
            f: Vec::with_capacity(nl),
        };
        let mut pose = Vec::with_capacity(nl);
        for (l, link) in self.links.iter().enumerate() {
            rnea.world_a.push(join(V3::zeros(), -model.gravity[l]));
            let (p0, r0, v0, a0) = match link.parent {
                Some(p) => {
                    let (pp, rp): &(V3, UnitQuaternion<f64>) = &pose[p];
                    (*pp, *rp, rnea.v[p], rnea.a[p])
                }
                None => (
                    V3::zeros(),
                    UnitQuaternion::identity(),
                    V6::zeros(),
                    rnea.world_a[l],
                ),
            };
            let mut p = p0 + r0 * model.joint_pos[l];
            let mut r = r0 * model.joint_rot[l];
            let axis = model.joint_axis[l];
            let s = link.q.start;
            match link.kind {
                JointType::Fixed => {}
                JointType::Revolute => {
                    r *=
                        UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_unchecked(axis), q[s]);
                }
                JointType::Prismatic => p += r * (axis * q[s]),
                JointType::Ball => r *= unit(q[s], q[s + 1], q[s + 2], q[s + 3]),
                JointType::Free => {
                    p += r * V3::new(q[s], q[s + 1], q[s + 2]);
                    r *= unit(q[s + 3], q[s + 4], q[s + 5], q[s + 6]);
                }
            }
            // Motion vectors: about an axis u through p, (u, p x u); along u, (0, u).
            let d0 = link.dofs.start;
            for d in link.dofs.clone() {
                rnea.link_of[d] = l;
                let k = d - d0;
                let (e, angular) = match link.kind {
                    JointType::Revolute => (axis, true),
                    JointType::Prismatic => (axis, false),
                    JointType::Ball => (V3::ith(k, 1.0), true),
                    _ => (V3::ith(k % 3, 1.0), k >= 3),
                };
                let u = r * e;
                rnea.s[d] = match angular {
                    true => join(u, p.cross(&u)),
                    false => join(V3::zeros(), u),
                };
            }
            // Spatial inertia [J h~; h~^T m] at the origin.
            let rm = r.to_rotation_matrix().into_inner();
            let c = p + rm * model.com[l];
            let m = model.mass[l];
            let j = rm * model.inertia[l] * rm.transpose()
                + (Matrix3::identity() * c.dot(&c) - c * c.transpose()) * m;
            let h = (c * m).cross_matrix();
            let im = blocks(j, h, h.transpose(), Matrix3::identity() * m);
            // Twist and bias acceleration: v = v_p + S qd, a = a_p + v_p x S qd.
            let mut dv = V6::zeros();
            for d in link.dofs.clone() {
                dv += rnea.s[d] * qd[d];
            }
            let v = v0 + dv;
            let a = a0 + cross_m(&v0, &dv);
            rnea.f.push(im * a + cross_f(&v, &(im * v)));
            rnea.v.push(v);
            rnea.a.push(a);
            rnea.inertia.push(im);
            pose.push((p, r));
        }
        rnea.composite = rnea.inertia.clone();
        for l in (0..nl).rev() {
            if let Some(p) = self.links[l].parent {
                let (ic, f) = (rnea.composite[l], rnea.f[l]);
                rnea.composite[p] += ic;
                rnea.f[p] += f;
            }
        }
        rnea
    }

    /// Adds the accelerations of `qdd` to `rnea`'s (each link's `S qdd` down its subtree), and
    /// their wrenches `I S qdd` to the subtree sums.
    fn rnea_accelerate(&self, rnea: &mut Rnea, qdd: &[f64]) {
        let nl = self.links.len();
        let mut da = vec![V6::zeros(); nl];
        for (l, link) in self.links.iter().enumerate() {
            let mut d = link.parent.map_or(V6::zeros(), |p| da[p]);
            for k in link.dofs.clone() {
                d += rnea.s[k] * qdd[k];
            }
            da[l] = d;
            rnea.a[l] += d;
        }
        let mut df: Vec<V6> = (0..nl).map(|l| rnea.inertia[l] * da[l]).collect();
        for l in (0..nl).rev() {
            rnea.f[l] += df[l];
            if let Some(p) = self.links[l].parent {
                let x = df[l];
                df[p] += x;
            }
        }
    }

    /// `d tau_id / d q` (tangent directions) and `d tau_id / d qd` at `rnea`'s state, as
    /// `n_dof x n_dof` rows (zero between articulations); `ic_s[j] = Ic S_j`.
    fn tau_derivatives(&self, rnea: &Rnea, ic_s: &[V6]) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
        let nl = self.links.len();
        // B = -I v~ + (I v)^x + v~* I, as a matrix of its argument, summed over subtrees.
        let mut bc: Vec<M6> = (0..nl)
            .map(|l| {
                let (im, v) = (&rnea.inertia[l], &rnea.v[l]);
                let (w, lv) = (top(v).cross_matrix(), bottom(v).cross_matrix());
                let crm = blocks(w, Matrix3::zeros(), lv, w);
                let crf = blocks(w, lv, Matrix3::zeros(), w);
                let p = im * v;
                let (pn, pf) = (-top(&p).cross_matrix(), -bottom(&p).cross_matrix());
                crf * im - im * crm + blocks(pn, pf, pf, Matrix3::zeros())
            })
            .collect();
        for l in (0..nl).rev() {
            if let Some(p) = self.links[l].parent {
                let x = bc[l];
                bc[p] += x;
            }
        }
        let n = self.n_dof;
        let (mut dq, mut dqd) = (vec![vec![0.0; n]; n], vec![vec![0.0; n]; n]);
        // Per velocity k: u_k, w_k, v_b x S_k - u_k, and the brackets over b's subtree.
        let per_dof: Vec<[V6; 5]> = (0..n)
            .map(|k| {
                let b = rnea.link_of[k];
                let (vp, ap) = match self.links[b].parent {
                    Some(p) => (rnea.v[p], rnea.a[p]),
                    None => (V6::zeros(), rnea.world_a[b]),
                };
                let sk = rnea.s[k];
                let u = cross_m(&sk, &vp);
                let w = cross_m(&sk, &ap) - cross_m(&u, &vp);
                let sdot = cross_m(&rnea.v[b], &sk) - u;
                let g = cross_f(&sk, &rnea.f[b]) - rnea.composite[b] * w - bc[b] * u;
                let h = rnea.composite[b] * sdot + bc[b] * sk;
                [u, w, sdot, g, h]
            })
            .collect();
        for j in 0..n {
            let bj = rnea.link_of[j];
            let z = bc[bj].transpose() * rnea.s[j];
            let [_, _, _, gj, hj] = &per_dof[j];
            self.for_dofs_above(rnea, j, |k| {
                let [u, w, sdot, ..] = &per_dof[k];
                // j at or below k's link.
                dq[j][k] = -(ic_s[j].dot(w) + z.dot(u));
                dqd[j][k] = ic_s[j].dot(sdot) + z.dot(&rnea.s[k]);
                // k's link strictly above j's: the transposed pair.
                if rnea.link_of[k] != bj {
                    dq[k][j] = rnea.s[k].dot(gj);
                    dqd[k][j] = rnea.s[k].dot(hj);
                }
            });
        }
        (dq, dqd)
    }
}

/// An error naming `method`'s result (a named matrix) that is not finite (a state or
/// parameters at which the dynamics overflow).
fn check_finite(method: &str, outputs: [(&str, &[Vec<f64>]); 3]) -> Result<(), Error> {
    for (name, m) in outputs {
        for (i, row) in m.iter().enumerate() {
            if let Some(j) = row.iter().position(|x| !x.is_finite()) {
                return Err(Error::InvalidInput {
                    what: format!("{method}: the result's {name}[{i}][{j}]"),
                    message: "is not finite: the state or the model's parameters overflow the \
                              dynamics (every input was finite)"
                        .into(),
                });
            }
        }
    }
    Ok(())
}
