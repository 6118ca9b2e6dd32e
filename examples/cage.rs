//! The field's first demo: a mass-spring cage (a free particle joined to the 26 pinned points
//! of a lattice around it) whose springs' rest lengths L-BFGS optimizes so that the centre
//! comes to rest at a target after 2 seconds.
//!
//! Run: `cargo run --release --example cage` (pictures in `target/demos/cage/`).

use adflex::kernels::{losses, scenes::cage};
use adflex::optim::{Optimizer, Params, Report};
use adflex::prelude::*;

/// What the demo runs.
pub struct Config {
    /// Simulated time (s) and step (s).
    pub duration: f64,
    pub dt: f64,
    pub target: Vec3<f64>,
    pub max_iters: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 2.0,
            dt: 1e-2,
            target: Vec3::new(0.2, -0.15, 0.1),
            max_iters: 20,
            progress: true,
        }
    }
    /// The test's size (the same: the demo takes well under a second).
    pub fn small() -> Self {
        Config {
            progress: false,
            ..Self::full()
        }
    }
}

/// What it found.
pub struct Outcome {
    pub report: Report,
    pub scene: cage::CageScene<f64>,
    /// The centre's trajectory with the optimized rest lengths.
    pub frames: Vec<State<f64>>,
    /// The last state with the first guess (the initial rest lengths).
    pub first_guess: State<f64>,
    /// Distance of the centre from the target at the end (m).
    pub miss: f64,
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let scene = cage::build::<f64>(cage::Cage::default());
    let model = &scene.model;
    let rest = model.param::<f64>("springs", "rest")?;
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let rollout = |tape: &mut Tape| -> Result<Vec<State<f64>>, Error> {
        let mut frames = vec![model.state()];
        for _ in 0..steps {
            let next = SemiImplicitEuler.step(model, tape, frames.last().unwrap(), None, cfg.dt)?;
            frames.push(next);
        }
        Ok(frames)
    };
    let first_guess = rollout(&mut Tape::new())?.pop().expect("a state");
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .grad_tol(1e-9)
        .progress(cfg.progress)
        .minimize(&Params::new().with(&rest), |tape| loss(&scene, cfg, tape))?;
    let frames = rollout(&mut Tape::new())?;
    let miss = (frames.last().unwrap().x.get(scene.center as usize) - cfg.target).norm();
    Ok(Outcome {
        report,
        scene,
        frames,
        first_guess,
        miss,
    })
}

/// The loss: the centre's squared distance from the target at the end of the rollout.
fn loss(scene: &cage::CageScene<f64>, cfg: &Config, tape: &mut Tape) -> Result<Array<f64>, Error> {
    let model = &scene.model;
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let end = SemiImplicitEuler.rollout(model, tape, &model.state(), None, cfg.dt, steps)?;
    let loss = Array::zeros(1);
    losses::distance_to_target(tape, &end.x, &[scene.center], cfg.target, 1.0, &loss);
    Ok(loss)
}

/// The optimizers side by side on the same problem from the same first guess, each given
/// `evals` loss evaluations (a rollout and its gradient each): `(name, report)`.
pub fn compare(cfg: &Config, evals: usize) -> Result<Vec<(&'static str, Report)>, Error> {
    let methods: [(&'static str, Optimizer); 3] = [
        ("L-BFGS", Optimizer::lbfgs()),
        ("Adam (lr 0.01)", Optimizer::adam(0.01)),
        (
            "gradient descent (lr 0.1)",
            Optimizer::gradient_descent(0.1),
        ),
    ];
    let mut out = Vec::new();
    for (name, optimizer) in methods {
        let scene = cage::build::<f64>(cage::Cage::default());
        let rest = scene.model.param::<f64>("springs", "rest")?;
        let report = optimizer
            .max_evals(evals)
            .max_iters(evals)
            .grad_tol(1e-12)
            .minimize(&Params::new().with(&rest), |tape| loss(&scene, cfg, tape))?;
        out.push((name, report));
    }
    Ok(out)
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    for it in &out.report.history {
        println!(
            "iteration {:2}: loss {:.3e}, |grad| {:.2e}",
            it.iter, it.loss, it.grad_norm
        );
    }
    println!("{}", out.report);
    let c = out.frames.last().unwrap().x.get(out.scene.center as usize);
    println!(
        "centre at t = {} s: ({:.4}, {:.4}, {:.4}), target ({:.4}, {:.4}, {:.4}): miss {:.2e} m ({:.1} s)",
        cfg.duration,
        c.x,
        c.y,
        c.z,
        cfg.target.x,
        cfg.target.y,
        cfg.target.z,
        out.miss,
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/cage");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.report.losses(),
            "cage: L-BFGS on 26 rest lengths",
        )?;
    }
    // The optimizers compared: loss against rollouts (loss and gradient evaluations).
    let runs = compare(&cfg, 40)?;
    let curves: Vec<(&str, Vec<(f64, f64)>)> = runs
        .iter()
        .map(|(name, r)| {
            let pts = r.history.iter().map(|it| (it.evaluations as f64, it.loss));
            (*name, pts.collect())
        })
        .collect();
    for (name, r) in &runs {
        println!(
            "{name}: loss {:.2e} after {} evaluations ({})",
            r.loss, r.evaluations, r.stop
        );
    }
    let series: Vec<(&str, &[(f64, f64)])> = curves.iter().map(|(n, p)| (*n, &p[..])).collect();
    for file in ["optimizers.svg", "optimizers.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "cage: three optimizers on the same 26 rest lengths",
            "rollouts (loss and gradient evaluations)",
            "loss (m^2)",
            &series,
        )?;
    }
    // The target, the centre's path, the first guess's end state behind the result, the
    // springs coloured by strain (red stretched, blue compressed) and the time.
    use adflex::viz::overlay::{ColorBy, Colormap, Ghost, Marker, Overlay, Trail, Values};
    let model = &out.scene.model;
    let last = out.report.history.last();
    let overlay = Overlay {
        markers: vec![Marker::target(cfg.target, "target")],
        trails: vec![Trail::of(out.scene.center as usize)],
        ghosts: vec![Ghost::of(&out.first_guess, "first guess, t = 2 s")],
        color_by: Some(ColorBy::new(
            Values::EdgeStrain,
            (-0.2, 0.2),
            Colormap::Diverging,
            "spring strain",
        )),
        captions: (0..out.frames.len())
            .map(|k| {
                format!(
                    "t = {:.2} s | L-BFGS: {} it., loss {:.1e}",
                    k as f64 * cfg.dt,
                    last.map_or(0, |it| it.iter),
                    last.map_or(f64::NAN, |it| it.loss)
                )
            })
            .collect(),
        ..Overlay::default()
    };
    let options = adflex::viz::render::RenderOptions {
        width: 720,
        height: 540,
        ..Default::default()
    };
    let n = out.frames.len();
    adflex::viz::render::render_gif_with(
        dir.join("cage.gif"),
        model,
        &out.frames,
        &options,
        &overlay,
        25.0,
        4,
    )?;
    adflex::viz::render::render_png_with(
        dir.join("cage.png"),
        model,
        &out.frames,
        n - 1,
        &options,
        &overlay,
    )?;
    println!(
        "pictures: {}/{{loss, optimizers}}.{{svg, png}}, cage.gif, cage.png",
        dir.display()
    );
    Ok(())
}
