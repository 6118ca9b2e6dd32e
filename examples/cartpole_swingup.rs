//! Cart-pole swing-up by trajectory optimization through the simulator.
//!
//! The cart-pole of `kernels/robots/cartpole.urdf` (a 1 kg cart on a rail, a 0.1 kg pole of
//! 1 m) starts hanging down at rest. The controls are the cart's force in each of 240 frames of
//! 1/60 s (4 semi-implicit substeps each). L-BFGS minimizes, through the whole 960-step rollout
//! on the tape, `c(T) + 4 mean(c(t) over the last eighth)` with
//! `c = 10 (1 - cos theta) + xd^2 + thetad^2 + 0.1 x^2` (upright and still at the end, and
//! held there) plus a small effort term `1e-4 mean(u^2)`.
//!
//! Run: `cargo run --release --example cartpole_swingup` (pictures in
//! `target/demos/cartpole_swingup/`).

use adflex::kernels::articulation::{urdf, ArticulationControl, ArticulationState, Articulations};
use adflex::kernels::losses;
use adflex::optim::{Optimizer, Params, Report};
use adflex::prelude::*;

/// `tau = (u[frame], 0)`: the cart's force this frame; the hinge is not driven.
#[diff_kernel]
fn cart_force(u: &Array<f64>, frame: usize, tau: &Array<f64>) {
    tau[0] = u[frame];
    tau[1] = 0.0;
}

/// Upright and still: `w (10 (1 - cos theta) + xd^2 + thetad^2 + 0.1 x^2)`.
#[diff_kernel]
fn upright_cost(q: &Array<f64>, qd: &Array<f64>, w: f64, loss: &Array<f64>) {
    let up = 1.0 - cos(q[1]);
    let still = qd[0] * qd[0] + qd[1] * qd[1];
    loss.atomic_add(0, w * (10.0 * up + still + 0.1 * q[0] * q[0]));
}

/// What the demo runs.
pub struct Config {
    /// Frames, substeps per frame and the frame time (s).
    pub frames: usize,
    pub substeps: usize,
    pub frame_dt: f64,
    pub max_iters: usize,
    pub progress: bool,
}

impl Config {
    /// The size: 240 frames x 4 substeps at 1/60 s.
    pub fn full() -> Self {
        Config {
            frames: 240,
            substeps: 4,
            frame_dt: 1.0 / 60.0,
            max_iters: 100,
            progress: true,
        }
    }

    /// The test's size: 3 s in 180 frames x 2 substeps.
    pub fn small() -> Self {
        Config {
            frames: 180,
            substeps: 2,
            frame_dt: 1.0 / 60.0,
            max_iters: 100,
            progress: false,
        }
    }
}

/// What it found.
pub struct Outcome {
    pub report: Report,
    /// The states at every frame of the optimized rollout.
    pub frames: Vec<ArticulationState<f64>>,
    /// The optimized forces (N).
    pub forces: Vec<f64>,
    /// `1 - cos theta`, `|xd|` and `|thetad|` at the end.
    pub upright: f64,
    pub speed: f64,
    pub spin: f64,
}

/// The cart-pole, hanging down.
pub fn cartpole() -> Articulations<f64> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/kernels/robots/cartpole.urdf");
    let mut model = urdf::load(path, &urdf::UrdfOptions::default())
        .and_then(|b| b.finalize())
        .expect("the repository's cartpole loads");
    model.q0 = vec![0.0, std::f64::consts::PI];
    model
}

fn rollout(
    model: &Articulations<f64>,
    cfg: &Config,
    u: &Array<f64>,
    tape: &mut Tape,
) -> Result<Vec<ArticulationState<f64>>, Error> {
    let dt = cfg.frame_dt / cfg.substeps as f64;
    let mut frames = vec![model.state()];
    for f in 0..cfg.frames {
        let control = ArticulationControl {
            tau: Array::zeros(2),
            ..model.control()
        };
        tape.launch(cart_force, 1, (u, f, &control.tau));
        let mut s = frames.last().unwrap().clone();
        for _ in 0..cfg.substeps {
            s = model.step(tape, &s, Some(&control), dt)?;
        }
        frames.push(s);
    }
    Ok(frames)
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let model = cartpole();
    // A small, fixed, nonzero start: hanging still is a stationary point of the loss.
    let u = Array::from_vec(
        (0..cfg.frames)
            .map(|f| 0.5 * (f as f64 * 0.7).sin())
            .collect(),
    );
    let w = 1e-4 / cfg.frames as f64;
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .progress(cfg.progress)
        .grad_tol(1e-7)
        .minimize(&Params::new().with(&u), |tape| {
            let frames = rollout(&model, cfg, &u, tape)?;
            // Upright and still at the end, and held there over the last `hold` frames.
            let loss = Array::zeros(1);
            let hold = cfg.frames / 8;
            for (k, s) in frames.iter().rev().take(hold).enumerate() {
                let w = if k == 0 { 1.0 } else { 4.0 / hold as f64 };
                tape.launch(upright_cost, 1, (&s.q, &s.qd, w, &loss));
            }
            losses::sum_of_squares(tape, &u, w, &loss);
            Ok(loss)
        })?;
    let frames = rollout(&model, cfg, &u, &mut Tape::new())?;
    let last = frames.last().unwrap();
    Ok(Outcome {
        report,
        upright: 1.0 - last.q.get(1).cos(),
        speed: last.qd.get(0).abs(),
        spin: last.qd.get(1).abs(),
        forces: u.to_vec(),
        frames,
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = if std::env::args().any(|a| a == "--small") {
        Config::small()
    } else {
        Config::full()
    };
    let out = run(&cfg)?;
    println!("{}", out.report);
    println!(
        "end: 1 - cos(theta) = {:.1e}, |cart speed| = {:.1e} m/s, |pole rate| = {:.1e} rad/s \
         ({:.1} s, {} L-BFGS iterations)",
        out.upright,
        out.speed,
        out.spin,
        start.elapsed().as_secs_f64(),
        out.report.history.len().saturating_sub(1)
    );
    let dir = std::path::Path::new("target/demos/cartpole_swingup");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.report.losses(),
            "cart-pole swing-up: L-BFGS on 240 forces",
        )?;
    }
    let t = |k: usize| k as f64 * cfg.frame_dt;
    let angle: Vec<(f64, f64)> = out
        .frames
        .iter()
        .enumerate()
        .map(|(k, s)| (t(k), s.q.get(1)))
        .collect();
    let cart: Vec<(f64, f64)> = out
        .frames
        .iter()
        .enumerate()
        .map(|(k, s)| (t(k), s.q.get(0)))
        .collect();
    let force: Vec<(f64, f64)> = out
        .forces
        .iter()
        .enumerate()
        .map(|(k, &u)| (t(k), u / 10.0))
        .collect();
    for file in ["trajectory.svg", "trajectory.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "cart-pole swing-up: the optimized motion",
            "time (s)",
            "rad, m, N/10",
            &[
                ("pole angle (0 = up)", &angle[..]),
                ("cart position", &cart[..]),
                ("force / 10", &force[..]),
            ],
        )?;
    }
    // The motion at a glance: the cart (a dot on the rail) and the 1 m pole, every half second.
    let every = (0.5 / cfg.frame_dt).round() as usize;
    let poses: Vec<(String, Vec<(f64, f64)>)> = out
        .frames
        .iter()
        .enumerate()
        .step_by(every)
        .map(|(k, s)| {
            let (x, th) = (s.q.get(0), s.q.get(1));
            (
                format!("t = {:.1} s", t(k)),
                vec![(x, 0.0), (x + th.sin(), th.cos())],
            )
        })
        .collect();
    let series: Vec<(&str, &[(f64, f64)])> =
        poses.iter().map(|(n, p)| (n.as_str(), &p[..])).collect();
    for file in ["motion.svg", "motion.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "cart-pole swing-up: the pole every 0.5 s (cart at the lower end)",
            "x (m)",
            "z (m)",
            &series,
        )?;
    }
    println!(
        "pictures: {}/{{loss, trajectory, motion}}.{{svg, png}}",
        dir.display()
    );
    Ok(())
}
