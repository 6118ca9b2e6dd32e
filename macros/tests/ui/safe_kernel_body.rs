// A hand-written kernel body must be an `unsafe impl`: its views must not outlive the launch.
use std::ops::Range;

use adflex_runtime::kernel::{Exec, KernelBody, Mode, ParamInfo, ScatterLog};
use adflex_runtime::AnyArray;

#[derive(Clone, Copy)]
struct Keep;

impl KernelBody<()> for Keep {
    const NAME: &'static str = "keep";
    const PARAMS: &'static [ParamInfo] = &[];
    fn arrays(_: &()) -> Vec<Option<&dyn AnyArray>> {
        Vec::new()
    }
    fn run(&self, _: Mode, _: &(), _: Range<usize>, _: &Exec) -> Vec<ScatterLog> {
        Vec::new()
    }
}

fn main() {}
