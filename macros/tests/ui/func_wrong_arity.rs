#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_func]
fn energy(a: f32, b: f32) -> f32 {
    a * b
}

#[diff_kernel]
fn k(x: &Array<f32>, y: &Array<f32>) {
    let t = tid();
    y[t] = energy(x[t]);
}

fn main() {}
