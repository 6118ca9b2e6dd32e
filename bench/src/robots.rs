//! `robots [--python PATH] [--newton PATH] [--steps 200] [--reps 5] [--no-grad-only MODEL [--threads N]]`: the articulation family
//! on the repository's robots (`kernels/robots/`): the time of a semi-implicit step recorded on
//! a tape (forward), of one on a `Tape::no_grad` (a rollout without derivatives), of a step's
//! forward and backward, and of the full `d qdd / d(q, qd, tau)` and `d tau / d(q, qd, qdd)`,
//! for the 7-DoF arm and the quadruped (`ant.xml`, free base and ground contact), on 1 and 2
//! threads. In the same run, with `--python`, the peers' script `bench/peers/robots.py`
//! (MuJoCo's `mj_step`, Pinocchio's `computeABADerivatives` and `computeRNEADerivatives`); with
//! `--newton` (a venv's python with `bench/peers/requirements-newton.txt`),
//! `bench/peers/newton_robots.py` (Newton's `SolverFeatherstone` on the CPU: a step on a tape,
//! and forward and backward); and the ratios. One JSON line each.

use std::collections::HashMap;
use std::process::Command;
use std::time::Instant;

use adflex_kernels::articulation::{mjcf, urdf, Articulations};
use adflex_runtime::prelude::*;

const ROBOTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../kernels/robots");

fn load(name: &str) -> Articulations<f64> {
    let b = if name == "arm7" {
        urdf::load(format!("{ROBOTS}/arm7.urdf"), &Default::default()).expect("arm7")
    } else {
        mjcf::load(format!("{ROBOTS}/ant.xml"))
            .expect("ant")
            .builder
    };
    b.finalize().expect("a valid robot")
}

/// How a rollout is timed.
#[derive(Clone, Copy, PartialEq)]
enum Pass {
    /// Steps recorded on a tape.
    Recorded,
    /// Steps on a `Tape::no_grad`.
    NoGrad,
    /// Steps recorded, then the tape's backward pass.
    Backward,
}

/// Microseconds per step: the best of `reps` rollouts of `steps` steps.
fn per_step(model: &Articulations<f64>, steps: usize, reps: usize, pass: Pass) -> f64 {
    let mut best = f64::INFINITY;
    let qd0: Vec<f64> = (0..model.n_dof)
        .map(|i| 0.1 * ((i % 5) as f64 - 2.0))
        .collect();
    for _ in 0..reps {
        let q = Array::from_vec(model.q0.clone());
        let qd = Array::from_vec(qd0.clone());
        let t0 = Instant::now();
        let mut tape = match pass {
            Pass::NoGrad => Tape::no_grad(),
            _ => Tape::new(),
        };
        let mut s = adflex_kernels::articulation::ArticulationState { q: q.clone(), qd };
        for _ in 0..steps {
            s = model.step(&mut tape, &s, None, 1e-3).expect("a step");
        }
        if pass == Pass::Backward {
            let w = vec![1.0; model.n_q];
            tape.vjp(&[&s.q], &w, &[&q]).expect("a gradient");
        }
        best = best.min(t0.elapsed().as_secs_f64());
    }
    1e6 * best / steps as f64
}

/// Microseconds per `forward_dynamics_derivatives` call (`inverse`: per
/// `inverse_dynamics_derivatives` call).
fn derivatives(model: &Articulations<f64>, reps: usize, inverse: bool) -> f64 {
    let q = model.q0.clone();
    let qd = vec![0.1; model.n_dof];
    let tau = vec![0.2; model.n_dof];
    let mut best = f64::INFINITY;
    for _ in 0..reps {
        let t0 = Instant::now();
        for _ in 0..20 {
            if inverse {
                model
                    .inverse_dynamics_derivatives(&q, &qd, &tau)
                    .expect("derivatives");
            } else {
                model
                    .forward_dynamics_derivatives(&q, &qd, &tau)
                    .expect("derivatives");
            }
        }
        best = best.min(t0.elapsed().as_secs_f64() / 20.0);
    }
    1e6 * best
}

pub fn main(rest: &[String]) {
    let arg = |name: &str| {
        rest.iter()
            .position(|a| a == name)
            .and_then(|k| rest.get(k + 1))
            .cloned()
    };
    let steps: usize = arg("--steps").and_then(|v| v.parse().ok()).unwrap_or(200);
    let reps: usize = arg("--reps").and_then(|v| v.parse().ok()).unwrap_or(5);
    // `--no-grad-only MODEL [--threads N]`: only that model's `no_grad` steps on N threads (1
    // by default; for a profiler).
    if let Some(name) = arg("--no-grad-only") {
        let model = load(&name);
        let threads = arg("--threads").and_then(|v| v.parse().ok()).unwrap_or(1);
        let us =
            adflex_runtime::with_threads(threads, || per_step(&model, steps, reps, Pass::NoGrad));
        println!("{{\"model\": \"{name}\", \"no_grad_step_us\": {us:.2}}}");
        return;
    }
    let mut ours = HashMap::new();
    for name in ["arm7", "quadruped"] {
        let model = load(name);
        for threads in [1, 2] {
            let (fwd, free, both) = adflex_runtime::with_threads(threads, || {
                (
                    per_step(&model, steps, reps, Pass::Recorded),
                    per_step(&model, steps, reps, Pass::NoGrad),
                    per_step(&model, steps, reps, Pass::Backward),
                )
            });
            ours.insert((name, threads, "step"), fwd);
            ours.insert((name, threads, "no_grad step"), free);
            ours.insert((name, threads, "forward_backward"), both);
            println!(
                "{{\"system\": \"adflex\", \"model\": \"{name}\", \"threads\": {threads}, \
                 \"step_us\": {fwd:.2}, \"no_grad_step_us\": {free:.2}, \
                 \"step_forward_backward_us\": {both:.2}}}"
            );
        }
        if name == "arm7" {
            let d = adflex_runtime::with_threads(1, || derivatives(&model, reps, false));
            let di = adflex_runtime::with_threads(1, || derivatives(&model, reps, true));
            ours.insert((name, 1, "derivatives"), d);
            ours.insert((name, 1, "inverse derivatives"), di);
            println!(
                "{{\"system\": \"adflex\", \"model\": \"arm7\", \"threads\": 1, \
                 \"forward_dynamics_derivatives_us\": {d:.2}, \
                 \"inverse_dynamics_derivatives_us\": {di:.2}}}"
            );
        }
    }
    if let Some(python) = arg("--python") {
        peer_ratios(&python, "robots.py", &ours);
    }
    if let Some(python) = arg("--newton") {
        peer_ratios(&python, "newton_robots.py", &ours);
    }
}

/// Runs the peers' script `bench/peers/{script}` with `python`, prints its lines and the ratio
/// of adflex's time (one thread) to each peer measurement it has a counterpart for.
fn peer_ratios(python: &str, script: &str, ours: &HashMap<(&str, usize, &str), f64>) {
    let script = format!("{}/peers/{script}", env!("CARGO_MANIFEST_DIR"));
    let out = Command::new(python)
        .arg(&script)
        .output()
        .unwrap_or_else(|e| panic!("{python} {script}: {e}"));
    let text = String::from_utf8_lossy(&out.stdout);
    print!("{text}");
    if !out.status.success() {
        eprintln!("{script} failed: {}", String::from_utf8_lossy(&out.stderr));
    }
    for line in text.lines() {
        let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        let (model, what, us) = (
            v["model"].as_str().unwrap_or(""),
            v["what"].as_str().unwrap_or(""),
            v["us"].as_f64().unwrap_or(f64::NAN),
        );
        let robot = if model == "arm7" { "arm7" } else { "quadruped" };
        let keys: &[&str] = match what {
            "mj_step" => &["step", "no_grad step"],
            // Newton's step is recorded on a tape, as adflex's "step".
            "step" => &["step"],
            "forward_backward" => &["forward_backward"],
            "computeABADerivatives" => &["derivatives"],
            "computeRNEADerivatives" => &["inverse derivatives"],
            _ => continue,
        };
        for key in keys {
            if let Some(o) = ours.get(&(robot, 1, *key)) {
                println!(
                    "{{\"ratio\": \"adflex {key} / {} {what}\", \"model\": \"{model}\", \
                     \"value\": {:.3}}}",
                    v["peer"].as_str().unwrap_or(""),
                    o / us
                );
            }
        }
    }
}
