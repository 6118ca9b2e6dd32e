//! The optimizers on problems with known minimizers, their bounds, stops and errors.

use std::ops::ControlFlow;

use adflex_optim::{Bounds, Convergence, Optimizer, Params, Stop};
use adflex_runtime::checkpoint::checkpointed;
use adflex_runtime::prelude::*;

/// `loss += sum_i w_i |x_i - target_i|^2`.
#[diff_kernel]
fn weighted_sq<R: Real>(x: &Array<Vec3<R>>, target: &Array<Vec3<R>>, w: R, loss: &Array<R>) {
    let i = tid();
    let d = x[i] - target[i];
    loss.atomic_add(0, w * dot(d, d));
}

/// `loss += (c_i - a_i)^2 (1 + c_i^2)`: a nonquadratic scalar problem, minimum at `c = a`.
#[diff_kernel]
fn bowl<R: Real>(c: &Array<R>, a: &Array<R>, loss: &Array<R>) {
    let i = tid();
    let d = c[i] - a[i];
    loss.atomic_add(0, d * d * (1.0 + c[i] * c[i]));
}

use adflex_macros::diff_kernel;

fn targets() -> Array<Vec3<f64>> {
    Array::from_vec(vec![Vec3::new(1.0, -2.0, 0.5), Vec3::new(0.0, 3.0, -1.0)])
}

fn solve(opt: Optimizer<'_>) -> (Array<Vec3<f64>>, Array<f32>, adflex_optim::Report) {
    let x = Array::from_vec(vec![Vec3::zeros(); 2]).named("x");
    let c = Array::from_vec(vec![0.0f32, 0.0, 0.0]).named("c");
    let a = Array::from_vec(vec![0.5f32, -1.5, 2.0]);
    let target = targets();
    let report = opt
        .progress(false)
        .minimize(&Params::new().with(&x).with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(weighted_sq, 2, (&x, &target, 2.0, &l));
            let lc = Array::<f32>::zeros(1);
            tape.launch(bowl, 3, (&c, &a, &lc));
            // Both losses in one f64 array: the f32 one is summed through a host step.
            let total = Array::<f64>::zeros(1);
            let (lb, lcb, tb) = (l.clone(), lc.clone(), total.clone());
            tape.record_fn(
                "sum",
                &[&l, &lc],
                &[&total],
                move || tb.set(0, lb.get(0) + lcb.get(0) as f64),
                {
                    let (l, lc, total) = (l.clone(), lc.clone(), total.clone());
                    move || {
                        let g = total.grad_buffer().unwrap().get(0);
                        l.ensure_grad().modify(|v| v[0] += g);
                        lc.ensure_grad().modify(|v| v[0] += g as f32);
                        Ok(())
                    }
                },
            );
            Ok(total)
        })
        .unwrap();
    (x, c, report)
}

fn assert_solved(x: &Array<Vec3<f64>>, c: &Array<f32>, tol: f64, what: &str) {
    for (got, want) in x.to_vec().iter().zip(targets().to_vec()) {
        assert!(
            (got - want).norm() < tol,
            "{what}: x = {got:?}, want {want:?}"
        );
    }
    for (got, want) in c.to_vec().iter().zip([0.5f32, -1.5, 2.0]) {
        assert!(
            ((got - want) as f64).abs() < tol,
            "{what}: c = {got}, want {want}"
        );
    }
}

#[test]
fn lbfgs_adam_and_gradient_descent_find_the_minimum_of_vec3_and_f32_parameters() {
    let (x, c, r) = solve(Optimizer::lbfgs().max_iters(50).grad_tol(1e-5));
    assert_solved(&x, &c, 1e-3, "L-BFGS");
    assert!(r.iterations < 30, "{r}");
    assert_eq!(r.history.len(), r.iterations + 1);
    assert!(r.loss < 1e-6 && r.initial_loss > 10.0, "{r}");

    let (x, c, r) = solve(Optimizer::adam(0.05).max_iters(2000).grad_tol(1e-4));
    assert_solved(&x, &c, 1e-2, "Adam");
    assert_eq!(
        r.stop,
        Stop::Converged(Convergence::GradientTolerance),
        "{r}"
    );

    let (x, c, r) = solve(
        Optimizer::gradient_descent(0.02)
            .max_iters(3000)
            .grad_tol(1e-4),
    );
    assert_solved(&x, &c, 1e-2, "gradient descent");
    assert_eq!(
        r.stop,
        Stop::Converged(Convergence::GradientTolerance),
        "{r}"
    );
    // The history's losses decrease for this convex problem and a small step.
    let l = r.losses();
    assert!(l.windows(2).all(|w| w[1] <= w[0] + 1e-12));
}

/// Minimizes `(c - a)^2 (1 + c^2)` with `c` bounded; returns the final `c`.
fn bounded(opt: Optimizer<'_>, start: f64, a: f64, bounds: Bounds) -> Result<f64, Error> {
    let c = Array::from_vec(vec![start]).named("c");
    let a = Array::from_vec(vec![a]);
    opt.progress(false)
        .minimize(&Params::new().bounded(&c, bounds), |tape| {
            let l = Array::zeros(1);
            tape.launch(bowl, 1, (&c, &a, &l));
            Ok(l)
        })?;
    Ok(c.get(0))
}

#[test]
fn bounds_keep_parameters_inside() {
    for opt in [Optimizer::adam(0.1), Optimizer::gradient_descent(0.05)] {
        // The unconstrained minimum (-1) is outside: projection ends on the bound.
        let c = bounded(opt.max_iters(500), 1.0, -1.0, Bounds::positive()).unwrap();
        assert!(c.abs() < 1e-9, "{c}");
    }
    // L-BFGS approaches the bound from inside, and finds interior minima exactly.
    let c = bounded(
        Optimizer::lbfgs().max_iters(60),
        1.0,
        -1.0,
        Bounds::positive(),
    )
    .unwrap();
    assert!(c > 0.0 && c < 1e-3, "{c}");
    let c = bounded(Optimizer::lbfgs(), 0.2, 0.7, Bounds::between(0.1, 0.9)).unwrap();
    assert!((c - 0.7).abs() < 1e-6, "{c}");
    let c = bounded(Optimizer::lbfgs(), -3.0, -1.5, Bounds::at_most(-0.5)).unwrap();
    assert!((c + 1.5).abs() < 1e-6, "{c}");
    // Starting on a bound is refused by L-BFGS, naming the component.
    let err = bounded(Optimizer::lbfgs(), 0.0, 1.0, Bounds::positive()).unwrap_err();
    assert!(err.to_string().contains("c[0]"), "{err}");
}

#[test]
fn the_reported_gradient_norm_is_the_parameters_even_at_a_bound() {
    // Towards the upper bound c = 1 of `Bounds::between(0, 1)` (the minimum, a = 2, is
    // outside), dc/du = s (1 - s) rounds to 0 once u > 37: the norm reported is still |dL/dc|
    // at the iterate, never 0, inf or NaN.
    let c = Array::from_vec(vec![0.5f64]);
    let a = Array::from_vec(vec![2.0f64]);
    let (mut norms, mut evaluations) = (Vec::new(), Vec::new());
    Optimizer::lbfgs()
        .progress(false)
        .max_iters(200)
        .on_iteration(|it| {
            norms.push(it.grad_norm);
            evaluations.push(it.evaluations);
            ControlFlow::Continue(())
        })
        .minimize(
            &Params::new().bounded(&c, Bounds::between(0.0, 1.0)),
            |tape| {
                let l = Array::zeros(1);
                tape.launch(bowl, 1, (&c, &a, &l));
                Ok(l)
            },
        )
        .unwrap();
    assert!(norms.iter().all(|g| g.is_finite()), "{norms:?}");
    // The count of evaluations never goes back (argmin may end with its problem taken out).
    assert!(
        evaluations.windows(2).all(|w| w[0] <= w[1]),
        "{evaluations:?}"
    );
    let last = *norms.last().unwrap();
    let x = c.get(0);
    assert!(x > 0.999, "{x}");
    let exact = (2.0 * (x - 2.0) * (1.0 + x * x) + 2.0 * x * (x - 2.0).powi(2)).abs();
    assert!((last - exact).abs() < 1e-3 * exact, "{last} vs {exact}");
}

#[test]
fn the_callback_sees_every_iteration_and_can_stop() {
    let c = Array::from_vec(vec![3.0f64]);
    let a = Array::from_vec(vec![0.0f64]);
    let mut seen = Vec::new();
    let r = Optimizer::adam(0.1)
        .progress(false)
        .on_iteration(|it| {
            seen.push(it.iter);
            if it.iter == 4 {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(bowl, 1, (&c, &a, &l));
            Ok(l)
        })
        .unwrap();
    assert_eq!(seen, vec![0, 1, 2, 3, 4]);
    assert_eq!(
        (r.stop, r.iterations, r.evaluations),
        (Stop::Callback, 4, 5)
    );
    // The parameter holds the best value, whose loss the report gives.
    let l = c.get(0).powi(2) * (1.0 + c.get(0).powi(2));
    assert_eq!(l, r.loss);
    let r = Optimizer::lbfgs()
        .progress(false)
        .target_loss(1e-3)
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(bowl, 1, (&c, &a, &l));
            Ok(l)
        })
        .unwrap();
    assert_eq!(r.stop, Stop::Converged(Convergence::TargetLoss));
    assert!(r.converged(), "{r}");
    assert!(r.loss <= 1e-3);
}

#[test]
fn a_parameter_the_loss_ignores_and_a_diverging_loss_are_errors() {
    let c = Array::from_vec(vec![1.0f64]).named("c");
    let unused = Array::from_vec(vec![1.0f64]).named("unused");
    let a = Array::from_vec(vec![0.0f64]);
    let err = Optimizer::lbfgs()
        .progress(false)
        .minimize(&Params::new().with(&c).with(&unused), |tape| {
            let l = Array::zeros(1);
            tape.launch(bowl, 1, (&c, &a, &l));
            Ok(l)
        })
        .unwrap_err();
    assert!(
        matches!(err, Error::InvalidInput { ref what, .. } if what.contains("unused")),
        "{err}"
    );
    assert!(!err.to_string().contains("requires_grad"), "{err}");

    let a = Array::from_vec(vec![f64::NAN]);
    let err = Optimizer::adam(0.1)
        .progress(false)
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(bowl, 1, (&c, &a, &l));
            Ok(l)
        })
        .unwrap_err();
    assert!(err.to_string().contains("loss (evaluation 1)"), "{err}");
    // Newton-CG names the loss and the evaluation too (not the product's gradient).
    let cd = Array::from_vec(vec![Dual::constant(1.0)]);
    let ad = Array::from_vec(vec![Dual::constant(f64::NAN)]);
    let err = Optimizer::newton_cg()
        .progress(false)
        .minimize_newton(&Params::new().with(&cd), |tape| {
            let l = Array::<Dual>::zeros(1);
            tape.launch(bowl, 1, (&cd, &ad, &l));
            Ok(l)
        })
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("the loss") && err.contains("NaN") && err.contains("evaluation 1"),
        "{err}"
    );
}

/// `loss += w (c - 3)^2 + sqrt(2 - c)`: pulled towards 3, NaN past the cliff at `c = 2`.
#[diff_kernel]
fn cliff<R: Real>(c: &Array<R>, w: R, loss: &Array<R>) {
    let d = c[0] - 3.0;
    loss.atomic_add(0, w * d * d + sqrt(2.0 - c[0]));
}

/// `loss += (c - 1.5)^2`, and NaN past 2.
#[diff_kernel]
fn nan_past_two<R: Real>(c: &Array<R>, loss: &Array<R>) {
    let d = c[0] - 1.5;
    loss.atomic_add(0, d * d + 0.0 * sqrt(2.0 - c[0]));
}

fn cliff_loss(c: f64, w: f64) -> f64 {
    w * (c - 3.0).powi(2) + (2.0 - c).sqrt()
}

#[test]
fn an_error_leaves_the_best_values_evaluated_and_lbfgs_keeps_its_best_point() {
    // Gradient descent steps over the cliff: the run diverged, and `c` holds the best value
    // before.
    let c = Array::from_vec(vec![0.0f64]).named("c");
    let mut losses = Vec::new();
    let r = Optimizer::gradient_descent(0.2)
        .progress(false)
        .on_iteration(|it| {
            losses.push(it.loss);
            ControlFlow::Continue(())
        })
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(cliff, 1, (&c, 1.0, &l));
            Ok(l)
        })
        .unwrap();
    assert!(
        matches!(&r.stop, Stop::Diverged(m) if m.contains("is NaN") && m.contains("learning rate")),
        "{r}"
    );
    assert!(
        !r.converged() && r.to_string().contains("NOT converged, diverged"),
        "{r}"
    );
    let best = losses.iter().cloned().fold(f64::INFINITY, f64::min);
    assert!(
        c.get(0) < 2.0 && cliff_loss(c.get(0), 1.0) == best,
        "c = {}",
        c.get(0)
    );

    // L-BFGS's line search backs off from points where the loss is NaN (its first step from
    // c = -3 lands at 6): the minimum at 1.5, next to the NaN region past 2, is found.
    let c = Array::from_vec(vec![-3.0f64]).named("c");
    let r = Optimizer::lbfgs()
        .progress(false)
        .max_iters(50)
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(nan_past_two, 1, (&c, &l));
            Ok(l)
        })
        .unwrap();
    assert!((c.get(0) - 1.5).abs() < 1e-6, "{r}, c = {}", c.get(0));
    assert!(r.converged(), "{r}");

    // With the infimum on the edge of the NaN region no point satisfies the line search's
    // conditions: the run ends (no error) with the best point it evaluated and the reason,
    // not converged (the gradient there is large).
    let c = Array::from_vec(vec![0.0f64]).named("c");
    let r = Optimizer::lbfgs()
        .progress(false)
        .max_iters(50)
        .minimize(&Params::new().with(&c), |tape| {
            let l = Array::zeros(1);
            tape.launch(cliff, 1, (&c, 0.1, &l));
            Ok(l)
        })
        .unwrap();
    // (L-BFGS restarts from its best point after each failed line search, so it creeps
    // towards the edge until its line search fails without progress or the budget is spent.)
    assert!(
        matches!(&r.stop, Stop::LineSearchFailed(_) | Stop::MaxIterations),
        "{r}"
    );
    assert!(!r.converged(), "{r}");
    let x = c.get(0);
    assert!(x < 2.0 && r.loss == cliff_loss(x, 0.1), "{r}, c = {x}");
    assert!(r.loss < r.initial_loss, "{r}, c = {x}");
}

#[test]
fn minimize_with_takes_a_checkpointed_rollout() {
    // x_{t+1} = k x_t for 12 steps from x_0 = 1; loss = (x_T - 2)^2; minimum at k = 2^(1/12).
    #[diff_kernel]
    fn scale<R: Real>(x: &Array<R>, k: &Array<R>, y: &Array<R>) {
        y[0] = k[0] * x[0];
    }
    #[diff_kernel]
    fn miss<R: Real>(x: &Array<R>, loss: &Array<R>) {
        loss.atomic_add(0, (x[0] - 2.0) * (x[0] - 2.0));
    }
    let k = Array::from_vec(vec![1.0f64]).named("k");
    let x0 = Array::from_vec(vec![1.0f64]);
    let r = Optimizer::lbfgs()
        .progress(false)
        .grad_tol(1e-10)
        .minimize_with(&Params::new().bounded(&k, Bounds::positive()), || {
            let step = |tape: &mut Tape, x: &Array<f64>| {
                let y = Array::zeros(1);
                tape.launch(scale, 1, (x, &k, &y));
                Ok(y)
            };
            let out = checkpointed(&x0, 12, 4, step, |tape, x| {
                let l = Array::zeros(1);
                tape.launch(miss, 1, (x, &l));
                Ok(l)
            })?;
            Ok(out.loss.get(0))
        })
        .unwrap();
    assert!(
        (k.get(0) - 2f64.powf(1.0 / 12.0)).abs() < 1e-7,
        "{} {r}",
        k.get(0)
    );
}

/// `r_i = p_0 exp(p_1 t_i) + p_2 - y_i` with `t_i = i / 10`: a nonlinear least-squares fit.
#[diff_kernel]
fn exp_residual<R: Real>(p: &Array<R>, y: &Array<R>, r: &Array<R>) {
    let i = tid();
    let t = 0.1 * (i as R);
    r[i] = p[0] * exp(p[1] * t) + p[2] - y[i];
}

/// `loss = 100 (y - x^2)^2 + (1 - x)^2` (Rosenbrock) plus a quartic coupling of a third
/// variable with a saddle at the start.
#[diff_kernel]
fn rosenbrock3<R: Real>(p: &Array<R>, loss: &Array<R>) {
    let x = p[0];
    let y = p[1];
    let z = p[2];
    loss.atomic_add(
        0,
        100.0 * (y - x * x) * (y - x * x) + (1.0 - x) * (1.0 - x) + z * z * z * z - z * z,
    );
}

fn samples() -> Array<f64> {
    Array::from_vec(
        (0..30)
            .map(|i| 2.0 * (-1.5 * 0.1 * i as f64).exp() + 0.3)
            .collect(),
    )
}

/// Gauss-Newton and Levenberg-Marquardt fit a nonlinear model in a few iterations (quadratic
/// convergence at a zero-residual solution), counting their passes over the simulation.
#[test]
fn gauss_newton_and_levenberg_marquardt_fit_in_a_few_iterations() {
    let y = samples();
    for opt in [Optimizer::gauss_newton(), Optimizer::levenberg_marquardt()] {
        let p = Array::from_vec(vec![1.0f64, 0.0, 0.0]).named("p");
        let report = opt
            .grad_tol(1e-13)
            .progress(false)
            .least_squares(&Params::new().with(&p), |tape| {
                let r = Array::zeros(30);
                tape.launch(exp_residual, 30, (&p, &y, &r));
                Ok(r)
            })
            .unwrap();
        assert!(report.converged(), "{report}");
        assert!(report.iterations <= 15, "{report}");
        let v = p.to_vec();
        assert!(
            (v[0] - 2.0).abs() < 1e-9 && (v[1] + 1.5).abs() < 1e-9 && (v[2] - 0.3).abs() < 1e-9,
            "{v:?}: {report}"
        );
        // Every iteration at least records, differentiates and multiplies once.
        assert!(report.passes >= 4 * report.iterations, "{report}");
        assert!(report.history.last().unwrap().passes <= report.passes);
    }
}

/// Newton-CG leaves a region of negative curvature (along z, near the maximum z = 0) for the
/// minimum, and takes fewer iterations than L-BFGS through Rosenbrock's valley.
#[test]
fn newton_cg_handles_negative_curvature_and_beats_lbfgs_on_iterations() {
    let p = Array::from_vec(vec![
        Dual::constant(-1.2),
        Dual::constant(1.0),
        Dual::constant(0.1),
    ]);
    let newton = Optimizer::newton_cg()
        .grad_tol(1e-10)
        .progress(false)
        .minimize_newton(&Params::new().with(&p), |tape| {
            let l = Array::<Dual>::zeros(1);
            tape.launch(rosenbrock3, 1, (&p, &l));
            Ok(l)
        })
        .unwrap();
    assert!(newton.converged(), "{newton}");
    let v: Vec<f64> = p.to_vec().iter().map(|d| d.re).collect();
    assert!(
        (v[0] - 1.0).abs() < 1e-8 && (v[1] - 1.0).abs() < 1e-8,
        "{v:?}"
    );
    // d2/dz2 = 12 z^2 - 2 < 0 at the start: the step follows the negative curvature to z^2 = 1/2.
    assert!((v[2] - 0.5f64.sqrt()).abs() < 1e-8, "{v:?}: {newton}");
    assert!(newton.loss < -0.25 + 1e-12, "{newton}");

    let q = Array::from_vec(vec![-1.2f64, 1.0, 0.1]);
    let lbfgs = Optimizer::lbfgs()
        .grad_tol(1e-10)
        .max_iters(500)
        .progress(false)
        .minimize(&Params::new().with(&q), |tape| {
            let l = Array::<f64>::zeros(1);
            tape.launch(rosenbrock3, 1, (&q, &l));
            Ok(l)
        })
        .unwrap();
    assert!(lbfgs.converged(), "{lbfgs}");
    assert!(
        newton.iterations < lbfgs.iterations,
        "Newton-CG {} iterations, L-BFGS {}",
        newton.iterations,
        lbfgs.iterations
    );
}

/// `r_i = a exp(b t_i) + c - y_i` with `a` given and `bc = [b, c]`: [`exp_residual`] with
/// its first parameter held.
#[diff_kernel]
fn exp_residual_held<R: Real>(bc: &Array<R>, a: R, y: &Array<R>, r: &Array<R>) {
    let i = tid();
    let t = 0.1 * (i as R);
    r[i] = a * exp(bc[0] * t) + bc[1] - y[i];
}

/// Gauss-Newton and Levenberg-Marquardt keep bounds by projection. The fit of `a exp(b t) + c`
/// to samples of `2 exp(-1.5 t) + 0.3` with `a <= 1.5` ends with `a` exactly on its bound and
/// `(b, c)` the fit with `a` held at 1.5 (found without bounds on a model of two parameters),
/// from a start inside and from one on the bound; a bound the fit does not reach changes
/// nothing; the projected gradient is what converges.
#[test]
fn gauss_newton_and_levenberg_marquardt_keep_bounds_by_projection() {
    let y = samples();
    let fit = |opt: Optimizer<'_>, start: [f64; 3], bounds: Bounds| {
        let p = Array::from_vec(start.to_vec()).named("p");
        // Converged by the projected gradient (the full one stays large at the bound). The
        // residual is not 0 at the bound, so Gauss-Newton converges linearly there.
        let report = opt
            .grad_tol_rel(1e-8)
            .progress(false)
            .least_squares(&Params::new().bounded(&p, bounds), |tape| {
                let r = Array::zeros(30);
                tape.launch(exp_residual, 30, (&p, &y, &r));
                Ok(r)
            })
            .unwrap();
        assert!(report.converged(), "{report}");
        (p.to_vec(), report)
    };
    // The fit with `a` held on the bound, by unbounded Gauss-Newton on (b, c).
    let bc = Array::from_vec(vec![0.0f64, 0.0]).named("bc");
    let held = Optimizer::gauss_newton()
        .grad_tol(1e-9)
        .progress(false)
        .least_squares(&Params::new().with(&bc), |tape| {
            let r = Array::zeros(30);
            tape.launch(exp_residual_held, 30, (&bc, 1.5, &y, &r));
            Ok(r)
        })
        .unwrap();
    assert!(held.converged(), "{held}");
    let bc = bc.to_vec();
    for opt in [Optimizer::gauss_newton, Optimizer::levenberg_marquardt] {
        for start in [[1.0, 0.0, 0.0], [1.5, 0.0, 0.0]] {
            let (p, report) = fit(opt(), start, Bounds::between(-10.0, 1.5));
            assert_eq!(p[0], 1.5, "{report}");
            assert!(
                (p[1] - bc[0]).abs() < 1e-6 && (p[2] - bc[1]).abs() < 1e-6,
                "{p:?} against {bc:?}: {report}"
            );
            // Far from 0 (the bound holds `a` back): the gradient pushes `a` out.
            assert!(report.loss > 1e-4, "{report}");
        }
        let (free, _) = fit(opt(), [1.0, 0.0, 0.0], Bounds::NONE);
        let (wide, report) = fit(opt(), [1.0, 0.0, 0.0], Bounds::between(-10.0, 10.0));
        for k in 0..3 {
            assert!(
                (free[k] - wide[k]).abs() < 1e-9,
                "{free:?} {wide:?}: {report}"
            );
        }
        assert!((wide[0] - 2.0).abs() < 1e-8 && (wide[1] + 1.5).abs() < 1e-8);
    }
}

/// The second-order methods say what they cannot do: another method's entry point, a start
/// outside the bounds, parameters that are not `Dual` for Newton-CG, a residual that is not finite.
#[test]
fn second_order_methods_refuse_what_they_cannot_run() {
    let y = samples();
    let p = Array::from_vec(vec![1.0f64, 0.0, 0.0]).named("p");
    let residual = |tape: &mut Tape| {
        let r = Array::zeros(30);
        tape.launch(exp_residual, 30, (&p, &y, &r));
        Ok(r)
    };
    let e = Optimizer::lbfgs()
        .progress(false)
        .least_squares(&Params::new().with(&p), residual)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("least_squares") && e.contains("Gauss-Newton"),
        "{e}"
    );
    let e = Optimizer::gauss_newton()
        .progress(false)
        .minimize(&Params::new().with(&p), |tape| {
            let l = Array::<f64>::zeros(1);
            tape.launch(rosenbrock3, 1, (&p, &l));
            Ok(l)
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("least_squares"), "{e}");
    let outside = Array::from_vec(vec![1.0f64, -0.5, 0.0]).named("p");
    let e = Optimizer::levenberg_marquardt()
        .progress(false)
        .least_squares(
            &Params::new().bounded(&outside, Bounds::positive()),
            |tape| {
                let r = Array::zeros(30);
                tape.launch(exp_residual, 30, (&outside, &y, &r));
                Ok(r)
            },
        )
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("p[1]") && e.contains("outside its bounds"),
        "{e}"
    );
    let e = Optimizer::newton_cg()
        .progress(false)
        .minimize_newton(&Params::new().with(&p), |tape| {
            let l = Array::<f64>::zeros(1);
            tape.launch(rosenbrock3, 1, (&p, &l));
            Ok(l)
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("Dual"), "{e}");
    let nan = Array::from_vec(vec![f64::NAN; 30]);
    let e = Optimizer::gauss_newton()
        .progress(false)
        .least_squares(&Params::new().with(&p), |tape| {
            let r = Array::zeros(30);
            tape.launch(exp_residual, 30, (&p, &nan, &r));
            Ok(r)
        })
        .unwrap_err()
        .to_string();
    assert!(e.contains("residual") && e.contains("NaN"), "{e}");
}

/// A Levenberg-Marquardt trial point where the simulation fails (a non-finite residual) is a
/// rejected step, not the end of the run.
#[test]
fn a_failing_trial_point_is_a_rejected_step() {
    // r = [10 (x - 3), sqrt(4 - x) - 1]: undefined (NaN) past x = 4, where a full step from
    // x = -20 lands; the minimum is at x = 3.
    #[diff_kernel]
    fn guarded<R: Real>(p: &Array<R>, r: &Array<R>) {
        let x = p[0];
        r[0] = 10.0 * (x - 3.0);
        r[1] = sqrt(4.0 - x) - 1.0;
    }
    let p = Array::from_vec(vec![-20.0f64]);
    let report = Optimizer::levenberg_marquardt()
        .grad_tol(1e-12)
        .progress(false)
        .least_squares(&Params::new().with(&p), |tape| {
            let r = Array::zeros(2);
            tape.launch(guarded, 1, (&p, &r));
            Ok(r)
        })
        .unwrap();
    assert!(report.converged(), "{report}");
    assert!((p.get(0) - 3.0).abs() < 1e-9, "{}: {report}", p.get(0));
}

/// A loss that keeps falling up to a wall where it stops being defined: Newton-CG's trust
/// region shrinks against the wall and the run says so (`Stop::StepFailed`, not converged:
/// the gradient is 1 there); with an evaluation budget it stops within the budget, even
/// inside its retries.
#[test]
fn newton_cg_at_a_wall_fails_by_name_and_keeps_its_budget() {
    #[diff_kernel]
    fn walled<R: Real>(p: &Array<R>, loss: &Array<R>) {
        let x = p[0];
        loss.atomic_add(0, x + 0.0 * sqrt(x - 0.999));
    }
    let run = |opt: Optimizer| {
        let p = Array::from_vec(vec![Dual::constant(1.5)]);
        opt.progress(false)
            .max_iters(1000)
            .minimize_newton(&Params::new().with(&p), |tape| {
                let l = Array::<Dual>::zeros(1);
                tape.launch(walled, 1, (&p, &l));
                Ok(l)
            })
            .unwrap()
    };
    let r = run(Optimizer::newton_cg());
    assert!(
        matches!(&r.stop, Stop::StepFailed(m) if m.contains("trust region")),
        "{r}"
    );
    assert!(!r.converged() && r.loss < 1.0 && r.loss >= 0.999, "{r}");
    assert!(
        r.evaluations < 60,
        "the retries stop once the region cannot move x: {r}"
    );
    assert!(r.to_string().contains("no step lowered the loss"), "{r}");
    let r = run(Optimizer::newton_cg().max_evals(8));
    assert_eq!(r.stop, Stop::MaxEvaluations, "{r}");
    assert!(r.evaluations <= 8, "{r}");
}

/// Gauss-Newton and Levenberg-Marquardt keep an evaluation budget, inside their backtracking
/// and damping too.
#[test]
fn gauss_newton_and_levenberg_marquardt_keep_their_budget() {
    let y = samples();
    for budget in [1, 2, 3, 5] {
        for opt in [Optimizer::gauss_newton(), Optimizer::levenberg_marquardt()] {
            // A far start: the first steps overshoot and backtrack.
            let p = Array::from_vec(vec![8.0f64, 3.0, -4.0]).named("p");
            let report = opt
                .grad_tol(1e-13)
                .max_evals(budget)
                .progress(false)
                .least_squares(&Params::new().with(&p), |tape| {
                    let r = Array::zeros(30);
                    tape.launch(exp_residual, 30, (&p, &y, &r));
                    Ok(r)
                })
                .unwrap();
            assert_eq!(report.stop, Stop::MaxEvaluations, "{report}");
            assert!(report.evaluations <= budget, "budget {budget}: {report}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Gauss-Newton by the KKT system: a state x_i that solves x_i³ + x_i = p0 + i p1 (i = 0..4),
// residuals x - target (more residuals than parameters, so the step is a least-squares one).

/// `c_i = x_i³ + x_i - p0 - w_i p1`.
#[diff_kernel]
fn cubic_constraint<R: Real>(x: &Array<R>, p: &Array<R>, w: &Array<R>, c: &Array<R>) {
    let i = tid();
    c[i] = x[i] * x[i] * x[i] + x[i] - p[0] - w[i] * p[1];
}

/// The root `s` of the constraint as a constant, and one Newton step from it: the value stays
/// the root, the derivative is the implicit function theorem's `(1, w_i) / (3 s² + 1)`.
#[diff_kernel]
fn cubic_solved<R: Real>(s: &Array<R>, p: &Array<R>, w: &Array<R>, x: &Array<R>) {
    let i = tid();
    let r = s[i];
    x[i] = r - (r * r * r + r - p[0] - w[i] * p[1]) / (3.0 * r * r + 1.0);
}

#[diff_kernel]
fn miss<R: Real>(x: &Array<R>, target: &Array<R>, r: &Array<R>) {
    let i = tid();
    r[i] = x[i] - target[i];
}

fn cubic_root(q: f64) -> f64 {
    let mut x = 0.0f64;
    for _ in 0..80 {
        x -= (x * x * x + x - q) / (3.0 * x * x + 1.0);
    }
    x
}

const N: usize = 4;

struct Cubic {
    p: Array<f64>,
    w: Array<f64>,
    target: Array<f64>,
}

impl Cubic {
    fn new(weights: Vec<f64>) -> Self {
        Cubic {
            p: Array::from_vec(vec![0.2, 0.1]).named("p"),
            w: Array::from_vec(weights),
            target: Array::from_vec(vec![0.3, 0.5, 0.55, 0.9]),
        }
    }
    fn roots(&self) -> Vec<f64> {
        let (p, w) = (self.p.to_vec(), self.w.to_vec());
        w.iter().map(|w| cubic_root(p[0] + w * p[1])).collect()
    }
    fn residuals(&self, tape: &mut Tape, x: &Array<f64>) -> Array<f64> {
        let r = Array::zeros(N).named("miss");
        tape.launch(miss, N, (x, &self.target, &r));
        r
    }
    fn solve(&self, tape: &mut Tape) -> Result<(Array<f64>, Array<f64>), Error> {
        let s = Array::from_vec(self.roots());
        let x = Array::zeros(N).named("x");
        tape.launch(cubic_solved, N, (&s, &self.p, &self.w, &x));
        Ok((x.clone(), self.residuals(tape, &x)))
    }
    fn constraint(&self, tape: &mut Tape, x: &Array<f64>) -> Array<f64> {
        let c = Array::zeros(N).named("c");
        tape.launch(cubic_constraint, N, (x, &self.p, &self.w, &c));
        c
    }
    fn run(&self, opt: Optimizer<'_>) -> Result<adflex_optim::Report, Error> {
        opt.progress(false).least_squares_kkt(
            &Params::new().with(&self.p),
            |tape| self.solve(tape),
            |tape, x| Ok((self.constraint(tape, x), self.residuals(tape, x))),
        )
    }
}

#[test]
fn the_kkt_step_is_the_gauss_newton_step_and_converges() {
    let cubic = Cubic::new(vec![0.0, 1.0, 2.0, 3.0]);
    // The Gauss-Newton step at the start, by hand: J_ij = dx_i/dp_j = (1, w_i) / (3 x_i² + 1),
    // dp = -(JᵀJ)⁻¹ Jᵀ r.
    let x = cubic.roots();
    let (w, t) = (cubic.w.to_vec(), cubic.target.to_vec());
    let (mut a, mut b) = ([[0.0; 2]; 2], [0.0; 2]);
    for i in 0..N {
        let d = 1.0 / (3.0 * x[i] * x[i] + 1.0);
        let j = [d, w[i] * d];
        for r in 0..2 {
            b[r] -= j[r] * (x[i] - t[i]);
            for c in 0..2 {
                a[r][c] += j[r] * j[c];
            }
        }
    }
    let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    let dp = [
        (a[1][1] * b[0] - a[0][1] * b[1]) / det,
        (a[0][0] * b[1] - a[1][0] * b[0]) / det,
    ];
    let p0 = cubic.p.to_vec();
    let one = cubic
        .run(Optimizer::kkt_gauss_newton().max_iters(1))
        .unwrap();
    assert_eq!(one.iterations, 1);
    // The full step was taken (one evaluation at the start, one at the trial point).
    assert_eq!(one.evaluations, 2, "{one}");
    // 6 unknowns (4 states, 2 parameters): 6 tangent sweeps and one recording.
    assert_eq!(one.sweeps, 7, "{one}");
    let p1 = cubic.p.to_vec();
    for k in 0..2 {
        assert!(
            (p1[k] - (p0[k] + dp[k])).abs() < 1e-12,
            "p{k}: {} against the Gauss-Newton step's {}",
            p1[k],
            p0[k] + dp[k]
        );
    }
    // From there it converges to the least-squares fit (a nonzero residual): the gradient
    // vanishes.
    cubic.p.assign(&p0);
    let report = cubic
        .run(Optimizer::kkt_gauss_newton().grad_tol(1e-8).max_iters(30))
        .unwrap();
    assert!(report.converged(), "{report}");
    assert!(report.iterations <= 10, "{report}");
    assert!(report.loss > 1e-4, "a fit with a residual: {report}");
    // After the first step, the columns come in three colours (the states touch disjoint
    // rows; p0 every constraint row; p1 all but the first): a recording, three sweeps and
    // the check's two per step.
    assert!(report.iterations >= 2, "{report}");
    assert_eq!(report.sweeps, 7 + 6 * (report.iterations - 1), "{report}");
}

/// `r[0] += x_i - share_i`: a residual on the sum of the state (every unknown in one row).
#[diff_kernel]
fn sum_miss<R: Real>(x: &Array<R>, share: &Array<R>, r: &Array<R>) {
    let i = tid();
    r.atomic_add(0, x[i] - share[i]);
}

/// A residual that reads every unknown of the state (their sum) is one dense row of the KKT
/// system: taken by a reverse pass, it leaves the colouring to the sparse rows, so a later
/// step takes 7 sweeps (the recording, three colours: the states, `p0`, `p1`; the dense row;
/// the check's two) where it would take one per unknown (302). The fit is Gauss-Newton's on
/// the same residuals (matrix free, through the solve).
#[test]
fn a_residual_on_every_unknown_is_one_reverse_pass_of_the_kkt_method() {
    let n = 300;
    let w = Array::from_vec((0..n).map(|i| i as f64 / n as f64).collect());
    let target = Array::from_vec((0..n).map(|i| 0.3 + 0.4 * i as f64 / n as f64).collect());
    let share = Array::from_vec(vec![0.6; n]);
    let p = Array::from_vec(vec![0.2, 0.1]).named("p");
    let residuals = |tape: &mut Tape, x: &Array<f64>| {
        let (r, total) = (Array::zeros(n).named("miss"), Array::zeros(1).named("sum"));
        tape.launch(miss, n, (x, &target, &r));
        tape.launch(sum_miss, n, (x, &share, &total));
        vec![r, total]
    };
    let solve = |tape: &mut Tape| -> Result<(Array<f64>, Vec<Array<f64>>), Error> {
        let (pv, wv) = (p.to_vec(), w.to_vec());
        let s = Array::from_vec(wv.iter().map(|w| cubic_root(pv[0] + w * pv[1])).collect());
        let x = Array::zeros(n).named("x");
        tape.launch(cubic_solved, n, (&s, &p, &w, &x));
        let r = residuals(tape, &x);
        Ok((x, r))
    };
    let report = Optimizer::kkt_gauss_newton()
        .grad_tol(1e-10)
        .max_iters(30)
        .progress(false)
        .least_squares_kkt(&Params::new().with(&p), solve, |tape, x| {
            let c = Array::zeros(n).named("c");
            tape.launch(cubic_constraint, n, (x, &p, &w, &c));
            Ok((c, residuals(tape, x)))
        })
        .unwrap();
    assert!(report.converged(), "{report}");
    // The point returned is the one that passed the test (its loss ties an earlier one's).
    assert!(report.grad_norm <= 1e-10, "{report}");
    assert!(report.iterations >= 2, "{report}");
    // The first step takes the columns one by one (302 unknowns, too few for probing) and the
    // recording, then 7 sweeps per step.
    let first = report.history[1].sweeps;
    assert_eq!(
        report.sweeps - first,
        7 * (report.iterations - 1),
        "{first} sweeps in the first step; {report}"
    );
    assert_eq!(first, 303, "{report}");
    let found = p.to_vec();
    p.assign(&[0.2, 0.1]);
    let gn = Optimizer::gauss_newton()
        .grad_tol(1e-10)
        .progress(false)
        .least_squares(&Params::new().with(&p), |tape| Ok(solve(tape)?.1))
        .unwrap();
    assert!(gn.converged(), "{gn}");
    let reference = p.to_vec();
    for k in 0..2 {
        assert!(
            (found[k] - reference[k]).abs() < 1e-8,
            "{found:?} {reference:?}"
        );
    }
}

/// The step does not depend on the parameters' units: with `p1` in units a billion times
/// smaller (its weights a billion times larger), the KKT system's entries span 18 orders of
/// magnitude, which unequilibrated pivots would call singular; the step is the same.
#[test]
fn the_kkt_step_does_not_depend_on_the_parameters_units() {
    let plain = Cubic::new(vec![0.0, 1.0, 2.0, 3.0]);
    let scaled = Cubic::new(vec![0.0, 1e9, 2e9, 3e9]);
    scaled.p.set(1, 0.1e-9);
    for cubic in [&plain, &scaled] {
        let report = cubic
            .run(Optimizer::kkt_gauss_newton().max_iters(1))
            .unwrap();
        assert_eq!(report.evaluations, 2, "the full step: {report}");
        assert!(report.to_string().contains("7 sweeps"), "{report}");
    }
    let (a, b) = (plain.p.to_vec(), scaled.p.to_vec());
    assert!((a[0] - b[0]).abs() < 1e-12, "{a:?} {b:?}");
    assert!((a[1] - b[1] * 1e9).abs() < 1e-12, "{a:?} {b:?}");
}

#[test]
fn the_kkt_method_refuses_what_it_cannot_solve() {
    let cubic = Cubic::new(vec![0.0, 1.0, 2.0, 3.0]);
    let err = |e: Error| e.to_string();
    // Residuals that differ between the two closures.
    let e = Optimizer::kkt_gauss_newton()
        .progress(false)
        .least_squares_kkt(
            &Params::new().with(&cubic.p),
            |tape| cubic.solve(tape),
            |tape, x| {
                let r = cubic.residuals(tape, x);
                let shifted = Array::zeros(N).named("shifted");
                tape.launch(
                    miss,
                    N,
                    (&r, &Array::from_vec(vec![0.0, 0.0, 1e-3, 0.0]), &shifted),
                );
                Ok((cubic.constraint(tape, x), shifted))
            },
        )
        .map(|_| ())
        .map_err(err)
        .unwrap_err();
    assert!(
        e.contains("`shifted` component 2") && e.contains("same residuals"),
        "{e}"
    );
    // A constraint with fewer equations than the state has unknowns.
    let e = Optimizer::kkt_gauss_newton()
        .progress(false)
        .least_squares_kkt(
            &Params::new().with(&cubic.p),
            |tape| cubic.solve(tape),
            |tape, x| {
                let c = Array::zeros(N - 1).named("short");
                tape.launch(cubic_constraint, N - 1, (x, &cubic.p, &cubic.w, &c));
                Ok((c, cubic.residuals(tape, x)))
            },
        )
        .map(|_| ())
        .map_err(err)
        .unwrap_err();
    assert!(
        e.contains("`short`") && e.contains("3 scalars and the state 4"),
        "{e}"
    );
    // Parameters the residuals cannot tell apart (every w_i = 1: p0 and p1 act alike).
    let twins = Cubic::new(vec![1.0; N]);
    let e = twins
        .run(Optimizer::kkt_gauss_newton())
        .map(|_| ())
        .map_err(err)
        .unwrap_err();
    assert!(e.contains("singular"), "{e}");
    // Another method, and a system above the size limit.
    let e = Optimizer::gauss_newton()
        .least_squares_kkt(
            &Params::new().with(&cubic.p),
            |tape| cubic.solve(tape),
            |tape, x| Ok((cubic.constraint(tape, x), cubic.residuals(tape, x))),
        )
        .map(|_| ())
        .map_err(err)
        .unwrap_err();
    assert!(e.contains("kkt_gauss_newton"), "{e}");
    let e = cubic
        .run(Optimizer::new(adflex_optim::Method::KktGaussNewton {
            largest: 13,
        }))
        .map(|_| ())
        .map_err(err)
        .unwrap_err();
    assert!(
        e.contains("14 rows (4 residuals + 2 x 4 state scalars + 2 parameters)")
            && e.contains("`largest` (13)"),
        "{e}"
    );
}

#[test]
fn closures_that_differentiate_differently_are_refused_at_the_first_step() {
    // `constrained`'s constraint weighs p1 twice as much as the solve in `residuals` does:
    // the same values at the solved state (p1's term is not zero, but the test only needs the
    // derivatives to differ), different derivatives.
    let cubic = Cubic::new(vec![0.0, 1.0, 2.0, 3.0]);
    let doubled = Array::from_vec(vec![0.0, 2.0, 4.0, 6.0]);
    let e = Optimizer::kkt_gauss_newton()
        .progress(false)
        .least_squares_kkt(
            &Params::new().with(&cubic.p),
            |tape| cubic.solve(tape),
            |tape, x| {
                // c_i = x³ + x - p0 - 2 w_i p1 + w_i p1 (held constant): the value of the
                // solve's constraint (zero), the derivative in p1 doubled.
                let c = Array::zeros(N).named("c");
                tape.launch(cubic_constraint, N, (x, &cubic.p, &doubled, &c));
                let shift = Array::from_vec(
                    cubic
                        .w
                        .to_vec()
                        .iter()
                        .map(|w| -w * cubic.p.get(1))
                        .collect(),
                );
                let c2 = Array::zeros(N).named("c2");
                tape.launch(miss, N, (&c, &shift, &c2));
                Ok((c2, cubic.residuals(tape, x)))
            },
        )
        .map(|_| ())
        .map_err(|e| e.to_string())
        .unwrap_err();
    assert!(e.contains("disagree with the gradient"), "{e}");
}

/// `x_i = s_i - (s_i³ + s_i - q_i) / (3 s_i² + 1)` per component, `q_i = a_i p0 + b_i p1`, from
/// the root `s_i`: the value is the root, the derivative the implicit function theorem's.
#[diff_kernel]
fn cubic_solved_vec3(
    s: &Array<Vec3<f64>>,
    p: &Array<f64>,
    a: &Array<Vec3<f64>>,
    b: &Array<Vec3<f64>>,
    x: &Array<Vec3<f64>>,
) {
    let i = tid();
    let r = s[i];
    let q = a[i] * p[0] + b[i] * p[1];
    let num = cw_mul(cw_mul(r, r), r) + r - q;
    let den = cw_mul(r, r) * 3.0 + vec3(1.0, 1.0, 1.0);
    x[i] = r - cw_div(num, den);
}

/// `c_i = x_i³ + x_i - a_i p0 - b_i p1`, per component.
#[diff_kernel]
fn cubic_constraint_vec3(
    x: &Array<Vec3<f64>>,
    p: &Array<f64>,
    a: &Array<Vec3<f64>>,
    b: &Array<Vec3<f64>>,
    c: &Array<Vec3<f64>>,
) {
    let i = tid();
    let y = x[i];
    c[i] = cw_mul(cw_mul(y, y), y) + y - a[i] * p[0] - b[i] * p[1];
}

#[diff_kernel]
fn miss_vec3(x: &Array<Vec3<f64>>, target: &Array<Vec3<f64>>, r: &Array<Vec3<f64>>) {
    let i = tid();
    r[i] = x[i] - target[i];
}

/// The KKT step with a state of `Vec3` (12 scalars in 4 elements) is the scalar problem's: the
/// same 12 cubics, as scalars, take the same first step and reach the same fit.
#[test]
fn the_kkt_step_with_a_vec3_state_is_the_scalar_one() {
    let n = 4;
    let a: Vec<Vec3<f64>> = (0..n)
        .map(|i| Vec3::new(1.0, 0.5 + 0.1 * i as f64, 0.2))
        .collect();
    let b: Vec<Vec3<f64>> = (0..n)
        .map(|i| Vec3::new(i as f64, 0.3, 1.0 - 0.2 * i as f64))
        .collect();
    let target: Vec<Vec3<f64>> = (0..n)
        .map(|i| Vec3::new(0.3 + 0.1 * i as f64, 0.5, 0.2 * i as f64))
        .collect();
    let p = Array::from_vec(vec![0.2, 0.1]).named("p");
    let (aa, ba, ta) = (
        Array::from_vec(a.clone()),
        Array::from_vec(b.clone()),
        Array::from_vec(target.clone()),
    );
    let roots = |p: &[f64]| -> Vec<Vec3<f64>> {
        (0..n)
            .map(|i| (a[i] * p[0] + b[i] * p[1]).map(cubic_root))
            .collect()
    };
    let residuals = |tape: &mut Tape, x: &Array<Vec3<f64>>| {
        let r = Array::zeros(n).named("miss");
        tape.launch(miss_vec3, n, (x, &ta, &r));
        r
    };
    let run = |opt: Optimizer<'_>| {
        opt.progress(false)
            .least_squares_kkt(
                &Params::new().with(&p),
                |tape| {
                    let s = Array::from_vec(roots(&p.to_vec()));
                    let x = Array::zeros(n).named("x");
                    tape.launch(cubic_solved_vec3, n, (&s, &p, &aa, &ba, &x));
                    Ok((x.clone(), residuals(tape, &x)))
                },
                |tape, x| {
                    let c = Array::zeros(n).named("c");
                    tape.launch(cubic_constraint_vec3, n, (x, &p, &aa, &ba, &c));
                    Ok((c, residuals(tape, x)))
                },
            )
            .unwrap()
    };
    // The scalar problem: the 12 components as the `Cubic` test's scalars (weights per
    // component: q = a p0 + b p1, so two weight arrays).
    let flat = |v: &[Vec3<f64>]| -> Vec<f64> { v.iter().flat_map(|u| [u.x, u.y, u.z]).collect() };
    let (fa, fb, ft) = (flat(&a), flat(&b), flat(&target));
    let by_hand = |p: [f64; 2]| -> [f64; 2] {
        // dp = -(JᵀJ)⁻¹ Jᵀ r, J_kj = (a_k, b_k) / (3 x_k² + 1).
        let (mut m, mut g) = ([[0.0; 2]; 2], [0.0; 2]);
        for k in 0..3 * n {
            let x = cubic_root(fa[k] * p[0] + fb[k] * p[1]);
            let d = 1.0 / (3.0 * x * x + 1.0);
            let j = [fa[k] * d, fb[k] * d];
            for r in 0..2 {
                g[r] -= j[r] * (x - ft[k]);
                for c in 0..2 {
                    m[r][c] += j[r] * j[c];
                }
            }
        }
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        [
            p[0] + (m[1][1] * g[0] - m[0][1] * g[1]) / det,
            p[1] + (m[0][0] * g[1] - m[1][0] * g[0]) / det,
        ]
    };
    let expected = by_hand([0.2, 0.1]);
    let one = run(Optimizer::kkt_gauss_newton().max_iters(1));
    // 14 unknowns (12 state scalars, 2 parameters): 14 tangent sweeps and one recording.
    assert_eq!(one.sweeps, 15, "{one}");
    assert_eq!(one.evaluations, 2, "the full step: {one}");
    let got = p.to_vec();
    for k in 0..2 {
        assert!(
            (got[k] - expected[k]).abs() < 1e-12,
            "p{k}: {got:?} against the Gauss-Newton step {expected:?}"
        );
    }
    p.assign(&[0.2, 0.1]);
    let report = run(Optimizer::kkt_gauss_newton().grad_tol(1e-9).max_iters(30));
    assert!(report.converged(), "{report}");
    assert!(report.loss > 1e-4, "a fit with a residual: {report}");
}

/// The KKT step in `f32` (state, constraint and residuals): the `f64` problem's step to f32's
/// precision, and a fit to the `f64` fit's parameters within 1e-4.
#[test]
fn the_kkt_step_in_f32_is_the_f64_one_to_f32_precision() {
    let w = vec![0.0, 1.0, 2.0, 3.0];
    let target = [0.3f32, 0.5, 0.55, 0.9];
    let (wa, ta) = (
        Array::from_vec(w.iter().map(|&v| v as f32).collect::<Vec<f32>>()),
        Array::from_vec(target.to_vec()),
    );
    let p = Array::from_vec(vec![0.2f32, 0.1]).named("p");
    let residuals = |tape: &mut Tape, x: &Array<f32>| {
        let r = Array::zeros(N).named("miss");
        tape.launch(miss, N, (x, &ta, &r));
        r
    };
    let run = |opt: Optimizer<'_>| {
        opt.progress(false).least_squares_kkt(
            &Params::new().with(&p),
            |tape| {
                let pv = p.to_vec();
                let s: Vec<f32> = w
                    .iter()
                    .map(|wi| cubic_root(pv[0] as f64 + wi * pv[1] as f64) as f32)
                    .collect();
                let s = Array::from_vec(s);
                let x = Array::zeros(N).named("x");
                tape.launch(cubic_solved, N, (&s, &p, &wa, &x));
                Ok((x.clone(), residuals(tape, &x)))
            },
            |tape, x| {
                let c = Array::zeros(N).named("c");
                tape.launch(cubic_constraint, N, (x, &p, &wa, &c));
                Ok((c, residuals(tape, x)))
            },
        )
    };
    let exact = Cubic::new(w.clone());
    let one = run(Optimizer::kkt_gauss_newton().max_iters(1)).unwrap();
    assert_eq!(one.sweeps, 7, "{one}");
    exact
        .run(Optimizer::kkt_gauss_newton().max_iters(1))
        .unwrap();
    let (got, want) = (p.to_vec(), exact.p.to_vec());
    for k in 0..2 {
        assert!(
            (got[k] as f64 - want[k]).abs() < 1e-5,
            "p{k}: f32 {got:?}, f64 {want:?}"
        );
    }
    p.assign(&[0.2, 0.1]);
    exact.p.assign(&[0.2, 0.1]);
    let fit = run(Optimizer::kkt_gauss_newton().grad_tol(1e-6).max_iters(30)).unwrap();
    exact
        .run(Optimizer::kkt_gauss_newton().grad_tol(1e-8).max_iters(30))
        .unwrap();
    let (got, want) = (p.to_vec(), exact.p.to_vec());
    for k in 0..2 {
        assert!(
            (got[k] as f64 - want[k]).abs() < 1e-4 * want[k].abs().max(1.0),
            "p{k}: f32 {got:?}, f64 {want:?} ({fit})"
        );
    }
}
