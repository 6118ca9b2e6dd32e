//! `peers`: the cloth benchmark of adflex (1 and 2 threads) and of the peer scripts
//! (`bench/peers/*_cloth.py`: Warp, Taichi, JAX) at several sizes, in one run, as JSONL.
//!
//! The peers run with `~/.cache/peers-venv/bin/python` (or `--python`) when it exists and are
//! skipped otherwise. Each line: `system, n, steps, threads, fwd_s_per_step,
//! fwd_bwd_s_per_step, loss, grad_v0_norm, grad_ke_norm, peak_rss_mb, date, wall_s, cmd`.
//! Sizes are run in order and, within a size, every system one after the other, so that the
//! ratios at one size come from the same minutes of the (noisy, shared) machine.

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
        for threads in [1, 2] {
            let cmd: Vec<String> = vec![
                exe.display().to_string(),
                "cloth".into(),
                "--n".into(),
                n.to_string(),
                "--steps".into(),
                o.steps.to_string(),
                "--threads".into(),
                threads.to_string(),
            ];
            let shown = format!("cargo run --release -p adflex-bench -- cloth --n {n} --steps {} --threads {threads}", o.steps);
            match run(&cmd).and_then(|(out, wall, rss)| {
                parse_json_line(&out)
                    .map(|v| (v, wall, rss))
                    .ok_or_else(|| format!("no JSON in `{out}`"))
            }) {
                Ok((v, wall, rss)) => emit(
                    normalize(
                        v,
                        &format!("adflex-{threads}t"),
                        Some(threads),
                        wall,
                        rss,
                        &shown,
                    ),
                    &mut lines,
                ),
                Err(e) => eprintln!("adflex n={n} threads={threads}: {e}"),
            }
        }
        let Some(py) = &o.python else { continue };
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
            let shown = cmd.join(" ");
            match run(&cmd).and_then(|(out, wall, rss)| {
                parse_json_line(&out)
                    .map(|v| (v, wall, rss))
                    .ok_or_else(|| format!("no JSON in `{out}`"))
            }) {
                Ok((v, wall, rss)) => {
                    let system = v
                        .get("peer")
                        .and_then(Value::as_str)
                        .unwrap_or(peer)
                        .to_string();
                    emit(normalize(v, &system, None, wall, rss, &shown), &mut lines)
                }
                Err(e) => eprintln!("{peer} n={n}: {e}"),
            }
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
}
