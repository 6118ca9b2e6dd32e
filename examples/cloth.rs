//! Cloth: Adam finds the initial velocity of a square of cloth (12 x 12 particles, springs and
//! bending, unpinned), tossed from 1 m up, so that it lands with its centre of mass on a
//! target spot on the ground after 1.2 seconds (each velocity component bounded by 4 m/s).
//! The loss is the horizontal miss: where the cloth lies, not how it folded. Adam rather than
//! L-BFGS: the landing (contact, friction, folding) makes the loss rough at small scales,
//! which stalls L-BFGS's line search.
//!
//! Run: `cargo run --release --example cloth` (pictures in `target/demos/cloth/`).

use adflex::kernels::losses;
use adflex::kernels::scenes::cloth::ClothGrid;
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;

pub struct Config {
    pub n: usize,
    pub duration: f64,
    pub dt: f64,
    pub target: Vec3<f64>,
    pub iterations: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            n: 12,
            duration: 1.2,
            dt: 1e-3,
            target: Vec3::new(1.0, 0.0, -0.4),
            iterations: 100,
            progress: true,
        }
    }
    pub fn small() -> Self {
        Config {
            n: 6,
            dt: 2e-3,
            progress: false,
            ..Self::full()
        }
    }
}

fn sheet(n: usize) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.particle_radius = 0.01;
    b.add_cloth_grid(&ClothGrid {
        ni: n,
        nj: n,
        origin: Vec3::new(-0.25, 1.0, -0.25),
        spacing: 0.5 / (n - 1) as f64,
        pinned: Vec::new(),
        spring_ke: 200.0,
        ..ClothGrid::default()
    });
    // Damping in contact only, for a bounce with restitution 0.2 (with the dFlex default the
    // ground's damping would also brake these 10 g particles in the air).
    b.set_ground(Ground {
        ke: 1e3,
        kd: ParticleContact::restitution_damping(1e3, 0.2, 0.01),
        mu: 0.5,
        damp_approach: false,
        ..Ground::default()
    });
    b.finalize()
}

/// `loss += (c.x - target.x)^2 + (c.z - target.z)^2`: the horizontal miss of a point (the
/// height at the end is the cloth's business: it lands, bounces and folds).
#[diff_kernel]
fn horizontal_miss(c: &Array<Vec3<f64>>, target: Vec3<f64>, loss: &Array<f64>) {
    let d = c[0] - target;
    loss.atomic_add(0, d.x * d.x + d.z * d.z);
}

/// The loss: the horizontal distance of the centre of mass from the target, squared.
fn record_loss(
    tape: &mut Tape,
    x: &Array<Vec3<f64>>,
    weights: &Array<f64>,
    target: Vec3<f64>,
) -> Array<f64> {
    let c = losses::center_of_mass(tape, x, weights);
    let loss = Array::zeros(1);
    tape.launch(horizontal_miss, 1, (&c, target, &loss));
    loss
}

/// `v[i] = u[0]`: one initial velocity for every particle.
#[diff_kernel]
fn broadcast(u: &Array<Vec3<f64>>, v: &Array<Vec3<f64>>) {
    v[tid()] = u[0];
}

fn initial(tape: &mut Tape, model: &Model<f64>, u: &Array<Vec3<f64>>) -> State<f64> {
    let s = model.state();
    let v = Array::zeros(s.x.len());
    tape.launch(broadcast, s.x.len(), (u, &v));
    State {
        x: s.x,
        v,
        bodies: None,
    }
}

pub struct Outcome {
    pub report: Report,
    /// Distance of the centre of mass from the target at the end (m), first and last.
    pub initial_miss: f64,
    pub miss: f64,
    pub frames: Vec<State<f64>>,
    /// Where the first guess's toss ends.
    pub first_guess: State<f64>,
    pub model: Model<f64>,
    pub velocity: Vec3<f64>,
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let model = sheet(cfg.n);
    let weights = losses::mass_weights(&model);
    let u = Array::from_vec(vec![Vec3::new(0.5, 1.0, 0.0)]).named("v0");
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let com_miss = |frames_end: &State<f64>| {
        let c = losses::center_of_mass(&mut Tape::new(), &frames_end.x, &weights).get(0);
        ((c.x - cfg.target.x).powi(2) + (c.z - cfg.target.z).powi(2)).sqrt()
    };
    let simulate = |u: &Array<Vec3<f64>>| -> Result<Vec<State<f64>>, Error> {
        let mut tape = Tape::new();
        let mut frames = vec![initial(&mut tape, &model, u)];
        for _ in 0..steps {
            let next = SemiImplicitEuler.step(
                &model,
                &mut Tape::new(),
                frames.last().unwrap(),
                None,
                cfg.dt,
            )?;
            frames.push(next);
        }
        Ok(frames)
    };
    let first_guess = simulate(&u)?.pop().expect("a state");
    let initial_miss = com_miss(&first_guess);
    let report = Optimizer::adam(0.1)
        .max_iters(cfg.iterations)
        .progress(cfg.progress)
        .target_loss(1e-5)
        .minimize(
            &Params::new().bounded(&u, Bounds::between(-4.0, 4.0)),
            |tape| {
                let s0 = initial(tape, &model, &u);
                let end = SemiImplicitEuler.rollout(&model, tape, &s0, None, cfg.dt, steps)?;
                Ok(record_loss(tape, &end.x, &weights, cfg.target))
            },
        )?;
    let frames = simulate(&u)?;
    Ok(Outcome {
        report,
        initial_miss,
        miss: com_miss(frames.last().unwrap()),
        frames,
        first_guess,
        model,
        velocity: u.get(0),
    })
}

/// Gradient check of the loss w.r.t. the initial velocity.
pub fn fd_check(cfg: &Config, u0: Vec3<f64>) -> adflex::runtime::gradcheck::Report {
    let model = sheet(cfg.n);
    let weights = losses::mass_weights(&model);
    let u = Array::from_vec(vec![u0]).named("v0");
    let steps = (cfg.duration / cfg.dt).round() as usize;
    adflex::runtime::gradcheck::GradCheck::new()
        .run(
            |tape| {
                let s0 = initial(tape, &model, &u);
                let end = SemiImplicitEuler
                    .rollout(&model, tape, &s0, None, cfg.dt, steps)
                    .unwrap();
                record_loss(tape, &end.x, &weights, cfg.target)
            },
            &[&u],
        )
        .unwrap()
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    println!("{}", out.report);
    let v = out.velocity;
    println!(
        "toss at ({:.3}, {:.3}, {:.3}) m/s: the cloth's centre of mass lands {:.1} mm from the target (first guess {:.0} mm) ({:.1} s)",
        v.x, v.y, v.z, 1e3 * out.miss, 1e3 * out.initial_miss, start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/cloth");
    std::fs::create_dir_all(dir)?;
    adflex::viz::plot::loss_curve(
        dir.join("loss.svg"),
        &out.report.losses(),
        "cloth toss: Adam on the initial velocity",
    )?;
    // The landing target, a corner's path, where the first guess landed, the speed.
    use adflex::viz::overlay::{ColorBy, Colormap, Ghost, Marker, Overlay, Trail, Values};
    let overlay = Overlay {
        markers: vec![Marker::target(cfg.target, "target (centre of mass)")],
        trails: vec![Trail::of(0)],
        ghosts: vec![Ghost::of(&out.first_guess, "first guess, end")],
        color_by: Some(ColorBy::new(
            Values::Speed,
            (0.0, 4.0),
            Colormap::Sequential,
            "speed (m/s)",
        )),
        captions: (0..out.frames.len())
            .map(|k| {
                format!(
                    "t = {:.2} s | Adam: {} it., miss {:.1} mm",
                    k as f64 * cfg.dt,
                    out.report.iterations,
                    1e3 * out.miss
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
        dir.join("cloth.gif"),
        &out.model,
        &out.frames,
        &options,
        &overlay,
        25.0,
        40,
    )?;
    adflex::viz::render::render_png_with(
        dir.join("cloth.png"),
        &out.model,
        &out.frames,
        out.frames.len() - 1,
        &options,
        &overlay,
    )?;
    println!(
        "pictures: {}/{{loss.svg, cloth.gif, cloth.png}}",
        dir.display()
    );
    Ok(())
}
