//! No silent wrong answers from the solvers: implicit Euler's Newton iteration and its adjoint
//! linear solve report non-convergence through `step` and `tape.backward` (per
//! `SolverPolicy`), a bad `dt` or a NaN parameter is an error naming it, a NaN residual never
//! counts as converged; and implicit Euler's gradients for bending, triangle FEM and
//! tetrahedral FEM parameters match central differences.
//!
//! Run with `--nocapture` to see the figures.

use crate::common;

use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Rk4, SemiImplicitEuler, SolverPolicy, Xpbd,
};
use adflex_kernels::solver::krylov::SolveSettings;
use adflex_kernels::statics::Equilibrium;
use adflex_kernels::{Model, ModelBuilder, State};
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;
use common::spring_system;

/// `loss += |x|^2 / 2 + <v, (1, 2, -0.5)>` over the particles.
#[diff_kernel]
fn rollout_loss(x: &Array<Vec3<f64>>, v: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    let w = vec3(1.0, 2.0, -0.5);
    loss.atomic_add(0, 0.5 * dot(x[t], x[t]) + dot(v[t], w));
}

fn loss_of(tape: &mut Tape, s: &State<f64>) -> Array<f64> {
    let loss = Array::zeros(1).named("loss");
    tape.launch(rollout_loss, s.x.len(), (&s.x, &s.v, &loss));
    loss
}

// ---------------------------------------------------------------------------------------------
// (a) Newton stopped by its iteration cap.

/// One Newton iteration on stiff springs at a large step cannot meet the tolerance: `step`
/// says so (naming the Newton solve, with the figures and what to do) and records nothing;
/// `Continue` and `Warn` accept the step, and the stats say it did not converge.
#[test]
fn capped_newton_is_an_error_unless_the_policy_accepts_it() {
    let model = spring_system(5000.0);
    let s0 = model.state();
    let capped = ImplicitEuler {
        max_newton: 1,
        ..ImplicitEuler::default()
    };
    let mut tape = Tape::new();
    let err = capped
        .step(&model, &mut tape, &s0, None, 0.5)
        .expect_err("one Newton iteration at omega dt ~ 35 cannot converge");
    println!("capped Newton: {err}");
    match &err {
        Error::NotConverged {
            solver,
            iterations,
            residual,
            tolerance,
            ..
        } => {
            assert_eq!(solver, "ImplicitEuler Newton");
            assert_eq!(*iterations, 1);
            assert!(residual > tolerance, "{residual} vs {tolerance}");
        }
        other => panic!("expected NotConverged, got {other:?}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("max_newton") && msg.contains("smaller dt"),
        "{msg}"
    );
    assert_eq!(tape.len(), 0, "a failed step records nothing");

    // Through rollout: the step that failed is named.
    let err = capped
        .rollout(&model, &mut Tape::new(), &s0, None, 0.5, 3)
        .unwrap_err();
    assert!(err.to_string().contains("rollout step 0 of 3"), "{err}");

    // The uncapped solve converges at the same step.
    assert!(ImplicitEuler::default()
        .step(&model, &mut Tape::new(), &s0, None, 0.5)
        .is_ok());

    for policy in [SolverPolicy::Continue, SolverPolicy::Warn] {
        let lenient = ImplicitEuler {
            on_failure: policy,
            ..capped.clone()
        };
        let mut tape = Tape::new();
        let (s1, stats) = lenient
            .step_with_stats(&model, &mut tape, &s0, None, 0.5)
            .unwrap();
        assert!(
            !stats.converged && stats.residual > stats.tolerance,
            "{stats:?}"
        );
        assert_eq!(tape.len(), 1);
        assert!(s1
            .x
            .to_vec()
            .iter()
            .all(|p| p.iter().all(|c| c.is_finite())));
        assert!(lenient
            .step(&model, &mut Tape::new(), &s0, None, 0.5)
            .is_ok());
    }
}

// ---------------------------------------------------------------------------------------------
// (b) The adjoint solve stopped by its iteration cap.

/// The rollout's loss, gradient of `v0`, and `backward`'s result with `integ`.
fn loss_and_grad(integ: &ImplicitEuler) -> (Result<(), Error>, Vec<Vec3<f64>>) {
    let model = spring_system(400.0);
    let s0 = model.state();
    let v0 = s0.v.named("v0").requires_grad();
    let s0 = State {
        x: s0.x.clone(),
        v: v0.clone(),
        bodies: None,
    };
    let mut tape = Tape::new();
    let s = integ
        .rollout(&model, &mut tape, &s0, None, 0.05, 3)
        .expect("the forward solves converge");
    let loss = loss_of(&mut tape, &s);
    let r = tape.backward(&loss);
    let g = v0.grad().map(|g| g.to_vec()).unwrap_or_default();
    (r, g)
}

/// The forward converges but the adjoint solve (capped at 2 iterations on 9 unknowns) cannot:
/// `tape.backward` returns the error, naming the adjoint solve and the tape step, instead of
/// a wrong gradient; `Continue` returns that approximate gradient (which is measurably wrong).
#[test]
fn capped_adjoint_solve_is_an_error_from_backward() {
    let capped = SolveSettings {
        max_iter: 2,
        ..SolveSettings::default()
    };
    let strict = ImplicitEuler {
        adjoint_linear: Some(capped),
        ..ImplicitEuler::default()
    };
    let (r, _) = loss_and_grad(&strict);
    let err = r.expect_err("a 2-iteration adjoint solve cannot converge on 9 unknowns");
    println!("capped adjoint: {err}");
    match &err {
        Error::NotConverged {
            solver,
            context,
            residual,
            tolerance,
            ..
        } => {
            assert!(
                solver.contains("ImplicitEuler adjoint linear solve"),
                "{solver}"
            );
            assert!(context.contains("implicit_euler") && context.contains("on the tape"));
            assert!(residual > tolerance);
        }
        other => panic!("expected NotConverged, got {other:?}"),
    }
    assert!(err.to_string().contains("adjoint_linear"), "{err}");

    let (r, truth) = loss_and_grad(&ImplicitEuler::default());
    r.unwrap();
    let (r, approx) = loss_and_grad(&ImplicitEuler {
        on_failure: SolverPolicy::Continue,
        ..strict
    });
    r.unwrap();
    let diff = truth
        .iter()
        .zip(&approx)
        .map(|(a, b)| (*a - *b).norm())
        .fold(0.0, f64::max);
    let scale = truth.iter().map(|a| a.norm()).fold(0.0, f64::max);
    println!(
        "dL/dv0 with the capped adjoint: max error {diff:.3e} (of max |dL/dv0| = {scale:.3e})"
    );
    assert!(
        diff > 1e-3 * scale,
        "the capped adjoint should be visibly wrong"
    );
}

// ---------------------------------------------------------------------------------------------
// (c) A bad time step.

fn assert_bad_dt<I: Integrator<f64>>(name: &str, integ: &I, model: &Model<f64>) {
    for dt in [f64::NAN, f64::INFINITY, 0.0, -1e-3] {
        let mut tape = Tape::new();
        match integ.step(model, &mut tape, &model.state(), None, dt) {
            Err(Error::InvalidInput { what, message }) => {
                assert_eq!(what, "dt", "{name}");
                assert!(message.contains(name), "{message}");
            }
            Err(e) => panic!("{name}, dt {dt}: expected InvalidInput, got {e}"),
            Ok(_) => panic!("{name}, dt {dt}: a step of dt = {dt} was accepted"),
        }
        assert_eq!(tape.len(), 0);
    }
}

/// A NaN, infinite, zero or negative `dt` is an error of every integrator, naming `dt`; for
/// implicit Euler it used to be `converged: true, residual: 0`.
#[test]
fn bad_dt_is_an_error_for_every_integrator() {
    let model = spring_system(100.0);
    assert_bad_dt("ImplicitEuler", &ImplicitEuler::default(), &model);
    assert_bad_dt("SemiImplicitEuler", &SemiImplicitEuler, &model);
    assert_bad_dt("ExplicitEuler", &ExplicitEuler, &model);
    assert_bad_dt("Rk4", &Rk4, &model);
    assert_bad_dt("Xpbd", &Xpbd::default(), &model);
    // Whatever the policy: bad input is not a convergence failure.
    let lenient = ImplicitEuler {
        on_failure: SolverPolicy::Continue,
        ..ImplicitEuler::default()
    };
    assert_bad_dt("ImplicitEuler", &lenient, &model);
    let r = lenient.step_with_stats(&model, &mut Tape::new(), &model.state(), None, f64::NAN);
    assert!(matches!(r, Err(Error::InvalidInput { .. })));
}

// ---------------------------------------------------------------------------------------------
// (d) NaN parameters and NaN residuals.

/// A NaN spring stiffness is an error naming the array and index (it used to freeze the state
/// silently: every residual NaN, "converged" at once).
#[test]
fn nan_stiffness_is_an_error_naming_it() {
    let model = spring_system(100.0);
    model.springs().unwrap().ke.set(2, f64::NAN);
    for policy in [SolverPolicy::Error, SolverPolicy::Continue] {
        let integ = ImplicitEuler {
            on_failure: policy,
            ..ImplicitEuler::default()
        };
        let err = integ
            .step(&model, &mut Tape::new(), &model.state(), None, 0.01)
            .unwrap_err();
        println!("NaN stiffness: {err}");
        match err {
            Error::InvalidInput { what, .. } => assert_eq!(what, "spring_ke[2]"),
            e => panic!("expected InvalidInput, got {e}"),
        }
    }
    // A NaN in the state too.
    let model = spring_system(100.0);
    let s = model.state();
    s.v.set(3, Vec3::new(0.0, f64::NAN, 0.0));
    let err = ImplicitEuler::default()
        .step(&model, &mut Tape::new(), &s, None, 0.01)
        .unwrap_err();
    assert!(
        matches!(err, Error::InvalidInput { ref what, .. } if what == "v[3]"),
        "{err}"
    );
}

/// Finite inputs whose forces overflow: the residual is not finite, and that is never
/// "converged" (it used to be: `residual: inf, converged: true`, the tolerance being
/// infinite too, and a NaN residual was skipped by the maximum).
#[test]
fn non_finite_residual_never_converges() {
    for (ke, dt) in [(1e300, 1e10), (1e300, 1e3), (1e200, 1e150)] {
        let model = spring_system(ke);
        let s0 = model.state();
        let lenient = ImplicitEuler {
            on_failure: SolverPolicy::Continue,
            ..ImplicitEuler::default()
        };
        let (_, stats) = lenient
            .step_with_stats(&model, &mut Tape::new(), &s0, None, dt)
            .unwrap();
        println!("overflowing forces (ke {ke:e}, dt {dt:e}): {stats:?}");
        assert!(!stats.converged, "{stats:?}");
        let err = ImplicitEuler::default()
            .step(&model, &mut Tape::new(), &s0, None, dt)
            .unwrap_err();
        assert!(
            matches!(err, Error::NotConverged { ref solver, .. } if solver == "ImplicitEuler Newton"),
            "{err}"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// Implicit Euler's gradients beyond springs.

/// Reverse mode of an implicit Euler rollout of `steps` steps of `dt` against central
/// differences for `params` (and `x0`, `v0`); also checks that each array in `params` gets a
/// non-zero gradient (a parameter left out of the implicit step's private copies would get 0).
fn check_implicit(name: &str, model: &Model<f64>, params: &[&dyn AnyArray], dt: f64, steps: usize) {
    let s0 = model.state();
    let (x0, v0) = (s0.x.named("x0"), s0.v.named("v0"));
    let mut all: Vec<&dyn AnyArray> = vec![&x0, &v0];
    all.extend(params);
    let integ = ImplicitEuler::default();
    let run = |tape: &mut Tape| {
        let s = State {
            x: x0.clone(),
            v: v0.clone(),
            bodies: None,
        };
        let s = integ.rollout(model, tape, &s, None, dt, steps).unwrap();
        loss_of(tape, &s)
    };
    let report = GradCheck::new().step(1e-6).run(run, &all).unwrap();
    println!("implicit Euler, {name}: {report}");
    report.assert_within(1e-5);
    for p in params {
        let norm = p.grad_any().map_or(0.0, |g| {
            (0..g.len() * g.element_dim())
                .map(|k| g.scalar(k).powi(2))
                .sum::<f64>()
                .sqrt()
        });
        println!("  |dL/d{}| = {norm:.3e}", p.label());
        assert!(norm > 0.0, "{name}: no gradient for {}", p.label());
    }
}

/// A bent hinge (two triangles on a shared edge, the edge pinned) with a bending element and
/// soft springs on the triangles' edges.
#[test]
fn implicit_euler_bending_gradients_match_finite_differences() {
    let mut b = ModelBuilder::<f64>::new();
    let e0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
    let e1 = b.add_particle(Vec3::new(0.0, 1.0, 1.0), Vec3::zeros(), 0.0);
    let o1 = b.add_particle(Vec3::new(0.9, 1.2, 0.4), Vec3::new(0.0, 0.2, 0.1), 0.3);
    let o2 = b.add_particle(Vec3::new(-0.8, 1.3, 0.6), Vec3::new(0.1, -0.3, 0.0), 0.4);
    for (i, j) in [(e0, o1), (e1, o1), (e0, o2), (e1, o2)] {
        b.add_spring(i, j, 50.0, 0.1);
    }
    b.add_bending([o1, o2, e0, e1], 0.3, 4.0, 0.2);
    let model = b.finalize();
    let bend = model.bending().unwrap();
    check_implicit(
        "bending hinge",
        &model,
        &[&bend.ke, &bend.kd, &bend.rest],
        0.02,
        5,
    );
}

/// A triangle membrane (StVK), one corner pinned, stretched by its initial velocities.
#[test]
fn implicit_euler_triangle_fem_gradients_match_finite_differences() {
    let mut b = ModelBuilder::<f64>::new();
    let p0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
    let p1 = b.add_particle(Vec3::new(1.0, 1.0, 0.1), Vec3::new(0.3, 0.1, 0.0), 0.5);
    let p2 = b.add_particle(Vec3::new(0.2, 1.1, 0.9), Vec3::new(-0.1, 0.2, 0.4), 0.7);
    b.add_triangle_fem(p0, p1, p2, 40.0, 25.0, 0.3);
    let model = b.finalize();
    let t = model.tri_fem().unwrap();
    check_implicit("triangle FEM", &model, &[&t.mu, &t.lambda, &t.kd], 0.02, 5);
}

/// A stable Neo-Hookean tetrahedron, one vertex pinned, deformed by its initial velocities.
#[test]
fn implicit_euler_tet_fem_gradients_match_finite_differences() {
    let mut b = ModelBuilder::<f64>::new();
    let p0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
    let p1 = b.add_particle(Vec3::new(1.0, 1.0, 0.0), Vec3::new(0.3, 0.1, 0.0), 0.5);
    let p2 = b.add_particle(Vec3::new(0.1, 1.9, 0.1), Vec3::new(-0.1, 0.2, 0.4), 0.7);
    let p3 = b.add_particle(Vec3::new(0.2, 1.1, 1.0), Vec3::new(0.0, -0.2, 0.3), 0.6);
    b.add_tet(p0, p1, p2, p3, 60.0, 90.0, 0.4);
    let model = b.finalize();
    let t = model.tets().unwrap();
    check_implicit("tet FEM", &model, &[&t.mu, &t.lambda, &t.kd], 0.02, 5);
}

/// Forward mode too: a capped tangent solve under `SolverPolicy::Error` is an error from
/// `tape.tangent()`, naming the solve and the step, rather than a wrong tangent.
#[test]
fn capped_tangent_solve_is_an_error_from_tangent() {
    let model = spring_system(400.0);
    let s0 = model.state();
    let integ = ImplicitEuler {
        adjoint_linear: Some(SolveSettings {
            max_iter: 2,
            ..SolveSettings::default()
        }),
        ..ImplicitEuler::default()
    };
    let mut tape = Tape::new();
    integ.step(&model, &mut tape, &s0, None, 0.05).unwrap();
    s0.v.set_tangent(Some(Array::from_vec(vec![Vec3::new(0.3, -0.2, 0.1); 4])));
    let msg = tape.tangent().unwrap_err().to_string();
    assert!(
        msg.contains("ImplicitEuler tangent linear solve (CG, then BiCGSTAB) did not converge")
            && msg.contains("implicit_euler"),
        "{msg}"
    );
}

// ---------------------------------------------------------------------------------------------
// (f) A user force recorded as a custom step: implicit Euler linearizes the forces by their
// tangents, so a custom step without one (or whose tangent fails) is an error naming the
// step, never a panic inside the Newton solve.

/// Linear drag `f -= c v` computed on the host with `record_fn`; its tangent is `tangent`.
#[derive(Clone, Debug)]
struct HostDrag {
    c: f64,
    tangent: HostTangent,
}

#[derive(Clone, Copy, Debug)]
enum HostTangent {
    Missing,
    Fails,
    Exact,
}

impl adflex_kernels::forces::Force<f64> for HostDrag {
    fn name(&self) -> &'static str {
        "host_drag"
    }
    fn eval(
        &self,
        cx: &adflex_kernels::forces::ForceContext<'_, f64>,
        tape: &mut Tape,
        f: &Array<Vec3<f64>>,
    ) {
        let c = self.c;
        let (v, out) = (cx.v.clone(), f.clone());
        let step = tape.record_fn(
            "host_drag",
            &[cx.v, f],
            &[f],
            || {
                let vv = v.to_vec();
                out.modify(|d| d.iter_mut().zip(&vv).for_each(|(f, v)| *f -= v * c));
            },
            || Ok(()),
        );
        let (v, out) = (cx.v.clone(), f.clone());
        match self.tangent {
            HostTangent::Missing => {}
            HostTangent::Fails => {
                step.with_tangent(|| Err(Error::Other("the drag has no linearization".into())))
            }
            HostTangent::Exact => step.with_tangent(move || {
                if let (Some(dv), Some(df)) = (v.tangent_buffer(), out.tangent_buffer()) {
                    let dv = dv.to_vec();
                    df.modify(|d| d.iter_mut().zip(&dv).for_each(|(f, v)| *f -= v * c));
                }
            }),
        }
    }
    fn params_mut(
        &mut self,
        _visit: &mut dyn FnMut(&'static str, &mut dyn adflex_kernels::forces::Param),
    ) {
    }
}

/// Two particles on a spring, with the host drag if `tangent` is given.
fn host_drag_system(tangent: Option<HostTangent>) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let p0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::new(0.5, 0.0, 0.0), 1.0);
    let p1 = b.add_particle(Vec3::new(0.6, 1.1, 0.1), Vec3::new(0.0, 0.3, -0.2), 2.0);
    b.add_spring_with_rest(p0, p1, 0.5, 50.0, 0.2);
    if let Some(tangent) = tangent {
        b.add_force(HostDrag { c: 0.7, tangent });
    }
    b.finalize()
}

#[test]
fn custom_force_without_a_working_tangent_is_an_error_naming_it() {
    for (kind, says) in [
        (HostTangent::Missing, "has no tangent"),
        (HostTangent::Fails, "the drag has no linearization"),
    ] {
        let model = host_drag_system(Some(kind));
        let mut tape = Tape::new();
        let err = ImplicitEuler::default()
            .step(&model, &mut tape, &model.state(), None, 0.01)
            .expect_err("the Newton solve needs the force's tangent");
        let msg = err.to_string();
        assert!(
            msg.contains("host_drag") && msg.contains(says) && msg.contains("ImplicitEuler"),
            "{kind:?}: {msg}"
        );
        // The static solve shares the Newton solver: the same error, not a panic.
        let err = Equilibrium::default()
            .solve(&model, &mut Tape::new(), &model.state())
            .expect_err("the Newton solve needs the force's tangent");
        let msg = err.to_string();
        assert!(
            msg.contains("host_drag") && msg.contains(says) && msg.contains("Equilibrium"),
            "{kind:?}: {msg}"
        );
    }
    // With its tangent, the same force steps, and the drag slows the particles down.
    let model = host_drag_system(Some(HostTangent::Exact));
    let free = host_drag_system(None);
    let (mut t1, mut t2) = (Tape::new(), Tape::new());
    let s = model.state();
    let with = ImplicitEuler::default()
        .step(&model, &mut t1, &s, None, 0.01)
        .unwrap();
    let without = ImplicitEuler::default()
        .step(&free, &mut t2, &free.state(), None, 0.01)
        .unwrap();
    let ke = |s: &State<f64>| s.v.to_vec().iter().map(|v| v.norm_squared()).sum::<f64>();
    assert!(
        ke(&with) < ke(&without),
        "{} !< {}",
        ke(&with),
        ke(&without)
    );
}
