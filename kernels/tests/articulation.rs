//! Articulated bodies: the dynamics of the repository's robots against Pinocchio and MuJoCo
//! (references in `references/robots.json`, from `references/robots.py`), derivatives against
//! Pinocchio's and central differences, rollouts' gradients, and bad robot files.

use adflex_kernels::articulation::{mjcf, urdf, Articulations, JointType};
use adflex_runtime::{Array, Tape};
use serde_json::Value;

const ROBOTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/robots");

fn load(file: &str, floating: bool) -> Articulations<f64> {
    let path = format!("{ROBOTS}/{file}");
    let b = if file.ends_with(".urdf") {
        urdf::load(
            &path,
            &urdf::UrdfOptions {
                floating_base: floating,
            },
        )
    } else {
        mjcf::load(&path).map(|m| m.builder)
    };
    b.unwrap_or_else(|e| panic!("{e}")).finalize().unwrap()
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
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/references/robots.json"
    ))
    .unwrap();
    let refs: Value = serde_json::from_str(&text).unwrap();
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
        let mut worst = [0.0f64; 6];
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
            if s.get("dqdd_dq").is_some() {
                let d = model.forward_dynamics_derivatives(&q, &qd, &tau).unwrap();
                worst[3] = worst[3].max(rel_err(&permute(&d.dq), &matf(&s["dqdd_dq"])));
                worst[4] = worst[4].max(rel_err(&permute(&d.dqd), &matf(&s["dqdd_dqd"])));
                worst[5] = worst[5].max(rel_err(&permute(&d.dtau), &matf(&s["dqdd_dtau"])));
            }
        }
        report.push(format!(
            "{file} ({}): M {:.1e}, bias {:.1e}, qdd {:.1e}, dqdd/dq {:.1e}, dqdd/dqd {:.1e}, dqdd/dtau {:.1e}",
            m["reference"].as_str().unwrap(),
            worst[0], worst[1], worst[2], worst[3], worst[4], worst[5]
        ));
        assert!(
            worst.iter().all(|&w| w < 1e-9),
            "{file}: relative errors {worst:?}\n{}",
            report.join("\n")
        );
    }
    println!("{}", report.join("\n"));
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
    for (file, floating) in [
        ("cartpole.urdf", false),
        ("arm7.urdf", false),
        ("quadruped.urdf", true),
        ("ant.xml", false),
        ("humanoid.xml", false),
    ] {
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
        println!("{file}: central differences vs tangent passes: dq {:.1e}, dqd {:.1e}, dtau {:.1e}", worst[0], worst[1], worst[2]);
        assert!(worst.iter().all(|&w| w < 1e-6), "{file}: {worst:?}");
    }
}
