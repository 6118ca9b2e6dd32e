//! The tetrahedral grid builder (`scenes::soft::TetGrid`): its geometry (volumes, masses,
//! orientation, boundary), a block resting on the ground without inverting, its elastic force
//! against central differences of its energy, and the gradient of a rollout with respect to
//! `mu` and the activation against central differences.

use adflex_kernels::prelude::*;
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;

fn signed_volumes(model: &Model<f64>, x: &[Vec3<f64>]) -> Vec<f64> {
    model
        .tets()
        .unwrap()
        .tets
        .to_vec()
        .iter()
        .map(|t| {
            let [a, b, c, d] = t.map(|i| x[i as usize]);
            (b - a).cross(&(c - a)).dot(&(d - a)) / 6.0
        })
        .collect()
}

#[test]
fn the_grid_fills_the_box_with_positive_tets_and_its_mass() {
    let g = TetGrid::<f64> {
        dims: [3, 2, 4],
        cell: 0.1,
        origin: Vec3::new(1.0, 2.0, -0.5),
        density: 500.0,
        ..TetGrid::default()
    };
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(Vec3::zeros(), Vec3::zeros(), 1.0); // not part of the grid
    let block = g.add_to(&mut b);
    let m = b.finalize();
    assert_eq!(block.particles, 1..1 + 4 * 3 * 5);
    assert_eq!(block.tets, 0..6 * 24);
    assert_eq!(
        m.particle_x.get(block.particle(3, 1, 2) as usize),
        Vec3::new(1.3, 2.1, -0.3)
    );
    let box_volume = 0.3 * 0.2 * 0.4;
    let x = m.particle_x.to_vec();
    let vols = signed_volumes(&m, &x);
    assert!(
        vols.iter().all(|&v| (v - 1e-3 / 6.0).abs() < 1e-12),
        "{vols:?}"
    );
    let total: f64 = vols.iter().sum();
    assert!((total - box_volume).abs() < 1e-12, "{total}");
    let rest: f64 = m.tets().unwrap().rest_volume.to_vec().iter().sum();
    assert!((rest - box_volume).abs() < 1e-12, "{rest}");
    let mass: f64 = m.particle_inv_mass.to_vec()[1..]
        .iter()
        .map(|w| 1.0 / w)
        .sum();
    assert!((mass - 500.0 * box_volume).abs() < 1e-9, "{mass}");
    // The boundary: 2 triangles per boundary cell face, outward, covering the box's surface.
    let s = block.surface_triangles();
    assert_eq!(s.len(), 2 * 2 * (3 * 2 + 2 * 4 + 3 * 4));
    let centre = Vec3::new(1.15, 2.1, -0.3);
    let mut area = 0.0;
    for t in s {
        let [a, b, c] = t.map(|i| x[i as usize]);
        let n = (b - a).cross(&(c - a));
        area += 0.5 * n.norm();
        assert!(
            n.dot(&((a + b + c) / 3.0 - centre)) > 0.0,
            "{t:?} points in"
        );
    }
    let box_area = 2.0 * (0.3 * 0.2 + 0.2 * 0.4 + 0.3 * 0.4);
    assert!((area - box_area).abs() < 1e-12, "{area}");
}

#[test]
fn a_block_lands_and_rests_on_the_ground_without_inverting() {
    let mut b = ModelBuilder::<f64>::new();
    let block = TetGrid {
        origin: Vec3::new(0.0, 0.03, 0.0),
        ..TetGrid::default()
    }
    .add_to(&mut b);
    // Damped on approach too (dFlex's ground), so that it settles within the 0.8 s simulated.
    b.set_ground(Ground {
        damp_approach: true,
        ..Ground::default()
    });
    let m = b.finalize();
    let mut s = m.state();
    let mut worst = f64::INFINITY;
    for step in 0..4000 {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, 2e-4)
            .unwrap();
        if step % 10 == 0 {
            let min = signed_volumes(&m, &s.x.to_vec())
                .into_iter()
                .fold(f64::INFINITY, f64::min);
            worst = worst.min(min / (0.05f64.powi(3) / 6.0));
        }
    }
    println!("smallest volume ratio J over the rollout: {worst:.3}");
    assert!(worst > 0.5, "a tetrahedron was squashed to J = {worst}");
    let x = s.x.to_vec();
    let bottom = x[block.particle(2, 0, 1) as usize].y;
    let top = x[block.particle(2, 2, 1) as usize].y;
    // Resting: the bottom vertices at their radius (0.01 m) above the plane, sunk by the
    // weight over the contact stiffness (2.5 kg on 15 vertices of 1000 N/m: 1.6 mm); the
    // block about its height.
    assert!((bottom - 0.0084).abs() < 1e-3, "bottom at {bottom}");
    assert!((top - bottom - 0.1).abs() < 0.01, "height {}", top - bottom);
    let vmax = s.v.to_vec().iter().map(|v| v.norm()).fold(0.0, f64::max);
    println!(
        "after 0.8 s: bottom at {bottom:.4} m, height {:.4} m, max speed {vmax:.3} m/s",
        top - bottom
    );
    assert!(vmax < 0.05, "{vmax}");
}

#[test]
fn the_elastic_force_is_minus_the_energy_gradient() {
    let mut b = ModelBuilder::<f64>::new();
    TetGrid {
        dims: [2, 1, 1],
        ..TetGrid::default()
    }
    .add_to(&mut b);
    let m = b.finalize();
    let mut r = adflex_testkit::Rng(7);
    let s = m.state();
    let x: Vec<Vec3<f64>> =
        s.x.to_vec()
            .iter()
            .map(|p| p + r.vec3(-0.008, 0.008))
            .collect();
    s.x.assign(&x);
    let f = m.eval_forces(&mut Tape::new(), &s, None).to_vec();
    let energy = |x: &[Vec3<f64>]| {
        let s = m.state();
        s.x.assign(x);
        m.elastic_energy(&mut Tape::new(), &s, None).get(0)
    };
    let h = 1e-7;
    let scale = f.iter().map(|f| f.norm()).fold(0.0, f64::max);
    assert!(scale > 1.0, "{scale}");
    let mut worst = 0.0f64;
    for i in 0..x.len() {
        for c in 0..3 {
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i][c] += h;
            xm[i][c] -= h;
            let de = (energy(&xp) - energy(&xm)) / (2.0 * h);
            worst = worst.max((f[i][c] + de).abs() / scale);
        }
    }
    println!("|f + dE/dx| / max|f| = {worst:.1e}");
    assert!(worst < 1e-6, "{worst}");
}

#[diff_kernel]
fn spread(x: &Array<Vec3<f64>>, w: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    loss.atomic_add(0, dot(x[t], w[t]));
}

/// The gradient of a loss of the final positions of a block squeezed by its initial
/// velocities and dropped on the ground, with respect to every tetrahedron's `mu` and
/// activation (and the initial velocities), against central differences.
#[test]
fn rollout_gradient_wrt_mu_and_activation() {
    let mut b = ModelBuilder::<f64>::new();
    TetGrid {
        dims: [2, 1, 1],
        origin: Vec3::new(0.0, 0.012, 0.0),
        ..TetGrid::default()
    }
    .add_to(&mut b);
    b.set_ground(Ground::default());
    let m = b.finalize();
    let mut r = adflex_testkit::Rng(11);
    let s0 = m.state();
    let n = m.particle_count;
    // No vertical velocity of 0 (the ground's damping has a kink there).
    s0.v.assign(
        &(0..n)
            .map(|_| r.vec3(-0.3, 0.3) - Vec3::new(0.0, 0.1, 0.0))
            .collect::<Vec<_>>(),
    );
    let tets = m.tets().unwrap();
    tets.activation.assign(
        &(0..tets.len())
            .map(|_| r.uniform(-0.05, 0.05))
            .collect::<Vec<_>>(),
    );
    let w = Array::from_vec(r.vec3s(n, -1.0, 1.0)).named("w");
    let report = GradCheck::new()
        .step(1e-6)
        .run(
            |tape| {
                let s = SemiImplicitEuler
                    .rollout(&m, tape, &s0, None, 5e-4, 30)
                    .unwrap();
                let loss = Array::zeros(1).named("loss");
                tape.launch(spread, n, (&s.x, &w, &loss));
                loss
            },
            // (`s0.v` too: with only `mu` and the activation, the runtime refuses the backward
            // pass, see the report of this change.)
            &[&tets.mu, &tets.activation, &s0.v],
        )
        .unwrap();
    println!("{report}");
    assert!(report.is_within(1e-5), "{report}");
}

/// The numbers `TetGrid`'s docs state for its defaults are what it gives (the docs once said
/// lambda = 100962 Pa; it is 89744).
#[test]
fn tet_grid_defaults_are_the_documented_ones() {
    let src = include_str!("../src/scenes/soft.rs");
    let g = adflex_kernels::prelude::TetGrid::<f64>::default();
    for (value, documented) in [(g.mu, "51282 Pa"), (g.lambda, "89744 Pa")] {
        assert!(
            src.contains(documented),
            "the docs no longer say {documented}"
        );
        let n: f64 = documented.trim_end_matches(" Pa").parse().unwrap();
        assert!(
            (value - n).abs() < 0.5,
            "{value} vs documented {documented}"
        );
    }
    assert_eq!(g.dims, [4, 2, 2]);
    assert_eq!(g.cell, 0.05);
    assert_eq!(g.density, 1000.0);
    assert_eq!(g.kd, 0.1);
}
