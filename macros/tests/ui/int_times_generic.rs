#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[diff_kernel]
fn twice<R: Real>(x: &Array<R>, y: &Array<R>) {
    let t = tid();
    y[t] = 2 * x[t];
}

fn main() {}
