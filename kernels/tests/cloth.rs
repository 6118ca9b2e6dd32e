//! The `cloth` benchmark scene against the reference (NVIDIA Warp 1.19, f32, T = 100).

use adflex_kernels::forces::bending::bending_edges;
use adflex_kernels::scenes::cloth;

/// Warp: (n, loss, |dL/dv0|, |dL/dke|).
const WARP: &[(usize, f64, f64, f64)] = &[
    (32, 0.00829959, 6.5834e-5, 7.0005e-10),
    (64, 0.00829663, 3.0457e-5, 6.2418e-10),
];

fn rel(a: f64, b: f64) -> f64 {
    (a - b).abs() / b.abs()
}

#[test]
fn topology_matches_reference_builder() {
    let n = 4;
    let scene = cloth::build::<f32>(n);
    let s = scene.model.springs().unwrap();
    // 2 n (n-1) structural + 2 (n-1)^2 shear springs; the first few in reference order.
    assert_eq!(s.len(), 2 * n * (n - 1) + 2 * (n - 1) * (n - 1));
    assert_eq!(
        &s.pairs.to_vec()[..6],
        &[[0, 4], [0, 1], [0, 5], [4, 1], [1, 5], [1, 2]]
    );
    // Edges shared by two triangles: 3 (n-1)^2 - 2 (n-1) interior edges.
    let b = scene.model.bending().unwrap();
    assert_eq!(b.len(), 3 * (n - 1) * (n - 1) - 2 * (n - 1));
    // From warp_cloth_scene.build(4): bends[:4].
    assert_eq!(
        &b.quads.to_vec()[..4],
        &[[0, 9, 4, 5], [4, 1, 5, 0], [0, 6, 5, 1], [1, 10, 5, 6]]
    );
    assert_eq!(bending_edges(&[[0, 1, 2], [0, 2, 3]]), vec![[1, 3, 2, 0]]);
    let w = scene.model.particle_inv_mass.to_vec();
    assert_eq!((w[0], w[n * (n - 1)], w[1]), (0.0, 0.0, 100.0));
}

#[test]
fn loss_and_gradients_match_warp() {
    for &(n, loss, gv, gk) in WARP {
        let scene = cloth::build::<f32>(n);
        let t0 = std::time::Instant::now();
        let out = cloth::rollout(&scene, 100, true).unwrap();
        println!(
            "N={n}: loss {:.8} (warp {loss:.8}), |dL/dv0| {:.5e} (warp {gv:.5e}), |dL/dke| {:.5e} (warp {gk:.5e}) [{:.2?}]",
            out.loss,
            out.grad_v0_norm,
            out.grad_ke_norm,
            t0.elapsed()
        );
        assert!(
            rel(out.loss, loss) < 5e-5,
            "loss {} vs Warp {loss}",
            out.loss
        );
        assert!(
            rel(out.grad_v0_norm, gv) < 1e-3,
            "|dL/dv0| {} vs Warp {gv}",
            out.grad_v0_norm
        );
        assert!(
            rel(out.grad_ke_norm, gk) < 1e-3,
            "|dL/dke| {} vs Warp {gk}",
            out.grad_ke_norm
        );
    }
}

/// N = 128 (Warp: loss 0.00829538). Slow in debug builds: `cargo test -- --ignored`.
#[test]
#[ignore]
fn loss_matches_warp_at_n128() {
    let scene = cloth::build::<f32>(128);
    let out = cloth::rollout(&scene, 100, true).unwrap();
    println!(
        "N=128: loss {:.8}, |dL/dv0| {:.5e}, |dL/dke| {:.5e}",
        out.loss, out.grad_v0_norm, out.grad_ke_norm
    );
    assert!(rel(out.loss, 0.00829538) < 5e-5, "loss {}", out.loss);
}

#[test]
fn f64_agrees_with_f32() {
    let a = cloth::rollout(&cloth::build::<f32>(16), 100, true).unwrap();
    let b = cloth::rollout(&cloth::build::<f64>(16), 100, true).unwrap();
    assert!(rel(a.loss, b.loss) < 1e-5, "{} vs {}", a.loss, b.loss);
    assert!(
        rel(a.grad_v0_norm, b.grad_v0_norm) < 1e-3,
        "{} vs {}",
        a.grad_v0_norm,
        b.grad_v0_norm
    );
    assert!(
        rel(a.grad_ke_norm, b.grad_ke_norm) < 1e-3,
        "{} vs {}",
        a.grad_ke_norm,
        b.grad_ke_norm
    );
}

/// Wall time per step, forward and forward + backward (run with `--release -- --ignored`).
#[test]
#[ignore]
fn timing() {
    for n in [64, 128] {
        let scene = cloth::build::<f32>(n);
        let _ = cloth::rollout(&scene, 10, true).unwrap();
        let t0 = std::time::Instant::now();
        let _ = cloth::rollout(&scene, 100, false).unwrap();
        let fwd = t0.elapsed().as_secs_f64() / 100.0;
        let t0 = std::time::Instant::now();
        let _ = cloth::rollout(&scene, 100, true).unwrap();
        let both = t0.elapsed().as_secs_f64() / 100.0;
        println!(
            "N={n}: forward {:.3} ms/step, forward+backward {:.3} ms/step",
            fwd * 1e3,
            both * 1e3
        );
    }
}

#[test]
fn triangles_added_twice_bend_once() {
    use adflex_kernels::prelude::RestAngle;
    use adflex_kernels::ModelBuilder;
    use adflex_runtime::Vec3;
    // A square of two triangles, both added as topology and again (reordered) as membranes.
    let mut b = ModelBuilder::<f64>::new();
    for (x, z) in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)] {
        b.add_particle(Vec3::new(x, 0.0, z), Vec3::zeros(), 0.1);
    }
    b.add_triangle(0, 1, 2);
    b.add_triangle(0, 2, 3);
    b.add_triangle_fem(1, 2, 0, 10.0, 10.0, 0.0);
    b.add_triangle_fem(3, 0, 2, 10.0, 10.0, 0.0);
    assert_eq!(b.add_bending_edges(1.0, 0.0, RestAngle::Flat), 1);
    let model = b.try_finalize().expect("no degenerate bending element");
    assert_eq!(model.bending().unwrap().quads.to_vec(), vec![[1, 3, 2, 0]]);
}
