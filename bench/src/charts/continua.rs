//! Stability of the continua: the largest stable MPM time step against the material's
//! stiffness, beside the wave-speed limit `dx / c` that `Mpm::stable_dt` reports.

use adflex_kernels::mpm::{Material, MpmBuilder};
use adflex_runtime::prelude::*;
use serde_json::json;

use super::plot::{Chart, Series, Style};

/// Whether a block of stiffness `e` (`mu = lambda = e`, density 1) dropped on the floor of a
/// 32 x 32 grid survives `time` seconds (it lands after about 0.3 s) in steps of `dt`: no
/// step error (a particle that is not finite, inverted or out of the grid) and a kinetic
/// energy that stays below 100 times its largest value in free fall.
fn stable(e: f64, dt: f64, time: f64) -> bool {
    let steps = (time / dt).ceil() as usize;
    let mut b = MpmBuilder::new(32, 1.0 / 32.0);
    b.add_rect(
        Vec2::new(0.35, 0.25),
        Vec2::new(0.3, 0.2),
        1.0,
        1.0,
        Material::Corotated { mu: e, lambda: e },
    );
    let mpm = b.finalize::<f64>().expect("a valid block");
    let mut s = mpm.state();
    // Free fall from 0.25 - 3 dx at g = 3.8: v^2 <= 2 g h.
    let fall = 2.0 * 3.8 * 0.25 * mpm.particle_count() as f64 * 0.5;
    for _ in 0..steps {
        let mut tape = Tape::new();
        match mpm.step(&mut tape, &s, None, dt) {
            Ok(next) => s = next,
            Err(_) => return false,
        }
    }
    let ke: f64 = s.v.to_vec().iter().map(|v| 0.5 * v.norm_squared()).sum();
    ke.is_finite() && ke < 100.0 * fall.max(1e-12)
}

/// The chart `mpm_stability.svg`: bisection on `log dt` per stiffness.
pub fn mpm_stability(
    out: &std::path::Path,
    quick: bool,
) -> Result<serde_json::Value, Box<dyn std::error::Error>> {
    let es: Vec<f64> = if quick {
        vec![10.0, 1e3]
    } else {
        vec![1.0, 10.0, 100.0, 1e3, 1e4, 1e5]
    };
    let time = if quick { 0.1 } else { 0.6 };
    let iters = if quick { 6 } else { 12 };
    let dx = 1.0 / 32.0;
    let theory = |e: f64| dx / (3.0 * e).sqrt();
    let mut data = Vec::new();
    let mut found = Vec::new();
    for &e in &es {
        // Bracket: stable at theory / 64, unstable at theory * 64 (checked).
        let (mut lo, mut hi) = ((theory(e) / 64.0).ln(), (theory(e) * 64.0).ln());
        let lo_ok = stable(e, lo.exp(), time);
        let hi_ok = stable(e, hi.exp(), time);
        let dt = if !lo_ok {
            f64::NAN
        } else if hi_ok {
            hi.exp()
        } else {
            for _ in 0..iters {
                let mid = 0.5 * (lo + hi);
                if stable(e, mid.exp(), time) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            lo.exp()
        };
        eprintln!(
            "  E {e:.0e}: largest stable dt {dt:.3e} ({:.2} of dx / c)",
            dt / theory(e)
        );
        data.push(json!({"E": e, "dt_max": dt, "dx_over_c": theory(e), "ratio": dt / theory(e)}));
        found.push((e, dt));
    }
    let mut chart = Chart::new(
        "MPM stability: largest stable dt vs stiffness (2D block on the floor, 32 x 32 grid)",
        "stiffness mu = lambda (Pa, density 1)",
        "largest stable dt (s)",
    )
    .log_log();
    chart.note = Some(format!(
        "Stable: {time} s (landing included) without a particle leaving the grid, inverting or \
         becoming NaN, kinetic energy below 100x that of the fall (bisection on log dt). The dashed line is Mpm::stable_dt, \
         dx over the P-wave speed sqrt((lambda + 2 mu) / rho)."
    ));
    chart
        .series
        .push(Series::new("measured", found, Style::Line, 0));
    chart.series.push(Series::new(
        "dx / c (Mpm::stable_dt)",
        es.iter().map(|&e| (e, theory(e))).collect(),
        Style::Dashed,
        8,
    ));
    chart.write(&out.join("mpm_stability.svg"))?;
    Ok(json!(data))
}
