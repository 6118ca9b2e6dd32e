//! Every kernel of the crate, in f64 on a random non-degenerate configuration: the adjoint
//! against central finite differences (every scalar of every array the kernel reads) and the
//! tangent against the adjoint (dot-product test).

use crate::common;

use adflex_kernels::constraints::{
    apply_corrections, distance_constraint_energy, solve_distance_constraints,
    velocity_from_positions,
};
use adflex_kernels::contact::ground::{eval_ground, ground_energy, ground_energy_radii};
use adflex_kernels::contact::particle::{
    eval_particle_contact, find_pairs, particle_contact_energy, particle_contact_energy_radii,
};
use adflex_kernels::contact::shapes::{eval_shape_contact, shape_contact_energy, ShapeKind};
use adflex_kernels::forces::bending::{bending_edges, bending_energy, eval_bending};
use adflex_kernels::forces::fem_tet::{eval_tetrahedra, tetrahedron_energy};
use adflex_kernels::forces::fem_tri::{eval_triangles, triangle_energy};
use adflex_kernels::forces::particle::{accelerations, add_forces, add_gravity_force, eval_drag};
use adflex_kernels::forces::spring::{eval_springs, spring_energy};
use adflex_kernels::integrators::semi_implicit::integrate_particles;
use adflex_kernels::rigid::{body_kinetic_energy, eval_body_ground, integrate_bodies};
use adflex_kernels::scenes::cloth::displacement_loss;
use adflex_kernels::ModelBuilder;
use adflex_runtime::{Array, Mat33, Quat, Vec3};
use common::{arr, check_kernel, Rng};

fn zeros3(n: usize, name: &str) -> Array<Vec3<f64>> {
    Array::zeros(n).named(name)
}

#[test]
fn springs() {
    let mut r = Rng(11);
    let x = arr(r.vec3s(6, 0.0, 1.0), "x");
    let v = arr(r.vec3s(6, -1.0, 1.0), "v");
    let pairs = arr(
        vec![
            [0u32, 1],
            [1, 2],
            [2, 3],
            [3, 4],
            [4, 5],
            [5, 0],
            [0, 3],
            [1, 4],
        ],
        "pairs",
    );
    let rest = arr(r.scalars(8, 0.2, 1.0), "rest");
    let ke = arr(r.scalars(8, 10.0, 50.0), "ke");
    let kd = arr(r.scalars(8, 0.1, 1.0), "kd");
    let f = zeros3(6, "f");
    check_kernel!(
        "eval_springs",
        eval_springs,
        8,
        (&x, &v, &pairs, &rest, &ke, &kd, &f),
        inputs = [x, v, rest, ke, kd],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    check_kernel!(
        "spring_energy",
        spring_energy,
        8,
        (&x, &pairs, &rest, &ke, &two_worlds(&x), &e),
        inputs = [x, rest, ke],
        outputs = [e]
    );
}

/// A 3x3 grid of particles, randomly displaced, with its triangles.
fn bumpy_grid(r: &mut Rng) -> (Vec<Vec3<f64>>, Vec<[u32; 3]>) {
    let mut x = Vec::new();
    for i in 0..3 {
        for j in 0..3 {
            x.push(Vec3::new(i as f64 * 0.5, 0.0, j as f64 * 0.5) + r.vec3(-0.15, 0.15));
        }
    }
    let mut tris = Vec::new();
    for i in 0..2u32 {
        for j in 0..2u32 {
            let (a, b, c, d) = (
                i * 3 + j,
                (i + 1) * 3 + j,
                (i + 1) * 3 + j + 1,
                i * 3 + j + 1,
            );
            tris.push([a, b, c]);
            tris.push([a, c, d]);
        }
    }
    (x, tris)
}

#[test]
fn bending() {
    let mut r = Rng(12);
    let (xs, tris) = bumpy_grid(&mut r);
    let quads = bending_edges(&tris);
    let m = quads.len();
    let x = arr(xs, "x");
    let v = arr(r.vec3s(9, -1.0, 1.0), "v");
    let quads = arr(quads, "quads");
    let rest = arr(r.scalars(m, -0.3, 0.3), "rest");
    let ke = arr(r.scalars(m, 0.5, 1.5), "ke");
    let kd = arr(r.scalars(m, 0.1, 0.5), "kd");
    let f = zeros3(9, "f");
    check_kernel!(
        "eval_bending",
        eval_bending,
        m,
        (&x, &v, &quads, &rest, &ke, &kd, &f),
        inputs = [x, v, rest, ke, kd],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    check_kernel!(
        "bending_energy",
        bending_energy,
        m,
        (&x, &quads, &rest, &ke, &two_worlds(&x), &e),
        inputs = [x, rest, ke],
        outputs = [e]
    );
}

#[test]
fn ground_contact() {
    let mut r = Rng(13);
    let n = 10;
    let x = arr(
        (0..n)
            .map(|_| {
                Vec3::new(
                    r.uniform(-1.0, 1.0),
                    r.uniform(-0.05, 0.05),
                    r.uniform(-1.0, 1.0),
                )
            })
            .collect(),
        "x",
    );
    let v = arr(r.vec3s(n, -1.0, 1.0), "v");
    let f = zeros3(n, "f");
    let up = Vec3::new(0.0, 1.0, 0.0);
    check_kernel!(
        "eval_ground",
        eval_ground,
        n,
        (&x, &v, up, 0.0, 0.01, 1000.0, 1.0, 1.0, 0.0, 0.5, 0.0, &f),
        inputs = [x, v],
        outputs = [f]
    );
    // Damping in contact only (`Ground::damp_approach = false`), ramped in over 2 cm (`damping_depth`).
    check_kernel!(
        "eval_ground (damping in contact only, ramped over 2 cm)",
        eval_ground,
        n,
        (&x, &v, up, 0.0, 0.01, 1000.0, 1.0, 0.0, 2e-2, 0.5, 0.0, &f),
        inputs = [x, v],
        outputs = [f]
    );
    // A tilted plane with an offset.
    let tilt = Vec3::new(0.1, 1.0, -0.2).normalize();
    check_kernel!(
        "eval_ground (tilted)",
        eval_ground,
        n,
        (&x, &v, tilt, -0.01, 0.01, 1000.0, 1.0, 1.0, 0.0, 0.5, 0.0, &f),
        inputs = [x, v],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    check_kernel!(
        "ground_energy",
        ground_energy,
        n,
        (&x, tilt, -0.01, 0.01, 1000.0, &two_worlds(&x), &e),
        inputs = [x],
        outputs = [e]
    );
    let radii = arr(r.scalars(n, 0.0, 0.03), "radius");
    check_kernel!(
        "ground_energy_radii",
        ground_energy_radii,
        n,
        (&x, up, 0.0, &radii, 1000.0, &two_worlds(&x), &e),
        inputs = [x, radii],
        outputs = [e]
    );
}

#[test]
fn particle_forces_and_integrator() {
    let mut r = Rng(14);
    let n = 7;
    let x = arr(r.vec3s(n, -1.0, 1.0), "x");
    let v = arr(r.vec3s(n, -1.0, 1.0), "v");
    let f = arr(r.vec3s(n, -1.0, 1.0), "f");
    let w = arr(r.scalars(n, 0.5, 2.0), "inv_mass");
    // Two worlds' gravity, the particles alternating between them.
    let g = arr(
        vec![Vec3::new(0.3, -9.8, 0.1), Vec3::new(-0.2, -1.6, 0.4)],
        "gravity",
    );
    let world = Array::from_vec((0..n as u32).map(|i| i % 2).collect());
    let out = zeros3(n, "out");
    check_kernel!(
        "eval_drag",
        eval_drag,
        n,
        (&v, 0.3, Vec3::new(1.0, 0.0, 0.5), &out),
        inputs = [v],
        outputs = [out]
    );
    check_kernel!(
        "add_forces",
        add_forces,
        n,
        (&f, &out),
        inputs = [f],
        outputs = [out]
    );
    check_kernel!(
        "accelerations",
        accelerations,
        n,
        (&f, &w, &g, &world, &out),
        inputs = [f, w, g],
        outputs = [out]
    );
    check_kernel!(
        "add_gravity_force",
        add_gravity_force,
        n,
        (&w, &g, &world, &out),
        inputs = [w, g],
        outputs = [out]
    );
    let (x1, v1) = (zeros3(n, "x1"), zeros3(n, "v1"));
    check_kernel!(
        "integrate_particles",
        integrate_particles,
        n,
        (&x, &v, &f, &w, &g, &world, 0.01, &x1, &v1),
        inputs = [x, v, f, w, g],
        outputs = [x1, v1]
    );
    let x0 = arr(r.vec3s(n, -1.0, 1.0), "x0");
    let loss: Array<f64> = Array::zeros(1);
    check_kernel!(
        "displacement_loss",
        displacement_loss,
        n,
        (&x, &x0, Vec3::new(0.0, -0.1, 0.0), 0.5, &loss),
        inputs = [x, x0],
        outputs = [loss]
    );
}

#[test]
fn triangle_membranes() {
    let mut r = Rng(15);
    let (rest_x, tris) = bumpy_grid(&mut r);
    let mut b = ModelBuilder::<f64>::new();
    for p in &rest_x {
        b.add_particle(*p, Vec3::zeros(), 1.0);
    }
    for t in &tris {
        b.add_triangle_fem(
            t[0],
            t[1],
            t[2],
            r.uniform(50.0, 100.0),
            r.uniform(20.0, 80.0),
            r.uniform(0.5, 2.0),
        );
    }
    let m = b.finalize();
    let t = m.tri_fem().unwrap();
    let x = arr(rest_x.iter().map(|p| p + r.vec3(-0.1, 0.1)).collect(), "x");
    let v = arr(r.vec3s(9, -1.0, 1.0), "v");
    let f = zeros3(9, "f");
    let nt = t.len();
    check_kernel!(
        "eval_triangles",
        eval_triangles,
        nt,
        (&x, &v, &t.tris, &t.dm_inv, &t.area, &t.mu, &t.lambda, &t.kd, &f),
        inputs = [x, v, t.dm_inv, t.area, t.mu, t.lambda, t.kd],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    check_kernel!(
        "triangle_energy",
        triangle_energy,
        nt,
        (
            &x,
            &t.tris,
            &t.dm_inv,
            &t.area,
            &t.mu,
            &t.lambda,
            &two_worlds(&x),
            &e
        ),
        inputs = [x, t.dm_inv, t.area, t.mu, t.lambda],
        outputs = [e]
    );
}

/// Two tetrahedra sharing a face, randomly deformed (builder and arrays).
fn two_tets(r: &mut Rng) -> (adflex_kernels::Model<f64>, Array<Vec3<f64>>) {
    let rest = [
        Vec3::new(0.0, 0.0, 0.0),
        Vec3::new(1.0, 0.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(0.0, 0.0, 1.0),
        Vec3::new(1.0, 1.0, 1.0),
    ];
    let mut b = ModelBuilder::<f64>::new();
    for p in &rest {
        b.add_particle(p + r.vec3(-0.1, 0.1), Vec3::zeros(), 1.0);
    }
    b.add_tet(0, 1, 2, 3, 100.0, 300.0, 1.5);
    b.add_tet(1, 2, 3, 4, 80.0, 200.0, 0.5);
    let m = b.finalize();
    let x = arr(rest.iter().map(|p| p + r.vec3(-0.2, 0.2)).collect(), "x");
    (m, x)
}

#[test]
fn tetrahedra() {
    let mut r = Rng(16);
    let (m, x) = two_tets(&mut r);
    let t = m.tets().unwrap();
    let v = arr(r.vec3s(5, -1.0, 1.0), "v");
    let act = arr(r.scalars(2, -0.2, 0.2), "activation");
    let f = zeros3(5, "f");
    check_kernel!(
        "eval_tetrahedra",
        eval_tetrahedra,
        2,
        (
            &x,
            &v,
            &t.tets,
            &t.dm_inv,
            &t.rest_volume,
            &t.mu,
            &t.lambda,
            &t.kd,
            &act,
            &f
        ),
        inputs = [x, v, t.dm_inv, t.rest_volume, t.mu, t.lambda, t.kd, act],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    check_kernel!(
        "tetrahedron_energy",
        tetrahedron_energy,
        2,
        (
            &x,
            &t.tets,
            &t.dm_inv,
            &t.rest_volume,
            &t.mu,
            &t.lambda,
            &act,
            &two_worlds(&x),
            &e
        ),
        inputs = [x, t.dm_inv, t.rest_volume, t.mu, t.lambda, act],
        outputs = [e]
    );
}

#[test]
fn particle_particle_contact() {
    let mut r = Rng(17);
    let n = 8;
    let radius = 0.2;
    let xs = r.vec3s(n, 0.0, 0.6);
    let pairs = find_pairs(&xs, 2.0 * radius);
    assert!(pairs.len() >= 4, "{pairs:?}");
    let np = pairs.len();
    let x = arr(xs, "x");
    let v = arr(r.vec3s(n, -1.0, 1.0), "v");
    let pairs = arr(pairs, "pairs");
    let f = zeros3(n, "f");
    check_kernel!(
        "eval_particle_contact",
        eval_particle_contact,
        np,
        (&x, &v, &pairs, radius, 1000.0, 1.0, 0.0, 0.5, 0.0, &f),
        inputs = [x, v],
        outputs = [f]
    );
    // The damping ramped in over 2 cm.
    check_kernel!(
        "eval_particle_contact (damping ramped over 2 cm)",
        eval_particle_contact,
        np,
        (&x, &v, &pairs, radius, 1000.0, 1.0, 2e-2, 0.5, 0.0, &f),
        inputs = [x, v],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    check_kernel!(
        "particle_contact_energy",
        particle_contact_energy,
        np,
        (&x, &pairs, radius, 1000.0, &two_worlds(&x), &e),
        inputs = [x],
        outputs = [e]
    );
    let radii = arr(vec![radius; x.len()], "radius");
    check_kernel!(
        "particle_contact_energy_radii",
        particle_contact_energy_radii,
        np,
        (&x, &pairs, &radii, 1000.0, &two_worlds(&x), &e),
        inputs = [x, radii],
        outputs = [e]
    );
}

#[test]
fn shape_contact() {
    let mut r = Rng(18);
    let shapes = [
        (ShapeKind::Sphere { radius: 0.5 }, Vec3::new(0.0, 0.0, 0.0)),
        (
            ShapeKind::Box {
                half_extents: Vec3::new(0.4, 0.3, 0.2),
            },
            Vec3::new(2.0, 0.0, 0.0),
        ),
        (
            ShapeKind::Capsule {
                radius: 0.3,
                half_length: 0.4,
            },
            Vec3::new(-2.0, 0.0, 0.0),
        ),
    ];
    let codes: Vec<_> = shapes.iter().map(|s| s.0.code()).collect();
    let kind = arr(codes.iter().map(|c| c.0).collect(), "kind");
    let size = arr(codes.iter().map(|c| c.1).collect(), "size");
    let pos = arr(shapes.iter().map(|s| s.1).collect(), "pos");
    let rots: Vec<Quat<f64>> = (0..3).map(|_| r.quat()).collect();
    let rot = arr(rots.clone(), "rot");
    // Particles near each shape's surface: inside, outside, on faces, edges and caps.
    let mut xs = Vec::new();
    for _ in 0..4 {
        let d = r.vec3(-1.0, 1.0).normalize();
        xs.push(d * r.uniform(0.45, 0.52));
    }
    let box_local = [
        Vec3::new(0.41, 0.1, 0.05),
        Vec3::new(-0.1, 0.29, 0.02),
        Vec3::new(0.41, 0.305, 0.1),
        Vec3::new(0.1, -0.05, -0.21),
    ];
    for p in box_local {
        xs.push(shapes[1].1 + rots[1].to_rotation_matrix_like(p));
    }
    let cap_local = [
        Vec3::new(0.1, 0.29, 0.0),
        Vec3::new(0.6, 0.1, 0.2),
        Vec3::new(-0.65, -0.1, 0.05),
        Vec3::new(0.0, 0.0, -0.31),
    ];
    for p in cap_local {
        xs.push(shapes[2].1 + rots[2].to_rotation_matrix_like(p));
    }
    let n = xs.len();
    let x = arr(xs, "x");
    let v = arr(r.vec3s(n, -1.0, 1.0), "v");
    let f = zeros3(n, "f");
    check_kernel!(
        "eval_shape_contact",
        eval_shape_contact,
        n * 3,
        (&x, &v, &kind, &pos, &rot, &size, 3usize, 0.02, 1000.0, 1.0, 0.0, 0.5, 0.0, &f),
        inputs = [x, v, pos, rot, size],
        outputs = [f]
    );
    check_kernel!(
        "eval_shape_contact (damping ramped over 2 cm)",
        eval_shape_contact,
        n * 3,
        (&x, &v, &kind, &pos, &rot, &size, 3usize, 0.02, 1000.0, 1.0, 2e-2, 0.5, 0.0, &f),
        inputs = [x, v, pos, rot, size],
        outputs = [f]
    );
    let e: Array<f64> = Array::zeros(2);
    let radii = arr(vec![0.02; n], "radius");
    check_kernel!(
        "shape_contact_energy",
        shape_contact_energy,
        n * 3,
        (
            &x,
            &kind,
            &pos,
            &rot,
            &size,
            3usize,
            &radii,
            1000.0,
            &two_worlds(&x),
            &e
        ),
        inputs = [x, pos, rot, size, radii],
        outputs = [e]
    );
    // Every particle is in contact with its shape.
    assert!(
        f.to_vec().iter().all(|f| f.norm() > 0.0),
        "{:?}",
        f.to_vec()
    );
}

/// Rotates `p` by the unit quaternion (host side, for test setups).
trait RotateLike {
    fn to_rotation_matrix_like(&self, p: Vec3<f64>) -> Vec3<f64>;
}

impl RotateLike for Quat<f64> {
    fn to_rotation_matrix_like(&self, p: Vec3<f64>) -> Vec3<f64> {
        let u = Vec3::new(self.i, self.j, self.k);
        let s = self.w;
        u * 2.0 * u.dot(&p) + p * (s * s - u.dot(&u)) + u.cross(&p) * 2.0 * s
    }
}

fn spd(r: &mut Rng) -> Mat33<f64> {
    let a = Mat33::from_fn(|_, _| r.uniform(-0.3, 0.3));
    a * a.transpose() + Mat33::from_diagonal(&Vec3::new(1.0, 2.0, 3.0))
}

#[test]
fn rigid_bodies() {
    let mut r = Rng(19);
    let nb = 2;
    let bx = arr(
        vec![Vec3::new(0.0, 0.15, 0.0), Vec3::new(1.0, 0.1, 0.0)],
        "body_x",
    );
    let bq = arr((0..nb).map(|_| r.quat()).collect(), "body_q");
    let bv = arr(r.vec3s(nb, -1.0, 1.0), "body_v");
    let bw = arr(r.vec3s(nb, -1.0, 1.0), "body_w");
    let mut cb = Vec::new();
    let mut cp = Vec::new();
    for b in 0..nb as u32 {
        for s in [
            [1.0, 1.0, 1.0],
            [-1.0, 1.0, -1.0],
            [1.0, -1.0, -1.0],
            [-1.0, -1.0, 1.0],
            [1.0, -1.0, 1.0],
            [-1.0, -1.0, -1.0],
        ] {
            cb.push(b);
            cp.push(Vec3::new(s[0] * 0.2, s[1] * 0.15, s[2] * 0.1) + r.vec3(-0.01, 0.01));
        }
    }
    let nc = cb.len();
    let cb = arr(cb, "contact_body");
    let cp = arr(cp, "contact_point");
    let (bf, bt) = (zeros3(nb, "body_f"), zeros3(nb, "body_t"));
    let up = Vec3::new(0.0, 1.0, 0.0);
    let rep = check_kernel!(
        "eval_body_ground",
        eval_body_ground,
        nc,
        (&bx, &bq, &bv, &bw, &cb, &cp, up, 0.0, 1000.0, 1.0, 0.5, 0.0, &bf, &bt),
        inputs = [bx, bq, bv, bw, cp],
        outputs = [bf, bt]
    );
    let _ = rep;
    assert!(
        bf.to_vec().iter().all(|f| f.y > 0.0),
        "both bodies touch the ground: {:?}",
        bf.to_vec()
    );

    let f = arr(r.vec3s(nb, -1.0, 1.0), "f");
    let tau = arr(r.vec3s(nb, -1.0, 1.0), "tau");
    let inv_mass = arr(r.scalars(nb, 0.5, 2.0), "inv_mass");
    let inertia_v: Vec<Mat33<f64>> = (0..nb).map(|_| spd(&mut r)).collect();
    let inv_inertia = arr(
        inertia_v.iter().map(|m| m.try_inverse().unwrap()).collect(),
        "inv_inertia",
    );
    let inertia = arr(inertia_v, "inertia");
    let gravity = arr(
        vec![Vec3::new(0.3, -9.8, 0.1), Vec3::new(-0.2, -1.6, 0.4)],
        "gravity",
    );
    let world = Array::from_vec((0..nb as u32).map(|i| i % 2).collect());
    let (x1, q1, v1, w1) = (
        zeros3(nb, "x1"),
        Array::<Quat<f64>>::zeros(nb).named("q1"),
        zeros3(nb, "v1"),
        zeros3(nb, "w1"),
    );
    check_kernel!(
        "integrate_bodies",
        integrate_bodies,
        nb,
        (
            &bx,
            &bq,
            &bv,
            &bw,
            &f,
            &tau,
            &inv_mass,
            &inertia,
            &inv_inertia,
            &gravity,
            &world,
            0.01,
            &x1,
            &q1,
            &v1,
            &w1
        ),
        inputs = [
            bx,
            bq,
            bv,
            bw,
            f,
            tau,
            inv_mass,
            inertia,
            inv_inertia,
            gravity
        ],
        outputs = [x1, q1, v1, w1]
    );
    let e: Array<f64> = Array::zeros(1);
    check_kernel!(
        "body_kinetic_energy",
        body_kinetic_energy,
        nb,
        (&bq, &bv, &bw, &inv_mass, &inertia, &e),
        inputs = [bq, bv, bw, inv_mass, inertia],
        outputs = [e]
    );
}

#[test]
fn xpbd_distance_constraints() {
    let mut r = Rng(20);
    let n = 6;
    let x = arr(r.vec3s(n, 0.0, 1.0), "x");
    let w = arr(r.scalars(n, 0.5, 2.0), "inv_mass");
    let pairs = arr(
        vec![[0u32, 1], [1, 2], [2, 3], [3, 4], [4, 5], [0, 5], [1, 4]],
        "pairs",
    );
    let m = pairs.len();
    let rest = arr(r.scalars(m, 0.2, 0.8), "rest");
    let compliance = arr(r.scalars(m, 1e-3, 1e-2), "compliance");
    let lambda = arr(r.scalars(m, -0.5, 0.5), "lambda");
    let dx = zeros3(n, "dx");
    let lambda_out: Array<f64> = Array::zeros(m).named("lambda_out");
    check_kernel!(
        "solve_distance_constraints",
        solve_distance_constraints,
        m,
        (
            &x,
            &w,
            &pairs,
            &rest,
            &compliance,
            &lambda,
            0.01,
            &dx,
            &lambda_out
        ),
        inputs = [x, w, rest, compliance, lambda],
        outputs = [dx, lambda_out]
    );
    let d = arr(r.vec3s(n, -0.1, 0.1), "d");
    let x1 = zeros3(n, "x1");
    check_kernel!(
        "apply_corrections",
        apply_corrections,
        n,
        (&x, &d, 0.8, &x1),
        inputs = [x, d],
        outputs = [x1]
    );
    let vv = zeros3(n, "v");
    check_kernel!(
        "velocity_from_positions",
        velocity_from_positions,
        n,
        (&d, &x, 0.01, &vv),
        inputs = [d, x],
        outputs = [vv]
    );
    let e: Array<f64> = Array::zeros(1);
    // Energies of soft constraints (the 1/compliance term needs a compliance large against h).
    let soft = arr(r.scalars(m, 0.05, 0.5), "compliance");
    check_kernel!(
        "distance_constraint_energy",
        distance_constraint_energy,
        m,
        (&x, &pairs, &rest, &soft, &e),
        inputs = [x, rest, soft],
        outputs = [e]
    );
}

/// Each particle's world for an energy kernel's check: alternately 0 and 1 (two energies).
fn two_worlds(x: &Array<Vec3<f64>>) -> Array<u32> {
    Array::from_vec((0..x.len()).map(|i| (i % 2) as u32).collect())
}
