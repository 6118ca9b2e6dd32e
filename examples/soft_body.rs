//! A soft crawler: a block of stable Neo-Hookean tetrahedra (a [`TetGrid`]) lying on the
//! ground with friction learns an open-loop gait. Every tetrahedron's activation (its rest
//! volume, `a > 0` contracts) is a sinusoid of a fixed frequency whose two amplitudes (sine and
//! cosine, so amplitude and phase) are shared by the tetrahedra of one group, a column of
//! cells along the body (x) and one layer (y): `2 x dims[0] x dims[1]` parameters, bounded to
//! `[-bound, bound]`. A small `#[diff_kernel]` ([`gait`]) turns them and the step index into
//! `Control::tet_activation` at every step.
//!
//! Adam minimizes the squared distance of the centre of mass after `duration` seconds to a goal
//! `goal_distance` in front of it (+x), plus a small regularizer on the amplitudes. The body
//! crawls: the optimizer finds a pattern of contractions that, with friction, moves it forward
//! while it keeps touching the ground (a crawl, not a jump: `main` prints how high the centre
//! of mass rises and how often the body is in flight, 0.26 cm and never at full size).
//!
//! Full size (6 x 2 x 2 cells of 5 cm, 144 tetrahedra, 24 amplitudes, 2 s at dt = 0.5 ms, 100
//! Adam iterations, about 20 s in release on 2 cores): the centre of mass moves +24.3 cm toward
//! the goal 30 cm ahead, against 0.00 cm with the initial small gait and lying still.
//!
//! Run: `cargo run --release --example soft_body` (pictures in `target/demos/soft_body/`).

use adflex::kernels::losses;
use adflex::optim::{Bounds, Optimizer, Params, Report};
use adflex::prelude::*;

/// The builder's default contact radius of a particle (m).
pub const PARTICLE_RADIUS: f64 = 0.01;

/// What the demo runs.
#[derive(Clone, Debug)]
pub struct Config {
    /// Cells along x, y, z (5 cm each).
    pub dims: [usize; 3],
    /// Young's modulus (Pa).
    pub young: f64,
    /// Simulated time (s) and step (s).
    pub duration: f64,
    pub dt: f64,
    /// Gait frequency (Hz).
    pub frequency: f64,
    /// The goal is this far in front (+x) of the initial centre of mass (m).
    pub goal_distance: f64,
    /// Amplitudes are kept in `[-bound, bound]`.
    pub bound: f64,
    /// Weight of the regularizer `sum amp^2` (m^2).
    pub regularizer: f64,
    /// Adam's learning rate and iterations.
    pub learning_rate: f64,
    pub iterations: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            dims: [6, 2, 2],
            young: 3e4,
            duration: 2.0,
            dt: 5e-4,
            frequency: 4.0,
            goal_distance: 0.3,
            bound: 0.3,
            regularizer: 1e-4,
            learning_rate: 0.03,
            iterations: 100,
            progress: true,
        }
    }
    /// The test's size: a 4 x 2 x 1 block (two layers, so it can bend) for a second.
    pub fn small() -> Self {
        Config {
            dims: [4, 2, 1],
            duration: 1.0,
            iterations: 25,
            progress: false,
            ..Self::full()
        }
    }
}

/// The scene: the block on the ground, the group of each tetrahedron.
pub struct Scene {
    pub model: Model<f64>,
    pub block: TetBlock,
    /// Group (`column x dims[1] + layer`) of each tetrahedron.
    pub group: Array<u32>,
    pub groups: usize,
    pub weights: Array<f64>,
}

pub fn scene(cfg: &Config) -> Scene {
    let mut b = ModelBuilder::<f64>::new();
    b.particle_radius = PARTICLE_RADIUS;
    let (mu, lambda) = adflex::kernels::forces::fem_tet::snh_lame(cfg.young, 0.3);
    let block = b.add_tet_grid(&TetGrid {
        dims: cfg.dims,
        // Resting on the ground: contact starts at a particle's radius.
        origin: Vec3::new(0.0, PARTICLE_RADIUS, 0.0),
        mu,
        lambda,
        ..TetGrid::default()
    });
    for t in block.surface_triangles() {
        b.add_triangle(t[0], t[1], t[2]);
    }
    b.set_ground(Ground {
        ke: 2e3,
        kd: 5.0,
        mu: 0.8,
        ..Ground::default()
    });
    let model = b.finalize();
    let [_, ny, nz] = cfg.dims;
    // Tetrahedra: six per cell, cells (i, j, k) row-major.
    let group: Vec<u32> = (0..block.tets.len())
        .map(|t| ((t / 6) / nz) as u32)
        .collect();
    let weights = losses::mass_weights(&model);
    Scene {
        model,
        block,
        group: Array::from_vec(group).named("group"),
        groups: cfg.dims[0] * ny,
        weights,
    }
}

/// The activation of tetrahedron `tid` at step `step`: the sinusoid of its group,
/// `amp[2g] sin(w t) + amp[2g+1] cos(w t)`, ramped in over the first 0.1 s.
#[diff_kernel]
pub fn gait(
    amp: &Array<f64>,
    group: &Array<u32>,
    step: usize,
    dt: f64,
    omega: f64,
    act: &Array<f64>,
) {
    let t = tid();
    let g = group[t] as usize;
    let time = dt * (step as f64);
    let ramp = min(time / 0.1, 1.0);
    act[t] = ramp * (amp[2 * g] * sin(omega * time) + amp[2 * g + 1] * cos(omega * time));
}

/// Simulates the gait `amp` on `tape`; returns the final state, and every state in `frames`
/// if given.
pub fn simulate(
    tape: &mut Tape,
    scene: &Scene,
    amp: &Array<f64>,
    cfg: &Config,
    mut frames: Option<&mut Vec<State<f64>>>,
) -> Result<State<f64>, Error> {
    let model = &scene.model;
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let omega = std::f64::consts::TAU * cfg.frequency;
    let n = scene.group.len();
    let mut s = model.state();
    if let Some(f) = frames.as_deref_mut() {
        f.push(s.clone());
    }
    for step in 0..steps {
        let act = Array::zeros(n).named("activation");
        tape.launch(gait, n, (amp, &scene.group, step, cfg.dt, omega, &act));
        let control = Control {
            tet_activation: Some(act),
            ..Control::default()
        };
        s = SemiImplicitEuler.step(model, tape, &s, Some(&control), cfg.dt)?;
        if let Some(f) = frames.as_deref_mut() {
            f.push(s.clone());
        }
    }
    Ok(s)
}

/// The demo's loss: `|com(T) - goal|^2 + regularizer sum amp^2`.
pub fn loss(
    tape: &mut Tape,
    scene: &Scene,
    amp: &Array<f64>,
    cfg: &Config,
) -> Result<Array<f64>, Error> {
    let end = simulate(tape, scene, amp, cfg, None)?;
    let loss = Array::zeros(1).named("loss");
    losses::center_of_mass_to_target(tape, &end.x, &scene.weights, goal(scene, cfg), 1.0, &loss);
    losses::sum_of_squares(tape, amp, cfg.regularizer, &loss);
    Ok(loss)
}

/// Centre of mass of a state (host).
pub fn com(scene: &Scene, s: &State<f64>) -> Vec3<f64> {
    let w = scene.weights.to_vec();
    s.x.to_vec()
        .iter()
        .zip(&w)
        .fold(Vec3::zeros(), |c, (x, w)| c + x * *w)
}

pub fn goal(scene: &Scene, cfg: &Config) -> Vec3<f64> {
    com(scene, &scene.model.state()) + Vec3::new(cfg.goal_distance, 0.0, 0.0)
}

/// The starting gait: small amplitudes (a fixed pattern, to break the symmetry).
pub fn initial_amplitudes(groups: usize) -> Vec<f64> {
    (0..2 * groups)
        .map(|k| 0.02 * (2.399 * k as f64 + 0.5).sin())
        .collect()
}

/// How far the centre of mass moves toward the goal (+x) with gait `amp` (m); the frames.
pub fn displacement(
    scene: &Scene,
    amp: &Array<f64>,
    cfg: &Config,
) -> Result<(f64, Vec<State<f64>>), Error> {
    let mut frames = Vec::new();
    let mut tape = Tape::new();
    let end = simulate(&mut tape, scene, amp, cfg, Some(&mut frames))?;
    let d = com(scene, &end).x - com(scene, &scene.model.state()).x;
    Ok((d, frames))
}

/// What it found.
pub struct Outcome {
    pub report: Report,
    pub scene: Scene,
    /// The optimized amplitudes.
    pub amplitudes: Vec<f64>,
    /// Centre-of-mass displacement toward the goal (m): passive (no activation), with the
    /// initial gait, with the optimized one.
    pub passive: f64,
    pub before: f64,
    pub after: f64,
    /// Highest rise of the centre of mass above its start during the optimized crawl (m): a
    /// crawl stays low, a hop would not.
    pub max_lift: f64,
    /// Fraction of the optimized crawl's states with no particle touching the ground (in
    /// flight).
    pub airborne: f64,
    /// The optimized crawl.
    pub frames: Vec<State<f64>>,
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let scene = scene(cfg);
    let zeros = Array::zeros(2 * scene.groups);
    let (passive, _) = displacement(&scene, &zeros, cfg)?;
    let amp = Array::from_vec(initial_amplitudes(scene.groups)).named("amplitudes");
    let (before, _) = displacement(&scene, &amp, cfg)?;
    let report = Optimizer::adam(cfg.learning_rate)
        .max_iters(cfg.iterations)
        .progress(cfg.progress)
        .minimize(
            &Params::new().bounded(&amp, Bounds::between(-cfg.bound, cfg.bound)),
            |tape| loss(tape, &scene, &amp, cfg),
        )?;
    let (after, frames) = displacement(&scene, &amp, cfg)?;
    let y0 = com(&scene, &frames[0]).y;
    let max_lift = frames
        .iter()
        .map(|s| com(&scene, s).y - y0)
        .fold(f64::NEG_INFINITY, f64::max);
    let airborne = frames
        .iter()
        .filter(|s| s.x.to_vec().iter().all(|p| p.y > PARTICLE_RADIUS))
        .count() as f64
        / frames.len() as f64;
    Ok(Outcome {
        report,
        amplitudes: amp.to_vec(),
        scene,
        passive,
        before,
        after,
        max_lift,
        airborne,
        frames,
    })
}

#[allow(dead_code)]
fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = Config::full();
    let out = run(&cfg)?;
    println!("{}", out.report);
    println!(
        "{} tetrahedra, {} particles, {} amplitudes; {} s at dt = {} s",
        out.scene.block.tets.len(),
        out.scene.block.particles.len(),
        out.amplitudes.len(),
        cfg.duration,
        cfg.dt
    );
    println!(
        "centre of mass toward the goal ({:.2} m ahead) after {} s: passive {:+.2} cm, initial gait {:+.2} cm, optimized {:+.2} cm ({} Adam iterations, {:.1} s)",
        cfg.goal_distance,
        cfg.duration,
        100.0 * out.passive,
        100.0 * out.before,
        100.0 * out.after,
        out.report.iterations,
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/soft_body");
    std::fs::create_dir_all(dir)?;
    adflex::viz::plot::loss_curve(
        dir.join("loss.svg"),
        &out.report.losses(),
        "soft body: Adam on a crawling gait",
    )?;
    // Coloured by actuation as in DiffTaichi's picture (red = extension, blue = contraction:
    // a particle gets minus the mean activation of its tetrahedra), the goal marked, the
    // starting pose as a ghost, the time and the result in the caption.
    use adflex::viz::overlay::{ColorBy, Colormap, Ghost, Marker, Overlay, Values};
    let model = &out.scene.model;
    let every = ((1.0 / 25.0) / cfg.dt).round().max(1.0) as usize;
    let tets = model.tets().expect("the block's tetrahedra").tets.to_vec();
    let group = out.scene.group.to_vec();
    let omega = std::f64::consts::TAU * cfg.frequency;
    let actuation = |step: usize| {
        let time = cfg.dt * step as f64;
        let ramp = (time / 0.1).min(1.0);
        let (mut sum, mut count) = (
            vec![0.0; model.particle_count],
            vec![0.0; model.particle_count],
        );
        for (t, tet) in tets.iter().enumerate() {
            let g = group[t] as usize;
            let (a, b) = (out.amplitudes[2 * g], out.amplitudes[2 * g + 1]);
            let act = ramp * (a * (omega * time).sin() + b * (omega * time).cos());
            for &i in tet {
                sum[i as usize] -= act;
                count[i as usize] += 1.0;
            }
        }
        sum.iter()
            .zip(&count)
            .map(|(s, c)| if *c > 0.0 { s / c } else { 0.0 })
            .collect()
    };
    let overlay = Overlay {
        markers: vec![Marker::target(
            goal(&out.scene, &cfg),
            "goal (centre of mass)",
        )],
        ghosts: vec![Ghost::of(&model.state(), "start")],
        color_by: Some(ColorBy::new(
            Values::Particles((0..out.frames.len()).map(actuation).collect()),
            (-cfg.bound, cfg.bound),
            Colormap::Diverging,
            "actuation",
        )),
        captions: (0..out.frames.len())
            .map(|k| {
                format!(
                    "t = {:.2} s | Adam: {} it., {:+.1} cm",
                    k as f64 * cfg.dt,
                    out.report.iterations,
                    100.0 * out.after
                )
            })
            .collect(),
        ..Overlay::default()
    };
    let options = adflex::viz::render::RenderOptions {
        width: 720,
        height: 480,
        draw_points: false,
        ..Default::default()
    };
    adflex::viz::render::render_gif_with(
        dir.join("soft_body.gif"),
        model,
        &out.frames,
        &options,
        &overlay,
        25.0,
        every,
    )?;
    adflex::viz::render::render_png_with(
        dir.join("soft_body.png"),
        model,
        &out.frames,
        out.frames.len() - 1,
        &options,
        &overlay,
    )?;
    println!(
        "the centre of mass rises at most {:.2} cm above its start; in flight {:.0}% of the time",
        100.0 * out.max_lift,
        100.0 * out.airborne
    );
    println!(
        "pictures: {}/{{loss.svg, soft_body.gif, soft_body.png}}",
        dir.display()
    );
    Ok(())
}
