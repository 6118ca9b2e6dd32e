//! Billiards: Adam optimizes the cue ball's initial position and velocity so that the object
//! ball ends at a destination after the collision, from a start where the cue ball *misses*
//! the object ball by 2 mm.
//!
//! With exact contact gradients (`leak = 0`), a miss has a gradient of exactly zero: the
//! optimizer stops at once. With the leaky preset (`ParticleContact::leaky`: pairs within a
//! tenth of a radius get a small fictitious stiffness in the adjoint only), the gradient
//! points towards the contact, and once the balls touch the true gradient takes over. The
//! final shot is checked with exact contact.
//!
//! Run: `cargo run --release --example billiards` (pictures in `target/demos/billiards/`).

use adflex::kernels::losses;
use adflex::optim::{Convergence, Optimizer, Params, Report, Stop};
use adflex::prelude::*;

pub const RADIUS: f64 = 0.0286;
pub const MASS: f64 = 0.17;

/// What the demo runs.
pub struct Config {
    pub duration: f64,
    pub dt: f64,
    pub destination: Vec3<f64>,
    pub iterations: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 1.5,
            dt: 1e-3,
            destination: Vec3::new(0.45, 0.0, -0.2),
            iterations: 200,
            progress: true,
        }
    }
    pub fn small() -> Self {
        Config {
            duration: 1.0,
            dt: 2e-3,
            destination: Vec3::new(0.3, 0.0, -0.12),
            iterations: 150,
            progress: false,
        }
    }
}

/// The table: the cue ball (0) aimed past the object ball (1) with a 2 mm gap, no gravity
/// (a top view in the x-z plane), light rolling drag.
fn table(leaky: bool, duration: f64) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    b.particle_radius = RADIUS;
    b.add_particle(
        Vec3::new(-0.5, 0.0, 2.0 * RADIUS + 0.002),
        Vec3::new(1.0, 0.0, 0.0),
        MASS,
    );
    b.add_particle(Vec3::zeros(), Vec3::zeros(), MASS);
    b.set_drag(Drag {
        kd: 0.03,
        wind: Vec3::zeros(),
    });
    let contact = ParticleContact {
        ke: 2e4,
        kd: ParticleContact::restitution_damping(2e4, 0.9, MASS / 2.0),
        mu: 0.0,
        ..ParticleContact::default()
    };
    b.set_particle_contact(if leaky {
        contact.leaky(RADIUS, MASS / 2.0, duration)
    } else {
        contact
    });
    b.finalize()
}

/// `x0[0] = cue[0]`, the other positions from `base`: the cue ball's state as a parameter.
#[diff_kernel]
fn place_cue(base: &Array<Vec3<f64>>, cue: &Array<Vec3<f64>>, out: &Array<Vec3<f64>>) {
    let i = tid();
    out[i] = select(i == 0, cue[0], base[i]);
}

/// The initial state with the cue ball's position and velocity from `cue_x`, `cue_v`.
fn initial(
    tape: &mut Tape,
    model: &Model<f64>,
    cue_x: &Array<Vec3<f64>>,
    cue_v: &Array<Vec3<f64>>,
) -> State<f64> {
    let s = model.state();
    let (x, v) = (Array::zeros(2), Array::zeros(2));
    tape.launch(place_cue, 2, (&s.x, cue_x, &x));
    tape.launch(place_cue, 2, (&s.v, cue_v, &v));
    State { x, v, bodies: None }
}

pub struct Attempt {
    pub report: Report,
    /// Object ball's distance from the destination with exact contact (m).
    pub miss: f64,
    pub frames: Vec<State<f64>>,
}

fn attempt(cfg: &Config, leaky: bool) -> Result<Attempt, Error> {
    let model = table(leaky, cfg.duration);
    let start = model.state();
    let cue_x = Array::from_vec(vec![start.x.get(0)]).named("cue_x");
    let cue_v = Array::from_vec(vec![start.v.get(0)]).named("cue_v");
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let report = Optimizer::adam(0.01)
        .max_iters(cfg.iterations)
        .progress(cfg.progress)
        .target_loss(1e-5)
        .minimize(&Params::new().with(&cue_x).with(&cue_v), |tape| {
            let s0 = initial(tape, &model, &cue_x, &cue_v);
            let end = SemiImplicitEuler.rollout(&model, tape, &s0, None, cfg.dt, steps)?;
            let loss = Array::zeros(1);
            losses::distance_to_target(tape, &end.x, &[1], cfg.destination, 1.0, &loss);
            Ok(loss)
        })?;
    // The shot found, replayed with exact contact.
    let exact = table(false, cfg.duration);
    let mut tape = Tape::new();
    let mut frames = vec![initial(&mut tape, &exact, &cue_x, &cue_v)];
    for _ in 0..steps {
        let next =
            SemiImplicitEuler.step(&exact, &mut tape, frames.last().unwrap(), None, cfg.dt)?;
        frames.push(next);
    }
    let miss = (frames.last().unwrap().x.get(1) - cfg.destination).norm();
    Ok(Attempt {
        report,
        miss,
        frames,
    })
}

pub struct Outcome {
    pub exact: Attempt,
    pub leaky: Attempt,
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    Ok(Outcome {
        exact: attempt(cfg, false)?,
        leaky: attempt(cfg, true)?,
    })
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    for (name, a) in [
        ("exact contact gradients", &out.exact),
        ("leaky contact gradients", &out.leaky),
    ] {
        println!("{name}: {}", a.report);
        println!("  object ball ends {:.4} m from the destination", a.miss);
    }
    if out.exact.report.stop == Stop::Converged(Convergence::GradientTolerance)
        && out.exact.report.iterations == 0
    {
        println!("exact: the miss has a zero gradient, so the optimizer cannot move");
    }
    let c = out.leaky.frames[0].x.get(0);
    let v = out.leaky.frames[0].v.get(0);
    println!(
        "leaky: cue ball from ({:.3}, {:.3}) at ({:.3}, {:.3}) m/s; object ball within {:.1} mm of the destination ({:.1} s)",
        c.x, c.z, v.x, v.z, 1e3 * out.leaky.miss, start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/billiards");
    std::fs::create_dir_all(dir)?;
    adflex::viz::plot::curves(
        dir.join("loss.svg"),
        "billiards: Adam from a miss",
        "iteration",
        "|object ball - destination|^2 (m^2)",
        &[
            (
                "exact gradients",
                &out.exact
                    .report
                    .losses()
                    .iter()
                    .enumerate()
                    .map(|(i, l)| (i as f64, *l))
                    .collect::<Vec<_>>(),
            ),
            (
                "leaky gradients",
                &out.leaky
                    .report
                    .losses()
                    .iter()
                    .enumerate()
                    .map(|(i, l)| (i as f64, *l))
                    .collect::<Vec<_>>(),
            ),
        ],
    )?;
    // A top view of the table: the destination, both balls' paths, the first guess (the
    // cue ball missing) as a ghost, the time and the result in the caption.
    use adflex::viz::overlay::{Ghost, Marker, Overlay, Region, Trail};
    use adflex::viz::render::{Camera, RenderOptions, Rgba};
    let model = table(false, cfg.duration);
    let frames = &out.leaky.frames;
    let mut cue = Trail::of(0);
    cue.color = Rgba::rgb(90, 90, 90);
    let felt = Rgba::rgb(196, 222, 196);
    let overlay = Overlay {
        markers: vec![Marker::target(cfg.destination, "destination")],
        trails: vec![cue, Trail::of(1)],
        regions: vec![Region::rect_xz((-0.7, 0.7), (-0.45, 0.3), -RADIUS, felt)],
        ghosts: vec![Ghost::of(
            out.exact.frames.last().unwrap(),
            "first guess (a miss), end",
        )],
        captions: (0..frames.len())
            .map(|k| {
                format!(
                    "t = {:.2} s | Adam: {} it., miss {:.1} mm",
                    k as f64 * cfg.dt,
                    out.leaky.report.iterations,
                    1e3 * out.leaky.miss
                )
            })
            .collect(),
        ..Overlay::default()
    };
    let options = RenderOptions {
        width: 720,
        height: 480,
        camera: Some(Camera::fit_with(
            &model,
            frames,
            &overlay,
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, -1.0),
        )),
        ..Default::default()
    };
    adflex::viz::render::render_gif_with(
        dir.join("billiards.gif"),
        &model,
        frames,
        &options,
        &overlay,
        25.0,
        40,
    )?;
    adflex::viz::render::render_png_with(
        dir.join("billiards.png"),
        &model,
        frames,
        frames.len() - 1,
        &options,
        &overlay,
    )?;
    println!(
        "pictures: {}/{{loss.svg, billiards.gif, billiards.png}}",
        dir.display()
    );
    Ok(())
}
