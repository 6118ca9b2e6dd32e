//! Particles against articulated links ([`LinkParticleContact`]), and the links' external
//! forces ([`ArticulationControl::link_f`], `link_t`): momentum shared exactly, rollout
//! gradients against central differences and forward mode against reverse mode, worlds kept
//! apart, a cloth resting on an arm, and the refusals.

use adflex_kernels::articulation::{
    ArticulationBuilder, ArticulationControl, ArticulationState, Articulations, ContactFilter,
    Inertial, Joint, Pose,
};
use adflex_kernels::coupling::LinkParticleContact;
use adflex_kernels::prelude::*;
use adflex_runtime::{Array, Quat, Tape, Vec3};

/// Three free bodies without gravity: a ball, a box turned about z, a capsule along y.
fn three_bodies() -> ArticulationBuilder {
    bodies_with_rod(false)
}

/// [`three_bodies`], the rod a cylinder along y when `cylinder` is set.
fn bodies_with_rod(cylinder: bool) -> ArticulationBuilder {
    let mut b = ArticulationBuilder::new();
    b.gravity = Vec3::zeros();
    let at = |x: f64| Joint::free().initial(&[x, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
    let ball = b.add_link(
        "ball",
        None,
        at(0.0),
        Inertial::sphere(1.0, 0.1, Vec3::zeros()),
    );
    b.add_contact_sphere(ball, Vec3::zeros(), 0.1);
    let cube = b.add_link(
        "box",
        None,
        at(1.0),
        Inertial::cuboid(2.0, Vec3::new(0.1, 0.1, 0.1), Vec3::zeros()),
    );
    let turn = nalgebra::UnitQuaternion::from_axis_angle(&Vec3::z_axis(), 0.3);
    b.add_contact_box(
        cube,
        &Pose::new(Vec3::zeros(), *turn.quaternion()),
        Vec3::new(0.1, 0.1, 0.1),
    );
    let rod = b.add_link(
        "rod",
        None,
        at(2.0),
        Inertial::cuboid(0.5, Vec3::new(0.05, 0.3, 0.05), Vec3::zeros()),
    );
    if cylinder {
        let along_y =
            nalgebra::UnitQuaternion::from_axis_angle(&Vec3::x_axis(), std::f64::consts::FRAC_PI_2);
        let shape = adflex_kernels::articulation::contact::GeomShape::Cylinder(0.05, 0.25);
        b.add_contact_shape(
            rod,
            &Pose::new(Vec3::zeros(), *along_y.quaternion()),
            &shape,
        );
    } else {
        b.add_contact_capsule(
            rod,
            Vec3::new(0.0, -0.25, 0.0),
            Vec3::new(0.0, 0.25, 0.0),
            0.05,
        );
    }
    b
}

/// Two particles per body, coming at it from above and from the side, off centre.
fn shot_particles() -> ModelBuilder<f64> {
    let mut pb = ModelBuilder::<f64>::new();
    pb.gravity = Vec3::zeros();
    pb.particle_radius = 0.02;
    for k in 0..3 {
        let x = k as f64;
        pb.add_particle(
            Vec3::new(x + 0.03, 0.02, 0.2),
            Vec3::new(0.1, 0.0, -1.5),
            0.05,
        );
        pb.add_particle(
            Vec3::new(x - 0.25, 0.05, -0.01),
            Vec3::new(1.2, 0.2, 0.0),
            0.08,
        );
    }
    pb
}

/// The world linear velocity of free body `k` (7 coordinates, 6 velocities each).
fn world_velocity(q: &[f64], qd: &[f64], k: usize) -> Vec3<f64> {
    let (s, d) = (7 * k, 6 * k);
    let r = Quat::new(q[s + 6], q[s + 3], q[s + 4], q[s + 5]);
    let l = Quat::new(0.0, qd[d], qd[d + 1], qd[d + 2]);
    (r * l * r.conjugate()).imag()
}

fn momentum(
    model: &Model<f64>,
    s: &State<f64>,
    arts: &Articulations<f64>,
    a: &ArticulationState<f64>,
) -> Vec3<f64> {
    let (q, qd) = (a.q.to_vec(), a.qd.to_vec());
    let mut p = Vec3::zeros();
    for i in 0..model.particle_count {
        p += s.v.get(i) / model.particle_inv_mass.get(i);
    }
    for k in 0..arts.n_links() {
        p += world_velocity(&q, &qd, k) * arts.mass.get(k);
    }
    p
}

struct Run {
    v0: Array<Vec3<f64>>,
    qd0: Array<f64>,
    end: State<f64>,
    aend: ArticulationState<f64>,
}

fn run(
    model: &Model<f64>,
    arts: &Articulations<f64>,
    coupling: &LinkParticleContact<f64>,
    (dv, dqd): (f64, f64),
    steps: usize,
    tape: &mut Tape,
) -> Run {
    let mut s = model.state();
    let mut v: Vec<Vec3<f64>> = s.v.to_vec();
    v[0].z += dv;
    s.v = Array::from_vec(v).requires_grad();
    let mut a = arts.state();
    let mut qd = a.qd.to_vec();
    qd[2] += dqd;
    a.qd = Array::from_vec(qd).requires_grad();
    let (v0, qd0) = (s.v.clone(), a.qd.clone());
    for _ in 0..steps {
        (s, a) = coupling
            .step(
                tape,
                (model, &SemiImplicitEuler),
                &s,
                None,
                arts,
                &a,
                None,
                1e-3,
            )
            .unwrap();
    }
    Run {
        v0,
        qd0,
        end: s,
        aend: a,
    }
}

#[test]
fn particles_and_free_bodies_share_momentum_with_right_gradients() {
    let arts = three_bodies().finalize::<f64>().unwrap();
    let model = shot_particles().finalize();
    let coupling = LinkParticleContact {
        ke: 2000.0,
        kd: 2.0,
        mu: 0.4,
        ..Default::default()
    };
    let steps = 300;
    let mut tape = Tape::new();
    let start = momentum(&model, &model.state(), &arts, &arts.state());
    let r = run(&model, &arts, &coupling, (0.0, 0.0), steps, &mut tape);
    let end = momentum(&model, &r.end, &arts, &r.aend);
    assert!(
        (end - start).norm() < 1e-9 * start.norm(),
        "momentum {start:?} -> {end:?}"
    );
    println!(
        "momentum kept to {:.1e} relative",
        (end - start).norm() / start.norm()
    );
    // Every body was hit: it moves, and spins (friction off its centre).
    let (q, qd) = (r.aend.q.to_vec(), r.aend.qd.to_vec());
    for k in 0..3 {
        let v = world_velocity(&q, &qd, k);
        let w = Vec3::new(qd[6 * k + 3], qd[6 * k + 4], qd[6 * k + 5]);
        assert!(
            v.norm() > 0.02 && w.norm() > 1e-3,
            "body {k}: v {v:?}, w {w:?}"
        );
    }

    // d(ball's z, particle 0's z)/d(particle 0's initial vz, ball's initial vz) (particle 0
    // hits the ball: each output depends on both families), reverse, forward and central
    // differences.
    let outs = |r: &Run| (r.aend.q.get(2), r.end.x.get(0).z);
    let n_q = arts.n_q;
    let np = model.particle_count;
    for (which, w) in [(0, 1.0), (1, 0.0)] {
        let mut wq = vec![0.0; n_q];
        wq[2] = w;
        let mut wx = vec![0.0; 3 * np];
        wx[2] = 1.0 - w;
        let g = tape
            .vjp(&[&r.aend.q, &r.end.x], &[wq, wx].concat(), &[&r.v0, &r.qd0])
            .unwrap();
        let loss = |d: (f64, f64)| {
            let o = outs(&run(&model, &arts, &coupling, d, steps, &mut Tape::new()));
            w * o.0 + (1.0 - w) * o.1
        };
        let h = 1e-6;
        let fd_v = (loss((h, 0.0)) - loss((-h, 0.0))) / (2.0 * h);
        let fd_qd = (loss((0.0, h)) - loss((0.0, -h))) / (2.0 * h);
        let (g_v, g_qd) = (g[2], g[3 * np + 2]);
        assert!(g_v != 0.0 && g_qd != 0.0, "output {which}: {g_v}, {g_qd}");
        for (name, g, fd) in [("v0", g_v, fd_v), ("qd0", g_qd, fd_qd)] {
            println!(
                "output {which}, d/d{name}: reverse {g:.6e}, differences {fd:.6e}, relative \
                 {:.1e}",
                (g - fd).abs() / fd.abs().max(1e-3)
            );
            assert!(
                (g - fd).abs() < 1e-6 * fd.abs().max(1e-3),
                "output {which}, d/d{name}: reverse {g} vs differences {fd}"
            );
        }
        // Forward mode along (1, 1) gives the sum.
        let mut dir = vec![0.0; 3 * np + arts.n_dof];
        dir[2] = 1.0;
        dir[3 * np + 2] = 1.0;
        let jv = tape
            .jvp(&[&r.v0, &r.qd0], &dir, &[&r.aend.q, &r.end.x])
            .unwrap();
        let forward = w * jv[2] + (1.0 - w) * jv[n_q + 2];
        println!(
            "output {which}: forward against reverse {:.1e}",
            (forward - (g_v + g_qd)).abs() / (g_v + g_qd).abs().max(1e-3)
        );
        assert!(
            (forward - (g_v + g_qd)).abs() < 1e-9 * (g_v + g_qd).abs().max(1e-3),
            "output {which}: forward {forward} vs reverse {}",
            g_v + g_qd
        );
    }
}

#[test]
fn worlds_do_not_touch_and_keep_their_bits() {
    let one = three_bodies();
    let parts = shot_particles();
    let coupling = LinkParticleContact::<f64>::default();
    let alone = run(
        &parts.finalize(),
        &one.finalize::<f64>().unwrap(),
        &coupling,
        (0.0, 0.0),
        150,
        &mut Tape::new(),
    );
    // World 1 is the same scene; world 0 has the bodies only, at the same places.
    let mut arts = ArticulationBuilder::new();
    arts.gravity = Vec3::zeros();
    arts.add_world(&one);
    arts.add_world(&one);
    let mut pb = ModelBuilder::<f64>::new();
    pb.gravity = Vec3::zeros();
    pb.particle_radius = 0.02;
    pb.add_world(&ModelBuilder::new());
    pb.add_world(&parts);
    let (model, arts) = (pb.finalize(), arts.finalize::<f64>().unwrap());
    assert_eq!((model.worlds.len(), arts.n_worlds()), (2, 2));
    let mut s = model.state();
    let mut a = arts.state();
    for _ in 0..150 {
        (s, a) = coupling
            .step(
                &mut Tape::new(),
                (&model, &SemiImplicitEuler),
                &s,
                None,
                &arts,
                &a,
                None,
                1e-3,
            )
            .unwrap();
    }
    // World 0's bodies were not hit by world 1's particles.
    assert!(a.qd.to_vec()[..18].iter().all(|&v| v == 0.0));
    let bits = |x: &[f64]| x.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.q.to_vec()[21..]), bits(&alone.aend.q.to_vec()));
    assert_eq!(bits(&a.qd.to_vec()[18..]), bits(&alone.aend.qd.to_vec()));
    let flat = |x: &Array<Vec3<f64>>| {
        x.to_vec()
            .iter()
            .flat_map(|v| [v.x, v.y, v.z])
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&flat(&s.x)), bits(&flat(&alone.end.x)));
}

#[test]
fn a_cloth_comes_to_rest_on_an_arm_and_weighs_on_it() {
    // A horizontal arm (z up) on a hinge about y at the origin, held by a PD servo, with a
    // capsule along x; a 6 x 6 cloth dropped across it.
    let mut b = ArticulationBuilder::new();
    let arm = b.add_link(
        "arm",
        None,
        Joint::revolute(Vec3::y()).pd(200.0, 5.0),
        Inertial::cuboid(1.0, Vec3::new(0.3, 0.03, 0.03), Vec3::new(0.3, 0.0, 0.0)),
    );
    b.add_contact_capsule(
        arm,
        Vec3::new(0.05, 0.0, 0.0),
        Vec3::new(0.55, 0.0, 0.0),
        0.04,
    );
    let arts = b.finalize::<f64>().unwrap();
    let mut pb = ModelBuilder::<f64>::new();
    pb.gravity = Vec3::new(0.0, 0.0, -9.81);
    pb.particle_radius = 0.01;
    let n = 6;
    let mut id = vec![vec![0u32; n]; n];
    for (i, row) in id.iter_mut().enumerate() {
        for (j, p) in row.iter_mut().enumerate() {
            let x = Vec3::new(0.15 + 0.04 * i as f64, -0.1 + 0.04 * j as f64, 0.1);
            *p = pb.add_particle(x, Vec3::zeros(), 0.01);
        }
    }
    for i in 0..n {
        for j in 0..n {
            if i + 1 < n {
                pb.add_spring(id[i][j], id[i + 1][j], 500.0, 0.5);
            }
            if j + 1 < n {
                pb.add_spring(id[i][j], id[i][j + 1], 500.0, 0.5);
            }
        }
    }
    // Air drag (time constant 0.1 s) calms the hanging edges.
    pb.set_drag(Drag::default());
    let model = pb.finalize();
    let coupling = LinkParticleContact {
        ke: 3000.0,
        kd: 1.0,
        ..Default::default()
    };
    let (mut s, mut a) = (model.state(), arts.state());
    let mut tape = Tape::new();
    for _ in 0..1500 {
        (s, a) = coupling
            .step(
                &mut tape,
                (&model, &SemiImplicitEuler),
                &s,
                None,
                &arts,
                &a,
                None,
                5e-4,
            )
            .unwrap();
        tape = Tape::new();
    }
    // The cloth lies on the capsule: no particle inside it, the middle row on top of it, slow.
    let x = s.x.to_vec();
    let v = s.v.to_vec();
    let (q, qd) = (a.q.get(0), a.qd.get(0));
    let turn = nalgebra::UnitQuaternion::from_axis_angle(&Vec3::y_axis(), q);
    for (k, p) in x.iter().enumerate() {
        let local = turn.inverse() * p;
        let along = local.x.clamp(0.05, 0.55);
        let gap = (local - Vec3::new(along, 0.0, 0.0)).norm() - 0.04 - 0.01;
        assert!(gap > -0.01, "particle {k} is {gap} m inside the arm");
    }
    let top = x.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max);
    assert!(top > 0.03 && top < 0.07, "the cloth's top at {top} m");
    assert!(v.iter().all(|v| v.norm() < 0.05), "still moving: {v:?}");
    // Its weight (36 x 0.01 kg, centred 0.25 m out) bends the servo further down than the
    // arm's own weight does (the tip down is a positive angle about y).
    let mut alone = arts.state();
    for _ in 0..1500 {
        alone = arts.step(&mut Tape::new(), &alone, None, 5e-4).unwrap();
    }
    let expected = 0.36 * 9.81 * 0.25 / 200.0;
    let extra = q - alone.q.get(0);
    println!("the cloth turns the arm by {extra:.5} rad ({expected:.5} expected), top {top:.4} m");
    assert!(
        extra > 0.7 * expected && extra < 1.3 * expected && qd.abs() < 0.05,
        "the cloth turns the arm by {extra} (about {expected} expected), speed {qd}"
    );
}

#[test]
fn applied_link_forces_move_a_free_body_as_newton_and_euler_say() {
    // A 2 kg body whose centre of mass is 0.1 m off its origin, turned, at rest.
    let mut b = ArticulationBuilder::new();
    b.gravity = Vec3::new(0.0, 0.0, -9.81);
    let turn = nalgebra::UnitQuaternion::from_axis_angle(&Vec3::x_axis(), 0.4);
    let q = turn.quaternion();
    let com = Vec3::new(0.1, 0.0, 0.0);
    let inertia = nalgebra::Matrix3::new(0.02, 0.001, 0.0, 0.001, 0.03, 0.002, 0.0, 0.002, 0.04);
    b.add_link(
        "body",
        None,
        Joint::free().initial(&[0.0, 0.0, 1.0, q.i, q.j, q.k, q.w]),
        Inertial::new(2.0, com, inertia),
    );
    let arts = b.finalize::<f64>().unwrap();
    let (f, t) = (Vec3::new(1.0, -2.0, 3.0), Vec3::new(0.3, 0.1, -0.2));
    let control = ArticulationControl {
        link_f: Some(Array::from_vec(vec![f])),
        link_t: Some(Array::from_vec(vec![t])),
        ..arts.control()
    };
    let dt = 1e-6;
    let next = arts
        .step(&mut Tape::new(), &arts.state(), Some(&control), dt)
        .unwrap();
    let qdd: Vec<f64> = next.qd.to_vec().iter().map(|v| v / dt).collect();
    // Expected: the centre of mass accelerates by f/m + g, the body turns by I_world^-1 t.
    let r = turn.to_rotation_matrix();
    let alpha_world = (r * inertia * r.transpose()).try_inverse().unwrap() * t;
    let a_com = f / 2.0 + Vec3::new(0.0, 0.0, -9.81);
    // The origin's acceleration (at rest: no centripetal term), in the link frame.
    let a_origin = r.transpose() * (a_com - alpha_world.cross(&(r * com)));
    let alpha = r.transpose() * alpha_world;
    let got = [
        Vec3::new(qdd[0], qdd[1], qdd[2]),
        Vec3::new(qdd[3], qdd[4], qdd[5]),
    ];
    assert!(
        (got[0] - a_origin).norm() < 1e-9,
        "{:?} vs {a_origin:?}",
        got[0]
    );
    assert!((got[1] - alpha).norm() < 1e-9, "{:?} vs {alpha:?}", got[1]);

    // A force of the wrong length is refused by name.
    let bad = ArticulationControl {
        link_f: Some(Array::from_vec(vec![f, f])),
        ..arts.control()
    };
    let message = arts
        .step(&mut Tape::new(), &arts.state(), Some(&bad), dt)
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(message.contains("control.link_f"), "{message}");
}

#[test]
fn mismatched_families_are_refused() {
    let arts = three_bodies().finalize::<f64>().unwrap();
    let mut pb = shot_particles();
    pb.gravity = Vec3::new(0.0, -9.81, 0.0);
    let model = pb.finalize();
    let mut b = three_bodies();
    b.gravity = Vec3::new(0.0, 0.0, -9.81);
    let falling = b.finalize::<f64>().unwrap();
    let coupling = LinkParticleContact::<f64>::default();
    let step = |arts: &Articulations<f64>, model: &Model<f64>, c: &LinkParticleContact<f64>| {
        c.step(
            &mut Tape::new(),
            (model, &SemiImplicitEuler),
            &model.state(),
            None,
            arts,
            &arts.state(),
            None,
            1e-3,
        )
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default()
    };
    // Gravity along -y for the particles but not for the links is fine without gravity on the
    // links; against z-up links it is refused.
    assert_eq!(step(&arts, &model, &coupling), "");
    let e = step(&falling, &model, &coupling);
    assert!(e.contains("gravity") && e.contains("world 0"), "{e}");
    let two = shot_particles().replicate(2).finalize();
    let e = step(&arts, &two, &coupling);
    assert!(
        e.contains("2 worlds") && e.contains("articulations 1"),
        "{e}"
    );
    let bad = LinkParticleContact {
        mu: -1.0,
        ..coupling
    };
    let e = step(&arts, &model, &bad);
    assert!(e.contains("LinkParticleContact::mu"), "{e}");
}

#[test]
fn shapes_that_touch_nothing_let_particles_through() {
    // A ball whose shape touches nothing (a visual geom, MuJoCo's contype = conaffinity = 0),
    // and the same ball touching: the particle passes through the first, bounces off the
    // second.
    let run = |filter: ContactFilter| {
        let mut b = ArticulationBuilder::new();
        b.gravity = Vec3::zeros();
        let ball = b.add_link(
            "ball",
            None,
            Joint::prismatic(Vec3::z()),
            Inertial::sphere(1.0, 0.1, Vec3::zeros()),
        );
        let s = b.add_contact_sphere(ball, Vec3::zeros(), 0.1);
        b.set_contact_filter(s, filter);
        let arts = b.finalize::<f64>().unwrap();
        let mut pb = ModelBuilder::<f64>::new();
        pb.gravity = Vec3::zeros();
        pb.add_particle(Vec3::new(0.0, 0.0, 0.2), Vec3::new(0.0, 0.0, -1.0), 0.1);
        let model = pb.finalize();
        let (mut s, mut a) = (model.state(), arts.state());
        for _ in 0..400 {
            (s, a) = LinkParticleContact::default()
                .step(
                    &mut Tape::new(),
                    (&model, &SemiImplicitEuler),
                    &s,
                    None,
                    &arts,
                    &a,
                    None,
                    1e-3,
                )
                .unwrap();
        }
        s.v.get(0).z
    };
    assert_eq!(run(ContactFilter::NONE), -1.0);
    assert!(run(ContactFilter::default()) > 0.0);
}

/// Particles hit a cylinder (the third body, along y) on its side from above and from the
/// side: momentum is kept, the cylinder moves, and `d(its z)/d(the particle from above's
/// initial vz)` agrees with central differences; an ellipsoid that would touch particles is
/// refused by name.
#[test]
fn particles_touch_cylinders_and_ellipsoids_are_refused() {
    let arts = bodies_with_rod(true).finalize::<f64>().unwrap();
    let model = shot_particles().finalize();
    let coupling = LinkParticleContact {
        ke: 2000.0,
        kd: 2.0,
        mu: 0.4,
        ..Default::default()
    };
    let roll = |dv: f64, tape: &mut Tape| {
        let mut s = model.state();
        let mut v: Vec<Vec3<f64>> = s.v.to_vec();
        v[4].z += dv;
        s.v = Array::from_vec(v).requires_grad();
        let v0 = s.v.clone();
        let mut a = arts.state();
        for _ in 0..300 {
            (s, a) = coupling
                .step(
                    tape,
                    (&model, &SemiImplicitEuler),
                    &s,
                    None,
                    &arts,
                    &a,
                    None,
                    1e-3,
                )
                .unwrap();
        }
        (v0, s, a)
    };
    let start = momentum(&model, &model.state(), &arts, &arts.state());
    let mut tape = Tape::new();
    let (v0, s, a) = roll(0.0, &mut tape);
    let end = momentum(&model, &s, &arts, &a);
    assert!(
        (end - start).norm() < 1e-9 * start.norm(),
        "momentum {start:?} -> {end:?}"
    );
    let v = world_velocity(&a.q.to_vec(), &a.qd.to_vec(), 2);
    assert!(v.x > 0.02 && v.z < -0.02, "the cylinder moves at {v:?}");
    let mut w = vec![0.0; arts.n_q];
    w[16] = 1.0;
    let g = tape.vjp(&[&a.q], &w, &[&v0]).unwrap()[3 * 4 + 2];
    let z = |dv: f64| roll(dv, &mut Tape::new()).2.q.get(16);
    let fd = (z(1e-6) - z(-1e-6)) / 2e-6;
    assert!(
        g != 0.0 && (g - fd).abs() < 1e-6 * fd.abs().max(1e-3),
        "reverse {g} vs differences {fd}"
    );

    let mut b = three_bodies();
    let egg = b.find("rod").unwrap();
    let shape =
        adflex_kernels::articulation::contact::GeomShape::Ellipsoid(Vec3::new(0.1, 0.1, 0.2));
    b.add_contact_shape(egg, &Pose::identity(), &shape);
    let arts = b.finalize::<f64>().unwrap();
    let e = coupling
        .step(
            &mut Tape::new(),
            (&model, &SemiImplicitEuler),
            &model.state(),
            None,
            &arts,
            &arts.state(),
            None,
            1e-3,
        )
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
    assert!(e.contains("ellipsoid on link \"rod\""), "{e}");
}
