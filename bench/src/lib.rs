//! Benchmarks and charts of adflex. The binary (`src/main.rs`) is the entry point:
//! `cargo run --release -p adflex-bench -- <scatter|kernels|cloth|peers|charts> ...`.

pub mod bound;
pub mod charts;
pub mod cloth;
pub mod gen;
pub mod hand;
pub mod kernels_cmp;
pub mod mpm;
pub mod overhead;
pub mod peers;
pub mod robots;
pub mod scatter;
pub mod scene_file;
pub mod second_order;
pub mod small;
pub mod smoke;
pub mod timing;
pub mod topo;
pub mod worlds;

/// The value after `--name` in `rest`, as a count.
pub fn arg(rest: &[String], name: &str) -> Option<usize> {
    rest.iter()
        .position(|a| a == name)
        .and_then(|k| rest.get(k + 1))
        .and_then(|v| v.parse().ok())
}

/// Runs `bench/peers/<script>` with `python` and `args`, and returns the first JSON line it
/// prints, or `None` after printing its stderr.
pub fn peer_json(python: &str, script: &str, args: &[String]) -> Option<serde_json::Value> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/peers/").to_string() + script;
    let out = std::process::Command::new(python)
        .arg(&path)
        .args(args)
        .output()
        .expect("the peer's python runs");
    let text = String::from_utf8_lossy(&out.stdout);
    let found = text.lines().find_map(|l| serde_json::from_str(l).ok());
    if found.is_none() {
        eprintln!(
            "{script} printed no result: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    found
}
