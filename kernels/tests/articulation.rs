//! Articulated bodies: the dynamics of the repository's robots against Pinocchio and MuJoCo
//! (references in `references/robots.json`, from `references/robots.py`), derivatives against
//! Pinocchio's and central differences, rollouts' gradients, and bad robot files.

use adflex_kernels::articulation::{urdf, Articulations, JointType};
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
        todo!()
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
