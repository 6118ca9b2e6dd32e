//! Launches flush subnormal floats to zero on every thread that runs them (serial, static
//! split, chunks; forward, adjoint, tangent), so the bits do not depend on the thread count;
//! host code keeps IEEE subnormals. (Turning the flush off is process-wide, so it is shown in
//! the doctest of `set_flush_subnormals`, not here where tests run concurrently.)

mod common;

use adflex_runtime::__test::split_launches;
use adflex_runtime::launch::{flush_subnormals, SERIAL_BELOW};
use adflex_runtime::prelude::*;
use common::{grid_pairs, random, shuffled};

#[adflex_macros::diff_kernel]
fn scale(x: &Array<f32>, s: f32, y: &Array<f32>) {
    let t = tid();
    y[t] = x[t] * s;
}

/// Products of tiny values scattered along pairs: many of them are subnormal.
#[adflex_macros::diff_kernel]
fn tiny_products(x: &Array<f32>, pairs: &Array<[u32; 2]>, f: &Array<f32>) {
    let t = tid();
    let [i, j] = pairs[t];
    let p = x[i] * x[j];
    f.atomic_add(i, p);
    f.atomic_sub(j, p * 0.5);
}

#[test]
fn launches_flush_subnormals_and_host_code_keeps_them() {
    assert!(flush_subnormals(), "on by default");
    let n = 2 * SERIAL_BELOW;
    let x = Array::from_vec(vec![1e-20f32; n]);
    let y = Array::from_vec(vec![1.0f32; n]);
    for threads in [1, 2] {
        with_threads(threads, || launch(scale, n, (&x, 1e-20, &y)));
        assert!(
            y.to_vec().iter().all(|&v| v == 0.0),
            "{threads} threads: 1e-40 is subnormal and flushed"
        );
    }
    let host = std::hint::black_box(1e-20f32) * std::hint::black_box(1e-20f32);
    assert!(host > 0.0 && host < f32::MIN_POSITIVE, "host code: {host}");
}

fn bits(a: &Array<f32>) -> Vec<u32> {
    a.to_vec().into_iter().map(f32::to_bits).collect()
}

/// Forward (on a tape), adjoint and tangent of `tiny_products` on `threads` threads.
fn run(threads: usize, pairs: &[[u32; 2]]) -> [Vec<u32>; 3] {
    let n = pairs.iter().flatten().max().map_or(0, |&m| m as usize + 1);
    // Magnitudes from 1e-25 to 1e-15: products from 1e-50 to 1e-30.
    let tiny: Vec<f32> = random(n, 1, -1.0, 1.0)
        .into_iter()
        .zip(random(n, 2, -25.0, -15.0))
        .map(|(a, e)| (a * 10f64.powf(e)) as f32)
        .collect();
    let x = Array::from_vec(tiny.clone()).requires_grad().named("x");
    let pairs = Array::from_vec(pairs.to_vec()).named("pairs");
    let f = Array::<f32>::zeros(n).named("f");
    with_threads(threads, || {
        let mut tape = Tape::new();
        tape.launch(tiny_products, pairs.len(), (&x, &pairs, &f));
        f.ensure_grad().assign(&tiny);
        tape.backward_with(&[&f]).unwrap();
        let fwd = bits(&f);
        x.set_tangent(Some(Array::from_vec(tiny.clone())));
        let tf = f.ensure_tangent();
        launch_tangent(tiny_products, pairs.len(), (&x, &pairs, &f));
        [fwd, bits(&x.grad().unwrap()), bits(&tf)]
    })
}

#[test]
fn flushed_results_have_the_same_bits_on_any_thread_count() {
    // Sizes differ per case: launches of one kernel, mode, size class and pool size share the
    // serial-or-parallel choice.
    for (shuffle, w) in [(false, 120), (true, 200)] {
        let p = match shuffle {
            false => grid_pairs(w),
            true => shuffled(grid_pairs(w)),
        };
        let one = run(1, &p);
        for (mode, b) in ["forward", "adjoint", "tangent"].iter().zip(&one) {
            let v: Vec<f32> = b.iter().map(|&u| f32::from_bits(u)).collect();
            assert!(v.iter().any(|&v| v != 0.0), "{mode}: something survives");
            assert!(
                v.iter().all(|v| *v == 0.0 || v.is_normal()),
                "{mode}: no subnormal is stored"
            );
        }
        for threads in [2, 3] {
            let before = split_launches();
            let many = run(threads, &p);
            if !shuffle {
                assert!(split_launches() > before, "mesh order runs split");
            }
            for (mode, (a, b)) in ["forward", "adjoint", "tangent"]
                .iter()
                .zip(one.iter().zip(&many))
            {
                assert_eq!(a, b, "{mode}, shuffled {shuffle}, 1 vs {threads} threads");
            }
        }
    }
}
