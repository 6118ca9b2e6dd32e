#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_func]
fn f(a: f32) -> f32 {
    a * tid() as f32
}

fn main() {}
