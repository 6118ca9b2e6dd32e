use adflex::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>, kd: f32) {
    let t = tid();
    kd = x[t];
}

fn main() {}
