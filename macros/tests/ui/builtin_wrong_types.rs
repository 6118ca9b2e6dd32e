#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn wrong(x: &Array<f64>, v: &Array<Vec3<f64>>, y: &Array<f64>) {
    let t = tid();
    y[t] = dot(x[t], v[t]);
}

fn main() {}
