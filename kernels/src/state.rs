//! What changes from step to step, and what drives it: the particles' [`State`] (with the
//! rigid bodies' [`BodyState`]) that integrators step, and the per-step actuation
//! [`Control`]. A physics family keeps its state arrays here, beside the others, so that
//! integrators, checkpoints and losses see one state.

use adflex_runtime::checkpoint::Checkpoint;
use adflex_runtime::{AnyArray, Array, Quat, Real, Vec3};

/// Everything that changes from step to step: particle positions (m) and velocities (m/s),
/// and the rigid body state if the model has bodies. Integrators return a new `State` (new
/// arrays) every step, so a tape keeps the whole trajectory.
#[derive(Clone, Debug)]
pub struct State<R: Real> {
    /// Particle positions (m).
    pub x: Array<Vec3<R>>,
    /// Particle velocities (m/s).
    pub v: Array<Vec3<R>>,
    /// Rigid bodies, if the model has any.
    pub bodies: Option<BodyState<R>>,
}

impl<R: Real> State<R> {
    /// New arrays with the same values (no gradients).
    pub fn deep_clone(&self) -> Self {
        State {
            x: self.x.deep_clone(),
            v: self.v.deep_clone(),
            bodies: self.bodies.as_ref().map(BodyState::deep_clone),
        }
    }

    /// Number of particles.
    pub fn particle_count(&self) -> usize {
        self.x.len()
    }
}

impl<R: Real> Checkpoint for State<R> {
    fn arrays(&self) -> Vec<&dyn AnyArray> {
        let mut a: Vec<&dyn AnyArray> = vec![&self.x, &self.v];
        if let Some(b) = &self.bodies {
            a.extend([&b.x as &dyn AnyArray, &b.q, &b.v, &b.w]);
        }
        a
    }
    fn snapshot(&self) -> Self {
        self.deep_clone()
    }
}

/// Per-step actuation. Every field is optional; absent means none (or the model's default).
#[derive(Clone, Debug, Default)]
pub struct Control<R: Real> {
    /// External force on each particle (N).
    pub particle_f: Option<Array<Vec3<R>>>,
    /// Activation of each tetrahedron (see [`crate::forces::fem_tet`]); replaces the model's
    /// default activation.
    pub tet_activation: Option<Array<R>>,
    /// External force on each body's centre of mass (N, world frame).
    pub body_f: Option<Array<Vec3<R>>>,
    /// External torque on each body (N m, world frame).
    pub body_t: Option<Array<Vec3<R>>>,
}

/// Forces (N) and torques (N m) on the rigid bodies, world frame.
pub type BodyForces<R> = (Array<Vec3<R>>, Array<Vec3<R>>);

/// The state of the rigid bodies: centre of mass position (m), orientation (unit quaternion),
/// linear velocity (m/s) and angular velocity (rad/s, world frame).
#[derive(Clone, Debug)]
pub struct BodyState<R: Real> {
    /// Position of the centre of mass (m).
    pub x: Array<Vec3<R>>,
    /// Orientation, body to world (unit quaternion).
    pub q: Array<Quat<R>>,
    /// Linear velocity (m/s).
    pub v: Array<Vec3<R>>,
    /// Angular velocity in world frame (rad/s).
    pub w: Array<Vec3<R>>,
}

impl<R: Real> BodyState<R> {
    /// New arrays with the same values (no gradients).
    pub fn deep_clone(&self) -> Self {
        BodyState {
            x: self.x.deep_clone(),
            q: self.q.deep_clone(),
            v: self.v.deep_clone(),
            w: self.w.deep_clone(),
        }
    }
}
