//! Leaky contact gradients on a billiards scene: a cue ball hits a rack of balls on a
//! frictionless plane (no gravity, no ground). The loss is a final position; its derivative
//! with respect to the cue ball's initial velocity is computed by central differences (the
//! true derivative: the leak changes only the adjoint, so the forward is the same) and by the
//! adjoint, exact (`leak = 0`) and leaky.
//!
//! Measured (rack of 6 balls of radius 28.6 mm, 0.17 kg, `ke = 1e5` N/m, 2500 steps of
//! 1e-4 s; relative errors of the adjoint's x and z components against central differences):
//! exact 9e-8, 2e-8; preset `leaky` (leak 1.4e-5, margin 2.9 mm) 1.9e-3, 1.6e-4; leak 1e-5,
//! margin 2.9 mm 1.4e-3, 1.2e-4; leak 1e-4, margin 5 mm 2.4e-2, 3.1e-3; leak 1e-3, margin
//! 5 mm 0.24, 0.031; leak 1e-2, margin 5 cm 1.4, 1.06 (both signs wrong). Run with
//! `--nocapture` for the table.

use adflex_kernels::prelude::*;
use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

const R: f64 = 0.0286; // billiard ball radius (m)
const M: f64 = 0.17; // mass (kg)
const KE: f64 = 1.0e5; // N/m
const DT: f64 = 1e-4;
const STEPS: usize = 2500;

/// The cue ball (particle 0) at `(-0.15, 0, 0)` moving at `v` towards a rack of `rows` rows
/// (1 + 2 + ...) with 1 mm gaps, apex at the origin.
fn billiards(contact: ParticleContact<f64>, rows: usize, v: Vec3<f64>) -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    b.particle_radius = R;
    b.add_particle(Vec3::new(-0.15, 0.0, 0.0), v, M);
    let d = 2.0 * R + 1e-3;
    for row in 0..rows {
        for k in 0..=row {
            let x = row as f64 * d * 3f64.sqrt() / 2.0;
            let z = (k as f64 - row as f64 / 2.0) * d;
            b.add_particle(Vec3::new(x, 0.0, z), Vec3::zeros(), M);
        }
    }
    b.set_particle_contact(contact);
    b.finalize()
}

#[diff_kernel]
fn final_position(x: &Array<Vec3<f64>>, i: usize, w: Vec3<f64>, loss: &Array<f64>) {
    loss[0] = dot(x[i], w);
}

/// The loss `w . x_T[last]` (the rack's last ball) and, if `grad`, its derivative with
/// respect to the cue ball's initial velocity.
fn run(model: &Model<f64>, grad: bool) -> (f64, Vec3<f64>) {
    let s0 = model.state();
    s0.v.zero_grad();
    let v0 = s0.v.clone().requires_grad();
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .rollout(model, &mut tape, &s0, None, DT, STEPS)
        .unwrap();
    let loss = Array::zeros(1).named("loss");
    let last = model.particle_count - 1;
    tape.launch(
        final_position,
        1,
        (&s.x, last, Vec3::new(0.3, 0.0, 1.0), &loss),
    );
    let l = loss.get(0);
    if !grad {
        return (l, Vec3::zeros());
    }
    tape.backward(&loss).unwrap();
    (l, v0.grad().unwrap().get(0))
}

/// Central differences of the loss with respect to the cue velocity's component `c`.
fn fd(contact: ParticleContact<f64>, rows: usize, v: Vec3<f64>, c: usize) -> f64 {
    let h = 1e-6;
    let (mut vp, mut vm) = (v, v);
    vp[c] += h;
    vm[c] -= h;
    let lp = run(&billiards(contact, rows, vp), false).0;
    let lm = run(&billiards(contact, rows, vm), false).0;
    (lp - lm) / (2.0 * h)
}

struct Measured {
    fd: Vec3<f64>,
    adjoint: Vec3<f64>,
}

impl Measured {
    fn rel(&self, c: usize) -> f64 {
        (self.adjoint[c] - self.fd[c]).abs() / self.fd[c].abs()
    }
}

fn measure(contact: ParticleContact<f64>, rows: usize, v: Vec3<f64>) -> Measured {
    let fd = Vec3::new(fd(contact, rows, v, 0), 0.0, fd(contact, rows, v, 2));
    let adjoint = run(&billiards(contact, rows, v), true).1;
    Measured { fd, adjoint }
}

#[test]
fn the_leaky_preset_keeps_the_gradients_sign_on_billiards() {
    let v = Vec3::new(2.0, 0.0, 0.05); // hits the apex slightly off centre
    let rows = 3;
    let base = ParticleContact {
        ke: KE,
        kd: 0.0,
        mu: 0.0,
        ..ParticleContact::default()
    };
    let exact = measure(base, rows, v);
    println!(
        "exact: fd {:?}, adjoint {:?}, rel errors {:.1e} {:.1e}",
        exact.fd,
        exact.adjoint,
        exact.rel(0),
        exact.rel(2)
    );
    assert!(exact.rel(0) < 1e-5 && exact.rel(2) < 1e-5);
    let preset = base.leaky(R, M / 2.0, DT * STEPS as f64);
    let mut table = vec![("preset", preset)];
    for (leak, margin) in [(1e-2, 0.05), (1e-3, 5e-3), (1e-4, 5e-3), (1e-5, 0.1 * R)] {
        table.push((
            "",
            ParticleContact {
                leak,
                margin,
                ..base
            },
        ));
    }
    let mut preset_errors = [0.0; 2];
    for (name, c) in table {
        let m = measure(c, rows, v);
        println!(
            "{name:6} leak {:.2e}, margin {:.4}: fd {:?} adjoint {:?} rel errors {:.2e} {:.2e}",
            c.leak,
            c.margin,
            m.fd,
            m.adjoint,
            m.rel(0),
            m.rel(2)
        );
        if name == "preset" {
            preset_errors = [m.rel(0), m.rel(2)];
            for k in [0, 2] {
                assert!(
                    m.adjoint[k].signum() == m.fd[k].signum(),
                    "component {k}: adjoint {} vs fd {}",
                    m.adjoint[k],
                    m.fd[k]
                );
            }
        }
    }
    assert!(
        preset_errors.iter().all(|e| *e < 0.01),
        "preset relative errors {preset_errors:?}"
    );
}
