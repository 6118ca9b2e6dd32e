//! Shared helpers of the kernel tests: a deterministic generator, array builders, and the
//! two checks every kernel gets (adjoint vs central differences, tangent vs adjoint).
#![allow(dead_code, unused_macros, unused_imports)]

pub mod oscillator;

use adflex_kernels::{Model, ModelBuilder};
use adflex_runtime::{Array, Mat22, Mat33, Quat, Vec3};

pub use adflex_testkit::Rng;

pub fn arr<T: adflex_runtime::Element>(v: Vec<T>, name: &str) -> Array<T> {
    Array::from_vec(v).named(name)
}

/// Tolerance of adjoint against central differences (relative, see `gradcheck::Report`).
pub const TOL: f64 = 1e-5;

/// Checks `kernel` launched with `args`: the adjoint against central differences for every
/// scalar of every array it reads (and that the gradient is not identically zero), and the
/// tangent against the adjoint by the dot-product test over `inputs`, with outputs `outputs`.
macro_rules! check_kernel {
    ($name:expr, $kernel:expr, $dim:expr, ($($arg:expr),* $(,)?), inputs = [$($i:expr),* $(,)?], outputs = [$($o:expr),* $(,)?]) => {{
        use adflex_runtime::prelude::*;
        use adflex_runtime::gradcheck::dot_test;
        let report = GradCheck::new().worst(usize::MAX).kernel($kernel, $dim, ($($arg,)*)).expect($name);
        if !report.is_within(common::TOL) {
            let mut r = report.clone();
            r.entries.truncate(12);
            panic!("{}: {}", $name, r);
        }
        assert!(report.entries.iter().any(|e| e.analytic != 0.0), "{}: the gradient is identically zero", $name);
        let d = dot_test(
            |tape: &mut Tape| {
                $( $o.fill(Value::zeroed()); )*
                tape.launch($kernel, $dim, ($($arg,)*));
                vec![$($o.boxed()),*]
            },
            &[$(&$i as &dyn AnyArray),*],
            7,
        )
        .expect($name);
        assert!(d.rel_error() <= 1e-9, "{}: dot-product test {:?}", $name, d);
        println!("{:<28} adjoint vs FD {:.1e} ({} scalars), dot test {:.1e}", $name, report.max_error, report.checked, d.rel_error());
        report
    }};
}
pub(crate) use check_kernel;

/// Four particles (one pinned) and five damped springs, none at rest, with gravity and initial
/// velocities: a small but fully three-dimensional, nonlinear system.
pub fn spring_system(ke: f64) -> Model<f64> {
    spring_system_with(ke, 0.0)
}

/// [`spring_system`] with particle 0 of mass `m0` (0: pinned, moving with its initial velocity).
pub fn spring_system_with(ke: f64, m0: f64) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let p0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::new(0.1, 0.0, 0.0), m0);
    let p1 = b.add_particle(Vec3::new(0.6, 1.1, 0.1), Vec3::new(0.0, 0.3, -0.2), 1.0);
    let p2 = b.add_particle(Vec3::new(1.1, 0.8, -0.2), Vec3::new(-0.4, 0.0, 0.1), 0.5);
    let p3 = b.add_particle(Vec3::new(0.5, 0.5, 0.3), Vec3::new(0.2, -0.1, 0.3), 2.0);
    for (k, (i, j)) in [(p0, p1), (p1, p2), (p2, p3), (p1, p3), (p0, p3)]
        .into_iter()
        .enumerate()
    {
        let d = (b.particle_position(i) - b.particle_position(j)).norm();
        b.add_spring_with_rest(
            i,
            j,
            d * (0.85 + 0.07 * k as f64),
            ke * (1.0 + 0.3 * k as f64),
            0.2,
        );
    }
    b.finalize()
}
