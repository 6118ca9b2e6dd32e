//! A pendulum (1 kg on a 1 m rod, released at 60 degrees, in light air drag) with its rod as a
//! stiff spring (`ke = 1e4` N/m: the rod's own vibration has `omega = 100` rad/s) under
//! explicit, semi-implicit and midpoint (RK2) steps, implicit Euler (full Newton, linearized,
//! and with the drag explicit), and with the rod as an XPBD distance constraint. For each method
//! and time step it reports whether the energy stays bounded, and compares with the theory of
//! each method on the oscillator `x'' = -omega^2 x`:
//!
//! - explicit Euler multiplies the energy by `1 + (omega dt)^2` every step: it always fails
//!   (the demo measures the growth rate once it dominates);
//! - semi-implicit (symplectic) Euler is stable for `omega dt < 2`, i.e. `dt < 0.02` s here;
//! - midpoint multiplies the rod mode's energy by `1 + (omega dt)^4 / 4` every step: it fails
//!   once that growth over the run is large (here beyond `dt` of about 2 ms);
//! - implicit Euler is stable for every `dt` (it damps), linearized (one Newton step) too;
//!   with the drag explicit (`gamma = kd / m`) it keeps the limit `gamma dt < 2 + (omega dt)^2
//!   / 2`, far away here;
//! - XPBD has no rod vibration at all (a constraint) and is stable for every `dt`.
//!
//! Run: `cargo run --release --example stiff_pendulum`.

use adflex::prelude::*;

pub const KE: f64 = 1e4;
pub const MASS: f64 = 1.0;
pub const LENGTH: f64 = 1.0;
pub const G: f64 = 9.81;
/// Air drag on the bob (N s/m).
pub const DRAG: f64 = 0.02;

/// What the demo runs.
pub struct Config {
    /// Simulated time (s).
    pub duration: f64,
    /// The time steps tried (s).
    pub dts: Vec<f64>,
}

impl Config {
    pub fn full() -> Self {
        Config {
            duration: 10.0,
            dts: vec![1e-3, 5e-3, 1e-2, 1.5e-2, 1.9e-2, 2.1e-2, 3e-2, 5e-2],
        }
    }
    pub fn small() -> Self {
        Config {
            duration: 2.0,
            dts: vec![1e-2, 1.9e-2, 2.1e-2, 5e-2],
        }
    }
}

/// The methods compared.
pub const METHODS: [&str; 7] = [
    "explicit Euler",
    "semi-implicit Euler",
    "midpoint",
    "implicit Euler",
    "linearized implicit Euler",
    "implicit Euler, drag explicit",
    "XPBD",
];

/// One run: a method at a time step.
pub struct Run {
    pub method: &'static str,
    pub dt: f64,
    /// max over time of E(t) / E(0) (infinite if it blew up or the solver failed).
    pub max_energy_ratio: f64,
    /// E(end) / E(0).
    pub final_energy_ratio: f64,
    /// (t, E(t) / E(0)) every few steps.
    pub energy: Vec<(f64, f64)>,
    /// An error the integrator returned, if any.
    pub error: Option<String>,
    /// The energy's growth factor per step once it grows exponentially (measured between
    /// the steps it passes 10 E0 and 1e5 E0), if it does.
    pub growth_per_step: Option<f64>,
}

impl Run {
    /// Stable: the energy never grew by more than 50%.
    pub fn stable(&self) -> bool {
        self.error.is_none() && self.max_energy_ratio < 1.5
    }
}

/// Explicit Euler's predicted energy growth per step, `1 + (omega dt)^2` (the rod's mode
/// dominates once it grows).
pub fn predicted_growth(dt: f64) -> f64 {
    let w = (KE / MASS).sqrt() * dt;
    1.0 + w * w
}

/// What theory predicts for `method` at `dt` over `duration` seconds: stable or not.
pub fn predicted_stable(method: &str, dt: f64, duration: f64) -> bool {
    let z = (KE / MASS).sqrt() * dt;
    match method {
        "explicit Euler" => false,
        "semi-implicit Euler" => z < 2.0,
        // The rod mode starts with about 1e-4 of the energy (the bob's weight stretches it):
        // growth by more than 100x over the run shows.
        "midpoint" => (duration / dt) * (1.0 + z.powi(4) / 4.0).ln() < 100f64.ln(),
        "implicit Euler, drag explicit" => DRAG / MASS * dt < 2.0 + z * z / 2.0,
        _ => true,
    }
}

fn pendulum(constraint: bool) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let pivot = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    let a = 60f64.to_radians();
    let bob = b.add_particle(
        Vec3::new(LENGTH * a.sin(), -LENGTH * a.cos(), 0.0),
        Vec3::zeros(),
        MASS,
    );
    if constraint {
        b.add_distance_constraint(pivot, bob, 0.0);
    } else {
        b.add_spring(pivot, bob, KE, 0.0);
    }
    b.set_drag(Drag {
        kd: DRAG,
        wind: Vec3::zeros(),
    });
    b.finalize()
}

/// Total energy (J), zero potential at the lowest point of the swing.
fn energy(model: &Model<f64>, s: &State<f64>) -> f64 {
    let (x, v) = (s.x.get(1), s.v.get(1));
    let spring = model.elastic_energy(&mut Tape::new(), s, None).get(0);
    0.5 * MASS * v.norm_squared() + MASS * G * (x.y + LENGTH) + spring
}

fn simulate(method: &'static str, dt: f64, duration: f64) -> Run {
    let model = pendulum(method == "XPBD");
    let steps = (duration / dt).round() as usize;
    let mut s = model.state();
    let e0 = energy(&model, &s);
    let mut run = Run {
        method,
        dt,
        max_energy_ratio: 1.0,
        final_energy_ratio: 1.0,
        energy: vec![(0.0, 1.0)],
        error: None,
        growth_per_step: None,
    };
    let mut passed_10: Option<(usize, f64)> = None;
    let every = (steps / 400).max(1);
    for k in 0..steps {
        // A fresh tape per step: no gradient is needed here.
        let mut tape = Tape::new();
        let next = match method {
            "explicit Euler" => ExplicitEuler.step(&model, &mut tape, &s, None, dt),
            "semi-implicit Euler" => SemiImplicitEuler.step(&model, &mut tape, &s, None, dt),
            "midpoint" => Midpoint.step(&model, &mut tape, &s, None, dt),
            "implicit Euler" => ImplicitEuler::default().step(&model, &mut tape, &s, None, dt),
            "linearized implicit Euler" => {
                ImplicitEuler::linearized().step(&model, &mut tape, &s, None, dt)
            }
            "implicit Euler, drag explicit" => ImplicitEuler::default()
                .with_explicit(["drag"])
                .step(&model, &mut tape, &s, None, dt),
            _ => Xpbd::default().step(&model, &mut tape, &s, None, dt),
        };
        s = match next {
            Ok(s) => s,
            Err(e) => {
                run.error = Some(e.to_string());
                run.max_energy_ratio = f64::INFINITY;
                break;
            }
        };
        let r = energy(&model, &s) / e0;
        let r = if r.is_finite() { r } else { f64::INFINITY };
        run.max_energy_ratio = run.max_energy_ratio.max(r);
        run.final_energy_ratio = r;
        if r > 10.0 && passed_10.is_none() {
            passed_10 = Some((k, r));
        }
        if let (Some((k1, r1)), None) = (passed_10, run.growth_per_step) {
            if r > 1e5 && k > k1 {
                run.growth_per_step = Some(((r / r1).ln() / (k - k1) as f64).exp());
            }
        }
        if (k + 1) % every == 0 {
            run.energy.push(((k + 1) as f64 * dt, r.min(1e6)));
        }
        if r > 1e6 {
            break; // blown up
        }
    }
    run
}

pub struct Outcome {
    pub runs: Vec<Run>,
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let mut runs = Vec::new();
    for method in METHODS {
        for &dt in &cfg.dts {
            runs.push(simulate(method, dt, cfg.duration));
        }
    }
    Ok(Outcome { runs })
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    let omega = (KE / MASS).sqrt();
    println!(
        "rod omega = {omega} rad/s; semi-implicit Euler's limit dt < 2 / omega = {} s",
        2.0 / omega
    );
    println!(
        "{:<29} {:>7} {:>8} {:>10} {:>10} {:>8} {:>8} {:>14}",
        "method", "dt (s)", "omega dt", "max E/E0", "end E/E0", "measured", "theory", "growth/step"
    );
    let mut agree = 0;
    for r in &out.runs {
        let measured = if r.stable() { "stable" } else { "FAILS" };
        let theory = if predicted_stable(r.method, r.dt, cfg.duration) {
            "stable"
        } else {
            "fails"
        };
        agree += (r.stable() == predicted_stable(r.method, r.dt, cfg.duration)) as usize;
        let doubling = match (r.method, r.growth_per_step) {
            ("explicit Euler", Some(g)) => format!("{g:.3} (theory {:.3})", predicted_growth(r.dt)),
            ("midpoint", Some(g)) => {
                let z = omega * r.dt;
                format!("{g:.3} (theory {:.3})", 1.0 + z.powi(4) / 4.0)
            }
            (_, Some(g)) => format!("{g:.3}"),
            (_, None) => "-".to_string(),
        };
        println!(
            "{:<29} {:>7} {:>8.2} {:>10.2e} {:>10.2e} {:>8} {:>8} {:>14}",
            r.method,
            r.dt,
            omega * r.dt,
            r.max_energy_ratio,
            r.final_energy_ratio,
            measured,
            theory,
            doubling
        );
    }
    println!(
        "measured stability agrees with theory in {agree} of {} runs ({:.1} s)",
        out.runs.len(),
        start.elapsed().as_secs_f64()
    );
    // The energy of each method at dt = 0.015 s (omega dt = 1.5) and at 0.021 s (2.1).
    let dir = std::path::Path::new("target/demos/stiff_pendulum");
    std::fs::create_dir_all(dir)?;
    for dt in [0.015, 0.021] {
        let series: Vec<(String, &[(f64, f64)])> = out
            .runs
            .iter()
            .filter(|r| r.dt == dt)
            .map(|r| (r.method.to_string(), &r.energy[..]))
            .collect();
        let series: Vec<(&str, &[(f64, f64)])> =
            series.iter().map(|(n, e)| (n.as_str(), *e)).collect();
        let file = dir.join(format!("energy_dt_{dt}.svg"));
        adflex::viz::plot::curves(
            &file,
            &format!("stiff pendulum, dt = {dt} s (omega dt = {:.1})", omega * dt),
            "time (s)",
            "E / E0",
            &series,
        )?;
        println!("plot: {}", file.display());
    }
    Ok(())
}
