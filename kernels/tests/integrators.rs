//! The integrators' rollouts are differentiable: reverse mode against central finite
//! differences of the whole rollout (f64), forward against reverse mode (dot-product test),
//! and their accuracy order on a damped spring with an exact solution.
//!
//! Run with `--nocapture` to see the measured errors and orders.

use crate::common;

use adflex_kernels::integrators::{
    ExplicitEuler, ImplicitEuler, Integrator, Midpoint, Rk4, SemiImplicitEuler, Xpbd,
};
use adflex_kernels::{Model, ModelBuilder, State};
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::{dot_test, jacobian_fd, GradCheck};
use adflex_runtime::prelude::*;
use common::oscillator::Oscillator;
use common::{spring_system, spring_system_with};

/// `loss += |x|^2 / 2 + <v, (1, 2, -0.5)>` over the particles.
#[diff_kernel]
fn rollout_loss(x: &Array<Vec3<f64>>, v: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    let w = vec3(1.0, 2.0, -0.5);
    loss.atomic_add(0, 0.5 * dot(x[t], x[t]) + dot(v[t], w));
}

/// Three particles on a chain of XPBD distance constraints (compliant), plus a soft spring.
fn constraint_system() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let p0 = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
    let p1 = b.add_particle(Vec3::new(0.5, 0.9, 0.1), Vec3::new(0.0, 0.2, 0.3), 1.0);
    let p2 = b.add_particle(Vec3::new(0.9, 0.6, -0.1), Vec3::new(0.3, 0.0, -0.2), 0.7);
    b.add_distance_constraint(p0, p1, 1e-3);
    b.add_distance_constraint(p1, p2, 2e-3);
    b.add_spring(p0, p2, 5.0, 0.1);
    let m = b.finalize();
    // Start off the constraints' rest lengths so the solve has work to do.
    let c = m.distance_constraints.as_ref().unwrap();
    c.rest.assign(&[0.45, 0.55]);
    m
}

/// The rollout from `(x0, v0)` on `tape`, then the loss.
fn rollout<I: Integrator<f64>>(
    integ: &I,
    model: &Model<f64>,
    tape: &mut Tape,
    x0: &Array<Vec3<f64>>,
    v0: &Array<Vec3<f64>>,
    dt: f64,
    steps: usize,
) -> State<f64> {
    let s = State {
        x: x0.clone(),
        v: v0.clone(),
        bodies: None,
    };
    integ.rollout(model, tape, &s, None, dt, steps).unwrap()
}

fn loss_of(tape: &mut Tape, s: &State<f64>) -> Array<f64> {
    let loss = Array::zeros(1).named("loss");
    tape.launch(rollout_loss, s.x.len(), (&s.x, &s.v, &loss));
    loss
}

/// Reverse mode against central differences for `x0`, `v0` and the spring parameters; the
/// dot test between forward and reverse mode. Returns the worst relative errors.
fn check_integrator<I: Integrator<f64>>(
    name: &str,
    integ: &I,
    model: &Model<f64>,
    dt: f64,
    steps: usize,
) -> (f64, f64) {
    check_integrator_within(name, integ, model, dt, steps, 1e-5, 1e-9)
}

/// [`check_integrator`] with the tolerances of the FD check and of the dot test.
fn check_integrator_within<I: Integrator<f64>>(
    name: &str,
    integ: &I,
    model: &Model<f64>,
    dt: f64,
    steps: usize,
    fd_tol: f64,
    dot_tol: f64,
) -> (f64, f64) {
    let s0 = model.state();
    let (x0, v0) = (s0.x.named("x0"), s0.v.named("v0"));
    let mut params: Vec<&dyn AnyArray> = vec![&x0, &v0];
    let springs = model.springs();
    if let Some(s) = springs {
        params.extend([&s.ke as &dyn AnyArray, &s.rest, &s.kd]);
    }
    if let Some(c) = &model.distance_constraints {
        params.extend([&c.compliance as &dyn AnyArray, &c.rest]);
    }
    // Inverse masses are differentiable away from 0 (pinned is a discrete choice).
    if model.particle_inv_mass.to_vec().iter().all(|&w| w > 0.0) {
        params.push(&model.particle_inv_mass);
    }
    let report = GradCheck::new()
        .step(1e-6)
        .run(
            |tape| {
                let s = rollout(integ, model, tape, &x0, &v0, dt, steps);
                loss_of(tape, &s)
            },
            &params,
        )
        .unwrap();
    println!("{name}: gradient vs central differences over {steps} steps: {report}");
    report.assert_within(fd_tol);
    let dot = dot_test(
        |tape| {
            let s = rollout(integ, model, tape, &x0, &v0, dt, steps);
            vec![s.x.boxed(), s.v.boxed()]
        },
        &params,
        7,
    )
    .unwrap();
    println!(
        "{name}: dot test <Jv, w> = {:.12e}, <v, J^T w> = {:.12e}, rel. error {:.1e}",
        dot.jv_w,
        dot.v_jtw,
        dot.rel_error()
    );
    dot.assert_within(dot_tol);
    (report.max_error, dot.rel_error())
}

#[test]
fn explicit_euler_gradients() {
    check_integrator(
        "explicit Euler",
        &ExplicitEuler,
        &spring_system(20.0),
        0.01,
        6,
    );
}

#[test]
fn semi_implicit_euler_gradients() {
    check_integrator(
        "semi-implicit Euler",
        &SemiImplicitEuler,
        &spring_system(20.0),
        0.01,
        6,
    );
}

#[test]
fn rk4_gradients() {
    check_integrator("RK4", &Rk4, &spring_system(20.0), 0.02, 4);
}

#[test]
fn midpoint_gradients() {
    check_integrator("midpoint", &Midpoint, &spring_system(20.0), 0.01, 6);
}

/// Linearized implicit Euler on stiff nonlinear springs (rest lengths, so the Jacobian changes
/// with the state and the stiffness): its gradient includes the second-order term (how the
/// Jacobian of the step changes with each input), by a central difference of adjoint passes,
/// and agrees with central differences of the whole rollout; its forward mode likewise.
#[test]
fn linearized_implicit_euler_gradients() {
    let lin = ImplicitEuler::linearized();
    let (fd, dot) = check_integrator_within(
        "linearized implicit Euler",
        &lin,
        &spring_system(400.0),
        0.05,
        5,
        1e-5,
        1e-7,
    );
    assert!(fd < 1e-5 && dot < 1e-7);
    // Free particles: the masses get their gradient too.
    check_integrator_within(
        "linearized implicit Euler (free, with masses)",
        &lin,
        &spring_system_with(400.0, 3.0),
        0.05,
        5,
        1e-5,
        1e-7,
    );
}

/// Implicit-explicit splits on the spring system with drag: drag explicit, springs implicit,
/// and the reverse, for the full and the linearized method.
#[test]
fn implicit_explicit_split_gradients() {
    let mut model = spring_system(400.0);
    model.forces.push(Box::new(adflex_kernels::prelude::Drag {
        kd: 0.7,
        wind: Vec3::new(0.5, 0.0, -0.3),
    }));
    for (label, integ, dot_tol) in [
        (
            "drag explicit",
            ImplicitEuler::default().with_explicit(["drag"]),
            1e-9,
        ),
        (
            "springs explicit",
            ImplicitEuler::default().with_explicit(["springs"]),
            1e-9,
        ),
        (
            "linearized, drag explicit",
            ImplicitEuler::linearized().with_explicit(["drag"]),
            1e-7,
        ),
    ] {
        check_integrator_within(
            &format!("implicit Euler, {label}"),
            &integ,
            &model,
            0.02,
            5,
            1e-5,
            dot_tol,
        );
    }
}

#[test]
fn xpbd_gradients() {
    let x = Xpbd {
        substeps: 3,
        iterations: 2,
        relaxation: 0.9,
        averaging: false,
    };
    check_integrator("XPBD", &x, &constraint_system(), 0.01, 3);
}

/// The default XPBD (averaged Jacobi corrections: each particle's summed correction divided
/// by its number of constraints, a constant) against central differences, on the chain and on
/// a small cloth (springs, no bending) with a compliant constraint on every edge (up to 8
/// per particle).
#[test]
fn xpbd_averaged_gradients() {
    let x = Xpbd {
        substeps: 3,
        iterations: 2,
        ..Xpbd::default()
    };
    assert!(x.averaging);
    check_integrator("XPBD (averaged)", &x, &constraint_system(), 0.01, 3);
    let mut b = ModelBuilder::<f64>::new();
    // Without bending: the dihedral angle of a flat sheet is not differentiable (a kink
    // that central differences straddle).
    b.add_cloth_grid(&adflex_kernels::scenes::cloth::ClothGrid {
        bend: None,
        ..adflex_kernels::scenes::cloth::ClothGrid::benchmark(3)
    });
    let pairs = b.finalize().springs().unwrap().pairs.to_vec();
    for (k, [i, j]) in pairs.into_iter().enumerate() {
        b.add_distance_constraint(i, j, 1e-3 * (1.0 + 0.1 * k as f64));
    }
    let cloth = b.finalize();
    // Start the constraints off their rest lengths so the solve has work to do.
    let c = cloth.distance_constraints.as_ref().unwrap();
    c.rest.modify(|r| {
        r.iter_mut()
            .enumerate()
            .for_each(|(k, r)| *r *= 0.9 + 0.02 * (k % 7) as f64)
    });
    check_integrator(
        "XPBD (averaged), 3x3 cloth",
        &Xpbd::default(),
        &cloth,
        0.01,
        2,
    );
}

/// Implicit Euler on stiff springs (omega dt up to about 3, where the explicit methods are
/// unstable): the IFT adjoint against central differences of the whole implicit rollout, and
/// the dot test of its forward mode (also a linear solve) against it.
#[test]
fn implicit_euler_gradients_match_finite_differences() {
    let model = spring_system(400.0);
    let (fd, dot) = check_integrator("implicit Euler", &ImplicitEuler::default(), &model, 0.05, 5);
    assert!(fd < 1e-5 && dot < 1e-9);
    // No pinned particle: the masses are differentiable too.
    let model = spring_system_with(400.0, 3.0);
    check_integrator(
        "implicit Euler (free, with masses)",
        &ImplicitEuler::default(),
        &model,
        0.05,
        5,
    );
}

/// The Newton iterations are not on the tape: one custom step per time step.
#[test]
fn implicit_euler_records_one_step_per_step() {
    let model = spring_system(400.0);
    let mut tape = Tape::new();
    let mut s = model.state();
    let integ = ImplicitEuler::default();
    let mut newton = 0;
    for _ in 0..5 {
        let (next, stats) = integ
            .step_with_stats(&model, &mut tape, &s, None, 0.05)
            .unwrap();
        assert!(stats.converged, "{stats:?}");
        newton += stats.newton_iterations;
        s = next;
    }
    assert_eq!(tape.len(), 5);
    assert!(
        newton > 5,
        "a nonlinear system needs more than one Newton iteration per step"
    );
    println!(
        "implicit Euler: {newton} Newton iterations in 5 steps, {} records on the tape",
        tape.len()
    );
}

/// A large step far from the solution needs the line search; the result satisfies the
/// implicit equations.
#[test]
fn implicit_euler_large_step_converges() {
    let model = spring_system(5000.0);
    let mut tape = Tape::new();
    let s0 = model.state();
    let (s1, stats) = ImplicitEuler::default()
        .step_with_stats(&model, &mut tape, &s0, None, 0.5)
        .unwrap();
    println!("implicit Euler, dt = 0.5 on ke = 5000: {stats:?}");
    assert!(stats.converged, "{stats:?}");
    // Check v' = v + dt a(x', v') and x' = x + dt v' directly.
    let mut t2 = Tape::new();
    let a = model.eval_accelerations(&mut t2, &s1, None);
    let w = model.particle_inv_mass.to_vec();
    for (i, &wi) in w.iter().enumerate() {
        if wi == 0.0 {
            continue;
        }
        let r = s1.v.get(i) - s0.v.get(i) - a.get(i) * 0.5;
        assert!(
            r.norm() < 1e-8 * (1.0 + a.get(i).norm()),
            "particle {i}: residual {r:?}"
        );
        let dx = s1.x.get(i) - s0.x.get(i) - s1.v.get(i) * 0.5;
        assert!(dx.norm() < 1e-12, "particle {i}: {dx:?}");
    }
}

/// Order of accuracy at t = 1 on a damped spring: the error ratio between `dt` and `dt / 2`.
fn order_ratio<I: Integrator<f64>>(integ: &I, osc: &Oscillator, dt: f64) -> (f64, f64, f64) {
    let (u, v) = osc.exact(1.0);
    let err = |dt: f64| {
        let steps = (1.0 / dt).round() as usize;
        let tr = osc.simulate(integ, dt, steps);
        (tr.final_displacement() - u).hypot(tr.final_velocity() - v)
    };
    let (e1, e2) = (err(dt), err(dt / 2.0));
    (e1, e2, e1 / e2)
}

#[test]
fn accuracy_order_on_a_damped_spring() {
    let osc = Oscillator {
        stiffness: 100.0,
        mass: 1.0,
        damping: 1.0,
        displacement: 0.1,
        velocity: 0.2,
    };
    type Run<'a> = &'a dyn Fn(f64) -> (f64, f64, f64);
    let first: [(&str, Run); 5] = [
        ("explicit Euler", &|dt| {
            order_ratio(&ExplicitEuler, &osc, dt)
        }),
        ("semi-implicit Euler", &|dt| {
            order_ratio(&SemiImplicitEuler, &osc, dt)
        }),
        ("implicit Euler", &|dt| {
            order_ratio(&ImplicitEuler::default(), &osc, dt)
        }),
        ("XPBD (spring, 2 substeps)", &|dt| {
            order_ratio(&Xpbd::new(2), &osc, dt)
        }),
        ("RK4", &|dt| order_ratio(&Rk4, &osc, dt)),
    ];
    // Midpoint: second order (error ratio 4 when dt halves).
    let (e1, e2, ratio) = order_ratio(&Midpoint, &osc, 0.005);
    println!("{:>26}: error at t=1 {e1:.3e} (dt = 0.005), {e2:.3e} (dt/2): ratio {ratio:.2}, order {:.2}", "midpoint", ratio.log2());
    assert!(
        (3.6..4.4).contains(&ratio),
        "midpoint: ratio {ratio} is not second order"
    );
    // Linearized implicit Euler: first order (on this linear spring it is implicit Euler).
    let (e1, e2, ratio) = order_ratio(&ImplicitEuler::linearized(), &osc, 0.0025);
    println!("{:>26}: error at t=1 {e1:.3e} (dt = 0.0025), {e2:.3e} (dt/2): ratio {ratio:.2}, order {:.2}", "linearized implicit Euler", ratio.log2());
    assert!((1.7..2.4).contains(&ratio), "linearized: ratio {ratio}");
    for (name, f) in first {
        let dt = if name == "RK4" { 0.02 } else { 0.0025 };
        let (e1, e2, ratio) = f(dt);
        println!("{name:>26}: error at t=1 {e1:.3e} (dt = {dt}), {e2:.3e} (dt/2): ratio {ratio:.2}, order {:.2}", ratio.log2());
        if name == "RK4" {
            assert!(ratio > 10.0, "{name}: ratio {ratio}");
            assert!(e1 < 1e-4, "{name}: {e1}");
        } else {
            assert!(
                (1.7..2.4).contains(&ratio),
                "{name}: ratio {ratio} is not first order"
            );
        }
    }
}

/// Newton with its line search converges on stiff nonlinear springs for large steps
/// (`omega dt` up to about 70), five steps each.
#[test]
fn implicit_euler_converges_on_stiff_large_steps() {
    for ke in [400.0, 5000.0] {
        for dt in [0.05, 0.1, 0.2, 0.5] {
            let model = spring_system(ke);
            let mut tape = Tape::new();
            let mut s = model.state();
            let (mut newton, mut linear) = (0, 0);
            for step in 0..5 {
                let (s1, st) = ImplicitEuler::default()
                    .step_with_stats(&model, &mut tape, &s, None, dt)
                    .unwrap();
                assert!(st.converged, "ke {ke}, dt {dt}, step {step}: {st:?}");
                newton += st.newton_iterations;
                linear += st.linear_iterations;
                s = s1;
            }
            println!("implicit Euler ke {ke} dt {dt}: {newton} Newton iterations, {linear} CG products in 5 steps");
        }
    }
}

/// Implicit Euler in f32 on the benchmark cloth (springs, bending, ground contact with
/// friction, two pinned corners) at a 16x larger step than the benchmark's: every step
/// converges, the cloth stays finite and above the ground, and the gradient of the scene's
/// loss with respect to the initial velocities and the stiffnesses comes back finite.
#[test]
fn implicit_euler_cloth_f32_with_contact() {
    use adflex_kernels::scenes::cloth::{build, displacement_loss};
    let scene = build::<f32>(8);
    let integ = ImplicitEuler::default();
    let mut tape = Tape::new();
    let mut s = scene.initial.clone();
    let (mut newton, mut linear, mut fallbacks) = (0, 0, 0);
    for step in 0..40 {
        let (next, st) = integ
            .step_with_stats(&scene.model, &mut tape, &s, None, 1.0 / 60.0)
            .unwrap();
        assert!(st.converged, "step {step}: {st:?}");
        newton += st.newton_iterations;
        linear += st.linear_iterations;
        fallbacks += st.fallbacks;
        s = next;
    }
    println!("implicit Euler, f32 cloth 8x8, dt = 1/60, 40 steps: {newton} Newton iterations, {linear} products, {fallbacks} BiCGSTAB fallbacks");
    let x = s.x.to_vec();
    assert!(x.iter().all(|p| p.iter().all(|c| c.is_finite())));
    let lowest = x.iter().map(|p| p.y).fold(f32::INFINITY, f32::min);
    assert!(lowest > -0.05, "lowest particle at {lowest}");
    let loss = Array::<f32>::zeros(1);
    let target = Vec3::new(0.0f32, -0.1, 0.0);
    tape.launch(
        displacement_loss,
        x.len(),
        (&s.x, &scene.initial.x, target, 1.0f32 / 64.0, &loss),
    );
    tape.backward(&loss).unwrap();
    let gv = scene.initial.v.grad().unwrap().to_vec();
    let gk = scene.model.springs().unwrap().ke.grad().unwrap().to_vec();
    let norm = |v: &[f32]| v.iter().map(|x| (*x as f64).powi(2)).sum::<f64>().sqrt();
    let gv_flat: Vec<f32> = gv.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
    let (nv, nk) = (norm(&gv_flat), norm(&gk));
    println!(
        "loss {:.6}, |dL/dv0| = {nv:.4e}, |dL/dke| = {nk:.4e}",
        loss.get(0)
    );
    assert!(nv.is_finite() && nv > 0.0 && nk.is_finite() && nk > 0.0);
}

/// ImplicitEuler converges through contact (issue: it used to stall at impact): a soft block
/// thrown onto the ground and a free cloth with bending dropped on it, at steps from 1 ms to
/// 1/30 s, with the ground's damping on approach and in contact only. Every step converges,
/// everything reaches the ground and nothing falls through it.
#[test]
fn implicit_euler_converges_through_contact() {
    use adflex_kernels::prelude::{ClothGrid, Ground, TetGrid};
    let ground = |damp_approach: bool| Ground {
        damp_approach,
        ..Ground::default()
    };
    let block = |damp_approach: bool, dims: [usize; 3]| {
        let mut b = ModelBuilder::<f64>::new();
        TetGrid::<f64> {
            dims,
            origin: Vec3::new(0.0, 0.2, 0.0),
            ..TetGrid::default()
        }
        .add_to(&mut b);
        b.set_ground(ground(damp_approach));
        let m = b.finalize();
        m.particle_v
            .modify(|v| v.iter_mut().for_each(|v| *v = Vec3::new(1.0, -1.0, 0.0)));
        m
    };
    let cloth = |damp_approach: bool| {
        let mut b = ModelBuilder::<f64>::new();
        b.add_cloth_grid(&ClothGrid::<f64> {
            pinned: vec![],
            // Low: with damping on approach a light cloth falls at about 0.1 m/s.
            origin: Vec3::new(0.0, 0.1, 0.0),
            ..ClothGrid::benchmark(12)
        });
        b.set_ground(ground(damp_approach));
        b.finalize()
    };
    let mut cases: Vec<(String, Model<f64>, f64)> = Vec::new();
    for damp in [false, true] {
        // Without approach damping, 0.017 s and 0.02 s cycled between the residual's and the
        // potential's steps at the impact before the line search kept to the potential.
        for dt in [1e-3, 4e-3, 1.0 / 60.0, 0.017, 0.02, 1.0 / 30.0] {
            cases.push((
                format!("block 2x1x1, damp_approach {damp}"),
                block(damp, [2, 1, 1]),
                dt,
            ));
        }
        for dt in [1e-3, 4e-3, 1.0 / 60.0] {
            cases.push((
                format!("block 4x2x2, damp_approach {damp}"),
                block(damp, [4, 2, 2]),
                dt,
            ));
        }
        for dt in [1.0 / 60.0, 1.0 / 30.0] {
            cases.push((
                format!("cloth 12x12 with bending, damp_approach {damp}"),
                cloth(damp),
                dt,
            ));
        }
    }
    for (name, model, dt) in cases {
        let steps = (1.5 / dt).round() as usize;
        let mut s = model.state();
        let (mut newton, mut evals) = (0, 0);
        let (mut lowest, mut touched) = (f64::INFINITY, f64::INFINITY);
        for k in 0..steps {
            let (next, st) = ImplicitEuler::default()
                .step_with_stats(&model, &mut Tape::new(), &s, None, dt)
                .unwrap_or_else(|e| panic!("{name}, dt {dt}: step {k}: {e}"));
            newton += st.newton_iterations;
            evals += st.force_evaluations;
            s = next;
            let low =
                s.x.to_vec()
                    .iter()
                    .map(|p| p.y)
                    .fold(f64::INFINITY, f64::min);
            lowest = lowest.min(low);
            touched = touched.min(low - model.particle_radius);
        }
        let v = s.v.to_vec();
        let speed = v.iter().map(|v| v.norm()).fold(0.0, f64::max);
        let mean = v.iter().fold(Vec3::zeros(), |a, b| a + b) / v.len() as f64;
        println!("{name}, dt {dt:.4}: {steps} steps, {newton} Newton iterations, {evals} force evaluations; lowest particle {lowest:.4} m; at t = 1.5 s fastest {speed:.2e} m/s, centre {:.2e} m/s", mean.norm());
        // Penalty contact (ke = 1000 N/m per particle) lets a 2 kg block landing at 2 m/s
        // sink about 2 cm; a solve that failed would let it through.
        assert!(lowest > -0.05, "{name}, dt {dt}: sank to {lowest}");
        assert!(
            touched < 0.0,
            "{name}, dt {dt}: never touched the ground ({touched})"
        );
    }
}

/// ImplicitEuler converges through particle-particle and shape contact: a pile of 27 balls
/// thrown onto a box and the ground, at steps of 2 and 4 ms. The contacts' damping ramps in
/// over `damping_depth`; switched on at contact (`damping_depth = 0`), the force jumps and
/// Newton stalls (at both steps here: the test can fail). At 8 ms this stiff, frictional pile
/// (`omega dt = 2.5` per contact) still fails to converge within 30 iterations, with an
/// error that says so.
#[test]
fn implicit_euler_converges_through_particle_and_shape_contact() {
    use adflex_kernels::prelude::{Ground, ParticleContact, Shape, ShapeKind};
    let pile = |depth: f64| {
        let mut b = ModelBuilder::<f64>::new();
        b.particle_radius = 0.05;
        for i in 0..3 {
            for j in 0..3 {
                for k in 0..3 {
                    let x = Vec3::new(i as f64, j as f64, k as f64) * 0.095;
                    b.add_particle(x + Vec3::new(0.0, 0.4, 0.0), Vec3::new(0.5, -2.0, 0.0), 0.1);
                }
            }
        }
        let contact = ParticleContact {
            ke: 1e4,
            kd: 5.0,
            damping_depth: depth,
            ..ParticleContact::default()
        };
        b.set_particle_contact(contact);
        b.set_shape_contact(contact);
        b.add_shape(Shape::new(
            ShapeKind::Box {
                half_extents: Vec3::new(0.1, 0.1, 0.1),
            },
            Vec3::new(0.2, 0.1, 0.1),
        ));
        b.set_ground(Ground {
            ke: 1e4,
            kd: 5.0,
            ..Ground::default()
        });
        b.finalize()
    };
    let run = |model: &Model<f64>, dt: f64| -> Result<(usize, f64), String> {
        let mut s = model.state();
        let mut newton = 0;
        let mut lowest = f64::INFINITY;
        for k in 0..(0.6 / dt).round() as usize {
            let (next, st) = ImplicitEuler::default()
                .step_with_stats(model, &mut Tape::new(), &s, None, dt)
                .map_err(|e| format!("step {k}: {e}"))?;
            newton += st.newton_iterations;
            s = next;
            lowest = s.x.to_vec().iter().map(|p| p.y).fold(lowest, f64::min);
        }
        Ok((newton, lowest))
    };
    let mut stalled = 0;
    for dt in [2e-3, 4e-3] {
        let (newton, lowest) = run(&pile(1e-4), dt).unwrap_or_else(|e| panic!("dt {dt}: {e}"));
        println!("dt {dt:.4}: {newton} Newton iterations, lowest centre {lowest:.4} m");
        assert!(lowest > 0.0, "dt {dt}: fell through the ground ({lowest})");
        if let Err(e) = run(&pile(0.0), dt) {
            println!("dt {dt:.4}, damping switched on at contact: {e}");
            stalled += 1;
        }
    }
    assert_eq!(
        stalled, 2,
        "the switched damping converged: the test cannot fail"
    );
}

/// The oscillator fixture against its exact solution after 1 s at dt = 0.01 s: RK4's error is
/// below 1e-6 and the methods rank by order (RK4, then semi-implicit, then explicit Euler).
#[test]
fn the_oscillator_ranks_the_methods_by_order() {
    use adflex_kernels::integrators::{ExplicitEuler, Rk4, SemiImplicitEuler};
    let osc = Oscillator {
        stiffness: 100.0,
        mass: 1.0,
        damping: 0.5,
        ..Oscillator::default()
    };
    let (dt, steps) = (0.01, 100);
    let (u, _) = osc.exact(1.0);
    let err = |t: common::oscillator::Trajectory| (t.final_displacement() - u).abs();
    let e_rk4 = err(osc.simulate(&Rk4, dt, steps));
    let e_semi = err(osc.simulate(&SemiImplicitEuler, dt, steps));
    let e_expl = err(osc.simulate(&ExplicitEuler, dt, steps));
    assert!(
        e_rk4 < 1e-6 && e_rk4 < e_semi && e_semi < e_expl,
        "{e_rk4:e} {e_semi:e} {e_expl:e}"
    );
}

// ---------------------------------------------------------------- Jacobian products of rollouts

/// A 10-step rollout of the spring system by `integrator`, from `v0`, with the springs' `ke`:
/// the final positions and velocities.
fn spring_rollout(
    model: &Model<f64>,
    integrator: &dyn Integrator<f64>,
    v0: &Array<Vec3<f64>>,
    tape: &mut Tape,
) -> Vec<Box<dyn AnyArray>> {
    let mut s = model.state();
    s.v = v0.clone();
    let end = integrator
        .rollout(model, tape, &s, None, 0.01, 10)
        .expect("rollout");
    vec![end.x.boxed(), end.v.boxed()]
}

/// `J v`, `J^T w` and `J^T J v` of whole rollouts (explicit and implicit integrators) with
/// respect to a parameter array and the initial velocities: `J v` against the Jacobian by
/// central differences (f64), `J^T w` against `J v` by the dot test, and the Gauss-Newton
/// product against `J^T (J v)` from `J` assembled column by column from tangent passes.
#[test]
fn jacobian_products_of_rollouts() {
    let integrators: [(&str, Box<dyn Integrator<f64>>); 2] = [
        ("semi-implicit Euler", Box::new(SemiImplicitEuler)),
        (
            "implicit Euler",
            // Converged far below the differences' step (their noise is tolerance / h).
            Box::new(ImplicitEuler {
                tolerance: Some(1e-13),
                ..ImplicitEuler::default()
            }),
        ),
    ];
    for (name, integrator) in &integrators {
        let model = spring_system(40.0);
        let ke = model.param::<f64>("springs", "ke").unwrap();
        let v0 = model.state().v;
        let inputs: [&dyn AnyArray; 2] = [&ke, &v0];
        let n_in = ke.len() + 3 * v0.len();
        let mut rng = common::Rng(0x5eed_0011);
        let v: Vec<f64> = (0..n_in).map(|_| rng.uniform(-1.0, 1.0)).collect();

        // J by central differences (before the tape is recorded: the differences write the
        // inputs, which a recorded tape would then refuse as changed), and J v from it.
        let fd = jacobian_fd(
            |t| spring_rollout(&model, &**integrator, &v0, t),
            &inputs,
            1e-5,
        )
        .unwrap();
        let mut tape = Tape::new();
        let outs = spring_rollout(&model, &**integrator, &v0, &mut tape);
        let outputs: Vec<&dyn AnyArray> = outs.iter().map(|o| &**o).collect();
        let n_out = 2 * 3 * v0.len();
        let jv = tape.jvp(&inputs, &v, &outputs).unwrap();
        assert_eq!(jv.len(), n_out);

        for (r, jv_r) in jv.iter().enumerate() {
            let row: f64 = (0..n_in).map(|c| fd.data[r * n_in + c] * v[c]).sum();
            let scale = jv.iter().fold(1e-3f64, |m, x| m.max(x.abs()));
            assert!(
                (jv_r - row).abs() <= 1e-6 * scale,
                "{name}: (J v)[{r}] = {jv_r:e}, central differences {row:e}"
            );
        }

        // The dot test: <J v, w> = <v, J^T w>.
        let w: Vec<f64> = (0..n_out).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let jtw = tape.vjp(&outputs, &w, &inputs).unwrap();
        let lhs: f64 = jv.iter().zip(&w).map(|(a, b)| a * b).sum();
        let rhs: f64 = v.iter().zip(&jtw).map(|(a, b)| a * b).sum();
        assert!(
            (lhs - rhs).abs() <= 1e-10 * lhs.abs().max(rhs.abs()),
            "{name}: <J v, w> = {lhs:e}, <v, J^T w> = {rhs:e}"
        );

        // J from unit tangents; J^T (J v) from it against the Gauss-Newton product.
        let mut j = vec![0.0; n_out * n_in];
        for c in 0..n_in {
            let mut e = vec![0.0; n_in];
            e[c] = 1.0;
            let col = tape.jvp(&inputs, &e, &outputs).unwrap();
            for r in 0..n_out {
                j[r * n_in + c] = col[r];
            }
        }
        let gn = tape.gauss_newton(&inputs, &outputs, &v).unwrap();
        for (c, gn_c) in gn.iter().enumerate() {
            let want: f64 = (0..n_out).map(|r| j[r * n_in + c] * jv[r]).sum();
            assert!(
                (gn_c - want).abs() <= 1e-10 * want.abs().max(1.0),
                "{name}: (J^T J v)[{c}] = {gn_c:e}, from J: {want:e}"
            );
        }
    }
}

/// Jacobian products refuse a vector of the wrong length, an input that a recorded step
/// writes and an output no step wrote, naming them.
#[test]
fn jacobian_products_name_their_mistakes() {
    let model = spring_system(40.0);
    let ke = model.param::<f64>("springs", "ke").unwrap();
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .step(&model, &mut tape, &model.state(), None, 0.01)
        .unwrap();
    let err = tape.jvp(&[&ke], &[1.0], &[&s.x]).unwrap_err().to_string();
    assert!(
        err.contains("Tape::jvp: v") && err.contains("spring_ke (5 scalars)"),
        "{err}"
    );
    let err = tape
        .vjp(&[&s.x], &[1.0; 3], &[&ke])
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("Tape::vjp: w") && err.contains("12 scalars"),
        "{err}"
    );
    let s2 = SemiImplicitEuler
        .step(&model, &mut tape, &s, None, 0.01)
        .unwrap();
    let err = tape
        .jvp(&[&s.x], &[0.0; 12], &[&s2.x])
        .unwrap_err()
        .to_string();
    assert!(err.contains("is written by a recorded step"), "{err}");
    // An output the tape never wrote would give zeros: refused.
    let elsewhere = Array::<Vec3<f64>>::zeros(4).named("elsewhere");
    let err = tape
        .jvp(&[&ke], &[0.0; 5], &[&elsewhere])
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("output `elsewhere`") && err.contains("another tape"),
        "{err}"
    );
    let err = tape
        .vjp(&[&elsewhere], &[0.0; 12], &[&ke])
        .unwrap_err()
        .to_string();
    assert!(err.contains("output `elsewhere`"), "{err}");
    // An input given twice would have its first tangent overwritten: refused.
    let err = tape
        .jvp(&[&ke, &ke], &[0.0; 10], &[&s.x])
        .unwrap_err()
        .to_string();
    assert!(err.contains("is given twice"), "{err}");
    // A direction or a seed that is not finite, naming the entry.
    let mut v = [0.0; 5];
    v[3] = f64::NAN;
    let err = tape.jvp(&[&ke], &v, &[&s2.x]).unwrap_err().to_string();
    assert!(
        err.contains("Tape::jvp: v[3]") && err.contains("not finite"),
        "{err}"
    );
    let mut w = [0.0; 12];
    w[7] = f64::INFINITY;
    let err = tape.vjp(&[&s2.x], &w, &[&ke]).unwrap_err().to_string();
    assert!(err.contains("Tape::vjp: w[7]"), "{err}");
    // An output given twice gets the sum of its seeds.
    let w1: Vec<f64> = (0..12).map(|k| 0.1 * k as f64 - 0.4).collect();
    let w2: Vec<f64> = (0..12).map(|k| 0.3 - 0.05 * k as f64).collect();
    let sum: Vec<f64> = w1.iter().zip(&w2).map(|(a, b)| a + b).collect();
    let once = tape.vjp(&[&s2.x], &sum, &[&ke]).unwrap();
    let both: Vec<f64> = w1.iter().chain(&w2).copied().collect();
    let twice = tape.vjp(&[&s2.x, &s2.x], &both, &[&ke]).unwrap();
    for (a, b) in once.iter().zip(&twice) {
        assert!(
            (a - b).abs() <= 1e-12 * a.abs().max(1.0),
            "{once:?} vs {twice:?}"
        );
    }
}

/// A `jvp` gives no tangent buffer to the tape's leaves it was not asked about (they count as
/// constant): forward mode through `ImplicitEuler`, which refuses tangents on arrays it does
/// not differentiate (the springs' index pairs), works after it, on the same tape and on a
/// fresh one.
#[test]
fn a_jvp_leaves_no_tangents_on_the_other_leaves() {
    let model = spring_system(40.0);
    let s0 = model.state();
    let mut tape = Tape::new();
    let s1 = SemiImplicitEuler
        .step(&model, &mut tape, &s0, None, 0.01)
        .unwrap();
    let s2 = ImplicitEuler::default()
        .step(&model, &mut tape, &s1, None, 0.01)
        .unwrap();
    let v: Vec<f64> = (0..s0.v.len() * 3).map(|k| 0.1 * k as f64).collect();
    let jv = tape.jvp(&[&s0.v], &v, &[&s2.x]).unwrap();
    assert!(jv.iter().any(|x| *x != 0.0) && jv.iter().all(|x| x.is_finite()));
    for input in tape.inputs() {
        if input.array.id() != s0.v.id() {
            assert!(
                input.array.tangent_any().is_none(),
                "`{}` has a tangent",
                input.array.label()
            );
        }
    }
    // `<J v, w> = <v, J^T w>` on the same tape.
    let w: Vec<f64> = (0..jv.len()).map(|k| 1.0 - 0.07 * k as f64).collect();
    let jtw = tape.vjp(&[&s2.x], &w, &[&s0.v]).unwrap();
    let (a, b): (f64, f64) = (
        jv.iter().zip(&w).map(|(x, y)| x * y).sum(),
        v.iter().zip(&jtw).map(|(x, y)| x * y).sum(),
    );
    assert!((a - b).abs() <= 1e-10 * a.abs().max(1.0), "{a} vs {b}");
    // A fresh tape through ImplicitEuler alone.
    let mut fresh = Tape::new();
    let s3 = ImplicitEuler::default()
        .step(&model, &mut fresh, &s0, None, 0.01)
        .unwrap();
    fresh.jvp(&[&s0.v], &v, &[&s3.x]).unwrap();
}

/// `rollout_jvp`, one step on a tape at a time, gives bit for bit the `J v` of a tape of the
/// whole rollout (explicit and implicit integrators), with respect to `ke` and the initial
/// state.
#[test]
fn rollout_jvp_is_the_whole_tapes() {
    use adflex_runtime::checkpoint::Checkpoint;
    use adflex_runtime::products::rollout_jvp;
    let integrators: [(&str, Box<dyn Integrator<f64>>); 2] = [
        ("semi-implicit Euler", Box::new(SemiImplicitEuler)),
        ("implicit Euler", Box::new(ImplicitEuler::default())),
    ];
    for (name, integrator) in &integrators {
        let model = spring_system(40.0);
        let ke = model.param::<f64>("springs", "ke").unwrap();
        let init = model.state();
        let mut rng = common::Rng(0x5eed_0022);
        let v_ke: Vec<f64> = (0..ke.len()).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let v_init: Vec<f64> = (0..6 * init.x.len())
            .map(|_| rng.uniform(-1.0, 1.0))
            .collect();
        let (end, stepwise) = rollout_jvp(
            &init,
            10,
            |tape, s, _| integrator.step(&model, tape, s, None, 0.01),
            &[&ke],
            &v_ke,
            &v_init,
        )
        .unwrap();
        let mut tape = Tape::new();
        let whole = integrator
            .rollout(&model, &mut tape, &init, None, 0.01, 10)
            .unwrap();
        let inputs: Vec<&dyn AnyArray> = [&ke as &dyn AnyArray]
            .into_iter()
            .chain(init.arrays())
            .collect();
        let v: Vec<f64> = v_ke.iter().chain(&v_init).copied().collect();
        let jv = tape.jvp(&inputs, &v, &whole.arrays()).unwrap();
        assert_eq!(end.x.to_vec(), whole.x.to_vec(), "{name}: the same rollout");
        assert!(jv.iter().any(|x| *x != 0.0), "{name}");
        assert_eq!(stepwise, jv, "{name}: stepwise vs whole-tape J v");
    }
    // A tangent of the wrong length is named.
    let model = spring_system(40.0);
    let err = rollout_jvp(
        &model.state(),
        1,
        |tape, s, _| SemiImplicitEuler.step(&model, tape, s, None, 0.01),
        &[],
        &[],
        &[0.0; 3],
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("rollout_jvp: v_init"), "{err}");
}
