//! Plastic MPM (snow): the spectral clamp's hand-written derivatives against central
//! differences (also where eigenvalues coincide) and forward mode against reverse mode;
//! Taichi's `mpm99` (fluid, jelly and snow in one scene) reproduced from its f64 run
//! (`references/taichi_mpm99.py`); rollouts through plasticity in 2D and 3D against central
//! differences; snow keeps a dent where jelly springs back; bad parameters refused by name;
//! the clamp's second-order rules (in `Dual`) against differences of its first-order ones, and
//! Hessian-vector products of a snow rollout against central differences of its gradients.

use adflex_kernels::mpm::plastic::{clamp_spectrum2, clamp_spectrum3};
use adflex_kernels::mpm::*;
use adflex_macros::diff_kernel;
use adflex_runtime::gradcheck::{dot_test, GradCheck};
use adflex_runtime::prelude::*;
use adflex_runtime::second_order::hvp;
use nalgebra::SMatrix;
use serde_json::Value;

/// A rotation by angles `a` about x, `b` about y, `c` about z.
fn rotation(a: f64, b: f64, c: f64) -> Mat33<f64> {
    let (sa, ca, sb, cb, sc, cc) = (a.sin(), a.cos(), b.sin(), b.cos(), c.sin(), c.cos());
    Mat33::new(1.0, 0.0, 0.0, 0.0, ca, -sa, 0.0, sa, ca)
        * Mat33::new(cb, 0.0, sb, 0.0, 1.0, 0.0, -sb, 0.0, cb)
        * Mat33::new(cc, -sc, 0.0, sc, cc, 0.0, 0.0, 0.0, 1.0)
}

/// `<adj, clamp(s + h e_k)>` differences against the adjoint's `k`-th entry, for every entry
/// of `s` and both bounds; and `<tangent(v), w> = <v, adjoint(w)>`.
fn check_clamp3(s: Mat33<f64>, lo: f64, hi: f64, what: &str) {
    let w = Mat33::from_fn(|i, j| ((3 * i + j) as f64 * 0.7 + 0.2).sin());
    let value = |s: Mat33<f64>, lo: f64, hi: f64| clamp_spectrum3.forward((s, lo, hi)).dot(&w);
    let (gs, glo, ghi) = clamp_spectrum3.adjoint((s, lo, hi), w);
    let h = 1e-6;
    for k in 0..9 {
        let mut e = Mat33::zeros();
        e[k] = h;
        let fd = (value(s + e, lo, hi) - value(s - e, lo, hi)) / (2.0 * h);
        assert!(
            (fd - gs[k]).abs() < 1e-7,
            "{what}: d/ds[{k}] {} vs {fd}",
            gs[k]
        );
    }
    let fd_lo = (value(s, lo + h, hi) - value(s, lo - h, hi)) / (2.0 * h);
    let fd_hi = (value(s, lo, hi + h) - value(s, lo, hi - h)) / (2.0 * h);
    assert!((fd_lo - glo).abs() < 1e-7, "{what}: d/dlo {glo} vs {fd_lo}");
    assert!((fd_hi - ghi).abs() < 1e-7, "{what}: d/dhi {ghi} vs {fd_hi}");
    let v = Mat33::from_fn(|i, j| ((2 * i + 5 * j) as f64 * 1.3 + 0.4).cos());
    let (dlo, dhi) = (0.3, -0.8);
    let (_, t) = clamp_spectrum3.tangent((s, lo, hi), (v, dlo, dhi));
    let forward = t.dot(&w);
    let reverse = gs.dot(&v) + glo * dlo + ghi * dhi;
    assert!(
        (forward - reverse).abs() <= 1e-12 * (1.0 + reverse.abs()),
        "{what}: <J v, w> = {forward}, <v, J^T w> = {reverse}"
    );
}

#[test]
fn the_spectral_clamp_differentiates_also_at_repeated_eigenvalues() {
    let q = rotation(0.3, -1.1, 0.7);
    let spd = |l: [f64; 3]| q * Mat33::from_diagonal(&Vec3::new(l[0], l[1], l[2])) * q.transpose();
    let (lo, hi) = (0.95, 1.05);
    // The value: eigenvalues clamped, eigenvectors kept.
    let out = clamp_spectrum3.forward((spd([1.2, 0.9, 1.0]), lo, hi));
    assert!((out - spd([1.05, 0.95, 1.0])).norm() < 1e-14, "{out}");
    for (l, what) in [
        ([1.2, 0.9, 1.0], "one eigenvalue per region"),
        ([1.2, 1.0, 1.0], "a repeated eigenvalue inside"),
        ([1.2, 0.9, 0.9], "a repeated eigenvalue below"),
        ([1.1, 1.1, 0.98], "a repeated eigenvalue above"),
        ([1.0, 1.0, 1.0], "the identity (all three equal, inside)"),
        ([0.5, 0.5, 0.5], "all three equal, below"),
        ([1.01, 0.99, 0.97], "all inside"),
    ] {
        check_clamp3(spd(l), lo, hi, what);
    }
    // A non-symmetric input: its symmetric part is clamped.
    let mut s = spd([1.2, 0.9, 1.0]);
    s[(0, 1)] += 0.05;
    check_clamp3(s, lo, hi, "a non-symmetric input");

    // 2D: the adjoint against central differences.
    let s2 = Mat22::new(1.1, 0.07, 0.07, 0.93);
    let w = Mat22::new(0.3, -0.7, 0.5, 1.1);
    let (g, glo, ghi) = clamp_spectrum2.adjoint((s2, lo, hi), w);
    let f = |s: Mat22<f64>, lo: f64, hi: f64| clamp_spectrum2.forward((s, lo, hi)).dot(&w);
    let h = 1e-6;
    for k in 0..4 {
        let mut e = Mat22::zeros();
        e[k] = h;
        let fd = (f(s2 + e, lo, hi) - f(s2 - e, lo, hi)) / (2.0 * h);
        assert!((fd - g[k]).abs() < 1e-7, "2D d/ds[{k}] {} vs {fd}", g[k]);
    }
    let fd = (f(s2, lo + h, hi) - f(s2, lo - h, hi)) / (2.0 * h);
    assert!(
        (fd - glo).abs() < 1e-7 && glo != 0.0,
        "2D d/dlo {glo} vs {fd}"
    );
    let fd = (f(s2, lo, hi + h) - f(s2, lo, hi - h)) / (2.0 * h);
    assert!(
        (fd - ghi).abs() < 1e-7 && ghi != 0.0,
        "2D d/dhi {ghi} vs {fd}"
    );
    // At the identity the derivative is the identity map on the symmetric part (no NaN from
    // the repeated eigenvalue).
    let (g, _, _) = clamp_spectrum2.adjoint((Mat22::identity(), lo, hi), w);
    assert!((g - (w + w.transpose()) * 0.5).norm() < 1e-15, "{g}");
}

/// `value + eps ε`, entry by entry.
fn dual<const N: usize>(
    value: &SMatrix<f64, N, N>,
    eps: &SMatrix<f64, N, N>,
) -> SMatrix<Dual, N, N> {
    SMatrix::from_fn(|i, j| Dual::new(value[(i, j)], eps[(i, j)]))
}

/// The `Dual` parts.
fn eps<const N: usize>(m: &SMatrix<Dual, N, N>) -> SMatrix<f64, N, N> {
    m.map(|v| v.eps)
}

/// The clamp's rules run in `Dual` along `(ds, dlo, dhi)` (and `dadj`, `dt` for the adjoint's
/// and the tangent's own inputs) against central differences of the `f64` rules along the
/// same direction, to `1e-7` of the largest entry; the value's `Dual` part against central
/// differences of the value.
#[allow(clippy::too_many_arguments)]
fn check_second_order<const N: usize>(
    s: SMatrix<f64, N, N>,
    (lo, hi): (f64, f64),
    ds: SMatrix<f64, N, N>,
    (dlo, dhi): (f64, f64),
    (adj, dadj): (SMatrix<f64, N, N>, SMatrix<f64, N, N>),
    (t, dt): (SMatrix<f64, N, N>, SMatrix<f64, N, N>),
    value: impl Fn(SMatrix<Dual, N, N>, Dual, Dual) -> SMatrix<Dual, N, N>,
    adjoint: impl Fn(
        SMatrix<Dual, N, N>,
        Dual,
        Dual,
        SMatrix<Dual, N, N>,
    ) -> (SMatrix<Dual, N, N>, Dual, Dual),
    tangent: impl Fn(
        SMatrix<Dual, N, N>,
        Dual,
        Dual,
        SMatrix<Dual, N, N>,
        Dual,
        Dual,
    ) -> SMatrix<Dual, N, N>,
    what: &str,
) {
    let h = 1e-6;
    let c = Dual::constant;
    let sd = dual(&s, &ds);
    let (lod, hid) = (Dual::new(lo, dlo), Dual::new(hi, dhi));
    // An f64 rule at the point moved by `e` along the direction.
    let at = |e: f64| {
        let (s, lo, hi) = (s + ds * e, c(lo + dlo * e), c(hi + dhi * e));
        let sc = dual(&s, &SMatrix::zeros());
        let (ga, gl, gh) = adjoint(sc, lo, hi, dual(&(adj + dadj * e), &SMatrix::zeros()));
        let tt = tangent(
            sc,
            lo,
            hi,
            dual(&(t + dt * e), &SMatrix::zeros()),
            c(0.3),
            c(-0.8),
        );
        (
            ga.map(|v| v.re),
            gl.re,
            gh.re,
            tt.map(|v| v.re),
            value(sc, lo, hi).map(|v| v.re),
        )
    };
    let (p, m) = (at(h), at(-h));
    let fd = |a: f64, b: f64| (a - b) / (2.0 * h);
    // The value's Dual part is its first derivative.
    let v_eps = eps(&value(sd, lod, hid));
    let v_fd = (p.4 - m.4) / (2.0 * h);
    assert!(
        (v_eps - v_fd).norm() < 1e-7,
        "{what}: value {v_eps} vs {v_fd}"
    );
    // The adjoint's Dual parts: its derivative along (ds, dlo, dhi, dadj).
    let (ga, gl, gh) = adjoint(sd, lod, hid, dual(&adj, &dadj));
    let ga_fd = (p.0 - m.0) / (2.0 * h);
    let scale = ga_fd.amax().max(1.0);
    assert!(
        (eps(&ga) - ga_fd).amax() < 1e-7 * scale,
        "{what}: adjoint {} vs {ga_fd}",
        eps(&ga)
    );
    assert!(
        (gl.eps - fd(p.1, m.1)).abs() < 1e-7 * scale,
        "{what}: d lo {} vs {}",
        gl.eps,
        fd(p.1, m.1)
    );
    assert!(
        (gh.eps - fd(p.2, m.2)).abs() < 1e-7 * scale,
        "{what}: d hi {} vs {}",
        gh.eps,
        fd(p.2, m.2)
    );
    // The tangent's Dual parts: its derivative along (ds, dlo, dhi, dt).
    let tt = tangent(sd, lod, hid, dual(&t, &dt), c(0.3), c(-0.8));
    let tt_fd = (p.3 - m.3) / (2.0 * h);
    assert!(
        (eps(&tt) - tt_fd).amax() < 1e-7 * tt_fd.amax().max(1.0),
        "{what}: tangent {} vs {tt_fd}",
        eps(&tt)
    );
    // The check can fail: the second-order part is not zero everywhere.
    assert!(
        what.contains("inside") || ga_fd.amax() > 1e-3 || tt_fd.amax() > 1e-3,
        "{what}: no second-order part to check"
    );
}

#[test]
fn the_spectral_clamps_second_order_rules_match_differences_of_its_first_order_ones() {
    let q = rotation(0.3, -1.1, 0.7);
    let spd = |l: [f64; 3]| q * Mat33::from_diagonal(&Vec3::new(l[0], l[1], l[2])) * q.transpose();
    let m3 = |a: f64, b: f64| Mat33::from_fn(|i, j| ((3 * i + j) as f64 * a + b).sin());
    for (l, what) in [
        ([1.2, 0.9, 1.0], "one eigenvalue per region"),
        ([1.2, 1.0, 1.0], "a repeated eigenvalue inside"),
        ([1.2, 0.9, 0.9], "a repeated eigenvalue below"),
        ([1.1, 1.1, 0.98], "a repeated eigenvalue above"),
        ([1.01, 0.99, 0.97], "all inside"),
        ([1.3, 1.2, 0.8], "two above, one below"),
    ] {
        check_second_order(
            spd(l),
            (0.95, 1.05),
            m3(1.3, 0.4) * 0.1,
            (0.02, -0.03),
            (m3(0.7, 0.2), m3(0.9, -0.5)),
            (m3(1.9, 0.1), m3(0.4, 1.2)),
            |s, lo, hi| clamp_spectrum3.forward((s, lo, hi)),
            |s, lo, hi, w| clamp_spectrum3.adjoint((s, lo, hi), w),
            |s, lo, hi, d, dlo, dhi| clamp_spectrum3.tangent((s, lo, hi), (d, dlo, dhi)).1,
            what,
        );
    }
    let m2 = |a: f64, b: f64| Mat22::from_fn(|i, j| ((2 * i + j) as f64 * a + b).cos());
    check_second_order(
        Mat22::new(1.1, 0.07, 0.02, 0.93),
        (0.95, 1.05),
        m2(1.1, 0.3) * 0.1,
        (0.01, 0.02),
        (m2(0.6, -0.2), m2(1.4, 0.8)),
        (m2(0.3, 0.9), m2(2.1, -0.4)),
        |s, lo, hi| clamp_spectrum2.forward((s, lo, hi)),
        |s, lo, hi, w| clamp_spectrum2.adjoint((s, lo, hi), w),
        |s, lo, hi, d, dlo, dhi| clamp_spectrum2.tangent((s, lo, hi), (d, dlo, dhi)).1,
        "2D, one eigenvalue above, one below",
    );
}

/// The reference file.
fn mpm99() -> Value {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/references/mpm99.json");
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// Taichi's `mpm99` scene as adflex builds it (see `references/taichi_mpm99.py`).
fn mpm99_scene(r: &Value) -> MpmBuilder {
    let n_grid = r["n_grid"].as_u64().unwrap() as usize;
    let dx = 1.0 / n_grid as f64;
    let (e, nu) = (r["E"].as_f64().unwrap(), r["nu"].as_f64().unwrap());
    let (mu, lambda) = Material::lame(e, nu);
    let p_vol = (dx * 0.5) * (dx * 0.5);
    let mut b = MpmBuilder::new(n_grid, dx);
    b.set_gravity(Vec2::new(0.0, r["gravity"].as_f64().unwrap()));
    b.set_floor(Floor::Coulomb(0.0));
    for block in r["blocks"].as_array().unwrap() {
        let pair =
            |k: &str| Vec2::new(block[k][0].as_f64().unwrap(), block[k][1].as_f64().unwrap());
        let material = match block["material"].as_u64().unwrap() {
            0 => Material::Fluid { bulk: lambda },
            1 => Material::Corotated {
                mu: 0.3 * mu,
                lambda: 0.3 * lambda,
            },
            _ => Material::snow(e, nu),
        };
        let ps = b.add_rect(pair("lo"), pair("size"), p_vol, p_vol, material);
        for p in ps {
            b.set_velocity(p, pair("v"));
        }
    }
    b
}

#[test]
fn taichis_mpm99_is_reproduced() {
    let r = mpm99();
    let mpm = mpm99_scene(&r).finalize::<f64>().unwrap();
    let n = mpm.particle_count();
    // The library's scene is the reference's.
    let scene = scenes::mpm99(32).finalize::<f64>().unwrap();
    let (a, b) = (scene.state(), mpm.state());
    assert_eq!(a.x.to_vec(), b.x.to_vec());
    assert_eq!(a.v.to_vec(), b.v.to_vec());
    assert_eq!(scene.mu.to_vec(), mpm.mu.to_vec());
    assert_eq!(scene.lambda.to_vec(), mpm.lambda.to_vec());
    assert_eq!(scene.kind.to_vec(), mpm.kind.to_vec());
    assert_eq!(scene.mass.to_vec(), mpm.mass.to_vec());
    assert_eq!(scene.gravity.to_vec(), mpm.gravity.to_vec());
    assert_eq!(scene.friction, mpm.friction);
    assert_eq!(scene.volume.to_vec(), mpm.volume.to_vec());
    for (a, b) in [
        (&scene.compression, &mpm.compression),
        (&scene.stretch, &mpm.stretch),
        (&scene.hardening, &mpm.hardening),
    ] {
        assert_eq!(a.to_vec(), b.to_vec());
    }
    assert_eq!(
        (scene.n_grid, scene.dx, scene.bound),
        (mpm.n_grid, mpm.dx, mpm.bound)
    );
    // The library's scene is what runs.
    let mpm = scene;
    assert_eq!(n, r["x"].as_array().unwrap().len());
    let dt = r["dt"].as_f64().unwrap();
    let mut s = mpm.state();
    for _ in 0..r["steps"].as_u64().unwrap() {
        s = mpm.step(&mut Tape::new(), &s, None, dt).unwrap();
    }
    let (x, v, f, jp) = (s.x.to_vec(), s.v.to_vec(), s.f.to_vec(), s.jp.to_vec());
    let (mut ex, mut ev, mut ef, mut ej) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let (mut packed, mut stretched) = (0, 0);
    // Taichi's own `ti.svd`, which treats an off-diagonal below 1e-5 as zero.
    let mut ti_svd = 0.0f64;
    for p in 0..n {
        let tx = &r["ti_svd_x"][p];
        let tx = Vec2::new(tx[0].as_f64().unwrap(), tx[1].as_f64().unwrap());
        ti_svd = ti_svd.max((x[p] - tx).norm());
        let rx = Vec2::new(
            r["x"][p][0].as_f64().unwrap(),
            r["x"][p][1].as_f64().unwrap(),
        );
        let rv = Vec2::new(
            r["v"][p][0].as_f64().unwrap(),
            r["v"][p][1].as_f64().unwrap(),
        );
        let rf = &r["F"][p];
        let rf = Mat22::new(
            rf[0].as_f64().unwrap(),
            rf[1].as_f64().unwrap(),
            rf[2].as_f64().unwrap(),
            rf[3].as_f64().unwrap(),
        );
        let rj = r["Jp"][p].as_f64().unwrap();
        ex = ex.max((x[p] - rx).norm());
        ev = ev.max((v[p] - rv).norm());
        ef = ef.max((f[p] - rf).norm());
        ej = ej.max((jp[p] - rj).abs());
        packed += usize::from(rj < 0.95);
        stretched += usize::from(rj > 1.01);
    }
    // The scene exercises the plasticity both ways.
    assert!(
        packed > 10 && stretched > 3,
        "{packed} packed, {stretched} stretched"
    );
    eprintln!(
        "mpm99 after 500 steps, largest differences: x {ex:.1e}, v {ev:.1e}, F {ef:.1e}, \
         Jp {ej:.1e}; x from the run with ti.svd {ti_svd:.1e}"
    );
    assert!(
        ex < 1e-12 && ev < 1e-10 && ef < 1e-12 && ej < 1e-12,
        "{ex} {ev} {ef} {ej}"
    );
    assert!(ti_svd < 1e-3, "{ti_svd}");
}

/// `loss[0] = -c[0].x + 2 c[0].y` (2D).
#[diff_kernel]
fn mean_loss<R: Real>(c: &Array<Vec2<R>>, loss: &Array<R>) {
    loss[0] = -c[0].x + 2.0 * c[0].y;
}

/// `loss[0] = -c[0].x + c[0].y + c[0].z` (3D).
#[diff_kernel]
fn mean_loss3<R: Real>(c: &Array<Vec3<R>>, loss: &Array<R>) {
    loss[0] = -c[0].x + c[0].y + c[0].z;
}

/// A snow block thrown at the floor with a spin (2D), in precision `R`.
fn thrown_snow<R: Real>(floor: Floor) -> Mpm<R> {
    let mut b = MpmBuilder::new(16, 1.0 / 16.0);
    b.set_floor(floor);
    let material = Material::Snow {
        mu: 30.0,
        lambda: 30.0,
        compression: 0.02,
        stretch: 0.01,
        hardening: 5.0,
    };
    let r = b.add_rect(
        Vec2::new(0.3, 0.22),
        Vec2::new(0.25, 0.2),
        1.0,
        1.0,
        material,
    );
    let xs = b.clone().finalize::<f64>().unwrap().state().x.to_vec();
    for (p, x) in r.zip(&xs) {
        b.set_velocity(
            p,
            Vec2::new(0.5 - 2.0 * (x.y - 0.32), -1.5 + 2.0 * (x.x - 0.42)),
        );
    }
    b.finalize::<R>().unwrap()
}

/// The gradient of `loss` along a fixed direction through the values of `arrays`
/// (`d_k = p_k sin(1.7 k + 0.3)`: relative to each value, so that moduli of 30 and yield
/// strains of 0.01 move alike), and its relative disagreement with the closest of the central
/// differences of relative steps 1e-3, 3e-4, 1e-4 and 3e-5.
///
/// One direction rather than a difference per scalar: a single particle's modulus moves the
/// loss by 1e-9, where a difference is mostly rounding. A sweep of steps because both ends
/// fail for a reason: the large steps cross kinks of the loss (a particle resting on the
/// yield surface changes branch, a floor node goes from sliding to sticking), the small ones
/// are rounding. Measured: the 2D yield strains on the Coulomb floor differ from the
/// gradient by 1e-1 at 1e-3 and 2e-2 at 3e-4 (kinks), 1e-8 at 1e-4 and 2e-8 at 3e-5; the 3D
/// moduli by 1.3e-7, 4.8e-8, 3.9e-6 (rounding), 7.4e-6.
fn along(loss: &dyn Fn(&mut Tape) -> Array<f64>, arrays: &[&Array<f64>]) -> (f64, f64) {
    let base: Vec<Vec<f64>> = arrays.iter().map(|a| a.to_vec()).collect();
    let dir = |k: usize| (1.7 * k as f64 + 0.3).sin();
    let set = |t: f64| {
        let mut k = 0;
        for (a, b) in arrays.iter().zip(&base) {
            for (i, v) in b.iter().enumerate() {
                a.set(i, v * (1.0 + t * dir(k)));
                k += 1;
            }
        }
    };
    set(0.0);
    for a in arrays {
        let _ = (*a).clone().requires_grad();
        a.zero_grad();
    }
    let mut tape = Tape::new();
    let l = loss(&mut tape);
    tape.backward(&l).unwrap();
    let mut analytic = 0.0;
    let mut k = 0;
    for (a, b) in arrays.iter().zip(&base) {
        for (g, v) in a.grad().unwrap().to_vec().iter().zip(b) {
            analytic += g * v * dir(k);
            k += 1;
        }
    }
    let at = |t: f64| {
        set(t);
        loss(&mut Tape::new()).get(0)
    };
    let error = [1e-3, 3e-4, 1e-4, 3e-5]
        .iter()
        .map(|&h| {
            let fd = (at(h) - at(-h)) / (2.0 * h);
            (analytic - fd).abs() / fd.abs()
        })
        .fold(f64::INFINITY, f64::min);
    set(0.0);
    (analytic, error)
}

/// `steps` steps of `mpm` (2D), the loss of the mean position.
fn snow_loss(mpm: &Mpm<f64>, tape: &mut Tape, steps: usize) -> Array<f64> {
    let mut s = mpm.state();
    for _ in 0..steps {
        s = mpm.step(tape, &s, None, 2e-3).unwrap();
    }
    let c = mpm.mean_position(tape, &s);
    let out = Array::zeros(1);
    tape.launch(mean_loss, 1, (&c, &out));
    out
}

#[test]
fn snow_rollouts_match_central_differences_and_tangents() {
    for floor in [Floor::Coulomb(0.3), Floor::Sticky] {
        let mpm = thrown_snow::<f64>(floor);
        let steps = 30;
        let loss = |tape: &mut Tape| snow_loss(&mpm, tape, steps);
        let groups: [(&str, Vec<&Array<f64>>); 4] = [
            ("moduli", vec![&mpm.mu, &mpm.lambda]),
            ("yield strains", vec![&mpm.compression, &mpm.stretch]),
            ("hardening", vec![&mpm.hardening]),
            ("masses", vec![&mpm.mass]),
        ];
        for (what, arrays) in &groups {
            let (analytic, error) = along(&loss, arrays);
            eprintln!("{floor:?}, {what}: {analytic:e}, {error:.1e} from a central difference");
            assert!(
                analytic.abs() > 1e-5,
                "{floor:?}, {what}: vanishing {analytic}"
            );
            assert!(
                error <= 1e-6,
                "{floor:?}, {what}: {analytic} is {error:e} from the differences"
            );
        }
        GradCheck::new()
            .run(loss, &[&mpm.gravity])
            .unwrap()
            .assert_within(1e-6);
        // The plasticity acted.
        let mut s = mpm.state();
        for _ in 0..steps {
            s = mpm.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
        }
        assert!(
            s.jp.to_vec().iter().any(|&j| j < 0.99),
            "{floor:?}: no packing"
        );
        let run = |tape: &mut Tape| {
            let mut s = mpm.state();
            for _ in 0..steps {
                s = mpm.step(tape, &s, None, 2e-3).unwrap();
            }
            vec![s.x.boxed(), s.f.boxed(), s.jp.boxed()]
        };
        let params: [&dyn AnyArray; 5] = [
            &mpm.mu,
            &mpm.lambda,
            &mpm.compression,
            &mpm.stretch,
            &mpm.hardening,
        ];
        dot_test(run, &params, 3).unwrap().assert_within(1e-10);
    }
}

#[test]
fn three_d_snow_rollouts_match_central_differences() {
    let mut b = MpmBuilder::new_3d(12, 1.0 / 12.0);
    let r = b.add_rect(
        Vec3::new(0.35, 0.28, 0.35),
        Vec3::new(0.25, 0.17, 0.25),
        1.0,
        1.0,
        Material::Snow {
            mu: 20.0,
            lambda: 20.0,
            compression: 0.02,
            stretch: 0.01,
            hardening: 5.0,
        },
    );
    let xs = b.clone().finalize::<f64>().unwrap().state().x.to_vec();
    for (p, x) in r.zip(&xs) {
        b.set_velocity(p, Vec3::new(0.2 - (x.y - 0.35), -2.5, 0.3 * (x.x - 0.45)));
    }
    let mpm = b.finalize::<f64>().unwrap();
    let steps = 15;
    let loss = |tape: &mut Tape| {
        let mut s = mpm.state();
        for _ in 0..steps {
            s = mpm.step(tape, &s, None, 2e-3).unwrap();
        }
        let c = mpm.mean_position(tape, &s);
        let out = Array::zeros(1);
        tape.launch(mean_loss3, 1, (&c, &out));
        out
    };
    for (what, arrays) in [
        ("moduli", vec![&mpm.mu, &mpm.lambda]),
        ("yield strains", vec![&mpm.compression, &mpm.stretch]),
        ("hardening", vec![&mpm.hardening]),
    ] {
        let (analytic, error) = along(&loss, &arrays);
        eprintln!("3D {what}: {analytic:e}, {error:.1e} from a central difference");
        assert!(analytic.abs() > 1e-8, "3D {what}: vanishing {analytic}");
        assert!(
            error <= 1e-6,
            "3D {what}: {analytic} is {error:e} from the differences"
        );
    }
    let mut s = mpm.state();
    for _ in 0..steps {
        s = mpm.step(&mut Tape::new(), &s, None, 2e-3).unwrap();
    }
    let jp = s.jp.to_vec();
    assert!(jp.iter().any(|&j| j < 0.99), "no packing: {jp:?}");
}

/// The height of a block (highest minus lowest particle) dropped on the floor, 0.6 s later,
/// as a fraction of its first height; and its particles' `Jp`.
fn squashed(material: Material) -> (f64, Vec<f64>) {
    let mut b = MpmBuilder::new(24, 1.0 / 24.0);
    let r = b.add_rect(
        Vec2::new(0.35, 0.2),
        Vec2::new(0.3, 0.2),
        1.0,
        1.0,
        material,
    );
    for p in r {
        b.set_velocity(p, Vec2::new(0.0, -3.0));
    }
    let mpm = b.finalize::<f64>().unwrap();
    let height = |x: &[Vec2<f64>]| {
        let ys = x.iter().map(|x| x.y);
        ys.clone().fold(f64::MIN, f64::max) - ys.fold(f64::MAX, f64::min)
    };
    let h0 = height(&mpm.state().x.to_vec());
    let mut s = mpm.state();
    for _ in 0..600 {
        s = mpm.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
    }
    (height(&s.x.to_vec()) / h0, s.jp.to_vec())
}

#[test]
fn snow_keeps_a_dent_where_jelly_springs_back() {
    let (mu, lambda) = (100.0, 100.0);
    let (jelly, jelly_jp) = squashed(Material::Corotated { mu, lambda });
    let (snow, snow_jp) = squashed(Material::Snow {
        mu,
        lambda,
        compression: 0.02,
        stretch: 0.01,
        hardening: 3.0,
    });
    eprintln!("height after the fall: jelly {jelly:.4}, snow {snow:.4} of the first");
    assert!(jelly_jp.iter().all(|&j| j == 1.0));
    assert!(snow_jp.iter().any(|&j| j < 0.95));
    assert!(jelly > 0.9 && snow < 0.8, "jelly {jelly}, snow {snow}");
}

#[test]
fn snow_within_its_limits_is_the_corotated_material() {
    // A gentle spin: every singular value stays inside [1 - 0.2, 1 + 0.2].
    let run = |material: Material| {
        let mut b = MpmBuilder::new(16, 1.0 / 16.0);
        let r = b.add_rect(Vec2::new(0.4, 0.4), Vec2::new(0.2, 0.2), 1.0, 1.0, material);
        let xs = b.clone().finalize::<f64>().unwrap().state().x.to_vec();
        for (p, x) in r.zip(&xs) {
            b.set_velocity(p, Vec2::new(-(x.y - 0.5), x.x - 0.5) * 0.5);
        }
        b.set_gravity(Vec2::zeros());
        let mpm = b.finalize::<f64>().unwrap();
        let mut s = mpm.state();
        for _ in 0..100 {
            s = mpm.step(&mut Tape::new(), &s, None, 1e-3).unwrap();
        }
        s
    };
    let (mu, lambda) = (20.0, 20.0);
    let a = run(Material::Corotated { mu, lambda });
    let b = run(Material::Snow {
        mu,
        lambda,
        compression: 0.2,
        stretch: 0.2,
        hardening: 10.0,
    });
    let dx: f64 =
        a.x.to_vec()
            .iter()
            .zip(b.x.to_vec())
            .map(|(p, q)| (p - q).norm())
            .fold(0.0, f64::max);
    assert!(dx < 1e-12, "{dx}");
    assert!(b.jp.to_vec().iter().all(|&j| (j - 1.0).abs() < 1e-12));
}

#[test]
fn bad_plasticity_is_refused_by_name() {
    let mut b = MpmBuilder::new(16, 1.0 / 16.0);
    b.add_rect(
        Vec2::new(0.4, 0.4),
        Vec2::new(0.125, 0.125),
        1.0,
        1.0,
        Material::Snow {
            mu: 10.0,
            lambda: 10.0,
            compression: 1.5,
            stretch: 0.01,
            hardening: 10.0,
        },
    );
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(
        e.contains("particles[0]") && e.contains("compression"),
        "{e}"
    );

    // A yield strain an optimizer moved out of range is refused at the step, by name.
    let mpm = thrown_snow::<f64>(Floor::Sticky);
    mpm.compression.set(3, 1.2);
    let e = mpm
        .step(&mut Tape::new(), &mpm.state(), None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("mpm.compression[3]") && e.contains("[0, 1)"),
        "{e}"
    );
    let mpm = thrown_snow::<f64>(Floor::Sticky);
    mpm.compression.set(2, 0.0);
    mpm.stretch.set(2, 0.0);
    let e = mpm
        .step(&mut Tape::new(), &mpm.state(), None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("particle 2") && e.contains("not both 0"), "{e}");

    // A state whose Jp is not positive.
    let mpm = thrown_snow::<f64>(Floor::Sticky);
    let s = mpm.state();
    s.jp.set(4, 0.0);
    let e = mpm
        .step(&mut Tape::new(), &s, None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("particle 4") && e.contains("Jp"), "{e}");

    // A snow particle whose F inverts within a step (I + dt C reflects x): the clamp keeps
    // the stored F a rotation times a positive stretch, so the inversion shows in Jp, which
    // turns negative, and the step refuses its own result by name rather than hand it on.
    let mpm = thrown_snow::<f64>(Floor::Sticky);
    let s = mpm.state();
    s.c.set(4, Mat22::new(-2.0 / 1e-3, 0.0, 0.0, 0.0));
    let e = mpm
        .step(&mut Tape::new(), &s, None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("particle 4")
            && e.contains("Jp")
            && e.contains("inverted")
            && e.contains("the step's result"),
        "{e}"
    );
}

/// `H v` of a snow rollout through plasticity (30 steps; the moduli, yield strains and
/// hardening, `v` relative to each value) against central differences of its `f64` gradient
/// along `v` (the closest of relative steps 1e-4, 3e-5 and 1e-5, as the loss has kinks; see
/// [`along`]), to 1e-6 of the largest entry; `w^T H v = v^T H w` to 1e-10.
#[test]
fn snow_hessian_vector_products_match_differences_of_gradients() {
    let steps = 30;
    let md = thrown_snow::<Dual>(Floor::Sticky);
    let mf = thrown_snow::<f64>(Floor::Sticky);
    let pd = [
        &md.mu,
        &md.lambda,
        &md.compression,
        &md.stretch,
        &md.hardening,
    ];
    let pf = [
        &mf.mu,
        &mf.lambda,
        &mf.compression,
        &mf.stretch,
        &mf.hardening,
    ];
    let base: Vec<f64> = pf.iter().flat_map(|a| a.to_vec()).collect();
    let direction = |phase: f64| -> Vec<f64> {
        base.iter()
            .enumerate()
            .map(|(k, p)| p * (1.7 * k as f64 + phase).sin())
            .collect()
    };
    let (v, w) = (direction(0.3), direction(1.1));
    let params: Vec<&dyn AnyArray> = pd
        .iter()
        .map(|a| {
            let _ = (*a).clone().requires_grad();
            *a as &dyn AnyArray
        })
        .collect();
    let loss_d = |tape: &mut Tape| -> Result<Array<Dual>, Error> {
        let mut s = md.state();
        for _ in 0..steps {
            s = md.step(tape, &s, None, 2e-3)?;
        }
        let c = md.mean_position(tape, &s);
        let out = Array::zeros(1);
        tape.launch(mean_loss, 1, (&c, &out));
        Ok(out)
    };
    let hv = hvp(&params, &v, loss_d).unwrap();
    let hw = hvp(&params, &w, loss_d).unwrap();
    let (whv, vhw): (f64, f64) = (
        w.iter().zip(&hv.hv).map(|(a, b)| a * b).sum(),
        v.iter().zip(&hw.hv).map(|(a, b)| a * b).sum(),
    );
    assert!(
        (whv - vhw).abs() <= 1e-10 * whv.abs().max(vhw.abs()),
        "w^T H v = {whv}, v^T H w = {vhw}"
    );
    // The f64 gradient at base + t v.
    for a in pf {
        let _ = (*a).clone().requires_grad();
    }
    let gradient = |t: f64| -> Vec<f64> {
        let mut k = 0;
        for a in pf {
            for i in 0..a.len() {
                a.set(i, base[k] + t * v[k]);
                k += 1;
            }
            a.zero_grad();
        }
        let mut tape = Tape::new();
        let l = snow_loss(&mf, &mut tape, steps);
        tape.backward(&l).unwrap();
        pf.iter().flat_map(|a| a.grad().unwrap().to_vec()).collect()
    };
    let scale = hv.hv.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    assert!(scale > 1e-6, "H v vanishes: {scale}");
    let error = [1e-4, 3e-5, 1e-5]
        .iter()
        .map(|&h| {
            let (p, m) = (gradient(h), gradient(-h));
            hv.hv
                .iter()
                .zip(p.iter().zip(&m))
                .map(|(a, (p, m))| (a - (p - m) / (2.0 * h)).abs())
                .fold(0.0f64, f64::max)
                / scale
        })
        .fold(f64::INFINITY, f64::min);
    eprintln!("snow H v: largest entry {scale:e}, {error:.1e} from differences of gradients");
    assert!(
        error <= 1e-6,
        "H v is {error:e} (of its largest entry) from the differences"
    );
    // The gradient the product carries is the f64 one.
    let g = gradient(0.0);
    for (a, b) in hv.grad.iter().zip(&g) {
        assert!((a - b).abs() <= 1e-12 * (1.0 + b.abs()), "{a} vs {b}");
    }
}
