#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn k(x: &Array<Vec3>, y: &Array<f32>) {
    let t = tid();
    let v = x[t];
    y[t] = v.norm();
}

fn main() {}
