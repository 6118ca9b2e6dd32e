//! Scatters above the serial threshold, and small launches of costly ids, give the same bits
//! for 1 or 2 threads and across runs, forward and adjoint.

mod common;

use adflex_runtime::launch::SERIAL_BELOW;
use adflex_runtime::prelude::*;
use common::{random, GatherScatter};

const DIM: usize = 100_000;

fn bits(v: Vec<f64>) -> Vec<u64> {
    v.into_iter().map(f64::to_bits).collect()
}

/// One forward and one adjoint launch; returns (out, x.grad) bits.
fn run(threads: usize) -> (Vec<u64>, Vec<u64>) {
    let x = Array::from_vec(random(1000, 11, -3.0, 3.0)).named("x");
    let idx = Array::from_vec(
        random(DIM, 12, 0.0, 1000.0)
            .into_iter()
            .map(|v| v as u32)
            .collect(),
    );
    let out = Array::<f64>::zeros(7).named("out");
    with_threads(threads, || {
        launch(GatherScatter, DIM, (&x, &idx, &out));
        x.ensure_grad();
        out.ensure_grad().assign(&random(7, 13, -1.0, 1.0));
        launch_adjoint(GatherScatter, DIM, (&x, &idx, &out));
    });
    (bits(out.to_vec()), bits(x.grad().unwrap().to_vec()))
}

/// The same through a tape (forward launch recorded, then backward).
fn run_tape(threads: usize) -> (Vec<u64>, Vec<u64>) {
    let x = Array::from_vec(random(1000, 14, -3.0, 3.0))
        .requires_grad()
        .named("x");
    let idx = Array::from_vec((0..DIM as u32).map(|i| (i * 7919) % 1000).collect());
    let out = Array::<f64>::zeros(7).named("out");
    with_threads(threads, || {
        let mut tape = Tape::new();
        tape.launch(GatherScatter, DIM, (&x, &idx, &out));
        tape.backward(&out).unwrap();
    });
    (bits(out.to_vec()), bits(x.grad().unwrap().to_vec()))
}

#[test]
fn scatter_is_deterministic() {
    const { assert!(DIM > SERIAL_BELOW) };
    let one = run(1);
    let two = run(2);
    let again = run(2);
    assert_eq!(one.0, two.0, "forward, 1 vs 2 threads");
    assert_eq!(one.1, two.1, "adjoint, 1 vs 2 threads");
    assert_eq!(two, again, "two runs");
    assert!(one.1.iter().any(|&b| f64::from_bits(b) != 0.0));

    let one = run_tape(1);
    let two = run_tape(2);
    assert_eq!(one, two, "tape, 1 vs 2 threads");
    assert_eq!(two, run_tape(2), "tape, two runs");
}

#[test]
fn summation_order_matters_here() {
    // Guard against a vacuous test: summing the same terms in another order changes the bits.
    let x = random(1000, 11, -3.0, 3.0);
    let idx: Vec<usize> = random(DIM, 12, 0.0, 1000.0)
        .into_iter()
        .map(|v| v as usize)
        .collect();
    let mut fwd = [0.0f64; 7];
    let mut rev = [0.0f64; 7];
    for i in 0..DIM {
        fwd[i % 7] += x[idx[i]] * x[idx[i]];
    }
    for i in (0..DIM).rev() {
        rev[i % 7] += x[idx[i]] * x[idx[i]];
    }
    assert_ne!(bits(fwd.to_vec()), bits(rev.to_vec()));
    let (out, _) = run(2);
    assert_eq!(out, bits(fwd.to_vec()), "thread-id order");
}

/// `out[t] = sum over 200 iterations of a[k % 4] * w[t]`: every thread reads a 4-element
/// array 200 times, so the adjoint scatters 200 contributions per thread into `a.grad`, more
/// than a chunk's log holds before it is applied early.
#[adflex_macros::diff_kernel]
fn loop_reads(a: &Array<f64>, w: &Array<f64>, out: &Array<f64>) {
    let t = tid();
    let mut s = 0.0;
    for k in 0..200 {
        s += a[k % 4] * w[t] * (1.0 + 0.001 * (k as f64));
    }
    out[t] = s;
}

fn loop_grads(threads: usize) -> Vec<u64> {
    let n = 16_384;
    let a = Array::from_vec(vec![0.3, -1.1, 2.0, 0.7]).requires_grad();
    let w = Array::from_vec(random(n, 21, -1.0, 1.0));
    let out = Array::<f64>::zeros(n);
    with_threads(threads, || {
        let mut tape = Tape::new();
        tape.launch(loop_reads, n, (&a, &w, &out));
        tape.backward(&out).unwrap();
    });
    bits(a.grad().unwrap().to_vec())
}

#[test]
fn logs_applied_early_keep_the_bits() {
    let one = loop_grads(1);
    assert_eq!(one, loop_grads(2), "1 vs 2 threads");
    assert_eq!(one, loop_grads(3), "1 vs 3 threads");
    assert!(one.iter().all(|&b| f64::from_bits(b) != 0.0));
}

#[test]
fn empty_and_tiny_launches_run_on_any_pool() {
    for threads in [1, 2] {
        with_threads(threads, || {
            let a = Array::from_vec(vec![1.0f64; 4]);
            let w = Array::<f64>::zeros(0);
            let out = Array::<f64>::zeros(0);
            launch(loop_reads, 0, (&a, &w, &out));
            let w = Array::from_vec(vec![1.0f64]);
            let out = Array::<f64>::zeros(1);
            launch(loop_reads, 1, (&a, &w, &out));
            assert!(out.get(0) != 0.0);
        });
    }
}

/// Like `loop_reads`, but thread 5 reads out of bounds.
#[adflex_macros::diff_kernel]
fn loop_reads_then_fails(a: &Array<f64>, w: &Array<f64>, out: &Array<f64>) {
    let t = tid();
    let mut s = 0.0;
    for k in 0..200 {
        s += a[k % 4] * w[t];
    }
    let bad = select(t == 5, 1000, 0);
    out[t] = s + a[bad];
}

#[test]
fn a_panicking_chunk_fails_the_launch_with_its_own_message_and_no_deadlock() {
    let n = 16_384;
    let a = Array::from_vec(vec![0.3, -1.1, 2.0, 0.7]).requires_grad();
    let w = Array::from_vec(random(n, 22, -1.0, 1.0));
    let out = Array::<f64>::zeros(n);
    for threads in [2, 3] {
        let err = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            with_threads(threads, || {
                let mut tape = Tape::new();
                tape.launch(loop_reads_then_fails, n, (&a, &w, &out));
            })
        }))
        .unwrap_err();
        let msg = err
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| err.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default();
        assert!(
            msg.contains("out of bounds") && msg.contains("1000"),
            "{threads} threads: {msg}"
        );
        // The adjoint: later chunks fill their logs of `a.grad` and wait for their turn to
        // apply them early while chunk 0 panics.
        out.ensure_grad().fill(1.0);
        let err = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            with_threads(threads, || {
                launch_adjoint(loop_reads_then_fails, n, (&a, &w, &out))
            })
        }))
        .unwrap_err();
        let msg = err.downcast_ref::<String>().cloned().unwrap_or_default();
        assert!(
            msg.contains("out of bounds"),
            "adjoint, {threads} threads: {msg}"
        );
    }
}

/// Chunk 0 is slow (300 iterations per thread, the others 1): while it runs, the other workers
/// finish and deposit every later chunk, more than may wait unapplied, so they also wait.
#[adflex_macros::diff_kernel]
fn slow_first_chunk(x: &Array<f64>, out: &Array<f64>) {
    let t = tid();
    let mut s = x[t % 1000];
    let n = if t < 2048 { 300 } else { 1 };
    for _k in 0..n {
        s = s * 0.999 + 0.001 * s * s;
    }
    out.atomic_add(t % 7, s);
}

fn slow_first_chunk_bits(threads: usize) -> (Vec<u64>, Vec<u64>) {
    let x = Array::from_vec(random(1000, 31, -1.0, 1.0)).requires_grad();
    let out = Array::<f64>::zeros(7);
    with_threads(threads, || {
        let mut tape = Tape::new();
        tape.launch(slow_first_chunk, 40 * 2048, (&x, &out));
        tape.backward(&out).unwrap();
    });
    (bits(out.to_vec()), bits(x.grad().unwrap().to_vec()))
}

#[test]
fn chunks_deposited_behind_a_slow_one_keep_the_bits() {
    let one = slow_first_chunk_bits(1);
    assert_eq!(one, slow_first_chunk_bits(2), "1 vs 2 threads");
    assert_eq!(one, slow_first_chunk_bits(3), "1 vs 3 threads");
    assert!(one.1.iter().any(|&b| f64::from_bits(b) != 0.0));
}

/// Costly ids in a small launch (400 ids of 2,000 iterations each, below the serial
/// threshold): after its first serial launches it is timed on the pool too, in 16 chunks.
#[adflex_macros::diff_kernel]
fn costly_ids(x: &Array<f64>, out: &Array<f64>) {
    let t = tid();
    let mut s = x[t];
    for _k in 0..2000 {
        s = s * 0.999 + 0.001 * sin(s);
    }
    out.atomic_add(t % 5, s);
}

fn costly_ids_bits(threads: usize) -> (Vec<u64>, Vec<u64>) {
    const { assert!(400 < SERIAL_BELOW) };
    let x = Array::from_vec(random(400, 41, -1.0, 1.0)).requires_grad();
    let out = Array::<f64>::zeros(5);
    with_threads(threads, || {
        let mut tape = Tape::new();
        for _ in 0..8 {
            tape.launch(costly_ids, 400, (&x, &out));
        }
        tape.backward(&out).unwrap();
    });
    (bits(out.to_vec()), bits(x.grad().unwrap().to_vec()))
}

#[test]
fn small_launches_of_costly_ids_keep_the_bits() {
    let one = costly_ids_bits(1);
    for threads in [2, 3, 2] {
        assert_eq!(one, costly_ids_bits(threads), "1 vs {threads} threads");
    }
    assert!(one.1.iter().all(|&b| f64::from_bits(b) != 0.0));
}
