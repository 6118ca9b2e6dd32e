//! A cart-pole balancing policy learned by gradients through the simulator, over many worlds.
//!
//! 64 cart-poles (`kernels/robots/cartpole.urdf`, one world each, one model, one launch per
//! kernel) start from random states around upright. A small network, written as kernels
//! (5 inputs `x, sin theta, cos theta, xd, thetad`, 32 tanh units, one force `10 tanh(.)` N
//! on the cart), drives them all. Training is short-horizon (SHAC-style): windows of 32 steps
//! of 1/50 s, each with the loss `mean over worlds and steps of c`, where
//! `c = (1 - cos theta) + 0.1 x^2 + 0.01 (xd^2 + thetad^2)`, and the window's last state
//! weighted as 16 more steps (a crude stand-in for SHAC's critic), backpropagated through the
//! window only, then one Adam step. The worlds go on from where the window left them; a world
//! whose pole passed 0.8 rad, whose cart left the rail, or that ran 10 s restarts from a new
//! random state.
//!
//! Success: from 256 new random starts, the fraction of cart-poles that stay balanced for
//! 10 s (`|theta| < 0.25` rad over the last 5 s, never past 90 degrees, the cart on the rail).
//! A second picture shows why the windows are short: the gradient's norm against the horizon
//! it is taken over.
//!
//! Run: `cargo run --release --example cartpole_policy` (pictures in
//! `target/demos/cartpole_policy/`).

use adflex::kernels::articulation::{urdf, ArticulationControl, ArticulationState, Articulations};
use adflex::prelude::*;

/// Hidden unit `tid % hidden` of world `tid / hidden`: `tanh(W1 obs + b1)`, with
/// `obs = (x, sin theta, cos theta, xd, thetad)` (each world's `q = (x, theta)`).
#[diff_kernel]
fn policy_hidden(
    q: &Array<f64>,
    qd: &Array<f64>,
    theta: &Array<f64>,
    hidden: usize,
    h: &Array<f64>,
) {
    let t = tid();
    let w = t / hidden;
    let j = t % hidden;
    let a = j * 6;
    let angle = q[2 * w + 1];
    let s = theta[a] * q[2 * w]
        + theta[a + 1] * sin(angle)
        + theta[a + 2] * cos(angle)
        + theta[a + 3] * qd[2 * w]
        + theta[a + 4] * qd[2 * w + 1]
        + theta[a + 5];
    h[t] = tanh(s);
}

/// World `tid`'s force on its cart: `u_max tanh(W2 h + b2)`; the hinge is not driven.
#[diff_kernel]
fn policy_force(h: &Array<f64>, theta: &Array<f64>, hidden: usize, u_max: f64, tau: &Array<f64>) {
    let w = tid();
    let out = hidden * 6;
    let mut s = theta[out + hidden];
    for j in 0..hidden {
        s = s + theta[out + j] * h[w * hidden + j];
    }
    tau[2 * w] = u_max * tanh(s);
    tau[2 * w + 1] = 0.0;
}

/// `loss += scale ((1 - cos theta) + 0.1 x^2 + 0.01 (xd^2 + thetad^2))` for world `tid`.
#[diff_kernel]
fn balance_cost(q: &Array<f64>, qd: &Array<f64>, scale: f64, loss: &Array<f64>) {
    let w = tid();
    let x = q[2 * w];
    let up = 1.0 - cos(q[2 * w + 1]);
    let still = qd[2 * w] * qd[2 * w] + qd[2 * w + 1] * qd[2 * w + 1];
    loss.atomic_add(0, scale * (up + 0.1 * x * x + 0.01 * still));
}

/// What the demo runs.
pub struct Config {
    /// Worlds trained together.
    pub worlds: usize,
    /// Steps per window (the horizon of each gradient).
    pub window: usize,
    /// Adam steps (one per window).
    pub iterations: usize,
    /// Hidden units.
    pub hidden: usize,
    /// Random starts the success is measured on.
    pub eval_worlds: usize,
    /// Horizons of the gradient-norm chart.
    pub horizons: Vec<usize>,
    pub seed: u64,
    /// Adam's step size.
    pub lr: f64,
}

impl Config {
    /// The size: 64 worlds, windows of 32 steps.
    pub fn full() -> Self {
        Config {
            worlds: 64,
            window: 32,
            iterations: 600,
            hidden: 32,
            eval_worlds: 256,
            horizons: vec![1, 2, 4, 8, 16, 32, 64, 128, 256, 500],
            seed: 7,
            lr: 3e-2,
        }
    }

    /// The test's size.
    pub fn small() -> Self {
        Config {
            worlds: 32,
            window: 32,
            iterations: 300,
            hidden: 32,
            eval_worlds: 64,
            horizons: vec![8, 32, 128, 500],
            seed: 7,
            lr: 3e-2,
        }
    }
}

/// Time step (s): 50 Hz, as the cart-pole benchmarks.
pub const DT: f64 = 0.02;
/// Steps in 10 s.
pub const EPISODE: usize = 500;
/// Weight of a window's last state, in steps.
pub const TERMINAL: f64 = 16.0;
/// A world restarts once its pole is this far from upright (rad).
pub const FALLEN: f64 = 0.8;
/// Largest force on the cart (N).
pub const U_MAX: f64 = 10.0;

/// What it learned.
pub struct Outcome {
    /// The window losses, one per Adam step.
    pub losses: Vec<f64>,
    /// Fraction of the evaluation's random starts balanced for 10 s, before and after.
    pub success_before: f64,
    pub success: f64,
    /// `(horizon, gradient norm)` at the initial and at the trained policy.
    pub grad_norms_initial: Vec<(usize, f64)>,
    pub grad_norms_trained: Vec<(usize, f64)>,
    /// One evaluation world's pole angle over 10 s (trained policy).
    pub angle: Vec<f64>,
}

/// A small deterministic generator (xorshift), uniform in `[lo, hi)`.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        lo + (hi - lo) * ((self.0 >> 11) as f64 / (1u64 << 53) as f64)
    }
}

/// `worlds` cart-poles in one model. The rail's ends (the slider's limits, +-4 m) are softened
/// to 1e3 N/m: the default 1e4 N/m on the 1.1 kg cart is past semi-implicit Euler's stability
/// limit at 1/50 s (`omega dt = 2`).
pub fn cartpoles(worlds: usize) -> Articulations<f64> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/kernels/robots/cartpole.urdf");
    let mut b = urdf::load(path, &urdf::UrdfOptions::default())
        .expect("the repository's cartpole loads")
        .replicate(worlds);
    b.limit_ke = 1e3;
    b.finalize().expect("the repository's cartpole builds")
}

/// A random start around upright: `x, theta` within 0.5 m and 0.4 rad, velocities within 0.5.
fn random_start(rng: &mut Rng) -> [f64; 4] {
    [
        rng.uniform(-0.5, 0.5),
        rng.uniform(-0.4, 0.4),
        rng.uniform(-0.5, 0.5),
        rng.uniform(-0.5, 0.5),
    ]
}

/// A state of the model from per-world starts `[x, theta, xd, thetad]`.
fn state_from(starts: &[[f64; 4]]) -> ArticulationState<f64> {
    ArticulationState {
        q: Array::from_vec(starts.iter().flat_map(|s| [s[0], s[1]]).collect()),
        qd: Array::from_vec(starts.iter().flat_map(|s| [s[2], s[3]]).collect()),
    }
}

/// One policy-driven step of every world, on the tape.
fn policy_step(
    model: &Articulations<f64>,
    tape: &mut Tape,
    s: &ArticulationState<f64>,
    theta: &Array<f64>,
    hidden: usize,
) -> Result<ArticulationState<f64>, Error> {
    let w = model.n_worlds();
    let h = Array::zeros(w * hidden);
    tape.launch(policy_hidden, w * hidden, (&s.q, &s.qd, theta, hidden, &h));
    let control = ArticulationControl {
        tau: Array::zeros(model.n_dof),
        ..model.control()
    };
    tape.launch(policy_force, w, (&h, theta, hidden, U_MAX, &control.tau));
    model.step(tape, s, Some(&control), DT)
}

/// The mean cost over worlds and `steps` steps from `start`, recorded on `tape`; the final
/// state.
fn window(
    model: &Articulations<f64>,
    tape: &mut Tape,
    start: &ArticulationState<f64>,
    theta: &Array<f64>,
    hidden: usize,
    steps: usize,
) -> Result<(Array<f64>, ArticulationState<f64>), Error> {
    let loss = Array::zeros(1);
    let scale = 1.0 / (model.n_worlds() * steps) as f64;
    let mut s = start.clone();
    for _ in 0..steps {
        s = policy_step(model, tape, &s, theta, hidden)?;
        tape.launch(balance_cost, model.n_worlds(), (&s.q, &s.qd, scale, &loss));
    }
    // The window's end counts as TERMINAL more steps: a crude stand-in for SHAC's critic, so
    // that a window does not end by letting the pole go.
    let end = TERMINAL * scale;
    tape.launch(balance_cost, model.n_worlds(), (&s.q, &s.qd, end, &loss));
    Ok((loss, s))
}

/// Fraction of `n` random starts the policy keeps balanced for 10 s; one world's angle.
fn evaluate(
    theta: &Array<f64>,
    hidden: usize,
    n: usize,
    rng: &mut Rng,
) -> Result<(f64, Vec<f64>), Error> {
    let model = cartpoles(n);
    let starts: Vec<[f64; 4]> = (0..n).map(|_| random_start(rng)).collect();
    let mut s = state_from(&starts);
    let mut ok = vec![true; n];
    let mut angle = Vec::with_capacity(EPISODE);
    for k in 0..EPISODE {
        // No gradients here: a fresh tape per step keeps nothing alive.
        s = policy_step(&model, &mut Tape::new(), &s, theta, hidden)?;
        let (q, _) = (s.q.to_vec(), s.qd.to_vec());
        angle.push(q[1]);
        for w in 0..n {
            let (x, th) = (q[2 * w], q[2 * w + 1]);
            let fell = th.abs() > std::f64::consts::FRAC_PI_2 || x.abs() > 4.0;
            if fell || (k >= EPISODE / 2 && th.abs() >= 0.25) {
                ok[w] = false;
            }
        }
    }
    Ok((ok.iter().filter(|b| **b).count() as f64 / n as f64, angle))
}

/// The gradient's norm, with respect to every weight, of the mean cost over `horizon` steps
/// from the same random starts.
fn grad_norm(
    model: &Articulations<f64>,
    theta: &Array<f64>,
    hidden: usize,
    starts: &ArticulationState<f64>,
    horizon: usize,
) -> Result<f64, Error> {
    theta.zero_grad();
    let mut tape = Tape::new();
    let (loss, _) = window(model, &mut tape, starts, theta, hidden, horizon)?;
    tape.backward(&loss)?;
    let g = theta.grad()?.to_vec();
    theta.zero_grad();
    Ok(g.iter().map(|x| x * x).sum::<f64>().sqrt())
}

/// The loss of one window of `steps` steps of `worlds` worlds from random starts (`seed`),
/// with the weights `values` (`hidden` units), and its gradient (for checking it).
pub fn window_loss_and_grad(
    values: &[f64],
    worlds: usize,
    hidden: usize,
    steps: usize,
    seed: u64,
) -> Result<(f64, Vec<f64>), Error> {
    let mut rng = Rng(seed | 1);
    let model = cartpoles(worlds);
    let starts: Vec<[f64; 4]> = (0..worlds).map(|_| random_start(&mut rng)).collect();
    let theta = Array::from_vec(values.to_vec()).requires_grad();
    let mut tape = Tape::new();
    let (loss, _) = window(
        &model,
        &mut tape,
        &state_from(&starts),
        &theta,
        hidden,
        steps,
    )?;
    tape.backward(&loss)?;
    Ok((loss.get(0), theta.grad()?.to_vec()))
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let mut rng = Rng(cfg.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let hidden = cfg.hidden;
    let n_theta = hidden * 6 + hidden + 1;
    // Small random weights (Glorot-like for the first layer, smaller for the output).
    let init: Vec<f64> = (0..n_theta)
        .map(|k| {
            if k < hidden * 6 {
                rng.uniform(-0.5, 0.5)
            } else {
                rng.uniform(-0.1, 0.1)
            }
        })
        .collect();
    let theta = Array::from_vec(init).requires_grad();
    let model = cartpoles(cfg.worlds);
    let chart_starts: Vec<[f64; 4]> = (0..cfg.worlds).map(|_| random_start(&mut rng)).collect();
    let chart_starts = state_from(&chart_starts);
    let norms = |theta: &Array<f64>| -> Result<Vec<(usize, f64)>, Error> {
        cfg.horizons
            .iter()
            .map(|&h| Ok((h, grad_norm(&model, theta, hidden, &chart_starts, h)?)))
            .collect()
    };
    let grad_norms_initial = norms(&theta)?;
    let (success_before, _) = evaluate(&theta, hidden, cfg.eval_worlds, &mut Rng(99))?;

    // Training: windows of `cfg.window` steps, one Adam step each.
    let (lr, beta1, beta2, eps, clip) = (cfg.lr, 0.9, 0.999, 1e-8, 1.0);
    let (mut m, mut v) = (vec![0.0; n_theta], vec![0.0; n_theta]);
    let starts: Vec<[f64; 4]> = (0..cfg.worlds).map(|_| random_start(&mut rng)).collect();
    let mut state = state_from(&starts);
    let mut age = vec![0usize; cfg.worlds];
    let mut losses = Vec::with_capacity(cfg.iterations);
    for it in 0..cfg.iterations {
        theta.zero_grad();
        let mut tape = Tape::new();
        // The window starts from the last one's values: gradients stop at its start.
        let start = ArticulationState {
            q: Array::from_vec(state.q.to_vec()),
            qd: Array::from_vec(state.qd.to_vec()),
        };
        let (loss, end) = window(&model, &mut tape, &start, &theta, hidden, cfg.window)?;
        tape.backward(&loss)?;
        losses.push(loss.get(0));
        let mut g = theta.grad()?.to_vec();
        let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm > clip {
            g.iter_mut().for_each(|x| *x *= clip / norm);
        }
        let mut values = theta.to_vec();
        let t = (it + 1) as i32;
        for k in 0..n_theta {
            m[k] = beta1 * m[k] + (1.0 - beta1) * g[k];
            v[k] = beta2 * v[k] + (1.0 - beta2) * g[k] * g[k];
            let (mh, vh) = (m[k] / (1.0 - beta1.powi(t)), v[k] / (1.0 - beta2.powi(t)));
            values[k] -= lr * mh / (vh.sqrt() + eps);
        }
        theta.assign(&values);
        // Worlds that fell, left the rail or ran a whole episode restart at random.
        let q = end.q.to_vec();
        let mut restart = Vec::new();
        for (w, a) in age.iter_mut().enumerate() {
            *a += cfg.window;
            let (x, th) = (q[2 * w], q[2 * w + 1]);
            if th.abs() > FALLEN || x.abs() > 4.0 || *a >= EPISODE {
                restart.push(w);
                *a = 0;
            }
        }
        state = if restart.is_empty() {
            end
        } else {
            let fresh: Vec<[f64; 4]> = (0..cfg.worlds).map(|_| random_start(&mut rng)).collect();
            model.select_worlds(&mut Tape::new(), &end, &restart, &state_from(&fresh))?
        };
    }
    let grad_norms_trained = norms(&theta)?;
    let (success, angle) = evaluate(&theta, hidden, cfg.eval_worlds, &mut Rng(99))?;
    Ok(Outcome {
        losses,
        success_before,
        success,
        grad_norms_initial,
        grad_norms_trained,
        angle,
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let args: Vec<String> = std::env::args().collect();
    let mut cfg = if args.iter().any(|a| a == "--small") {
        Config::small()
    } else {
        Config::full()
    };
    let value = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|k| args.get(k + 1))
            .map(|v| v.parse::<f64>().expect("a number"))
    };
    if let Some(v) = value("--lr") {
        cfg.lr = v;
    }
    if let Some(v) = value("--iterations") {
        cfg.iterations = v as usize;
    }
    if let Some(v) = value("--window") {
        cfg.window = v as usize;
    }
    if let Some(v) = value("--worlds") {
        cfg.worlds = v as usize;
    }
    let out = run(&cfg)?;
    println!(
        "{} worlds, {} windows of {} steps: window loss {:.3e} -> {:.3e}; balanced for 10 s \
         from {} random starts: {:.1}% before training, {:.1}% after ({:.1} s)",
        cfg.worlds,
        cfg.iterations,
        cfg.window,
        out.losses[0],
        out.losses.last().copied().unwrap_or(f64::NAN),
        cfg.eval_worlds,
        100.0 * out.success_before,
        100.0 * out.success,
        start.elapsed().as_secs_f64()
    );
    println!("gradient norm against horizon (steps: initial policy, trained policy):");
    for ((h, a), (_, b)) in out.grad_norms_initial.iter().zip(&out.grad_norms_trained) {
        println!("  {h:>4}: {a:.3e}  {b:.3e}");
    }
    let dir = std::path::Path::new("target/demos/cartpole_policy");
    std::fs::create_dir_all(dir)?;
    let pts = |v: &[(usize, f64)]| -> Vec<(f64, f64)> {
        v.iter().map(|&(h, g)| (h as f64 * DT, g)).collect()
    };
    let (a, b) = (pts(&out.grad_norms_initial), pts(&out.grad_norms_trained));
    let title = format!(
        "cart-pole policy: gradient norm against horizon (training windows: {:.2} s)",
        cfg.window as f64 * DT
    );
    for file in ["grad_norm.svg", "grad_norm.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            &title,
            "horizon (s)",
            "gradient norm",
            &[("initial policy", &a[..]), ("trained policy", &b[..])],
        )?;
    }
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.losses,
            "cart-pole policy: window loss per Adam step (64 worlds)",
        )?;
    }
    let angle: Vec<(f64, f64)> = out
        .angle
        .iter()
        .enumerate()
        .map(|(k, &a)| ((k + 1) as f64 * DT, a))
        .collect();
    for file in ["angle.svg", "angle.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "cart-pole policy: a new random start, 10 s",
            "time (s)",
            "pole angle (rad, 0 = up)",
            &[("pole angle", &angle[..])],
        )?;
    }
    println!(
        "pictures: {}/{{grad_norm, loss, angle}}.{{svg, png}}",
        dir.display()
    );
    Ok(())
}
