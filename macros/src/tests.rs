//! Unit tests of the compiler that need no runtime: lowering shapes and the code dump.

use quote::quote;

use crate::expand::expand;
use crate::Kind;

#[test]
fn expand_dir_writes_the_generated_code() {
    let dir = std::env::temp_dir().join(format!("adflex-expand-{}", std::process::id()));
    std::env::set_var("ADFLEX_EXPAND_DIR", &dir);
    let out = expand(
        quote!(),
        quote! {
            fn scale(x: &Array<f32>, s: f32, y: &Array<f32>) {
                let t = tid();
                y[t] = x[t] * s;
            }
        },
        Kind::Kernel,
    );
    std::env::remove_var("ADFLEX_EXPAND_DIR");
    let text = std::fs::read_to_string(dir.join("scale.rs")).expect("the dump file exists");
    assert!(text.contains("fn run("), "{text}");
    assert!(
        text.contains("adj_mul"),
        "the adjoint rule of `*` is called: {text}"
    );
    assert!(
        text.contains("tan_mul"),
        "the tangent rule of `*` is called: {text}"
    );
    assert!(!out.to_string().contains("compile_error"));
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn errors_become_compile_errors_with_a_stub() {
    let out = expand(
        quote!(),
        quote! {
            fn bad(x: &Array<f32>, y: &Array<f32>) {
                let c = |a: f32| a;
                y[tid()] = x[tid()].norm();
            }
        },
        Kind::Kernel,
    )
    .to_string();
    assert_eq!(out.matches("compile_error").count(), 2, "{out}");
    assert!(out.contains("closures are not supported"), "{out}");
    assert!(out.contains("call the builtin `length(v)`"), "{out}");
    assert!(
        out.contains("struct bad"),
        "the stub keeps the name defined: {out}"
    );
}

#[test]
fn while_loop_lowers_to_a_loop_with_an_exit() {
    let out = expand(
        quote!(),
        quote! {
            fn f(x: f64, n: usize) -> f64 {
                let mut i = 0;
                let mut s = x;
                while i < n {
                    s = s * x;
                    i += 1;
                }
                s
            }
        },
        Kind::Func,
    )
    .to_string();
    // The adjoint pops each iteration's carried values off a stack.
    assert!(out.contains("__stack"), "{out}");
    assert!(out.contains("pop"), "{out}");
}
