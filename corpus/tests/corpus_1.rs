//! The second half of the generated corpus (see tests/corpus.rs): a separate test crate, so
//! that cargo compiles the two halves in parallel.
#![allow(dead_code, unused_parens, clippy::all)]

mod support;

use adflex::prelude::*;
use support::{arrays_f32, arrays_f64, check, relaunch_err, run_direct, run_group, Case, Outcome};

include!(concat!(env!("OUT_DIR"), "/corpus_1.rs"));
include!(concat!(env!("OUT_DIR"), "/corpus_tests_1.rs"));
