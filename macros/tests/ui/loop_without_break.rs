#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>, y: &Array<f32>) {
    let t = tid();
    let mut s = x[t];
    loop {
        s = s * 0.5;
    }
    y[t] = s;
}

fn main() {}
