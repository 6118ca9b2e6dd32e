//! `mpm [--n-grid 128] [--steps 1024] [--iters 5] [--serial-below N] [--python PATH]`: DiffTaichi's walker
//! (`WalkerTask`, f32): the seconds per optimization iteration (a checkpointed rollout
//! forward and backward), the median of `--iters` after one warm-up, on 1 thread and on 2,
//! and the forward rollout alone. With `--python` (a venv's python with `taichi==1.7.4`),
//! `bench/peers/taichi_mpm.py` on the same scene in the same run (its median after two
//! compiling iterations), then the ratios. One JSON line each.

use std::time::Instant;

use adflex_kernels::mpm::{scenes, WalkerTask};
use adflex_runtime::prelude::*;
use serde_json::json;

use crate::arg;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Median seconds of `f` over `reps` runs after one warm-up.
fn time(reps: usize, mut f: impl FnMut()) -> f64 {
    f();
    median(
        (0..reps.max(1))
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

pub fn main(rest: &[String]) {
    let n_grid = arg(rest, "--n-grid").unwrap_or(128);
    let steps = arg(rest, "--steps").unwrap_or(1024);
    let iters = arg(rest, "--iters").unwrap_or(5);
    if let Some(n) = arg(rest, "--serial-below") {
        let mut s = adflex_runtime::settings::settings();
        s.serial_below = n;
        s.apply();
    }
    let task = WalkerTask::<f32>::new(n_grid, steps, 1e-3);
    let forward = with_threads(2, || {
        time(iters, || {
            let mut s = task.mpm.state();
            for t in 0..steps {
                let mut tape = Tape::new();
                s = task.step(&mut tape, &s, t).expect("the walker steps").0;
            }
        })
    });
    let mut ours = Vec::new();
    for threads in [1, 2] {
        let s = with_threads(threads, || {
            time(iters, || {
                task.loss_and_grad().expect("the walker's gradient");
            })
        });
        ours.push(s);
        println!(
            "{}",
            json!({"peer": "adflex", "n_grid": n_grid, "particles": task.mpm.particle_count(),
                "steps": steps, "threads": threads, "s_per_iter": s})
        );
    }
    println!(
        "{}",
        json!({"peer": "adflex", "case": "forward rollout only", "threads": 2, "s": forward})
    );
    println!(
        "{}",
        json!({"ratio": "adflex iteration, 2 threads / 1 thread", "value": ours[1] / ours[0]})
    );
    let Some(python) = rest
        .iter()
        .position(|a| a == "--python")
        .and_then(|k| rest.get(k + 1))
    else {
        return;
    };
    for threads in [1, 2] {
        let args = [
            "--n-grid".to_string(),
            n_grid.to_string(),
            "--steps".into(),
            steps.to_string(),
            "--iters".into(),
            (iters + 2).to_string(),
            "--threads".into(),
            threads.to_string(),
        ];
        let Some(v) = crate::peer_json(python, "taichi_mpm.py", &args) else {
            return;
        };
        let s = v["s_per_iter"].as_f64().unwrap_or(f64::NAN);
        println!(
            "{}",
            json!({"peer": v["peer"], "n_grid": n_grid, "particles": v["particles"],
                "steps": steps, "threads": threads, "s_per_iter": s})
        );
        println!(
            "{}",
            json!({"ratio": format!("adflex / Taichi (ti.cpu) per iteration, {threads} thread(s)"),
                "value": ours[threads - 1] / s})
        );
    }
}

/// `snow [--n-grid 128] [--steps 200] [--iters 5] [--python PATH]`: Taichi's `mpm99` scene
/// (fluid, jelly and snow, [`scenes::mpm99`], f32, `dt = 1e-4`): the seconds per forward step
/// on 1 and 2 threads (the median of `--iters` rollouts of `--steps` steps after one), and per
/// step of a rollout on one tape with its backward pass (gradients of every particle's
/// moduli, yield strains and hardening, and of the initial state). With `--python` (a venv
/// with `taichi==1.7.4`), `kernels/tests/references/taichi_mpm99.py --bench`: mpm99 itself
/// (`ti.svd`, f32) on the same scene, forward only (Taichi's SVD has no derivative), then the
/// ratios. One JSON line each.
pub fn snow(rest: &[String]) {
    let n_grid = arg(rest, "--n-grid").unwrap_or(128);
    let steps = arg(rest, "--steps").unwrap_or(200);
    let iters = arg(rest, "--iters").unwrap_or(5);
    let mpm = scenes::mpm99(n_grid)
        .finalize::<f32>()
        .expect("the mpm99 scene builds");
    let n = mpm.particle_count();
    let mut forward = Vec::new();
    for threads in [1, 2] {
        let s = with_threads(threads, || {
            time(iters, || {
                let mut s = mpm.state();
                for _ in 0..steps {
                    s = mpm
                        .step(&mut Tape::new(), &s, None, 1e-4)
                        .expect("mpm99 steps");
                }
            })
        }) / steps as f64;
        forward.push(s);
        let backward = with_threads(threads, || {
            time(iters, || {
                for a in [
                    &mpm.mu,
                    &mpm.lambda,
                    &mpm.compression,
                    &mpm.stretch,
                    &mpm.hardening,
                ] {
                    let _ = a.clone().requires_grad();
                    a.zero_grad();
                }
                let s0 = mpm.state();
                let _ = s0.v.clone().requires_grad();
                let mut tape = Tape::new();
                let mut s = s0.clone();
                for _ in 0..steps {
                    s = mpm.step(&mut tape, &s, None, 1e-4).expect("mpm99 steps");
                }
                let c = mpm.mean_position(&mut tape, &s);
                tape.backward(&c).expect("mpm99's gradient");
            })
        }) / steps as f64;
        println!(
            "{}",
            json!({"peer": "adflex", "case": "mpm99", "n_grid": n_grid, "particles": n,
                "threads": threads, "s_per_step": s, "forward_backward_s_per_step": backward})
        );
    }
    let Some(python) = rest
        .iter()
        .position(|a| a == "--python")
        .and_then(|k| rest.get(k + 1))
    else {
        return;
    };
    for threads in [1, 2] {
        let args = [
            "--bench".to_string(),
            "--n-grid".into(),
            n_grid.to_string(),
            "--steps".into(),
            steps.to_string(),
            "--threads".into(),
            threads.to_string(),
        ];
        let script = "../../kernels/tests/references/taichi_mpm99.py";
        let Some(v) = crate::peer_json(python, script, &args) else {
            return;
        };
        println!("{v}");
        let s = v["s_per_step"].as_f64().unwrap_or(f64::NAN);
        println!(
            "{}",
            json!({"ratio": format!("adflex / Taichi (ti.cpu) per mpm99 step, {threads} thread(s)"),
                "value": forward[threads - 1] / s})
        );
    }
}
