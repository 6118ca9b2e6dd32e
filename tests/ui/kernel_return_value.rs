use adflex::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>) -> f32 {
    x[tid()] * 2.0
}

fn main() {}
