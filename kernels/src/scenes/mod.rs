//! Ready-made scenes and scene builders, built with [`crate::ModelBuilder`]: the benchmark
//! scene of `docs/scenes.md` ([`cloth`]), the demos' cage ([`cage`]) and soft bodies
//! ([`soft::TetGrid`]).

pub mod cage;
pub mod cloth;
pub mod soft;
