//! Shared helpers of the kernel tests: a deterministic generator, array builders, and the
//! two checks every kernel gets (adjoint vs central differences, tangent vs adjoint).
#![allow(dead_code, unused_macros, unused_imports)]

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
