//! Ready-made scenes and scene builders, built with [`crate::ModelBuilder`]: the benchmark
//! scenes of `bench/SCENES.md` ([`cloth`]) and soft bodies ([`soft::TetGrid`]).

pub mod cloth;
pub mod soft;
