#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

fn square_adj(a: f32, adj_out: f32) -> (f32,) {
    (2.0 * a * adj_out,)
}

#[diff_func(adjoint = square_adj)]
fn square(a: f32) -> f32 {
    a * a
}

fn main() {}
