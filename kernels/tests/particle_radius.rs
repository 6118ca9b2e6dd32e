//! Per-particle contact radii (`ModelBuilder::set_particle_radius`): balls of different sizes
//! rest on the ground and on a shape at their own radii, a pair touches at `r_i + r_j`, the
//! model keeps an array of radii only when they differ, bad radii are problems naming the
//! particle, and the contact gradients with per-particle radii match central differences.

use adflex_kernels::prelude::*;
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;

fn settle(m: &Model<f64>, steps: usize) -> State<f64> {
    let mut s = m.state();
    for _ in 0..steps {
        s = SemiImplicitEuler
            .step(m, &mut Tape::new(), &s, None, 5e-4)
            .unwrap();
    }
    s
}

#[test]
fn balls_rest_on_the_ground_and_a_shape_at_their_own_radii() {
    let mut b = ModelBuilder::<f64>::new();
    let small = b.add_particle_with_radius(Vec3::new(0.0, 0.05, 0.0), Vec3::zeros(), 0.1, 0.02);
    let big = b.add_particle_with_radius(Vec3::new(1.0, 0.15, 0.0), Vec3::zeros(), 0.1, 0.1);
    let plain = b.add_particle(Vec3::new(2.0, 0.05, 0.0), Vec3::zeros(), 0.1);
    let on_sphere = b.add_particle_with_radius(Vec3::new(3.0, 0.6, 0.0), Vec3::zeros(), 0.1, 0.05);
    // Damped on approach too, so that the balls settle quickly (this test is about radii).
    b.set_ground(Ground {
        ke: 1.0e4,
        kd: 2.0,
        damp_approach: true,
        ..Ground::default()
    });
    b.add_shape(Shape::new(
        ShapeKind::Sphere { radius: 0.3 },
        Vec3::new(3.0, 0.2, 0.0),
    ));
    b.set_shape_contact(ParticleContact {
        ke: 1.0e4,
        kd: 2.0,
        mu: 1.0,
        ..ParticleContact::default()
    });
    let m = b.finalize();
    assert_eq!(
        m.particle_radii.as_ref().unwrap().to_vec(),
        vec![0.02, 0.1, 0.01, 0.05]
    );
    let x = settle(&m, 4000).x.to_vec();
    // Sunk by m g / ke = 1e-4 m.
    for (i, rest) in [(small, 0.02), (big, 0.1), (plain, 0.01), (on_sphere, 0.55)] {
        let y = x[i as usize].y;
        println!("particle {i}: rests at {y:.5} (radius surface at {rest})");
        assert!(
            (y - rest + 1e-4).abs() < 2e-4,
            "particle {i} at {y}, expected {rest}"
        );
    }
}

#[test]
fn a_pair_touches_at_the_sum_of_its_radii() {
    let force_at = |d: f64| {
        let mut b = ModelBuilder::<f64>::new();
        b.gravity = Vec3::zeros();
        b.add_particle_with_radius(Vec3::zeros(), Vec3::zeros(), 1.0, 0.03);
        b.add_particle_with_radius(Vec3::new(d, 0.0, 0.0), Vec3::zeros(), 1.0, 0.12);
        b.set_particle_contact(ParticleContact::default());
        let m = b.finalize();
        m.eval_forces(&mut Tape::new(), &m.state(), None).get(1).x
    };
    assert_eq!(force_at(0.1501), 0.0);
    let f = force_at(0.1499);
    assert!((f - 1000.0 * 1e-4).abs() < 1e-9, "{f}");
    // Dynamics: a small ball thrown at a big one at rest comes to r_i + r_j and pushes it.
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    b.add_particle_with_radius(Vec3::zeros(), Vec3::new(0.2, 0.0, 0.0), 0.1, 0.01);
    b.add_particle_with_radius(Vec3::new(0.2, 0.0, 0.0), Vec3::zeros(), 0.1, 0.09);
    b.set_particle_contact(ParticleContact {
        ke: 1.0e4,
        ..ParticleContact::default()
    });
    let m = b.finalize();
    let mut s = m.state();
    let mut closest = f64::INFINITY;
    for _ in 0..2000 {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, 5e-4)
            .unwrap();
        let x = s.x.to_vec();
        closest = closest.min((x[1] - x[0]).norm());
    }
    println!("closest approach {closest:.5} (r_i + r_j = 0.1)");
    assert!(closest < 0.1 && closest > 0.099, "{closest}");
    let v = s.v.to_vec();
    // Equal masses: the momentum passes to the big ball.
    assert!(v[0].x.abs() < 0.05 && v[1].x > 0.15, "{v:?}");
}

#[test]
fn radii_cost_only_when_they_differ() {
    let mut b = ModelBuilder::<f64>::new();
    b.particle_radius = 0.05;
    b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
    b.add_particle_with_radius(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0, 0.05);
    let m = b.finalize();
    assert!(m.particle_radii.is_none());
    assert_eq!(m.particle_radius_of(1), 0.05);
    b.set_particle_radius(0, 0.2);
    let m = b.finalize();
    assert_eq!(m.particle_radii.as_ref().unwrap().to_vec(), vec![0.2, 0.05]);
    assert_eq!(m.particle_radius_of(0), 0.2);
}

#[test]
fn bad_radii_are_problems_naming_the_particle() {
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
    b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::zeros(), 1.0);
    b.set_particle_radius(1, f64::NAN);
    b.set_particle_radius(0, -0.1);
    b.set_particle_radius(5, 0.1);
    let e = b.try_finalize().unwrap_err();
    let shown: Vec<String> = e.problems.iter().map(|p| p.to_string()).collect();
    println!("{shown:#?}");
    assert_eq!(e.problems.len(), 3);
    assert!(shown[0].starts_with("particles[1].radius"), "{}", shown[0]);
    assert!(shown[1].starts_with("particles[0].radius"), "{}", shown[1]);
    assert!(shown[2].contains("out of range"), "{}", shown[2]);
}

#[test]
fn scene_files_take_a_radius_per_particle() {
    let json = r#"{
        "particle_radius": 0.02,
        "particles": [ { "x": [0, 1, 0], "mass": 1 }, { "x": [1, 1, 0], "mass": 1, "radius": 0.1 } ]
    }"#;
    let m = ModelBuilder::<f64>::from_json_str(json).unwrap().finalize();
    assert_eq!(m.particle_radii.as_ref().unwrap().to_vec(), vec![0.02, 0.1]);
    let bad = r#"{ "particles": [ { "x": [0, 1, 0], "mass": 1, "radius": -1 } ] }"#;
    let err = ModelBuilder::<f64>::from_json_str(bad).unwrap_err();
    assert_eq!(err.field.as_deref(), Some("particles[0].radius"), "{err:?}");
}

#[diff_kernel]
fn weigh(x: &Array<Vec3<f64>>, v: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    let w = vec3(1.0, 2.0, -0.5);
    loss.atomic_add(0, dot(x[t], w) * 10.0 + dot(v[t], w));
}

/// Ground, particle and shape contact, every particle with its own radius and in contact
/// during the rollout: the gradient with respect to the initial positions and velocities
/// against central differences.
#[test]
fn contact_gradients_with_per_particle_radii() {
    let mut b = ModelBuilder::<f64>::new();
    let v = |x: f64, y: f64, z: f64| Vec3::new(x, y, z);
    // In the ground.
    b.add_particle_with_radius(v(0.0, 0.035, 0.0), v(0.3, -0.1, 0.2), 1.0, 0.04);
    b.add_particle_with_radius(v(0.5, 0.08, 0.0), v(-0.1, -0.2, 0.1), 1.0, 0.09);
    b.set_ground(Ground::default());
    // Two overlapping particles of different radii.
    b.add_particle_with_radius(v(3.0, 1.0, 0.0), v(0.1, 0.03, 0.2), 1.0, 0.02);
    b.add_particle_with_radius(v(3.1, 1.01, 0.0), v(-0.1, 0.1, 0.0), 1.0, 0.09);
    b.set_particle_contact(ParticleContact::default());
    // On a box.
    b.add_shape(Shape::new(
        ShapeKind::Box {
            half_extents: v(0.3, 0.3, 0.3),
        },
        v(2.0, 0.5, 0.0),
    ));
    b.add_particle_with_radius(v(2.05, 0.86, 0.0), v(0.2, -0.1, 0.1), 1.0, 0.07);
    let m = b.finalize();
    let s0 = m.state();
    let report = GradCheck::new()
        .step(1e-6)
        .run(
            |tape| {
                let s = SemiImplicitEuler
                    .rollout(&m, tape, &s0, None, 1e-2, 4)
                    .unwrap();
                let loss = Array::zeros(1).named("loss");
                tape.launch(weigh, s.x.len(), (&s.x, &s.v, &loss));
                loss
            },
            &[&s0.x, &s0.v],
        )
        .unwrap();
    println!("{report}");
    assert!(report.is_within(1e-5), "{report}");
}
