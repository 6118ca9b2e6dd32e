//! Cart-pole worlds spread over MPI ranks: each rank rolls out its share, forward and backward,
//! and rank 0 prints every world's loss and gradients and the gradients of the parameters the
//! worlds share (summed in world order), as one JSON line. The same bits on any number of
//! ranks, and with `--single` (one process, no MPI).
//!
//! `mpirun -np 4 worlds_mpi [--worlds 64] [--steps 100] [--single]`
//! Failure drills: `--fail error|panic|exit|kill --fail-rank R`, `--disagree-rank R`.

use std::time::Instant;

use adflex_distributed::*;
use adflex_kernels::articulation::{urdf, ArticulationBuilder, ArticulationControl, Articulations};
use adflex_runtime::prelude::*;

const ROBOTS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../kernels/robots");

fn arg(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|k| args.get(k + 1))
        .cloned()
}

/// The scene: world `w` a cart-pole with its own tilt and gravity.
fn scene(n: usize, tweak: bool) -> ArticulationBuilder {
    let base =
        urdf::load(format!("{ROBOTS}/cartpole.urdf"), &Default::default()).expect("cartpole.urdf");
    let pole = base.find("pole").expect("a pole").0;
    let mut b = ArticulationBuilder::new();
    for w in 0..n {
        let mut s = base.clone();
        s.links_mut()[pole].joint.initial = vec![0.1 + 0.01 * (w % 13) as f64];
        s.gravity.z = -9.81 * (1.0 + 0.001 * w as f64);
        if tweak && w == 0 {
            s.gravity.z *= 1.0 + 1e-12;
        }
        b.add_world(&s);
    }
    b
}

/// World outputs: loss, d loss / d (rail, cart, pole masses), d loss / d gravity z, and
/// d loss / d the cart's force at step 0.
fn simulate(
    all: &ArticulationBuilder,
    worlds: std::ops::Range<usize>,
    steps: usize,
) -> Result<Vec<Vec<f64>>, String> {
    let b = all.worlds_in(worlds.clone());
    let model: Articulations<f64> = b.finalize().map_err(|e| e.to_string())?;
    let _ = model.mass.clone().requires_grad();
    let _ = model.gravity.clone().requires_grad();
    let mut tape = Tape::new();
    let mut s = model.state();
    let mut forces = Vec::new();
    for k in 0..steps {
        let mut tau = vec![0.0; model.n_dof];
        for (i, info) in model.worlds.iter().enumerate() {
            let w = worlds.start + i; // the world's global index: its force never depends on its rank
            tau[info.dofs.start] = 0.3 * (0.1 * k as f64 + w as f64).sin();
        }
        let tau = Array::from_vec(tau).requires_grad();
        let c = ArticulationControl {
            tau: tau.clone(),
            ..model.control()
        };
        s = model
            .step(&mut tape, &s, Some(&c), 1e-2)
            .map_err(|e| e.to_string())?;
        forces.push(tau);
    }
    let loss = Array::zeros(model.n_worlds());
    adflex_kernels::losses::per_world_sum_of_squares(&mut tape, &model.q_world, &s.q, 1.0, &loss);
    tape.backward(&loss).map_err(|e| e.to_string())?;
    let mass = model.mass.grad().map_err(|e| e.to_string())?.to_vec();
    let gravity = model.gravity.grad().map_err(|e| e.to_string())?.to_vec();
    let tau0 = forces[0].grad().map_err(|e| e.to_string())?.to_vec();
    Ok(model
        .worlds
        .iter()
        .enumerate()
        .map(|(i, info)| {
            let mut out = vec![loss.get(i)];
            out.extend(&mass[info.links.clone()]);
            out.push(gravity[i].z);
            out.push(tau0[info.dofs.start]);
            out
        })
        .collect())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = arg(&args, "--worlds").map_or(64, |v| v.parse().expect("--worlds N"));
    let steps: usize = arg(&args, "--steps").map_or(100, |v| v.parse().expect("--steps N"));
    let fail = arg(&args, "--fail");
    let fail_rank: Option<usize> = arg(&args, "--fail-rank").map(|v| v.parse().expect("rank"));
    let disagree: Option<usize> = arg(&args, "--disagree-rank").map(|v| v.parse().expect("rank"));
    let comm: Box<dyn Communicator> = if args.iter().any(|a| a == "--single") {
        Box::new(SingleProcess)
    } else {
        Box::new(MpiComm::init().expect("MPI initializes"))
    };
    let rank = comm.rank();
    let all = scene(n, disagree == Some(rank));
    let start = Instant::now();
    let out = run_worlds(&*comm, n, fingerprint(&all), |worlds| {
        if fail_rank == Some(rank) {
            match fail.as_deref() {
                Some("error") => return Err("simulated solver failure".into()),
                Some("panic") => panic!("simulated panic"),
                Some("exit") => std::process::exit(3),
                // Killed by SIGKILL, as the OOM killer or a scheduler would.
                Some("kill") => {
                    // SAFETY: signals this process only; it never returns.
                    unsafe { libc::kill(libc::getpid(), libc::SIGKILL) };
                    std::thread::sleep(std::time::Duration::from_secs(60));
                }
                _ => {}
            }
        }
        simulate(&all, worlds, steps)
    });
    let seconds = start.elapsed().as_secs_f64();
    let size = comm.size();
    drop(comm); // finalizes MPI
    match out {
        Ok(out) => {
            if rank == 0 {
                let line = serde_json::json!({
                    "ranks": size,
                    "worlds": n,
                    "steps": steps,
                    "per_world": out.per_world,
                    "shared_mass_grad": out.sum(1..4),
                    "seconds": seconds,
                });
                println!("{line}");
            }
        }
        Err(e) => {
            eprintln!("worlds_mpi (rank {rank}): {e}");
            std::process::exit(2);
        }
    }
}
