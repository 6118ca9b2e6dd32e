//! `scene-file [--mb 50] [--file PATH]`: reading a large valid JSON scene with
//! [`ModelBuilder::from_json_str`] against plain `serde_json` on the same text (typed, into
//! mirror structs of the particles and springs; and into a `serde_json::Value`). Each case
//! runs in its own process (so that its peak RSS is its own) and prints one JSON line:
//! `{"case", "mb", "secs", "peak_rss_mb"}`; the parent prints them and the ratios.

use std::process::Command;
use std::time::Instant;

use adflex_kernels::ModelBuilder;
use serde::Deserialize;

/// A scene of particles in a row joined by springs, of about `mb` megabytes.
pub fn scene_json(mb: f64) -> String {
    let target = (mb * 1e6) as usize;
    let mut particles = String::with_capacity(target / 2 + 1024);
    let mut springs = String::with_capacity(target / 2 + 1024);
    let mut n = 0usize;
    while particles.len() + springs.len() < target {
        if n > 0 {
            particles.push_str(",\n");
            springs.push_str(&format!(
                "{}    {{ \"i\": {}, \"j\": {n}, \"ke\": 100.0, \"kd\": 0.1 }}",
                if n > 1 { ",\n" } else { "" },
                n - 1
            ));
        }
        particles.push_str(&format!(
            "    {{ \"x\": [{:.4}, 1.0, {:.4}], \"v\": [0, 0, 0], \"mass\": 0.01 }}",
            (n % 1000) as f64 * 0.01,
            (n / 1000) as f64 * 0.01
        ));
        n += 1;
    }
    format!("{{\n  \"particles\": [\n{particles}\n  ],\n  \"springs\": [\n{springs}\n  ]\n}}\n")
}

#[derive(Deserialize)]
#[allow(dead_code)]
struct Mirror {
    particles: Vec<MirrorParticle>,
    springs: Vec<MirrorSpring>,
}

#[derive(Deserialize)]
#[allow(dead_code)]
struct MirrorParticle {
    x: [f64; 3],
    v: [f64; 3],
    mass: f64,
}

#[derive(Deserialize)]
#[allow(dead_code)]
struct MirrorSpring {
    i: u32,
    j: u32,
    ke: f64,
    kd: f64,
}

/// Peak resident set size of this process (MB), from /proc (0 where there is none).
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(0.0, |kb| kb / 1024.0)
}

/// The cases, in the order they run.
pub const CASES: [&str; 3] = [
    "serde_json_typed",
    "serde_json_value",
    "adflex_from_json_str",
];

/// Runs one case on the file `path` in this process and returns its JSON line.
pub fn run_case(case: &str, path: &str) -> Result<String, String> {
    let src = std::fs::read_to_string(path).map_err(|e| format!("{path}: {e}"))?;
    let t = Instant::now();
    let count = match case {
        "serde_json_typed" => {
            let m: Mirror = serde_json::from_str(&src).map_err(|e| e.to_string())?;
            m.particles.len()
        }
        "serde_json_value" => {
            let v: serde_json::Value = serde_json::from_str(&src).map_err(|e| e.to_string())?;
            v["particles"].as_array().map_or(0, Vec::len)
        }
        "adflex_from_json_str" => ModelBuilder::<f32>::from_json_str(&src)
            .map_err(|e| e.to_string())?
            .particle_count(),
        _ => return Err(format!("unknown case `{case}` (one of {CASES:?})")),
    };
    let secs = t.elapsed().as_secs_f64();
    Ok(format!(
        "{{\"case\": \"{case}\", \"mb\": {:.1}, \"particles\": {count}, \"secs\": {secs:.3}, \"peak_rss_mb\": {:.1}}}",
        src.len() as f64 / 1e6,
        peak_rss_mb()
    ))
}

/// `scene-file [--mb 50] [--file PATH]`: writes the scene (if `PATH` does not exist) and runs
/// every case in a child process.
pub fn main(args: &[String]) -> Result<(), String> {
    let get = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|k| args.get(k + 1))
    };
    let mb: f64 = match get("--mb") {
        Some(v) => v.parse().map_err(|_| format!("--mb: not a number: {v}"))?,
        None => 50.0,
    };
    let path = get("--file").cloned().unwrap_or_else(|| {
        format!(
            "{}/adflex-scene-{mb}mb.json",
            std::env::temp_dir().display()
        )
    });
    if !std::path::Path::new(&path).exists() {
        std::fs::write(&path, scene_json(mb)).map_err(|e| format!("{path}: {e}"))?;
    }
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let mut secs = Vec::new();
    for case in CASES {
        let out = Command::new(&exe)
            .args(["scene-file-case", case, &path])
            .output()
            .map_err(|e| e.to_string())?;
        if !out.status.success() {
            return Err(String::from_utf8_lossy(&out.stderr).into_owned());
        }
        let line = String::from_utf8_lossy(&out.stdout).trim().to_string();
        println!("{line}");
        let v: serde_json::Value = serde_json::from_str(&line).map_err(|e| e.to_string())?;
        secs.push((
            v["secs"].as_f64().unwrap_or(0.0),
            v["peak_rss_mb"].as_f64().unwrap_or(0.0),
        ));
    }
    let (base, mine) = (secs[0], secs[2]);
    eprintln!(
        "from_json_str / serde_json typed: time {:.2}x, peak RSS {:.2}x",
        mine.0 / base.0,
        mine.1 / base.1
    );
    Ok(())
}
