#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>, y: &Array<f32>) {
    let t = tid();
    let a = x[t];
    y[t] = *a;
}

fn main() {}
