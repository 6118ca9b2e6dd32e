//! The physics families through their common face (`adflex_kernels::family`): the one list of
//! families against the folders and the architecture table, one generic rollout and one
//! generic checkpointed rollout for every family (the same bits, the gradients against
//! central differences), and the errors a generic caller gets.

use adflex_kernels::articulation::{urdf, Articulations};
use adflex_kernels::family::{self, families, Family, ParticleSystem};
use adflex_kernels::fluid::{FluidGrid, FluidState, Pressure};
use adflex_kernels::integrators::ImplicitEuler;
use adflex_kernels::mpm::{Material, Mpm, MpmBuilder, MpmState, D3};
use adflex_kernels::{Model, ModelBuilder, SemiImplicitEuler};
use adflex_macros::diff_kernel;
use adflex_runtime::checkpoint::Checkpoint;
use adflex_runtime::prelude::*;

/// `loss[0] = sum_i w_i x_i` over the components of `x`: a loss that reads every element.
#[diff_kernel]
fn weighted_vec3(x: &Array<Vec3<f64>>, loss: &Array<f64>) {
    let i = tid();
    let w = 1.0 + 0.1 * (i as f64);
    loss.atomic_add(0, w * (x[i].x + 2.0 * x[i].y - 0.5 * x[i].z));
}

#[diff_kernel]
fn weighted_vec2(x: &Array<Vec2<f64>>, loss: &Array<f64>) {
    let i = tid();
    let w = 1.0 + 0.1 * (i as f64);
    loss.atomic_add(0, w * (x[i].x + 2.0 * x[i].y));
}

#[diff_kernel]
fn weighted(x: &Array<f64>, loss: &Array<f64>) {
    let i = tid();
    let w = 1.0 + 0.1 * (i as f64);
    loss.atomic_add(0, w * x[i] * x[i]);
}

/// A loss over a family's state.
type LossFn<'a, S> = &'a dyn Fn(&mut Tape, &S) -> Result<Array<f64>, Error>;

/// A case: a family, a state whose first array requires gradients, a control and a loss.
struct Case<'a, F: Family<f64>> {
    family: &'a F,
    control: F::Control,
    init: &'a dyn Fn() -> F::State,
    loss: LossFn<'a, F::State>,
    steps: usize,
    dt: f64,
}

/// The loss and the gradient with respect to the first array of the initial state, by one
/// rollout on one tape or checkpointed every `every` steps (`None`).
fn run<F: Family<f64>>(c: &Case<'_, F>, every: Option<usize>) -> (f64, Vec<u64>) {
    let s0 = (c.init)();
    let out = match every {
        None => {
            let mut tape = Tape::new();
            let end = family::rollout(c.family, &mut tape, &s0, &c.control, c.steps, c.dt).unwrap();
            let l = (c.loss)(&mut tape, &end).unwrap();
            tape.backward(&l).unwrap();
            l.get(0)
        }
        Some(every) => {
            family::checkpointed_rollout(c.family, &s0, &c.control, c.steps, every, c.dt, c.loss)
                .unwrap()
                .loss
                .get(0)
        }
    };
    let a = s0.arrays()[0];
    let g = a.grad_any().expect("the first array requires gradients");
    let g = (0..a.len() * a.element_dim()).map(|k| g.scalar(k).to_bits());
    (out, g.collect())
}

/// A checkpointed rollout against a rollout on one tape (the same bits), and the gradient
/// against a central difference along a fixed direction `d_k = sin(1.7 k + 0.3)` over the
/// scalars of the first array.
fn check_family<F: Family<f64>>(c: &Case<'_, F>) {
    let (l, g) = run(c, None);
    let (lc, gc) = run(c, Some(3));
    assert_eq!(l.to_bits(), lc.to_bits(), "{}: loss", F::NAME);
    assert_eq!(g, gc, "{}: the checkpointed gradient", F::NAME);
    let g: Vec<f64> = g.into_iter().map(f64::from_bits).collect();
    let dir = |k: usize| (1.7 * k as f64 + 0.3).sin();
    let at = |h: f64| {
        let s = (c.init)();
        let a = s.arrays()[0];
        for k in 0..a.len() * a.element_dim() {
            a.set_scalar(k, a.scalar(k) + h * dir(k));
        }
        let mut tape = Tape::new();
        let end = family::rollout(c.family, &mut tape, &s, &c.control, c.steps, c.dt).unwrap();
        (c.loss)(&mut tape, &end).unwrap().get(0)
    };
    let h = 1e-6;
    let fd = (at(h) - at(-h)) / (2.0 * h);
    let analytic: f64 = g.iter().enumerate().map(|(k, g)| g * dir(k)).sum();
    assert!(
        analytic.abs() > 1e-3,
        "{}: a vanishing derivative {analytic}",
        F::NAME
    );
    assert!(
        (fd - analytic).abs() <= 1e-6 * fd.abs(),
        "{}: gradient {analytic} against central difference {fd}",
        F::NAME
    );
}

fn particles() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let p: Vec<u32> = (0..4)
        .map(|i| {
            let x = Vec3::new(0.3 * i as f64, 1.0 + 0.05 * i as f64, 0.1 * (i % 2) as f64);
            b.add_particle(
                x,
                Vec3::new(0.2 * i as f64, -0.3, 0.1 - 0.1 * i as f64),
                0.1,
            )
        })
        .collect();
    for w in p.windows(2) {
        b.add_spring(w[0], w[1], 200.0, 0.5);
    }
    b.finalize()
}

#[test]
fn every_family_is_listed_once_and_in_the_architecture_table() {
    let list = families();
    let names: Vec<&str> = list.iter().map(|f| f.name).collect();
    let mut unique = names.clone();
    unique.sort_unstable();
    unique.dedup();
    assert_eq!(
        unique.len(),
        names.len(),
        "a family listed twice: {names:?}"
    );
    let src = concat!(env!("CARGO_MANIFEST_DIR"), "/src/");
    for f in &list {
        assert!(
            std::path::Path::new(&format!("{src}{}", f.path)).exists(),
            "family `{}`: `kernels/src/{}` does not exist",
            f.name,
            f.path
        );
    }
    // docs/architecture.md's table of families: `| `name` | `kernels/src/path` | ... |`.
    let doc = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/architecture.md"
    ))
    .unwrap();
    let table: Vec<(String, String)> = doc
        .lines()
        .skip_while(|l| !l.starts_with("| family |"))
        .skip(2)
        .take_while(|l| l.starts_with('|'))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            (
                cells[1].trim_matches('`').to_string(),
                cells[2].trim_matches('`').to_string(),
            )
        })
        .collect();
    let expected: Vec<(String, String)> = list
        .iter()
        .map(|f| (f.name.to_string(), format!("kernels/src/{}", f.path)))
        .collect();
    assert_eq!(
        table, expected,
        "docs/architecture.md's table of families differs from `family::families()`"
    );
}

#[test]
fn every_family_rolls_out_and_checkpoints_to_the_same_bits_with_right_gradients() {
    // Particles with springs, by semi-implicit Euler and by implicit Euler.
    let model = particles();
    for integrator in [
        &SemiImplicitEuler as &dyn adflex_kernels::Integrator<f64>,
        &ImplicitEuler::default(),
    ] {
        let sys = ParticleSystem::new(&model, integrator);
        let init = || {
            let s = sys.initial_state();
            let _ = s.x.clone().requires_grad();
            s
        };
        let loss = |tape: &mut Tape, s: &adflex_kernels::State<f64>| {
            let l = Array::zeros(1);
            tape.launch(weighted_vec3, s.x.len(), (&s.x, &l));
            Ok(l)
        };
        check_family(&Case {
            family: &sys,
            control: sys.default_control(),
            init: &init,
            loss: &loss,
            steps: 7,
            dt: 2e-3,
        });
    }

    // A robot arm under gravity.
    let arm: Articulations<f64> = urdf::load(
        concat!(env!("CARGO_MANIFEST_DIR"), "/robots/arm7.urdf"),
        &Default::default(),
    )
    .unwrap()
    .finalize()
    .unwrap();
    let init = || {
        let s = arm.initial_state();
        let _ = s.q.clone().requires_grad();
        s
    };
    let loss = |tape: &mut Tape, s: &adflex_kernels::articulation::ArticulationState<f64>| {
        let l = Array::zeros(1);
        tape.launch(weighted, s.q.len(), (&s.q, &l));
        Ok(l)
    };
    check_family(&Case {
        family: &arm,
        control: arm.default_control(),
        init: &init,
        loss: &loss,
        steps: 7,
        dt: 1e-3,
    });

    // An elastic MPM block, in 2D and in 3D, thrown with a shearing velocity.
    let (mu, lambda) = Material::lame(400.0, 0.2);
    let mut b = MpmBuilder::new(16, 1.0 / 16.0);
    let block = Material::Corotated { mu, lambda };
    b.add_rect([0.4, 0.4].into(), [0.2, 0.2].into(), 1e-2, 1e-2, block);
    let mpm: Mpm<f64> = b.finalize().unwrap();
    let init = || {
        let s = mpm.initial_state();
        let v: Vec<Vec2<f64>> = (s.x.to_vec().iter())
            .map(|p| Vec2::new(2.0 * (p.y - 0.5), 0.5 - p.x))
            .collect();
        s.v.assign(&v);
        let _ = s.x.clone().requires_grad();
        s
    };
    let loss = |tape: &mut Tape, s: &MpmState<f64>| {
        let l = Array::zeros(1);
        tape.launch(weighted_vec2, s.x.len(), (&s.x, &l));
        Ok(l)
    };
    check_family(&Case {
        family: &mpm,
        control: mpm.default_control(),
        init: &init,
        loss: &loss,
        steps: 7,
        dt: 1e-3,
    });
    let mut b = MpmBuilder::new_3d(12, 1.0 / 12.0);
    let size = Vec3::new(0.25, 0.25, 0.25);
    b.add_rect(Vec3::new(0.35, 0.35, 0.35), size, 1e-2, 1e-3, block);
    let mpm: Mpm<f64, D3> = b.finalize().unwrap();
    let init = || {
        let s = mpm.initial_state();
        let v: Vec<Vec3<f64>> = (s.x.to_vec().iter())
            .map(|p| Vec3::new(2.0 * (p.y - 0.5), 0.5 - p.z, p.x - 0.5))
            .collect();
        s.v.assign(&v);
        let _ = s.x.clone().requires_grad();
        s
    };
    let loss = |tape: &mut Tape, s: &MpmState<f64, D3>| {
        let l = Array::zeros(1);
        tape.launch(weighted_vec3, s.x.len(), (&s.x, &l));
        Ok(l)
    };
    check_family(&Case {
        family: &mpm,
        control: mpm.default_control(),
        init: &init,
        loss: &loss,
        steps: 7,
        dt: 1e-3,
    });

    // Smoke on a 3D grid (CG pressure).
    let grid = FluidGrid::new_3d(6, 1.0 / 6.0).unwrap();
    let init = || {
        let s: FluidState<f64> = grid.initial_state();
        let c = grid.cells();
        for (k, a) in s.velocity.iter().chain([&s.density]).enumerate() {
            a.assign(
                &(0..c)
                    .map(|i| ((i * (3 + 2 * k)) % 7) as f64 * 0.1 - 0.27)
                    .collect::<Vec<_>>(),
            );
        }
        let _ = s.velocity[0].clone().requires_grad();
        s
    };
    let loss = |tape: &mut Tape, s: &FluidState<f64>| {
        let l = Array::zeros(1);
        tape.launch(weighted, s.density.len(), (&s.density, &l));
        Ok(l)
    };
    check_family(&Case {
        family: &grid,
        control: Pressure::cg(),
        init: &init,
        loss: &loss,
        steps: 4,
        dt: 0.02,
    });

    // Smoke on a grid, both pressure solves.
    let grid = FluidGrid::new(8, 1.0 / 8.0).unwrap();
    for pressure in [Pressure::Jacobi(20), Pressure::cg()] {
        let init = || {
            let s: FluidState<f64> = grid.initial_state();
            let c = grid.cells();
            let field = |a: &Array<f64>, f: &dyn Fn(usize) -> f64| {
                a.assign(&(0..c).map(f).collect::<Vec<_>>())
            };
            field(&s.velocity[0], &|i| ((i * 7) % 5) as f64 * 0.2 - 0.37);
            field(&s.velocity[1], &|i| ((i * 3) % 7) as f64 * 0.1 - 0.27);
            field(&s.density, &|i| ((i * 5) % 9) as f64 * 0.1);
            let _ = s.velocity[0].clone().requires_grad();
            s
        };
        let loss = |tape: &mut Tape, s: &FluidState<f64>| {
            let l = Array::zeros(1);
            tape.launch(weighted, s.density.len(), (&s.density, &l));
            Ok(l)
        };
        check_family(&Case {
            family: &grid,
            control: pressure,
            init: &init,
            loss: &loss,
            steps: 7,
            dt: 0.02,
        });
    }
}

#[test]
fn a_generic_caller_gets_errors_naming_the_step() {
    let model = particles();
    let sys = ParticleSystem::new(&model, &SemiImplicitEuler);
    let mut tape = Tape::new();
    let err = family::rollout(
        &sys,
        &mut tape,
        &sys.initial_state(),
        &sys.default_control(),
        5,
        -1.0,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("particles rollout step 0 of 5"), "{err}");
    assert!(err.contains("dt"), "{err}");

    // A robot's state or control of the wrong length is an error naming it, not a panic.
    let arm: Articulations<f64> = urdf::load(
        concat!(env!("CARGO_MANIFEST_DIR"), "/robots/arm7.urdf"),
        &Default::default(),
    )
    .unwrap()
    .finalize()
    .unwrap();
    let mut c = arm.default_control();
    c.tau = Array::zeros(3);
    let err = family::rollout(&arm, &mut tape, &arm.initial_state(), &c, 2, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("control.tau") && err.contains("articulations rollout step 0"),
        "{err}"
    );
    let mut s = arm.initial_state();
    s.qd = Array::zeros(2);
    let err = Family::<f64>::step(&arm, &mut tape, &s, &arm.default_control(), 1e-3)
        .unwrap_err()
        .to_string();
    assert!(err.contains("state.qd"), "{err}");

    let grid = FluidGrid::new(8, 1.0 / 8.0).unwrap();
    let mut s: FluidState<f64> = grid.initial_state();
    s.velocity.pop();
    let err = Family::<f64>::step(&grid, &mut tape, &s, &Pressure::cg(), 0.01)
        .unwrap_err()
        .to_string();
    assert!(err.contains("velocity") && err.contains("2D"), "{err}");

    let err = family::checkpointed_rollout(
        &sys,
        &sys.initial_state(),
        &sys.default_control(),
        0,
        1,
        1e-3,
        |_, s| Ok(s.x.clone()),
    )
    .expect_err("zero steps is an error")
    .to_string();
    assert!(err.contains("particles") && err.contains("steps"), "{err}");
}
