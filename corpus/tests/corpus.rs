//! The generated corpus (see corpus/build.rs and corpus/gen.rs): a few hundred random kernels
//! built from the builtins and the control flow of the kernel language, each checked in f64
//! (adjoint against central differences, tangent against adjoint) and run in f32.
#![allow(dead_code, unused_parens, clippy::all)]

mod support;

use adflex::prelude::*;
use support::{arrays_f32, arrays_f64, check, relaunch_err, run_direct, run_group, Case, Outcome};

include!(concat!(env!("OUT_DIR"), "/corpus.rs"));
include!(concat!(env!("OUT_DIR"), "/corpus_tests.rs"));

// ---- the checker itself: it must report a wrong derivative and step off a kink ------------

/// `x * x` with a wrong adjoint (`3 x` instead of `2 x`) and a consistent tangent: the kind of
/// bug the corpus is for.
#[diff_func(adjoint = wrong_square_adjoint, tangent = wrong_square_tangent)]
fn wrong_square<R: Real>(x: R) -> R {
    x * x
}

fn wrong_square_adjoint<R: Real>(x: R, adj: R) -> (R,) {
    (adj * x * R::lit(3.0),)
}

fn wrong_square_tangent<R: Real>(x: R, dx: R) -> R {
    dx * x * R::lit(3.0)
}

#[diff_kernel]
fn meta_wrong<R: Real>(x0: &Array<R>, x1: &Array<R>, n: usize, y: &Array<R>) {
    let t = tid();
    y[t] = wrong_square(x0[t]) + x1[(t + 1) % n];
}

fn run_meta_wrong(xs: &[Vec<f64>], seed: u64) -> Outcome {
    let a = arrays_f64(xs);
    let y: Array<f64> = Array::zeros(LEN);
    let checked = check(&[&a[0], &a[1]], &[&y], seed, &|m| {
        run_direct(m, meta_wrong, LEN, (&a[0], &a[1], LEN, &y))
    });
    let y64: Array<f64> = Array::zeros(LEN);
    run_direct(Mode::Forward, meta_wrong, LEN, (&a[0], &a[1], LEN, &y64));
    let b = arrays_f32(xs);
    let y32: Array<f32> = Array::zeros(LEN);
    run_direct(Mode::Forward, meta_wrong, LEN, (&b[0], &b[1], LEN, &y32));
    Outcome {
        checked,
        relaunch_err: 0.0,
        y64: y64.to_vec(),
        y32: y32.to_vec(),
    }
}

#[test]
fn checker_reports_a_wrong_derivative() {
    let case = Case {
        name: "meta_wrong",
        inputs: 2,
        seed: 5,
        run: run_meta_wrong,
        src: "",
        funcs: &[],
    };
    match support::run_case(&case) {
        support::Verdict::Bug(msg) => {
            assert!(msg.contains("adjoint vs central differences"), "{msg}")
        }
        support::Verdict::Pass { .. } => panic!("a wrong adjoint passed the check"),
    }
}

/// `max(x0 - c, 0)`: a kink at `x0 == c`.
#[diff_kernel]
fn meta_kink<R: Real>(x0: &Array<R>, x1: &Array<R>, c: R, y: &Array<R>) {
    let t = tid();
    y[t] = max(x0[t] - c, 0.0) + x1[t] * x0[t];
}

const KINK_SEED: u64 = 9;

/// Puts the kink exactly at `x0[0]` of the first inputs the driver draws for `KINK_SEED`.
fn kink_at() -> f64 {
    support::Rng(KINK_SEED | 1).uniform(support::LO, support::HI)
}

fn run_meta_kink(xs: &[Vec<f64>], seed: u64) -> Outcome {
    let c = kink_at();
    let a = arrays_f64(xs);
    let y: Array<f64> = Array::zeros(LEN);
    let checked = check(&[&a[0], &a[1]], &[&y], seed, &|m| {
        run_direct(m, meta_kink, LEN, (&a[0], &a[1], c, &y))
    });
    let y64: Array<f64> = Array::zeros(LEN);
    run_direct(Mode::Forward, meta_kink, LEN, (&a[0], &a[1], c, &y64));
    let b = arrays_f32(xs);
    let y32: Array<f32> = Array::zeros(LEN);
    run_direct(
        Mode::Forward,
        meta_kink,
        LEN,
        (&b[0], &b[1], c as f32, &y32),
    );
    Outcome {
        checked,
        relaunch_err: 0.0,
        y64: y64.to_vec(),
        y32: y32.to_vec(),
    }
}

#[test]
fn checker_moves_inputs_off_a_kink() {
    let case = Case {
        name: "meta_kink",
        inputs: 2,
        seed: KINK_SEED,
        run: run_meta_kink,
        src: "",
        funcs: &[],
    };
    match support::run_case(&case) {
        support::Verdict::Pass { moved } => {
            assert_eq!(moved, 1, "the first inputs sit on the kink")
        }
        support::Verdict::Bug(msg) => panic!("a kink was reported as a bug: {msg}"),
    }
}

/// A store overwritten by a later launch (or a later store) must not receive the gradient of
/// the element: the two-launch check catches an adjoint that reads the gradient of a store
/// without taking it (the bug the first corpus missed, because it never stored twice).
#[diff_kernel]
fn meta_store<R: Real>(x0: &Array<R>, x1: &Array<R>, n: usize, y: &Array<R>) {
    let t = tid();
    y[t] = x0[t] * x1[(t + 1) % n];
}

#[test]
fn relaunch_check_catches_an_adjoint_that_keeps_the_gradient_of_a_store() {
    let xs = [
        vec![0.7, 1.1, 0.9, 1.3, 0.6, 1.2],
        vec![1.4, 0.8, 1.0, 0.5, 1.25, 0.95],
    ];
    assert_eq!(xs[0].len(), LEN);
    let moved: Vec<Vec<f64>> = xs
        .iter()
        .map(|v| v.iter().rev().map(|x| 2.0 - x).collect())
        .collect();
    let right = |m: Mode, xs: &[Array<f64>], y: &Array<f64>| {
        run_direct(m, meta_store, LEN, (&xs[0], &xs[1], LEN, y))
    };
    // The old adjoint: `adj_v += y.grad[i]` without zeroing it.
    let keeps = |m: Mode, xs: &[Array<f64>], y: &Array<f64>| {
        let before = y.grad_buffer().map(|g| g.to_vec());
        right(m, xs, y);
        if let (Mode::Adjoint, Some(g)) = (m, before) {
            y.grad().unwrap().assign(&g);
        }
    };
    let ok = relaunch_err(&arrays_f64(&xs), &arrays_f64(&moved), 7, &right);
    assert!(ok <= support::TOL, "{ok:e}");
    let bad = relaunch_err(&arrays_f64(&xs), &arrays_f64(&moved), 7, &keeps);
    assert!(bad > 1e-2, "the check cannot tell: {bad:e}");
}
