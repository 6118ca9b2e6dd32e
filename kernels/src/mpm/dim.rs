//! The dimension of an MPM model: [`D2`] or [`D3`], each with its vector and matrix types. The
//! builder, model and state are written once over [`Dim`]; the launches of a step per
//! dimension are [`Launches`](super::Launches) (`step.rs`).

use std::fmt::Debug;

use adflex_runtime::prelude::*;
use adflex_runtime::{Element, Mat22, Mat33, Vec2, Vec3};

use super::kernels::{mpm3_weighted_sum, mpm_weighted_sum};

/// Two dimensions: `Vec2`, `Mat22`, a 3 x 3 stencil.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct D2;
/// Three dimensions: `Vec3`, `Mat33`, a 3 x 3 x 3 stencil; the floor is the `y = 0` side.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct D3;

/// What an MPM model needs of its dimension (its types; the launches of a step are
/// [`Launches`](super::Launches), which [`D2`] and [`D3`] implement: code generic over the
/// dimension that steps a model bounds `D: Launches`).
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
    /// Records `out[0] += sum_p x[p] * weight`.
    fn launch_weighted_sum<R: Real>(
        tape: &mut Tape,
        x: &Array<Self::V<R>>,
        weight: R,
        out: &Array<Self::V<R>>,
    );
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
    fn launch_weighted_sum<R: Real>(
        tape: &mut Tape,
        x: &Array<Vec3<R>>,
        weight: R,
        out: &Array<Vec3<R>>,
    ) {
        tape.launch(mpm3_weighted_sum, x.len(), (x, weight, out));
    }
}
