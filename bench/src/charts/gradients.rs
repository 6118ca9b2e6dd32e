//! Charts 3 and 4: gradient accuracy against cost (reverse mode, forward mode, finite
//! differences; f32 and f64) on a spring chain, and the gradient over long horizons on cloth.

use std::time::Instant;

use adflex_kernels::prelude::*;
use adflex_kernels::scenes::cloth::displacement_loss;
use adflex_runtime::prelude::*;
use serde_json::json;

use super::plot::{Chart, Series, Style};

const CHAIN: usize = 10;
const CHAIN_STEPS: usize = 200;
const CHAIN_DT: f64 = 1e-3;

/// A chain of `CHAIN` particles along x, the first pinned, joined by springs of stiffness
/// `100 + 10 k` (the parameters), swinging under gravity.
fn chain<R: Real>() -> Model<R> {
    let mut b = ModelBuilder::<R>::new();
    for k in 0..CHAIN {
        let m = if k == 0 { 0.0 } else { 0.1 };
        b.add_particle(
            Vec3::new(R::lit(0.1 * k as f64), R::lit(1.0), R::lit(0.0)),
            Vec3::zeros(),
            R::lit(m),
        );
    }
    for k in 0..CHAIN - 1 {
        b.add_spring(
            k as u32,
            k as u32 + 1,
            R::lit(100.0 + 10.0 * k as f64),
            R::lit(0.5),
        );
    }
    b.finalize()
}

/// Records the rollout and the loss `sum |x_T - x_0 - (0, -0.3, 0)|^2`.
fn chain_loss<R: Real>(model: &Model<R>, tape: &mut Tape) -> Array<R> {
    let s0 = model.state();
    let s = SemiImplicitEuler
        .rollout(model, tape, &s0, None, R::lit(CHAIN_DT), CHAIN_STEPS)
        .unwrap();
    let loss = Array::zeros(1).named("loss");
    let target = Vec3::new(R::lit(0.0), R::lit(-0.3), R::lit(0.0));
    tape.launch(
        displacement_loss,
        s.x.len(),
        (&s.x, &s0.x, target, R::lit(1.0), &loss),
    );
    loss
}

fn ke<R: Real>(m: &Model<R>) -> Array<R> {
    m.springs().expect("springs").ke.clone()
}

/// Best wall time of 3 runs of `f`, and its last result.
fn best_of<T>(mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..3 {
        let t0 = Instant::now();
        let r = f();
        best = best.min(t0.elapsed().as_secs_f64());
        last = Some(r);
    }
    (best, last.unwrap())
}

fn reverse<R: Real>(m: &Model<R>) -> Vec<f64> {
    let ke = ke(m).requires_grad();
    ke.zero_grad();
    let mut tape = Tape::new();
    let l = chain_loss(m, &mut tape);
    tape.backward(&l).expect("backward");
    ke.grad()
        .expect("grad")
        .to_vec()
        .iter()
        .map(|g| g.to_f64())
        .collect()
}

fn forward_mode<R: Real>(m: &Model<R>) -> Result<Vec<f64>, Error> {
    let ke = ke(m);
    let mut tape = Tape::new();
    let l = chain_loss(m, &mut tape);
    let mut g = Vec::with_capacity(ke.len());
    for k in 0..ke.len() {
        let mut e = vec![R::zero(); ke.len()];
        e[k] = R::one();
        ke.set_tangent(Some(Array::from_vec(e)));
        tape.tangent()?;
        g.push(l.tangent_buffer().expect("loss tangent").get(0).to_f64());
    }
    ke.set_tangent(None);
    Ok(g)
}

fn finite_diff<R: Real>(m: &Model<R>, h: f64) -> Vec<f64> {
    let ke = ke(m);
    let mut g = Vec::with_capacity(ke.len());
    for k in 0..ke.len() {
        let k0 = ke.get(k);
        let (kp, km) = (
            R::lit(k0.to_f64() * (1.0 + h)),
            R::lit(k0.to_f64() * (1.0 - h)),
        );
        ke.set(k, kp);
        let lp = chain_loss(m, &mut Tape::new()).get(0).to_f64();
        ke.set(k, km);
        let lm = chain_loss(m, &mut Tape::new()).get(0).to_f64();
        ke.set(k, k0);
        g.push((lp - lm) / (kp.to_f64() - km.to_f64()));
    }
    g
}

fn rel(g: &[f64], r: &[f64]) -> f64 {
    let d: f64 = g
        .iter()
        .zip(r)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt();
    d / r.iter().map(|b| b * b).sum::<f64>().sqrt()
}

/// Floor for plotting errors on a log axis (the f64 reverse mode is the reference: error 0).
const FLOOR: f64 = 1e-16;

/// `e` raised to [`FLOOR`]; NaN stays NaN (e.g. a finite difference whose step rounds away).
fn floored(e: f64) -> f64 {
    if e.is_nan() {
        e
    } else {
        e.max(FLOOR)
    }
}

/// Chart 3: relative error of dL/dke against the time to compute the whole gradient.
pub fn accuracy(
    out: &std::path::Path,
    quick: bool,
) -> Result<serde_json::Value, Box<dyn std::error::Error>> {
    let hs: Vec<f64> = if quick {
        vec![1e-2, 1e-4, 1e-6]
    } else {
        (1..=10).map(|e| 10f64.powi(-e)).collect()
    };
    let (m32, m64) = (chain::<f32>(), chain::<f64>());
    let reference = reverse(&m64);
    let mut data = Vec::new();
    let mut cost = Chart::new(
        format!("Gradient accuracy vs cost: dL/dke of a {CHAIN}-particle spring chain, {CHAIN_STEPS} steps"),
        "time for the whole gradient (s)",
        "relative error of dL/dke",
    )
    .log_log();
    cost.note = Some(format!(
        "Reference: reverse mode in f64 (plotted at {FLOOR:.0e}). Forward mode: one tangent pass per parameter ({} passes). \
         Finite differences: central, 2 x {} rollouts, relative steps h = 1e-1 .. 1e-10 (in f32, steps below 1e-7 \
         round to no change of ke and give no value).",
        CHAIN - 1,
        CHAIN - 1
    ));
    let mut by_h = Chart::new(
        "Finite differences: error vs step, against reverse and forward mode",
        "relative step h",
        "relative error of dL/dke",
    )
    .log_log();
    let hr = (hs[hs.len() - 1], hs[0]);
    for (prec, c0) in [("f32", 0usize), ("f64", 1usize)] {
        let (t_rev, g_rev) = if prec == "f32" {
            best_of(|| reverse(&m32))
        } else {
            best_of(|| reverse(&m64))
        };
        let e_rev = floored(rel(&g_rev, &reference));
        let (t_fwd, g_fwd) = if prec == "f32" {
            best_of(|| forward_mode(&m32))
        } else {
            best_of(|| forward_mode(&m64))
        };
        let e_fwd = match &g_fwd {
            Ok(g) => floored(rel(g, &reference)),
            Err(e) => {
                eprintln!("  forward mode {prec}: {e}");
                f64::NAN
            }
        };
        eprintln!(
            "  {prec}: reverse {e_rev:.2e} in {t_rev:.2e} s; forward {e_fwd:.2e} in {t_fwd:.2e} s"
        );
        data.push(
            json!({"method": "reverse", "precision": prec, "seconds": t_rev, "rel_error": e_rev}),
        );
        data.push(
            json!({"method": "forward", "precision": prec, "seconds": t_fwd, "rel_error": e_fwd}),
        );
        let mut fd_pts = Vec::new();
        let mut fd_h = Vec::new();
        for &h in &hs {
            let (t, g) = if prec == "f32" {
                best_of(|| finite_diff(&m32, h))
            } else {
                best_of(|| finite_diff(&m64, h))
            };
            let e = floored(rel(&g, &reference));
            eprintln!("  {prec}: FD h {h:.0e}: {e:.2e} in {t:.2e} s");
            data.push(json!({"method": "finite differences", "precision": prec, "h": h, "seconds": t, "rel_error": e}));
            fd_pts.push((t, e));
            fd_h.push((h, e));
        }
        let (cr, cf, cd) = (c0 * 3, c0 * 3 + 1, c0 * 3 + 2);
        cost.series.push(Series::new(
            format!("reverse mode, {prec}"),
            vec![(t_rev, e_rev)],
            Style::Points,
            cr,
        ));
        cost.series.push(Series::new(
            format!("forward mode, {prec}"),
            vec![(t_fwd, e_fwd)],
            Style::Points,
            cf,
        ));
        cost.series.push(Series::new(
            format!("finite differences, {prec} (one point per h)"),
            fd_pts,
            Style::Points,
            cd,
        ));
        by_h.series.push(Series::new(
            format!("finite differences, {prec}"),
            fd_h,
            Style::Line,
            cd,
        ));
        by_h.series.push(Series::new(
            format!("reverse mode, {prec}"),
            vec![(hr.0, e_rev), (hr.1, e_rev)],
            Style::Dashed,
            cr,
        ));
        by_h.series.push(Series::new(
            format!("forward mode, {prec}"),
            vec![(hr.0, e_fwd * 1.3), (hr.1, e_fwd * 1.3)],
            Style::Dashed,
            cf,
        ));
    }
    by_h.note = Some(format!(
        "Reference: reverse mode in f64 (its line is drawn at {FLOOR:.0e}). Forward-mode lines are drawn 1.3x above their value \
         so that they do not hide the reverse-mode lines. In f32, steps below 1e-7 round to no change of ke (no value)."
    ));
    cost.write(&out.join("gradient_accuracy.svg"))?;
    by_h.write(&out.join("gradient_accuracy_fd_step.svg"))?;
    Ok(json!(data))
}

/// A cloth of `n x n` (the benchmark's sheet) with spring stiffness `ke`, with or without the
/// ground; returns the model and an initial state whose velocities require grad.
fn cloth(n: usize, ke: f32, ground: bool) -> (Model<f32>, State<f32>) {
    let mut b = ModelBuilder::<f32>::new();
    b.particle_radius = 0.01;
    let mut grid = ClothGrid::benchmark(n);
    grid.spring_ke = ke;
    b.add_cloth_grid(&grid);
    if ground {
        // The benchmark scene's ground (damping on approach, as in Warp).
        b.set_ground(Ground {
            damp_approach: true,
            ..Ground::default()
        });
    }
    let model = b.finalize();
    let s0 = model.state();
    let _ = s0.v.clone().requires_grad();
    (model, s0)
}

/// `|dL/dv0|` after `steps` steps (loss of the cloth scene).
fn grad_v0(
    model: &Model<f32>,
    s0: &State<f32>,
    n: usize,
    steps: usize,
) -> Result<(f64, f64), Error> {
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .rollout(model, &mut tape, s0, None, 1e-3, steps)
        .unwrap();
    let loss = Array::zeros(1).named("loss");
    let target = Vec3::new(0.0, -0.1, 0.0);
    tape.launch(
        displacement_loss,
        s.x.len(),
        (&s.x, &s0.x, target, 1.0 / (n * n) as f32, &loss),
    );
    s0.v.zero_grad();
    tape.backward(&loss)?;
    let g = s0.v.grad()?.to_vec();
    let norm = g
        .iter()
        .map(|v| v.norm_squared() as f64)
        .sum::<f64>()
        .sqrt();
    Ok((loss.get(0) as f64, norm))
}

/// Chart 4: the norm of dL/dv0 against the number of steps.
pub fn long_horizon(
    out: &std::path::Path,
    quick: bool,
) -> Result<serde_json::Value, Box<dyn std::error::Error>> {
    let n = 16;
    let steps: Vec<usize> = if quick {
        vec![10, 100]
    } else {
        vec![10, 20, 50, 100, 200, 500, 1000, 2000]
    };
    let cases = [
        ("soft (ke = 50), no contact", 50.0f32, false),
        ("soft (ke = 50), ground contact", 50.0, true),
        ("stiff (ke = 2000), no contact", 2000.0, false),
        ("stiff (ke = 2000), ground contact", 2000.0, true),
    ];
    let mut chart = Chart::new(
        format!("Gradient over long horizons: |dL/dv0| vs steps ({n}x{n} cloth, dt = 1 ms, f32)"),
        "steps",
        "|dL/dv0|",
    )
    .log_log();
    chart.note = Some("Loss of the cloth scene: mean |x_T - x_0 - (0, -0.1, 0)|^2. The sheet is pinned at two corners: without the ground it swings from the pins; with it, it lands after about 65 steps and comes to rest (friction).".into());
    let mut data = Vec::new();
    for (c, (name, ke, ground)) in cases.iter().enumerate() {
        let (model, s0) = cloth(n, *ke, *ground);
        let mut pts = Vec::new();
        for &t in &steps {
            let (loss, g) = grad_v0(&model, &s0, n, t)?;
            eprintln!("  {name}: {t} steps: loss {loss:.4e}, |dL/dv0| {g:.3e}");
            data.push(json!({"case": name, "steps": t, "loss": loss, "grad_v0_norm": g}));
            if g.is_finite() {
                pts.push((t as f64, g));
            }
        }
        chart.series.push(Series::new(*name, pts, Style::Line, c));
    }
    chart.write(&out.join("gradient_long_horizon.svg"))?;
    Ok(json!(data))
}
