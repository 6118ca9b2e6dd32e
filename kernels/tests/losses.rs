//! The loss kernels and helpers against central finite differences in f64, on a tape and in a
//! checkpointed rollout with a per-step (trajectory) loss.

use adflex_kernels::losses;
use adflex_kernels::prelude::*;
use adflex_runtime::checkpoint::Checkpointed;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;
use adflex_testkit::Rng;

#[test]
fn every_loss_kernel_matches_finite_differences() {
    let mut rng = Rng(7);
    let x = Array::from_vec(rng.vec3s(5, -1.0, 1.0));
    let y = Array::from_vec(rng.vec3s(5, -1.0, 1.0));
    let w = Array::from_vec(rng.scalars(5, 0.1, 1.0));
    let a = Array::from_vec(rng.scalars(4, -2.0, 2.0));
    let idx = Array::from_vec(vec![4u32, 0, 2]);
    let out = Array::<f64>::zeros(1);
    let g = GradCheck::new();
    let t = Vec3::new(0.3, -0.2, 0.5);
    g.kernel(losses::sq_distance_to_point, 3, (&x, &idx, t, 0.7, &out))
        .unwrap()
        .assert_within(1e-7);
    g.kernel(losses::sq_distance_between, 5, (&x, &y, 1.3, &out))
        .unwrap()
        .assert_within(1e-7);
    let c = Array::<Vec3<f64>>::zeros(1);
    g.kernel(losses::weighted_point_sum, 5, (&x, &w, &c))
        .unwrap()
        .assert_within(1e-7);
    g.kernel(losses::sum_sq, 4, (&a, 0.5, &out))
        .unwrap()
        .assert_within(1e-7);
    g.kernel(losses::sum_sq_vec3, 5, (&x, 2.0, &out))
        .unwrap()
        .assert_within(1e-7);
    // Per world: worlds 0 and 1 of the 5 entries.
    let world = Array::from_vec(vec![0u32, 1, 1, 0, 1]);
    let per_world = Array::<f64>::zeros(2);
    let b = Array::from_vec(rng.scalars(5, -2.0, 2.0));
    g.kernel(losses::sum_sq_per_world, 5, (&world, &b, 0.5, &per_world))
        .unwrap()
        .assert_within(1e-7);
    g.kernel(
        losses::sum_sq_vec3_per_world,
        5,
        (&world, &x, 2.0, &per_world),
    )
    .unwrap()
    .assert_within(1e-7);
}

fn chain() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let mut prev = b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.0);
    for k in 1..5 {
        let p = b.add_particle(
            Vec3::new(0.2 * k as f64, 1.0, 0.0),
            Vec3::zeros(),
            0.1 * k as f64,
        );
        b.add_spring(prev, p, 200.0, 0.2);
        prev = p;
    }
    b.finalize()
}

#[test]
fn the_helpers_values_and_gradients_through_a_rollout() {
    let model = chain();
    let weights = losses::mass_weights(&model);
    // Pinned particle 0 has weight 0; the rest are mass / total (0.1 + .. + 0.4 = 1).
    let w = weights.to_vec();
    assert_eq!(w[0], 0.0);
    assert!((w[3] - 0.3).abs() < 1e-15);
    let s0 = model.state();
    let com = {
        let mut tape = Tape::new();
        losses::center_of_mass(&mut tape, &s0.x, &weights).get(0)
    };
    assert!((com.x - (0.2 * 0.1 + 0.4 * 0.2 + 0.6 * 0.3 + 0.8 * 0.4)).abs() < 1e-12);

    let rest = model.param::<f64>("springs", "rest").unwrap();
    let v0 = s0.v.clone().named("v0");
    let recorded = Array::from_vec(
        (0..5)
            .map(|k| Vec3::new(0.2 * k as f64, 0.9, 0.05))
            .collect::<Vec<_>>(),
    );
    let report = GradCheck::new()
        .step(1e-6)
        .run(
            |tape| {
                let s = State {
                    x: s0.x.clone(),
                    v: v0.clone(),
                    bodies: None,
                };
                let end = SemiImplicitEuler
                    .rollout(&model, tape, &s, None, 1e-3, 30)
                    .unwrap();
                let l = Array::zeros(1);
                losses::distance_to_target(
                    tape,
                    &end.x,
                    &[2, 4],
                    Vec3::new(0.5, 0.8, 0.0),
                    1.0,
                    &l,
                );
                losses::frame_mismatch(tape, &end.x, &recorded, 0.5, &l);
                losses::center_of_mass_to_target(tape, &end.x, &weights, Vec3::zeros(), 2.0, &l);
                losses::sum_of_squares(tape, &rest, 0.1, &l);
                losses::sum_of_squares_vec3(tape, &end.v, 0.01, &l);
                l
            },
            &[&v0, &rest],
        )
        .unwrap();
    report.assert_within(1e-6);
}

#[test]
fn a_trajectory_loss_in_a_checkpointed_rollout_matches_finite_differences() {
    // Record a trajectory with one stiffness, then measure the mismatch of another's.
    let model = chain();
    let ke = model.param::<f64>("springs", "ke").unwrap();
    let steps = 40;
    let frames: Vec<Array<Vec3<f64>>> = {
        let mut tape = Tape::new();
        let mut s = model.state();
        let mut out = vec![s.x.deep_clone()];
        for _ in 0..steps {
            s = SemiImplicitEuler
                .step(&model, &mut tape, &s, None, 1e-3)
                .unwrap();
            out.push(s.x.deep_clone());
        }
        out
    };
    ke.modify(|k| k.iter_mut().for_each(|k| *k *= 1.3));
    let s0 = model.state();
    let run = || -> f64 {
        let out = Checkpointed::new(steps)
            .every(7)
            .run(
                &s0,
                |tape, s, _t| SemiImplicitEuler.step(&model, tape, s, None, 1e-3),
                |tape, s, t, acc| {
                    losses::frame_mismatch(tape, &s.x, &frames[t], 1.0, acc);
                    Ok(())
                },
            )
            .unwrap();
        out.loss.get(0)
    };
    let _ = ke.clone().requires_grad();
    let l = run();
    assert!(l > 0.0);
    let g = ke.grad().unwrap().to_vec();
    let h = 1e-5;
    for (i, &gi) in g.iter().enumerate() {
        let k = ke.get(i);
        ke.set(i, k + h);
        let lp = run();
        ke.set(i, k - h);
        let lm = run();
        ke.set(i, k);
        let fd = (lp - lm) / (2.0 * h);
        assert!(
            (fd - gi).abs() <= 1e-6 * fd.abs().max(1e-9),
            "ke[{i}]: adjoint {} fd {fd}",
            gi
        );
    }
}

#[test]
fn a_missing_or_mistyped_parameter_is_an_error_naming_what_exists() {
    let model = chain();
    let err = model.param::<f64>("spring", "ke").unwrap_err();
    let msg = err.to_string();
    assert!(
        msg.contains("spring.ke") && msg.contains("springs.rest, springs.ke, springs.kd"),
        "{msg}"
    );
    let err = model.param::<f32>("springs", "ke").unwrap_err();
    assert!(err.to_string().contains("f32"), "{err}");
    assert_eq!(model.param::<f64>("springs", "kd").unwrap().len(), 4);
}
