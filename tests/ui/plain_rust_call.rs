use adflex::prelude::*;

fn helper(a: f32) -> f32 {
    a * 2.0
}

#[diff_kernel]
fn k(x: &Array<f32>, y: &Array<f32>) {
    let t = tid();
    y[t] = helper(x[t]);
}

fn main() {}
