#![allow(unused_imports)]
use adflex_macros::{diff_func, diff_kernel};
use adflex_runtime::prelude::*;

#[derive(Clone, Copy)]
struct Particle {
    mass: f32,
}

#[diff_kernel]
fn k(x: &Array<f32>, y: &Array<f32>) {
    let t = tid();
    let p = Particle { mass: x[t] };
    y[t] = x[t];
}

fn main() {
    let p = Particle { mass: 1.0 };
    assert_eq!(p.mass, 1.0);
}
