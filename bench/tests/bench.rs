//! Tests of the benchmark binary and of the kernels it compares.

use std::process::Command;

use adflex_bench::cloth::FIELDS;

fn run(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_adflex-bench"))
        .args(args)
        .output()
        .expect("running adflex-bench");
    assert!(
        out.status.success(),
        "adflex-bench {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// `cloth` prints exactly one JSON line with every field, and its loss at N = 32, T = 100 is
/// Warp's (0.00829959, /work/peers-results.jsonl) to 4 significant digits.
#[test]
fn cloth_json_line_and_loss_match_warp() {
    let out = run(&[
        "cloth",
        "--n",
        "32",
        "--steps",
        "100",
        "--reps",
        "1",
        "--threads",
        "2",
    ]);
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 1, "expected one line, got {out:?}");
    let v: serde_json::Value = serde_json::from_str(lines[0]).expect("valid JSON");
    let obj = v.as_object().expect("a JSON object");
    for f in FIELDS {
        assert!(obj.contains_key(f), "missing field {f} in {out}");
    }
    assert_eq!(obj.len(), FIELDS.len(), "unexpected fields in {out}");
    assert_eq!(v["system"], "adflex");
    assert_eq!(
        (v["n"].as_u64(), v["steps"].as_u64(), v["threads"].as_u64()),
        (Some(32), Some(100), Some(2))
    );
    for f in [
        "fwd_s_per_step",
        "fwd_bwd_s_per_step",
        "grad_v0_norm",
        "grad_ke_norm",
        "peak_rss_mb",
    ] {
        let x = v[f]
            .as_f64()
            .unwrap_or_else(|| panic!("{f} is not a number in {out}"));
        assert!(x.is_finite() && x > 0.0, "{f} = {x}");
    }
    let loss = v["loss"].as_f64().unwrap();
    assert_eq!(
        format!("{loss:.3e}"),
        format!("{:.3e}", 0.00829959f64),
        "loss {loss}"
    );
}

/// The hand-written kernels and the generated ones agree (forces and adjoints).
#[test]
fn hand_written_kernels_match_generated() {
    let e = adflex_bench::kernels_cmp::check::<f64>(8);
    assert!(e.iter().all(|&x| x < 1e-12), "f64: {e:?}");
    // In f32 the two computations round differently; f64 is the check.
    let e = adflex_bench::kernels_cmp::check::<f32>(16);
    assert!(e.iter().all(|&x| x < 3e-5), "f32: {e:?}");
}

/// Every scatter strategy gives the serial sums (bitwise for the ordered ones).
#[test]
fn scatter_strategies_agree() {
    use adflex_bench::scatter::*;
    let (n, x, pairs) = grid(40);
    let mut reference = vec![Default::default(); n];
    serial(&x, &pairs, &mut reference);
    let mut out = reference.clone();
    adflex_runtime::with_threads(2, || {
        logs(&x, &pairs, &mut out, 256);
        assert!(out == reference);
        let mut pool = Vec::new();
        logs_reused(&x, &pairs, &mut out, 256, &mut pool);
        assert!(out == reference);
        let mut pool = Vec::new();
        dense(&x, &pairs, &mut out, 256, &mut pool);
        let scale = reference.iter().map(|v| v.norm()).fold(0.0f32, f32::max);
        assert!(out
            .iter()
            .zip(&reference)
            .all(|(a, b)| (a - b).norm() <= 1e-5 * scale));
        cas(&x, &pairs, &mut out, 256);
        assert!(out
            .iter()
            .zip(&reference)
            .all(|(a, b)| (a - b).norm() <= 1e-5 * scale));
    });
}
