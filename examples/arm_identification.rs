//! Inertial-parameter identification of a robot arm from a recorded trajectory.
//!
//! The 7-DoF arm of `kernels/robots/arm7.urdf` is driven by known joint torques (a sum of
//! sines per joint) for `duration` seconds, and its joint angles are recorded every `every`
//! steps. The simulator then starts from wrong masses of the seven moving links (x1.3 or x0.7)
//! and L-BFGS recovers them by matching the recorded angles, through the whole rollout on the
//! tape: the masses are the model's own array (`model.mass`; `com`, `inertia` and
//! `joint_pos` are arrays too). The centres of mass are taken as known: with them free as
//! well, a short trajectory is matched as closely by moving first moments `m c` as by moving
//! masses, and the masses are not identified.
//!
//! Run: `cargo run --release --example arm_identification`

use adflex::kernels::articulation::{urdf, ArticulationControl, ArticulationState, Articulations};
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;

/// `loss += w |q - target|^2`.
#[diff_kernel]
fn mismatch(q: &Array<f64>, target: &Array<f64>, w: f64, loss: &Array<f64>) {
    let i = tid();
    let d = q[i] - target[i];
    loss.atomic_add(0, w * d * d);
}

/// What the demo runs.
pub struct Config {
    pub duration: f64,
    pub dt: f64,
    pub every: usize,
    pub max_iters: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 0.3,
            dt: 5e-4,
            every: 10,
            max_iters: 100,
            progress: true,
        }
    }

    pub fn small() -> Self {
        Config {
            duration: 0.3,
            dt: 1e-3,
            every: 10,
            max_iters: 60,
            progress: false,
        }
    }
}

/// What it found.
pub struct Outcome {
    pub report: Report,
    /// Largest relative error of the moving links' masses: first guess, found.
    pub mass_error: (f64, f64),
}

pub fn arm() -> Articulations<f64> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/kernels/robots/arm7.urdf");
    urdf::load(path, &urdf::UrdfOptions::default())
        .and_then(|b| b.finalize())
        .expect("the repository's arm loads")
}

/// The known torques at step `s`: a sum of two sines per joint.
fn torques(n: usize, s: usize, dt: f64) -> Vec<f64> {
    let t = s as f64 * dt;
    (0..n)
        .map(|j| {
            let a = 3.0 / (1.0 + j as f64);
            a * (t * (3.0 + j as f64)).sin()
                + 0.5 * a * (t * (7.0 + 2.0 * j as f64) + j as f64).sin()
        })
        .collect()
}

/// The recorded (or simulated) angles every `every` steps.
fn rollout(
    model: &Articulations<f64>,
    cfg: &Config,
    tape: &mut Tape,
) -> Result<Vec<Array<f64>>, Error> {
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let mut s: ArticulationState<f64> = model.state();
    let mut frames = Vec::new();
    for k in 0..steps {
        let control = ArticulationControl {
            tau: Array::from_vec(torques(model.n_dof, k, cfg.dt)),
            ..model.control()
        };
        s = model.step(tape, &s, Some(&control), cfg.dt)?;
        if (k + 1) % cfg.every == 0 {
            frames.push(s.q.clone());
        }
    }
    Ok(frames)
}

/// The largest relative error of the moving links' masses (the base is welded to the world).
fn mass_error(model: &Articulations<f64>, truth: &[f64]) -> f64 {
    let m = model.mass.to_vec();
    (1..m.len())
        .map(|i| (m[i] / truth[i] - 1.0).abs())
        .fold(0.0, f64::max)
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let model = arm();
    let truth = model.mass.to_vec();
    let recorded: Vec<Array<f64>> = rollout(&model, cfg, &mut Tape::new())?
        .into_iter()
        .map(|a| a.deep_clone())
        .collect();
    // The first guess: masses off by 30% (the centres of mass are known).
    model.mass.modify(|m| {
        for (i, x) in m.iter_mut().enumerate().skip(1) {
            *x *= if i % 2 == 0 { 1.3 } else { 0.7 };
        }
    });
    let first = mass_error(&model, &truth);
    let w = 1.0 / (recorded.len() * model.n_dof) as f64;
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .progress(cfg.progress)
        .grad_tol(1e-10)
        .minimize(
            &Params::new().bounded(&model.mass, Bounds::positive()),
            |tape| {
                let frames = rollout(&model, cfg, tape)?;
                let loss = Array::zeros(1);
                for (q, target) in frames.iter().zip(&recorded) {
                    tape.launch(mismatch, q.len(), (q, target, w, &loss));
                }
                Ok(loss)
            },
        )?;
    Ok(Outcome {
        report,
        mass_error: (first, mass_error(&model, &truth)),
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
        "largest mass error {:.1}% -> {:.2e} ({:.1} s)",
        100.0 * out.mass_error.0,
        out.mass_error.1,
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/arm_identification");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.report.losses(),
            "arm identification: L-BFGS on the 7 link masses",
        )?;
    }
    println!("pictures: {}/loss.{{svg, png}}", dir.display());
    Ok(())
}
