//! adflex-bench: `cargo run --release -p adflex-bench -- <command> [options]`
//!
//! - `scatter [--quick]`: deterministic scatter strategies and the serial threshold
//! - `kernels [--quick]`: hand-written against generated spring and bending kernels
//! - `overhead`: where the generated spring kernel loses time against the hand-written one
//! - `small [--steps 2000] [--reps 7]`: a launch-bound scene (the demos' cage, f64): time per
//!   gradient and per launch, one JSON line
//! - `bound [--n 128]`: streaming bandwidth (triad, 1 and 2 threads) and the compulsory
//!   traffic and flops of one cloth step: the memory-bandwidth bound, one JSON line
//! - `adjoint-memory [--threads K]`: peak memory of a parallel adjoint with many
//!   contributions per thread (a 4-element array read in a 10,000-iteration loop)
//! - `cloth --n 128 --steps 100 [--threads K] [--f64] [--reps R]`: the cloth benchmark, one
//!   JSON line
//! - `peers [--out FILE] [--sizes 32,64,128,256] [--steps 100] [--rounds R] [--no-python]
//!   [--wait-each L]`: adflex and the peer scripts, as JSONL
//! - `robots [--python PATH] [--newton PATH] [--steps 200] [--reps 5]`: articulated robots
//!   (arm, quadruped) per step, forward and backward, and `d qdd / d(q, qd, tau)`; with
//!   `--python`, MuJoCo and Pinocchio, with `--newton`, Newton's Featherstone solver, in the
//!   same run, and the ratios
//! - `worlds [--worlds 1024] [--frames 240] [--substeps 4] [--reps 2] [--python PATH]
//!   [--newton PATH]`: many worlds in one model (256 cloths against one; cartpoles), forward
//!   and backward: time per world-step at W = 1 and W = 1024, on 1 and 2 threads, peak
//!   memory; with `--python`, MuJoCo's batched rollout; with `--newton`, Newton's worlds
//! - `worlds-implicit [--worlds 16] [--steps 10] [--reps 1]`: implicit Euler on W cloths of
//!   different sizes dropped on the ground, as W worlds of one model (each solved by its own
//!   Newton iteration) against W models stepped one after another: seconds per step forward
//!   and backward, and the shared passes per step
//! - `mpm [--n-grid 128] [--steps 1024] [--iters 5] [--python PATH]`: DiffTaichi's MPM
//!   walker, seconds per optimization iteration on 1 and 2 threads; with `--python`, the
//!   Taichi script on the same scene in the same run, and the ratios
//! - `snow [--n-grid 128] [--steps 200] [--iters 5] [--python PATH]`: Taichi's `mpm99` scene
//!   (fluid, jelly, snow), seconds per forward step and per step forward and backward on 1
//!   and 2 threads; with `--python`, mpm99 in Taichi (forward) and the ratios
//! - `smoke [--n 110] [--steps 100] [--iters 3] [--jacobi 30] [--python PATH]`: the
//!   smoke-control task per optimization iteration, CG and Jacobi pressure; with `--python`,
//!   Taichi (Jacobi) and JAX (CG and Jacobi) in the same run, their losses and the ratios
//! - `second-order [--n 32] [--steps 100] [--rounds 5]`: a Hessian-vector product (forward
//!   over reverse, in `Dual`) and a Gauss-Newton product on the cloth scene, against a
//!   gradient in the same run, and the ratios
//! - `scene-file [--mb 50] [--file PATH]`: reading a large JSON scene against plain
//!   serde_json, time and peak RSS of each in its own process, as JSON lines
//! - `charts --out docs/charts [--peers FILE] [--quick] [--only NAME,..]`: every chart as SVG
//!
//! Any command takes `--wait-load L`: first wait (up to 20 min) for the 1-minute load average
//! to drop below `L`, so that timings are not taken while other builds run.

use adflex_bench::*;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let cmd = args.first().map(String::as_str).unwrap_or("");
    let rest = &args[args.len().min(1)..];
    let flag = |name: &str| rest.iter().any(|a| a == name);
    // `--wait-load L`: wait (up to 20 min) for the 1-minute load average to drop below L.
    let mut rest: Vec<String> = rest.to_vec();
    if let Some(k) = rest.iter().position(|a| a == "--wait-load") {
        let limit: f64 = rest.get(k + 1).and_then(|v| v.parse().ok()).unwrap_or(1.5);
        rest.drain(k..(k + 2).min(rest.len()));
        let l = timing::wait_for_load(limit, 1200.0);
        eprintln!("load average {l} (waited for < {limit})");
    }
    let rest = &rest[..];
    match cmd {
        "scatter" => scatter::main(flag("--quick")),
        "kernels" => kernels_cmp::main(flag("--quick")),
        "overhead" => overhead::main(),
        "small" => {
            let num = |name: &str, default: usize| {
                rest.iter()
                    .position(|a| a == name)
                    .and_then(|k| rest.get(k + 1))
                    .and_then(|v| v.parse().ok())
                    .unwrap_or(default)
            };
            small::main(num("--steps", 2000), num("--reps", 7))
        }
        "bound" => {
            let n = rest
                .iter()
                .position(|a| a == "--n")
                .and_then(|k| rest.get(k + 1))
                .and_then(|v| v.parse().ok())
                .unwrap_or(128);
            bound::main(n)
        }
        "adjoint-memory" => {
            let threads = rest
                .iter()
                .position(|a| a == "--threads")
                .and_then(|k| rest.get(k + 1))
                .and_then(|v| v.parse().ok())
                .unwrap_or(2);
            small::adjoint_memory(threads)
        }
        "charts" => {
            if let Err(e) = charts::parse(rest)
                .map_err(Into::into)
                .and_then(|o| charts::main(&o))
            {
                eprintln!("charts: {e}");
                std::process::exit(2);
            }
        }
        "peers" => {
            if let Err(e) = peers::parse(rest).and_then(|o| peers::main(&o)) {
                eprintln!("peers: {e}");
                std::process::exit(2);
            }
        }
        "scene-file" => {
            if let Err(e) = scene_file::main(rest) {
                eprintln!("scene-file: {e}");
                std::process::exit(2);
            }
        }
        "scene-file-case" => {
            let arg = |k: usize| rest.get(k).map(String::as_str).unwrap_or("");
            match scene_file::run_case(arg(0), arg(1)) {
                Ok(line) => println!("{line}"),
                Err(e) => {
                    eprintln!("scene-file-case: {e}");
                    std::process::exit(2);
                }
            }
        }
        "robots" => robots::main(rest),
        "worlds" => worlds::main(rest),
        "mpm" => mpm::main(rest),
        "snow" => mpm::snow(rest),
        "smoke" => smoke::main(rest),
        "second-order" => second_order::main(rest),
        "worlds-case" => println!("{}", worlds::case(rest)),
        "worlds-implicit" => worlds::implicit(rest),
        "cloth" => match cloth::parse(rest) {
            Ok(o) => println!("{}", cloth::run(&o)),
            Err(e) => {
                eprintln!("cloth: {e}");
                std::process::exit(2);
            }
        },
        _ => {
            eprintln!("usage: adflex-bench <scatter|kernels|overhead|cloth|peers|charts|scene-file|robots|worlds|mpm|smoke|second-order> [options] (see src/main.rs)");
            std::process::exit(2);
        }
    }
}
