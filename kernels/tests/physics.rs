//! Physics sanity of the kernels: finite derivatives at degenerate configurations, internal
//! forces that sum to zero, forces that vanish at rest and derive from their energies, energy
//! behaviour of the integrator, rigid body dynamics (the tennis racket theorem), contact, XPBD.

use crate::common;

use adflex_kernels::contact::ground::{eval_ground, Ground};
use adflex_kernels::contact::particle::{eval_particle_contact, find_pairs, ParticleContact};
use adflex_kernels::contact::shapes::{eval_shape_contact, Shape, ShapeKind};
use adflex_kernels::forces::bending::eval_bending;
use adflex_kernels::forces::fem_tet::eval_tetrahedra;
use adflex_kernels::forces::spring::eval_springs;
use adflex_kernels::prelude::*;
use adflex_kernels::scenes::cloth;
use adflex_runtime::checkpoint::checkpointed;
use adflex_runtime::prelude::*;
use common::{arr, Rng};

// ---- degenerate configurations: every derivative finite ------------------------------------

/// The value with every differentiable component 1.
fn ones<T: Value>() -> T {
    let mut one = T::zeroed();
    for k in 0..T::DIM {
        one.set_component(k, 1.0);
    }
    one
}

/// Runs a kernel forward, adjoint (all output adjoints 1) and tangent (all input tangents 1),
/// and asserts that outputs, input gradients and output tangents are finite.
macro_rules! assert_finite_derivatives {
    ($name:expr, $kernel:expr, $dim:expr, ($($arg:expr),* $(,)?), inputs = [$($i:expr),*], outputs = [$($o:expr),*]) => {{
        $( $o.fill(Value::zeroed()); )*
        launch($kernel, $dim, ($($arg,)*));
        $( assert_eq!($o.first_non_finite(), None, "{}: forward output `{}` not finite", $name, $o.label()); )*
        $( $o.ensure_grad().fill(ones()); )*
        $( $i.ensure_grad().fill(Value::zeroed()); )*
        launch_adjoint($kernel, $dim, ($($arg,)*));
        $( assert_eq!($i.grad().unwrap().first_non_finite(), None, "{}: adjoint of `{}` not finite", $name, $i.label()); )*
        $( { let t = $i.zeros_like(); t.fill(ones()); $i.set_tangent(Some(t)); } )*
        $( $o.ensure_tangent().fill(Value::zeroed()); )*
        launch_tangent($kernel, $dim, ($($arg,)*));
        $( assert_eq!($o.tangent_buffer().unwrap().first_non_finite(), None, "{}: tangent of `{}` not finite", $name, $o.label()); )*
        $( $i.set_tangent(None); )*
    }};
}

#[test]
fn flat_cloth_at_rest_has_finite_gradients_and_tangents() {
    // At t = 0 the cloth is flat (cos_theta = 1 in every bending element, the sign test 0) and
    // at rest (|vt| = 0 in the friction); springs are at rest length.
    let scene = cloth::build::<f64>(4);
    let mut tape = Tape::new();
    tape.check_finite(true);
    let (_, loss) = cloth::forward(&scene, &mut tape, 3).unwrap();
    tape.backward(&loss).unwrap();
    let g = scene.initial.v.grad().unwrap();
    assert_eq!(g.first_non_finite(), None);
    assert!(g.to_vec().iter().any(|g| g.norm() > 0.0));
    // Forward mode through the same tape.
    scene
        .initial
        .v
        .set_tangent(Some(Array::from_vec(vec![Vec3::new(0.1, -0.2, 0.3); 16])));
    tape.tangent().unwrap();
    assert_eq!(loss.tangent_buffer().unwrap().first_non_finite(), None);
    scene.initial.v.set_tangent(None);

    // The bending kernel alone on the flat, resting sheet: zero force, finite derivatives.
    let m = &scene.model;
    let b = m.bending().unwrap();
    let (x, v) = (m.particle_x.deep_clone(), m.particle_v.deep_clone());
    let f: Array<Vec3<f64>> = Array::zeros(16);
    assert_finite_derivatives!(
        "eval_bending (flat)",
        eval_bending,
        b.len(),
        (&x, &v, &b.quads, &b.rest, &b.ke, &b.kd, &f),
        inputs = [x, v],
        outputs = [f]
    );
    assert!(f.to_vec().iter().all(|f| f.norm() == 0.0));
}

#[test]
fn degenerate_elements_have_finite_derivatives() {
    // A zero-length spring.
    let x = arr(vec![Vec3::new(0.3, 0.2, 0.1); 2], "x");
    let v = arr(
        vec![Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0)],
        "v",
    );
    let pairs = arr(vec![[0u32, 1]], "pairs");
    let (rest, ke, kd) = (
        arr(vec![0.5], "rest"),
        arr(vec![10.0], "ke"),
        arr(vec![0.1], "kd"),
    );
    let f: Array<Vec3<f64>> = Array::zeros(2);
    assert_finite_derivatives!(
        "eval_springs (zero length)",
        eval_springs,
        1,
        (&x, &v, &pairs, &rest, &ke, &kd, &f),
        inputs = [x, v, rest, ke, kd],
        outputs = [f]
    );
    assert_eq!(f.get(0), Vec3::zeros());

    // A bending element with a collapsed triangle (all four points collinear).
    let x = arr((0..4).map(|k| Vec3::new(k as f64, 0.0, 0.0)).collect(), "x");
    let v = arr(vec![Vec3::new(0.0, 1.0, 0.0); 4], "v");
    let quads = arr(vec![[0u32, 1, 2, 3]], "quads");
    let (rest, bke, bkd) = (
        arr(vec![0.1], "rest"),
        arr(vec![1.0], "ke"),
        arr(vec![0.1], "kd"),
    );
    let f: Array<Vec3<f64>> = Array::zeros(4);
    assert_finite_derivatives!(
        "eval_bending (collinear)",
        eval_bending,
        1,
        (&x, &v, &quads, &rest, &bke, &bkd, &f),
        inputs = [x, v, rest, bke, bkd],
        outputs = [f]
    );

    // Ground contact with zero tangential velocity: at rest, and moving along the normal.
    let x = arr(
        vec![
            Vec3::new(0.0, -0.01, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.5, 0.01, 0.0),
        ],
        "x",
    );
    let up = Vec3::new(0.0, 1.0, 0.0);
    for vel in [Vec3::zeros(), Vec3::new(0.0, -0.5, 0.0)] {
        let v = arr(vec![vel; 3], "v");
        let f: Array<Vec3<f64>> = Array::zeros(3);
        assert_finite_derivatives!(
            "eval_ground (vt = 0)",
            eval_ground,
            3,
            (&x, &v, up, 0.0, 0.01, 1000.0, 1.0, 1.0, 0.0, 0.5, 0.0, &f),
            inputs = [x, v],
            outputs = [f]
        );
    }

    // Two coincident particles in contact.
    let x = arr(vec![Vec3::new(0.2, 0.2, 0.2); 2], "x");
    let v = arr(vec![Vec3::zeros(); 2], "v");
    let f: Array<Vec3<f64>> = Array::zeros(2);
    assert_finite_derivatives!(
        "eval_particle_contact (coincident)",
        eval_particle_contact,
        1,
        (&x, &v, &pairs, 0.1, 1000.0, 1.0, 1e-4, 0.5, 0.0, &f),
        inputs = [x, v],
        outputs = [f]
    );

    // A particle at the centre of a sphere, on the axis of a capsule, at the centre of a box.
    let kind = arr(vec![0u32, 1, 2], "kind");
    let pos = arr(vec![Vec3::zeros(); 3], "pos");
    let rot = arr(vec![Quat::identity(); 3], "rot");
    let size = arr(
        vec![
            Vec3::new(0.5, 0.0, 0.0),
            Vec3::new(0.3, 0.3, 0.3),
            Vec3::new(0.2, 0.4, 0.0),
        ],
        "size",
    );
    let x = arr(vec![Vec3::zeros()], "x");
    let v = arr(vec![Vec3::zeros()], "v");
    let f: Array<Vec3<f64>> = Array::zeros(1);
    assert_finite_derivatives!(
        "eval_shape_contact (centre)",
        eval_shape_contact,
        3,
        (&x, &v, &kind, &pos, &rot, &size, 3usize, 0.01, 1000.0, 1.0, 1e-4, 0.5, 0.0, &f),
        inputs = [x, v, pos, rot, size],
        outputs = [f]
    );

    // An inverted tetrahedron (J < 0) and a flat one (J = 0).
    let mut b = ModelBuilder::<f64>::new();
    for p in [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ] {
        b.add_particle(Vec3::new(p[0], p[1], p[2]), Vec3::zeros(), 1.0);
    }
    b.add_tet(0, 1, 2, 3, 100.0, 300.0, 1.0);
    let m = b.finalize();
    let t = m.tets().unwrap();
    for z in [-0.5, 0.0] {
        let x = arr(
            vec![
                Vec3::zeros(),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
                Vec3::new(0.0, 0.0, z),
            ],
            "x",
        );
        let v = arr(vec![Vec3::zeros(); 4], "v");
        let f: Array<Vec3<f64>> = Array::zeros(4);
        assert_finite_derivatives!(
            "eval_tetrahedra (inverted)",
            eval_tetrahedra,
            1,
            (
                &x,
                &v,
                &t.tets,
                &t.dm_inv,
                &t.rest_volume,
                &t.mu,
                &t.lambda,
                &t.kd,
                &t.activation,
                &f
            ),
            inputs = [x, v],
            outputs = [f]
        );
    }
}

// ---- internal forces: zero sum, zero torque, zero at rest, minus the energy gradient ------

/// A scene with springs, bending, membranes and tetrahedra on a bumpy 3x3x2 block.
fn solid(r: &mut Rng) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..2 {
                b.add_particle(
                    Vec3::new(i as f64, k as f64, j as f64) * 0.5 + r.vec3(-0.1, 0.1),
                    Vec3::zeros(),
                    1.0,
                );
            }
        }
    }
    let id = |i: u32, j: u32, k: u32| (i * 3 + j) * 2 + k;
    let mut tris = Vec::new();
    for i in 0..2 {
        for j in 0..2 {
            let (a, bb, c, d) = (
                id(i, j, 1),
                id(i + 1, j, 1),
                id(i + 1, j + 1, 1),
                id(i, j + 1, 1),
            );
            tris.push([a, bb, c]);
            tris.push([a, c, d]);
            b.add_spring(a, c, 40.0, 0.5);
            b.add_spring(bb, d, 30.0, 0.2);
            // Two tetrahedra per column cell.
            b.add_tet(
                id(i, j, 0),
                id(i + 1, j, 0),
                id(i, j + 1, 0),
                a,
                100.0,
                400.0,
                0.5,
            );
            b.add_tet(
                id(i + 1, j + 1, 0),
                id(i + 1, j, 0),
                id(i, j + 1, 0),
                c,
                80.0,
                300.0,
                0.5,
            );
        }
    }
    for t in &tris {
        b.add_triangle_fem(t[0], t[1], t[2], 50.0, 20.0, 0.3);
    }
    b.add_bending_edges(0.5, 0.05, RestAngle::Initial);
    b.gravity = Vec3::zeros();
    b.finalize()
}

/// Each internal force component of `m` alone at state `s`: (name, force array).
fn component_forces(m: &Model<f64>, s: &State<f64>) -> Vec<(&'static str, Vec<Vec3<f64>>)> {
    let mut out = Vec::new();
    let n = m.particle_count;
    let mut tape = Tape::new();
    let mut one = |name, run: &dyn Fn(&mut Tape, &Array<Vec3<f64>>)| {
        let f = Array::zeros(n);
        run(&mut tape, &f);
        out.push((name, f.to_vec()));
    };
    one("springs", &|t, f| {
        m.springs().unwrap().eval(t, &s.x, &s.v, f)
    });
    one("bending", &|t, f| {
        m.bending().unwrap().eval(t, &s.x, &s.v, f)
    });
    one("triangles", &|t, f| {
        m.tri_fem().unwrap().eval(t, &s.x, &s.v, f)
    });
    one("tetrahedra", &|t, f| {
        m.tets().unwrap().eval(t, &s.x, &s.v, None, f)
    });
    out
}

fn deformed(m: &Model<f64>, r: &mut Rng, vel: f64) -> State<f64> {
    let s = m.state();
    s.x.assign(
        &s.x.to_vec()
            .iter()
            .map(|p| p + r.vec3(-0.08, 0.08))
            .collect::<Vec<_>>(),
    );
    s.v.assign(&r.vec3s(m.particle_count, -vel, vel));
    s
}

#[test]
fn internal_forces_sum_to_zero_and_exert_no_torque() {
    let mut r = Rng(31);
    let m = solid(&mut r);
    // With velocities (damping included): the net force vanishes.
    let s = deformed(&m, &mut r, 1.0);
    for (name, f) in component_forces(&m, &s) {
        let scale = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
        let net: Vec3<f64> = f.iter().sum();
        assert!(scale > 0.0, "{name}: no force");
        assert!(
            net.norm() < 1e-12 * scale,
            "{name}: net force {net:?} (scale {scale})"
        );
    }
    // Elastic forces alone (v = 0): the net torque vanishes too (rotation invariant energies).
    let s = deformed(&m, &mut r, 0.0);
    let x = s.x.to_vec();
    for (name, f) in component_forces(&m, &s) {
        let scale = f
            .iter()
            .zip(&x)
            .map(|(f, x)| f.norm() * x.norm())
            .fold(0.0, f64::max);
        let torque: Vec3<f64> = f.iter().zip(&x).map(|(f, x)| x.cross(f)).sum();
        assert!(
            torque.norm() < 1e-12 * scale,
            "{name}: net torque {torque:?} (scale {scale})"
        );
    }
}

#[test]
fn forces_vanish_at_rest() {
    let mut r = Rng(32);
    let m = solid(&mut r);
    // The rest shape: springs at rest length, membranes and tetrahedra undeformed, bending at
    // its initial angle; no velocity.
    for (name, f) in component_forces(&m, &m.state()) {
        let worst = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
        assert!(worst < 1e-10, "{name}: force {worst} at rest");
    }
    // ... and after a rigid motion (rotation + translation) of the rest shape.
    let s = m.state();
    let q = r.quat();
    let rot = nalgebra::UnitQuaternion::from_quaternion(q);
    s.x.assign(
        &s.x.to_vec()
            .iter()
            .map(|p| rot * p + Vec3::new(1.0, 2.0, 3.0))
            .collect::<Vec<_>>(),
    );
    for (name, f) in component_forces(&m, &s) {
        let worst = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
        assert!(worst < 1e-9, "{name}: force {worst} after a rigid motion");
    }
}

#[test]
fn elastic_forces_are_minus_the_energy_gradient() {
    let mut r = Rng(33);
    let m = solid(&mut r);
    let s = deformed(&m, &mut r, 0.0);
    // Energy gradient by the adjoint of the energy kernels.
    let x = s.x.clone().requires_grad();
    let mut tape = Tape::new();
    let e = m.elastic_energy(&mut tape, &s, None);
    tape.backward(&e).unwrap();
    let grad = x.grad().unwrap().to_vec();
    let mut f = vec![Vec3::zeros(); m.particle_count];
    for (_, fc) in component_forces(&m, &s) {
        f.iter_mut().zip(&fc).for_each(|(a, b)| *a += b);
    }
    // Bending's force leaves out the variation of the edge length in its energy
    // `ke/2 |e| (angle - rest)^2`: add `ke/2 (angle - rest)^2 d|e|/dx` back.
    let bending = m.bending().unwrap();
    let xs = s.x.to_vec();
    let (quads, rest, ke) = (
        bending.quads.to_vec(),
        bending.rest.to_vec(),
        bending.ke.to_vec(),
    );
    for (q, (rest, ke)) in quads.iter().zip(rest.iter().zip(&ke)) {
        let c = adflex_kernels::forces::bending::dihedral_angle(&xs, *q) - rest;
        let e_hat = (xs[q[3] as usize] - xs[q[2] as usize]).normalize();
        f[q[3] as usize] -= e_hat * (0.5 * ke * c * c);
        f[q[2] as usize] += e_hat * (0.5 * ke * c * c);
    }
    let scale = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
    for (k, (g, f)) in grad.iter().zip(&f).enumerate() {
        assert!(
            (g + f).norm() < 1e-10 * scale,
            "particle {k}: -dE/dx {:?} vs force {f:?}",
            -g
        );
    }
}

/// Each contact force at rest (`v = 0`: no damping, no friction) is minus the gradient of its
/// own energy (`Force::energy`, which `ImplicitEuler`'s line search uses): ground, particle
/// pairs and shapes, with penetrating and separated particles, uniform and per-particle radii.
#[test]
fn contact_forces_at_rest_are_minus_their_energy_gradient() {
    for radii in [false, true] {
        let mut r = Rng(if radii { 35 } else { 34 });
        let mut b = ModelBuilder::<f64>::new();
        for _ in 0..40 {
            let i = b.add_particle(
                r.vec3(-0.5, 0.5) + Vec3::new(0.0, 0.3, 0.0),
                Vec3::zeros(),
                1.0,
            );
            if radii {
                b.set_particle_radius(i, r.uniform(0.05, 0.2));
            }
        }
        b.particle_radius = 0.15;
        b.set_ground(Ground {
            ke: 2000.0,
            ..Ground::default()
        });
        b.set_particle_contact(ParticleContact {
            ke: 700.0,
            ..ParticleContact::default()
        });
        b.add_shape(Shape::new(
            ShapeKind::Sphere { radius: 0.3 },
            Vec3::new(0.2, 0.4, 0.0),
        ));
        let mut bx = Shape::new(
            ShapeKind::Box {
                half_extents: Vec3::new(0.2, 0.1, 0.3),
            },
            Vec3::new(-0.2, 0.2, 0.1),
        );
        bx.rot = nalgebra::UnitQuaternion::from_euler_angles(0.3, -0.2, 0.5).into_inner();
        b.add_shape(bx);
        b.add_shape(Shape::new(
            ShapeKind::Capsule {
                radius: 0.1,
                half_length: 0.3,
            },
            Vec3::new(0.0, 0.6, -0.2),
        ));
        b.set_shape_contact(ParticleContact {
            ke: 1500.0,
            ..ParticleContact::default()
        });
        let m = b.finalize();
        let s = m.state();
        let x = s.x.clone().requires_grad();
        let mut touching = 0;
        for force in &m.forces {
            let cx = m.context(&s, None);
            let (mut tape, e) = (Tape::new(), Array::<f64>::zeros(1));
            assert!(
                force.energy(&cx, &mut tape, &e),
                "{}: no energy",
                force.name()
            );
            x.zero_grad();
            tape.backward(&e).unwrap();
            let g = x.grad().unwrap().to_vec();
            let f = Array::zeros(m.particle_count);
            force.eval(&cx, &mut Tape::new(), &f);
            let f = f.to_vec();
            let scale = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
            assert!(scale > 1.0, "{}: no particle in contact", force.name());
            touching += 1;
            for (k, (g, f)) in g.iter().zip(&f).enumerate() {
                assert!(
                    (g + f).norm() <= 1e-12 * scale,
                    "{} (radii {radii}) particle {k}: -dE/dx {:?} vs force {f:?}",
                    force.name(),
                    -g
                );
            }
        }
        assert_eq!(touching, 3);
    }
}

// ---- integrator energy, pinned particles, what a scene launches ---------------------------

#[test]
fn undamped_spring_energy_stays_bounded_under_semi_implicit_euler() {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    let p = b.add_particle(Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.0, 0.3, 0.0), 1.0);
    let q = b.add_particle(Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, -0.3, 0.1), 2.0);
    b.add_spring_with_rest(p, q, 0.8, 100.0, 0.0);
    let m = b.finalize();
    let energy = |s: &State<f64>| {
        let (x, v) = (s.x.to_vec(), s.v.to_vec());
        let ke = 0.5 * v[0].norm_squared() + 0.5 * 2.0 * v[1].norm_squared();
        let c = (x[0] - x[1]).norm() - 0.8;
        ke + 0.5 * 100.0 * c * c
    };
    let mut s = m.state();
    let e0 = energy(&s);
    let (mut lo, mut hi) = (e0, e0);
    for _ in 0..20000 {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, 1e-3)
            .unwrap();
        let e = energy(&s);
        lo = lo.min(e);
        hi = hi.max(e);
    }
    // Symplectic: the energy oscillates by O(dt) around its initial value, with no drift.
    assert!(
        (hi - lo) / e0 < 0.02,
        "energy in [{lo}, {hi}], initial {e0}"
    );
    assert!((energy(&s) - e0).abs() / e0 < 0.02);
}

#[test]
fn pinned_particles_stay_put_and_a_scene_launches_only_what_it_has() {
    let scene = cloth::build::<f32>(8);
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .step(&scene.model, &mut tape, &scene.initial, None, 1e-3)
        .unwrap();
    // springs, bending, ground, integrate: nothing else.
    assert_eq!(tape.len(), 4, "{tape:?}");
    let (x0, x1) = (scene.initial.x.to_vec(), s.x.to_vec());
    assert_eq!(x0[0], x1[0]);
    assert_eq!(x0[7 * 8], x1[7 * 8]);
    assert!(x1[5].y < x0[5].y);
    // Free particles only: one launch (the integrator) per step.
    let mut b = ModelBuilder::<f32>::new();
    b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
    let m = b.finalize();
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .step(&m, &mut tape, &m.state(), None, 0.1)
        .unwrap();
    assert_eq!(tape.len(), 1);
    assert!((s.v.get(0).y + 0.98).abs() < 1e-6);
}

#[test]
fn checkpointed_cloth_gradients_equal_the_plain_tape() {
    let scene = cloth::build::<f64>(5);
    let plain = cloth::rollout(&scene, 20, true).unwrap();
    scene.initial.v.zero_grad();
    scene.model.springs().unwrap().ke.zero_grad();
    let m = &scene.model;
    let x0 = scene.initial.x.clone();
    let out = checkpointed(
        &scene.initial,
        20,
        6,
        |tape, s| SemiImplicitEuler.step(m, tape, s, None, 1e-3),
        |tape, s| {
            let loss = Array::zeros(1);
            tape.launch(
                cloth::displacement_loss,
                25,
                (&s.x, &x0, Vec3::new(0.0, -0.1, 0.0), 1.0 / 25.0, &loss),
            );
            Ok(loss)
        },
    )
    .unwrap();
    assert_eq!(out.loss.get(0), plain.loss);
    assert_eq!(scene.initial.v.grad().unwrap().to_vec(), plain.grad_v0);
    assert_eq!(
        scene.model.springs().unwrap().ke.grad().unwrap().to_vec(),
        plain.grad_ke
    );
}

// ---- contact ------------------------------------------------------------------------------

#[test]
fn leaky_ground_gradient_reaches_particles_above_the_ground() {
    let x = arr(
        vec![Vec3::new(0.0, 0.5, 0.0), Vec3::new(0.0, -0.02, 0.0)],
        "x",
    );
    let v = arr(vec![Vec3::zeros(); 2], "v");
    let f: Array<Vec3<f64>> = Array::zeros(2);
    let up = Vec3::new(0.0, 1.0, 0.0);
    for leak in [0.0, 0.1] {
        f.fill(Vec3::zeros());
        launch(
            eval_ground,
            2,
            (&x, &v, up, 0.0, 0.01, 1000.0, 1.0, 1.0, 0.0, 0.5, leak, &f),
        );
        // The forward force is the same with or without leak.
        assert_eq!(f.get(0), Vec3::zeros());
        assert!((f.get(1).y - 30.0).abs() < 1e-9);
        f.ensure_grad().fill(Vec3::new(0.0, 1.0, 0.0));
        x.ensure_grad().fill(Vec3::zeros());
        v.ensure_grad().fill(Vec3::zeros());
        launch_adjoint(
            eval_ground,
            2,
            (&x, &v, up, 0.0, 0.01, 1000.0, 1.0, 1.0, 0.0, 0.5, leak, &f),
        );
        let g = x.grad().unwrap().to_vec();
        // d f_y / d y = -ke * slope: slope 1 in contact, `leak` above the ground.
        assert!((g[1].y + 1000.0).abs() < 1e-9);
        assert!(
            (g[0].y + 1000.0 * leak).abs() < 1e-9,
            "leak {leak}: {:?}",
            g[0]
        );
    }
}

#[test]
fn grid_broad_phase_finds_exactly_the_close_pairs() {
    let mut r = Rng(41);
    let xs: Vec<Vec3<f64>> = r.vec3s(600, -1.0, 1.0);
    let cutoff = 0.15;
    let mut brute = Vec::new();
    for i in 0..xs.len() {
        for j in i + 1..xs.len() {
            if (xs[i] - xs[j]).norm() < cutoff {
                brute.push([i as u32, j as u32]);
            }
        }
    }
    assert!(brute.len() > 50);
    assert_eq!(find_pairs(&xs, cutoff), brute);
}

#[test]
fn particles_pile_up_without_interpenetrating() {
    // A 2x2x3 block of particles dropped onto the ground: they scatter and settle, and
    // contact keeps them apart all along.
    let mut r = Rng(42);
    let mut b = ModelBuilder::<f64>::new();
    b.particle_radius = 0.05;
    for i in 0..2 {
        for j in 0..2 {
            for k in 0..3 {
                let p = Vec3::new(i as f64 * 0.11, 0.1 + k as f64 * 0.11, j as f64 * 0.11)
                    + r.vec3(-0.004, 0.004);
                b.add_particle(p, Vec3::zeros(), 0.01);
            }
        }
    }
    b.set_ground(Ground {
        ke: 1000.0,
        kd: 0.05,
        mu: 0.5,
        ..Ground::default()
    });
    b.set_particle_contact(ParticleContact {
        ke: 2000.0,
        kd: 0.5,
        mu: 0.5,
        ..ParticleContact::default()
    });
    let m = b.finalize();
    let mut s = m.state();
    let mut closest = f64::INFINITY;
    for _ in 0..4000 {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, 5e-4)
            .unwrap();
        let x = s.x.to_vec();
        for i in 0..x.len() {
            for j in i + 1..x.len() {
                closest = closest.min((x[i] - x[j]).norm());
            }
        }
    }
    // Overlap at most a few millimetres (the weight of the block over the contact stiffness).
    assert!(
        closest > 0.095,
        "two particles came {closest} m close (diameter 0.1)"
    );
    let x = s.x.to_vec();
    assert!(x.iter().all(|p| p.y > 0.045 && p.y < 0.3), "{x:?}");
}

#[test]
fn particles_come_to_rest_on_shapes() {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::new(0.0, -9.8, 0.0);
    b.particle_radius = 0.02;
    b.add_particle(Vec3::new(0.0, 0.7, 0.0), Vec3::zeros(), 0.01); // onto the sphere's top
    b.add_particle(Vec3::new(2.0, 0.5, 0.1), Vec3::zeros(), 0.01); // onto the box's top face
    b.add_particle(Vec3::new(-2.2, 0.5, 0.0), Vec3::zeros(), 0.01); // onto the capsule
    b.add_shape(Shape::new(ShapeKind::Sphere { radius: 0.5 }, Vec3::zeros()));
    b.add_shape(Shape::new(
        ShapeKind::Box {
            half_extents: Vec3::new(0.4, 0.3, 0.2),
        },
        Vec3::new(2.0, 0.0, 0.0),
    ));
    b.add_shape(Shape::new(
        ShapeKind::Capsule {
            radius: 0.3,
            half_length: 0.4,
        },
        Vec3::new(-2.0, 0.0, 0.0),
    ));
    b.set_shape_contact(ParticleContact {
        ke: 1000.0,
        kd: 2.0,
        mu: 1.0,
        ..ParticleContact::default()
    });
    let m = b.finalize();
    let mut s = m.state();
    for _ in 0..6000 {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, 5e-4)
            .unwrap();
    }
    let x = s.x.to_vec();
    let v = s.v.to_vec();
    // Resting on the surface, sunk by about m g / ke = 1e-4 m.
    assert!((x[0].y - 0.52).abs() < 2e-3, "{:?}", x[0]);
    assert!((x[1].y - 0.32).abs() < 2e-3, "{:?}", x[1]);
    assert!((x[2].y - 0.32).abs() < 2e-3, "{:?}", x[2]);
    assert!(v.iter().all(|v| v.norm() < 1e-2), "{v:?}");
}

// ---- rigid bodies -------------------------------------------------------------------------

fn body_angular_velocity(s: &BodyState<f64>) -> Vec3<f64> {
    let q = nalgebra::UnitQuaternion::from_quaternion(s.q.get(0));
    q.inverse() * s.w.get(0)
}

fn spin(wb: Vec3<f64>, steps: usize, dt: f64) -> (Vec<Vec3<f64>>, f64) {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    let inertia = Mat33::from_diagonal(&Vec3::new(1.0, 2.0, 3.0));
    b.add_body(
        Vec3::zeros(),
        Quat::identity(),
        Vec3::zeros(),
        wb,
        1.0,
        inertia,
    );
    let m = b.finalize();
    let mut s = m.state();
    let mut hist = Vec::new();
    let mut qnorm_err: f64 = 0.0;
    for _ in 0..steps {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, dt)
            .unwrap();
        let bs = s.bodies.as_ref().unwrap();
        qnorm_err = qnorm_err.max((bs.q.get(0).norm() - 1.0).abs());
        hist.push(body_angular_velocity(bs));
    }
    (hist, qnorm_err)
}

#[test]
fn tennis_racket_theorem() {
    // Inertia (1, 2, 3). Spinning about the intermediate axis (y) with a small perturbation,
    // the body flips: w_y changes sign. About the largest (z) or smallest (x) axis it is stable.
    let (mid, qerr) = spin(Vec3::new(0.01, 1.0, 0.01), 10000, 2e-3);
    assert!(qerr < 1e-12, "quaternion norm drifts by {qerr}");
    let min_wy = mid.iter().map(|w| w.y).fold(f64::INFINITY, f64::min);
    assert!(
        min_wy < -0.9,
        "no flip about the intermediate axis: min w_y = {min_wy}"
    );
    let (major, _) = spin(Vec3::new(0.01, 0.01, 1.0), 10000, 2e-3);
    assert!(
        major.iter().all(|w| w.z > 0.99),
        "rotation about the major axis is not stable"
    );
    let (minor, _) = spin(Vec3::new(1.0, 0.01, 0.01), 10000, 2e-3);
    assert!(
        minor.iter().all(|w| w.x > 0.99),
        "rotation about the minor axis is not stable"
    );
    // Kinetic energy w.I w / 2 stays close to its initial value through the flip.
    let e = |w: &Vec3<f64>| 0.5 * (w.x * w.x + 2.0 * w.y * w.y + 3.0 * w.z * w.z);
    let e0 = e(&Vec3::new(0.01, 1.0, 0.01));
    assert!(mid.iter().all(|w| (e(w) - e0).abs() / e0 < 0.05));
}

#[test]
fn a_box_falls_and_rests_on_the_ground() {
    let mut b = ModelBuilder::<f64>::new();
    let h = Vec3::new(0.2, 0.1, 0.15);
    let mass = 1.0;
    let inertia = Mat33::from_diagonal(&Vec3::new(
        h.y * h.y + h.z * h.z,
        h.x * h.x + h.z * h.z,
        h.x * h.x + h.y * h.y,
    )) * (mass / 3.0);
    let q = Quat::from_polar_decomposition(
        1.0,
        0.3,
        nalgebra::Unit::new_normalize(Vec3::new(1.0, 0.0, 1.0)),
    );
    let body = b.add_body(
        Vec3::new(0.0, 0.5, 0.0),
        q,
        Vec3::zeros(),
        Vec3::new(0.0, 1.0, 0.0),
        mass,
        inertia,
    );
    for sx in [-1.0, 1.0] {
        for sy in [-1.0, 1.0] {
            for sz in [-1.0, 1.0] {
                b.add_body_contact_point(body, Vec3::new(sx * h.x, sy * h.y, sz * h.z));
            }
        }
    }
    b.set_ground(Ground {
        ke: 2e4,
        kd: 200.0,
        mu: 0.8,
        ..Ground::default()
    });
    let m = b.finalize();
    let mut s = m.state();
    for _ in 0..6000 {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, 5e-4)
            .unwrap();
    }
    let bs = s.bodies.as_ref().unwrap();
    // Resting on its largest face: centre at the half height 0.1 (sunk by m g / (4 ke)).
    let y = bs.x.get(0).y;
    assert!((y - 0.1).abs() < 5e-3, "rest height {y}");
    assert!(
        bs.v.get(0).norm() < 0.05 && bs.w.get(0).norm() < 0.2,
        "not at rest: v {:?} w {:?}",
        bs.v.get(0),
        bs.w.get(0)
    );
}

// ---- XPBD --------------------------------------------------------------------------------

#[test]
fn xpbd_rigid_constraints_converge_and_compliant_ones_balance() {
    let mut b = ModelBuilder::<f64>::new();
    let mut r = Rng(51);
    for k in 0..5 {
        b.add_particle(
            Vec3::new(k as f64 * 0.3, 0.0, 0.0),
            Vec3::zeros(),
            if k == 0 { 0.0 } else { 1.0 },
        );
    }
    for k in 0..4 {
        b.add_distance_constraint(k, k + 1, 0.0);
    }
    let m = b.finalize();
    let dc = m.distance_constraints.as_ref().unwrap();
    let x: Array<Vec3<f64>> = Array::from_vec(
        m.particle_x
            .to_vec()
            .iter()
            .map(|p| p + r.vec3(-0.05, 0.05))
            .collect(),
    );
    let mut tape = Tape::new();
    let (mut xk, mut lam) = (x.clone(), dc.zero_lambda());
    for _ in 0..200 {
        (xk, lam) = dc.iterate(&mut tape, &xk, &m.particle_inv_mass, &lam, 1e-2, 1.0);
    }
    let p = xk.to_vec();
    for k in 0..4 {
        assert!(
            ((p[k] - p[k + 1]).norm() - 0.3).abs() < 1e-6,
            "constraint {k}: {}",
            (p[k] - p[k + 1]).norm()
        );
    }
    assert_eq!(p[0], x.get(0), "the pinned particle moved");
    // Differentiable: gradient of the final position w.r.t. the starting one is finite.
    let l = Array::zeros(1);
    tape.launch(
        cloth::displacement_loss,
        5,
        (&xk, &x, Vec3::zeros(), 1.0, &l),
    );
    let x_req = x.clone().requires_grad();
    tape.backward(&l).unwrap();
    assert_eq!(x_req.grad().unwrap().first_non_finite(), None);

    // A compliant constraint converges to C = -alpha lambda / dt^2 (stretched, not rigid).
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0);
    b.add_particle(Vec3::new(0.5, 0.0, 0.0), Vec3::zeros(), 1.0);
    let (alpha, dt) = (1e-4, 1e-2);
    b.add_distance_constraint(0, 1, alpha);
    let m = b.finalize();
    let dc = m.distance_constraints.as_ref().unwrap();
    let mut xk: Array<Vec3<f64>> = Array::from_vec(vec![Vec3::zeros(), Vec3::new(0.7, 0.0, 0.0)]);
    let mut lam = dc.zero_lambda();
    let mut tape = Tape::new();
    for _ in 0..100 {
        (xk, lam) = dc.iterate(&mut tape, &xk, &m.particle_inv_mass, &lam, dt, 1.0);
    }
    let c = (xk.get(0) - xk.get(1)).norm() - 0.5;
    assert!(
        c > 0.01,
        "a compliant constraint should stay stretched: C = {c}"
    );
    assert!(
        (c + alpha / (dt * dt) * lam.get(0)).abs() < 1e-9,
        "C = {c}, lambda = {}",
        lam.get(0)
    );
}
