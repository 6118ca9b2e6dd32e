//! Gradients of a long rollout in bounded memory: the `cloth` scene (N = 64) for 10,000 steps,
//! differentiated with checkpointing, reporting the peak resident memory.
//!
//! A plain tape keeps every step's state and forces (about 3 arrays of 4,096 `Vec3<f32>` per
//! step, plus their gradients): several GB for 10,000 steps. `checkpointed` keeps one state
//! every `k` steps and recomputes each segment during backward.
//!
//! Run: `cargo run --release --example checkpoint_memory -- [steps] [every] [--plain]`
//! (defaults: 10000 steps, a checkpoint every 100; `--plain` uses an ordinary tape instead).

use adflex::kernels::scenes::cloth::{self, displacement_loss};
use adflex::prelude::*;

/// Peak resident set size of this process in MB (Linux `VmHWM`).
fn peak_rss_mb() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|kb| kb.parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let plain = args.iter().any(|a| a == "--plain");
    let nums: Vec<usize> = args.iter().filter_map(|a| a.parse().ok()).collect();
    let steps = nums.first().copied().unwrap_or(10_000);
    let every = nums.get(1).copied().unwrap_or(100);
    let n = 64;
    let scene = cloth::build::<f32>(n);
    let model = &scene.model;
    let ke = &model.springs().expect("the cloth has springs").ke;
    let target = Vec3::new(0.0, -0.1, 0.0);
    let scale = 1.0 / (n * n) as f32;
    let x0 = scene.initial.x.clone();
    let step = |tape: &mut Tape, s: &State<f32>| SemiImplicitEuler.step(model, tape, s, None, 1e-3);
    let loss = |tape: &mut Tape, s: &State<f32>| {
        let l = Array::zeros(1).named("loss");
        tape.launch(displacement_loss, s.x.len(), (&s.x, &x0, target, scale, &l));
        Ok(l)
    };
    let start = std::time::Instant::now();
    let value = if plain {
        let mut tape = Tape::new();
        let mut s = scene.initial.clone();
        for _ in 0..steps {
            s = step(&mut tape, &s)?;
        }
        let l = loss(&mut tape, &s)?;
        tape.backward(&l)?;
        l.get(0)
    } else {
        checkpointed(&scene.initial, steps, every, step, loss)?
            .loss
            .get(0)
    };
    let norm = |v: Vec<f64>| v.iter().map(|g| g * g).sum::<f64>().sqrt();
    let g_v0 = norm(
        scene
            .initial
            .v
            .grad()?
            .to_vec()
            .iter()
            .flat_map(|g| g.iter().map(|c| *c as f64))
            .collect(),
    );
    let g_ke = norm(ke.grad()?.to_vec().iter().map(|g| *g as f64).collect());
    println!(
        "{{\"steps\": {steps}, \"n\": {n}, \"mode\": \"{}\", \"every\": {every}, \"loss\": {value:e}, \
         \"grad_v0_norm\": {g_v0:e}, \"grad_ke_norm\": {g_ke:e}, \"seconds\": {:.1}, \"peak_rss_mb\": {:.1}}}",
        if plain { "plain" } else { "checkpointed" },
        start.elapsed().as_secs_f64(),
        peak_rss_mb()
    );
    Ok(())
}
