//! The physics crate's integration tests, one binary (one link, one copy of the generic
//! code they instantiate) with a module per subject.

mod common;

mod articulation;
mod cloth;
mod contact_leak;
mod coupling;
mod every_force;
mod families;
mod fluid;
mod gradients;
mod integrators;
mod link_contact;
mod losses;
mod mpm;
mod particle_radius;
mod physics;
mod restitution;
mod scene_file;
mod second_order;
mod snow;
mod soft_body;
mod solver_failure;
mod stability;
mod statics;
mod tied;
mod user_force_checks;
mod validation;
mod worlds;
mod xpbd_cloth;
