//! Articulated bodies: the dynamics of the repository's robots against Pinocchio and MuJoCo
//! (references in `references/robots.json`, from `references/robots.py`), derivatives against
//! Pinocchio's and central differences, rollouts' gradients, and bad robot files.

use adflex_kernels::articulation::{mjcf, urdf, ArticulationState, Articulations, JointType};
use adflex_runtime::{Array, Quat, Tape};
use serde_json::Value;

const ROBOTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/robots");

/// The team's robots with analytical derivatives to check: file, and whether a URDF's base
/// floats.
const DERIVATIVE_ROBOTS: [(&str, bool); 10] = [
    ("cartpole.urdf", false),
    ("arm7.urdf", false),
    ("quadruped.urdf", true),
    ("ant.xml", false),
    ("hopper.xml", false),
    ("humanoid.xml", false),
    ("walker.xml", false),
    ("swimmer.xml", false),
    ("servo_arm.xml", false),
    ("weightless_arm.xml", false),
];

fn load(file: &str, floating: bool) -> Articulations<f64> {
    load_as(file, floating)
}

/// [`load`] in any precision.
fn load_as<R: adflex_runtime::Real>(file: &str, floating: bool) -> Articulations<R> {
    let path = format!("{ROBOTS}/{file}");
    let b = if file.ends_with(".urdf") {
        urdf::load(
            &path,
            &urdf::UrdfOptions {
                floating_base: floating,
                ..Default::default()
            },
        )
    } else {
        mjcf::load(&path).map(|m| m.builder)
    };
    b.unwrap_or_else(|e| panic!("{e}")).finalize().unwrap()
}

/// The references from Pinocchio and MuJoCo (`references/robots.py`).
fn references() -> Value {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/references/robots.json");
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// An MJCF robot without contact or joint limits (MuJoCo's limits are constraints, not
/// compared here).
fn in_the_air(file: &str) -> mjcf::Mjcf {
    let mut robot = mjcf::load(format!("{ROBOTS}/{file}")).unwrap();
    let b = &mut robot.builder;
    (b.ground, b.link_contact) = (None, false);
    for l in b.links_mut() {
        l.joint.limits = None;
    }
    robot
}

/// The reference's joints in this model: for each, (q range, dof range) here.
fn joint_map(model: &Articulations<f64>, joints: &[Value]) -> Vec<(usize, usize, usize, usize)> {
    joints
        .iter()
        .map(|j| {
            let name = j["name"].as_str().unwrap();
            let kind = j["kind"].as_str().unwrap();
            let l = model
                .links
                .iter()
                .find(|l| {
                    l.joint == name
                        || (kind == "free" && l.kind == JointType::Free && l.parent.is_none())
                })
                .unwrap_or_else(|| panic!("joint {name} not in the model"));
            (l.q.start, l.q.len(), l.dofs.start, l.dofs.len())
        })
        .collect()
}

fn vecf(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn matf(v: &Value) -> Vec<Vec<f64>> {
    v.as_array().unwrap().iter().map(vecf).collect()
}

/// Largest difference relative to the largest entry of the reference.
fn rel_err(ours: &[Vec<f64>], reference: &[Vec<f64>]) -> f64 {
    let scale = reference
        .iter()
        .flatten()
        .fold(0.0f64, |m, x| m.max(x.abs()))
        .max(1e-300);
    let mut worst = 0.0f64;
    for (a, b) in ours.iter().zip(reference) {
        for (x, y) in a.iter().zip(b) {
            worst = worst.max((x - y).abs() / scale);
        }
    }
    worst
}

#[test]
fn dynamics_agree_with_pinocchio_and_mujoco() {
    let refs = references();
    let mut report = Vec::new();
    for m in refs["models"].as_array().unwrap() {
        let file = m["file"].as_str().unwrap();
        let model = load(file, m["floating_base"].as_bool().unwrap());
        let map = joint_map(&model, m["joints"].as_array().unwrap());
        let nv = model.n_dof;
        // Reference dof index -> ours.
        let mut dof = Vec::new();
        for &(_, _, d, n) in &map {
            dof.extend(d..d + n);
        }
        assert_eq!(dof.len(), nv, "{file}: every velocity is mapped");
        // The step's acceleration with the joints' springs and damping, without contact or
        // limit penalties (MuJoCo's limits are constraints, its qfrc_passive has neither).
        // (A free joint's linear velocity is stepped in the world frame: qd' - qd is qdd only
        // without one.)
        let free = m["joints"]
            .as_array()
            .unwrap()
            .iter()
            .any(|j| j["kind"] == "free");
        // (The damping explicit, as in qfrc_passive, and only for models whose actuators
        // exert nothing at ctrl = 0: qfrc_passive has no actuator force.)
        let stepper = (!file.ends_with(".urdf") && !free)
            .then(|| {
                let mut b = in_the_air(file).builder;
                b.implicit_damping = false;
                b.integrator = adflex_kernels::articulation::ArticulationIntegrator::Euler;
                let idle = b.actuators().iter().all(|a| a.bias == [0.0; 3]);
                idle.then(|| b.finalize::<f64>().unwrap())
            })
            .flatten();
        let mut worst = [0.0f64; 10];
        for s in m["states"].as_array().unwrap() {
            let (rq, rqd, rtau) = (vecf(&s["q"]), vecf(&s["qd"]), vecf(&s["tau"]));
            let (mut q, mut qd, mut tau) = (vec![0.0; model.n_q], vec![0.0; nv], vec![0.0; nv]);
            let (mut kq, mut kv) = (0, 0);
            for &(qs, nq, ds, n) in &map {
                q[qs..qs + nq].copy_from_slice(&rq[kq..kq + nq]);
                qd[ds..ds + n].copy_from_slice(&rqd[kv..kv + n]);
                tau[ds..ds + n].copy_from_slice(&rtau[kv..kv + n]);
                kq += nq;
                kv += n;
            }
            let mut tape = Tape::new();
            let (qa, qda, ta) = (
                Array::from_vec(q.clone()),
                Array::from_vec(qd.clone()),
                Array::from_vec(tau.clone()),
            );
            let mm = model.block(&model.mass_matrix(&mut tape, &qa), 0);
            let c = model.bias_forces(&mut tape, &qa, &qda).to_vec();
            let qdd = model
                .forward_dynamics(&mut tape, &qa, &qda, &ta)
                .unwrap()
                .to_vec();
            let permute = |m: &[Vec<f64>]| -> Vec<Vec<f64>> {
                (0..nv)
                    .map(|i| (0..nv).map(|j| m[dof[i]][dof[j]]).collect())
                    .collect()
            };
            let pv = |v: &[f64]| vec![(0..nv).map(|i| v[dof[i]]).collect::<Vec<_>>()];
            worst[0] = worst[0].max(rel_err(&permute(&mm), &matf(&s["mass_matrix"])));
            worst[1] = worst[1].max(rel_err(&pv(&c), &[vecf(&s["bias"])]));
            worst[2] = worst[2].max(rel_err(&pv(&qdd), &[vecf(&s["qdd"])]));
            if let (Some(p), Some(stepper)) = (s.get("passive"), &stepper) {
                // With dt = 1, qd' - qd is the acceleration.
                use adflex_kernels::articulation::{ArticulationControl, ArticulationState};
                use adflex_runtime::Vec3;
                let state = ArticulationState {
                    q: qa.clone(),
                    qd: qda.clone(),
                };
                let control = ArticulationControl {
                    tau: ta.clone(),
                    ..stepper.control()
                };
                let next = stepper
                    .step(&mut tape, &state, Some(&control), 1.0)
                    .unwrap();
                let ours: Vec<f64> = (0..nv).map(|i| next.qd.get(i) - qd[i]).collect();
                let rm = nalgebra::DMatrix::from_fn(nv, nv, |i, j| matf(&s["mass_matrix"])[i][j]);
                let (rt, rc, rp) = (vecf(&s["tau"]), vecf(&s["bias"]), vecf(p));
                let rhs = nalgebra::DVector::from_fn(nv, |i, _| rt[i] - rc[i] + rp[i]);
                let expected = rm.lu().solve(&rhs).unwrap();
                let ours = pv(&ours).remove(0);
                let expected: Vec<f64> = expected.iter().copied().collect();
                worst[6] = worst[6].max(rel_err(&[ours], &[expected]));
                // A wrench on each body (MuJoCo's xfrc_applied: at the centre of mass, world
                // frame) through the control's link_f and link_t, without joint torques.
                if let Some(wr) = s.get("link_wrench") {
                    let nl = stepper.n_links();
                    let (mut f, mut t) = (vec![Vec3::zeros(); nl], vec![Vec3::zeros(); nl]);
                    let names = wr["bodies"].as_array().unwrap();
                    for (name, w) in names.iter().zip(matf(&wr["wrench"])) {
                        let name = name.as_str().unwrap();
                        let l = stepper.links.iter().position(|x| x.name == name);
                        let l = l.unwrap_or_else(|| panic!("{file}: no link \"{name}\""));
                        f[l] = Vec3::new(w[0], w[1], w[2]);
                        t[l] = Vec3::new(w[3], w[4], w[5]);
                    }
                    let control = ArticulationControl {
                        link_f: Some(Array::from_vec(f)),
                        link_t: Some(Array::from_vec(t)),
                        ..stepper.control()
                    };
                    let next = stepper
                        .step(&mut tape, &state, Some(&control), 1.0)
                        .unwrap();
                    let ours: Vec<f64> = (0..nv).map(|i| next.qd.get(i) - qd[i]).collect();
                    worst[9] = worst[9].max(rel_err(&pv(&ours), &[vecf(&wr["qdd"])]));
                }
            }
            if s.get("dqdd_dq").is_some() {
                let d = model.forward_dynamics_derivatives(&q, &qd, &tau).unwrap();
                worst[3] = worst[3].max(rel_err(&permute(&d.dq), &matf(&s["dqdd_dq"])));
                worst[4] = worst[4].max(rel_err(&permute(&d.dqd), &matf(&s["dqdd_dqd"])));
                worst[5] = worst[5].max(rel_err(&permute(&d.dtau), &matf(&s["dqdd_dtau"])));
            }
            if s.get("dtau_dq").is_some() {
                // Pinocchio's computeRNEADerivatives at its own qdd (ours agrees with it).
                let t = model.inverse_dynamics_derivatives(&q, &qd, &qdd).unwrap();
                worst[7] = worst[7].max(rel_err(&permute(&t.dq), &matf(&s["dtau_dq"])));
                worst[8] = worst[8].max(rel_err(&permute(&t.dqd), &matf(&s["dtau_dqd"])));
                assert!(rel_err(&t.dqdd, &mm) < 1e-14, "{file}: d tau / d qdd is M");
            }
        }
        report.push(format!(
            "{file} ({}): M {:.1e}, bias {:.1e}, qdd {:.1e}, dqdd/dq {:.1e}, dqdd/dqd {:.1e}, dqdd/dtau {:.1e}, qdd with springs and damping {:.1e}, dtau/dq {:.1e}, dtau/dqd {:.1e}, qdd with link wrenches {:.1e}",
            m["reference"].as_str().unwrap(),
            worst[0], worst[1], worst[2], worst[3], worst[4], worst[5], worst[6], worst[7], worst[8], worst[9]
        ));
        assert!(
            worst.iter().all(|&w| w < 1e-9),
            "{file}: relative errors {worst:?}\n{}",
            report.join("\n")
        );
    }
    println!("{}", report.join("\n"));
}

/// Rollouts of the MJCF robots with random controls (some beyond their ranges) step by step
/// as MuJoCo's `mj_step` by each of its integrators adflex offers (Euler: damping implicit,
/// actuators, springs, the fluid explicit; RK4; implicitfast), contact and limits off on both
/// sides: the states every 50 steps agree.
#[test]
fn mjcf_rollouts_agree_with_mujoco_step_by_step() {
    let checked = mjcf_rollouts("rollouts", false);
    assert!(
        checked[0] >= 6 && checked[1] >= 6 && checked[2] >= 5,
        "every MJCF robot has rollout references ({checked:?})"
    );
    // The file's integrator is the model's.
    let walker = mjcf::load(format!("{ROBOTS}/walker.xml")).unwrap();
    assert_eq!(
        walker.builder.integrator,
        adflex_kernels::articulation::ArticulationIntegrator::Rk4
    );
}

/// As [`mjcf_rollouts_agree_with_mujoco_step_by_step`] with the joint limits on: every limited
/// joint starts past one of its limits, moving into it, under gravity and controls, so that
/// MuJoCo's soft limit constraints act in most steps (its solver run to convergence), as the
/// time-constant limits do here.
#[test]
fn mjcf_rollouts_with_limits_agree_with_mujoco_step_by_step() {
    let checked = mjcf_rollouts("limit_rollouts", true);
    assert!(
        checked[0] >= 5 && checked[1] >= 5 && checked[2] >= 4,
        "every MJCF robot with limits has rollout references ({checked:?})"
    );
}

/// Checks the references' rollouts under `key` (with the joints' limits when `limits`), and
/// returns how many it checked by each integrator (Euler, RK4, implicitfast).
fn mjcf_rollouts(key: &str, limits: bool) -> [usize; 3] {
    use adflex_kernels::articulation::{
        ArticulationControl, ArticulationIntegrator, ArticulationState,
    };
    let refs = references();
    let mut report = Vec::new();
    let mut checked = [0; 3];
    for m in refs["models"].as_array().unwrap() {
        let Some(rollouts) = m.get(key) else {
            continue;
        };
        let file = m["file"].as_str().unwrap();
        for r in rollouts.as_array().unwrap() {
            let mut robot = match limits {
                false => in_the_air(file),
                true => {
                    let mut robot = mjcf::load(format!("{ROBOTS}/{file}")).unwrap();
                    (robot.builder.ground, robot.builder.link_contact) = (None, false);
                    robot
                }
            };
            let name = r["integrator"].as_str().unwrap();
            let (k, integrator) = match name {
                "Euler" => (0, ArticulationIntegrator::Euler),
                "RK4" => (1, ArticulationIntegrator::Rk4),
                "implicitfast" => (2, ArticulationIntegrator::ImplicitFast),
                o => panic!("{file}: integrator {o}"),
            };
            robot.builder.integrator = integrator;
            let model = robot.builder.finalize::<f64>().unwrap();
            let worst = rollout_error(&model, &m["joints"], r, file, name);
            assert_eq!(
                robot.timestep.unwrap().min(0.002),
                r["dt"].as_f64().unwrap(),
                "{file}: the time step"
            );
            report.push(format!("{file}, {name}: worst {worst:.1e}"));
            checked[k] += 1;
        }
    }
    println!("{}", report.join("\n"));

    /// The largest difference from MuJoCo's states along the rollout `r`, relative to the
    /// state's size.
    fn rollout_error(
        model: &Articulations<f64>,
        joints: &Value,
        r: &Value,
        file: &str,
        integrator: &str,
    ) -> f64 {
        let map = joint_map(model, joints.as_array().unwrap());
        let to_ours = |rq: &[f64], rqd: &[f64]| {
            let (mut q, mut qd) = (vec![0.0; model.n_q], vec![0.0; model.n_dof]);
            let (mut kq, mut kv) = (0, 0);
            for &(qs, nq, ds, n) in &map {
                q[qs..qs + nq].copy_from_slice(&rq[kq..kq + nq]);
                qd[ds..ds + n].copy_from_slice(&rqd[kv..kv + n]);
                kq += nq;
                kv += n;
            }
            (q, qd)
        };
        let dt = r["dt"].as_f64().unwrap();
        let (q0, qd0) = to_ours(&vecf(&r["q0"]), &vecf(&r["qd0"]));
        let mut s = ArticulationState {
            q: Array::from_vec(q0),
            qd: Array::from_vec(qd0),
        };
        let control = ArticulationControl {
            ctrl: Array::from_vec(vecf(&r["ctrl"])),
            ..model.control()
        };
        let every = r["every"].as_u64().unwrap() as usize;
        let (rq, rqd) = (matf(&r["q"]), matf(&r["qd"]));
        let mut worst = 0.0f64;
        for (k, (eq, eqd)) in rq.iter().zip(&rqd).enumerate() {
            for _ in 0..every {
                s = model
                    .step(&mut Tape::new(), &s, Some(&control), dt)
                    .unwrap();
            }
            let (eq, eqd) = to_ours(eq, eqd);
            let err = |a: &[f64], b: &[f64]| {
                let scale = b.iter().fold(1.0f64, |m, x| m.max(x.abs()));
                a.iter()
                    .zip(b)
                    .fold(0.0f64, |m, (x, y)| m.max((x - y).abs() / scale))
            };
            let e = err(&s.q.to_vec(), &eq).max(err(&s.qd.to_vec(), &eqd));
            worst = worst.max(e);
            assert!(
                e < 1e-8,
                "{file}, {integrator}: after {} steps, q {:?} qd {:?}, MuJoCo q {eq:?} qd {eqd:?}",
                (k + 1) * every,
                s.q.to_vec(),
                s.qd.to_vec()
            );
        }
        worst
    }
    checked
}

/// `qdd` at a state, on a throwaway tape.
fn qdd_at(model: &Articulations<f64>, q: &[f64], qd: &[f64], tau: &[f64]) -> Vec<f64> {
    let mut tape = Tape::new();
    let (qa, qda, ta) = (
        Array::from_vec(q.to_vec()),
        Array::from_vec(qd.to_vec()),
        Array::from_vec(tau.to_vec()),
    );
    model
        .forward_dynamics(&mut tape, &qa, &qda, &ta)
        .unwrap()
        .to_vec()
}

#[test]
fn forward_dynamics_derivatives_match_central_differences() {
    let mut rng = adflex_testkit::Rng(7);
    for (file, floating) in DERIVATIVE_ROBOTS {
        let model = load(file, floating);
        let n = model.n_dof;
        // A random state: random tangent displacement of the initial configuration.
        let q = model.integrate(
            &model.q0,
            &(0..n).map(|_| rng.uniform(-1.0, 1.0)).collect::<Vec<_>>(),
        );
        let qd: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let tau: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let d = model.forward_dynamics_derivatives(&q, &qd, &tau).unwrap();
        let h = 1e-6;
        let mut worst = [0.0f64; 3];
        for j in 0..n {
            let mut e = vec![0.0; n];
            e[j] = h;
            let f = |dq: &[f64], dqd: &[f64], dt: &[f64]| {
                let qp = model.integrate(&q, dq);
                let qdp: Vec<f64> = qd.iter().zip(dqd).map(|(a, b)| a + b).collect();
                let tp: Vec<f64> = tau.iter().zip(dt).map(|(a, b)| a + b).collect();
                qdd_at(&model, &qp, &qdp, &tp)
            };
            let z = vec![0.0; n];
            let m: Vec<f64> = e.iter().map(|x| -x).collect();
            let cols = [
                (f(&e, &z, &z), f(&m, &z, &z), &d.dq),
                (f(&z, &e, &z), f(&z, &m, &z), &d.dqd),
                (f(&z, &z, &e), f(&z, &z, &m), &d.dtau),
            ];
            for (k, (p, mi, an)) in cols.iter().enumerate() {
                let scale = an.iter().flatten().fold(1.0f64, |a, x| a.max(x.abs()));
                for i in 0..n {
                    let fd = (p[i] - mi[i]) / (2.0 * h);
                    worst[k] = worst[k].max((fd - an[i][j]).abs() / scale);
                }
            }
        }
        println!(
            "{file}: central differences vs the closed form: dq {:.1e}, dqd {:.1e}, dtau {:.1e}",
            worst[0], worst[1], worst[2]
        );
        assert!(worst.iter().all(|&w| w < 1e-6), "{file}: {worst:?}");
    }
}

/// A tree of every joint kind (a free base; ball, fixed, prismatic and revolute joints below
/// it on two branches), a second articulation on a ball joint, and all of it again in a second
/// world under another gravity.
fn every_joint_kind() -> Articulations<f64> {
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint, Pose};
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    let at = |x: f64, y: f64, z: f64| Pose::at(Vec3::new(x, y, z));
    let body =
        |m: f64, x: f64| Inertial::cuboid(m, Vec3::new(0.2, 0.1, 0.15), Vec3::new(x, 0.02, -0.1));
    let base = b.add_link("base", None, Joint::free(), body(3.0, 0.05));
    let ball = b.add_link(
        "ball",
        Some(base),
        Joint::ball().origin(at(0.1, 0.0, -0.2)),
        body(1.0, 0.1),
    );
    let weld = b.add_link(
        "weld",
        Some(ball),
        Joint::fixed().origin(at(0.0, 0.2, -0.1)),
        body(0.5, -0.1),
    );
    let slide = b.add_link(
        "slide",
        Some(weld),
        Joint::prismatic(Vec3::new(0.3, 1.0, 0.2))
            .origin(at(0.1, 0.0, 0.0))
            .armature(0.05),
        body(0.7, 0.0),
    );
    b.add_link(
        "hinge",
        Some(slide),
        Joint::revolute(Vec3::new(1.0, 0.2, -0.4)),
        body(0.4, 0.2),
    );
    b.add_link(
        "arm",
        Some(base),
        Joint::revolute(Vec3::z())
            .origin(at(-0.2, 0.1, 0.0))
            .armature(0.02),
        body(0.6, -0.15),
    );
    b.add_link(
        "pendulum",
        None,
        Joint::ball().origin(at(1.0, 0.0, 1.0)),
        body(1.5, 0.3),
    );
    let mut other = b.clone();
    other.gravity = Vec3::new(1.0, -2.0, -5.0);
    b.add_world(&other);
    b.finalize().unwrap()
}

/// The closed-form derivatives of the forward and inverse dynamics against the recorded
/// dynamics' tangent passes (one per tangent direction, velocity and torque or acceleration)
/// on every robot and on a tree of every joint kind in two worlds: the same to 1e-10 of each
/// matrix's size.
#[test]
fn dynamics_derivatives_match_the_recorded_dynamics() {
    let mut rng = adflex_testkit::Rng(11);
    let mut models: Vec<(String, Articulations<f64>)> = DERIVATIVE_ROBOTS
        .into_iter()
        .map(|(f, floating)| (f.to_string(), load(f, floating)))
        .collect();
    models.push(("every joint kind".into(), every_joint_kind()));
    for (name, model) in &models {
        let n = model.n_dof;
        let mut random = |k: f64| (0..n).map(|_| rng.uniform(-k, k)).collect::<Vec<_>>();
        let q = model.integrate(&model.q0, &random(1.0));
        let (qd, x) = (random(2.0), random(3.0));
        let worst = derivatives_against_tangents(model, &q, &qd, &x);
        println!(
            "{name}: closed form vs tangent passes: dqdd/dq {:.1e}, dqdd/dqd {:.1e}, \
             dqdd/dtau {:.1e}, dtau/dq {:.1e}, dtau/dqd {:.1e}, dtau/dqdd {:.1e}",
            worst[0], worst[1], worst[2], worst[3], worst[4], worst[5]
        );
        assert!(worst.iter().all(|&w| w < 1e-10), "{name}: {worst:?}");
    }
}

/// The largest differences, relative to each matrix's largest entry, between the closed-form
/// derivatives (forward dynamics at `tau = x`, inverse at `qdd = x`) and the recorded
/// dynamics' tangent passes; asserts on the way that the inverse dynamics undo the forward.
fn derivatives_against_tangents(
    model: &Articulations<f64>,
    q: &[f64],
    qd: &[f64],
    x: &[f64],
) -> [f64; 6] {
    use adflex_runtime::AnyArray;
    let n = model.n_dof;
    let d = model.forward_dynamics_derivatives(q, qd, x).unwrap();
    let t = model.inverse_dynamics_derivatives(q, qd, x).unwrap();
    let mut tape = Tape::new();
    let (qa, qda, xa) = (
        Array::from_vec(q.to_vec()),
        Array::from_vec(qd.to_vec()),
        Array::from_vec(x.to_vec()),
    );
    let qdd = model.forward_dynamics(&mut tape, &qa, &qda, &xa).unwrap();
    let tau = model.inverse_dynamics(&mut tape, &qa, &qda, &xa);
    // The inverse dynamics undo the forward (the armature's force included).
    let back = model
        .inverse_dynamics(&mut Tape::new(), &qa, &qda, &qdd)
        .to_vec();
    let err = back
        .iter()
        .zip(x)
        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        err < 1e-10,
        "inverse dynamics of qdd(tau) is tau to {err:e}"
    );
    let inputs: [&dyn AnyArray; 3] = [&qa, &qda, &xa];
    let mut worst = [0.0f64; 6];
    let derivatives = [&d.dq, &d.dqd, &d.dtau, &t.dq, &t.dqd, &t.dqdd];
    for (k, ours) in derivatives.into_iter().enumerate() {
        let scale = ours.iter().flatten().fold(1e-300f64, |a, x| a.max(x.abs()));
        for j in 0..n {
            let mut v = vec![0.0; model.n_q + 2 * n];
            match k % 3 {
                0 => {
                    let mut e = vec![0.0; n];
                    e[j] = 1.0;
                    v[..model.n_q].copy_from_slice(&model.tangent_to_coords(q, &e));
                }
                w => v[model.n_q + (w - 1) * n + j] = 1.0,
            }
            let out = if k < 3 { &qdd } else { &tau };
            let col = tape.jvp(&inputs, &v, &[out]).unwrap();
            for i in 0..n {
                worst[k] = worst[k].max((col[i] - ours[i][j]).abs() / scale);
            }
        }
    }
    worst
}

/// The closed forms read a model's fields as the kernels do, also when a user edited them:
/// a joint axis and a joint rotation that are not unit, an inertia that is not symmetric (its
/// symmetric part counts), a free joint below the root, and a ball joint's quaternion in `q`
/// that is not unit (both normalize it).
#[test]
fn dynamics_derivatives_read_edited_models_as_the_kernels_do() {
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint, Pose};
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    let body = |m: f64| Inertial::cuboid(m, Vec3::new(0.2, 0.1, 0.3), Vec3::new(0.1, 0.0, -0.1));
    let base = b.add_link("base", None, Joint::revolute(Vec3::x()), body(2.0));
    // A free joint below the root: a body attached to a moving link only by its coordinates.
    let free = b.add_link(
        "floating",
        Some(base),
        Joint::free().origin(Pose::at(Vec3::new(0.0, 0.3, 0.0))),
        body(1.0),
    );
    b.add_link("ball", Some(free), Joint::ball(), body(0.5));
    b.add_link(
        "slide",
        Some(base),
        Joint::prismatic(Vec3::y()).origin(Pose::at(Vec3::new(0.2, 0.0, 0.1))),
        body(0.8),
    );
    let model = b.finalize::<f64>().unwrap();
    model.joint_axis.set(0, Vec3::new(0.0, 2.0, 1.0));
    model.joint_axis.set(3, Vec3::new(-3.0, 0.5, 0.0));
    model.joint_rot.set(3, Quat::new(0.2, 0.0, 0.4, 1.5));
    let mut i = model.inertia.get(1);
    i[(0, 1)] += 0.02;
    i[(2, 0)] -= 0.01;
    model.inertia.set(1, i);
    let mut rng = adflex_testkit::Rng(5);
    let n = model.n_dof;
    let mut random = |k: f64| (0..n).map(|_| rng.uniform(-k, k)).collect::<Vec<_>>();
    let mut q = model.integrate(&model.q0, &random(1.0));
    let ball = model.links.iter().find(|l| l.name == "ball").unwrap();
    for c in &mut q[ball.q.clone()] {
        *c *= 2.0;
    }
    let (qd, x) = (random(2.0), random(3.0));
    let worst = derivatives_against_tangents(&model, &q, &qd, &x);
    println!(
        "edited model: closed form vs tangent passes {:?}",
        worst.map(|w| format!("{w:.1e}"))
    );
    assert!(worst.iter().all(|&w| w < 1e-10), "{worst:?}");
}

/// An `f32` model's derivatives are its `f64` twin's at the same (rounded) values.
#[test]
fn dynamics_derivatives_of_an_f32_model() {
    let (narrow, wide) = (
        load_as::<f32>("quadruped.urdf", true),
        load("quadruped.urdf", true),
    );
    let n = wide.n_dof;
    let mut rng = adflex_testkit::Rng(3);
    let q = wide.integrate(
        &wide.q0,
        &(0..n).map(|_| rng.uniform(-1.0, 1.0)).collect::<Vec<_>>(),
    );
    let qd: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let narrow_of = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
    let wide_of = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<_>>();
    let (q, qd) = (wide_of(&narrow_of(&q)), wide_of(&narrow_of(&qd)));
    let a = narrow
        .forward_dynamics_derivatives(&narrow_of(&q), &narrow_of(&qd), &narrow_of(&qd))
        .unwrap();
    let b = wide.forward_dynamics_derivatives(&q, &qd, &qd).unwrap();
    for (x, y) in [(&a.dq, &b.dq), (&a.dqd, &b.dqd), (&a.dtau, &b.dtau)] {
        let scale = y.iter().flatten().fold(1e-300f64, |m, v| m.max(v.abs()));
        let diff = x
            .iter()
            .flatten()
            .zip(y.iter().flatten())
            .fold(0.0f64, |m, (u, v)| m.max((u - v).abs()));
        // The model's parameters are rounded to f32: differences of that order.
        assert!(diff / scale < 1e-5, "f32 vs f64: {:e}", diff / scale);
    }
}

/// Bad inputs to the derivatives are named, not NaN.
#[test]
fn dynamics_derivatives_refuse_bad_inputs_by_name() {
    let model = load("arm7.urdf", false);
    let n = model.n_dof;
    let (q, z) = (model.q0.clone(), vec![0.0; n]);
    let e = model
        .forward_dynamics_derivatives(&q[..n - 1], &z, &z)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("forward_dynamics_derivatives: q") && e.contains(&format!("needs {n}")),
        "{e}"
    );
    let mut qd = z.clone();
    qd[3] = f64::NAN;
    let e = model
        .forward_dynamics_derivatives(&q, &qd, &z)
        .unwrap_err()
        .to_string();
    assert!(e.contains("qd[3]") && e.contains("NaN"), "{e}");
    let mut qdd = z.clone();
    qdd[1] = f64::INFINITY;
    let e = model
        .inverse_dynamics_derivatives(&q, &z, &qdd)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("inverse_dynamics_derivatives: qdd[1]") && e.contains("inf"),
        "{e}"
    );
    // A quaternion of norm 0 in q, and bad model values: named, never NaN.
    let quadruped = load("quadruped.urdf", true);
    let (n, mut q) = (quadruped.n_dof, quadruped.q0.clone());
    let z = vec![0.0; n];
    q[3..7].fill(0.0);
    let e = quadruped
        .inverse_dynamics_derivatives(&q, &z, &z)
        .unwrap_err()
        .to_string();
    assert!(e.contains("q[3..7]") && e.contains("norm 0"), "{e}");
    let q = quadruped.q0.clone();
    type Edit = fn(&mut Articulations<f64>);
    let edits: [(Edit, &str); 6] = [
        (
            |m| m.joint_rot.set(2, Quat::new(0.0, 0.0, 0.0, 0.0)),
            "model.joint_rot[2]",
        ),
        (
            |m| m.joint_axis.set(2, adflex_runtime::Vec3::zeros()),
            "model.joint_axis[2]",
        ),
        (
            |m| {
                m.gravity
                    .set(0, adflex_runtime::Vec3::new(0.0, f64::NAN, 0.0))
            },
            "model.gravity[0]",
        ),
        (|m| m.gravity = Array::zeros(0), "model.gravity"),
        (|m| m.mass.set(1, f64::INFINITY), "model.mass[1]"),
        (|m| m.armature = Array::zeros(1), "model.armature"),
    ];
    for (edit, named) in edits {
        // A fresh model each time: a clone shares its arrays.
        let mut m = load("quadruped.urdf", true);
        edit(&mut m);
        for e in [
            m.inverse_dynamics_derivatives(&q, &z, &z).unwrap_err(),
            m.forward_dynamics_derivatives(&q, &z, &z).unwrap_err(),
        ] {
            let e = e.to_string();
            assert!(e.contains(named), "{named}: {e}");
        }
    }
}

/// A free box, spinning and falling: one link on a free joint.
fn spinning_box() -> Articulations<f64> {
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint};
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    b.add_link(
        "box",
        None,
        Joint::free().initial(&[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
        Inertial::cuboid(2.0, Vec3::new(0.3, 0.2, 0.1), Vec3::new(0.05, 0.0, 0.0)),
    );
    b.finalize().unwrap()
}

/// Rolls `model` out for `steps` semi-implicit steps from `(q, qd)` with per-step torques
/// `taus` and PD targets; returns the final state's `(q, qd)` on `tape`.
fn rollout(
    model: &Articulations<f64>,
    tape: &mut Tape,
    q: &Array<f64>,
    qd: &Array<f64>,
    taus: &[Array<f64>],
    dt: f64,
) -> (Array<f64>, Array<f64>) {
    use adflex_kernels::articulation::{ArticulationControl, ArticulationState};
    let mut s = ArticulationState {
        q: q.clone(),
        qd: qd.clone(),
    };
    let idle = model.control();
    for tau in taus {
        let c = ArticulationControl {
            tau: tau.clone(),
            ..idle.clone()
        };
        s = model.step(tape, &s, Some(&c), dt).unwrap();
    }
    (s.q, s.qd)
}

#[test]
fn rollout_gradients_match_central_differences() {
    use adflex_kernels::articulation::ArticulationIntegrator::{self, *};
    fn by(m: Articulations<f64>, integrator: ArticulationIntegrator) -> Articulations<f64> {
        Articulations { integrator, ..m }
    }
    fn air(file: &str, integrator: ArticulationIntegrator) -> Articulations<f64> {
        let mut b = in_the_air(file).builder;
        b.integrator = integrator;
        b.finalize().unwrap()
    }
    let mut rng = adflex_testkit::Rng(11);
    let models = [
        ("spinning box", spinning_box()),
        ("cartpole", load("cartpole.urdf", false)),
        ("arm7", load("arm7.urdf", false)),
        ("quadruped", load("quadruped.urdf", true)),
        ("humanoid", load("humanoid.xml", false)),
        // Its springs and damping, in the air (contact has its own tests); the file asks RK4.
        ("walker (RK4)", {
            let mut b = mjcf::load(format!("{ROBOTS}/walker.xml")).unwrap().builder;
            (b.ground, b.link_contact) = (None, false);
            b.finalize().unwrap()
        }),
        // The other integrators through free and ball joints, in the air (this start drives
        // the humanoid's feet into the ground at speeds where central differences fail).
        ("spinning box (RK4)", by(spinning_box(), Rk4)),
        ("humanoid (RK4)", air("humanoid.xml", Rk4)),
        ("humanoid (implicitfast)", air("humanoid.xml", ImplicitFast)),
    ];
    for (name, model) in &models {
        let n = model.n_dof;
        let steps = 40;
        let dt = 2e-3;
        // Inside the joint limits, so that no limit switches on (a kink) during the rollout.
        let (lower, upper) = (model.lower.to_vec(), model.upper.to_vec());
        let start: Vec<f64> = (0..n)
            .map(|d| {
                let (lo, hi) = (lower[d].max(-0.5), upper[d].min(0.5));
                rng.uniform(lo + 0.3 * (hi - lo), hi - 0.3 * (hi - lo))
            })
            .collect();
        let q0 = model.integrate(&model.q0, &start);
        let qd0: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let taus0: Vec<Vec<f64>> = (0..steps)
            .map(|_| (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect())
            .collect();
        let w: Vec<f64> = (0..model.n_q + n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        // J^T w by one backward pass over the rollout.
        let q = Array::from_vec(q0.clone());
        let qd = Array::from_vec(qd0.clone());
        let taus: Vec<Array<f64>> = taus0.iter().map(|t| Array::from_vec(t.clone())).collect();
        let mut tape = Tape::new();
        let (qf, qdf) = rollout(model, &mut tape, &q, &qd, &taus, dt);
        let mut inputs: Vec<&dyn adflex_runtime::AnyArray> =
            vec![&q, &qd, &model.mass, &model.joint_pos];
        inputs.extend(taus.iter().map(|t| t as &dyn adflex_runtime::AnyArray));
        let grad = tape.vjp(&[&qf, &qdf], &w, &inputs).unwrap();
        assert!(
            grad.iter().all(|g| g.is_finite()),
            "{name}: a non-finite gradient"
        );
        // Central differences along random directions of every input at once.
        // Perturbed copies of the parameters (`Articulations::clone` shares the arrays).
        let (mass0, jpos0) = (model.mass.to_vec(), model.joint_pos.to_vec());
        let loss = |v: &[f64], h: f64| -> f64 {
            let mut k = 0;
            let mut take = |x: &[f64]| -> Vec<f64> {
                let out = x.iter().zip(&v[k..]).map(|(a, b)| a + h * b).collect();
                k += x.len();
                out
            };
            let q = Array::from_vec(take(&q0));
            let qd = Array::from_vec(take(&qd0));
            let mass = Array::from_vec(take(&mass0));
            let jp: Vec<f64> = jpos0.iter().flat_map(|p| [p.x, p.y, p.z]).collect();
            let joint_pos = Array::from_vec(
                take(&jp)
                    .chunks(3)
                    .map(|c| adflex_runtime::Vec3::new(c[0], c[1], c[2]))
                    .collect(),
            );
            let taus: Vec<Array<f64>> = taus0.iter().map(|t| Array::from_vec(take(t))).collect();
            let m = Articulations {
                mass,
                joint_pos,
                ..model.clone()
            };
            let mut tape = Tape::new();
            let (qf, qdf) = rollout(&m, &mut tape, &q, &qd, &taus, dt);
            let f: Vec<f64> = qf.to_vec().into_iter().chain(qdf.to_vec()).collect();
            f.iter().zip(&w).map(|(a, b)| a * b).sum()
        };
        let mut worst = 0.0f64;
        // One direction per input (initial q, qd, masses, joint placements, torques), then
        // all at once.
        let sizes = [
            model.n_q,
            n,
            model.n_links(),
            3 * model.n_links(),
            n * steps,
        ];
        for group in 0..=sizes.len() {
            let start: usize = sizes[..group.min(sizes.len())].iter().sum();
            let end = if group == sizes.len() {
                grad.len()
            } else {
                start + sizes[group]
            };
            let start = if group == sizes.len() { 0 } else { start };
            let v: Vec<f64> = (0..grad.len())
                .map(|i| {
                    if (start..end).contains(&i) {
                        rng.uniform(-1.0, 1.0)
                    } else {
                        0.0
                    }
                })
                .collect();
            let h = 1e-6;
            let fd = (loss(&v, h) - loss(&v, -h)) / (2.0 * h);
            let an: f64 = grad.iter().zip(&v).map(|(a, b)| a * b).sum();
            // Relative to the sum of the terms' sizes: along every input at once the
            // directional derivative is a sum of hundreds of terms that may nearly cancel.
            let terms: f64 = grad.iter().zip(&v).map(|(a, b)| (a * b).abs()).sum();
            worst = worst.max((fd - an).abs() / an.abs().max(terms).max(1e-2));
        }
        println!("{name}: rollout gradient vs central differences {worst:.1e}");
        assert!(worst < 1e-6, "{name}: {worst:.2e}");
    }
}

#[test]
fn gradients_are_finite_and_right_at_singular_configurations() {
    // (model, q0, qd0): identity quaternion and no angular velocity; a straight chain at rest;
    // a joint exactly at its limit.
    let cartpole = load("cartpole.urdf", false);
    let arm = load("arm7.urdf", false);
    let cases = [
        ("box at rest, identity", spinning_box(), None, 0.0),
        ("straight arm at rest", arm, None, 0.0),
        ("slider at its limit", cartpole, Some(vec![4.0, 0.0]), 0.0),
    ];
    for (name, model, q0, v0) in cases {
        let q0 = q0.unwrap_or_else(|| model.q0.clone());
        let qd0 = vec![v0; model.n_dof];
        let taus0 = vec![vec![0.0; model.n_dof]; 20];
        let w: Vec<f64> = (0..model.n_q + model.n_dof)
            .map(|i| 1.0 + 0.1 * i as f64)
            .collect();
        let (q, qd) = (Array::from_vec(q0.clone()), Array::from_vec(qd0.clone()));
        let taus: Vec<Array<f64>> = taus0.iter().map(|t| Array::from_vec(t.clone())).collect();
        let mut tape = Tape::new();
        let (qf, qdf) = rollout(&model, &mut tape, &q, &qd, &taus, 1e-3);
        let g = tape.vjp(&[&qf, &qdf], &w, &[&q, &qd]).unwrap();
        assert!(g.iter().all(|x| x.is_finite()), "{name}: {g:?}");
        // Central differences of each velocity (the kinks are in q at a limit).
        // At the limit, only the slider's own velocity has a known side (the pole's moves the
        // cart into or away from the limit, depending on the sign).
        let checked = if name.contains("limit") {
            1
        } else {
            model.n_dof
        };
        for j in 0..checked {
            let f = |h: f64| {
                let mut qd = qd0.clone();
                qd[j] += h;
                let mut tape = Tape::new();
                let (qf, qdf) = rollout(
                    &model,
                    &mut tape,
                    &Array::from_vec(q0.clone()),
                    &Array::from_vec(qd),
                    &taus,
                    1e-3,
                );
                let f: Vec<f64> = qf.to_vec().into_iter().chain(qdf.to_vec()).collect();
                f.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
            };
            // At the limit the force switches on for motion into it: the gradient is the
            // one-sided derivative of the free side (`x == upper` is not a violation).
            let (fd, tol) = if name.contains("limit") {
                ((f(0.0) - f(-1e-7)) / 1e-7, 1e-5)
            } else {
                ((f(1e-6) - f(-1e-6)) / 2e-6, 1e-6)
            };
            let an = g[model.n_q + j];
            assert!(
                (fd - an).abs() <= tol * an.abs().max(1.0),
                "{name}: velocity {j}: {an} vs central differences {fd}"
            );
        }
    }
}

#[test]
fn a_box_comes_to_rest_on_the_ground() {
    use adflex_kernels::articulation::{ArticulationBuilder, GroundContact, Inertial, Joint, Pose};
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    let half = Vec3::new(0.2, 0.1, 0.05);
    let l = b.add_link(
        "box",
        None,
        Joint::free().initial(&[0.0, 0.0, 0.3, 0.1, 0.0, 0.0, 1.0]),
        Inertial::cuboid(1.0, half, Vec3::zeros()),
    );
    b.add_contact_box(l, &Pose::identity(), half);
    b.ground = Some(GroundContact::default());
    let model = b.finalize::<f64>().unwrap();
    let mut tape = Tape::new();
    let mut s = model.state();
    for _ in 0..1500 {
        s = model.step(&mut tape, &s, None, 1e-3).unwrap();
    }
    let q = s.q.to_vec();
    let speed = s.qd.to_vec().iter().fold(0.0f64, |m, x| m.max(x.abs()));
    // Resting flat on four corners: sunk by m g / (4 ke).
    let expected = 0.05 - 9.81 / (4.0 * 1e4);
    assert!(
        (q[2] - expected).abs() < 1e-4,
        "height {} vs {expected}",
        q[2]
    );
    assert!(speed < 1e-3, "still moving: {speed}");
    // Flat: the body's z axis is the world's.
    let r = Quat::new(q[6], q[3], q[4], q[5]);
    let z = r * Quat::new(0.0, 0.0, 0.0, 1.0) * r.conjugate();
    assert!(z.k > 1.0 - 1e-6, "tilted: {z:?}");
}

/// Rolls `model` out from `(q0, qd0)` under the torques `taus0` (one vector per step), checks
/// `J^T w` of the final state (one backward pass, random `w`) against central differences
/// along `directions` random directions of all the torques to 1e-4 relative (the tolerance
/// through contact), and returns the final coordinates.
fn check_torque_gradients(
    model: &Articulations<f64>,
    q0: &[f64],
    qd0: &[f64],
    taus0: &[Vec<f64>],
    dt: f64,
    directions: usize,
    rng: &mut adflex_testkit::Rng,
) -> Vec<f64> {
    let n = model.n_dof;
    let w: Vec<f64> = (0..model.n_q + n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let run = |h: f64, v: &[f64], tape: &mut Tape| {
        let taus: Vec<Array<f64>> = taus0
            .iter()
            .enumerate()
            .map(|(s, t)| {
                let shifted = t.iter().enumerate().map(|(d, x)| x + h * v[s * n + d]);
                Array::from_vec(shifted.collect())
            })
            .collect();
        let (q, qd) = (Array::from_vec(q0.to_vec()), Array::from_vec(qd0.to_vec()));
        let (qf, qdf) = rollout(model, tape, &q, &qd, &taus, dt);
        (taus, qf, qdf)
    };
    let zero = vec![0.0; n * taus0.len()];
    let mut tape = Tape::new();
    let (taus, qf, qdf) = run(0.0, &zero, &mut tape);
    let inputs: Vec<&dyn adflex_runtime::AnyArray> = taus
        .iter()
        .map(|t| t as &dyn adflex_runtime::AnyArray)
        .collect();
    let g = tape.vjp(&[&qf, &qdf], &w, &inputs).unwrap();
    assert!(g.iter().all(|x| x.is_finite()), "a non-finite gradient");
    let f = |v: &[f64], h: f64| {
        let (_, qf, qdf) = run(h, v, &mut Tape::new());
        let f: Vec<f64> = qf.to_vec().into_iter().chain(qdf.to_vec()).collect();
        f.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
    };
    for _ in 0..directions {
        let v: Vec<f64> = (0..g.len()).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let fd = (f(&v, 1e-6) - f(&v, -1e-6)) / 2e-6;
        let an: f64 = g.iter().zip(&v).map(|(a, b)| a * b).sum();
        println!("through contact: {an} vs central differences {fd}");
        assert!((fd - an).abs() <= 1e-4 * an.abs().max(1e-2), "{an} vs {fd}");
    }
    qf.to_vec()
}

#[test]
fn quadruped_rollout_through_ground_contact_has_right_gradients() {
    // The MJCF ant dropped onto its floor, its hips and ankles driven by torques.
    let robot = mjcf::load(format!("{ROBOTS}/ant.xml")).unwrap();
    let mut b = robot.builder;
    assert!(b.ground.is_some() && b.contacts().len() > 8);
    let mass: f64 = b.links().iter().map(|l| l.inertial.mass).sum();
    println!("ant mass {mass}");
    let g = b.ground.as_mut().unwrap();
    // A contact as stiff as the ant is light (about 1 cm sag on one foot).
    (g.ke, g.kd) = (mass * 9.81 / 0.01, mass * 5.0);
    let model = b.finalize::<f64>().unwrap();
    let n = model.n_dof;
    let steps = 250;
    let dt = 2e-3;
    let mut rng = adflex_testkit::Rng(5);
    // The ankles start inside their ranges.
    let (lower, upper) = (model.lower.to_vec(), model.upper.to_vec());
    let mid: Vec<f64> = (0..n)
        .map(|d| {
            if lower[d].is_finite() {
                0.5 * (lower[d] + upper[d])
            } else {
                0.0
            }
        })
        .collect();
    let q0 = model.integrate(&model.q0, &mid);
    let qd0 = vec![0.0; n];
    let taus0: Vec<Vec<f64>> = (0..steps)
        .map(|_| {
            (0..n)
                .map(|d| if d < 6 { 0.0 } else { rng.uniform(-0.05, 0.05) })
                .collect()
        })
        .collect();
    let qf = check_torque_gradients(&model, &q0, &qd0, &taus0, dt, 3, &mut rng);
    // It landed: the torso is held up by the legs, above the ground and below its start.
    let z = qf[2];
    assert!(z > 0.1 && z < 0.7, "torso height {z}");
}

/// Parses a URDF and returns its error.
fn urdf_error(text: &str) -> adflex_kernels::articulation::ArticulationError {
    match urdf::parse(text, &urdf::UrdfOptions::default()).and_then(|b| b.finalize::<f64>()) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e,
    }
}

fn mjcf_error(text: &str) -> adflex_kernels::articulation::ArticulationError {
    match mjcf::parse(text).and_then(|m| m.builder.finalize::<f64>()) {
        Ok(_) => panic!("accepted:\n{text}"),
        Err(e) => e,
    }
}

const URDF: &str = r#"<robot name="r">
  <link name="a"/>
  <link name="b">
    <inertial><mass value="1"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/></inertial>
  </link>
  <joint name="j" type="revolute">
    <parent link="a"/><child link="b"/><axis xyz="0 0 1"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/>
  </joint>
</robot>"#;

#[test]
fn urdf_joint_friction_is_refused_unless_left_out_as_pinocchio_does() {
    let with = URDF.replace(
        "<origin xyz=\"0 0 0.1\" rpy=\"0 0 0\"/>",
        "<origin xyz=\"0 0 0.1\" rpy=\"0 0 0\"/>\n    <dynamics damping=\"0.5\" friction=\"0.3\"/>",
    );
    let e = urdf::parse(&with, &Default::default()).unwrap_err();
    assert_eq!(e.line, Some(9), "{e}");
    assert!(e.to_string().contains("ignore_friction"), "{e}");
    let negative = with.replace("friction=\"0.3\"", "friction=\"-1\"");
    let ignore = urdf::UrdfOptions {
        ignore_friction: true,
        ..Default::default()
    };
    let e = urdf::parse(&negative, &ignore).unwrap_err();
    assert!(e.to_string().contains("negative"), "{e}");
    // Left out: the model is the one without friction (damping kept), bit for bit.
    let without = with.replace(" friction=\"0.3\"", "");
    let a = urdf::parse(&with, &ignore)
        .unwrap()
        .finalize::<f64>()
        .unwrap();
    let b = urdf::parse(&without, &Default::default())
        .unwrap()
        .finalize::<f64>()
        .unwrap();
    assert_eq!(a.damping.to_vec(), vec![0.5]);
    let mut tape = Tape::new();
    let s = |m: &Articulations<f64>, tape: &mut Tape| {
        let state = ArticulationState {
            q: Array::from_vec(vec![0.4]),
            qd: Array::from_vec(vec![1.5]),
        };
        let next = m.step(tape, &state, None, 1e-3).unwrap();
        (next.q.to_vec(), next.qd.to_vec())
    };
    assert_eq!(s(&a, &mut tape), s(&b, &mut tape));
}

#[test]
fn bad_urdf_is_refused_naming_the_element_and_line() {
    assert!(urdf::parse(URDF, &Default::default())
        .unwrap()
        .finalize::<f64>()
        .is_ok());
    let cases: [(&str, &str, u32, &str); 11] = [
        (
            "<parent link=\"a\"/>",
            "<parent link=\"z\"/>",
            6,
            "parent link \"z\" is not defined",
        ),
        ("<mass value=\"1\"/>", "<mass value=\"0\"/>", 4, "zero"),
        ("<mass value=\"1\"/>", "<mass value=\"-2\"/>", 4, "negative"),
        ("ixx=\"0.1\"", "ixx=\"-0.1\"", 4, "positive semi-definite"),
        (
            "type=\"revolute\"",
            "type=\"screw\"",
            6,
            "joint type `screw`",
        ),
        (
            "xyz=\"0 0 0.1\"",
            "xyz=\"0 NaN 0.1\"",
            8,
            "not a finite number",
        ),
        (
            "<axis xyz=\"0 0 1\"/>",
            "<axis xyz=\"0 0 0\"/>",
            7,
            "axis is zero",
        ),
        ("<link name=\"a\"/>", "<link name=\"a\"/><foo/>", 2, "<foo>"),
        // A misspelt attribute is an error, not a default.
        (
            "<axis xyz=\"0 0 1\"/>",
            "<axis xyz=\"0 0 1\"/><limit lower=\"-1\" uper=\"1\"/>",
            7,
            "uper",
        ),
        ("<mass value", "<mass valeu=\"2\" value", 4, "valeu"),
        // URDF requires a revolute or prismatic joint's limits (a continuous one has none).
        (
            "<limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/>",
            "",
            6,
            "revolute joint needs a `<limit",
        ),
    ];
    for (from, to, line, message) in cases {
        let e = urdf_error(&URDF.replacen(from, to, 1));
        assert_eq!(e.line, Some(line), "{e}");
        assert!(e.to_string().contains(message), "{e}");
    }
    // A cycle: b is the parent of a too (a then has a parent, and no link is the root).
    let cycle = URDF.replace(
        "</robot>",
        "<joint name=\"k\" type=\"fixed\"><parent link=\"b\"/><child link=\"a\"/></joint></robot>",
    );
    assert!(urdf_error(&cycle).to_string().contains("cycle"));
    let slider = URDF
        .replace("type=\"revolute\"", "type=\"prismatic\"")
        .replace(
            "<limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/>",
            "",
        );
    let e = urdf_error(&slider);
    assert!(
        e.to_string().contains("prismatic joint needs a `<limit"),
        "{e}"
    );
    let hinge = URDF
        .replace("type=\"revolute\"", "type=\"continuous\"")
        .replace(
            "<limit lower=\"-1\" upper=\"1\" effort=\"1\" velocity=\"1\"/>",
            "",
        );
    assert!(urdf::parse(&hinge, &Default::default()).is_ok());
    // Two parents.
    let two = URDF.replace(
        "</robot>",
        "<link name=\"c\"/><joint name=\"k\" type=\"fixed\"><parent link=\"c\"/><child link=\"b\"/></joint></robot>",
    );
    assert!(urdf_error(&two)
        .to_string()
        .contains("child of a second joint"));
}

const MJCF: &str = r#"<mujoco>
  <worldbody>
    <body name="a" pos="0 0 1" quat="1 0 0 0">
      <joint name="j" type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 -0.5" mass="1" diaginertia="0.1 0.1 0.1"/>
    </body>
  </worldbody>
</mujoco>"#;

#[test]
fn bad_mjcf_is_refused_naming_the_element_and_line() {
    assert!(mjcf::parse(MJCF).unwrap().builder.finalize::<f64>().is_ok());
    let cases: [(&str, &str, u32, &str); 32] = [
        ("quat=\"1 0 0 0\"", "quat=\"0 0 0 0\"", 3, "norm 0"),
        ("mass=\"1\"", "mass=\"0\"", 5, "zero"),
        ("mass=\"1\"", "mass=\"-1\"", 5, "negative"),
        (
            "diaginertia=\"0.1 0.1 0.1\"",
            "diaginertia=\"0.1 -0.1 0.3\"",
            5,
            "semi-definite",
        ),
        ("type=\"hinge\"", "type=\"screw\"", 4, "screw"),
        (
            "axis=\"0 1 0\"",
            "axis=\"0 nan 0\"",
            4,
            "not a finite number",
        ),
        ("<worldbody>", "<worldbody><tendon/>", 2, "<tendon>"),
        (
            "<joint name",
            "<joint frictionloss=\"3\" name",
            4,
            "frictionloss",
        ),
        (
            "<joint name",
            "<joint range=\"-1 1\" margin=\"1\" name",
            4,
            "closes the range",
        ),
        (
            "<worldbody>",
            "<option density=\"-1.2\"/><worldbody>",
            2,
            "non-negative",
        ),
        (
            "<worldbody>",
            "<option><flag passive=\"disable\"/></option><worldbody>",
            2,
            "passive",
        ),
        (
            "<worldbody>",
            "<option><flag gravty=\"disable\"/></option><worldbody>",
            2,
            "flag `gravty` is not supported",
        ),
        (
            "<worldbody>",
            "<worldbody><geom type=\"ellipsoid\" size=\"0.1 0.1 0.1\"/>",
            2,
            "an ellipsoid of the worldbody",
        ),
        (
            "</worldbody>",
            "</worldbody><contact><exclude body1=\"world\" body2=\"a\"/></contact>",
            7,
            "excluding the world",
        ),
        (
            "<worldbody>",
            "<option collision=\"predefined\"/><worldbody>",
            2,
            "collision",
        ),
        (
            "<worldbody>",
            "<option><flag sleep=\"enable\"/></option><worldbody>",
            2,
            "sleep",
        ),
        (
            "<worldbody>",
            "<default><geom fluidshape=\"ellipsoid\"/></default><worldbody>",
            2,
            "fluidshape",
        ),
        (
            "<joint name",
            "<joint range=\"-1 1\" solimplimit=\"0.9 0.95 0.001 0.3 2\" name",
            4,
            "midpoint",
        ),
        (
            "</worldbody>",
            "</worldbody><default><tendon limited=\"true\"/></default><tendon><fixed><joint joint=\"j\"/></fixed></tendon>",
            7,
            "gives tendons `limited`",
        ),
        (
            "type=\"hinge\"",
            "type=\"ball\" stiffness=\"2\"",
            4,
            "stiffness",
        ),
        (
            "<mujoco>",
            "<mujoco><compiler coordinate=\"global\"/>",
            1,
            "global",
        ),
        (
            "</worldbody>",
            "</worldbody><tendon><fixed range=\"0 1\"><joint joint=\"j\"/></fixed></tendon>",
            7,
            "range",
        ),
        (
            "</worldbody>",
            "</worldbody><tendon><fixed stiffness=\"-1\"><joint joint=\"j\"/></fixed></tendon>",
            7,
            "stiffness must be non-negative",
        ),
        (
            "</worldbody>",
            "</worldbody><tendon><fixed><joint joint=\"nope\"/></fixed></tendon>",
            7,
            "nope",
        ),
        (
            "mass=\"1\" diaginertia=\"0.1 0.1 0.1\"",
            "mass=\"1\" quat=\"0 1 0 0\" fullinertia=\"0.1 0.1 0.1 0 0 0\"",
            5,
            "body's frame",
        ),
        (
            "</worldbody>",
            "</worldbody><actuator><motor joint=\"j\" gear=\"1 0 0 0 1 0\"/></actuator>",
            7,
            "gear",
        ),
        (
            "</worldbody>",
            "</worldbody><actuator><general joint=\"j\" dyntype=\"filter\"/></actuator>",
            7,
            "dyntype=\"filter\" is not supported",
        ),
        (
            "</worldbody>",
            "</worldbody><actuator><motor joint=\"j\" forcerange=\"1 -1\"/></actuator>",
            7,
            "forcerange: lower >= upper",
        ),
        (
            "<joint name",
            "<joint limited=\"true\" range=\"0.5 0.5\" name",
            4,
            "lower 0.5 >= upper 0.5",
        ),
        // MuJoCo's keywords, and names repeated within a kind.
        (
            "<joint name",
            "<joint limited=\"maybe\" range=\"0 1\" name",
            4,
            "limited=\"maybe\": MuJoCo's keywords are true, false and auto",
        ),
        (
            "</worldbody>",
            "</worldbody><actuator><motor joint=\"j\" ctrllimited=\"yes\" ctrlrange=\"0 1\"/></actuator>",
            7,
            "ctrllimited=\"yes\"",
        ),
        (
            "    </body>\n  </worldbody>",
            "      <body name=\"a\"><joint/><geom size=\"0.1\"/></body>\n    </body>\n  </worldbody>",
            6,
            "a second body with this name",
        ),
    ];
    for (from, to, line, message) in cases {
        let e = mjcf_error(&MJCF.replacen(from, to, 1));
        assert_eq!(e.line, Some(line), "{e}");
        assert!(e.to_string().contains(message), "{e}");
    }
    // Unsupported top-level physics is refused, not dropped.
    let e = mjcf_error(&MJCF.replace("</mujoco>", "<equality/></mujoco>"));
    assert!(e.to_string().contains("<equality>"), "{e}");
    // An actuator on a joint that does not exist.
    let e = mjcf_error(&MJCF.replace(
        "</mujoco>",
        "<actuator><motor joint=\"k\"/></actuator></mujoco>",
    ));
    assert!(e.to_string().contains("joint \"k\" is not defined"), "{e}");
    // With contact switched off (dm_control's reacher), a worldbody ellipsoid touches nothing.
    let off = MJCF.replace(
        "<worldbody>",
        "<option><flag contact=\"disable\"/></option>\
         <worldbody><geom type=\"ellipsoid\" size=\"0.1 0.1 0.1\"/>",
    );
    assert!(mjcf::parse(&off).unwrap().builder.finalize::<f64>().is_ok());
}

/// Where MuJoCo reads an attribute in a way of its own, the reader follows it.
#[test]
fn mjcf_reads_ranges_box_fromto_and_zaxis_as_mujoco() {
    use adflex_kernels::articulation::mjcf::GeomShape;
    use adflex_runtime::Vec3;
    // `limited="auto"` limits only a range with lower < upper; `range="0 0"` is MuJoCo's
    // default and leaves the joint free, and a control range "0 0" clamps nothing.
    let m =
        mjcf::parse(&MJCF.replace("<joint name=\"j\"", "<joint range=\"0 0\" name=\"j\"")).unwrap();
    assert_eq!(m.builder.links()[0].joint.limits, None);
    let m = mjcf::parse(&MJCF.replace("<joint name=\"j\"", "<joint range=\"-30 45\" name=\"j\""))
        .unwrap();
    let (lo, hi) = m.builder.links()[0].joint.limits.unwrap();
    assert!((lo + 30f64.to_radians()).abs() < 1e-12 && (hi - 45f64.to_radians()).abs() < 1e-12);
    let m = mjcf::parse(&MJCF.replace(
        "</mujoco>",
        "<actuator><motor joint=\"j\" ctrlrange=\"0 0\"/></actuator></mujoco>",
    ))
    .unwrap();
    assert_eq!(m.builder.actuators()[0].ctrl_range, None);
    // A class's <motor> and <position> defaults are one actuator default, as in MuJoCo: the
    // gear and control range of a default <motor> apply to a <position>.
    let m = mjcf::parse(
        &MJCF
            .replace(
                "<mujoco>",
                "<mujoco><default><motor gear=\"3\" ctrlrange=\"-1 1\"/></default>",
            )
            .replace(
                "</mujoco>",
                "<actuator><position joint=\"j\" kp=\"2\"/></actuator></mujoco>",
            ),
    )
    .unwrap();
    let a = &m.builder.actuators()[0];
    assert_eq!(a.ctrl_range, Some((-1.0, 1.0)));
    assert_eq!(
        (a.gear, a.gain, a.bias),
        (3.0, [2.0, 0.0, 0.0], [0.0, -2.0, 0.0])
    );
    // A box from `fromto` has a square cross-section of half-side `size[0]`.
    let m = mjcf::parse(&MJCF.replace(
        "<inertial pos=\"0 0 -0.5\" mass=\"1\" diaginertia=\"0.1 0.1 0.1\"/>",
        "<geom type=\"box\" fromto=\"0 0 0 0 0 -0.4\" size=\"0.05\"/>",
    ))
    .unwrap();
    let g = m.geoms.iter().find(|g| g.link.is_some()).unwrap();
    assert_eq!(g.shape, GeomShape::Box(Vec3::new(0.05, 0.05, 0.2)));
    // An element's own orientation overrides its class's, whichever attribute each uses.
    let m = mjcf::parse(
        &MJCF
            .replace(
                "<mujoco>",
                "<mujoco><default><geom quat=\"0 1 0 0\"/></default>",
            )
            .replace(
                "</body>",
                "<geom type=\"box\" size=\"0.1 0.2 0.3\" euler=\"0 0 90\"/></body>",
            ),
    )
    .unwrap();
    let g = m.geoms.iter().find(|g| g.link.is_some()).unwrap();
    let half = std::f64::consts::FRAC_1_SQRT_2;
    assert!((g.pose.rot.coords - Quat::new(half, 0.0, 0.0, half).coords).norm() < 1e-12);
    // `zaxis="0 0 -1"` is half a turn about x, as MuJoCo's: a child body at y = 1 goes to
    // y = -1 (about y it would stay at y = 1).
    let m = mjcf::parse(&MJCF.replace(
        "quat=\"1 0 0 0\"",
        "zaxis=\"0 0 -1\"",
    ).replace(
        "</body>",
        "<body name=\"b\" pos=\"0 1 0\"><joint name=\"k\" axis=\"1 0 0\"/><inertial pos=\"0 0 0\" mass=\"1\" diaginertia=\"0.1 0.1 0.1\"/></body></body>",
    ))
    .unwrap();
    let model = m.builder.finalize::<f64>().unwrap();
    let kin = model.kinematics(&mut Tape::new(), &model.state().q);
    let b = model.links.iter().position(|l| l.name == "b").unwrap();
    let p = kin.link_p.get(b);
    assert!((p - Vec3::new(0.0, -1.0, 1.0)).norm() < 1e-12, "{p:?}");
    // Geoms outside MuJoCo's default `inertiagrouprange` (0 to 5) have no mass: a 1 kg box,
    // and a decorative sphere in group 6.
    let geoms = "<geom type=\"box\" size=\"0.1 0.1 0.1\" mass=\"1\"/>\
                 <geom type=\"sphere\" size=\"0.2\" group=\"GROUP\"/>";
    let inertial = "<inertial pos=\"0 0 -0.5\" mass=\"1\" diaginertia=\"0.1 0.1 0.1\"/>";
    for (group, mass) in [
        ("6", 1.0),
        ("5", 1.0 + 4.0 / 3.0 * std::f64::consts::PI * 0.008 * 1000.0),
    ] {
        let m = mjcf::parse(&MJCF.replace(inertial, &geoms.replace("GROUP", group))).unwrap();
        let got = m.builder.links()[0].inertial.mass;
        assert!(
            (got - mass).abs() < 1e-9,
            "group {group}: mass {got}, MuJoCo's {mass}"
        );
    }
}

/// Siblings in document order (MuJoCo's), or by joint name (Pinocchio's, through urdfdom):
/// with pin 4.1 and mujoco 4.0, this robot's joints are [alpha, zeta, mid] and [zeta, mid,
/// alpha].
#[test]
fn urdf_siblings_follow_mujoco_or_pinocchio() {
    let link = |n: &str| {
        format!(
            "<link name=\"{n}\"><inertial><mass value=\"1\"/><inertia ixx=\"1\" ixy=\"0\" \
             ixz=\"0\" iyy=\"1\" iyz=\"0\" izz=\"1\"/></inertial></link>"
        )
    };
    let joint = |n: &str, p: &str, c: &str| {
        format!(
            "<joint name=\"{n}\" type=\"revolute\"><parent link=\"{p}\"/><child \
             link=\"{c}\"/><axis xyz=\"0 0 1\"/><limit lower=\"-1\" upper=\"1\"/></joint>"
        )
    };
    let text = format!(
        "<robot name=\"t\">{}{}{}{}{}{}{}</robot>",
        link("base"),
        link("L1"),
        link("L2"),
        link("L3"),
        joint("zeta", "base", "L1"),
        joint("alpha", "base", "L2"),
        joint("mid", "L1", "L3")
    );
    for (pinocchio_order, expected) in [
        (false, ["zeta", "mid", "alpha"]),
        (true, ["alpha", "zeta", "mid"]),
    ] {
        let options = urdf::UrdfOptions {
            pinocchio_order,
            ..Default::default()
        };
        let b = urdf::parse(&text, &options).unwrap();
        let names: Vec<&str> = b.links()[1..]
            .iter()
            .map(|l| l.joint.name.as_str())
            .collect();
        assert_eq!(names, expected, "pinocchio_order {pinocchio_order}");
        assert!(b.finalize::<f64>().is_ok());
    }
    // Equal bounds leave a joint free, as MuJoCo 4.0 reads them ("limit ignored").
    let equal = text.replacen("lower=\"-1\" upper=\"1\"", "lower=\"0.3\" upper=\"0.3\"", 1);
    let m = urdf::parse(&equal, &Default::default())
        .unwrap()
        .finalize::<f64>()
        .unwrap();
    assert_eq!(m.lower.to_vec(), vec![f64::NEG_INFINITY, -1.0, -1.0]);
    assert_eq!(m.upper.to_vec(), vec![f64::INFINITY, 1.0, 1.0]);
}

#[test]
fn a_joint_that_moves_no_mass_is_refused() {
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint};
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    b.add_link(
        "a",
        None,
        Joint::revolute(Vec3::z()).name("spin"),
        Inertial::point(1.0, Vec3::zeros()),
    );
    let e = b.finalize::<f64>().unwrap_err();
    assert!(
        e.to_string().contains("joint \"spin\"") && e.to_string().contains("no mass"),
        "{e}"
    );
}

#[test]
fn link_spheres_collide_conserving_momentum_with_right_gradients() {
    use adflex_kernels::articulation::{ArticulationBuilder, GroundContact, Inertial, Joint};
    use adflex_runtime::Vec3;
    // Two free balls (two articulations), no gravity, the ground far below; the first moves
    // toward the second at 1 m/s, slightly off centre.
    let mut b = ArticulationBuilder::new();
    b.gravity = Vec3::zeros();
    for (name, x, y) in [("a", 0.0, 0.0), ("b", 0.3, 0.02)] {
        let l = b.add_link(
            name,
            None,
            Joint::free().initial(&[x, y, 0.0, 0.0, 0.0, 0.0, 1.0]),
            Inertial::sphere(1.0, 0.1, Vec3::zeros()),
        );
        b.add_contact_sphere(l, Vec3::zeros(), 0.1);
    }
    b.ground = Some(GroundContact {
        offset: -100.0,
        ke: 1e4,
        kd: 10.0,
        mu: 0.2,
        ..GroundContact::default()
    });
    b.link_contact = true;
    let model = b.finalize::<f64>().unwrap();
    assert_eq!(model.capsule_pairs.len(), 1);
    let steps = 300;
    let run = |v0: f64, tape: &mut Tape| {
        let q = Array::from_vec(model.q0.clone());
        let qd = Array::from_vec(vec![
            v0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        ]);
        let taus = vec![Array::zeros(12); steps];
        let (qf, qdf) = rollout(&model, tape, &q, &qd, &taus, 1e-3);
        (q, qd, qf, qdf)
    };
    let mut tape = Tape::new();
    let (_, qd, qf, qdf) = run(1.0, &mut tape);
    let (v, p) = (qdf.to_vec(), qf.to_vec());
    // Linear velocities in the world: the balls do not rotate much, check momentum along x.
    let rot = |s: usize| Quat::new(p[s + 6], p[s + 3], p[s + 4], p[s + 5]);
    let world = |s: usize, d: usize| {
        let r = rot(s);
        let l = Quat::new(0.0, v[d], v[d + 1], v[d + 2]);
        (r * l * r.conjugate()).imag()
    };
    let momentum = world(0, 0) + world(7, 6);
    assert!(
        (momentum.x - 1.0).abs() < 1e-9 && momentum.y.abs() < 1e-9,
        "{momentum:?}"
    );
    assert!(
        world(7, 6).x > 0.5,
        "the second ball was hit: {:?}",
        world(7, 6)
    );
    // d(final x of ball b)/d(initial speed of a) through the collision.
    let mut w = vec![0.0; 14 + 12];
    w[7] = 1.0;
    let g = tape.vjp(&[&qf, &qdf], &w, &[&qd]).unwrap()[0];
    let f = |v0: f64| run(v0, &mut Tape::new()).2.get(7);
    let fd = (f(1.0 + 1e-6) - f(1.0 - 1e-6)) / 2e-6;
    assert!((g - fd).abs() < 1e-4 * fd.abs().max(1e-2), "{g} vs {fd}");
}

#[test]
fn a_spinning_free_body_keeps_its_world_velocity() {
    // No force: the centre of mass... here the link origin (the box's centre of mass is off
    // it by 5 cm) moves with the body, so check the centre of mass's world velocity instead.
    let model = spinning_box();
    model.gravity.set(0, adflex_runtime::Vec3::zeros());
    let mut tape = Tape::new();
    let mut s = model.state();
    s.qd.assign(&[0.3, -0.2, 0.5, 4.0, 1.0, -2.0]);
    let com = model.com.get(0);
    let com_velocity = |s: &adflex_kernels::articulation::ArticulationState<f64>| {
        let (q, v) = (s.q.to_vec(), s.qd.to_vec());
        let r = Quat::new(q[6], q[3], q[4], q[5]);
        let w = adflex_runtime::Vec3::new(v[3], v[4], v[5]);
        let local = adflex_runtime::Vec3::new(v[0], v[1], v[2]) + w.cross(&com);
        (r * Quat::from_imag(local) * r.conjugate()).imag()
    };
    let start = com_velocity(&s);
    for _ in 0..2000 {
        s = model.step(&mut tape, &s, None, 1e-3).unwrap();
    }
    let end = com_velocity(&s);
    assert!(
        (end - start).norm() < 2e-3 * start.norm(),
        "{start:?} -> {end:?}"
    );
}

#[test]
fn a_muscle_lifts_a_pendulum_with_right_gradients() {
    use adflex_kernels::articulation::{
        ArticulationBuilder, ArticulationControl, Inertial, Joint, Muscle,
    };
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    let base = b.add_link("base", None, Joint::fixed(), Inertial::massless());
    let pole = b.add_link(
        "pole",
        Some(base),
        Joint::revolute(Vec3::y()).name("hinge"),
        Inertial::sphere(1.0, 0.05, Vec3::new(0.0, 0.0, -0.5)),
    );
    b.add_muscle(Muscle {
        name: "lifter".into(),
        origin: (base, Vec3::new(0.3, 0.0, 0.2)),
        insertion: (pole, Vec3::new(0.0, 0.0, -0.3)),
        f_max: 50.0,
        l_opt: 0.4,
        tendon_slack: 0.1,
        v_max: 10.0,
    });
    let model = b.finalize::<f64>().unwrap();
    let steps = 400;
    let run = |a: f64, tape: &mut Tape| {
        let act = Array::from_vec(vec![a]);
        let mut s = model.state();
        let c = ArticulationControl {
            activation: act.clone(),
            ..model.control()
        };
        for _ in 0..steps {
            s = model.step(tape, &s, Some(&c), 1e-3).unwrap();
        }
        (act, s)
    };
    // Passive: it swings a little (the tendon is stretched); active: it is pulled toward the
    // origin's side (a rotation about +y moving the bob toward +x is negative).
    let passive = run(0.0, &mut Tape::new()).1.q.get(0);
    let mut tape = Tape::new();
    let (act, s) = run(0.5, &mut tape);
    let active = s.q.get(0);
    assert!(active < passive - 0.1, "active {active}, passive {passive}");
    let g = tape.vjp(&[&s.q], &[1.0], &[&act]).unwrap()[0];
    let f = |a: f64| run(a, &mut Tape::new()).1.q.get(0);
    let fd = (f(0.5 + 1e-6) - f(0.5 - 1e-6)) / 2e-6;
    assert!((g - fd).abs() < 1e-6 * fd.abs().max(1e-3), "{g} vs {fd}");
}

#[test]
fn the_same_robot_runs_in_f32() {
    // The arm, swinging under gravity from a bent pose (no limit reached).
    let path = format!("{ROBOTS}/arm7.urdf");
    let b = urdf::load(&path, &Default::default()).unwrap();
    let mut m64: Articulations<f64> = b.finalize().unwrap();
    let mut m32: Articulations<f32> = b.finalize().unwrap();
    m64.q0 = vec![0.3; 7];
    m32.q0 = vec![0.3; 7];
    let (mut s64, mut s32) = (m64.state(), m32.state());
    let (mut t64, mut t32) = (Tape::new(), Tape::new());
    for _ in 0..200 {
        s64 = m64.step(&mut t64, &s64, None, 1e-3).unwrap();
        s32 = m32.step(&mut t32, &s32, None, 1e-3).unwrap();
    }
    let (a, b) = (s64.q.to_vec(), s32.q.to_vec());
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - *y as f64).abs())
        .fold(0.0, f64::max);
    assert!(worst < 1e-4, "f32 and f64 differ by {worst}");
}

#[test]
fn urdf_quadruped_stands_on_its_collision_spheres_with_right_gradients() {
    use adflex_kernels::articulation::GroundContact;
    let options = urdf::UrdfOptions {
        floating_base: true,
        collisions: true,
        ..Default::default()
    };
    let mut b = urdf::load(format!("{ROBOTS}/quadruped.urdf"), &options).unwrap();
    assert_eq!(b.contacts().len(), 8 + 4, "a box's corners and four feet");
    b.ground = Some(GroundContact::default());
    let mut model: Articulations<f64> = b.finalize().unwrap();
    model.q0[2] = 0.25; // the torso 25 cm up
    let n = model.n_dof;
    let steps = 400;
    let mut rng = adflex_testkit::Rng(3);
    let taus0: Vec<Vec<f64>> = (0..steps)
        .map(|_| {
            (0..n)
                .map(|d| if d < 6 { 0.0 } else { rng.uniform(-0.2, 0.2) })
                .collect()
        })
        .collect();
    let q0 = model.q0.clone();
    let qf = check_torque_gradients(&model, &q0, &vec![0.0; n], &taus0, 1e-3, 2, &mut rng);
    let z = qf[2];
    assert!(
        z > 0.05 && z < 0.25,
        "torso height {z}: it stands on its feet"
    );
}

#[test]
fn urdf_collisions_outside_the_shapes_are_refused_when_read() {
    let with_mesh = URDF.replace(
        "<link name=\"b\">",
        "<link name=\"b\"><collision><geometry><mesh filename=\"b.stl\"/></geometry></collision>",
    );
    // Ignored by default (meshes are most robots' collision geometry)...
    assert!(urdf::parse(&with_mesh, &Default::default()).is_ok());
    // ... and refused, naming the element and line, when contact shapes are asked for.
    let options = urdf::UrdfOptions {
        collisions: true,
        ..Default::default()
    };
    let e = urdf::parse(&with_mesh, &options).unwrap_err();
    assert_eq!(e.line, Some(3), "{e}");
    assert!(e.to_string().contains("<mesh>"), "{e}");
}

#[test]
fn checkpointed_robot_rollouts_give_the_whole_tapes_gradients() {
    use adflex_kernels::articulation::ArticulationControl;
    use adflex_runtime::checkpoint::checkpointed;
    let model = load("arm7.urdf", false);
    let tau = Array::from_vec(vec![0.3, -0.2, 0.1, 0.4, -0.1, 0.2, 0.05]).requires_grad();
    let control = ArticulationControl {
        tau: tau.clone(),
        ..model.control()
    };
    let step = |tape: &mut Tape, s: &adflex_kernels::articulation::ArticulationState<f64>| {
        model.step(tape, s, Some(&control), 1e-3)
    };
    let loss = |tape: &mut Tape, s: &adflex_kernels::articulation::ArticulationState<f64>| {
        let l = Array::zeros(1);
        adflex_kernels::losses::sum_of_squares(tape, &s.q, 1.0, &l);
        Ok(l)
    };
    // The whole tape.
    let mut tape = Tape::new();
    let mut s = model.state();
    for _ in 0..200 {
        s = step(&mut tape, &s).unwrap();
    }
    let l = loss(&mut tape, &s).unwrap();
    tape.backward(&l).unwrap();
    let whole = tau.grad().unwrap().to_vec();
    // Checkpointed every 20 steps.
    tau.zero_grad();
    let out = checkpointed(&model.state(), 200, 20, step, loss).unwrap();
    assert_eq!(out.loss.get(0), l.get(0));
    assert_eq!(tau.grad().unwrap().to_vec(), whole, "bit for bit");
    assert!(whole.iter().any(|g| *g != 0.0));
}

/// A directory of its own under the system's temporary one, for files a test writes.
fn scratch_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("adflex-{name}-{}", std::process::id()));
    std::fs::create_dir_all(d.join("parts")).unwrap();
    d
}

#[test]
fn mjcf_reads_includes_ref_flags_margins_and_walls_as_mujoco() {
    use adflex_kernels::articulation::{ArticulationState, JointType};
    // `<include>`: the included file's elements in its place, nested includes relative to the
    // main file's directory (as MuJoCo), and an error in an included file names that file.
    let dir = scratch_dir("mjcf-include");
    let write = |f: &str, t: &str| std::fs::write(dir.join(f), t).unwrap();
    write(
        "parts/defaults.xml",
        "<mujocoinclude>\n  <default><joint damping=\"0.7\"/></default>\n  \
         <include file=\"parts/option.xml\"/>\n</mujocoinclude>",
    );
    write(
        "parts/option.xml",
        "<mujocoinclude><option timestep=\"0.004\"/></mujocoinclude>",
    );
    let main = MJCF.replace(
        "<mujoco>",
        "<mujoco>\n<include file=\"parts/defaults.xml\"/>",
    );
    write("main.xml", &main);
    let m = mjcf::load(dir.join("main.xml")).unwrap();
    assert_eq!(m.timestep, Some(0.004));
    assert_eq!(m.builder.links()[0].joint.damping, 0.7);
    write(
        "parts/option.xml",
        "<mujocoinclude>\n\n<option timestep=\"0.004\" tolerence=\"1\"/></mujocoinclude>",
    );
    let e = mjcf::load(dir.join("main.xml")).unwrap_err();
    assert!(e.file.as_deref().unwrap().ends_with("option.xml"), "{e}");
    assert_eq!(e.line, Some(3), "{e}");
    // An error after the included lines still names the main file's own line.
    write(
        "main.xml",
        &main.replace("type=\"hinge\"", "type=\"screw\""),
    );
    write(
        "parts/option.xml",
        "<mujocoinclude><option timestep=\"0.004\"/></mujocoinclude>",
    );
    let e = mjcf::load(dir.join("main.xml")).unwrap_err();
    assert!(e.file.as_deref().unwrap().ends_with("main.xml"), "{e}");
    assert_eq!(e.line, Some(5), "{e}");
    write("main.xml", &main.replace("defaults.xml", "missing.xml"));
    let e = mjcf::load(dir.join("main.xml")).unwrap_err();
    assert!(
        e.to_string().contains("missing.xml") && e.line == Some(2),
        "{e}"
    );
    write(
        "parts/defaults.xml",
        "<mujocoinclude><include file=\"parts/defaults.xml\"/></mujocoinclude>",
    );
    write("main.xml", &main);
    let e = mjcf::load(dir.join("main.xml")).unwrap_err();
    assert!(e.to_string().contains("includes itself"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();

    // `ref`: the body is where the file puts it when the coordinate equals ref, which is
    // the initial coordinate (the hopper's are checked against MuJoCo's M, bias and qdd in
    // `dynamics_agree_with_pinocchio_and_mujoco`).
    let with_ref = |r: &str| {
        let xml = MJCF
            .replace("type=\"hinge\"", &format!("type=\"hinge\" ref=\"{r}\""))
            .replace("</body>", "<body name=\"b\" pos=\"0.3 0 -1\"><joint name=\"s\" type=\"slide\" axis=\"1 0 0\" ref=\"0.2\"/><inertial pos=\"0 0 0\" mass=\"1\" diaginertia=\"0.1 0.1 0.1\"/></body></body>");
        mjcf::parse(&xml)
            .unwrap()
            .builder
            .finalize::<f64>()
            .unwrap()
    };
    let (a, b) = (with_ref("30"), with_ref("0"));
    assert!((a.q0[0] - 30f64.to_radians()).abs() < 1e-15);
    assert_eq!(a.q0[1], 0.2);
    let mut tape = Tape::new();
    let (qa, qb) = (Array::from_vec(a.q0.clone()), Array::from_vec(b.q0.clone()));
    let (ka, kb) = (a.kinematics(&mut tape, &qa), b.kinematics(&mut tape, &qb));
    for l in 0..2 {
        let (pa, pb) = (ka.link_p.get(l), kb.link_p.get(l));
        assert!((pa - pb).norm() < 1e-12, "link {l}: {pa:?} vs {pb:?}");
    }

    // Flags: what they switch off is off; a limit's margin shrinks its range (MuJoCo's limit
    // pushes back to `margin` inside it; in radians for a hinge, as MuJoCo reads it).
    let floor = MJCF.replace(
        "<worldbody>",
        "<worldbody><geom type=\"plane\" size=\"1 1 1\"/>",
    );
    let flagged = |f: &str| {
        let xml = floor
            .replace(
                "<worldbody>",
                &format!("<option><flag {f}/></option><worldbody>"),
            )
            .replace("<joint name", "<joint range=\"-60 60\" margin=\"0.1\" name");
        mjcf::parse(&xml).unwrap().builder
    };
    let on = flagged("energy=\"enable\"");
    assert!(on.ground.is_some() && on.link_contact && on.gravity.z < 0.0);
    let (lo, hi) = on.links()[0].joint.limits.unwrap();
    assert!(
        (lo - (0.1 - 60f64.to_radians())).abs() < 1e-15
            && (hi - (60f64.to_radians() - 0.1)).abs() < 1e-15
    );
    let off = flagged("contact=\"disable\"");
    assert!(off.ground.is_none() && !off.link_contact);
    assert_eq!(flagged("gravity=\"disable\"").gravity.norm(), 0.0);
    assert_eq!(flagged("limit=\"disable\"").links()[0].joint.limits, None);
    let c = flagged("constraint=\"disable\"");
    assert!(c.ground.is_none() && c.links()[0].joint.limits.is_none());

    // MuJoCo's limit law: the time constant (`solreflimit`; a step keeps it at least twice
    // its `dt` unless `refsafe` is off) and impedance (`solimplimit`), scaled by the joint's
    // inertia as a limit sees it, 1 / (M^-1)[0][0] = 0.1 + 1 * 0.5^2 here.
    let limit = |extra: &str, option: &str| {
        let xml = MJCF
            .replace("<worldbody>", &format!("{option}<worldbody>"))
            .replace(
                "<joint name",
                &format!("<joint range=\"-30 30\" {extra} name"),
            );
        let m = mjcf::parse(&xml)
            .unwrap()
            .builder
            .finalize::<f64>()
            .unwrap();
        assert_eq!(m.limit_m.get(0), 0.1 + 0.25);
        (m.limit_k.get(0), m.limit_b.get(0), m.limit_imp.get(0))
    };
    let inertia = 0.1 + 0.25;
    let (k, b, imp) = limit("", "");
    assert!(
        (k - inertia / (0.95f64 * 0.02).powi(2)).abs() < 1e-9 * k,
        "{k}"
    );
    assert!((b - 2.0 * inertia / (0.95 * 0.02)).abs() < 1e-9 * b, "{b}");
    assert_eq!((imp.x, imp.y, imp.z), (0.9, 0.95, 0.001));
    let refsafe = |option: &str| {
        let xml = MJCF.replace("<worldbody>", &format!("{option}<worldbody>"));
        mjcf::parse(&xml).unwrap().builder.limit_refsafe
    };
    assert!(refsafe(""));
    assert!(!refsafe("<option><flag refsafe=\"disable\"/></option>"));
    let (k, b, imp) = limit("solreflimit=\"0.03 0.5\" solimplimit=\"0 0.8 0.03\"", "");
    assert!(
        (k - inertia / (0.8f64 * 0.03 * 0.5).powi(2)).abs() < 1e-9 * k,
        "{k}"
    );
    assert!((b - 2.0 * inertia / (0.8 * 0.03)).abs() < 1e-9 * b, "{b}");
    assert_eq!((imp.x, imp.y, imp.z), (1e-4, 0.8, 0.03));

    // `settotalmass` scales every body's mass and inertia to the total.
    let total = mjcf::parse(&MJCF.replace("<mujoco>", "<mujoco><compiler settotalmass=\"7\"/>"))
        .unwrap()
        .builder;
    assert_eq!(total.links()[0].inertial.mass, 7.0);
    assert!((total.links()[0].inertial.inertia[(0, 0)] - 0.7).abs() < 1e-15);

    // A second plane is a wall, a box in the worldbody a post: a ball sliding into the wall
    // stops there and comes back; a geom that touches nothing is not a shape.
    let xml = r#"<mujoco>
  <worldbody>
    <geom type="plane" size="5 5 .1"/>
    <geom name="wall" type="plane" pos="1 0 0" zaxis="-1 0 0"/>
    <geom name="post" type="box" pos="-1 0 0.5" size="0.1 0.1 0.5"/>
    <geom name="rail" type="capsule" fromto="-1 1 0 1 1 0" size="0.02" contype="0" conaffinity="0"/>
    <body name="ball" pos="0 0 0.5">
      <joint name="x" type="slide" axis="1 0 0"/>
      <geom type="sphere" size="0.1" mass="1"/>
    </body>
  </worldbody>
</mujoco>"#;
    let b = mjcf::parse(xml).unwrap().builder;
    let world = b.find("world").unwrap();
    assert_eq!(b.links()[world.0].joint.kind, JointType::Fixed);
    assert_eq!(
        b.contact_shapes()
            .iter()
            .filter(|s| s.link == world)
            .count(),
        2
    );
    let model = b.finalize::<f64>().unwrap();
    for (v0, wall) in [(1.0, 1.0), (-1.0, -0.9)] {
        let mut s = ArticulationState {
            q: Array::from_vec(vec![0.0]),
            qd: Array::from_vec(vec![v0]),
        };
        let (mut reach, mut tape) = (0.0f64, Tape::new());
        for _ in 0..1000 {
            s = model
                .step(&mut tape, &s, Some(&model.control()), 1e-3)
                .unwrap();
            reach = if v0 > 0.0 {
                reach.max(s.q.get(0))
            } else {
                reach.min(s.q.get(0))
            };
        }
        let face = wall - 0.1f64.copysign(v0);
        assert!(
            (reach - face).abs() < 0.04,
            "the ball reached {reach}, the face is at {face}"
        );
        assert!(s.qd.get(0) * v0 < 0.0, "it bounced back: {}", s.qd.get(0));
    }
}

/// A steady load pressing a joint into a time-constant limit is cancelled as by MuJoCo's soft
/// constraint: at rest the joint sags `r = (1 - d) a0 / (d^2 k)` past the limit (`a0` the
/// load's acceleration, `d` the impedance at `r`, `k = 1 / (dmax tc zeta)^2`), not the
/// `a0 / (d^2 k)` of a spring of the same stiffness.
#[test]
fn a_load_on_a_time_constant_limit_sags_as_under_mujocos_constraint() {
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint};
    use adflex_runtime::Vec3;
    // A point mass 0.5 m below a hinge about y, gravity along x: it presses into -0.2.
    let mut b = ArticulationBuilder::new();
    b.gravity = Vec3::new(9.81, 0.0, 0.0);
    let j = Joint::revolute(Vec3::y())
        .limits(-0.2, 0.2)
        .limit_time_constant(0.02, 1.0);
    b.add_link(
        "pole",
        None,
        j,
        Inertial::point(1.5, Vec3::new(0.0, 0.0, -0.5)),
    );
    let model = b.finalize::<f64>().unwrap();
    let mut s = model.state();
    let c = model.control();
    for _ in 0..2000 {
        s = model.step(&mut Tape::new(), &s, Some(&c), 2e-3).unwrap();
    }
    let (q, r) = (s.q.get(0), s.q.get(0) + 0.2);
    assert!(s.qd.get(0).abs() < 1e-9, "at rest: {}", s.qd.get(0));
    // The load's acceleration there (torque over inertia) and MuJoCo's impedance at `r`.
    let a0 = -9.81 * q.cos() / 0.5;
    let (dmin, dmax, width) = (0.9, 0.95, 0.001);
    let w = (r.abs() / width).min(1.0);
    let y = if w > 0.5 {
        1.0 - 2.0 * (1.0 - w).powi(2)
    } else {
        2.0 * w * w
    };
    let d = dmin + y * (dmax - dmin);
    let k = 1.0 / (dmax * 0.02f64).powi(2);
    let expected = (1.0 - d) * a0 / (d * d * k);
    println!(
        "sag {r:.6e}, MuJoCo's law {expected:.6e}, a spring's {:.3e}",
        a0 / (d * d * k)
    );
    assert!(
        r < 0.0 && (r - expected).abs() < 1e-9 * expected.abs().max(1e-3),
        "{r} vs {expected}"
    );
}

#[test]
fn limits_with_a_time_constant_come_back_alike_for_light_and_heavy_links_at_any_step() {
    use adflex_kernels::articulation::{
        ArticulationBuilder, ArticulationControl, ArticulationIntegrator, ArticulationState,
        Inertial, Joint,
    };
    use adflex_runtime::Vec3;
    // A pendulum started 0.5 rad past its upper limit 0.1, a weak gravity along x pulling it
    // towards its lower limit (the same acceleration whatever its mass; without a load, the
    // steps past half the time constant land it exactly on the other limit, where rounding
    // decides whether it touches).
    let pendulum = |mass: f64, tc: Option<f64>| {
        let mut b = ArticulationBuilder::new();
        b.gravity = Vec3::new(2.0, 0.0, 0.0);
        let mut j = Joint::revolute(Vec3::y()).limits(-0.1, 0.1);
        if let Some(tc) = tc {
            j = j.limit_time_constant(tc, 1.0);
        }
        b.add_link(
            "pole",
            None,
            j,
            Inertial::point(mass, Vec3::new(0.0, 0.0, -0.5)),
        );
        b.finalize::<f64>().unwrap()
    };
    let run = |model: &Articulations<f64>, q0: f64, dt: f64, t: f64| -> Vec<f64> {
        let mut s = ArticulationState {
            q: Array::from_vec(vec![q0]),
            qd: Array::from_vec(vec![0.0]),
        };
        let c: ArticulationControl<f64> = model.control();
        let mut tape = Tape::new();
        let mut out = Vec::new();
        for _ in 0..(t / dt).round() as usize {
            s = model.step(&mut tape, &s, Some(&c), dt).unwrap();
            out.push(s.q.get(0));
        }
        out
    };
    let tc = 0.02;
    // Each integrator, at steps under and over half the time constant (RK4's stages take
    // `refsafe` at the step's `dt` too).
    let integrators = [
        ArticulationIntegrator::Euler,
        ArticulationIntegrator::Rk4,
        ArticulationIntegrator::ImplicitFast,
    ];
    for (integrator, dt) in integrators
        .into_iter()
        .flat_map(|i| [1e-3, 0.01, 0.05].map(|dt| (i, dt)))
    {
        let by = |mut model: Articulations<f64>| {
            model.integrator = integrator;
            model
        };
        let light = run(&by(pendulum(1e-3, Some(tc))), 0.6, dt, 0.3);
        let heavy = run(&by(pendulum(1e3, Some(tc))), 0.6, dt, 0.3);
        let case = format!("{integrator:?}, dt {dt}");
        // The same motion whatever the inertia (to rounding).
        for (a, b) in light.iter().zip(&heavy) {
            assert!(
                (a - b).abs() < 1e-12,
                "{case}: light {a} vs heavy {b}\n{light:?}\n{heavy:?}"
            );
        }
        // MuJoCo's constraint only pushes: the joint comes back into its range within a few
        // time constants (at least `2 dt`, MuJoCo's `refsafe`, so stable at a step 2.5 times
        // the time constant too), and never goes farther out than it started.
        let tc_step = tc.max(2.0 * dt);
        let back = light.iter().position(|&x| x < 0.1);
        println!("{case}: back in the range after {back:?} steps");
        assert!(
            back.is_some_and(|k| (k + 1) as f64 * dt <= 5.0 * tc_step),
            "{case}: not back within 5 time constants: {light:?}"
        );
        assert!(
            light.iter().all(|x| x.abs() <= 0.6 + 1e-9),
            "{case}: {light:?}"
        );
    }
    // The builder's one stiffness for every joint: in 50 ms a light link is back, a heavy one
    // has hardly moved (the behaviour the time constant avoids).
    let light = run(&pendulum(1e-3, None), 0.6, 1e-4, 0.05);
    let heavy = run(&pendulum(1e3, None), 0.6, 1e-4, 0.05);
    let (l, h) = (light.last().unwrap(), heavy.last().unwrap());
    assert!(
        *l < 0.11 && *h > 0.5,
        "penalty limit: light at {l}, heavy at {h}"
    );

    // Gradients through the limit: d q(T) / d q0 and d q(T) / d mass against central
    // differences, and forward mode against reverse.
    let model = pendulum(2.0, Some(tc));
    let loss_at = |q0: f64, m: f64| -> f64 {
        let model = Articulations {
            mass: Array::from_vec(vec![m]),
            ..model.clone()
        };
        *run(&model, q0, 0.01, 0.05).last().unwrap()
    };
    let q0 = Array::from_vec(vec![0.35]);
    let mut tape = Tape::new();
    let mut s = ArticulationState {
        q: q0.clone(),
        qd: Array::from_vec(vec![0.0]),
    };
    let c = model.control();
    for _ in 0..5 {
        s = model.step(&mut tape, &s, Some(&c), 0.01).unwrap();
    }
    let g = tape.vjp(&[&s.q], &[1.0], &[&q0, &model.mass]).unwrap();
    let h = 1e-6;
    let fd = [
        (loss_at(0.35 + h, 2.0) - loss_at(0.35 - h, 2.0)) / (2.0 * h),
        (loss_at(0.35, 2.0 + h) - loss_at(0.35, 2.0 - h)) / (2.0 * h),
    ];
    println!("through the limit: {g:?} vs central differences {fd:?}");
    // (The limit's stiffness is fixed when the model is built: a later mass edit matters.)
    for k in 0..2 {
        assert!(
            (g[k] - fd[k]).abs() < 1e-6 * fd[k].abs().max(1e-2),
            "{g:?} vs {fd:?}"
        );
    }
    let jv = tape.jvp(&[&q0, &model.mass], &[1.0, 0.3], &[&s.q]).unwrap();
    assert!(
        (jv[0] - (g[0] + 0.3 * g[1])).abs() < 1e-9,
        "{jv:?} vs {g:?}"
    );
}

#[test]
fn a_fluid_propels_a_swimmer_with_right_gradients_of_density_viscosity_and_wind() {
    use adflex_kernels::articulation::{ArticulationControl, ArticulationState};
    // The swimmer's fluid forces are checked against MuJoCo's in
    // `dynamics_agree_with_pinocchio_and_mujoco` (its step's passive forces).
    let model = load("swimmer.xml", false);
    assert!(model.fluid_on);
    let n = model.n_dof;
    let dt = 0.01;
    // A travelling wave along the body.
    let taus = |steps: usize| -> Vec<Array<f64>> {
        (0..steps)
            .map(|k| {
                let t = k as f64 * dt;
                let mut tau = vec![0.0; n];
                tau[3] = 0.3 * (6.0 * t).sin();
                tau[4] = 0.3 * (6.0 * t - 1.2).sin();
                Array::from_vec(tau)
            })
            .collect()
    };
    let roll = |m: &Articulations<f64>, tape: &mut Tape, taus: &[Array<f64>]| {
        let mut s = m.state();
        for tau in taus {
            let c = ArticulationControl {
                tau: tau.clone(),
                ..m.control()
            };
            s = m.step(tape, &s, Some(&c), dt).unwrap();
        }
        s
    };
    // It swims: its centre of mass moves in the fluid; in empty space (no fluid) internal
    // torques cannot move it (but for the step's drift, O(dt): about 1 mm here).
    let com = |m: &Articulations<f64>, q: &Array<f64>| -> nalgebra::Vector3<f64> {
        let k = m.kinematics(&mut Tape::new(), q);
        let (mut first, mut total) = (nalgebra::Vector3::zeros(), 0.0);
        for l in 0..m.n_links() {
            let r = nalgebra::UnitQuaternion::from_quaternion(k.link_r.get(l));
            first += (k.link_p.get(l) + r * m.com.get(l)) * m.mass.get(l);
            total += m.mass.get(l);
        }
        first / total
    };
    let long = taus(600);
    let start = com(&model, &model.state().q);
    let swim = (com(&model, &roll(&model, &mut Tape::new(), &long).q) - start).norm();
    let dry = Articulations {
        fluid_on: false,
        ..model.clone()
    };
    let still = (com(&dry, &roll(&dry, &mut Tape::new(), &long).q) - start).norm();
    println!("centre of mass moved {swim:.4} m in 6 s in the fluid, {still:.1e} m without");
    assert!(swim > 0.05 && still < 0.1 * swim, "{swim} vs {still}");

    // Gradients of the final state with respect to density, viscosity and wind.
    let short = taus(120);
    let mut tape = Tape::new();
    let s = roll(&model, &mut tape, &short);
    let mut rng = adflex_testkit::Rng(3);
    let w: Vec<f64> = (0..model.n_q + n).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let params: [&dyn adflex_runtime::AnyArray; 3] =
        [&model.fluid_density, &model.fluid_viscosity, &model.wind];
    let g = tape.vjp(&[&s.q, &s.qd], &w, &params).unwrap();
    let loss = |d: f64, v: f64, wind: [f64; 3]| -> f64 {
        let m = Articulations {
            fluid_density: Array::from_vec(vec![d]),
            fluid_viscosity: Array::from_vec(vec![v]),
            wind: Array::from_vec(vec![adflex_runtime::Vec3::new(wind[0], wind[1], wind[2])]),
            ..model.clone()
        };
        let s: ArticulationState<f64> = roll(&m, &mut Tape::new(), &short);
        let f: Vec<f64> = s.q.to_vec().into_iter().chain(s.qd.to_vec()).collect();
        f.iter().zip(&w).map(|(a, b)| a * b).sum()
    };
    let (d0, v0) = (model.fluid_density.get(0), model.fluid_viscosity.get(0));
    let w0 = model.wind.get(0);
    let w0 = [w0.x, w0.y, w0.z];
    let mut worst = 0.0f64;
    for (k, scale) in [(0, d0), (1, v0), (2, 1.0), (3, 1.0), (4, 1.0)] {
        let h = 1e-6 * scale;
        let at = |sign: f64| {
            let mut p = (d0, v0, w0);
            match k {
                0 => p.0 += sign * h,
                1 => p.1 += sign * h,
                _ => p.2[k - 2] += sign * h,
            }
            loss(p.0, p.1, p.2)
        };
        let fd = (at(1.0) - at(-1.0)) / (2.0 * h);
        worst = worst.max((fd - g[k]).abs() / fd.abs().max(1e-3));
        println!(
            "d loss / d fluid parameter {k}: {:.6e} vs central differences {fd:.6e}",
            g[k]
        );
    }
    assert!(worst < 1e-6, "{worst:.2e}");
    // Forward mode against reverse mode.
    let v = [0.3, -0.7, 0.2, 0.5, -0.1];
    let jv = tape.jvp(&params, &v, &[&s.q, &s.qd]).unwrap();
    let lhs: f64 = jv.iter().zip(&w).map(|(a, b)| a * b).sum();
    let rhs: f64 = g.iter().zip(&v).map(|(a, b)| a * b).sum();
    assert!(
        (lhs - rhs).abs() < 1e-9 * rhs.abs().max(1.0),
        "{lhs} vs {rhs}"
    );
}

/// MuJoCo's actuators (motor with clamped control and force, position and velocity servos, a
/// general one with affine gain and bias, a motor on a fixed tendon, a damper) and passive tendons
/// (a spring and damper, a dead band): the gradients of a rollout with respect to the controls and
/// every actuator and tendon parameter against central differences and forward mode; a control
/// clamped by its range gets no gradient; each world's controls drive its own robot.
/// By each integrator: Euler, RK4 and implicitfast (whose solve has the actuators' and
/// tendons' damping, so their gradients flow through the mass matrix too).
#[test]
fn actuators_have_right_gradients_clamp_and_stay_in_their_worlds() {
    use adflex_kernels::articulation::ArticulationIntegrator::*;
    for integrator in [Euler, Rk4, ImplicitFast] {
        check_actuators(integrator);
    }
}

fn check_actuators(integrator: adflex_kernels::articulation::ArticulationIntegrator) {
    use adflex_kernels::articulation::{ArticulationControl, Articulations};
    let mut b = mjcf::load(format!("{ROBOTS}/servo_arm.xml"))
        .unwrap()
        .builder;
    (b.ground, b.link_contact) = (None, false);
    b.integrator = integrator;
    let model = b.finalize::<f64>().unwrap();
    assert_eq!(model.actuator_names[3], "wrist_general");
    // The last control is past its range (-2, 2): clamped, so its gradient is 0.
    let ctrl0 = [0.5, 0.9, 0.7, 2.5, -0.6, 0.4];
    let (na, nc) = (ctrl0.len(), model.act_coef.len());
    assert_eq!((model.act_gear.len(), nc), (na, na + 1));
    let (steps, dt) = (150, 2e-3);
    let w: Vec<f64> = (0..model.n_q + model.n_dof)
        .map(|i| (i as f64 * 0.7).sin())
        .collect();
    let flat = |a: &Array<adflex_runtime::Vec3<f64>>| -> Vec<f64> {
        a.to_vec().iter().flat_map(|v| [v.x, v.y, v.z]).collect()
    };
    // Inputs, flattened: ctrl, gear, gain, bias, tendon coefficients, damping, and the
    // passive tendons' stiffness, damping and rest lengths.
    let nt = model.tendon_stiffness.len();
    assert_eq!(nt, 2);
    let p0: Vec<f64> = ctrl0
        .iter()
        .copied()
        .chain(model.act_gear.to_vec())
        .chain(flat(&model.act_gain))
        .chain(flat(&model.act_bias))
        .chain(model.act_coef.to_vec())
        .chain(model.damping.to_vec())
        .chain(model.tendon_stiffness.to_vec())
        .chain(model.tendon_damping.to_vec())
        .chain(model.tendon_rest_lo.to_vec())
        .chain(model.tendon_rest_hi.to_vec())
        .collect();
    let at = |k: usize| {
        let d = 8 * na + nc + 4;
        [
            0,
            na,
            2 * na,
            5 * na,
            8 * na,
            8 * na + nc,
            d,
            d + nt,
            d + 2 * nt,
            d + 3 * nt,
        ][k]
    };
    let arrays = |p: &[f64]| {
        let v3 = |x: &[f64]| {
            Array::from_vec(
                x.chunks(3)
                    .map(|c| adflex_runtime::Vec3::new(c[0], c[1], c[2]))
                    .collect(),
            )
        };
        let m = Articulations {
            act_gear: Array::from_vec(p[at(1)..at(2)].to_vec()),
            act_gain: v3(&p[at(2)..at(3)]),
            act_bias: v3(&p[at(3)..at(4)]),
            act_coef: Array::from_vec(p[at(4)..at(5)].to_vec()),
            damping: Array::from_vec(p[at(5)..at(6)].to_vec()),
            tendon_stiffness: Array::from_vec(p[at(6)..at(7)].to_vec()),
            tendon_damping: Array::from_vec(p[at(7)..at(8)].to_vec()),
            tendon_rest_lo: Array::from_vec(p[at(8)..at(9)].to_vec()),
            tendon_rest_hi: Array::from_vec(p[at(9)..].to_vec()),
            ..model.clone()
        };
        (Array::from_vec(p[..na].to_vec()), m)
    };
    let run = |tape: &mut Tape, ctrl: &Array<f64>, m: &Articulations<f64>| {
        let control = ArticulationControl {
            ctrl: ctrl.clone(),
            ..m.control()
        };
        let mut s = m.state();
        for _ in 0..steps {
            s = m.step(tape, &s, Some(&control), dt).unwrap();
        }
        s
    };
    let loss = |p: &[f64]| {
        let (ctrl, m) = arrays(p);
        let s = run(&mut Tape::new(), &ctrl, &m);
        let f: Vec<f64> = s.q.to_vec().into_iter().chain(s.qd.to_vec()).collect();
        f.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
    };
    let (ctrl, m) = arrays(&p0);
    let mut tape = Tape::new();
    let s = run(&mut tape, &ctrl, &m);
    let inputs: [&dyn adflex_runtime::AnyArray; 10] = [
        &ctrl,
        &m.act_gear,
        &m.act_gain,
        &m.act_bias,
        &m.act_coef,
        &m.damping,
        &m.tendon_stiffness,
        &m.tendon_damping,
        &m.tendon_rest_lo,
        &m.tendon_rest_hi,
    ];
    let g = tape.vjp(&[&s.q, &s.qd], &w, &inputs).unwrap();
    assert_eq!(g.len(), p0.len());
    assert_eq!(g[3], 0.0, "a clamped control has no gradient");
    // (Relative to the largest gradient below a hundredth of it: central differences'
    // rounding is about 1e-9 here.)
    let gmax = g.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let mut worst = 0.0f64;
    for k in 0..p0.len() {
        let h = 1e-6 * p0[k].abs().max(1.0);
        let mut p = p0.clone();
        p[k] += h;
        let up = loss(&p);
        p[k] -= 2.0 * h;
        let fd = (up - loss(&p)) / (2.0 * h);
        worst = worst.max((fd - g[k]).abs() / fd.abs().max(1e-2 * gmax));
    }
    println!("{integrator:?}: actuator gradients against central differences: {worst:.1e}");
    assert!(worst < 1e-6, "{worst:.2e}");
    assert!(
        g[..3].iter().chain(&g[4..5]).all(|x| x.abs() > 1e-3),
        "{g:?}"
    );
    // Forward mode against reverse mode.
    let v: Vec<f64> = (0..p0.len()).map(|i| (i as f64 * 1.3).cos()).collect();
    let jv = tape.jvp(&inputs, &v, &[&s.q, &s.qd]).unwrap();
    let lhs: f64 = jv.iter().zip(&w).map(|(a, b)| a * b).sum();
    let rhs: f64 = g.iter().zip(&v).map(|(a, b)| a * b).sum();
    assert!(
        (lhs - rhs).abs() < 1e-9 * rhs.abs().max(1.0),
        "{lhs} vs {rhs}"
    );

    // Three worlds: world 1's controls drive world 1 only, with the bits of one world alone.
    let mut b3 = mjcf::load(format!("{ROBOTS}/servo_arm.xml"))
        .unwrap()
        .builder;
    (b3.ground, b3.link_contact) = (None, false);
    b3.integrator = integrator;
    let worlds = b3.replicate(3).finalize::<f64>().unwrap();
    assert_eq!(worlds.worlds[1].actuators, na..2 * na);
    let mut c3 = vec![0.0; 3 * na];
    c3[na..2 * na].copy_from_slice(&ctrl0);
    let s3 = run(&mut Tape::new(), &Array::from_vec(c3), &worlds);
    let alone = run(&mut Tape::new(), &Array::from_vec(ctrl0.to_vec()), &model);
    assert_eq!(
        s3.q.to_vec()[worlds.worlds[1].q.clone()],
        alone.q.to_vec()[..]
    );
    let idle = run(&mut Tape::new(), &Array::zeros(na), &model);
    assert_eq!(
        s3.q.to_vec()[worlds.worlds[0].q.clone()],
        idle.q.to_vec()[..]
    );
}

/// Joint damping is implicit in the step, as in MuJoCo's Euler integrator: a light link with
/// a strong damper slows to `qd m / (m + dt d)` per step instead of blowing up, and the
/// explicit law (`implicit_damping = false`) is the one that blows up.
#[test]
fn joint_damping_is_implicit_and_stable_at_any_step() {
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint};
    use adflex_runtime::Vec3;
    let build = |implicit: bool| {
        let mut b = ArticulationBuilder::new();
        b.gravity = Vec3::zeros();
        b.implicit_damping = implicit;
        b.add_link(
            "wheel",
            None,
            Joint::revolute(Vec3::z()).damping(100.0),
            Inertial::sphere(0.1, 0.1, Vec3::zeros()),
        );
        b.finalize::<f64>().unwrap()
    };
    let (dt, m, d) = (1e-2, 0.4 * 0.1 * 0.1 * 0.1, 100.0);
    for implicit in [true, false] {
        let model = build(implicit);
        let mut s = model.state();
        s.qd.set(0, 1.0);
        let mut expected = 1.0;
        for _ in 0..20 {
            s = model.step(&mut Tape::new(), &s, None, dt).unwrap();
            expected *= m / (m + dt * d);
        }
        let v = s.qd.get(0);
        if implicit {
            // (qd + qdd dt cancels to 4e-4 of qd each step: 2.5e-13 of rounding a step.)
            assert!((v - expected).abs() < 1e-10 * expected, "{v} vs {expected}");
        } else {
            assert!(
                v.abs() > 1e10,
                "explicit damping at dt d / m = 2.5e3 blows up: {v}"
            );
        }
    }
}

/// RK4 is fourth-order on a tumbling free body (rotations included: its stages combine in
/// exponential coordinates), Euler first-order: halving the step divides the error by about
/// 16 and 2. The free body spins about an axis near its unstable middle one, torque-free.
#[test]
fn rk4_is_fourth_order_through_rotations_and_euler_first() {
    use adflex_kernels::articulation::ArticulationIntegrator::{self, *};
    let end_state = |integrator: ArticulationIntegrator, dt: f64| -> Vec<f64> {
        let model = Articulations {
            integrator,
            ..spinning_box()
        };
        let mut s = model.state();
        for (d, w) in [(0, 0.3), (3, 0.2), (4, 4.0), (5, 0.3)] {
            s.qd.set(d, w);
        }
        let steps = (0.5 / dt).round() as usize;
        for _ in 0..steps {
            s = model.step(&mut Tape::new(), &s, None, dt).unwrap();
        }
        s.q.to_vec().into_iter().chain(s.qd.to_vec()).collect()
    };
    let exact = end_state(Rk4, 1.0 / 3200.0);
    let error = |i, dt| -> f64 {
        let s = end_state(i, dt);
        s.iter()
            .zip(&exact)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
    };
    let rk4 = (error(Rk4, 1.0 / 50.0), error(Rk4, 1.0 / 100.0));
    let euler = (error(Euler, 1.0 / 400.0), error(Euler, 1.0 / 800.0));
    println!("errors: RK4 {rk4:?}, Euler {euler:?}");
    assert!(rk4.0 / rk4.1 > 12.0 && rk4.0 / rk4.1 < 20.0, "RK4: {rk4:?}");
    assert!(
        euler.0 / euler.1 > 1.6 && euler.0 / euler.1 < 2.5,
        "Euler: {euler:?}"
    );
}

/// MuJoCo's implicitfast keeps a stiff velocity servo (`kv dt / m = 100`) stable where Euler's
/// explicit actuator force blows up; it solves with `M + dt kv`, so the speed goes to the
/// servo's by `m / (m + dt kv)` per step.
#[test]
fn implicitfast_keeps_a_stiff_velocity_servo_stable() {
    use adflex_kernels::articulation::ArticulationIntegrator::{self, *};
    use adflex_kernels::articulation::{
        Actuator, ArticulationBuilder, ArticulationControl, Inertial, Joint,
    };
    use adflex_runtime::Vec3;
    let build = |integrator: ArticulationIntegrator| {
        let mut b = ArticulationBuilder::new();
        b.gravity = Vec3::zeros();
        b.integrator = integrator;
        let l = b.add_link(
            "slider",
            None,
            Joint::prismatic(Vec3::x()),
            Inertial::point(0.01, Vec3::zeros()),
        );
        b.add_actuator(Actuator::velocity(l, 100.0));
        b.finalize::<f64>().unwrap()
    };
    let (dt, m, kv) = (1e-2, 0.01, 100.0);
    for integrator in [ImplicitFast, Euler] {
        let model = build(integrator);
        let control = ArticulationControl {
            ctrl: Array::from_vec(vec![1.0]),
            ..model.control()
        };
        let mut s = model.state();
        let mut expected = 0.0;
        for _ in 0..20 {
            s = model
                .step(&mut Tape::new(), &s, Some(&control), dt)
                .unwrap();
            expected = 1.0 + (expected - 1.0) * m / (m + dt * kv);
        }
        let v = s.qd.get(0);
        match integrator {
            ImplicitFast => assert!((v - expected).abs() < 1e-12, "{v} vs {expected}"),
            _ => assert!(v.abs() > 1e10, "explicit: {v}"),
        }
    }
}

/// What an integrator cannot do is refused, naming why: implicitfast with a fluid (its
/// velocity derivative is not computed) at `finalize` and at `step` when set on the model,
/// and MJCF's `integrator="implicit"`.
#[test]
fn integrators_refuse_what_they_cannot_do() {
    use adflex_kernels::articulation::ArticulationIntegrator::*;
    let mut b = mjcf::load(format!("{ROBOTS}/swimmer.xml")).unwrap().builder;
    b.integrator = ImplicitFast;
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("fluid") && e.contains("Rk4"), "{e}");
    b.integrator = Euler;
    let model = Articulations {
        integrator: ImplicitFast,
        ..b.finalize::<f64>().unwrap()
    };
    let e = model
        .step(&mut Tape::new(), &model.state(), None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("ImplicitFast") && e.contains("fluid"), "{e}");
    let e = mjcf_error(
        r#"<mujoco>
  <option integrator="implicit"/>
  <worldbody><body><joint type="hinge"/><geom size="0.1"/></body></worldbody>
</mujoco>"#,
    )
    .to_string();
    assert!(e.contains("line 2") && e.contains("implicitfast"), "{e}");

    // A tendon across two articulations cannot join one articulation's mass matrix.
    use adflex_kernels::articulation::{ArticulationBuilder, Inertial, Joint, TendonSpring};
    use adflex_runtime::Vec3;
    let mut b = ArticulationBuilder::new();
    let l: Vec<_> = (0..2)
        .map(|k| {
            b.add_link(
                format!("pole{k}"),
                None,
                Joint::revolute(Vec3::y()),
                Inertial::point(1.0, Vec3::new(0.0, 0.0, 0.5)),
            )
        })
        .collect();
    b.add_tendon_spring(TendonSpring {
        name: "across".into(),
        joints: vec![(l[0], 1.0), (l[1], -1.0)],
        stiffness: 1.0,
        damping: 0.5,
        rest: None,
    });
    let ok = b.finalize::<f64>().unwrap();
    b.integrator = ImplicitFast;
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("several articulations"), "{e}");
    let set = Articulations {
        integrator: ImplicitFast,
        ..ok
    };
    let e = set
        .step(&mut Tape::new(), &set.state(), None, 1e-3)
        .unwrap_err()
        .to_string();
    assert!(e.contains("several articulations"), "{e}");
}

/// MJCF's `integrator` is read (`implicitfast` too), kept by a later `<option>` that does not
/// set it, and kept by `add_builder` into an empty builder.
#[test]
fn mjcf_integrator_is_read_kept_and_carried() {
    use adflex_kernels::articulation::{ArticulationBuilder, ArticulationIntegrator::*};
    let robot = |options: &str| {
        mjcf::parse(&format!(
            r#"<mujoco>{options}
  <worldbody><body><joint type="hinge"/><geom size="0.1" pos="0 0 0.2"/></body></worldbody>
</mujoco>"#
        ))
        .unwrap()
    };
    assert_eq!(robot("").builder.integrator, Euler);
    let r =
        robot(r#"<option integrator="implicitfast" timestep="0.004"/><option gravity="0 0 -1"/>"#);
    assert_eq!(
        (r.builder.integrator, r.timestep),
        (ImplicitFast, Some(0.004))
    );
    let mut b = ArticulationBuilder::new();
    b.add_builder(&robot(r#"<option integrator="RK4"/>"#).builder);
    assert_eq!(b.integrator, Rk4);
    // A second robot stepped otherwise is refused at finalize.
    b.add_builder(&robot("").builder);
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("integrator"), "{e}");
}

/// `<flag spring|damper|actuation="disable">` switch those forces off, as MuJoCo's: springs and
/// damping of joints and tendons, the actuators' forces (their controls remain), and with
/// springs and dampers both off the fluid too (MuJoCo 4 has no `passive` flag: refused).
#[test]
fn mjcf_flags_switch_springs_dampers_and_actuation_off() {
    let with_flags = |file: &str, flags: &str| {
        let text = std::fs::read_to_string(format!("{ROBOTS}/{file}")).unwrap();
        let text = match text.find("<option") {
            Some(_) if text.contains("<flag") => text.replace("<flag ", &format!("<flag {flags} ")),
            Some(i) => {
                let close = i + text[i..].find('>').unwrap();
                match text[..close].ends_with('/') {
                    true => format!(
                        "{}><flag {flags}/></option>{}",
                        &text[..close - 1],
                        &text[close + 1..]
                    ),
                    false => format!("{}><flag {flags}/>{}", &text[..close], &text[close + 1..]),
                }
            }
            None => text.replace(
                "<worldbody>",
                &format!("<option><flag {flags}/></option><worldbody>"),
            ),
        };
        mjcf::parse(&text).map(|m| m.builder)
    };
    let b = with_flags("servo_arm.xml", r#"spring="disable""#).unwrap();
    assert!(b.links().iter().all(|l| l.joint.stiffness == 0.0));
    assert!(b.tendon_springs().iter().all(|t| t.stiffness == 0.0));
    assert!(b.links().iter().any(|l| l.joint.damping > 0.0));
    let b = with_flags("servo_arm.xml", r#"damper="disable" actuation="disable""#).unwrap();
    assert!(b.links().iter().all(|l| l.joint.damping == 0.0));
    assert!(b.tendon_springs().iter().all(|t| t.damping == 0.0));
    assert!(b.links().iter().any(|l| l.joint.stiffness > 0.0));
    assert_eq!(b.actuators().len(), 6, "the controls remain");
    assert!(b
        .actuators()
        .iter()
        .all(|a| a.gain == [0.0; 3] && a.bias == [0.0; 3] && a.force_range.is_none()));
    // Without actuation the controls move nothing.
    let model = b.finalize::<f64>().unwrap();
    let run = |ctrl: Vec<f64>| {
        let control = adflex_kernels::articulation::ArticulationControl {
            ctrl: Array::from_vec(ctrl),
            ..model.control()
        };
        let mut s = model.state();
        for _ in 0..20 {
            s = model
                .step(&mut Tape::new(), &s, Some(&control), 2e-3)
                .unwrap();
        }
        s.q.to_vec()
    };
    assert_eq!(run(vec![1.0; 6]), run(vec![0.0; 6]));
    // The fluid goes with springs and dampers both, not with one.
    let swimmer = |flags| with_flags("swimmer.xml", flags).unwrap().fluid.is_some();
    assert!(swimmer(r#"damper="disable""#));
    assert!(!swimmer(r#"spring="disable" damper="disable""#));
    let e = with_flags("servo_arm.xml", r#"passive="disable""#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("passive"), "{e}");
}

/// Mesh geoms that touch nothing on bodies with an `<inertial>` (how MuJoCo Menagerie's robots
/// draw their links) are decoration: the model loads and its dynamics are the model's without
/// them, bit for bit. A mesh that would touch, or whose mass would count, is refused by line.
#[test]
fn mjcf_passes_over_decoration_meshes_and_refuses_the_others() {
    let text = r#"<mujoco>
  <compiler meshdir="assets"/>
  <asset><mesh name="link_vis" file="link.obj"/></asset>
  <default>
    <default class="visual"><geom type="mesh" contype="0" conaffinity="0" group="2"/></default>
  </default>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <geom class="visual" mesh="link_vis"/>
    <body name="a" pos="0 0 1">
      <joint name="j" type="hinge" axis="0 1 0"/>
      <inertial pos="0 0 -0.5" mass="1" diaginertia="0.1 0.1 0.1"/>
      <geom class="visual" mesh="link_vis"/>
      <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.05"/>
      <body name="b" pos="0 0 -0.5">
        <joint name="k" type="hinge" axis="1 0 0"/>
        <geom type="sphere" size="0.1" pos="0 0 -0.3"/>
        <geom name="shell" type="mesh" mesh="link_vis" contype="0" conaffinity="0" mass="0"/>
      </body>
    </body>
  </worldbody>
</mujoco>"#;
    let plain = text
        .lines()
        .filter(|l| !l.contains("mesh=\"link_vis\""))
        .collect::<Vec<_>>()
        .join("\n");
    let with = mjcf::parse(text).unwrap();
    let without = mjcf::parse(&plain).unwrap();
    assert_eq!(with.geoms, without.geoms);
    let (a, b) = (
        with.builder.finalize::<f64>().unwrap(),
        without.builder.finalize::<f64>().unwrap(),
    );
    let q = Array::from_vec(vec![0.3, -0.7]);
    let qd = Array::from_vec(vec![1.1, 0.4]);
    let mut tape = Tape::new();
    let (ma, mb) = (a.mass_matrix(&mut tape, &q), b.mass_matrix(&mut tape, &q));
    assert_eq!(ma.to_vec(), mb.to_vec());
    let (ca, cb) = (
        a.bias_forces(&mut tape, &q, &qd),
        b.bias_forces(&mut tape, &q, &qd),
    );
    assert_eq!(ca.to_vec(), cb.to_vec());

    // A mesh that would touch: refused at its line, saying how to make it decoration.
    let touching = text.replace(
        "<geom class=\"visual\" mesh=\"link_vis\"/>\n      <geom type=\"capsule\"",
        "<geom type=\"mesh\" mesh=\"link_vis\"/>\n      <geom type=\"capsule\"",
    );
    let e = mjcf::parse(&touching).unwrap_err();
    assert_eq!(e.line, Some(13), "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains("link_vis") && msg.contains("contype=\"0\"") && msg.contains("touch"),
        "{msg}"
    );
    // Contacts off: it touches nothing, and loads.
    let off = touching.replace(
        "<default>",
        "<option><flag contact=\"disable\"/></option><default>",
    );
    assert!(mjcf::parse(&off).is_ok());
    // A mesh whose mass would count (its body has no <inertial>, and it is not `mass="0"`).
    let e = mjcf::parse(&text.replace(" mass=\"0\"/>", "/>")).unwrap_err();
    assert_eq!(e.line, Some(18), "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains("`shell`") && msg.contains("<inertial>"),
        "{msg}"
    );
    // Out of the groups whose mass counts (MuJoCo's inertiagrouprange 0 to 5): decoration.
    assert!(mjcf::parse(&text.replace(" mass=\"0\"/>", " group=\"6\"/>")).is_ok());
    // A mesh geom naming a class that does not exist is refused (its defaults would be lost).
    assert!(
        mjcf::parse(&text.replace("<geom class=\"visual\" mesh", "<geom class=\"nope\" mesh"))
            .is_err()
    );
}

/// Gravity compensation (MuJoCo's `gravcomp`, checked against MuJoCo's passive forces and
/// rollouts on `servo_arm.xml` in `dynamics_agree_with_pinocchio_and_mujoco`): links fully
/// compensated are weightless; gradients in the fractions and the masses agree with central
/// differences, forward mode with reverse; a NaN is refused by name; with springs and dampers
/// both switched off it goes, as MuJoCo's passive forces do.
#[test]
fn gravity_compensation_makes_links_weightless_with_right_gradients() {
    use adflex_kernels::articulation::{ArticulationBuilder, ArticulationState};
    let xml = |g1: &str, g2: &str| {
        format!(
            r#"<mujoco><worldbody>
  <body name="a" pos="0 0 1" gravcomp="{g1}"><joint name="j" type="hinge" axis="0 1 0"/>
    <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03"/>
    <body name="b" pos="0.4 0 0" gravcomp="{g2}"><joint name="k" type="hinge" axis="1 0 0"/>
      <geom type="sphere" size="0.05" pos="0.3 0 0.1"/></body></body></worldbody></mujoco>"#
        )
    };
    let build = |b: ArticulationBuilder| b.finalize::<f64>().unwrap();
    let roll = |model: &Articulations<f64>, tape: &mut Tape, q0: &Array<f64>, steps: usize| {
        let mut s = ArticulationState {
            q: q0.clone(),
            qd: Array::from_vec(vec![0.2, -0.1]),
        };
        for _ in 0..steps {
            s = model.step(tape, &s, None, 2e-3).unwrap();
        }
        s
    };
    let q0 = Array::from_vec(vec![0.3, -0.5]);
    // Weightless: the same motion as without gravity.
    let full = build(mjcf::parse(&xml("1", "1")).unwrap().builder);
    let mut b = mjcf::parse(&xml("0", "0")).unwrap().builder;
    b.gravity = adflex_runtime::Vec3::zeros();
    let no_gravity = build(b);
    let falls = build(mjcf::parse(&xml("0", "0")).unwrap().builder);
    let (a, z, f) = (
        roll(&full, &mut Tape::new(), &q0, 300),
        roll(&no_gravity, &mut Tape::new(), &q0, 300),
        roll(&falls, &mut Tape::new(), &q0, 300),
    );
    for (x, y) in a.q.to_vec().iter().zip(z.q.to_vec()) {
        assert!((x - y).abs() < 1e-12, "{:?} vs {:?}", a.q, z.q);
    }
    assert!(
        (a.q.get(0) - f.q.get(0)).abs() > 0.05,
        "gravity does nothing?"
    );

    // Gradients in the two fractions and the two masses.
    let model = build(mjcf::parse(&xml("0.4", "0.7")).unwrap().builder);
    assert_eq!(model.gravcomp_link.to_vec(), vec![0, 1]);
    let w = [0.7, -1.3, 0.4, 0.9];
    let loss = |gc: [f64; 2], m: [f64; 2]| -> f64 {
        let model = Articulations {
            gravcomp: Array::from_vec(gc.to_vec()),
            mass: Array::from_vec(m.to_vec()),
            ..model.clone()
        };
        let s = roll(&model, &mut Tape::new(), &q0, 100);
        let x: Vec<f64> = s.q.to_vec().into_iter().chain(s.qd.to_vec()).collect();
        x.iter().zip(w).map(|(a, b)| a * b).sum()
    };
    let (gc0, m0) = ([0.4, 0.7], [model.mass.get(0), model.mass.get(1)]);
    let mut tape = Tape::new();
    let s = roll(&model, &mut tape, &q0, 100);
    let g = tape
        .vjp(&[&s.q, &s.qd], &w, &[&model.gravcomp, &model.mass])
        .unwrap();
    let h = 1e-6;
    for k in 0..4 {
        let (mut gp, mut gm, mut mp, mut mm) = (gc0, gc0, m0, m0);
        if k < 2 {
            (gp[k], gm[k]) = (gc0[k] + h, gc0[k] - h);
        } else {
            (mp[k - 2], mm[k - 2]) = (m0[k - 2] + h, m0[k - 2] - h);
        }
        let fd = (loss(gp, mp) - loss(gm, mm)) / (2.0 * h);
        assert!(
            (g[k] - fd).abs() < 1e-6 * fd.abs().max(1e-3),
            "input {k}: {g:?}, central difference {fd}"
        );
    }
    assert!(g[0].abs() > 1e-3 && g[1].abs() > 1e-3, "{g:?}");
    let v = [0.3, -0.8, 0.5, 0.2];
    let jv = tape
        .jvp(&[&model.gravcomp, &model.mass], &v, &[&s.q, &s.qd])
        .unwrap();
    let lhs: f64 = jv.iter().zip(w).map(|(a, b)| a * b).sum();
    let rhs: f64 = g.iter().zip(v).map(|(a, b)| a * b).sum();
    assert!(
        (lhs - rhs).abs() < 1e-9 * rhs.abs().max(1.0),
        "{lhs} vs {rhs}"
    );

    // A NaN is refused by name; springs and dampers off take it away, as in MuJoCo.
    let mut b = mjcf::parse(&xml("0.4", "0.7")).unwrap().builder;
    b.links_mut()[1].gravcomp = f64::NAN;
    let e = b.finalize::<f64>().unwrap_err().to_string();
    assert!(e.contains("\"b\"") && e.contains("gravcomp"), "{e}");
    let off = xml("1", "1").replace(
        "<worldbody>",
        "<option><flag spring=\"disable\" damper=\"disable\"/></option><worldbody>",
    );
    let off = build(mjcf::parse(&off).unwrap().builder);
    assert!(off.gravcomp_link.is_empty());
}
