//! Benchmarks and charts of adflex. The binary (`src/main.rs`) is the entry point:
//! `cargo run --release -p adflex-bench -- <scatter|kernels|cloth|peers|charts> ...`.

pub mod bound;
pub mod charts;
pub mod cloth;
pub mod gen;
pub mod hand;
pub mod kernels_cmp;
pub mod mpm;
pub mod overhead;
pub mod peers;
pub mod robots;
pub mod scatter;
pub mod scene_file;
pub mod small;
pub mod smoke;
pub mod timing;
pub mod topo;
pub mod worlds;
