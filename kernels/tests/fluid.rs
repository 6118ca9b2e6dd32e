//! Grid fluids: each kernel and whole smoke rollouts against central differences in f64 and
//! forward mode against reverse mode, through both pressure solves; the projection's exact
//! zero divergence; the Jacobi gradient tending to the CG one (implicit function theorem) as
//! its iteration count grows; the CG step's constant tape length; errors.

use adflex_kernels::fluid::kernels::{advect, divergence, pressure_jacobi, subtract_gradient};
use adflex_kernels::fluid::scenes::{filter_axis, squared_error, SmokeTask};
use adflex_kernels::fluid::{FluidGrid, Pressure};
use adflex_kernels::solver::krylov::SolveSettings;
use adflex_runtime::gradcheck::{dot_test, GradCheck};
use adflex_runtime::prelude::*;

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn field(&mut self, n: usize, lo: f64, hi: f64, name: &str) -> Array<f64> {
        Array::from_vec(
            (0..n)
                .map(|_| lo + (hi - lo) * self.next())
                .collect::<Vec<_>>(),
        )
        .named(name)
    }
}

#[test]
fn each_kernel_matches_central_differences_and_its_tangent() {
    let n = 8;
    let c = n * n;
    let mut r = Rng(3);
    let q = r.field(c, -1.0, 1.0, "q");
    let u = r.field(c, -2.0, 2.0, "u");
    let v = r.field(c, -2.0, 2.0, "v");
    let p = r.field(c, -1.0, 1.0, "p");
    let out = Array::<f64>::zeros(c).named("out");
    let out2 = Array::<f64>::zeros(c).named("out2");
    // Advection backtraces up to 2 cells, some past the walls (clamped).
    GradCheck::new()
        .kernel(advect, c, (&q, &u, &v, n, 0.9, &out))
        .unwrap()
        .assert_within(1e-6);
    let run = |tape: &mut Tape| {
        let o = out.zeros_like();
        tape.launch(advect, c, (&q, &u, &v, n, 0.9, &o));
        vec![o.boxed()]
    };
    dot_test(run, &[&q, &u, &v], 1)
        .unwrap()
        .assert_within(1e-10);
    GradCheck::new()
        .kernel(divergence, c, (&u, &v, n, 0.1, &out))
        .unwrap()
        .assert_within(1e-6);
    GradCheck::new()
        .kernel(subtract_gradient, c, (&u, &v, &p, n, 0.1, &out, &out2))
        .unwrap()
        .assert_within(1e-6);
    GradCheck::new()
        .kernel(pressure_jacobi, c, (&p, &q, n, -0.04, &out))
        .unwrap()
        .assert_within(1e-6);
    let run = |tape: &mut Tape| {
        let (a, b, d, j) = (
            out.zeros_like(),
            out.zeros_like(),
            out.zeros_like(),
            out.zeros_like(),
        );
        tape.launch(divergence, c, (&u, &v, n, 0.1, &d));
        tape.launch(subtract_gradient, c, (&u, &v, &p, n, 0.1, &a, &b));
        tape.launch(pressure_jacobi, c, (&p, &q, n, -0.04, &j));
        vec![a.boxed(), b.boxed(), d.boxed(), j.boxed()]
    };
    dot_test(run, &[&u, &v, &p, &q], 2)
        .unwrap()
        .assert_within(1e-10);
}

#[test]
fn projection_leaves_no_divergence_and_jacobi_converges_to_it() {
    let grid = FluidGrid::new(16, 1.0 / 16.0).unwrap();
    let mut r = Rng(5);
    let u = r.field(256, -1.0, 1.0, "u");
    let v = r.field(256, -1.0, 1.0, "v");
    let mut tape = Tape::new();
    let before = grid.divergence(&mut tape, &u, &v).unwrap().to_vec();
    let (pu, pv) = grid.project(&mut tape, &u, &v, &Pressure::cg()).unwrap();
    let after = grid.divergence(&mut tape, &pu, &pv).unwrap().to_vec();
    let max = |d: &[f64]| d.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(
        max(&after) < 1e-8 * max(&before),
        "{} -> {}",
        max(&before),
        max(&after)
    );
    // Jacobi's residual divergence falls with its iteration count.
    let mut last = f64::INFINITY;
    for k in [10, 100, 1000] {
        let (ju, jv) = grid
            .project(&mut tape, &u, &v, &Pressure::Jacobi(k))
            .unwrap();
        let d = max(&grid.divergence(&mut tape, &ju, &jv).unwrap().to_vec());
        assert!(d < last, "{k} iterations: {d} after {last}");
        last = d;
    }
}

/// `steps` steps of smoke from `(u0, v0)` carrying `d0`; the loss is the squared distance of
/// the final density to `target`.
#[allow(clippy::too_many_arguments)]
fn smoke_loss(
    grid: &FluidGrid,
    tape: &mut Tape,
    u0: &Array<f64>,
    v0: &Array<f64>,
    d0: &Array<f64>,
    target: &Array<f64>,
    steps: usize,
    method: &Pressure,
) -> Array<f64> {
    let (mut u, mut v, mut d) = (u0.clone(), v0.clone(), d0.clone());
    for _ in 0..steps {
        (u, v, d) = grid.step(tape, &u, &v, &d, 0.03, method).unwrap();
    }
    let loss = Array::zeros(1).named("loss");
    tape.launch(squared_error, grid.cells(), (&d, target, &loss));
    loss
}

fn smoke_setup() -> (FluidGrid, [Array<f64>; 4]) {
    let grid = FluidGrid::new(8, 1.0 / 8.0).unwrap();
    let mut r = Rng(9);
    let c = grid.cells();
    (
        grid,
        [
            r.field(c, -1.0, 1.0, "u0"),
            r.field(c, -1.0, 1.0, "v0"),
            r.field(c, 0.0, 1.0, "density0"),
            r.field(c, 0.0, 1.0, "target"),
        ],
    )
}

#[test]
fn smoke_rollout_gradients_match_central_differences_with_both_pressure_solves() {
    let (grid, [u0, v0, d0, target]) = smoke_setup();
    for method in [Pressure::Jacobi(20), Pressure::cg()] {
        let report = GradCheck::new()
            .run(
                |tape| smoke_loss(&grid, tape, &u0, &v0, &d0, &target, 4, &method),
                &[&u0, &v0, &d0],
            )
            .unwrap();
        report.assert_within(1e-6);
        assert!(u0.grad().unwrap().to_vec().iter().any(|g| *g != 0.0));
        let run = |tape: &mut Tape| {
            let (mut u, mut v, mut d) = (u0.clone(), v0.clone(), d0.clone());
            for _ in 0..4 {
                (u, v, d) = grid.step(tape, &u, &v, &d, 0.03, &method).unwrap();
            }
            vec![u.boxed(), v.boxed(), d.boxed()]
        };
        dot_test(run, &[&u0, &v0, &d0], 4)
            .unwrap()
            .assert_within(1e-10);
    }
}

/// The gradient of the loss with respect to the initial velocity.
fn velocity_gradient(method: &Pressure) -> (Vec<f64>, usize) {
    let (grid, [u0, v0, d0, target]) = smoke_setup();
    let _ = u0.clone().requires_grad();
    let _ = v0.clone().requires_grad();
    let mut tape = Tape::new();
    let loss = smoke_loss(&grid, &mut tape, &u0, &v0, &d0, &target, 3, method);
    tape.backward(&loss).unwrap();
    let mut g = u0.grad().unwrap().to_vec();
    g.extend(v0.grad().unwrap().to_vec());
    (g, tape.len())
}

#[test]
fn jacobi_gradients_tend_to_the_implicit_cg_gradient() {
    let (cg, cg_len) = velocity_gradient(&Pressure::cg());
    let norm = cg.iter().map(|g| g * g).sum::<f64>().sqrt();
    let mut errors = Vec::new();
    for k in [5, 20, 80, 320, 1280] {
        let (j, len) = velocity_gradient(&Pressure::Jacobi(k));
        let e = j
            .iter()
            .zip(&cg)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt()
            / norm;
        errors.push((k, e, len));
    }
    for w in errors.windows(2) {
        assert!(w[1].1 < w[0].1, "{errors:?}");
    }
    assert!(errors.last().unwrap().1 < 1e-8, "{errors:?}");
    // The CG step is one record per solve whatever its iteration count; Jacobi's k records.
    assert!(errors[4].2 > cg_len + 3 * 1000, "{errors:?} vs {cg_len}");
}

#[test]
fn bad_grids_inputs_and_unconverged_solves_are_errors() {
    assert!(FluidGrid::new(7, 0.1)
        .unwrap_err()
        .to_string()
        .contains("even"));
    assert!(FluidGrid::new(8, f64::NAN)
        .unwrap_err()
        .to_string()
        .contains("dx"));
    let grid = FluidGrid::new(8, 0.125).unwrap();
    let (u, short) = (
        Array::<f64>::zeros(64),
        Array::<f64>::zeros(10).named("short"),
    );
    let mut tape = Tape::new();
    let e = grid
        .step(&mut tape, &u, &short, &u, 0.01, &Pressure::cg())
        .unwrap_err()
        .to_string();
    assert!(e.contains("short") && e.contains("64 cells"), "{e}");
    assert!(grid
        .step(&mut tape, &u, &u, &u, 0.0, &Pressure::cg())
        .is_err());
    let mut r = Rng(1);
    let (u, v) = (r.field(64, -1.0, 1.0, "u"), r.field(64, -1.0, 1.0, "v"));
    let few = Pressure::Cg(SolveSettings {
        rel_tol: 1e-14,
        abs_tol: 0.0,
        max_iter: 2,
    });
    let e = grid
        .project(&mut tape, &u, &v, &few)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("fluid pressure CG (forward)") && e.contains("max_iter"),
        "{e}"
    );
}

/// Semi-Lagrangian advection is stable at any CFL number: with bilinear interpolation the
/// density stays within its initial bounds, at 0.5 and at 8 cells per step alike, while the
/// projection keeps the velocity divergence-free.
#[test]
fn advection_is_bounded_at_any_cfl_number() {
    for cfl in [0.5, 8.0] {
        let grid = FluidGrid::new(16, 1.0 / 16.0).unwrap();
        let mut r = Rng(31);
        let u = r.field(256, -1.0, 1.0, "u");
        let v = r.field(256, -1.0, 1.0, "v");
        let d0 = r.field(256, 0.2, 0.9, "density");
        let mut tape = Tape::new();
        let (mut u, mut v) = grid.project(&mut tape, &u, &v, &Pressure::cg()).unwrap();
        let mut d = d0.clone();
        // dt so that the fastest cell moves `cfl` cells per step.
        let speed = u
            .to_vec()
            .iter()
            .chain(&v.to_vec())
            .fold(0.0f64, |m, x| m.max(x.abs()));
        let dt = cfl * grid.dx() / speed;
        for _ in 0..40 {
            (u, v, d) = grid
                .step(&mut tape, &u, &v, &d, dt, &Pressure::cg())
                .unwrap();
        }
        let d = d.to_vec();
        let (lo, hi) = d
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
        assert!(
            lo >= 0.2 - 1e-12 && hi <= 0.9 + 1e-12,
            "CFL {cfl}: density in [{lo}, {hi}]"
        );
        let div = grid.divergence(&mut tape, &u, &v).unwrap().to_vec();
        assert!(div.iter().all(|x| x.abs() < 1e-6), "CFL {cfl}");
    }
}

#[test]
fn three_d_kernels_projection_and_rollouts_differentiate() {
    use adflex_kernels::fluid::kernels::{
        advect3, divergence3, pressure_jacobi3, subtract_gradient3,
    };
    let n = 6;
    let c = n * n * n;
    let mut r = Rng(41);
    let q = r.field(c, -1.0, 1.0, "q");
    let (u, v, w) = (
        r.field(c, -2.0, 2.0, "u"),
        r.field(c, -2.0, 2.0, "v"),
        r.field(c, -2.0, 2.0, "w"),
    );
    let p = r.field(c, -1.0, 1.0, "p");
    let outs = [(); 3].map(|_| Array::<f64>::zeros(c));
    GradCheck::new()
        .kernel(advect3, c, (&q, &u, &v, &w, n, 0.9, &outs[0]))
        .unwrap()
        .assert_within(1e-6);
    GradCheck::new()
        .kernel(divergence3, c, (&u, &v, &w, n, 0.1, &outs[0]))
        .unwrap()
        .assert_within(1e-6);
    GradCheck::new()
        .kernel(
            subtract_gradient3,
            c,
            (&u, &v, &w, &p, n, 0.1, &outs[0], &outs[1], &outs[2]),
        )
        .unwrap()
        .assert_within(1e-6);
    GradCheck::new()
        .kernel(pressure_jacobi3, c, (&p, &q, n, -0.04, &outs[0]))
        .unwrap()
        .assert_within(1e-6);
    let run = |tape: &mut Tape| {
        let o = [(); 6].map(|_| Array::<f64>::zeros(c));
        tape.launch(advect3, c, (&q, &u, &v, &w, n, 0.9, &o[0]));
        tape.launch(divergence3, c, (&u, &v, &w, n, 0.1, &o[1]));
        tape.launch(
            subtract_gradient3,
            c,
            (&u, &v, &w, &p, n, 0.1, &o[2], &o[3], &o[4]),
        );
        tape.launch(pressure_jacobi3, c, (&p, &q, n, -0.04, &o[5]));
        o.into_iter().map(|a| a.boxed()).collect()
    };
    dot_test(run, &[&q, &u, &v, &w, &p], 3)
        .unwrap()
        .assert_within(1e-10);

    // The projection leaves no divergence.
    let grid = FluidGrid::new_3d(8, 1.0 / 8.0).unwrap();
    let mut r = Rng(43);
    let vel = [(); 3].map(|_| r.field(512, -1.0, 1.0, "velocity"));
    let mut tape = Tape::new();
    let before = grid
        .divergence_3d(&mut tape, &vel[0], &vel[1], &vel[2])
        .unwrap()
        .to_vec();
    let [pu, pv, pw] = grid
        .project_3d(&mut tape, [&vel[0], &vel[1], &vel[2]], &Pressure::cg())
        .unwrap();
    let after = grid
        .divergence_3d(&mut tape, &pu, &pv, &pw)
        .unwrap()
        .to_vec();
    let max = |d: &[f64]| d.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(
        max(&after) < 1e-8 * max(&before),
        "{} -> {}",
        max(&before),
        max(&after)
    );
    // A 2D call on a 3D grid is an error, not a wrong answer.
    assert!(grid.project(&mut tape, &pu, &pv, &Pressure::cg()).is_err());

    // Smoke rollouts in 3D through both pressure solves, against central differences.
    let grid = FluidGrid::new_3d(6, 1.0 / 6.0).unwrap();
    let mut r = Rng(47);
    let [u0, v0, w0, d0, target] = [(); 5].map(|_| r.field(216, -1.0, 1.0, "field"));
    for method in [Pressure::Jacobi(10), Pressure::cg()] {
        let loss = |tape: &mut Tape| {
            let (mut vel, mut d) = ([u0.clone(), v0.clone(), w0.clone()], d0.clone());
            for _ in 0..3 {
                (vel, d) = grid
                    .step_3d(tape, [&vel[0], &vel[1], &vel[2]], &d, 0.05, &method)
                    .unwrap();
            }
            let out = Array::zeros(1);
            tape.launch(squared_error, 216, (&d, &target, &out));
            out
        };
        GradCheck::new()
            .run(loss, &[&u0, &v0, &w0, &d0])
            .unwrap()
            .assert_within(1e-6);
        assert!(w0.grad().unwrap().to_vec().iter().any(|g| *g != 0.0));
    }
}

/// The CG's host operator is the matrix the Jacobi kernels iterate with, and symmetric (so
/// the adjoint solve with the same operator is the transposed one), in 2D and 3D; 2D calls on
/// a 3D grid are errors.
#[test]
fn the_pressure_operator_is_symmetric_and_the_jacobi_one() {
    use adflex_kernels::fluid::apply_pressure_operator;
    for (n, dim) in [(6usize, 2usize), (4, 3)] {
        let c = n.pow(dim as u32);
        let column = |j: usize| {
            let mut e = vec![0.0; c];
            e[j] = 1.0;
            let mut out = vec![0.0; c];
            apply_pressure_operator(n, dim, &e, &mut out);
            out
        };
        let a: Vec<Vec<f64>> = (0..c).map(column).collect();
        for (i, row) in a.iter().enumerate() {
            for (j, x) in row.iter().enumerate() {
                assert_eq!(*x, a[j][i], "{dim}D: A[{i}][{j}]");
            }
        }
        // Many Jacobi iterations reach the CG pressure.
        let grid = if dim == 2 {
            FluidGrid::new(n, 0.1)
        } else {
            FluidGrid::new_3d(n, 0.1)
        }
        .unwrap();
        let div = Rng(53).field(c, -1.0, 1.0, "div");
        let mut tape = Tape::new();
        let cg = grid
            .pressure(&mut tape, &div, &Pressure::cg())
            .unwrap()
            .to_vec();
        let jacobi = grid
            .pressure(&mut tape, &div, &Pressure::Jacobi(3000))
            .unwrap()
            .to_vec();
        let scale = cg.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        for (a, b) in cg.iter().zip(&jacobi) {
            assert!((a - b).abs() < 1e-9 * scale, "{dim}D: {a} vs {b}");
        }
    }
    let grid = FluidGrid::new_3d(4, 0.25).unwrap();
    let f = Array::<f64>::zeros(64);
    let e = grid
        .advect(&mut Tape::new(), &f, &f, &f, 0.1)
        .unwrap_err()
        .to_string();
    assert!(e.contains("2D"), "{e}");
    assert!(grid.divergence(&mut Tape::new(), &f, &f).is_err());
}

/// The smoothed smoke task: the filter kernel along each axis (asymmetric weights, cells near
/// both walls) against central differences, forward against reverse, and its values on a
/// single-cell spike (the documented direction); the task's loss through the velocity filter,
/// a rollout and the coarse term against central differences; the filter of a constant field
/// is the constant away from the walls and less at them (zero outside); bad widths are errors
/// naming the method.
#[test]
fn the_smoothed_smoke_task_differentiates_through_its_filter() {
    let n = 10;
    let c = n * n;
    let mut r = Rng(21);
    let q = r.field(c, -1.0, 1.0, "q");
    let weights = [0.05, 0.15, 0.4, 0.3, 0.1];
    let w = Array::from_vec(weights.to_vec()).named("weights");
    let out = Array::<f64>::zeros(c).named("out");
    for axis in 0..2 {
        GradCheck::new()
            .kernel(filter_axis, c, (&q, &w, n, 2usize, axis, &out))
            .unwrap()
            .assert_within(1e-6);
        let run = |tape: &mut Tape| {
            let o = out.zeros_like();
            tape.launch(filter_axis, c, (&q, &w, n, 2usize, axis, &o));
            vec![o.boxed()]
        };
        dot_test(run, &[&q, &w], 2).unwrap().assert_within(1e-10);
        // A spike at cell (4, 6): out[t] = w[k] where t is k - 2 cells before the spike.
        let mut spike = vec![0.0; c];
        spike[4 * n + 6] = 1.0;
        let spike = Array::from_vec(spike);
        let o = out.zeros_like();
        launch(filter_axis, c, (&spike, &w, n, 2usize, axis, &o));
        let o = o.to_vec();
        let stride = if axis == 0 { n } else { 1 };
        for (k, wk) in weights.iter().enumerate() {
            let t = 4 * n + 6 + 2 * stride - k * stride;
            assert_eq!(o[t], *wk, "axis {axis}, k {k}");
        }
        assert!((o.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }
    let task = SmokeTask::new(12, 5, Pressure::cg())
        .unwrap()
        .smoothed(1.5)
        .unwrap()
        .with_coarse_loss(2.0)
        .unwrap();
    let ones = Array::from_vec(vec![1.0; 144]);
    task.u0.assign(&ones.to_vec());
    let mut tape = Tape::new();
    let (u, _) = task.initial_velocity(&mut tape);
    let u = u.to_vec();
    // 1.5 cells: cut at 5 cells, so the centre (5..7) sees no wall.
    assert!((u[6 * 12 + 6] - 1.0).abs() < 1e-12, "{}", u[6 * 12 + 6]);
    assert!(u[0] < 0.5 && u[0] > 0.0, "{}", u[0]);
    task.u0.assign(&r.field(144, -0.5, 0.5, "").to_vec());
    task.v0.assign(&r.field(144, -0.5, 0.5, "").to_vec());
    GradCheck::new()
        .run(|tape| task.loss(tape).unwrap(), &[&task.u0, &task.v0])
        .unwrap()
        .assert_within(1e-6);
    assert!(task.u0.grad().unwrap().to_vec().iter().any(|g| *g != 0.0));
    let coarse = task.loss(&mut Tape::new()).unwrap().get(0) - task.distance().unwrap();
    assert!(coarse > 1e-3, "the coarse term adds {coarse}");
    for bad in [-1.0, f64::NAN, f64::INFINITY, 13.0] {
        let task = || SmokeTask::new(12, 5, Pressure::cg()).unwrap();
        let e = task().smoothed(bad).unwrap_err().to_string();
        assert!(
            e.contains("SmokeTask::smoothed") && e.contains("12 cells"),
            "{e}"
        );
        let e = task().with_coarse_loss(bad).unwrap_err().to_string();
        assert!(e.contains("SmokeTask::with_coarse_loss"), "{e}");
    }
}

/// The smoke task is mirror-symmetric about `x = 1/2`, so at a mirror-symmetric flow (`u`
/// odd, `v` even) the gradient must be too: `gu` odd and `gv` even, to rounding. (At rest it
/// is not: every backtraced point lands on a cell centre, where the bilinear interpolation's
/// derivative is one-sided; measured there, the asymmetry is as large as the gradient.)
#[test]
fn the_smoke_gradient_keeps_the_tasks_mirror_symmetry() {
    let n = 32;
    let task = SmokeTask::new(n, 30, Pressure::cg()).unwrap();
    let (u, v): (Vec<f64>, Vec<f64>) = (0..n * n)
        .map(|t| {
            let x = ((t / n) as f64 + 0.5) / n as f64 - 0.5;
            let y = ((t % n) as f64 + 0.5) / n as f64 - 0.35;
            let g = (-(x * x + y * y) / 0.045).exp();
            (0.3 * x * y * g / 0.0225, 0.3 * g * (1.0 - x * x / 0.0225))
        })
        .unzip();
    task.u0.assign(&u);
    task.v0.assign(&v);
    task.loss_and_grad().unwrap();
    let (gu, gv) = (
        task.u0.grad().unwrap().to_vec(),
        task.v0.grad().unwrap().to_vec(),
    );
    let (mut asymmetry, mut size) = (0.0f64, 0.0f64);
    for t in 0..n * n {
        let m = (n - 1 - t / n) * n + t % n;
        asymmetry = asymmetry
            .max((gu[t] + gu[m]).abs())
            .max((gv[t] - gv[m]).abs());
        size = size.max(gu[t].abs()).max(gv[t].abs());
    }
    assert!(size > 0.1, "{size}");
    assert!(asymmetry < 1e-12 * size, "{asymmetry:e} of {size:e}");
}
