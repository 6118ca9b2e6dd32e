//! Finite-difference checking of the math rules (tests only).
//!
//! [`check_rule`] checks a builtin's adjoint and tangent rules in `f64` against central
//! differences of its forward function at random points, and checks the two rules against
//! each other (`<tan(x, v), w> == <v, adj(x, w)>`). [`smoke_f32`] checks that the rules run
//! in `f32` and agree with `f64`. [`fd_tests!`] generates one test doing both per builtin and
//! type combination.

use super::matrix::MatrixValue;
use crate::{Real, Value};

/// Random points per rule.
pub(crate) const POINTS: usize = 8;
/// Step of the central differences.
const H: f64 = 1e-6;
/// Tolerance of the finite-difference comparisons, relative to `max(1, |a|, |b|)`.
pub(crate) const FD_TOL: f64 = 1e-6;
/// Tolerance of the dot-product test (both sides analytic).
const DOT_TOL: f64 = 1e-10;
/// Tolerance of the `f32` against `f64` comparison.
pub(crate) const F32_TOL: f64 = 1e-5;

/// xorshift64*: a fixed-seed generator, so every test sees the same points on every run.
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Rng((seed ^ 0x9E37_79B9_7F4A_7C15) | 1)
    }
    fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    /// Uniform in `[lo, hi)`.
    pub(crate) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        let u = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        lo + (hi - lo) * u
    }
    /// Uniform in `0..n`.
    pub(crate) fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

fn seed_of(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

// ---------------------------------------------------------------------------------------------
// samplers: `Fn(&mut Rng) -> T`

/// Every component uniform in `[lo, hi)`.
pub(crate) fn fill<T: Value>(rng: &mut Rng, lo: f64, hi: f64) -> T {
    let mut t = T::zeroed();
    for k in 0..T::DIM {
        t.set_component(k, rng.range(lo, hi));
    }
    t
}
/// Components in `[-1, 1)`.
pub(crate) fn any<T: Value>(rng: &mut Rng) -> T {
    fill(rng, -1.0, 1.0)
}
/// Components in `[-2, 2)`.
pub(crate) fn wide<T: Value>(rng: &mut Rng) -> T {
    fill(rng, -2.0, 2.0)
}
/// Components in `[0.2, 2)` (domain of sqrt, ln, pow).
pub(crate) fn pos<T: Value>(rng: &mut Rng) -> T {
    fill(rng, 0.2, 2.0)
}
/// Components in `[-0.9, 0.9)` (inside the domain of asin, acos).
pub(crate) fn unit<T: Value>(rng: &mut Rng) -> T {
    fill(rng, -0.9, 0.9)
}
/// Components of magnitude in `[0.5, 1.5)`, either sign (divisors).
pub(crate) fn away<T: Value>(rng: &mut Rng) -> T {
    let mut t = T::zeroed();
    for k in 0..T::DIM {
        let m = rng.range(0.5, 1.5);
        t.set_component(k, if rng.below(2) == 0 { m } else { -m });
    }
    t
}
/// `2 I + E` with `E` in `[-0.5, 0.5)`: a well-conditioned matrix.
pub(crate) fn wellcond<M: MatrixValue>(rng: &mut Rng) -> M {
    let e: M = fill(rng, -0.5, 0.5);
    M::mat_identity()
        .lin_scale(<M::Scalar as Real>::lit(2.0))
        .lin_add(e)
}
/// A constant (for non-differentiable arguments).
pub(crate) fn just<T: Copy>(t: T) -> impl Fn(&mut Rng) -> T {
    move |_| t
}
/// An index in `0..n`.
pub(crate) fn idx(n: usize) -> impl Fn(&mut Rng) -> usize {
    move |rng| rng.below(n)
}

// ---------------------------------------------------------------------------------------------
// argument tuples and calling rules on them

/// A tuple of values, flattened to its differentiable components.
pub(crate) trait Args: Copy {
    const DIM: usize;
    fn zeroed() -> Self;
    fn component(&self, k: usize) -> f64;
    fn set_component(&mut self, k: usize, x: f64);
}

/// A forward function of the tuple `In`.
pub(crate) trait Fwd<In, Out> {
    fn call(&self, x: In) -> Out;
}
/// An adjoint rule: `adj_f(a, b, .., w) -> (adj_a, adj_b, ..)` (a single adjoint for arity 1).
pub(crate) trait Adj<In, Out> {
    fn call(&self, x: In, w: Out) -> In;
}
/// A tangent rule: `tan_f(a, b, .., da, db, ..) -> dout`.
pub(crate) trait Tan<In, Out> {
    fn call(&self, x: In, v: In) -> Out;
}

impl<F: Fn(A, O) -> A, A, O> Adj<(A,), O> for F {
    fn call(&self, x: (A,), w: O) -> (A,) {
        (self(x.0, w),)
    }
}

macro_rules! arity {
    ($(($($A:ident $i:tt),+)),*) => {$(
        impl<$($A: Value),+> Args for ($($A,)+) {
            const DIM: usize = 0 $(+ $A::DIM)+;
            fn zeroed() -> Self {
                ($($A::zeroed(),)+)
            }
            #[allow(unused_assignments)]
            fn component(&self, k: usize) -> f64 {
                let mut k = k;
                $(
                    if k < $A::DIM {
                        return self.$i.component(k);
                    }
                    k -= $A::DIM;
                )+
                unreachable!()
            }
            #[allow(unused_assignments)]
            fn set_component(&mut self, k: usize, x: f64) {
                let mut k = k;
                $(
                    if k < $A::DIM {
                        return self.$i.set_component(k, x);
                    }
                    k -= $A::DIM;
                )+
                unreachable!()
            }
        }
        impl<F: Fn($($A),+) -> O, $($A,)+ O> Fwd<($($A,)+), O> for F {
            fn call(&self, x: ($($A,)+)) -> O {
                self($(x.$i),+)
            }
        }
        impl<F: Fn($($A,)+ $($A),+) -> O, $($A,)+ O> Tan<($($A,)+), O> for F {
            fn call(&self, x: ($($A,)+), v: ($($A,)+)) -> O {
                self($(x.$i,)+ $(v.$i),+)
            }
        }
    )*};
}
arity!(
    (A 0),
    (A 0, B 1),
    (A 0, B 1, C 2),
    (A 0, B 1, C 2, D 3),
    (A 0, B 1, C 2, D 3, E 4),
    (A 0, B 1, C 2, D 3, E 4, G 5),
    (A 0, B 1, C 2, D 3, E 4, G 5, H 6),
    (A 0, B 1, C 2, D 3, E 4, G 5, H 6, I 7),
    (A 0, B 1, C 2, D 3, E 4, G 5, H 6, I 7, J 8)
);

macro_rules! adj_arity {
    ($(($($A:ident $i:tt),+)),*) => {$(
        impl<F: Fn($($A,)+ O) -> ($($A,)+), $($A,)+ O> Adj<($($A,)+), O> for F {
            fn call(&self, x: ($($A,)+), w: O) -> ($($A,)+) {
                self($(x.$i,)+ w)
            }
        }
    )*};
}
adj_arity!(
    (A 0, B 1),
    (A 0, B 1, C 2),
    (A 0, B 1, C 2, D 3),
    (A 0, B 1, C 2, D 3, E 4),
    (A 0, B 1, C 2, D 3, E 4, G 5),
    (A 0, B 1, C 2, D 3, E 4, G 5, H 6),
    (A 0, B 1, C 2, D 3, E 4, G 5, H 6, I 7),
    (A 0, B 1, C 2, D 3, E 4, G 5, H 6, I 7, J 8)
);

// ---------------------------------------------------------------------------------------------
// the checks

/// `|a - b| <= tol * max(1, |a|, |b|)`.
pub(crate) fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * 1f64.max(a.abs()).max(b.abs())
}

fn flat<T: Value>(t: &T) -> Vec<f64> {
    (0..T::DIM).map(|k| t.component(k)).collect()
}
fn flat_args<T: Args>(t: &T) -> Vec<f64> {
    (0..T::DIM).map(|k| t.component(k)).collect()
}
fn inner<T: Value>(a: &T, b: &T) -> f64 {
    (0..T::DIM).map(|k| a.component(k) * b.component(k)).sum()
}
fn inner_args<T: Args>(a: &T, b: &T) -> f64 {
    (0..T::DIM).map(|k| a.component(k) * b.component(k)).sum()
}
/// `x + s v` on the differentiable components.
fn axpy<T: Args>(x: &T, s: f64, v: &T) -> T {
    let mut y = *x;
    for k in 0..T::DIM {
        y.set_component(k, x.component(k) + s * v.component(k));
    }
    y
}

/// Checks `adj` and `tan` against central differences of `f` at [`POINTS`] random points
/// drawn by `sample` (in f64), and against each other (dot-product test).
pub(crate) fn check_rule<In: Args, Out: Value>(
    name: &str,
    sample: impl Fn(&mut Rng) -> In,
    f: impl Fwd<In, Out>,
    adj: impl Adj<In, Out>,
    tan: impl Tan<In, Out>,
) {
    check_rule_tol(name, sample, f, adj, tan, FD_TOL)
}

/// [`check_rule`] with the finite-difference tolerance `tol`.
pub(crate) fn check_rule_tol<In: Args, Out: Value>(
    name: &str,
    sample: impl Fn(&mut Rng) -> In,
    f: impl Fwd<In, Out>,
    adj: impl Adj<In, Out>,
    tan: impl Tan<In, Out>,
    tol: f64,
) {
    let mut rng = Rng::new(seed_of(name));
    for p in 0..POINTS {
        let x = sample(&mut rng);
        let w: Out = any(&mut rng);
        let mut v = In::zeroed();
        for k in 0..In::DIM {
            v.set_component(k, rng.range(-1.0, 1.0));
        }
        let at = || format!("{name}, point {p}, inputs {:?}", flat_args(&x));

        let y = f.call(x);
        assert!(
            flat(&y).iter().all(|c| c.is_finite()),
            "{}: non-finite output {:?}",
            at(),
            flat(&y)
        );

        // adjoint against central differences of <w, f(x)>
        let g = adj.call(x, w);
        for k in 0..In::DIM {
            let (mut xp, mut xm) = (x, x);
            xp.set_component(k, x.component(k) + H);
            xm.set_component(k, x.component(k) - H);
            let fd = (inner(&w, &f.call(xp)) - inner(&w, &f.call(xm))) / (2.0 * H);
            let a = g.component(k);
            assert!(
                close(fd, a, tol),
                "{}: adjoint component {k}: rule {a}, central difference {fd}",
                at()
            );
        }

        // tangent against central differences of f along v
        let t = tan.call(x, v);
        let (fp, fm) = (f.call(axpy(&x, H, &v)), f.call(axpy(&x, -H, &v)));
        for k in 0..Out::DIM {
            let fd = (fp.component(k) - fm.component(k)) / (2.0 * H);
            let a = t.component(k);
            assert!(
                close(fd, a, tol),
                "{}: tangent component {k}: rule {a}, central difference {fd}",
                at()
            );
        }

        // dot-product test
        let (lhs, rhs) = (inner(&t, &w), inner_args(&v, &g));
        assert!(
            close(lhs, rhs, DOT_TOL),
            "{}: <tan, w> = {lhs} but <v, adj> = {rhs}",
            at()
        );
    }
}

/// Runs the rules in `f32` and in `f64` on the same (f32-representable) points and checks that
/// values, adjoints and tangents agree to [`F32_TOL`].
#[allow(clippy::too_many_arguments)]
pub(crate) fn smoke_f32<I32: Args, O32: Value, I64: Args, O64: Value>(
    name: &str,
    s32: impl Fn(&mut Rng) -> I32,
    s64: impl Fn(&mut Rng) -> I64,
    f32_: impl Fwd<I32, O32>,
    f64_: impl Fwd<I64, O64>,
    a32: impl Adj<I32, O32>,
    a64: impl Adj<I64, O64>,
    t32: impl Tan<I32, O32>,
    t64: impl Tan<I64, O64>,
) {
    assert_eq!(I32::DIM, I64::DIM);
    assert_eq!(O32::DIM, O64::DIM);
    let seed = seed_of(name) ^ 0xf32;
    for p in 0..POINTS {
        // same draws for both, then the f64 point set to the f32 one exactly
        let x32 = s32(&mut Rng::new(seed + p as u64));
        let mut x64 = s64(&mut Rng::new(seed + p as u64));
        let mut rng = Rng::new(seed + 1000 + p as u64);
        let (mut w32, mut w64) = (O32::zeroed(), O64::zeroed());
        let (mut v32, mut v64) = (I32::zeroed(), I64::zeroed());
        for k in 0..I32::DIM {
            x64.set_component(k, x32.component(k));
            v32.set_component(k, rng.range(-1.0, 1.0));
            v64.set_component(k, v32.component(k));
        }
        for k in 0..O32::DIM {
            w32.set_component(k, rng.range(-1.0, 1.0));
            w64.set_component(k, w32.component(k));
        }
        let same = |what: &str, a: Vec<f64>, b: Vec<f64>| {
            for (k, (a, b)) in a.iter().zip(&b).enumerate() {
                assert!(
                    close(*a, *b, F32_TOL),
                    "{name}, point {p}: f32 {what} component {k} is {a}, f64 gives {b}"
                );
            }
        };
        same("value", flat(&f32_.call(x32)), flat(&f64_.call(x64)));
        same(
            "adjoint",
            flat_args(&a32.call(x32, w32)),
            flat_args(&a64.call(x64, w64)),
        );
        same(
            "tangent",
            flat(&t32.call(x32, v32)),
            flat(&t64.call(x64, v64)),
        );
    }
}

/// One test per line: `name: f, adj_f, tan_f [Type = sampler, ...];`, the types written in
/// terms of a scalar `R` (each test runs the finite-difference check with `R = f64` and the
/// smoke test with `R = f32`).
macro_rules! fd_tests {
    ($( $test:ident: $f:ident, $adj:ident, $tan:ident [$($t:ty = $g:expr),+ $(,)?]; )*) => {$(
        #[test]
        fn $test() {
            #[allow(clippy::extra_unused_type_parameters)]
            fn sample<R: $crate::Real>(rng: &mut $crate::math::check::Rng) -> ($($t,)+) {
                ($(($g)(rng),)+)
            }
            $crate::math::check::check_rule(stringify!($test), sample::<f64>, $f, $adj, $tan);
            $crate::math::check::smoke_f32(
                stringify!($test), sample::<f32>, sample::<f64>, $f, $f, $adj, $adj, $tan, $tan,
            );
        }
    )*};
}
pub(crate) use fd_tests;
