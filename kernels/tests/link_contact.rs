//! Contact between the links of articulations: the closest-point rules against dense
//! sampling, collisions of capsules, spheres and boxes (momentum, resting heights, a capsule
//! resting level on a box's face, across a beam and over an edge) with
//! rollout gradients against central differences and forward mode against reverse mode, and
//! MuJoCo's contact filters read from MJCF.

use adflex_kernels::articulation::contact::{
    capsule_box_point, closest_on_segment_to_box, closest_on_segments, segment_box_contact,
    GeomShape,
};
use adflex_kernels::articulation::{
    mjcf, ArticulationBuilder, ArticulationState, Articulations, ContactFilter, GroundContact,
    Inertial, Joint, Pose,
};
use adflex_runtime::{Array, Quat, Tape, Vec3};
use adflex_testkit::Rng;

fn rand3(rng: &mut Rng, s: f64) -> Vec3<f64> {
    Vec3::new(rng.uniform(-s, s), rng.uniform(-s, s), rng.uniform(-s, s))
}

/// The distance from `p` to the box of half extents `h` at the origin (0 inside).
fn box_distance(p: &Vec3<f64>, h: &Vec3<f64>) -> f64 {
    let q = Vec3::new(
        p.x.clamp(-h.x, h.x),
        p.y.clamp(-h.y, h.y),
        p.z.clamp(-h.z, h.z),
    );
    (p - q).norm()
}

#[test]
fn closest_points_match_dense_sampling() {
    let mut rng = Rng(17);
    let n = 4000;
    for case in 0..200 {
        let (a0, b0) = (rand3(&mut rng, 1.0), rand3(&mut rng, 1.0));
        // Some sphere-like (zero-length) and parallel segments too.
        let a1 = if case % 10 == 0 {
            a0
        } else {
            a0 + rand3(&mut rng, 1.0)
        };
        let b1 = match case % 7 {
            0 => b0 + (a1 - a0) * 0.7,
            _ => b0 + rand3(&mut rng, 1.0),
        };
        let st = closest_on_segments::call(a0, a1, b0, b1);
        let found = ((a0 + (a1 - a0) * st.x) - (b0 + (b1 - b0) * st.y)).norm();
        let mut best = f64::INFINITY;
        for i in 0..=n {
            let p = a0 + (a1 - a0) * (i as f64 / n as f64);
            // The closest point of segment b to p, exactly.
            let d = b1 - b0;
            let t = if d.norm_squared() > 0.0 {
                ((p - b0).dot(&d) / d.norm_squared()).clamp(0.0, 1.0)
            } else {
                0.0
            };
            best = best.min((p - (b0 + d * t)).norm());
        }
        assert!(
            found <= best + 1e-9 && found >= best - 2.0 / n as f64,
            "segments {case}: {found} vs sampled {best}"
        );

        // A segment and a box.
        let half = Vec3::new(
            rng.uniform(0.1, 0.5),
            rng.uniform(0.1, 0.5),
            rng.uniform(0.1, 0.5),
        );
        let (p0, d) = (rand3(&mut rng, 1.5), rand3(&mut rng, 1.5));
        let range = closest_on_segment_to_box(p0, d, half);
        let s = 0.5 * (range.x + range.y);
        let found = box_distance(&(p0 + d * s), &half);
        let best = (0..=n)
            .map(|i| box_distance(&(p0 + d * (i as f64 / n as f64)), &half))
            .fold(f64::INFINITY, f64::min);
        assert!(
            found <= best + 1e-9,
            "segment and box {case}: {found} vs sampled {best}"
        );
        // The contact's signed distance: the distance minus the radius outside; inside, minus
        // the depth to the nearest face.
        let m = segment_box_contact::call(p0, d, 0.05, half, range);
        let (at, normal, dist) = (
            m.column(0).into_owned(),
            m.column(1).into_owned(),
            m[(0, 2)],
        );
        let p = p0 + d * s;
        if found > 0.0 {
            assert!(
                (dist - (found - 0.05)).abs() < 1e-9,
                "{case}: {dist} vs {found}"
            );
            // Midway between the box's surface and the capsule's.
            let surface = p - normal * 0.05;
            assert!((box_distance(&(at - normal * (0.5 * dist)), &half)).abs() < 1e-9);
            assert!(
                (at - (surface - normal * (0.5 * dist))).norm() < 1e-9,
                "{case}"
            );
        } else {
            let gap = (half - p.abs()).min();
            assert!(
                (dist + gap + 0.05).abs() < 1e-9,
                "{case}: {dist} vs depth {gap}"
            );
        }
    }
}

#[test]
fn contact_rules_derivatives_match_differences_and_forward_mode() {
    use adflex_runtime::DiffFunc;
    let mut rng = Rng(4);
    let mut bad = Vec::new();
    let mut fading = 0;
    for case in 0..200 {
        let a0 = rand3(&mut rng, 1.0);
        let a1 = a0 + rand3(&mut rng, 1.0);
        let b0 = rand3(&mut rng, 1.0);
        let b1 = b0 + rand3(&mut rng, 1.0);
        let w = Vec3::new(0.0, 0.0, 0.0) + rand3(&mut rng, 1.0);
        // f = w . (closest point on a - closest point on b), a smooth function of the ends
        // away from the clamps' switches.
        let f = |a0: Vec3<f64>, a1: Vec3<f64>, b0: Vec3<f64>, b1: Vec3<f64>| {
            let st = closest_on_segments::call(a0, a1, b0, b1);
            w.dot(&((a0 + (a1 - a0) * st.x) - (b0 + (b1 - b0) * st.y)))
        };
        let da = [rand3(&mut rng, 1.0), rand3(&mut rng, 1.0)];
        let db = [rand3(&mut rng, 1.0), rand3(&mut rng, 1.0)];
        let h = 1e-6;
        let fd = (f(
            a0 + da[0] * h,
            a1 + da[1] * h,
            b0 + db[0] * h,
            b1 + db[1] * h,
        ) - f(
            a0 - da[0] * h,
            a1 - da[1] * h,
            b0 - db[0] * h,
            b1 - db[1] * h,
        )) / (2.0 * h);
        let st = closest_on_segments::call(a0, a1, b0, b1);
        // The derivative through the chain rule: the seeds on (s, t) come from the points.
        let seed = adflex_runtime::Vec2::new(w.dot(&(a1 - a0)), -w.dot(&(b1 - b0)));
        let (ga0, ga1, gb0, gb1) = DiffFunc::adjoint(&closest_on_segments, (a0, a1, b0, b1), seed);
        let direct = w.dot(&(da[0] * (1.0 - st.x) + da[1] * st.x))
            - w.dot(&(db[0] * (1.0 - st.y) + db[1] * st.y));
        let reverse =
            direct + ga0.dot(&da[0]) + ga1.dot(&da[1]) + gb0.dot(&db[0]) + gb1.dot(&db[1]);
        if (reverse - fd).abs() > 1e-6 * fd.abs().max(1.0) {
            bad.push(format!(
                "segments {case}: reverse {reverse} vs differences {fd} st {st:?}"
            ));
        }
        let (_, tangent) = DiffFunc::tangent(
            &closest_on_segments,
            (a0, a1, b0, b1),
            (da[0], da[1], db[0], db[1]),
        );
        let forward = direct + seed.dot(&tangent);
        assert!(
            (forward - reverse).abs() < 1e-10 * reverse.abs().max(1.0),
            "segments {case}: forward {forward} vs reverse {reverse}"
        );

        // The box rule: w . (contact point) + distance.
        let half = Vec3::new(0.3, 0.2, 0.4);
        let (p0, d) = (rand3(&mut rng, 1.2), rand3(&mut rng, 1.2));
        let g = |p0: Vec3<f64>, d: Vec3<f64>| {
            let range = closest_on_segment_to_box(p0, d, half);
            let m = segment_box_contact::call(p0, d, 0.05, half, range);
            w.dot(&m.column(0).into_owned()) + m[(0, 2)] + w.dot(&m.column(1).into_owned())
        };
        let (dp, dd) = (rand3(&mut rng, 1.0), rand3(&mut rng, 1.0));
        let fd = (g(p0 + dp * h, d + dd * h) - g(p0 - dp * h, d - dd * h)) / (2.0 * h);
        let range = closest_on_segment_to_box(p0, d, half);
        let seed = adflex_runtime::Mat33::from_columns(&[w, w, Vec3::new(1.0, 0.0, 0.0)]);
        let (gp, gd, _, _, _) =
            DiffFunc::adjoint(&segment_box_contact, (p0, d, 0.05, half, range), seed);
        let reverse = gp.dot(&dp) + gd.dot(&dd);
        if (reverse - fd).abs() > 1e-6 * fd.abs().max(1.0) {
            bad.push(format!(
                "segment and box {case}: reverse {reverse} vs differences {fd} range {range:?}"
            ));
        }
        let (_, t) = DiffFunc::tangent(
            &segment_box_contact,
            (p0, d, 0.05, half, range),
            (dp, dd, 0.0, Vec3::zeros(), adflex_runtime::Vec2::zeros()),
        );
        let forward = (t.component_mul(&seed)).sum();
        assert!(
            (forward - reverse).abs() < 1e-10 * reverse.abs().max(1.0),
            "segment and box {case}: forward {forward} vs reverse {reverse}"
        );
        // A capsule's extra contact points: w . (point + normal) + depth, times the weight.
        for c in 0..8u32 {
            let k = |p0: Vec3<f64>, d: Vec3<f64>| {
                let e = capsule_box_point::call(p0, d, 0.05, half, c);
                (w.dot(&e.column(0).into_owned()) + w.dot(&e.column(1).into_owned()) + e[(0, 2)])
                    * e[(1, 2)]
            };
            let fd = (k(p0 + dp * h, d + dd * h) - k(p0 - dp * h, d - dd * h)) / (2.0 * h);
            let e = capsule_box_point::call(p0, d, 0.05, half, c);
            let value =
                w.dot(&e.column(0).into_owned()) + w.dot(&e.column(1).into_owned()) + e[(0, 2)];
            let seed = adflex_runtime::Mat33::from_columns(&[
                w * e[(1, 2)],
                w * e[(1, 2)],
                Vec3::new(e[(1, 2)], value, 0.0),
            ]);
            let (gp, gd, _, _, _) =
                DiffFunc::adjoint(&capsule_box_point, (p0, d, 0.05, half, c), seed);
            let reverse = gp.dot(&dp) + gd.dot(&dd);
            if (reverse - fd).abs() > 1e-6 * fd.abs().max(1.0) {
                bad.push(format!(
                    "capsule point {c}, case {case}: reverse {reverse} vs differences {fd}"
                ));
            }
            let (_, t) = DiffFunc::tangent(
                &capsule_box_point,
                (p0, d, 0.05, half, c),
                (dp, dd, 0.0, Vec3::zeros(), 0),
            );
            let forward = (t.component_mul(&seed)).sum();
            assert!(
                (forward - reverse).abs() < 1e-10 * reverse.abs().max(1.0),
                "capsule point {c}, case {case}: forward {forward} vs reverse {reverse}"
            );
            if e[(1, 2)] > 0.0 && e[(1, 2)] < 1.0 {
                fading += 1;
            }
        }
    }
    assert!(
        fading > 0,
        "no crossing fading in: the weight's slope is not checked"
    );
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// A free body at `x` (no rotation) with a contact shape, in a builder without gravity whose
/// ground is far below.
fn free_body(b: &mut ArticulationBuilder, name: &str, x: Vec3<f64>, shape: &str) {
    // 1 kg, with the inertia of its shape (a capsule's as a slender box's).
    let half = match shape {
        "capsule_y" => Vec3::new(0.05, 0.45, 0.05),
        "capsule_z" => Vec3::new(0.05, 0.05, 0.45),
        _ => Vec3::new(0.1, 0.1, 0.1),
    };
    let inertial = match shape {
        "sphere" => Inertial::sphere(1.0, 0.1, Vec3::zeros()),
        _ => Inertial::cuboid(1.0, half, Vec3::zeros()),
    };
    let l = b.add_link(
        name,
        None,
        Joint::free().initial(&[x.x, x.y, x.z, 0.0, 0.0, 0.0, 1.0]),
        inertial,
    );
    match shape {
        // Along y.
        "capsule_y" => {
            b.add_contact_capsule(l, Vec3::new(0.0, -0.4, 0.0), Vec3::new(0.0, 0.4, 0.0), 0.05);
        }
        // Along z.
        "capsule_z" => {
            b.add_contact_capsule(l, Vec3::new(0.0, 0.0, -0.4), Vec3::new(0.0, 0.0, 0.4), 0.05);
        }
        "box" => {
            b.add_contact_box(l, &Pose::identity(), Vec3::new(0.1, 0.1, 0.1));
        }
        // Along z.
        "cylinder" => {
            let shape = adflex_kernels::articulation::contact::GeomShape::Cylinder(0.1, 0.1);
            b.add_contact_shape(l, &Pose::identity(), &shape);
        }
        // A cube turned 45 degrees about z (an edge along z leads along x), or about y (an
        // edge along y faces -x).
        "box_edge_z" | "box_edge_y" => {
            let axis = if shape == "box_edge_z" {
                Vec3::z()
            } else {
                Vec3::y()
            };
            let turn = nalgebra::UnitQuaternion::from_axis_angle(
                &nalgebra::Unit::new_normalize(axis),
                std::f64::consts::FRAC_PI_4,
            );
            let pose = Pose::new(Vec3::zeros(), *turn.quaternion());
            b.add_contact_box(l, &pose, Vec3::new(0.1, 0.1, 0.1));
        }
        _ => {
            b.add_contact_sphere(l, Vec3::zeros(), 0.1);
        }
    }
}

fn space(b: &mut ArticulationBuilder) {
    b.gravity = Vec3::zeros();
    b.ground = Some(GroundContact {
        offset: -100.0,
        ke: 1e4,
        kd: 10.0,
        mu: 0.3,
        ..GroundContact::default()
    });
    b.link_contact = true;
}

/// The world linear velocity of free body `k` (7 coordinates, 6 velocities each).
fn world_velocity(q: &[f64], qd: &[f64], k: usize) -> Vec3<f64> {
    let (s, d) = (7 * k, 6 * k);
    let r = Quat::new(q[s + 6], q[s + 3], q[s + 4], q[s + 5]);
    let l = Quat::new(0.0, qd[d], qd[d + 1], qd[d + 2]);
    (r * l * r.conjugate()).imag()
}

/// Rolls two free bodies out, the first thrown along x at `v0`; returns the tape's state.
fn throw(
    model: &Articulations<f64>,
    v0: f64,
    steps: usize,
    tape: &mut Tape,
) -> (Array<f64>, Array<f64>, Array<f64>) {
    let q = Array::from_vec(model.q0.clone());
    let mut qd0 = vec![0.0; model.n_dof];
    qd0[0] = v0;
    qd0[4] = 0.3; // a little spin about y
    let qd = Array::from_vec(qd0).requires_grad();
    let mut s = ArticulationState { q, qd: qd.clone() };
    for _ in 0..steps {
        s = model.step(tape, &s, None, 1e-3).unwrap();
    }
    (qd, s.q, s.qd)
}

/// The thrown body hits the other: momentum is conserved, the other moves off, and
/// `d(x of the second body)/d(speed)` agrees with central differences, in reverse and in
/// forward mode.
fn check_collision(first: &str, second: &str, offset: Vec3<f64>) {
    let mut b = ArticulationBuilder::new();
    space(&mut b);
    // (Not a whole number of steps away: a contact that starts exactly at a step is a kink.)
    free_body(&mut b, "a", Vec3::new(-0.0123, 0.0, 0.0), first);
    free_body(&mut b, "b", Vec3::new(0.4, 0.0, 0.0) + offset, second);
    let model = b.finalize::<f64>().unwrap();
    let steps = 400;
    let mut tape = Tape::new();
    let (qd0, q, qd) = throw(&model, 1.0, steps, &mut tape);
    let (p, v) = (q.to_vec(), qd.to_vec());
    let momentum = world_velocity(&p, &v, 0) + world_velocity(&p, &v, 1);
    assert!(
        (momentum - Vec3::new(1.0, 0.0, 0.0)).norm() < 1e-9,
        "{first} hits {second}: momentum {momentum:?}"
    );
    let hit = world_velocity(&p, &v, 1);
    assert!(
        hit.x > 0.3,
        "{first} hits {second}: the second moves at {hit:?}"
    );
    let mut w = vec![0.0; 14 + 12];
    w[7] = 1.0;
    let g = tape.vjp(&[&q, &qd], &w, &[&qd0]).unwrap()[0];
    let f = |v0: f64| throw(&model, v0, steps, &mut Tape::new()).1.get(7);
    let fd = (f(1.0 + 1e-6) - f(1.0 - 1e-6)) / 2e-6;
    assert!(
        (g - fd).abs() < 1e-5 * fd.abs().max(1e-2),
        "{first} hits {second}: reverse {g} vs differences {fd}"
    );
    let mut dir = vec![0.0; 12];
    dir[0] = 1.0;
    let jv = tape.jvp(&[&qd0], &dir, &[&q]).unwrap();
    assert!(
        (jv[7] - g).abs() < 1e-9 * g.abs().max(1e-2),
        "{first} hits {second}: forward {} vs reverse {g}",
        jv[7]
    );
}

#[test]
fn capsules_spheres_and_boxes_collide_with_right_gradients() {
    // Capsules crossing in their middles (their end spheres never meet).
    check_collision("capsule_y", "capsule_z", Vec3::new(0.0, 0.0, 0.0));
    // A sphere into a capsule's side, slightly off its axis.
    check_collision("sphere", "capsule_z", Vec3::new(0.0, 0.03, 0.1));
    // A sphere into a box's face, and a capsule's side into a box's edge.
    check_collision("sphere", "box", Vec3::new(0.0, 0.02, 0.05));
    check_collision("capsule_z", "box", Vec3::new(0.0, 0.05, 0.0));
    // A box into a box, offset so that corners of each meet faces of the other.
    check_collision("box", "box", Vec3::new(0.0, 0.15, 0.05));
    // Two cubes meeting edge on edge, the edges crossing at right angles: no corner of either
    // enters the other.
    check_collision("box_edge_z", "box_edge_y", Vec3::new(0.0, 0.01, 0.02));
    // A sphere into a cylinder's side, off its axis; a capsule along its axis into its side;
    // a capsule crossing it.
    check_collision("sphere", "cylinder", Vec3::new(0.0, 0.04, 0.03));
    check_collision("capsule_z", "cylinder", Vec3::new(0.0, 0.03, 0.2));
    check_collision("capsule_y", "cylinder", Vec3::new(0.0, 0.0, 0.05));
}

#[test]
fn shapes_rest_on_a_fixed_box() {
    // A table: a box welded to the world; a ball, a lying capsule and a box dropped on it.
    let top = 0.5;
    for (shape, height) in [("sphere", 0.1), ("capsule_y", 0.05), ("box", 0.1)] {
        let mut b = ArticulationBuilder::new();
        b.ground = Some(GroundContact {
            offset: -10.0,
            ..GroundContact::default()
        });
        b.link_contact = true;
        fixed_table(&mut b, top, Vec3::new(1.0, 1.0, 0.25));
        free_body(
            &mut b,
            "thing",
            Vec3::new(0.1, -0.2, top + height + 0.05),
            shape,
        );
        let model = b.finalize::<f64>().unwrap();
        let mut s = model.state();
        for _ in 0..2000 {
            s = model.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
        }
        let (q, v) = (s.q.to_vec(), s.qd.to_vec());
        // Sunk by its weight over the contacts' stiffness: one contact for the ball, two for
        // the capsule (its end spheres, as on the ground); for the box its four lower edges at
        // full depth and its four side edges at half.
        let contacts = match shape {
            "box" => 6.0,
            "capsule_y" => 2.0,
            _ => 1.0,
        };
        let expected = top + height - 9.81 / (contacts * 1e4);
        assert!(
            (q[2] - expected).abs() < 2e-4,
            "{shape}: height {} vs {expected}",
            q[2]
        );
        // At rest but for a slow creep: smoothed Coulomb friction has no static friction.
        let speed = v[..3].iter().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(speed < 5e-3, "{shape}: still moving at {speed}");
    }
}

/// A table: a 10 kg box of half extents `half`, welded to the world with its top at `top`.
fn fixed_table(b: &mut ArticulationBuilder, top: f64, half: Vec3<f64>) {
    let table = b.add_link(
        "table",
        None,
        Joint::fixed().origin(Pose::at(Vec3::new(0.0, 0.0, top - half.z))),
        Inertial::cuboid(10.0, half, Vec3::zeros()),
    );
    b.add_contact_box(table, &Pose::identity(), half);
}

/// A 1 kg capsule along y (half-length 0.4, radius 0.05) centred at `y` above a table (a
/// fixed box of half extents `half` whose top is at 0.5), tilted by `tilt` about x (its +y end
/// higher), released, and stepped 4 s: its height and its axis' tilt from level at the end.
fn capsule_on_table(half: Vec3<f64>, y: f64, tilt: f64) -> (f64, f64) {
    let (height, level, _) = heavy_capsule_on_table(half, y, tilt, 1.0);
    (height, level)
}

/// [`capsule_on_table`] for a capsule of `mass` kg; also returns its final `y`.
fn heavy_capsule_on_table(half: Vec3<f64>, y: f64, tilt: f64, mass: f64) -> (f64, f64, f64) {
    let top = 0.5;
    let mut b = ArticulationBuilder::new();
    b.ground = Some(GroundContact {
        offset: -10.0,
        ..GroundContact::default()
    });
    b.link_contact = true;
    fixed_table(&mut b, top, half);
    let (s, c) = (0.5 * tilt).sin_cos();
    let l = b.add_link(
        "capsule",
        None,
        Joint::free().initial(&[0.1, y, top + 0.05 + 0.4 * tilt.abs() + 0.01, s, 0.0, 0.0, c]),
        Inertial::cuboid(mass, Vec3::new(0.05, 0.45, 0.05), Vec3::zeros()),
    );
    b.add_contact_capsule(l, Vec3::new(0.0, -0.4, 0.0), Vec3::new(0.0, 0.4, 0.0), 0.05);
    let model = b.finalize::<f64>().unwrap();
    let mut st = model.state();
    // (Across a beam it rocks on a lever of 0.1 m, damped 16 times less than on its ends:
    // 1.2e-3 rad from level after 2 s.)
    for _ in 0..4000 {
        st = model.step(&mut Tape::new(), &st, None, 1e-3).unwrap();
    }
    let q = st.q.to_vec();
    let axis = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        q[6], q[3], q[4], q[5],
    )) * Vec3::y();
    (q[2], axis.z.asin().abs(), q[1])
}

#[test]
fn capsules_rest_level_on_boxes_on_their_ends_and_the_boxs_edges() {
    // Released tilted by 0.05 rad, a capsule settles level on two contacts (sunk by its
    // weight over twice the stiffness): on a wide table its end spheres; across a beam
    // narrower than it, the beam's two edges; half over a table's edge (its centre of mass
    // over the table), its end and the table's edge. On one contact at its middle, or at its
    // lower end once tilted, it would rock.
    let expected = 0.5 + 0.05 - 9.81 / 2e4;
    for (what, half, y) in [
        ("on a wide table", Vec3::new(1.0, 1.0, 0.25), 0.0),
        ("across a narrow beam", Vec3::new(1.0, 0.1, 0.25), 0.0),
        (
            "half over the table's edge",
            Vec3::new(1.0, 1.0, 0.25),
            0.85,
        ),
    ] {
        for tilt in [0.05, -0.05] {
            let (height, level) = capsule_on_table(half, y, tilt);
            assert!(
                (height - expected).abs() < 2e-4,
                "{what}, tilt {tilt}: height {height} vs {expected}"
            );
            assert!(
                level < 1e-3,
                "{what}, tilt {tilt}: still {level} rad from level"
            );
        }
    }
}

#[test]
fn a_capsule_pressed_deeper_than_its_radius_into_a_box_is_pushed_out_up() {
    // 120 kg across a beam 0.4 m wide, on contacts of 1e4 N/m: the axis sinks below the
    // beam's top face and the points over the beam's edges, now on its side faces, fade out.
    // The closest point then pushes the capsule out through the nearest face, the top: it
    // stays on the beam, its axis some centimetres below the top (0.392 m high 4 s after its
    // release; 0.432 at rest on the closest point alone: 1,177 N = 1e4 N/m x (6.8 cm + the
    // radius)), instead of falling through to the floor 10 m below.
    let (height, _, y1) = heavy_capsule_on_table(Vec3::new(1.0, 0.2, 0.25), 0.0, 0.0, 120.0);
    assert!(
        height > 0.35 && height < 0.5,
        "height {height} (the top is at 0.5, the beam's bottom at 0)"
    );
    assert!(y1.abs() < 1e-3, "moved along the capsule to y = {y1}");
}

/// A 1 kg ball (radius 0.1) dropped from `h` above a surface (the ground, or a fixed box's
/// top when `on_box`) with the law's `onset`, undamped, rolled out 0.4 s at 1 ms: the ball's
/// final height and `d(height)/dh` by reverse mode (checked against forward mode).
fn bounce(onset: f64, on_box: bool, h: f64) -> (f64, f64) {
    let mut b = ArticulationBuilder::new();
    b.ground = Some(GroundContact {
        offset: if on_box { -10.0 } else { 0.0 },
        kd: 0.0,
        onset,
        ..GroundContact::default()
    });
    b.link_contact = true;
    if on_box {
        fixed_table(&mut b, 0.0, Vec3::new(1.0, 1.0, 0.25));
    }
    free_body(&mut b, "ball", Vec3::new(0.0, 0.0, 0.1 + h), "sphere");
    let model = b.finalize::<f64>().unwrap();
    let q = Array::from_vec(model.q0.clone()).requires_grad();
    let mut s = ArticulationState {
        q: q.clone(),
        qd: Array::zeros(model.n_dof),
    };
    let tape = &mut Tape::new();
    for _ in 0..400 {
        s = model.step(tape, &s, None, 1e-3).unwrap();
    }
    let mut w = vec![0.0; model.n_q];
    w[2] = 1.0;
    let g = tape.vjp(&[&s.q], &w, &[&q]).unwrap()[2];
    let mut dir = vec![0.0; model.n_q];
    dir[2] = 1.0;
    let jv = tape.jvp(&[&q], &dir, &[&s.q]).unwrap()[2];
    assert!(
        (jv - g).abs() < 1e-9 * g.abs().max(1.0),
        "forward {jv} vs reverse {g}"
    );
    (s.q.get(2), g)
}

#[test]
fn a_contact_onset_makes_a_rollouts_gradient_smooth_across_time_steps() {
    // The onset's rule against central differences and forward mode.
    use adflex_kernels::contact::law::contact_onset;
    use adflex_runtime::DiffFunc;
    for (c, onset) in [(-1e-3f64, 2e-3f64), (-3e-3, 2e-3), (-0.5, 0.0), (0.0, 2e-3)] {
        let h = 1e-7;
        let fd =
            (contact_onset::call(c + h, onset) - contact_onset::call(c - h, onset)) / (2.0 * h);
        let (g, _): (f64, f64) = DiffFunc::adjoint(&contact_onset, (c, onset), 1.0);
        let (_, t): (f64, f64) = DiffFunc::tangent(&contact_onset, (c, onset), (1.0, 0.0));
        assert!(
            (g - fd).abs() < 1e-7 && (t - g).abs() < 1e-14,
            "c {c}: {g} {t} {fd}"
        );
    }
    assert_eq!(contact_onset::call(-0.25, 0.0), -0.25);
    // Dropped from 41 heights 0.2 mm apart (the ball falls 2 mm per step at the impact), the
    // number of steps in contact changes several times. With the plain law each change is a
    // kink of the final height, a jump of its derivative; with an onset of 5 mm the
    // derivative varies smoothly. Largest change of the derivative between neighbours
    // (measured: 1.66 with the plain law, 0.067 with the onset, on the ground and on a box):
    for on_box in [false, true] {
        let jumps = |onset: f64| {
            let g: Vec<f64> = (0..41)
                .map(|i| bounce(onset, on_box, 0.2 + 2e-4 * i as f64).1)
                .collect();
            g.windows(2)
                .map(|w| (w[1] - w[0]).abs())
                .fold(0.0, f64::max)
        };
        let (plain, smooth) = (jumps(0.0), jumps(5e-3));
        assert!(
            smooth < 0.1 * plain,
            "on box {on_box}: the derivative jumps by {smooth} with an onset, {plain} without"
        );
        // And the derivative with the onset is the final height's (central differences).
        let f = |h: f64| bounce(5e-3, on_box, h).0;
        let fd = (f(0.201 + 1e-6) - f(0.201 - 1e-6)) / 2e-6;
        let (_, g) = bounce(5e-3, on_box, 0.201);
        assert!(
            (g - fd).abs() < 1e-5 * fd.abs().max(1e-2),
            "on box {on_box}: {g} vs {fd}"
        );
    }
}

/// A 1 kg body of `shape` (as [`free_body`]) `gap` above a base whose top is at `z = 0`:
/// the `ground` itself, or (the ground then far below) a fixed `box`, a `capsule` lying along
/// x (`capsule_y`: along y) or an upright `cylinder`; every contact with the law of `ground`.
fn body_on(base: &str, shape: &str, ground: GroundContact<f64>, gap: f64) -> Articulations<f64> {
    let mut b = ArticulationBuilder::new();
    b.ground = Some(GroundContact {
        offset: if base == "ground" { 0.0 } else { -10.0 },
        ..ground
    });
    b.link_contact = true;
    // The top of the base at z = 0.
    let (pose, inertial) = (
        Pose::at(Vec3::new(0.0, 0.0, -0.25)),
        Inertial::cuboid(10.0, Vec3::new(1.0, 1.0, 0.25), Vec3::zeros()),
    );
    if base != "ground" {
        let l = b.add_link("base", None, Joint::fixed().origin(pose), inertial);
        let shape = match base {
            "box" => GeomShape::Box(Vec3::new(1.0, 1.0, 0.25)),
            "capsule" | "capsule_y" => GeomShape::Capsule(0.25, 0.5),
            _ => GeomShape::Cylinder(0.25, 0.25),
        };
        // A capsule lying along x or y (its axis at the base's centre), the others upright.
        let turn = match base {
            "capsule" => nalgebra::UnitQuaternion::from_axis_angle(
                &Vec3::y_axis(),
                std::f64::consts::FRAC_PI_2,
            ),
            "capsule_y" => nalgebra::UnitQuaternion::from_axis_angle(
                &Vec3::x_axis(),
                std::f64::consts::FRAC_PI_2,
            ),
            _ => nalgebra::UnitQuaternion::identity(),
        };
        b.add_contact_shape(l, &Pose::new(Vec3::zeros(), *turn.quaternion()), &shape)
            .unwrap();
    }
    let half_height = match shape {
        "capsule_y" => 0.05,
        _ => 0.1,
    };
    free_body(
        &mut b,
        "body",
        Vec3::new(0.0, 0.0, half_height + gap),
        shape,
    );
    b.finalize::<f64>().unwrap()
}

/// The shapes resting on bases that the tests of every contact kernel use: on the ground (a
/// sphere, a capsule's end spheres, a box's corners, a cylinder's rim points) and on fixed
/// shapes (a sphere, a capsule and a box on a box, a sphere on a capsule and on a cylinder, a
/// capsule lying parallel on a capsule).
const EVERY_CONTACT: [(&str, &str); 10] = [
    ("ground", "sphere"),
    ("ground", "capsule_y"),
    ("ground", "box"),
    ("ground", "cylinder"),
    ("box", "sphere"),
    ("box", "capsule_y"),
    ("box", "box"),
    ("capsule", "sphere"),
    ("cylinder", "sphere"),
    ("capsule_y", "capsule_y"),
];

/// Every articulation contact gets the onset: a 1 kg body resting (on soft contacts, so that
/// each is deeper than the onset) sinks deeper by exactly `onset / 2`, on every base of
/// [`EVERY_CONTACT`].
/// The onset (1.5 mm) differs from `damping_depth` (1 mm): an argument swapped shows.
#[test]
fn every_contact_rests_deeper_by_half_the_onset() {
    let rest = |base: &str, shape: &str, onset: f64| -> f64 {
        let ground = GroundContact {
            // (A box on a box: its side edges touch at half the depth of its lower edges,
            // 2.7 mm at this stiffness, beyond the onset.)
            ke: 3e2,
            onset,
            ..GroundContact::default()
        };
        let model = body_on(base, shape, ground, 0.01);
        let mut s = model.state();
        for _ in 0..3000 {
            s = model.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
        }
        s.q.get(2)
    };
    let onset = 1.5e-3;
    let mut bad = Vec::new();
    for (base, shape) in EVERY_CONTACT {
        let drop = rest(base, shape, 0.0) - rest(base, shape, onset);
        // A box on a box rests on its 4 lower edges at the depth `p` and its 4 side edges at
        // `p / 2` (the middle of their part inside): `4 (p - o/2) + 4 (p/2 - o/2) = const`
        // moves `p` by `(8 / 6) o / 2`.
        let expected = match (base, shape) {
            ("box", "box") => 4.0 / 3.0 * 0.5 * onset,
            _ => 0.5 * onset,
        };
        if (drop - expected).abs() > 0.05 * onset {
            bad.push(format!(
                "{shape} on {base}: sinks {drop} deeper, not {expected}"
            ));
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
    // An onset too small to divide by is refused, by name.
    let e = ground_refused(GroundContact {
        onset: 1e-312,
        ..GroundContact::default()
    });
    assert!(e.contains("onset"), "{e}");
}

/// The error of a model whose ball touches `ground` (the test asks that it be refused).
fn ground_refused(ground: GroundContact<f64>) -> String {
    let mut b = ArticulationBuilder::new();
    b.ground = Some(ground);
    free_body(&mut b, "ball", Vec3::new(0.0, 0.0, 0.2), "sphere");
    b.finalize::<f64>().unwrap_err().to_string()
}

/// The stiction tolerance `vs`: its rule against central differences and forward mode, and
/// every articulation contact kernel receives it: a body pressed 1 mm into its base and
/// sliding at 2 mm/s (so that the friction is in its smoothed range) is slowed by a
/// friction `mu |f| v / (v + vs)`, which scales by `(v + vs) / (v + vs')` from `vs` to `vs'`
/// at every contact point alike. A tolerance of 0 (friction 0 / 0 at rest) is refused.
#[test]
fn every_contact_slides_with_the_stiction_tolerance() {
    use adflex_kernels::contact::law::{
        contact_force, contact_force_with_stiction, STICTION_TOLERANCE,
    };
    use adflex_runtime::DiffFunc;
    // The rule, in all seven arguments (the friction's smoothed range and beyond it).
    let n = Vec3::new(0.6, 0.0, 0.8);
    for v in [Vec3::new(3e-3, -4e-3, 1e-3), Vec3::new(0.4, 0.3, -0.2)] {
        let args = (n, -2e-3, v, 1e4, 50.0, 0.7, 0.02);
        let w = Vec3::new(0.3, -0.5, 0.9);
        let wv = |a: (Vec3<f64>, f64, Vec3<f64>, f64, f64, f64, f64)| {
            w.dot(&contact_force_with_stiction::call(
                a.0, a.1, a.2, a.3, a.4, a.5, a.6,
            ))
        };
        let g: (Vec3<f64>, f64, Vec3<f64>, f64, f64, f64, f64) =
            DiffFunc::adjoint(&contact_force_with_stiction, args, w);
        let h = 1e-7;
        // Directional: along the velocity's x, the depth and the tolerance.
        let dir = (
            Vec3::zeros(),
            0.3,
            Vec3::new(1.0, 0.0, 0.0),
            0.0,
            0.0,
            0.0,
            0.5,
        );
        let at = |t: f64| {
            (
                args.0,
                args.1 + t * dir.1,
                args.2 + t * dir.2,
                args.3,
                args.4,
                args.5,
                args.6 + t * dir.6,
            )
        };
        let fd = (wv(at(h)) - wv(at(-h))) / (2.0 * h);
        let rev = g.1 * dir.1 + g.2.dot(&dir.2) + g.6 * dir.6;
        let tan = w.dot(&DiffFunc::tangent(&contact_force_with_stiction, args, dir).1);
        assert!(
            (rev - fd).abs() < 1e-6 * fd.abs().max(1.0) && (tan - rev).abs() < 1e-9 * rev.abs(),
            "v {v:?}: reverse {rev}, forward {tan}, central differences {fd}"
        );
        // `contact_force` is the law at the default tolerance.
        let plain = contact_force::call(n, -2e-3, v, 1e4, 50.0, 0.7);
        let with =
            contact_force_with_stiction::call(n, -2e-3, v, 1e4, 50.0, 0.7, STICTION_TOLERANCE);
        assert_eq!(plain, with);
    }
    assert_eq!(
        GroundContact::default().stiction_tolerance,
        STICTION_TOLERANCE
    );
    // Every kernel: the change of the sliding velocity in one short step.
    let (v, vs, vs2) = (2e-3, 0.01, 0.03);
    let mut bad = Vec::new();
    for (base, shape) in EVERY_CONTACT {
        let slowed = |stiction_tolerance: f64| {
            // (Explicit friction: the law itself; an implicit step's is
            // `implicit_friction_settles_where_explicit_friction_chatters`'s.)
            let ground = GroundContact {
                stiction_tolerance,
                mu: 0.5,
                implicit_friction: false,
                ..GroundContact::default()
            };
            let model = body_on(base, shape, ground, -1e-3);
            let s = model.state();
            s.qd.set(0, v);
            // (A short step: the body's turn by the friction's torque is negligible.)
            let next = model.step(&mut Tape::new(), &s, None, 1e-6).unwrap();
            v - next.qd.get(0)
        };
        let (a, b) = (slowed(vs), slowed(vs2));
        let expected = (v + vs2) / (v + vs);
        if !(a > 0.0 && (a / b - expected).abs() < 1e-6 * expected) {
            bad.push(format!(
                "{shape} on {base}: slowed by {a} and {b}, ratio {} not {expected}",
                a / b
            ));
        }
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
    for vs in [0.0, -0.01, f64::NAN, 1e-12] {
        let e = ground_refused(GroundContact {
            stiction_tolerance: vs,
            ..GroundContact::default()
        });
        assert!(e.contains("stiction_tolerance"), "{vs}: {e}");
    }
}

/// Implicit ground friction (`GroundContact::implicit_friction`, the default): an `Euler` or
/// `ImplicitFast` step solves with the friction's damper `k (I - n n^T)`, `k = mu |fn| /
/// sqrt(|u|^2 + vs^2)`, in its matrix.
/// - Closed form: a ball on two sliders (a light carriage along x, the ball along z on it),
///   resting on the ground and pushed along x at `v` well below `vs`: one step scales `v` by
///   `1 - dt k / (m + dt d)` (the x slider's mass `m`, the friction's coefficient `k` and its
///   damper `d`, both `mu |fn| / vs` at rest), where the explicit law gives `1 - dt k / m`
///   (checked too with the option off, which is unstable here: `dt k / m` is 3.9).
/// - A box resting on a face, turning slowly about the normal, at MJCF's defaults (friction
///   1, 2 ms): it stops, where the explicit law turns it back and forth for ever.
/// - Gradients of a rollout in which the box slides, turns and sticks, against central
///   differences, and forward mode against reverse.
#[test]
fn implicit_friction_settles_where_explicit_friction_chatters() {
    use adflex_kernels::articulation::ArticulationIntegrator::{Euler, ImplicitFast};
    let slider = |implicit_friction: bool| {
        let mut b = ArticulationBuilder::new();
        b.ground = Some(GroundContact {
            mu: 1.0,
            implicit_friction,
            ..GroundContact::default()
        });
        let carriage = b.add_link(
            "carriage",
            None,
            Joint::prismatic(Vec3::x()),
            Inertial::point(0.02, Vec3::zeros()),
        );
        let ball = b.add_link(
            "ball",
            Some(carriage),
            Joint::prismatic(Vec3::z()).initial(&[0.05]),
            Inertial::point(1.0, Vec3::zeros()),
        );
        b.add_contact_sphere(ball, Vec3::zeros(), 0.05);
        b.finalize::<f64>().unwrap()
    };
    let (dt, v) = (4e-3, 1e-4);
    for integrator in [Euler, ImplicitFast] {
        for implicit in [true, false] {
            let mut model = slider(implicit);
            model.integrator = integrator;
            let mut s = model.state();
            for _ in 0..3000 {
                s = model.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
            }
            assert!(s.qd.get(1).abs() < 1e-9, "settled: {:?}", s.qd.to_vec());
            s.qd.set(0, v);
            // The friction's coefficient at this state (1 kg on the ground, 1e4 N/m).
            let fn_ = -1e4 * (s.q.get(1) - 0.05).min(0.0);
            let k = 1.0 * fn_ / (v + 0.01);
            let damper = 1.0 * fn_ / (v * v + 1e-4f64).sqrt();
            let m = 1.02;
            let next = model.step(&mut Tape::new(), &s, None, dt).unwrap();
            let (got, expected) = match implicit {
                true => (next.qd.get(0) / v, 1.0 - dt * k / (m + dt * damper)),
                false => (next.qd.get(0) / v, 1.0 - dt * k / m),
            };
            assert!(
                (got - expected).abs() < 1e-9,
                "{integrator:?}, implicit {implicit}: v scaled by {got}, expected {expected} \
                 (dt k / m = {})",
                dt * k / m
            );
        }
    }

    // The box at MJCF's defaults, turning at 0.05 rad/s.
    let box_on_floor = |implicit: bool| {
        let text = r#"<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>
            <body name="box" pos="0 0 0.0488"><freejoint/>
              <geom type="box" size="0.1 0.07 0.05" density="1000"/></body>
            </worldbody></mujoco>"#;
        let mut b = mjcf::parse(text).unwrap().builder;
        b.ground.as_mut().unwrap().implicit_friction = implicit;
        b.finalize::<f64>().unwrap()
    };
    let spin = |model: &Articulations<f64>, steps: usize| {
        let mut s = model.state();
        s.qd.set(5, 0.05);
        let mut late = 0.0f64;
        for k in 0..steps {
            s = model.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
            if k >= steps - 100 {
                late = late.max(s.qd.get(5).abs());
            }
        }
        late
    };
    let (settled, chatter) = (
        spin(&box_on_floor(true), 1000),
        spin(&box_on_floor(false), 1000),
    );
    println!("turn rate over the last 100 steps: implicit {settled:.3e}, explicit {chatter:.3e}");
    assert!(
        settled < 1e-6,
        "implicit friction: still turning at {settled} rad/s"
    );
    assert!(
        chatter > 1e-3,
        "explicit friction settled ({chatter}): the test is moot"
    );

    // Gradients: the box thrown sliding and turning, stopping within the rollout.
    let model = box_on_floor(true);
    let q0 = model.q0.clone();
    let worst = thrown_body_gradients(&model, &q0, [0.15, -0.05, 0.0, 0.0, 0.0, 1.0], |m| {
        &mut m.contact_mu
    });
    println!("through implicit friction: worst relative gradient error {worst:.2e}");
}

/// The gradients of a free body's rollout (150 steps of 2 ms from `q0` at `qd0`, sliding and
/// turning; loss: its final position and turn) with respect to its initial velocity and its
/// contacts' friction coefficients (`mu`, an array of the model) against central
/// differences to 1e-6 relative, and forward mode against reverse. Returns the worst
/// relative error.
fn thrown_body_gradients(
    model: &Articulations<f64>,
    q0: &[f64],
    qd0: [f64; 6],
    mu: impl Fn(&mut Articulations<f64>) -> &mut Array<f64>,
) -> f64 {
    let run = |model: &Articulations<f64>, qd0: &[f64], tape: &mut Tape| {
        let s = ArticulationState {
            q: Array::from_vec(q0.to_vec()),
            qd: Array::from_vec(qd0.to_vec()),
        };
        let mut t = s.clone();
        for _ in 0..150 {
            t = model.step(tape, &t, None, 2e-3).unwrap();
        }
        (s, t)
    };
    let w = [1.0, 0.5, 0.0, 0.0, 0.0, 2.0, 0.0];
    let loss = |model: &Articulations<f64>, qd0: &[f64]| -> f64 {
        let (_, t) = run(model, qd0, &mut Tape::new());
        t.q.to_vec().iter().zip(&w).map(|(a, b)| a * b).sum()
    };
    let mut tape = Tape::new();
    let (s, t) = run(model, &qd0, &mut tape);
    let moved = (t.q.get(0) - q0[0]).hypot(t.q.get(1) - q0[1]);
    assert!(moved > 5e-4, "the body slid {moved} m: the rollout is moot");
    let mut m = model.clone();
    let mu_values = mu(&mut m).to_vec();
    let g = tape.vjp(&[&t.q], &w, &[&s.qd, &*mu(&mut m)]).unwrap();
    let h = 1e-6;
    let mut worst = 0.0f64;
    for i in [0, 1, 5] {
        let at = |e: f64| {
            let mut x = qd0;
            x[i] += e;
            loss(model, &x)
        };
        let fd = (at(h) - at(-h)) / (2.0 * h);
        worst = worst.max((g[i] - fd).abs() / fd.abs().max(1e-3));
    }
    let with_mu = |e: f64| {
        let mut m = model.clone();
        *mu(&mut m) = Array::from_vec(mu_values.iter().map(|m| m + e).collect());
        loss(&m, &qd0)
    };
    let fd_mu = (with_mu(h) - with_mu(-h)) / (2.0 * h);
    let rev_mu: f64 = g[6..].iter().sum();
    worst = worst.max((rev_mu - fd_mu).abs() / fd_mu.abs().max(1e-3));
    assert!(worst < 1e-6, "{g:?}, friction: {rev_mu} against {fd_mu}");
    let dir = [0.3, -0.2, 0.1, 0.4, -0.1, 0.5];
    let jv = tape.jvp(&[&s.qd], &dir, &[&t.q]).unwrap();
    let jv_w: f64 = jv.iter().zip(&w).map(|(a, b)| a * b).sum();
    let gw: f64 = g[..6].iter().zip(&dir).map(|(a, b)| a * b).sum();
    assert!(
        (jv_w - gw).abs() < 1e-9 * gw.abs().max(1.0),
        "{jv_w} vs {gw}"
    );
    worst
}

/// A box resting on a static box (a table: a worldbody geom, so a link fixed to the world) at
/// MJCF's defaults: with implicit friction its friction's damper is on the box's link, and a
/// push settles as on the floor; explicit, the box rocks and slides back and forth at every
/// step for ever (4.8 mm/s, measured before the change). Gradients through the table's
/// friction against central differences, forward mode against reverse.
#[test]
fn implicit_friction_settles_a_box_on_a_table() {
    let on_table = |implicit: bool| {
        let text = r#"<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>
            <geom type="box" size="0.3 0.3 0.1" pos="0 0 0.1"/>
            <body name="box" pos="0 0 0.2488"><freejoint/>
              <geom type="box" size="0.1 0.07 0.05" density="1000"/></body>
            </worldbody></mujoco>"#;
        let mut b = mjcf::parse(text).unwrap().builder;
        b.ground.as_mut().unwrap().implicit_friction = implicit;
        b.finalize::<f64>().unwrap()
    };
    // Settled, pushed (turning and sliding), then the largest speed over the last 100 steps.
    let late = |model: &Articulations<f64>| {
        let mut s = model.state();
        for _ in 0..500 {
            s = model.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
        }
        s.qd.set(0, s.qd.get(0) + 0.02);
        s.qd.set(5, s.qd.get(5) + 0.05);
        let mut most = 0.0f64;
        for k in 0..1500 {
            s = model.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
            if k >= 1400 {
                most = s.qd.to_vec().iter().fold(most, |m, x| m.max(x.abs()));
            }
        }
        most
    };
    let table = on_table(true);
    assert!(
        table.link_fixed.to_vec().contains(&1),
        "the table is a link fixed to the world"
    );
    let (settled, rocking) = (late(&table), late(&on_table(false)));
    println!(
        "largest speed over the last 100 steps: implicit {settled:.3e}, explicit {rocking:.3e}"
    );
    assert!(
        settled < 1e-6,
        "implicit friction: still moving at {settled}"
    );
    assert!(
        rocking > 1e-4,
        "explicit friction settled ({rocking}): the test is moot"
    );

    // The box thrown sliding and turning on the table until it stops.
    let q0 = table.q0.clone();
    let worst = thrown_body_gradients(&table, &q0, [0.4, -0.1, 0.0, 0.0, 0.0, 1.5], |m| {
        &mut m.box_pair_mu
    });
    println!("through the table's implicit friction: worst relative gradient error {worst:.2e}");
}

/// A capsule resting on fixed shapes (worldbody geoms) at MJCF's defaults: on a table (its
/// contacts along the box's face), across two rails (capsules crossing) and in the groove
/// between two parallel rails (capsules touching along a line). With implicit friction each
/// contact's damper is on the capsule's link and a push settles; explicit, it keeps moving.
/// Gradients through the friction of the table and of the rails against central differences,
/// forward mode against reverse.
#[test]
fn implicit_friction_settles_capsules_on_fixed_shapes() {
    let scene = |fixed: &str, body: &str, implicit: bool| {
        let text = format!(
            r#"<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>{fixed}
            <body name="capsule" pos="{body}"><freejoint/>
              <geom type="capsule" fromto="-0.2 0 0 0.2 0 0" size="0.03" density="1000"/>
            </body></worldbody></mujoco>"#
        );
        let mut b = mjcf::parse(&text).unwrap().builder;
        b.ground.as_mut().unwrap().implicit_friction = implicit;
        b.finalize::<f64>().unwrap()
    };
    let table = r#"<geom type="box" size="0.5 0.5 0.1" pos="0 0 0.1"/>"#;
    let across = r#"<geom type="capsule" fromto="0.1 -0.5 0.2 0.1 0.5 0.2" size="0.02"/>
        <geom type="capsule" fromto="-0.1 -0.5 0.2 -0.1 0.5 0.2" size="0.02"/>"#;
    let groove = r#"<geom type="capsule" fromto="-0.5 -0.04 0.2 0.5 -0.04 0.2" size="0.02"/>
        <geom type="capsule" fromto="-0.5 0.04 0.2 0.5 0.04 0.2" size="0.02"/>"#;
    let cases = [
        ("on a table", table, "0 0 0.2295"),
        ("across two rails", across, "0 0 0.2495"),
        ("in a groove", groove, "0 0 0.2295"),
    ];
    // Settled, pushed along its axis, then over the last 100 steps the largest change of a
    // velocity in one step (chatter: explicit friction flips the velocities at every step)
    // and the largest speed. (Not turned: the friction under a turning capsule rolls it, and
    // a capsule rolls on a plane, or along a rail, without loss.) Implicitly the capsule
    // still creeps as smoothed friction lets it: across the rails at about 1e-7 m/s (the
    // contacts' normals lean with the capsule, pressed in a little more at one rail than at
    // the other), and in the groove it sinks as the friction that wedges it yields (2e-6 m/s,
    // halving every half second).
    let late = |model: &Articulations<f64>| {
        let mut s = model.state();
        for _ in 0..500 {
            s = model.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
        }
        s.qd.set(0, s.qd.get(0) + 0.02);
        let (mut chatter, mut speed) = (0.0f64, 0.0f64);
        for k in 0..1500 {
            let next = model.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
            if k >= 1400 {
                for (a, b) in s.qd.to_vec().iter().zip(next.qd.to_vec()) {
                    chatter = chatter.max((b - a).abs());
                    speed = speed.max(b.abs());
                }
            }
            s = next;
        }
        (chatter, speed)
    };
    for (what, fixed, body) in cases {
        let implicit = scene(fixed, body, true);
        assert!(implicit.link_fixed.to_vec().contains(&1), "{what}");
        let (chatter, speed) = late(&implicit);
        let (explicit_chatter, _) = late(&scene(fixed, body, false));
        println!(
            "{what}: late change in a step implicit {chatter:.2e} (speed {speed:.2e}), \
             explicit {explicit_chatter:.2e}"
        );
        assert!(
            chatter < 1e-7 && speed < 1e-5,
            "{what}, implicit friction: {chatter}, {speed}"
        );
        assert!(
            explicit_chatter > 1e-4,
            "{what}: explicit friction settled: moot"
        );
    }
    // Thrown sliding and turning on the table, across the rails and along the groove (the
    // parallel contacts' dampers).
    type Mu = fn(&mut Articulations<f64>) -> &mut Array<f64>;
    let throws: [(usize, [f64; 6], Mu); 3] = [
        (0, [0.4, -0.1, 0.0, 0.0, 0.0, 1.5], |m| &mut m.box_pair_mu),
        (1, [0.1, 0.4, 0.0, 0.0, 0.0, 1.5], |m| {
            &mut m.capsule_pair_mu
        }),
        (2, [0.4, 0.02, 0.0, 0.0, 0.0, 0.3], |m| {
            &mut m.capsule_pair_mu
        }),
    ];
    for (c, qd0, mu) in throws {
        let (what, fixed, body) = cases[c];
        let model = scene(fixed, body, true);
        let worst = thrown_body_gradients(&model, &model.q0.clone(), qd0, mu);
        println!("{what}, thrown: worst relative gradient error {worst:.2e}");
    }
}

/// A capsule lying on another, parallel, touches it at the two ends of their overlap (as a
/// capsule on the ground rests on its ends), not at one point under its middle: tilted by
/// up to 0.2 degrees about the horizontal normal to both axes, it is pushed back by a torque
/// proportional to the tilt, `2 ke (l/2)^2` per radian for an overlap of length `l` (one point
/// would jump to the lower end: a torque of `ke depth l/2` at any tilt), and borne by both
/// ends. Crossed at right angles, one contact as before; and a rollout of the capsule rocking
/// on the other, with its derivative against central differences and forward mode.
#[test]
fn parallel_capsules_touch_at_both_ends_of_their_overlap() {
    let ke = GroundContact::default().ke;
    let depth = 2e-3;
    // The body's (`capsule_y`: 0.8 m long, on a fixed capsule 1 m long) acceleration about x
    // and along z (the force on it, m = 1 kg) in one short step from rest, pressed `depth`
    // into the base, turned by `angle` about `axis`.
    let push = |base: &str, axis: Vec3<f64>, angle: f64| -> (f64, f64) {
        let model = body_on(base, "capsule_y", GroundContact::default(), -depth);
        let s = model.state();
        for k in 0..3 {
            s.q.set(3 + k, axis[k] * (0.5 * angle).sin());
        }
        s.q.set(6, (0.5 * angle).cos());
        let dt = 1e-7;
        let next = model.step(&mut Tape::new(), &s, None, dt).unwrap();
        (next.qd.get(3) / dt, next.qd.get(2) / dt + 9.81)
    };
    let (pitch, yaw) = (Vec3::x(), Vec3::z());
    let degree = std::f64::consts::PI / 180.0;
    // The capsule's inertia about x (a 1 kg box of half extents 0.05, 0.45, 0.05).
    let ixx = (0.45f64.powi(2) + 0.05f64.powi(2)) / 3.0;
    let stiffness = 2.0 * ke * 0.4f64.powi(2);
    let (level_torque, level_force) = push("capsule_y", pitch, 0.0);
    assert!(level_torque.abs() < 1e-6, "level: {level_torque}");
    assert!(
        (level_force - 2.0 * ke * depth).abs() < 1e-3 * ke * depth,
        "borne by {level_force} N, not two contacts' {}",
        2.0 * ke * depth
    );
    for deg in [-0.2, -0.1, -0.05, 0.05, 0.1, 0.2] {
        let tilt = deg * degree;
        let (torque, force) = push("capsule_y", pitch, tilt);
        let expected = -stiffness * tilt.sin() * tilt.cos() / ixx;
        assert!(
            (torque - expected).abs() < 0.02 * expected.abs(),
            "tilted {deg} degrees: {torque} rad/s^2, expected {expected}"
        );
        assert!(
            (force - level_force).abs() < 1e-3 * level_force,
            "{deg}: {force}"
        );
    }
    // Through the blend (0.3 to 1.7 degrees) and past it, every 0.05 degrees: pitched, the
    // torque grows in size without a jump (one end lifts off at 0.29 degrees, and the lower
    // end is also the closest point); turned about the vertical (the axes crossing), the force
    // falls smoothly from the two ends' to the one contact's of the crossing.
    let sweep = |axis: Vec3<f64>| -> Vec<(f64, f64)> {
        (0..=50)
            .map(|k| push("capsule_y", axis, 0.05 * k as f64 * degree))
            .collect()
    };
    let pitched = sweep(pitch);
    let largest = pitched.iter().map(|p| p.0.abs()).fold(0.0, f64::max);
    for (k, w) in pitched.windows(2).enumerate() {
        let (a, b) = (w[0].0.abs(), w[1].0.abs());
        assert!(
            b >= a && b - a < 0.1 * largest,
            "pitched {} degrees: torque {a} then {b} (largest {largest})",
            0.05 * k as f64
        );
    }
    let turned = sweep(yaw);
    for (k, w) in turned.windows(2).enumerate() {
        assert!(
            (w[1].1 - w[0].1).abs() < 0.1 * level_force && w[1].1 <= w[0].1 + 1e-9,
            "turned {} degrees: force {} then {}",
            0.05 * k as f64,
            w[0].1,
            w[1].1
        );
    }
    let crossing = turned.last().unwrap().1;
    assert!(
        (crossing - ke * depth).abs() < 0.02 * ke * depth,
        "turned 2.5 degrees: {crossing} N, not one contact's {}",
        ke * depth
    );
    // Crossed at right angles (the base along x): one contact.
    let (_, crossed) = push("capsule", pitch, 0.0);
    assert!(
        (crossed - ke * depth).abs() < 1e-3 * ke * depth,
        "crossed: {crossed} N"
    );
    // End to end on one line (the body beyond the base's end along y, its axis on the base's):
    // one contact, though the axes are parallel.
    let model = body_on("capsule_y", "capsule_y", GroundContact::default(), 0.0);
    let s = model.state();
    s.q.set(1, 0.5 + 0.25 + 0.4 + 0.05 - depth);
    s.q.set(2, -0.25);
    let dt = 1e-7;
    let next = model.step(&mut Tape::new(), &s, None, dt).unwrap();
    let along = next.qd.get(1) / dt;
    assert!(
        (along - ke * depth).abs() < 1e-3 * ke * depth,
        "end to end: pushed by {along} N, not one contact's {}",
        ke * depth
    );
    // Rocking: the tilt after 0.3 s against the initial angular velocity about x.
    let rock = |w0: f64| -> (f64, f64) {
        let model = body_on("capsule_y", "capsule_y", GroundContact::default(), -5e-4);
        let qd = Array::from_vec({
            let mut qd = vec![0.0; model.n_dof];
            qd[3] = w0;
            qd
        })
        .requires_grad();
        let mut s = ArticulationState {
            q: Array::from_vec(model.q0.clone()),
            qd: qd.clone(),
        };
        let tape = &mut Tape::new();
        for _ in 0..300 {
            s = model.step(tape, &s, None, 1e-3).unwrap();
        }
        let mut w = vec![0.0; model.n_q];
        w[3] = 1.0;
        let g = tape.vjp(&[&s.q], &w, &[&qd]).unwrap()[3];
        let mut dir = vec![0.0; model.n_dof];
        dir[3] = 1.0;
        let jv = tape.jvp(&[&qd], &dir, &[&s.q]).unwrap()[3];
        assert!(
            (jv - g).abs() < 1e-9 * g.abs().max(1e-3),
            "forward {jv} vs reverse {g}"
        );
        (s.q.get(3), g)
    };
    for w0 in [0.05, 1.0, 3.0] {
        let h = 1e-6;
        let fd = (rock(w0 + h).0 - rock(w0 - h).0) / (2.0 * h);
        let (_, g) = rock(w0);
        assert!(
            (g - fd).abs() < 1e-5 * fd.abs().max(1e-3),
            "w0 {w0}: {g} vs central differences {fd}"
        );
    }
}

const TWO_BALLS: &str = r#"<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1" FLOOR/>
    <body name="a" pos="0 0 0.5">
      <freejoint/>
      <geom type="sphere" size="0.1" A/>
      <body name="child" pos="0.1 0 0">
        <joint type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.05"/>
      </body>
    </body>
    <body name="b" pos="0.15 0 0.5">
      <freejoint/>
      <geom type="box" size="0.1 0.1 0.1" B/>
    </body>
  </worldbody>
  CONTACT
</mujoco>"#;

fn two_balls(floor: &str, a: &str, b: &str, contact: &str) -> Articulations<f64> {
    let xml = TWO_BALLS
        .replace("FLOOR", floor)
        .replace(" A/", &format!(" {a}/"))
        .replace(" B/", &format!(" {b}/"))
        .replace("CONTACT", contact);
    mjcf::parse(&xml).unwrap().builder.finalize().unwrap()
}

#[test]
fn mjcf_contact_filters_follow_mujoco() {
    // Everything default: a's sphere and b's box touch, the child's capsule and b's box touch,
    // a and its child never (parent and child); all touch the floor (1 + 2 + 8 spheres).
    let m = two_balls("", "", "", "");
    assert_eq!((m.capsule_pairs.len(), m.box_pairs.len()), (0, 2));
    assert_eq!(m.contact_link.len(), 11);
    // contype 2 on a's sphere: its conaffinity 1 still accepts b's contype 1.
    let m = two_balls("", r#"contype="2""#, "", "");
    assert_eq!(m.box_pairs.len(), 2);
    // contype 2, conaffinity 2: b (1, 1) and the floor (1, 1) no longer touch it.
    let m = two_balls("", r#"contype="2" conaffinity="2""#, "", "");
    assert_eq!(m.box_pairs.len(), 1);
    assert_eq!(m.contact_link.len(), 10);
    // The floor's conaffinity 0 and contype 0: nothing touches it; links still touch.
    let m = two_balls(r#"contype="0" conaffinity="0""#, "", "", "");
    assert_eq!((m.contact_link.len(), m.box_pairs.len()), (0, 2));
    // Excluded by name.
    let m = two_balls(
        "",
        "",
        "",
        r#"<contact><exclude body1="b" body2="child"/></contact>"#,
    );
    assert_eq!(m.box_pairs.len(), 1);
    // Defaults apply.
    let xml = TWO_BALLS
        .replace(
            "<worldbody>",
            r#"<default><geom conaffinity="0"/></default><worldbody>"#,
        )
        .replace("FLOOR", r#"conaffinity="1""#)
        .replace(" A/", "/")
        .replace(" B/", "/")
        .replace("CONTACT", "");
    let m: Articulations<f64> = mjcf::parse(&xml).unwrap().builder.finalize().unwrap();
    assert_eq!((m.box_pairs.len(), m.contact_link.len()), (0, 11));
    // Bad masks and exclusions are errors naming the element and its line.
    for (bad, needle) in [
        (two_balls_text("", r#"contype="-1""#, ""), "contype"),
        (
            two_balls_text("", "", "").replace(
                "CONTACT",
                r#"<contact><exclude body1="a" body2="nobody"/></contact>"#,
            ),
            "nobody",
        ),
        (
            two_balls_text("", "", "").replace(
                "CONTACT",
                r#"<contact><pair geom1="x" geom2="y"/></contact>"#,
            ),
            "pair",
        ),
    ] {
        let e = mjcf::parse(&bad.replace("CONTACT", "")).unwrap_err();
        assert!(e.to_string().contains(needle), "{e}");
        assert!(e.line.is_some(), "{e}");
    }
}

fn two_balls_text(floor: &str, a: &str, b: &str) -> String {
    TWO_BALLS
        .replace("FLOOR", floor)
        .replace(" A/", &format!(" {a}/"))
        .replace(" B/", &format!(" {b}/"))
}

#[test]
fn builder_contact_filters_welds_and_bad_shapes() {
    let mut b = ArticulationBuilder::new();
    space(&mut b);
    free_body(&mut b, "a", Vec3::zeros(), "sphere");
    free_body(&mut b, "b", Vec3::new(0.5, 0.0, 0.0), "sphere");
    // A box welded to b: it never touches b's sphere, but touches a's.
    let b_link = b.find("b").unwrap();
    let welded = b.add_link(
        "b_plate",
        Some(b_link),
        Joint::fixed().origin(Pose::at(Vec3::new(0.2, 0.0, 0.0))),
        Inertial::massless(),
    );
    b.add_contact_box(welded, &Pose::identity(), Vec3::new(0.05, 0.05, 0.05));
    let m: Articulations<f64> = b.clone().finalize().unwrap();
    assert_eq!((m.capsule_pairs.len(), m.box_pairs.len()), (1, 1));
    // Filters: a's sphere of type 2 accepting 2 touches neither.
    let mut f = b.clone();
    f.set_contact_filter(
        0,
        ContactFilter {
            contype: 2,
            conaffinity: 2,
        },
    );
    let m: Articulations<f64> = f.finalize().unwrap();
    assert_eq!((m.capsule_pairs.len(), m.box_pairs.len()), (0, 0));
    // Worlds: the same scene twice has twice the pairs, never across worlds.
    let m: Articulations<f64> = b.replicate(2).finalize().unwrap();
    assert_eq!((m.capsule_pairs.len(), m.box_pairs.len()), (2, 2));
    // Bad shapes are errors naming the shape and the link.
    let mut bad = b.clone();
    bad.add_contact_box(welded, &Pose::identity(), Vec3::new(0.05, 0.0, 0.05));
    let e = bad.finalize::<f64>().unwrap_err().to_string();
    assert!(
        e.contains("contact shape 3") && e.contains("b_plate"),
        "{e}"
    );
    let mut bad = b.clone();
    bad.add_contact_sphere(welded, Vec3::new(f64::NAN, 0.0, 0.0), 0.1);
    assert!(bad.finalize::<f64>().is_err());
    // Link contact needs a law.
    let mut bad = b;
    bad.ground = None;
    let e = bad.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("link_contact"), "{e}");
}

#[test]
fn mjcf_static_bodies_and_bodies_with_several_joints_follow_mujoco() {
    let xml = r#"<mujoco>
  <worldbody>
    <geom type="plane" size="5 5 0.1"/>
    <geom type="plane" size="5 5 0.1" contype="0" conaffinity="0"/>
    <body name="base" pos="0 0 0.5">
      <geom type="box" size="0.2 0.2 0.2"/>
      <body name="arm" pos="0 0 0.2">
        <joint type="hinge" axis="0 1 0"/>
        <joint type="hinge" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.4" size="0.05"/>
        <body name="hand" pos="0 0 0.4">
          <joint type="hinge" axis="0 1 0"/>
          <joint type="hinge" axis="1 0 0"/>
          <geom type="sphere" size="0.05"/>
        </body>
      </body>
    </body>
    <body name="post" pos="1 0 0.5">
      <geom type="box" size="0.1 0.1 0.5"/>
    </body>
  </worldbody>
</mujoco>"#;
    // The arm touches its static base (MuJoCo filters a parent only when it moves) and the
    // static post; the hand (behind two joints) never touches the arm, its parent, but touches
    // the base and the post; the base and the post, both fixed to the world, never touch; the
    // decorative second plane (touching nothing) is passed over.
    let m: Articulations<f64> = mjcf::parse(xml).unwrap().builder.finalize().unwrap();
    assert_eq!((m.capsule_pairs.len(), m.box_pairs.len()), (0, 4));
    // Excluding the arm and the base removes that pair only.
    let m: Articulations<f64> = mjcf::parse(&xml.replace(
        "</worldbody>",
        r#"</worldbody><contact><exclude body1="arm" body2="base"/></contact>"#,
    ))
    .unwrap()
    .builder
    .finalize()
    .unwrap();
    assert_eq!(m.box_pairs.len(), 3);

    // MuJoCo's filterparent is by welds: an arm with two joints on a moving torso never
    // touches the torso nor a plate welded to the torso (declared after the arm), nor does a
    // hand welded to the arm; both touch a ball on a joint of its own under the torso.
    let xml = r#"<mujoco>
  <worldbody>
    <body name="torso" pos="0 0 1">
      <freejoint/>
      <geom type="box" size="0.2 0.2 0.05"/>
      <body name="arm" pos="0.2 0 0">
        <joint type="hinge" axis="0 1 0"/>
        <joint type="hinge" axis="1 0 0"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.05"/>
        <body name="hand" pos="0.3 0 0">
          <geom type="sphere" size="0.05"/>
        </body>
      </body>
      <body name="plate" pos="0.3 0 -0.1">
        <geom type="box" size="0.1 0.1 0.02"/>
      </body>
      <body name="ball" pos="0.3 0 -0.3">
        <joint type="slide" axis="0 0 1"/>
        <geom type="sphere" size="0.05"/>
      </body>
    </body>
  </worldbody>
</mujoco>"#;
    let m: Articulations<f64> = mjcf::parse(xml).unwrap().builder.finalize().unwrap();
    // The arm and the ball, the hand and the ball (two segment pairs); no box pair (the torso
    // and the plate are one weld, the parent of the arm's and of the ball's).
    assert_eq!((m.capsule_pairs.len(), m.box_pairs.len()), (2, 0));
}

#[test]
fn a_builder_added_to_another_keeps_its_contact_settings() {
    // An MJCF robot without a plane: its links touch each other, and there is no floor.
    let xml = r#"<mujoco><worldbody>
    <body name="a"><freejoint/><geom type="sphere" size="0.1"/></body>
    <body name="b" pos="0.15 0 0"><freejoint/><geom type="sphere" size="0.1"/></body>
  </worldbody></mujoco>"#;
    let robot = mjcf::parse(xml).unwrap().builder;
    assert_eq!(robot.ground_filter, ContactFilter::NONE);
    let mut scene = ArticulationBuilder::new();
    scene.add_builder(&robot);
    assert_eq!(scene.ground_filter, ContactFilter::NONE);
    let m: Articulations<f64> = scene.finalize().unwrap();
    assert_eq!((m.capsule_pairs.len(), m.contact_link.len()), (1, 0));
    // Replicated worlds keep the exclusions of each.
    let xml = xml.replace(
        "</worldbody>",
        r#"</worldbody><contact><exclude body1="a" body2="b"/></contact>"#,
    );
    let robot = mjcf::parse(&xml).unwrap().builder;
    let m: Articulations<f64> = robot.replicate(3).finalize().unwrap();
    assert_eq!(m.capsule_pairs.len(), 0);
    let m: Articulations<f64> = robot.replicate(3).worlds_in(1..3).finalize().unwrap();
    assert_eq!(m.capsule_pairs.len(), 0);
}

#[test]
fn friction_is_per_shape_and_the_larger_of_a_contacts_two_as_in_mujoco() {
    // MJCF: the floor 0.5, a's sphere 0.2, the child's capsule MuJoCo's default 1, b's box 1.5.
    let m = two_balls(
        r#"friction="0.5 0.005 0.0001""#,
        r#"friction="0.2""#,
        r#"friction="1.5 0.1""#,
        "",
    );
    // Against the floor: a's sphere max(0.5, 0.2), the capsule's ends 1, the box's corners 1.5.
    let mut floor = vec![0.5, 1.0, 1.0];
    floor.extend([1.5; 8]);
    assert_eq!(m.contact_mu.to_vec(), floor);
    // Between links: both pairs are with the box.
    assert_eq!(m.box_pair_mu.to_vec(), vec![1.5, 1.5]);
    let m = two_balls("", r#"friction="0.2""#, r#"friction="0.3""#, "");
    assert_eq!(m.box_pair_mu.to_vec(), vec![0.3, 1.0]);
    // A negative friction is an error naming the geom's line.
    let e = mjcf::parse(&two_balls_text("", r#"friction="-1""#, "").replace("CONTACT", ""))
        .unwrap_err();
    assert!(
        e.to_string().contains("friction") && e.line == Some(6),
        "{e}"
    );

    // The builder: a shape without friction has the ground's; one with its own, the larger.
    let slide = |ground_mu: f64, own: Option<f64>| -> Articulations<f64> {
        let mut b = ArticulationBuilder::new();
        b.ground = Some(GroundContact {
            mu: ground_mu,
            ..GroundContact::default()
        });
        let half = Vec3::new(0.1, 0.1, 0.1);
        let z = 0.1 - 9.81 / 4e4; // resting on its four lower corners
        let l = b.add_link(
            "box",
            None,
            Joint::free().initial(&[0.0, 0.0, z, 0.0, 0.0, 0.0, 1.0]),
            Inertial::cuboid(1.0, half, Vec3::zeros()),
        );
        let k = b.add_contact_box(l, &Pose::identity(), half);
        if let Some(mu) = own {
            b.set_contact_friction(k, mu);
        }
        b.finalize().unwrap()
    };
    // Thrown along x at 1 m/s for `steps` ms: it slides `v^2 / (2 mu g)`.
    let throw = |m: &Articulations<f64>, steps: usize, tape: &mut Tape| -> Array<f64> {
        let mut qd = vec![0.0; 6];
        qd[0] = 1.0;
        let mut s = ArticulationState {
            q: Array::from_vec(m.q0.clone()),
            qd: Array::from_vec(qd),
        };
        for _ in 0..steps {
            s = m.step(tape, &s, None, 1e-3).unwrap();
        }
        s.q
    };
    let distance = |m: &Articulations<f64>, tape: &mut Tape| throw(m, 400, tape);
    let own = slide(0.1, Some(0.4));
    assert_eq!(own.contact_mu.to_vec(), vec![0.4; 8]);
    assert_eq!(slide(0.6, Some(0.4)).contact_mu.to_vec(), vec![0.6; 8]);
    let x = distance(&own, &mut Tape::new()).get(0);
    let same = distance(&slide(0.4, None), &mut Tape::new()).get(0);
    assert_eq!(x.to_bits(), same.to_bits(), "0.4 its own or the ground's");
    let expected = 1.0 / (2.0 * 0.4 * 9.81);
    assert!(
        (x - expected).abs() < 0.05 * expected,
        "slid {x} m, Coulomb's law gives {expected} m"
    );
    // Invalid: an error naming the shape.
    let mut b = ArticulationBuilder::new();
    let l = b.add_link(
        "l",
        None,
        Joint::free(),
        Inertial::sphere(1.0, 0.1, Vec3::zeros()),
    );
    let k = b.add_contact_sphere(l, Vec3::zeros(), 0.1);
    b.set_contact_friction(k, f64::NAN);
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(
        e.contains("contact shape 0") && e.contains("friction"),
        "{e}"
    );

    // The gradient of the distance with respect to the contacts' friction: against central
    // differences, and forward mode against reverse mode. (Stopped mid-slide: 200 steps.)
    let model = slide(0.4, None);
    let run = |mu: f64, tape: &mut Tape| {
        let mut m = model.clone();
        m.contact_mu = Array::from_vec(vec![mu; 8]).requires_grad();
        let q = throw(&m, 200, tape);
        (m.contact_mu, q)
    };
    let mut tape = Tape::new();
    let (mu, q) = run(0.4, &mut tape);
    let mut w = vec![0.0; 7];
    w[0] = 1.0;
    let g: f64 = tape.vjp(&[&q], &w, &[&mu]).unwrap().iter().sum();
    let f = |mu: f64| run(mu, &mut Tape::new()).1.get(0);
    let fd = (f(0.4 + 1e-6) - f(0.4 - 1e-6)) / 2e-6;
    assert!(fd < -0.01, "more friction, less sliding: {fd}");
    assert!(
        (g - fd).abs() < 1e-5 * fd.abs(),
        "reverse {g} vs differences {fd}"
    );
    let jv = tape.jvp(&[&mu], &[1.0; 8], &[&q]).unwrap();
    assert!(
        (jv[0] - g).abs() < 1e-9 * g.abs(),
        "forward {} vs reverse {g}",
        jv[0]
    );
}

/// A random unit quaternion.
fn rand_quat(rng: &mut Rng) -> Quat<f64> {
    let q = Quat::new(
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
    );
    q / q.norm()
}

/// The exact depth along `n` of the deepest point of an ellipsoid (semi-axes `a`, frame `q`)
/// or of cylinder contact `variant`'s cap rim (radius `size.x`, half-length `size.y`), below
/// the shape's centre: `min over the surface (or rim) of n . x`.
fn exact_depth(variant: u32, q: Quat<f64>, size: Vec3<f64>, n: Vec3<f64>) -> f64 {
    let m = (q.conjugate() * Quat::new(0.0, n.x, n.y, n.z) * q).imag();
    if variant == 0 {
        -size.component_mul(&m).norm()
    } else {
        let z = if variant > 4 { -size.y } else { size.y };
        z * m.z - size.x * (m.x * m.x + m.y * m.y).sqrt()
    }
}

#[test]
fn cylinder_and_ellipsoid_contact_points_are_deepest_with_right_derivatives() {
    use adflex_kernels::articulation::contact::support_offset;
    use adflex_kernels::contact::shapes::sdf_cylinder;
    use adflex_runtime::DiffFunc;
    let mut rng = Rng(11);
    let h = 1e-6;
    let mut bad = Vec::new();
    for case in 0..300 {
        let q = rand_quat(&mut rng);
        let size = Vec3::new(
            rng.uniform(0.05, 0.5),
            rng.uniform(0.05, 0.5),
            rng.uniform(0.05, 0.5),
        );
        let mut n = rand3(&mut rng, 1.0).normalize();
        if case % 5 == 0 {
            // Within 5 degrees of the cylinder's axis (either way), where the weights blend.
            let axis = Vec3::new(0.0, 0.0, if case % 10 == 0 { 1.0 } else { -1.0 });
            let near = axis + rand3(&mut rng, 0.06);
            n = (q * Quat::new(0.0, near.x, near.y, near.z) * q.conjugate())
                .imag()
                .normalize();
        }
        for variant in 0..9u32 {
            let o = support_offset::call(variant, q, size, n);
            let x = o.xyz();
            let m = (q.conjugate() * Quat::new(0.0, n.x, n.y, n.z) * q).imag();
            let tilt = (m.x * m.x + m.y * m.y).sqrt();
            // The deepest points, to within the easing near upright, weighing 1 - u (the
            // ellipsoid's 1); the others fixed on the rim, weighing u.
            let u = (1.0 - 130.0 * tilt * tilt).max(0.0).powi(2);
            if matches!(variant, 0 | 1 | 5) {
                let weight = if variant == 0 { 1.0 } else { 1.0 - u };
                assert!((o.w - weight).abs() < 1e-12, "case {case}: weight {}", o.w);
                let err = n.dot(&x) - exact_depth(variant, q, size, n);
                let bound = if variant == 0 {
                    1e-12
                } else {
                    size.x * 2.1e-6 / tilt
                };
                assert!(
                    (-1e-12..=bound).contains(&err),
                    "case {case} variant {variant}: {err} above the deepest (tilt {tilt})"
                );
            } else {
                let local = (q.conjugate() * Quat::new(0.0, x.x, x.y, x.z) * q).imag();
                let angle = [0.0f64, 120.0, 240.0][(variant as usize - 2) % 4].to_radians();
                let z = if variant > 4 { -size.y } else { size.y };
                let fixed = Vec3::new(size.x * angle.cos(), size.x * angle.sin(), z);
                assert!(
                    (local - fixed).norm() < 1e-12 && (o.w - u).abs() < 1e-12,
                    "case {case} variant {variant}: {local:?} weighing {}",
                    o.w
                );
            }
            // Reverse mode against central differences, forward against reverse, along a
            // random direction of (q, size, n).
            let (dq, ds, dn) = (
                rand_quat(&mut rng),
                rand3(&mut rng, 0.1),
                rand3(&mut rng, 1.0),
            );
            let w = rand3(&mut rng, 1.0).push(rng.uniform(-1.0, 1.0));
            let f = |e: f64| {
                w.dot(&support_offset::call(
                    variant,
                    q + dq * e,
                    size + ds * e,
                    n + dn * e,
                ))
            };
            let fd = (f(h) - f(-h)) / (2.0 * h);
            let (_, gq, gs, gn) = DiffFunc::adjoint(&support_offset, (variant, q, size, n), w);
            let reverse = gq.coords.dot(&dq.coords) + gs.dot(&ds) + gn.dot(&dn);
            if (reverse - fd).abs() > 1e-6 * fd.abs().max(1.0) {
                bad.push(format!(
                    "case {case} variant {variant}: reverse {reverse} vs {fd}"
                ));
            }
            let (_, t) = DiffFunc::tangent(&support_offset, (variant, q, size, n), (0, dq, ds, dn));
            assert!(
                (w.dot(&t) - reverse).abs() < 1e-10 * reverse.abs().max(1.0),
                "case {case} variant {variant}: forward {} vs reverse {reverse}",
                w.dot(&t)
            );
        }
        // The particles' cylinder SDF (along x): the distance against dense sampling of the
        // surface outside, its normal against the SDF's differences.
        let p = rand3(&mut rng, 0.8);
        let g = sdf_cylinder::call(p, size);
        let (r, l) = (size.x, size.y);
        let rho = (p.y * p.y + p.z * p.z).sqrt();
        let outside = Vec3::new((p.x.abs() - l).max(0.0), 0.0, (rho - r).max(0.0)).norm();
        let inside = (p.x.abs() - l).max(rho - r).min(0.0);
        assert!(
            (g.w - (outside + inside)).abs() < 1e-12,
            "case {case}: sdf {} vs {}",
            g.w,
            outside + inside
        );
        let grad = Vec3::from_fn(|k, _| {
            let e = Vec3::from_fn(|j, _| if j == k { h } else { 0.0 });
            (sdf_cylinder::call(p + e, size).w - sdf_cylinder::call(p - e, size).w) / (2.0 * h)
        });
        assert!(
            (grad - g.xyz()).norm() < 1e-6,
            "case {case}: normal {:?} vs the SDF's slope {grad:?}",
            g.xyz()
        );
    }
    // Upright (the deepest direction undefined): finite, and every rim point equally deep.
    let up: Vec3<f64> = Vec3::new(0.2, 0.3, 0.0);
    for variant in 1..9u32 {
        let x = support_offset::call(variant, Quat::identity(), up, Vec3::z());
        let (_, gq, gs, gn) = DiffFunc::adjoint(
            &support_offset,
            (variant, Quat::identity(), up, Vec3::z()),
            adflex_runtime::Vec4::new(1.0, 1.0, 1.0, 1.0),
        );
        assert!(
            x.iter()
                .chain(gq.coords.iter())
                .chain(gs.iter())
                .chain(gn.iter())
                .all(|v| v.is_finite()),
            "upright variant {variant}: {x:?} {gq:?} {gs:?} {gn:?}"
        );
        // Upright the deepest point is at the cap's centre and weighs nothing.
        let z = if variant > 4 { -0.3 } else { 0.3 };
        let (rim, weight) = match variant {
            1 | 5 => (0.0, 0.0),
            _ => (0.2, 1.0),
        };
        assert!(
            (x.z - z).abs() < 1e-15 && (x.xy().norm() - rim).abs() < 1e-12 && x.w == weight,
            "upright variant {variant}: {x:?}"
        );
    }
    assert!(bad.is_empty(), "{}", bad.join("\n"));
}

/// A 1 kg free body at `x` turned by `rot`, with one contact shape (a cylinder of radius 0.1
/// and half-length 0.15, or an ellipsoid of semi-axes 0.1, 0.15, 0.2) and its inertia, over
/// the default ground; contact between links off.
fn round_body(shape: &str, x: Vec3<f64>, rot: Quat<f64>) -> Articulations<f64> {
    use adflex_kernels::articulation::contact::GeomShape;
    let (geom, inertia) = match shape {
        "cylinder" => {
            let (r, h): (f64, f64) = (0.1, 0.15);
            let side = (3.0 * r * r + 4.0 * h * h) / 12.0;
            (
                GeomShape::Cylinder(r, h),
                Vec3::new(side, side, r * r / 2.0),
            )
        }
        _ => {
            let a = Vec3::new(0.1, 0.15, 0.2);
            let i = |p: f64, q: f64| (p * p + q * q) / 5.0;
            (
                GeomShape::Ellipsoid(a),
                Vec3::new(i(a.y, a.z), i(a.x, a.z), i(a.x, a.y)),
            )
        }
    };
    let mut b = ArticulationBuilder::new();
    b.ground = Some(GroundContact::default());
    let l = b.add_link(
        shape,
        None,
        Joint::free().initial(&[x.x, x.y, x.z, rot.i, rot.j, rot.k, rot.w]),
        Inertial::new(
            1.0,
            Vec3::zeros(),
            nalgebra::Matrix3::from_diagonal(&inertia),
        ),
    );
    b.add_contact_shape(l, &Pose::identity(), &geom).unwrap();
    b.finalize().unwrap()
}

fn turn(axis: Vec3<f64>, angle: f64) -> Quat<f64> {
    *nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle)
        .quaternion()
}

/// Steps `model` from `q` with velocities `qd` for `steps` steps of 1 ms; the heights of the
/// body's centre at every step and the last state.
fn roll(model: &Articulations<f64>, qd: &[f64], steps: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let mut s = model.state();
    s.qd = Array::from_vec(qd.to_vec());
    let mut heights = Vec::new();
    for _ in 0..steps {
        s = model.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
        heights.push(s.q.get(2));
    }
    (heights, s.q.to_vec(), s.qd.to_vec())
}

#[test]
fn cylinders_and_ellipsoids_rest_and_roll_on_the_ground() {
    let weight = 9.81 / 1e4; // the sinking of one contact under the body's weight
                             // (shape, orientation, resting height of the centre with its contacts sharing the weight)
    let cases = [
        // Upright on a cap: three rim points.
        ("cylinder", Quat::identity(), 0.15 - weight / 3.0),
        // On its side: the two caps' deepest points.
        (
            "cylinder",
            turn(Vec3::x(), std::f64::consts::FRAC_PI_2),
            0.1 - weight / 2.0,
        ),
        // An ellipsoid on its shortest semi-axis (x turned down), by one point.
        (
            "ellipsoid",
            turn(Vec3::y(), std::f64::consts::FRAC_PI_2),
            0.1 - weight,
        ),
    ];
    for (shape, rot, height) in cases {
        let model = round_body(shape, Vec3::new(0.3, -0.2, height + 0.02), rot);
        let (h, q, qd) = roll(&model, &[0.0; 6], 2000);
        assert!(
            (h[1999] - height).abs() < 5e-5,
            "{shape} {rot:?}: rests at {} instead of {height}",
            h[1999]
        );
        // Still, and as it was turned. (The smoothed friction's steep slope at rest makes
        // the velocities of a tall body alternate in sign from step to step, by about 1e-3:
        // the position does not move.)
        let r = Quat::new(q[6], q[3], q[4], q[5]);
        let (_, later, _) = roll(&model, &[0.0; 6], 2500);
        let drift = q
            .iter()
            .zip(&later)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            drift < 2e-5,
            "{shape}: moved by {drift} in 0.5 s; at {qd:?}"
        );
        assert!(
            (r.coords - rot.coords).norm() < 1e-3,
            "{shape}: turned to {r:?}"
        );
    }
    // A cylinder on its side rolls along x at 1 m/s without bumps (its contacts at 120
    // degrees from the deepest never reach the ground) and without slipping.
    let side = turn(Vec3::x(), std::f64::consts::FRAC_PI_2);
    let rest = 0.1 - weight / 2.0;
    let model = round_body("cylinder", Vec3::new(0.0, 0.0, rest), side);
    // The body's z axis is the world's -y: spinning at -10 rad/s about it rolls along +x.
    let (h, q, qd) = roll(&model, &[1.0, 0.0, 0.0, 0.0, 0.0, -10.0], 1000);
    let wobble = h.iter().fold(0.0f64, |m, z| m.max((z - rest).abs()));
    // (The free joint's linear velocity is in the body's frame.)
    let speed = world_velocity(&q, &qd, 0).x;
    assert!(
        wobble < 2e-5,
        "the rolling cylinder's height wanders by {wobble}"
    );
    assert!(
        (q[0] - 1.0).abs() < 0.02 && (speed - 1.0).abs() < 0.02 && (qd[5] + 10.0).abs() < 0.2,
        "rolled to x = {} at {} m/s, spinning at {}",
        q[0],
        speed,
        qd[5]
    );
}

/// Drops a tilted, spinning cylinder or ellipsoid on the ground; returns the initial
/// velocities (requiring gradients) and the last state.
fn tumble(
    model: &Articulations<f64>,
    spin: f64,
    tape: &mut Tape,
) -> (Array<f64>, Array<f64>, Array<f64>) {
    let qd = Array::from_vec(vec![0.3, 0.1, -0.2, spin, -0.5, 1.0]).requires_grad();
    let mut s = ArticulationState {
        q: Array::from_vec(model.q0.clone()),
        qd: qd.clone(),
    };
    for _ in 0..300 {
        s = model.step(tape, &s, None, 1e-3).unwrap();
    }
    (qd, s.q, s.qd)
}

#[test]
fn cylinder_and_ellipsoid_ground_contact_gradients_match_differences() {
    let tilt = turn(Vec3::new(1.0, 0.4, 0.0), 0.6);
    for shape in ["cylinder", "ellipsoid"] {
        // Its lowest point 1.23 cm above the ground: in contact from about step 50.
        let model = round_body(shape, Vec3::new(0.0, 0.0, 0.2), tilt);
        let mut tape = Tape::new();
        let (qd0, q, qd) = tumble(&model, 2.0, &mut tape);
        let low = q.get(2);
        assert!(low < 0.19, "{shape}: never fell ({low})");
        let w: Vec<f64> = (0..13).map(|k| ((k as f64) * 0.7 + 0.3).sin()).collect();
        let g = tape.vjp(&[&q, &qd], &w, &[&qd0]).unwrap();
        let loss = |spin: f64| {
            let (_, q, qd) = tumble(&model, spin, &mut Tape::new());
            let x: Vec<f64> = q.to_vec().into_iter().chain(qd.to_vec()).collect();
            x.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        let fd = (loss(2.0 + 1e-6) - loss(2.0 - 1e-6)) / 2e-6;
        assert!(
            (g[3] - fd).abs() < 1e-4 * fd.abs().max(1e-2),
            "{shape}: reverse {} vs differences {fd}",
            g[3]
        );
        let mut dir = vec![0.0; 6];
        dir[3] = 1.0;
        let jv = tape.jvp(&[&qd0], &dir, &[&q, &qd]).unwrap();
        let forward: f64 = jv.iter().zip(&w).map(|(a, b)| a * b).sum();
        assert!(
            (forward - g[3]).abs() < 1e-9 * fd.abs().max(1e-2),
            "{shape}: forward {forward} vs reverse {}",
            g[3]
        );
    }
}

#[test]
fn cylinders_and_ellipsoids_touching_other_links_are_refused_by_name() {
    use adflex_kernels::articulation::{contact::GeomShape, urdf};
    let mut b = ArticulationBuilder::new();
    space(&mut b);
    free_body(&mut b, "a", Vec3::zeros(), "box");
    let wheel = b.add_link(
        "wheel",
        None,
        Joint::free(),
        Inertial::sphere(1.0, 0.1, Vec3::zeros()),
    );
    b.add_contact_shape(wheel, &Pose::identity(), &GeomShape::Cylinder(0.1, 0.05));
    let e = b.clone().finalize::<f64>().unwrap_err().to_string();
    assert!(
        e.contains("Cylinder")
            && e.contains("\"wheel\"")
            && e.contains("\"a\"")
            && e.contains("exclude"),
        "{e}"
    );
    // Excluded, or with link contact off, it touches the ground only.
    let mut ok = b.clone();
    ok.exclude_contact(b.find("a").unwrap(), wheel);
    let m: Articulations<f64> = ok.finalize().unwrap();
    assert_eq!((m.support_link.len(), m.capsule_pairs.len()), (8, 0));
    // Bad sizes name the shape.
    let mut bad = ArticulationBuilder::new();
    let l = bad.add_link(
        "egg",
        None,
        Joint::free(),
        Inertial::sphere(1.0, 0.1, Vec3::zeros()),
    );
    bad.add_contact_shape(
        l,
        &Pose::identity(),
        &GeomShape::Ellipsoid(Vec3::new(0.1, 0.0, 0.1)),
    );
    let e = bad.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("contact shape 0") && e.contains("egg"), "{e}");

    // MJCF: a cylinder on the floor stands on it; one that would touch another body's geom
    // is refused, and excluded it loads.
    let xml = |other: &str, contact: &str| {
        format!(
            r#"<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>
            <body name="can" pos="0 0 0.2"><freejoint/>
              <geom type="cylinder" size="0.05 0.1" mass="1"/></body>
            {other}</worldbody>{contact}</mujoco>"#
        )
    };
    let m: Articulations<f64> = mjcf::parse(&xml("", ""))
        .unwrap()
        .builder
        .finalize()
        .unwrap();
    let (h, _, _) = roll(&m, &[0.0; 6], 1500);
    // (MJCF's ground lets the robot's weight sink one contact by 5 mm; three share it.)
    let stands = 0.1 - 0.005 / 3.0;
    assert!(
        (h[1499] - stands).abs() < 5e-5,
        "the can stands at {}",
        h[1499]
    );
    // (A sphere touches it.)
    let sphere =
        r#"<body name="ball" pos="0.5 0 0.2"><freejoint/><geom type="sphere" size="0.05"/></body>"#;
    let m: Articulations<f64> = mjcf::parse(&xml(sphere, ""))
        .unwrap()
        .builder
        .finalize()
        .unwrap();
    assert_eq!(m.cylinder_pairs.len(), 1);
    let ball = r#"<body name="ball" pos="0.5 0 0.2"><freejoint/>
        <geom type="box" size="0.05 0.05 0.05"/></body>"#;
    let e = mjcf::parse(&xml(ball, ""))
        .unwrap()
        .builder
        .finalize::<f64>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("\"can\"") && e.contains("\"ball\""), "{e}");
    let excluded = xml(
        ball,
        r#"<contact><exclude body1="can" body2="ball"/></contact>"#,
    );
    assert!(mjcf::parse(&excluded)
        .unwrap()
        .builder
        .finalize::<f64>()
        .is_ok());

    // A ball dropped off-centre on a worldbody post rests on its cap (MJCF's ground sinks the
    // robot's weight by 5 mm).
    let post = r#"<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>
        <geom type="cylinder" pos="0 0 0.25" size="0.1 0.25"/>
        <body name="ball" pos="0.03 0.01 0.6"><freejoint/><geom type="sphere" size="0.05"/></body>
        </worldbody></mujoco>"#;
    let m: Articulations<f64> = mjcf::parse(post).unwrap().builder.finalize().unwrap();
    let (h, q, _) = roll(&m, &[0.0; 6], 1500);
    assert!(
        (h[1499] - 0.545).abs() < 1e-4 && (q[0] - 0.03).abs() < 1e-3,
        "the ball rests at {:?}",
        &q[..3]
    );

    // URDF: a cylinder collision is a contact shape.
    let urdf_text = r#"<robot name="r"><link name="base"><inertial><mass value="1"/>
        <inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
        <collision><geometry><cylinder radius="0.1" length="0.3"/></geometry></collision>
        </link></robot>"#;
    let opts = urdf::UrdfOptions {
        collisions: true,
        floating_base: true,
        ..Default::default()
    };
    let b = urdf::parse(urdf_text, &opts).unwrap();
    assert_eq!(b.contact_shapes()[0].shape, GeomShape::Cylinder(0.1, 0.15));
}
