//! [`Dual`]: the `f64` dual number `re + eps·ε` (`ε² = 0`), a scalar kernels can run in.
//!
//! A kernel generic over `R: Real` run with `R = Dual` carries, beside every value, its
//! derivative along one direction. Running a whole recorded simulation *and its backward pass*
//! in `Dual` differentiates the adjoint code forward: the gradients' `eps` parts are the
//! Hessian-vector product `H v` of the loss (forward over reverse). [`crate::second_order`]
//! drives this; the type is public so a simulation can be written for it.
//!
//! Comparisons (`==`, `<`, `max`, `abs`'s branch, ...) look at `re` only, so a kernel takes
//! the same branches in `Dual` as in `f64` and the `eps` parts are the derivative of the path
//! `f64` takes. Rounding functions (`floor`, ...) have derivative zero.

use std::fmt;
use std::ops::{
    Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Rem, RemAssign, Sub, SubAssign,
};

use approx::{AbsDiffEq, RelativeEq, UlpsEq};
use num_traits::{FromPrimitive, Num, One, Signed, Zero};
use simba::scalar::{ComplexField, Field, RealField, SubsetOf};
use simba::simd::SimdValue;

/// An `f64` dual number: a value `re` and its derivative `eps` along one direction.
///
/// ```
/// use adflex_runtime::{Dual, Real};
/// use nalgebra::ComplexField;
/// // d/dx sin(x^2) at x = 1.5 is 2x cos(x^2).
/// let x = Dual::new(1.5, 1.0);
/// let y = (x * x).sin();
/// assert!((y.eps - 3.0 * (2.25f64).cos()).abs() < 1e-15);
/// assert_eq!(y.to_f64(), (2.25f64).sin());
/// ```
#[derive(Clone, Copy, Default)]
#[repr(C)]
pub struct Dual {
    /// The value.
    pub re: f64,
    /// Its derivative along the direction being followed.
    pub eps: f64,
}

// SAFETY: two `f64`s, `repr(C)`, no padding; every bit pattern is valid.
unsafe impl bytemuck::Zeroable for Dual {}
// SAFETY: as above.
unsafe impl bytemuck::Pod for Dual {}

impl Dual {
    /// `re + eps·ε`.
    #[inline(always)]
    pub const fn new(re: f64, eps: f64) -> Self {
        Dual { re, eps }
    }

    /// A constant: derivative zero.
    #[inline(always)]
    pub const fn constant(re: f64) -> Self {
        Dual { re, eps: 0.0 }
    }

    /// `f(re) + f'(re)·eps·ε` from the value `fx = f(re)` and the derivative `dfx = f'(re)`.
    /// A constant stays constant even where `f'` is infinite (`sqrt` at 0), not `inf · 0 =
    /// NaN`.
    #[inline(always)]
    fn chain(self, fx: f64, dfx: f64) -> Self {
        Dual {
            re: fx,
            eps: if self.eps == 0.0 { 0.0 } else { dfx * self.eps },
        }
    }
}

impl fmt::Debug for Dual {
    #[inline]
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}+{:?}ε", self.re, self.eps)
    }
}

impl fmt::Display for Dual {
    #[inline]
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}+{}ε", self.re, self.eps)
    }
}

// Comparisons see the value only (see the module's docs).
impl PartialEq for Dual {
    #[inline(always)]
    fn eq(&self, o: &Self) -> bool {
        self.re == o.re
    }
}

impl PartialOrd for Dual {
    #[inline(always)]
    fn partial_cmp(&self, o: &Self) -> Option<std::cmp::Ordering> {
        self.re.partial_cmp(&o.re)
    }
}

impl From<f64> for Dual {
    #[inline]
    fn from(x: f64) -> Self {
        Dual::constant(x)
    }
}

impl Add for Dual {
    type Output = Dual;
    #[inline(always)]
    fn add(self, o: Dual) -> Dual {
        Dual::new(self.re + o.re, self.eps + o.eps)
    }
}

impl Sub for Dual {
    type Output = Dual;
    #[inline(always)]
    fn sub(self, o: Dual) -> Dual {
        Dual::new(self.re - o.re, self.eps - o.eps)
    }
}

impl Mul for Dual {
    type Output = Dual;
    #[inline(always)]
    fn mul(self, o: Dual) -> Dual {
        Dual::new(self.re * o.re, self.eps * o.re + self.re * o.eps)
    }
}

impl Div for Dual {
    type Output = Dual;
    #[inline(always)]
    fn div(self, o: Dual) -> Dual {
        let q = self.re / o.re;
        Dual::new(q, (self.eps - q * o.eps) / o.re)
    }
}

impl Rem for Dual {
    type Output = Dual;
    /// `a - b·q` with `q` the integer quotient of `fmod`: derivative `da - db·q`.
    #[inline(always)]
    fn rem(self, o: Dual) -> Dual {
        let r = self.re % o.re;
        // The exact quotient (`a / b` may round across an integer: 1.0 % 0.1 has q = 9).
        let q = ((self.re - r) / o.re).round();
        Dual::new(r, self.eps - o.eps * q)
    }
}

impl Neg for Dual {
    type Output = Dual;
    #[inline(always)]
    fn neg(self) -> Dual {
        Dual::new(-self.re, -self.eps)
    }
}

macro_rules! assign_ops {
    ($($tr:ident $f:ident $op:tt),*) => {$(
        impl $tr for Dual {
            #[inline(always)]
            fn $f(&mut self, o: Dual) {
                *self = *self $op o;
            }
        }
    )*};
}
assign_ops!(AddAssign add_assign +, SubAssign sub_assign -, MulAssign mul_assign *,
    DivAssign div_assign /, RemAssign rem_assign %);

impl Zero for Dual {
    #[inline]
    fn zero() -> Self {
        Dual::constant(0.0)
    }
    #[inline]
    fn is_zero(&self) -> bool {
        self.re == 0.0
    }
}

impl One for Dual {
    #[inline]
    fn one() -> Self {
        Dual::constant(1.0)
    }
}

impl Num for Dual {
    type FromStrRadixErr = <f64 as Num>::FromStrRadixErr;
    #[inline]
    fn from_str_radix(s: &str, radix: u32) -> Result<Self, Self::FromStrRadixErr> {
        f64::from_str_radix(s, radix).map(Dual::constant)
    }
}

impl FromPrimitive for Dual {
    #[inline]
    fn from_i64(n: i64) -> Option<Self> {
        Some(Dual::constant(n as f64))
    }
    #[inline]
    fn from_u64(n: u64) -> Option<Self> {
        Some(Dual::constant(n as f64))
    }
    #[inline]
    fn from_f64(n: f64) -> Option<Self> {
        Some(Dual::constant(n))
    }
    #[inline]
    fn from_f32(n: f32) -> Option<Self> {
        Some(Dual::constant(n as f64))
    }
}

impl Signed for Dual {
    #[inline]
    fn abs(&self) -> Self {
        ComplexField::abs(*self)
    }
    #[inline]
    fn abs_sub(&self, o: &Self) -> Self {
        if self.re <= o.re {
            Dual::zero()
        } else {
            *self - *o
        }
    }
    #[inline]
    fn signum(&self) -> Self {
        Dual::constant(self.re.signum())
    }
    #[inline]
    fn is_positive(&self) -> bool {
        self.re > 0.0
    }
    #[inline]
    fn is_negative(&self) -> bool {
        self.re < 0.0
    }
}

impl AbsDiffEq for Dual {
    type Epsilon = Dual;
    #[inline]
    fn default_epsilon() -> Dual {
        Dual::constant(f64::default_epsilon())
    }
    #[inline]
    fn abs_diff_eq(&self, o: &Self, e: Dual) -> bool {
        self.re.abs_diff_eq(&o.re, e.re)
    }
}

impl RelativeEq for Dual {
    #[inline]
    fn default_max_relative() -> Dual {
        Dual::constant(f64::default_max_relative())
    }
    #[inline]
    fn relative_eq(&self, o: &Self, e: Dual, r: Dual) -> bool {
        self.re.relative_eq(&o.re, e.re, r.re)
    }
}

impl UlpsEq for Dual {
    #[inline]
    fn default_max_ulps() -> u32 {
        f64::default_max_ulps()
    }
    #[inline]
    fn ulps_eq(&self, o: &Self, e: Dual, m: u32) -> bool {
        self.re.ulps_eq(&o.re, e.re, m)
    }
}

impl SimdValue for Dual {
    const LANES: usize = 1;
    type Element = Dual;
    type SimdBool = bool;
    #[inline]
    fn splat(v: Dual) -> Self {
        v
    }
    #[inline]
    fn extract(&self, _: usize) -> Dual {
        *self
    }
    #[inline]
    unsafe fn extract_unchecked(&self, _: usize) -> Dual {
        *self
    }
    #[inline]
    fn replace(&mut self, _: usize, v: Dual) {
        *self = v
    }
    #[inline]
    unsafe fn replace_unchecked(&mut self, _: usize, v: Dual) {
        *self = v
    }
    #[inline]
    fn select(self, cond: bool, other: Self) -> Self {
        if cond {
            self
        } else {
            other
        }
    }
}

impl Field for Dual {}

impl SubsetOf<Dual> for Dual {
    #[inline]
    fn to_superset(&self) -> Dual {
        *self
    }
    #[inline]
    fn from_superset_unchecked(e: &Dual) -> Self {
        *e
    }
    #[inline]
    fn is_in_subset(_: &Dual) -> bool {
        true
    }
}

macro_rules! float_subset {
    ($($t:ty),*) => {$(
        impl SubsetOf<Dual> for $t {
            #[inline]
            fn to_superset(&self) -> Dual {
                Dual::constant(*self as f64)
            }
            #[inline]
            fn from_superset_unchecked(e: &Dual) -> Self {
                e.re as $t
            }
            #[inline]
            fn is_in_subset(e: &Dual) -> bool {
                e.eps == 0.0
            }
        }
    )*};
}
float_subset!(f32, f64);

impl ComplexField for Dual {
    type RealField = Dual;

    #[inline]
    fn from_real(re: Dual) -> Self {
        re
    }
    #[inline]
    fn real(self) -> Dual {
        self
    }
    #[inline]
    fn imaginary(self) -> Dual {
        Dual::zero()
    }
    #[inline]
    fn modulus(self) -> Dual {
        self.abs()
    }
    #[inline]
    fn modulus_squared(self) -> Dual {
        self * self
    }
    #[inline]
    fn argument(self) -> Dual {
        if self.re >= 0.0 {
            Dual::zero()
        } else {
            Dual::pi()
        }
    }
    #[inline]
    fn norm1(self) -> Dual {
        self.abs()
    }
    #[inline]
    fn scale(self, factor: Dual) -> Self {
        self * factor
    }
    #[inline]
    fn unscale(self, factor: Dual) -> Self {
        self / factor
    }
    #[inline]
    fn floor(self) -> Self {
        Dual::constant(self.re.floor())
    }
    #[inline]
    fn ceil(self) -> Self {
        Dual::constant(self.re.ceil())
    }
    #[inline]
    fn round(self) -> Self {
        Dual::constant(self.re.round())
    }
    #[inline]
    fn trunc(self) -> Self {
        Dual::constant(self.re.trunc())
    }
    #[inline]
    fn fract(self) -> Self {
        Dual::new(self.re.fract(), self.eps)
    }
    #[inline]
    fn mul_add(self, a: Self, b: Self) -> Self {
        self * a + b
    }
    #[inline]
    fn abs(self) -> Dual {
        if self.re < 0.0 {
            -self
        } else {
            self
        }
    }
    #[inline]
    fn hypot(self, o: Self) -> Dual {
        (self * self + o * o).sqrt()
    }
    #[inline]
    fn recip(self) -> Self {
        Dual::one() / self
    }
    #[inline]
    fn conjugate(self) -> Self {
        self
    }
    #[inline]
    fn sin(self) -> Self {
        self.chain(self.re.sin(), self.re.cos())
    }
    #[inline]
    fn cos(self) -> Self {
        self.chain(self.re.cos(), -self.re.sin())
    }
    #[inline]
    fn sin_cos(self) -> (Self, Self) {
        (self.sin(), self.cos())
    }
    #[inline]
    fn tan(self) -> Self {
        let t = self.re.tan();
        self.chain(t, 1.0 + t * t)
    }
    #[inline]
    // At |x| >= 1, like the library's rules: derivative 0 (not infinite).
    fn asin(self) -> Self {
        let d = if self.re.abs() < 1.0 {
            1.0 / (1.0 - self.re * self.re).sqrt()
        } else {
            0.0
        };
        self.chain(self.re.asin(), d)
    }
    #[inline]
    fn acos(self) -> Self {
        let d = if self.re.abs() < 1.0 {
            -1.0 / (1.0 - self.re * self.re).sqrt()
        } else {
            0.0
        };
        self.chain(self.re.acos(), d)
    }
    #[inline]
    fn atan(self) -> Self {
        self.chain(self.re.atan(), 1.0 / (1.0 + self.re * self.re))
    }
    #[inline]
    fn sinh(self) -> Self {
        self.chain(self.re.sinh(), self.re.cosh())
    }
    #[inline]
    fn cosh(self) -> Self {
        self.chain(self.re.cosh(), self.re.sinh())
    }
    #[inline]
    fn tanh(self) -> Self {
        let t = self.re.tanh();
        self.chain(t, 1.0 - t * t)
    }
    #[inline]
    fn asinh(self) -> Self {
        self.chain(self.re.asinh(), 1.0 / (self.re * self.re + 1.0).sqrt())
    }
    #[inline]
    fn acosh(self) -> Self {
        self.chain(self.re.acosh(), 1.0 / (self.re * self.re - 1.0).sqrt())
    }
    #[inline]
    fn atanh(self) -> Self {
        self.chain(self.re.atanh(), 1.0 / (1.0 - self.re * self.re))
    }
    #[inline]
    fn log(self, base: Dual) -> Self {
        self.ln() / base.ln()
    }
    #[inline]
    fn log2(self) -> Self {
        self.chain(self.re.log2(), 1.0 / (self.re * std::f64::consts::LN_2))
    }
    #[inline]
    fn log10(self) -> Self {
        self.chain(self.re.log10(), 1.0 / (self.re * std::f64::consts::LN_10))
    }
    #[inline]
    fn ln(self) -> Self {
        self.chain(self.re.ln(), 1.0 / self.re)
    }
    #[inline]
    fn ln_1p(self) -> Self {
        self.chain(self.re.ln_1p(), 1.0 / (1.0 + self.re))
    }
    #[inline]
    // At 0, like the library's rule: derivative 0 (not infinite).
    fn sqrt(self) -> Self {
        let s = self.re.sqrt();
        self.chain(s, if self.re == 0.0 { 0.0 } else { 0.5 / s })
    }
    #[inline]
    fn exp(self) -> Self {
        let e = self.re.exp();
        self.chain(e, e)
    }
    #[inline]
    fn exp2(self) -> Self {
        let e = self.re.exp2();
        self.chain(e, e * std::f64::consts::LN_2)
    }
    #[inline]
    fn exp_m1(self) -> Self {
        self.chain(self.re.exp_m1(), self.re.exp())
    }
    #[inline]
    fn powi(self, n: i32) -> Self {
        if n == 0 {
            return Dual::one();
        }
        self.chain(self.re.powi(n), n as f64 * self.re.powi(n - 1))
    }
    #[inline]
    fn powf(self, n: Dual) -> Self {
        let p = self.re.powf(n.re);
        // d(x^n) = n x^(n-1) dx + x^n ln(x) dn; the second term only where it is defined.
        let dx = if self.eps == 0.0 {
            0.0
        } else {
            n.re * self.re.powf(n.re - 1.0) * self.eps
        };
        // x^n ln x -> 0 as x -> 0 (for n > 0).
        let dn = if n.eps == 0.0 || p == 0.0 {
            0.0
        } else {
            p * self.re.ln() * n.eps
        };
        Dual::new(p, dx + dn)
    }
    #[inline]
    fn powc(self, n: Self) -> Self {
        self.powf(n)
    }
    #[inline]
    fn cbrt(self) -> Self {
        let c = self.re.cbrt();
        self.chain(c, 1.0 / (3.0 * c * c))
    }
    #[inline]
    fn is_finite(&self) -> bool {
        self.re.is_finite() && self.eps.is_finite()
    }
    #[inline]
    fn try_sqrt(self) -> Option<Self> {
        (self.re >= 0.0).then(|| self.sqrt())
    }
}

impl RealField for Dual {
    #[inline]
    fn is_sign_positive(&self) -> bool {
        self.re.is_sign_positive()
    }
    #[inline]
    fn is_sign_negative(&self) -> bool {
        self.re.is_sign_negative()
    }
    #[inline]
    fn copysign(self, sign: Self) -> Self {
        if self.re.is_sign_negative() == sign.re.is_sign_negative() {
            self
        } else {
            -self
        }
    }
    #[inline]
    fn max(self, o: Self) -> Self {
        if o.re > self.re {
            o
        } else {
            self
        }
    }
    #[inline]
    fn min(self, o: Self) -> Self {
        if o.re < self.re {
            o
        } else {
            self
        }
    }
    #[inline]
    fn clamp(self, lo: Self, hi: Self) -> Self {
        RealField::min(RealField::max(self, lo), hi)
    }
    #[inline]
    fn atan2(self, x: Self) -> Self {
        // d atan2(y, x) = (x dy - y dx) / (x^2 + y^2); 0 at the origin, like the library's rule.
        let r2 = self.re * self.re + x.re * x.re;
        let d = if r2 > 0.0 {
            (x.re * self.eps - self.re * x.eps) / r2
        } else {
            0.0
        };
        Dual::new(self.re.atan2(x.re), d)
    }
    #[inline]
    fn min_value() -> Option<Self> {
        Some(Dual::constant(f64::MIN))
    }
    #[inline]
    fn max_value() -> Option<Self> {
        Some(Dual::constant(f64::MAX))
    }
    #[inline]
    fn pi() -> Self {
        Dual::constant(std::f64::consts::PI)
    }
    #[inline]
    fn two_pi() -> Self {
        Dual::constant(std::f64::consts::TAU)
    }
    #[inline]
    fn frac_pi_2() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_2)
    }
    #[inline]
    fn frac_pi_3() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_3)
    }
    #[inline]
    fn frac_pi_4() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_4)
    }
    #[inline]
    fn frac_pi_6() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_6)
    }
    #[inline]
    fn frac_pi_8() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_8)
    }
    #[inline]
    fn frac_1_pi() -> Self {
        Dual::constant(std::f64::consts::FRAC_1_PI)
    }
    #[inline]
    fn frac_2_pi() -> Self {
        Dual::constant(std::f64::consts::FRAC_2_PI)
    }
    #[inline]
    fn frac_2_sqrt_pi() -> Self {
        Dual::constant(std::f64::consts::FRAC_2_SQRT_PI)
    }
    #[inline]
    fn e() -> Self {
        Dual::constant(std::f64::consts::E)
    }
    #[inline]
    fn log2_e() -> Self {
        Dual::constant(std::f64::consts::LOG2_E)
    }
    #[inline]
    fn log10_e() -> Self {
        Dual::constant(std::f64::consts::LOG10_E)
    }
    #[inline]
    fn ln_2() -> Self {
        Dual::constant(std::f64::consts::LN_2)
    }
    #[inline]
    fn ln_10() -> Self {
        Dual::constant(std::f64::consts::LN_10)
    }
}

impl crate::Value for Dual {
    /// One differentiable component, the value `re` (what gradient checks perturb).
    const DIM: usize = 1;
    #[inline(always)]
    fn zeroed() -> Self {
        Dual::constant(0.0)
    }
    #[inline(always)]
    fn neg_zeroed() -> Self {
        Dual::new(-0.0, -0.0)
    }
    #[inline(always)]
    fn acc(&mut self, o: Self) {
        *self += o;
    }
    #[inline(always)]
    fn acc_neg(&mut self, o: Self) {
        *self -= o;
    }
    #[inline]
    fn component(&self, _: usize) -> f64 {
        self.re
    }
    #[inline]
    fn set_component(&mut self, _: usize, x: f64) {
        self.re = x;
    }
    const DUAL: bool = true;
    #[inline]
    fn eps_component(&self, _: usize) -> f64 {
        self.eps
    }
    #[inline]
    fn set_eps_component(&mut self, _: usize, x: f64) {
        self.eps = x;
    }
}

impl crate::Real for Dual {
    #[inline(always)]
    fn lit(x: f64) -> Self {
        Dual::constant(x)
    }
    /// The value; the derivative is dropped.
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self.re
    }
    #[inline(always)]
    fn tiny() -> Self {
        Dual::constant(1e-150)
    }
    #[inline(always)]
    fn eps(self) -> f64 {
        self.eps
    }
    #[inline(always)]
    fn with_eps(self, eps: f64) -> Self {
        Dual::new(self.re, eps)
    }
}
