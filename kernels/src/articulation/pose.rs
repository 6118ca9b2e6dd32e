//! Frames and mass properties of articulations: a link's id, a rigid transform, a link's
//! inertia, and the quaternion helpers the builder, the loaders, the contact shapes and the
//! fluid share.

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

/// Mass properties of a link, in its frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Inertial {
    /// Mass (kg).
    pub mass: f64,
    /// Centre of mass (m).
    pub com: Vec3<f64>,
    /// Rotational inertia about the centre of mass, in the link's axes (kg m^2).
    pub inertia: Mat33<f64>,
}

impl Inertial {
    /// `mass` at `com` with `inertia` about it.
    pub fn new(mass: f64, com: Vec3<f64>, inertia: Mat33<f64>) -> Self {
        Inertial { mass, com, inertia }
    }

    /// No mass (a frame, or an intermediate link of a compound joint).
    pub fn massless() -> Self {
        Self::new(0.0, Vec3::zeros(), Mat33::zeros())
    }

    /// A point mass.
    pub fn point(mass: f64, com: Vec3<f64>) -> Self {
        Self::new(mass, com, Mat33::zeros())
    }

    /// A solid sphere of `mass` and `radius` centred at `com`.
    pub fn sphere(mass: f64, radius: f64, com: Vec3<f64>) -> Self {
        Self::new(
            mass,
            com,
            Mat33::identity() * (0.4 * mass * radius * radius),
        )
    }

    /// A solid box of `mass` and half extents `half`, centred at `com`, axis aligned.
    pub fn cuboid(mass: f64, half: Vec3<f64>, com: Vec3<f64>) -> Self {
        let (x, y, z) = (half.x * half.x, half.y * half.y, half.z * half.z);
        let i = Mat33::from_diagonal(&Vec3::new(y + z, x + z, x + y)) * (mass / 3.0);
        Self::new(mass, com, i)
    }

    /// The sum of two bodies' mass properties in one frame.
    pub fn combine(&self, other: &Inertial) -> Inertial {
        let m = self.mass + other.mass;
        if m <= 0.0 {
            return Inertial::massless();
        }
        let c = (self.com * self.mass + other.com * other.mass) / m;
        let shift = |i: &Inertial| {
            let d = i.com - c;
            i.inertia + (Mat33::identity() * d.dot(&d) - d * d.transpose()) * i.mass
        };
        Inertial::new(m, c, shift(self) + shift(other))
    }

    /// These mass properties seen from a frame in which this one is at `pose`.
    pub fn transformed(&self, pose: &Pose) -> Inertial {
        let r = rotation_matrix(&pose.rot);
        Inertial::new(
            self.mass,
            pose.transform_point(&self.com),
            r * self.inertia * r.transpose(),
        )
    }
}
