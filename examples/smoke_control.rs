//! Smoke control (after DiffTaichi's `smoke` example): the initial velocity field that
//! carries a disc of smoke to a target, found by gradient descent through 100 steps of an
//! incompressible grid fluid on a 110 x 110 grid.
//!
//! The smoke starts as a disc low in the box and must rise and split into two discs
//! ([`SmokeTask`]). The parameters are the `2 x 110^2` initial velocities; each iteration is a
//! rollout on a tape and its backward pass, through the semi-Lagrangian advection and the
//! pressure projection by conjugate gradients with an implicit-function-theorem adjoint
//! (one transposed solve per step; `--jacobi K` uses K unrolled Jacobi iterations instead).
//!
//! Run: `cargo run --release --example smoke_control` (pictures in
//! `target/demos/smoke_control/`; `--small` for the test's size).

use adflex::kernels::fluid::scenes::SmokeTask;
use adflex::kernels::fluid::Pressure;
use adflex::prelude::*;

/// The demo's sizes.
#[derive(Clone, Debug)]
pub struct Config {
    /// Cells per axis (even).
    pub n: usize,
    /// Steps per rollout.
    pub steps: usize,
    /// Gradient descent iterations.
    pub iterations: usize,
    /// Gradient descent step.
    pub lr: f64,
    /// The pressure solve.
    pub pressure: Pressure,
}

impl Config {
    /// DiffTaichi's sizes: 110 x 110, 100 steps.
    pub fn full() -> Self {
        Config {
            n: 110,
            steps: 100,
            iterations: 50,
            lr: 1.0,
            pressure: Pressure::cg(),
        }
    }

    /// The test's size: 32 x 32, 30 steps.
    pub fn small() -> Self {
        Config {
            n: 32,
            steps: 30,
            iterations: 20,
            lr: 1.0,
            pressure: Pressure::cg(),
        }
    }
}

/// What the demo did.
pub struct Outcome {
    /// The loss at each iteration (before its update), and after the last.
    pub losses: Vec<f64>,
    /// Median seconds per iteration (rollout and backward).
    pub seconds_per_iteration: f64,
    /// The initial density, the final density before and after training, the target.
    pub fields: [Vec<f64>; 4],
}

/// Runs the optimization.
pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let task = SmokeTask::new(cfg.n, cfg.steps, cfg.pressure.clone())?;
    let before = task.final_density()?.to_vec();
    let mut losses = Vec::new();
    let mut times = Vec::new();
    for _ in 0..cfg.iterations {
        let start = std::time::Instant::now();
        losses.push(task.loss_and_grad()?);
        times.push(start.elapsed().as_secs_f64());
        task.descend(cfg.lr)?;
    }
    losses.push(task.loss_and_grad()?);
    times.sort_by(f64::total_cmp);
    Ok(Outcome {
        losses,
        seconds_per_iteration: times.get(times.len() / 2).copied().unwrap_or(f64::NAN),
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
    let mut cfg = if args.iter().any(|a| a == "--small") {
        Config::small()
    } else {
        Config::full()
    };
    if let Some(k) = args
        .iter()
        .position(|a| a == "--jacobi")
        .and_then(|k| args.get(k + 1))
    {
        cfg.pressure = Pressure::Jacobi(k.parse()?);
    }
    let out = run(&cfg)?;
    println!(
        "smoke control, {} x {} grid, {} steps, pressure {:?}: loss {:.4} -> {:.4} in {} iterations \
         ({:.1}% of the first); {:.2} s per iteration (forward and backward)",
        cfg.n,
        cfg.n,
        cfg.steps,
        cfg.pressure,
        out.losses[0],
        out.losses.last().unwrap(),
        cfg.iterations,
        100.0 * out.losses.last().unwrap() / out.losses[0],
        out.seconds_per_iteration
    );
    let dir = std::path::Path::new("target/demos/smoke_control");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.losses,
            "smoke control: squared distance to the target per iteration",
        )?;
    }
    let [a, b, c, d] = &out.fields;
    let fields = [
        (&a[..], "initial"),
        (&b[..], "final, untrained"),
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
