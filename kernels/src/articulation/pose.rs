//! Frames of articulations: a link's id and a rigid transform, and the quaternion helpers the
//! builder, the loaders and the contact shapes share.

use adflex_runtime::prelude::*;

/// A link of an [`ArticulationBuilder`](super::ArticulationBuilder), by its index.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LinkId(pub usize);

/// A rigid transform: position and unit quaternion (`x, y, z, w`, nalgebra's `Quaternion`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Translation (m).
    pub pos: Vec3<f64>,
    /// Rotation.
    pub rot: Quat<f64>,
}

impl Pose {
    /// The identity.
    pub fn identity() -> Self {
        Pose {
            pos: Vec3::zeros(),
            rot: Quat::identity(),
        }
    }

    /// A translation.
    pub fn at(pos: Vec3<f64>) -> Self {
        Pose {
            pos,
            rot: Quat::identity(),
        }
    }

    /// A translation and a rotation.
    pub fn new(pos: Vec3<f64>, rot: Quat<f64>) -> Self {
        Pose { pos, rot }
    }

    /// `self * other`: `other` expressed in `self`'s parent frame.
    pub fn compose(&self, other: &Pose) -> Pose {
        Pose {
            pos: self.pos + rotate(&self.rot, &other.pos),
            rot: self.rot * other.rot,
        }
    }

    /// Maps a point of this frame to the parent frame.
    pub fn transform_point(&self, p: &Vec3<f64>) -> Vec3<f64> {
        self.pos + rotate(&self.rot, p)
    }

    /// Maps a direction of this frame to the parent frame.
    pub fn transform_vector(&self, v: &Vec3<f64>) -> Vec3<f64> {
        rotate(&self.rot, v)
    }
}

/// The shortest rotation taking unit `a` to unit `b`.
pub(crate) fn from_to(a: &Vec3<f64>, b: &Vec3<f64>) -> Quat<f64> {
    let c = a.dot(b);
    if c < -1.0 + 1e-12 {
        // Opposite: half a turn about an axis orthogonal to `a`; for `a = z` about x, as
        // MuJoCo's `zaxis="0 0 -1"` (z x y = -x, the same half turn).
        let o = if a.y.abs() < 0.9 {
            Vec3::y()
        } else {
            Vec3::x()
        };
        return Quat::from_parts(0.0, a.cross(&o).normalize());
    }
    Quat::from_parts(1.0 + c, a.cross(b)).normalize()
}

/// The rotation by `angle` (rad) about the unit `axis`.
pub(crate) fn axis_angle(axis: &Vec3<f64>, angle: f64) -> Quat<f64> {
    let (s, c) = (0.5 * angle).sin_cos();
    Quat::from_parts(c, axis * s)
}

/// `q v q*` for a unit `q`.
pub(crate) fn rotate(q: &Quat<f64>, v: &Vec3<f64>) -> Vec3<f64> {
    let u = q.imag();
    let t = u.cross(v) * 2.0;
    v + t * q.w + u.cross(&t)
}

/// The rotation matrix of a unit quaternion.
pub(crate) fn rotation_matrix(q: &Quat<f64>) -> Mat33<f64> {
    Mat33::from_columns(&[
        rotate(q, &Vec3::x()),
        rotate(q, &Vec3::y()),
        rotate(q, &Vec3::z()),
    ])
}
