//! Generates the corpus from a fixed seed (own xorshift generator; see `gen.rs`):
//! `$OUT_DIR/corpus.rs` (random `#[diff_func]`s and `#[diff_kernel]`s) and
//! `$OUT_DIR/corpus_tests.rs` (a runner per kernel, the case table and the `#[test]`s), included
//! by `tests/corpus.rs`; with `PARTS > 1` the kernels are split over `corpus.rs`,
//! `corpus_1.rs`, ... (and `corpus_tests.rs`, `corpus_tests_1.rs`, ...), one per test crate
//! (`tests/corpus.rs`, `tests/corpus_1.rs`, ...), which cargo compiles in parallel.

// The generator favours index loops and explicit bounds that mirror the generated code.
#[allow(
    clippy::needless_range_loop,
    clippy::manual_clamp,
    clippy::let_and_return,
    clippy::unnecessary_map_or
)]
#[path = "gen.rs"]
mod gen;

use std::collections::BTreeSet;
use std::fmt::Write;

/// The corpus' seed. Changing it gives a different corpus.
const SEED: u64 = 0xAD_F1E5_C0A9_2024;
/// Number of kernels.
const N_KERNELS: usize = 240;
/// Number of `#[diff_func]`s the kernels call.
const N_FUNCS: usize = 12;
/// Kernels per `#[test]`.
const PER_TEST: usize = 30;
/// Number of test crates the kernels are split over.
const PARTS: usize = 2;

/// The squashing functions the generated code calls to keep values in range.
pub const HELPERS: &str = "\
/// `b * tanh(x / b)`: `x` squashed into `(-b, b)`.
#[diff_func]
fn sq<R: Real>(x: R, b: R) -> R {
    b * tanh(x / b)
}

/// `x` squashed into `(m - r, m + r)`.
#[diff_func]
fn sqi<R: Real>(x: R, m: R, r: R) -> R {
    m + r * tanh((x - m) / r)
}

/// `v / (1 + |v|^2 / 100)`: length at most 5, direction kept.
#[diff_func]
fn vsq<R: Real>(v: Vec3<R>) -> Vec3<R> {
    v * (1.0 / (1.0 + length_sq(v) * 0.01))
}

/// `m / (1 + |m|_F^2 / 100)`: entries at most 5 in magnitude, signs kept.
#[diff_func]
fn msq<R: Real>(m: Mat33<R>) -> Mat33<R> {
    m * (1.0 / (1.0 + ddot(m, m) * 0.01))
}

";

thread_local! {
    static SEED_USED: std::cell::Cell<u64> = const { std::cell::Cell::new(SEED) };
}

fn sub_seed(i: u64, salt: u64) -> u64 {
    let seed = SEED_USED.with(|s| s.get());
    let mut r = gen::Rng::new(
        seed ^ salt.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ i.wrapping_mul(0xD1B5_4A32_D192_ED03),
    );
    r.next()
}

fn env_usize(name: &str) -> Option<usize> {
    println!("cargo:rerun-if-env-changed={name}");
    std::env::var(name).ok().and_then(|v| v.parse().ok())
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=gen.rs");
    println!("cargo:rerun-if-env-changed=ADFLEX_CORPUS_DUMP");
    println!("cargo:rerun-if-env-changed=ADFLEX_CORPUS_EXPERIMENT");
    let out = std::path::PathBuf::from(std::env::var_os("OUT_DIR").unwrap());
    // For bug hunting beyond the checked-in corpus: ADFLEX_CORPUS_SEED=<u64> gives another
    // corpus, ADFLEX_CORPUS_SIZE=big larger programs (slower to compile).
    println!("cargo:rerun-if-env-changed=ADFLEX_CORPUS_SEED");
    println!("cargo:rerun-if-env-changed=ADFLEX_CORPUS_SIZE");
    let seed = std::env::var("ADFLEX_CORPUS_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(SEED);
    SEED_USED.with(|s| s.set(seed));
    if std::env::var("ADFLEX_CORPUS_SIZE").is_ok_and(|v| v == "big") {
        gen::set_sizes(gen::Sizes::BIG);
    }

    let mut feat = gen::Features::default();
    let mut funcs: Vec<gen::Func> = Vec::new();
    for i in 0..N_FUNCS {
        let sigs: Vec<gen::FuncSig> = funcs.iter().map(|f| f.sig.clone()).collect();
        funcs.push(gen::gen_func(i, sub_seed(i as u64, 1), &sigs, &mut feat));
    }
    let sigs: Vec<gen::FuncSig> = funcs.iter().map(|f| f.sig.clone()).collect();
    // (ADFLEX_CORPUS_N=k: only the first k kernels, for working on the generator)
    let n_kernels = env_usize("ADFLEX_CORPUS_N").unwrap_or(N_KERNELS);
    let kernels: Vec<gen::Kernel> = (0..n_kernels)
        .map(|i| gen::gen_kernel(i, sub_seed(i as u64, 2), &sigs, &mut feat))
        .collect();

    let parts = PARTS;
    let per_part = n_kernels.div_ceil(parts);
    let mut files = Vec::new();
    for part in 0..parts {
        let lo = (part * per_part).min(n_kernels);
        let hi = ((part + 1) * per_part).min(n_kernels);
        let (code, tests) = write_part(&funcs, &kernels, lo, hi, &feat);
        let suffix = if part == 0 {
            String::new()
        } else {
            format!("_{part}")
        };
        files.push((format!("corpus{suffix}.rs"), code));
        files.push((format!("corpus_tests{suffix}.rs"), tests));
    }
    for (name, text) in &files {
        std::fs::write(out.join(name), text).unwrap();
    }
    if let Some(dir) = std::env::var_os("ADFLEX_CORPUS_DUMP") {
        let dir = std::path::PathBuf::from(dir);
        let _ = std::fs::create_dir_all(&dir);
        for (name, text) in &files {
            let _ = std::fs::write(dir.join(name), text);
        }
    }
}

/// The code (helpers, functions, kernels `lo..hi`) and the tests of one part of the corpus.
fn write_part(
    funcs: &[gen::Func],
    kernels: &[gen::Kernel],
    lo: usize,
    hi: usize,
    feat: &gen::Features,
) -> (String, String) {
    // ---- the functions and kernels ----
    let mut code = String::new();
    writeln!(code, "// Generated by corpus/build.rs (seed {:#x}, sizes {:?}); do not edit. Kernels {lo}..{hi}.", SEED_USED.with(|s| s.get()), gen::sizes()).unwrap();
    writeln!(code, "//").unwrap();
    writeln!(
        code,
        "// Constructs in the whole corpus (count of occurrences):"
    )
    .unwrap();
    for (k, v) in &feat.counts {
        writeln!(code, "//   {k}: {v}").unwrap();
    }
    writeln!(code).unwrap();
    code.push_str(HELPERS);
    for f in funcs {
        code.push_str(&f.src);
        code.push('\n');
    }
    for k in &kernels[lo..hi] {
        code.push_str(&k.src);
        code.push('\n');
    }

    // ---- runners, cases, tests ----
    let mut t = String::new();
    writeln!(
        t,
        "// Generated by corpus/build.rs (seed {:#x}); do not edit. Kernels {lo}..{hi}.\n",
        SEED_USED.with(|s| s.get())
    )
    .unwrap();
    writeln!(
        t,
        "/// Length of every array, and number of threads, of every kernel."
    )
    .unwrap();
    writeln!(t, "pub const LEN: usize = {};\n", gen::LEN).unwrap();
    for k in &kernels[lo..hi] {
        let name = &k.name;
        let n = k.n_inputs;
        let ins: Vec<String> = (0..n).map(|j| format!("&a[{j}]")).collect();
        let bs: Vec<String> = (0..n).map(|j| format!("&b[{j}]")).collect();
        let idx = if k.has_idx { "&idx, " } else { "" };
        let (pv64, pv32) = if k.value_param {
            (
                format!(", {:?}f64", gen::VALUE_PARAM),
                format!(", {:?}f32", gen::VALUE_PARAM),
            )
        } else {
            (String::new(), String::new())
        };
        let ins = ins.join(", ");
        let bs = bs.join(", ");
        writeln!(t, "fn run_{name}(xs: &[Vec<f64>], seed: u64) -> Outcome {{").unwrap();
        if k.has_idx {
            let ids: Vec<String> = k.idx.iter().map(|i| format!("{i}")).collect();
            writeln!(
                t,
                "    let idx: Array<u32> = Array::from_vec(vec![{}]);",
                ids.join(", ")
            )
            .unwrap();
        }
        writeln!(t, "    let a = arrays_f64(xs);").unwrap();
        writeln!(t, "    let y: Array<f64> = Array::zeros(LEN);").unwrap();
        writeln!(t, "    let checked = check(&[{ins}], &[&y], seed, &|m| run_direct(m, {name}, LEN, ({ins}, {idx}LEN{pv64}, &y)));").unwrap();
        // Two launches writing one array (the second on inputs moved within their range).
        let xs_ins: Vec<String> = (0..n).map(|j| format!("&xs[{j}]")).collect();
        let xs_ins = xs_ins.join(", ");
        writeln!(t, "    let moved: Vec<Vec<f64>> = xs.iter().map(|v| v.iter().rev().map(|x| 2.0 - x).collect()).collect();").unwrap();
        writeln!(t, "    let relaunch_err = relaunch_err(&arrays_f64(xs), &arrays_f64(&moved), seed, &|m, xs: &[Array<f64>], y: &Array<f64>| run_direct(m, {name}, LEN, ({xs_ins}, {idx}LEN{pv64}, y)));").unwrap();
        writeln!(t, "    let a = arrays_f64(xs);").unwrap();
        writeln!(t, "    let y64: Array<f64> = Array::zeros(LEN);").unwrap();
        writeln!(
            t,
            "    run_direct(Mode::Forward, {name}, LEN, ({ins}, {idx}LEN{pv64}, &y64));"
        )
        .unwrap();
        writeln!(t, "    let b = arrays_f32(xs);").unwrap();
        writeln!(t, "    let y32: Array<f32> = Array::zeros(LEN);").unwrap();
        writeln!(
            t,
            "    run_direct(Mode::Forward, {name}, LEN, ({bs}, {idx}LEN{pv32}, &y32));"
        )
        .unwrap();
        writeln!(
            t,
            "    Outcome {{ checked, relaunch_err, y64: y64.to_vec(), y32: y32.to_vec() }}"
        )
        .unwrap();
        writeln!(t, "}}\n").unwrap();
    }
    writeln!(t, "/// The kernels of this part, with their sources.").unwrap();
    writeln!(t, "pub static CASES: &[Case] = &[").unwrap();
    for (i, k) in kernels.iter().enumerate().take(hi).skip(lo) {
        // the functions it calls, transitively
        let mut need: BTreeSet<usize> = k.calls.clone();
        loop {
            let more: BTreeSet<usize> = need
                .iter()
                .flat_map(|&f| funcs[f].calls.iter().cloned())
                .collect();
            let before = need.len();
            need.extend(more);
            if need.len() == before {
                break;
            }
        }
        writeln!(
            t,
            "    Case {{ name: {:?}, inputs: {}, seed: {:#x}, run: run_{}, src: {:?}, funcs: &{:?} }},",
            k.name,
            k.n_inputs,
            sub_seed(i as u64, 3),
            k.name,
            k.src,
            need.iter().collect::<Vec<_>>()
        )
        .unwrap();
    }
    writeln!(t, "];\n").unwrap();
    writeln!(t, "/// The source of every generated `#[diff_func]`.").unwrap();
    writeln!(t, "pub static FUNC_SRC: &[&str] = &[").unwrap();
    for f in funcs {
        writeln!(t, "    {:?},", f.src).unwrap();
    }
    writeln!(t, "];\n").unwrap();
    let mut g = lo;
    while g < hi {
        let e = (g + PER_TEST).min(hi);
        writeln!(
            t,
            "#[test]\nfn corpus_k{g:03}_to_k{:03}() {{\n    run_group(&CASES[{}..{}]);\n}}\n",
            e - 1,
            g - lo,
            e - lo
        )
        .unwrap();
        g = e;
    }
    (code, t)
}
