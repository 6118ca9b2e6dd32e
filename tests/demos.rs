//! Every demo of `examples/` at a test size, asserting its success criterion. Each example
//! is included as a module: its `run(&Config::small())` is what `main` runs at full size.

#[path = "../examples/cage.rs"]
#[allow(dead_code)]
mod cage;

#[test]
fn cage_centre_reaches_the_target_in_a_few_lbfgs_iterations() {
    let out = cage::run(&cage::Config::small()).unwrap();
    assert!(out.miss < 1e-4, "miss {} m: {}", out.miss, out.report);
    // The loss falls by 4 orders of magnitude within 3 iterations.
    let l = out.report.losses();
    assert!(l[3.min(l.len() - 1)] < 1e-4 * l[0], "{:?}", l);
}

#[path = "../examples/stiff_pendulum.rs"]
#[allow(dead_code)]
mod stiff_pendulum;

#[test]
fn stiff_pendulum_stability_matches_theory() {
    let out = stiff_pendulum::run(&stiff_pendulum::Config::small()).unwrap();
    assert_eq!(out.runs.len(), 16);
    for r in &out.runs {
        assert_eq!(
            r.stable(),
            stiff_pendulum::predicted_stable(r.method, r.dt),
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
