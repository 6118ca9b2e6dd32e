//! System identification by second-order methods, beside L-BFGS: the 20 spring stiffnesses
//! of a hanging net recovered from a recorded trajectory.
//!
//! A 3 x 3 net of point masses (two top corners pinned), joined by 12 structural and 8 shear springs,
//! is pushed and swings under gravity. A "real" run with hidden stiffnesses records the
//! positions every 5 steps; from a uniform guess, four methods fit the 20 values by matching
//! the recorded frames (the residuals `x_sim - x_recorded`, the loss `½ |r|²`):
//! - L-BFGS on the loss's gradient (one forward and one backward pass per evaluation);
//! - Gauss-Newton and Levenberg-Marquardt on matrix-free Gauss-Newton products
//!   (`Tape::gauss_newton`: a tangent and an adjoint pass each), `Optimizer::least_squares`;
//! - Newton-CG with a trust region on Hessian-vector products by forward over reverse, the
//!   simulation run in `Dual` (`adflex::runtime::second_order`), `Optimizer::minimize_newton`.
//!
//! Then the inverse-design demo's cable (`examples/inverse_design.rs`: rest lengths for which
//! the equilibrium is a target parabola) by the same four methods; its products go through the
//! equilibrium solve by the implicit function theorem (a Gauss-Newton product is a tangent and
//! an adjoint linear solve; a Hessian-vector product adds the theorem's second-order term),
//! and by a fifth: Gauss-Newton by the KKT system (`Optimizer::least_squares_kkt`, the
//! formulation of sparse Gauss-Newton), which solves for the step, the positions' change and
//! the equilibrium's multipliers at once, on the constraint `statics::net_force`.
//!
//! The charts are the loss against passes over the simulation (forward, backward or tangent
//! sweeps; for the cable, equilibrium solves and linear solves), the cost measure the methods
//! share.
//!
//! Run: `cargo run --release --example second_order`

use adflex::kernels::losses;
use adflex::kernels::statics::{self, Equilibrium};
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;

#[path = "inverse_design.rs"]
#[allow(dead_code)]
pub mod inverse_design;

/// What the demo runs.
pub struct Config {
    /// Simulated time (s), step (s), and a recorded frame every `every` steps.
    pub duration: f64,
    pub dt: f64,
    pub every: usize,
    /// Iterations at most per method, and the loss at which each stops.
    pub max_iters: usize,
    pub target_loss: f64,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 1.0,
            dt: 2e-3,
            every: 5,
            max_iters: 400,
            target_loss: 1e-18,
            progress: true,
        }
    }
    /// The test's size.
    pub fn small() -> Self {
        Config {
            duration: 0.4,
            dt: 4e-3,
            every: 5,
            max_iters: 300,
            target_loss: 1e-18,
            progress: false,
        }
    }
}

/// The hidden stiffness of spring `k` (N/m).
pub fn true_ke(k: usize) -> f64 {
    60.0 + 90.0 * (((k * 7) % 11) as f64 / 10.0)
}

/// The hidden damping of spring `k` (N s/m).
pub fn true_kd(k: usize) -> f64 {
    let _ = k;
    GUESS_KD
}

/// The guess every method starts from: stiffness (N/m) and damping (N s/m).
pub const GUESS_KE: f64 = 100.0;
pub const GUESS_KD: f64 = 0.05;

/// One method's run.
pub struct Run {
    pub name: &'static str,
    pub report: Report,
    /// The largest relative error of the recovered stiffnesses.
    pub worst_relative_error: f64,
}

/// What the demo found.
pub struct Outcome {
    pub runs: Vec<Run>,
    /// Residuals (recorded frames x particles x 3; the two pinned ones' are zero).
    pub residuals: usize,
}

/// The net with stiffnesses `ke` and dampings `kd`, in any scalar.
fn net<R: Real>(ke: &[f64], kd: &[f64]) -> Model<R> {
    let l = |x: f64| R::lit(x);
    let mut b = ModelBuilder::<R>::new();
    let n = 3;
    for r in 0..n {
        for c in 0..n {
            let x = Vec3::new(l(0.3 * c as f64), l(-0.3 * r as f64), l(0.0));
            // Pushed sideways and out of plane, so that every spring stretches.
            let v = Vec3::new(
                l(0.8 * r as f64 * (c as f64 - 1.0)),
                l(0.0),
                l(1.2 * r as f64 - 0.4 * c as f64),
            );
            // The top corners pinned.
            let m = if r == 0 && c != 1 {
                0.0
            } else {
                0.05 + 0.02 * c as f64
            };
            b.add_particle(x, v, l(m));
        }
    }
    let id = |r: usize, c: usize| (r * n + c) as u32;
    let mut pairs = Vec::new();
    for r in 0..n {
        for c in 0..n {
            if c + 1 < n {
                pairs.push((id(r, c), id(r, c + 1)));
            }
            if r + 1 < n {
                pairs.push((id(r, c), id(r + 1, c)));
            }
            if r + 1 < n && c + 1 < n {
                pairs.push((id(r, c), id(r + 1, c + 1)));
                pairs.push((id(r, c + 1), id(r + 1, c)));
            }
        }
    }
    for (k, (i, j)) in pairs.into_iter().enumerate() {
        b.add_spring(i, j, l(ke[k]), l(kd[k]));
    }
    b.finalize()
}

/// The number of springs of the net.
pub const SPRINGS: usize = 20;

/// `out[i] = x[i] - recorded[i]`.
#[diff_kernel]
fn difference<R: Real>(x: &Array<Vec3<R>>, recorded: &Array<Vec3<R>>, out: &Array<Vec3<R>>) {
    let i = tid();
    out[i] = x[i] - recorded[i];
}

/// Records the rollout on `tape` and returns one residual array per recorded frame.
fn residuals<R: Real>(
    model: &Model<R>,
    cfg: &Config,
    recorded: &[Array<Vec3<R>>],
    tape: &mut Tape,
) -> Result<Vec<Array<Vec3<R>>>, Error> {
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let mut s = model.state();
    let mut out = Vec::new();
    for t in 1..=steps {
        s = SemiImplicitEuler.step(model, tape, &s, None, R::lit(cfg.dt))?;
        if t % cfg.every == 0 {
            let r = Array::<Vec3<R>>::zeros(s.x.len());
            tape.launch(
                difference,
                s.x.len(),
                (&s.x, &recorded[t / cfg.every - 1], &r),
            );
            out.push(r);
        }
    }
    Ok(out)
}

/// `½ |r|²` of the residuals, recorded on `tape`.
fn loss<R: Real>(
    model: &Model<R>,
    cfg: &Config,
    recorded: &[Array<Vec3<R>>],
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let loss = Array::<R>::zeros(1);
    for r in residuals(model, cfg, recorded, tape)? {
        tape.launch(
            adflex::kernels::losses::sum_sq_vec3,
            r.len(),
            (&r, R::lit(0.5), &loss),
        );
    }
    Ok(loss)
}

/// The recorded frames of the "real" run, in `R`.
fn record<R: Real>(cfg: &Config) -> Result<Vec<Array<Vec3<R>>>, Error> {
    let truth: Model<f64> = net(
        &(0..SPRINGS).map(true_ke).collect::<Vec<_>>(),
        &(0..SPRINGS).map(true_kd).collect::<Vec<_>>(),
    );
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let mut s = truth.state();
    let mut frames = Vec::new();
    for t in 1..=steps {
        s = SemiImplicitEuler.step(&truth, &mut Tape::new(), &s, None, cfg.dt)?;
        if t % cfg.every == 0 {
            let x: Vec<Vec3<R>> = s.x.to_vec().iter().map(|p| p.map(R::lit)).collect();
            frames.push(Array::from_vec(x));
        }
    }
    Ok(frames)
}

/// The largest relative error of the stiffnesses and dampings `ke`, `kd`.
fn worst_error(ke: &[f64], kd: &[f64]) -> f64 {
    let e = |v: &[f64], t: fn(usize) -> f64| {
        v.iter()
            .enumerate()
            .map(|(k, v)| (v / t(k) - 1.0).abs())
            .fold(0.0, f64::max)
    };
    e(ke, true_ke).max(e(kd, true_kd))
}

fn optimizer<'a>(cfg: &Config, o: Optimizer<'a>) -> Optimizer<'a> {
    o.max_iters(cfg.max_iters)
        .target_loss(cfg.target_loss)
        .progress(cfg.progress)
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let (ke0, kd0) = (vec![GUESS_KE; SPRINGS], vec![GUESS_KD; SPRINGS]);
    let rec64 = record::<f64>(cfg)?;
    let mut runs = Vec::new();

    let model: Model<f64> = net(&ke0, &kd0);
    let ke = model.param::<f64>("springs", "ke")?;
    let kd = model.param::<f64>("springs", "kd")?;
    let params = Params::new().with(&ke);
    let report = optimizer(cfg, Optimizer::lbfgs())
        .minimize(&params, |tape| loss(&model, cfg, &rec64, tape))?;
    runs.push(Run {
        name: "L-BFGS",
        worst_relative_error: worst_error(&ke.to_vec(), &kd.to_vec()),
        report,
    });

    for (name, o) in [
        ("Gauss-Newton", Optimizer::gauss_newton()),
        ("Levenberg-Marquardt", Optimizer::levenberg_marquardt()),
    ] {
        ke.assign(&ke0);
        kd.assign(&kd0);
        let report = optimizer(cfg, o)
            .least_squares(&params, |tape| residuals(&model, cfg, &rec64, tape))?;
        runs.push(Run {
            name,
            worst_relative_error: worst_error(&ke.to_vec(), &kd.to_vec()),
            report,
        });
    }

    let recd = record::<Dual>(cfg)?;
    let dual: Model<Dual> = net(&ke0, &kd0);
    let ke_d = dual.param::<Dual>("springs", "ke")?;
    let kd_d = dual.param::<Dual>("springs", "kd")?;
    let report = optimizer(cfg, Optimizer::newton_cg())
        .minimize_newton(&Params::new().with(&ke_d), |tape| {
            loss(&dual, cfg, &recd, tape)
        })?;
    let re = |a: &Array<Dual>| a.to_vec().iter().map(|k| k.re).collect::<Vec<_>>();
    runs.push(Run {
        name: "Newton-CG",
        worst_relative_error: worst_error(&re(&ke_d), &re(&kd_d)),
        report,
    });
    Ok(Outcome {
        runs,
        residuals: rec64.len() * rec64[0].len() * 3,
    })
}

/// The inverse-design cable of `cfg` fitted by L-BFGS, Gauss-Newton, Levenberg-Marquardt and
/// Newton-CG on the loss `½ |x* - target|²`, every method from the same rest lengths. Each run's
/// `worst_relative_error` is the largest distance from the target after it, relative to the
/// sag.
pub fn design(cfg: &inverse_design::Config, opt: &Config) -> Result<Vec<Run>, Error> {
    let sc = inverse_design::scene::<f64>(cfg)?;
    let rest0 = sc.rest.to_vec();
    let solver = Equilibrium::default();
    let n = sc.model.particle_count;
    let miss = |guess: &State<f64>| -> Result<f64, Error> {
        let x = solver.solve(&sc.model, &mut Tape::new(), guess)?.x.to_vec();
        Ok(x.iter()
            .zip(&sc.target)
            .map(|(a, b)| (*a - *b).norm())
            .fold(0.0, f64::max)
            / cfg.sag)
    };
    let mut runs = Vec::new();
    // Every solve warm starts from the last equilibrium.
    let mut guess = sc.first.deep_clone();
    // L-BFGS as the inverse-design demo runs it, with the rest lengths kept positive (its
    // line search's long trial steps otherwise reach equilibria the warm start cannot leave).
    let bounded = Params::new().bounded(&sc.rest, Bounds::positive());
    let report = optimizer(opt, Optimizer::lbfgs()).minimize(&bounded, |tape| {
        let eq = solver.solve(&sc.model, tape, &guess)?;
        guess = eq.deep_clone();
        let loss = Array::zeros(1);
        losses::frame_mismatch(tape, &eq.x, &sc.recorded, 0.5, &loss);
        Ok(loss)
    })?;
    runs.push(Run {
        name: "L-BFGS",
        worst_relative_error: miss(&guess)?,
        report,
    });
    // The same bounds for Gauss-Newton and Levenberg-Marquardt (kept by projection).
    for (name, o) in [
        ("Gauss-Newton", Optimizer::gauss_newton()),
        ("Levenberg-Marquardt", Optimizer::levenberg_marquardt()),
    ] {
        sc.rest.assign(&rest0);
        let mut guess = sc.first.deep_clone();
        let bounded = Params::new().bounded(&sc.rest, Bounds::positive());
        let report = optimizer(opt, o).least_squares(&bounded, |tape| {
            let eq = solver.solve(&sc.model, tape, &guess)?;
            guess = eq.deep_clone();
            let r = Array::<Vec3<f64>>::zeros(n);
            tape.launch(difference, n, (&eq.x, &sc.recorded, &r));
            Ok(r)
        })?;
        runs.push(Run {
            name,
            worst_relative_error: miss(&guess)?,
            report,
        });
    }
    // Gauss-Newton by the KKT system over the positions, the rest lengths and the
    // equilibrium's multipliers (sparse Gauss-Newton's formulation), on the constraint
    // `statics::net_force`.
    sc.rest.assign(&rest0);
    let mut guess = sc.first.deep_clone();
    // The fit has a residual (the pull): converged once the gradient is 1e-9 of the first.
    let kkt = optimizer(opt, Optimizer::kkt_gauss_newton()).grad_tol_rel(1e-9);
    let report = kkt.least_squares_kkt(
        &Params::new().with(&sc.rest),
        |tape| {
            let eq = solver.solve(&sc.model, tape, &guess)?;
            guess = eq.deep_clone();
            let r = Array::<Vec3<f64>>::zeros(n);
            tape.launch(difference, n, (&eq.x, &sc.recorded, &r));
            Ok((eq.x, r))
        },
        |tape, x| {
            let c = statics::net_force(&sc.model, tape, x)?;
            let r = Array::<Vec3<f64>>::zeros(n);
            tape.launch(difference, n, (x, &sc.recorded, &r));
            Ok((c, r))
        },
    )?;
    runs.push(Run {
        name: "Gauss-Newton (KKT)",
        worst_relative_error: miss(&guess)?,
        report,
    });
    // Newton-CG on the cable in `Dual`, warm started the same way.
    let sd = inverse_design::scene::<Dual>(cfg)?;
    let mut guess = sd.first.deep_clone();
    let report = optimizer(opt, Optimizer::newton_cg()).minimize_newton(
        &Params::new().with(&sd.rest),
        |tape| {
            let eq = solver.solve(&sd.model, tape, &guess)?;
            guess = eq.deep_clone();
            let loss = Array::<Dual>::zeros(1);
            losses::frame_mismatch(tape, &eq.x, &sd.recorded, Dual::constant(0.5), &loss);
            Ok(loss)
        },
    )?;
    let re = |v: Vec<Dual>| v.iter().map(|r| r.re).collect::<Vec<_>>();
    sc.rest.assign(&re(sd.rest.to_vec()));
    let last = State {
        x: Array::from_vec(guess.x.to_vec().iter().map(|p| p.map(|c| c.re)).collect()),
        v: Array::zeros(n),
        bodies: None,
    };
    runs.push(Run {
        name: "Newton-CG",
        worst_relative_error: miss(&last)?,
        report,
    });
    Ok(runs)
}

/// `out[i] = weight (p[i] - p0[i])`: a pull towards the nominal design.
#[diff_kernel]
fn regularization<R: Real>(p: &Array<R>, p0: &Array<R>, weight: R, out: &Array<R>) {
    let i = tid();
    out[i] = weight * (p[i] - p0[i]);
}

/// What the sheet's inverse design found ([`sheet`]).
pub struct Sheet {
    pub report: Report,
    /// Free particles and rest lengths (the design variables).
    pub free: usize,
    pub springs: usize,
    /// Unknowns of the KKT system's columns (state scalars and parameters) and its rows.
    pub unknowns: usize,
    pub rows: usize,
    /// Tangent sweeps of the first step (probing for the pattern, then one per colour and the
    /// check) and of a later one (one per colour, the check).
    pub first_sweeps: usize,
    pub later_sweeps: usize,
    /// Largest distance from the target shape (m) relative to the sag, before and after.
    pub initial_error: f64,
    pub final_error: f64,
    /// The net's height along its middle line `u = 0.5` (points `(v, y)`, m): the target
    /// shape, the first guess's equilibrium and the design's.
    pub profiles: [Vec<(f64, f64)>; 3],
}

impl std::fmt::Display for Sheet {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} free particles, {} rest lengths; the KKT system has {} rows and {} unknowns' \
             columns; sweeps of the first step {} (probing for the pattern), of a later one {} (one per \
             colour, the check's two and the recording); worst distance from the target / sag \
             {:.1e} -> {:.1e}; {}",
            self.free,
            self.springs,
            self.rows,
            self.unknowns,
            self.first_sweeps,
            self.later_sweeps,
            self.initial_error,
            self.final_error,
            self.report
        )
    }
}

/// Inverse design at a size the dense KKT system could not take: a square net of
/// `side + 1` x `side + 1` point masses (the border pinned; structural and shear springs)
/// hangs under gravity, and Gauss-Newton by the KKT system finds the springs' rest lengths for
/// which its equilibrium is a target shape (the equilibrium of hidden rest lengths: a sag
/// deeper on one side). The residuals are the free particles' distances from the target and a
/// weak pull (weight `1e-2`) of each rest length towards its start: there are more springs
/// than free coordinates.
pub fn sheet(side: usize, opt: &Config) -> Result<Sheet, Error> {
    let h = 1.0 / side as f64;
    let nodes = side + 1;
    let at = |i: usize, j: usize| (i * nodes + j) as u32;
    let build = |stretch: &dyn Fn(f64, f64) -> f64| -> Model<f64> {
        let mut b = ModelBuilder::<f64>::new();
        for i in 0..nodes {
            for j in 0..nodes {
                let border = i == 0 || j == 0 || i == side || j == side;
                let (u, v) = (i as f64 * h, j as f64 * h);
                // A shallow dome below the pins: the side the net hangs to.
                let y = -0.05 * (std::f64::consts::PI * u).sin() * (std::f64::consts::PI * v).sin();
                b.add_particle(
                    Vec3::new(u, y, v),
                    Vec3::zeros(),
                    if border { 0.0 } else { 0.01 },
                );
            }
        }
        let mut spring = |a: (usize, usize), c: (usize, usize)| {
            let length = h
                * (((a.0 as f64 - c.0 as f64).powi(2) + (a.1 as f64 - c.1 as f64).powi(2)).sqrt());
            let mid = ((a.0 + c.0) as f64 * h / 2.0, (a.1 + c.1) as f64 * h / 2.0);
            b.add_spring_with_rest(
                at(a.0, a.1),
                at(c.0, c.1),
                length * stretch(mid.0, mid.1),
                50.0,
                0.0,
            );
        };
        for i in 0..nodes {
            for j in 0..nodes {
                if i < side {
                    spring((i, j), (i + 1, j));
                }
                if j < side {
                    spring((i, j), (i, j + 1));
                }
                if i < side && j < side {
                    spring((i, j), (i + 1, j + 1));
                    spring((i + 1, j), (i, j + 1));
                }
            }
        }
        b.finalize()
    };
    let solver = Equilibrium::default();
    // The hidden design: rest lengths up to 4% longer, more so towards one side.
    let truth = build(&|u, v| 1.0 + 0.04 * (std::f64::consts::PI * u).sin() * v);
    let target = solver.solve(&truth, &mut Tape::new(), &truth.state())?.x;
    let model = build(&|_, _| 0.99);
    let rest = model.param::<f64>("springs", "rest")?;
    let rest0 = Array::from_vec(rest.to_vec());
    let (n, springs) = (model.particle_count, rest.len());
    let free = (side - 1) * (side - 1);
    let first = solver.solve(&model, &mut Tape::new(), &model.state())?;
    let sag = target.to_vec().iter().fold(0.0f64, |m, p| m.max(-p.y));
    let error = |x: &Array<Vec3<f64>>| -> f64 {
        x.to_vec()
            .iter()
            .zip(target.to_vec())
            .map(|(a, b)| (*a - b).norm())
            .fold(0.0, f64::max)
            / sag
    };
    let initial_error = error(&first.x);
    let profile = |x: &Array<Vec3<f64>>| -> Vec<(f64, f64)> {
        (0..nodes)
            .map(|j| (j as f64 * h, x.get(at(side / 2, j) as usize).y))
            .collect()
    };
    let residuals = |tape: &mut Tape, x: &Array<Vec3<f64>>| {
        let r = Array::<Vec3<f64>>::zeros(n).named("miss");
        tape.launch(difference, n, (x, &target, &r));
        let pull = Array::<f64>::zeros(springs).named("pull");
        tape.launch(regularization, springs, (&rest, &rest0, 1e-2, &pull));
        (r, pull)
    };
    let mut guess = first.deep_clone();
    // The fit has a residual (the pull): converged once the gradient is 1e-9 of the first.
    let kkt = optimizer(opt, Optimizer::kkt_gauss_newton()).grad_tol_rel(1e-9);
    let report = kkt.least_squares_kkt(
        &Params::new().with(&rest),
        |tape| {
            let eq = solver.solve(&model, tape, &guess)?;
            guess = eq.deep_clone();
            let r = residuals(tape, &eq.x);
            Ok((eq.x, r))
        },
        |tape, x| Ok((statics::net_force(&model, tape, x)?, residuals(tape, x))),
    )?;
    let final_error = error(&guess.x);
    let unknowns = 3 * n + springs;
    let sweeps: Vec<usize> = report.history.iter().map(|i| i.sweeps).collect();
    Ok(Sheet {
        report,
        free,
        springs,
        unknowns,
        // The residuals (3n + springs), the unknowns, the constraint's equations (3n).
        rows: 2 * unknowns + 3 * n,
        first_sweeps: sweeps.get(1).copied().unwrap_or(0),
        later_sweeps: match sweeps.len() {
            0..=2 => 0,
            _ => sweeps[2] - sweeps[1],
        },
        initial_error,
        final_error,
        profiles: [profile(&target), profile(&first.x), profile(&guess.x)],
    })
}

/// The first iteration of `report` whose loss is at most `level` (`None`: never).
fn first_at(report: &Report, level: f64) -> Option<&adflex::optim::Iteration> {
    report.history.iter().find(|i| i.loss <= level)
}

/// Passes of `report` until its loss first falls to `level` (`None`: never).
pub fn passes_to(report: &Report, level: f64) -> Option<usize> {
    first_at(report, level).map(|i| i.passes)
}

/// Seconds of `report` until its loss first falls to `level` (`None`: never).
pub fn seconds_to(report: &Report, level: f64) -> Option<f64> {
    first_at(report, level).map(|i| i.elapsed.as_secs_f64())
}

/// Prints the runs' passes and time to `level` and writes their charts, loss against passes
/// and against time, as `dir/name.{svg,png}` and `dir/name_time.{svg,png}`.
fn report(
    runs: &[Run],
    level: f64,
    dir: &std::path::Path,
    name: &str,
    title: &str,
) -> Result<(), Box<dyn std::error::Error>> {
    for r in runs {
        let sweeps = match r.report.sweeps {
            0 => String::new(),
            n => format!(" (+{n} constraint sweeps)"),
        };
        println!(
            "  {:<20} {:>6} passes{sweeps}, {} s to the level ({} passes to a millionth of it); \
             {:>4} iterations, {:>7.2} s; final loss {:.2e}, worst error {:.1e}; {}",
            r.name,
            passes_to(&r.report, level).map_or("never".into(), |p| p.to_string()),
            seconds_to(&r.report, level).map_or("never".into(), |t| format!("{t:.3}")),
            passes_to(&r.report, 1e-6 * level).map_or("never".into(), |p| p.to_string()),
            r.report.iterations,
            r.report.elapsed.as_secs_f64(),
            r.report.loss,
            r.worst_relative_error,
            r.report.stop
        );
    }
    // Each run's loss against `x` of its iterations.
    let curves = |x: fn(&adflex::optim::Iteration) -> f64| -> Vec<(&str, Vec<(f64, f64)>)> {
        runs.iter()
            .map(|r| {
                (
                    r.name,
                    r.report.history.iter().map(|i| (x(i), i.loss)).collect(),
                )
            })
            .collect()
    };
    let series = curves(|i| i.passes as f64);
    let timed = curves(|i| i.elapsed.as_secs_f64());
    let refs: Vec<(&str, &[(f64, f64)])> = series.iter().map(|(n, p)| (*n, &p[..])).collect();
    let timed: Vec<(&str, &[(f64, f64)])> = timed.iter().map(|(n, p)| (*n, &p[..])).collect();
    for ext in ["svg", "png"] {
        adflex::viz::plot::curves(
            dir.join(format!("{name}.{ext}")),
            title,
            "passes over the simulation",
            "loss",
            &refs,
        )?;
        adflex::viz::plot::curves(
            dir.join(format!("{name}_time.{ext}")),
            &title.replace("passes", "time"),
            "seconds",
            "loss",
            &timed,
        )?;
    }
    Ok(())
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let cfg = Config::full();
    let dir = std::path::Path::new("target/demos/second_order");
    std::fs::create_dir_all(dir)?;
    let out = run(&cfg)?;
    let l0 = out.runs[0].report.initial_loss;
    let level = 1e-10 * l0;
    println!(
        "identification: {} spring stiffnesses, {} residuals; loss {:.3e} at the guess; passes \
         to reach {:.1e} (1e-10 of it); worst error = largest relative stiffness error:",
        SPRINGS, out.residuals, l0, level
    );
    report(
        &out.runs,
        level,
        dir,
        "identification",
        "identification: loss against passes",
    )?;
    let runs = design(&inverse_design::Config::full(), &cfg)?;
    let l0 = runs[0].report.initial_loss;
    let level = 1e-10 * l0;
    println!(
        "inverse design: {} rest lengths; loss {:.3e} at the start; passes (equilibrium solves \
         and linear solves) to reach {:.1e}; worst error = largest distance from the target / \
         sag:",
        inverse_design::Config::full().segments,
        l0,
        level
    );
    report(
        &runs,
        level,
        dir,
        "design",
        "inverse design: loss against passes",
    )?;
    let sheet = sheet(30, &cfg)?;
    println!("inverse design of a sheet by the KKT system: {sheet}");
    let [target, first, found] = &sheet.profiles;
    // Steps: an iteration's loss is known once its sweeps are done.
    let history = &sheet.report.history;
    let sweeps: Vec<(f64, f64)> = (history.first().map(|i| (0.0, i.loss)).into_iter())
        .chain(history.windows(2).flat_map(|w| {
            let x = w[1].sweeps as f64;
            [(x, w[0].loss), (x, w[1].loss)]
        }))
        .collect();
    for ext in ["svg", "png"] {
        adflex::viz::plot::curves(
            dir.join(format!("sheet.{ext}")),
            "sheet: height along the middle line u = 0.5",
            "v (m)",
            "height (m)",
            &[
                ("first guess", &first[..]),
                ("designed (under the target)", &found[..]),
                ("target", &target[..]),
            ],
        )?;
        adflex::viz::plot::curves(
            dir.join(format!("sheet_loss.{ext}")),
            "sheet: Gauss-Newton by the KKT system, loss against tangent sweeps",
            "tangent sweeps",
            "loss",
            &[("KKT Gauss-Newton", &sweeps[..])],
        )?;
    }
    println!(
        "charts: {}/{{identification,design}}{{,_time}}.{{svg,png}}, sheet{{,_loss}}.{{svg,png}}",
        dir.display()
    );
    Ok(())
}
