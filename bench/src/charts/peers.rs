//! Chart 5: time per step of the cloth benchmark against N, for adflex and its peers, from the
//! JSONL that `adflex-bench peers` writes.

use std::collections::BTreeMap;

use serde_json::{json, Value};

use super::plot::{Chart, Series, Style};

/// Reads the JSONL; returns the lines that parse.
pub fn read(path: &std::path::Path) -> Result<Vec<Value>, Box<dyn std::error::Error>> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("{}: {e} (run `adflex-bench peers` first)", path.display()))?;
    Ok(text
        .lines()
        .filter_map(crate::peers::parse_json_line)
        .collect())
}

fn label(system: &str) -> String {
    match system {
        "adflex-1t" => "adflex, 1 thread".into(),
        "adflex-2t" => "adflex, 2 threads".into(),
        "warp-cpu" => "Warp (CPU, 1 thread)".into(),
        "taichi-cpu" => "Taichi (CPU)".into(),
        "jax-cpu" => "JAX (CPU, jit)".into(),
        s => s.into(),
    }
}

pub fn chart(
    out: &std::path::Path,
    path: &std::path::Path,
) -> Result<Value, Box<dyn std::error::Error>> {
    let rows = read(path)?;
    let mut by: BTreeMap<String, Vec<&Value>> = BTreeMap::new();
    for r in &rows {
        if let Some(s) = r["system"].as_str() {
            by.entry(s.to_string()).or_default().push(r);
        }
    }
    let order = [
        "adflex-1t",
        "adflex-2t",
        "warp-cpu",
        "taichi-cpu",
        "jax-cpu",
    ];
    let mut systems: Vec<&String> = by.keys().collect();
    systems.sort_by_key(|s| order.iter().position(|o| o == s).unwrap_or(order.len()));
    let date = rows
        .first()
        .and_then(|r| r["date"].as_str())
        .unwrap_or("?")
        .to_string();
    for (field, file, what) in [
        ("fwd_s_per_step", "peers_forward.svg", "forward"),
        (
            "fwd_bwd_s_per_step",
            "peers_forward_backward.svg",
            "forward + backward",
        ),
    ] {
        let mut c = Chart::new(
            format!("Cloth benchmark: {what} time per step vs N (f32, 100 steps)"),
            "N (particles per side)",
            "seconds per step",
        )
        .log_log();
        c.note = Some(format!("One run of `adflex-bench peers` ({date}); best of 3 reps per system and size. Taichi's gradients are NaN on this scene."));
        for (k, s) in systems.iter().enumerate() {
            let mut pts: Vec<(f64, f64)> = by[*s]
                .iter()
                .filter_map(|r| Some((r["n"].as_f64()?, r[field].as_f64()?)))
                .collect();
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
            let color = order.iter().position(|o| o == s).unwrap_or(5 + k);
            c.series
                .push(Series::new(label(s), pts, Style::Line, color));
        }
        c.write(&out.join(file))?;
    }
    std::fs::write(out.join("peers_table.md"), table(&rows, &systems, &by))?;
    Ok(json!({ "source": path.display().to_string(), "rows": rows.len() }))
}

fn num(v: &Value, f: &str) -> Option<f64> {
    v[f].as_f64()
}

/// The markdown table of a peers run: one row per size and system, times in ms per step and
/// as a ratio to Warp's at the same size.
fn table(rows: &[Value], systems: &[&String], by: &BTreeMap<String, Vec<&Value>>) -> String {
    let mut sizes: Vec<u64> = rows.iter().filter_map(|r| r["n"].as_u64()).collect();
    sizes.sort();
    sizes.dedup();
    let mut t = String::from(
        "| N | system | forward (ms/step) | fwd+bwd (ms/step) | fwd / Warp | fwd+bwd / Warp | loss | grad_v0_norm | peak RSS (MB) | load avg |\n\
         |---:|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for n in sizes {
        let at = |s: &str| {
            by.get(s)
                .and_then(|v| v.iter().find(|r| r["n"].as_u64() == Some(n)).copied())
        };
        let warp = at("warp-cpu");
        for s in systems {
            let Some(r) = at(s) else { continue };
            let ratio = |f: &str| match (num(r, f), warp.and_then(|w| num(w, f))) {
                (Some(a), Some(b)) => format!("{:.2}", a / b),
                _ => "-".into(),
            };
            let ms = |f: &str| num(r, f).map_or("-".into(), |x| format!("{:.3}", x * 1e3));
            let g = num(r, "grad_v0_norm").map_or("NaN".into(), |x| format!("{x:.4e}"));
            t += &format!(
                "| {n} | {} | {} | {} | {} | {} | {} | {g} | {} | {} |\n",
                label(s),
                ms("fwd_s_per_step"),
                ms("fwd_bwd_s_per_step"),
                ratio("fwd_s_per_step"),
                ratio("fwd_bwd_s_per_step"),
                num(r, "loss").map_or("-".into(), |x| format!("{x:.7}")),
                num(r, "peak_rss_mb").map_or("-".into(), |x| format!("{x:.0}")),
                r["load_avg"].as_str().unwrap_or("-"),
            );
        }
    }
    t
}
