//! The dimension of an MPM model: [`D2`] or [`D3`], each with its vector and matrix types and
//! the launches of its kernels. The builder, model and state are written once over [`Dim`].

use std::fmt::Debug;

use adflex_runtime::prelude::*;
use adflex_runtime::{Element, Mat22, Mat33, Vec2, Vec3};

use super::kernels::{
    mpm3_g2p, mpm3_grid_update, mpm3_p2g, mpm3_weighted_sum, mpm_g2p, mpm_grid_update, mpm_p2g,
    mpm_weighted_sum,
};
use super::model::{Mpm, MpmState};

/// Two dimensions: `Vec2`, `Mat22`, a 3 x 3 stencil.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct D2;
/// Three dimensions: `Vec3`, `Mat33`, a 3 x 3 x 3 stencil; the floor is the `y = 0` side.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct D3;

/// What an MPM model needs of its dimension.
pub trait Dim: Copy + Debug + Default + Send + Sync + 'static {
    /// 2 or 3.
    const D: usize;
    /// A point or velocity.
    type V<R: Real>: Element + Copy + PartialEq + Debug;
    /// A deformation gradient or APIC matrix.
    type M<R: Real>: Element + Copy + Debug;
    /// The vector with components `c` (`D` of them).
    fn vector<R: Real>(c: &[f64]) -> Self::V<R>;
    /// The components of `v`.
    fn components<R: Real>(v: &Self::V<R>) -> Vec<f64>;
    /// The identity matrix.
    fn identity<R: Real>() -> Self::M<R>;
    /// Whether every component of `v` is in `[lo, hi)` (false for NaN); no allocation, as
    /// it runs on every particle of every step.
    fn inside<R: Real>(v: &Self::V<R>, lo: f64, hi: f64) -> bool;
    /// The determinant of `m`.
    fn determinant<R: Real>(m: &Self::M<R>) -> f64;
    /// Records the three kernels of one step on `tape` and returns the new state (inputs
    /// already checked).
    fn launch_step<R: Real>(
        mpm: &Mpm<R, Self>,
        tape: &mut Tape,
        state: &MpmState<R, Self>,
        actuation: &Array<R>,
        dt: f64,
    ) -> MpmState<R, Self>;
    /// Records `out[0] += sum_p x[p] * weight`.
    fn launch_weighted_sum<R: Real>(
        tape: &mut Tape,
        x: &Array<Self::V<R>>,
        weight: R,
        out: &Array<Self::V<R>>,
    );
}

/// The grid arrays of a step: momentum, mass, velocity.
type Grid<R, D> = (Array<<D as Dim>::V<R>>, Array<R>, Array<<D as Dim>::V<R>>);

/// The fresh arrays of a step: the next state and the grid.
fn fresh<R: Real, D: Dim>(n: usize, ng: usize) -> (MpmState<R, D>, Grid<R, D>) {
    let cells = ng.pow(D::D as u32);
    (
        MpmState {
            x: Array::zeros(n).named("mpm.x"),
            v: Array::zeros(n).named("mpm.v"),
            c: Array::zeros(n).named("mpm.C"),
            f: Array::zeros(n).named("mpm.F"),
        },
        (
            Array::zeros(cells).named("mpm.grid_mv"),
            Array::zeros(cells).named("mpm.grid_m"),
            Array::zeros(cells).named("mpm.grid_v"),
        ),
    )
}

/// [`Dim::launch_step`] of a dimension: the same three launches in 2D and 3D but for the
/// kernels, and the 3D kernels' `stencil` bound.
macro_rules! launch_step {
    ($d:ty, $p2g:ident, $grid:ident, $g2p:ident $(, $stencil:expr)?) => {
        fn launch_step<R: Real>(
            mpm: &Mpm<R, $d>,
            tape: &mut Tape,
            s: &MpmState<R, $d>,
            actuation: &Array<R>,
            dt: f64,
        ) -> MpmState<R, $d> {
            let (n, ng) = (mpm.particle_count(), mpm.n_grid);
            let (dx, dtr) = (R::lit(mpm.dx), R::lit(dt));
            let (next, (mv, m, gv)) = fresh::<R, $d>(n, ng);
            let p = (&mpm.mass, &mpm.volume, &mpm.mu, &mpm.lambda, &mpm.kind);
            let a = (&mpm.actuator, &mpm.act_gain, &mpm.fiber);
            tape.launch(
                $p2g,
                n,
                (
                    &s.x, &s.v, &s.c, &s.f, p.0, p.1, p.2, p.3, p.4, a.0, a.1, a.2, actuation,
                    ng, $($stencil,)? dx, dtr, &next.f, &mv, &m,
                ),
            );
            let (cells, friction) = (ng.pow(<$d as Dim>::D as u32), R::lit(mpm.friction));
            let grid = (&mv, &m, &mpm.gravity, ng, mpm.bound, friction, dtr, &gv);
            tape.launch($grid, cells, grid);
            tape.launch($g2p, n, (&s.x, &gv, ng, $($stencil,)? dx, dtr, &next.x, &next.v, &next.c));
            next
        }
    };
}

impl Dim for D2 {
    const D: usize = 2;
    type V<R: Real> = Vec2<R>;
    type M<R: Real> = Mat22<R>;
    fn vector<R: Real>(c: &[f64]) -> Vec2<R> {
        Vec2::new(R::lit(c[0]), R::lit(c[1]))
    }
    fn components<R: Real>(v: &Vec2<R>) -> Vec<f64> {
        vec![v.x.to_f64(), v.y.to_f64()]
    }
    fn identity<R: Real>() -> Mat22<R> {
        Mat22::identity()
    }
    fn inside<R: Real>(v: &Vec2<R>, lo: f64, hi: f64) -> bool {
        v.iter().all(|c| (lo..hi).contains(&c.to_f64()))
    }
    fn determinant<R: Real>(m: &Mat22<R>) -> f64 {
        m.map(|v| v.to_f64()).determinant()
    }
    launch_step!(D2, mpm_p2g, mpm_grid_update, mpm_g2p);
    fn launch_weighted_sum<R: Real>(
        tape: &mut Tape,
        x: &Array<Vec2<R>>,
        weight: R,
        out: &Array<Vec2<R>>,
    ) {
        tape.launch(mpm_weighted_sum, x.len(), (x, weight, out));
    }
}

impl Dim for D3 {
    const D: usize = 3;
    type V<R: Real> = Vec3<R>;
    type M<R: Real> = Mat33<R>;
    fn vector<R: Real>(c: &[f64]) -> Vec3<R> {
        Vec3::new(R::lit(c[0]), R::lit(c[1]), R::lit(c[2]))
    }
    fn components<R: Real>(v: &Vec3<R>) -> Vec<f64> {
        vec![v.x.to_f64(), v.y.to_f64(), v.z.to_f64()]
    }
    fn identity<R: Real>() -> Mat33<R> {
        Mat33::identity()
    }
    fn inside<R: Real>(v: &Vec3<R>, lo: f64, hi: f64) -> bool {
        v.iter().all(|c| (lo..hi).contains(&c.to_f64()))
    }
    fn determinant<R: Real>(m: &Mat33<R>) -> f64 {
        m.map(|v| v.to_f64()).determinant()
    }
    launch_step!(D3, mpm3_p2g, mpm3_grid_update, mpm3_g2p, 3usize);
    fn launch_weighted_sum<R: Real>(
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        weight: R,
        out: &Array<Vec3<R>>,
    ) {
        tape.launch(mpm3_weighted_sum, x.len(), (x, weight, out));
    }
}
