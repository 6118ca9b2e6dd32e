//! `cloth`: the cloth benchmark of `docs/scenes.md` on the kernels crate's scene
//! (`adflex_kernels::scenes::cloth`), one JSON line per run.

use std::time::Instant;

use adflex_kernels::scenes::cloth;
use adflex_runtime::{with_threads, Real};
use serde_json::json;

/// Options of one run.
#[derive(Clone, Debug)]
pub struct Opts {
    pub n: usize,
    pub steps: usize,
    pub threads: usize,
    pub f64: bool,
    /// Timed repetitions of each of forward and forward+backward (after one warm-up).
    pub reps: usize,
}

impl Default for Opts {
    fn default() -> Self {
        Opts {
            n: 128,
            steps: 100,
            threads: 1,
            f64: false,
            reps: 3,
        }
    }
}

fn run_typed<R: Real>(o: &Opts) -> serde_json::Value {
    let scene = cloth::build::<R>(o.n);
    let timed = |backward: bool| {
        let t0 = Instant::now();
        let r = cloth::rollout(&scene, o.steps, backward).expect("cloth rollout");
        (t0.elapsed().as_secs_f64(), r)
    };
    // warm-up (page in, grow allocator pools)
    let _ = timed(true);
    let mut fwd = f64::INFINITY;
    let mut both = f64::INFINITY;
    let mut last = None;
    for _ in 0..o.reps.max(1) {
        fwd = fwd.min(timed(false).0);
    }
    for _ in 0..o.reps.max(1) {
        let (s, r) = timed(true);
        both = both.min(s);
        last = Some(r);
    }
    let r = last.expect("at least one rep");
    let steps = o.steps.max(1) as f64;
    json!({
        "system": if o.f64 { "adflex-f64" } else { "adflex" },
        "n": o.n,
        "steps": o.steps,
        "threads": o.threads,
        "fwd_s_per_step": fwd / steps,
        "fwd_bwd_s_per_step": both / steps,
        "loss": r.loss,
        "grad_v0_norm": r.grad_v0_norm,
        "grad_ke_norm": r.grad_ke_norm,
        "peak_rss_mb": crate::timing::peak_rss_mb(),
    })
}

/// Runs the benchmark; returns the JSON object (fields in the order of docs/scenes.md).
pub fn run(o: &Opts) -> serde_json::Value {
    with_threads(o.threads.max(1), || {
        if o.f64 {
            run_typed::<f64>(o)
        } else {
            run_typed::<f32>(o)
        }
    })
}

/// The fields every line has, in order.
pub const FIELDS: [&str; 10] = [
    "system",
    "n",
    "steps",
    "threads",
    "fwd_s_per_step",
    "fwd_bwd_s_per_step",
    "loss",
    "grad_v0_norm",
    "grad_ke_norm",
    "peak_rss_mb",
];

/// Parses `cloth` options from the command line.
pub fn parse(args: &[String]) -> Result<Opts, String> {
    let mut o = Opts::default();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut val = |name: &str| -> Result<usize, String> {
            it.next()
                .ok_or(format!("{name} needs a value"))?
                .parse()
                .map_err(|e| format!("{name}: {e}"))
        };
        match a.as_str() {
            "--n" => o.n = val("--n")?,
            "--steps" => o.steps = val("--steps")?,
            "--threads" => o.threads = val("--threads")?,
            "--reps" => o.reps = val("--reps")?,
            "--f64" => o.f64 = true,
            other => return Err(format!("unknown option `{other}`")),
        }
    }
    if o.n < 2 {
        return Err("--n must be at least 2".into());
    }
    Ok(o)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_has_every_field() {
        let v = run(&Opts {
            n: 4,
            steps: 3,
            threads: 1,
            f64: false,
            reps: 1,
        });
        let line = v.to_string();
        let back: serde_json::Value = serde_json::from_str(&line).unwrap();
        let obj = back.as_object().unwrap();
        for f in FIELDS {
            assert!(obj.contains_key(f), "missing {f} in {line}");
        }
        assert_eq!(obj["system"], "adflex");
        assert!(obj["loss"].as_f64().unwrap() > 0.0);
    }

    #[test]
    fn parses_options() {
        let a: Vec<String> = "--n 64 --steps 10 --threads 2 --f64"
            .split(' ')
            .map(String::from)
            .collect();
        let o = parse(&a).unwrap();
        assert_eq!((o.n, o.steps, o.threads, o.f64), (64, 10, 2, true));
        assert!(parse(&["--bogus".to_string()]).is_err());
    }
}
