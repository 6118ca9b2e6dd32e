//! A 7-DoF arm throws a ball to a target.
//!
//! The arm of `kernels/robots/arm7.urdf` holds a ball in a cup on its last link (a floor, a
//! back wall and two side walls: boxes touching the ball, a sphere on a free joint, with the
//! library's contact law). Its joints' PD servos hold a bent pose; the throw is a torque
//! sequence added on the base yaw and the shoulder, elbow and wrist pitch joints (piecewise
//! linear in time, `knots` values per joint over the swing). The ball rides in the cup while
//! the arm swings and leaves it, through the open front, when the cup slows down: the release
//! is contact ending, not a command. L-BFGS finds the torques that put the ball on a target
//! point at the end of the rollout, through every contact step of the cup and the release,
//! from a first guess that throws 55 cm wide of it. The cup's contact law has an onset (the
//! force rises from 0 with zero slope over 2 mm): without it the loss is rough at the scale of
//! a time step and the search stalls centimetres away, depending on the first guess's last
//! digits.
//!
//! Run: `cargo run --release --example arm_throw` (pictures in `target/demos/arm_throw/`).

use adflex::kernels::articulation::{
    urdf, ArticulationControl, ArticulationState, Articulations, ContactFilter, GroundContact,
    Inertial, Joint, Pose,
};
use adflex::optim::{Optimizer, Params, Report};
use adflex::prelude::*;

/// `tau[d] = base[d]` plus, for the `n` swing joints, their torques interpolated between knots
/// `k` and `k + 1` of `knots` (`knots[n k + j]` for swing joint `j`, in units of 20 N m, so
/// that the parameters are of order 1) with weight `w`.
#[diff_kernel]
fn swing_torque(
    knots: &Array<f64>,
    joints: &Array<u32>,
    base: &Array<f64>,
    n: usize,
    k: usize,
    w: f64,
    tau: &Array<f64>,
) {
    let d = tid();
    let mut t = base[d];
    for j in 0..n {
        if joints[j] as usize == d {
            t += 20.0 * ((1.0 - w) * knots[n * k + j] + w * knots[n * (k + 1) + j]);
        }
    }
    tau[d] = t;
}

/// `loss = |x - target|^2` for the ball's position (coordinates `start..start + 3` of `q`).
#[diff_kernel]
fn miss(q: &Array<f64>, start: usize, target: Vec3<f64>, loss: &Array<f64>) {
    let x = vec3(q[start], q[start + 1], q[start + 2]);
    let d = x - target;
    loss[0] = dot(d, d);
}

/// What the demo runs.
pub struct Config {
    /// Time step (s).
    pub dt: f64,
    /// The ball settles in the cup for `settle` s, the arm swings for `swing` s, then the
    /// ball flies until `duration`.
    pub settle: f64,
    pub swing: f64,
    pub duration: f64,
    /// Torque knots of each swing joint.
    pub knots: usize,
    /// The first guess's knots are multiplied by `1 + perturb` (0: the demo's).
    pub perturb: f64,
    pub max_iters: usize,
    pub progress: bool,
}

impl Config {
    pub fn full() -> Self {
        Config {
            dt: 1e-3,
            settle: 0.1,
            swing: 0.3,
            duration: 0.8,
            knots: 6,
            perturb: 0.0,
            max_iters: 150,
            progress: true,
        }
    }

    pub fn small() -> Self {
        Config {
            dt: 2e-3,
            max_iters: 40,
            progress: false,
            ..Config::full()
        }
    }
}

/// The scene: the arm with its cup, and the ball.
pub struct Scene {
    pub model: Articulations<f64>,
    /// The arm's velocities that swing (base yaw; shoulder, elbow and wrist pitch).
    pub joints: [u32; 4],
    /// Where the ball's coordinates start in `q`.
    pub ball: usize,
    /// Where the ball sits in the cup at the start (world).
    pub ball_start: Vec3<f64>,
    /// The servos' feedforward: gravity compensation of the holding pose.
    pub hold: Array<f64>,
    /// The cup: its link and its floor's centre in the link frame.
    pub cup: (usize, Vec3<f64>),
}

/// The arm's pose while it holds the ball (rad): leaning back, elbow and wrist bent.
const HOLD: [f64; 7] = [0.0, -0.5, 0.0, 1.2, 0.0, 0.6, 0.0];
const BALL_RADIUS: f64 = 0.035;

pub fn scene() -> Scene {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/kernels/robots/arm7.urdf");
    let mut b = urdf::load(path, &urdf::UrdfOptions::default()).expect("the arm loads");
    for (k, l) in b.links_mut().iter_mut().skip(1).enumerate() {
        l.joint.initial = vec![HOLD[k]];
    }
    let arm: Articulations<f64> = b.clone().finalize().expect("the arm");
    let q = Array::from_vec(arm.q0.clone());
    // Servos critically damped at 20 rad/s on each joint's own inertia (`M_kk`): stiff enough
    // to hold the pose, and stable in the explicit damping term (`kv dt / M_kk = 0.04`).
    let m = arm.block(&arm.mass_matrix(&mut Tape::new(), &q), 0);
    let w = 4.0;
    for (k, l) in b.links_mut().iter_mut().skip(1).enumerate() {
        l.joint.kp = w * w * m[k][k];
        l.joint.kv = 2.0 * w * m[k][k];
    }
    // The last link's pose in the holding pose, to set the cup upright in the world.
    let kin = arm.kinematics(&mut Tape::new(), &q);
    let last = arm.n_links() - 1;
    let (p, r) = (kin.link_p.get(last), kin.link_r.get(last));
    let tip = p + rotate(&r, &Vec3::new(0.0, 0.0, 0.12));
    // The cup's frame in the link's frame: at the tip, axes along the world's.
    let cup = Pose::new(Vec3::new(0.0, 0.0, 0.12), r.conjugate());
    let link = b.find("link7").expect("the arm's last link");
    let place = |offset: Vec3<f64>| cup.compose(&Pose::at(offset));
    b.add_contact_box(link, &place(Vec3::zeros()), Vec3::new(0.07, 0.06, 0.01));
    b.add_contact_box(
        link,
        &place(Vec3::new(-0.08, 0.0, 0.04)),
        Vec3::new(0.01, 0.06, 0.05),
    );
    for y in [-0.07, 0.07] {
        b.add_contact_box(
            link,
            &place(Vec3::new(0.0, y, 0.04)),
            Vec3::new(0.07, 0.01, 0.05),
        );
    }
    // The ball, on a free joint, resting on the cup's floor.
    let ball_start = tip + Vec3::new(0.0, 0.0, 0.01 + BALL_RADIUS + 1e-3);
    let ball = b.add_link(
        "ball",
        None,
        Joint::free().initial(&[ball_start.x, ball_start.y, ball_start.z, 0.0, 0.0, 0.0, 1.0]),
        Inertial::sphere(0.1, BALL_RADIUS, Vec3::zeros()),
    );
    b.add_contact_sphere(ball, Vec3::zeros(), BALL_RADIUS);
    // The cup's law; no floor (the ball is caught in the air). The ball's release is a
    // contact ending, and its rolling over the cup's floor many contacts beginning and ending:
    // with the plain law each is a kink of the throw's result per time step, and the loss is
    // rough at the scale of a step (its gradient led L-BFGS astray: misses of 3.5 to 36 cm after
    // 40 iterations, depending on the first guess's last digits). The force's onset over 2 mm
    // smooths those kinks; a slick cup (`mu` 0.1) keeps the smoothed friction's slope at rest,
    // `mu |f| / (0.01 m/s)`, within what the time step integrates, and the little damping
    // keeps its kink (where a contact stops closing) small. So the search converges from
    // every first guess tried (`docs/performance.md`).
    b.ground = Some(GroundContact {
        ke: 2e3,
        kd: 1.0,
        mu: 0.1,
        onset: 2e-3,
        ..GroundContact::default()
    });
    b.ground_filter = ContactFilter::NONE;
    b.link_contact = true;
    let model: Articulations<f64> = b.finalize().expect("the arm and the ball");
    // Gravity compensation of the holding pose, added to the servos.
    let tape = &mut Tape::new();
    let gravity = model
        .bias_forces(
            tape,
            &Array::from_vec(model.q0.clone()),
            &Array::zeros(model.n_dof),
        )
        .to_vec();
    let mut hold = vec![0.0; model.n_dof];
    hold[..7].copy_from_slice(&gravity[..7]);
    Scene {
        ball: model.n_q - 7,
        joints: [0, 1, 3, 5],
        ball_start,
        hold: Array::from_vec(hold),
        cup: (last, Vec3::new(0.0, 0.0, 0.12)),
        model,
    }
}

fn rotate(q: &Quat<f64>, v: &Vec3<f64>) -> Vec3<f64> {
    (q * Quat::from_imag(*v) * q.conjugate()).imag()
}

/// Rolls the throw out for `knots` on `tape`; returns the states.
pub fn throw(
    s: &Scene,
    cfg: &Config,
    knots: &Array<f64>,
    tape: &mut Tape,
) -> Result<Vec<ArticulationState<f64>>, Error> {
    let m = &s.model;
    let steps = (cfg.duration / cfg.dt).round() as usize;
    let joints = Array::from_vec(s.joints.to_vec());
    let mut target_q = vec![0.0; m.n_dof];
    target_q[..7].copy_from_slice(&HOLD);
    let hold = ArticulationControl {
        tau: s.hold.clone(),
        target_q: Array::from_vec(target_q),
        ..m.control()
    };
    let mut state = m.state();
    let mut states = vec![state.clone()];
    for k in 0..steps {
        let t = k as f64 * cfg.dt - cfg.settle;
        let control = if t >= 0.0 && t < cfg.swing {
            // Knot `i` at `i swing / (knots - 1)`.
            let u = t / cfg.swing * (cfg.knots - 1) as f64;
            let i = (u.floor() as usize).min(cfg.knots - 2);
            let tau = Array::zeros(m.n_dof);
            tape.launch(
                swing_torque,
                m.n_dof,
                (
                    knots,
                    &joints,
                    &s.hold,
                    s.joints.len(),
                    i,
                    u - i as f64,
                    &tau,
                ),
            );
            ArticulationControl {
                tau,
                ..hold.clone()
            }
        } else {
            hold.clone()
        };
        state = m.step(tape, &state, Some(&control), cfg.dt)?;
        states.push(state.clone());
    }
    Ok(states)
}

/// The first guess, a throw that misses: the shoulder pushes forward and the elbow opens for
/// the first half of the swing, both brake in the second; base yaw and wrist idle.
fn first_guess(knots: usize) -> Vec<f64> {
    (0..knots)
        .flat_map(|k| {
            let s = if 2 * k < knots { 1.0 } else { -1.0 };
            [0.0, s, -s, 0.0]
        })
        .collect()
}

/// Points `(x, z)` of the ball's path.
pub type Path = Vec<(f64, f64)>;

/// What it found.
pub struct Outcome {
    pub report: Report,
    /// The target, from where the ball starts.
    pub target: Vec3<f64>,
    /// Distance from the target at the end (m): first guess, found.
    pub miss: (f64, f64),
    /// The ball's path (x, z from where it starts) for the first guess and the throw found.
    pub paths: (Path, Path),
    /// When the ball last touched the cup (s).
    pub release: f64,
}

fn ball_at(s: &Scene, st: &ArticulationState<f64>) -> Vec3<f64> {
    Vec3::new(st.q.get(s.ball), st.q.get(s.ball + 1), st.q.get(s.ball + 2))
}

pub fn run(cfg: &Config) -> Result<Outcome, Error> {
    let s = scene();
    // The target: 1 m in front of where the ball starts and 0.3 m below, at the end.
    let target = s.ball_start + Vec3::new(1.0, 0.0, -0.3);
    let guess: Vec<f64> = first_guess(cfg.knots)
        .into_iter()
        .map(|k| k * (1.0 + cfg.perturb))
        .collect();
    let knots = Array::from_vec(guess);
    let path = |states: &[ArticulationState<f64>]| -> Path {
        states
            .iter()
            .map(|st| {
                let x = ball_at(&s, st) - s.ball_start;
                (x.x, x.z)
            })
            .collect()
    };
    let first = throw(&s, cfg, &knots, &mut Tape::new())?;
    let miss0 = (ball_at(&s, first.last().unwrap()) - target).norm();
    let report = Optimizer::lbfgs()
        .max_iters(cfg.max_iters)
        .progress(cfg.progress)
        .minimize(&Params::new().with(&knots), |tape| {
            let states = throw(&s, cfg, &knots, tape)?;
            let loss = Array::zeros(1);
            tape.launch(miss, 1, (&states.last().unwrap().q, s.ball, target, &loss));
            Ok(loss)
        })?;
    let found = throw(&s, cfg, &knots, &mut Tape::new())?;
    let miss1 = (ball_at(&s, found.last().unwrap()) - target).norm();
    // The release: the first time the ball is more than 5 cm from the cup's floor.
    let release = found
        .iter()
        .position(|st| {
            let kin = s.model.kinematics(&mut Tape::new(), &st.q);
            let (p, r) = (kin.link_p.get(s.cup.0), kin.link_r.get(s.cup.0));
            (ball_at(&s, st) - (p + rotate(&r, &s.cup.1))).norm() > 0.05 + BALL_RADIUS
        })
        .map_or(f64::INFINITY, |k| k as f64 * cfg.dt);
    Ok(Outcome {
        report,
        target: target - s.ball_start,
        miss: (miss0, miss1),
        paths: (path(&first), path(&found)),
        release,
    })
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let start = std::time::Instant::now();
    let cfg = if std::env::args().any(|a| a == "--small") {
        Config::small()
    } else {
        Config::full()
    };
    let out = run(&cfg)?;
    println!("{}", out.report);
    println!(
        "ball {:.1} mm from the target (first guess {:.0} mm), released at {:.3} s ({:.1} s)",
        1e3 * out.miss.1,
        1e3 * out.miss.0,
        out.release,
        start.elapsed().as_secs_f64()
    );
    let dir = std::path::Path::new("target/demos/arm_throw");
    std::fs::create_dir_all(dir)?;
    for file in ["loss.svg", "loss.png"] {
        adflex::viz::plot::loss_curve(
            dir.join(file),
            &out.report.losses(),
            "arm throw: L-BFGS on the swing torques",
        )?;
    }
    // The target and the ball's start as crosses 4 cm wide.
    let cross = |x: f64, z: f64| {
        let d = 0.02;
        [(x - d, z), (x + d, z), (x, z), (x, z - d), (x, z + d)]
    };
    let target = cross(out.target.x, out.target.z);
    // (Both relative to the ball's start, as the paths.)
    let start = cross(out.paths.0[0].0, out.paths.0[0].1);
    for file in ["path.svg", "path.png"] {
        adflex::viz::plot::curves(
            dir.join(file),
            "arm throw: the ball's path, side view",
            "x from the start (m)",
            "z from the start (m)",
            &[
                ("first guess", &out.paths.0[..]),
                ("throw found", &out.paths.1[..]),
                ("start", &start[..]),
                ("target", &target[..]),
            ],
        )?;
    }
    println!("pictures: {}/{{loss, path}}.{{svg, png}}", dir.display());
    Ok(())
}
