#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn scale(x: &Array<f32>, s: f32, y: &Array<f32>) {
    let t = tid();
    y[t] = x[t] * s;
}

fn main() {
    let x: Array<f32> = Array::zeros(4);
    let y: Array<f32> = Array::zeros(4);
    launch(scale, 4, (&x, &y));
}
