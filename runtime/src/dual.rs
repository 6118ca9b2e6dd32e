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
    #[inline(always)]
    fn chain(self, fx: f64, dfx: f64) -> Self {
        Dual {
            re: fx,
            eps: dfx * self.eps,
        }
    }
}

impl fmt::Debug for Dual {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}+{:?}ε", self.re, self.eps)
    }
}

impl fmt::Display for Dual {
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
    /// `a - b·trunc(a / b)`: derivative `da - db·trunc(a / b)`.
    #[inline(always)]
    fn rem(self, o: Dual) -> Dual {
        let t = (self.re / o.re).trunc();
        Dual::new(self.re % o.re, self.eps - o.eps * t)
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
    fn zero() -> Self {
        Dual::constant(0.0)
    }
    fn is_zero(&self) -> bool {
        self.re == 0.0
    }
}

impl One for Dual {
    fn one() -> Self {
        Dual::constant(1.0)
    }
}

impl Num for Dual {
    type FromStrRadixErr = <f64 as Num>::FromStrRadixErr;
    fn from_str_radix(s: &str, radix: u32) -> Result<Self, Self::FromStrRadixErr> {
        f64::from_str_radix(s, radix).map(Dual::constant)
    }
}

impl FromPrimitive for Dual {
    fn from_i64(n: i64) -> Option<Self> {
        Some(Dual::constant(n as f64))
    }
    fn from_u64(n: u64) -> Option<Self> {
        Some(Dual::constant(n as f64))
    }
    fn from_f64(n: f64) -> Option<Self> {
        Some(Dual::constant(n))
    }
    fn from_f32(n: f32) -> Option<Self> {
        Some(Dual::constant(n as f64))
    }
}

impl Signed for Dual {
    fn abs(&self) -> Self {
        ComplexField::abs(*self)
    }
    fn abs_sub(&self, o: &Self) -> Self {
        if self.re <= o.re {
            Dual::zero()
        } else {
            *self - *o
        }
    }
    fn signum(&self) -> Self {
        Dual::constant(self.re.signum())
    }
    fn is_positive(&self) -> bool {
        self.re > 0.0
    }
    fn is_negative(&self) -> bool {
        self.re < 0.0
    }
}

impl AbsDiffEq for Dual {
    type Epsilon = Dual;
    fn default_epsilon() -> Dual {
        Dual::constant(f64::default_epsilon())
    }
    fn abs_diff_eq(&self, o: &Self, e: Dual) -> bool {
        self.re.abs_diff_eq(&o.re, e.re)
    }
}

impl RelativeEq for Dual {
    fn default_max_relative() -> Dual {
        Dual::constant(f64::default_max_relative())
    }
    fn relative_eq(&self, o: &Self, e: Dual, r: Dual) -> bool {
        self.re.relative_eq(&o.re, e.re, r.re)
    }
}

impl UlpsEq for Dual {
    fn default_max_ulps() -> u32 {
        f64::default_max_ulps()
    }
    fn ulps_eq(&self, o: &Self, e: Dual, m: u32) -> bool {
        self.re.ulps_eq(&o.re, e.re, m)
    }
}

impl SimdValue for Dual {
    const LANES: usize = 1;
    type Element = Dual;
    type SimdBool = bool;
    fn splat(v: Dual) -> Self {
        v
    }
    fn extract(&self, _: usize) -> Dual {
        *self
    }
    unsafe fn extract_unchecked(&self, _: usize) -> Dual {
        *self
    }
    fn replace(&mut self, _: usize, v: Dual) {
        *self = v
    }
    unsafe fn replace_unchecked(&mut self, _: usize, v: Dual) {
        *self = v
    }
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
    fn to_superset(&self) -> Dual {
        *self
    }
    fn from_superset_unchecked(e: &Dual) -> Self {
        *e
    }
    fn is_in_subset(_: &Dual) -> bool {
        true
    }
}

macro_rules! float_subset {
    ($($t:ty),*) => {$(
        impl SubsetOf<Dual> for $t {
            fn to_superset(&self) -> Dual {
                Dual::constant(*self as f64)
            }
            fn from_superset_unchecked(e: &Dual) -> Self {
                e.re as $t
            }
            fn is_in_subset(e: &Dual) -> bool {
                e.eps == 0.0
            }
        }
    )*};
}
float_subset!(f32, f64);

impl ComplexField for Dual {
    type RealField = Dual;

    fn from_real(re: Dual) -> Self {
        re
    }
    fn real(self) -> Dual {
        self
    }
    fn imaginary(self) -> Dual {
        Dual::zero()
    }
    fn modulus(self) -> Dual {
        self.abs()
    }
    fn modulus_squared(self) -> Dual {
        self * self
    }
    fn argument(self) -> Dual {
        if self.re >= 0.0 {
            Dual::zero()
        } else {
            Dual::pi()
        }
    }
    fn norm1(self) -> Dual {
        self.abs()
    }
    fn scale(self, factor: Dual) -> Self {
        self * factor
    }
    fn unscale(self, factor: Dual) -> Self {
        self / factor
    }
    fn floor(self) -> Self {
        Dual::constant(self.re.floor())
    }
    fn ceil(self) -> Self {
        Dual::constant(self.re.ceil())
    }
    fn round(self) -> Self {
        Dual::constant(self.re.round())
    }
    fn trunc(self) -> Self {
        Dual::constant(self.re.trunc())
    }
    fn fract(self) -> Self {
        Dual::new(self.re.fract(), self.eps)
    }
    fn mul_add(self, a: Self, b: Self) -> Self {
        self * a + b
    }
    fn abs(self) -> Dual {
        if self.re < 0.0 {
            -self
        } else {
            self
        }
    }
    fn hypot(self, o: Self) -> Dual {
        (self * self + o * o).sqrt()
    }
    fn recip(self) -> Self {
        Dual::one() / self
    }
    fn conjugate(self) -> Self {
        self
    }
    fn sin(self) -> Self {
        self.chain(self.re.sin(), self.re.cos())
    }
    fn cos(self) -> Self {
        self.chain(self.re.cos(), -self.re.sin())
    }
    fn sin_cos(self) -> (Self, Self) {
        (self.sin(), self.cos())
    }
    fn tan(self) -> Self {
        let t = self.re.tan();
        self.chain(t, 1.0 + t * t)
    }
    fn asin(self) -> Self {
        self.chain(self.re.asin(), 1.0 / (1.0 - self.re * self.re).sqrt())
    }
    fn acos(self) -> Self {
        self.chain(self.re.acos(), -1.0 / (1.0 - self.re * self.re).sqrt())
    }
    fn atan(self) -> Self {
        self.chain(self.re.atan(), 1.0 / (1.0 + self.re * self.re))
    }
    fn sinh(self) -> Self {
        self.chain(self.re.sinh(), self.re.cosh())
    }
    fn cosh(self) -> Self {
        self.chain(self.re.cosh(), self.re.sinh())
    }
    fn tanh(self) -> Self {
        let t = self.re.tanh();
        self.chain(t, 1.0 - t * t)
    }
    fn asinh(self) -> Self {
        self.chain(self.re.asinh(), 1.0 / (self.re * self.re + 1.0).sqrt())
    }
    fn acosh(self) -> Self {
        self.chain(self.re.acosh(), 1.0 / (self.re * self.re - 1.0).sqrt())
    }
    fn atanh(self) -> Self {
        self.chain(self.re.atanh(), 1.0 / (1.0 - self.re * self.re))
    }
    fn log(self, base: Dual) -> Self {
        self.ln() / base.ln()
    }
    fn log2(self) -> Self {
        self.chain(self.re.log2(), 1.0 / (self.re * std::f64::consts::LN_2))
    }
    fn log10(self) -> Self {
        self.chain(self.re.log10(), 1.0 / (self.re * std::f64::consts::LN_10))
    }
    fn ln(self) -> Self {
        self.chain(self.re.ln(), 1.0 / self.re)
    }
    fn ln_1p(self) -> Self {
        self.chain(self.re.ln_1p(), 1.0 / (1.0 + self.re))
    }
    fn sqrt(self) -> Self {
        let s = self.re.sqrt();
        self.chain(s, 0.5 / s)
    }
    fn exp(self) -> Self {
        let e = self.re.exp();
        self.chain(e, e)
    }
    fn exp2(self) -> Self {
        let e = self.re.exp2();
        self.chain(e, e * std::f64::consts::LN_2)
    }
    fn exp_m1(self) -> Self {
        self.chain(self.re.exp_m1(), self.re.exp())
    }
    fn powi(self, n: i32) -> Self {
        if n == 0 {
            return Dual::one();
        }
        self.chain(self.re.powi(n), n as f64 * self.re.powi(n - 1))
    }
    fn powf(self, n: Dual) -> Self {
        let p = self.re.powf(n.re);
        // d(x^n) = n x^(n-1) dx + x^n ln(x) dn; the second term only where it is defined.
        let dx = if self.eps == 0.0 {
            0.0
        } else {
            n.re * self.re.powf(n.re - 1.0) * self.eps
        };
        let dn = if n.eps == 0.0 {
            0.0
        } else {
            p * self.re.ln() * n.eps
        };
        Dual::new(p, dx + dn)
    }
    fn powc(self, n: Self) -> Self {
        self.powf(n)
    }
    fn cbrt(self) -> Self {
        let c = self.re.cbrt();
        self.chain(c, 1.0 / (3.0 * c * c))
    }
    fn is_finite(&self) -> bool {
        self.re.is_finite() && self.eps.is_finite()
    }
    fn try_sqrt(self) -> Option<Self> {
        (self.re >= 0.0).then(|| self.sqrt())
    }
}

impl RealField for Dual {
    fn is_sign_positive(&self) -> bool {
        self.re.is_sign_positive()
    }
    fn is_sign_negative(&self) -> bool {
        self.re.is_sign_negative()
    }
    fn copysign(self, sign: Self) -> Self {
        if self.re.is_sign_negative() == sign.re.is_sign_negative() {
            self
        } else {
            -self
        }
    }
    fn max(self, o: Self) -> Self {
        if o.re > self.re {
            o
        } else {
            self
        }
    }
    fn min(self, o: Self) -> Self {
        if o.re < self.re {
            o
        } else {
            self
        }
    }
    fn clamp(self, lo: Self, hi: Self) -> Self {
        RealField::min(RealField::max(self, lo), hi)
    }
    fn atan2(self, x: Self) -> Self {
        // d atan2(y, x) = (x dy - y dx) / (x^2 + y^2)
        let r2 = self.re * self.re + x.re * x.re;
        Dual::new(
            self.re.atan2(x.re),
            (x.re * self.eps - self.re * x.eps) / r2,
        )
    }
    fn min_value() -> Option<Self> {
        Some(Dual::constant(f64::MIN))
    }
    fn max_value() -> Option<Self> {
        Some(Dual::constant(f64::MAX))
    }
    fn pi() -> Self {
        Dual::constant(std::f64::consts::PI)
    }
    fn two_pi() -> Self {
        Dual::constant(std::f64::consts::TAU)
    }
    fn frac_pi_2() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_2)
    }
    fn frac_pi_3() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_3)
    }
    fn frac_pi_4() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_4)
    }
    fn frac_pi_6() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_6)
    }
    fn frac_pi_8() -> Self {
        Dual::constant(std::f64::consts::FRAC_PI_8)
    }
    fn frac_1_pi() -> Self {
        Dual::constant(std::f64::consts::FRAC_1_PI)
    }
    fn frac_2_pi() -> Self {
        Dual::constant(std::f64::consts::FRAC_2_PI)
    }
    fn frac_2_sqrt_pi() -> Self {
        Dual::constant(std::f64::consts::FRAC_2_SQRT_PI)
    }
    fn e() -> Self {
        Dual::constant(std::f64::consts::E)
    }
    fn log2_e() -> Self {
        Dual::constant(std::f64::consts::LOG2_E)
    }
    fn log10_e() -> Self {
        Dual::constant(std::f64::consts::LOG10_E)
    }
    fn ln_2() -> Self {
        Dual::constant(std::f64::consts::LN_2)
    }
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
        *self = *self + o;
    }
    #[inline(always)]
    fn acc_neg(&mut self, o: Self) {
        *self = *self - o;
    }
    fn component(&self, _: usize) -> f64 {
        self.re
    }
    fn set_component(&mut self, _: usize, x: f64) {
        self.re = x;
    }
    const DUAL: bool = true;
    fn eps_component(&self, _: usize) -> f64 {
        self.eps
    }
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
