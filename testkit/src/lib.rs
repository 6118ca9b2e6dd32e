//! The test harness every test crate of adflex shares: a deterministic generator and the
//! kernel check (the adjoint against central finite differences in f64, the tangent against
//! the adjoint by the dot-product test). Not published; the public
//! `adflex_runtime::gradcheck` checks whole tapes, this checks one kernel's three modes.

use adflex_runtime::{Array, Mode, Quat, Vec3};

/// A deterministic xorshift generator (tests need no rand dependency for this).
pub struct Rng(pub u64);

impl Rng {
    pub fn next_f64(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    /// Uniform in `[lo, hi)`.
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }
    pub fn vec(&mut self, n: usize, lo: f64, hi: f64) -> Vec<f64> {
        (0..n).map(|_| self.uniform(lo, hi)).collect()
    }
    /// Same as [`Rng::vec`].
    pub fn scalars(&mut self, n: usize, lo: f64, hi: f64) -> Vec<f64> {
        self.vec(n, lo, hi)
    }
    /// A `Vec3` with components uniform in `[lo, hi)`.
    pub fn vec3(&mut self, lo: f64, hi: f64) -> Vec3<f64> {
        Vec3::new(
            self.uniform(lo, hi),
            self.uniform(lo, hi),
            self.uniform(lo, hi),
        )
    }
    /// `n` of [`Rng::vec3`].
    pub fn vec3s(&mut self, n: usize, lo: f64, hi: f64) -> Vec<Vec3<f64>> {
        (0..n).map(|_| self.vec3(lo, hi)).collect()
    }
    /// A random unit quaternion.
    pub fn quat(&mut self) -> Quat<f64> {
        let q = Quat::new(
            self.uniform(-1.0, 1.0),
            self.uniform(-1.0, 1.0),
            self.uniform(-1.0, 1.0),
            self.uniform(-1.0, 1.0),
        );
        q / q.norm()
    }
}

/// Result of a gradient check.
#[derive(Debug)]
pub struct Checked {
    /// Worst relative error of the adjoint against central differences.
    pub adjoint_err: f64,
    /// Where it is: (input array, index, adjoint, central difference).
    pub worst: (usize, usize, f64, f64),
    /// Relative error of the dot-product test `<J v, w> = <v, J^T w>`.
    pub dot_err: f64,
    /// `<J v, w>` (tangent) and `<v, J^T w>` (adjoint).
    pub dot: (f64, f64),
    /// The adjoint gradient (of `<w, outputs>` with respect to each input).
    pub grad: Vec<Vec<f64>>,
}

/// `|a - b| / max(|a|, |b|, 1)`.
pub fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(1.0)
}

/// Checks one kernel: `run(mode)` launches it on `inputs` (read) and `outputs` (written).
///
/// The loss is `<w, outputs>` for a random `w`. The adjoint gradient is compared with central
/// differences (h = 1e-6) of the loss for every input entry, and the tangent `J v` for a random
/// `v` with the adjoint by the dot-product test.
/// (`run` is a `&dyn Fn`, so this is compiled once, not once per kernel.)
pub fn check(
    inputs: &[&Array<f64>],
    outputs: &[&Array<f64>],
    seed: u64,
    run: &dyn Fn(Mode),
) -> Checked {
    let mut rng = Rng(seed | 1);
    let forward = || -> Vec<Vec<f64>> {
        for o in outputs {
            o.fill(0.0);
        }
        run(Mode::Forward);
        outputs.iter().map(|o| o.to_vec()).collect()
    };
    let w: Vec<Vec<f64>> = outputs
        .iter()
        .map(|o| rng.vec(o.len(), -1.0, 1.0))
        .collect();
    let loss = |ys: &[Vec<f64>]| -> f64 {
        ys.iter()
            .zip(&w)
            .map(|(y, w)| y.iter().zip(w).map(|(a, b)| a * b).sum::<f64>())
            .sum()
    };
    forward();
    // Adjoint.
    for (o, w) in outputs.iter().zip(&w) {
        o.ensure_grad().assign(w);
    }
    for i in inputs {
        i.ensure_grad().fill(0.0);
    }
    run(Mode::Adjoint);
    let grad: Vec<Vec<f64>> = inputs.iter().map(|i| i.grad().unwrap().to_vec()).collect();
    // Central differences.
    let h = 1e-6;
    let mut adjoint_err: f64 = 0.0;
    let mut worst = (0, 0, 0.0, 0.0);
    for (ai, (a, g)) in inputs.iter().zip(&grad).enumerate() {
        for (k, &gk) in g.iter().enumerate() {
            let x0 = a.get(k);
            a.set(k, x0 + h);
            let lp = loss(&forward());
            a.set(k, x0 - h);
            let lm = loss(&forward());
            a.set(k, x0);
            let fd = (lp - lm) / (2.0 * h);
            let e = rel(fd, gk);
            // NaN counts as the worst error
            if e > adjoint_err || e.is_nan() && !adjoint_err.is_nan() {
                adjoint_err = e;
                worst = (ai, k, gk, fd);
            }
        }
    }
    // Tangent and the dot-product test.
    let v: Vec<Vec<f64>> = inputs.iter().map(|i| rng.vec(i.len(), -1.0, 1.0)).collect();
    for (i, v) in inputs.iter().zip(&v) {
        i.set_tangent(Some(Array::from_vec(v.clone())));
    }
    for o in outputs {
        o.ensure_tangent().fill(0.0);
    }
    forward();
    run(Mode::Tangent);
    let jv: f64 = outputs
        .iter()
        .zip(&w)
        .map(|(o, w)| {
            o.tangent_buffer()
                .unwrap()
                .to_vec()
                .iter()
                .zip(w)
                .map(|(a, b)| a * b)
                .sum::<f64>()
        })
        .sum();
    let vjtw: f64 = v
        .iter()
        .zip(&grad)
        .map(|(v, g)| v.iter().zip(g).map(|(a, b)| a * b).sum::<f64>())
        .sum();
    for i in inputs {
        i.set_tangent(None);
    }
    Checked {
        adjoint_err,
        worst,
        dot_err: rel(jv, vjtw),
        dot: (jv, vjtw),
        grad,
    }
}

/// Asserts the check passed: adjoint within `tol` of central differences, dot test to 1e-10,
/// and a gradient that is not identically zero (a check that cannot fail is a defect).
#[track_caller]
pub fn assert_checked(c: &Checked, tol: f64) {
    assert!(
        c.adjoint_err <= tol,
        "adjoint vs central differences: relative error {:e} > {tol:e} at input {} index {}: \
         adjoint {:e}, central difference {:e}",
        c.adjoint_err,
        c.worst.0,
        c.worst.1,
        c.worst.2,
        c.worst.3
    );
    assert!(
        c.dot_err <= 1e-10,
        "tangent vs adjoint (dot-product test): relative error {:e}",
        c.dot_err
    );
    assert!(
        c.grad.iter().flatten().any(|g| *g != 0.0),
        "the gradient is identically zero: the check cannot fail"
    );
}
