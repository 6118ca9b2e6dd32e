//! Gradient checks: they pass on correct adjoints and fail on a wrong one.

mod common;

use adflex_runtime::gradcheck::{
    dot_test, gradcheck, gradcheck_kernel, jacobian_adjoint, jacobian_fd, jacobian_tangent,
    GradCheck, SWEEP,
};
use adflex_runtime::prelude::*;
use common::{random, Square, Step, SumSq};

#[test]
fn kernel_check_passes_on_correct_adjoints() {
    let x = Array::from_vec(random(6, 1, -2.0, 2.0)).named("x");
    let y = Array::<f64>::zeros(6).named("y");
    let r = gradcheck_kernel(Square::<false>, 6, (&x, 1.5, &y)).unwrap();
    assert_eq!(r.checked, 6);
    r.assert_within(1e-7);
    // The outputs hold the forward result afterwards.
    let expected: Vec<f64> = x.to_vec().iter().map(|x| 1.5 * x * x).collect();
    assert_eq!(y.to_vec(), expected);

    // Atomic output: restored before every run, so its initial value does not pile up.
    let loss = Array::from_vec(vec![10.0]).named("loss");
    gradcheck_kernel(SumSq, 6, (&x, &loss))
        .unwrap()
        .assert_within(1e-7);
    let sum: f64 = x.to_vec().iter().map(|x| x * x).sum();
    assert!((loss.get(0) - (10.0 + sum)).abs() < 1e-12);

    // Several inputs and outputs, scatters in the adjoint.
    let (n, m) = (9, 4);
    let xs = Array::from_vec(random(n, 2, -1.0, 1.0)).named("x");
    let vs = Array::from_vec(random(n, 3, -1.0, 1.0)).named("v");
    let ps = Array::from_vec(random(m, 4, 0.5, 2.0)).named("p");
    let (x2, v2) = (Array::<f64>::zeros(n), Array::<f64>::zeros(n));
    let r = GradCheck::new()
        .worst(3)
        .kernel(Step, n, (&xs, &vs, &ps, 0.1, &x2, &v2))
        .unwrap();
    assert_eq!((r.checked, r.entries.len()), (2 * n + m, 3));
    r.assert_within(1e-7);
}

#[test]
fn kernel_check_fails_on_a_wrong_adjoint() {
    let x = Array::from_vec(random(5, 5, 0.5, 2.0)).named("x");
    let y = Array::<f64>::zeros(5).named("y");
    let r = gradcheck_kernel(Square::<true>, 5, (&x, 1.5, &y)).unwrap();
    assert!(!r.is_within(1e-3), "{r}");
    // Analytic 3 a x against numeric 2 a x: relative error 1/3.
    assert!((r.max_error - 1.0 / 3.0).abs() < 1e-6, "{r}");
    let e = &r.entries[0];
    assert_eq!((e.array.as_str(), e.component), ("x", 0));
    assert!((e.analytic / e.numeric - 1.5).abs() < 1e-6);
    let shown = r.to_string();
    assert!(
        shown.contains("max relative error") && shown.contains("analytic"),
        "{shown}"
    );
}

#[test]
#[should_panic(expected = "gradient check failed")]
fn assert_within_panics_on_a_wrong_adjoint() {
    let x = Array::from_vec(random(3, 6, 0.5, 2.0)).named("x");
    let y = Array::<f64>::zeros(3);
    gradcheck_kernel(Square::<true>, 3, (&x, 2.0, &y))
        .unwrap()
        .assert_within(1e-4);
}

#[test]
fn tape_check_fails_on_a_wrong_adjoint_and_restores_params() {
    let x = Array::from_vec(random(4, 7, -1.0, 1.0)).named("x");
    let before: Vec<u64> = x.to_vec().iter().map(|v| v.to_bits()).collect();
    let f = |tape: &mut Tape| {
        let y = Array::<f64>::zeros(4);
        let l = Array::<f64>::zeros(1);
        tape.launch(Square::<true>, 4, (&x, 0.5, &y));
        tape.launch(SumSq, 4, (&y, &l));
        l
    };
    let r = gradcheck(f, &[&x]).unwrap();
    assert!(!r.is_within(1e-2), "{r}");
    let after: Vec<u64> = x.to_vec().iter().map(|v| v.to_bits()).collect();
    assert_eq!(before, after, "perturbed values restored exactly");
}

#[test]
fn f32_values_restore_exactly() {
    let x = Array::from_vec(vec![0.1f32, 1.0 / 3.0, -7.25]).named("x32");
    let before: Vec<u32> = x.to_vec().iter().map(|v| v.to_bits()).collect();
    let r = GradCheck::new()
        .step(1e-3)
        .run(
            |tape| {
                let l = Array::<f32>::zeros(1);
                let (xb, lb) = (x.clone(), l.clone());
                tape.record_fn(
                    "sum",
                    &[&x],
                    &[&l],
                    || l.set(0, x.to_vec().iter().sum()),
                    move || {
                        let d = lb.grad_buffer().unwrap().get(0);
                        if let Some(g) = xb.grad_buffer() {
                            g.modify(|g| g.iter_mut().for_each(|g| *g += d));
                        }
                        Ok(())
                    },
                );
                l
            },
            &[&x],
        )
        .unwrap();
    r.assert_within(1e-2);
    let after: Vec<u32> = x.to_vec().iter().map(|v| v.to_bits()).collect();
    assert_eq!(before, after);
}

#[test]
fn jacobians_three_ways_and_dot_test() {
    let (n, m) = (5, 2);
    let x = Array::from_vec(random(n, 8, -1.0, 1.0)).named("x");
    let v = Array::from_vec(random(n, 9, -1.0, 1.0)).named("v");
    let p = Array::from_vec(random(m, 10, 0.5, 2.0)).named("p");
    // Two steps and a loss: outputs x2, v2 and the loss.
    let f = |tape: &mut Tape| {
        let (x1, v1) = (Array::<f64>::zeros(n), Array::<f64>::zeros(n));
        let (x2, v2) = (Array::<f64>::zeros(n), Array::<f64>::zeros(n));
        let l = Array::<f64>::zeros(1);
        tape.launch(Step, n, (&x, &v, &p, 0.1, &x1, &v1));
        tape.launch(Step, n, (&x1, &v1, &p, 0.1, &x2, &v2));
        tape.launch(SumSq, n, (&x2, &l));
        vec![x2.boxed(), v2.boxed(), l.boxed()]
    };
    let inputs: [&dyn AnyArray; 3] = [&x, &v, &p];
    let ja = jacobian_adjoint(f, &inputs).unwrap();
    let jt = jacobian_tangent(f, &inputs).unwrap();
    let jf = jacobian_fd(f, &inputs, 1e-6).unwrap();
    assert_eq!((ja.rows, ja.cols), (2 * n + 1, 2 * n + m));
    assert!(ja.max_abs_diff(&jt) < 1e-12, "adjoint vs tangent");
    assert!(ja.max_abs_diff(&jf) < 1e-7, "adjoint vs fd");
    // d x2[0] / d x[0] is about 1 for a small dt.
    assert!((ja[(0, 0)] - 1.0).abs() < 0.1);
    for seed in 0..3 {
        dot_test(f, &inputs, seed).unwrap().assert_within(1e-12);
    }
    // Inputs need not require grad, and no tangent is left on them.
    assert!(!x.is_requires_grad());
    assert!(x.tangent_buffer().is_none());
}

/// `loss += q(x)^3` where `q(x) = (x + 2^20) - 2^20` rounds `x` to a multiple of 2^-32
/// (round-off in the forward pass, like a long rollout's): its adjoint `3 q^2` is the right
/// gradient (of the smooth function the computation approximates), and the loss is noisy at
/// the 1e-10 level.
#[adflex_macros::diff_kernel]
fn noisy_cubes(x: &Array<f64>, loss: &Array<f64>) {
    let q = (x[tid()] + 1048576.0) - 1048576.0;
    loss.atomic_add(0, q * q * q);
}

/// `loss += x^3`, smooth.
#[adflex_macros::diff_kernel]
fn cubes(x: &Array<f64>, loss: &Array<f64>) {
    let v = x[tid()];
    loss.atomic_add(0, v * v * v);
}

#[test]
fn a_noisy_but_right_gradient_passes_at_the_defaults_and_not_at_a_tiny_fixed_step() {
    let x = Array::from_vec(random(8, 11, -2.0, 2.0)).named("x");
    let f = |tape: &mut Tape| {
        let l = Array::<f64>::zeros(1);
        tape.launch(noisy_cubes, 8, (&x, &l));
        l
    };
    let r = gradcheck(f, &[&x]).unwrap();
    println!("{r}");
    assert_eq!(r.h, None);
    r.assert_within(1e-9);
    // The uncertainties are honest: small against the derivatives (so that a wrong gradient
    // would show), but not zero.
    for e in &r.entries {
        assert!(e.uncertainty > 0.0, "{r}");
        assert!(e.uncertainty < 1e-4 * e.numeric.abs().max(1e-2), "{r}");
        let scale = x.get(e.index).abs().max(1.0);
        assert!(
            SWEEP
                .iter()
                .any(|s| (e.step / (s * scale) - 1.0).abs() < 1e-6),
            "{r}"
        );
    }
    // The old problem: a fixed small step divides the noise by h.
    let r = GradCheck::new().step(1e-8).run(f, &[&x]).unwrap();
    println!("{r}");
    assert!(!r.is_within(1e-3), "{r}");
    assert_eq!(r.h, Some(1e-8));
}

/// `loss = sum x^3` on the host, with a backward `k * 3 x^2`, over a forward pass whose value
/// is rounded to a multiple of `q` (0: exact).
fn host_cubes(x: &Array<f64>, k: f64, q: f64) -> impl Fn(&mut Tape) -> Array<f64> + '_ {
    move |tape| {
        let loss = Array::<f64>::zeros(1).named("loss");
        let (xb, lb) = (x.clone(), loss.clone());
        tape.record_fn(
            "cubes",
            &[x],
            &[&loss],
            || {
                let v: f64 = x.to_vec().iter().map(|v| v * v * v).sum();
                loss.set(0, if q > 0.0 { (v / q).round() * q } else { v });
            },
            move || {
                let (d, xs) = (lb.grad_buffer().unwrap().get(0), xb.to_vec());
                if let Some(g) = xb.grad_buffer() {
                    g.modify(|g| {
                        g.iter_mut()
                            .zip(xs)
                            .for_each(|(g, x)| *g += k * 3.0 * x * x * d)
                    });
                }
                Ok(())
            },
        );
        loss
    }
}

#[test]
fn an_adjoint_off_by_one_percent_fails_at_the_defaults() {
    let x = Array::from_vec(random(6, 12, 0.5, 2.0)).named("x");
    // Right: passes, exact or rounded to 1e-9.
    for q in [0.0, 1e-9] {
        let r = gradcheck(host_cubes(&x, 1.0, q), &[&x]).unwrap();
        assert!(r.is_within(1e-9), "q = {q}: {r}");
    }
    // Off by 1%: fails (the error beyond the uncertainty is about 1%), exact or noisy.
    for q in [0.0, 1e-9] {
        let r = gradcheck(host_cubes(&x, 1.01, q), &[&x]).unwrap();
        println!("{r}");
        assert!(!r.is_within(1e-3), "q = {q}: {r}");
        assert!(r.max_error > 0.9e-2 && r.max_error < 1e-2, "q = {q}: {r}");
        assert!(r.to_string().contains("+-"), "{r}");
    }
    // And a kernel check with a wrong adjoint still fails at its full error.
    let x = Array::from_vec(random(5, 13, 0.5, 2.0)).named("x");
    let y = Array::<f64>::zeros(5);
    let r = gradcheck_kernel(Square::<true>, 5, (&x, 1.5, &y)).unwrap();
    assert!((r.max_error - 1.0 / 3.0).abs() < 1e-6, "{r}");
}

#[test]
fn the_sweep_resolves_smooth_derivatives_to_near_rounding() {
    // x^3 at |x| <= 2: the Richardson value is exact up to rounding, far better than one
    // central difference at 1e-6.
    let x = Array::from_vec(random(8, 14, -2.0, 2.0)).named("x");
    let f = |tape: &mut Tape| {
        let l = Array::<f64>::zeros(1);
        tape.launch(cubes, 8, (&x, &l));
        l
    };
    let r = GradCheck::new().worst(8).run(f, &[&x]).unwrap();
    for e in &r.entries {
        let exact = 3.0 * x.get(e.index).powi(2);
        assert!((e.numeric - exact).abs() <= 1e-9 * exact.max(1.0), "{r}");
        assert!(e.uncertainty <= 1e-8 * exact.max(1.0), "{r}");
        assert!((e.numeric - exact).abs() <= e.uncertainty.max(1e-13), "{r}");
    }
    assert_eq!(r.max_error, 0.0, "{r}");
}

/// `x^3`, with an adjoint (and tangent) 1% too large.
#[adflex_macros::diff_func(adjoint = cube_adjoint, tangent = cube_tangent)]
fn cube_off<R: Real>(x: R) -> R {
    x * x * x
}
fn cube_adjoint<R: Real>(x: R, adj_out: R) -> (R,) {
    (R::lit(3.03) * x * x * adj_out,)
}
fn cube_tangent<R: Real>(x: R, dx: R) -> R {
    R::lit(3.03) * x * x * dx
}

/// [`noisy_cubes`] with the 1%-wrong adjoint of [`cube_off`].
#[adflex_macros::diff_kernel]
fn noisy_cubes_off(x: &Array<f64>, loss: &Array<f64>) {
    let q = (x[tid()] + 1048576.0) - 1048576.0;
    loss.atomic_add(0, cube_off(q));
}

#[test]
fn kernel_checks_at_the_defaults_pass_noisy_right_adjoints_and_fail_noisy_wrong_ones() {
    let x = Array::from_vec(random(6, 15, 0.5, 2.0)).named("x");
    let loss = Array::<f64>::zeros(1);
    let r = gradcheck_kernel(noisy_cubes, 6, (&x, &loss)).unwrap();
    assert!(r.is_within(1e-9), "{r}");
    let r = GradCheck::new()
        .step(1e-8)
        .kernel(noisy_cubes, 6, (&x, &loss))
        .unwrap();
    assert!(!r.is_within(1e-4), "{r}");
    let r = gradcheck_kernel(noisy_cubes_off, 6, (&x, &loss)).unwrap();
    assert!(!r.is_within(1e-3), "{r}");
    assert!(r.max_error > 0.9e-2, "{r}");
}
