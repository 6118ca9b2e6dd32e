//! `Value`: what every kernel value can do so that adjoints and tangents can be built for it
//! without the macro knowing its type.

use nalgebra::{Matrix2, Matrix3, Matrix4, Quaternion, Vector2, Vector3, Vector4};

use crate::Real;

/// A value a kernel computes with. Adjoints and tangents of a value have the value's own type.
///
/// Index types (integers, `bool`, `[u32; N]`) are values with no differentiable components
/// (`DIM == 0`): their adjoints stay zero and accumulating into them does nothing.
pub trait Value: Copy + Send + Sync + 'static {
    /// Number of differentiable scalar components.
    const DIM: usize;
    /// The zero of this type.
    fn zeroed() -> Self;
    /// The zero every adjoint and tangent accumulator starts from: `-0.0` in every component,
    /// the identity of floating-point addition (`-0.0 + x` is `x` bitwise, while `0.0 + -0.0`
    /// is `0.0`), so the compiler can drop the first accumulation into each adjoint.
    #[inline(always)]
    fn neg_zeroed() -> Self {
        Self::zeroed()
    }
    /// `self += other` for adjoint accumulation (a no-op for index types).
    fn acc(&mut self, other: Self);
    /// `self -= other` for adjoint accumulation (a no-op for index types).
    fn acc_neg(&mut self, other: Self);
    /// Differentiable component `k < DIM`, widened to `f64`.
    fn component(&self, k: usize) -> f64;
    /// Sets differentiable component `k < DIM` from an `f64`.
    fn set_component(&mut self, k: usize, x: f64);
    /// Whether the components are [`Dual`](crate::Dual) numbers (see [`crate::second_order`]):
    /// host code that computes in `f64`, which would drop their derivative parts, refuses
    /// them with an error instead of a silently wrong second derivative.
    const DUAL: bool = false;
    /// The relative rounding of the components: `f32::EPSILON` for values in `f32`,
    /// `f64::EPSILON` otherwise (what a tolerance on their derivatives must allow).
    const EPSILON: f64 = f64::EPSILON;
    /// The derivative part of component `k` of a dual value (0 otherwise).
    fn eps_component(&self, _k: usize) -> f64 {
        0.0
    }
    /// Sets the derivative part of component `k` of a dual value (nothing otherwise).
    fn set_eps_component(&mut self, _k: usize, _x: f64) {}
    /// `len` copies of [`Value::zeroed`]. Types whose zero is all-zero bytes take their memory
    /// zeroed from the allocator (for a large array, fresh pages nobody has written yet).
    #[doc(hidden)]
    fn zeroed_vec(len: usize) -> Vec<Self> {
        // For integers, `bool` and the reals, the standard library already asks for zeroed memory.
        vec![Self::zeroed(); len]
    }
}

/// The zero of `v`'s type every adjoint and tangent accumulator starts from
/// ([`Value::neg_zeroed`]).
#[inline(always)]
pub fn zero_like<T: Value>(_v: &T) -> T {
    T::neg_zeroed()
}

/// `adj += g`, the one accumulation the generated adjoints use.
#[inline(always)]
pub fn acc<T: Value>(adj: &mut T, g: T) {
    adj.acc(g)
}

/// `adj -= g`.
#[inline(always)]
pub fn acc_neg<T: Value>(adj: &mut T, g: T) {
    adj.acc_neg(g)
}

macro_rules! index_value {
    ($($t:ty),*) => {$(
        impl Value for $t {
            const DIM: usize = 0;
            #[inline(always)] fn zeroed() -> Self { Default::default() }
            #[inline(always)] fn acc(&mut self, _: Self) {}
            #[inline(always)] fn acc_neg(&mut self, _: Self) {}
            fn component(&self, _: usize) -> f64 { panic!("index values have no differentiable components") }
            fn set_component(&mut self, _: usize, _: f64) { panic!("index values have no differentiable components") }
        }
    )*};
}
// `(usize, usize)` is the index of a matrix entry `m[(r, c)]`.
index_value!(
    u8,
    u16,
    u32,
    u64,
    usize,
    i8,
    i16,
    i32,
    i64,
    isize,
    bool,
    (),
    (usize, usize)
);

impl<T: Value + Default, const N: usize> Value for [T; N] {
    const DIM: usize = T::DIM * N;
    #[inline(always)]
    fn zeroed() -> Self {
        [T::zeroed(); N]
    }
    #[inline(always)]
    fn neg_zeroed() -> Self {
        [T::neg_zeroed(); N]
    }
    #[inline(always)]
    fn acc(&mut self, other: Self) {
        for (a, b) in self.iter_mut().zip(other) {
            a.acc(b);
        }
    }
    #[inline(always)]
    fn acc_neg(&mut self, other: Self) {
        for (a, b) in self.iter_mut().zip(other) {
            a.acc_neg(b);
        }
    }
    fn component(&self, k: usize) -> f64 {
        self[k / T::DIM].component(k % T::DIM)
    }
    fn set_component(&mut self, k: usize, x: f64) {
        self[k / T::DIM].set_component(k % T::DIM, x)
    }
    const DUAL: bool = T::DUAL;
    const EPSILON: f64 = T::EPSILON;
    fn eps_component(&self, k: usize) -> f64 {
        self[k / T::DIM].eps_component(k % T::DIM)
    }
    fn set_eps_component(&mut self, k: usize, x: f64) {
        self[k / T::DIM].set_eps_component(k % T::DIM, x)
    }
}

macro_rules! real_value {
    ($($t:ty),*) => {$(
        impl Value for $t {
            const DIM: usize = 1;
            #[inline(always)] fn zeroed() -> Self { 0.0 }
            #[inline(always)] fn neg_zeroed() -> Self { -0.0 }
            #[inline(always)] fn acc(&mut self, other: Self) { *self += other }
            #[inline(always)] fn acc_neg(&mut self, other: Self) { *self -= other }
            fn component(&self, _: usize) -> f64 { *self as f64 }
            fn set_component(&mut self, _: usize, x: f64) { *self = x as $t }
            const EPSILON: f64 = <$t>::EPSILON as f64;
        }
    )*};
}
real_value!(f32, f64);

macro_rules! matrix_value {
    ($($t:ident: $n:expr),*) => {$(
        impl<R: Real> Value for $t<R> {
            const DIM: usize = $n;
            #[inline(always)] fn zeroed() -> Self { $t::zeros() }
            #[inline(always)] fn neg_zeroed() -> Self { $t::repeat(-R::zero()) }
            #[inline(always)] fn acc(&mut self, other: Self) { *self += other }
            #[inline(always)] fn acc_neg(&mut self, other: Self) { *self -= other }
            fn component(&self, k: usize) -> f64 { self[k].to_f64() }
            fn set_component(&mut self, k: usize, x: f64) { self[k] = R::lit(x).with_eps(self[k].eps()) }
            const DUAL: bool = R::DUAL;
            const EPSILON: f64 = <R as Value>::EPSILON;
            fn eps_component(&self, k: usize) -> f64 { self[k].eps() }
            fn set_eps_component(&mut self, k: usize, x: f64) { self[k] = self[k].with_eps(x) }
            fn zeroed_vec(len: usize) -> Vec<Self> { bytemuck::zeroed_vec(len) }
        }
    )*};
}
matrix_value!(Vector2: 2, Vector3: 3, Vector4: 4, Matrix2: 4, Matrix3: 9, Matrix4: 16);

impl<R: Real> Value for Quaternion<R> {
    const DIM: usize = 4;
    #[inline(always)]
    fn zeroed() -> Self {
        Quaternion::from(Vector4::zeros())
    }
    #[inline(always)]
    fn neg_zeroed() -> Self {
        Quaternion::from(Vector4::repeat(-R::zero()))
    }
    #[inline(always)]
    fn acc(&mut self, other: Self) {
        self.coords += other.coords
    }
    #[inline(always)]
    fn acc_neg(&mut self, other: Self) {
        self.coords -= other.coords
    }
    fn component(&self, k: usize) -> f64 {
        self.coords[k].to_f64()
    }
    fn set_component(&mut self, k: usize, x: f64) {
        self.coords[k] = R::lit(x).with_eps(self.coords[k].eps())
    }
    const DUAL: bool = R::DUAL;
    const EPSILON: f64 = <R as Value>::EPSILON;
    fn eps_component(&self, k: usize) -> f64 {
        self.coords[k].eps()
    }
    fn set_eps_component(&mut self, k: usize, x: f64) {
        self.coords[k] = self.coords[k].with_eps(x)
    }
    fn zeroed_vec(len: usize) -> Vec<Self> {
        bytemuck::zeroed_vec(len)
    }
}
