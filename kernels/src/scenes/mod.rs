//! Ready-made scenes: the benchmark scenes of `bench/SCENES.md`, built with [`crate::ModelBuilder`].

pub mod cloth;
