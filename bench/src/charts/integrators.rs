//! Charts 1 and 2: the integrators of `adflex_kernels::integrators` on a mass-spring
//! oscillator with an exact solution (`kernels/tests/common/oscillator.rs`).

// The kernels' tests' fixture, shared by path (it is not part of the library's API).
#[path = "../../../kernels/tests/common/oscillator.rs"]
#[allow(dead_code)]
mod oscillator;

use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Midpoint, Rk4, SemiImplicitEuler, Xpbd,
};
use adflex_kernels::prelude::Drag;
use adflex_runtime::{Tape, Vec3};
use oscillator::{Oscillator, Trajectory, REST_LENGTH};
use serde_json::json;

use super::plot::{Chart, Series, Style};

/// The integrators compared, by name, with whether they run on the XPBD constraint model.
pub fn integrators() -> Vec<(&'static str, Box<dyn Integrator<f64>>, bool)> {
    vec![
        ("explicit Euler", Box::new(ExplicitEuler), false),
        ("semi-implicit Euler", Box::new(SemiImplicitEuler), false),
        ("midpoint (RK2)", Box::new(Midpoint), false),
        ("RK4", Box::new(Rk4), false),
        ("implicit Euler", Box::new(ImplicitEuler::default()), false),
        (
            "linearized implicit Euler",
            Box::new(ImplicitEuler::linearized()),
            false,
        ),
        ("XPBD (8 substeps)", Box::new(Xpbd::default()), true),
    ]
}

fn simulate(
    osc: &Oscillator,
    integ: &dyn Integrator<f64>,
    xpbd: bool,
    dt: f64,
    steps: usize,
) -> Trajectory {
    if xpbd {
        osc.simulate_model(&osc.constraint_model(), integ, dt, steps)
    } else {
        osc.simulate_model(&osc.model(), integ, dt, steps)
    }
}

/// Chart 1: error at t = 1 s against wall time per simulated second, over a range of dt.
pub fn error_vs_cost(
    out: &std::path::Path,
    quick: bool,
) -> Result<serde_json::Value, Box<dyn std::error::Error>> {
    // k = 100 N/m, m = 1 kg: omega = 10 rad/s; c = 1 N s/m: damping ratio 0.05.
    let damped = Oscillator::new(100.0, 1.0, 1.0);
    let undamped = Oscillator::new(100.0, 1.0, 0.0);
    let steps_list: Vec<usize> = if quick {
        vec![16, 64, 256]
    } else {
        vec![8, 16, 32, 64, 128, 256, 512, 1024, 2048, 4096, 8192]
    };
    let mut chart = Chart::new(
        "Integrators: error at t = 1 s vs cost (damped spring, omega = 10 rad/s)",
        "wall time per simulated second (s)",
        "|u(1) - u_exact(1)| (m)",
    )
    .log_log();
    chart.note = Some(
        "dt = 1/steps, steps 8..8192. XPBD: distance constraint of compliance 1/k, no damping \
         (compared with the undamped exact solution). Time: best of 3, stepping only."
            .into(),
    );
    let mut data = Vec::new();
    for (c, (name, integ, xpbd)) in integrators().into_iter().enumerate() {
        let osc = if xpbd { undamped } else { damped };
        let (u_exact, _) = osc.exact(1.0);
        let mut pts = Vec::new();
        for &steps in &steps_list {
            let dt = 1.0 / steps as f64;
            let mut best = f64::INFINITY;
            let mut err = f64::NAN;
            for _ in 0..3 {
                let tr = simulate(&osc, integ.as_ref(), xpbd, dt, steps);
                best = best.min(tr.seconds);
                err = (tr.final_displacement() - u_exact).abs();
            }
            eprintln!("  {name}: dt {dt:.2e}: error {err:.3e}, {best:.3e} s per simulated s");
            data.push(json!({"integrator": name, "dt": dt, "omega_dt": dt * osc.omega(), "error": err, "seconds_per_simulated_second": best}));
            if err.is_finite() {
                pts.push((best, err));
            }
        }
        chart.series.push(Series::new(name, pts, Style::Line, c));
    }
    chart.write(&out.join("integrators_error_vs_cost.svg"))?;
    Ok(json!(data))
}

/// Whether `steps` steps of `dt` keep the energy below `limit` times the initial energy.
fn stable(
    osc: &Oscillator,
    integ: &dyn Integrator<f64>,
    xpbd: bool,
    dt: f64,
    steps: usize,
    limit: f64,
) -> bool {
    let tr = simulate(osc, integ, xpbd, dt, steps);
    let r = tr.max_energy_ratio();
    r.is_finite() && r <= limit
}

/// Chart 2: the largest stable dt against the spring stiffness, by bisection on log dt.
pub fn stability(
    out: &std::path::Path,
    quick: bool,
) -> Result<serde_json::Value, Box<dyn std::error::Error>> {
    const STEPS: usize = 300;
    const LIMIT: f64 = 1e3;
    const DT_MIN: f64 = 1e-7;
    const DT_MAX: f64 = 10.0;
    let ks: Vec<f64> = if quick {
        vec![1e2, 1e4]
    } else {
        vec![1e1, 1e2, 1e3, 1e4, 1e5, 1e6]
    };
    let iters = if quick { 8 } else { 16 };
    let mut chart = Chart::new(
        "Stability: largest stable dt vs spring stiffness (m = 1 kg, undamped)",
        "stiffness k (N/m)",
        "largest stable dt (s)",
    )
    .log_log();
    chart.note = Some(format!(
        "Stable: energy stays below {LIMIT:.0e} x initial over {STEPS} steps (bisection on log dt). \
         Points at {DT_MAX} s: no instability found (implicit Euler, linearized implicit Euler and XPBD, on top of each other). Explicit Euler and midpoint grow every step; their curves depend on the step count."
    ));
    let mut data = Vec::new();
    for (c, (name, integ, xpbd)) in integrators().into_iter().enumerate() {
        let mut pts = Vec::new();
        for &k in &ks {
            let osc = Oscillator::new(k, 1.0, 0.0);
            let dt = if stable(&osc, integ.as_ref(), xpbd, DT_MAX, STEPS, LIMIT) {
                DT_MAX
            } else if !stable(&osc, integ.as_ref(), xpbd, DT_MIN, STEPS, LIMIT) {
                f64::NAN
            } else {
                let (mut lo, mut hi) = (DT_MIN.ln(), DT_MAX.ln());
                for _ in 0..iters {
                    let mid = 0.5 * (lo + hi);
                    if stable(&osc, integ.as_ref(), xpbd, mid.exp(), STEPS, LIMIT) {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                lo.exp()
            };
            eprintln!(
                "  {name}: k {k:.0e}: dt_max {dt:.3e} (omega dt {:.3})",
                dt * osc.omega()
            );
            data.push(
                json!({"integrator": name, "k": k, "dt_max": dt, "omega_dt": dt * osc.omega()}),
            );
            pts.push((k, dt));
        }
        chart.series.push(Series::new(name, pts, Style::Line, c));
    }
    let theory: Vec<(f64, f64)> = ks.iter().map(|&k| (k, 2.0 / k.sqrt())).collect();
    chart.series.push(Series::new(
        "theory, semi-implicit Euler: omega dt = 2",
        theory,
        Style::Dashed,
        8,
    ));
    let rk4: Vec<(f64, f64)> = ks.iter().map(|&k| (k, 8f64.sqrt() / k.sqrt())).collect();
    chart.series.push(Series::new(
        "theory, RK4: omega dt = 2.83",
        rk4,
        Style::Dashed,
        6,
    ));
    chart.write(&out.join("integrators_stability.svg"))?;
    Ok(json!(data))
}

/// Chart 3: an implicit-explicit split (spring implicit, linear drag explicit) on a spring of
/// omega = 10 rad/s: the largest stable `gamma dt` (`gamma = c / m`) against `omega dt`, by
/// bisection, with the theory `gamma dt < 2 + (omega dt)^2 / 2` and the fully explicit
/// treatment of the drag alone (`gamma dt < 2`).
pub fn imex_stability(
    out: &std::path::Path,
    quick: bool,
) -> Result<serde_json::Value, Box<dyn std::error::Error>> {
    const STEPS: usize = 300;
    const LIMIT: f64 = 1e3;
    let zs: Vec<f64> = if quick {
        vec![0.5, 2.0]
    } else {
        vec![0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0]
    };
    let iters = if quick { 10 } else { 24 };
    // Released from 1 micrometre so that a growth of 1e3 in energy stays within the 1-D model.
    let osc = Oscillator {
        displacement: 1e-6,
        ..Oscillator::new(100.0, 1.0, 0.0)
    };
    let imex = ImplicitEuler::default().with_explicit(["drag"]);
    // Stepped here (not `Oscillator::simulate_model`) to stop at the first energy past the
    // limit: a diverged state later overflows the solve.
    let stable = |dt: f64, q: f64| {
        let mut model = osc.model();
        model.forces.push(Box::new(Drag {
            kd: q / dt,
            wind: Vec3::zeros(),
        }));
        let mut s = model.state();
        let energy =
            |s: &adflex_kernels::State<f64>| osc.energy(s.x.get(1).x - REST_LENGTH, s.v.get(1).x);
        let e0 = energy(&s);
        for _ in 0..STEPS {
            s = match imex.step(&model, &mut Tape::new(), &s, None, dt) {
                Ok(s) => s,
                Err(_) => return false,
            };
            let r = energy(&s) / e0;
            if r.is_nan() || r > LIMIT {
                return false;
            }
        }
        true
    };
    let mut chart = Chart::new(
        "Implicit-explicit split: spring implicit, drag explicit (largest stable gamma dt)",
        "omega dt",
        "largest stable gamma dt",
    )
    .log_log();
    chart.note = Some(format!(
        "Stable: energy below {LIMIT:.0e} x initial over {STEPS} steps (bisection on log gamma dt). \
         Theory: the step matrix's spectral radius is 1 at gamma dt = 2 + (omega dt)^2 / 2."
    ));
    let (mut measured, mut theory, mut data) = (Vec::new(), Vec::new(), Vec::new());
    for &z in &zs {
        let dt = z / osc.omega();
        let (mut lo, mut hi) = (1e-2f64.ln(), 1e4f64.ln());
        for _ in 0..iters {
            let mid = 0.5 * (lo + hi);
            if stable(dt, mid.exp()) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let q = lo.exp();
        let t = 2.0 + z * z / 2.0;
        eprintln!("  IMEX: omega dt {z}: largest stable gamma dt {q:.4} (theory {t:.4})");
        data.push(json!({"omega_dt": z, "gamma_dt_max": q, "theory": t}));
        measured.push((z, q));
        theory.push((z, t));
    }
    chart.series.push(Series::new(
        "measured (implicit Euler, drag explicit)",
        measured,
        Style::Line,
        0,
    ));
    chart.series.push(Series::new(
        "theory: 2 + (omega dt)^2 / 2",
        theory,
        Style::Dashed,
        8,
    ));
    let explicit: Vec<(f64, f64)> = zs.iter().map(|&z| (z, 2.0)).collect();
    chart.series.push(Series::new(
        "drag alone, explicit: gamma dt = 2",
        explicit,
        Style::Dashed,
        6,
    ));
    chart.write(&out.join("integrators_imex_stability.svg"))?;
    Ok(json!(data))
}
