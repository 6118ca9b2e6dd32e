//! The scalar types kernels compute in, and the value types built on them.

/// A floating-point scalar a kernel can be differentiated in: `f32` (for speed) or `f64` (for
/// checking). Kernels written generically over `R: Real` run in either.
pub trait Real:
    nalgebra::RealField + Copy + Default + Send + Sync + std::fmt::Debug + crate::Value + bytemuck::Pod
{
    /// Converts a literal; the macro emits `R::lit(..)` for float literals in generic kernels.
    fn lit(x: f64) -> Self;
    /// Widens to `f64` (for gradient checks and reports).
    fn to_f64(self) -> f64;
    /// The smallest positive value whose square is still normal; guards singular rules.
    fn tiny() -> Self;
    /// The derivative part of a [`Dual`](crate::Dual) (0 for `f32` and `f64`).
    #[inline(always)]
    fn eps(self) -> f64 {
        0.0
    }
    /// This value with derivative part `eps` (unchanged for `f32` and `f64`, which have none).
    #[inline(always)]
    fn with_eps(self, _eps: f64) -> Self {
        self
    }
}

impl Real for f32 {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn tiny() -> Self {
        1e-18
    }
}

impl Real for f64 {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn tiny() -> Self {
        1e-150
    }
}

/// 2-vector (nalgebra `Vector2`), `f32` unless a scalar is named.
pub type Vec2<R = f32> = nalgebra::Vector2<R>;
/// 3-vector (nalgebra `Vector3`), `f32` unless a scalar is named.
pub type Vec3<R = f32> = nalgebra::Vector3<R>;
/// 4-vector (nalgebra `Vector4`), `f32` unless a scalar is named.
pub type Vec4<R = f32> = nalgebra::Vector4<R>;
/// 2x2 matrix (nalgebra `Matrix2`), `f32` unless a scalar is named.
pub type Mat22<R = f32> = nalgebra::Matrix2<R>;
/// 3x3 matrix (nalgebra `Matrix3`), `f32` unless a scalar is named.
pub type Mat33<R = f32> = nalgebra::Matrix3<R>;
/// Quaternion (nalgebra `Quaternion`, components `i, j, k, w`), not necessarily unit.
pub type Quat<R = f32> = nalgebra::Quaternion<R>;
