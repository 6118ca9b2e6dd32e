//! Losses users write every time, as kernels that *add* into a loss array (`out[0]`, usually
//! of length 1): on a plain tape, several terms and several steps add into one array; in a
//! [`Checkpointed`] rollout, the per-state loss
//! closure calls them with the accumulator it is given.
//!
//! Every function records one launch (on `tape`) and is differentiable with respect to the
//! positions (and, where an array is passed, its values); `scale` multiplies the term.
//!
//! ```
//! use adflex_kernels::losses;
//! use adflex_kernels::prelude::*;
//! use adflex_runtime::{Array, Tape, Vec3};
//!
//! // A particle thrown sideways: how far from (1, 0, 0) does it end, and how do the initial
//! // velocities change that?
//! let mut b = ModelBuilder::<f64>::new();
//! b.add_particle(Vec3::new(0.0, 1.0, 0.0), Vec3::new(1.0, 0.0, 0.0), 1.0);
//! let model = b.finalize();
//! let s0 = model.state();
//! let v0 = s0.v.clone().requires_grad();
//! let mut tape = Tape::new();
//! let end = SemiImplicitEuler.rollout(&model, &mut tape, &s0, None, 1e-2, 50).unwrap();
//! let loss = Array::zeros(1);
//! losses::distance_to_target(&mut tape, &end.x, &[0], Vec3::new(1.0, 0.0, 0.0), 1.0, &loss);
//! tape.backward(&loss).unwrap();
//! // It falls below the target: throwing it higher (against the gradient) lands it nearer.
//! assert!(v0.grad().unwrap().get(0).y < 0.0);
//! ```

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use crate::model::Model;
use crate::state::BodyState;

/// `out[0] += scale * |x[idx[t]] - target|^2`.
#[diff_kernel]
pub fn sq_distance_to_point<R: Real>(
    x: &Array<Vec3<R>>,
    idx: &Array<u32>,
    target: Vec3<R>,
    scale: R,
    out: &Array<R>,
) {
    let d = x[idx[tid()]] - target;
    out.atomic_add(0, scale * dot(d, d));
}

/// `out[0] += scale * |x[t] - y[t]|^2`.
#[diff_kernel]
pub fn sq_distance_between<R: Real>(
    x: &Array<Vec3<R>>,
    y: &Array<Vec3<R>>,
    scale: R,
    out: &Array<R>,
) {
    let t = tid();
    let d = x[t] - y[t];
    out.atomic_add(0, scale * dot(d, d));
}

/// `out[0] += w[t] * x[t]` (a weighted sum of points).
#[diff_kernel]
pub fn weighted_point_sum<R: Real>(x: &Array<Vec3<R>>, w: &Array<R>, out: &Array<Vec3<R>>) {
    let t = tid();
    out.atomic_add(0, x[t] * w[t]);
}

/// `out[0] += scale * a[t]^2`.
#[diff_kernel]
pub fn sum_sq<R: Real>(a: &Array<R>, scale: R, out: &Array<R>) {
    let t = tid();
    out.atomic_add(0, scale * a[t] * a[t]);
}

/// `out[world[t]] += scale * a[t]^2`: one sum per world.
#[diff_kernel]
pub fn sum_sq_per_world<R: Real>(world: &Array<u32>, a: &Array<R>, scale: R, out: &Array<R>) {
    let t = tid();
    out.atomic_add(world[t] as usize, scale * a[t] * a[t]);
}

/// `out[world[t]] += scale * |a[t]|^2`: one sum per world.
#[diff_kernel]
pub fn sum_sq_vec3_per_world<R: Real>(
    world: &Array<u32>,
    a: &Array<Vec3<R>>,
    scale: R,
    out: &Array<R>,
) {
    let t = tid();
    out.atomic_add(world[t] as usize, scale * dot(a[t], a[t]));
}

/// `out[0] += scale * |x[t]|^2`.
#[diff_kernel]
pub fn sum_sq_vec3<R: Real>(a: &Array<Vec3<R>>, scale: R, out: &Array<R>) {
    let t = tid();
    out.atomic_add(0, scale * dot(a[t], a[t]));
}

fn indices(particles: &[u32], len: usize, what: &str) -> Array<u32> {
    if let Some(&i) = particles.iter().find(|&&i| i as usize >= len) {
        panic!("losses::{what}: index {i} out of range for {len} points");
    }
    Array::from_vec(particles.to_vec()).named("loss_indices")
}

/// Adds `scale * sum over i in particles of |x[i] - target|^2` (m²) to `out[0]`.
/// Panics if an index is out of range.
pub fn distance_to_target<R: Real>(
    tape: &mut Tape,
    x: &Array<Vec3<R>>,
    particles: &[u32],
    target: Vec3<R>,
    scale: R,
    out: &Array<R>,
) {
    let idx = indices(particles, x.len(), "distance_to_target");
    tape.launch(
        sq_distance_to_point,
        particles.len(),
        (x, &idx, target, scale, out),
    );
}

/// Adds `scale * |x_body - target|^2` (m²) for the centre of mass of rigid body `body`.
pub fn body_distance_to_target<R: Real>(
    tape: &mut Tape,
    bodies: &BodyState<R>,
    body: u32,
    target: Vec3<R>,
    scale: R,
    out: &Array<R>,
) {
    let idx = indices(&[body], bodies.x.len(), "body_distance_to_target");
    tape.launch(
        sq_distance_to_point,
        1,
        (&bodies.x, &idx, target, scale, out),
    );
}

/// Adds `scale * sum_i |x[i] - recorded[i]|^2` (m²): the mismatch of one frame of a
/// trajectory against a recorded frame (call it on every state of a rollout for a trajectory
/// loss). Panics if the lengths differ.
pub fn frame_mismatch<R: Real>(
    tape: &mut Tape,
    x: &Array<Vec3<R>>,
    recorded: &Array<Vec3<R>>,
    scale: R,
    out: &Array<R>,
) {
    assert_eq!(
        x.len(),
        recorded.len(),
        "losses::frame_mismatch: {} positions against a recorded frame of {}",
        x.len(),
        recorded.len()
    );
    tape.launch(sq_distance_between, x.len(), (x, recorded, scale, out));
}

/// The particles' weights for [`center_of_mass`]: mass over total mass, pinned (infinite
/// mass) particles excluded. Panics if every particle is pinned.
pub fn mass_weights<R: Real>(model: &Model<R>) -> Array<R> {
    let m: Vec<f64> = model
        .particle_inv_mass
        .to_vec()
        .iter()
        .map(|w| {
            if w.to_f64() > 0.0 {
                1.0 / w.to_f64()
            } else {
                0.0
            }
        })
        .collect();
    let total: f64 = m.iter().sum();
    assert!(
        total > 0.0,
        "losses::mass_weights: every particle is pinned"
    );
    Array::from_vec(m.iter().map(|m| R::lit(m / total)).collect()).named("mass_weights")
}

/// Records and returns the weighted centre `sum_i w[i] x[i]` (m; a new array of one element):
/// with [`mass_weights`], the centre of mass.
pub fn center_of_mass<R: Real>(
    tape: &mut Tape,
    x: &Array<Vec3<R>>,
    weights: &Array<R>,
) -> Array<Vec3<R>> {
    assert_eq!(
        x.len(),
        weights.len(),
        "losses::center_of_mass: {} positions and {} weights",
        x.len(),
        weights.len()
    );
    let c = Array::zeros(1).named("center_of_mass");
    tape.launch(weighted_point_sum, x.len(), (x, weights, &c));
    c
}

/// Adds `scale * |sum_i w[i] x[i] - target|^2` (m²): the centre of mass's distance to a
/// target (with [`mass_weights`]).
pub fn center_of_mass_to_target<R: Real>(
    tape: &mut Tape,
    x: &Array<Vec3<R>>,
    weights: &Array<R>,
    target: Vec3<R>,
    scale: R,
    out: &Array<R>,
) {
    let c = center_of_mass(tape, x, weights);
    distance_to_target(tape, &c, &[0], target, scale, out);
}

/// Adds `scale * sum_i a[i]^2` (a regularizer on controls or parameters).
pub fn sum_of_squares<R: Real>(tape: &mut Tape, a: &Array<R>, scale: R, out: &Array<R>) {
    tape.launch(sum_sq, a.len(), (a, scale, out));
}

/// Adds `scale * a[i]^2` to `out[world[i]]`: a loss per world (`world` an index array such as
/// `Articulations::q_world`, `dof_world` or `Model::particle_world`; `out` one entry per
/// world). Backpropagating `out` gives each world's parameters the gradient of its own loss.
///
/// # Panics
/// If `world` and `a` differ in length, or a world has no entry in `out`, with a message
/// saying which.
pub fn per_world_sum_of_squares<R: Real>(
    tape: &mut Tape,
    world: &Array<u32>,
    a: &Array<R>,
    scale: R,
    out: &Array<R>,
) {
    check_per_world(world, a.len(), out.len());
    tape.launch(sum_sq_per_world, a.len(), (world, a, scale, out));
}

/// `world` must give one world per entry, each below `out`'s length.
fn check_per_world(world: &Array<u32>, n: usize, worlds: usize) {
    assert!(
        world.len() == n,
        "per_world_sum_of_squares: the index array has {} entries and the values {n} (pair \
         `q_world` with `q`, `dof_world` with `qd`, `particle_world` with `x` or `v`)",
        world.len()
    );
    if let Some(w) = world.to_vec().into_iter().find(|&w| w as usize >= worlds) {
        panic!(
            "per_world_sum_of_squares: world {w} has no entry in the loss array (length \
             {worlds}: one per world)"
        );
    }
}

/// [`per_world_sum_of_squares`] for an array of vectors (`scale |a[i]|^2` to `out[world[i]]`).
pub fn per_world_sum_of_squares_vec3<R: Real>(
    tape: &mut Tape,
    world: &Array<u32>,
    a: &Array<Vec3<R>>,
    scale: R,
    out: &Array<R>,
) {
    check_per_world(world, a.len(), out.len());
    tape.launch(sum_sq_vec3_per_world, a.len(), (world, a, scale, out));
}

/// Adds `scale * sum_i |a[i]|^2` for an array of vectors (e.g. velocities: a kinetic-energy
/// like penalty, or forces).
pub fn sum_of_squares_vec3<R: Real>(tape: &mut Tape, a: &Array<Vec3<R>>, scale: R, out: &Array<R>) {
    tape.launch(sum_sq_vec3, a.len(), (a, scale, out));
}
