//! Restitution of particle contact: `ParticleContact::with_restitution(e, m_eff)` sets the
//! damping that makes a head-on contact return `e` times the approach speed. Two equal balls
//! meet head on (no gravity, no ground, no friction); the ratio of the separation to the
//! approach speed is measured with a small time step.
//!
//! Measured (`ke = 1e4` N/m, 1 kg each, `m_eff = 0.5` kg, `dt = 2e-5` s, semi-implicit Euler):
//! see the printed figures with `--nocapture`; each is within 0.01 of `e`.

use adflex_kernels::contact::particle::{restitution_damping_ratio, restitution_of_damping_ratio};
use adflex_kernels::prelude::*;
use adflex_runtime::{Tape, Vec3};

/// The ratio of the separation to the approach speed of two balls of 1 kg, radius 0.05 m,
/// approaching at 1 m/s with `contact`, stepped with `dt`.
fn bounce(contact: ParticleContact<f64>, dt: f64) -> f64 {
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    b.particle_radius = 0.05;
    b.add_particle(Vec3::new(-0.06, 0.0, 0.0), Vec3::new(0.5, 0.0, 0.0), 1.0);
    b.add_particle(Vec3::new(0.06, 0.0, 0.0), Vec3::new(-0.5, 0.0, 0.0), 1.0);
    b.set_particle_contact(contact);
    let m = b.finalize();
    let mut s = m.state();
    let approach = 1.0;
    let mut touched = false;
    for _ in 0..(0.2 / dt) as usize {
        s = SemiImplicitEuler
            .step(&m, &mut Tape::new(), &s, None, dt)
            .unwrap();
        let (x, v) = (s.x.to_vec(), s.v.to_vec());
        let gap = (x[1] - x[0]).norm() - 0.1;
        touched |= gap < 0.0;
        if touched && gap > 0.0 {
            return (v[1].x - v[0].x) / approach;
        }
    }
    panic!("the balls did not separate");
}

#[test]
fn restitution_of_two_equal_balls_matches_e() {
    let ke = 1.0e4;
    for e in [0.5_f64, 0.9] {
        let c = ParticleContact {
            ke,
            mu: 0.0,
            ..ParticleContact::default()
        }
        .with_restitution(e, 0.5);
        assert!((c.restitution(0.5) - e).abs() < 1e-12);
        let ratio = bounce(c, 2e-5);
        println!("e = {e}: kd = {:.4} N s/m, measured ratio {ratio:.4}", c.kd);
        assert!((ratio - e).abs() < 0.01, "e = {e}: measured {ratio}");
    }
}

/// `e = 1` is `kd = 0`: no loss, up to the integrator's error, which grows with `dt`
/// (semi-implicit Euler over a contact that begins and ends inside a step).
#[test]
fn no_damping_is_elastic_up_to_the_step() {
    let c = ParticleContact {
        ke: 1.0e4,
        mu: 0.0,
        ..ParticleContact::default()
    }
    .with_restitution(1.0, 0.5);
    assert_eq!(c.kd, 0.0);
    let fine = bounce(c, 2e-5);
    let coarse = bounce(c, 1e-3);
    println!("e = 1: measured ratio {fine:.5} at dt = 2e-5, {coarse:.5} at dt = 1e-3");
    assert!((fine - 1.0).abs() < 2e-3, "{fine}");
}

/// The textbook relation (damping in both halves of the contact) would be wrong here: the
/// library's damping acts only while the balls approach.
#[test]
fn the_relation_is_the_one_sided_dashpots() {
    for e in [0.1_f64, 0.3, 0.5, 0.9, 0.99] {
        let z = restitution_damping_ratio(e);
        assert!((restitution_of_damping_ratio(z) - e).abs() < 1e-12, "{e}");
        let textbook = -e.ln() / (std::f64::consts::PI.powi(2) + e.ln().powi(2)).sqrt();
        assert!(z > textbook, "{e}: {z} vs {textbook}");
    }
    assert_eq!(restitution_damping_ratio(1.0), 0.0);
    assert!((restitution_damping_ratio((-1.0f64).exp()) - 1.0).abs() < 1e-9);
    // Tiny restitutions have large but finite damping ratios (e ~ 1 / (2 zeta)).
    for e in [1e-6_f64, 1e-100, 1e-200, 1e-300] {
        let z = restitution_damping_ratio(e);
        assert!(z.is_finite() && (z * 2.0 * e - 1.0).abs() < 0.1, "{e}: {z}");
        let back = restitution_of_damping_ratio(z);
        assert!((back / e - 1.0).abs() < 1e-9, "{e}: {back}");
    }
}

/// A ball dropped on the ground with `damp_approach = false` (damping in contact only)
/// bounces with the restitution the particle relation gives for `m_eff = m` (with the dFlex
/// default the same `kd` would also brake the fall: here it stops the ball before it lands).
#[test]
fn the_ground_has_a_restitution_when_it_damps_in_contact_only() {
    let (ke, m, e, dt) = (1.0e4, 0.5, 0.6, 2e-5);
    let kd = ParticleContact::restitution_damping(ke, e, m);
    let drop = |damp_approach: bool| -> Option<f64> {
        let mut b = ModelBuilder::<f64>::new();
        b.gravity = Vec3::zeros();
        b.add_particle(Vec3::new(0.0, 0.05, 0.0), Vec3::new(0.0, -1.0, 0.0), m);
        b.set_ground(Ground {
            ke,
            kd,
            mu: 0.0,
            damp_approach,
            ..Ground::default()
        });
        let model = b.finalize();
        let mut s = model.state();
        let mut impact = None;
        for _ in 0..20_000 {
            s = SemiImplicitEuler
                .step(&model, &mut Tape::new(), &s, None, dt)
                .unwrap();
            let (y, vy) = (s.x.get(0).y, s.v.get(0).y);
            if impact.is_none() && y <= model.particle_radius {
                impact = Some(-vy);
            }
            if let Some(v_in) = impact {
                if y > model.particle_radius + 1e-3 {
                    return Some(vy / v_in);
                }
            }
        }
        None
    };
    let in_contact = drop(false).expect("a bounce");
    println!("ground, e = {e}: measured {in_contact:.4} (damping in contact only)");
    assert!((in_contact - e).abs() < 0.01, "{in_contact}");
    assert_eq!(
        drop(true),
        None,
        "damping on approach stops this ball in the air"
    );
}

/// The default ground does not damp a particle in mid-air: it falls freely until it touches
/// (it used to: the default was dFlex's damping on approach, an air drag of `kd v`).
#[test]
fn the_default_ground_lets_particles_fall_freely() {
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.01);
    b.set_ground(Ground::default());
    let model = b.finalize();
    let dt = 1e-3;
    let s = SemiImplicitEuler
        .rollout(&model, &mut Tape::new(), &model.state(), None, dt, 300)
        .unwrap();
    // Semi-implicit Euler's free fall: v = g t exactly, after 0.3 s (the particle is at about
    // 0.56 m, far above the ground).
    let v = s.v.get(0).y;
    assert!((v - model.gravity.get(0).y * 0.3).abs() < 1e-12, "{v}");
    let with_approach = Ground {
        damp_approach: true,
        ..Ground::default()
    };
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::zeros(), 0.01);
    b.set_ground(with_approach);
    let model = b.finalize();
    let s = SemiImplicitEuler
        .rollout(&model, &mut Tape::new(), &model.state(), None, dt, 300)
        .unwrap();
    assert!(
        s.v.get(0).y > -0.11,
        "dFlex's ground brakes it to about 0.1 m/s"
    );
}
