//! MLS-MPM: each kernel and whole rollouts against central differences in f64, forward mode
//! against reverse mode, physics that can be computed by hand (free fall, conserved momentum),
//! determinism over threads, checkpointing, and the errors of bad input and unstable steps.

use adflex_kernels::mpm::kernels::{mpm_g2p, mpm_grid_update, mpm_p2g};
use adflex_kernels::mpm::*;
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::{dot_test, GradCheck};
use adflex_runtime::prelude::*;

/// `loss[0] = -c[0].x`: DiffTaichi's `diffmpm` loss from the mean position.
#[diff_kernel]
fn minus_x<R: Real>(c: &Array<Vec2<R>>, loss: &Array<R>) {
    loss[0] = -c[0].x;
}

/// A tiny deterministic generator.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn in_range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next()
    }
}

#[test]
fn each_kernel_matches_central_differences_and_its_tangent() {
    let (n, ng, dx, dt) = (12, 16usize, 1.0 / 16.0, 2e-3);
    let mut rng = Rng(7);
    let mut vec2s = |lo: f64, hi: f64| -> Vec<Vec2<f64>> {
        (0..n)
            .map(|_| Vec2::new(rng.in_range(lo, hi), rng.in_range(lo, hi)))
            .collect()
    };
    let x = Array::from_vec(vec2s(0.3, 0.7)).named("x");
    let v = Array::from_vec(vec2s(-1.0, 1.0)).named("v");
    let fiber = Array::from_vec(vec2s(-1.0, 1.0)).named("fiber");
    let mut rng = Rng(11);
    let mut mat = |s: f64, d: f64| -> Vec<Mat22<f64>> {
        (0..n)
            .map(|_| {
                Mat22::new(
                    d + rng.in_range(-s, s),
                    rng.in_range(-s, s),
                    rng.in_range(-s, s),
                    d + rng.in_range(-s, s),
                )
            })
            .collect()
    };
    let c = Array::from_vec(mat(3.0, 0.0)).named("C");
    let f = Array::from_vec(mat(0.2, 1.0)).named("F");
    let scalars = |lo: f64, hi: f64, seed: u64| {
        let mut r = Rng(seed);
        Array::from_vec((0..n).map(|_| r.in_range(lo, hi)).collect::<Vec<f64>>())
    };
    let mass = scalars(0.5, 2.0, 1).named("mass");
    let volume = scalars(0.5, 2.0, 2).named("volume");
    let mu = scalars(5.0, 20.0, 3).named("mu");
    let lambda = scalars(5.0, 20.0, 4).named("lambda");
    let act_gain = scalars(1.0, 4.0, 5).named("act_gain");
    // Snow's plasticity: bounds the random F's stretches cross, some packed, some loose.
    let jp = scalars(0.8, 1.2, 6).named("Jp");
    let compression = scalars(0.02, 0.1, 7).named("compression");
    let stretch = scalars(0.01, 0.05, 8).named("stretch");
    let hardening = scalars(1.0, 10.0, 9).named("hardening");
    // All four materials, two actuators.
    let kind = Array::from_vec((0..n as u32).map(|p| p % 4).collect::<Vec<u32>>());
    let actuator = Array::from_vec((0..n as u32).map(|p| p % 2).collect::<Vec<u32>>());
    let actuation = Array::from_vec(vec![0.3, -0.7]).named("actuation");
    let f_out = Array::<Mat22<f64>>::zeros(n).named("F_out");
    let jp_out = Array::<f64>::zeros(n).named("Jp_out");
    let grid_mv = Array::<Vec2<f64>>::zeros(ng * ng).named("grid_mv");
    let grid_m = Array::<f64>::zeros(ng * ng).named("grid_m");
    let p2g_args = (
        &x,
        &v,
        &c,
        &f,
        &jp,
        &mass,
        &volume,
        &mu,
        &lambda,
        &kind,
        &compression,
        &stretch,
        &hardening,
        &actuator,
        &act_gain,
        &fiber,
        &actuation,
        ng,
        dx,
        dt,
        &f_out,
        &jp_out,
        &grid_mv,
        &grid_m,
    );
    GradCheck::new()
        .kernel(mpm_p2g, n, p2g_args)
        .unwrap()
        .assert_within(1e-6);
    let p2g_inputs: [&dyn AnyArray; 15] = [
        &x,
        &v,
        &c,
        &f,
        &jp,
        &mass,
        &volume,
        &mu,
        &lambda,
        &compression,
        &stretch,
        &hardening,
        &act_gain,
        &fiber,
        &actuation,
    ];
    let p2g_run = |tape: &mut Tape| {
        let (fo, jo, mv, m) = (
            f_out.zeros_like(),
            jp_out.zeros_like(),
            grid_mv.zeros_like(),
            grid_m.zeros_like(),
        );
        tape.launch(
            mpm_p2g,
            n,
            (
                &x,
                &v,
                &c,
                &f,
                &jp,
                &mass,
                &volume,
                &mu,
                &lambda,
                &kind,
                &compression,
                &stretch,
                &hardening,
                &actuator,
                &act_gain,
                &fiber,
                &actuation,
                ng,
                dx,
                dt,
                &fo,
                &jo,
                &mv,
                &m,
            ),
        );
        vec![fo.boxed(), jo.boxed(), mv.boxed(), m.boxed()]
    };
    dot_test(p2g_run, &p2g_inputs, 3)
        .unwrap()
        .assert_within(1e-10);

    // The grid update, with every wall active: random momenta on every node, both floors.
    let mut r = Rng(5);
    let mv = Array::from_vec(
        (0..ng * ng)
            .map(|_| Vec2::new(r.in_range(-1.0, 1.0), r.in_range(-1.0, 1.0)))
            .collect::<Vec<_>>(),
    )
    .named("grid_mv");
    let m = Array::from_vec(
        (0..ng * ng)
            .map(|_| r.in_range(0.5, 2.0))
            .collect::<Vec<f64>>(),
    )
    .named("grid_m");
    let gravity = Array::from_vec(vec![Vec2::new(0.3, -3.8)]).named("gravity");
    let grid_v = Array::<Vec2<f64>>::zeros(ng * ng).named("grid_v");
    for friction in [-1.0, 0.5] {
        GradCheck::new()
            .kernel(
                mpm_grid_update,
                ng * ng,
                (&mv, &m, &gravity, ng, 3usize, friction, dt, &grid_v),
            )
            .unwrap()
            .assert_within(1e-6);
        let run = |tape: &mut Tape| {
            let out = grid_v.zeros_like();
            tape.launch(
                mpm_grid_update,
                ng * ng,
                (&mv, &m, &gravity, ng, 3usize, friction, dt, &out),
            );
            vec![out.boxed()]
        };
        dot_test(run, &[&mv, &m, &gravity], 4)
            .unwrap()
            .assert_within(1e-10);
    }

    // Grid to particle.
    let (xo, vo, co) = (x.zeros_like(), v.zeros_like(), c.zeros_like());
    GradCheck::new()
        .kernel(mpm_g2p, n, (&x, &mv, ng, dx, dt, &xo, &vo, &co))
        .unwrap()
        .assert_within(1e-6);
    let run = |tape: &mut Tape| {
        let (xo, vo, co) = (x.zeros_like(), v.zeros_like(), c.zeros_like());
        tape.launch(mpm_g2p, n, (&x, &mv, ng, dx, dt, &xo, &vo, &co));
        vec![xo.boxed(), vo.boxed(), co.boxed()]
    };
    dot_test(run, &[&x, &mv], 5).unwrap().assert_within(1e-10);
}

/// The walker on a coarse grid, in f64.
fn small_walker(floor: Floor) -> Mpm<f64> {
    let mut b = scenes::walker(32);
    b.set_floor(floor);
    b.finalize::<f64>().unwrap()
}

/// `steps` steps of the walker with a constant actuation, the loss `-mean x`.
fn walker_loss(mpm: &Mpm<f64>, tape: &mut Tape, act: &Array<f64>, steps: usize) -> Array<f64> {
    let mut s = mpm.state();
    for _ in 0..steps {
        s = mpm.step(tape, &s, Some(act), 2e-3).unwrap();
    }
    let c = mpm.mean_position(tape, &s);
    let loss = Array::zeros(1).named("loss");
    tape.launch(minus_x, 1, (&c, &loss));
    loss
}

#[test]
fn rollout_gradients_match_central_differences_and_tangents() {
    for floor in [Floor::Sticky, Floor::Coulomb(0.5)] {
        let mpm = small_walker(floor);
        let act = Array::from_vec(vec![0.8, -0.5, 0.3, -0.9]).named("actuation");
        let steps = 40;
        let report = GradCheck::new()
            .run(
                |tape| walker_loss(&mpm, tape, &act, steps),
                &[&act, &mpm.gravity, &mpm.mu, &mpm.lambda, &mpm.act_gain],
            )
            .unwrap();
        report.assert_within(1e-6);
        assert!(act.grad().unwrap().to_vec().iter().all(|g| *g != 0.0));
        let run = |tape: &mut Tape| {
            let mut s = mpm.state();
            for _ in 0..steps {
                s = mpm.step(tape, &s, Some(&act), 2e-3).unwrap();
            }
            vec![s.x.boxed(), s.f.boxed()]
        };
        dot_test(run, &[&act, &mpm.gravity, &mpm.mu, &mpm.mass], 9)
            .unwrap()
            .assert_within(1e-10);
    }
}

/// Final positions and the gradients of the loss with respect to the actuation and `mu`.
fn bits(mpm: &Mpm<f64>, act: &Array<f64>) -> (Vec<Vec2<f64>>, Vec<f64>, Vec<f64>) {
    act.zero_grad();
    mpm.mu.zero_grad();
    let mut tape = Tape::new();
    let loss = walker_loss(mpm, &mut tape, act, 30);
    tape.backward(&loss).unwrap();
    let x = tape_free_positions(mpm, act);
    (
        x,
        act.grad().unwrap().to_vec(),
        mpm.mu.grad().unwrap().to_vec(),
    )
}

fn tape_free_positions(mpm: &Mpm<f64>, act: &Array<f64>) -> Vec<Vec2<f64>> {
    let mut tape = Tape::new();
    let mut s = mpm.state();
    for _ in 0..30 {
        s = mpm.step(&mut tape, &s, Some(act), 2e-3).unwrap();
    }
    s.x.to_vec()
}

#[test]
fn the_scatter_is_deterministic_over_threads() {
    let mpm = small_walker(Floor::Sticky);
    let _ = mpm.mu.clone().requires_grad();
    let act = Array::from_vec(vec![0.8, -0.5, 0.3, -0.9]).requires_grad();
    let defaults = adflex_runtime::settings::settings();
    let mut parallel = defaults;
    parallel.serial_below = 1;
    parallel.apply();
    let one = with_threads(1, || bits(&mpm, &act));
    let two = with_threads(2, || bits(&mpm, &act));
    let three = with_threads(3, || bits(&mpm, &act));
    adflex_runtime::settings::set_settings(defaults);
    assert_eq!(one, two, "1 and 2 threads");
    assert_eq!(one, three, "1 and 3 threads");
    assert!(one.1.iter().all(|g| *g != 0.0));
}

#[test]
fn checkpointed_rollouts_give_the_tapes_gradients_bit_for_bit() {
    let mpm = small_walker(Floor::Coulomb(0.5));
    let act = Array::from_vec(vec![0.8, -0.5, 0.3, -0.9]).requires_grad();
    let steps = 30;
    let mut tape = Tape::new();
    let loss = walker_loss(&mpm, &mut tape, &act, steps);
    tape.backward(&loss).unwrap();
    let plain = act.grad().unwrap().to_vec();
    act.zero_grad();
    let out = Checkpointed::new(steps)
        .every(7)
        .run(
            &mpm.state(),
            |tape, s, _| mpm.step(tape, s, Some(&act), 2e-3),
            |tape, s, t, acc| {
                if t == steps {
                    let c = mpm.mean_position(tape, s);
                    tape.launch(minus_x, 1, (&c, acc));
                }
                Ok(())
            },
        )
        .unwrap();
    assert_eq!(out.loss.get(0), loss.get(0));
    assert_eq!(act.grad().unwrap().to_vec(), plain);
}

#[test]
fn a_block_in_free_fall_follows_gravity_exactly() {
    // Away from the walls, with F = I and a uniform velocity field, MLS-MPM moves every
    // particle by symplectic Euler: v_n = g n dt, x_n = x_0 + g dt^2 n (n + 1) / 2.
    let mut b = MpmBuilder::new(64, 1.0 / 64.0);
    let g = Vec2::new(0.5, -9.8);
    b.set_gravity(g);
    b.add_rect(
        Vec2::new(0.4, 0.6),
        Vec2::new(0.1, 0.1),
        1.0,
        1.0,
        Material::NeoHookean {
            mu: 50.0,
            lambda: 50.0,
        },
    );
    let mpm = b.finalize::<f64>().unwrap();
    let mut tape = Tape::new();
    let s0 = mpm.state();
    let mut s = s0.clone();
    let (dt, n) = (1e-3, 50);
    for _ in 0..n {
        s = mpm.step(&mut tape, &s, None, dt).unwrap();
    }
    let shift = g * (dt * dt * (n * (n + 1)) as f64 / 2.0);
    for (x, x0) in s.x.to_vec().iter().zip(s0.x.to_vec()) {
        assert!(
            (x - (x0 + shift)).norm() < 1e-12,
            "{x:?} vs {:?}",
            x0 + shift
        );
    }
    for v in s.v.to_vec() {
        assert!((v - g * (dt * n as f64)).norm() < 1e-11, "{v:?}");
    }
}

#[test]
fn a_spinning_block_keeps_its_momentum() {
    // No gravity, away from the walls: the transfers conserve linear momentum exactly
    // (up to rounding), and the spinning block keeps its angular momentum
    // sum m (x × v) + APIC's m (C D)-term to a small drift.
    let mut b = MpmBuilder::new(64, 1.0 / 64.0);
    b.set_gravity(Vec2::zeros());
    let r = b.add_rect(
        Vec2::new(0.4, 0.4),
        Vec2::new(0.2, 0.1),
        1.0,
        1.0,
        Material::Corotated {
            mu: 20.0,
            lambda: 20.0,
        },
    );
    let center = Vec2::new(0.5, 0.45);
    let xs: Vec<Vec2<f64>> = {
        let m = b.clone().finalize::<f64>().unwrap();
        m.state().x.to_vec()
    };
    for (p, x) in r.zip(&xs) {
        let d = x - center;
        b.set_velocity(p, Vec2::new(0.3 - 2.0 * d.y, 0.1 + 2.0 * d.x));
    }
    let mpm = b.finalize::<f64>().unwrap();
    let momentum = |s: &MpmState<f64>| -> (Vec2<f64>, f64) {
        let (x, v) = (s.x.to_vec(), s.v.to_vec());
        let p = v.iter().fold(Vec2::zeros(), |a, v| a + v);
        let l = x
            .iter()
            .zip(&v)
            .map(|(x, v)| x.x * v.y - x.y * v.x)
            .sum::<f64>();
        (p, l)
    };
    let mut tape = Tape::new();
    let mut s = mpm.state();
    let (p0, l0) = momentum(&s);
    for _ in 0..100 {
        s = mpm.step(&mut tape, &s, None, 1e-3).unwrap();
    }
    let (p1, l1) = momentum(&s);
    assert!(
        (p1 - p0).norm() < 1e-11 * p0.norm().max(1.0),
        "{p0:?} -> {p1:?}"
    );
    // The particles' x × v part alone changes a little (APIC keeps the rest in C).
    assert!((l1 - l0).abs() < 2e-2 * l0.abs(), "{l0} -> {l1}");
}

#[test]
fn bad_input_and_unstable_steps_are_errors_naming_the_cause() {
    // The builder: a particle in the wall, a NaN mass, a bound too thick.
    let mut b = MpmBuilder::new(32, 1.0 / 32.0);
    b.add_particle(
        Vec2::new(0.01, 0.5),
        1.0,
        1.0,
        Material::Corotated {
            mu: 1.0,
            lambda: 1.0,
        },
    );
    b.add_particle(
        Vec2::new(0.5, 0.5),
        f64::NAN,
        1.0,
        Material::Corotated {
            mu: 1.0,
            lambda: 1.0,
        },
    );
    b.add_particle(
        Vec2::new(0.5, 0.5),
        1.0,
        1.0,
        Material::NeoHookean {
            mu: -1.0,
            lambda: 1.0,
        },
    );
    let e = b.finalize::<f64>().unwrap_err().to_string();
    for what in [
        "particles[0].x",
        "particles[1].mass",
        "particles[2].material",
    ] {
        assert!(e.contains(what), "{what} in {e}");
    }
    let mut b = MpmBuilder::new(32, 1.0 / 32.0);
    b.set_bound(16);
    assert!(b
        .finalize::<f64>()
        .unwrap_err()
        .to_string()
        .contains("bound"));

    // A step: dt, the actuation's length.
    let mpm = small_walker(Floor::Sticky);
    let mut tape = Tape::new();
    let s = mpm.state();
    let e = mpm.step(&mut tape, &s, None, -1.0).unwrap_err();
    assert!(e.to_string().contains("dt"), "{e}");
    let short = Array::from_vec(vec![0.0; 3]).named("act");
    let e = mpm
        .step(&mut tape, &s, Some(&short), 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("act") && e.contains("4 actuators"), "{e}");

    // Far beyond the stable step, the walker blows up: an error naming a particle, never a
    // NaN handed on.
    let dt = 40.0 * mpm.stable_dt();
    let mut s = mpm.state();
    let act = Array::from_vec(vec![1.0, -1.0, 1.0, -1.0]);
    let mut err = None;
    for _ in 0..200 {
        match mpm.step(&mut tape, &s, Some(&act), dt) {
            Ok(next) => s = next,
            Err(e) => {
                err = Some(e.to_string());
                break;
            }
        }
    }
    let err = err.expect("the step at 40x the stable dt must fail");
    assert!(
        err.contains("particle") && err.contains("stable_dt"),
        "{err}"
    );
}

/// Stability at the limit the elastic waves give: a stiff jelly block dropped on the floor
/// stays finite and inside the box for 2,000 steps at half the model's `stable_dt`, and the
/// step fails (an error, not a NaN) well beyond it.
#[test]
fn steps_are_stable_below_the_wave_speed_limit() {
    let run = |factor: f64| -> Result<f64, String> {
        let mut b = MpmBuilder::new(32, 1.0 / 32.0);
        b.add_rect(
            Vec2::new(0.35, 0.3),
            Vec2::new(0.3, 0.2),
            1.0,
            1.0,
            Material::Corotated {
                mu: 400.0,
                lambda: 400.0,
            },
        );
        let mpm = b.finalize::<f64>().unwrap();
        let dt = factor * mpm.stable_dt();
        let mut s = mpm.state();
        let mut top: f64 = 0.0;
        for _ in 0..2000 {
            let mut tape = Tape::new();
            s = mpm
                .step(&mut tape, &s, None, dt)
                .map_err(|e| e.to_string())?;
        }
        for x in s.x.to_vec() {
            top = top.max(x.y);
        }
        Ok(top)
    };
    let top = run(0.5).unwrap();
    assert!(
        top < 0.5 + 1e-3,
        "the block bounced above where it started: {top}"
    );
    let err = run(8.0).unwrap_err();
    assert!(err.contains("stable_dt"), "{err}");
}

#[test]
fn three_d_kernels_match_central_differences_and_their_tangents() {
    use adflex_kernels::mpm::kernels::{mpm3_g2p, mpm3_grid_update, mpm3_p2g};
    let (n, ng, dx, dt) = (8, 8usize, 1.0 / 8.0, 2e-3);
    let mut r = Rng(17);
    let mut v3 = |lo: f64, hi: f64| -> Vec<Vec3<f64>> {
        (0..n)
            .map(|_| Vec3::new(r.in_range(lo, hi), r.in_range(lo, hi), r.in_range(lo, hi)))
            .collect()
    };
    let x = Array::from_vec(v3(0.35, 0.65)).named("x");
    let v = Array::from_vec(v3(-1.0, 1.0)).named("v");
    let fiber = Array::from_vec(v3(-1.0, 1.0)).named("fiber");
    let mut r = Rng(19);
    let mut mat = |s: f64, d: f64| -> Vec<Mat33<f64>> {
        (0..n)
            .map(|_| Mat33::from_fn(|i, j| if i == j { d } else { 0.0 } + r.in_range(-s, s)))
            .collect()
    };
    let c = Array::from_vec(mat(3.0, 0.0)).named("C");
    let f = Array::from_vec(mat(0.2, 1.0)).named("F");
    let scalars = |lo: f64, hi: f64, seed: u64| {
        let mut r = Rng(seed);
        Array::from_vec((0..n).map(|_| r.in_range(lo, hi)).collect::<Vec<f64>>())
    };
    let (mass, volume) = (
        scalars(0.5, 2.0, 1).named("mass"),
        scalars(0.5, 2.0, 2).named("volume"),
    );
    let (mu, lambda) = (
        scalars(5.0, 20.0, 3).named("mu"),
        scalars(5.0, 20.0, 4).named("lambda"),
    );
    let act_gain = scalars(1.0, 4.0, 5).named("act_gain");
    let jp = scalars(0.8, 1.2, 6).named("Jp");
    let compression = scalars(0.02, 0.1, 7).named("compression");
    let stretch = scalars(0.01, 0.05, 8).named("stretch");
    let hardening = scalars(1.0, 10.0, 9).named("hardening");
    let kind = Array::from_vec((0..n as u32).map(|p| p % 4).collect::<Vec<u32>>());
    let actuator = Array::from_vec((0..n as u32).map(|p| p % 2).collect::<Vec<u32>>());
    let actuation = Array::from_vec(vec![0.3, -0.7]).named("actuation");
    let cells = ng * ng * ng;
    let (f_out, jp_out, grid_mv, grid_m) = (
        Array::<Mat33<f64>>::zeros(n).named("F_out"),
        Array::<f64>::zeros(n).named("Jp_out"),
        Array::<Vec3<f64>>::zeros(cells).named("grid_mv"),
        Array::<f64>::zeros(cells).named("grid_m"),
    );
    GradCheck::new()
        .kernel(
            mpm3_p2g,
            n,
            (
                &x,
                &v,
                &c,
                &f,
                &jp,
                &mass,
                &volume,
                &mu,
                &lambda,
                &kind,
                &compression,
                &stretch,
                &hardening,
                &actuator,
                &act_gain,
                &fiber,
                &actuation,
                ng,
                3usize,
                dx,
                dt,
                &f_out,
                &jp_out,
                &grid_mv,
                &grid_m,
            ),
        )
        .unwrap()
        .assert_within(1e-6);
    let run = |tape: &mut Tape| {
        let (fo, jo, mv, m) = (
            f_out.zeros_like(),
            jp_out.zeros_like(),
            grid_mv.zeros_like(),
            grid_m.zeros_like(),
        );
        tape.launch(
            mpm3_p2g,
            n,
            (
                &x,
                &v,
                &c,
                &f,
                &jp,
                &mass,
                &volume,
                &mu,
                &lambda,
                &kind,
                &compression,
                &stretch,
                &hardening,
                &actuator,
                &act_gain,
                &fiber,
                &actuation,
                ng,
                3usize,
                dx,
                dt,
                &fo,
                &jo,
                &mv,
                &m,
            ),
        );
        vec![fo.boxed(), jo.boxed(), mv.boxed(), m.boxed()]
    };
    let inputs: [&dyn AnyArray; 12] = [
        &x,
        &v,
        &c,
        &f,
        &jp,
        &mu,
        &lambda,
        &compression,
        &stretch,
        &hardening,
        &fiber,
        &actuation,
    ];
    dot_test(run, &inputs, 6).unwrap().assert_within(1e-10);
    let mut r = Rng(23);
    let mv = Array::from_vec(
        (0..cells)
            .map(|_| {
                Vec3::new(
                    r.in_range(-1.0, 1.0),
                    r.in_range(-1.0, 1.0),
                    r.in_range(-1.0, 1.0),
                )
            })
            .collect::<Vec<_>>(),
    );
    let m = Array::from_vec(
        (0..cells)
            .map(|_| r.in_range(0.5, 2.0))
            .collect::<Vec<f64>>(),
    );
    let gravity = Array::from_vec(vec![Vec3::new(0.3, -3.8, 0.2)]);
    let gv = Array::<Vec3<f64>>::zeros(cells);
    for friction in [-1.0, 0.5] {
        GradCheck::new()
            .kernel(
                mpm3_grid_update,
                cells,
                (&mv, &m, &gravity, ng, 2usize, friction, dt, &gv),
            )
            .unwrap()
            .assert_within(1e-6);
    }
    let (xo, vo, co) = (x.zeros_like(), v.zeros_like(), c.zeros_like());
    GradCheck::new()
        .kernel(mpm3_g2p, n, (&x, &mv, ng, 3usize, dx, dt, &xo, &vo, &co))
        .unwrap()
        .assert_within(1e-6);
    let run = |tape: &mut Tape| {
        let (xo, vo, co) = (x.zeros_like(), v.zeros_like(), c.zeros_like());
        tape.launch(mpm3_g2p, n, (&x, &mv, ng, 3usize, dx, dt, &xo, &vo, &co));
        vec![xo.boxed(), vo.boxed(), co.boxed()]
    };
    dot_test(run, &[&x, &mv], 7).unwrap().assert_within(1e-10);
}

#[test]
fn three_d_polar_rotation_is_a_rotation_and_leaves_a_symmetric_stretch() {
    use adflex_kernels::mpm::kernels::polar_rotation3;
    let mut r = Rng(29);
    // F = Q1 diag(s) Q2 with stretches from 1e-4 to 1e4 and random rotations.
    let rotation = |r: &mut Rng| {
        let axis = Vec3::new(
            r.in_range(-1.0, 1.0),
            r.in_range(-1.0, 1.0),
            r.in_range(-1.0, 1.0),
        );
        nalgebra::Rotation3::from_scaled_axis(axis * 3.0).into_inner()
    };
    for k in 0..40 {
        let spread = [0.4, 2.0, 4.0, 8.0][k % 4];
        let s = Vec3::from_fn(|_, _| 10f64.powf(r.in_range(-spread, spread) / 2.0));
        let (q1, q2) = (rotation(&mut r), rotation(&mut r));
        let f = q1 * Mat33::from_diagonal(&s) * q2;
        let rot = polar_rotation3::call(f);
        assert!(
            (rot.transpose() * rot - Mat33::identity()).norm() < 1e-10,
            "stretches {s:?}: {rot}"
        );
        assert!((rot - q1 * q2).norm() < 1e-9, "stretches {s:?}");
        let st = rot.transpose() * f;
        assert!((st - st.transpose()).norm() < 1e-9 * st.norm(), "{st}");
    }
}

/// A particle that inverts where its material cannot take it is an error naming it, never
/// a reflection or a NaN handed on; the 2D corotated material takes inversion.
#[test]
fn inverted_particles_are_refused_where_the_material_needs_det_f_positive() {
    let material = Material::Corotated {
        mu: 10.0,
        lambda: 10.0,
    };
    let mut b = MpmBuilder::new_3d(16, 1.0 / 16.0);
    b.add_rect(
        Vec3::new(0.4, 0.4, 0.4),
        Vec3::new(0.125, 0.125, 0.125),
        1.0,
        1.0,
        material,
    );
    let mpm = b.finalize::<f64>().unwrap();
    let s = mpm.state();
    s.f.set(5, Mat33::from_diagonal(&Vec3::new(-1.0, 1.0, 1.0)));
    let e = mpm
        .step(&mut Tape::new(), &s, None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("particle 5") && e.contains("inverted"), "{e}");
    let mut b = MpmBuilder::new(16, 1.0 / 16.0);
    b.add_rect(
        Vec2::new(0.4, 0.4),
        Vec2::new(0.125, 0.125),
        1.0,
        1.0,
        material,
    );
    let mpm = b.finalize::<f64>().unwrap();
    let s = mpm.state();
    s.f.set(5, Mat22::new(-1.0, 0.0, 0.0, 1.0));
    mpm.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
    let mut b = MpmBuilder::new(16, 1.0 / 16.0);
    b.add_rect(
        Vec2::new(0.4, 0.4),
        Vec2::new(0.125, 0.125),
        1.0,
        1.0,
        Material::NeoHookean {
            mu: 10.0,
            lambda: 10.0,
        },
    );
    let mpm = b.finalize::<f64>().unwrap();
    let s = mpm.state();
    s.f.set(2, Mat22::new(-1.0, 0.0, 0.0, 1.0));
    let e = mpm
        .step(&mut Tape::new(), &s, None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("particle 2") && e.contains("inverted"), "{e}");
    // A state array of the wrong length.
    let short = MpmState {
        v: Array::zeros(3).named("v"),
        ..mpm.state()
    };
    let e = mpm
        .step(&mut Tape::new(), &short, None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("3 values"), "{e}");
}

/// A jelly cube in 3D: free fall exactly as symplectic Euler, then a rollout's gradient
/// with respect to the moduli and gravity against central differences, and forward mode
/// against reverse mode.
#[test]
fn three_d_rollouts_fall_exactly_and_differentiate() {
    let mut b = MpmBuilder::new_3d(16, 1.0 / 16.0);
    let g = Vec3::new(0.4, -9.8, -0.3);
    b.set_gravity(g);
    b.add_rect(
        Vec3::new(0.4, 0.5, 0.4),
        Vec3::new(0.125, 0.125, 0.125),
        1.0,
        1.0,
        Material::Corotated {
            mu: 20.0,
            lambda: 20.0,
        },
    );
    let mpm = b.finalize::<f64>().unwrap();
    assert_eq!(mpm.particle_count(), 4 * 4 * 4);
    let (dt, steps) = (1e-3, 20);
    let mut tape = Tape::new();
    let s0 = mpm.state();
    let mut s = s0.clone();
    for _ in 0..steps {
        s = mpm.step(&mut tape, &s, None, dt).unwrap();
    }
    let shift = g * (dt * dt * (steps * (steps + 1)) as f64 / 2.0);
    for (x, x0) in s.x.to_vec().iter().zip(s0.x.to_vec()) {
        assert!(
            (x - (x0 + shift)).norm() < 1e-12,
            "{x:?} vs {:?}",
            x0 + shift
        );
    }

    // On the floor (sticky, then Coulomb), with a spin so that the cube deforms.
    for floor in [Floor::Sticky, Floor::Coulomb(0.4)] {
        let mut b = MpmBuilder::new_3d(12, 1.0 / 12.0);
        b.set_floor(floor);
        let r = b.add_rect(
            Vec3::new(0.35, 0.26, 0.35),
            Vec3::new(0.25, 0.17, 0.25),
            1.0,
            1.0,
            Material::NeoHookean {
                mu: 10.0,
                lambda: 10.0,
            },
        );
        let xs: Vec<Vec3<f64>> = b.clone().finalize::<f64>().unwrap().state().x.to_vec();
        for (p, x) in r.zip(&xs) {
            b.set_velocity(p, Vec3::new(0.2 - (x.y - 0.35), -0.5, 0.3 * (x.x - 0.45)));
        }
        let mpm = b.finalize::<f64>().unwrap();
        let loss = |tape: &mut Tape| {
            let mut s = mpm.state();
            for _ in 0..15 {
                s = mpm.step(tape, &s, None, 2e-3).unwrap();
            }
            let c = mpm.mean_position(tape, &s);
            let out = Array::zeros(1);
            tape.launch(minus_x3, 1, (&c, &out));
            out
        };
        GradCheck::new()
            .run(loss, &[&mpm.mu, &mpm.lambda, &mpm.gravity, &mpm.mass])
            .unwrap()
            .assert_within(1e-6);
        assert!(mpm.mu.grad().unwrap().to_vec().iter().any(|g| *g != 0.0));
        let run = |tape: &mut Tape| {
            let mut s = mpm.state();
            for _ in 0..15 {
                s = mpm.step(tape, &s, None, 2e-3).unwrap();
            }
            vec![s.x.boxed(), s.f.boxed()]
        };
        dot_test(run, &[&mpm.mu, &mpm.lambda, &mpm.gravity], 8)
            .unwrap()
            .assert_within(1e-10);
    }
}

/// `loss[0] = -c[0].x + c[0].y + c[0].z` (3D).
#[diff_kernel]
fn minus_x3<R: Real>(c: &Array<Vec3<R>>, loss: &Array<R>) {
    loss[0] = -c[0].x + c[0].y + c[0].z;
}
