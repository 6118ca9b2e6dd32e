//! Smoke control (after DiffTaichi's `smoke` example): the initial velocity field that
//! carries a disc of smoke to a target, found by L-BFGS through 100 steps of an
//! incompressible grid fluid on a 110 x 110 grid.
//!
//! The smoke starts as a disc low in the box and must rise and split into two discs
//! ([`SmokeTask`]). Each evaluation is a rollout on a tape and its backward pass, through the
//! semi-Lagrangian advection and the pressure projection by conjugate gradients with an
//! implicit-function-theorem adjoint (one transposed solve per step; `--jacobi K` uses K
//! unrolled Jacobi iterations instead). Three choices make the task solvable where
//! DiffTaichi's plain set-up (per-cell velocities from rest, squared distance) stalls with
//! the smoke smeared into filaments (`--plain` runs it):
//! - the parameters are filtered by a Gaussian of 3 cells into the initial velocity
//!   ([`SmokeTask::smoothed`]), so each step moves smooth flows;
//! - the loss adds the distance of the densities filtered by 6 cells
//!   ([`SmokeTask::with_coarse_loss`]), which has a gradient towards target discs the smoke
//!   does not touch yet;
//! - the first guess is a vortex pair in the disc ([`dipole`]), not rest: at rest every
//!   backtraced point lands on a cell centre, where bilinear interpolation's derivative is
//!   one-sided, so the first gradient is lopsided and the two halves part unevenly.
//!
//! `--descent` takes the peers' normalized gradient-descent steps (the benchmark's loop)
//! instead of L-BFGS.
//!
//! Run: `cargo run --release --example smoke_control` (pictures in
//! `target/demos/smoke_control/`; `--small` for the test's size, `--iters N`).

use adflex::kernels::fluid::scenes::SmokeTask;
use adflex::kernels::fluid::Pressure;
use adflex::optim::{Optimizer, Params};
use adflex::prelude::*;

/// The demo's sizes and choices.
#[derive(Clone, Debug)]
pub struct Config {
    /// Cells per axis (even).
    pub n: usize,
    /// Steps per rollout.
    pub steps: usize,
    /// Iterations (L-BFGS's or gradient descent's).
    pub iterations: usize,
    /// Gradient descent's step (with `lbfgs: false`).
    pub lr: f64,
    /// The pressure solve.
    pub pressure: Pressure,
    /// Width (cells) of the Gaussian filter from the parameters to the initial velocity.
    pub smoothing_sigma: f64,
    /// Width (cells) of the loss's coarse term (0: none).
    pub coarse_sigma: f64,
    /// Strength of the first guess's vortex pair (m/s; 0: at rest).
    pub guess_strength: f64,
    /// L-BFGS (true) or the peers' normalized gradient descent with step `lr`.
    pub lbfgs: bool,
}

impl Config {
    /// DiffTaichi's sizes: 110 x 110, 100 steps; L-BFGS, 50 iterations.
    pub fn full() -> Self {
        Config {
            n: 110,
            steps: 100,
            iterations: 50,
            lr: 1.0,
            pressure: Pressure::cg(),
            smoothing_sigma: 3.0,
            coarse_sigma: 6.0,
            guess_strength: 0.3,
            lbfgs: true,
        }
    }

    /// The test's size: 32 x 32, 30 steps, filters of 1 and 2 cells.
    pub fn small() -> Self {
        Config {
            n: 32,
            steps: 30,
            iterations: 20,
            smoothing_sigma: 1.0,
            coarse_sigma: 2.0,
            ..Config::full()
        }
    }

    /// DiffTaichi's set-up: per-cell velocities from rest, the squared distance alone.
    pub fn plain(self) -> Self {
        Config {
            smoothing_sigma: 0.0,
            coarse_sigma: 0.0,
            guess_strength: 0.0,
            ..self
        }
    }
}

/// What the demo did.
pub struct Outcome {
    /// The loss at each iteration (before its update), and after the last.
    pub losses: Vec<f64>,
    /// The squared distance of the final density to the target, from the first guess and
    /// after training ([`SmokeTask::distance`]: the loss without its coarse term).
    pub distances: (f64, f64),
    /// Seconds per loss-and-gradient evaluation (a rollout and its backward pass): the
    /// median for gradient descent, the mean over L-BFGS's evaluations.
    pub seconds_per_evaluation: f64,
    /// The initial density, the final density before and after training, the target.
    pub fields: [Vec<f64>; 4],
}

/// The velocity `(u, v)` of a vortex pair of strength `a` (m/s) centred in the disc of smoke,
/// just above its centre, on an `n x n` grid: the stream function `psi = -a (x - 0.5) g`
/// with `g` a Gaussian of 0.15 around `(0.5, 0.35)` (`u = dpsi/dy`, `v = -dpsi/dx`), so the
/// fluid rises at `a` in the middle and turns outwards on both sides: divergence-free and
/// mirror-symmetric.
pub fn dipole(n: usize, a: f64) -> (Vec<f64>, Vec<f64>) {
    let s2 = 0.15f64 * 0.15;
    (0..n * n)
        .map(|t| {
            let x = ((t / n) as f64 + 0.5) / n as f64 - 0.5;
            let y = ((t % n) as f64 + 0.5) / n as f64 - 0.35;
            let g = (-(x * x + y * y) / (2.0 * s2)).exp();
            (a * x * y * g / s2, a * g * (1.0 - x * x / s2))
        })
        .unzip()
}

/// Runs the optimization.
pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let task = SmokeTask::new(cfg.n, cfg.steps, cfg.pressure.clone())?
        .smoothed(cfg.smoothing_sigma)?
        .with_coarse_loss(cfg.coarse_sigma)?;
    let (u, v) = dipole(cfg.n, cfg.guess_strength);
    task.u0.assign(&u);
    task.v0.assign(&v);
    let (before, distance_before) = (task.final_density()?.to_vec(), task.distance()?);
    let (losses, seconds_per_evaluation) = if cfg.lbfgs {
        let params = Params::new().with(&task.u0).with(&task.v0);
        let report = Optimizer::lbfgs()
            .max_iters(cfg.iterations)
            .minimize_with(&params, || task.loss_and_grad())?;
        // Not converged within the budget is the expected outcome here: say so.
        println!("L-BFGS: {report}");
        (
            report.losses(),
            report.elapsed.as_secs_f64() / report.evaluations.max(1) as f64,
        )
    } else {
        let (mut losses, mut times) = (Vec::new(), Vec::new());
        for _ in 0..cfg.iterations {
            let start = std::time::Instant::now();
            losses.push(task.loss_and_grad()?);
            times.push(start.elapsed().as_secs_f64());
            task.descend(cfg.lr)?;
        }
        losses.push(task.loss_and_grad()?);
        times.sort_by(f64::total_cmp);
        (
            losses,
            times.get(times.len() / 2).copied().unwrap_or(f64::NAN),
        )
    };
    Ok(Outcome {
        losses,
        distances: (distance_before, task.distance()?),
        seconds_per_evaluation,
        fields: [
            task.density0.to_vec(),
            before,
            task.final_density()?.to_vec(),
            task.target.to_vec(),
        ],
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let flag = |name: &str| args.iter().any(|a| a == name);
    let value = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|k| args.get(k + 1))
    };
    let mut cfg = if flag("--small") {
        Config::small()
    } else {
        Config::full()
    };
    if flag("--plain") {
        cfg = cfg.plain();
    }
    if let Some(k) = value("--jacobi") {
        cfg.pressure = Pressure::Jacobi(k.parse()?);
    }
    if let Some(k) = value("--iters") {
        cfg.iterations = k.parse()?;
    }
    cfg.lbfgs = !flag("--descent");
    let out = run(&cfg)?;
    let (d0, d1) = out.distances;
    println!(
        "smoke control, {} x {} grid, {} steps, pressure {:?}: loss {:.4} -> {:.4} in {} \
         iterations; squared distance to the target {d0:.2} -> {d1:.2} ({:.1}%); {:.2} s per \
         evaluation (forward and backward)",
        cfg.n,
        cfg.n,
        cfg.steps,
        cfg.pressure,
        out.losses[0],
        out.losses.last().unwrap(),
        out.losses.len() - 1,
        100.0 * d1 / d0,
        out.seconds_per_evaluation
    );
    let dir = std::path::Path::new("target/demos/smoke_control");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.losses,
            "smoke control: loss (squared distance, plain and filtered) per iteration",
        )?;
    }
    let [a, b, c, d] = &out.fields;
    let fields = [
        (&a[..], "initial"),
        (&b[..], "final, first guess"),
        (&c[..], "final, trained"),
        (&d[..], "target"),
    ];
    adflex::viz::points::render_fields_png(
        dir.join("smoke.png"),
        &fields,
        1.0,
        (330 / cfg.n).max(1) as u32,
    )?;
    println!("pictures in {}", dir.display());
    Ok(())
}
