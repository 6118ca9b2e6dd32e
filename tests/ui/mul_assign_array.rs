use adflex::prelude::*;

#[diff_kernel]
fn k(x: &Array<f32>) {
    let t = tid();
    x[t] *= 2.0;
}

fn main() {}
