//! Each way a run can end, on a loss built for it: the report says what happened, and says
//! "converged" only where the numbers show a minimum.

use std::ops::ControlFlow;

use adflex_macros::diff_kernel;
use adflex_optim::{Convergence, Optimizer, Params, Report, Stop};
use adflex_runtime::prelude::*;

/// `loss += sum_i w_i (c_i - a_i)^2`: a quadratic, minimum 0 at `c = a`.
#[diff_kernel]
fn quadratic(c: &Array<f64>, a: &Array<f64>, loss: &Array<f64>) {
    let i = tid();
    let d = c[i] - a[i];
    loss.atomic_add(0, (1.0 + i as f64) * d * d);
}

/// `loss += (c - a)^2 + 1`: a minimum of 1 (not 0).
#[diff_kernel]
fn lifted<R: Real>(c: &Array<R>, a: &Array<R>, loss: &Array<R>) {
    let d = c[0] - a[0];
    loss.atomic_add(0, d * d + 1.0);
}

/// `loss += |c - a| + 0.1 (c - a)`: a kink at the minimum `c = a`, gradient 0.9 or -1.1 on
/// either side, never small.
#[diff_kernel]
fn kink<R: Real>(c: &Array<R>, a: &Array<R>, loss: &Array<R>) {
    let d = c[0] - a[0];
    loss.atomic_add(0, abs(d) + 0.1 * d);
}

/// `loss += -c^2`: unbounded below.
#[diff_kernel]
fn hill<R: Real>(c: &Array<R>, loss: &Array<R>) {
    loss.atomic_add(0, -(c[0] * c[0]));
}

/// `loss += (c - 1)^2 + 0 * sqrt(4 - c^2)`: minimum at 1, NaN where `|c| > 2`.
#[diff_kernel]
fn walled<R: Real>(c: &Array<R>, loss: &Array<R>) {
    let d = c[0] - 1.0;
    loss.atomic_add(0, d * d + 0.0 * sqrt(4.0 - c[0] * c[0]));
}

fn minimize(
    opt: Optimizer<'_>,
    c: &Array<f64>,
    kernel: impl Fn(&mut Tape, &Array<f64>) -> Array<f64>,
) -> Report {
    opt.progress(false)
        .minimize(&Params::new().with(c), |tape| Ok(kernel(tape, c)))
        .unwrap()
}

fn quadratic_loss(a: &Array<f64>) -> impl Fn(&mut Tape, &Array<f64>) -> Array<f64> + '_ {
    move |tape, c| {
        let l = Array::zeros(1);
        tape.launch(quadratic, c.len(), (c, a, &l));
        l
    }
}

#[test]
fn a_quadratic_converges_by_the_gradient_test_and_by_no_progress_at_a_stationary_point() {
    let a = Array::from_vec(vec![1.0, -2.0, 0.5]);
    // The relative gradient test.
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(
        Optimizer::lbfgs().grad_tol_rel(1e-8),
        &c,
        quadratic_loss(&a),
    );
    assert_eq!(
        r.stop,
        Stop::Converged(Convergence::GradientTolerance),
        "{r}"
    );
    assert!(
        r.converged() && r.grad_norm <= 1e-8 * r.initial_grad_norm,
        "{r}"
    );
    assert!(
        r.to_string().starts_with("converged: the gradient norm"),
        "{r}"
    );
    // The absolute one, with gradient descent.
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(
        Optimizer::gradient_descent(0.05)
            .max_iters(1000)
            .grad_tol(1e-9),
        &c,
        quadratic_loss(&a),
    );
    assert_eq!(r.stop, Stop::Converged(Convergence::GradientTolerance));
    assert!(r.grad_norm <= 1e-9, "{r}");

    // No tolerance at all: L-BFGS runs until no lower point can be found, where the gradient
    // is tiny: converged (whatever argmin's wording of its line search's end).
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(Optimizer::lbfgs(), &c, quadratic_loss(&a));
    assert!(r.converged(), "{r}");
    assert!(r.loss < 1e-20, "{r}");
    for (got, want) in c.to_vec().iter().zip(a.to_vec()) {
        assert!((got - want).abs() < 1e-10, "{got} vs {want}: {r}");
    }
    // The report's gradient norm is the best point's.
    let exact: f64 = (0..3)
        .map(|i| (2.0 * (1.0 + i as f64) * (c.get(i) - a.get(i))).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!((r.grad_norm - exact).abs() <= 1e-12, "{r}");
}

/// `loss += (c_i^2 - 2 - 0.37 i)^2`: minima at irrational `c`, so that the gradient never
/// vanishes exactly.
#[diff_kernel]
fn roots(c: &Array<f64>, loss: &Array<f64>) {
    let i = tid();
    let d = c[i] * c[i] - 2.0 - 0.37 * i as f64;
    loss.atomic_add(0, d * d);
}

#[test]
fn a_non_finite_trial_point_after_converging_to_1e_30_is_not_divergence() {
    // L-BFGS converges to a loss near 1e-31; then its steps no longer change the point, its
    // memory becomes 0/0 and the next trial point is NaN (the run that used to be reported as
    // diverged, "lower the learning rate"). It converged: no lower point at a stationary point.
    for n in [1, 3, 8] {
        let c = Array::from_vec(vec![1.0f64; n]);
        let seen = std::cell::RefCell::new(Vec::new());
        let r = minimize(Optimizer::lbfgs().max_iters(1000), &c, |tape, c| {
            let l = Array::zeros(1);
            tape.launch(roots, n, (c, &l));
            seen.borrow_mut().push(l.get(0));
            l
        });
        let seen = seen.into_inner();
        let tiny = seen.iter().position(|&l| l < 1e-28).expect("converges");
        assert!(seen[tiny..].iter().any(|l| l.is_nan()), "n = {n}: {seen:?}");
        assert_eq!(
            r.stop,
            Stop::Converged(Convergence::NoProgress),
            "n = {n}: {r}"
        );
        assert!(
            r.loss < 1e-28 && r.grad_norm < 1e-12 * r.initial_grad_norm,
            "{r}"
        );
        assert!(
            r.to_string().starts_with("converged: no lower point"),
            "{r}"
        );
    }
}

#[test]
fn non_finite_trial_points_before_converging_are_not_divergence() {
    // From c = -1.9, L-BFGS's first trial step lands past the NaN wall at |c| = 2: the run
    // backs off and converges.
    let c = Array::from_vec(vec![-1.9f64]);
    let seen = std::cell::RefCell::new(Vec::new());
    let r = minimize(Optimizer::lbfgs().max_iters(60), &c, |tape, c| {
        let l = Array::zeros(1);
        tape.launch(walled, 1, (c, &l));
        seen.borrow_mut().push((c.get(0), l.get(0)));
        l
    });
    let seen = seen.into_inner();
    assert!(seen[1].1.is_nan(), "{seen:?}");
    assert!(r.converged(), "{r}");
    assert!(!matches!(r.stop, Stop::Diverged(_)), "{r}");
    assert!((c.get(0) - 1.0).abs() < 1e-8, "{r}");
}

#[test]
fn a_kink_at_the_minimum_is_a_failed_line_search_not_convergence() {
    let a = Array::from_vec(vec![0.3f64]);
    let c = Array::from_vec(vec![2.0f64]);
    let r = minimize(Optimizer::lbfgs().max_iters(200), &c, |tape, c| {
        let l = Array::zeros(1);
        tape.launch(kink, 1, (c, &a, &l));
        l
    });
    assert!(!r.converged(), "{r}");
    assert!(
        matches!(&r.stop, Stop::LineSearchFailed(m) if m.contains("argmin")),
        "{r}"
    );
    // The gradient at the best point is 0.9 or -1.1 (or 0.1 on the kink itself, where the
    // adjoint of `abs` is 0): not small, and the report says so.
    assert!(r.grad_norm >= 0.1 - 1e-12, "{r}");
    assert!(r.to_string().contains("NOT converged"), "{r}");
}

#[test]
fn a_wrong_gradient_is_a_failed_line_search_not_convergence() {
    // loss = (c - 1)^2 with the sign of its gradient flipped (a wrong hand-written backward):
    // the search direction leads uphill.
    let c = Array::from_vec(vec![3.0f64]).named("c");
    let r = Optimizer::lbfgs()
        .progress(false)
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::<f64>::zeros(1);
            let (cb, lb) = (c.clone(), l.clone());
            tape.record_fn(
                "wrong",
                &[&c],
                &[&l],
                || l.set(0, (c.get(0) - 1.0).powi(2)),
                move || {
                    let d = lb.grad_buffer().unwrap().get(0);
                    let x = cb.get(0);
                    cb.ensure_grad().modify(|g| g[0] -= 2.0 * (x - 1.0) * d);
                    Ok(())
                },
            );
            Ok(l)
        })
        .unwrap();
    assert!(!r.converged(), "{r}");
    assert!(matches!(r.stop, Stop::LineSearchFailed(_)), "{r}");
    // Nothing better than the start was found, and the arrays hold it.
    assert_eq!((r.loss, c.get(0)), (4.0, 3.0), "{r}");
}

#[test]
fn losses_that_run_away_diverge() {
    // Gradient descent with a step too large for the curvature: the loss and the gradient
    // grow geometrically.
    let a = Array::from_vec(vec![1.0, -2.0, 0.5]);
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(
        Optimizer::gradient_descent(1.0).max_iters(1000),
        &c,
        quadratic_loss(&a),
    );
    assert!(
        matches!(&r.stop, Stop::Diverged(m) if m.contains("lower the learning rate")),
        "{r}"
    );
    assert!(!r.converged() && r.loss == r.initial_loss, "{r}");
    assert!(r.iterations < 100, "{r}");

    // A loss unbounded below: L-BFGS's line search extrapolates until the loss is not
    // finite, far below any scale of the loss: diverged.
    let c = Array::from_vec(vec![0.5f64]);
    let r = minimize(Optimizer::lbfgs().max_iters(100), &c, |tape, c| {
        let l = Array::zeros(1);
        tape.launch(hill, 1, (c, &l));
        l
    });
    assert!(matches!(r.stop, Stop::Diverged(_)), "{r}");
    assert!(!r.converged() && r.loss < -1e12, "{r}");

    // A NaN loss at an iterate of gradient descent.
    let c = Array::from_vec(vec![0.0f64]);
    let r = minimize(Optimizer::gradient_descent(2.0), &c, |tape, c| {
        let l = Array::zeros(1);
        tape.launch(walled, 1, (c, &l));
        l
    });
    assert!(
        matches!(&r.stop, Stop::Diverged(m) if m.contains("is NaN")),
        "{r}"
    );
}

#[test]
fn budgets_are_spent_not_converged() {
    let a = Array::from_vec(vec![1.0, -2.0, 0.5]);
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(Optimizer::adam(0.01).max_iters(5), &c, quadratic_loss(&a));
    assert_eq!(
        (r.stop.clone(), r.iterations),
        (Stop::MaxIterations, 5),
        "{r}"
    );
    assert!(!r.converged(), "{r}");
    assert!(
        r.to_string().contains("maximum number of iterations"),
        "{r}"
    );

    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(
        Optimizer::lbfgs().max_iters(1000).max_evals(4),
        &c,
        quadratic_loss(&a),
    );
    assert_eq!(r.stop, Stop::MaxEvaluations, "{r}");
    assert!(r.evaluations <= 4 && !r.converged(), "{r}");
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(
        Optimizer::gradient_descent(0.01).max_evals(7),
        &c,
        quadratic_loss(&a),
    );
    assert_eq!(
        (r.stop.clone(), r.evaluations),
        (Stop::MaxEvaluations, 7),
        "{r}"
    );
}

#[test]
fn target_loss_and_callback() {
    let a = Array::from_vec(vec![1.0, -2.0, 0.5]);
    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(Optimizer::lbfgs().target_loss(1e-6), &c, quadratic_loss(&a));
    assert_eq!(r.stop, Stop::Converged(Convergence::TargetLoss), "{r}");
    assert!(r.converged() && r.loss <= 1e-6, "{r}");
    assert!(r.to_string().contains("the loss reached its target"), "{r}");

    let c = Array::from_vec(vec![0.0f64; 3]);
    let r = minimize(
        Optimizer::adam(0.1).on_iteration(|it| match it.iter {
            3 => ControlFlow::Break(()),
            _ => ControlFlow::Continue(()),
        }),
        &c,
        quadratic_loss(&a),
    );
    assert_eq!((r.stop.clone(), r.iterations), (Stop::Callback, 3), "{r}");
    assert!(!r.converged(), "{r}");
}

#[test]
fn a_loss_that_stops_changing_converged_at_a_minimum_and_stalled_elsewhere() {
    // Near the minimum of (c - a)^2 + 1 the loss stops changing (relative 1e-12): converged.
    let a = Array::from_vec(vec![0.7f64]);
    let lifted_loss = |tape: &mut Tape, c: &Array<f64>| {
        let l = Array::zeros(1);
        tape.launch(lifted, 1, (c, &a, &l));
        l
    };
    let c = Array::from_vec(vec![0.0f64]);
    let r = minimize(
        Optimizer::gradient_descent(0.2)
            .max_iters(10_000)
            .loss_tol(1e-12),
        &c,
        lifted_loss,
    );
    assert_eq!(r.stop, Stop::Converged(Convergence::LossChange), "{r}");
    assert!((c.get(0) - 0.7).abs() < 1e-5, "{r}");

    // A learning rate far too small: the loss barely changes while the gradient is large.
    let c = Array::from_vec(vec![0.0f64]);
    let r = minimize(
        Optimizer::gradient_descent(1e-14)
            .max_iters(100)
            .loss_tol(1e-12),
        &c,
        lifted_loss,
    );
    assert!(
        matches!(&r.stop, Stop::Stalled(m) if m.contains("gradient norm")),
        "{r}"
    );
    assert!(!r.converged() && r.iterations == 1, "{r}");
    assert!(r.to_string().contains("NOT converged, stalled"), "{r}");
}
