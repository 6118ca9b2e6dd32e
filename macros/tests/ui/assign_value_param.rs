#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>, kd: f32) {
    let t = tid();
    kd = x[t];
}

fn main() {}
