use adflex::prelude::*;

#[diff_func]
fn f(a: f32) -> f32 {
    a * tid() as f32
}

fn main() {}
