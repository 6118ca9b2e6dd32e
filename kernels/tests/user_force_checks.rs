//! What a user-written force cannot get wrong silently: a parameter its visitor forgets, an
//! extra one, a NaN in a parameter or the state, a force that overflows. Every integrator
//! returns a right gradient or an error naming the array (never a wrong gradient, a NaN state
//! or a panic).

use adflex_kernels::forces::{Force, ForceContext, Param};
use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Midpoint, Rk4, SemiImplicitEuler, Xpbd,
};
use adflex_kernels::statics::Equilibrium;
use adflex_kernels::{Model, ModelBuilder, State};
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;

/// A magnet pulling particle `i` towards `pole[i]` with strength `k[i]` (N/m) and a damping
/// `c[0]` (N s/m) of the velocity.
#[diff_kernel]
fn magnet(
    x: &Array<Vec3<f64>>,
    v: &Array<Vec3<f64>>,
    pole: &Array<Vec3<f64>>,
    k: &Array<f64>,
    c: &Array<f64>,
    f: &Array<Vec3<f64>>,
) {
    let i = tid();
    f.atomic_add(i, (pole[i] - x[i]) * k[i] - v[i] * c[0]);
}

/// Which arrays the visitor lists.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Visits {
    /// `pole`, `k` and `c`: right.
    All,
    /// `pole` and `c`, not `k`: the user forgot one.
    ForgetsK,
    /// All, plus an array the kernel never reads.
    Extra,
}

#[derive(Clone, Debug)]
struct Magnet {
    pole: Array<Vec3<f64>>,
    k: Array<f64>,
    c: Array<f64>,
    unused: Array<f64>,
    visits: Visits,
}

impl Force<f64> for Magnet {
    fn name(&self) -> &'static str {
        "magnet"
    }
    fn eval(&self, cx: &ForceContext<'_, f64>, tape: &mut Tape, f: &Array<Vec3<f64>>) {
        tape.launch(
            magnet,
            self.k.len(),
            (cx.x, cx.v, &self.pole, &self.k, &self.c, f),
        );
    }
    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        visit("pole", &mut self.pole);
        if self.visits != Visits::ForgetsK {
            visit("k", &mut self.k);
        }
        visit("c", &mut self.c);
        if self.visits == Visits::Extra {
            visit("unused", &mut self.unused);
        }
    }
}

/// Three particles with magnets, linked by springs; returns the model and the magnet's `k`.
fn scene(visits: Visits) -> (Model<f64>, Array<f64>) {
    let mut b = ModelBuilder::<f64>::new();
    let v = Vec3::new;
    let p = [
        b.add_particle(v(0.0, 1.0, 0.0), v(0.1, 0.0, 0.2), 1.0),
        b.add_particle(v(0.6, 1.1, 0.1), v(0.0, 0.3, -0.2), 0.7),
        b.add_particle(v(1.1, 0.8, -0.2), v(-0.4, 0.0, 0.1), 1.3),
    ];
    b.add_spring(p[0], p[1], 30.0, 0.1);
    b.add_spring(p[1], p[2], 40.0, 0.1);
    let k = Array::from_vec(vec![5.0, 8.0, 3.0]).named("magnet_k");
    b.add_force(Magnet {
        pole: Array::from_vec(vec![v(0.0, 0.5, 0.0), v(1.0, 0.5, 0.0), v(1.5, 0.4, 0.3)])
            .named("magnet_pole"),
        k: k.clone(),
        c: Array::from_vec(vec![0.2]).named("magnet_c"),
        unused: Array::from_vec(vec![1.0, 2.0]).named("magnet_unused"),
        visits,
    });
    (b.finalize(), k)
}

#[diff_kernel]
fn loss_kernel(x: &Array<Vec3<f64>>, v: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    loss.atomic_add(0, dot(x[t], x[t]) + 0.3 * dot(v[t], vec3(1.0, -1.0, 0.5)));
}

fn integrators() -> Vec<(&'static str, Box<dyn Integrator<f64>>)> {
    vec![
        ("ExplicitEuler", Box::new(ExplicitEuler)),
        ("SemiImplicitEuler", Box::new(SemiImplicitEuler)),
        ("Midpoint", Box::new(Midpoint)),
        ("Rk4", Box::new(Rk4)),
        ("Xpbd", Box::new(Xpbd::default())),
        ("ImplicitEuler", Box::new(ImplicitEuler::default())),
        (
            "ImplicitEuler::linearized",
            Box::new(ImplicitEuler::linearized()),
        ),
        (
            "ImplicitEuler, magnet explicit",
            Box::new(ImplicitEuler::default().with_explicit(["magnet"])),
        ),
    ]
}

/// The tolerance of the gradient checks: XPBD's are noisier (see every_force.rs).
fn tol(name: &str) -> f64 {
    if name == "Xpbd" {
        1e-4
    } else {
        1e-5
    }
}

/// The gradient of a short rollout's loss w.r.t. `params`, against central differences.
fn gradcheck(
    name: &str,
    integ: &dyn Integrator<f64>,
    model: &Model<f64>,
    params: &[&dyn AnyArray],
) -> Result<adflex_runtime::gradcheck::Report, Error> {
    let s0 = model.state();
    let mut failure = None;
    // XPBD's velocities are position differences over a substep: a larger step (see
    // every_force.rs).
    let h = if name == "Xpbd" { 1e-4 } else { 1e-6 };
    let report = GradCheck::new().step(h).run(
        |tape| {
            let loss = Array::zeros(1).named("loss");
            let s = State {
                x: s0.x.clone(),
                v: s0.v.clone(),
                bodies: None,
            };
            match integ.rollout(model, tape, &s, None, 0.01, 4) {
                Ok(s) => tape.launch(loss_kernel, s.x.len(), (&s.x, &s.v, &loss)),
                Err(e) => failure = Some(e),
            }
            loss
        },
        params,
    );
    match failure {
        Some(e) => Err(e),
        None => report,
    }
}

/// A forgotten parameter that requires a gradient: the solvers that work on private copies of
/// the visited parameters (implicit Euler, linearized or split, and the static solve) refuse
/// the step with an error naming the force, the kernel and the array; the integrators that
/// differentiate the tape directly give the right gradient.
#[test]
fn a_forgotten_parameter_is_an_error_or_a_right_gradient() {
    for (name, integ) in integrators() {
        let (model, k) = scene(Visits::ForgetsK);
        let k = k.requires_grad();
        match gradcheck(name, integ.as_ref(), &model, &[&k]) {
            Ok(report) => {
                println!("{name}, k forgotten: {report}");
                assert!(
                    !name.starts_with("ImplicitEuler") || name.contains("explicit"),
                    "{name} must refuse a forgotten parameter"
                );
                assert!(report.is_within(tol(name)), "{name}: {report}");
            }
            Err(e) => {
                let msg = e.to_string();
                println!("{name}, k forgotten: {msg}");
                assert!(name.starts_with("ImplicitEuler") && !name.contains("explicit"));
                assert!(
                    msg.contains("force `magnet`")
                        && msg.contains("magnet_k")
                        && msg.contains("kernel `magnet`")
                        && msg.contains("params_mut"),
                    "{msg}"
                );
            }
        }
    }
    let (model, k) = scene(Visits::ForgetsK);
    let _ = k.requires_grad();
    let err = Equilibrium::default()
        .solve(&model, &mut Tape::new(), &model.state())
        .unwrap_err();
    assert!(err.to_string().contains("magnet_k"), "{err}");
}

/// Marked after the step, before `backward`: the adjoint refuses too.
#[test]
fn a_forgotten_parameter_marked_after_the_step_fails_the_backward() {
    let (model, k) = scene(Visits::ForgetsK);
    let s0 = model.state();
    let v0 = s0.v.clone().requires_grad();
    let s = State { v: v0, ..s0 };
    let mut tape = Tape::new();
    let s1 = ImplicitEuler::default()
        .step(&model, &mut tape, &s, None, 0.01)
        .unwrap();
    let _ = k.requires_grad();
    let loss = Array::zeros(1);
    tape.launch(loss_kernel, 3, (&s1.x, &s1.v, &loss));
    let msg = tape.backward(&loss).unwrap_err().to_string();
    assert!(
        msg.contains("magnet_k") && msg.contains("params_mut"),
        "{msg}"
    );
}

/// Forward mode with a tangent on a forgotten parameter: an error, not an ignored tangent.
#[test]
fn a_forgotten_parameter_with_a_tangent_fails_the_tangent_pass() {
    let (model, k) = scene(Visits::ForgetsK);
    let mut tape = Tape::new();
    let s1 = ImplicitEuler::default()
        .step(&model, &mut tape, &model.state(), None, 0.01)
        .unwrap();
    k.set_tangent(Some(Array::from_vec(vec![1.0, 0.0, 0.0])));
    let _ = s1;
    let msg = tape.tangent().unwrap_err().to_string();
    assert!(msg.contains("magnet_k") && msg.contains("tangent"), "{msg}");
}

/// Visited right, or with an extra array the kernel never reads: the right gradient through
/// every integrator (the extra array's is zero).
#[test]
fn visited_and_extra_parameters_get_right_gradients() {
    for visits in [Visits::All, Visits::Extra] {
        for (name, integ) in integrators() {
            let (model, _) = scene(visits);
            let params = model.params();
            let arrays: Vec<&dyn AnyArray> = params.iter().map(|(_, _, a)| &**a).collect();
            let report = gradcheck(name, integ.as_ref(), &model, &arrays).unwrap();
            println!("{name}, {visits:?}: {report}");
            assert!(report.is_within(tol(name)), "{name}: {report}");
            if visits == Visits::Extra {
                let unused = model.param::<f64>("magnet", "unused").unwrap();
                // No gradient buffer (nothing reaches it) or a zero one.
                let g = unused.grad().map_or(vec![0.0, 0.0], |g| g.to_vec());
                assert_eq!(g, vec![0.0, 0.0], "{name}");
            }
        }
    }
}

/// A NaN in the initial velocity or in a force's parameter: every integrator's step is an
/// error naming the array and index (and the rollout step), not a NaN state.
#[test]
fn a_nan_input_is_an_error_naming_the_array() {
    for (name, integ) in integrators() {
        // In the state.
        let (model, _) = scene(Visits::All);
        let s = model.state();
        s.v.set(1, Vec3::new(0.0, f64::NAN, 0.0));
        let err = integ
            .rollout(&model, &mut Tape::new(), &s, None, 0.01, 5)
            .unwrap_err();
        let msg = err.to_string();
        println!("{name}, NaN in v[1]: {msg}");
        assert!(
            matches!(err, Error::InvalidInput { ref what, .. } if what == "v[1]"),
            "{name}: {err:?}"
        );
        assert!(msg.contains("rollout step 0 of 5"), "{msg}");
        // In a parameter.
        let (model, k) = scene(Visits::All);
        k.set(2, f64::INFINITY);
        let err = integ
            .rollout(&model, &mut Tape::new(), &model.state(), None, 0.01, 5)
            .unwrap_err();
        println!("{name}, Inf in magnet_k[2]: {err}");
        assert!(
            matches!(err, Error::InvalidInput { ref what, .. } if what == "magnet_k[2]"),
            "{name}: {err:?}"
        );
    }
}

/// Explicit Euler on a spring far beyond its stability limit overflows from finite inputs: the
/// step where the state first becomes non-finite is an error (naming the state array and the
/// rollout step), the steps before are fine.
#[test]
fn an_overflowing_rollout_stops_at_the_first_non_finite_step() {
    let mut b = ModelBuilder::<f64>::new();
    let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    let c = b.add_particle(Vec3::new(1.1, 0.0, 0.0), Vec3::zeros(), 1.0);
    b.add_spring_with_rest(a, c, 1.0, 1e8, 0.0);
    let model = b.finalize();
    let err = ExplicitEuler
        .rollout(&model, &mut Tape::new(), &model.state(), None, 0.1, 1000)
        .unwrap_err();
    let msg = err.to_string();
    println!("{msg}");
    assert!(matches!(err, Error::NonFinite { .. }), "{err:?}");
    assert!(
        msg.contains("ExplicitEuler step (in rollout step") && msg.contains("`v`"),
        "{msg}"
    );
}

/// Anomaly mode: a user force whose kernel produces a NaN from finite inputs (a square root of
/// a negative number) makes the step return the kernel's name, never a panic.
#[test]
fn anomaly_mode_names_the_kernel_of_the_first_nan() {
    #[diff_kernel]
    fn bad_force(x: &Array<Vec3<f64>>, f: &Array<Vec3<f64>>) {
        let i = tid();
        f.atomic_add(i, vec3(sqrt(x[i].y - 5.0), 0.0, 0.0));
    }
    #[derive(Clone, Debug)]
    struct Bad;
    impl Force<f64> for Bad {
        fn name(&self) -> &'static str {
            "bad"
        }
        fn eval(&self, cx: &ForceContext<'_, f64>, tape: &mut Tape, f: &Array<Vec3<f64>>) {
            tape.launch(bad_force, cx.x.len(), (cx.x, f));
        }
        fn params_mut(&mut self, _: &mut dyn FnMut(&'static str, &mut dyn Param)) {}
    }
    let (mut model, _) = scene(Visits::All);
    model.forces.push(Box::new(Bad));
    for (name, integ) in integrators() {
        if name.starts_with("ImplicitEuler") {
            continue; // its scratch evaluations are not on the caller's tape
        }
        let mut tape = Tape::new();
        tape.check_finite(true);
        let err = integ
            .step(&model, &mut tape, &model.state(), None, 0.01)
            .unwrap_err();
        println!("{name}: {err}");
        assert!(
            matches!(err, Error::NonFinite { ref kernel, pass: "forward", .. } if kernel == "bad_force"),
            "{name}: {err:?}"
        );
    }
}

/// An anomaly belongs to the step that recorded it: after a failed step, a retry on the same
/// tape (at another step, from good inputs) is not failed by the old anomaly.
#[test]
fn a_retry_on_the_same_tape_is_not_failed_by_an_earlier_anomaly() {
    let mut b = ModelBuilder::<f64>::new();
    let a = b.add_particle(Vec3::zeros(), Vec3::zeros(), 0.0);
    let c = b.add_particle(Vec3::new(1.1, 0.0, 0.0), Vec3::zeros(), 1.0);
    b.add_spring_with_rest(a, c, 1.0, 1e8, 0.0);
    let model = b.finalize();
    let mut tape = Tape::new();
    tape.check_finite(true);
    let err = ExplicitEuler
        .rollout(&model, &mut tape, &model.state(), None, 0.1, 1000)
        .unwrap_err();
    assert!(matches!(err, Error::NonFinite { .. }), "{err:?}");
    assert!(tape.anomaly().is_some());
    // A step from the initial state at a tiny dt is fine.
    ExplicitEuler
        .step(&model, &mut tape, &model.state(), None, 1e-6)
        .unwrap();
}
