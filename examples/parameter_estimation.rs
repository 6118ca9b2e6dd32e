//! Real to sim: recover hidden physical parameters from a recorded trajectory alone.
//!
//! Three particles joined by three damped springs slide on a table with Coulomb friction.
//! A "real" run with the true spring stiffnesses `ke`, spring dampings `kd` and friction
//! coefficient `mu` records the positions every few steps; the simulator then starts from
//! wrong guesses (stiffness x2, damping x0.5, friction x2) and L-BFGS recovers all seven
//! values by matching the recorded trajectory, with a checkpointed rollout
//! (`adflex::runtime::checkpoint::Checkpointed`, memory O(sqrt T)) and the loss
//! `adflex::kernels::losses::frame_mismatch` on every k-th state.
//!
//! The library's ground friction is a scalar field, not a gradient target, so the friction
//! here is the example's own force: a `#[diff_kernel]` and an `impl Force` with `mu` as an
//! array. The table carries the particles' weight, so the model has no gravity and the
//! friction's normal force is `m g`: `f = -mu m g v_t / sqrt(|v_t|^2 + eps^2)` (smoothed
//! Coulomb friction, `v_t` the velocity along the table).
//!
//! Run: `cargo run --release --example parameter_estimation`

use adflex::kernels::forces::{Force, ForceContext, Param};
use adflex::kernels::losses;
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;
use adflex::runtime::checkpoint::Checkpointed;

/// Smoothed Coulomb friction of the table `y = const` on particle `i`: `-mu[0] weight[i] v_t /
/// sqrt(|v_t|^2 + eps^2)` (N), `weight = m g` the normal force.
#[diff_kernel]
fn table_friction(
    v: &Array<Vec3<f64>>,
    weight: &Array<f64>,
    mu: &Array<f64>,
    eps: f64,
    f: &Array<Vec3<f64>>,
) {
    let i = tid();
    let vt = vec3(v[i].x, 0.0, v[i].z);
    let s = sqrt(dot(vt, vt) + eps * eps);
    f.atomic_add(i, vt * (-(mu[0] * weight[i]) / s));
}

/// The friction force component: `mu` (one coefficient for the table) is its parameter array.
#[derive(Clone, Debug)]
pub struct TableFriction {
    /// Normal force on each particle (N): its weight.
    pub weight: Array<f64>,
    /// Friction coefficient (1), one element.
    pub mu: Array<f64>,
    /// Smoothing speed (m/s): below it friction fades like viscous damping.
    pub eps: f64,
}

impl Force<f64> for TableFriction {
    fn name(&self) -> &'static str {
        "table_friction"
    }
    fn eval(&self, cx: &ForceContext<'_, f64>, tape: &mut Tape, f: &Array<Vec3<f64>>) {
        tape.launch(
            table_friction,
            self.weight.len(),
            (cx.v, &self.weight, &self.mu, self.eps, f),
        );
    }
    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("mu", &mut self.mu);
    }
}

/// What the demo runs.
pub struct Config {
    /// Simulated time (s), step (s), and a recorded frame every `every` steps.
    pub duration: f64,
    pub dt: f64,
    pub every: usize,
    pub max_iters: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 2.0,
            dt: 1e-3,
            every: 10,
            max_iters: 400,
            progress: true,
        }
    }
    /// The test's size.
    pub fn small() -> Self {
        Config {
            duration: 1.0,
            dt: 2e-3,
            every: 5,
            max_iters: 300,
            progress: false,
        }
    }
}

/// The hidden values: per-spring stiffness (N/m) and damping (N s/m), table friction.
pub const TRUE_KE: [f64; 3] = [60.0, 90.0, 120.0];
pub const TRUE_KD: [f64; 3] = [0.4, 0.6, 0.3];
pub const TRUE_MU: f64 = 0.25;

/// What it found.
pub struct Outcome {
    pub report: Report,
    /// `(name, true, recovered)` for every parameter.
    pub values: Vec<(String, f64, f64)>,
    /// The largest relative error of the recovered values.
    pub worst_relative_error: f64,
    /// The recorded ("real") frames and the simulation with the recovered values.
    pub recorded: Vec<State<f64>>,
    pub frames: Vec<State<f64>>,
}

/// The scene with the given parameters.
fn scene(ke: &[f64], kd: &[f64], mu: f64) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros(); // the table carries the weight
    let m = [0.1, 0.15, 0.12];
    let x = [
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(0.5, 0.0, 0.0),
        Vec3::new(0.2, 0.0, 0.4),
    ];
    // Thrown sideways and spinning, the springs stretched and compressed.
    let v = [
        Vec3::new(2.0, 0.0, -1.0),
        Vec3::new(-1.0, 0.0, 2.5),
        Vec3::new(0.5, 0.0, -2.0),
    ];
    for k in 0..3 {
        b.add_particle(x[k], v[k], m[k]);
    }
    let rest = [0.4, 0.5, 0.35];
    for (s, (i, j)) in [(0, 1), (1, 2), (2, 0)].into_iter().enumerate() {
        b.add_spring_with_rest(i, j, rest[s], ke[s], kd[s]);
    }
    b.add_force(TableFriction {
        weight: Array::from_vec(m.iter().map(|m| m * 9.8).collect()),
        mu: Array::from_vec(vec![mu]),
        eps: 0.01,
    });
    b.finalize()
}

/// Every state of a rollout, without gradients.
fn simulate(model: &Model<f64>, cfg: &Config, steps: usize) -> Result<Vec<State<f64>>, Error> {
    let mut frames = vec![model.state()];
    for _ in 0..steps {
        let mut tape = Tape::new();
        let next =
            SemiImplicitEuler.step(model, &mut tape, frames.last().unwrap(), None, cfg.dt)?;
        frames.push(next);
    }
    Ok(frames)
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let steps = (cfg.duration / cfg.dt).round() as usize;
    // The "real" run, recorded every `every` steps.
    let truth = scene(&TRUE_KE, &TRUE_KD, TRUE_MU);
    let all = simulate(&truth, cfg, steps)?;
    let recorded: Vec<State<f64>> = all.iter().step_by(cfg.every).cloned().collect();

    // The simulator, from wrong guesses.
    let model = scene(
        &TRUE_KE.map(|k| 2.0 * k),
        &TRUE_KD.map(|k| 0.5 * k),
        2.0 * TRUE_MU,
    );
    let ke = model.param::<f64>("springs", "ke")?;
    let kd = model.param::<f64>("springs", "kd")?;
    let mu = model.param::<f64>("table_friction", "mu")?;
    let params = Params::new()
        .bounded(&ke, Bounds::positive())
        .bounded(&kd, Bounds::positive())
        .bounded(&mu, Bounds::positive());
    let s0 = model.state();
    let dt = cfg.dt;
    let every = cfg.every;
    let scale = 1.0 / recorded.len() as f64;
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .grad_tol(1e-14)
        .target_loss(1e-16)
        .progress(cfg.progress)
        .minimize_with(&params, || {
            let out = Checkpointed::new(steps).run(
                &s0,
                |tape, s, _t| SemiImplicitEuler.step(&model, tape, s, None, dt),
                |tape, s, t, acc| {
                    if t % every == 0 {
                        losses::frame_mismatch(tape, &s.x, &recorded[t / every].x, scale, acc);
                    }
                    Ok(())
                },
            )?;
            Ok(out.loss.get(0))
        })?;

    let mut values = Vec::new();
    for (name, arr, truth) in [
        ("ke", &ke, TRUE_KE.to_vec()),
        ("kd", &kd, TRUE_KD.to_vec()),
        ("mu", &mu, vec![TRUE_MU]),
    ] {
        for (k, (t, r)) in truth.iter().zip(arr.to_vec()).enumerate() {
            values.push((format!("{name}[{k}]"), *t, r));
        }
    }
    let worst_relative_error = values
        .iter()
        .fold(0.0f64, |m, (_, t, r)| m.max((r - t).abs() / t.abs()));
    let frames = simulate(&model, cfg, steps)?;
    Ok(Outcome {
        report,
        values,
        worst_relative_error,
        recorded,
        frames,
    })
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    println!("{}", out.report);
    println!(
        "{:>8} {:>10} {:>10} {:>10}",
        "", "true", "recovered", "rel. err"
    );
    for (name, t, r) in &out.values {
        println!(
            "{name:>8} {t:>10.4} {r:>10.4} {:>10.2e}",
            (r - t).abs() / t.abs()
        );
    }
    println!(
        "worst relative error {:.2e} after {} L-BFGS iterations ({} rollouts of {} steps, {:.1} s)",
        out.worst_relative_error,
        out.report.iterations,
        out.report.evaluations,
        (cfg.duration / cfg.dt).round(),
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/parameter_estimation");
    std::fs::create_dir_all(dir)?;
    adflex::viz::plot::loss_curve(
        dir.join("loss.svg"),
        &out.report.losses(),
        "real to sim: L-BFGS on the trajectory mismatch",
    )?;
    // Particle 0's x coordinate: the recording and the simulation with the recovered values.
    let t_rec: Vec<(f64, f64)> = out
        .recorded
        .iter()
        .enumerate()
        .map(|(k, s)| ((k * cfg.every) as f64 * cfg.dt, s.x.get(0).x))
        .collect();
    let t_sim: Vec<(f64, f64)> = out
        .frames
        .iter()
        .enumerate()
        .map(|(k, s)| (k as f64 * cfg.dt, s.x.get(0).x))
        .collect();
    adflex::viz::plot::curves(
        dir.join("trajectory.svg"),
        "recorded vs simulated with the recovered parameters",
        "time (s)",
        "x of particle 0 (m)",
        &[("recorded", &t_rec), ("recovered", &t_sim)],
    )?;
    println!("pictures: {}/{{loss.svg, trajectory.svg}}", dir.display());
    Ok(())
}
