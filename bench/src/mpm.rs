//! `mpm [--n-grid 128] [--steps 1024] [--iters 5] [--serial-below N] [--python PATH]`: DiffTaichi's walker
//! (`WalkerTask`, f32): the seconds per optimization iteration (a checkpointed rollout
//! forward and backward), the median of `--iters` after one warm-up, on 1 thread and on 2,
//! and the forward rollout alone. With `--python` (a venv's python with `taichi==1.7.4`),
//! `bench/peers/taichi_mpm.py` on the same scene in the same run (its median after two
//! compiling iterations), then the ratios. One JSON line each.

use std::time::Instant;

use adflex_kernels::mpm::WalkerTask;
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
