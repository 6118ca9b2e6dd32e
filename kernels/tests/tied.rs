//! Tied parameters (one material for all tetrahedra, or one per group) and per-step control
//! sequences: their gradients through every integrator against central differences, and
//! their errors.

use adflex_kernels::integrators::{ImplicitEuler, Integrator, Midpoint, SemiImplicitEuler};
use adflex_kernels::prelude::{Ground, TetGrid};
use adflex_kernels::tied::{ControlSequence, Tied};
use adflex_kernels::{Model, ModelBuilder};
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::GradCheck;
use adflex_runtime::prelude::*;

#[diff_kernel]
fn loss_kernel(x: &Array<Vec3<f64>>, v: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let t = tid();
    let d = x[t] - vec3(0.05, 0.02, 0.03);
    loss.atomic_add(0, dot(d, d) + 0.1 * dot(v[t], vec3(1.0, 0.5, -0.2)));
}

/// A small soft block (2 x 1 x 1 cells, 12 tetrahedra) falling onto the ground, turning.
fn block() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    TetGrid::<f64> {
        dims: [2, 1, 1],
        origin: Vec3::new(0.0, 0.03, 0.0),
        ..TetGrid::default()
    }
    .add_to(&mut b);
    b.set_ground(Ground {
        damp_approach: false,
        ..Ground::default()
    });
    let m = b.finalize();
    m.particle_v.modify(|v| {
        for (k, v) in v.iter_mut().enumerate() {
            *v = Vec3::new(0.3, -0.5 + 0.05 * k as f64, 0.1);
        }
    });
    m
}

fn integrators() -> Vec<(&'static str, Box<dyn Integrator<f64>>)> {
    vec![
        ("SemiImplicitEuler", Box::new(SemiImplicitEuler)),
        ("Midpoint", Box::new(Midpoint)),
        ("ImplicitEuler", Box::new(ImplicitEuler::default())),
    ]
}

/// One `mu` and per-layer `lambda` for all the block's tetrahedra: their gradients (sums over
/// the tied elements) against central differences, through every integrator.
#[test]
fn tied_material_gradients_match_finite_differences() {
    for (name, integ) in integrators() {
        let model = block();
        let mu = Tied::all(&model, "tets", "mu").unwrap();
        let n = model.tets().unwrap().len();
        let layers: Vec<u32> = (0..n as u32).map(|k| k % 3).collect();
        let lambda = Tied::groups(&model, "tets", "lambda", &layers).unwrap();
        assert_eq!(lambda.values.len(), 3);
        let s0 = model.state();
        // The default step choice (relative to mu ~ 5e4 Pa): a fixed 1e-6 Pa is round-off.
        let report = GradCheck::new()
            .run(
                |tape| {
                    mu.apply(tape);
                    lambda.apply(tape);
                    let s = integ.rollout(&model, tape, &s0, None, 2e-3, 6).unwrap();
                    let loss = Array::zeros(1);
                    tape.launch(loss_kernel, s.x.len(), (&s.x, &s.v, &loss));
                    loss
                },
                &[&mu.values, &lambda.values],
            )
            .unwrap();
        println!("{name}: tied mu and lambda: {report}");
        assert!(report.is_within(1e-5), "{name}: {report}");
        assert!(report.entries.iter().all(|e| e.analytic != 0.0), "{name}");
    }
}

#[test]
fn tying_errors_name_the_parameter() {
    let model = block();
    let n = model.tets().unwrap().len();
    let msg = Tied::all(&model, "tets", "young").unwrap_err().to_string();
    assert!(
        msg.contains("tets.young") && msg.contains("tets.mu"),
        "{msg}"
    );
    let msg = Tied::groups(&model, "tets", "mu", &[0, 1])
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains(&format!("2 group indices for {n} elements")),
        "{msg}"
    );
    let gap: Vec<u32> = (0..n as u32).map(|k| 2 * (k % 2)).collect();
    let msg = Tied::groups(&model, "tets", "mu", &gap)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("group 1 has no element"), "{msg}");
    let mut stray = vec![0u32; n];
    stray[3] = u32::MAX;
    let msg = Tied::groups(&model, "tets", "mu", &stray)
        .unwrap_err()
        .to_string();
    assert!(msg.contains("of element 3 is not below"), "{msg}");
}

/// Per-step particle forces and tetrahedron activations: gradients of every step's controls
/// against central differences, through every integrator.
#[test]
fn control_sequence_gradients_match_finite_differences() {
    for (name, integ) in integrators() {
        let model = block();
        let steps = 4;
        let seq = ControlSequence::new(&model, steps)
            .with_particle_forces()
            .with_tet_activation();
        let f = seq.particle_f.clone().unwrap();
        let a = seq.tet_activation.clone().unwrap();
        f.modify(|f| {
            for (k, f) in f.iter_mut().enumerate() {
                *f = Vec3::new(0.01 * (k % 5) as f64, 0.02, -0.01 * (k % 3) as f64);
            }
        });
        a.modify(|a| {
            for (k, a) in a.iter_mut().enumerate() {
                *a = 0.05 * ((k % 7) as f64 - 3.0);
            }
        });
        let s0 = model.state();
        let report = GradCheck::new()
            .step(1e-6)
            .run(
                |tape| {
                    let s = seq
                        .rollout(integ.as_ref(), &model, tape, &s0, 2e-3)
                        .unwrap();
                    let loss = Array::zeros(1);
                    tape.launch(loss_kernel, s.x.len(), (&s.x, &s.v, &loss));
                    loss
                },
                &[&f, &a],
            )
            .unwrap();
        println!("{name}: control sequence: {report}");
        assert!(report.is_within(1e-5), "{name}: {report}");
        // The last step's forces move the final position: nonzero gradients in every step.
        let g = f.grad().unwrap().to_vec();
        for k in 0..steps {
            let n = model.particle_count;
            assert!(
                g[k * n..(k + 1) * n].iter().any(|g| g.norm() > 0.0),
                "{name}: step {k}"
            );
        }
    }
    let model = block();
    let seq = ControlSequence::new(&model, 2).with_particle_forces();
    let msg = seq.control(&mut Tape::new(), 2).unwrap_err().to_string();
    assert!(msg.contains("step 2 of a sequence of 2 steps"), "{msg}");
}
