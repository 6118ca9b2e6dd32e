//! Static equilibria (`adflex_kernels::statics::Equilibrium`): the solution has zero net force,
//! its implicit-function-theorem gradient with respect to the springs' rest lengths and
//! stiffnesses, the particles' (inverse) masses and the pins' positions matches central
//! differences of the re-solved equilibrium in f64, and failures are errors.

use adflex_kernels::solver::krylov::SolveSettings;
use adflex_kernels::statics::Equilibrium;
use adflex_kernels::{Model, ModelBuilder, State};
use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

/// A square net of `n x n` particles in the horizontal plane, its four corners pinned, joined
/// by structural and shear springs whose rest lengths are 90% of their lengths (so the net is
/// in tension), sagging under gravity like a trampoline.
fn net(n: u32) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let h = 0.25;
    for j in 0..n {
        for i in 0..n {
            let corner = (i == 0 || i == n - 1) && (j == 0 || j == n - 1);
            // Unequal masses, so that every mass matters differently.
            let m = if corner {
                0.0
            } else {
                0.05 + 0.01 * ((i + 2 * j) % 3) as f64
            };
            b.add_particle(Vec3::new(i as f64 * h, 0.0, j as f64 * h), Vec3::zeros(), m);
        }
    }
    let id = |i: u32, j: u32| j * n + i;
    let mut k = 0;
    let mut spring = |b: &mut ModelBuilder<f64>, p: u32, q: u32| {
        let d = (b.particle_position(p) - b.particle_position(q)).norm();
        let ke = 150.0 + 20.0 * (k % 4) as f64;
        k += 1;
        b.add_spring_with_rest(p, q, 0.9 * d, ke, 0.1);
    };
    for j in 0..n {
        for i in 0..n {
            if i + 1 < n {
                spring(&mut b, id(i, j), id(i + 1, j));
            }
            if j + 1 < n {
                spring(&mut b, id(i, j), id(i, j + 1));
            }
            if i + 1 < n && j + 1 < n {
                spring(&mut b, id(i, j), id(i + 1, j + 1));
                spring(&mut b, id(i + 1, j), id(i, j + 1));
            }
        }
    }
    b.finalize()
}

/// `out += sum_i c_i . x_i`.
#[diff_kernel]
fn weighted(x: &Array<Vec3<f64>>, c: &Array<Vec3<f64>>, out: &Array<f64>) {
    let i = tid();
    out.atomic_add(0, dot(x[i], c[i]));
}

fn weights(n: usize) -> Array<Vec3<f64>> {
    Array::from_vec(
        (0..n)
            .map(|i| {
                let t = i as f64;
                Vec3::new((1.3 * t).sin(), (0.7 * t + 0.4).cos(), 0.5 + 0.1 * t)
            })
            .collect(),
    )
}

/// The loss of the equilibrium from `guess`, recorded on `tape`.
fn loss(
    model: &Model<f64>,
    tape: &mut Tape,
    guess: &State<f64>,
    c: &Array<Vec3<f64>>,
) -> (Array<f64>, State<f64>) {
    // Tight: the central differences divide the solve's error by the step.
    let solver = Equilibrium {
        tolerance: Some(1e-14),
        ..Equilibrium::default()
    };
    let eq = solver.solve(model, tape, guess).unwrap();
    let l = Array::zeros(1);
    tape.launch(weighted, model.particle_count, (&eq.x, c, &l));
    (l, eq)
}

/// The derivative of `f` at `p0` by fourth-order central differences with step `h`:
/// `(8 (f(p0 + h) - f(p0 - h)) - (f(p0 + 2h) - f(p0 - 2h))) / 12h`. Its truncation error,
/// `O(h^4)`, lets `h` be large enough (`1e-4` relative) that roundoff divided by `h` stays far
/// below the `1e-6` the tests ask for.
fn central(mut f: impl FnMut(f64) -> f64, p0: f64, h: f64) -> f64 {
    let d1 = f(p0 + h) - f(p0 - h);
    let d2 = f(p0 + 2.0 * h) - f(p0 - 2.0 * h);
    (8.0 * d1 - d2) / (12.0 * h)
}

/// Checks the gradient of the loss with respect to every scalar of `param` against central
/// differences ([`central`]), re-solving the equilibrium for each.
fn check_param(model: &Model<f64>, param: &Array<f64>, what: &str) {
    let c = weights(model.particle_count);
    let guess = model.state();
    param.zero_grad();
    let param = param.clone().requires_grad();
    let mut tape = Tape::new();
    let (l, eq) = loss(model, &mut tape, &guess, &c);
    tape.backward(&l).unwrap();
    let g = param.grad().unwrap().to_vec();
    let base = eq.x.to_vec();
    let start = State {
        x: Array::from_vec(base),
        v: guess.v.clone(),
        bodies: None,
    };
    let mut worst = 0.0f64;
    let numeric: Vec<f64> = (0..param.len())
        .map(|k| {
            let p0 = param.get(k);
            let h = 1e-4 * p0.abs().max(1e-3);
            let eval = |p: f64| {
                param.set(k, p);
                let (l, _) = loss(model, &mut Tape::new(), &start, &c);
                l.get(0)
            };
            let n = central(eval, p0, h);
            param.set(k, p0);
            n
        })
        .collect();
    let scale = numeric.iter().fold(0.0f64, |m, n| m.max(n.abs()));
    assert!(scale > 0.0, "{what}: the loss does not depend on it");
    for (k, (a, n)) in g.iter().zip(&numeric).enumerate() {
        let err = (a - n).abs() / (n.abs() + 1e-3 * scale);
        worst = worst.max(err);
        assert!(
            err < 1e-6,
            "{what}[{k}]: adjoint {a:e}, central differences {n:e}, relative error {err:e}"
        );
    }
    println!(
        "{what}: {} entries, worst relative error {worst:.1e}",
        g.len()
    );
    param.zero_grad();
}

#[test]
fn the_equilibrium_has_zero_net_force() {
    let model = net(5);
    let (eq, stats) = Equilibrium::default()
        .solve_with_stats(&model, &mut Tape::new(), &model.state())
        .unwrap();
    assert!(
        stats.converged && stats.residual <= stats.tolerance,
        "{stats:?}"
    );
    assert!(stats.tolerance <= 1e-10 * 10.0, "{stats:?}");
    // Net force f + m g on every free particle, evaluated independently.
    let f = model.eval_forces(&mut Tape::new(), &eq, None).to_vec();
    let w = model.particle_inv_mass.to_vec();
    let mut worst = 0.0f64;
    for (i, (f, w)) in f.iter().zip(&w).enumerate() {
        if *w > 0.0 {
            let net = *f + model.gravity.get(0) * (1.0 / w);
            worst = worst.max(net.norm());
            assert!(net.norm() < 1e-9, "particle {i}: net force {net:?}");
        }
    }
    // It sags: the middle is below the pins.
    assert!(eq.x.get(12).y < -0.01, "{:?}", eq.x.get(12));
    println!("{stats:?}, worst net force {worst:.1e} N");
}

#[test]
fn gradient_wrt_rest_lengths_matches_central_differences() {
    let model = net(4);
    check_param(&model, &model.param("springs", "rest").unwrap(), "rest");
}

#[test]
fn gradient_wrt_stiffness_matches_central_differences() {
    let model = net(4);
    check_param(&model, &model.param("springs", "ke").unwrap(), "ke");
}

#[test]
fn gradient_wrt_masses_matches_central_differences() {
    // Gravity loads the particles by their masses: the inverse masses are inputs (the pinned
    // corners' zeros stay zero; their gradient is not checked by perturbing them).
    let model = net(4);
    let w = model.particle_inv_mass.clone();
    let c = weights(model.particle_count);
    let w = w.requires_grad();
    let mut tape = Tape::new();
    let (l, eq) = loss(&model, &mut tape, &model.state(), &c);
    tape.backward(&l).unwrap();
    let g = w.grad().unwrap().to_vec();
    let start = State {
        x: Array::from_vec(eq.x.to_vec()),
        v: model.state().v,
        bodies: None,
    };
    let mut checked = 0;
    for (k, &gk) in g.iter().enumerate() {
        let w0 = w.get(k);
        if w0 == 0.0 {
            continue;
        }
        let eval = |v: f64| {
            w.set(k, v);
            loss(&model, &mut Tape::new(), &start, &c).0.get(0)
        };
        let n = central(eval, w0, 1e-4 * w0);
        w.set(k, w0);
        let err = (gk - n).abs() / n.abs().max(1e-6);
        assert!(
            err < 1e-6,
            "inv_mass[{k}]: adjoint {gk}, numeric {n}, error {err:e}"
        );
        checked += 1;
    }
    assert_eq!(checked, 12);
}

#[test]
fn gradient_wrt_the_pins_matches_central_differences() {
    // The pinned particles' positions come from the guess: moving a pin moves the net. The
    // free particles' guessed positions are only a starting point: no gradient.
    let model = net(4);
    let c = weights(model.particle_count);
    let guess = model.state();
    let x0 = guess.x.clone().requires_grad();
    let mut tape = Tape::new();
    let (l, eq) = loss(&model, &mut tape, &guess, &c);
    tape.backward(&l).unwrap();
    let g = x0.grad().unwrap().to_vec();
    let base = eq.x.to_vec();
    for i in 0..model.particle_count {
        let pinned = model.particle_inv_mass.get(i) == 0.0;
        for d in 0..3 {
            let ga = g[i][d];
            if !pinned {
                assert_eq!(ga, 0.0, "free particle {i}: the guess has no gradient");
                continue;
            }
            let eval = |s: f64| {
                let mut x = base.clone();
                x[i][d] += s;
                let start = State {
                    x: Array::from_vec(x),
                    v: guess.v.clone(),
                    bodies: None,
                };
                loss(&model, &mut Tape::new(), &start, &c).0.get(0)
            };
            let n = central(eval, 0.0, 1e-4);
            let err = (ga - n).abs() / n.abs().max(1e-3);
            assert!(
                err < 1e-6,
                "pin {i}[{d}]: adjoint {ga}, numeric {n}, error {err:e}"
            );
        }
    }
}

#[test]
fn one_newton_iteration_on_a_hard_problem_is_an_error() {
    // Stiff springs, a flat start far from the sagged equilibrium.
    let model = net(5);
    let ke = model.param::<f64>("springs", "ke").unwrap();
    ke.modify(|k| k.iter_mut().for_each(|k| *k = 5.0));
    let capped = Equilibrium {
        max_newton: 1,
        ..Equilibrium::default()
    };
    let err = capped
        .solve(&model, &mut Tape::new(), &model.state())
        .unwrap_err();
    assert!(
        matches!(err, Error::NotConverged { ref solver, .. } if solver == "Equilibrium Newton"),
        "{err}"
    );
    assert!(err.to_string().contains("raise `max_newton`"), "{err}");
}

#[test]
fn an_adjoint_solve_that_stops_short_is_a_backward_error() {
    let model = net(5);
    let rest = model
        .param::<f64>("springs", "rest")
        .unwrap()
        .requires_grad();
    let solver = Equilibrium {
        adjoint_linear: Some(SolveSettings {
            max_iter: 2,
            ..SolveSettings::default()
        }),
        ..Equilibrium::default()
    };
    let mut tape = Tape::new();
    let eq = solver.solve(&model, &mut tape, &model.state()).unwrap();
    let l = Array::zeros(1);
    tape.launch(
        weighted,
        model.particle_count,
        (&eq.x, &weights(model.particle_count), &l),
    );
    let err = tape.backward(&l).unwrap_err();
    assert!(
        err.to_string().contains("Equilibrium adjoint linear solve"),
        "{err}"
    );
    let _ = rest;
}

#[test]
fn a_nan_parameter_is_invalid_input() {
    let model = net(3);
    let rest = model.param::<f64>("springs", "rest").unwrap();
    rest.set(2, f64::NAN);
    let err = Equilibrium::default()
        .solve(&model, &mut Tape::new(), &model.state())
        .unwrap_err();
    match err {
        Error::InvalidInput { what, .. } => assert!(what.ends_with("[2]"), "{what}"),
        e => panic!("expected InvalidInput, got {e}"),
    }
    // And a NaN in the guess.
    let model = net(3);
    let guess = model.state();
    guess.x.set(4, Vec3::new(f64::NAN, 0.0, 0.0));
    let err = Equilibrium::default()
        .solve(&model, &mut Tape::new(), &guess)
        .unwrap_err();
    assert!(matches!(err, Error::InvalidInput { .. }), "{err}");
}

/// Forward mode through the equilibrium (`K dx* = M da`): `J v` with respect to the rest
/// lengths, stiffnesses, inverse masses and the pins agrees with the checked reverse mode by
/// the dot test, and with central differences along `v`; so Gauss-Newton products go through
/// quasi-static problems.
#[test]
fn tangent_agrees_with_the_adjoint_and_with_differences() {
    let model = net(4);
    let rest = model.param::<f64>("springs", "rest").unwrap();
    let ke = model.param::<f64>("springs", "ke").unwrap();
    let w = model.particle_inv_mass.clone();
    let guess = model.state();
    let inputs: [&dyn AnyArray; 4] = [&rest, &ke, &w, &guess.x];
    let n_in: usize = inputs.iter().map(|a| a.n_scalars()).sum();
    let mut v: Vec<f64> = (0..n_in)
        .map(|k| ((k * 37 % 11) as f64 - 5.0) / 5.0)
        .collect();
    // Inverse masses: only the free particles' (a pinned particle's 0 stays 0); small steps.
    let off = rest.len() + ke.len();
    for i in 0..w.len() {
        v[off + i] = if w.get(i) > 0.0 {
            v[off + i] * 0.5
        } else {
            0.0
        };
    }
    let solver = Equilibrium {
        tolerance: Some(1e-14),
        adjoint_linear: Some(SolveSettings {
            rel_tol: 1e-13,
            ..SolveSettings::default()
        }),
        ..Equilibrium::default()
    };
    let mut tape = Tape::new();
    let eq = solver.solve(&model, &mut tape, &guess).unwrap();
    let outputs: [&dyn AnyArray; 1] = [&eq.x];
    let jv = tape.jvp(&inputs, &v, &outputs).unwrap();
    let n_out = 3 * model.particle_count;
    let wv: Vec<f64> = (0..n_out)
        .map(|k| ((k * 13 % 7) as f64 - 3.0) / 3.0)
        .collect();
    let jtw = tape.vjp(&outputs, &wv, &inputs).unwrap();
    let lhs: f64 = jv.iter().zip(&wv).map(|(a, b)| a * b).sum();
    let rhs: f64 = v.iter().zip(&jtw).map(|(a, b)| a * b).sum();
    assert!(
        (lhs - rhs).abs() <= 1e-9 * lhs.abs().max(rhs.abs()),
        "<J v, w> = {lhs:e}, <v, J^T w> = {rhs:e}"
    );
    // J v against central differences of the re-solved equilibrium along v.
    let base: Vec<Vec<f64>> = inputs
        .iter()
        .map(|a| (0..a.n_scalars()).map(|k| a.scalar(k)).collect())
        .collect();
    let solve_at = |s: f64| -> Vec<f64> {
        let mut k = 0;
        for (a, b) in inputs.iter().zip(&base) {
            for (j, x) in b.iter().enumerate() {
                a.set_scalar(j, x + s * v[k]);
                k += 1;
            }
        }
        let x = solver
            .solve(&model, &mut Tape::new(), &guess)
            .unwrap()
            .x
            .to_vec();
        x.iter().flat_map(|p| [p.x, p.y, p.z]).collect()
    };
    let h = 1e-4;
    let (p1, m1, p2, m2) = (
        solve_at(h),
        solve_at(-h),
        solve_at(2.0 * h),
        solve_at(-2.0 * h),
    );
    solve_at(0.0);
    let scale = jv.iter().fold(1e-6f64, |m, x| m.max(x.abs()));
    for k in 0..n_out {
        let fd = (8.0 * (p1[k] - m1[k]) - (p2[k] - m2[k])) / (12.0 * h);
        assert!(
            (jv[k] - fd).abs() <= 1e-6 * scale,
            "(J v)[{k}] = {:e}, central differences {fd:e}",
            jv[k]
        );
    }
}

/// `statics::net_force`, the constraint of Gauss-Newton by the KKT system: zero at the
/// solved equilibrium, its derivatives in the positions (free and pinned), the rest lengths,
/// the stiffnesses and the inverse masses against central differences, forward mode against
/// reverse mode, and its errors.
#[test]
fn the_net_force_constraint_vanishes_at_equilibrium_and_differentiates() {
    use adflex_kernels::statics::net_force;
    use adflex_runtime::gradcheck::GradCheck;

    let model = net(4);
    let eq = Equilibrium::default()
        .solve(&model, &mut Tape::new(), &model.state())
        .unwrap();
    let c = net_force(&model, &mut Tape::new(), &eq.x).unwrap().to_vec();
    let worst = c.iter().map(|c| c.norm()).fold(0.0, f64::max);
    assert!(worst < 1e-9, "net force {worst:e} N at the equilibrium");
    // Away from it: the pinned rows are x - pin (zero where x is), the free ones the net force.
    let x = Array::from_vec(
        eq.x.to_vec()
            .iter()
            .enumerate()
            .map(|(i, p)| p + Vec3::new(0.01 * (i % 3) as f64, -0.02, 0.005 * (i % 2) as f64))
            .collect(),
    )
    .named("x");
    let c = net_force(&model, &mut Tape::new(), &x).unwrap().to_vec();
    let f = model
        .eval_forces(
            &mut Tape::new(),
            &State {
                x: x.clone(),
                v: Array::zeros(16),
                bodies: None,
            },
            None,
        )
        .to_vec();
    for (i, w) in model.particle_inv_mass.to_vec().iter().enumerate() {
        let expected = match *w > 0.0 {
            true => f[i] + model.gravity.get(0) / *w,
            false => Vec3::zeros(),
        };
        assert!((c[i] - expected).norm() < 1e-9, "particle {i}: {:?}", c[i]);
    }
    // Derivatives: a weighted sum of the constraint against central differences, in every
    // input the KKT system differentiates.
    let rest = model.param::<f64>("springs", "rest").unwrap();
    let ke = model.param::<f64>("springs", "ke").unwrap();
    let inv_mass = &model.particle_inv_mass;
    // Zero weight on the pinned rows: their `pin` is the value `x` holds when recorded, held
    // constant by the derivatives (the identity row, checked below) but moved by a
    // difference of `x`.
    let free = inv_mass.to_vec();
    let w = Array::from_vec(
        weights(16)
            .to_vec()
            .iter()
            .zip(&free)
            .map(|(w, f)| if *f > 0.0 { *w } else { Vec3::zeros() })
            .collect(),
    );
    let report = GradCheck::new()
        .step(1e-6)
        .run(
            |tape| {
                let c = net_force(&model, tape, &x).unwrap();
                let out = Array::zeros(1);
                tape.launch(weighted, 16, (&c, &w, &out));
                out
            },
            &[&x, &rest, &ke],
        )
        .unwrap();
    report.assert_within(1e-6);
    // The inverse mass of a free particle (a pinned one's 0 is where the row changes kind,
    // so central differences there mean nothing).
    let mut tape = Tape::new();
    let c = net_force(&model, &mut tape, &x).unwrap();
    let flat_w: Vec<f64> = w.to_vec().iter().flat_map(|v| [v.x, v.y, v.z]).collect();
    let g = tape.vjp(&[&c], &flat_w, &[inv_mass]).unwrap();
    let w0 = inv_mass.get(5);
    let at = |wi: f64| {
        inv_mass.set(5, wi);
        let c = net_force(&model, &mut Tape::new(), &x).unwrap().to_vec();
        inv_mass.set(5, w0);
        c.iter()
            .zip(w.to_vec())
            .map(|(c, w)| c.dot(&w))
            .sum::<f64>()
    };
    let h = 1e-6 * w0;
    let fd = (at(w0 + h) - at(w0 - h)) / (2.0 * h);
    assert!(
        (g[5] - fd).abs() <= 1e-6 * fd.abs(),
        "d/dw5: {} against {fd}",
        g[5]
    );
    // <J v, u> = <v, J^T u> over the positions and the rest lengths.
    let mut tape = Tape::new();
    let c = net_force(&model, &mut tape, &x).unwrap();
    let nv = 3 * 16 + rest.len();
    let v: Vec<f64> = (0..nv)
        .map(|k| ((k * 37) % 11) as f64 / 11.0 - 0.4)
        .collect();
    let u: Vec<f64> = (0..48).map(|k| ((k * 53) % 7) as f64 / 7.0 - 0.5).collect();
    let jv = tape.jvp(&[&x, &rest], &v, &[&c]).unwrap();
    let jtu = tape.vjp(&[&c], &u, &[&x, &rest]).unwrap();
    let (a, b): (f64, f64) = (
        jv.iter().zip(&u).map(|(a, b)| a * b).sum(),
        v.iter().zip(&jtu).map(|(a, b)| a * b).sum(),
    );
    assert!(
        (a - b).abs() <= 1e-12 * a.abs().max(b.abs()),
        "{a} against {b}"
    );
    // A pinned particle's row is the identity in its own position.
    let mut e = vec![0.0; nv];
    e[0] = 1.0; // particle 0 (a corner, pinned), x component
    let col = tape.jvp(&[&x, &rest], &e, &[&c]).unwrap();
    assert_eq!(col[0], 1.0);
    assert!(col[1..3].iter().all(|v| *v == 0.0));
    // Errors: a wrong number of positions, named.
    let e = net_force(&model, &mut Tape::new(), &Array::zeros(3))
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 positions for a model of 16 particles"), "{e}");
}
