//! Charts 1 and 2: the integrators of `adflex_kernels::integrators` on a mass-spring
//! oscillator with an exact solution (`integrators::oscillator`).

use adflex_kernels::integrators::oscillator::{Oscillator, Trajectory};
use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Rk4, SemiImplicitEuler, Xpbd,
};
use serde_json::json;

use super::plot::{Chart, Series, Style};

/// The integrators compared, by name, with whether they run on the XPBD constraint model.
pub fn integrators() -> Vec<(&'static str, Box<dyn Integrator<f64>>, bool)> {
    vec![
        ("explicit Euler", Box::new(ExplicitEuler), false),
        ("semi-implicit Euler", Box::new(SemiImplicitEuler), false),
        ("RK4", Box::new(Rk4), false),
        ("implicit Euler", Box::new(ImplicitEuler::default()), false),
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
         Points at {DT_MAX} s: no instability found (implicit Euler and XPBD, on top of each other). Explicit Euler grows every step; its curve depends on the step count."
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
