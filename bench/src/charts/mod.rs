//! `charts --out docs/charts [--peers FILE] [--quick] [--only NAME,...]`: every chart of
//! docs/performance.md as SVG, with the numbers behind each in `<name>.json`.

pub mod continua;
pub mod gradients;
pub mod integrators;
pub mod peers;
pub mod plot;

use std::path::PathBuf;

/// Options of the charts command.
pub struct Opts {
    pub out: PathBuf,
    pub peers: PathBuf,
    pub quick: bool,
    pub only: Option<Vec<String>>,
}

pub fn parse(args: &[String]) -> Result<Opts, String> {
    let mut o = Opts {
        out: PathBuf::from("docs/charts"),
        peers: PathBuf::new(),
        quick: false,
        only: None,
    };
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut val = |name: &str| it.next().cloned().ok_or(format!("{name} needs a value"));
        match a.as_str() {
            "--out" => o.out = val("--out")?.into(),
            "--peers" => o.peers = val("--peers")?.into(),
            "--quick" => o.quick = true,
            "--only" => o.only = Some(val("--only")?.split(',').map(String::from).collect()),
            other => return Err(format!("unknown option `{other}`")),
        }
    }
    if o.peers.as_os_str().is_empty() {
        o.peers = o.out.join("peers.jsonl");
    }
    Ok(o)
}

type ChartFn = fn(&Opts) -> Result<serde_json::Value, Box<dyn std::error::Error>>;

pub fn main(o: &Opts) -> Result<(), Box<dyn std::error::Error>> {
    std::fs::create_dir_all(&o.out)?;
    let charts: [(&str, ChartFn); 7] = [
        ("integrators_error_vs_cost", |o| {
            integrators::error_vs_cost(&o.out, o.quick)
        }),
        ("integrators_stability", |o| {
            integrators::stability(&o.out, o.quick)
        }),
        ("integrators_imex_stability", |o| {
            integrators::imex_stability(&o.out, o.quick)
        }),
        ("gradient_accuracy", |o| {
            gradients::accuracy(&o.out, o.quick)
        }),
        ("gradient_long_horizon", |o| {
            gradients::long_horizon(&o.out, o.quick)
        }),
        ("peers", |o| peers::chart(&o.out, &o.peers)),
        ("mpm_stability", |o| {
            continua::mpm_stability(&o.out, o.quick)
        }),
    ];
    for (name, f) in charts {
        if let Some(only) = &o.only {
            if !only.iter().any(|n| name.starts_with(n.as_str())) {
                continue;
            }
        }
        eprintln!("chart {name}");
        let t0 = std::time::Instant::now();
        let data = f(o)?;
        if !data.is_null() {
            let meta = serde_json::json!({
                "chart": name,
                "machine": crate::timing::machine(),
                "date": crate::timing::now_iso(),
                "load_avg_at_end": crate::timing::loadavg(),
                "seconds": t0.elapsed().as_secs_f64(),
                "data": data,
            });
            std::fs::write(
                o.out.join(format!("{name}.json")),
                serde_json::to_string_pretty(&meta)? + "\n",
            )?;
        }
        eprintln!("  done in {:.1} s", t0.elapsed().as_secs_f64());
    }
    Ok(())
}
