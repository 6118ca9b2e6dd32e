//! Every demo of `examples/` at a test size, asserting its success criterion. Each example
//! is included as a module: its `run(&Config::small())` is what `main` runs at full size.

#[path = "../examples/cage.rs"]
#[allow(dead_code)]
mod cage;

#[test]
fn cage_centre_reaches_the_target_in_a_few_lbfgs_iterations() {
    let out = cage::run(&cage::Config::small()).unwrap();
    assert!(out.miss < 1e-4, "miss {} m: {}", out.miss, out.report);
    // The loss falls by 4 orders of magnitude within 3 iterations.
    let l = out.report.losses();
    assert!(l[3.min(l.len() - 1)] < 1e-4 * l[0], "{:?}", l);
}
