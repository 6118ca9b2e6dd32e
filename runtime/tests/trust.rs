//! Paths that once gave a wrong answer with no error, or stopped the program: each is now right
//! or refused with an error naming what is wrong.

mod common;

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::mpsc;
use std::time::Duration;

use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::gradcheck;
use adflex_runtime::prelude::*;

fn panic_message(r: Result<(), Box<dyn std::any::Any + Send>>) -> String {
    let e = r.expect_err("expected a panic");
    e.downcast_ref::<String>()
        .cloned()
        .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
        .unwrap_or_default()
}

// ---- repeated stores: only the last store of an element receives its gradient ---------------

#[diff_kernel]
fn double_store(x: &Array<f64>, y: &Array<f64>) {
    let t = tid();
    y[t] = x[t] * 5.0;
    y[t] = x[t] * x[t];
}

#[diff_kernel]
fn store_in_loop(x: &Array<f64>, n: usize, y: &Array<f64>) {
    let t = tid();
    let mut s = 1.0;
    for k in 0..n {
        s = s * x[t * n + k];
        y[t] = s;
    }
}

#[diff_kernel]
fn store_in_branch(x: &Array<f64>, y: &Array<f64>) {
    let t = tid();
    y[t] = x[t] * 3.0;
    if x[t] > 0.0 {
        y[t] = x[t] * x[t] * x[t];
    }
}

/// Stores at an index the macro cannot prove is the thread's own (`2 t + 1`), twice.
#[diff_kernel]
fn store_strided(x: &Array<f64>, y: &Array<f64>) {
    let t = tid();
    let i = 2 * t + 1;
    y[i] = x[t] * 7.0;
    y[i] = sin(x[t]);
}

#[diff_kernel]
fn total(y: &Array<f64>, loss: &Array<f64>) {
    loss.atomic_add(0, y[tid()]);
}

#[diff_kernel]
fn sum_sq(y: &Array<f64>, loss: &Array<f64>) {
    let v = y[tid()];
    loss.atomic_add(0, v * v);
}

#[diff_kernel]
fn scale(x: &Array<f64>, s: f64, y: &Array<f64>) {
    let t = tid();
    y[t] = x[t] * s;
}

#[test]
fn repeated_store_in_one_thread_gives_the_last_store_the_gradient() {
    let x = Array::from_vec(vec![3.0f64]).requires_grad();
    let (y, loss) = (Array::zeros(1), Array::zeros(1));
    let mut tape = Tape::new();
    tape.launch(double_store, 1, (&x, &y));
    tape.launch(total, 1, (&y, &loss));
    tape.backward(&loss).unwrap();
    assert_eq!(y.get(0), 9.0);
    assert_eq!(x.grad().unwrap().get(0), 6.0); // 11 before: 5 from the overwritten store
}

#[test]
fn store_in_a_loop_gets_the_gradient_of_its_last_iteration() {
    let x = Array::from_vec(vec![1.0f64, 2.0, 3.0]).requires_grad();
    let (y, loss) = (Array::zeros(1), Array::zeros(1));
    let mut tape = Tape::new();
    tape.launch(store_in_loop, 1, (&x, 3usize, &y));
    tape.launch(total, 1, (&y, &loss));
    tape.backward(&loss).unwrap();
    assert_eq!(x.grad().unwrap().to_vec(), vec![6.0, 3.0, 2.0]); // [9, 4, 2] before
}

#[test]
fn repeated_stores_match_finite_differences() {
    let x = Array::from_vec(vec![0.7f64, -1.3, 2.1, 0.4, -0.2, 1.1]).named("x");
    let (n, m) = (x.len(), 2);
    let xs = x.clone();
    gradcheck(
        |tape| {
            let y = Array::zeros(n);
            let y2 = Array::zeros(n);
            let y3 = Array::zeros(n / m);
            let y4 = Array::zeros(2 * n + 1);
            let loss = Array::zeros(1);
            tape.launch(double_store, n, (&xs, &y));
            tape.launch(store_in_branch, n, (&xs, &y2));
            tape.launch(store_in_loop, n / m, (&xs, m, &y3));
            tape.launch(store_strided, n, (&xs, &y4));
            for a in [&y, &y2, &y3, &y4] {
                tape.launch(sum_sq, a.len(), (a, &loss));
            }
            loss
        },
        &[&x],
    )
    .unwrap()
    .assert_within(1e-7);
}

#[test]
fn a_launch_that_overwrites_an_array_cuts_the_gradient_of_the_earlier_writer() {
    let x = Array::from_vec(vec![1.0f64, 2.0]).requires_grad();
    let c = Array::from_vec(vec![10.0f64, 20.0]).requires_grad();
    let (y, loss) = (Array::zeros(2), Array::zeros(1));
    let mut tape = Tape::new();
    tape.launch(scale, 2, (&x, 2.0, &y));
    tape.launch(scale, 2, (&c, 3.0, &y)); // overwrites y
    tape.launch(sum_sq, 2, (&y, &loss));
    tape.backward(&loss).unwrap();
    assert_eq!(x.grad().unwrap().to_vec(), vec![0.0, 0.0]); // [120, 240] before
    assert_eq!(c.grad().unwrap().to_vec(), vec![180.0, 360.0]); // 2 * 3c * 3
}

#[test]
fn a_host_write_between_a_writer_and_a_reader_is_refused() {
    let x = Array::from_vec(vec![1.0f64, 2.0])
        .requires_grad()
        .named("x");
    let y = Array::zeros(2).named("y");
    let loss = Array::zeros(1).named("loss");
    let mut tape = Tape::new();
    tape.launch(scale, 2, (&x, 2.0, &y));
    y.set(0, 100.0); // the tape cannot see this
    tape.launch(sum_sq, 2, (&y, &loss));
    let err = tape.backward(&loss).unwrap_err();
    assert!(matches!(err, Error::WrittenOffTape { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("`y`") && msg.contains("scale") && msg.contains("sum_sq"),
        "{msg}"
    );
    assert_eq!(x.grad().unwrap().to_vec(), vec![0.0, 0.0]); // nothing ran
}

#[diff_kernel]
fn add_scaled(x: &Array<f64>, s: f64, f: &Array<f64>) {
    let t = tid();
    f.atomic_add(t, x[t] * s);
}

/// Forces accumulated by a launch whose adjoint runs, then by one that reads only constants
/// (its adjoint is skipped): the reader of the sum is on the chain, not written off the tape.
#[test]
fn an_accumulation_by_a_constant_launch_is_not_an_off_tape_write() {
    let x = Array::from_vec(vec![1.0f64, 2.0])
        .requires_grad()
        .named("x");
    let c = Array::from_vec(vec![5.0f64, 6.0]).named("c");
    let f = Array::zeros(2).named("f");
    let loss = Array::zeros(1).named("loss");
    let mut tape = Tape::new();
    tape.launch(add_scaled, 2, (&x, 2.0, &f));
    tape.launch(add_scaled, 2, (&c, 1.0, &f));
    tape.launch(sum_sq, 2, (&f, &loss));
    tape.backward(&loss).unwrap();
    // loss = sum (2 x + c)^2: d/dx = 4 (2 x + c).
    assert_eq!(x.grad().unwrap().to_vec(), vec![28.0, 40.0]);

    // A host write after the constant launch still cuts the running writer's path.
    x.zero_grad();
    let (f, loss) = (Array::zeros(2).named("f"), Array::zeros(1).named("loss"));
    let mut tape = Tape::new();
    tape.launch(add_scaled, 2, (&x, 2.0, &f));
    f.set(1, 0.0);
    tape.launch(add_scaled, 2, (&c, 1.0, &f));
    tape.launch(sum_sq, 2, (&f, &loss));
    let err = tape.backward(&loss).unwrap_err();
    assert!(matches!(err, Error::WrittenOffTape { .. }), "{err}");
}

// ---- backward that reaches nothing -------------------------------------------------------

#[test]
fn backward_that_reaches_no_parameter_is_an_error() {
    let x = Array::from_vec(vec![1.0f64, 2.0]).named("x"); // no requires_grad
    let (y, loss) = (Array::zeros(2), Array::zeros(1).named("loss"));
    let mut tape = Tape::new();
    tape.launch(scale, 2, (&x, 2.0, &y));
    tape.launch(sum_sq, 2, (&y, &loss));
    let err = tape.backward(&loss).unwrap_err();
    assert!(matches!(err, Error::NothingToDifferentiate { .. }), "{err}");
    assert!(err.to_string().contains("`loss`"), "{err}");

    // The loss computed on another tape than the parameters' launches.
    let p = Array::from_vec(vec![1.0f64, 2.0]).requires_grad();
    let (q, loss2) = (Array::zeros(2), Array::zeros(1));
    let mut first = Tape::new();
    first.launch(scale, 2, (&p, 2.0, &q));
    let mut second = Tape::new();
    second.launch(sum_sq, 2, (&q, &loss2));
    let err = second.backward(&loss2).unwrap_err();
    assert!(matches!(err, Error::NothingToDifferentiate { .. }), "{err}");
}

// ---- deadlocks and re-entrance -----------------------------------------------------------

#[diff_kernel]
fn copy(src: &Array<f64>, dst: &Array<f64>) {
    let t = tid();
    dst[t] = src[t];
}

#[test]
fn opposite_copies_from_two_threads_do_not_deadlock() {
    let a = Array::from_vec(vec![1.0f64; 64]);
    let b = Array::from_vec(vec![2.0f64; 64]);
    let (tx, rx) = mpsc::channel();
    for k in 0..2 {
        let (a, b, tx) = (a.clone(), b.clone(), tx.clone());
        std::thread::spawn(move || {
            for _ in 0..2000 {
                if k == 0 {
                    launch(copy, 64, (&a, &b));
                } else {
                    launch(copy, 64, (&b, &a));
                }
            }
            tx.send(()).unwrap();
        });
    }
    for _ in 0..2 {
        rx.recv_timeout(Duration::from_secs(60))
            .expect("two threads copying a -> b and b -> a deadlocked");
    }
}

#[test]
fn reentrant_access_inside_modify_is_an_error_not_a_deadlock() {
    let y = Array::from_vec(vec![1.0f64, 2.0]).named("y");
    let msg = panic_message(catch_unwind(AssertUnwindSafe(|| {
        y.modify(|d| d[0] = y.get(1));
    })));
    assert!(msg.contains("`y`") && msg.contains("deadlock"), "{msg}");
    // The array stays usable.
    y.set(0, 5.0);
    assert_eq!(y.to_vec(), vec![5.0, 2.0]);
}

#[test]
fn a_launch_inside_modify_of_its_array_is_an_error_and_leaves_the_thread_clean() {
    let x = Array::from_vec(vec![1.0f64, 2.0]).named("x");
    let idx = Array::from_vec(vec![1u32, 0]).named("idx");
    let y = Array::<f64>::zeros(2).named("y");
    // Reading `x` in a launch while this thread writes it in `modify`: refused by name.
    let msg = panic_message(catch_unwind(AssertUnwindSafe(|| {
        x.modify(|_| launch(gather, 2, (&x, &idx, &y)));
    })));
    assert!(msg.contains("`x`") && msg.contains("deadlock"), "{msg}");
    // A launch on other arrays inside `modify` runs; afterwards every lock is released.
    let other = Array::from_vec(vec![0.0f64; 2]);
    other.modify(|_| launch(gather, 2, (&x, &idx, &y)));
    assert_eq!(y.to_vec(), vec![2.0, 1.0]);
    x.modify(|d| d[0] = 3.0);
    launch(gather, 2, (&x, &idx, &y));
    assert_eq!(y.to_vec(), vec![2.0, 3.0]);
}

// ---- a kernel that panics leaves usable arrays --------------------------------------------

#[diff_kernel]
fn gather(x: &Array<f64>, idx: &Array<u32>, y: &Array<f64>) {
    let t = tid();
    y[t] = x[idx[t]];
}

#[test]
fn arrays_stay_usable_after_a_kernel_panics() {
    let x = Array::from_vec(vec![1.0f64, 2.0]).named("x");
    let idx = Array::from_vec(vec![0u32, 7]).named("idx");
    let y = Array::zeros(2).named("y");
    let before = y.version();
    let msg = panic_message(catch_unwind(AssertUnwindSafe(|| {
        launch(gather, 2, (&x, &idx, &y));
    })));
    assert!(msg.contains("index 7 out of bounds"), "{msg}");
    // No PoisonError: every later use works, and the half-written array has a new version
    // (a tape that recorded a read of it refuses to differentiate through it).
    assert!(y.version() > before);
    assert_eq!(y.to_vec()[0], 1.0);
    idx.set(1, 1);
    launch(gather, 2, (&x, &idx, &y));
    assert_eq!(y.to_vec(), vec![1.0, 2.0]);
}

// ---- stores from several threads to one element ------------------------------------------

#[diff_kernel]
fn store_to_zero(x: &Array<f64>, y: &Array<f64>) {
    let t = tid();
    y[0] = x[t];
}

#[diff_kernel]
fn reverse(x: &Array<f64>, n: usize, y: &Array<f64>) {
    let t = tid();
    y[n - 1 - t] = x[t];
}

#[test]
fn two_threads_storing_to_one_element_is_refused() {
    for n in [4usize, 20_000] {
        let x = Array::from_vec(vec![1.0f64; n]);
        let y = Array::zeros(1).named("y");
        let msg = panic_message(catch_unwind(AssertUnwindSafe(|| {
            launch(store_to_zero, n, (&x, &y));
        })));
        assert!(
            msg.contains("store_to_zero") && msg.contains("`y`") && msg.contains("index 0"),
            "{msg}"
        );
    }
}

#[test]
fn a_scatter_claimed_at_the_thread_id_that_is_not_is_refused() {
    // A hand-written kernel whose view claims every index is the thread id, scattering at 0:
    // a parallel chunk not starting at 0 panics instead of racing.
    let n = 20_000;
    let x = Array::from_vec(vec![1.0f64; n]);
    let loss = Array::zeros(1).named("loss");
    let msg = panic_message(catch_unwind(AssertUnwindSafe(|| {
        with_threads(2, || {
            for _ in 0..4 {
                launch(common::MisclaimedScatter, n, (&x, &loss));
            }
        })
    })));
    assert!(
        msg.contains("misclaimed")
            && msg.contains("`loss`")
            && msg.contains("outside the thread ids"),
        "{msg}"
    );
}

#[test]
fn stores_at_distinct_computed_indices_run_in_parallel() {
    let n = 20_000;
    let x = Array::from_vec((0..n).map(|i| i as f64).collect());
    let y = Array::zeros(n);
    for threads in [1, 2] {
        with_threads(threads, || launch(reverse, n, (&x, n, &y)));
        assert_eq!(y.get(0), (n - 1) as f64);
        assert_eq!(y.get(n - 1), 0.0);
    }
}

// ---- small things ---------------------------------------------------------------------------

#[test]
fn with_threads_refuses_absurd_pools_at_once() {
    let start = std::time::Instant::now();
    let msg = panic_message(catch_unwind(|| {
        with_threads(10_000, || ());
    }));
    assert!(
        msg.contains("10000") && msg.contains("between 1 and"),
        "{msg}"
    );
    assert!(start.elapsed() < Duration::from_secs(2));
    let msg = panic_message(catch_unwind(|| {
        with_threads(0, || ());
    }));
    assert!(msg.contains("between 1 and"), "{msg}");
}

#[test]
fn array_passed_twice_message_is_clean() {
    let y = Array::zeros(2).named("y");
    let msg = panic_message(catch_unwind(AssertUnwindSafe(|| {
        launch(copy, 2, (&y, &y));
    })));
    assert!(msg.contains("passed as both `src` and `dst`"), "{msg}");
    assert!(!msg.contains("  "), "a run of spaces: {msg:?}");
}

#[test]
fn retain_grad_keeps_the_gradient_of_an_intermediate_final_value() {
    let x = Array::from_vec(vec![1.0f64, 2.0]).requires_grad();
    let c = Array::from_vec(vec![10.0f64, 20.0]).requires_grad();
    let (y, loss) = (Array::zeros(2), Array::zeros(1));
    let mut tape = Tape::new();
    tape.launch(scale, 2, (&x, 2.0, &y));
    tape.launch(scale, 2, (&c, 3.0, &y));
    tape.launch(sum_sq, 2, (&y, &loss));
    tape.retain_grad(&y);
    tape.backward(&loss).unwrap();
    // dloss/dy = 2 y (y = 3c), and still no gradient for x (its store was overwritten).
    assert_eq!(y.grad().unwrap().to_vec(), vec![60.0, 120.0]);
    assert_eq!(x.grad().unwrap().to_vec(), vec![0.0, 0.0]);
    assert_eq!(c.grad().unwrap().to_vec(), vec![180.0, 360.0]);
}

#[diff_kernel]
fn fill_const(c: f64, y: &Array<f64>) {
    let t = tid();
    y[t] = c;
}

#[test]
fn an_overwrite_from_constants_cuts_the_gradient_too() {
    // The second writer depends on nothing differentiable, so its adjoint has nothing to
    // compute, but it must still take the gradient of what it overwrote.
    let x = Array::from_vec(vec![1.0f64, 2.0]).requires_grad();
    let (y, loss) = (Array::zeros(2), Array::zeros(1));
    let mut tape = Tape::new();
    tape.launch(scale, 2, (&x, 2.0, &y));
    tape.launch(fill_const, 2, (0.5, &y));
    tape.launch(sum_sq, 2, (&y, &loss));
    // Reaches x only through y's overwritten values: nothing to differentiate... except that
    // the loss does not depend on x at all; x.grad must be zero, not 2 * 2 * 0.5 * 2.
    match tape.backward(&loss) {
        Ok(()) => assert_eq!(x.grad().unwrap().to_vec(), vec![0.0, 0.0]),
        Err(e) => assert!(matches!(e, Error::NothingToDifferentiate { .. }), "{e}"),
    }
}
