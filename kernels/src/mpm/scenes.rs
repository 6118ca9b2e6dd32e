//! Ready-made MPM scenes and tasks: DiffTaichi's walker ([`walker`]) and its open-loop
//! sine-wave controller ([`WalkerTask`]); the fluid, jelly and snow of Taichi's `mpm99`
//! ([`mpm99`]).

use adflex_macros::diff_kernel;
use adflex_runtime::checkpoint::Checkpointed;
use adflex_runtime::prelude::*;

use super::{Material, Mpm, MpmBuilder, MpmState};

/// Sine waves per actuator of the walker's controller.
pub const WAVES: usize = 4;
/// Angular frequency of the controller's waves (rad/s).
pub const OMEGA: f64 = 20.0;

/// DiffTaichi's `diffmpm` walker on an `n_grid x n_grid` grid of the unit square: a body
/// `0.3 x 0.1` on four legs `0.05 x 0.1`, each leg one actuator (0 to 3, left to right)
/// contracting or extending vertically with strength 4; fixed-corotated material with
/// `mu = lambda = 10`, particle mass and volume 1, sticky floor, gravity 3.8, walls 3 nodes
/// thick. At `n_grid = 128` it has 2,976 particles (DiffTaichi's size); at 64, 744. It stands
/// `0.03` above the bottom of the grid (DiffTaichi's offset), or just inside the walls on
/// coarser grids.
pub fn walker(n_grid: usize) -> MpmBuilder {
    let dx = 1.0 / n_grid as f64;
    let mut b = MpmBuilder::new(n_grid, dx);
    let material = Material::Corotated {
        mu: 10.0,
        lambda: 10.0,
    };
    let offset = Vec2::new(0.1, f64::max(0.03, 3.5 * dx));
    let rect = |b: &mut MpmBuilder, x: f64, y: f64, w: f64, h: f64| {
        b.add_rect(
            offset + Vec2::new(x, y),
            Vec2::new(w, h),
            1.0,
            1.0,
            material,
        )
    };
    rect(&mut b, 0.0, 0.1, 0.3, 0.1);
    for (k, x) in [0.0, 0.05, 0.2, 0.25].into_iter().enumerate() {
        let leg = rect(&mut b, x, 0.0, 0.05, 0.1);
        b.actuate(leg, k, 4.0, Vec2::new(0.0, 1.0));
    }
    b
}

/// The materials and numerics of Taichi's `mpm99` example on a layout of its own (mpm99 drops
/// three blocks of 3,000 random particles at rest), on an `n_grid x n_grid` grid of the unit
/// square: a
/// block of fluid (`0.2 x 0.2` at `(0.15, 0.15)`, falling at 1 m/s), one of jelly (`0.15 x
/// 0.15` at `(0.42, 0.45)`, 2 m/s; corotated with `0.3` times the moduli) and one of snow
/// (`0.2 x 0.2` at `(0.62, 0.2)`, 3 m/s; [`Material::snow`]), Young's modulus 1000 and Poisson's
/// ratio 0.2, density 1 (each particle's volume a quarter of a cell), gravity 50, a floor
/// without friction. mpm99 steps it with `dt = 1e-4` at `n_grid = 128`. At `n_grid = 32` it is
/// the scene `kernels/tests/references/taichi_mpm99.py` runs in Taichi (352 particles);
/// at 128, 6,444.
pub fn mpm99(n_grid: usize) -> MpmBuilder {
    let dx = 1.0 / n_grid as f64;
    let (e, nu) = (1000.0, 0.2);
    let (mu, lambda) = Material::lame(e, nu);
    let p_vol = (0.5 * dx) * (0.5 * dx);
    let mut b = MpmBuilder::new(n_grid, dx);
    b.set_gravity(Vec2::new(0.0, -50.0));
    b.set_floor(super::Floor::Coulomb(0.0));
    let blocks = [
        (Material::Fluid { bulk: lambda }, [0.15, 0.15], 0.2, -1.0),
        (
            Material::Corotated {
                mu: 0.3 * mu,
                lambda: 0.3 * lambda,
            },
            [0.42, 0.45],
            0.15,
            -2.0,
        ),
        (Material::snow(e, nu), [0.62, 0.2], 0.2, -3.0),
    ];
    for (material, lo, size, vy) in blocks {
        let lo = Vec2::new(lo[0], lo[1]);
        let ps = b.add_rect(lo, Vec2::new(size, size), p_vol, p_vol, material);
        for p in ps {
            b.set_velocity(p, Vec2::new(0.0, vy));
        }
    }
    b
}

/// Actuator `tid`'s value: `tanh(sum_j w[4 tid + j] sin(phase + j pi / 2) + b[tid])`
/// (DiffTaichi's open-loop controller, [`WAVES`] = 4 waves).
#[diff_kernel]
pub fn sine_controller<R: Real>(w: &Array<R>, b: &Array<R>, phase: R, act: &Array<R>) {
    let i = tid();
    let mut s = b[i];
    for j in 0..4 {
        s += w[i * 4 + j] * sin(phase + (j as R) * 1.5707963267948966);
    }
    act[i] = tanh(s);
}

/// `loss[0] = -c[0].x`: minus the mean `x` (walk right).
#[diff_kernel]
pub fn minus_x<R: Real>(c: &Array<Vec2<R>>, loss: &Array<R>) {
    loss[0] = -c[0].x;
}

/// DiffTaichi's walker task: the model, the controller's weights and biases (the gradient
/// targets), the rollout's length and time step. The loss is minus the mean `x` of the
/// particles after `steps` steps.
#[derive(Clone, Debug)]
pub struct WalkerTask<R: Real> {
    /// The walker.
    pub mpm: Mpm<R>,
    /// `WAVES` weights per actuator, row by row.
    pub weights: Array<R>,
    /// One bias per actuator.
    pub bias: Array<R>,
    /// Steps per rollout.
    pub steps: usize,
    /// Time step (s).
    pub dt: f64,
}

impl<R: Real> WalkerTask<R> {
    /// The walker on an `n_grid` grid with [`WalkerTask::initial_weights`], zero biases,
    /// `steps` steps of `dt`.
    pub fn new(n_grid: usize, steps: usize, dt: f64) -> Self {
        let mpm: Mpm<R> = walker(n_grid)
            .finalize()
            .expect("the walker is a valid scene");
        let n = mpm.n_actuators;
        let w = Self::initial_weights(n).into_iter().map(R::lit).collect();
        WalkerTask {
            weights: Array::from_vec(w).named("weights").requires_grad(),
            bias: Array::zeros(n).named("bias").requires_grad(),
            mpm,
            steps,
            dt,
        }
    }

    /// Small random weights (standard deviation 0.01, uniform) from a 64-bit linear
    /// congruential generator seeded with 1: the numbers `bench/peers/taichi_mpm.py` starts
    /// from too.
    pub fn initial_weights(n_actuators: usize) -> Vec<f64> {
        let mut s: u64 = 1;
        (0..n_actuators * WAVES)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let u = (s >> 11) as f64 / (1u64 << 53) as f64;
                0.01 * 3f64.sqrt() * (2.0 * u - 1.0)
            })
            .collect()
    }

    /// Records step `t`: the controller, then the MPM step; returns the new state and the
    /// step's actuation.
    pub fn step(
        &self,
        tape: &mut Tape,
        s: &MpmState<R>,
        t: usize,
    ) -> Result<(MpmState<R>, Array<R>), Error> {
        let n = self.mpm.n_actuators;
        let act = Array::zeros(n).named("actuation");
        let phase = R::lit(OMEGA * t as f64 * self.dt);
        tape.launch(sine_controller, n, (&self.weights, &self.bias, phase, &act));
        Ok((self.mpm.step(tape, s, Some(&act), self.dt)?, act))
    }

    /// The loss of one rollout, with its gradient accumulated into the gradient buffers of
    /// the weights and biases (zeroed first) by a checkpointed backward pass (a checkpoint
    /// every `sqrt(steps)` steps).
    pub fn loss_and_grad(&self) -> Result<f64, Error> {
        self.weights.zero_grad();
        self.bias.zero_grad();
        let steps = self.steps;
        let out = Checkpointed::new(steps).run(
            &self.mpm.state(),
            |tape, s, t| Ok(self.step(tape, s, t)?.0),
            |tape, s, t, acc| {
                if t == steps {
                    let c = self.mpm.mean_position(tape, s);
                    tape.launch(minus_x, 1, (&c, acc));
                }
                Ok(())
            },
        )?;
        Ok(out.loss.get(0).to_f64())
    }
}
