//! Ready-made scenes (the benchmark scenes of `docs/scenes.md`, the demos' scenes), built with [`crate::ModelBuilder`].

pub mod cage;
pub mod cloth;
