//! Launches whose scatters index through index arrays alone run as a static split (one range
//! per worker, logging only what an earlier range also touches): the bits are a serial
//! launch's in forward, adjoint and tangent mode, for any thread count, for index arrays in
//! mesh order (the split) or in random order (the chunked launch), and after the index
//! arrays change.

mod common;

use std::sync::{Mutex, MutexGuard, PoisonError};

use adflex_runtime::__test::split_launches;
use adflex_runtime::prelude::*;
use common::{grid_pairs, random, shuffled};

/// The count of split launches is the process's: tests that read it run one at a time.
fn alone() -> MutexGuard<'static, ()> {
    static ONE: Mutex<()> = Mutex::new(());
    ONE.lock().unwrap_or_else(PoisonError::into_inner)
}

/// A pair force with a branch: some pairs add to `i`, every pair subtracts from `j`.
#[adflex_macros::diff_kernel]
fn pair_forces(x: &Array<f64>, pairs: &Array<[u32; 2]>, k: &Array<f64>, f: &Array<f64>) {
    let t = tid();
    let [i, j] = pairs[t];
    let d = (x[j] - x[i]) * k[t];
    if d > 0.0 {
        f.atomic_add(i, d * d);
    }
    f.atomic_sub(j, d * x[i]);
}

/// Values over many scales: a different order of additions gives other bits.
fn wide(n: usize) -> Vec<f64> {
    random(n, 1, -1.0, 1.0)
        .into_iter()
        .zip(random(n, 2, -6.0, 6.0))
        .map(|(a, e)| a * 10f64.powf(e))
        .collect()
}

fn bits(a: &Array<f64>) -> Vec<u64> {
    a.to_vec().into_iter().map(f64::to_bits).collect()
}

/// Panics naming the first element where `a` and `b` differ.
fn same_bits(a: &[u64], b: &[u64], what: &str) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = a.iter().zip(b).position(|(x, y)| x != y) {
        let (x, y) = (f64::from_bits(a[i]), f64::from_bits(b[i]));
        panic!("{what}: first difference at element {i}: {x:e} vs {y:e}");
    }
}

/// Forward, adjoint (through a tape) and tangent of `pair_forces` on `threads` threads:
/// the bits of `f`, of `x.grad` and of `f`'s tangent.
fn run(threads: usize, pairs: &[[u32; 2]]) -> [Vec<u64>; 3] {
    let n = pairs.iter().flatten().max().map_or(0, |&m| m as usize + 1);
    let x = Array::from_vec(wide(n)).requires_grad().named("x");
    let pairs = Array::from_vec(pairs.to_vec()).named("pairs");
    let k = Array::from_vec(random(pairs.len(), 3, 0.5, 2.0)).named("k");
    let f = Array::<f64>::zeros(n).named("f");
    with_threads(threads, || {
        let mut tape = Tape::new();
        tape.launch(pair_forces, pairs.len(), (&x, &pairs, &k, &f));
        f.ensure_grad().assign(&random(n, 4, -1.0, 1.0));
        tape.backward_with(&[&f]).unwrap();
        let fwd = bits(&f);
        x.set_tangent(Some(Array::from_vec(random(n, 5, -1.0, 1.0))));
        let tf = f.ensure_tangent();
        launch_tangent(pair_forces, pairs.len(), (&x, &pairs, &k, &f));
        [fwd, bits(&x.grad().unwrap()), bits(&tf)]
    })
}

#[test]
fn mesh_ordered_scatters_split_with_the_serial_bits() {
    let _alone = alone();
    let pairs = grid_pairs(150);
    let one = run(1, &pairs);
    assert!(one
        .iter()
        .all(|b| b.iter().any(|&v| f64::from_bits(v) != 0.0)));
    for threads in [2, 3, 4] {
        let before = split_launches();
        let many = run(threads, &pairs);
        assert!(
            split_launches() >= before + 3,
            "{threads} threads: forward, adjoint and tangent ran split"
        );
        for (mode, (a, b)) in ["forward", "adjoint", "tangent"]
            .iter()
            .zip(one.iter().zip(&many))
        {
            same_bits(a, b, &format!("{mode}, 1 vs {threads} threads"));
        }
    }
}

#[test]
fn summation_order_matters_in_this_test() {
    // The check above could not fail if any order gave the same bits.
    let pairs = grid_pairs(150);
    let mut reversed = pairs.clone();
    reversed.reverse();
    assert_ne!(run(1, &pairs)[0], run(1, &reversed)[0]);
}

#[test]
fn randomly_ordered_scatters_keep_the_serial_bits() {
    let _alone = alone();
    let pairs = shuffled(grid_pairs(100));
    let one = run(1, &pairs);
    for threads in [2, 3] {
        let many = run(threads, &pairs);
        for (mode, (a, b)) in ["forward", "adjoint", "tangent"]
            .iter()
            .zip(one.iter().zip(&many))
        {
            same_bits(a, b, &format!("{mode}, 1 vs {threads} threads"));
        }
    }
}

#[test]
fn changed_index_arrays_are_planned_again() {
    let _alone = alone();
    let w = 250;
    let n = (w * w) as usize;
    let x = Array::from_vec(wide(n));
    let pairs = Array::from_vec(grid_pairs(w));
    let k = Array::from_vec(random(pairs.len(), 3, 0.5, 2.0));
    let forces = |threads: usize| {
        let f = Array::<f64>::zeros(n);
        with_threads(threads, || {
            launch(pair_forces, pairs.len(), (&x, &pairs, &k, &f))
        });
        bits(&f)
    };
    same_bits(&forces(1), &forces(2), "1 vs 2 threads");
    // Same array, new contents that still split: the pairs in reverse order. The second
    // range now starts at the middle row, which the first range touches too; the old plan
    // had the second range first to touch it, so a stale plan would write it directly,
    // ahead of the first range's additions.
    pairs.modify(|p| p.reverse());
    let before = split_launches();
    let two = forces(2);
    assert!(split_launches() > before, "the launch ran split");
    same_bits(&forces(1), &two, "1 vs 2 threads after the change");
}
