//! Where each integrator is stable and where it fails, on an undamped spring
//! (`omega = sqrt(k / m)`) and a stiff pendulum. Run with `--nocapture` for the figures.

use crate::common;

use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Midpoint, Rk4, SemiImplicitEuler, Xpbd,
};
use adflex_kernels::prelude::Drag;
use adflex_kernels::{Model, ModelBuilder};
use adflex_runtime::{Tape, Vec3};
use common::oscillator::Oscillator;

/// Whether an energy ratio reached `threshold` (or overflowed to NaN).
fn diverged(ratio: f64, threshold: f64) -> bool {
    ratio.is_nan() || ratio >= threshold
}

/// An undamped spring of omega = 10 rad/s.
fn spring() -> Oscillator {
    Oscillator {
        stiffness: 100.0,
        mass: 1.0,
        damping: 0.0,
        displacement: 0.1,
        velocity: 0.0,
    }
}

/// The same spring released from 1 micrometre, so that a growing solution can be followed for
/// a factor 1e10 in energy before the mass reaches the anchor (where the 1-D model ends).
fn tiny_spring() -> Oscillator {
    Oscillator {
        displacement: 1e-6,
        ..spring()
    }
}

/// Explicit Euler multiplies the energy of an undamped oscillator by exactly
/// `1 + (omega dt)^2` every step: it grows for every `dt`, however small.
#[test]
fn explicit_euler_energy_grows_for_every_dt() {
    let osc = tiny_spring();
    for omega_dt in [0.01f64, 0.1, 0.5, 1.0, 1.9] {
        // At most 100 steps, and no more than a growth of 1e10.
        let steps = 100.min((1e10f64.ln() / (1.0 + omega_dt * omega_dt).ln()) as usize);
        let tr = osc.simulate(&ExplicitEuler, osc.dt_for(omega_dt), steps);
        for k in 1..tr.energy.len() {
            assert!(
                tr.energy[k] > tr.energy[k - 1],
                "omega dt = {omega_dt}: energy did not grow at step {k}"
            );
        }
        let expected = (1.0 + omega_dt * omega_dt).powi(steps as i32);
        let ratio = tr.final_energy_ratio();
        println!(
            "explicit Euler, omega dt = {omega_dt}: E_{steps} / E_0 = {ratio:.6e} (theory (1 + (omega dt)^2)^{steps} = {expected:.6e}), growth per step {:.6}",
            ratio.powf(1.0 / steps as f64)
        );
        assert!(ratio > 1.0);
        assert!(
            (ratio / expected - 1.0).abs() < 1e-6,
            "omega dt = {omega_dt}: {ratio} vs {expected}"
        );
    }
}

/// Semi-implicit (symplectic) Euler keeps the energy bounded for `omega dt < 2` (it conserves
/// `v^2 + omega^2 u^2 - omega^2 dt u v`, so from rest the energy oscillates below
/// `E0 / (1 - omega dt / 2)`), and diverges beyond.
#[test]
fn semi_implicit_euler_bounded_below_2_diverges_above() {
    let osc = spring();
    let tr = osc.simulate(&SemiImplicitEuler, osc.dt_for(1.9), 10_000);
    let max = tr.max_energy_ratio();
    let bound = 1.0 / (1.0 - 0.95);
    println!("semi-implicit Euler, omega dt = 1.9: max E / E0 over 10000 steps = {max:.4} (bound {bound:.4}), final {:.4}", tr.final_energy_ratio());
    assert!(max.is_finite() && max <= bound * (1.0 + 1e-9), "{max}");
    // The energy oscillates but does not drift: the last 1000 steps reach the same peak.
    let late = tr.energy[9000..].iter().fold(0.0f64, |m, &e| m.max(e)) / tr.energy[0];
    assert!((late / max - 1.0).abs() < 0.05, "late peak {late} vs {max}");

    let osc = tiny_spring();
    let tr = osc.simulate(&SemiImplicitEuler, osc.dt_for(2.1), 20);
    let ratio = tr.final_energy_ratio();
    println!(
        "semi-implicit Euler, omega dt = 2.1: E_20 / E_0 = {ratio:.3e} (growth per step {:.3})",
        ratio.powf(0.05)
    );
    assert!(diverged(ratio, 1e9), "{ratio}");
}

/// RK4 (not required by the issue, but charted): bounded and slightly dissipative below
/// `omega dt = 2 sqrt(2)`, divergent above.
#[test]
fn rk4_bounded_below_2_83_diverges_above() {
    let osc = spring();
    let tr = osc.simulate(&Rk4, osc.dt_for(2.7), 1000);
    println!(
        "RK4, omega dt = 2.7: max E / E0 = {:.6}, final {:.3e}",
        tr.max_energy_ratio(),
        tr.final_energy_ratio()
    );
    assert!(tr.max_energy_ratio() <= 1.0 + 1e-12);
    let osc = tiny_spring();
    let tr = osc.simulate(&Rk4, osc.dt_for(3.0), 25);
    println!(
        "RK4, omega dt = 3.0: E_25 / E0 = {:.3e}",
        tr.final_energy_ratio()
    );
    assert!(diverged(tr.final_energy_ratio(), 1e8));
}

/// Midpoint (RK2) multiplies the complex amplitude of an undamped oscillator by
/// `1 + i omega dt - (omega dt)^2 / 2` per step: the energy by `1 + (omega dt)^4 / 4`, for
/// every `dt` (it grows, slowly where `omega dt` is small).
#[test]
fn midpoint_amplification_matches_theory() {
    let osc = tiny_spring();
    for omega_dt in [0.1f64, 0.5, 1.0, 2.0, 3.0] {
        let theory = 1.0 + omega_dt.powi(4) / 4.0;
        // At most 20 steps, and a growth of at most 1e8 (within the 1-D model).
        let steps = 20.min((8.0 * 10f64.ln() / theory.ln()) as usize);
        let tr = osc.simulate(&Midpoint, osc.dt_for(omega_dt), steps);
        let per_step = tr.final_energy_ratio().powf(1.0 / steps as f64);
        println!("midpoint, omega dt = {omega_dt}: energy factor per step {per_step:.12} (theory |1 + i z - z^2/2|^2 = {theory:.12})");
        assert!(
            (per_step / theory - 1.0).abs() < 1e-9,
            "omega dt = {omega_dt}: {per_step} vs {theory}"
        );
        for k in 1..tr.energy.len() {
            assert!(
                tr.energy[k] > tr.energy[k - 1],
                "omega dt = {omega_dt}: no growth at step {k}"
            );
        }
    }
}

/// Linearized implicit Euler on a linear spring is implicit Euler: the energy factor is
/// `1 / (1 + (omega dt)^2)` per step for any `dt` (one linear solve per step).
#[test]
fn linearized_implicit_euler_is_unconditionally_stable_on_a_linear_spring() {
    let osc = spring();
    for omega_dt in [0.5f64, 2.0, 10.0, 100.0, 1e4] {
        let tr = osc.simulate(&ImplicitEuler::linearized(), osc.dt_for(omega_dt), 50);
        let first = tr.energy[1] / tr.energy[0];
        let theory = 1.0 / (1.0 + omega_dt * omega_dt);
        println!("linearized implicit Euler, omega dt = {omega_dt}: E1 / E0 = {first:.6e} (theory {theory:.6e}), max over 50 steps {:.6}", tr.max_energy_ratio());
        assert!(
            (first / theory - 1.0).abs() < 1e-6,
            "omega dt = {omega_dt}: {first} vs {theory}"
        );
        assert!(tr.max_energy_ratio() <= 1.0 + 1e-12);
    }
}

/// The spectral radius of implicit Euler with the spring implicit (`z = omega dt`) and a
/// linear damping force explicit (`q = gamma dt`, `gamma = c / m`): the step matrix is
/// `[[1, dt (1 - q)], [-dt omega^2, 1 - q]] / (1 + z^2)` on `(u, v)`, stable iff
/// `q < 2 + z^2 / 2`.
fn imex_spectral_radius(z: f64, q: f64) -> f64 {
    spectral_radius((2.0 - q) / (1.0 + z * z), (1.0 - q) / (1.0 + z * z))
}

/// The largest eigenvalue modulus of a real 2x2 matrix of trace `t` and determinant `d`.
fn spectral_radius(t: f64, d: f64) -> f64 {
    let disc = t * t - 4.0 * d;
    if disc >= 0.0 {
        let s = disc.sqrt();
        ((t + s) / 2.0).abs().max(((t - s) / 2.0).abs())
    } else {
        d.sqrt()
    }
}

/// The spring of [`spring`] without damping, plus drag `c` (N s/m) as its own force.
fn spring_with_drag(c: f64) -> Model<f64> {
    let mut m = tiny_spring().model();
    m.forces.push(Box::new(Drag {
        kd: c,
        wind: Vec3::zeros(),
    }));
    m
}

/// The spectral radius of the step matrix of a linear one-degree-of-freedom trajectory, fitted
/// from its first three states: `M [s0 s1] = [s1 s2]`, `s_k = (u_k, v_k)`.
fn fitted_spectral_radius(u: &[f64], v: &[f64]) -> f64 {
    let (a, b, c, d) = (u[0], u[1], v[0], v[1]); // [s0 s1] = [[a, b], [c, d]]
    let det = a * d - b * c;
    let inv = [[d / det, -b / det], [-c / det, a / det]];
    let rhs = [[u[1], u[2]], [v[1], v[2]]];
    let m = |i: usize, j: usize| rhs[i][0] * inv[0][j] + rhs[i][1] * inv[1][j];
    spectral_radius(m(0, 0) + m(1, 1), m(0, 0) * m(1, 1) - m(0, 1) * m(1, 0))
}

/// An implicit-explicit split keeps the explicit part's stability limit: spring implicit,
/// drag explicit is stable for `gamma dt < 2 + (omega dt)^2 / 2`. Measured: the spectral
/// radius of the step (fitted from the trajectory) against theory, and the energy after enough
/// steps for a factor 1e6 (growth beyond the limit, decay below). Treating the drag implicitly
/// too is stable at every one of these steps.
#[test]
fn implicit_explicit_split_stability_limit_matches_theory() {
    let osc = tiny_spring();
    let imex = ImplicitEuler::default().with_explicit(["drag"]);
    for z in [0.5f64, 2.0, 4.0] {
        let dt = osc.dt_for(z);
        let limit = 2.0 + z * z / 2.0;
        for frac in [0.5, 0.9, 0.98, 1.02, 1.1, 1.5] {
            let q = frac * limit;
            let model = spring_with_drag(q / dt); // m = 1 kg: gamma = c
            let theory = imex_spectral_radius(z, q);
            let steps = ((3.0 * 10f64.ln() / theory.ln().abs()).ceil() as usize).clamp(3, 400);
            let tr = osc.simulate_model(&model, &imex, dt, steps);
            let fitted = fitted_spectral_radius(&tr.u, &tr.v);
            let ratio = tr.final_energy_ratio();
            println!("implicit spring, explicit drag, omega dt = {z}, gamma dt = {q:.3} ({frac} x limit {limit}): spectral radius {fitted:.9} (theory {theory:.9}), E_{steps} / E_0 = {ratio:.2e}");
            assert!(
                (fitted / theory - 1.0).abs() < 1e-6,
                "z {z} q {q}: {fitted} vs {theory}"
            );
            if frac > 1.0 {
                assert!(
                    ratio > 1e3,
                    "z {z} q {q}: beyond the limit but E ratio {ratio}"
                );
                let tr = osc.simulate_model(&model, &ImplicitEuler::default(), dt, steps);
                assert!(
                    tr.max_energy_ratio() <= 1.0 + 1e-9,
                    "fully implicit, z {z} q {q}"
                );
            } else {
                assert!(
                    ratio < 1e-3,
                    "z {z} q {q}: within the limit but E ratio {ratio}"
                );
            }
        }
    }
}

/// Implicit Euler stays bounded at omega dt = 100 (where every explicit method above blows up
/// in a few steps): each step multiplies the energy by `1 / (1 + (omega dt)^2)`.
#[test]
fn implicit_euler_bounded_at_omega_dt_100() {
    let osc = spring();
    let dt = osc.dt_for(100.0);
    let tr = osc.simulate(&ImplicitEuler::default(), dt, 200);
    let max = tr.max_energy_ratio();
    let first = tr.energy[1] / tr.energy[0];
    println!(
        "implicit Euler, omega dt = 100: max E / E0 over 200 steps = {max:.6}, E1 / E0 = {first:.4e} (theory {:.4e}), final {:.3e}",
        1.0 / (1.0 + 1e4),
        tr.final_energy_ratio()
    );
    assert!(max <= 1.0 + 1e-12);
    assert!((first * (1.0 + 1e4) - 1.0).abs() < 1e-6, "{first}");
    assert!(tr.u.iter().chain(&tr.v).all(|x| x.is_finite()));
    // Newton converges every step.
    let model = osc.model();
    let mut s = model.state();
    for _ in 0..20 {
        let (next, st) = ImplicitEuler::default()
            .step_with_stats(&model, &mut Tape::new(), &s, None, dt)
            .unwrap();
        assert!(st.converged, "{st:?}");
        s = next;
    }
    // The explicit methods at the same step.
    let osc = tiny_spring();
    for (name, ratio) in [
        (
            "explicit Euler",
            osc.simulate(&ExplicitEuler, dt, 2).final_energy_ratio(),
        ),
        (
            "semi-implicit Euler",
            osc.simulate(&SemiImplicitEuler, dt, 2).final_energy_ratio(),
        ),
        ("RK4", osc.simulate(&Rk4, dt, 1).final_energy_ratio()),
    ] {
        println!("{name}, omega dt = 100: E / E_0 = {ratio:.3e} after 1-2 steps");
        assert!(diverged(ratio, 1e6), "{name}: {ratio}");
    }
}

/// A pendulum of `links` links of 1 m / `links` (a chain of particles of 1 kg) hanging from a
/// pinned point, released horizontally; as XPBD distance constraints of compliance
/// `compliance` or (if `spring` is some stiffness) as springs.
fn pendulum(links: usize, compliance: f64, spring: Option<f64>) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let mut prev = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    let l = 1.0 / links as f64;
    for k in 1..=links {
        let p = b.add_particle(Vec3::new(k as f64 * l, 0.0, 0.0), Vec3::zeros(), 1.0);
        match spring {
            Some(ke) => {
                b.add_spring(prev, p, ke, 0.0);
            }
            None => {
                b.add_distance_constraint(prev, p, compliance);
            }
        }
        prev = p;
    }
    b.finalize()
}

/// The largest relative error of any link length over `steps` steps of `dt`.
fn max_length_error<I: Integrator<f64>>(
    model: &Model<f64>,
    integ: &I,
    dt: f64,
    steps: usize,
) -> f64 {
    let n = model.particle_count;
    let rest = 1.0 / (n - 1) as f64;
    let mut s = model.state();
    let mut worst = 0.0f64;
    for _ in 0..steps {
        // A state that overflowed is an error of the step: the method failed.
        s = match integ.step(model, &mut Tape::new(), &s, None, dt) {
            Ok(s) => s,
            Err(_) => return f64::INFINITY,
        };
        let x = s.x.to_vec();
        for k in 1..n {
            let e = ((x[k] - x[k - 1]).norm() - rest).abs() / rest;
            worst = if e.is_nan() {
                f64::INFINITY
            } else {
                worst.max(e)
            };
        }
    }
    worst
}

/// XPBD keeps a stiff (inextensible) pendulum's length over 10 s at 60 Hz, where a spring
/// of comparable stiffness under semi-implicit Euler at the same step explodes.
#[test]
fn xpbd_keeps_a_stiff_pendulums_length() {
    let dt = 1.0 / 60.0;
    let steps = 600;
    let single = max_length_error(&pendulum(1, 0.0, None), &Xpbd::default(), dt, steps);
    println!(
        "XPBD, rigid single pendulum, dt = 1/60, 600 steps: max relative length error {single:.3e}"
    );
    assert!(single < 1e-9, "{single}");
    let chain = max_length_error(
        &pendulum(3, 0.0, None),
        &Xpbd {
            substeps: 20,
            iterations: 2,
            relaxation: 1.0,
            ..Xpbd::default()
        },
        dt,
        steps,
    );
    println!("XPBD, rigid triple pendulum, 20 substeps x 2 Jacobi passes: max relative length error {chain:.3e}");
    assert!(chain < 5e-3, "{chain}");
    let compliant = max_length_error(&pendulum(1, 1e-6, None), &Xpbd::default(), dt, steps);
    println!(
        "XPBD, single pendulum of compliance 1e-6 m/N: max relative length error {compliant:.3e}"
    );
    assert!(compliant < 1e-4, "{compliant}");
    // A spring of 1e6 N/m (omega dt = 16.7) under semi-implicit Euler at the same step.
    let spring = max_length_error(&pendulum(1, 0.0, Some(1e6)), &SemiImplicitEuler, dt, 100);
    println!("semi-implicit Euler, spring pendulum of 1e6 N/m at dt = 1/60: max relative length error {spring:.3e}");
    assert!(diverged(spring, 1.0), "{spring}");
}
