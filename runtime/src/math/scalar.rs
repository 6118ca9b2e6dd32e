//! Scalar functions: elementary functions, rounding, `min`/`max`/`clamp`, `lerp`, `select`,
//! `step` and `smoothstep`.
//!
//! Every rule is finite at the function's singular points wherever the function itself is
//! finite there; the convention chosen is in each function's docs (they follow NVIDIA Warp).

use super::vector_space::{one, Linear, Ordered};
use crate::{Real, Value};

/// `(forward, adjoint, tangent)` of a one-argument scalar function from its value and its
/// derivative `d` (both expressions in `x`).
macro_rules! unary {
    ($(
        $(#[$doc:meta])*
        $f:ident, $adj:ident, $tan:ident: |$x:ident| $val:expr, d = $d:expr;
    )*) => {$(
        $(#[$doc])*
        #[inline(always)]
        pub fn $f<R: Real>($x: R) -> R {
            $val
        }
        #[doc(hidden)] // a rule: only generated code calls it
        #[doc = concat!("Adjoint of [`", stringify!($f), "`]: `adj * ", stringify!($f), "'(x)`.")]
        #[inline]
        #[allow(unused_variables)]
        pub fn $adj<R: Real>($x: R, adj: R) -> R {
            adj * $d
        }
        #[doc(hidden)] // a rule: only generated code calls it
        #[doc = concat!("Tangent of [`", stringify!($f), "`]: `dx * ", stringify!($f), "'(x)`.")]
        #[inline]
        #[allow(unused_variables)]
        pub fn $tan<R: Real>($x: R, dx: R) -> R {
            dx * $d
        }
    )*};
}

/// `1 / sqrt(1 - x^2)` for `|x| < 1`, 0 otherwise (the derivative of asin; Warp's convention).
#[inline]
fn inv_sqrt_one_minus_sq<R: Real>(x: R) -> R {
    let s = R::one() - x * x;
    if s > R::zero() {
        R::one() / s.sqrt()
    } else {
        R::zero()
    }
}

/// `x` clamped to `[-1, 1]` (the domain of asin and acos).
#[inline(always)]
fn clamp_unit<R: Real>(x: R) -> R {
    if x < -R::one() {
        -R::one()
    } else if x > R::one() {
        R::one()
    } else {
        x
    }
}

unary! {
    /// Square root. Singular point: at `x == 0` the derivative is taken as 0 (not infinite);
    /// for `x < 0` value and derivative are NaN.
    sqrt, adj_sqrt, tan_sqrt: |x| x.sqrt(),
        d = if x == R::zero() { R::zero() } else { R::lit(0.5) / x.sqrt() };
    /// Sine. No singular points.
    sin, adj_sin, tan_sin: |x| x.sin(), d = x.cos();
    /// Cosine. No singular points.
    cos, adj_cos, tan_cos: |x| x.cos(), d = -x.sin();
    /// Tangent. Infinite, like the function, at odd multiples of pi/2.
    tan, adj_tan, tan_tan: |x| x.tan(), d = { let c = x.cos(); R::one() / (c * c) };
    /// Arcsine of `x` clamped to `[-1, 1]`. Singular points: derivative 0 for `|x| >= 1`
    /// (Warp's convention).
    asin, adj_asin, tan_asin: |x| clamp_unit(x).asin(), d = inv_sqrt_one_minus_sq(x);
    /// Arccosine of `x` clamped to `[-1, 1]`. Singular points: derivative 0 for `|x| >= 1`
    /// (Warp's convention).
    acos, adj_acos, tan_acos: |x| clamp_unit(x).acos(), d = -inv_sqrt_one_minus_sq(x);
    /// Arctangent. No singular points.
    atan, adj_atan, tan_atan: |x| x.atan(), d = R::one() / (R::one() + x * x);
    /// Hyperbolic sine. No singular points.
    sinh, adj_sinh, tan_sinh: |x| x.sinh(), d = x.cosh();
    /// Hyperbolic cosine. No singular points.
    cosh, adj_cosh, tan_cosh: |x| x.cosh(), d = x.sinh();
    /// Hyperbolic tangent. No singular points.
    tanh, adj_tanh, tan_tanh: |x| x.tanh(), d = { let t = x.tanh(); R::one() - t * t };
    /// Exponential. No singular points.
    exp, adj_exp, tan_exp: |x| x.exp(), d = x.exp();
    /// Natural logarithm. At `x == 0` value and derivative are infinite, like the function;
    /// NaN for `x < 0`.
    ln, adj_ln, tan_ln: |x| x.ln(), d = R::one() / x;
    /// Base-2 logarithm. At `x == 0` value and derivative are infinite, like the function.
    log2, adj_log2, tan_log2: |x| x.log2(), d = R::one() / (x * R::ln_2());
    /// Base-10 logarithm. At `x == 0` value and derivative are infinite, like the function.
    log10, adj_log10, tan_log10: |x| x.log10(), d = R::one() / (x * R::ln_10());
    /// Largest integer `<= x`. Zero derivative (piecewise constant).
    floor, adj_floor, tan_floor: |x| x.floor(), d = R::zero();
    /// Smallest integer `>= x`. Zero derivative (piecewise constant).
    ceil, adj_ceil, tan_ceil: |x| x.ceil(), d = R::zero();
    /// Nearest integer, halves away from zero. Zero derivative (piecewise constant).
    round, adj_round, tan_round: |x| x.round(), d = R::zero();
    /// 1 if `x >= 0`, else 0 (note: Warp's `step` is the reverse). Zero derivative.
    step, adj_step, tan_step: |x| if x >= R::zero() { R::one() } else { R::zero() }, d = R::zero();
}

// ---------------------------------------------------------------------------------------------
// two-argument functions

/// `atan2(y, x)`, the angle of the point `(x, y)`. Singular point: zero gradient at `(0, 0)`.
#[inline(always)]
pub fn atan2<R: Real>(y: R, x: R) -> R {
    y.atan2(x)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`atan2`](fn@atan2): `adj * (x, -y) / (x^2 + y^2)` (for `y`, `x`); zero at `(0, 0)`.
#[inline]
pub fn adj_atan2<R: Real>(y: R, x: R, adj: R) -> (R, R) {
    let d = x * x + y * y;
    if d > R::zero() {
        (adj * x / d, -adj * y / d)
    } else {
        (R::zero(), R::zero())
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`atan2`](fn@atan2): `(x dy - y dx) / (x^2 + y^2)`; zero at `(0, 0)`.
#[inline]
pub fn tan_atan2<R: Real>(y: R, x: R, dy: R, dx: R) -> R {
    let d = x * x + y * y;
    if d > R::zero() {
        (x * dy - y * dx) / d
    } else {
        R::zero()
    }
}

/// `d/dx x^y` and `d/dy x^y`, finite everywhere: `d/dx` is `y x^(y-1)` except at `x == 0`,
/// where it is 1 for `y == 1` and 0 otherwise (infinite for `y < 1` in truth); `d/dy` is
/// `ln(x) x^y` for `x > 0` and 0 otherwise.
#[inline]
fn d_pow<R: Real>(x: R, y: R) -> (R, R) {
    let dx = if x == R::zero() {
        if y == R::one() {
            R::one()
        } else {
            R::zero()
        }
    } else {
        y * x.powf(y - R::one())
    };
    let dy = if x > R::zero() {
        x.ln() * x.powf(y)
    } else {
        R::zero()
    };
    (dx, dy)
}

/// `x^y` for real `y`. Singular points: at `x == 0` the derivative in `x` is 0 (1 if `y == 1`)
/// instead of infinite; the derivative in `y`, `ln(x) x^y`, is taken as 0 for `x <= 0`.
/// Negative `x` with non-integer `y` gives NaN like the function.
#[inline(always)]
pub fn pow<R: Real>(x: R, y: R) -> R {
    x.powf(y)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`pow`](fn@pow): `adj * (y x^(y-1), ln(x) x^y)`, with the conventions of [`pow`](fn@pow).
#[inline]
pub fn adj_pow<R: Real>(x: R, y: R, adj: R) -> (R, R) {
    let (dx, dy) = d_pow(x, y);
    (adj * dx, adj * dy)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`pow`](fn@pow): `y x^(y-1) dx + ln(x) x^y dy`, with the conventions of [`pow`](fn@pow).
#[inline]
pub fn tan_pow<R: Real>(x: R, y: R, dx: R, dy: R) -> R {
    let (gx, gy) = d_pow(x, y);
    gx * dx + gy * dy
}

/// `n x^(n-1)`, 0 for `n == 0`.
#[inline]
fn d_powi<R: Real>(x: R, n: i32) -> R {
    if n == 0 {
        R::zero()
    } else {
        R::lit(n as f64) * x.powi(n - 1)
    }
}

/// `x^n` for an integer `n`. Derivative `n x^(n-1)` (0 for `n == 0`); at `x == 0` with `n < 0`
/// value and derivative are infinite like the function. `n` is not differentiable.
#[inline(always)]
pub fn powi<R: Real>(x: R, n: i32) -> R {
    x.powi(n)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`powi`](fn@powi): `(adj n x^(n-1), 0)`.
#[inline]
pub fn adj_powi<R: Real>(x: R, n: i32, adj: R) -> (R, i32) {
    (adj * d_powi(x, n), 0)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`powi`](fn@powi): `n x^(n-1) dx`.
#[inline]
pub fn tan_powi<R: Real>(x: R, n: i32, dx: R, _dn: i32) -> R {
    dx * d_powi(x, n)
}

// ---------------------------------------------------------------------------------------------
// abs, sign: scalars and signed integers

/// Rule of `abs` and `sign`: `R` and the signed integers.
pub trait SignedRule: Value {
    /// `|x|`.
    fn abs_fwd(self) -> Self;
    /// -1, 0 or 1.
    fn sign_fwd(self) -> Self;
    /// `adj * sign(x)` (zero for integers).
    fn abs_adj(self, adj: Self) -> Self;
}

impl<R: Real> SignedRule for R {
    #[inline(always)]
    fn abs_fwd(self) -> Self {
        self.abs()
    }
    #[inline(always)]
    fn sign_fwd(self) -> Self {
        if self > R::zero() {
            R::one()
        } else if self < R::zero() {
            -R::one()
        } else {
            R::zero()
        }
    }
    #[inline]
    fn abs_adj(self, adj: Self) -> Self {
        adj * self.sign_fwd()
    }
}

macro_rules! signed_int {
    ($($t:ty),*) => {$(
        impl SignedRule for $t {
            #[inline(always)]
            fn abs_fwd(self) -> Self { self.abs() }
            #[inline(always)]
            fn sign_fwd(self) -> Self { self.signum() }
            #[inline(always)]
            fn abs_adj(self, _: Self) -> Self { 0 }
        }
    )*};
}
signed_int!(i8, i16, i32, i64, isize);

/// `|x|` (scalars, signed integers). Derivative `sign(x)`; singular point: `abs'(0) = 0`.
#[inline(always)]
pub fn abs<T: SignedRule>(x: T) -> T {
    x.abs_fwd()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`abs`](fn@abs): `adj * sign(x)` (0 at `x == 0`).
#[inline(always)]
pub fn adj_abs<T: SignedRule>(x: T, adj: T) -> T {
    x.abs_adj(adj)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`abs`](fn@abs): `dx * sign(x)` (0 at `x == 0`).
#[inline(always)]
pub fn tan_abs<T: SignedRule>(x: T, dx: T) -> T {
    x.abs_adj(dx)
}

/// Sign of `x`: -1, 0 or 1, with `sign(0) == 0` (scalars, signed integers). Zero derivative
/// everywhere.
#[inline(always)]
pub fn sign<T: SignedRule>(x: T) -> T {
    x.sign_fwd()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`sign`](fn@sign): zero.
#[inline(always)]
pub fn adj_sign<T: SignedRule>(_x: T, _adj: T) -> T {
    T::zeroed()
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`sign`](fn@sign): zero.
#[inline(always)]
pub fn tan_sign<T: SignedRule>(_x: T, _dx: T) -> T {
    T::zeroed()
}

// ---------------------------------------------------------------------------------------------
// min, max, clamp: scalars and integers

/// `if a < b { a } else { b }` (scalars, integers). Tie: the gradient goes to `b` (Warp).
#[inline(always)]
pub fn min<T: Ordered>(a: T, b: T) -> T {
    if a < b {
        a
    } else {
        b
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`min`](fn@min): `adj` to the argument returned (`b` on a tie).
#[inline]
pub fn adj_min<T: Ordered>(a: T, b: T, adj: T) -> (T, T) {
    if a < b {
        (adj, T::zeroed())
    } else {
        (T::zeroed(), adj)
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`min`](fn@min): the tangent of the argument returned (`b` on a tie).
#[inline]
pub fn tan_min<T: Ordered>(a: T, b: T, da: T, db: T) -> T {
    if a < b {
        da
    } else {
        db
    }
}

/// `if a > b { a } else { b }` (scalars, integers). Tie: the gradient goes to `b` (Warp).
#[inline(always)]
pub fn max<T: Ordered>(a: T, b: T) -> T {
    if a > b {
        a
    } else {
        b
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`max`](fn@max): `adj` to the argument returned (`b` on a tie).
#[inline]
pub fn adj_max<T: Ordered>(a: T, b: T, adj: T) -> (T, T) {
    if a > b {
        (adj, T::zeroed())
    } else {
        (T::zeroed(), adj)
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`max`](fn@max): the tangent of the argument returned (`b` on a tie).
#[inline]
pub fn tan_max<T: Ordered>(a: T, b: T, da: T, db: T) -> T {
    if a > b {
        da
    } else {
        db
    }
}

/// `if x < lo { lo } else if x > hi { hi } else { x }` (scalars, integers). Ties (`x == lo` or
/// `x == hi`) send the gradient to `x` (Warp).
#[inline(always)]
pub fn clamp<T: Ordered>(x: T, lo: T, hi: T) -> T {
    if x < lo {
        lo
    } else if x > hi {
        hi
    } else {
        x
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`clamp`](fn@clamp): `adj` to the argument returned (`x` on ties).
#[inline]
pub fn adj_clamp<T: Ordered>(x: T, lo: T, hi: T, adj: T) -> (T, T, T) {
    let z = T::zeroed();
    if x < lo {
        (z, adj, z)
    } else if x > hi {
        (z, z, adj)
    } else {
        (adj, z, z)
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`clamp`](fn@clamp): the tangent of the argument returned (`x` on ties).
#[inline]
pub fn tan_clamp<T: Ordered>(x: T, lo: T, hi: T, dx: T, dlo: T, dhi: T) -> T {
    if x < lo {
        dlo
    } else if x > hi {
        dhi
    } else {
        dx
    }
}

// ---------------------------------------------------------------------------------------------
// lerp, select, smoothstep

/// `a (1 - t) + b t` for `a`, `b` scalars, vectors, matrices or quaternions and a scalar `t`.
/// No singular points.
#[inline(always)]
pub fn lerp<T: Linear>(a: T, b: T, t: T::Scalar) -> T {
    a.lin_scale(one::<T::Scalar>() - t).lin_add(b.lin_scale(t))
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`lerp`](fn@lerp): `(adj (1 - t), adj t, <adj, b - a>)`.
#[inline]
pub fn adj_lerp<T: Linear>(a: T, b: T, t: T::Scalar, adj: T) -> (T, T, T::Scalar) {
    (
        adj.lin_scale(one::<T::Scalar>() - t),
        adj.lin_scale(t),
        adj.lin_inner(b.lin_sub(a)),
    )
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`lerp`](fn@lerp): `da (1 - t) + db t + (b - a) dt`.
#[inline]
pub fn tan_lerp<T: Linear>(a: T, b: T, t: T::Scalar, da: T, db: T, dt: T::Scalar) -> T {
    lerp(da, db, t).lin_add(b.lin_sub(a).lin_scale(dt))
}

/// `a` if `c`, else `b`, for any value type. The gradient goes to the argument returned; `c`
/// is not differentiable.
#[inline(always)]
pub fn select<T: Value>(c: bool, a: T, b: T) -> T {
    if c {
        a
    } else {
        b
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`select`](fn@select): `(false, adj, 0)` if `c`, else `(false, 0, adj)`.
#[inline]
pub fn adj_select<T: Value>(c: bool, _a: T, _b: T, adj: T) -> (bool, T, T) {
    if c {
        (false, adj, T::zeroed())
    } else {
        (false, T::zeroed(), adj)
    }
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`select`](fn@select): `da` if `c`, else `db`.
#[inline]
pub fn tan_select<T: Value>(c: bool, _a: T, _b: T, _dc: bool, da: T, db: T) -> T {
    if c {
        da
    } else {
        db
    }
}

/// `(t, dt/de0, dt/de1, dt/dx)` for `t = (x - e0) / (e1 - e0)` clamped to `[0, 1]`, the
/// derivatives being zero where `t` is clamped (also where `e0 == e1`).
#[inline]
fn smoothstep_t<R: Real>(e0: R, e1: R, x: R) -> (R, R, R, R) {
    let (zero, one) = (R::zero(), R::one());
    let w = e1 - e0;
    if w == zero {
        let t = if x < e0 { zero } else { one };
        return (t, zero, zero, zero);
    }
    let t = (x - e0) / w;
    if t <= zero {
        (zero, zero, zero, zero)
    } else if t >= one {
        (one, zero, zero, zero)
    } else {
        (t, (t - one) / w, -t / w, one / w)
    }
}

/// Hermite smoothstep `t^2 (3 - 2t)` with `t = clamp((x - e0) / (e1 - e0), 0, 1)`. Outside
/// `(e0, e1)` the gradient is zero; singular point: for `e0 == e1` it is a step (0 for
/// `x < e0`, else 1) with zero gradient.
#[inline(always)]
pub fn smoothstep<R: Real>(e0: R, e1: R, x: R) -> R {
    let t = smoothstep_t(e0, e1, x).0;
    t * t * (R::lit(3.0) - R::lit(2.0) * t)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Adjoint of [`smoothstep`](fn@smoothstep): `adj 6t(1-t) dt/d(e0, e1, x)`.
#[inline]
pub fn adj_smoothstep<R: Real>(e0: R, e1: R, x: R, adj: R) -> (R, R, R) {
    let (t, t0, t1, tx) = smoothstep_t(e0, e1, x);
    let g = adj * R::lit(6.0) * t * (R::one() - t);
    (g * t0, g * t1, g * tx)
}
#[doc(hidden)] // a rule: only generated code calls it
/// Tangent of [`smoothstep`](fn@smoothstep): `6t(1-t) (dt/de0 de0 + dt/de1 de1 + dt/dx dx)`.
#[inline]
pub fn tan_smoothstep<R: Real>(e0: R, e1: R, x: R, de0: R, de1: R, dx: R) -> R {
    let (t, t0, t1, tx) = smoothstep_t(e0, e1, x);
    R::lit(6.0) * t * (R::one() - t) * (t0 * de0 + t1 * de1 + tx * dx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::check::*;
    use crate::{Mat22, Mat33, Quat, Vec2, Vec3, Vec4};

    /// A pair `(lo, hi)` with `lo < hi` and `x` around them, for `clamp` and `smoothstep`.
    fn lo<T: Value>(rng: &mut Rng) -> T {
        fill(rng, -1.0, -0.3)
    }
    fn hi<T: Value>(rng: &mut Rng) -> T {
        fill(rng, 0.3, 1.0)
    }
    fn bool_any(rng: &mut Rng) -> bool {
        rng.below(2) == 0
    }

    fd_tests! {
        sqrt_r: sqrt, adj_sqrt, tan_sqrt [R = pos];
        sin_r: sin, adj_sin, tan_sin [R = wide];
        cos_r: cos, adj_cos, tan_cos [R = wide];
        tan_r: tan, adj_tan, tan_tan [R = any];
        asin_r: asin, adj_asin, tan_asin [R = unit];
        acos_r: acos, adj_acos, tan_acos [R = unit];
        atan_r: atan, adj_atan, tan_atan [R = wide];
        sinh_r: sinh, adj_sinh, tan_sinh [R = wide];
        cosh_r: cosh, adj_cosh, tan_cosh [R = wide];
        tanh_r: tanh, adj_tanh, tan_tanh [R = wide];
        exp_r: exp, adj_exp, tan_exp [R = wide];
        ln_r: ln, adj_ln, tan_ln [R = pos];
        log2_r: log2, adj_log2, tan_log2 [R = pos];
        log10_r: log10, adj_log10, tan_log10 [R = pos];
        floor_r: floor, adj_floor, tan_floor [R = wide];
        ceil_r: ceil, adj_ceil, tan_ceil [R = wide];
        round_r: round, adj_round, tan_round [R = wide];
        step_r: step, adj_step, tan_step [R = any];
        atan2_r: atan2, adj_atan2, tan_atan2 [R = any, R = any];
        pow_r: pow, adj_pow, tan_pow [R = pos, R = wide];
        powi_r: powi, adj_powi, tan_powi [R = away, i32 = |rng: &mut Rng| rng.below(7) as i32 - 3];
        abs_r: abs, adj_abs, tan_abs [R = any];
        sign_r: sign, adj_sign, tan_sign [R = any];
        min_r: min, adj_min, tan_min [R = any, R = any];
        max_r: max, adj_max, tan_max [R = any, R = any];
        clamp_r: clamp, adj_clamp, tan_clamp [R = wide, R = lo, R = hi];
        lerp_r: lerp, adj_lerp, tan_lerp [R = any, R = any, R = any];
        lerp_v2: lerp, adj_lerp, tan_lerp [Vec2<R> = any, Vec2<R> = any, R = any];
        lerp_v3: lerp, adj_lerp, tan_lerp [Vec3<R> = any, Vec3<R> = any, R = any];
        lerp_v4: lerp, adj_lerp, tan_lerp [Vec4<R> = any, Vec4<R> = any, R = any];
        lerp_m22: lerp, adj_lerp, tan_lerp [Mat22<R> = any, Mat22<R> = any, R = any];
        lerp_m33: lerp, adj_lerp, tan_lerp [Mat33<R> = any, Mat33<R> = any, R = any];
        lerp_q: lerp, adj_lerp, tan_lerp [Quat<R> = any, Quat<R> = any, R = any];
        select_r: select, adj_select, tan_select [bool = bool_any, R = any, R = any];
        select_v3: select, adj_select, tan_select [bool = bool_any, Vec3<R> = any, Vec3<R> = any];
        select_m33: select, adj_select, tan_select [bool = bool_any, Mat33<R> = any, Mat33<R> = any];
        select_u32: select, adj_select, tan_select [bool = bool_any, u32 = just(1u32), u32 = just(2u32)];
        smoothstep_inside: smoothstep, adj_smoothstep, tan_smoothstep [R = lo, R = hi, R = |r: &mut Rng| fill(r, -0.3, 0.3)];
        smoothstep_any: smoothstep, adj_smoothstep, tan_smoothstep [R = lo, R = hi, R = wide];
        smoothstep_reversed: smoothstep, adj_smoothstep, tan_smoothstep [R = hi, R = lo, R = any];
    }

    #[test]
    fn singular_points() {
        // sqrt'(0) = 0
        assert_eq!(sqrt(0.0f64), 0.0);
        assert_eq!(adj_sqrt(0.0f64, 1.0), 0.0);
        assert_eq!(tan_sqrt(0.0f32, 1.0), 0.0);
        // asin, acos at +-1 and beyond: finite values (clamped), derivative 0
        for x in [1.0f64, -1.0, 1.5, -1.5] {
            for (v, a, t) in [
                (asin(x), adj_asin(x, 1.0), tan_asin(x, 1.0)),
                (acos(x), adj_acos(x, 1.0), tan_acos(x, 1.0)),
            ] {
                assert!(v.is_finite(), "value at {x}");
                assert_eq!((a, t), (0.0, 0.0), "derivative at {x}");
            }
        }
        assert_eq!(acos(1.0f64), 0.0);
        assert_eq!(acos(-1.0f64), std::f64::consts::PI);
        assert_eq!(asin(1.0f64), std::f64::consts::FRAC_PI_2);
        assert_eq!(asin(-1.0f64), -std::f64::consts::FRAC_PI_2);
        assert_eq!(acos(1.0f32), 0.0);
        assert_eq!(adj_acos(-1.0f32, 1.0), 0.0);
        // atan2(0, 0): zero gradient
        assert_eq!(atan2(0.0f64, 0.0), 0.0);
        assert_eq!(adj_atan2(0.0f64, 0.0, 1.0), (0.0, 0.0));
        assert_eq!(tan_atan2(0.0f64, 0.0, 1.0, 1.0), 0.0);
        // abs'(0) = 0, sign(0) = 0
        assert_eq!(abs(0.0f64), 0.0);
        assert_eq!(adj_abs(0.0f64, 1.0), 0.0);
        assert_eq!(tan_abs(0.0f64, 1.0), 0.0);
        assert_eq!(adj_abs(-2.0f64, 1.0), -1.0);
        assert_eq!(sign(0.0f64), 0.0);
        assert_eq!(sign(-3.0f32), -1.0);
        assert_eq!(adj_sign(2.0f64, 1.0), 0.0);
        // min, max, clamp ties
        assert_eq!(adj_min(1.0f64, 1.0, 1.0), (0.0, 1.0));
        assert_eq!(tan_min(1.0f64, 1.0, 2.0, 3.0), 3.0);
        assert_eq!(adj_max(1.0f64, 1.0, 1.0), (0.0, 1.0));
        assert_eq!(tan_max(1.0f64, 1.0, 2.0, 3.0), 3.0);
        assert_eq!(adj_clamp(0.0f64, 0.0, 1.0, 1.0), (1.0, 0.0, 0.0));
        assert_eq!(adj_clamp(1.0f64, 0.0, 1.0, 1.0), (1.0, 0.0, 0.0));
        assert_eq!(tan_clamp(1.0f64, 0.0, 1.0, 2.0, 3.0, 4.0), 2.0);
        assert_eq!(adj_clamp(-1.0f64, 0.0, 1.0, 1.0), (0.0, 1.0, 0.0));
        assert_eq!(adj_clamp(2.0f64, 0.0, 1.0, 1.0), (0.0, 0.0, 1.0));
        // pow at x == 0: finite
        assert_eq!(adj_pow(0.0f64, 0.5, 1.0), (0.0, 0.0));
        assert_eq!(adj_pow(0.0f64, 1.0, 1.0), (1.0, 0.0));
        assert_eq!(adj_pow(0.0f64, 3.0, 1.0), (0.0, 0.0));
        assert_eq!(adj_pow(0.0f64, 0.0, 1.0), (0.0, 0.0));
        assert_eq!(tan_pow(0.0f64, 0.5, 1.0, 1.0), 0.0);
        // pow with x < 0 and integer y: d/dx still right, d/dy taken as 0
        assert_eq!(adj_pow(-2.0f64, 2.0, 1.0), (-4.0, 0.0));
        // powi with n == 0
        assert_eq!(adj_powi(0.0f64, 0, 1.0), (0.0, 0));
        // smoothstep with e0 == e1: a step with zero gradient
        assert_eq!(smoothstep(1.0f64, 1.0, 0.5), 0.0);
        assert_eq!(smoothstep(1.0f64, 1.0, 1.5), 1.0);
        assert_eq!(adj_smoothstep(1.0f64, 1.0, 1.5, 1.0), (0.0, 0.0, 0.0));
        // rounding and step: zero gradient
        assert_eq!(adj_floor(1.5f64, 1.0), 0.0);
        assert_eq!(step(0.0f64), 1.0);
        assert_eq!(step(-1e-30f64), 0.0);
        assert_eq!(adj_step(0.0f64, 1.0), 0.0);
    }

    #[test]
    fn integers() {
        assert_eq!(min(3u32, 2), 2);
        assert_eq!(max(3usize, 2), 3);
        assert_eq!(clamp(7i32, 0, 5), 5);
        assert_eq!(clamp(-7i64, 0, 5), 0);
        assert_eq!(adj_min(3u32, 2, 0), (0, 0));
        assert_eq!(abs(-3i32), 3);
        assert_eq!(sign(-3i32), -1);
        assert_eq!(sign(0i64), 0);
        assert_eq!(adj_abs(-3i32, 1), 0);
        assert_eq!(select(true, 1u32, 2), 1);
        assert_eq!(select(false, [1u32, 2], [3, 4]), [3, 4]);
    }

    #[test]
    fn values() {
        assert_eq!(lerp(1.0f64, 3.0, 0.25), 1.5);
        assert_eq!(smoothstep(0.0f64, 2.0, 1.0), 0.5);
        assert_eq!(smoothstep(0.0f64, 2.0, -1.0), 0.0);
        assert_eq!(smoothstep(0.0f64, 2.0, 3.0), 1.0);
        assert_eq!(round(-2.5f64), -3.0);
        assert_eq!(powi(2.0f64, -2), 0.25);
        // literal inference
        let v = Vec3::new(1.0f32, 2.0, 3.0);
        let _: Vec3<f32> = lerp(v, v, 0.5);
        let _: f32 = min(1.0, 2.0f32);
        let _: f32 = lerp(1.0, 2.0, 0.5f32);
        let _: f32 = clamp(0.5f32, 0.0, 1.0);
    }
}
