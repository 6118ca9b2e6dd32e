//! Compile-fail tests: every construct outside the kernel language is rejected with the
//! macro's own message at the user's span (and nothing else). Bless with
//! `TRYBUILD=overwrite cargo test -p adflex-macros --test ui`.

#[test]
fn ui() {
    let t = trybuild::TestCases::new();
    t.compile_fail("tests/ui/*.rs");
}
