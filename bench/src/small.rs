//! Launch-bound scenes: the cage of the demos (27 particles, 26 springs, f64), 2,000 steps of
//! semi-implicit Euler on a tape and a backward pass; the time per gradient and per launch.

use std::time::Instant;

use adflex_kernels::losses;
use adflex_kernels::scenes::cage::{self, Cage};
use adflex_kernels::Integrator;
use adflex_kernels::SemiImplicitEuler;
use adflex_runtime::prelude::*;

/// `small [--steps 2000] [--reps 7]`: best-of-`reps` times of the cage gradient, one JSON line.
pub fn main(steps: usize, reps: usize) {
    let scene = cage::build::<f64>(Cage::default());
    let model = &scene.model;
    let rest = model.param::<f64>("springs", "rest").expect("springs");
    let _ = rest.clone().requires_grad();
    let (mut fwd, mut total, mut launches) = (f64::INFINITY, f64::INFINITY, 0);
    for _ in 0..reps {
        rest.zero_grad();
        let t0 = Instant::now();
        let mut tape = Tape::new();
        let end = SemiImplicitEuler
            .rollout(model, &mut tape, &model.state(), None, 1e-3, steps)
            .expect("stable");
        let loss = Array::zeros(1);
        losses::distance_to_target(
            &mut tape,
            &end.x,
            &[scene.center],
            Vec3::zeros(),
            1.0,
            &loss,
        );
        let t1 = Instant::now();
        tape.backward(&loss).expect("a gradient");
        let t2 = Instant::now();
        launches = tape.len();
        fwd = fwd.min((t1 - t0).as_secs_f64());
        total = total.min((t2 - t0).as_secs_f64());
    }
    println!(
        "{{\"scene\": \"cage\", \"steps\": {steps}, \"launches\": {launches}, \"forward_ms\": {:.3}, \
         \"gradient_ms\": {:.3}, \"us_per_forward_launch\": {:.3}, \"us_per_adjoint_launch\": {:.3}}}",
        1e3 * fwd,
        1e3 * total,
        1e6 * fwd / launches as f64,
        1e6 * (total - fwd) / launches as f64
    );
}

/// `out[t] = sum over 10,000 iterations of a[k % 4] * w[t]`: the adjoint scatters 10,000
/// contributions per thread into a 4-element gradient.
#[adflex_macros::diff_kernel]
pub fn loop_reads(a: &Array<f32>, w: &Array<f32>, out: &Array<f32>) {
    let t = tid();
    let mut s = 0.0;
    for k in 0..10000 {
        s += a[k % 4] * w[t];
    }
    out[t] = s;
}

/// `adjoint-memory [--threads K]`: the loop kernel over 8,192 threads, forward and adjoint on
/// a tape; time and the process's peak RSS, one JSON line (run once per thread count: the
/// peak is per process).
pub fn adjoint_memory(threads: usize) {
    let n = 8192;
    let a = Array::from_vec(vec![0.5f32, -0.25, 1.0, 2.0]).requires_grad();
    let w = Array::from_vec((0..n).map(|i| (i % 17) as f32 * 0.01).collect::<Vec<_>>());
    let out = Array::<f32>::zeros(n);
    let base = crate::timing::peak_rss_mb();
    let t0 = Instant::now();
    adflex_runtime::with_threads(threads, || {
        let mut tape = Tape::new();
        tape.launch(loop_reads, n, (&a, &w, &out));
        tape.backward(&out).expect("a gradient");
    });
    println!(
        "{{\"case\": \"adjoint-memory\", \"threads\": {threads}, \"dim\": {n}, \"iterations\": 10000, \
         \"seconds\": {:.3}, \"peak_rss_mb\": {:.1}, \"rss_before_mb\": {base:.1}, \"grad\": {:?}}}",
        t0.elapsed().as_secs_f64(),
        crate::timing::peak_rss_mb(),
        a.grad().expect("grad").to_vec()
    );
}
