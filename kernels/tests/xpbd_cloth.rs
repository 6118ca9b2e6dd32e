//! XPBD on the library's cloth with distance constraints on every spring edge: the default
//! solver (averaged Jacobi) stays finite and keeps the constraints, and a diverging solve is an
//! error of `step` naming the XPBD constraint solve (not a NaN blamed on the bending kernel).
//!
//! Run with `--nocapture` to see the figures.

use std::time::Instant;

use adflex_kernels::contact::ground::Ground;
use adflex_kernels::integrators::{Integrator, Xpbd};
use adflex_kernels::scenes::cloth::ClothGrid;
use adflex_kernels::{Model, ModelBuilder};
use adflex_runtime::prelude::*;

/// The `cloth` scene's sheet (springs, bending, ground, two pinned corners) with `n` particles
/// per side and a rigid distance constraint on every spring's edge.
fn constrained_cloth(n: usize) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.particle_radius = 0.01;
    b.add_cloth_grid(&ClothGrid::benchmark(n));
    // The benchmark scene's ground (damping on approach, as in Warp).
    b.set_ground(Ground {
        damp_approach: true,
        ..Ground::default()
    });
    let pairs = b.finalize().springs().unwrap().pairs.to_vec();
    for [i, j] in pairs {
        b.add_distance_constraint(i, j, 0.0);
    }
    b.finalize()
}

/// Runs `steps` steps of `dt` with `integ` on one tape in `check_finite` mode; returns the
/// first error, or the largest relative constraint violation and speed over the run.
fn run(n: usize, integ: &Xpbd, dt: f64, steps: usize) -> Result<(f64, f64), Error> {
    let model = constrained_cloth(n);
    let c = model.distance_constraints.as_ref().unwrap();
    let mut tape = Tape::new();
    tape.check_finite(true);
    let mut s = model.state();
    let (mut violation, mut speed) = (0.0f64, 0.0f64);
    for _ in 0..steps {
        s = integ.step(&model, &mut tape, &s, None, dt)?;
        let x = s.x.to_vec();
        assert!(x.iter().all(|p| p.iter().all(|c| c.is_finite())));
        violation = violation.max(c.max_relative_violation(&x));
        speed = s.v.to_vec().iter().map(|v| v.norm()).fold(speed, f64::max);
    }
    Ok((violation, speed))
}

/// The default XPBD keeps the constrained cloth finite and its edges at their rest lengths
/// (it used to give NaN within 10 steps at every size: summed Jacobi corrections of 8
/// constraints per particle overshoot).
#[test]
fn default_xpbd_is_stable_on_constrained_cloth() {
    let steps = 12;
    for n in [10, 30, 70] {
        for dt in [1e-3, 1.0 / 60.0] {
            let start = Instant::now();
            let (violation, speed) = run(n, &Xpbd::default(), dt, steps)
                .unwrap_or_else(|e| panic!("{n}x{n}, dt {dt}: {e}"));
            println!(
                "default XPBD, cloth {n}x{n}, dt = {dt:.4}, {steps} steps: max relative edge \
                 violation {violation:.2e}, max speed {speed:.3} m/s ({:.2} s)",
                start.elapsed().as_secs_f64()
            );
            // Free fall for 12 steps of 1/60 s reaches 2 m/s; a blow-up is far beyond.
            assert!(speed < 3.0, "{n}x{n}, dt {dt}: speed {speed}");
            // 16 Jacobi passes per step propagate slowly across a large sheet: the edges
            // stretch by up to 5% at 70x70 and 1/60 s (0.02% at the scene's 1 ms).
            let bound = if dt < 0.01 { 1e-3 } else { 0.1 };
            assert!(violation < bound, "{n}x{n}, dt {dt}: violation {violation}");
        }
    }
    // Bounded over time: 2 s at 60 Hz settles (at 2.1% for 30x30), no drift or blow-up.
    let (violation, speed) = run(30, &Xpbd::default(), 1.0 / 60.0, 120).unwrap();
    println!("default XPBD, cloth 30x30, 120 steps of 1/60 s: max violation {violation:.2e}, max speed {speed:.3} m/s");
    assert!(violation < 0.05 && speed < 3.0, "{violation} {speed}");
}

/// Summed Jacobi corrections at relaxation 1 (the old default) diverge on the cloth: the step
/// says so, naming the XPBD constraint solve and its kernels, before any NaN reaches the
/// bending kernel (which `check_finite` used to blame).
#[test]
fn diverging_constraint_solve_is_an_error_naming_it() {
    let summed = Xpbd {
        averaging: false,
        ..Xpbd::default()
    };
    // Over-relaxation far past the stable range of the averaged update.
    let over = Xpbd {
        relaxation: 8.0,
        ..Xpbd::default()
    };
    for (name, integ) in [
        ("summed, relaxation 1", summed),
        ("averaged, relaxation 8", over),
    ] {
        for n in [10, 30] {
            let err = run(n, &integ, 1.0 / 60.0, 10).expect_err("the solve diverges");
            println!("{name}, cloth {n}x{n}: {err}");
            match &err {
                Error::NotConverged {
                    solver, context, ..
                } => {
                    assert_eq!(solver, "Xpbd constraint solve");
                    assert!(context.contains("solve_distance_constraints"), "{context}");
                    assert!(context.contains("substep"), "{context}");
                }
                other => panic!("expected NotConverged, got {other:?}"),
            }
            let msg = err.to_string();
            assert!(!msg.contains("bend"), "{msg}");
            assert!(msg.contains("relaxation"), "{msg}");
        }
    }
}

/// Relaxation and substeps are checked.
#[test]
fn invalid_xpbd_settings_are_errors() {
    let model = constrained_cloth(4);
    for integ in [
        Xpbd {
            relaxation: f64::NAN,
            ..Xpbd::default()
        },
        Xpbd {
            relaxation: 0.0,
            ..Xpbd::default()
        },
        Xpbd {
            substeps: 0,
            ..Xpbd::default()
        },
    ] {
        let err = integ
            .step(&model, &mut Tape::new(), &model.state(), None, 1e-3)
            .unwrap_err();
        assert!(matches!(err, Error::InvalidInput { .. }), "{err}");
    }
}
