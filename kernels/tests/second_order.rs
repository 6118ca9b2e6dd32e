//! Hessian-vector products by forward over reverse (`second_order::hvp`): against central
//! differences of f64 gradients, symmetric, through kernels with every kind of construct,
//! through rollouts of library forces and integrators (taped and checkpointed), and refused
//! where they would be silently wrong.

use crate::common;

use adflex_kernels::articulation::{urdf, ArticulationState, Articulations};
use adflex_kernels::fluid::{FluidGrid, Pressure};
use adflex_kernels::forces::{Force, ForceContext, Param};
use adflex_kernels::integrators::{ImplicitEuler, Integrator, Rk4, SemiImplicitEuler};
use adflex_kernels::mpm::{Material, Mpm, MpmBuilder};
use adflex_kernels::statics::Equilibrium;
use adflex_kernels::{Model, ModelBuilder, State};
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;
use adflex_runtime::second_order::{hessian, hvp, hvp_with, Hvp};
use adflex_runtime::Element;

/// A kernel with a dynamic loop, stores to an intermediate, atomics, branches and many
/// builtins (vectors, matrices, transcendental functions).
#[diff_kernel]
fn busy<R: Real>(p: &Array<R>, v: &Array<Vec3<R>>, tmp: &Array<R>, loss: &Array<R>) {
    let i = tid();
    let a = v[i];
    let b = v[(i + 1) % 3];
    let k = p[i];
    let mut s = 0.0;
    let mut j = 0;
    while j < 3 {
        s = s + sin(k * p[j]) * exp(0.3 * p[j]);
        j += 1;
    }
    let c = cross(a, b);
    let m = outer(a, b) + mat33_identity() * (2.0 + k * k);
    let mi = inverse(m);
    let n = normalize(c + vec3(0.1, 0.2, 0.3));
    let q = dot(mi * a, n) + sqrt(1.0 + length_sq(c)) + atan2(k, 1.5 + p[0]);
    let r = if q > 0.0 {
        q * q * k
    } else {
        pow(1.0 + k * k, 1.5) - q
    };
    let t = r + s * tanh(k) + determinant(m) * 0.01;
    tmp[i] = t;
    loss.atomic_add(0, t * t + ln(1.0 + k * k) * dot(a, b));
}

fn busy_loss<R: Real + Element>(
    tape: &mut Tape,
    p: &Array<R>,
    v: &Array<Vec3<R>>,
) -> Result<Array<R>, Error> {
    let tmp = Array::<R>::zeros(3);
    let loss = Array::<R>::zeros(1);
    tape.launch(busy, 3, (p, v, &tmp, &loss));
    Ok(loss)
}

/// A parameter array given twice to `hvp` or `hessian` is refused (its second copy's
/// direction would overwrite the first's).
#[test]
fn a_parameter_given_twice_is_refused() {
    let p =
        Array::from_vec(vec![Dual::from(0.4), Dual::from(-0.3), Dual::from(0.9)]).requires_grad();
    let v = Array::from_vec(vec![
        Vec3::new(
            Dual::from(0.1),
            Dual::from(0.2),
            Dual::from(0.3)
        );
        3
    ]);
    let e = hvp(&[&p, &p], &[1.0; 6], |t| busy_loss(t, &p, &v)).unwrap_err();
    assert!(e.to_string().contains("given twice"), "{e}");
    let e = hessian(&[&p, &p], |t| busy_loss(t, &p, &v)).unwrap_err();
    assert!(e.to_string().contains("given twice"), "{e}");
}

/// The f64 gradient of `f` at the parameters' values `x`, over all their components.
fn grad_f64(
    params: &[&dyn AnyArray],
    x: &[f64],
    f: &mut dyn FnMut(&mut Tape) -> Result<Array<f64>, Error>,
) -> Vec<f64> {
    set(params, x);
    for p in params {
        p.reset_grad();
    }
    let mut tape = Tape::new();
    let l = f(&mut tape).unwrap();
    tape.backward(&l).unwrap();
    params
        .iter()
        .flat_map(|p| {
            let g = p.grad_any().unwrap();
            (0..g.len() * g.element_dim())
                .map(|k| g.scalar(k))
                .collect::<Vec<_>>()
        })
        .collect()
}

fn get(params: &[&dyn AnyArray]) -> Vec<f64> {
    params
        .iter()
        .flat_map(|p| (0..p.len() * p.element_dim()).map(|k| p.scalar(k)))
        .collect()
}

fn set(params: &[&dyn AnyArray], x: &[f64]) {
    let mut k = 0;
    for p in params {
        for j in 0..p.len() * p.element_dim() {
            p.set_scalar(j, x[k]);
            k += 1;
        }
    }
}

/// The derivative of the f64 gradient along `v` by fourth-order central differences:
/// `(8 (g(x + h v) - g(x - h v)) - (g(x + 2h v) - g(x - 2h v))) / 12h`.
fn hv_by_differences(
    params: &[&dyn AnyArray],
    v: &[f64],
    h: f64,
    f: &mut dyn FnMut(&mut Tape) -> Result<Array<f64>, Error>,
) -> Vec<f64> {
    let x = get(params);
    let at = |s: f64| {
        x.iter()
            .zip(v)
            .map(|(a, b)| a + s * h * b)
            .collect::<Vec<_>>()
    };
    let (p1, m1) = (
        grad_f64(params, &at(1.0), f),
        grad_f64(params, &at(-1.0), f),
    );
    let (p2, m2) = (
        grad_f64(params, &at(2.0), f),
        grad_f64(params, &at(-2.0), f),
    );
    set(params, &x);
    (0..x.len())
        .map(|k| (8.0 * (p1[k] - m1[k]) - (p2[k] - m2[k])) / (12.0 * h))
        .collect()
}

fn assert_close(what: &str, got: &[f64], want: &[f64], rel: f64) {
    let scale = want.iter().fold(1e-8f64, |m, x| m.max(x.abs()));
    for (k, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= rel * scale,
            "{what}[{k}]: {g:e}, central differences of gradients {w:e} (scale {scale:e})"
        );
    }
    assert!(
        got.iter().any(|x| *x != 0.0),
        "{what}: identically zero, the check cannot fail"
    );
}

/// `H u` (random `u`, from `seed`, zero at the components `zero`) of the `Dual` loss at `dp`
/// against fourth-order central differences (step `h`) of the f64 loss's gradient at `fp` to
/// `rel` of the largest component, and symmetric (`w^T H u = u^T H w` to 1e-10). Returns the
/// product.
fn agrees(
    what: &str,
    (dp, fp, zero): (&[&dyn AnyArray], &[&dyn AnyArray], &[usize]),
    (h, rel, seed): (f64, f64, u64),
    loss_d: &mut dyn FnMut(&mut Tape) -> Result<Array<Dual>, Error>,
    loss_f: &mut dyn FnMut(&mut Tape) -> Result<Array<f64>, Error>,
) -> Hvp {
    let n: usize = fp.iter().map(|p| p.len() * p.element_dim()).sum();
    let mut rng = common::Rng(seed);
    let mut random = || -> Vec<f64> {
        (0..n)
            .map(|k| match zero.contains(&k) {
                true => 0.0,
                false => rng.uniform(-1.0, 1.0),
            })
            .collect()
    };
    let (u, w) = (random(), random());
    let hu = hvp(dp, &u, &mut *loss_d).unwrap();
    let hw = hvp(dp, &w, &mut *loss_d).unwrap();
    let fd = hv_by_differences(fp, &u, h, loss_f);
    assert_close(&format!("{what}: H u"), &hu.hv, &fd, rel);
    let (a, b) = (dot(&w, &hu.hv), dot(&u, &hw.hv));
    assert!(
        (a - b).abs() <= 1e-10 * a.abs().max(b.abs()),
        "{what}: w^T H u = {a:e}, u^T H w = {b:e}"
    );
    hu
}

fn dual_of(x: &[f64]) -> Vec<Dual> {
    x.iter().map(|&v| Dual::constant(v)).collect()
}

fn vec3_dual(v: Vec3<f64>) -> Vec3<Dual> {
    v.map(Dual::constant)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

const P0: [f64; 3] = [0.4, -0.7, 1.1];

fn v0() -> Vec<Vec3<f64>> {
    vec![
        Vec3::new(0.3, -0.2, 0.5),
        Vec3::new(-0.4, 0.6, 0.1),
        Vec3::new(0.2, 0.9, -0.3),
    ]
}

/// `H v` of a kernel with loops, stores, atomics, branches and matrix, vector and
/// transcendental builtins against central differences of its f64 gradient, and symmetric
/// (`u^T H v = v^T H u`).
#[test]
fn hvp_of_a_busy_kernel_matches_differences_and_is_symmetric() {
    let p = Array::from_vec(dual_of(&P0)).requires_grad();
    let vv = Array::from_vec(v0().into_iter().map(vec3_dual).collect()).requires_grad();
    let params: [&dyn AnyArray; 2] = [&p, &vv];
    let mut rng = common::Rng(0x2e55);
    let n = 3 + 9;
    let u: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let w: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let hu = hvp(&params, &u, |t| busy_loss(t, &p, &vv)).unwrap();
    let hw = hvp(&params, &w, |t| busy_loss(t, &p, &vv)).unwrap();
    // The derivative parts are cleared after each product.
    assert!(p.to_vec().iter().all(|x| x.eps == 0.0));

    let pf = Array::from_vec(P0.to_vec()).requires_grad();
    let vf = Array::from_vec(v0()).requires_grad();
    let fparams: [&dyn AnyArray; 2] = [&pf, &vf];
    let fd = hv_by_differences(&fparams, &u, 1e-5, &mut |t| busy_loss(t, &pf, &vf));
    assert_close("H u", &hu.hv, &fd, 1e-6);
    // The values are the f64 gradient's, and the loss's derivative part is its slope.
    let g = grad_f64(&fparams, &get(&fparams), &mut |t| busy_loss(t, &pf, &vf));
    assert_close("gradient", &hu.grad, &g, 1e-14);
    assert!((hu.slope - dot(&g, &u)).abs() <= 1e-12 * hu.slope.abs().max(1.0));

    let (a, b) = (dot(&w, &hu.hv), dot(&u, &hw.hv));
    assert!(
        (a - b).abs() <= 1e-10 * a.abs().max(b.abs()),
        "w^T H u = {a:e}, u^T H w = {b:e}"
    );

    // The dense Hessian is symmetric and its columns are the products.
    let h = hessian(&params, |t| busy_loss(t, &p, &vv)).unwrap();
    for (i, row) in h.iter().enumerate() {
        for (j, &x) in row.iter().enumerate() {
            let y = h[j][i];
            assert!(
                (x - y).abs() <= 1e-10 * x.abs().max(y.abs()).max(1.0),
                "H[{i}][{j}]"
            );
        }
    }
    let hu_dense: Vec<f64> = (0..n)
        .map(|i| (0..n).map(|j| h[j][i] * u[j]).sum())
        .collect();
    assert_close("H u from the columns", &hu.hv, &hu_dense, 1e-12);
}

/// Four particles with springs, a membrane triangle, a tetrahedron and a bending hinge,
/// built in any scalar.
fn scene<R: Real>() -> Model<R> {
    scene_with(false)
}

/// [`scene`], with particles 0 and 2 pinned if `pin` (so that it has one equilibrium).
fn scene_with<R: Real>(pin: bool) -> Model<R> {
    let l = |x: f64| R::lit(x);
    let v3 = |x: f64, y: f64, z: f64| Vec3::new(l(x), l(y), l(z));
    let mut b = ModelBuilder::<R>::new();
    let (m0, m2) = if pin { (0.0, 0.0) } else { (1.5, 0.5) };
    let p0 = b.add_particle(v3(0.0, 1.0, 0.0), v3(0.1, 0.0, 0.0), l(m0));
    let p1 = b.add_particle(v3(0.6, 1.1, 0.1), v3(0.0, 0.3, -0.2), l(1.0));
    let p2 = b.add_particle(v3(1.1, 0.8, -0.2), v3(-0.4, 0.0, 0.1), l(m2));
    let p3 = b.add_particle(v3(0.5, 0.5, 0.3), v3(0.2, -0.1, 0.3), l(2.0));
    for (k, (i, j)) in [(p0, p1), (p1, p2), (p2, p3), (p1, p3), (p0, p3)]
        .into_iter()
        .enumerate()
    {
        let d = (b.particle_position(i) - b.particle_position(j)).norm();
        b.add_spring_with_rest(
            i,
            j,
            d * l(0.85 + 0.07 * k as f64),
            l(40.0 * (1.0 + 0.3 * k as f64)),
            l(0.2),
        );
    }
    b.add_triangle_fem(p0, p1, p2, l(20.0), l(30.0), l(0.1));
    b.add_tet(p0, p1, p2, p3, l(15.0), l(25.0), l(0.1));
    b.add_bending([p0, p2, p1, p3], l(0.3), l(2.0), l(0.05));
    b.finalize()
}

/// The rollout's loss: squared final positions and velocities, weighted.
#[diff_kernel]
fn state_loss<R: Real>(x: &Array<Vec3<R>>, v: &Array<Vec3<R>>, loss: &Array<R>) {
    let i = tid();
    loss.atomic_add(0, length_sq(x[i]) + 0.3 * length_sq(v[i]) + x[i].x * v[i].y);
}

fn rollout_loss<R: Real + Element>(
    model: &Model<R>,
    integrator: &dyn Integrator<R>,
    v0: &Array<Vec3<R>>,
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let mut s: State<R> = model.state();
    s.v = v0.clone();
    let end = integrator.rollout(model, tape, &s, None, R::lit(0.01), 12)?;
    let loss = Array::<R>::zeros(1);
    tape.launch(state_loss, end.x.len(), (&end.x, &end.v, &loss));
    Ok(loss)
}

/// `H v` of whole rollouts of library forces (springs, membrane, tetrahedron, bending) by
/// semi-implicit Euler and RK4, with respect to every force's stiffness and the initial
/// velocities, against central differences of f64 gradients; and symmetric.
#[test]
fn hvp_of_rollouts_matches_differences() {
    type Pair = (
        &'static str,
        Box<dyn Integrator<Dual>>,
        Box<dyn Integrator<f64>>,
    );
    let integrators: [Pair; 2] = [
        (
            "semi-implicit Euler",
            Box::new(SemiImplicitEuler),
            Box::new(SemiImplicitEuler),
        ),
        ("RK4", Box::new(Rk4), Box::new(Rk4)),
    ];
    let names = [
        ("springs", "ke"),
        ("triangle_fem", "mu"),
        ("tets", "lambda"),
        ("bending", "ke"),
    ];
    for (name, id, if64) in &integrators {
        let md = scene::<Dual>();
        let mf = scene::<f64>();
        let dparams: Vec<Array<Dual>> = names
            .iter()
            .map(|(f, p)| md.param::<Dual>(f, p).unwrap().requires_grad())
            .collect();
        let fparams: Vec<Array<f64>> = names
            .iter()
            .map(|(f, p)| mf.param::<f64>(f, p).unwrap().requires_grad())
            .collect();
        let vd = md.state().v.requires_grad();
        let vf = mf.state().v.requires_grad();
        let mut dp: Vec<&dyn AnyArray> = dparams.iter().map(|a| a as &dyn AnyArray).collect();
        dp.push(&vd);
        let mut fp: Vec<&dyn AnyArray> = fparams.iter().map(|a| a as &dyn AnyArray).collect();
        fp.push(&vf);
        let hu = agrees(
            name,
            (&dp, &fp, &[]),
            (1e-4, 1e-6, 0x0dd5),
            &mut |t| rollout_loss(&md, &**id, &vd, t),
            &mut |t| rollout_loss(&mf, &**if64, &vf, t),
        );
        let n = hu.hv.len();
        println!(
            "{name}: {n} parameters, |H u| = {:.3e}",
            hu.hv.iter().map(|x| x * x).sum::<f64>().sqrt()
        );
    }
}

/// Three particles pressed into the ground, joined by springs; particle 0 at rest (`at_rest`)
/// or sliding.
fn on_ground<R: Real>(at_rest: bool) -> Model<R> {
    let l = |x: f64| R::lit(x);
    let v3 = |x: f64, y: f64, z: f64| Vec3::new(l(x), l(y), l(z));
    let mut b = ModelBuilder::<R>::new();
    // At about the depth where the ground carries the weight (so that contact holds
    // throughout). Sliding: fast enough that friction does not stop them, and approaching
    // the ground (the contact damping has a kink at a normal speed of exactly 0).
    let (v0, vn) = if at_rest { (0.0, 0.0) } else { (0.5, -0.03) };
    let p0 = b.add_particle(v3(0.0, -0.005, 0.0), v3(v0, vn, -v0), l(1.0));
    let p1 = b.add_particle(v3(0.3, -0.004, 0.0), v3(0.6, vn, 0.2), l(0.8));
    let p2 = b.add_particle(v3(0.1, -0.006, 0.3), v3(-0.3, vn, 0.6), l(1.2));
    for (i, j) in [(p0, p1), (p1, p2), (p2, p0)] {
        b.add_spring(i, j, l(50.0), l(0.1));
    }
    b.set_ground(adflex_kernels::prelude::Ground {
        ke: l(2e3),
        kd: l(10.0),
        mu: l(0.1),
        ..adflex_kernels::prelude::Ground::default()
    });
    b.finalize()
}

/// Through ground contact and friction: from rest (a tangential speed of exactly 0, where
/// `length`'s derivative is singular and friction has a kink) `H v` is finite and symmetric;
/// sliding (smooth there) it matches central differences of f64 gradients.
#[test]
fn hvp_through_ground_contact_is_finite_from_rest_and_matches_differences_sliding() {
    for at_rest in [true, false] {
        let md = on_ground::<Dual>(at_rest);
        let mf = on_ground::<f64>(at_rest);
        let ke_d = md.param::<Dual>("springs", "ke").unwrap().requires_grad();
        let ke_f = mf.param::<f64>("springs", "ke").unwrap().requires_grad();
        let (vd, vf) = (md.state().v.requires_grad(), mf.state().v.requires_grad());
        let dp: [&dyn AnyArray; 2] = [&ke_d, &vd];
        let fp: [&dyn AnyArray; 2] = [&ke_f, &vf];
        let mut rng = common::Rng(0x96d);
        let u: Vec<f64> = (0..12).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let w: Vec<f64> = (0..12).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let hu = hvp(&dp, &u, |t| rollout_loss(&md, &SemiImplicitEuler, &vd, t)).unwrap();
        let hw = hvp(&dp, &w, |t| rollout_loss(&md, &SemiImplicitEuler, &vd, t)).unwrap();
        assert!(hu.hv.iter().all(|x| x.is_finite()), "{:?}", hu.hv);
        let (a, b) = (dot(&w, &hu.hv), dot(&u, &hw.hv));
        assert!(
            (a - b).abs() <= 1e-10 * a.abs().max(b.abs()),
            "at rest {at_rest}: w^T H u = {a:e}, u^T H w = {b:e}"
        );
        if !at_rest {
            let fd = hv_by_differences(&fp, &u, 1e-5, &mut |t| {
                rollout_loss(&mf, &SemiImplicitEuler, &vf, t)
            });
            assert_close("H u through contact", &hu.hv, &fd, 1e-6);
        }
    }
}

/// A checkpointed rollout in `Dual` gives the taped rollout's product (the recomputed
/// segments carry their derivative parts too).
#[test]
fn hvp_through_a_checkpointed_rollout_is_the_taped_one() {
    let md = scene::<Dual>();
    let ke = md.param::<Dual>("springs", "ke").unwrap().requires_grad();
    let vd = md.state().v.requires_grad();
    let params: [&dyn AnyArray; 2] = [&ke, &vd];
    let n = ke.len() + 3 * vd.len();
    let mut rng = common::Rng(0xc4ec);
    let u: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let taped = hvp(&params, &u, |t| {
        rollout_loss(&md, &SemiImplicitEuler, &vd, t)
    })
    .unwrap();
    let ck = hvp_with(&params, &u, || {
        let mut s: State<Dual> = md.state();
        s.v = vd.clone();
        let dt = Dual::constant(0.01);
        let out = checkpointed(
            &s,
            12,
            5,
            |tape, s| SemiImplicitEuler.step(&md, tape, s, None, dt),
            |tape, s| {
                let loss = Array::<Dual>::zeros(1);
                tape.launch(state_loss, s.x.len(), (&s.x, &s.v, &loss));
                Ok(loss)
            },
        )?;
        Ok(out.loss.get(0))
    })
    .unwrap();
    assert_close("checkpointed H u", &ck.hv, &taped.hv, 1e-12);
    assert!((ck.loss - taped.loss).abs() <= 1e-14 * taped.loss.abs());
    assert!((ck.slope - taped.slope).abs() <= 1e-12 * taped.slope.abs());
}

/// Implicit Euler held to tight tolerances, so that central differences of its gradient
/// resolve the product (its solves' error over `h`).
fn tight_implicit() -> ImplicitEuler {
    let tight = adflex_kernels::solver::krylov::SolveSettings {
        rel_tol: 1e-14,
        abs_tol: 1e-20,
        max_iter: 1000,
    };
    ImplicitEuler {
        tolerance: Some(1e-14),
        linear: tight,
        on_failure: adflex_kernels::integrators::SolverPolicy::Continue,
        ..ImplicitEuler::default()
    }
}

/// The parameters of the implicit paths' checks: every force's stiffness, the spring rest
/// lengths and the initial velocities.
const STIFFNESSES: [(&str, &str); 5] = [
    ("springs", "ke"),
    ("springs", "rest"),
    ("triangle_fem", "mu"),
    ("tets", "lambda"),
    ("bending", "ke"),
];

/// `H u` against central differences of the f64 gradient, and `w^T H u = u^T H w`, for the
/// loss of the scene's parameters (`STIFFNESSES`) and a state array (the initial positions
/// if `positions`, else the velocities), passed to the loss closures.
fn check_hvp<F, D>(
    what: &str,
    (pin, positions, masses): (bool, bool, bool),
    h: f64,
    rel: f64,
    mut loss_f: F,
    mut loss_d: D,
) where
    F: FnMut(&Model<f64>, &Array<Vec3<f64>>, &mut Tape) -> Result<Array<f64>, Error>,
    D: FnMut(&Model<Dual>, &Array<Vec3<Dual>>, &mut Tape) -> Result<Array<Dual>, Error>,
{
    let md = scene_with::<Dual>(pin);
    let mf = scene_with::<f64>(pin);
    let dparams: Vec<Array<Dual>> = STIFFNESSES
        .iter()
        .map(|(f, p)| md.param::<Dual>(f, p).unwrap().requires_grad())
        .collect();
    let fparams: Vec<Array<f64>> = STIFFNESSES
        .iter()
        .map(|(f, p)| mf.param::<f64>(f, p).unwrap().requires_grad())
        .collect();
    let (vd, vf) = match positions {
        true => (md.state().x, mf.state().x),
        false => (md.state().v, mf.state().v),
    };
    let (vd, vf) = (vd.requires_grad(), vf.requires_grad());
    let mut dp: Vec<&dyn AnyArray> = dparams.iter().map(|a| a as &dyn AnyArray).collect();
    dp.push(&vd);
    let mut fp: Vec<&dyn AnyArray> = fparams.iter().map(|a| a as &dyn AnyArray).collect();
    fp.push(&vf);
    // The inverse masses last, with a zero direction on the pinned particles (0 and 2).
    let (wd, wf) = (
        md.particle_inv_mass.clone().requires_grad(),
        mf.particle_inv_mass.clone().requires_grad(),
    );
    let mut zero = Vec::new();
    if masses {
        dp.push(&wd);
        fp.push(&wf);
        let first: usize = fp.iter().map(|p| p.len() * p.element_dim()).sum::<usize>() - wf.len();
        zero = if pin { vec![first, first + 2] } else { vec![] };
    }
    let hu = agrees(
        what,
        (&dp, &fp, &zero),
        (h, rel, 0x1f7),
        &mut |t| loss_d(&md, &vd, t),
        &mut |t| loss_f(&mf, &vf, t),
    );
    // The gradient is the f64 one.
    let g = grad_f64(&fp, &get(&fp), &mut |t| loss_f(&mf, &vf, t));
    assert_close(&format!("{what}: gradient"), &hu.grad, &g, 1e-9);
}

/// Through implicit Euler's implicit-function-theorem adjoint, with its second-order term:
/// 12 steps of the scene (free, and with pinned particles; all forces implicit, and bending
/// explicit), with respect to the stiffnesses, the initial velocities and the inverse masses,
/// `H u` against central differences of f64 gradients and symmetric.
#[test]
fn hvp_through_implicit_euler_matches_differences() {
    for (pin, explicit) in [(false, false), (true, false), (true, true)] {
        let ie = match explicit {
            true => tight_implicit().with_explicit(["bending"]),
            false => tight_implicit(),
        };
        check_hvp(
            &format!("implicit Euler (pinned {pin}, bending explicit {explicit})"),
            (pin, false, true),
            1e-4,
            1e-6,
            |m, v, t| rollout_loss(m, &ie, v, t),
            |m, v, t| rollout_loss(m, &ie, v, t),
        );
    }
}

/// A user's force wrapping a library one, without `Force::to_f64`: implicit Euler then solves
/// in `Dual`.
#[derive(Clone, Debug)]
struct NoF64(Box<dyn Force<Dual>>);

impl Force<Dual> for NoF64 {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn eval(&self, cx: &ForceContext<'_, Dual>, tape: &mut Tape, f: &Array<Vec3<Dual>>) {
        self.0.eval(cx, tape, f)
    }
    fn energy(&self, cx: &ForceContext<'_, Dual>, tape: &mut Tape, e: &Array<Dual>) -> bool {
        self.0.energy(cx, tape, e)
    }
    fn params_mut(&mut self, visit: &mut dyn FnMut(&'static str, &mut dyn Param)) {
        self.0.params_mut(visit)
    }
}

/// Implicit Euler runs a Hessian-vector product's solves on the model's real parts in `f64`
/// when every force converts (`Force::to_f64`), and in `Dual` otherwise: both give the same
/// `H u` (and the same gradient, the f64 one).
#[test]
fn hvp_through_implicit_euler_is_the_same_with_a_force_that_stays_dual() {
    let ie = tight_implicit();
    let direction: Vec<f64> = (0..5 + 12)
        .map(|k| ((k * 7 % 11) as f64 - 5.0) / 5.0)
        .collect();
    let run = |opaque: bool| {
        let mut md = scene_with::<Dual>(false);
        if opaque {
            md.forces = md
                .forces
                .into_iter()
                .map(|f| Box::new(NoF64(f)) as Box<dyn Force<Dual>>)
                .collect();
        }
        let ke = md.param::<Dual>("springs", "ke").unwrap().requires_grad();
        let v = md.state().v.requires_grad();
        hvp(&[&ke, &v], &direction, |t| rollout_loss(&md, &ie, &v, t)).unwrap()
    };
    let (twin, dual) = (run(false), run(true));
    assert_close(
        "H u, solves in f64 against in Dual",
        &twin.hv,
        &dual.hv,
        1e-9,
    );
    assert_close(
        "gradient, solves in f64 against in Dual",
        &twin.grad,
        &dual.grad,
        1e-11,
    );
}

/// The equilibrium from the guess `x0` (whose pinned particles are the pins), then a short
/// rollout from it with the model's initial velocities.
fn equilibrium_loss<R: Real + Element>(
    model: &Model<R>,
    x0: &Array<Vec3<R>>,
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let eq = Equilibrium {
        tolerance: Some(1e-14),
        on_failure: adflex_kernels::integrators::SolverPolicy::Continue,
        linear: adflex_kernels::solver::krylov::SolveSettings {
            rel_tol: 1e-14,
            abs_tol: 1e-20,
            max_iter: 1000,
        },
        ..Equilibrium::default()
    };
    let guess = State {
        x: x0.clone(),
        ..model.state()
    };
    let mut s = eq.solve(model, tape, &guess)?;
    s.v = model.state().v;
    let end = SemiImplicitEuler.rollout(model, tape, &s, None, R::lit(0.01), 4)?;
    let loss = Array::<R>::zeros(1);
    tape.launch(state_loss, end.x.len(), (&end.x, &end.v, &loss));
    Ok(loss)
}

/// Through `Equilibrium`'s implicit-function-theorem adjoint, with its second-order term:
/// the scene hanging from its two pinned particles (whose positions are in the direction),
/// then released.
#[test]
fn hvp_through_equilibrium_matches_differences() {
    check_hvp(
        "equilibrium",
        (true, true, true),
        1e-4,
        1e-6,
        equilibrium_loss,
        equilibrium_loss,
    );
}

/// The density's squared distance to a target.
#[diff_kernel]
fn density_error<R: Real>(d: &Array<R>, target: &Array<R>, loss: &Array<R>) {
    let i = tid();
    let e = d[i] - target[i];
    loss.atomic_add(0, e * e);
}

/// Three steps of smoke on an 8 x 8 grid, projected by CG with its implicit adjoint.
fn smoke_loss<R: Real + Element>(
    u0: &Array<R>,
    v0: &Array<R>,
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let grid = FluidGrid::new(8, 1.0 / 8.0)?;
    let cells = grid.cells();
    let field = |seed: u64, lo: f64, hi: f64| {
        let mut rng = common::Rng(seed);
        Array::from_vec((0..cells).map(|_| R::lit(rng.uniform(lo, hi))).collect())
    };
    let (d0, target) = (field(0xd0, 0.0, 1.0), field(0x7a, 0.0, 1.0));
    let cg = Pressure::Cg(adflex_kernels::solver::krylov::SolveSettings {
        rel_tol: 1e-14,
        abs_tol: 1e-30,
        max_iter: 10_000,
    });
    let (mut u, mut v, mut d) = (u0.clone(), v0.clone(), d0);
    for _ in 0..3 {
        (u, v, d) = grid.step(tape, &u, &v, &d, 0.03, &cg)?;
    }
    let loss = Array::<R>::zeros(1);
    tape.launch(density_error, cells, (&d, &target, &loss));
    Ok(loss)
}

/// Through the fluid's CG pressure solve (a linear solve with a constant operator: each part
/// its own solve), forward and adjoint.
#[test]
fn hvp_through_the_fluid_cg_pressure_matches_differences() {
    let mut rng = common::Rng(0x5e0);
    let u: Vec<f64> = (0..64).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let v: Vec<f64> = (0..64).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let (ud, vd) = (
        Array::from_vec(dual_of(&u)).requires_grad(),
        Array::from_vec(dual_of(&v)).requires_grad(),
    );
    let (uf, vf) = (
        Array::from_vec(u).requires_grad(),
        Array::from_vec(v).requires_grad(),
    );
    agrees(
        "smoke",
        (&[&ud, &vd], &[&uf, &vf], &[]),
        (1e-5, 1e-6, 0x5e1),
        &mut |t| smoke_loss(&ud, &vd, t),
        &mut |t| smoke_loss(&uf, &vf, t),
    );
}

/// `sum_i q_i sin(q_i) + 0.3 qd_i^2`.
#[diff_kernel]
fn joint_loss<R: Real>(q: &Array<R>, qd: &Array<R>, loss: &Array<R>) {
    let i = tid();
    loss.atomic_add(0, q[i] * sin(q[i]) + 0.3 * qd[i] * qd[i]);
}

/// 20 steps of a robot loaded from the repository, from a bent pose.
fn robot_loss<R: Real + Element>(
    model: &Articulations<R>,
    q: &Array<R>,
    qd: &Array<R>,
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let mut s = ArticulationState {
        q: q.clone(),
        qd: qd.clone(),
    };
    for _ in 0..20 {
        s = model.step(tape, &s, None, R::lit(2e-3))?;
    }
    let loss = Array::<R>::zeros(1);
    tape.launch(joint_loss, s.qd.len(), (&s.q, &s.qd, &loss));
    Ok(loss)
}

/// Through the articulations' mass-matrix solve (a dense Cholesky solve whose matrix moves
/// along the direction): the 7-DoF arm and the cartpole, with respect to the start state and
/// the links' masses.
#[test]
fn hvp_through_articulated_robots_matches_differences() {
    for file in ["arm7.urdf", "cartpole.urdf"] {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/robots/").to_string() + file;
        let b = urdf::load(&path, &Default::default()).unwrap();
        let md: Articulations<Dual> = b.finalize().unwrap();
        let mf: Articulations<f64> = b.finalize().unwrap();
        let n = mf.n_dof;
        let mut rng = common::Rng(0xa7);
        let q0: Vec<f64> = (0..n).map(|_| rng.uniform(-0.3, 0.3)).collect();
        let qd0: Vec<f64> = (0..n).map(|_| rng.uniform(-0.5, 0.5)).collect();
        let (qd_, qdd_) = (
            Array::from_vec(dual_of(&q0)).requires_grad(),
            Array::from_vec(dual_of(&qd0)).requires_grad(),
        );
        let (qf, qdf) = (
            Array::from_vec(q0).requires_grad(),
            Array::from_vec(qd0).requires_grad(),
        );
        let (massd, massf) = (
            md.mass.clone().requires_grad(),
            mf.mass.clone().requires_grad(),
        );
        let dp: [&dyn AnyArray; 3] = [&qd_, &qdd_, &massd];
        let fp: [&dyn AnyArray; 3] = [&qf, &qdf, &massf];
        agrees(
            file,
            (&dp, &fp, &[]),
            (1e-4, 1e-6, 0xa8),
            &mut |t| robot_loss(&md, &qd_, &qdd_, t),
            &mut |t| robot_loss(&mf, &qf, &qdf, t),
        );
    }
}

/// `sum_p |x_p|^2 + 0.3 |v_p|^2` over 2D material points.
#[diff_kernel]
fn points_loss<R: Real>(x: &Array<Vec2<R>>, v: &Array<Vec2<R>>, loss: &Array<R>) {
    let i = tid();
    loss.atomic_add(0, dot(x[i], x[i]) + 0.3 * dot(v[i], v[i]));
}

/// Eight MLS-MPM steps of a falling, spinning block (`material`), from the state `v0`.
fn mpm_loss<R: Real + Element>(
    mpm: &Mpm<R>,
    v0: &Array<Vec2<R>>,
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let mut s = mpm.state();
    s.v = v0.clone();
    for _ in 0..8 {
        s = mpm.step(tape, &s, None, 1e-3)?;
    }
    let loss = Array::<R>::zeros(1);
    tape.launch(points_loss, s.x.len(), (&s.x, &s.v, &loss));
    Ok(loss)
}

/// Through MLS-MPM (the transfers' B-splines, APIC, the constitutive models): `H u` with
/// respect to the initial velocities and the Lamé parameters against central differences.
#[test]
fn hvp_through_mpm_matches_differences() {
    for material in [
        Material::Corotated {
            mu: 30.0,
            lambda: 20.0,
        },
        Material::NeoHookean {
            mu: 30.0,
            lambda: 20.0,
        },
    ] {
        let mut b = MpmBuilder::new(16, 1.0 / 16.0);
        let r = b.add_rect(
            Vec2::new(0.4, 0.4),
            Vec2::new(0.125, 0.125),
            1.0,
            1.0,
            material,
        );
        for (k, p) in r.enumerate() {
            let a = 0.37 * k as f64;
            b.set_velocity(p, Vec2::new(0.3 * a.sin(), 0.2 * a.cos()));
        }
        let md = b.finalize::<Dual>().unwrap();
        let mf = b.finalize::<f64>().unwrap();
        let (vd, vf) = (md.state().v.requires_grad(), mf.state().v.requires_grad());
        let (mud, muf) = (md.mu.clone().requires_grad(), mf.mu.clone().requires_grad());
        let (ld, lf) = (
            md.lambda.clone().requires_grad(),
            mf.lambda.clone().requires_grad(),
        );
        let dp: [&dyn AnyArray; 3] = [&vd, &mud, &ld];
        let fp: [&dyn AnyArray; 3] = [&vf, &muf, &lf];
        agrees(
            &format!("{material:?}"),
            (&dp, &fp, &[]),
            (1e-5, 1e-6, 0x3b3),
            &mut |t| mpm_loss(&md, &vd, t),
            &mut |t| mpm_loss(&mf, &vf, t),
        );
    }
}

/// A box tumbling onto the ground on four contact points, in any scalar.
fn tumbling<R: Real>() -> Model<R> {
    let l = |x: f64| R::lit(x);
    let mut b = ModelBuilder::<R>::new();
    // A unit quaternion: cos 0.2 + sin 0.2 (1, 0.2, 0.5)/|.|.
    let (c, s) = (0.2f64.cos(), 0.2f64.sin() / 1.3f64.sqrt());
    let q = Quat::new(l(c), l(s), l(0.2 * s), l(0.5 * s));
    let inertia = Mat33::from_diagonal(&Vec3::new(l(0.2), l(0.3), l(0.4)));
    let v3 = |x: f64, y: f64, z: f64| Vec3::new(l(x), l(y), l(z));
    let body = b.add_body(
        v3(0.0, 0.12, 0.0),
        q,
        v3(0.4, -0.3, 0.1),
        v3(0.5, 2.0, -1.0),
        l(1.5),
        inertia,
    );
    for (x, z) in [(0.1, 0.1), (-0.1, 0.1), (0.1, -0.1), (-0.1, -0.1)] {
        b.add_body_contact_point(body, v3(x, -0.1, z));
    }
    b.set_ground(adflex_kernels::prelude::Ground {
        ke: l(2e3),
        kd: l(10.0),
        mu: l(0.3),
        ..adflex_kernels::prelude::Ground::default()
    });
    b.finalize()
}

/// `|x|^2 + 0.3 |v|^2 + 0.1 |w|^2 + q.x` of the bodies.
#[diff_kernel]
fn body_loss<R: Real>(
    x: &Array<Vec3<R>>,
    q: &Array<Quat<R>>,
    v: &Array<Vec3<R>>,
    w: &Array<Vec3<R>>,
    loss: &Array<R>,
) {
    let i = tid();
    loss.atomic_add(
        0,
        dot(x[i], x[i]) + 0.3 * dot(v[i], v[i]) + 0.1 * dot(w[i], w[i]) + q[i].x,
    );
}

fn body_rollout<R: Real + Element>(
    model: &Model<R>,
    v0: &Array<Vec3<R>>,
    w0: &Array<Vec3<R>>,
    tape: &mut Tape,
) -> Result<Array<R>, Error> {
    let mut s = model.state();
    let b = s.bodies.as_mut().unwrap();
    b.v = v0.clone();
    b.w = w0.clone();
    let end = SemiImplicitEuler.rollout(model, tape, &s, None, R::lit(2e-3), 40)?;
    let b = end.bodies.unwrap();
    let loss = Array::<R>::zeros(1);
    tape.launch(body_loss, b.x.len(), (&b.x, &b.q, &b.v, &b.w, &loss));
    Ok(loss)
}

/// Through rigid bodies (the quaternion update, the gyroscopic term) and their ground
/// contact with friction: `H u` with respect to the initial linear and angular velocities.
#[test]
fn hvp_through_a_tumbling_rigid_body_matches_differences() {
    let (md, mf) = (tumbling::<Dual>(), tumbling::<f64>());
    let (bd, bf) = (
        &md.bodies.as_ref().unwrap().initial,
        &mf.bodies.as_ref().unwrap().initial,
    );
    let (vd, wd) = (
        bd.v.deep_clone().requires_grad(),
        bd.w.deep_clone().requires_grad(),
    );
    let (vf, wf) = (
        bf.v.deep_clone().requires_grad(),
        bf.w.deep_clone().requires_grad(),
    );
    let dp: [&dyn AnyArray; 2] = [&vd, &wd];
    let fp: [&dyn AnyArray; 2] = [&vf, &wf];
    agrees(
        "tumbling body",
        (&dp, &fp, &[]),
        (1e-5, 1e-6, 0xb0d),
        &mut |t| body_rollout(&md, &vd, &wd, t),
        &mut |t| body_rollout(&mf, &vf, &wf, t),
    );
}

/// What would be silently wrong is refused: a solver step without a second-order rule
/// (linearized implicit Euler), a custom step not declared dual-safe, a wrong direction, a parameter that is not `Dual`.
#[test]
fn second_order_refuses_what_it_cannot_differentiate() {
    let md = scene::<Dual>();
    let ke = md.param::<Dual>("springs", "ke").unwrap().requires_grad();
    let u = vec![1.0; ke.len()];
    let err = hvp(&[&ke], &u, |t| {
        rollout_loss(&md, &ImplicitEuler::linearized(), &md.state().v, t)
    })
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("linearized implicit Euler") && err.contains("second-order"),
        "{err}"
    );

    // A custom step on Dual arrays, not declared dual-safe, then declared.
    let x = Array::from_vec(vec![Dual::constant(3.0)]).requires_grad();
    let run = |safe: bool| {
        hvp(&[&x], &[1.0], |tape| {
            let y = Array::<Dual>::zeros(1);
            let (xb, yb) = (x.clone(), y.clone());
            let (xf, yf) = (x.clone(), y.clone());
            let step = tape.record_fn(
                "cube",
                &[&x],
                &[&y],
                move || yf.set(0, xf.get(0) * xf.get(0) * xf.get(0)),
                move || {
                    let g = yb.grad_buffer().map_or(Dual::constant(0.0), |g| g.get(0));
                    if let Some(gx) = xb.grad_buffer() {
                        let x = xb.get(0);
                        gx.set(0, gx.get(0) + Dual::constant(3.0) * x * x * g);
                    }
                    Ok(())
                },
            );
            if safe {
                step.dual_safe();
            }
            Ok(y)
        })
    };
    let err = run(false).unwrap_err().to_string();
    assert!(err.contains("cube") && err.contains("dual_safe"), "{err}");
    let ok = run(true).unwrap();
    assert_eq!(ok.hv, vec![18.0], "d2(x^3) = 6x = 18");

    let e = hvp(&[&x], &[1.0, 2.0], |t| busy_loss(t, &x, &Array::zeros(3)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("2 entries") && e.contains("1 scalar"), "{e}");
    let e = hvp(&[&x], &[f64::NAN], |t| busy_loss(t, &x, &Array::zeros(3)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("v[0]"), "{e}");
    let f = Array::from_vec(vec![1.0f64]).named("plain").requires_grad();
    let e = hvp(&[&f], &[1.0], |t| busy_loss(t, &x, &Array::zeros(3)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("plain") && e.contains("Dual"), "{e}");
    let nog = Array::from_vec(vec![Dual::constant(1.0)]).named("frozen");
    let e = hvp(&[&nog], &[1.0], |t| busy_loss(t, &x, &Array::zeros(3)))
        .unwrap_err()
        .to_string();
    assert!(e.contains("frozen") && e.contains("requires_grad"), "{e}");
}

fn softplus_adj<R: Real>(x: R, g: R) -> (R,) {
    (g / (R::lit(1.0) + (-x).exp()),)
}
fn softplus_tan<R: Real>(x: R, dx: R) -> R {
    dx / (R::lit(1.0) + (-x).exp())
}
fn softplus_adj_f64<R: Real>(x: R, g: R) -> (R,) {
    // Through f64: drops a Dual's derivative part.
    (R::lit(g.to_f64() / (1.0 + (-x.to_f64()).exp())),)
}

#[diff_func(adjoint = softplus_adj, tangent = softplus_tan, dual_safe)]
fn softplus<R: Real>(x: R) -> R {
    ln(1.0 + exp(x))
}

#[diff_func(adjoint = softplus_adj_f64, tangent = softplus_tan)]
fn softplus_undeclared<R: Real>(x: R) -> R {
    ln(1.0 + exp(x))
}

#[diff_kernel]
fn soft<R: Real>(x: &Array<R>, loss: &Array<R>) {
    let i = tid();
    loss.atomic_add(0, softplus(x[i] * x[i]));
}

#[diff_kernel]
fn soft_undeclared<R: Real>(x: &Array<R>, loss: &Array<R>) {
    let i = tid();
    loss.atomic_add(0, softplus_undeclared(x[i] * x[i]));
}

/// A custom adjoint declared `dual_safe` is differentiated as written (checked against the
/// closed form); one not declared stops the product with an error naming the kernel and the
/// function and saying how to fix it.
#[test]
fn custom_adjoints_must_be_declared_dual_safe() {
    let x = Array::from_vec(vec![Dual::constant(0.7)]).requires_grad();
    let out = hvp(&[&x], &[1.0], |tape| {
        let l = Array::<Dual>::zeros(1);
        tape.launch(soft, 1, (&x, &l));
        Ok(l)
    })
    .unwrap();
    // f = softplus(x^2): f'' = 2 s(x^2) + 4 x^2 s(x^2)(1 - s(x^2)), s the logistic function.
    let s = 1.0 / (1.0 + (-0.49f64).exp());
    let want = 2.0 * s + 4.0 * 0.49 * s * (1.0 - s);
    assert!((out.hv[0] - want).abs() < 1e-14, "{} vs {want}", out.hv[0]);

    let undeclared = |tape: &mut Tape| {
        let l = Array::<Dual>::zeros(1);
        tape.launch(soft_undeclared, 1, (&x, &l));
        Ok(l)
    };
    let err = hvp(&[&x], &[1.0], undeclared)
        .expect_err("an undeclared custom adjoint must not run in Dual")
        .to_string();
    assert!(
        err.contains("soft_undeclared")
            && err.contains("softplus_undeclared")
            && err.contains("dual_safe"),
        "{err}"
    );
    // Forward mode over a Dual tape too, and the runtime is fine afterwards.
    let mut tape = Tape::new();
    let l = undeclared(&mut tape).unwrap();
    let _ = x.clone().ensure_tangent();
    let err = tape.tangent().unwrap_err().to_string();
    assert!(err.contains("softplus_undeclared"), "{err}");
    assert!(l.get(0).re > 0.0);
    let again = hvp(&[&x], &[1.0], |tape| {
        let l = Array::<Dual>::zeros(1);
        tape.launch(soft, 1, (&x, &l));
        Ok(l)
    })
    .unwrap();
    assert_eq!(again.hv, out.hv);
}

/// Through implicit friction against fixed shapes (worldbody geoms): a capsule sliding on a
/// table (the capsule-box points' dampers) and one sliding across a rail (a capsule pair's),
/// whose dampers join the mass matrix, with respect to the start velocities and the pairs'
/// friction.
#[test]
fn hvp_through_implicit_friction_on_fixed_shapes_matches_differences() {
    use adflex_kernels::articulation::mjcf;
    let text = r#"<mujoco><worldbody><geom type="plane" size="5 5 0.1"/>
        <geom type="box" size="0.4 0.4 0.1" pos="0 0 0.1"/>
        <geom type="capsule" fromto="0 0.7 0.2 0 1.3 0.2" size="0.02"/>
        <body pos="0 0 0.228"><freejoint/>
          <geom type="capsule" fromto="-0.2 0 0 0.2 0 0" size="0.03" density="1000"/></body>
        <body pos="0 1 0.248"><freejoint/>
          <geom type="capsule" fromto="-0.2 0 0 0.2 0 0" size="0.03" density="1000"/></body>
        </worldbody></mujoco>"#;
    let b = mjcf::parse(text).unwrap().builder;
    let md: Articulations<Dual> = b.finalize().unwrap();
    let mf: Articulations<f64> = b.finalize().unwrap();
    assert!(mf.link_fixed.to_vec().contains(&1), "the damper path");
    assert!(!mf.capsule_pairs.is_empty() && !mf.box_pairs.is_empty());
    let mut rng = common::Rng(0xf1);
    let qd0: Vec<f64> = (0..mf.n_dof).map(|_| rng.uniform(-0.2, 0.2)).collect();
    let (q_d, q_f) = (
        Array::from_vec(dual_of(&mf.q0)),
        Array::from_vec(mf.q0.clone()),
    );
    let (qd_d, qd_f) = (
        Array::from_vec(dual_of(&qd0)).requires_grad(),
        Array::from_vec(qd0).requires_grad(),
    );
    let (box_d, box_f) = (
        md.box_pair_mu.clone().requires_grad(),
        mf.box_pair_mu.clone().requires_grad(),
    );
    let (cap_d, cap_f) = (
        md.capsule_pair_mu.clone().requires_grad(),
        mf.capsule_pair_mu.clone().requires_grad(),
    );
    let dp: [&dyn AnyArray; 3] = [&qd_d, &box_d, &cap_d];
    let fp: [&dyn AnyArray; 3] = [&qd_f, &box_f, &cap_f];
    agrees(
        "implicit friction on fixed shapes",
        (&dp, &fp, &[]),
        (1e-4, 1e-6, 0xf2),
        &mut |t| robot_loss(&md, &q_d, &qd_d, t),
        &mut |t| robot_loss(&mf, &q_f, &qd_f, t),
    );
}

/// Through the contact between links (a capsule pressed into a box and into a sphere, the
/// closest-point rules and the law), with respect to the start velocities and the masses.
#[test]
fn hvp_through_link_contact_matches_differences() {
    use adflex_kernels::articulation::{ArticulationBuilder, GroundContact, Inertial, Joint, Pose};
    let mut b = ArticulationBuilder::new();
    b.gravity = Vec3::zeros();
    b.ground = Some(GroundContact {
        offset: -100.0,
        ke: 1e3,
        kd: 5.0,
        mu: 0.4,
        ..GroundContact::default()
    });
    b.link_contact = true;
    let body = |b: &mut ArticulationBuilder, x: f64, y: f64| {
        b.add_link(
            format!("body{x}"),
            None,
            Joint::free().initial(&[x, y, 0.0, 0.0, 0.0, 0.0, 1.0]),
            Inertial::cuboid(1.0, Vec3::new(0.1, 0.2, 0.1), Vec3::zeros()),
        )
    };
    // A capsule along y between a box and a sphere, pressed 1 cm into each.
    let c = body(&mut b, 0.0, 0.0);
    b.add_contact_capsule(c, Vec3::new(0.0, -0.3, 0.0), Vec3::new(0.0, 0.3, 0.0), 0.05);
    let k = body(&mut b, 0.14, 0.05);
    b.add_contact_box(k, &Pose::identity(), Vec3::new(0.1, 0.1, 0.1));
    let s = body(&mut b, -0.14, -0.1);
    b.add_contact_sphere(s, Vec3::zeros(), 0.1);
    let md: Articulations<Dual> = b.finalize().unwrap();
    let mf: Articulations<f64> = b.finalize().unwrap();
    assert_eq!((md.capsule_pairs.len(), md.box_pairs.len()), (1, 2));
    let mut rng = common::Rng(0xc0);
    let qd0: Vec<f64> = (0..mf.n_dof).map(|_| rng.uniform(-0.2, 0.2)).collect();
    let (q_d, q_f) = (
        Array::from_vec(dual_of(&mf.q0)),
        Array::from_vec(mf.q0.clone()),
    );
    let (qd_d, qd_f) = (
        Array::from_vec(dual_of(&qd0)).requires_grad(),
        Array::from_vec(qd0).requires_grad(),
    );
    let (massd, massf) = (
        md.mass.clone().requires_grad(),
        mf.mass.clone().requires_grad(),
    );
    let dp: [&dyn AnyArray; 2] = [&qd_d, &massd];
    let fp: [&dyn AnyArray; 2] = [&qd_f, &massf];
    agrees(
        "link contact",
        (&dp, &fp, &[]),
        (1e-4, 1e-6, 0xc1),
        &mut |t| robot_loss(&md, &q_d, &qd_d, t),
        &mut |t| robot_loss(&mf, &q_f, &qd_f, t),
    );
}
