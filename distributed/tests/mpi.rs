//! The MPI path, run with `mpirun` (Open MPI) on this machine: `cargo test -p
//! adflex-distributed --features mpi`. Every world's loss and gradients, and the gradients
//! of the shared parameters, are bitwise the single process's on 2 and 4 (oversubscribed)
//! ranks; a rank that fails, panics, exits or is killed, or ranks that build different scenes,
//! end the job with an error naming the rank, never a hang.
#![cfg(feature = "mpi")]

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_worlds_mpi");

/// Runs `worlds_mpi args` on `np` ranks (`None`: one process without MPI); its exit code,
/// stdout and stderr. A run that takes over 2 minutes is a hang: killed, and the test fails.
fn run(np: Option<usize>, args: &[&str]) -> (Option<i32>, String, String) {
    let mut cmd = match np {
        Some(n) => {
            let mut c = Command::new("mpirun");
            c.args(["--oversubscribe", "-np", &n.to_string(), BIN]);
            c
        }
        None => {
            let mut c = Command::new(BIN);
            c.arg("--single");
            c
        }
    };
    // Containers and CI run as root; Open MPI refuses without these.
    cmd.env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("RUST_BACKTRACE", "0")
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    let mut child = cmd.spawn().expect("mpirun runs (Open MPI installed?)");
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().expect("waiting for mpirun") {
            let out = child.wait_with_output().expect("mpirun's output");
            let _ = status;
            return (
                out.status.code(),
                String::from_utf8_lossy(&out.stdout).into_owned(),
                String::from_utf8_lossy(&out.stderr).into_owned(),
            );
        }
        if start.elapsed() > Duration::from_secs(120) {
            let _ = child.kill();
            panic!("worlds_mpi {args:?} on {np:?} ranks hung for 2 minutes");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn result(np: Option<usize>, worlds: usize) -> serde_json::Value {
    let (code, out, err) = run(np, &["--worlds", &worlds.to_string(), "--steps", "60"]);
    assert_eq!(code, Some(0), "{np:?} ranks: {err}");
    let mut v: serde_json::Value = serde_json::from_str(out.trim()).expect(&out);
    let o = v.as_object_mut().unwrap();
    o.remove("seconds");
    o.remove("ranks");
    v
}

#[test]
fn ranks_give_the_single_process_bits() {
    let one = result(None, 37);
    assert_eq!(one["per_world"].as_array().unwrap().len(), 37);
    for np in [1, 2, 4] {
        assert_eq!(result(Some(np), 37), one, "{np} ranks");
    }
}

#[test]
fn a_failing_rank_ends_the_job_naming_it() {
    let cases: [(&[&str], usize, &str); 5] = [
        (
            &["--fail", "error", "--fail-rank", "1"],
            2,
            "rank 1 failed on worlds 4..8: simulated solver failure",
        ),
        (
            &["--fail", "panic", "--fail-rank", "2"],
            4,
            "rank 2 failed on worlds 4..6: panicked: simulated panic",
        ),
        (
            &["--disagree-rank", "1"],
            2,
            "rank 1's scene differs from rank 0's",
        ),
        // Open MPI names the process `[[job,1],1]` (4.x) or `[prterun-host-pid@1,1]` (5.x).
        (&["--fail", "exit", "--fail-rank", "1"], 2, "Exit code"),
        (
            &["--fail", "kill", "--fail-rank", "3"],
            4,
            "process rank 3 with PID",
        ),
    ];
    for (args, np, says) in cases {
        let mut all = vec!["--worlds", "8", "--steps", "20"];
        all.extend(args);
        let (code, out, err) = run(Some(np), &all);
        assert!(code != Some(0), "{args:?}: exit {code:?}");
        assert!(out.trim().is_empty(), "{args:?}: a partial result {out}");
        assert!(err.contains(says), "{args:?}: {err}");
        if args.contains(&"exit") {
            assert!(err.contains(",1],1]") || err.contains("@1,1]"), "{err}");
        }
    }
}
