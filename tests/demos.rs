//! Every demo of `examples/` at a test size, asserting its success criterion. Each example
//! is included as a module: its `run(&Config::small())` is what `main` runs at full size.

#[path = "../examples/cage.rs"]
#[allow(dead_code)]
mod cage;
#[path = "../examples/inverse_design.rs"]
#[allow(dead_code)]
mod inverse_design;
#[path = "../examples/parameter_estimation.rs"]
#[allow(dead_code)]
mod parameter_estimation;

#[test]
fn cage_centre_reaches_the_target_in_a_few_lbfgs_iterations() {
    let out = cage::run(&cage::Config::small()).unwrap();
    assert!(out.miss < 1e-4, "miss {} m: {}", out.miss, out.report);
    // The loss falls by 4 orders of magnitude within 3 iterations.
    let l = out.report.losses();
    assert!(l[3.min(l.len() - 1)] < 1e-4 * l[0], "{:?}", l);
}

#[test]
fn inverse_design_cable_takes_the_target_shape() {
    let out = inverse_design::run(&inverse_design::Config::small()).unwrap();
    // The equilibrium's RMS distance from the target parabola falls by more than 100x (in
    // practice by ~1e7, to ~1e-8 m).
    assert!(
        out.final_error < 1e-2 * out.initial_error && out.final_error < 1e-5,
        "{:e} m -> {:e} m: {}",
        out.initial_error,
        out.final_error,
        out.report
    );
    assert_eq!(out.frames.len(), 2);
}

#[test]
fn parameter_estimation_recovers_stiffness_damping_and_friction() {
    let out = parameter_estimation::run(&parameter_estimation::Config::small()).unwrap();
    // From 2x / 0.5x guesses, every value within 1% (in practice within ~1e-6: the recorded
    // trajectory is noise-free).
    for (name, t, r) in &out.values {
        assert!(
            (r - t).abs() < 1e-2 * t.abs(),
            "{name}: true {t}, recovered {r}: {}",
            out.report
        );
    }
    assert_eq!(out.values.len(), 7);
    assert_eq!(out.frames.len(), out.recorded.len() * 5 - 4);
}
