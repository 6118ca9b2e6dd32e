//! `worlds [--worlds 1024] [--frames 240] [--substeps 4] [--reps 2] [--python PATH]
//! [--newton PATH]`: many
//! worlds in one model. W cartpoles (`kernels/robots/cartpole.urdf`) rolled out for
//! `frames x substeps` semi-implicit steps (dt 1/240 s, a force on each cart), forward and
//! backward: the time per world-step at W = 1 and W = `--worlds` on 1 thread and on 2 (one
//! model, and the worlds in two shares, a model and tape each), and each case's peak memory (each case runs in its own process: `worlds-case`). With
//! `--python`, MuJoCo's batched rollout of the same cartpoles (`bench/peers/worlds.py`,
//! forward only) in the same run; with `--newton`, Newton's worlds on the CPU
//! (`bench/peers/newton_worlds.py`, Featherstone, forward and backward on a `wp.Tape`). One
//! JSON line each, then the ratios. First, 256 cloths of 16 x 16 as worlds against one
//! 256 x 256 cloth.

use std::process::Command;
use std::time::Instant;

use adflex_kernels::articulation::{urdf, ArticulationBuilder, ArticulationControl, Articulations};
use adflex_runtime::prelude::*;
use serde_json::{json, Value};

use crate::arg;

const ROBOTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../kernels/robots");

/// W cartpoles, world `w`'s pole tilted by `0.1 + 0.1 (w mod 8)`.
fn cartpoles(worlds: usize) -> Articulations<f64> {
    let base =
        urdf::load(format!("{ROBOTS}/cartpole.urdf"), &Default::default()).expect("cartpole.urdf");
    let pole = base.find("pole").expect("a pole").0;
    let mut b = ArticulationBuilder::new();
    for w in 0..worlds {
        let mut s = base.clone();
        s.links_mut()[pole].joint.initial = vec![0.1 + 0.1 * (w % 8) as f64];
        b.add_world(&s);
    }
    b.finalize().expect("cartpoles")
}

/// Seconds for one rollout of `steps` steps and its backward pass (the gradient of the sum of
/// the worlds' losses with respect to every step's forces).
fn rollout(model: &Articulations<f64>, steps: usize) -> f64 {
    let t0 = Instant::now();
    let mut tape = Tape::new();
    let mut s = model.state();
    let idle = model.control();
    let mut forces = Vec::with_capacity(steps);
    for k in 0..steps {
        let mut tau = vec![0.0; model.n_dof];
        for (w, info) in model.worlds.iter().enumerate() {
            tau[info.dofs.start] = 0.5 * (0.01 * k as f64 + w as f64).sin();
        }
        let tau = Array::from_vec(tau).requires_grad();
        let c = ArticulationControl {
            tau: tau.clone(),
            ..idle.clone()
        };
        s = model
            .step(&mut tape, &s, Some(&c), 1.0 / 240.0)
            .expect("a step");
        forces.push(tau);
    }
    let loss = Array::zeros(1);
    adflex_kernels::losses::sum_of_squares(&mut tape, &s.q, 1.0, &loss);
    tape.backward(&loss).expect("a gradient");
    assert!(forces[0].grad().expect("a gradient").get(0).is_finite());
    t0.elapsed().as_secs_f64()
}

/// One case in this process: a JSON line with the time per world-step and the peak memory.
pub fn case(rest: &[String]) -> Value {
    let worlds = arg(rest, "--worlds").unwrap_or(1024);
    let threads = arg(rest, "--threads").unwrap_or(1);
    let steps = arg(rest, "--frames").unwrap_or(240) * arg(rest, "--substeps").unwrap_or(4);
    let reps = arg(rest, "--reps").unwrap_or(2);
    if let Some(n) = arg(rest, "--serial-below") {
        let mut s = adflex_runtime::settings::settings();
        s.serial_below = n;
        s.apply();
    }
    // `--shares k`: the worlds split into k models, each rolled out as its own task with its
    // own tape (`adflex_distributed::run_worlds_in_threads`; a world's bits do not depend on
    // its model's other worlds).
    let shares = arg(rest, "--shares").unwrap_or(1);
    let models: Vec<Articulations<f64>> = (0..shares)
        .map(|k| cartpoles(adflex_distributed::shard(worlds, k, shares).len()))
        .collect();
    let best = with_threads(threads, || {
        (0..reps.max(1))
            .map(|_| {
                let t0 = Instant::now();
                adflex_distributed::run_worlds_in_threads(shares, shares, |k| {
                    rollout(&models[k.start], steps);
                    Ok(vec![vec![]])
                })
                .expect("the shares run");
                t0.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min)
    });
    json!({
        "system": "adflex",
        "model": "cartpole",
        "worlds": worlds,
        "threads": threads,
        "shares": shares,
        "steps": steps,
        "forward_backward_us_per_world_step": 1e6 * best / (worlds * steps) as f64,
        "peak_rss_mb": crate::timing::peak_rss_mb(),
    })
}

/// 256 cloths of 16 x 16 as worlds of one model against one 256 x 256 cloth (the same
/// particles): seconds per step of `steps` steps forward and backward, best of `reps`, on
/// `threads` threads.
fn cloths(threads: usize, steps: usize, reps: usize) -> (f64, f64) {
    use adflex_kernels::scenes::cloth;
    let one = cloth::build::<f32>(256);
    let small = cloth::build::<f32>(16);
    let mut b = adflex_kernels::ModelBuilder::<f32>::new();
    b.particle_radius = 0.01;
    let mut grid = adflex_kernels::ModelBuilder::<f32>::new();
    grid.particle_radius = 0.01;
    grid.add_cloth_grid(&adflex_kernels::prelude::ClothGrid::benchmark(16));
    grid.set_ground(small.model.ground().expect("the scene's ground"));
    for _ in 0..256 {
        b.add_world(&grid);
    }
    let model = b.finalize();
    let many = cloth::Cloth {
        n: 256, // the loss's scale: 1 / 256^2 over the same number of particles
        initial: model.state(),
        model,
    };
    let _ = many.initial.v.clone().requires_grad();
    let _ = many
        .model
        .springs()
        .expect("springs")
        .ke
        .clone()
        .requires_grad();
    let time = |scene: &cloth::Cloth<f32>| {
        with_threads(threads, || {
            (0..reps.max(1))
                .map(|_| {
                    let t0 = Instant::now();
                    cloth::rollout(scene, steps, true).expect("a cloth rollout");
                    t0.elapsed().as_secs_f64() / steps as f64
                })
                .fold(f64::INFINITY, f64::min)
        })
    };
    (time(&many), time(&one))
}

/// Cloth `j` of [`implicit`]: its own size, stiffness and height, dropped on the ground.
fn implicit_cloth(j: usize) -> adflex_kernels::ModelBuilder<f64> {
    let mut b = adflex_kernels::ModelBuilder::<f64>::new();
    b.add_cloth_grid(&adflex_kernels::prelude::ClothGrid {
        spring_ke: 400.0 + 50.0 * (j % 5) as f64,
        origin: Vec3::new(0.0, 0.05 + 0.01 * (j % 7) as f64, 0.0),
        ..adflex_kernels::prelude::ClothGrid::benchmark(8 + j % 5)
    });
    b.set_ground(adflex_kernels::prelude::Ground::default());
    b
}

/// Implicit Euler (1/60 s) on `--worlds` cloths as worlds of one model, against the same
/// cloths as separate models stepped one after another: seconds per step, forward and
/// backward (the gradient of every particle's height with respect to the initial
/// velocities), best of `--reps`, and each case's force evaluations and tangent products per
/// step. One JSON line, on one thread.
pub fn implicit(rest: &[String]) {
    use adflex_kernels::integrators::ImplicitEuler;
    let worlds = arg(rest, "--worlds").unwrap_or(16);
    let steps = arg(rest, "--steps").unwrap_or(10);
    let reps = arg(rest, "--reps").unwrap_or(1);
    let solver = ImplicitEuler::default();
    // Seconds, force evaluations and products of `steps` steps of `model` and the backward.
    let run = |model: &adflex_kernels::Model<f64>| {
        let t0 = Instant::now();
        let mut tape = Tape::new();
        let s0 = model.state();
        let v0 = s0.v.clone().requires_grad();
        let mut s = s0;
        let (mut evaluations, mut products) = (0, 0);
        for _ in 0..steps {
            let (next, stats) = solver
                .step_with_stats(model, &mut tape, &s, None, 1.0 / 60.0)
                .expect("an implicit step");
            evaluations += stats.force_evaluations;
            products += stats.linear_iterations;
            s = next;
        }
        let loss = Array::zeros(1);
        adflex_kernels::losses::sum_of_squares_vec3(&mut tape, &s.x, 1.0, &loss);
        tape.backward(&loss).expect("a backward pass");
        assert!(v0.grad().is_ok());
        (t0.elapsed().as_secs_f64(), evaluations, products)
    };
    let mut together = adflex_kernels::ModelBuilder::<f64>::new();
    let apart: Vec<_> = (0..worlds)
        .map(|j| {
            together.add_world(&implicit_cloth(j));
            implicit_cloth(j).finalize()
        })
        .collect();
    let together = together.finalize();
    let best = |f: &(dyn Fn() -> (f64, usize, usize) + Sync)| {
        with_threads(1, || {
            (0..reps.max(1))
                .map(|_| f())
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .expect("a run")
        })
    };
    let (t_together, e_together, p_together) = best(&|| run(&together));
    let (t_apart, e_apart, p_apart) = best(&|| {
        apart
            .iter()
            .map(run)
            .fold((0.0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2))
    });
    println!(
        "{}",
        json!({"system": "adflex", "case": "implicit Euler, cloths as worlds vs apart",
               "worlds": worlds, "steps": steps, "threads": 1,
               "together_s_per_step": t_together / steps as f64,
               "apart_s_per_step": t_apart / steps as f64,
               "ratio": t_together / t_apart,
               "together_evaluations_per_step": e_together as f64 / steps as f64,
               "apart_evaluations_per_step": e_apart as f64 / steps as f64,
               "together_products_per_step": p_together as f64 / steps as f64,
               "apart_products_per_step": p_apart as f64 / steps as f64})
    );
}

pub fn main(rest: &[String]) {
    for threads in [1, 2] {
        let (many, one) = cloths(threads, 50, 3);
        println!(
            "{}",
            json!({"system": "adflex", "case": "256 cloths of 16 x 16 (worlds) vs one 256 x 256",
                   "threads": threads, "worlds_s_per_step": many, "one_cloth_s_per_step": one,
                   "ratio": many / one})
        );
    }
    let worlds = arg(rest, "--worlds").unwrap_or(1024);
    let frames = arg(rest, "--frames").unwrap_or(240);
    let substeps = arg(rest, "--substeps").unwrap_or(4);
    let reps = arg(rest, "--reps").unwrap_or(2);
    let me = std::env::current_exe().expect("the bench binary");
    let mut ours = Vec::new();
    for (w, t, shares) in [(1, 1, 1), (worlds, 1, 1), (worlds, 2, 1), (worlds, 2, 2)] {
        let out = Command::new(&me)
            .args(["worlds-case", "--worlds", &w.to_string(), "--threads"])
            .arg(t.to_string())
            .args(["--shares", &shares.to_string()])
            .args(["--frames", &frames.to_string(), "--substeps"])
            .arg(substeps.to_string())
            .args(["--reps", &reps.to_string()])
            .output()
            .expect("the bench runs itself");
        let line = String::from_utf8_lossy(&out.stdout);
        println!("{}", line.trim());
        let v: Value = serde_json::from_str(line.trim()).expect("a JSON line");
        ours.push(
            v["forward_backward_us_per_world_step"]
                .as_f64()
                .unwrap_or(f64::NAN),
        );
    }
    println!(
        "{}",
        json!({"ratio": format!("per world-step, W = {worlds} / W = 1 (1 thread)"),
               "value": ours[1] / ours[0]})
    );
    println!(
        "{}",
        json!({"ratio": format!("speed-up of 2 threads over 1 at W = {worlds}, one model"),
               "value": ours[1] / ours[2]})
    );
    println!(
        "{}",
        json!({"ratio": format!(
            "speed-up of 2 threads over 1 at W = {worlds}, two shares of the worlds"),
               "value": ours[1] / ours[3]})
    );
    if let Some(python) = rest
        .iter()
        .position(|a| a == "--newton")
        .and_then(|k| rest.get(k + 1))
    {
        let script = concat!(env!("CARGO_MANIFEST_DIR"), "/peers/newton_worlds.py");
        let out = Command::new(python)
            .arg(script)
            .args(["--worlds", &worlds.to_string(), "--steps"])
            .arg((frames * substeps).to_string())
            .output()
            .expect("the Newton peer's python runs");
        for line in String::from_utf8_lossy(&out.stdout).lines() {
            println!("{line}");
            let Ok(v) = serde_json::from_str::<Value>(line) else {
                continue;
            };
            let k = if v["worlds"].as_u64() == Some(1) {
                0
            } else {
                1
            };
            let us = v["forward_backward_us_per_world_step"]
                .as_f64()
                .unwrap_or(f64::NAN);
            println!(
                "{}",
                json!({"ratio": format!(
                    "adflex / Newton forward+backward, W = {}, 1 thread",
                    v["worlds"]),
                    "value": ours[k] / us})
            );
        }
    }
    let Some(python) = rest
        .iter()
        .position(|a| a == "--python")
        .and_then(|k| rest.get(k + 1))
    else {
        return;
    };
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/peers/worlds.py");
    let out = Command::new(python)
        .arg(script)
        .args(["--worlds", &worlds.to_string(), "--steps"])
        .arg((frames * substeps).to_string())
        .output()
        .expect("the peer's python runs");
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        println!("{line}");
        let Ok(v) = serde_json::from_str::<Value>(line) else {
            continue;
        };
        let (w, t) = (v["worlds"].as_u64(), v["threads"].as_u64());
        let k = match (w, t) {
            (Some(1), Some(1)) => 0,
            (Some(_), Some(1)) => 1,
            _ => 3,
        };
        let us = v["us_per_world_step"].as_f64().unwrap_or(f64::NAN);
        println!(
            "{}",
            json!({"ratio": format!(
                "adflex forward+backward / MuJoCo rollout forward, W = {}, {} thread(s)",
                w.unwrap_or(0), t.unwrap_or(0)),
                "value": ours[k] / us})
        );
    }
}
