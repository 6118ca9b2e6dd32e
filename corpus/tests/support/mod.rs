//! The corpus driver, on the shared checker of `adflex-testkit` (adjoint against central finite
//! differences in f64, tangent against adjoint by the dot-product test):
//! runs each generated kernel, moves the inputs when a mismatch is only a branch boundary, and
//! reports every other mismatch with the kernel's source.
#![allow(dead_code)]

use std::panic::{catch_unwind, AssertUnwindSafe};

use adflex::prelude::*;
use adflex::runtime::kernel::{Kernel, KernelBody};

/// Tolerance of the adjoint against central differences (relative, as in tests/common).
pub const TOL: f64 = 1e-6;
/// Tolerance of the dot-product test.
pub const DOT_TOL: f64 = 1e-10;
/// Tolerance of the f32 forward against the f64 forward (relative to max(|f64|, 1)).
pub const F32_TOL: f64 = 1e-3;
/// Inputs are drawn from `[LO, HI)`.
pub const LO: f64 = 0.5;
pub const HI: f64 = 1.5;
/// How far the inputs are moved to tell a branch boundary from a wrong derivative.
pub const NEAR: f64 = 1e-4;
/// Input seeds tried per kernel before a failure that only ever shows at boundaries is reported.
pub const ATTEMPTS: u64 = 4;

pub use adflex_testkit::{check, rel, Checked, Rng};

/// Two launches of one kernel writing one output array, the second on other inputs (`b`),
/// as on a tape that overwrites (or accumulates into) an array: the loss `<w, y>` after both,
/// its gradient by the two adjoints in reverse order against central differences, for the
/// inputs of both launches. Only the stores of the second launch may receive the gradient of
/// an element it overwrote. Returns the worst relative error.
/// (`run(mode, inputs, y)` runs one launch; a `&dyn Fn`, compiled once.)
pub fn relaunch_err(
    a: &[Array<f64>],
    b: &[Array<f64>],
    seed: u64,
    run: &dyn Fn(Mode, &[Array<f64>], &Array<f64>),
) -> f64 {
    let mut rng = Rng(seed.rotate_left(29) | 1);
    let y = Array::<f64>::zeros(super::LEN);
    let w = rng.vec(super::LEN, -1.0, 1.0);
    let loss = || -> f64 {
        y.fill(0.0);
        run(Mode::Forward, a, &y);
        run(Mode::Forward, b, &y);
        y.to_vec().iter().zip(&w).map(|(y, w)| y * w).sum()
    };
    loss();
    for x in a.iter().chain(b) {
        x.ensure_grad().fill(0.0);
    }
    y.ensure_grad().assign(&w);
    run(Mode::Adjoint, b, &y);
    run(Mode::Adjoint, a, &y);
    let h = 1e-6;
    let mut worst: f64 = 0.0;
    for x in a.iter().chain(b) {
        let g = x.grad().unwrap().to_vec();
        for (k, gk) in g.iter().enumerate() {
            let x0 = x.get(k);
            x.set(k, x0 + h);
            let lp = loss();
            x.set(k, x0 - h);
            let lm = loss();
            x.set(k, x0);
            worst = worst.max(rel((lp - lm) / (2.0 * h), *gk));
        }
    }
    worst
}

/// Runs `kernel` over thread ids `0..dim` in `mode` on this thread (`launch_serial`: the same
/// bits as `launch_mode` for launches this small), without `launch_mode`'s thread-pool code,
/// which would be compiled once per kernel and argument type and dominate the corpus' compile
/// time.
pub fn run_direct<K, A>(mode: Mode, kernel: K, dim: usize, args: A)
where
    K: Kernel<A> + KernelBody<<K as Kernel<A>>::Owned>,
{
    assert!(dim < adflex::runtime::launch::SERIAL_BELOW);
    RUNS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    adflex::runtime::launch_serial(mode, kernel, dim, args);
}

/// The inputs as f64 arrays.
pub fn arrays_f64(xs: &[Vec<f64>]) -> Vec<Array<f64>> {
    xs.iter().map(|v| Array::from_vec(v.clone())).collect()
}

/// The inputs as f32 arrays.
pub fn arrays_f32(xs: &[Vec<f64>]) -> Vec<Array<f32>> {
    xs.iter()
        .map(|v| Array::from_vec(v.iter().map(|&x| x as f32).collect()))
        .collect()
}

/// Kernel runs so far (all threads of the test binary).
pub static RUNS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// What one run of a kernel gives: the f64 check, and its forward in f64 and in f32.
pub struct Outcome {
    pub checked: Checked,
    /// See [`relaunch_err`].
    pub relaunch_err: f64,
    pub y64: Vec<f64>,
    pub y32: Vec<f32>,
}

/// One generated kernel.
pub struct Case {
    pub name: &'static str,
    /// Number of input arrays (each `LEN` long).
    pub inputs: usize,
    /// Seed of its first inputs.
    pub seed: u64,
    /// Builds the arrays from the inputs, checks the kernel in f64 and runs it in f32.
    pub run: fn(&[Vec<f64>], u64) -> Outcome,
    /// The kernel's source.
    pub src: &'static str,
    /// The functions it calls (directly or not): indices into `FUNC_SRC`.
    pub funcs: &'static [usize],
}

fn inputs(case: &Case, seed: u64) -> Vec<Vec<f64>> {
    let mut rng = Rng(seed | 1);
    (0..case.inputs)
        .map(|_| rng.vec(super::LEN, LO, HI))
        .collect()
}

/// Runs the checks on inputs `xs`; `Err` says what failed.
fn evaluate(case: &Case, xs: &[Vec<f64>], seed: u64) -> Result<(), String> {
    let o = catch_unwind(AssertUnwindSafe(|| (case.run)(xs, seed))).map_err(|p| {
        let msg = p
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
        format!("panicked: {}", msg.unwrap_or_default())
    })?;
    let c = &o.checked;
    if let Some(y) = o.y64.iter().find(|y| !y.is_finite()) {
        return Err(format!("the f64 forward is not finite: {y}"));
    }
    if !(c.adjoint_err <= TOL) {
        let (a, k, g, fd) = c.worst;
        return Err(format!(
            "adjoint vs central differences: relative error {:e} > {TOL:e} at x{a}[{k}]: adjoint {g:e}, central difference {fd:e}",
            c.adjoint_err
        ));
    }
    if !(o.relaunch_err <= TOL) {
        return Err(format!(
            "two launches writing one array: adjoint vs central differences, relative error {:e} > {TOL:e}",
            o.relaunch_err
        ));
    }
    if !(c.dot_err <= DOT_TOL) {
        return Err(format!(
            "tangent vs adjoint (dot-product test): relative error {:e} > {DOT_TOL:e}: <J v, w> = {:e}, <v, J^T w> = {:e}",
            c.dot_err, c.dot.0, c.dot.1
        ));
    }
    if !c.grad.iter().flatten().any(|g| *g != 0.0) {
        return Err("the gradient is identically zero: the check cannot fail".into());
    }
    for (k, (a, b)) in o.y32.iter().zip(&o.y64).enumerate() {
        if !((*a as f64 - b).abs() <= F32_TOL * b.abs().max(1.0)) {
            return Err(format!(
                "f32 forward disagrees with f64 at y[{k}]: {a} vs {b}"
            ));
        }
    }
    Ok(())
}

/// Whether a failure at `xs` is local: it disappears when the inputs move by at most `NEAR`
/// (so `xs` is within `NEAR` of a branch boundary or a kink, where central differences
/// straddle two branches). A wrong derivative fails on a whole neighbourhood.
fn near_boundary(case: &Case, xs: &[Vec<f64>], seed: u64) -> bool {
    let mut rng = Rng(seed.rotate_left(17) | 1);
    (0..6).any(|_| {
        let moved: Vec<Vec<f64>> = xs
            .iter()
            .map(|v| v.iter().map(|x| x + rng.uniform(-NEAR, NEAR)).collect())
            .collect();
        evaluate(case, &moved, seed).is_ok()
    })
}

/// How a case ended.
pub enum Verdict {
    /// Passed after `moved` input moves away from boundaries.
    Pass { moved: u64 },
    /// A mismatch that persists: a bug.
    Bug(String),
}

pub fn run_case(case: &Case) -> Verdict {
    let mut boundary_msgs = Vec::new();
    for attempt in 0..ATTEMPTS {
        let seed = case
            .seed
            .wrapping_add(attempt.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let xs = inputs(case, seed);
        match evaluate(case, &xs, seed) {
            Ok(()) => return Verdict::Pass { moved: attempt },
            Err(e) => {
                if near_boundary(case, &xs, seed) {
                    eprintln!("{}: inputs (seed {seed:#x}) within {NEAR:e} of a branch boundary ({e}); moving them", case.name);
                    boundary_msgs.push(e);
                    continue;
                }
                return Verdict::Bug(format!(
                    "{}: {e}\n  (persists when the inputs move by up to {NEAR:e}; input seed {seed:#x}; inputs {xs:?})",
                    case.name
                ));
            }
        }
    }
    Verdict::Bug(format!(
        "{}: every one of {ATTEMPTS} input seeds was near a branch boundary (suspicious): {boundary_msgs:?}",
        case.name
    ))
}

/// Runs a group of cases and panics naming every failing kernel, with its source.
pub fn run_group(cases: &[Case]) {
    let start = std::time::Instant::now();
    let mut bugs = Vec::new();
    let mut moved = 0;
    for case in cases {
        match run_case(case) {
            Verdict::Pass { moved: m } => moved += m,
            Verdict::Bug(msg) => {
                let funcs: String = case
                    .funcs
                    .iter()
                    .map(|&f| format!("{}\n", super::FUNC_SRC[f]))
                    .collect();
                bugs.push(format!(
                    "{msg}\n---- source of {} ----\n{funcs}{}",
                    case.name, case.src
                ))
            }
        }
    }
    eprintln!(
        "{} kernels ({}..{}): {} passed, {} failed, {moved} input moves away from boundaries, {} kernel runs, {:.3} s",
        cases.len(),
        cases.first().map_or("", |c| c.name),
        cases.last().map_or("", |c| c.name),
        cases.len() - bugs.len(),
        bugs.len(),
        RUNS.load(std::sync::atomic::Ordering::Relaxed),
        start.elapsed().as_secs_f64()
    );
    if !bugs.is_empty() {
        panic!(
            "{} of {} kernels fail their gradient check:\n\n{}",
            bugs.len(),
            cases.len(),
            bugs.join("\n\n")
        );
    }
}
