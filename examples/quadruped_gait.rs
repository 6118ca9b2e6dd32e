//! An open-loop gait for a quadruped, found by gradients through ground contact.
//!
//! The quadruped of `kernels/robots/quadruped.urdf` (a 5 kg torso on a free joint, four legs of
//! a hip about z and a knee, 14 degrees of freedom, read with its collision spheres and box)
//! stands on a frictional floor, its eight joints held by PD servos. Their targets follow one
//! sine per joint, `a_j sin(2 pi f t + phi_j)`, at a fixed frequency. L-BFGS tunes the 8
//! amplitudes (within 0.6 rad) and 8 phases to carry the torso as far as possible along +x in
//! `duration` seconds: the loss is `-x_T + 0.5 y_T^2 + 0.01 |a|^2`, through every contact of
//! the rollout on the tape.
//!
//! Run: `cargo run --release --example quadruped_gait`

use adflex::kernels::articulation::{
    urdf, ArticulationControl, ArticulationState, Articulations, GroundContact,
};
use adflex::kernels::losses;
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;

/// The joints' PD targets at time `t`: `target[6 + j] = a[j] sin(w t + phi[j])` (the free
/// joint's six are not driven).
#[diff_kernel]
fn gait(a: &Array<f64>, phi: &Array<f64>, w: f64, t: f64, target: &Array<f64>) {
    let j = tid();
    target[j + 6] = a[j] * sin(w * t + phi[j]);
}

/// `-x + 0.5 y^2` of the torso (coordinates 0 and 1 of the free joint).
#[diff_kernel]
fn distance(q: &Array<f64>, loss: &Array<f64>) {
    loss.atomic_add(0, 0.5 * q[1] * q[1] - q[0]);
}

/// What the demo runs.
pub struct Config {
    pub duration: f64,
    pub dt: f64,
    pub frequency: f64,
    pub max_iters: usize,
    pub progress: bool,
    /// The first guess's amplitudes (0.2 rad) times `1 + perturb`.
    pub perturb: f64,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 2.0,
            dt: 2e-3,
            frequency: 2.0,
            max_iters: 40,
            progress: true,
            perturb: 0.0,
        }
    }

    pub fn small() -> Self {
        Config {
            duration: 1.0,
            dt: 2e-3,
            frequency: 2.0,
            max_iters: 15,
            progress: false,
            perturb: 0.0,
        }
    }
}

/// What it found.
pub struct Outcome {
    pub report: Report,
    /// Distance the torso moved along x (m): with the first guess, and found.
    pub distance: (f64, f64),
    /// The torso's lowest height during the found gait (m).
    pub lowest: f64,
    /// The torso's path `(t, x, y, z)` during the found gait.
    pub path: Vec<(f64, f64, f64, f64)>,
    /// The found gait's distance simulated again with half the time step (m): a gait that
    /// exploited the discretization would not survive it.
    pub distance_half_dt: f64,
}

/// The quadruped of `quadruped.urdf` on a floating base, standing on its sphere feet.
pub fn quadruped() -> Articulations<f64> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/kernels/robots/quadruped.urdf");
    let options = urdf::UrdfOptions {
        floating_base: true,
        collisions: true,
        ..Default::default()
    };
    let mut b = urdf::load(path, &options).expect("the repository's quadruped loads");
    // The feet's friction smoothed below 0.1 m/s and explicit: each foot bears a quarter of
    // the torso through a light shin, where the default 0.01 m/s makes explicit friction at
    // rest a damper too stiff for the step, and the gradient through the rollout explodes
    // (norm 2e6-1.4e7 at the first guess of the small run, against 0.7). Implicit friction
    // (the default since) removes that: at 0.01 m/s the first guess's gradient norm is 2.2,
    // and the small run reaches 0.47 m (0.64 m at 0.1 m/s, against 0.41 m explicit); but the
    // full run's line search then fails at its 17th iteration (1.02 m), so the figures quoted
    // for this demo are the explicit law's.
    b.ground = Some(GroundContact {
        stiction_tolerance: 0.1,
        implicit_friction: false,
        ..GroundContact::default()
    });
    // PD servos hold the legs (the gait moves their targets).
    for l in b.links_mut() {
        if l.joint.kind.is_scalar() {
            l.joint = l.joint.clone().pd(30.0, 1.0);
        }
    }
    let mut model: Articulations<f64> = b.finalize().expect("a valid robot");
    model.q0[2] = 0.2;
    model
}

fn rollout(
    model: &Articulations<f64>,
    cfg: &Config,
    a: &Array<f64>,
    phi: &Array<f64>,
    tape: &mut Tape,
) -> Result<Vec<ArticulationState<f64>>, Error> {
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let w = 2.0 * std::f64::consts::PI * cfg.frequency;
    let mut states = vec![model.state()];
    for k in 0..steps {
        let control = ArticulationControl {
            target_q: Array::zeros(model.n_dof),
            ..model.control()
        };
        tape.launch(gait, 8, (a, phi, w, k as f64 * cfg.dt, &control.target_q));
        let next = model.step(tape, states.last().unwrap(), Some(&control), cfg.dt)?;
        states.push(next);
    }
    Ok(states)
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let model = quadruped();
    let a = Array::from_vec(vec![0.2 * (1.0 + cfg.perturb); 8]);
    let phi = Array::from_vec((0..8).map(|j| 0.8 * j as f64).collect());
    let x = |s: &[ArticulationState<f64>]| s.last().unwrap().q.get(0) - s[0].q.get(0);
    let first = x(&rollout(&model, cfg, &a, &phi, &mut Tape::new())?);
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .progress(cfg.progress)
        .minimize(
            &Params::new()
                .bounded(&a, Bounds::between(-0.6, 0.6))
                .with(&phi),
            |tape| {
                let states = rollout(&model, cfg, &a, &phi, tape)?;
                let loss = Array::zeros(1);
                tape.launch(distance, 1, (&states.last().unwrap().q, &loss));
                losses::sum_of_squares(tape, &a, 1e-2, &loss);
                Ok(loss)
            },
        )?;
    let states = rollout(&model, cfg, &a, &phi, &mut Tape::new())?;
    let half = Config {
        dt: cfg.dt / 2.0,
        duration: cfg.duration,
        frequency: cfg.frequency,
        max_iters: 0,
        progress: false,
        perturb: cfg.perturb,
    };
    let distance_half_dt = x(&rollout(&model, &half, &a, &phi, &mut Tape::new())?);
    let path = states
        .iter()
        .enumerate()
        .map(|(k, s)| (k as f64 * cfg.dt, s.q.get(0), s.q.get(1), s.q.get(2)))
        .collect();
    Ok(Outcome {
        path,
        distance_half_dt,
        report,
        distance: (first, x(&states)),
        lowest: states
            .iter()
            .map(|s| s.q.get(2))
            .fold(f64::INFINITY, f64::min),
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
        "torso moved {:.3} m along x in {} s ({:.3} m at half the time step; first guess {:.3} \
         m; lowest torso height {:.3} m) ({:.1} s)",
        out.distance.1,
        cfg.duration,
        out.distance_half_dt,
        out.distance.0,
        out.lowest,
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/quadruped_gait");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.report.losses(),
            "quadruped gait: L-BFGS on 8 amplitudes and 8 phases",
        )?;
    }
    // The torso's path: seen from above, and its height.
    let top: Vec<(f64, f64)> = out.path.iter().map(|p| (p.1, p.2)).collect();
    let x: Vec<(f64, f64)> = out.path.iter().map(|p| (p.0, p.1)).collect();
    let z: Vec<(f64, f64)> = out.path.iter().map(|p| (p.0, p.3)).collect();
    for file in ["path.svg", "path.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "quadruped gait: the torso's path seen from above",
            "x (m)",
            "y (m)",
            &[("torso", &top[..])],
        )?;
    }
    for file in ["progress.svg", "progress.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "quadruped gait: torso position along x and height",
            "time (s)",
            "m",
            &[("x", &x[..]), ("height", &z[..])],
        )?;
    }
    println!(
        "pictures: {}/{{loss, path, progress}}.{{svg, png}}",
        dir.display()
    );
    Ok(())
}
