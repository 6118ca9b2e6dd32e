//! `second-order [--n 32] [--steps 100] [--rounds 5]`: the cost of second-order products on
//! the cloth benchmark scene (springs, bending, ground contact; `n x n` particles, `steps`
//! semi-implicit steps), against a gradient (forward and backward, f64) in the same run,
//! interleaved:
//! - a Hessian-vector product by forward over reverse (`second_order::hvp`: the forward and
//!   backward passes in `Dual`), with respect to the springs' stiffnesses and the initial
//!   velocities;
//! - a Gauss-Newton product `JᵀJ v` of the final positions, on a recorded tape (a tangent and
//!   an adjoint pass), and with the recording forward pass.
//!
//! With `--implicit`, the rollout is by implicit Euler (its implicit-function-theorem adjoint,
//! and in `Dual` the theorem's second-order term), `steps` defaulting to 20.
//!
//! One JSON line: seconds per call of each, and the ratios to the gradient.

use std::time::Duration;

use adflex_kernels::integrators::{ImplicitEuler, Integrator, SemiImplicitEuler};
use adflex_kernels::scenes::cloth;
use adflex_runtime::second_order::hvp;
use adflex_runtime::{AnyArray, Dual, Tape};
use serde_json::json;

use crate::arg;
use crate::timing::{fmt_s, interleaved, Case};

pub fn main(rest: &[String]) {
    let n = arg(rest, "--n").unwrap_or(32);
    let implicit = rest.iter().any(|a| a == "--implicit");
    let steps = arg(rest, "--steps").unwrap_or(if implicit { 20 } else { 100 });
    let by_f: Box<dyn Integrator<f64>> = match implicit {
        true => Box::new(ImplicitEuler::default()),
        false => Box::new(SemiImplicitEuler),
    };
    let by_d: Box<dyn Integrator<Dual>> = match implicit {
        true => Box::new(ImplicitEuler::default()),
        false => Box::new(SemiImplicitEuler),
    };
    let (by_f, by_d) = (&*by_f, &*by_d);
    let rounds = arg(rest, "--rounds").unwrap_or(5);
    let f = cloth::build::<f64>(n);
    let d = cloth::build::<Dual>(n);
    let ke_f = f.model.springs().expect("springs").ke.clone();
    let ke_d = d.model.springs().expect("springs").ke.clone();
    let (v0_f, v0_d) = (f.initial.v.clone(), d.initial.v.clone());
    let inputs_f: [&dyn AnyArray; 2] = [&ke_f, &v0_f];
    let inputs_d: [&dyn AnyArray; 2] = [&ke_d, &v0_d];
    let dim = ke_f.len() + 3 * v0_f.len();
    let v: Vec<f64> = (0..dim)
        .map(|k| ((k * 37 % 23) as f64 - 11.0) / 11.0)
        .collect();

    // The product must be a number (a NaN would time a wrong answer).
    let check = hvp(&inputs_d, &v, |tape| {
        cloth::forward_by(&d, tape, steps, by_d).map(|(_, loss)| loss)
    })
    .expect("Hessian-vector product");
    assert!(
        check.hv.iter().chain(&check.grad).all(|x| x.is_finite()),
        "the cloth's Hessian-vector product is not finite"
    );
    let mut recorded = Tape::new();
    let (end, _) = cloth::forward_by(&f, &mut recorded, steps, by_f).expect("the cloth's rollout");
    let mut cases = vec![
        Case::new("gradient", || {
            if implicit {
                let mut tape = Tape::new();
                let (_, loss) = cloth::forward_by(&f, &mut tape, steps, by_f).expect("rollout");
                tape.backward(&loss).expect("gradient");
            } else {
                // The cloth benchmark's own gradient (`docs/performance.md`).
                cloth::rollout(&f, steps, true).expect("gradient");
            }
        }),
        Case::new("hvp", || {
            hvp(&inputs_d, &v, |tape| {
                cloth::forward_by(&d, tape, steps, by_d).map(|(_, loss)| loss)
            })
            .expect("Hessian-vector product");
        }),
        Case::new("gauss-newton on the tape", || {
            recorded
                .gauss_newton(&inputs_f, &[&end.x], &v)
                .expect("Gauss-Newton product");
        }),
        Case::new("gauss-newton with its forward", || {
            let mut tape = Tape::new();
            let (s, _) = cloth::forward_by(&f, &mut tape, steps, by_f).expect("rollout");
            tape.gauss_newton(&inputs_f, &[&s.x], &v)
                .expect("Gauss-Newton product");
        }),
    ];
    let t = interleaved(&mut cases, rounds, Duration::from_millis(400));
    for (c, s) in cases.iter().zip(&t) {
        eprintln!(
            "{:<32} {:>10}  {:.2}x gradient",
            c.name,
            fmt_s(*s),
            s / t[0]
        );
    }
    println!(
        "{}",
        json!({
            "scene": "cloth", "n": n, "steps": steps, "parameters": dim,
            "integrator": if implicit { "implicit Euler" } else { "semi-implicit Euler" },
            "threads": rayon::current_num_threads(),
            "s_gradient": t[0], "s_hvp": t[1], "s_gauss_newton_on_tape": t[2],
            "s_gauss_newton_with_forward": t[3],
            "hvp_over_gradient": t[1] / t[0],
            "gauss_newton_on_tape_over_gradient": t[2] / t[0],
            "gauss_newton_with_forward_over_gradient": t[3] / t[0],
        })
    );
}
