//! The mass-spring cage of the field's first demo (dFlex's): a free particle at the centre of
//! a 3 x 3 x 3 lattice of pinned particles, joined to each of the 26 by a damped spring.
//! Optimizing the springs' rest lengths moves where the centre comes to rest.

use adflex_runtime::{Real, Vec3};

use crate::model::{Model, ModelBuilder};

/// The cage's parameters (SI units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Cage<R: Real> {
    /// Distance between neighbouring lattice points (m; default 0.5).
    pub spacing: R,
    /// Mass of the centre particle (kg; default 1).
    pub mass: R,
    /// Stiffness of each spring (N/m; default 50).
    pub ke: R,
    /// Damping of each spring (N s/m; default 2).
    pub kd: R,
    /// Gravity (m/s²; default `(0, -9.81, 0)`).
    pub gravity: Vec3<R>,
}

/// `spacing = 0.5` m, `mass = 1` kg, `ke = 50` N/m, `kd = 2` N s/m, gravity `-9.81` m/s² in
/// y: the centre settles (sagging 2 cm) within about one second.
impl<R: Real> Default for Cage<R> {
    fn default() -> Self {
        Cage {
            spacing: R::lit(0.5),
            mass: R::lit(1.0),
            ke: R::lit(50.0),
            kd: R::lit(2.0),
            gravity: Vec3::new(R::lit(0.0), R::lit(-9.81), R::lit(0.0)),
        }
    }
}

/// A built cage.
#[derive(Clone, Debug)]
pub struct CageScene<R: Real> {
    /// The model (27 particles, 26 springs; the springs' `rest` is the usual target).
    pub model: Model<R>,
    /// Index of the free centre particle.
    pub center: u32,
}

/// Builds the cage centred at the origin.
///
/// ```
/// use adflex_kernels::scenes::cage::{self, Cage};
/// let scene = cage::build::<f64>(Cage::default());
/// assert_eq!(scene.model.particle_count, 27);
/// assert_eq!(scene.model.springs().unwrap().rest.len(), 26);
/// ```
pub fn build<R: Real>(c: Cage<R>) -> CageScene<R> {
    let mut b = ModelBuilder::<R>::new();
    b.gravity = c.gravity;
    let center = b.add_particle(Vec3::zeros(), Vec3::zeros(), c.mass);
    for i in -1i32..=1 {
        for j in -1i32..=1 {
            for k in -1i32..=1 {
                if (i, j, k) == (0, 0, 0) {
                    continue;
                }
                let p = Vec3::new(R::lit(i as f64), R::lit(j as f64), R::lit(k as f64)) * c.spacing;
                let outer = b.add_particle(p, Vec3::zeros(), R::lit(0.0));
                b.add_spring(center, outer, c.ke, c.kd);
            }
        }
    }
    CageScene {
        model: b.finalize(),
        center,
    }
}
