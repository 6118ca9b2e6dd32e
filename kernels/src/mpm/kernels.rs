//! The kernels of one MLS-MPM step (2D, quadratic B-splines, APIC): particle to grid, grid
//! update with boundary conditions, grid to particle.

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

use super::plastic::{clamp_spectrum2, clamp_spectrum3};

/// The fixed-corotated material (`kind` 0 in [`mpm_p2g`]).
pub const COROTATED: u32 = 0;
/// The compressible neo-Hookean material (`kind` 1).
pub const NEO_HOOKEAN: u32 = 1;
/// A weakly compressible fluid (`kind` 2): the deformation gradient keeps only its volume.
pub const FLUID: u32 = 2;
/// Snow (`kind` 3, Stomakhin et al. 2013): fixed corotated elasticity whose singular values
/// of `F` are clamped to `[1 - compression, 1 + stretch]` each step (the excess becomes plastic
/// deformation, tracked by its volume ratio `Jp`), and whose moduli harden by
/// `exp(hardening (1 - Jp))` (MLS-MPM's `mpm99` convention: the hardening of the step's
/// start).
pub const SNOW: u32 = 3;

/// Quadratic B-spline weight of node `k` (0, 1, 2 from the base node) for a particle at
/// `fx` cells from the base node (`0.5 <= fx < 1.5`).
#[diff_func]
pub fn bspline_weight<R: Real>(fx: R, k: usize) -> R {
    if k == 0 {
        let d = 1.5 - fx;
        0.5 * d * d
    } else if k == 1 {
        let d = fx - 1.0;
        0.75 - d * d
    } else {
        let d = fx - 0.5;
        0.5 * d * d
    }
}

/// The base node of the 3 x 3 stencil of a particle at `xg` (in cells): `floor(xg - 0.5)`
/// per axis, as floats (its derivative is zero).
#[diff_func]
pub fn stencil_base<R: Real>(xg: Vec2<R>) -> Vec2<R> {
    vec2(floor(xg.x - 0.5), floor(xg.y - 0.5))
}

/// The rotation `R` of the polar decomposition `F = R S` in 2D (closed form: `R` rotates by
/// `atan2(F10 - F01, F00 + F11)`). At `F00 + F11 = F10 - F01 = 0` (an inverted, degenerate
/// `F`) the rotation is undefined and the result is 0 with a zero derivative.
#[diff_func]
pub fn polar_rotation<R: Real>(f: Mat22<R>) -> Mat22<R> {
    let d = normalize(vec2(f[(0, 0)] + f[(1, 1)], f[(1, 0)] - f[(0, 1)]));
    mat22(d.x, -d.y, d.y, d.x)
}

/// Kirchhoff stress `tau = P F^T` of a material of `kind` ([`COROTATED`], [`NEO_HOOKEAN`],
/// [`FLUID`]) with Lame parameters `mu`, `lambda` at deformation gradient `f`:
///
/// - fixed corotated: `2 mu (F - R) F^T + lambda (J - 1) J I`;
/// - neo-Hookean: `mu (F F^T - I) + lambda ln(J) I` (needs `J > 0`);
/// - fluid: `lambda (J - 1) J I` (`mu` unused);
/// - any other `kind` is the fluid's (snow's stress, with its plastic projection and
///   hardening, is computed in [`mpm_p2g`] itself).
#[diff_func]
pub fn kirchhoff_stress<R: Real>(f: Mat22<R>, mu: R, lambda: R, kind: u32) -> Mat22<R> {
    let j = determinant(f);
    let id = mat22_identity();
    if kind == 0 {
        let r = polar_rotation(f);
        (f - r) * transpose(f) * (2.0 * mu) + id * (lambda * (j - 1.0) * j)
    } else if kind == 1 {
        (f * transpose(f) - id) * mu + id * (lambda * ln(j))
    } else {
        id * (lambda * (j - 1.0) * j)
    }
}

/// Particle to grid: updates particle `tid`'s deformation gradient into `f_out` (and its
/// plastic volume ratio `Jp` into `jp_out`: [`SNOW`] changes it, the other materials copy
/// it), and scatters its mass, momentum and stress (APIC affine momentum `C` and the MLS force)
/// into the `n_grid x n_grid` nodes of its stencil (`grid_mv`, `grid_m`, node
/// `i * n_grid + j`).
///
/// Snow's plastic projection: with `F = R S` (polar), `S` becomes
/// [`clamp_spectrum2`]`(S, 1 - compression, 1 + stretch)` (the singular values of `F` clamped),
/// `Jp` is multiplied by `det F / det F_new`, and the stress is the corotated one of `F_new`
/// with `mu` and `lambda` times `exp(hardening (1 - Jp))`.
///
/// Active stress: `a F (d d^T) F^T` added to the Kirchhoff stress, with `a =
/// actuation[actuator[p]] * act_gain[p]` and `d = fiber[p]` (a contraction or extension along
/// the fiber in the rest frame).
#[diff_kernel]
pub fn mpm_p2g<R: Real>(
    x: &Array<Vec2<R>>,
    v: &Array<Vec2<R>>,
    c: &Array<Mat22<R>>,
    f: &Array<Mat22<R>>,
    jp: &Array<R>,
    mass: &Array<R>,
    volume: &Array<R>,
    mu: &Array<R>,
    lambda: &Array<R>,
    kind: &Array<u32>,
    compression: &Array<R>,
    stretch: &Array<R>,
    hardening: &Array<R>,
    actuator: &Array<u32>,
    act_gain: &Array<R>,
    fiber: &Array<Vec2<R>>,
    actuation: &Array<R>,
    n_grid: usize,
    dx: R,
    dt: R,
    f_out: &Array<Mat22<R>>,
    jp_out: &Array<R>,
    grid_mv: &Array<Vec2<R>>,
    grid_m: &Array<R>,
) {
    let p = tid();
    let xg = x[p] / dx;
    let base = stencil_base(xg);
    let fx = xg - base;
    let bx = base.x as usize;
    let by = base.y as usize;
    let cp = c[p];
    let mut fp = (mat22_identity() + cp * dt) * f[p];
    let k = kind[p];
    let mut jn = jp[p];
    let mut tau = mat22(0.0, 0.0, 0.0, 0.0);
    if k == 3 {
        // Snow: F = R S, the stretch's eigenvalues clamped, then corotated with hardened moduli.
        let r = polar_rotation(fp);
        let s = clamp_spectrum2(transpose(r) * fp, 1.0 - compression[p], 1.0 + stretch[p]);
        let j = determinant(s);
        jn = jn * determinant(fp) / j;
        fp = r * s;
        let h = exp(hardening[p] * (1.0 - jp[p]));
        tau = (fp - r) * transpose(fp) * (2.0 * mu[p] * h)
            + mat22_identity() * (lambda[p] * h * (j - 1.0) * j);
    } else {
        if k == 2 {
            let sj = sqrt(determinant(fp));
            fp = mat22(sj, 0.0, 0.0, sj);
        }
        tau = kirchhoff_stress(fp, mu[p], lambda[p], k);
    }
    f_out[p] = fp;
    jp_out[p] = jn;
    let d = fiber[p];
    let a = actuation[actuator[p]] * act_gain[p];
    tau += fp * outer(d, d) * transpose(fp) * a;
    let m = mass[p];
    let affine = tau * (-(dt * volume[p] * 4.0) / (dx * dx)) + cp * m;
    let mv = v[p] * m;
    for i in 0..3 {
        let wx = bspline_weight(fx.x, i);
        for j in 0..3 {
            let w = wx * bspline_weight(fx.y, j);
            let dpos = vec2(i as R - fx.x, j as R - fx.y) * dx;
            let node = (bx + i) * n_grid + by + j;
            grid_mv.atomic_add(node, (mv + affine * dpos) * w);
            grid_m.atomic_add(node, w * m);
        }
    }
}

/// Grid update of node `tid` (`i = tid / n_grid`, `j = tid % n_grid`): velocity from
/// momentum (zero at nodes without mass), gravity, then the walls of the box: the nodes
/// `i < bound` and `i > n_grid - bound` (as DiffTaichi's `diffmpm`: `bound` nodes thick on
/// the low side, `bound - 1` on the high side) stop a velocity into the wall; so does the
/// ceiling. At the floor (`j < bound`) a velocity into it is zeroed if `friction < 0`
/// (sticky), else it slides with Coulomb friction `friction` (the normal velocity removed,
/// the tangential one reduced by `friction` times it, stopping if that reverses it).
#[diff_kernel]
pub fn mpm_grid_update<R: Real>(
    grid_mv: &Array<Vec2<R>>,
    grid_m: &Array<R>,
    gravity: &Array<Vec2<R>>,
    n_grid: usize,
    bound: usize,
    friction: R,
    dt: R,
    grid_v: &Array<Vec2<R>>,
) {
    let t = tid();
    let i = t / n_grid;
    let j = t % n_grid;
    let m = grid_m[t];
    // Empty nodes stay at rest (no epsilon in the division: it would bias light nodes).
    let mut vo = vec2(0.0, 0.0);
    if m > 0.0 {
        vo = grid_mv[t] / m + gravity[0] * dt;
    }
    if i < bound && vo.x < 0.0 {
        vo = vec2(0.0, 0.0);
    }
    if i + bound > n_grid && vo.x > 0.0 {
        vo = vec2(0.0, 0.0);
    }
    if j < bound && vo.y < 0.0 {
        if friction < 0.0 {
            vo = vec2(0.0, 0.0);
        } else {
            let lit = abs(vo.x) + 1e-10;
            if lit + friction * vo.y <= 0.0 {
                vo = vec2(0.0, 0.0);
            } else {
                vo = vec2((1.0 + friction * vo.y / lit) * vo.x, 0.0);
            }
        }
    }
    if j + bound > n_grid && vo.y > 0.0 {
        vo = vec2(0.0, 0.0);
    }
    grid_v[t] = vo;
}

/// Grid to particle: particle `tid`'s new velocity and APIC matrix `C` from the grid
/// velocities of its stencil, and its position advected by the new velocity.
#[diff_kernel]
pub fn mpm_g2p<R: Real>(
    x: &Array<Vec2<R>>,
    grid_v: &Array<Vec2<R>>,
    n_grid: usize,
    dx: R,
    dt: R,
    x_out: &Array<Vec2<R>>,
    v_out: &Array<Vec2<R>>,
    c_out: &Array<Mat22<R>>,
) {
    let p = tid();
    let xp = x[p];
    let xg = xp / dx;
    let base = stencil_base(xg);
    let fx = xg - base;
    let bx = base.x as usize;
    let by = base.y as usize;
    let mut nv = vec2(0.0, 0.0);
    let mut nc = mat22(0.0, 0.0, 0.0, 0.0);
    for i in 0..3 {
        let wx = bspline_weight(fx.x, i);
        for j in 0..3 {
            let w = wx * bspline_weight(fx.y, j);
            let dpos = vec2(i as R - fx.x, j as R - fx.y);
            let gv = grid_v[(bx + i) * n_grid + by + j];
            nv += gv * w;
            nc += outer(gv, dpos) * (4.0 * w / dx);
        }
    }
    v_out[p] = nv;
    x_out[p] = xp + nv * dt;
    c_out[p] = nc;
}

/// Adds `x[tid] * weight` into `out[0]` (with `weight = 1 / n`: the mean position).
#[diff_kernel]
pub fn mpm_weighted_sum<R: Real>(x: &Array<Vec2<R>>, weight: R, out: &Array<Vec2<R>>) {
    out.atomic_add(0, x[tid()] * weight);
}

/// The base node of the 3 x 3 x 3 stencil of a particle at `xg` (in cells), 3D.
#[diff_func]
pub fn stencil_base3<R: Real>(xg: Vec3<R>) -> Vec3<R> {
    vec3(floor(xg.x - 0.5), floor(xg.y - 0.5), floor(xg.z - 0.5))
}

/// The rotation of the polar decomposition `F = R S` in 3D by Higham's scaled Newton
/// iteration `R <- (g R + R^-T / g) / 2`, `g = (|R^-1| / |R|)^(1/2)` (Frobenius norms), 10
/// times from `R = F`: orthogonal to rounding for stretches from 1e-4 to 1e4 (tested). Needs
/// `det F > 0` (an inverted `F` gives a reflection): [`Mpm::step`](super::Mpm::step) refuses
/// inverted 3D corotated particles.
#[diff_func]
pub fn polar_rotation3<R: Real>(f: Mat33<R>) -> Mat33<R> {
    let mut r = f;
    for _k in 0..10 {
        let ri = inverse(r);
        let g = sqrt(sqrt(ddot(ri, ri) / ddot(r, r)));
        r = (r * g + transpose(ri) / g) * 0.5;
    }
    r
}

/// Kirchhoff stress in 3D, as [`kirchhoff_stress`].
#[diff_func]
pub fn kirchhoff_stress3<R: Real>(f: Mat33<R>, mu: R, lambda: R, kind: u32) -> Mat33<R> {
    let j = determinant(f);
    let id = mat33_identity();
    if kind == 0 {
        let r = polar_rotation3(f);
        (f - r) * transpose(f) * (2.0 * mu) + id * (lambda * (j - 1.0) * j)
    } else if kind == 1 {
        (f * transpose(f) - id) * mu + id * (lambda * ln(j))
    } else {
        id * (lambda * (j - 1.0) * j)
    }
}

/// Particle to grid in 3D ([`mpm_p2g`] on an `n_grid^3` grid, node `(i n + j) n + k`). A fluid
/// particle's `F` becomes `J^(1/3) I`. `stencil` is 3: the outer loop over the stencil's
/// first axis stays a loop (a bound that is not a literal), because the 27 copies of the body
/// unrolled into one function overflow rustc's stack in debug builds.
#[diff_kernel]
pub fn mpm3_p2g<R: Real>(
    x: &Array<Vec3<R>>,
    v: &Array<Vec3<R>>,
    c: &Array<Mat33<R>>,
    f: &Array<Mat33<R>>,
    jp: &Array<R>,
    mass: &Array<R>,
    volume: &Array<R>,
    mu: &Array<R>,
    lambda: &Array<R>,
    kind: &Array<u32>,
    compression: &Array<R>,
    stretch: &Array<R>,
    hardening: &Array<R>,
    actuator: &Array<u32>,
    act_gain: &Array<R>,
    fiber: &Array<Vec3<R>>,
    actuation: &Array<R>,
    n_grid: usize,
    stencil: usize,
    dx: R,
    dt: R,
    f_out: &Array<Mat33<R>>,
    jp_out: &Array<R>,
    grid_mv: &Array<Vec3<R>>,
    grid_m: &Array<R>,
) {
    let p = tid();
    let xg = x[p] / dx;
    let base = stencil_base3(xg);
    let fx = xg - base;
    let bx = base.x as usize;
    let by = base.y as usize;
    let bz = base.z as usize;
    let cp = c[p];
    let mut fp = (mat33_identity() + cp * dt) * f[p];
    let k = kind[p];
    let mut jn = jp[p];
    let mut tau = mat33_identity() * 0.0;
    if k == 3 {
        let r = polar_rotation3(fp);
        let s = clamp_spectrum3(transpose(r) * fp, 1.0 - compression[p], 1.0 + stretch[p]);
        let j = determinant(s);
        jn = jn * determinant(fp) / j;
        fp = r * s;
        let h = exp(hardening[p] * (1.0 - jp[p]));
        tau = (fp - r) * transpose(fp) * (2.0 * mu[p] * h)
            + mat33_identity() * (lambda[p] * h * (j - 1.0) * j);
    } else {
        if k == 2 {
            let s = pow(determinant(fp), 1.0 / 3.0);
            fp = mat33_identity() * s;
        }
        tau = kirchhoff_stress3(fp, mu[p], lambda[p], k);
    }
    f_out[p] = fp;
    jp_out[p] = jn;
    let d = fiber[p];
    let a = actuation[actuator[p]] * act_gain[p];
    tau += fp * outer(d, d) * transpose(fp) * a;
    let m = mass[p];
    let affine = tau * (-(dt * volume[p] * 4.0) / (dx * dx)) + cp * m;
    let mv = v[p] * m;
    for i in 0..stencil {
        let wx = bspline_weight(fx.x, i);
        for j in 0..3 {
            let wxy = wx * bspline_weight(fx.y, j);
            for l in 0..3 {
                let w = wxy * bspline_weight(fx.z, l);
                let dpos = vec3(i as R - fx.x, j as R - fx.y, l as R - fx.z) * dx;
                let node = ((bx + i) * n_grid + by + j) * n_grid + bz + l;
                grid_mv.atomic_add(node, (mv + affine * dpos) * w);
                grid_m.atomic_add(node, w * m);
            }
        }
    }
}

/// Grid update in 3D ([`mpm_grid_update`]): the floor is the `y = 0` side, the other five
/// sides are walls that stop a velocity into them.
#[diff_kernel]
pub fn mpm3_grid_update<R: Real>(
    grid_mv: &Array<Vec3<R>>,
    grid_m: &Array<R>,
    gravity: &Array<Vec3<R>>,
    n_grid: usize,
    bound: usize,
    friction: R,
    dt: R,
    grid_v: &Array<Vec3<R>>,
) {
    let t = tid();
    let i = t / (n_grid * n_grid);
    let j = (t / n_grid) % n_grid;
    let k = t % n_grid;
    let m = grid_m[t];
    let mut vo = vec3(0.0, 0.0, 0.0);
    if m > 0.0 {
        vo = grid_mv[t] / m + gravity[0] * dt;
    }
    if (i < bound && vo.x < 0.0) || (i + bound > n_grid && vo.x > 0.0) {
        vo = vec3(0.0, 0.0, 0.0);
    }
    if (k < bound && vo.z < 0.0) || (k + bound > n_grid && vo.z > 0.0) {
        vo = vec3(0.0, 0.0, 0.0);
    }
    if j < bound && vo.y < 0.0 {
        if friction < 0.0 {
            vo = vec3(0.0, 0.0, 0.0);
        } else {
            let vt = vec3(vo.x, 0.0, vo.z);
            let lit = length(vt) + 1e-10;
            if lit + friction * vo.y <= 0.0 {
                vo = vec3(0.0, 0.0, 0.0);
            } else {
                vo = vt * (1.0 + friction * vo.y / lit);
            }
        }
    }
    if j + bound > n_grid && vo.y > 0.0 {
        vo = vec3(0.0, 0.0, 0.0);
    }
    grid_v[t] = vo;
}

/// Grid to particle in 3D ([`mpm_g2p`]); `stencil` is 3, as in [`mpm3_p2g`].
#[diff_kernel]
pub fn mpm3_g2p<R: Real>(
    x: &Array<Vec3<R>>,
    grid_v: &Array<Vec3<R>>,
    n_grid: usize,
    stencil: usize,
    dx: R,
    dt: R,
    x_out: &Array<Vec3<R>>,
    v_out: &Array<Vec3<R>>,
    c_out: &Array<Mat33<R>>,
) {
    let p = tid();
    let xp = x[p];
    let xg = xp / dx;
    let base = stencil_base3(xg);
    let fx = xg - base;
    let bx = base.x as usize;
    let by = base.y as usize;
    let bz = base.z as usize;
    let mut nv = vec3(0.0, 0.0, 0.0);
    let mut nc = mat33_identity() * 0.0;
    for i in 0..stencil {
        let wx = bspline_weight(fx.x, i);
        for j in 0..3 {
            let wxy = wx * bspline_weight(fx.y, j);
            for l in 0..3 {
                let w = wxy * bspline_weight(fx.z, l);
                let dpos = vec3(i as R - fx.x, j as R - fx.y, l as R - fx.z);
                let gv = grid_v[((bx + i) * n_grid + by + j) * n_grid + bz + l];
                nv += gv * w;
                nc += outer(gv, dpos) * (4.0 * w / dx);
            }
        }
    }
    v_out[p] = nv;
    x_out[p] = xp + nv * dt;
    c_out[p] = nc;
}

/// Adds `x[tid] * weight` into `out[0]`, 3D.
#[diff_kernel]
pub fn mpm3_weighted_sum<R: Real>(x: &Array<Vec3<R>>, weight: R, out: &Array<Vec3<R>>) {
    out.atomic_add(0, x[tid()] * weight);
}
