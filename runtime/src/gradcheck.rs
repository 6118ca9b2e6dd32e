//! Gradient checks for users: adjoint gradients against central finite differences, Jacobians
//! three ways (adjoint rows, tangent columns, finite differences) and the dot-product test
//! `<J v, w> = <v, J^T w>` between forward and reverse mode.
//!
//! # The finite-difference step, chosen per scalar
//!
//! No single step suits every computation: a large one has truncation error (and may cross a
//! kink, a contact switching on), a small one amplifies the round-off of the forward pass (a
//! long rollout's loss is smooth only down to some noise level, so its difference quotient
//! at `h = 1e-6` can be off by percents while the adjoint is right). By default
//! ([`GradCheck::new`]) each scalar `x` is checked with a sweep: central differences `D(h)` at
//! the three steps `h = s * 1e-3, s * 1e-4, s * 1e-5`, `s = max(|x|, 1)` (6 evaluations), and
//! their Richardson extrapolations (which cancel the `h^2` error term). Each of these
//! estimates gets an uncertainty: twice its disagreement with the next finer estimate
//! (truncation error, and the noise of the finer one) plus three times its own noise, `3 e /
//! (sqrt(2) h)`, where `e` is the noise of one evaluation of the computation, estimated from
//! the even part of the differences (`f(x+h) + f(x-h) - 2 f(x)` at the two finest steps, whose
//! noise is independent of the odd part's) and at least a few rounding errors of the loss
//! value. The estimate with the smallest uncertainty is the numeric derivative
//! ([`Entry::numeric`], with [`Entry::uncertainty`] and [`Entry::step`]), and the check
//! compares the adjoint with it *beyond* that uncertainty ([`Entry::error`]): a right gradient
//! passes however noisy the forward pass (the uncertainty grows with the noise), and a wrong
//! one fails as soon as its error exceeds what the differences can resolve (an adjoint off by
//! 1% fails unless the loss is noisy at the 1e-3 level at steps of `1e-3 s`; the uncertainty
//! in the report says how well each derivative was resolved).
//!
//! [`GradCheck::step`] fixes the step instead: one central difference per scalar (2
//! evaluations), uncertainty 0, as plain central differences do.
//!
//! Finite differences need `f64`: an `f32` array cannot represent small perturbations and an
//! `f32` loss is noisy at the 1e-7 level. Check a kernel written generically over `R: Real`
//! through its `f64` instantiation; the `f32` one runs the same source. Every perturbed value
//! is restored exactly (also when the computation panics).
//!
//! The Jacobian functions and [`dot_test`] take a computation with several outputs: a closure
//! that records its steps on the tape it is given and returns the output arrays
//! (`vec![y.boxed(), z.boxed()]`).

use std::collections::HashSet;
use std::fmt;
use std::ops::Index;

use crate::array::{AnyArray, Array, Element};
use crate::error::Error;
use crate::kernel::{Access, Kernel, KernelBody, Mode};
use crate::launch::bind;
use crate::tape::Tape;

/// Settings of a gradient check. [`gradcheck`] and [`gradcheck_kernel`] use the defaults
/// (the step chosen per scalar, see the [module docs](self)).
///
/// ```
/// use adflex_runtime::gradcheck::GradCheck;
/// let check = GradCheck::new().step(1e-7).worst(5).seed(42);
/// # let _ = check;
/// ```
#[derive(Debug, Clone)]
pub struct GradCheck {
    /// A fixed step, or `None`: a sweep per scalar.
    h: Option<f64>,
    worst: usize,
    seed: u64,
    floor: f64,
}

impl Default for GradCheck {
    fn default() -> Self {
        GradCheck {
            h: None,
            worst: 10,
            seed: 0x5eed_ad1e,
            floor: 1e-12,
        }
    }
}

/// The steps of the sweep, relative to `max(|x|, 1)` (see the [module docs](self)).
pub const SWEEP: [f64; 3] = [1e-3, 1e-4, 1e-5];

/// One checked scalar: where it is, both derivatives, how well the numeric one is known and
/// their relative error beyond that.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// The array's label.
    pub array: String,
    /// Element index.
    pub index: usize,
    /// Component within the element (0 for scalars; `k` of a vector).
    pub component: usize,
    /// The adjoint (tape) derivative.
    pub analytic: f64,
    /// The finite-difference derivative (a central difference or its Richardson
    /// extrapolation, whichever is known best; see the [module docs](self)).
    pub numeric: f64,
    /// An estimate of how far `numeric` may be from the true derivative (absolute; from the
    /// disagreement of the steps and the noise of the computation); 0 with a fixed step.
    pub uncertainty: f64,
    /// The step of `numeric` (the larger one, for an extrapolation).
    pub step: f64,
    /// `max(|analytic - numeric| - uncertainty, 0) / max(|analytic|, |numeric|, scale)`: the
    /// relative error beyond what the differences resolve, see [`Report`].
    pub error: f64,
}

/// The result of a gradient check: the worst entries first.
///
/// The error of an entry is relative, and counts only what exceeds the finite differences'
/// uncertainty `u`: `max(|a - n| - u, 0) / max(|a|, |n|, s)` where `s` is `1e-3` times the
/// largest `|n|` of the whole check (so derivatives that are zero are compared at the scale of
/// the gradient, not at their own) and at least [`GradCheck::floor`]. A NaN counts as failing.
#[derive(Debug, Clone)]
pub struct Report {
    /// The worst entries, worst first (at most [`GradCheck::worst`]).
    pub entries: Vec<Entry>,
    /// Number of scalars checked.
    pub checked: usize,
    /// The largest error (NaN if any derivative was NaN).
    pub max_error: f64,
    /// The fixed finite-difference step ([`GradCheck::step`]), or `None`: chosen per scalar
    /// ([`Entry::step`]).
    pub h: Option<f64>,
}

impl Report {
    /// Whether every entry is within `tol` (and none is NaN).
    pub fn is_within(&self, tol: f64) -> bool {
        self.entries.iter().all(|e| e.error <= tol)
    }

    /// Panics with the report if an entry's error exceeds `tol`.
    pub fn assert_within(&self, tol: f64) {
        if !self.is_within(tol) {
            panic!("gradient check failed (tolerance {tol:e}):\n{self}");
        }
    }
}

impl fmt::Display for Report {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.h {
            Some(h) => writeln!(
                f,
                "gradient check of {} scalars (fixed step h = {h:e}): max relative error {:e}",
                self.checked, self.max_error
            )?,
            None => writeln!(
                f,
                "gradient check of {} scalars (steps chosen per scalar): max relative error \
                 beyond the finite differences' uncertainty {:e}",
                self.checked, self.max_error
            )?,
        }
        if self.entries.is_empty() {
            return Ok(());
        }
        let w = self
            .entries
            .iter()
            .map(|e| e.array.len())
            .max()
            .unwrap_or(0)
            .max(5);
        writeln!(
            f,
            "  {:<w$} {:>7} {:>4} {:>23} {:>23} {:>10} {:>8} {:>10}",
            "array", "index", "comp", "analytic", "numeric", "+-", "step", "rel.error"
        )?;
        for e in &self.entries {
            writeln!(
                f,
                "  {:<w$} {:>7} {:>4} {:>23.15e} {:>23.15e} {:>10.2e} {:>8.1e} {:>10.3e}",
                e.array,
                e.index,
                e.component,
                e.analytic,
                e.numeric,
                e.uncertainty,
                e.step,
                e.error
            )?;
        }
        Ok(())
    }
}

/// A small deterministic generator (splitmix64) for seeds and directions.
struct Rng(u64);

impl Rng {
    /// Uniform in `[-1, 1)`.
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        (z >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

fn values(a: &dyn AnyArray) -> Vec<f64> {
    (0..a.n_scalars()).map(|k| a.scalar(k)).collect()
}

fn grads(a: &dyn AnyArray) -> Vec<f64> {
    match a.grad_any() {
        Some(g) => values(&*g),
        None => vec![0.0; a.n_scalars()],
    }
}

fn ids(arrays: &[&dyn AnyArray]) -> HashSet<u64> {
    arrays.iter().map(|a| a.id()).collect()
}

/// Puts a perturbed scalar back when dropped (also on panic).
struct Restore<'a> {
    array: &'a dyn AnyArray,
    k: usize,
    value: f64,
}

impl Drop for Restore<'_> {
    fn drop(&mut self) {
        self.array.set_scalar(self.k, self.value);
    }
}

/// Central differences of `eval` (a vector-valued function of the current array values) with
/// respect to every scalar of `inputs`: one column per scalar. Uses the perturbation actually
/// stored (after rounding to the element type) and restores every value exactly.
fn central(inputs: &[&dyn AnyArray], h: f64, mut eval: impl FnMut() -> Vec<f64>) -> Vec<Vec<f64>> {
    each_scalar(inputs, |x0, set| {
        let xp = set(x0 + h);
        let fp = eval();
        let xm = set(x0 - h);
        let fm = eval();
        fp.iter()
            .zip(&fm)
            .map(|(p, m)| (p - m) / (xp - xm))
            .collect()
    })
}

/// `f(x0, set)` for every scalar of `inputs`, `x0` its value and `set(x)` storing `x` there and
/// returning the value actually stored (after rounding to the element type); the scalar is
/// restored exactly afterwards, also if `f` panics.
fn each_scalar<T>(
    inputs: &[&dyn AnyArray],
    mut f: impl FnMut(f64, &mut dyn FnMut(f64) -> f64) -> T,
) -> Vec<T> {
    let mut out = Vec::new();
    for &a in inputs {
        for k in 0..a.n_scalars() {
            let x0 = a.scalar(k);
            let guard = Restore {
                array: a,
                k,
                value: x0,
            };
            out.push(f(x0, &mut |x| {
                a.set_scalar(k, x);
                a.scalar(k)
            }));
            drop(guard);
            debug_assert_eq!(a.scalar(k).to_bits(), x0.to_bits());
        }
    }
    out
}

/// A finite-difference derivative: its value, uncertainty and step.
#[derive(Clone, Copy, Debug)]
struct Fd {
    value: f64,
    uncertainty: f64,
    step: f64,
}

/// The derivatives of the scalar function `eval` (of the current array values; `f0` is its
/// value at them) with respect to every scalar of `inputs`, each by a sweep of steps (see the
/// [module docs](self)). Uses the perturbations actually stored and restores every value
/// exactly.
fn sweep(inputs: &[&dyn AnyArray], f0: f64, mut eval: impl FnMut() -> f64) -> Vec<Fd> {
    each_scalar(inputs, |x0, set| {
        let s = x0.abs().max(1.0);
        // Per step: the half-width, the central difference, the second-derivative estimate
        // (from the even part).
        let mut h = [0.0; 3];
        let mut d = [0.0; 3];
        let mut dd = [0.0; 3];
        let mut fmax = f0.abs();
        for (j, rel) in SWEEP.iter().enumerate() {
            let xp = set(x0 + s * rel);
            let fp = eval();
            let xm = set(x0 - s * rel);
            let fm = eval();
            let (hp, hm) = (xp - x0, x0 - xm);
            h[j] = 0.5 * (xp - xm);
            d[j] = (fp - fm) / (xp - xm);
            dd[j] = ((fp - f0) / hp - (f0 - fm) / hm) / h[j];
            fmax = fmax.max(fp.abs()).max(fm.abs());
        }
        choose(&h, &d, &dd, fmax)
    })
}

/// The best-known derivative from the sweep's central differences `d` at half-widths `h`
/// (decreasing) and second-derivative estimates `dd` (see the [module docs](self)).
fn choose(h: &[f64; 3], d: &[f64; 3], dd: &[f64; 3], fmax: f64) -> Fd {
    // Richardson: D(h) = f' + c h^2 + ...
    let rich =
        |i: usize, j: usize| d[j] + (d[j] - d[i]) * h[j] * h[j] / (h[i] * h[i] - h[j] * h[j]);
    let (r01, r12) = (rich(0, 1), rich(1, 2));
    // The noise of one evaluation: the even part at the two finest steps (its noise
    // dominated by the finest: e sqrt(6) / h^2), at least a few roundings of the loss.
    let even = (dd[2] - dd[1]).abs() * h[2] * h[2] / 6f64.sqrt();
    let e = if even.is_finite() {
        even
    } else {
        f64::INFINITY
    };
    let e = e.max(4.0 * f64::EPSILON * fmax);
    let noise = |j: usize| 3.0 * e / (std::f64::consts::SQRT_2 * h[j]);
    let candidates = [
        (d[0], 2.0 * (d[0] - r01).abs() + noise(0), h[0]),
        (r01, 2.0 * (r01 - r12).abs() + noise(1), h[0]),
        (d[1], 2.0 * (d[1] - r12).abs() + noise(1), h[1]),
        (d[2], 2.0 * (d[2] - d[1]).abs() + noise(2), h[2]),
    ];
    candidates
        .iter()
        .filter(|(v, u, _)| v.is_finite() && u.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|&(value, uncertainty, step)| Fd {
            value,
            uncertainty,
            step,
        })
        .unwrap_or(Fd {
            value: f64::NAN,
            uncertainty: f64::NAN,
            step: h[0],
        })
}

/// The derivatives of `eval` by a fixed step `h` or by a sweep (`None`).
fn numeric(
    inputs: &[&dyn AnyArray],
    h: Option<f64>,
    f0: f64,
    mut eval: impl FnMut() -> f64,
) -> Vec<Fd> {
    match h {
        Some(h) => central(inputs, h, || vec![eval()])
            .into_iter()
            .map(|c| Fd {
                value: c[0],
                uncertainty: 0.0,
                step: h,
            })
            .collect(),
        None => sweep(inputs, f0, eval),
    }
}

fn sum_scalars(a: &dyn AnyArray) -> f64 {
    values(a).iter().sum()
}

impl GradCheck {
    /// The defaults: the step chosen per scalar (see the [module docs](self)), the 10 worst
    /// entries, a fixed seed, floor `1e-12`.
    pub fn new() -> Self {
        Self::default()
    }

    /// A fixed finite-difference step `h` for every scalar (central differences
    /// `(f(x+h) - f(x-h)) / 2h`, 2 evaluations per scalar, no uncertainty estimate) instead of
    /// the default sweep.
    pub fn step(mut self, h: f64) -> Self {
        self.h = Some(h);
        self
    }

    /// How many of the worst entries the report keeps.
    pub fn worst(mut self, n: usize) -> Self {
        self.worst = n;
        self
    }

    /// The seed of the random weights and directions.
    pub fn seed(mut self, seed: u64) -> Self {
        self.seed = seed;
        self
    }

    /// The smallest scale relative errors are taken against (see [`Report`]).
    pub fn floor(mut self, floor: f64) -> Self {
        self.floor = floor;
        self
    }

    fn report(&self, inputs: &[&dyn AnyArray], analytic: &[f64], numeric: &[Fd]) -> Report {
        let scale = numeric.iter().fold(0.0f64, |m, n| m.max(n.value.abs())) * 1e-3;
        let scale = scale.max(self.floor);
        let mut entries = Vec::with_capacity(analytic.len());
        let mut at = 0;
        for &a in inputs {
            let dim = a.element_dim();
            let label = a.label();
            for k in 0..a.n_scalars() {
                let (an, fd) = (analytic[at], numeric[at]);
                let nu = fd.value;
                let beyond = ((an - nu).abs() - fd.uncertainty).max(0.0);
                let error = beyond / an.abs().max(nu.abs()).max(scale);
                entries.push(Entry {
                    array: label.clone(),
                    index: k / dim,
                    component: k % dim,
                    analytic: an,
                    numeric: nu,
                    uncertainty: fd.uncertainty,
                    step: fd.step,
                    error: if an.is_nan() || nu.is_nan() || fd.uncertainty.is_nan() {
                        f64::NAN
                    } else {
                        error
                    },
                });
                at += 1;
            }
        }
        let key = |e: &Entry| {
            if e.error.is_nan() {
                f64::INFINITY
            } else {
                e.error
            }
        };
        entries.sort_by(|a, b| key(b).total_cmp(&key(a)));
        let max_error = entries.first().map_or(0.0, |e| e.error);
        let checked = entries.len();
        entries.truncate(self.worst);
        Report {
            entries,
            checked,
            max_error,
            h: self.h,
        }
    }

    /// Checks the gradient of the computation `f` with respect to every scalar of `params`.
    ///
    /// `f` records the whole computation on the tape it is given and returns the loss array
    /// (its elements are summed). It runs once for the adjoint gradient and 6 times per scalar
    /// of `params` for the differences (2 with a fixed [`GradCheck::step`]), each time on a
    /// fresh tape: it must recompute everything
    /// from the parameters (allocate or zero the arrays it accumulates into). `params` need not
    /// require grad; their gradient buffers are zeroed and overwritten.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// let x = Array::from_vec(vec![1.0f64, -2.0]).named("x");
    /// let report = gradcheck(
    ///     |tape| {
    ///         // loss = sum x^3 on the host, with its backward 3 x^2.
    ///         let loss = Array::<f64>::zeros(1);
    ///         let (xb, lb) = (x.clone(), loss.clone());
    ///         tape.record_fn(
    ///             "cubes", &[&x], &[&loss],
    ///             || loss.set(0, x.to_vec().iter().map(|v| v * v * v).sum()),
    ///             move || {
    ///                 let (d, xs) = (lb.grad_buffer().unwrap().get(0), xb.to_vec());
    ///                 if let Some(g) = xb.grad_buffer() {
    ///                     g.modify(|g| g.iter_mut().zip(xs).for_each(|(g, x)| *g += 3.0 * x * x * d));
    ///                 }
    ///                 Ok(())
    ///             },
    ///         );
    ///         loss
    ///     },
    ///     &[&x],
    /// )
    /// .unwrap();
    /// report.assert_within(1e-6);
    /// ```
    pub fn run<L: Element>(
        &self,
        mut f: impl FnMut(&mut Tape) -> Array<L>,
        params: &[&dyn AnyArray],
    ) -> Result<Report, Error> {
        for p in params {
            p.zero_grad();
        }
        let mut tape = Tape::new();
        let loss = f(&mut tape);
        tape.backward_sources(&loss, &ids(params))?;
        drop(tape);
        let f0 = sum_scalars(&loss);
        let analytic: Vec<f64> = params.iter().flat_map(|&p| grads(p)).collect();
        let numeric = numeric(params, self.h, f0, || {
            let mut tape = Tape::new();
            sum_scalars(&f(&mut tape))
        });
        Ok(self.report(params, &analytic, &numeric))
    }

    /// Checks one launch of `kernel`: with random weights `w` on the scalars of the arrays it
    /// writes, the loss `<w, outputs>` is differentiated by the adjoint kernel and by central
    /// differences with respect to every scalar of every array it reads.
    ///
    /// Value parameters are not checked (pass a value as a 1-element array to check it).
    /// Outputs are restored before every run, so `atomic_*` outputs start from their values at
    /// the call; at the end they hold the result of one forward launch. The gradient buffers
    /// of the kernel's arrays are allocated if missing and overwritten.
    ///
    /// ```
    /// use adflex_runtime::prelude::*;
    /// use adflex_macros::diff_kernel;
    ///
    /// #[diff_kernel]
    /// fn spring_energy(x: &Array<f64>, k: &Array<f64>, e: &Array<f64>) {
    ///     let t = tid();
    ///     let d = x[t + 1] - x[t] - 1.0;
    ///     e[t] = 0.5 * k[t] * d * d;
    /// }
    /// let x = Array::from_vec(vec![0.0, 1.2, 2.1]);
    /// let k = Array::from_vec(vec![10.0, 20.0]);
    /// let e = Array::zeros(2);
    /// GradCheck::new().kernel(spring_energy, 2, (&x, &k, &e))?.assert_within(1e-6);
    /// # Ok::<(), Error>(())
    /// ```
    pub fn kernel<K, A>(&self, kernel: K, dim: usize, args: A) -> Result<Report, Error>
    where
        K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
    {
        let bound = bind(kernel, args);
        let arrays = bound.arrays();
        let (mut inputs, mut outputs): (Vec<&dyn AnyArray>, Vec<&dyn AnyArray>) =
            (Vec::new(), Vec::new());
        for (p, a) in bound.params().iter().zip(&arrays) {
            let Some(a) = *a else { continue };
            let list = match p.access {
                Access::Read if a.element_dim() > 0 => &mut inputs,
                Access::Store | Access::Atomic => &mut outputs,
                _ => continue,
            };
            if !list.iter().any(|b| b.id() == a.id()) {
                list.push(a);
            }
        }
        let saved: Vec<Vec<f64>> = outputs.iter().map(|&o| values(o)).collect();
        let mut rng = Rng(self.seed);
        let weights: Vec<Vec<f64>> = outputs
            .iter()
            .map(|&o| (0..o.n_scalars()).map(|_| rng.next()).collect())
            .collect();
        let restore = || {
            for (o, v) in outputs.iter().zip(&saved) {
                for (k, &x) in v.iter().enumerate() {
                    o.set_scalar(k, x);
                }
            }
        };
        let eval = || {
            restore();
            bound.run(Mode::Forward, dim);
            let mut sum = 0.0;
            for (o, w) in outputs.iter().zip(&weights) {
                for (k, w) in w.iter().enumerate() {
                    sum += w * o.scalar(k);
                }
            }
            sum
        };

        let f0 = eval();
        for a in &inputs {
            a.ensure_grad();
            a.zero_grad();
        }
        for (o, w) in outputs.iter().zip(&weights) {
            o.ensure_grad();
            let g = o.grad_any().expect("just allocated");
            for (k, &w) in w.iter().enumerate() {
                g.set_scalar(k, w);
            }
        }
        bound.run(Mode::Adjoint, dim);
        let analytic: Vec<f64> = inputs.iter().flat_map(|&a| grads(a)).collect();
        let numeric = numeric(&inputs, self.h, f0, eval);
        restore();
        bound.run(Mode::Forward, dim);
        Ok(self.report(&inputs, &analytic, &numeric))
    }
}

/// [`GradCheck::run`] with the default settings.
pub fn gradcheck<L: Element>(
    f: impl FnMut(&mut Tape) -> Array<L>,
    params: &[&dyn AnyArray],
) -> Result<Report, Error> {
    GradCheck::new().run(f, params)
}

/// [`GradCheck::kernel`] with the default settings.
pub fn gradcheck_kernel<K, A>(kernel: K, dim: usize, args: A) -> Result<Report, Error>
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    GradCheck::new().kernel(kernel, dim, args)
}

/// A dense Jacobian: one row per output scalar, one column per input scalar, in the order of
/// the arrays, elements and components.
#[derive(Debug, Clone, PartialEq)]
pub struct Jacobian {
    /// Number of output scalars.
    pub rows: usize,
    /// Number of input scalars.
    pub cols: usize,
    /// Row-major entries.
    pub data: Vec<f64>,
}

impl Jacobian {
    fn zeros(rows: usize, cols: usize) -> Self {
        Jacobian {
            rows,
            cols,
            data: vec![0.0; rows * cols],
        }
    }

    /// The largest `|self[i, j] - other[i, j]|`. Panics if the shapes differ.
    pub fn max_abs_diff(&self, other: &Jacobian) -> f64 {
        assert_eq!(
            (self.rows, self.cols),
            (other.rows, other.cols),
            "Jacobians of different shapes"
        );
        self.data
            .iter()
            .zip(&other.data)
            .fold(0.0, |m, (a, b)| m.max((a - b).abs()))
    }
}

impl Index<(usize, usize)> for Jacobian {
    type Output = f64;
    fn index(&self, (i, j): (usize, usize)) -> &f64 {
        assert!(
            i < self.rows && j < self.cols,
            "Jacobian index out of bounds"
        );
        &self.data[i * self.cols + j]
    }
}

fn outputs_of(outs: &[Box<dyn AnyArray>]) -> Vec<&dyn AnyArray> {
    outs.iter().map(|b| &**b).collect()
}

/// The Jacobian of `f`'s outputs with respect to `inputs`, one row per backward pass (reverse
/// mode). `f` runs once. `inputs` need not require grad; gradient buffers on the tape are
/// zeroed and overwritten.
///
/// ```
/// use adflex_runtime::prelude::*;
/// use adflex_runtime::gradcheck::{jacobian_adjoint, jacobian_fd};
/// use adflex_runtime::AnyArray;
/// let x = Array::from_vec(vec![3.0f64]);
/// let f = |tape: &mut Tape| {
///     let y = Array::<f64>::zeros(2);
///     let (xb, yb) = (x.clone(), y.clone());
///     tape.record_fn("y = (x, x^2)", &[&x], &[&y], || y.assign(&[x.get(0), x.get(0) * x.get(0)]),
///         move || {
///             let (gy, x) = (yb.grad_buffer().unwrap(), xb.get(0));
///             if let Some(g) = xb.grad_buffer() {
///                 g.modify(|g| g[0] += gy.get(0) + 2.0 * x * gy.get(1));
///             }
///             Ok(())
///         });
///     vec![y.boxed()]
/// };
/// let j = jacobian_adjoint(f, &[&x]).unwrap();
/// assert_eq!((j[(0, 0)], j[(1, 0)]), (1.0, 6.0));
/// assert!(j.max_abs_diff(&jacobian_fd(f, &[&x], 1e-6).unwrap()) < 1e-6);
/// ```
pub fn jacobian_adjoint(
    mut f: impl FnMut(&mut Tape) -> Vec<Box<dyn AnyArray>>,
    inputs: &[&dyn AnyArray],
) -> Result<Jacobian, Error> {
    let mut tape = Tape::new();
    let outs = f(&mut tape);
    let outs = outputs_of(&outs);
    let sources = ids(inputs);
    let rows = outs.iter().map(|&o| o.n_scalars()).sum();
    let cols = inputs.iter().map(|&a| a.n_scalars()).sum();
    let mut j = Jacobian::zeros(rows, cols);
    for o in &outs {
        o.ensure_grad();
    }
    let mut row = 0;
    for o in &outs {
        for k in 0..o.n_scalars() {
            tape.zero();
            for a in inputs.iter().chain(&outs) {
                a.zero_grad();
            }
            o.grad_any().expect("allocated").set_scalar(k, 1.0);
            tape.backward_seeded(&outs, &sources)?;
            let g: Vec<f64> = inputs.iter().flat_map(|&a| grads(a)).collect();
            j.data[row * cols..(row + 1) * cols].copy_from_slice(&g);
            row += 1;
        }
    }
    Ok(j)
}

fn tangents(a: &dyn AnyArray) -> Vec<f64> {
    match a.tangent_any() {
        Some(t) => values(&*t),
        None => vec![0.0; a.n_scalars()],
    }
}

/// The Jacobian of `f`'s outputs with respect to `inputs`, one column per forward-mode pass
/// ([`Tape::tangent`]). `f` runs once. The inputs must be leaves (no recorded step writes
/// them); their tangent buffers are left zeroed.
pub fn jacobian_tangent(
    mut f: impl FnMut(&mut Tape) -> Vec<Box<dyn AnyArray>>,
    inputs: &[&dyn AnyArray],
) -> Result<Jacobian, Error> {
    let mut tape = Tape::new();
    let outs = f(&mut tape);
    let outs = outputs_of(&outs);
    let rows = outs.iter().map(|&o| o.n_scalars()).sum();
    let cols = inputs.iter().map(|&a| a.n_scalars()).sum();
    let mut j = Jacobian::zeros(rows, cols);
    let mut col = 0;
    for a in inputs {
        for k in 0..a.n_scalars() {
            for b in inputs {
                b.reset_tangent();
            }
            a.tangent_any().expect("allocated").set_scalar(k, 1.0);
            tape.tangent()?;
            let t: Vec<f64> = outs.iter().flat_map(|&o| tangents(o)).collect();
            for (i, v) in t.into_iter().enumerate() {
                j.data[i * cols + col] = v;
            }
            col += 1;
        }
    }
    for b in inputs {
        b.clear_tangent();
    }
    Ok(j)
}

/// The Jacobian of `f`'s outputs with respect to `inputs` by central differences with step
/// `h`; `f` runs twice per input scalar, each time on a fresh tape. Every perturbed value is
/// restored exactly.
pub fn jacobian_fd(
    mut f: impl FnMut(&mut Tape) -> Vec<Box<dyn AnyArray>>,
    inputs: &[&dyn AnyArray],
    h: f64,
) -> Result<Jacobian, Error> {
    let cols_data = central(inputs, h, || {
        let mut tape = Tape::new();
        let outs = f(&mut tape);
        outs.iter().flat_map(|o| values(&**o)).collect()
    });
    let cols = cols_data.len();
    let rows = cols_data.first().map_or_else(
        || {
            let mut tape = Tape::new();
            f(&mut tape).iter().map(|o| o.n_scalars()).sum()
        },
        Vec::len,
    );
    let mut j = Jacobian::zeros(rows, cols);
    for (c, col) in cols_data.iter().enumerate() {
        for (r, v) in col.iter().enumerate() {
            j.data[r * cols + c] = *v;
        }
    }
    Ok(j)
}

/// The two sides of the dot-product test, see [`dot_test`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DotTest {
    /// `<J v, w>` (forward mode).
    pub jv_w: f64,
    /// `<v, J^T w>` (reverse mode).
    pub v_jtw: f64,
}

impl DotTest {
    /// `|jv_w - v_jtw| / max(|jv_w|, |v_jtw|, 1e-300)`.
    pub fn rel_error(&self) -> f64 {
        (self.jv_w - self.v_jtw).abs() / self.jv_w.abs().max(self.v_jtw.abs()).max(1e-300)
    }

    /// Panics with both sides if [`DotTest::rel_error`] exceeds `tol`.
    pub fn assert_within(&self, tol: f64) {
        let e = self.rel_error();
        assert!(
            e <= tol,
            "dot-product test failed: <J v, w> = {:e}, <v, J^T w> = {:e}, relative error {e:e} > {tol:e}",
            self.jv_w,
            self.v_jtw
        );
    }
}

/// The dot-product test between forward and reverse mode: with random `v` (over the inputs)
/// and `w` (over the outputs), `<J v, w>` from one tangent pass equals `<v, J^T w>` from one
/// backward pass, up to rounding. `f` runs once; inputs must be leaves (see
/// [`jacobian_tangent`]). Gradient buffers on the tape are overwritten.
pub fn dot_test(
    mut f: impl FnMut(&mut Tape) -> Vec<Box<dyn AnyArray>>,
    inputs: &[&dyn AnyArray],
    seed: u64,
) -> Result<DotTest, Error> {
    let mut tape = Tape::new();
    let outs = f(&mut tape);
    let outs = outputs_of(&outs);
    let mut rng = Rng(seed);
    let v: Vec<Vec<f64>> = inputs
        .iter()
        .map(|&a| (0..a.n_scalars()).map(|_| rng.next()).collect())
        .collect();
    let w: Vec<Vec<f64>> = outs
        .iter()
        .map(|&o| (0..o.n_scalars()).map(|_| rng.next()).collect())
        .collect();
    for (a, v) in inputs.iter().zip(&v) {
        a.reset_tangent();
        let t = a.tangent_any().expect("allocated");
        for (k, &x) in v.iter().enumerate() {
            t.set_scalar(k, x);
        }
    }
    tape.tangent()?;
    let dot = |x: &[Vec<f64>], y: Vec<f64>| x.iter().flatten().zip(y).map(|(a, b)| a * b).sum();
    let jv_w = dot(&w, outs.iter().flat_map(|&o| tangents(o)).collect());
    tape.zero();
    for a in inputs.iter().chain(&outs) {
        a.zero_grad();
    }
    for (o, w) in outs.iter().zip(&w) {
        o.ensure_grad();
        let g = o.grad_any().expect("allocated");
        for (k, &x) in w.iter().enumerate() {
            g.set_scalar(k, x);
        }
    }
    tape.backward_seeded(&outs, &ids(inputs))?;
    let v_jtw = dot(&v, inputs.iter().flat_map(|&a| grads(a)).collect());
    for a in inputs {
        a.clear_tangent();
    }
    Ok(DotTest { jv_w, v_jtw })
}
