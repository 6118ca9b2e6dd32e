//! Gradient checks shared by the integration tests: adjoint against central finite differences
//! in f64, tangent against adjoint by the dot-product test.
#![allow(dead_code)]

use adflex::prelude::*;

pub use adflex_testkit::{assert_checked, Checked, Rng};

/// Checks one kernel (see [`adflex_testkit::check`]): `run(mode)` launches it on `inputs` (read)
/// and `outputs` (written).
pub fn check(
    inputs: &[&Array<f64>],
    outputs: &[&Array<f64>],
    seed: u64,
    run: impl Fn(Mode),
) -> Checked {
    adflex_testkit::check(inputs, outputs, seed, &run)
}
