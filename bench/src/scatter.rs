//! `scatter`: how to make `atomic_add` deterministic, measured (issue 3).
//!
//! A spring-like scatter: `M = 2 P` contributions of `Vec3<f32>` from `P` springs on a square
//! grid of `N` particles (`P ~ 2N`, so `M ~ 4N`) into `N` targets, with every strategy zeroing
//! the target first and computing the same `d = x[i] - x[j]`:
//!
//! - `runtime`: a real `#[diff_kernel]` launch (per-chunk logs applied in chunk order when the
//!   launch is parallel; a direct serial loop on one thread or below `SERIAL_BELOW`);
//! - `logs (hand)`: the runtime's algorithm written by hand, without the kernel machinery;
//! - `dense (hand)`: per-chunk dense partial sums over the window of targets the chunk
//!   touched (accumulated in a per-worker scratch of length N, then copied out), reduced in
//!   chunk order by target range in parallel;
//! - `CAS atomics`: compare-and-swap on the f32 bits (not deterministic; the usual baseline);
//! - `serial`: a plain loop.

use std::cell::RefCell;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::launch::{CHUNK, SERIAL_BELOW};
use adflex_runtime::prelude::*;
use rayon::prelude::*;

use crate::timing::{fmt_s, interleaved, Case};

/// The force of an undamped spring of stiffness 50 and rest length 0.01 (the arithmetic of a
/// cloth spring: a length, a division, a product).
#[diff_func]
fn force(xij: Vec3) -> Vec3 {
    let l = length(xij);
    xij * (50.0 * (l - 0.01) / l)
}

#[inline(always)]
fn force_h(xij: Vec3) -> Vec3 {
    let l = xij.norm();
    xij * (50.0 * (l - 0.01) / l)
}

#[diff_kernel]
fn spring_scatter(x: &Array<Vec3>, pairs: &Array<[u32; 2]>, f: &Array<Vec3>) {
    let t = tid();
    let [i, j] = pairs[t];
    let d = force(x[i] - x[j]);
    f.atomic_sub(i, d);
    f.atomic_add(j, d);
}

/// Springs of an `s x s` grid (right and down neighbours) and positions: `(N, x, pairs)`.
pub fn grid(s: usize) -> (usize, Vec<Vec3>, Vec<[u32; 2]>) {
    let n = s * s;
    let h = 1.0 / (s.max(2) - 1) as f32;
    let x: Vec<Vec3> = (0..n)
        .map(|p| {
            let (a, b) = ((p / s) as f32, (p % s) as f32);
            Vec3::new(a * h, 0.1 * (0.37 * a + 0.11 * b).sin(), b * h)
        })
        .collect();
    let mut pairs = Vec::with_capacity(2 * n);
    for a in 0..s {
        for b in 0..s {
            let p = (a * s + b) as u32;
            if b + 1 < s {
                pairs.push([p, p + 1]);
            }
            if a + 1 < s {
                pairs.push([p, p + s as u32]);
            }
        }
    }
    (n, x, pairs)
}

#[derive(Clone, Copy)]
struct SyncPtr(*mut Vec3);
unsafe impl Send for SyncPtr {}
unsafe impl Sync for SyncPtr {}

impl SyncPtr {
    /// The pointer (a method, so that closures capture the whole `Sync` wrapper).
    fn get(self) -> *mut Vec3 {
        self.0
    }
}

fn zero() -> Vec3 {
    Vec3::zeros()
}

/// The plain serial loop.
pub fn serial(x: &[Vec3], pairs: &[[u32; 2]], f: &mut [Vec3]) {
    f.fill(zero());
    for &[i, j] in pairs {
        let (i, j) = (i as usize, j as usize);
        let d = force_h(x[i] - x[j]);
        f[i] -= d;
        f[j] += d;
    }
}

/// The runtime's strategy by hand: per-chunk logs, applied in chunk order (by target range
/// in parallel when there are at least 2^16 entries).
pub fn logs(x: &[Vec3], pairs: &[[u32; 2]], f: &mut [Vec3], chunk: usize) {
    f.fill(zero());
    let logs: Vec<Vec<(u32, Vec3)>> = pairs
        .par_chunks(chunk)
        .map(|c| {
            let mut log = Vec::new();
            for &[i, j] in c {
                let d = force_h(x[i as usize] - x[j as usize]);
                log.push((i, -d));
                log.push((j, d));
            }
            log
        })
        .collect();
    let entries: usize = logs.iter().map(Vec::len).sum();
    let parts = if entries < 1 << 16 {
        1
    } else {
        rayon::current_num_threads()
    };
    let len = f.len();
    let step = len.div_ceil(parts).max(1);
    let p = SyncPtr(f.as_mut_ptr());
    (0..parts).into_par_iter().for_each(|k| {
        let (lo, hi) = (k * step, ((k + 1) * step).min(len));
        for log in &logs {
            for &(i, v) in log {
                let i = i as usize;
                if lo <= i && i < hi {
                    // SAFETY: parts write disjoint ranges of f.
                    unsafe { *p.get().add(i) += v }
                }
            }
        }
    });
}

/// [`logs`] with the log buffers kept from one launch to the next (no allocation, no page
/// faults once warm): isolates what the fresh allocations of the runtime's logs cost.
pub fn logs_reused(
    x: &[Vec3],
    pairs: &[[u32; 2]],
    f: &mut [Vec3],
    chunk: usize,
    pool: &mut Vec<Vec<(u32, Vec3)>>,
) {
    f.fill(zero());
    let nchunks = pairs.len().div_ceil(chunk);
    pool.resize_with(nchunks, Vec::new);
    pool.par_iter_mut()
        .zip(pairs.par_chunks(chunk))
        .for_each(|(log, c)| {
            log.clear();
            for &[i, j] in c {
                let d = force_h(x[i as usize] - x[j as usize]);
                log.push((i, -d));
                log.push((j, d));
            }
        });
    let logs = &*pool;
    let entries: usize = logs.iter().map(Vec::len).sum();
    let parts = if entries < 1 << 16 {
        1
    } else {
        rayon::current_num_threads()
    };
    let len = f.len();
    let step = len.div_ceil(parts).max(1);
    let p = SyncPtr(f.as_mut_ptr());
    (0..parts).into_par_iter().for_each(|k| {
        let (lo, hi) = (k * step, ((k + 1) * step).min(len));
        for log in logs {
            for &(i, v) in log {
                let i = i as usize;
                if lo <= i && i < hi {
                    // SAFETY: parts write disjoint ranges of f.
                    unsafe { *p.get().add(i) += v }
                }
            }
        }
    });
}

thread_local! {
    static SCRATCH: RefCell<Vec<Vec3>> = const { RefCell::new(Vec::new()) };
}

/// Per-chunk dense partial sums over the touched window, reduced in chunk order. `pool` keeps
/// the window buffers from one launch to the next (as a runtime would keep them per worker).
pub fn dense(
    x: &[Vec3],
    pairs: &[[u32; 2]],
    f: &mut [Vec3],
    chunk: usize,
    pool: &mut Vec<(usize, Vec<Vec3>)>,
) {
    let n = f.len();
    pool.resize_with(pairs.len().div_ceil(chunk), || (0, Vec::new()));
    pool.par_iter_mut()
        .zip(pairs.par_chunks(chunk))
        .for_each(|((base, win), c)| {
            SCRATCH.with(|s| {
                let mut s = s.borrow_mut();
                if s.len() < n {
                    s.resize(n, zero());
                }
                let (mut lo, mut hi) = (usize::MAX, 0);
                for &[i, j] in c {
                    let (i, j) = (i as usize, j as usize);
                    let d = force_h(x[i] - x[j]);
                    s[i] -= d;
                    s[j] += d;
                    lo = lo.min(i.min(j));
                    hi = hi.max(i.max(j));
                }
                win.clear();
                *base = 0;
                if lo <= hi {
                    *base = lo;
                    win.extend_from_slice(&s[lo..=hi]);
                    s[lo..=hi].fill(zero());
                }
            })
        });
    let partials = &*pool;
    let total: usize = partials.iter().map(|p| p.1.len()).sum();
    let parts = if total < 1 << 15 {
        1
    } else {
        rayon::current_num_threads()
    };
    let step = n.div_ceil(parts).max(1);
    f.par_chunks_mut(step).enumerate().for_each(|(k, out)| {
        let base = k * step;
        out.fill(zero());
        for (lo, w) in partials {
            let a = base.max(*lo);
            let b = (base + out.len()).min(lo + w.len());
            for t in a..b {
                out[t - base] += w[t - lo];
            }
        }
    });
}

#[inline(always)]
fn atomic_add_f32(a: &AtomicU32, v: f32) {
    let mut old = a.load(Ordering::Relaxed);
    loop {
        let new = (f32::from_bits(old) + v).to_bits();
        match a.compare_exchange_weak(old, new, Ordering::Relaxed, Ordering::Relaxed) {
            Ok(_) => return,
            Err(x) => old = x,
        }
    }
}

/// Compare-and-swap atomics on the f32 bits (order depends on scheduling).
pub fn cas(x: &[Vec3], pairs: &[[u32; 2]], f: &mut [Vec3], chunk: usize) {
    f.fill(zero());
    // SAFETY: Vec3<f32> is three contiguous f32; AtomicU32 has the layout of u32/f32.
    let fa: &[AtomicU32] =
        unsafe { std::slice::from_raw_parts(f.as_mut_ptr() as *const AtomicU32, 3 * f.len()) };
    pairs.par_chunks(chunk).for_each(|c| {
        for &[i, j] in c {
            let (i, j) = (i as usize, j as usize);
            let d = force_h(x[i] - x[j]);
            for k in 0..3 {
                atomic_add_f32(&fa[3 * i + k], -d[k]);
                atomic_add_f32(&fa[3 * j + k], d[k]);
            }
        }
    });
}

/// Minor page faults of this process so far (field 10 of /proc/self/stat).
pub fn minor_faults() -> u64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            let after = s.rsplit_once(')')?.1.to_string();
            after.split_whitespace().nth(7)?.parse().ok()
        })
        .unwrap_or(0)
}

fn max_rel_diff(a: &[Vec3], b: &[Vec3]) -> f64 {
    let scale = a.iter().map(|v| v.norm()).fold(0.0f32, f32::max).max(1e-30);
    a.iter()
        .zip(b)
        .map(|(p, q)| ((p - q).norm() / scale) as f64)
        .fold(0.0, f64::max)
}

/// One row of the strategy table.
pub struct StrategyRow {
    pub n: usize,
    pub m: usize,
    pub threads: usize,
    /// seconds per scatter: runtime, logs (hand), logs reused (hand), dense (hand), CAS, serial
    pub s: [f64; 6],
    /// minor page faults per scatter, same order
    pub faults: [f64; 6],
}

/// Runs the strategy comparison at grid sides `sides` with 1 and 2 threads.
pub fn strategies(sides: &[usize], rounds: usize, batch: Duration) -> Vec<StrategyRow> {
    let mut rows = Vec::new();
    for &s in sides {
        let (n, x, pairs) = grid(s);
        let xa = Array::from_vec(x.clone()).named("x");
        let pa = Array::from_vec(pairs.clone()).named("pairs");
        let fa = Array::<Vec3>::zeros(n).named("f");
        for threads in [1, 2] {
            let row = with_threads(threads, || {
                // Correctness first: the same sums (bitwise for the ordered ones).
                let mut reference = vec![zero(); n];
                serial(&x, &pairs, &mut reference);
                fa.fill(zero());
                launch(spring_scatter, pairs.len(), (&xa, &pa, &fa));
                let rt = fa.to_vec();
                let mut out = vec![zero(); n];
                logs(&x, &pairs, &mut out, CHUNK);
                assert!(out == reference, "hand logs differ from serial");
                assert!(rt == reference, "runtime scatter differs from serial");
                let mut dpool = Vec::new();
                dense(&x, &pairs, &mut out, CHUNK, &mut dpool);
                assert!(max_rel_diff(&out, &reference) < 1e-5, "dense differs");
                cas(&x, &pairs, &mut out, CHUNK);
                assert!(max_rel_diff(&out, &reference) < 1e-5, "cas differs");

                let mut pool = Vec::new();
                logs_reused(&x, &pairs, &mut out, CHUNK, &mut pool);
                assert!(out == reference, "hand logs (reused) differ from serial");
                let (mut f1, mut f2, mut f3, mut f4, mut f5) =
                    (out.clone(), out.clone(), out.clone(), out.clone(), out);
                let mut cases = vec![
                    Case::new("runtime", || {
                        fa.fill(zero());
                        launch(spring_scatter, pairs.len(), (&xa, &pa, &fa));
                    }),
                    Case::new("logs", || logs(&x, &pairs, &mut f1, CHUNK)),
                    Case::new("logs reused", || {
                        logs_reused(&x, &pairs, &mut f5, CHUNK, &mut pool)
                    }),
                    Case::new("dense", || dense(&x, &pairs, &mut f2, CHUNK, &mut dpool)),
                    Case::new("cas", || cas(&x, &pairs, &mut f3, CHUNK)),
                    Case::new("serial", || serial(&x, &pairs, &mut f4)),
                ];
                let t = interleaved(&mut cases, rounds, batch);
                let mut faults = [0.0; 6];
                for (k, c) in cases.iter_mut().enumerate() {
                    let f0 = minor_faults();
                    for _ in 0..10 {
                        (c.f)();
                    }
                    faults[k] = (minor_faults() - f0) as f64 / 10.0;
                }
                StrategyRow {
                    n,
                    m: 2 * pairs.len(),
                    threads,
                    s: [t[0], t[1], t[2], t[3], t[4], t[5]],
                    faults,
                }
            });
            eprintln!(
                "N={} M={} threads={}: {} (page faults per call {:?})",
                row.n,
                row.m,
                row.threads,
                row.s
                    .iter()
                    .map(|&s| fmt_s(s))
                    .collect::<Vec<_>>()
                    .join(" | "),
                row.faults
            );
            rows.push(row);
        }
    }
    rows
}

/// One row of the serial-threshold table.
pub struct ThresholdRow {
    pub dim: usize,
    /// runtime launch, 1 thread (direct serial)
    pub rt1: f64,
    /// runtime launch, 2 threads (serial below SERIAL_BELOW, logged chunks above)
    pub rt2: f64,
    /// plain serial loop (no launch)
    pub plain: f64,
    /// hand parallel logs on 2 threads, chunk = min(CHUNK, dim/2): the parallel path forced
    pub par2: f64,
    /// hand dense windows (buffers reused) on 2 threads, same chunks
    pub dense2: f64,
}

/// Launch overhead at small dims: serial against forced-parallel.
pub fn threshold(dims: &[usize], rounds: usize, batch: Duration) -> Vec<ThresholdRow> {
    let mut rows = Vec::new();
    for &dim in dims {
        let s = ((dim as f64 / 2.0).sqrt().ceil() as usize + 1).max(2);
        let (n, x, mut pairs) = grid(s);
        pairs.truncate(dim);
        assert_eq!(pairs.len(), dim);
        let xa = Array::from_vec(x.clone()).named("x");
        let pa = Array::from_vec(pairs.clone()).named("pairs");
        let fa = Array::<Vec3>::zeros(n).named("f");
        let run = |threads: usize, which: usize| {
            with_threads(threads, || {
                let mut out = vec![zero(); n];
                let mut pool = Vec::new();
                let chunk = CHUNK.min(dim.div_ceil(2)).max(1);
                let mut cases = vec![match which {
                    0 => Case::new("rt", || {
                        fa.fill(zero());
                        launch(spring_scatter, pairs.len(), (&xa, &pa, &fa));
                    }),
                    1 => Case::new("plain", || serial(&x, &pairs, &mut out)),
                    2 => Case::new("par", || logs(&x, &pairs, &mut out, chunk)),
                    _ => Case::new("dense", || dense(&x, &pairs, &mut out, chunk, &mut pool)),
                }];
                interleaved(&mut cases, rounds, batch)[0]
            })
        };
        let row = ThresholdRow {
            dim,
            rt1: run(1, 0),
            rt2: run(2, 0),
            plain: run(1, 1),
            par2: run(2, 2),
            dense2: run(2, 3),
        };
        eprintln!(
            "dim={dim}: runtime 1t {} 2t {} plain {} forced parallel 2t {} dense 2t {}",
            fmt_s(row.rt1),
            fmt_s(row.rt2),
            fmt_s(row.plain),
            fmt_s(row.par2),
            fmt_s(row.dense2)
        );
        rows.push(row);
    }
    rows
}

/// Runs both measurements and prints markdown tables.
pub fn main(quick: bool) {
    let (rounds, batch) = if quick {
        (2, Duration::from_millis(20))
    } else {
        (7, Duration::from_millis(60))
    };
    let sides: &[usize] = if quick { &[64, 256] } else { &[64, 256, 512] };
    println!("machine: {}", crate::timing::machine());
    println!("date: {}", crate::timing::today());
    println!("load average at start: {}", crate::timing::loadavg());
    println!("CHUNK = {CHUNK}, SERIAL_BELOW = {SERIAL_BELOW}\n");
    let rows = strategies(sides, rounds, batch);
    println!("| N targets | M contributions | threads | (a) runtime launch | logs by hand | logs by hand, buffers reused | (b) dense per chunk, buffers reused | (c) CAS atomics | (d) serial loop |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for r in &rows {
        println!(
            "| {} | {} | {} | {} |",
            r.n,
            r.m,
            r.threads,
            r.s.iter()
                .map(|&s| fmt_s(s))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    println!("\nminor page faults per scatter (same columns):\n");
    for r in &rows {
        println!(
            "| {} | {} | {} | {} |",
            r.n,
            r.m,
            r.threads,
            r.faults
                .iter()
                .map(|f| format!("{f:.0}"))
                .collect::<Vec<_>>()
                .join(" | ")
        );
    }
    let rows = threshold(&[64, 256, 1024, 4096, 16384, 65536], rounds, batch);
    println!("\n| dim (springs) | runtime, 1 thread | runtime, 2 threads | plain loop, no launch | logs by hand, forced parallel, 2 threads | dense by hand, forced parallel, 2 threads |");
    println!("|---:|---:|---:|---:|---:|---:|");
    for r in &rows {
        println!(
            "| {} | {} | {} | {} | {} | {} |",
            r.dim,
            fmt_s(r.rt1),
            fmt_s(r.rt2),
            fmt_s(r.plain),
            fmt_s(r.par2),
            fmt_s(r.dense2)
        );
    }
}
