//! Continua by the moving least squares material point method (MLS-MPM, Hu et al. 2018), in
//! 2D ([`D2`], the default) and 3D ([`D3`], [`MpmBuilder::new_3d`]): particles carry mass, velocity, the APIC affine matrix `C` and the deformation
//! gradient `F`; each step scatters them to a grid with quadratic B-splines, updates the grid
//! velocities with gravity and the walls, and gathers them back.
//!
//! - [`MpmBuilder`] describes the grid, walls, particles, [`Material`]s (elastic, fluid, and
//!   snow, whose plasticity is in [`plastic`]) and actuators;
//!   [`MpmBuilder::finalize`] checks it into an [`Mpm`].
//! - [`Mpm::step`] records the three kernels of a step on a tape ([`kernels::mpm_p2g`],
//!   [`kernels::mpm_grid_update`], [`kernels::mpm_g2p`]); every per-particle parameter, the
//!   gravity, the initial state and the actuation can require gradients.
//! - The particle-to-grid scatter is deterministic: the same bits on any number of threads.
//! - [`MpmState`] implements [`Checkpoint`](adflex_runtime::checkpoint::Checkpoint), so long
//!   rollouts keep only their checkpoints in memory.
//!
//! The model and the boundary conditions are those of DiffTaichi's `diffmpm` (Hu et al.
//! 2020): [`scenes::walker`] builds its walking robot, [`WalkerTask`] its controller and loss.
//! [`scenes::mpm99`] has the fluid, jelly and snow of Taichi's `mpm99`.

mod dim;
pub mod kernels;
mod model;
pub mod plastic;
pub mod scenes;
mod step;

pub use dim::{Dim, D2, D3};
pub use model::{Floor, Material, Mpm, MpmBuilder, MpmState};
pub use scenes::WalkerTask;
pub use step::Launches;
