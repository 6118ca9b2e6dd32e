//! A generated corpus of random `#[diff_kernel]`s and `#[diff_func]`s (see `build.rs` and
//! `gen.rs`), compiled and gradient-checked by `tests/corpus.rs`.
//!
//! `build.rs` writes `$OUT_DIR/corpus.rs` (the kernels and functions) and
//! `$OUT_DIR/corpus_tests.rs` (one runner per kernel, the case table and the `#[test]`s) from a
//! fixed seed, so the corpus is the same on every build. Set `ADFLEX_CORPUS_DUMP=dir` when
//! building to also copy both files into `dir` for reading.
