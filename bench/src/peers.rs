//! `peers`: the cloth benchmark of adflex (1 and 2 threads) and of the peer scripts
//! (`bench/peers/*_cloth.py`: Warp, Taichi, JAX) at several sizes, in one run, as JSONL.
//!
//! The peers run with `~/.cache/peers-venv/bin/python` (or `--python`) when it exists and are
//! skipped otherwise. Each line: `system, n, steps, threads, fwd_s_per_step,
//! fwd_bwd_s_per_step, loss, grad_v0_norm, grad_ke_norm, peak_rss_mb, date, wall_s, cmd`.
//! Sizes are run in order and, within a size, every system one after the other, so that the
//! ratios at one size come from the same minutes of the (noisy, shared) machine. With
//! `--rounds R` each size runs every system R times, round by round (A B C .. A B C ..), and
//! each system's line keeps its best forward and best forward+backward time (`rounds`: R;
//! each process already reports the best of its own repetitions): one slow process, a
//! common event on a shared machine, then does not decide a ratio.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use serde_json::{json, Value};

/// Options of the run.
#[derive(Clone, Debug)]
pub struct Opts {
    pub out: PathBuf,
    pub sizes: Vec<usize>,
    pub steps: usize,
    pub python: Option<PathBuf>,
    pub peers_dir: PathBuf,
    /// Peers to run (`warp`, `taichi`, `jax`).
    pub peers: Vec<String>,
    /// Before each size, wait (up to 10 min) for the load average to drop below this.
    pub wait_each: Option<f64>,
    /// Runs of every system per size, interleaved; the best time of each kind is kept.
    pub rounds: usize,
}

fn default_python() -> Option<PathBuf> {
    let home = std::env::var_os("HOME")?;
    let p = Path::new(&home).join(".cache/peers-venv/bin/python");
    p.exists().then_some(p)
}

fn default_peers_dir() -> PathBuf {
    std::env::var_os("ADFLEX_PEERS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("peers");
            p.canonicalize().unwrap_or(p)
        })
}

pub fn parse(args: &[String]) -> Result<Opts, String> {
    let mut o = Opts {
        out: PathBuf::from("docs/charts/peers.jsonl"),
        sizes: vec![32, 64, 128, 256],
        steps: 100,
        python: default_python(),
        peers_dir: default_peers_dir(),
        peers: vec!["warp".into(), "taichi".into(), "jax".into()],
        wait_each: None,
        rounds: 1,
    };
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut val = |name: &str| it.next().cloned().ok_or(format!("{name} needs a value"));
        match a.as_str() {
            "--out" => o.out = val("--out")?.into(),
            "--sizes" => {
                o.sizes = val("--sizes")?
                    .split(',')
                    .map(|s| s.trim().parse().map_err(|e| format!("--sizes: {e}")))
                    .collect::<Result<_, _>>()?
            }
            "--steps" => {
                o.steps = val("--steps")?
                    .parse()
                    .map_err(|e| format!("--steps: {e}"))?
            }
            "--python" => o.python = Some(val("--python")?.into()),
            "--no-python" => o.python = None,
            "--peers-dir" => o.peers_dir = val("--peers-dir")?.into(),
            "--peers" => o.peers = val("--peers")?.split(',').map(String::from).collect(),
            "--wait-each" => {
                o.wait_each = Some(
                    val("--wait-each")?
                        .parse()
                        .map_err(|e| format!("--wait-each: {e}"))?,
                )
            }
            "--rounds" => {
                o.rounds = val("--rounds")?
                    .parse()
                    .map_err(|e| format!("--rounds: {e}"))?;
                if o.rounds == 0 {
                    return Err("--rounds must be at least 1".into());
                }
            }
            other => return Err(format!("unknown option `{other}`")),
        }
    }
    Ok(o)
}

/// Parses the last JSON line of a program's output; Python's bare `NaN`/`Infinity` become null.
pub fn parse_json_line(out: &str) -> Option<Value> {
    let line = out
        .lines()
        .rev()
        .find(|l| l.trim_start().starts_with('{'))?;
    let fixed = line
        .replace("-Infinity", "null")
        .replace("Infinity", "null")
        .replace("NaN", "null");
    serde_json::from_str(&fixed).ok()
}

/// Runs `cmd`, under `/usr/bin/time` when present for the peak RSS; returns (stdout, wall s,
/// peak RSS MB).
fn run(cmd: &[String]) -> Result<(String, f64, Option<f64>), String> {
    let timed = Path::new("/usr/bin/time").exists();
    let mut c = if timed {
        let mut c = Command::new("/usr/bin/time");
        c.arg("-f").arg("ADFLEX_MAXRSS_KB %M").args(cmd);
        c
    } else {
        let mut c = Command::new(&cmd[0]);
        c.args(&cmd[1..]);
        c
    };
    let t0 = Instant::now();
    let out = c.output().map_err(|e| format!("{}: {e}", cmd[0]))?;
    let wall = t0.elapsed().as_secs_f64();
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        return Err(format!(
            "`{}` failed: {}",
            cmd.join(" "),
            stderr.lines().rev().take(5).collect::<Vec<_>>().join(" | ")
        ));
    }
    let rss = stderr
        .lines()
        .find_map(|l| l.strip_prefix("ADFLEX_MAXRSS_KB "))
        .and_then(|k| k.trim().parse::<f64>().ok())
        .map(|kb| kb / 1024.0);
    Ok((String::from_utf8_lossy(&out.stdout).into_owned(), wall, rss))
}

fn normalize(
    raw: Value,
    system: &str,
    threads: Option<usize>,
    wall: f64,
    rss: Option<f64>,
    cmd: &str,
) -> Value {
    let g = |k: &str| raw.get(k).cloned().unwrap_or(Value::Null);
    json!({
        "system": system,
        "n": g("n"),
        "steps": g("steps"),
        "threads": threads.map_or(g("threads"), |t| json!(t)),
        "fwd_s_per_step": g("fwd_s_per_step"),
        "fwd_bwd_s_per_step": g("fwd_bwd_s_per_step"),
        "loss": g("loss"),
        "grad_v0_norm": g("grad_v0_norm"),
        "grad_ke_norm": g("grad_ke_norm"),
        "peak_rss_mb": match g("peak_rss_mb") { Value::Null => json!(rss), v => v },
        "date": crate::timing::now_iso(),
        "load_avg": crate::timing::loadavg(),
        "wall_s": (wall * 100.0).round() / 100.0,
        "cmd": cmd,
    })
}

/// One system's command at one size.
struct Job {
    name: String,
    /// adflex's thread count; `None` for a peer.
    threads: Option<usize>,
    cmd: Vec<String>,
    /// The command as a user would type it.
    shown: String,
}

/// adflex on 1 and 2 threads, then each peer whose script exists (when there is a Python).
fn jobs(o: &Opts, exe: &Path, n: usize) -> Vec<Job> {
    let mut jobs: Vec<Job> = [1, 2]
        .into_iter()
        .map(|threads| Job {
            name: "adflex".into(),
            threads: Some(threads),
            cmd: [
                exe.display().to_string(),
                "cloth".into(),
                "--n".into(),
                n.to_string(),
                "--steps".into(),
                o.steps.to_string(),
                "--threads".into(),
                threads.to_string(),
            ]
            .into(),
            shown: format!(
                "cargo run --release -p adflex-bench -- cloth --n {n} --steps {} --threads {threads}",
                o.steps
            ),
        })
        .collect();
    let Some(py) = &o.python else { return jobs };
    for peer in &o.peers {
        let script = o.peers_dir.join(format!("{peer}_cloth.py"));
        if !script.exists() {
            eprintln!("skipping {peer}: {} not found", script.display());
            continue;
        }
        let cmd: Vec<String> = vec![
            py.display().to_string(),
            script.display().to_string(),
            "--n".into(),
            n.to_string(),
            "--steps".into(),
            o.steps.to_string(),
        ];
        jobs.push(Job {
            name: peer.clone(),
            threads: None,
            shown: cmd.join(" "),
            cmd,
        });
    }
    jobs
}

/// `a` with the better (smaller) of each time of `a` and `b`, the larger peak RSS, and the
/// date, load and wall time of the run that gave the best forward+backward.
fn keep_best(a: Value, b: Value) -> Value {
    let t = |v: &Value, k: &str| v[k].as_f64().unwrap_or(f64::INFINITY);
    let (mut out, other) = if t(&b, "fwd_bwd_s_per_step") < t(&a, "fwd_bwd_s_per_step") {
        (b, a)
    } else {
        (a, b)
    };
    if t(&other, "fwd_s_per_step") < t(&out, "fwd_s_per_step") {
        out["fwd_s_per_step"] = other["fwd_s_per_step"].clone();
    }
    let rss = |v: &Value| v["peak_rss_mb"].as_f64();
    if let (Some(x), Some(y)) = (rss(&out), rss(&other)) {
        out["peak_rss_mb"] = json!(x.max(y));
    }
    out
}

pub fn main(o: &Opts) -> Result<(), String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    if let Some(dir) = o.out.parent() {
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    }
    let mut lines = Vec::new();
    let emit = |v: Value, lines: &mut Vec<String>| {
        eprintln!("{v}");
        lines.push(v.to_string());
        // write as we go: a long run that fails late keeps what it measured
        let _ = std::fs::write(&o.out, lines.join("\n") + "\n");
    };
    match &o.python {
        Some(p) => eprintln!("peers: {} with {}", o.peers_dir.display(), p.display()),
        None => eprintln!("peers: no Python venv (~/.cache/peers-venv); running adflex only"),
    }
    for &n in &o.sizes {
        if let Some(limit) = o.wait_each {
            let l = crate::timing::wait_for_load(limit, 600.0);
            eprintln!("n={n}: load average {l}");
        }
        let jobs = jobs(o, &exe, n);
        let mut best: Vec<Option<Value>> = vec![None; jobs.len()];
        for round in 0..o.rounds {
            for (job, best) in jobs.iter().zip(&mut best) {
                match run(&job.cmd).and_then(|(out, wall, rss)| {
                    parse_json_line(&out)
                        .map(|v| (v, wall, rss))
                        .ok_or_else(|| format!("no JSON in `{out}`"))
                }) {
                    Ok((v, wall, rss)) => {
                        let system = match &job.threads {
                            Some(t) => format!("adflex-{t}t"),
                            None => v
                                .get("peer")
                                .and_then(Value::as_str)
                                .unwrap_or(&job.name)
                                .to_string(),
                        };
                        let line = normalize(v, &system, job.threads, wall, rss, &job.shown);
                        eprintln!("round {}/{}: {line}", round + 1, o.rounds);
                        *best = Some(match best.take() {
                            None => line,
                            Some(b) => keep_best(b, line),
                        });
                    }
                    Err(e) => eprintln!("{} n={n}: {e}", job.name),
                }
            }
        }
        for mut line in best.into_iter().flatten() {
            line["rounds"] = json!(o.rounds);
            emit(line, &mut lines);
        }
    }
    eprintln!("wrote {} lines to {}", lines.len(), o.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn python_nan_parses() {
        let v = super::parse_json_line(
            "noise\n{\"peer\": \"taichi-cpu\", \"loss\": 0.5, \"grad_v0_norm\": NaN}\n",
        )
        .unwrap();
        assert!(v["grad_v0_norm"].is_null());
        assert_eq!(v["loss"], 0.5);
    }

    #[test]
    fn rounds_keep_each_best_time() {
        use serde_json::json;
        let a = json!({"fwd_s_per_step": 1.0, "fwd_bwd_s_per_step": 5.0, "peak_rss_mb": 10.0, "date": "a"});
        let b = json!({"fwd_s_per_step": 2.0, "fwd_bwd_s_per_step": 4.0, "peak_rss_mb": 12.0, "date": "b"});
        let k = super::keep_best(a, b);
        assert_eq!(k["fwd_s_per_step"], 1.0);
        assert_eq!(k["fwd_bwd_s_per_step"], 4.0);
        assert_eq!(k["peak_rss_mb"], 12.0);
        assert_eq!(k["date"], "b");
        assert!(super::parse(&["--rounds".into(), "0".into()]).is_err());
        assert_eq!(
            super::parse(&["--rounds".into(), "3".into()])
                .unwrap()
                .rounds,
            3
        );
    }
}
