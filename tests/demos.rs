//! Every demo of `examples/` at a test size, asserting its success criterion. Each example
//! is included as a module: its `run(&Config::small())` is what `main` runs at full size.

#[path = "../examples/arm_identification.rs"]
#[allow(dead_code)]
mod arm_identification;
#[path = "../examples/arm_throw.rs"]
#[allow(dead_code)]
mod arm_throw;
#[path = "../examples/cage.rs"]
#[allow(dead_code)]
mod cage;
#[path = "../examples/cartpole_policy.rs"]
#[allow(dead_code)]
mod cartpole_policy;
#[path = "../examples/cartpole_swingup.rs"]
#[allow(dead_code)]
mod cartpole_swingup;
// The inverse-design demo is loaded once, inside the second-order demo that uses it.
use second_order::inverse_design;
#[path = "../examples/parameter_estimation.rs"]
#[allow(dead_code)]
mod parameter_estimation;
#[path = "../examples/quadruped_gait.rs"]
#[allow(dead_code)]
mod quadruped_gait;

#[test]
fn cage_centre_reaches_the_target_in_a_few_lbfgs_iterations() {
    let out = cage::run(&cage::Config::small()).unwrap();
    assert!(out.miss < 1e-4, "miss {} m: {}", out.miss, out.report);
    // The loss falls by 4 orders of magnitude within 3 iterations.
    let l = out.report.losses();
    assert!(l[3.min(l.len() - 1)] < 1e-4 * l[0], "{:?}", l);
}

/// The optimizers' chart of the cage demo: with the same budget of 40 rollouts, L-BFGS
/// converges and ends far below Adam and gradient descent, which both lower the loss.
#[test]
fn cage_optimizers_compared_on_one_budget() {
    let runs = cage::compare(&cage::Config::small(), 40).unwrap();
    let names: Vec<&str> = runs.iter().map(|(n, _)| *n).collect();
    assert_eq!(names.len(), 3);
    let (lbfgs, others) = runs.split_first().unwrap();
    assert!(lbfgs.1.converged(), "{}", lbfgs.1);
    for (name, r) in others {
        assert!(r.evaluations <= 40, "{name}: {}", r);
        assert!(r.loss < r.initial_loss, "{name}: {}", r);
        assert!(
            lbfgs.1.loss < 1e-6 * r.loss,
            "L-BFGS {} vs {name} {}",
            lbfgs.1,
            r
        );
    }
}

#[path = "../examples/stiff_pendulum.rs"]
#[allow(dead_code)]
mod stiff_pendulum;

#[test]
fn stiff_pendulum_stability_matches_theory() {
    let cfg = stiff_pendulum::Config::small();
    let out = stiff_pendulum::run(&cfg).unwrap();
    assert_eq!(out.runs.len(), 4 * stiff_pendulum::METHODS.len());
    for r in &out.runs {
        assert_eq!(
            r.stable(),
            stiff_pendulum::predicted_stable(r.method, r.dt, cfg.duration),
            "{} at dt = {}: max E/E0 = {}, error {:?}",
            r.method,
            r.dt,
            r.max_energy_ratio,
            r.error
        );
        if r.method == "explicit Euler" && r.dt <= 0.01 {
            // The energy grows by the linear theory's factor per step (within 15%) while
            // omega dt <= 1 (larger steps stretch the rod into its nonlinear range).
            let g = r
                .growth_per_step
                .expect("explicit Euler's energy grows exponentially");
            let p = stiff_pendulum::predicted_growth(r.dt);
            assert!(
                (g.ln() / p.ln() - 1.0).abs() < 0.15,
                "dt {}: {g} vs {p}",
                r.dt
            );
        }
    }
}

#[path = "../examples/billiards.rs"]
#[allow(dead_code)]
mod billiards;

#[test]
fn billiards_from_a_miss_needs_leaky_gradients_and_then_lands_the_ball() {
    let out = billiards::run(&billiards::Config::small()).unwrap();
    // Exact gradients of a miss are zero: no progress.
    assert_eq!(out.exact.report.history[0].grad_norm, 0.0);
    assert_eq!(out.exact.report.iterations, 0);
    // Leaky ones find the contact; the shot, replayed with exact contact, lands within 1 cm.
    assert!(
        out.leaky.miss < 0.01,
        "{} m: {}",
        out.leaky.miss,
        out.leaky.report
    );
}

#[path = "../examples/rigid_body.rs"]
#[allow(dead_code)]
mod rigid_body;

#[test]
fn rigid_body_flips_about_its_intermediate_axis_and_the_throw_lands_on_target() {
    let out = rigid_body::run(&rigid_body::Config::small()).unwrap();
    assert!(rigid_body::flips(&out.spins[0], 0).is_empty());
    assert!(!rigid_body::flips(&out.spins[1], 1).is_empty(), "no flip");
    assert!(rigid_body::flips(&out.spins[2], 2).is_empty());
    let t = &out.throw;
    assert!(
        t.miss < 0.03 && t.miss < 0.1 * t.initial_miss,
        "{} m: {}",
        t.miss,
        t.report
    );
    assert!(t.speed < 1e-3, "not at rest: {} m/s", t.speed);
}

#[test]
fn inverse_design_cable_takes_the_target_shape() {
    let out = inverse_design::run(&inverse_design::Config::small()).unwrap();
    // The equilibrium's RMS distance from the target parabola falls by more than 100x (in
    // practice by ~1e7, to ~1e-8 m).
    assert!(
        out.final_error < 1e-2 * out.initial_error && out.final_error < 1e-5,
        "{:e} m -> {:e} m: {}",
        out.initial_error,
        out.final_error,
        out.report
    );
    assert_eq!(out.frames.len(), 2);
}

#[test]
fn parameter_estimation_recovers_stiffness_damping_and_friction() {
    let out = parameter_estimation::run(&parameter_estimation::Config::small()).unwrap();
    // From 2x / 0.5x guesses, every value within 1% (in practice within ~1e-6: the recorded
    // trajectory is noise-free).
    for (name, t, r) in &out.values {
        assert!(
            (r - t).abs() < 1e-2 * t.abs(),
            "{name}: true {t}, recovered {r}: {}",
            out.report
        );
    }
    assert_eq!(out.values.len(), 7);
    assert_eq!(out.frames.len(), out.recorded.len() * 5 - 4);
}

#[path = "../examples/second_order.rs"]
#[allow(dead_code)]
mod second_order;

/// Gauss-Newton, Levenberg-Marquardt and Newton-CG identify the net's stiffnesses and design
/// the cable in a handful of iterations, where L-BFGS takes many, and in fewer passes over
/// the simulation (Gauss-Newton by the KKT system, on the cable, in 3x fewer).
#[test]
fn second_order_methods_take_fewer_iterations_and_passes_than_lbfgs() {
    let cfg = second_order::Config::small();
    let out = second_order::run(&cfg).unwrap();
    let design = second_order::design(&inverse_design::Config::small(), &cfg).unwrap();
    for (problem, runs) in [("identification", &out.runs), ("design", &design)] {
        let lbfgs = &runs[0];
        let level = 1e-10 * lbfgs.report.initial_loss;
        let base = second_order::passes_to(&lbfgs.report, level).unwrap_or_else(|| {
            panic!(
                "{problem}: L-BFGS does not reach {level:e}: {}",
                lbfgs.report
            )
        });
        for r in runs {
            println!(
                "{problem}: {:<20} {} iterations, {:?} passes to {level:.1e}, worst error {:.1e}",
                r.name,
                r.report.iterations,
                second_order::passes_to(&r.report, level),
                r.worst_relative_error
            );
            assert!(r.report.converged(), "{problem}, {}: {}", r.name, r.report);
            assert!(
                r.worst_relative_error < 1e-6,
                "{problem}, {}: worst error {:e}",
                r.name,
                r.worst_relative_error
            );
            if r.name == "L-BFGS" {
                continue;
            }
            assert!(
                5 * r.report.iterations <= lbfgs.report.iterations,
                "{problem}, {}: {} iterations against L-BFGS's {}",
                r.name,
                r.report.iterations,
                lbfgs.report.iterations
            );
            let passes = second_order::passes_to(&r.report, level).unwrap();
            assert!(
                passes < base,
                "{problem}, {}: {passes} passes against L-BFGS's {base}",
                r.name
            );
            // Gauss-Newton's and Levenberg-Marquardt's solves are preconditioned by the
            // products of the earlier ones: at least 1.5x fewer passes (measured on this
            // small run: 1.9x and 2.2x on the net, 1.8x and 1.7x on the cable).
            if r.name == "Gauss-Newton" || r.name == "Levenberg-Marquardt" {
                assert!(
                    3 * passes <= 2 * base,
                    "{problem}, {}: {passes} passes against L-BFGS's {base}",
                    r.name
                );
            }
            // The KKT form needs no linear solve through the equilibrium per product: at
            // least 3x fewer passes than L-BFGS (the target), and the exact fit.
            if r.name == "Gauss-Newton (KKT)" {
                assert!(
                    3 * passes <= base,
                    "{problem}: {passes} passes against L-BFGS's {base}"
                );
                assert!(r.report.sweeps > 0, "{}", r.report);
            }
        }
    }
}

/// Gauss-Newton by the KKT system designs a sheet (rest lengths for a target equilibrium) at
/// a size where the system is assembled sparse: the first step finds the pattern by probing
/// (a few rounds of sweeps, far fewer than one per unknown), every step takes one sweep per
/// colour of the columns and the check's two; the equilibrium takes the target shape.
#[test]
fn the_kkt_method_designs_a_sheet_with_coloured_sweeps() {
    let cfg = second_order::Config {
        max_iters: 30,
        ..second_order::Config::small()
    };
    let sh = second_order::sheet(12, &cfg).unwrap();
    println!("sheet: {sh}");
    assert!(sh.report.converged(), "{}", sh.report);
    assert!(
        sh.first_sweeps > sh.later_sweeps && 2 * sh.first_sweeps < sh.unknowns,
        "{} sweeps in the first step for {} unknowns",
        sh.first_sweeps,
        sh.unknowns
    );
    assert!(
        sh.later_sweeps > 2 && 10 * sh.later_sweeps < sh.unknowns,
        "{} sweeps per later step for {} unknowns",
        sh.later_sweeps,
        sh.unknowns
    );
    assert!(
        sh.final_error < 1e-3 && sh.final_error < 1e-2 * sh.initial_error,
        "{:e} -> {:e}",
        sh.initial_error,
        sh.final_error
    );
}

#[path = "../examples/soft_body.rs"]
#[allow(dead_code)]
mod soft_body;

#[test]
fn soft_body_crawls_toward_the_goal() {
    let cfg = soft_body::Config::small();
    let out = soft_body::run(&cfg).unwrap();
    println!(
        "{}\npassive {:+.4} m, initial {:+.4} m, optimized {:+.4} m",
        out.report, out.passive, out.before, out.after
    );
    // The optimized gait moves the centre of mass forward by more than 5 cm (12.7 cm when
    // written), at least 5 cm more than the initial gait and than lying still, and the loss
    // fell. It is a crawl: the body never leaves the ground and its centre of mass stays low.
    assert!(out.after > 0.05, "{} m: {}", out.after, out.report);
    assert!(
        out.after > out.before + 0.05,
        "{} vs {}",
        out.after,
        out.before
    );
    assert!(
        out.after > out.passive + 0.05,
        "{} vs {}",
        out.after,
        out.passive
    );
    assert_eq!(out.airborne, 0.0);
    assert!(out.max_lift < 0.01, "{} m", out.max_lift);
    assert!(out.report.loss < out.report.initial_loss, "{}", out.report);
}

#[test]
fn soft_body_loss_gradient_matches_central_differences() {
    // A 2 x 1 x 1 block for 100 steps: the demo's loss (rollout, gait kernel, ground contact
    // with friction, centre of mass, regularizer) w.r.t. its four amplitudes, in f64.
    let cfg = soft_body::Config {
        dims: [2, 1, 1],
        duration: 0.05,
        ..soft_body::Config::small()
    };
    let scene = soft_body::scene(&cfg);
    let amp = adflex::prelude::Array::from_vec(
        soft_body::initial_amplitudes(scene.groups)
            .iter()
            .map(|a| 5.0 * a)
            .collect(),
    )
    .named("amplitudes");
    let report = adflex::runtime::gradcheck::GradCheck::new()
        .step(1e-6)
        .run(
            |tape| soft_body::loss(tape, &scene, &amp, &cfg).unwrap(),
            &[&amp],
        )
        .unwrap();
    println!("{report}");
    assert_eq!(report.checked, 4);
    assert!(report.is_within(1e-5), "{report}");
}

#[path = "../examples/cloth.rs"]
#[allow(dead_code)]
mod cloth;

#[test]
fn cloth_lands_on_the_target_spot() {
    let out = cloth::run(&cloth::Config::small()).unwrap();
    assert!(
        out.miss < 0.02 && out.miss < 0.05 * out.initial_miss,
        "{} m (first guess {} m): {}",
        out.miss,
        out.initial_miss,
        out.report
    );
}

#[test]
fn cloth_loss_gradient_matches_central_differences() {
    let cfg = cloth::Config {
        n: 4,
        ..cloth::Config::small()
    };
    let report = cloth::fd_check(&cfg, adflex::prelude::Vec3::new(0.5, 1.0, 0.0));
    assert!(report.is_within(1e-6), "{report}");
}

/// The cart-pole swings up from hanging and ends upright and nearly still within 100 L-BFGS
/// iterations (3 s, 180 frames of 2 substeps).
#[test]
fn cartpole_swings_up_and_stays_upright() {
    let out = cartpole_swingup::run(&cartpole_swingup::Config::small()).unwrap();
    assert!(out.report.history.len() <= 101);
    assert!(
        out.upright < 1e-2 && out.speed < 0.2 && out.spin < 0.2,
        "1 - cos theta {:.1e}, cart {:.2} m/s, pole {:.2} rad/s: {}",
        out.upright,
        out.speed,
        out.spin,
        out.report
    );
    // It did swing: the pole passed through horizontal on the way.
    assert!(out.frames.iter().any(|s| s.q.get(1).cos().abs() < 0.2));
}

/// The arm's seven link masses, started 30% off, are recovered from a recorded trajectory.
#[test]
fn arm_masses_are_identified_from_a_trajectory() {
    let out = arm_identification::run(&arm_identification::Config::small()).unwrap();
    assert!(out.mass_error.0 > 0.29);
    assert!(
        out.mass_error.1 < 1e-4,
        "mass error {:.2e}: {}",
        out.mass_error.1,
        out.report
    );
}

/// The arm's throw, tuned through the cup's contacts and the release, lands the ball within
/// 1 mm of a target it first missed by over 50 cm; the ball left the cup during the swing.
#[test]
fn arm_throws_the_ball_to_the_target() {
    // From the demo's first guess and from one changed in its last digits (which, before the
    // cup's contact had an onset, decided between 3.5 and 36 cm).
    for perturb in [0.0, -1e-9] {
        let cfg = arm_throw::Config {
            perturb,
            ..arm_throw::Config::small()
        };
        let out = arm_throw::run(&cfg).unwrap();
        assert!(out.miss.0 > 0.5, "first guess {}", out.miss.0);
        assert!(out.miss.1 < 1e-3, "miss {} m: {}", out.miss.1, out.report);
        assert!(
            out.release > cfg.settle && out.release < cfg.settle + cfg.swing + 0.1,
            "released at {} s",
            out.release
        );
    }
}

/// The quadruped's open-loop gait, tuned through ground contact, carries the torso forward
/// (1 s and 15 iterations at this size) on its legs, from the first guess and from one a
/// millionth off (before the feet's stiction tolerance was raised, such neighbours walked
/// 0.12 m or 0.54 m: the gradient through 500 steps had exploded to norms of 1e6-1e7).
#[test]
fn quadruped_gait_moves_forward_through_contact() {
    for perturb in [0.0, 1e-6] {
        let cfg = quadruped_gait::Config {
            perturb,
            ..quadruped_gait::Config::small()
        };
        let out = quadruped_gait::run(&cfg).unwrap();
        assert!(
            out.distance.1 > 0.3 && out.distance.1 > out.distance.0 + 0.2,
            "perturbed by {perturb}: moved {:?}: {}",
            out.distance,
            out.report
        );
        // A gradient of the size of the loss's changes, not one blown up by the steps.
        assert!(
            out.report.initial_grad_norm < 10.0,
            "{}",
            out.report.initial_grad_norm
        );
        // The torso (a box 10 cm high) stays off the floor, and the gait is not an artefact
        // of the time step.
        assert!(out.lowest > 0.06, "the torso touched down: {}", out.lowest);
        assert!(
            (out.distance_half_dt - out.distance.1).abs() < 0.1 * out.distance.1,
            "{} m at half the time step, {} m found",
            out.distance_half_dt,
            out.distance.1
        );
    }
}

/// A balancing policy trained by gradients through 32 worlds (short windows) keeps most new
/// random starts balanced for 10 s; untrained, none. The gradient over a long horizon is
/// orders of magnitude larger than over a window: why the windows are short.
#[test]
fn cartpole_policy_learns_to_balance_over_many_worlds() {
    let cfg = cartpole_policy::Config::small();
    let out = cartpole_policy::run(&cfg).unwrap();
    assert!(out.success_before < 0.1, "{}", out.success_before);
    assert!(
        out.success >= 0.8,
        "balanced in {:.1}% of worlds",
        100.0 * out.success
    );
    let norm = |h: usize| {
        out.grad_norms_initial
            .iter()
            .find(|p| p.0 == h)
            .map(|p| p.1)
            .unwrap()
    };
    assert!(
        norm(500) > 100.0 * norm(cfg.window),
        "{:?}",
        out.grad_norms_initial
    );
}

/// The policy's window gradient (through the network kernels, 4 worlds and 32 steps of the
/// cart-poles) against central differences along a random direction.
#[test]
fn cartpole_policy_gradient_matches_central_differences() {
    let hidden = 8;
    let n = hidden * 7 + 1;
    let mut rng = adflex_testkit::Rng(5);
    let values: Vec<f64> = (0..n).map(|_| rng.uniform(-0.5, 0.5)).collect();
    let dir: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let at = |t: f64| {
        let v: Vec<f64> = values.iter().zip(&dir).map(|(a, d)| a + t * d).collect();
        cartpole_policy::window_loss_and_grad(&v, 4, hidden, 32, 3).unwrap()
    };
    let (_, g) = at(0.0);
    let h = 1e-6;
    let fd = (at(h).0 - at(-h).0) / (2.0 * h);
    let ad: f64 = g.iter().zip(&dir).map(|(a, b)| a * b).sum();
    assert!((ad - fd).abs() < 1e-6 * fd.abs().max(1e-8), "{ad} vs {fd}");
}

#[path = "../examples/mpm_walker.rs"]
#[allow(dead_code)]
mod mpm_walker;

/// The walker walks right under gradient descent, and its loss curve is Taichi's: the same
/// losses to 1e-4, and the progress `loss_k - loss_0` within 5% of Taichi's at every
/// iteration.
#[test]
fn mpm_walker_learns_to_walk_as_in_taichi() {
    let out = mpm_walker::run(&mpm_walker::Config::small()).unwrap();
    let taichi = mpm_walker::taichi_losses(mpm_walker::TAICHI_SMALL);
    assert_eq!(out.losses.len(), taichi.len());
    for (k, (a, t)) in out.losses.iter().zip(&taichi).enumerate() {
        assert!(
            (a - t).abs() < 1e-4 * t.abs(),
            "iteration {k}: {a} vs Taichi {t}"
        );
        if k > 0 {
            let (pa, pt) = (a - out.losses[0], t - taichi[0]);
            assert!(
                (pa - pt).abs() < 0.05 * pt.abs(),
                "iteration {k}: progress {pa:e} vs Taichi {pt:e}"
            );
        }
    }
    assert!(
        out.distance_after > 1.5 * out.distance_before,
        "{} -> {}",
        out.distance_before,
        out.distance_after
    );
    assert_eq!(out.frames.len(), 6);
    assert_eq!(out.frames_before.len(), 6);
}

#[path = "../examples/smoke_control.rs"]
#[allow(dead_code)]
mod smoke_control;

/// Smoke control through the CG pressure solve's implicit adjoint: L-BFGS on the filtered
/// initial velocity brings the final density much closer to the target, and the smoke parts
/// evenly (the first guess is mirror-symmetric; a lopsided gradient would break it).
#[test]
fn smoke_control_moves_the_smoke_towards_the_target() {
    let cfg = smoke_control::Config::small();
    let out = smoke_control::run(&cfg).unwrap();
    let (first, last) = (out.losses[0], *out.losses.last().unwrap());
    assert!(last < 0.2 * first, "loss {first} -> {last}");
    assert!(out.losses.iter().all(|l| l.is_finite()));
    let (before, after) = out.distances;
    assert!(after < 0.25 * before, "distance {before} -> {after}");
    let d = &out.fields[2];
    let half = |left: bool| -> f64 {
        (0..d.len())
            .filter(|t| (t / cfg.n < cfg.n / 2) == left)
            .map(|t| d[t])
            .sum()
    };
    let (l, r) = (half(true), half(false));
    assert!((l - r).abs() < 0.1 * (l + r), "left {l}, right {r}");
}
