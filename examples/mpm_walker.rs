//! DiffTaichi's elastic walker (`diffmpm`, Hu et al. 2020) learned by gradients through
//! MLS-MPM.
//!
//! A 2D robot of 2,976 particles (a body on four legs, fixed-corotated, `mu = lambda = 10`)
//! on a 128 x 128 grid, `dt = 1e-3`, 1,024 steps. Each leg is an actuator whose value at step
//! `t` is `tanh(sum_j w[i, j] sin(20 t dt + j pi / 2) + b[i])` (an open-loop controller of
//! four sine waves); it adds a vertical active stress of strength 4. The loss is minus the
//! mean `x` of the particles at the end: walk right. 80 iterations of gradient descent with
//! step 0.1 from small random weights, the gradients through the whole rollout by
//! checkpointing (memory: the checkpoints, not the 1,024 steps).
//!
//! The same model in Taichi is `bench/peers/taichi_mpm.py` (same initial weights), for the
//! loss curve and the time per iteration side by side (`adflex-bench mpm`).
//!
//! Run: `cargo run --release --example mpm_walker` (pictures in
//! `target/demos/mpm_walker/`; `--small` for the test's size).
//!
//! The scene, controller and loss are [`WalkerTask`]'s, which the benchmark times too.

use adflex::kernels::mpm::WalkerTask;
use adflex::prelude::*;
use adflex::viz::points::{actuation_color, render_strip_png, Frame2d, StripOptions};
use adflex::viz::render::Rgba;

/// The demo's sizes.
#[derive(Clone, Debug)]
pub struct Config {
    /// Grid nodes per axis.
    pub n_grid: usize,
    /// Steps per rollout.
    pub steps: usize,
    /// Gradient descent iterations.
    pub iterations: usize,
    /// Gradient descent step.
    pub lr: f64,
    /// Time step (s).
    pub dt: f64,
}

impl Config {
    /// DiffTaichi's sizes.
    pub fn full() -> Self {
        Config {
            n_grid: 128,
            steps: 1024,
            iterations: 80,
            lr: 0.1,
            dt: 1e-3,
        }
    }

    /// The test's size: a 64 x 64 grid (744 particles), 300 steps, 6 iterations.
    pub fn small() -> Self {
        Config {
            n_grid: 64,
            steps: 300,
            iterations: 6,
            lr: 0.1,
            dt: 1e-3,
        }
    }
}

/// What the demo did.
pub struct Outcome {
    /// The loss at each iteration (before its update), and after the last.
    pub losses: Vec<f64>,
    /// Seconds per iteration (forward and backward), the median.
    pub seconds_per_iteration: f64,
    /// How far the mean position moved right, before and after training.
    pub distance_before: f64,
    pub distance_after: f64,
    /// Frames of the trained walker, for the picture.
    pub frames: Vec<Frame2d>,
}

/// Runs the rollout forward only, keeping pictures of `panels` frames.
fn film(task: &WalkerTask<f32>, panels: usize) -> Result<Vec<Frame2d>, Error> {
    let mpm = &task.mpm;
    let actuator = mpm.actuator.to_vec();
    let gain = mpm.act_gain.to_vec();
    let mut s = mpm.state();
    let mut frames = Vec::new();
    let every = (task.steps / panels).max(1);
    for t in 0..task.steps {
        let mut tape = Tape::new();
        let (next, act) = task.step(&mut tape, &s, t)?;
        s = next;
        if (t + 1) % every == 0 && frames.len() < panels {
            let (a, x) = (act.to_vec(), s.x.to_vec());
            let color = |p: usize| {
                if gain[p] != 0.0 {
                    actuation_color(a[actuator[p] as usize] as f64)
                } else {
                    Rgba::rgb(30, 30, 30)
                }
            };
            frames.push(Frame2d {
                points: x.iter().map(|p| [p.x as f64, p.y as f64]).collect(),
                colors: (0..x.len()).map(color).collect(),
                caption: format!("t = {:.2} s", (t + 1) as f64 * task.dt),
            });
        }
    }
    Ok(frames)
}

/// Trains the walker by gradient descent.
pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let task = WalkerTask::<f32>::new(cfg.n_grid, cfg.steps, cfg.dt);
    let x0 = task.mpm.state().x.to_vec();
    let mean_x0 = x0.iter().map(|p| p.x as f64).sum::<f64>() / x0.len() as f64;
    let mut losses = Vec::new();
    let mut times = Vec::new();
    for _ in 0..cfg.iterations {
        let start = std::time::Instant::now();
        losses.push(task.loss_and_grad()?);
        times.push(start.elapsed().as_secs_f64());
        for p in [&task.weights, &task.bias] {
            let g = p.grad()?.to_vec();
            p.modify(|v| {
                v.iter_mut()
                    .zip(&g)
                    .for_each(|(v, g)| *v -= cfg.lr as f32 * g)
            });
        }
    }
    losses.push(task.loss_and_grad()?);
    times.sort_by(f64::total_cmp);
    Ok(Outcome {
        distance_before: -losses[0] - mean_x0,
        distance_after: -losses.last().unwrap() - mean_x0,
        losses,
        seconds_per_iteration: times.get(times.len() / 2).copied().unwrap_or(f64::NAN),
        frames: film(&task, 6)?,
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let small = std::env::args().any(|a| a == "--small");
    let cfg = if small {
        Config::small()
    } else {
        Config::full()
    };
    let out = run(&cfg)?;
    println!(
        "walker, {} x {} grid, {} steps: loss {:.4} -> {:.4} in {} iterations; walked {:.4} before \
         training, {:.4} after; {:.2} s per iteration (forward and backward)",
        cfg.n_grid,
        cfg.n_grid,
        cfg.steps,
        out.losses[0],
        out.losses.last().unwrap(),
        cfg.iterations,
        out.distance_before,
        out.distance_after,
        out.seconds_per_iteration
    );
    let dir = std::path::Path::new("target/demos/mpm_walker");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.losses,
            "MPM walker: loss (minus the mean x) per iteration",
        )?;
    }
    let mut opts = StripOptions::default();
    opts.region = ([0.0, 0.0], [1.0, 0.4]);
    opts.floor = Some(3.0 / cfg.n_grid as f64);
    render_strip_png(dir.join("walker.png"), &out.frames, &opts)?;
    println!("pictures in {}", dir.display());
    Ok(())
}
