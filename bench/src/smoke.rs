//! `smoke [--n 110] [--steps 100] [--iters 3] [--jacobi 30] [--python PATH]`: the smoke-control
//! task (`SmokeTask`, f64) per optimization iteration (a rollout on a tape and its backward
//! pass), with the pressure by CG and its implicit adjoint and by `--jacobi` unrolled Jacobi
//! iterations, on 2 threads. With `--python` (a venv's python with `taichi==1.7.4` and
//! `jax==0.10.2`), `bench/peers/taichi_smoke.py` (Jacobi) and `bench/peers/jax_smoke.py` (CG
//! and Jacobi) on the same task in the same run, the largest relative difference between
//! their losses and ours over the iterations, and the ratios. One JSON line each.

use std::time::Instant;

use adflex_kernels::fluid::scenes::SmokeTask;
use adflex_kernels::fluid::Pressure;
use serde_json::{json, Value};

use crate::arg;

/// Losses of `iters + 1` iterations of normalized gradient descent (step 1), and the median
/// seconds per iteration after the first.
fn ours(n: usize, steps: usize, iters: usize, pressure: Pressure) -> (Vec<f64>, f64) {
    let task = SmokeTask::new(n, steps, pressure).expect("an even grid");
    let mut losses = Vec::new();
    let mut times = Vec::new();
    for _ in 0..=iters {
        let t = Instant::now();
        losses.push(task.loss_and_grad().expect("the smoke's gradient"));
        times.push(t.elapsed().as_secs_f64());
        task.descend(1.0).expect("gradients");
    }
    let mut steady = times[1..].to_vec();
    steady.sort_by(f64::total_cmp);
    (losses, steady[steady.len() / 2])
}

pub fn main(rest: &[String]) {
    let n = arg(rest, "--n").unwrap_or(110);
    let steps = arg(rest, "--steps").unwrap_or(100);
    let iters = arg(rest, "--iters").unwrap_or(3).max(1);
    let k = arg(rest, "--jacobi").unwrap_or(30);
    let mut mine = Vec::new();
    for (name, pressure) in [("cg", Pressure::cg()), ("jacobi", Pressure::Jacobi(k))] {
        let (losses, s) = ours(n, steps, iters, pressure);
        let label = if name == "cg" {
            "cg".to_string()
        } else {
            format!("jacobi {k}")
        };
        println!(
            "{}",
            json!({"peer": "adflex", "n": n, "steps": steps, "pressure": label, "losses": losses,
                "s_per_iter": s})
        );
        mine.push((label, losses, s));
    }
    let Some(python) = rest
        .iter()
        .position(|a| a == "--python")
        .and_then(|k| rest.get(k + 1))
    else {
        return;
    };
    let common = [
        "--n".to_string(),
        n.to_string(),
        "--steps".into(),
        steps.to_string(),
        "--iters".into(),
        (iters + 1).to_string(),
        "--jacobi".into(),
        k.to_string(),
    ];
    let runs: [(&str, &[&str]); 3] = [
        ("taichi_smoke.py", &[]),
        ("jax_smoke.py", &["--pressure", "cg"]),
        ("jax_smoke.py", &["--pressure", "jacobi"]),
    ];
    for (script, extra) in runs {
        let args: Vec<String> = common
            .iter()
            .cloned()
            .chain(extra.iter().map(|e| e.to_string()))
            .collect();
        let Some(v) = crate::peer_json(python, script, &args) else {
            continue;
        };
        println!("{v}");
        let label = v["pressure"].as_str().unwrap_or("").to_string();
        let Some((_, losses, s)) = mine.iter().find(|m| m.0 == label) else {
            continue;
        };
        let theirs: Vec<f64> = v["losses"]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default();
        let worst = losses
            .iter()
            .zip(&theirs)
            .map(|(a, b)| (a - b).abs() / b.abs())
            .fold(0.0, f64::max);
        println!(
            "{}",
            json!({"ratio": format!("adflex / {} per iteration, pressure {label}", v["peer"]),
                "value": s / v["s_per_iter"].as_f64().unwrap_or(f64::NAN),
                "largest relative loss difference": worst})
        );
    }
}
