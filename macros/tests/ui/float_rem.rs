#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn wrap(x: &Array<f64>, y: &Array<f64>) {
    let t = tid();
    y[t] = x[t] % 2.0;
}

fn main() {}
