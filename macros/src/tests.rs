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

/// Every construct outside the kernel language is refused by the check pass with its one
/// message (and lowering, which then does not run, adds nothing).
#[test]
fn check_refuses_each_construct_once() {
    let cases: &[(Kind, proc_macro2::TokenStream, &str)] = &[
        (
            Kind::Kernel,
            quote!(let c = |a: f32| a;),
            "closures are not supported",
        ),
        (
            Kind::Kernel,
            quote!(let v = vec![1.0];),
            "macro calls are not supported",
        ),
        (
            Kind::Kernel,
            quote!(println!("{}", 1);),
            "macro calls are not supported",
        ),
        (
            Kind::Kernel,
            quote!(let r = &s;),
            "references are not supported",
        ),
        (Kind::Kernel, quote!(let r = *s;), "references and pointers"),
        (
            Kind::Kernel,
            quote!(let Some(a) = s else { return; };),
            "`let .. else`",
        ),
        (
            Kind::Kernel,
            quote!(let t = (s, s);),
            "tuples are not supported",
        ),
        (Kind::Kernel, quote!(let p = P { a: s };), "struct literals"),
        (Kind::Kernel, quote!(let a = [s, s];), "array literals"),
        (
            Kind::Kernel,
            quote!(let r = 0..3;),
            "ranges are only supported",
        ),
        (Kind::Kernel, quote!('a: for i in 0..3 {}), "loop labels"),
        (
            Kind::Kernel,
            quote!(for i in 0..3 {
                break 'a;
            }),
            "labelled `break`",
        ),
        (
            Kind::Kernel,
            quote!(let b = 'a: { 1.0 };),
            "labelled blocks",
        ),
        (
            Kind::Kernel,
            quote!(loop {
                let a = s;
            }),
            "`loop` without `break`",
        ),
        (Kind::Kernel, quote!(break;), "`break` outside of a loop"),
        (
            Kind::Kernel,
            quote!(for i in 0..3 {
                continue 'a;
            }),
            "labelled `continue`",
        ),
        (
            Kind::Kernel,
            quote!(loop {
                break s;
            }),
            "`break` with a value",
        ),
        (
            Kind::Kernel,
            quote!(while let Some(a) = s {}),
            "`while let`",
        ),
        (Kind::Kernel, quote!(if let Some(a) = s {}), "`if let`"),
        (
            Kind::Kernel,
            quote!(let a = s.sqrt();),
            "method calls are not differentiable",
        ),
        (
            Kind::Kernel,
            quote!(let a = Vec3::new(s, s, s);),
            "is not differentiable",
        ),
        (
            Kind::Kernel,
            quote!(let a = <f32 as T>::f(s);),
            "qualified paths",
        ),
        (
            Kind::Kernel,
            quote!(let a = no_grad(s, s);),
            "`no_grad` takes one expression",
        ),
        (
            Kind::Kernel,
            quote!(let a = tid(s);),
            "`tid()` takes no arguments",
        ),
        (Kind::Kernel, quote!(let a = s.q;), "only the components"),
        (
            Kind::Kernel,
            quote!(let a = "s";),
            "only numeric and boolean literals",
        ),
        (
            Kind::Kernel,
            quote!(let (a, b) = s;),
            "this pattern is not supported",
        ),
        (
            Kind::Kernel,
            quote!(let [a, (b)] = s;),
            "destructure into names",
        ),
        (Kind::Kernel, quote!(let a;), "declare locals with a value"),
        (
            Kind::Kernel,
            quote!(
                fn g() {}
            ),
            "items (fn, use, const, struct ..)",
        ),
        (
            Kind::Kernel,
            quote!(for (i, j) in 0..3 {}),
            "binds a plain name",
        ),
        (Kind::Kernel, quote!(for i in s {}), "integer ranges only"),
        (Kind::Kernel, quote!(for i in 0.. {}), "needs both bounds"),
        (
            Kind::Kernel,
            quote!(let a = match 1 { 0 => s, 1 => s };),
            "must end with a `_ =>`",
        ),
        (
            Kind::Kernel,
            quote!(let a = match 1 { ..=3 => s, _ => s };),
            "need both bounds",
        ),
        (
            Kind::Kernel,
            quote!(let a = match 1 { Some(x) => s, _ => s };),
            "takes integer literals",
        ),
        (Kind::Kernel, quote!(return s;), "returns no value"),
        (
            Kind::Kernel,
            quote!(let a = unsafe { s };),
            "`unsafe` blocks",
        ),
        (
            Kind::Func,
            quote!(let a = tid();),
            "`tid()` is only available",
        ),
    ];
    for (kind, stmts, msg) in cases {
        let item = match kind {
            Kind::Kernel => quote!(fn k(s: f32, y: &Array<f32>) { #stmts }),
            Kind::Func => quote!(fn f(s: f32) -> f32 { #stmts s }),
        };
        let out = expand(quote!(), item, *kind).to_string();
        assert_eq!(
            out.matches("compile_error").count(),
            1,
            "{stmts}: one error expected: {out}"
        );
        assert!(out.contains(msg), "{stmts}: `{msg}` expected: {out}");
    }
}

/// The emitted `static_scatters` of a kernel, mode by mode (forward, adjoint, tangent):
/// `Some` with the targets' parameter indices, or `None`.
fn static_scatters(kernel: proc_macro2::TokenStream) -> Vec<String> {
    let out = expand(quote!(), kernel, Kind::Kernel).to_string();
    let from = out
        .find("fn static_scatters")
        .expect("static_scatters is emitted");
    let list = &out[from..from + out[from..].find("fn scatter_indices").unwrap()];
    list.split(":: option :: Option :: ")
        .skip(1)
        .map(|m| match m.find("targets : & [") {
            Some(t) => {
                let rest = &m[t + "targets : & [".len()..];
                format!("Some[{}]", &rest[..rest.find(']').unwrap()].trim())
            }
            None => "None".to_string(),
        })
        .collect()
}

#[test]
fn scatters_through_index_arrays_are_static_and_others_are_not() {
    // Indices read from an index array at the thread id: static in every mode (the adjoint
    // scatters into `x`'s gradient at `i` and `j`).
    let pairs = static_scatters(quote! {
        fn k(x: &Array<f32>, pairs: &Array<[u32; 2]>, f: &Array<f32>) {
            let t = tid();
            let [i, j] = pairs[t];
            f.atomic_add(i, x[i] - x[j]);
        }
    });
    assert_eq!(pairs, ["Some[2usize]", "Some[0usize]", "Some[2usize]"]);
    // A constant loop is unrolled: its indices are constants, static.
    let unrolled = static_scatters(quote! {
        fn k(x: &Array<f32>, f: &Array<f32>) {
            for k in 0..4 {
                f.atomic_add(k, x[tid()]);
            }
        }
    });
    assert_eq!(unrolled, ["Some[1usize]", "Some[]", "Some[1usize]"]);
    // A dynamic loop's index, a value parameter, an index computed in a branch: not static.
    let loop_index = static_scatters(quote! {
        fn k(x: &Array<f32>, m: usize, f: &Array<f32>) {
            for k in 0..m {
                f.atomic_add(k, x[tid()]);
            }
        }
    });
    assert_eq!(loop_index, ["None", "Some[]", "None"]);
    let value = static_scatters(quote! {
        fn k(x: &Array<f32>, n: usize, f: &Array<f32>) {
            f.atomic_add(n, x[tid()]);
        }
    });
    assert_eq!(value, ["None", "Some[]", "None"]);
    let branch = static_scatters(quote! {
        fn k(x: &Array<f32>, pairs: &Array<[u32; 2]>, f: &Array<f32>) {
            let t = tid();
            if x[t] > 0.0 {
                let i = pairs[t][0];
                f.atomic_add(i, x[t]);
            }
        }
    });
    assert_eq!(branch, ["None", "Some[]", "None"]);
}
