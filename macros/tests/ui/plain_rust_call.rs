#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

fn helper(a: f32) -> f32 {
    a * 2.0
}

#[diff_kernel]
fn k(x: &Array<f32>, y: &Array<f32>) {
    let t = tid();
    y[t] = helper(x[t]);
}

fn main() {}
