//! `bound [--n 128]`: the memory-bandwidth bound of one cloth step. Measures the machine's
//! streaming bandwidth (a STREAM-like triad `a = b + s c` over 3 x 128 MB of f32, 1 and 2
//! threads, best of 5) and counts the compulsory traffic of one step of the `cloth` scene (each
//! array a launch touches read once, written once, accumulated arrays read and written), and
//! the flops by operation counts of the kernels' formulas; one JSON line.

use std::time::Instant;

use adflex_kernels::scenes::cloth;
use rayon::prelude::*;
use serde_json::json;

fn triad(threads: usize) -> f64 {
    let n = 32 << 20; // 32 M f32 = 128 MB per array
    let b = vec![1.0f32; n];
    let c = vec![2.0f32; n];
    let mut a = vec![0.0f32; n];
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a pool");
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t0 = Instant::now();
        pool.install(|| {
            a.par_chunks_mut(1 << 16)
                .zip(b.par_chunks(1 << 16).zip(c.par_chunks(1 << 16)))
                .for_each(|(a, (b, c))| {
                    for k in 0..a.len() {
                        a[k] = b[k] + 3.0 * c[k];
                    }
                });
        });
        best = best.min(t0.elapsed().as_secs_f64());
    }
    std::hint::black_box(&a);
    // Read b and c, write a (and read it for ownership: counted as STREAM does, 3 arrays).
    3.0 * (n * 4) as f64 / best / 1e9
}

/// Bytes and flops of one forward step of the cloth scene at `n` (f32).
pub fn step_traffic(n: usize) -> (f64, f64, usize, usize, usize) {
    let scene = cloth::build::<f32>(n);
    let m = &scene.model;
    let p = m.particle_count;
    let s = m.springs().map_or(0, |s| s.rest.len());
    let b = m.bending().map_or(0, |b| b.quads.len());
    let v3 = 12.0;
    let (p_, s_, b_) = (p as f64, s as f64, b as f64);
    // springs: x, v read; pairs (8), rest, ke (4 each) read; f accumulated (read + write).
    let springs = 2.0 * p_ * v3 + s_ * 16.0 + 2.0 * p_ * v3;
    // bending: x, v read; quads (16), rest, ke, kd (4 each); f accumulated.
    let bending = 2.0 * p_ * v3 + b_ * 28.0 + 2.0 * p_ * v3;
    // ground: x, v read; f accumulated.
    let ground = 2.0 * p_ * v3 + 2.0 * p_ * v3;
    // zeroing f; integrate: x, v, f, inverse mass read, x', v' written.
    let integrate = p_ * v3 + 3.0 * p_ * v3 + p_ * 4.0 + 2.0 * p_ * v3;
    let bytes = springs + bending + ground + integrate;
    // flops per element by operation count of the formulas (sqrt and division as one).
    let flops = s_ * 40.0 + b_ * 260.0 + p_ * 35.0 + p_ * 15.0;
    (bytes, flops, p, s, b)
}

pub fn main(n: usize) {
    let (bw1, bw2) = (triad(1), triad(2));
    let (bytes, flops, p, s, b) = step_traffic(n);
    println!(
        "{}",
        json!({
            "n": n,
            "particles": p,
            "springs": s,
            "bending": b,
            "forward_bytes_per_step": bytes,
            "forward_flops_per_step": flops,
            "triad_gb_s_1_thread": bw1,
            "triad_gb_s_2_threads": bw2,
            "forward_bound_ms_per_step_1_thread": 1e3 * bytes / (bw1 * 1e9),
            "forward_bound_ms_per_step_2_threads": 1e3 * bytes / (bw2 * 1e9),
            "machine": crate::timing::machine(),
            "load": crate::timing::loadavg(),
        })
    );
}
