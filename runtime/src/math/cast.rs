//! Casts: `cast::<_, T>(x)` is what `x as T` lowers to. Between `f32` and `f64` the gradient
//! flows (the derivative is 1); every cast from or to an integer (or from `bool`) has zero
//! derivative, which is exact: float to integer is piecewise constant, and integers carry no
//! gradient.

/// Rule of `self as B`.
pub trait CastRule<B>: Sized {
    /// `self as B`.
    fn cast_fwd(self) -> B;
    /// The adjoint of `self` given that of the result.
    fn cast_adj(self, adj: B) -> Self;
    /// The tangent of the result given that of `self`.
    fn cast_tan(self, da: Self) -> B;
}

/// `a as B` (floats, integers, `bool` to integers). Derivative 1 between floats, 0 otherwise.
#[inline(always)]
pub fn cast<A: CastRule<B>, B>(a: A) -> B {
    a.cast_fwd()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`cast`]: `adj as A` between floats, 0 otherwise.
#[inline(always)]
pub fn adj_cast<A: CastRule<B>, B>(a: A, adj: B) -> A {
    a.cast_adj(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`cast`]: `da as B` between floats, 0 otherwise.
#[inline(always)]
pub fn tan_cast<A: CastRule<B>, B>(a: A, da: A) -> B {
    a.cast_tan(da)
}

use crate::Real;

/// Between floats (generic both ways, so `x as R` and `x as f64` work in generic kernels):
/// derivative 1. A `Dual`'s derivative part goes along (to another `Dual`).
impl<A: Real, B: Real> CastRule<B> for A {
    #[inline(always)]
    fn cast_fwd(self) -> B {
        B::lit(self.to_f64()).with_eps(self.eps())
    }
    #[inline(always)]
    fn cast_adj(self, adj: B) -> A {
        A::lit(adj.to_f64()).with_eps(adj.eps())
    }
    #[inline(always)]
    fn cast_tan(self, da: A) -> B {
        B::lit(da.to_f64()).with_eps(da.eps())
    }
}

/// Casts with zero derivative from `$a` to each of the `$b`.
macro_rules! cast_zero {
    ($a:ty => $($b:ty),*) => {$(
        impl CastRule<$b> for $a {
            #[inline(always)]
            fn cast_fwd(self) -> $b { self as $b }
            #[inline(always)]
            fn cast_adj(self, _: $b) -> $a { Default::default() }
            #[inline(always)]
            fn cast_tan(self, _: $a) -> $b { Default::default() }
        }
    )*};
}

/// Integer `$a` to every integer (zero derivative) and to every float (generic over `Real`).
macro_rules! cast_from_int {
    ($($a:ty),*) => {$(
        cast_zero!($a => u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);
        impl<B: Real> CastRule<B> for $a {
            #[inline(always)]
            fn cast_fwd(self) -> B { B::lit(self as f64) }
            #[inline(always)]
            fn cast_adj(self, _: B) -> $a { Default::default() }
            #[inline(always)]
            fn cast_tan(self, _: $a) -> B { B::zero() }
        }
    )*};
}
cast_from_int!(u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);

/// Float to integer (piecewise constant: zero derivative), generic over the float.
macro_rules! cast_to_int {
    ($($b:ty),*) => {$(
        impl<A: Real> CastRule<$b> for A {
            #[inline(always)]
            fn cast_fwd(self) -> $b { self.to_f64() as $b }
            #[inline(always)]
            fn cast_adj(self, _: $b) -> A { A::zero() }
            #[inline(always)]
            fn cast_tan(self, _: A) -> $b { Default::default() }
        }
    )*};
}
cast_to_int!(u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);
cast_zero!(bool => u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;

    #[test]
    fn floats() {
        // f64 -> f64 is the only cast whose output keeps f64 precision for central differences
        check_rule(
            "cast_f64_f64",
            |rng| (any::<f64>(rng),),
            cast::<f64, f64>,
            adj_cast::<f64, f64>,
            tan_cast::<f64, f64>,
        );
        // the others: derivative exactly 1 (up to the rounding of the cast itself)
        assert_eq!(cast::<_, f64>(1.5f32), 1.5);
        assert_eq!(cast::<_, f32>(1.5f64), 1.5f32);
        assert_eq!(cast::<_, f32>(1.5f32), 1.5f32);
        assert_eq!(adj_cast::<_, f64>(1.5f32, 2.0), 2.0f32);
        assert_eq!(adj_cast::<_, f32>(1.5f64, 2.0), 2.0f64);
        assert_eq!(adj_cast::<_, f32>(1.5f32, 2.0), 2.0f32);
        assert_eq!(tan_cast::<_, f32>(1.5f64, 2.0), 2.0f32);
        assert_eq!(tan_cast::<_, f64>(1.5f32, 2.0), 2.0f64);
    }

    #[test]
    fn generic() {
        fn half<R: Real>(i: u32, x: R) -> (R, f64, u32) {
            (cast::<_, R>(i), cast::<_, f64>(x), cast::<_, u32>(x))
        }
        assert_eq!(half(3, 2.5f32), (3.0, 2.5, 2));
        assert_eq!(half(3, 2.5f64), (3.0, 2.5, 2));
    }

    #[test]
    fn integers() {
        assert_eq!(cast::<_, u32>(3.7f32), 3);
        assert_eq!(cast::<_, i32>(-3.7f64), -3);
        assert_eq!(cast::<_, f32>(3u32), 3.0);
        assert_eq!(cast::<_, usize>(3u32), 3);
        assert_eq!(cast::<_, i64>(-3i32), -3);
        assert_eq!(cast::<_, u32>(true), 1);
        assert_eq!(adj_cast::<_, u32>(3.7f32, 5), 0.0);
        assert_eq!(tan_cast::<_, u32>(3.7f32, 1.0), 0);
        assert_eq!(adj_cast::<_, f64>(3u32, 1.0), 0);
        assert_eq!(tan_cast::<_, f64>(3u32, 1), 0.0);
        assert_eq!(adj_cast::<_, usize>(3u32, 1), 0);
    }
}
