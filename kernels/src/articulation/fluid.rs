//! Forces of a still or moving fluid on the links, as MuJoCo's inertia-box fluid model.
//!
//! Each link with mass stands, for the fluid, for the box with its inertia: in the link's
//! principal axes of inertia, with principal moments `I` and mass `m`, the box's sides are
//! `b_i = sqrt(6 (I_j + I_k - I_i) / m)`. With the link's angular velocity `w` and the
//! velocity `v` of its centre of mass relative to the wind, both in those axes, a fluid of
//! density `rho` and viscosity `beta` exerts at the centre of mass
//! - viscous (Stokes) drag: force `-3 pi d beta v`, torque `-pi d^3 beta w`, `d` the mean
//!   side;
//! - quadratic drag: force `-rho/2 b_j b_k |v_i| v_i` and torque
//!   `-rho/64 b_i (b_j^4 + b_k^4) |w_i| w_i` along each axis `i`.
//!
//! Set [`ArticulationBuilder::fluid`](super::ArticulationBuilder) (MJCF: `<option density
//! viscosity wind>`); the forces join the step's passive forces (those of a control), as
//! MuJoCo adds them to `qfrc_passive`. The boxes are fixed when the model is built: the
//! forces depend on the masses and inertias given then, not on later edits of the mass
//! arrays, while density, viscosity and wind can be edited and differentiated.

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

/// The fluid's properties.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fluid {
    /// Density (kg/m^3).
    pub density: f64,
    /// Dynamic viscosity (Pa s).
    pub viscosity: f64,
    /// The fluid's velocity (m/s, world frame).
    pub wind: adflex_runtime::Vec3<f64>,
}

/// Fluid forces on link `fluid_link[tid]`, whose principal axes are `fluid_rot` in its frame,
/// centre of mass `fluid_com` (link frame) and inertia box `fluid_box` (full sides); the
/// wrench (moment about the origin, force) is added to `ext_n`, `ext_f`.
#[diff_kernel]
pub fn articulation_fluid<R: Real>(
    fluid_link: &Array<u32>,
    fluid_com: &Array<Vec3<R>>,
    fluid_rot: &Array<Quat<R>>,
    fluid_box: &Array<Vec3<R>>,
    link_p: &Array<Vec3<R>>,
    link_r: &Array<Quat<R>>,
    link_w: &Array<Vec3<R>>,
    link_v: &Array<Vec3<R>>,
    density: &Array<R>,
    viscosity: &Array<R>,
    wind: &Array<Vec3<R>>,
    ext_n: &Array<Vec3<R>>,
    ext_f: &Array<Vec3<R>>,
) {
    let t = tid();
    let l = fluid_link[t] as usize;
    let r = link_r[l] * fluid_rot[t];
    let c = link_p[l] + quat_rotate(link_r[l], fluid_com[t]);
    let w = link_w[l];
    // The centre of mass's velocity relative to the fluid, and the spin, in the box's axes.
    let lv = quat_rotate_inv(r, link_v[l] + cross(w, c) - wind[0]);
    let lw = quat_rotate_inv(r, w);
    let b = fluid_box[t];
    let rho = density[0];
    let beta = viscosity[0];
    let d = (b.x + b.y + b.z) / 3.0;
    let pi = 3.141592653589793;
    let b4 = vec3(
        b.x * b.x * b.x * b.x,
        b.y * b.y * b.y * b.y,
        b.z * b.z * b.z * b.z,
    );
    let drag = vec3(
        b.y * b.z * abs(lv.x) * lv.x,
        b.x * b.z * abs(lv.y) * lv.y,
        b.x * b.y * abs(lv.z) * lv.z,
    );
    let spin = vec3(
        b.x * (b4.y + b4.z) * abs(lw.x) * lw.x,
        b.y * (b4.x + b4.z) * abs(lw.y) * lw.y,
        b.z * (b4.x + b4.y) * abs(lw.z) * lw.z,
    );
    let lf = lv * (-3.0 * pi * d * beta) - drag * (0.5 * rho);
    let ln = lw * (-pi * d * d * d * beta) - spin * (rho / 64.0);
    let f = quat_rotate(r, lf);
    ext_f.atomic_add(l, f);
    ext_n.atomic_add(l, quat_rotate(r, ln) + cross(c, f));
}

/// A link's box for the fluid: the link (in the model's order), its centre of mass (link
/// frame), principal axes (a rotation in the link frame) and the box's full sides.
pub(crate) struct InertiaBox {
    pub link: u32,
    pub com: adflex_runtime::Vec3<f64>,
    pub rot: adflex_runtime::Quat<f64>,
    pub sides: adflex_runtime::Vec3<f64>,
}

/// The inertia box of each link with mass, from the links' mass properties in the model's
/// order.
pub(crate) fn inertia_boxes<'a>(
    inertials: impl Iterator<Item = &'a super::pose::Inertial>,
) -> Vec<InertiaBox> {
    use adflex_runtime::Vec3;
    inertials
        .enumerate()
        .filter(|(_, i)| i.mass > 0.0)
        .map(|(l, i)| {
            let sym = (i.inertia + i.inertia.transpose()) * 0.5;
            let eig = nalgebra::SymmetricEigen::new(sym);
            let mut axes = eig.eigenvectors;
            if axes.determinant() < 0.0 {
                axes.column_mut(2).neg_mut();
            }
            let rot = nalgebra::Rotation3::from_matrix_unchecked(axes);
            let q = *nalgebra::UnitQuaternion::from_rotation_matrix(&rot).quaternion();
            let m = eig.eigenvalues;
            let side = |a: usize, b: usize, c: usize| {
                (6.0 * (m[b] + m[c] - m[a]).max(1e-12) / i.mass).sqrt()
            };
            InertiaBox {
                link: l as u32,
                com: i.com,
                rot: q,
                sides: Vec3::new(side(0, 1, 2), side(1, 0, 2), side(2, 0, 1)),
            }
        })
        .collect()
}
