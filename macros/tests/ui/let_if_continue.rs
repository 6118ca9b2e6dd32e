#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn skip(x: &Array<f64>, n: usize, y: &Array<f64>) {
    let t = tid();
    let mut s = 0.0;
    for k in 0..n {
        let b = if x[k] > 0.0 { continue; } else { x[k] * 2.0 };
        s = s + b;
    }
    y[t] = s;
}

fn main() {}
