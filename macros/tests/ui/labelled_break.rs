#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>, n: usize, y: &Array<f32>) {
    let t = tid();
    let mut s = 0.0;
    for i in 0..n {
        for j in 0..n {
            s = s + x[i] * x[j];
            if s > 10.0 {
                break 'outer;
            }
        }
    }
    y[t] = s;
}

fn main() {}
