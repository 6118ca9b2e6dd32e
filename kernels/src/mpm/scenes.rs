//! Ready-made MPM scenes.

use adflex_runtime::Vec2;

use super::{Material, MpmBuilder};

/// DiffTaichi's `diffmpm` walker on an `n_grid x n_grid` grid of the unit square: a body
/// `0.3 x 0.1` on four legs `0.05 x 0.1`, each leg one actuator (0 to 3, left to right)
/// contracting or extending vertically with strength 4; fixed-corotated material with
/// `mu = lambda = 10`, particle mass and volume 1, sticky floor, gravity 3.8, walls 3 nodes
/// thick. At `n_grid = 128` it has 2,976 particles (DiffTaichi's size); at 64, 744. It stands
/// `0.03` above the bottom of the grid (DiffTaichi's offset), or just inside the walls on
/// coarser grids.
pub fn walker(n_grid: usize) -> MpmBuilder {
    let dx = 1.0 / n_grid as f64;
    let mut b = MpmBuilder::new(n_grid, dx);
    let material = Material::Corotated {
        mu: 10.0,
        lambda: 10.0,
    };
    let offset = Vec2::new(0.1, f64::max(0.03, 3.5 * dx));
    let rect = |b: &mut MpmBuilder, x: f64, y: f64, w: f64, h: f64| {
        b.add_rect(
            offset + Vec2::new(x, y),
            Vec2::new(w, h),
            1.0,
            1.0,
            material,
        )
    };
    rect(&mut b, 0.0, 0.1, 0.3, 0.1);
    for (k, x) in [0.0, 0.05, 0.2, 0.25].into_iter().enumerate() {
        let leg = rect(&mut b, x, 0.0, 0.05, 0.1);
        b.actuate(leg, k, 4.0, Vec2::new(0.0, 1.0));
    }
    b
}
