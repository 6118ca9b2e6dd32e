//! The tape: backward against formulas and finite differences, skipping, version checks,
//! custom steps, scopes, DOT, tangents, NaN detection.

mod common;

use adflex_runtime::gradcheck::{dot_test, gradcheck};
use adflex_runtime::prelude::*;
use adflex_runtime::BackwardStats;
use common::{double_on_host, Sqrt, Square, SumSq};

fn xs() -> Vec<f64> {
    vec![0.5, -1.25, 2.0, 0.75]
}

/// loss = sum (a x^2)^2 recorded on `tape`.
fn square_loss(tape: &mut Tape, x: &Array<f64>, a: f64) -> (Array<f64>, Array<f64>) {
    let y = Array::<f64>::zeros(x.len()).named("y");
    let loss = Array::<f64>::zeros(1).named("loss");
    tape.launch(Square::<false>, x.len(), (x, a, &y));
    tape.launch(SumSq, x.len(), (&y, &loss));
    (y, loss)
}

#[test]
fn backward_matches_formula_and_fd() {
    let a = 1.5;
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    let (y, loss) = square_loss(&mut tape, &x, a);
    tape.backward(&loss).unwrap();
    let expected: Vec<f64> = xs().iter().map(|x| 4.0 * a * a * x * x * x).collect();
    let got = x.grad().unwrap().to_vec();
    for (g, e) in got.iter().zip(&expected) {
        assert!(
            (g - e).abs() <= 1e-12 * e.abs().max(1.0),
            "{got:?} vs {expected:?}"
        );
    }
    // The intermediate got a gradient buffer, and the stores that wrote it took their
    // gradient (2 y) out of it: what remains is the gradient with respect to y's value before
    // `square` overwrote it, zero.
    let gy = y.grad().unwrap().to_vec();
    assert_eq!(gy, vec![0.0; xs().len()]);
    assert_eq!(tape.last_backward(), BackwardStats { run: 2, skipped: 0 });

    let x2 = Array::from_vec(xs()).named("x");
    gradcheck(|t| square_loss(t, &x2, a).1, &[&x2])
        .unwrap()
        .assert_within(1e-7);
}

#[test]
fn intermediate_grads_restart_from_zero_on_every_backward_on_any_pool() {
    // A chain of eight squarings added into their outputs: eight intermediates, whose
    // gradients an adjoint reads without taking them (unlike those of stores), so a backward
    // zeroes them first, on the pool's threads when it has several.
    #[adflex_macros::diff_kernel]
    fn add_square(x: &Array<f64>, a: f64, y: &Array<f64>) {
        let t = tid();
        y.atomic_add(t, x[t] * x[t] * a);
    }
    for threads in [1, 2, 3] {
        with_threads(threads, || {
            let x = Array::from_vec(xs()).requires_grad().named("x");
            let mut tape = Tape::new();
            let mut ys = vec![x.clone()];
            for k in 0..8 {
                let y = Array::<f64>::zeros(x.len()).named(format!("y{k}"));
                tape.launch(add_square, x.len(), (ys.last().unwrap(), 0.9, &y));
                ys.push(y);
            }
            let loss = Array::<f64>::zeros(1).named("loss");
            tape.launch(SumSq, x.len(), (ys.last().unwrap(), &loss));
            tape.backward(&loss).unwrap();
            let first: Vec<Vec<f64>> = ys.iter().map(|y| y.grad().unwrap().to_vec()).collect();
            tape.backward(&loss).unwrap();
            assert_eq!(
                x.grad().unwrap().to_vec(),
                first[0].iter().map(|g| 2.0 * g).collect::<Vec<_>>(),
                "{threads} threads: the leaf accumulates"
            );
            for (k, y) in ys.iter().enumerate().skip(1) {
                assert_eq!(
                    y.grad().unwrap().to_vec(),
                    first[k],
                    "{threads} threads: y{} restarts from zero",
                    k - 1
                );
            }
        });
    }
}

#[test]
fn zero_and_reset() {
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    let (y, loss) = square_loss(&mut tape, &x, 1.0);
    tape.backward(&loss).unwrap();
    let g1 = x.grad().unwrap().to_vec();
    let gy = y.grad().unwrap().to_vec();
    tape.backward(&loss).unwrap();
    let g2 = x.grad().unwrap().to_vec();
    // Leaves accumulate; intermediates are recomputed from zero.
    assert_eq!(
        g2,
        g1.iter().map(|g| 2.0 * g).collect::<Vec<_>>(),
        "leaf grads accumulate"
    );
    assert_eq!(
        y.grad().unwrap().to_vec(),
        gy,
        "intermediate grads start from zero"
    );
    tape.zero();
    assert!(x.grad().unwrap().to_vec().iter().all(|&g| g == 0.0));
    tape.backward(&loss).unwrap();
    assert_eq!(x.grad().unwrap().to_vec(), g1);
    assert_eq!(tape.len(), 2);
    tape.reset();
    assert!(tape.is_empty());
    assert!(x.grad().unwrap().to_vec().iter().all(|&g| g == 0.0));
    assert!(matches!(tape.backward(&loss), Err(Error::NotOnTape { .. })));
}

#[test]
fn skips_adjoints_that_cannot_contribute() {
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let c = Array::from_vec(xs()).named("c"); // constant
    let y1 = Array::<f64>::zeros(4).named("y1");
    let y2 = Array::<f64>::zeros(4).named("y2");
    let y3 = Array::<f64>::zeros(4).named("y3");
    let loss = Array::<f64>::zeros(1).named("loss");
    let other = Array::<f64>::zeros(1).named("other");
    let mut tape = Tape::new();
    tape.launch(Square::<false>, 4, (&c, 2.0, &y1)); // reads no requires-grad array
    tape.launch(Square::<false>, 4, (&x, 2.0, &y2)); // runs
    tape.launch(Square::<false>, 4, (&x, 3.0, &y3)); // does not reach the loss
    tape.launch(SumSq, 4, (&y1, &other)); // reaches neither
    tape.launch(SumSq, 4, (&y2, &loss)); // runs
    tape.launch(SumSq, 4, (&y1, &loss)); // reaches the loss, reads only constants
    tape.backward(&loss).unwrap();
    assert_eq!(tape.last_backward(), BackwardStats { run: 2, skipped: 4 });
    assert!(y2.grad().is_ok());
    // No gradient buffers off the paths from x to the loss.
    for a in [&c, &y1, &y3, &other] {
        assert!(
            matches!(a.grad(), Err(Error::NoGrad { .. })),
            "{}",
            a.label()
        );
    }
}

#[test]
fn grad_without_requires_grad_is_an_error() {
    let a = Array::<f64>::zeros(3).named("plain");
    assert_eq!(
        a.grad().unwrap_err(),
        Error::NoGrad {
            array: "plain".into()
        }
    );
    assert!(a.grad().unwrap_err().to_string().contains("requires_grad"));
}

#[test]
fn not_on_tape() {
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    square_loss(&mut tape, &x, 1.0);
    let stray = Array::<f64>::zeros(1).named("stray");
    assert_eq!(
        tape.backward(&stray),
        Err(Error::NotOnTape {
            array: "stray".into()
        })
    );
    // x is read, not written, by the tape.
    assert!(matches!(tape.backward(&x), Err(Error::NotOnTape { .. })));
    assert!(matches!(
        tape.backward_with(&[&stray]),
        Err(Error::NotOnTape { .. })
    ));
}

#[test]
fn array_changed_after_launch_is_an_error() {
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    let (_, loss) = square_loss(&mut tape, &x, 1.0);
    let recorded = x.version();
    x.assign(&[1.0, 2.0, 3.0, 4.0]);
    let err = tape.backward(&loss).unwrap_err();
    assert_eq!(
        err,
        Error::ArrayChanged {
            kernel: "square".into(),
            launch: 0,
            param: "x".into(),
            array: "x".into(),
            recorded,
            now: recorded + 1,
        }
    );
    let msg = err.to_string();
    assert!(
        msg.contains("`x`") && msg.contains("square") && msg.contains("#0"),
        "{msg}"
    );
    // Nothing ran, nothing was seeded.
    assert!(x.grad().unwrap().to_vec().iter().all(|&g| g == 0.0));
    assert_eq!(loss.grad_buffer().map(|g| g.get(0)), None);
}

#[test]
fn array_changed_names_the_scope() {
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    let loss = Array::<f64>::zeros(1).named("loss");
    let y = tape.scope("step 3", |tape| {
        let y = Array::<f64>::zeros(4).named("y");
        tape.launch(Square::<false>, 4, (&x, 1.0, &y));
        y
    });
    tape.launch(SumSq, 4, (&y, &loss));
    y.set(0, 7.0); // the loss kernel read y
    match tape.backward(&loss).unwrap_err() {
        Error::ArrayChanged {
            kernel,
            launch,
            param,
            array,
            ..
        } => {
            assert_eq!((kernel.as_str(), launch), ("sum_sq", 1));
            assert_eq!((param.as_str(), array.as_str()), ("x", "y"));
        }
        e => panic!("{e}"),
    }
    // A change to an array only a skipped launch read is not an error.
    let mut tape = Tape::new();
    let c = Array::from_vec(xs()).named("c");
    let yc = Array::<f64>::zeros(4);
    let loss = Array::<f64>::zeros(1);
    tape.scope("outer", |tape| {
        tape.scope("inner", |tape| {
            tape.launch(Square::<false>, 4, (&x, 1.0, &y))
        })
    });
    tape.launch(Square::<false>, 4, (&c, 1.0, &yc));
    tape.launch(SumSq, 4, (&y, &loss));
    c.set(0, 1.0);
    tape.backward(&loss).unwrap();
    x.set(0, 1.0);
    match tape.backward(&loss).unwrap_err() {
        Error::ArrayChanged { kernel, launch, .. } => {
            assert_eq!((kernel.as_str(), launch), ("outer/inner/square", 0))
        }
        e => panic!("{e}"),
    }
}

#[test]
fn custom_step_in_a_chain() {
    let a = 0.75;
    let chain = |tape: &mut Tape, x: &Array<f64>| {
        let y = Array::<f64>::zeros(x.len()).named("y");
        let loss = Array::<f64>::zeros(1).named("loss");
        tape.launch(Square::<false>, x.len(), (x, a, &y));
        let z = double_on_host(tape, &y);
        tape.launch(SumSq, x.len(), (&z, &loss));
        loss
    };
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    let loss = chain(&mut tape, &x);
    tape.backward(&loss).unwrap();
    assert_eq!(tape.last_backward(), BackwardStats { run: 3, skipped: 0 });
    // loss = sum (2 a x^2)^2, d/dx = 16 a^2 x^3.
    for (g, x) in x.grad().unwrap().to_vec().iter().zip(xs()) {
        let e = 16.0 * a * a * x * x * x;
        assert!((g - e).abs() <= 1e-12 * e.abs().max(1.0));
    }
    let x2 = Array::from_vec(xs()).named("x");
    gradcheck(|t| chain(t, &x2), &[&x2])
        .unwrap()
        .assert_within(1e-7);

    // backward_with: seed the custom step's output by hand (a vector-Jacobian product).
    let x3 = Array::from_vec(xs()).requires_grad().named("x");
    let mut tape = Tape::new();
    let y = Array::<f64>::zeros(4).named("y");
    tape.launch(Square::<false>, 4, (&x3, a, &y));
    let z = double_on_host(&mut tape, &y);
    assert!(matches!(
        tape.backward_with(&[&z]),
        Err(Error::NoGrad { .. })
    ));
    z.ensure_grad().assign(&[1.0, 0.0, 0.0, -1.0]);
    tape.backward_with(&[&z]).unwrap();
    let g = x3.grad().unwrap().to_vec();
    let x = xs();
    assert_eq!(g, vec![4.0 * a * x[0], 0.0, 0.0, -4.0 * a * x[3]]);

    // A host write to the custom step's input is caught too.
    y.set(1, 0.0);
    match tape.backward_with(&[&z]).unwrap_err() {
        Error::ArrayChanged { kernel, param, .. } => {
            assert_eq!((kernel.as_str(), param.as_str()), ("double", "input 0"))
        }
        e => panic!("{e}"),
    }
}

#[test]
fn scopes_and_dot() {
    let x = Array::from_vec(xs()).requires_grad().named("x");
    let loss = Array::<f64>::zeros(1).named("loss");
    let mut tape = Tape::new();
    let mut cur = x.clone();
    for s in 0..2 {
        cur = tape.scope(format!("step {s}"), |tape| {
            let y = Array::<f64>::zeros(4).named(format!("y{s}"));
            tape.launch(Square::<false>, 4, (&cur, 0.5, &y));
            y
        });
    }
    tape.push_scope("loss");
    tape.launch(SumSq, 4, (&cur, &loss));
    tape.pop_scope();
    let dot = tape.to_dot();
    for needle in [
        "digraph tape {",
        "square",
        "sum_sq",
        "dim 4",
        "cluster_",
        "label=\"step 0\"",
        "label=\"step 1\"",
        "scope: step 1",
        "label=\"x\"",
        "label=\"y1\"",
        "label=\"loss\"",
        "fillcolor=lightblue",
        "style=dashed",
    ] {
        assert!(dot.contains(needle), "missing {needle:?} in\n{dot}");
    }
    assert_eq!(dot.matches(" -> ").count(), 6);
    assert!(dot.trim_end().ends_with('}'));
}

#[test]
fn tangent_over_the_tape() {
    let a = 1.25;
    let x = Array::from_vec(xs()).named("x");
    let chain = |tape: &mut Tape| {
        let y = Array::<f64>::zeros(4).named("y");
        let loss = Array::<f64>::zeros(1).named("loss");
        tape.launch(Square::<false>, 4, (&x, a, &y));
        let z = double_on_host(tape, &y);
        tape.launch(SumSq, 4, (&z, &loss));
        vec![z.boxed(), loss.boxed()]
    };
    dot_test(chain, &[&x], 7).unwrap().assert_within(1e-12);

    // The tangent pass runs only tangent kernels: forward values and versions stay.
    let mut tape = Tape::new();
    let outs = chain(&mut tape);
    let loss_value = outs[1].scalar(0);
    let versions: Vec<u64> = outs.iter().map(|o| o.version()).collect();
    x.set_tangent(Some(Array::from_vec(vec![1.0, 0.0, 0.0, 0.0])));
    tape.tangent().unwrap();
    tape.tangent().unwrap(); // twice: outputs' tangents are reset, not accumulated
    assert_eq!(outs[1].scalar(0), loss_value);
    assert_eq!(
        outs.iter().map(|o| o.version()).collect::<Vec<_>>(),
        versions
    );
    // d loss / d x0 = 16 a^2 x0^3
    let x0 = xs()[0];
    let dl = outs[1].tangent_any().unwrap().scalar(0);
    assert!((dl - 16.0 * a * a * x0 * x0 * x0).abs() < 1e-12);
    x.set_tangent(None);

    // A custom step without a tangent is an error, not a silent zero.
    let mut tape = Tape::new();
    let y = Array::<f64>::zeros(4);
    tape.record_fn("no tangent", &[&x], &[&y], || {}, || Ok(()));
    assert!(matches!(tape.tangent(), Err(Error::Other(m)) if m.contains("no tangent")));
}

/// A custom step whose backward fails (e.g. an adjoint solve that did not converge): the error
/// reaches `tape.backward`, with the step's scoped name and position in its context, instead
/// of a silently wrong gradient.
#[test]
fn custom_step_backward_error_reaches_backward() {
    let x = Array::from_vec(vec![1.0f64, 2.0])
        .requires_grad()
        .named("x");
    let y = Array::<f64>::zeros(2).named("y");
    let mut tape = Tape::new();
    let (xb, yb) = (x.clone(), y.clone());
    tape.scope("step 7", |tape| {
        tape.record_fn(
            "solve",
            &[&x],
            &[&y],
            || y.assign(&x.to_vec()),
            move || {
                let _ = (&xb, &yb);
                Err(Error::NotConverged {
                    solver: "test adjoint CG".into(),
                    context: String::new(),
                    iterations: 3,
                    residual: 0.5,
                    tolerance: 1e-10,
                    hint: "raise the iteration cap".into(),
                })
            },
        );
    });
    let err = tape.backward(&y).unwrap_err();
    match &err {
        Error::NotConverged {
            solver,
            context,
            iterations,
            ..
        } => {
            assert_eq!(solver, "test adjoint CG");
            assert!(
                context.contains("step 7/solve") && context.contains("#0"),
                "{context}"
            );
            assert_eq!(*iterations, 3);
        }
        other => panic!("expected NotConverged, got {other:?}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("did not converge") && msg.contains("raise the iteration cap"),
        "{msg}"
    );
}

/// Anomaly mode: a NaN in a forward launch is kept as the tape's first anomaly, naming the
/// kernel, array, index and pass, and returned by backward and tangent; nothing panics.
#[test]
fn nan_in_forward_is_an_error_with_kernel_array_index() {
    let x = Array::from_vec(vec![1.0, 4.0, -1.0, 9.0])
        .requires_grad()
        .named("x");
    let y = Array::<f64>::zeros(4).named("y");
    let z = Array::<f64>::zeros(4).named("z");
    let mut tape = Tape::new();
    tape.check_finite(true);
    tape.launch(Sqrt, 4, (&x, &y));
    tape.launch(Sqrt, 4, (&y, &z)); // NaN again: the first one is kept
    let err = tape.anomaly().cloned().expect("an anomaly");
    let msg = err.to_string();
    assert!(
        msg.contains("`sqrt`")
            && msg.contains("`y`")
            && msg.contains("index 2")
            && msg.contains("forward"),
        "{msg}"
    );
    assert_eq!(tape.backward(&z).unwrap_err(), err);
    assert_eq!(tape.tangent().unwrap_err(), err);
    tape.reset();
    assert!(tape.anomaly().is_none());
    // Off by default.
    let mut tape = Tape::new();
    tape.launch(Sqrt, 4, (&x, &y));
    assert!(y.get(2).is_nan());
    assert!(tape.anomaly().is_none());
}

#[test]
fn non_finite_adjoint_is_reported() {
    let x = Array::from_vec(vec![1.0, 0.0, 4.0])
        .requires_grad()
        .named("x");
    let y = Array::<f64>::zeros(3).named("y");
    let loss = Array::<f64>::zeros(1).named("loss");
    let mut tape = Tape::new();
    tape.check_finite(true);
    tape.scope("s", |tape| tape.launch(Sqrt, 3, (&x, &y)));
    tape.launch(SumSq, 3, (&y, &loss));
    assert_eq!(
        tape.backward(&loss).unwrap_err(),
        Error::NonFinite {
            kernel: "s/sqrt".into(),
            launch: 0,
            param: "x".into(),
            array: "x".into(),
            index: 1,
            pass: "adjoint",
        }
    );
}

/// A custom step that updates an array in place (an input that is also an output): later
/// steps and `backward` see the updated array as the step's, not as changed since, and a host
/// write after the step is still caught.
#[test]
fn custom_step_in_place() {
    let x = Array::from_vec(vec![1.0f64, -2.0, 0.5])
        .requires_grad()
        .named("x");
    let y = Array::<f64>::zeros(3).named("y");
    let loss = Array::<f64>::zeros(1).named("loss");
    let mut tape = Tape::new();
    tape.launch(Square::<false>, 3, (&x, 1.0, &y));
    // y *= 3 on the host; its gradient (kept in place) is scaled the same way.
    let yb = y.clone();
    tape.record_fn(
        "triple",
        &[&y],
        &[&y],
        || y.modify(|d| d.iter_mut().for_each(|v| *v *= 3.0)),
        move || {
            if let Some(g) = yb.grad_buffer() {
                g.modify(|d| d.iter_mut().for_each(|v| *v *= 3.0));
            }
            Ok(())
        },
    )
    .with_tangent(|| Ok(()));
    tape.launch(SumSq, 3, (&y, &loss));
    tape.backward(&loss).unwrap();
    // loss = sum (3 x^2)^2 = 9 sum x^4, d/dx = 36 x^3.
    for (g, x) in x.grad().unwrap().to_vec().iter().zip([1.0f64, -2.0, 0.5]) {
        assert!(
            (g - 36.0 * x * x * x).abs() <= 1e-12 * (36.0 * x * x * x).abs(),
            "{g}"
        );
    }
    assert!(tape.tangent().is_ok());
    y.assign(&[0.0, 0.0, 0.0]);
    tape.zero();
    assert!(matches!(
        tape.backward(&loss),
        Err(Error::ArrayChanged { .. })
    ));
}

/// A `no_grad` tape runs every step (launches and custom steps) with the recording tape's
/// bits, keeps nothing, and refuses every derivative by name; `check_finite` still works, and
/// names the step's position among those it ran.
#[test]
fn no_grad_tape_runs_keeps_nothing_and_refuses_derivatives() {
    let run = |tape: &mut Tape| {
        let x = Array::from_vec(xs()).requires_grad().named("x");
        let (y, loss) = square_loss(tape, &x, 1.5);
        let z = double_on_host(tape, &y);
        (x, y, z, loss)
    };
    let mut recorded = Tape::new();
    let (_, y0, z0, l0) = run(&mut recorded);
    let mut tape = Tape::no_grad();
    assert!(!tape.is_recording() && recorded.is_recording());
    let (x, y, z, loss) = run(&mut tape);
    assert_eq!(y.to_vec(), y0.to_vec());
    assert_eq!(z.to_vec(), z0.to_vec());
    assert_eq!(loss.to_vec(), l0.to_vec());
    assert_eq!(recorded.len(), 3);
    assert!(tape.is_empty());
    let refused = |e: Error, what: &str| {
        let msg = e.to_string();
        assert!(
            msg.contains(what) && msg.contains("Tape::no_grad()") && msg.contains("Tape::new()"),
            "{msg}"
        );
    };
    refused(tape.backward(&loss).unwrap_err(), "Tape::backward");
    loss.ensure_grad();
    refused(
        tape.backward_with(&[&loss]).unwrap_err(),
        "Tape::backward_with",
    );
    refused(tape.tangent().unwrap_err(), "Tape::tangent");
    refused(tape.vjp(&[&loss], &[1.0], &[&x]).unwrap_err(), "Tape::vjp");
    refused(tape.jvp(&[&x], &xs(), &[&loss]).unwrap_err(), "Tape::jvp");
    // The recording tape's gradient is untouched by any of it.
    recorded.backward(&l0).unwrap();

    // check_finite: the first NaN, at its position among the steps this tape ran.
    let mut tape = Tape::no_grad();
    tape.check_finite(true);
    let a = Array::from_vec(vec![1.0, -1.0]).named("a");
    let (b, c) = (Array::<f64>::zeros(2).named("b"), Array::<f64>::zeros(2));
    tape.launch(Square::<false>, 2, (&a, 1.0, &b));
    tape.launch(Sqrt, 2, (&a, &c));
    let msg = tape.anomaly().expect("a NaN").to_string();
    assert!(
        msg.contains("`sqrt`") && msg.contains("#1") && msg.contains("index 1"),
        "{msg}"
    );
    assert!(tape.is_empty());
}
