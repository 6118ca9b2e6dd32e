//! Rigid bodies, two ways.
//!
//! 1. The tennis racket theorem: a free body (principal inertia 1, 2, 3 kg m²) spun about its
//!    intermediate axis with a 1% perturbation flips over and back periodically; spun about
//!    the smallest or the largest axis it stays put. The demo reports the flip times and the
//!    energy drift.
//! 2. Optimization through rigid contact: Adam finds the initial velocity of a box, thrown
//!    from 30 cm up, so that it lands, slides on the ground with friction and comes to rest
//!    at a target 1 m away.
//!
//! Run: `cargo run --release --example rigid_body` (pictures in `target/demos/rigid_body/`).

use adflex::kernels::losses;
use adflex::optim::{Optimizer, Params, Report};
use adflex::prelude::*;

pub struct Config {
    /// Spin: duration (s) and step (s).
    pub spin_time: f64,
    pub spin_dt: f64,
    /// Throw: duration (s), step (s), Adam iterations.
    pub throw_time: f64,
    pub throw_dt: f64,
    pub iterations: usize,
    pub target: Vec3<f64>,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            spin_time: 40.0,
            spin_dt: 2e-3,
            throw_time: 1.5,
            throw_dt: 1e-3,
            iterations: 80,
            target: Vec3::new(1.0, 0.1, 0.3),
            progress: true,
        }
    }
    pub fn small() -> Self {
        Config {
            spin_time: 12.0,
            spin_dt: 4e-3,
            progress: false,
            ..Self::full()
        }
    }
}

const INERTIA: [f64; 3] = [1.0, 2.0, 3.0];

/// Body-frame angular velocity of body 0.
fn body_omega(s: &BodyState<f64>) -> Vec3<f64> {
    let q = nalgebra::UnitQuaternion::from_quaternion(s.q.get(0));
    q.inverse() * s.w.get(0)
}

/// One spin: the body-frame angular velocity over time, and the largest relative drift of
/// the kinetic energy.
pub struct Spin {
    pub omega: Vec<(f64, Vec3<f64>)>,
    pub energy_drift: f64,
}

fn spin(axis: usize, cfg: &Config) -> Result<Spin, Error> {
    let mut w = Vec3::new(0.01, 0.01, 0.01);
    w[axis] = 1.0;
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    let inertia = Mat33::from_diagonal(&Vec3::from(INERTIA));
    b.add_body(
        Vec3::zeros(),
        Quat::identity(),
        Vec3::zeros(),
        w,
        1.0,
        inertia,
    );
    let model = b.finalize();
    let energy = |w: &Vec3<f64>| 0.5 * (0..3).map(|k| INERTIA[k] * w[k] * w[k]).sum::<f64>();
    let e0 = energy(&w);
    let mut s = model.state();
    let mut out = Spin {
        omega: vec![(0.0, w)],
        energy_drift: 0.0,
    };
    let steps = (cfg.spin_time / cfg.spin_dt).round() as usize;
    for k in 0..steps {
        s = SemiImplicitEuler.step(&model, &mut Tape::new(), &s, None, cfg.spin_dt)?;
        let wb = body_omega(s.bodies.as_ref().expect("a body"));
        out.energy_drift = out.energy_drift.max((energy(&wb) - e0).abs() / e0);
        out.omega.push(((k + 1) as f64 * cfg.spin_dt, wb));
    }
    Ok(out)
}

/// Times (s) at which the spin component about `axis` changes sign.
pub fn flips(spin: &Spin, axis: usize) -> Vec<f64> {
    spin.omega
        .windows(2)
        .filter(|w| w[0].1[axis].signum() != w[1].1[axis].signum())
        .map(|w| w[1].0)
        .collect()
}

fn box_model(v0: Vec3<f64>) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let h = Vec3::new(0.2, 0.1, 0.15);
    let mass = 1.0;
    let inertia = Mat33::from_diagonal(&Vec3::new(
        h.y * h.y + h.z * h.z,
        h.x * h.x + h.z * h.z,
        h.x * h.x + h.y * h.y,
    )) * (mass / 3.0);
    let body = b.add_body(
        Vec3::new(0.0, 0.3, 0.0),
        Quat::identity(),
        v0,
        Vec3::zeros(),
        mass,
        inertia,
    );
    for sx in [-1.0, 1.0] {
        for sy in [-1.0, 1.0] {
            for sz in [-1.0, 1.0] {
                b.add_body_contact_point(body, Vec3::new(sx * h.x, sy * h.y, sz * h.z));
            }
        }
    }
    b.set_ground(Ground {
        ke: 2e4,
        kd: 200.0,
        mu: 0.5,
        ..Ground::default()
    });
    b.finalize()
}

pub struct Throw {
    pub report: Report,
    /// The box's distance from the target at the end (m), and its speed (m/s).
    pub miss: f64,
    pub speed: f64,
    pub initial_miss: f64,
    pub frames: Vec<State<f64>>,
    /// Where the first guess's throw ends.
    pub first_guess: State<f64>,
    pub model: Model<f64>,
}

fn throw(cfg: &Config) -> Result<Throw, Error> {
    let model = box_model(Vec3::new(1.0, 0.0, 0.0));
    let s0 = model.state();
    let v0 = s0.bodies.as_ref().expect("a body").v.clone().named("v0");
    let steps = (cfg.throw_time / cfg.throw_dt).round() as usize;
    let rollout =
        |tape: &mut Tape| SemiImplicitEuler.rollout(&model, tape, &s0, None, cfg.throw_dt, steps);
    let end_of = |s: &State<f64>| s.bodies.as_ref().expect("a body").x.get(0);
    let first_guess = rollout(&mut Tape::new())?;
    let initial_miss = (end_of(&first_guess) - cfg.target).norm();
    let report = Optimizer::adam(0.05)
        .max_iters(cfg.iterations)
        .progress(cfg.progress)
        .target_loss(1e-5)
        .minimize(&Params::new().with(&v0), |tape| {
            let end = rollout(tape)?;
            let loss = Array::zeros(1);
            let bodies = end.bodies.as_ref().expect("a body");
            losses::body_distance_to_target(tape, bodies, 0, cfg.target, 1.0, &loss);
            Ok(loss)
        })?;
    let mut frames = vec![s0.clone()];
    for _ in 0..steps {
        let next = SemiImplicitEuler.step(
            &model,
            &mut Tape::new(),
            frames.last().unwrap(),
            None,
            cfg.throw_dt,
        )?;
        frames.push(next);
    }
    let last = frames.last().unwrap().bodies.as_ref().expect("a body");
    Ok(Throw {
        report,
        miss: (last.x.get(0) - cfg.target).norm(),
        speed: last.v.get(0).norm(),
        initial_miss,
        frames,
        first_guess,
        model,
    })
}

pub struct Outcome {
    /// Spins about the smallest, intermediate and largest axes.
    pub spins: [Spin; 3],
    pub throw: Throw,
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    Ok(Outcome {
        spins: [spin(0, cfg)?, spin(1, cfg)?, spin(2, cfg)?],
        throw: throw(cfg)?,
    })
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    for (axis, name) in ["smallest", "intermediate", "largest"].iter().enumerate() {
        let s = &out.spins[axis];
        let f = flips(s, axis);
        println!(
            "spin about the {name} axis: {} flips in {} s{}; energy drift {:.1e}",
            f.len(),
            cfg.spin_time,
            if f.is_empty() {
                String::new()
            } else {
                format!(" (at {:.1?} s)", f)
            },
            s.energy_drift
        );
    }
    let t = &out.throw;
    let v = t.frames[0].bodies.as_ref().unwrap().v.get(0);
    println!("throw: {}", t.report);
    println!(
        "throw: initial velocity ({:.3}, {:.3}, {:.3}) m/s; the box rests {:.1} mm from the target (first guess: {:.0} mm), speed {:.1e} m/s ({:.1} s)",
        v.x, v.y, v.z, 1e3 * t.miss, 1e3 * t.initial_miss, t.speed, start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/rigid_body");
    std::fs::create_dir_all(dir)?;
    let s = &out.spins[1];
    let series: Vec<Vec<(f64, f64)>> = (0..3)
        .map(|k| {
            s.omega
                .iter()
                .step_by(10)
                .map(|(t, w)| (*t, w[k]))
                .collect()
        })
        .collect();
    adflex::viz::plot::curves(
        dir.join("flip.svg"),
        "spin about the intermediate axis: body-frame angular velocity",
        "time (s)",
        "rad/s",
        &[
            ("w_x (smallest)", &series[0]),
            ("w_y (intermediate)", &series[1]),
            ("w_z (largest)", &series[2]),
        ],
    )?;
    adflex::viz::plot::loss_curve(
        dir.join("loss.svg"),
        &t.report.losses(),
        "throw a box to a target: Adam",
    )?;
    // The target, where the first guess came to rest, the time and the result.
    use adflex::viz::overlay::{Ghost, Marker, Overlay};
    let overlay = Overlay {
        markers: vec![Marker::target(cfg.target, "target")],
        ghosts: vec![Ghost::of(&t.first_guess, "first guess, end")],
        captions: (0..t.frames.len())
            .map(|k| {
                format!(
                    "t = {:.2} s | Adam: {} it., miss {:.1} mm",
                    k as f64 * cfg.throw_dt,
                    t.report.iterations,
                    1e3 * t.miss
                )
            })
            .collect(),
        ..Overlay::default()
    };
    let options = adflex::viz::render::RenderOptions {
        width: 720,
        height: 480,
        ..Default::default()
    };
    adflex::viz::render::render_gif_with(
        dir.join("throw.gif"),
        &t.model,
        &t.frames,
        &options,
        &overlay,
        25.0,
        40,
    )?;
    adflex::viz::render::render_png_with(
        dir.join("throw.png"),
        &t.model,
        &t.frames,
        t.frames.len() - 1,
        &options,
        &overlay,
    )?;
    println!(
        "pictures: {}/{{flip.svg, loss.svg, throw.gif, throw.png}}",
        dir.display()
    );
    Ok(())
}
