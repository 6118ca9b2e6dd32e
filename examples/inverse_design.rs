//! Inverse design in quasistatics: a cable of point masses joined by springs, pinned at both
//! ends, hangs under gravity; L-BFGS finds the springs' rest lengths for which its
//! equilibrium is a target curve (a parabola of a given sag, which a chain of equal masses at
//! equal horizontal spacing can take exactly).
//!
//! Each loss evaluation solves the equilibrium `f(x*; rest) = 0` with
//! `adflex::kernels::statics::Equilibrium` (Newton, matrix-free CG on the tangent kernels),
//! warm started from the previous one, and its gradient comes from the implicit function
//! theorem: one adjoint linear solve per evaluation, no unrolled solver.
//!
//! Run: `cargo run --release --example inverse_design`

use adflex::kernels::losses;
use adflex::kernels::statics::Equilibrium;
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;

/// What the demo runs.
pub struct Config {
    /// Segments of the cable (particles: `segments + 1`, the two ends pinned).
    pub segments: usize,
    /// Distance between the pins (m) and the target's sag at mid-span (m).
    pub span: f64,
    pub sag: f64,
    /// Mass of each free particle (kg) and spring stiffness (N/m).
    pub mass: f64,
    pub ke: f64,
    pub max_iters: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            segments: 60,
            span: 2.0,
            sag: 0.6,
            mass: 0.02,
            ke: 400.0,
            max_iters: 300,
            progress: true,
        }
    }
    /// The test's size.
    pub fn small() -> Self {
        Config {
            segments: 12,
            max_iters: 150,
            progress: false,
            ..Self::full()
        }
    }
}

/// What it found.
pub struct Outcome {
    pub report: Report,
    pub model: Model<f64>,
    /// The target curve (one point per particle).
    pub target: Vec<Vec3<f64>>,
    /// The equilibrium with the initial rest lengths, and with the optimized ones.
    pub frames: Vec<State<f64>>,
    /// RMS distance of the equilibrium from the target over the particles (m), before and
    /// after.
    pub initial_error: f64,
    pub final_error: f64,
    /// The largest distance after (m).
    pub final_max_error: f64,
    /// The optimized rest lengths (m).
    pub rest: Vec<f64>,
}

/// The parabola of sag `sag` through the pins, at equal horizontal spacing.
fn parabola(cfg: &Config) -> Vec<Vec3<f64>> {
    (0..=cfg.segments)
        .map(|i| {
            let s = i as f64 / cfg.segments as f64;
            Vec3::new(s * cfg.span, -4.0 * cfg.sag * s * (1.0 - s), 0.0)
        })
        .collect()
}

/// RMS and largest distance between two frames (m).
fn errors(x: &[Vec3<f64>], target: &[Vec3<f64>]) -> (f64, f64) {
    let d: Vec<f64> = x
        .iter()
        .zip(target)
        .map(|(a, b)| (*a - *b).norm())
        .collect();
    let rms = (d.iter().map(|d| d * d).sum::<f64>() / d.len() as f64).sqrt();
    (rms, d.iter().fold(0.0, |m: f64, d| m.max(*d)))
}

/// The cable with its initial rest lengths, the target, and the equilibrium it starts from,
/// in any scalar (`Dual` for Newton-CG in `examples/second_order.rs`).
pub struct Scene<R: Real> {
    pub model: Model<R>,
    /// The springs' rest lengths: the design variables.
    pub rest: Array<R>,
    pub target: Vec<Vec3<f64>>,
    pub recorded: Array<Vec3<R>>,
    pub first: State<R>,
}

pub fn scene<R: Real>(cfg: &Config) -> Result<Scene<R>, Error> {
    let n = cfg.segments;
    let l = R::lit;
    let h = cfg.span / n as f64;
    // The cable starts as a shallow curve (the side it hangs to), with every rest length the
    // straight span's share: taut, it sags far less than the target.
    let mut b = ModelBuilder::<R>::new();
    for i in 0..=n {
        let s = i as f64 / n as f64;
        let m = if i == 0 || i == n { 0.0 } else { cfg.mass };
        b.add_particle(
            Vec3::new(l(s * cfg.span), l(-0.1 * s * (1.0 - s)), l(0.0)),
            Vec3::zeros(),
            l(m),
        );
    }
    for i in 0..n as u32 {
        b.add_spring_with_rest(i, i + 1, l(h), l(cfg.ke), l(0.0));
    }
    let model = b.finalize();
    let rest = model.param::<R>("springs", "rest")?;
    let target = parabola(cfg);
    let recorded = Array::from_vec(target.iter().map(|p| p.map(l)).collect());
    let first = Equilibrium::default().solve(&model, &mut Tape::new(), &model.state())?;
    Ok(Scene {
        model,
        rest,
        target,
        recorded,
        first,
    })
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let Scene {
        model,
        rest,
        target,
        recorded,
        first,
    } = scene::<f64>(cfg)?;
    let solver = Equilibrium::default();
    let (initial_error, _) = errors(&first.x.to_vec(), &target);

    // Warm start every solve from the last equilibrium.
    let mut guess = first.deep_clone();
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .grad_tol(1e-12)
        .target_loss(1e-14)
        .progress(cfg.progress)
        .minimize(&Params::new().bounded(&rest, Bounds::positive()), |tape| {
            let eq = solver.solve(&model, tape, &guess)?;
            guess = eq.deep_clone();
            let loss = Array::zeros(1);
            losses::frame_mismatch(tape, &eq.x, &recorded, 1.0, &loss);
            Ok(loss)
        })?;
    // `rest` holds the best values found.
    let last = solver.solve(&model, &mut Tape::new(), &guess)?;
    let (final_error, final_max_error) = errors(&last.x.to_vec(), &target);
    Ok(Outcome {
        report,
        rest: rest.to_vec(),
        model,
        target,
        frames: vec![first, last],
        initial_error,
        final_error,
        final_max_error,
    })
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    println!("{}", out.report);
    let (lo, hi) = out
        .rest
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), r| {
            (lo.min(*r), hi.max(*r))
        });
    println!(
        "cable of {} springs, target: parabola of sag {} m over {} m; rest lengths now {:.4}..{:.4} m \
         (were {:.4} m)",
        cfg.segments,
        cfg.sag,
        cfg.span,
        lo,
        hi,
        cfg.span / cfg.segments as f64
    );
    println!(
        "shape error (RMS over particles): {:.3e} m -> {:.3e} m (x{:.1e} smaller; largest {:.2e} m) \
         in {} L-BFGS iterations, {} equilibrium solves ({:.1} s)",
        out.initial_error,
        out.final_error,
        out.initial_error / out.final_error,
        out.final_max_error,
        out.report.iterations,
        out.report.evaluations,
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/inverse_design");
    std::fs::create_dir_all(dir)?;
    let profile = |xs: &[Vec3<f64>]| xs.iter().map(|p| (p.x, p.y)).collect::<Vec<_>>();
    adflex::viz::plot::curves(
        dir.join("shape.svg"),
        "inverse design: the cable's equilibrium against the target",
        "x (m)",
        "y (m)",
        &[
            ("target parabola", &profile(&out.target)),
            (
                "equilibrium, initial rest lengths",
                &profile(&out.frames[0].x.to_vec()),
            ),
            (
                "equilibrium, optimized",
                &profile(&out.frames[out.frames.len() - 1].x.to_vec()),
            ),
        ],
    )?;
    adflex::viz::plot::loss_curve(
        dir.join("loss.svg"),
        &out.report.losses(),
        "inverse design: L-BFGS",
    )?;
    println!("pictures: {}/{{shape.svg, loss.svg}}", dir.display());
    Ok(())
}
